"""The features stage: SIFT for every usable image of a folder, cached per image.

Before any image is decoded, every header is checked
(:func:`pipeline.frontend.images.check_headers`) and the intrinsics are resolved
and checked (:func:`pipeline.frontend.intrinsics.resolve_intrinsics`), so a bad
``--K`` fails in a second, not after SIFT. Images that cannot be used are left out
with their reason.

WORK folder layout::

    WORK/features.json            manifest: image folder, names, sizes (w, h), K per image
                                  and its source, skipped images and why, item keys, and the
                                  images whose contrast threshold was lowered (``lowered``:
                                  {name: {n_normal, n_keypoints, contrast_used, preblur_sigma, affine}})
    WORK/features/chunk-*.npz     one image each: keypoints (n, 2) float32 px, scales,
                                  orientations (deg), responses, descriptors (n, 128) uint8,
                                  size (w, h), n_normal, lowered, contrast_used, preblur_sigma
    WORK/features/index.json      the item keys of the current images
    WORK/features.record.json     the stage record (pipeline.stage)

An image's item key hashes the result-affecting options and the image file's
name, size and mtime: a changed image or option is extracted again, an unchanged
one never. Command line::

    python -m pipeline.features --images DIR --work WORK [--K FILE | --database DB] [--max-image-size 1600]
                                [--executor auto|serial|threads|processes|dask] [--scheduler ADDRESS]
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import write_json
from pipeline.core.errors import CacheError, InputFileError, PipelineError
from pipeline.core.readers import array_field, name_list, read_json
from pipeline.core.store import ItemStore, item_key
from pipeline.frontend.features import FeatureConfig, extract_sift_adaptive
from pipeline.frontend.images import IMAGE_EXTENSIONS, check_headers, ends_crc, list_images, read_gray
from pipeline.frontend.intrinsics import check_K, resolve_intrinsics
from pipeline.stage import Stage, StageRecord, fingerprint_of, read_record

logger = logging.getLogger(__name__)

__all__ = ["FeaturesStage", "FeatureSet", "load_features", "load_manifest", "main", "main_cli", "MANIFEST",
           "STORE"]

MANIFEST = "features.json"
STORE = "features"


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
        lowered: ``{name: {n_normal, n_keypoints, contrast_used, preblur_sigma, affine}}`` of the images
            whose contrast threshold was lowered (low texture).
        digest: the features stage's fingerprint (downstream cache input).
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
    lowered: dict[str, dict[str, Any]] = field(default_factory=dict)


def _extract_task(args: tuple[str, str, str, dict[str, Any], str]) -> tuple[str, str, int | None, str]:
    """Worker: read one image, extract SIFT and write it as one chunk of the store at ``args[4]``.

    Returns ``(key, name, number of keypoints or None, chunk file name or the reason it was skipped)``.
    """
    path, name, key, cfg, folder = args
    gray, reason = read_gray(path)
    if gray is None:
        return key, name, None, reason
    kp, info = extract_sift_adaptive(gray, FeatureConfig(**cfg))
    chunk = ItemStore(folder).write_chunk({key: {
        "keypoints": kp.xy, "scales": kp.scales, "orientations": kp.orientations, "responses": kp.responses,
        "descriptors": kp.descriptors, "size": np.array([gray.shape[1], gray.shape[0]]),
        "n_normal": np.array(info.n_normal), "lowered": np.array(info.lowered),
        "contrast_used": np.array(info.contrast_used), "preblur_sigma": np.array(info.preblur_sigma),
        "affine": np.array(info.affine)}})
    return key, name, len(kp.xy), chunk.name


def _lowered_record(item: dict[str, np.ndarray]) -> dict[str, Any] | None:
    """What the extraction of one image lowered, from its stored arrays (None: nothing)."""
    if "lowered" not in item or not bool(item["lowered"]):
        return None
    return {"n_normal": int(item["n_normal"]), "n_keypoints": int(len(item["keypoints"])),
            "contrast_used": round(float(item["contrast_used"]), 6), "preblur_sigma": float(item["preblur_sigma"]),
            "affine": bool(item.get("affine", False))}


class FeaturesStage(Stage[FeatureConfig]):
    """SIFT features of an image folder.

    Args:
        work: WORK folder.
        config: extraction options.
        images: image folder.
        K_path: intrinsics file or folder (None: look in ``images``, then EXIF, then the default).
        progress: show a progress bar.
    """

    name = "features"
    title = "SIFT features"
    config_cls = FeatureConfig

    def __init__(self, work: Path, config: FeatureConfig | None = None, *, images: Path,
                 K_path: Path | None = None, progress: bool = True) -> None:
        super().__init__(work, config)
        self.images = Path(images)
        self.K_path = None if K_path is None else Path(K_path)
        self.progress = progress
        self._scan: dict[str, Any] | None = None

    def scan(self) -> dict[str, Any]:
        """List the images, check their headers and resolve K (no decoding); done once."""
        if self._scan is not None:
            return self._scan
        names, other = list_images(self.images)
        if other:
            logger.info("ignoring %d non-image file(s) in %s: %s", len(other), self.images,
                        ", ".join(other[:5]) + (" ..." if len(other) > 5 else ""))
        if len(names) < 2:
            raise InputFileError(
                f"{self.images} holds {len(names)} image file(s) ({', '.join(names) or 'none'}) but at least 2 "
                f"are needed; supported extensions: {', '.join(e.lstrip('.') for e in IMAGE_EXTENSIONS)}")
        sizes, bad = check_headers(self.images, names)
        for n, why in bad.items():
            logger.warning("skipping %s: it %s", self.images / n, why)
        ok = [n for n in names if n in sizes]
        if len(ok) < 2:
            raise InputFileError(f"only {len(ok)} of {len(names)} images in {self.images} are usable "
                                 f"({'; '.join(f'{n} {w}' for n, w in list(bad.items())[:5])}); at least 2 are needed")
        K, sources = resolve_intrinsics(self.images, ok, np.array([sizes[n] for n in ok], np.int64), self.K_path)
        sigs = {}
        for n in ok:  # an image is known by its size, time and the checksum of its ends (a copy with the same time)
            st = (self.images / n).stat()
            sigs[n] = (int(st.st_size), int(st.st_mtime_ns), ends_crc(self.images / n))
        self._scan = {"names": ok, "other": other, "sizes": sizes, "bad": bad, "K": K, "sources": sources,
                      "sigs": sigs}
        return self._scan

    def inputs(self) -> dict[str, str]:
        s = self.scan()
        return {"images": fingerprint_of(str(self.images.resolve()), [[n, *s["sigs"][n]] for n in s["names"]]),
                "K": fingerprint_of(np.round(s["K"], 9).tolist(), s["sources"])}

    def _keys(self) -> dict[str, str]:
        s = self.scan()
        fp = self.config.fingerprint()
        return {n: item_key(fp, n, *s["sigs"][n]) for n in s["names"]}

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        s = self.scan()
        cfg = self.config
        logger.info("features: %s", cfg)
        keys = self._keys()
        store = ItemStore(self.folder / STORE)
        if not self.overwrite:
            store.drop_damaged(list(keys.values()), lambda i, item: _image_features(item, s["names"][i]),
                               f"images' features in {self.folder / STORE}")
        done = set() if self.overwrite else store.done(keys.values())
        todo = [n for n in s["names"] if keys[n] not in done]
        skipped = [{"name": n, "reason": w} for n, w in s["bad"].items()]
        folder = str(store.folder.resolve())  # workers write their chunks (absolute: they may run elsewhere)
        tasks = [(str((self.images / n).resolve()), n, keys[n], cfg.as_dict(), folder) for n in todo]
        n_kp: list[int] = []
        with cfg.open_executor(len(tasks), "threads") as ex:
            bar = tqdm(ex.map(_extract_task, tasks), total=len(tasks), desc="features", unit="img",
                       disable=not self.progress)
            for key, name, n, chunk_or_reason in bar:
                if n is None:
                    skipped.append({"name": name, "reason": chunk_or_reason})
                    logger.warning("skipping %s: it %s", self.images / name, chunk_or_reason)
                    continue
                store.adopt(chunk_or_reason, [key])
                n_kp.append(n)
        failed = {d["name"] for d in skipped}
        usable = [n for n in s["names"] if n not in failed]
        if len(usable) < 2:
            why = "; ".join(f"{d['name']} {d['reason']}" for d in skipped[:5])
            raise InputFileError(f"only {len(usable)} of {len(s['names']) + len(s['bad'])} images in {self.images} "
                                 f"are usable ({why}); at least 2 are needed")
        files = store.write_index([keys[n] for n in usable])
        keep = [s["names"].index(n) for n in usable]
        lowered = {}
        for n in usable:
            rec = _lowered_record(store.get(keys[n]))
            if rec is not None:
                lowered[n] = rec
        manifest = {
            "format": "rotavg-features",
            "images": str(self.images.resolve()),
            "names": usable,
            "sizes": [list(s["sizes"][n]) for n in usable],
            "K": s["K"][keep].tolist(),
            "K_source": [s["sources"][k] for k in keep],
            "skipped": skipped,
            "ignored_files": s["other"],
            "signatures": [list(s["sigs"][n][:2]) for n in usable],  # size, time (the ends' CRC is in the keys)
            "keys": [keys[n] for n in usable],
            "config": cfg.as_dict(),
            "lowered": lowered,
            "n_extracted": len(n_kp),
            "n_cached": len(usable) - len(n_kp),
        }
        path = write_json(self.folder / MANIFEST, manifest)
        logger.info("features: %d images (%d extracted, %d from cache, %d skipped); median %d keypoints per "
                    "extracted image", len(usable), len(n_kp), len(usable) - len(n_kp), len(skipped),
                    int(np.median(n_kp)) if n_kp else 0)
        if lowered:
            logger.info("features: low texture, contrast threshold lowered for %d image(s): %s", len(lowered),
                        ", ".join(f"{n} ({r['n_normal']} -> {r['n_keypoints']} keypoints)"
                                  for n, r in list(lowered.items())[:5]) + (" ..." if len(lowered) > 5 else ""))
        n_affine = sum(bool(r["affine"]) for r in lowered.values())
        if n_affine:
            logger.info("features: texture-starved, detected over simulated viewpoints (affine) in %d image(s)",
                        n_affine)
        return [path, *files], {"n_images": len(usable), "n_extracted": len(n_kp), "n_skipped": len(skipped),
                                "n_lowered": len(lowered), "n_affine": n_affine}

    def verify(self, record: StageRecord) -> None:
        m = load_manifest(self.folder)
        store = ItemStore(self.folder / STORE)
        if list(store.load_index()) != list(m["keys"]):
            raise CacheError(f"{self.folder / MANIFEST} and its store disagree on the images")
        store.check(m["keys"], lambda i, item: _image_features(item, m["names"][i]),
                    f"images' features in {self.folder / STORE}")  # the manifest's fields: load_manifest


def load_manifest(work: Path) -> dict:
    """The features manifest of ``work``, checked; a missing or damaged one gives an error naming the command to run."""
    path = Path(work) / MANIFEST
    if not path.is_file():
        raise InputFileError(f"{path} not found: run `python -m pipeline.features --images DIR --work {work}` first")
    m = read_json(path, "the features manifest", CacheError)
    try:
        if not isinstance(m, dict):
            raise ValueError("not a mapping")
        n = len(name_list(m["names"], "names"))
        if n == 0:
            raise ValueError("no image")
        name_list(m["keys"], "keys", n)
        array_field(m["sizes"], np.int64, (n, 2), "sizes", low=1, high=2 ** 31)
        for k, K in enumerate(array_field(m["K"], float, (n, 3, 3), "K")):
            check_K(K, f"K of image {k}")
        array_field(m["signatures"], np.int64, (n, 2), "signatures", low=0)
        if not isinstance(m["images"], str) or not isinstance(m.get("K_source", []), list):
            raise ValueError("images or K_source of the wrong type")
        if not all(isinstance(d, dict) and isinstance(d.get("name"), str) and isinstance(d.get("reason"), str)
                   for d in m.get("skipped", [])):
            raise ValueError("skipped is not a list of {name, reason}")
        FeatureConfig.from_dict(m["config"])
    except (ValueError, KeyError, TypeError, OverflowError, PipelineError) as exc:
        raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:100]}); re-run pipeline.features") from None
    return m


def _image_features(item: Any, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The (n, 2) keypoints and (n, 128) descriptors of one stored image, checked."""
    kp, desc = item["keypoints"], item["descriptors"]
    if not (kp.ndim == 2 and kp.shape[1] == 2 and kp.dtype.kind == "f" and np.isfinite(kp).all()
            and desc.shape == (len(kp), 128) and desc.dtype == np.uint8):
        raise CacheError(f"{item.source}: the features of {name} are damaged (keypoints {kp.shape} {kp.dtype}, "
                         f"descriptors {desc.shape} {desc.dtype})")
    return kp.astype(np.float32), desc


