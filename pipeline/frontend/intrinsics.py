"""The one resolver of camera intrinsics: every K the pipeline uses comes from here.

Intrinsics are taken, per image, from the first source that has them:

1. a file or folder given by the user (``--K``) or found in the image folder:
   ``K.txt`` (one 3×3 for all images); a per-image cameras file (``name fx fy cx cy
   [...]`` as the renderer writes); Middlebury ``*_par.txt``
   (``name k11..k33 r11..r33 t1 t2 t3``); a reference folder with K (Strecha
   ``gt_dense_cameras/``); or a camera file with lens distortion
   (:mod:`pipeline.frontend.distortion`: a COLMAP ``cameras.txt``/``.bin`` or model
   folder, an OpenCV K followed by its distortion coefficients, an OpenCV
   ``.yaml``/``.xml``), whose pinhole part is the K here and whose distortion the
   cameras stage applies (:func:`camera_models_for_names`). Without ``--K``,
   ``K.txt``, ``cameras.txt`` or a single ``*_par.txt`` inside the image folder is used;
2. the EXIF focal length (``pycolmap.infer_camera_from_image``, COLMAP's reader
   with its sensor database, else Pillow's ``FocalLengthIn35mmFilm``): a prior,
   which the cameras stage (:mod:`pipeline.frontend.camera_stage`) checks against
   the view graph;
3. otherwise ``f = 1.2·max(w, h)`` (COLMAP's default factor), a start value that the
   cameras stage replaces by a focal estimated from the view graph.

Every K is checked (finite, ``fx, fy > 0``, last row ``0 0 1``, invertible) when
it is read, before any image is processed. The source of each K is recorded.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import InputFileError
from pipeline.core.names import match_names, split_fields
from pipeline.frontend.distortion import CameraModel, is_camera_model_file, pinhole_K, read_camera_models

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_FOCAL_FACTOR", "parse_intrinsics_file", "check_K", "find_intrinsics_file", "exif_focal",
           "default_K", "read_intrinsics", "resolve_intrinsics", "intrinsics_for_names", "camera_models_for_names",
           "intrinsics_summary", "focal_summary"]

DEFAULT_FOCAL_FACTOR = 1.2
MAX_FILE_BYTES = 64 << 20


def check_K(K: np.ndarray, where: str | os.PathLike) -> np.ndarray:
    """``K`` as a (3, 3) float array if it is a usable pinhole matrix, else :class:`InputFileError`."""
    K = np.asarray(K, dtype=np.float64)
    ok = (K.shape == (3, 3) and np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0
          and abs(K[2, 2] - 1) < 1e-6 and np.allclose(K[2, :2], 0))
    if not ok:
        raise InputFileError(f"{where}: {np.round(K, 6).tolist()} is not a pinhole K "
                             "(finite, fx > 0, fy > 0, last row 0 0 1)")
    with np.errstate(all="ignore"):  # entries near the float limit overflow: singular for our purpose
        singular = not (abs(np.linalg.det(K)) >= 1e-12 * max(K[0, 0] * K[1, 1], 1e-300) and np.linalg.cond(K) <= 1e12)
    if singular:
        raise InputFileError(f"{where}: K {np.round(K, 6).tolist()} is singular; check its values")
    return K


def _read_text(path: Path) -> str:
    if path.stat().st_size > MAX_FILE_BYTES:
        raise InputFileError(f"{path} is {path.stat().st_size >> 20} MB; an intrinsics file is a few kB")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path} is not UTF-8 text ({exc.reason} at byte {exc.start}); "
                             "pass a K.txt (3x3) or a cameras file") from None


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
    rows = [(k, split_fields(ln, f"{path} line {k}")) for k, ln in enumerate(_read_text(path).splitlines(), 1)]
    rows = [(k, ln) for k, ln in rows if ln]
    try:
        nums: list[float] | None = [float(v) for _, ln in rows for v in ln]
    except ValueError:
        nums = None  # has names: a per-image file
    per_image = nums is None or (len(nums) != 9 and all(len(ln) in (1, 5, 17, 22) for _, ln in rows))
    if not per_image:
        if len(nums) != 9:  # type: ignore[arg-type]
            raise InputFileError(f"{path}: {len(nums)} numbers, but a K.txt holds exactly 9 (one 3x3 matrix)")  # type: ignore[arg-type]
        return check_K(np.array(nums).reshape(3, 3), path)
    out: dict[str, np.ndarray] = {}
    for k, ln in rows:
        if len(ln) == 1 and ln[0].isascii() and ln[0].isdigit():
            continue  # Middlebury's first line is the image count
        name, vals = ln[0], ln[1:]
        try:
            v = [float(x) for x in vals]
        except ValueError:
            raise InputFileError(f"{path} line {k}: expected 'name' followed by numbers, "
                                 f"got {' '.join(ln)[:80]!r}") from None
        if len(v) == 21:  # Middlebury: name k11..k33 r11..r33 t1 t2 t3
            K = np.array(v[:9]).reshape(3, 3)
        elif len(v) in (4, 16):  # cameras file: name fx fy cx cy [r11..r33 t1 t2 t3]
            K = np.array([[v[0], 0, v[2]], [0, v[1], v[3]], [0, 0, 1.0]])
        else:
            raise InputFileError(
                f"{path} line {k}: {len(v)} numbers after the name; expected 4 or 16 "
                "('name fx fy cx cy [r11..r33 t1 t2 t3]') or 21 (Middlebury 'name k11..k33 r11..r33 t1 t2 t3')")
        if not name:
            raise InputFileError(f"{path} line {k}: empty image name")
        if name in out:
            raise InputFileError(f"{path} line {k}: image {name!r} is listed twice")
        out[name] = check_K(K, f"{path} line {k}")
    if not out:
        raise InputFileError(f"{path} holds no camera; expected K.txt (3x3) or lines 'name fx fy cx cy ...'")
    return out


def find_intrinsics_file(folder: str | os.PathLike) -> Path | None:
    """``K.txt``, ``cameras.txt`` or the single ``*_par.txt`` in ``folder``, if present."""
    folder = Path(folder)
    for name in ("K.txt", "cameras.txt"):
        if (folder / name).is_file():
            return folder / name
    par = sorted(folder.glob("*_par.txt"))
    return par[0] if len(par) == 1 else None


def read_intrinsics(source: str | os.PathLike) -> np.ndarray | dict[str, np.ndarray]:
    """A shared (3, 3) K or ``{name: K}`` from a K file, a cameras file or a reference folder with K."""
    path = Path(source)
    if not path.exists():
        raise InputFileError(f"intrinsics file {path} does not exist; pass a K.txt (3x3) or a cameras file")
    if is_camera_model_file(path):  # COLMAP or OpenCV, with distortion: its pinhole part
        models = read_camera_models(path)
        if "*" in models:
            return check_K(pinhole_K(models["*"]), path)
        return {nm: check_K(pinhole_K(cam), f"{path} ({nm})") for nm, cam in models.items()}
    if path.is_file():
        return parse_intrinsics_file(path)
    from pipeline.reference.truth import read_reference  # noqa: PLC0415 - a folder of true cameras

    ref = read_reference(path)
    if getattr(ref, "K", None) is None:
        raise InputFileError(f"{path} holds no intrinsics; pass a K.txt (3x3) or a cameras file with K")
    Kref = np.asarray(ref.K, dtype=float)
    return {nm: check_K(Kref if Kref.ndim == 2 else Kref[k], f"{path} ({nm})") for k, nm in enumerate(ref.names)}


def intrinsics_for_names(parsed: np.ndarray | dict[str, np.ndarray], names: list[str], where: str | os.PathLike
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) K for ``names`` from :func:`read_intrinsics`'s result and an (N,) mask of those found."""
    n = len(names)
    if isinstance(parsed, np.ndarray):
        return np.broadcast_to(parsed, (n, 3, 3)).copy(), np.ones(n, bool)
    keys = list(parsed)
    idx = match_names(names, keys, what=str(where))
    K = np.zeros((n, 3, 3))
    found = idx >= 0
    if found.any():
        K[found] = np.stack([parsed[keys[i]] for i in idx[found]])
    return K, found


