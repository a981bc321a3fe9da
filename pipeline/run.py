"""The whole pipeline on an image folder: images → rotations → evaluation → report.

The implementation behind the top-level ``run.py`` (a thin entry point); also
``python -m pipeline.run``. Usage::

    python run.py [IMAGE_DIR] [--out DIR] [--config configs/NAME.yaml] [--methods M ...]
                  [--gt REF] [--K FILE] [--no-reference] [--overwrite] [-v | -q]

Stages, in order (each one is the ``main()`` of its ``python -m pipeline.<stage>``
command, so running the stage commands one by one on the same folders gives the
same files):

1. features          ``pipeline.features``      → OUT/work/features.json (+ per-image cache)
2. matching          ``pipeline.matching``      → OUT/work/...
3. two-view          ``pipeline.two_view``      → OUT/work/... (RANSAC view graph)
4. two-view BA       ``pipeline.two_view_ba``   → OUT/work/viewgraph.npz (with H)
5. view graph        largest connected component → OUT/viewgraph.npz (the rest named)
6. averaging         ``pipeline.average``       → OUT/rotations/<method>.txt + .json
7. pycolmap          ``pipeline.reference``     → OUT/reference/ (rotations.txt, reference.json)
8. evaluation        ``pipeline.evaluate``      → OUT/metrics.json
9. report            ``pipeline.report``        → OUT/report.md + PNGs

Averaging methods (``--methods``; default IRLS-ℓ½, plus, when the view graph has
H, IRLS-H-ℓ½ and SDP-cSO(3), the latter when it has at most ``run.sdp_max_n``
cameras):

- ``irls`` (= ``irls-l0.5``), ``irls-<loss>`` for any loss of ``pipeline.average``
  (``l2``, ``l1``, ``l<p>``, ``geman-mcclure``, ``huber``, ...): paper 1;
- ``irls-h`` (= ``irls-h-l0.5``), ``irls-h-<loss>``: the same IRLS with each
  residual in its H metric (``pipeline.averaging.irls_h``; not in either paper);
- ``l1`` (the initial ℓ1 step alone), ``weiszfeld``;
- ``sdp`` (= ``sdp-cso3``), ``sdp-cso3-iso``, ``sdp-o3-iso``, ``sdp-o3-aniso``.

References: ``--gt REF`` (true cameras: a rendered cameras file, Strecha
``gt_dense_cameras/``, Middlebury ``*_par.txt``, a COLMAP model or a rotations
file) and the pycolmap reconstruction. Every method is evaluated against every
reference; pycolmap is also evaluated against the truth.

With no IMAGE_DIR, a tiny scene is rendered (``pipeline.synthetic.render``) into
OUT/scene and the pipeline runs on it with its cameras file as the truth.

Re-running with the same ``--out`` reuses every finished stage (each stage's own
cache); ``--overwrite`` redoes everything.
"""

from __future__ import annotations

import os

# pycolmap's OpenMP runtime busy-waits otherwise (15-60x slower on 2 shared cores)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.averaging import registry  # noqa: E402
from pipeline.averaging.convergence import error_vs_time_curves  # noqa: E402
from pipeline.averaging.registry import parse_methods  # noqa: E402
from pipeline.averaging.stage import run_averaging  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core.config import load_yaml, stage_config  # noqa: E402
from pipeline.core.errors import InputFileError, PipelineError  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402

logger = logging.getLogger("run")

# configs/ sits beside the package in a checkout; without it the dataclass defaults apply
DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"
STAGES = ("features", "matching", "two_view", "two_view_ba", "viewgraph", "averaging", "reference", "evaluation",
          "report")


