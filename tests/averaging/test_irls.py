"""IRLS (paper 1, Algs. 1 and 3): sign convention, exact and noisy recovery, stats, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.averaging.init import initial_rotations, rotations_from_tree, spanning_tree
from pipeline.averaging.irls import irls
from pipeline.averaging.kernel import DenseCholesky, LaplacianSolver, apply_update, edge_residuals
from pipeline.averaging.solve import average
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

LOSSES = ["l2", "l1", "l0.5", "geman-mcclure", "huber", "pseudo-huber", "andrews", "bisquare",
          "cauchy", "fair", "logistic", "talwar", "welsch"]


def _graph(n=20, p=0.5, sigma_deg=0.0, outlier_frac=0.0, seed=0):
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    iu = np.array(np.triu_indices(n, 1)).T
    keep = rng.random(len(iu)) < p
    keep[np.flatnonzero((iu[:, 1] - iu[:, 0]) == 1)] = True  # a Hamiltonian path keeps it connected
    e = iu[keep]
    vg = ViewGraph.from_absolute([f"c{i}" for i in range(n)], R, e)
    Rrel = so3.exp(np.deg2rad(sigma_deg) * rng.standard_normal((vg.n_edges, 3))) @ vg.R_rel
    out = rng.random(vg.n_edges) < outlier_frac
    Rrel[out] = so3.random_rotations(int(out.sum()), rng)
    return ViewGraph(vg.names, vg.edges, Rrel), R, out


def _err_deg(R_est, R_true):
    G = so3.chordal_mean(np.swapaxes(R_true, 1, 2) @ R_est)  # R_est ≈ R_true G
    return np.rad2deg(so3.angle_between(R_est, R_true @ G))


def test_linearized_residual_sign():
    """r(R_i exp(Δω_i)) ≈ r − A ΔΩ with A = ViewGraph.incidence(): the sign the solver uses."""
    vg, R, _ = _graph(8, 0.8, sigma_deg=5.0, seed=1)
    rng = np.random.default_rng(2)
    dw = 1e-5 * rng.standard_normal((vg.n_cameras, 3))
    r0 = edge_residuals(vg.edges, vg.R_rel, R)
    r1 = edge_residuals(vg.edges, vg.R_rel, apply_update(R, dw))
    A = vg.incidence()
    pred = r0 - A @ dw
    # Paper 1 eq. 19 drops O(θ) Jacobian terms; residuals are ~5°, so the first-order
    # prediction is accurate to ~10% of the step, while the wrong sign is off by 200%.
    step = np.abs(A @ dw).max()
    assert np.abs(r1 - pred).max() < 0.15 * step
    assert np.abs(r1 - (r0 + A @ dw)).max() > 1.5 * step


def test_one_l2_step_solves_the_linear_problem():
    vg, R, _ = _graph(10, 0.7, sigma_deg=0.0, seed=3)
    # Perturb the truth slightly; a single ℓ2 step must undo most of it.
    rng = np.random.default_rng(4)
    R0 = R @ so3.exp(np.deg2rad(0.5) * rng.standard_normal((10, 3)))
    res = irls(vg, loss="l2", init=R0, l1_iterations=0, max_iterations=1, tol_rad=0.0)
    assert _err_deg(res.R, R).max() < 0.05 * _err_deg(R0, R).max()


@pytest.mark.parametrize("loss", LOSSES)
def test_noise_free_recovery_every_loss(loss):
    vg, R, _ = _graph(20, 0.5, seed=5)
    rng = np.random.default_rng(6)
    R0 = R @ so3.exp(np.deg2rad(2.0) * rng.standard_normal((20, 3)))
    res = irls(vg, loss=loss, init=R0, tol_rad=1e-12, max_iterations=60)
    assert _err_deg(res.R, R).max() < 1e-6
    assert res.residuals_rad.max() < 1e-7
    # the recovery starts from R0 (not from a spanning tree, which is exact on noise-free data): without
    # iterations R0 itself comes back
    assert _err_deg(irls(vg, loss=loss, init=R0, l1_iterations=0, max_iterations=0).R, R0).max() < 1e-9


def test_noisy_recovery_with_outliers():
    vg, R, out = _graph(40, 0.5, sigma_deg=1.0, outlier_frac=0.2, seed=7)
    res = irls(vg)  # ℓ½, MST init, paper defaults
    e = _err_deg(res.R, R)
    assert np.median(e) < 0.5 and e.max() < 1.5
    # Outlier edges are the discounted ones.
    assert np.median(res.weights[out]) < 0.05 * np.median(res.weights[~out])
    assert res.stats["converged"]


def test_l2_converges_to_a_stationary_point():
    vg, R, _ = _graph(30, 0.5, sigma_deg=3.0, seed=8)
    res = irls(vg, loss="l2", tol_rad=1e-10, max_iterations=100)
    # Paper 1 §4.3: at convergence AᵀΦr = 0. Checked on the cost itself, ½ Σ angle(R_ij, R_j R_iᵀ)², by central
    # differences over every camera's three rotation directions, not by the solver's own statistic.
    i, j = vg.edges[:, 0], vg.edges[:, 1]

    def cost(Rs: np.ndarray) -> float:
        return 0.5 * float(np.sum(so3.angle_between(vg.R_rel, Rs[j] @ np.swapaxes(Rs[i], 1, 2)) ** 2))

    def fd_gradient(Rs: np.ndarray, h: float = 1e-6) -> np.ndarray:
        g = np.zeros((len(Rs), 3))
        for k in range(len(Rs)):
            for a in range(3):
                d = np.zeros(3)
                d[a] = h
                Rp, Rm = Rs.copy(), Rs.copy()
                Rp[k], Rm[k] = so3.exp(d) @ Rs[k], so3.exp(-d) @ Rs[k]
                g[k, a] = (cost(Rp) - cost(Rm)) / (2 * h)
        return g

    assert np.abs(fd_gradient(res.R)).max() < 1e-7
    assert np.abs(fd_gradient(R)).max() > 1e-3  # the truth is not the noisy problem's minimum: the check can fail
    assert res.stats["gradient_norm"] < 1e-8 and res.stats["converged"]


def test_history_and_stats_recorded():
    vg, _, _ = _graph(15, 0.6, sigma_deg=2.0, seed=9)
    res = irls(vg, loss="geman-mcclure")
    irls_h = [h for h in res.history if h["stage"] == "irls"]
    l1_h = [h for h in res.history if h["stage"] == "l1"]
    assert len(irls_h) == res.iterations and 1 <= len(l1_h) <= 5
    assert all({"cost", "mean_step_rad", "time_s"} <= set(h) for h in res.history)
    times = [h["time_s"] for h in res.history]
    assert times == sorted(times)
    assert res.weights.shape == (vg.n_edges,) and res.residuals_rad.shape == (vg.n_edges,)
    s = res.summary()
    assert s["n_cameras"] == 15 and s["n_edges"] == vg.n_edges and "gradient_norm" in s


def test_iteration_cap_is_respected():
    vg, _, _ = _graph(15, 0.6, sigma_deg=2.0, seed=10)
    res = irls(vg, loss="l0.5", max_iterations=2, tol_rad=0.0)
    assert res.iterations == 2 and not res.stats["converged"]


def test_a_polish_stopped_at_its_cap_says_so(caplog):
    """The polish (the t + Haar mixture EM after IRLS) records its iterations and whether its stopping rule was met;
    stopped at its cap, it says so in the stats and in a warning, as the IRLS stage does."""
    vg, _, _ = _graph(15, 0.6, sigma_deg=2.0, outlier_frac=0.2, seed=11)
    done = average(vg, "irls")
    model = done.stats["polish_model"]
    assert model["converged"] and 1 <= model["iterations"] < 50
    with caplog.at_level("WARNING", logger="pipeline.averaging.irls"):
        capped = average(vg, "irls", refine_iterations=2, rescue=False)
    model = capped.stats["polish_model"]
    assert model["iterations"] == 2 and not model["converged"]
    assert "polish stopped at its iteration cap (refine_iterations = 2)" in caplog.text


def test_redescending_loss_with_isolated_camera_does_not_fail():
    """Talwar gives weight 0 to every edge of a camera whose edges are all outliers."""
    vg, R, _ = _graph(12, 0.6, sigma_deg=0.5, seed=11)
    bad = np.flatnonzero((vg.edges == 3).any(axis=1))
    Rrel = vg.R_rel.copy()
    Rrel[bad] = so3.exp(np.full((bad.size, 3), 0.8)) @ Rrel[bad]
    vg2 = ViewGraph(vg.names, vg.edges, Rrel)
    R0 = R @ so3.exp(np.deg2rad(0.7) * np.random.default_rng(3).standard_normal((12, 3)))  # pairs within Talwar's 5°
    res = irls(vg2, loss="talwar", l1_iterations=0, init=R0)
    assert np.all(np.isfinite(res.R))
    e, e0 = _err_deg(res.R, R), _err_deg(R0, R)
    assert np.delete(e, 3).max() < 1.0 and np.median(np.delete(e, 3)) < 0.5 * np.median(np.delete(e0, 3))
    assert np.all(res.weights[bad] == 0.0) and np.all(np.delete(res.weights, bad) > 0)


def test_laplacian_solver_pins_gauge():
    vg, _, _ = _graph(10, 0.6, seed=12)
    s = LaplacianSolver(vg.edges, 10, ref=4)
    s.factor(np.ones(vg.n_edges))
    b = np.random.default_rng(0).standard_normal((10, 3))
    x = s.solve(b)
    assert np.all(x[4] == 0)
    L = (vg.incidence().T @ vg.incidence()).toarray()
    keep = np.arange(10) != 4
    np.testing.assert_allclose(L[np.ix_(keep, keep)] @ x[keep], b[keep], atol=1e-10)


def test_spanning_tree_init_is_exact_on_consistent_edges():
    vg, R, _ = _graph(25, 0.4, seed=13)
    for kind in ("mst", "random"):
        tree = spanning_tree(vg, kind, seed=1)
        assert tree.size == 24
        R0 = rotations_from_tree(vg, tree)
        assert _err_deg(R0, R).max() < 1e-9



def test_a_deep_tree_is_chained_edge_by_edge_from_any_root():
    # A video-like chain 1500 deep with inconsistent edges: every tree edge must hold exactly (the chaining
    # reproduces each measured step, walked forward or backward from the root) and the root is the identity.
    n = 1500
    rng = np.random.default_rng(3)
    e = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    e = np.concatenate([e, [[0, n - 1], [5, 700]]])  # two edges off the tree
    vg = ViewGraph([f"c{i}" for i in range(n)], e, so3.random_rotations(len(e), rng))
    tree = np.arange(n - 1)
    for root in (0, 777, n - 1):
        R = rotations_from_tree(vg, tree, root=root)
        np.testing.assert_allclose(R[root], np.eye(3), atol=1e-15)
        i, j = e[tree, 0], e[tree, 1]
        pred = R[j] @ np.swapaxes(R[i], 1, 2)
        assert np.abs(pred - vg.R_rel[tree]).max() < 1e-11
        assert np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max() < 1e-11

def test_mst_prefers_high_inlier_edges():
    vg, _, _ = _graph(10, 1.0, seed=14)
    inl = np.ones(vg.n_edges)
    path = (vg.edges[:, 1] - vg.edges[:, 0]) == 1
    inl[path] = 100
    vg2 = ViewGraph(vg.names, vg.edges, vg.R_rel, inliers=inl)
    assert set(spanning_tree(vg2, "mst")) == set(np.flatnonzero(path))


def test_user_init_rejected_when_bad():
    vg, _, _ = _graph(6, 1.0, seed=15)
    with pytest.raises(ValueError, match=r"expected \(6, 3, 3\)"):
        initial_rotations(vg, np.zeros((5, 3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        initial_rotations(vg, np.full((6, 3, 3), np.nan))


def test_disconnected_graph_solves_largest_component_and_names_the_rest(caplog):
    vg, R, _ = _graph(10, 0.8, seed=16)
    names = vg.names + ["x0", "x1", "x2"]
    R3 = np.concatenate([R, so3.random_rotations(3, np.random.default_rng(0))])
    e = np.concatenate([vg.edges, [[10, 11], [11, 12]]])
    vg2 = ViewGraph.from_absolute(names, R3, e)
    with caplog.at_level("WARNING"):
        res = average(vg2)
    assert res.names == vg.names
    assert res.dropped_names == ["x0", "x1", "x2"]
    assert "x0" in caplog.text
    assert np.all(res.edge_index < vg.n_edges)
    with pytest.raises(ViewGraphError, match="not connected"):
        irls(vg2)


def test_empty_graph_rejected():
    vg = ViewGraph([], np.zeros((0, 2)), np.zeros((0, 3, 3)))
    with pytest.raises(ViewGraphError, match="empty"):
        average(vg)


def test_graph_without_edges_rejected():
    vg = ViewGraph(["a", "b"], np.zeros((0, 2)), np.zeros((0, 3, 3)), allow_isolated=True)
    with pytest.raises(ViewGraphError, match="no edge"):
        average(vg)


def test_nan_rotation_rejected():
    vg, _, _ = _graph(5, 1.0, seed=17)
    with pytest.raises(ViewGraphError, match="NaN"):
        R = vg.R_rel.copy()
        R[0, 0, 0] = np.nan
        ViewGraph(vg.names, vg.edges, R)
    # A graph mutated after validation is caught by the averaging entry point too.
    vg.R_rel[1, 1, 1] = np.nan
    with pytest.raises(ViewGraphError, match="NaN"):
        average(vg)


def test_unknown_loss_and_method_rejected():
    vg, _, _ = _graph(5, 1.0, seed=18)
    with pytest.raises(ValueError, match="unknown loss 'nope'; valid names"):
        average(vg, loss="nope")
    with pytest.raises(ValueError, match="unknown method 'foo'; valid methods: irls, irls-h, l1, weiszfeld, sdp"):
        average(vg, method="foo")


def test_dense_graph_factors_densely_and_solves_the_same_system():
    """A view graph whose SuperLU factor fills (random pairs: 3.5% of the Laplacian nonzero, the factor more than
    DENSE_FILL) switches to a dense Cholesky after the first factor; one whose matrix is itself dense (1DSfM-like:
    most pairs measured) is factored densely from the first; both solve the same system as SuperLU to rounding;
    a sparse chain stays with SuperLU."""
    import pipeline.averaging.kernel as kernel
    from pipeline.averaging.block import BlockLaplacianSolver
    from pipeline.synthetic.graphs import paper1_graph

    g = paper1_graph(300, 0.03, 1.0, 0.0, seed=3)
    L = LaplacianSolver(g.vg.edges, 300)
    assert L.matrix(np.ones(g.vg.n_edges)).nnz < kernel.DENSE_PATTERN * 300**2
    L.factor(np.ones(g.vg.n_edges))
    assert L._factor.dense is True and not isinstance(L._lu, DenseCholesky)  # decided from the first factor's fill
    L.factor(np.ones(g.vg.n_edges))
    assert isinstance(L._lu, DenseCholesky)
    vg, _, _ = _graph(60, 0.7, seed=3)
    w = np.random.default_rng(1).uniform(0.1, 2.0, vg.n_edges)
    b = np.random.default_rng(2).standard_normal((60, 3))
    auto, sparse = LaplacianSolver(vg.edges, 60, ref=5), LaplacianSolver(vg.edges, 60, ref=5, dense=False)
    auto.factor(w)
    assert auto._factor.dense is True and isinstance(auto._lu, DenseCholesky)  # decided from the matrix itself
    auto.factor(w)
    sparse.factor(w)
    assert isinstance(auto._lu, DenseCholesky) and not isinstance(sparse._lu, DenseCholesky)
    np.testing.assert_allclose(auto.solve(b), sparse.solve(b), rtol=0, atol=1e-12 * np.abs(sparse.solve(b)).max())
    # the block (IRLS-H) solver likewise, and through the CG-with-factor path of solve_reusing
    rng = np.random.default_rng(4)
    A = rng.standard_normal((vg.n_edges, 3, 3))
    B = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    blk, blk_sparse = BlockLaplacianSolver(vg.edges, 60, ref=5), BlockLaplacianSolver(vg.edges, 60, ref=5, dense=False)
    for s in (blk, blk_sparse):
        s.factor(B)
        s.factor(B)
    assert isinstance(blk._lu, DenseCholesky) and not isinstance(blk_sparse._lu, DenseCholesky)
    x1, x2 = blk.solve_reusing(1.01 * B, b), blk_sparse.solve_reusing(1.01 * B, b)
    np.testing.assert_allclose(x1, x2, rtol=0, atol=1e-6 * np.abs(x2).max())
    chain = np.stack([np.arange(59), np.arange(1, 60)], 1)
    s = LaplacianSolver(chain, 60)
    s.factor(np.ones(59))
    s.factor(np.ones(59))
    assert s._factor.dense is False and not isinstance(s._lu, DenseCholesky)


def test_dense_cholesky_hands_lapack_a_fortran_array_whatever_the_sparse_format(monkeypatch):
    # LAPACK factors a Fortran-ordered array in place; any other order is copied first (the certificate's
    # 7500-row CSC matrix: 5.6 s against 1.6 s). CSR and CSC give opposite orders from toarray().
    import scipy.linalg as la
    import scipy.sparse as sp

    import pipeline.averaging.kernel as kernel

    seen = []
    real = la.cho_factor
    monkeypatch.setattr(kernel.la, "cho_factor", lambda a, **k: seen.append(a.flags.f_contiguous) or real(a, **k))
    rng = np.random.default_rng(0)
    M = rng.standard_normal((40, 40))
    A = M @ M.T + 40 * np.eye(40)
    b = rng.standard_normal(40)
    for fmt in (sp.csr_matrix, sp.csc_matrix, np.asarray):
        np.testing.assert_allclose(DenseCholesky(fmt(A)).solve(b), np.linalg.solve(A, b), rtol=1e-10)
    assert seen == [True, True, True]


def test_dense_and_sparse_factors_give_the_same_irls_result(monkeypatch):
    import pipeline.averaging.kernel as kernel

    vg, R, _ = _graph(50, 0.8, sigma_deg=1.0, outlier_frac=0.1, seed=5)
    runs = {}
    for dense in (True, False):
        init = kernel.SymmetricFactorizer.__init__
        monkeypatch.setattr(kernel.SymmetricFactorizer, "__init__", lambda self, d=None, _m=dense, _i=init: _i(self, _m))
        runs[dense] = average(vg, "irls").R
    assert np.max(np.rad2deg(so3.angle_between(runs[True], runs[False]))) < 1e-8
    assert np.median(_err_deg(runs[True], R)) < 1.0


def test_a_matrix_that_is_not_positive_definite_falls_back_to_superlu():
    import scipy.sparse as sp

    from pipeline.averaging.kernel import SymmetricFactorizer

    A = sp.csc_matrix(np.diag([2.0, -1.0, 3.0]))  # symmetric, nonsingular, indefinite
    with pytest.raises(np.linalg.LinAlgError):
        DenseCholesky(A)
    lu = SymmetricFactorizer(dense=True)(A)
    assert not isinstance(lu, DenseCholesky)
    np.testing.assert_allclose(lu.solve(np.array([2.0, 1.0, 3.0])), [1.0, -1.0, 1.0])


def test_graph_residuals_equal_edge_residuals_and_follow_the_graph_when_it_changes():
    from pipeline.averaging.kernel import graph_residuals

    vg, R, _ = _graph(40, 0.5, sigma_deg=3.0, outlier_frac=0.3, seed=8)
    R_now = R @ so3.exp(np.random.default_rng(9).standard_normal((40, 3)) * 0.2)
    a, b = edge_residuals(vg.edges, vg.R_rel, R_now), graph_residuals(vg, R_now)
    ok = np.linalg.norm(a, axis=1) < np.pi - 1e-6  # at π, r and −r are the same rotation
    assert ok.sum() > 0.9 * vg.n_edges and np.abs(a - b)[ok].max() < 1e-14
    # the quaternions kept on the graph are converted again after an in-place change of R_rel
    vg.R_rel[3] = so3.exp(np.array([0.0, 0.0, 0.5])) @ vg.R_rel[3]
    np.testing.assert_allclose(graph_residuals(vg, R_now)[3], edge_residuals(vg.edges, vg.R_rel, R_now)[3],
                               atol=1e-14)
    assert np.linalg.norm(graph_residuals(vg, R_now)[3] - b[3]) > 0.1


def test_a_camera_matched_mostly_wrong_is_moved_to_the_rotation_its_right_edges_agree_on():
    """A camera with 80% Haar-outlier edges: its ℓ1 start is outvoted, and the rescue moves it to the rotation its
    right edges propose; a camera of a repeated-structure block (edges wrong by one rotation, fewer than its right
    ones) stays."""
    from pipeline.averaging.rescue import rescue_cameras

    rng = np.random.default_rng(11)
    n = 60
    R = so3.random_rotations(n, rng)
    iu = np.array(np.triu_indices(n, 1)).T
    vg = ViewGraph.from_absolute([f"c{i}" for i in range(n)], R, iu[rng.random(len(iu)) < 0.6])
    R_rel = so3.exp(np.deg2rad(0.5) * rng.standard_normal((vg.n_edges, 3))) @ vg.R_rel
    at0 = np.flatnonzero(np.any(vg.edges == 0, axis=1))
    bad = rng.choice(at0, size=int(0.8 * at0.size), replace=False)
    R_rel[bad] = so3.random_rotations(bad.size, rng)
    vg = ViewGraph(vg.names, vg.edges, R_rel)
    start = R.copy()
    start[0] = so3.exp(np.array([0.0, 2.0, 0.0])) @ R[0]  # camera 0 in a wrong basin, 115° off
    theta = np.linalg.norm(edge_residuals(vg.edges, vg.R_rel, start), axis=1)
    res = rescue_cameras(vg, start, theta, np.deg2rad(5.0))
    assert res.cameras.tolist() == [0] and res.support_after[0] == at0.size - bad.size
    assert np.rad2deg(so3.angle_between(res.R[0], R[0])) < 0.5 and np.array_equal(res.R[1:], start[1:])
    # the whole IRLS on a dense graph as 1DSfM's: without the rescue a camera is lost, with it not, and the result
    # says which camera moved
    from pipeline.synthetic.protocols import dense_graph

    g, _ = dense_graph(seed=0)
    with_rescue, without = average(g.vg, "irls"), average(g.vg, "irls", rescue=False)
    lost = np.flatnonzero(_err_deg(without.R, g.R_true) > 30)
    assert lost.size >= 1 and np.all(_err_deg(with_rescue.R, g.R_true)[lost] < 2.0)
    assert set(with_rescue.stats["rescue"]["moved"]) >= {g.vg.names[k] for k in lost}
    assert with_rescue.stats["rescue"]["kept"] and without.stats["rescue"] is None
    assert np.median(_err_deg(with_rescue.R, g.R_true)) < 0.75 * np.median(_err_deg(without.R, g.R_true))
    # a block: 5 of camera 1's 30 edges wrong by one common rotation S (repeated structure): it is not moved there
    e1 = np.flatnonzero(np.any(vg.edges == 1, axis=1) & ~np.isin(np.arange(vg.n_edges), at0))
    R_rel = vg.R_rel.copy()
    S = so3.exp(np.array([0.0, 0.0, np.pi / 2]))
    R_rel[e1[:5]] = R_rel[e1[:5]] @ S
    vg2 = ViewGraph(vg.names, vg.edges, R_rel)
    theta2 = np.linalg.norm(edge_residuals(vg2.edges, vg2.R_rel, R), axis=1)
    assert 1 not in rescue_cameras(vg2, R, theta2, np.deg2rad(5.0)).cameras
    # two rival clusters (a symmetric building): 7 of camera 0's wrong edges become mirrored pairs, all wrong by one
    # half turn, against its 8 right ones: ambiguous, it is left where it is; with 3 mirrored, the right ones win
    n_right = at0.size - bad.size
    for n_mirror, moved in ((7, False), (3, True)):
        R_rel = vg.R_rel.copy()
        mirror = bad[:n_mirror]
        i, j = vg.edges[mirror, 0], vg.edges[mirror, 1]
        R_rel[mirror] = R[j] @ so3.exp(np.array([0.0, np.pi, 0.0])) @ np.swapaxes(R[i], 1, 2)
        vg3 = ViewGraph(vg.names, vg.edges, R_rel)
        theta3 = np.linalg.norm(edge_residuals(vg3.edges, vg3.R_rel, start), axis=1)
        res3 = rescue_cameras(vg3, start, theta3, np.deg2rad(5.0))
        assert n_right == 8 and (0 in res3.cameras) == moved
        if moved:
            assert np.rad2deg(so3.angle_between(res3.R[0], R[0])) < 0.5


def test_dense_factors_take_one_blas_thread_where_threads_gain_nothing_or_crash():
    """One BLAS thread below DENSE_SINGLE_THREAD_SIZE rows and above BLAS_THREADS_MAX_SIZE (OpenBLAS's threaded
    Cholesky dies with a segmentation fault from about 16,000 rows), every thread between."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import pipeline.averaging.kernel as kernel

    def blas_threads_inside(n: int) -> set[int]:
        with kernel.blas_threads(n):
            return {int(d["num_threads"]) for d in threadpool_info() if d["user_api"] == "blas"}

    with threadpool_limits(limits=2, user_api="blas"):  # two threads outside, so that one inside can be told apart
        outside = {int(d["num_threads"]) for d in threadpool_info() if d["user_api"] == "blas"}
        assert 2 in outside  # a single-threaded build (cvxpy's solvers bring one) stays at 1 whatever is asked
        assert blas_threads_inside(kernel.DENSE_SINGLE_THREAD_SIZE - 1) == {1}
        assert blas_threads_inside(kernel.BLAS_THREADS_MAX_SIZE + 1) == {1}
        assert blas_threads_inside(kernel.DENSE_SINGLE_THREAD_SIZE) == outside
        assert blas_threads_inside(kernel.BLAS_THREADS_MAX_SIZE) == outside
