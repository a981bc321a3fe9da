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


def _plain_l1_step(solver, r, max_iterations, eps_abs=1e-7, eps_rel=1e-5, relax=1.6, check_every=5):
    """The ADMM of :func:`l1_step` as first written, on ``r`` as given (its memory order included)."""
    A, AT, M = solver.A, solver.AT, r.shape[0]
    z, u = np.zeros_like(r), np.zeros_like(r)
    rho = 1.0 / max(float(np.median(np.abs(r))), 1e-6)
    norm = lambda a: float(np.sqrt(np.square(a).sum()))  # noqa: E731
    for k in range(1, max_iterations + 1):
        x = solver.solve(AT @ (r + z - u))
        Ax = A @ x
        v = relax * (Ax - r) + (1.0 - relax) * z + u
        z_old, u = z, np.clip(v, -1.0 / rho, 1.0 / rho)
        z = v - u
        if k % check_every and k < max_iterations:
            continue
        r_pri, s_dual = norm(Ax - z - r), rho * norm(AT @ (z - z_old))
        eps_pri = np.sqrt(3 * M) * eps_abs + eps_rel * max(norm(Ax), norm(z), norm(r))
        if r_pri <= eps_pri and s_dual <= np.sqrt(3 * solver.n) * eps_abs + eps_rel * rho * norm(AT @ u):
            break
        if r_pri > 10.0 * s_dual:
            rho, u = rho * 2.0, u / 2.0
        elif s_dual > 10.0 * r_pri:
            rho, u = rho / 2.0, u * 2.0
    return x, k, float(np.abs(A @ x - r).sum()), z, u, rho


def test_admm_on_column_major_residuals_is_the_plain_iteration_to_the_last_bit():
    edges, rng = _random_graph(40, 0.5, 5)
    r = np.asfortranarray(0.05 * rng.standard_normal((len(edges), 3)) * np.where(rng.random((len(edges), 1)) < 0.2,
                                                                                  20.0, 1.0))  # as graph_residuals'
    solver = LaplacianSolver(edges, 40, ref=0)
    solver.factor(np.ones(len(edges)))
    for cap, eps in ((7, 1e-7), (2000, 1e-4)):  # stopped by the cap; by the tolerances after changes of ρ (990)
        st = l1_step(solver, r, max_iterations=cap, eps_abs=eps, eps_rel=1e-3)
        x, k, obj, z, u, rho = _plain_l1_step(solver, r, cap, eps_abs=eps, eps_rel=1e-3)
        assert (st.iterations, st.objective, st.rho, st.converged) == (k, obj, rho, k < cap)
        assert st.rho != 1.0 / float(np.median(np.abs(r)))
        for a, b in ((st.x, x), (st.z, z), (st.u, u)):
            assert a.tobytes() == b.tobytes()
