"""Focal length from a view graph's two-view geometry (pipeline.frontend.focal, camera_estimate.estimate_focal)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import ConfigError
from pipeline.frontend import focal as fk
from pipeline.frontend.camera_estimate import CamerasConfig, estimate_focal


def _views(n_cams: int = 6, f: float = 900.0, size=(800, 600), seed: int = 0, sigma: float = 0.5):
    """A ring of cameras around a random point cloud; every pair's matches (px) and the true rotations."""
    rng = np.random.default_rng(seed)
    w, h = size
    K = fk.K_from_focal(f, np.array([(w - 1) / 2, (h - 1) / 2]))
    X = rng.uniform([-2, -2, -2], [2, 2, 2], (1500, 3))
    R, t = [], []
    for k in range(n_cams):
        a = 2 * np.pi * k / n_cams * 0.35
        C = 9 * np.array([np.sin(a), 0.15 * rng.standard_normal(), -np.cos(a)])
        z = (rng.normal(0, 0.6, 3) - C)
        z /= np.linalg.norm(z)
        x = np.cross([0, 1, 0], z)
        x /= np.linalg.norm(x)
        Rk = np.stack([x, np.cross(z, x), z])
        R.append(Rk)
        t.append(-Rk @ C)
    proj = []
    for Rk, tk in zip(R, t):
        p = (X @ Rk.T + tk) @ K.T
        proj.append(p[:, :2] / p[:, 2:])
    x1s, x2s, pairs = [], [], []
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            ok = np.all([(q >= 0).all(1) & (q < [w, h]).all(1) for q in (proj[i], proj[j])], 0)
            x1s.append(proj[i][ok] + sigma * rng.standard_normal((ok.sum(), 2)))
            x2s.append(proj[j][ok] + sigma * rng.standard_normal((ok.sum(), 2)))
            pairs.append((i, j))
    return x1s, x2s, np.array(pairs), np.array(R), K


def test_sampson_and_profile_minimum_at_the_truth() -> None:
    x1s, x2s, pairs, R, K = _views(3, seed=1)
    pp = K[:2, 2]
    F = fk.fundamental_ransac(x1s[0], x2s[0], 2.0, seed=0)
    assert F is not None and len(F.inliers) > 0.95 * len(x1s[0])
    assert np.median(np.abs(fk.sampson_px(F.F, x1s[0], x2s[0]))) < 1.0
    grid = fk.log_grid(500, 1600, 21)
    cost, Rs, s2, _ = fk.pair_profile(x1s[0], x2s[0], F.F, pp, pp, grid, grid)
    assert abs(fk.refine_min(grid, cost) / 900 - 1) < 0.03
    g = int(np.argmin(np.abs(grid - 900)))
    assert np.degrees(so3.angle_between(Rs[g], R[1] @ R[0].T)) < 0.5
    assert 0.1 < s2 < 1.0  # Sampson distances of σ = 0.5 px noise


def test_chordal_average_recovers_consistent_rotations() -> None:
    rng = np.random.default_rng(0)
    R = so3.exp(rng.normal(size=(6, 3)))
    E = np.array([(i, j) for i in range(6) for j in range(i + 1, 6)])
    Rrel = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    Rh = fk.chordal_average(E, Rrel, 6)
    np.testing.assert_allclose(Rh[E[:, 1]] @ np.swapaxes(Rh[E[:, 0]], 1, 2), Rrel, atol=1e-8)


def test_rotation_consistency_is_lowest_where_rotations_close_the_loops() -> None:
    rng = np.random.default_rng(1)
    R = so3.exp(rng.normal(size=(5, 3)))
    E = np.array([(i, (i + 1) % 5) for i in range(5)] + [(0, 2), (1, 3)])
    E = np.sort(E, axis=1)
    true = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    w = so3.log(true)
    # grid point g scales every relative rotation angle by s_g: only s = 1 closes the loops
    scales = np.array([0.8, 0.9, 1.0, 1.1, 1.2])
    Rg = np.stack([so3.exp(w * s) for s in scales], axis=1)
    cost = fk.rotation_consistency_cost(Rg, E, 5)
    assert int(np.argmin(cost)) == 2 and cost[2] < 1e-12


def test_shared_focal_of_a_small_view_graph() -> None:
    x1s, x2s, pairs, _, _ = _views(6, f=900.0, seed=2)
    cfg = CamerasConfig(grid_points=13, refine_points=5, max_points=200, workers=1)
    est = estimate_focal(x1s, x2s, pairs, 6, (800, 600), np.full(len(pairs), 2.0), cfg)
    assert est.n_pairs == len(pairs) and est.method == "profile+rotcons"
    assert abs(est.f / 900 - 1) < 0.02, est.f
    prior = estimate_focal(x1s, x2s, pairs, 6, (800, 600), np.full(len(pairs), 2.0), cfg, prior=1000.0)
    assert abs(prior.f / 900 - 1) < 0.02 and prior.prior == "exif 1000.0 px" and not prior.note
    wrong = estimate_focal(x1s, x2s, pairs, 6, (800, 600), np.full(len(pairs), 2.0), cfg, prior=2500.0)
    assert abs(wrong.f / 900 - 1) < 0.02 and "disagrees with the EXIF focal" in wrong.note


