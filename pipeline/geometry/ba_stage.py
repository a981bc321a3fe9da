"""The two-view BA stage: every accepted pair refined, with its rotation precision ``H_ij`` (``python -m pipeline.two_view_ba``).

It reads the two-view result (:func:`pipeline.geometry.two_view_stage.load_two_view`),
refines each pair with :func:`pipeline.geometry.ba_solver.refine_pair` in chunks
on an executor whose workers die with this process (:mod:`pipeline.core.parallel`),
keeps every finished chunk in an item store (an interrupted run resumes per pair)
and writes::

    WORK/viewgraph.npz             a ViewGraph with H, BA inlier counts and per-edge stats
                                   (allow_isolated=True), read by the averaging stage
    WORK/two_view_ba.record.json   the stage record: options, counts, timings and the
                                   pairs that were dropped, with reasons
    WORK/two_view_ba_pairs/        the per-pair results (chunks)

Per-edge stats written: ``t`` (M, 3) refined unit translation, ``t_ransac``,
``R_ransac`` (M, 3, 3), ``ba_sigma2`` (px²), ``ba_rms_px``, ``ba_iterations``,
``ba_n_points``, ``ba_n_inliers``, ``ba_converged``, ``ba_rotation_change_deg``
(angle between the RANSAC and the refined rotation), ``ba_cond_H``, ``ba_focal`` (M, 2)
(the focal lengths of cameras i and j at the optimum: refined when ``refine_focal`` is
on and the cameras stage did not read them from a file), plus every stat of the input
graph that is not overwritten.
"""

from __future__ import annotations

import functools
import logging
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from pipeline.core import so3
from pipeline.core.errors import CacheError, InputFileError
from pipeline.core.store import ItemStore, compute_missing, item_key
from pipeline.core.viewgraph import ViewGraph, precision_problem
from pipeline.geometry.ba_focal import focal_columns
from pipeline.geometry.ba_solver import BAConfig, TwoViewBAError, refine_pair
from pipeline.geometry.stage_io import PairStage, read_viewgraph, recorded_output, rerun_hint, stage_cli
from pipeline.geometry.two_view_stage import NAME as TWO_VIEW, load_two_view
from pipeline.stage import StageRecord, read_record

__all__ = ["TwoViewBAStage", "load_ba_viewgraph", "main_cli", "OUTPUT_NAME"]

logger = logging.getLogger(__name__)

NAME = "two_view_ba"
COMMAND = "pipeline.two_view_ba"
OUTPUT_NAME = "viewgraph.npz"
STORE = "two_view_ba_pairs"
_STATS = ("t", "t_ransac", "R_ransac", "ba_sigma2", "ba_rms_px", "ba_iterations", "ba_n_points", "ba_n_inliers",
          "ba_converged", "ba_rotation_change_deg", "ba_cond_H")

Task = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _refine_chunk(tasks: list[Task], config: BAConfig) -> list[dict[str, Any]]:
    """Worker: refine a chunk of pairs given as arrays; failures become records with a reason."""
    out = []
    for xi, xj, Ki, Kj, R0, t0, A in tasks:
        t_start, c_start = time.perf_counter(), time.thread_time()
        try:
            res = refine_pair(xi, xj, Ki, Kj, R0, t0, config, focal=A)
        except (TwoViewBAError, ValueError, np.linalg.LinAlgError) as exc:
            out.append({"ok": False, "reason": " ".join(str(exc).split()), "n_points": int(len(xi))})
            continue
        out.append({
            "ok": True,
            "R": res.R, "t": res.t, "H": res.H, "sigma2": res.sigma2, "iterations": res.iterations,
            "n_points": int(len(xi)), "n_inliers": res.n_inliers, "converged": res.converged,
            "rms_px": res.rms_px, "time_s": time.perf_counter() - t_start, "cpu_s": time.thread_time() - c_start,
            "focal": np.array([res.K_i[0, 0], res.K_j[0, 0]]),
        })
    return out


def _known_intrinsics(work: Path, n: int, per_image_only: bool = False) -> np.ndarray:
    """(n,) True where K comes from a file (never refined); all True without a cameras result.

    ``per_image_only`` (``refine_focal: auto``): also True for every image whose focal was not estimated on its
    own by the cameras stage (``K_source`` ``estimated:view-graph…``), so that only those are refined.
    """
    from pipeline.frontend.camera_stage import NAME as CAMERAS, PER_IMAGE_SOURCE, load_cameras  # noqa: PLC0415

    if read_record(work, CAMERAS) is None:
        logger.info("two-view BA: no cameras result in %s; every K is taken as known (refine_focal has no effect)",
                    work)
        return np.ones(n, bool)
    cams = load_cameras(work)
    known = cams.known
    if per_image_only:
        known = known | ~np.array([src.startswith(PER_IMAGE_SOURCE) for src in cams.K_source], bool)
    if len(known) != n:
        raise CacheError(f"the cameras of {work} are of {len(known)} images, the two-view result of {n}; re-run "
                         "the front end")
    return known


