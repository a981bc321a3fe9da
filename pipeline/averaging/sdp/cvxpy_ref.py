"""The SDP relaxations of paper 2 written plainly in cvxpy: the readable reference.

This states the primal SDP exactly as in paper 2 (SDP-O(3)-ISO, §3, and
SDP-cSO(3), §4.3), in the DESIGN.md convention ``X_ji = R_j R_iᵀ``:

    minimize    −Σ_edges ⟨C_e, X_ji⟩            (C_e = M_ij R̃_ij / s, or R̃_ij)
    subject to  X ⪰ 0,  X_ii = I,
                𝒜(X_ji) + I ⪰ 0 on every edge    (cSO(3) variants, eq. 27)

It builds the problem block by block, with a Python loop over edges, which is
what makes it slow: cvxpy's per-block expression building dominates the wall
time at N ≈ 100 (DESIGN.md). :func:`pipeline.averaging.sdp.solve.solve_sdp` builds the same
SDP directly; the tests check both reach the same optimum on small problems and
``benchmarks/sdp_lu_sphinx.py`` reports the speed-up.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from pipeline.averaging.result import AveragingResult
from pipeline.averaging.sdp.certificate import edge_cost, numerical_rank, relative_gap, round_to_rotations
from pipeline.averaging.sdp.conic import check_inputs, edge_weights
from pipeline.core.viewgraph import ViewGraph

__all__ = ["solve_sdp_cvxpy", "conv_so3_lmi_expr"]


def conv_so3_lmi_expr(Y: Any) -> Any:
    """``𝒜(Y) + I`` of paper 2, eq. 27, for a 3×3 cvxpy expression ``Y``."""
    import cvxpy as cp

    y = lambda a, b: Y[a - 1, b - 1]  # noqa: E731 - 1-based, as printed in the paper
    A = cp.bmat([
        [-y(1, 1) - y(2, 2) + y(3, 3), y(1, 3) + y(3, 1), y(1, 2) - y(2, 1), y(2, 3) + y(3, 2)],
        [y(1, 3) + y(3, 1), y(1, 1) - y(2, 2) - y(3, 3), y(2, 3) - y(3, 2), y(1, 2) + y(2, 1)],
        [y(1, 2) - y(2, 1), y(2, 3) - y(3, 2), y(1, 1) + y(2, 2) + y(3, 3), y(3, 1) - y(1, 3)],
        [y(2, 3) + y(3, 2), y(1, 2) + y(2, 1), y(3, 1) - y(1, 3), -y(1, 1) + y(2, 2) - y(3, 3)],
    ])
    return A + np.eye(4)


def solve_sdp_cvxpy(
    vg: ViewGraph,
    variant: str = "cso3",
    solver: str = "scs",
    eps_abs: float = 1e-5,
    eps_rel: float = 1e-6,
    verbose: bool = False,
) -> AveragingResult:
    """Solve one of the four SDP variants through cvxpy (reference, slow to build).

    Args:
        vg: connected view graph (with ``H`` for the anisotropic variants).
        variant: ``"cso3"``, ``"cso3-iso"``, ``"o3-iso"`` or ``"o3-aniso"``.
        solver: ``"scs"`` or ``"clarabel"`` (the cvxpy back end).
        eps_abs, eps_rel: tolerances passed to the back end.
        verbose: solver log.

    Returns:
        An :class:`AveragingResult` named ``"sdp-cvxpy-<variant>"``; ``stats`` has
        ``build_s`` (cvxpy expression building and compilation), ``solve_s``,
        ``sdp_value`` (the optimum, unscaled), ``rank``, ``primal_cost``, ``gap``.
    """
    import cvxpy as cp

    aniso, cso3 = check_inputs(vg, variant, solver)
    t0 = time.perf_counter()
    C, scale = edge_weights(vg, aniso)
    N = vg.n_cameras
    X = cp.Variable((3 * N, 3 * N), PSD=True)
    blk = lambda r, c: X[3 * r : 3 * r + 3, 3 * c : 3 * c + 3]  # noqa: E731
    constraints = [blk(i, i) == np.eye(3) for i in range(N)]
    terms = []
    for e, (i, j) in enumerate(vg.edges):
        terms.append(cp.sum(cp.multiply(C[e], blk(j, i))))
        if cso3:
            Z = cp.Variable((4, 4), PSD=True)
            constraints.append(Z == conv_so3_lmi_expr(blk(j, i)))
    problem = cp.Problem(cp.Minimize(-cp.sum(cp.hstack(terms))), constraints)
    if solver == "scs":
        opts = dict(eps_abs=eps_abs, eps_rel=eps_rel, eps_infeas=1e-8, max_iters=500_000)
        backend = cp.SCS
    else:
        opts = dict(tol_gap_abs=eps_abs, tol_gap_rel=eps_rel, tol_feas=eps_rel)
        backend = cp.CLARABEL
    problem.solve(solver=backend, verbose=verbose, **opts)
    t2 = time.perf_counter()
    # cvxpy compiles inside solve(); the back end's own time is reported separately.
    solve_s = float(problem.solver_stats.solve_time or 0.0)
    t1 = t2 - solve_s
    Xv = 0.5 * (X.value + X.value.T)
    R, lam = round_to_rotations(Xv)
    rank = numerical_rank(lam)
    sdp_value = float(problem.value) * scale
    primal_cost = edge_cost(vg.edges, C, R) * scale
    stats = {
        "variant": variant,
        "solver": solver,
        "build_s": t1 - t0,
        "solve_s": t2 - t1,
        "rank": rank,
        "eigenvalues": [float(v) for v in lam[:6]],
        "sdp_value": sdp_value,
        "primal_cost": primal_cost,
        "gap": relative_gap(primal_cost, sdp_value),
        "status": str(problem.status),
        "cost_scale": scale,
    }
    return AveragingResult(
        method=f"sdp-cvxpy-{variant}", names=list(vg.names), R=R, time_s=t2 - t0,
        edge_index=np.arange(vg.n_edges), stats=stats,
    )
