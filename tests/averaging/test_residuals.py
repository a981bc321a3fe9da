"""The fused residual and mixture kernels give, bit for bit, what their plain numpy formulations give."""

import numpy as np
from scipy.special import gammaln

from pipeline.averaging import residuals
from pipeline.averaging.kernel import LaplacianSolver, effective_weights
from pipeline.averaging.mixture import MixtureModel, dof_factor, em_update, fit_mixture, log_haar, mixture_terms
from pipeline.averaging.residuals import edge_residuals, graph_residuals, held_measurements
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph


def _plain_residuals(vg: ViewGraph, R: np.ndarray) -> np.ndarray:
    # from the view graph itself, not from the kernel's memo of it (a wrong memo would be on both sides)
    q_rel = np.ascontiguousarray(so3.quat_from_matrix(vg.R_rel).T)
    e0, e1 = np.asarray(vg.edges[:, 0], np.int64), np.asarray(vg.edges[:, 1], np.int64)
    q = np.ascontiguousarray(so3.quat_from_matrix(R).T)
    qj = q[:, e1]
    qj[1:] *= -1.0
    return so3.log_quat(so3.quat_multiply(so3.quat_multiply(qj, q_rel, axis=0), q[:, e0], axis=0).T)


def _plain_mixture_terms(q, half_logdet, lh, s, nu, eps):
    lt = (gammaln(0.5 * (nu + 3.0)) - gammaln(0.5 * nu) - 1.5 * np.log(nu * np.pi) - 3.0 * np.log(s)
          + half_logdet - 0.5 * (nu + 3.0) * np.log1p(q / (nu * s * s)))
    a = np.log1p(-eps) + lt
    b = np.log(eps) + lh
    m = np.maximum(a, b)
    ll = m + np.log(np.exp(a - m) + np.exp(b - m))
    return ll, np.exp(a - ll), (nu + 3.0) / (nu + q / (s * s))


def test_graph_residuals_are_those_of_the_quaternion_products_to_the_last_bit_and_fortran_ordered():
    rng = np.random.default_rng(3)
    n, m = 30, 300
    edges = np.unique(np.sort(rng.integers(0, n, (m, 2)), axis=1), axis=0)
    edges = edges[edges[:, 0] < edges[:, 1]]
    R = so3.random_rotations(n, rng)
    noise = so3.exp(rng.standard_normal((len(edges), 3)) * np.where(rng.random(len(edges)) < 0.2, 2.0, 0.01)[:, None])
    exact = ViewGraph([f"c{i}" for i in range(n)], edges, so3.relative(R, edges))  # every residual below 1e-8
    noisy = ViewGraph([f"c{i}" for i in range(n)], edges, noise @ so3.relative(R, edges))
    for vg in (exact, noisy):
        for at in (R, so3.random_rotations(n, rng)):
            r = graph_residuals(vg, at)
            assert np.array_equal(r, _plain_residuals(vg, at))
            assert r.flags["F_CONTIGUOUS"]  # the einsums downstream round as on log_quat's product
    assert np.abs(graph_residuals(exact, R)).max() < 1e-8 < np.abs(graph_residuals(noisy, R)).max()


def test_mixture_terms_are_the_plain_log_sum_exp_to_the_last_bit():
    rng = np.random.default_rng(4)
    theta = np.abs(rng.standard_normal(5000)) * np.where(rng.random(5000) < 0.3, 1.0, 0.01)
    q, hl, lh = theta**2, 1.5 * np.log(rng.uniform(0.5, 2.0, 5000)), log_haar(theta)
    nus = np.array([1.0, 1.5, 3.0, 32.0])[:, None]
    for args in [(q, hl, lh, 0.012, 1.5, 0.27),  # em_update's call: scalars
                 (q[None], hl[None], lh[None], np.full((4, 1), 0.01), nus, np.full((4, 1), 0.2)),  # the ν grid
                 (q, hl, lh, 0.01, 3.0, np.full((2, 1), 0.2))]:  # eps alone on a grid
        for fused, plain in zip(mixture_terms(*args), _plain_mixture_terms(*args)):
            assert fused.shape == plain.shape and np.array_equal(fused, plain)


def _graph(seed: int, n: int = 30, m: int = 300) -> tuple[ViewGraph, np.ndarray]:
    rng = np.random.default_rng(seed)
    edges = np.unique(np.sort(rng.integers(0, n, (m, 2)), axis=1), axis=0)
    edges = edges[edges[:, 0] < edges[:, 1]]
    R = so3.random_rotations(n, rng)
    noise = so3.exp(rng.standard_normal((len(edges), 3)) * 0.05)
    return ViewGraph([f"c{i}" for i in range(n)], edges, noise @ so3.relative(R, edges)), R


