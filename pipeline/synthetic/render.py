"""Rendered synthetic scenes with known cameras, for the image front end's tests.

The scene is a set of textured rectangles that are not coplanar: a ground plane,
a back wall and seven boxes of different sizes standing on the ground (5 faces each). Every
rectangle carries its own procedural texture, rich in blob and corner structure
at several scales so that SIFT finds features at every octave.

Rendering is exact for planar geometry: a rectangle with corner ``P0`` and edge
vectors ``a`` and ``b`` (world units per texture pixel) maps texture pixel
``(u, v, 1)`` to the image through the plane-induced homography
``K [R a | R b | R P0 + t]``; ``cv2.warpPerspective`` resamples the texture and
a z-buffer of inverse depth (an affine function of the pixel for a plane)
resolves occlusions. Views are rendered at ``supersample`` times the size and
area-averaged down, which removes the aliasing of plain bilinear warping.

Conventions: world z is up; ``R`` is cam_from_world (``x_cam = R X + t``);
camera axes x right, y down, z forward (OpenCV/COLMAP pinhole).

Output folder (``render_scene(out=...)`` or the command line)::

    DIR/view_000.png ...     the images (8-bit RGB PNG)
    DIR/cameras.txt          one line per image: name fx fy cx cy r11 .. r33 t1 t2 t3
    DIR/points3d.txt         (optional) x y z of points sampled on the visible surfaces

Command line::

    python -m pipeline.synthetic.render --views 12 --seed 0 --out DIR [--noise 0.5] [--points]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.atomic import atomic_open, atomic_path, check_writable
from pipeline.core.errors import PipelineError
from pipeline.geometry.epipolar import essential_from_Rt, normalize, sampson_distance  # noqa: F401 - essential_from_Rt: old import path
from pipeline.synthetic.scene import Plane, look_at, make_planes, procedural_texture, ring_cameras  # noqa: F401

logger = logging.getLogger(__name__)

__all__ = [
    "SceneConfig",
    "Plane",
    "RenderedScene",
    "make_planes",
    "ring_cameras",
    "render_view",
    "render_scene",
    "essential_from_Rt",
    "write_cameras_txt",
    "main",
    "main_cli",
]


@dataclass(frozen=True, kw_only=True)
class SceneConfig:
    """Scene and camera parameters of a rendered scene.

    Attributes:
        n_views: number of cameras.
        width, height: image size in pixels.
        focal: focal length in pixels (``fx = fy``); principal point at the centre.
        arc_deg: angular extent of the camera arc around the object (degrees).
            The arc faces the back wall, so every view sees most of the scene and
            all pairs of a 12-view arc overlap.
        radius: horizontal distance of the cameras from the look-at point.
        height_cam: camera height above the ground.
        jitter: random perturbation of camera positions (world units), so that
            the views are not exactly on a circle.
        noise_sigma: standard deviation of additive Gaussian pixel noise (0-255 scale).
        supersample: render at this factor and area-average down (anti-aliasing).
        texture_px_per_unit: texture resolution (pixels per world unit).
    """

    n_views: int = 12
    width: int = 640
    height: int = 480
    focal: float = 560.0
    arc_deg: float = 80.0
    radius: float = 7.0
    height_cam: float = 3.2
    jitter: float = 0.15
    noise_sigma: float = 0.0
    supersample: int = 2
    texture_px_per_unit: float = 220.0


@dataclass
class RenderedScene:
    """Images and true cameras of a rendered scene.

    Attributes:
        names: N image names (``view_000.png`` ...).
        images: N (h, w, 3) uint8 RGB images.
        K: (N, 3, 3) intrinsics.
        R: (N, 3, 3) cam_from_world rotations.
        t: (N, 3) cam_from_world translations.
        points: (P, 3) world points sampled on the scene surfaces (visible in >= 2 views).
        depth: N (h, w) float32 depth maps (z in the camera frame; inf where nothing is seen).
        out: output folder, if written.
    """

    names: list[str]
    images: list[np.ndarray]
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    depth: list[np.ndarray] = field(default_factory=list)
    out: Path | None = None

    @property
    def centers(self) -> np.ndarray:
        """(N, 3) camera centres ``-Rᵀ t``."""
        return -np.einsum("nji,nj->ni", self.R, self.t)

    def relative_pose(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(R_ij, t_ij)`` with ``x_j = R_ij x_i + t_ij``; ``t_ij`` of unit norm."""
        R_ij = self.R[j] @ self.R[i].T
        t_ij = self.t[j] - R_ij @ self.t[i]
        return R_ij, t_ij / np.linalg.norm(t_ij)

    def epipolar_distance_px(self, i: int, j: int, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
        """|Sampson distance| in pixels (view i's focal) of matches ``x_i ↔ x_j`` (n, 2) from the true geometry."""
        R, t = self.relative_pose(i, j)
        y_i, y_j = normalize(x_i, self.K[i]), normalize(x_j, self.K[j])
        return np.abs(sampson_distance(R, t, y_i, y_j)) * self.K[i][0, 0]

    def project(self, i: int, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points X (P, 3) into view i: pixels (P, 2) and depths (P,)."""
        Xc = X @ self.R[i].T + self.t[i]
        x = Xc @ self.K[i].T
        return x[:, :2] / x[:, 2:3], Xc[:, 2]


# --------------------------------------------------------------------- texture


def supersampled_grid(K: np.ndarray, width: int, height: int, s: int
                      ) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray, np.ndarray]:
    """The camera of an image rendered at ``s`` times the size: ``K_s``, ``W``, ``H``, ``K_s⁻¹`` and the
    pixel coordinates ``uu`` (1, W), ``vv`` (H, 1) (float32)."""
    S = np.diag([s, s, 1.0])
    # pixel centres: x_s = s·(x + 0.5) − 0.5 keeps the principal point consistent
    S[0, 2] = S[1, 2] = (s - 1) / 2
    Ks = S @ K
    W, H = width * s, height * s
    return (Ks, W, H, np.linalg.inv(Ks), np.arange(W, dtype=np.float32)[None, :],
            np.arange(H, dtype=np.float32)[:, None])


def render_view(planes: list[Plane], K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int,
                supersample: int = 2, background: int = 90) -> tuple[np.ndarray, np.ndarray]:
    """Render one view of textured planes with a z-buffer.

    Args:
        planes: the scene.
        K: (3, 3) intrinsics; R: (3, 3) cam_from_world; t: (3,).
        width, height: output size.
        supersample: render at this factor, then area-average down.
    Returns:
        image (height, width, 3) uint8 RGB and depth (height, width) float32 (inf = empty).
    """
    s = int(supersample)
    Ks, W, H, Kinv, uu, vv = supersampled_grid(K, width, height, s)
    best = np.zeros((H, W), np.float32)  # inverse depth of the nearest surface so far
    image = np.full((H, W, 3), background, np.uint8)
    for pl in planes:
        # plane-induced homography: texture pixel -> image pixel, with the texture's
        # pixel-centre convention (texel (u, v) covers [u, u+1) x [v, v+1))
        Hm = Ks @ np.column_stack([R @ pl.a, R @ pl.b, R @ pl.origin + t])
        Hc = Hm @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
        n_c = R @ pl.normal
        d_c = float(n_c @ (R @ pl.origin + t))  # the plane is n_c·X = d_c in the camera frame
        if abs(d_c) < 1e-9:
            continue  # seen edge-on
        # work in the bounding box of the projected rectangle when it is entirely in
        # front of the camera (the usual case); otherwise in the whole image
        Xc = pl.corners() @ R.T + t
        x0, y0, x1, y1 = 0, 0, W, H
        if np.all(Xc[:, 2] > 1e-6):
            pc = Xc @ Ks.T
            pc = pc[:, :2] / pc[:, 2:3]
            x0, y0 = max(0, int(np.floor(pc[:, 0].min())) - 1), max(0, int(np.floor(pc[:, 1].min())) - 1)
            x1, y1 = min(W, int(np.ceil(pc[:, 0].max())) + 2), min(H, int(np.ceil(pc[:, 1].max())) + 2)
            if x1 <= x0 or y1 <= y0:
                continue  # outside the view
        T = np.array([[1.0, 0, -x0], [0, 1, -y0], [0, 0, 1]])
        # the alpha channel marks the rectangle's pixels
        warped = cv2.warpPerspective(pl.rgba, T @ Hc, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
        # inverse depth 1/z = n_c·(K⁻¹ x) / d_c is affine in the pixel; its sign also
        # removes the mirror image the homography gives of points behind the camera
        coef = ((n_c @ Kinv) / d_c).astype(np.float32)
        invz = coef[0] * uu[:, x0:x1] + (coef[1] * vv[y0:y1] + coef[2])
        zb = best[y0:y1, x0:x1]
        closer = (warped[..., 3] >= 128) & (invz > zb)
        zb[closer] = invz[closer]
        image[y0:y1, x0:x1][closer] = warped[..., :3][closer]
    if s > 1:
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
        best = best[s // 2::s, s // 2::s][:height, :width]
    depth = np.where(best > 0, 1.0 / np.maximum(best, 1e-12), np.inf).astype(np.float32)
    return image, depth


def _sample_points(planes: list[Plane], scene_K, scene_R, scene_t, depths, rng, n_per_plane: int = 400) -> np.ndarray:
    """Points on the planes that are visible (not occluded) in at least two views."""
    pts = []
    for pl in planes:
        h, w = pl.texture.shape[:2]
        uv = rng.uniform([0, 0], [w, h], (n_per_plane, 2))
        pts.append(pl.origin + uv[:, :1] * pl.a + uv[:, 1:] * pl.b)
    X = np.concatenate(pts)
    n_vis = np.zeros(len(X), int)
    for K, R, t, D in zip(scene_K, scene_R, scene_t, depths):
        Xc = X @ R.T + t
        z = Xc[:, 2]
        x = Xc @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = x[:, 0] / x[:, 2], x[:, 1] / x[:, 2]
        hh, ww = D.shape
        ok = (z > 0) & (u >= 0) & (u <= ww - 1) & (v >= 0) & (v <= hh - 1)
        ui, vi = np.clip(np.round(u).astype(int), 0, ww - 1), np.clip(np.round(v).astype(int), 0, hh - 1)
        ok &= np.abs(D[vi, ui] - z) < 0.02 * z
        n_vis += ok
    return X[n_vis >= 2]


def write_cameras_txt(path: Path, names: list[str], K: np.ndarray, R: np.ndarray, t: np.ndarray) -> Path:
    """Write ``name fx fy cx cy r11 .. r33 t1 t2 t3`` per line (cam_from_world), atomically."""
    from pipeline.reference.truth import write_cameras_file

    return Path(write_cameras_file(path, names, K, R, t))


def render_scene(n_views: int = 12, seed: int = 0, out: str | Path | None = None, *,
                 config: SceneConfig | None = None, noise_sigma: float | None = None,
                 write_points: bool = False, overwrite: bool = True) -> RenderedScene:
    """Render a seeded scene; optionally write images, ``cameras.txt`` and ``points3d.txt``.

    Args:
        n_views: number of views (overrides ``config.n_views``).
        seed: seeds textures, camera jitter and pixel noise; same seed → same images.
        out: output folder, or None to keep everything in memory.
        config: scene parameters (defaults: :class:`SceneConfig`).
        noise_sigma: overrides ``config.noise_sigma``.
        write_points: also write ``points3d.txt``.
        overwrite: when False and ``out/cameras.txt`` exists, images are not re-written.
    Returns:
        :class:`RenderedScene`.
    """
    cfg = config or SceneConfig()
    if n_views < 2:
        raise PipelineError(f"n_views={n_views} but a scene needs at least 2 views")
    cfg = dataclasses.replace(cfg, n_views=int(n_views))
    if noise_sigma is not None:
        cfg = dataclasses.replace(cfg, noise_sigma=float(noise_sigma))
    if out is not None:
        check_writable(out)  # before the rendering
    rng = np.random.default_rng(seed)
    planes = make_planes(int(rng.integers(2**31)), cfg.texture_px_per_unit)
    K, R, t = ring_cameras(cfg, np.random.default_rng(int(rng.integers(2**31))))
    noise_rng = np.random.default_rng(int(rng.integers(2**31)))
    names = [f"view_{i:03d}.png" for i in range(cfg.n_views)]
    images, depths = [], []
    t0 = time.perf_counter()
    for i in range(cfg.n_views):
        img, depth = render_view(planes, K[i], R[i], t[i], cfg.width, cfg.height, cfg.supersample)
        if cfg.noise_sigma > 0:
            img = np.clip(img + noise_rng.normal(0, cfg.noise_sigma, img.shape), 0, 255).astype(np.uint8)
        images.append(img)
        depths.append(depth)
    logger.debug("rendered %d views in %.2f s", cfg.n_views, time.perf_counter() - t0)
    points = _sample_points(planes, K, R, t, depths, np.random.default_rng(seed + 1))
    scene = RenderedScene(names, images, K, R, t, points, depths)
    if out is not None:
        out = Path(out)
        for name, img in zip(names, images):
            with atomic_path(out / name, suffix=".png") as tmp:
                if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
                    raise PipelineError(f"could not write {out / name}")
        write_cameras_txt(out / "cameras.txt", names, K, R, t)
        if write_points:
            with atomic_open(out / "points3d.txt") as f:
                f.write("# x y z (world)\n")
                np.savetxt(f, points, fmt="%.9g")
        scene.out = out
    return scene


def main(out: str | Path, n_views: int = 12, seed: int = 0, noise_sigma: float = 0.0, write_points: bool = False,
         config: SceneConfig | None = None) -> Path:
    """Render a scene into ``out`` and return the path of its ``cameras.txt``."""
    t0 = time.perf_counter()
    scene = render_scene(n_views, seed, out, config=config, noise_sigma=noise_sigma, write_points=write_points)
    logger.info("rendered %d views (%dx%d) into %s in %.2f s", len(scene.names), scene.images[0].shape[1],
                scene.images[0].shape[0], out, time.perf_counter() - t0)
    return Path(out) / "cameras.txt"


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli
    from pipeline.core.errors import ConfigError

    p = argparse.ArgumentParser(prog="python -m pipeline.synthetic.render", description=__doc__.split("\n")[0])
    p.add_argument("--views", type=int, default=12, help="number of views (default 12)")
    p.add_argument("--seed", type=int, default=0, help="random seed (textures, cameras, noise)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--noise", type=float, default=0.0, help="Gaussian pixel noise sigma, 0-255 scale (default 0)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--points", action="store_true", help="also write points3d.txt (true 3D points)")

    def body(a: argparse.Namespace) -> int:
        for flag, v, low in (("--width", a.width, 16), ("--height", a.height, 16)):  # views: render_scene's check
            if v < low:
                raise ConfigError(f"{flag} {v}; expected at least {low}")
        if not a.noise >= 0:
            raise ConfigError(f"--noise {a.noise}; expected a pixel noise sigma >= 0")
        cfg = SceneConfig(width=a.width, height=a.height, focal=560.0 * a.width / 640)
        main(a.out, a.views, a.seed, a.noise, a.points, cfg)
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
