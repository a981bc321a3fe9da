"""Reference cameras to evaluate against, from every supported source.

All readers return a :class:`Reference` with cam_from_world rotations:

============================  ====================================================
source                        recognised by
============================  ====================================================
rotations file                text, 10 fields a line (``pipeline.io.rotations``)
rendered-scene cameras file   text, 17 fields a line: ``name fx fy cx cy r11 … r33
                              t1 t2 t3`` (cam_from_world ``x = R X + t``)
Middlebury ``*_par.txt``      text, 22 fields a line: ``name k11 … k33 r11 … r33
                              t1 t2 t3``, projection ``K [R | t]``, R cam_from_world;
                              an optional first line holds the camera count
``.mat`` file                 ``Rgt`` of either layout of :mod:`pipeline.io.mat`;
                              cameras with an all-zero block are left out
Strecha ``gt_dense_cameras/``  a folder of ``NNNN.jpg.camera`` files (or its
                              parent); each holds K (3 rows), distortion (1 row),
                              R = **world_from_cam** (3 rows), centre C, image size.
                              The camera name is the image file name ``NNNN.jpg``
COLMAP model folder           ``cameras.bin``/``images.bin`` (or ``.txt``); names
                              are ``image.name``, rotations
                              ``image.cam_from_world().rotation.matrix()``
============================  ====================================================
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import atomic_open
from pipeline.core.errors import InputFileError
from pipeline.io.rotations import read_rotations

logger = logging.getLogger(__name__)

__all__ = ["Reference", "read_reference", "read_cameras_file", "write_cameras_file", "read_strecha", "read_middlebury", "read_colmap_model"]

# Text references are written with a few digits; accept them as rotations up to
# this tolerance and project them onto SO(3).
REF_ROTATION_TOL = 1e-5


@dataclass
class Reference:
    """Reference cameras.

    Attributes:
        names: N camera (image) names.
        R: (N, 3, 3) cam_from_world rotations.
        K: (N, 3, 3) intrinsics, when the source has them.
        centers: (N, 3) camera centres in world coordinates, when known.
        kind: the source format ("rotations", "cameras", "middlebury", "mat",
            "strecha", "colmap").
    """

    names: list[str]
    R: np.ndarray
    K: np.ndarray | None = None
    centers: np.ndarray | None = None
    kind: str = ""


def _clean_rotations(path: Path, names: list[str], R: np.ndarray, what: str = "R") -> np.ndarray:
    ok = so3.is_rotation(R, REF_ROTATION_TOL)
    if not np.all(ok):
        k = int(np.flatnonzero(~ok)[0])
        raise InputFileError(
            f"{path}: {what} of camera {names[k]!r} is not a rotation "
            f"(det={np.linalg.det(np.nan_to_num(R[k])):.6g}); check the file's column order"
        )
    return so3.project_to_so3(R)


def _check_unique(path: Path, names: list[str]) -> None:
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputFileError(f"{path}: camera names repeat: {dup[:5]}")


def _read_table(path: Path, n_fields: int, layout: str, allow_count_line: bool = False) -> tuple[list[str], np.ndarray]:
    """Rows of ``name v1 … v_{n_fields−1}``; ``#`` comments and blank lines skipped."""
    names: list[str] = []
    rows: list[list[float]] = []
    with open(path) as f:
        first = True
        for lineno, line in enumerate(f, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            if first and allow_count_line and len(parts) == 1 and parts[0].isdigit():
                first = False
                continue
            first = False
            if len(parts) != n_fields:
                raise InputFileError(f"{path}:{lineno}: expected '{layout}' ({n_fields} fields), got {len(parts)}")
            try:
                rows.append([float(x) for x in parts[1:]])
            except ValueError:
                raise InputFileError(f"{path}:{lineno}: every field after the name must be a number") from None
            names.append(parts[0])
    if not names:
        raise InputFileError(f"{path} holds no cameras")
    _check_unique(path, names)
    vals = np.array(rows)
    if not np.all(np.isfinite(vals)):
        raise InputFileError(f"{path}: NaN or inf values")
    return names, vals


def read_cameras_file(path: str | os.PathLike) -> Reference:
    """Read a rendered-scene cameras file: ``name fx fy cx cy r11 … r33 t1 t2 t3`` per line.

    Returns:
        Reference with K (zero skew), cam_from_world R and centres ``C = −Rᵀ t``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"cameras file {path} does not exist")
    names, v = _read_table(path, 17, "name fx fy cx cy r11 ... r33 t1 t2 t3")
    n = len(names)
    K = np.zeros((n, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = v[:, 0], v[:, 1], v[:, 2], v[:, 3], 1.0
    R = _clean_rotations(path, names, v[:, 4:13].reshape(n, 3, 3))
    t = v[:, 13:16]
    C = -np.einsum("nba,nb->na", R, t)
    return Reference(names, R, K, C, "cameras")


def write_cameras_file(path: str | os.PathLike, names: list[str], K: np.ndarray, R: np.ndarray, t: np.ndarray) -> Path:
    """Write a rendered-scene cameras file atomically (skew of K is not stored).

    Args:
        path: output file.
        names: N image names (no whitespace).
        K: (N, 3, 3) or (3, 3) intrinsics.
        R: (N, 3, 3) cam_from_world rotations.
        t: (N, 3) cam_from_world translations (``x = R X + t``).
    """
    n = len(names)
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (n, 3, 3))
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if R.shape != (n, 3, 3) or t.shape != (n, 3):
        raise ValueError(f"R.shape={R.shape}, t.shape={t.shape} but expected ({n}, 3, 3) and ({n}, 3)")
    bad = [x for x in names if not x or any(c.isspace() for c in x)]
    if bad:
        raise ValueError(f"camera names may not be empty or contain whitespace: {bad[:3]}")
    with atomic_open(path) as f:
        f.write("# name fx fy cx cy r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3\n")
        f.write("# R, t: cam_from_world (x_cam = R X + t); K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]\n")
        for k, name in enumerate(names):
            vals = [K[k, 0, 0], K[k, 1, 1], K[k, 0, 2], K[k, 1, 2], *R[k].ravel(), *t[k]]
            f.write(name + " " + " ".join(f"{x:.17g}" for x in vals) + "\n")
    return Path(path)


def read_middlebury(path: str | os.PathLike) -> Reference:
    """Read a Middlebury ``*_par.txt``: ``name k11 … k33 r11 … r33 t1 t2 t3`` (R cam_from_world)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"Middlebury parameter file {path} does not exist")
    names, v = _read_table(path, 22, "imgname k11 ... k33 r11 ... r33 t1 t2 t3", allow_count_line=True)
    n = len(names)
    K = v[:, 0:9].reshape(n, 3, 3)
    R = _clean_rotations(path, names, v[:, 9:18].reshape(n, 3, 3))
    t = v[:, 18:21]
    return Reference(names, R, K, -np.einsum("nba,nb->na", R, t), "middlebury")


