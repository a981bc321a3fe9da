"""Shared by the readers of other tools' text files (1DSfM, g2o, GLOMAP, rotations)."""

from __future__ import annotations

import numpy as np

__all__ = ["repeated_pair"]


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
