"""The refinement of a lens the cameras stage estimated: modelled about the principal point, on the measured keypoints.

The cameras stage estimates one radial term before any principal point is known, so it undistorts about the image
centre. A real lens is centred on the principal point, which is rarely the centre. Refined on those undistorted
keypoints, the residual is not radial about any point, and no camera model absorbs it; refined on the measured
keypoints with COLMAP's SIMPLE_RADIAL (``refine.lens: measured``), the lens and its centre are what the bundle
adjustment estimates.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.run import main
from pipeline.synthetic.distort import render_distorted_scene
from pipeline.synthetic.render import SceneConfig

K1, OFFSET = -0.12, (14.0, -10.0)
CFG = SceneConfig(width=640, height=480, focal=500.0, noise_sigma=1.0)


def _refined(out: Path, lens: str, images: Path, gt: Path) -> dict:
    cfg = out.parent / f"{lens}.yaml"
    cfg.write_text(f"run:\n  plots: false\n  methods: [irls-h]\nrefine:\n  lens: {lens}\n")
    m = json.loads(main(images, out, cfg, gt=gt, reference=False, quiet=True).read_text())
    ((label, row),) = [(k, v) for k, v in m["methods"].items() if v.get("method") == "refine"]
    return row | {"stats": json.loads((out / "rotations" / f"{label}.json").read_text())}


@pytest.mark.slow
def test_a_lens_off_the_image_centre_is_refined_about_its_principal_point(tmp_path: Path) -> None:
    scene = render_distorted_scene(10, 1, tmp_path / "scene", K1, config=CFG, principal_offset=OFFSET)
    images = tmp_path / "images"
    images.mkdir()
    for n in scene.names:  # the images alone: no K, no lens file, no EXIF
        shutil.copy(scene.out / n, images / n)
    gt = scene.out / "cameras.txt"
    measured = _refined(tmp_path / "out", "measured", images, gt)
    undistorted = _refined(tmp_path / "out", "undistorted", images, gt)  # the same front end, refined again
    err_m = measured["references"]["truth"]["median_deg"]
    err_u = undistorted["references"]["truth"]["median_deg"]
    assert measured["status"] == "ok" and undistorted["status"] == "ok"
    assert err_m < 0.5 * err_u, (err_m, err_u)
    # the lens and its centre, found by the bundle adjustment (our pixels: centres at integers)
    (pp,) = [v["px"] for v in measured["stats"]["stats"]["principal_point"].values()]
    truth_pp = np.array([(CFG.width - 1) / 2, (CFG.height - 1) / 2]) + OFFSET
    assert np.max(np.abs(np.array(pp) - truth_pp)) < 2.0, (pp, truth_pp)
    (k1,) = [v["k1"] for v in measured["stats"]["stats"]["radial"].values()]
    assert abs(k1 / K1 - 1) < 0.05, k1


def test_the_camera_model_keeps_a_measured_lens_and_refuses_one_it_cannot_hold() -> None:
    from pipeline.refine.model import camera_groups, colmap_camera

    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    assert colmap_camera(K, False) == (0, [500.0, 320.0, 240.0])  # SIMPLE_PINHOLE, COLMAP's pixels
    assert colmap_camera(K, False, radial=True) == (2, [500.0, 320.0, 240.0, 0.0])
    assert colmap_camera(K, False, radial=False, k1=-0.1) == (2, [500.0, 320.0, 240.0, -0.1])  # held, not dropped
    with pytest.raises(ValueError, match="radial term"):
        colmap_camera(K, True, k1=-0.1)  # a known camera is PINHOLE: its keypoints are undistorted already
    # two images of one K but different lenses are two cameras
    ids, first = camera_groups(np.stack([K, K, K]), np.array([[640, 480]] * 3), np.zeros(3, bool),
                               np.array([0.0, -0.1, 0.0]))
    assert ids[0] == ids[2] != ids[1] and len(first) == 2


def test_a_radial_term_for_a_known_camera_is_refused() -> None:
    from pipeline.refine.refine import refine_rotations

    K = np.array([[[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]] * 2)
    with pytest.raises(ValueError, match="K is known"):
        refine_rotations(["a", "b"], K, np.array([[640, 480]] * 2), [np.zeros((0, 2))] * 2, np.zeros((0, 2), int),
                         np.zeros(1, int), np.zeros((0, 2), int), np.zeros((0, 3, 3)), np.zeros((0, 3)),
                         np.stack([np.eye(3)] * 2), known_K=True, k1=np.array([0.0, -0.1]))