def read_strecha(path: str | os.PathLike) -> Reference:
    """Read a Strecha ``gt_dense_cameras`` folder (or the dataset folder that holds it).

    Each ``NAME.camera`` file holds 26 numbers: K (3×3), distortion (3), R (3×3,
    world_from_cam), centre C (3), image size (2). The returned rotation is
    ``Rᵀ`` (cam_from_world) and the name is ``NAME`` (the image file name).
    """
    path = Path(path)
    if (path / "gt_dense_cameras").is_dir():
        path = path / "gt_dense_cameras"
    files = sorted(path.glob("*.camera"))
    if not files:
        raise InputFileError(f"{path}: no *.camera files; expected Strecha's gt_dense_cameras folder")
    names, Ks, Rs, Cs = [], [], [], []
    for fp in files:
        try:
            vals = np.array(fp.read_text().split(), dtype=float)
        except ValueError:
            raise InputFileError(f"{fp}: every entry must be a number") from None
        if vals.size != 26:
            raise InputFileError(f"{fp}: expected 26 numbers (K 3×3, distortion 3, R 3×3, C 3, size 2), got {vals.size}")
        names.append(fp.name[: -len(".camera")])
        Ks.append(vals[0:9].reshape(3, 3))
        Rs.append(vals[12:21].reshape(3, 3).T)  # world_from_cam → cam_from_world
        Cs.append(vals[21:24])
    R = _clean_rotations(path, names, np.array(Rs))
    return Reference(names, R, np.array(Ks), np.array(Cs), "strecha")


