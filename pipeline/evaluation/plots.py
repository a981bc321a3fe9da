"""The report's plots (matplotlib, Agg backend, never shown), each written atomically as PNG.

- :func:`plot_error_distribution`: per-camera error histogram and cumulative
  distribution of every method against one reference (paper 1, Fig. 5a–b);
- :func:`plot_convergence`: error (median over cameras when the method recorded
  it per iteration, otherwise its cost) against time (paper 1, Fig. 5c);
- :func:`plot_edge_errors`: log-log distribution of the relative-rotation errors
  of the view graph's edges against a reference (paper 1, Fig. 2);
- :func:`plot_viewgraph`: the view graph, cameras placed at their reference
  centres when known (else a spectral layout), edges coloured by error or weight.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.atomic import save_figure

__all__ = ["plot_error_distribution", "plot_convergence", "plot_edge_errors", "spectral_layout", "plot_viewgraph"]


def _plt():
    import matplotlib  # noqa: PLC0415  (lazy: only the report needs it)

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


def plot_error_distribution(errors: dict[str, np.ndarray], path: Path, ref: str) -> Path:
    """Histogram and CDF of per-camera errors of each method (paper 1, Fig. 5a–b)."""
    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    finite = {k: np.asarray(v, float)[np.isfinite(v)] for k, v in errors.items()}
    allv = np.concatenate([v for v in finite.values() if v.size] or [np.zeros(1)])
    hi = max(float(np.percentile(allv, 99)) if allv.size else 1.0, 1e-3) * 1.05
    bins = np.linspace(0, hi, 30)
    for k, v in finite.items():
        if not v.size:
            continue
        ax1.hist(np.clip(v, 0, hi), bins=bins, histtype="step", lw=1.6, label=f"{k} (n={v.size})")
        s = np.sort(v)
        ax2.step(s, np.arange(1, s.size + 1) / s.size, where="post", lw=1.6, label=k)
    ax1.set(xlabel="camera rotation error (°)", ylabel="cameras", title=f"error histogram vs {ref}")
    ax2.set(xlabel="camera rotation error (°)", ylabel="fraction of cameras ≤ x", title=f"cumulative vs {ref}",
            ylim=(0, 1.02))
    ax1.legend(fontsize=8)
    ax2.legend(fontsize=8)
    return save_figure(fig, path)


def plot_convergence(histories: dict[str, list[dict[str, float]]], path: Path) -> Path | None:
    """Median error (or cost) against cumulative time, per iterative method (paper 1, Fig. 5c)."""
    usable = {k: h for k, h in histories.items() if h}
    if not usable:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    ylabel = "median camera error (°)"
    for k, h in usable.items():
        t = np.array([r.get("time_s", np.nan) for r in h], float)
        key = "median_deg" if all("median_deg" in r for r in h) else "cost"
        if key == "cost":
            ylabel = "median error (°) or cost (where no per-iteration error)"
        y = np.array([r.get(key, np.nan) for r in h], float)
        ax.plot(t, y, marker="o", ms=3, label=f"{k} ({'median' if key == 'median_deg' else 'cost'})")
    ax.set_yscale("log")
    ax.set(xlabel="time (s)", ylabel=ylabel, title="convergence of the iterative methods")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_edge_errors(edge_errors: dict[str, np.ndarray], path: Path, ref: str) -> Path | None:
    """Log-log distribution of the edges' relative-rotation errors (paper 1, Fig. 2)."""
    finite = {k: np.asarray(v, float)[np.isfinite(v)] for k, v in edge_errors.items()}
    finite = {k: v for k, v in finite.items() if v.size}
    if not finite:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    allv = np.concatenate(list(finite.values()))
    lo = max(float(allv[allv > 0].min()) if np.any(allv > 0) else 1e-3, 1e-4)
    bins = np.logspace(np.log10(lo), np.log10(max(180.0, allv.max())), 30)
    for k, v in finite.items():
        counts, edges = np.histogram(np.maximum(v, lo), bins=bins)
        centers = np.sqrt(edges[:-1] * edges[1:])
        keep = counts > 0
        ax.loglog(centers[keep], counts[keep] / v.size, marker="o", ms=3, label=f"{k} (M={v.size})")
    ax.set(xlabel="relative rotation error (°)", ylabel="fraction of edges", title=f"edge errors vs {ref}")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def spectral_layout(n: int, edges: np.ndarray) -> np.ndarray:
    """(n, 2) positions from the 2nd/3rd Laplacian eigenvectors (a picture when no centres are known)."""
    if n <= 2 or len(edges) == 0:
        ang = 2 * np.pi * np.arange(n) / max(n, 1)
        return np.c_[np.cos(ang), np.sin(ang)]
    A = np.zeros((n, n))
    A[edges[:, 0], edges[:, 1]] = A[edges[:, 1], edges[:, 0]] = 1.0
    L = np.diag(A.sum(1)) - A
    w, V = np.linalg.eigh(L)
    return V[:, 1:3]


def plot_viewgraph(n: int, edges: np.ndarray, values: np.ndarray | None, path: Path, label: str,
                   positions: np.ndarray | None = None, names: list[str] | None = None) -> Path:
    """The view graph with edges coloured by ``values`` (error or weight)."""
    plt = _plt()
    from matplotlib.collections import LineCollection  # noqa: PLC0415

    P = np.asarray(positions, float)[:, :2] if positions is not None else spectral_layout(n, edges)
    if positions is not None and np.asarray(positions).shape[1] == 3:
        # project the centres on their two principal directions: cameras on a ring or an arc stay readable
        C = np.asarray(positions, float)
        C0 = C - C.mean(0)
        _, _, Vt = np.linalg.svd(C0, full_matrices=False)
        P = C0 @ Vt[:2].T
    fig, ax = plt.subplots(figsize=(6, 5))
    segs = np.stack([P[edges[:, 0]], P[edges[:, 1]]], axis=1) if len(edges) else np.zeros((0, 2, 2))
    v = np.asarray(values, float) if values is not None else np.ones(len(edges))
    lc = LineCollection(segs, array=np.where(np.isfinite(v), v, np.nan), cmap="viridis", linewidths=1.5)
    ax.add_collection(lc)
    ax.scatter(P[:, 0], P[:, 1], s=25, c="k", zorder=3)
    if names is not None and n <= 40:
        for k, nm in enumerate(names):
            ax.annotate(Path(nm).stem, P[k], fontsize=6, xytext=(3, 3), textcoords="offset points")
    fig.colorbar(lc, ax=ax, label=label.replace("_", " ") + (" (°)" if "error" in label else ""))
    ax.autoscale()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(title=f"view graph: {n} cameras, {len(edges)} edges", xticks=[], yticks=[])
    return save_figure(fig, path)
