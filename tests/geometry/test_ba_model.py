"""The two-view BA model: Jacobians against central differences, the tangent basis."""

from __future__ import annotations

import numpy as np

from pipeline.core import so3
from pipeline.geometry.ba_model import residuals_and_jacobian, tangent_basis


def test_jacobian_matches_central_differences(make_skewed_K) -> None:
    rng = np.random.default_rng(0)
    n = 25
    Ki, Kj = make_skewed_K(500.0, 320.0, 240.0), make_skewed_K(650.0, 300.0, 250.0, aspect=0.97, skew=-1.3)
    R = so3.exp(np.array([0.1, -0.25, 0.05]))
    t = np.array([0.8, 0.1, -0.2])
    t /= np.linalg.norm(t)
    P = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.05, 0.3, n)])
    x_i = rng.uniform(0, 640, (n, 2))
    x_j = rng.uniform(0, 480, (n, 2))
    r0, J = residuals_and_jacobian(R, t, P, x_i, x_j, Ki, Kj)
    assert r0.shape == (n, 4) and J.shape == (n, 4, 8)
    B = tangent_basis(t)
    eps = 1e-6
    J_fd = np.zeros_like(J)
    for k in range(8):
        rs = []
        for sgn in (1.0, -1.0):
            Rk, tk, Pk = R, t, P.copy()
            if k < 3:
                Rk = so3.exp(sgn * eps * np.eye(3)[k]) @ R  # left perturbation
            elif k < 5:
                tk = t + sgn * eps * B[:, k - 3]
                tk = tk / np.linalg.norm(tk)
            else:
                Pk[:, k - 5] += sgn * eps
            rs.append(residuals_and_jacobian(Rk, tk, Pk, x_i, x_j, Ki, Kj)[0])
        J_fd[:, :, k] = (rs[0] - rs[1]) / (2 * eps)
    scale = np.abs(J_fd).max()
    np.testing.assert_allclose(J, J_fd, atol=1e-6 * scale, rtol=1e-5)


def test_tangent_basis_is_orthonormal_and_tangent() -> None:
    for t in (np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), np.array([0.3, -0.4, 0.866])):
        t = t / np.linalg.norm(t)
        B = tangent_basis(t)
        np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(B.T @ t, 0.0, atol=1e-12)
