"""Image listing, robust reading and camera intrinsics for the image front end.

Intrinsics are taken, per image, from the first source that has them:

1. a file: ``K.txt`` (one 3×3 matrix for all images), or a per-image cameras file
   (``name fx fy cx cy [...]`` as written by :mod:`pipeline.synthetic.render`, or
   Middlebury ``*_par.txt`` lines ``name k11..k33 r11..r33 t1 t2 t3``). Without an
   explicit file, ``K.txt``, ``cameras.txt`` or a single ``*_par.txt`` inside the
   image folder is used;
2. the EXIF focal length, read through ``pycolmap.infer_camera_from_image``
   (COLMAP's EXIF reader with its sensor-size database), else through Pillow's
   ``FocalLengthIn35mmFilm`` tag;
3. otherwise ``f = 1.2·max(w, h)`` (COLMAP's default factor), with a warning.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.errors import InputFileError

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".pbm", ".bmp", ".tif", ".tiff", ".webp")
DEFAULT_FOCAL_FACTOR = 1.2

__all__ = [
    "IMAGE_EXTENSIONS",
    "list_images",
    "read_gray",
    "image_size",
    "parse_intrinsics_file",
    "find_intrinsics_file",
    "exif_focal",
    "default_K",
    "resolve_intrinsics",
]


def list_images(folder: str | os.PathLike) -> tuple[list[str], list[str]]:
    """Image file names (sorted) in ``folder`` and the other files that were ignored.

    Raises:
        InputFileError: the folder does not exist.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(f"image folder {folder} does not exist or is not a folder; pass --images DIR with your images")
    names, other = [], []
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        (names if p.suffix.lower() in IMAGE_EXTENSIONS else other).append(p.name)
    return names, other


def _jpeg_truncated(data: np.ndarray) -> bool:
    """True if JPEG bytes lack the end-of-image marker (a truncated download or copy)."""
    tail = data[-64:].tobytes().rstrip(b"\x00\n\r\t ")
    return not tail.endswith(b"\xff\xd9")


