"""Run a reader of other programs' files in a child process, with a time and a memory limit.

Some libraries hang on a truncated file or allocate gigabytes on a damaged one
(pycolmap's model readers do both). Such a read runs here in a child process
forked from a helper process that imported the reader's modules once, under an
address-space limit, and is killed at its time limit: a call costs a fork, not a
fresh interpreter. The helper ends when this process ends (its stdin closes);
the child's own output is discarded.
"""

from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Callable, Sequence

__all__ = ["SandboxError", "run_limited"]

_HELPER = r'''
import importlib, os, pickle, select, signal, struct, sys, time
proto_in, proto_out = os.fdopen(os.dup(0), "rb"), os.fdopen(os.dup(1), "wb")
null = os.open(os.devnull, os.O_RDWR)
for fd in (0, 1, 2):
    os.dup2(null, fd)
for name in sys.argv[1:]:
    importlib.import_module(name)

def read_msg(f):
    head = f.read(4)
    if len(head) < 4:
        return None
    return pickle.loads(f.read(struct.unpack("<I", head)[0]))

def write_msg(f, obj):
    data = pickle.dumps(obj)
    f.write(struct.pack("<I", len(data)) + data)
    f.flush()

while True:
    req = read_msg(proto_in)
    if req is None:
        break
    fn, args, memory, timeout = req
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        try:
            import ctypes
            ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)  # die with the helper
        except Exception:
            pass
        if memory:
            import resource
            resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
        try:
            result = ("ok", fn(*args))
        except BaseException as exc:
            result = ("error", f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}")
        try:
            data = pickle.dumps(result)
        except Exception as exc:
            data = pickle.dumps(("error", f"unpicklable result ({exc})"))
        with os.fdopen(w, "wb") as f:
            f.write(data)
        os._exit(0)
    os.close(w)
    chunks, deadline = [], time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([r], [], [], left)[0]:
            os.kill(pid, signal.SIGKILL)
            reply = ("timeout", timeout)
            break
        chunk = os.read(r, 1 << 16)
        if not chunk:
            reply = None
            break
        chunks.append(chunk)
    os.close(r)
    _, status = os.waitpid(pid, 0)
    if reply is None:
        data = b"".join(chunks)
        reply = pickle.loads(data) if data else ("crashed", os.waitstatus_to_exitcode(status))
    write_msg(proto_out, reply)
'''


class SandboxError(Exception):
    """The sandboxed call failed: its exception, a crash, or its time limit (the message says which)."""


class _Helper:
    """A helper process with ``preload`` imported, started on first use and again if it died."""

    def __init__(self, preload: tuple[str, ...]) -> None:
        self.proc: subprocess.Popen | None = None
        self.preload = preload
        self.lock = threading.Lock()

    def call(self, request: tuple) -> tuple:
        with self.lock:
            if self.proc is None or self.proc.poll() is not None:
                self._start()
            proc: Any = self.proc
            data = pickle.dumps(request)
            try:
                proc.stdin.write(struct.pack("<I", len(data)) + data)
                proc.stdin.flush()
                head = proc.stdout.read(4)
                if len(head) < 4:
                    raise EOFError
                return pickle.loads(proc.stdout.read(struct.unpack("<I", head)[0]))
            except (OSError, EOFError):
                self.proc = None
                return ("crashed", "the helper process ended")
            except BaseException:  # interrupted mid-exchange (Ctrl-C): the protocol is out of step
                proc.kill()
                self.proc = None
                raise

    def _start(self) -> None:
        root = str(Path(__file__).resolve().parents[2])  # the folder holding this `pipeline` package
        env = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE",
               "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
        self.proc = subprocess.Popen([sys.executable, "-c", _HELPER, *self.preload], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)


_HELPERS: dict[tuple[str, ...], _Helper] = {}  # one per set of preloaded modules: each forks only what it needs


def run_limited(fn: Callable[..., Any], *args: Any, timeout: float, memory_bytes: int | None = None,
                preload: Sequence[str] = ()) -> Any:
    """``fn(*args)`` computed in a child process; its (picklable) result.

    Args:
        fn: a module-level function (it is pickled by reference).
        args: its picklable arguments.
        timeout: seconds before the child is killed.
        memory_bytes: the child's address-space limit (None: none).
        preload: modules the helper process imports once, so that a call does not pay for them.

    Raises:
        SandboxError: ``fn`` raised (its type and message), the child crashed, or it timed out.
    """
    key = tuple(sorted(set(preload)))
    helper = _HELPERS.setdefault(key, _Helper(key))
    status, value = helper.call((fn, args, memory_bytes, float(timeout)))
    if status == "ok":
        return value
    if status == "timeout":
        raise SandboxError(f"it did not finish within {value:.0f} s")
    if status == "crashed":
        raise SandboxError(f"it crashed ({value if isinstance(value, str) else f'exit code {value}'})")
    raise SandboxError(value)
