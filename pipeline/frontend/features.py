"""SIFT features (OpenCV): the kernel, a pure function on an image.

Each image is read as grey, resized so that its longest side is at most
``max_image_size`` (a 3072×2048 image is not processed at full size), and
OpenCV's SIFT keeps the ``max_keypoints`` strongest keypoints; their coordinates
are scaled back to the full-resolution pixel frame (pixel centres at integers),
where the intrinsics K live. The stage that runs it over a folder, caches it per
image and reads it back is :mod:`pipeline.frontend.feature_stage`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.core.config import option
from pipeline.core.errors import ConfigError
from pipeline.core.parallel import ExecutorOptions

__all__ = ["FeatureConfig", "Keypoints", "extract_sift"]


@dataclass(frozen=True, kw_only=True)
class FeatureConfig(ExecutorOptions):
    """SIFT extraction options (YAML section ``features``).

    ``precise_upscale``: with OpenCV's default (False) the 2× upsampled first octave
    shifts every keypoint by +0.25 px in x and y (measured: median offset (0.252,
    0.248) px on Gaussian blobs of known centre, (0.002, 0.000) px with True). That
    bias made the two-view Hessians overconfident, so it is on by default.
    """

    SECTION = "features"

    max_keypoints: int = option(8192, "keep at most this many keypoints (strongest response first)", ge=8)
    max_image_size: int = option(1600, "longest side used for extraction, px (0 or less: full size)")
    contrast_threshold: float = option(0.02, "OpenCV's contrastThreshold (lower: more keypoints in weak texture)",
                                       gt=0)
    edge_threshold: float = option(10.0, "OpenCV's edgeThreshold", gt=0)
    n_octave_layers: int = option(3, "scales per octave", ge=1, le=10)
    sigma: float = option(1.6, "Gaussian blur of the base octave", gt=0)
    precise_upscale: bool = option(True, "OpenCV's enable_precise_upscale (removes a +0.25 px bias)")
    workers: int = option(2, "images extracted concurrently (threads: OpenCV releases the GIL)", ge=1, runtime=True)

    def check(self) -> None:
        if 0 < self.max_image_size < 64:
            raise ConfigError(f"[features] max_image_size={self.max_image_size} but expected >= 64 "
                              "(or <= 0 for full size)")


@dataclass
class Keypoints:
    """SIFT output of one image (full-resolution pixel coordinates).

    Attributes:
        xy: (n, 2) float32 keypoint positions, pixel centres at integers.
        scales: (n,) float32 keypoint sizes in full-resolution pixels.
        orientations: (n,) float32 degrees.
        responses: (n,) float32 detector responses.
        descriptors: (n, 128) uint8 SIFT descriptors.
    """

    xy: np.ndarray
    scales: np.ndarray
    orientations: np.ndarray
    responses: np.ndarray
    descriptors: np.ndarray



def _sift(config: FeatureConfig) -> cv2.SIFT:
    return cv2.SIFT_create(
        nfeatures=config.max_keypoints,
        nOctaveLayers=config.n_octave_layers,
        contrastThreshold=config.contrast_threshold,
        edgeThreshold=config.edge_threshold,
        sigma=config.sigma,
        enable_precise_upscale=config.precise_upscale,
    )


def extract_sift(gray: np.ndarray, config: FeatureConfig | None = None) -> Keypoints:
    """SIFT on a copy resized to ``config.max_image_size``, scaled back to full resolution.

    Args:
        gray: (h, w) uint8 image.
        config: extraction options.
    Returns:
        :class:`Keypoints` in the pixel frame of ``gray``.
    """
    config = config or FeatureConfig()
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray.shape={gray.shape}, dtype={gray.dtype} but expected (h, w) uint8")
    h, w = gray.shape
    scale = 1.0
    img = gray
    if config.max_image_size > 0 and max(h, w) > config.max_image_size:
        scale = config.max_image_size / max(h, w)
        new_w, new_h = max(1, round(w * scale)), max(1, round(h * scale))
        img = cv2.resize(gray, (new_w, new_h), interpolation=cv2.INTER_AREA)
    kps, desc = _sift(config).detectAndCompute(img, None)
    n = len(kps)
    if n == 0:
        return Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32),
                         np.zeros(0, np.float32), np.zeros((0, 128), np.uint8))
    xy = cv2.KeyPoint_convert(kps).astype(np.float32).reshape(-1, 2)
    size = np.array([k.size for k in kps], np.float32)
    ori = np.array([k.angle for k in kps], np.float32)
    resp = np.array([k.response for k in kps], np.float32)
    if scale != 1.0:
        # per-axis factors of the integer-rounded resize; pixel centres at integers
        sx, sy = w / img.shape[1], h / img.shape[0]
        xy = (xy + 0.5) * np.array([sx, sy], np.float32) - 0.5
        size = size * np.float32(0.5 * (sx + sy))
    # OpenCV's SIFT descriptors are integers in [0, 255] stored as float: uint8 is lossless
    desc = np.clip(np.round(desc), 0, 255).astype(np.uint8)
    # OpenCV may return a few more than nfeatures (ties); keep the strongest
    if n > config.max_keypoints:
        keep = np.argsort(-resp, kind="stable")[: config.max_keypoints]
        xy, size, ori, resp, desc = xy[keep], size[keep], ori[keep], resp[keep], desc[keep]
    return Keypoints(xy, size, ori, resp, desc)
