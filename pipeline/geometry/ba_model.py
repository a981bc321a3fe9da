"""The two-view bundle-adjustment model: parametrization, projection, residuals and Jacobians.

* **Model.** Camera i is the origin. Point k is ``X_k = m_k / ρ_k`` with
  ``m_k = (a_k, b_k, 1)`` its normalized ray in camera i and ``ρ_k`` its
  inverse depth, so ``x_i = K_i m`` (no dependence on ρ) and
  ``x_j = π(K_j (R m + ρ t))`` (the projection is scale invariant, so the
  ``1/ρ`` drops out and points at infinity, ρ = 0, are regular). ``R = R_ij =
  R_j R_iᵀ`` (pycolmap's ``cam2_from_cam1``) and ``t = t_ij`` with
  ``x_j = R x_i + t`` and ``‖t‖ = 1``, which fixes the scale gauge.
* **Variables.** 3 + 2 + 3n: the rotation with the left perturbation
  ``R ← exp([δ]×) R`` (the convention of ``H_ij``), the translation on the
  unit sphere ``t ← normalize(t + B δt)`` with ``B`` (3, 2) an orthonormal basis
  of the tangent plane (:func:`tangent_basis`), and (a, b, ρ) per point.

The Jacobians are checked against central differences in the tests. The
elimination of the points and the translation is in
:mod:`pipeline.geometry.ba_hessian`; the solver in :mod:`pipeline.geometry.ba_solver`.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["tangent_basis", "exp3", "project", "jacobians", "residuals_and_jacobian", "point_s2", "triangulate",
           "translation_from_rotation"]

# Internally every per-point array is component-major, (k, n), so that each
# formula below is a handful of contiguous length-n vector operations.


def tangent_basis(t: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the tangent plane of the unit sphere at ``t``.

    Args:
        t: (3,) unit vector.

    Returns:
        (3, 2) matrix B with ``Bᵀ B = I`` and ``Bᵀ t = 0``.
    """
    # Cross with the axis least aligned with t: never degenerate.
    x, y, z = t.tolist()
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax <= ay and ax <= az:  # t × e_x
        b1 = (0.0, z, -y)
    elif ay <= az:  # t × e_y
        b1 = (-z, 0.0, x)
    else:  # t × e_z
        b1 = (y, -x, 0.0)
    s = 1.0 / math.sqrt(b1[0] ** 2 + b1[1] ** 2 + b1[2] ** 2)
    b1 = (b1[0] * s, b1[1] * s, b1[2] * s)
    b2 = (y * b1[2] - z * b1[1], z * b1[0] - x * b1[2], x * b1[1] - y * b1[0])
    return np.array([[b1[0], b2[0]], [b1[1], b2[1]], [b1[2], b2[2]]])


def exp3(w: np.ndarray) -> np.ndarray:
    """Rodrigues for one rotation vector (the batched ``so3.exp`` costs more for a single one)."""
    x, y, z = w.tolist()
    th2 = x * x + y * y + z * z
    W = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    W2 = W @ W
    if th2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    W *= a
    W2 *= b
    W += W2
    W.flat[::4] += 1.0  # I + a W + b W²
    return W


def project(R, t, P, xi, xj, Ki, Kj):
    """Residuals (4, n) px, validity (n,) (in front of camera j) and what the Jacobian reuses.

    ``P`` (3, n) holds (a, b, ρ); ``xi``, ``xj`` are (2, n).
    """
    n = P.shape[1]
    r = np.empty((4, n))
    # Every formula works on whole (k, n) blocks: at n ≈ 1000 the cost is the
    # number of numpy calls, not the arithmetic.
    # K's last row is (0, 0, 1), so (K m)_z = 1 and image i is affine in (a, b).
    ab = P[:2]
    np.matmul(Ki[:2, :2], ab, out=r[:2])
    r[:2] += Ki[:2, 2, None]
    r[:2] -= xi
    pR = R[:, :2] @ ab
    pR += R[:, 2, None]
    p = t[:, None] * P[2]
    p += pR
    z = p[2]
    valid = z > 1e-9 * np.abs(p).sum(axis=0)
    iz = np.divide(1.0, z)
    if not valid.all():
        iz[~valid] = 1.0
    uv = Kj[:2, :2] @ p[:2]  # projection in image j (px)
    uv *= iz
    uv += Kj[:2, 2, None]
    np.subtract(uv, xj, out=r[2:])
    return r, valid, (pR, iz, uv)


