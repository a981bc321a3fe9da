"""A shared focal length from the two-view geometry of a whole view graph (no K, no EXIF needed).

Pure kernels on arrays (no I/O); the cameras stage (:mod:`pipeline.frontend.camera_stage`)
calls them per pair and on the graph.

1. :func:`fundamental_ransac`: F of one pair from raw pixels (pycolmap's LO-RANSAC,
   trials capped) and :func:`homography_ratio`, which flags planar and zero-baseline
   pairs: their F says nothing about the focal length.
2. :func:`pair_profile`: the pair's profile likelihood over a grid of focal lengths,
   ``C(f) = min_{R,t} Σ ρ(Sampson_px²)`` on its F inliers. At each f the relative pose
   starts from the decomposition of ``E = K(f)ᵀ F K(f)`` and from the previous grid
   point's optimum and PoseLib (``refine_relative_pose``, Cauchy loss) refines it.
3. :func:`profile_cost`: each pair's profile normalized by its own σ² (a Δχ²) and
   capped (``cap·log(1 + Δ/cap)``), summed over pairs: degenerate pairs (flat
   profiles) add nothing, a wrong pair cannot dominate.
4. :func:`rotation_consistency_cost`: at each grid focal the pairs' refined rotations
   are averaged (chordal, then Cauchy-weighted chordal steps) and the robust residual
   is the cost. It fixes f where F cannot: on a ring such as templeSparseRing, whose
   pairs all sit near Sturm's degenerate configuration for a shared focal, the
   rotations must add up around the ring.
5. :func:`joint_focal`: the sum of both costs, each divided by its range over the
   grid, minimized with a parabola in log f (research r13: within 1.4% on fountain,
   castle and temple; pycolmap's ``calibrate_view_graph`` misses temple by 49%).

:func:`poselib_shared_focal` (PoseLib's 6-point shared-focal solver per pair,
combined by a median) is the maintained alternative.

Conventions: pixels with the centre of the top-left pixel at (0, 0) (OpenCV, our
front end); ``x2ᵀ F x1 = 0``; ``x2 = R x1 + t`` (pycolmap ``cam2_from_cam1``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from pipeline.core import so3
from pipeline.geometry.epipolar import pose_from_essential, sampson_for_matrix

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__all__ = ["CHI2_1_MEDIAN", "PairF", "fundamental_ransac", "homography_ratio", "log_grid", "K_from_focal",
           "sampson_px", "pair_profile", "profile_cost", "rotation_consistency_cost", "chordal_average",
           "joint_focal", "refine_min", "poselib_shared_focal"]

CHI2_1_MEDIAN = 0.454936


def K_from_focal(f: float, pp: np.ndarray) -> np.ndarray:
    """(3, 3) pinhole K with one focal ``f`` (px) and principal point ``pp`` (2,)."""
    return np.array([[f, 0.0, pp[0]], [0.0, f, pp[1]], [0.0, 0.0, 1.0]])


def log_grid(lo: float, hi: float, n: int) -> np.ndarray:
    """``n`` log-spaced values from ``lo`` to ``hi``."""
    return np.exp(np.linspace(np.log(lo), np.log(hi), n))


def sampson_px(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (px) of matches ``x1 ↔ x2`` (n, 2) under F (``x2ᵀ F x1 = 0``)."""
    return sampson_for_matrix(F, x1, x2)


@dataclass
class PairF:
    """F of one pair and its inliers.

    Attributes:
        F: (3, 3) unit-norm fundamental matrix, ``x2ᵀ F x1 = 0``.
        inliers: (k,) indices into the putative matches.
        n_matches: putative matches.
    """

    F: np.ndarray
    inliers: np.ndarray
    n_matches: int


