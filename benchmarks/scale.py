"""Issue 16, acceptance 1-3: retrieval pair selection and growth of the whole path on large rendered scenes.

For each rendered scene (``pipeline.synthetic.large``: street, ring, grid at N views) the whole
pipeline (``python -m pipeline.run``) runs with ``matching.pairs: auto`` (retrieval above 40
images) in a child process, and this script reads its ``metrics.json``:

- **retrieval** (acceptance 1): recall of the renderer's truly overlapping pairs among the
  selected pairs, and the fraction of all N(N-1)/2 pairs matched; the median rotation error
  (truth, l2 alignment, the first default method: IRLS-l0.5; every method is in the row) against an exhaustive run on the
  same scene, where affordable (``--exhaustive-sizes``, default 100 only: N = 300 exhaustive
  means 44,850 pairs);
- **growth** (acceptance 2): our path (features → matching → two-view → BA → view graph →
  averaging, ``metrics.json: our_path_s``; the runs set ``refine: false``) per image at each N, the ratio at the largest N
  against the smallest, and the peak memory of the run (``ru_maxrss`` of the child process
  and its descendants, from ``os.wait4``);
- **against incremental** (acceptance 3): at ``--reference-sizes`` (default 200) the same run
  also runs the pycolmap incremental reference (``reference.use_our_matches``: pycolmap verifies
  and maps our keypoints and retrieval matches); its time is the features and matching it
  reuses plus its own stage, and its error against the truth is pycolmap's median error, on the images it
  registered; ours is given on all N and on those same images (``error_ratio_same_images``). With
  ``--pycolmap-own-sizes`` pycolmap's own path (its SIFT, exhaustive matching, mapping: what
  ``run.py`` runs by default as the reference) is timed as well, on a copy of the run;
- **the pipeline's product** (acceptance 1 again): at ``--refine-sizes`` the refinement that ``run.py`` runs by
  default (``python -m pipeline.refine --out RUN``: pycolmap's global positioning and bundle adjustment started
  from the recommended averaging) is run on the finished retrieval run and, where there is one, on the exhaustive
  run; their median errors and ratio are recorded (``refined``).

Scenes, feature caches and runs live in ``--work`` (outside git; re-runs reuse them: the
exhaustive run starts from the retrieval run's features). Usage::

    OMP_WAIT_POLICY=PASSIVE python benchmarks/scale.py [--layouts street ring grid] [--sizes 100 200 300]
        [--work /work/scratch/scale] [--exhaustive-sizes 100] [--reference-sizes 200] [--refine-sizes 300]
        [--json PATH]

Prints a table and writes ``benchmarks/results/scale.json`` (merged with the rows already there).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.frontend.matching_stage import load_matches  # noqa: E402
from pipeline.frontend.retrieval import pair_recall  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import rotation_errors_deg  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
from pipeline.synthetic import large  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "scale.json"
FEATURE_FILES = ("features", "features.json", "features.record.json")


def scene_dir(work: Path, layout: str, n: int, seed: int = 0) -> Path:
    """The rendered scene (rendered now unless already there, with the renderer's ``seed``; a work folder holds
    the scenes of one seed)."""
    d = work / "scenes" / f"{layout}-{n}"
    if not (d / "scene.json").is_file():
        t0 = time.perf_counter()
        large.main(d, layout, n, seed)
        print(f"rendered {d} in {time.perf_counter() - t0:.0f} s", flush=True)
    rendered = json.loads((d / "scene.json").read_text()).get("seed", 0)
    if rendered != seed:
        raise SystemExit(f"error: {d} was rendered with seed {rendered}, not {seed}; give each seed its own --work")
    return d


def run_pipeline(scene: Path, out: Path, pairs: str, reference: bool, log: Path,
                 our_matches: bool = True) -> tuple[dict, float, float]:
    """``python -m pipeline.run`` on ``scene`` in a child process: its metrics, wall time and peak RSS (MB).

    The child's CPU time (user + system, its threads and reaped descendants included) goes into
    ``metrics["cpu_s"]``: on a shared machine it is the figure that does not depend on the load.
    """
    cfg = out.parent / f"{out.name}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    # the path to the averaged rotations (issue 16): pycolmap's refinement, on by default, is left out
    cfg.write_text(f"run:\n  plots: false\n  refine: false\n  reference: {str(reference).lower()}\n"
                   f"matching:\n  pairs: {pairs}\n"
                   f"reference:\n  use_our_matches: {str(our_matches).lower()}\n")
    cmd = [sys.executable, "-m", "pipeline.run", str(scene), "--out", str(out), "--config", str(cfg),
           "--gt", str(scene / "cameras.txt"), "--K", str(scene / "K.txt"), "-q"]
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed; see {log}")
    metrics = json.loads((out / "metrics.json").read_text())
    metrics["cpu_s"] = usage.ru_utime + usage.ru_stime
    return metrics, wall, usage.ru_maxrss / 1024.0


def first_method(metrics: dict) -> tuple[str, float]:
    label = next(iter(metrics["methods"]))
    return label, float(metrics["methods"][label].get("median_deg", float("nan")))


def pycolmap_own(work: Path, layout: str, n: int, ours: dict) -> dict:
    """pycolmap's own path (its SIFT, exhaustive matching, incremental mapping) on the scene of a finished
    retrieval run: the run is copied (our stages are reused) and only the reference runs."""
    runs = work / "runs"
    src, out = runs / f"{layout}-{n}", runs / f"{layout}-{n}-pycolmap-own"
    if not out.exists():
        shutil.copytree(src, out, ignore=shutil.ignore_patterns("reference", "metrics.json"))
    m, wall, rss = run_pipeline(work / "scenes" / f"{layout}-{n}", out, "auto", True,
                                runs / f"{layout}-{n}-pycolmap-own.log", our_matches=False)
    pyc = m.get("pycolmap", {})
    t = m["stages"].get("reference")
    return {"median_deg": pyc.get("median_deg"), "n_registered": pyc.get("n_registered"), "time_s": t,
            "pycolmap_times": pyc.get("time_s"), "peak_rss_mb": rss,
            "time_ratio_ours": ours["our_path_s"] / t if t else None,
            "error_ratio_ours": ours["median_deg"] / pyc["median_deg"] if pyc.get("median_deg") else None}


def on_pycolmap_images(out: Path, scene: Path, metrics: dict, label: str) -> dict:
    """Our ``label`` rotations on the images pycolmap registered (aligned on those alone): the like-for-like error
    when pycolmap leaves part of the scene out, and its ratio to pycolmap's median there."""
    unreg = set((metrics.get("peers", {}).get("pycolmap") or {}).get("unregistered", {}))
    pyc = metrics.get("pycolmap", {}).get("median_deg")
    est = read_reference(out / "rotations" / f"{label}.txt")
    truth = read_reference(scene / "cameras.txt")
    R, mask = match_reference(est.names, truth.names, truth.R)
    same = mask & np.array([nm not in unreg for nm in est.names])
    if not same.any() or not pyc:
        return {}
    med = float(np.nanmedian(rotation_errors_deg(est.R, R, same)))
    return {"ours_on_its_images_deg": med, "n_its_images": int(same.sum()), "error_ratio_same_images": med / pyc}


