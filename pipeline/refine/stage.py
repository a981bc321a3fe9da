"""The refine stage: averaged rotations finished by pycolmap's multi-view machinery (``python -m pipeline.refine``).

It reads our front end's WORK folder (features, two-view inliers, the two-view BA
view graph) and one averaging method's rotations in ``OUT/rotations/``, runs
:func:`pipeline.refine.refine.refine_rotations`, and writes, atomically::

    OUT/sparse/                          the COLMAP model (cameras, images, points3D, rigs,
                                         frames), opened by ``pycolmap.Reconstruction(path)``;
                                         absent when the refinement failed
    OUT/rotations/<start>+refine.txt     the rotations to use: refined, or averaged where the
                                         refinement failed or moved a camera more than
                                         ``max_change_deg`` (the cameras of <start>.txt, then
                                         those the refinement placed: ``place_left_out``)
    OUT/rotations/<start>+refine.json    status, warnings, per camera: refined or kept averaged
                                         and why, change from the averaged rotation, predicted
                                         uncertainty (√tr Σ, degrees) and covariance (rad²)
    OUT/refine.record.json               the stage record

The start is a method's label, or ``auto``: the recommended one (:func:`recommended_start`).
The averaged rotations file is never changed: both sets stay.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.core.atomic import atomic_dir, write_json
from pipeline.core.errors import CacheError, InputFileError, PipelineError
from pipeline.core.names import match_names, positions
from pipeline.io.rotations import read_rotations, write_rotations
from pipeline.refine.refine import RefineConfig, RefineResult, refine_rotations
from pipeline.stage import Stage, StageRecord, read_record

logger = logging.getLogger(__name__)

__all__ = ["RefineStage", "recommended_start", "run_refine", "refine_for_run", "refine_notes", "refined_label",
           "load_inputs",
           "main_cli", "MODEL", "PREFERRED"]

MODEL = "sparse"
GRAPH = "viewgraph.npz"  # the checked view graph (pipeline.graph.stage) beside the rotations
ROTATIONS = "rotations"
#: The recommended starts, best first: IRLS-H-ℓ½ where the view graph has H, else IRLS-ℓ½. The
#: refined result hardly depends on the start (r14: < 1e-4° between both); what matters is a
#: robust start for the edge filter and for global positioning's basin.
PREFERRED = ("irls-h-l0.5", "irls-l0.5")


def refined_label(start: str) -> str:
    return f"{start}+refine"


def recommended_start(labels: Sequence[str]) -> tuple[str, str]:
    """The method to start from among ``labels`` (those run) and why."""
    labels = list(labels)
    for p in PREFERRED:
        if p in labels:
            return p, f"{p}: the recommended start ({' > '.join(PREFERRED)})"
    if not labels:
        raise PipelineError("no averaged rotations to refine: run an averaging method first")
    return labels[0], f"{labels[0]}: the first method run (none of {', '.join(PREFERRED)} ran)"


def _known_K(sources: Sequence[str], n: int) -> np.ndarray:
    """Intrinsics read from a file are known (kept constant); estimated, EXIF and default focals are refined."""
    if len(sources) != n:
        return np.zeros(n, bool)
    from pipeline.frontend.camera_stage import given_source  # noqa: PLC0415

    return np.array([given_source(str(s)) for s in sources], bool)


def _intrinsics(work: Path, fs: Any, lens: str = "measured"
                ) -> tuple[np.ndarray, list[np.ndarray], list[str], np.ndarray]:
    """The starting intrinsics: the cameras stage's (estimated focal, undistorted keypoints), else the features'.

    Returns K (N, 3, 3), the keypoints, each K's source and each camera's starting k1. The keypoints are those
    the geometry used (undistorted where the cameras stage found distortion: the model's cameras are then
    pinhole in undistorted pixels, k1 = 0), except that with ``lens="measured"`` an image whose lens the stage
    estimated, and whose K no file gave, keeps its measured keypoints and starts from the stage's SIMPLE_RADIAL k1.
    """
    from pipeline.frontend.camera_stage import cameras_for, given_source  # noqa: PLC0415

    n = len(fs.names)
    cams = cameras_for(work, fs.names)
    if cams is None:
        return fs.K, list(fs.keypoints), list(fs.K_source), np.zeros(n)
    kp = list(cams.keypoints_for_geometry(fs.keypoints))
    k1 = np.zeros(n)
    if lens == "measured":
        for k, (m, src) in enumerate(zip(cams.models, cams.distortion_source)):
            if (src.startswith("estimated") and m.model == "SIMPLE_RADIAL" and m.params[3] != 0.0
                    and not given_source(cams.K_source[k])):  # a given K is held: its lens stays undone
                k1[k], kp[k] = float(m.params[3]), np.asarray(fs.keypoints[k], np.float64)[:, :2]
    return cams.K, kp, list(cams.K_source), k1


def _checked_pairs(vg: Any, graph: Path | None, weak: bool = True) -> Any:
    """The two-view BA graph ``vg`` cut to the pairs whose matches make tracks: those the view-graph stage kept
    (``graph``, OUT/viewgraph.npz) and, with ``weak``, those it rejected only because their rotation is poorly
    determined (``tracks`` in the summary beside it, :func:`pipeline.graph.stage.track_pairs`)."""
    from pipeline.core.viewgraph import ViewGraph, pair_keys  # noqa: PLC0415
    from pipeline.graph.stage import SUMMARY, load_graph_summary  # noqa: PLC0415

    if graph is None or not Path(graph).is_file():
        return vg
    g = ViewGraph.load(graph, allow_isolated=True)
    pairs = [positions(vg.names, g.names, missing=-1)[g.edges.reshape(-1, 2)]]  # as cameras of vg (−1: not in it)
    if weak and (Path(graph).parent / SUMMARY).is_file():
        rows = load_graph_summary(Path(graph).parent).get("pairs", [])
        try:  # one row per pair in the JSON file
            weak_names = [str(nm) for r in rows if r.get("tracks") is True and r.get("status") == "rejected"
                          for nm in (r["pair"][0], r["pair"][1])]
        except (TypeError, KeyError, IndexError, AttributeError):
            raise CacheError(f"{Path(graph).parent / SUMMARY} has malformed pairs; re-run the view-graph stage"
                             ) from None
        pairs.append(positions(vg.names, weak_names, missing=-1).reshape(-1, 2))
    P, n = np.concatenate(pairs), len(vg.names)
    P = P[(P >= 0).all(axis=1)]
    E = np.asarray(vg.edges, np.int64).reshape(-1, 2)
    keep = np.isin(pair_keys(E[:, 0], E[:, 1], n), pair_keys(P[:, 0], P[:, 1], n))  # either orientation
    return ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep], H=vg.H[keep],
                     inliers=None if vg.inliers is None else vg.inliers[keep],
                     stats={k: np.asarray(v)[keep] for k, v in vg.stats.items()}, allow_isolated=True)


def load_inputs(work: Path, rotations: Path, graph: Path | None = None, lens: str = "measured",
                weak_pairs: bool = True) -> tuple[dict[str, Any], list[str], np.ndarray]:
    """The keyword inputs of :func:`refine_rotations` from WORK and an averaged rotations file.

    Only the pairs of the checked view graph ``graph`` (OUT/viewgraph.npz: what the view-graph
    stage kept) make tracks, and with ``weak_pairs`` those it rejected only as poorly determined
    (weak H: their matches passed the inlier gates); every two-view BA pair without ``graph``.

    ``lens``: :class:`~pipeline.refine.refine.RefineConfig`'s ``lens`` (which keypoints, which starting k1).

    Returns:
        the inputs (over every image of the features; NaN rotations for images the file
        lacks), the file's camera names and (len(names),) their images' indices.
    """
    from pipeline.frontend.feature_stage import load_features  # noqa: PLC0415
    from pipeline.geometry.ba_stage import load_ba_viewgraph  # noqa: PLC0415
    from pipeline.geometry.two_view_stage import load_two_view  # noqa: PLC0415

    fs = load_features(work, descriptors=False)
    tv = load_two_view(work)
    vg = _checked_pairs(load_ba_viewgraph(work), graph, weak_pairs)
    n = len(fs.names)
    if tv.vg.n_cameras != n or vg.n_cameras != n:
        raise CacheError(f"the two-view results in {work} are of {tv.vg.n_cameras} images, the features of {n}; "
                         "re-run the front end")
    # the pairs that passed two-view BA, with their two-view inliers and refined poses
    try:
        offsets, matches = tv.inliers_of(vg.edges)
    except ValueError:
        raise CacheError(f"the two-view BA view graph in {work} has pairs the two-view result lacks; re-run the front "
                         "end") from None
    names, R = read_rotations(rotations)
    cams = match_names(names, list(fs.names), what=f"the images of {work}")
    if np.any(cams < 0) or len(set(cams.tolist())) != len(cams):
        raise InputFileError(f"{rotations} names cameras that are not images of {work} (e.g. "
                             f"{[nm for nm, c in zip(names, cams) if c < 0][:3]}); re-run the averaging")
    R_init = np.full((n, 3, 3), np.nan)
    R_init[cams] = R
    K, keypoints, sources, k1 = _intrinsics(work, fs, lens)
    return {"names": list(fs.names), "K": K, "sizes": fs.sizes, "keypoints": keypoints, "edges": vg.edges,
            "match_offsets": offsets,
            "matches": matches, "cam2_from_cam1": vg.R_rel,
            "t_cam2_from_cam1": np.asarray(vg.stats["t"], float), "R_init": R_init,
            "known_K": _known_K(sources, n), "k1": k1}, list(names), cams


class RefineStage(Stage[RefineConfig]):
    """One averaging method's rotations refined by pycolmap (folder = OUT).

    Args:
        folder: OUT; the averaged rotations are read from ``OUT/rotations/<start>.txt``.
        config: options; ``config.start`` may be ``auto``.
        work: the front end's WORK folder (default ``OUT/work``).
        methods: the labels of the methods run (to resolve ``auto``; default: the records
            found in ``OUT/rotations``).
    """

    name = "refine"
    title = "multi-view refinement (pycolmap)"
    config_cls = RefineConfig
    # 2: no BA σ for a camera it did not refine; 3: no covariance where pycolmap's is not finite (a warning);
    # 4: a principal point refined to near the image centre is held there (refine.min_principal_point_offset);
    # 5: the principal-point probe's screen (one bundle adjustment) spares its run where the centre is no misfit
    version = 5

    def __init__(self, folder: Path, config: RefineConfig | None = None, *, work: Path | None = None,
                 methods: Sequence[str] | None = None) -> None:
        super().__init__(folder, config)
        self.work = Path(work) if work is not None else self.folder / "work"
        self.rot_dir = self.folder / ROTATIONS
        if self.config.start == "auto":
            if methods is None:
                methods = sorted(p.name[:-len(".record.json")] for p in self.rot_dir.glob("*.record.json")
                                 if "+" not in p.name)
                if not methods:
                    raise InputFileError(f"no averaged rotations to refine in {self.rot_dir}: run run.py with --out "
                                         f"{self.folder}, or `python -m pipeline.average {self.work}/viewgraph.npz "
                                         f"--out {self.rot_dir}/irls-l0.5.txt` (a method's label as the file name)")
            self.start, self.start_why = recommended_start(methods)
        else:
            self.start, self.start_why = self.config.start, f"{self.config.start}: configured"
        self.label = refined_label(self.start)
        self.rotations_path = self.rot_dir / f"{self.label}.txt"
        self.stats_path = self.rot_dir / f"{self.label}.json"
        self.known_K: np.ndarray | None = None
        self.placed: dict[str, str] = {}

    def inputs(self) -> dict[str, str]:
        if not (self.rot_dir / f"{self.start}.record.json").is_file():
            raise InputFileError(f"{self.rot_dir} has no rotations of '{self.start}', the refinement's start: run that "
                                 "averaging method first (run.py --methods), or set refine.start to a method that ran")
        out = {"averaging": self.upstream("averaging", self.rot_dir, self.start).fingerprint}
        ups = ("features", "cameras", "two_view", "two_view_ba") if read_record(self.work, "cameras") is not None \
            else ("features", "two_view", "two_view_ba")
        out.update({up: self.upstream(up, self.work).fingerprint for up in ups})
        graph = read_record(self.folder, "viewgraph")  # the checked pairs, when the view-graph stage ran here
        if graph is not None:
            out["viewgraph"] = graph.fingerprint
        return out

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        logger.info("refine: start %s; options %s", self.start_why, self.config.as_dict())
        inputs, start_names, rows = load_inputs(self.work, self.rot_dir / f"{self.start}.txt", self.folder / GRAPH,
                                                 self.config.lens, self.config.weak_pairs)
        self.known_K = inputs["known_K"]
        R_start, through = self._left_out_starts(inputs)
        res = refine_rotations(**inputs, config=self.config, scratch=self.folder, R_start=R_start)
        placed = [k for k in np.flatnonzero(through) if res.refined[k]]  # started from its pairs and refined
        start_names, rows = list(start_names) + [inputs["names"][k] for k in placed], np.r_[rows, placed].astype(int)
        self.placed = {inputs["names"][k]: (f"placed by the refinement alone, from its {int(through[k])} pair(s) the "
                                            "view graph rejected as weak (rotation poorly determined); no averaged "
                                            "rotation confirms it") for k in placed}
        paths: list[Path] = []
        model = self.folder / MODEL
        if res.reconstruction is not None:
            with atomic_dir(model) as tmp:
                res.reconstruction.write(tmp)
            paths += sorted(p for p in model.rglob("*") if p.is_file())
        else:
            shutil.rmtree(model, ignore_errors=True)  # a model of an earlier run would not match these rotations
        header = (f"rotations of {self.start} refined by pycolmap (global positioning, bundle adjustment, "
                  f"retriangulation): status {res.status}; averaged where not refined")
        paths.append(write_rotations(self.rotations_path, start_names, res.R[rows], header=header))
        stats = refine_stats(res, start_names, rows, self)
        paths.append(write_json(self.stats_path, stats))
        logger.info("refine: %s, %d of %d cameras refined in %.1f s (%d points); %s", res.status,
                    int(res.refined[rows].sum()), len(rows), res.stats["times"]["total"], res.stats.get("n_points", 0),
                    self.rotations_path)
        return paths, {k: stats[k] for k in ("label", "status", "n_cameras", "n_refined", "n_points", "time_s")}

    def _left_out_starts(self, inputs: dict[str, Any]) -> tuple[np.ndarray | None, np.ndarray]:
        """Starts of the images the view graph left out (not solved as a component of their own) whose pairs make
        tracks, chained from the averaged rotations (``place_left_out``); the pairs each came through."""
        from pipeline.graph.stage import SUMMARY, load_graph_summary  # noqa: PLC0415
        from pipeline.refine.checks import chain_starts  # noqa: PLC0415

        n = len(inputs["names"])
        if not (self.config.place_left_out and self.config.weak_pairs and (self.folder / SUMMARY).is_file()):
            return None, np.zeros(n, np.int64)
        left = {nm for nm, why in load_graph_summary(self.folder).get("left_out", {}).items()
                if not str(why).startswith("solved as component")}
        targets = np.array([nm in left for nm in inputs["names"]], bool) & ~np.isfinite(inputs["R_init"]).all(axis=(1, 2))
        if not targets.any():
            return None, np.zeros(n, np.int64)
        return chain_starts(inputs["edges"], inputs["cam2_from_cam1"], inputs["R_init"], targets)

    def verify(self, record: StageRecord) -> None:
        names, _ = read_rotations(self.rotations_path)
        start_names, _ = read_rotations(self.rot_dir / f"{self.start}.txt")
        stats = read_stats(self.stats_path)
        if list(names) != list(start_names) + list(stats.get("placed") or {}):
            raise CacheError(f"{self.rotations_path} holds other cameras than {self.start}.txt and the images the "
                             "refinement placed")
        if stats.get("n_cameras") != len(names) or (stats.get("model") is not None) != (self.folder / MODEL).is_dir():
            raise CacheError(f"{self.stats_path} does not describe {self.rotations_path} and {self.folder / MODEL}")


def _deg(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _model_focals(rec: Any) -> dict[int, float]:
    """Image index → the model's (refined, mean of fx and fy) focal length in pixels; empty without a model."""
    if rec is None:
        return {}
    out = {}
    for iid in rec.reg_image_ids():
        f = rec.camera(rec.image(iid).camera_id).focal_length_x, rec.camera(rec.image(iid).camera_id).focal_length_y
        out[iid - 1] = float(np.mean(f))
    return out


