"""Conjugate gradients with a (block-)Jacobi preconditioner on well-connected view graphs (iterative.solve_iteratively).

The answer must be the current system's, whichever path gives it: checked against a dense solve. The path itself is
checked too: a well-connected graph is solved without new factors, a chain never tries the preconditioner, and a
preconditioner that does not converge ends the trial for the run and still gives the right answer.
"""

from __future__ import annotations

import numpy as np
import pytest

import pipeline.averaging.iterative as iterative
import pipeline.averaging.kernel as kernel
from pipeline.averaging import average
from pipeline.averaging.block import BlockLaplacianSolver
from pipeline.averaging.iterative import JacobiPreconditioner
from pipeline.averaging.kernel import LaplacianSolver
from pipeline.core import so3
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.synthetic.graphs import paper1_graph, with_outliers


def _direct(solver, A, b):
    bb = np.array(b, dtype=np.float64)
    bb[solver.pinned] = 0.0
    x = np.linalg.solve(A.toarray(), bb.reshape(A.shape[0], -1))
    return x.reshape(bb.shape)


def _well_connected(n=400, seed=3):
    g = paper1_graph(n, 0.03, 1.0, 0.0, seed=seed)  # random pairs, degree about 12: the factor fills
    return g


def test_the_preconditioner_inverts_the_diagonal_blocks():
    rng = np.random.default_rng(0)
    n = 7
    M = rng.standard_normal((3 * n, 3 * n))
    A = M @ M.T + 3 * n * np.eye(3 * n)
    import scipy.sparse as sp

    R = rng.standard_normal((3 * n, 2))
    D = np.zeros_like(A)
    for k in range(n):
        D[3 * k:3 * k + 3, 3 * k:3 * k + 3] = A[3 * k:3 * k + 3, 3 * k:3 * k + 3]
    np.testing.assert_allclose(JacobiPreconditioner(sp.csc_matrix(A), 3).solve(R), np.linalg.solve(D, R), rtol=1e-12)
    np.testing.assert_allclose(JacobiPreconditioner(sp.csc_matrix(A), 3).solve(R[:, 0]), np.linalg.solve(D, R[:, 0]),
                               rtol=1e-12)
    np.testing.assert_allclose(JacobiPreconditioner(sp.csc_matrix(A)).solve(R), R / np.diag(A)[:, None], rtol=1e-15)


def test_a_well_connected_graph_is_solved_without_new_factors(monkeypatch):
    g = _well_connected()
    rng = np.random.default_rng(1)
    S = LaplacianSolver(g.vg.edges, g.vg.n_cameras, ref=0)
    S.factor(np.ones(g.vg.n_edges))
    assert S._factor.jacobi is True
    used = []
    monkeypatch.setattr(iterative, "JacobiPreconditioner", lambda *a, _J=JacobiPreconditioner: used.append(1) or _J(*a))
    b = rng.standard_normal((g.vg.n_cameras, 3))
    for spread in (2.0, 1e3):  # an IRLS-like reweighting, then weights over six decades
        w = np.exp(rng.uniform(-np.log(spread), np.log(spread), g.vg.n_edges))
        x = S.solve_reusing(w, b)
        np.testing.assert_allclose(x, _direct(S, S.matrix(w), b), rtol=0, atol=1e-6 * np.abs(x).max())
    assert S.n_factorizations == 1 and len(used) == 2 and S._factor.jacobi is True


def test_a_chain_never_tries_the_preconditioner():
    n = 400
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    S = LaplacianSolver(chain, n)
    S.factor(np.ones(n - 1))
    assert S._factor.jacobi is False
    assert iterative.solve_iteratively(S._factor, S.matrix(np.ones(n - 1)), np.ones((n, 3)), 1e-8) == (None, 0)


def test_a_preconditioner_that_does_not_converge_ends_the_trial(monkeypatch):
    g = _well_connected()
    rng = np.random.default_rng(2)
    S = LaplacianSolver(g.vg.edges, g.vg.n_cameras, ref=0)
    S.factor(np.ones(g.vg.n_edges))
    monkeypatch.setattr(iterative, "JACOBI_MAX_CG", 2)
    w = rng.uniform(0.5, 2.0, g.vg.n_edges)
    b = rng.standard_normal((g.vg.n_cameras, 3))
    x = S.solve_reusing(w, b)
    assert S._factor.jacobi is False
    np.testing.assert_allclose(x, _direct(S, S.matrix(w), b), rtol=0, atol=1e-6 * np.abs(x).max())


