"""Shared by the readers of other tools' text files (1DSfM, g2o, GLOMAP, rotations)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.core.errors import InputFileError

__all__ = ["repeated_pair", "line_numbers"]


def repeated_pair(ij: np.ndarray) -> tuple[int, int] | None:
    """Rows ``(first, k)`` of the first camera pair given a second time (row k), in either orientation; else None.

    Args:
        ij: (M, 2) endpoints as the file gives them (any integer labels).
    """
    ij = np.asarray(ij).reshape(-1, 2)
    if ij.shape[0] < 2:
        return None
    _, first, inverse = np.unique(np.sort(ij, axis=1), axis=0, return_index=True, return_inverse=True)
    first_of = first[inverse.ravel()]
    again = np.flatnonzero(first_of != np.arange(ij.shape[0]))
    return None if again.size == 0 else (int(first_of[again[0]]), int(again[0]))


def line_numbers(path: Path, lineno: int, parts: list[str], kind=float) -> list:
    """The fields of line ``lineno`` of ``path`` as numbers (``kind``); one error line naming it otherwise."""
    try:
        vals = [kind(x) for x in parts]
    except ValueError:
        raise InputFileError(f"{path}:{lineno}: expected {'integers' if kind is int else 'numbers'}, "
                             f"got {' '.join(parts)[:60]!r}") from None
    if kind is float and not all(map(math.isfinite, vals)):  # per line: math, not numpy (4× faster on 300k EGs)
        raise InputFileError(f"{path}:{lineno}: NaN or inf value; fix or delete the line")
    return vals
