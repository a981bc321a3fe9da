"""View-dependent appearance of the low-texture turntable: shading computed per texel, per view.

:func:`texel_shading` returns the grey levels of one plane's albedo texture as one view sees
it: Lambertian ``albedo·(ambient + (1 − ambient)·max(0, n·l))`` with the light direction
``l`` taken at every texel (a point lamp near the object makes the shading vary within a
facet), the normal ``n`` interpolated across the facet when the plane carries
``edge_normals`` (the sides of a prism then shade like a smooth cylinder: Phong
interpolation), and optionally a Blinn–Phong specular lobe
``specular·max(0, n·h)^shininess`` (``h`` the half vector of the light and the view) that
moves with the camera. With a lamp fixed to the camera, none of these is fixed to the
surface: features on shading gradients, on highlights and on the sliding occluding contour
match between views without being one 3-D point. Vectorized over texels (no loop over pixels).
"""

from __future__ import annotations

import numpy as np

__all__ = ["texel_normals", "texel_shading"]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def texel_normals(normal: np.ndarray, edge_normals: np.ndarray | None, h: int, w: int, smooth: bool) -> np.ndarray:
    """(h, w, 3) outward unit normals at the texel centres: the plane's ``normal`` everywhere, or, when
    ``smooth`` and ``edge_normals`` (2, 3) are given (the normals at texture column 0 and column w), their
    normalized linear interpolation across the columns."""
    if not smooth or edge_normals is None:
        return np.broadcast_to(np.asarray(normal, float), (h, w, 3))
    s = ((np.arange(w) + 0.5) / w)[:, None]
    n = _unit((1 - s) * edge_normals[0] + s * edge_normals[1])  # (w, 3)
    return np.broadcast_to(n[None], (h, w, 3))


def texel_shading(albedo: np.ndarray, origin: np.ndarray, a: np.ndarray, b: np.ndarray, normal: np.ndarray,
                  light: np.ndarray, eye: np.ndarray, ambient: float, *, edge_normals: np.ndarray | None = None,
                  smooth: bool = True, specular: float = 0.0, shininess: float = 30.0) -> np.ndarray:
    """(h, w) float grey levels (not clipped) of the plane ``X(u, v) = origin + u·a + v·b`` with albedo
    texture ``albedo`` (h, w), lit by a point lamp at ``light`` (3,) and seen from ``eye`` (3,) (module docstring).

    Args:
        smooth: interpolate ``edge_normals`` across the facet (else the plane's normal).
        specular: peak grey levels of the highlight (0: none); shininess: its exponent (larger: tighter).
    """
    h, w = albedo.shape
    u, v = np.arange(w) + 0.5, np.arange(h) + 0.5
    X = origin + u[None, :, None] * a + v[:, None, None] * b  # (h, w, 3)
    n = texel_normals(normal, edge_normals, h, w, smooth)
    lv = _unit(light - X)
    ndl = np.einsum("hwk,hwk->hw", n, lv)
    out = albedo * (ambient + (1 - ambient) * np.maximum(ndl, 0.0))
    if specular > 0:
        half = _unit(lv + _unit(eye - X))
        ndh = np.maximum(np.einsum("hwk,hwk->hw", n, half), 0.0)
        out = out + specular * np.where(ndl > 0, ndh ** shininess, 0.0)
    return out
