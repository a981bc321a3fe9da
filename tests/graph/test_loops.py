"""pipeline.graph.loops: wrong edges found by the cycles they break, long cycles, co-location claims."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.graph.cycles import find_triangles
from pipeline.graph.loops import colocation_check, cycle_check, cycle_filter, group_median


def _graph(n=25, p=0.5, noise_deg=0.5, seed=0, n_out=0):
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    E = np.stack(np.triu_indices(n, 1), 1)
    E = E[rng.random(len(E)) < p]
    Rm = so3.exp(np.deg2rad(noise_deg) * rng.standard_normal((len(E), 3))) @ (R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2))
    out = rng.choice(len(E), n_out, replace=False)
    Rm[out] = so3.random_rotations(n_out, rng)
    return R, E, Rm, out


@pytest.mark.parametrize("max_len", [3, 4])
def test_outliers_are_removed_and_few_inliers_lost(max_len):
    _, E, Rm, out = _graph(n_out=15, seed=1)
    res = cycle_filter(E, Rm, 25, np.full(len(E), 0.5), max_len=max_len)
    assert set(out.tolist()) <= set(res.removed)
    assert len(set(res.removed) - set(out.tolist())) <= 0.02 * len(E)
    assert res.confirmed[res.kept].mean() > 0.95 and not res.confirmed[~res.kept].any()


def _greedy_by_definition(res, E: np.ndarray, max_bad_fraction: float = 0.5) -> list[int]:
    """The greedy removal as the module docstring defines it, recounting every edge's blame over every live
    inconsistent cycle each round (quadratic; the reference for the filter's batched search)."""
    M, edges, ok = len(E), res.cycles.edges, res.consistent
    alive, kept, removed = np.ones(len(edges), bool), np.ones(M, bool), []
    while True:
        live = edges[alive]
        valid = live >= 0
        n_c = np.bincount(live[valid], minlength=M)
        n_b = np.bincount(live[valid & ~ok[alive][:, None]], minlength=M)
        frac = np.where(n_c > 0, n_b / np.maximum(n_c, 1), 0.0)
        blame = np.zeros(M, int)
        for cycle in edges[alive & ~ok]:
            es = cycle[cycle >= 0]
            f = frac[es]
            if np.sum(f == f.max()) == 1:
                blame[es[np.argmax(f)]] += 1
        cand = np.flatnonzero(kept & (n_c >= 1) & (frac > max_bad_fraction) & (blame >= 1))
        if not cand.size:
            return removed
        best = int(cand[np.lexsort((-n_b[cand], -frac[cand]))[0]])
        kept[best] = False
        removed.append(best)
        alive &= ~np.any(edges == best, axis=1)


@pytest.mark.parametrize("seed,n_out,max_len", [(1, 15, 3), (1, 15, 4), (2, 40, 4), (3, 80, 4)])
def test_the_greedy_removal_is_the_one_its_definition_gives(seed, n_out, max_len):
    _, E, Rm, _ = _graph(n=20, p=0.6, seed=seed, n_out=n_out)
    sigma = np.random.default_rng(seed).uniform(0.3, 1.0, len(E))  # ties in the fractions are rare, not absent
    res = cycle_filter(E, Rm, 20, sigma, max_len=max_len)
    assert len(res.removed) >= n_out // 2
    assert res.removed == _greedy_by_definition(res, E)


def test_calibration_absorbs_a_common_overconfidence():
    # σ given 4x too small: κ² ≈ 16 is estimated, and nothing good is removed
    _, E, Rm, _ = _graph(noise_deg=2.0, seed=2)
    res = cycle_filter(E, Rm, 25, np.full(len(E), 0.5), max_deg=None)
    assert 8 < res.kappa2 < 30 and len(res.removed) <= 0.02 * len(E)
    res = cycle_filter(E, Rm, 25, np.full(len(E), 0.5), max_deg=None, calibrate=False)
    assert len(res.removed) > 0.1 * len(E)


def test_a_lone_bad_triangle_blames_nobody():
    R = so3.random_rotations(3, np.random.default_rng(0))
    E = np.array([[0, 1], [1, 2], [0, 2]])
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    Rm[2] = so3.exp(np.deg2rad([0, 20.0, 0])) @ Rm[2]
    res = cycle_filter(E, Rm, 3, np.full(3, 0.5))
    assert res.kept.all() and not res.confirmed.any() and res.n_bad.tolist() == [1, 1, 1]


def test_ring_without_triangles_uses_4_cycles():
    rng = np.random.default_rng(4)
    n = 16
    R = so3.random_rotations(n, rng)
    E = np.array(sorted({tuple(sorted((k, (k + s) % n))) for k in range(n) for s in (1, 3)}))
    Rm = so3.exp(np.deg2rad(0.3) * rng.standard_normal((len(E), 3))) @ (R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2))
    bad = rng.choice(len(E), 3, replace=False)
    Rm[bad] = so3.exp(np.deg2rad(40.0) * np.array([0, 0, 1.0])) @ Rm[bad]
    assert len(find_triangles(E, n)) == 0
    assert set(cycle_filter(E, Rm, n, np.full(len(E), 0.5)).removed) == set(bad.tolist())
    assert not cycle_filter(E, Rm, n, np.full(len(E), 0.5), max_len=3).removed  # triangles alone see nothing


