"""A pycolmap reconstruction of an image folder as a peer to compare with: what every mapper shares.

The incremental reference (:mod:`pipeline.reference.incremental`) and the global one
(:mod:`pipeline.reference.global_mapping`, GLOMAP) are :class:`PeerStage` subclasses
that differ only in their mapping call. Everything else is here, done the same way
for both:

- **images**: every header is checked first (:func:`pipeline.frontend.images.check_headers`);
  an image pycolmap cannot safely decode is left out with a warning and listed, with
  why, among the unregistered images;
- **K**: intrinsics the pipeline knows (``--K``, or the file the feature stage finds in
  the image folder) are read by the one K resolver and passed as fixed PINHOLE
  cameras (:func:`known_intrinsics`); otherwise pycolmap uses EXIF or its default
  focal and refines it;
- **database**: pycolmap's SIFT + exhaustive matching (or our matches), built once
  under a key of the images, K and database options
  (:mod:`pipeline.reference.database`). Peers given the same ``database_dir`` share it:
  it is read, never written, by the mappers;
- **models, result files, summary, timing**: :mod:`pipeline.reference.models`; the
  time is extraction + matching (from the database's timings) + mapping.

pycolmap's OpenMP runtime busy-waits on idle threads, which inflates times 15-60× on
a shared 2-core machine, so ``OMP_WAIT_POLICY=PASSIVE`` is set before pycolmap is
first imported.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Sequence

import numpy as np

from pipeline.core.atomic import remove_stale_temporaries
from pipeline.core.config import option
from pipeline.core.errors import CacheError, InputFileError, PipelineError
from pipeline.reference import models as rm
from pipeline.reference.database import DatabaseConfig, build_database, ensure_database, remove_database, \
    tidy_databases
from pipeline.stage import Stage, StageRecord, fingerprint_of

logger = logging.getLogger(__name__)

__all__ = ["PeerConfig", "PeerStage", "known_intrinsics", "pycolmap_module", "run_peer", "peer_cli"]


@dataclass(frozen=True, kw_only=True)
class PeerConfig(DatabaseConfig):
    """Options every pycolmap peer has: its database's, and the mapping's common ones."""

    seed: int = option(0, "random seed of the mapper (reproducible model selection)", ge=0)
    min_model_size: int = option(3, "smallest model pycolmap keeps", ge=2)
    refine_known_intrinsics: bool = option(False, "let bundle adjustment refine a K we passed")


def pycolmap_module() -> Any:
    """pycolmap, imported with ``OMP_WAIT_POLICY=PASSIVE`` and glog quiet unless debugging."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import pycolmap  # noqa: PLC0415  (lazy: heavy import, and the env var must be set first)

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


