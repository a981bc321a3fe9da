"""The two-view bundle adjustment of one pair and its rotation precision ``H_ij`` (:func:`refine_pair`).

For a pair (i, j) this refines the relative pose and the points by a robust
Levenberg–Marquardt bundle adjustment (:mod:`pipeline.geometry.ba_lm`) and turns
its Gauss–Newton Hessian into the precision of the relative rotation
(DESIGN.md, "The two-view Hessian"):

* **Outliers.** After the robust fit, points whose leave-one-out squared
  residual ``‖r_k‖² / (1 − h_k)`` (``h_k`` the point's leverage) exceeds
  ``inlier_chi2 · σ²`` (σ known) or, with σ estimated from the median of those
  statistics, the F(1, 0.369·n) quantile of the same tail probability
  (:func:`studentized_threshold`), or that lie more than 3 sd behind camera i, are dropped
  and the pose is refined again by plain least squares on the inliers
  (DESIGN.md: "drop points with large error and refine again"); the dropped
  points are checked once more at the new pose. ``H`` is then the Gauss–Newton
  precision of a least-squares estimate on Gaussian data: the case in which it
  is calibrated.
* **Precision.** ``H_full = JᵀWJ / σ²`` at the optimum. The points are
  eliminated block by block, then the translation block
  (:mod:`pipeline.geometry.ba_hessian`), leaving ``H_ij`` (3, 3) in 1/rad² for
  ``Δω`` with ``R_true = exp([Δω]×) R̂``. σ² is either the known pixel variance
  or ``Σ r² / (2·n_obs − n_params)``; with n inlier points there are
  ``2·n_obs = 4n`` residuals and ``n_params = 3n + 5`` unknowns, so the
  denominator is ``n − 5``; it is divided by the mean of χ²₁ truncated at the
  inlier threshold used (0.988 at 10.83), so the cut tail does not bias it. When the final
  refit is switched off, IRLS weights are used: ``Σ w r² / (Σ w − 5)``.
  With σ² estimated from ν residual degrees of freedom the rotation's error
  is a Student-t with ν dof, not a Gaussian: its covariance is ``ν/(ν − 2)``
  times ``σ̂² S⁻¹``, so H (and ``H_pose``, the focal sd) carry that factor and
  the mean NEES is 3 at any ν (without it, ``3ν/(ν − 2)``: 3.6 at 16 points).
* **Pure rotation.** The translation block is eliminated with a
  pseudo-inverse, so a zero-baseline pair still gets a finite H; a zero ``t0``
  (as a front end may report there) is replaced by the epipolar least-squares t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from pipeline.core import so3
from pipeline.core.config import option
from pipeline.core.errors import PipelineError
from pipeline.core.parallel import ExecutorOptions
from pipeline.geometry.ba_focal import FocalUnknowns, focal_columns
from pipeline.geometry.ba_hessian import linearize, marginalize_translation, pinv_sym, reduced_system
from pipeline.geometry.ba_lm import levenberg_marquardt, robust_sigma
from pipeline.geometry.ba_model import point_s2, project, translation_from_rotation, triangulate

__all__ = ["BAConfig", "PairBAResult", "TwoViewBAError", "refine_pair"]


class TwoViewBAError(PipelineError):
    """A pair the two-view bundle adjustment cannot process."""


@dataclass(frozen=True, kw_only=True)
class BAConfig(ExecutorOptions):
    """Options of the two-view bundle adjustment (YAML section ``two_view_ba``)."""

    SECTION = "two_view_ba"

    enabled: bool = option(True, "run the BA; false keeps the RANSAC pose, triangulates the points "
                                 "(points-only refinement at that pose) and computes H there")
    sigma_px: float | None = option(None, "known pixel noise σ (px); null estimates σ² from the residuals", gt=0)
    loss: Literal["none", "huber", "cauchy"] = option("cauchy", "robust loss on each point's residual norm")
    loss_scale_px: float | None = option(None, "scale c of the robust loss (px); null: loss_scale_sigmas times σ "
                                               "(the known one, else a median-based estimate at the start)", gt=0)
    loss_scale_sigmas: float = option(3.0, "robust loss scale in units of σ (see loss_scale_px)", gt=0)
    refit_inliers: bool = option(True, "after the robust fit, drop the points beyond the inlier threshold and "
                                       "refine again by least squares; H and σ² then come from the inliers")
    inlier_chi2: float = option(10.83, "a point is an inlier when ‖r_k‖²/(1 − h_k) ≤ inlier_chi2·σ² for a known σ "
                                       "(10.83: the 99.9% quantile of χ²₁, one redundant residual per point); with σ "
                                       "estimated, the studentized threshold of the same tail probability", gt=0)
    max_iterations: int = option(50, "LM iterations (linearizations) per fit", ge=1)
    tol: float = option(1e-6, "stop when the relative cost decrease falls below this", ge=0)
    min_points: int = option(12, "pairs with fewer (inlier) points are rejected (5 pose unknowns + σ² need "
                                 ">= 6)", ge=6)
    refine_focal: Literal["auto", "none", "shared", "per_camera"] = option(
        "auto", "refine the focal length of cameras whose intrinsics are not known (estimated, EXIF or default), "
                "marginalized into H with the translation: none, one shared by the pair, or one per camera; "
                "auto: per camera for the images whose focal the cameras stage estimated on its own (per-image "
                "view-graph calibration), none for the others; known intrinsics are never refined")
    workers: int = option(2, "processes refining pairs (1 = in this process)", ge=1, runtime=True)
    chunk_size: int = option(8, "pairs per task sent to a worker (and per resumable chunk)", ge=1, runtime=True)
    progress: bool = option(True, "show a progress bar", runtime=True)


@dataclass
class PairBAResult:
    """Refined pose, points and rotation precision of one pair.

    Attributes:
        R: (3, 3) refined ``R_ij = R_j R_iᵀ``.
        t: (3,) refined unit translation, ``x_j = R x_i + t``.
        points: (n, 3) points in camera i (NaN for points at or beyond infinity, ρ ≤ 0).
        point_params: (n, 3) (a, b, ρ): normalized ray in camera i and inverse depth.
        residuals: (n, 4) pixel residuals (image i x, y, image j x, y) at the optimum.
        sigma2: pixel noise variance used for ``H`` (px²): known or estimated.
        sigma2_estimated: True when ``sigma2`` was estimated from the residuals.
        variance_inflation: ``ν/(ν − 2)`` for σ² estimated from ν residual degrees of
            freedom (the Student-t covariance), 1 for a known σ: ``H = S_rot / (σ² ·
            variance_inflation)``.
        H: (3, 3) precision of ``Δω`` (1/rad²), ``R_true = exp([Δω]×) R``; with ``sigma2``
            estimated, the inverse covariance of the Student-t error, ``(ν − 2)/ν · S_rot/σ̂²``.
        H_pose: (5, 5) precision of (δ, δt) with the points marginalized (same factor).
        iterations: LM linearizations over all fits (robust + refit).
        inlier_mask: (n,) points kept for the final fit and for ``H``.
        cost_history: robust cost (½ Σ ρ(‖r_k‖²), px²) after each accepted step,
            starting with the initial cost; the refit's history follows.
        converged: every fit met ``tol`` before ``max_iterations``.
        t_basis: (3, 2) tangent basis of ``t`` used for ``H_pose``.
        K_i, K_j: (3, 3) intrinsics at the optimum (refined when focal lengths were unknowns).
        focal_log_sd: (m,) marginal sd of the refined log focal scales (relative: 0.01 = 1%).
    """

    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    point_params: np.ndarray
    residuals: np.ndarray
    sigma2: float
    sigma2_estimated: bool
    H: np.ndarray
    H_pose: np.ndarray
    iterations: int
    inlier_mask: np.ndarray
    cost_history: list[float] = field(default_factory=list)
    converged: bool = True
    variance_inflation: float = 1.0
    t_basis: np.ndarray | None = None
    K_i: np.ndarray | None = None
    K_j: np.ndarray | None = None
    focal_log_sd: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n_inliers(self) -> int:
        return int(self.inlier_mask.sum())

    @property
    def rms_px(self) -> float:
        """RMS of the inliers' residual components (px)."""
        r = self.residuals[self.inlier_mask]
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