def fundamental_ransac(x1: np.ndarray, x2: np.ndarray, max_error_px: float, seed: int = 0, max_trials: int = 10000,
                       min_inliers: int = 30) -> PairF | None:
    """Robust F from pixel correspondences (pycolmap ``estimate_fundamental_matrix``: LO-RANSAC + Sampson polish).

    Args:
        x1, x2: (n, 2) putative matches (px).
        max_error_px: inlier threshold (px).
        seed: RANSAC seed.
        max_trials: iteration cap (pycolmap's default of 100000 costs minutes on a bad pair).
        min_inliers: fewer inliers give None.
    Returns:
        :class:`PairF`, or None.
    """
    import pycolmap  # noqa: PLC0415 - heavy import, only where F is estimated

    x1 = np.ascontiguousarray(x1, np.float64)
    x2 = np.ascontiguousarray(x2, np.float64)
    if len(x1) < max(8, min_inliers):
        return None
    o = pycolmap.RANSACOptions()
    o.max_error = float(max_error_px)
    o.random_seed = int(seed)
    o.max_num_trials = int(max_trials)
    o.min_num_trials = min(100, int(max_trials))
    o.confidence = 0.9999
    r = pycolmap.estimate_fundamental_matrix(x1, x2, o)
    if r is None:
        return None
    idx = np.flatnonzero(np.asarray(r["inlier_mask"], bool).ravel())
    if len(idx) < min_inliers:
        return None
    F = np.asarray(r["F"], np.float64)
    return PairF(F=F / np.linalg.norm(F), inliers=idx, n_matches=len(x1))


def homography_ratio(x1: np.ndarray, x2: np.ndarray, max_error_px: float, seed: int = 0) -> float:
    """Homography inliers over the number of matches given (COLMAP calls a pair planar or panoramic above 0.8)."""
    import cv2  # noqa: PLC0415

    if len(x1) < 4:
        return 1.0
    cv2.setRNGSeed(int(seed))
    H, m = cv2.findHomography(np.asarray(x1, np.float64), np.asarray(x2, np.float64), cv2.RANSAC,
                              float(max_error_px), maxIters=2000, confidence=0.999)
    return 0.0 if H is None else float(m.sum()) / len(x1)


# ------------------------------------------------------------------ per-pair profile
def _pose_sampson(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray
                  ) -> np.ndarray:
    """Sampson distances (px) of pixel matches under the pose (R, t) and intrinsics K1, K2."""
    E = np.cross(t[None, :], R.T).T  # [t]× R
    return sampson_for_matrix(np.linalg.inv(K2).T @ E @ np.linalg.inv(K1), x1, x2)


