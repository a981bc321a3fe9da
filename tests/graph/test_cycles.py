"""pipeline.graph.cycles and bridges: every triangle and 4-cycle once, against brute force; rotations close."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from pipeline.core import so3
from pipeline.graph.cycles import EdgeIndex, cycle_angles, edge_cycles, find_cycles, find_triangles
from pipeline.graph.flags import bridges


def _random_graph(rng, n, p):
    E = np.stack(np.triu_indices(n, 1), 1)
    return E[rng.random(len(E)) < p]


def _brute_cycles(E, act, n):
    S = {tuple(e) for e, a in zip(E.tolist(), act) if a}
    tri = {frozenset(c) for c in itertools.combinations(range(n), 3)
           if all(tuple(sorted(p)) in S for p in itertools.combinations(c, 2))}
    four = set()
    for a, b, c, d in itertools.permutations(range(n), 4):
        ring = ((a, b), (b, c), (c, d), (d, a))
        if a == min(a, b, c, d) and b < d and all(tuple(sorted(p)) in S for p in ring):
            four.add(frozenset(tuple(sorted(p)) for p in ring))
    return tri, four


@pytest.mark.parametrize("seed", range(6))
def test_short_cycles_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 14
    E = _random_graph(rng, n, 0.35)
    act = rng.random(len(E)) < 0.9
    tri, four = _brute_cycles(E, act, n)
    cyc = find_cycles(E, n, act, 4)
    t, q = cyc.length == 3, cyc.length == 4
    got_t = [frozenset(E[row[:3]].ravel().tolist()) for row in cyc.edges[t]]
    got_q = [frozenset(tuple(E[e]) for e in row) for row in cyc.edges[q]]
    assert len(got_t) == len(set(got_t)) and set(got_t) == tri  # each once
    assert len(got_q) == len(set(got_q)) and set(got_q) == four
    assert act[cyc.edges[cyc.edges >= 0]].all()
    # every walk closes: each edge starts where the previous one ended
    for row, fwd, L in zip(cyc.edges, cyc.forward, cyc.length):
        start = [E[e, 0] if f else E[e, 1] for e, f in zip(row[:L], fwd[:L])]
        end = [E[e, 1] if f else E[e, 0] for e, f in zip(row[:L], fwd[:L])]
        assert all(end[s] == start[(s + 1) % L] for s in range(L))
    assert len(find_triangles(E, n, act)) == len(tri) and (find_cycles(E, n, act, 3).length == 3).all()


def test_exact_rotations_compose_to_identity_and_a_bad_edge_shows():
    rng = np.random.default_rng(1)
    n = 12
    E = _random_graph(rng, n, 0.5)
    R = so3.random_rotations(n, rng)
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    cyc = find_cycles(E, n)
    assert cycle_angles(Rm, cyc).max() < 1e-6
    Rm[3] = so3.exp(np.deg2rad([0, 0, 7.0])) @ Rm[3]
    ang = cycle_angles(Rm, cyc)
    through = np.isin(np.arange(len(cyc)), edge_cycles(cyc, len(E))[1][slice(*edge_cycles(cyc, len(E))[0][3:5])])
    assert np.allclose(ang[through], 7.0, atol=1e-6) and ang[~through].max() < 1e-6


def test_edge_index_and_a_large_sparse_graph():
    # a ring of 3000 cameras, each paired with its 4 successors: no (N, N) array is formed
    n = 3000
    a = np.repeat(np.arange(n), 4)
    b = (a + np.tile(np.arange(1, 5), n)) % n
    E = np.unique(np.sort(np.stack([a, b], 1), axis=1), axis=0)
    idx = EdgeIndex(E, n)
    np.testing.assert_array_equal(idx.lookup(E[:, 1], E[:, 0]), np.arange(len(E)))
    assert idx.lookup(np.array([0]), np.array([10]))[0] == -1
    cyc = find_cycles(E, n)
    assert (cyc.length == 3).sum() == 6 * n  # {i, i+a, i+a+b} with a + b <= 4: 6 per start
    assert (cyc.length == 4).sum() > 0


def test_4_cycles_stay_within_their_budget():
    rng = np.random.default_rng(3)
    n = 30
    E = _random_graph(rng, n, 0.5)
    full = find_cycles(E, n)
    n4 = int((full.length == 4).sum())
    capped = find_cycles(E, n, max_four_cycles=n4 // 10)
    q = capped.length == 4
    assert 0 < q.sum() <= n4 // 10 and (capped.length == 3).sum() == (full.length == 3).sum()
    whole = {frozenset(r.tolist()) for r in full.edges[full.length == 4]}
    assert {frozenset(r.tolist()) for r in capped.edges[q]} <= whole  # a subset of the true 4-cycles


@pytest.mark.parametrize("seed", range(5))
def test_bridges_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    for _ in range(30):
        n = int(rng.integers(2, 22))
        E = _random_graph(rng, n, rng.uniform(0.05, 0.35))
        if not len(E):
            continue
        act = rng.random(len(E)) < 0.9

        def n_comp(mask):
            e = E[mask]
            return connected_components(sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                        directed=False)[0]

        base = n_comp(act)
        want = np.zeros(len(E), bool)
        for k in np.flatnonzero(act):
            m = act.copy()
            m[k] = False
            want[k] = n_comp(m) > base
        np.testing.assert_array_equal(bridges(E, n, act), want)
