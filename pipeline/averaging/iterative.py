"""Conjugate gradients for the averaging's normal equations, preconditioned by a factor or by the diagonal blocks.

:func:`cg_with_factor` runs preconditioned CG on ``A x = b`` with any preconditioner that has ``solve``: the
factor of an earlier IRLS matrix (:class:`~pipeline.averaging.kernel.LaplacianSolver`, the block solver of
IRLS-H), or :class:`JacobiPreconditioner`, the inverse of the matrix's own 1×1 or 3×3 diagonal blocks, which
:func:`solve_iteratively` uses on well-connected view graphs (the factor fills there, and the matrix is well
conditioned). Pure functions on arrays.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

__all__ = ["ITERATIVE_FILL", "JACOBI_MAX_CG", "JacobiPreconditioner", "solve_iteratively", "solve_without_factoring",
           "cg_with_factor"]

#: A first factor that fills more than this share of n² marks a well-connected (expander-like) view graph, whose
#: weighted Laplacians conjugate gradients with a (block-)diagonal preconditioner solve in tens of sparse products:
#: far cheaper than a new factor or a stale one's triangular solves (measured: 1920 random cameras with 12k edges,
#: fill 18%, 41–74 iterations at 12–22 ms against 76–89 ms for SuperLU's factor and solve). Such graphs are well
#: conditioned whatever their weights; where they are not, :data:`JACOBI_MAX_CG` ends the trial for the run.
ITERATIVE_FILL = 0.1
#: Iteration cap of the (block-)Jacobi conjugate gradients; past it, factors serve the rest of the run.
JACOBI_MAX_CG = 150


class JacobiPreconditioner:
    """The inverse of a symmetric matrix's diagonal blocks (1×1 or 3×3), as a preconditioner's ``solve``."""

    def __init__(self, A: sp.spmatrix, block: int = 1) -> None:
        self.block = int(block)
        #: The inverse of the diagonal for 1×1 blocks (:func:`cg_with_factor` then runs its own loop), else None.
        self.inverse_diagonal: np.ndarray | None = None
        if self.block == 1:
            self._inv = self.inverse_diagonal = 1.0 / A.diagonal()
            return
        C = A.tocoo()
        r, c, b = C.row, C.col, self.block
        on = r // b == c // b
        D = np.zeros((A.shape[0] // b, b, b))
        D[r[on] // b, r[on] % b, c[on] % b] = C.data[on]
        self._inv = np.linalg.inv(D)

    def solve(self, R: np.ndarray) -> np.ndarray:
        if self.block == 1:
            return R * self._inv.reshape((-1,) + (1,) * (R.ndim - 1))
        X = R.reshape(self._inv.shape[0], self.block, -1)
        return np.einsum("nij,njk->nik", self._inv, X).reshape(R.shape)


def solve_iteratively(factorizer: Any, A: sp.spmatrix, b: np.ndarray, rtol: float, block: int = 1,
                      min_n: int = 0) -> tuple[np.ndarray | None, int]:
    """Conjugate gradients with a (block-)Jacobi preconditioner, where the factorizer found the graph well
    connected (``factorizer.jacobi``); None when it is not, or when they did not converge within
    :data:`JACOBI_MAX_CG` iterations, which ends the trial for the factorizer's run (a
    :class:`~pipeline.averaging.kernel.SymmetricFactorizer`), or below ``min_n`` cameras, where a factor is cheaper.
    Returns the CG iterations spent.
    """
    if not factorizer.jacobi or A.shape[0] // block < min_n:
        return None, 0
    x, n_it = cg_with_factor(A, b, JacobiPreconditioner(A, block), rtol, JACOBI_MAX_CG)
    if x is None:
        factorizer.jacobi = False
    return x, n_it


def solve_without_factoring(factorizer: Any, A: sp.spmatrix, b: np.ndarray, lu: Any, same_gauge: bool, rtol: float,
                            max_cg: int, block: int = 1, min_n: int = 0) -> tuple[np.ndarray | None, int]:
    """The reuse path of both IRLS solvers: :func:`solve_iteratively` first, then CG preconditioned by the last
    factor ``lu`` where the gauge it was made for is unchanged (``same_gauge``). Returns the solution, or None when
    neither served and the caller must factor, and the CG iterations spent."""
    x, n_it = solve_iteratively(factorizer, A, b, rtol, block, min_n)
    if x is None and same_gauge:
        x, n_cg = cg_with_factor(A, b, lu, rtol, max_cg)
        n_it += n_cg
    return x, n_it


def cg_with_factor(A: sp.spmatrix, b: np.ndarray, lu: Any, rtol: float, max_cg: int
                   ) -> tuple[np.ndarray | None, int]:
    """Conjugate gradients on ``A x = b`` preconditioned by the factor ``lu`` of a nearby matrix.

    The columns of ``b`` are solved together (one sparse product and one triangular solve
    per iteration for all of them), each with its own step lengths.

    Args:
        A: (n, n) the current symmetric positive-definite matrix.
        b: (n,) or (n, k) right-hand side(s).
        lu: the preconditioner, anything with ``solve``: the factor of an earlier matrix (SuperLU or
            :class:`~pipeline.averaging.kernel.DenseCholesky`) or a :class:`JacobiPreconditioner`.
        rtol: relative residual tolerance, per column.
        max_cg: iteration cap.

    Returns:
        The solution with ``b``'s shape, or None when a column did not converge; the CG
        iterations spent.
    """
    B = np.asarray(b, dtype=np.float64).reshape(b.shape[0], -1)
    inv = getattr(lu, "inverse_diagonal", None)  # a 1×1 Jacobi preconditioner's: its own loop
    if inv is not None:
        X, n_it = _cg_diagonal(A, B, inv, rtol, max_cg)
        return (None if X is None else X.reshape(b.shape)), n_it
    X = np.zeros_like(B)
    Rr = B.copy()
    tol = rtol * np.linalg.norm(B, axis=0)
    if np.all(np.linalg.norm(Rr, axis=0) <= tol):
        return X.reshape(b.shape), 0
    Z = lu.solve(np.asfortranarray(Rr)).reshape(B.shape)
    P = Z.copy()
    rz = np.einsum("ij,ij->j", Rr, Z)
    for it in range(1, max_cg + 1):
        AP = A @ P
        pap = np.einsum("ij,ij->j", P, AP)
        alpha = np.divide(rz, pap, out=np.zeros_like(rz), where=pap != 0)
        X += alpha * P
        Rr -= alpha * AP
        if np.all(np.linalg.norm(Rr, axis=0) <= tol):
            return (X.reshape(b.shape), it) if np.all(np.isfinite(X)) else (None, it)
        Z = lu.solve(np.asfortranarray(Rr)).reshape(B.shape)
        rz_new = np.einsum("ij,ij->j", Rr, Z)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz != 0)
        P = Z + beta * P
        rz = rz_new
    return None, max_cg


def _scale_columns(a: np.ndarray, c: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``a * c`` for (n, k) ``a`` and (k,) ``c``, column by column: the same products, twice as fast as the
    broadcast, whose inner loop runs over the k = 3 entries of a row."""
    for j in range(a.shape[1]):
        np.multiply(a[:, j], c[j], out=out[:, j])
    return out


