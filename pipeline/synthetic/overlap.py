"""The truth of which views of a rendered scene overlap: surface points seen by both views, from similar directions.

Surface points are sampled uniformly by area on the scene's planes (masks respected); a
point is *seen* by a view when it is in front, inside the image, not occluded (the
view's depth map) and not at a grazing angle (incidence below ``max_incidence_deg``). A
pair's overlap is the number of points seen by both views *with the two viewing rays at
the point within* ``max_ray_deg`` (what a SIFT descriptor can still match: an affine tilt
of about 2), divided by the number seen by the view that sees fewer. Pairs at or above a
threshold (0.3) *truly overlap*. Pure functions on arrays.
"""

from __future__ import annotations

import numpy as np

from pipeline.synthetic.scene import Plane

__all__ = ["sample_surface", "visibility", "covisibility", "true_pairs"]


def sample_surface(planes: list[Plane], density: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points sampled uniformly by area on the planes, where their mask (if any) is set.

    Args:
        planes: the scene; a plane with a ``mask`` attribute ((h, w) uint8) exists only where it is > 0.
        density: points per world unit².
    Returns:
        X (P, 3) world points and their outward normals (P, 3).
    """
    Xs, Ns = [], []
    for pl in planes:  # one vectorized draw per plane
        h, w = pl.texture.shape[:2]
        area = np.linalg.norm(np.cross(pl.a * w, pl.b * h))
        uv = rng.uniform([0, 0], [w, h], (max(1, int(round(area * density))), 2))
        m = getattr(pl, "mask", None)
        if m is not None:
            uv = uv[m[np.clip(uv[:, 1].astype(int), 0, h - 1), np.clip(uv[:, 0].astype(int), 0, w - 1)] > 0]
        Xs.append(pl.origin + uv[:, :1] * pl.a + uv[:, 1:] * pl.b)
        Ns.append(np.broadcast_to(pl.normal, (len(uv), 3)))
    return np.concatenate(Xs), np.concatenate(Ns)


def visibility(X: np.ndarray, normals: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
               depths: list[np.ndarray], max_incidence_deg: float = 80.0, depth_tol: float = 0.01) -> np.ndarray:
    """(N, P) bool: point p is seen by view n (in front, in the image, unoccluded, not grazing).

    Args:
        X: (P, 3) points; normals: (P, 3) outward unit normals.
        K, R, t: (N, 3, 3), (N, 3, 3), (N, 3) cameras (cam_from_world); depths: N (h, w) depth maps (inf: empty).
    """
    centres = -np.einsum("nji,nj->ni", R, t)
    vis = np.zeros((len(R), len(X)), bool)
    cos_max = np.cos(np.deg2rad(max_incidence_deg))
    for n in range(len(R)):  # one vectorized projection per view
        Xc = X @ R[n].T + t[n]
        z = Xc[:, 2]
        x = Xc @ K[n].T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
        hh, ww = depths[n].shape
        ok = (z > 0) & (u >= 0) & (u <= ww - 1) & (v >= 0) & (v <= hh - 1)
        ui = np.clip(np.nan_to_num(np.round(u)), 0, ww - 1).astype(int)
        vi = np.clip(np.nan_to_num(np.round(v)), 0, hh - 1).astype(int)
        ok &= np.abs(depths[n][vi, ui] - z) < depth_tol * np.maximum(z, 1e-9) + 2e-3
        ray = centres[n] - X
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        vis[n] = ok & (np.sum(ray * normals, 1) > cos_max)
    return vis


def covisibility(X: np.ndarray, vis: np.ndarray, centres: np.ndarray, max_ray_deg: float = 60.0) -> np.ndarray:
    """(N, N) overlap of every pair of views (module docstring); 1 on the diagonal.

    Args:
        X: (P, 3) points; vis: (N, P) from :func:`visibility`; centres: (N, 3) camera centres.
    """
    N = len(vis)
    rays = centres[:, None, :] - X[None]
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    cnt = vis.sum(1).astype(float)
    ov = np.eye(N)
    cmin = np.cos(np.deg2rad(max_ray_deg))
    for i in range(N):  # one (N, P) product per view
        both = vis[i][None] & vis & (np.einsum("pk,npk->np", rays[i], rays) >= cmin)
        ov[i] = both.sum(1) / np.maximum(np.minimum(cnt[i], cnt), 1)
    ov = np.minimum(ov, ov.T)
    np.fill_diagonal(ov, 1.0)
    return ov


def true_pairs(overlap: np.ndarray, threshold: float = 0.3) -> np.ndarray:
    """(P, 2) pairs ``i < j`` whose overlap is at least ``threshold``."""
    iu = np.triu_indices(len(overlap), 1)
    return np.stack(iu, 1)[overlap[iu] >= threshold]