def test_cycle_check_on_a_ring():
    # a 12-camera ring, no short cycle: one edge 20° off breaks the long cycle of every edge
    rng = np.random.default_rng(2)
    n = 12
    R = so3.random_rotations(n, rng)
    E = np.array([[k, k + 1] for k in range(n - 1)] + [[0, n - 1]])
    Rm = so3.exp(np.deg2rad(0.5) * rng.standard_normal((n, 3))) @ (R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2))
    Rm[4] = so3.exp(np.deg2rad([0, 0, 20.0])) @ Rm[4]
    kept, none = np.ones(n, bool), np.zeros(n, bool)
    pc = cycle_check(E, Rm, n, kept, kept, np.full(n, 1.0), none)
    assert pc.checked.all() and (pc.path_length == n - 1).all() and not pc.consistent.any()
    assert not pc.path_confirmed.any()  # no confirmed path: the edges may not be rejected on it
    Rm[4] = R[E[4, 1]] @ R[E[4, 0]].T
    pc = cycle_check(E, Rm, n, kept, kept, np.full(n, 1.0), none)
    assert pc.consistent.all() and pc.discrepancy_deg.max() < 3 * np.sqrt(12)
    # a path whose threshold would exceed max_path_deg checks nothing
    assert not cycle_check(E, Rm, n, kept, kept, np.full(n, 5.0), none, max_path_deg=15).checked.any()


