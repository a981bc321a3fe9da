"""Rotation averaging stage: one entry point for every method, plus its command line.

Methods:

* ``irls`` (default): paper 1, Algorithm 3: spanning tree, ℓ1 steps, then IRLS
  with one of the 13 losses of Table 1 (ℓ½ by default);
* ``irls-h``: the same IRLS with each edge's residual in the metric of its two-view
  Hessian H (``pipeline.averaging.irls_h``; needs H; not in either paper);
* ``l1``: paper 1, Algorithm 2 alone (ℓ1 steps until the mean update is small);
* ``weiszfeld``: Hartley et al. (2011), one camera at a time (a baseline);
* ``sdp``: paper 2's certifiable SDP (``pipeline.averaging.sdp.solve_sdp``).

Disconnected graphs: every method solves the largest connected component; the
other cameras are listed by name in ``dropped_names`` (and in the JSON stats) and
a warning is logged. They are never silently dropped.

Command line::

    python -m pipeline.average INPUT --method irls|irls-h|l1|weiszfeld|sdp [--loss NAME]
        [--alpha-deg A] [--alpha A_H] [--init mst|random|FILE] [--variant V] [--solver scs|clarabel]
        --out ROTATIONS [--json STATS]

INPUT is a view-graph ``.npz`` or a supported ``.mat``; ROTATIONS a rotations text
file (:mod:`pipeline.io.rotations`); STATS a JSON file with at least ``time_s``,
``iterations``, ``n_cameras`` and ``n_edges``. A re-run with the same options and
existing outputs is skipped (the configuration hash is stored in both files)
unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.averaging.irls import check_graph, irls
from pipeline.averaging.l1 import l1_averaging, edge_residuals
from pipeline.averaging.init import initial_rotations
from pipeline.averaging.losses import LOSS_NAMES, get_loss
from pipeline.averaging.result import AveragingResult
from pipeline.averaging.weiszfeld import weiszfeld
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["average", "main", "main_cli", "METHODS"]

logger = logging.getLogger(__name__)

METHODS = ("irls", "irls-h", "l1", "weiszfeld", "sdp")


def _l1_only(vg: ViewGraph, init: str | np.ndarray, max_iterations: int = 100, tol_rad: float = 1e-3,
             admm_max_iterations: int = 200, seed: int | None = 0, init_weights: np.ndarray | None = None) -> AveragingResult:
    """Paper 1, Algorithm 2 run to convergence (a method of its own)."""
    check_graph(vg)
    t0 = time.perf_counter()
    R0 = initial_rotations(vg, init, weights=init_weights, seed=seed)
    R, hist = l1_averaging(vg, R0, max_iterations=max_iterations, tol_rad=tol_rad, admm_max_iterations=admm_max_iterations)
    theta = np.linalg.norm(edge_residuals(vg.edges, vg.R_rel, R), axis=1)
    return AveragingResult(
        method="l1", names=list(vg.names), R=R, time_s=time.perf_counter() - t0, iterations=len(hist),
        edge_index=np.arange(vg.n_edges), residuals_rad=theta, weights=None, history=hist,
        stats={"final_cost": float(theta.sum()), "converged": bool(hist and hist[-1]["mean_step_rad"] < tol_rad)},
    )


def average(
    vg: ViewGraph,
    method: str = "irls",
    loss: str = "l0.5",
    alpha_deg: float = 5.0,
    init: str | np.ndarray = "mst",
    variant: str = "cso3",
    solver: str = "scs",
    **kw: Any,
) -> AveragingResult:
    """Average the relative rotations of a view graph.

    Args:
        vg: the view graph; if disconnected, its largest component is solved.
        method: ``"irls"``, ``"irls-h"`` (IRLS in the H metric,
            :func:`pipeline.averaging.irls_h.irls_h`), ``"l1"``, ``"weiszfeld"`` or ``"sdp"``.
        loss: IRLS loss (see :func:`pipeline.averaging.losses.get_loss`).
        alpha_deg: IRLS loss scale α in degrees.
        init: ``"mst"``, ``"random"`` or (N, 3, 3) initial rotations for the
            cameras of ``vg`` (all of them, in ``vg`` order).
        variant, solver: SDP relaxation and conic solver (``method="sdp"``).
        **kw: passed to the method (e.g. ``max_iterations``, ``tol_rad``,
            ``eps_rad``, ``l1_iterations``, ``seed``, ``refine`` for IRLS). For
            IRLS, ``refine`` defaults to True here (the product default: a
            trimmed-ℓ2 polish after convergence, see :func:`irls`) while
            :func:`irls` itself defaults to paper 1's Algorithm 3 alone.

    Returns:
        :class:`AveragingResult` for the solved component; ``edge_index`` indexes
        ``vg.edges``; ``dropped_names`` lists the cameras left out.

    Raises:
        ValueError: unknown method or loss.
        ViewGraphError: an empty graph, a graph without edges, NaN rotations.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid methods: {', '.join(METHODS)}")
    if method in ("irls", "irls-h"):
        get_loss(loss, alpha_deg, kw.get("eps_rad"))  # fail fast on a bad name
    if method == "irls-h" and vg.H is None:
        raise ViewGraphError("method 'irls-h' needs a view graph with H (two-view BA precisions); "
                             "run the two-view BA stage or use method 'irls'")
    if vg.n_cameras == 0:
        raise ViewGraphError("the view graph is empty (no cameras); nothing to average")
    if vg.n_edges == 0:
        raise ViewGraphError(f"the view graph has {vg.n_cameras} camera(s) but no edge; nothing to average")
    if not np.all(np.isfinite(vg.R_rel)):
        raise ViewGraphError("R_rel contains NaN or inf; fix or drop those edges before averaging")
    sub, edge_kept, dropped = vg, np.arange(vg.n_edges), []
    if not isinstance(init, str):
        init = np.asarray(init, dtype=np.float64)
        if init.shape != (vg.n_cameras, 3, 3):
            raise ValueError(f"init rotations have shape {init.shape} but expected ({vg.n_cameras}, 3, 3)")
    if not vg.is_connected():
        sub, res = vg.largest_component()
        edge_kept, dropped = res.edge_kept, res.dropped_names
        logger.warning(
            "view graph has %d components; solving the largest (%d of %d cameras); dropped: %s%s",
            int(vg.components().max()) + 1, sub.n_cameras, vg.n_cameras,
            ", ".join(dropped[:10]), " ..." if len(dropped) > 10 else "",
        )
        if not isinstance(init, str):
            init = init[res.kept]
        if "init_weights" in kw and kw["init_weights"] is not None:
            kw["init_weights"] = np.asarray(kw["init_weights"])[edge_kept]
    if method == "irls":
        kw.setdefault("refine", True)
        out = irls(sub, loss=loss, alpha_deg=alpha_deg, init=init, **kw)
    elif method == "irls-h":
        from pipeline.averaging.irls_h import irls_h

        out = irls_h(sub, loss=loss, init=init, **kw)
    elif method == "l1":
        out = _l1_only(sub, init, **kw)
    elif method == "weiszfeld":
        out = weiszfeld(sub, init=init, **kw)
    else:
        try:
            from pipeline.averaging.sdp import solve_sdp
        except ImportError as exc:  # pragma: no cover - depends on helper C's module
            raise ValueError(f"method 'sdp' is unavailable: {exc}") from exc
        out = solve_sdp(sub, variant=variant, solver=solver, **kw)
    if out.edge_index is None:
        out.edge_index = np.arange(sub.n_edges)
    out.edge_index = np.asarray(edge_kept)[out.edge_index]
    out.dropped_names = list(dropped) + [n for n in out.dropped_names if n not in dropped]
    return out


