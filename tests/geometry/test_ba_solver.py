"""The two-view bundle adjustment of one pair (refine_pair): accuracy, robustness, calibration of H, rejects."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import ConfigError
from pipeline.geometry.ba_solver import BAConfig, TwoViewBAError, refine_pair, studentized_threshold
from pipeline.synthetic.pairs import SyntheticPair, synthetic_pair


# --------------------------------------------------------------- refinement
def test_noise_free_pair_recovers_truth_from_rough_start() -> None:
    sp = synthetic_pair(80, sigma_px=0.0, seed=5, init_perturb_deg=3.0)
    res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(sigma_px=1.0))
    assert np.rad2deg(so3.angle_between(res.R, sp.R)) < 1e-6
    assert np.rad2deg(np.arccos(min(1.0, res.t @ sp.t))) < 1e-5
    np.testing.assert_allclose(res.points, sp.points, rtol=1e-6)
    assert res.converged and res.iterations <= 12


def test_result_fields_and_convention(pair200: SyntheticPair) -> None:
    sp = pair200
    res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
    n = len(sp.x_i)
    assert res.R.shape == (3, 3) and res.t.shape == (3,) and res.points.shape == (n, 3)
    assert res.residuals.shape == (n, 4) and res.inlier_mask.shape == (n,)
    assert abs(np.linalg.norm(res.t) - 1.0) < 1e-12
    np.testing.assert_allclose(res.H, res.H.T, atol=0)
    assert np.linalg.eigvalsh(res.H)[0] > 0
    # BA lowers the error of the 1° perturbed start to a small fraction of it.
    assert np.rad2deg(so3.angle_between(res.R, sp.R)) < 0.5
    assert res.cost_history[0] > res.cost_history[-1]
    # x_j = R x_i + t holds for the refined points (projected), within the noise.
    Xj = res.points @ res.R.T + res.t
    proj = (Xj @ sp.K_j.T)[:, :2] / Xj[:, 2:3]
    assert np.sqrt(np.mean(np.sum((proj - sp.x_j) ** 2, axis=1))) < 2.0
    assert 0.7 < res.sigma2 < 1.4 and res.sigma2_estimated


def test_known_sigma_is_used_verbatim(pair200: SyntheticPair) -> None:
    sp = pair200
    # Plain least squares: the fit itself does not depend on σ, only H's scale does.
    a = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(sigma_px=2.0, loss="none", refit_inliers=False))
    b = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(sigma_px=1.0, loss="none", refit_inliers=False))
    assert a.sigma2 == 4.0 and not a.sigma2_estimated
    np.testing.assert_allclose(a.H * 4.0, b.H, rtol=1e-6)


def test_ba_off_keeps_ransac_pose(pair200: SyntheticPair) -> None:
    sp = pair200
    res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(enabled=False))
    np.testing.assert_allclose(res.R, sp.R0, atol=1e-12)
    np.testing.assert_allclose(res.t, sp.t0, atol=1e-12)
    assert res.iterations >= 1 and np.linalg.eigvalsh(res.H)[0] > 0
    # A 1° wrong pose leaves larger residuals than the refined one.
    on = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
    assert res.sigma2 > 2.0 * on.sigma2


def test_robust_loss_and_refit_reject_outliers() -> None:
    sp = synthetic_pair(200, sigma_px=1.0, outlier_frac=0.15, seed=11)
    err = {}
    for loss in ("none", "cauchy", "huber"):
        res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(loss=loss))
        err[loss] = np.rad2deg(so3.angle_between(res.R, sp.R))
        if loss == "cauchy":
            # Outliers found: few of them survive and almost no inlier is lost.
            assert np.mean(res.inlier_mask[sp.outlier_mask]) < 0.2
            assert np.mean(res.inlier_mask[~sp.outlier_mask]) > 0.97
            assert 0.7 < res.sigma2 < 1.4
    assert err["cauchy"] < 0.3 and err["huber"] < 0.3
    # Plain least squares without the robust start is visibly hurt.
    no_refit = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(loss="none", refit_inliers=False))
    assert no_refit.sigma2 > 10.0


@pytest.mark.slow
def test_calibration_small_monte_carlo() -> None:
    """100 noise draws on one scene: mean NEES ≈ 3 and covariance ≈ mean(H)⁻¹.

    Bounds: with 100 draws the mean of χ²₃ has sd √(6/100) ≈ 0.245, so [2.3, 3.7]
    is ≈ ±2.9 sd; a variance ratio along a fixed direction has sd √(2/100) ≈ 0.14,
    so [0.6, 1.5] is ≈ 2.9 sd below and 3.5 sd above.
    """
    for sigma_known in (True, False):
        cfg = BAConfig(sigma_px=1.0 if sigma_known else None)
        dws, Hs = [], []
        for d in range(100):
            sp = synthetic_pair(200, sigma_px=1.0, seed=1000 + d, scene_seed=42)
            res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, cfg)
            dws.append(so3.log(sp.R @ res.R.T))  # R_true = exp([Δω]×) R̂
            Hs.append(res.H)
        dws, Hs = np.array(dws), np.array(Hs)
        nees = np.einsum("ni,nij,nj->n", dws, Hs, dws)
        assert 2.3 < nees.mean() < 3.7, (sigma_known, nees.mean())
        C = np.cov(dws.T, bias=True) + np.outer(dws.mean(0), dws.mean(0))
        lam, Q = np.linalg.eigh(np.linalg.inv(Hs.mean(0)))
        ratios = np.einsum("ik,ij,jk->k", Q, C, Q) / lam
        assert np.all((ratios > 0.6) & (ratios < 1.5)), (sigma_known, ratios)


def test_calibration_with_few_points() -> None:
    """20 points, σ estimated: mean NEES ≈ 3 over 300 draws, and ≈ 0.1% of the inliers dropped.

    Two effects that vanish at 200 points decide this case. σ̂² has only ν = 15 degrees
    of freedom, so the error is a Student-t whose covariance is ν/(ν − 2) = 1.15× that of
    the Gaussian (``variance_inflation``); and the inlier test's σ comes from a median of
    20 residuals that the fit has shrunk by 1 − 5/20, which (before the leave-one-out
    median and the studentized threshold) dropped ~2.4% of the inliers, biased σ̂² low
    and gave a mean NEES of ≈ 5. Bounds: the sd of the mean is 0.16 here (measured), so
    [2.5, 3.55] is ≈ ±3 sd; the t factor left out gives ≈ 3.5, the old inlier test ≈ 5.
    """
    nees, dropped = [], 0
    for d in range(300):
        sp = synthetic_pair(20, sigma_px=1.0, seed=2000 + d, scene_seed=42)
        res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
        nu = res.n_inliers - 5.0
        assert res.sigma2_estimated and res.variance_inflation == pytest.approx(nu / (nu - 2.0), rel=1e-12)
        dw = so3.log(sp.R @ res.R.T)
        nees.append(dw @ res.H @ dw)
        dropped += 20 - res.n_inliers
    assert 2.5 < np.mean(nees) < 3.55, np.mean(nees)
    assert dropped / (300 * 20) < 0.004, dropped  # 0.1% expected (the χ²₁ tail at 10.83)


def test_studentized_threshold_keeps_the_false_rejection_rate() -> None:
    """stat/σ̂² with σ̂² on ν dof exceeds the threshold with the χ²₁ tail probability of ``chi2``."""
    rng = np.random.default_rng(3)
    for nu in (4.0, 12.0, 60.0):
        thr = studentized_threshold(10.83, nu)
        x = rng.chisquare(1, 2_000_000) / (rng.chisquare(nu, 2_000_000) / nu)
        assert abs(np.mean(x > thr) - 0.001) < 1e-4, (nu, thr, np.mean(x > thr))
    assert studentized_threshold(10.83, 4.0) > studentized_threshold(10.83, 60.0) > 10.83
    assert studentized_threshold(10.83, float("inf")) == 10.83


def test_least_certain_direction_is_the_weak_one() -> None:
    """H's smallest eigenvector points where a perturbation changes the residuals least."""
    sp = synthetic_pair(150, sigma_px=0.5, seed=9)
    res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(sigma_px=0.5))
    lam, Q = np.linalg.eigh(res.H)
    assert lam[-1] / lam[0] > 3.0  # two-view rotation precision is anisotropic
    cfg = BAConfig(sigma_px=0.5, enabled=False)
    costs = []
    for k in (0, 2):
        R_pert = so3.exp(1e-3 * Q[:, k]) @ res.R
        # Best translation is not re-fitted here: compare the points-only fits.
        r = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, R_pert, res.t, cfg)
        costs.append(np.sum(r.residuals[r.inlier_mask] ** 2))
    assert costs[0] < costs[1]


