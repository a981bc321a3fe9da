"""A pycolmap incremental reconstruction of an image folder, used as a reference (a stage).

The reference answers "how far are our rotations from what a standard
incremental SfM gives on the same images". By default it runs pycolmap's own
SIFT extraction and exhaustive matching, so it does not depend on our front
end; ``use_our_matches`` instead imports our keypoints and matches from the
WORK folder of :mod:`pipeline.frontend.feature_stage` /
:mod:`pipeline.frontend.matching_stage` into the COLMAP database and lets pycolmap
verify and map them.

Every image header is checked first (:func:`pipeline.frontend.images.check_headers`):
an image pycolmap cannot safely decode (a PNG whose header claims 60000×60000
pixels would make it abort) is left out with a warning and listed, with why,
among the unregistered images.

Intrinsics the pipeline knows (``--K``: a ``K.txt``, a per-image cameras file,
a Middlebury ``*_par.txt``, a reference folder with K; or, without ``--K``, the
file the feature stage finds in the image folder) are read by the one K
resolver (:mod:`pipeline.frontend.intrinsics`) and passed to pycolmap as fixed
PINHOLE cameras; otherwise pycolmap uses EXIF or its default focal
(1.2·max(w, h)) and refines it.

Output folder layout (``OUT`` = the stage's folder)::

    OUT/database-<key>.db          COLMAP database (features + verified matches),
    OUT/database-<key>.times.json  reused while the images, K and database options
                                   are unchanged
    OUT/models-<key>/<k>/          every model pycolmap returned (COLMAP binary)
    OUT/model/, OUT/rotations.txt, OUT/reference.json   the result (pipeline.reference.models)
    OUT/reference.record.json      the stage record (pipeline.stage)

An interrupted run resumes from the last finished step (database, then
mapping); its temporaries carry :data:`pipeline.core.atomic.TMP_TAG` and the next
run removes them, and entries of other keys are removed when a run finishes.

pycolmap's OpenMP runtime busy-waits on idle threads, which inflates times
15-60× on a shared 2-core machine, so ``OMP_WAIT_POLICY=PASSIVE`` is set
before pycolmap is first imported.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.atomic import remove_stale_temporaries
from pipeline.core.config import option
from pipeline.core.errors import CacheError, InputFileError, PipelineError
from pipeline.reference import models as rm
from pipeline.reference.database import (DatabaseConfig, build_database, ensure_database, remove_database,
                                         tidy_databases)
from pipeline.stage import Stage, StageRecord, fingerprint_of

logger = logging.getLogger(__name__)

__all__ = ["ReferenceConfig", "IncrementalReferenceStage", "known_intrinsics", "main", "main_cli"]


@dataclass(frozen=True, kw_only=True)
class ReferenceConfig(DatabaseConfig):
    """Options of the pycolmap incremental reference (YAML section ``reference``)."""

    SECTION = "reference"

    seed: int = option(0, "random seed of the mapper (reproducible model selection)", ge=0)
    min_model_size: int = option(3, "smallest model pycolmap keeps", ge=2)
    refine_known_intrinsics: bool = option(False, "let bundle adjustment refine a K we passed")


def _pycolmap() -> Any:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import pycolmap  # noqa: PLC0415  (lazy: heavy import, and the env var must be set first)

    # glog INFO lines of every mapping step drown the pipeline's own log unless debugging
    pycolmap.logging.minloglevel = 0 if logger.isEnabledFor(logging.DEBUG) else 1
    return pycolmap


def known_intrinsics(K: str | os.PathLike | np.ndarray | None, names: list[str]) -> np.ndarray | None:
    """(N, 3, 3) intrinsics of ``names`` from the one K resolver, or None when ``K`` is None.

    Args:
        K: None; a file or folder that :func:`pipeline.frontend.intrinsics.read_intrinsics`
            reads (``K.txt``, a per-image cameras file, a Middlebury ``*_par.txt``, a
            reference folder with K); or a (3, 3) or (N, 3, 3) array in the order of ``names``.
        names: image file names.
    Raises:
        InputFileError: an unreadable source, a bad K, or an image without K.
    """
    from pipeline.frontend.intrinsics import check_K, intrinsics_for_names, read_intrinsics  # noqa: PLC0415

    if K is None:
        return None
    n = len(names)
    if isinstance(K, np.ndarray):
        arr = np.asarray(K, dtype=float)
        if arr.shape not in ((3, 3), (n, 3, 3)):
            raise InputFileError(f"K.shape={arr.shape} but expected (3, 3) or ({n}, 3, 3)")
        out = np.broadcast_to(arr, (n, 3, 3)).copy()
        for k in range(n):
            check_K(out[k], f"K of {names[k]}")
        return out
    out, found = intrinsics_for_names(read_intrinsics(K), names, K)
    if not found.all():
        missing = [nm for nm, f in zip(names, found) if not f]
        raise InputFileError(f"{K} has no intrinsics for {missing[:5]}{'...' if len(missing) > 5 else ''}; "
                             "give a K for every image, or none")
    return out


class IncrementalReferenceStage(Stage[ReferenceConfig]):
    """pycolmap's incremental reconstruction of an image folder, as a reference.

    Args:
        folder: output folder ``OUT``.
        config: options.
        images: image folder.
        names: image file names to use (default: every image in the folder).
        K: known intrinsics (see :func:`known_intrinsics`), or None.
        work: our front end's WORK folder (only for ``use_our_matches``).
        progress: show progress bars.
    """

    name = "reference"
    title = "pycolmap reference"
    config_cls = ReferenceConfig

    def __init__(self, folder: Path, config: ReferenceConfig | None = None, *, images: Path,
                 names: list[str] | None = None, K: str | os.PathLike | np.ndarray | None = None,
                 work: Path | None = None, progress: bool = True) -> None:
        super().__init__(folder, config)
        self.images = Path(images)
        self.names = None if names is None else list(names)
        self.K = K
        self.work = None if work is None else Path(work)
        self.progress = progress
        self._scan: dict[str, Any] | None = None

    def scan(self) -> dict[str, Any]:
        """List the images, check their headers and resolve K (no decoding); done once."""
        if self._scan is not None:
            return self._scan
        from pipeline.frontend.images import check_headers, list_images  # noqa: PLC0415
        from pipeline.frontend.intrinsics import find_intrinsics_file  # noqa: PLC0415

        if self.config.use_our_matches and self.work is None:
            raise PipelineError("use_our_matches=True needs the WORK folder of our front end (work=...)")
        names = self.names if self.names is not None else list_images(self.images)[0]
        if len(names) < 2:
            raise InputFileError(f"{self.images} has {len(names)} image(s); a reconstruction needs at least 2")
        sizes, bad = check_headers(self.images, names)
        for n, why in bad.items():
            logger.warning("pycolmap reference: leaving out %s: it %s", self.images / n, why)
        given = [n for n in names if n in sizes]
        if len(given) < 2:
            raise InputFileError(f"only {len(given)} of the {len(names)} images in {self.images} can be given to "
                                 "pycolmap; a reconstruction needs at least 2")
        K = self.K
        if K is None and self.config.find_K_in_folder:
            K = find_intrinsics_file(self.images)  # the same file our feature stage picks up
        Ks = known_intrinsics(K, given)
        sigs = []
        for n in given:
            st = (self.images / n).stat()
            sigs.append([n, int(st.st_size), int(st.st_mtime_ns)])
        self._scan = {"names": list(names), "given": given, "bad": bad, "Ks": Ks, "sigs": sigs}
        return self._scan

    def inputs(self) -> dict[str, str]:
        s = self.scan()
        out = {"images": fingerprint_of(str(self.images.resolve()), s["sigs"], s["names"], sorted(s["bad"].items())),
               "K": fingerprint_of(None if s["Ks"] is None else s["Ks"].tolist())}
        if self.config.use_our_matches:
            for up in ("features", "matching"):
                out[up] = self.upstream(up, self.work).fingerprint
        return out

    def _keys(self, inputs: dict[str, str]) -> tuple[str, str]:
        """Keys of the database (images, K, upstream, database options) and of the models (+ mapping options)."""
        db_key = fingerprint_of("database", sorted(inputs.items()), self.config.database_options())
        return db_key[:12], fingerprint_of(db_key, self.config.result_dict())[:12]

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        pc = _pycolmap()
        s, cfg = self.scan(), self.config
        db_key, models_key = self._keys(self.inputs())
        db_path = self.folder / f"database-{db_key}.db"
        models_dir = self.folder / f"models-{models_key}"
        if self.overwrite:
            shutil.rmtree(models_dir, ignore_errors=True)
        logger.info("pycolmap: %s %d images", "importing our matches for" if cfg.use_our_matches else
                    "extracting and matching", len(s["given"]))
        times = ensure_database(db_path, s["given"], lambda tmp: build_database(
            pc, tmp, self.images, s["given"], s["Ks"], cfg, self.work, self.progress), overwrite=self.overwrite)
        times = {k: v for k, v in times.items() if k in ("extract_s", "match_s")}
        recs = None
        if models_dir.is_dir():
            try:
                recs, times["map_s"] = rm.load_models(pc, models_dir)
            except CacheError as exc:
                logger.warning("%s; mapping again", exc)
                shutil.rmtree(models_dir, ignore_errors=True)
        if recs is None:
            logger.info("pycolmap: incremental mapping")
            rm.write_models(models_dir, lambda tmp: self._map(pc, db_path, tmp))
            recs, times["map_s"] = rm.load_models(pc, models_dir)
        summary, rec, R = rm.summarize_models(pc, recs, db_path, s["names"], s["given"], s["bad"])
        times["total_s"] = float(sum(times.values()))
        summary = {"config": cfg.as_dict(), "known_K": s["Ks"] is not None, **summary, "time_s": times["total_s"],
                   "times": times, "pycolmap": pc.__version__}
        files = rm.write_result(self.folder, summary, rec, R, header=f"pycolmap {pc.__version__} incremental "
                                "reconstruction, largest model, cam_from_world")
        self._remove_other_keys(db_path, models_dir)
        logger.info("pycolmap reference: %d/%d images registered in %.1f s (%d model(s))", summary["n_registered"],
                    len(s["names"]), summary["time_s"], summary["n_models"])
        return files, {k: summary[k] for k in ("n_images", "n_registered", "n_models", "time_s")}

    def _map(self, pc: Any, db_path: Path, out: Path) -> dict[int, Any]:
        """pycolmap's incremental mapping of the database into folder ``out``."""
        from tqdm import tqdm  # noqa: PLC0415

        cfg = self.config
        opts = pc.IncrementalPipelineOptions()
        opts.num_threads = cfg.num_threads
        opts.random_seed = cfg.seed
        opts.min_model_size = cfg.min_model_size
        opts.multiple_models = True
        if self.scan()["Ks"] is not None and not cfg.refine_known_intrinsics:
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
        with tqdm(total=len(self.scan()["given"]), desc="pycolmap mapping", unit="img",
                  disable=not self.progress) as bar:
            # the callback fires once per registered image (the first pair counts as two)
            return pc.incremental_mapping(db_path, self.images, out, options=opts,
                                          initial_image_pair_callback=lambda: bar.update(2),
                                          next_image_callback=lambda: bar.update(1))

    def _remove_other_keys(self, db_path: Path, models_dir: Path) -> None:
        """Databases and models of other images or options: a finished run keeps only its own."""
        for p in self.folder.glob("database-*.db"):
            if p != db_path:
                remove_database(p)
        for p in self.folder.glob("models-*"):
            if p != models_dir and p.is_dir():
                shutil.rmtree(p, ignore_errors=True)

    def verify(self, record: StageRecord) -> None:
        rm.verify_result(self.folder)

    def run(self, overwrite: bool = False) -> StageRecord:
        """As :meth:`Stage.run`; what a killed run left is removed even when the result is reused."""
        remove_stale_temporaries(self.folder)
        if self.folder.is_dir():
            tidy_databases(self.folder)
            # the untagged temporaries of earlier versions
            for p in [*self.folder.glob(".models-*"), *self.folder.glob(".model.*"), *self.folder.glob(".times-*.json")]:
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
        return super().run(overwrite)


