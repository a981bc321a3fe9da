"""How much of the real scenes' figures is the luck of RANSAC: the whole run again under other seeds.

Every pair's RANSAC (PoseLib's LO-RANSAC, ``two_view.seed``) draws its samples from one seed. On a scene whose
pairs are strong, another seed finds the same inliers to a few and the figures move in their last digit; on one
whose view graph rests on a few weak pairs (templeSparseRing: 23 pairs, four blocks joined by bridges) a pair's
20-odd inliers can come out otherwise, and a weak-H decision or a bridge pair's estimate with them. This runs
``run.py`` on fountain-P11, castle-P30 and templeSparseRing (true K, no peers: ``--no-reference``) once per seed,
with every other setting the default, and prints each method's median and mean error against the truth per seed,
their spread, and on how many seeds each comparison of issue 15's item 2 holds (IRLS-H ≤ IRLS-ℓ½; IRLS-ℓ½ ≤
colmap-ra on median and on mean).

    python benchmarks/ransac_seeds.py [--scenes temple fountain castle] [--seeds 0 1 2 3 4 5 6 7] [--keep DIR]

→ ``benchmarks/results/ransac_seeds.json``. Seed 0 is the default, whose run the README's rows come from.
A run folder under ``--keep`` whose config is the same is read, not run again, whatever code made it: empty the
folder after a change of the code.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from statistics import median

import yaml
from refine import SCENES  # the scenes' images, truth and K (benchmarks/, the script's folder, is on sys.path)

from pipeline.core.atomic import write_json

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "ransac_seeds.json"
METHODS = ("irls-l0.5", "irls-h-l0.5", "sdp-cso3", "colmap-ra", "irls-h-l0.5+refine")


def run_seed(scene: str, seed: int, data: Path, root: Path) -> dict:
    """``run.py`` on ``scene`` with ``two_view.seed`` = ``seed`` (or its kept run): per method median / mean, and the
    view graph's kept pairs and flagged cameras."""
    out = root / f"{scene}-{seed}"
    cfg = yaml.safe_load((REPO / "configs" / "default.yaml").read_text())
    cfg["two_view"] = {**(cfg.get("two_view") or {}), "seed": seed}
    cfg.setdefault("run", {})["plots"] = False
    conf, done = root / f"{scene}-{seed}.yaml", out / "metrics.json"
    text = yaml.safe_dump(cfg)
    if not (done.is_file() and conf.is_file() and conf.read_text() == text):  # else: the kept run of this config
        shutil.rmtree(out, ignore_errors=True)
        conf.write_text(text)
        images, truth, K = (data / p for p in SCENES[scene])
        cmd = [sys.executable, str(REPO / "run.py"), str(images), "--K", str(K), "--gt", str(truth), "--no-reference",
               "--config", str(conf), "--out", str(out), "-q"]
        with open(root / f"{scene}-{seed}.log", "w") as log:
            if subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode != 0:
                raise RuntimeError(f"{' '.join(cmd)} failed: see {log.name}")
    metrics = json.loads(done.read_text())
    graph = json.loads((out / "viewgraph.json").read_text())
    row = {"scene": scene, "seed": seed,
           "pairs_kept": sum(p["status"] == "kept" for p in graph["pairs"]),
           "flagged": sum(c.get("status") != "checked" for c in metrics["evidence"]["cameras"].values())}
    for m in METHODS:
        got = metrics["methods"].get(m, {})
        row[m] = {"median_deg": got.get("median_deg"), "mean_deg": got.get("mean_deg")}
    return row


def summary(rows: list[dict]) -> dict:
    """Per method the smallest, median and largest of the seeds' medians; and on how many seeds each comparison
    holds."""
    out: dict = {"n_seeds": len(rows)}
    for m in METHODS:
        med = [r[m]["median_deg"] for r in rows if r[m]["median_deg"] is not None]
        if med:
            out[m] = {"median_deg": {"min": min(med), "median": median(med), "max": max(med)}}
    both = [r for r in rows if r["irls-l0.5"]["median_deg"] is not None and r["irls-h-l0.5"]["median_deg"] is not None]
    out["irls_h_le_irls"] = sum(r["irls-h-l0.5"]["median_deg"] <= r["irls-l0.5"]["median_deg"] for r in both)

    def le(r: dict, key: str) -> bool:
        return r["irls-l0.5"][key] <= r["colmap-ra"][key]

    out["irls_le_colmap_ra_median"] = sum(le(r, "median_deg") for r in rows)
    out["irls_le_colmap_ra_mean"] = sum(le(r, "mean_deg") for r in rows)
    out["irls_le_colmap_ra_both"] = sum(le(r, "median_deg") and le(r, "mean_deg") for r in rows)
    return out


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.4f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["temple", "fountain", "castle"], choices=list(SCENES))
    ap.add_argument("--seeds", nargs="+", type=int, default=list(range(8)))
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="the shared data folder")
    ap.add_argument("--keep", type=Path, default=None, help="keep (and reuse) the run folders here")
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    root = a.keep or Path(tempfile.mkdtemp(prefix="bench_seeds_"))
    root.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    scenes: dict = {}
    try:
        for scene in a.scenes:
            if not (a.data / SCENES[scene][0]).is_dir():
                print(f"skipping {scene}: {a.data / SCENES[scene][0]} not found")
                continue
            head = "  ".join(f"{m:>19s}" for m in METHODS)
            print(f"{scene}: seed  pairs  flagged  {head}   (median / mean, deg)")
            mine = []
            for seed in a.seeds:
                r = run_seed(scene, seed, a.data, root)
                mine.append(r)
                print(f"  {seed:10d}  {r['pairs_kept']:5d}  {r['flagged']:7d}  " + "  ".join(
                    f"{_fmt(r[m]['median_deg']):>9s}/{_fmt(r[m]['mean_deg']):<9s}" for m in METHODS), flush=True)
            scenes[scene] = summary(mine)
            s = scenes[scene]
            print(f"  IRLS-H <= IRLS-l0.5 (median) on {s['irls_h_le_irls']} of {len(mine)} seeds; IRLS-l0.5 <= "
                  f"colmap-ra on median {s['irls_le_colmap_ra_median']}, mean {s['irls_le_colmap_ra_mean']}, both "
                  f"{s['irls_le_colmap_ra_both']}")
            rows += mine
    finally:
        if a.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    write_json(a.json, {"rows": rows, "summary": scenes,
                        "command": "python benchmarks/ransac_seeds.py " + " ".join(argv or sys.argv[1:]),
                        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}})
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