# --------------------------------------------------------------------------- main
def _options_hash(input_path: Path, options: dict[str, Any]) -> str:
    st = input_path.stat()
    blob = json.dumps({"input": str(input_path.resolve()), "size": st.st_size, "mtime": st.st_mtime_ns,
                       **{k: str(v) for k, v in sorted(options.items())}}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:12]


def _stored_hash(path: Path) -> str | None:
    try:
        with open(path) as f:
            for line in f:
                if not line.startswith("#"):
                    break
                if "config_hash=" in line:
                    return line.split("config_hash=", 1)[1].strip()
    except OSError:
        return None
    return None


def _load_init(init: str, vg: ViewGraph) -> str | np.ndarray:
    if init in ("mst", "random"):
        return init
    from pipeline.io.rotations import read_rotations

    p = Path(init)
    if not p.is_file():
        raise InputFileError(f"--init {init!r} is neither 'mst', 'random' nor an existing rotations file")
    names, R = read_rotations(p)
    idx = {n: k for k, n in enumerate(names)}
    missing = [n for n in vg.names if n not in idx]
    if missing:
        raise InputFileError(
            f"{p} lacks initial rotations for {len(missing)} camera(s), e.g. {missing[:5]}; "
            "give every camera of the view graph or use --init mst"
        )
    return R[[idx[n] for n in vg.names]]