#: Relative efficiency of σ² from the median of n χ²₁ draws against the mean-square estimate
#: (asymptotic variance 1/(4 n f(m)²) of the median m = 0.455 of χ²₁, f its density there):
#: the median-based σ² has the precision of a mean square with 0.369·n degrees of freedom.
MEDIAN_SIGMA2_EFFICIENCY = 0.369


def studentized_threshold(chi2: float, dof: float) -> float:
    """The inlier threshold on ``stat/σ̂²`` when σ̂² has ``dof`` degrees of freedom.

    An inlier's leave-one-out statistic over an independent σ̂² is F(1, ν), not χ²₁:
    keep the false-rejection rate of ``chi2`` as a χ²₁ threshold (0.1% at 10.83).
    With a median-based σ̂² over 16 points (ν ≈ 6) the χ²₁ threshold alone drops 1.7% of
    the inliers instead of 0.1% (with the residuals' 1 − h shrinkage as well, 2.4% measured),
    which biases σ̂² low and H overconfident.
    """
    from scipy.special import chdtrc, fdtri  # noqa: PLC0415

    if not math.isfinite(dof) or dof > 1e6:
        return float(chi2)
    return float(fdtri(1.0, max(dof, 1.0), 1.0 - chdtrc(1.0, chi2)))


