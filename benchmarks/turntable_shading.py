"""Low-texture turntables whose appearance is not fixed to the surface: do the view graph's checks and flags hold?

The held-out real set (a dark, smooth object turning under fixed lamps on a black background) breaks what the
default rendered turntable keeps: a feature is no longer always one 3-D point. Scenes
(:mod:`pipeline.synthetic.lowtex`, contrast 8, 16 views on a ring, 640×480):

- ``turn_base_s{0,1}``: the default scene (24-/12-sided prisms, world lamp, flat shading): the control;
- ``turn_sil_s{0,1}``: 64-/32-sided prisms (nearly smooth silhouettes), the world lamp, flat shading: the
  sliding occluding contour alone;
- ``turn_mild_s{0,1}``: and a lamp riding with the camera, per-texel (smooth, Phong-interpolated) shading,
  ambient 0.35;
- ``turn_strong_s{0,1}``: the same with ambient 0.1 and a specular highlight (60 grey levels, exponent 20);
- ``turn_harsh_s{0,1}``: contrast 6, the lamp 0.85 units off the camera (up and to the side), ambient 0.05, a broad
  highlight (80 grey levels, exponent 10).

Each runs through ``run.py``'s ``main`` exactly as :mod:`front_end_checks` runs its scenes (its ``measure``:
accepted pairs, pairs > 5°, truly overlapping pairs kept, images solved, flags); added per method: the cameras
> 1° and > 2° and which of them are flagged, the certificate beside a result with an unflagged camera > 1°; per
accepted pair: its error, its view-graph reason, its inliers' true transfer error (the renderer's depth maps) and
the share of them within 3 px of an occluding contour (a depth jump or the background)::

    python benchmarks/turntable_shading.py --work W [--scenes turn_mild_s0 ...]
    python benchmarks/turntable_shading.py --work W --label cyc5 --set viewgraph.cycle_max_deg=5   # a counterfactual
    python benchmarks/turntable_shading.py --table                                                  # the table

Writes ``benchmarks/results/turntable_shading.json`` (entries of other scenes are kept) and prints a table.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import runpy  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.io.rotations import read_rotations  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import rotation_errors_deg  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "turntable_shading.json"
SIDES = dict(body_sides=64, limb_sides=32, contrast=8.0)
KINDS = {"base": dict(contrast=8.0),  # today's default scene (front_end_checks' lowtex_c8): the control
         "sil": dict(SIDES),
         "mild": dict(SIDES, light="camera", shading="smooth", ambient=0.35),
         "strong": dict(SIDES, light="camera", shading="smooth", ambient=0.1, specular=60.0, shininess=20.0),
         "harsh": dict(SIDES, contrast=6.0, light="camera", lamp_offset=(0.6, -0.6, 0.0), shading="smooth",
                       ambient=0.05, specular=80.0, shininess=10.0)}
SCENES = {f"turn_{k}_s{s}": (k, s) for k in KINDS for s in (0, 1)}


def render(work: Path, names: list[str]) -> None:
    from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex, write_scene  # noqa: PLC0415

    for name in names:
        d = work / "scenes" / name
        if not (d / "scene.json").is_file():
            kind, seed = SCENES[name]
            write_scene(render_lowtex(LowTexConfig(**KINDS[kind]), seed=seed), d)


def contour_mask(depth: np.ndarray, band: int = 3, rel_jump: float = 0.05) -> np.ndarray:
    """(h, w) bool: within ``band`` px of an occluding contour (background next to surface, or a relative depth
    jump above ``rel_jump``)."""
    import cv2  # noqa: PLC0415

    fin = np.isfinite(depth)
    d = np.where(fin, depth, 1e6).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    jump = (cv2.dilate(d, k) - cv2.erode(d, k)) > rel_jump * cv2.erode(d, k)
    edge = jump | (fin != cv2.erode(fin.astype(np.uint8), k).astype(bool))
    return cv2.dilate(edge.astype(np.uint8), np.ones((2 * band + 1, 2 * band + 1), np.uint8)).astype(bool)


def _flag_kinds(msgs: list[str]) -> list[str]:
    """The kinds of a camera's flags: 'methods' (the averaging methods disagree on it) or 'graph' (its pairs)."""
    return sorted({"methods" if "methods disagree" in m else "graph" for m in msgs})


