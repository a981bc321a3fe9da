"""The refinement's choice of the pairs that make tracks (``pipeline.refine.stage._checked_pairs``): index keys
matched with ``np.isin`` against one name-pair set lookup per edge, in the same run.

    python benchmarks/refine_pairs.py [--repeats R]

The "before" is the definition kept in ``tests/refine/test_checked_pairs.py`` (``_reference``, loaded from that
file). Input: a dense graph of 5000 cameras and 300,000 pairs as the two-view BA graph; the view-graph stage's
output beside it keeps a random 80% and its summary lists every pair (the rejected ones half with ``tracks``). Both
read the same files; they must give the same graph (checked). Reports median times; writes
``benchmarks/results/refine_pairs.json`` atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import runpy
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from _common import median_time as _timed, save_results  # noqa: E402  (benchmarks/, the script's folder)
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.graph.stage import SUMMARY  # noqa: E402
from pipeline.refine.stage import _checked_pairs  # noqa: E402
from pipeline.synthetic.protocols import dense_graph  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "refine_pairs.json"
REFERENCE = runpy.run_path(str(HERE.parent / "tests" / "refine" / "test_checked_pairs.py"))["_reference"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    g0 = dense_graph(5000, 300000, seed=0)[0].vg
    M, rng = g0.n_edges, np.random.default_rng(0)
    vg = ViewGraph(g0.names, g0.edges, g0.R_rel, H=np.tile(np.eye(3), (M, 1, 1)), allow_isolated=True)
    k = rng.random(M) < 0.8
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        ViewGraph(vg.names, vg.edges[k], vg.R_rel[k], allow_isolated=True).save(out / "viewgraph.npz")
        tracks = rng.random(M) < 0.5
        rows = [{"pair": [vg.names[i], vg.names[j]], "status": "kept" if k[e] else "rejected",
                 "tracks": bool(k[e] or tracks[e])} for e, (i, j) in enumerate(vg.edges.tolist())]
        (out / SUMMARY).write_text(json.dumps({"names": vg.names, "left_out": {}, "n_cameras": len(vg.names),
                                               "n_edges": int(k.sum()), "pairs": rows}))
        t_after, got = _timed(lambda: _checked_pairs(vg, out / "viewgraph.npz"), a.repeats)
        t_before, want = _timed(lambda: REFERENCE(vg, out / "viewgraph.npz"), a.repeats)
    same = np.array_equal(got.edges, want.edges) and np.array_equal(got.R_rel, want.R_rel)
    row = {"n_cameras": vg.n_cameras, "n_edges": M, "n_selected": got.n_edges, "before_s": t_before,
           "after_s": t_after, "speedup": t_before / t_after, "identical": bool(same), "repeats": a.repeats}
    print(f"{'pairs':>7s} {'selected':>8s} {'before s':>9s} {'after s':>8s} {'speedup':>7s}  same")
    print(f"{M:7d} {got.n_edges:8d} {t_before:9.3f} {t_after:8.3f} {row['speedup']:7.2f}  {same}")
    save_results(a.json, [row], "refine_pairs.py", argv)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
