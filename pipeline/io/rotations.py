"""Rotations text files.

One camera per line: ``name r11 r12 r13 r21 r22 r23 r31 r32 r33``, the
cam_from_world rotation in row-major order. ``#`` starts a comment; blank lines
are ignored. A name with whitespace, ``#`` or ``"`` is written in double quotes
(:func:`pipeline.core.names.quote_name`).

:func:`read_rotations` also reads GLOMAP's rotation files (``NAME QW QX QY QZ``,
:mod:`pipeline.io.glomap`), recognised by their 5 fields a line. Matrices within
``tol`` of SO(3) (default 1e-3; files printed with a few digits) are projected onto it
with one warning; beyond, refused (:mod:`pipeline.io.near_rotation`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.atomic import atomic_open
from pipeline.core.errors import InputFileError
from pipeline.core.names import match_names, quote_name, split_fields
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL, projected_or_input_error


def write_rotations(path: str | os.PathLike, names: list[str], R: np.ndarray, header: str | None = None) -> Path:
    """Write rotations atomically.

    Args:
        path: output file.
        names: N camera names (not empty; quoted in the file when they hold whitespace).
        R: (N, 3, 3) cam_from_world rotations.
        header: optional comment lines written first.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (len(names), 3, 3):
        raise ValueError(f"R.shape={R.shape} but expected ({len(names)}, 3, 3)")
    if not all(names):
        raise ValueError("camera names may not be empty")
    with atomic_open(path) as f:
        if header:
            for line in header.splitlines():
                f.write(f"# {line}\n")
        f.write("# name r11 r12 r13 r21 r22 r23 r31 r32 r33 (cam_from_world, row-major)\n")
        for name, Ri in zip(names, R):
            f.write(quote_name(name) + " " + " ".join(f"{x:.17g}" for x in Ri.ravel()) + "\n")
    return Path(path)


def read_rotations(path: str | os.PathLike, tol: float = DEFAULT_ROTATION_TOL) -> tuple[list[str], np.ndarray]:
    """Read a rotations file (ours, or GLOMAP's ``NAME QW QX QY QZ``).

    Returns:
        names: N camera names, in file order.
        R: (N, 3, 3) cam_from_world rotations.

    Raises:
        InputFileError: missing file, a line without 10 fields, a value that is
            not a number, a repeated name, or a matrix farther than ``tol`` from SO(3).
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"rotations file {path} does not exist")
    names: list[str] = []
    rows: list[list[float]] = []
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path} is not a rotations text file (not UTF-8: {exc.reason} at byte {exc.start})"
                             ) from None
    except OSError as exc:
        raise InputFileError(f"rotations file {path} cannot be read ({exc.strerror or exc})") from None
    rows_of = [(k, split_fields(ln, f"{path}:{k}")) for k, ln in enumerate(lines, 1)]
    first = next((parts for _, parts in rows_of if parts), [])
    raw = next((ln.split() for ln in lines if ln.split() and not ln.split()[0].startswith("#")), [])
    if len(first) == 5 or (len(first) != 10 and len(raw) == 5):  # GLOMAP's: a '#' there is part of a name
        from pipeline.io.glomap import read_glomap_rotations  # noqa: PLC0415

        return read_glomap_rotations(path, tol)
    for lineno, parts in rows_of:
        if not parts:
            continue
        if len(parts) != 10:
            raise InputFileError(f"{path}:{lineno}: expected 'name r11 ... r33' (10 fields), got {len(parts)} "
                                 "(GLOMAP's rotation files have 5: NAME QW QX QY QZ)")
        try:
            vals = [float(x) for x in parts[1:]]
        except ValueError:
            raise InputFileError(f"{path}:{lineno}: rotation entries must be numbers") from None
        if not parts[0]:
            raise InputFileError(f"{path}:{lineno}: empty camera name")
        names.append(parts[0])
        rows.append(vals)
    if not names:
        raise InputFileError(f"{path} holds no rotations")
    if len(set(names)) != len(names):
        seen: set[str] = set()
        dup = sorted({n for n in names if n in seen or seen.add(n)})
        raise InputFileError(f"{path}: camera names repeat: {dup[:5]}")
    R = np.array(rows).reshape(-1, 3, 3)
    return names, projected_or_input_error(R, tol, what="the matrix", source=str(path),
                                           labels=[f"of camera {n!r}" for n in names])


def rotations_for(path: str | os.PathLike, names: list[str], lacking: str, remedy: str,
                  tol: float = DEFAULT_ROTATION_TOL) -> np.ndarray:
    """(N, 3, 3) the rotations file ``path``'s rotations of the cameras ``names`` (matched by name), for a start or
    a g2o file's vertices; :class:`InputFileError` "<lacking> for k camera(s), e.g. [...]; <remedy>" where the file
    lacks some."""
    file_names, R = read_rotations(path, tol)
    idx = match_names(list(names), file_names, what=str(path))
    missing = [n for n, k in zip(names, idx) if k < 0]
    if missing:
        raise InputFileError(f"{lacking} for {len(missing)} camera(s), e.g. {missing[:5]}; {remedy}")
    return R[idx]
