"""The two-view BA with unknown focal lengths (refine_focal): Jacobian, equivalence when off, calibration of H."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import ConfigError
from pipeline.geometry.ba_focal import FocalUnknowns, focal_columns, scale_K
from pipeline.geometry.ba_model import project, tangent_basis, triangulate
from pipeline.geometry.ba_solver import BAConfig, refine_pair
from pipeline.synthetic.pairs import perturbed_focal, synthetic_pair


def test_focal_columns() -> None:
    assert focal_columns("none").shape == (2, 0)
    np.testing.assert_array_equal(focal_columns("shared"), [[1], [1]])
    np.testing.assert_array_equal(focal_columns("per_camera"), np.eye(2))
    np.testing.assert_array_equal(focal_columns("shared", known_i=True), [[0], [1]])
    np.testing.assert_array_equal(focal_columns("per_camera", known_j=True), [[1], [0]])
    assert focal_columns("shared", True, True).shape == (2, 0)
    with pytest.raises(ValueError, match="refine_focal='both'"):
        focal_columns("both")  # type: ignore[arg-type]


def test_config_rejects_unknown_mode() -> None:
    with pytest.raises(ConfigError, match="refine_focal"):
        BAConfig(refine_focal="all")  # type: ignore[arg-type]


@pytest.mark.parametrize("A", [np.ones((2, 1)), np.eye(2), np.array([[0.0], [1.0]])])
def test_focal_jacobian_matches_finite_differences(A: np.ndarray) -> None:
    sp = synthetic_pair(25, sigma_px=0.5, seed=4, offset_axes=True)
    Ki, Kj = sp.K_i, sp.K_j @ np.diag([1.0, 1.0, 1.0])
    Kj = scale_K(Kj, 0.03)
    xi, xj = np.ascontiguousarray(sp.x_i.T), np.ascontiguousarray(sp.x_j.T)
    P = triangulate(sp.R, sp.t, xi, xj, Ki, Kj)
    fu = FocalUnknowns(A, Ki, Kj)
    _, _, aux = project(sp.R, sp.t, P, xi, xj, Ki, Kj)
    Jf = fu.jacobian(P, Ki, Kj, aux)
    eps = 1e-6
    for c in range(fu.m):
        d = np.zeros(fu.m)
        d[c] = eps
        rp = project(sp.R, sp.t, P, xi, xj, *fu.Ks(d))[0]
        rm = project(sp.R, sp.t, P, xi, xj, *fu.Ks(-d))[0]
        fd = (rp - rm) / (2 * eps)
        np.testing.assert_allclose(Jf[:, c], fd, atol=1e-6 * np.abs(fd).max())
    assert tangent_basis(sp.t).shape == (3, 2)


def test_none_mode_is_the_plain_ba_to_the_last_digit() -> None:
    sp = synthetic_pair(150, sigma_px=1.0, seed=3, offset_axes=True)
    a = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
    b = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(refine_focal="none"), focal=np.zeros((2, 0)))
    c = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, BAConfig(refine_focal="shared"),
                    focal=focal_columns("shared", True, True))
    for r in (b, c):
        assert np.array_equal(a.R, r.R) and np.array_equal(a.H, r.H) and a.sigma2 == r.sigma2
    assert len(a.focal_log_sd) == 0 and np.array_equal(a.K_i, sp.K_i)


def test_noise_free_focal_recovered_from_a_wrong_start() -> None:
    sp = synthetic_pair(120, sigma_px=0.0, seed=7, offset_axes=True)
    K0 = perturbed_focal(sp.K_i, 0.05, 1)
    assert abs(K0[0, 0] / sp.K_i[0, 0] - 1) > 0.005
    res = refine_pair(sp.x_i, sp.x_j, K0, K0, sp.R0, sp.t0, BAConfig(sigma_px=1.0, refine_focal="shared"))
    assert abs(res.K_i[0, 0] / sp.K_i[0, 0] - 1) < 1e-6 and np.array_equal(res.K_i, res.K_j)
    assert np.degrees(so3.angle_between(res.R, sp.R)) < 1e-5
    assert res.H_pose.shape == (6, 6) and res.focal_log_sd.shape == (1,)


def test_one_known_camera_keeps_its_focal() -> None:
    sp = synthetic_pair(150, sigma_px=0.5, seed=2, offset_axes=True)
    K0 = perturbed_focal(sp.K_j, 0.04, 2)
    res = refine_pair(sp.x_i, sp.x_j, sp.K_i, K0, sp.R0, sp.t0, BAConfig(refine_focal="shared"),
                      focal=focal_columns("shared", known_i=True))
    assert np.array_equal(res.K_i, sp.K_i)
    assert abs(res.K_j[0, 0] / sp.K_j[0, 0] - 1) < 3 * res.focal_log_sd[0] + 1e-9


@pytest.mark.parametrize("mode", ["shared", "per_camera"])
def test_H_stays_calibrated_with_the_focal_marginalized(mode: str) -> None:
    """Mean NEES of Δω over noise draws with a focal 5% off at the start (the benchmark runs 500 draws)."""
    nees, fnees, nees_fixed = [], [], []
    for d in range(80):
        sp = synthetic_pair(200, sigma_px=1.0, seed=5000 + d, scene_seed=1, offset_axes=True)
        K0 = perturbed_focal(sp.K_i, 0.05, 5000 + d)
        r = refine_pair(sp.x_i, sp.x_j, K0, K0, sp.R0, sp.t0, BAConfig(refine_focal=mode))
        dw = so3.log(sp.R @ r.R.T)
        nees.append(dw @ r.H @ dw)
        fnees.append((math.log(r.K_i[0, 0] / sp.K_i[0, 0]) / r.focal_log_sd[0]) ** 2)
        if d < 20:
            r0 = refine_pair(sp.x_i, sp.x_j, K0, K0, sp.R0, sp.t0)
            dw0 = so3.log(sp.R @ r0.R.T)
            nees_fixed.append(dw0 @ r0.H @ dw0)
    assert 2.3 < np.mean(nees) < 3.8, np.mean(nees)  # 80 draws: sd of the mean ≈ 0.27
    assert 0.6 < np.mean(fnees) < 1.5, np.mean(fnees)
    assert np.mean(nees_fixed) > 6.0  # a wrong focal held fixed makes H overconfident
