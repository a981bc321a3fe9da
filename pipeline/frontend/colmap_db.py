"""Reading a COLMAP database (made by COLMAP, pycolmap, hloc or GLOMAP) through pycolmap's ``Database`` API.

What the pipeline takes from a database: each image's camera (model and
parameters), its keypoints, and the inlier matches of every pair the database
has verified (its two-view geometries). No SQL of our own: every read is a
``pycolmap.Database`` call.

Conventions on the way in:

- COLMAP puts pixel centres at +0.5 (:data:`COLMAP_PIXEL_OFFSET`); our keypoints
  and K put them at integers (OpenCV), so both are shifted by −0.5;
- a camera model with distortion (``SIMPLE_RADIAL``, ``OPENCV``, fisheye models,
  ...) has its keypoints undistorted with pycolmap's own model
  (``Camera.cam_from_img``) and re-projected with the pinhole part of the camera
  (its focal lengths and principal point), so that the rest of the pipeline sees
  a pinhole camera; spherical models are refused.

Every failure to read is one :class:`~pipeline.core.errors.InputFileError` line
that names the database.
"""

from __future__ import annotations

import atexit
import hashlib
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline.core.atomic import TMP_TAG
from pipeline.core.errors import InputFileError

__all__ = ["COLMAP_PIXEL_OFFSET", "DbImage", "open_database", "read_images", "verified_pairs", "read_inlier_matches",
           "keypoints_for_image", "iter_keypoints", "pinhole_K", "check_database_file", "database_fingerprint"]

logger = logging.getLogger(__name__)

COLMAP_PIXEL_OFFSET = 0.5
_SQLITE_MAGIC = b"SQLite format 3\x00"
_PINHOLE = ("SIMPLE_PINHOLE", "PINHOLE")
_REFUSED = ("EQUIRECTANGULAR",)
MIN_INLIERS = 1


@dataclass(frozen=True)
class DbImage:
    """One image of a database: its id, name and camera (model, parameters, size)."""

    image_id: int
    name: str
    camera_id: int
    model: str
    params: tuple[float, ...]
    width: int
    height: int


def check_database_file(path: str | os.PathLike) -> Path:
    """``path`` if it is an existing SQLite file; :class:`InputFileError` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"COLMAP database {path} does not exist; pass --database DB (a database.db written by "
                             "COLMAP, pycolmap, hloc or GLOMAP)")
    try:
        with open(path, "rb") as f:
            magic = f.read(len(_SQLITE_MAGIC))
    except OSError as exc:
        raise InputFileError(f"COLMAP database {path} cannot be read ({exc.strerror or exc})") from None
    if magic != _SQLITE_MAGIC:
        raise InputFileError(f"{path} is not a COLMAP database (not an SQLite file); pass the database.db of "
                             "COLMAP, pycolmap, hloc or GLOMAP")
    return path


def database_fingerprint(path: str | os.PathLike) -> str:
    """A 16-hex-digit hash of a database's content.

    SQLite's file change counter and version-valid-for number in the file header
    (bytes 24–27 and 92–95) change whenever a program opens the database read-write,
    even when nothing is written; those bytes are left out. (We never open the user's
    file with pycolmap: see :func:`_private_copy`.)
    """
    path = check_database_file(path)
    h = hashlib.sha1()
    try:
        with open(path, "rb") as f:
            head = bytearray(f.read(100))
            head[24:28] = head[92:96] = b"\0\0\0\0"
            h.update(bytes(head))
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise InputFileError(f"COLMAP database {path} cannot be read ({exc.strerror or exc})") from None
    return h.hexdigest()[:16]


_COPIES: dict[tuple[str, int, int], Path] = {}


def _remove_copies() -> None:
    for copy in _COPIES.values():
        shutil.rmtree(copy.parent, ignore_errors=True)
    _COPIES.clear()


def _private_copy(path: Path) -> Path:
    """A copy of the database (and its ``-wal`` journal) in a temporary folder, made once per process.

    pycolmap opens a database read-write: it creates COLMAP's tables when they are
    missing and bumps the header's change counters. It only ever sees this copy, so that
    the user's file is never changed; the copies are removed when the process ends.
    """
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    copy = _COPIES.get(key)
    if copy is None or not copy.is_file():
        if not _COPIES:
            atexit.register(_remove_copies)
        folder = Path(tempfile.mkdtemp(prefix=f"{TMP_TAG}db-"))
        copy = folder / "database.db"
        try:
            shutil.copyfile(path, copy)
            for side in ("-wal",):
                if Path(f"{path}{side}").is_file():
                    shutil.copyfile(f"{path}{side}", f"{copy}{side}")
        except OSError as exc:
            shutil.rmtree(folder, ignore_errors=True)
            raise InputFileError(f"COLMAP database {path} cannot be read ({exc.strerror or exc})") from None
        _COPIES[key] = copy
    return copy


class open_database:  # noqa: N801 - used as a context manager, like open()
    """``with open_database(path) as db:`` a ``pycolmap.Database`` of a private copy, closed on exit.

    Errors name the user's file; the user's file is never opened by pycolmap.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = check_database_file(path)
        self.db: Any = None

    def __enter__(self) -> Any:
        import pycolmap  # noqa: PLC0415

        copy = _private_copy(self.path)
        try:
            self.db = pycolmap.Database.open(str(copy))
            self.db.num_images()  # a file that is SQLite but not COLMAP's fails here
        except Exception as exc:  # noqa: BLE001 - pycolmap raises RuntimeError/ValueError of its own
            raise InputFileError(f"{self.path} is not a readable COLMAP database ({' '.join(str(exc).split())[:100]})"
                                 ) from None
        return self.db

    def __exit__(self, *exc: Any) -> None:
        if self.db is not None:
            self.db.close()