def measure(work: Path, layout: str, n: int, exhaustive: bool, reference: bool, fresh: bool = False,
            seed: int = 0) -> dict:
    scene = scene_dir(work, layout, n, seed)
    runs = work / "runs"
    out = runs / f"{layout}-{n}"
    if fresh:  # time every stage again (the scene stays)
        for d in (out, runs / f"{layout}-{n}-exhaustive"):
            shutil.rmtree(d, ignore_errors=True)
    m, wall, rss = run_pipeline(scene, out, "auto", reference, runs / f"{layout}-{n}.log")
    truth = large.true_pairs(large.load_overlap(scene), float(json.loads((scene / "scene.json").read_text())
                                                                  ["config"]["overlap_threshold"]))
    sel = load_matches(out / "work").pairs
    label, err = first_method(m)
    row = {"layout": layout, "n": n, "seed": seed, "pairs": m.get("pairs", {}), "recall": pair_recall(sel, truth, n),
           "method": label, "median_deg": err, "methods_median_deg": {k: v.get("median_deg") for k, v in
                                                                      m["methods"].items()},
           "our_path_s": m["our_path_s"], "per_image_s": m["our_path_s"] / n, "stages_s": m["stages"],
           "stages_reused": m["stages_reused"], "wall_s": wall, "cpu_s": m["cpu_s"],
           "cpu_per_image_s": m["cpu_s"] / n, "load_avg": os.getloadavg(), "peak_rss_mb": rss,
           "n_cameras_graph": m["input"]["n_cameras_graph"], "n_edges": m["input"]["n_edges"]}
    if reference:
        pyc = m.get("pycolmap", {})
        st = m["stages"]
        t_pyc = st.get("features", 0.0) + st.get("matching", 0.0) + st.get("reference", 0.0)
        row["pycolmap"] = {"median_deg": pyc.get("median_deg"), "n_registered": pyc.get("n_registered"),
                           "stage_s": st.get("reference"), "time_s": t_pyc,
                           "time_ratio_ours": m["our_path_s"] / t_pyc if t_pyc else None,
                           "error_ratio_ours": err / pyc["median_deg"] if pyc.get("median_deg") else None}
        row["pycolmap"] |= on_pycolmap_images(out, scene, m, label)
    if exhaustive:
        ex = runs / f"{layout}-{n}-exhaustive"
        (ex / "work").mkdir(parents=True, exist_ok=True)
        for f in FEATURE_FILES:  # the retrieval run's features: only matching onwards differs
            src, dst = out / "work" / f, ex / "work" / f
            if src.exists() and not dst.exists():
                (shutil.copytree if src.is_dir() else shutil.copy2)(src, dst)
        me, wall_e, rss_e = run_pipeline(scene, ex, "exhaustive", False, runs / f"{layout}-{n}-exhaustive.log")
        _, err_e = first_method(me)
        meds = {k: v.get("median_deg") for k, v in me["methods"].items()}
        row["exhaustive"] = {"median_deg": err_e, "methods_median_deg": meds,
                             "error_ratio_methods": {k: row["methods_median_deg"][k] / v for k, v in meds.items()
                                                     if v and row["methods_median_deg"].get(k) is not None},
                             "our_path_s": me["our_path_s"], "wall_s": wall_e, "cpu_s": me["cpu_s"],
                             "peak_rss_mb": rss_e, "n_pairs": me.get("pairs", {}).get("n_pairs"),
                             "error_ratio_retrieval": err / err_e if err_e else None,
                             "features_reused": bool(me["stages_reused"].get("features"))}
    return row


