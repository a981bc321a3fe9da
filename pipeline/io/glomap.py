"""GLOMAP / COLMAP-global rotation and relative-pose text files.

Established from GLOMAP's source (``colmap/glomap`` ``glomap/io/pose_io.{h,cc}``, and the
same file after the merge into COLMAP, ``colmap/colmap`` ``src/glomap/io/pose_io.{h,cc}``):

* ``WriteGlobalRotation``: one line per registered image, ``IMAGE_NAME QW QX QY QZ``, the
  **cam_from_world** rotation (``image.CamFromWorld().rotation``), Eigen's coefficients
  written as ``coeffs()[(i + 3) % 4]`` for i = 0..3, i.e. w, x, y, z; no header; images in
  increasing image-id order; default stream precision (6 significant digits, so read back
  with the near-rotation tolerance); the older GLOMAP wrote a trailing space.
* ``ReadRelPose`` / ``WriteRelPose``: ``IMAGE_NAME_1 IMAGE_NAME_2 QW QX QY QZ TX TY TZ``,
  the pair's ``cam2_from_cam1`` (rotation and translation), split on single spaces (names
  cannot contain spaces). ``cam2_from_cam1`` of (image1, image2) is this project's
  ``R_ij = R_j R_iᵀ`` for (i, j) = (image1, image2).
* ``ReadRelWeight``: ``IMAGE_NAME_1 IMAGE_NAME_2 WEIGHT``.
* ``ReadGravity``: ``IMAGE_NAME GX GY GZ`` (not handled here).

Lines are parsed on any whitespace here (a superset of GLOMAP's single-space split);
blank lines and lines starting with ``#`` are skipped (GLOMAP itself writes none); a ``#``
within a line is part of an image name (``IMG#12.jpg``), as GLOMAP writes it.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import atomic_open
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.common import repeated_pair
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL, NearRotationError, normalize_near_unit_quaternions

__all__ = ["write_glomap_rotations", "read_glomap_rotations", "write_glomap_relpose", "read_glomap_relpose"]

logger = logging.getLogger(__name__)


def _check_names(names: list[str]) -> None:
    bad = [n for n in names if not n or any(c.isspace() for c in n)]
    if bad:
        raise ValueError(f"GLOMAP files split on spaces: image names may not be empty or contain whitespace: {bad[:3]}")


def _lines(path: Path, n_fields: int, layout: str):
    """Yield (lineno, fields) of a whitespace-separated file; one-line errors naming the file."""
    if not path.is_file():
        raise InputFileError(f"GLOMAP file {path} does not exist")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path} is not a readable text file ({exc.__class__.__name__})") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):  # a comment line; '#' within a line is part of a name
            continue
        if len(parts) != n_fields:
            raise InputFileError(f"{path}:{lineno}: expected '{layout}' ({n_fields} fields), got {len(parts)}")
        yield lineno, parts


def _floats(path: Path, lineno: int, parts: list[str]) -> list[float]:
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        raise InputFileError(f"{path}:{lineno}: expected numbers, got {' '.join(parts)!r}") from None
    if not np.all(np.isfinite(vals)):
        raise InputFileError(f"{path}:{lineno}: NaN or inf value; fix or delete the line")
    return vals


def write_glomap_rotations(path: str | os.PathLike, names: list[str], R: np.ndarray) -> Path:
    """Write ``NAME QW QX QY QZ`` (cam_from_world), full precision, in the given order.

    Args:
        path: output file.
        names: N image names (no whitespace).
        R: (N, 3, 3) cam_from_world rotations.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (len(names), 3, 3):
        raise ValueError(f"R.shape={R.shape} but expected ({len(names)}, 3, 3)")
    _check_names(names)
    q = so3.quat_from_matrix(R)  # (w, x, y, z), w >= 0
    path = Path(path)
    with atomic_open(path) as f:
        for name, qi in zip(names, q):
            f.write(name + " " + " ".join(f"{v:.17g}" for v in qi) + "\n")
    return path


def read_glomap_rotations(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL
                          ) -> tuple[list[str], np.ndarray]:
    """Read ``NAME QW QX QY QZ`` lines (GLOMAP's ``WriteGlobalRotation``).

    Quaternions with | ‖q‖ − 1 | ≤ ``rotation_tol`` are normalized (one warning).

    Returns:
        names (file order) and (N, 3, 3) cam_from_world rotations.

    Raises:
        InputFileError: missing file, wrong field count, non-numbers, a repeated name, an empty
            file, a quaternion far from unit norm (one line naming the file).
    """
    path = Path(path)
    names, qs = [], []
    for lineno, parts in _lines(path, 5, "IMAGE_NAME QW QX QY QZ"):
        names.append(parts[0])
        qs.append(_floats(path, lineno, parts[1:]))
    if not names:
        raise InputFileError(f"{path} holds no rotations")
    if len(set(names)) != len(names):
        seen: set[str] = set()
        dup = [n for n in names if n in seen or seen.add(n)]
        raise InputFileError(f"{path}: image names repeat: {sorted(set(dup))[:5]}")
    try:
        q, _ = normalize_near_unit_quaternions(np.array(qs), rotation_tol, source=str(path), labels=names)
    except NearRotationError as exc:
        raise InputFileError(str(exc)) from None
    return names, so3.matrix_from_quat(q)


