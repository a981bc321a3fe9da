"""Riemannian Newton polish of the fixed-weight problem (1) of :mod:`~pipeline.averaging.certificate.problem`.

A critical point makes the certificate sharp; the bound itself needs no stationarity.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline.averaging.certificate.eigen import ldl_inertia
from pipeline.averaging.certificate.problem import block_matrix, connection_laplacian, sym, vee_skew
from pipeline.core import so3

__all__ = ["newton_system", "polish"]


def newton_system(n: int, edges: np.ndarray, C: np.ndarray, D: np.ndarray, L: sp.csr_matrix,
                   R: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray, float]:
    """Exact second-order model of ``f(R_i exp([δ_i]×))`` = ``f + gᵀδ + δᵀ Hq δ + O(δ³)``.

    With ``A_ab = R_aᵀ L_ab R_b`` for every nonzero block of L: ``Hq_ab = tr(A_ab) I − A_abᵀ``,
    plus ``sym(R_iᵀ G_i) − tr(R_iᵀ G_i) I`` on the diagonal (``G = LY``, the term of the
    second-order retraction); ``g_i = 4 vee(skew(R_iᵀ G_i))``.
    """
    Y = R.reshape(3 * n, 3)
    G = (L @ Y).reshape(n, 3, 3)
    K = np.swapaxes(R, 1, 2) @ G  # R_iᵀ G_i
    f = float(np.trace(K, axis1=1, axis2=2).sum())
    g = 4.0 * vee_skew(K)
    i, j = edges[:, 0], edges[:, 1]
    A_ji = -np.swapaxes(R[j], 1, 2) @ C @ R[i]          # R_jᵀ L_ji R_i
    H_ji = np.trace(A_ji, axis1=1, axis2=2)[:, None, None] * np.eye(3) - np.swapaxes(A_ji, 1, 2)
    A_ii = np.swapaxes(R, 1, 2) @ D @ R
    trK = np.trace(K, axis1=1, axis2=2)
    H_ii = (np.trace(A_ii, axis1=1, axis2=2)[:, None, None] * np.eye(3) - np.swapaxes(A_ii, 1, 2)
            + sym(K) - trK[:, None, None] * np.eye(3))
    Hq = block_matrix(n, np.concatenate([j, i, np.arange(n)]), np.concatenate([i, j, np.arange(n)]),
                    np.concatenate([H_ji, np.swapaxes(H_ji, 1, 2), H_ii]))
    Hq = sp.csc_matrix(0.5 * (Hq + Hq.T))
    return Hq, g, f


def polish(n: int, edges: np.ndarray, C: np.ndarray, D: np.ndarray, R0: np.ndarray,
           max_iterations: int = 20, grad_tol: float = 1e-12, ref: int = 0, fills: bool | None = None
           ) -> tuple[np.ndarray, dict[str, Any]]:
    """Riemannian Newton (Levenberg-damped) on the fixed-weight problem (1).

    The Newton matrix is factored by the same LDLᵀ as the certificate; a negative pivot
    (indefinite model) raises the damping until the model is convex, and a step that
    does not decrease f is rejected (damping ×10). The gauge is fixed by pinning ``ref``.

    Args:
        n, edges, C, D: the problem (see :func:`connection_laplacian`).
        R0: (N, 3, 3) start (e.g. the IRLS output).
        max_iterations: Newton iteration cap.
        grad_tol: stop when ‖g‖_∞ ≤ grad_tol·(f + Σ|w|) (relative to the cost scale).
        ref: camera pinned for the gauge.
        fills: whether the graph's sparse factor fills (:func:`~pipeline.averaging.certificate.eigen.ldl_inertia`).

    Returns:
        R: polished rotations; info: iterations, costs, gradient norms, max move (rad).
    """
    L = connection_laplacian(n, edges, C, D)
    R = R0.copy()
    scale = float(np.abs(D).sum()) / 3.0 + 1e-300
    mu = 0.0
    hist: list[dict[str, float]] = []
    keep = np.ones(3 * n, dtype=bool)
    keep[3 * ref: 3 * ref + 3] = False
    it = 0
    Hq, g, f = newton_system(n, edges, C, D, L, R)
    for it in range(1, max_iterations + 1):
        gmax = float(np.abs(g).max())
        hist.append({"cost": f, "grad_max": gmax, "mu": mu})
        if gmax <= grad_tol * (abs(f) + scale):
            break
        Hr = Hq[keep][:, keep].tocsc()
        dscale = np.maximum(Hr.diagonal(), 1e-12 * scale)
        accepted = False
        for _ in range(30):
            A = (Hr + mu * sp.diags(dscale)).tocsc()
            lu, n_neg, msg = ldl_inertia(A, fills)
            if msg or n_neg > 0:
                mu = max(1e-8, 10.0 * mu)
                continue
            d = np.zeros(3 * n)
            d[keep] = lu.solve(-0.5 * g.ravel()[keep])
            Rn = R @ so3.exp(d.reshape(n, 3))
            Hn, gn, fn = newton_system(n, edges, C, D, L, Rn)
            if fn <= f + 1e-14 * (abs(f) + scale):
                R, Hq, g, f = Rn, Hn, gn, fn
                mu = 0.0 if mu < 1e-6 else mu / 10.0
                accepted = True
                break
            mu = max(1e-8, 10.0 * mu)
        if not accepted:
            break
    move = so3.angle(np.swapaxes(R0, 1, 2) @ R)  # right-perturbation angle per camera (same gauge: ref pinned)
    return R, {"iterations": it, "history": hist, "final_cost": f, "final_grad_max": float(np.abs(g).max()),
               "max_move_rad": float(move.max()), "median_move_rad": float(np.median(move))}
