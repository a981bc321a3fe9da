"""Two-view bundle adjustment and the Schur-marginalized 3×3 rotation Hessian ``H_ij``.

For every accepted pair (i, j) of the front end this stage refines the relative
pose and the points by a robust Levenberg–Marquardt bundle adjustment and turns
its Gauss–Newton Hessian into the precision of the relative rotation
(``../shared/DESIGN.md``, "The two-view Hessian"):

* **Model.** Camera i is the origin. Point k is ``X_k = m_k / ρ_k`` with
  ``m_k = (a_k, b_k, 1)`` its normalized ray in camera i and ``ρ_k`` its
  inverse depth, so ``x_i = K_i m`` (no dependence on ρ) and
  ``x_j = π(K_j (R m + ρ t))`` (the projection is scale invariant, so the
  ``1/ρ`` drops out and points at infinity, ρ = 0, are regular). ``R = R_ij =
  R_j R_iᵀ`` and ``t = t_ij`` with ``x_j = R x_i + t`` and ``‖t‖ = 1``, which
  fixes the scale gauge.
* **Variables.** 3 + 2 + 3n: the rotation with the left perturbation
  ``R ← exp([δ]×) R`` (the convention of ``H_ij``), the translation on the
  unit sphere ``t ← normalize(t + B δt)`` with ``B`` (3, 2) an orthonormal basis
  of the tangent plane, and (a, b, ρ) per point.
* **Solver.** Levenberg–Marquardt with IRLS weights of a robust loss (Huber or
  Cauchy) on each point's 4-vector of pixel residuals. The normal equations are
  reduced by the Schur complement on the 3×3 point blocks, leaving a 5×5 system;
  because each point's 4×3 Jacobian has a one-dimensional left null space
  ``n_k``, its Schur term ``W_k V_k⁻¹ W_kᵀ`` leaves the rank-one
  ``Jc_kᵀ n_k n_kᵀ Jc_k``, computed in closed form with O(n) vector operations
  (:func:`rotation_hessian` keeps the textbook route with batched 3×3 inverses;
  the tests check they agree). No dense ``(3n+5)²`` matrix is ever formed.
  Per-point arrays are component-major (k, n) so every formula is a few
  contiguous vector operations. At n ≈ 1000 the time is set by the number of
  numpy calls, not by the arithmetic, so the hot path works on whole (k, n)
  blocks in place and reuses a state's linearization (Jacobian, null vectors)
  between the inlier test, the next fit and ``H``: about 2–3 ms of CPU for
  1000 points.
* **Outliers.** After the robust fit, points whose leave-one-out squared
  residual ``‖r_k‖² / (1 − h_k)`` (``h_k`` the point's leverage) exceeds
  ``inlier_chi2 · σ²``, or that lie more than 3 sd behind camera i, are dropped
  and the pose is refined again by plain least squares on the inliers
  (DESIGN.md: "drop points with large error and refine again"); the dropped
  points are checked once more at the new pose. ``H`` is then the Gauss–Newton
  precision of a least-squares estimate on Gaussian data: the case in which it
  is calibrated.
* **Precision.** ``H_full = JᵀWJ / σ²`` at the optimum. The points are
  eliminated block by block, then the translation block, leaving ``H_ij`` (3, 3)
  in 1/rad² for ``Δω`` with ``R_true = exp([Δω]×) R̂``. σ² is either the known
  pixel variance or ``Σ r² / (2·n_obs − n_params)``; with n inlier points there
  are ``2·n_obs = 4n`` residuals and ``n_params = 3n + 5`` unknowns, so the
  denominator is ``n − 5``; it is divided by 0.988, the mean of χ²₁ truncated
  at the inlier threshold, so the cut tail does not bias it. When the final
  refit is switched off, IRLS weights are used: ``Σ w r² / (Σ w − 5)``.
* **Pure rotation.** The translation block is eliminated with a
  pseudo-inverse, so a zero-baseline pair still gets a finite H; a zero ``t0``
  (as a front end may report there) is replaced by the epipolar least-squares t.

WORK layout (read and written by :func:`main`):

* input: whatever :func:`pipeline.two_view.load_two_view` reads (helper D's
  stage), giving the RANSAC view graph, the intrinsics and the inlier
  correspondences of every edge;
* output: ``WORK/viewgraph.npz`` (a :class:`~pipeline.core.viewgraph.ViewGraph` with
  ``H``, BA inlier counts and per-edge stats, ``allow_isolated=True``) and
  ``WORK/viewgraph.json`` (configuration, its hash, a fingerprint of the input,
  timings and the pairs that were dropped, with reasons). A re-run with the same
  configuration and input skips the work unless ``overwrite=True``.

Per-edge stats written: ``t`` (M, 3) refined unit translation, ``t_ransac``,
``R_ransac`` (M, 3, 3), ``ba_sigma2`` (px²), ``ba_rms_px``, ``ba_iterations``,
``ba_n_points``, ``ba_n_inliers``, ``ba_converged``, ``ba_rotation_change_deg``
(angle between the RANSAC and the refined rotation), ``ba_cond_H``, plus every
stat of the input graph that is not overwritten.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.core import so3
from pipeline.core.atomic import write_json
from pipeline.core.config import config_hash, load_yaml, stage_config
from pipeline.core.errors import InputFileError, PipelineError
from pipeline.core.viewgraph import ViewGraph

__all__ = [
    "BAConfig",
    "PairBAResult",
    "TwoViewBAError",
    "marginalize_translation",
    "normal_equation_blocks",
    "residuals_and_jacobian",
    "SyntheticPair",
    "refine_pair",
    "refine_pairs",
    "rotation_hessian",
    "synthetic_pair",
    "tangent_basis",
    "main",
    "main_cli",
]

logger = logging.getLogger(__name__)

LOSSES = ("none", "huber", "cauchy")
# Median of a χ²₁ variable: each inlier point's squared residual is ≈ σ²·χ²₁
# (4 residuals, 3 point unknowns), so median(‖r_k‖²)/0.4549 estimates σ² robustly.
CHI2_1_MEDIAN = 0.454936
# Residual standing in for an observation behind camera j, so that the cost
# penalizes (and LM rejects) steps that push a point behind a camera.
_INVALID_RESIDUAL2 = 1e12
OUTPUT_NAME = "viewgraph.npz"
SUMMARY_NAME = "viewgraph.json"


class TwoViewBAError(PipelineError):
    """A pair the two-view bundle adjustment cannot process."""


@dataclass(frozen=True, kw_only=True)
class BAConfig:
    """Options of the two-view bundle adjustment stage (YAML section ``two_view_ba``).

    Attributes:
        enabled: run the BA. False keeps the RANSAC pose, triangulates the points
            (points-only refinement at that pose) and computes ``H`` there.
        sigma_px: known pixel noise σ (px). None estimates σ² from the residuals.
        loss: robust loss on each point's residual norm: "none", "huber", "cauchy".
        loss_scale_px: scale c of the robust loss (px). None: ``loss_scale_sigmas``
            times σ (the known one, else a median-based estimate at the start).
        loss_scale_sigmas: see ``loss_scale_px``.
        refit_inliers: after the robust fit, drop the points beyond the inlier
            threshold and refine again by least squares; ``H`` and σ² then come
            from the inliers with unit weights.
        inlier_chi2: a point is an inlier when ``‖r_k‖² ≤ inlier_chi2 · σ²``;
            10.83 is the 99.9% quantile of χ²₁ (one redundant residual per point).
        max_iterations: LM iterations (linearizations) per fit.
        tol: stop when the relative cost decrease falls below this.
        min_points: pairs with fewer (inlier) points are rejected.
        workers: processes for :func:`main` (1 = in-process).
        chunk_size: pairs per task sent to a worker process.
    """

    enabled: bool = True
    sigma_px: float | None = None
    loss: str = "cauchy"
    loss_scale_px: float | None = None
    loss_scale_sigmas: float = 3.0
    refit_inliers: bool = True
    inlier_chi2: float = 10.83
    max_iterations: int = 50
    tol: float = 1e-6
    min_points: int = 12
    workers: int = 2
    chunk_size: int = 8

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss={self.loss!r} is not supported; use one of {list(LOSSES)}")
        if self.sigma_px is not None and not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ValueError(f"sigma_px={self.sigma_px} but expected a positive number of pixels or None")
        if self.loss_scale_px is not None and not self.loss_scale_px > 0:
            raise ValueError(f"loss_scale_px={self.loss_scale_px} but expected a positive number of pixels or None")
        if not self.loss_scale_sigmas > 0:
            raise ValueError(f"loss_scale_sigmas={self.loss_scale_sigmas} but expected > 0")
        if not self.inlier_chi2 > 0:
            raise ValueError(f"inlier_chi2={self.inlier_chi2} but expected > 0 (e.g. 10.83)")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations={self.max_iterations} but expected >= 1")
        if self.min_points < 6:
            raise ValueError(f"min_points={self.min_points} but expected >= 6 (5 pose unknowns + σ²)")
        if self.workers < 1 or self.chunk_size < 1:
            raise ValueError(f"workers={self.workers}, chunk_size={self.chunk_size} but both must be >= 1")


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
        H: (3, 3) precision of ``Δω`` (1/rad²), ``R_true = exp([Δω]×) R``.
        H_pose: (5, 5) precision of (δ, δt) with the points marginalized.
        iterations: LM linearizations over all fits (robust + refit).
        inlier_mask: (n,) points kept for the final fit and for ``H``.
        cost_history: robust cost (½ Σ ρ(‖r_k‖²), px²) after each accepted step,
            starting with the initial cost; the refit's history follows.
        converged: every fit met ``tol`` before ``max_iterations``.
        t_basis: (3, 2) tangent basis of ``t`` used for ``H_pose``.
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
    t_basis: np.ndarray | None = None

    @property
    def n_inliers(self) -> int:
        return int(self.inlier_mask.sum())

    @property
    def rms_px(self) -> float:
        """RMS of the inliers' residual components (px)."""
        r = self.residuals[self.inlier_mask]
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


