"""Paper 1, Fig. 4: statistical efficiency of every loss against noise (issue 3, item 3).

Protocol (paper 1 §6): ``paper1_graph(100, p=0.5, σ, outlier_frac)`` with σ = 0, 1,
…, 10° per axis, 25 trials per level, 0% and 20% outlier edges. For each graph
the initial ℓ1 stage (paper 1 Alg. 3: MST, then 5 steps of Alg. 2) is computed
once and every loss starts IRLS from it (identical to running Alg. 3 per loss,
without recomputing the shared stage). Losses: the 13 of Table 1 at α = 5°, with
ℓ½ in three forms: ``l0.5`` (our default quadratic core of radius α, no polish),
``l0.5-pure`` (floor 1e-6 rad, the paper's ℓ½) and ``l0.5+refine`` (the product
default of ``pipeline.average``). Weiszfeld (Hartley et al.) runs from the MST.

The error of a trial is the median camera error after ℓ2 alignment; the table
and plot show its mean over trials. Output: ``benchmarks/results/irls_fig4.json``
and ``irls_fig4.png``. Jobs run on 2 processes.

Usage: ``python benchmarks/irls_fig4.py [--quick] [--trials 25] [--no-weiszfeld]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from pipeline.core.atomic import save_figure, write_json
from pipeline.averaging.irls import irls
from pipeline.averaging.weiszfeld import weiszfeld
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.synthetic.graphs import paper1_graph

RESULTS = Path(__file__).resolve().parent / "results"
LOSSES = ["l2", "l1", "l0.5", "l0.5-pure", "l0.5+refine", "geman-mcclure", "huber", "pseudo-huber", "andrews",
          "bisquare", "cauchy", "fair", "logistic", "talwar", "welsch"]


def job(args: tuple[float, float, int, bool]) -> dict:
    outlier, sigma, trial, with_w = args
    logging.getLogger("pipeline").setLevel(logging.ERROR)
    g = paper1_graph(100, 0.5, sigma, outlier, seed=100000 * int(outlier * 100) + 1000 * int(sigma * 10) + trial)
    vg = g.vg
    t = time.perf_counter()
    start = irls(vg, max_iterations=0)  # MST + 5 ℓ1 steps (Alg. 2)
    t_l1 = time.perf_counter() - t
    out: dict = {"outlier": outlier, "sigma": sigma, "trial": trial, "median": {}, "mean": {}, "time_s": {}}
    for name in LOSSES:
        kw: dict = {}
        loss = name
        if name == "l0.5-pure":
            loss, kw = "l0.5", {"eps_rad": 1e-6}
        elif name == "l0.5+refine":
            loss, kw = "l0.5", {"refine": True}
        r = irls(vg, loss=loss, init=start.R, l1_iterations=0, **kw)
        e = rotation_errors_deg(r.R, g.R_true)
        out["median"][name] = float(np.median(e))
        out["mean"][name] = float(np.mean(e))
        out["time_s"][name] = r.time_s + t_l1
    if with_w:
        r = weiszfeld(vg, init="mst")
        e = rotation_errors_deg(r.R, g.R_true)
        out["median"]["weiszfeld"] = float(np.median(e))
        out["mean"]["weiszfeld"] = float(np.mean(e))
        out["time_s"]["weiszfeld"] = r.time_s
    return out


def plot(res: dict, png: Path) -> None:
    """Error against noise for every method, one panel per outlier level; fixed colours."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - matplotlib is a dependency
        print(f"plot skipped: {exc}")
        return
    sigmas = res["sigmas_deg"]
    table = res["table_mean_of_median_deg"]
    methods = list(next(iter(table.values())).keys())
    cmap = plt.get_cmap("tab20")
    colour = {m: cmap(k % 20) for k, m in enumerate(methods)}
    bold = {"l2", "l1", "l0.5", "l0.5-pure", "l0.5+refine", "geman-mcclure", "weiszfeld"}
    fig, axes = plt.subplots(1, 2, figsize=(14, 5.5))
    for ax, (key, t) in zip(axes, table.items()):
        for m in methods:
            if key == "outliers_20pct" and m == "l2":
                continue  # off the scale (about 8°), as in the paper's Fig. 4(b)
            ax.plot(sigmas, t[m], "-" if m in bold else ":", marker="o", ms=3, lw=2 if m in bold else 1,
                    color=colour[m], label=m)
        ax.set_xlabel("noise σ per axis (deg)")
        ax.set_ylabel("mean over trials of the median camera error (deg)")
        ax.set_title(f"N=100, p=0.5, {key.split('_')[1].replace('pct', '%')} outliers"
                     + (" (ℓ2 omitted: ≈ 8°)" if "20" in key else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    save_figure(fig, png)
    print(f"wrote {png}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 trials, σ ∈ {0, 2, 5, 8, 10}")
    ap.add_argument("--trials", type=int, default=25)
    ap.add_argument("--no-weiszfeld", action="store_true")
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "irls_fig4.json")
    ap.add_argument("--replot", action="store_true", help="only redraw the PNG from an existing JSON")
    a = ap.parse_args(argv)
    if a.replot:
        import json

        plot(json.loads(a.out.read_text()), a.out.with_suffix(".png"))
        return 0
    sigmas = [0.0, 2.0, 5.0, 8.0, 10.0] if a.quick else [float(s) for s in range(11)]
    trials = 3 if a.quick else a.trials
    jobs = [(o, s, t, not a.no_weiszfeld) for o in (0.0, 0.2) for s in sigmas for t in range(trials)]
    t0 = time.perf_counter()
    with Pool(a.processes) as pool:
        rows = pool.map(job, jobs, chunksize=4)
    methods = LOSSES + ([] if a.no_weiszfeld else ["weiszfeld"])
    table: dict[str, dict[str, list[float]]] = {}
    for o in (0.0, 0.2):
        key = f"outliers_{int(o * 100)}pct"
        table[key] = {m: [float(np.mean([r["median"][m] for r in rows if r["outlier"] == o and r["sigma"] == s]))
                          for s in sigmas] for m in methods}
    # Orderings (paper 1 §6): mean over σ > 0 of the trial-mean median error.
    order = {}
    for key, t in table.items():
        avg = {m: float(np.mean(v[1:])) for m, v in t.items()}
        order[key] = sorted(avg, key=avg.get)
    gm0 = table["outliers_0pct"]["geman-mcclure"]
    l2_0 = table["outliers_0pct"]["l2"]
    checks = {
        "no_outliers_best": order["outliers_0pct"][0],
        "no_outliers_ranking": order["outliers_0pct"],
        "outliers20_best": order["outliers_20pct"][0],
        "outliers20_ranking": order["outliers_20pct"],
        "gm_over_l2_ratio_by_sigma_0pct": [g / l if l > 0 else None for g, l in zip(gm0, l2_0)],
    }
    print(f"Fig. 4, N=100, p=0.5, {trials} trials, mean over trials of the median camera error (deg)")
    for key, t in table.items():
        print(f"\n{key}")
        print(f"  {'loss':14s}" + "".join(f"{s:7.0f}°" for s in sigmas))
        for m in methods:
            print(f"  {m:14s}" + "".join(f"{v:8.3f}" for v in t[m]))
        print(f"  ranking (best first, σ > 0): {', '.join(order[key])}")
    print("\nGM/ℓ2 error ratio by σ (0% outliers):", ", ".join(f"{x:.2f}" if x else "-" for x in checks["gm_over_l2_ratio_by_sigma_0pct"]))
    res = {"protocol": "paper1_graph(100, 0.5, sigma, outliers), alpha 5 deg", "sigmas_deg": sigmas, "trials": trials,
           "table_mean_of_median_deg": table, "checks": checks, "elapsed_s": time.perf_counter() - t0, "rows": rows}
    write_json(a.out, res)
    plot(res, a.out.with_suffix(".png"))
    print(f"wrote {a.out} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
