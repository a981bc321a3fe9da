"""Robust relative rotation averaging by joint IRLS in the Lie algebra (paper 1, Algorithms 1 and 3).

Each iteration (paper 1, Alg. 1):

1. residuals ``r_ij = log(R_jᵀ R_ij R_i)`` (eq. 7), batched over edges;
2. weights ``φ_ij = φ(‖r_ij‖)`` of the chosen loss (Table 1, eq. 12);
3. the quasi-Newton step of eq. 21, in this code's sign convention (see
   :mod:`pipeline.averaging.kernel`): ``(Aᵀ Φ A) ΔΩ = Aᵀ Φ r`` with one sparse
   factorization of the gauge-fixed weighted Laplacian shared by the three axes
   (reused as a preconditioner while the weights change little);
4. ``R_i ← R_i exp([Δω_i]×)``.

**Stopping** (:mod:`~pipeline.averaging.stopping`): the cost has settled (relative
decrease ≤ ``ftol``) and the *largest* camera update is ≤ ``xtol_scale`` × the robust
residual scale σ̂ (or ≤ ``tol_rad`` when given), not paper 1's mean update of 1e-3 rad.

**Start** (``start``). Paper 1's Algorithm 3 runs ℓ1 steps from a spanning tree
(``"l1"``). With outliers from repeated structure, all rotating about one axis, one exact
ℓ1 step takes a good inlier-weighted tree (4.2° median) to a wrong basin (23–26°) that
IRLS never leaves, and COLMAP (also ℓ1 first) fails the same way; IRLS straight from the
tree (``"tree"``) reaches the right basin. A tree drawn without weights runs through
outliers, which the ℓ1 stage is for. ``"auto"`` (default): with inlier counts (or
``init_weights``, or a start given as rotations) the tree branch runs, and the ℓ1 branch
too when more than ``auto_bad_share`` of the edges end beyond max(10 σ̂, 30°); without
weights, ``"l1"``. When both branches run (``"both"``, or ``"auto"`` on a broken tree), the
one with the lower :func:`~pipeline.averaging.polish.selection_cost` is kept.

**Polish** (``refine``, ``polish``; not in paper 1). ℓ½'s slowly decaying influence
leaves outliers a small pull, and on real graphs the noise is heavy-tailed. ``"mixture"``
(default) fits a Student-t + Haar-outlier mixture to the residuals by EM
(:mod:`~pipeline.averaging.mixture`): each edge is weighted by its inlier posterior times
its latent t precision, ν is chosen by likelihood (Gaussian data get ν = 32, i.e. least
squares on the inliers). ``trust_inliers`` (off by default) adds a second polish with per-edge
trust ``n_e/median n`` from the inlier counts, kept if its likelihood is higher: it is likelier
on every graph measured, yet less accurate on the three real graphs and on most synthetic ones
(notes/issue-15.md): the likelihood of the residuals cannot see an error the edges share.
``"talwar"``: least squares on the
edges under τ = max(3.76 σ̂, ``refine_min_deg``) (earlier versions).

**Rescue** (``rescue``, after the mixture polish): a camera that fewer than a quarter of its
edges support (a dense graph's camera matched mostly wrong, left by the ℓ1 start where its
outliers outvoted it) is moved to the rotation that most of its edges' proposals agree on, and
the polish runs again; the result is kept if the polish's likelihood is higher
(:mod:`~pipeline.averaging.rescue`). ``stats["rescue"]`` names the cameras moved.

**Certificate** (``certify``): the final reweighted problem (fixed weights) is checked
for global optimality by a dual certificate (:mod:`~pipeline.averaging.certificate`):
"verified", "not verified" or "could not decide", with the cost, the edge set and the
numbers. It proves optimality of that problem, never accuracy.

At a fixed point ``AᵀΦr = 0``, the gradient of the final problem (paper 1, eq. 23);
its norm is ``stats["gradient_norm"]``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np

from pipeline.averaging.certificate import certify_weights
from pipeline.averaging.init import initial_rotations
from pipeline.averaging.kernel import LaplacianSolver, check_graph, graph_residuals
from pipeline.averaging.l1 import L1StartConfig, l1_averaging
from pipeline.averaging.losses import Loss, get_loss
from pipeline.averaging.mixture import noise_edges
from pipeline.averaging.polish import mixture_polish, residual_angles, reweighted, selection_cost, talwar_polish
from pipeline.averaging.rescue import rescue_cameras
from pipeline.averaging.result import AveragingResult, method_config, start_of
from pipeline.averaging.stopping import StopConfig, StopRule, robust_scale
from pipeline.core.config import option
from pipeline.core.errors import ConfigError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["IRLSConfig", "irls", "isotropic_start"]

logger = logging.getLogger(__name__)

#: Agreement radius of the rescue: max(5°, 4 s), s the polish's per-axis noise scale (two proposals of one camera
#: each carry an edge's noise and a neighbour's error).
RESCUE_TOL_DEG = 5.0
RESCUE_TOL_SCALE = 4.0


@dataclass(frozen=True, kw_only=True)
class IRLSConfig(L1StartConfig, StopConfig):
    """Options of :func:`irls` (the ``irls`` method); the module docstring says what each does."""

    SECTION = "averaging.irls"
    loss: str = option("l0.5", "IRLS loss of paper 1, Table 1 (l2, l1, l<p>, geman-mcclure, huber, cauchy, ...)")
    alpha_deg: float = option(5.0, "loss scale α in degrees", gt=0)
    eps_rad: float | None = option(None, "weight floor of ℓ1/ℓp (p < 2) in radians; null: α for p < 1, 1e-6 "
                                         "otherwise", gt=0)
    start: Literal["auto", "tree", "l1", "both"] = option(
        "auto", "tree → IRLS, tree → ℓ1 → IRLS (paper 1), both (keep the better), or auto")
    auto_bad_share: float = option(0.25, "auto: also run the ℓ1 branch when this share of the edges ends beyond "
                                         "max(10 σ̂, 30°)", gt=0, le=1)
    refine: bool = option(True, "after convergence, the polish (not in paper 1)")
    polish: Literal["mixture", "talwar"] = option("mixture", "polish: t + Haar mixture EM, or trimmed ℓ2 (Talwar)")
    trust_inliers: bool = option(False, "mixture polish: also try per-edge trust from inlier counts (kept if likelier; "
                                        "off: likelier but less accurate on the real and synthetic graphs measured)")
    refine_iterations: int = option(50, "iteration cap of the polish", ge=0)
    refine_min_deg: float = option(1.0, "Talwar polish: lower bound of the trimming threshold, degrees", ge=0)
    certify: bool = option(True, "dual certificate of the final reweighted problem (stats['certificate'])")
    rescue: bool = option(True, "mixture polish: then move each camera that fewer than a quarter of its edges "
                                "support to the rotation most of its edges agree on, and polish again; kept if the "
                                "polish's likelihood is higher (rescue.py)")

    def check(self) -> None:
        try:
            get_loss(self.loss, self.alpha_deg, self.eps_rad)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None


#: What ``irls()`` called bare is: paper 1's Algorithm 3 alone, as in the paper.
BARE = {"refine": False, "start": "l1", "certify": False}


def _branch(vg: ViewGraph, R0: np.ndarray, solver: LaplacianSolver, lossf: Loss, cfg: IRLSConfig, l1: bool,
            t0: float) -> dict[str, Any]:
    history: list[dict[str, float]] = []
    R = R0
    if l1 and cfg.l1_iterations > 0:
        offset = time.perf_counter() - t0
        R, h1 = l1_averaging(vg, R, max_iterations=cfg.l1_iterations, tol_rad=cfg.l1_tol_rad,
                             admm_max_iterations=cfg.admm_max_iterations, solver=solver)
        for h in h1:
            h["time_s"] += offset
        history.extend(h1)
    R, it, ok = reweighted(vg, R, solver, lossf.phi, lambda th: float(lossf.rho(th).sum()), cfg.stop_rule(), "irls",
                           t0, history)
    return {"R": R, "history": history, "iterations": it, "converged": ok,
            "l1_iterations": sum(1 for h in history if h.get("stage") == "l1")}


def isotropic_start(vg: ViewGraph, cfg: IRLSConfig, init: Any, init_weights: np.ndarray | None, solver: LaplacianSolver,
                    lossf: Loss, t0: float) -> tuple[dict[str, Any], dict[str, Any]]:
    """The start branches of :func:`irls` (module docstring): the chosen run and a summary of every branch."""
    start = start_of(init, cfg)
    R0 = initial_rotations(vg, start, weights=init_weights, seed=cfg.seed)
    mode = cfg.start
    if mode == "auto" and isinstance(start, str) and init_weights is None and vg.inliers is None:
        mode = "l1"  # a tree drawn without weights runs through outliers: paper 1's ℓ1 stage is for that
    runs: dict[str, dict[str, Any]] = {}
    if mode in ("tree", "auto", "both"):
        runs["tree"] = _branch(vg, R0, solver, lossf, cfg, False, t0)
    bad = float("nan")
    need_l1 = mode in ("l1", "both")
    if mode == "auto":
        th = residual_angles(vg, runs["tree"]["R"])
        bad = float(np.mean(th > max(10.0 * robust_scale(th), np.deg2rad(30.0))))
        need_l1 = bad > cfg.auto_bad_share
    if need_l1:
        runs["l1"] = _branch(vg, R0, solver, lossf, cfg, True, t0)
    sel: dict[str, float | None] = {k: None for k in runs}
    if len(runs) > 1:
        thetas = {k: residual_angles(vg, v["R"]) for k, v in runs.items()}
        s_sel = min(robust_scale(t) for t in thetas.values())
        sel = {k: selection_cost(t, s_sel) for k, t in thetas.items()}
    best = min(sel, key=lambda k: sel[k] or 0.0)
    summary = {"start_used": best, "auto_bad_share_measured": bad,
               "branches": {k: {"selection_cost": sel[k], "iterations": v["iterations"], "converged": v["converged"],
                                "l1_iterations": v["l1_iterations"]} for k, v in runs.items()}}
    return runs[best], summary


def irls(vg: ViewGraph, config: IRLSConfig | None = None, *, init: str | np.ndarray | None = None,
         init_weights: np.ndarray | None = None, **options: Any) -> AveragingResult:
    """Robust rotation averaging: a start (tree and/or ℓ1), IRLS, a polish, a certificate (module docstring).

    Called bare (no ``config``), this is paper 1's Algorithm 3 alone (:data:`BARE`: start
    ``"l1"``, no polish, no certificate); the ``irls`` method of the registry, run by
    ``run.py`` and ``python -m pipeline.average``, has the :class:`IRLSConfig` defaults.

    Args:
        vg: a connected view graph (see :func:`pipeline.averaging.average` for
            disconnected ones).
        config: the options; ``**options`` override its fields (:class:`IRLSConfig`).
        init: ``"mst"``, ``"random"`` or (N, 3, 3) initial rotations.
        init_weights: (M,) edge weights for the ``"mst"`` tree (default: inliers).

    Returns:
        :class:`AveragingResult` with ``residuals_rad``, the final problem's ``weights``
        and ``kept`` edges, the chosen branch's ``history`` and ``stats``
        (``gradient_norm``, ``final_cost``, ``converged``, ``start_used``, ``branches``,
        ``polish_model``, ``certificate``, ...).
    """
    cfg = method_config(IRLSConfig, config, options, init, bare=BARE)
    check_graph(vg)
    lossf = get_loss(cfg.loss, cfg.alpha_deg, cfg.eps_rad)
    t0 = time.perf_counter()
    N, M = vg.n_cameras, vg.n_edges
    solver = LaplacianSolver(vg.edges, N, ref=int(np.argmax(vg.degrees())))
    run, starts = isotropic_start(vg, cfg, init, init_weights, solver, lossf, t0)
    R, history, it, converged = run["R"], run["history"], run["iterations"], run["converged"]
    polish_rule = StopRule(cfg.ftol, 0.01, cfg.tol_rad, cfg.refine_iterations)
    tau, model, trust_used, trust, fits = None, None, None, None, {}
    if cfg.refine and cfg.polish == "talwar":
        R, tau = talwar_polish(vg, R, solver, cfg.refine_min_deg, polish_rule, t0, history)
    elif cfg.refine:
        trust_used, fits, trust = _mixture(vg, R, solver, cfg, polish_rule, t0, history)
        R, model = fits[trust_used].R, fits[trust_used].model
    r = graph_residuals(vg, R)
    theta = np.sqrt(np.einsum("ma,ma->m", r, r))
    rescue_stats = None
    if cfg.refine and model is not None and cfg.rescue:
        again, rescue_stats = _rescue(vg, R, theta, model, solver, cfg, polish_rule, t0, history)
        if again is not None:
            trust_used, fits, trust = again
            R, model = fits[trust_used].R, fits[trust_used].model
            r = graph_residuals(vg, R)
            theta = np.sqrt(np.einsum("ma,ma->m", r, r))
    if tau is not None:
        w = (theta <= tau).astype(np.float64)
        kept = w > 0
    elif model is not None:
        w, kept = fits[trust_used].weights, fits[trust_used].gamma >= 0.5
        m = 1.0 if trust is None else trust
        normalized = np.sqrt(m) * theta / model.s
    else:
        w = lossf.phi(theta)
        kept = w >= 0.05 * float(np.max(w))  # an edge with < 5% of the full weight has hardly any say
    grad = solver.AT @ (w[:, None] * r)
    t_solve = time.perf_counter() - t0
    n_l1 = run["l1_iterations"]
    if not converged and cfg.max_iterations > 0:
        logger.warning("IRLS-%s stopped at the iteration cap (%d) with largest step %.3g rad",
                       lossf.name, cfg.max_iterations, history[-1]["max_step_rad"])
    polish_it, polish_ok = (fits[trust_used].iterations, fits[trust_used].converged) if fits else (0, True)
    if not polish_ok:
        logger.warning("IRLS-%s's polish stopped at its iteration cap (refine_iterations = %d) with largest step "
                       "%.3g rad", lossf.name, cfg.refine_iterations, history[-1]["max_step_rad"])
    stats: dict[str, Any] = {
        "loss": lossf.name, "alpha_deg": float(cfg.alpha_deg),
        "gradient_norm": float(np.sqrt(np.square(grad).sum())),
        "final_cost": float(lossf.rho(theta).sum()), "converged": converged,
        "l1_iterations": n_l1, "irls_iterations": it,
        "n_factorizations": solver.n_factorizations, "n_cg_iterations": solver.n_cg_iterations,
        **starts,
        "polish": (cfg.polish if cfg.refine else "none"),
        "refine_threshold_deg": None if tau is None else float(np.rad2deg(tau)),
        "polish_model": None if model is None else {
            "trust": trust_used, "nu": model.nu, "s_deg": float(np.rad2deg(model.s)), "eps": model.eps,
            "iterations": polish_it, "converged": polish_ok,
            "loglik": {k: v.model.loglik for k, v in fits.items()}, "n_outliers": int(np.sum(model.gamma < 0.5))},
        "normalized_residuals": None if model is None else normalized.tolist(),
        "rescue": rescue_stats,
        "n_kept": int(kept.sum()), "solve_s": t_solve,
        "config": {"loss": lossf.name, "alpha_deg": cfg.alpha_deg, "eps_rad": lossf.eps_rad,
                   "max_iterations": cfg.max_iterations, "ftol": cfg.ftol, "xtol_scale": cfg.xtol_scale,
                   "tol_rad": cfg.tol_rad, "l1_iterations": cfg.l1_iterations, "l1_tol_rad": cfg.l1_tol_rad,
                   "admm_max_iterations": cfg.admm_max_iterations, "start": cfg.start, "polish": cfg.polish,
                   "init": cfg.init if isinstance(start_of(init, cfg), str) else "user",
                   "seed": cfg.seed or 0, "refine": cfg.refine, "rescue": cfg.rescue},
    }
    if cfg.certify:
        what = _final_problem(lossf, cfg, tau, model, trust_used)
        stats["certificate"] = certify_weights(vg, R, w, kept, what=what, method=f"IRLS-{lossf.name}", theta=theta,
                                               fills=solver.fills)
    elapsed = time.perf_counter() - t0
    logger.info("IRLS-%s: %d cameras, %d edges, start %s, %d ℓ1 + %d IRLS iterations, %.3f s, median residual %.3f°",
                lossf.name, N, M, starts["start_used"], n_l1, it, elapsed, np.rad2deg(np.median(theta)))
    return AveragingResult(
        method=f"irls-{lossf.name}" + ("+polish" if cfg.refine else ""), names=list(vg.names), R=R, time_s=elapsed,
        iterations=it, dropped_names=[], edge_index=np.arange(M), residuals_rad=theta, weights=w, kept=kept,
        history=history, stats=stats)


class PolishFit(NamedTuple):
    """One mixture polish of :func:`_mixture`: its rotations, fitted model, history, final weights, inlier
    posteriors, iterations and whether its stopping rule was met."""

    R: np.ndarray
    model: Any
    history: list[dict[str, float]]
    weights: np.ndarray
    gamma: np.ndarray
    iterations: int
    converged: bool


def _mixture(vg: ViewGraph, R: np.ndarray, solver: LaplacianSolver, cfg: IRLSConfig, rule: StopRule, t0: float,
             history: list[dict[str, float]]) -> tuple[str, dict[str, PolishFit], np.ndarray | None]:
    """The mixture polish, isotropic and (with inlier counts) with per-edge trust; the likelier one wins.

    Returns the winner's name, every polish by name, and the winner's per-edge trust (None: isotropic); the winner's
    iterations are appended to ``history``."""
    trusts: dict[str, np.ndarray | None] = {"iso": None}
    if cfg.trust_inliers and vg.inliers is not None:
        n_in = np.maximum(np.asarray(vg.inliers, dtype=np.float64), 1.0)
        trusts["inliers"] = n_in / np.median(n_in)
    fits: dict[str, PolishFit] = {}
    R_iso = R
    noise = noise_edges(vg.edges, vg.n_cameras)  # the edges the residual model is fitted to, once
    for name, m in trusts.items():  # "iso" first; the trusted polish starts from its answer
        hist: list[dict[str, float]] = []
        Rt, model, w, gamma, it, ok = mixture_polish(vg, R_iso, solver, m, rule, t0, hist, refit=len(trusts) > 1,
                                                     noise=noise)
        fits[name] = PolishFit(Rt, model, hist, w, gamma, it, ok)
        if name == "iso":
            R_iso = Rt
    best = max(fits, key=lambda k: fits[k].model.loglik)
    history.extend(fits[best].history)
    return best, fits, trusts[best]


def _rescue(vg: ViewGraph, R: np.ndarray, theta: np.ndarray, model: Any, solver: LaplacianSolver, cfg: IRLSConfig,
            rule: StopRule, t0: float, history: list[dict[str, float]]) -> tuple[Any, dict[str, Any]]:
    """The rescue after the mixture polish (module docstring): the re-polished :func:`_mixture` result when it
    moved cameras and the polish's own likelihood is higher (its iterations appended to ``history``), else None;
    and the rescue's stats."""
    tol = max(np.deg2rad(RESCUE_TOL_DEG), RESCUE_TOL_SCALE * model.s)
    res = rescue_cameras(vg, R, theta, tol)
    stats: dict[str, Any] = {"tol_deg": float(np.rad2deg(tol)), "moved": [vg.names[k] for k in res.cameras],
                             "support_before": res.support_before.tolist(), "support_after": res.support_after.tolist(),
                             "degree": res.degree[res.cameras].tolist(), "kept": False}
    if not res.cameras.size:
        return None, stats
    hist: list[dict[str, float]] = []
    best, fits, trust = _mixture(vg, res.R, solver, cfg, rule, t0, hist)
    loglik = fits[best].model.loglik
    stats["loglik"] = [model.loglik, loglik]  # the polish's own objective decides
    if loglik <= model.loglik:
        return None, stats
    history.extend(hist)
    stats["kept"] = True
    logger.info("IRLS: %d camera(s) moved to the rotation their edges agree on (%s)", res.cameras.size,
                ", ".join(stats["moved"][:5]))
    return (best, fits, trust), stats


def _final_problem(lossf: Loss, cfg: IRLSConfig, tau: float | None, model: Any, trust: str | None) -> str:
    """What the final reweighted problem is, in words, for the certificate's statement."""
    if tau is not None:
        return f"the trimmed least-squares cost (Talwar at {np.rad2deg(tau):.2g}°) of IRLS-{lossf.name}"
    if model is not None:
        how = "inlier-count trust, " if trust == "inliers" else ""
        return (f"the final reweighted least-squares cost of IRLS-{lossf.name} ({how}t-weights, ν={model.nu:g}, "
                f"s={np.rad2deg(model.s):.2g}°)")
    return f"the final reweighted least-squares cost of IRLS-{lossf.name} (α={cfg.alpha_deg:g}°)"
