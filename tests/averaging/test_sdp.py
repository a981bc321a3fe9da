"""Tests of the SDP rotation averaging (paper 2): pipeline.averaging.sdp (conic, solve, certificate, cvxpy_ref)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.averaging.sdp.certificate import (
    edge_cost,
    numerical_rank,
    relative_gap,
    resolution_check,
    round_to_rotations,
    weight_matrices,
)
from pipeline.averaging.sdp.conic import (
    VARIANTS,
    build_conic,
    conv_so3_lmi,
    edge_weights,
    svec_index,
    unsvec,
)
from pipeline.averaging.sdp.solve import solve_sdp
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph


# ----------------------------------------------------------------- fixtures
def random_precisions(m: int, lo: float, hi: float, rng: np.random.Generator) -> np.ndarray:
    Q = so3.random_rotations(m, rng)
    lam = rng.uniform(lo, hi, (m, 3))
    return Q @ (lam[:, :, None] * np.swapaxes(Q, 1, 2))


def noisy_graph(n: int, p: float, seed: int, eig=(1.0, 10.0), noise: bool = True, cov_eig: bool = False):
    """Paper 2 §5.1 protocol in our convention: R̃_ij = exp([Δω]×) R_j R_iᵀ, Δω ~ N(0, H⁻¹).

    ``eig`` is the range of the eigenvalues of H, or of H⁻¹ when ``cov_eig``.
    """
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(n, rng)
    ii, jj = np.triu_indices(n, 1)
    keep = rng.random(ii.size) < p
    keep[np.flatnonzero(jj == ii + 1)] = True  # a path keeps the graph connected
    E = np.c_[ii, jj][keep]
    H = random_precisions(len(E), *eig, rng)
    if cov_eig:
        H = np.linalg.inv(H)
    R_rel = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    if noise:
        L = np.linalg.cholesky(np.linalg.inv(H))
        dw = (L @ rng.standard_normal((len(E), 3, 1)))[..., 0]
        R_rel = so3.exp(dw) @ R_rel
    vg = ViewGraph([f"c{k}" for k in range(n)], E, R_rel, H=H)
    return vg, R


def aligned_errors_deg(R_est: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """Per-camera angle after the ℓ2-optimal global rotation G: R_est ≈ R_ref G."""
    G = so3.project_to_so3(np.einsum("nji,njk->ik", R_ref, R_est))
    return np.degrees(so3.angle_between(R_est, R_ref @ G))


def frob_error(R_est: np.ndarray, R_ref: np.ndarray) -> float:
    """Paper 2's √Σ‖R_i − R_i*‖²_F after the optimal global alignment."""
    G = so3.project_to_so3(np.einsum("nji,njk->ik", R_ref, R_est))
    return float(np.sqrt(np.sum((R_est - R_ref @ G) ** 2)))


@pytest.fixture(scope="module")
def clean_graph():
    return noisy_graph(8, 0.5, seed=1, noise=False)


@pytest.fixture(scope="module")
def noisy():
    return noisy_graph(9, 0.5, seed=2)


# ------------------------------------------------------- building blocks
def test_conv_so3_lmi_is_rank_one_psd_on_rotations_and_rejects_reflections():
    rng = np.random.default_rng(0)
    Z = conv_so3_lmi(so3.random_rotations(20, rng))
    lam = np.linalg.eigvalsh(Z)
    assert np.all(lam[:, :3] > -1e-9) and np.allclose(lam[:, :3], 0, atol=1e-9)
    assert np.allclose(lam[:, 3], 4.0)  # tr(𝒜(R) + I) = 4 and rank 1
    # det −1 orthogonal matrices are outside conv(SO(3)): the LMI must fail
    refl = -so3.random_rotations(20, rng)
    assert np.all(np.linalg.eigvalsh(conv_so3_lmi(refl))[:, 0] < -1.0)
    # the centre of conv(SO(3)) (Y = 0) is strictly inside
    assert np.allclose(conv_so3_lmi(np.zeros((3, 3))), np.eye(4))


