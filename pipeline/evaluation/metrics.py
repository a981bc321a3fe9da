"""Evaluation kernels: alignment, per-camera errors, summaries, paper 2's metrics, edge statistics.

Pure functions on arrays (no I/O). The estimate is compared after one global
rotation G, the gauge freedom of rotation averaging: with cam_from_world
rotations, ``R_i^est ≈ R_i^ref G``. The error of camera i is the geodesic angle
of ``R_i^est (R_i^ref G)ᵀ``.

Alignment (paper 1, §6 "Different comparison methods", Table 6): since
``d(R_i^est, R_i^ref G) = d(Q_i, G)`` with ``Q_i = R_i^refᵀ R_i^est``, G is a mean of
the ``Q_i``:

- ``"l2"`` (default, as paper 1's tables): the closed-form chordal mean
  ``proj_SO(3)(Σ Q_i)``, refined to the geodesic (Karcher) mean, which minimizes
  ``Σ θ_i²``;
- ``"l1"``: the geodesic median, minimizing ``Σ θ_i``, by Weiszfeld iterations
  on SO(3) from the chordal mean;
- ``"none"``: G = I, for estimates already in the reference frame.

Also here: paper 2's ``√Σ‖R_i − R_i*‖²_F`` after the best (chordal) alignment,
paper 2's Mahalanobis error (eq. C.13), and paper 1's Table 2 edge statistics of
a view graph against a reference.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = [
    "ALIGN_METHODS",
    "align_rotations",
    "rotation_errors_deg",
    "frobenius_error",
    "mahalanobis_error",
    "summarize",
    "edge_errors_deg",
    "edge_stats",
]

ALIGN_METHODS = ("l2", "l1", "none")
PCT_BELOW = (1, 2, 5, 10)
PCT_ABOVE = (10, 30, 60, 90)


def _prepare(R_est: np.ndarray, R_ref: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    R_est = np.asarray(R_est, dtype=np.float64)
    R_ref = np.asarray(R_ref, dtype=np.float64)
    if R_est.ndim != 3 or R_est.shape[1:] != (3, 3):
        raise ValueError(f"R_est.shape={R_est.shape} but expected (N, 3, 3)")
    if R_ref.shape != R_est.shape:
        raise ValueError(f"R_ref.shape={R_ref.shape} but expected R_est's shape {R_est.shape} (one reference per camera)")
    n = R_est.shape[0]
    m = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != (n,):
        raise ValueError(f"mask.shape={m.shape} but expected ({n},)")
    m = m & np.all(np.isfinite(R_est), axis=(1, 2)) & np.all(np.isfinite(R_ref), axis=(1, 2))
    return R_est, R_ref, m


def _geodesic_median(Q: np.ndarray, G0: np.ndarray, tol: float, max_iterations: int) -> np.ndarray:
    """Weiszfeld iterations on SO(3) for ``argmin_G Σ d(Q_i, G)`` (paper 1, §6; Hartley et al.)."""
    G = G0
    for _ in range(max_iterations):
        v = so3.log(Q @ G.T)  # (K, 3) tangent vectors at G, left-trivialized
        d = np.linalg.norm(v, axis=1)
        # A sample at G itself has no defined direction; its weight is capped so
        # the step stays finite (the standard Weiszfeld safeguard).
        w = 1.0 / np.maximum(d, 1e-12)
        step = (w[:, None] * v).sum(axis=0) / w.sum()
        G = so3.exp(step) @ G
        if np.linalg.norm(step) < tol:
            break
    return G


def align_rotations(
    R_est: np.ndarray,
    R_ref: np.ndarray,
    mask: np.ndarray | None = None,
    method: str = "l2",
    tol: float = 1e-12,
    max_iterations: int = 200,
) -> np.ndarray:
    """The global rotation G with ``R_est[i] ≈ R_ref[i] @ G``.

    Args:
        R_est: (N, 3, 3) estimated cam_from_world rotations.
        R_ref: (N, 3, 3) reference rotations, same camera order.
        mask: (N,) True where the reference exists (default all).
        method: "l2" (chordal, then Karcher mean), "l1" (Weiszfeld geodesic
            median) or "none" (identity).
        tol: stopping tolerance on the update, radians.
        max_iterations: iteration cap of the refinement.

    Returns:
        (3, 3) rotation G.
    """
    if method not in ALIGN_METHODS:
        raise ValueError(f"align method {method!r} is not one of {ALIGN_METHODS}")
    R_est, R_ref, m = _prepare(R_est, R_ref, mask)
    if method == "none":
        return np.eye(3)
    if not np.any(m):
        raise ValueError("no camera has a reference rotation; check that the names match the reference")
    Q = np.swapaxes(R_ref[m], 1, 2) @ R_est[m]
    if method == "l2":
        return so3.karcher_mean(Q, tol=tol, max_iterations=max_iterations)  # starts from the chordal mean
    return _geodesic_median(Q, so3.chordal_mean(Q), tol, max_iterations)


def rotation_errors_deg(R_est: np.ndarray, R_ref: np.ndarray, mask: np.ndarray | None = None, align: str = "l2") -> np.ndarray:
    """(N,) angle of ``R_est[i] (R_ref[i] G)ᵀ`` in degrees after alignment; NaN where mask is False."""
    R_est, R_ref, m = _prepare(R_est, R_ref, mask)
    G = align_rotations(R_est, R_ref, m, align)
    err = np.full(R_est.shape[0], np.nan)
    err[m] = np.degrees(so3.angle_between(R_est[m], R_ref[m] @ G))
    return err


def frobenius_error(R_est: np.ndarray, R_ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Paper 2's ``√Σ_i ‖R_i − R_i*‖²_F`` after the best alignment.

    The best alignment for this metric is the chordal one,
    ``G = proj_SO(3)(Σ R_refᵢᵀ R_estᵢ)``, which makes the value independent of the
    gauge of ``R_est``.
    """
    R_est, R_ref, m = _prepare(R_est, R_ref, mask)
    if not np.any(m):
        raise ValueError("no camera has a reference rotation; check that the names match the reference")
    G = so3.chordal_mean(np.swapaxes(R_ref[m], 1, 2) @ R_est[m])
    return float(np.sqrt(np.sum((R_est[m] - R_ref[m] @ G) ** 2)))


