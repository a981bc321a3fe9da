"""5-point RANSAC of one pair (estimate_pair): accuracy on synthetic points, degeneracy flags, rejects."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import ConfigError
from pipeline.geometry.ransac import TwoViewConfig, estimate_pair, iteration_cap


def _deg(Ra, Rb):
    return float(np.degrees(so3.angle_between(Ra, Rb)))


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


@pytest.mark.parametrize("method", ["poselib", "magsac", "ransac"])
def test_synthetic_points_accuracy(method):
    rng = np.random.default_rng(0)
    x_i, x_j, K_i, K_j, R_j, t_j = _random_pair(rng)
    g = estimate_pair(x_i, x_j, K_i, K_j, TwoViewConfig(method=method))
    assert g.ok and _deg(g.R, R_j) < 0.2
    assert np.degrees(np.arccos(g.t @ (t_j / np.linalg.norm(t_j)))) < 2.0
    assert not g.small_baseline and not g.planar


def test_iteration_cap_finds_a_pair_with_min_inliers_at_the_confidence():
    cfg = TwoViewConfig()
    for n in (12, 20, 30, 36, 60):
        k = iteration_cap(n, cfg)
        w = cfg.min_inliers / n
        if k < cfg.max_iterations:  # the chance of never drawing an all-inlier sample is within 1 - confidence
            assert (1 - w ** 5) ** k <= 1 - cfg.confidence < (1 - w ** 5) ** (k - 1)
    assert iteration_cap(12, cfg) == 1 and iteration_cap(1000, cfg) == cfg.max_iterations
    assert [iteration_cap(n, cfg) for n in (20, 30, 40)] == sorted(iteration_cap(n, cfg) for n in (20, 30, 40))
    # a pair whose only support is min_inliers true matches among random ones is still found (seeds 0-19)
    rng = np.random.default_rng(7)
    found = 0
    for seed in range(20):
        x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, n=30)
        bad = np.arange(30) >= 14  # 14 true matches, 16 random: just above min_inliers
        x_j[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
        g = estimate_pair(x_i, x_j, K_i, K_j, TwoViewConfig(seed=seed))
        found += g.ok and _deg(g.R, R_j) < 1.0
    assert found >= 19, found


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
    x_i, x_j, K_i, K_j, _, _ = _random_pair(rng, n=10)
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert not g.ok and "too few matches (10 < min_matches=12)" in g.reason
    x_i, x_j, K_i, K_j, _, _ = _random_pair(rng, n=60)
    x_j = rng.uniform([0, 0], [640, 480], x_j.shape)  # pure noise
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert not g.ok and "too few" in g.reason


def _with_static(rng, n_static):
    """A true pair plus n_static matches that did not move (a static object: x_j = x_i + 0.2 px noise)."""
    x_i, x_j, K_i, K_j, R_j, _ = _random_pair(rng, n=200)
    s = rng.uniform([50, 50], [590, 430], (n_static, 2))
    return (np.vstack([x_i, s]), np.vstack([x_j, s + rng.normal(0, 0.2, s.shape)]), K_i, K_j, R_j)


def test_zero_motion_matches_are_removed_and_the_motion_estimated():
    rng = np.random.default_rng(8)
    x_i, x_j, K_i, K_j, R_j = _with_static(rng, 600)  # the static object dominates: rotation I explains it
    plain = estimate_pair(x_i, x_j, K_i, K_j, TwoViewConfig(static_px=0))
    assert plain.ok and _deg(plain.R, np.eye(3)) < 0.5 and _deg(plain.R, R_j) > 10  # the wrong, static model
    g = estimate_pair(x_i, x_j, K_i, K_j)
    assert g.ok and g.n_static == 600 and g.n_matches == 200 and _deg(g.R, R_j) < 0.3
    assert g.inlier_mask.shape == (800,) and not g.inlier_mask[200:].any() and g.inlier_mask[:200].mean() > 0.9
    x_i, x_j, K_i, K_j, R_j = _with_static(rng, 100)  # a minority of static matches changes nothing
    assert estimate_pair(x_i, x_j, K_i, K_j).n_static == 0


def test_a_pair_with_no_image_motion_is_rejected():
    rng = np.random.default_rng(9)
    s = rng.uniform([50, 50], [590, 430], (300, 2))
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    g = estimate_pair(s, s + rng.normal(0, 0.2, s.shape), K, K)
    assert not g.ok and g.reason.startswith("no image motion: 300 of 300 matches did not move")


def test_config_and_input_validation():
    with pytest.raises(ConfigError, match="method"):
        TwoViewConfig(method="lmeds")
    with pytest.raises(ConfigError, match="threshold_px"):
        TwoViewConfig(threshold_px=0)
    with pytest.raises(ConfigError, match="confidence"):
        TwoViewConfig(confidence=1.0)
    with pytest.raises(ConfigError, match="min_inliers=4 but expected >= 5"):
        TwoViewConfig(min_inliers=4)
    with pytest.raises(ConfigError, match="refine='no'"):
        TwoViewConfig(refine="no")
    assert TwoViewConfig(workers=1, chunk_size=1, progress=False).fingerprint() == TwoViewConfig().fingerprint()
    with pytest.raises(ValueError, match="two \\(n, 2\\) arrays"):
        estimate_pair(np.zeros((30, 2)), np.zeros((29, 2)), np.eye(3), np.eye(3))