def _guard(path: Path, what: str) -> Any:
    """Context for a pycolmap read: any failure becomes one line naming the database."""
    class _G:
        def __enter__(self) -> None:
            return None

        def __exit__(self, tp: Any, exc: Any, tb: Any) -> bool:
            if isinstance(exc, Exception) and not isinstance(exc, InputFileError):
                raise InputFileError(f"{path}: cannot read {what} ({' '.join(str(exc).split())[:100]})") from None
            return False
    return _G()


def read_images(path: str | os.PathLike) -> list[DbImage]:
    """Every image of the database with its camera, in image-id order."""
    with open_database(path) as db, _guard(Path(path), "images and cameras"):
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        out = []
        for img in sorted(db.read_all_images(), key=lambda i: i.image_id):
            cam = cams.get(img.camera_id)
            if cam is None:
                raise InputFileError(f"{path}: image {img.name!r} refers to camera {img.camera_id}, which is missing")
            out.append(DbImage(int(img.image_id), str(img.name), int(img.camera_id), str(cam.model.name),
                               tuple(float(v) for v in cam.params), int(cam.width), int(cam.height)))
    return out


def verified_pairs(path: str | os.PathLike) -> list[tuple[int, int, int]]:
    """``(image_id1, image_id2, n_inliers)`` of every pair with verified inlier matches."""
    import pycolmap  # noqa: PLC0415

    with open_database(path) as db, _guard(Path(path), "the two-view geometries"):
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
        out = []
        for pid, n in zip(pair_ids, counts):
            if int(n) >= MIN_INLIERS:
                a, b = pycolmap.pair_id_to_image_pair(int(pid))
                out.append((int(a), int(b), int(n)))
    return out


def read_inlier_matches(path: str | os.PathLike, pairs: list[tuple[int, int]]) -> Iterator[np.ndarray]:
    """The verified inlier matches (m, 2) int64 of each ``(image_id1, image_id2)`` pair, in order.

    A pair whose geometry is degenerate or undefined yields an empty array.
    """
    import pycolmap  # noqa: PLC0415

    bad = {pycolmap.TwoViewGeometryConfiguration.UNDEFINED, pycolmap.TwoViewGeometryConfiguration.DEGENERATE,
           pycolmap.TwoViewGeometryConfiguration.WATERMARK}
    with open_database(path) as db, _guard(Path(path), "inlier matches"):
        for a, b in pairs:
            g = db.read_two_view_geometry(int(a), int(b))
            m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
            yield m[:0] if g.config in bad else m


