"""Robust IRLS in the metric of the two-view Hessians H (anisotropic IRLS), calibrated per edge.

Paper 1's IRLS (:mod:`pipeline.averaging.irls`) weighs every edge's residual
isotropically: one scalar weight ``φ(‖r_ij‖)`` per edge. Paper 2 shows that the
two-view uncertainty is strongly anisotropic and that weighting by H pays. This
module joins the two: the same joint IRLS in the Lie algebra, with each edge's
residual measured in its own Mahalanobis norm and the robust loss applied to that
norm. It is a local method; its final reweighted problem is checked by the dual
certificate of :mod:`~pipeline.averaging.certificate`, and SDP-cSO(3) solves the
least-squares version globally.

**Calibrated** (``calibrate``, the ``irls-h`` method's default; issue 15): H is
overconfident on real images by factors that differ from edge to edge, so the product
runs a robust isotropic start (:func:`pipeline.averaging.irls.irls`), then for each
candidate metric (H, H shrunk towards isotropy, H's shape with inlier-count magnitudes,
isotropic, ...; ``metrics``) an EM fit of a Student-t + Haar mixture in that metric, and
keeps the likeliest (:mod:`~pipeline.averaging.calibration`). What follows describes the
step they share and the **global-scale** variant (``calibrate: false``; ``irls_h()``
called bare), which was the method before.

The residual of paper 1 (eq. 7) is ``r_ij = log(R_jᵀ R̃_ij R_i)``. With H defined
for the left perturbation ``R_j R_iᵀ = exp([Δω]×) R̃_ij`` (docs/CONVENTIONS.md),
``Δω = −R_j r_ij``, so ``Δωᵀ H_ij Δω = r_ijᵀ W_ij r_ij`` with
``W_ij = R_jᵀ H_ij R_j``. Each iteration:

1. ``q_ij = r_ijᵀ W_ij r_ij`` and the normalized residual ``t_ij = √(q_ij) / s``;
2. weights ``φ_ij = φ(t_ij)`` of the chosen loss, with α in units of ``s``;
3. the block step ``(Σ A_kᵀ φ_k G_kᵀ H_k G_k A_k) ΔΩ = −Σ A_kᵀ φ_k G_kᵀ H_k Δω_k``
   (paper 1, eq. 21, with 3×3 blocks in place of scalars; same sign convention as
   :mod:`pipeline.averaging.kernel`) on the gauge-fixed (3N, 3N) block Laplacian, by
   conjugate gradients preconditioned with the SuperLU factor of an earlier
   iteration's matrix, refactoring only when CG needs more than 15 iterations or
   the gauge changes (:meth:`BlockLaplacianSolver.solve_reusing`; N = 10,000: 2
   factorizations instead of 13, 2× faster, same rotations);
4. ``R_i ← R_i exp([Δω_i]×)``.

**The step's Jacobian.** After ``R_i ← R_i exp([δ_i]×)``, ``R_j ← R_j exp([δ_j]×)``,
``R_j R_iᵀ R̃ᵀ = exp([R_j(δ_j − δ_i)]×) exp([Δω]×)``, so to first order
``Δω ← Δω + G (δ_j − δ_i)`` with ``G = J_l⁻¹(Δω) R_j`` (``J_l⁻¹`` the inverse left
Jacobian of SO(3)). With ``J_l⁻¹ = I`` the step above is exactly paper 1's
``(Σ AᵀWA) ΔΩ = Σ AᵀW r``; keeping ``J_l⁻¹`` makes the fixed point the stationary
point of ``Σ ρ(t_ij)``. For isotropic weights the two fixed points coincide
(``J_l⁻ᵀ(Δω) Δω = Δω``); for anisotropic H the ``J_l⁻¹ = I`` fixed point is off
the minimizer of ``Σ Δωᵀ H Δω`` by a fraction of the error of the order of the
noise in radians (measured on paper2_graph(15, 0.5): largest camera gap 2–9% of
the median camera error at 1.3–1.6° median error, 0.2–0.4% at 0.15°).

**Scale.** H from two-view BA is a precision only if the reprojection noise model
holds; on real images it is often overconfident by a common factor (this project
measured a median NEES of 14 on templeSparseRing and 86 on fountain-P11, against
3 in theory). The loss therefore does not read ``√q`` as a number of standard
deviations: ``s² = median(q) / 2.366`` (2.366 is the median of χ²₃) is estimated
from the residuals of the starting point, a robust NEES calibration, and the loss
scale α is in units of ``s`` (``alpha_sigma``, default 2; not degrees, hence not
``alpha_deg`` as in :mod:`pipeline.averaging.irls`).

**Start and polish (global scale).** A spanning tree, isotropic ℓ1 steps (paper 1,
Algorithm 2), then the anisotropic IRLS, then (with ``refine``) a trimmed least-squares
polish: ``s`` is re-estimated from the converged residuals and edges with ``t > 3.76``
(the 99.7% point of χ₃) get weight 0 (Talwar). Stages stop as in
:mod:`~pipeline.averaging.stopping`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from pipeline.averaging.block import BlockLaplacianSolver, anisotropic_step, edge_metric, jl_inv, left_errors
from pipeline.averaging.calibration import DEFAULT_METRICS, RACE_CHECKPOINTS, check_metric, race_metrics, shape_metric
from pipeline.averaging.certificate import certify_weights, metric_from_H
from pipeline.averaging.init import initial_rotations
from pipeline.averaging.irls import IRLSConfig, irls
from pipeline.averaging.kernel import LaplacianSolver, apply_update, check_graph
from pipeline.averaging.l1 import L1StartConfig, l1_averaging
from pipeline.averaging.losses import Loss, get_loss
from pipeline.averaging.result import AveragingResult, method_config, start_of
from pipeline.averaging.stopping import StopConfig, StopRule, converged, robust_scale
from pipeline.core.config import option
from pipeline.core.errors import ConfigError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["IRLSHConfig", "BlockLaplacianSolver", "irls_h", "edge_metric", "CHI2_3_MEDIAN", "TRIM_T"]

logger = logging.getLogger(__name__)

#: Median of the χ² distribution with 3 degrees of freedom.
CHI2_3_MEDIAN = 2.3660
#: 99.7% point of the χ distribution with 3 degrees of freedom: the polish's trimming threshold.
TRIM_T = 3.76
_jl_inv = jl_inv  # the name earlier versions exported


def _squared_norms(vg: ViewGraph, R: np.ndarray) -> np.ndarray:
    _, _, dom = left_errors(vg, R)
    return np.einsum("ma,mab,mb->m", dom, vg.H, dom)


def _scale(q: np.ndarray) -> float:
    # No degrees-of-freedom correction for fitted residuals: scaling s² by M/(M−N+1) trims
    # fewer inliers on synthetic graphs (~0.3% instead of ~1%) but made templeSparseRing worse
    # (0.425° → 0.468° median) and the other real/rendered scenes equal or slightly worse.
    s2 = float(np.median(q)) / CHI2_3_MEDIAN
    if not (np.isfinite(s2) and s2 > 0):
        # every residual is zero to rounding (exact data): any positive scale gives the same answer
        s2 = float(np.mean(q)) / 3.0 if np.mean(q) > 0 else 1.0
    return s2


def _steps(vg: ViewGraph, R: np.ndarray, solver: BlockLaplacianSolver, lossf: Loss, s2: float, rule: StopRule,
           stage: str, t0: float, history: list[dict[str, float]], reuse: bool = True) -> tuple[np.ndarray, int, bool]:
    it, f_prev = 0, np.inf
    for it in range(1, rule.max_iterations + 1):
        q = _squared_norms(vg, R)
        t = np.sqrt(q / s2)
        f = float(lossf.rho(t).sum())
        dw = anisotropic_step(vg, R, solver, vg.H, lossf.phi(t) / s2, reuse=reuse)
        if not np.all(np.isfinite(dw)):
            raise ViewGraphError(f"anisotropic IRLS step {it} is not finite (loss {lossf.name}); "
                                 "the weighted block Laplacian is singular. Check H for NaN or try another loss")
        theta = np.linalg.norm(left_errors(vg, R)[0], axis=1)
        R = apply_update(R, dw)
        norms = np.linalg.norm(dw, axis=1)
        history.append({"stage": stage, "cost": f, "mean_step_rad": float(norms.mean()),
                        "max_step_rad": float(norms.max()), "time_s": time.perf_counter() - t0})
        if converged(f_prev, f, float(norms.max()), rule, robust_scale(theta)):
            return R, it, True
        f_prev = f
    return R, it, False


@dataclass(frozen=True, kw_only=True)
class IRLSHConfig(L1StartConfig, StopConfig):
    """Options of :func:`irls_h` (the ``irls-h`` method); see :func:`irls_h` for what each does."""

    SECTION = "averaging.irls-h"
    loss: str = option("l0.5", "loss of paper 1, Table 1 (calibrated: of the isotropic start; global scale: "
                               "on the H-normalized residual)")
    calibrate: bool = option(True, "per-edge calibration of H by likelihood (false: one global scale, as before)")
    metrics: tuple[str, ...] = option(DEFAULT_METRICS, "calibrate: candidate metrics (iso, inliers, shrink:<λ>, "
                                                       "power:<p>, shape:<p>, shape-inl:<p>)")
    start: Literal["auto", "tree", "l1", "both"] = option("auto", "calibrate: the start branches of the isotropic "
                                                                  "start (as irls)")
    alpha_sigma: float = option(2.0, "global scale: loss scale α in units of the robust residual scale s", gt=0)
    refine: bool = option(True, "global scale: after convergence, least squares on the edges with t <= 3.76")
    refine_iterations: int = option(50, "iteration cap of the polish (global scale) or of each metric's EM", ge=0)
    scale: float | None = option(None, "global scale: a fixed s² (NEES scale of H) instead of the robust estimate",
                                 gt=0)
    race: bool = option(True, "calibrate: stop a candidate metric whose likelihood trails the leader's by a wide "
                              "margin after a few EM iterations (false: every candidate runs to its end)")
    certify: bool = option(True, "dual certificate of the final reweighted problem (stats['certificate'])")

    def check(self) -> None:
        try:
            get_loss(self.loss)
            for m in self.metrics:
                check_metric(m)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if not self.metrics:
            raise ConfigError("[averaging.irls-h] metrics is empty; give at least one, e.g. shrink:0")


def irls_h(vg: ViewGraph, config: IRLSHConfig | None = None, *, init: str | np.ndarray | None = None,
           init_weights: np.ndarray | None = None, **options: Any) -> AveragingResult:
    """Robust rotation averaging with each edge's residual in its (calibrated) H metric.

    Called bare (no ``config``), this is the global-scale variant (``calibrate=False``,
    no certificate); the ``irls-h`` method of the registry calibrates (module docstring).

    Args:
        vg: a connected view graph with H.
        config: the options; ``**options`` override its fields (:class:`IRLSHConfig`):
        loss: loss name of :func:`pipeline.averaging.losses.get_loss` (default ℓ½).
        alpha_sigma: (global scale) loss scale α in units of the robust residual scale
            ``s``, not degrees. Default 2: residuals up to 2s are in ℓ½'s quadratic core.
        init: ``"mst"``, ``"random"`` or (N, 3, 3) initial rotations.
        max_iterations, ftol, xtol_scale, tol_rad: the stopping rule.
        l1_iterations, l1_tol_rad, admm_max_iterations, start: the isotropic start.
        refine: (global scale) after convergence, re-estimate ``s`` and run least squares
            on the edges with ``t ≤ 3.76`` (Talwar).
        scale: (global scale) a fixed ``s²`` instead of the robust estimate.
        metrics: (calibrated) the candidate metrics.

    Returns:
        :class:`AveragingResult` with ``residuals_rad`` (geodesic angles), the final
        problem's ``weights`` and ``kept`` edges, and ``stats``: calibrated, ``selected``
        metric and the ``candidates`` table; global scale, ``scale_s2`` of each stage,
        ``normalized_residuals`` and ``n_trimmed``; both, ``certificate`` when asked.

    Raises:
        ViewGraphError: the view graph has no H, or a step is not finite.
    """
    cfg = method_config(IRLSHConfig, config, options, init, bare={"calibrate": False, "certify": False})
    check_graph(vg)
    if vg.H is None:
        raise ViewGraphError("anisotropic IRLS needs a view graph with H (two-view BA precisions); "
                             "run the two-view BA stage or use method 'irls'")
    t0 = time.perf_counter()
    solve = _calibrated if cfg.calibrate else _global_scale
    res, P, what = solve(vg, cfg, init, init_weights, t0)
    if cfg.certify:
        res.stats["certificate"] = certify_weights(vg, res.R, res.weights, res.kept, M=metric_from_H(P), what=what,
                                                   method=res.method, fills=res.stats["factor_fills"])
    res.time_s = time.perf_counter() - t0
    return res


def _calibrated(vg: ViewGraph, cfg: IRLSHConfig, init: Any, init_weights: np.ndarray | None, t0: float
                ) -> tuple[AveragingResult, np.ndarray, str]:
    """Robust isotropic start, then one mixture EM per candidate metric; the likeliest wins."""
    iso_cfg = IRLSConfig.from_dict({
        "loss": cfg.loss, "init": cfg.init, "seed": cfg.seed, "l1_iterations": cfg.l1_iterations,
        "l1_tol_rad": cfg.l1_tol_rad, "admm_max_iterations": cfg.admm_max_iterations, "start": cfg.start,
        "max_iterations": cfg.max_iterations, "ftol": cfg.ftol, "xtol_scale": cfg.xtol_scale, "tol_rad": cfg.tol_rad,
        "refine_iterations": cfg.refine_iterations, "certify": False})
    start = irls(vg, iso_cfg, init=None if isinstance(init, str) else init, init_weights=init_weights)
    solver = BlockLaplacianSolver(vg.edges, vg.n_cameras, ref=int(np.argmax(vg.degrees())))
    rule = StopRule(cfg.ftol, 0.01, cfg.tol_rad, cfg.refine_iterations)
    metrics = {name: P for name in dict.fromkeys(cfg.metrics) if (P := shape_metric(vg, name)) is not None}
    fits, dropped = race_metrics(vg, start.R, metrics, rule, solver, RACE_CHECKPOINTS if cfg.race else ())
    best = max(fits, key=lambda k: fits[k].loglik)
    f = fits[best]
    r, _, dom = left_errors(vg, f.R)
    theta = np.linalg.norm(r, axis=1)
    normalized = np.sqrt(np.einsum("ma,mab,mb->m", dom, metrics[best], dom)) / f.s
    kept = np.asarray(f.gamma) >= 0.5
    logger.info("IRLS-H (calibrated): %d cameras, %d edges, metric %s (ν=%g, ε=%.2f), %d edges rejected, %.3f s",
                vg.n_cameras, vg.n_edges, best, f.nu, f.eps, int((~kept).sum()), time.perf_counter() - t0)
    res = AveragingResult(
        method=f"irls-h-{start.stats['loss']}+calibrated", names=list(vg.names), R=f.R, time_s=0.0,
        iterations=f.iterations, edge_index=np.arange(vg.n_edges), residuals_rad=theta, weights=f.weights, kept=kept,
        history=start.history, stats={
            "loss": start.stats["loss"], "calibrate": True, "selected": best, "nu": f.nu, "s": f.s, "eps": f.eps,
            "converged": f.converged, "start_used": start.stats["start_used"],
            "start_polish_model": start.stats["polish_model"], "l1_iterations": start.stats["l1_iterations"],
            "irls_iterations": start.stats["irls_iterations"], "n_kept": int(kept.sum()),
            "normalized_residuals": normalized.tolist(),
            "n_factorizations": solver.n_factorizations, "n_cg_iterations": solver.n_cg_iterations,
            "factor_fills": solver.fills,
            "candidates": {**{k: {"loglik": v.loglik, "nu": v.nu, "s": v.s, "eps": v.eps, "iterations": v.iterations,
                                  "converged": v.converged, "n_outliers": int(np.sum(v.gamma < 0.5))}
                              for k, v in fits.items()},
                           **{k: {"loglik": v["loglik"], "iterations": v["iterations"], "dropped_behind": v["behind"]}
                              for k, v in dropped.items()}}})
    what = f"the final reweighted cost of calibrated IRLS-H (metric {best}, t-weights, ν={f.nu:g})"
    return res, metrics[best], what


def _global_scale(vg: ViewGraph, cfg: IRLSHConfig, init: Any, init_weights: np.ndarray | None, t0: float
                  ) -> tuple[AveragingResult, np.ndarray, str]:
    """The anisotropic IRLS with one robust scale s² for every edge (earlier versions' method)."""
    # get_loss takes degrees; the normalized residual t is dimensionless, used here as if radians
    lossf = get_loss(cfg.loss, float(np.rad2deg(cfg.alpha_sigma)), None)
    R = initial_rotations(vg, start_of(init, cfg), weights=init_weights, seed=cfg.seed)
    ref = int(np.argmax(vg.degrees()))
    history: list[dict[str, float]] = []
    if cfg.l1_iterations > 0:
        R, h1 = l1_averaging(vg, R, max_iterations=cfg.l1_iterations, tol_rad=cfg.l1_tol_rad,
                             admm_max_iterations=cfg.admm_max_iterations,
                             solver=LaplacianSolver(vg.edges, vg.n_cameras, ref=ref))
        history.extend(h1)
    solver = BlockLaplacianSolver(vg.edges, vg.n_cameras, ref=ref)
    scale = cfg.scale
    s2 = scale if scale is not None else _scale(_squared_norms(vg, R))
    R, it, ok = _steps(vg, R, solver, lossf, s2, cfg.stop_rule(), "irls-h", t0, history)
    s2_refine, n_trimmed, final = None, 0, lossf
    if cfg.refine:
        s2_refine = scale if scale is not None else _scale(_squared_norms(vg, R))
        final = get_loss("talwar", float(np.rad2deg(TRIM_T)))
        R, _, _ = _steps(vg, R, solver, final, s2_refine, StopRule(cfg.ftol, 0.01, cfg.tol_rad, cfg.refine_iterations),
                         "refine", t0, history)
    s2_final = s2_refine if s2_refine is not None else s2
    t = np.sqrt(_squared_norms(vg, R) / s2_final)
    if cfg.refine:
        n_trimmed = int(np.sum(t > TRIM_T))
    phi = final.phi(t)
    kept = phi >= 0.05 * float(np.max(phi))
    if not ok and cfg.max_iterations > 0:
        logger.warning("anisotropic IRLS-%s stopped at the iteration cap (%d) with largest step %.3g rad",
                       lossf.name, cfg.max_iterations, history[-1]["max_step_rad"])
    logger.info("IRLS-H-%s: %d cameras, %d edges, %d IRLS iterations, s² = %.3g, %d edges trimmed, %.3f s",
                lossf.name, vg.n_cameras, vg.n_edges, it, s2_final, n_trimmed, time.perf_counter() - t0)
    res = AveragingResult(
        method=f"irls-h-{lossf.name}" + ("+polish" if cfg.refine else ""), names=list(vg.names), R=R, time_s=0.0,
        iterations=it, edge_index=np.arange(vg.n_edges), residuals_rad=np.linalg.norm(left_errors(vg, R)[0], axis=1),
        weights=phi / s2_final, kept=kept, history=history, stats={
            "loss": lossf.name, "calibrate": False, "alpha": float(cfg.alpha_sigma), "scale_s2": float(s2),
            "scale_s2_refine": None if s2_refine is None else float(s2_refine),
            "normalized_residuals": t.tolist(), "n_trimmed": n_trimmed, "converged": ok,
            "l1_iterations": sum(1 for h in history if h.get("stage") == "l1"), "irls_iterations": it,
            "n_factorizations": solver.n_factorizations, "n_cg_iterations": solver.n_cg_iterations,
            "factor_fills": solver.fills, "refine": cfg.refine, "n_kept": int(kept.sum())})
    what = (f"the trimmed least-squares cost of IRLS-H (t ≤ {TRIM_T}, s² = {s2_final:.3g})" if cfg.refine
            else f"the final reweighted cost of IRLS-H-{lossf.name}")
    return res, vg.H, what