def refine_stats(res: RefineResult, names: list[str], rows: np.ndarray, stage: RefineStage) -> dict[str, Any]:
    """The JSON stats of a refinement over the start's cameras ``names`` (images ``rows`` of ``res``)."""
    sigma = np.degrees(np.sqrt(np.trace(res.cov, axis1=1, axis2=2))) if res.cov is not None else \
        np.full(len(res.R), np.nan)
    cams = list(zip(names, rows.tolist()))
    focal = _model_focals(res.reconstruction)
    cameras = {}
    for nm, k in cams:
        c: dict[str, Any] = {"refined": bool(res.refined[k]), "change_deg": _deg(res.change_deg[k]),
                             "sigma_deg": _deg(sigma[k]) if res.refined[k] else None}
        if not res.refined[k]:
            c["kept_averaged_why"] = res.why[k]
            if np.isfinite(res.R_refined[k]).all():
                c["refined_cam_from_world"] = res.R_refined[k].ravel().tolist()
        if res.refined[k] and res.cov is not None and np.isfinite(res.cov[k]).all():
            c["cov_rad2"] = res.cov[k].ravel().tolist()
        if k in focal:
            c["focal_px"] = focal[k]
        cameras[nm] = c
    ok_sigma = sigma[rows][res.refined[rows] & np.isfinite(sigma[rows])]  # a camera not refined has no BA σ
    s = res.stats
    return {"method": "refine", "label": stage.label, "start": stage.start, "start_why": stage.start_why,
            "status": res.status, "warnings": res.warnings, "n_cameras": len(rows),
            "n_refined": int(res.refined[rows].sum()),
            "kept_averaged": {nm: res.why[k] for nm, k in cams if not res.refined[k]},
            "anchored": [nm for nm, k in cams if res.anchored is not None and res.anchored[k]],
            "placed": dict(stage.placed),
            "sigma_median_deg": float(np.median(ok_sigma)) if len(ok_sigma) else None,
            "uncertainty_deg": {nm: _deg(sigma[k]) if res.refined[k] else None for nm, k in cams},
            "change_from_averaged_deg": {nm: _deg(res.change_deg[k]) for nm, k in cams},
            "focal_px_median": float(np.median(list(focal.values()))) if focal else None,
            "focal_refined": not bool(np.all(stage.known_K)) if stage.known_K is not None else None,
            "principal_point": s.get("principal_point"), "principal_point_rejected": s.get("principal_point_rejected"),
            "principal_point_fixed_why": s.get("principal_point_fixed_why"),
            "principal_point_near_centre": s.get("principal_point_near_centre"),
            "principal_point_probe": {k: v for k, v in (s.get("principal_point_probe") or {}).items() if k != "cameras"}
            or None,
            "model": MODEL if res.reconstruction is not None else None, "n_points": int(s.get("n_points", 0)),
            "time_s": float(s["times"]["total"]), "times": s["times"], "options": stage.config.as_dict(),
            "stats": {k: v for k, v in s.items() if k != "times"}, "cameras": cameras}