def _classify(R, t, P, state, w, sigma, chi2, Ki, Kj, cache=None, focal=None) -> tuple[np.ndarray, float, float]:
    """Inlier points (n,) at the current fit, and the σ and threshold used.

    Leave-one-out residual test and cheirality. A point that pulled the pose
    towards itself hides its error; its leave-one-out residual does not. With
    ``h_k = w_k j_kᵀ S⁻¹ j_k`` its leverage in the reduced pose system,
    ``e_k² / (1 − h_k)`` is ≈ σ²·χ²₁ for an inlier. ``sigma=None`` estimates σ from
    the median of those statistics (the residuals themselves are shrunk by
    ``1 − h_k``: 5/n on average, 31% at 16 points) and then tests against
    :func:`studentized_threshold` for that median's precision; a known σ uses ``chi2``.
    A point more than 3 sd behind camera i (ρ < −3σ_ρ) is rejected too: a false
    match that happens to lie near its epipolar line often triangulates there.
    """
    r, valid, aux = state
    _, J, nv, j, _ = linearize(R, t, P, Kj, Ki, aux, cache)
    if focal is not None:
        j = np.vstack([j, focal.reduced(nv, focal.jacobian(P, Ki, Kj, aux))])
    S = (j * w) @ j.T
    h = w * (j * (pinv_sym(S) @ j)).sum(axis=0)
    np.minimum(np.maximum(h, 0.0, out=h), 0.99, out=h)  # np.clip, without its overhead
    stat = point_s2(r) / (1.0 - h)
    if sigma is None:
        sigma = robust_sigma(stat[valid])
        chi2 = studentized_threshold(chi2, MEDIAN_SIGMA2_EFFICIENCY * int(valid.sum()))
    g = np.sqrt((J[:, 7] * J[:, 7]).sum(axis=0))  # |d r_j / d ρ| (px per unit ρ)
    behind = P[2] * g < -3.0 * sigma
    return valid & ~behind & (stat <= chi2 * sigma**2), sigma, chi2