def camera_errors(out: Path, gt: Path, metrics: dict) -> dict:
    """Per method: each camera's error against the truth; those > 1° and > 2° with their flags' kinds."""
    truth = read_reference(gt)
    flags = (metrics.get("evidence") or {}).get("flags", {})
    res = {}
    for label, m in metrics["methods"].items():
        names, R = read_rotations(out / "rotations" / f"{label}.txt")
        Rr, mk = match_reference(list(names), truth.names, truth.R)
        e = rotation_errors_deg(R, Rr, mk)
        over1 = {n: {"deg": round(float(x), 2), "flags": _flag_kinds(flags.get(n, []))}
                 for n, x in zip(names, e) if x > 1}
        unf2 = [n for n, v in over1.items() if v["deg"] > 2 and not v["flags"]]
        sel = np.array([n not in flags for n in names], bool)  # the unflagged cameras, aligned on themselves only
        e_unf = rotation_errors_deg(R[sel], Rr[sel], mk[sel]) if sel.sum() >= 2 else np.array([])
        res[label] = {"n": len(names), "median_deg": round(float(np.nanmedian(e)), 3),
                      "n_within_1": int(np.sum(e <= 1)),
                      "n_within_1_unflagged": int(sum(x <= 1 and n not in flags for n, x in zip(names, e))),
                      "n_over_1": len(over1), "n_over_1_unflagged": sum(not v["flags"] for v in over1.values()),
                      "n_over_2": sum(v["deg"] > 2 for v in over1.values()), "n_over_2_unflagged": len(unf2),
                      "n_over_2_only_methods_flag": sum(v["deg"] > 2 and v["flags"] == ["methods"]
                                                        for v in over1.values()),
                      "acceptance": bool(not unf2 and np.sum(e <= 1) >= 6),
                      "max_unflagged_deg_aligned_on_unflagged": round(float(np.nanmax(e_unf)), 2) if len(e_unf) else None,
                      "certified": m.get("certified"), "over_1": over1}
    return res


def _triangle_residuals_deg(edges: np.ndarray, R: np.ndarray) -> dict[int, list[float]]:
    """For each edge index, the rotation residuals (°) of the triangles of ``edges`` it closes."""
    idx = {(int(a), int(b)): k for k, (a, b) in enumerate(edges)}
    Rij = lambda i, j: R[idx[(i, j)]] if (i, j) in idx else R[idx[(j, i)]].T  # noqa: E731
    has = lambda i, j: (min(i, j), max(i, j)) in idx  # noqa: E731
    nodes = sorted({int(x) for x in edges.ravel()})
    out: dict[int, list[float]] = {k: [] for k in range(len(edges))}
    for k, (i, j) in enumerate(edges):
        for m in nodes:
            if m not in (i, j) and has(i, m) and has(j, m):
                C = Rij(int(j), m) @ Rij(int(i), int(j)) @ Rij(int(i), m).T  # R_jm R_ij R_imᵀ = I when consistent
                out[k].append(float(np.degrees(np.arccos(np.clip((np.trace(C) - 1) / 2, -1, 1)))))
    return out