def read_stats(path: Path) -> dict[str, Any]:
    """The stats JSON of a refinement; :class:`CacheError` naming it if unreadable."""
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
        if not isinstance(d, dict) or d.get("method") != "refine" or not isinstance(d.get("cameras"), dict):
            raise ValueError("not the stats of a refinement")
        return d
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); re-run `python -m pipeline.refine`") \
            from None


def run_refine(out: Path, config: RefineConfig, methods: Sequence[str] | None = None, work: Path | None = None,
               overwrite: bool = False) -> dict[str, dict[str, Any]]:
    """Run (or reuse) the stage in ``out``: ``{label: {"rotations", "stats", "record"}}``, as the averaging stage's."""
    stage = RefineStage(Path(out), config, work=work, methods=methods)
    record = stage.run(overwrite)
    summary = {k: v for k, v in read_stats(stage.stats_path).items() if k not in ("cameras", "options", "stats")}
    return {stage.label: {"rotations": stage.rotations_path, "stats": summary, "record": record}}


def refine_notes(results: dict[str, dict[str, Any]]) -> list[str]:
    """The report's notes on a refinement (:func:`run_refine`'s result): its start, status and every kept camera."""
    notes = []
    for label, r in results.items():
        s = r["stats"]
        notes.append(f"{label}: started from {s['start_why']}; status {s['status']}, {s['n_refined']}/{s['n_cameras']} "
                     f"cameras refined" + (f"; COLMAP model in {MODEL}/" if s.get("model") else "; no model written"))
        if s.get("focal_refined") and s.get("focal_px_median") is not None:
            notes.append(f"{label}: focal lengths not given by a file were refined by pycolmap's bundle adjustment "
                         f"(from the cameras stage's); median {s['focal_px_median']:.1f} px")
        probe = (s.get("principal_point_probe") or {}).get("decision")
        if s.get("principal_point_fixed_why"):
            notes.append(f"{label}: principal points kept at the image centres: {s['principal_point_fixed_why']}"
                         + (f"; probed: {probe}" if probe else ""))
        elif probe:
            notes.append(f"{label}: {probe}")
        if s.get("principal_point_near_centre"):
            off = max(float(pp.get("offset_px", 0.0)) for pp in s["principal_point_near_centre"].values())
            notes.append(f"{label}: principal points held at the image centres, as COLMAP's mappers hold them: refined, "
                         f"they came within {off:.1f} px of the centre (refine.min_principal_point_offset), nearer "
                         "than their real error")
        for cid, pp in (s.get("principal_point") or {}).items():
            sd = pp.get("sd_px")  # null where it is not finite (a singular covariance)
            notes.append(f"{label}: principal point of camera {cid} refined to ({pp['px'][0]:.1f}, {pp['px'][1]:.1f}) "
                         + (f"px, standard deviation {sd:.2f} px" if sd is not None else
                            "px, no finite standard deviation"))
        if s["status"] == "failed":
            notes.append(f"{label}: the refinement failed, so its rotations are the averaged ones of {s['start']}")
        notes += [f"{label}: {nm}, left out of the view graph, is {why}" for nm, why in (s.get("placed") or {}).items()]
        notes += [f"{label}: {nm} {'is not refined' if nm in s.get('anchored', ()) else 'keeps its averaged rotation'}"
                  f": {why}" for nm, why in s["kept_averaged"].items() if why != "no averaged rotation"]
    return notes


