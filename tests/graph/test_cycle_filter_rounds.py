"""pipeline.graph.loops.cycle_filter: its greedy rounds (cycle owners kept up to date, counts updated as edges go)
give exactly what the rounds' definition gives, written here on its own: every round recounts the live cycles
through each edge from scratch, finds each inconsistent cycle's owner by sorting its edges' bad fractions, and drops
the first candidate (by bad fraction, then bad count, then index) that owns one. Only the set-up before the rounds
(the cycles, their angles and verdicts: ``CycleRounds.start``) is shared with the code under test."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.graph.loops import CycleRounds, cycle_filter

FIELDS = ("kept", "n_cycles", "n_bad", "confirmed", "alive")  # what the rounds decide (the rest is set up before them)


def _recount(cyc_edges, live, bad, M):
    """Live cycles and live inconsistent cycles through each edge, counted from scratch."""
    e = cyc_edges[live]
    valid = e >= 0
    n_c = np.bincount(e[valid], minlength=M)
    n_b = np.bincount(e[valid & bad[live][:, None]], minlength=M)
    return n_c, n_b


def _reference(edges, R_rel, n_cameras, sigma_deg, *, max_len=4, k_sigma=3.0, min_deg=1.0, max_deg=10.0,
               max_bad_fraction=0.5, min_cycles=1, calibrate=True, active=None, max_four_cycles=2_000_000):
    """The rounds by their definition (module docstring), one edge per round, nothing carried between rounds but
    which edges and cycles are gone."""
    st = CycleRounds.start(edges, R_rel, n_cameras, sigma_deg, max_len=max_len, k_sigma=k_sigma, min_deg=min_deg,
                           max_deg=max_deg, calibrate=calibrate, active=active, max_four_cycles=max_four_cycles)
    cyc_edges, bad = st.cycles.edges, ~st.consistent
    kept = st.kept.copy()
    M = len(kept)
    live = np.ones(len(cyc_edges), bool)
    n_c, n_b = _recount(cyc_edges, live, bad, M)
    n_cycles, n_bad = n_c.copy(), n_b.copy()
    removed = []
    while True:
        n_c, n_b = _recount(cyc_edges, live, bad, M)
        frac = np.where(n_c > 0, n_b / np.maximum(n_c, 1), 0.0)
        fpad = np.append(frac, -1.0)  # a triangle's fourth slot never tops a cycle
        padded = np.where(cyc_edges >= 0, cyc_edges, M)
        F = fpad[padded]
        order = np.argsort(-F, axis=1, kind="stable")
        top = np.take_along_axis(F, order[:, :2], axis=1)
        owner = np.where(top[:, 0] > top[:, 1], np.take_along_axis(padded, order[:, :1], axis=1)[:, 0], -1)
        owned = set(owner[live & bad & (owner >= 0)].tolist())
        cand = [e for e in range(M) if kept[e] and n_c[e] >= min_cycles and frac[e] > max_bad_fraction]
        cand.sort(key=lambda e: (-frac[e], -n_b[e], e))
        best = next((e for e in cand if e in owned), -1)
        if best < 0:
            break
        n_cycles[best], n_bad[best] = n_c[best], n_b[best]
        kept[best] = False
        removed.append(best)
        live &= ~np.any(cyc_edges == best, axis=1)
    n_c, n_b = _recount(cyc_edges, live, bad, M)
    n_cycles[kept], n_bad[kept] = n_c[kept], n_b[kept]
    confirmed = np.zeros(M, bool)
    good = cyc_edges[live & ~bad]
    confirmed[good[good >= 0]] = True
    return dict(kept=kept, removed=removed, n_cycles=n_cycles, n_bad=n_bad, confirmed=confirmed & kept, alive=live)


def _random_graph(rng, n, p, n_out, noise_deg=1.0):
    R = so3.random_rotations(n, rng)
    E = np.stack(np.triu_indices(n, 1), 1)
    E = E[rng.random(len(E)) < p]
    Rm = so3.exp(np.deg2rad(noise_deg) * rng.standard_normal((len(E), 3))) @ (R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2))
    out = rng.choice(len(E), min(n_out, len(E)), replace=False)
    Rm[out] = so3.random_rotations(len(out), rng)
    return E, Rm


def _same(E, Rm, n, sigma, **kw):
    got, want = cycle_filter(E, Rm, n, sigma, **kw), _reference(E, Rm, n, sigma, **kw)
    assert got.removed == want["removed"]
    for f in FIELDS:
        assert np.array_equal(getattr(got, f), want[f]), f
    return got


@pytest.mark.parametrize("seed", range(12))
def test_random_graphs_give_the_reference_removals(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(6, 40))
    E, Rm = _random_graph(rng, n, rng.uniform(0.2, 0.9), int(rng.integers(0, 60)))
    # equal σ: many equal fractions, so ties (a cycle without a strict owner, equal priorities) are common
    sigma = np.full(len(E), 0.5) if seed % 2 else rng.uniform(0.2, 1.5, len(E))
    kw = dict(max_len=3 if seed % 3 == 0 else 4, min_cycles=1 + seed % 3, calibrate=seed % 4 != 1,
              max_deg=None if seed % 5 == 0 else 10.0,
              active=rng.random(len(E)) < 0.9 if seed % 4 == 2 else None)
    res = _same(E, Rm, n, sigma, **kw)
    if seed in (1, 3, 5):
        assert res.removed, "the case must exercise the rounds"


def test_many_removals_with_ties():
    rng = np.random.default_rng(7)
    E, Rm = _random_graph(rng, 30, 0.7, 120)
    res = _same(E, Rm, 30, np.full(len(E), 0.5))
    assert len(res.removed) > 30


@pytest.mark.parametrize("case", ["empty", "one edge", "one triangle", "bad triangle", "duplicates"])
def test_edge_cases(case):
    rng = np.random.default_rng(3)
    R = so3.random_rotations(5, rng)
    if case == "empty":
        E = np.zeros((0, 2), np.int64)
    elif case == "one edge":
        E = np.array([[0, 1]])
    elif case in ("one triangle", "bad triangle"):
        E = np.array([[0, 1], [0, 2], [1, 2]])
    else:  # the same pair measured twice, in two triangles that share it
        E = np.array([[0, 1], [0, 1], [0, 2], [1, 2], [1, 3], [0, 3], [2, 3], [1, 2]])
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    if case in ("bad triangle", "duplicates"):
        Rm[:1] = so3.random_rotations(1, rng)
    _same(E, Rm, 5, np.full(len(E), 0.5))