def pinhole_K(model: str, params: tuple[float, ...], where: str) -> np.ndarray:
    """The pinhole part of a camera, as a (3, 3) K with pixel centres at integers (OpenCV)."""
    import pycolmap  # noqa: PLC0415

    cam = pycolmap.Camera.create_from_model_name(0, model, 1.0, 1, 1)
    cam.params = list(params)
    fx, fy = float(cam.focal_length_x), float(cam.focal_length_y)
    cx, cy = float(cam.principal_point_x), float(cam.principal_point_y)
    K = np.array([[fx, 0.0, cx - COLMAP_PIXEL_OFFSET], [0.0, fy, cy - COLMAP_PIXEL_OFFSET], [0.0, 0.0, 1.0]])
    if not (np.isfinite(K).all() and fx > 0 and fy > 0):
        raise InputFileError(f"{where}: camera {model} {list(params)} has no usable focal length")
    return K


def _camera(image: DbImage) -> Any:
    import pycolmap  # noqa: PLC0415

    cam = pycolmap.Camera.create_from_model_name(image.camera_id, image.model, 1.0, image.width, image.height)
    cam.params = list(image.params)
    return cam


def iter_keypoints(path: str | os.PathLike, images: list[DbImage]) -> Iterator[dict[str, np.ndarray]]:
    """:func:`keypoints_for_image` of each image, the database opened once."""
    with open_database(path) as db:
        for image in images:
            yield keypoints_for_image(db, path, image)


def keypoints_for_image(db: Any, path: str | os.PathLike, image: DbImage) -> dict[str, np.ndarray]:
    """Keypoints of one image of the open database ``db`` (file ``path``) in our convention, undistorted when its
    camera model has distortion.

    Returns:
        ``keypoints`` (n, 2) float32 (pinhole pixels, centres at integers), ``scales``,
        ``orientations`` (deg), ``responses`` (n,) float32, ``descriptors`` (n, 128) uint8
        or (0, 128) when the database has none, and ``n_not_undistorted``.
    """
    if image.model in _REFUSED:
        raise InputFileError(f"{path}: image {image.name!r} has a {image.model} camera; only perspective models "
                             "(pinhole, radial, OpenCV, fisheye) can be used")
    with _guard(Path(path), f"the keypoints of {image.name!r}"):
        kp = np.asarray(db.read_keypoints(image.image_id), dtype=np.float64) if db.exists_keypoints(
            image.image_id) else np.zeros((0, 2))
        desc = np.zeros((0, 128), np.uint8)
        if db.exists_descriptors(image.image_id):
            d = np.asarray(db.read_descriptors(image.image_id).data)
            if d.dtype == np.uint8 and d.shape == (len(kp), 128):
                desc = d
    if kp.ndim != 2 or kp.shape[1] < 2 or not np.isfinite(kp[:, :2]).all():
        raise InputFileError(f"{path}: the keypoints of {image.name!r} are not finite (n, 2+) coordinates")
    xy = kp[:, :2]
    n_bad = 0
    if image.model not in _PINHOLE and len(xy):
        K = pinhole_K(image.model, image.params, f"{path} ({image.name})")
        cam_xy = _camera(image).cam_from_img(np.ascontiguousarray(xy))
        und = cam_xy @ K[:2, :2].T + K[:2, 2]
        ok = np.isfinite(und).all(axis=1)
        n_bad = int((~ok).sum())
        xy = np.where(ok[:, None], und, xy - COLMAP_PIXEL_OFFSET)  # a point the model cannot undistort stays as is
    else:
        xy = xy - COLMAP_PIXEL_OFFSET
    if kp.shape[1] >= 6:  # affine shape [x, y, a11, a12, a21, a22]
        scales = np.sqrt(np.abs(kp[:, 2] * kp[:, 5] - kp[:, 3] * kp[:, 4]))
        orient = np.rad2deg(np.arctan2(kp[:, 4], kp[:, 2]))
    else:
        scales, orient = np.ones(len(kp)), np.zeros(len(kp))
    return {"keypoints": xy.astype(np.float32), "scales": scales.astype(np.float32),
            "orientations": orient.astype(np.float32), "responses": np.zeros(len(kp), np.float32),
            "descriptors": desc, "n_not_undistorted": np.asarray(n_bad)}