def read_colmap_model(path: str | os.PathLike) -> Reference:
    """Read the registered images of a COLMAP model folder with pycolmap.

    Names are ``image.name``; rotations ``image.cam_from_world().rotation.matrix()``.
    """
    path = Path(path)
    import pycolmap  # lazy: pycolmap is heavy and only this reader needs it

    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError
        raise InputFileError(f"{path}: pycolmap cannot read this model folder ({exc})") from exc
    names, Rs, Ks, Cs = [], [], [], []
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        if not image.has_pose:
            continue
        names.append(image.name)
        Rs.append(np.asarray(image.cam_from_world().rotation.matrix()))
        Ks.append(np.asarray(rec.cameras[image.camera_id].calibration_matrix()))
        Cs.append(np.asarray(image.projection_center()))
    if not names:
        raise InputFileError(f"{path}: the COLMAP model has no registered image")
    _check_unique(path, names)
    R = _clean_rotations(path, names, np.array(Rs))
    return Reference(names, R, np.array(Ks), np.array(Cs), "colmap")


def _first_row_fields(path: Path) -> int:
    with open(path) as f:
        for line in f:
            parts = line.split("#", 1)[0].split()
            if parts and not (len(parts) == 1 and parts[0].isdigit()):
                return len(parts)
    return 0


def read_reference(path: str | os.PathLike) -> Reference:
    """Read reference cameras from any supported source (see the module docstring).

    Raises:
        InputFileError: a missing path, an unrecognised format, or malformed content.
    """
    path = Path(path)
    from pipeline.io.onedsfm import is_1dsfm_folder, read_1dsfm_reference  # noqa: PLC0415 - issue 15 formats

    if is_1dsfm_folder(path) or path.name == "gt_bundle.out":
        return Reference(*read_1dsfm_reference(path), kind="1dsfm")
    if path.is_dir():
        if any((path / f"images{ext}").is_file() for ext in (".bin", ".txt")):
            return read_colmap_model(path)
        if any((path / "0" / f"images{ext}").is_file() for ext in (".bin", ".txt")):
            logger.info("%s holds COLMAP model 0; reading %s", path, path / "0")
            return read_colmap_model(path / "0")
        if (path / "gt_dense_cameras").is_dir() or any(path.glob("*.camera")):
            return read_strecha(path)
        raise InputFileError(
            f"{path}: folder is neither a COLMAP model (images.bin/.txt; pass the model folder, "
            "e.g. sparse/0) nor a Strecha gt_dense_cameras folder (*.camera files)"
        )
    if not path.is_file():
        raise InputFileError(f"reference {path} does not exist")
    if path.suffix.lower() == ".mat":
        from pipeline.io.mat import read_mat

        data = read_mat(path)
        if data.R_gt is None:
            raise InputFileError(f"{path} has no ground truth (no Rgt variable)")
        keep = np.flatnonzero(data.gt_mask)
        return Reference([data.vg.names[k] for k in keep], data.R_gt[keep], kind="mat")
    try:
        nf = _first_row_fields(path)
    except UnicodeDecodeError:
        raise InputFileError(f"{path} is not a text file; expected a rotations, cameras or *_par.txt file, a .mat file or a folder") from None
    if nf in (10, 5):  # ours, or GLOMAP's NAME QW QX QY QZ
        names, R = read_rotations(path, tol=REF_ROTATION_TOL)
        return Reference(names, so3.project_to_so3(R), kind="rotations")
    if nf == 17:
        return read_cameras_file(path)
    if nf == 22:
        return read_middlebury(path)
    raise InputFileError(
        f"{path}: unrecognised reference with {nf} fields per line; expected 10 (rotations: name r11..r33), "
        "17 (cameras: name fx fy cx cy r11..r33 t1 t2 t3) or 22 (Middlebury: name k11..k33 r11..r33 t1 t2 t3)"
    )
