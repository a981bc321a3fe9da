"""The fixed-weight problem the certificate is about: its connection Laplacian, multipliers and LMI terms.

For fixed edge weights ``w_e ≥ 0`` and symmetric 3×3 edge metrics ``M_e`` (``M_e = I``:
isotropic; ``M_e = tr(H_e)/2·I − H_e``: paper 2, eq. 5)

    f(Y) = Σ_e 2 w_e (tr M_e − ⟨M_e R̃_e, R_j R_iᵀ⟩) = tr(Yᵀ L Y)                 (1)

with ``Y = [R_1; …; R_N]`` (3N, 3) and the (3N, 3N) connection Laplacian ``L``:
off-diagonal blocks ``L_ji = −C_e``, ``L_ij = −C_eᵀ`` with ``C_e = w_e M_e R̃_e``,
diagonal blocks ``L_ii = Σ_{e∋i} w_e M_e``. For ``M_e = I`` this is the weighted chordal
cost ``Σ w_e ‖R_j − R̃_e R_i‖²_F``; for any ``M_e`` of paper 2's form it is ≥ 0 on SO(3)
(paper 2, Corollary 1). See :mod:`pipeline.averaging.certificate` for the certificate.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline.core import so3

__all__ = ["metric_from_H", "chordal_weights", "edge_costs", "connection_laplacian", "diag_blocks",
           "lagrange_multipliers", "certificate_matrix", "rounding_floor", "lmi_multipliers", "lmi_apply",
           "lmi_ascent", "block_matrix", "sym", "vee_skew"]


def sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def vee_skew(A: np.ndarray) -> np.ndarray:
    """vee(skew(A)) for (..., 3, 3) → (..., 3)."""
    return 0.5 * np.stack([A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]], -1)


def metric_from_H(H: np.ndarray) -> np.ndarray:
    """Paper 2, eq. 5: ``M = tr(H)/2·I − H`` for (..., 3, 3) precisions."""
    H = sym(np.asarray(H, dtype=np.float64))
    return 0.5 * np.trace(H, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - H


def _H_from_metric(M: np.ndarray) -> np.ndarray:
    """Inverse of :func:`metric_from_H`: ``H = tr(M)·I − M``."""
    return np.trace(M, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - M


def chordal_weights(theta: np.ndarray, phi: np.ndarray, max_exact: float = np.pi / 2) -> np.ndarray:
    """Chordal weights with the same stationary points as IRLS's reweighted geodesic problem.

    IRLS's final step solves ``Σ φ_e θ_e²`` with fixed φ; its gradient is
    ``Σ 2 φ_e θ_e ∇θ_e``. The chordal term ``w ‖R_j − R̃R_i‖² = 4w(1 − cos θ)`` has gradient
    ``4 w sin θ ∇θ``. With ``w_e = φ_e θ_e / (2 sin θ_e)`` (→ φ_e/2 as θ → 0) both gradients
    coincide at the IRLS rotations, and ``w_e‖·‖² ≈ φ_e θ_e²`` for small θ.

    The factor θ/(2 sin θ) grows without bound as θ → π (×1000 at θ = π − 1e-3): robust
    losses without a hard cut-off (ℓ½) leave outliers with θ near π and a small φ, and the
    factor would turn them into heavy edges whose chordal problem is no longer certifiable
    (measured: kNN N = 2000, ℓ½ weights, "not verified" with the exact factor, "verified"
    with it capped). Beyond ``max_exact`` (90°) the factor is held at its value there (π/4),
    so only edges with residuals above 90° differ from the exact conversion; the polish then
    moves the rotations by what that difference implies (reported in ``polish``).

    Args:
        theta: (M,) geodesic residual angles (rad) at the IRLS output.
        phi: (M,) final IRLS weights (≥ 0).
        max_exact: angle beyond which the factor is held constant.

    Returns:
        (M,) chordal weights ≥ 0.
    """
    th = np.clip(np.asarray(theta, dtype=np.float64), 0.0, max_exact)
    small = th < 1e-4
    ratio = np.where(small, 1.0 + th**2 / 6.0, th / np.where(small, 1.0, np.sin(th)))
    return 0.5 * np.asarray(phi, dtype=np.float64) * ratio


def edge_costs(edges: np.ndarray, C: np.ndarray, trM: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Per-edge terms of (1): ``2(w tr M_e − ⟨C_e, R_j R_iᵀ⟩)``, (M,)."""
    Q = so3.relative(R, edges)
    return 2.0 * (trM - np.einsum("mab,mab->m", C, Q))


