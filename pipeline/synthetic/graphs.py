"""Synthetic view graphs with known rotations, seeded and deterministic.

Three protocols, all in the project's conventions (``../shared/DESIGN.md``):
cam_from_world ``R_i``; edge ``(i, j)``, ``i < j``, measures ``R_ij = R_j R_iᵀ``;
noise acts on the left, ``R̃_ij = exp([Δω]×) R_j R_iᵀ``.

- :func:`paper1_graph`: paper 1 (Chatterjee & Govindu), §6 "Statistical
  efficiency" / Fig. 4. Haar-random cameras, each pair kept with probability
  ``p``, isotropic Gaussian noise of ``σ`` per axis, a fraction of edges replaced
  by Haar-random rotations (outliers).
- :func:`paper2_graph`: paper 2 (Olsson et al.), §5.1 and supplement C.1.
  ``K_obs = max(N−1, ⌈p·N(N−1)/2⌉)`` distinct pairs, anisotropic precisions
  ``H_ij`` with a Haar-random eigenbasis and eigenvalues uniform in a range,
  ``Δω ~ N(0, H⁻¹)``.
- :func:`knn_graph`: a scale protocol. Cameras at uniform points of the unit
  square, each linked to its ``k`` nearest neighbours (mean degree ≈ 14 for
  ``k = 12``), isotropic noise and outliers as in paper 1. N = 10,000 takes well
  under 2 s.

Camera names are the 0-based indices as strings, as for ``.mat`` inputs.
Every generator redraws its edge set (same generator stream, so still
deterministic) until the graph is connected, because rotation averaging is
defined only up to one rotation per connected component (``paper2_graph`` can
also follow paper 2 literally, "every camera has an edge", with
``connected=False``).
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

logger = logging.getLogger(__name__)

__all__ = ["SyntheticGraph", "paper1_graph", "paper2_graph", "knn_graph", "with_outliers"]

MAX_TRIES = 1000


@dataclass
class SyntheticGraph:
    """A noisy view graph and the truth it was drawn from.

    Attributes:
        vg: the measurements; ``vg.H`` is set where the protocol defines it
            (paper 2), else None.
        R_true: (N, 3, 3) true cam_from_world rotations.
        outlier_mask: (M,) True for edges replaced by a random rotation.
    """

    vg: ViewGraph
    R_true: np.ndarray
    outlier_mask: np.ndarray


def _check(n: int, p: float | None = None, sigma_deg: float | None = None, outlier_frac: float | None = None) -> None:
    if int(n) != n or n < 2:
        raise ValueError(f"n={n} but expected an integer >= 2 cameras")
    if p is not None and not (0.0 < p <= 1.0):
        raise ValueError(f"p={p} but expected a fraction of observed pairs in (0, 1]")
    if sigma_deg is not None and not (np.isfinite(sigma_deg) and sigma_deg >= 0):
        raise ValueError(f"sigma_deg={sigma_deg} but expected a finite value >= 0 (degrees per axis)")
    if outlier_frac is not None and not (0.0 <= outlier_frac <= 1.0):
        raise ValueError(f"outlier_frac={outlier_frac} but expected a fraction in [0, 1]")


def _is_connected(n: int, edges: np.ndarray) -> bool:
    if edges.shape[0] < n - 1:
        return False
    A = sp.coo_matrix((np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    n_comp, _ = connected_components(A, directed=False)
    return n_comp == 1


def _pairs(n: int) -> np.ndarray:
    """(n(n−1)/2, 2) all pairs ``i < j`` in row-major order."""
    i, j = np.triu_indices(n, 1)
    return np.stack([i, j], axis=1).astype(np.int64)


def _true_relative(R: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(M, 3, 3) ``R_j R_iᵀ`` for each edge."""
    return so3.relative(R, edges)


def _isotropic_measurements(
    R: np.ndarray, edges: np.ndarray, sigma_deg: float, outlier_frac: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Paper 1's noise model on given edges.

    ``Δω = σ·z`` with ``z ~ N(0, I₃)`` (σ in radians, per axis, so the angle
    ``|Δω|`` follows σ times a chi distribution with 3 dof: mean ≈ 1.6σ), and
    ``R̃_ij = exp([Δω]×) R_j R_iᵀ``. Then ``round(outlier_frac·M)`` edges, chosen
    uniformly without replacement, are replaced by Haar-random rotations.
    """
    M = edges.shape[0]
    dw = np.deg2rad(sigma_deg) * rng.standard_normal((M, 3))
    R_rel = so3.exp(dw) @ _true_relative(R, edges)
    idx, rot = _draw_outliers(M, outlier_frac, rng)
    mask = np.zeros(M, dtype=bool)
    mask[idx] = True
    R_rel[idx] = rot
    return R_rel, mask


def _draw_outliers(m: int, frac: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``round(frac·m)`` edge indices drawn uniformly without replacement, and as many Haar-random rotations."""
    n_out = int(round(frac * m))
    if not n_out:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3))
    idx = rng.choice(m, size=n_out, replace=False)
    return idx, so3.random_rotations(n_out, rng)


