"""Where per-item work runs: in this process, in a pool of processes, or on a Dask cluster.

Every per-image and per-pair stage maps a picklable function over chunks of
work through an :class:`Executor`. The result is the same whatever runs it: the
functions are deterministic and results come back in order.

- ``serial``: in this process (tests, small runs, debugging);
- ``threads``: a thread pool, for work in libraries that release the GIL
  (OpenCV's SIFT and FLANN, BLAS);
- ``processes``: a local pool; its workers die with their parent, even on
  SIGKILL (Linux ``PR_SET_PDEATHSIG``, and a watchdog thread elsewhere);
- ``dask``: ``dask.distributed`` (:mod:`pipeline.core.dask_executor`), a
  ``LocalCluster`` or an existing scheduler.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Literal, Protocol, Sequence, TypeVar

from pipeline.core.config import Config, option

__all__ = ["Executor", "SerialExecutor", "ThreadExecutor", "ProcessExecutor", "make_executor", "die_with_parent",
           "ExecutorOptions", "BACKENDS", "balanced_chunk_size", "TASKS_PER_WORKER", "split"]

logger = logging.getLogger(__name__)
T = TypeVar("T")
R = TypeVar("R")


class Executor(Protocol):
    """Maps a function over items, yielding results in order.

    ``each(fn, items)`` is for work that leaves its output on disk: it yields ``(index, result)`` as each item
    finishes, in any order, where ``result`` may be None when fetching it would cost a round trip (Dask).
    ``chunks(items, chunk_size)`` cuts items into tasks of at most ``chunk_size`` (a Dask cluster cuts finer, so
    that every worker gets work: :func:`balanced_chunk_size`).
    """

    workers: int

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]: ...

    def each(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R | None]]: ...

    def chunks(self, items: Sequence[T], chunk_size: int) -> list[Sequence[T]]: ...

    def close(self) -> None: ...


def split(items: Sequence[T], size: int) -> list[Sequence[T]]:
    """``items`` in consecutive chunks of ``size`` (the last one shorter)."""
    return [items[s:s + size] for s in range(0, len(items), size)]


class _Fetching:
    """:meth:`Executor.each` for executors whose results cost nothing to fetch: ``map``'s, numbered; and
    :meth:`Executor.chunks`: items cut as configured (a local pool is sized to the chunks)."""

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        raise NotImplementedError

    def each(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R | None]]:
        return enumerate(self.map(fn, items))

    def chunks(self, items: Sequence[T], chunk_size: int) -> list[Sequence[T]]:
        return split(items, chunk_size)


class SerialExecutor(_Fetching):
    """Runs everything in this process."""

    workers = 1

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        for it in items:
            yield fn(it)

    def close(self) -> None:
        pass

    def __enter__(self) -> "SerialExecutor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class ThreadExecutor(_Fetching):
    """A thread pool in this process.

    While it is open, BLAS runs single-threaded (threadpoolctl): the pool's threads are
    the parallelism, and OpenBLAS threads inside each of them only oversubscribe the cores
    (measured on 2 loaded cores: a 1500×1500 descriptor product took 2.7× the CPU and 1.6×
    the wall time with 2 BLAS threads). The products are the same either way.
    """

    def __init__(self, workers: int) -> None:
        self.workers = max(1, int(workers))
        self._pool = ThreadPoolExecutor(max_workers=self.workers)
        self._blas = _single_threaded_blas() if self.workers > 1 else None

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        return self._pool.map(fn, items)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._blas is not None:
            self._blas.restore_original_limits()
            self._blas = None

    def __enter__(self) -> "ThreadExecutor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _single_threaded_blas() -> Any:
    """BLAS limited to one thread until ``.restore_original_limits()``; None without threadpoolctl."""
    try:
        from threadpoolctl import threadpool_limits  # noqa: PLC0415
    except ImportError:  # pragma: no cover - an optional speed-up
        return None
    return threadpool_limits(limits=1, user_api="blas")


def _watch_parent(ppid: int) -> None:
    while True:
        if os.getppid() != ppid:
            os._exit(1)
        time.sleep(0.5)


def die_with_parent(parent_pid: int | None = None) -> None:
    """Make this (worker) process exit when its parent dies, even by SIGKILL.

    Args:
        parent_pid: the pid of the process that started this one. A parent that
            died while this worker was still starting (before this call) ends the
            worker at once; without it that worker would watch its new parent, init.
    """
    expected = os.getppid() if parent_pid is None else parent_pid
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            PR_SET_PDEATHSIG = 1
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        except OSError:  # pragma: no cover - no libc: the watchdog below still works
            pass
    if os.getppid() != expected:
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(expected,), daemon=True).start()


def _init_worker(threads: int, parent_pid: int | None = None) -> None:
    die_with_parent(parent_pid)
    # Ctrl-C reaches the whole process group: the parent stops the pool and says so in one line, a worker says nothing
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # one pool worker per core: keep each worker's own libraries to one thread
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        import cv2  # noqa: PLC0415

        cv2.setNumThreads(threads)
    except ImportError:  # pragma: no cover
        pass


class ProcessExecutor(_Fetching):
    """A local process pool whose workers never outlive this process."""

    def __init__(self, workers: int) -> None:
        self.workers = max(1, int(workers))
        # spawn, not fork: a child forked from a process whose OpenCV thread pool has run
        # (SIFT, FLANN) deadlocks in cv2.setNumThreads (measured: every worker, forever)
        self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker, initargs=(1, os.getpid()))

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        # the workers are spawned here (every item is submitted at once): started with SIGINT ignored, a Ctrl-C
        # while they import prints no traceback of theirs (the disposition survives exec; Python then keeps it)
        try:
            previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        except ValueError:  # not the main thread
            return self._pool.map(fn, items)
        try:
            return self._pool.map(fn, items)
        finally:
            signal.signal(signal.SIGINT, previous)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "ProcessExecutor":
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        if exc_type is not None:  # interrupted or failed: the workers ignore Ctrl-C, so stop them here
            for proc in list(getattr(self._pool, "_processes", {}).values()):
                proc.terminate()
            self._pool.shutdown(wait=False, cancel_futures=True)
            return
        self.close()


BACKENDS = ("auto", "serial", "threads", "processes", "dask")
#: A Dask cluster gets at least this many tasks per worker where the items allow it: the last tasks of a stage
#: leave workers idle, the more so the fewer tasks each worker has (2 workers, 120 pairs: 1.66x the speed of one
#: worker with 4 pairs per task, 1.56x with 8), and a cluster of many machines has many workers.
TASKS_PER_WORKER = 16


def balanced_chunk_size(n_items: int, chunk_size: int, workers: int) -> int:
    """Items per task on a Dask cluster of ``workers`` workers: at most ``chunk_size``, fewer when that would leave
    fewer than :data:`TASKS_PER_WORKER` tasks per worker (a chunk is also the unit of resumption, and the items'
    results do not depend on how they are cut)."""
    return max(1, min(int(chunk_size), -(-int(n_items) // (TASKS_PER_WORKER * max(1, int(workers))))))


@dataclass(frozen=True, kw_only=True)
class ExecutorOptions(Config):
    """Where a per-image or per-pair stage runs its work (runtime options: they never change a result).

    A stage config derives from this and declares its own ``workers``.
    """

    executor: Literal["auto", "serial", "threads", "processes", "dask"] = option(
        "auto", "where per-item work runs: auto (the stage's default pool), serial, threads, processes, or dask "
        "(a local cluster of `workers` processes)", runtime=True)
    scheduler: str | None = option(None, "address of an existing Dask scheduler (tcp://host:8786); implies "
                                   "executor dask", runtime=True)

    def backend(self, auto: str) -> str:
        """The backend to use: ``auto`` replaced by the stage's default, ``dask`` whenever a scheduler is set."""
        if self.scheduler:
            return "dask"
        return auto if self.executor == "auto" else self.executor

    def open_executor(self, n_tasks: int, auto: str) -> Any:
        """An executor for ``n_tasks`` tasks (a local pool of at most ``n_tasks`` workers)."""
        workers = int(getattr(self, "workers", 1))
        backend = self.backend(auto)
        return make_executor(workers if backend == "dask" else min(workers, max(n_tasks, 1)), backend, self.scheduler)


def make_executor(workers: int = 1, backend: str = "processes", scheduler: str | None = None) -> Any:
    """An executor for ``workers`` workers.

    Args:
        workers: workers of a local pool or cluster; 1 runs serially.
        backend: ``"serial"``, ``"threads"``, ``"processes"`` or ``"dask"``.
        scheduler: address of an existing Dask scheduler (implies ``"dask"``).
    """
    if scheduler is not None or backend == "dask":
        from pipeline.core.dask_executor import DaskExecutor  # noqa: PLC0415 - optional dependency

        return DaskExecutor(workers=workers, scheduler=scheduler)
    if backend == "serial" or workers <= 1:
        return SerialExecutor()
    if backend == "threads":
        return ThreadExecutor(workers)
    if backend == "processes":
        return ProcessExecutor(workers)
    raise ValueError(f"unknown executor backend {backend!r}; choose serial, threads, processes or dask")
