"""The view-graph robust filter (step 6) solving only the components with a cycle, against one subgraph per component
(lone cameras and trees built, then skipped), in the same run.

    python benchmarks/robust_components.py [--repeats R]

The "before" is the definition kept in ``tests/graph/test_robust_components.py`` (``_reference``, loaded from that
file). Graph: a dense 1DSfM-like graph of 3000 cameras and 60,000 pairs with very uneven popularity (LogNormal σ 2:
many cameras in few pairs, so the checks leave hundreds of lone cameras), synthetic inlier counts; the filter gets
the checks' state just before step 6 (captured from ``check_view_graph``). Both must reject the same pairs with the
same reasons (checked). Reports median times; writes ``benchmarks/results/robust_components.json`` atomically.
"""

from __future__ import annotations

import argparse
import copy
import os
import runpy
import statistics
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

import pipeline.graph.checks as checks  # noqa: E402
from _common import save_results  # noqa: E402  (benchmarks/, the script's folder)
from pipeline.synthetic.protocols import dense_graph, synthetic_inlier_counts  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "robust_components.json"
REFERENCE = runpy.run_path(str(HERE.parent / "tests" / "graph" / "test_robust_components.py"))["_reference"]


def _state_before_step6(vg):
    """The arguments ``check_view_graph`` hands the robust filter (its checks copied before the filter runs)."""
    seen, filt = {}, checks._robust_filter

    def grab(vg_, chk, sw, cfg):
        seen["args"] = (vg_, copy.deepcopy(chk), sw, cfg)
        return filt(vg_, chk, sw, cfg)

    checks._robust_filter = grab
    try:
        checks.check_view_graph(vg)
    finally:
        checks._robust_filter = filt
    return seen["args"]


def _timed(fn, args, repeats):
    vg, chk0, sw, cfg = args
    times, out = [], None
    for _ in range(repeats):
        chk = copy.deepcopy(chk0)
        t = time.perf_counter()
        n = fn(vg, chk, sw, cfg)
        times.append(time.perf_counter() - t)
        out = (n, chk)
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    sg, sig = dense_graph(3000, 60000, popularity_sigma_ln=2.0, seed=0)
    sg.vg.inliers = synthetic_inlier_counts(sig, sg.outlier_mask, 1.0, np.random.default_rng(1))
    args = _state_before_step6(sg.vg)
    vg, chk0 = args[0], args[1]
    keep = chk0.kept | (args[3].robust_unconfirmed & (chk0.step == "unconfirmed"))
    n_comp = len(np.unique(checks.ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep], allow_isolated=True)
                           .components()))
    t_after, (n_a, ca) = _timed(checks._robust_filter, args, a.repeats)
    t_before, (n_b, cb) = _timed(REFERENCE, args, a.repeats)
    same = n_a == n_b and all(np.array_equal(getattr(ca, f), getattr(cb, f)) for f in ("kept", "reason", "step"))
    row = {"graph": "dense 3000 / 60k pairs, popularity σ 2", "n_cameras": vg.n_cameras, "n_edges": vg.n_edges,
           "n_components": n_comp, "n_rejected": n_a, "before_s": t_before, "after_s": t_after,
           "speedup": t_before / t_after, "identical": bool(same), "repeats": a.repeats}
    print(f"{'graph':38s} {'pairs':>6s} {'comps':>5s} {'rejected':>8s} {'before s':>9s} {'after s':>8s} "
          f"{'speedup':>7s}  same")
    print(f"{row['graph']:38s} {vg.n_edges:6d} {n_comp:5d} {n_a:8d} {t_before:9.3f} {t_after:8.3f} "
          f"{row['speedup']:7.2f}  {same}")
    save_results(a.json, [row], "robust_components.py", argv)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