def paper1_graph(n: int, p: float, sigma_deg: float, outlier_frac: float = 0.0, seed: int = 0) -> SyntheticGraph:
    """Paper 1, Fig. 4 protocol (there: n = 100, p = 0.5, σ in 0…10°, 0 or 20% outliers).

    1. ``n`` Haar-random cam_from_world rotations.
    2. Each of the ``n(n−1)/2`` pairs kept independently with probability ``p``
       (redrawn until the graph is connected).
    3. Noise: ``Δω ~ N(0, σ² I₃)`` (σ = ``sigma_deg`` in radians on each axis),
       ``R̃_ij = exp([Δω]×) R_j R_iᵀ``.
    4. ``round(outlier_frac·M)`` edges replaced by Haar-random rotations.

    Args:
        n: number of cameras (>= 2).
        p: probability that a pair is observed.
        sigma_deg: per-axis noise standard deviation, degrees.
        outlier_frac: fraction of edges that are outliers.
        seed: seed of ``numpy.random.default_rng``.

    Returns:
        SyntheticGraph with ``vg.H = None``.
    """
    _check(n, p, sigma_deg, outlier_frac)
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    pairs = _pairs(n)
    for _ in range(MAX_TRIES):
        edges = pairs[rng.random(pairs.shape[0]) < p]
        if _is_connected(n, edges):
            break
    else:
        raise ValueError(f"no connected graph in {MAX_TRIES} draws with n={n}, p={p}; increase p")
    R_rel, mask = _isotropic_measurements(R, edges, sigma_deg, outlier_frac, rng)
    vg = ViewGraph([str(i) for i in range(n)], edges, R_rel)
    return SyntheticGraph(vg, R, mask)