def test_the_block_solver_too():
    g = _well_connected()
    rng = np.random.default_rng(4)
    A = rng.standard_normal((g.vg.n_edges, 3, 3))
    B = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    S = BlockLaplacianSolver(g.vg.edges, g.vg.n_cameras, ref=0)
    S.factor(B)
    assert S._factor.jacobi is True
    b = rng.standard_normal((g.vg.n_cameras, 3))
    B1 = B * rng.uniform(0.3, 3.0, g.vg.n_edges)[:, None, None]
    it0 = S.n_cg_iterations
    x = S.solve_reusing(B1, b)
    assert S.n_factorizations == 1 and it0 < S.n_cg_iterations <= iterative.JACOBI_MAX_CG
    np.testing.assert_allclose(x, _direct(S, S.matrix(B1), b), rtol=0, atol=1e-5 * np.abs(x).max())


@pytest.mark.parametrize("method", ["irls", "irls-h"])
def test_irls_gives_the_rotations_of_the_factored_path(monkeypatch, method):
    g = paper1_graph(400, 0.03, 2.0, 0.0, seed=5)
    vg, _ = with_outliers(g.vg, 0.1, seed=6)
    if method == "irls-h":
        vg = vg.with_H(np.broadcast_to(np.diag([1e4, 2e4, 4e4]), (vg.n_edges, 3, 3)).copy())
    used = []
    orig = iterative.solve_iteratively
    monkeypatch.setattr(iterative, "solve_iteratively", lambda *a, **k: used.append(1) or orig(*a, **k))
    fast = average(vg, method).R
    assert used
    monkeypatch.setattr(iterative, "solve_iteratively", lambda *a, **k: (None, 0))
    slow = average(vg, method).R
    assert rotation_errors_deg(fast, slow, align="none").max() < 1e-4
    assert np.median(rotation_errors_deg(fast, g.R_true)) < 1.0


def test_an_expander_is_recognised_before_its_first_factor_and_a_spatial_graph_is_not(monkeypatch):
    """From FILL_PROBE_MIN_N rows, a first matrix is probed: 1200 cameras with random pairs (degree 16, 1.4% of
    the Laplacian nonzero: a sparse pattern whose factor fills) are solved to 1e-6 by diagonal-preconditioned CG
    within the probe's steps, so the very first factor is dense, with no SuperLU factor at all; a grid's and a
    band's (streets, video) are not, and SuperLU factors them as before. The solutions are the systems' own."""
    rng = np.random.default_rng(4)
    n = 1200
    pairs = np.unique(np.sort(rng.integers(0, n, (11000, 2)), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] < pairs[:, 1]][:9600]
    side = np.arange(n).reshape(30, 40)
    grid = np.r_[np.c_[side[:, :-1].ravel(), side[:, 1:].ravel()], np.c_[side[:-1].ravel(), side[1:].ravel()]]
    band = np.r_[np.c_[np.arange(n - 1), np.arange(1, n)], np.c_[np.arange(n - 6), np.arange(6, n)]]
    superlu_calls = []
    real = kernel.factor_symmetric
    monkeypatch.setattr(kernel, "factor_symmetric", lambda A: superlu_calls.append(A.shape[0]) or real(A))
    for name, e, expander in (("random", pairs, True), ("grid", grid, False), ("band", band, False)):
        superlu_calls.clear()
        solver = LaplacianSolver(e, n)
        w = rng.uniform(0.5, 2.0, len(e))
        solver.factor(w)
        A = solver.matrix(w)
        assert A.nnz < kernel.DENSE_PATTERN * n * n, name
        assert kernel.well_conditioned(A) is expander, name
        assert solver.fills is expander and (not superlu_calls) is expander, name
        b = rng.standard_normal((n, 3))
        np.testing.assert_allclose(solver.solve(b), _direct(solver, A, b), atol=1e-8, err_msg=name)