def camera_models_for_names(source: str | os.PathLike, names: list[str]) -> list[CameraModel | None]:
    """The camera model (with its distortion) of each of ``names`` from a COLMAP or OpenCV camera file.

    Returns:
        N models, None for the images the file does not name; all None when ``source``
        is a plain K file (no distortion).
    """
    if not is_camera_model_file(source):
        return [None] * len(names)
    models = read_camera_models(source)
    if "*" in models:
        return [models["*"]] * len(names)
    keys = list(models)
    idx = match_names(names, keys, what=str(source))
    return [models[keys[i]] if i >= 0 else None for i in idx]


def exif_focal(path: str | os.PathLike) -> float | None:
    """Focal length in pixels from the EXIF tags, or None."""
    try:
        import pycolmap  # noqa: PLC0415

        cam = pycolmap.infer_camera_from_image(str(path))
        if cam.has_prior_focal_length:
            return float(cam.mean_focal_length())
    except Exception:  # noqa: BLE001 - fall through to Pillow
        logger.debug("pycolmap could not read EXIF of %s", path, exc_info=True)
    try:
        from PIL import Image  # noqa: PLC0415

        from pipeline.frontend.images import header_exif  # noqa: PLC0415

        with Image.open(path) as im:
            exif = header_exif(im)  # not getexif: a PNG's would decode the whole image
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
    """Pinhole K with the principal point at the image centre, ((w − 1)/2, (h − 1)/2): pixel centres at integers.

    (w/2, h/2) would be the centre in COLMAP's convention (pixel centres at +0.5), half a pixel off in ours: a
    bias of about 0.5/f rad in every rotation that the refinement, which holds an unknown principal point at
    the image centre, cannot remove.
    """
    f = focal if focal is not None else DEFAULT_FOCAL_FACTOR * max(w, h)
    return np.array([[f, 0, (w - 1) / 2.0], [0, f, (h - 1) / 2.0], [0, 0, 1.0]])


