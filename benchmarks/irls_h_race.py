"""IRLS-H's race of the candidate metrics: the same selection and rotations as running every candidate to its end,
for less time, and IRLS-H's time against the isotropic IRLS-ℓ½ it starts from.

IRLS-H (calibrated, the product's ``irls-h``) fits one Student-t + Haar mixture by EM per candidate metric and keeps
the likeliest (``pipeline.averaging.calibration``). The race (``race: true``, the default) stops a candidate that
trails the leader by a wide margin at EM iterations 3, 9 and 27. This benchmark runs, on each graph, in the same
process: ``irls-h`` (race), ``irls-h`` with ``race=False`` (every candidate to its end: the method before the race)
and ``irls`` (IRLS-ℓ½, the start IRLS-H runs first), each ``--repeat`` times (median wall time), and reports the
metric each IRLS-H chose, the largest rotation difference between the two (degrees, no alignment), the EM
iterations, and the time ratios.

Graphs:
* the checked view graphs of fountain-P11, castle-P30 and templeSparseRing (``--runs``: ``<runs>/<scene>/
  viewgraph.npz`` as ``run.py --K <true K> --out <runs>/<scene>`` wrote them);
* ``miscalibrated_h_graph`` (kNN k = 12, H overconfident by edge-varying factors with exaggerated anisotropy, 10%
  outliers) at N = ``--sizes``, seeds ``--seeds``.

Usage::

    OMP_WAIT_POLICY=PASSIVE python benchmarks/irls_h_race.py [--runs /work/runs] [--sizes 300 1000 2000]

Writes ``benchmarks/results/irls_h_race.json``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.synthetic.protocols import miscalibrated_h_graph
from robust_averaging import timed  # its median-of-repeats timer (this script's folder is on sys.path)

RESULTS = Path(__file__).resolve().parent / "results"
SCENES = ("fountain-P11", "castle-P30", "temple")


def em_iterations(res: Any) -> int:
    return int(sum(c["iterations"] for c in res.stats["candidates"].values()))


def row_of(label: str, vg: ViewGraph, repeat: int, R_true: np.ndarray | None) -> dict[str, Any]:
    race, t_race = timed(vg, "irls-h", repeat)
    full, t_full = timed(vg, "irls-h", repeat, race=False)
    iso, t_iso = timed(vg, "irls", repeat)
    row: dict[str, Any] = {
        "graph": label, "n_cameras": vg.n_cameras, "n_edges": vg.n_edges,
        "selected_race": race.stats["selected"], "selected_full": full.stats["selected"],
        "max_rotation_diff_deg": float(rotation_errors_deg(race.R, full.R, align="none").max()),
        "dropped": sorted(k for k, c in race.stats["candidates"].items() if "dropped_behind" in c),
        "em_iterations_race": em_iterations(race), "em_iterations_full": em_iterations(full),
        "time_race_s": t_race, "time_full_s": t_full, "time_irls_s": t_iso,
        "speedup": t_full / t_race, "irls_h_over_irls_race": t_race / t_iso, "irls_h_over_irls_full": t_full / t_iso,
        "certificate": race.stats["certificate"]["verdict"]}
    if R_true is not None:
        row["median_deg_race"] = float(np.median(rotation_errors_deg(race.R, R_true)))
    print(f"  {label:22s} N={vg.n_cameras:5d} M={vg.n_edges:6d}  {row['selected_race']:14s} (full: "
          f"{row['selected_full']:14s}) diff {row['max_rotation_diff_deg']:.1e}°  EM it {row['em_iterations_full']:4d}"
          f" -> {row['em_iterations_race']:4d}  time {t_full:7.3f} -> {t_race:7.3f} s ({row['speedup']:.1f}x)  "
          f"IRLS-l0.5 {t_iso:6.3f} s: IRLS-H / IRLS {row['irls_h_over_irls_full']:5.1f} -> "
          f"{row['irls_h_over_irls_race']:5.1f}", flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=Path, default=Path("/work/runs"), help="folder with <scene>/viewgraph.npz")
    p.add_argument("--sizes", type=int, nargs="+", default=[300, 1000, 2000])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--repeat", type=int, default=3, help="calls per timing (median)")
    p.add_argument("--out", type=Path, default=RESULTS / "irls_h_race.json")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rows = []
    print("IRLS-H: race against every candidate to its end, and against IRLS-l0.5")
    for scene in SCENES:
        path = a.runs / scene / "viewgraph.npz"
        if path.is_file():
            rows.append(row_of(scene, ViewGraph.load(path), a.repeat, None))
        else:
            print(f"  {scene}: no {path}; skipped")
    for n in a.sizes:
        for seed in a.seeds:
            g, _ = miscalibrated_h_graph(n, seed=seed)
            rows.append(row_of(f"miscalibrated-H {n} s{seed}", g.vg, a.repeat, g.R_true))
    out = {"argv": sys.argv[1:], "load_average": os.getloadavg(), "rows": rows,
           "same_selection_everywhere": all(r["selected_race"] == r["selected_full"] for r in rows),
           "max_rotation_diff_deg": max((r["max_rotation_diff_deg"] for r in rows), default=None)}
    write_json(a.out, out)
    print(f"same selection on all {len(rows)} graphs: {out['same_selection_everywhere']}; largest rotation "
          f"difference {out['max_rotation_diff_deg']:.1e}°\nwrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
