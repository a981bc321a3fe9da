"""A rendered low-texture turntable scene with known cameras and known pair overlap (issue 13).

A dark, faceted, dinosaur-like object (body, legs, neck, tail: 24- and 12-sided prisms;
a box head; five back plates; ≈ 140 planes) on a nearly black stand and a black
background, seen by a ring of 16 cameras at 25° elevation, 640×480, f = 620 px (the
Middlebury sparse-ring geometry). Each facet carries a dark, low-contrast grey texture
(mean ``albedo`` grey levels, standard deviation ``contrast``), Lambertian shading from
a lamp fixed in the world (``light="world"``, the Middlebury gantry) or moving with the
camera (``"camera"``, a turntable with its lamp: harder), and Gaussian sensor noise.
Faceted prisms make silhouettes slide over the surface from view to view and legs
occlude one another: matches on outlines and T-junctions are not 3-D consistent, as on a
real smooth object. View-dependent appearance (off by default, :mod:`pipeline.synthetic.shading`):
``shading="smooth"`` shades every texel from its own light direction and, on prism sides,
from normals interpolated across the facet (a smooth cylinder's shading); ``specular`` adds a
highlight that moves with the view; ``body_sides`` / ``limb_sides`` (e.g. 64 / 32) make the
silhouettes nearly smooth contours. The truth of which pairs overlap comes from
:mod:`pipeline.synthetic.overlap`; 32 of the 120 pairs (the 22.5° and 45° neighbours) do.

:func:`write_scene` writes images, ``cameras.txt`` (the truth), ``K.txt``, ``overlap.npy``
and ``scene.json`` (``true_pairs``). The wrong-pair scenes are :mod:`pipeline.synthetic.injected`.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.atomic import atomic_open, atomic_path, write_json
from pipeline.core.errors import PipelineError
from pipeline.synthetic.overlap import covisibility, sample_surface, true_pairs, visibility
from pipeline.synthetic.render import render_view
from pipeline.synthetic.scene import Plane, look_at
from pipeline.synthetic.shading import texel_shading

__all__ = ["LowTexConfig", "MaskedPlane", "LowTexScene", "dino_planes", "turntable_ring", "shade_planes",
           "render_views", "render_lowtex", "write_scene"]


@dataclass
class MaskedPlane(Plane):
    """A :class:`Plane` with an alpha ``mask`` (polygons, discs), its unshaded grey ``albedo_tex`` and, on a
    prism's side, ``edge_normals`` (2, 3): the smooth surface's normals at texture column 0 and column w."""

    mask: np.ndarray | None = None
    albedo_tex: np.ndarray | None = None
    edge_normals: np.ndarray | None = None

    @property
    def rgba(self) -> np.ndarray:  # type: ignore[override]
        if getattr(self, "_rgba", None) is None:
            alpha = (np.full(self.texture.shape[:2], 255, np.uint8) if self.mask is None else self.mask)[..., None]
            self._rgba = np.concatenate([self.texture, alpha], axis=2)
        return self._rgba


def lowtex_texture(h: int, w: int, rng: np.random.Generator, albedo: float, contrast: float) -> np.ndarray:
    """A dark, low-contrast plaster-like grey texture (h, w) float32: value noise, faint blotches, speckle."""
    img = np.zeros((h, w), np.float32)
    amp = 1.0
    for cell in (48, 24, 12, 6):
        gh, gw = max(2, h // cell + 2), max(2, w // cell + 2)
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        img += amp * cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]
        amp *= 0.7
    img = (img - img.mean()) / (img.std() + 1e-6)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    for _ in range(max(1, int(h * w / 4000))):  # faint stains, 1.5 contrast deep
        cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(2, 8)
        img += rng.choice([-1.5, 1.5]) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))
    img = albedo + contrast * img + rng.normal(0, 0.3 * contrast, (h, w)).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.float32)


def _quad(origin, u_vec, v_vec, px: float, rng: np.random.Generator, name: str, albedo: float, contrast: float,
          mask_fn=None) -> MaskedPlane:
    u_vec, v_vec, origin = (np.asarray(x, float) for x in (u_vec, v_vec, origin))
    w = max(8, int(round(np.linalg.norm(u_vec) * px)))
    h = max(8, int(round(np.linalg.norm(v_vec) * px)))
    alb = lowtex_texture(h, w, rng, albedo, contrast)
    tex = np.repeat(np.clip(alb, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return MaskedPlane(origin, u_vec / w, v_vec / h, tex, name, mask=None if mask_fn is None else mask_fn(h, w),
                       albedo_tex=alb)


def _polygon_mask(n_sides: int):
    def fn(h: int, w: int) -> np.ndarray:
        ang = np.arange(n_sides) * 2 * np.pi / n_sides + np.pi / n_sides
        pts = np.stack([(w - 1) / 2 * (1 + np.cos(ang)), (h - 1) / 2 * (1 + np.sin(ang))], 1)
        m = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(m, np.round(pts).astype(np.int32), 255)
        return m
    return fn


def prism(p0, p1, radius: float, n_sides: int, name: str, **kw) -> list[MaskedPlane]:
    """A closed n-sided prism from ``p0`` to ``p1`` (a faceted cylinder) with outward normals."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    ax = p1 - p0
    L = np.linalg.norm(ax)
    ax = ax / L
    e1 = np.cross(ax, np.array([0, 0, 1.0]) if abs(ax[2]) < 0.9 else np.array([1.0, 0, 0]))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ax, e1)
    ang = np.arange(n_sides + 1) * 2 * np.pi / n_sides
    ring = radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    planes = []
    for k in range(n_sides):
        a, u = ring[k], ring[k + 1] - ring[k]
        out = np.dot(np.cross(u, ax), a + ring[k + 1]) > 0  # normal u × axis points outwards
        planes.append(_quad(p0 + a if out else p1 + a, u, L * ax if out else -L * ax, name=f"{name}-s{k}", **kw))
        planes[-1].edge_normals = np.stack([ring[k], ring[k + 1]]) / radius  # column 0 is at ring[k]
    for p, sgn, cname in ((p0, -1, "c0"), (p1, 1, "c1")):  # n-gon caps
        u, v = 2 * radius * e1, 2 * radius * e2
        v = -v if np.dot(np.cross(u, v), sgn * ax) < 0 else v
        planes.append(_quad(p - 0.5 * u - 0.5 * v, u, v, name=f"{name}-{cname}", mask_fn=_polygon_mask(n_sides), **kw))
    return planes


