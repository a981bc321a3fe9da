"""ℓ1 step of paper 1, Algorithm 2 (ADMM) against scipy.optimize.linprog."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linprog

from pipeline.core import so3
from pipeline.averaging.kernel import LaplacianSolver
from pipeline.averaging.l1 import l1_averaging, l1_step
from pipeline.core.viewgraph import ViewGraph


def _lad_linprog(A: np.ndarray, b: np.ndarray, ref: int) -> float:
    """min ‖A x − b‖₁ with x_ref = 0, as an LP: min Σt, −t <= A x − b <= t."""
    M, N = A.shape
    keep = np.arange(N) != ref
    Ak = A[:, keep]
    n = Ak.shape[1]
    c = np.r_[np.zeros(n), np.ones(M)]
    I = np.eye(M)
    A_ub = np.block([[Ak, -I], [-Ak, -I]])
    b_ub = np.r_[b, -b]
    res = linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=[(None, None)] * n + [(0, None)] * M, method="highs")
    assert res.status == 0
    return float(res.fun)


def _random_graph(n, p, seed):
    rng = np.random.default_rng(seed)
    iu = np.array(np.triu_indices(n, 1)).T
    keep = (rng.random(len(iu)) < p) | ((iu[:, 1] - iu[:, 0]) == 1)
    return iu[keep], rng


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_admm_matches_linprog(seed):
    edges, rng = _random_graph(12, 0.5, seed)
    N, M = 12, len(edges)
    r = 0.05 * rng.standard_normal((M, 3))
    out = rng.random(M) < 0.2  # outlier edges, each with its own large offset
    r[out] += rng.uniform(-1, 1, (int(out.sum()), 3))
    solver = LaplacianSolver(edges, N, ref=0)
    solver.factor(np.ones(M))
    st = l1_step(solver, r, max_iterations=20000, eps_abs=1e-10, eps_rel=1e-9)
    A = solver.A.toarray()
    opt = sum(_lad_linprog(A, r[:, k], 0) for k in range(3))
    assert st.objective == pytest.approx(opt, rel=1e-5, abs=1e-7)
    assert np.all(st.x[0] == 0)


def test_admm_exact_on_consistent_data():
    edges, rng = _random_graph(10, 0.6, 3)
    solver = LaplacianSolver(edges, 10, ref=2)
    solver.factor(np.ones(len(edges)))
    x_true = rng.standard_normal((10, 3))
    x_true -= x_true[2]
    r = solver.A @ x_true
    st = l1_step(solver, r, max_iterations=5000, eps_abs=1e-12, eps_rel=1e-10)
    np.testing.assert_allclose(st.x, x_true, atol=1e-6)


def test_l1_averaging_is_robust_to_outliers():
    edges, rng = _random_graph(20, 0.6, 4)
    R = so3.random_rotations(20, rng)
    vg = ViewGraph.from_absolute([str(i) for i in range(20)], R, edges)
    Rrel = vg.R_rel.copy()
    out = rng.random(vg.n_edges) < 0.15
    Rrel[out] = so3.random_rotations(int(out.sum()), rng)
    vg = ViewGraph(vg.names, vg.edges, Rrel)
    R0 = R @ so3.exp(np.deg2rad(5) * rng.standard_normal((20, 3)))
    Rl1, hist = l1_averaging(vg, R0, max_iterations=20, admm_max_iterations=500)
    G = so3.chordal_mean(np.swapaxes(R, 1, 2) @ Rl1)
    assert np.rad2deg(so3.angle_between(Rl1, R @ G)).max() < 0.1
    assert hist[-1]["mean_step_rad"] < hist[0]["mean_step_rad"]