class PeerStage(Stage[PeerConfig]):
    """A pycolmap reconstruction of an image folder (subclasses implement :meth:`map`).

    Args:
        folder: output folder ``OUT``.
        config: options.
        images: image folder.
        names: image file names to use (default: every image in the folder).
        K: known intrinsics (see :func:`known_intrinsics`), or None.
        work: our front end's WORK folder (only for ``use_our_matches``).
        progress: show progress bars.
        database_dir: where the COLMAP database is kept (default ``folder``); peers given
            the same one share a database built with the same options.
    """

    #: What the summary and messages call the mapping ("incremental mapping", ...).
    mapping: ClassVar[str]

    def __init__(self, folder: Path, config: PeerConfig | None = None, *, images: Path,
                 names: list[str] | None = None, K: str | os.PathLike | np.ndarray | None = None,
                 work: Path | None = None, progress: bool = True, database_dir: Path | None = None) -> None:
        super().__init__(folder, config)
        self.images = Path(images)
        self.names = None if names is None else list(names)
        self.K = K
        self.work = None if work is None else Path(work)
        self.progress = progress
        self.database_dir = self.folder if database_dir is None else Path(database_dir)
        self._scan: dict[str, Any] | None = None

    def map(self, pc: Any, db_path: Path, out: Path) -> dict[int, Any]:
        """pycolmap's mapping of the database into folder ``out``: its models by index."""
        raise NotImplementedError

    def scan(self) -> dict[str, Any]:
        """List the images, check their headers and resolve K (no decoding); done once."""
        if self._scan is not None:
            return self._scan
        from pipeline.frontend.images import check_headers, ends_crc, list_images  # noqa: PLC0415
        from pipeline.frontend.intrinsics import find_intrinsics_file  # noqa: PLC0415

        if self.config.use_our_matches and self.work is None:
            raise PipelineError("use_our_matches=True needs the WORK folder of our front end (work=...)")
        names = self.names if self.names is not None else list_images(self.images)[0]
        if len(names) < 2:
            raise InputFileError(f"{self.images} has {len(names)} image(s); a reconstruction needs at least 2")
        sizes, bad = check_headers(self.images, names, say_orientation=False)  # our features stage said it
        for n, why in bad.items():
            logger.warning("%s: leaving out %s: it %s", self.title, self.images / n, why)
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
            sigs.append([n, int(st.st_size), int(st.st_mtime_ns), ends_crc(self.images / n)])
        self._scan = {"names": list(names), "given": given, "bad": bad, "Ks": Ks, "sigs": sigs}
        return self._scan

    def inputs(self) -> dict[str, str]:
        s = self.scan()
        out = {"images": fingerprint_of(str(self.images.resolve()), s["sigs"], s["names"], sorted(s["bad"].items())),
               "K": fingerprint_of(None if s["Ks"] is None else s["Ks"].tolist())}
        if self.config.use_our_matches:
            for up in ("features", "matching"):
                out[up] = self.upstream(up, self.work).fingerprint
            out["verification"] = "2"  # 2: every matched pair, with no pairs file (names with spaces kept their pairs)
        return out

    def _keys(self, inputs: dict[str, str]) -> tuple[str, str]:
        """Keys of the database (images, K, upstream, database options) and of the models (+ mapping options)."""
        db_key = fingerprint_of("database", sorted(inputs.items()), self.config.database_options())
        return db_key[:12], fingerprint_of(db_key, self.config.result_dict())[:12]

    def common_options(self, opts: Any) -> Any:
        """Set the options every pycolmap pipeline has (threads, seed, model size, several models) on ``opts``."""
        opts.num_threads = self.config.num_threads
        opts.random_seed = self.config.seed
        opts.min_model_size = self.config.min_model_size
        opts.multiple_models = True
        return opts

    def fixed_intrinsics(self) -> bool:
        """Whether bundle adjustment keeps the cameras' K constant (a K was passed and not to be refined)."""
        return self.scan()["Ks"] is not None and not self.config.refine_known_intrinsics

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        pc = pycolmap_module()
        s, cfg = self.scan(), self.config
        db_key, models_key = self._keys(self.inputs())
        db_path = self.database_dir / f"database-{db_key}.db"
        models_dir = self.folder / f"models-{models_key}"
        if self.overwrite:
            shutil.rmtree(models_dir, ignore_errors=True)
        logger.info("pycolmap: %s %d images", "importing our matches for" if cfg.use_our_matches else
                    "extracting and matching", len(s["given"]))
        times = ensure_database(db_path, s["given"], lambda tmp: build_database(
            pc, tmp, self.images, s["given"], s["Ks"], cfg, self.work, self.progress),
            overwrite=self.overwrite and self.database_dir == self.folder)
        times = {k: v for k, v in times.items() if k in ("extract_s", "match_s")}
        recs = None
        if models_dir.is_dir():
            try:
                recs, times["map_s"] = rm.load_models(pc, models_dir)
            except CacheError as exc:
                logger.warning("%s; mapping again", exc)
                shutil.rmtree(models_dir, ignore_errors=True)
        if recs is None:
            logger.info("pycolmap: %s", self.mapping)
            rm.write_models(models_dir, lambda tmp: self.map(pc, db_path, tmp))
            recs, times["map_s"] = rm.load_models(pc, models_dir)
        summary, rec, R = rm.summarize_models(pc, recs, db_path, s["names"], s["given"], s["bad"], self.mapping)
        times["total_s"] = float(sum(times.values()))
        summary = {"config": cfg.as_dict(), "known_K": s["Ks"] is not None, **summary, "time_s": times["total_s"],
                   "times": times, "pycolmap": pc.__version__, "mapping": self.mapping}
        files = rm.write_result(self.folder, summary, rec, R, header=f"pycolmap {pc.__version__} {self.mapping}, "
                                "largest model, cam_from_world")
        self._remove_other_keys(db_path, models_dir)
        logger.info("%s: %d/%d images registered in %.1f s (%d model(s))", self.title, summary["n_registered"],
                    len(s["names"]), summary["time_s"], summary["n_models"])
        return files, {k: summary[k] for k in ("n_images", "n_registered", "n_models", "time_s")}

    def _remove_other_keys(self, db_path: Path, models_dir: Path) -> None:
        """Databases and models of other images or options: a finished run keeps only its own.

        A shared database folder belongs to the peer that owns it: its databases are left alone.
        """
        if self.database_dir == self.folder:
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


