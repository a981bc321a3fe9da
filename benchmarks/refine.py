"""Our refined rotations against pycolmap's global (GLOMAP) and incremental SfM, with the true K (issue 14).

    python benchmarks/refine.py [--only fountain,castle,temple] [--data DIR] [--keep DIR] [--repeat K]
    python benchmarks/refine.py --only castle-0-18,castle-11-29,castle-even,castle-0-9,castle-10-19,castle-20-29

The ``castle-*`` subsets are smaller scenes cut from castle-P30 (the images named, linked into a folder of their
own with ``K.txt``): courtyards of 10–19 images with the repeated façades and outlier pairs of the whole, as the
held-out Strecha scenes (castle-P19, entry-P10) are; each is a scene of its own for every method and peer.

One run per scene, in a fresh folder, with the true K given to everyone (Strecha
``images/K.txt``, Middlebury ``templeSR_par.txt``), kept constant in every bundle
adjustment; the truth (Strecha ``gt_dense_cameras/``, ``templeSR_par.txt``) is read by the
evaluation only. In one process, one after the other:

1. **our path**: ``run.main`` without the peers and without plots: features → matching →
   two-view → two-view BA → averaging (the default methods) → refine. The path to the
   refined model is the stages' wall times with the averaging of the refinement's start
   only (the other methods are rows of the report, not steps to the model); the path with
   every default method (``metrics.json``'s ``our_path_s``) is reported beside it. CPU:
   this process's and its reaped workers', without the other methods' averaging;
2. **GLOMAP**: the GLOMAP peer stage (``pipeline.reference.global_mapping``) exactly as
   ``run.py`` calls it; its time is pycolmap's extraction + matching + ``global_mapping``;
   With ``--repeat K`` both paths first run once untimed (a warm-up: in one process the
   first path pays alone for what every later one reuses, such as pycolmap's first
   call), then K times in fresh folders; the time ratio is the median of the K;
3. ``run.main`` again with the peers: our stages and GLOMAP are reused, the incremental
   reference maps the same database; ``metrics.json`` then holds every row.

Reported per scene: the median error against the truth of our refined rotations
(``<start>+refine``), GLOMAP and the incremental reference, each pair scored on the
images both register (aligned on them, ℓ2), the registered counts, the predicted
uncertainty beside the error, and the time ratio ours / GLOMAP (wall; CPU beside it).

Results: ``benchmarks/results/refine.json`` (atomic) and a table. Data: ``../shared/data``
(Strecha et al. CVPR 2008 via openMVG's SfM_quality_evaluation; Seitz et al. CVPR 2006).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MPLBACKEND", "Agg")

import argparse  # noqa: E402
import atexit  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core.names import match_names  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "refine.json"
FRONT_END = ("features", "matching", "two_view", "two_view_ba", "viewgraph")
SCENES = {  # name: (images, truth, K), relative to the data folder
    "fountain": ("strecha/fountain-P11/images", "strecha/fountain-P11/gt_dense_cameras",
                 "strecha/fountain-P11/images/K.txt"),
    "castle": ("strecha/castle-P30/images", "strecha/castle-P30/gt_dense_cameras", "strecha/castle-P30/images/K.txt"),
    "temple": ("middlebury-templeSparseRing", "middlebury-templeSparseRing/templeSR_par.txt",
               "middlebury-templeSparseRing/templeSR_par.txt"),
}
#: Scenes cut from castle-P30: name → the image numbers (0000.jpg …) it keeps.
SUBSETS = {"castle-0-18": range(0, 19), "castle-11-29": range(11, 30), "castle-even": range(0, 30, 2),
           "castle-0-9": range(0, 10), "castle-10-19": range(10, 20), "castle-20-29": range(20, 30)}


def scene_paths(name: str, data: Path, root: Path) -> tuple[Path, Path, Path]:
    """(images, truth, K) of a scene; a subset's images are links in ``root/images-<name>`` beside a copy of K."""
    if name not in SUBSETS:
        return tuple(data / p for p in SCENES[name])
    images, gt, K = (data / p for p in SCENES["castle"])
    folder = root / f"images-{name}"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for k in SUBSETS[name]:
        (folder / f"{k:04d}.jpg").symlink_to(images / f"{k:04d}.jpg")
    shutil.copyfile(K, folder / "K.txt")
    return folder, gt, folder / "K.txt"


def cpu_s() -> float:
    """CPU seconds of this process and of its reaped children (the process pools' workers)."""
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def scored_on_common(a, b, truth) -> dict:
    """Median/mean error against ``truth`` of references ``a`` and ``b`` on the images both register."""
    from pipeline.evaluation.compare import summarize_against
    from pipeline.reference import Reference

    common = [n for n in a.names if n in set(b.names)]
    out = {"n_common": len(common)}
    for ref in (a, b):
        idx = match_names(common, list(ref.names))
        sub = Reference(common, ref.R[idx], label=ref.label)
        s, _ = summarize_against(common, sub.R, truth, "l2")
        out[ref.label] = {k: s.get(k) for k in ("n_evaluated", "median_deg", "mean_deg", "max_deg")}
    return out


