"""Issue 15, item 3's heavy-tailed protocol over many seeds: how often does any estimator beat COLMAP there?

Item 3 asks that ours be at or below COLMAP's median **and** mean error on every seed of each synthetic protocol
(N = 500 and 2000, three seeds each). On ``heavy-t`` (``pipeline.synthetic.protocols``: Student-t noise, ν = 3,
s = 1°, and 10% Haar outliers) ours met it on 2 of the 6 draws, within ±2%. This script measures whether that is a
shortfall of our method or a property of the protocol: on many more seeds it scores, beside ours (``irls``) and
``colmap-ra`` (pycolmap's ``run_rotation_averaging``), the maximum-likelihood rotations of the protocol's *true*
model on its *true* inlier edges (``oracle_t3`` of ``robust_averaging.py``: it reads the truth, so it is not a
method, but no method that must find the model and the outliers from the data can be expected to do better).

For each estimator it gives the share p of seeds on which it is at or below COLMAP on the median, the mean and
both, with a 95% Wilson interval, and p⁶: the chance that an estimator with that per-draw rate meets item 3's six
draws at once (draws are independent). Errors are medians and means of the cameras' errors after the ℓ2 alignment
of ``pipeline.evaluate``, as in ``robust_averaging.py``.

Usage::

    python benchmarks/heavy_tail_limit.py [--seeds500 30] [--seeds2000 10]

Writes ``benchmarks/results/heavy_tail_limit.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.averaging import average
from pipeline.core.atomic import write_json
from pipeline.synthetic.protocols import make_protocol
from robust_averaging import errors, oracle_t3  # benchmarks/, the script's folder, is on sys.path

RESULTS = Path(__file__).resolve().parent / "results"
ESTIMATORS = ("ours", "oracle_t3")


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a binomial share k / n."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return float(c - h), float(c + h)


def draw(n: int, seed: int) -> dict[str, Any]:
    """One heavy-t draw: ours, COLMAP and the oracle's errors, and which are at or below COLMAP's."""
    g, _, _ = make_protocol("heavy-t", n, seed)
    t = time.perf_counter()
    ours = average(g.vg, "irls")
    row: dict[str, Any] = {"n": n, "seed": seed, "ours_s": time.perf_counter() - t,
                           "ours": errors(ours.R, g.R_true), "colmap": errors(average(g.vg, "colmap-ra").R, g.R_true),
                           "oracle_t3": errors(oracle_t3(g, ours.R), g.R_true)}
    c = row["colmap"]
    for est in ESTIMATORS:
        e = row[est]
        row[f"{est}_le_colmap"] = {"median": bool(e["median_deg"] <= c["median_deg"]),
                                   "mean": bool(e["mean_deg"] <= c["mean_deg"])}
        row[f"{est}_le_colmap"]["both"] = all(row[f"{est}_le_colmap"].values())
        row[f"{est}_over_colmap"] = {"median": e["median_deg"] / c["median_deg"], "mean": e["mean_deg"] / c["mean_deg"]}
    return row


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per estimator: the share of draws at or below COLMAP (median, mean, both), its interval, and p⁶."""
    out: dict[str, Any] = {"n_draws": len(rows)}
    for est in ESTIMATORS:
        s: dict[str, Any] = {}
        for key in ("median", "mean", "both"):
            k = sum(r[f"{est}_le_colmap"][key] for r in rows)
            lo, hi = wilson(k, len(rows))
            s[key] = {"k": k, "share": k / len(rows), "wilson95": [lo, hi]}
        p = s["both"]["share"]
        s["p_six_of_six"] = p ** 6
        s["p_six_of_six_upper"] = s["both"]["wilson95"][1] ** 6
        ratios = np.array([[r[f"{est}_over_colmap"]["median"], r[f"{est}_over_colmap"]["mean"]] for r in rows])
        s["ratio_median_of_draws"] = {"median": float(np.median(ratios[:, 0])), "mean": float(np.median(ratios[:, 1]))}
        s["ratio_range"] = {"median": [float(ratios[:, 0].min()), float(ratios[:, 0].max())],
                            "mean": [float(ratios[:, 1].min()), float(ratios[:, 1].max())]}
        out[est] = s
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds500", type=int, default=30, help="draws at N = 500 (seeds 0 …)")
    ap.add_argument("--seeds2000", type=int, default=10, help="draws at N = 2000 (seeds 0 …)")
    ap.add_argument("--json", type=Path, default=RESULTS / "heavy_tail_limit.json")
    a = ap.parse_args(argv)
    rows = []
    for n, k in ((500, a.seeds500), (2000, a.seeds2000)):
        for seed in range(k):
            r = draw(n, seed)
            rows.append(r)
            print(f"N={n:5d} seed {seed:2d}: ours {r['ours']['median_deg']:.4f}/{r['ours']['mean_deg']:.4f}  "
                  f"oracle {r['oracle_t3']['median_deg']:.4f}/{r['oracle_t3']['mean_deg']:.4f}  "
                  f"colmap {r['colmap']['median_deg']:.4f}/{r['colmap']['mean_deg']:.4f}  "
                  f"ours<=colmap {r['ours_le_colmap']['both']}  oracle<=colmap {r['oracle_t3_le_colmap']['both']}",
                  flush=True)
    out = {"command": "python benchmarks/heavy_tail_limit.py " + " ".join(sys.argv[1:]), "rows": rows,
           "summary": summary(rows), "by_size": {str(n): summary([r for r in rows if r["n"] == n])
                                                 for n in sorted({r["n"] for r in rows})}}
    print(f"{'estimator':10s} {'≤ COLMAP: median':>18s} {'mean':>10s} {'both':>10s} {'95% (both)':>16s} {'p^6':>8s}")
    for est in ESTIMATORS:
        s = out["summary"][est]
        lo, hi = s["both"]["wilson95"]
        print(f"{est:10s} {s['median']['share']:18.2f} {s['mean']['share']:10.2f} {s['both']['share']:10.2f} "
              f"{f'{lo:.2f}–{hi:.2f}':>16s} {s['p_six_of_six']:8.4f}")
    write_json(a.json, out)
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
