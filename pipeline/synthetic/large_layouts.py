"""The layouts of the large rendered scenes: street, ring and grid (planes and cameras).

:mod:`pipeline.synthetic.large` renders them and computes which pairs truly overlap;
this module only builds the geometry. Every rectangle carries its own procedural
texture (:func:`pipeline.synthetic.scene.procedural_texture`), so that image retrieval
has something to tell apart. Each layout has a fixed camera density, so the scene grows
with the number of views and the number of truly overlapping partners per view stays
about constant (not every pair overlaps):

``street``
    A straight street along world x, lined on both sides by buildings (one facade per
    building, setbacks ±0.6 m, 2–5 balconies / bay windows protruding 0.4–1.5 m) with
    1–3 boxes per building on the sidewalks. The cameras walk down the street looking
    at the left-hand facades (y > 0), pan at the end, walk back looking at the
    right-hand ones, 2 m apart, 1.6 m high, with yaw ±15°, pitch 3–12° up and roll ±3°.
``ring``
    A central building (a convex polygon, one texture per face, with balconies)
    surrounded by statues; cameras on a circle 8 m outside it look inward, 2.5 m apart.
    The building hides the far side, so only neighbours on the circle overlap.
``grid``
    An aerial survey: cameras on a rows × cols grid, 8 m apart along track and 9 m
    across, 20 m above a ground of distinct tiles with a dense town, looking down 0–12°
    off nadir, flown as a serpentine.

Conventions as :mod:`pipeline.synthetic.scene`: world z up, ``R`` cam_from_world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.synthetic.scene import Plane, look_at, procedural_texture

__all__ = ["LAYOUTS", "LargeSceneConfig", "LargeScene", "make_scene"]

LAYOUTS = ("street", "ring", "grid")


@dataclass(frozen=True, kw_only=True)
class LargeSceneConfig:
    """Parameters of a large rendered scene.

    Attributes:
        layout: ``"street"``, ``"ring"`` or ``"grid"``.
        n_views: number of cameras.
        width, height, focal: image size and focal length (pixels); principal point at the centre.
        spacing: distance between consecutive cameras (m); None: the layout's default
            (street 2.0, ring 2.5 on the camera circle, grid 8.0 along track).
        supersample: render at this factor and area-average down.
        noise_sigma: additive Gaussian pixel noise (0–255 scale).
        texel_per_px: texture resolution relative to the image resolution at the
            layout's typical viewing distance.
        points_per_view: sampling density of the overlap points, as the expected number
            of points a view sees.
        max_tilt, max_scale: co-visibility conditions (see the module docstring and :func:`pair_overlap`).
        overlap_threshold: score at or above which a pair truly overlaps.
    """

    layout: str = "street"
    n_views: int = 100
    width: int = 640
    height: int = 480
    focal: float = 560.0
    spacing: float | None = None
    supersample: int = 2
    noise_sigma: float = 0.0
    texel_per_px: float = 1.0
    points_per_view: int = 3000
    max_tilt: float = 2.0
    max_scale: float = 2.0
    overlap_threshold: float = 0.1

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ConfigError(f"layout={self.layout!r} but expected one of {LAYOUTS}")
        if self.n_views < 2:
            raise ConfigError(f"n_views={self.n_views} but expected >= 2")


@dataclass
class LargeScene:
    """Geometry of a scene (images are rendered on demand by :func:`render_large`).

    Attributes:
        planes: textured rectangles.
        K: (3, 3) intrinsics (common to all views).
        R: (N, 3, 3) cam_from_world; t: (N, 3).
        point_density: overlap points per m² (see ``points_per_view``).
        config: the parameters.
    """

    planes: list[Plane]
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    point_density: float
    config: LargeSceneConfig

    @property
    def centers(self) -> np.ndarray:
        """(N, 3) camera centres ``-Rᵀ t``."""
        return -np.einsum("nji,nj->ni", self.R, self.t)


# ------------------------------------------------------------------ scene pieces


def _rect(origin, u_vec, v_vec, px_per_m: float, rng: np.random.Generator, name: str) -> Plane:
    """A rectangle ``origin + s·u_vec + r·v_vec`` (s, r in [0, 1]) with its own RGBA texture."""
    u_vec, v_vec, origin = (np.asarray(x, float) for x in (u_vec, v_vec, origin))
    w = max(16, int(round(np.linalg.norm(u_vec) * px_per_m)))
    h = max(16, int(round(np.linalg.norm(v_vec) * px_per_m)))
    rgba = np.empty((h, w, 4), np.uint8)
    rgba[..., :3] = procedural_texture(h, w, rng)
    rgba[..., 3] = 255
    pl = Plane(origin, u_vec / w, v_vec / h, rgba[..., :3], name)
    pl._rgba = rgba  # Plane.rgba would otherwise build (and keep) a second copy
    return pl


def _box(center_xy, size, yaw: float, px_per_m: float, rng, name: str, z0: float = 0.0,
         top: bool = True, wall_scale: float = 1.0, bottom: bool = False) -> list[Plane]:
    """Faces (4 sides, optional top and bottom) of a box whose base is at height ``z0``, yawed about z
    (a×b inward); the side faces' texture resolution is ``wall_scale · px_per_m``."""
    sx, sy, sz = size
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey, ez = np.array([c, s, 0.0]) * sx, np.array([-s, c, 0.0]) * sy, np.array([0, 0, 1.0]) * sz
    o = np.array([center_xy[0], center_xy[1], z0]) - ex / 2 - ey / 2
    faces = [(o + ez, ex, -ez, "front"), (o + ey + ex + ez, -ex, -ez, "back"),
             (o + ex + ez, ey, -ez, "right"), (o + ey + ez, -ey, -ez, "left")]
    if top:
        faces.append((o + ez + ey, ex, -ey, "top"))
    if bottom:
        faces.append((o, ex, ey, "bottom"))
    return [_rect(p, a, b, px_per_m * (1.0 if n in ("top", "bottom") else wall_scale), rng, f"{name}-{n}")
            for p, a, b, n in faces]


