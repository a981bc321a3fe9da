"""A pycolmap incremental reconstruction of an image folder, used as a reference.

The reference answers "how far are our rotations from what a standard
incremental SfM gives on the same images". By default it runs pycolmap's own
SIFT extraction and exhaustive matching, so it does not depend on our front
end; ``use_our_matches=True`` instead imports our keypoints and matches from
the WORK folder of :mod:`pipeline.frontend.features` / :mod:`pipeline.frontend.matching` into the
COLMAP database and lets pycolmap verify and map them.

Intrinsics the pipeline knows (a ``K.txt`` with one 3×3 matrix, or any
per-image reference file that :func:`pipeline.io.references.read_reference`
reads with K, e.g. a rendered cameras file or a Middlebury ``*_par.txt``) are
passed to pycolmap as fixed PINHOLE cameras; otherwise pycolmap uses EXIF or
its default focal (1.2·max(w, h)) and refines it.

Output folder layout (``OUT`` = the ``out`` argument)::

    OUT/database-<hash>.db     COLMAP database (features + verified matches)
    OUT/models-<hash>/<k>/     every model pycolmap returned (COLMAP binary)
    OUT/model/                 the largest model (COLMAP binary), readable by
                               read_reference as a "COLMAP model folder"
    OUT/rotations.txt          cam_from_world of every registered image, by name
    OUT/reference.json         summary: registered / unregistered names (with why),
                               the models and the images each one leaves out,
                               timings, configuration

A second call with the same configuration and images returns at once; an
interrupted call resumes from the last finished step (database, then mapping).

pycolmap's OpenMP runtime busy-waits on idle threads, which inflates times
15-60× on a shared 2-core machine, so ``OMP_WAIT_POLICY=PASSIVE`` is set
before pycolmap is first imported (it has no effect if it was imported
already with another policy).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline.core.atomic import atomic_path, write_json
from pipeline.core.config import config_hash
from pipeline.core.errors import InputFileError, PipelineError
from pipeline.io.rotations import read_rotations, write_rotations

logger = logging.getLogger(__name__)

@dataclass(frozen=True, kw_only=True)
class ReferenceConfig:
    """Options of the pycolmap reference reconstruction.

    Attributes:
        max_image_size: longest side at which pycolmap extracts SIFT (keypoints
            are scaled back to full resolution); -1 for full size.
        max_num_features: SIFT features per image.
        use_our_matches: import our keypoints and matches (from ``work``)
            instead of running pycolmap's extraction and matching.
        num_threads: threads for pycolmap (-1: all cores).
        seed: random seed of the mapper (reproducible model selection).
        min_model_size: smallest model pycolmap keeps.
        refine_known_intrinsics: let bundle adjustment refine a K we passed.
        camera_model: pycolmap camera model when no K is known.
        find_K_in_folder: without an explicit K, use the ``K.txt`` /
            ``cameras.txt`` / ``*_par.txt`` in the image folder, as the feature
            stage does.
    """

    max_image_size: int = 1600
    max_num_features: int = 8192
    use_our_matches: bool = False
    num_threads: int = -1
    seed: int = 0
    min_model_size: int = 3
    refine_known_intrinsics: bool = False
    camera_model: str = "SIMPLE_RADIAL"
    find_K_in_folder: bool = True


@dataclass
class ReferenceResult:
    """A loaded reference reconstruction.

    Attributes:
        names: registered image names of the largest model.
        R: (n, 3, 3) cam_from_world rotations of ``names``.
        summary: the content of ``reference.json``.
    """

    names: list[str]
    R: np.ndarray
    summary: dict[str, Any]


def _pycolmap():
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import pycolmap  # noqa: PLC0415  (lazy: heavy import, and the env var must be set first)

    return pycolmap


def list_images(images: Path) -> list[str]:
    """Sorted image file names in ``images`` (the front end's listing, so both see the same images)."""
    from pipeline.frontend.images import list_images as _list  # noqa: PLC0415

    return _list(images)[0]


def load_known_K(K: str | os.PathLike | np.ndarray | None, names: list[str]) -> np.ndarray | None:
    """Intrinsics per image, from a K file, a per-image cameras file, a reference folder or an array.

    Args:
        K: None; a ``K.txt`` path (one 3×3 for every image); a per-image file that
            :func:`pipeline.frontend.intrinsics.parse_intrinsics_file` reads (rendered cameras
            file, Middlebury ``*_par.txt``); a folder that
            :func:`pipeline.io.references.read_reference` reads with K (Strecha
            ``gt_dense_cameras/``); a (3,3) or (N,3,3) array in the order of ``names``.
        names: image file names.

    Returns:
        (N, 3, 3) intrinsics, or None when K is None.
    """
    if K is None:
        return None
    n = len(names)
    if isinstance(K, np.ndarray):
        arr = np.asarray(K, dtype=float)
        if arr.shape == (3, 3):
            return np.broadcast_to(arr, (n, 3, 3)).copy()
        if arr.shape == (n, 3, 3):
            return arr.copy()
        raise InputFileError(f"K.shape={arr.shape} but expected (3, 3) or ({n}, 3, 3)")
    path = Path(K)
    if not path.exists():
        raise InputFileError(f"intrinsics file {path} does not exist; pass a K.txt (3×3) or a cameras file")
    if path.is_file():
        from pipeline.frontend.intrinsics import parse_intrinsics_file  # noqa: PLC0415

        parsed = parse_intrinsics_file(path)
        if isinstance(parsed, np.ndarray):
            return np.broadcast_to(parsed, (n, 3, 3)).copy()
        by_name = dict(parsed)
    else:
        from pipeline.io.references import read_reference  # noqa: PLC0415

        ref = read_reference(path)
        if ref.K is None:
            raise InputFileError(f"{path} holds no intrinsics; pass a K.txt (3×3) or a cameras file with K")
        Kref = np.asarray(ref.K, dtype=float)
        by_name = {nm: (Kref if Kref.ndim == 2 else Kref[k]) for k, nm in enumerate(ref.names)}
    by_stem = {Path(nm).stem: v for nm, v in by_name.items()}
    out = np.zeros((n, 3, 3))
    missing = []
    for k, nm in enumerate(names):
        v = by_name.get(nm, by_stem.get(Path(nm).stem))
        if v is None:
            missing.append(nm)
        else:
            out[k] = v
    if missing:
        raise InputFileError(f"{path} has no intrinsics for {missing[:5]}{'...' if len(missing) > 5 else ''}; "
                             "give a K for every image, or none")
    return out


def _images_fingerprint(images: Path, names: list[str]) -> str:
    h = hashlib.sha1()
    for nm in names:
        st = (images / nm).stat()
        h.update(f"{nm}:{st.st_size}:{int(st.st_mtime)}\n".encode())
    return h.hexdigest()[:12]


@contextlib.contextmanager
def _atomic_dir(path: Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; it replaces ``path`` when the block exits cleanly."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}."))
    try:
        yield tmp
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# Our K files and keypoints put pixel centres at integer coordinates (OpenCV); COLMAP puts
# them at +0.5 (the image's top-left corner is (0, 0)), so principal points and keypoints
# are shifted by half a pixel on the way in.
COLMAP_PIXEL_OFFSET = 0.5


