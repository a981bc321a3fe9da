"""Analysis: what pairwise measurements allow, the Cramér–Rao bound of rotation averaging.

The edges of a view graph are modelled as Gaussian, ``R̃_ij = exp([Δω]×) R_j R_iᵀ``
with ``Δω ~ N(0, W_ij⁻¹)`` (``W_ij`` = H_ij, possibly rescaled). The information
of the rotations is ``Σ_e A_eᵀ W_e A_e`` (:func:`information`); its pseudo-inverse
is the covariance an efficient estimator reaches, and :func:`predicted_errors`
draws from it and scores the draws as the evaluation does (aligned on a subset
of cameras). :func:`pose_information` adds each pair's translation direction
(the two-view BA's 5×5 pose precision, with the camera centres as unknowns): what
a global SfM from pairwise poses could reach. Used by ``benchmarks/temple_limit.py``;
checked against Monte Carlo in ``tests/evaluation/test_analysis.py``.

Perturbations are on the left (``R_i ← exp(ω_i) R_i``), as everywhere in the
pipeline (docs/CONVENTIONS.md).
"""

from __future__ import annotations

import numpy as np

from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["information", "pose_jacobian", "pose_information", "predicted_errors"]


def information(vg: ViewGraph, R: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Dense (3N, 3N) ``Σ_e A_eᵀ W_e A_e`` for left perturbations ``R_i ← exp(ω_i) R_i``.

    The residual of edge (i, j) is ``ω_j − R_ij ω_i`` (camera j's frame), so
    ``A_e`` is ``−R_ij`` at i and ``I`` at j; the blocks are scattered with
    ``np.add.at`` (no loop over edges).
    """
    N = vg.n_cameras
    i, j = vg.edges.T
    Rt = so3.relative(R, vg.edges)
    RtT = np.swapaxes(Rt, 1, 2)
    B = np.zeros((N, N, 3, 3))
    np.add.at(B, (i, i), RtT @ W @ Rt)
    np.add.at(B, (j, j), W)
    np.add.at(B, (i, j), -RtT @ W)
    np.add.at(B, (j, i), -W @ Rt)
    return B.transpose(0, 2, 1, 3).reshape(3 * N, 3 * N)


def pose_jacobian(vg: ViewGraph, R: np.ndarray, C: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(M, 5, 4, 3) Jacobian of each pair's ``(δ, δt)`` with respect to ``(ω_i, ω_j, δc_i, δc_j)``.

    ``R_i ← exp(ω_i) R_i`` and ``c_i ← c_i + δc_i`` (world frame). Edge (i, j) measures
    ``R_ij = R_j R_iᵀ`` and the direction ``t`` of ``u = R_j (c_i − c_j)`` (``x_j = R_ij x_i + t_ij``):
    ``δ = ω_j − R_ij ω_i`` and ``δt = Bᵀ(I − ttᵀ)/‖u‖ · (−[u]× ω_j + R_j δc_i − R_j δc_j)``, with
    ``B`` (M, 3, 2) the tangent basis in which the two-view BA gives ``δt``.
    """
    i, j = vg.edges.T
    u = np.einsum("mab,mb->ma", R[j], C[i] - C[j])
    nu = np.linalg.norm(u, axis=1)
    t = u / np.maximum(nu, 1e-300)[:, None]
    P = np.einsum("mab,mac->mbc", B, np.eye(3) - t[:, :, None] * t[:, None, :]) / np.maximum(nu, 1e-300)[:, None, None]
    A = np.zeros((vg.n_edges, 5, 4, 3))
    A[:, :3, 0] = -so3.relative(R, vg.edges)
    A[:, :3, 1] = np.eye(3)
    A[:, 3:, 1] = -P @ so3.hat(u)
    A[:, 3:, 2] = P @ R[j]
    A[:, 3:, 3] = -P @ R[j]
    return A


def pose_information(vg: ViewGraph, R: np.ndarray, C: np.ndarray, B: np.ndarray, S: np.ndarray,
                     min_baseline: float = 0.0) -> np.ndarray:
    """Dense (6N, 6N) information ``Σ_e A_eᵀ S_e A_e`` of rotations then camera centres from pairwise poses.

    ``A_e`` is :func:`pose_jacobian`'s and ``S`` (M, 5, 5) the two-view BA's precision of
    ``(δ, δt)``. Pairs with a baseline at or below ``min_baseline`` (a zero-baseline pair
    measures no direction) keep their rotation rows only. The gauge is 7-dimensional (a
    similarity of the world), more where the centres are not rigid.
    """
    N = vg.n_cameras
    i, j = vg.edges.T
    A = pose_jacobian(vg, R, C, B)
    A[np.linalg.norm(C[i] - C[j], axis=1) <= min_baseline, 3:] = 0.0
    cols = np.stack([i, j, N + i, N + j], axis=1)  # (M, 4) block columns
    SA = np.einsum("mrs,mskb->mrkb", S, A)
    G = np.einsum("mrka,mrlb->mklab", A, SA)  # (M, 4, 4, 3, 3): A_kᵀ S A_l
    out = np.zeros((2 * N, 2 * N, 3, 3))
    np.add.at(out, (cols[:, :, None], cols[:, None, :]), G)
    return out.transpose(0, 2, 1, 3).reshape(6 * N, 6 * N)


def predicted_errors(J: np.ndarray, R: np.ndarray, mask: np.ndarray, draws: int, seed: int) -> np.ndarray:
    """(draws,) median camera error (deg) of Gaussian draws with covariance ``J⁺``, aligned on ``mask``.

    ``J`` is (3N, 3N) over the rotations, or (6N, 6N) over rotations then centres
    (only the rotations are scored). Its null space (the gauge) gets no variance.

    The alignment removes the best common rotation ``ω_i = R_i v`` on the masked
    cameras, the linearization of the evaluation's ℓ2 alignment.
    """
    lam, V = np.linalg.eigh(J)
    tol = lam[-1] * 1e-12
    inv = np.where(lam > tol, 1.0 / np.where(lam > tol, lam, 1.0), 0.0)
    L = V * np.sqrt(inv)
    Z = np.random.default_rng(seed).standard_normal((J.shape[0], draws))
    w = (L[: 3 * mask.size] @ Z).T.reshape(draws, -1, 3)[:, mask]  # (draws, n, 3)
    G = R[mask].reshape(-1, 3)  # ω_i = R_i v stacked: (3n, 3)
    P = np.eye(G.shape[0]) - G @ np.linalg.pinv(G)
    w = (w.reshape(draws, -1) @ P.T).reshape(draws, -1, 3)
    return np.median(np.degrees(np.linalg.norm(w, axis=2)), axis=1)
