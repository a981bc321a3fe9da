"""The residual model of the IRLS polish (:mod:`~pipeline.averaging.polish`) and of the IRLS-H calibration
(:mod:`~pipeline.averaging.calibration`).

Each edge's residual vector ``r_e`` (3,) is drawn from

    (1 − ε) · t_ν(0, s² P_e⁻¹)  +  ε · Haar

a 3-D Student-t in a per-edge metric ``P_e`` (a Gaussian whose covariance is inflated by a latent
Gamma-distributed factor per edge), mixed with the density of the residual of a Haar-random relative
rotation (the outliers). Everything is in terms of ``q_e = r_eᵀ P_e r_e``, ``½ log det P_e`` and the
residual angle ``θ_e = ‖r_e‖`` (for the outlier density), so the isotropic case (``P = m I``) and the
anisotropic one share the code. All functions are vectorized over edges; the fit also over a grid of ν.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaln

from pipeline.graph.flags import bridges, two_edge_blocks

__all__ = ["NU_GRID", "EPS_MAX", "log_haar", "mixture_terms", "fit_mixture", "MixtureModel", "em_update", "dof_factor",
           "noise_edges"]

#: ν tried when fitting (1: Cauchy-like … 32: nearly Gaussian).
NU_GRID = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 16.0, 32.0)
#: Cap of the outlier share ε: uncapped, a sparse graph's likelihood rises by calling edges outliers and
#: fitting the rest exactly (templeSparseRing, 31 edges for 16 cameras: ε = 0.48 and s → 0).
EPS_MAX = 0.3
#: EM on fixed residuals stops early once (s, ε) change by less than this (relative s, absolute ε).
EM_TOL = 1e-6


def log_haar(theta: np.ndarray) -> np.ndarray:
    """log density, in rotation-vector space, of the residual of a Haar-random relative rotation.

    The angle of a Haar rotation has density (1 − cos θ)/π on [0, π]; spread over the sphere of radius
    θ: ``p(r) = (1 − cos θ) / (4π² θ²)`` (→ 1/(8π²) as θ → 0).
    """
    th = np.maximum(theta, 1e-6)
    return np.log(np.maximum(1.0 - np.cos(th), 1e-300)) - np.log(4.0 * np.pi**2 * th * th)


def mixture_terms(q: np.ndarray, half_logdet: np.ndarray, lh: np.ndarray, s: float | np.ndarray,
                   nu: float | np.ndarray, eps: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-edge log-likelihood, inlier posterior γ and latent precision u = (ν+3)/(ν + q/s²).

    Broadcasts: q, half_logdet, lh (M,) or (1, M); s, nu, eps scalars or (K, 1).

    The log-sum-exp ``m + log(exp(a − m) + exp(b − m))``, ``m = max(a, b)``, is evaluated as
    ``m + log(1 + exp(−|a − b|))``: one of its two exponentials is exp(0) = 1 exactly and the other's argument is
    ±(a − b) exactly, so the values are the same to the last bit with one exponential fewer; every (K, M) pass
    writes in place (EM calls this hundreds of times per IRLS run).
    """
    lt = np.empty(np.broadcast_shapes(*map(np.shape, (q, half_logdet, lh, s, nu, eps))))
    np.divide(q, nu * s * s, out=lt)
    np.log1p(lt, out=lt)
    lt *= 0.5 * (nu + 3.0)
    np.subtract(gammaln(0.5 * (nu + 3.0)) - gammaln(0.5 * nu) - 1.5 * np.log(nu * np.pi) - 3.0 * np.log(s)
                + half_logdet, lt, out=lt)
    a = np.add(np.log1p(-eps), lt, out=lt)
    b = np.log(eps) + lh
    ll = np.subtract(a, b)
    np.abs(ll, out=ll)
    np.negative(ll, out=ll)
    np.exp(ll, out=ll)
    ll += 1.0
    np.log(ll, out=ll)
    ll += np.maximum(a, b)
    gamma = np.subtract(a, ll, out=a)
    u = nu + q / (s * s)
    return ll, np.exp(gamma, out=gamma), np.divide(nu + 3.0, u, out=u)


@dataclass
class MixtureModel:
    """Fitted (ν, s, ε), the mean per-edge log-likelihood and the inlier posteriors γ (M,)."""

    nu: float
    s: float
    eps: float
    loglik: float
    gamma: np.ndarray


def dof_factor(gamma: np.ndarray, n_cameras: int) -> float:
    """``M_in/(M_in − N + 1)``: fitted residuals are shorter than the noise (3(N − 1) of the 3 M_in
    inlier residual dimensions are absorbed by the rotations); the s² update is multiplied by it."""
    m_in = float(np.sum(gamma))
    return m_in / max(m_in - n_cameras + 1, 1.0)


