"""The low-texture turntable's view-dependent appearance: options off leave the images unchanged; on, the
shading varies within a facet, follows the camera, and a highlight moves with the view."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.synthetic.lowtex import LowTexConfig, dino_planes, render_lowtex, shade_planes
from pipeline.synthetic.shading import texel_shading

SMALL = dict(n_views=3, width=160, height=120, focal=155.0)
# sha256 of the three images of SMALL (seed 0), rendered by the generator before the shading options (62191c4)
BEFORE = {"world": "22bcb9a67be3a13141e788419b97a5c85c023af61ffcf960228983af93b7702c",
          "camera": "2afc0cae3a5ca8a1d72e8c152f5e689e03fd2eaa431d083bbf1b74f1c4073e7c"}


def _digest(images) -> str:
    return hashlib.sha256(b"".join(im.tobytes() for im in images)).hexdigest()


@pytest.mark.parametrize("light", ["world", "camera"])
def test_defaults_render_the_images_of_before(light):
    assert _digest(render_lowtex(LowTexConfig(light=light, **SMALL), seed=0).images) == BEFORE[light]


def test_smooth_and_specular_change_the_images_but_not_the_geometry():
    base = render_lowtex(LowTexConfig(light="camera", **SMALL), seed=0)
    new = render_lowtex(LowTexConfig(light="camera", shading="smooth", specular=60.0, **SMALL), seed=0)
    assert np.array_equal(base.R, new.R) and np.array_equal(base.true_pairs, new.true_pairs)
    diffs = []
    for a, b, da, db in zip(base.images, new.images, base.depths, new.depths):
        assert np.array_equal(da, db)  # same surfaces, same occlusions
        diffs.append(np.abs(a.astype(int) - b.astype(int))[np.isfinite(da)])
    diffs = np.concatenate(diffs)
    assert diffs.max() > 30 and np.mean(diffs > 3) > 0.05  # highlights, and shading across the facets


def _body_side(planes, k: int):
    return next(p for p in planes if p.name == f"body-s{k}")


def test_smooth_shading_varies_within_a_facet_and_flat_does_not():
    planes = dino_planes(0, body_sides=24)
    pl = _body_side(planes, 6)
    across = pl.a / np.linalg.norm(pl.a)  # the facet's columns run around the prism
    eye = pl.corners().mean(0) + 2.0 * pl.normal
    light = pl.corners().mean(0) + 2.0 * (0.5 * pl.normal + 0.866 * across)  # 60° off the facet's normal
    flat = shade_planes([pl], light, 0.2, eye=eye)[0].texture[..., 0].astype(float)
    smooth = shade_planes([pl], light, 0.2, eye=eye, smooth=True)[0].texture[..., 0].astype(float)
    alb = pl.albedo_tex
    ok = alb > 20
    ratio_flat, ratio_smooth = flat[ok] / alb[ok], smooth[ok] / alb[ok]
    assert np.ptp(ratio_flat) < 0.05  # one factor per plane (up to rounding)
    cols = (smooth / np.maximum(alb, 1)).mean(0)
    # the 15° the facet spans around the prism: n·l from about cos 67.5° to cos 52.5° across its columns
    assert np.ptp(cols) > 0.15 and np.all(np.diff(cols) > 0), cols


def test_camera_light_on_a_cylinder_is_brightest_where_it_faces_the_camera():
    """A 64-sided prism lit from the camera: the brightest side is the one facing the camera, so the
    shading moves over the surface when the camera moves (features on it are not fixed to it)."""
    planes = [p for p in dino_planes(0, body_sides=64) if p.name.startswith("body-s")]
    brightest = []
    for az in (-0.5, 0.0, 0.5):  # cameras around the body's axis (x), at distance 2
        eye = np.array([0.0, 2.0 * np.sin(az), 0.49 - 2.0 * np.cos(az)])  # below/side of the body
        lit = [texel_shading(np.full(p.albedo_tex.shape, 100.0), p.origin, p.a, p.b, p.normal, eye, eye, 0.0,
                             edge_normals=p.edge_normals).mean() for p in planes]
        facing = [float(p.normal @ (eye - p.corners().mean(0))) / np.linalg.norm(eye - p.corners().mean(0))
                  for p in planes]
        assert int(np.argmax(lit)) == int(np.argmax(facing))
        brightest.append(int(np.argmax(lit)))
    assert len(set(brightest)) == 3


def test_specular_peak_is_at_the_mirror_direction_and_moves_with_the_eye():
    alb = np.full((1, 41), 50.0)
    origin, a, b = np.array([-2.05, -0.05, 0.0]), np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.1, 0.0])
    n = np.array([0.0, 0.0, 1.0])  # the plane z = 0; texel centres at y = 0, x = -2.0, -1.9, ..., 2.0
    light = np.array([0.0, 0.0, 3.0])
    peaks = []
    for ex in (1.0, 2.0):
        eye = np.array([ex, 0.0, 3.0])
        s = texel_shading(alb, origin, a, b, n, light, eye, 0.3, smooth=False, specular=80.0, shininess=200.0)
        d = texel_shading(alb, origin, a, b, n, light, eye, 0.3, smooth=False)
        spec = (s - d)[0]
        peaks.append(origin[0] + (np.argmax(spec) + 0.5) * a[0])
        assert spec.max() == pytest.approx(80.0, rel=0.02) and spec.min() < 1.0
    assert peaks == pytest.approx([0.5, 1.0], abs=1e-9)  # the mirror point halfway between light and eye


def test_many_sides_and_validation():
    n24 = sum(p.name.startswith("body-s") for p in dino_planes(0))
    n64 = sum(p.name.startswith("body-s") for p in dino_planes(0, body_sides=64, limb_sides=32))
    assert (n24, n64) == (24, 64)
    for bad in (dict(shading="phong"), dict(body_sides=2), dict(specular=-1.0)):
        with pytest.raises(PipelineError):
            render_lowtex(LowTexConfig(**SMALL, **bad), seed=0)
    with pytest.raises(PipelineError, match="eye"):
        shade_planes(dino_planes(0)[:1], np.zeros(3), 0.3, smooth=True)
