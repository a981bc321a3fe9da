"""Certifiable SDP rotation averaging (paper 2), solved directly with SCS or Clarabel.

:func:`solve_sdp` builds the relaxation (:mod:`pipeline.averaging.sdp.conic`), solves
it, recovers a dual-feasible lower bound (:func:`extract`), rounds ``X`` to rotations
and certifies them (:mod:`pipeline.averaging.sdp.certificate`). A small problem that
the first solve leaves uncertified, or certified with a gap that is a sizeable share
of the residual cost, is solved again by Clarabel at a tight tolerance (the
fallback); the problem itself is never changed. Every option is a field of
:class:`SdpConfig`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline.averaging.result import AveragingResult, method_config
from pipeline.averaging.sdp.certificate import (
    CERT_KAPPA,
    edge_cost,
    numerical_rank,
    relative_gap,
    resolution_check,
    round_to_rotations,
    weight_matrices,
)
from pipeline.averaging.sdp.conic import SOLVERS, VARIANTS, ConicProblem, build_conic, check_inputs, edge_weights, unsvec
from pipeline.averaging.sdp.refine import dual_certificate_gap, polish_rounding, verified_start
from pipeline.core import so3
from pipeline.core.config import Config, option
from pipeline.core.errors import ConfigError, PipelineError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["SdpConfig", "solve_sdp", "extract", "resolution_check", "CERT_KAPPA", "FALLBACK_MAX_CAMERAS", "FALLBACK_EPS", "FALLBACK_MAX_ITERS",
           "FALLBACK_SCS_MAX_ITERS", "FALLBACK_RESIDUAL_GAP"]

logger = logging.getLogger(__name__)

#: Largest N for which an uncertified solve is retried with Clarabel at FALLBACK_EPS. Its cost
#: grows fast: with one huge H, N = 30 (M = 160) took 17 s CPU and 0.43 GB, N = 50 (M ≈ 370)
#: over 47 s CPU and 3.5 GB without finishing (notes/issue-4.md, "Temple: heterogeneous H").
FALLBACK_MAX_CAMERAS = 30
FALLBACK_EPS = 1e-12
FALLBACK_MAX_ITERS = 400
#: SCS iteration cap when the Clarabel fallback is available (N ≤ FALLBACK_MAX_CAMERAS) and the
#: caller set none. Well-conditioned problems need a few hundred iterations (fountain-P11: 600,
#: rendered scenes: ~300); templeSparseRing's one huge H took SCS 46 850 iterations (34 s) to a
#: rank-24 uncertified answer that Clarabel then fixed in 0.1 s. A capped SCS run that has not
#: converged is handed to the fallback (Clarabel at N ≤ 30: at most a few seconds).
FALLBACK_SCS_MAX_ITERS = 2000
#: A solve whose gap exceeds this share of the residual cost (plus the requested relative
#: accuracy of |d*|) is re-solved as an uncertified one is.
FALLBACK_RESIDUAL_GAP = 1e-2
_SCS_SETTINGS = {
    "normalize", "scale", "adaptive_scale", "rho_x", "max_iters", "eps_abs", "eps_rel", "eps_infeas",
    "alpha", "time_limit_secs", "verbose", "acceleration_lookback", "acceleration_interval",
    "warm_start", "write_data_filename", "log_csv_filename", "use_indirect", "mkl",
}



@dataclass(frozen=True, kw_only=True)
class SdpConfig(Config):
    """Options of :func:`solve_sdp` (the ``sdp`` method; YAML section ``sdp``)."""

    SECTION = "sdp"
    variant: str = option("cso3", "relaxation: cso3 (SDP-cSO(3)), cso3-iso, o3-iso or o3-aniso")
    solver: str = option("scs", "conic solver: scs or clarabel")
    eps_abs: float = option(1e-5, "absolute solver tolerance (paper 2, §5)", gt=0)
    eps_rel: float = option(1e-6, "relative solver tolerance (paper 2, §5)", gt=0)
    max_iterations: int | None = option(None, "solver iteration cap (null: 500 000 for SCS as in paper 2, "
                                              "200 for Clarabel)", ge=1)
    cert_kappa: float = option(CERT_KAPPA, "a rank-3 solution is certified when its gap is at most this share "
                                           "of the cost's resolution (gap_residual <= kappa·ρ)", gt=0)
    edges: str = option("robust", "the edges the SDP sees: robust (those the robust stage keeps) or all")
    robust_method: str = option("auto", "the robust stage: irls-h, irls or auto (irls-h when the cost is "
                                        "anisotropic)")
    cost: str = option("calibrated", "robust edges, anisotropic variants: calibrated (the robust stage's final "
                                     "precisions) or raw (the two-view H)")
    keep: str = option("auto", "robust edges: posterior (inlier posterior >= 0.5), weight (and a normalized "
                               "residual <= 3) or auto (weight for the raw cost, else posterior)")
    form: str | None = option(None, "conic statement: primal or dual (null: primal for SCS, dual for Clarabel)")
    lmi_pairs: str = option("edges", "pairs with the conv(SO(3)) LMI: edges (observed pairs) or all")
    fallback: bool = option(True, "re-solve a small uncertified or loose problem with Clarabel at 1e-12")
    polish: bool = option(True, "refine the rounded rotations by Newton on the same cost (never raises it) and "
                                "bound them by their own dual certificate too (false: the solver's answer alone)")
    certify_start: bool = option(True, "robust edges: first polish the robust stage's rotations on the SDP's cost "
                                       "and test their dual certificate; when it proves them optimal as a solve's "
                                       "would be, the conic program is not solved (SE-Sync's verification; needs "
                                       "polish; false: always solve it)")
    fallback_max_cameras: int = option(FALLBACK_MAX_CAMERAS, "largest N for the fallback", ge=0)
    fallback_scs_max_iterations: int | None = option(
        FALLBACK_SCS_MAX_ITERS, "SCS cap when the fallback applies and max_iterations is null; "
        "an unsolved problem goes to the fallback (null: no cap)", ge=1)
    solver_log: bool = option(False, "print the conic solver's log", runtime=True)

    def check(self) -> None:
        if self.variant not in VARIANTS:
            raise ConfigError(f"unknown SDP variant {self.variant!r}; expected one of {sorted(VARIANTS)}")
        if self.solver not in SOLVERS:
            raise ConfigError(f"unknown SDP solver {self.solver!r}; expected one of {list(SOLVERS)}")
        if self.form not in (None, "primal", "dual"):
            raise ConfigError(f"unknown conic form {self.form!r}; expected 'primal' or 'dual'")
        if self.lmi_pairs not in ("edges", "all"):
            raise ConfigError(f"lmi_pairs={self.lmi_pairs!r} but expected 'edges' (observed pairs) or 'all'")
        for key, allowed in (("edges", ("robust", "all")), ("robust_method", ("auto", "irls-h", "irls")),
                             ("cost", ("calibrated", "raw")), ("keep", ("auto", "posterior", "weight"))):
            if getattr(self, key) not in allowed:
                raise ConfigError(f"[sdp] {key}={getattr(self, key)!r} but expected one of {list(allowed)}")


def _solve_scs(prob: ConicProblem, eps_abs: float, eps_rel: float, max_iters: int | None,
               verbose: bool, **kw: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, int]:
    import scs

    cone = {"z": prob.n_zero, "s": [prob.n_big] + [4] * prob.n_small}
    settings = dict(eps_abs=eps_abs, eps_rel=eps_rel, eps_infeas=1e-8, verbose=verbose,
                    max_iters=500_000 if max_iters is None else int(max_iters))
    unknown = sorted(set(kw) - _SCS_SETTINGS)
    if unknown:
        raise ValueError(f"unknown SCS setting(s) {unknown}; allowed: {sorted(_SCS_SETTINGS)}")
    settings.update(kw)
    solver = scs.SCS({"P": None, "A": prob.A, "b": prob.b, "c": prob.c}, cone, **settings)
    sol = solver.solve()
    info = sol["info"]
    return sol["x"], sol["y"], sol["s"], str(info["status"]), int(info["iter"])


def _failed_tests(att: dict[str, Any], kappa: float) -> str:
    """The certificate's test an attempt failed, named first (rank, then the gap), then the other and the status."""
    rank = f"rank {att['rank']} (need 3)"
    gap = f"gap {att['gap_vs_resolution']:.3g} × the cost's resolution (need <= {kappa:g})"
    first, then = (rank, gap) if att["rank"] != 3 else (gap, "rank 3")
    return f"{first}; {then}, solver status {att['status']}"


