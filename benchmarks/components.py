"""Several scenes in one folder: every connected component of the view graph solved, each scene scored against its
own truth.

Builds folders of symbolic links to ``../shared/data`` images (read in place; names prefixed by scene so that they
do not collide), with no K and no EXIF, runs ``run.py FOLDER --no-reference`` on each, and scores, in ``OUT`` and in
every ``OUT/component-k/``, each method's rotations on each scene's images against that scene's truth (aligned on
those images alone: two scenes in one component share a frame, but their truths do not). Sets:

* ``fountain+temple``: fountain-P11 (11 images, 3072×2048) and templeSparseRing (16, 640×480): 27 images,
  matched exhaustively;
* ``fountain+castle+temple``: castle-P30 (30) added: 57 images, so retrieval pairs. Fountain-P11 was taken in
  castle-P30's courtyard, so those two may form one component.

Usage::

    python benchmarks/components.py [--sets fountain+temple] [--work W]

Writes ``benchmarks/results/components.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.io.rotations import read_rotations
from pipeline.reference.truth import read_reference

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
DATA = REPO.parent / "shared" / "data"
#: scene -> (image folder, image glob, truth, name prefix)
SCENES = {
    "fountain": ("strecha/fountain-P11/images", "*.jpg", "strecha/fountain-P11/gt_dense_cameras", "fountain_"),
    "castle": ("strecha/castle-P30/images", "*.jpg", "strecha/castle-P30/gt_dense_cameras", "castle_"),
    "temple": ("middlebury-templeSparseRing", "*.png", "middlebury-templeSparseRing/templeSR_par.txt", "temple_"),
}
SETS = {"fountain+temple": ("fountain", "temple"), "fountain+castle+temple": ("fountain", "castle", "temple")}


def build_folder(folder: Path, scenes: tuple[str, ...], data: Path) -> dict[str, str]:
    """Links to every image of ``scenes`` in ``folder``; returns {link name: scene}."""
    folder.mkdir(parents=True, exist_ok=True)
    owner = {}
    for sc in scenes:
        src, pattern, _, prefix = SCENES[sc]
        for p in sorted((data / src).glob(pattern)):
            link = folder / f"{prefix}{p.name}"
            if not link.exists():
                link.symlink_to(p.resolve())
            owner[link.name] = sc
    return owner


def score(out: Path, owner: dict[str, str], truths: dict[str, Any]) -> dict[str, Any]:
    """Per method, per scene present in ``out``: the median error of its images against that scene's truth."""
    rows: dict[str, Any] = {}
    for path in sorted((out / "rotations").glob("*.txt")):
        names, R = read_rotations(path)
        R = np.asarray(R)
        per: dict[str, Any] = {}
        for sc in sorted({owner[n] for n in names}):
            ref = truths[sc]
            idx = {n: k for k, n in enumerate(ref.names)}
            prefix = SCENES[sc][3]
            sel = [k for k, n in enumerate(names) if owner[n] == sc]
            Rt = np.stack([ref.R[idx[names[k][len(prefix):]]] for k in sel])
            e = rotation_errors_deg(R[sel], Rt)
            per[sc] = {"n_images": len(sel), "median_deg": float(np.median(e)), "mean_deg": float(np.mean(e))}
        rows[path.stem] = per
    return rows


def run_set(name: str, work: Path, data: Path) -> dict[str, Any]:
    scenes = SETS[name]
    folder, out = work / name / "images", work / name / "out"
    owner = build_folder(folder, scenes, data)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, str(REPO / "run.py"), str(folder), "--out", str(out), "--no-reference", "-q"],
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        return {"set": name, "error": (r.stderr.strip().splitlines() or ["?"])[-1]}
    truths = {sc: read_reference(data / SCENES[sc][2]) for sc in scenes}
    metrics = json.loads((out / "metrics.json").read_text())
    parts = [("OUT", out, metrics)] + [(c["folder"], out / c["folder"], json.loads(
        (out / c["folder"] / "metrics.json").read_text())) for c in metrics.get("components", [])]
    comps = []
    for label, d, m in parts:
        comps.append({"folder": label, "n_images": m["input"]["n_cameras_graph"],
                      "scenes": sorted({owner[n] for n in json.loads((d / "viewgraph.json").read_text())["names"]}),
                      "focal_px": [round(f["min_px"], 1) for f in m["intrinsics"].get("focal", [])]
                      + [round(f["max_px"], 1) for f in m["intrinsics"].get("focal", [])],
                      "methods": score(d, owner, truths)})
    left = [n for n, why in metrics["input"]["left_out_why"].items() if "solved as component" not in why]
    return {"set": name, "n_images": len(owner), "wall_s": wall, "components": comps, "not_solved": left,
            "pairs": metrics.get("pairs", {})}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    p.add_argument("--work", type=Path, default=None, help="where the folders and runs go (default: a temporary one)")
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--out", type=Path, default=RESULTS / "components.json")
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = a.work or Path(tmp)
        for name in a.sets:
            row = run_set(name, work, a.data)
            rows.append(row)
            if "error" in row:
                print(f"{name}: run failed: {row['error']}", flush=True)
                continue
            print(f"{name}: {row['n_images']} images, {row['wall_s']:.0f} s, not solved: {len(row['not_solved'])}")
            for c in row["components"]:
                print(f"  {c['folder']:12s} {c['n_images']:3d} images, scenes {'+'.join(c['scenes'])}, focal "
                      f"{sorted(set(c['focal_px']))} px")
                for method, per in c["methods"].items():
                    print(f"    {method:20s} " + "  ".join(f"{sc} {v['median_deg']:.4f}° ({v['n_images']})"
                                                           for sc, v in per.items()), flush=True)
    write_json(a.out, {"argv": sys.argv[1:], "load_average": os.getloadavg(), "rows": rows})
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
