"""pipeline.graph.loops.cycle_filter: the greedy rounds with cycle owners kept up to date give exactly what the
earlier rounds gave (every candidate re-sorted and re-checked against its cycles each round), kept here as the
definition."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.graph.cycles import expand_rows
from pipeline.graph.loops import CycleRounds, _fraction, _owners, cycle_filter

FIELDS = ("kept", "n_cycles", "n_bad", "confirmed", "alive")  # what the rounds decide (the rest is set up before them)


def _first_blamed_ref(order, bptr, bthrough, padded, alive, frac, batch=16):
    start = 0
    while start < len(order):
        cand = order[start:start + batch]
        who, pos = expand_rows(bptr, cand)
        cycles = bthrough[pos]
        live = alive[cycles]
        who, cycles = who[live], cycles[live]
        owned = _owners(padded[cycles], frac) == cand[who]
        hits = np.flatnonzero(np.bincount(who[owned], minlength=len(cand)))
        if hits.size:
            return int(cand[hits[0]])
        start += batch
        batch *= 2
    return -1


def _reference(edges, R_rel, n_cameras, sigma_deg, *, max_len=4, k_sigma=3.0, min_deg=1.0, max_deg=10.0,
               max_bad_fraction=0.5, min_cycles=1, calibrate=True, active=None, max_four_cycles=2_000_000):
    """The filter's rounds before the owners were kept: each round sorts every candidate and checks them in order."""
    st = CycleRounds.start(edges, R_rel, n_cameras, sigma_deg, max_len=max_len, k_sigma=k_sigma, min_deg=min_deg,
                           max_deg=max_deg, calibrate=calibrate, active=active, max_four_cycles=max_four_cycles)
    alive, n_c, n_b, kept = st.alive, st.n_c, st.n_b, st.kept
    M = len(kept)
    _, bptr, bthrough, padded = st.inconsistent()
    frac = np.append(_fraction(n_b, n_c), -1.0)
    while True:
        c = np.flatnonzero(kept & (n_c >= min_cycles) & (frac[:M] > max_bad_fraction))
        best = _first_blamed_ref(c[np.lexsort((-n_b[c], -frac[c]))], bptr, bthrough, padded, alive, frac)
        if best < 0:
            break
        _, changed = st.drop(best)
        frac[changed] = _fraction(n_b[changed], n_c[changed])
    r = st.result()
    return dict(kept=r.kept, removed=r.removed, n_cycles=r.n_cycles, n_bad=r.n_bad, kappa2=r.kappa2,
                confirmed=r.confirmed, consistent=r.consistent, alive=r.alive, angles=r.angles,
                confirm_deg=r.confirm_deg)


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