# ------------------------------------------------------------------ rejects
@pytest.mark.parametrize(
    "kw, match",
    [
        ({"loss": "tukey"}, "loss='tukey' but expected one of"),
        ({"sigma_px": -1.0}, "sigma_px=-1.0"),
        ({"loss_scale_px": 0.0}, "loss_scale_px=0.0"),
        ({"loss_scale_sigmas": 0.0}, "loss_scale_sigmas=0.0"),
        ({"inlier_chi2": -2.0}, "inlier_chi2=-2.0"),
        ({"max_iterations": 0}, "max_iterations=0"),
        ({"min_points": 3}, "min_points=3"),
        ({"workers": 0}, "workers=0"),
    ],
)
def test_config_rejects_bad_values(kw: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        BAConfig(**kw)


def test_config_is_typed_and_workers_do_not_enter_the_fingerprint() -> None:
    with pytest.raises(ConfigError, match="enabled='false' but expected true or false"):
        BAConfig(enabled="false")
    with pytest.raises(ConfigError, match="sigma_px=nan"):
        BAConfig(sigma_px=float("nan"))
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['max_iters'\]"):
        BAConfig.from_dict({"max_iters": 3})
    base = BAConfig().fingerprint()
    assert BAConfig(workers=1, chunk_size=3, progress=False).fingerprint() == base
    assert BAConfig(loss="huber").fingerprint() != base


def test_refine_pair_rejects_bad_inputs(pair200: SyntheticPair) -> None:
    sp = pair200
    args = [sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0]
    with pytest.raises(ValueError, match=r"x_i.shape=\(200, 2\), x_j.shape=\(199, 2\)"):
        refine_pair(sp.x_i, sp.x_j[:-1], *args[2:])
    bad = sp.x_i.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        refine_pair(bad, *args[1:])
    with pytest.raises(ValueError, match=r"K_j.shape=\(2, 3\)"):
        refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j[:2], sp.R0, sp.t0)
    Kbad = sp.K_i.copy()
    Kbad[2] = [0.0, 0.0, 2.0]
    with pytest.raises(ValueError, match="K_i must be an upper-triangular pinhole"):
        refine_pair(sp.x_i, sp.x_j, Kbad, sp.K_j, sp.R0, sp.t0)
    with pytest.raises(ValueError, match="R0 must be a"):
        refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, 2.0 * sp.R0, sp.t0)
    with pytest.raises(ValueError, match="R0 must be a"):
        refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, -sp.R0, sp.t0)
    with pytest.raises(ValueError, match="t0 must be a finite"):
        refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, np.array([np.nan, 0.0, 1.0]))
    with pytest.raises(TwoViewBAError, match="pair has 8 correspondences but min_points=12"):
        refine_pair(sp.x_i[:8], sp.x_j[:8], sp.K_i, sp.K_j, sp.R0, sp.t0)


