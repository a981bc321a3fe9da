"""Which image pairs to match (``matching.pairs``).

- ``exhaustive``: all ``N(N−1)/2`` pairs;
- ``sequential:K``: each image with the next ``K`` in name order (video, ordered captures);
- a path: a pairs file, one ``name_a name_b`` per line (hloc's format; a name with
  spaces in double quotes); names are matched by :func:`pipeline.core.names.match_names` (exact, then stem);
- ``database``: the pairs a COLMAP database has verified: with ``run.py --database DB``
  the database's own inlier matches; ``database:DB`` with our features, the pairs
  ``DB`` verified, matched by us (:mod:`pipeline.frontend.database_stage`);
- ``retrieval:K`` (or ``retrieval``: K from the collection size): each image with its K most
  similar images by a global descriptor of its own SIFT (:mod:`pipeline.frontend.retrieval`);
- ``auto`` (the default): exhaustive up to ``exhaustive_max_images`` images, retrieval above
  (:func:`choose_pairs` resolves it and says what it chose).

Every selector returns sorted, unique index pairs ``(a, b)`` with ``a < b``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.core.errors import ConfigError, InputFileError
from pipeline.core.names import match_names, split_fields

__all__ = ["exhaustive_pairs", "sequential_pairs", "read_pairs", "parse_selector", "select_pairs", "resolve_auto",
           "choose_pairs", "selection_summary"]

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
    extra: set[int] = set()  # lines of more than two fields (a score, or a name holding spaces, unquoted)
    for ln_no, line in enumerate(text.splitlines(), 1):
        tok = split_fields(line, f"{path} line {ln_no}")
        if not tok:
            continue
        if len(tok) < 2:
            raise InputFileError(f"{path} line {ln_no}: expected 'name_a name_b', got {line.strip()[:80]!r}")
        rows.append((ln_no, tok[0], tok[1]))
        if len(tok) > 2:
            extra.add(ln_no)
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
                    f"(e.g. {', '.join(names[:3])}); was it skipped as unreadable, or are the pairs from another folder?"
                    + (" (a name holding spaces is written in double quotes: \"IMG 0001.jpg\")" if ln_no in extra
                       else ""))
        if idx[a] != idx[b]:
            out.append(sorted((int(idx[a]), int(idx[b]))))
    if not out:
        raise InputFileError(f"{path} lists no pair of two different images")
    return np.unique(np.array(out, np.int64), axis=0)


def _parse_retrieval(spec: str) -> tuple[str, int | None] | None:
    """``("auto", None)``, ``("retrieval", K or None)``, or None when ``spec`` is neither."""
    s = spec.strip()
    kind, colon, arg = s.partition(":")
    if s == "auto":
        return "auto", None
    if kind != "retrieval":
        return None
    if not colon:
        return "retrieval", None
    try:
        k = int(arg)
    except ValueError:
        k = 0
    if k < 1:
        raise ConfigError(f"[matching] pairs={spec!r}: write retrieval:K with K >= 1 neighbours per image "
                          "(e.g. retrieval:12), or retrieval to choose K from the number of images")
    return "retrieval", k


def parse_selector(spec: str) -> tuple[str, int | Path | None]:
    """``("exhaustive", None)``, ``("sequential", K)``, ``("retrieval", K or None)``, ``("auto", None)`` or
    ``("file", path)`` from a ``matching.pairs`` value."""
    s = spec.strip()
    kind, _, arg = s.partition(":")
    if s == "exhaustive":
        return "exhaustive", None
    if kind == "database":
        return "database", (Path(arg) if arg else None)
    if (parsed := _parse_retrieval(s)) is not None:
        return parsed
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
    raise ConfigError(f"[matching] pairs={spec!r} but expected auto, exhaustive, sequential:K, retrieval:K, "
                      "database[:DB] or an "
                      "existing pairs file")


def select_pairs(spec: str, names: list[str]) -> np.ndarray:
    """The pairs of ``names`` chosen by ``spec`` (see :func:`parse_selector`; not ``retrieval``/``auto``,
    which need descriptors: :func:`choose_pairs`)."""
    kind, arg = parse_selector(spec)
    if kind in ("auto", "retrieval"):
        raise ConfigError(f"[matching] pairs={spec!r} needs the images' descriptors: use choose_pairs")
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


def resolve_auto(n_images: int, exhaustive_max_images: int) -> str:
    """What ``auto`` selects for ``n_images`` images: ``"exhaustive"`` up to ``exhaustive_max_images``, else
    ``"retrieval"``."""
    return "exhaustive" if n_images <= exhaustive_max_images else "retrieval"


def choose_pairs(spec: str, names: list[str], descriptors: Callable[[], tuple[list[np.ndarray], list[np.ndarray]]],
                 exhaustive_max_images: int = 50, seed: int = 0, ranked: dict[str, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, dict[str, Any]]:
    """The pairs of ``names`` chosen by ``spec``, and what was chosen.

    Args:
        spec: a ``matching.pairs`` value (see :func:`parse_selector`).
        names: the N image names.
        descriptors: called only when retrieval runs: N descriptor arrays (n_i, 128) uint8 and
            N response arrays (n_i,).
        exhaustive_max_images: ``auto`` is exhaustive up to this many images, retrieval above.
        seed: seed of the retrieval vocabulary.
        ranked: when given and retrieval runs, filled with each image's ranked ``neighbours`` and their
            ``similarities`` (:func:`pipeline.frontend.retrieval.retrieve_pairs`).
    Returns:
        pairs (P, 2) sorted unique ``a < b``, and ``{"spec", "selector", "k", "n_images", "n_pairs",
        "n_exhaustive", "fraction"}`` (plus the vocabulary size and time when retrieval ran).
    """
    kind, arg = parse_selector(spec)
    n = len(names)
    info: dict[str, Any] = {"spec": spec, "selector": kind, "k": None}
    if kind == "auto":
        kind = resolve_auto(n, exhaustive_max_images)
        info.update(selector=kind, auto=True, exhaustive_max_images=exhaustive_max_images)
    if kind == "retrieval":
        from pipeline.frontend.retrieval import retrieve_pairs  # noqa: PLC0415 - faiss is imported on use

        descs, responses = descriptors()
        res = retrieve_pairs(descs, None if arg is None else int(arg), responses=responses, seed=seed)  # type: ignore[arg-type]
        pairs = res["pairs"]
        if ranked is not None:
            ranked.update(neighbours=res["neighbours"], similarities=res["similarities"])
        info.update(k=res["k"], n_words=res["n_words"], time_s=round(res["time_s"], 3))
    else:
        pairs = select_pairs(kind if kind == "exhaustive" else spec, names)
        info["k"] = int(arg) if kind == "sequential" else None  # type: ignore[arg-type]
    return pairs, selection_summary(info, n, len(pairs))


def selection_summary(info: dict[str, Any], n: int, n_pairs: int) -> dict[str, Any]:
    """``info`` with the counts of a selection of ``n_pairs`` pairs among ``n`` images against exhaustive."""
    n_all = n * (n - 1) // 2
    info.update(n_images=n, n_pairs=int(n_pairs), n_exhaustive=n_all,
                fraction=round(n_pairs / n_all, 6) if n_all else 0.0)
    return info
