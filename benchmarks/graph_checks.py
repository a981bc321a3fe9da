"""The view graph's cycle filter at size, against recounting every edge's blame each round, in the same run.

    python benchmarks/graph_checks.py [--quick] [--repeats R]

``pipeline.graph.loops.cycle_filter`` removes, greedily, the edge that most short cycles disagree with, provided
it is strictly the most suspicious edge of at least one live inconsistent cycle (its "blame"). The filter looks
for the first such candidate in priority order, checking the candidates in growing batches against the cycles
through them. The reference here recounts every edge's blame over every live inconsistent cycle in each round
(vectorized: one sort of the (K, 4) fractions per round), which is what the filter did before. Both must remove
the same edges in the same order (checked). Graphs: kNN view graphs (2° noise, Haar outliers) of 300 and 2000
cameras, and a dense 1DSfM-like graph (247 cameras, 6000 edges, 28–55% outliers: about 800,000 cycles).
Reports the median time of each and the ratio; writes ``benchmarks/results/graph_checks.json`` atomically.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from _common import median_time as _timed, save_results  # noqa: E402  (benchmarks/, the script's folder)
from pipeline.graph.loops import CycleRounds, cycle_filter  # noqa: E402
from pipeline.synthetic.graphs import knn_graph  # noqa: E402
from pipeline.synthetic.protocols import dense_graph  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "graph_checks.json"


def recount_filter(edges: np.ndarray, R_rel: np.ndarray, n: int, sigma_deg: np.ndarray, max_len: int = 4,
                   k_sigma: float = 3.0, min_deg: float = 1.0, max_deg: float = 10.0,
                   max_bad_fraction: float = 0.5) -> list[int]:
    """The removal order of :func:`cycle_filter` with every blame recounted in every round (the reference)."""
    st = CycleRounds.start(edges, R_rel, n, sigma_deg, max_len=max_len, k_sigma=k_sigma, min_deg=min_deg,
                           max_deg=max_deg)
    cyc, ok, alive, n_c, n_b, kept = st.cycles, st.consistent, st.alive, st.n_c, st.n_b, st.kept
    M, bad_idx = len(kept), np.flatnonzero(~ok)
    while True:
        frac = np.where(n_c > 0, n_b / np.maximum(n_c, 1), 0.0)
        cand = kept & (n_c >= 1) & (frac > max_bad_fraction)
        if cand.any():
            ce = cyc.edges[bad_idx[alive[bad_idx]]]
            f = np.where(ce >= 0, frac[np.maximum(ce, 0)], -1.0)
            top = np.sort(f, axis=1)
            second = np.where(f == top[:, -1:], top[:, -2:-1], top[:, -1:])
            cand &= np.bincount(ce[(ce >= 0) & (f > second)], minlength=M) >= 1
        if not cand.any():
            return st.removed
        c = np.flatnonzero(cand)
        best = int(c[np.lexsort((-n_b[c], -frac[c]))[0]])
        st.drop(best)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the two kNN graphs only")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    graphs = [("kNN 300, 15% outliers", knn_graph(300, k=12, sigma_deg=2.0, outlier_frac=0.15, seed=0).vg),
              ("kNN 2000, 15% outliers", knn_graph(2000, k=12, sigma_deg=2.0, outlier_frac=0.15, seed=0).vg)]
    if not a.quick:
        graphs.append(("dense 247 / 6000 edges", dense_graph(n=247, target_edges=6000, seed=0)[0].vg))
    rows = []
    print(f"{'graph':26s} {'edges':>6s} {'removed':>7s} {'ours s':>8s} {'recount s':>9s} {'ratio':>6s}  same")
    for name, vg in graphs:
        sigma = np.full(vg.n_edges, 1.0)
        t_ours, res = _timed(lambda: cycle_filter(vg.edges, vg.R_rel, vg.n_cameras, sigma, max_len=4), a.repeats)
        t_ref, ref = _timed(lambda: recount_filter(vg.edges, vg.R_rel, vg.n_cameras, sigma), 1)
        row = {"graph": name, "n_cameras": vg.n_cameras, "n_edges": vg.n_edges, "n_cycles": len(res.cycles),
               "n_inconsistent": int((~res.consistent).sum()), "n_removed": len(res.removed), "ours_s": t_ours,
               "recount_s": t_ref, "ratio": t_ours / t_ref, "same_removals": res.removed == ref}
        rows.append(row)
        print(f"{name:26s} {vg.n_edges:6d} {len(res.removed):7d} {t_ours:8.2f} {t_ref:9.2f} {row['ratio']:6.2f}  "
              f"{row['same_removals']}", flush=True)
    save_results(a.json, rows, "graph_checks.py", argv)
    return 0 if all(r["same_removals"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
