"""After the SDP: refine the rounded rotations locally, and bound their suboptimality with a dual certificate.

- :func:`polish_rounding`: rounding the relaxation's ``X`` gives rotations near, not at, a
  minimizer of the cost when the solver stopped early; they are refined by Riemannian
  Newton on the same cost (as SE-Sync does) when that lowers it. Any rotations give a valid
  primal cost and the lower bound is the solver's, so the gap can only shrink.
- :func:`dual_certificate_gap`: the conic solver's dual point is only as accurate as the
  solver; the dual certificate of :mod:`pipeline.averaging.certificate`, built exactly from
  the rotations' own stationarity (with paper 2's conv(SO(3)) multipliers for an
  anisotropic cost), proves a gap bound that can be far sharper. Either bound proves the
  same statement: the rotations are the global optimum of the cost to within the gap.
- :func:`verified_start`: the same certificate asked of a start (the robust stage's rotations,
  polished on the SDP's cost) before any conic solve: where it proves them optimal, the conic
  program need not run (SE-Sync's way).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from pipeline.averaging.certificate import UNDECIDED, VERIFIED, certify
from pipeline.averaging.certificate.newton import polish
from pipeline.averaging.certificate.problem import diag_blocks
from pipeline.averaging.sdp.certificate import edge_cost, relative_gap, resolution_check
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["polish_rounding", "dual_certificate_gap", "verified_start"]


def _metrics(vg: ViewGraph, C: np.ndarray) -> np.ndarray:
    """``M_e`` (M, 3, 3) of the cost ``−Σ ⟨C_e, R_j R_iᵀ⟩`` with ``C_e = M_e R̃_e``."""
    M = C @ np.swapaxes(vg.R_rel, 1, 2)
    return 0.5 * (M + np.swapaxes(M, 1, 2))


def polish_rounding(vg: ViewGraph, C: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The rotations ``R`` (N, 3, 3) refined by Newton on ``−Σ ⟨C_e, R_j R_iᵀ⟩``, if that lowers the cost.

    Returns:
        ``(R, largest move in degrees)``, or None when the polish does not lower the cost.
    """
    D = diag_blocks(vg.n_cameras, vg.edges, _metrics(vg, C))
    try:
        Rp, _ = polish(vg.n_cameras, vg.edges, C, D, R, max_iterations=10)
    except (np.linalg.LinAlgError, RuntimeError, ValueError):
        return None
    if not np.all(np.isfinite(Rp)) or edge_cost(vg.edges, C, Rp) >= edge_cost(vg.edges, C, R):
        return None
    Rp = so3.project_to_so3(Rp)
    return Rp, float(np.rad2deg(so3.angle_between(Rp, R).max()))


def dual_certificate_gap(vg: ViewGraph, C: np.ndarray, scale: float, R: np.ndarray, target: float,
                         use_lmi: bool | None = None) -> float | None:
    """A proven bound on ``f(R) − f*`` (unscaled units) from the dual certificate, or None if not verified.

    Args:
        vg: the view graph of the SDP.
        C: (M, 3, 3) its scaled weighted measurements (``M_e R̃_e / scale``).
        scale: the cost scale (costs in the unscaled units are ``scale`` × the scaled ones).
        R: (N, 3, 3) the rotations to certify.
        target: the gap (unscaled) the caller needs; the certificate is asked for that much.
        use_lmi: the conv(SO(3)) multipliers (None: where the cost is anisotropic; False for a relaxation
            without those constraints, SDP-O(3)-ANISO, whose dual has no such multipliers).
    """
    # the certificate's cost is Σ 2 (tr M_e − ⟨M_e R̃_e, Q_e⟩): twice the SDP's residual cost, scaled
    M = _metrics(vg, C)
    trace = 2.0 * float(np.trace(M, axis1=1, axis2=2).sum())
    f_res = 2.0 * edge_cost(vg.edges, C, R) + trace
    want = 0.9 * 2.0 * target / scale  # 0.9: a verified bound stays clear of the target
    if not (np.isfinite(f_res) and f_res > 0 and want > 0):
        return None
    # certify proves gap_tol · f_res plus its cost's rounding level (1e3·ε·Σ_i tr D_i, Σ_i tr D_i = 2 Σ_e tr M_e):
    # first ask for what is left of the target after that level; where S's own rounding floor keeps that from
    # being proven, the whole target still gives a proven bound (above the target, but maybe below the solver's)
    room = want - 1e3 * np.finfo(float).eps * trace
    for tol in dict.fromkeys(min(t / f_res, 0.5) for t in (room, want) if t > 0):
        try:
            cert, _ = certify(vg.n_cameras, vg.edges, vg.R_rel, R, np.ones(vg.n_edges), M, gap_tol=tol,
                              do_polish=False, k_margin=0, use_lmi=use_lmi)
        except (np.linalg.LinAlgError, RuntimeError, ValueError):
            return None
        if cert.verdict == VERIFIED:
            return float(cert.gap_bound * scale / 2.0)
        if cert.verdict != UNDECIDED:  # "not verified": a negative direction, which another η does not remove
            return None
    return None