def block_matrix(n: int, bi: np.ndarray, bj: np.ndarray, B: np.ndarray) -> sp.csr_matrix:
    """(3n, 3n) sparse matrix with 3×3 blocks ``B[k]`` added at block (bi[k], bj[k])."""
    a = np.arange(3)
    rows = (3 * bi[:, None, None] + a[None, :, None]).repeat(3, axis=2)
    cols = (3 * bj[:, None, None] + a[None, None, :]).repeat(3, axis=1)
    return sp.csr_matrix((B.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n))


def connection_laplacian(n: int, edges: np.ndarray, C: np.ndarray, D: np.ndarray) -> sp.csr_matrix:
    """The (3N, 3N) matrix L of (1).

    Args:
        n: number of cameras N.
        edges: (M, 2) ``(i, j)``.
        C: (M, 3, 3) ``w_e M_e R̃_e`` (``L_ji = −C_e``, ``L_ij = −C_eᵀ``).
        D: (N, 3, 3) symmetric diagonal blocks ``Σ_{e∋i} w_e M_e``.
    """
    i, j = edges[:, 0], edges[:, 1]
    bi = np.concatenate([j, i, np.arange(n)])
    bj = np.concatenate([i, j, np.arange(n)])
    B = np.concatenate([-C, -np.swapaxes(C, 1, 2), D])
    return block_matrix(n, bi, bj, B)


def diag_blocks(n: int, edges: np.ndarray, WM: np.ndarray) -> np.ndarray:
    """``Σ_{e∋i} WM_e`` (N, 3, 3) for per-edge symmetric blocks WM (M, 3, 3)."""
    D = np.zeros((n, 9))
    flat = WM.reshape(-1, 9)
    for col in (0, 1):
        np.add.at(D, edges[:, col], flat)  # vectorized scatter over edges
    return D.reshape(n, 3, 3)