def _check_principal_points(K: np.ndarray, sizes: np.ndarray, names: list[str], src: Path) -> None:
    """Refuse a K whose principal point lies outside its image: it was made for images of another size."""
    c, wh = K[:, :2, 2], np.asarray(sizes, float)
    bad = np.flatnonzero(np.any((c < 0) | (c > wh), axis=1))
    if bad.size:
        k = int(bad[0])
        raise InputFileError(
            f"{src} puts the principal point of {names[k]} at ({c[k, 0]:.1f}, {c[k, 1]:.1f}) px, outside its "
            f"{int(wh[k, 0])}×{int(wh[k, 1])} image ({bad.size} image(s) so): the K is for images of another size "
            "(e.g. the full-resolution ones); scale its first two rows by the images' scale")


def resolve_intrinsics(folder: Path, names: list[str], sizes: np.ndarray, K_path: Path | None = None,
                       parsed: np.ndarray | dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, list[str]]:
    """One K per image, from a file, EXIF or the default focal length.

    Args:
        folder: image folder.
        names: N image file names.
        sizes: (N, 2) image sizes (w, h).
        K_path: explicit intrinsics file or folder, or None to look for one in ``folder``.
        parsed: the already-read content of ``K_path`` (it is read here if None).
    Returns:
        K (N, 3, 3) and the source of each (``"file:<path>"``, ``"exif"``, ``"default"``).
    """
    src = Path(K_path) if K_path is not None else find_intrinsics_file(folder)
    if src is not None and parsed is None:
        parsed = read_intrinsics(src)
    if src is not None:
        logger.info("intrinsics from %s", src)
        K, found = intrinsics_for_names(parsed, names, src)
        if not found.any():
            raise InputFileError(f"{src} names none of the {len(names)} images of {folder} (e.g. {names[0]}): it is "
                                 "the intrinsics of other images; pass the file made for these, or none")
        _check_principal_points(K[found], sizes[found], [n for n, f in zip(names, found) if f], src)
    else:
        K, found = np.zeros((len(names), 3, 3)), np.zeros(len(names), bool)
    sources = [f"file:{src}" if f else "" for f in found]
    missing_default: list[str] = []
    for k in np.flatnonzero(~found):  # per image without a file entry: EXIF, else the default
        w, h = (int(v) for v in sizes[k])
        f = exif_focal(folder / names[k])
        K[k] = default_K(w, h, f)
        sources[k] = "exif" if f is not None else "default"
        if f is None:
            missing_default.append(names[k])
    if src is not None and not found.all():
        absent = [n for n, f in zip(names, found) if not f]
        logger.warning("%s has no intrinsics for %d image(s) (%s); using EXIF or the default focal length for them",
                       src, len(absent), ", ".join(absent[:5]) + (" ..." if len(absent) > 5 else ""))
    if missing_default:
        logger.warning(
            "no intrinsics file and no EXIF focal length for %d image(s) (%s): f = %.1f·max(w, h) is only a start "
            "value, which the cameras stage replaces by a focal estimated from the view graph (unless "
            "cameras.estimate_focal is off). Pass --K K.txt (3x3) or a cameras file for the most accurate rotations",
            len(missing_default), ", ".join(missing_default[:5]) + (" ..." if len(missing_default) > 5 else ""),
            DEFAULT_FOCAL_FACTOR)
    return K, sources