def main(input_path: str | Path, out_path: str | Path, json_path: str | Path | None = None,
         overwrite: bool = False, **options: Any) -> Path:
    """Read a view graph, average it, write rotations (and JSON stats) atomically.

    Args:
        input_path: view-graph ``.npz`` or supported ``.mat``.
        out_path: rotations text file to write.
        json_path: optional JSON stats file.
        overwrite: recompute even if outputs with the same configuration exist.
        **options: :func:`average` options; ``init`` may be a rotations file path.

    Returns:
        ``out_path``.
    """
    from pipeline.core.atomic import write_json
    from pipeline.io.mat import read_input_graph
    from pipeline.io.rotations import write_rotations

    input_path, out_path = Path(input_path), Path(out_path)
    if not input_path.is_file():
        raise InputFileError(f"input view graph {input_path} does not exist")
    options = {k: v for k, v in options.items() if v is not None}
    h = _options_hash(input_path, options)
    if not overwrite and out_path.is_file() and _stored_hash(out_path) == h and (json_path is None or Path(json_path).is_file()):
        logger.info("%s is up to date (config_hash=%s); skipping (use --overwrite to recompute)", out_path, h)
        return out_path
    data = read_input_graph(input_path)
    vg = data.vg
    init = options.pop("init", "mst")
    init_R = _load_init(init, vg) if isinstance(init, str) else init
    logger.info("averaging %s: %d cameras, %d edges, options %s", input_path, vg.n_cameras, vg.n_edges, options)
    res = average(vg, init=init_R, **options)
    header = f"rotation averaging of {input_path.name}: method={res.method} config_hash={h}"
    if res.dropped_names:
        header = f"dropped (not in the largest component): {' '.join(res.dropped_names)}\n" + header
    write_rotations(out_path, res.names, res.R, header=header)
    if json_path is not None:
        stats = res.summary()
        stats.update({"input": str(input_path), "config_hash": h, "options": {k: str(v) for k, v in options.items()},
                      "init": init if isinstance(init, str) else "array", "history": res.history})
        if res.weights is not None and res.residuals_rad is not None:
            w = res.weights / max(float(np.max(res.weights)), 1e-300)
            order = np.argsort(w)[:20]
            e = vg.edges[res.edge_index[order]]
            stats["n_edges_weight_below_1pct"] = int((w < 0.01).sum())
            stats["most_downweighted_edges"] = [
                {"i": vg.names[a], "j": vg.names[b], "residual_deg": float(np.rad2deg(res.residuals_rad[k])),
                 "relative_weight": float(w[k])} for (a, b), k in zip(e, order)
            ]
        if data.R_gt is not None:
            from pipeline.evaluate import summarize

            kept = np.array([vg.names.index(n) for n in res.names])
            mask = None if data.gt_mask is None else data.gt_mask[kept]
            if mask is None or mask.any():
                stats["vs_ground_truth"] = summarize(res.R, data.R_gt[kept], mask)
        write_json(json_path, stats)
    logger.info("%s: %d cameras in %.3f s, %d iterations -> %s", res.method, len(res.names), res.time_s, res.iterations, out_path)
    return out_path


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli

    p = argparse.ArgumentParser(prog="python -m pipeline.average", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", type=Path, help="view-graph .npz or supported .mat")
    p.add_argument("--method", choices=METHODS, default="irls")
    p.add_argument("--loss", default="l0.5", help="IRLS loss: " + ", ".join(LOSS_NAMES) + " (default l0.5)")
    p.add_argument("--alpha-deg", type=float, default=5.0, help="loss scale α in degrees (default 5)")
    p.add_argument("--floor-deg", type=float, default=None,
                   help="residual floor of ℓ1/ℓp weights in degrees (default: α for p<1, 5.7e-5 otherwise)")
    p.add_argument("--alpha", type=float, default=None,
                   help="irls-h: loss scale α in units of the robust residual scale (default 2)")
    p.add_argument("--no-refine", action="store_true",
                   help="IRLS: skip the final trimmed-ℓ2 polish (paper 1's Algorithm 3 alone)")
    p.add_argument("--init", default="mst", help="mst | random | a rotations file (default mst)")
    p.add_argument("--max-iterations", type=int, default=None, help="iteration cap (IRLS / Weiszfeld sweeps)")
    p.add_argument("--tol-rad", type=float, default=None, help="stopping tolerance on the update (default 1e-3 rad)")
    p.add_argument("--l1-iterations", type=int, default=None, help="initial ℓ1 steps (Algorithm 2) before IRLS (default 20 inexact steps)")
    p.add_argument("--seed", type=int, default=None, help="seed of the random spanning tree")
    p.add_argument("--variant", default="cso3", help="SDP variant: cso3, cso3-iso, o3-iso, o3-aniso")
    p.add_argument("--solver", default="scs", choices=("scs", "clarabel"), help="SDP solver")
    p.add_argument("--out", type=Path, required=True, help="rotations text file to write")
    p.add_argument("--json", type=Path, default=None, help="JSON stats file to write")
    p.add_argument("--overwrite", action="store_true", help="recompute even if the outputs are up to date")

    def body(a: argparse.Namespace) -> int:
        opts: dict[str, Any] = {"method": a.method, "init": a.init}
        if a.method == "irls":
            get_loss(a.loss, a.alpha_deg)  # a bad name fails before any work
            opts.update(loss=a.loss, alpha_deg=a.alpha_deg,
                        eps_rad=None if a.floor_deg is None else float(np.deg2rad(a.floor_deg)),
                        l1_iterations=a.l1_iterations, refine=not a.no_refine)
        if a.method == "irls-h":
            get_loss(a.loss)
            opts.update(loss=a.loss, alpha=a.alpha, l1_iterations=a.l1_iterations, refine=not a.no_refine)
        if a.method in ("irls", "irls-h", "l1", "weiszfeld"):
            opts.update(tol_rad=a.tol_rad, seed=a.seed)
            opts["max_sweeps" if a.method == "weiszfeld" else "max_iterations"] = a.max_iterations
        if a.method == "sdp":
            opts.update(variant=a.variant, solver=a.solver)
        out = main(a.input, a.out, a.json, overwrite=a.overwrite, **opts)
        print(out)
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