@dataclass(frozen=True, kw_only=True)
class RunConfig:
    """Options of run.py itself (YAML section ``run``).

    Attributes:
        methods: averaging methods; empty = IRLS-ℓ½ plus SDP-cSO(3) when N ≤ sdp_max_n.
        sdp_max_n: largest view graph (cameras) on which SDP runs by default.
        sdp_solver: conic solver of the SDP ("scs" or "clarabel").
        reference: run the pycolmap reference.
        align: global alignment of the evaluation ("l2" or "l1").
        scene_views: views of the default rendered scene (no IMAGE_DIR).
        scene_seed: seed of the default rendered scene.
        scene_noise: pixel noise (0-255 scale) of the default rendered scene.
        plots: write the PNG plots of the report.
    """

    methods: tuple[str, ...] = ()
    sdp_max_n: int = 60
    sdp_solver: str = "scs"
    reference: bool = True
    align: str = "l2"
    scene_views: int = 8
    scene_seed: int = 0
    scene_noise: float = 0.0
    plots: bool = True

    def __post_init__(self) -> None:
        m = self.methods  # a YAML scalar (methods: irls) is one entry, not its characters
        object.__setattr__(self, "methods", (m,) if isinstance(m, str) else tuple(m or ()))
        if self.align not in ("l2", "l1"):
            raise InputFileError(f"[run] align={self.align!r}; expected 'l2' or 'l1'")
        if self.sdp_max_n < 0:
            raise InputFileError(f"[run] sdp_max_n={self.sdp_max_n}; expected >= 0")


def _mtimes(paths: list[Path]) -> list[int | None]:
    return [p.stat().st_mtime_ns if p.exists() else None for p in paths]


class StageRunner:
    """Times stages, prints one progress line per stage, records whether a stage reused its result."""

    def __init__(self, quiet: bool = False) -> None:
        self.times: dict[str, float] = {}
        self.reused: dict[str, bool] = {}
        self.quiet = quiet
        self.k = 0

    def __call__(self, name: str, title: str, fn: Callable[[], Any],
                 outputs: Callable[[], list[Path]] | None = None) -> Any:
        """Run stage ``name``; ``outputs`` lists its result files (unchanged mtimes = reused)."""
        self.k += 1
        if not self.quiet:
            print(f"[{self.k}/{len(STAGES)}] {title} ...", file=sys.stderr, flush=True)
        before = (outputs(), _mtimes(outputs())) if outputs else None
        t0 = time.perf_counter()
        res = fn()
        dt = time.perf_counter() - t0
        self.times[name] = dt
        if outputs and before is not None:
            paths = outputs()
            self.reused[name] = bool(paths) and paths == before[0] and _mtimes(paths) == before[1]
        if not self.quiet:
            tag = " (reused)" if self.reused.get(name) else ""
            print(f"[{self.k}/{len(STAGES)}] {title}: {dt:.2f} s{tag}", file=sys.stderr, flush=True)
        return res


# ----------------------------------------------------------------------- stages
def _cfg(module: Any, cls_names: tuple[str, ...], yaml_data: dict, section: str) -> Any:
    """The stage's config dataclass from YAML, or None when the module has no known config class."""
    for n in cls_names:
        cls = getattr(module, n, None)
        if cls is not None:
            return stage_config(cls, yaml_data, section)
    if yaml_data.get(section):
        raise InputFileError(f"[{section}] options given but {module.__name__} has no config class")
    return None


def _left_out_reasons(vg_all: ViewGraph, labels: np.ndarray, rejected: list[dict]) -> dict[str, str]:
    """Why each camera outside the largest component is left out."""
    deg = vg_all.degrees()
    sizes = np.bincount(labels)
    reasons: dict[str, str] = {}
    for k, nm in enumerate(vg_all.names):
        if labels[k] == 0:
            continue
        if deg[k] == 0:
            mine = [r for r in rejected if nm in r.get("names", [])]
            why = [str(r.get("reason", "?")) for r in mine]
            common = max(set(why), key=why.count) if why else "no match with any image"
            reasons[nm] = (f"no accepted image pair ({len(mine)} pair(s) rejected, most often: {common})"
                           if mine else f"no accepted image pair ({common})")
        else:
            others = [n for j, n in enumerate(vg_all.names) if labels[j] == labels[k] and j != k]
            reasons[nm] = (f"in another connected component of {sizes[labels[k]]} images "
                           f"(with {', '.join(others[:5])}{'...' if len(others) > 5 else ''}), not linked to the largest")
    return reasons


