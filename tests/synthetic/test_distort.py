"""Scenes rendered through a radially distorting lens (pipeline.synthetic.distort)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.frontend.distortion import distort_points, read_camera_models
from pipeline.frontend.intrinsics import read_intrinsics
from pipeline.reference.truth import read_reference
from pipeline.synthetic.distort import render_distorted_scene
from pipeline.synthetic.render import SceneConfig, render_scene

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=120.0)


def test_k1_zero_is_the_plain_render_and_the_files_describe_the_lens(tmp_path) -> None:
    plain = render_scene(2, 4, config=CFG)
    same = render_distorted_scene(2, 4, tmp_path / "u", 0.0, config=CFG)
    np.testing.assert_array_equal(same.R, plain.R)
    diff = np.abs(same.images[0].astype(float) - plain.images[0].astype(float))
    assert diff.mean() < 6.0  # the same view, resampled once more (2x canvas, area average)
    lens = read_camera_models(tmp_path / "u" / "lens.txt")["*"]
    assert lens.model == "SIMPLE_RADIAL" and lens.params[3] == 0.0
    np.testing.assert_allclose(read_intrinsics(tmp_path / "u" / "K.txt"), plain.K[0])
    assert read_reference(tmp_path / "u" / "cameras.txt").names == same.names


def test_distorted_view_is_the_pinhole_view_warped(tmp_path) -> None:
    d = render_distorted_scene(2, 4, tmp_path / "d", -0.2, config=CFG)
    u = render_scene(2, 4, config=CFG)
    lens = read_camera_models(tmp_path / "d" / "lens.txt")["*"]
    # a pinhole pixel x_u appears at distort(x_u) in the distorted image
    xu = np.array([[60.0, 50.0], [250.0, 190.0], [160.0, 120.0]])
    xd = np.rint(distort_points(lens, xu)).astype(int)
    a = d.images[0][xd[:, 1], xd[:, 0]].astype(float)
    b = u.images[0][np.rint(xu[:, 1]).astype(int), np.rint(xu[:, 0]).astype(int)].astype(float)
    assert np.abs(a - b).mean() < 25.0
    assert np.abs(d.images[0].astype(float) - u.images[0].astype(float)).mean() > 10.0  # not the same picture


def test_a_lens_that_folds_the_image_is_refused(tmp_path) -> None:
    with pytest.raises(PipelineError, match="folds the image"):
        render_distorted_scene(2, 0, tmp_path / "x", -0.9, config=CFG)


def test_several_cameras_each_with_its_own_lens(tmp_path) -> None:
    """pipeline.synthetic.mixed with k1_range: each view its own SIMPLE_RADIAL lens, written per view; view 0 (whose
    focal is drawn before its k1) is the lens-free view warped by its own lens."""
    from pipeline.frontend.distortion import CameraModel
    from pipeline.synthetic.mixed import render_mixed_cameras

    plain = render_mixed_cameras(tmp_path / "p", 3, seed=2, same_size=True, config=CFG)
    lensed = render_mixed_cameras(tmp_path / "l", 3, seed=2, same_size=True, config=CFG, k1_range=(-0.25, -0.15))
    k1 = np.loadtxt(tmp_path / "l" / "truth" / "k1.txt")
    rows = [r.split() for r in (tmp_path / "l" / "truth" / "lens.txt").read_text().splitlines()[1:]]
    assert len(k1) == len(rows) == 3 and np.all((k1 >= -0.25) & (k1 <= -0.15)) and len(set(k1.round(6))) == 3
    assert [r[1] for r in rows] == ["SIMPLE_RADIAL"] * 3 and np.allclose([float(r[7]) for r in rows], k1, atol=1e-6)
    np.testing.assert_allclose(lensed.K[0], plain.K[0])
    lens = CameraModel("SIMPLE_RADIAL", 320, 240, tuple(float(v) for v in rows[0][4:8]))
    img_l = (tmp_path / "l" / "images" / lensed.names[0])
    img_p = (tmp_path / "p" / "images" / plain.names[0])
    import cv2

    a_img, b_img = cv2.imread(str(img_l)).astype(float), cv2.imread(str(img_p)).astype(float)
    xu = np.array([[60.0, 50.0], [250.0, 190.0], [160.0, 120.0], [100.0, 180.0]])
    xd = np.rint(distort_points(lens, xu)).astype(int)
    a = a_img[xd[:, 1], xd[:, 0]]
    b = b_img[np.rint(xu[:, 1]).astype(int), np.rint(xu[:, 0]).astype(int)]
    assert np.abs(a - b).mean() < 25.0
    assert np.abs(a_img - b_img).mean() > 10.0  # not the same picture
