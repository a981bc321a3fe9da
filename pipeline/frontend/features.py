"""SIFT features (OpenCV): the kernel, a pure function on an image.

Each image is read as grey, resized so that its longest side is at most
``max_image_size`` (a 3072×2048 image is not processed at full size), and
OpenCV's SIFT keeps the ``max_keypoints`` strongest keypoints; their coordinates
are scaled back to the full-resolution pixel frame (pixel centres at integers),
where the intrinsics K live. The stage that runs it over a folder, caches it per
image and reads it back is :mod:`pipeline.frontend.feature_stage`.

**Low texture** (issue 13). A dark, low-contrast image gives few keypoints at the
usual contrast threshold. OpenCV keeps a keypoint when its interpolated DoG value
``|D| ≥ contrastThreshold / nOctaveLayers`` (image in [0, 1]) and reports ``|D|`` as
its ``response``, so a detection at a lower threshold cut at a response is exactly a
detection at that threshold. An image with fewer than ``min_keypoints`` keypoints
(per 640×480 at extraction size, at most ``max_keypoints / 2``) at
``contrast_threshold`` is therefore detected once more at ``contrast_floor`` and keeps
its ``min_keypoints`` strongest, never below the floor: its threshold alone is lowered,
as OpenSfM's ``feature_min_frames`` does (COLMAP's CPU SIFT has no such rule; its
``darkness_adaptivity`` exists in SiftGPU only). Before that second detection the image
is blurred by ``preblur_sigma``: OpenCV's SIFT starts from a 2× upsampled image, whose
finest octave is noise on a dark image; the blur doubled the correct matches of the
rendered low-texture scene (research r13-lowtex). Every other image keeps exactly the
features of one detection at ``contrast_threshold``. No local contrast equalization
(CLAHE): its tone curve follows the content, which moves between views, and it gave
fewer correct matches than the lowered threshold at the same keypoint count.

**Texture-starved images** (``affine_below``). An image that even at ``contrast_floor`` has
fewer than half its target is detected again over simulated viewpoints (ASIFT, :func:`_affine`:
tilts up to ``√2^affine_max_tilt``, our own warps with pixel centres at integers). On the
rendered low-texture turntables (8 scenes) it raised the truly overlapping pairs kept from
50–72% to 81–97% and solved every image (7–8 of 16 before on four of them); it costs about
1 s per 640×480 image, and only such images pay it (templeSparseRing's lowered images reach
83–100% of their target at the floor and are not affected).

**Speed.** On an image that will be lowered, describing the normal detection is wasted
work (half of a SIFT pass). Once most images seen by this process were lowered
(:class:`_LowTextureOdds`), the normal pass detects only, and describes its keypoints
(``compute``) only when there are enough of them: the same keypoints and descriptors
bit for bit (tested), a third less time on low-texture collections, a quarter more on
the rare textured image among them. The lowered detection lets OpenCV cut at the target
before describing (``nfeatures``): a fifth fewer descriptors on the temple, the same
features in the same order (tested).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.core.config import option
from pipeline.core.errors import ConfigError
from pipeline.core.parallel import ExecutorOptions

__all__ = ["FeatureConfig", "Keypoints", "Extraction", "extract_sift", "extract_sift_adaptive", "keypoint_target"]

#: Image area (px², 640×480) at which ``min_keypoints`` applies as given.
REFERENCE_AREA = 640 * 480


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
    min_keypoints: int = option(2000, "an image with fewer keypoints at contrast_threshold (per 640x480 at extraction "
                                      "size, at most max_keypoints/2) keeps its strongest this many down to "
                                      "contrast_floor (0: never lowered)", ge=0)
    contrast_floor: float = option(0.0025, "lowest contrastThreshold of a lowered image", gt=0)
    preblur_sigma: float = option(1.0, "Gaussian blur (px at extraction size) of a lowered image before its "
                                       "detection at the lower threshold (0: none)", ge=0)
    affine_below: float = option(0.5, "a lowered image that still has fewer than this fraction of its target at "
                                      "contrast_floor is detected again over simulated viewpoints (ASIFT, same SIFT, "
                                      "our own warps; 0: never)", ge=0, le=1)
    affine_max_tilt: int = option(2, "tilts simulated by the affine detection: 1, √2, ... up to √2^this "
                                     "(2: up to a 60° change of viewpoint)", ge=1, le=6)
    workers: int = option(2, "images extracted concurrently (threads: OpenCV releases the GIL)", ge=1, runtime=True)

    def check(self) -> None:
        if 0 < self.max_image_size < 64:
            raise ConfigError(f"[features] max_image_size={self.max_image_size} but expected >= 64 "
                              "(or <= 0 for full size)")
        if self.contrast_floor > self.contrast_threshold:
            raise ConfigError(f"[features] contrast_floor={self.contrast_floor} but expected <= contrast_threshold="
                              f"{self.contrast_threshold} (the floor is the lowest threshold ever used)")


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




@dataclass
class Extraction:
    """What one image's extraction did (the per-image record of the features stage).

    Attributes:
        n_normal: keypoints at ``contrast_threshold`` (before the ``max_keypoints`` cut).
        lowered: the threshold was lowered for this image (it had fewer than its target).
        contrast_used: the ``contrastThreshold`` the kept keypoints reach (OpenCV units).
        preblur_sigma: the blur applied before detection (0: none).
        target: the keypoint target of this image.
        affine: the lowered detection was repeated over simulated viewpoints (``affine_below``).
    """

    n_normal: int
    lowered: bool = False
    contrast_used: float = 0.0
    preblur_sigma: float = 0.0
    target: int = 0
    affine: bool = False


def _sift(config: FeatureConfig, contrast: float | None = None, nfeatures: int | None = None) -> cv2.SIFT:
    return cv2.SIFT_create(
        nfeatures=config.max_keypoints if nfeatures is None else nfeatures,
        nOctaveLayers=config.n_octave_layers,
        contrastThreshold=config.contrast_threshold if contrast is None else contrast,
        edgeThreshold=config.edge_threshold,
        sigma=config.sigma,
        enable_precise_upscale=config.precise_upscale,
    )


def keypoint_target(config: FeatureConfig, width: int, height: int) -> int:
    """The keypoint count below which an image of ``width × height`` (extraction size) is lowered."""
    return min(int(round(config.min_keypoints * width * height / REFERENCE_AREA)), config.max_keypoints // 2)


def _arrays(kps: tuple, desc: np.ndarray | None) -> tuple[np.ndarray, ...]:
    n = len(kps)
    if n == 0:
        return (np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32),
                np.zeros(0, np.float32), np.zeros((0, 128), np.uint8))
    xy = cv2.KeyPoint_convert(kps).astype(np.float32).reshape(-1, 2)
    size = np.array([k.size for k in kps], np.float32)
    ori = np.array([k.angle for k in kps], np.float32)
    resp = np.array([k.response for k in kps], np.float32)
    # OpenCV's SIFT descriptors are integers in [0, 255] stored as float: uint8 is lossless
    desc = np.clip(np.round(desc), 0, 255).astype(np.uint8)
    return xy, size, ori, resp, desc


def extract_sift_adaptive(gray: np.ndarray, config: FeatureConfig | None = None) -> tuple[Keypoints, Extraction]:
    """SIFT with the low-texture rule of the module docstring, and what it did.

    Args:
        gray: (h, w) uint8 image.
        config: extraction options.
    Returns:
        :class:`Keypoints` in the pixel frame of ``gray`` and the :class:`Extraction` record.
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
    target = keypoint_target(config, img.shape[1], img.shape[0]) if config.min_keypoints > 0 else 0
    sift = _sift(config)
    if target > 0 and LOW_TEXTURE_ODDS.likely():  # detect first: describe only if the image is not lowered
        kps = sift.detect(img, None)
        kps, desc = sift.compute(img, kps) if len(kps) >= target else (kps, None)
    else:
        kps, desc = sift.detectAndCompute(img, None)
    info = Extraction(n_normal=len(kps), contrast_used=config.contrast_threshold, target=target)
    if len(kps) < target:
        xy, size, ori, resp, desc = _lowered(img, config, target, info)
    else:
        xy, size, ori, resp, desc = _arrays(kps, desc)
    if target > 0:
        LOW_TEXTURE_ODDS.record(info.lowered)
    if scale != 1.0:
        # per-axis factors of the integer-rounded resize; pixel centres at integers
        sx, sy = w / img.shape[1], h / img.shape[0]
        xy = (xy + 0.5) * np.array([sx, sy], np.float32) - 0.5
        size = size * np.float32(0.5 * (sx + sy))
    # OpenCV may return a few more than nfeatures (ties); keep the strongest
    if len(xy) > config.max_keypoints:
        keep = np.argsort(-resp, kind="stable")[: config.max_keypoints]
        xy, size, ori, resp, desc = xy[keep], size[keep], ori[keep], resp[keep], desc[keep]
    return Keypoints(xy, size, ori, resp, desc), info