def refined(work: Path, layout: str, n: int) -> dict:
    """The refinement (``run.py``'s default last step) of the finished retrieval and exhaustive runs of a scene:
    its median error against the truth, each, and their ratio. Runs ``python -m pipeline.refine`` in a child
    process (a re-run reuses a finished refinement)."""
    scene, runs = work / "scenes" / f"{layout}-{n}", work / "runs"
    truth = read_reference(scene / "cameras.txt")
    out: dict = {}
    for kind, run in (("retrieval", runs / f"{layout}-{n}"), ("exhaustive", runs / f"{layout}-{n}-exhaustive")):
        if not (run / "metrics.json").is_file():
            continue
        t0 = time.perf_counter()
        with open(runs / f"{run.name}-refine.log", "w") as f:
            subprocess.run([sys.executable, "-m", "pipeline.refine", "--out", str(run), "-q"], stdout=f,
                           stderr=subprocess.STDOUT, check=True)
        wall = time.perf_counter() - t0
        summary = json.loads((run / "refine.record.json").read_text())["summary"]
        label = summary["label"]
        est = read_reference(run / "rotations" / f"{label}.txt")
        R, mask = match_reference(est.names, truth.names, truth.R)
        out[kind] = {"label": label, "status": summary["status"],
                     "median_deg": float(np.nanmedian(rotation_errors_deg(est.R, R, mask))), "wall_s": wall,
                     "times_s": json.loads((run / "rotations" / f"{label}.json").read_text())["times"]}
    if len(out) == 2:
        out["error_ratio_retrieval"] = out["retrieval"]["median_deg"] / out["exhaustive"]["median_deg"]
    return out


def summarize(rows: list[dict]) -> dict:
    """Acceptance figures from the rows: recall/fraction, error ratios, growth per layout."""
    out: dict = {"growth": {}}
    for lay in sorted({r["layout"] for r in rows}):
        rs = sorted((r for r in rows if r["layout"] == lay), key=lambda r: r["n"])
        if len(rs) >= 2:
            cpu = [r.get("cpu_per_image_s") for r in (rs[0], rs[-1])]
            out["growth"][lay] = {"n": [rs[0]["n"], rs[-1]["n"]],
                                  "per_image_ratio": rs[-1]["per_image_s"] / rs[0]["per_image_s"],
                                  "cpu_per_image_ratio": cpu[1] / cpu[0] if None not in cpu else None,
                                  "peak_rss_mb_max": max((r["peak_rss_mb"] for r in rs  # null: not measured
                                                          if r.get("peak_rss_mb") is not None), default=None)}
    return out


