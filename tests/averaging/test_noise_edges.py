"""The residual model is fitted to the edges that can have a residual: a bridge (an edge in no cycle) is fitted
exactly whatever its error, so its zero residual says nothing of the noise (``mixture.noise_edges``)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.averaging import average
from pipeline.averaging.mixture import fit_mixture, noise_edges
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

# a K4 on 0–3 and a triangle on 4–6, joined by the bridge (3, 4); a path 6–7–8 and a pendant 0–9 hang off them
CLUSTERS = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3), (4, 5), (4, 6), (5, 6)]
BRIDGES = [(3, 4), (6, 7), (7, 8), (0, 9)]


def test_noise_edges_are_the_edges_on_a_cycle_with_the_rotations_they_fit():
    edges = np.array(CLUSTERS[:4] + BRIDGES[:2] + CLUSTERS[4:] + BRIDGES[2:])
    mask, n_fit = noise_edges(edges, 10)
    is_bridge = [tuple(e) in BRIDGES for e in edges.tolist()]
    assert mask is not None and mask.tolist() == [not b for b in is_bridge]
    # the 9 cycle edges fit the rotations of two blocks, 3 + 2 = 5 relative rotations: 4 redundant, as the whole
    # graph's 13 − 10 + 1 cycles; the degrees-of-freedom factor's count N − 1 is n_fit − 1
    assert mask.sum() - (n_fit - 1) == len(edges) - 10 + 1 == 4
    assert noise_edges(np.array(CLUSTERS[:6]), 4) == (None, 4)  # no bridge: every edge counts
    assert noise_edges(np.array([(0, 1), (1, 2), (1, 3)]), 4) == (None, 4)  # a tree: nothing to fit


def _sparse_turntable(seed: int, sigma_deg: float) -> tuple[ViewGraph, np.ndarray]:
    """16 cameras: a K4 and a triangle, each camera of the rest joined by one bridge, as a dark turntable's graph
    (10 of 19 edges bridges), every edge with isotropic Gaussian noise of ``sigma_deg`` per axis."""
    rng = np.random.default_rng(seed)
    tree = [(3, 4)] + [(k, k + 1) for k in range(6, 15)]
    edges = np.array(CLUSTERS + tree)
    R = so3.random_rotations(16, rng)
    clean = ViewGraph.from_absolute([f"c{k}" for k in range(16)], R, edges)
    noise = so3.exp(np.deg2rad(sigma_deg) * rng.standard_normal((len(edges), 3)))
    return ViewGraph.from_edges(clean.names, clean.edges, noise @ clean.R_rel), R


@pytest.mark.parametrize("seed", range(4))
def test_bridges_do_not_collapse_the_scale_of_a_sparse_graph(seed):
    """Before, the ten bridges' zero residuals drew s to its floor (1e-12 rad) and the t-weights then called the
    nine cycle edges outliers (weights ≤ 1e-23 of the bridges'), though every edge had the same 0.5° noise."""
    sigma = 0.5
    vg, _ = _sparse_turntable(seed, sigma)
    res = average(vg, "irls")
    model = res.stats["polish_model"]
    # s from 9 residuals with 4 redundant rotations (12 degrees of freedom): within a factor 2 of the noise
    assert 0.5 * sigma < model["s_deg"] < 2.0 * sigma, model
    assert model["n_outliers"] == 0 and res.kept.all()
    # the bridges' weights are the t-weight of a zero residual, not a thousand-fold outlier's
    w = res.weights / np.median(res.weights)
    assert w.min() > 0.1 and w.max() < 10.0, w
    H = np.broadcast_to(np.eye(3) / np.deg2rad(sigma) ** 2, (vg.n_edges, 3, 3)).copy()
    resh = average(vg.with_H(H), "irls-h")
    assert resh.kept.all(), resh.kept
    assert resh.stats["certificate"]["verdict"] == "verified"


def test_a_fit_on_the_cycle_edges_gives_every_edge_its_posterior():
    """``fit``: the model from the chosen edges alone (the same as fitting them by themselves), and every edge's
    inlier posterior under it."""
    rng = np.random.default_rng(3)
    theta = np.deg2rad(0.5) * np.linalg.norm(rng.standard_normal((40, 3)), axis=1)
    theta[:10] = 0.0  # bridges
    fit = np.arange(40) >= 10
    both = fit_mixture(theta ** 2, np.zeros(40), theta, 25, fit=fit)
    alone = fit_mixture(theta[fit] ** 2, np.zeros(30), theta[fit], 25)
    assert (both.nu, both.s, both.eps, both.loglik) == (alone.nu, alone.s, alone.eps, alone.loglik)
    assert both.gamma.shape == (40,) and np.array_equal(both.gamma[fit], alone.gamma)
    assert np.all(both.gamma[:10] > 0.99)  # a zero residual is the model's likeliest inlier
