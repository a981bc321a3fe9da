"""Two-view geometry: accuracy on rendered pairs and synthetic points, degeneracy flags, ViewGraph output, resume."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from pipeline import features, matching, two_view
from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.synthetic.render import SceneConfig, essential_from_Rt, render_scene
from pipeline.two_view import TwoViewConfig, estimate_pair, load_two_view

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)


def _deg(Ra, Rb):
    return float(np.degrees(so3.angle_between(Ra, Rb)))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    scene = render_scene(n_views=4, seed=5, out=tmp_path_factory.mktemp("scene"), config=CFG)
    w = tmp_path_factory.mktemp("work")
    features.main(scene.out, w, progress=False)
    matching.main(w, progress=False)
    two_view.main(w, progress=False)
    return scene, w


def _project(K, R, t, X, rng=None, sigma=0.0):
    x = (X @ R.T + t) @ K.T
    x = x[:, :2] / x[:, 2:]
    return x + (rng.normal(0, sigma, x.shape) if rng is not None else 0)


def _random_pair(rng, n=300, baseline=1.0, planar=False, K_i=None, K_j=None):
    K_i = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]) if K_i is None else K_i
    K_j = K_i if K_j is None else K_j
    X = rng.uniform([-2, -1.5, 4], [2, 1.5, 8], (n, 3))
    if planar:
        X[:, 2] = 6 + 0.1 * X[:, 0]
    R_j = so3.exp(np.deg2rad(np.array([3.0, -12.0, 4.0])))
    c_j = np.array([baseline, 0.1 * baseline, 0.0])
    t_j = -R_j @ c_j
    x_i = _project(K_i, np.eye(3), np.zeros(3), X, rng, 0.3)
    x_j = _project(K_j, R_j, t_j, X, rng, 0.3)
    return x_i, x_j, K_i, K_j, R_j, t_j


def test_rendered_pair_essential_matrix_agrees_with_truth(work):
    scene, w = work
    d = load_two_view(w)
    k = int(np.flatnonzero((d.vg.edges[:, 0] == 0) & (d.vg.edges[:, 1] == 2))[0])
    R_true, t_true = scene.relative_pose(0, 2)
    R, t = d.vg.R_rel[k], d.vg.stats["t"][k]
    assert _deg(R, R_true) < 0.3
    assert np.degrees(np.arccos(np.clip(t @ t_true, -1, 1))) < 2.0
    E_true, E = essential_from_Rt(R_true, t_true), essential_from_Rt(R, t)
    E_true, E = E_true / np.linalg.norm(E_true), E / np.linalg.norm(E)
    assert min(np.linalg.norm(E - E_true), np.linalg.norm(E + E_true)) < 0.02
    # the stored inlier correspondences satisfy the true epipolar constraint to sub-pixel
    x_i, x_j = d.correspondences(k)
    y_i = np.column_stack([x_i, np.ones(len(x_i))]) @ np.linalg.inv(scene.K[0]).T
    y_j = np.column_stack([x_j, np.ones(len(x_j))]) @ np.linalg.inv(scene.K[2]).T
    Ex, Etx = y_i @ E_true.T, y_j @ E_true
    s = np.abs(np.sum(y_j * Ex, 1)) / np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2)
    assert np.median(s * scene.K[0][0, 0]) < 0.5 and len(x_i) == d.vg.inliers[k]


@pytest.mark.slow
def test_rendered_12_view_ring_median_error(tmp_path):
    """Acceptance (issue 5) at reduced size: RANSAC alone, median relative-rotation error ≤ 0.3°."""
    cfg = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=120.0)
    scene = render_scene(n_views=12, seed=0, out=tmp_path / "scene", config=cfg)
    w = tmp_path / "w"
    features.main(scene.out, w, progress=False)
    matching.main(w, progress=False)
    two_view.main(w, progress=False)
    d = load_two_view(w)
    vg = d.vg
    assert vg.n_edges >= 60  # nearly all 66 pairs of the ring overlap and are accepted
    R_true = np.einsum("mij,mkj->mik", scene.R[vg.edges[:, 1]], scene.R[vg.edges[:, 0]])
    err = np.degrees(so3.angle_between(vg.R_rel, R_true))
    assert np.median(err) < 0.3


def test_viewgraph_convention_and_contents(work):
    scene, w = work
    d = load_two_view(w)
    vg = d.vg
    assert vg.names == scene.names and vg.n_edges == 6 and not d.rejected
    R_true = np.einsum("mij,mkj->mik", scene.R[vg.edges[:, 1]], scene.R[vg.edges[:, 0]])  # R_j R_iᵀ
    err = np.degrees(so3.angle_between(vg.R_rel, R_true))
    assert np.median(err) < 0.3 and err.max() < 1.0
    assert vg.stats["t"].shape == (6, 3)
    np.testing.assert_allclose(np.linalg.norm(vg.stats["t"], axis=1), 1.0, atol=1e-9)
    for key in ("n_matches", "degenerate", "small_baseline", "planar", "median_triangulation_deg"):
        assert vg.stats[key].shape == (6,)
    assert np.all(vg.inliers <= vg.stats["n_matches"])
    np.testing.assert_allclose(d.K, scene.K)
    with pytest.raises(IndexError, match="out of range"):
        d.correspondences(6)


def test_resume_skips_finished_work(work):
    _, w = work
    p1 = two_view.main(w, progress=False)
    assert json.loads((w / "two_view.json").read_text())["n_computed"] == 0
    p2 = two_view.main(w, overwrite=True, progress=False)
    assert json.loads((w / "two_view.json").read_text())["n_computed"] == 6 and p1 == p2
    p3 = two_view.main(w, TwoViewConfig(threshold_px=2.0), progress=False)
    assert p3 != p1 and json.loads((w / "two_view.json").read_text())["n_computed"] == 6


@pytest.mark.parametrize("method", ["magsac", "ransac"])
def test_synthetic_points_accuracy(method):
    rng = np.random.default_rng(0)
    x_i, x_j, K_i, K_j, R_j, t_j = _random_pair(rng)
    g = estimate_pair(x_i, x_j, K_i, K_j, TwoViewConfig(method=method))
    assert g.ok and _deg(g.R, R_j) < 0.2
    assert np.degrees(np.arccos(g.t @ (t_j / np.linalg.norm(t_j)))) < 2.0
    assert not g.small_baseline and not g.planar


def test_different_intrinsics_per_image():
    rng = np.random.default_rng(1)
    K_j = np.array([[900.0, 0, 500], [0, 880, 380], [0, 0, 1]])
    x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, K_j=K_j)
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert g.ok and _deg(g.R, R_j) < 0.2
    # the same matches with the wrong K for image j give a visibly worse rotation
    g_wrong = estimate_pair(x_i, x_j, K_i, K_i)
    assert not g_wrong.ok or _deg(g_wrong.R, R_j) > 1.0


def test_outliers_are_rejected():
    rng = np.random.default_rng(2)
    x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, n=400)
    bad = rng.random(400) < 0.4
    x_j[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert g.ok and _deg(g.R, R_j) < 0.3
    assert np.mean(g.inlier_mask[bad]) < 0.05 and np.mean(g.inlier_mask[~bad]) > 0.9


def test_zero_baseline_is_flagged_and_rotation_recovered():
    rng = np.random.default_rng(3)
    x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, baseline=0.0)
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert g.ok and g.small_baseline and _deg(g.R, R_j) < 0.2
    np.testing.assert_array_equal(g.t, 0)


def test_small_baseline_is_flagged():
    rng = np.random.default_rng(4)
    x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, baseline=0.05)
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert g.ok and g.small_baseline and g.median_triangulation_deg < 1.0


def test_dominant_plane_is_flagged():
    rng = np.random.default_rng(5)
    x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, planar=True)
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert g.planar
    g2 = estimate_pair(*_random_pair(np.random.default_rng(5))[:4])
    assert not g2.planar


def test_too_few_matches_rejected_with_reason():
    rng = np.random.default_rng(6)
    x_i, x_j, K_i, K_j, _, _ = _random_pair(rng, n=12)
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert not g.ok and "too few matches (12 < min_matches=20)" in g.reason
    x_i, x_j, K_i, K_j, _, _ = _random_pair(rng, n=60)
    x_j = rng.uniform([0, 0], [640, 480], x_j.shape)  # pure noise
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert not g.ok and "too few" in g.reason


def test_config_and_input_validation():
    with pytest.raises(ValueError, match="method"):
        TwoViewConfig(method="lmeds")
    with pytest.raises(ValueError, match="threshold_px"):
        TwoViewConfig(threshold_px=0)
    with pytest.raises(ValueError, match="confidence"):
        TwoViewConfig(confidence=1.0)
    with pytest.raises(ValueError, match="two \\(n, 2\\) arrays"):
        estimate_pair(np.zeros((30, 2)), np.zeros((29, 2)), np.eye(3), np.eye(3))


def test_two_view_without_matches(tmp_path):
    with pytest.raises(InputFileError, match="pipeline.features"):
        two_view.main(tmp_path, progress=False)
    with pytest.raises(InputFileError, match="pipeline.two_view"):
        load_two_view(tmp_path)


def test_cli_help():
    r = subprocess.run([sys.executable, "-m", "pipeline.two_view", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--threshold" in r.stdout
