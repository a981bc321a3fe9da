"""One radial distortion parameter from a view graph's correspondences, before the focal length is known.

Pure kernels on arrays (no I/O); the cameras stage calls them per pair and on the graph.

The model is COLMAP's ``SIMPLE_RADIAL`` written at a nominal scale ``s = max(w, h)``
(:func:`pipeline.frontend.distortion.radial_undistort`): ``x_d = c + (1 + κ|u|²)(x_u − c)``,
``u = (x_u − c)/s``. The family is closed under the choice of scale (COLMAP's ``k1``
is ``κ f²/s²``), so κ is fitted with no focal length. Per pair F is free (7 dof,
which absorbs the unknown focal); the cost is the robust Sampson distance measured
in the *distorted* (measured) pixels, the epipolar constraint's gradient taken
through ``∂x_u/∂x_d`` (:func:`sampson_distorted`). F cannot absorb a radial warp, so
one parameter is observable from two views (Fitzgibbon, CVPR 2001). Each pair's
profile over a κ grid (:func:`radial_profile`, F refined by PoseLib's
``refine_fundamental`` warm-started along the grid) is normalized by its own σ²
and capped, the profiles are summed, and the minimum is refined by a parabola
(:func:`joint_kappa`). A quasi-likelihood ratio test against κ = 0, which discounts the
drop by the pairs' disagreement beyond their noise, keeps an undistorted camera
undistorted (:func:`kappa_test`).
"""

from __future__ import annotations

import numpy as np

from pipeline.frontend.distortion import radial_undistort
from pipeline.frontend.focal import CHI2_1_MEDIAN

__all__ = ["sampson_distorted", "radial_profile", "joint_kappa", "kappa_test", "kappa_to_k1"]


def sampson_distorted(F: np.ndarray, xu1: np.ndarray, xu2: np.ndarray, J1: np.ndarray, J2: np.ndarray) -> np.ndarray:
    """First-order distance (px of the measured images) of ``x_u2ᵀ F x_u1 = 0``.

    Args:
        F: (3, 3).  xu1, xu2: (n, 2) undistorted pixels.  J1, J2: (n, 2, 2) ``∂x_u/∂x_d``.
    Returns:
        (n,) signed distances.
    """
    h1 = np.column_stack([xu1, np.ones(len(xu1))])
    h2 = np.column_stack([xu2, np.ones(len(xu2))])
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.sum(h2 * Fx1, axis=1)
    g1 = np.einsum("na,nab->nb", Ftx2[:, :2], J1)
    g2 = np.einsum("na,nab->nb", Fx1[:, :2], J2)
    den = (g1 * g1).sum(axis=1) + (g2 * g2).sum(axis=1)
    return num / np.sqrt(np.maximum(den, 1e-300))


def radial_profile(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, c: np.ndarray, s: float, kappa: np.ndarray,
                   c_px: float = 2.0, iterations: int = 30, start: int | None = None) -> tuple[np.ndarray, float]:
    """One pair's profile cost over a κ grid: F refined on the undistorted inliers at each κ.

    The sweep starts at grid point ``start`` (with the given F) and moves out in both
    directions, each point warm-started from its neighbour's F.

    Args:
        x1, x2: (n, 2) measured inlier pixels.  F: (3, 3) start, of the points undistorted
            at ``kappa[start]``.  c: (2,) centre.  s: nominal scale.
        kappa: (G,) increasing grid.  c_px: Cauchy scale (px).  iterations: PoseLib iterations.
        start: index of the start point (default: the point nearest κ = 0).
    Returns:
        ``(cost (G,) px², σ² px²)``, σ² from the median squared distance at the start point.
    """
    import poselib  # noqa: PLC0415

    G = len(kappa)
    cost = np.empty(G)
    g0 = int(np.argmin(np.abs(kappa))) if start is None else int(start)
    F_at = {g0: np.asarray(F, np.float64)}
    sigma2 = 1.0
    c2 = c_px * c_px
    opts = {"loss_type": "CAUCHY", "loss_scale": c_px, "max_iterations": iterations}
    for g in [*range(g0, G), *range(g0 - 1, -1, -1)]:  # a 1-D sweep; the work inside is vectorized
        start = F_at[g0 if g == g0 else (g - 1 if g > g0 else g + 1)]
        xu1, J1 = radial_undistort(x1, c, s, float(kappa[g]))
        xu2, J2 = radial_undistort(x2, c, s, float(kappa[g]))
        Fg, _ = poselib.refine_fundamental(xu1, xu2, start, opts)
        F_at[g] = np.asarray(Fg)
        e = sampson_distorted(F_at[g], xu1, xu2, J1, J2)
        cost[g] = float(c2 * np.log1p(e * e / c2).sum())
        if g == g0:
            sigma2 = max(float(np.median(e * e)) / CHI2_1_MEDIAN, 1e-6)
    return cost, sigma2


def _parabola_min(x: np.ndarray, y: np.ndarray) -> float:
    k = int(np.argmin(y))
    if k == 0 or k == len(y) - 1:
        return float(x[k])
    a, b, _ = np.polyfit(x[k - 1:k + 2], y[k - 1:k + 2], 2)
    return float(-b / (2 * a)) if a > 0 else float(x[k])


