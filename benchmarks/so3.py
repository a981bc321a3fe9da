"""Batched SO(3) exp and log against scipy.spatial.transform.Rotation, in the same run.

    python benchmarks/so3.py [--quick] [--n N] [--repeats R]

Times ``so3.exp`` (rotation vectors → matrices) and ``so3.log`` (matrices →
rotation vectors) on 10⁶ Haar-random rotations (10⁵ with --quick), against
``Rotation.from_rotvec(w).as_matrix()`` and ``Rotation.from_matrix(R).as_rotvec()``.
Reports the median of the repeats and the ratio ours / scipy (target ≤ 2).
Also checks that both give the same numbers. Writes
``benchmarks/results/so3.json`` atomically.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import scipy  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from pipeline.core import so3  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "so3.json"


def _time(fn, repeats: int) -> tuple[float, list[float]]:
    fn()  # warm-up: page faults and caches
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="10⁵ rotations, 3 repeats")
    parser.add_argument("--n", type=int, default=None, help="number of rotations (default 10⁶)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats (default 7)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    n = args.n or (100_000 if args.quick else 1_000_000)
    repeats = args.repeats or (3 if args.quick else 7)

    rng = np.random.default_rng(0)
    R = so3.random_rotations(n, rng)
    w = Rotation.from_matrix(R).as_rotvec()

    # Same numbers first: a fast wrong answer is no answer.
    exp_diff = float(np.abs(so3.exp(w) - Rotation.from_rotvec(w).as_matrix()).max())
    log_diff = float(np.abs(so3.log(R) - w).max())

    rows = []
    for op, ours, theirs in [
        ("exp", lambda: so3.exp(w), lambda: Rotation.from_rotvec(w).as_matrix()),
        ("log", lambda: so3.log(R), lambda: Rotation.from_matrix(R).as_rotvec()),
    ]:
        t_ours, all_ours = _time(ours, repeats)
        t_scipy, all_scipy = _time(theirs, repeats)
        rows.append(
            {
                "op": op,
                "n": n,
                "ours_s": t_ours,
                "scipy_s": t_scipy,
                "ratio": t_ours / t_scipy,
                "ours_all_s": all_ours,
                "scipy_all_s": all_scipy,
            }
        )

    print(f"SO(3) batched maps, n = {n:,}, median of {repeats} repeats (numpy {np.__version__}, scipy {scipy.__version__})")
    print(f"{'op':<5}{'ours (s)':>12}{'scipy (s)':>12}{'ours/scipy':>12}{'target':>9}")
    for r in rows:
        ok = "ok" if r["ratio"] <= 2.0 else "MISSED"
        print(f"{r['op']:<5}{r['ours_s']:>12.4f}{r['scipy_s']:>12.4f}{r['ratio']:>12.2f}{'<= 2 ' + ok:>9}")
    print(f"max |exp - scipy| = {exp_diff:.2e}, max |log - scipy| = {log_diff:.2e}")
    write_json(
        args.out,
        {
            "benchmark": "so3",
            "n": n,
            "repeats": repeats,
            "results": rows,
            "max_abs_diff": {"exp": exp_diff, "log": log_diff},
            "target_ratio": 2.0,
            "met": all(r["ratio"] <= 2.0 for r in rows),
            "machine": {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__, "cpus": os.cpu_count()},
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
