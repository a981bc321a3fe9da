"""Bundler v0.3 files (``bundle.out``; 1DSfM's ``gt_bundle.out``): cameras, in the project's convention.

Layout (Bundler's documentation; Theia's ``ReadBundlerFiles`` reads it the same way): ``# Bundle
file v0.3``; ``<num_cameras> <num_points>``; per camera ``f k1 k2``, 3 rows of R, then t; then
the points (position, colour, view list), which are not read. R is world-to-camera in Bundler's
frame, whose camera looks down **−z** (y up); this project's (COLMAP/OpenCV) looks down +z. With
``F = diag(1, −1, −1)``: ``R_cv = F R_bundler``, ``t_cv = F t_bundler``. A camera with f <= 0
(or an all-zero R) was not reconstructed. Camera k is image k of the ``list.txt`` beside it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.atomic import atomic_open
from pipeline.core.errors import InputFileError
from pipeline.io.common import line_numbers as _numbers
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL, OneWarning, projected_or_input_error

__all__ = ["BUNDLER_TO_CV", "read_bundler", "write_bundler"]

#: diag(1, −1, −1): Bundler (camera looks down −z, y up) ↔ OpenCV/COLMAP (+z, y down).
BUNDLER_TO_CV = np.diag([1.0, -1.0, -1.0])


def _bundle_cameras(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the header and the camera lines of a Bundler file; the points after them (most of
    a published file, hundreds of MB) are neither decoded nor kept."""
    if not path.is_file():
        raise InputFileError(f"1DSfM bundle file {path} does not exist")
    body: list[tuple[int, list[str]]] = []
    need = 1
    try:
        with open(path, encoding="utf-8-sig") as fh:
            for lineno, line in enumerate(fh, 1):
                parts = line.split()
                if not parts or parts[0].startswith("#"):
                    continue
                body.append((lineno, parts))
                if len(body) == 1:
                    if len(parts) != 2:
                        raise InputFileError(f"{path}:{lineno}: expected '<num_cameras> <num_points>'")
                    need = 1 + 5 * max(0, _numbers(path, lineno, parts, int)[0])
                if len(body) >= need:
                    break
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path} is not a readable text file ({exc.__class__.__name__})") from None
    return body


def read_bundler(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL, *,
                 _near: OneWarning | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read the cameras of a Bundler v0.3 file, converted to cam_from_world OpenCV convention.

    Its near-rotations are projected with one warning for the file, or with ``_near``'s one warning for a dataset
    of several files (1DSfM's).

    Returns:
        R: (K, 3, 3) ``F R_bundler`` (identity where unregistered), t: (K, 3) ``F t_bundler``,
        f: (K,) focal lengths, registered: (K,) bool (False for f <= 0 or an all-zero R).

    Raises:
        InputFileError: missing file, bad header or counts, truncated camera block, a
            registered rotation far from SO(3) (one line naming the file).
    """
    path = Path(path)
    body = _bundle_cameras(path)
    if not body:
        raise InputFileError(f"{path}: empty Bundler file")
    lineno, head = body[0]
    n_cam = _numbers(path, lineno, head, int)[0]
    if n_cam < 0 or len(body) < 1 + 5 * n_cam:
        raise InputFileError(f"{path}: header announces {n_cam} cameras but the file has "
                             f"{(len(body) - 1) // 5} complete camera blocks")
    rows = []
    for k in range(n_cam):
        blk = body[1 + 5 * k: 6 + 5 * k]
        for ln, parts in blk:
            if len(parts) != 3:
                raise InputFileError(f"{path}:{ln}: camera {k}: expected 3 numbers, got {len(parts)}")
        rows.append([x for ln, parts in blk for x in _numbers(path, ln, parts)])
    a = np.array(rows, dtype=np.float64).reshape(n_cam, 15)
    f = a[:, 0]
    Rb = a[:, 3:12].reshape(n_cam, 3, 3)
    tb = a[:, 12:15]
    registered = (f > 0) & (np.abs(Rb).sum(axis=(1, 2)) > 0)  # Bundler (and Theia's reader): f <= 0 = not reconstructed
    R = np.broadcast_to(np.eye(3), (n_cam, 3, 3)).copy()
    if registered.any():
        labels = [f"camera {k}" for k in np.flatnonzero(registered)]
        P = projected_or_input_error(Rb[registered], rotation_tol, what="camera rotation", source=str(path),
                                     labels=labels) if _near is None else \
            _near.rotations(Rb[registered], "camera rotation", labels, source=path)
        R[registered] = BUNDLER_TO_CV @ P
    t = np.where(registered[:, None], tb @ BUNDLER_TO_CV.T, 0.0)
    return R, t, f, registered


def write_bundler(path: str | os.PathLike, R: np.ndarray, t: np.ndarray, f: np.ndarray,
                  registered: np.ndarray | None = None) -> Path:
    """Write cameras (OpenCV cam_from_world R, t) as a Bundler v0.3 file with no points.

    Unregistered cameras are written as all zeros (f = 0, R = 0, t = 0).
    """
    R = np.asarray(R, float)
    K = R.shape[0]
    registered = np.ones(K, bool) if registered is None else np.asarray(registered, bool)
    path = Path(path)
    with atomic_open(path) as fh:
        fh.write("# Bundle file v0.3\n")
        fh.write(f"{K} 0\n")
        for k in range(K):
            if registered[k]:
                Rb, tb, fk = BUNDLER_TO_CV @ R[k], BUNDLER_TO_CV @ t[k], f[k]
            else:
                Rb, tb, fk = np.zeros((3, 3)), np.zeros(3), 0.0
            fh.write(f"{fk:.17g} 0 0\n")
            for row in Rb:
                fh.write(" ".join(f"{x:.17g}" for x in row) + "\n")
            fh.write(" ".join(f"{x:.17g}" for x in tb) + "\n")
    return path
