"""Deciding ``S ⪰ −ηI`` for an isotropic cost without factoring S: a perturbation bound from the consistent problem.

For the isotropic cost (1) of :mod:`~pipeline.averaging.certificate` with weights ``w_e`` (``M_e = I``), write
``S = P + E`` where P is the connection Laplacian of the same weights with every measurement ``R̃_e`` replaced by
the relative rotation of the point itself, ``Q_e = R_j R_iᵀ``:

- ``P = B (L_w ⊗ I₃) Bᵀ`` with ``B = blkdiag(R_i)`` orthogonal and ``L_w`` the scalar weighted Laplacian: P ⪰ 0,
  and its null space is ``span(Y)`` on a connected weighted graph;
- ``E = S − P`` has the off-diagonal blocks ``−w_e (R̃_e − Q_e)`` (and their transposes) and the diagonal blocks
  ``−Λ_i``: as small as the weighted residuals.

The weights of a robust solution differ by decades from camera to camera, so everything is scaled by the
weighted degrees ``d_i = Σ_{e∋i} w_e`` (``D = blkdiag(d_i I₃)``); ``T = D^{-1/2}(S + ηI)D^{-1/2}`` has the inertia
of ``S + ηI`` (Sylvester). Then ``D^{-1/2}PD^{-1/2} = B (L̃ ⊗ I₃) Bᵀ`` with ``L̃ = I − D^{-1/2}WD^{-1/2}`` the
normalized Laplacian, whose null space is ``U = span(D^{1/2}Y)`` (orthogonal columns of norm ``√Σd``), and the
block Gershgorin bound gives ``‖D^{-1/2}ED^{-1/2}‖₂ ≤ ε = max_i (‖Λ_i‖/d_i + Σ_{e∋i} w_e ‖R̃_e − Q_e‖/√(d_i d_j))``
(Frobenius norms, which bound the spectral ones). For a unit ``x = a û + b ẑ`` (``û ∈ U``, ``ẑ ⊥ U``, unit):

- ``ûᵀTû = (cᵀYᵀSYc + ηN)/Σd ≥ α = (ηN − ‖sym(YᵀSY)‖)/Σd`` (``YᵀSY`` is skew, so that norm is rounding);
- ``|ẑᵀTû| ≤ ‖Tû‖ ≤ γ = (‖D^{-1/2}SY‖_F + η‖D^{-1/2}Y‖)/√Σd``, with ``‖D^{-1/2}Y‖ = (Σ 1/d_i)^{1/2}``;
- ``ẑᵀTẑ ≥ λ₂(L̃) − ε``.

So ``T ≻ 0``, i.e. ``λ_min(S) > −η``, once ``α > 0`` and ``λ₂(L̃) > μ₀ = ε + γ²/α``. That is proven by one dense
Cholesky of the N×N matrix ``L̃ + vvᵀ − μ₀I`` (``v`` the unit null vector of L̃; L̃'s eigenvalues lie in [0, 2],
so μ₀ < 1 is needed): a third of the rows of S, about 1/27 of the flops of S's dense factor. The graphs where S's
factor is dense (a 1DSfM graph, an unordered collection's random pairs) are the well-connected ones, whose
normalized λ₂ is a large share of 1, far above ε: there the bound decides. Where it does not (a Cholesky that fails,
α ≤ 0, μ₀ ≥ 1, or an η below S's rounding level) the exact inertia of S decides as before
(:func:`~pipeline.averaging.certificate.eigen.min_eigenvalue`).
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.averaging.certificate.eigen import EigenResult, dense_inertia_fits
from pipeline.averaging.certificate.problem import rounding_floor
from pipeline.averaging.kernel import DenseCholesky
from pipeline.core import so3

__all__ = ["perturbation_bound"]

#: Safety factor on the computed bounds (their own rounding).
SAFETY = 1.0 + 1e-6
#: The dense Cholesky's accuracy on the normalized Laplacian (entries of size ≤ 1): added to the μ₀ it must prove.
FLOOR = 1e-10


def _normalized_laplacian(n: int, edges: np.ndarray, w: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``I − D^{-1/2} W D^{-1/2}`` of the weighted graph as a dense (N, N) Fortran-ordered array."""
    A = np.zeros((n, n), order="F")
    i, j = edges[:, 0], edges[:, 1]
    flat = A.reshape(-1, order="F")  # a view: A is Fortran-ordered
    off = -w / np.sqrt(d[i] * d[j])
    np.add.at(flat, i + n * j, off)
    np.add.at(flat, j + n * i, off)
    flat[np.arange(n) * (n + 1)] += 1.0
    return A