def main(images: str | os.PathLike, out: str | os.PathLike, K: str | os.PathLike | np.ndarray | None = None,
         overwrite: bool = False, config: ReferenceConfig | None = None, work: str | os.PathLike | None = None,
         names: list[str] | None = None, progress: bool = True) -> Path:
    """Reconstruct ``images`` with pycolmap into ``out`` (resumable); returns ``out/reference.json``.

    Args:
        images: folder of images.
        out: output folder (created).
        K: known intrinsics (see :func:`known_intrinsics`), or None.
        overwrite: redo everything.
        config: options; defaults to ``ReferenceConfig()``.
        work: our front end's WORK folder (only for ``use_our_matches``).
        names: image file names to use (default: every image in the folder).
        progress: show progress bars.
    """
    images = Path(images)
    if not images.is_dir():
        raise InputFileError(f"image folder {images} does not exist or is not a folder; pass --images DIR")
    IncrementalReferenceStage(Path(out), config, images=images, names=names, K=K,
                              work=None if work is None else Path(work), progress=progress).run(overwrite)
    return Path(out) / rm.SUMMARY


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    parser = argparse.ArgumentParser(prog="python -m pipeline.reference",
                                     description="pycolmap incremental reconstruction of an image folder (a reference)")
    parser.add_argument("--images", required=True, type=Path, help="folder of images")
    parser.add_argument("--out", required=True, type=Path, help="output folder (resumable cache)")
    parser.add_argument("--K", type=Path, default=None, help="K.txt (3×3) or per-image cameras file")
    parser.add_argument("--config", type=Path, default=None, help="YAML config; its [reference] section is used")
    parser.add_argument("--our-matches", type=Path, default=None, metavar="WORK",
                        help="reuse our keypoints and matches from this WORK folder (sets --use-our-matches)")
    parser.add_argument("--overwrite", action="store_true", help="redo everything")
    add_config_args(parser, ReferenceConfig)

    def body(a: argparse.Namespace) -> int:
        cfg = config_from_args(ReferenceConfig, a, a.config, use_our_matches=True if a.our_matches else None)
        p = main(a.images, a.out, K=a.K, overwrite=a.overwrite, config=cfg, work=a.our_matches, progress=not a.quiet)
        s = rm.read_summary(p.parent)
        print(f"registered {s['n_registered']}/{s['n_images']} images in {s['time_s']:.1f} s "
              f"({s['n_models']} model(s)); rotations: {a.out / rm.ROTATIONS}")
        for nm, why in s["unregistered"].items():
            print(f"  not registered: {nm}: {why}")
        return 0

    return run_cli(body, parser, argv)