def box(center, size, yaw: float, name: str, bottom: bool = False, **kw) -> list[MaskedPlane]:
    """The faces of a box centred at ``center`` (3,), yawed about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey, ez = np.array([c, s, 0.0]) * size[0], np.array([-s, c, 0.0]) * size[1], np.array([0, 0, 1.0]) * size[2]
    o = np.asarray(center, float) - ex / 2 - ey / 2 - ez / 2
    faces = [(o + ez, ex, -ez, "front"), (o + ey + ex + ez, -ex, -ez, "back"), (o + ex + ez, ey, -ez, "right"),
             (o + ey + ez, -ey, -ez, "left"), (o + ez + ey, ex, -ey, "top")] + ([(o, ex, ey, "bottom")] if bottom
                                                                                 else [])
    return [_quad(p, a, b, name=f"{name}-{n}", **kw) for p, a, b, n in faces]


def dino_planes(seed: int = 0, albedo: float = 60.0, contrast: float = 6.0, px_per_unit: float = 500.0,
                body_sides: int = 24, limb_sides: int = 12) -> list[MaskedPlane]:
    """The faceted object (about 1.3 × 0.5 × 1.0 world units) and its nearly black 16-gon stand ("stand")."""
    rng = np.random.default_rng(seed)
    kw = dict(px=px_per_unit, rng=rng, albedo=albedo, contrast=contrast)
    P = prism([-0.32, 0, 0.48], [0.30, 0, 0.50], 0.17, body_sides, "body", **kw)
    for k, (x, y) in enumerate([(0.2, 0.09), (0.2, -0.09), (-0.2, 0.09), (-0.2, -0.09)]):
        P += prism([x, y, 0.0], [x + 0.02, y, 0.36], 0.05, limb_sides, f"leg{k}", **kw)
    P += prism([0.26, 0, 0.52], [0.46, 0, 0.82], 0.065, limb_sides, "neck", **kw)
    P += box([0.53, 0.0, 0.86], (0.22, 0.11, 0.11), np.deg2rad(-8), "head", bottom=True, **kw)
    P += prism([-0.30, 0, 0.46], [-0.72, 0.05, 0.20], 0.055, limb_sides, "tail", **kw)
    for k, x in enumerate(np.linspace(-0.22, 0.18, 5)):
        h = 0.09 + 0.05 * np.cos(x * 4)
        P += box([x, 0.0, 0.63 + h / 2], (0.07, 0.02, h), np.deg2rad(rng.uniform(-10, 10)), f"plate{k}", **kw)
    r = 0.55
    P.append(_quad([-r, -r, 0.0], [2 * r, 0, 0], [0, 2 * r, 0], px_per_unit * 0.4, rng, "stand", 8.0, 1.0,
                   _polygon_mask(16)))
    return P


def turntable_ring(n_views: int, radius: float, elevation_deg: float, target, focal: float, width: int,
                   height: int, rng: np.random.Generator, jitter: float = 0.01,
                   roll_deg: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cameras evenly spaced in azimuth on a ring around ``target`` (a turntable seen from the object).

    Returns:
        K (n, 3, 3), R (n, 3, 3) cam_from_world, t (n, 3).
    """
    target = np.asarray(target, float)
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
    el = np.deg2rad(elevation_deg)
    Rs, ts = [], []
    for k in range(n_views):
        az = 2 * np.pi * k / n_views
        c = target + radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        R, t = look_at(c + rng.normal(0, jitter, 3), target + rng.normal(0, jitter, 3))
        roll = rng.normal(0, np.deg2rad(roll_deg))
        Rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
        Rs.append(Rz @ R)
        ts.append(Rz @ t)
    return np.repeat(K[None], n_views, 0), np.array(Rs), np.array(ts)