def lagrange_multipliers(L: sp.spmatrix, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Λ_i = sym((LY)_i R_iᵀ)`` and the Riemannian gradient blocks ``skew((LY)_i R_iᵀ) R_i``.

    Returns:
        Lam: (N, 3, 3) symmetric multipliers.
        G: (N, 3, 3) ``(S Y)_i`` (zero at a first-order critical point).
    """
    n = R.shape[0]
    LY = (L @ R.reshape(3 * n, 3)).reshape(n, 3, 3)
    P = LY @ np.swapaxes(R, 1, 2)
    Lam = sym(P)
    G = (P - Lam) @ R
    return Lam, G


def rounding_floor(S: sp.spmatrix) -> float:
    """``1e3·ε·‖S‖₁``: the rounding level of S, below which no test of ``S ⪰ −ηI`` decides anything."""
    return 1e3 * float(np.finfo(float).eps) * float(abs(S).sum(axis=0).max())


def certificate_matrix(L: sp.spmatrix, Lam: np.ndarray) -> sp.csc_matrix:
    """``S = L − blkdiag(Λ)`` as CSC (3N, 3N)."""
    n = Lam.shape[0]
    S = L - block_matrix(n, np.arange(n), np.arange(n), Lam)
    S = sp.csc_matrix(0.5 * (S + S.T))  # exact symmetry (Λ is symmetric; guards round-off)
    S.sum_duplicates()
    return S


def lmi_multipliers(edges: np.ndarray, C: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The smallest conv(SO(3)) multipliers ``V_e`` (M, 3, 3) that make each edge's effective weight PSD.

    For each edge, with ``P = sym(C_e Q_eᵀ)`` and its effective ``H = tr(P)·I − P`` with eigenvalues
    η₁ ≥ η₂ ≥ η₃ (eigenvectors u), ``V_e = ½ max(0, η₁ − η₂ − η₃) u₁u₁ᵀ``: then ``sym(C'_e Q_eᵀ)`` of
    :func:`lmi_apply` is PSD whenever H ⪰ 0.
    """
    Q = so3.relative(R, edges)
    P = sym(C @ np.swapaxes(Q, 1, 2))
    eta, U = np.linalg.eigh(_H_from_metric(P))  # ascending: η₃ ≤ η₂ ≤ η₁
    excess = np.maximum(0.0, eta[:, 2] - eta[:, 1] - eta[:, 0])
    u1 = U[:, :, 2]
    return 0.5 * excess[:, None, None] * u1[:, :, None] * u1[:, None, :]


def lmi_apply(edges: np.ndarray, C: np.ndarray, R: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``C'_e = C_e − 2𝓜(V_e) Q_e`` for multipliers ``V`` (M, 3, 3), each PSD.

    Every PSD ``V_e`` is a multiplier of the edge's conv(SO(3)) LMI at the rotations ``R``: the LMI's dual
    variables with complementary slackness are ``W_e = B Z Bᵀ ⪰ 0`` (``B`` spanning the null space of the
    rank-one ``𝒜(Q_e) + I``), and ``𝒜*(W_e) = −2𝓜(V_e) Q_e`` with ``V_e`` congruent to ``Z`` (checked in
    ``tests/averaging/test_certificate.py``). ``𝓜(V_e)`` is symmetric, so ``C'`` keeps ``R``'s stationarity.
    """
    return C - 2.0 * metric_from_H(V) @ so3.relative(R, edges)


def lmi_ascent(edges: np.ndarray, R: np.ndarray, V: np.ndarray, witnesses: np.ndarray, lam: float,
               factor: float = 2.0) -> np.ndarray:
    """One projected supergradient step on the PSD multipliers ``V`` (M, 3, 3), raising S's negative eigenvalues.

    ``S`` depends on ``V_e`` through ``−2 (x_j − Q_e x_i)ᵀ 𝓜(V_e) (x_j − Q_e x_i)`` (the edge's block and, by
    stationarity, its two multipliers Λ), so for a unit eigenvector v, with ``z_e = v_j − Q_e v_i``, the
    supergradient of its eigenvalue is ``g_e = 2 z_e z_eᵀ − |z_e|² I``; over the ``witnesses`` (3N, k), the
    eigenvectors of the negative eigenvalues, the sum of theirs (a supergradient of their sum, which moves them
    together where one at a time would zigzag between them). The step is ``factor``·|lam|/‖g‖² (``factor`` 2:
    Polyak's towards ``|lam|``, ``lam`` < 0 the smallest eigenvalue; the caller searches longer ones), and each
    ``V_e`` is projected back onto the PSD cone. Every PSD V keeps the certificate valid (:func:`lmi_apply`).
    """
    W = np.asarray(witnesses, dtype=np.float64).reshape(3 * R.shape[0], -1)
    Vb = W.T.reshape(W.shape[1], -1, 3)  # (k, N, 3)
    z = Vb[:, edges[:, 1]] - np.einsum("mab,kmb->kma", so3.relative(R, edges), Vb[:, edges[:, 0]])
    g = 2.0 * np.einsum("kma,kmb->mab", z, z) - np.einsum("kma,kma->m", z, z)[:, None, None] * np.eye(3)
    g2 = float(np.sum(g * g))
    if not g2 > 0:
        return V
    w, E = np.linalg.eigh(V + (factor * abs(lam) / g2) * g)
    return np.einsum("mab,mb,mcb->mac", E, np.maximum(w, 0.0), E)
