"""Scale of SDP-cSO(3): N = 100, 200, 400 on two graph families, SCS vs Clarabel.

Graphs (true rotations, H with eigenvalues in [10, 100] 1/rad², noise Δω ~ N(0, H⁻¹),
``R̃_ij = exp([Δω]×) R_j R_iᵀ`` as in paper 2 §5.1):

* ``p0.2``: ``paper2_graph(N, 0.2)`` (a random 20% of the pairs);
* ``knn14``: the edges of ``knn_graph(N, k=12, outlier_frac=0)`` (mean degree ≈ 14),
  whose measurements are redrawn with H exactly as paper2_graph does (knn_graph
  itself carries no H).

Solvers, each run in a subprocess with a 10-minute limit and an address-space cap:
SCS (primal form), Clarabel (dual form) without and with chordal decomposition.
Clarabel without decomposition forms a dense (svec 3N)² block in its KKT system
(16 GB at N = 100), so it is skipped, with the reason, where that exceeds the cap.
Reported: wall time (build + solve), build and solve times, their ratio, rank,
gap, errors against the truth; GTSAM Shonan (isotropic) and an anisotropic LM from
its result as peers where they finish.

    python benchmarks/sdp_scale.py [--quick] [--sizes 100 200 400] [--time-limit 600]
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.averaging.peers import have_gtsam, lm_anisotropic, shonan
from pipeline.core import so3
from pipeline.core.atomic import write_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.metrics import frobenius_error, rotation_errors_deg
from pipeline.synthetic.graphs import knn_graph, paper2_graph, random_precisions, sample_left_noise

OUT = Path(__file__).resolve().parent / "results" / "sdp_scale.json"
MEM_CAP_GB = 8.0


def make_graph(kind: str, n: int, seed: int = 0) -> tuple[ViewGraph, np.ndarray]:
    if kind == "p0.2":
        g = paper2_graph(n, 0.2, seed=seed)
        return g.vg, g.R_true
    g = knn_graph(n, k=12, outlier_frac=0.0, seed=seed)
    rng = np.random.default_rng([seed, n, 14])
    E = g.vg.edges
    H = random_precisions(E.shape[0], (10.0, 100.0), rng)
    R_rel = so3.exp(sample_left_noise(H, rng)) @ g.R_true[E[:, 1]] @ np.swapaxes(g.R_true[E[:, 0]], 1, 2)
    return ViewGraph(g.vg.names, E, R_rel, H=H), g.R_true


_CHILD = """
import json, resource, sys, time, logging
logging.disable(logging.WARNING)
cap = int(float(sys.argv[5]) * 2**30)
resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
import runpy
from pipeline.evaluation.metrics import frobenius_error, rotation_errors_deg
import numpy as np
from pipeline.averaging.sdp import solve_sdp
make_graph = runpy.run_path(sys.argv[6])["make_graph"]  # this benchmark's graphs, without touching sys.path
vg, R_true = make_graph(sys.argv[1], int(sys.argv[2]))
kw = json.loads(sys.argv[4])
t0 = time.perf_counter()
r = solve_sdp(vg, "cso3", sys.argv[3], **kw)
wall = time.perf_counter() - t0
st = r.stats
print(json.dumps({"wall_s": wall, "cpu_s": time.process_time(), "frobenius": frobenius_error(r.R, R_true),
                  "median_deg": float(np.nanmedian(rotation_errors_deg(r.R, R_true))),
                  **{k: st[k] for k in ("build_s", "solve_s", "rank", "gap", "certified", "status",
                                         "solver_iterations", "n_variables", "n_constraints")}}))