def mahalanobis_error(
    R_est: np.ndarray,
    R_ref: np.ndarray,
    vg: ViewGraph,
    mask: np.ndarray | None = None,
    G: np.ndarray | None = None,
) -> float:
    """Paper 2's Mahalanobis error (supplement, eq. C.13).

    ``√Σ_i min{Δω_i⁻ᵀ H_i Δω_i⁻, Δω_i⁺ᵀ H_i Δω_i⁺}`` with ``ω_i = log(R_i^est Gᵀ)``
    (the estimate aligned to the reference), ``ω_i* = log(R_i^ref)``,
    ``Δω_i^∓ = ω_i ∓ ω_i*`` and ``H_i = Σ_{j: {i,j} observed} H_ij``, the sum over
    the camera's edges, as the paper defines it ("all other cameras fixed").
    The minimum handles the sign ambiguity of axis-angle vectors near π.

    Args:
        R_est: (N, 3, 3) estimate.
        R_ref: (N, 3, 3) reference.
        vg: view graph with H, whose cameras are in the same order.
        mask: (N,) cameras with a reference.
        G: (3, 3) alignment (default: identity).
    """
    R_est, R_ref, m = _prepare(R_est, R_ref, mask)
    if vg.H is None:
        raise ValueError("the Mahalanobis error needs a view graph with H (precisions)")
    if vg.n_cameras != R_est.shape[0]:
        raise ValueError(f"view graph has {vg.n_cameras} cameras but R_est has {R_est.shape[0]}; use the same camera order")
    G = np.eye(3) if G is None else np.asarray(G, dtype=np.float64)
    H_cam = np.zeros((vg.n_cameras, 3, 3))
    np.add.at(H_cam, vg.edges[:, 0], vg.H)
    np.add.at(H_cam, vg.edges[:, 1], vg.H)
    w = so3.log(R_est[m] @ G.T)
    w_ref = so3.log(R_ref[m])
    Hm = H_cam[m]
    q = lambda d: np.einsum("na,nab,nb->n", d, Hm, d)  # noqa: E731
    return float(np.sqrt(np.sum(np.minimum(q(w - w_ref), q(w + w_ref)))))


