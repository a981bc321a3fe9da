"""Image retrieval for pair selection: a visual vocabulary fitted on the collection's own SIFT (the kernel).

No downloaded weights. The vocabulary is k-means (faiss ``faiss.Kmeans``, seeded) on an
even sample of the collection's RootSIFT descriptors, as a two-level tree
(``k1`` × up to ``k2`` words, :func:`choose_vocabulary`: about 6 training descriptors per
leaf word, 256 × 128 = 32,768 words for 200k descriptors). A word of so fine a
vocabulary, fitted on the collection itself, is nearly a track (one surface point seen
by a few images), which separates overlapping pairs from look-alikes. Each image is a
tf-idf bag of words (Sivic & Zisserman 2003; Nistér & Stewénius 2006) with
square-rooted term frequencies (against bursts), L2-normalised; two images' similarity
is the cosine of their vectors. The pairs are each image's ``k`` most similar images, as
a symmetric union (:func:`knn_pairs`); ``k`` defaults to :func:`choose_k` (≈ 1.5·log₂ N).
Each image's next-ranked images (up to ``RANKED_PER_K``·k, :func:`ranked_neighbours`) are
kept for the loop-closure round (:mod:`pipeline.frontend.loop_closure`).

Every function is pure (arrays in, arrays out, no I/O, no logging). Shapes: D = 128,
N images, n_i descriptors of image i, W words.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from pipeline.frontend.matching import root_sift

__all__ = ["Vocabulary", "sample_descriptors", "kmeans", "fit_vocabulary", "assign", "bow_vectors", "similarity",
           "knn_pairs", "ranked_neighbours", "choose_k", "choose_vocabulary", "retrieve_pairs", "pair_recall",
           "RANKED_PER_K"]

RANKED_PER_K = 4  # ranked neighbours kept per image, in multiples of k: the loop-closure round's candidates


def _as_root_sift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT of uint8 SIFT; float input is taken as RootSIFT already (float32)."""
    return root_sift(desc) if desc.dtype == np.uint8 else np.ascontiguousarray(desc, np.float32)


