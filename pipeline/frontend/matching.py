"""Descriptor matching of one image pair: ratio test and mutual nearest-neighbour check (the kernel).

Descriptors are compared as RootSIFT (L1-normalise, square root: Arandjelović &
Zisserman 2012), whose L2 distance is the Hellinger kernel distance of SIFT.
A match ``(a, b)`` is kept when ``b`` is ``a``'s nearest neighbour in the other
image with ``d1 < ratio · d2`` (Lowe's ratio test), and, with ``mutual=True``,
``a`` is also ``b``'s nearest neighbour.

Nearest-neighbour search (``method``):

- ``"flann"``: one FLANN kd-forest per image, built once and queried by every
  pair that image is in (approximate; ``flann_checks`` leaves per query);
- ``"bf"``: exact brute force as a BLAS product ``D_a D_bᵀ`` (RootSIFT
  descriptors have unit norm, so ``‖a − b‖² = 2 − 2 aᵀb``), in row blocks of at most 32 MB;
- ``"auto"`` (default): ``"flann"`` when both images have more than
  ``bf_max_keypoints`` keypoints, else ``"bf"``. Measured on this machine
  (``python benchmarks/frontend.py``, see ``notes/issue-5.md``).

The stage that matches the selected pairs of a folder is
:mod:`pipeline.frontend.matching_stage`; pair selection is :mod:`pipeline.frontend.pairs`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from pipeline.core.config import option
from pipeline.core.parallel import ExecutorOptions

__all__ = ["MatchingConfig", "root_sift", "match_descriptors", "FlannIndex", "match_prepared"]


@dataclass(frozen=True, kw_only=True)
class MatchingConfig(ExecutorOptions):
    """Matching options (YAML section ``matching``)."""

    SECTION = "matching"

    pairs: str = option("auto", "which pairs to match: auto (exhaustive up to exhaustive_max_images images, "
                        "retrieval above), exhaustive, sequential:K, retrieval:K (K most similar images; retrieval: "
                        "K from N), database (the pairs a COLMAP database verified: --database DB, or database:DB), "
                        "or a pairs file (lines 'name_a name_b')")
    exhaustive_max_images: int = option(50, "pairs=auto matches every pair up to this many images, and each image "
                                        "with its most similar ones (retrieval) above (48 low-texture views: "
                                        "refined 1.1–1.2× more accurate exhaustive, at 1.7× the time)", ge=1)
    ratio: float = option(0.8, "Lowe's ratio-test threshold on L2 distances", gt=0, le=1)
    mutual: bool = option(True, "keep only mutual nearest neighbours")
    method: Literal["auto", "flann", "bf"] = option("auto", "nearest-neighbour search (see pipeline.frontend.matching)")
    bf_max_keypoints: int = option(6000, "'auto' uses brute force when an image has at most this many keypoints",
                                   ge=0)
    flann_trees: int = option(4, "kd-trees per FLANN index", ge=1)
    flann_checks: int = option(32, "leaves visited per FLANN query (accuracy/speed)", ge=1)
    chunk_size: int = option(32, "pairs per task (a task resumes as a whole)", ge=1, runtime=True)
    workers: int = option(2, "pairs matched concurrently (threads)", ge=1, runtime=True)

    def check(self) -> None:
        from pipeline.frontend.pairs import parse_selector  # noqa: PLC0415 - pairs imports nothing of this module

        parse_selector(self.pairs)  # exhaustive, sequential:K or an existing file: refused here, before any work


def root_sift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT: ``sqrt(d / ‖d‖₁)`` (unit L2 norm), float32 (n, 128)."""
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(d)


