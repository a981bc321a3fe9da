"""Descriptor matching over image pairs: ratio test and mutual nearest-neighbour check.

Stage 2 of the image front end. Pairs are all ``N(N-1)/2`` image pairs by default,
or those of a pairs file (one ``name_a name_b`` per line, hloc's format).
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

Pairs are processed by a thread pool (``workers``): OpenCV's FLANN search and
numpy's BLAS release the GIL.

WORK folder layout written by this stage::

    WORK/matches.json                      manifest: file, features digest, config, pair count,
                                           digest, pairs computed in the last run
    WORK/matches-<features key>-<hash>.npz names (N,), pairs (P, 2) indices into names,
                                           offsets (P+1,), matches (total, 2) int32
                                           keypoint indices (in image a, in image b)

Re-running with the same features and config skips the stage; with new images
(or new pairs) only the missing pairs are matched, the others are reused (unless
one of the two image files changed: size and mtime are compared).

Command line::

    python -m pipeline.matching --work WORK [--pairs FILE] [--ratio 0.8]
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
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import save_npz, write_json
from pipeline.core.config import config_hash
from pipeline.core.errors import InputFileError
from pipeline.features import FeatureSet, load_features

logger = logging.getLogger(__name__)

__all__ = ["MatchingConfig", "MatchSet", "root_sift", "match_descriptors", "exhaustive_pairs", "read_pairs",
           "main", "load_matches", "main_cli", "MANIFEST"]

MANIFEST = "matches.json"


@dataclass(frozen=True, kw_only=True)
class MatchingConfig:
    """Matching options.

    Attributes:
        ratio: Lowe's ratio-test threshold on L2 distances.
        mutual: keep only mutual nearest neighbours.
        method: ``"auto"``, ``"flann"`` or ``"bf"`` (see the module docstring).
        bf_max_keypoints: ``"auto"`` uses brute force when an image has at most this many keypoints.
        flann_trees: kd-trees per FLANN index.
        flann_checks: leaves visited per FLANN query (accuracy/speed).
        workers: pairs matched concurrently (threads).
    """

    ratio: float = 0.8
    mutual: bool = True
    method: str = "auto"
    bf_max_keypoints: int = 6000
    flann_trees: int = 4
    flann_checks: int = 32
    workers: int = 2

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ValueError(f"ratio={self.ratio} but expected 0 < ratio <= 1 (0.8 is usual)")
        if self.method not in ("auto", "flann", "bf"):
            raise ValueError(f"method={self.method!r} but expected 'auto', 'flann' or 'bf'")
        if self.workers < 1:
            raise ValueError(f"workers={self.workers} but expected >= 1")

    def key(self) -> str:
        """Hash of the options that change the result (not ``workers``)."""
        return config_hash(self, exclude=("workers",))


@dataclass
class MatchSet:
    """Matches of a WORK folder (see :func:`load_matches`).

    Attributes:
        names: N image names (those of the features).
        pairs: (P, 2) image indices ``a < b``.
        matches: P arrays (m_p, 2) int32 keypoint indices (in a, in b).
        digest: cache key of this result for downstream stages.
    """

    names: list[str]
    pairs: np.ndarray
    matches: list[np.ndarray]
    digest: str = ""


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


class _FlannIndex:
    """A FLANN kd-forest over one image's descriptors, built on first use."""

    def __init__(self, desc: np.ndarray, config: MatchingConfig) -> None:
        self.desc = desc
        self.config = config
        self._index = None

    def knn(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if self._index is None:
            ip, _ = _flann_params(self.config)
            # FLANN's randomized kd-trees draw from OpenCV's RNG, which is per thread: seed it here,
            # in the thread that builds the index, so the same images give the same matches
            # whatever the thread scheduling or what ran before in the process.
            cv2.setRNGSeed(0)
            self._index = cv2.flann_Index(self.desc, ip)
        k = min(k, len(self.desc))
        idx, dist = self._index.knnSearch(q, k, params=_flann_params(self.config)[1])
        return idx.astype(np.int64).reshape(len(q), k), np.sqrt(np.maximum(dist, 0)).reshape(len(q), k)


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
    return _match_prepared(qa, qb, None, None, config)


def _use_flann(na: int, nb: int, config: MatchingConfig) -> bool:
    if config.method == "flann":
        return True
    if config.method == "bf":
        return False
    return min(na, nb) > config.bf_max_keypoints


def _match_prepared(qa: np.ndarray, qb: np.ndarray, ia: _FlannIndex | None, ib: _FlannIndex | None,
                    config: MatchingConfig) -> np.ndarray:
    if len(qa) < 2 or len(qb) < 2:
        return np.zeros((0, 2), np.int32)
    if _use_flann(len(qa), len(qb), config):
        ib = ib or _FlannIndex(qb, config)
        idx, dist = ib.knn(qa, 2)
        mutual = None
        if config.mutual:
            ia = ia or _FlannIndex(qa, config)
            back = ia.knn(qb, 1)[0][:, 0]
            mutual = back[idx[:, 0]] == np.arange(len(qa))
        return _select(idx[:, 0], dist[:, 0], dist[:, 1], mutual, config.ratio)
    idx1, d1, d2, mutual = _nn2_bf(qa, qb)
    return _select(idx1, d1, d2, mutual if config.mutual else None, config.ratio)


def exhaustive_pairs(n: int) -> np.ndarray:
    """All pairs ``(a, b)``, ``a < b``, of n images: (n(n-1)/2, 2)."""
    a, b = np.triu_indices(n, k=1)
    return np.stack([a, b], axis=1).astype(np.int64)


def read_pairs(path: Path, names: list[str]) -> np.ndarray:
    """Pairs from a file of ``name_a name_b`` lines, as sorted unique index pairs (P, 2).

    Raises:
        InputFileError: missing file, malformed line, unknown image name or no pair.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"pairs file {path} does not exist")
    index = {n: k for k, n in enumerate(names)}
    index_stem = {Path(n).stem: k for k, n in enumerate(names)}
    out = []
    for ln_no, line in enumerate(path.read_text().splitlines(), 1):
        tok = line.split("#")[0].split()
        if not tok:
            continue
        if len(tok) < 2:
            raise InputFileError(f"{path} line {ln_no}: expected 'name_a name_b', got {line.strip()!r}")
        ks = []
        for t in tok[:2]:
            k = index.get(t, index_stem.get(Path(t).stem))
            if k is None:
                raise InputFileError(
                    f"{path} line {ln_no}: image {t!r} is not among the {len(names)} images with features "
                    f"(e.g. {', '.join(names[:3])}); was it skipped as unreadable, or are the pairs from another folder?"
                )
            ks.append(k)
        if ks[0] != ks[1]:
            out.append(sorted(ks))
    if not out:
        raise InputFileError(f"{path} lists no pair of two different images")
    return np.unique(np.array(out, np.int64), axis=0)


def _pair_key(names: list[str], pairs: np.ndarray) -> list[tuple[str, str]]:
    return [(names[a], names[b]) for a, b in pairs]


def main(work: Path, config: MatchingConfig | None = None, pairs_path: Path | None = None, overwrite: bool = False,
         progress: bool = True) -> Path:
    """Match the features of ``work`` over exhaustive pairs or those of ``pairs_path``.

    Returns:
        path of the matches file ``WORK/matches-<key>.npz``.
    """
    config = config or MatchingConfig()
    work = Path(work)
    t_start = time.perf_counter()
    logger.info("matching: %s", config)
    fs: FeatureSet = load_features(work)
    pairs = exhaustive_pairs(len(fs.names)) if pairs_path is None else read_pairs(pairs_path, fs.names)
    fkey = fs.config.cache_key() if fs.config is not None else "x"
    out = work / f"matches-{fkey}-{config.key()}.npz"
    wanted = _pair_key(fs.names, pairs)
    sigs = fs.signatures.tolist() if fs.signatures is not None else []
    digest = hashlib.sha1(json.dumps([fkey, config.key(), wanted, sigs]).encode()).hexdigest()[:12]
    man_path = work / MANIFEST
    if not overwrite and man_path.is_file() and out.is_file():
        try:
            man = json.loads(man_path.read_text())
        except json.JSONDecodeError:
            man = {}
        if man.get("digest") == digest and man.get("file") == out.name:
            logger.info("matching: %d pairs already matched in %s; skipping (use --overwrite to redo)", len(pairs), out)
            write_json(man_path, {**man, "n_computed": 0, "n_reused": int(len(pairs))})
            return out
    # reuse pairs matched earlier with the same features and config
    # (an image whose file changed since has new features: its old pairs are redone)
    previous: dict[tuple[str, str], np.ndarray] = {}
    sig_now = {n: tuple(sg) for n, sg in zip(fs.names, fs.signatures.tolist())} if fs.signatures is not None else {}
    if not overwrite and out.is_file():
        try:
            old = load_matches_file(out)
            with np.load(out) as d:
                old_sig = d["signatures"].tolist() if "signatures" in d.files else [None] * len(old.names)
            same = {n for n, sg in zip(old.names, old_sig) if sg is not None and sig_now.get(n) == tuple(sg)}
            previous = {k: m for k, m in zip(_pair_key(old.names, old.pairs), old.matches) if k[0] in same and k[1] in same}
        except (InputFileError, KeyError, OSError, ValueError):
            previous = {}
    todo = [p for p, key in enumerate(wanted) if key not in previous]
    results: dict[int, np.ndarray] = {p: previous[key] for p, key in enumerate(wanted) if key in previous}
    if todo:
        prepared = [root_sift(d) for d in fs.descriptors]
        indexes = [_FlannIndex(q, config) for q in prepared]

        def job(p: int) -> tuple[int, np.ndarray]:
            a, b = pairs[p]
            return p, _match_prepared(prepared[a], prepared[b], indexes[a], indexes[b], config)

        # build each needed FLANN index once, in parallel, before the pair loop
        needed = sorted({int(x) for p in todo for x in pairs[p]})
        if any(_use_flann(len(prepared[a]), len(prepared[b]), config) for a, b in pairs[todo]):
            with ThreadPoolExecutor(max_workers=config.workers) as pool:
                list(pool.map(lambda k: indexes[k].knn(prepared[k][:1], 1), needed))
        with ThreadPoolExecutor(max_workers=config.workers) as pool:
            for p, m in tqdm(pool.map(job, todo), total=len(todo), desc="matching", unit="pair", disable=not progress):
                results[p] = m
    matches = [results[p] for p in range(len(pairs))]
    counts = np.array([len(m) for m in matches], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    flat = np.concatenate(matches).astype(np.int32) if len(matches) else np.zeros((0, 2), np.int32)
    sig_arr = fs.signatures if fs.signatures is not None else np.zeros((len(fs.names), 2), np.int64)
    save_npz(out, names=np.array(fs.names), pairs=pairs, offsets=offsets, matches=flat.reshape(-1, 2),
             features_digest=np.array(fs.digest), signatures=sig_arr)
    write_json(man_path, {
        "format": "rotavg-matches",
        "file": out.name,
        "features_digest": fs.digest,
        "config": dataclasses.asdict(config),
        "config_hash": config_hash(config),
        "n_pairs": int(len(pairs)),
        "n_computed": len(todo),
        "n_reused": int(len(pairs) - len(todo)),
        "pairs_file": str(pairs_path) if pairs_path else None,
        "digest": digest,
    })
    logger.info("matching: %d pairs (%d matched, %d reused) in %.1f s; median %d matches per pair",
                len(pairs), len(todo), len(pairs) - len(todo), time.perf_counter() - t_start,
                int(np.median(counts)) if len(counts) else 0)
    return out


def load_matches_file(path: Path) -> MatchSet:
    """Read a matches file written by :func:`main`."""
    path = Path(path)
    try:
        with np.load(path) as d:
            names = [str(n) for n in d["names"]]
            pairs = d["pairs"].astype(np.int64).reshape(-1, 2)
            off = d["offsets"]
            flat = d["matches"]
    except (OSError, KeyError, ValueError) as exc:
        raise InputFileError(f"{path} is not a readable matches file ({exc}); re-run pipeline.matching --overwrite") from None
    return MatchSet(names, pairs, [flat[off[k]:off[k + 1]] for k in range(len(pairs))])


def load_matches(work: Path) -> MatchSet:
    """The current matches of ``work`` (the file named in ``WORK/matches.json``)."""
    work = Path(work)
    man_path = work / MANIFEST
    if not man_path.is_file():
        raise InputFileError(f"{man_path} not found: run `python -m pipeline.matching --work {work}` first")
    man = json.loads(man_path.read_text())
    ms = load_matches_file(work / man["file"])
    ms.digest = man["digest"]
    return ms


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli
    from pipeline.core.config import load_yaml, stage_config

    p = argparse.ArgumentParser(prog="python -m pipeline.matching", description="Match the SIFT features of WORK (ratio test + mutual check).")
    p.add_argument("--work", type=Path, required=True, help="WORK folder written by pipeline.features")
    p.add_argument("--pairs", type=Path, default=None, help="pairs file ('name_a name_b' per line); default: all pairs")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'matching' section is used")
    p.add_argument("--ratio", type=float, default=None, help="ratio-test threshold (default 0.8)")
    p.add_argument("--method", choices=["auto", "flann", "bf"], default=None)
    p.add_argument("--overwrite", action="store_true", help="match all pairs again")

    def body(a: argparse.Namespace) -> int:
        cfg = stage_config(MatchingConfig, load_yaml(a.config), "matching", ratio=a.ratio, method=a.method)
        print(main(a.work, cfg, a.pairs, overwrite=a.overwrite, progress=not a.quiet))
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