def _pct(values: np.ndarray, thresholds: tuple[int, ...], below: bool) -> dict[str, float]:
    if values.size == 0:
        return {str(t): float("nan") for t in thresholds}
    return {str(t): float(100.0 * np.mean(values < t if below else values > t)) for t in thresholds}


def summarize(
    R_est: np.ndarray,
    R_ref: np.ndarray,
    mask: np.ndarray | None = None,
    align: str = "l2",
    vg: ViewGraph | None = None,
) -> dict[str, Any]:
    """Summary statistics of the per-camera errors.

    Returns:
        dict with ``n_cameras``, ``n_evaluated``, ``align``, ``median_deg``,
        ``mean_deg``, ``rms_deg``, ``max_deg``, ``frobenius`` (paper 2),
        ``pct_below`` {"1", "2", "5", "10"} (percent of evaluated cameras under
        that many degrees), and ``mahalanobis`` (paper 2, eq. C.13) when ``vg``
        with H is given in the same camera order.
    """
    R_est, R_ref, m = _prepare(R_est, R_ref, mask)
    G = align_rotations(R_est, R_ref, m, align)
    e = np.degrees(so3.angle_between(R_est[m], R_ref[m] @ G))
    out: dict[str, Any] = {
        "n_cameras": int(R_est.shape[0]),
        "n_evaluated": int(m.sum()),
        "align": align,
        "median_deg": float(np.median(e)),
        "mean_deg": float(np.mean(e)),
        "rms_deg": float(np.sqrt(np.mean(e**2))),
        "max_deg": float(np.max(e)),
        "frobenius": frobenius_error(R_est, R_ref, m),
        "pct_below": _pct(e, PCT_BELOW, below=True),
    }
    if vg is not None and vg.H is not None:
        out["mahalanobis"] = mahalanobis_error(R_est, R_ref, vg, m, G)
    return out


def edge_errors_deg(vg: ViewGraph, R_ref: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(M,) angle between each measured ``R̃_ij`` and ``R_j^ref R_i^refᵀ``, degrees; NaN where an end has no reference."""
    R_ref = np.asarray(R_ref, dtype=np.float64)
    if R_ref.shape != (vg.n_cameras, 3, 3):
        raise ValueError(f"R_ref.shape={R_ref.shape} but expected ({vg.n_cameras}, 3, 3), one per camera of the view graph")
    m = np.ones(vg.n_cameras, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != (vg.n_cameras,):
        raise ValueError(f"mask.shape={m.shape} but expected ({vg.n_cameras},)")
    i, j = vg.edges.T
    ok = m[i] & m[j]
    err = np.full(vg.n_edges, np.nan)
    err[ok] = np.degrees(so3.angle_between(vg.R_rel[ok], R_ref[j[ok]] @ np.swapaxes(R_ref[i[ok]], 1, 2)))
    return err


def edge_stats(vg: ViewGraph, R_ref: np.ndarray, mask: np.ndarray | None = None) -> dict[str, Any]:
    """Paper 1, Table 2 statistics of the relative-rotation errors.

    Returns:
        dict with ``n_edges``, ``n_evaluated``, ``mean_deg``, ``median_deg``,
        ``rms_deg`` and ``pct_above`` {"10", "30", "60", "90"} (percent of the
        evaluated edges with a larger error).
    """
    e = edge_errors_deg(vg, R_ref, mask)
    e = e[np.isfinite(e)]
    nan = float("nan")
    return {
        "n_edges": int(vg.n_edges),
        "n_evaluated": int(e.size),
        "mean_deg": float(np.mean(e)) if e.size else nan,
        "median_deg": float(np.median(e)) if e.size else nan,
        "rms_deg": float(np.sqrt(np.mean(e**2))) if e.size else nan,
        "pct_above": _pct(e, PCT_ABOVE, below=False),
    }
