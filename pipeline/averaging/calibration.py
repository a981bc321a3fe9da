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

For each metric :class:`MixtureEM` runs EM from a robust isotropic start: the E-step
gives the inlier posterior γ and the latent precision ``u = (ν+3)/(ν + q/s²)``
(``q = Δωᵀ P Δω``); the rotation step is the block Gauss–Newton step of IRLS-H with
``H ← γ u P / s²`` (:func:`~pipeline.averaging.block.anisotropic_step`); (s, ε) are
updated in closed form; ν comes from a grid. The metric whose fit has the highest
log-likelihood per edge is kept (the likelihood includes ``½ log det P``, so every
metric is a density of the same residual vectors). Nothing reads the truth. The candidates
race (:func:`race_metrics`): one that trails the leader by a wide margin after a few EM
iterations stops there, so that the selection costs about one EM run instead of six.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.averaging.block import BlockLaplacianSolver, anisotropic_step, left_errors
from pipeline.averaging.kernel import REUSE_MIN_N, apply_update
from pipeline.averaging.mixture import NU_GRID, em_update, fit_mixture, noise_edges
from pipeline.averaging.stopping import StopRule, converged, robust_scale
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["shape_metric", "DEFAULT_METRICS", "RACE_CHECKPOINTS", "MixtureFit", "MixtureEM", "mixture_irls",
           "race_metrics", "check_metric"]

#: The metrics tried by default: every selection seen on the real scenes (shrink:0, shrink:0.5)
#: and on miscalibrated synthetic H (shape-inl:0.5), plus the isotropic ones.
DEFAULT_METRICS = ("iso", "inliers", "shrink:0", "shrink:0.5", "shrink:1", "shape-inl:0.5")
#: The race of the candidates (:func:`race_metrics`): at EM iteration k, a candidate more than g nats per edge
#: behind the leader stops.
RACE_CHECKPOINTS = ((3, 0.3), (9, 0.15), (27, 0.075))
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


class MixtureEM:
    """EM / IRLS for the t + Haar mixture in the metric ``P`` (module docstring), from rotations ``R0``, one
    iteration per :meth:`step`, so that :func:`race_metrics` can run several candidates side by side.

    Args:
        vg: the connected view graph.
        R0: (N, 3, 3) start (a robust isotropic solution).
        metric: the candidate's name.
        P: (M, 3, 3) its metric.
        rule: stopping rule (cost −Σ loglik; update against the isotropic robust scale).
        solver: the block solver of ``vg`` (its factor is reused across candidates).
        nus: ν grid (fixed during the iterations, re-chosen at the end and by :meth:`loglik`).
    """

    def __init__(self, vg: ViewGraph, R0: np.ndarray, metric: str, P: np.ndarray, rule: StopRule,
                 solver: BlockLaplacianSolver, nus: tuple[float, ...] = NU_GRID,
                 noise: tuple[np.ndarray | None, int] | None = None) -> None:
        self.vg, self.metric, self.P, self.rule, self.solver, self.nus = vg, metric, P, rule, solver, nus
        self.half_logdet = 0.5 * np.linalg.slogdet(P)[1]
        self.R = R0.copy()
        self.q, self.theta = _quadratic(vg, self.R, P)
        # bridges say nothing of the noise; ``noise`` is :func:`noise_edges` of vg where the caller has it
        self.fit, self.n_fit = noise_edges(vg.edges, vg.n_cameras) if noise is None else noise
        self.model = fit_mixture(self.q, self.half_logdet, self.theta, self.n_fit, nus, fit=self.fit)
        self.f_prev, self.iterations, self.converged, self.done = np.inf, 0, False, rule.max_iterations < 1

    def step(self) -> bool:
        """One EM iteration (E-step, (s, ε), a rotation step); True once the rule is met or the cap reached."""
        if self.done:
            return True
        vg, n = self.vg, self.vg.n_cameras
        self.iterations += 1
        w, self.model = em_update(self.q, self.half_logdet, self.theta, self.model, self.n_fit, fit=self.fit)
        f = -self.model.loglik * self.q.size
        dw = anisotropic_step(vg, self.R, self.solver, self.P, w, reuse=n >= REUSE_MIN_N)
        if not np.all(np.isfinite(dw)):
            raise ViewGraphError(f"IRLS-H calibration ({self.metric}) step {self.iterations} is not finite; "
                                 "check H for NaN")
        self.R = apply_update(self.R, dw)
        self.q, self.theta = _quadratic(vg, self.R, self.P)
        step = float(np.sqrt(np.einsum("na,na->n", dw, dw)).max())
        self.converged = converged(self.f_prev, f, step, self.rule, robust_scale(self.theta))
        self.f_prev = f
        self.done = self.converged or self.iterations >= self.rule.max_iterations
        return self.done

    def loglik(self) -> float:
        """Mean per-edge log-likelihood at the current rotations, ν re-chosen from the grid (as the final fit's)."""
        return fit_mixture(self.q, self.half_logdet, self.theta, self.n_fit, self.nus, s0=self.model.s,
                           eps0=max(self.model.eps, 1e-3), fit=self.fit).loglik

    def result(self) -> MixtureFit:
        """The fit at the current rotations: (ν, s, ε, ``loglik``) refitted (for the selection); ``weights``
        ``γ u / s²`` and ``gamma`` of the last EM state, the final problem whose fixed point the rotations are."""
        n, fit = self.n_fit, self.fit
        w, last = em_update(self.q, self.half_logdet, self.theta, self.model, n, fit=fit)  # the next step's weights
        model = fit_mixture(self.q, self.half_logdet, self.theta, n, self.nus, s0=last.s, eps0=max(last.eps, 1e-3),
                            fit=fit)
        return MixtureFit(self.metric, self.R, model.nu, model.s, model.eps, model.loglik, last.gamma, w,
                          self.iterations, self.converged)


