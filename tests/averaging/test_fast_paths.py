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


def test_one_blas_thread_finds_the_libraries_again_after_an_import(monkeypatch):
    """A library loaded after the first use (OpenCV brings its own OpenBLAS when first imported) is limited too: the
    controllers are looked up again once a module was imported since (here: a stale list that holds none)."""
    monkeypatch.setattr(kernel, "_BLAS_LIBS", [])
    monkeypatch.setattr(kernel, "_BLAS_MODULES", -1)
    outside = _blas_counts()
    with kernel._one_blas_thread():
        assert _blas_counts() == {1}
    assert len(kernel._BLAS_LIBS) == len([d for d in threadpool_info() if d["user_api"] == "blas"]) > 0
    assert _blas_counts() == outside
    monkeypatch.setattr(kernel, "_BLAS_LIBS", [])  # no import since: the list stands as it is
    with kernel._one_blas_thread():
        assert kernel._BLAS_LIBS == []


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


def test_converged_takes_the_median_only_where_it_decides():
    from pipeline.averaging import stopping
    from pipeline.averaging.stopping import StopRule, converged, robust_scale

    rng = np.random.default_rng(7)
    taken = []
    real = stopping.robust_scale
    stopping.robust_scale = lambda th: taken.append(1) or real(th)
    try:
        for _ in range(400):
            theta = np.abs(rng.standard_normal(50)) * 10.0 ** rng.uniform(-4, -1)
            f = float(rng.uniform(1, 2))
            f_prev = f * (1 + float(rng.choice([0.0, 1e-7, 1e-6, 1e-4, 1e-2])))
            step = float(10.0 ** rng.uniform(-12, -1))
            rule = StopRule(1e-5, 0.05, None if rng.random() < 0.8 else 1e-3, 100)
            taken.clear()
            lazy = converged(f_prev, f, step, rule, theta=theta)
            assert lazy == converged(f_prev, f, step, rule, robust_scale(theta))
            settled = abs(f_prev - f) <= rule.ftol * abs(f) or step <= stopping.XTOL_FLOOR
            assert len(taken) == int(settled and rule.tol_rad is None)
    finally:
        stopping.robust_scale = real


def test_em_update_gives_the_inner_fit_then_the_terms_at_its_scale_to_the_bit():
    from pipeline.averaging.mixture import MixtureModel, _fit, em_update, log_haar, mixture_terms

    rng = np.random.default_rng(11)
    for trial in range(20):
        M = int(rng.integers(50, 30000))
        theta = np.abs(rng.standard_normal(M)) * np.deg2rad(rng.uniform(0.1, 3))
        bad = rng.random(M) < rng.uniform(0, 0.4)
        theta[bad] = rng.uniform(0, np.pi, int(bad.sum()))
        m = np.ones(M) if trial % 2 else np.exp(rng.uniform(-1, 1, M))  # isotropic, and with per-edge trust
        q, hl = m * theta * theta, 1.5 * np.log(m)
        model = MixtureModel(float(rng.choice([1.0, 3.0, 32.0])), float(np.deg2rad(rng.uniform(0.2, 2))),
                             float(rng.uniform(0.01, 0.3)), 0.0, np.ones(M))
        n = int(rng.integers(10, 300))
        for inner in (1, 2, 10):
            w, got = em_update(q, hl, theta, model, n, inner=inner)
            lh = log_haar(theta)  # the reference: the inner EM, then the terms evaluated again at its (s, ε)
            ref = _fit(q, hl, lh, n, (model.nu,), inner - 1, model.s, max(model.eps, 1e-4), 0.3) if inner > 1 else model
            ll, g, u = mixture_terms(q, hl, lh, ref.s, ref.nu, ref.eps)
            assert np.array_equal(w, g * u / (ref.s * ref.s))
            assert np.array_equal(got.gamma, g) and got.loglik == float(ll.mean()) and got.nu == ref.nu


