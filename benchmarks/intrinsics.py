"""Unknown intrinsics and lens distortion (issue 13, acceptance items 1, 2 and 5).

    python benchmarks/intrinsics.py [--only fountain,castle,temple,nees,lens,lens-centre]
                                    [--modes none,auto,shared,per_camera]
                                    [--draws 500] [--keep DIR]

1. **Scenes without K** (fountain-P11, castle-P30, templeSparseRing from ``../shared/data``):
   each runs ``run.py``'s ``main()`` on a folder of symlinks to its images alone (no
   ``K.txt``, no ``*_par.txt``; the images carry no EXIF), with the pycolmap incremental
   reference in the same run, also without K (SIMPLE_RADIAL, one camera per image as
   COLMAP's AUTO mode gives without EXIF). Reported: the focal the cameras stage
   estimated and where it came from (the report's own words), its error against the
   true one (read here from ``K.txt``/``templeSR_par.txt``, for scoring only), each
   averaging method's median error against the truth on every image and on the
   images pycolmap registered, and pycolmap's. Then the same run with the two-view BA
   refining the focal (``refine_focal: shared``, ``per_camera``; front end and
   reference reused): the measurement behind the default ``none``.
2. **Calibration of H with a refined focal** (``--draws`` draws per configuration):
   synthetic pairs whose optical axes do not meet (``synthetic_pair(offset_axes=True)``),
   σ = 1 px, 200 points, the BA started 1° off and with the focal off by up to ±5%.
   Mean NEES of Δω against ``H`` (target [2.8, 3.2], sd of the mean ≈ 0.11 at 500
   draws), and the focal's own NEES against its marginal sd (target 1). Baselines:
   the focal left 5% off (``none``), and the true K.
3. **A lens**: the rendered scene of ``tests/test_run_intrinsics.py`` (8 views, 640×480,
   SIMPLE_RADIAL k1 = −0.15) and its k1 = 0 twin through the same resampling: the
   errors with the distortion ignored, read from a COLMAP cameras file, and estimated.
4. **A lens off the image centre** (``lens-centre``): rendered scenes of 8–12 views (1024×768, f = 900 px)
   through a SIMPLE_RADIAL lens centred on a principal point 0–24 px from the image centre, run
   without K, file or EXIF (focal and k1 estimated); the refinement with ``refine.lens: measured``
   (default) and ``undistorted`` on the same front end, scored against the truth.

Writes ``benchmarks/results/intrinsics.json`` (sections merged with an earlier run's).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MPLBACKEND", "Agg")

import argparse  # noqa: E402
import atexit  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core import so3  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.evaluation.compare import SUBSET_PREFIX  # noqa: E402
from pipeline.frontend.images import IMAGE_EXTENSIONS  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# ../shared/data beside the checkout (a git worktree sits one level deeper)
DATA = next((p / "shared" / "data" for p in REPO.parents if (p / "shared" / "data").is_dir()), REPO.parent / "shared" / "data")
RESULTS = REPO / "benchmarks" / "results" / "intrinsics.json"
MODES = ("none", "auto", "shared", "per_camera")


def _scenes(data: Path) -> dict[str, tuple[Path, Path, np.ndarray]]:
    """name -> (image folder, truth, true K), the true K read for scoring only."""
    out = {}
    for name in ("fountain-P11", "castle-P30"):
        d = data / "strecha" / name
        if d.is_dir():
            out[name] = (d / "images", d / "gt_dense_cameras", np.loadtxt(d / "images" / "K.txt").reshape(3, 3))
    t = data / "middlebury-templeSparseRing"
    if t.is_dir():
        row = (t / "templeSR_par.txt").read_text().split("\n")[1].split()
        out["temple"] = (t, t / "templeSR_par.txt", np.array([float(v) for v in row[1:10]]).reshape(3, 3))
    return out


def images_only(src: Path, dst: Path) -> Path:
    """A folder of symlinks to the images of ``src`` alone: no K.txt, cameras.txt or *_par.txt is found."""
    dst.mkdir(parents=True, exist_ok=True)
    for p in sorted(src.iterdir()):
        if p.suffix.lower() in IMAGE_EXTENSIONS and not (dst / p.name).exists():
            (dst / p.name).symlink_to(p.resolve())
    return dst


def _row(m: dict, f_true: float) -> dict:
    focal = m["intrinsics"]["focal"]
    f = focal[0]["median_px"]
    row = {"focal_px": f, "focal_source": [x["source"] for x in focal], "focal_error_pct": 100 * (f / f_true - 1),
           "f_true_px": f_true, "distortion": m["intrinsics"]["distortion"], "estimates": m["intrinsics"]["estimates"],
           "stages_s": m["stages"], "n_edges": m["input"]["n_edges"], "methods": {}}
    for label, s in m["methods"].items():
        refs = s.get("references", {})
        sub = next((v for k, v in refs.items() if k.startswith(SUBSET_PREFIX)), None)
        row["methods"][label] = {"median_deg": refs.get("truth", {}).get("median_deg"),
                                 "n_evaluated": refs.get("truth", {}).get("n_evaluated"),
                                 "median_deg_on_pycolmap_images": None if sub is None else sub.get("median_deg")}
    p = m.get("pycolmap") or {}
    row["pycolmap_noK"] = {k: p.get(k) for k in ("median_deg", "n_registered", "n_images", "time_s")}
    row["peers_noK"] = {lb: {k: q.get(k) for k in ("median_deg", "n_registered", "n_images", "time_s")}
                        for lb, q in (m.get("peers") or {}).items()}
    row["refine_focal_px"] = {k: v.get("focal_px_median") for k, v in m["methods"].items() if v.get("method") == "refine"}
    return row


def scene_rows(name: str, images: Path, gt: Path, K: np.ndarray, root: Path, modes: tuple[str, ...] = MODES,
               min_keypoints: int | None = None) -> dict:
    from pipeline.run import main  # noqa: PLC0415

    imgs = images_only(images, root / name / "images")
    out: dict = {}
    tag = "" if min_keypoints is None else f"-minkp{min_keypoints}"
    for mode in modes:
        dst = root / name / f"out-{mode}{tag}"
        if mode != "none" and not dst.exists():
            shutil.copytree(root / name / f"out-none{tag}", dst)  # front end and reference reused; BA onwards again
        cfg = root / name / f"{mode}{tag}.yaml"
        feats = "" if min_keypoints is None else f"features:\n  min_keypoints: {min_keypoints}\n"
        cfg.write_text(f"run:\n  plots: false\n{feats}two_view_ba:\n  refine_focal: {mode}\n")
        t0 = time.perf_counter()
        m = json.loads(Path(main(imgs, dst, cfg, gt=gt, reference=True, quiet=True)).read_text())
        key = mode if min_keypoints is None else f"{mode}, features.min_keypoints={min_keypoints}"
        out[key] = _row(m, float(K[0, 0])) | {"wall_s": time.perf_counter() - t0}
        r = out[key]
        meds = {k: round(v["median_deg"], 4) for k, v in r["methods"].items()}
        print(f"{name:13s} refine_focal={mode:10s}{tag} f {r['focal_px']:8.1f} px ({r['focal_error_pct']:+.2f}%, "
              f"{', '.join(r['focal_source'])})  ours {meds}  pycolmap no K {r['pycolmap_noK']['median_deg']:.4f} "
              f"({r['pycolmap_noK']['n_registered']}/{r['pycolmap_noK']['n_images']})  {r['wall_s']:.0f} s", flush=True)
    return out


# ----------------------------------------------------------------------- NEES
def nees_config(mode: str, scene_seed: int, draws: int, sigma_known: bool = False, true_start: bool = False) -> dict:
    from pipeline.geometry.ba_solver import BAConfig, TwoViewBAError, refine_pair  # noqa: PLC0415
    from pipeline.synthetic.pairs import perturbed_focal, synthetic_pair  # noqa: PLC0415

    cfg = BAConfig(refine_focal=mode, sigma_px=1.0 if sigma_known else None)
    nees, fnees, fails = [], [], 0
    t0 = time.perf_counter()
    for d in range(draws):  # Monte Carlo: one BA per draw
        sp = synthetic_pair(200, 1.0, seed=10_000 + d, scene_seed=scene_seed, offset_axes=True)
        K0 = sp.K_i if true_start else perturbed_focal(sp.K_i, 0.05, 10_000 + d)
        try:
            r = refine_pair(sp.x_i, sp.x_j, K0, K0, sp.R0, sp.t0, cfg)
        except TwoViewBAError:
            fails += 1
            continue
        dw = so3.log(sp.R @ r.R.T)
        nees.append(float(dw @ r.H @ dw))
        if len(r.focal_log_sd):
            fnees.append((math.log(r.K_i[0, 0] / sp.K_i[0, 0]) / r.focal_log_sd[0]) ** 2)
    row = {"mode": mode, "scene_seed": scene_seed, "sigma": "known" if sigma_known else "estimated",
           "start": "true K" if true_start else "focal ±5%", "draws": draws, "failed": fails,
           "mean_nees": float(np.mean(nees)), "in_2.8_3.2": bool(2.8 <= np.mean(nees) <= 3.2),
           "focal_nees": float(np.mean(fnees)) if fnees else None, "time_s": time.perf_counter() - t0}
    fn = "–" if row["focal_nees"] is None else f"{row['focal_nees']:.3f}"
    print(f"NEES  {mode:10s} scene {scene_seed}  σ {row['sigma']:9s} start {row['start']:9s}  mean NEES "
          f"{row['mean_nees']:.3f} {'ok' if row['in_2.8_3.2'] else 'OUT'}  focal NEES {fn}", flush=True)
    return row


def nees_rows(draws: int) -> list[dict]:
    rows = [nees_config(m, s, draws) for s in (0, 1, 2) for m in ("shared", "per_camera")]
    rows.append(nees_config("shared", 0, draws, sigma_known=True))
    rows.append(nees_config("none", 0, draws))
    rows.append(nees_config("none", 0, draws, true_start=True))
    return rows


# ----------------------------------------------------------------------- lens
def lens_rows(root: Path) -> dict:
    from pipeline.run import main  # noqa: PLC0415
    from pipeline.synthetic.distort import render_distorted_scene  # noqa: PLC0415
    from pipeline.synthetic.render import SceneConfig  # noqa: PLC0415

    cfg = SceneConfig(width=640, height=480, focal=500.0, noise_sigma=1.0)
    for name, k1 in (("U0", 0.0), ("D", -0.15)):
        if not (root / name / "lens.txt").exists():
            render_distorted_scene(8, 0, root / name, k1, config=cfg)
    (root / "plain.yaml").write_text("run:\n  plots: false\n")
    (root / "estimate.yaml").write_text("run:\n  plots: false\ncameras:\n  radial: estimate\n")
    out: dict = {}
    for tag, short, img, K, y in (("undistorted (k1 = 0, same resampling)", "U0", "U0", "K.txt", "plain.yaml"),
                                  ("distorted, ignored", "D-none", "D", "K.txt", "plain.yaml"),
                                  ("distorted, read (COLMAP SIMPLE_RADIAL)", "D-known", "D", "lens.txt", "plain.yaml"),
                                  ("distorted, estimated (radial: estimate)", "D-est", "D", "K.txt", "estimate.yaml")):
        m = json.loads(Path(main(root / img, root / f"out-{short}", root / y, gt=root / img / "cameras.txt",
                                 K=root / img / K, reference=False, quiet=True)).read_text())
        med = {k: v["references"]["truth"]["median_deg"] for k, v in m["methods"].items()}
        out[tag] = {"median_deg": med, "mean_of_medians_deg": float(np.mean(list(med.values()))),
                    "distortion": m["intrinsics"]["distortion"]}
    base = out["undistorted (k1 = 0, same resampling)"]["mean_of_medians_deg"]
    for tag, r in out.items():
        r["ratio_to_undistorted"] = r["mean_of_medians_deg"] / base
        print(f"lens  {tag:42s} {({k: round(v, 4) for k, v in r['median_deg'].items()})}  mean of medians "
              f"{r['mean_of_medians_deg']:.4f}° ({r['ratio_to_undistorted']:.2f}×)", flush=True)
    return out


# ------------------------------------------------------------ lens off the centre
#: (seed, k1, lens centre from the image centre (px), views, arc (degrees)): 12 views on an 80° arc, and fewer
#: views on narrower arcs (like fountain-P11's 11 frontal views), where a principal point is harder to determine
LENS_CENTRE = ((0, -0.08, (12.0, 9.0), 12, 80.0), (1, -0.08, (0.0, 0.0), 12, 80.0), (2, -0.05, (-20.0, 14.0), 12, 80.0),
               (3, -0.08, (0.0, 0.0), 12, 80.0), (4, -0.08, (0.0, 0.0), 12, 80.0), (5, -0.08, (8.0, -6.0), 12, 80.0),
               (0, -0.08, (10.0, -8.0), 8, 40.0), (1, -0.08, (-12.0, 10.0), 8, 40.0), (2, -0.08, (10.0, -8.0), 11, 30.0))


def lens_centre_rows(root: Path) -> list[dict]:
    """Item 4 of the docstring: the scenes of :data:`LENS_CENTRE`, each refined both ways."""
    from pipeline.run import main  # noqa: PLC0415
    from pipeline.synthetic.distort import render_distorted_scene  # noqa: PLC0415
    from pipeline.synthetic.render import SceneConfig  # noqa: PLC0415

    rows = []
    for seed, k1, off, n_views, arc in LENS_CENTRE:
        cfg = SceneConfig(width=1024, height=768, focal=900.0, noise_sigma=1.0, n_views=n_views, arc_deg=arc)
        d = root / (f"s{seed}" if (n_views, arc) == (12, 80.0) else f"s{seed}_n{n_views}_a{arc:g}")
        if not (d / "scene" / "lens.txt").exists():
            render_distorted_scene(cfg.n_views, seed, d / "scene", k1, config=cfg, principal_offset=off)
        images_only(d / "scene", d / "images")
        row: dict = {"seed": seed, "k1": k1, "principal_offset_px": list(off), "n_views": n_views, "arc_deg": arc,
                     "refined_median_deg": {}}
        for lens in ("measured", "undistorted"):
            y = d / f"{lens}.yaml"
            y.write_text(f"run:\n  plots: false\n  methods: [irls-h]\nrefine:\n  lens: {lens}\n")
            m = json.loads(Path(main(d / "images", d / "out", y, gt=d / "scene" / "cameras.txt", reference=False,
                                     quiet=True)).read_text())
            (ref,) = [k for k, v in m["methods"].items() if v.get("method") == "refine"]
            row["refined_median_deg"][lens] = m["methods"][ref]["references"]["truth"]["median_deg"]
            stats = json.loads((d / "out" / "rotations" / f"{ref}.json").read_text())["stats"]
            row[f"{lens}_principal_point_px"] = [v["px"] for v in (stats.get("principal_point") or {}).values()]
            row[f"{lens}_k1"] = [v["k1"] for v in (stats.get("radial") or {}).values()]
        row["averaged_median_deg"] = m["methods"]["irls-h-l0.5"]["references"]["truth"]["median_deg"]
        row["true_principal_point_px"] = [(cfg.width - 1) / 2 + off[0], (cfg.height - 1) / 2 + off[1]]
        r = row["refined_median_deg"]
        print(f"lens-centre {n_views} views, {arc:g}° arc, seed {seed}, k1 {k1:+.2f}, offset {off}: refined "
              f"measured {r['measured']:.4f}°, undistorted {r['undistorted']:.4f}° "
              f"(averaged {row['averaged_median_deg']:.4f}°)", flush=True)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", default="", help="comma-separated subset: fountain,castle,temple,nees,lens,lens-centre")
    ap.add_argument("--modes", default=",".join(MODES), help=f"two_view_ba.refine_focal modes of the scene runs "
                    f"({', '.join(MODES)}; 'none' is the default config and always runs first)")
    ap.add_argument("--min-keypoints", type=int, default=None, help="features.min_keypoints of the scene runs "
                    "(default: the config's; 0 turns the low-texture re-detection off)")
    ap.add_argument("--draws", type=int, default=500, help="NEES draws per configuration")
    ap.add_argument("--keep", type=Path, default=None, help="keep the run folders here (default: a temp folder)")
    ap.add_argument("--data", type=Path, default=DATA, help=f"the shared data folder (default {DATA})")
    ap.add_argument("--results", type=Path, default=RESULTS, help=f"the JSON written (default {RESULTS})")
    a = ap.parse_args(argv)
    only = set(filter(None, a.only.split(","))) or {"fountain", "castle", "temple", "nees", "lens"}
    root = a.keep or Path(tempfile.mkdtemp(prefix="bench_intrinsics_"))
    if a.keep is None:  # a temp folder of runs is removed at exit (--keep keeps them)
        atexit.register(shutil.rmtree, root, True)
    res = json.loads(a.results.read_text()) if a.results.exists() else {}
    res.setdefault("scenes", {})
    for name, (images, gt, K) in _scenes(a.data).items():
        if name.split("-")[0] in only or name in only:
            modes = ("none", *[m for m in a.modes.split(",") if m in MODES and m != "none"])
            rows = scene_rows(name, images, gt, K, root, modes, a.min_keypoints)
            res["scenes"][name] = res["scenes"].get(name, {}) | rows
            write_json(a.results, res)
    if "nees" in only:
        res["nees"] = nees_rows(a.draws)
        write_json(a.results, res)
    if "lens" in only:
        res["lens"] = lens_rows(root / "lens")
        write_json(a.results, res)
    if "lens-centre" in only:
        res["lens_centre"] = lens_centre_rows(root / "lens-centre")
        write_json(a.results, res)
    print(f"results: {a.results}" + (f"  (runs in {root})" if a.keep else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