def refine_for_run(out: Path, config: RefineConfig, methods: Sequence[str], work: Path, overwrite: bool,
                   notes: list[str]) -> dict[str, dict[str, Any]]:
    """:func:`run_refine` for ``run.py``: its notes appended to ``notes``; a failure to run is a note, not an error.

    Returns:
        ``{label: result}`` to add to the averaging results (empty when the stage could not run).
    """
    try:
        res = run_refine(out, config, methods, work, overwrite)
    except (PipelineError, RuntimeError, ValueError, OSError) as exc:  # the averaged rotations stand without it
        notes.append(f"refine failed: {' '.join(str(exc).split())}; the averaged rotations are kept")
        logger.warning("%s", notes[-1])
        return {}
    notes += refine_notes(res)
    return res


def main_cli(argv: Sequence[str] | None = None) -> int:
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m pipeline.refine", description="Refine one averaging method's "
                                "rotations with pycolmap (global positioning, BA, retriangulation); writes "
                                "OUT/sparse/ and OUT/rotations/<start>+refine.txt.")
    p.add_argument("--out", type=Path, required=True, help="the run's output folder (holds rotations/)")
    p.add_argument("--work", type=Path, default=None, help="the front end's WORK folder (default OUT/work)")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'refine' section is used")
    p.add_argument("--overwrite", action="store_true", help="recompute even if an intact result exists")
    add_config_args(p, RefineConfig)

    def body(a: argparse.Namespace) -> int:
        cfg = config_from_args(RefineConfig, a, a.config)
        res = run_refine(a.out, cfg, work=a.work, overwrite=a.overwrite)
        for label, r in res.items():
            s = r["stats"]
            print(f"{label}: {s['status']}, {s['n_refined']}/{s['n_cameras']} cameras refined; {r['rotations']}")
            for nm, why in s["kept_averaged"].items():
                print(f"  {'not refined' if nm in s.get('anchored', ()) else 'kept averaged'}: {nm}: {why}")
            for nm, why in (s.get("placed") or {}).items():
                print(f"  placed: {nm}: {why}")
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