def noise_edges(edges: np.ndarray, n: int) -> tuple[np.ndarray | None, int]:
    """The edges whose residuals say something of the noise, and the ``n_cameras`` of their fit.

    A bridge (an edge in no cycle) is fitted exactly by any rotations: its residual is zero whatever its
    error. Left in the fit, a sparse graph's bridges (a dark turntable: 10 of 19 edges) pull s towards zero
    and the Student-t then calls every edge of a cycle an outlier; their likelihood also rewards a metric for
    claiming a high precision where nothing can contradict it. Cut out (as integrating the rotations out of
    the likelihood would: a bridge's precision cancels), the cycles alone inform (s, ε, ν), with the
    degrees-of-freedom correction for the rotations they fit: ``N − C'`` of them, C' the blocks left when
    the B bridges are cut (B + 1 in a connected graph).

    Returns:
        (M,) bool of the non-bridge edges, or None where every edge counts (no bridge, or no cycle at all),
        and the ``n_cameras`` to pass with them (``N − B`` where the graph is connected).
    """
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    br = bridges(edges, n)
    if not br.any() or br.all():
        return None, n
    blocks = int(two_edge_blocks(edges, n, np.ones(len(edges), bool), br).max()) + 1
    return ~br, n - blocks + 1


def _check_fit(fit: np.ndarray) -> None:
    """A ``fit`` mask must select an edge: a model fitted to none would be NaN (:func:`noise_edges` returns None
    rather than an empty mask)."""
    if not np.any(fit):
        raise ValueError("fit selects no edge: pass fit=None to fit every edge")


