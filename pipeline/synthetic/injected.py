"""Rendered scenes whose wrong pairs are well supported: a static second object on a turntable, a repeated structure.

Each comes with its true cameras, the truly overlapping pairs (:mod:`pipeline.synthetic.overlap`)
and the *injected* pairs: pairs that do not overlap but match well on something other than
the cameras' motion. Matching the true pairs plus the injected ones (a pairs file) tests that
the front end rejects or down-weights every injected pair (issue 13, item 4):

- :func:`render_turntable_with_static`: the textured boxes of the default scene on a
  turntable (the cameras on a ring), and a second textured box beside it, fixed relative to
  the camera. Every pair sees that box unmoved: a consistent zero-motion match (relative
  rotation I, wrong by the turntable's angle). Injected: the opposite views (i, i + n/2),
  which share nothing but the static box;
- :func:`render_repeated`: two identical textured boxes, the copy turned by
  ``copy_angle_deg`` about the ring's axis, plus distinct boxes; views ``copy_angle_deg``
  apart see the two copies alike, and RANSAC may return the copy's pose (wrong by about
  ``copy_angle_deg``). Injected: (i, i + n/4) for three i.
"""

from __future__ import annotations

import numpy as np

from pipeline.synthetic.lowtex import LowTexScene, render_views, turntable_ring
from pipeline.synthetic.overlap import covisibility, sample_surface, true_pairs, visibility
from pipeline.synthetic.scene import Plane, _box, make_planes

__all__ = ["render_turntable_with_static", "render_repeated"]


def _truth(planes: list[Plane], K, R, t, depths, density: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    X, normals = sample_surface(planes, density, np.random.default_rng(seed + 1))
    ov = covisibility(X, visibility(X, normals, K, R, t, depths), -np.einsum("nji,nj->ni", R, t), 60.0)
    return ov, true_pairs(ov)


def _injected(n: int, step: int, starts, tp: np.ndarray) -> np.ndarray:
    pairs = {tuple(sorted((i, (i + step) % n))) for i in starts} - {tuple(p) for p in tp.tolist()}
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def render_turntable_with_static(n_views: int = 16, seed: int = 0, static_scale: float = 0.5,
                                 static_offset=(2.3, 1.5, 6.0), noise_sigma: float = 1.0, width: int = 640,
                                 height: int = 480, focal: float = 560.0) -> LowTexScene:
    """The turntable scene with a static box (module docstring); ``info["injected"]`` lists the injected pairs.

    Args:
        static_offset: the static box's centre in the camera frame (x right, y down, z forward).
        static_scale: its size factor.
    """
    rng = np.random.default_rng(seed)
    planes = [p for p in make_planes(int(rng.integers(2**31))) if p.name not in ("ground", "wall")]
    K, R, t = turntable_ring(n_views, 8.0, 28.0, [0.0, 0.3, 0.8], focal, width, height,
                             np.random.default_rng(int(rng.integers(2**31))), jitter=0.03)
    s = static_scale
    sb = _box((0.0, 0.0), (0.9 * s, 0.9 * s, 1.0 * s), np.deg2rad(30), 220.0,
              np.random.default_rng(int(rng.integers(2**31))), "static")
    # the box's own frame has z up; in the camera frame up is -y
    Rs = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]) @ np.array(
        [[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1]])
    images, depths = render_views(planes, K, R, t, width, height, noise_sigma=noise_sigma,
                                  rng=np.random.default_rng(int(rng.integers(2**31))), background=20,
                                  static=(sb, Rs, np.asarray(static_offset, float)))
    ov, tp = _truth(planes, K, R, t, depths, 300.0, seed)
    inj = _injected(n_views, n_views // 2, range(n_views), tp)
    info = {"scene": "turntable+static", "seed": seed, "n_true_pairs": int(len(tp)), "injected": inj.tolist()}
    return LowTexScene([f"tt_{k:03d}.png" for k in range(n_views)], images, K, R, t, ov, tp, info)


def render_repeated(n_views: int = 16, seed: int = 0, copy_angle_deg: float = 90.0, copy_size: float = 0.8,
                    n_distinct: int = 8, noise_sigma: float = 1.0, width: int = 640, height: int = 480,
                    focal: float = 560.0, injected_starts=(0, 5, 10)) -> LowTexScene:
    """Two identical boxes and distinct ones on a ring (module docstring); ``info["injected"]`` lists the injected pairs."""
    rng = np.random.default_rng(seed)
    tex_rng = np.random.default_rng(int(rng.integers(2**31)))
    box_a = _box((1.8, 0.0), tuple(copy_size * np.array([1.4, 1.2, 1.6])), np.deg2rad(20), 220.0, tex_rng, "A")
    a = np.deg2rad(copy_angle_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    box_b = [Plane(Rz @ p.origin, Rz @ p.a, Rz @ p.b, p.texture, p.name.replace("A", "B")) for p in box_a]
    spots = [(-1.6, -1.2), (-1.2, 1.4), (0.4, -1.9), (-0.2, 0.2), (1.0, 1.9), (-2.3, 0.1), (1.2, -1.0), (0.3, 1.0)]
    others: list[Plane] = []
    for k, (x, y) in enumerate(spots[:n_distinct]):
        others += _box((x, y), (0.7, 0.7, 0.6 + 0.25 * (k % 4)), tex_rng.uniform(0, np.pi), 220.0, tex_rng, f"o{k}")
    planes = box_a + box_b + others
    K, R, t = turntable_ring(n_views, 9.0, 30.0, [0.0, 0.0, 0.7], focal, width, height,
                             np.random.default_rng(int(rng.integers(2**31))), jitter=0.03)
    images, depths = render_views(planes, K, R, t, width, height, noise_sigma=noise_sigma,
                                  rng=np.random.default_rng(int(rng.integers(2**31))), background=20)
    ov, tp = _truth(planes, K, R, t, depths, 200.0, seed)
    step = int(round(copy_angle_deg / 360.0 * n_views))
    inj = _injected(n_views, step, injected_starts, tp)
    info = {"scene": "repeated", "seed": seed, "copy_angle_deg": copy_angle_deg, "n_true_pairs": int(len(tp)),
            "injected": inj.tolist()}
    return LowTexScene([f"rep_{k:03d}.png" for k in range(n_views)], images, K, R, t, ov, tp, info)
