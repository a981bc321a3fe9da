"""The synthetic world of the renderer: textured planes, procedural textures, and camera layouts.

A scene is a set of textured rectangles that are not coplanar: a ground plane, a
back wall and boxes of different sizes standing on the ground (5 faces each). Every
rectangle carries its own procedural texture, rich in blob and corner structure
at several scales so that SIFT finds features at every octave. Conventions: world
z is up; ``R`` is cam_from_world (``x_cam = R X + t``); camera axes x right, y down,
z forward. :mod:`pipeline.synthetic.render` renders views of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from pipeline.synthetic.render import SceneConfig

__all__ = ["Plane", "procedural_texture", "make_planes", "look_at", "ring_cameras"]


@dataclass
class Plane:
    """A textured rectangle ``X(u, v) = origin + u·a + v·b`` for texture pixel ``(u, v)``.

    Attributes:
        origin: (3,) world position of texture pixel (0, 0).
        a, b: (3,) world displacement per texture pixel along u and v.
        texture: (h, w, 3) uint8 texture image.
        name: label for debugging.
    """

    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    texture: np.ndarray
    name: str = ""

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.a, self.b)
        return n / np.linalg.norm(n)

    @property
    def rgba(self) -> np.ndarray:
        """(h, w, 4) texture with an opaque alpha channel (cached)."""
        if getattr(self, "_rgba", None) is None:
            alpha = np.full(self.texture.shape[:2] + (1,), 255, np.uint8)
            self._rgba = np.concatenate([self.texture, alpha], axis=2)
        return self._rgba

    def corners(self) -> np.ndarray:
        """(4, 3) world corners."""
        h, w = self.texture.shape[:2]
        return np.stack([self.origin, self.origin + w * self.a, self.origin + w * self.a + h * self.b, self.origin + h * self.b])


def procedural_texture(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A colour texture with structure at several scales (RGB uint8, (h, w, 3)).

    Layers, from coarse to fine: smooth multi-octave value noise (blobs at every
    scale SIFT's pyramid looks at), random filled ellipses, rectangles and
    polygons (corners and edges), thin random lines, and fine speckle. Random
    colours per shape give distinct descriptors after grey conversion.
    """
    img = np.zeros((h, w, 3), np.float32)
    # multi-octave value noise: random grids upsampled with cubic interpolation
    amp = 1.0
    for cell in (256, 128, 64, 32, 16, 8):
        gh, gw = max(2, h // cell + 2), max(2, w // cell + 2)
        grid = rng.standard_normal((gh, gw, 3)).astype(np.float32)
        up = cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]
        img += amp * up
        amp *= 0.75
    img = (img - img.mean()) / (img.std() + 1e-6)
    img = np.clip(128 + 40 * img, 0, 255)
    canvas = img.astype(np.uint8).copy()
    area = h * w
    n_shapes = int(area / 700)
    # log-uniform sizes (shapes at every octave), painted largest first so that
    # the fine structure stays on top
    sizes = np.sort(np.exp(rng.uniform(np.log(4), np.log(max(8.0, min(h, w) / 10)), n_shapes)))[::-1]
    for size in sizes:
        size = float(size)
        kind = rng.integers(0, 4)
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        if kind == 0:
            axes = (max(1, int(size)), max(1, int(size * rng.uniform(0.3, 1.0))))
            cv2.ellipse(canvas, (cx, cy), axes, float(rng.uniform(0, 180)), 0, 360, color, -1, cv2.LINE_AA)
        elif kind == 1:
            s2 = size * rng.uniform(0.3, 1.0)
            ang = rng.uniform(0, np.pi)
            c, s = np.cos(ang), np.sin(ang)
            pts = np.array([[-size, -s2], [size, -s2], [size, s2], [-size, s2]]) @ np.array([[c, s], [-s, c]])
            cv2.fillConvexPoly(canvas, (pts + [cx, cy]).astype(np.int32), color, cv2.LINE_AA)
        elif kind == 2:
            k = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, k))
            rad = size * rng.uniform(0.4, 1.0, k)
            pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1)
            cv2.fillPoly(canvas, [pts.astype(np.int32)], color, cv2.LINE_AA)
        else:
            ang = rng.uniform(0, np.pi)
            d = np.array([np.cos(ang), np.sin(ang)]) * size * 2
            p0 = (int(cx - d[0]), int(cy - d[1]))
            p1 = (int(cx + d[0]), int(cy + d[1]))
            cv2.line(canvas, p0, p1, color, int(rng.integers(1, 4)), cv2.LINE_AA)
    speckle = rng.normal(0, 6, (h, w, 1)).astype(np.float32)
    out = np.clip(canvas.astype(np.float32) + speckle, 0, 255)
    return out.astype(np.uint8)