def read_gray(path: str | os.PathLike) -> tuple[np.ndarray | None, str]:
    """Read an image as 8-bit grey.

    Returns:
        ``(image (h, w) uint8, "")`` or ``(None, reason)`` when the file cannot be used.
    """
    path = Path(path)
    try:
        data = np.fromfile(path, np.uint8)
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror or exc})"
    if data.size == 0:
        return None, "is empty (0 bytes)"
    is_jpeg = data.size >= 3 and data[:3].tobytes() == b"\xff\xd8\xff"
    # libjpeg decodes a truncated JPEG into a partly grey image with only a warning;
    # such an image would give wrong features, so it is refused here
    if is_jpeg and _jpeg_truncated(data):
        return None, "is a truncated JPEG (no end-of-image marker); re-copy or re-download it"
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        return None, "is not an image OpenCV can decode (corrupt, truncated or not an image)"
    if img.dtype == np.uint16:
        img = (img / 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if min(img.shape[:2]) < 16:
        return None, f"is too small ({img.shape[1]}x{img.shape[0]} pixels)"
    return img, ""


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(w, h)`` from the file header (Pillow), or None."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception:  # noqa: BLE001 - any failure means "unknown"
        return None


def parse_intrinsics_file(path: str | os.PathLike) -> np.ndarray | dict[str, np.ndarray]:
    """Read ``K.txt`` (one 3×3) or a per-image cameras file.

    Returns:
        a (3, 3) matrix shared by all images, or ``{name: (3, 3)}``.
    Raises:
        InputFileError: the file is missing or in none of the supported layouts.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"intrinsics file {path} does not exist")
    lines = [ln.split("#")[0].split() for ln in path.read_text().splitlines()]
    lines = [ln for ln in lines if ln]
    try:
        nums: list[float] | None = [float(v) for ln in lines for v in ln]
    except ValueError:
        nums = None  # has names: a per-image file
    if nums is not None:
        if len(nums) != 9:
            raise InputFileError(f"{path}: {len(nums)} numbers, but a K.txt holds exactly 9 (one 3x3 matrix)")
        K = np.array(nums).reshape(3, 3)
        _check_K(K, path)
        return K
    out: dict[str, np.ndarray] = {}
    for k, ln in enumerate(lines):
        if len(ln) == 1 and ln[0].isdigit():
            continue  # Middlebury's first line is the image count
        name, vals = ln[0], ln[1:]
        try:
            v = [float(x) for x in vals]
        except ValueError:
            raise InputFileError(f"{path} line {k + 1}: expected 'name' followed by numbers, got {' '.join(ln)[:80]!r}") from None
        if len(v) == 21:  # Middlebury: name k11..k33 r11..r33 t1 t2 t3
            K = np.array(v[:9]).reshape(3, 3)
        elif len(v) in (4, 16):  # cameras file: name fx fy cx cy [r11..r33 t1 t2 t3]
            K = np.array([[v[0], 0, v[2]], [0, v[1], v[3]], [0, 0, 1.0]])
        else:
            raise InputFileError(
                f"{path} line {k + 1}: {len(v)} numbers after the name; expected 4 or 16 "
                "('name fx fy cx cy [r11..r33 t1 t2 t3]') or 21 (Middlebury 'name k11..k33 r11..r33 t1 t2 t3')"
            )
        _check_K(K, path)
        out[name] = K
    if not out:
        raise InputFileError(f"{path} holds no camera; expected K.txt (3x3) or lines 'name fx fy cx cy ...'")
    return out


def _check_K(K: np.ndarray, path: Path) -> None:
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and abs(K[2, 2] - 1) < 1e-6 and np.allclose(K[2, :2], 0)):
        raise InputFileError(f"{path}: {K.tolist()} is not a pinhole K (fx, fy > 0, last row 0 0 1)")


def find_intrinsics_file(folder: str | os.PathLike) -> Path | None:
    """``K.txt``, ``cameras.txt`` or the single ``*_par.txt`` in ``folder``, if present."""
    folder = Path(folder)
    for name in ("K.txt", "cameras.txt"):
        if (folder / name).is_file():
            return folder / name
    par = sorted(folder.glob("*_par.txt"))
    return par[0] if len(par) == 1 else None


def exif_focal(path: str | os.PathLike) -> float | None:
    """Focal length in pixels from the EXIF tags, or None."""
    try:
        import pycolmap

        cam = pycolmap.infer_camera_from_image(str(path))
        if cam.has_prior_focal_length:
            return float(cam.mean_focal_length())
    except Exception:  # noqa: BLE001 - fall through to Pillow
        logger.debug("pycolmap could not read EXIF of %s", path, exc_info=True)
    try:
        from PIL import Image

        with Image.open(path) as im:
            exif = im.getexif()
            w, h = im.size
            sub = exif.get_ifd(0x8769) if hasattr(exif, "get_ifd") else {}
            f35 = sub.get(0xA405) or exif.get(0xA405)  # FocalLengthIn35mmFilm
            if f35:
                # 35 mm film is 36 mm wide: f_px = f35 / 36 · (long side in pixels)
                return float(f35) / 36.0 * max(w, h)
    except Exception:  # noqa: BLE001
        logger.debug("Pillow could not read EXIF of %s", path, exc_info=True)
    return None


def default_K(w: int, h: int, focal: float | None = None) -> np.ndarray:
    """Pinhole K with the principal point at the image centre."""
    f = focal if focal is not None else DEFAULT_FOCAL_FACTOR * max(w, h)
    return np.array([[f, 0, w / 2.0], [0, f, h / 2.0], [0, 0, 1.0]])


def resolve_intrinsics(folder: Path, names: list[str], sizes: np.ndarray, K_path: Path | None = None) -> tuple[np.ndarray, list[str]]:
    """One K per image, from a file, EXIF or the default focal length.

    Args:
        folder: image folder.
        names: N image file names.
        sizes: (N, 2) image sizes (w, h).
        K_path: explicit intrinsics file, or None to look for one in ``folder``.
    Returns:
        K (N, 3, 3) and the source of each (``"file:<path>"``, ``"exif"``, ``"default"``).
    """
    src_file = Path(K_path) if K_path is not None else find_intrinsics_file(folder)
    parsed = parse_intrinsics_file(src_file) if src_file is not None else None
    if src_file is not None:
        logger.info("intrinsics from %s", src_file)
    K = np.zeros((len(names), 3, 3))
    sources: list[str] = []
    missing_default: list[str] = []
    by_stem = {Path(n).stem: v for n, v in parsed.items()} if isinstance(parsed, dict) else {}
    for k, name in enumerate(names):
        Kk = None
        if isinstance(parsed, np.ndarray):
            Kk = parsed
        elif isinstance(parsed, dict):
            Kk = parsed.get(name, by_stem.get(Path(name).stem))
        if Kk is not None:
            K[k] = Kk
            sources.append(f"file:{src_file}")
            continue
        w, h = (int(v) for v in sizes[k])
        f = exif_focal(folder / name)
        if f is not None:
            K[k] = default_K(w, h, f)
            sources.append("exif")
        else:
            K[k] = default_K(w, h)
            sources.append("default")
            missing_default.append(name)
    if isinstance(parsed, dict):
        absent = [n for n, s in zip(names, sources) if not s.startswith("file:")]
        if absent:
            logger.warning("%s has no intrinsics for %d image(s) (%s); using EXIF or the default focal length for them",
                           src_file, len(absent), ", ".join(absent[:5]) + (" ..." if len(absent) > 5 else ""))
    if missing_default:
        logger.warning(
            "no intrinsics file and no EXIF focal length for %d image(s) (%s): assuming f = %.1f·max(w, h). "
            "Pass --K K.txt (3x3) or a cameras file for accurate rotations",
            len(missing_default), ", ".join(missing_default[:5]) + (" ..." if len(missing_default) > 5 else ""),
            DEFAULT_FOCAL_FACTOR,
        )
    return K, sources
