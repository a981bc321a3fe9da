"""Robust losses and the Levenberg–Marquardt iteration of the two-view BA.

Levenberg–Marquardt with IRLS weights of a robust loss (Huber or Cauchy) on each
point's 4-vector of pixel residuals. Every iteration eliminates the points
exactly (:mod:`pipeline.geometry.ba_hessian`), solves the damped 5×5 pose
system and moves each point by its Gauss–Newton step given the pose step. At
n ≈ 1000 the time is set by the number of numpy calls, not by the arithmetic,
so the hot path works on whole (k, n) blocks in place: about 2–3 ms of CPU for
1000 points.
"""

from __future__ import annotations

import numpy as np

from pipeline.geometry.ba_hessian import linearize, point_step, reduced_system
from pipeline.geometry.ba_model import exp3, point_s2, project

__all__ = ["LOSSES", "CHI2_1_MEDIAN", "robust_loss", "robust_cost", "robust_sigma", "levenberg_marquardt"]

LOSSES = ("none", "huber", "cauchy")
# Median of a χ²₁ variable: each inlier point's squared residual is ≈ σ²·χ²₁
# (4 residuals, 3 point unknowns), so median(‖r_k‖²)/0.4549 estimates σ² robustly.
CHI2_1_MEDIAN = 0.454936
# Residual standing in for an observation behind camera j, so that the cost
# penalizes (and LM rejects) steps that push a point behind a camera.
_INVALID_RESIDUAL2 = 1e12


