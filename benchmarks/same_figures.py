"""Do two runs of run.py give the same figures? (issue 12, acceptance 1: a refactor changes no number)

    python benchmarks/same_figures.py BEFORE_OUT AFTER_OUT [--name default]

Compares, method by method: the rotations files (bit for bit), every figure against the truth in
metrics.json, and every figure against pycolmap. pycolmap's own reconstruction differs from run to run
(its image ids follow the order its threads finish), so the figures against pycolmap are also re-scored
on BEFORE's pycolmap model, which isolates our side. Prints a table and writes
benchmarks/results/same_figures_<name>.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.compare import summarize_against
from pipeline.io.rotations import read_rotations
from pipeline.reference.truth import read_reference

RESULTS = Path(__file__).resolve().parent / "results"
KEYS = ("median_deg", "mean_deg", "rms_deg", "max_deg", "frobenius", "mahalanobis")


def _numbers(d: dict) -> dict[str, float]:
    return {k: float(v) for k, v in d.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def compare(before: Path, after: Path) -> dict:
    mb = json.loads((before / "metrics.json").read_text())
    ma = json.loads((after / "metrics.json").read_text())
    ref = None
    if (before / "reference" / "rotations.txt").is_file():
        ref = read_reference(before / "reference" / "rotations.txt").replace(label="pycolmap")
    vg = ViewGraph.load(after / "viewgraph.npz")
    rows = {}
    for label, eb in mb["methods"].items():
        ea = ma["methods"].get(label)
        if ea is None:
            rows[label] = {"missing_after": True}
            continue
        body = [[ln for ln in (d / "rotations" / f"{label}.txt").read_text().splitlines() if not ln.startswith("#")]
                for d in (before, after)]
        truth_diff = 0.0
        for ref_name, sb in eb["references"].items():
            if not ref_name.startswith("truth"):
                continue
            sa = _numbers(ea["references"].get(ref_name, {}))
            truth_diff = max([truth_diff] + [abs(v - sa.get(k, np.inf)) for k, v in _numbers(sb).items()])
        pyc_diff = None
        if ref is not None and "pycolmap" in eb["references"]:
            names, R = read_rotations(after / "rotations" / f"{label}.txt")
            s = summarize_against(list(names), np.asarray(R), ref, "l2", vg)[0]
            pyc_diff = max(abs(s[k] - eb["references"]["pycolmap"][k]) for k in KEYS)
        rows[label] = {"rotations_identical": body[0] == body[1], "n_cameras": len(body[1]),
                       "max_diff_vs_truth": truth_diff, "max_diff_vs_pycolmap_same_model": pyc_diff}
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--name", default="run")
    a = ap.parse_args()
    rows = compare(a.before, a.after)
    print(f"{'method':<14} {'rotations':<10} {'cams':>4} {'max diff vs truth':>18} {'vs pycolmap (same model)':>25}")
    for label, r in rows.items():
        if r.get("missing_after"):
            print(f"{label:<14} missing after")
            continue
        pyc = "–" if r["max_diff_vs_pycolmap_same_model"] is None else f"{r['max_diff_vs_pycolmap_same_model']:.3g}"
        print(f"{label:<14} {'identical' if r['rotations_identical'] else 'DIFFER':<10} {r['n_cameras']:>4} "
              f"{r['max_diff_vs_truth']:>18.3g} {pyc:>25}")
    write_json(RESULTS / f"same_figures_{a.name}.json", {"before": str(a.before), "after": str(a.after), "methods": rows})


if __name__ == "__main__":
    main()