def random_precisions(m: int, eig_range: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """(m, 3, 3) precisions ``Q diag(λ) Qᵀ``, Q Haar-random, λ uniform in ``eig_range`` (1/rad²)."""
    lo, hi = float(eig_range[0]), float(eig_range[1])
    if not (0 < lo <= hi < np.inf):
        raise ValueError(f"eig_range={eig_range} but expected 0 < low <= high < inf (1/rad²)")
    Q = so3.random_rotations(m, rng)
    lam = rng.uniform(lo, hi, size=(m, 3))
    return np.einsum("mab,mb,mcb->mac", Q, lam, Q)


def sample_left_noise(H: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(m, 3) draws ``Δω ~ N(0, H⁻¹)`` for precisions H (m, 3, 3).

    With ``H = L Lᵀ`` (Cholesky), ``Δω = L⁻ᵀ z`` has covariance ``L⁻ᵀL⁻¹ = H⁻¹``.
    """
    L = np.linalg.cholesky(H)
    z = rng.standard_normal((H.shape[0], 3, 1))
    return np.linalg.solve(np.swapaxes(L, 1, 2), z)[..., 0]


def _random_tree(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n−1, 2) edges of a uniformly random labelled tree (a random Prüfer sequence, decoded)."""
    if n == 2:
        return np.array([[0, 1]], dtype=np.int64)
    seq = rng.integers(0, n, size=n - 2)
    degree = np.bincount(seq, minlength=n) + 1
    leaves = list(np.flatnonzero(degree == 1))
    heapq.heapify(leaves)
    out = np.empty((n - 1, 2), dtype=np.int64)
    for k, v in enumerate(seq):  # O(n log n) over cameras, not edges
        leaf = heapq.heappop(leaves)
        out[k] = (leaf, v)
        degree[v] -= 1
        if degree[v] == 1:
            heapq.heappush(leaves, v)
    out[n - 2] = (heapq.heappop(leaves), heapq.heappop(leaves))
    return np.sort(out, axis=1)


def paper2_graph(
    n: int, p: float, eig_range: tuple[float, float] = (10.0, 100.0), seed: int = 0, connected: bool = True
) -> SyntheticGraph:
    """Paper 2, §5.1 / supplement protocol with anisotropic noise.

    1. ``n`` Haar-random cam_from_world rotations.
    2. ``K_obs = max(n−1, ⌈p·n(n−1)/2⌉)`` distinct pairs drawn uniformly without
       replacement, redrawn until every camera has an edge (and, with
       ``connected``, until the graph is connected). When ``K_obs = n−1`` and
       ``connected``, the connected draws are exactly the spanning trees, so a
       uniformly random tree is drawn directly (rejection would take ~forever).
    3. ``H_ij = Q diag(λ) Qᵀ``: Q Haar-random, λ uniform in ``eig_range`` (1/rad²).
       Paper 2 §5.1 samples the eigenvalues of ``H⁻¹`` in [0.01, 0.1], i.e.
       ``eig_range = (10, 100)``; its Fig. 2 uses [0.1, 1], i.e. ``(1, 10)``.
    4. ``Δω ~ N(0, H_ij⁻¹)`` and ``R̃_ij = exp([Δω]×) R_j R_iᵀ`` (left
       perturbation; Δω is symmetric, so ``H_ij`` is also the precision of the
       project's ``R_j R_iᵀ = exp([−Δω]×) R̃_ij`` and is what the view graph stores).

    Args:
        n: number of cameras (>= 2).
        p: fraction of the pairs observed (paper 2's "1 − missing data").
        eig_range: (low, high) range of the eigenvalues of H, 1/rad².
        seed: seed of ``numpy.random.default_rng``.
        connected: also require a connected graph (default), which rotation
            averaging and one-rotation alignment need.

    Returns:
        SyntheticGraph with ``vg.H`` set and no outliers.
    """
    _check(n, p)
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    pairs = _pairs(n)
    k_obs = max(n - 1, math.ceil(p * pairs.shape[0]))
    if connected and k_obs == n - 1:
        edges = _random_tree(n, rng)
        edges = edges[np.lexsort((edges[:, 1], edges[:, 0]))]
    else:
        for _ in range(MAX_TRIES):
            idx = np.sort(rng.choice(pairs.shape[0], size=k_obs, replace=False))
            edges = pairs[idx]
            ok = _is_connected(n, edges) if connected else np.all(np.bincount(edges.ravel(), minlength=n) > 0)
            if ok:
                break
        else:
            what = "connected graph" if connected else "graph with an edge at every camera"
            raise ValueError(f"no {what} in {MAX_TRIES} draws of {k_obs} pairs with n={n}, p={p}; increase p")
    H = random_precisions(edges.shape[0], eig_range, rng)
    dw = sample_left_noise(H, rng)
    R_rel = so3.exp(dw) @ _true_relative(R, edges)
    vg = ViewGraph([str(i) for i in range(n)], edges, R_rel, H=H)
    return SyntheticGraph(vg, R, np.zeros(edges.shape[0], dtype=bool))


def knn_graph(n: int, k: int = 12, sigma_deg: float = 2.0, outlier_frac: float = 0.15, seed: int = 0) -> SyntheticGraph:
    """Scale protocol: a k-nearest-neighbour graph on random points of the unit square.

    1. ``n`` points uniform in [0, 1]² and ``n`` Haar-random rotations.
    2. Each point linked to its ``k`` nearest neighbours; the union of these
       links, undirected, is the edge set (mean degree ≈ 14 for k = 12, since
       most but not all neighbour relations are mutual). Redrawn until connected.
    3. Noise and outliers as in :func:`paper1_graph`: ``Δω ~ N(0, σ² I₃)`` per
       axis, ``round(outlier_frac·M)`` edges replaced by Haar-random rotations.

    Args:
        n: number of cameras (> k).
        k: neighbours per camera.
        sigma_deg: per-axis noise standard deviation, degrees.
        outlier_frac: fraction of edges that are outliers.
        seed: seed of ``numpy.random.default_rng``.

    Returns:
        SyntheticGraph with ``vg.H = None``.
    """
    _check(n, None, sigma_deg, outlier_frac)
    if int(k) != k or k < 1 or k >= n:
        raise ValueError(f"k={k} but expected an integer in [1, n−1] = [1, {n - 1}]")
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    for _ in range(MAX_TRIES):
        pts = rng.random((n, 2))
        _, nbr = cKDTree(pts).query(pts, k=k + 1)
        src = np.repeat(np.arange(n), k)
        dst = nbr[:, 1:].ravel()
        # Coincident points could put a point among its own neighbours; drop those.
        ok = src != dst
        a, b = np.minimum(src[ok], dst[ok]), np.maximum(src[ok], dst[ok])
        key = np.unique(a.astype(np.int64) * n + b)
        edges = np.stack([key // n, key % n], axis=1)
        if _is_connected(n, edges):
            break
    else:
        raise ValueError(f"no connected {k}-NN graph in {MAX_TRIES} draws with n={n}; increase k")
    R_rel, mask = _isotropic_measurements(R, edges, sigma_deg, outlier_frac, rng)
    vg = ViewGraph([str(i) for i in range(n)], edges, R_rel)
    return SyntheticGraph(vg, R, mask)


def with_outliers(vg: ViewGraph, frac: float, seed: int = 0) -> tuple[ViewGraph, np.ndarray]:
    """Replace ``round(frac·M)`` edges' ``R_rel`` by Haar-random rotations, keeping their H.

    Returns:
        the new view graph and the (M,) outlier mask.
    """
    _check(2, outlier_frac=frac)
    idx, rot = _draw_outliers(vg.n_edges, frac, np.random.default_rng(seed))
    out = np.zeros(vg.n_edges, dtype=bool)
    out[idx] = True
    R_rel = vg.R_rel.copy()
    R_rel[out] = rot  # in edge order (as benchmarks/results/irls_h.json was made), not in draw order
    return ViewGraph(vg.names, vg.edges, R_rel, H=vg.H, inliers=vg.inliers), out
