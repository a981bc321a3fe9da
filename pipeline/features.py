"""SIFT features (OpenCV), cached per image.

Stage 1 of the image front end. Each image is read as grey, resized so that its
longest side is at most ``max_image_size`` (a 3072×2048 image is not processed
at full size), and OpenCV's SIFT keeps the ``max_keypoints`` strongest
keypoints; their coordinates are scaled back to the full-resolution pixel frame
(pixel centres at integers), where the intrinsics K live.

WORK folder layout written by this stage::

    WORK/features.json                      manifest: image folder, names, sizes (w, h),
                                            K per image and its source, skipped images,
                                            config, config hash and a digest of all of it
    WORK/features/<hash>/<image name>.npz   per-image cache: keypoints (n, 2) float32 px,
                                            scales (n,), orientations (n,) deg,
                                            responses (n,), descriptors (n, 128) uint8,
                                            the image's byte size and mtime

``<hash>`` is the config hash, so a changed configuration never reads a stale
cache; an image whose size or mtime changed is extracted again. Re-running
extracts only images without a valid cache entry unless ``overwrite=True``.

Command line::

    python -m pipeline.features --images DIR --work WORK [--K FILE] [--max-image-size 1600]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import save_npz, write_json
from pipeline.core.config import config_hash
from pipeline.core.errors import InputFileError
from pipeline.images import IMAGE_EXTENSIONS, list_images, read_gray, resolve_intrinsics

logger = logging.getLogger(__name__)

__all__ = ["FeatureConfig", "FeatureSet", "Keypoints", "extract_sift", "main", "load_features", "main_cli",
           "MANIFEST", "FEATURES_DIR"]

MANIFEST = "features.json"
FEATURES_DIR = "features"


@dataclass(frozen=True, kw_only=True)
class FeatureConfig:
    """SIFT extraction options.

    Attributes:
        max_keypoints: keep at most this many keypoints (strongest response first).
        max_image_size: resize so that the longest side is at most this (pixels);
            0 or negative keeps the full size.
        contrast_threshold: OpenCV's ``contrastThreshold`` (lower: more keypoints
            in weak texture; OpenCV's default is 0.04).
        edge_threshold: OpenCV's ``edgeThreshold``.
        n_octave_layers: scales per octave.
        sigma: Gaussian blur of the base octave.
        precise_upscale: OpenCV's ``enable_precise_upscale``. With OpenCV's
            default (False) the 2× upsampled first octave shifts every keypoint by
            +0.25 px in x and y (measured: median offset (0.252, 0.248) px on
            Gaussian blobs of known centre, (0.002, 0.000) px with True). That bias
            made the two-view Hessians overconfident, so it is on by default.
        workers: images extracted concurrently (threads: OpenCV releases the GIL).
    """

    max_keypoints: int = 8192
    max_image_size: int = 1600
    contrast_threshold: float = 0.02
    edge_threshold: float = 10.0
    n_octave_layers: int = 3
    sigma: float = 1.6
    precise_upscale: bool = True
    workers: int = 2

    def __post_init__(self) -> None:
        if self.max_keypoints < 8:
            raise ValueError(f"max_keypoints={self.max_keypoints} but expected >= 8")
        if 0 < self.max_image_size < 64:
            raise ValueError(f"max_image_size={self.max_image_size} but expected >= 64 (or <= 0 for full size)")
        if self.workers < 1:
            raise ValueError(f"workers={self.workers} but expected >= 1")

    def cache_key(self) -> str:
        """Hash of the options that change the features (not ``workers``)."""
        return config_hash(self, exclude=("workers",))


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
class FeatureSet:
    """Features of all usable images of a WORK folder (see :func:`load_features`).

    Attributes:
        names: N image file names, sorted.
        K: (N, 3, 3) intrinsics at full resolution.
        sizes: (N, 2) image sizes (w, h).
        keypoints: N arrays (n_i, 2) float32, full-resolution pixels.
        descriptors: N arrays (n_i, 128) uint8.
        images: image folder.
        K_source: N strings: ``file:<path>``, ``exif`` or ``default``.
        digest: hash of names, K and the feature config (downstream cache key).
        config: the extraction config.
        signatures: (N, 2) int64 byte size and mtime (ns) of each image file.
    """

    names: list[str]
    K: np.ndarray
    sizes: np.ndarray
    keypoints: list[np.ndarray]
    descriptors: list[np.ndarray]
    images: Path | None = None
    K_source: list[str] = field(default_factory=list)
    digest: str = ""
    config: FeatureConfig | None = None
    signatures: np.ndarray | None = None


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


def _cache_path(work: Path, key: str, name: str) -> Path:
    return work / FEATURES_DIR / key / f"{name}.npz"


def _file_sig(path: Path) -> tuple[int, int]:
    st = path.stat()
    return int(st.st_size), int(st.st_mtime_ns)


def _cache_valid(cache: Path, sig: tuple[int, int]) -> tuple[int, int] | None:
    """The cached ``(w, h)`` if ``cache`` holds features of an image with signature ``sig``."""
    if not cache.is_file():
        return None
    try:
        with np.load(cache) as d:
            if int(d["file_size"]) == sig[0] and int(d["file_mtime_ns"]) == sig[1]:
                return int(d["size"][0]), int(d["size"][1])
    except Exception:  # noqa: BLE001 - a damaged cache entry is recomputed
        logger.debug("cache entry %s unreadable; recomputing", cache)
    return None


def main(images: Path, work: Path, config: FeatureConfig | None = None, K_path: Path | None = None,
         overwrite: bool = False, progress: bool = True) -> Path:
    """Extract SIFT for every readable image of ``images`` into ``work``.

    Args:
        images: image folder.
        work: WORK folder (created if absent).
        config: extraction options.
        K_path: intrinsics file (``K.txt`` or a per-image cameras file); None looks
            for one in ``images``, then EXIF, then the default focal length.
        overwrite: re-extract even when a valid cache entry exists.
        progress: show a progress bar.
    Returns:
        path of the manifest ``WORK/features.json``.
    Raises:
        InputFileError: the folder does not exist, or fewer than 2 images are usable.
    """
    config = config or FeatureConfig()
    images, work = Path(images), Path(work)
    t_start = time.perf_counter()
    logger.info("features: %s", config)
    names, other = list_images(images)
    if other:
        logger.info("ignoring %d non-image file(s) in %s: %s", len(other), images,
                    ", ".join(other[:5]) + (" ..." if len(other) > 5 else ""))
    if len(names) < 2:
        raise InputFileError(
            f"{images} holds {len(names)} image file(s) ({', '.join(names) or 'none'}) but at least 2 are needed; "
            f"supported extensions: {', '.join(e.lstrip('.') for e in IMAGE_EXTENSIONS)}"
        )
    key = config.cache_key()
    sigs = {n: _file_sig(images / n) for n in names}
    sizes: dict[str, tuple[int, int]] = {}
    todo: list[str] = []
    for n in names:
        hit = None if overwrite else _cache_valid(_cache_path(work, key, n), sigs[n])
        if hit is None:
            todo.append(n)
        else:
            sizes[n] = hit
    skipped: list[dict[str, str]] = []

    def job(name: str) -> tuple[str, tuple[int, int] | None, str, int]:
        gray, reason = read_gray(images / name)
        if gray is None:
            return name, None, reason, 0
        kp = extract_sift(gray, config)
        save_npz(_cache_path(work, key, name), keypoints=kp.xy, scales=kp.scales, orientations=kp.orientations,
                 responses=kp.responses, descriptors=kp.descriptors, size=np.array([gray.shape[1], gray.shape[0]]),
                 file_size=sigs[name][0], file_mtime_ns=sigs[name][1])
        return name, (gray.shape[1], gray.shape[0]), "", len(kp.xy)

    n_kp: list[int] = []
    if todo:
        with ThreadPoolExecutor(max_workers=min(config.workers, len(todo))) as pool:
            bar = tqdm(pool.map(job, todo), total=len(todo), desc="features", unit="img", disable=not progress)
            for name, size, reason, nk in bar:
                if size is None:
                    skipped.append({"name": name, "reason": reason})
                    logger.warning("skipping %s: it %s", images / name, reason)
                else:
                    sizes[name] = size
                    n_kp.append(nk)
    usable = [n for n in names if n in sizes]
    if len(usable) < 2:
        why = "; ".join(f"{s['name']} {s['reason']}" for s in skipped[:5])
        raise InputFileError(f"only {len(usable)} of {len(names)} images in {images} are usable ({why}); at least 2 are needed")
    size_arr = np.array([sizes[n] for n in usable], np.int64)
    K, sources = resolve_intrinsics(images, usable, size_arr, K_path)
    digest = hashlib.sha1(json.dumps([key, usable, np.round(K, 6).tolist()]).encode()).hexdigest()[:12]
    manifest = {
        "format": "rotavg-features",
        "images": str(images.resolve()),
        "names": usable,
        "sizes": size_arr.tolist(),
        "K": K.tolist(),
        "K_source": sources,
        "skipped": skipped,
        "ignored_files": other,
        "signatures": [list(sigs[n]) for n in usable],
        "n_extracted": len(n_kp),
        "n_cached": len(usable) - len(n_kp),
        "config": dataclasses.asdict(config),
        "config_hash": config_hash(config),
        "cache_key": key,
        "digest": digest,
    }
    out = write_json(work / MANIFEST, manifest)
    logger.info("features: %d images (%d extracted, %d from cache, %d skipped) in %.1f s; median %d keypoints per extracted image",
                len(usable), len(n_kp), len(usable) - len(n_kp), len(skipped), time.perf_counter() - t_start,
                int(np.median(n_kp)) if n_kp else 0)
    return out


def load_manifest(work: Path) -> dict:
    """The features manifest of ``work``; a missing one gives an error naming the command to run."""
    path = Path(work) / MANIFEST
    if not path.is_file():
        raise InputFileError(f"{path} not found: run `python -m pipeline.features --images DIR --work {work}` first")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputFileError(f"{path} is not valid JSON ({exc}); re-run pipeline.features with --overwrite") from None


def load_features(work: Path) -> FeatureSet:
    """Read the features written by :func:`main` (keypoints, descriptors, K, sizes)."""
    work = Path(work)
    m = load_manifest(work)
    kps, descs = [], []
    for n in m["names"]:
        p = _cache_path(work, m["cache_key"], n)
        if not p.is_file():
            raise InputFileError(f"{p} is missing: re-run `python -m pipeline.features --images {m['images']} --work {work}`")
        with np.load(p) as d:
            kps.append(d["keypoints"].astype(np.float32))
            descs.append(d["descriptors"])
    return FeatureSet(
        names=list(m["names"]),
        K=np.array(m["K"], float).reshape(-1, 3, 3),
        sizes=np.array(m["sizes"], np.int64).reshape(-1, 2),
        keypoints=kps,
        descriptors=descs,
        images=Path(m["images"]),
        K_source=list(m.get("K_source", [])),
        digest=m["digest"],
        config=FeatureConfig(**m["config"]),
        signatures=np.array(m.get("signatures", [[0, 0]] * len(m["names"])), np.int64).reshape(-1, 2),
    )


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli
    from pipeline.core.config import load_yaml, stage_config

    p = argparse.ArgumentParser(prog="python -m pipeline.features", description="SIFT features of an image folder (cached per image).")
    p.add_argument("--images", type=Path, required=True, help="folder of images")
    p.add_argument("--work", type=Path, required=True, help="WORK folder for the front end's outputs")
    p.add_argument("--K", type=Path, default=None, help="intrinsics: K.txt (3x3) or a per-image cameras file")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'features' section is used")
    p.add_argument("--max-keypoints", type=int, default=None)
    p.add_argument("--max-image-size", type=int, default=None, help="longest side used for extraction (default 1600)")
    p.add_argument("--overwrite", action="store_true", help="re-extract even cached images")

    def body(a: argparse.Namespace) -> int:
        cfg = stage_config(FeatureConfig, load_yaml(a.config), "features", max_keypoints=a.max_keypoints,
                           max_image_size=a.max_image_size)
        out = main(a.images, a.work, cfg, a.K, overwrite=a.overwrite, progress=not a.quiet)
        print(out)
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
