"""Readers of true cameras, from every supported source; one entry: :func:`read_reference`.

All readers return a :class:`pipeline.reference.types.Reference` with cam_from_world rotations:

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

Every malformed file gives one :class:`InputFileError` line that names the file:
not UTF-8, wrong field counts, values that are not numbers or not finite, a
matrix that is not a rotation, a K that is not a pinhole matrix (NaN, a focal
length of 0), repeated names.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import atomic_open
from pipeline.core.errors import InputFileError
from pipeline.core.names import quote_name, split_fields
from pipeline.reference.types import Reference

logger = logging.getLogger(__name__)

__all__ = ["read_reference", "read_cameras_file", "write_cameras_file", "read_strecha", "read_middlebury",
           "read_colmap_model", "REF_ROTATION_TOL"]

# Text references are written with a few digits; accept them as rotations up to
# this tolerance and project them onto SO(3).
REF_ROTATION_TOL = 1e-5
MAX_TEXT_BYTES = 256 << 20
COLMAP_TIMEOUT_S = 20.0  # + 1 s per 2 MB of model: reading a COLMAP model in a child process  # a reference of a million cameras is ~200 MB of text
ROTATIONS_LAYOUT = "name r11 ... r33"
CAMERAS_LAYOUT = "name fx fy cx cy r11 ... r33 t1 t2 t3"
MIDDLEBURY_LAYOUT = "imgname k11 ... k33 r11 ... r33 t1 t2 t3"


def _check_K(path: Path, names: list[str], K: np.ndarray) -> np.ndarray:
    from pipeline.frontend.intrinsics import check_K  # noqa: PLC0415 - the one K check of the pipeline

    for k, n in enumerate(names):
        check_K(K[k], f"{path} (camera {n!r})")
    return K


def _clean_rotations(path: Path, names: list[str], R: np.ndarray, what: str = "R") -> np.ndarray:
    """``R`` projected onto SO(3) if every matrix is a rotation up to :data:`REF_ROTATION_TOL`."""
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


def _read_text(path: Path, what: str) -> str:
    """The file as UTF-8 text; one-line errors for a missing, huge, unreadable or binary file."""
    if not path.is_file():
        raise InputFileError(f"{what} {path} does not exist")
    try:
        size = path.stat().st_size
        if size > MAX_TEXT_BYTES:
            raise InputFileError(f"{path} is {size >> 20} MB, more than a reference file holds; check the path")
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path} is not a text file (not UTF-8: {exc.reason} at byte {exc.start}); expected a "
                             "rotations, cameras or *_par.txt file, a .mat file or a folder") from None
    except OSError as exc:
        raise InputFileError(f"{path} cannot be read ({exc.strerror or exc})") from None


def _rows(text: str, path: Path | str = "line") -> list[tuple[int, list[str]]]:
    """``(line number, fields)`` of the non-blank lines; ``#`` starts a comment; ``"a name"`` is one field."""
    out = []
    for lineno, line in enumerate(text.split("\n"), 1):
        parts = split_fields(line, f"{path}:{lineno}")
        if parts:
            out.append((lineno, parts))
    return out


def _read_table(path: Path, text: str, n_fields: int, layout: str, allow_count_line: bool = False
                ) -> tuple[list[str], np.ndarray]:
    """Rows of ``name v1 … v_{n_fields−1}`` as names and an (N, n_fields − 1) finite array."""
    rows = _rows(text, path)
    if allow_count_line and rows and len(rows[0][1]) == 1 and rows[0][1][0].isdigit():
        rows = rows[1:]
    names: list[str] = []
    vals: list[list[float]] = []
    for lineno, parts in rows:
        if len(parts) != n_fields:
            raise InputFileError(f"{path}:{lineno}: expected '{layout}' ({n_fields} fields), got {len(parts)}")
        try:
            vals.append([float(x) for x in parts[1:]])
        except ValueError:
            raise InputFileError(f"{path}:{lineno}: every field after the name must be a number") from None
        if not parts[0]:
            raise InputFileError(f"{path}:{lineno}: empty camera name")
        names.append(parts[0])
    if not names:
        raise InputFileError(f"{path} holds no cameras")
    _check_unique(path, names)
    v = np.array(vals)
    if not np.all(np.isfinite(v)):
        lineno = rows[int(np.flatnonzero(~np.all(np.isfinite(v), axis=1))[0])][0]
        raise InputFileError(f"{path}:{lineno}: NaN or inf values")
    return names, v


