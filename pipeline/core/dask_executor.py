"""Per-item work on ``dask.distributed``: a local cluster of single-threaded worker processes, or an existing one.

:class:`DaskExecutor` follows the :class:`pipeline.core.parallel.Executor`
protocol: ``map(fn, items)`` submits every item at once (the scheduler balances
them over the workers) and yields the results in item order. The functions it
runs are module-level and take small arguments (paths, item keys, configs): each
task reads what it needs from disk itself, so that nothing of the collection is
held by the client or shipped through the scheduler.

- ``DaskExecutor(workers)`` starts a ``LocalCluster`` of ``workers`` worker
  *processes* with one thread each (OpenCV, BLAS and OpenMP set to one thread in
  each, so that results do not depend on thread partitioning); its scratch space
  is a temporary folder removed on :meth:`close`, and its workers die with this
  process, even on SIGKILL;
- ``DaskExecutor(scheduler="tcp://host:8786")`` uses an existing cluster, the
  way a user with several machines would (``dask scheduler`` and ``dask worker
  ADDRESS --nthreads 1`` on each machine, with the same data folders and the
  pipeline importable); closing disconnects and leaves the cluster running.

:func:`local_cluster` starts one cluster for a whole run, so that the stages of
``run.py`` share it (each stage connects by address).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import signal
import tempfile
from typing import Any, Callable, Iterator, Sequence, TypeVar

from pipeline.core.errors import PipelineError
from pipeline.core.parallel import balanced_chunk_size, die_with_parent, split

__all__ = ["DaskExecutor", "LocalDaskCluster", "local_cluster", "check_scheduler", "client_session", "single_thread",
           "require_distributed"]

logger = logging.getLogger(__name__)
T = TypeVar("T")
R = TypeVar("R")

_ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "OMP_WAIT_POLICY": "PASSIVE"}
#: Dask settings of the local cluster. Its scheduler and nannies run in this process, beside the two
#: workers on a small machine, so their housekeeping comes out of a worker's core: the statistical
#: profiler in each worker (a stack sample every 10 ms, for a dashboard this cluster does not start), the
#: event-loop tick (20 ms), the system monitor (500 ms) and the nannies' memory check (100 ms). None
#: of them schedules or balances tasks. Measured on 2 cores, 120 pairs in 90 tasks: this process's
#: event-loop CPU 0.63 -> 0.40 s.
LEAN_CONFIG = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "500ms",
               "distributed.admin.system-monitor.interval": "2s",
               "distributed.worker.memory.monitor-interval": "1s"}
CONNECT_TIMEOUT_S = 10
_DISTRIBUTED_LOG = logging.getLogger("distributed")


def require_distributed() -> Any:
    """The ``distributed`` module; :class:`PipelineError` with the install command if it is missing."""
    try:
        import distributed  # noqa: PLC0415 - optional at import time of the package
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise PipelineError(f"executor 'dask' needs dask.distributed ({exc}); pip install 'dask[distributed]'") from None
    return distributed


def single_thread(client_pid: int | None = None) -> int:
    """Worker set-up: one thread for OpenCV, BLAS and OpenMP; die with the client that started this worker.

    Args:
        client_pid: pid of the process whose ``LocalCluster`` started this worker
            (None for a worker of an external cluster).
    Returns:
        this worker's pid.
    """
    os.environ.update(_ONE_THREAD)
    with contextlib.suppress(ImportError):
        import cv2  # noqa: PLC0415

        cv2.setNumThreads(1)
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits  # noqa: PLC0415

        threadpool_limits(1)
    if client_pid is not None and os.getppid() == client_pid:
        die_with_parent(client_pid)
        # a worker of our own cluster: Ctrl-C reaches the whole process group, and the client closes the cluster
        # and says so in one line; the worker prints no traceback of its own
        with contextlib.suppress(ValueError):  # not this process's main thread: left as it is
            signal.signal(signal.SIGINT, signal.SIG_IGN)
    return os.getpid()


class LocalDaskCluster:
    """A ``LocalCluster`` of ``workers`` single-threaded worker processes, scratch space in a temporary folder.

    Args:
        workers: worker processes (default: one per core).
    """

    def __init__(self, workers: int | None = None) -> None:
        distributed = require_distributed()
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        # the scheduler and nannies log here at INFO, also as clients leave and when the cluster closes
        self._log_level = _DISTRIBUTED_LOG.level
        _DISTRIBUTED_LOG.setLevel(max(logging.WARNING, self._log_level))
        self.scratch = tempfile.mkdtemp(prefix="rotavg-dask-")
        import dask  # noqa: PLC0415 - with distributed

        try:
            with dask.config.set(LEAN_CONFIG):  # read by the scheduler and nannies here, passed on to the workers
                self.cluster = distributed.LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                    silence_logs=logging.ERROR, local_directory=self.scratch, env=dict(_ONE_THREAD),
                    host="127.0.0.1")
        except BaseException:
            shutil.rmtree(self.scratch, ignore_errors=True)
            _DISTRIBUTED_LOG.setLevel(self._log_level)
            raise
        self.address: str = self.cluster.scheduler_address
        try:
            with distributed.Client(self.address, timeout=CONNECT_TIMEOUT_S, set_as_default=False) as client:
                client.run(single_thread, os.getpid())
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        try:
            self.cluster.close()
        finally:
            shutil.rmtree(self.scratch, ignore_errors=True)
            _DISTRIBUTED_LOG.setLevel(self._log_level)

    def __enter__(self) -> "LocalDaskCluster":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


@contextlib.contextmanager
def local_cluster(workers: int | None = None) -> Iterator[LocalDaskCluster]:
    """A :class:`LocalDaskCluster` for the duration of a ``with`` block (closed also on Ctrl-C)."""
    cluster = LocalDaskCluster(workers)
    try:
        yield cluster
    finally:
        cluster.close()


#: A scheduler's address: ``[protocol://]host:port`` (host a name, an IPv4 address or a bracketed IPv6 one).
ADDRESS = re.compile(r"(?:[a-z][a-z0-9+]*://)?(?:\[[0-9A-Fa-f:.]+\]|[\w.\-]+):\d{1,5}|inproc://\S+")


def check_scheduler(address: str, timeout: float | None = None) -> int:
    """The number of workers of the Dask scheduler at ``address``; :class:`PipelineError` if unreachable or empty.

    ``timeout``: seconds to wait for the connection (default :data:`CONNECT_TIMEOUT_S`).
    """
    if not ADDRESS.fullmatch(str(address).strip()):  # a client of a malformed address hangs 20 s in its __del__
        raise PipelineError(f"--scheduler {address!r} is not a Dask scheduler address; expected [PROTOCOL://]HOST:PORT, "
                            "e.g. tcp://127.0.0.1:8786 (what `dask scheduler` prints)")
    distributed = require_distributed()
    try:
        with distributed.Client(address, timeout=timeout or CONNECT_TIMEOUT_S, set_as_default=False) as client:
            n = len(client.scheduler_info()["workers"])
    except (OSError, TimeoutError, ValueError) as exc:
        raise PipelineError(f"cannot reach the Dask scheduler at {address!r} ({' '.join(str(exc).split())[:100]}); "
                            "start one (`dask scheduler`, `dask worker ADDRESS --nthreads 1`) or drop --scheduler"
                            ) from None
    if n == 0:
        raise PipelineError(f"the Dask scheduler at {address!r} has no worker; start `dask worker {address} "
                            "--nthreads 1` on each machine")
    return n


_SESSION: dict[str, Any] | None = None


@contextlib.contextmanager
def client_session() -> Iterator[None]:
    """Within the block, the stages that reach a scheduler by its address share one client of it.

    Each stage used to check the scheduler, connect and set up the workers again: a fifth of a second of
    work in this process, during which the workers waited. ``run.py`` runs its stages in one session; the
    clients are closed at its end (nested sessions share the outer one).
    """
    global _SESSION
    if _SESSION is not None:
        yield
        return
    _SESSION = {}
    try:
        yield
    finally:
        clients, _SESSION = _SESSION, None
        for client in clients.values():
            with contextlib.suppress(Exception):
                client.close()


def _connect(address: str, client_pid: int | None = None) -> Any:
    """A client of the scheduler at ``address`` whose workers run single-threaded.

    Args:
        client_pid: this process's pid when it started the cluster (its workers then die with it); None for an
            external scheduler, which is checked first.
    """
    distributed = require_distributed()
    if client_pid is None:
        check_scheduler(address)
    client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    try:
        client.run(single_thread, client_pid)
    except BaseException:
        client.close()
        raise
    return client


def _session_client(address: str) -> Any | None:
    """The session's client of ``address`` (connected on first use), or None outside a session."""
    if _SESSION is None:
        return None
    client = _SESSION.get(address)
    if client is None or client.status != "running":
        client = _SESSION[address] = _connect(address)
    return client