# --------------------------------------------------------------------------- model
# Internally every per-point array is component-major, (k, n), so that each
# formula below is a handful of contiguous length-n vector operations.


def tangent_basis(t: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the tangent plane of the unit sphere at ``t``.

    Args:
        t: (3,) unit vector.

    Returns:
        (3, 2) matrix B with ``Bᵀ B = I`` and ``Bᵀ t = 0``.
    """
    # Cross with the axis least aligned with t: never degenerate.
    x, y, z = t.tolist()
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax <= ay and ax <= az:  # t × e_x
        b1 = (0.0, z, -y)
    elif ay <= az:  # t × e_y
        b1 = (-z, 0.0, x)
    else:  # t × e_z
        b1 = (y, -x, 0.0)
    s = 1.0 / math.sqrt(b1[0] ** 2 + b1[1] ** 2 + b1[2] ** 2)
    b1 = (b1[0] * s, b1[1] * s, b1[2] * s)
    b2 = (y * b1[2] - z * b1[1], z * b1[0] - x * b1[2], x * b1[1] - y * b1[0])
    return np.array([[b1[0], b2[0]], [b1[1], b2[1]], [b1[2], b2[2]]])


def _exp3(w: np.ndarray) -> np.ndarray:
    """Rodrigues for one rotation vector (the batched ``so3.exp`` costs more for a single one)."""
    x, y, z = w.tolist()
    th2 = x * x + y * y + z * z
    W = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    W2 = W @ W
    if th2 < 1e-16:
        a, b = 1.0, 0.5
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    W *= a
    W2 *= b
    W += W2
    W.flat[::4] += 1.0  # I + a W + b W²
    return W


def _project(R, t, P, xi, xj, Ki, Kj):
    """Residuals (4, n) px, validity (n,) (in front of camera j) and what the Jacobian reuses.

    ``P`` (3, n) holds (a, b, ρ); ``xi``, ``xj`` are (2, n).
    """
    n = P.shape[1]
    r = np.empty((4, n))
    # Every formula works on whole (k, n) blocks: at n ≈ 1000 the cost is the
    # number of numpy calls, not the arithmetic.
    # K's last row is (0, 0, 1), so (K m)_z = 1 and image i is affine in (a, b).
    ab = P[:2]
    np.matmul(Ki[:2, :2], ab, out=r[:2])
    r[:2] += Ki[:2, 2, None]
    r[:2] -= xi
    pR = R[:, :2] @ ab
    pR += R[:, 2, None]
    p = t[:, None] * P[2]
    p += pR
    z = p[2]
    valid = z > 1e-9 * np.abs(p).sum(axis=0)
    iz = np.divide(1.0, z)
    if not valid.all():
        iz[~valid] = 1.0
    uv = Kj[:2, :2] @ p[:2]  # projection in image j (px)
    uv *= iz
    uv += Kj[:2, 2, None]
    np.subtract(uv, xj, out=r[2:])
    return r, valid, (pR, iz, uv)


def _jacobians(R, t, B, P, Kj, aux) -> np.ndarray:
    """Jacobian of the image-j residuals, (2, 8, n): columns δ (3), δt (2), (a, b, ρ) (3).

    The image-i residuals have the constant point Jacobian ``[[K00, K01, 0],
    [0, K11, 0]]`` and no pose dependence; they enter through
    :func:`_point_null_vectors` and :func:`_point_step`.
    """
    pR, iz, uv = aux
    n = P.shape[1]
    # A = d r_j / d p = dπ/dq · K_j, (2, 3, n); row 0 is (A00, A01, A02), row 1 (0, A11, A12).
    A = np.empty((2, 3, n))
    # Row by row: numpy broadcasts a (2, 2, 1) factor into a strided block slowly.
    np.multiply(Kj[0, 0], iz, out=A[0, 0])
    np.multiply(Kj[0, 1], iz, out=A[0, 1])
    A[1, 0] = 0.0
    np.multiply(Kj[1, 1], iz, out=A[1, 1])
    np.subtract(Kj[:2, 2, None], uv, out=A[:, 2])
    A[:, 2] *= iz
    x, y, z = pR
    J = np.empty((2, 8, n))
    # d(exp([δ]×) R m)/dδ = −[R m]×; a row aᵀ(−[v]×) is (v × a)ᵀ. Both rows at once.
    np.subtract(y * A[:, 2], z * A[:, 1], out=J[:, 0])
    np.subtract(z * A[:, 0], x * A[:, 2], out=J[:, 1])
    np.subtract(x * A[:, 1], y * A[:, 0], out=J[:, 2])
    # d p/dδt = ρ B (normalizing t + B δt has no first-order effect);
    # d p/d(a, b, ρ) = [R e1, R e2, t].
    T = np.empty((5, 3))
    T[:2] = B.T
    T[2:4] = R[:, :2].T
    T[4] = t
    np.matmul(T, A, out=J[:, 3:])
    J[:, 3:5] *= P[2]
    return J


def residuals_and_jacobian(R, t, points, x_i, x_j, K_i, K_j) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and full Jacobian of one pair, per point (for tests and checks).

    Args:
        R: (3, 3) ``R_ij``.  t: (3,) unit ``t_ij``.
        points: (n, 3) parameters (a, b, ρ).
        x_i, x_j: (n, 2) pixels.  K_i, K_j: (3, 3).

    Returns:
        ``r (n, 4)`` px (image i x, y, image j x, y) and ``J (n, 4, 8)``, the
        derivatives with respect to (δ (3), δt (2) in :func:`tangent_basis` (t),
        a, b, ρ), with ``R ← exp([δ]×) R`` and ``t ← normalize(t + B δt)``.
    """
    P = np.asarray(points, dtype=np.float64).T
    r, _, aux = _project(R, t, P, np.asarray(x_i).T, np.asarray(x_j).T, K_i, K_j)
    Jj = _jacobians(R, t, tangent_basis(t), P, K_j, aux)
    n = P.shape[1]
    J = np.zeros((n, 4, 8))
    J[:, 0, 5:7] = K_i[0, :2]
    J[:, 1, 6] = K_i[1, 1]
    J[:, 2:4] = Jj.transpose(2, 0, 1)
    return r.T, J


def _robust(s2: np.ndarray, loss: str, c: float) -> tuple[np.ndarray, np.ndarray]:
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


def _point_s2(r: np.ndarray) -> np.ndarray:
    """Squared residual norm of each point, (n,), from (4, n) residuals."""
    return (r * r).sum(axis=0)  # rows added in order, as r0² + r1² + r2² + r3²


def _cost(r: np.ndarray, valid: np.ndarray, active: np.ndarray, loss: str, c: float,
          s2: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """½ Σ_active ρ(‖r_k‖²), the IRLS weights (0 outside ``active`` and behind camera j)
    and the squared point residuals (n,) (``_INVALID_RESIDUAL2`` behind camera j).

    ``active`` is a (n,) 0/1 float mask; ``s2`` may pass the squared residuals if known.
    """
    all_valid = bool(valid.all())
    if s2 is None:
        s2 = _point_s2(r)
        if not all_valid:
            s2[~valid] = _INVALID_RESIDUAL2
    rho, w = _robust(s2, loss, c)
    # w is a fresh array (for loss "none" a new array of ones).
    w *= active
    if not all_valid:
        w[~valid] = 0.0
    return 0.5 * float(rho @ active), w, s2


def _inv3(V: np.ndarray) -> np.ndarray:
    """Batched inverse of (n, 3, 3) symmetric matrices by cofactors."""
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, f = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    A = d * f - e * e
    Bc = c * e - b * f
    C = b * e - c * d
    det = a * A + b * Bc + c * C
    inv = np.empty_like(V)
    inv[:, 0, 0] = A
    inv[:, 0, 1] = inv[:, 1, 0] = Bc
    inv[:, 0, 2] = inv[:, 2, 0] = C
    inv[:, 1, 1] = a * f - c * c
    inv[:, 1, 2] = inv[:, 2, 1] = b * c - a * e
    inv[:, 2, 2] = a * d - b * b
    return inv / det[:, None, None]


def _pinv_sym(S: np.ndarray) -> np.ndarray:
    """``np.linalg.pinv(S, hermitian=True)`` of one small symmetric matrix (same steps, less overhead)."""
    lam, u = np.linalg.eigh(S)
    sgn = np.copysign(1.0, lam)
    s = np.abs(lam)
    idx = np.argsort(s)[::-1]
    sgn, s, u = sgn[idx], s[idx], u[:, idx]
    vt = np.transpose(u * sgn[None, :]).conjugate()
    large = s > 1e-15 * s.max()
    s = np.divide(1.0, s, where=large, out=s)
    s[~large] = 0.0
    return np.matmul(np.transpose(vt), np.multiply(s[:, None], np.transpose(u)))


def _psd_inverse_solve(A: np.ndarray, b: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """``A⁺ b`` for a symmetric PSD ``A``, treating eigenvalues below rcond·max as zero."""
    lam, Q = np.linalg.eigh(0.5 * (A + A.T))
    keep = lam > rcond * max(lam[-1], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    return Q @ (inv[:, None] * (Q.T @ b))


def marginalize_translation(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Schur complement of the translation block of a (5, 5) pose information matrix.

    Args:
        S: (5, 5) information of (δ, δt) with the points already eliminated.

    Returns:
        ``(H_rot (3, 3), S (5, 5) symmetrized)``.
    """
    S = 0.5 * (S + S.T)
    # A pseudo-inverse of the translation block: with (near) zero parallax the
    # translation direction is unobservable and must not leak into the rotation.
    H = S[:3, :3] - S[:3, 3:] @ _psd_inverse_solve(S[3:, 3:], S[3:, :3])
    return 0.5 * (H + H.T), S


def rotation_hessian(U: np.ndarray, V: np.ndarray, Wm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Marginalize the points (block Schur with batched 3×3 inverses), then the translation.

    The textbook route; :func:`refine_pair` uses the equivalent closed form of
    :func:`_point_null_vectors` (rank-one per point), and the tests check that
    both give the same ``H``.

    Args:
        U: (5, 5) pose block of ``JᵀWJ`` (rotation δ first, then translation δt).
        V: (n, 3, 3) point blocks.
        Wm: (n, 5, 3) pose–point blocks.

    Returns:
        ``(H_rot (3, 3), S (5, 5))``: the rotation block after eliminating the
        points and the translation, and the pose block after eliminating the points.
    """
    Vinv = _inv3(V)
    S = U - np.tensordot(np.matmul(Wm, Vinv), Wm, axes=([0, 2], [0, 2]))
    return marginalize_translation(S)


def normal_equation_blocks(J: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blocks of ``JᵀWJ`` from per-point Jacobians (as from :func:`residuals_and_jacobian`).

    Args:
        J: (n, 4, 8) per-point Jacobians.
        w: (n,) point weights (default 1).

    Returns:
        ``U (5, 5), V (n, 3, 3), Wm (n, 5, 3)``.
    """
    w = np.ones(J.shape[0]) if w is None else np.asarray(w, dtype=np.float64)
    M = np.einsum("n,nai,naj->nij", w, J, J)
    return M[:, :5, :5].sum(axis=0), M[:, 5:, 5:], M[:, :5, 5:]


def _point_null_vectors(J: np.ndarray, Ki: np.ndarray) -> np.ndarray:
    """Unit left null vector (4, n) of each point's 4×3 Jacobian (image-i rows, then image j).

    Eliminating a point from its 4 residuals leaves exactly one direction: the
    Schur complement of point k is ``Jc_kᵀ n_k n_kᵀ Jc_k`` (``I − Jp Jp⁺ = n nᵀ``),
    so the block elimination ``U − Σ W V⁻¹ Wᵀ`` becomes a sum of rank-one terms,
    computed here in closed form. A point with no ρ information (on the
    epipole's ray) gets n = 0 and does not constrain the pose.
    """
    p00, p01, p02 = J[0, 5], J[0, 6], J[0, 7]
    p10, p11, p12 = J[1, 5], J[1, 6], J[1, 7]
    nv = np.empty((4, J.shape[2]))
    # nᵀ (column) = 0, column by column: ρ gives (n2, n3), then a gives n0, b gives n1.
    nv[2] = p12
    np.negative(p02, out=nv[3])
    np.subtract(p02 * p10, p12 * p00, out=nv[0])
    nv[0] /= Ki[0, 0]
    np.subtract(p02 * p11, p12 * p01, out=nv[1])
    if Ki[0, 1] != 0.0:  # skew
        nv[1] -= Ki[0, 1] * nv[0]
    nv[1] /= Ki[1, 1]
    norm = np.sqrt((nv * nv).sum(axis=0))
    tiny = norm <= 1e-12 * max(float(norm.max(initial=0.0)), 1e-300)
    if tiny.any():
        norm[tiny] = np.inf
    nv /= norm
    return nv


def _reduced_jacobian(J: np.ndarray, nv: np.ndarray) -> np.ndarray:
    """Pose Jacobian (5, n) of each point's residual along its null vector, ``j_k = n_kᵀ Jc_k``."""
    return (nv[2:, None, :] * J[:, :5]).sum(axis=0)


def _reduced_system(r: np.ndarray, w: np.ndarray, J: np.ndarray, nv: np.ndarray,
                    j: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pose system with the points eliminated: S (5,5) = Σ w j jᵀ and g (5,) = Σ w j e.

    ``e_k = n_kᵀ r_k`` is point k's residual orthogonal to its own Jacobian and
    ``j_k = n_kᵀ Jc_k`` its pose Jacobian (image i has no pose dependence);
    ``j`` (5, n) may be passed if known.
    """
    e = (nv * r).sum(axis=0)
    if j is None:
        j = _reduced_jacobian(J, nv)
    jw = j * w
    return jw @ j.T, jw @ e


def _rho_gain(J: np.ndarray) -> np.ndarray:
    """``−‖d r_j / d ρ‖²`` (n,) for :func:`_point_step`; −inf where ρ is unobservable (its step is then 0)."""
    c = J[:, 7]
    den = (c * c).sum(axis=0)
    den[den <= 1e-24 * max(float(den.max(initial=0.0)), 1e-300)] = np.inf
    return np.negative(den, out=den)


def _point_step(s: np.ndarray, nv: np.ndarray, J: np.ndarray, Ki: np.ndarray, nden: np.ndarray | None = None) -> np.ndarray:
    """Gauss–Newton point steps (3, n) minimizing ``‖s_k + Jp_k δp_k‖`` for each point.

    The optimal residual is ``n nᵀ s``, so ``Jp δp = −(s − n nᵀ s)``: the image-i
    rows give (δa, δb) by back substitution, the image-j rows then give δρ.
    ``nden`` is :func:`_rho_gain` of ``J`` if known.
    """
    sp = nv * (nv * s).sum(axis=0)
    np.subtract(s, sp, out=sp)
    dp = np.empty((3, s.shape[1]))
    np.divide(sp[1], -Ki[1, 1], out=dp[1])  # −sp1 / K11
    if Ki[0, 1] != 0.0:
        np.multiply(Ki[0, 1], dp[1], out=dp[0])
        dp[0] += sp[0]
        dp[0] /= -Ki[0, 0]  # (−sp0 − K01 δb) / K00
    else:
        np.divide(sp[0], -Ki[0, 0], out=dp[0])
    # Image-j rows: δρ = cᵀ q / ‖c‖² with c = d r_j/dρ and q = −(sp + J_a δa + J_b δb);
    # the signs are folded into nden = −‖c‖².
    q = J[:, 5] * dp[0]
    q += J[:, 6] * dp[1]
    q += sp[2:]
    q *= J[:, 7]
    np.divide(q.sum(axis=0), _rho_gain(J) if nden is None else nden, out=dp[2])
    return dp


def _linearize(R, t, P, Kj, Ki, aux, cache=None):
    """Tangent basis (3, 2), Jacobian (2, 8, n), point null vectors (4, n) and reduced
    pose Jacobian (5, n) (:func:`_reduced_jacobian`) and :func:`_rho_gain` (n,) at a state.

    ``cache`` (a dict or None) remembers the last state's linearization, keyed by the
    identity of its ``aux`` tuple from :func:`_project`: the inlier test, the next
    fit and the final ``H`` often linearize the very same state.
    """
    if cache is not None and cache.get("aux") is aux:
        return cache["B"], cache["J"], cache["nv"], cache["j"], cache["nden"]
    B = tangent_basis(t)
    J = _jacobians(R, t, B, P, Kj, aux)
    nv = _point_null_vectors(J, Ki)
    j = _reduced_jacobian(J, nv)
    nden = _rho_gain(J)
    if cache is not None:
        cache.update(aux=aux, B=B, J=J, nv=nv, j=j, nden=nden)
    return B, J, nv, j, nden


def _lm(R, t, P, xi, xj, Ki, Kj, active, loss, c, tol, max_iterations, fix_pose, adapt_scale=None, state=None, cache=None):
    """Levenberg–Marquardt with IRLS weights on the robust cost.

    Each iteration eliminates the points exactly (:func:`_reduced_system`), damps
    the 5×5 pose system (Marquardt: ``S + λ diag(S)``), solves it, and moves each
    point by its Gauss–Newton step given the pose step. ``active`` (n,) selects
    the points in the cost; the others are frozen. With ``fix_pose`` only the
    points move. With ``adapt_scale = k`` the loss scale shrinks to ``k·σ̂``
    (median-based) after each accepted step, never grows, and the cost is
    re-evaluated at the new scale so that every comparison uses one scale.

    Returns:
        ``R, t, P, (r, valid, aux), w, history, iterations, converged, c``;
        ``state`` = ``(r, valid, aux)`` of :func:`_project` at the input, if known;
        ``cache`` (see :func:`_linearize`) shares the Jacobian of a state with the caller.
    """
    r, valid, aux = state if state is not None else _project(R, t, P, xi, xj, Ki, Kj)
    active_b = np.asarray(active, dtype=bool)
    all_active = bool(active_b.all())
    active = active_b.astype(np.float64)
    cost, w, s2 = _cost(r, valid, active, loss, c)
    history = [cost]
    lam = 1e-4
    iterations = 0
    converged = False
    while iterations < max_iterations:
        iterations += 1
        B, J, nv, j, nden = _linearize(R, t, P, Kj, Ki, aux, cache)
        frozen = w <= 0.0
        any_frozen = bool(frozen.any())
        if not fix_pose:
            S, g = _reduced_system(r, w, J, nv, j)
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
                Sd.flat[::6] += lam * dS + floor  # S + diag(λ dS + floor)
                dc = np.linalg.solve(Sd, neg_g)
                s_ = r.copy()
                s_[2:] += dc @ Jc
            dp = _point_step(s_, nv, J, Ki, nden)
            if any_frozen:
                np.copyto(dp, 0.0, where=frozen)  # dp[:, frozen] = 0, without fancy indexing
            if trial >= 4:
                # The pose damping alone did not help: shorten the point steps too.
                dp *= 0.5 ** (trial - 3)
            # NaN and inf propagate into a sum: one reduction checks every entry.
            if not np.isfinite(float(dc.sum()) + float(dp.sum())):
                lam *= 10.0
                continue
            R_new = _exp3(dc[:3]) @ R
            t_new = t + B @ dc[3:]
            t_new /= np.sqrt(t_new @ t_new)
            P_new = P + dp
            r_new, valid_new, aux_new = _project(R_new, t_new, P_new, xi, xj, Ki, Kj)
            cost_new, w_new, s2_new = _cost(r_new, valid_new, active, loss, c)
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
        r, valid, aux, w, s2 = r_new, valid_new, aux_new, w_new, s2_new
        cost = cost_new
        history.append(cost)
        lam = max(lam / 10.0, 1e-10)
        rescaled = False
        if adapt_scale is not None:
            c_new = adapt_scale * _robust_sigma(s2 if all_active and valid.all() else s2[valid & active_b])
            if c_new < 0.9 * c:
                c, rescaled = c_new, True
                cost, w, s2 = _cost(r, valid, active, loss, c, s2)
        # Relative test, with an absolute floor (1e-14 px² per point) for noise-free data.
        if not rescaled and decrease <= tol * cost + 1e-14 * P.shape[1]:
            converged = True
            break
    return R, t, P, (r, valid, aux), w, history, iterations, converged, c


def _triangulate(R: np.ndarray, t: np.ndarray, xi: np.ndarray, xj: np.ndarray, Ki: np.ndarray, Kj: np.ndarray) -> np.ndarray:
    """Initial (a, b, ρ), (3, n): ray of camera i and the linear least-squares inverse depth.

    ``xi``, ``xj`` are (2, n). Kept operation for operation as first written: the
    scipy peer in ``benchmarks/two_view_ba.py`` starts from it, and its Cauchy
    run is chaotic in the start point (1e-16 changes turn 44 evaluations into ~900).
    """
    Kii = np.linalg.inv(Ki)
    Kji = np.linalg.inv(Kj)
    mi = Kii[:, :2] @ xi + Kii[:, 2:3]
    mi /= mi[2]
    mj = Kji[:, :2] @ xj + Kji[:, 2:3]
    # m_j ∥ R m_i + ρ t  ⇒  m_j × (R m_i) + ρ (m_j × t) = 0, least squares in ρ.
    q = R @ mi
    c = np.stack([mj[1] * q[2] - mj[2] * q[1], mj[2] * q[0] - mj[0] * q[2], mj[0] * q[1] - mj[1] * q[0]])
    d = np.stack([mj[1] * t[2] - mj[2] * t[1], mj[2] * t[0] - mj[0] * t[2], mj[0] * t[1] - mj[1] * t[0]])
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = -(c * d).sum(axis=0) / (d * d).sum(axis=0)
    # Points triangulated behind camera i (or on the epipole) start at infinity.
    rho = np.where(np.isfinite(rho), np.maximum(rho, 0.0), 0.0)
    return np.vstack([mi[:2], rho])


def _classify(R, t, P, state, w, sigma, chi2, Ki, Kj, cache=None) -> np.ndarray:
    """Inlier points (n,) at the current fit: leave-one-out residual test and cheirality.

    A point that pulled the pose towards itself hides its error; its
    leave-one-out residual does not. With ``h_k = w_k j_kᵀ S⁻¹ j_k`` its leverage
    in the reduced pose system, ``e_k² / (1 − h_k)`` is ≈ σ²·χ²₁ for an inlier.
    A point more than 3 sd behind camera i (ρ < −3σ_ρ) is rejected too: a false
    match that happens to lie near its epipolar line often triangulates there.
    """
    r, valid, aux = state
    _, J, nv, j, _ = _linearize(R, t, P, Kj, Ki, aux, cache)
    S = (j * w) @ j.T
    h = w * (j * (_pinv_sym(S) @ j)).sum(axis=0)
    np.minimum(np.maximum(h, 0.0, out=h), 0.99, out=h)  # np.clip, without its overhead
    stat = _point_s2(r) / (1.0 - h)
    g = np.sqrt((J[:, 7] * J[:, 7]).sum(axis=0))  # |d r_j / d ρ| (px per unit ρ)
    behind = P[2] * g < -3.0 * sigma
    return valid & ~behind & (stat <= chi2 * sigma**2)


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
        t0 = _translation_from_rotation(xi, xj, Ks[0], Ks[1], R0)
    return xi, xj, Ks[0], Ks[1], R0, t0 / np.linalg.norm(t0)


def _translation_from_rotation(xi, xj, Ki, Kj, R) -> np.ndarray:
    """Unit t minimizing Σ (t · (m_j × R m_i))², signed to put most points in front.

    ``xi``, ``xj`` are (n, 2) pixels.
    """
    mi = np.column_stack([xi, np.ones(len(xi))]) @ np.linalg.inv(Ki).T
    mj = np.column_stack([xj, np.ones(len(xj))]) @ np.linalg.inv(Kj).T
    A = np.cross(mj, mi @ R.T)
    t = np.linalg.svd(A, full_matrices=False)[2][-1]
    rho = _triangulate(R, t, np.ascontiguousarray(xi.T), np.ascontiguousarray(xj.T), Ki, Kj)[2]
    rho_neg = _triangulate(R, -t, np.ascontiguousarray(xi.T), np.ascontiguousarray(xj.T), Ki, Kj)[2]
    return t if (rho > 0).sum() >= (rho_neg > 0).sum() else -t


def refine_pair(
    x_i: np.ndarray,
    x_j: np.ndarray,
    K_i: np.ndarray,
    K_j: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    config: BAConfig | None = None,
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
    all_pts = np.ones(n, dtype=bool)
    P = _triangulate(R, t, xi, xj, Ki, Kj)
    fix_pose = not cfg.enabled
    iterations = 0
    converged = True
    history: list[float] = []

    state = _project(R, t, P, xi, xj, Ki, Kj)
    cache: dict[str, Any] = {}

    def run(loss: str, c: float, active: np.ndarray, tol: float, adapt: float | None = None):
        nonlocal R, t, P, iterations, converged, state
        R, t, P, state, w, hist, it, conv, c = _lm(
            R, t, P, xi, xj, Ki, Kj, active, loss, c, tol, cfg.max_iterations, fix_pose, adapt, state, cache
        )
        history.extend(hist)
        iterations += it
        converged = converged and conv
        return state[0], state[1], w, c

    # 1. Robust fit. Without a known σ (or scale) the loss scale starts from the
    #    median residual of the initial pose and shrinks with it (a rough initial
    #    pose inflates the first estimate).
    r, valid, _ = state
    sigma_ref = cfg.sigma_px if cfg.sigma_px is not None else _robust_sigma(_point_s2(r)[valid])
    c = cfg.loss_scale_px if cfg.loss_scale_px is not None else cfg.loss_scale_sigmas * sigma_ref
    adapt = cfg.loss_scale_sigmas if (cfg.loss != "none" and cfg.loss_scale_px is None and cfg.sigma_px is None) else None
    tol_robust = max(cfg.tol, 1e-4) if cfg.refit_inliers else cfg.tol
    r, valid, w, c = run(cfg.loss, c, all_pts, tol_robust, adapt)
    sigma_cls = cfg.sigma_px if cfg.sigma_px is not None else _robust_sigma(_point_s2(r)[valid])
    inliers = _classify(R, t, P, state, w, sigma_cls, cfg.inlier_chi2, Ki, Kj, cache)
    # 2. Drop the outliers and refine again by least squares (unit weights). If
    #    outliers were dropped, check every point once more at the new pose
    #    (the dropped points first re-triangulated there) and refit if the set changed.
    if cfg.refit_inliers:
        for round_ in range(2):
            if inliers.sum() < cfg.min_points:
                raise TwoViewBAError(
                    f"only {int(inliers.sum())} of {n} points are inliers (threshold {np.sqrt(cfg.inlier_chi2) * sigma_cls:.3g} px) "
                    f"but min_points={cfg.min_points}; the pose is unreliable: drop the pair or raise inlier_chi2"
                )
            r, valid, w, _ = run("none", c, inliers, cfg.tol)
            if round_ == 1 or inliers.all():
                break
            out = ~inliers
            P_out = _lm(R, t, P[:, out], xi[:, out], xj[:, out], Ki, Kj, np.ones(int(out.sum()), bool),
                        "none", c, cfg.tol, 3, True)[2]
            P = P.copy()
            P[:, out] = P_out
            state = _project(R, t, P, xi, xj, Ki, Kj)
            new = _classify(R, t, P, state, inliers.astype(np.float64), sigma_cls, cfg.inlier_chi2, Ki, Kj, cache)
            # Any point of the fit that now fails forces another fit (a hidden
            # outlier biases H); a few (≤ 0.5%) dropped points coming back do not.
            if not np.any(inliers & ~new) and int((new & ~inliers).sum()) <= max(1, int(0.005 * n)):
                break
            inliers = new
        inliers &= valid
        w = inliers.astype(np.float64)
    s2 = _point_s2(r)
    wsum = float(w.sum())
    if cfg.sigma_px is not None:
        sigma2, estimated = float(cfg.sigma_px) ** 2, False
    else:
        dof = wsum - 5.0  # 2·n_obs − n_params = 4n − (3n + 5) for unit weights
        if dof <= 0:
            raise TwoViewBAError(f"{wsum:.1f} effective points leave no degrees of freedom to estimate σ²; pass sigma_px")
        sigma2 = float((w * s2).sum() / dof)
        if cfg.refit_inliers:
            # The inlier test cut the tail of each point's σ²·χ²₁: divide by the
            # mean of a χ²₁ truncated at inlier_chi2 (0.988 at 10.83) to stay unbiased.
            q = np.sqrt(cfg.inlier_chi2)
            sigma2 /= 1.0 - 2.0 * q * np.exp(-0.5 * cfg.inlier_chi2) / np.sqrt(2.0 * np.pi) / math.erf(q / np.sqrt(2.0))
        # A noise-free pair would give H = ∞; floor σ at 1e-6 px.
        sigma2, estimated = max(sigma2, 1e-12), True
    # 3. H_full = JᵀWJ/σ² at the optimum; points, then translation, marginalized.
    B, J, nv, j, _ = _linearize(R, t, P, Kj, Ki, state[2], cache)
    S_pose, _ = _reduced_system(r, w, J, nv, j)
    H_rot, S = marginalize_translation(S_pose)
    H = H_rot / sigma2
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
        H=H, H_pose=S / sigma2, iterations=iterations, inlier_mask=inliers, cost_history=history,
        converged=bool(converged), t_basis=B,
    )


def _robust_sigma(s2: np.ndarray) -> float:
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


# ------------------------------------------------------------------ synthetic pair
@dataclass
class SyntheticPair:
    """A synthetic two-view problem with known truth (see :func:`synthetic_pair`).

    Attributes:
        x_i, x_j: (n, 2) noisy pixel observations (outliers replaced in image j).
        K_i, K_j: (3, 3) intrinsics.
        R, t: true ``R_ij`` (3, 3) and unit ``t_ij`` (3,).
        points: (n, 3) true points in camera i.
        outlier_mask: (n,) True for outlier matches.
        R0, t0: perturbed initial pose, standing in for RANSAC.
    """

    x_i: np.ndarray
    x_j: np.ndarray
    K_i: np.ndarray
    K_j: np.ndarray
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    outlier_mask: np.ndarray
    R0: np.ndarray
    t0: np.ndarray


def synthetic_pair(
    n_points: int = 200,
    sigma_px: float = 1.0,
    outlier_frac: float = 0.0,
    seed: int = 0,
    scene_seed: int | None = None,
    init_perturb_deg: float = 1.0,
    size: tuple[int, int] = (640, 480),
    focal: float = 600.0,
) -> SyntheticPair:
    """A converging pair of pinhole cameras looking at random points, with pixel noise.

    Camera i is at the origin looking down +z; camera j sits on a random unit
    baseline mostly sideways (so ``‖t‖ = 1``) and is turned towards the centre of
    the point cloud (depths 4–10 baselines), with a random roll. Points are
    uniform in camera i's frustum and kept only where both images see them.

    Args:
        n_points: number of correspondences.
        sigma_px: std of the Gaussian noise added to all four pixel coordinates.
        outlier_frac: fraction of matches whose image-j point is replaced by a
            uniform random pixel at least 20 px from its true position.
        seed: seed of the noise, the outliers and the initial pose.
        scene_seed: seed of the geometry (cameras, points); default ``seed``.
            Fixing it and varying ``seed`` gives Monte-Carlo noise draws.
        init_perturb_deg: size of the random perturbation of ``R0`` and ``t0``.
        size: image (width, height) in px.
        focal: focal length in px.

    Returns:
        The pair with its truth.
    """
    if n_points < 1 or not 0.0 <= outlier_frac < 1.0 or sigma_px < 0:
        raise ValueError(f"n_points={n_points}, outlier_frac={outlier_frac}, sigma_px={sigma_px}: need n>=1, 0<=frac<1, sigma>=0")
    geo = np.random.default_rng(seed if scene_seed is None else scene_seed)
    rng = np.random.default_rng([seed, 7919])
    w, h = size
    K = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
    centre = np.array([0.0, 0.0, 7.0])
    ang = geo.uniform(0, 2 * np.pi)
    C = np.array([np.cos(ang), 0.25 * np.sin(ang), 0.0])
    C[2] = geo.uniform(-0.2, 0.2)
    C /= np.linalg.norm(C)
    # Look-at rotation (cam_from_world rows = camera axes in camera-i frame).
    zc = centre - C
    zc /= np.linalg.norm(zc)
    xc = np.cross([0.0, 1.0, 0.0], zc)
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    Rj = np.stack([xc, yc, zc])
    # A random roll about camera j's optical axis.
    Rj = so3.exp(np.array([0.0, 0.0, geo.uniform(-0.3, 0.3)])) @ Rj
    tj = -Rj @ C
    pts = []
    total = 0
    while total < n_points:
        m = 4 * n_points + 64
        z = geo.uniform(4.0, 10.0, m)
        u = geo.uniform(0, w, m)
        v = geo.uniform(0, h, m)
        X = np.column_stack([(u - K[0, 2]) / focal * z, (v - K[1, 2]) / focal * z, z])
        Xj = X @ Rj.T + tj
        uvj = Xj @ K.T
        uvj = uvj[:, :2] / uvj[:, 2:3]
        ok = (Xj[:, 2] > 0.5) & (uvj[:, 0] >= 0) & (uvj[:, 0] < w) & (uvj[:, 1] >= 0) & (uvj[:, 1] < h)
        pts.append(X[ok])
        total += int(ok.sum())
    X = np.concatenate(pts)[:n_points]
    xi_true = (X @ K.T)[:, :2] / X[:, 2:3]
    Xj = X @ Rj.T + tj
    xj_true = (Xj @ K.T)[:, :2] / Xj[:, 2:3]
    x_i = xi_true + sigma_px * rng.standard_normal((n_points, 2))
    x_j = xj_true + sigma_px * rng.standard_normal((n_points, 2))
    n_out = int(round(outlier_frac * n_points))
    outlier = np.zeros(n_points, dtype=bool)
    if n_out:
        idx = rng.choice(n_points, n_out, replace=False)
        outlier[idx] = True
        cand = rng.uniform([0, 0], [w, h], (n_out, 2))
        far = np.linalg.norm(cand - xj_true[idx], axis=1) < 20.0
        while np.any(far):
            cand[far] = rng.uniform([0, 0], [w, h], (int(far.sum()), 2))
            far = np.linalg.norm(cand - xj_true[idx], axis=1) < 20.0
        x_j[idx] = cand
    d = rng.standard_normal(3)
    R0 = so3.exp(np.deg2rad(init_perturb_deg) * d / np.linalg.norm(d)) @ Rj
    e = rng.standard_normal(3)
    e -= e.dot(tj) * tj
    t0 = tj + np.tan(np.deg2rad(init_perturb_deg)) * e / max(np.linalg.norm(e), 1e-12)
    t0 /= np.linalg.norm(t0)
    return SyntheticPair(x_i=x_i, x_j=x_j, K_i=K, K_j=K.copy(), R=Rj, t=tj, points=X, outlier_mask=outlier, R0=R0, t0=t0)


# ----------------------------------------------------------------- many pairs
def _refine_chunk(args: tuple[list[tuple[np.ndarray, ...]], dict[str, Any]]) -> list[dict[str, Any]]:
    """Worker: refine a chunk of pairs given as arrays; failures become records with a reason."""
    tasks, cfg_dict = args
    cfg = BAConfig(**cfg_dict)
    out = []
    for xi, xj, Ki, Kj, R0, t0 in tasks:
        t_start, c_start = time.perf_counter(), time.thread_time()
        try:
            res = refine_pair(xi, xj, Ki, Kj, R0, t0, cfg)
        except (TwoViewBAError, ValueError, np.linalg.LinAlgError) as exc:
            out.append({"ok": False, "reason": " ".join(str(exc).split()), "n_points": int(len(xi))})
            continue
        out.append({
            "ok": True,
            "R": res.R, "t": res.t, "H": res.H, "sigma2": res.sigma2, "iterations": res.iterations,
            "n_points": int(len(xi)), "n_inliers": res.n_inliers, "converged": res.converged,
            "rms_px": res.rms_px, "time_s": time.perf_counter() - t_start, "cpu_s": time.thread_time() - c_start,
        })
    return out


def refine_pairs(
    tasks: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    config: BAConfig | None = None,
    progress: bool = False,
) -> list[dict[str, Any]]:
    """Refine many pairs, in ``config.workers`` processes, in chunks.

    Args:
        tasks: per pair ``(x_i (n,2), x_j (n,2), K_i, K_j, R0, t0)``.
        config: options (``workers``, ``chunk_size`` used here).
        progress: show a tqdm bar over chunks.

    Returns:
        One dict per pair, in order: ``ok`` and either ``R, t, H, sigma2,
        iterations, n_points, n_inliers, converged, rms_px, time_s, cpu_s`` or ``reason``.
    """
    cfg = config or BAConfig()
    cfg_dict = dataclasses.asdict(cfg)
    chunks = [(list(tasks[s:s + cfg.chunk_size]), cfg_dict) for s in range(0, len(tasks), cfg.chunk_size)]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), desc="two-view BA", unit="pair")
    results: list[dict[str, Any]] = []
    try:
        if cfg.workers == 1 or len(chunks) <= 1:
            for ch in chunks:
                results += _refine_chunk(ch)
                if bar is not None:
                    bar.update(len(ch[0]))
        else:
            with ProcessPoolExecutor(max_workers=min(cfg.workers, len(chunks))) as ex:
                for ch, res in zip(chunks, ex.map(_refine_chunk, chunks)):
                    results += res
                    if bar is not None:
                        bar.update(len(ch[0]))
    finally:
        if bar is not None:
            bar.close()
    return results


# ------------------------------------------------------------------------- stage
def _fingerprint(vg: ViewGraph, K: np.ndarray) -> str:
    h = hashlib.sha1()
    for a in (vg.edges, vg.R_rel, np.asarray(K, dtype=np.float64), vg.inliers if vg.inliers is not None else np.zeros(0)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update("\n".join(vg.names).encode())
    return h.hexdigest()[:16]


def main(work: Path, config: BAConfig | None = None, overwrite: bool = False, progress: bool = True) -> Path:
    """Refine every pair of ``WORK``'s two-view graph and write ``WORK/viewgraph.npz`` with ``H``.

    Args:
        work: the WORK folder of the front end (``pipeline.two_view`` has run).
        config: options; default :class:`BAConfig`.
        overwrite: redo the work even if a matching result exists.
        progress: show a progress bar.

    Returns:
        Path of the written (or reused) view graph.
    """
    cfg = config or BAConfig()
    work = Path(work)
    if not work.is_dir():
        raise InputFileError(f"WORK folder {work} does not exist; run the front end (features, matching, two_view) first")
    from pipeline.two_view import load_two_view  # the front end; imported lazily so this module stands alone

    out = work / OUTPUT_NAME
    summary_path = work / SUMMARY_NAME
    data = load_two_view(work)
    vg_in = data.vg
    K = np.asarray(data.K, dtype=np.float64)
    fp = _fingerprint(vg_in, K)
    chash = config_hash(cfg)
    if out.is_file() and summary_path.is_file() and not overwrite:
        try:
            prev = json.loads(summary_path.read_text())
        except (OSError, ValueError):
            prev = {}
        if prev.get("config_hash") == chash and prev.get("input_fingerprint") == fp:
            logger.info("two-view BA: %s is up to date (config %s); skipping", out, chash)
            return out
        logger.info("two-view BA: %s is stale (config or input changed); recomputing", out)
    logger.info("two-view BA config: %s", dataclasses.asdict(cfg))
    M = vg_in.n_edges
    if "t" not in vg_in.stats:
        raise InputFileError(f"the two-view graph in {work} has no per-edge 't' statistic; re-run `python -m pipeline.two_view --work {work} --overwrite`")
    t_in = np.asarray(vg_in.stats["t"], dtype=np.float64).reshape(M, 3)
    tasks = []
    for k in range(M):  # gathering the per-edge arrays: I/O, not the hot path
        xi, xj = data.correspondences(k)
        i, j = vg_in.edges[k]
        tasks.append((np.asarray(xi, np.float64), np.asarray(xj, np.float64), K[i], K[j], vg_in.R_rel[k], t_in[k]))
    t0 = time.perf_counter()
    results = refine_pairs(tasks, cfg, progress=progress)
    elapsed = time.perf_counter() - t0
    ok = np.array([r["ok"] for r in results], dtype=bool)
    kept = np.flatnonzero(ok)
    dropped = [
        {"edge": int(k), "pair": [vg_in.names[vg_in.edges[k, 0]], vg_in.names[vg_in.edges[k, 1]]], "reason": results[k]["reason"]}
        for k in np.flatnonzero(~ok)
    ]
    for d in dropped:
        logger.warning("two-view BA dropped pair %s–%s: %s", d["pair"][0], d["pair"][1], d["reason"])
    good = [results[k] for k in kept]
    R = np.array([r["R"] for r in good]).reshape(-1, 3, 3)
    H = np.array([r["H"] for r in good]).reshape(-1, 3, 3)
    stats = {name: np.asarray(v)[kept] for name, v in vg_in.stats.items()}
    stats["t_ransac"] = t_in[kept]
    stats["t"] = np.array([r["t"] for r in good]).reshape(-1, 3)
    stats["R_ransac"] = vg_in.R_rel[kept]
    stats["ba_sigma2"] = np.array([r["sigma2"] for r in good], dtype=np.float64)
    stats["ba_rms_px"] = np.array([r["rms_px"] for r in good], dtype=np.float64)
    stats["ba_iterations"] = np.array([r["iterations"] for r in good], dtype=np.int64)
    stats["ba_n_points"] = np.array([r["n_points"] for r in good], dtype=np.int64)
    stats["ba_n_inliers"] = np.array([r["n_inliers"] for r in good], dtype=np.int64)
    stats["ba_converged"] = np.array([r["converged"] for r in good], dtype=bool)
    stats["ba_rotation_change_deg"] = np.rad2deg(so3.angle_between(R, vg_in.R_rel[kept])) if len(kept) else np.zeros(0)
    lamH = np.linalg.eigvalsh(H) if len(kept) else np.zeros((0, 3))
    stats["ba_cond_H"] = lamH[:, -1] / lamH[:, 0] if len(kept) else np.zeros(0)
    vg = ViewGraph(vg_in.names, vg_in.edges[kept], R, H=H, inliers=stats["ba_n_inliers"], stats=stats, allow_isolated=True)
    vg.save(out)
    times = np.array([r["time_s"] for r in good])
    summary = {
        "stage": "two_view_ba",
        "config": dataclasses.asdict(cfg),
        "config_hash": chash,
        "input_fingerprint": fp,
        "n_pairs_in": M,
        "n_pairs_out": int(len(kept)),
        "dropped": dropped,
        "time_s": elapsed,
        "median_pair_time_ms": float(np.median(times) * 1e3) if times.size else None,
        "median_pair_cpu_ms": float(np.median([r["cpu_s"] for r in good]) * 1e3) if good else None,
        "median_iterations": float(np.median(stats["ba_iterations"])) if len(kept) else None,
        "median_rotation_change_deg": float(np.median(stats["ba_rotation_change_deg"])) if len(kept) else None,
        "median_cond_H": float(np.median(stats["ba_cond_H"])) if len(kept) else None,
    }
    write_json(summary_path, summary)
    logger.info(
        "two-view BA: %d/%d pairs refined in %.1f s (median %.1f ms/pair, %s iterations), %d dropped; wrote %s",
        len(kept), M, elapsed, summary["median_pair_time_ms"] or float("nan"), summary["median_iterations"], len(dropped), out,
    )
    return out


def main_cli(argv: Sequence[str] | None = None) -> int:
    from pipeline.core.cli import run_cli

    parser = argparse.ArgumentParser(
        prog="python -m pipeline.two_view_ba",
        description="Two-view bundle adjustment of every accepted pair in WORK and the marginalized 3×3 rotation "
        "Hessian H_ij; writes WORK/viewgraph.npz for the averaging stage.",
    )
    parser.add_argument("--work", required=True, type=Path, help="WORK folder of the front end")
    parser.add_argument("--config", type=Path, default=None, help="YAML config; section 'two_view_ba'")
    parser.add_argument("--sigma-px", type=float, default=None, help="known pixel noise σ (default: estimate)")
    parser.add_argument("--loss", choices=LOSSES, default=None, help="robust loss (default cauchy)")
    parser.add_argument("--loss-scale-px", type=float, default=None, help="robust loss scale in px (default 3σ)")
    parser.add_argument("--no-ba", action="store_true", help="keep the RANSAC pose; compute H at it")
    parser.add_argument("--no-refit", action="store_true", help="keep the robust weights; no inlier refit")
    parser.add_argument("--workers", type=int, default=None, help="processes (default 2)")
    parser.add_argument("--overwrite", action="store_true", help="recompute even if an up-to-date result exists")

    def body(a: argparse.Namespace) -> int:
        cfg = stage_config(
            BAConfig, load_yaml(a.config), "two_view_ba",
            sigma_px=a.sigma_px, loss=a.loss, loss_scale_px=a.loss_scale_px, workers=a.workers,
            enabled=False if a.no_ba else None, refit_inliers=False if a.no_refit else None,
        )
        path = main(a.work, cfg, overwrite=a.overwrite, progress=not a.quiet)
        print(path)
        return 0

    return run_cli(body, parser, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
