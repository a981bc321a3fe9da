"""Synthetic two-view problems with known truth, for the tests and benchmarks of :mod:`pipeline.geometry`.

- :func:`synthetic_pair`: one converging pair of pinhole cameras looking at
  random points, with pixel noise, outliers and a perturbed initial pose;
- :func:`synthetic_pairs`: such a pair on every edge ``(i, j)``, ``i < j``, of a
  set of cameras (each pair its own scene), shaped like a two-view result.

Convention: ``R = R_ij = R_j R_iᵀ`` (cam2_from_cam1) and ``x_j = R x_i + t``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core import so3

__all__ = ["SyntheticPair", "synthetic_pair", "synthetic_pairs", "perturbed_focal"]


@dataclass
class SyntheticPair:
    """A synthetic two-view problem with known truth (see :func:`synthetic_pair`).

    Attributes:
        x_i, x_j: (n, 2) noisy pixel observations (outliers replaced in image j).
        K_i, K_j: (3, 3) intrinsics.
        R, t: true ``R_ij`` (3, 3) and unit ``t_ij`` (3,).
        points: (n, 3) true points in camera i.
        outlier_mask: (n,) True for outlier matches.
        R0, t0: perturbed initial pose, standing in for RANSAC.
    """

    x_i: np.ndarray
    x_j: np.ndarray
    K_i: np.ndarray
    K_j: np.ndarray
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    outlier_mask: np.ndarray
    R0: np.ndarray
    t0: np.ndarray


def synthetic_pair(
    n_points: int = 200,
    sigma_px: float = 1.0,
    outlier_frac: float = 0.0,
    seed: int = 0,
    scene_seed: int | None = None,
    init_perturb_deg: float = 1.0,
    size: tuple[int, int] = (640, 480),
    focal: float = 600.0,
    offset_axes: bool = False,
) -> SyntheticPair:
    """A converging pair of pinhole cameras looking at random points, with pixel noise.

    Camera i is at the origin looking down +z; camera j sits on a random unit
    baseline mostly sideways (so ``‖t‖ = 1``) and is turned towards the centre of
    the point cloud (depths 4–10 baselines), with a random roll. Points are
    uniform in camera i's frustum and kept only where both images see them.

    Args:
        n_points: number of correspondences.
        sigma_px: std of the Gaussian noise added to all four pixel coordinates.
        outlier_frac: fraction of matches whose image-j point is replaced by a
            uniform random pixel at least 20 px from its true position.
        seed: seed of the noise, the outliers and the initial pose.
        scene_seed: seed of the geometry (cameras, points); default ``seed``.
            Fixing it and varying ``seed`` gives Monte-Carlo noise draws.
        init_perturb_deg: size of the random perturbation of ``R0`` and ``t0``.
        size: image (width, height) in px.
        focal: focal length in px.
        offset_axes: aim camera j 1.5 units beside the cloud centre, so that the two
            optical axes do not meet: the focal length is then observable from the pair
            (aimed at the centre from nearly equal distances, the pair is close to
            Sturm's degenerate configuration for a shared focal).

    Returns:
        The pair with its truth.
    """
    if n_points < 1 or not 0.0 <= outlier_frac < 1.0 or sigma_px < 0:
        raise ValueError(f"n_points={n_points}, outlier_frac={outlier_frac}, sigma_px={sigma_px}: need n>=1, 0<=frac<1, sigma>=0")
    geo = np.random.default_rng(seed if scene_seed is None else scene_seed)
    rng = np.random.default_rng([seed, 7919])
    w, h = size
    K = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
    centre = np.array([0.0, 0.0, 7.0])
    ang = geo.uniform(0, 2 * np.pi)
    C = np.array([np.cos(ang), 0.25 * np.sin(ang), 0.0])
    C[2] = geo.uniform(-0.2, 0.2)
    C /= np.linalg.norm(C)
    if offset_axes:
        centre = np.array([geo.choice([-1.0, 1.0]) * 1.5, geo.uniform(-1.0, 1.0), 7.0])
    # Look-at rotation (cam_from_world rows = camera axes in camera-i frame).
    zc = centre - C
    zc /= np.linalg.norm(zc)
    xc = np.cross([0.0, 1.0, 0.0], zc)
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    Rj = np.stack([xc, yc, zc])
    # A random roll about camera j's optical axis.
    Rj = so3.exp(np.array([0.0, 0.0, geo.uniform(-0.3, 0.3)])) @ Rj
    tj = -Rj @ C
    pts = []
    total = 0
    while total < n_points:
        m = 4 * n_points + 64
        z = geo.uniform(4.0, 10.0, m)
        u = geo.uniform(0, w, m)
        v = geo.uniform(0, h, m)
        X = np.column_stack([(u - K[0, 2]) / focal * z, (v - K[1, 2]) / focal * z, z])
        Xj = X @ Rj.T + tj
        uvj = Xj @ K.T
        uvj = uvj[:, :2] / uvj[:, 2:3]
        ok = (Xj[:, 2] > 0.5) & (uvj[:, 0] >= 0) & (uvj[:, 0] < w) & (uvj[:, 1] >= 0) & (uvj[:, 1] < h)
        pts.append(X[ok])
        total += int(ok.sum())
    X = np.concatenate(pts)[:n_points]
    xi_true = (X @ K.T)[:, :2] / X[:, 2:3]
    Xj = X @ Rj.T + tj
    xj_true = (Xj @ K.T)[:, :2] / Xj[:, 2:3]
    x_i = xi_true + sigma_px * rng.standard_normal((n_points, 2))
    x_j = xj_true + sigma_px * rng.standard_normal((n_points, 2))
    n_out = int(round(outlier_frac * n_points))
    outlier = np.zeros(n_points, dtype=bool)
    if n_out:
        idx = rng.choice(n_points, n_out, replace=False)
        outlier[idx] = True
        cand = rng.uniform([0, 0], [w, h], (n_out, 2))
        far = np.linalg.norm(cand - xj_true[idx], axis=1) < 20.0
        while np.any(far):
            cand[far] = rng.uniform([0, 0], [w, h], (int(far.sum()), 2))
            far = np.linalg.norm(cand - xj_true[idx], axis=1) < 20.0
        x_j[idx] = cand
    d = rng.standard_normal(3)
    R0 = so3.exp(np.deg2rad(init_perturb_deg) * d / np.linalg.norm(d)) @ Rj
    e = rng.standard_normal(3)
    e -= e.dot(tj) * tj
    t0 = tj + np.tan(np.deg2rad(init_perturb_deg)) * e / max(np.linalg.norm(e), 1e-12)
    t0 /= np.linalg.norm(t0)
    return SyntheticPair(x_i=x_i, x_j=x_j, K_i=K, K_j=K.copy(), R=Rj, t=tj, points=X, outlier_mask=outlier, R0=R0, t0=t0)


def synthetic_pairs(n_cams: int, n_points: int = 60, sigma_px: float = 0.5, outlier_frac: float = 0.0
                    ) -> tuple[list[str], np.ndarray, list[SyntheticPair]]:
    """A :func:`synthetic_pair` on every edge ``(i, j)``, ``i < j``, of ``n_cams`` cameras.

    Each pair is its own scene (seed ``10 i + j``): the pairs are not views of one
    world, which a per-pair stage does not need.

    Args:
        n_cams: number of cameras (names ``im0.png``, ...).
        n_points, sigma_px, outlier_frac: as in :func:`synthetic_pair`.

    Returns:
        ``(names, edges (M, 2), pairs)`` with the pairs in edge order.
    """
    if n_cams < 2:
        raise ValueError(f"n_cams={n_cams} but expected >= 2")
    edges, pairs = [], []
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            edges.append((i, j))
            pairs.append(synthetic_pair(n_points, sigma_px=sigma_px, outlier_frac=outlier_frac, seed=10 * i + j))
    return [f"im{k}.png" for k in range(n_cams)], np.array(edges, dtype=np.int64), pairs


def perturbed_focal(K: np.ndarray, rel_error: float, seed: int) -> np.ndarray:
    """``K`` with its focal lengths scaled by a uniform random factor in ``1 ± rel_error``: a start value.

    Args:
        K: (3, 3) true intrinsics.  rel_error: largest relative error.  seed: seed of the factor.
    """
    out = np.array(K, dtype=np.float64)
    out[:2, :2] *= 1.0 + np.random.default_rng([seed, 31337]).uniform(-rel_error, rel_error)
    return out