def shade_planes(planes: list[Plane], light: np.ndarray, ambient: float, *, eye: np.ndarray | None = None,
                 smooth: bool = False, specular: float = 0.0, shininess: float = 30.0) -> list[Plane]:
    """Copies with Lambertian shading ``albedo·(ambient + (1 − ambient)·max(0, n·l))`` from a point ``light``:
    one factor per plane (at its centre), or per texel with ``smooth`` (interpolated normals) or a
    ``specular`` highlight seen from ``eye`` (:func:`pipeline.synthetic.shading.texel_shading`)."""
    per_texel = smooth or specular > 0
    if per_texel and eye is None:
        raise PipelineError("shade_planes: smooth or specular shading needs the camera centre (eye)")
    out = []
    for pl in planes:
        alb = getattr(pl, "albedo_tex", None)
        if alb is None:
            out.append(pl)
            continue
        if per_texel:
            g = np.clip(texel_shading(alb, pl.origin, pl.a, pl.b, pl.normal, light, eye, ambient,
                                      edge_normals=pl.edge_normals, smooth=smooth, specular=specular,
                                      shininess=shininess), 0, 255).astype(np.uint8)
        else:
            lv = light - pl.corners().mean(axis=0)
            f = ambient + (1 - ambient) * max(0.0, float(pl.normal @ (lv / np.linalg.norm(lv))))
            g = np.clip(alb * f, 0, 255).astype(np.uint8)
        out.append(MaskedPlane(pl.origin, pl.a, pl.b, np.repeat(g[..., None], 3, 2), pl.name, mask=pl.mask,
                               albedo_tex=alb, edge_normals=pl.edge_normals))
    return out


def _moved(p: Plane, A: np.ndarray, b: np.ndarray) -> Plane:
    """``p`` under the rigid motion ``X ↦ A X + b``."""
    return dataclasses.replace(p, origin=A @ p.origin + b, a=A @ p.a, b=A @ p.b)