def jacobians(R, t, B, P, Kj, aux) -> np.ndarray:
    """Jacobian of the image-j residuals, (2, 8, n): columns δ (3), δt (2), (a, b, ρ) (3).

    The image-i residuals have the constant point Jacobian ``[[K00, K01, 0],
    [0, K11, 0]]`` and no pose dependence; they enter through
    :func:`point_null_vectors` and :func:`point_step`.
    """
    pR, iz, uv = aux
    n = P.shape[1]
    # A = d r_j / d p = dπ/dq · K_j, (2, 3, n); row 0 is (A00, A01, A02), row 1 (0, A11, A12).
    A = np.empty((2, 3, n))
    # Row by row: numpy broadcasts a (2, 2, 1) factor into a strided block slowly.
    np.multiply(Kj[0, 0], iz, out=A[0, 0])
    np.multiply(Kj[0, 1], iz, out=A[0, 1])
    A[1, 0] = 0.0
    np.multiply(Kj[1, 1], iz, out=A[1, 1])
    np.subtract(Kj[:2, 2, None], uv, out=A[:, 2])
    A[:, 2] *= iz
    x, y, z = pR
    J = np.empty((2, 8, n))
    # d(exp([δ]×) R m)/dδ = −[R m]×; a row aᵀ(−[v]×) is (v × a)ᵀ. Both rows at once.
    np.subtract(y * A[:, 2], z * A[:, 1], out=J[:, 0])
    np.subtract(z * A[:, 0], x * A[:, 2], out=J[:, 1])
    np.subtract(x * A[:, 1], y * A[:, 0], out=J[:, 2])
    # d p/dδt = ρ B (normalizing t + B δt has no first-order effect);
    # d p/d(a, b, ρ) = [R e1, R e2, t].
    T = np.empty((5, 3))
    T[:2] = B.T
    T[2:4] = R[:, :2].T
    T[4] = t
    np.matmul(T, A, out=J[:, 3:])
    J[:, 3:5] *= P[2]
    return J


def residuals_and_jacobian(R, t, points, x_i, x_j, K_i, K_j) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and full Jacobian of one pair, per point (for tests and checks).

    Args:
        R: (3, 3) ``R_ij``.  t: (3,) unit ``t_ij``.
        points: (n, 3) parameters (a, b, ρ).
        x_i, x_j: (n, 2) pixels.  K_i, K_j: (3, 3).

    Returns:
        ``r (n, 4)`` px (image i x, y, image j x, y) and ``J (n, 4, 8)``, the
        derivatives with respect to (δ (3), δt (2) in :func:`tangent_basis` (t),
        a, b, ρ), with ``R ← exp([δ]×) R`` and ``t ← normalize(t + B δt)``.
    """
    P = np.asarray(points, dtype=np.float64).T
    r, _, aux = project(R, t, P, np.asarray(x_i).T, np.asarray(x_j).T, K_i, K_j)
    Jj = jacobians(R, t, tangent_basis(t), P, K_j, aux)
    n = P.shape[1]
    J = np.zeros((n, 4, 8))
    J[:, 0, 5:7] = K_i[0, :2]
    J[:, 1, 6] = K_i[1, 1]
    J[:, 2:4] = Jj.transpose(2, 0, 1)
    return r.T, J


def point_s2(r: np.ndarray) -> np.ndarray:
    """Squared residual norm of each point, (n,), from (4, n) residuals."""
    return (r * r).sum(axis=0)  # rows added in order, as r0² + r1² + r2² + r3²


def triangulate(R: np.ndarray, t: np.ndarray, xi: np.ndarray, xj: np.ndarray, Ki: np.ndarray, Kj: np.ndarray) -> np.ndarray:
    """Initial (a, b, ρ), (3, n): ray of camera i and the linear least-squares inverse depth.

    ``xi``, ``xj`` are (2, n). Kept operation for operation as first written: the
    scipy peer in ``benchmarks/two_view_ba.py`` starts from it, and its Cauchy
    run is chaotic in the start point (1e-16 changes turn 44 evaluations into ~900).
    """
    Kii = np.linalg.inv(Ki)
    Kji = np.linalg.inv(Kj)
    mi = Kii[:, :2] @ xi + Kii[:, 2:3]
    mi /= mi[2]
    mj = Kji[:, :2] @ xj + Kji[:, 2:3]
    # m_j ∥ R m_i + ρ t  ⇒  m_j × (R m_i) + ρ (m_j × t) = 0, least squares in ρ.
    q = R @ mi
    c = np.stack([mj[1] * q[2] - mj[2] * q[1], mj[2] * q[0] - mj[0] * q[2], mj[0] * q[1] - mj[1] * q[0]])
    d = np.stack([mj[1] * t[2] - mj[2] * t[1], mj[2] * t[0] - mj[0] * t[2], mj[0] * t[1] - mj[1] * t[0]])
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = -(c * d).sum(axis=0) / (d * d).sum(axis=0)
    # Points triangulated behind camera i (or on the epipole) start at infinity.
    rho = np.where(np.isfinite(rho), np.maximum(rho, 0.0), 0.0)
    return np.vstack([mi[:2], rho])


def translation_from_rotation(xi, xj, Ki, Kj, R) -> np.ndarray:
    """Unit t minimizing Σ (t · (m_j × R m_i))², signed to put most points in front.

    ``xi``, ``xj`` are (n, 2) pixels.
    """
    mi = np.column_stack([xi, np.ones(len(xi))]) @ np.linalg.inv(Ki).T
    mj = np.column_stack([xj, np.ones(len(xj))]) @ np.linalg.inv(Kj).T
    A = np.cross(mj, mi @ R.T)
    t = np.linalg.svd(A, full_matrices=False)[2][-1]
    rho = triangulate(R, t, np.ascontiguousarray(xi.T), np.ascontiguousarray(xj.T), Ki, Kj)[2]
    rho_neg = triangulate(R, -t, np.ascontiguousarray(xi.T), np.ascontiguousarray(xj.T), Ki, Kj)[2]
    return t if (rho > 0).sum() >= (rho_neg > 0).sum() else -t