def intrinsics_summary(cams: Any) -> dict[str, Any]:
    """What metrics.json and the report say about the intrinsics: the focal used, where it came from, the distortion.

    ``cams``: the cameras stage's :class:`~pipeline.frontend.camera_stage.CameraSet`.

    Returns:
        ``{"focal": [{source, n_images, median_px, min_px, max_px}], "distortion": [{source,
        n_images, models}], "per_image": {name: {...}}, "estimates": [...]}``.
    """
    focal = [{"source": s} | v for s, v in focal_summary(cams.K, cams.K_source).items()]
    dist = []
    for s in sorted(set(cams.distortion_source)):
        idx = [k for k, d in enumerate(cams.distortion_source) if d == s]
        dist.append({"source": s, "n_images": len(idx), "models": sorted({cams.models[k].model for k in idx}),
                     "extra_params": sorted({cams.models[k].extra_params for k in idx})[:5]})
    per = {nm: {"focal_px": [float(cams.K[k, 0, 0]), float(cams.K[k, 1, 1])],
                "principal_point_px": [float(cams.K[k, 0, 2]), float(cams.K[k, 1, 2])], "source": cams.K_source[k],
                "camera": cams.models[k].as_dict(), "distortion_source": cams.distortion_source[k]}
           for k, nm in enumerate(cams.names)}
    groups = [{k: v for k, v in g.items() if k != "images"} | {"n_images": len(g.get("images", []))}
              for g in cams.estimate.get("groups", [])]
    for g in groups:
        if "focal" in g:
            g["focal"] = {k: v for k, v in g["focal"].items() if k not in ("grid", "cost")}
    return {"focal": focal, "distortion": dist, "per_image": per, "estimates": groups}


def focal_summary(K: np.ndarray, sources: list[str]) -> dict[str, Any]:
    """The focal used per source, for the record and the report."""
    out: dict[str, Any] = {}
    for s in sorted(set(sources)):
        f = K[[k for k, x in enumerate(sources) if x == s], 0, 0]
        out[s] = {"n_images": int(len(f)), "median_px": float(np.median(f)), "min_px": float(f.min()),
                  "max_px": float(f.max())}
    return out