def test_l1_step_objective_is_that_of_its_answer():
    from pipeline.averaging.kernel import LaplacianSolver
    from pipeline.averaging.l1 import l1_step

    rng = np.random.default_rng(13)
    n, m = 60, 500
    e = rng.integers(0, n, (m, 2))
    e = np.unique(np.sort(e[e[:, 0] != e[:, 1]], axis=1), axis=0)
    e = np.unique(np.vstack([e, np.stack([np.arange(n - 1), np.arange(1, n)], 1)]), axis=0)
    S = LaplacianSolver(e, n)
    S.factor(np.ones(e.shape[0]))
    r = rng.standard_normal((e.shape[0], 3)) * 0.01
    for its in (0, 1, 7, 10):
        st = l1_step(S, r, max_iterations=its)
        assert st.objective == float(np.abs(S.A @ st.x - r).sum())


def test_the_averagings_dense_factors_take_one_blas_thread_at_every_size_they_come_in():
    """A 2000-camera expander's factors (and any up to DENSE_MAX_SIZE rows) run on one thread: on a shared machine a
    second thread that waits for a core makes the factor 10–20 times slower."""
    seen: list[set[int]] = []
    real = la.cho_factor

    def spy(*args, **kwargs):
        seen.append(_blas_counts())
        return real(*args, **kwargs)

    assert kernel.DENSE_SINGLE_THREAD_SIZE > kernel.DENSE_MAX_SIZE
    rng = np.random.default_rng(17)
    n = 2000
    X = rng.standard_normal((n, 50))
    la.cho_factor = spy
    try:
        DenseCholesky(X @ X.T + np.eye(n))
    finally:
        la.cho_factor = real
    assert seen == [{1}]


def test_unique_keys_is_numpys_unique_with_its_inverse():
    rng = np.random.default_rng(19)
    # every case on the mask path (size ≤ 16 × count; above it the function is np.unique itself): one key, the
    # boundary, a dense Laplacian's 80k keys, many repeats of few keys
    for size, count in ((10, 1), (16 * 500, 500), (61009, 80000), (50, 5000), (7, 40)):
        assert size <= 16 * count
        keys = rng.integers(0, size, count)
        u, inv = kernel._unique_keys(keys, size)
        u0, inv0 = np.unique(keys, return_inverse=True)
        assert np.array_equal(u, u0) and np.array_equal(inv, inv0) and u.dtype == u0.dtype and inv.dtype == inv0.dtype


def test_laplacian_pattern_is_that_of_the_sorted_unique_entries(monkeypatch):
    from pipeline.averaging.kernel import LaplacianSolver

    rng = np.random.default_rng(23)
    for n, m, parallel in ((247, 20000, False), (40, 300, True), (2000, 20000, False)):
        e = rng.integers(0, n, (m, 2))
        e = e[e[:, 0] != e[:, 1]]
        if not parallel:
            e = np.unique(np.sort(e, 1), axis=0)
        fast = LaplacianSolver(e, n, ref=1)
        with monkeypatch.context() as mp:  # the reference: numpy's unique throughout
            mp.setattr(kernel, "_unique_keys", lambda keys, size: np.unique(keys, return_inverse=True))
            mp.setattr(np, "bincount", lambda a, *args, **kw: np.ones(np.unique(a).size, int)
                       if np.unique(a).size == a.size else np.full(1, 2))
            ref = LaplacianSolver(e, n, ref=1)
        for name in ("_pos", "_row", "_col", "_diag", "_indices", "_indptr"):
            assert np.array_equal(getattr(fast, name), getattr(ref, name)), name
        assert (fast._off is None) == (ref._off is None) == parallel
        w = rng.uniform(0.1, 2.0, e.shape[0])
        A, B = fast.matrix(w), ref.matrix(w)
        assert np.array_equal(A.data, B.data) and np.array_equal(A.indices, B.indices)