def perturbation_bound(n: int, edges: np.ndarray, w: np.ndarray, R_rel: np.ndarray, R: np.ndarray,
                       Lam: np.ndarray, G: np.ndarray, S: object, eta: float) -> EigenResult | None:
    """Prove ``S ⪰ −ηI`` for the isotropic cost (module docstring), or return None where the bound cannot.

    Args:
        n: number of cameras N.
        edges: (K, 2) the edges with weight.
        w: (K,) their weights (> 0).
        R_rel: (K, 3, 3) their measurements.
        R: (N, 3, 3) the rotations certified (Y stacks them).
        Lam: (N, 3, 3) the Lagrange multipliers Λ_i.
        G: (N, 3, 3) the blocks of S Y.
        S: the (3N, 3N) sparse certificate matrix ``L − blkdiag(Λ)``.
        eta: the tolerance η.

    Returns:
        An :class:`EigenResult` with ``n_below = 0`` where the bound proves ``S ⪰ −ηI`` (its ``times`` hold
        ``bound_s``), else None (also for an η below S's rounding level, ``1e3·ε·‖S‖₁``, which nothing proves, and
        where two N×N copies would not fit in memory: :func:`~.eigen.dense_inertia_fits`).
    """
    t0 = time.perf_counter()
    if not eta >= rounding_floor(S):  # below S's rounding level nothing is decided
        return None
    if not dense_inertia_fits(n):  # its two N×N copies (the matrix and its factor) must fit, as S's would
        return None
    edges = np.asarray(edges, dtype=np.int64)
    w = np.asarray(w, dtype=np.float64)
    i, j = edges[:, 0], edges[:, 1]
    d = np.bincount(i, w, n) + np.bincount(j, w, n)
    if not np.all(d > 0):
        return None
    Y = R.reshape(3 * n, 3)
    YSY = Y.T @ np.asarray(S @ Y)
    alpha = (eta * n - float(np.linalg.norm(0.5 * (YSY + YSY.T), 2))) / d.sum()
    gamma = (np.sqrt(np.sum(np.square(G).reshape(n, 9).sum(axis=1) / d)) + eta * np.sqrt(np.sum(1.0 / d))) / np.sqrt(
        d.sum())
    if not (np.isfinite(alpha) and np.isfinite(gamma)) or alpha <= 0:
        return None
    Q = so3.relative(R, edges)
    dev = w * np.linalg.norm((R_rel - Q).reshape(-1, 9), axis=1) / np.sqrt(d[i] * d[j])
    rows = np.linalg.norm(Lam.reshape(n, 9), axis=1) / d + np.bincount(i, dev, n) + np.bincount(j, dev, n)
    mu0 = (float(rows.max()) + gamma**2 / alpha) * SAFETY + FLOOR
    if not mu0 < 1.0:
        return None
    A = _normalized_laplacian(n, edges, w, d)
    v = np.sqrt(d) / np.linalg.norm(np.sqrt(d))
    A += np.outer(v, v)  # lifts the null vector of the normalized Laplacian to 1 (its eigenvalues lie in [0, 2])
    A[np.diag_indices(n)] -= mu0
    try:
        DenseCholesky(A)
    except np.linalg.LinAlgError:
        return None
    return EigenResult(True, 0, np.nan, np.nan, None, np.nan, "", {"bound_s": time.perf_counter() - t0})
