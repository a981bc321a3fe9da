"""Rendered synthetic scenes: determinism, geometry, cameras file, overlap, CLI."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pipeline.core.errors import PipelineError
from pipeline.synthetic.render import SceneConfig, essential_from_Rt, make_planes, render_scene

SMALL = SceneConfig(width=200, height=150, focal=175.0, texture_px_per_unit=120.0)


def test_same_seed_same_images_other_seed_other_images():
    a = render_scene(n_views=2, seed=3, config=SMALL, noise_sigma=1.0)
    b = render_scene(n_views=2, seed=3, config=SMALL, noise_sigma=1.0)
    c = render_scene(n_views=2, seed=4, config=SMALL, noise_sigma=1.0)
    for x, y in zip(a.images, b.images):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.R, b.R)
    assert not np.array_equal(a.images[0], c.images[0])
    assert a.images[0].shape == (150, 200, 3) and a.images[0].dtype == np.uint8


def test_scene_has_three_non_coplanar_planes():
    planes = make_planes(0, px_per_unit=40.0)
    normals = np.array([p.normal for p in planes])
    # rank 3: the planes' normals span space (ground, wall and box sides)
    assert np.linalg.matrix_rank(normals, tol=1e-6) == 3
    assert len(planes) >= 3


def test_cameras_are_rotations_and_look_at_the_scene():
    s = render_scene(n_views=4, seed=0, config=SMALL)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", s.R, s.R), np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(s.R), 1.0, atol=1e-12)
    for img in s.images:  # the background (grey 90) covers less than a third of each view
        assert np.mean(np.all(img == 90, axis=2)) < 0.33


def test_depth_maps_agree_with_projected_points():
    s = render_scene(n_views=3, seed=1, config=SMALL)
    assert len(s.points) > 200
    for i in range(3):
        x, z = s.project(i, s.points)
        h, w = s.depth[i].shape
        ok = (z > 0) & (x[:, 0] > 1) & (x[:, 0] < w - 2) & (x[:, 1] > 1) & (x[:, 1] < h - 2)
        u, v = np.round(x[ok]).astype(int).T
        rel = np.abs(s.depth[i][v, u] - z[ok]) / z[ok]
        # most sampled points are unoccluded in each view and agree with the z-buffer
        assert np.mean(rel < 0.01) > 0.5


def test_all_pairs_of_a_12_view_ring_overlap():
    cfg = SceneConfig(width=160, height=120, focal=140.0, texture_px_per_unit=60.0)
    s = render_scene(n_views=12, seed=0, config=cfg)
    vis = []
    for i in range(12):
        x, z = s.project(i, s.points)
        u = np.clip(np.round(x[:, 0]).astype(int), 0, 159)
        v = np.clip(np.round(x[:, 1]).astype(int), 0, 119)
        inside = (z > 0) & (x[:, 0] >= 0) & (x[:, 0] <= 159) & (x[:, 1] >= 0) & (x[:, 1] <= 119)
        vis.append(inside & (np.abs(s.depth[i][v, u] - z) < 0.02 * z))
    vis = np.array(vis)
    shared = (vis[:, None, :] & vis[None, :, :]).sum(-1)
    iu = np.triu_indices(12, 1)
    assert shared[iu].min() > 0.1 * vis.sum(1).min()


def test_true_essential_matrix_is_satisfied_by_true_points():
    s = render_scene(n_views=2, seed=2, config=SMALL)
    R, t = s.relative_pose(0, 1)
    E = essential_from_Rt(R, t)
    Xc0 = s.points @ s.R[0].T + s.t[0]
    Xc1 = s.points @ s.R[1].T + s.t[1]
    y0, y1 = Xc0 / Xc0[:, 2:], Xc1 / Xc1[:, 2:]
    np.testing.assert_allclose(np.einsum("ni,ij,nj->n", y1, E, y0), 0, atol=1e-9)


def test_writes_images_cameras_and_points(tmp_path):
    from pipeline.reference.truth import read_cameras_file

    s = render_scene(n_views=2, seed=0, out=tmp_path, config=SMALL, write_points=True)
    assert sorted(p.name for p in tmp_path.glob("*.png")) == s.names
    ref = read_cameras_file(tmp_path / "cameras.txt")
    assert ref.names == s.names
    np.testing.assert_allclose(ref.R, s.R, atol=1e-9)
    np.testing.assert_allclose(ref.K, s.K, atol=1e-9)
    pts = np.loadtxt(tmp_path / "points3d.txt")
    np.testing.assert_allclose(pts, s.points, rtol=1e-6, atol=1e-6)


def test_rejects_fewer_than_two_views():
    with pytest.raises(PipelineError, match="at least 2 views"):
        render_scene(n_views=1, config=SMALL)


def test_cli_run(tmp_path):  # --help: tests/test_help.py
    r = subprocess.run([sys.executable, "-m", "pipeline.synthetic.render", "--views", "2", "--seed", "5", "--out",
                        str(tmp_path), "--width", "120", "--height", "90", "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "cameras.txt").is_file() and (tmp_path / "view_001.png").is_file()
    r = subprocess.run([sys.executable, "-m", "pipeline.synthetic.render", "--views", "1", "--out", str(tmp_path)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) == 1
