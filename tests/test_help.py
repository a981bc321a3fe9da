"""One ``--help`` smoke test for every command (issue 12, item 5).

The commands are ``python run.py`` and every module of the package that runs as
``python -m``: those with ``if __name__ == "__main__":`` and the packages with a
``__main__.py``, found by scanning the package, so that a new command is covered
without editing this file. Each prints its usage and the options a user needs.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# The options each documented command must list (a command not named here needs only a usage line).
EXPECTED = {
    "run.py": ["--methods", "--gt", "--K", "--config", "--no-reference"],
    "pipeline.run": ["--methods", "--gt", "--K"],
    "pipeline.features": ["--images", "--work", "--K", "--max-image-size"],
    "pipeline.matching": ["--work", "--pairs", "--ratio"],
    "pipeline.two_view": ["--work", "--threshold-px"],
    "pipeline.two_view_ba": ["--work", "--sigma-px"],
    "pipeline.loop_closure": ["--work", "--min-hops", "--max-fraction"],
    "pipeline.average": ["--method", "--loss", "--json", "--init", "--out"],
    "pipeline.reference": ["--images", "--out", "--K"],
    "pipeline.evaluate": ["--reference", "--align", "--rotations"],
    "pipeline.synthetic.render": ["--views", "--seed", "--out"],
    "pipeline.convert": ["--to", "--rotation-tol"],
    "pipeline.refine": ["--out"],
    "pipeline.reference.global_mapping": ["--images", "--out", "--K"],
}


def _python_m_commands() -> list[str]:
    out = []
    for path in sorted((REPO / "pipeline").rglob("*.py")):
        mod = ".".join(path.relative_to(REPO).with_suffix("").parts)
        if path.name == "__main__.py":
            out.append(mod.rsplit(".", 1)[0])
        elif re.search(r"^if __name__ == .__main__.:", path.read_text(encoding="utf-8"), re.M):
            out.append(mod)
    return sorted(set(out))


COMMANDS = ["run.py", *_python_m_commands()]


def test_every_documented_command_is_found():
    assert set(EXPECTED) <= set(COMMANDS), set(EXPECTED) - set(COMMANDS)


@pytest.mark.parametrize("command", COMMANDS)
def test_help(command: str) -> None:
    argv = [str(REPO / "run.py")] if command == "run.py" else ["-m", command]
    r = subprocess.run([sys.executable, *argv, "--help"], capture_output=True, text=True, timeout=120, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.lower().startswith("usage:") and not r.stderr.strip(), (r.stdout[:300], r.stderr[-1000:])
    for flag in EXPECTED.get(command, []):
        assert flag in r.stdout, f"{command} --help does not list {flag}"
