"""SDP-cSO(3) as run.py runs it: its start's dual certificate first, the conic program only where that fails.

    python benchmarks/sdp_start.py [--sizes 20 50] [--seeds 0 1] [--lowtex-views 48] [--runs DIR ...]
                                   [--work DIR] [--out benchmarks/results/sdp_start.json]

The robust SDP (``average(vg, "sdp")``: the robust stage's edges and calibrated cost) first polishes
the robust stage's rotations on the SDP's cost and tests their dual certificate; when it proves them
optimal to the test a conic solve must pass, no conic program is solved (``sdp.certify_start``, as
SE-Sync verifies a local solution). This benchmark times that against the conic solve alone
(``certify_start=False``: SCS, run.py's solver, with the Clarabel fallback at N ≤ 30), on the same
graph in the same run, and checks that both give the same rotations, both certified:

- ``synthetic``: paper 2's anisotropic graphs (``paper2_graph``, edge probability 0.5, H eigenvalues
  1e3–1e4) with 15% outlier edges, N = ``--sizes``, seeds ``--seeds``;
- ``lowtex``: the rendered low-texture turntable with ``--lowtex-views`` views (a ring as Middlebury's
  templeRing and dinoRing, 47 and 48 views), its view graph made by ``run.py --methods irls-h
  --no-reference`` in ``--work``;
- ``runs``: the view graphs of ``run.py`` runs (``--runs DIR ...``, each with ``viewgraph.npz`` and the
  truth named in its ``metrics.json``).

Every row: cameras, edges, the two wall times and their ratio, who proved each result, the largest
rotation difference between them, and the median error against the truth. Writes
``benchmarks/results/sdp_start.json`` (atomically) and prints a table.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("GLOG_minloglevel", "2")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.averaging import average  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import rotation_errors_deg  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
from pipeline.synthetic.graphs import paper2_graph, with_outliers  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "sdp_start.json"


def compare(label: str, vg: ViewGraph, R_true: np.ndarray | None, mask: np.ndarray | None = None) -> dict[str, Any]:
    """Both ways of solving the robust SDP on ``vg``, timed and compared (one row)."""
    res, wall = {}, {}
    for key, opts in (("start", {}), ("conic", {"certify_start": False})):
        t = time.perf_counter()
        res[key] = average(vg, "sdp", **opts)
        wall[key] = time.perf_counter() - t
    row: dict[str, Any] = {"graph": label, "n_cameras": vg.n_cameras, "n_edges": vg.n_edges,
                           "wall_s": wall, "time_ratio": wall["start"] / wall["conic"],
                           "max_difference_deg": float(rotation_errors_deg(res["start"].R, res["conic"].R).max())}
    for key, r in res.items():
        st = r.stats
        row[key] = {"solver": st["solver"], "solver_iterations": st["solver_iterations"],
                    "certified": st["certified"], "certified_by": st["certified_by"],
                    "gap_vs_resolution": st["gap_vs_resolution"], "fallback": st["fallback"],
                    "n_kept": st.get("n_kept"), "statement": st["certificate"]["statement"]}
        if R_true is not None:
            row[key]["median_deg"] = float(np.nanmedian(rotation_errors_deg(r.R, R_true, mask)))
    print(f"  {label:28s} N={vg.n_cameras:3d} M={vg.n_edges:4d}  start {wall['start']:7.2f} s "
          f"({row['start']['solver']}, certified {row['start']['certified']})  conic {wall['conic']:7.2f} s "
          f"({row['conic']['solver']}, {row['conic']['solver_iterations']} it., certified {row['conic']['certified']})"
          f"  ratio {row['time_ratio']:.4f}  max diff {row['max_difference_deg']:.2g}°"
          + (f"  median {row['start']['median_deg']:.4f}° / {row['conic']['median_deg']:.4f}°"
             if R_true is not None else ""), flush=True)
    return row


def from_run(run: Path) -> tuple[ViewGraph, np.ndarray | None, np.ndarray | None]:
    """A run's checked view graph and, where its ``metrics.json`` names one, the truth on its cameras."""
    vg = ViewGraph.load(run / "viewgraph.npz")
    gt = json.loads((run / "metrics.json").read_text()).get("input", {}).get("gt")
    if not gt:
        return vg, None, None
    ref = read_reference(gt)
    R_true, mask = match_reference(list(vg.names), ref.names, ref.R)
    return vg, R_true, mask


def lowtex_run(views: int, work: Path) -> Path:
    """Render the low-texture turntable with ``views`` views and make its view graph with ``run.py``."""
    from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex, write_scene  # noqa: PLC0415

    scene, run = work / f"lowtex{views}", work / f"lowtex{views}_run"
    if not (scene / "cameras.txt").is_file():
        write_scene(render_lowtex(LowTexConfig(n_views=views), seed=0), scene)
    if not (run / "viewgraph.npz").is_file():
        subprocess.run([sys.executable, str(ROOT / "run.py"), str(scene), "--K", str(scene / "K.txt"),
                        "--gt", str(scene / "cameras.txt"), "--methods", "irls-h", "--no-reference", "-q",
                        "--out", str(run)], check=True)
    return run


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", type=int, nargs="*", default=[20, 50], help="synthetic graphs' camera counts")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--lowtex-views", type=int, nargs="*", default=[48], help="rendered turntable rings (none: skip)")
    p.add_argument("--runs", type=Path, nargs="*", default=[], help="run.py output folders")
    p.add_argument("--work", type=Path, default=None, help="where the rendered scenes and their runs go (kept)")
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rows = []
    print("robust SDP-cSO(3): the start's certificate first vs the conic solve alone (SCS), same graph")
    for n in a.sizes:
        for seed in a.seeds:
            g = paper2_graph(n, 0.5, eig_range=(1e3, 1e4), seed=seed)
            vg, _ = with_outliers(g.vg, 0.15, seed=seed + 100)
            rows.append({"kind": "synthetic", "seed": seed, **compare(f"paper2 N={n} seed {seed}", vg, g.R_true)})
    with tempfile.TemporaryDirectory() as tmp:
        work = a.work or Path(tmp)
        for views in a.lowtex_views:
            run = lowtex_run(views, work)
            rows.append({"kind": "lowtex", "run": str(run), **compare(f"lowtex ring, {views} views", *from_run(run))})
    for run in a.runs:
        rows.append({"kind": "run", "run": str(run), **compare(run.name, *from_run(run))})
    out = {"benchmark": "sdp_start", "argv": sys.argv[1:], "load_average": os.getloadavg(), "rows": rows,
           "all_same": all(r["max_difference_deg"] < 1e-3 for r in rows),
           "all_certified": all(r["start"]["certified"] and r["conic"]["certified"] for r in rows)}
    write_json(a.out, out)
    print(f"same rotations (< 1e-3°) on every graph: {out['all_same']}; both certified on every graph: "
          f"{out['all_certified']}\nwrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
