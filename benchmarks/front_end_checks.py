"""Issue 13, items 3–4: low texture and no wrong pair unseen, measured before and after, in the same way.

Scenes (each through ``run.py``'s ``main`` with its K and its truth):

- ``lowtex_c{6,8,12,20}_s{0,1}``: the rendered low-texture turntable (:mod:`pipeline.synthetic.lowtex`),
  contrast 6–20 grey levels, two seeds; the renderer knows which of the 120 pairs truly overlap;
- ``temple``: Middlebury templeSparseRing with K, with the pycolmap reference (its verified pairs are
  counted from its database, and each is scored by the relative pose pycolmap derives from its own geometry and
  inliers: pycolmap's count holds wrong pairs too);
- ``fountain``, ``castle``: Strecha fountain-P11 and castle-P30 with K (textured: the features must not change);
- ``static`` / ``repeated``: wrong but well-supported pairs injected into rendered scenes
  (:mod:`pipeline.synthetic.injected`), matched on a pairs file (true pairs + injected); ``*_control``:
  the true pairs only.

Per run: accepted pairs (after: the view graph's kept pairs; before: every pair of the two-view BA
graph, which the old view-graph stage averaged), their error against the truth, the truly
overlapping pairs kept, the images solved or left out with why, each method's camera errors,
the flagged cameras and whether every camera more than 1° off is flagged.

"Before" is the package before this work (commit 2729d04), run by this same script with that
package first on the path; "after" is the installed package::

    python benchmarks/front_end_checks.py --work W --render-only           # the rendered scenes, once
    PYTHONPATH=/path/to/2729d04 python benchmarks/front_end_checks.py --work W --label before --json W/before.json
    python benchmarks/front_end_checks.py --work W --label after --before W/before.json   # writes the results

``--scenes`` picks scenes (default all); ``--sizes`` adds the sparse-cycle scaling table (after only).
Writes ``benchmarks/results/front_end_checks.json`` (entries of other scenes are kept).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import glob  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core import so3  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import edge_errors_deg, rotation_errors_deg  # noqa: E402
from pipeline.io.rotations import read_rotations  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
from pipeline.run import main as run_main  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")
RESULTS = REPO / "benchmarks" / "results" / "front_end_checks.json"
LOWTEX = [(c, s) for c in (6, 8, 12, 20) for s in (0, 1)]


def scene_specs(work: Path) -> dict[str, dict]:
    specs: dict[str, dict] = {}
    for c, s in LOWTEX:
        d = work / "scenes" / f"lowtex_c{c}_s{s}"
        specs[f"lowtex_c{c}_s{s}"] = dict(images=d, gt=d / "cameras.txt", kind="lowtex", contrast=c, seed=s)
    t = DATA / "middlebury-templeSparseRing"
    specs["temple"] = dict(images=t, gt=t / "templeSR_par.txt", K=t / "templeSR_par.txt", reference=True)
    for name, folder in (("fountain", "fountain-P11"), ("castle", "castle-P30")):
        d = DATA / "strecha" / folder
        specs[name] = dict(images=d / "images", gt=d / "gt_dense_cameras", K=d / "images" / "K.txt")
    for kind in ("static", "repeated"):
        d = work / "scenes" / kind
        specs[kind] = dict(images=d, gt=d / "cameras.txt", kind=kind, pairs="all")
        specs[f"{kind}_control"] = dict(images=d, gt=d / "cameras.txt", kind=kind, pairs="true")
    return specs


def render(work: Path) -> None:
    """Render every synthetic scene not yet in ``work/scenes`` (needs the package of this issue)."""
    from pipeline.synthetic.injected import render_repeated, render_turntable_with_static  # noqa: PLC0415
    from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex, write_scene  # noqa: PLC0415

    for c, s in LOWTEX:
        d = work / "scenes" / f"lowtex_c{c}_s{s}"
        if not (d / "scene.json").is_file():
            write_scene(render_lowtex(LowTexConfig(contrast=float(c)), seed=s), d)
    for kind, fn in (("static", render_turntable_with_static), ("repeated", render_repeated)):
        if not (work / "scenes" / kind / "scene.json").is_file():
            write_scene(fn(), work / "scenes" / kind)


def _truth_pairs(folder: Path) -> tuple[list[str], set[tuple[str, str]], set[tuple[str, str]]]:
    d = json.loads((folder / "scene.json").read_text())
    n = d["names"]
    tp = {(n[a], n[b]) for a, b in d["true_pairs"]}
    inj = {(n[a], n[b]) for a, b in d.get("injected", [])}
    return n, tp, inj


OVERRIDES: list[str] = []  # "section.key=value" from --set


def _config(spec: dict, out: Path) -> Path | None:
    sections: dict[str, list[str]] = {"run": ["  plots: false"]}
    for o in OVERRIDES:
        key, _, value = o.partition("=")
        section, _, name = key.partition(".")
        sections.setdefault(section, []).append(f"  {name}: {value}")
    lines: list[str] = []
    for section, opts in sections.items():
        if section != "matching":
            lines += [f"{section}:", *opts]
    if "pairs" in spec:
        _, tp, inj = _truth_pairs(spec["images"])
        pf = out.parent / f"{out.name}_pairs.txt"
        pf.write_text("".join(f"{a} {b}\n" for a, b in sorted(tp | inj if spec["pairs"] == "all" else tp)))
        lines += ["matching:", f"  pairs: {pf}", *sections.get("matching", [])]
    elif "matching" in sections:
        lines += ["matching:", *sections["matching"]]
    p = out.parent / f"{out.name}.yaml"
    p.write_text("\n".join(lines) + "\n")
    return p


def _pycolmap_verified(out: Path, truth, min_inliers: int = 15) -> dict | None:
    """pycolmap's verified pairs with at least ``min_inliers`` inliers (its database, same run), and how many of
    them are right: each pair's relative pose from its own geometry and inliers
    (``pycolmap.estimate_two_view_geometry_pose``, with the database's cameras: the true K), against the truth."""
    import pycolmap  # noqa: PLC0415

    dbs = sorted(glob.glob(str(out / "reference" / "database-*.db")))
    if not dbs:
        return None
    db = pycolmap.Database.open(dbs[0]) if hasattr(pycolmap.Database, "open") else pycolmap.Database(dbs[0])
    try:
        images = {im.image_id: im for im in db.read_all_images()}
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        ref = dict(zip(truth.names, truth.R))
        pair_ids, geoms = db.read_two_view_geometries()
        errors, keypoints = {}, {}
        for pid, g in zip(pair_ids, geoms):  # one pose per pair: a few dozen, not a hot path
            if len(g.inlier_matches) < min_inliers:
                continue
            a, b = (images[i] for i in pycolmap.pair_id_to_image_pair(pid))
            for im in (a, b):  # each image's keypoints read once
                if im.image_id not in keypoints:
                    keypoints[im.image_id] = np.asarray(db.read_keypoints(im.image_id), np.float64)[:, :2]
            pts = [keypoints[a.image_id], keypoints[b.image_id]]
            ok = pycolmap.estimate_two_view_geometry_pose(cameras[a.camera_id], pts[0], cameras[b.camera_id], pts[1], g)
            if not ok or g.cam2_from_cam1 is None or a.name not in ref or b.name not in ref:
                errors[f"{a.name} {b.name}"] = None
                continue
            errors[f"{a.name} {b.name}"] = float(np.degrees(so3.angle_between(g.cam2_from_cam1.rotation.matrix(),
                                                                             ref[b.name] @ ref[a.name].T)))
    finally:
        db.close()
    wrong = {k: round(e, 2) for k, e in errors.items() if e is None or e > 5}
    return {"n": len(errors), "n_within_5": len(errors) - len(wrong), "over_5_deg": wrong}


def _verified_fields(v: dict | None) -> dict:
    if v is None:
        return {"verified_pairs_ge15": None}
    return {"verified_pairs_ge15": v["n"], "verified_pairs_ge15_within_5": v["n_within_5"],
            "verified_pairs_ge15_over_5": v["over_5_deg"]}


def measure(name: str, spec: dict, work: Path, label: str) -> dict:
    out = work / "runs" / f"{name}_{label}"
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    metrics = json.loads(run_main(spec["images"], out, _config(spec, out), gt=spec["gt"], K=spec.get("K"),
                                  reference=bool(spec.get("reference")), quiet=True).read_text())
    wall = time.perf_counter() - t0
    truth = read_reference(spec["gt"])
    vg_ba = ViewGraph.load(out / "work" / "viewgraph.npz", allow_isolated=True)
    R_ref, mask = match_reference(vg_ba.names, truth.names, truth.R)
    err = edge_errors_deg(vg_ba, R_ref, mask)
    pair_names = [(vg_ba.names[a], vg_ba.names[b]) for a, b in vg_ba.edges]
    summary_path = out / "viewgraph.json"
    s = json.loads(summary_path.read_text())
    if "pairs" in s:  # after: the checked graph's kept pairs (every component)
        kept = {tuple(p["pair"]) for p in s["pairs"] if p["status"] == "kept"}
        acc = np.array([p in kept for p in pair_names], bool)
    else:  # before: the old view-graph stage averaged every pair of the BA graph
        acc = np.ones(len(pair_names), bool)
    e_acc = err[acc]
    r: dict = {"label": label, "wall_s": round(wall, 1), "n_images": len(vg_ba.names),
               "n_pairs_two_view_ba": int(vg_ba.n_edges), "n_accepted": int(acc.sum()),
               "n_accepted_gt5": int(np.sum(e_acc > 5)), "max_accepted_err_deg": float(np.nanmax(e_acc)) if acc.any()
               else None, "median_accepted_err_deg": float(np.nanmedian(e_acc)) if acc.any() else None,
               "n_solved": int(metrics["input"]["n_cameras_graph"]), "left_out": metrics["input"]["left_out_why"],
               "stages_s": {k: round(v, 2) for k, v in metrics["stages"].items()}}
    # optical axes within 60°: the pairs that look at the object from similar directions
    z = R_ref[:, 2, :]
    ax = np.degrees(np.arccos(np.clip(np.einsum("ma,ma->m", z[vg_ba.edges[:, 0]], z[vg_ba.edges[:, 1]]), -1, 1)))
    r["n_accepted_axes_within_60"] = int(np.sum(acc & (ax <= 60)))
    if spec.get("kind"):
        _, tp, inj = _truth_pairs(spec["images"])
        ok5 = {p for p, a, e in zip(pair_names, acc, err) if a and e <= 5}
        acc_set = {p for p, a in zip(pair_names, acc) if a}
        r.update(n_true_pairs=len(tp), true_pairs_kept=len(acc_set & tp), true_pairs_kept_within_5=len(ok5 & tp),
                 recall=round(len(acc_set & tp) / max(len(tp), 1), 4), accepted_not_true=len(acc_set - tp))
        if inj and spec.get("pairs") == "all":
            fate = {}
            rows = {tuple(p["pair"]): p for p in s.get("pairs", [])}
            for p in sorted(inj):
                if p in rows:
                    fate[" ".join(p)] = f"{rows[p]['status']} at {rows[p]['step'] or '-'}: {rows[p]['reason']}"
                else:
                    fate[" ".join(p)] = "kept" if p in acc_set else "not in the two-view BA graph (rejected before)"
            r["injected"] = fate
            r["n_injected"] = len(inj)
            r["n_injected_kept"] = sum(p in acc_set for p in inj)
    flags = set((metrics.get("evidence") or {}).get("flags", {}))
    r["n_flagged"] = len(flags)
    r["messages"] = (metrics.get("evidence") or {}).get("messages", [])
    r["methods"] = {}
    for label_m, m in metrics["methods"].items():
        names, R = read_rotations(out / "rotations" / f"{label_m}.txt")
        Rr, mk = match_reference(list(names), truth.names, truth.R)
        e = rotation_errors_deg(R, Rr, mk)
        off = [nm for nm, x in zip(names, e) if x > 1.0]
        r["methods"][label_m] = {"median_deg": float(np.nanmedian(e)), "max_deg": float(np.nanmax(e)),
                                 "n_cameras": len(names), "certified": m.get("certified"),
                                 "n_over_1deg": len(off), "n_over_1deg_unflagged": len([x for x in off if x not in flags])}
    if spec.get("reference"):
        p = metrics.get("pycolmap") or {}
        r["pycolmap"] = {"median_deg": p.get("median_deg"), "n_registered": p.get("n_registered"),
                         **_verified_fields(_pycolmap_verified(out, truth))}
    return r


def scaling(sizes: list[int]) -> list[dict]:
    """check_view_graph on ring graphs of N cameras, each paired with its 20 nearest (sparse cycles)."""
    from pipeline.core import so3  # noqa: PLC0415
    from pipeline.graph.checks import ViewGraphConfig, check_view_graph  # noqa: PLC0415

    rows = []
    for n in sizes:
        rng = np.random.default_rng(0)
        a = np.repeat(np.arange(n), 10)
        b = (a + np.tile(np.arange(1, 11), n)) % n
        E = np.unique(np.sort(np.stack([a, b], 1), axis=1), axis=0)
        R = so3.random_rotations(n, rng)
        Rm = so3.exp(np.deg2rad(0.5) * rng.standard_normal((len(E), 3))) @ (R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2))
        bad = rng.choice(len(E), len(E) // 20, replace=False)
        Rm[bad] = so3.random_rotations(len(bad), rng)
        M = len(E)
        vg = ViewGraph([f"c{k}" for k in range(n)], E, Rm, H=np.broadcast_to(np.eye(3) / np.deg2rad(0.5) ** 2,
                                                                              (M, 3, 3)).copy(),
                       inliers=np.full(M, 100), stats={"n_inliers_E": np.full(M, 100), "n_matches": np.full(M, 150),
                                                       "median_triangulation_deg": np.full(M, 10.0)})
        t0 = time.perf_counter()
        chk = check_view_graph(vg, ViewGraphConfig())
        dt = time.perf_counter() - t0
        rows.append({"n_cameras": n, "n_edges": M, "n_wrong": len(bad), "n_short_cycles": chk.info["n_short_cycles"],
                     "wrong_removed": int((~chk.kept[bad]).sum()), "good_removed": int((~chk.kept).sum() - (~chk.kept[bad]).sum()),
                     "time_s": round(dt, 2)})
        print(f"scaling N={n}: {rows[-1]}", flush=True)
    return rows


def table(results: dict) -> str:
    head = ("scene", "run", "acc", ">5°", "max°", "true kept", "solved", "median° per method", "flagged")
    rows = [head]
    for name, by in results.items():
        for label, r in by.items():
            tk = f"{r['true_pairs_kept']}/{r['n_true_pairs']}" if "n_true_pairs" in r else "–"
            med = " / ".join(f"{m['median_deg']:.3f}" for m in r["methods"].values())
            rows.append((name, label, str(r["n_accepted"]), str(r["n_accepted_gt5"]),
                         f"{r['max_accepted_err_deg']:.2f}" if r["max_accepted_err_deg"] is not None else "–", tk,
                         f"{r['n_solved']}/{r['n_images']}", med, str(r.get("n_flagged", "–"))))
    w = [max(len(r[c]) for r in rows) for c in range(len(head))]
    return "\n".join("  ".join(c.ljust(w[k]) for k, c in enumerate(r)) for r in rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, required=True, help="scratch folder: scenes and runs")
    p.add_argument("--scenes", nargs="*", default=None, help="scene names (default all)")
    p.add_argument("--label", default="after", help="'after' (this package) or 'before'")
    p.add_argument("--json", type=Path, default=None, help="write this run's figures here (before runs)")
    p.add_argument("--before", type=Path, default=None, help="a before run's JSON to put beside the after figures")
    p.add_argument("--render-only", action="store_true")
    p.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE",
                   help="config options for every run, e.g. two_view.guided=true (use another --label)")
    p.add_argument("--sizes", nargs="*", type=int, default=[], help="scaling table sizes (e.g. 1000 3000 10000)")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    OVERRIDES[:] = a.set
    if a.render_only:
        render(a.work)
        return 0
    specs = scene_specs(a.work)
    names = a.scenes or list(specs)
    results: dict = {}
    for name in names:
        if not Path(specs[name]["images"]).is_dir():
            print(f"{name}: {specs[name]['images']} not found, skipped", flush=True)
            continue
        results[name] = {a.label: measure(name, specs[name], a.work, a.label)}
        print(f"{name} {a.label}: {json.dumps({k: v for k, v in results[name][a.label].items() if k not in ('left_out', 'injected', 'stages_s')})}", flush=True)
    if a.json is not None:
        write_json(a.json, results)
    if a.before is not None and a.before.is_file():
        for name, by in json.loads(a.before.read_text()).items():
            if name in results:
                results[name] = {**by, **results[name]}
    if a.label == "after":
        old = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
        doc = {"scenes": {**old.get("scenes", {}), **results}, "scaling": old.get("scaling", [])}
        if a.sizes:
            doc["scaling"] = scaling(a.sizes)
        doc["commands"] = __doc__.split("package::")[1].split("``--scenes``")[0].strip()
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        write_json(RESULTS, doc)
        print(table(doc["scenes"]))
        print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