def _column_norms(R: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(R, axis=0)`` of a row-major (n, k) ``R``, the same numbers: for k > 1 its sums run down the
    rows one at a time, as ``einsum``'s do (twice as fast); a single column is summed pairwise, by norm itself."""
    return np.linalg.norm(R, axis=0) if R.shape[1] == 1 else np.sqrt(np.einsum("ij,ij->j", R, R))


def _cg_diagonal(A: sp.spmatrix, B: np.ndarray, inv: np.ndarray, rtol: float, max_cg: int
                 ) -> tuple[np.ndarray | None, int]:
    """:func:`cg_with_factor`'s loop with the 1×1 Jacobi preconditioner ``inv`` (n,), the inverse of A's diagonal: the
    same iterates to the bit (tested), with a third less work besides the sparse product (no copies, no
    temporaries, the products by a step length column by column; measured on the IRLS systems of a 2000-camera
    graph). Its column sums are those of the generic loop (:func:`_column_norms`; ``einsum`` gives the same sums
    on row-major and mixed operands), so the step lengths and the stopping decisions are the same numbers."""
    X = np.zeros_like(B)
    Rr = B.copy()
    tmp = np.empty_like(B)
    tol = rtol * np.linalg.norm(B, axis=0)
    if np.all(_column_norms(Rr) <= tol):
        return X, 0
    scale = inv[:, None]
    positive = bool(np.all(inv > 0) and np.all(np.isfinite(inv)))
    d_min = 1.0 / float(np.max(inv)) if positive else 0.0  # 0: the norm at every iteration
    tol2 = tol * tol * (1.0 + 1e-9)
    Z = np.multiply(Rr, scale)
    P = Z.copy()
    rz = np.einsum("ij,ij->j", Rr, Z)
    for it in range(1, max_cg + 1):
        AP = A @ P
        pap = np.einsum("ij,ij->j", P, AP)
        alpha = np.divide(rz, pap, out=np.zeros_like(rz), where=pap != 0)
        X += _scale_columns(P, alpha, tmp)
        Rr -= _scale_columns(AP, alpha, AP)
        np.multiply(Rr, scale, out=Z)
        rz_new = np.einsum("ij,ij->j", Rr, Z)
        # ‖r‖² ≥ rᵀD⁻¹r · min D: beyond the tolerance by a margin far above the sums' rounding (n·ε), a column is
        # not converged whatever the norm's last bits, and the norm is not taken (4 of 5 iterations on IRLS systems)
        if not np.any(rz_new * d_min > tol2):
            if np.all(_column_norms(Rr) <= tol):
                return (X, it) if np.all(np.isfinite(X)) else (None, it)
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz != 0)
        P = np.add(Z, _scale_columns(P, beta, P), out=P)
        rz = rz_new
    return None, max_cg
