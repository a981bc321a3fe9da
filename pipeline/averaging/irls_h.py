"""Robust IRLS in the metric of the two-view Hessians H (anisotropic IRLS).

Paper 1's IRLS (:mod:`pipeline.averaging.irls`) weighs every edge's residual
isotropically: one scalar weight ``φ(‖r_ij‖)`` per edge. Paper 2 shows that the
two-view uncertainty is strongly anisotropic and that weighting by H pays. This
module joins the two: the same joint IRLS in the Lie algebra, with each edge's
residual measured in its own Mahalanobis norm and the robust loss applied to that
norm. It is a local method (no certificate); SDP-cSO(3) solves the least-squares
version globally.

The residual of paper 1 (eq. 7) is ``r_ij = log(R_jᵀ R̃_ij R_i)``. With H defined
for the left perturbation ``R_j R_iᵀ = exp([Δω]×) R̃_ij`` (DESIGN.md),
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

**Start and polish.** As :func:`pipeline.averaging.irls.irls`: a spanning tree,
isotropic ℓ1 steps (paper 1, Algorithm 2), then the anisotropic IRLS, then (with
``refine``) a trimmed least-squares polish: ``s`` is re-estimated from the
converged residuals and edges with ``t > 3.76`` (the 99.7% point of χ₃) get
weight 0 (Talwar).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from pipeline.averaging.init import initial_rotations
from pipeline.averaging.kernel import LaplacianSolver, apply_update, check_graph, edge_residuals
from pipeline.averaging.l1 import L1StartConfig, l1_averaging
from pipeline.averaging.losses import Loss, get_loss
from pipeline.averaging.result import AveragingResult, method_config, start_of
from pipeline.core import so3
from pipeline.core.config import option
from pipeline.core.errors import ConfigError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["IRLSHConfig", "BlockLaplacianSolver", "irls_h", "edge_metric", "CHI2_3_MEDIAN", "TRIM_T"]

logger = logging.getLogger(__name__)

#: Median of the χ² distribution with 3 degrees of freedom.
CHI2_3_MEDIAN = 2.3660
#: 99.7% point of the χ distribution with 3 degrees of freedom: the polish's trimming threshold.
TRIM_T = 3.76


class BlockLaplacianSolver:
    """Factor and solve gauge-fixed block Laplacians ``Σ_k A_kᵀ B_k A_k`` with 3×3 edge blocks.

    The (3N, 3N) sparsity pattern and the map from the (M, 3, 3) blocks to matrix
    entries are built once; :meth:`factor` scatters the blocks with
    ``np.bincount`` and calls SuperLU once. The gauge is fixed as in
    :class:`pipeline.averaging.kernel.LaplacianSolver`: one pinned camera per
    connected component of the edges with a nonzero block.

    Args:
        edges: (M, 2) camera indices.
        n: number of cameras N.
        ref: the camera pinned when the weighted graph is connected.
    """

    def __init__(self, edges: np.ndarray, n: int, ref: int = 0) -> None:
        edges = np.asarray(edges, dtype=np.int64)
        M = edges.shape[0]
        self.n, self.edges = int(n), edges
        self._pins = LaplacianSolver(edges, n, ref=ref)._pins  # the same gauge rule
        i, j = edges[:, 0], edges[:, 1]
        p, q = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        p, q = p.ravel(), q.ravel()  # the 9 entries of a block, row-major
        # 4 blocks per edge: (i,i) +B, (j,j) +B, (i,j) −B, (j,i) −B; then N identity-diagonal slots.
        bi = np.concatenate([i, j, i, j])
        bj = np.concatenate([i, j, j, i])
        rows = np.concatenate([(3 * bi[:, None] + p).ravel(), 3 * np.arange(n)[:, None].repeat(3, 1).ravel()
                               + np.tile(np.arange(3), n)])
        cols = np.concatenate([(3 * bj[:, None] + q).ravel(), 3 * np.arange(n)[:, None].repeat(3, 1).ravel()
                               + np.tile(np.arange(3), n)])
        N3 = 3 * n
        keys = cols * N3 + rows  # CSC order
        ukeys, inv = np.unique(keys, return_inverse=True)
        n_blk = 4 * M * 9
        self._pos = inv[:n_blk]
        self._sign = np.repeat([1.0, 1.0, -1.0, -1.0], M * 9)
        # block entry (edge, p, q) in the flattened (M·9,) array of blocks
        self._src = np.tile((np.arange(M)[:, None] * 9 + np.arange(9)).ravel(), 4)
        self._row, self._col = ukeys % N3, ukeys // N3
        self._diag = inv[n_blk:].reshape(n, 3)
        self._nnz = ukeys.size
        self._indptr = np.searchsorted(self._col, np.arange(N3 + 1)).astype(np.int32)
        self._indices = self._row.astype(np.int32)
        self._lu: sla.SuperLU | None = None
        self.pinned = np.zeros(n, dtype=bool)
        self._lu_pinned = self.pinned
        self.n_factorizations = 0
        self.n_cg_iterations = 0

    def matrix(self, B: np.ndarray) -> sp.csc_matrix:
        """The gauge-fixed (3N, 3N) block Laplacian for edge blocks ``B`` (M, 3, 3)."""
        B = np.asarray(B, dtype=np.float64)
        self.pinned = self._pins(np.trace(B, axis1=1, axis2=2))
        data = np.bincount(self._pos, weights=self._sign * B.reshape(-1)[self._src], minlength=self._nnz)
        if self.pinned.any():
            cam_row, cam_col = self._row // 3, self._col // 3
            data *= ~(self.pinned[cam_row] | self.pinned[cam_col])
            data[self._diag[self.pinned].ravel()] = 1.0
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(3 * self.n, 3 * self.n))

    def factor(self, B: np.ndarray) -> None:
        """Factor the gauge-fixed block Laplacian for edge blocks ``B`` (M, 3, 3)."""
        self._factorize(self.matrix(B))

    def _factorize(self, A: sp.csc_matrix) -> None:
        self._lu = sla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
        self._lu_pinned = self.pinned.copy()
        self.n_factorizations += 1

    def solve_reusing(self, B: np.ndarray, b: np.ndarray, rtol: float = 1e-7, max_cg: int = 15) -> np.ndarray:
        """Solve the system of blocks ``B`` for ``b`` (N, 3), reusing the last factor when it serves.

        IRLS weights change little from one iteration to the next, so the factor of the
        previous matrix is a near-exact preconditioner for the current one: conjugate
        gradients on the current matrix, preconditioned by it, reach ``rtol`` in a few
        matrix-vector products. When they do not within ``max_cg`` iterations, or when the
        gauge (the pinned cameras) changed, the current matrix is factored instead. The
        solution is that of the current matrix either way (to ``rtol``).
        """
        A = self.matrix(B)  # sets self.pinned for B
        pinned = self.pinned
        if self._lu is not None and np.array_equal(pinned, self._lu_pinned):
            bb = np.array(b, dtype=np.float64, copy=True)
            bb[pinned] = 0.0
            lu = self._lu
            prec = sla.LinearOperator(A.shape, matvec=lambda v: lu.solve(np.asarray(v, dtype=np.float64)))
            n_it = [0]

            def count(_):
                n_it[0] += 1

            x, info = sla.cg(A, bb.reshape(-1), M=prec, rtol=rtol, atol=0.0, maxiter=max_cg, callback=count)
            self.n_cg_iterations += n_it[0]
            if info == 0 and np.all(np.isfinite(x)):
                x = x.reshape(self.n, 3)
                x[pinned] = 0.0
                return x
        self._factorize(A)
        return self.solve(b)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the current factor; ``b`` (N, 3) → (N, 3), 0 at pinned cameras."""
        if self._lu is None:
            raise RuntimeError("BlockLaplacianSolver.solve called before factor()")
        b = np.array(b, dtype=np.float64, copy=True)
        b[self.pinned] = 0.0
        x = self._lu.solve(b.reshape(-1)).reshape(self.n, 3)
        x[self.pinned] = 0.0
        return x

    def rhs(self, g: np.ndarray) -> np.ndarray:
        """``Σ_k A_kᵀ g_k`` for per-edge vectors ``g`` (M, 3): −g at camera i, +g at camera j."""
        i, j = self.edges[:, 0], self.edges[:, 1]
        return np.stack([np.bincount(j, g[:, a], self.n) - np.bincount(i, g[:, a], self.n) for a in range(3)], axis=1)


