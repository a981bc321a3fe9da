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
(:func:`joint_kappa`). A likelihood-ratio test against κ = 0 keeps an undistorted
camera undistorted (:func:`kappa_is_significant`).
"""

from __future__ import annotations

import numpy as np

from pipeline.frontend.distortion import radial_undistort
from pipeline.frontend.focal import CHI2_1_MEDIAN

__all__ = ["sampson_distorted", "radial_profile", "joint_kappa", "kappa_is_significant", "kappa_to_k1"]


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


def kappa_is_significant(kappa: np.ndarray, joint: np.ndarray, kappa_hat: float, chi2: float) -> bool:
    """Likelihood-ratio test of κ̂ against κ = 0: is the joint cost at 0 above its minimum by more than ``chi2``?

    The joint cost is interpolated linearly on the grid; ``chi2`` = 10.83 is the 99.9%
    quantile of χ²₁ (one parameter).
    """
    if not np.any(kappa <= 0) or not np.any(kappa >= 0):
        return True  # the grid does not reach κ = 0: nothing to test against
    at0 = float(np.interp(0.0, kappa, joint))
    at_hat = float(np.interp(kappa_hat, kappa, joint))
    return at0 - at_hat > chi2


def kappa_to_k1(kappa: float, s: float, f: float) -> float:
    """COLMAP ``SIMPLE_RADIAL`` k1 (normalized coordinates) from κ at nominal scale s: ``k1 = κ f²/s²``."""
    return kappa * f * f / (s * s)
