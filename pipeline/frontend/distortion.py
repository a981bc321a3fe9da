"""Lens distortion: camera models read where they are given, keypoints undistorted before any geometry.

A camera model here is COLMAP's (:class:`CameraModel`: a model name such as
``SIMPLE_RADIAL`` or ``OPENCV``, the image size and the parameters in COLMAP's
order and pixel convention, centre of the top-left pixel at (0.5, 0.5)). pycolmap
evaluates every model (``Camera.cam_from_img``), so no distortion formula is
re-implemented for reading; :func:`undistort_points` maps measured pixels to the
pixels of the ideal pinhole camera with the same focal lengths and principal point
(our convention, pixel centres at integers), which the whole geometry then uses.

Readers (:func:`read_camera_models`), each returning ``{image name or "*": model}``:

- a COLMAP ``cameras.txt`` or ``cameras.bin`` (one camera: every image; several: the
  ``images.txt``/``images.bin`` beside it says which image uses which), or a COLMAP
  model folder holding them;
- an OpenCV-style K with distortion coefficients: a text file of 9 + 4, 5 or 8
  numbers (K row by row, then ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``), or an OpenCV
  FileStorage ``.yaml``/``.yml``/``.xml`` with ``camera_matrix`` and
  ``distortion_coefficients`` (as ``cv2.calibrateCamera`` users save them).

:func:`radial_undistort` is the one-parameter radial family used when the
distortion is estimated (:mod:`pipeline.frontend.radial`): ``x_d = c + (1 + κ|u|²)(x_u − c)``
with ``u = (x_u − c)/s`` at a nominal scale ``s``; it is COLMAP's ``SIMPLE_RADIAL``
with ``k1 = κ f²/s²`` (:func:`simple_radial`).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.errors import InputFileError

__all__ = ["CameraModel", "COLMAP_OFFSET", "PINHOLE_MODELS", "n_params", "read_camera_models", "is_camera_model_file",
           "pinhole_K", "undistort_points", "distort_points", "simple_radial", "opencv_model", "radial_undistort"]

COLMAP_OFFSET = 0.5  # COLMAP puts pixel centres at +0.5, we at integers
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# model name -> (COLMAP model id, parameter count); the ids are those of cameras.bin
_MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5), "OPENCV": (4, 8),
           "OPENCV_FISHEYE": (5, 8), "FULL_OPENCV": (6, 12), "FOV": (7, 5), "SIMPLE_RADIAL_FISHEYE": (8, 4),
           "RADIAL_FISHEYE": (9, 5), "THIN_PRISM_FISHEYE": (10, 12)}
_BY_ID = {v[0]: k for k, v in _MODELS.items()}
_OPENCV_SUFFIXES = (".yaml", ".yml", ".xml")


@dataclass(frozen=True)
class CameraModel:
    """One COLMAP camera.

    Attributes:
        model: COLMAP model name (``SIMPLE_RADIAL``, ``OPENCV``, ...).
        width, height: image size (px).
        params: parameters in COLMAP's order and pixel convention (centre of the top-left pixel at (0.5, 0.5)).
    """

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    @property
    def has_distortion(self) -> bool:
        return self.model not in PINHOLE_MODELS and any(p != 0.0 for p in self.extra_params)

    @property
    def extra_params(self) -> tuple[float, ...]:
        return self.params[len(_fxfy(self.model)) + 2:]

    def pycolmap(self):  # noqa: ANN201 - pycolmap.Camera, imported lazily
        import pycolmap  # noqa: PLC0415

        return pycolmap.Camera(model=self.model, width=int(self.width), height=int(self.height),
                               params=[float(p) for p in self.params])

    def as_dict(self) -> dict:
        return {"model": self.model, "width": self.width, "height": self.height, "params": list(self.params)}


def n_params(model: str) -> int:
    """The parameter count of a COLMAP model name; :class:`InputFileError` for an unknown one."""
    if model not in _MODELS:
        raise InputFileError(f"camera model {model!r} is not supported; use one of {', '.join(_MODELS)}")
    return _MODELS[model][1]


def _checked(model: str, w: int, h: int, params: list[float], where: str) -> CameraModel:
    if len(params) != n_params(model):
        raise InputFileError(f"{where}: {model} takes {n_params(model)} parameters, got {len(params)}")
    if not (np.all(np.isfinite(params)) and all(params[k] > 0 for k in _fxfy(model))):
        raise InputFileError(f"{where}: {model} parameters {params} are not finite with positive focal lengths")
    if w < 1 or h < 1 or w > 1 << 20 or h > 1 << 20:
        raise InputFileError(f"{where}: image size {w}x{h} is not plausible")
    return CameraModel(model, int(w), int(h), tuple(float(p) for p in params))


# ------------------------------------------------------------------------ COLMAP
def _colmap_cameras_txt(path: Path) -> dict[int, CameraModel]:
    cams: dict[int, CameraModel] = {}
    for k, line in enumerate(_text(path).splitlines()):
        v = line.split("#")[0].split()
        if not v:
            continue
        where = f"{path} line {k + 1}"
        try:
            cid, model, w, h, params = int(v[0]), v[1], int(v[2]), int(v[3]), [float(x) for x in v[4:]]
        except (ValueError, IndexError):
            raise InputFileError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]', got {line[:80]!r}") from None
        cams[cid] = _checked(model, w, h, params, where)
    if not cams:
        raise InputFileError(f"{path} holds no camera")
    return cams


def _colmap_images_txt(path: Path) -> dict[str, int]:
    out: dict[str, int] = {}
    lines = [ln for ln in _text(path).splitlines() if not ln.lstrip().startswith("#")]
    k = 0
    while k < len(lines):  # IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then a line of points (maybe empty)
        v = lines[k].split()
        if not v:
            k += 1
            continue
        try:
            [float(x) for x in v[1:8]]
            out[" ".join(v[9:])] = int(v[8])
        except (ValueError, IndexError):
            raise InputFileError(f"{path}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME' lines, got "
                                 f"{lines[k][:80]!r}") from None
        k += 2
    return out


class _Reader:
    """Bounds-checked little-endian reads of a COLMAP binary file."""

    def __init__(self, path: Path) -> None:
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str) -> tuple:
        n = struct.calcsize("<" + fmt)  # the file's packed size: a native calcsize pads "i7d" to 64 bytes, not 60
        if self.pos + n > len(self.data):
            raise InputFileError(f"{self.path} is truncated (a COLMAP binary file)")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += n
        return out

    def name(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise InputFileError(f"{self.path} is truncated (a COLMAP binary file)")
        s = self.data[self.pos:end].decode("utf-8", "replace")
        self.pos = end + 1
        return s


def _colmap_cameras_bin(path: Path) -> dict[int, CameraModel]:
    r = _Reader(path)
    (n,) = r.take("Q")
    if n > len(r.data):
        raise InputFileError(f"{path} claims {n} cameras; it is not a COLMAP cameras.bin")
    cams = {}
    for _ in range(n):  # one record per camera: a handful
        cid, mid, w, h = r.take("iiQQ")
        if mid not in _BY_ID:
            raise InputFileError(f"{path}: camera {cid} has the unsupported model id {mid}")
        model = _BY_ID[mid]
        cams[cid] = _checked(model, w, h, list(r.take("d" * n_params(model))), f"{path} camera {cid}")
    return cams


def _colmap_images_bin(path: Path) -> dict[str, int]:
    r = _Reader(path)
    (n,) = r.take("Q")
    out = {}
    for _ in range(min(n, len(r.data))):  # one record per image
        r.take("i7d")
        (cid,) = r.take("i")
        name = r.name()
        (npts,) = r.take("Q")
        if r.pos + 24 * npts > len(r.data):
            raise InputFileError(f"{path} is truncated (a COLMAP images.bin)")
        r.pos += 24 * npts  # points2D: x, y (double), point3D id (int64)
        out[name] = cid
    return out


def _colmap(path: Path) -> dict[str, CameraModel]:
    folder = path if path.is_dir() else path.parent
    cam_file = path if path.is_file() else next((folder / f"cameras{e}" for e in (".bin", ".txt")
                                                 if (folder / f"cameras{e}").is_file()), None)
    if cam_file is None:
        raise InputFileError(f"{path} holds no cameras.bin or cameras.txt")
    cams = _colmap_cameras_bin(cam_file) if cam_file.suffix == ".bin" else _colmap_cameras_txt(cam_file)
    if len(cams) == 1:
        return {"*": next(iter(cams.values()))}
    img_file = next((folder / f"images{e}" for e in (cam_file.suffix, ".bin", ".txt") if (folder / f"images{e}").is_file()),
                    None)
    if img_file is None:
        raise InputFileError(f"{cam_file} holds {len(cams)} cameras but no images.bin/.txt beside it says which image "
                             "uses which; pass the COLMAP model folder")
    images = _colmap_images_bin(img_file) if img_file.suffix == ".bin" else _colmap_images_txt(img_file)
    missing = sorted({c for c in images.values() if c not in cams})
    if missing:
        raise InputFileError(f"{img_file} uses camera id(s) {missing[:5]} that {cam_file} lacks")
    return {name: cams[cid] for name, cid in images.items()}


# ------------------------------------------------------------------------ OpenCV
def opencv_model(K: np.ndarray, dist: list[float] | np.ndarray, width: int, height: int, where: str = "") -> CameraModel:
    """``OPENCV`` (4 coefficients) or ``FULL_OPENCV`` (5 or 8) from an OpenCV K and distortion vector.

    OpenCV puts pixel centres at integers, COLMAP at +0.5: the principal point is shifted.
    """
    d = [float(v) for v in np.asarray(dist, float).ravel()]
    if len(d) not in (4, 5, 8):
        raise InputFileError(f"{where}: {len(d)} distortion coefficients; expected 4, 5 or 8 (k1 k2 p1 p2 [k3 [k4 k5 "
                             "k6]]); thin-prism and tilt models are not supported")
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise InputFileError(f"{where}: K has skew {K[0, 1]}, which COLMAP's OpenCV models cannot hold")
    pin = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + COLMAP_OFFSET, float(K[1, 2]) + COLMAP_OFFSET]
    if len(d) == 4:
        return _checked("OPENCV", width, height, pin + d, where)
    d = d + [0.0] * (8 - len(d))
    return _checked("FULL_OPENCV", width, height, pin + d[:4] + [d[4], d[5], d[6], d[7]], where)


def _opencv_storage(path: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int] | None]:
    import cv2  # noqa: PLC0415

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise InputFileError(f"{path} is not an OpenCV FileStorage file ({' '.join(str(exc).split())[-80:]})") from None
    try:
        K = fs.getNode("camera_matrix").mat()
        d = next((fs.getNode(n).mat() for n in ("distortion_coefficients", "dist_coeffs", "dist_coeff")
                  if not fs.getNode(n).empty()), None)
        w, h = fs.getNode("image_width").real(), fs.getNode("image_height").real()
    finally:
        fs.release()
    if K is None or d is None:
        raise InputFileError(f"{path}: expected the nodes camera_matrix and distortion_coefficients")
    return np.asarray(K, float).reshape(3, 3), np.asarray(d, float).ravel(), (int(w), int(h)) if w > 0 and h > 0 else None


def _text(path: Path) -> str:
    if path.stat().st_size > 256 << 20:
        raise InputFileError(f"{path} is {path.stat().st_size >> 20} MB; a camera file is far smaller")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def _opencv_text(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(K, coefficients) of a text file of 9 + 4/5/8 numbers; None for any other layout."""
    try:
        nums = [float(v) for ln in _text(path).splitlines() for v in ln.split("#")[0].split()]
    except ValueError:
        return None
    if len(nums) <= 9:
        return None
    return np.array(nums[:9]).reshape(3, 3), np.array(nums[9:])