"""


def run_child(kind: str, n: int, solver: str, kw: dict, time_limit: float) -> dict:
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", _CHILD, kind, str(n), solver, json.dumps(kw), str(MEM_CAP_GB),
                            str(Path(__file__).resolve())], capture_output=True, text=True,
                           timeout=time_limit + 60)
    except subprocess.TimeoutExpired:
        return {"failed": f"killed after {time.perf_counter() - t0:.0f} s (limit {time_limit} s)"}
    if p.returncode:
        tail = (p.stderr.strip().splitlines() or ["?"])[-1]
        return {"failed": f"exit {p.returncode}: {tail[:200]}", "wall_s": time.perf_counter() - t0}
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N = 30 and 60 only")
    ap.add_argument("--sizes", type=int, nargs="*", default=[100, 200, 400])
    ap.add_argument("--kinds", nargs="*", default=["p0.2", "knn14"])
    ap.add_argument("--time-limit", type=float, default=600.0)
    ap.add_argument("--clarabel-time-limit", type=float, default=300.0,
                    help="Clarabel's limit (its iterations are long, so the child is killed at limit + 60 s)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    sizes = [30, 60] if args.quick else args.sizes
    configs = {
        "scs": ("scs", {"time_limit_secs": args.time_limit}),
        "clarabel": ("clarabel", {"time_limit": args.clarabel_time_limit}),
        "clarabel-chordal": ("clarabel", {"time_limit": args.clarabel_time_limit, "chordal_decomposition_enable": True}),
    }
    out: dict = {"setup": {"sizes": sizes, "kinds": args.kinds, "variant": "cso3", "time_limit_s": args.time_limit,
                           "mem_cap_gb": MEM_CAP_GB}, "runs": []}
    for n in sizes:
        for kind in args.kinds:
            vg, R_true = make_graph(kind, n)
            base = {"N": n, "kind": kind, "M": vg.n_edges, "mean_degree": float(vg.degrees().mean())}
            svec = 3 * n * (3 * n + 1) // 2
            for name, (solver, kw) in configs.items():
                failed_smaller = [r["N"] for r in out["runs"] if r["config"] == name and r["kind"] == kind
                                  and ("failed" in r or "skipped" in r)]
                if failed_smaller:
                    res = {"skipped": f"failed or skipped at N={min(failed_smaller)}"}
                elif name == "clarabel" and svec**2 * 8 > MEM_CAP_GB * 2**30 / 2:
                    res = {"skipped": f"dense PSD block of the KKT system needs {svec**2 * 8 / 2**30:.0f} GB "
                                      f"(svec size {svec}); cap {MEM_CAP_GB} GB"}
                else:
                    res = run_child(kind, n, solver, kw, kw["time_limit_secs" if solver == "scs" else "time_limit"])
                if "build_s" in res and res.get("solve_s"):
                    res["build_over_solve"] = res["build_s"] / res["solve_s"]
                out["runs"].append({**base, "config": name, **res})
                write_json(OUT, out)
                print(f"N={n:4d} {kind:6s} M={vg.n_edges:6d} {name:17s} " + (
                    f"wall {res['wall_s']:8.1f} s build {res['build_s']:.3f} s ({100 * res.get('build_over_solve', 0):.2f}% of solve) "
                    f"rank {res['rank']} gap {res['gap']:.1e} iters {res['solver_iterations']} {res['status']} "
                    f"frob {res['frobenius']:.3f}" if "rank" in res else str(res)), flush=True)
            if have_gtsam():
                R_sh, lam, t_sh = shonan(vg)
                R_lm, t_lm, it = lm_anisotropic(vg, R_sh)
                for name, R, t in (("gtsam-shonan3", R_sh, t_sh), ("gtsam-shonan3+lm-aniso", R_lm, t_sh + t_lm)):
                    res = {"wall_s": t, "frobenius": frobenius_error(R, R_true),
                           "median_deg": float(np.nanmedian(rotation_errors_deg(R, R_true)))}
                    out["runs"].append({**base, "config": name, **res})
                    print(f"N={n:4d} {kind:6s} M={vg.n_edges:6d} {name:17s} wall {t:8.1f} s frob {res['frobenius']:.3f}",
                          flush=True)
                write_json(OUT, out)
    ok = [r for r in out["runs"] if r["config"].startswith(("scs", "clarabel")) and r.get("rank") == 3
          and r["wall_s"] <= args.time_limit]
    out["largest_N_within_limit"] = {c: max([r["N"] for r in ok if r["config"] == c], default=None)
                                     for c in configs}
    out["max_build_over_solve"] = max([r.get("build_over_solve", 0) for r in out["runs"]], default=None)
    write_json(OUT, out)
    print(f"largest N solved (rank 3) within {args.time_limit:.0f} s: {out['largest_N_within_limit']}")
    print(f"max build/solve ratio: {out['max_build_over_solve']}")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
