"""Everything ``run.py`` checks before the first stage runs: the whole config, the methods, ``--K``, ``--gt``,
the output folder, and every image's name and header.

:func:`prepare` reads and validates all of it (each section of the YAML file into
its typed config, so an unknown key, a wrong type or a bad value fails here), then
lists the images, checks their headers and resolves and checks their intrinsics
without decoding a pixel. A bad input costs a second, not the front end.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pipeline.averaging import registry
from pipeline.averaging.registry import MethodSpec, parse_methods
from pipeline.core.config import Config, check_sections, load_yaml, option, stage_config
from pipeline.core.errors import InputFileError, PipelineError
from pipeline.core.names import match_names
from pipeline.evaluation.compare import EvaluationConfig
from pipeline.frontend.feature_stage import FeaturesStage
from pipeline.frontend.features import FeatureConfig
from pipeline.frontend.matching import MatchingConfig
from pipeline.frontend.pairs import parse_selector
from pipeline.geometry.ba_solver import BAConfig
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.graph.stage import ViewGraphConfig
from pipeline.reference.incremental import ReferenceConfig
from pipeline.reference.types import Reference

logger = logging.getLogger(__name__)

__all__ = ["RunConfig", "Plan", "prepare", "STAGE_CONFIGS", "DEFAULT_CONFIG", "default_out"]

# configs/ sits beside the package in a checkout; without it the dataclass defaults apply
DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


@dataclass(frozen=True, kw_only=True)
class RunConfig(Config):
    """Options of run.py itself (YAML section ``run``)."""

    SECTION = "run"

    methods: tuple[str, ...] = option((), "averaging methods; empty: the registry's defaults for the view graph")
    sdp_max_n: int = option(60, "largest view graph (cameras) on which SDP-cSO(3) runs by default", ge=0)
    sdp_solver: Literal["scs", "clarabel"] = option("scs", "conic solver of the SDP")
    reference: bool = option(True, "run the pycolmap reference")
    align: Literal["l2", "l1"] = option("l2", "global alignment of the evaluation")
    scene_views: int = option(8, "views of the default rendered scene (no IMAGE_DIR)", ge=2)
    scene_seed: int = option(0, "seed of the default rendered scene", ge=0)
    scene_noise: float = option(0.0, "pixel noise (0-255 scale) of the default rendered scene", ge=0)
    plots: bool = option(True, "write the PNG plots of the report")


STAGE_CONFIGS: dict[str, type[Config]] = {
    c.SECTION: c for c in (RunConfig, FeatureConfig, MatchingConfig, TwoViewConfig, BAConfig, ViewGraphConfig,
                           ReferenceConfig, EvaluationConfig)}


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
    reference: bool
    overwrite: bool
    quiet: bool
    features: FeaturesStage
    notes: list[str] = field(default_factory=list)
    times: dict[str, float] = field(default_factory=dict)

    @property
    def work(self) -> Path:
        return self.out / "work"

    @property
    def progress(self) -> bool:
        return not self.quiet

    def config(self, section: str, **runtime: Any) -> Any:
        """The typed config of ``section``, with runtime options (progress) applied where it has them."""
        cfg = self.configs[section]
        have = {f for f in type(cfg).__dataclass_fields__}
        return cfg.replace(**{k: v for k, v in runtime.items() if k in have})


def default_out(images: Path | None) -> Path:
    return Path("out") / ("default" if images is None else (Path(images).resolve().name or "run"))


def _check_writable(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise PipelineError(f"the output folder {out} is a file; choose a folder with --out DIR")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_probe"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise PipelineError(f"cannot write to the output folder {out} ({exc.strerror or exc}); "
                            "choose a writable folder with --out DIR") from None


def _check_truth(truth: Reference, gt: Path, names: list[str]) -> None:
    idx = match_names(names, list(truth.names), what=f"--gt {gt}")  # an ambiguous stem is an error here
    if (idx >= 0).sum() < 2:
        raise InputFileError(f"--gt {gt} names none or one of the {len(names)} images (e.g. {names[:3]}; it has "
                             f"{list(truth.names)[:3]}); pass the true cameras of these images")


def prepare(images: Path | None = None, out: Path | None = None, config: Path | None = None,
            methods: list[str] | None = None, gt: Path | None = None, K: Path | None = None,
            reference: bool | None = None, overwrite: bool = False, quiet: bool = False) -> Plan:
    """Check every input and build every config; render the default scene when ``images`` is None."""
    yaml_data = load_yaml(config if config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.exists() else None))
    check_sections(yaml_data, [*STAGE_CONFIGS, *registry.sections()], config or "config")
    configs = {s: stage_config(c, yaml_data, s) for s, c in STAGE_CONFIGS.items()}
    run_cfg: RunConfig = configs["run"]  # type: ignore[assignment]
    parse_selector(configs["matching"].pairs)  # type: ignore[attr-defined]  # a bad matching.pairs fails here
    overrides = {"sdp": {"solver": run_cfg.sdp_solver}}
    given = parse_methods(methods or run_cfg.methods, yaml_data, overrides)
    out = Path(out) if out is not None else default_out(images)
    _check_writable(out)
    notes: list[str] = []
    times: dict[str, float] = {}
    if images is None:
        from pipeline.synthetic import render  # noqa: PLC0415

        scene = out / "scene"
        if not (scene / "cameras.txt").exists() or overwrite:
            t0 = time.perf_counter()
            render.main(scene, n_views=run_cfg.scene_views, seed=run_cfg.scene_seed, noise_sigma=run_cfg.scene_noise)
            times["render"] = time.perf_counter() - t0
        images, gt = scene, gt if gt is not None else scene / "cameras.txt"
        notes.append(f"default scene: {run_cfg.scene_views} rendered views (seed {run_cfg.scene_seed}) in {scene}; "
                     "truth = its cameras.txt")
    images = Path(images)
    if not images.is_dir():
        raise InputFileError(f"image folder {images} does not exist or is not a folder; pass a folder of images")
    features = FeaturesStage(out / "work", configs["features"], images=images, K_path=K, progress=not quiet)
    scan = features.scan()  # names, headers and K, checked without decoding a pixel
    truth = None
    if gt is not None:
        from pipeline.reference.truth import read_reference  # noqa: PLC0415

        truth = read_reference(gt)
        _check_truth(truth, Path(gt), scan["names"])
        truth = truth.replace(label="truth")
    n_default = sum(1 for s in scan["sources"] if s == "default")
    if n_default:
        notes.append(f"{n_default} image(s) had no K file and no EXIF focal: default focal 1.2·max(w, h) used")
    notes += [f"image {n} left out: it {why}" for n, why in scan["bad"].items()]
    return Plan(images=images, out=out, K=None if K is None else Path(K), gt=None if gt is None else Path(gt),
                truth=truth, run=run_cfg, configs=configs, yaml=yaml_data, methods=list(given), overrides=overrides,
                reference=run_cfg.reference if reference is None else reference, overwrite=overwrite, quiet=quiet,
                features=features, notes=notes, times=times)