def _relief(p0, u, n, width: float, height: float, px_per_m: float, rng, name: str,
            count: tuple[int, int] = (2, 5)) -> list[Plane]:
    """Boxes protruding from a facade (balconies, bay windows, pilasters), so a view of it is not a
    single plane (a dominant plane makes the relative pose two-fold ambiguous).

    Args:
        p0: (3,) bottom corner of the facade where it starts; u: (3,) unit direction along it;
        n: (3,) unit horizontal normal towards the viewers; width, height: facade size (m).
    """
    u, n, p0 = (np.asarray(x, float) for x in (u, n, p0))
    yaw = float(np.arctan2(u[1], u[0]))
    out: list[Plane] = []
    for m in range(int(rng.integers(count[0], count[1] + 1))):
        bw, d, bh = rng.uniform(1.0, 3.0), rng.uniform(0.4, 1.5), rng.uniform(1.0, min(3.0, height - 0.6))
        s_ = rng.uniform(min(bw / 2 + 0.2, width / 2), max(width - bw / 2 - 0.2, width / 2))
        z0 = rng.uniform(0.3, max(0.31, height - bh - 0.3))
        c = p0 + s_ * u + (d / 2) * n
        out += _box((c[0], c[1]), (bw, d, bh), yaw, px_per_m, rng, f"{name}-r{m}", z0=z0, bottom=True)
    return out


def _ground_tiles(x0: float, x1: float, y0: float, y1: float, tile: float, px_per_m: float, rng, name: str) -> list[Plane]:
    """Ground z = 0 over [x0, x1] × [y0, y1] as tiles of about ``tile`` m, normals up."""
    nx, ny = max(1, int(np.ceil((x1 - x0) / tile))), max(1, int(np.ceil((y1 - y0) / tile)))
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    out = []
    for a in range(nx):
        for b in range(ny):
            # u along +x, v along -y: a×b = -z points into the ground (the convention of every plane here)
            out.append(_rect([xs[a], ys[b + 1], 0.0], [xs[a + 1] - xs[a], 0, 0], [0, -(ys[b + 1] - ys[b]), 0],
                             px_per_m, rng, f"{name}-{a}-{b}"))
    return out


