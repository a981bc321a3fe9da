"""Epipolar primitives on arrays: normalized coordinates, E, Sampson distances, depths, rotation-only fits.

Convention: a pair ``(i, j)`` has ``x_j = R x_i + t`` for points in the camera
frames, i.e. ``R = R_ij = R_j R_iᵀ`` is pycolmap's ``cam2_from_cam1`` rotation and
``t`` its translation (unit norm where it is a direction). Normalized image
coordinates are ``y = K⁻¹ x`` (pixels to the plane z = 1).
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.core import so3

__all__ = ["normalize", "essential_from_Rt", "sampson_distance", "sampson_for_matrix", "refine_pose", "rotation_from_bearings",
           "rotation_only_residual_px", "triangulation_depths", "pose_from_essential"]


def normalize(x: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n, 2) pixels → (n, 2) normalized image coordinates ``K⁻¹ x``."""
    xh = np.column_stack([x, np.ones(len(x))])
    y = xh @ np.linalg.inv(K).T
    return y[:, :2] / y[:, 2:3]


def essential_from_Rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``E = [t]× R`` for ``x_j = R x_i + t`` (normalized so that ‖E‖_F = √2 for unit t)."""
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def sampson_distance(R: np.ndarray, t: np.ndarray, y_i: np.ndarray, y_j: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (normalized units) of matches under ``E = [t]× R``.

    Args:
        R: (3, 3) cam2_from_cam1; t: (3,); y_i, y_j: (n, 2) normalized coordinates.
    Returns:
        (n,) distances; multiply by the focal length for pixels.
    """
    E = np.cross(t[None, :], R.T).T  # [t]× R, column by column
    return sampson_for_matrix(E, y_i, y_j)


def sampson_for_matrix(M: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Signed Sampson distances of matches under ``x_jᵀ M x_i = 0`` (M an essential or fundamental matrix).

    Args:
        M: (3, 3); x_i, x_j: (n, 2) points in the units of M (normalized for E, pixels for F).
    Returns:
        (n,) distances in the same units.
    """
    hi = np.column_stack([x_i, np.ones(len(x_i))])
    hj = np.column_stack([x_j, np.ones(len(x_j))])
    Ex = hi @ M.T
    Etx = hj @ M
    num = np.sum(hj * Ex, axis=1)
    den = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-30))


def refine_pose(R0: np.ndarray, t0: np.ndarray, y_i: np.ndarray, y_j: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimize the soft-ℓ1 Sampson error over (R, t) with ‖t‖ = 1 (5 dof).

    Args:
        R0, t0: initial pose (``x_j = R x_i + t``).
        y_i, y_j: (n, 2) normalized inlier coordinates.
        scale: soft-ℓ1 scale in normalized units (the inlier threshold).
    Returns:
        refined ``(R, t)``.
    """
    from scipy.optimize import least_squares  # noqa: PLC0415 - scipy.optimize is slow to import

    t0 = t0 / np.linalg.norm(t0)
    # orthonormal basis of the tangent plane of the unit sphere at t0
    B = np.linalg.svd(t0[None, :])[2][1:].T  # (3, 2)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = so3.exp(p[:3]) @ R0  # left perturbation, as in the view graph's convention
        t = t0 + B @ p[3:]
        return R, t / np.linalg.norm(t)

    res = least_squares(lambda p: sampson_distance(*unpack(p), y_i, y_j), np.zeros(5), loss="soft_l1", f_scale=scale,
                        method="trf", x_scale=1.0, max_nfev=50)
    return unpack(res.x)


def rotation_from_bearings(y_i: np.ndarray, y_j: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rotation with ``b_j ≈ R b_i`` for unit bearings of normalized points (Kabsch).

    Args:
        y_i, y_j: (n, 2) normalized coordinates; w: (n,) weights or None.
    Returns:
        (3, 3) cam2_from_cam1 rotation.
    """
    bi = np.column_stack([y_i, np.ones(len(y_i))])
    bj = np.column_stack([y_j, np.ones(len(y_j))])
    bi /= np.linalg.norm(bi, axis=1, keepdims=True)
    bj /= np.linalg.norm(bj, axis=1, keepdims=True)
    w = np.ones(len(bi)) if w is None else w
    U, _, Vt = np.linalg.svd((bj * w[:, None]).T @ bi)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_only_residual_px(R: np.ndarray, x_i: np.ndarray, x_j: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> np.ndarray:
    """(n,) distances in image j between x_j and x_i mapped by ``K_j R K_i⁻¹`` (pixels)."""
    Hinf = K_j @ R @ np.linalg.inv(K_i)
    p = np.column_stack([x_i, np.ones(len(x_i))]) @ Hinf.T
    return np.linalg.norm(p[:, :2] / p[:, 2:3] - x_j, axis=1)


def triangulation_depths(R: np.ndarray, t: np.ndarray, y_i: np.ndarray, y_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths ``(z_i, z_j)`` (n,) of the midpoint triangulation of each match under ``x_j = R x_i + t``.

    Solves ``z_i R b_i + t ≈ z_j b_j`` in the least-squares sense, point by point in
    closed form (a 2×2 system), with ``b = (y, 1)`` so that z is the depth.
    """
    bi = np.column_stack([y_i, np.ones(len(y_i))]) @ R.T
    bj = np.column_stack([y_j, np.ones(len(y_j))])
    a11 = np.sum(bi * bi, 1)
    a12 = -np.sum(bi * bj, 1)
    a22 = np.sum(bj * bj, 1)
    r1 = -bi @ t
    r2 = bj @ t
    det = a11 * a22 - a12 * a12
    det = np.where(np.abs(det) < 1e-15, 1e-15, det)  # parallel rays: depth at "infinity", sign kept
    return (a22 * r1 - a12 * r2) / det, (a11 * r2 - a12 * r1) / det


def pose_from_essential(E: np.ndarray, y_i: np.ndarray, y_j: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The decomposition of E that puts the most masked matches in front of both cameras.

    Unlike ``cv2.recoverPose``, distant points are not discarded (OpenCV drops points
    farther than 50 baselines, which rejects every match of a small-baseline pair).

    Returns:
        R (3, 3) cam2_from_cam1, unit t (3,), and (n,) bool: masked matches with positive depths.
    """
    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.ravel()
    best = None
    for R, tt in ((R1, t), (R1, -t), (R2, t), (R2, -t)):
        zi, zj = triangulation_depths(R, tt, y_i, y_j)
        front = mask & (zi > 0) & (zj > 0)
        if best is None or front.sum() > best[2].sum():
            best = (R, tt / np.linalg.norm(tt), front)
    return best
