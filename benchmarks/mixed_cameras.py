"""Images of several cameras without K or EXIF (issue 13, item 1): per-image focal lengths from the view graph.

Rendered scenes (``pipeline.synthetic.mixed``: each view its own focal, 0.8–1.25× the scene's, and with
``sizes: mixed`` its own image size among 7) run through ``run.py``'s ``main`` with no K and with the pycolmap
incremental reference in the same run (also without K: one camera per image). Each scene runs twice on the same
features, matches and pycolmap reference: ``cameras.per_image_focal: off`` (the group focal lengths alone, as
before) and ``auto`` (the default). Reported per run: the focal error of every image against its own (median and max |%|), each
method's median rotation error against the truth, pycolmap's, and the ratio of the refined rotations' median to
pycolmap's.

``lens`` scenes (``--kinds``) are the mixed-size scenes with each view its own lens too (SIMPLE_RADIAL k1 uniform in
``--k1``, default −0.08 … 0.04), run with the per-image focal lengths on and the refinement's radial term off and
on (``refine.radial``): photos of several cameras, each with its own distortion.

    python benchmarks/mixed_cameras.py [--seeds 0 1 2] [--views 10] [--kinds mixed same lens] [--work DIR]

Prints a table and writes ``benchmarks/results/mixed_cameras.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MPLBACKEND", "Agg")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.synthetic.mixed import render_mixed_cameras  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "mixed_cameras.json"


def run_one(scene, out: Path, per_image: str, seed_from: Path | None, radial: str = "auto") -> dict:
    from pipeline.run import main  # noqa: PLC0415

    if seed_from is not None and not out.exists():  # the same features, matches and pycolmap reference
        shutil.copytree(seed_from, out, ignore=shutil.ignore_patterns("metrics.json"))
    cfg = out.parent / f"{out.name}.yaml"
    cfg.write_text(f"run:\n  plots: false\ncameras:\n  per_image_focal: {per_image}\nrefine:\n  radial: \"{radial}\"\n")
    t0 = time.perf_counter()
    m = json.loads(Path(main(scene.images, out, cfg, gt=scene.truth / "cameras.txt", reference=True,
                             quiet=True)).read_text())
    cams = json.loads((out / "work" / "cameras.json").read_text())
    f = np.array([K[0][0] for K in cams["K"]])
    err = 100 * (f / scene.K[:, 0, 0] - 1)
    pyc = m.get("pycolmap", {})
    ref = next((v for k, v in m["methods"].items() if k.endswith("+refine")), {})
    row = {"per_image_focal": per_image, "refine_radial": radial, "wall_s": time.perf_counter() - t0,
           "refine_status": ref.get("status"), "refine_n_refined": ref.get("n_refined"),
           "focal_error_pct": err.round(3).tolist(), "focal_abs_error_pct_median": float(np.median(np.abs(err))),
           "focal_abs_error_pct_max": float(np.max(np.abs(err))), "K_source": sorted(set(cams["K_source"])),
           "per_image": {k: v for k, v in cams["estimate"].get("per_image", {}).items() if k != "calibrations"},
           "methods_median_deg": {k: v.get("median_deg") for k, v in m["methods"].items()},
           "methods_max_deg": {k: v.get("max_deg") for k, v in m["methods"].items()},
           "pycolmap_median_deg": pyc.get("median_deg"), "pycolmap_registered": pyc.get("n_registered")}
    refined = [v for k, v in row["methods_median_deg"].items() if k.endswith("+refine")]
    if refined and pyc.get("median_deg"):
        row["refined_over_pycolmap"] = refined[0] / pyc["median_deg"]
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--kinds", nargs="+", default=["mixed", "same", "lens"], choices=["mixed", "same", "lens"])
    ap.add_argument("--k1", type=float, nargs=2, default=[-0.08, 0.04], help="lens scenes: the range of k1")
    ap.add_argument("--work", type=Path, default=None, help="keep the scenes and runs here (default: a temp folder)")
    ap.add_argument("--json", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    root = a.work or Path(tempfile.mkdtemp(prefix="bench_mixed_"))
    rows = []
    try:
        for sizes in a.kinds:
            # the variants of a kind share its features, matches and pycolmap reference
            variants = [("auto", "off"), ("auto", "auto")] if sizes == "lens" else [("off", "auto"), ("auto", "auto")]
            for seed in a.seeds:
                name = f"{sizes}-s{seed}"
                scene = render_mixed_cameras(root / name / "scene", a.views, seed, same_size=sizes == "same",
                                             k1_range=tuple(a.k1) if sizes == "lens" else None)
                first = None
                for per_image, radial in variants:
                    out = root / name / f"run-{per_image}-radial-{radial}"
                    r = run_one(scene, out, per_image, first, radial) | {"scene": name, "sizes": sizes, "seed": seed}
                    first = first or out
                    rows.append(r)
                    meds = {k: round(v, 4) for k, v in r["methods_median_deg"].items() if v is not None}
                    print(f"{name:9s} per_image_focal={per_image:4s} radial={radial:4s} focal |err| median "
                          f"{r['focal_abs_error_pct_median']:6.2f}% "
                          f"max {r['focal_abs_error_pct_max']:6.2f}%  ours {meds}  pycolmap "
                          f"{r['pycolmap_median_deg']:.4f} ({r['pycolmap_registered']}/{a.views})", flush=True)
    finally:
        if a.work is None:
            shutil.rmtree(root, ignore_errors=True)
    write_json(a.json, {"argv": argv if argv is not None else sys.argv[1:], "views": a.views,
                        "k1": a.k1, "rows": rows})
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
