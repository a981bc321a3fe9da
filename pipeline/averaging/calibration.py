"""Per-edge calibration of the two-view precisions H for IRLS-H, chosen by likelihood (issue 15, item 3).

H from two-view BA is overconfident by factors that differ from edge to edge and
exaggerates the anisotropy. Measured against the truth, for diagnosis only: per
eigen-direction of H, from the smallest to the largest eigenvalue, the median NEES (1 if
calibrated) is 4.4 / 18 / 41 on fountain-P11, 8.1 / 50 / 57 on castle-P30 and
1.9 / 1.2 / 6.2 on templeSparseRing; the per-edge log10 NEES has an interquartile range of
1.1, 2.0 and 0.43 (0.53 for a calibrated χ²₃). One global scale absorbs neither.

**Model.** Each edge's residual ``Δω_e`` (the left perturbation of docs/CONVENTIONS.md)
is drawn from ``(1 − ε) · t_ν(0, s² P_e⁻¹) + ε · Haar``: a Student-t in a *metric*
``P_e`` (a Gaussian whose covariance is inflated by a latent per-edge factor, which
absorbs edge-varying overconfidence) mixed with the residual of a Haar-random rotation
(outliers). The metrics tried (:func:`shape_metric`):

- ``iso``: ``P = I``; ``inliers``: ``P = (n_e / median n) I`` (trust from the inlier count);
- ``shrink:λ``: ``P = (1 − λ) Ĥ + λ tr(Ĥ)/3 · I``, ``Ĥ = H / median(tr H / 3)``: H shrunk
  towards its isotropic part (λ = 0: H itself; λ = 1: isotropic with H's magnitude);
- ``power:p``: ``P = Ĥ^p``;
- ``shape:p`` / ``shape-inl:p``: H's anisotropy alone (``Ĥ^p`` at unit mean eigenvalue),
  with magnitude 1 or ``n_e / median n``.

For each metric :func:`mixture_irls` runs EM from a robust isotropic start: the E-step
gives the inlier posterior γ and the latent precision ``u = (ν+3)/(ν + q/s²)``
(``q = Δωᵀ P Δω``); the rotation step is the block Gauss–Newton step of IRLS-H with
``H ← γ u P / s²`` (:func:`~pipeline.averaging.block.anisotropic_step`); (s, ε) are
updated in closed form; ν comes from a grid. The metric whose fit has the highest
log-likelihood per edge is kept (the likelihood includes ``½ log det P``, so every
metric is a density of the same residual vectors). Nothing reads the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.averaging.block import BlockLaplacianSolver, anisotropic_step, left_errors
from pipeline.averaging.kernel import REUSE_MIN_N, apply_update
from pipeline.averaging.mixture import NU_GRID, em_update, fit_mixture
from pipeline.averaging.stopping import StopRule, converged, robust_scale
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["shape_metric", "DEFAULT_METRICS", "MixtureFit", "mixture_irls", "check_metric"]

#: The metrics tried by default: every selection seen on the real scenes (shrink:0, shrink:0.5)
#: and on miscalibrated synthetic H (shape-inl:0.5), plus the isotropic ones.
DEFAULT_METRICS = ("iso", "inliers", "shrink:0", "shrink:0.5", "shrink:1", "shape-inl:0.5")
_KINDS = ("iso", "inliers", "shrink", "power", "shape", "shape-inl")


def check_metric(kind: str) -> None:
    """Raise ValueError unless ``kind`` names a metric of :func:`shape_metric`."""
    base, _, arg = kind.partition(":")
    if base not in _KINDS or (base in ("iso", "inliers")) != (arg == ""):
        raise ValueError(f"unknown metric {kind!r}; expected iso, inliers, shrink:<λ>, power:<p>, shape:<p> or "
                         "shape-inl:<p>")
    if arg:
        try:
            float(arg)
        except ValueError:
            raise ValueError(f"metric {kind!r}: {arg!r} is not a number") from None


def _sym_power(H: np.ndarray, p: float) -> np.ndarray:
    lam, V = np.linalg.eigh(0.5 * (H + np.swapaxes(H, 1, 2)))
    lam = np.maximum(lam, lam[:, -1:] * 1e-12)
    return np.einsum("mab,mb,mcb->mac", V, lam**p, V)


def shape_metric(vg: ViewGraph, kind: str) -> np.ndarray | None:
    """The metric ``P_e`` (M, 3, 3) of a candidate (module docstring), or None when ``vg`` cannot supply it."""
    check_metric(kind)
    M = vg.n_edges
    eye = np.broadcast_to(np.eye(3), (M, 3, 3))
    n = None if vg.inliers is None else np.maximum(np.asarray(vg.inliers, dtype=np.float64), 1.0)
    if kind == "iso":
        return eye.copy()
    if kind == "inliers":
        return None if n is None else eye * (n / np.median(n))[:, None, None]
    if vg.H is None:
        return None
    base, _, arg = kind.partition(":")
    H = 0.5 * (vg.H + np.swapaxes(vg.H, 1, 2))
    tr3 = np.trace(H, axis1=1, axis2=2) / 3.0
    Hn = H / np.median(tr3)
    p = float(arg)
    if base == "shrink":
        return (1.0 - p) * Hn + p * (tr3 / np.median(tr3))[:, None, None] * eye
    if base == "power":
        return _sym_power(Hn, p)
    S = _sym_power(Hn, p)
    S = S / (np.trace(S, axis1=1, axis2=2) / 3.0)[:, None, None]
    if base == "shape-inl":
        return None if n is None else S * (n / np.median(n))[:, None, None]
    return S


@dataclass
class MixtureFit:
    """The EM fit of one metric: rotations, (ν, s, ε), mean per-edge log-likelihood, posteriors, weights."""

    metric: str
    R: np.ndarray
    nu: float
    s: float
    eps: float
    loglik: float
    gamma: np.ndarray
    weights: np.ndarray
    iterations: int
    converged: bool


def _quadratic(vg: ViewGraph, R: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r, _, dom = left_errors(vg, R)
    return np.einsum("ma,mab,mb->m", dom, P, dom), np.sqrt(np.einsum("ma,ma->m", r, r))


def mixture_irls(vg: ViewGraph, R0: np.ndarray, metric: str, P: np.ndarray, rule: StopRule,
                 solver: BlockLaplacianSolver, nus: tuple[float, ...] = NU_GRID) -> MixtureFit:
    """EM / IRLS for the t + Haar mixture in the metric ``P`` (module docstring), from rotations ``R0``.

    Args:
        vg: the connected view graph.
        R0: (N, 3, 3) start (a robust isotropic solution).
        metric: the candidate's name.
        P: (M, 3, 3) its metric.
        rule: stopping rule (cost −Σ loglik; update against the isotropic robust scale).
        solver: the block solver of ``vg`` (its factor is reused across candidates).
        nus: ν grid (fixed during the iterations, re-chosen at the end).

    Returns:
        :class:`MixtureFit`: (ν, s, ε, ``loglik``) of the model refitted at the end (for the
        selection); ``weights`` ``γ u / s²`` and ``gamma`` of the last EM state, the final
        problem whose fixed point the rotations are.
    """
    half_logdet = 0.5 * np.linalg.slogdet(P)[1]
    n = vg.n_cameras
    R = R0.copy()
    q, theta = _quadratic(vg, R, P)
    model = fit_mixture(q, half_logdet, theta, n, nus)
    f_prev, ok, it = np.inf, False, 0
    for it in range(1, rule.max_iterations + 1):
        w, model = em_update(q, half_logdet, theta, model, n)
        f = -model.loglik * q.size
        dw = anisotropic_step(vg, R, solver, P, w, reuse=vg.n_cameras >= REUSE_MIN_N)
        if not np.all(np.isfinite(dw)):
            raise ViewGraphError(f"IRLS-H calibration ({metric}) step {it} is not finite; check H for NaN")
        R = apply_update(R, dw)
        q, theta = _quadratic(vg, R, P)
        step = float(np.sqrt(np.einsum("na,na->n", dw, dw)).max())
        if converged(f_prev, f, step, rule, robust_scale(theta)):
            ok = True
            break
        f_prev = f
    w, last = em_update(q, half_logdet, theta, model, n)  # the next step's weights: R is their fixed point
    model = fit_mixture(q, half_logdet, theta, n, nus, s0=last.s, eps0=max(last.eps, 1e-3))
    return MixtureFit(metric, R, model.nu, model.s, model.eps, model.loglik, last.gamma, w, it, ok)
