"""Which image pairs to match (``matching.pairs``).

- ``exhaustive``: all ``N(N−1)/2`` pairs;
- ``sequential:K``: each image with the next ``K`` in name order (video, ordered captures);
- a path: a pairs file, one ``name_a name_b`` per line (hloc's format; a name with
  spaces in double quotes); names are matched by :func:`pipeline.core.names.match_names` (exact, then stem);
- ``database``: the pairs a COLMAP database has verified: with ``run.py --database DB``
  the database's own inlier matches; ``database:DB`` with our features, the pairs
  ``DB`` verified, matched by us (:mod:`pipeline.frontend.database_stage`).

Every selector returns sorted, unique index pairs ``(a, b)`` with ``a < b``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError, InputFileError
from pipeline.core.names import match_names, split_fields

__all__ = ["exhaustive_pairs", "sequential_pairs", "read_pairs", "parse_selector", "select_pairs"]

MAX_PAIRS_FILE_BYTES = 256 << 20


def exhaustive_pairs(n: int) -> np.ndarray:
    """All pairs ``(a, b)``, ``a < b``, of n images: (n(n-1)/2, 2)."""
    a, b = np.triu_indices(n, k=1)
    return np.stack([a, b], axis=1).astype(np.int64)


def sequential_pairs(n: int, k: int) -> np.ndarray:
    """Each image with the next ``k`` images: (≤ n·k, 2)."""
    a, b = np.triu_indices(n, k=1)
    keep = (b - a) <= k
    return np.stack([a[keep], b[keep]], axis=1).astype(np.int64)


def read_pairs(path: str | os.PathLike, names: list[str]) -> np.ndarray:
    """Pairs from a file of ``name_a name_b`` lines, as sorted unique index pairs (P, 2).

    Raises:
        InputFileError: missing or unreadable file, malformed line, unknown image name or no pair.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"pairs file {path} does not exist")
    if path.stat().st_size > MAX_PAIRS_FILE_BYTES:
        raise InputFileError(f"pairs file {path} is {path.stat().st_size >> 20} MB; expected 'name_a name_b' lines")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"pairs file {path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    rows: list[tuple[int, str, str]] = []
    for ln_no, line in enumerate(text.splitlines(), 1):
        tok = split_fields(line, f"{path} line {ln_no}")
        if not tok:
            continue
        if len(tok) < 2:
            raise InputFileError(f"{path} line {ln_no}: expected 'name_a name_b', got {line.strip()[:80]!r}")
        rows.append((ln_no, tok[0], tok[1]))
    if not rows:
        raise InputFileError(f"{path} lists no pair of two different images")
    wanted = sorted({t for _, a, b in rows for t in (a, b)})
    idx = dict(zip(wanted, match_names(wanted, names, what=f"the images with features (pairs file {path})")))
    out = []
    for ln_no, a, b in rows:
        for t in (a, b):
            if idx[t] < 0:
                raise InputFileError(
                    f"{path} line {ln_no}: image {t!r} is not among the {len(names)} images with features "
                    f"(e.g. {', '.join(names[:3])}); was it skipped as unreadable, or are the pairs from another folder?")
        if idx[a] != idx[b]:
            out.append(sorted((int(idx[a]), int(idx[b]))))
    if not out:
        raise InputFileError(f"{path} lists no pair of two different images")
    return np.unique(np.array(out, np.int64), axis=0)


def parse_selector(spec: str) -> tuple[str, int | Path | None]:
    """``("exhaustive", None)``, ``("sequential", K)`` or ``("file", path)`` from a ``matching.pairs`` value."""
    s = spec.strip()
    kind, _, arg = s.partition(":")
    if s == "exhaustive":
        return "exhaustive", None
    if kind == "database":
        return "database", (Path(arg) if arg else None)
    if kind == "sequential":
        try:
            k = int(arg)
        except ValueError:
            k = 0
        if k < 1:
            raise ConfigError(f"[matching] pairs={spec!r}: write sequential:K with K >= 1 (e.g. sequential:10)")
        return "sequential", k
    if Path(s).is_file():
        return "file", Path(s)
    raise ConfigError(f"[matching] pairs={spec!r} but expected exhaustive, sequential:K, database[:DB] or an "
                      "existing pairs file")


def select_pairs(spec: str, names: list[str]) -> np.ndarray:
    """The pairs of ``names`` chosen by ``spec`` (see :func:`parse_selector`)."""
    kind, arg = parse_selector(spec)
    if kind == "exhaustive":
        return exhaustive_pairs(len(names))
    if kind == "sequential":
        return sequential_pairs(len(names), int(arg))  # type: ignore[arg-type]
    if kind == "database":
        if arg is None:
            raise ConfigError("[matching] pairs='database' takes the pairs of the COLMAP database given with "
                              "--database DB; without it write database:PATH")
        from pipeline.frontend.database_stage import database_pairs  # noqa: PLC0415

        return database_pairs(arg, names)  # type: ignore[arg-type]
    return read_pairs(arg, names)  # type: ignore[arg-type]