def _nn2_bf(qa: np.ndarray, db: np.ndarray, block: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact nearest and second-nearest neighbours of rows of ``qa`` in ``db`` (unit vectors).

    The similarity matrix is formed in row blocks of at most 2²³ entries (32 MB):
    one BLAS call per block, as few blocks as that memory bound allows.

    Returns:
        idx1 (n,), d1 (n,), d2 (n,) L2 distances of rows of ``qa``, and (n,) bool:
        row a is also the nearest neighbour of its match ``idx1[a]`` (mutual check).
    """
    n, m = len(qa), len(db)
    if block is None:
        block = max(256, (1 << 23) // max(m, 1))
    idx1 = np.empty(n, np.int64)
    s1 = np.empty(n, np.float32)
    s2 = np.full(n, -1.0, np.float32)
    col_best = np.full(m, -np.inf, np.float32)
    rows = np.arange(min(block, n))
    for start in range(0, n, block):
        S = qa[start:start + block] @ db.T  # cosine similarities
        r = rows[: len(S)]
        a = S.argmax(axis=1)
        idx1[start:start + len(S)] = a
        s1[start:start + len(S)] = S[r, a]
        # a column max is a fast contiguous reduction, unlike a column argmax: the
        # mutual check only needs to know whether S[a, b] is b's best score
        np.maximum(col_best, S.max(axis=0), out=col_best)
        if m > 1:
            S[r, a] = -np.inf
            s2[start:start + len(S)] = S.max(axis=1)
    d1 = np.sqrt(np.maximum(2 - 2 * s1, 0))
    d2 = np.sqrt(np.maximum(2 - 2 * s2, 0)) if m > 1 else np.full(n, np.inf, np.float32)
    return idx1, d1, d2, s1 >= col_best[idx1]


def _flann_params(config: MatchingConfig) -> tuple[dict, dict]:
    return dict(algorithm=1, trees=config.flann_trees), dict(checks=config.flann_checks)


class FlannIndex:
    """A FLANN kd-forest over one image's descriptors, built on first use."""

    def __init__(self, desc: np.ndarray, config: MatchingConfig) -> None:
        self.desc = desc
        self.config = config
        self._index = None
        self._lock = threading.Lock()

    def knn(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            self._build()
        k = min(k, len(self.desc))
        idx, dist = self._index.knnSearch(q, k, params=_flann_params(self.config)[1])
        return idx.astype(np.int64).reshape(len(q), k), np.sqrt(np.maximum(dist, 0)).reshape(len(q), k)

    def _build(self) -> None:
        if self._index is None:
            ip, _ = _flann_params(self.config)
            # FLANN's randomized kd-trees draw from OpenCV's RNG, which is per thread: seed it here,
            # in the thread that builds the index, so the same images give the same matches
            # whatever the thread scheduling or what ran before in the process.
            cv2.setRNGSeed(0)
            self._index = cv2.flann_Index(self.desc, ip)


def _select(idx1: np.ndarray, d1: np.ndarray, d2: np.ndarray, mutual: np.ndarray | None, ratio: float) -> np.ndarray:
    """Matches ``(a, b)`` that pass the ratio test and, if ``mutual`` (n,) bool is given, the mutual check."""
    a = np.arange(len(idx1))
    ok = d1 < ratio * d2
    if mutual is not None:
        ok &= mutual
    return np.stack([a[ok], idx1[ok]], axis=1).astype(np.int32)


def match_descriptors(da: np.ndarray, db: np.ndarray, config: MatchingConfig | None = None) -> np.ndarray:
    """Match two descriptor sets (pure function).

    Args:
        da: (n_a, 128) descriptors (uint8 SIFT or float RootSIFT; uint8 is converted to RootSIFT).
        db: (n_b, 128).
        config: matching options.
    Returns:
        (m, 2) int32 indices ``(in a, in b)``.
    """
    config = config or MatchingConfig()
    qa = root_sift(da) if da.dtype == np.uint8 else np.ascontiguousarray(da, np.float32)
    qb = root_sift(db) if db.dtype == np.uint8 else np.ascontiguousarray(db, np.float32)
    return match_prepared(qa, qb, None, None, config)


def _use_flann(na: int, nb: int, config: MatchingConfig) -> bool:
    if config.method == "flann":
        return True
    if config.method == "bf":
        return False
    return min(na, nb) > config.bf_max_keypoints


def match_prepared(qa: np.ndarray, qb: np.ndarray, ia: FlannIndex | None, ib: FlannIndex | None,
                    config: MatchingConfig) -> np.ndarray:
    if len(qa) < 2 or len(qb) < 2:
        return np.zeros((0, 2), np.int32)
    if _use_flann(len(qa), len(qb), config):
        ib = ib or FlannIndex(qb, config)
        idx, dist = ib.knn(qa, 2)
        mutual = None
        if config.mutual:
            ia = ia or FlannIndex(qa, config)
            back = ia.knn(qb, 1)[0][:, 0]
            mutual = back[idx[:, 0]] == np.arange(len(qa))
        return _select(idx[:, 0], dist[:, 0], dist[:, 1], mutual, config.ratio)
    idx1, d1, d2, mutual = _nn2_bf(qa, qb)
    return _select(idx1, d1, d2, mutual if config.mutual else None, config.ratio)