def joint_kappa(kappa: np.ndarray, cost: np.ndarray, sigma2: np.ndarray, cap: float = 25.0
                ) -> tuple[float, np.ndarray]:
    """κ minimizing the capped sum of the pairs' normalized profiles.

    Args:
        kappa: (G,) grid.  cost: (M, G) per-pair profiles (px²).  sigma2: (M,) per-pair σ².
        cap: where a pair's Δχ² stops counting fully.
    Returns:
        ``(κ, joint cost (G,))``; the joint cost is in Δχ² units (0 at its minimum).
    """
    d = (cost - cost.min(axis=1, keepdims=True)) / sigma2[:, None]
    J = (cap * np.log1p(d / cap)).sum(axis=0)
    return _parabola_min(kappa, J), J - J.min()


def _own_minimum(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(M,) each row's minimum between grid points: the vertex of the parabola through its lowest point and
    the two beside it (the lowest point itself at the grid's ends or where the parabola is not convex)."""
    g = np.clip(np.argmin(y, axis=1), 1, len(x) - 2)  # x has >= 3 points (kappa_test)
    rows = np.arange(len(y))
    xs = np.stack([x[g - 1], x[g], x[g + 1]], 1)
    ys = np.stack([y[rows, g - 1], y[rows, g], y[rows, g + 1]], 1)
    V = np.stack([xs * xs, xs, np.ones_like(xs)], 2)  # (M, 3, 3)
    a, b, c = np.linalg.solve(V, ys[:, :, None])[:, :, 0].T
    vx = -b / (2 * np.where(a > 0, a, 1.0))
    inside = (a > 0) & (vx >= xs[:, 0]) & (vx <= xs[:, 2])
    return np.minimum(y.min(axis=1), np.where(inside, c - b * b / (4 * np.where(a > 0, a, 1.0)), np.inf))


def _quadratic_at(x: np.ndarray, y: np.ndarray, x0: float) -> np.ndarray:
    """Each row of ``y`` (M, G) at ``x0``, by the parabola through the three grid points nearest ``x0``.

    Linear interpolation would overstate a sharp convex profile between grid points by
    up to a quarter of its curvature times the spacing², and the test compares such values.
    """
    k = int(np.clip(np.searchsorted(x, x0), 1, len(x) - 2))
    k = k - 1 if k > 1 and abs(x[k - 2] - x0) < abs(x[k + 1] - x0) else k
    coef = np.linalg.solve(np.vander(x[k - 1:k + 2], 3), y[:, k - 1:k + 2].T)  # (3, M), one shared 3×3 system
    return (np.vander([x0], 3) @ coef)[0]


def kappa_test(kappa: np.ndarray, cost: np.ndarray, sigma2: np.ndarray, kappa_hat: float, chi2: float,
               cap: float = 25.0) -> tuple[bool, float, float, float]:
    """Quasi-likelihood ratio test of a shared κ̂ against κ = 0 (McCullagh & Nelder, *GLMs*, §9.2).

    The joint cost is a sum of the pairs' Δχ² (:func:`joint_kappa`), each in units of its
    own σ², which the median of its residuals estimates. If that were the whole error,
    the pairs' Δχ² at the shared κ̂ would add up to about ``M − 1``. When they add up to
    more, the pairs disagree about κ beyond their noise (keypoints worse than their
    median, a per-image lens, a model error that a per-pair κ absorbs), and the joint
    drop overstates the evidence by that dispersion ``φ = Σ_k ρ(Δχ²_k(κ̂)) / (M − 1)``
    (Pearson's estimate; ρ the same cap as the joint cost). The statistic is the drop
    divided by ``max(φ, 1)``, against ``F(1, M − 1)`` at the level that ``chi2`` gives
    χ²₁ (10.83: 99.9%), which tends to that χ² threshold as M grows.

    Args:
        kappa: (G,) grid.  cost: (M, G) per-pair profiles (px²).  sigma2: (M,) per-pair σ².
        kappa_hat: the joint minimizer.  chi2: the χ²₁ threshold that sets the level.
        cap: the cap of :func:`joint_kappa`.
    Returns:
        ``(significant, drop, dispersion φ, critical value)``; a grid that does not reach
        κ = 0 has nothing to test against and is significant.
    """
    from scipy import stats  # noqa: PLC0415

    if len(kappa) < 3:
        raise ValueError(f"kappa has {len(kappa)} grid points but the test needs at least 3 (a parabola through them)")
    d = (cost - _own_minimum(kappa, cost)[:, None]) / sigma2[:, None]
    rho = cap * np.log1p(np.maximum(d, 0.0) / cap)
    per_pair = np.maximum(_quadratic_at(kappa, rho, kappa_hat), 0.0)
    at0 = float(np.maximum(_quadratic_at(kappa, rho, 0.0), 0.0).sum())
    drop = at0 - float(per_pair.sum())
    M = len(cost)
    phi = float(per_pair.sum()) / (M - 1) if M > 1 else 1.0
    crit = float(stats.f.ppf(stats.chi2.cdf(chi2, 1), 1, M - 1)) if M > 1 else float("inf")
    if not np.any(kappa <= 0) or not np.any(kappa >= 0):
        return True, drop, phi, crit
    return bool(drop / max(phi, 1.0) > crit), drop, phi, crit


def kappa_to_k1(kappa: float, s: float, f: float) -> float:
    """COLMAP ``SIMPLE_RADIAL`` k1 (normalized coordinates) from κ at nominal scale s: ``k1 = κ f²/s²``."""
    return kappa * f * f / (s * s)