def timed_paths(name: str, paths: tuple[Path, Path, Path], out: Path, config: Path, yaml_data: dict
                ) -> tuple[dict, dict]:
    """Our path (fresh, without the peers) then GLOMAP's, in ``out``: their times and CPU times."""
    from pipeline import run
    from pipeline.core.config import stage_config
    from pipeline.frontend.feature_stage import load_features
    from pipeline.reference import ReferenceConfig, load_reference
    from pipeline.reference import global_mapping as glomap

    images, gt, K = paths
    shutil.rmtree(out, ignore_errors=True)
    load0 = os.getloadavg()[0]
    c0, t0 = cpu_s(), time.perf_counter()
    m = _json(run.main(images, out, config=config, gt=gt, K=K, reference=False, quiet=True))
    cpu = cpu_s() - c0
    refine = next(v for v in m["methods"].values() if v.get("method") == "refine")
    starts = {k: _json(out / "rotations" / f"{k}.record.json")["time_s"] for k, v in m["methods"].items()
              if v.get("method") != "refine"}  # each averaging method's stage time
    st = m["stages"]
    path = sum(st[k] for k in FRONT_END) + starts[refine["start"]] + st["refine"]
    ours = {"path_s": path, "path_all_methods_s": m["our_path_s"], "cpu_s": cpu,
            "cpu_path_s": cpu - (sum(starts.values()) - starts[refine["start"]]) - st.get("report", 0.0),
            "averaging_s": starts, "run_wall_s": time.perf_counter() - t0, "stages_s": st, "load_avg": load0}
    print(f"  {name}: our path {path:.1f} s, with every averaging method {m['our_path_s']:.1f} s ({cpu:.1f} s CPU)",
          flush=True)

    rc = stage_config(ReferenceConfig, yaml_data, "reference")
    gc = glomap.GlobalReferenceConfig.sharing_database(rc, yaml_data.get("global_reference"))
    names = list(load_features(out / "work", descriptors=False).names)
    load1 = os.getloadavg()[0]
    c0 = cpu_s()
    glomap.main(images, out / "reference-global", K=K, config=gc, work=out / "work", names=names, progress=False,
                database_dir=out / "reference")
    g, g_cpu = load_reference(out / "reference-global").info, cpu_s() - c0
    print(f"  {name}: GLOMAP {g['time_s']:.1f} s ({g_cpu:.1f} s CPU)", flush=True)
    return ours, {"time_s": g["time_s"], "times": g["times"], "cpu_s": g_cpu, "load_avg": load1}


def run_scene(name: str, data: Path, root: Path, config: Path, yaml_data: dict, repeat: int = 1) -> dict:
    from pipeline import run
    from pipeline.io.rotations import read_rotations
    from pipeline.reference import Reference, load_reference
    from pipeline.reference.truth import read_reference

    paths = scene_paths(name, data, root)
    images, gt, K = paths
    out = root / name
    if repeat > 1:  # untimed: the first run of a process pays for both what only it pays (module loading, caches)
        timed_paths(name, paths, root / f"{name}-warmup", config, yaml_data)
    ours, glo = timed_paths(name, paths, out, config, yaml_data)
    reps = [(ours, glo)] + [timed_paths(name, paths, root / f"{name}-time{k}", config, yaml_data)
                            for k in range(1, repeat)]
    m = _json(run.main(images, out, config=config, gt=gt, K=K, quiet=True))  # ours and GLOMAP reused
    truth = read_reference(gt).replace(label="truth")
    label = next(k for k, v in m["methods"].items() if v.get("method") == "refine")
    rn, R = read_rotations(out / "rotations" / f"{label}.txt")
    mine = Reference(list(rn), R, label="ours")
    peers = {"glomap": load_reference(out / "reference-global", label="glomap"),
             "incremental": load_reference(out / "reference", label="incremental")}
    r = m["methods"][label]
    row = {"scene": name, "label": label, "status": r["status"], "n_images": m["input"]["n_images"],
           "n_refined": r["n_refined"], "refined": {k: r.get(k) for k in ("n_evaluated", "median_deg", "mean_deg",
                                                                            "max_deg", "sigma_median_deg")},
           "start": {k: m["methods"][r["start"]].get(k) for k in ("median_deg", "mean_deg")},
           "ours": ours, "peers": {}, "kept_averaged": r["kept_averaged"]}
    for key, p in peers.items():
        info = p.info
        pm = m["peers"]["glomap" if key == "glomap" else "pycolmap"]
        row["peers"][key] = {"n_registered": info["n_registered"], "unregistered": info["unregistered"],
                             "time_s": info["time_s"], "times": info["times"],
                             "truth": {k: pm.get(k) for k in ("n_evaluated", "median_deg", "mean_deg", "max_deg")},
                             "pairwise": scored_on_common(mine, p, truth)}
    row["peers"]["glomap"].update(cpu_s=glo["cpu_s"], load_avg=glo["load_avg"])
    g = row["peers"]["glomap"]
    row["time_ratio"] = ours["path_s"] / g["time_s"]
    row["time_ratio_all_methods"] = ours["path_all_methods_s"] / g["time_s"]
    row["cpu_ratio"] = ours["cpu_path_s"] / glo["cpu_s"] if glo["cpu_s"] > 0 else None
    if repeat > 1:  # the time alone, measured again in fresh folders, ours then GLOMAP each time
        row["time_repeats"] = [{"path_s": o["path_s"], "glomap_s": q["time_s"], "ratio": o["path_s"] / q["time_s"],
                                "cpu_ratio": o["cpu_path_s"] / q["cpu_s"], "load_avg": [o["load_avg"], q["load_avg"]]}
                               for o, q in reps]
        row["time_ratio_median"] = float(np.median([t["ratio"] for t in row["time_repeats"]]))
    row["accept"] = {
        "refined_le_each_peer": all(row["peers"][k]["pairwise"]["ours"]["median_deg"]
                                    <= row["peers"][k]["pairwise"][k]["median_deg"] for k in peers),
        "time_ratio_le_1": row["time_ratio"] <= 1.0,
    }
    if name == "temple":
        row["accept"]["temple_all_16_registered"] = r["n_evaluated"] == 16 and r["status"] == "ok"
    return row