def test_a_held_graph_is_fingerprinted_once_and_validated_again_after_the_hold(monkeypatch):
    vg, R = _graph(5)
    calls = []
    fingerprint = residuals._fingerprint
    monkeypatch.setattr(residuals, "_fingerprint", lambda a: calls.append(1) or fingerprint(a))
    before = graph_residuals(vg, R)
    assert len(calls) == 2  # R_rel and edges, at every evaluation outside a hold
    with held_measurements(vg):
        with held_measurements(vg):  # holds nest
            assert np.array_equal(graph_residuals(vg, R), before)
        for _ in range(3):
            assert np.array_equal(graph_residuals(vg, R), before)
    assert len(calls) == 4 and not residuals._HELD
    vg.R_rel[:] = vg.R_rel[::-1].copy()  # changed in place between two solves
    with held_measurements(vg):
        after = graph_residuals(vg, R)
    assert len(calls) == 6
    assert np.allclose(after, edge_residuals(vg.edges, vg.R_rel, R), atol=1e-12) and not np.allclose(after, before)


def test_a_copy_of_a_held_graph_is_validated_as_any_graph():
    vg, R = _graph(6)
    with held_measurements(vg):
        graph_residuals(vg, R)
        copy = ViewGraph(vg.names, vg.edges, vg.R_rel.copy())
        copy.__dict__.update(vg.__dict__)  # the memo travels with a shallow copy of the attributes
        copy.R_rel = copy.R_rel[::-1].copy()
        assert np.allclose(graph_residuals(copy, R), edge_residuals(copy.edges, copy.R_rel, R), atol=1e-12)


def test_laplacian_entries_without_parallel_edges_are_those_of_the_full_scatter_to_the_last_bit():
    vg, _ = _graph(7)
    rng = np.random.default_rng(7)
    fast, full = LaplacianSolver(vg.edges, vg.n_cameras), LaplacianSolver(vg.edges, vg.n_cameras)
    full._off = None
    assert fast._off is not None
    cut = (rng.random(vg.n_edges) < 0.3) | np.any(vg.edges == 3, axis=1)  # camera 3 left with zero weights only
    for w in (rng.random(vg.n_edges), np.where(cut, 0.0, rng.random(vg.n_edges) * 1e3)):
        for _ in range(2):  # the gauge's mask is kept between calls
            a, b = fast.matrix(w), full.matrix(w)
            assert np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
            assert a.data.tobytes() == b.data.tobytes()  # signed zeros included
            assert np.array_equal(fast.pinned, full.pinned)
    assert fast.pinned.sum() > 1  # the zero weights cut the graph: several gauges, zeroed rows and columns


def test_parallel_edges_are_summed_by_the_full_scatter():
    edges = np.array([[0, 1], [1, 2], [0, 1], [2, 0]])
    solver = LaplacianSolver(edges, 3)
    assert solver._off is None
    w = np.array([1.0, 2.0, 3.0, 4.0])
    A = solver.A.toarray()
    L = A.T @ np.diag(effective_weights(w)) @ A
    L[0, :] = L[:, 0] = 0.0
    L[0, 0] = 1.0
    assert np.array_equal(solver.matrix(w).toarray(), L)


def test_em_update_is_the_inner_fit_then_the_step_to_the_last_bit():
    rng = np.random.default_rng(8)
    theta = np.abs(rng.standard_normal(4000)) * np.where(rng.random(4000) < 0.2, 1.0, 0.01)
    m = rng.uniform(0.5, 2.0, 4000)
    q, hl = m * theta * theta, 1.5 * np.log(m)
    model = MixtureModel(3.0, 0.012, 0.2, 0.0, np.ones(4000))
    w, new = em_update(q, hl, theta, model, 50)
    inner = fit_mixture(q, hl, theta, 50, (model.nu,), 9, model.s, max(model.eps, 1e-4))
    ll, g, u = mixture_terms(q, hl, log_haar(theta), inner.s, inner.nu, inner.eps)
    s = max(float(np.sqrt(dof_factor(g, 50) * np.sum(g * u * q) / (3.0 * max(float(g.sum()), 1e-12)))), 1e-12)
    assert np.array_equal(w, g * u / (inner.s * inner.s)) and np.array_equal(new.gamma, g)
    assert (new.s, new.eps, new.loglik) == (s, float(np.clip(1.0 - g.mean(), 1e-4, 0.3)), float(ll.mean()))
