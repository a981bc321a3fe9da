"""The COLMAP database of a pycolmap reference: its options, building, progress polling and reading.

Shared by every reconstruction peer that starts from a COLMAP database
(:mod:`pipeline.reference.incremental` today; ``pycolmap.global_mapping`` can use the
same database and helpers). The database is built by pycolmap's own SIFT
extraction and exhaustive matching, or from our keypoints and matches
(``use_our_matches``), under a temporary name carrying
:data:`pipeline.core.atomic.TMP_TAG`; its WAL is checkpointed before it is renamed
into place, so an interrupted build leaves only tagged entries (the database and
its ``-wal``/``-shm``) that the next run removes.

pycolmap's feature extraction and matching have no progress callback:
:class:`DatabaseProgress` polls the database they write, lock-free.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from pipeline.core.atomic import atomic_path, write_json
from pipeline.core.config import Config, option
from pipeline.core.errors import CacheError, ConfigError, PipelineError

logger = logging.getLogger(__name__)

__all__ = ["DatabaseConfig", "DatabaseProgress", "COLMAP_PIXEL_OFFSET", "pinhole_params", "build_database",
           "ensure_database", "check_database", "remove_database", "tidy_databases", "verified_degree",
           "split_pair_id"]

# Our K files and keypoints put pixel centres at integer coordinates (OpenCV); COLMAP puts
# them at +0.5 (the image's top-left corner is (0, 0)), so principal points and keypoints
# are shifted by half a pixel on the way in.
COLMAP_PIXEL_OFFSET = 0.5
CAMERA_MODELS = Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                        "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV", "THIN_PRISM_FISHEYE",
                        "RAD_TAN_THIN_PRISM_FISHEYE", "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE",
                        "EUCM", "EQUIRECTANGULAR"]  # COLMAP's camera models (pycolmap.CameraModelId)


@dataclass(frozen=True, kw_only=True)
class DatabaseConfig(Config):
    """Options of the COLMAP database a pycolmap reference maps from (YAML section ``reference``)."""

    SECTION = "reference"

    max_image_size: int = option(1600, "longest side at which pycolmap extracts SIFT (keypoints are scaled "
                                       "back to full resolution); -1 for full size", ge=-1)
    max_num_features: int = option(8192, "SIFT features per image", ge=1)
    use_our_matches: bool = option(False, "import our keypoints and matches (from WORK) instead of running "
                                          "pycolmap's extraction and matching")
    num_threads: int = option(-1, "threads for pycolmap (-1: all cores)", ge=-1, runtime=True)
    camera_model: CAMERA_MODELS = option("SIMPLE_RADIAL", "pycolmap camera model when no K is known")
    find_K_in_folder: bool = option(True, "without an explicit K, use the K.txt / cameras.txt / *_par.txt "
                                          "in the image folder, as the feature stage does")
    verification_seed: int = option(0, "random seed of pycolmap's two-view verification (RANSAC), so that a database "
                                       "built again verifies the same inliers; -1: from the clock (COLMAP's default: "
                                       "two builds of castle's internet imitation differed on 17 of 34 pairs). The "
                                       "mapping can still differ between builds: the extraction's threads may number "
                                       "the images in another order", ge=-1)

    def check(self) -> None:
        if self.max_image_size == 0:
            raise ConfigError(f"[{self.SECTION}] max_image_size=0 but expected a positive size or -1 (full size)")
        if self.num_threads == 0:
            raise ConfigError(f"[{self.SECTION}] num_threads=0 but expected a positive count or -1 (all cores)")

    def database_options(self) -> dict[str, Any]:
        """The result-affecting options of the database (those of this class)."""
        own = {f for f in DatabaseConfig.__dataclass_fields__}
        return {k: v for k, v in self.result_dict().items() if k in own}


def pinhole_params(K: np.ndarray) -> list[float]:
    """COLMAP PINHOLE parameters ``fx, fy, cx, cy`` of our (3, 3) K (pixel centres shifted by +0.5)."""
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + COLMAP_PIXEL_OFFSET, float(K[1, 2]) + COLMAP_PIXEL_OFFSET]


class DatabaseProgress:
    """A progress bar for a pycolmap call that has no callback, fed by polling its database.

    pycolmap's feature extraction and exhaustive matching write one row per image
    (``keypoints``) or per pair (``matches``) as they go; a daemon thread counts the
    rows of ``table`` through a lock-free (``immutable``) read-only SQLite connection
    every ``period`` seconds, so it never blocks the writer. A half-written or
    not-yet-created database just skips that poll; the bar never touches the
    database's content.
    """

    def __init__(self, db_path: Path, table: str, total: int, desc: str, enabled: bool, period: float = 0.5):
        from tqdm import tqdm  # noqa: PLC0415

        self.db_path, self.table, self.period = Path(db_path), table, period
        self.bar = tqdm(total=total, desc=desc, unit="img" if table == "keypoints" else "pair", disable=not enabled)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True) if enabled else None

    def count(self) -> int | None:
        if not self.db_path.exists():
            return None
        try:
            # immutable=1: no locks at all, so COLMAP's writer is never blocked by this reader (a
            # plain read-only connection takes SHARED locks, and a writer that finds the database
            # busy drops the image: seen as "could not read the image"). The price is that a read
            # can see a half-written page; it then raises and this poll is skipped.
            con = sqlite3.connect(f"file:{self.db_path}?mode=ro&immutable=1", uri=True, timeout=0.0)
            try:
                return int(con.execute(f"SELECT COUNT(*) FROM {self.table}").fetchone()[0])
            finally:
                con.close()
        except sqlite3.Error:
            return None

    def _update(self) -> None:
        n = self.count()
        if n is not None and n > self.bar.n:
            self.bar.update(min(n, self.bar.total or n) - self.bar.n)

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self._update()

    def __enter__(self) -> "DatabaseProgress":
        if self._thread is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            if exc[0] is None:
                self._update()
        self.bar.close()


def build_database(pc: Any, db_path: Path, images: Path, names: list[str], Ks: np.ndarray | None,
                   cfg: DatabaseConfig, work: Path | None, progress: bool = False) -> dict[str, float]:
    """Extract + match (or import ours) into a fresh database at ``db_path``; returns timings."""
    reader = pc.ImageReaderOptions()
    same_K = Ks is not None and np.allclose(Ks, Ks[0])
    if Ks is not None:
        reader.camera_model = "PINHOLE"
        if same_K:
            reader.camera_params = ",".join(f"{v:.10g}" for v in pinhole_params(Ks[0]))
        mode = pc.CameraMode.SINGLE if same_K else pc.CameraMode.PER_IMAGE
    else:
        reader.camera_model = cfg.camera_model
        mode = pc.CameraMode.AUTO
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    if cfg.use_our_matches:
        if work is None:
            raise PipelineError("use_our_matches=True needs the WORK folder of our front end (work=...)")
        _import_our_matches(pc, db_path, images, names, reader, mode, work)
        times["extract_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        # every matched pair, with no pairs file: its 'NAME1 NAME2' lines cannot hold a name with a space
        pc.geometric_verification(str(db_path), two_view_geometry_options=_verification(pc, cfg))
        times["match_s"] = time.perf_counter() - t1
    else:
        ext = pc.FeatureExtractionOptions()
        ext.max_image_size = cfg.max_image_size
        ext.num_threads = cfg.num_threads
        ext.sift.max_num_features = cfg.max_num_features
        with DatabaseProgress(db_path, "keypoints", len(names), "pycolmap features", progress):
            pc.extract_features(db_path, images, image_names=names, camera_mode=mode, reader_options=reader,
                                extraction_options=ext, device=pc.Device.cpu)
        times["extract_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        mopt = pc.FeatureMatchingOptions()
        mopt.num_threads = cfg.num_threads
        n_pairs = len(names) * (len(names) - 1) // 2
        with DatabaseProgress(db_path, "matches", n_pairs, "pycolmap matching", progress):
            pc.match_exhaustive(db_path, matching_options=mopt, verification_options=_verification(pc, cfg),
                                device=pc.Device.cpu)
        times["match_s"] = time.perf_counter() - t1
    if Ks is not None and not same_K:
        # PER_IMAGE cameras were created from the reader defaults: set each one to its known K
        db = pc.Database.open(db_path)
        try:
            for img in db.read_all_images():
                cam = db.read_camera(img.camera_id)
                cam.params = pinhole_params(Ks[names.index(img.name)])
                db.update_camera(cam)
        finally:
            db.close()
    return times


def _verification(pc: Any, cfg: DatabaseConfig) -> Any:
    """pycolmap's two-view verification options, seeded (``verification_seed``)."""
    opts = pc.TwoViewGeometryOptions()
    opts.ransac.random_seed = int(cfg.verification_seed)
    return opts


