"""What several benchmarks share: the median wall time of repeated calls (the machine is shared and noisy), and
their results file (rows, the command that made them, the machine)."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from pipeline.core.atomic import write_json


def median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """The median wall time of ``repeats`` calls of ``fn`` (seconds) and the last call's result."""
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def save_results(path: Path, rows: list[dict[str, Any]], script: str, argv: Sequence[str] | None) -> None:
    """Write ``{"rows", "command", "machine"}`` to ``path`` atomically and say so; ``script``: the benchmark's file
    name, ``argv``: its arguments (None: the command line's)."""
    write_json(path, {"rows": rows, "command": f"python benchmarks/{script} " + " ".join(argv or sys.argv[1:]),
                      "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}})
    print(f"wrote {path}")