class _LowTextureOdds:
    """How many of the images this process extracted were lowered: the choice of the faster order of work
    (module docstring, *Speed*); it never changes the features."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.seen = self.lowered = 0

    def record(self, lowered: bool) -> None:
        with self._lock:
            self.seen += 1
            self.lowered += bool(lowered)

    def likely(self) -> bool:
        with self._lock:
            return self.seen >= 2 and 2 * self.lowered > self.seen


LOW_TEXTURE_ODDS = _LowTextureOdds()


def _lowered(img: np.ndarray, config: FeatureConfig, target: int, info: Extraction) -> tuple[np.ndarray, ...]:
    """The detection of a low-texture image: blurred, at the floor, cut at its ``target``-th response."""
    if config.preblur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), config.preblur_sigma)
    L = config.n_octave_layers
    # OpenCV cuts at the target-th response before describing (its retainBest keeps ties, as `keep` below does)
    xy, size, ori, resp, desc = _arrays(*_sift(config, config.contrast_floor, target).detectAndCompute(img, None))
    if len(resp) >= target and resp.min() > config.contrast_threshold / L:
        # more than target keypoints reach the normal threshold: all of them stay (below), none may be cut
        xy, size, ori, resp, desc = _arrays(*_sift(config, config.contrast_floor, 0).detectAndCompute(img, None))
    # OpenCV's own order of an uncut detection (its KeyPoint_LessThan): x, y, larger size, angle, response
    order = np.lexsort((-resp, ori, -size, xy[:, 1], xy[:, 0]))
    xy, size, ori, resp, desc = xy[order], size[order], ori[order], resp[order], desc[order]
    thr = config.contrast_floor / L
    if len(resp) >= target:
        thr = max(thr, float(np.sort(resp)[::-1][target - 1]))
    thr = min(thr, config.contrast_threshold / L)  # everything a normal detection keeps stays
    keep = np.flatnonzero(resp >= thr)
    info.lowered = True
    info.contrast_used = float(thr * L)
    info.preblur_sigma = float(config.preblur_sigma)
    out = xy[keep], size[keep], ori[keep], resp[keep], desc[keep]
    if len(keep) < config.affine_below * target:  # uncut (fewer than target): the floor detection itself
        return _affine(img, config, info, out)
    return out


def _affine(img: np.ndarray, config: FeatureConfig, info: Extraction,
            identity: tuple[np.ndarray, ...] | None = None) -> tuple[np.ndarray, ...]:
    """The floor detection over simulated viewpoints (ASIFT; ``img`` already blurred; ``identity``: the
    floor detection of ``img`` when already made).

    Even at ``contrast_floor`` a texture-starved image has too few keypoints for a wide
    baseline: on the rendered low-texture turntable SIFT finds 0–5 correct matches on a
    45° pair. As in ASIFT (Morel & Yu 2009), the image is warped by each simulated tilt
    ``t = √2^k`` (1 ≤ k ≤ ``affine_max_tilt``) in directions φ stepped by 72°/t over 180°:
    rotated by φ, blurred along x by σ = 0.8·√(t² − 1) against aliasing, compressed along x by
    1/t; SIFT runs on each warped image (within its valid area, 4 px in) and its keypoints are
    mapped back. The identity view is the floor detection itself. The warps are ours, not
    OpenCV's ``AffineFeature``: its nearest-neighbour compression puts pixel centres at
    half-integers and moved keypoints by a median 0.16 px on Gaussian blobs of known centre
    (tested: < 0.05 px). A 45° pair of the same scene: 46 correct matches of 81 where the floor
    detection had 0 of 14 (``affine_max_tilt`` 2: 11 views, 0.8 s per 640×480 image; the whole
    extraction of such an image about 1 s). Keypoint sizes and angles are those of the
    simulated view.
    """
    sift = _sift(config, config.contrast_floor, 0)
    h, w = img.shape
    parts = [identity if identity is not None else _arrays(*sift.detectAndCompute(img, None))]
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], np.float64)
    for k in range(1, config.affine_max_tilt + 1):
        t = float(np.sqrt(2.0) ** k)
        for phi in np.arange(0.0, 180.0, 72.0 / t):  # a handful of views per tilt (not a loop over points)
            c, s_ = np.cos(np.deg2rad(phi)), np.sin(np.deg2rad(phi))
            rotation = np.array([[c, -s_], [s_, c]])
            A = rotation / np.array([[t], [1.0]])  # rotate by φ, then compress x by 1/t (pixel centres at integers)
            q = corners @ A.T
            b = -q.min(axis=0)
            size = tuple(int(v) for v in np.ceil(q.max(axis=0) + b) + 1)
            M = np.hstack([A, b[:, None]])
            # the blur along the compressed axis happens before the compression: rotate, blur, compress
            Rm = np.hstack([rotation, (b * np.array([t, 1.0]))[:, None]])
            rot = cv2.warpAffine(img, Rm, (int(np.ceil(size[0] * t)), size[1]), flags=cv2.INTER_LINEAR)
            rot = cv2.GaussianBlur(rot, (0, 0), sigmaX=0.8 * np.sqrt(t * t - 1.0), sigmaY=0.01)
            warped = cv2.warpAffine(rot, np.array([[1.0 / t, 0.0, 0.0], [0.0, 1.0, 0.0]]), size, flags=cv2.INTER_LINEAR)
            mask = cv2.warpAffine(np.full((h, w), 255, np.uint8), M, size, flags=cv2.INTER_NEAREST)
            mask = cv2.erode(mask, np.ones((9, 9), np.uint8))
            xy, sz, ori, resp, desc = _arrays(*sift.detectAndCompute(warped, mask))
            xy = ((xy.astype(np.float64) - b) @ np.linalg.inv(A).T).astype(np.float32)
            parts.append((xy, sz, ori, resp, desc))
    xy, size, ori, resp, desc = (np.concatenate(a) for a in zip(*parts))
    info.affine = True
    info.contrast_used = float(config.contrast_floor)
    return xy, size, ori, resp, desc


def extract_sift(gray: np.ndarray, config: FeatureConfig | None = None) -> Keypoints:
    """SIFT on a copy resized to ``config.max_image_size``, scaled back to full resolution.

    The threshold of a low-texture image is lowered (:func:`extract_sift_adaptive`).

    Args:
        gray: (h, w) uint8 image.
        config: extraction options.
    Returns:
        :class:`Keypoints` in the pixel frame of ``gray``.
    """
    return extract_sift_adaptive(gray, config)[0]