def test_zero_translation_start_is_recovered(pair200: SyntheticPair) -> None:
    """A front end may report t = 0 (pure rotation); the BA then starts from the epipolar t."""
    sp = pair200
    res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, np.zeros(3))
    assert np.rad2deg(np.arccos(min(1.0, res.t @ sp.t))) < 2.0
    assert np.rad2deg(so3.angle_between(res.R, sp.R)) < 0.5


def test_pure_rotation_pair_gives_finite_H() -> None:
    """Zero baseline: t is unobservable, the rotation is not; H must stay finite and PD."""
    rng = np.random.default_rng(4)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    R = so3.exp(np.array([0.02, -0.05, 0.01]))
    x_i = rng.uniform([0, 0], [640, 480], (150, 2))
    m = np.column_stack([x_i, np.ones(150)]) @ np.linalg.inv(K).T
    q = m @ R.T @ K.T
    x_j = q[:, :2] / q[:, 2:] + 0.3 * rng.standard_normal((150, 2))
    x_i = x_i + 0.3 * rng.standard_normal((150, 2))
    res = refine_pair(x_i, x_j, K, K, so3.exp(np.array([0.0, 0.003, 0.0])) @ R, np.zeros(3))
    assert np.rad2deg(so3.angle_between(res.R, R)) < 0.05
    lam = np.linalg.eigvalsh(res.H)
    assert np.all(np.isfinite(lam)) and lam[0] > 0


def test_mostly_outliers_is_rejected_with_reason() -> None:
    sp = synthetic_pair(40, sigma_px=1.0, outlier_frac=0.8, seed=2)
    with pytest.raises(TwoViewBAError, match="inliers"):
        refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(sigma_px=1.0, min_points=20))