def run_peer(stage_cls: type[PeerStage], images: str | os.PathLike, out: str | os.PathLike,
             K: str | os.PathLike | np.ndarray | None = None, overwrite: bool = False, config: PeerConfig | None = None,
             work: str | os.PathLike | None = None, names: list[str] | None = None, progress: bool = True,
             database_dir: str | os.PathLike | None = None) -> Path:
    """Reconstruct ``images`` with the peer ``stage_cls`` into ``out`` (resumable); returns ``out/reference.json``."""
    images = Path(images)
    if not images.is_dir():
        raise InputFileError(f"image folder {images} does not exist or is not a folder; pass --images DIR")
    stage_cls(Path(out), config, images=images, names=names, K=K, work=None if work is None else Path(work),
              progress=progress, database_dir=None if database_dir is None else Path(database_dir)).run(overwrite)
    return Path(out) / rm.SUMMARY


def peer_cli(stage_cls: type[PeerStage], prog: str, description: str, argv: Sequence[str] | None = None) -> int:
    """``python -m <prog> --images DIR --out OUT [--K FILE] [--config YAML] [options] [--overwrite]``."""
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    cfg_cls: Any = stage_cls.config_cls
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--images", required=True, type=Path, help="folder of images")
    parser.add_argument("--out", required=True, type=Path, help="output folder (resumable cache)")
    parser.add_argument("--K", type=Path, default=None, help="K.txt (3×3) or per-image cameras file")
    parser.add_argument("--config", type=Path, default=None, help=f"YAML config; its [{cfg_cls.SECTION}] section is used")
    parser.add_argument("--our-matches", type=Path, default=None, metavar="WORK",
                        help="reuse our keypoints and matches from this WORK folder (sets --use-our-matches)")
    parser.add_argument("--database-dir", type=Path, default=None,
                        help="folder of the COLMAP database, shared with another peer (default: OUT)")
    parser.add_argument("--overwrite", action="store_true", help="redo everything")
    add_config_args(parser, cfg_cls)

    def body(a: argparse.Namespace) -> int:
        cfg = config_from_args(cfg_cls, a, a.config, use_our_matches=True if a.our_matches else None)
        p = run_peer(stage_cls, a.images, a.out, K=a.K, overwrite=a.overwrite, config=cfg, work=a.our_matches,
                     progress=not a.quiet, database_dir=a.database_dir)
        s = rm.read_summary(p.parent)
        print(f"registered {s['n_registered']}/{s['n_images']} images in {s['time_s']:.1f} s "
              f"({s['n_models']} model(s)); rotations: {a.out / rm.ROTATIONS}")
        for nm, why in s["unregistered"].items():
            print(f"  not registered: {nm}: {why}")
        return 0

    return run_cli(body, parser, argv)