def write_glomap_relpose(path: str | os.PathLike, vg: ViewGraph, t: np.ndarray | None = None) -> Path:
    """Write ``NAME1 NAME2 QW QX QY QZ TX TY TZ`` per edge (cam2_from_cam1 = ``R_ij``).

    Args:
        path: output file.
        vg: the view graph (edges i < j, ``R_ij = R_j R_iᵀ``).
        t: (M, 3) translations of cam2_from_cam1 (default ``vg.stats["t"]``, the pipeline's, if present, else 0).
    """
    _check_names(vg.names)
    if t is None:
        t = vg.stats.get("t", np.zeros((vg.n_edges, 3)))
    t = np.asarray(t, dtype=np.float64).reshape(vg.n_edges, 3)
    q = so3.quat_from_matrix(vg.R_rel)
    path = Path(path)
    with atomic_open(path) as f:
        for (i, j), qi, ti in zip(vg.edges, q, t):
            f.write(f"{vg.names[i]} {vg.names[j]} " + " ".join(f"{v:.17g}" for v in (*qi, *ti)) + "\n")
    return path


def read_glomap_relpose(path: str | os.PathLike, rotation_tol: float = DEFAULT_ROTATION_TOL,
                        names: list[str] | None = None) -> ViewGraph:
    """Read GLOMAP relative poses into a ViewGraph (cam2_from_cam1 translations in ``stats["t"]``, as the pipeline's).

    Args:
        path: the file.
        rotation_tol: quaternion-norm tolerance.
        names: the camera list (default: names in order of first appearance).

    Raises:
        InputFileError: malformed lines, unknown names (when ``names`` is given), a pair given
            twice, quaternions far from unit norm (one line naming the file).
    """
    path = Path(path)
    pairs, vals = [], []
    for lineno, parts in _lines(path, 9, "IMAGE_NAME_1 IMAGE_NAME_2 QW QX QY QZ TX TY TZ"):
        pairs.append((lineno, parts[0], parts[1]))
        vals.append(_floats(path, lineno, parts[2:]))
    if not pairs:
        raise InputFileError(f"{path} holds no relative poses")
    if names is None:
        names = list(dict.fromkeys(n for _, a, b in pairs for n in (a, b)))
    index = {n: k for k, n in enumerate(names)}
    unknown = [(ln, n) for ln, a, b in pairs for n in (a, b) if n not in index]
    if unknown:
        raise InputFileError(f"{path}:{unknown[0][0]}: image {unknown[0][1]!r} is not in the camera list")
    v = np.array(vals)
    try:
        q, _ = normalize_near_unit_quaternions(v[:, :4], rotation_tol, source=str(path),
                                               labels=[f"of line {ln}" for ln, _, _ in pairs])
    except NearRotationError as exc:
        raise InputFileError(str(exc)) from None
    edges = np.array([(index[a], index[b]) for _, a, b in pairs], dtype=np.int64)
    rep = repeated_pair(edges)
    if rep is not None:  # named by the file's image names and lines
        a, b = rep
        raise InputFileError(f"{path}:{pairs[b][0]}: images {pairs[b][1]} and {pairs[b][2]} already have a relative pose on "
                             f"line {pairs[a][0]}; each pair may appear once, in either orientation: delete one of the lines")
    if np.any(edges[:, 0] == edges[:, 1]):
        k = int(np.flatnonzero(edges[:, 0] == edges[:, 1])[0])
        raise InputFileError(f"{path}:{pairs[k][0]}: a pair of an image with itself; delete the line")
    R = so3.matrix_from_quat(q)
    t = v[:, 4:]
    # orient i < j: R_ji = R_ijᵀ and t_ji = −R_ijᵀ t_ij (the inverse rigid transform)
    flip = edges[:, 0] > edges[:, 1]
    t = np.where(flip[:, None], -np.einsum("mba,mb->ma", R, t), t)
    try:
        vg = ViewGraph.from_edges(names, edges, R, stats={"t": t}, allow_isolated=True)
    except ViewGraphError as exc:
        raise InputFileError(f"{path}: {exc}") from None
    return vg
