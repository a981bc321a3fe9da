"""The view-graph checks before and after a change of their rules, on the same two-view BA graphs.

The checks are a pure function of the two-view BA graph (``pipeline.graph.checks``), so two sets
of rules can be compared on one front-end run, with nothing else varying. This script reads the
runs that ``benchmarks/front_end_checks.py --work W --label after`` left in ``W/runs/<scene>_after``
(fountain-P11, castle-P30, templeSparseRing, the low-texture turntables, the injected static and
repeated scenes and their controls; each run's truth is the ``--gt`` its ``metrics.json`` records)
and applies to each BA graph

- ``before`` (``--change bridges``, the default): the rules of 534a003 (no bridge exception, every
  non-rotation-only pair a co-location witness): ``keep_bridges: false``, ``colocation_min_parallax_deg: 0``;
  (``--change robust-unconfirmed``): the robust filter's solution on the kept pairs alone;
- ``after``: the defaults.

Per scene and rule set: pairs kept, kept pairs more than 5° from the truth (and the worst), images
solved (largest component), pairs kept by the bridge exception, co-location rejections, and the
median error of IRLS-ℓ½ and IRLS-H on the kept graph (ℓ2 alignment). Usage::

    python benchmarks/front_end_checks.py --work W --label after --json W/after.json
    python benchmarks/checks_compare.py --work W [--json benchmarks/results/checks_compare.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.averaging.solve import average  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import edge_errors_deg, rotation_errors_deg  # noqa: E402
from pipeline.geometry.ba_stage import load_ba_viewgraph  # noqa: E402
from pipeline.graph.checks import ViewGraphConfig, check_view_graph  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "checks_compare.json"
#: Rule changes compared (``--change``): "before" against the defaults ("after").
CHANGES = {
    # 534a003 → the bridge exception and co-location witnesses with parallax (issue 16)
    "bridges": ViewGraphConfig(keep_bridges=False, colocation_min_parallax_deg=0.0),
    # the robust filter's solution without the pairs dropped as unconfirmed (before 2026-12-03, seventh session)
    "robust-unconfirmed": ViewGraphConfig(robust_unconfirmed=False),
}
RULES = {"before": CHANGES["bridges"], "after": ViewGraphConfig()}


def compare(vg: ViewGraph, R_ref: np.ndarray, mask: np.ndarray) -> dict:
    err = edge_errors_deg(vg, R_ref, mask)
    out: dict = {}
    for label, cfg in RULES.items():
        chk = check_view_graph(vg, cfg)
        k = chk.kept
        sub, restr = ViewGraph(vg.names, vg.edges[k], vg.R_rel[k], H=vg.H[k], allow_isolated=True).largest_component()
        row = {"kept": int(k.sum()), "kept_gt5": int(np.sum(err[k] > 5)),
               "max_err_deg": round(float(np.nanmax(err[k])), 3) if k.any() else None, "solved": sub.n_cameras,
               "bridged": int(chk.info.get("bridged", 0)), "colocation": int(chk.info["colocation"])}
        for method in ("irls", "irls-h"):
            res = average(sub, method)
            idx = [vg.names.index(n) for n in res.names]
            row[f"{method}_median_deg"] = round(float(np.median(rotation_errors_deg(np.asarray(res.R), R_ref[idx],
                                                                                   mask[idx]))), 4)
        out[label] = row
    out["same_pairs"] = out["before"]["kept"] == out["after"]["kept"]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="the work folder of front_end_checks.py")
    p.add_argument("--json", type=Path, default=RESULTS)
    p.add_argument("--change", choices=list(CHANGES), default="bridges", help="which rule change to compare")
    a = p.parse_args(argv)
    RULES["before"] = CHANGES[a.change]
    rows = {}
    for out in sorted((a.work / "runs").glob("*_after")):
        gt = json.loads((out / "metrics.json").read_text())["input"].get("gt") if (out / "metrics.json").is_file() \
            else None
        if not gt or not (out / "work").is_dir():
            continue
        name = out.name.removesuffix("_after")
        vg = load_ba_viewgraph(out / "work")
        truth = read_reference(gt)
        R_ref, mask = match_reference(vg.names, truth.names, truth.R)
        rows[name] = compare(vg, R_ref, mask)
    cols = ("kept", "kept_gt5", "max_err_deg", "solved", "bridged", "colocation", "irls_median_deg",
            "irls-h_median_deg")
    print(f"{'scene':18s} {'rules':7s} " + " ".join(f"{c:>17s}" for c in cols))
    for name, r in rows.items():
        for label in RULES:
            print(f"{name:18s} {label:7s} " + " ".join(f"{str(r[label][c]):>17s}" for c in cols))
    a.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(a.json, {"rows": rows, "change": a.change, "command": "python benchmarks/checks_compare.py " + " ".join(
        sys.argv[1:] if argv is None else argv)})
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
