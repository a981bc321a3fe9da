"""Per-item results of a stage (one image, one pair), kept in chunk files so that work resumes per item.

A per-image or per-pair stage computes its items in chunks (on an
:class:`pipeline.core.parallel.Executor`) and writes each finished chunk at once,
atomically, as one ``.npz`` in its store folder. Every item has a key that hashes
everything its result depends on (the stage's result-affecting options and the
item's own inputs), so

- an interrupted run resumes: finished chunks are found and their items skipped;
- a changed option or input gives new keys, never a stale result;
- adding images reuses every pair already done;
- a damaged chunk file, or an item that reads well but fails its stage's check, is removed with a warning and
  its items recomputed.

An item's result is a mapping of names to arrays (scalars as 0-d arrays, strings
as 0-d unicode arrays). The store's index (``index.json``, written when the stage
finishes) maps each current key to its chunk file; readers open only the chunks
they need.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import re
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from pipeline.core.atomic import save_npz_uncompressed, write_json
from pipeline.core.errors import CacheError
from pipeline.core.readers import read_json, read_npz

__all__ = ["ItemStore", "Item", "item_key", "compute_missing", "write_results"]

logger = logging.getLogger(__name__)

INDEX = "index.json"
_CHUNK = re.compile(r"chunk-[0-9a-f]{16}\.npz")
_SEP = "__"
#: What starting a pool of processes costs, in CPU seconds per worker (spawn, and each worker importing
#: numpy, OpenCV and the package; measured: 0.6 s). :func:`compute_missing` starts a pool only for work
#: of at least ``POOL_MIN_SHARE`` times that: shorter work runs on threads of this process, which start
#: at once. ``ROTAVG_POOL_STARTUP_S`` overrides the cost (0: a pool whenever workers > 1).
POOL_STARTUP_S = 0.6
POOL_MIN_SHARE = 4.0


def _pool_pays_off(rest_cpu_s: float, workers: int) -> bool:
    """Whether ``rest_cpu_s`` CPU seconds of work are worth starting ``workers`` processes for.

    On free cores a pool returns its start-up once the work is about twice it; the
    margin ``POOL_MIN_SHARE`` keeps the start-up a small part of the work, since on a
    busy machine it is pure extra work. CPU time, not wall time, so that the load of
    other processes does not change the choice.
    """
    startup = float(os.environ.get("ROTAVG_POOL_STARTUP_S", POOL_STARTUP_S))
    return startup <= 0 or rest_cpu_s >= POOL_MIN_SHARE * startup * workers


def item_key(*parts: Any) -> str:
    """A 20-hex-digit key from strings, numbers and arrays (their bytes, dtype and shape)."""
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
        h.update(b"\x00")
    return h.hexdigest()[:20]


class Item(dict):
    """One item's arrays (``{name: array}``); ``source`` is its chunk file, and a missing array is a :class:`CacheError`."""

    def __init__(self, source: Path) -> None:
        super().__init__()
        self.source = source

    def __missing__(self, name: str) -> np.ndarray:
        raise CacheError(f"chunk {self.source} is damaged (an item lacks its array {name!r})")


_LAYOUT, _DATA = "layout", "data"
_ALIGN = 16


def _pack(items: Iterable[Mapping[str, Any]]) -> dict[str, np.ndarray]:
    """The arrays of a chunk's items as one byte buffer and its layout (JSON: per item, per name, the dtype,
    shape and offset): a chunk is read with two archive members instead of one per array."""
    layout: list[dict[str, list[Any]]] = []
    parts: list[bytes] = []
    offset = 0
    for item in items:
        entry = {}
        for name, v in item.items():
            a = np.asarray(v)  # tobytes() is C order whatever the strides
            if a.dtype.hasobject:
                raise TypeError(f"array {name!r} holds Python objects")
            entry[name] = [a.dtype.str, list(a.shape), offset]
            b = a.tobytes()
            pad = -len(b) % _ALIGN
            parts += [b, bytes(pad)]
            offset += len(b) + pad
        layout.append(entry)
    return {_LAYOUT: np.array(json.dumps(layout)), _DATA: np.frombuffer(b"".join(parts), np.uint8)}


