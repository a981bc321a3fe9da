"""Weiszfeld ℓ1 averaging baseline (Hartley et al. 2011)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.averaging.weiszfeld import independent_sets, weiszfeld
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph
from pipeline.averaging.init import initial_rotations


def _graph(n, p, sigma_deg, seed):
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    iu = np.array(np.triu_indices(n, 1)).T
    e = iu[(rng.random(len(iu)) < p) | ((iu[:, 1] - iu[:, 0]) == 1)]
    vg = ViewGraph.from_absolute([str(i) for i in range(n)], R, e)
    Rrel = so3.exp(np.deg2rad(sigma_deg) * rng.standard_normal((vg.n_edges, 3))) @ vg.R_rel
    return ViewGraph(vg.names, vg.edges, Rrel), R


def _err(R_est, R):
    G = so3.chordal_mean(np.swapaxes(R, 1, 2) @ R_est)
    return np.rad2deg(so3.angle_between(R_est, R @ G))


def test_independent_sets_partition_without_internal_edges():
    vg, _ = _graph(40, 0.3, 0.0, 0)
    sets = independent_sets(vg)
    allc = np.sort(np.concatenate(sets))
    np.testing.assert_array_equal(allc, np.arange(40))
    label = np.empty(40, int)
    for k, s in enumerate(sets):
        label[s] = k
    assert np.all(label[vg.edges[:, 0]] != label[vg.edges[:, 1]])


def test_recovers_noise_free_from_perturbed_start():
    vg, R = _graph(15, 0.6, 0.0, 1)
    rng = np.random.default_rng(2)
    R0 = R @ so3.exp(np.deg2rad(5) * rng.standard_normal((15, 3)))
    res = weiszfeld(vg, init=R0, tol_rad=1e-9, max_iterations=2000)
    assert _err(res.R, R).max() < 1e-3
    assert res.stats["converged"]


def test_moves_off_a_data_point():
    """After a spanning-tree init each camera sits on one neighbour's estimate; it must still move."""
    vg, R = _graph(20, 0.5, 2.0, 3)
    res = weiszfeld(vg, init="mst")
    assert res.history[0]["max_step_rad"] > 1e-3
    assert np.median(_err(res.R, R)) < 2.0


def test_sequential_order_option():
    vg, R = _graph(8, 0.8, 1.0, 4)
    res = weiszfeld(vg, order=np.arange(8)[::-1])
    assert res.stats["n_independent_sets"] == 8
    # well below its spanning-tree start (1.6° median, 2.2° worst here): the sweeps in this order moved the cameras
    start = initial_rotations(vg, "mst")
    assert np.median(_err(res.R, R)) < 0.6 * np.median(_err(start, R)) and np.median(_err(res.R, R)) < 1.0


def test_disconnected_rejected():
    vg = ViewGraph.from_absolute(list("abcd"), so3.random_rotations(4, np.random.default_rng(0)), [[0, 1], [2, 3]])
    with pytest.raises(ViewGraphError, match="not connected"):
        weiszfeld(vg)