def _result(item: dict[str, np.ndarray]) -> dict[str, Any]:
    """A stored result with its scalars back as Python values."""
    return {k: (v.item() if v.ndim == 0 else v) for k, v in item.items()}


_SHAPES = {"R": (3, 3), "t": (3,), "H": (3, 3), "focal": (2,), "sigma2": (), "iterations": (), "n_points": (),
           "n_inliers": (), "converged": (), "rms_px": (), "time_s": (), "cpu_s": (), "ok": ()}


def _check_result(item: dict[str, np.ndarray]) -> None:
    """:class:`CacheError` where a stored pair result reads well but is not what :func:`_refine_chunk` writes: a
    field missing or of the wrong shape, or a refined pair whose R is not a rotation, whose t is not a unit vector,
    whose H is not a precision (finite, symmetric, positive definite) or whose figures are out of their range."""
    if "ok" not in item or np.shape(item["ok"]) != ():
        raise CacheError("lacks its 'ok' flag")
    fields = _SHAPES if bool(item["ok"]) else {"reason": (), "n_points": ()}
    wrong = [f for f, shape in fields.items() if f not in item or np.shape(item[f]) != shape]
    if wrong:
        raise CacheError(f"lacks the field {wrong[0]!r} or has it in another shape")
    if not bool(item["ok"]):
        return
    r = _result(item)
    problem = precision_problem(np.asarray(r["H"], np.float64)[None])
    if problem is not None:
        raise CacheError(f"has an H that {problem[1].split(';')[0]}")
    t = np.asarray(r["t"], np.float64)
    if not (so3.is_rotation(np.asarray(r["R"], np.float64)) and np.isfinite(t).all()
            and abs(np.linalg.norm(t) - 1.0) <= 1e-6):
        raise CacheError("has an R that is not a rotation or a t that is not a unit vector")
    figures = np.array([r["sigma2"], r["rms_px"], *r["focal"], r["time_s"], r["cpu_s"]], np.float64)
    if not (np.isfinite(figures).all() and r["sigma2"] > 0 and np.all(figures[1:] >= 0) and np.all(r["focal"] > 0)
            and 0 <= r["n_inliers"] <= r["n_points"] and r["iterations"] >= 0):
        raise CacheError("has a figure out of its range (σ², rms, focal, times, counts)")


def load_ba_viewgraph(work: Path) -> ViewGraph:
    """The view graph with ``H`` that :class:`TwoViewBAStage` wrote in ``work``.

    Raises:
        InputFileError: the stage has not run in ``work``.
        CacheError: the file is damaged (one line naming it; a re-run of the stage heals it).
    """
    _, path = recorded_output(Path(work), NAME, OUTPUT_NAME, COMMAND)
    try:
        vg = read_viewgraph(path)
    except CacheError as exc:
        raise CacheError(f"{exc}; {rerun_hint(COMMAND, work)}") from None
    if vg.H is None:
        raise CacheError(f"{path} has no H; {rerun_hint(COMMAND, work)}")
    return vg


