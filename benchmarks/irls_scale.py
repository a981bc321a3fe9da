"""Scale: N = 8000 cameras, ~100,000 edges (issue 3, acceptance item 5).

The size of paper 1's San Francisco set (7866 cameras, 101,512 edges; 294 s for
IRLS-ℓ½ in the paper's single-threaded MATLAB, Table 5). Graph:
``knn_graph(8000, k=22, σ=2°, 15% outliers)``. We time ``pipeline.average.average``
with its defaults (IRLS-ℓ½, MST init, 5 ℓ1 steps, IRLS, trimmed-ℓ2 polish) and,
in the same run, ``pycolmap.run_rotation_averaging`` with defaults. Memory: peak
RSS of this process (``resource.getrusage``, which includes the graph generation
and pycolmap when it runs), and the RSS growth during our solver measured in a
fresh subprocess, so that pycolmap's memory is not counted against ours.

Usage: ``python benchmarks/irls_scale.py [--quick] [--no-colmap]``
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"

CHILD = r"""
import json, resource, sys, time, logging
import numpy as np
logging.disable(logging.WARNING)
from pipeline.synthetic.graphs import knn_graph
from pipeline.averaging import average
from pipeline.evaluation.metrics import rotation_errors_deg
n, k, seed = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
g = knn_graph(n, k=k, sigma_deg=2.0, outlier_frac=0.15, seed=seed)
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
res = average(g.vg)
wall = time.perf_counter() - t
rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
e = rotation_errors_deg(res.R, g.R_true)
print(json.dumps({"n": n, "m": g.vg.n_edges, "wall_s": wall, "solver_time_s": res.time_s,
                  "l1_iterations": res.stats["l1_iterations"], "irls_iterations": res.iterations,
                  "peak_rss_mb_after_generation": rss0 / 1024, "peak_rss_mb": rss1 / 1024,
                  "median_deg": float(np.median(e)), "max_deg": float(e.max())}))
"""


def main(argv: list[str] | None = None) -> int:
    from pipeline.core.atomic import write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="N = 2000, k = 22")
    ap.add_argument("--n", type=int, default=8000)
    ap.add_argument("--k", type=int, default=22)
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    ap.add_argument("--no-colmap", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS / "irls_scale.json")
    a = ap.parse_args(argv)
    n = 2000 if a.quick else a.n
    seeds = a.seeds[:1] if a.quick else a.seeds
    rows = []
    for seed in seeds:
        out = subprocess.run([sys.executable, "-c", CHILD, str(n), str(a.k), str(seed)], capture_output=True, text=True)
        if out.returncode != 0:
            print(out.stderr[-2000:])
            return 1
        row = json.loads(out.stdout.strip().splitlines()[-1])
        if not a.no_colmap:
            from pipeline.averaging.peers import run_colmap
            from pipeline.evaluation.metrics import rotation_errors_deg
            from pipeline.synthetic.graphs import knn_graph

            g = knn_graph(n, k=a.k, sigma_deg=2.0, outlier_frac=0.15, seed=seed)
            R, reg, dt, ok = run_colmap(g.vg)
            e = rotation_errors_deg(R, g.R_true, reg)
            e = e[np.isfinite(e)]
            row["colmap_default"] = {"time_s": dt, "median_deg": float(np.median(e)), "max_deg": float(e.max()),
                                     "n_registered": int(reg.sum())}
            row["time_ratio_vs_colmap"] = row["wall_s"] / dt
        rows.append(row)
        print(json.dumps(row), flush=True)
    summary = {
        "n": n,
        "m_mean": float(np.mean([r["m"] for r in rows])),
        "wall_s_median": float(np.median([r["wall_s"] for r in rows])),
        "wall_s_max": float(np.max([r["wall_s"] for r in rows])),
        "peak_rss_mb_max": float(np.max([r["peak_rss_mb"] for r in rows])),
        "target": "<= 20 s and <= 4096 MB at N=8000, ~100k edges",
        "paper1_matlab_snf_s": 294,
        "this_process_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    print("summary:", json.dumps(summary))
    write_json(a.out, {"rows": rows, "summary": summary})
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
