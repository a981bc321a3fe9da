"""A COLMAP database in place of our features and matches: ``run.py --database DB IMAGE_DIR``.

:class:`DatabaseFeaturesStage` is the features stage for a database: it writes
the same files as :class:`pipeline.frontend.feature_stage.FeaturesStage` (the
manifest ``features.json`` and the per-image store ``features/``), with the
database's keypoints (undistorted to pinhole pixels, see
:mod:`pipeline.frontend.colmap_db`) and the database's cameras as K. Its record
fingerprints the database file. The manifest names the database, and the
matching stage (:mod:`pipeline.frontend.matching_stage`) then takes the verified
inlier matches from it (:func:`database_matches`) instead of matching
descriptors; every pair then goes on through our RANSAC and two-view BA.

Images are those of IMAGE_DIR that the database holds (names matched by
:func:`pipeline.core.names.match_names`); pixels are never decoded here.
:func:`check_database` checks a database against a folder up front, in a second.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.errors import InputFileError
from pipeline.core.names import match_names
from pipeline.core.store import ItemStore, item_key
from pipeline.frontend import colmap_db
from pipeline.frontend.feature_stage import MANIFEST, STORE, FeaturesStage
from pipeline.frontend.features import FeatureConfig
from pipeline.frontend.images import list_images
from pipeline.stage import fingerprint_of

__all__ = ["DatabaseFeaturesStage", "check_database", "database_matches", "database_pairs"]

logger = logging.getLogger(__name__)

_CHUNK = 64  # pairs read from the database per chunk of the matches store


def _select(db: Path, folder: Path) -> tuple[list[str], list[colmap_db.DbImage]]:
    """The folder's image names that the database holds, and their database images."""
    names, _ = list_images(folder)
    images = colmap_db.read_images(db)
    idx = match_names(names, [im.name for im in images], what=f"the database {db}")
    keep = [(n, images[i]) for n, i in zip(names, idx) if i >= 0]
    if len(keep) < 2:
        raise InputFileError(
            f"the database {db} holds {len(images)} image(s) ({', '.join(im.name for im in images[:3]) or 'none'}) "
            f"but {len(keep)} of them are in {folder} ({', '.join(names[:3]) or 'no image'}); pass the image folder "
            "the database was made from")
    if len(keep) < len(names):
        logger.warning("%d image(s) of %s are not in the database %s and are left out", len(names) - len(keep),
                       folder, db)
    return [n for n, _ in keep], [im for _, im in keep]


def check_database(db: Path, folder: Path) -> dict[str, Any]:
    """Check a database against an image folder before any work: readable, images in common, verified pairs.

    Returns:
        ``names``, ``images`` (:class:`~pipeline.frontend.colmap_db.DbImage`), ``K`` (N, 3, 3)
        and ``n_verified`` (verified pairs among these images).
    Raises:
        InputFileError: one line naming the database.
    """
    names, images = _select(db, folder)
    K = np.stack([colmap_db.pinhole_K(im.model, im.params, f"{db} ({im.name})") for im in images])
    ids = {im.image_id for im in images}
    n_verified = sum(1 for a, b, _ in colmap_db.verified_pairs(db) if a in ids and b in ids)
    if n_verified == 0:
        raise InputFileError(f"the database {db} has no verified matches between the {len(names)} images of "
                             f"{folder}; run matching with geometric verification (e.g. pycolmap.match_exhaustive)")
    distorted = sorted({im.model for im in images} - set(colmap_db._PINHOLE))
    if distorted:
        logger.info("database cameras %s have distortion: keypoints are undistorted with pycolmap's camera model",
                    ", ".join(distorted))
    return {"names": names, "images": images, "K": K, "n_verified": n_verified}