def is_camera_model_file(path: str | os.PathLike) -> bool:
    """True for the files and folders :func:`read_camera_models` reads (COLMAP, OpenCV with distortion)."""
    p = Path(path)
    if p.is_dir():
        return any((p / f"cameras{e}").is_file() for e in (".bin", ".txt"))
    if p.suffix.lower() in _OPENCV_SUFFIXES or p.name == "cameras.bin":
        return True
    if not p.is_file():
        return False
    try:
        first = next((ln.split() for ln in _text(p).splitlines() if ln.split("#")[0].strip()), [])
    except InputFileError:
        return False
    if len(first) >= 2 and first[0].isdigit() and first[1] in _MODELS:
        return True
    return _opencv_text(p) is not None


def read_camera_models(path: str | os.PathLike, sizes: dict[str, tuple[int, int]] | None = None
                       ) -> dict[str, CameraModel]:
    """Camera models from a COLMAP or OpenCV file (see the module docstring).

    Args:
        path: the file or COLMAP model folder.
        sizes: ``{image name: (w, h)}``, the size of an OpenCV camera when its file has none.
    Returns:
        ``{image name: model}``, or ``{"*": model}`` for one camera shared by every image.
    Raises:
        InputFileError: not a readable camera file.
    """
    p = Path(path)
    if not p.exists():
        raise InputFileError(f"camera file {p} does not exist")
    if p.is_dir() or p.name in ("cameras.txt", "cameras.bin") or (
            p.is_file() and p.suffix.lower() not in _OPENCV_SUFFIXES and _opencv_text(p) is None):
        return _colmap(p)
    if p.suffix.lower() in _OPENCV_SUFFIXES:
        K, d, wh = _opencv_storage(p)
    else:
        K, d = _opencv_text(p)  # type: ignore[misc]
        wh = None
    if wh is None:
        wh = next(iter((sizes or {}).values()), (int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1))))
    return {"*": opencv_model(K, d, wh[0], wh[1], str(p))}