def _import_our_matches(pc: Any, db_path: Path, images: Path, names: list[str], reader: Any, mode: Any,
                        work: Path) -> None:
    """Write our keypoints and putative matches into a COLMAP database."""
    from pipeline.frontend.feature_stage import load_features  # noqa: PLC0415
    from pipeline.frontend.matching_stage import load_matches  # noqa: PLC0415

    fs = load_features(work, descriptors=False)
    if list(fs.names) != list(names):
        raise PipelineError(f"the features in {work} are of other images ({len(fs.names)} vs {len(names)}); "
                            "re-run the features stage on this folder")
    md = load_matches(work)
    pc.Database.open(db_path).close()  # import_images needs an existing database file
    pc.import_images(db_path, images, camera_mode=mode, image_names=names, options=reader)
    db = pc.Database.open(db_path)
    try:
        ids = {img.name: img.image_id for img in db.read_all_images()}
        for k, nm in enumerate(fs.names):
            kp = np.asarray(fs.keypoints[k], dtype=np.float32)[:, :2] + np.float32(COLMAP_PIXEL_OFFSET)
            db.write_keypoints(ids[nm], np.ascontiguousarray(kp))
        for (i, j), m in zip(np.asarray(md.pairs).tolist(), md.matches):
            db.write_matches(ids[fs.names[i]], ids[fs.names[j]], np.ascontiguousarray(np.asarray(m, dtype=np.uint32)))
    finally:
        db.close()