def test_the_loop_thresholds_are_k_sigma_of_the_loops_own_variance():
    """Both checks' thresholds pinned, on noise-free rotations with one edge turned by a share of its threshold:
    the path check's 3·√(σ_e² + Σ_path σ²) on a 12-camera ring (3·√12 ≈ 10.4° at σ = 1°), the cycle filter's
    3·√(Σ_cycle σ²) on a triangle (3·√3 ≈ 5.2°, uncalibrated); 0.8 of it passes, 1.3 of it does not."""
    rng = np.random.default_rng(4)
    n = 12
    R = so3.random_rotations(n, rng)
    E = np.array([[k, k + 1] for k in range(n - 1)] + [[0, n - 1]])
    exact = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    kept, none, sigma = np.ones(n, bool), np.zeros(n, bool), np.full(n, 1.0)
    thr = 3 * np.sqrt(12.0)
    for share, ok in ((0.8, True), (1.3, False)):
        Rm = exact.copy()
        Rm[4] = so3.exp(np.deg2rad([0, share * thr, 0])) @ Rm[4]
        pc = cycle_check(E, Rm, n, kept, kept, sigma, none, max_path_deg=20.0)
        np.testing.assert_allclose(pc.threshold_deg, thr, rtol=1e-9)
        np.testing.assert_allclose(pc.discrepancy_deg, share * thr, rtol=1e-6)
        assert pc.checked.all() and (pc.consistent == ok).all(), (share, pc.discrepancy_deg)
    T = np.array([[0, 1], [0, 2], [1, 2]])
    exact = R[T[:, 1]] @ np.swapaxes(R[T[:, 0]], 1, 2)
    thr = 3 * np.sqrt(3.0)
    for share, ok in ((0.8, True), (1.3, False)):
        Rm = exact.copy()
        Rm[0] = so3.exp(np.deg2rad([share * thr, 0, 0])) @ Rm[0]
        res = cycle_filter(T, Rm, 3, np.full(3, 1.0), calibrate=False, max_deg=None)
        np.testing.assert_allclose(res.angles, share * thr, rtol=1e-6)
        assert res.consistent.tolist() == [ok], (share, res.angles)


def test_cycle_check_prefers_confirmed_paths():
    # edge (0, 3) is 30° off; 0-1-2-3 is a chain of confirmed edges, 0-4-3 a cheaper unconfirmed detour
    rng = np.random.default_rng(5)
    R = so3.random_rotations(5, rng)
    E = np.array([[0, 1], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4]])
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    Rm[1] = so3.exp(np.deg2rad([30.0, 0, 0])) @ Rm[1]
    conf = np.array([True, False, False, True, True, False])
    sig = np.array([1.0, 1.0, 0.1, 1.0, 1.0, 0.1])
    pc = cycle_check(E, Rm, 5, np.ones(6, bool), ~conf, sig, conf)
    assert pc.path_length[1] == 3 and pc.path_confirmed[1] and not pc.consistent[1]
    assert pc.checked[[2, 5]].all() and not pc.path_confirmed[[2, 5]].any()  # their paths use edge (0, 3)


def _circle(n=6):
    ang = np.arange(n) * 2 * np.pi / n
    C = np.stack([5 * np.cos(ang), 5 * np.sin(ang), np.zeros(n)], 1)
    R = []
    for c in C:
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R.append(np.stack([x, np.cross(z, x), z]))
    return C, np.array(R)


def _translations(R, C, E):
    tv = -np.einsum("nij,nj->ni", R, C)
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    T = tv[E[:, 1]] - np.einsum("mij,mj->mi", Rm, tv[E[:, 0]])
    nrm = np.linalg.norm(T, axis=1, keepdims=True)
    return Rm, np.where(nrm > 1e-9, T / np.maximum(nrm, 1e-12), 0.0)


def test_colocation_claims_are_tested_by_third_cameras():
    C, R = _circle()
    E = np.stack(np.triu_indices(6, 1), 1)
    Rm, T = _translations(R, C, E)
    ro, every = np.zeros(len(E), bool), np.ones(len(E), bool)
    n_w, med, rej = colocation_check(E, Rm, T, ro, every, 6)
    assert not rej.any() and np.isnan(med).all()  # nothing claims a shared centre
    k = [tuple(e) for e in E.tolist()].index((0, 2))
    T[k], ro[k] = 0, True  # a wrong claim: 0 and 2 stand at one place
    n_w, med, rej = colocation_check(E, Rm, T, ro, every, 6)
    assert n_w[k] >= 4 and rej[k] and med[k] > 30 and rej.sum() == 1
    C2 = C.copy()
    C2[2] = C[0]  # the claim is true
    Rm, T2 = _translations(R, C2, E)
    n_w, med, rej = colocation_check(E, Rm, T2, ro, every, 6)
    assert not rej[k] and med[k] < 1e-6


