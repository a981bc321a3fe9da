"""A rendered scene of several cameras: each view its own focal length and, optionally, its own image size.

Photos from different cameras (an internet collection) have no common K; without EXIF each image's focal must
come from the view graph. The scene is that of :func:`pipeline.synthetic.render.render_scene` (same planes and
camera arc); each view's focal is drawn log-uniformly in ``focal_range`` × the configured focal (scaled to the
view's size) and its size from ``sizes``. The true cameras go to ``truth/cameras.txt`` beside the image folder
(not in it: a ``cameras.txt`` among the images would be read as their K), with ``truth/focal.txt``.

With ``k1_range`` each view also has its own lens: a ``SIMPLE_RADIAL`` k1 drawn uniformly in the range
(:class:`pipeline.synthetic.distort.LensWarp`), as photos of different cameras have; ``truth/lens.txt`` holds
every view's lens as a COLMAP cameras.txt line (camera id = view index + 1) and ``truth/k1.txt`` the k1 alone.
The truth's ``cameras.txt`` holds the pinhole part.

    python -m pipeline.synthetic.mixed OUT [--views 10] [--seed 0] [--same-size] [--k1 LO HI]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.atomic import atomic_open, atomic_path
from pipeline.core.cli import run_cli
from pipeline.core.errors import PipelineError
from pipeline.frontend.distortion import COLMAP_OFFSET
from pipeline.synthetic.distort import LensWarp
from pipeline.synthetic.render import SceneConfig, render_view, write_cameras_txt
from pipeline.synthetic.scene import make_planes, ring_cameras

__all__ = ["MixedScene", "SIZES", "render_mixed_cameras", "main_cli"]

#: Image sizes (w, h) drawn from: landscape and portrait, 4:3.
SIZES = ((640, 480), (800, 600), (720, 540), (768, 576), (704, 528), (480, 640), (600, 800))


@dataclass
class MixedScene:
    """Names, per-view K (N, 3, 3), sizes (N, 2), cam_from_world R (N, 3, 3) and t (N, 3); the folders."""

    names: list[str]
    K: np.ndarray
    sizes: np.ndarray
    R: np.ndarray
    t: np.ndarray
    images: Path
    truth: Path


def render_mixed_cameras(out: str | Path, n_views: int = 10, seed: int = 0, same_size: bool = False,
                         focal_range: tuple[float, float] = (0.8, 1.25), config: SceneConfig | None = None,
                         k1_range: tuple[float, float] | None = None) -> MixedScene:
    """Render the scene to ``out/images`` and its truth to ``out/truth`` (see the module docstring)."""
    if n_views < 2:
        raise PipelineError(f"n_views={n_views} but a scene needs at least 2 views")
    cfg = dataclasses.replace(config or SceneConfig(), n_views=int(n_views))
    rng = np.random.default_rng(seed)
    planes = make_planes(int(rng.integers(2**31)), cfg.texture_px_per_unit)
    _, R, t = ring_cameras(cfg, np.random.default_rng(int(rng.integers(2**31))))
    out = Path(out)
    images, truth = out / "images", out / "truth"
    images.mkdir(parents=True, exist_ok=True)
    truth.mkdir(parents=True, exist_ok=True)
    names, Ks, sizes, k1s = [], [], [], []
    lo, hi = np.log(focal_range[0]), np.log(focal_range[1])
    for i in range(n_views):
        w, h = (cfg.width, cfg.height) if same_size else SIZES[int(rng.integers(len(SIZES)))]
        f = cfg.focal * max(w, h) / max(cfg.width, cfg.height) * float(np.exp(rng.uniform(lo, hi)))
        K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
        if k1_range is None:  # the draws of the scenes without a lens, unchanged
            img, _ = render_view(planes, K, R[i], t[i], w, h, cfg.supersample)
        else:
            k1s.append(float(rng.uniform(*k1_range)))
            img = LensWarp.of(K, k1s[-1], w, h).render(planes, R[i], t[i], cfg.supersample)
        name = f"view_{i:03d}.png"
        with atomic_path(images / name, suffix=".png") as tmp:
            if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
                raise PipelineError(f"could not write {images / name}")
        names.append(name)
        Ks.append(K)
        sizes.append((w, h))
    K_all = np.array(Ks)
    write_cameras_txt(truth / "cameras.txt", names, K_all, R, t)
    with atomic_path(truth / "focal.txt", suffix=".txt") as tmp:
        np.savetxt(tmp, K_all[:, 0, 0], fmt="%.6f")
    if k1_range is not None:
        with atomic_open(truth / "lens.txt") as fh:
            fh.write(f"# COLMAP cameras.txt: CAMERA_ID MODEL WIDTH HEIGHT f cx cy k1 (centre of the top-left pixel at "
                     f"({COLMAP_OFFSET}, {COLMAP_OFFSET})); camera id = view index + 1\n")
            for i, (K, (w, h), k1) in enumerate(zip(K_all, sizes, k1s)):
                f, cx, cy = float(K[0, 0]), float(K[0, 2]) + COLMAP_OFFSET, float(K[1, 2]) + COLMAP_OFFSET
                fh.write(f"{i + 1} SIMPLE_RADIAL {int(w)} {int(h)} {f!r} {cx!r} {cy!r} {k1!r}\n")
        with atomic_path(truth / "k1.txt", suffix=".txt") as tmp:
            np.savetxt(tmp, np.array(k1s), fmt="%.6f")
    return MixedScene(names, K_all, np.array(sizes), R, t, images, truth)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m pipeline.synthetic.mixed", description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path, help="output folder (images/ and truth/ are written in it)")
    p.add_argument("--views", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--same-size", action="store_true", help="every view 640×480 (only the focal lengths differ)")
    p.add_argument("--k1", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                   help="each view its own SIMPLE_RADIAL lens, k1 uniform in [LO, HI] (e.g. -0.08 0.04)")
    return p


def main_cli(argv: list[str] | None = None) -> int:
    def body(a: argparse.Namespace) -> int:
        s = render_mixed_cameras(a.out, a.views, a.seed, a.same_size, k1_range=None if a.k1 is None else tuple(a.k1))
        print(f"rendered {len(s.names)} views to {s.images}; truth in {s.truth}")
        return 0

    return run_cli(body, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main_cli())