def _check_inputs(xi, xj, Ki, Kj, R0, t0):
    xi = np.asarray(xi, dtype=np.float64)
    xj = np.asarray(xj, dtype=np.float64)
    if xi.ndim != 2 or xi.shape[1] != 2 or xi.shape != xj.shape:
        raise ValueError(f"x_i.shape={xi.shape}, x_j.shape={xj.shape} but expected two equal (n, 2) pixel arrays")
    if not (np.isfinite(xi).all() and np.isfinite(xj).all()):
        raise ValueError("x_i or x_j contains NaN or inf; pass finite pixel coordinates of the matched points")
    Ks = []
    for name, K in (("K_i", Ki), ("K_j", Kj)):
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"{name}.shape={K.shape} but expected (3, 3)")
        k20, k21, k22 = K[2].tolist()
        # np.allclose(K[2], (0, 0, 1)) with its default tolerances, on three scalars.
        last_row_ok = abs(k20) <= 1e-8 and abs(k21) <= 1e-8 and abs(k22 - 1.0) <= 1e-8 + 1e-5
        if not last_row_ok or K[1, 0] != 0.0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"{name} must be an upper-triangular pinhole matrix with positive focal lengths and last row (0, 0, 1); got {K.tolist()}")
        Ks.append(K)
    R0 = np.asarray(R0, dtype=np.float64)
    ortho_err = np.abs(R0 @ R0.T - np.eye(3)).max() if R0.shape == (3, 3) else np.inf
    if R0.shape != (3, 3) or not np.isfinite(R0).all() or ortho_err > 1e-5 or np.linalg.det(R0) < 0:
        raise ValueError(f"R0 must be a (3, 3) rotation matrix (orthonormal, det +1); got {np.asarray(R0).tolist()}")
    if ortho_err > 1e-12:
        R0 = so3.project_to_so3(R0)
    t0 = np.asarray(t0, dtype=np.float64).reshape(-1)
    if t0.shape != (3,) or not np.all(np.isfinite(t0)):
        raise ValueError(f"t0 must be a finite (3,) translation; got {t0.tolist()}")
    if np.linalg.norm(t0) < 1e-12:
        # A front end may report t = 0 for a (near) pure rotation: start from the
        # translation that best satisfies the epipolar constraint given R0.
        t0 = translation_from_rotation(xi, xj, Ks[0], Ks[1], R0)
    return xi, xj, Ks[0], Ks[1], R0, t0 / np.linalg.norm(t0)