def same_intrinsics(K: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(M,) bool: ``np.allclose(K[i], K[j])`` of each pair (i, j) of ``edges``, for all pairs at once."""
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    return np.isclose(K[e[:, 0]], K[e[:, 1]]).all(axis=(1, 2))


def pair_tasks(data: Any, K: np.ndarray, t_in: np.ndarray, mode: str, known: np.ndarray) -> list[Task]:
    """One BA task per edge of the two-view result ``data``: its inliers, intrinsics, start and focal columns (a
    "shared" focal of two cameras with different K is refined per camera)."""
    vg_in = data.vg
    edges = np.asarray(vg_in.edges, np.int64).reshape(-1, 2)
    same = same_intrinsics(K, edges)
    tasks: list[Task] = []
    for k, (i, j) in enumerate(edges.tolist()):  # gathering the per-edge arrays (one task each): I/O
        xi, xj = data.correspondences(k)
        A = focal_columns(mode if same[k] or mode != "shared" else "per_camera", bool(known[i]), bool(known[j]))
        tasks.append((np.asarray(xi, np.float64), np.asarray(xj, np.float64), K[i], K[j], vg_in.R_rel[k], t_in[k],
                      A))
    return tasks


class TwoViewBAStage(PairStage[BAConfig]):
    """Two-view BA of every pair of the two-view result in a WORK folder (folder = WORK)."""

    name = NAME
    title = "two-view BA"
    config_cls = BAConfig
    store = STORE

    def inputs(self) -> dict[str, str]:
        if not self.folder.is_dir():
            raise InputFileError(f"WORK folder {self.folder} does not exist; run the front end "
                                 "(features, matching, two_view) first")
        from pipeline.frontend.camera_stage import NAME as CAMERAS  # noqa: PLC0415

        two_view = self.upstream(TWO_VIEW)
        cams = read_record(self.folder, CAMERAS)  # its K's (and which focal lengths to refine) are read here too
        if cams is not None and two_view.inputs.get(CAMERAS) != cams.fingerprint:
            raise InputFileError(f"the two-view result in {self.folder} was computed "
                                 f"{'before' if CAMERAS not in two_view.inputs else 'with other intrinsics than'} "
                                 f"the cameras stage's result there; re-run `python -m pipeline.two_view --work "
                                 f"{self.folder}` first")
        return {TWO_VIEW: two_view.fingerprint, **({CAMERAS: cams.fingerprint} if cams is not None else {})}

    def verify(self, record: StageRecord) -> None:
        path = self.folder / OUTPUT_NAME
        vg = read_viewgraph(path)
        n_images = self.upstream(TWO_VIEW).summary.get("n_images")
        if vg.n_cameras != n_images:
            raise CacheError(f"{path} has {vg.n_cameras} cameras but the two-view result {n_images}")
        if vg.n_edges != record.summary.get("n_pairs_out"):
            raise CacheError(f"{path} has {vg.n_edges} edges but its record says {record.summary.get('n_pairs_out')}")
        missing = [k for k in _STATS if k not in vg.stats]
        if vg.H is None or missing:
            raise CacheError(f"{path} lacks {'H' if vg.H is None else 'the per-edge stats ' + str(missing)}")

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        cfg, work = self.config, self.folder
        data = load_two_view(work)
        vg_in = data.vg
        K = np.asarray(data.K, dtype=np.float64)
        logger.info("two-view BA config: %s", cfg.as_dict())
        M = vg_in.n_edges
        t_in = np.asarray(vg_in.stats["t"], dtype=np.float64).reshape(M, 3)
        mode = "per_camera" if cfg.refine_focal == "auto" else cfg.refine_focal
        known = (_known_intrinsics(work, vg_in.n_cameras, per_image_only=cfg.refine_focal == "auto")
                 if mode != "none" else np.ones(vg_in.n_cameras, bool))
        tasks = pair_tasks(data, K, t_in, mode, known)
        fp = cfg.fingerprint()
        keys = [item_key(fp, *task) for task in tasks]
        store = ItemStore(work / self.store)
        store.drop_damaged(keys, lambda k, item: _check_result(item),
                           f"pairs' two-view BA results in {work / self.store}",
                           name=lambda k: "-".join(vg_in.names[c] for c in vg_in.edges[k]))
        done = store.done(keys)
        t0 = time.perf_counter()
        with tqdm(total=M, initial=sum(k in done for k in keys), desc="two-view BA", unit="pair",
                  disable=not cfg.progress) as bar:
            n_computed = compute_missing(store, keys, tasks.__getitem__, functools.partial(_refine_chunk, config=cfg),
                                         workers=cfg.workers, chunk_size=cfg.chunk_size, on_chunk=bar.update,
                                         backend=cfg.backend("processes"), scheduler=cfg.scheduler)
        elapsed = time.perf_counter() - t0
        results = [_result(store.get(k)) for k in keys]
        vg, summary = _assemble(vg_in, t_in, results)
        out = vg.save(work / OUTPUT_NAME)
        summary.update(n_computed=n_computed, ba_time_s=elapsed)
        logger.info(
            "two-view BA: %d/%d pairs refined (%d computed, %d reused) in %.1f s (median %.1f ms/pair, %s iterations), "
            "%d dropped; wrote %s", summary["n_pairs_out"], M, n_computed, M - n_computed, elapsed,
            summary["median_pair_time_ms"] or float("nan"), summary["median_iterations"], len(summary["dropped"]), out,
        )
        return [out] + store.write_index(keys), summary


def _too_few_points(reason: str) -> bool:
    """Whether a pair's failure is :func:`refine_pair`'s "too few points or inliers" (a weak pair, not a fault)."""
    return reason.startswith(("only ", "pair has ")) or "effective points leave" in reason


def _assemble(vg_in: ViewGraph, t_in: np.ndarray, results: list[dict[str, Any]]) -> tuple[ViewGraph, dict[str, Any]]:
    """The refined view graph of the pairs that succeeded and the summary of the run."""
    ok = np.array([r["ok"] for r in results], dtype=bool)
    kept = np.flatnonzero(ok)
    dropped = [
        {"edge": int(k), "pair": [vg_in.names[vg_in.edges[k, 0]], vg_in.names[vg_in.edges[k, 1]]], "reason": results[k]["reason"]}
        for k in np.flatnonzero(~ok)
    ]
    weak = [d for d in dropped if _too_few_points(d["reason"])]
    for d in dropped:  # a pair with too few points is a weak pair, as RANSAC's are: one line for them all
        if not _too_few_points(d["reason"]):
            logger.warning("two-view BA dropped pair %s–%s: %s", d["pair"][0], d["pair"][1], d["reason"])
    if weak:
        logger.info("two-view BA dropped %d pair(s) with too few inlier points to trust their pose (e.g. %s); each is "
                    "listed with its reason among the view graph's rejected pairs", len(weak),
                    "; ".join(f"{d['pair'][0]}–{d['pair'][1]}: {d['reason']}" for d in weak[:2]))
    good = [results[k] for k in kept]
    R = np.array([r["R"] for r in good]).reshape(-1, 3, 3)
    H = np.array([r["H"] for r in good]).reshape(-1, 3, 3)
    stats = {name: np.asarray(v)[kept] for name, v in vg_in.stats.items()}
    stats["t_ransac"] = t_in[kept]
    stats["t"] = np.array([r["t"] for r in good]).reshape(-1, 3)
    stats["R_ransac"] = vg_in.R_rel[kept]
    stats["ba_sigma2"] = np.array([r["sigma2"] for r in good], dtype=np.float64)
    stats["ba_rms_px"] = np.array([r["rms_px"] for r in good], dtype=np.float64)
    stats["ba_iterations"] = np.array([r["iterations"] for r in good], dtype=np.int64)
    stats["ba_n_points"] = np.array([r["n_points"] for r in good], dtype=np.int64)
    stats["ba_n_inliers"] = np.array([r["n_inliers"] for r in good], dtype=np.int64)
    stats["ba_converged"] = np.array([r["converged"] for r in good], dtype=bool)
    stats["ba_focal"] = np.array([r["focal"] for r in good], dtype=np.float64).reshape(-1, 2)
    stats["ba_rotation_change_deg"] = np.rad2deg(so3.angle_between(R, vg_in.R_rel[kept])) if len(kept) else np.zeros(0)
    lamH = np.linalg.eigvalsh(H) if len(kept) else np.zeros((0, 3))
    stats["ba_cond_H"] = lamH[:, -1] / lamH[:, 0] if len(kept) else np.zeros(0)
    vg = ViewGraph(vg_in.names, vg_in.edges[kept], R, H=H, inliers=stats["ba_n_inliers"], stats=stats, allow_isolated=True)
    times = np.array([r["time_s"] for r in good])
    summary = {
        "n_images": vg.n_cameras,
        "n_pairs_in": vg_in.n_edges,
        "n_pairs_out": int(len(kept)),
        "dropped": dropped,
        "median_pair_time_ms": float(np.median(times) * 1e3) if times.size else None,
        "median_pair_cpu_ms": float(np.median([r["cpu_s"] for r in good]) * 1e3) if good else None,
        "median_iterations": float(np.median(stats["ba_iterations"])) if len(kept) else None,
        "median_rotation_change_deg": float(np.median(stats["ba_rotation_change_deg"])) if len(kept) else None,
        "median_cond_H": float(np.median(stats["ba_cond_H"])) if len(kept) else None,
    }
    return vg, summary


def main_cli(argv: Sequence[str] | None = None) -> int:
    return stage_cli(TwoViewBAStage, "python -m pipeline.two_view_ba",
                     "Two-view bundle adjustment of every accepted pair in WORK and the marginalized 3×3 rotation "
                     "Hessian H_ij; writes WORK/viewgraph.npz for the averaging stage.", OUTPUT_NAME, argv)
