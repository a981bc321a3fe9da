"""A COLMAP database through ``run.py --database`` against our image path, on Strecha fountain-P11 (issue 16).

The database is what a user of pycolmap would bring: ``pycolmap.extract_features``
(the known K given: camera model PINHOLE with the true K, one camera for all
images; every other option pycolmap's default) and ``pycolmap.match_exhaustive``
(defaults: ratio test, cross check, geometric verification), on the images of
``../shared/data/strecha/fountain-P11``. It then goes through

- ``python run.py IMAGES --database DB --gt gt_dense_cameras --no-reference``:
  the database's cameras, keypoints and verified inlier matches, then our RANSAC,
  two-view BA (H) and averaging;
- ``python run.py IMAGES --K IMAGES/K.txt --gt gt_dense_cameras --no-reference``:
  our own SIFT and matching,

in the same run, and the median rotation error against the truth of each
averaging method is compared (target: database ≤ 1.5 × image path).

    OMP_WAIT_POLICY=PASSIVE python benchmarks/database.py [--work DIR] [--keep]

Writes ``benchmarks/results/database.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before pycolmap: its OpenMP threads busy-wait otherwise

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline import run  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.frontend.intrinsics import parse_intrinsics_file  # noqa: E402
from pipeline.reference.database import pinhole_params  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# ../shared/data beside the checkout (a worktree under wt/ has it two levels up)
DATA = next((d / "shared" / "data" / "strecha" / "fountain-P11" for d in REPO.parents[:2]
             if (d / "shared" / "data").is_dir()), REPO.parent / "shared" / "data" / "strecha" / "fountain-P11")
RESULTS = REPO / "benchmarks" / "results" / "database.json"


def make_database(db: Path, images: Path, K: np.ndarray) -> dict:
    """pycolmap.extract_features + match_exhaustive with the known K (PINHOLE, one camera); timings."""
    import pycolmap  # noqa: PLC0415

    db.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in pinhole_params(K))
    t0 = time.perf_counter()
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    t2 = time.perf_counter()
    return {"extract_s": t1 - t0, "match_s": t2 - t1, "camera_params": reader.camera_params}


def medians(metrics: Path) -> dict[str, float]:
    m = json.loads(metrics.read_text())
    out = {}
    for label, s in m["methods"].items():
        truth = s.get("references", {}).get("truth", {})
        out[label] = float(truth.get("median_deg", s.get("median_deg")))
    return out


def run_case(out: Path, **kw: object) -> tuple[dict[str, float], dict, float]:
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    metrics = run.main(DATA / "images", out, gt=DATA / "gt_dense_cameras", reference=False, quiet=True,
                       **kw)  # type: ignore[arg-type]
    wall = time.perf_counter() - t0
    m = json.loads(Path(metrics).read_text())
    return medians(Path(metrics)), {"n_edges": m["input"]["n_edges"], "n_cameras": m["input"]["n_cameras_graph"],
                                    "stages_s": m["stages"]}, wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=REPO / "out" / "bench-database", help="scratch folder")
    ap.add_argument("--keep", action="store_true", help="keep the scratch folder")
    ap.add_argument("--out", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"skipping: {DATA} not found")
        return 0
    a.work.mkdir(parents=True, exist_ok=True)
    K = parse_intrinsics_file(DATA / "images" / "K.txt")
    db = a.work / "database.db"
    made = make_database(db, DATA / "images", np.asarray(K))
    print(f"database: extract {made['extract_s']:.1f} s, match {made['match_s']:.1f} s", flush=True)
    med_db, info_db, wall_db = run_case(a.work / "from-database", database=db)
    med_im, info_im, wall_im = run_case(a.work / "from-images", K=DATA / "images" / "K.txt")
    rows = {}
    print(f"\n{'method':<16} {'database median°':>17} {'images median°':>15} {'ratio':>7}")
    for label in med_im:
        if label in med_db:
            ratio = med_db[label] / med_im[label] if med_im[label] > 0 else float("inf")
            rows[label] = {"database_median_deg": med_db[label], "images_median_deg": med_im[label], "ratio": ratio}
            print(f"{label:<16} {med_db[label]:17.4f} {med_im[label]:15.4f} {ratio:7.2f}")
    out = {"data": str(DATA), "database": made, "from_database": {**info_db, "wall_s": wall_db},
           "from_images": {**info_im, "wall_s": wall_im}, "methods": rows,
           "max_ratio": max(r["ratio"] for r in rows.values()), "target_ratio": 1.5}
    print(f"worst ratio database / images: {out['max_ratio']:.2f} (target <= 1.5); edges {info_db['n_edges']} vs "
          f"{info_im['n_edges']}; wall {wall_db:.1f} s vs {wall_im:.1f} s")
    write_json(a.out, out)
    print(f"wrote {a.out}")
    if not a.keep:
        shutil.rmtree(a.work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