def edge_metric(vg: ViewGraph, R: np.ndarray) -> np.ndarray:
    """``W_ij = R_jᵀ H_ij R_j`` (M, 3, 3): H in the frame of the residual ``log(R_jᵀ R̃_ij R_i)``."""
    Rj = R[vg.edges[:, 1]]
    return np.swapaxes(Rj, 1, 2) @ vg.H @ Rj


def _squared_norms(vg: ViewGraph, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r = edge_residuals(vg.edges, vg.R_rel, R)
    W = edge_metric(vg, R)
    return r, W, np.einsum("ma,mab,mb->m", r, W, r)


def _jl_inv(w: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian of SO(3), (M, 3) → (M, 3, 3):
    ``log(exp([a]×) exp([w]×)) = w + J_l⁻¹(w) a + O(|a|²)``.

    ``J_l⁻¹(w) = I − ½[w]× + c(θ)[w]×²`` with ``c = 1/θ² − cot(θ/2)/(2θ)`` (finite at θ = π;
    its series ``1/12 + θ²/720 + θ⁴/30240`` below 1e-3 rad).
    """
    th = np.sqrt(np.einsum("ma,ma->m", w, w))
    small = th < 1e-3
    ts = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th**2 / 720.0 + th**4 / 30240.0,
                 1.0 / ts**2 - 1.0 / (2.0 * ts * np.tan(0.5 * ts)))
    K = so3.hat(w)
    return np.eye(3) - 0.5 * K + c[:, None, None] * (K @ K)


def _scale(q: np.ndarray) -> float:
    # No degrees-of-freedom correction for fitted residuals: scaling s² by M/(M−N+1) trims
    # fewer inliers on synthetic graphs (~0.3% instead of ~1%) but made templeSparseRing worse
    # (0.425° → 0.468° median) and the other real/rendered scenes equal or slightly worse.
    s2 = float(np.median(q)) / CHI2_3_MEDIAN
    if not (np.isfinite(s2) and s2 > 0):
        # every residual is zero to rounding (exact data): any positive scale gives the same answer
        s2 = float(np.mean(q)) / 3.0 if np.mean(q) > 0 else 1.0
    return s2


def _steps(vg: ViewGraph, R: np.ndarray, solver: BlockLaplacianSolver, lossf: Loss, s2: float, max_iterations: int,
           tol_rad: float, stage: str, t0: float, history: list[dict[str, float]], reuse: bool = True
           ) -> tuple[np.ndarray, int, bool]:
    it = 0
    for it in range(1, max_iterations + 1):
        r, W, q = _squared_norms(vg, R)
        t = np.sqrt(q / s2)
        phi = lossf.phi(t)
        # Gauss–Newton in Δω = −R_j r (module docstring): Δω ← Δω + G (δ_j − δ_i), G = J_l⁻¹(Δω) R_j.
        Rj = R[vg.edges[:, 1]]
        dom = -np.einsum("mab,mb->ma", Rj, r)
        G = _jl_inv(dom) @ Rj
        HG = vg.H @ G
        w = (phi / s2)[:, None, None]
        B = w * (np.swapaxes(G, 1, 2) @ HG)
        g = solver.rhs(-np.einsum("mba,mb->ma", w * HG, dom))
        if reuse:
            dw = solver.solve_reusing(B, g)
        else:
            solver.factor(B)
            dw = solver.solve(g)
        if not np.all(np.isfinite(dw)):
            raise ViewGraphError(f"anisotropic IRLS step {it} is not finite (loss {lossf.name}); "
                                 "the weighted block Laplacian is singular. Check H for NaN or try another loss")
        R = apply_update(R, dw)
        norms = np.linalg.norm(dw, axis=1)
        history.append({"stage": stage, "cost": float(lossf.rho(t).sum()), "mean_step_rad": float(norms.mean()),
                        "max_step_rad": float(norms.max()), "time_s": time.perf_counter() - t0})
        if norms.mean() < tol_rad:
            return R, it, True
    return R, it, False


@dataclass(frozen=True, kw_only=True)
class IRLSHConfig(L1StartConfig):
    """Options of :func:`irls_h` (the ``irls-h`` method); see :func:`irls_h` for what each does."""

    SECTION = "averaging.irls-h"
    loss: str = option("l0.5", "loss of paper 1, Table 1, on the H-normalized residual")
    alpha_sigma: float = option(2.0, "loss scale α in units of the robust residual scale s (not degrees)", gt=0)
    max_iterations: int = option(100, "IRLS iteration cap", ge=0)
    tol_rad: float = option(1e-5, "stop when the mean camera update is below this (radians)", ge=0)
    refine: bool = option(True, "after convergence, least squares on the edges with t <= 3.76 (Talwar)")
    refine_iterations: int = option(20, "iteration cap of the polish", ge=0)
    scale: float | None = option(None, "a fixed s² (NEES scale of H) instead of the robust estimate", gt=0)

    def check(self) -> None:
        try:
            get_loss(self.loss)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None


def irls_h(vg: ViewGraph, config: IRLSHConfig | None = None, *, init: str | np.ndarray | None = None,
           init_weights: np.ndarray | None = None, **options: Any) -> AveragingResult:
    """Robust rotation averaging with each edge's residual in its H metric.

    Args:
        vg: a connected view graph with H.
        config: the options; ``**options`` override its fields (:class:`IRLSHConfig`):
        loss: loss name of :func:`pipeline.averaging.losses.get_loss` (default ℓ½).
        alpha_sigma: loss scale α in units of the robust residual scale ``s`` (module
            docstring), not degrees. Default 2: residuals up to 2s (≈ 1.3× the
            median of an inlier) are in ℓ½'s quadratic core.
        init: ``"mst"``, ``"random"`` or (N, 3, 3) initial rotations.
        max_iterations, tol_rad: IRLS cap and stop on the mean camera update
            (radians; 1e-5 by default, 0.0006°; at N = 500, 1e-6 took 13 iterations
            instead of 9 for the same median error).
        l1_iterations, l1_tol_rad, admm_max_iterations: the isotropic ℓ1 start (see
            :func:`pipeline.averaging.irls.irls`); 0 skips it.
        seed: seed for ``init="random"``.
        init_weights: (M,) weights of the ``"mst"`` tree (default: inliers).
        refine: after convergence, re-estimate ``s`` and run least squares on the
            edges with ``t ≤ 3.76`` (Talwar).
        refine_iterations: iteration cap of the polish.
        scale: a fixed ``s²`` (the NEES scale of H) instead of the robust estimate.

    Returns:
        :class:`AveragingResult` with ``residuals_rad`` (geodesic angles), ``weights``
        and ``stats`` (``scale_s2`` of each stage, ``normalized_residuals``,
        ``n_trimmed``, ``converged``, iteration counts).

    Raises:
        ViewGraphError: the view graph has no H, or a step is not finite.
    """
    cfg = method_config(IRLSHConfig, config, options, init)
    check_graph(vg)
    if vg.H is None:
        raise ViewGraphError("anisotropic IRLS needs a view graph with H (two-view BA precisions); "
                             "run the two-view BA stage or use method 'irls'")
    # get_loss takes degrees; the normalized residual t is dimensionless, used here as if radians
    lossf = get_loss(cfg.loss, float(np.rad2deg(cfg.alpha_sigma)), None)
    t0 = time.perf_counter()
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
    s2 = scale if scale is not None else _scale(_squared_norms(vg, R)[2])
    R, it, converged = _steps(vg, R, solver, lossf, s2, cfg.max_iterations, cfg.tol_rad, "irls-h", t0, history)
    s2_refine, n_trimmed = None, 0
    refine = cfg.refine
    if refine:
        s2_refine = scale if scale is not None else _scale(_squared_norms(vg, R)[2])
        tal = get_loss("talwar", float(np.rad2deg(TRIM_T)))
        R, _, _ = _steps(vg, R, solver, tal, s2_refine, cfg.refine_iterations, cfg.tol_rad, "refine", t0, history)
    r, W, q = _squared_norms(vg, R)
    s2_final = s2_refine if s2_refine is not None else s2
    t = np.sqrt(q / s2_final)
    if refine:
        n_trimmed = int(np.sum(t > TRIM_T))
    phi = (tal if refine else lossf).phi(t)
    elapsed = time.perf_counter() - t0
    if not converged and cfg.max_iterations > 0:
        logger.warning("anisotropic IRLS-%s stopped at the iteration cap (%d) with mean step %.3g rad > %.3g rad",
                       lossf.name, cfg.max_iterations, history[-1]["mean_step_rad"], cfg.tol_rad)
    logger.info("IRLS-H-%s: %d cameras, %d edges, %d IRLS iterations, s² = %.3g, %d edges trimmed, %.3f s",
                lossf.name, vg.n_cameras, vg.n_edges, it, s2_final, n_trimmed, elapsed)
    n_l1 = sum(1 for h in history if h.get("stage") == "l1")
    return AveragingResult(
        method=f"irls-h-{lossf.name}" + ("+refine" if refine else ""),
        names=list(vg.names),
        R=R,
        time_s=elapsed,
        iterations=it,
        edge_index=np.arange(vg.n_edges),
        residuals_rad=np.linalg.norm(r, axis=1),
        weights=phi,
        history=history,
        stats={
            "loss": lossf.name,
            "alpha": float(cfg.alpha_sigma),
            "scale_s2": float(s2),
            "scale_s2_refine": None if s2_refine is None else float(s2_refine),
            "normalized_residuals": t.tolist(),
            "n_trimmed": n_trimmed,
            "converged": converged,
            "l1_iterations": n_l1,
            "irls_iterations": it,
            "n_factorizations": solver.n_factorizations,
            "n_cg_iterations": solver.n_cg_iterations,
            "refine": refine,
        },
    )