def load_features(work: Path, descriptors: bool = True) -> FeatureSet:
    """Read the features written by the stage (keypoints, descriptors, K, sizes), checked."""
    work = Path(work)
    m = load_manifest(work)
    store = ItemStore(work / STORE)
    store.load_index()
    kps, descs = [], []
    for name, k in zip(m["names"], m["keys"]):  # one read per image
        kp, desc = _image_features(store.get(k), name)
        kps.append(kp)
        descs.append(desc if descriptors else np.zeros((0, 128), np.uint8))
    rec = read_record(work, FeaturesStage.name)
    return FeatureSet(
        names=list(m["names"]),
        K=np.array(m["K"], float).reshape(-1, 3, 3),
        sizes=np.array(m["sizes"], np.int64).reshape(-1, 2),
        keypoints=kps,
        descriptors=descs,
        images=Path(m["images"]),
        K_source=list(m.get("K_source", [])),
        digest=rec.fingerprint if rec is not None else "",
        config=FeatureConfig.from_dict(m["config"]),
        signatures=np.array(m["signatures"], np.int64).reshape(-1, 2),
        lowered=dict(m.get("lowered") or {}),
    )


def main(images: Path, work: Path, config: FeatureConfig | None = None, K_path: Path | None = None,
         overwrite: bool = False, progress: bool = True, database: Path | None = None) -> Path:
    """Run the stage (reusing an intact cached result); returns the manifest path.

    With ``database`` (a COLMAP database of ``images``) its cameras and keypoints are taken instead
    (:mod:`pipeline.frontend.database_stage`), and the matching stage then takes its verified matches.
    """
    if database is not None:
        from pipeline.frontend.database_stage import DatabaseFeaturesStage  # noqa: PLC0415 - it imports this module

        if K_path is not None:
            raise InputFileError("--database DB takes the intrinsics from the database; drop --K")
        DatabaseFeaturesStage(work, config, images=images, database=database, progress=progress).run(overwrite)
    else:
        FeaturesStage(work, config, images=images, K_path=K_path, progress=progress).run(overwrite)
    return Path(work) / MANIFEST


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m pipeline.features",
                                description="SIFT features of an image folder (cached per image).")
    p.add_argument("--images", type=Path, required=True, help="folder of images")
    p.add_argument("--work", type=Path, required=True, help="WORK folder for the front end's outputs")
    p.add_argument("--K", type=Path, default=None, help="intrinsics: K.txt (3x3) or a per-image cameras file")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'features' section is used")
    p.add_argument("--database", type=Path, default=None, metavar="DB",
                   help="a COLMAP database of these images: take its cameras and keypoints (and, in the matching "
                        "stage, its verified matches) instead of extracting SIFT")
    p.add_argument("--overwrite", action="store_true", help="re-extract even cached images")
    add_config_args(p, FeatureConfig)

    def body(a: argparse.Namespace) -> int:
        cfg = config_from_args(FeatureConfig, a, a.config)
        print(main(a.images, a.work, cfg, a.K, overwrite=a.overwrite, progress=not a.quiet, database=a.database))
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