def _json(path: Path) -> dict:
    import json

    return json.loads(Path(path).read_text())


def table(rows: list[dict]) -> str:
    lines = [f"{'scene':<13} {'pair':<22} {'common':>6} {'ours med°':>10} {'peer med°':>10} {'peer reg':>9}",
             "-" * 76]
    for r in rows:
        for key, p in r["peers"].items():
            pw = p["pairwise"]
            lines.append(f"{r['scene']:<13} {'ours vs ' + key:<22} {pw['n_common']:>6} {pw['ours']['median_deg']:>10.4f} "
                         f"{pw[key]['median_deg']:>10.4f} {p['n_registered']:>4}/{r['n_images']:<4}")
        s = r["refined"]
        lines.append(f"{'':<13} refined {s['n_evaluated']}/{r['n_images']} images ({r['status']}): median "
                     f"{s['median_deg']:.4f}° (start {r['start']['median_deg']:.4f}°), predicted σ "
                     f"{s['sigma_median_deg'] or float('nan'):.4f}°")
        g = r["peers"]["glomap"]
        lines.append(f"{'':<13} time: our path {r['ours']['path_s']:.1f} s / GLOMAP {g['time_s']:.1f} s = "
                     f"{r['time_ratio']:.2f} (CPU {r['ours']['cpu_path_s']:.1f} / {g['cpu_s']:.1f} s = "
                     f"{r['cpu_ratio'] or float('nan'):.2f}; with every averaging method "
                     f"{r['time_ratio_all_methods']:.2f}); acceptance {r['accept']}")
        if r.get("time_repeats"):
            ratios = ", ".join(f"{t['ratio']:.2f}" for t in r["time_repeats"])
            lines.append(f"{'':<13} time ratio over {len(r['time_repeats'])} repeats: {ratios} "
                         f"(median {r['time_ratio_median']:.2f})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", default="fountain,castle,temple",
                    help=f"comma-separated, of {', '.join([*SCENES, *SUBSETS])}")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="the shared data folder")
    ap.add_argument("--keep", type=Path, default=None, help="keep the run folders here (default: a temp folder)")
    ap.add_argument("--repeat", type=int, default=1, help="measure the time this many times per scene (median), "
                    "after one untimed warm-up of both paths")
    a = ap.parse_args(argv)
    names = [n for n in a.only.split(",") if n]
    unknown = [n for n in names if n not in SCENES and n not in SUBSETS]
    if unknown:
        print(f"error: unknown scene(s) {unknown}; choose from {', '.join([*SCENES, *SUBSETS])}", file=sys.stderr)
        return 2
    root = a.keep or Path(tempfile.mkdtemp(prefix="bench_refine_"))
    if a.keep is None:  # a temp folder of runs is removed at exit (--keep keeps them)
        atexit.register(shutil.rmtree, root, True)
    yaml_data = yaml.safe_load((REPO / "configs" / "default.yaml").read_text())
    yaml_data.setdefault("run", {})["plots"] = False  # no plots in the run (the report is not timed anyway)
    config = root / "bench.yaml"
    root.mkdir(parents=True, exist_ok=True)
    config.write_text(yaml.safe_dump(yaml_data))
    prev = _json(RESULTS) if RESULTS.exists() else {}
    rows = {r["scene"]: r for r in prev.get("scenes", [])}
    for n in names:
        source = SCENES["castle" if n in SUBSETS else n][0]
        if not (a.data / source).is_dir():
            print(f"skipping {n}: {a.data / source} not found")
            continue
        rows[n] = run_scene(n, a.data, root, config, yaml_data, a.repeat)
    result = {"scenes": [rows[n] for n in [*SCENES, *SUBSETS] if n in rows], "machine": {"cores": os.cpu_count()},
              "note": "one run per scene with the true K; ours, then GLOMAP, then the incremental reference, in one "
                      "process; each pair scored on the images both register (l2 alignment)"}
    write_json(RESULTS, result)
    print(table(result["scenes"]))
    print(f"\nwrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
