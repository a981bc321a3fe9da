"""Front-end benchmark: our features + matching + RANSAC vs pycolmap, in the same run.

For each data set (Strecha fountain-P11, Middlebury templeSparseRing, a rendered
12-view scene), the same images at the same maximum image size (1600 px) go
through

- ours: ``pipeline.features`` (OpenCV SIFT, 8192 keypoints) + ``pipeline.matching``
  + ``pipeline.two_view`` (5-point MAGSAC + refinement), fresh WORK folder;
- pycolmap: ``extract_features`` (COLMAP SIFT, 8192 keypoints, CPU) +
  ``match_exhaustive`` (CPU brute force, ratio 0.8, cross check, geometric
  verification with relative pose), fresh database, the same pinhole K.

Reported: wall time per stage, the ratio ours / pycolmap (target ≤ 1.0), and the
relative-rotation error of the accepted pairs against the reference cameras
(paper 1, Table 2 statistics) for both. Also measured: the nearest-neighbour
search options (FLANN, BLAS brute force, OpenCV BFMatcher) on one 8192-keypoint
pair, 1 vs 2 matching threads, and the renderer's time per 640×480 view.

    python benchmarks/frontend.py [--quick] [--repeats N]

``--quick``: temple and the rendered scene only, one repeat. Writes
``benchmarks/results/frontend.json``; data sets not measured in this run keep their
earlier entry (each entry records when it was measured and with how many repeats). OMP_WAIT_POLICY=PASSIVE is set before
pycolmap is imported (its OpenMP threads otherwise busy-wait on 2 cores).
"""

from __future__ import annotations

import os

os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

import argparse  # noqa: E402
import logging  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

import pycolmap  # noqa: E402

from pipeline import features, matching  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.evaluation.metrics import edge_stats  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.geometry.two_view_stage import TwoViewConfig, TwoViewStage, load_two_view  # noqa: E402

DATA = REPO.parent / "shared" / "data"
MAX_SIZE = 1600
MAX_KP = 8192


def datasets(quick: bool, tmp: Path) -> list[dict]:
    out = []
    if not quick:
        d = DATA / "strecha" / "fountain-P11"
        out.append(dict(name="fountain-P11", images=d / "images", K=d / "images" / "K.txt", ref=d / "gt_dense_cameras"))
    d = DATA / "middlebury-templeSparseRing"
    out.append(dict(name="templeSparseRing", images=d, K=d / "templeSR_par.txt", ref=d / "templeSR_par.txt"))
    from pipeline.synthetic.render import render_scene

    from pipeline.synthetic.render import SceneConfig, make_planes, render_view

    t0 = time.perf_counter()
    scene = render_scene(n_views=12, seed=0, out=tmp / "scene")
    render_s = time.perf_counter() - t0
    # the view itself (warps + z-buffer), without texture generation and PNG writing
    cfg = SceneConfig()
    t0 = time.perf_counter()
    planes = make_planes(0, cfg.texture_px_per_unit)
    texture_s = time.perf_counter() - t0
    per_view = []
    for i in range(12):
        t0 = time.perf_counter()
        render_view(planes, scene.K[i], scene.R[i], scene.t[i], cfg.width, cfg.height, cfg.supersample)
        per_view.append(time.perf_counter() - t0)
    out.append(dict(name="rendered-12", images=tmp / "scene", K=tmp / "scene" / "cameras.txt",
                    ref=tmp / "scene" / "cameras.txt", render_s_per_view=render_s / 12,
                    render_view_only_median_s=float(np.median(per_view)), render_view_only_max_s=float(np.max(per_view)),
                    texture_generation_s=texture_s))
    return [d for d in out if Path(d["images"]).is_dir()]