def _solve_clarabel(prob: ConicProblem, eps_abs: float, eps_rel: float, max_iters: int | None,
                    verbose: bool, **kw: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, int]:
    import clarabel

    settings = clarabel.DefaultSettings()
    settings.verbose = verbose
    settings.tol_gap_abs = eps_abs
    settings.tol_gap_rel = eps_rel
    settings.tol_feas = eps_rel
    settings.max_iter = 200 if max_iters is None else int(max_iters)
    for key, value in kw.items():
        if not hasattr(settings, key):
            raise ValueError(f"unknown Clarabel setting {key!r}; see clarabel.DefaultSettings")
        setattr(settings, key, value)
    cones = [clarabel.ZeroConeT(prob.n_zero)] if prob.n_zero else []
    cones += [clarabel.PSDTriangleConeT(prob.n_big)] + [clarabel.PSDTriangleConeT(4)] * prob.n_small
    P = sp.csc_matrix((prob.A.shape[1], prob.A.shape[1]))
    solver = clarabel.DefaultSolver(P, prob.c, prob.A, prob.b, cones, settings)
    sol = solver.solve()
    return (np.asarray(sol.x), np.asarray(sol.z), np.asarray(sol.s), str(sol.status), int(sol.iterations))


def extract(prob: ConicProblem, x: np.ndarray, y: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The SDP solution ``X`` and a dual-feasible lower bound from the solver's output.

    The dual point ``(Υ, W)`` is read from the solver (``W_e`` from a cone vector,
    PSD by construction), the slack ``S = blkdiag(Υ) − Ñ − Σ E_e(𝒜*(W_e))`` is
    recomputed exactly, and if ``λ_min(S) < 0`` every ``Υ_ii`` is raised by
    ``|λ_min|`` so that ``S ⪰ 0``. The dual objective of that point,
    ``−tr Υ − Σ tr W_e``, is a lower bound on the SDP optimum and so on the
    rotation-averaging cost (weak duality), whatever the solver's accuracy.

    Returns:
        X: (3N, 3N) primal solution.
        lower_bound: in the solver's (scaled) units.
        lam_min: ``λ_min(S)`` before the shift (≈ 0 at an accurate solution).
    """
    n, m_big, z = prob.n_big, prob.m_big, prob.n_zero
    if prob.form == "dual":
        X = unsvec(y[:m_big], n, prob.solver)
        xd = np.array(x, dtype=np.float64)
        if prob.n_small:
            xd[2 * n:] = s[m_big:]  # the 6N Υ entries come first (n = 3N)
        S_vec = prob.b[:m_big] - prob.A[:m_big] @ xd
        dual_obj = -(prob.c @ xd)
    else:
        X = unsvec(x, n, prob.solver)
        yd = np.array(y, dtype=np.float64)
        # Dual feasibility Aᵀy + c = 0 with A_big = −I gives svec(S) = y_big exactly:
        S_vec = prob.A[:z].T @ yd[:z] + prob.c
        if prob.n_small:
            S_vec = S_vec + prob.A[z + m_big:].T @ yd[z + m_big:]
        dual_obj = -(prob.b[:z] @ yd[:z]) - prob.b[z + m_big:] @ yd[z + m_big:]
    lam_min = float(np.linalg.eigvalsh(unsvec(S_vec, n, prob.solver))[0])
    return X, float(dual_obj + n * min(0.0, lam_min)), lam_min




def solve_sdp(vg: ViewGraph, variant: str | None = None, solver: str | None = None, config: SdpConfig | None = None,
              **options: Any) -> AveragingResult:
    """Certifiable SDP rotation averaging (paper 2), solved directly with SCS or Clarabel.

    With ``edges="robust"`` (the ``sdp`` method's default; not when called bare) the SDP
    runs on the edges a robust stage keeps, and says so (:mod:`pipeline.averaging.sdp.robust`).
    ``certified`` is decided against the cost's resolution (:func:`resolution_check`).

    Args:
        vg: a connected view graph; ``H`` on every edge for the anisotropic variants.
        variant: ``"cso3"`` (SDP-cSO(3), default), ``"cso3-iso"``, ``"o3-iso"`` or
            ``"o3-aniso"`` (see :mod:`pipeline.averaging.sdp.conic`); overrides the config's.
        solver: ``"scs"`` or ``"clarabel"``; overrides the config's.
        config: the options (:class:`SdpConfig`).
        **options: fields of :class:`SdpConfig` (``eps_abs``, ``eps_rel``: paper 2, §5,
            1e-5 and 1e-6, for Clarabel ``tol_gap_abs`` and ``tol_gap_rel``/``tol_feas``;
            ``max_iterations``; ``cert_kappa``; ``form``; ``lmi_pairs``; ``fallback``,
            ``fallback_max_cameras``, ``fallback_scs_max_iterations``; ``solver_log``). Any
            other key is a setting of the conic solver, checked by it (e.g.
            ``chordal_decomposition_enable=True`` for Clarabel, ``time_limit_secs`` for SCS).

    The fallback: when ``N`` is at most ``fallback_max_cameras`` and the solve is not
    certified, or its gap exceeds :data:`FALLBACK_RESIDUAL_GAP` of the residual cost
    ``f + Σ tr M_e`` (beyond ``eps_rel·|d*|``), the same SDP is solved again by
    Clarabel (dual form) at tolerance :data:`FALLBACK_EPS` and the better certificate
    is kept. This matters when one edge's ``H`` is orders of magnitude above the others
    (the cost's constant ``−Σ tr M_e`` then hides the residual part below a first-order
    solver's accuracy; see notes/issue-4.md, "Temple: heterogeneous H"). With
    ``fallback_scs_max_iterations`` (the :class:`SdpConfig` default, 2000, which
    ``run.py`` uses) and no ``max_iterations``, SCS stops there and leaves a problem it
    has not solved to Clarabel. Called bare (no ``config``) there is no such cap, as in
    paper 2.

    Returns:
        An :class:`AveragingResult` named ``"sdp-<variant>"``; ``stats`` holds
        ``build_s``, ``solve_s``, ``rank``, ``eigenvalues`` (top 6), ``lower_bound``,
        ``sdp_value``, ``primal_cost``, ``gap`` (relative: ``(primal_cost −
        lower_bound)/|lower_bound|``), ``gap_abs``, ``certified``, ``status``,
        ``solver_iterations``, ``cost_scale``, ``variant``, ``solver``, ``gap_residual``
        (``gap_abs / (primal_cost + cost_offset)``, the gap as a share of the part of
        the cost the rotations change; ``cost_offset = Σ tr M_e``, or ``3M`` when
        isotropic), ``fallback`` (the reported solve is the Clarabel re-solve) and
        ``first_attempt`` (summary of the replaced solve, or None). ``solver``,
        ``form``, ``status``, ``eps_*`` describe the reported solve. Costs are in
        the unscaled units of ``−Σ_edges ⟨M_ij R̃_ij, R_j R_iᵀ⟩``.

    Raises:
        ValueError: unknown variant, solver, form or solver setting.
        ViewGraphError: anisotropic variant without ``H``; a disconnected graph.
        PipelineError: the solver failed to return a solution.
    """
    fields = {f.name for f in dataclasses.fields(SdpConfig)}
    opts = {k: v for k, v in options.items() if k in fields}
    opts.update({k: v for k, v in (("variant", variant), ("solver", solver)) if v is not None})
    cfg = method_config(SdpConfig, config, opts, bare={"fallback_scs_max_iterations": None, "edges": "all",
                                                        "certify_start": False})
    settings = {k: v for k, v in options.items() if k not in fields}
    if cfg.edges == "robust":
        from pipeline.averaging.sdp.robust import solve_robust  # noqa: PLC0415 - it runs the IRLS methods

        return solve_robust(vg, cfg, settings, _solve)
    return _solve(vg, cfg, settings)


def _solve(vg: ViewGraph, cfg: SdpConfig, settings: dict[str, Any], start: np.ndarray | None = None
           ) -> AveragingResult:
    """One SDP on ``vg``; with ``start`` (N, 3, 3) and ``certify_start``, first
    :func:`~pipeline.averaging.sdp.refine.verified_start`."""
    # SCS converges in fewer iterations on the primal form (as JuMP states it for
    # paper 2); Clarabel on the dual form, whose slack carries the graph's sparsity
    # that its chordal decomposition exploits.
    solver = cfg.solver
    form = cfg.form or ("primal" if solver == "scs" else "dual")
    aniso, cso3 = check_inputs(vg, cfg.variant, solver)
    t0 = time.perf_counter()
    C, scale = edge_weights(vg, aniso)
    # Σ_e tr M_e: the cost of a perfect fit is −offset, and f + offset ≥ 0 is the part of the
    # cost that depends on the residuals (f_e + tr M_e = (1 − cos θ_e) u_eᵀ H_e u_e ≥ 0).
    offset = float(np.sum(np.trace(weight_matrices(0.5 * (vg.H + np.swapaxes(vg.H, 1, 2))),
                                   axis1=1, axis2=2))) if aniso else 3.0 * vg.n_edges
    lmi_edges = np.argwhere(np.triu(np.ones((vg.n_cameras,) * 2, bool), 1)) if cfg.lmi_pairs == "all" else None
    common = dict(vg=vg, C=C, scale=scale, offset=offset, cso3=cso3, lmi_edges=lmi_edges, kappa=cfg.cert_kappa,
                  polish=cfg.polish)
    first = att = verified_start(start, **common) if start is not None and cfg.certify_start else None
    if first is None:
        small = cfg.fallback and vg.n_cameras <= cfg.fallback_max_cameras
        max_iters = cfg.max_iterations
        if cfg.fallback_scs_max_iterations is not None and solver == "scs" and max_iters is None and small:
            max_iters = int(cfg.fallback_scs_max_iterations)
        first = _attempt(solver=solver, form=form, eps_abs=cfg.eps_abs, eps_rel=cfg.eps_rel, max_iters=max_iters,
                         verbose=cfg.solver_log, kw=settings, **common)
        tight = min(cfg.eps_abs, cfg.eps_rel) <= FALLBACK_EPS and solver == "clarabel"
        att = _fallback(first, cfg, common) if small and not tight else first
    t3 = time.perf_counter()
    method = f"sdp-{cfg.variant}"
    if not att["certified"]:
        logger.warning("%s is NOT certified optimal: %s; the rotations are a rounding of the relaxation, not a proven "
                       "optimum", method, _failed_tests(att, cfg.cert_kappa))
    R = att["R"]
    used_fallback = att is not first
    return AveragingResult(
        method=method,
        names=list(vg.names),
        R=R,
        time_s=t3 - t0,
        iterations=int(att["iterations"] + (first["iterations"] if used_fallback else 0)),
        edge_index=np.arange(vg.n_edges),
        residuals_rad=so3.angle_between(so3.relative(R, vg.edges), vg.R_rel),
        stats=_stats(att, first, cfg, offset, scale),
    )


def _fallback(att: dict[str, Any], cfg: SdpConfig, common: dict[str, Any]) -> dict[str, Any]:
    """The Clarabel re-solve of an uncertified or loose first attempt, if it is better; else ``att``."""
    offset = common["offset"]
    # Refine also a "certified" solve whose gap, beyond the requested relative accuracy, is a
    # sizeable share of the residual cost: the relative gap divides by |d*| ≈ offset, which
    # one edge with a huge H can make so large that a 1e-4 test is met by poor rotations.
    loose = att["gap_abs"] > (FALLBACK_RESIDUAL_GAP * max(att["primal_cost"] + offset, 0.0)
                              + cfg.eps_rel * abs(att["lower_bound"]))
    if att["certified"] and not loose:
        return att
    # The SDP value is dominated by the constant −Σ tr M_e; when one edge's H is orders of
    # magnitude above the others (e.g. a zero-baseline pair), the residual part that fixes
    # the rotations sits below a first-order solver's 1e-6 relative accuracy, and an
    # interior-point method at its default tolerance stops on the interior of the optimal
    # face (high rank). The same SDP solved by Clarabel to FALLBACK_EPS is cheap at small N.
    logger.info(
        "sdp-%s: %s (%s form) gave rank %d, relative gap %.3g, gap %.3g of the residual cost "
        "(certified: %s, status %s); re-solving the same SDP with Clarabel at tolerance %.0e",
        cfg.variant, att["solver"], att["form"], att["rank"], att["gap"], att["gap_residual"], att["certified"],
        att["status"], FALLBACK_EPS,
    )
    try:
        att2 = _attempt(solver="clarabel", form="dual", eps_abs=FALLBACK_EPS, eps_rel=FALLBACK_EPS,
                        max_iters=FALLBACK_MAX_ITERS, verbose=cfg.solver_log, kw={}, **common)
    except PipelineError as err:  # keep the first solve; the warning of the caller still reports it
        logger.warning("sdp-%s: the Clarabel re-solve failed (%s); keeping the %s result", cfg.variant, err,
                       att["solver"])
        return att
    same = att2["certified"] == att["certified"]
    return att2 if ((att2["gap_abs"] < att["gap_abs"]) if same else att2["certified"]) else att


_STAT_KEYS = ("build_s", "solve_s", "certificate_s", "rank", "eigenvalues", "lower_bound", "sdp_value",
              "primal_cost", "gap", "gap_abs", "gap_residual")


def _stats(att: dict[str, Any], first: dict[str, Any], cfg: SdpConfig, offset: float, scale: float
           ) -> dict[str, Any]:
    """The ``stats`` of the reported attempt ``att`` (``first`` when no fallback replaced it)."""
    return {
        "variant": cfg.variant,
        "solver": att["solver"],
        **{k: att[k] for k in _STAT_KEYS},
        "cost_offset": offset,
        "cert_kappa": cfg.cert_kappa,
        "resolution": att["resolution"],
        "gap_vs_resolution": att["gap_vs_resolution"],
        "cost_rounding": att["cost_rounding"],
        "certified_by": att["certified_by"],
        "polish_move_deg": att["polish_move_deg"],
        "certified": att["certified"],
        "status": att["status"],
        "solver_iterations": att["iterations"],
        "dual_lambda_min": att["dual_lambda_min"],
        "cost_scale": scale,
        "cost_units": "-sum_edges <M_ij R~_ij, R_j R_i^T>, unscaled (M_ij = I when isotropic)",
        "form": att["form"],
        "lmi_pairs": cfg.lmi_pairs,
        "n_variables": att["n_variables"],
        "n_constraints": att["n_constraints"],
        "eps_abs": att["eps_abs"],
        "eps_rel": att["eps_rel"],
        "fallback": att is not first,
        "first_attempt": None if first is att else {
            k: first[k] for k in ("solver", "form", "status", "rank", "gap", "gap_residual", "certified",
                                  "solve_s", "iterations")
        },
    }

def _attempt(vg: ViewGraph, C: np.ndarray, scale: float, offset: float, cso3: bool,
             lmi_edges: np.ndarray | None, kappa: float, polish: bool, solver: str, form: str, eps_abs: float,
             eps_rel: float, max_iters: int | None, verbose: bool, kw: dict[str, Any]) -> dict[str, Any]:
    """Build, solve, round and certify once with one solver setting; see :func:`solve_sdp`."""
    t0 = time.perf_counter()
    prob = build_conic(vg.n_cameras, vg.edges, C, cso3, solver, form, lmi_edges)
    t1 = time.perf_counter()
    run = _solve_scs if solver == "scs" else _solve_clarabel
    x, y, s, status, iters = run(prob, eps_abs, eps_rel, max_iters, verbose, **kw)
    t2 = time.perf_counter()
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.any(x != 0)):
        raise PipelineError(
            f"{solver} returned no usable solution (status {status!r}); try the other solver "
            "or looser tolerances"
        )
    X, lb_scaled, lam_min_S = extract(prob, x, y, s)
    R, lam = round_to_rotations(X)
    polish_move = polish_rounding(vg, C, R) if polish else None
    if polish_move is not None:
        R, polish_move = polish_move
    rank = numerical_rank(lam)
    lower_bound = lb_scaled * scale
    sdp_value = float(-np.sum(C * X.reshape(vg.n_cameras, 3, vg.n_cameras, 3)
                              .transpose(0, 2, 1, 3)[vg.edges[:, 1], vg.edges[:, 0]])) * scale
    primal_cost = edge_cost(vg.edges, C, R) * scale
    gap = relative_gap(primal_cost, lower_bound)
    gap_abs = primal_cost - lower_bound
    check = resolution_check(gap_abs, primal_cost, offset, vg.n_cameras, vg.n_edges, rank, kappa)
    check["certified_by"] = "the conic solver's dual bound" if check["certified"] else None
    if polish and not check["certified"]:  # a sharper bound: the dual certificate of the rounded rotations
        dual = dual_certificate_gap(vg, C, scale, R, kappa * check["resolution"] + check["cost_rounding"])
        if dual is not None and dual < gap_abs:
            gap_abs = dual
            check = {**resolution_check(gap_abs, primal_cost, offset, vg.n_cameras, vg.n_edges, 3, kappa),
                     "certified_by": "the dual certificate of the rounded rotations"}
    return {
        "solver": solver, "form": form, "R": R, "rank": rank,
        "eigenvalues": [float(v) for v in lam[:6]],
        "lower_bound": lower_bound, "sdp_value": sdp_value, "primal_cost": primal_cost,
        "gap": gap, "gap_abs": gap_abs,
        # the gap against the part of the cost the rotations change, not |d*| (which the
        # constant −Σ tr M_e can dominate): it decides ``certified``
        **check, "status": status, "iterations": iters,
        "dual_lambda_min": lam_min_S, "build_s": t1 - t0, "solve_s": t2 - t1,
        "certificate_s": time.perf_counter() - t2,
        "n_variables": int(prob.A.shape[1]), "n_constraints": int(prob.A.shape[0]),
        "eps_abs": eps_abs, "eps_rel": eps_rel, "polish_move_deg": polish_move,
    }