def _centers(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -np.einsum("nba,nb->na", R, t)


def _rotations_text(path: Path, text: str) -> Reference:
    names, v = _read_table(path, text, 10, ROTATIONS_LAYOUT)
    return Reference(names, _clean_rotations(path, names, v.reshape(-1, 3, 3)), source="rotations")


def _glomap_text(path: Path, text: str) -> Reference:
    """GLOMAP's rotation file: ``NAME QW QX QY QZ`` (cam_from_world)."""
    from pipeline.io.glomap import read_glomap_rotations  # noqa: PLC0415

    names, R = read_glomap_rotations(path)
    return Reference(names, R, source="glomap")


def _cameras_text(path: Path, text: str) -> Reference:
    names, v = _read_table(path, text, 17, CAMERAS_LAYOUT)
    n = len(names)
    K = np.zeros((n, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = v[:, 0], v[:, 1], v[:, 2], v[:, 3], 1.0
    R = _clean_rotations(path, names, v[:, 4:13].reshape(n, 3, 3))
    _check_K(path, names, K)
    return Reference(names, R, K=K, centers=_centers(R, v[:, 13:16]), source="cameras")


def _middlebury_text(path: Path, text: str) -> Reference:
    names, v = _read_table(path, text, 22, MIDDLEBURY_LAYOUT, allow_count_line=True)
    n = len(names)
    K = v[:, 0:9].reshape(n, 3, 3)
    R = _clean_rotations(path, names, v[:, 9:18].reshape(n, 3, 3))
    _check_K(path, names, K)
    return Reference(names, R, K=K, centers=_centers(R, v[:, 18:21]), source="middlebury")


def read_cameras_file(path: str | os.PathLike) -> Reference:
    """Read a rendered-scene cameras file: ``name fx fy cx cy r11 … r33 t1 t2 t3`` per line.

    Returns:
        Reference with K (zero skew), cam_from_world R and centres ``C = −Rᵀ t``.
    """
    path = Path(path)
    return _cameras_text(path, _read_text(path, "cameras file"))


def write_cameras_file(path: str | os.PathLike, names: list[str], K: np.ndarray, R: np.ndarray, t: np.ndarray) -> Path:
    """Write a rendered-scene cameras file atomically (skew of K is not stored).

    Args:
        path: output file.
        names: N image names (quoted in the file when they hold whitespace).
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
    if not all(names):
        raise ValueError("camera names may not be empty")
    with atomic_open(path) as f:
        f.write("# name fx fy cx cy r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3\n")
        f.write("# R, t: cam_from_world (x_cam = R X + t); K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]\n")
        for k, name in enumerate(names):
            vals = [K[k, 0, 0], K[k, 1, 1], K[k, 0, 2], K[k, 1, 2], *R[k].ravel(), *t[k]]
            f.write(quote_name(name) + " " + " ".join(f"{x:.17g}" for x in vals) + "\n")
    return Path(path)


def read_middlebury(path: str | os.PathLike) -> Reference:
    """Read a Middlebury ``*_par.txt``: ``name k11 … k33 r11 … r33 t1 t2 t3`` (R cam_from_world)."""
    path = Path(path)
    return _middlebury_text(path, _read_text(path, "Middlebury parameter file"))


def read_strecha(path: str | os.PathLike) -> Reference:
    """Read a Strecha ``gt_dense_cameras`` folder (or the dataset folder that holds it).

    Each ``NAME.camera`` file holds 26 numbers: K (3×3), distortion (3), R (3×3,
    world_from_cam), centre C (3), image size (2). The returned rotation is
    ``Rᵀ`` (cam_from_world) and the name is ``NAME`` (the image file name).
    """
    path = Path(path)
    if (path / "gt_dense_cameras").is_dir():
        path = path / "gt_dense_cameras"
    files = sorted(p for p in path.glob("*.camera") if p.is_file())
    if not files:
        raise InputFileError(f"{path}: no *.camera files; expected Strecha's gt_dense_cameras folder")
    names, Ks, Rs, Cs = [], [], [], []
    for fp in files:
        fields = _read_text(fp, "camera file").split()
        try:
            vals = np.array(fields, dtype=float)
        except ValueError:
            raise InputFileError(f"{fp}: every entry must be a number") from None
        if vals.size != 26:
            raise InputFileError(f"{fp}: expected 26 numbers (K 3×3, distortion 3, R 3×3, C 3, size 2), got {vals.size}")
        if not np.all(np.isfinite(vals)):
            raise InputFileError(f"{fp}: NaN or inf values")
        names.append(fp.name[: -len(".camera")])
        Ks.append(vals[0:9].reshape(3, 3))
        Rs.append(vals[12:21].reshape(3, 3).T)  # world_from_cam → cam_from_world
        Cs.append(vals[21:24])
        _check_K(fp, names[-1:], Ks[-1:])
        _clean_rotations(fp, names[-1:], Rs[-1][None])  # names the file of a bad R
    R = _clean_rotations(path, names, np.array(Rs))
    return Reference(names, R, K=np.array(Ks), centers=np.array(Cs), source="strecha")


# pycolmap's model readers hang on some truncated files (images.bin, frames.bin) and allocate
# gigabytes on others (points3D.bin), so a user's model is read in a child process with a time
# and a memory limit (pipeline.core.sandbox); it sends back plain arrays.
def _colmap_arrays(path: str) -> dict[str, Any]:
    """The registered images of the COLMAP model in ``path`` as plain arrays (runs in the sandbox)."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import pycolmap  # noqa: PLC0415

    pycolmap.logging.minloglevel = 2
    rec = pycolmap.Reconstruction(path)
    names, Rs, Ks, Cs = [], [], [], []
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        if not image.has_pose:
            continue
        names.append(str(image.name))
        Rs.append(np.asarray(image.cam_from_world().rotation.matrix()))
        Ks.append(np.asarray(rec.cameras[image.camera_id].calibration_matrix()))
        Cs.append(np.asarray(image.projection_center()))
    return {"names": names, "R": np.array(Rs, dtype=float).reshape(-1, 3, 3),
            "K": np.array(Ks, dtype=float).reshape(-1, 3, 3), "C": np.array(Cs, dtype=float).reshape(-1, 3)}


def read_colmap_model(path: str | os.PathLike) -> Reference:
    """Read the registered images of a COLMAP model folder with pycolmap (in a sandboxed child process).

    Names are ``image.name``; rotations ``image.cam_from_world().rotation.matrix()``.
    """
    from pipeline.core.sandbox import SandboxError, run_limited  # noqa: PLC0415

    path = Path(path)
    if (path / "images.bin").is_file():
        from pipeline.reference.colmap_binary import check_binary_model  # noqa: PLC0415

        check_binary_model(path)  # pycolmap trusts the counts of a damaged binary file
    size = sum(p.stat().st_size for p in path.iterdir() if p.is_file()) if path.is_dir() else 0
    try:
        arr = run_limited(_colmap_arrays, str(path), timeout=COLMAP_TIMEOUT_S + size / 2e6,
                          memory_bytes=(2 << 30) + 20 * size, preload=("numpy", "pycolmap", __name__))
    except SandboxError as exc:
        why = str(exc)
        if "did not finish" in why:
            why += "; a file of the model is truncated or damaged"
        raise InputFileError(f"{path}: pycolmap cannot read this model folder ({why})") from None
    names, Rs, Ks, C = arr["names"], arr["R"], arr["K"], arr["C"]
    if not names:
        raise InputFileError(f"{path}: the COLMAP model has no registered image")
    _check_unique(path, names)
    R = _clean_rotations(path, names, Rs)
    if not np.all(np.isfinite(C)):
        raise InputFileError(f"{path}: a camera centre is NaN or inf")
    return Reference(names, R, K=_check_K(path, names, Ks), centers=C, source="colmap")


def read_reference(path: str | os.PathLike) -> Reference:
    """Read reference cameras from any supported source (see the module docstring).

    Raises:
        InputFileError: a missing path, an unrecognised format, or malformed content.
    """
    path = Path(path)
    from pipeline.io.onedsfm import is_1dsfm_folder, read_1dsfm_reference  # noqa: PLC0415

    if is_1dsfm_folder(path) or path.name == "gt_bundle.out":
        names, R = read_1dsfm_reference(path)
        return Reference(names, R, source="1dsfm")
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
        from pipeline.io.mat import read_mat  # noqa: PLC0415

        data = read_mat(path)
        if data.R_gt is None:
            raise InputFileError(f"{path} has no ground truth (no Rgt variable)")
        keep = np.flatnonzero(data.gt_mask)
        return Reference([data.vg.names[k] for k in keep], data.R_gt[keep], source="mat")
    text = _read_text(path, "reference")
    rows = _rows(text, path)
    first = next((parts for _, parts in rows if not (len(parts) == 1 and parts[0].isdigit())), [])
    readers = {10: _rotations_text, 5: _glomap_text, 17: _cameras_text, 22: _middlebury_text}
    if len(first) not in readers:
        raise InputFileError(
            f"{path}: unrecognised reference with {len(first)} fields per line; expected 10 (rotations: "
            "name r11..r33), 5 (GLOMAP rotations: name qw qx qy qz), 17 (cameras: name fx fy cx cy r11..r33 t1 t2 t3) or 22 (Middlebury: name k11..k33 "
            "r11..r33 t1 t2 t3)")
    return readers[len(first)](path, text)
