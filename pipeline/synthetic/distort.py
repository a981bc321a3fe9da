"""Rendered scenes seen through a lens with radial distortion (COLMAP ``SIMPLE_RADIAL``), with known truth.

:func:`render_distorted_scene` renders the same world and cameras as
:func:`pipeline.synthetic.render.render_scene` (same seed, same random streams), but
each view goes through the lens of a ``SIMPLE_RADIAL`` camera, ``y_d = (1 + k1|y|²) y``
in normalized coordinates ``y = K⁻¹ x`` (COLMAP's model and convention): the pinhole view
is rendered on a larger canvas at twice the resolution, warped so that pixel
``x_d`` shows what the pinhole camera sees at ``undistort(x_d)`` (pycolmap's
``cam_from_img``), area-averaged to full size, and given the same pixel noise.
``k1 = 0`` gives the undistorted scene through the very same resampling: the fair
baseline of a distortion test.

Output folder::

    DIR/view_000.png ...   the images
    DIR/cameras.txt        truth: name fx fy cx cy r11 .. r33 t1 t2 t3 (the pinhole K, cam_from_world)
    DIR/lens.txt           the lens as a COLMAP cameras.txt line: 1 SIMPLE_RADIAL w h f cx cy k1
    DIR/K.txt              the pinhole K alone (3×3)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.atomic import atomic_open, atomic_path
from pipeline.core.errors import PipelineError
from pipeline.frontend.distortion import COLMAP_OFFSET, simple_radial, undistort_points
from pipeline.synthetic.render import RenderedScene, SceneConfig, render_view, write_cameras_txt
from pipeline.synthetic.scene import make_planes, ring_cameras

__all__ = ["render_distorted_scene", "LensWarp"]


@dataclass(frozen=True)
class LensWarp:
    """One ``SIMPLE_RADIAL`` lens (pinhole ``K``, ``k1``, size ``w × h``) as a resampling of a 2× pinhole render.

    The distorted image's pixel ``x_d`` shows what the pinhole camera sees at ``undistort(x_d)``: the pinhole
    view is rendered on a 2× canvas with a margin (``Kb``), remapped by ``mapx, mapy`` and area-averaged to
    full size (module docstring). ``k1 = 0`` is the same resampling with no lens.
    """

    K: np.ndarray
    w: int
    h: int
    margin: int
    Kb: np.ndarray
    mapx: np.ndarray
    mapy: np.ndarray

    @classmethod
    def of(cls, K: np.ndarray, k1: float, w: int, h: int) -> "LensWarp":
        lens = simple_radial(float(K[0, 0]), K[:2, 2], k1, w, h)
        # the 2× grid of distorted pixel centres (x1 = (x2 + ½)/2 − ½) and the pinhole pixels they see
        u2, v2 = np.meshgrid(np.arange(2 * w, dtype=np.float64), np.arange(2 * h, dtype=np.float64))
        xd = np.column_stack([(u2.ravel() + 0.5) / 2 - 0.5, (v2.ravel() + 0.5) / 2 - 0.5])
        xu = undistort_points(lens, xd) if k1 != 0.0 else xd
        if not np.isfinite(xu).all():
            raise PipelineError(f"k1={k1} folds the image over (no inverse at the corners); use a smaller |k1|")
        margin = int(np.ceil(max(0.0, -xu.min(), xu[:, 0].max() - w, xu[:, 1].max() - h))) + 4
        big = 2 * (xu + margin + 0.5) - 0.5  # pixels of the 2× canvas with the margin
        Kb = np.diag([2.0, 2.0, 1.0]) @ K
        Kb[:2, 2] = 2.0 * (K[:2, 2] + margin + 0.5) - 0.5  # the 2× canvas: x2 = 2(x1 + margin + ½) − ½
        return cls(K, int(w), int(h), margin, Kb, big[:, 0].reshape(2 * h, 2 * w).astype(np.float32),
                   big[:, 1].reshape(2 * h, 2 * w).astype(np.float32))

    def render(self, planes: list, R: np.ndarray, t: np.ndarray, supersample: int) -> np.ndarray:
        """The (h, w, 3) uint8 RGB view through the lens of a camera at cam_from_world ``R``, ``t`` (no noise)."""
        w, h, m = self.w, self.h, self.margin
        canvas, _ = render_view(planes, self.Kb, R, t, 2 * (w + 2 * m), 2 * (h + 2 * m), supersample)
        return cv2.resize(cv2.remap(canvas, self.mapx, self.mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                    borderValue=(90, 90, 90)), (w, h), interpolation=cv2.INTER_AREA)


def render_distorted_scene(n_views: int, seed: int, out: str | Path, k1: float, *,
                           config: SceneConfig | None = None,
                           principal_offset: tuple[float, float] = (0.0, 0.0)) -> RenderedScene:
    """Render a seeded scene through a ``SIMPLE_RADIAL`` lens and write it (see the module docstring).

    Args:
        n_views: number of views.  seed: as :func:`~pipeline.synthetic.render.render_scene`'s.
        out: output folder.  k1: COLMAP's radial coefficient (normalized coordinates; −0.15 is
            strong barrel distortion).  config: scene parameters.
        principal_offset: (dx, dy) pixels of the principal point, the lens's centre, from the image centre
            (a real camera's is rarely at the centre: Strecha's is 15 and 17 px from it at 3072 × 2048).
    Returns:
        The scene (``images`` are the distorted ones; ``K`` the pinhole part of the lens).
    """
    cfg = dataclasses.replace(config or SceneConfig(), n_views=int(n_views))
    if n_views < 2:
        raise PipelineError(f"n_views={n_views} but a scene needs at least 2 views")
    rng = np.random.default_rng(seed)  # the draws of render_scene, in its order
    planes = make_planes(int(rng.integers(2**31)), cfg.texture_px_per_unit)
    K, R, t = ring_cameras(cfg, np.random.default_rng(int(rng.integers(2**31))))
    K[:, :2, 2] += np.asarray(principal_offset, float)
    noise_rng = np.random.default_rng(int(rng.integers(2**31)))
    w, h = cfg.width, cfg.height
    lens = simple_radial(cfg.focal, K[0][:2, 2], k1, w, h)
    warp = LensWarp.of(K[0], k1, w, h)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = [f"view_{i:03d}.png" for i in range(cfg.n_views)]
    images = []
    for i, name in enumerate(names):  # one view at a time: each is a full render
        img = warp.render(planes, R[i], t[i], cfg.supersample)
        if cfg.noise_sigma > 0:
            img = np.clip(img + noise_rng.normal(0, cfg.noise_sigma, img.shape), 0, 255).astype(np.uint8)
        images.append(img)
        with atomic_path(out / name, suffix=".png") as tmp:
            if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
                raise PipelineError(f"could not write {out / name}")
    write_cameras_txt(out / "cameras.txt", names, K, R, t)
    p = lens.params
    with atomic_open(out / "lens.txt") as f:
        f.write(f"# COLMAP cameras.txt: CAMERA_ID MODEL WIDTH HEIGHT f cx cy k1 (centre of the top-left pixel at "
                f"({COLMAP_OFFSET}, {COLMAP_OFFSET}))\n1 SIMPLE_RADIAL {w} {h} {p[0]!r} {p[1]!r} {p[2]!r} {p[3]!r}\n")
    with atomic_open(out / "K.txt") as f:
        np.savetxt(f, K[0], fmt="%.17g")
    return RenderedScene(names, images, K, R, t, np.zeros((0, 3)), [], out)