def test_svec_index_orders_match_each_solver_convention():
    n = 3
    p, q = np.tril_indices(n)
    # SCS: lower triangle column-major: (0,0),(1,0),(2,0),(1,1),(2,1),(2,2)
    scs_order = [(0, 0), (1, 0), (2, 0), (1, 1), (2, 1), (2, 2)]
    # Clarabel: upper triangle column-major: (0,0),(0,1),(1,1),(0,2),(1,2),(2,2) = (p>=q) row-major
    cla_order = [(0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2)]
    for solver, order in (("scs", scs_order), ("clarabel", cla_order)):
        idx = svec_index(p, q, n, solver)
        got = [None] * len(idx)
        for k, (a, b) in zip(idx, zip(p, q)):
            got[k] = (int(a), int(b))
        assert got == order, solver
    for solver in ("scs", "clarabel"):
        n = 7
        p, q = np.tril_indices(n)
        assert np.array_equal(np.sort(svec_index(p, q, n, solver)), np.arange(n * (n + 1) // 2))


@pytest.mark.parametrize("solver", ["scs", "clarabel"])
def test_unsvec_inverts_an_isometric_svec(solver):
    rng = np.random.default_rng(3)
    S = rng.standard_normal((6, 6))
    S = S + S.T
    p, q = np.tril_indices(6)
    v = np.zeros(21)
    v[svec_index(p, q, 6, solver)] = np.where(p == q, 1.0, np.sqrt(2)) * S[p, q]
    assert np.allclose(unsvec(v, 6, solver), S)
    assert np.isclose(v @ v, np.sum(S * S))  # ⟨svec A, svec B⟩ = ⟨A, B⟩


def test_weight_matrices_reproduce_the_quadratic_form_eq4():
    rng = np.random.default_rng(4)
    H = random_precisions(10, 0.5, 20.0, rng)
    M = weight_matrices(H)
    w = rng.standard_normal((10, 3))
    W = so3.hat(w)
    lhs = np.einsum("ni,nij,nj->n", w, H, w)
    rhs = np.trace(np.swapaxes(W, 1, 2) @ M @ W, axis1=1, axis2=2)
    assert np.allclose(lhs, rhs)
    assert np.allclose(weight_matrices(np.diag([1.0, 2.0, 3.0])[None]), np.diag([2.0, 1.0, 0.0]))


def test_numerical_rank_follows_the_999_rule():
    assert numerical_rank(np.array([1.0, 1.0, 1.0, 0.0, 0.0])) == 3
    assert numerical_rank(np.array([1.0, 1.0, 1.0, 0.01])) == 4  # 3/3.01 < 0.999
    assert numerical_rank(np.array([0.0005, 1.0, 1.0, 1.0])) == 3  # 3/3.0005 > 0.999
    assert numerical_rank(np.array([2.0, 1.0, -1e-9])) == 2


def test_round_to_rotations_recovers_rotations_up_to_gauge_and_fixes_the_sign():
    rng = np.random.default_rng(5)
    R = so3.random_rotations(6, rng)
    Y = R.reshape(18, 3)
    R_hat, lam = round_to_rotations(Y @ Y.T)
    assert np.allclose(lam[:3], 6.0) and np.allclose(lam[3:], 0.0, atol=1e-9)
    assert np.all(np.linalg.det(R_hat) > 0)
    assert aligned_errors_deg(R_hat, R).max() < 1e-6
    with pytest.raises(ValueError, match=r"expected \(3N, 3N\)"):
        round_to_rotations(np.eye(4))


def test_direct_build_objective_matches_the_cost_definition(noisy):
    """cᵀ svec(YYᵀ) of the primal form equals −Σ⟨C_e, R_j R_iᵀ⟩ for both svec conventions."""
    vg, R = noisy
    C, _ = edge_weights(vg, anisotropic=True)
    X = R.reshape(-1, 3) @ R.reshape(-1, 3).T
    n = X.shape[0]
    p, q = np.tril_indices(n)
    for solver in ("scs", "clarabel"):
        prob = build_conic(vg.n_cameras, vg.edges, C, cso3=True, solver=solver, form="primal")
        x = np.zeros(prob.m_big)
        x[svec_index(p, q, n, solver)] = np.where(p == q, 1.0, np.sqrt(2)) * X[p, q]
        assert np.isclose(prob.c @ x, edge_cost(vg.edges, C, R))
        # the point YYᵀ is feasible: equalities hold and every cone slack is PSD
        s = prob.b - prob.A @ x
        assert np.allclose(s[: prob.n_zero], 0)
        Z = s[prob.n_zero + prob.m_big:].reshape(-1, 10)
        pk, pl = np.tril_indices(4)
        for k in range(3):  # a few edges: rebuild the 4×4 slack and check it is 𝒜(X_ji) + I
            i, j = vg.edges[k]
            Zk = unsvec(Z[k], 4, solver)
            assert np.allclose(Zk, conv_so3_lmi(R[j] @ R[i].T), atol=1e-9)


# ------------------------------------------------------------ solutions
@pytest.mark.parametrize("solver", ["scs", "clarabel"])
@pytest.mark.parametrize("variant", ["cso3", "cso3-iso", "o3-iso"])
def test_noise_free_input_gives_exact_rotations_rank3_and_zero_gap(clean_graph, variant, solver):
    vg, R = clean_graph
    res = solve_sdp(vg, variant, solver)
    st = res.stats
    assert st["rank"] == 3
    # Certified means a gap small against what the cost resolves (issue 15). Exact data resolve
    # everything (resolution ≈ 0): only a solve to the cost's rounding is certified, which the
    # isotropic variants reach; whether cso3's re-solve does is the solver's, not asserted (it stopped
    # at 56× the rounding when measured). Whatever the verdict, it follows the rule, and the
    # rotations are exact (below).
    if variant != "cso3":
        assert st["certified"], st
    assert st["certified"] == (st["gap_abs"] <= 0.01 * st["resolution"] + st["cost_rounding"])
    assert 0 <= st["gap"] < 1e-5 or abs(st["gap"]) < 1e-6
    assert aligned_errors_deg(res.R, R).max() < 0.05
    # at the truth every term is −tr(M_ij) (aniso) or −3 (iso): the optimum is known exactly
    expected = -np.sum(np.trace(weight_matrices(vg.H), axis1=1, axis2=2)) if variant == "cso3" else -3.0 * vg.n_edges
    assert np.isclose(st["primal_cost"], expected, rtol=1e-6)
    assert st["lower_bound"] <= st["primal_cost"] + 1e-9 * abs(expected)
    assert res.method == f"sdp-{variant}" and res.R.shape == (vg.n_cameras, 3, 3)
    assert res.residuals_rad.shape == (vg.n_edges,)
    for key in ("build_s", "solve_s", "rank", "lower_bound", "primal_cost", "gap", "certified",
                "status", "solver_iterations", "eigenvalues"):
        assert key in st


def test_o3_aniso_is_not_tight_and_says_so(caplog):
    """Paper 2, Theorem 1 / Fig. 2: without conv(SO(3)) the anisotropic relaxation is not tight.

    Fig. 2's setting: inverse-Hessian eigenvalues in [0.1, 1].
    """
    vg, R = noisy_graph(12, 0.5, seed=0, eig=(0.1, 1.0), cov_eig=True)
    with caplog.at_level(logging.WARNING, logger="pipeline.averaging.sdp.solve"):
        res = solve_sdp(vg, "o3-aniso", "scs")
    assert res.stats["rank"] > 3
    assert res.stats["certified"] is False
    assert f"NOT certified optimal: rank {res.stats['rank']} (need 3); gap " in caplog.text  # the failed test first


def test_lower_bound_is_below_the_cost_of_any_rotations(noisy):
    vg, R = noisy
    res = solve_sdp(vg, "cso3", "scs")
    C, s = edge_weights(vg, anisotropic=True)
    st = res.stats
    truth_cost = edge_cost(vg.edges, C, R) * s
    assert st["lower_bound"] <= truth_cost
    assert st["lower_bound"] <= st["primal_cost"]
    assert st["certified"] and st["rank"] == 3 and st["gap"] < 1e-5
    # the noisy optimum fits the data better than the truth does
    assert st["primal_cost"] <= truth_cost
    # the reported gap is (f(R̂) − d*)/|d*|, computed here from its parts
    assert st["gap"] == pytest.approx((st["primal_cost"] - st["lower_bound"]) / abs(st["lower_bound"]), rel=1e-9)
    assert relative_gap(2.0, -4.0) == pytest.approx(1.5) and relative_gap(1.0, 1.0) == 0.0


def test_resolution_check_certifies_rank_three_within_a_share_of_the_resolution():
    """certified ⇔ rank 3 and gap ≤ κ·ρ·f_res + the cost's rounding, with ρ = (N − 1)/(M − N + 1) and
    f_res = f(R̂) + offset; the figures it returns, recomputed here."""
    N, M, primal, offset = 11, 31, -80.0, 100.0  # f_res = 20, ρ = 10/21
    res = 10 / 21 * 20.0
    floor = 1e3 * np.finfo(float).eps * 100.0
    ok = resolution_check(0.005 * res, primal, offset, N, M, rank=3)
    assert ok["certified"] and ok["resolution"] == pytest.approx(res) and ok["cost_rounding"] == pytest.approx(floor)
    assert ok["gap_vs_resolution"] == pytest.approx(0.005) and ok["gap_residual"] == pytest.approx(0.005 * res / 20)
    assert not resolution_check(0.02 * res, primal, offset, N, M, rank=3)["certified"]  # above κ = 1%
    assert not resolution_check(0.0, primal, offset, N, M, rank=4)["certified"]  # a zero gap does not make rank 4 tight
    exact = resolution_check(0.5 * floor, -offset, offset, N, M, rank=3)  # exact data: f_res = 0, only the rounding
    assert exact["certified"] and exact["resolution"] == 0.0
    assert not resolution_check(2 * floor, -offset, offset, N, M, rank=3)["certified"]


@pytest.mark.parametrize("form", ["primal", "dual"])
@pytest.mark.parametrize("solver", ["scs", "clarabel"])
def test_primal_and_dual_forms_reach_the_same_optimum(noisy, form, solver):
    vg, _ = noisy
    ref = solve_sdp(vg, "cso3", "clarabel", form="dual", eps_abs=1e-8, eps_rel=1e-8)
    res = solve_sdp(vg, "cso3", solver, form=form)
    assert res.stats["form"] == form
    assert res.stats["lower_bound"] == pytest.approx(ref.stats["lower_bound"], rel=1e-5)
    assert aligned_errors_deg(res.R, ref.R).max() < 0.05


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["scs", "clarabel"])
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_direct_build_matches_the_cvxpy_reference(noisy, variant, solver):
    from pipeline.averaging.sdp.cvxpy_ref import solve_sdp_cvxpy

    vg, _ = noisy
    ref = solve_sdp_cvxpy(vg, variant, solver)
    res = solve_sdp(vg, variant, solver)
    assert ref.stats["status"] == "optimal"
    assert res.stats["sdp_value"] == pytest.approx(ref.stats["sdp_value"], rel=2e-5)
    assert res.stats["lower_bound"] == pytest.approx(ref.stats["sdp_value"], rel=2e-5)
    assert res.stats["rank"] == ref.stats["rank"]
    if res.stats["rank"] == 3:
        assert aligned_errors_deg(res.R, ref.R).max() < 0.05


# ---------------------------------------------- paper 2, supplement C.1
def c1_instance(sigma: float, seed: int, eps: float = 1e-3):
    """Three cameras, two 'certain' edges (covariance εI) and one with covariance diag(σ, ε, ε)."""
    rng = np.random.default_rng(seed)
    R = so3.random_rotations(3, rng)
    E = np.array([[0, 1], [0, 2], [1, 2]])
    cov = np.array([np.eye(3) * eps, np.eye(3) * eps, np.diag([sigma, eps, eps])])
    dw = (np.linalg.cholesky(cov) @ rng.standard_normal((3, 3, 1)))[..., 0]
    R_rel = so3.exp(dw) @ R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    return ViewGraph(["a", "b", "c"], E, R_rel, H=np.linalg.inv(cov)), R


def test_c1_anisotropic_error_stays_flat_and_would_catch_a_transposed_block():
    """Paper 2, supplement C.1: noise along one axis of one edge.

    The anisotropic solution must ignore that axis (error as with small σ); the isotropic
    one must not. Feeding the precision in the wrong frame (what a transposed block or a
    right-instead-of-left perturbation does, ``R̃ H R̃ᵀ``) must break it. ε = 1e-5 (the
    paper uses 1e-3) makes the certain edges certain enough for a sharp test.
    """
    eps = 1e-5
    med = {}
    for sigma in (0.01, 0.3):
        aniso, iso, wrong = [], [], []
        for seed in range(12):
            vg, R = c1_instance(sigma, seed, eps)
            aniso.append(frob_error(solve_sdp(vg, "cso3").R, R))
            iso.append(frob_error(solve_sdp(vg, "o3-iso").R, R))
            H_wrong = vg.H.copy()
            H_wrong[2] = vg.R_rel[2] @ vg.H[2] @ vg.R_rel[2].T
            wrong.append(frob_error(solve_sdp(vg.with_H(H_wrong), "cso3").R, R))
        med[sigma] = [float(np.median(v)) for v in (aniso, iso, wrong)]
    aniso, iso, wrong = med[0.3]
    assert aniso < 0.02  # ≈ the error of the two certain edges alone
    assert aniso < 1.5 * med[0.01][0]  # flat in σ
    assert iso > 5 * aniso and iso > 3 * med[0.01][1]  # the isotropic error grows
    assert wrong > 3 * aniso


# ------------------------------------------------------------ bad input
def test_anisotropic_variants_without_H_are_rejected(clean_graph):
    vg, _ = clean_graph
    no_H = vg.with_H(None)
    for variant in ("cso3", "o3-aniso"):
        with pytest.raises(ViewGraphError, match="needs a precision H_ij on every edge"):
            solve_sdp(no_H, variant)
    # the isotropic ones do not need H
    assert solve_sdp(no_H, "cso3-iso").stats["certified"]


def test_H_not_positive_definite_is_rejected(clean_graph):
    vg, _ = clean_graph
    H = vg.H.copy()
    H[0] = np.diag([1.0, 1.0, -0.5])
    with pytest.raises(ViewGraphError, match="not positive definite"):
        solve_sdp(vg.with_H(H), "cso3")


def test_disconnected_graph_is_rejected():
    rng = np.random.default_rng(7)
    R = so3.random_rotations(6, rng)
    vg = ViewGraph.from_absolute([str(k) for k in range(6)], R, [[0, 1], [1, 2], [3, 4], [4, 5]])
    with pytest.raises(ViewGraphError, match="not connected.*largest_component"):
        solve_sdp(vg, "cso3-iso")


def test_unknown_variant_solver_and_form_are_rejected(clean_graph):
    vg, _ = clean_graph
    with pytest.raises(ValueError, match="unknown SDP variant 'so3'"):
        solve_sdp(vg, "so3")
    with pytest.raises(ValueError, match="unknown SDP solver 'mosek'"):
        solve_sdp(vg, "cso3", solver="mosek")
    with pytest.raises(ValueError, match="unknown conic form"):
        solve_sdp(vg, "cso3", form="both")
    with pytest.raises(ValueError, match=r"unknown SCS setting\(s\) \['nonsense'\]"):
        solve_sdp(vg, "cso3", solver="scs", nonsense=1)
    with pytest.raises(ValueError, match="unknown Clarabel setting 'nonsense'"):
        solve_sdp(vg, "cso3", solver="clarabel", nonsense=1)


def test_lmis_on_all_pairs_give_a_relaxation_at_least_as_strong():
    vg, R_true = noisy_graph(10, 0.4, seed=11, eig=(0.1, 1.0), cov_eig=True)
    edges_only = solve_sdp(vg, "cso3", "clarabel", eps_abs=1e-9, eps_rel=1e-9)
    all_pairs = solve_sdp(vg, "cso3", "clarabel", eps_abs=1e-9, eps_rel=1e-9, lmi_pairs="all")
    assert all_pairs.stats["n_constraints"] > edges_only.stats["n_constraints"]
    assert all_pairs.stats["lower_bound"] >= edges_only.stats["lower_bound"] - 1e-6 * abs(edges_only.stats["lower_bound"])
    # ... and still a relaxation: no bound above the cost of a feasible point (either solution, or the truth)
    C, sc = edge_weights(vg, anisotropic=True)
    f_true = edge_cost(vg.edges, C, R_true) * sc
    for res in (edges_only, all_pairs):
        tol = 1e-6 * abs(res.stats["primal_cost"])
        assert res.stats["lower_bound"] <= min(edges_only.stats["primal_cost"], all_pairs.stats["primal_cost"], f_true) + tol
    with pytest.raises(ValueError, match="lmi_pairs='some'"):
        solve_sdp(vg, "cso3", lmi_pairs="some")


# ------------------------------------------- heterogeneous H (issue 4, temple)
@pytest.fixture(scope="module")
def one_huge_edge():
    """Edge 0's H is 1e4× the others' (like a zero-baseline pair): the constant −Σ tr M_e of
    the cost is then ~1e4× the residual part that fixes the rotations."""
    vg, R = noisy_graph(10, 0.4, seed=3, eig=(10.0, 100.0))
    H = vg.H.copy()
    H[0] *= 1e4
    return vg.with_H(H), R


def test_one_huge_H_defeats_a_default_tolerance_solve(one_huge_edge, caplog):
    # Negative control for the fallback below: the same SDP at the default tolerance stops on
    # the interior of the optimal face (high rank) and is not certified.
    vg, _ = one_huge_edge
    with caplog.at_level(logging.WARNING):
        res = solve_sdp(vg, "cso3", "clarabel", fallback=False, polish=False)  # the rounding as it comes
    assert res.stats["rank"] > 3 and not res.stats["certified"] and not res.stats["fallback"]
    assert "NOT certified" in caplog.text


def test_one_huge_H_is_certified_by_the_tight_fallback(one_huge_edge):
    vg, R_true = one_huge_edge
    res = solve_sdp(vg, "cso3", "clarabel", polish=False)
    st = res.stats
    assert st["fallback"] and st["first_attempt"]["rank"] > 3
    assert st["rank"] == 3 and st["certified"]
    # the gap is small against the residual part of the cost, not only against |d*| ≈ Σ tr M
    assert st["gap_residual"] < 1e-2
    assert st["cost_offset"] == pytest.approx(np.sum(np.trace(weight_matrices(vg.H), axis1=1, axis2=2)))
    # a global optimum costs no more than the ground truth, and its bound is below both
    M = weight_matrices(vg.H)
    truth_cost = edge_cost(vg.edges, M @ vg.R_rel, R_true)
    assert st["lower_bound"] <= st["primal_cost"] <= truth_cost
    # rounding found the minimizer: a cSO(3) optimum with errors like the noise (a few degrees)
    assert np.median(aligned_errors_deg(res.R, R_true)) < 6.0
    # issue 15: the high-rank rounding, polished on the same cost, is certified by the dual certificate of
    # the rotations themselves, without the re-solve; the same minimizer
    pol = solve_sdp(vg, "cso3", "clarabel")
    assert pol.stats["certified"] and not pol.stats["fallback"]
    assert pol.stats["certified_by"] == "the dual certificate of the rounded rotations"
    assert pol.stats["primal_cost"] <= st["primal_cost"] + 1e-6 * abs(st["primal_cost"])
    assert aligned_errors_deg(pol.R, res.R).max() < 0.05


def test_an_uncertified_result_names_the_test_it_failed_first() -> None:
    """Fountain's message named a passing rank first ("rank 3 (need 3), gap 0.0205× ...") before the failing gap."""
    from pipeline.averaging.sdp.solve import _failed_tests  # noqa: PLC0415

    att = {"rank": 3, "gap_vs_resolution": 0.0205, "status": "solved"}
    assert _failed_tests(att, 0.01) == ("gap 0.0205 × the cost's resolution (need <= 0.01); rank 3, solver status "
                                        "solved")
    att = {"rank": 5, "gap_vs_resolution": 0.001, "status": "solved"}
    assert _failed_tests(att, 0.01).startswith("rank 5 (need 3); gap 0.001 ×")