def run_ours(ds: dict, work: Path) -> dict:
    t = {}
    t0 = time.perf_counter()
    features.main(ds["images"], work, features.FeatureConfig(max_image_size=MAX_SIZE, max_keypoints=MAX_KP),
                  K_path=ds["K"], overwrite=True, progress=False)
    t["features_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    matching.main(work, overwrite=True, progress=False)
    t["matching_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    TwoViewStage(work, TwoViewConfig(progress=False)).run(overwrite=True)
    t["two_view_s"] = time.perf_counter() - t0
    t["total_s"] = t["features_s"] + t["matching_s"] + t["two_view_s"]
    t["vg"] = load_two_view(work).vg
    return t


def run_pycolmap(ds: dict, db_dir: Path, K: np.ndarray) -> dict:
    db = db_dir / "database.db"
    if db.exists():
        db.unlink()
    names = sorted(p.name for p in Path(ds["images"]).iterdir() if p.suffix.lower() in (".jpg", ".png"))
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = MAX_SIZE
    ext.num_threads = 2
    ext.sift.max_num_features = MAX_KP
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
    t = {}
    t0 = time.perf_counter()
    pycolmap.extract_features(db, ds["images"], image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    t["features_s"] = time.perf_counter() - t0
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = 2
    vo = pycolmap.TwoViewGeometryOptions()
    vo.compute_relative_pose = True
    t0 = time.perf_counter()
    pycolmap.match_exhaustive(db, matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)
    t["matching_s"] = time.perf_counter() - t0
    t["total_s"] = t["features_s"] + t["matching_s"]
    # relative rotations of the verified pairs, as a view graph in our convention
    database = pycolmap.Database.open(str(db)) if hasattr(pycolmap.Database, "open") else pycolmap.Database(str(db))
    try:
        id_to_name = {im.image_id: im.name for im in database.read_all_images()}
        pair_ids, geoms = database.read_two_view_geometries()
    finally:
        database.close()
    names_sorted = sorted(id_to_name.values())
    index = {n: k for k, n in enumerate(names_sorted)}
    edges, Rs, n_in = [], [], []
    for pid, g in zip(pair_ids, geoms):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        C = pycolmap.TwoViewGeometryConfiguration
        if len(g.inlier_matches) < 15 or g.config not in (C.CALIBRATED, C.PLANAR, C.PANORAMIC, C.PLANAR_OR_PANORAMIC):
            continue
        i, j = index[id_to_name[a]], index[id_to_name[b]]
        R = np.asarray(g.cam2_from_cam1.rotation.matrix())  # cam_b from cam_a
        if i > j:
            i, j, R = j, i, R.T
        edges.append((i, j))
        Rs.append(R)
        n_in.append(len(g.inlier_matches))
    t["vg"] = ViewGraph.from_edges(names_sorted, np.array(edges).reshape(-1, 2), np.array(Rs).reshape(-1, 3, 3),
                                   inliers=np.array(n_in), allow_isolated=True) if edges else None
    return t


def accuracy(vg: ViewGraph | None, ref_path: Path) -> dict:
    if vg is None or vg.n_edges == 0:
        return {"n_edges": 0}
    ref = read_reference(ref_path)
    R_ref, mask = match_reference(vg.names, ref.names, ref.R)
    return edge_stats(vg, R_ref, mask)


def nn_search_timing(work: Path) -> dict:
    """FLANN vs brute force on the two largest keypoint sets of ``work``."""
    import cv2

    fs = features.load_features(work)
    order = np.argsort([-len(k) for k in fs.keypoints])[:2]
    qa, qb = (matching.root_sift(fs.descriptors[k]) for k in order)
    res = {"n_a": len(qa), "n_b": len(qb)}
    for name, fn in [
        ("bf_blas", lambda: matching.match_descriptors(qa, qb, matching.MatchingConfig(method="bf"))),
        ("flann_incl_2_index_builds", lambda: matching.match_descriptors(qa, qb, matching.MatchingConfig(method="flann"))),
        ("opencv_bfmatcher_knn", lambda: cv2.BFMatcher(cv2.NORM_L2).knnMatch(qa, qb, k=2)),
    ]:
        ts = []
        for _ in range(2):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        res[name + "_s"] = min(ts)
    ia, ib = matching._FlannIndex(qa, matching.MatchingConfig()), matching._FlannIndex(qb, matching.MatchingConfig())
    ia.knn(qa[:1], 1)
    ib.knn(qb[:1], 1)
    t0 = time.perf_counter()
    matching._match_prepared(qa, qb, ia, ib, matching.MatchingConfig(method="flann"))
    res["flann_prebuilt_index_s"] = time.perf_counter() - t0
    times: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(2):  # alternate, so that load changes hit both settings
        for workers in (1, 2):
            t0 = time.perf_counter()
            matching.main(work, matching.MatchingConfig(workers=workers), overwrite=True, progress=False)
            times[workers].append(time.perf_counter() - t0)
    for workers, ts in times.items():
        res[f"matching_all_pairs_workers{workers}_s"] = min(ts)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="temple + rendered scene, one repeat")
    ap.add_argument("--repeats", type=int, default=None, help="repeats per data set (median reported; default 3, quick 1)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "frontend.json")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    repeats = args.repeats or (1 if args.quick else 3)
    tmp = Path(tempfile.mkdtemp(prefix="bench-frontend-"))
    previous: dict = {}
    if args.out.is_file():  # keep the data sets this run does not measure (e.g. fountain after --quick)
        try:
            import json

            previous = json.loads(args.out.read_text()).get("datasets", {})
        except ValueError:
            previous = {}
    results: dict = {"max_image_size": MAX_SIZE, "max_keypoints": MAX_KP, "repeats": repeats, "datasets": previous,
                     "cpu_count": os.cpu_count(), "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
                     "pycolmap": pycolmap.__version__}
    try:
        for ds in datasets(args.quick, tmp):
            rows: dict = {"ours": [], "pycolmap": []}
            acc: dict = {}
            for r in range(repeats):
                work = tmp / f"work-{ds['name']}"
                o = run_ours(ds, work)
                ds["_work"] = work
                K = features.load_features(work).K[0]
                p = run_pycolmap(ds, tmp, K)
                rows["ours"].append({k: v for k, v in o.items() if k != "vg"})
                rows["pycolmap"].append({k: v for k, v in p.items() if k != "vg"})
                if r == 0:
                    acc["ours"] = accuracy(o["vg"], ds["ref"])
                    acc["ours"]["n_pairs"] = len(o["vg"].names) * (len(o["vg"].names) - 1) // 2
                    acc["pycolmap"] = accuracy(p["vg"], ds["ref"])
            med = {who: {k: float(np.median([row[k] for row in rows[who]])) for k in rows[who][0]} for who in rows}
            entry = {"median": med, "runs": rows, "ratio_total": med["ours"]["total_s"] / med["pycolmap"]["total_s"],
                     "ratio_features": med["ours"]["features_s"] / med["pycolmap"]["features_s"],
                     "ratio_matching_plus_ransac": (med["ours"]["matching_s"] + med["ours"]["two_view_s"]) / med["pycolmap"]["matching_s"],
                     "accuracy": acc}
            for key in ("render_s_per_view", "render_view_only_median_s", "render_view_only_max_s", "texture_generation_s"):
                if key in ds:
                    entry[key] = ds[key]
            entry["measured_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            entry["repeats"] = repeats
            if ds["name"] == "fountain-P11" or (args.quick and ds["name"] == "rendered-12"):
                entry["nn_search"] = nn_search_timing(ds["_work"])
            results["datasets"][ds["name"]] = entry
            write_json(args.out, results)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nfront end, max image size {MAX_SIZE}, {MAX_KP} keypoints, median of {repeats} run(s), wall seconds")
    hdr = f"{'data set':18s} {'who':9s} {'features':>9s} {'matching':>9s} {'2-view':>8s} {'total':>8s} {'ratio':>6s} {'edges':>6s} {'med err°':>9s}"
    print(hdr)
    print("-" * len(hdr))
    for name, e in results["datasets"].items():
        for who in ("ours", "pycolmap"):
            m = e["median"][who]
            a = e["accuracy"][who]
            ratio = f"{e['ratio_total']:.2f}" if who == "ours" else ""
            print(f"{name:18s} {who:9s} {m['features_s']:9.2f} {m['matching_s']:9.2f} {m.get('two_view_s', float('nan')):8.2f} "
                  f"{m['total_s']:8.2f} {ratio:>6s} {a.get('n_edges', 0):6d} {a.get('median_deg', float('nan')):9.3f}")
    for name, e in results["datasets"].items():
        if "nn_search" in e:
            print(f"\nnearest-neighbour search on one pair of {name} ({e['nn_search']['n_a']} x {e['nn_search']['n_b']} keypoints):")
            for k, v in e["nn_search"].items():
                if k.endswith("_s"):
                    print(f"  {k:40s} {v:8.3f} s")
        if "render_s_per_view" in e:
            print(f"\nrenderer: {e['render_s_per_view']:.3f} s per 640x480 view incl. textures and PNG writing; "
                  f"view only: median {e.get('render_view_only_median_s', float('nan')):.3f} s, "
                  f"max {e.get('render_view_only_max_s', float('nan')):.3f} s")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
