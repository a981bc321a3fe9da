"""The command runner of the bad-input matrix (the tiny scene and its finished run are in ``tests/conftest.py``).

Every matrix case runs a command line as a new user would: ``python run.py …`` or
``python -m pipeline.<command> …``, in a process of its own (its exit code, its
stderr, its working folder). Paying the interpreter's imports for each of ~90
cases would take minutes on this machine, so :class:`Commands` keeps one helper
process that has imported the package and forks a fresh child per command; the
child runs the command exactly as ``python -m`` / ``python run.py`` would
(:mod:`runpy`, ``__name__ == "__main__"``). ``BADINPUT_EXEC=1`` runs every case
in a new interpreter instead (``subprocess``), to check that the two agree.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[2]
MEMORY_LIMIT = 8 << 30  # address space of one command: far more than a tiny scene needs

# The helper: imports the package once, then forks one child per request. A request is one JSON
# line {argv, cwd, stdout, stderr, timeout, memory}; the reply one line {rc}. rc is None on timeout. The
# address-space limit turns a reader that would allocate gigabytes into a failed case, not a swapping machine.
_SERVER = r"""
import json, os, runpy, signal, sys, time
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.umask(0o022)
import pipeline.run, pipeline.features, pipeline.matching, pipeline.two_view, pipeline.two_view_ba  # noqa
import pipeline.average, pipeline.evaluate, pipeline.reference.incremental, pipeline.synthetic.render  # noqa
proto = os.fdopen(os.dup(1), "w")
for line in sys.stdin:
    req = json.loads(line)
    pid = os.fork()
    if pid == 0:
        os.setpgid(0, 0)
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (req["memory"], resource.getrlimit(resource.RLIMIT_AS)[1]))
        os.chdir(req["cwd"])
        out = os.open(req["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        err = os.open(req["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(out, 1)
        os.dup2(err, 2)
        argv = req["argv"]
        code = 0
        try:
            if argv[0] == "-m":
                sys.argv = [argv[1], *argv[2:]]
                runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
            else:
                sys.argv = list(argv)
                runpy.run_path(argv[0], run_name="__main__")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:
            import traceback
            traceback.print_exc()
            code = 1
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    deadline = time.monotonic() + req["timeout"]
    rc = None
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            rc = os.waitstatus_to_exitcode(status)
            break
        time.sleep(0.01)
    if rc is None:
        os.killpg(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    proto.write(json.dumps({"rc": rc}) + "\n")
    proto.flush()
"""


@dataclass
class Result:
    """What a command did: exit code (None if it hung), stdout, stderr."""

    rc: int | None
    stdout: str
    stderr: str

    @property
    def lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.strip()]


class Commands:
    """Runs ``python run.py …`` / ``python -m pipeline.X …`` in a process of its own per call."""

    def __init__(self, scratch: Path) -> None:
        self.scratch = scratch
        self.env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_WAIT_POLICY": "PASSIVE"}
        self.exec_each = os.environ.get("BADINPUT_EXEC") == "1"
        self.server: subprocess.Popen | None = None
        self.k = 0

    def _server(self) -> subprocess.Popen:
        if self.server is None or self.server.poll() is not None:
            self.server = subprocess.Popen([sys.executable, "-c", _SERVER], stdin=subprocess.PIPE,
                                           stdout=subprocess.PIPE, text=True, cwd=REPO, env=self.env)
        return self.server

    def __call__(self, *argv: str | Path, cwd: Path | None = None, timeout: float = 300) -> Result:
        """Run ``python run.py ARGS`` (first item ``"run.py"``) or ``python -m MODULE ARGS`` (first items ``"-m", MODULE``)."""
        args = [str(a) for a in argv]
        if args[0] == "run.py":
            args[0] = str(REPO / "run.py")
        self.k += 1
        out, err = self.scratch / f"{self.k}.out", self.scratch / f"{self.k}.err"
        cwd = cwd or REPO
        if self.exec_each:
            try:
                r = subprocess.run([sys.executable, *args], cwd=cwd, env=self.env, capture_output=True, text=True,
                                   timeout=timeout)
                return Result(r.returncode, r.stdout, r.stderr)
            except subprocess.TimeoutExpired as exc:
                return Result(None, str(exc.stdout or ""), str(exc.stderr or ""))
        server = self._server()
        req = {"argv": args, "cwd": str(cwd), "stdout": str(out), "stderr": str(err), "timeout": timeout,
               "memory": MEMORY_LIMIT}
        server.stdin.write(json.dumps(req) + "\n")  # type: ignore[union-attr]
        server.stdin.flush()  # type: ignore[union-attr]
        rc = json.loads(server.stdout.readline())["rc"]  # type: ignore[union-attr]
        return Result(rc, out.read_text(errors="replace"), err.read_text(errors="replace"))

    def close(self) -> None:
        if self.server is not None and self.server.poll() is None:
            self.server.stdin.close()  # type: ignore[union-attr]
            self.server.wait(30)


@pytest.fixture(scope="session")
def cli(tmp_path_factory) -> Commands:
    c = Commands(tmp_path_factory.mktemp("cli"))
    yield c
    c.close()