class DatabaseFeaturesStage(FeaturesStage):
    """The features stage fed by a COLMAP database (folder = WORK).

    Args:
        work: WORK folder.
        config: the features options (recorded; extraction options do not apply).
        images: the image folder the database was made from.
        database: the COLMAP database.
        progress: unused (reading is fast); kept for the features stage's signature.
    """

    def __init__(self, work: Path, config: FeatureConfig | None = None, *, images: Path, database: Path,
                 progress: bool = True) -> None:
        super().__init__(work, config, images=images, progress=progress)
        self.database = Path(database)

    def scan(self) -> dict[str, Any]:
        if self._scan is None:
            c = check_database(self.database, self.images)
            self._scan = {**c, "sources": [f"database:{im.model}" for im in c["images"]], "bad": {}, "other": [],
                          "db_fp": colmap_db.database_fingerprint(self.database)}
        return self._scan

    def inputs(self) -> dict[str, str]:
        s = self.scan()
        return {"database": s["db_fp"], "images": fingerprint_of(str(self.images.resolve()), s["names"])}

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        s = self.scan()
        keys = [item_key("colmap-database", s["db_fp"], im.image_id, n) for n, im in zip(s["names"], s["images"])]
        store = ItemStore(self.folder / STORE)
        done = set() if self.overwrite else store.done(keys)
        todo = [k for k, key in enumerate(keys) if key not in done]
        n_kp, n_bad = [], 0
        for k, arrays in zip(todo, colmap_db.iter_keypoints(self.database, [s["images"][k] for k in todo])):
            im = s["images"][k]
            n_bad += int(arrays.pop("n_not_undistorted"))
            store.write_chunk({keys[k]: {**arrays, "size": np.array([im.width, im.height])}})
            n_kp.append(len(arrays["keypoints"]))
        if n_bad:
            logger.warning("%d keypoint(s) could not be undistorted by their camera model and were kept as they are",
                           n_bad)
        files = store.write_index(keys)
        manifest = {
            "format": "rotavg-features", "images": str(self.images.resolve()), "names": s["names"],
            "sizes": [[im.width, im.height] for im in s["images"]], "K": s["K"].tolist(), "K_source": s["sources"],
            "skipped": [], "ignored_files": [], "signatures": [[0, 0] for _ in keys], "keys": keys,
            "config": self.config.as_dict(), "n_extracted": len(todo), "n_cached": len(keys) - len(todo),
            "database": str(self.database.resolve()), "database_fingerprint": s["db_fp"],
            "image_ids": [im.image_id for im in s["images"]],
        }
        path = write_json(self.folder / MANIFEST, manifest)
        logger.info("features from the database %s: %d images (%d read, %d from cache); median %d keypoints per image "
                    "read", self.database, len(keys), len(todo), len(keys) - len(todo),
                    int(np.median(n_kp)) if n_kp else 0)
        return [path, *files], {"n_images": len(keys), "n_extracted": len(todo), "n_skipped": 0,
                                "database": str(self.database)}


def database_pairs(db: Path, names: list[str]) -> np.ndarray:
    """The pairs (P, 2), ``a < b``, of ``names`` that the database ``db`` verified (selector ``database:DB``)."""
    images = colmap_db.read_images(db)
    idx = match_names([im.name for im in images], names, what=f"the images with features (database {db})")
    where = {im.image_id: int(i) for im, i in zip(images, idx) if i >= 0}
    out = {tuple(sorted((where[a], where[b]))) for a, b, _ in colmap_db.verified_pairs(db) if a in where and b in where}
    if not out:
        raise InputFileError(f"the database {db} verified no pair among the {len(names)} images with features")
    return np.array(sorted(out), np.int64).reshape(-1, 2)


def database_matches(fm: dict, selected: np.ndarray | None, key_of: Callable[[int, int], str], store: ItemStore,
                     overwrite: bool = False, on_chunk: Callable[[int], None] | None = None
                     ) -> tuple[np.ndarray, list[str], int]:
    """Fill the matches store from the database named by the features manifest ``fm``.

    Args:
        fm: the features manifest of a :class:`DatabaseFeaturesStage`.
        selected: (S, 2) pairs to keep among the verified ones, or None for all of them.
        key_of: the item key of pair ``(a, b)``.
        store: the matching stage's item store.
        overwrite: read every pair again.
        on_chunk: progress callback (pairs per finished chunk).
    Returns:
        the pairs (P, 2) sorted, their keys, and the number of pairs read.
    """
    db = Path(fm["database"])
    if colmap_db.database_fingerprint(db) != fm.get("database_fingerprint"):
        raise InputFileError(f"the database {db} changed since its features were read; re-run the features stage")
    where = {int(i): k for k, i in enumerate(fm["image_ids"])}
    found: dict[tuple[int, int], tuple[int, int, bool]] = {}
    for a, b, _ in colmap_db.verified_pairs(db):
        if a in where and b in where and where[a] != where[b]:
            i, j = where[a], where[b]
            found[(min(i, j), max(i, j))] = (a, b, i > j)
    if selected is not None:
        keep = {(int(a), int(b)) for a, b in selected}
        found = {p: v for p, v in found.items() if p in keep}
    pairs = np.array(sorted(found), np.int64).reshape(-1, 2)
    if not len(pairs):
        raise InputFileError(f"the database {db} verified no pair among the selected pairs of its {len(where)} images")
    keys = [key_of(int(a), int(b)) for a, b in pairs]
    done = set() if overwrite else store.done(keys)
    todo = [p for p, k in enumerate(keys) if k not in done]
    for s in range(0, len(todo), _CHUNK):
        chunk = todo[s:s + _CHUNK]
        ids = [found[(int(pairs[p][0]), int(pairs[p][1]))][:2] for p in chunk]
        res = {}
        for p, m in zip(chunk, colmap_db.read_inlier_matches(db, ids)):
            swap = found[(int(pairs[p][0]), int(pairs[p][1]))][2]
            res[keys[p]] = {"matches": (m[:, ::-1] if swap else m).astype(np.int32)}
        store.write_chunk(res)
        if on_chunk is not None:
            on_chunk(len(chunk))
    return pairs, keys, len(todo)