def pair_table(out: Path, scene, work: Path | None = None) -> list[dict]:
    """Every kept pair: its error (°), its Mahalanobis error under its H (χ² with 3 dof when H is right), the
    triangle residuals it closes among the kept pairs, and its RANSAC inliers' truth: the share off by > 3 px
    (the renderer's depth maps) and the share within 3 px of an occluding contour in either view."""
    from pipeline.core import so3  # noqa: PLC0415
    from pipeline.core.viewgraph import ViewGraph  # noqa: PLC0415

    vg = ViewGraph.load(out / "viewgraph.npz", allow_isolated=True)
    rows_vg = {tuple(p["pair"]): p for p in json.loads((out / "viewgraph.json").read_text())["pairs"]}
    work = out / "work" if work is None else work  # a component's folder has none: its run's
    tv = np.load(work / "two_view.npz", allow_pickle=False)
    corr = np.load(work / "two_view_corr.npz", allow_pickle=False)
    tv_names = [str(n) for n in tv["names"]]
    tv_idx = {(tv_names[a], tv_names[b]): k for k, (a, b) in enumerate(tv["edges"])}
    sc = {n: k for k, n in enumerate(scene.names)}
    contour = [contour_mask(d) for d in scene.depths]
    tri = _triangle_residuals_deg(vg.edges, vg.R_rel)
    rows = []
    for k, (i, j) in enumerate(vg.edges):
        na, nb = vg.names[i], vg.names[j]
        a, b = sc[na], sc[nb]
        R_true = scene.R[b] @ scene.R[a].T
        dw = so3.log(R_true @ vg.R_rel[k].T)
        r = {"pair": f"{na[7:10]}-{nb[7:10]}", "err_deg": round(float(np.degrees(np.linalg.norm(dw))), 2),
             "maha2": round(float(dw @ vg.H[k] @ dw), 1) if vg.H is not None else None,
             "sigma_deg": round(float(np.degrees(np.sqrt(np.trace(np.linalg.inv(vg.H[k]))))), 2)
             if vg.H is not None else None,
             "inliers": int(vg.inliers[k]), "tier": rows_vg.get((na, nb), {}).get("tier"),
             "confirmed": rows_vg.get((na, nb), {}).get("confirmed"),
             "ba_rms_px": round(float(vg.stats["ba_rms_px"][k]), 2) if "ba_rms_px" in vg.stats else None,
             "tri_deg": [round(x, 2) for x in sorted(tri[k])]}
        t = tv_idx.get((na, nb))
        if t is not None:
            lo, hi = corr["offsets"][t], corr["offsets"][t + 1]
            xi, xj = corr["x_i"][lo:hi], corr["x_j"][lo:hi]
            te = scene.transfer_error_px(a, b, xi, xj)
            h, w = contour[a].shape
            on = lambda c, x: c[np.clip(np.round(x[:, 1]).astype(int), 0, h - 1),  # noqa: E731
                                np.clip(np.round(x[:, 0]).astype(int), 0, w - 1)]
            sil = on(contour[a], xi) | on(contour[b], xj)
            r.update(n_corr=int(hi - lo), share_off_3px=round(float(np.mean(te > 3)), 3),
                     share_contour=round(float(np.mean(sil)), 3),
                     share_off_among_contour=round(float(np.mean(te[sil] > 3)), 3) if sil.any() else None)
        rows.append(r)
    return rows


def measure_scene(fec: dict, name: str, work: Path, label: str = "after") -> dict:
    from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex  # noqa: PLC0415

    d = work / "scenes" / name
    r = fec["measure"](name, dict(images=d, gt=d / "cameras.txt", kind="lowtex"), work, label)
    out = work / "runs" / f"{name}_{label}"
    metrics = json.loads((out / "metrics.json").read_text())
    kind, seed = SCENES[name]
    scene = render_lowtex(LowTexConfig(**KINDS[kind]), seed=seed)  # the depth maps (the images are the same)
    r["cameras"] = camera_errors(out, d / "cameras.txt", metrics)
    r["flags"] = {n: _flag_kinds(v) for n, v in ((metrics.get("evidence") or {}).get("flags", {})).items()}
    r["pairs"] = pair_table(out, scene)
    r["components"] = {}
    for comp in sorted(out.glob("component-*")):  # solved in frames of their own: scored in their own frame
        cm = json.loads((comp / "metrics.json").read_text())
        r["components"][comp.name] = {"cameras": camera_errors(comp, d / "cameras.txt", cm),
                                      "flags": {n: _flag_kinds(v) for n, v in
                                                ((cm.get("evidence") or {}).get("flags", {})).items()},
                                      "pairs": pair_table(comp, scene, out / "work")}
    return r