# --------------------------------------------------------------------- undistort
def pinhole_K(cam: CameraModel) -> np.ndarray:
    """(3, 3) pinhole K of a model (its focal lengths and principal point), our pixel convention."""
    p = cam.params
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if len(_fxfy(cam.model)) == 1 else (p[0], p[1], p[2], p[3])
    return np.array([[fx, 0.0, cx - COLMAP_OFFSET], [0.0, fy, cy - COLMAP_OFFSET], [0.0, 0.0, 1.0]])


def _fxfy(model: str) -> tuple[int, ...]:
    return (0,) if model.startswith("SIMPLE") or model in ("RADIAL", "RADIAL_FISHEYE") else (0, 1)


def undistort_points(cam: CameraModel, x: np.ndarray) -> np.ndarray:
    """Measured pixels (n, 2) → pixels of the ideal pinhole camera :func:`pinhole_K` (pycolmap's ``cam_from_img``)."""
    x = np.asarray(x, np.float64).reshape(-1, 2)
    if not cam.has_distortion:
        return x.copy()
    y = np.asarray(cam.pycolmap().cam_from_img(np.ascontiguousarray(x + COLMAP_OFFSET)), np.float64)
    K = pinhole_K(cam)
    return y @ K[:2, :2].T + K[:2, 2]