def robust_loss(s2: np.ndarray, loss: str, c: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust cost ρ(s²) (px², ρ(s²) = s² near 0) and the IRLS weight ρ'(s²)."""
    if loss == "none":
        return s2, np.ones(s2.shape)
    c2 = c * c
    if loss == "huber":
        s = np.sqrt(s2)
        inside = s <= c
        return np.where(inside, s2, 2.0 * c * s - c2), np.where(inside, 1.0, c / np.maximum(s, 1e-300))
    # cauchy
    q = s2 / c2
    rho = np.log1p(q)
    rho *= c2
    q += 1.0
    return rho, np.divide(1.0, q, out=q)


def robust_cost(r: np.ndarray, valid: np.ndarray, active: np.ndarray, loss: str, c: float,
                s2: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """½ Σ_active ρ(‖r_k‖²), the IRLS weights (0 outside ``active`` and behind camera j)
    and the squared point residuals (n,) (``_INVALID_RESIDUAL2`` behind camera j).

    ``active`` is a (n,) 0/1 float mask; ``s2`` may pass the squared residuals if known.
    """
    all_valid = bool(valid.all())
    if s2 is None:
        s2 = point_s2(r)
        if not all_valid:
            s2[~valid] = _INVALID_RESIDUAL2
    rho, w = robust_loss(s2, loss, c)
    # w is a fresh array (for loss "none" a new array of ones).
    w *= active
    if not all_valid:
        w[~valid] = 0.0
    return 0.5 * float(rho @ active), w, s2


def robust_sigma(s2: np.ndarray) -> float:
    """σ from the median squared point residual (each ≈ σ²·χ²₁ for inliers)."""
    n = s2.size
    if n == 0:
        return 1.0
    # np.median by hand (its generic path costs more than the selection itself):
    # the same order statistics and the same mean of the middle pair; position
    # n − 1 of the partition holds a NaN if there is one.
    h = n // 2
    part = np.partition(s2, (h - 1, h, n - 1) if n % 2 == 0 and h > 0 else (h, n - 1))
    if np.isnan(part[n - 1]):
        return float("nan")
    med = (part[h - 1] + part[h]) / 2.0 if n % 2 == 0 else part[h]
    return float(np.sqrt(max(med / CHI2_1_MEDIAN, 1e-12)))


def levenberg_marquardt(R, t, P, xi, xj, Ki, Kj, active, loss, c, tol, max_iterations, fix_pose, adapt_scale=None, state=None, cache=None, focal=None):
    """Levenberg–Marquardt with IRLS weights on the robust cost.

    Each iteration eliminates the points exactly (:func:`reduced_system`), damps
    the 5×5 pose system (Marquardt: ``S + λ diag(S)``), solves it, and moves each
    point by its Gauss–Newton step given the pose step. ``active`` (n,) selects
    the points in the cost; the others are frozen. With ``fix_pose`` only the
    points move. With ``adapt_scale = k`` the loss scale shrinks to ``k·σ̂``
    (median-based) after each accepted step, never grows, and the cost is
    re-evaluated at the new scale so that every comparison uses one scale.
    With ``focal`` (:class:`pipeline.geometry.ba_focal.FocalUnknowns`, m > 0) the
    system is (5+m)×(5+m) and the accepted focal lengths are kept in it; ``Ki``,
    ``Kj`` must then be its current ones.

    Returns:
        ``R, t, P, (r, valid, aux), w, history, iterations, converged, c``;
        ``state`` = ``(r, valid, aux)`` of :func:`project` at the input, if known;
        ``cache`` (see :func:`linearize`) shares the Jacobian of a state with the caller.
    """
    if focal is not None and focal.m == 0:
        focal = None
    if focal is not None and fix_pose:
        raise ValueError("fix_pose moves the points only; it cannot refine the focal lengths")
    r, valid, aux = state if state is not None else project(R, t, P, xi, xj, Ki, Kj)
    active_b = np.asarray(active, dtype=bool)
    all_active = bool(active_b.all())
    active = active_b.astype(np.float64)
    cost, w, s2 = robust_cost(r, valid, active, loss, c)
    history = [cost]
    lam = 1e-4
    iterations = 0
    converged = False
    while iterations < max_iterations:
        iterations += 1
        B, J, nv, j, nden = linearize(R, t, P, Kj, Ki, aux, cache)
        if focal is not None:
            Jf = focal.jacobian(P, Ki, Kj, aux)
            j = np.vstack([j, focal.reduced(nv, Jf)])
        frozen = w <= 0.0
        any_frozen = bool(frozen.any())
        if not fix_pose:
            S, g = reduced_system(r, w, J, nv, j)
            dS = np.diag(S).copy()
            floor = 1e-12 * max(float(dS.max()), 1e-300)
            Jc = J[:, :5]
            neg_g = -g
        accepted = False
        for trial in range(12):
            if fix_pose:
                dc = np.zeros(5)
                s_ = r
            else:
                Sd = S.copy()
                Sd.flat[::S.shape[0] + 1] += lam * dS + floor  # S + diag(λ dS + floor)
                dc = np.linalg.solve(Sd, neg_g)
                s_ = r.copy()
                s_[2:] += dc[:5] @ Jc
                if focal is not None:
                    s_ += np.einsum("a,ran->rn", dc[5:], Jf)
            dp = point_step(s_, nv, J, Ki, nden)
            if any_frozen:
                np.copyto(dp, 0.0, where=frozen)  # dp[:, frozen] = 0, without fancy indexing
            if trial >= 4:
                # The pose damping alone did not help: shorten the point steps too.
                dp *= 0.5 ** (trial - 3)
            # NaN and inf propagate into a sum: one reduction checks every entry.
            if not np.isfinite(float(dc.sum()) + float(dp.sum())):
                lam *= 10.0
                continue
            R_new = exp3(dc[:3]) @ R
            t_new = t + B @ dc[3:5]
            t_new /= np.sqrt(t_new @ t_new)
            P_new = P + dp
            Ki_new, Kj_new = Ki, Kj
            if focal is not None:
                phi_new = focal.phi + dc[5:]
                if not focal.admissible(phi_new):
                    lam *= 10.0
                    continue
                Ki_new, Kj_new = focal.Ks(phi_new)
            r_new, valid_new, aux_new = project(R_new, t_new, P_new, xi, xj, Ki_new, Kj_new)
            cost_new, w_new, s2_new = robust_cost(r_new, valid_new, active, loss, c)
            if cost_new <= cost:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            # No damping gives a decrease: a (numerical) minimum.
            converged = True
            break
        decrease = cost - cost_new
        R, t, P = R_new, t_new, P_new
        if focal is not None:
            Ki, Kj = Ki_new, Kj_new
            focal.accept(phi_new, Ki, Kj)
        r, valid, aux, w, s2 = r_new, valid_new, aux_new, w_new, s2_new
        cost = cost_new
        history.append(cost)
        lam = max(lam / 10.0, 1e-10)
        rescaled = False
        if adapt_scale is not None:
            c_new = adapt_scale * robust_sigma(s2 if all_active and valid.all() else s2[valid & active_b])
            if c_new < 0.9 * c:
                c, rescaled = c_new, True
                cost, w, s2 = robust_cost(r, valid, active, loss, c, s2)
        # Relative test, with an absolute floor (1e-14 px² per point) for noise-free data.
        if not rescaled and decrease <= tol * cost + 1e-14 * P.shape[1]:
            converged = True
            break
    return R, t, P, (r, valid, aux), w, history, iterations, converged, c

