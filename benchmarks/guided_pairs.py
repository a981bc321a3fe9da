"""Guided matching pair by pair against the truth: every matched pair of a finished WORK folder estimated
without and with ``two_view.guided``, its rotation error, what guided matching did and what it cost.

    python benchmarks/guided_pairs.py --work OUT/work --gt CAMERAS [--scene SCENE_DIR] [--limit N]

``--scene`` (a rendered scene's folder) names the truly overlapping pairs from its ``scene.json``;
otherwise a pair "overlaps" when its optical axes are within 60°. Prints one row per pair that is
true or accepted either way, and the counts: true pairs within 5° without / with, pairs > 5° without / with.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pipeline.core import so3
from pipeline.evaluation.compare import match_reference
from pipeline.frontend.camera_stage import cameras_for
from pipeline.frontend.feature_stage import load_features
from pipeline.frontend.matching import root_sift
from pipeline.frontend.matching_stage import load_matches
from pipeline.geometry.guided import estimate_pair_guided
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.reference.truth import read_reference


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, required=True, help="a WORK folder with features, matches and cameras")
    p.add_argument("--gt", type=Path, required=True, help="true cameras")
    p.add_argument("--scene", type=Path, default=None, help="rendered scene folder (its scene.json: true pairs)")
    p.add_argument("--limit", type=int, default=0, help="only the first N pairs (0: all)")
    a = p.parse_args()
    fs, ms = load_features(a.work), load_matches(a.work)
    K = cameras_for(a.work, fs.names).K
    truth = read_reference(a.gt)
    R, _ = match_reference(fs.names, truth.names, truth.R)
    tp = {tuple(x) for x in json.loads((a.scene / "scene.json").read_text())["true_pairs"]} if a.scene else None
    q = [root_sift(d) for d in fs.descriptors]
    off, on = TwoViewConfig(), TwoViewConfig(guided=True)
    rows, t_on = [], []
    pairs = list(zip(ms.pairs.tolist(), ms.matches))[: a.limit or None]
    for (i, j), m in pairs:
        R_true = R[j] @ R[i].T
        ax = float(np.degrees(np.arccos(np.clip(R[i][2] @ R[j][2], -1, 1))))
        true = (i, j) in tp if tp is not None else ax <= 60
        g0, _, _ = estimate_pair_guided(fs.keypoints[i], q[i], fs.keypoints[j], q[j], m, K[i], K[j], off)
        t0 = time.perf_counter()
        g1, _, how = estimate_pair_guided(fs.keypoints[i], q[i], fs.keypoints[j], q[j], m, K[i], K[j], on)
        t_on.append(time.perf_counter() - t0)
        e0 = float(np.degrees(so3.angle_between(g0.R, R_true))) if g0.ok else np.nan
        e1 = float(np.degrees(so3.angle_between(g1.R, R_true))) if g1.ok else np.nan
        rows.append((true, g0.ok, e0, g1.ok, e1))
        if true or g0.ok or g1.ok:
            print(f"{i:3d} {j:3d} {'true ' if true else 'other'} axes {ax:5.1f}° matches {len(m):4d} | off: "
                  f"{g0.n_inliers:4d} inliers {e0:6.2f}° | on: {g1.n_inliers:4d} inliers {e1:6.2f}° | harvest "
                  f"{how.n_harvest:4d} chance {how.n_null:4d} p {how.p_value:.1e} {'used' if how.used else how.reason}"
                  f" | {t_on[-1]:.1f} s", flush=True)
    r = np.array([(t, o0, e0 <= 5, o1, e1 <= 5) for t, o0, e0, o1, e1 in rows], bool)
    print(f"true pairs {int(r[:, 0].sum())}: within 5° off {int((r[:, 0] & r[:, 1] & r[:, 2]).sum())}, "
          f"on {int((r[:, 0] & r[:, 3] & r[:, 4]).sum())}; estimated > 5° off {int((r[:, 1] & ~r[:, 2]).sum())}, "
          f"on {int((r[:, 3] & ~r[:, 4]).sum())}; guided time per pair median {np.median(t_on):.2f} s, "
          f"max {np.max(t_on):.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