def test_too_few_pairs_give_no_estimate() -> None:
    x1s, x2s, pairs, _, _ = _views(2, seed=3)
    est = estimate_focal(x1s, x2s, pairs, 2, (800, 600), np.full(1, 2.0), CamerasConfig(workers=1))
    assert np.isnan(est.f) and "min_pairs" in est.note


def test_poselib_method() -> None:
    x1s, x2s, pairs, _, _ = _views(5, f=900.0, seed=4)
    est = estimate_focal(x1s, x2s, pairs, 5, (800, 600), np.full(len(pairs), 2.0),
                         CamerasConfig(focal_method="poselib", workers=1))
    assert est.method == "poselib" and abs(est.f / 900 - 1) < 0.03


def test_config_checks() -> None:
    with pytest.raises(ConfigError, match="focal_range"):
        CamerasConfig(focal_range=(2.0, 1.0))
    with pytest.raises(ConfigError, match="radial_refine"):
        CamerasConfig(radial_refine=(0.05,))
    with pytest.raises(ConfigError, match="focal_method"):
        CamerasConfig(focal_method="bougnoux")  # type: ignore[arg-type]


def test_focal_jackknife_flags_a_focal_that_rests_on_one_image() -> None:
    """A complete graph of 6 views fixes f: leave-one-image-out sd under max_focal_sd (5%) and the truth within 2%. The same views
    seen only through pairs with image 0 (a star): leaving image 0 out leaves no pair, so the focal rests on it and
    is flagged, with the reason."""
    x1s, x2s, pairs, _, _ = _views(6, f=900.0, seed=2)
    cfg = CamerasConfig(grid_points=13, refine_points=5, max_points=200, workers=1)
    est = estimate_focal(x1s, x2s, pairs, 6, (800, 600), np.full(len(pairs), 2.0), cfg)
    assert est.determined and 0 < est.sd_rel < cfg.max_focal_sd and abs(est.f / 900 - 1) < 0.02, est.sd_rel
    star = np.flatnonzero(pairs[:, 0] == 0)
    est = estimate_focal([x1s[k] for k in star], [x2s[k] for k in star], pairs[star], 6, (800, 600),
                         np.full(len(star), 2.0), cfg)
    assert not est.determined and est.sd_rel == np.inf and "poorly determined" in est.note
    assert est.summary()["determined"] is False
    # no pair at all: no estimate, and the summary does not call its NaN determined
    none = estimate_focal([], [], np.zeros((0, 2), np.int64), 6, (800, 600), np.zeros(0), cfg)
    assert np.isnan(none.f) and none.summary()["determined"] is False


def test_a_finer_grid_starts_from_its_coarse_neighbours() -> None:
    """A pair's cost can have several basins; a finer grid's sweep that started only from the decomposition of
    ``K2ᵀ F K1`` could settle in a worse one than the coarse points beside it (a real pair: 411 px² above them at
    every fine point), and the joint minimum then fell on a coarse point. Here a pair's matches come from two
    motions (60% / 40%) and its F from the smaller group: started from F alone, the fine grid stays in the worse
    basin; started also from its coarse neighbours' poses (``ends``, either one) it has the good basin's costs,
    and a grid whose every point starts badly recovers backwards from the pose past its last point."""
    x1s, x2s, _, _, K = _views(3, seed=1)
    pp = K[:2, 2]
    m = len(x1s[1]) * 2 // 5
    x1, x2 = np.r_[x1s[0], x1s[1][:m]], np.r_[x2s[0], x2s[1][:m]]
    F_major = fk.fundamental_ransac(x1s[0], x2s[0], 2.0, seed=0).F
    F_minor = fk.fundamental_ransac(x1s[1][:m], x2s[1][:m], 2.0, seed=0).F
    coarse = fk.log_grid(600, 1400, 15)
    c_coarse, R_c, _, t_c = fk.pair_profile(x1, x2, F_major, pp, pp, coarse, coarse)
    fine = fk.log_grid(coarse[6], coarse[8], 6)[1:-1]
    good, *_ = fk.pair_profile(x1, x2, F_major, pp, pp, fine, fine)
    alone, *_ = fk.pair_profile(x1, x2, F_minor, pp, pp, fine, fine)
    assert np.all(alone > 1.5 * good)  # the worse basin at every fine point
    for ends in (((R_c[6], t_c[6]), None), (None, (R_c[8], t_c[8]))):
        seeded, *_ = fk.pair_profile(x1, x2, F_minor, pp, pp, fine, fine, ends=ends)
        np.testing.assert_allclose(seeded, good, rtol=1e-6)
    back, *_ = fk.pair_profile(x1, x2, F_minor, pp, pp, coarse[:7], coarse[:7], ends=(None, (R_c[7], t_c[7])))
    np.testing.assert_allclose(back, c_coarse[:7], rtol=1e-6)
