"""pipeline.synthetic.graphs: the three protocols, their noise models and determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.synthetic.graphs import SyntheticGraph, knn_graph, paper1_graph, paper2_graph


def _residuals(g: SyntheticGraph) -> np.ndarray:
    """(M, 3) Δω with R̃_ij = exp([Δω]×) R_j R_iᵀ."""
    i, j = g.vg.edges.T
    true_rel = g.R_true[j] @ np.swapaxes(g.R_true[i], 1, 2)
    return so3.log(g.vg.R_rel @ np.swapaxes(true_rel, 1, 2))


@pytest.mark.parametrize(
    "make",
    [lambda s: paper1_graph(40, 0.3, 2.0, 0.1, seed=s), lambda s: paper2_graph(30, 0.2, seed=s), lambda s: knn_graph(200, seed=s)],
)
def test_deterministic_and_seeded(make) -> None:
    a, b, c = make(3), make(3), make(4)
    for x, y in [(a.vg.edges, b.vg.edges), (a.vg.R_rel, b.vg.R_rel), (a.R_true, b.R_true), (a.outlier_mask, b.outlier_mask)]:
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.R_true, c.R_true)
    assert a.vg.is_connected() and a.vg.names[:2] == ["0", "1"]


def test_paper1_protocol() -> None:
    g = paper1_graph(100, 0.5, 5.0, 0.2, seed=0)
    n_pairs = 100 * 99 / 2
    M = g.vg.n_edges
    assert abs(M - 0.5 * n_pairs) < 5 * math.sqrt(n_pairs * 0.25)  # binomial, 5σ
    assert g.vg.H is None
    assert g.outlier_mask.sum() == round(0.2 * M)
    r = _residuals(g)
    inl = r[~g.outlier_mask]
    # Per-axis Gaussian of σ = 5°: each axis has that standard deviation, no correlation.
    np.testing.assert_allclose(np.degrees(inl.std(axis=0)), 5.0, rtol=0.06)
    assert np.abs(np.corrcoef(inl.T) - np.eye(3)).max() < 0.07
    # Outliers are Haar-random: their errors spread up to 180° (mean ≈ 126°).
    out_deg = np.degrees(np.linalg.norm(r[g.outlier_mask], axis=1))
    assert 110 < out_deg.mean() < 140


def test_paper1_noise_free() -> None:
    g = paper1_graph(20, 0.4, 0.0, seed=1)
    assert np.abs(_residuals(g)).max() < 1e-12 and not g.outlier_mask.any()


def test_paper2_protocol() -> None:
    n, p = 60, 0.3
    g = paper2_graph(n, p, eig_range=(10.0, 100.0), seed=2)
    assert g.vg.n_edges == max(n - 1, math.ceil(p * n * (n - 1) / 2))
    assert np.all(g.vg.degrees() > 0)
    lam = np.linalg.eigvalsh(g.vg.H)
    assert lam.min() >= 10.0 - 1e-9 and lam.max() <= 100.0 + 1e-9
    # Δω ~ N(0, H⁻¹) on the left: the NEES Δωᵀ H Δω averages 3 (chi-square, 3 dof).
    r = _residuals(g)
    nees = np.einsum("na,nab,nb->n", r, g.vg.H, r)
    assert abs(nees.mean() - 3.0) < 5 * math.sqrt(6 / nees.size)
    # Whitened residuals are isotropic (the NEES above is what tells a right-perturbation generator: its mean is
    # off 3 on these anisotropic H).
    L = np.linalg.cholesky(g.vg.H)
    z = np.einsum("nba,nb->na", L, r)
    np.testing.assert_allclose(np.cov(z.T), np.eye(3), atol=0.15)


def test_paper2_sparse_graph_has_min_edges_and_every_camera() -> None:
    g = paper2_graph(25, 0.01, eig_range=(1.0, 10.0), seed=3)  # K_obs = N − 1: a spanning tree
    assert g.vg.n_edges == 24 and g.vg.is_connected()


def test_paper2_literal_protocol_without_connectivity() -> None:
    # connected=False: only "every camera has an edge" (the wording); may be disconnected.
    graphs = [paper2_graph(10, 0.1, seed=s, connected=False) for s in range(20)]
    assert all(g.vg.n_edges == 9 and g.vg.degrees().min() >= 1 for g in graphs)
    assert not all(g.vg.is_connected() for g in graphs)


def test_random_spanning_tree_is_uniform() -> None:
    from collections import Counter

    from pipeline.synthetic.graphs import _random_tree

    rng = np.random.default_rng(0)
    counts = Counter(tuple(map(tuple, _random_tree(4, rng))) for _ in range(8000))
    assert len(counts) == 16  # Cayley: 4^(4−2) labelled trees
    assert max(counts.values()) < 1.25 * 500 and min(counts.values()) > 0.75 * 500


def test_knn_protocol_degree_and_noise() -> None:
    g = knn_graph(2000, k=12, sigma_deg=2.0, outlier_frac=0.15, seed=4)
    deg = g.vg.degrees()
    assert deg.min() >= 12 and 13.0 < deg.mean() < 15.0  # mean degree ≈ 14
    assert g.outlier_mask.sum() == round(0.15 * g.vg.n_edges)
    inl = _residuals(g)[~g.outlier_mask]
    np.testing.assert_allclose(np.degrees(inl.std(axis=0)), 2.0, rtol=0.05)


@pytest.mark.slow
def test_knn_scale_10000() -> None:
    g = knn_graph(10_000, seed=5)  # its time is a benchmark's business, not a test's (no wall-clock asserts)
    assert g.vg.n_cameras == 10_000 and g.vg.is_connected()


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: paper1_graph(1, 0.5, 1.0), r"n=1 but expected an integer >= 2"),
        (lambda: paper1_graph(10, 0.0, 1.0), r"p=0.0 but expected a fraction"),
        (lambda: paper1_graph(10, 0.5, -1.0), r"sigma_deg=-1.0 but expected"),
        (lambda: paper1_graph(10, 0.5, 1.0, outlier_frac=1.5), r"outlier_frac=1.5"),
        (lambda: paper2_graph(10, 0.5, eig_range=(0.0, 1.0)), r"eig_range=\(0.0, 1.0\) but expected 0 < low"),
        (lambda: knn_graph(10, k=10), r"k=10 but expected an integer in \[1, n−1\]"),
    ],
)
def test_bad_arguments(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()