def sample_descriptors(descs: list[np.ndarray], n_max: int, seed: int = 0) -> np.ndarray:
    """An even sample of at most ``n_max`` rows over all images (each image contributes alike).

    Args:
        descs: N arrays (n_i, D) uint8 SIFT or RootSIFT.
        n_max: sample size.
    Returns:
        (m, D) float32 RootSIFT, m ≤ n_max.
    """
    rng = np.random.default_rng(seed)
    per = max(1, n_max // max(1, len(descs)))
    out = []
    for d in descs:  # per image (not per descriptor)
        if len(d) > per:
            d = d[np.sort(rng.choice(len(d), per, replace=False))]
        out.append(_as_root_sift(d))
    return np.concatenate(out) if out else np.zeros((0, 128), np.float32)


def kmeans(X: np.ndarray, k: int, n_iter: int = 20, seed: int = 0) -> np.ndarray:
    """k-means centroids (min(k, m), D) float32 of X (m, D): faiss Lloyd iterations on the whole sample."""
    import faiss  # noqa: PLC0415 - imported on first use (a heavy import)

    X = np.ascontiguousarray(X, np.float32)
    k = int(min(k, len(X)))
    km = faiss.Kmeans(X.shape[1], k, niter=n_iter, seed=seed, verbose=False, max_points_per_centroid=1 << 30,
                       min_points_per_centroid=1)
    km.train(X)
    return np.asarray(km.centroids, np.float32)


def _nearest(X: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Index (m,) of the nearest row of C (k, D) for each row of X (m, D): exact, one BLAS product per block."""
    out = np.empty(len(X), np.int64)
    c2 = np.einsum("kd,kd->k", C, C)
    step = max(1, (1 << 22) // max(1, len(C)))
    for s in range(0, len(X), step):  # blocks of at most 4M distances (16 MB)
        out[s:s + step] = np.argmin(c2[None, :] - 2.0 * (X[s:s + step] @ C.T), axis=1)
    return out


@dataclass
class Vocabulary:
    """A one- or two-level vocabulary.

    Attributes:
        top: (k1, D) first-level centroids.
        leaves: k1 arrays (k2_c, D): the second-level centroids of each first-level cell
            (empty for a flat vocabulary).
        offsets: (k1 + 1,) the first word id of each cell's leaves.
    """

    top: np.ndarray
    leaves: list[np.ndarray] = field(default_factory=list)
    offsets: np.ndarray | None = None

    @property
    def n_words(self) -> int:
        return int(self.offsets[-1]) if self.leaves and self.offsets is not None else len(self.top)


def fit_vocabulary(X: np.ndarray, branching: tuple[int, ...] = (64, 64), n_iter: int = 20, seed: int = 0) -> Vocabulary:
    """Fit a flat (``(k,)``) or two-level (``(k1, k2)``) vocabulary on descriptors X (m, D).

    The second level clusters each first-level cell's points into at most ``k2`` words (fewer
    when the cell has fewer than 4·k2 points, so that no word is fitted on one or two points).
    """
    if len(branching) not in (1, 2) or min(branching) < 1:
        raise ValueError(f"branching={branching} but expected one or two positive levels, e.g. (256, 128)")
    X = _as_root_sift(X)
    top = kmeans(X, branching[0], n_iter, seed)
    if len(branching) == 1:
        return Vocabulary(top)
    cell = _nearest(X, top)
    leaves, sizes = [], []
    for c in range(len(top)):  # one small k-means per cell (k1 of them)
        Xc = X[cell == c]
        k2 = int(min(branching[1], max(1, len(Xc) // 4)))
        L = kmeans(Xc, k2, n_iter, seed + 1 + c) if len(Xc) > k2 else (Xc if len(Xc) else top[c:c + 1])
        leaves.append(np.ascontiguousarray(L, np.float32))
        sizes.append(len(L))
    return Vocabulary(top, leaves, np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64))


def assign(desc: np.ndarray, vocab: Vocabulary) -> np.ndarray:
    """Word id (n,) of each descriptor (n, D) (uint8 SIFT or RootSIFT): the nearest centroid per level."""
    X = _as_root_sift(desc)
    cell = _nearest(X, vocab.top)
    if not vocab.leaves or vocab.offsets is None:
        return cell
    words = np.empty(len(X), np.int64)
    order = np.argsort(cell, kind="stable")
    bounds = np.searchsorted(cell[order], np.arange(len(vocab.top) + 1))
    for c in np.flatnonzero(np.diff(bounds)):  # occupied cells (≤ k1), vectorized inside
        rows = order[bounds[c]:bounds[c + 1]]
        words[rows] = vocab.offsets[c] + _nearest(X[rows], vocab.leaves[c])
    return words


def bow_vectors(words: list[np.ndarray], n_words: int, tf_power: float = 0.5) -> sp.csr_matrix:
    """tf-idf bag-of-words vectors (N, W) with L2-normalised rows.

    Args:
        words: N arrays of word ids.
        n_words: vocabulary size W.
        tf_power: term-frequency exponent (0.5: square root against bursts; 1: plain counts).
    """
    N = len(words)
    rows = np.repeat(np.arange(N), [len(w) for w in words])
    cols = np.concatenate(words) if N else np.zeros(0, np.int64)
    tf = sp.csr_matrix((np.ones(len(cols)), (rows, cols)), shape=(N, n_words))
    tf.sum_duplicates()
    idf = np.log(N / np.maximum(np.bincount(tf.indices, minlength=n_words), 1))
    tf.data = tf.data**tf_power
    G = tf @ sp.diags(idf)
    norms = np.sqrt(np.asarray(G.multiply(G).sum(axis=1)).ravel())
    return sp.csr_matrix(sp.diags(1.0 / np.maximum(norms, 1e-12)) @ G)


def similarity(G: np.ndarray | sp.spmatrix) -> np.ndarray:
    """(N, N) cosine similarities of unit rows, with the diagonal set to -inf."""
    S = G @ G.T
    S = S.toarray() if sp.issparse(S) else np.array(S, dtype=np.float64)
    np.fill_diagonal(S, -np.inf)
    return S


def knn_pairs(S: np.ndarray, k: int) -> np.ndarray:
    """Symmetric union of each row's ``k`` most similar columns: (P, 2) sorted unique pairs ``a < b``.

    Ties are broken by the column index (a stable sort), so the result is deterministic.
    """
    return _union_pairs(ranked_neighbours(S, k)[0])


def _union_pairs(nn: np.ndarray) -> np.ndarray:
    """Symmetric union (P, 2), sorted unique ``a < b``, of each row's neighbours ``nn`` (N, k)."""
    if nn.shape[1] == 0:
        return np.zeros((0, 2), np.int64)
    a, b = np.repeat(np.arange(nn.shape[0]), nn.shape[1]), nn.ravel().astype(np.int64)
    P = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    return np.unique(P[P[:, 0] != P[:, 1]], axis=0).astype(np.int64)


def ranked_neighbours(S: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's ``m`` most similar columns, best first: indices (N, m') int32 and similarities (N, m') float32,
    ``m' = min(m, N − 1)``; ties broken by the column index, as in :func:`knn_pairs`."""
    m = int(max(0, min(m, S.shape[0] - 1)))
    nn = np.argsort(-S, axis=1, kind="stable")[:, :m]
    return nn.astype(np.int32), np.take_along_axis(S, nn, axis=1).astype(np.float32)


def choose_k(n_images: int, k_min: int = 8, k_max: int = 40) -> int:
    """Neighbours per image: ``round(1.5·log2 N)`` clamped to [k_min, k_max] and to N − 1.

    N = 100 → 10, 200 → 11, 300 → 12, 1000 → 15: the matched pairs grow as N·log N, not N².
    """
    return int(min(n_images - 1, max(k_min, min(k_max, round(1.5 * math.log2(max(n_images, 2)))))))


def choose_vocabulary(n_train: int, k1: int = 256, k2_max: int = 128, per_word: int = 6) -> tuple[int, int]:
    """Two-level branching ``(k1, k2)`` with about ``per_word`` training descriptors per leaf word."""
    k1 = int(max(1, min(k1, n_train // (4 * per_word))))
    return k1, int(min(k2_max, max(4, n_train // (per_word * k1))))


def retrieve_pairs(descs: list[np.ndarray], k: int | None = None, *, n_train: int = 200_000,
                   branching: tuple[int, ...] | None = None, max_per_image: int = 2000,
                   responses: list[np.ndarray] | None = None, seed: int = 0) -> dict:
    """Descriptors → vocabulary → tf-idf vectors → similarities → each image's k nearest → pairs.

    Args:
        descs: N arrays (n_i, 128) uint8 SIFT (or float32 RootSIFT).
        k: neighbours per image (None: :func:`choose_k`).
        n_train: descriptors sampled to fit the vocabulary.
        branching: vocabulary levels (None: :func:`choose_vocabulary`).
        max_per_image: describe each image by its ``max_per_image`` strongest features (by
            ``responses`` when given, else the first ones); 0 keeps all.
        seed: seed of the sample and of k-means (the result is deterministic).
    Returns:
        dict with ``pairs`` (P, 2) ``a < b`` sorted unique, ``k``, ``n_words``, ``time_vocab_s``, ``time_s``,
        and ``neighbours`` (N, m) int32 / ``similarities`` (N, m) float32: each image's
        ``m = min(N − 1, RANKED_PER_K·k)`` most similar images, best first.
    """
    N = len(descs)
    if N < 2:
        return {"pairs": np.zeros((0, 2), np.int64), "k": 0, "n_words": 0, "time_vocab_s": 0.0, "time_s": 0.0,
                "neighbours": np.zeros((N, 0), np.int32), "similarities": np.zeros((N, 0), np.float32)}
    t0 = time.perf_counter()
    k = choose_k(N) if k is None else int(k)
    if k < 1:
        raise ValueError(f"k={k} but expected at least 1 neighbour per image")
    if max_per_image > 0:
        descs = [d if len(d) <= max_per_image else
                 d[np.sort(np.argsort(-responses[i], kind="stable")[:max_per_image] if responses is not None
                           else np.arange(max_per_image))] for i, d in enumerate(descs)]
    X = sample_descriptors(descs, n_train, seed)
    n_words, t1 = 0, t0
    if len(X) < 8:  # too few features for a vocabulary: no evidence against any pair
        S = np.zeros((N, N))
        np.fill_diagonal(S, -np.inf)
    else:
        vocab = fit_vocabulary(X, branching or choose_vocabulary(len(X)), seed=seed)
        n_words, t1 = vocab.n_words, time.perf_counter()
        S = similarity(bow_vectors([assign(d, vocab) for d in descs], vocab.n_words))
    nn, sim = ranked_neighbours(S, RANKED_PER_K * k)  # one sort: the k nearest are its first k columns
    return {"pairs": _union_pairs(nn[:, :k]), "k": k, "n_words": n_words, "time_vocab_s": t1 - t0,
            "time_s": time.perf_counter() - t0, "neighbours": nn, "similarities": sim}


def pair_recall(selected: np.ndarray, truth: np.ndarray, n_images: int) -> dict:
    """Recall of the ``truth`` pairs (M, 2) among ``selected`` (P, 2) (both ``a < b``) and the fraction of all pairs."""
    def key(P: np.ndarray) -> np.ndarray:
        return np.asarray(P, np.int64).reshape(-1, 2) @ np.array([n_images, 1], np.int64)

    hit = np.isin(key(truth), key(selected))
    n_all = n_images * (n_images - 1) // 2
    return {"recall": float(hit.mean()) if len(hit) else float("nan"), "n_true": int(len(hit)),
            "n_found": int(hit.sum()), "n_selected": int(len(selected)),
            "fraction_matched": len(selected) / n_all if n_all else float("nan")}