def stage_viewgraph(work: Path, out: Path, rejected: list[dict] | None = None) -> tuple[ViewGraph, dict[str, str], Path]:
    """Stage 5: the largest connected component of the BA view graph, saved as OUT/viewgraph.npz.

    Args:
        work: WORK folder holding ``viewgraph.npz`` (two-view BA's output).
        out: OUT folder.
        rejected: the two-view stage's rejected pairs (to say why an image has no edge).

    Returns:
        the component, ``{name: why}`` of the cameras left out, and the saved path.
    """
    vg_all = ViewGraph.load(work / "viewgraph.npz", allow_isolated=True)
    if vg_all.n_edges == 0:
        raise PipelineError(f"no pair of the {vg_all.n_cameras} images has enough geometrically consistent matches; "
                            "the images must overlap (see the warnings above for each pair's reason)")
    sub, info = vg_all.largest_component()
    left_out: dict[str, str] = {}
    if info.dropped_names:
        left_out = _left_out_reasons(vg_all, vg_all.components(), rejected or [])
        logger.warning("the view graph is not connected: using the largest component (%d of %d images); left out: %s",
                       sub.n_cameras, vg_all.n_cameras, "; ".join(f"{n}: {w}" for n, w in left_out.items()))
    path = out / "viewgraph.npz"
    if path.exists():
        try:
            old = ViewGraph.load(path)
            if (old.names == sub.names and np.array_equal(old.edges, sub.edges) and np.array_equal(old.R_rel, sub.R_rel)
                    and (old.H is None) == (sub.H is None) and (sub.H is None or np.array_equal(old.H, sub.H))):
                return old, left_out, path
        except PipelineError:
            pass
    sub.save(path)
    return sub, left_out, path


def _summ(evaluate: Any, names: list[str], R: np.ndarray, ref: Any, align: str, vg: ViewGraph | None = None
          ) -> tuple[dict[str, Any], np.ndarray]:
    R_ref, mask = evaluate.match_reference(names, ref.names, ref.R)
    if not mask.any():
        return {"n_cameras": len(names), "n_evaluated": 0, "note": "no camera in common with the reference"}, \
            np.full(len(names), np.nan)
    use_vg = vg if (vg is not None and vg.H is not None and list(vg.names) == list(names)) else None
    s = evaluate.summarize(R, R_ref, mask, align=align, vg=use_vg)
    errs = evaluate.rotation_errors_deg(R, R_ref, mask, align=align)
    missing = [n for n, m in zip(names, mask) if not m]
    if missing:
        s["not_in_reference"] = missing
    return s, errs


@dataclass
class RefSet:
    name: str
    names: list[str]
    R: np.ndarray
    centers: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)


SUBSET_PREFIX = "truth, pycolmap's"


def truth_on_registered(truth: "RefSet | None", pyc: "RefSet", vg: ViewGraph) -> "RefSet | None":
    """The truth restricted to the images pycolmap registered, when it left out some of ours.

    pycolmap's errors are over the images it registers; ours over every image of the
    view graph. Scoring our methods on pycolmap's images too (aligned on them) is the
    like-for-like comparison; None when pycolmap registered all of ours or there is no truth.
    """
    if truth is None:
        return None
    from pipeline import evaluate  # noqa: PLC0415

    _, in_pyc = evaluate.match_reference(list(vg.names), pyc.names, pyc.R)
    if in_pyc.all():
        return None
    R_t, mask = evaluate.match_reference(list(pyc.names), truth.names, truth.R)
    if mask.sum() < 2:
        return None
    names = [n for n, m in zip(pyc.names, mask) if m]
    return RefSet(f"{SUBSET_PREFIX} {len(names)} images", names, np.asarray(R_t)[mask])