def _unpack(layout: np.ndarray, data: np.ndarray, n: int) -> list[dict[str, np.ndarray]]:
    """The items :func:`_pack` wrote (views of ``data``); ValueError if the layout does not fit the buffer."""
    spec = json.loads(str(layout.item())) if layout.ndim == 0 and layout.dtype.kind == "U" else None
    if not isinstance(spec, list) or len(spec) != n or data.dtype != np.uint8 or data.ndim != 1:
        raise ValueError("the layout does not describe the chunk's items")
    buf = data.data
    out = []
    for entry in spec:
        if not isinstance(entry, dict):
            raise ValueError("an item's layout is not a mapping")
        fields = {}
        for name, (dtype, shape, offset) in entry.items():
            dt = np.dtype(dtype)
            if dt.hasobject or not all(isinstance(k, int) and k >= 0 for k in [*shape, offset]):
                raise ValueError(f"array {name!r} has a bad layout")
            count = int(np.prod(shape, dtype=np.int64)) if shape else 1
            if offset + count * dt.itemsize > len(data):
                raise ValueError(f"array {name!r} runs past the end of the chunk")
            fields[name] = np.frombuffer(buf, dt, count, offset).reshape(tuple(shape))
        out.append(fields)
    return out


def _chunk_name(keys: Iterable[str]) -> str:
    return "chunk-" + hashlib.sha1("\n".join(sorted(keys)).encode()).hexdigest()[:16] + ".npz"


