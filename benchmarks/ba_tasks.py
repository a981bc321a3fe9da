"""The two-view BA stage's task gathering (``pipeline.geometry.ba_stage.pair_tasks``: one task per pair, the "same
K" test of all pairs at once) against the per-pair ``np.allclose`` loop it replaced, in the same run.

    python benchmarks/ba_tasks.py [--repeats R]

The "before" is the definition kept in ``tests/geometry/test_ba_tasks.py`` (``_reference_tasks``, loaded from that
file). Input: a dense graph of 2000 cameras and 50,000 pairs with 15–400 inliers each (arrays in memory, as the
two-view result gives them), two intrinsics among the cameras, half of them known. The tasks are gathered on every
run of the stage, also when every pair's result is already stored. Both must give the same tasks (checked). Reports
median times; writes ``benchmarks/results/ba_tasks.json`` atomically.
"""

from __future__ import annotations

import argparse
import os
import runpy
import types
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from _common import median_time as _timed, save_results  # noqa: E402  (benchmarks/, the script's folder)
from pipeline.geometry.ba_stage import pair_tasks  # noqa: E402
from pipeline.synthetic.protocols import dense_graph  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "ba_tasks.json"
REFERENCE = runpy.run_path(str(HERE.parent / "tests" / "geometry" / "test_ba_tasks.py"))["_reference_tasks"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    vg = dense_graph(2000, 50000, seed=0)[0].vg
    M, rng = vg.n_edges, np.random.default_rng(0)
    off = np.r_[0, np.cumsum(rng.integers(15, 400, M))]
    x1, x2 = rng.random((off[-1], 2)), rng.random((off[-1], 2))
    data = types.SimpleNamespace(vg=vg, correspondences=lambda k: (x1[off[k]:off[k + 1]], x2[off[k]:off[k + 1]]))
    K = np.tile(np.diag([1000.0, 1000.0, 1.0]), (vg.n_cameras, 1, 1))
    K[::3, 0, 0] = 1100.0
    t_in, known = rng.standard_normal((M, 3)), rng.random(vg.n_cameras) < 0.5
    rows = []
    print(f"{'mode':>10s} {'pairs':>6s} {'before s':>9s} {'after s':>8s} {'speedup':>7s}  same")
    for mode in ("shared", "per_camera"):
        t_after, got = _timed(lambda: pair_tasks(data, K, t_in, mode, known), a.repeats)
        t_before, want = _timed(lambda: REFERENCE(data, K, t_in, mode, known), a.repeats)
        same = len(got) == len(want) and all(x.dtype == y.dtype and np.array_equal(x, y)
                                             for p, q in zip(got, want) for x, y in zip(p, q))
        rows.append({"mode": mode, "n_edges": M, "before_s": t_before, "after_s": t_after,
                     "speedup": t_before / t_after, "identical": bool(same), "repeats": a.repeats})
        print(f"{mode:>10s} {M:6d} {t_before:9.3f} {t_after:8.3f} {t_before / t_after:7.2f}  {same}")
    save_results(a.json, rows, "ba_tasks.py", argv)
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