def evaluate_all(vg: ViewGraph, ransac_vg: ViewGraph | None, results: dict[str, dict], refs: list[RefSet],
                 pyc: RefSet | None, align: str) -> tuple[dict, dict, dict]:
    """Stage 8: every method against every reference; the view graph's edges; pycolmap against the truth."""
    from pipeline import evaluate  # noqa: PLC0415
    from pipeline.io.rotations import read_rotations  # noqa: PLC0415

    methods: dict[str, Any] = {}
    cam_errors: dict[str, dict[str, np.ndarray]] = {r.name: {} for r in refs}
    for label, res in results.items():
        names, R = read_rotations(res["rotations"])
        entry: dict[str, Any] = {k: v for k, v in res["stats"].items() if k not in ("history",)}
        if "certified" in entry:
            entry["certificate"] = {k: entry.get(k) for k in ("certified", "rank", "gap", "gap_residual", "lower_bound",
                                                               "primal_cost", "cost_offset", "status", "solver",
                                                               "fallback") if k in entry} | (entry.get("certificate") or {})
        entry["references"] = {}
        for r in refs:
            s, e = _summ(evaluate, list(names), np.asarray(R), r, align, vg)
            entry["references"][r.name] = s
            cam_errors[r.name][label] = e
        if refs:
            entry.update({k: v for k, v in entry["references"][refs[0].name].items()})
            entry["reference"] = refs[0].name
        methods[label] = entry
    edges: dict[str, Any] = {}
    edge_err: dict[str, dict[str, np.ndarray]] = {}
    for r in refs:
        edge_err[r.name] = {}
        for tag, g in (("ransac", ransac_vg), ("ba", vg)):
            if g is None:
                continue
            R_ref, mask = evaluate.match_reference(list(g.names), r.names, r.R)
            if r is refs[0]:
                edges[tag] = {**evaluate.edge_stats(g, R_ref, mask), "reference": r.name}
            edge_err[r.name][tag] = evaluate.edge_errors_deg(g, R_ref, mask)
    pyc_metrics: dict[str, Any] = {}
    if pyc is not None:
        pyc_metrics = {"time_s": pyc.info.get("time_s"), "n_images": pyc.info.get("n_images"),
                       "n_registered": pyc.info.get("n_registered"), "unregistered": pyc.info.get("unregistered", {}),
                       "n_models": pyc.info.get("n_models")}
        truth = [r for r in refs if r.name == "truth"]
        if truth and len(pyc.names):
            s, e = _summ(evaluate, pyc.names, pyc.R, truth[0], align)
            pyc_metrics.update(s)
            cam_errors["truth"]["pycolmap"] = e
    return {"methods": methods, "edges": edges, "pycolmap": pyc_metrics}, cam_errors, edge_err


# ----------------------------------------------------------------------- driver
@dataclass
class RunArgs:
    images: Path | None = None
    out: Path | None = None
    config: Path | None = None
    methods: list[str] | None = None
    gt: Path | None = None
    K: Path | None = None
    reference: bool | None = None
    overwrite: bool = False
    quiet: bool = False


def default_out(images: Path | None) -> Path:
    return Path("out") / ("default" if images is None else (Path(images).resolve().name or "run"))


