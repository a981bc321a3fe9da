"""Image listing, header checks and robust reading for the image front end.

Every image is checked from its header before any work (:func:`check_headers`):
a file that is not an image, whose header claims an absurd size (a decoder would
try to allocate gigabytes), or that is too small, is left out with its reason.
Reading (:func:`read_gray`) refuses truncated or corrupt JPEGs, which libjpeg
would otherwise decode into partly grey images with only a warning, and PNGs whose
chunks are damaged (bad CRC, truncated). Intrinsics
are resolved in :mod:`pipeline.frontend.intrinsics`.
"""

from __future__ import annotations

import logging
import os
import zlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipeline.core.errors import InputFileError
from pipeline.stage import RECORD_SUFFIX

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".pbm", ".bmp", ".tif", ".tiff", ".webp")
MAX_PIXELS = 250_000_000  # 250 Mpx: more is a damaged or hostile header, not a photo
MIN_SIDE = 16

__all__ = ["IMAGE_EXTENSIONS", "MAX_PIXELS", "list_images", "read_gray", "image_size", "header_exif", "check_headers",
           "ends_crc"]


def list_images(folder: str | os.PathLike) -> tuple[list[str], list[str]]:
    """Image names (sorted) under ``folder`` and the other files that were ignored.

    Subfolders are read too, as COLMAP's image reader does: an image in one is named by its path relative to
    ``folder`` with ``/`` (``cam0/0001.jpg``, the name COLMAP and hloc give it). Hidden files and folders are
    skipped, and so is a folder of this pipeline's own outputs (one holding a stage record, ``*.record.json``),
    whose plots are PNG files, should ``--out`` lie inside the image folder. Symbolic links to folders are followed
    once each.

    Raises:
        InputFileError: the folder does not exist.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(f"image folder {folder} does not exist or is not a folder; pass --images DIR with your images")
    names, other = [], []
    seen = {os.path.realpath(folder)}

    def unreadable(exc: OSError) -> None:  # a subfolder os.walk cannot list: said, not passed over in silence
        logger.warning("cannot read the folder %s (%s): its images are left out", exc.filename, exc.strerror or exc)

    for root, dirs, files in os.walk(folder, onerror=unreadable, followlinks=True):
        rel = Path(root).relative_to(folder)
        if rel != Path(".") and any(f.endswith(RECORD_SUFFIX) for f in files):  # our outputs: plots, not photos
            dirs[:] = []
            continue
        keep = []
        for d in sorted(dirs):
            real = os.path.realpath(os.path.join(root, d))
            if not d.startswith(".") and real not in seen:  # a link back up (or twice to one folder) is read once
                seen.add(real)
                keep.append(d)
        dirs[:] = keep
        for f in files:
            if f.startswith(".") or not os.path.isfile(os.path.join(root, f)):
                continue
            name = (rel / f).as_posix()
            (names if Path(f).suffix.lower() in IMAGE_EXTENSIONS else other).append(name)
    return sorted(names), sorted(other)


def _jpeg_truncated(data: np.ndarray) -> bool:
    """True if JPEG bytes lack the end-of-image marker (a truncated download or copy)."""
    tail = data[-64:].tobytes().rstrip(b"\x00\n\r\t ")
    return not tail.endswith(b"\xff\xd9")


def _jpeg_corrupt(data: np.ndarray) -> str:
    """libjpeg's complaint about corrupt entropy-coded data ('' if none), from a strict 1/8-scale decode."""
    import simplejpeg  # noqa: PLC0415

    kw = dict(colorspace="GRAY", min_height=1, min_width=1, min_factor=8)
    try:
        simplejpeg.decode_jpeg(data.tobytes(), strict=True, **kw)
    except ValueError as exc:
        try:  # a JPEG that decodes only when warnings are ignored is corrupt
            simplejpeg.decode_jpeg(data.tobytes(), strict=False, **kw)
        except ValueError:
            return ""  # not a layout this check reads (e.g. CMYK): OpenCV decides
        return " ".join(str(exc).split())[:80]
    return ""


