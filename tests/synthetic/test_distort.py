"""Scenes rendered through a radially distorting lens (pipeline.synthetic.distort)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.frontend.distortion import CameraModel, read_camera_models, undistort_points
from pipeline.frontend.intrinsics import read_intrinsics
from pipeline.reference.truth import read_reference
from pipeline.synthetic.distort import render_distorted_scene
from pipeline.synthetic.render import SceneConfig, render_scene

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=120.0)


def _warp_error(distorted: np.ndarray, pinhole: np.ndarray, lens: CameraModel, k1_factor: float = 1.0,
                margin: int = 16) -> float:
    """Mean grey-level difference, over the image's interior, between the distorted render and the pinhole render
    warped through ``lens`` (its k1 times ``k1_factor``): each distorted pixel sampled where the lens took it from."""
    import cv2

    lens = CameraModel(lens.model, lens.width, lens.height, tuple(lens.params[:3]) + (lens.params[3] * k1_factor,))
    h, w = distorted.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    xu = undistort_points(lens, np.column_stack([xx.ravel(), yy.ravel()]))
    mx, my = xu[:, 0].reshape(h, w).astype(np.float32), xu[:, 1].reshape(h, w).astype(np.float32)
    warped = cv2.remap(pinhole.astype(np.float32), mx, my, cv2.INTER_LINEAR)
    inside = (mx > margin) & (mx < w - 1 - margin) & (my > margin) & (my < h - 1 - margin)
    inside[:margin], inside[-margin:], inside[:, :margin], inside[:, -margin:] = False, False, False, False
    return float(np.abs(warped - distorted.astype(np.float32))[inside].mean())


def _is_the_lens(distorted: np.ndarray, pinhole: np.ndarray, lens: CameraModel) -> None:
    """The distorted render is the pinhole one warped by ``lens``, to a resampling's difference (the plain render
    against itself re-rendered: under 6 grey levels), and clearly better than by a lens 20% weaker or stronger."""
    err = _warp_error(distorted, pinhole, lens)
    assert err < 3.0, err
    for f in (0.8, 1.2):
        assert _warp_error(distorted, pinhole, lens, f) > 1.5 * err, f


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
    _is_the_lens(d.images[0], u.images[0], lens)  # a pinhole pixel x_u appears at distort(x_u) in the distorted image
    assert np.abs(d.images[0].astype(float) - u.images[0].astype(float)).mean() > 10.0  # not the same picture


def test_a_lens_that_folds_the_image_is_refused(tmp_path) -> None:
    with pytest.raises(PipelineError, match="folds the image"):
        render_distorted_scene(2, 0, tmp_path / "x", -0.9, config=CFG)


def test_several_cameras_each_with_its_own_lens(tmp_path) -> None:
    """pipeline.synthetic.mixed with k1_range: each view its own SIMPLE_RADIAL lens, written per view; view 0 (whose
    focal is drawn before its k1) is the lens-free view warped by its own lens."""
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
    _is_the_lens(a_img, b_img, lens)
    assert np.abs(a_img - b_img).mean() > 10.0  # not the same picture
