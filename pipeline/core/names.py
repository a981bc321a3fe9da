"""One image-name matcher for every place that pairs our images with another list.

A name matches another exactly, or else by file stem: ``"0001"`` matches
``"0001.jpg"`` and ``"img/0001.png"`` matches ``"0001.jpg"``. A stem that two
names on the other side share is ambiguous: :func:`match_names` raises, naming
both, unless ``ambiguous="skip"``, which leaves such names unmatched.
"""

from __future__ import annotations

from pathlib import PurePosixPath
from typing import Literal

import numpy as np

from pipeline.core.errors import InputFileError

__all__ = ["stem", "match_names", "rows_by_name"]


def stem(name: str) -> str:
    """The file name without folders and without its last extension."""
    p = PurePosixPath(str(name).replace("\\", "/"))
    return p.name[: -len(p.suffix)] if p.suffix else p.name


def match_names(names: list[str], other: list[str], *, what: str = "the reference",
                ambiguous: Literal["error", "skip"] = "error") -> np.ndarray:
    """(N,) index into ``other`` of each of ``names``, or −1 where none matches.

    Args:
        names: our N image names.
        other: the names of the other list (a reference, a K file, a pairs file).
        what: how to call ``other`` in messages.
        ambiguous: ``"error"`` raises :class:`InputFileError` when one of
            ``names`` matches only by a stem that several of ``other`` share;
            ``"skip"`` leaves it unmatched.
    """
    other = [str(o) for o in other]
    exact = {n: k for k, n in enumerate(other)}
    by_stem: dict[str, list[int]] = {}
    for k, n in enumerate(other):
        by_stem.setdefault(stem(n), []).append(k)
    out = np.full(len(names), -1, dtype=np.int64)
    for q, n in enumerate(names):
        n = str(n)
        if n in exact:
            out[q] = exact[n]
            continue
        cand = by_stem.get(stem(n), [])
        if len(cand) == 1:
            out[q] = cand[0]
        elif len(cand) > 1 and ambiguous == "error":
            raise InputFileError(f"image {n!r} matches several names of {what} by its stem "
                                 f"({', '.join(repr(other[k]) for k in cand[:3])}); rename them so that stems are unique")
    return out


def rows_by_name(names: list[str], other: list[str], arr: np.ndarray, *, what: str = "the reference"
                 ) -> np.ndarray | None:
    """Rows of ``arr`` (one per ``other``) for ``names``; None if any name has no match."""
    idx = match_names(names, other, what=what)
    if np.any(idx < 0):
        return None
    return np.asarray(arr)[idx]
