"""Anisotropic IRLS (irls-h) against its peers on paper 2-style anisotropic graphs.

Setup: ``pipeline.synthetic.graphs.paper2_graph(N, p, eig_range, seed)`` with
``p = 12/(N−1)`` (mean degree 12), N ∈ {20, 50, 100, 500}, eigenvalues of H uniform
in (1, 1000) or (10, 100) 1/rad² (per-axis noise σ from 1.8° to 57°, or 5.7° to 18°),
``Δω ~ N(0, H⁻¹)``; then 0% or 10% of the edges replaced by Haar-random rotations,
their H kept (so H says nothing about which edges are wrong). Seeds 0, 1, 2; the
same graph is used at both outlier rates.

Methods, in the same run:

* ``irls-h``: ``pipeline.average.average(vg, method="irls-h")``, the product default
  (ℓ½ with α = 2 robust scale units, trimmed-ℓ2 polish);
* ``irls``: ``average(vg, method="irls")``, isotropic (paper 1), product default;
* ``sdp-cso3``: ``solve_sdp(vg, "cso3", "scs")`` (paper 2; anisotropic least
  squares, certifiable, not robust), N ≤ 100 only (SCS: ~5 s per instance at N = 100);
* ``gtsam-lm``: GTSAM ``BetweenFactorRot3`` + ``noiseModel.Gaussian.Information(H)``,
  Levenberg–Marquardt (``pipeline.averaging.peers.lm_anisotropic``; local, not robust)
  from our spanning tree + ℓ1 start (``irls(vg, max_iterations=0)``, its time added);
* ``colmap``: ``pycolmap.run_rotation_averaging`` with default options
  (``pipeline.averaging.peers.run_colmap``: isotropic ℓ1 + IRLS);
* ``oracle``: irls-h with the ℓ2 loss and no polish on the true inlier edges only
  (with 0% outliers: anisotropic least squares on every edge).

Errors: per-camera angle after ℓ2 alignment to the truth (``pipeline.evaluate``).
Wall time: the solver call (ours: ``AveragingResult.time_s``, spanning tree
included; pycolmap: ``run_rotation_averaging``), the median of 3 repeats for the
fast methods (1 at N = 500 and on the scale rows). A cell of the table pools its
seeds: the median over seeds of each seed's median error, the max of the max errors,
the median time. Ratios: irls-h time / pycolmap time, irls-h time / GTSAM time,
irls-h median / oracle median (per seed, then the median over seeds).

Scale rows: ``knn_graph(N, k=12)`` for N = 2000 and 10,000, noise-free relative
rotations, then anisotropic noise from ``H = random_precisions(M, (1, 1000))`` on
the inliers and 10% outliers; irls-h vs irls vs pycolmap (and the oracle).

``OMP_WAIT_POLICY=PASSIVE`` is set before pycolmap loads. Results:
``benchmarks/results/irls_h.json`` (``--quick``: ``irls_h_quick.json``).

Usage: ``python benchmarks/irls_h.py [--quick] [--no-scale] [--no-sdp]``
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("GLOG_minloglevel", "1")  # pycolmap's per-call INFO lines

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.averaging import average  # noqa: E402
from pipeline.averaging.irls import irls  # noqa: E402
from pipeline.averaging.peers import have_gtsam, lm_anisotropic, run_colmap  # noqa: E402
from pipeline.core import so3  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.evaluation.metrics import rotation_errors_deg  # noqa: E402
from pipeline.synthetic.graphs import knn_graph, paper2_graph, random_precisions, sample_left_noise, with_outliers  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
EIG_RANGES = [(1.0, 1000.0), (10.0, 100.0)]
OUTLIER_FRACS = [0.0, 0.1]
METHODS = ["irls-h", "irls", "sdp-cso3", "gtsam-lm", "colmap", "oracle"]


def anisotropic_knn(n: int, eig_range: tuple[float, float], outlier_frac: float, seed: int):
    """kNN graph (k = 12) with Δω ~ N(0, H⁻¹), H from random_precisions, and outliers."""
    g = knn_graph(n, k=12, sigma_deg=0.0, outlier_frac=outlier_frac, seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    H = random_precisions(g.vg.n_edges, eig_range, rng)
    dw = sample_left_noise(H, rng)
    R_rel = g.vg.R_rel.copy()
    inl = ~g.outlier_mask
    R_rel[inl] = so3.exp(dw[inl]) @ R_rel[inl]
    return ViewGraph(g.vg.names, g.vg.edges, R_rel, H=H), g.R_true, g.outlier_mask


def errors(R: np.ndarray, R_true: np.ndarray, mask: np.ndarray | None = None) -> dict:
    e = rotation_errors_deg(R, R_true, mask)
    e = e[np.isfinite(e)]
    return {"median_deg": float(np.median(e)), "max_deg": float(e.max()), "n_gt10": int((e > 10).sum()),
            "n_evaluated": int(e.size)}


def on_subset(res, vg: ViewGraph, R_true: np.ndarray) -> dict:
    """Errors of a result that may cover only part of the cameras (largest component)."""
    keep = np.zeros(vg.n_cameras, dtype=bool)
    idx = [vg.names.index(x) for x in res.names]
    keep[idx] = True
    R = np.tile(np.eye(3), (vg.n_cameras, 1, 1))
    R[idx] = res.R
    return errors(R, R_true, keep)


def timed(fn, reps: int):
    """Run ``fn`` ``reps`` times; returns (last output, median seconds). fn returns (output, seconds)."""
    ts = []
    for _ in range(reps):
        out, dt = fn()
        ts.append(dt)
    return out, float(np.median(ts)), [float(t) for t in ts]


def run_instance(vg: ViewGraph, R_true: np.ndarray, out: np.ndarray, reps: int, sdp: bool, gtsam: bool,
                 colmap: bool = True) -> dict:
    rec: dict[str, dict] = {}

    def ours(**kw):
        def f():
            r = average(vg, **kw)
            return r, r.time_s
        return f

    r, t, ts = timed(ours(method="irls-h"), reps)
    rec["irls-h"] = {**errors(r.R, R_true), "time_s": t, "times_s": ts, "iterations": r.iterations,
                     "n_factorizations": r.stats["n_factorizations"], "n_trimmed": r.stats["n_trimmed"],
                     "outliers_trimmed": int(np.sum(np.asarray(r.stats["normalized_residuals"])[out] > 3.76)),
                     "n_outliers": int(out.sum())}
    r, t, ts = timed(ours(method="irls"), reps)
    rec["irls"] = {**errors(r.R, R_true), "time_s": t, "times_s": ts}
    if sdp:
        from pipeline.averaging.sdp import solve_sdp

        r = solve_sdp(vg, variant="cso3", solver="scs")
        rec["sdp-cso3"] = {**errors(r.R, R_true), "time_s": r.time_s, "rank": r.stats.get("rank"),
                           "certified": r.stats.get("certified")}
    if gtsam:
        def g():
            l1 = irls(vg, max_iterations=0)  # spanning tree + ℓ1 steps (Algorithm 2), as our IRLS starts
            R, dt, it = lm_anisotropic(vg, l1.R)
            return (R, it), dt + l1.time_s
        (R, it), t, ts = timed(g, reps)
        rec["gtsam-lm"] = {**errors(R, R_true), "time_s": t, "times_s": ts, "iterations": it}
    if colmap:
        def c():
            R, reg, dt, ok = run_colmap(vg)
            return (R, reg, ok), dt
        (R, reg, ok), t, ts = timed(c, reps)
        rec["colmap"] = {**errors(R, R_true, reg), "time_s": t, "times_s": ts, "ok": ok,
                         "n_registered": int(reg.sum())}
    inl = ViewGraph(vg.names, vg.edges[~out], vg.R_rel[~out], H=vg.H[~out], allow_isolated=True)
    r = average(inl, method="irls-h", loss="l2", refine=False)
    rec["oracle"] = {**on_subset(r, vg, R_true), "time_s": r.time_s}
    h = rec["irls-h"]
    ratios = {"median_vs_oracle": h["median_deg"] / rec["oracle"]["median_deg"],
              "median_vs_irls": h["median_deg"] / rec["irls"]["median_deg"]}
    if colmap:
        ratios["time_vs_colmap"] = h["time_s"] / rec["colmap"]["time_s"]
    if gtsam:
        ratios["time_vs_gtsam"] = h["time_s"] / rec["gtsam-lm"]["time_s"]
    return {"methods": rec, "ratios": ratios}


def summarize(rows: list[dict]) -> dict:
    """Pool the seeds of one cell."""
    s: dict = {"seeds": len(rows), "M": int(np.median([r["M"] for r in rows]))}
    for m in METHODS:
        have = [r["methods"][m] for r in rows if m in r["methods"]]
        if have:
            s[m] = {"median_deg": float(np.median([x["median_deg"] for x in have])),
                    "max_deg": float(max(x["max_deg"] for x in have)),
                    "time_s": float(np.median([x["time_s"] for x in have])), "n": len(have)}
    s["ratios"] = {k: float(np.median([r["ratios"][k] for r in rows if k in r["ratios"]]))
                   for k in rows[0]["ratios"]}
    return s


def fmt(x: float | None, w: int = 6, d: int = 3) -> str:
    return f"{'—':>{w}s}" if x is None else f"{x:{w}.{d}f}"


def table(cells: list[dict]) -> str:
    cols = ["irls-h", "irls", "sdp-cso3", "gtsam-lm", "colmap", "oracle"]
    short = {"irls-h": "irlsH", "irls": "irls", "sdp-cso3": "sdp", "gtsam-lm": "gtsam", "colmap": "colmap",
             "oracle": "oracle"}
    head = (f"{'eig(H)':>9s} {'out':>4s} {'N':>5s} {'M':>6s} | median° " + " ".join(f"{short[c]:>6s}" for c in cols)
            + " | max° " + " ".join(f"{short[c]:>6s}" for c in ("irls-h", "irls", "gtsam-lm", "colmap", "oracle"))
            + " | time s " + " ".join(f"{short[c]:>6s}" for c in ("irls-h", "irls", "sdp-cso3", "gtsam-lm", "colmap"))
            + " | tH/tCol tH/tGt medH/orc")
    lines = [head, "-" * len(head)]
    for c in cells:
        s = c["summary"]
        g = (lambda m, k: s[m][k] if m in s else None)
        eig = f"{c['eig_range'][0]:g}-{c['eig_range'][1]:g}"
        d = 2 if s.get("M", 0) >= 10000 else 3
        lines.append(
            f"{eig:>9s} {100 * c['outlier_frac']:3.0f}% {c['N']:5d} {s['M']:6d} | {'':7s} "
            + " ".join(fmt(g(m, "median_deg")) for m in cols)
            + " | " + " ".join(fmt(g(m, "max_deg"), 6, 2) for m in ("irls-h", "irls", "gtsam-lm", "colmap", "oracle"))
            + "      | " + " ".join(fmt(g(m, "time_s"), 6, d) for m in ("irls-h", "irls", "sdp-cso3", "gtsam-lm", "colmap"))
            + f"   | {fmt(s['ratios'].get('time_vs_colmap'), 6, 2)} {fmt(s['ratios'].get('time_vs_gtsam'), 6, 2)}"
            f" {fmt(s['ratios'].get('median_vs_oracle'), 7, 3)}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="N = 20 and 100, seed 0, SDP at N = 20, scale N = 2000 (< 1 min)")
    ap.add_argument("--sizes", type=int, nargs="*", default=None)
    ap.add_argument("--seeds", type=int, nargs="*", default=None)
    ap.add_argument("--scale-sizes", type=int, nargs="*", default=None)
    ap.add_argument("--no-scale", action="store_true", help="skip the kNN scale rows")
    ap.add_argument("--no-sdp", action="store_true", help="skip SDP-cSO(3)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    sizes = a.sizes or ([20, 100] if a.quick else [20, 50, 100, 500])
    seeds = a.seeds if a.seeds is not None else ([0] if a.quick else [0, 1, 2])
    scale_sizes = [] if a.no_scale else (a.scale_sizes or ([2000] if a.quick else [2000, 10000]))
    out_path = a.out or RESULTS / ("irls_h_quick.json" if a.quick else "irls_h.json")
    gtsam = have_gtsam()
    if not gtsam:
        print("GTSAM not installed (pip install -e '.[bench]'): skipping gtsam-lm")
    t_start = time.perf_counter()
    setup = {"protocol": "paper2_graph(N, p=12/(N-1), eig_range, seed); outliers: Haar-random R_rel, H kept",
             "sizes": sizes, "seeds": seeds, "eig_ranges": EIG_RANGES, "outlier_fracs": OUTLIER_FRACS,
             "sdp": ("scs, N <= " + ("20" if a.quick else "100")) if not a.no_sdp else "skipped",
             "gtsam": gtsam, "quick": a.quick, "env": {"OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY")}}
    rows: list[dict] = []
    cells: list[dict] = []
    for eig in EIG_RANGES:
        for n in sizes:
            p = min(1.0, 12.0 / (n - 1))
            graphs = {seed: paper2_graph(n, p, eig_range=eig, seed=seed) for seed in seeds}
            for frac in OUTLIER_FRACS:
                cell_rows = []
                for seed in seeds:
                    g = graphs[seed]
                    vg, out = with_outliers(g.vg, frac, seed=1000 + seed)
                    sdp = (not a.no_sdp) and n <= (20 if a.quick else 100)
                    rec = run_instance(vg, g.R_true, out, reps=3 if n <= 100 else 1, sdp=sdp, gtsam=gtsam)
                    row = {"eig_range": list(eig), "outlier_frac": frac, "N": n, "p": p, "seed": seed,
                           "M": vg.n_edges, **rec}
                    rows.append(row)
                    cell_rows.append(row)
                cell = {"eig_range": list(eig), "outlier_frac": frac, "N": n, "summary": summarize(cell_rows)}
                cells.append(cell)
                print(table([cell]).splitlines()[-1] + f"   [{time.perf_counter() - t_start:.0f} s]", flush=True)
                write_json(out_path, {"setup": setup, "cells": cells, "rows": rows, "partial": True})
    scale_cells: list[dict] = []
    for n in scale_sizes:
        eig, frac = (1.0, 1000.0), 0.1
        vg, R_true, out = anisotropic_knn(n, eig, frac, seed=0)
        rec = run_instance(vg, R_true, out, reps=3, sdp=False, gtsam=False)  # median of 3: single shots are noisy
        row = {"eig_range": list(eig), "outlier_frac": frac, "N": n, "seed": 0, "M": vg.n_edges,
               "graph": "knn_graph k=12 + anisotropic noise", **rec}
        scale_cells.append({"eig_range": list(eig), "outlier_frac": frac, "N": n, "summary": summarize([row]),
                            "row": row})
        print(table(scale_cells[-1:]).splitlines()[-1] + f"   [kNN; {time.perf_counter() - t_start:.0f} s]",
              flush=True)
        write_json(out_path, {"setup": setup, "cells": cells, "rows": rows, "scale": scale_cells, "partial": True})
    elapsed = time.perf_counter() - t_start
    overall = {}
    if cells:
        ratios = [r["ratios"] for r in rows]
        overall = {
            "median_vs_oracle_median": float(np.median([x["median_vs_oracle"] for x in ratios])),
            "median_vs_oracle_max": float(max(x["median_vs_oracle"] for x in ratios)),
            "median_vs_irls_median": float(np.median([x["median_vs_irls"] for x in ratios])),
            "irls_h_beats_irls_share": float(np.mean([x["median_vs_irls"] < 1 for x in ratios])),
            "time_vs_colmap_median": float(np.median([x["time_vs_colmap"] for x in ratios])),
        }
        if gtsam:
            overall["time_vs_gtsam_median"] = float(np.median([x["time_vs_gtsam"] for x in ratios]))
    write_json(out_path, {"setup": setup, "cells": cells, "rows": rows, "scale": scale_cells, "overall": overall,
                          "elapsed_s": elapsed, "partial": False})
    print("\nPaper 2-style graphs (p = 12/(N−1)); kNN rows: knn_graph k=12, H eig 1–1000, 10% outliers, 1 seed.")
    print("Per cell: median over seeds of median error, max of max errors, median wall time; ratios per seed, "
          "then median.")
    print(table(cells + scale_cells))
    print(f"overall: {overall}")
    print(f"wrote {out_path} ({elapsed:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
