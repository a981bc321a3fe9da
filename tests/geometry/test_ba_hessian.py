"""The Schur elimination: the closed form used by refine_pair equals the textbook block route and a dense inverse."""

from __future__ import annotations

import numpy as np

from pipeline.geometry.ba_hessian import normal_equation_blocks, rotation_hessian
from pipeline.geometry.ba_model import residuals_and_jacobian
from pipeline.geometry.ba_solver import BAConfig, refine_pair
from pipeline.synthetic.pairs import SyntheticPair


def test_closed_form_schur_equals_block_schur(pair200: SyntheticPair, make_skewed_K) -> None:
    """The rank-one elimination in refine_pair equals U − Σ W V⁻¹ Wᵀ with batched 3×3 inverses."""
    sp = pair200
    Kj = make_skewed_K(610.0, 330.0, 235.0, skew=0.5)
    # Re-project image j with a skewed K_j so the skew paths are exercised.
    xj_n = np.column_stack([sp.x_j, np.ones(len(sp.x_j))]) @ np.linalg.inv(sp.K_j).T
    x_j = (xj_n @ Kj.T)[:, :2]
    res = refine_pair(sp.x_i, x_j, sp.K_i, Kj, sp.R0, sp.t0, BAConfig(tol=1e-12))
    _, J = residuals_and_jacobian(res.R, res.t, res.point_params, sp.x_i, x_j, sp.K_i, Kj)
    J = J[res.inlier_mask]  # H is built from the inliers (unit weights)
    U, V, Wm = normal_equation_blocks(J)
    H_block, S_block = rotation_hessian(U, V, Wm)
    s2 = res.sigma2 * res.variance_inflation  # σ̂² with the Student-t factor (estimated σ)
    assert res.sigma2_estimated and 1.0 < res.variance_inflation < 1.02
    np.testing.assert_allclose(H_block / s2, res.H, rtol=1e-8)
    np.testing.assert_allclose(S_block / s2, res.H_pose, rtol=1e-7, atol=1e-9 * np.abs(res.H_pose).max())
    # Also against a dense inverse of the full (3n+5) information: the rotation block of its inverse.
    Jf = np.zeros((4 * len(J), 5 + 3 * len(J)))
    for k in range(len(J)):
        Jf[4 * k : 4 * k + 4, :5] = J[k, :, :5]
        Jf[4 * k : 4 * k + 4, 5 + 3 * k : 8 + 3 * k] = J[k, :, 5:]
    info = Jf.T @ Jf
    cov = np.linalg.inv(info)
    np.testing.assert_allclose(np.linalg.inv(cov[:3, :3]) / s2, res.H, rtol=1e-5)