class DaskExecutor:
    """Maps functions over items on ``dask.distributed``, results in order.

    Args:
        workers: worker processes of the local cluster started when ``scheduler``
            is None (default: one per core).
        scheduler: address of an existing scheduler (``tcp://host:8786``); its
            workers are used as they are and the cluster outlives this executor.
    """

    def __init__(self, workers: int | None = None, scheduler: str | None = None) -> None:
        distributed = require_distributed()
        self._local: LocalDaskCluster | None = None
        self._shared = False
        try:
            if scheduler is None:
                self._local = LocalDaskCluster(workers)
                self.client = _connect(self._local.address, os.getpid())
            else:
                shared = _session_client(scheduler)
                self.client, self._shared = (shared, True) if shared is not None else (_connect(scheduler), False)
            self.workers = max(1, len(self.client.scheduler_info()["workers"]))
        except BaseException:
            if self._local is not None:
                self._local.close()
            raise

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        """``fn`` of every item, in item order; every item is submitted at once."""
        futures = self.client.map(fn, list(items), pure=False)
        try:
            for f in futures:
                yield f.result()
                f.release()
        finally:
            self.client.cancel(futures)

    def chunks(self, items: Sequence[T], chunk_size: int) -> list[Sequence[T]]:
        """``items`` in tasks of at most ``chunk_size``, fewer where a worker would get too few tasks."""
        return split(items, balanced_chunk_size(len(items), chunk_size, self.workers))

    def each(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[tuple[int, R | None]]:
        """``(index, None)`` as each item's ``fn`` finishes, in any order; the results are not fetched.

        For work that leaves its output on disk (the per-item stages write their own chunks): fetching a
        result costs a round trip through the scheduler per task, about half of this process's CPU per
        task (measured: 4.2 against 2.1 ms). A task's error is raised here.
        """
        distributed = require_distributed()
        futures = self.client.map(fn, list(items), pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for f in distributed.as_completed(futures, loop=self.client.loop):
                if f.status != "finished":
                    f.result()  # raises the task's exception
                    raise PipelineError(f"a Dask task ended as {f.status!r}")
                f.release()
                yield index[f.key], None
        finally:
            self.client.cancel(futures)

    def close(self) -> None:
        if self._shared:  # the session's connection serves the next stage too
            return
        try:
            self.client.close()
        finally:
            if self._local is not None:
                self._local.close()

    def __enter__(self) -> "DaskExecutor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