def _png_corrupt(path: Path) -> str:
    """Pillow's complaint about a PNG's chunks (CRC, truncation; '' if none), read without decoding pixels.

    libpng, under OpenCV, prints its own errors to stderr for such a file, and some
    damaged headers cost it seconds; this check is silent and reads the file once.
    """
    from PIL import Image  # noqa: PLC0415

    try:
        with Image.open(path) as im:
            im.verify()
    except Exception as exc:  # noqa: BLE001 - any complaint means a damaged file
        return " ".join(str(exc).split())[:80] or type(exc).__name__
    return ""


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
    # libjpeg decodes a truncated or corrupt JPEG into a partly grey image with only a
    # warning; such an image would give wrong features, so it is refused here
    if is_jpeg and _jpeg_truncated(data):
        return None, "is a truncated JPEG (no end-of-image marker); re-copy or re-download it"
    if is_jpeg:
        why = _jpeg_corrupt(data)
        if why:
            return None, f"is a corrupt JPEG ({why}); re-copy or re-download it"
    if data[:8].tobytes() == b"\x89PNG\r\n\x1a\n":
        why = _png_corrupt(path)
        if why:
            return None, f"is a corrupt PNG ({why}); re-copy or re-download it"
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        return None, f"cannot be decoded ({' '.join(str(exc).split())[-80:]})"
    if img is None:
        return None, "is not an image OpenCV can decode (corrupt, truncated or not an image)"
    if img.dtype == np.uint16:
        img = (img / 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = cv2.normalize(img.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if min(img.shape[:2]) < MIN_SIDE:
        return None, f"is too small ({img.shape[1]}x{img.shape[0]} pixels)"
    return img, ""


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(w, h)`` from the file header (Pillow), or None."""
    got = _header(path)
    return None if got is None else got[0]


def _header(path: str | os.PathLike) -> tuple[tuple[int, int], int] | None:
    """``((w, h), EXIF orientation)`` from the file header (Pillow; orientation 1 where there is none), or None."""
    try:
        from PIL import Image  # noqa: PLC0415

        Image.MAX_IMAGE_PIXELS = None  # the size is judged by check_headers, not by a Pillow warning
        with Image.open(path) as im:
            return (int(im.size[0]), int(im.size[1])), _orientation(im)
    except Exception:  # noqa: BLE001 - any failure means "unknown"
        return None


def header_exif(im: Any) -> Any:
    """An open image's EXIF (Pillow's ``Image.Exif``, empty where there is none), without decoding its pixels.

    Pillow's ``getexif`` of a PNG decodes the whole image to look for an eXIf chunk after the pixel data: a 140 kB
    PNG of 12000×12000 pixels cost 0.4 s and 137 MB there, before its size could be judged. A PNG's eXIf chunk
    comes before the pixels (PNG 3rd edition), where opening the file has already read it.
    """
    from PIL import Image  # noqa: PLC0415

    if im.format != "PNG":
        return im.getexif()
    exif = Image.Exif()
    raw = im.info.get("exif")
    if raw:
        exif.load(raw)
    return exif


def _orientation(im: Any) -> int:
    """An open image's EXIF orientation (1 where there is none or it cannot be read), without decoding its pixels."""
    try:
        return int(header_exif(im).get(0x0112, 1) or 1)
    except Exception:  # noqa: BLE001 - an unreadable EXIF block is no orientation
        return 1


def check_headers(folder: Path, names: list[str], say_orientation: bool = True
                  ) -> tuple[dict[str, tuple[int, int]], dict[str, str]]:
    """Sizes from the headers of ``names``, and the reason for each image left out.

    Decodes nothing, so a header that claims 60000×60000 pixels costs nothing. Images with an EXIF orientation
    tag are named in one warning (``say_orientation``): their stored pixels are used, as COLMAP uses them.

    Returns:
        ``{name: (w, h)}`` of the usable images and ``{name: reason}`` of the others.
    """
    sizes: dict[str, tuple[int, int]] = {}
    bad: dict[str, str] = {}
    turned: dict[str, int] = {}
    for n in names:  # one header read per image
        path = Path(folder) / n
        try:
            if path.stat().st_size == 0:
                bad[n] = "is empty (0 bytes)"
                continue
        except OSError as exc:
            bad[n] = f"cannot be read ({exc.strerror or exc})"
            continue
        got = _header(path)
        wh = None if got is None else got[0]
        if got is not None and got[1] != 1:
            turned[n] = got[1]
        if wh is None:
            bad[n] = "is not an image this program can read (corrupt, truncated or not an image)"
        elif wh[0] * wh[1] > MAX_PIXELS:
            bad[n] = (f"claims {wh[0]}x{wh[1]} pixels in its header, more than {MAX_PIXELS // 1_000_000} Mpx; "
                      "a damaged file, or resize it")
        elif min(wh) < MIN_SIDE:
            bad[n] = f"is too small ({wh[0]}x{wh[1]} pixels)"
        else:
            sizes[n] = wh
    if turned and say_orientation:  # COLMAP reads the stored pixels too; a K or truth for the turned picture would not fit
        n0 = next(iter(turned))
        logger.warning("%d image(s) carry an EXIF orientation tag (e.g. %s: %d); their pixels are used as stored, as "
                       "COLMAP uses them, so their K and true cameras must be for the stored orientation (rotate the "
                       "files themselves to change it)", len(turned), n0, turned[n0])
    return sizes, bad


def ends_crc(path: Path, head: int = 1 << 18, tail: int = 1 << 16) -> str:
    """CRC-32 of a file's first 256 kB and last 64 kB: with its size and time, what tells an image from another one
    put in its place (re-copied with its time kept) without reading whole photos on every run."""
    with open(path, "rb") as f:
        crc = zlib.crc32(f.read(head))
        size = f.seek(0, os.SEEK_END)
        if size > head:
            f.seek(max(head, size - tail))
            crc = zlib.crc32(f.read(tail), crc)
    return f"{crc & 0xFFFFFFFF:08x}"