def check_writable(out: Path) -> None:
    """Fail early, with an actionable message, when OUT cannot be written."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_probe"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise PipelineError(f"cannot write to the output folder {out} ({exc.strerror or exc}); "
                            "choose a writable folder with --out DIR") from None


def main(images: Path | None = None, out: Path | None = None, config: Path | None = None,
         methods: list[str] | None = None, gt: Path | None = None, K: Path | None = None,
         reference: bool | None = None, overwrite: bool = False, quiet: bool = False) -> Path:
    """Run the whole pipeline; returns the path of ``OUT/metrics.json``."""
    from pipeline import features as st_features  # noqa: PLC0415
    from pipeline import matching as st_matching  # noqa: PLC0415
    from pipeline import two_view as st_two_view  # noqa: PLC0415
    from pipeline import two_view_ba as st_ba  # noqa: PLC0415
    from pipeline import reference as st_reference  # noqa: PLC0415
    from pipeline import report as st_report  # noqa: PLC0415

    t_start = time.perf_counter()
    yaml_data = load_yaml(config if config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None))
    allowed = {"run", "features", "matching", "two_view", "two_view_ba", "reference", *registry.sections()}
    unknown = sorted(set(yaml_data) - allowed)
    if unknown:
        raise InputFileError(f"{config}: unknown section(s) {unknown}; allowed sections are {sorted(allowed)}")
    rcfg = stage_config(RunConfig, yaml_data, "run")
    overrides = {"sdp": {"solver": rcfg.sdp_solver}}
    given = parse_methods(methods or rcfg.methods, yaml_data, overrides)  # checked before any work
    out = Path(out) if out is not None else default_out(images)
    check_writable(out)
    progress = not quiet
    runner = StageRunner(quiet)
    notes: list[str] = []

    if images is None:
        from pipeline.synthetic import render  # noqa: PLC0415

        scene = out / "scene"
        if not (scene / "cameras.txt").exists() or overwrite:
            t0 = time.perf_counter()
            render.main(scene, n_views=rcfg.scene_views, seed=rcfg.scene_seed, noise_sigma=rcfg.scene_noise)
            runner.times["render"] = time.perf_counter() - t0
        images = scene
        gt = gt if gt is not None else scene / "cameras.txt"
        notes.append(f"default scene: {rcfg.scene_views} rendered views (seed {rcfg.scene_seed}) in {scene}; "
                     "truth = its cameras.txt")
    images = Path(images)
    if not images.is_dir():
        raise InputFileError(f"image folder {images} does not exist or is not a folder; pass a folder of images")
    truth = None
    if gt is not None:
        from pipeline.io.references import read_reference  # noqa: PLC0415

        truth = read_reference(gt)  # read early: a bad --gt fails before hours of work
    work = out / "work"

    runner("features", "features", lambda: st_features.main(
        images, work, _cfg(st_features, ("FeatureConfig",), yaml_data, "features"), K_path=K, overwrite=overwrite,
        progress=progress), lambda: [work / "features.record.json"])
    fs = st_features.load_features(work)
    n_default = sum(1 for s in fs.K_source if s == "default")
    if n_default:
        notes.append(f"{n_default} image(s) had no K file and no EXIF focal: default focal 1.2·max(w, h) used")
    runner("matching", "matching", lambda: st_matching.main(
        work, _cfg(st_matching, ("MatchingConfig",), yaml_data, "matching"), overwrite=overwrite, progress=progress),
        lambda: [work / "matching.record.json"])
    runner("two_view", "two-view geometry", lambda: st_two_view.main(
        work, _cfg(st_two_view, ("TwoViewConfig",), yaml_data, "two_view"), overwrite=overwrite, progress=progress),
        lambda: sorted(work.glob("two_view-*.npz")))
    runner("two_view_ba", "two-view BA", lambda: st_ba.main(
        work, _cfg(st_ba, ("BAConfig",), yaml_data, "two_view_ba"), overwrite=overwrite, progress=progress),
        lambda: [work / "viewgraph.npz"])
    try:
        tv = st_two_view.load_two_view(work)
        rejected, ransac_vg = list(tv.rejected), tv.vg
    except (PipelineError, OSError, AttributeError):
        rejected, ransac_vg = [], None
    vg, left_out, vg_path = runner("viewgraph", "view graph", lambda: stage_viewgraph(work, out, rejected))
    dropped = list(left_out)
    if dropped:
        notes.append(f"view graph not connected: the largest component ({vg.n_cameras} images) is used; "
                     f"left out: {', '.join(dropped)}")
        notes += [f"left out of the view graph: {n}: {w}" for n, w in left_out.items()]

    specs = list(given)
    if not specs:
        specs, why = registry.default_methods(vg, rcfg, yaml_data, overrides)
        notes += why

    def do_averaging() -> dict[str, dict]:
        res = {}
        from tqdm import tqdm  # noqa: PLC0415

        for spec in tqdm(specs, desc="averaging", unit="method", disable=not progress):
            res[spec.label] = run_averaging(out / "rotations", spec, vg_path, overwrite)
        return res

    results = runner("averaging", "rotation averaging", do_averaging)

    pyc = None
    if rcfg.reference if reference is None else reference:
        rc = _cfg(st_reference, ("ReferenceConfig",), yaml_data, "reference")
        try:
            ref_json = runner("reference", "pycolmap reference", lambda: st_reference.main(
                images, out / "reference", K=K, overwrite=overwrite, config=rc, work=work, names=list(fs.names),
                progress=progress),
                lambda: [out / "reference" / "reference.json"])
            rr = st_reference.load_reference_result(ref_json)
        except (PipelineError, RuntimeError, ValueError, OSError) as exc:
            # the reference only scores our result: its failure must not throw our rotations away
            msg = " ".join(str(exc).split())
            logger.warning("the pycolmap reference failed (%s); continuing without it", msg)
            notes.append(f"pycolmap reference failed: {msg}")
            rr = None
        if rr is not None:
            pyc = RefSet("pycolmap", rr.names, rr.R, info=rr.summary)
            if not rr.names:
                notes.append("pycolmap registered no image")
            for nm, why in rr.summary.get("unregistered", {}).items():
                notes.append(f"pycolmap did not register {nm}: {why}")
    else:
        runner.times["reference"] = 0.0
        runner.k += 1

    truth_ref = None if truth is None else RefSet(
        "truth", list(truth.names), np.asarray(truth.R), None if truth.centers is None else np.asarray(truth.centers))
    refs: list[RefSet] = [truth_ref] if truth_ref is not None else []
    if pyc is not None and len(pyc.names) >= 2:
        sub = truth_on_registered(truth_ref, pyc, vg)
        refs += ([sub] if sub is not None else []) + [pyc]
    metrics, cam_err, edge_err = runner("evaluation", "evaluation", lambda: evaluate_all(
        vg, ransac_vg, results, refs, pyc, rcfg.align))
    if not refs:
        notes.append("no reference: pass --gt REF or enable the pycolmap reference to get errors")

    def do_report() -> Path:
        histories = error_vs_time_curves(vg, specs, results, refs[0], rcfg.align) if refs else {}
        for label, c in histories.items():
            metrics["methods"][label]["error_vs_time"] = c
        table = {r.name: {k: m["references"][r.name] | {kk: m.get(kk) for kk in ("time_s", "certified", "rank", "gap")
                                                            if kk in m}
                          for k, m in metrics["methods"].items()} for r in refs}
        if pyc is not None and "truth" in table and "median_deg" in metrics["pycolmap"]:
            for r in refs:
                if r.name == "truth" or r.name.startswith(SUBSET_PREFIX):
                    table[r.name]["pycolmap (incremental)"] = metrics["pycolmap"]
        edge_vals: dict[str, np.ndarray] = {}
        if refs and refs[0].name in edge_err and "ba" in edge_err[refs[0].name]:
            edge_vals[f"error_vs_{refs[0].name}"] = edge_err[refs[0].name]["ba"]
        if vg.inliers is not None:
            edge_vals["inliers"] = np.asarray(vg.inliers, float)
        pos = None
        if refs and refs[0].centers is not None:
            pos = _rows_by_name(list(vg.names), refs[0].names, np.asarray(refs[0].centers))
        data = st_report.ReportData(
            metrics=table, camera_errors=cam_err, edge_errors=edge_err, histories=histories,
            vg_edges=vg.edges, vg_names=list(vg.names), edge_values=edge_vals if rcfg.plots else {}, positions=pos,
            notes=notes, stages={k + (" (reused)" if runner.reused.get(k) else ""): v for k, v in runner.times.items()},
            title=f"Rotations of {images}")
        if not rcfg.plots:
            data.camera_errors, data.edge_errors, data.histories, data.vg_edges = {}, {}, {}, None
        return st_report.write_report(out, data)

    runner("report", "report", do_report)
    metrics["stages"] = dict(runner.times)
    metrics["stages_reused"] = dict(runner.reused)
    metrics["total_s"] = time.perf_counter() - t_start
    metrics["our_path_s"] = sum(runner.times.get(k, 0.0) for k in
                                ("features", "matching", "two_view", "two_view_ba", "viewgraph", "averaging"))
    metrics["input"] = {"images": str(images), "n_images": len(fs.names), "n_cameras_graph": vg.n_cameras,
                        "n_edges": vg.n_edges, "left_out": dropped,
                        "left_out_why": left_out, "gt": None if gt is None else str(gt),
                        "K": None if K is None else str(K), "config": dataclasses.asdict(rcfg)}
    metrics["notes"] = notes
    path = write_json(out / "metrics.json", metrics)
    if not quiet:
        print(summary_table(metrics, refs), flush=True)
        print(f"report: {out / 'report.md'}\nmetrics: {path}", flush=True)
    return path


def _rows_by_name(names: list[str], ref_names: list[str], arr: np.ndarray) -> np.ndarray | None:
    """Rows of ``arr`` (one per ``ref_names``) for ``names``, matched by name then stem; None if any is missing."""
    by = {n: k for k, n in enumerate(ref_names)}
    by_stem = {Path(n).stem: k for k, n in enumerate(ref_names)}
    idx = [by.get(n, by_stem.get(Path(n).stem)) for n in names]
    if any(i is None for i in idx):
        return None
    return arr[np.array(idx, dtype=int)]


def summary_table(metrics: dict, refs: list[RefSet]) -> str:
    """The final console table: one row per method and reference."""
    rows = [("method", "reference", "cams", "median°", "mean°", "max°", "time s", "note")]
    for label, m in metrics["methods"].items():
        note = ""
        if "certified" in m:
            note = "certified" if m["certified"] else "NOT certified"
        for rname, s in m.get("references", {}).items():
            rows.append((label, rname, f"{s.get('n_evaluated', 0)}", _f(s.get("median_deg")), _f(s.get("mean_deg")),
                         _f(s.get("max_deg")), _f(m.get("time_s"), 2), note))
        if not m.get("references"):
            rows.append((label, "–", str(m.get("n_cameras", "")), "–", "–", "–", _f(m.get("time_s"), 2), note))
    p = metrics.get("pycolmap") or {}
    if "median_deg" in p:
        rows.append(("pycolmap", "truth", f"{p.get('n_evaluated', 0)}", _f(p.get("median_deg")), _f(p.get("mean_deg")),
                     _f(p.get("max_deg")), _f(p.get("time_s"), 2), f"{p.get('n_registered')}/{p.get('n_images')} reg."))
    w = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w[k]) for k, c in enumerate(r)) for r in rows]
    lines.insert(1, "  ".join("-" * x for x in w))
    return "\n".join(lines)


def _f(v: Any, nd: int = 3) -> str:
    try:
        return f"{float(v):.{nd}f}"
    except (TypeError, ValueError):
        return "–"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="run.py", description="Rotation averaging from images, evaluated and reported. "
                                "With no IMAGE_DIR, runs on a rendered default scene.")
    p.add_argument("images", nargs="?", type=Path, default=None, help="folder of images (default: render a scene)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: out/<folder name>)")
    p.add_argument("--config", type=Path, default=None, help="YAML config (default: configs/default.yaml)")
    p.add_argument("--methods", nargs="+", default=None, metavar="M",
                   help=f"averaging methods: {registry.tokens_help()}; put IMAGE_DIR first or separate methods "
                        "by commas")
    p.add_argument("--gt", type=Path, default=None, help="true cameras (cameras file, gt_dense_cameras/, *_par.txt, "
                   "COLMAP model, rotations file)")
    p.add_argument("--K", type=Path, default=None, help="intrinsics: K.txt (3×3) or a per-image cameras file")
    p.add_argument("--no-reference", action="store_true", help="skip the pycolmap reference")
    p.add_argument("--overwrite", action="store_true", help="redo every stage")
    return p


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli  # noqa: PLC0415

    def body(a: argparse.Namespace) -> int:
        main(a.images, a.out, a.config, a.methods, a.gt, a.K, False if a.no_reference else None, a.overwrite, a.quiet)
        return 0

    return run_cli(body, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main_cli())
