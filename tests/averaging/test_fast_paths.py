"""The averaging's faster kernels against plain references: the same numbers to the bit where the code says so."""

from __future__ import annotations

import numpy as np
import scipy.linalg as la
from threadpoolctl import threadpool_info, threadpool_limits

import pipeline.averaging.kernel as kernel
from pipeline.averaging.kernel import DenseCholesky


def _blas_counts() -> set[int]:
    return {int(d["num_threads"]) for d in threadpool_info() if d["user_api"] == "blas"}


def test_one_blas_thread_sets_and_restores_the_libraries_own_counts():
    outside = _blas_counts()
    with kernel._one_blas_thread():
        assert _blas_counts() == {1}
        with kernel._one_blas_thread():  # nested
            assert _blas_counts() == {1}
        assert _blas_counts() == {1}
    assert _blas_counts() == outside
    with threadpool_limits(limits=1, user_api="blas"):  # a caller's own limit is what is restored
        with kernel._one_blas_thread():
            pass
        assert _blas_counts() == {1}
    assert _blas_counts() == outside


def test_dense_solve_takes_one_blas_thread_and_gives_lapacks_solution_to_the_bit():
    rng = np.random.default_rng(3)
    seen: list[set[int]] = []
    real = la.cho_solve

    def spy(*args, **kwargs):
        seen.append(_blas_counts())
        return real(*args, **kwargs)

    for n in (50, kernel.DENSE_SINGLE_THREAD_SIZE + 200):  # below and above the factor's threshold
        X = rng.standard_normal((n, n // 3))
        A = X @ X.T + np.eye(n)
        b = rng.standard_normal((n, 3))
        f = DenseCholesky(A)
        reference = la.cho_solve(f._c, b, check_finite=False)  # the process's own BLAS threads
        la.cho_solve, seen[:] = spy, []
        try:
            x = f.solve(b)
        finally:
            la.cho_solve = real
        assert seen == [{1}]
        assert np.array_equal(x, reference)


class _PlainDiagonal:
    """The 1×1 Jacobi preconditioner as any other preconditioner: what the generic CG loop runs with."""

    def __init__(self, A) -> None:
        self._inv = 1.0 / A.diagonal()

    def solve(self, R: np.ndarray) -> np.ndarray:
        return R * self._inv.reshape((-1,) + (1,) * (R.ndim - 1))


def test_diagonal_cg_gives_the_generic_loops_iterates_to_the_bit():
    from pipeline.averaging.iterative import JacobiPreconditioner, cg_with_factor
    from pipeline.averaging.kernel import LaplacianSolver

    rng = np.random.default_rng(5)
    n_solved = 0
    for trial in range(12):
        n = int(rng.integers(30, 400))
        m = int(rng.integers(3 * n, 12 * n))
        e = rng.integers(0, n, (m, 2))
        e = np.unique(np.sort(e[e[:, 0] != e[:, 1]], axis=1), axis=0)
        e = np.vstack([e, np.stack([np.arange(n - 1), np.arange(1, n)], 1)])  # connected
        e = np.unique(e, axis=0)
        S = LaplacianSolver(e, n, ref=0)
        A = S.matrix(np.exp(rng.uniform(-np.log(1e3), np.log(1e3), e.shape[0])))
        for shape, order in (((n, 3), "C"), ((n, 3), "F"), ((n,), "C"), ((n, 1), "C")):
            b = np.asarray(rng.standard_normal(shape), order=order)
            b[0] = 0.0
            for rtol, cap in ((1e-8, 150), (1e-12, 5)):  # converged, and stopped at the cap
                fast = cg_with_factor(A, b, JacobiPreconditioner(A), rtol, cap)
                plain = cg_with_factor(A, b, _PlainDiagonal(A), rtol, cap)
                assert fast[1] == plain[1]
                assert (fast[0] is None) == (plain[0] is None)
                if fast[0] is not None:
                    n_solved += 1
                    assert fast[0].shape == b.shape and np.array_equal(fast[0], plain[0])
    assert n_solved > 40  # most systems were solved, not all stopped at the cap