class ItemStore:
    """A folder of chunk files holding per-item results.

    Args:
        folder: the store's folder (created when written).
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self._where: dict[str, str] | None = None
        self._cache: dict[str, dict[str, dict[str, np.ndarray]]] = {}

    # ------------------------------------------------------------------ write
    def write_chunk(self, results: Mapping[str, Mapping[str, Any]]) -> Path:
        """Write the results ``{key: {name: array}}`` of one finished chunk; returns its path."""
        keys = list(results)
        path = self.folder / _chunk_name(keys)
        # zlib took most of the stores' write time (descriptors barely compress)
        save_npz_uncompressed(path, keys=np.array(keys, dtype=str), **_pack(results[k] for k in keys))
        if self._where is not None:
            self._where.update({k: path.name for k in keys})
        return path

    @staticmethod
    def chunk_name(keys: Iterable[str]) -> str:
        """The file name :meth:`write_chunk` gives the chunk of ``keys`` (in any order)."""
        return _chunk_name(keys)

    def adopt_chunk(self, keys: Sequence[str], name: str | None = None) -> None:
        """Register the chunk a worker wrote for ``keys``; ``name``, when the worker's result gave it, must be
        the one :meth:`chunk_name` derives (an executor that does not fetch results gives None)."""
        expected = _chunk_name(keys)
        if name is not None and name != expected:
            raise CacheError(f"{self.folder}: a worker wrote chunk {name} for items that belong in {expected}")
        self.adopt(expected, keys)

    def adopt(self, name: str, keys: Iterable[str]) -> None:
        """Register the chunk file ``name`` that a worker wrote into this folder, holding ``keys``."""
        if self._where is not None:
            self._where.update({k: name for k in keys})

    # ------------------------------------------------------------------- read
    @staticmethod
    def read_chunk(path: Path) -> dict[str, dict[str, np.ndarray]]:
        """All items of one chunk file; :class:`CacheError` if it is damaged."""
        data = read_npz(path, "chunk file", CacheError)
        try:
            keys = data.pop("keys")
            if keys.ndim != 1 or keys.dtype.kind != "U":
                raise ValueError(f"keys has shape {keys.shape} and dtype {keys.dtype}")
            out: dict[str, dict[str, np.ndarray]] = {str(k): Item(path) for k in keys}
            if len(out) != len(keys):
                raise ValueError("a key repeats")
            if set(data) == {_LAYOUT, _DATA}:
                for q, fields in enumerate(_unpack(data[_LAYOUT], data[_DATA], len(keys))):
                    out[str(keys[q])].update(fields)
                return out
            for name, v in data.items():  # the one-array-per-field chunks of earlier versions
                q, _, field = name.partition(_SEP)
                if not (q.isascii() and q.isdigit() and int(q) < len(keys) and field):
                    raise ValueError(f"stray array {name!r}")
                out[str(keys[int(q)])][field] = v
        except Exception as exc:  # noqa: BLE001 - any failure to read means a damaged chunk
            raise CacheError(f"chunk {path} is damaged ({type(exc).__name__}: {' '.join(str(exc).split())[:80]})") from None
        return out

    def scan(self) -> dict[str, str]:
        """``{key: chunk file name}`` of every intact chunk; damaged chunks are removed with a warning."""
        where: dict[str, str] = {}
        if self.folder.is_dir():
            for path in sorted(self.folder.glob("chunk-*.npz")):
                try:
                    items = self.read_chunk(path)
                except CacheError as exc:
                    logger.warning("%s; removing it, its items will be recomputed", exc)
                    path.unlink(missing_ok=True)
                    continue
                where.update({k: path.name for k in items})
        self._where = where
        return where

    def done(self, keys: Iterable[str]) -> set[str]:
        """The subset of ``keys`` already computed (scans the folder on first use)."""
        where = self._where if self._where is not None else self.scan()
        return {k for k in keys if k in where}

    def get(self, key: str) -> dict[str, np.ndarray]:
        """The result of ``key`` (chunks are read once and kept)."""
        where = self._where if self._where is not None else self.load_index()
        if key not in where:
            raise CacheError(f"{self.folder} has no result for item {key}")
        name = where[key]
        if name not in self._cache:
            self._cache = {name: self.read_chunk(self.folder / name)}  # keep one chunk: bounded memory
        if key not in self._cache[name]:
            raise CacheError(f"chunk {self.folder / name} lacks the item {key} that {self.folder / INDEX} places there")
        return self._cache[name][key]

    def check(self, keys: Sequence[str], check: Callable[[int, dict[str, np.ndarray]], Any], what: str) -> None:
        """Apply ``check(i, item)`` to the item of each key; where it raises :class:`CacheError` (or the item cannot
        be read), the chunks holding those items are removed, so that a recompute cannot reuse them, and one
        :class:`CacheError` names how many ``what`` failed and the first reason."""
        bad, first = self._damaged(range(len(keys)), keys, check)
        if bad:
            n_files = self._remove_chunks(bad)
            raise CacheError(f"{len(bad)} {what} damaged, e.g. {first}; their {n_files} chunk file(s) removed")

    def drop_damaged(self, keys: Sequence[str], check: Callable[[int, dict[str, np.ndarray]], Any], what: str,
                     name: Callable[[int], str] | None = None) -> int:
        """Before a stage reuses the items of ``keys`` already in the store: apply ``check(i, item)`` (``i`` the
        item's position in ``keys``) to each, and remove the chunks of those that fail it (it raises
        :class:`CacheError`), with one warning, so that :func:`compute_missing` computes them again: an item that
        reads well but is wrong is never taken back. ``name(i)``, when given, names the item in the warning
        (``"a.png-b.png: <reason>"``). Returns the number of damaged items."""
        done = self.done(keys)
        bad, first = self._damaged([i for i, k in enumerate(keys) if k in done], keys, check, name)
        if bad:
            n_files = self._remove_chunks(bad)
            logger.warning("%d %s damaged, e.g. %s; their %d chunk file(s) removed, they are recomputed", len(bad),
                           what, first, n_files)
        return len(bad)

    def _damaged(self, positions: Iterable[int], keys: Sequence[str],
                 check: Callable[[int, dict[str, np.ndarray]], Any], name: Callable[[int], str] | None = None
                 ) -> tuple[list[str], str]:
        """The keys at ``positions`` whose item cannot be read or fails ``check``, and the first reason (prefixed by
        ``name(i)`` when given)."""
        bad: list[str] = []
        first = ""
        for i in positions:
            try:
                check(i, self.get(keys[i]))
                continue
            except CacheError as exc:
                why = " ".join(str(exc).split())
            except (KeyError, IndexError, ValueError, TypeError) as exc:  # not the layout the stage writes
                why = f"an item not as the stage writes it ({type(exc).__name__}: {exc})"
            bad.append(keys[i])
            first = first or (f"{name(i)}: {why}" if name is not None else why)
        return bad, first

    def _remove_chunks(self, keys: Sequence[str]) -> int:
        """Remove the chunk files holding ``keys`` (and forget every item in them); returns how many."""
        where = self._where if self._where is not None else self.load_index()
        names = {where[k] for k in keys if k in where}
        for name in names:
            (self.folder / name).unlink(missing_ok=True)
        self._where = {k: v for k, v in where.items() if v not in names}
        self._cache = {}
        return len(names)

    # ------------------------------------------------------------------ index
    def write_index(self, keys: list[str]) -> list[Path]:
        """Record the current keys, remove chunks none of them uses; returns the files in use."""
        where = self._where if self._where is not None else self.scan()
        missing = [k for k in keys if k not in where]
        if missing:
            raise CacheError(f"{self.folder}: {len(missing)} item(s) were not computed")
        used = sorted({where[k] for k in keys})
        for path in self.folder.glob("chunk-*.npz"):
            if path.name not in used:
                path.unlink(missing_ok=True)
        write_json(self.folder / INDEX, {"keys": keys, "chunks": [where[k] for k in keys]})
        self._where = {k: where[k] for k in keys}
        return [self.folder / u for u in used] + [self.folder / INDEX]

    def load_index(self) -> dict[str, str]:
        """The index written by :meth:`write_index`; :class:`CacheError` if missing or damaged."""
        path = self.folder / INDEX
        d = read_json(path, "the index", CacheError)
        try:
            keys, chunks = d["keys"], d["chunks"]
            if not (isinstance(keys, list) and isinstance(chunks, list) and len(keys) == len(chunks)):
                raise ValueError("keys and chunks are not lists of the same length")
            if not all(isinstance(k, str) for k in keys) or len(set(keys)) != len(keys):
                raise ValueError("keys are not unique strings")
            if not all(isinstance(c, str) and _CHUNK.fullmatch(c) for c in chunks):
                raise ValueError("a chunk is not named chunk-<hex>.npz")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise CacheError(f"the index {path} is missing or damaged ({' '.join(str(exc).split())[:80]})") from None
        self._where = dict(zip(map(str, keys), map(str, chunks)))
        return self._where

    def keys(self) -> list[str]:
        return list((self._where if self._where is not None else self.load_index()).keys())


def write_results(folder: str, keys: Sequence[str], work: Callable[[list[Any]], list[Mapping[str, Any]]],
                  tasks: list[Any]) -> str:
    """Worker: ``work(tasks)`` written as one chunk of the store at ``folder``; returns the chunk's file name.

    The worker writes its own results (compression and all), so that the process
    that hands out the work only records which chunk holds which keys.
    """
    return ItemStore(folder).write_chunk(dict(zip(keys, work(tasks)))).name


def _write_packed(job: tuple[list[str], list[Any]], folder: str,
                  work: Callable[[list[Any]], list[Mapping[str, Any]]]) -> str:
    return write_results(folder, job[0], work, job[1])


def _timed(write: Callable[[Any], str], job: Any) -> tuple[str, float]:
    """``write(job)`` and the CPU seconds of the thread that ran it."""
    t0 = time.thread_time()
    return write(job), time.thread_time() - t0


def compute_missing(store: ItemStore, keys: Sequence[str], make_task: Callable[[int], Any],
                    work: Callable[[list[Any]], list[Mapping[str, Any]]], *, workers: int = 1, chunk_size: int = 8,
                    on_chunk: Callable[[int], None] | None = None, backend: str = "processes",
                    scheduler: str | None = None) -> int:
    """Compute the items of ``keys`` that ``store`` lacks, chunk by chunk, writing each finished chunk at once.

    Args:
        store: the stage's item store.
        keys: the key of every item (duplicates are computed once).
        make_task: ``make_task(k)`` is the picklable input of item ``k`` (built only for missing items).
        work: ``work(tasks)`` returns the results of a chunk of tasks, in order; a
            module-level function (or a ``functools.partial`` of one), run on the
            executor of :func:`pipeline.core.parallel.make_executor`.
        workers: workers of the executor (1 or a single chunk runs in this process; work shorter than
            starting a pool of processes runs on threads of this process).
        chunk_size: items per chunk (a chunk is the unit of work and of resumption); on a Dask cluster fewer,
            so that every worker gets work (:func:`pipeline.core.parallel.balanced_chunk_size`).
        on_chunk: called with the number of items of each finished chunk (progress).
        backend, scheduler: the executor (:func:`pipeline.core.parallel.make_executor`);
            ``"dask"`` starts a local cluster of ``workers`` processes unless ``scheduler`` is set.

    Returns:
        The number of items computed.
    """
    from pipeline.core.parallel import make_executor, split  # noqa: PLC0415 - keeps this module's imports light

    done = store.done(keys)
    todo: list[int] = []
    seen: set[str] = set()
    for k, key in enumerate(keys):
        if key not in done and key not in seen:
            seen.add(key)
            todo.append(k)
    if not todo:
        return 0
    # absolute: the workers may run in another folder or on another machine (with the same file system)
    write = functools.partial(_write_packed, folder=str(store.folder.resolve()), work=work)

    def finish(chunk_keys: list[str], name: str | None) -> None:
        store.adopt_chunk(chunk_keys, name)
        if on_chunk is not None:
            on_chunk(len(chunk_keys))

    local = backend != "dask" and scheduler is None
    # a Dask cluster is reached first: how many workers it has (here or on other machines) sets how finely to cut
    executor = None if local else make_executor(workers, backend, scheduler)
    try:
        chunks = split(todo, chunk_size) if executor is None else executor.chunks(todo, chunk_size)
        jobs = [([keys[k] for k in c], [make_task(k) for k in c]) for c in chunks]
        n_workers = min(workers, len(jobs))
        if local and backend == "processes" and n_workers > 1:
            # the first chunks, one per worker, run on threads of this process (which start at once and run in
            # parallel where the work releases the GIL: OpenCV, PoseLib, BLAS) and time the work: a pool of
            # processes pays off only when the rest is long beside starting it; otherwise threads go on
            probe = make_executor(n_workers, "threads")
            try:
                timed = list(probe.map(functools.partial(_timed, write), jobs[:n_workers]))
            finally:
                probe.close()
            for (chunk_keys, _), (name, _) in zip(jobs, timed):
                finish(chunk_keys, name)
            jobs = jobs[n_workers:]
            rest = float(np.mean([t for _, t in timed])) * len(jobs)
            n_workers = min(n_workers, len(jobs))
            if not jobs:
                return len(todo)
            if not _pool_pays_off(rest, n_workers):
                logger.debug("%d chunks left, about %.1f CPU s: threads of this process, no pool", len(jobs), rest)
                backend = "threads"
        if executor is None:
            executor = make_executor(max(n_workers, 1), backend, scheduler)
        for i, name in executor.each(write, jobs):
            finish(jobs[i][0], name)
    finally:
        if executor is not None:
            executor.close()
    return len(todo)