def _cam(center, yaw: float, pitch: float, roll: float) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world of a camera at ``center`` looking along heading ``yaw`` (about z, from +x),
    elevated by ``pitch`` (up positive), rolled by ``roll`` about its optical axis."""
    d = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)])
    R, t = look_at(np.asarray(center, float), np.asarray(center, float) + d)
    cr, sr = np.cos(roll), np.sin(roll)
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return Rz @ R, Rz @ t


def _cam_down(center, heading: float, tilt: float, tilt_dir: float) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world of a camera looking down (nadir tilted by ``tilt`` towards ``tilt_dir``),
    image x axis along ``heading``."""
    d = np.array([np.sin(tilt) * np.cos(tilt_dir), np.sin(tilt) * np.sin(tilt_dir), -np.cos(tilt)])
    z = d / np.linalg.norm(d)
    xh = np.array([np.cos(heading), np.sin(heading), 0.0])
    x = xh - (xh @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ np.asarray(center, float)


# ------------------------------------------------------------------ layouts


def _street(cfg: LargeSceneConfig, rng: np.random.Generator) -> tuple[list[Plane], list, float]:
    s = cfg.spacing or 2.0
    n_pan = 7 if cfg.n_views >= 40 else 5  # 30° (or 45°) steps over 180°
    n_walk = cfg.n_views - 2 * n_pan
    n1 = (n_walk + 1) // 2
    n2 = n_walk - n1
    L = n1 * s
    x_lo, x_hi = -12.0, L + 12.0
    px_m = cfg.texel_per_px * cfg.focal / 8.0  # facades seen from about 8 m
    planes: list[Plane] = []
    for side in (+1, -1):
        x = x_lo
        k = 0
        while x < x_hi:
            w = min(rng.uniform(6, 14), x_hi - x + 1.0)
            h = rng.uniform(6, 12)
            y = side * (6.0 + rng.uniform(-0.6, 0.6))
            # a×b points away from the street (into the building), as for every plane here
            if side > 0:
                planes.append(_rect([x, y, h], [w, 0, 0], [0, 0, -h], px_m, rng, f"facadeL{k}"))
                planes += _relief([x, y, 0], [1, 0, 0], [0, -1, 0], w, h, px_m * 1.2, rng, f"facadeL{k}")
            else:
                planes.append(_rect([x + w, y, h], [-w, 0, 0], [0, 0, -h], px_m, rng, f"facadeR{k}"))
                planes += _relief([x + w, y, 0], [-1, 0, 0], [0, 1, 0], w, h, px_m * 1.2, rng, f"facadeR{k}")
            # 1–3 objects on the sidewalk in front of it (kiosks, vans, trees)
            for m in range(int(rng.integers(1, 4))):
                bx = x + rng.uniform(1, max(1.5, w - 1))
                by = side * rng.uniform(3.0, 4.8)
                size = (rng.uniform(0.6, 2.5), rng.uniform(0.5, 1.4), rng.uniform(0.8, 3.5))
                planes += _box((bx, by), size, rng.uniform(-0.3, 0.3), px_m * 1.3, rng, f"obj{side}-{k}-{m}")
            x += w
            k += 1
    # buildings closing both ends of the street (a T-junction), seen by the panning views
    for name, xe, sgn in (("endE", x_hi, +1), ("endW", x_lo, -1)):
        h = rng.uniform(8, 12)
        if sgn > 0:  # at x_hi facing -x: u along +y, a×b = (+y)×(-z) = -x... into the building is +x
            planes.append(_rect([xe, -6.6, h], [0, 13.2, 0], [0, 0, -h], px_m, rng, name))
            planes += _relief([xe, -6.6, 0], [0, 1, 0], [-1, 0, 0], 13.2, h, px_m * 1.2, rng, name)
        else:
            planes.append(_rect([xe, 6.6, h], [0, -13.2, 0], [0, 0, -h], px_m, rng, name))
            planes += _relief([xe, 6.6, 0], [0, -1, 0], [1, 0, 0], 13.2, h, px_m * 1.2, rng, name)
    planes += _ground_tiles(x_lo, x_hi, -6.6, 6.6, 8.0, px_m * 0.8, rng, "road")
    cams = []

    def walk(x: float, side: int) -> None:
        c = np.array([x + rng.normal(0, 0.2), -side * 2.0 + rng.normal(0, 0.2), 1.6 + rng.normal(0, 0.05)])
        yaw = side * np.pi / 2 + np.deg2rad(rng.uniform(-15, 15))
        cams.append(_cam(c, yaw, np.deg2rad(rng.uniform(3, 12)), np.deg2rad(rng.normal(0, 3))))

    def pan(x: float, yaws: np.ndarray) -> None:
        for yaw in yaws:  # a pan on the spot (about 10 cm of hand motion): nearly pure rotation pairs
            c = np.array([x, 0.0, 1.6]) + rng.normal(0, [0.05, 0.05, 0.02])
            cams.append(_cam(c, yaw + np.deg2rad(rng.normal(0, 3)), np.deg2rad(rng.uniform(3, 12)),
                             np.deg2rad(rng.normal(0, 3))))

    for k in range(n1):  # down the street looking at the left facades (y > 0)
        walk(k * s, +1)
    pan(L, np.linspace(np.pi / 2, -np.pi / 2, n_pan))  # turn at the east end: left side, end wall, right side
    for k in range(n2):  # back, looking at the right facades (y < 0)
        walk(L - s - k * s, -1)
    pan(-s, np.linspace(-np.pi / 2, -3 * np.pi / 2, n_pan))  # turn at the west end, closing the loop
    return planes, cams, cfg.points_per_view / 70.0  # a view sees about 70 m² of facade and ground


def _ring(cfg: LargeSceneConfig, rng: np.random.Generator) -> tuple[list[Plane], list, float]:
    s = cfg.spacing or 2.5
    r_c = max(12.0, cfg.n_views * s / (2 * np.pi))
    r_b = r_c - 8.0
    px_m = cfg.texel_per_px * cfg.focal / 8.0
    planes: list[Plane] = []
    n_faces = max(6, int(round(2 * np.pi * r_b / 7.0)))  # faces about 7 m wide
    ang = np.linspace(0, 2 * np.pi, n_faces + 1)
    for k in range(n_faces):
        p0 = r_b * np.array([np.cos(ang[k]), np.sin(ang[k])])
        p1 = r_b * np.array([np.cos(ang[k + 1]), np.sin(ang[k + 1])])
        h = rng.uniform(7, 12)
        # a×b = (p1 - p0) × (-z) points into the building for counter-clockwise p0 -> p1
        planes.append(_rect([p0[0], p0[1], h], [p1[0] - p0[0], p1[1] - p0[1], 0], [0, 0, -h], px_m, rng, f"face{k}"))
        u = np.array([p1[0] - p0[0], p1[1] - p0[1], 0.0])
        wlen = float(np.linalg.norm(u))
        u /= wlen
        planes += _relief([p0[0], p0[1], 0.0], u, [u[1], -u[0], 0.0], wlen, h, px_m * 1.2, rng, f"face{k}")
    n_obj = int(round(2 * np.pi * r_b / 6.0))
    for m in range(n_obj):
        a = rng.uniform(0, 2 * np.pi)
        r = r_b + rng.uniform(1.5, 4.0)
        size = (rng.uniform(0.6, 2.0), rng.uniform(0.6, 2.0), rng.uniform(0.8, 3.0))
        planes += _box((r * np.cos(a), r * np.sin(a)), size, rng.uniform(0, np.pi), px_m * 1.3, rng, f"statue{m}")
    R_out = r_c + 12.0
    # ground tiles of the annulus between the building and 12 m behind the cameras (tiles are
    # drawn lazily: only those whose centre is in the annulus get a texture)
    nt = int(np.ceil(2 * R_out / 8.0))
    edges = np.linspace(-R_out, R_out, nt + 1)
    for a in range(nt):
        for b in range(nt):
            ctr = np.array([edges[a] + edges[a + 1], edges[b] + edges[b + 1]]) / 2
            if r_b - 6.0 < np.linalg.norm(ctr) < R_out:
                planes.append(_rect([edges[a], edges[b + 1], 0.0], [edges[a + 1] - edges[a], 0, 0],
                                    [0, -(edges[b + 1] - edges[b]), 0], px_m * 0.8, rng, f"ground-{a}-{b}"))
    cams = []
    phis = np.linspace(0, 2 * np.pi, cfg.n_views, endpoint=False)
    for phi in phis:
        c = np.array([r_c * np.cos(phi), r_c * np.sin(phi), 1.6]) + rng.normal(0, [0.2, 0.2, 0.05])
        yaw = phi + np.pi + np.deg2rad(rng.uniform(-15, 15))
        cams.append(_cam(c, yaw, np.deg2rad(rng.uniform(3, 12)), np.deg2rad(rng.normal(0, 3))))
    return planes, cams, cfg.points_per_view / 70.0


def _grid(cfg: LargeSceneConfig, rng: np.random.Generator) -> tuple[list[Plane], list, float]:
    s = cfg.spacing or 8.0  # along track
    s_y = 9.0  # across track
    alt = 20.0
    n = cfg.n_views
    rows = max(1, int(round(np.sqrt(n * 3 / 4))))
    cols = int(np.ceil(n / rows))
    px_m = cfg.texel_per_px * cfg.focal / alt
    W, Hh = (cols - 1) * s, (rows - 1) * s_y
    m = 14.0
    planes: list[Plane] = _ground_tiles(-m, W + m, -m, Hh + m, 10.0, px_m, rng, "ground")
    # a dense town: buildings up to 10 m under cameras at 18 m, so that no view is dominated by one
    # plane (a planar view makes the relative pose two-fold ambiguous)
    n_bld = int((W + 2 * m) * (Hh + 2 * m) / 40.0)  # one building per 40 m²
    for b in range(n_bld):
        cx, cy = rng.uniform(-m, W + m), rng.uniform(-m, Hh + m)
        size = (rng.uniform(2.0, 5.0), rng.uniform(2.0, 5.0), rng.uniform(2.0, 12.0))
        # texture resolution for the distance it is seen from (a roof 10 m high is seen from 8 m:
        # a coarse texture there is blurred and gives few features, leaving only ground matches);
        # the walls, seen obliquely, at 0.6 of it
        px_roof = cfg.texel_per_px * cfg.focal / (alt - size[2])
        planes += _box((cx, cy), size, rng.uniform(0, np.pi), px_roof, rng, f"bld{b}", wall_scale=0.6)
    cams = []
    for i in range(n):
        r, c = divmod(i, cols)
        cc = c if r % 2 == 0 else cols - 1 - c  # serpentine
        heading = 0.0 if r % 2 == 0 else np.pi
        ctr = np.array([cc * s, r * s_y, alt]) + rng.normal(0, [0.5, 0.5, 0.3])
        cams.append(_cam_down(ctr, heading + np.deg2rad(rng.uniform(-10, 10)), np.deg2rad(rng.uniform(0, 12)),
                              rng.uniform(0, 2 * np.pi)))
    return planes, cams, cfg.points_per_view / 350.0  # a view sees about 23 m × 17 m


def make_scene(config: LargeSceneConfig, seed: int = 0) -> LargeScene:
    """Build the planes (with textures) and cameras of a layout (deterministic in ``seed``)."""
    rng = np.random.default_rng([seed, LAYOUTS.index(config.layout)])
    build = {"street": _street, "ring": _ring, "grid": _grid}[config.layout]
    planes, cams, density = build(config, rng)
    K = np.array([[config.focal, 0, (config.width - 1) / 2], [0, config.focal, (config.height - 1) / 2], [0, 0, 1.0]])
    R = np.array([c[0] for c in cams])
    t = np.array([c[1] for c in cams])
    return LargeScene(planes, K, R, t, density, config)

