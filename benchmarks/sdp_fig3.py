"""Paper 2, Fig. 3 / Fig. C.2: errors of ISO vs cSO(3) and run times of all four variants.

Grid: N ∈ {5, 10, 20, 50, 100} × p ∈ {0.1, 0.3, 0.5, 1.0}; instances from
``paper2_graph(N, p)`` (eigenvalues of H⁻¹ in [0.01, 0.1], i.e. of H in [10, 100],
paper 2 §5.1). Every instance is solved by the four variants with SCS (paper 2, §5
tolerances). Reported per (N, p): median error √Σ‖R_i − R_i*‖²_F of each variant,
the share of instances where cSO(3) beats O(3)-ISO, rank-3 rates and median wall
times (build + solve). Plots: error histograms of SDP-O(3)-ISO vs SDP-cSO(3) per p
(pooled over N) and run time vs N per p for all four variants.

The paper runs 100 instances per cell; the 2-core machine allows fewer
(``--instances``, scaled down for N ≥ 50).

    python benchmarks/sdp_fig3.py [--quick] [--instances 10]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.averaging.sdp import solve_sdp
from pipeline.core.atomic import save_figure, write_json
from pipeline.evaluation.metrics import frobenius_error
from pipeline.synthetic.graphs import paper2_graph

RESULTS = Path(__file__).resolve().parent / "results"
OUT = RESULTS / "sdp_fig3.json"
PNG_ERR = RESULTS / "sdp_fig3_errors.png"
PNG_TIME = RESULTS / "sdp_fig3_runtimes.png"
NS = [5, 10, 20, 50, 100]
PS = [0.1, 0.3, 0.5, 1.0]
ORDER = ["o3-iso", "o3-aniso", "cso3-iso", "cso3"]


def n_instances(n: int, base: int) -> int:
    return max(1, base if n <= 20 else base // 3 if n <= 50 else base // 5)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N ≤ 20 and 3 instances per cell")
    ap.add_argument("--instances", type=int, default=10)
    ap.add_argument("--from-json", action="store_true",
                    help="only summarize and plot the rows already in the results JSON (e.g. of an interrupted run)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    ns = NS[:3] if args.quick else NS
    base = 3 if args.quick else args.instances
    rows = []
    t_start = time.perf_counter()
    if args.from_json:
        import json

        rows = json.loads(OUT.read_text())["rows"]
        ns = sorted({r["N"] for r in rows})
    for n in ([] if args.from_json else ns):
        for p in PS:
            for k in range(n_instances(n, base)):
                g = paper2_graph(n, p, seed=1000 * n + int(100 * p) * 7 + k)
                row = {"N": n, "p": p, "k": k, "M": g.vg.n_edges}
                for v in ORDER:
                    r = solve_sdp(g.vg, v, "scs")
                    row[v] = {"err": frobenius_error(r.R, g.R_true), "time_s": r.time_s,
                              "rank": r.stats["rank"], "iters": r.stats["solver_iterations"]}
                rows.append(row)
            cell = [r for r in rows if r["N"] == n and r["p"] == p]
            med = {v: np.median([r[v]["err"] for r in cell]) for v in ORDER}
            tm = {v: np.median([r[v]["time_s"] for r in cell]) for v in ORDER}
            print(f"N={n:3d} p={p:.1f} ({len(cell)} inst, M≈{cell[0]['M']}): median err "
                  + " ".join(f"{v}={med[v]:.4f}" for v in ORDER) + " | median s "
                  + " ".join(f"{v}={tm[v]:.2f}" for v in ORDER)
                  + f"  [{time.perf_counter() - t_start:.0f} s]", flush=True)
            write_json(OUT, {"rows": rows, "partial": True})

    cells = []
    for n in ns:
        for p in PS:
            cell = [r for r in rows if r["N"] == n and r["p"] == p]
            if not cell:
                continue
            cells.append({
                "N": n, "p": p, "instances": len(cell),
                "median_err": {v: float(np.median([r[v]["err"] for r in cell])) for v in ORDER},
                "median_time_s": {v: float(np.median([r[v]["time_s"] for r in cell])) for v in ORDER},
                "rank3_rate": {v: float(np.mean([r[v]["rank"] == 3 for r in cell])) for v in ORDER},
                "cso3_better_than_iso": float(np.mean([r["cso3"]["err"] < r["o3-iso"]["err"] for r in cell])),
            })
    all_iso = np.array([r["o3-iso"]["err"] for r in rows])
    all_cso = np.array([r["cso3"]["err"] for r in rows])
    overall = {"median_err_o3_iso": float(np.median(all_iso)), "median_err_cso3": float(np.median(all_cso)),
               "cso3_better_share": float(np.mean(all_cso < all_iso)),
               "cso3_lower_median_in_cells": int(sum(c["median_err"]["cso3"] < c["median_err"]["o3-iso"] for c in cells)),
               "n_cells": len(cells),
               "rank3_rate": {v: float(np.mean([r[v]["rank"] == 3 for r in rows])) for v in ORDER},
               "median_time_s": {v: float(np.median([r[v]["time_s"] for r in rows])) for v in ORDER}}
    write_json(OUT, {"setup": {"Ns": ns, "ps": PS, "eig_range_H": [10, 100], "solver": "scs",
                               "instances_base": base, "complete": not args.from_json}, "overall": overall, "cells": cells, "rows": rows,
                     "elapsed_s": time.perf_counter() - t_start})
    print(f"\n{'N':>4s} {'p':>4s} {'inst':>4s} {'err ISO':>8s} {'err cSO3':>8s} {'cSO3<ISO':>8s} "
          + " ".join(f"{'t ' + v:>12s}" for v in ORDER))
    for c in cells:
        print(f"{c['N']:4d} {c['p']:4.1f} {c['instances']:4d} {c['median_err']['o3-iso']:8.4f} "
              f"{c['median_err']['cso3']:8.4f} {c['cso3_better_than_iso']:8.2f} "
              + " ".join(f"{c['median_time_s'][v]:12.3f}" for v in ORDER))
    print(f"overall: {overall}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PS), figsize=(4 * len(PS), 3.2))
    for ax, p in zip(axes, PS):
        iso = [r["o3-iso"]["err"] for r in rows if r["p"] == p]
        cso = [r["cso3"]["err"] for r in rows if r["p"] == p]
        bins = np.linspace(0, max(max(iso), max(cso)), 25)
        ax.hist(iso, bins, alpha=0.6, label="SDP-O(3)-ISO")
        ax.hist(cso, bins, alpha=0.6, label="SDP-cSO(3)")
        ax.set_title(f"p = {p}")
        ax.set_xlabel("√Σ‖R_i − R_i*‖²_F")
    axes[0].legend()
    fig.tight_layout()
    save_figure(fig, PNG_ERR, dpi=100)
    fig, axes = plt.subplots(1, len(PS), figsize=(4 * len(PS), 3.2), sharey=True)
    for ax, p in zip(axes, PS):
        for v in ORDER:
            have = [n for n in ns if any(r["p"] == p and r["N"] == n for r in rows)]
            med = [np.median([r[v]["time_s"] for r in rows if r["p"] == p and r["N"] == n]) for n in have]
            ax.plot(have, med, "-o", label=f"SDP-{v}")
            xs = [r["N"] for r in rows if r["p"] == p]
            ax.scatter(xs, [r[v]["time_s"] for r in rows if r["p"] == p], s=6, alpha=0.4)
        ax.set_yscale("log")
        ax.set_title(f"p = {p}")
        ax.set_xlabel("N cameras")
    axes[0].set_ylabel("wall time (s), build + solve")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, PNG_TIME, dpi=100)
    print(f"wrote {OUT}, {PNG_ERR}, {PNG_TIME}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