def distort_points(cam: CameraModel, x_u: np.ndarray) -> np.ndarray:
    """Inverse of :func:`undistort_points`: ideal pinhole pixels → measured pixels (``img_from_cam``)."""
    K = pinhole_K(cam)
    y = (np.asarray(x_u, np.float64) - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    return np.asarray(cam.pycolmap().img_from_cam(np.column_stack([y, np.ones(len(y))])), np.float64) - COLMAP_OFFSET


def simple_radial(f: float, c: np.ndarray, k1: float, width: int, height: int) -> CameraModel:
    """COLMAP ``SIMPLE_RADIAL`` with focal ``f``, principal point ``c`` (our convention) and ``k1``."""
    return CameraModel("SIMPLE_RADIAL", int(width), int(height),
                       (float(f), float(c[0]) + COLMAP_OFFSET, float(c[1]) + COLMAP_OFFSET, float(k1)))


def radial_undistort(x: np.ndarray, c: np.ndarray, s: float, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """Undistort pixels under ``x_d = c + (1 + κ|u|²)(x_u − c)``, ``u = (x_u − c)/s``; and ``∂x_u/∂x_d``.

    Newton on the radius ``r_d = r_u (1 + κ r_u²)``, vectorized (equal to pycolmap's
    ``SIMPLE_RADIAL`` inverse to 1e-6 px in the tests).

    Args:
        x: (n, 2) measured pixels.  c: (2,) centre.  s: nominal scale (px).  kappa: κ.
    Returns:
        ``(x_u (n, 2), J (n, 2, 2))``.
    """
    d = (np.asarray(x, np.float64) - c) / s
    rd = np.sqrt((d * d).sum(axis=1))
    ru = rd.copy()
    for _ in range(20):  # Newton on all radii at once
        ru -= (ru * (1.0 + kappa * ru * ru) - rd) / (1.0 + 3.0 * kappa * ru * ru)
    u = d * np.where(rd > 0, ru / np.maximum(rd, 1e-300), 1.0)[:, None]
    # ∂x_d/∂x_u = (1 + κ|u|²) I + 2κ u uᵀ; its 2×2 inverse in closed form
    a = 1.0 + kappa * (u * u).sum(axis=1)
    A = a[:, None, None] * np.eye(2) + 2.0 * kappa * u[:, :, None] * u[:, None, :]
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    Ji = np.stack([np.stack([A[:, 1, 1], -A[:, 0, 1]], -1), np.stack([-A[:, 1, 0], A[:, 0, 0]], -1)], -2)
    return c + s * u, Ji / det[:, None, None]
