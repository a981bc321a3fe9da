"""Fixtures of the bad-input matrix and the fuzzer: a tiny rendered scene, a finished run on it, and a command runner.

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
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
TINY = SceneConfig(width=240, height=180, focal=210.0, supersample=1)
N_VIEWS = 6
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


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """6 rendered views of 240×180 pixels with their true cameras (``cameras.txt``)."""
    out = tmp_path_factory.mktemp("tiny_scene")
    render_scene(N_VIEWS, 0, out, config=TINY)
    return out


@pytest.fixture(scope="session")
def tiny_config(tmp_path_factory) -> Path:
    """run.py options for fast cases: IRLS only, no reference, no plots, no process pools."""
    p = tmp_path_factory.mktemp("tiny_cfg") / "tiny.yaml"
    p.write_text("run:\n  methods: [irls]\n  reference: false\n  plots: false\n"
                 "features:\n  workers: 1\nmatching:\n  workers: 1\n"
                 "two_view:\n  workers: 1\ntwo_view_ba:\n  workers: 1\n")
    return p


@pytest.fixture(scope="session")
def baseline(tiny_scene, tiny_config, tmp_path_factory) -> Path:
    """A finished ``run.py`` on the tiny scene (with ``--gt``): the OUT folder to copy, damage and re-run."""
    from pipeline import run

    out = tmp_path_factory.mktemp("baseline") / "out"
    t0 = time.perf_counter()
    run.main(tiny_scene, out, config=tiny_config, gt=tiny_scene / "cameras.txt", quiet=True, reference=False)
    assert (out / "metrics.json").is_file(), f"baseline run failed after {time.perf_counter() - t0:.1f} s"
    return out


@pytest.fixture
def run_copy(baseline, tmp_path) -> Path:
    """This test's own copy of the finished OUT folder (every stage up to date)."""
    return Path(shutil.copytree(baseline, tmp_path / "out", copy_function=shutil.copy2))