def fit_mixture(q: np.ndarray, half_logdet: np.ndarray, theta: np.ndarray, n_cameras: int | None = None,
                nus: tuple[float, ...] = NU_GRID, iterations: int = 25,
                s0: float | None = None, eps0: float = 0.1, eps_max: float = EPS_MAX,
                max_grid_edges: int = 3000, fit: np.ndarray | None = None) -> MixtureModel:
    """EM for (s, ε) on fixed residuals, every ν of the grid at once; the best ν by likelihood.

    Args:
        q: (M,) ``rᵀ P r``; half_logdet: (M,) ``½ log det P``; theta: (M,) ``‖r‖`` (radians).
        n_cameras: N for the degrees-of-freedom correction of s² (None: no correction).
        nus: ν grid. iterations: EM iterations. s0, eps0: start. eps_max: cap of ε (a robust
            estimator cannot resolve more outliers; uncapped, a sparse graph's likelihood rises by
            calling edges outliers and fitting the rest exactly).
        max_grid_edges: the grid search runs on an evenly strided subsample of at most this many
            edges (it only picks ν); (s, ε) are then refitted on all edges for the chosen ν.
        fit: (M,) bool, the edges the model is fitted to (:func:`noise_edges`; None: all); ``loglik`` is
            their mean, ``gamma`` every edge's posterior under the fitted model.
    """
    if fit is not None:
        _check_fit(fit)
        q, half_logdet, theta = (np.asarray(a, dtype=np.float64) for a in (q, half_logdet, theta))
        sub = fit_mixture(q[fit], half_logdet[fit], theta[fit], n_cameras, nus, iterations, s0, eps0, eps_max,
                          max_grid_edges)
        gamma = np.empty(q.size)
        gamma[fit] = sub.gamma
        gamma[~fit] = mixture_terms(q[~fit], half_logdet[~fit], log_haar(theta[~fit]), sub.s, sub.nu, sub.eps)[1]
        return MixtureModel(sub.nu, sub.s, sub.eps, sub.loglik, gamma)
    q_all = np.asarray(q, dtype=np.float64)
    if len(nus) > 1 and q_all.size > max_grid_edges:
        idx = np.linspace(0, q_all.size - 1, max_grid_edges).astype(np.int64)
        sub = fit_mixture(q_all[idx], np.asarray(half_logdet)[idx], np.asarray(theta)[idx], None, nus,
                          iterations, s0, eps0, eps_max)
        return fit_mixture(q_all, half_logdet, theta, n_cameras, (sub.nu,), max(iterations // 2, 5), sub.s,
                           max(sub.eps, 1e-3), eps_max)
    return _fit(np.asarray(q, dtype=np.float64), np.asarray(half_logdet, dtype=np.float64),
                log_haar(np.asarray(theta, dtype=np.float64)), n_cameras, nus, iterations, s0, eps0, eps_max)


def _fit(q: np.ndarray, half_logdet: np.ndarray, lh: np.ndarray, n_cameras: int | None, nus: tuple[float, ...],
         iterations: int, s0: float | None, eps0: float, eps_max: float) -> MixtureModel:
    """:func:`fit_mixture`'s EM on all the edges given, with the outlier densities ``lh`` = :func:`log_haar` (θ)."""
    return _fit_terms(q, half_logdet, lh, n_cameras, nus, iterations, s0, eps0, eps_max)[0]


def _fit_terms(q: np.ndarray, half_logdet: np.ndarray, lh: np.ndarray, n_cameras: int | None,
               nus: tuple[float, ...], iterations: int, s0: float | None, eps0: float, eps_max: float
               ) -> tuple[MixtureModel, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`_fit`, and the chosen ν's :func:`mixture_terms` (M,) at the fitted (s, ε): (ll, γ, u)."""
    q = q[None]
    hl = half_logdet[None]
    lh = lh[None]
    nu = np.asarray(nus, dtype=np.float64)[:, None]
    s = np.full_like(nu, s0 if s0 is not None else max(np.sqrt(np.median(q) / 2.366), 1e-12))
    eps = np.full_like(nu, eps0)
    for _ in range(iterations):
        _, g, u = mixture_terms(q, hl, lh, s, nu, eps)
        gs = np.maximum(g.sum(1, keepdims=True), 1e-12)
        dof = gs / np.maximum(gs - n_cameras + 1, 1.0) if n_cameras else 1.0
        s_new = np.maximum(np.sqrt(dof * np.sum(g * u * q, 1, keepdims=True) / (3.0 * gs)), 1e-12)
        eps_new = np.clip(1.0 - g.mean(1, keepdims=True), 1e-4, eps_max)
        settled = np.all(np.abs(s_new - s) <= EM_TOL * s) and np.all(np.abs(eps_new - eps) <= EM_TOL)
        s, eps = s_new, eps_new
        if settled:  # EM has converged on these residuals: further iterations change nothing visible
            break
    ll, g, u = mixture_terms(q, hl, lh, s, nu, eps)
    k = int(np.argmax(ll.mean(1)))
    model = MixtureModel(float(nu[k, 0]), float(s[k, 0]), float(eps[k, 0]), float(ll[k].mean()), g[k])
    return model, (ll[k], g[k], u[k])


def em_update(q: np.ndarray, half_logdet: np.ndarray, theta: np.ndarray, model: MixtureModel,
              n_cameras: int | None = None, eps_max: float = EPS_MAX, inner: int = 10,
              fit: np.ndarray | None = None) -> tuple[np.ndarray, MixtureModel]:
    """E-step + M-step of (s, ε) at the current residuals (ν fixed); returns the rotation step's weights.

    ``inner`` EM iterations on (s, ε) with the rotations fixed come first (cheap, no linear solve):
    with a single one the scale crawls (castle-P30: 100 outer iterations, the cost still falling
    by 1e-4 per step while the largest camera update was already 4e-7 rad); with 10 the outer loop
    converges in about 10 iterations.

    With ``fit`` (:func:`noise_edges`), (s, ε) and the likelihood come from those edges alone; the weights
    and posteriors of the others (bridges) are evaluated at the same (s, ε).

    Returns:
        the IRLS weights ``γ u / s²`` (M,) of the rotation M-step (a weighted least squares in the
        metric P), and the updated model.
    """
    if fit is not None:
        _check_fit(fit)
    q_all = np.asarray(q, dtype=np.float64)
    hl_all = np.asarray(half_logdet, dtype=np.float64)
    lh_all = log_haar(np.asarray(theta, dtype=np.float64))  # once, for the inner EM and the step's weights
    q, half_logdet, lh = (q_all, hl_all, lh_all) if fit is None else (q_all[fit], hl_all[fit], lh_all[fit])
    if inner > 1:  # the inner EM ends with the terms at its (s, ε), which are the step's: not evaluated again
        model, (ll, g, u) = _fit_terms(q, half_logdet, lh, n_cameras, (model.nu,), inner - 1, model.s,
                                       max(model.eps, 1e-4), eps_max)
    else:
        ll, g, u = mixture_terms(q, half_logdet, lh, model.s, model.nu, model.eps)
    dof = dof_factor(g, n_cameras) if n_cameras else 1.0
    s = max(float(np.sqrt(dof * np.sum(g * u * q) / (3.0 * max(float(g.sum()), 1e-12)))), 1e-12)
    eps = float(np.clip(1.0 - g.mean(), 1e-4, eps_max))
    loglik = float(ll.mean())
    if fit is not None:  # the other edges' terms at the step's (s, ε); the fitted edges' are those above
        g_all, u_all = np.empty(q_all.size), np.empty(q_all.size)
        g_all[fit], u_all[fit] = g, u
        _, g_all[~fit], u_all[~fit] = mixture_terms(q_all[~fit], hl_all[~fit], lh_all[~fit], model.s, model.nu,
                                                    model.eps)
        g, u = g_all, u_all
    w = g * u / (model.s * model.s)
    return w, MixtureModel(model.nu, s, eps, loglik, g)