def render_views(planes: list[Plane], K, R, t, width: int, height: int, *, noise_sigma: float, rng, supersample=2,
                 background: int = 0, lamp: tuple[str, tuple[float, float, float]] | None = None, ambient=1.0,
                 static: tuple[list[Plane], np.ndarray, np.ndarray] | None = None, smooth: bool = False,
                 specular: float = 0.0, shininess: float = 30.0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Render every view; ``lamp = ("world" | "camera", position)`` shades the albedo planes per view
    (``smooth``, ``specular``, ``shininess``: :func:`shade_planes`); ``static = (planes, R_s, t_s)`` is an object
    fixed in the camera frame (every view sees it from one pose)."""
    images, depths = [], []
    for n in range(len(R)):
        pls = planes
        if lamp is not None:
            C = -R[n].T @ t[n]
            light = np.asarray(lamp[1], float) if lamp[0] == "world" else C + R[n].T @ np.asarray(lamp[1], float)
            pls = shade_planes(planes, light, ambient, eye=C, smooth=smooth, specular=specular, shininess=shininess)
        if static is not None:  # X_world = R_nᵀ (R_s X + t_s − t_n)
            A, b = R[n].T @ static[1], R[n].T @ (static[2] - t[n])
            pls = list(pls) + [_moved(p, A, b) for p in static[0]]
        img, depth = render_view(pls, K[n], R[n], t[n], width, height, supersample, background=background)
        if noise_sigma > 0:
            img = np.clip(img + rng.normal(0, noise_sigma, img.shape), 0, 255).astype(np.uint8)
        images.append(img)
        depths.append(depth)
    return images, depths


@dataclass(frozen=True, kw_only=True)
class LowTexConfig:
    """Parameters of the low-texture turntable scene (module docstring)."""

    n_views: int = 16
    width: int = 640
    height: int = 480
    focal: float = 620.0
    world_lamp: tuple[float, float, float] = (1.5, -2.0, 3.0)
    radius: float = 2.0
    elevation_deg: float = 25.0
    light: str = "world"
    ambient: float = 0.35
    albedo: float = 60.0
    contrast: float = 8.0
    lamp_offset: tuple[float, float, float] = (0.0, -0.4, 0.0)
    noise_sigma: float = 1.5
    supersample: int = 2
    px_per_unit: float = 500.0
    overlap_threshold: float = 0.3
    max_ray_deg: float = 60.0
    body_sides: int = 24
    limb_sides: int = 12
    shading: str = "flat"
    specular: float = 0.0
    shininess: float = 30.0


@dataclass
class LowTexScene:
    """A rendered scene and its truth: cameras (cam_from_world), pair ``overlap`` (N, N), ``true_pairs`` (P, 2),
    and each view's depth map ``depths`` (h, w), inf where nothing is seen."""

    names: list[str]
    images: list[np.ndarray]
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    overlap: np.ndarray
    true_pairs: np.ndarray
    info: dict = field(default_factory=dict)
    depths: list[np.ndarray] = field(default_factory=list)

    def transfer_error_px(self, a: int, b: int, x_a: np.ndarray, x_b: np.ndarray) -> np.ndarray:
        """(m,) distance (px) from ``x_b`` (m, 2) to ``x_a`` (m, 2) of view a lifted with a's depth map and
        projected into view b: the truth of a match; inf where view a sees nothing at ``x_a``."""
        x = np.asarray(x_a, dtype=np.float64)
        h, w = self.depths[a].shape
        z = self.depths[a][np.clip(np.round(x[:, 1]).astype(int), 0, h - 1), np.clip(np.round(x[:, 0]).astype(int), 0, w - 1)]
        seen = np.isfinite(z) & (z > 0)
        X = (np.column_stack([x, np.ones(len(x))]) @ np.linalg.inv(self.K[a]).T) * np.where(seen, z, 0.0)[:, None]
        p = ((X - self.t[a]) @ self.R[a] @ self.R[b].T + self.t[b]) @ self.K[b].T
        p = p[:, :2] / np.where(np.abs(p[:, 2:]) > 1e-9, p[:, 2:], 1e-9)
        return np.where(seen, np.linalg.norm(p - np.asarray(x_b, dtype=np.float64), axis=1), np.inf)


def render_lowtex(config: LowTexConfig | None = None, seed: int = 0) -> LowTexScene:
    """The low-texture turntable scene (module docstring)."""
    cfg = config or LowTexConfig()
    if cfg.light not in ("world", "camera"):
        raise PipelineError(f"light={cfg.light!r} but expected 'world' or 'camera'")
    if cfg.shading not in ("flat", "smooth"):
        raise PipelineError(f"shading={cfg.shading!r} but expected 'flat' or 'smooth'")
    if min(cfg.body_sides, cfg.limb_sides) < 3 or not cfg.specular >= 0:
        raise PipelineError(f"body_sides={cfg.body_sides}, limb_sides={cfg.limb_sides}, specular={cfg.specular}: "
                            "expected at least 3 sides and specular >= 0")
    rng = np.random.default_rng(seed)
    planes = dino_planes(int(rng.integers(2**31)), cfg.albedo, cfg.contrast, cfg.px_per_unit, cfg.body_sides,
                         cfg.limb_sides)
    K, R, t = turntable_ring(cfg.n_views, cfg.radius, cfg.elevation_deg, [0.0, 0.0, 0.42], cfg.focal, cfg.width,
                             cfg.height, np.random.default_rng(int(rng.integers(2**31))))
    lamp = ("world", cfg.world_lamp) if cfg.light == "world" else ("camera", cfg.lamp_offset)
    images, depths = render_views(planes, K, R, t, cfg.width, cfg.height, noise_sigma=cfg.noise_sigma,
                                  rng=np.random.default_rng(int(rng.integers(2**31))), supersample=cfg.supersample,
                                  lamp=lamp, ambient=cfg.ambient, smooth=cfg.shading == "smooth",
                                  specular=cfg.specular, shininess=cfg.shininess)
    X, normals = sample_surface([p for p in planes if p.name != "stand"], 4000.0, np.random.default_rng(seed + 1))
    ov = covisibility(X, visibility(X, normals, K, R, t, depths), -np.einsum("nji,nj->ni", R, t), cfg.max_ray_deg)
    tp = true_pairs(ov, cfg.overlap_threshold)
    info = {"scene": "lowtex", "config": dataclasses.asdict(cfg), "seed": seed, "n_true_pairs": int(len(tp))}
    return LowTexScene([f"lowtex_{k:03d}.png" for k in range(cfg.n_views)], images, K, R, t, ov, tp, info, depths)


def write_scene(scene: LowTexScene, out: str | Path) -> Path:
    """Write images, ``cameras.txt``, ``K.txt``, ``overlap.npy`` and ``scene.json``; returns ``cameras.txt``."""
    from pipeline.reference.truth import write_cameras_file  # noqa: PLC0415

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name, img in zip(scene.names, scene.images):
        with atomic_path(out / name, suffix=".png") as tmp:
            if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
                raise PipelineError(f"could not write {out / name}")
    with atomic_open(out / "K.txt") as f:
        np.savetxt(f, scene.K[0])
    with atomic_path(out / "overlap.npy", suffix=".npy") as tmp:
        np.save(tmp, scene.overlap)
    write_json(out / "scene.json", {**scene.info, "names": scene.names, "true_pairs": scene.true_pairs.tolist()})
    return Path(write_cameras_file(out / "cameras.txt", scene.names, scene.K, scene.R, scene.t))


def read_true_pairs(folder: str | Path) -> tuple[list[str], np.ndarray]:
    """The names and the truly overlapping pairs (P, 2) of a scene written by :func:`write_scene`."""
    d = json.loads((Path(folder) / "scene.json").read_text(encoding="utf-8"))
    return list(d["names"]), np.asarray(d["true_pairs"], np.int64).reshape(-1, 2)