def test_a_view_of_the_same_pan_is_no_witness():
    # a pan on the spot: cameras 0, 1, 2 within 5 cm of one place, 12 m from the wall they look at; camera 3 is
    # 4 m away. The claim (1, 2) is true at the scale of the scene, but camera 0, 5 cm from both, sees their centres
    # in unrelated directions: only a witness with a real baseline (camera 3) may judge it
    rng = np.random.default_rng(4)
    C = np.r_[rng.normal(0, 0.05, (3, 3)), [[4.0, 0, 0]]]
    R = so3.random_rotations(4, rng)
    E = np.array([[0, 1], [0, 2], [1, 2], [0, 3], [1, 3], [2, 3]])
    Rm, T = _translations(R, C, E)
    ro = np.zeros(len(E), bool)
    ro[2], T[2] = True, 0
    n_w, med, rej = colocation_check(E, Rm, T, ro, np.ones(len(E), bool), 4)
    assert n_w[2] == 2 and med[2] > 10 and rej[2]  # camera 0's direction pulls the median of two over the limit
    wide = np.array([False, False, False, True, True, True])  # the pairs with a real baseline (parallax)
    n_w, med, rej = colocation_check(E, Rm, T, ro, np.ones(len(E), bool), 4, witness=wide)
    assert n_w[2] == 1 and med[2] < 2 and not rej[2]


def test_colocation_witnesses_from_4_cycles():
    # a chain plus two false claims (0, 4), (1, 5) with the true rotations: no triangle, one 4-cycle 0-1-5-4
    rng = np.random.default_rng(3)
    C, R = rng.normal(0, 3, (8, 3)), so3.random_rotations(8, rng)
    E = np.array([[k, k + 1] for k in range(7)] + [[0, 4], [1, 5]])
    Rm, T = _translations(R, C, E)
    ro = np.zeros(len(E), bool)
    ro[-2:], T[-2:] = True, 0
    n_w, _, rej = colocation_check(E, Rm, T, ro, np.ones(len(E), bool), 8)
    assert n_w[-2] == n_w[-1] == 1 and rej[-2] and rej[-1]


def test_group_median():
    c, m = group_median(np.array([2, 0, 2, 2, 0]), np.array([5.0, 1.0, 1.0, 3.0, 2.0]), 4)
    assert c.tolist() == [2, 0, 3, 0] and m[0] == 1.5 and m[2] == 3.0 and np.isnan(m[[1, 3]]).all()


def test_each_confirmed_edge_knows_its_tightest_consistent_cycle():
    # K4 with exact rotations but edge (0, 1) turned 3°: every cycle through it closes at 3°, the triangle 1-2-3
    # and the 4-cycles avoiding it close at 0; with a threshold above 3° all are consistent
    R = so3.random_rotations(4, np.random.default_rng(5))
    E = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    Rm[0] = so3.exp(np.deg2rad([0, 3.0, 0])) @ Rm[0]
    res = cycle_filter(E, Rm, 4, np.full(6, 2.0), max_len=3, calibrate=False)
    assert res.kept.all() and res.confirmed.all()
    by_angle = {tuple(sorted(e[e >= 0].tolist())): a for e, a in zip(res.cycles.edges, res.angles)}
    for k in range(6):  # the definition: the smallest angle among the consistent cycles through the edge
        assert res.confirm_deg[k] == pytest.approx(min(a for c, a in by_angle.items() if k in c), abs=1e-12)
    assert res.confirm_deg[0] == pytest.approx(3.0, abs=1e-6)
    assert np.all(res.confirm_deg[1:] < 1e-6)
    # a tighter threshold: the cycles through (0, 1) are inconsistent; it is confirmed by none
    res = cycle_filter(E, Rm, 4, np.full(6, 0.2), max_len=3, calibrate=False, min_deg=1.0, max_deg=2.0)
    assert not res.confirmed[0] and res.confirm_deg[0] == np.inf
