"""The residual model is fitted to the edges that can have a residual: a bridge (an edge in no cycle) is fitted
exactly whatever its error, so its zero residual says nothing of the noise (``mixture.noise_edges``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.averaging import average
from pipeline.averaging.mixture import em_update, fit_mixture, log_haar, mixture_terms, noise_edges
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph
from pipeline.graph.flags import bridges

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


def _residuals():
    rng = np.random.default_rng(4)
    theta = np.deg2rad(0.5) * np.linalg.norm(rng.standard_normal((40, 3)), axis=1)
    theta[:10] = np.deg2rad([0, 0, 0.1, 0.3, 1, 2, 5, 20, 60, 120])  # the 'bridges' mid-iteration: any residual
    return theta, np.arange(40) >= 10, np.zeros(40)


def test_fit_mixture_gives_the_other_edges_their_posterior_at_the_fitted_model():
    theta, fit, hl = _residuals()
    both = fit_mixture(theta ** 2, hl, theta, 25, fit=fit)
    g = mixture_terms(theta[~fit] ** 2, hl[~fit], log_haar(theta[~fit]), both.s, both.nu, both.eps)[1]
    np.testing.assert_allclose(both.gamma[~fit], g, rtol=1e-12)
    assert both.gamma[9] < 0.5  # the 120° one is an outlier


@pytest.mark.parametrize("inner", [1, 10])
def test_em_update_with_fit_is_the_update_of_the_fitted_edges(inner):
    theta, fit, hl = _residuals()
    m0 = fit_mixture(theta[fit] ** 2, hl[fit], theta[fit], 25)
    w, m = em_update(theta ** 2, hl, theta, m0, 25, inner=inner, fit=fit)
    ws, ms = em_update(theta[fit] ** 2, hl[fit], theta[fit], m0, 25, inner=inner)
    assert (m.nu, m.s, m.eps, m.loglik) == (ms.nu, ms.s, ms.eps, ms.loglik)
    np.testing.assert_array_equal(w[fit], ws)
    np.testing.assert_array_equal(m.gamma[fit], ms.gamma)
    if inner == 1:  # no inner EM: the step's (s, ε) are m0's, and the other edges' weights are theirs
        _, g, u = mixture_terms(theta[~fit] ** 2, hl[~fit], log_haar(theta[~fit]), m0.s, m0.nu, m0.eps)
        np.testing.assert_allclose(w[~fit], g * u / m0.s ** 2, rtol=1e-12)
        np.testing.assert_allclose(m.gamma[~fit], g, rtol=1e-12)


def test_noise_edges_counts_the_cycle_rank_of_a_disconnected_graph():
    # CLUSTERS + BRIDGES without (3, 4): K4 + pendant 9, and triangle + path 6-7-8; plus an isolated camera 10
    edges = np.array(CLUSTERS + [b for b in BRIDGES if b != (3, 4)])
    mask, n_fit = noise_edges(edges, 11)
    assert mask.tolist() == (~bridges(edges, 11)).tolist()
    assert mask.sum() - (n_fit - 1) == 3 + 1  # K4's 3 cycles and the triangle's 1: M − N + c = 12 − 11 + 3


@pytest.mark.parametrize("seed", range(2))
def test_the_trusted_polish_and_its_final_refit_fit_the_cycles_only(seed):
    vg, _ = _sparse_turntable(seed, 0.5)
    vg = dataclasses.replace(vg, inliers=np.random.default_rng(seed).integers(50, 500, vg.n_edges))
    model = average(vg, "irls", trust_inliers=True).stats["polish_model"]
    assert set(model["loglik"]) == {"iso", "inliers"}
    assert 0.25 < model["s_deg"] < 1.0, model


def test_the_metric_race_ignores_the_bridges_precisions():
    """A bridge's precision cancels: scaling the bridges' H changes no candidate's likelihood."""
    vg, _ = _sparse_turntable(0, 0.5)
    br = bridges(vg.edges, vg.n_cameras)
    out = []
    for scale in (1.0, 100.0):
        H = np.broadcast_to(np.eye(3) / np.deg2rad(0.5) ** 2, (vg.n_edges, 3, 3)).copy()
        H[br] *= scale
        out.append({k: v["loglik"] for k, v in average(vg.with_H(H), "irls-h").stats["candidates"].items()})
    assert out[0].keys() == out[1].keys()
    for k in out[0]:
        assert out[0][k] == pytest.approx(out[1][k], abs=1e-6), (k, out)


def test_a_fit_that_selects_no_edge_is_refused():
    theta = np.full(5, 0.01)
    with pytest.raises(ValueError, match="selects no edge"):
        fit_mixture(theta ** 2, np.zeros(5), theta, 3, fit=np.zeros(5, bool))
    model = fit_mixture(theta ** 2, np.zeros(5), theta, 3)
    with pytest.raises(ValueError, match="selects no edge"):
        em_update(theta ** 2, np.zeros(5), theta, model, 3, fit=np.zeros(5, bool))