def refine_pair(
    x_i: np.ndarray,
    x_j: np.ndarray,
    K_i: np.ndarray,
    K_j: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    config: BAConfig | None = None,
    focal: np.ndarray | None = None,
) -> PairBAResult:
    """Two-view BA of one pair and the marginalized rotation precision ``H_ij``.

    Args:
        x_i: (n, 2) pixel coordinates in image i.
        x_j: (n, 2) matching pixel coordinates in image j.
        K_i: (3, 3) intrinsics of camera i.
        K_j: (3, 3) intrinsics of camera j.
        R0: (3, 3) initial ``R_ij = R_j R_iᵀ`` (e.g. from RANSAC).
        t0: (3,) initial translation, ``x_j = R_ij x_i + t_ij`` (any positive scale).
        config: options; default :class:`BAConfig`.
        focal: (2, m) which camera each focal unknown scales
            (:func:`pipeline.geometry.ba_focal.focal_columns`); default: ``config.refine_focal``
            with both cameras unknown. K_i, K_j are then start values; the focal lengths
            are marginalized into ``H`` with the translation.

    Returns:
        The refined pair. ``H`` is (3, 3) symmetric positive definite in 1/rad².

    Raises:
        ValueError: malformed inputs.
        TwoViewBAError: too few points or inliers, or a singular rotation Hessian.
    """
    cfg = config or BAConfig()
    xi, xj, Ki, Kj, R, t = _check_inputs(x_i, x_j, K_i, K_j, R0, t0)
    n = xi.shape[0]
    if n < cfg.min_points:
        raise TwoViewBAError(f"pair has {n} correspondences but min_points={cfg.min_points}; lower min_points or drop the pair")
    xi, xj = np.ascontiguousarray(xi.T), np.ascontiguousarray(xj.T)
    # "auto" is the stage's to resolve per camera (it passes ``focal``); a pair alone has no per-image estimate
    A = (focal_columns("none" if cfg.refine_focal == "auto" else cfg.refine_focal) if focal is None
         else np.asarray(focal, np.float64).reshape(2, -1))
    if A.shape[1] and cfg.refine_focal == "shared" and focal is None and not np.allclose(Ki, Kj):
        raise ValueError("refine_focal='shared' needs K_i == K_j at the start; use per_camera for two cameras")
    fu = FocalUnknowns(A, Ki, Kj) if A.shape[1] and cfg.enabled else None
    m = 0 if fu is None else fu.m
    all_pts = np.ones(n, dtype=bool)
    P = triangulate(R, t, xi, xj, Ki, Kj)
    fix_pose = not cfg.enabled
    iterations = 0
    converged = True
    history: list[float] = []

    state = project(R, t, P, xi, xj, Ki, Kj)
    cache: dict[str, Any] = {}

    def run(loss: str, c: float, active: np.ndarray, tol: float, adapt: float | None = None):
        nonlocal R, t, P, iterations, converged, state, Ki, Kj
        R, t, P, state, w, hist, it, conv, c = levenberg_marquardt(
            R, t, P, xi, xj, Ki, Kj, active, loss, c, tol, cfg.max_iterations, fix_pose, adapt, state, cache, fu
        )
        if fu is not None:
            Ki, Kj = fu.K_i, fu.K_j
        history.extend(hist)
        iterations += it
        converged = converged and conv
        return state[0], state[1], w, c

    # 1. Robust fit. Without a known σ (or scale) the loss scale starts from the
    #    median residual of the initial pose and shrinks with it (a rough initial
    #    pose inflates the first estimate).
    r, valid, _ = state
    sigma_ref = cfg.sigma_px if cfg.sigma_px is not None else robust_sigma(point_s2(r)[valid])
    c = cfg.loss_scale_px if cfg.loss_scale_px is not None else cfg.loss_scale_sigmas * sigma_ref
    adapt = cfg.loss_scale_sigmas if (cfg.loss != "none" and cfg.loss_scale_px is None and cfg.sigma_px is None) else None
    tol_robust = max(cfg.tol, 1e-4) if cfg.refit_inliers else cfg.tol
    r, valid, w, c = run(cfg.loss, c, all_pts, tol_robust, adapt)
    inliers, sigma_cls, chi2_cls = _classify(R, t, P, state, w, cfg.sigma_px, cfg.inlier_chi2, Ki, Kj, cache, fu)
    # 2. Drop the outliers and refine again by least squares (unit weights). If
    #    outliers were dropped, check every point once more at the new pose
    #    (the dropped points first re-triangulated there) and refit if the set changed.
    if cfg.refit_inliers:
        for round_ in range(2):
            if inliers.sum() < cfg.min_points:
                raise TwoViewBAError(
                    f"only {int(inliers.sum())} of {n} points are inliers (threshold {np.sqrt(chi2_cls) * sigma_cls:.3g} px) "
                    f"but min_points={cfg.min_points}: too few to trust the pose"
                )
            r, valid, w, _ = run("none", c, inliers, cfg.tol)
            if round_ == 1 or inliers.all():
                break
            out = ~inliers
            P_out = levenberg_marquardt(R, t, P[:, out], xi[:, out], xj[:, out], Ki, Kj, np.ones(int(out.sum()), bool),
                        "none", c, cfg.tol, 3, True)[2]
            P = P.copy()
            P[:, out] = P_out
            state = project(R, t, P, xi, xj, Ki, Kj)
            new = _classify(R, t, P, state, inliers.astype(np.float64), sigma_cls, chi2_cls, Ki, Kj, cache, fu)[0]
            # Any point of the fit that now fails forces another fit (a hidden
            # outlier biases H); a few (≤ 0.5%) dropped points coming back do not.
            if not np.any(inliers & ~new) and int((new & ~inliers).sum()) <= max(1, int(0.005 * n)):
                break
            inliers = new
        inliers &= valid
        w = inliers.astype(np.float64)
    s2 = point_s2(r)
    wsum = float(w.sum())
    variance_inflation = 1.0
    if cfg.sigma_px is not None:
        sigma2, estimated = float(cfg.sigma_px) ** 2, False
    else:
        dof = wsum - 5.0 - m  # 2·n_obs − n_params = 4n − (3n + 5 + m) for unit weights
        if dof <= 0:
            raise TwoViewBAError(f"{wsum:.1f} effective points leave no degrees of freedom to estimate σ²; pass sigma_px")
        sigma2 = float((w * s2).sum() / dof)
        if cfg.refit_inliers:
            # The inlier test cut the tail of each point's σ²·χ²₁: divide by the
            # mean of a χ²₁ truncated at the threshold used (0.988 at 10.83) to stay unbiased.
            q = np.sqrt(chi2_cls)
            sigma2 /= 1.0 - 2.0 * q * np.exp(-0.5 * chi2_cls) / np.sqrt(2.0 * np.pi) / math.erf(q / np.sqrt(2.0))
        # A noise-free pair would give H = ∞; floor σ at 1e-6 px.
        sigma2, estimated = max(sigma2, 1e-12), True
        # σ² estimated from ν = dof residual degrees of freedom makes the error a Student-t
        # with ν dof (scale σ̂²·S⁻¹), whose covariance is ν/(ν − 2) times larger.
        if dof <= 2.0:
            raise TwoViewBAError(f"{wsum:.1f} effective points leave {dof:.1f} ≤ 2 degrees of freedom: the rotation's "
                                 "error has no finite variance; pass sigma_px or raise min_points")
        variance_inflation = dof / (dof - 2.0)
    # 3. H_full = JᵀWJ/σ² at the optimum; points, then translation, marginalized.
    B, J, nv, j, _ = linearize(R, t, P, Kj, Ki, state[2], cache)
    if fu is not None:  # the focal rows: marginalized with the translation below
        j = np.vstack([j, fu.reduced(nv, fu.jacobian(P, Ki, Kj, state[2]))])
    S_pose, _ = reduced_system(r, w, J, nv, j)
    H_rot, S = marginalize_translation(S_pose)
    H = H_rot / (sigma2 * variance_inflation)
    lam = np.linalg.eigvalsh(H)
    if not (np.all(np.isfinite(lam)) and lam[0] > 1e-12 * max(lam[-1], 1e-300) and lam[0] > 0):
        raise TwoViewBAError(f"the rotation Hessian is singular (eigenvalues {lam.tolist()}); the pair does not constrain the rotation")
    rho = P[2]
    X = np.empty((3, n))
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(P[:2], rho, out=X[:2])
        np.divide(1.0, rho, out=X[2])
    X[:, ~(rho > 0)] = np.nan
    X = X.T
    return PairBAResult(
        R=R, t=t, points=X, point_params=P.T.copy(), residuals=r.T.copy(), sigma2=sigma2, sigma2_estimated=estimated,
        H=H, H_pose=S / (sigma2 * variance_inflation), iterations=iterations, inlier_mask=inliers, cost_history=history,
        converged=bool(converged), t_basis=B, K_i=Ki, K_j=Kj, focal_log_sd=_focal_sd(S, sigma2 * variance_inflation, m),
        variance_inflation=variance_inflation,
    )


def _focal_sd(S: np.ndarray, sigma2: float, m: int) -> np.ndarray:
    """Marginal sd of the m log focal scales (points and pose marginalized)."""
    if m == 0:
        return np.zeros(0)
    cov = np.linalg.pinv(S / sigma2, rcond=1e-14, hermitian=True)
    return np.sqrt(np.maximum(np.diag(cov)[5:], 0.0))

