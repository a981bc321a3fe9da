"""Everything ``run.py`` checks before the first stage runs: the whole config, the methods, ``--K``, ``--gt``,
the output folder, and every image's name and header.

:func:`prepare` reads and validates all of it (each section of the YAML file into
its typed config, so an unknown key, a wrong type or a bad value fails here), then
lists the images, checks their headers and resolves and checks their intrinsics
without decoding a pixel. A bad input costs a second, not the front end.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Literal

from pipeline.averaging import registry
from pipeline.averaging.registry import MethodSpec, parse_methods
from pipeline.core.atomic import TMP_TAG, write_json
from pipeline.core.config import Config, check_sections, load_yaml, option, stage_config
from pipeline.core.errors import ConfigError, InputFileError, PipelineError
from pipeline.core.names import match_names
from pipeline.evaluation.compare import EvaluationConfig
from pipeline.frontend.camera_estimate import CamerasConfig
from pipeline.frontend.feature_stage import FeaturesStage
from pipeline.frontend.features import FeatureConfig
from pipeline.frontend.loop_stage import LoopClosureConfig
from pipeline.frontend.matching import MatchingConfig
from pipeline.frontend.pairs import parse_selector, select_pairs
from pipeline.geometry.ba_solver import BAConfig
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.graph.stage import ViewGraphConfig
from pipeline.reference.global_mapping import GlobalReferenceConfig
from pipeline.reference.incremental import ReferenceConfig
from pipeline.reference.types import Reference
from pipeline.refine.refine import RefineConfig
from pipeline.stage import output_digest

logger = logging.getLogger(__name__)

__all__ = ["RunConfig", "Plan", "prepare", "load_configs", "STAGE_CONFIGS", "DEFAULT_CONFIG", "default_out",
           "PER_ITEM"]

# configs/ sits beside the package in a checkout; without it the dataclass defaults apply
DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


@dataclass(frozen=True, kw_only=True)
class RunConfig(Config):
    """Options of run.py itself (YAML section ``run``)."""

    SECTION = "run"

    methods: tuple[str, ...] = option((), "averaging methods; empty: the registry's defaults for the view graph")
    sdp_max_n: int = option(60, "largest view graph (cameras) on which SDP-cSO(3) runs by default", ge=0)
    sdp_solver: Literal["scs", "clarabel"] = option("scs", "conic solver of the SDP")
    reference: bool = option(True, "run the pycolmap references (incremental; GLOMAP too with global_reference)")
    refine: bool = option(True, "refine the recommended (or refine.start) method's rotations with pycolmap")
    second_opinion: bool = option(True, "where one averaging method ran and no refined row came of it, also run "
                                  "IRLS-l0.5 (colmap-ra when that is the method) so that the methods' disagreement "
                                  "can flag the cameras where either errs")
    global_reference: bool = option(True, "run pycolmap's global SfM (GLOMAP) beside the incremental reference")
    align: Literal["l2", "l1"] = option("l2", "global alignment of the evaluation")
    scene_views: int = option(8, "views of the default rendered scene (no IMAGE_DIR)", ge=2)
    scene_seed: int = option(0, "seed of the default rendered scene", ge=0)
    scene_noise: float = option(0.0, "pixel noise (0-255 scale) of the default rendered scene", ge=0)
    plots: bool = option(True, "write the PNG plots of the report")


PER_ITEM = ("features", "matching", "two_view", "two_view_ba")  # the sections whose work runs on an executor
STAGE_CONFIGS: dict[str, type[Config]] = {
    c.SECTION: c for c in (RunConfig, FeatureConfig, MatchingConfig, CamerasConfig, TwoViewConfig, BAConfig,
                           LoopClosureConfig, ViewGraphConfig, ReferenceConfig, GlobalReferenceConfig, RefineConfig,
                           EvaluationConfig)}


@dataclass
class Plan:
    """A checked run: its folders, inputs and every typed config."""

    images: Path
    out: Path
    K: Path | None
    gt: Path | None
    truth: Reference | None
    run: RunConfig
    configs: dict[str, Config]
    yaml: dict[str, Any]
    methods: list[MethodSpec]
    overrides: dict[str, dict[str, Any]]
    overwrite: bool
    quiet: bool
    features: FeaturesStage
    notes: list[str] = field(default_factory=list)
    times: dict[str, float] = field(default_factory=dict)
    database: Path | None = None
    work_dir: Path | None = None  # the front end's folder when it is not OUT/work (another component's run)
    components: list[dict[str, Any]] = field(default_factory=list)  # the other components solved, for metrics.json
    skipped: dict[str, str] = field(default_factory=dict)  # the steps the run leaves out: {step: why, in a few words}

    @property
    def work(self) -> Path:
        return self.work_dir if self.work_dir is not None else self.out / "work"

    def for_component(self, folder: Path, k: int) -> "Plan":
        """The plan of the k-th component's run in ``folder``: the same inputs, configs and front end (this run's
        WORK), its own outputs; the pycolmap peers are not run again (they ran once on every image, in OUT)."""
        peers = {s: self.skipped.get(s, "ran once, on every image, above") for s in ("reference", "global_reference")}
        return dataclasses.replace(self, out=Path(folder), work_dir=self.work, skipped={**self.skipped, **peers}, notes=[
            f"component {k} of the view graph: no pair links its images to the largest component's (in the run's "
            f"own folder), so its rotations are in a frame of their own"], times={}, components=[])

    @property
    def progress(self) -> bool:
        return not self.quiet

    @contextlib.contextmanager
    def executors(self) -> Iterator[None]:
        """One local Dask cluster for every per-item stage set to ``executor: dask`` without a scheduler.

        The stages reach it by its address (as ``--scheduler`` would), through one client shared by the
        stages (:func:`pipeline.core.dask_executor.client_session`); the cluster is closed, its workers
        gone, when the block ends, also on Ctrl-C.
        """
        dask = [s for s in PER_ITEM if self.configs[s].executor == "dask" or self.configs[s].scheduler]
        if not dask:
            yield
            return
        from pipeline.core.dask_executor import client_session, local_cluster  # noqa: PLC0415

        want = [s for s in dask if not self.configs[s].scheduler]
        saved = {s: self.configs[s] for s in want}
        with contextlib.ExitStack() as stack:
            if want:
                cluster = stack.enter_context(local_cluster(max(self.configs[s].workers for s in want)))
                logger.info("Dask: a local cluster of %d worker(s) at %s", cluster.workers, cluster.address)
                self.configs.update({s: self.configs[s].replace(scheduler=cluster.address) for s in want})
                self.features.config = self.configs["features"]
            stack.enter_context(client_session())  # closed before the cluster
            try:
                yield
            finally:
                self.configs.update(saved)
                self.features.config = self.configs["features"]

    def note_features(self, manifest: dict[str, Any]) -> None:
        """Notes from the features stage: each image it left out (those it could not decode, too), and
        the images whose detection was changed for low texture (lowered threshold, simulated viewpoints)."""
        notes = [f"image {d['name']} left out: it {d['reason']}" for d in manifest.get("skipped", [])]
        lowered = manifest.get("lowered") or {}
        affine = [n for n, r in lowered.items() if r.get("affine")]

        def some(names: list[str]) -> str:
            return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")

        if lowered:
            notes.append(f"low texture: the contrast threshold was lowered for {len(lowered)} of "
                         f"{len(manifest.get('names', []))} images ({some(list(lowered))})")
        if affine:
            notes.append(f"texture-starved: {len(affine)} image(s) detected over simulated viewpoints (ASIFT): "
                         f"{some(affine)}; expect fewer, less certain pairs there")
        self.notes.extend(n for n in notes if n not in self.notes)

    def config(self, section: str, **runtime: Any) -> Any:
        """The typed config of ``section``, with runtime options (progress) applied where it has them."""
        cfg = self.configs[section]
        have = {f for f in type(cfg).__dataclass_fields__}
        return cfg.replace(**{k: v for k, v in runtime.items() if k in have})


def default_out(images: Path | None) -> Path:
    return Path("out") / ("default" if images is None else (Path(images).resolve().name or "run"))


def _check_writable(out: Path) -> None:
    """The output folder can be written; a check that leaves nothing behind (folders it made are removed)."""
    if out.exists() and not out.is_dir():
        raise PipelineError(f"the output folder {out} is a file; choose a folder with --out DIR")
    made = [p for p in [out, *out.parents] if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-probe{TMP_TAG}{os.getpid()}"  # tagged: a later run removes it if we are killed
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise PipelineError(f"cannot write to the output folder {out} ({exc.strerror or exc}); "
                            "choose a writable folder with --out DIR") from None
    finally:
        for p in made:  # innermost first; the run creates the folder when it starts
            with contextlib.suppress(OSError):
                p.rmdir()


def _check_truth(truth: Reference, gt: Path, names: list[str]) -> None:
    # an ambiguous stem is an error here, and so are two images that match one true camera
    idx = match_names(names, list(truth.names), what=f"--gt {gt}", unique=True)
    if (idx >= 0).sum() < 2:
        raise InputFileError(f"--gt {gt} names none or one of the {len(names)} images (e.g. {names[:3]}; it has "
                             f"{list(truth.names)[:3]}); pass the true cameras of these images")


def _executor_configs(configs: dict[str, Config], executor: str | None, scheduler: str | None) -> None:
    """Apply ``--executor``/``--scheduler`` to the per-item sections; check every scheduler address up front."""
    for s in PER_ITEM:
        configs[s] = configs[s].replace(executor=executor, scheduler=scheduler)
    dask = [configs[s] for s in PER_ITEM if configs[s].backend("auto") == "dask"]  # type: ignore[attr-defined]
    if dask:
        from pipeline.core import dask_executor  # noqa: PLC0415 - imports dask only when asked for

        dask_executor.require_distributed()
        for address in sorted({c.scheduler for c in dask if c.scheduler}):  # type: ignore[attr-defined]
            dask_executor.check_scheduler(address)


def load_configs(config: Path | None = None, methods: list[str] | None = None
                 ) -> tuple[dict[str, Any], dict[str, Config], list[MethodSpec], dict[str, dict[str, Any]]]:
    """Read the YAML config (default ``configs/default.yaml``) and build every typed config and method spec.

    Returns:
        The YAML data, ``{section: config}``, the method specs of ``methods`` (or of
        ``run.methods``; empty: the registry's defaults apply) and the overrides that
        the ``run`` section gives the methods.
    Raises:
        PipelineError: one line naming the file, section and key of the first problem.
    """
    path = config if config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None)
    yaml_data = load_yaml(path)
    try:
        check_sections(yaml_data, [*STAGE_CONFIGS, *registry.sections()], path or "config")
        configs = {s: stage_config(c, yaml_data, s) for s, c in STAGE_CONFIGS.items()}
        configs["global_reference"] = GlobalReferenceConfig.sharing_database(configs["reference"],  # one database
                                                                             yaml_data.get("global_reference"))
        run_cfg: RunConfig = configs["run"]  # type: ignore[assignment]
        overrides = {"sdp": {"solver": run_cfg.sdp_solver}}
        return yaml_data, configs, parse_methods(methods or run_cfg.methods, yaml_data, overrides), overrides
    except ConfigError as exc:  # a "[section] key=value" message, or run.methods, comes from the file: name it
        msg = str(exc)
        if path is not None and msg.startswith("["):
            msg = f"{msg} (in {path})"
        elif path is not None and not methods and msg.startswith("unknown method"):
            msg = f"[run] methods: {msg} (in {path})"
        raise ConfigError(msg) from None


#: What the default scene was rendered with, and each file's CRC-32: a scene of other settings, or one damaged, is
#: rendered again (the features stage would skip a damaged view and solve the others).
SCENE_RECORD = "scene.json"


def _scene_intact(scene: Path, spec: dict[str, Any]) -> bool:
    """Whether ``scene`` holds the default scene of ``spec``, every file as it was written, and no other view."""
    import json  # noqa: PLC0415

    try:
        rec = json.loads((scene / SCENE_RECORD).read_text())
        crc = dict(rec.pop("crc32"))
        views = {p.name for p in scene.glob("view_*.png")}
        return rec == spec and views == set(crc) - {"cameras.txt"} and all(
            output_digest(scene / n) == c for n, c in crc.items())
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False


def _clear_scene(scene: Path) -> None:
    """Remove the files of an earlier default scene (its views, cameras and record; nothing else)."""
    for p in [*scene.glob("view_*.png"), scene / "cameras.txt", scene / "points3d.txt", scene / SCENE_RECORD]:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def prepare(images: Path | None = None, out: Path | None = None, config: Path | None = None,
            methods: list[str] | None = None, gt: Path | None = None, K: Path | None = None,
            reference: bool | None = None, overwrite: bool = False, quiet: bool = False,
            database: Path | None = None, executor: str | None = None, scheduler: str | None = None) -> Plan:
    """Check every input and build every config; render the default scene when ``images`` is None.

    ``database``: a COLMAP database whose cameras, keypoints and verified matches replace our
    features and matching (``images`` is then the folder it was made from).
    ``executor``, ``scheduler``: where the per-item stages run (overriding their sections).
    """
    yaml_data, configs, given, overrides = load_configs(config, methods)
    _executor_configs(configs, executor, scheduler)
    if database is not None and images is None:
        raise PipelineError("--database DB needs the image folder it was made from (run.py --database DB IMAGE_DIR)")
    if database is not None and K is not None:
        raise PipelineError("--database DB takes the intrinsics from the database's cameras: drop --K")
    run_cfg: RunConfig = configs["run"]  # type: ignore[assignment]
    parse_selector(configs["matching"].pairs)  # type: ignore[attr-defined]  # a bad matching.pairs fails here
    out = Path(out) if out is not None else default_out(images)
    _check_writable(out)
    notes: list[str] = []
    times: dict[str, float] = {}
    if images is None:
        from pipeline.synthetic import render  # noqa: PLC0415

        scene = out / "scene"
        spec = {"views": run_cfg.scene_views, "seed": run_cfg.scene_seed, "noise": run_cfg.scene_noise}
        if overwrite or not _scene_intact(scene, spec):
            t0 = time.perf_counter()
            _clear_scene(scene)
            render.main(scene, n_views=run_cfg.scene_views, seed=run_cfg.scene_seed, noise_sigma=run_cfg.scene_noise)
            files = sorted(p.name for p in scene.glob("view_*.png")) + ["cameras.txt"]
            write_json(scene / SCENE_RECORD, {**spec, "crc32": {n: output_digest(scene / n) for n in files}})
            times["render"] = time.perf_counter() - t0
        images, gt = scene, gt if gt is not None else scene / "cameras.txt"
        notes.append(f"default scene: {run_cfg.scene_views} rendered views (seed {run_cfg.scene_seed}) in {scene}; "
                     "truth = its cameras.txt")
    images = Path(images)
    if not images.is_dir():
        raise InputFileError(f"image folder {images} does not exist or is not a folder; pass a folder of images")
    if out.resolve() == images.resolve():
        raise InputFileError(f"--out {out} is the image folder: the run's plots would be read as photos by the next "
                             f"run; pass another output folder (the default is {default_out(images)})")
    if database is not None:
        from pipeline.frontend.database_stage import DatabaseFeaturesStage  # noqa: PLC0415

        features: FeaturesStage = DatabaseFeaturesStage(out / "work", configs["features"], images=images,
                                                        database=Path(database), progress=not quiet)
        notes.append(f"features and verified matches from the COLMAP database {database}")
    else:
        features = FeaturesStage(out / "work", configs["features"], images=images, K_path=K, progress=not quiet)
    scan = features.scan()  # names, headers and K, checked without decoding a pixel
    kind, arg = parse_selector(configs["matching"].pairs)  # type: ignore[attr-defined]
    if kind == "file" or (kind == "database" and arg is not None):  # a pairs file's or database's names
        select_pairs(configs["matching"].pairs, scan["names"])  # type: ignore[attr-defined]
    truth = None
    if gt is not None:
        from pipeline.reference.truth import read_reference  # noqa: PLC0415

        truth = read_reference(gt)
        _check_truth(truth, Path(gt), scan["names"])
        truth = truth.replace(label="truth")
    n_default = sum(1 for s in scan["sources"] if s == "default")
    n_exif = sum(1 for s in scan["sources"] if s == "exif")
    estimate = configs["cameras"].estimate_focal  # type: ignore[attr-defined]
    if n_default:
        notes.append(f"{n_default} image(s) had no K file and no EXIF focal: " + (
            "their focal length is to be estimated from the view graph (cameras stage)" if estimate else
            "default focal 1.2·max(w, h) used (cameras.estimate_focal is off)"))
    if n_exif:
        notes.append(f"{n_exif} image(s) have an EXIF focal and no K file: " + (
            "EXIF is a prior; the focal length is estimated from the view graph near it" if estimate else
            "the EXIF focal is used as it is (cameras.estimate_focal is off)"))
    notes += [f"image {n} left out: it {why}" for n, why in scan["bad"].items()]
    return Plan(images=images, out=out, K=None if K is None else Path(K), gt=None if gt is None else Path(gt),
                truth=truth, run=run_cfg, configs=configs, yaml=yaml_data, methods=list(given), overrides=overrides,
                overwrite=overwrite, quiet=quiet, features=features, notes=notes, times=times,
                database=None if database is None else Path(database), skipped=_skipped(run_cfg, reference))


def _skipped(run_cfg: RunConfig, reference: bool | None) -> dict[str, str]:
    """The optional steps a run leaves out (the refinement, the pycolmap peers), each with the flag or config key
    that leaves it out; ``reference``: False for ``--no-reference``, True to run the peers, None: ``run.reference``."""
    out = {} if run_cfg.refine else {"refine": "run.refine: false"}
    if reference is False or (reference is None and not run_cfg.reference):
        why = "--no-reference" if reference is False else "run.reference: false"
        return {**out, "reference": why, "global_reference": why}
    return out if run_cfg.global_reference else {**out, "global_reference": "run.global_reference: false"}
