"""Retrieval's k on a small collection that overlaps densely: the saturated images' next-ranked pairs (issue 16).

A rendered low-texture turntable ring of 48 views (Middlebury's templeRing and dinoRing
have 47 and 48) is above the exhaustive limit of 40 images, so ``matching.pairs: auto``
takes retrieval with k = 8; each view overlaps about 15 others. Per seed, three runs of
``python -m pipeline.run`` with the true K and cameras (no pycolmap reference):

- ``saturated``: the default (the loop-closure round also matches the further ranked
  images, not looking more than 60° apart, of each image whose lower-ranked candidates all
  verified, where ≥ 95% of the matched pairs verified: ``loop_closure.saturated_share``);
- ``k only``: the same with ``loop_closure.saturated_share: 2`` (never);
- ``exhaustive`` (with ``--exhaustive``): every pair.

Reported per run: the truly overlapping pairs found (the renderer's), the share of all
pairs matched, the view graph's edges and every method's median error against the truth.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/retrieval_saturated.py [--seeds 0 1 2] [--exhaustive] [--work DIR]
        [--labels saturated]

Writes ``benchmarks/results/retrieval_saturated.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before pycolmap: its OpenMP threads busy-wait otherwise

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.frontend.matching_stage import load_matches  # noqa: E402
from pipeline.frontend.retrieval import pair_recall  # noqa: E402
from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex, write_scene  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "retrieval_saturated.json"
CONFIGS = {"saturated": "", "k only": "loop_closure:\n  saturated_share: 2.0\n",
           "exhaustive": "matching:\n  pairs: exhaustive\n"}


def scene(work: Path, seed: int, views: int) -> Path:
    d = work / f"ring{views}_s{seed}"
    if not (d / "scene.json").is_file():
        write_scene(render_lowtex(LowTexConfig(n_views=views, contrast=8.0), seed=seed), d)
    return d


def one(work: Path, sc: Path, label: str) -> dict:
    out = work / f"{sc.name}_{label.replace(' ', '_')}"
    cfg = out.parent / f"{out.name}.yaml"
    cfg.write_text("run:\n  plots: false\n" + CONFIGS[label])
    cmd = [sys.executable, "-m", "pipeline.run", str(sc), "--K", str(sc / "K.txt"), "--gt", str(sc / "cameras.txt"),
           "--config", str(cfg), "--out", str(out), "--no-reference", "-q"]
    t0 = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as f:
        subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, check=True)
    m = json.loads((out / "metrics.json").read_text())
    truth = np.asarray(json.loads((sc / "scene.json").read_text())["true_pairs"], np.int64).reshape(-1, 2)
    matches = load_matches(out / "work")
    rec = pair_recall(matches.pairs, truth, int(m["pairs"]["n_images"]))
    meds = {k: v.get("references", {}).get("truth", {}).get("median_deg") for k, v in m["methods"].items()}
    lc = m["pairs"].get("loop_closure") or {}
    return {"label": label, "recall": rec["recall"], "fraction_matched": rec["fraction_matched"],
            "n_pairs": rec["n_selected"], "n_saturated": lc.get("n_saturated"), "n_extended": lc.get("n_extended"),
            "n_transitive": lc.get("n_transitive"),
            "n_edges": next((v["n_edges"] for v in m["methods"].values() if "n_edges" in v), None),
            "median_deg": meds, "wall_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--views", type=int, default=48)
    p.add_argument("--exhaustive", action="store_true", help="also match every pair")
    p.add_argument("--labels", nargs="+", choices=list(CONFIGS), default=None,
                   help="run only these (their rows replace those of --json; the others are kept)")
    p.add_argument("--work", type=Path, default=Path("/tmp/retrieval_saturated"))
    p.add_argument("--json", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    labels = a.labels or ["saturated", "k only"] + (["exhaustive"] if a.exhaustive else [])
    rows = []
    if a.labels and a.json.is_file():  # the rows of the other runs stand
        rows = [r for r in json.loads(a.json.read_text())["rows"] if r["label"] not in labels or r["seed"] not in a.seeds]
    for seed in a.seeds:
        sc = scene(a.work, seed, a.views)
        for label in labels:
            r = {"seed": seed, **one(a.work, sc, label)}
            rows.append(r)
            rows.sort(key=lambda r: (r["seed"], list(CONFIGS).index(r["label"])))
            md = r["median_deg"]
            print(f"seed {seed} {label:10s}: recall {r['recall']:.3f} at {r['fraction_matched']:.3f} of all pairs, "
                  f"{r['n_edges']} edges, saturated {r['n_saturated']} (+{r['n_extended']}), transitive "
                  f"+{r['n_transitive']}; "
                  + ", ".join(f"{k} {v:.4f}°" for k, v in md.items() if v is not None), flush=True)
            write_json(a.json, {"rows": rows, "command": "python benchmarks/retrieval_saturated.py "
                                + " ".join(sys.argv[1:] if argv is None else argv)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
