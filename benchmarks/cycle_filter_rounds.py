"""The cycle filter's greedy rounds with each inconsistent cycle's owner kept up to date, against the rounds before
(every candidate re-sorted and re-checked against its cycles in each round), in the same run.

    python benchmarks/cycle_filter_rounds.py [--quick] [--repeats R]

The "before" is the definition kept in ``tests/graph/test_cycle_filter_rounds.py`` (``_reference``, loaded from that
file). Graphs, with the σ the view-graph checks give them (``pair_evidence`` of synthetic inlier counts): a kNN
graph of 3000 cameras (protocol "repeated") and, unless ``--quick``, a dense 1DSfM-like graph of 2000 cameras and
50,000 pairs (about 570,000 short cycles, 13,000 removals). Both versions must give the same removals and the same
arrays (checked). Reports median times; writes ``benchmarks/results/cycle_filter_rounds.json`` atomically.
"""

from __future__ import annotations

import argparse
import os
import runpy
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from _common import median_time as _timed, save_results  # noqa: E402  (benchmarks/, the script's folder)
from pipeline.graph.checks import ViewGraphConfig  # noqa: E402
from pipeline.graph.loops import cycle_filter  # noqa: E402
from pipeline.graph.tiers import pair_evidence  # noqa: E402
from pipeline.synthetic.protocols import dense_graph, make_protocol, synthetic_inlier_counts  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "cycle_filter_rounds.json"
DEFINITION = runpy.run_path(str(HERE.parent / "tests" / "graph" / "test_cycle_filter_rounds.py"))
FIELDS = DEFINITION["FIELDS"]


def _inputs(vg, cfg: ViewGraphConfig) -> tuple[tuple, dict]:
    sw = np.nan_to_num(pair_evidence(vg).sigma_weak_deg, nan=cfg.sigma_floor_deg)
    kw = dict(max_len=cfg.max_cycle_length, k_sigma=cfg.cycle_k_sigma, min_deg=cfg.cycle_min_deg,
              max_deg=cfg.cycle_max_deg, max_bad_fraction=cfg.max_bad_fraction, max_four_cycles=cfg.max_four_cycles)
    return (vg.edges, vg.R_rel, vg.n_cameras, np.maximum(sw, cfg.sigma_floor_deg)), kw


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the kNN graph only")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    graphs = [("kNN 3000 (repeated)", make_protocol("repeated", 3000, 0)[0].vg)]
    if not a.quick:
        sg, sig = dense_graph(2000, 50000, seed=0)
        sg.vg.inliers = synthetic_inlier_counts(sig, sg.outlier_mask, 1.0, np.random.default_rng(1))
        graphs.append(("dense 2000 / 50k pairs", sg.vg))
    cfg, rows = ViewGraphConfig(), []
    print(f"{'graph':24s} {'pairs':>6s} {'cycles':>7s} {'removed':>7s} {'before s':>9s} {'after s':>8s} "
          f"{'speedup':>7s}  same")
    for name, vg in graphs:
        args, kw = _inputs(vg, cfg)
        t_after, res = _timed(lambda: cycle_filter(*args, **kw), a.repeats)
        t_before, ref = _timed(lambda: DEFINITION["_reference"](*args, **kw), a.repeats)
        same = (res.removed == ref["removed"] and res.kappa2 == ref["kappa2"]
                and all(np.array_equal(getattr(res, f), ref[f]) for f in FIELDS))
        row = {"graph": name, "n_cameras": vg.n_cameras, "n_edges": vg.n_edges, "n_cycles": len(res.cycles),
               "n_removed": len(res.removed), "before_s": t_before, "after_s": t_after,
               "speedup": t_before / t_after, "identical": bool(same), "repeats": a.repeats}
        rows.append(row)
        print(f"{name:24s} {vg.n_edges:6d} {len(res.cycles):7d} {len(res.removed):7d} {t_before:9.2f} "
              f"{t_after:8.2f} {row['speedup']:7.2f}  {same}", flush=True)
    save_results(a.json, rows, "cycle_filter_rounds.py", argv)
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