def table(results: dict) -> str:
    head = ("scene", "acc", ">5°", "max°", "true kept", "solved", "flagged (graph/methods only)",
            "method: ≤1° (unflagged) / >1° (unfl.) / >2° (unfl.; flagged only as methods disagreeing) cert")
    rows = [head]
    for name, r in results.items():
        nf = len(r["flags"])
        ng = sum("graph" in v for v in r["flags"].values())
        first = True
        for m, c in r["cameras"].items():
            cert = {True: " cert", False: " not-cert", None: ""}[c["certified"]]
            cell = (f"{m}: {c['n_within_1']} ({c['n_within_1_unflagged']}) / {c['n_over_1']} ({c['n_over_1_unflagged']})"
                    f" / {c['n_over_2']} ({c['n_over_2_unflagged']}; {c['n_over_2_only_methods_flag']}){cert}")
            if first:
                rows.append((name, str(r["n_accepted"]), str(r["n_accepted_gt5"]), f"{r['max_accepted_err_deg']:.2f}",
                             f"{r['true_pairs_kept']}/{r['n_true_pairs']}", f"{r['n_solved']}/{r['n_images']}",
                             f"{nf} ({ng}/{nf - ng})", cell))
                first = False
            else:
                rows.append(("", "", "", "", "", "", "", cell))
        for cname, comp in r.get("components", {}).items():
            for k, (m, c) in enumerate(comp["cameras"].items()):
                rows.append((f"  {cname}" if k == 0 else "", "", "", "", "", str(c["n"]) if k == 0 else "",
                             str(len(comp["flags"])) if k == 0 else "",
                             f"{m}: {c['n_within_1']} ({c['n_within_1_unflagged']}) / {c['n_over_1']} "
                             f"({c['n_over_1_unflagged']}) / {c['n_over_2']} ({c['n_over_2_unflagged']}; "
                             f"{c['n_over_2_only_methods_flag']})"))
    w = [max(len(x[c]) for x in rows) for c in range(len(head))]
    return "\n".join("  ".join(c.ljust(w[k]) for k, c in enumerate(x)) for x in rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, help="scratch folder: scenes and runs (needed unless --table)")
    p.add_argument("--scenes", nargs="*", default=None, help=f"scene names (default all: {' '.join(SCENES)})")
    p.add_argument("--render-only", action="store_true")
    p.add_argument("--table", action="store_true", help="print the table of every scene in the results file, run nothing")
    p.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE",
                   help="config options for every run (a counterfactual, e.g. viewgraph.cycle_max_deg=5); give --label")
    p.add_argument("--label", default="after", help="runs go to runs/NAME_LABEL; results of another label than "
                                                    "'after' are stored as NAME@LABEL")
    a = p.parse_args()
    if a.table:
        done = json.loads(RESULTS.read_text())["scenes"]
        print(table({n: done[n] for n in sorted(done, key=lambda n: (n.split("@")[0] not in SCENES,
                                                                     list(SCENES).index(n.split("@")[0])
                                                                     if n.split("@")[0] in SCENES else 0, n))}))
        return 0
    if a.work is None:
        p.error("--work is needed to render or run")
    if a.set and a.label == "after":
        p.error("--set needs a --label of its own (the default runs are 'after')")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    names = a.scenes or list(SCENES)
    render(a.work, names)
    if a.render_only:
        return 0
    fec = runpy.run_path(str(REPO / "benchmarks" / "front_end_checks.py"), run_name="front_end_checks")
    old = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    results = dict(old.get("scenes", {}))
    fec["OVERRIDES"][:] = a.set
    keys = []
    for name in names:
        key = name if a.label == "after" else f"{name}@{a.label}"
        results[key] = measure_scene(fec, name, a.work, a.label) | ({"set": a.set} if a.set else {})
        keys.append(key)
        bad = [x for x in results[key]["pairs"] if x["err_deg"] > 5]
        print(f"{key}: {len(bad)} kept pairs > 5°: {bad}", flush=True)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS, {"scenes": results, "command": "python benchmarks/turntable_shading.py --work W"})
    print(table({k: results[k] for k in keys}))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