def pair_profile(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, pp1: np.ndarray, pp2: np.ndarray,
                 f1: np.ndarray, f2: np.ndarray, c_px: float = 2.0, iterations: int = 25,
                 ends: tuple[tuple[np.ndarray, np.ndarray] | None, tuple[np.ndarray, np.ndarray] | None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Profile cost of one pair along a path of focal lengths.

    At grid point g the cameras have focals ``f1[g]``, ``f2[g]`` (equal for a shared
    focal); the cost is ``min_{R,t} Σ c² log(1 + s²/c²)`` over the Sampson distances s
    (px). The minimization is local (PoseLib's refinement) and a pair's cost can have
    several basins, so each point is refined from several starts and the best kept: the
    decomposition of ``K2ᵀ F K1``, the previous point's optimum (a forward sweep), the next
    point's (a backward sweep), and, with ``ends``, the optima of the points just outside the
    path (a finer grid between two points of a coarser one starts from theirs). Without the
    backward sweep and the ends, a finer grid could settle in a worse basin than the coarse
    points beside it, and the joint minimum then fell on a coarse point for no reason
    (a real pair: 411 px² above its coarse neighbours at every fine point).

    Args:
        x1, x2: (n, 2) inlier pixels.  F: (3, 3).  pp1, pp2: (2,) principal points.
        f1, f2: (G,) focal lengths along the path.  c_px: Cauchy scale (px).
        iterations: LM iterations per refinement.
        ends: ``(before, after)`` poses ``(R, t)`` (or None) of the points just outside the path.
    Returns:
        ``(cost (G,) px², rotations (G, 3, 3) cam2_from_cam1, σ² px², translations (G, 3))``;
        σ² from the median squared Sampson distance at the best grid point.
    """
    import poselib  # noqa: PLC0415

    cam = {"model": "SIMPLE_PINHOLE", "width": 0, "height": 0, "params": [1.0, 0.0, 0.0]}
    G = len(f1)
    cost = np.full(G, np.inf)
    Rs = np.empty((G, 3, 3))
    ts = np.empty((G, 3))
    c2 = c_px * c_px
    before, after = ends if ends is not None else (None, None)

    def refine(g: int, starts: list[tuple[np.ndarray, np.ndarray]], decompose: bool = False) -> None:
        """Refine point g from ``starts`` (and, with ``decompose``, from the decomposition of K2ᵀ F K1)."""
        a, b = float(f1[g]), float(f2[g])
        K1, K2 = K_from_focal(a, pp1), K_from_focal(b, pp2)
        y1, y2 = (x1 - pp1) / a, (x2 - pp2) / b
        if decompose:
            U, _, Vt = np.linalg.svd(K2.T @ F @ K1)
            starts = [pose_from_essential(U @ np.diag([1.0, 1.0, 0.0]) @ Vt, y1, y2, np.ones(len(x1), bool))[:2],
                      *starts]
        opts = {"loss_type": "CAUCHY", "loss_scale": c_px / np.sqrt(a * b), "max_iterations": iterations}
        for Rs0, ts0 in starts:
            pose0 = poselib.CameraPose()
            pose0.R = Rs0
            pose0.t = ts0 / max(np.linalg.norm(ts0), 1e-300)
            pose, _ = poselib.refine_relative_pose(y1, y2, pose0, cam, cam, opts)
            R, t = np.asarray(pose.R), np.asarray(pose.t)
            s = _pose_sampson(R, t, x1, x2, K1, K2)
            c = float(c2 * np.log1p(s * s / c2).sum())
            if c < cost[g]:
                cost[g], Rs[g], ts[g] = c, R, t

    prev = before
    for g in range(G):  # forward: a 1-D sweep (tens of points); the work inside is vectorized over the matches
        refine(g, [] if prev is None else [prev], decompose=True)
        prev = (Rs[g], ts[g])
    nxt = after
    for g in range(G - 1, -1, -1):  # backward: each point also from the next one's optimum
        if nxt is not None:
            refine(g, [nxt])
        nxt = (Rs[g], ts[g])
    g = int(np.argmin(cost))
    s = _pose_sampson(Rs[g], ts[g], x1, x2, K_from_focal(f1[g], pp1), K_from_focal(f2[g], pp2))
    return cost, Rs, max(float(np.median(s * s)) / CHI2_1_MEDIAN, 1e-6), ts


def profile_cost(cost: np.ndarray, sigma2: np.ndarray, cap: float = 25.0) -> np.ndarray:
    """Robust sum over pairs of their normalized profiles: ``Σ_k cap·log(1 + ΔC_k(f)/(σ²_k cap))``.

    Args:
        cost: (M, G) per-pair profile costs (px²).  sigma2: (M,) per-pair σ² (px²).
        cap: where a pair's Δχ² stops counting fully.
    Returns:
        (G,) joint cost.
    """
    d = (cost - cost.min(axis=1, keepdims=True)) / sigma2[:, None]
    return (cap * np.log1p(d / cap)).sum(axis=0)


# --------------------------------------------------------------- rotation consistency
def chordal_average(edges: np.ndarray, R_rel: np.ndarray, n: int, w: np.ndarray | None = None) -> np.ndarray:
    """Weighted chordal ℓ2 rotation averaging (spectral relaxation, then projection).

    Minimizes ``Σ w ‖R_j − R_ij R_i‖²_F`` over cam_from_world ``R_i`` through the top three
    eigenvectors of the 3N×3N connection matrix (N ≤ a few hundred here).

    Args:
        edges: (M, 2) camera indices.  R_rel: (M, 3, 3) ``R_ij``.  n: cameras.  w: (M,) weights.
    Returns:
        (n, 3, 3) rotations, camera 0 the identity.
    """
    w = np.ones(len(edges)) if w is None else w
    A = np.zeros((n, n, 3, 3))
    wR = w[:, None, None] * R_rel
    np.add.at(A, (edges[:, 1], edges[:, 0]), wR)
    np.add.at(A, (edges[:, 0], edges[:, 1]), np.swapaxes(wR, 1, 2))
    lam, V = np.linalg.eigh(A.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n))
    Y = V[:, -3:] * np.sqrt(np.maximum(lam[-3:], 0.0))
    if np.sum(np.linalg.det(Y.reshape(n, 3, 3)) < 0) > n / 2:
        Y[:, 0] *= -1.0  # the eigenvectors fix Y only up to O(3): make most blocks proper rotations
    R = so3.project_to_so3(Y.reshape(n, 3, 3))
    return R @ R[0].T


def rotation_consistency_cost(R_rel: np.ndarray, edges: np.ndarray, n: int, loss_deg: float = 2.0,
                              steps: int = 10) -> np.ndarray:
    """Robust rotation-averaging residual of the pairs' rotations at each grid focal.

    Args:
        R_rel: (M, G, 3, 3) each pair's refined rotation at each grid point.
        edges: (M, 2) camera indices (into ``n`` cameras).
        n: cameras.  loss_deg: Cauchy scale of the residual angle.  steps: reweighted averaging steps.
    Returns:
        (G,) cost ``Σ c² log(1 + (θ/c)²)`` (rad²) at each grid point.
    """
    c = np.deg2rad(loss_deg)
    out = np.empty(R_rel.shape[1])
    for g in range(R_rel.shape[1]):  # a 1-D sweep; each averaging is vectorized over edges
        Rg = R_rel[:, g]
        w = None
        for _ in range(steps + 1):
            R = chordal_average(edges, Rg, n, w)
            # residual of each edge: R_jᵀ R_ij R_i (paper 1, eq. 7)
            a = so3.angle(np.swapaxes(R[edges[:, 1]], 1, 2) @ Rg @ R[edges[:, 0]])
            w = 1.0 / (1.0 + (a / c) ** 2)
        out[g] = float((c * c * np.log1p((a / c) ** 2)).sum())
    return out


def refine_min(grid: np.ndarray, cost: np.ndarray) -> float:
    """Minimizer of a sampled 1-D cost: a parabola in log f through the best grid point and its neighbours."""
    k = int(np.argmin(cost))
    if k == 0 or k == len(cost) - 1:
        return float(grid[k])
    x = np.log(grid[k - 1:k + 2])
    A = np.column_stack([x**2, x, np.ones(3)])
    a, b, _ = np.linalg.solve(A, cost[k - 1:k + 2])
    if a <= 0:
        return float(grid[k])
    return float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))


def joint_focal(grid: np.ndarray, profile: np.ndarray, rotation: np.ndarray | None,
                scales: tuple[float, float] | None = None) -> tuple[float, np.ndarray, tuple[float, float]]:
    """The focal minimizing ``profile/range_p + rotation/range_r`` over ``grid`` (research r13's profile+rotcons).

    Args:
        grid: (G,) focal lengths, increasing.  profile, rotation: (G,) costs (rotation may be None).
        scales: the two ranges to divide by; default their ranges over this grid (pass
            the coarse grid's to keep the same weighting on a refined grid).
    Returns:
        ``(f, summed cost (G,), scales)``.
    """
    if scales is None:
        rp = max(float(profile.max() - profile.min()), 1e-300)
        rr = 1.0 if rotation is None else max(float(rotation.max() - rotation.min()), 1e-300)
        scales = (rp, rr)
    J = profile / scales[0] + (0.0 if rotation is None else rotation / scales[1])
    return refine_min(grid, J), J, scales


def poselib_shared_focal(x1: np.ndarray, x2: np.ndarray, pp: np.ndarray, max_error_px: float, seed: int = 0,
                         max_trials: int = 10000) -> tuple[float, int]:
    """PoseLib's 6-point shared-focal relative pose (RANSAC + refinement) on one pair.

    Returns:
        ``(f, inliers)``; f is NaN when PoseLib finds no model.
    """
    import poselib  # noqa: PLC0415

    x1 = np.ascontiguousarray(x1, np.float64)
    x2 = np.ascontiguousarray(x2, np.float64)
    try:
        pair, info = poselib.estimate_shared_focal_relative_pose(
            x1, x2, np.asarray(pp, np.float64),
            {"max_epipolar_error": float(max_error_px), "seed": int(seed), "max_iterations": int(max_trials)}, {})
    except (RuntimeError, ValueError):
        return float("nan"), 0
    return float(pair.camera1.focal()), int(np.sum(info["inliers"]))