def print_table(rows: list[dict]) -> None:
    print(f"{'scene':12s} {'K':>3s} {'pairs':>6s} {'frac':>6s} {'recall':>6s} {'med°':>7s} {'exh med°':>8s} "
          f"{'ratio':>5s} {'path s':>7s} {'s/img':>6s} {'MB':>6s} {'pyc°':>7s} {'pyc s':>7s} {'t ratio':>7s}")
    for r in sorted(rows, key=lambda r: (r["layout"], r["n"])):
        ex, pc = r.get("exhaustive", {}), r.get("pycolmap", {})

        def f(v: object, fmt: str) -> str:
            return format(v, fmt) if isinstance(v, (int, float)) and v is not None else "-"

        print(f"{r['layout'] + '-' + str(r['n']):12s} {f(r['pairs'].get('k'), '3d'):>3s} "
              f"{r['recall']['n_selected']:6d} {r['recall']['fraction_matched']:6.3f} {r['recall']['recall']:6.3f} "
              f"{r['median_deg']:7.3f} {f(ex.get('median_deg'), '8.3f'):>8s} "
              f"{f(ex.get('error_ratio_retrieval'), '5.2f'):>5s} {r['our_path_s']:7.1f} {r['per_image_s']:6.2f} "
              f"{f(r.get('peak_rss_mb'), '6.0f'):>6s} {f(pc.get('median_deg'), '7.3f'):>7s} {f(pc.get('time_s'), '7.1f'):>7s} "
              f"{f(pc.get('time_ratio_ours'), '7.2f'):>7s}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--layouts", nargs="+", default=list(large.LAYOUTS), choices=large.LAYOUTS)
    p.add_argument("--sizes", nargs="+", type=int, default=[100, 200, 300])
    p.add_argument("--work", type=Path, default=Path("/work/scratch/scale"))
    p.add_argument("--exhaustive-sizes", nargs="*", type=int, default=[100])
    p.add_argument("--reference-sizes", nargs="*", type=int, default=[200])
    p.add_argument("--pycolmap-own-sizes", nargs="*", type=int, default=[],
                   help="also time pycolmap's own path (its SIFT + exhaustive matching + mapping) at these N")
    p.add_argument("--refine-sizes", nargs="*", type=int, default=[],
                   help="also refine the finished runs at these N (the pipeline's product) and compare them")
    p.add_argument("--fresh", action="store_true", help="remove the runs of these scenes first (times every stage)")
    p.add_argument("--only-pycolmap-own", action="store_true", help="keep the rows already in --json; add pycolmap's own path")
    p.add_argument("--rescore", action="store_true", help="run nothing: add the same-images comparison with "
                   "pycolmap to the rows of --json from their finished runs in --work")
    p.add_argument("--seed", type=int, default=0, help="the renderer's seed (one seed per --work folder)")
    p.add_argument("--json", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    old = json.loads(a.json.read_text()).get("rows", []) if a.json.is_file() else []
    rows = {(r["layout"], r["n"]): r for r in old}
    if a.rescore:
        for (lay, n), r in rows.items():
            out = a.work / "runs" / f"{lay}-{n}"
            if "pycolmap" in r and (out / "metrics.json").is_file():
                r["pycolmap"] |= on_pycolmap_images(out, a.work / "scenes" / f"{lay}-{n}",
                                                    json.loads((out / "metrics.json").read_text()), r["method"])
                print(f"{lay}-{n}: ours {r['method']} on pycolmap's {r['pycolmap'].get('n_its_images')} images "
                      f"{r['pycolmap'].get('ours_on_its_images_deg'):.4f}° vs its {r['pycolmap']['median_deg']:.4f}°"
                      f" ({r['pycolmap'].get('error_ratio_same_images'):.2f}×); all {n}: {r['median_deg']:.4f}°")
        write_json(a.json, {**json.loads(a.json.read_text()), "rows": list(rows.values())})
        return 0
    for lay in a.layouts:
        for n in a.sizes:
            print(f"--- {lay}-{n}", flush=True)
            prev = rows.get((lay, n))
            if not (prev and a.only_pycolmap_own):
                rows[(lay, n)] = measure(a.work, lay, n, n in a.exhaustive_sizes, n in a.reference_sizes, a.fresh,
                                         a.seed)
            if n in a.pycolmap_own_sizes:
                rows[(lay, n)]["pycolmap_own"] = pycolmap_own(a.work, lay, n, rows[(lay, n)])
            if n in a.refine_sizes:
                rows[(lay, n)]["refined"] = ref = refined(a.work, lay, n)
                print(f"refined {lay}-{n}: " + ", ".join(f"{k} {v['label']} {v['median_deg']:.4f}°"
                                                         for k, v in ref.items() if isinstance(v, dict))
                      + (f", ratio {ref['error_ratio_retrieval']:.2f}" if "error_ratio_retrieval" in ref else ""),
                      flush=True)
            res = {"rows": list(rows.values()), "summary": summarize(list(rows.values())),
                   "command": "python benchmarks/scale.py " + " ".join(sys.argv[1:] if argv is None else argv),
                   "machine": {"cpus": os.cpu_count(), "load_avg": os.getloadavg()}}
            a.json.parent.mkdir(parents=True, exist_ok=True)
            write_json(a.json, res)  # strict JSON: a figure not measured is null
            print_table([rows[(lay, n)]])
    print_table(list(rows.values()))
    print(json.dumps(summarize(list(rows.values())), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