def _rect(origin, u_vec, v_vec, px_per_unit: float, rng: np.random.Generator, name: str) -> Plane:
    """A rectangle spanned by world vectors ``u_vec`` and ``v_vec`` from ``origin``."""
    u_vec, v_vec, origin = (np.asarray(x, float) for x in (u_vec, v_vec, origin))
    w = max(16, int(round(np.linalg.norm(u_vec) * px_per_unit)))
    h = max(16, int(round(np.linalg.norm(v_vec) * px_per_unit)))
    tex = procedural_texture(h, w, rng)
    return Plane(origin, u_vec / w, v_vec / h, tex, name)


def _box(center_xy, size, yaw: float, px_per_unit: float, rng: np.random.Generator, name: str) -> list[Plane]:
    """Five faces (4 sides + top) of a box standing on the ground, yawed about z."""
    sx, sy, sz = size
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey, ez = np.array([c, s, 0.0]) * sx, np.array([-s, c, 0.0]) * sy, np.array([0, 0, 1.0]) * sz
    o = np.array([center_xy[0], center_xy[1], 0.0]) - ex / 2 - ey / 2
    # each face spanned so that its normal a×b points out of the box
    faces = [
        (o + ez, ex, -ez, "front"),  # y-min side: normal = ex × (-ez) = -ey direction
        (o + ey + ex + ez, -ex, -ez, "back"),
        (o + ex + ez, ey, -ez, "right"),
        (o + ey + ez, -ey, -ez, "left"),
        (o + ez + ey, ex, -ey, "top"),
    ]
    return [_rect(p, a, b, px_per_unit, rng, f"{name}-{n}") for p, a, b, n in faces]


def make_planes(seed: int = 0, px_per_unit: float = 220.0) -> list[Plane]:
    """The scene's textured rectangles: ground, back wall and seven boxes (37 planes).

    Args:
        seed: texture seed; the geometry is fixed.
        px_per_unit: texture resolution.
    Returns:
        list of :class:`Plane`.
    """
    rng = np.random.default_rng(seed)
    planes = [
        # ground z = 0, x in [-4, 4], y in [-3.5, 3]
        _rect([-4.0, 3.0, 0.0], [8.0, 0, 0], [0, -6.5, 0], px_per_unit * 0.7, rng, "ground"),
        # back wall y = 3, x in [-4, 4], z in [0, 4]
        _rect([-4.0, 3.0, 4.0], [8.0, 0, 0], [0, 0, -4.0], px_per_unit * 0.7, rng, "wall"),
    ]
    planes += _box((0.0, 0.2), (1.6, 1.3, 1.2), np.deg2rad(25), px_per_unit, rng, "box1")
    planes += _box((1.9, 1.6), (0.9, 0.9, 1.8), np.deg2rad(-15), px_per_unit, rng, "box2")
    # smaller boxes spread over the ground put features at many depths and on many
    # planes, so that no single plane dominates a view (a dominant plane makes E ill-conditioned)
    planes += _box((-2.0, 1.8), (0.8, 0.8, 2.4), np.deg2rad(10), px_per_unit, rng, "box3")
    planes += _box((-2.3, -1.0), (0.7, 0.9, 0.7), np.deg2rad(40), px_per_unit, rng, "box4")
    planes += _box((2.4, -0.9), (1.0, 0.6, 0.9), np.deg2rad(-30), px_per_unit, rng, "box5")
    planes += _box((0.4, -2.3), (0.6, 0.6, 0.5), np.deg2rad(5), px_per_unit, rng, "box6")
    planes += _box((-0.9, 2.4), (0.9, 0.5, 1.4), np.deg2rad(0), px_per_unit, rng, "box7")
    return planes


# --------------------------------------------------------------------- cameras


def look_at(center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world ``(R, t)`` of a camera at ``center`` looking at ``target``."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)  # image y points down
    R = np.stack([x, y, z])
    return R, -R @ center


def ring_cameras(cfg: SceneConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cameras on an arc in front of the back wall, all looking at the boxes.

    Returns:
        K (N, 3, 3), R (N, 3, 3) cam_from_world, t (N, 3).
    """
    n = cfg.n_views
    target = np.array([0.5, 0.8, 0.6])
    half = np.deg2rad(cfg.arc_deg) / 2
    ang = np.linspace(-half, half, n) if n > 1 else np.zeros(1)
    K = np.array([[cfg.focal, 0, (cfg.width - 1) / 2], [0, cfg.focal, (cfg.height - 1) / 2], [0, 0, 1]])
    Rs, ts = [], []
    for a in ang:
        c = target + np.array([cfg.radius * np.sin(a), -cfg.radius * np.cos(a), cfg.height_cam - target[2]])
        c = c + rng.normal(0, cfg.jitter, 3)
        aim = target + rng.normal(0, 0.2, 3)
        R, t = look_at(c, aim)
        # a small random roll so the rotations are not all about z
        roll = rng.normal(0, np.deg2rad(3))
        cr, sr = np.cos(roll), np.sin(roll)
        Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
        Rs.append(Rz @ R)
        ts.append(Rz @ t)
    return np.repeat(K[None], n, 0), np.array(Rs), np.array(ts)


# --------------------------------------------------------------------- rendering
