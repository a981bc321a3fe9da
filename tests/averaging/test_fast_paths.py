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
