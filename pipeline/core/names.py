"""One image-name matcher for every place that pairs our images with another list.

A name matches another exactly, or else by file stem: ``"0001"`` matches
``"0001.jpg"`` and ``"img/0001.png"`` matches ``"0001.jpg"``. A stem that two
names on the other side share is ambiguous: :func:`match_names` raises, naming
both, unless ``ambiguous="skip"``, which leaves such names unmatched. Between
our own lists (a view graph's cameras, a method's), names are matched exactly:
:func:`positions`.

Names in our text formats (rotations, cameras, intrinsics and pairs files) are
one field each: :func:`quote_name` writes a name that holds whitespace, ``#`` or
a double quote in double quotes (JSON string syntax), and :func:`split_fields`
reads such a line back. So ``IMG 0001.JPG`` works end to end, and every file
without quotes reads exactly as before.
"""

from __future__ import annotations

import json
import re
from pathlib import PurePosixPath
from typing import Literal, Sequence

import numpy as np

from pipeline.core.errors import InputFileError

__all__ = ["stem", "match_names", "rows_by_name", "positions", "quote_name", "split_fields"]

_TOKEN = re.compile(r'"(?:[^"\\\n]|\\.)*"|[^\s"#]+|#|"')


def quote_name(name: str) -> str:
    """``name`` as one field of a text file: as is, or quoted when it holds whitespace, ``#`` or ``"``."""
    name = str(name)
    if name and not any(c.isspace() or c in '#"' for c in name):
        return name
    return json.dumps(name, ensure_ascii=False)


def split_fields(line: str, where: str = "line") -> list[str]:
    """The fields of one line of a text file: split at whitespace, ``#`` starts a comment, ``"…"`` is one field.

    Raises:
        InputFileError: a quoted field is not closed (``where`` names the file and line).
    """
    if '"' not in line:
        return line.split("#", 1)[0].split()
    out: list[str] = []
    for m in _TOKEN.finditer(line):
        tok = m.group()
        if tok == "#":
            break
        if tok[0] == '"':
            try:
                tok = json.loads(tok)
            except ValueError:
                raise InputFileError(f"{where}: a quoted name is not closed or has a bad escape; write names "
                                     'with spaces as "name with spaces"') from None
        out.append(tok)
    return out


def stem(name: str) -> str:
    """The file name without folders and without its last extension."""
    p = PurePosixPath(str(name).replace("\\", "/"))
    return p.name[: -len(p.suffix)] if p.suffix else p.name


def match_names(names: list[str], other: list[str], *, what: str = "the reference",
                ambiguous: Literal["error", "skip"] = "error", unique: bool = False) -> np.ndarray:
    """(N,) index into ``other`` of each of ``names``, or −1 where none matches.

    Args:
        names: our N image names.
        other: the names of the other list (a reference, a K file, a pairs file).
        what: how to call ``other`` in messages.
        ambiguous: ``"error"`` raises :class:`InputFileError` when one of
            ``names`` matches only by a stem that several of ``other`` share;
            ``"skip"`` leaves it unmatched.
        unique: each name of ``other`` may be matched by one of ``names`` only (a
            reference: ``a.png`` and ``a.jpg`` must not both get the camera ``a``);
            :class:`InputFileError` otherwise.
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
    if unique:
        hit = out[out >= 0]
        counts = np.bincount(hit, minlength=len(other)) if hit.size else np.zeros(0, np.int64)
        if np.any(counts > 1):
            k = int(np.argmax(counts > 1))
            both = [repr(str(n)) for n, i in zip(names, out) if i == k][:2]
            raise InputFileError(f"images {' and '.join(both)} both match {other[k]!r} of {what}; give it the "
                                 "full file names (with extensions) so that each image has its own entry")
    return out


def rows_by_name(names: list[str], other: list[str], arr: np.ndarray, *, what: str = "the reference"
                 ) -> np.ndarray | None:
    """Rows of ``arr`` (one per ``other``) for ``names``; None if any name has no match."""
    idx = match_names(names, other, what=what)
    if np.any(idx < 0):
        return None
    return np.asarray(arr)[idx]


def positions(names: Sequence[str], subset: Sequence[str], missing: int | None = None) -> np.ndarray:
    """(len(subset),) int64: where each of ``subset`` stands in ``names`` (unique names, matched exactly: what
    ``names.index`` gives for each, in one pass over ``names``).

    A name not in ``names`` is ``missing`` (e.g. −1, for our lists that hold only some of the cameras); with
    ``missing=None`` it raises ValueError, as ``index`` does.
    """
    pos = {n: k for k, n in enumerate(names)}
    if missing is not None:
        return np.array([pos.get(n, missing) for n in subset], np.int64)
    try:
        return np.array([pos[n] for n in subset], np.int64)
    except KeyError as exc:
        raise ValueError(f"{exc.args[0]!r} is not in list") from None