def split_pair_id(pid: int) -> tuple[int, int]:
    """COLMAP's image ids of a pair id: ``pair_id = 2147483647 · id1 + id2`` with ``id1 < id2``."""
    k = 2147483647
    return int(pid // k), int(pid % k)


def verified_degree(pc: Any, db_path: Path) -> tuple[dict[str, int], dict[str, int]]:
    """Per image name: number of verified pairs, and number of keypoints."""
    db = pc.Database.open(db_path)
    try:
        imgs = db.read_all_images()
        names = {img.image_id: img.name for img in imgs}
        n_kp = {img.name: int(db.num_keypoints_for_image(img.image_id)) if db.exists_keypoints(img.image_id) else 0
                for img in imgs}
        pair_ids, geoms = db.read_two_view_geometries()
    finally:
        db.close()
    deg = {nm: 0 for nm in names.values()}
    for pid, g in zip(pair_ids, geoms):
        if len(g.inlier_matches) == 0:
            continue
        a, b = split_pair_id(int(pid))
        for x in (a, b):
            if x in names:
                deg[names[x]] += 1
    return deg, n_kp


# --------------------------------------------------------------------- on disk
def _siblings(db_path: Path) -> list[Path]:
    return [db_path.with_name(db_path.name + s) for s in ("-wal", "-shm", "-journal")]


def _checkpoint(db_path: Path) -> None:
    """Fold the write-ahead log into the database file (SQLite removes ``-wal``/``-shm`` on the last close)."""
    con = sqlite3.connect(str(db_path))
    try:
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    finally:
        con.close()


def check_database(db_path: Path, names: list[str]) -> None:
    """:class:`CacheError` unless ``db_path`` is an intact COLMAP database of (a subset of) ``names``."""
    try:
        con = sqlite3.connect(str(db_path))
        try:
            if con.execute("PRAGMA quick_check").fetchone()[0] != "ok":
                raise sqlite3.DatabaseError("quick_check failed")
            in_db = [r[0] for r in con.execute("SELECT name FROM images")]
            con.execute("SELECT COUNT(*) FROM keypoints").fetchone()
            con.execute("SELECT COUNT(*) FROM two_view_geometries").fetchone()
        finally:
            con.close()
    except sqlite3.Error as exc:
        raise CacheError(f"the database {db_path} is damaged ({exc})") from None
    other = sorted(set(in_db) - set(names))
    if other or not in_db:
        raise CacheError(f"the database {db_path} holds other images ({other[:3] or 'none of ours'})")


def tidy_databases(folder: Path) -> None:
    """Fold the ``-wal``/``-shm`` files a killed pycolmap left beside a finished database into it; remove orphans."""
    for p in folder.glob("database-*.db-*"):
        db = p.with_name(p.name.rsplit("-", 1)[0])
        if not db.is_file():
            p.unlink(missing_ok=True)
        elif p.exists():
            with contextlib.suppress(sqlite3.Error):
                _checkpoint(db)  # SQLite removes the side files when its last connection closes


def remove_database(db_path: Path) -> None:
    """Remove a database with its timings and its SQLite side files."""
    for p in [db_path, db_path.with_suffix(".times.json"), *_siblings(db_path)]:
        p.unlink(missing_ok=True)


def _read_times(path: Path) -> dict[str, float]:
    """The timings beside a database; :class:`CacheError` if they are missing or damaged."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        times = {str(k): float(v) for k, v in d.items()}
        if not times or not all(t >= 0 for t in times.values()):
            raise ValueError("no timings")
        return times
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        raise CacheError(f"the timings of the pycolmap database, {path}, are missing or damaged "
                         f"({' '.join(str(exc).split())[:60]})") from None


def ensure_database(db_path: Path, names: list[str], build: Callable[[Path], dict[str, float]],
                    overwrite: bool = False) -> dict[str, float]:
    """The timings of the database at ``db_path``, built by ``build(tmp_path)`` unless an intact one is there.

    The database is built under a tagged temporary name and renamed into place
    once complete, with its timings in ``<db>.times.json``; a damaged one is
    rebuilt with a warning.
    """
    times_path = db_path.with_suffix(".times.json")
    if db_path.exists() and not overwrite:
        try:
            check_database(db_path, names)
            times = _read_times(times_path)  # the peers' timings back the speed comparisons: never guessed
            logger.info("pycolmap: reusing database %s", db_path)
            return times
        except CacheError as exc:
            logger.warning("%s; building it again", exc)
    remove_database(db_path)
    with atomic_path(db_path) as tmp:
        tmp.unlink()  # pycolmap creates the database itself
        try:
            times = build(tmp)
            _checkpoint(tmp)
        except BaseException:
            for p in _siblings(tmp):
                p.unlink(missing_ok=True)
            raise
        write_json(times_path, times)
    return times
