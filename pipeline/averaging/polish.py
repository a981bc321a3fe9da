"""The reweighted stages of the isotropic IRLS: the IRLS loop itself, its start branches and its polish.

- :func:`reweighted`: paper 1, Algorithm 1 (reweighted Laplacian steps), stopped by
  :mod:`~pipeline.averaging.stopping` (cost and largest update), each solve reusing the
  previous factor as a preconditioner (:meth:`LaplacianSolver.solve_reusing`);
- :func:`mixture_polish`: EM for the Student-t + Haar residual mixture of
  :mod:`~pipeline.averaging.mixture` (IRLS weight γ_e·u_e·m_e/s²: inlier posterior ×
  latent t precision × per-edge trust), with (s, ε) in closed form and ν from a grid by
  likelihood;
- :func:`talwar_polish`: least squares on the edges under τ = max(3.76 σ̂, 1°) (the
  polish of earlier versions);
- :func:`selection_cost`: the Cauchy-like cost that judges two start branches.

Pure functions on arrays and the view graph (no I/O, no logging); vectorized over edges.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from pipeline.averaging.kernel import LaplacianSolver, apply_update, graph_residuals
from pipeline.averaging.losses import get_loss
from pipeline.averaging.mixture import NU_GRID, MixtureModel, em_update, fit_mixture, noise_edges
from pipeline.averaging.stopping import StopRule, converged, robust_scale
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["residual_angles", "reweighted", "mixture_polish", "talwar_polish", "selection_cost", "TRIM_SIGMA"]

#: 99.7% point of σ·χ₃: the Talwar polish's threshold in units of the robust scale σ̂.
TRIM_SIGMA = 3.76

History = list[dict[str, float]]


def residual_angles(vg: ViewGraph, R: np.ndarray) -> np.ndarray:
    """(M,) residual angles ``‖log(R_jᵀ R̃_ij R_i)‖`` in radians."""
    r = graph_residuals(vg, R)
    return np.sqrt(np.einsum("ma,ma->m", r, r))


def selection_cost(theta: np.ndarray, s: float, nu: float = 1.0) -> float:
    """Student-t negative log-likelihood (up to constants) of residual angles ``theta`` (M,) at scale ``s``.

    ``Σ (ν+3)/2 · log(1 + θ²/(ν s²))``; with ν = 1 every residual costs something, but only
    logarithmically, so many inliers broken by a few degrees cost more than a few outliers
    left at 90°.
    """
    return float(0.5 * (nu + 3.0) * np.sum(np.log1p(np.square(theta / s) / nu)))


def reweighted(vg: ViewGraph, R: np.ndarray, solver: LaplacianSolver, weight_fn: Callable[[np.ndarray], np.ndarray],
               cost_fn: Callable[[np.ndarray], float], rule: StopRule, stage: str, t0: float, history: History
               ) -> tuple[np.ndarray, int, bool]:
    """Paper 1, Algorithm 1: reweighted Laplacian steps until :func:`~pipeline.averaging.stopping.converged`.

    Args:
        vg: the connected view graph.
        R: (N, 3, 3) start.
        solver: the Laplacian solver of ``vg``'s edges.
        weight_fn: edge weights (M,) from residual angles (M,).
        cost_fn: the cost whose decrease is tested, from residual angles.
        rule: the stopping rule.
        stage: the history's stage name.
        t0: the method's start time (``time.perf_counter``).
        history: one record per iteration is appended.

    Returns:
        The rotations, the iterations taken and whether the rule was met.
    """
    f_prev = np.inf
    it = 0
    for it in range(1, rule.max_iterations + 1):
        r = graph_residuals(vg, R)
        theta = np.sqrt(np.einsum("ma,ma->m", r, r))
        f = float(cost_fn(theta))
        phi = weight_fn(theta)
        # Paper 1, eq. 21 in our sign convention: (AᵀΦA) ΔΩ = AᵀΦ r.
        dw = solver.solve_reusing(phi, solver.AT @ (phi[:, None] * r))
        if not np.all(np.isfinite(dw)):
            raise ViewGraphError(f"IRLS step {it} ({stage}) is not finite; the weighted Laplacian is singular. "
                                 "Check for NaN rotations or try another loss")
        R = apply_update(R, dw)
        norms = np.sqrt(np.einsum("na,na->n", dw, dw))
        step = float(norms.max())
        history.append({"stage": stage, "cost": f, "mean_step_rad": float(norms.mean()), "max_step_rad": step,
                        "time_s": time.perf_counter() - t0})
        if converged(f_prev, f, step, rule, theta=theta):
            return R, it, True
        f_prev = f
    return R, it, False


def mixture_polish(vg: ViewGraph, R: np.ndarray, solver: LaplacianSolver, trust: np.ndarray | None, rule: StopRule,
                   t0: float, history: History, stage: str = "refine", nus: tuple[float, ...] = NU_GRID,
                   refit: bool = True, noise: tuple[np.ndarray | None, int] | None = None
                   ) -> tuple[np.ndarray, MixtureModel, np.ndarray, np.ndarray, int, bool]:
    """EM for the t + Haar residual mixture with isotropic per-edge trust ``trust`` (M,) or 1.

    The E-step weights ``γ u m / s²`` drive the scalar IRLS step; (s, ε) are re-estimated
    in closed form each iteration (10 inner EM steps, a degrees-of-freedom correction of
    s²); ν is chosen on :data:`~pipeline.averaging.mixture.NU_GRID` at the start and, with
    ``refit``, again at the end for the likelihood. The model is fitted to the edges on a cycle
    (``noise``: :func:`~pipeline.averaging.mixture.noise_edges` of ``vg``, computed where None).

    Returns:
        The rotations; the fitted model at them (``loglik``: mean per-edge log-likelihood,
        to compare polishes); the final problem's weights (M,), i.e. those the next step
        would use, of which the rotations are the fixed point; the inlier posteriors (M,);
        the iterations taken and whether the rule was met (False: stopped at its cap).
    """
    fit, n = noise_edges(vg.edges, vg.n_cameras) if noise is None else noise  # bridges say nothing of the noise
    m = np.ones(vg.n_edges) if trust is None else np.asarray(trust, dtype=np.float64)
    hl = 1.5 * np.log(m)  # ½ log det(m I)
    th = residual_angles(vg, R)
    state = {"model": fit_mixture(m * th * th, hl, th, n, nus, fit=fit)}

    def weights(theta: np.ndarray) -> np.ndarray:
        w, state["model"] = em_update(m * theta * theta, hl, theta, state["model"], n, fit=fit)
        return w * m

    R, it, ok = reweighted(vg, R, solver, weights, lambda theta: -state["model"].loglik * theta.size, rule, stage, t0,
                           history)
    th = residual_angles(vg, R)
    w_final = weights(th)
    last = state["model"]
    if not refit:
        return R, last, w_final, last.gamma, it, ok
    model = fit_mixture(m * th * th, hl, th, n, nus, s0=last.s, eps0=max(last.eps, 1e-3), fit=fit)
    return R, model, w_final, last.gamma, it, ok


def talwar_polish(vg: ViewGraph, R: np.ndarray, solver: LaplacianSolver, min_deg: float, rule: StopRule, t0: float,
                  history: History) -> tuple[np.ndarray, float]:
    """Least squares on the edges under τ = max(3.76 σ̂, ``min_deg``) (Talwar); returns (R, τ radians)."""
    tau = max(TRIM_SIGMA * robust_scale(residual_angles(vg, R)), float(np.deg2rad(min_deg)))
    tal = get_loss("talwar", float(np.rad2deg(tau)))
    R, _, _ = reweighted(vg, R, solver, tal.phi, lambda th: float(tal.rho(th).sum()), rule, "refine", t0, history)
    return R, tau