def _pinhole_params(K: np.ndarray) -> list[float]:
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + COLMAP_PIXEL_OFFSET, float(K[1, 2]) + COLMAP_PIXEL_OFFSET]


class _DatabaseProgress:
    """A progress bar for a pycolmap call that has no callback, fed by polling its database.

    pycolmap's feature extraction and exhaustive matching write one row per image
    (``keypoints``) or per pair (``matches``) as they go; a daemon thread counts the
    rows of ``table`` through a lock-free (``immutable``) read-only SQLite connection
    every ``period`` seconds, so it never blocks the writer. A half-written or
    not-yet-created database just skips that poll; the bar never touches the
    database's content.
    """

    def __init__(self, db_path: Path, table: str, total: int, desc: str, enabled: bool, period: float = 0.5):
        import threading

        from tqdm import tqdm  # noqa: PLC0415

        self.db_path, self.table, self.period = Path(db_path), table, period
        self.bar = tqdm(total=total, desc=desc, unit="img" if table == "keypoints" else "pair", disable=not enabled)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True) if enabled else None

    def count(self) -> int | None:
        import sqlite3

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

    def __enter__(self) -> "_DatabaseProgress":
        if self._thread is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            if exc[0] is None:
                self._update()
        self.bar.close()


def _build_database(pc, db_path: Path, images: Path, names: list[str], Ks: np.ndarray | None,
                    cfg: ReferenceConfig, work: Path | None, progress: bool = False) -> dict[str, float]:
    """Extract + match (or import ours) into a fresh database at ``db_path``; returns timings."""
    reader = pc.ImageReaderOptions()
    same_K = Ks is not None and np.allclose(Ks, Ks[0])
    if Ks is not None:
        reader.camera_model = "PINHOLE"
        if same_K:
            reader.camera_params = ",".join(f"{v:.10g}" for v in _pinhole_params(Ks[0]))
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
        pairs_path = db_path.with_suffix(".pairs.txt")
        _write_pairs_from_db(pc, db_path, pairs_path)
        pc.verify_matches(db_path, pairs_path, pc.TwoViewGeometryOptions())
        times["match_s"] = time.perf_counter() - t1
    else:
        ext = pc.FeatureExtractionOptions()
        ext.max_image_size = cfg.max_image_size
        ext.num_threads = cfg.num_threads
        ext.sift.max_num_features = cfg.max_num_features
        with _DatabaseProgress(db_path, "keypoints", len(names), "pycolmap features", progress):
            pc.extract_features(db_path, images, image_names=names, camera_mode=mode, reader_options=reader,
                                extraction_options=ext, device=pc.Device.cpu)
        times["extract_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        mopt = pc.FeatureMatchingOptions()
        mopt.num_threads = cfg.num_threads
        n_pairs = len(names) * (len(names) - 1) // 2
        with _DatabaseProgress(db_path, "matches", n_pairs, "pycolmap matching", progress):
            pc.match_exhaustive(db_path, matching_options=mopt, device=pc.Device.cpu)
        times["match_s"] = time.perf_counter() - t1
    if Ks is not None and not same_K:
        # PER_IMAGE cameras were created from the reader defaults: set each one to its known K
        db = pc.Database.open(db_path)
        try:
            for img in db.read_all_images():
                cam = db.read_camera(img.camera_id)
                cam.params = _pinhole_params(Ks[names.index(img.name)])
                db.update_camera(cam)
        finally:
            db.close()
    return times


def _import_our_matches(pc, db_path: Path, images: Path, names: list[str], reader, mode, work: Path) -> None:
    """Write our keypoints and putative matches into a COLMAP database."""
    from pipeline.frontend.feature_stage import load_features  # noqa: PLC0415
    from pipeline import matching as our_matching  # noqa: PLC0415

    fs = load_features(work)
    if list(fs.names) != list(names):
        raise PipelineError(f"the features in {work} are of other images ({len(fs.names)} vs {len(names)}); "
                            "re-run the features stage on this folder")
    loader = getattr(our_matching, "load_matches", None)
    if loader is None:
        raise PipelineError("pipeline.frontend.matching exposes no load_matches(work); cannot reuse our matches")
    md = loader(work)
    pc.Database.open(db_path).close()  # import_images needs an existing database file
    pc.import_images(db_path, images, camera_mode=mode, image_names=names, options=reader)
    db = pc.Database.open(db_path)
    try:
        ids = {img.name: img.image_id for img in db.read_all_images()}
        for k, nm in enumerate(fs.names):
            kp = np.asarray(fs.keypoints[k], dtype=np.float32)[:, :2] + np.float32(COLMAP_PIXEL_OFFSET)
            db.write_keypoints(ids[nm], np.ascontiguousarray(kp))
        pairs, matches = _matches_as_lists(md)
        for (i, j), m in zip(pairs, matches):
            db.write_matches(ids[fs.names[i]], ids[fs.names[j]], np.ascontiguousarray(np.asarray(m, dtype=np.uint32)))
    finally:
        db.close()


def _matches_as_lists(md: Any) -> tuple[list[tuple[int, int]], list[np.ndarray]]:
    """Accept the matching stage's result in the shapes it may take: (pairs, list of (n,2))."""
    if isinstance(md, tuple) and len(md) == 2:
        return [tuple(map(int, p)) for p in md[0]], list(md[1])
    pairs = getattr(md, "pairs", None)
    matches = getattr(md, "matches", None)
    if pairs is None or matches is None:
        raise PipelineError("cannot read our matches: expected .pairs and .matches from pipeline.frontend.matching.load_matches")
    return [tuple(map(int, p)) for p in np.asarray(pairs)], list(matches)


def _write_pairs_from_db(pc, db_path: Path, pairs_path: Path) -> None:
    db = pc.Database.open(db_path)
    try:
        names = {img.image_id: img.name for img in db.read_all_images()}
        pair_ids, _ = db.read_all_matches()
    finally:
        db.close()
    lines = []
    for pid in pair_ids:
        a, b = pc.pair_id_to_image_pair(pid) if hasattr(pc, "pair_id_to_image_pair") else _split_pair_id(pid)
        lines.append(f"{names[a]} {names[b]}\n")
    pairs_path.write_text("".join(lines))


def _split_pair_id(pid: int) -> tuple[int, int]:
    # COLMAP: pair_id = 2147483647 * id1 + id2 with id1 < id2
    k = 2147483647
    return int(pid // k), int(pid % k)


def _verified_degree(pc, db_path: Path) -> tuple[dict[str, int], dict[str, int]]:
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
        a, b = _split_pair_id(int(pid))
        for x in (a, b):
            if x in names:
                deg[names[x]] += 1
    return deg, n_kp


def _run_mapping(pc, db_path: Path, images: Path, models_dir: Path, cfg: ReferenceConfig, known_K: bool,
                 n_images: int = 0, progress: bool = False) -> dict[int, Any]:
    opts = pc.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    opts.random_seed = cfg.seed
    opts.min_model_size = cfg.min_model_size
    opts.multiple_models = True
    if known_K and not cfg.refine_known_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
    from tqdm import tqdm  # noqa: PLC0415

    with _atomic_dir(models_dir) as tmp, tqdm(total=n_images, desc="pycolmap mapping", unit="img",
                                               disable=not progress) as bar:
        # the callback fires once per registered image (the first pair counts as two)
        recs = pc.incremental_mapping(db_path, images, tmp, options=opts,
                                      initial_image_pair_callback=lambda: bar.update(2),
                                      next_image_callback=lambda: bar.update(1))
        for k, rec in recs.items():
            d = tmp / str(k)
            d.mkdir(exist_ok=True)
            rec.write(d)
    return recs


def reconstruct(images: Path, out: Path, names: list[str], Ks: np.ndarray | None, cfg: ReferenceConfig,
                work: Path | None = None, overwrite: bool = False, progress: bool = False) -> dict[str, Any]:
    """Run (or resume) the pycolmap reconstruction; returns the summary dict (also written to JSON)."""
    pc = _pycolmap()
    # glog INFO lines of every mapping step drown the pipeline's own log unless debugging
    pc.logging.minloglevel = 0 if logger.isEnabledFor(logging.DEBUG) else 1
    h = config_hash(cfg)
    db_path = out / f"database-{h}.db"
    models_dir = out / f"models-{h}"
    if overwrite:
        for p in (db_path, models_dir):
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    times: dict[str, float] = {}
    timing_path = out / f".times-{h}.json"
    prev_times = json.loads(timing_path.read_text()) if timing_path.exists() else {}
    if not db_path.exists():
        logger.info("pycolmap: %s %d images", "importing our matches for" if cfg.use_our_matches else
                    "extracting and matching", len(names))
        with atomic_path(db_path) as tmp:
            tmp.unlink()
            times.update(_build_database(pc, tmp, images, names, Ks, cfg, work, progress))
        write_json(timing_path, times)
    else:
        logger.info("pycolmap: reusing database %s", db_path)
        times.update({k: v for k, v in prev_times.items() if k in ("extract_s", "match_s")})
    t0 = time.perf_counter()
    if not models_dir.exists():
        logger.info("pycolmap: incremental mapping")
        _run_mapping(pc, db_path, images, models_dir, cfg, Ks is not None, len(names), progress)
        times["map_s"] = time.perf_counter() - t0
        write_json(timing_path, times)
    else:
        times["map_s"] = prev_times.get("map_s", 0.0)
    recs = {}
    for d in sorted(models_dir.iterdir(), key=lambda p: int(p.name) if p.name.isdigit() else 1 << 30):
        if d.is_dir() and d.name.isdigit():
            recs[int(d.name)] = pc.Reconstruction(d)
    return _summarize(pc, recs, db_path, names, out, cfg, times, Ks is not None)


def _summarize(pc, recs: dict[int, Any], db_path: Path, names: list[str], out: Path, cfg: ReferenceConfig,
               times: dict[str, float], known_K: bool) -> dict[str, Any]:
    models = []
    for k, rec in recs.items():
        reg = sorted(rec.images[i].name for i in rec.reg_image_ids())
        models.append({"index": k, "n_registered": len(reg), "registered": reg,
                       "left_out": sorted(set(names) - set(reg)), "n_points3D": int(rec.num_points3D())})
    models.sort(key=lambda m: (-m["n_registered"], m["index"]))
    deg, n_kp = _verified_degree(pc, db_path)
    used = models[0] if models else None
    registered = used["registered"] if used else []
    R = np.zeros((len(registered), 3, 3))
    if used:
        rec = recs[used["index"]]
        by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
        R = np.stack([by_name[nm].cam_from_world().rotation.matrix() for nm in registered]) if registered else R
        model_dir = out / "model"
        with _atomic_dir(model_dir) as tmp:
            rec.write(tmp)
    unregistered: dict[str, str] = {}
    for nm in names:
        if nm in registered:
            continue
        other = [m for m in models[1:] if nm in m["registered"]]
        if nm not in n_kp:
            why = "pycolmap could not read the image"
        elif n_kp[nm] == 0:
            why = "no SIFT features found"
        elif other:
            why = f"registered only in a smaller model ({other[0]['n_registered']} images, model {other[0]['index']})"
        elif deg.get(nm, 0) == 0:
            why = "no geometrically verified match with any other image"
        else:
            why = f"{deg[nm]} verified image pairs, but incremental mapping could not register it"
        unregistered[nm] = why
    for nm, why in unregistered.items():
        logger.warning("pycolmap reference: %s not registered: %s", nm, why)
    if len(models) > 1:
        for m in models[1:]:
            logger.warning("pycolmap returned another model of %d images (%s); the largest (%d images) is used; "
                           "this one leaves out %d images", m["n_registered"], ", ".join(m["registered"][:6]),
                           used["n_registered"], len(m["left_out"]))
    times["total_s"] = float(sum(v for k, v in times.items() if k != "total_s"))
    summary = {
        "config": dataclasses.asdict(cfg),
        "config_hash": config_hash(cfg),
        "known_K": known_K,
        "images": list(names),
        "n_images": len(names),
        "n_registered": len(registered),
        "registered": registered,
        "unregistered": unregistered,
        "n_models": len(models),
        "used_model": used["index"] if used else None,
        "models": [{k: v for k, v in m.items()} for m in models],
        "time_s": times["total_s"],
        "times": times,
    }
    if registered:
        write_rotations(out / "rotations.txt", registered, R,
                        header=f"pycolmap {pc.__version__} incremental reconstruction, largest model, cam_from_world")
    return summary


def main(images: str | os.PathLike, out: str | os.PathLike, K: str | os.PathLike | np.ndarray | None = None,
         overwrite: bool = False, config: ReferenceConfig | None = None, work: str | os.PathLike | None = None,
         names: list[str] | None = None, progress: bool = True) -> Path:
    """Reconstruct ``images`` with pycolmap into ``out`` (resumable); returns ``out/reference.json``.

    Args:
        images: folder of images.
        out: output folder (created).
        K: known intrinsics (see :func:`load_known_K`), or None.
        overwrite: redo everything.
        config: options; defaults to ``ReferenceConfig()``.
        work: our front end's WORK folder (only for ``use_our_matches``).
        names: image file names to use (default: every image in the folder).
        progress: show a progress bar during mapping.

    Returns:
        Path of ``reference.json``.
    """
    cfg = config or ReferenceConfig()
    images, out = Path(images), Path(out)
    names = list(names) if names is not None else list_images(images)
    if len(names) < 2:
        raise InputFileError(f"{images} has {len(names)} image(s); a reconstruction needs at least 2")
    if K is None and cfg.find_K_in_folder:
        from pipeline.frontend.intrinsics import find_intrinsics_file  # noqa: PLC0415

        K = find_intrinsics_file(images)  # the same file our feature stage picks up
    Ks = load_known_K(K, names)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "reference.json"
    key = {"config_hash": config_hash(cfg), "images": names, "fingerprint": _images_fingerprint(images, names),
           "K": None if Ks is None else hashlib.sha1(np.ascontiguousarray(Ks).tobytes()).hexdigest()[:12]}
    if json_path.exists() and not overwrite:
        try:
            prev = json.loads(json_path.read_text())
        except (OSError, ValueError):
            prev = {}
        if prev.get("cache_key") == key:
            logger.info("pycolmap reference: reusing %s (%d/%d registered)", json_path, prev.get("n_registered", 0),
                        len(names))
            return json_path
    fresh = overwrite or (json_path.exists() and json.loads(json_path.read_text()).get("cache_key") != key)
    summary = reconstruct(images, out, names, Ks, cfg, work=Path(work) if work else None, overwrite=fresh,
                          progress=progress)
    summary["cache_key"] = key
    write_json(json_path, summary)
    logger.info("pycolmap reference: %d/%d images registered in %.1f s (%d model(s))", summary["n_registered"],
                len(names), summary["time_s"], summary["n_models"])
    return json_path


def load_reference_result(out: str | os.PathLike) -> ReferenceResult:
    """Load what :func:`main` wrote in ``out`` (a folder or its ``reference.json``)."""
    out = Path(out)
    if out.is_file():
        out = out.parent
    json_path = out / "reference.json"
    if not json_path.exists():
        raise InputFileError(f"{json_path} does not exist; run `python -m pipeline.reference` first")
    summary = json.loads(json_path.read_text())
    if summary.get("n_registered", 0) == 0:
        return ReferenceResult([], np.zeros((0, 3, 3)), summary)
    names, R = read_rotations(out / "rotations.txt")
    return ReferenceResult(list(names), np.asarray(R), summary)


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli  # noqa: PLC0415
    from pipeline.core.config import load_yaml, stage_config  # noqa: PLC0415

    parser = argparse.ArgumentParser(prog="python -m pipeline.reference",
                                     description="pycolmap incremental reconstruction of an image folder (a reference)")
    parser.add_argument("--images", required=True, type=Path, help="folder of images")
    parser.add_argument("--out", required=True, type=Path, help="output folder (resumable cache)")
    parser.add_argument("--K", type=Path, default=None, help="K.txt (3×3) or per-image cameras file")
    parser.add_argument("--config", type=Path, default=None, help="YAML config; its [reference] section is used")
    parser.add_argument("--our-matches", type=Path, default=None, metavar="WORK",
                        help="reuse our keypoints and matches from this WORK folder")
    parser.add_argument("--max-image-size", type=int, default=None)
    parser.add_argument("--overwrite", action="store_true", help="redo everything")

    def body(a: argparse.Namespace) -> int:
        cfg = stage_config(ReferenceConfig, load_yaml(a.config), "reference", max_image_size=a.max_image_size,
                           use_our_matches=True if a.our_matches else None)
        p = main(a.images, a.out, K=a.K, overwrite=a.overwrite, config=cfg, work=a.our_matches, progress=not a.quiet)
        s = json.loads(p.read_text())
        print(f"registered {s['n_registered']}/{s['n_images']} images in {s['time_s']:.1f} s "
              f"({s['n_models']} model(s)); rotations: {a.out / 'rotations.txt'}")
        for nm, why in s["unregistered"].items():
            print(f"  not registered: {nm}: {why}")
        return 0

    return run_cli(body, parser, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
