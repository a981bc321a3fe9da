"""Normal equations of the two-view BA and the Schur elimination of the points and the translation.

The normal equations ``JᵀWJ`` are reduced by the Schur complement on the 3×3
point blocks, leaving a 5×5 pose system. Because each point's 4×3 Jacobian has
a one-dimensional left null space ``n_k``, its Schur term ``W_k V_k⁻¹ W_kᵀ``
leaves the rank-one ``Jc_kᵀ n_k n_kᵀ Jc_k``, computed in closed form with O(n)
vector operations (:func:`point_null_vectors`, :func:`reduced_system`);
:func:`rotation_hessian` keeps the textbook route with batched 3×3 inverses, and
the tests check that they agree. No dense ``(3n+5)²`` matrix is ever formed.
Eliminating the translation block next (:func:`marginalize_translation`, with a
pseudo-inverse so that a zero-baseline pair still gets a finite ``H``) leaves
the 3×3 rotation information.

Per-point arrays are component-major (k, n) so every formula is a few
contiguous vector operations; :func:`linearize` reuses a state's linearization
(Jacobian, null vectors) between the inlier test, the next fit and ``H``.
"""

from __future__ import annotations

import numpy as np

from pipeline.geometry.ba_model import jacobians, tangent_basis

__all__ = ["marginalize_translation", "rotation_hessian", "normal_equation_blocks", "point_null_vectors",
           "reduced_jacobian", "reduced_system", "rho_gain", "point_step", "linearize", "pinv_sym"]


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


def pinv_sym(S: np.ndarray) -> np.ndarray:
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

    The textbook route; :func:`~pipeline.geometry.ba_solver.refine_pair` uses the equivalent closed form of
    :func:`point_null_vectors` (rank-one per point), and the tests check that
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


def point_null_vectors(J: np.ndarray, Ki: np.ndarray) -> np.ndarray:
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


def reduced_jacobian(J: np.ndarray, nv: np.ndarray) -> np.ndarray:
    """Pose Jacobian (5, n) of each point's residual along its null vector, ``j_k = n_kᵀ Jc_k``."""
    return (nv[2:, None, :] * J[:, :5]).sum(axis=0)


def reduced_system(r: np.ndarray, w: np.ndarray, J: np.ndarray, nv: np.ndarray,
                    j: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pose system with the points eliminated: S (5,5) = Σ w j jᵀ and g (5,) = Σ w j e.

    ``e_k = n_kᵀ r_k`` is point k's residual orthogonal to its own Jacobian and
    ``j_k = n_kᵀ Jc_k`` its pose Jacobian (image i has no pose dependence);
    ``j`` (5, n) may be passed if known.
    """
    e = (nv * r).sum(axis=0)
    if j is None:
        j = reduced_jacobian(J, nv)
    jw = j * w
    return jw @ j.T, jw @ e


def rho_gain(J: np.ndarray) -> np.ndarray:
    """``−‖d r_j / d ρ‖²`` (n,) for :func:`point_step`; −inf where ρ is unobservable (its step is then 0)."""
    c = J[:, 7]
    den = (c * c).sum(axis=0)
    den[den <= 1e-24 * max(float(den.max(initial=0.0)), 1e-300)] = np.inf
    return np.negative(den, out=den)


def point_step(s: np.ndarray, nv: np.ndarray, J: np.ndarray, Ki: np.ndarray, nden: np.ndarray | None = None) -> np.ndarray:
    """Gauss–Newton point steps (3, n) minimizing ``‖s_k + Jp_k δp_k‖`` for each point.

    The optimal residual is ``n nᵀ s``, so ``Jp δp = −(s − n nᵀ s)``: the image-i
    rows give (δa, δb) by back substitution, the image-j rows then give δρ.
    ``nden`` is :func:`rho_gain` of ``J`` if known.
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
    np.divide(q.sum(axis=0), rho_gain(J) if nden is None else nden, out=dp[2])
    return dp


def linearize(R, t, P, Kj, Ki, aux, cache=None):
    """Tangent basis (3, 2), Jacobian (2, 8, n), point null vectors (4, n) and reduced
    pose Jacobian (5, n) (:func:`reduced_jacobian`) and :func:`rho_gain` (n,) at a state.

    ``cache`` (a dict or None) remembers the last state's linearization, keyed by the
    identity of its ``aux`` tuple from :func:`project`: the inlier test, the next
    fit and the final ``H`` often linearize the very same state.
    """
    if cache is not None and cache.get("aux") is aux:
        return cache["B"], cache["J"], cache["nv"], cache["j"], cache["nden"]
    B = tangent_basis(t)
    J = jacobians(R, t, B, P, Kj, aux)
    nv = point_null_vectors(J, Ki)
    j = reduced_jacobian(J, nv)
    nden = rho_gain(J)
    if cache is not None:
        cache.update(aux=aux, B=B, J=J, nv=nv, j=j, nden=nden)
    return B, J, nv, j, nden