def mixture_irls(vg: ViewGraph, R0: np.ndarray, metric: str, P: np.ndarray, rule: StopRule,
                 solver: BlockLaplacianSolver, nus: tuple[float, ...] = NU_GRID) -> MixtureFit:
    """:class:`MixtureEM` run until its rule is met (or its cap); returns :meth:`MixtureEM.result`."""
    em = MixtureEM(vg, R0, metric, P, rule, solver, nus)
    while not em.step():
        pass
    return em.result()


def race_metrics(vg: ViewGraph, R0: np.ndarray, metrics: dict[str, np.ndarray], rule: StopRule,
                 solver: BlockLaplacianSolver, checkpoints: tuple[tuple[int, float], ...] = RACE_CHECKPOINTS
                 ) -> tuple[dict[str, MixtureFit], dict[str, dict[str, float]]]:
    """One :class:`MixtureEM` per candidate metric, run side by side; a candidate whose log-likelihood trails the
    leader's by more than the margin at a checkpoint stops there.

    Each checkpoint ``(k, g)``: every candidate still running is advanced to iteration ``k`` (or its end), then
    each is scored by :meth:`MixtureEM.loglik` (ν re-chosen, as the final selection does); those more than ``g``
    (nats per edge) below the best are dropped. The others run to their end. EM raises a candidate's likelihood
    every iteration, and by little after the first few: on 26 view graphs (the three real scenes, the rendered
    turntables, streets, rings and grids, and the miscalibrated-H protocols, N = 11–1000) the metric chosen at
    convergence led when scored so at iterations 3, 5, 10, 15 and 20, while the others trailed it by 0.07–0.85
    nats per edge at the end (notes/issue-15.md, last section). With ``checkpoints=()`` every candidate runs to its end (the selection before the race).

    Returns:
        The fits of the candidates that ran to their end (the selection is among them), and for each dropped one
        ``{"checkpoint", "iterations", "loglik", "behind"}``: where it stopped, the EM iterations it ran (fewer
        where it had converged before), its score and how far behind the leader's (nats per edge).
    """
    noise = noise_edges(vg.edges, vg.n_cameras)  # once for every candidate
    ems = {name: MixtureEM(vg, R0, name, P, rule, solver, noise=noise) for name, P in metrics.items()}
    dropped: dict[str, dict[str, float]] = {}
    for k, margin in checkpoints:
        alive = [e for name, e in ems.items() if name not in dropped]
        if len(alive) < 2:
            break
        for em in alive:
            while em.iterations < k and not em.step():
                pass
        score = {em.metric: em.loglik() for em in alive}
        lead = max(score.values())
        for name, ll in score.items():
            if ll < lead - margin:
                dropped[name] = {"checkpoint": k, "iterations": ems[name].iterations, "loglik": ll, "behind": lead - ll}
    fits = {}
    for name, em in ems.items():
        if name not in dropped:
            while not em.step():
                pass
            fits[name] = em.result()
    return fits, dropped