def verified_start(start: np.ndarray, vg: ViewGraph, C: np.ndarray, scale: float, offset: float, cso3: bool,
                    lmi_edges: np.ndarray | None, kappa: float, polish: bool) -> dict[str, Any] | None:
    """``start`` polished on the SDP's cost and proven its global optimum by its dual certificate, or None.

    This is how SE-Sync solves its SDP: a local solution of the rank-3 problem, then the dual
    certificate of :mod:`pipeline.averaging.certificate` (with the conv(SO(3)) multipliers only
    where the relaxation has them, ``cso3``). If it proves a gap within the same resolution test a
    conic solve must pass, ``X = YYᵀ`` of these rotations solves the SDP to that gap, and the conic
    program (minutes by SCS at 50 cameras) need not run; otherwise the caller solves it. The
    robust stage's rotations on the calibrated cost are already its stationary point (the polish
    moves them by ~1e-3°). Returns an attempt record as :func:`pipeline.averaging.sdp.solve._attempt`'s (no
    solver: ``solver`` "none", 0 iterations).
    """
    if not polish:  # the caller asked for the solver's answer alone
        return None
    t0 = time.perf_counter()
    R, move = start, 0.0
    polished = polish_rounding(vg, C, start)
    if polished is not None:
        R, move = polished
    primal_cost = edge_cost(vg.edges, C, R) * scale
    need = resolution_check(0.0, primal_cost, offset, vg.n_cameras, vg.n_edges, 3, kappa)
    gap_abs = dual_certificate_gap(vg, C, scale, R, kappa * need["resolution"] + need["cost_rounding"],
                                   use_lmi=None if cso3 else False)
    if gap_abs is None:
        return None
    check = resolution_check(gap_abs, primal_cost, offset, vg.n_cameras, vg.n_edges, 3, kappa)
    if not check["certified"]:
        return None
    n = vg.n_cameras
    return {
        "solver": "none", "form": None, "R": R, "rank": 3, "eigenvalues": [float(n)] * 3 + [0.0] * 3,  # X = YYᵀ
        "lower_bound": primal_cost - gap_abs, "sdp_value": primal_cost, "primal_cost": primal_cost,
        "gap": relative_gap(primal_cost, primal_cost - gap_abs), "gap_abs": gap_abs, **check,
        "certified_by": "the dual certificate of the robust stage's rotations polished on this cost, with no "
                        "conic solve",
        "status": "verified at the start", "iterations": 0, "dual_lambda_min": None, "build_s": 0.0,
        "solve_s": 0.0, "certificate_s": time.perf_counter() - t0, "n_variables": None, "n_constraints": None,
        "eps_abs": None, "eps_rel": None, "polish_move_deg": move,
    }
