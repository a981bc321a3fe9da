"""Deciding ``S ⪰ −ηI`` for the certificate matrix: LDLᵀ inertia, the margin, a negative witness.

One sparse LDLᵀ of ``S + ηI`` (SuperLU, symmetric mode, diagonal pivots only, symmetric
permutation checked): by Sylvester's law of inertia the number of negative pivots is the
number of eigenvalues of S below −η. The same factor drives a shift-invert Lanczos on
the complement of ``span(Y)`` for the first non-trivial eigenvalue (the margin); with
negative pivots, Lanczos on S (smallest algebraic) returns an explicit negative eigenpair.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from pipeline.averaging.kernel import DENSE_FILL, DENSE_MAX_SIZE, DenseCholesky

__all__ = ["EigenResult", "ldl_inertia", "min_eigenvalue", "DENSE_MAX"]

#: Largest S (3N) whose witness eigenpair is found by a dense eigendecomposition instead of Lanczos.
DENSE_MAX = 600


@dataclass
class EigenResult:
    """Outcome of the test ``S ⪰ −η I``.

    Attributes:
        ok: the computation succeeded (factor symmetric, finite, Lanczos converged when needed).
        n_below: number of eigenvalues of S below −η (inertia of the LDLᵀ of S + ηI).
        lambda_min: smallest eigenvalue found (on span(Y)⊥ when n_below = 0; the witness
            Rayleigh quotient otherwise), NaN if not computed.
        lambda_nontrivial: first eigenvalue of S on span(Y)⊥ near 0 (the margin), NaN if
            not computed.
        witness: (3N,) unit eigenvector of ``lambda_min`` when n_below > 0, else None.
        residual: ‖S v − λ v‖ of the reported eigenpair.
        message: what failed, if anything.
        times: seconds per step.
    """

    ok: bool
    n_below: int
    lambda_min: float
    lambda_nontrivial: float
    witness: np.ndarray | None
    residual: float
    message: str = ""
    times: dict[str, float] = field(default_factory=dict)


def ldl_inertia(A: sp.csc_matrix) -> tuple[sla.SuperLU | DenseCholesky | None, int, str]:
    """LDLᵀ-equivalent SuperLU factor (symmetric mode, no off-diagonal pivoting).

    A matrix with more nonzeros than :data:`~pipeline.averaging.kernel.DENSE_FILL` of its n² (a dense view
    graph's) is first tried by a dense Cholesky: where it succeeds the matrix is positive-definite, no pivot is
    negative, and that factor serves (ten times faster on a 247-camera graph of 20,000 edges); where it fails,
    SuperLU counts the negative pivots.

    Returns the factor, the number of negative pivots and an error message ("" if fine).
    """
    n = A.shape[0]
    if n <= DENSE_MAX_SIZE and A.nnz > DENSE_FILL * n * n:
        try:
            return DenseCholesky(A), 0, ""
        except np.linalg.LinAlgError:  # not positive-definite: SuperLU's pivots say how far from it
            pass
    try:
        lu = sla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options=dict(SymmetricMode=True))
    except RuntimeError as exc:  # exactly singular
        return None, -1, f"factorization failed ({exc})"
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return lu, -1, "SuperLU pivoted off the diagonal; inertia not available"
    d = lu.U.diagonal()
    if not np.all(np.isfinite(d)):
        return lu, -1, "non-finite pivots"
    return lu, int(np.sum(d < 0)), ""


def min_eigenvalue(S: sp.csc_matrix, Y: np.ndarray, eta: float, k_margin: int = 1,
                   lanczos_tol: float = 1e-8, maxiter: int = 3000) -> EigenResult:
    """Decide ``S ⪰ −ηI`` and report the numbers behind it (module docstring).

    Args:
        S: (3N, 3N) symmetric certificate matrix.
        Y: (3N, 3) stacked rotations (S Y ≈ 0).
        eta: tolerance η > 0.
        k_margin: non-trivial eigenvalues to compute near 0 when S ⪰ −ηI (0 skips).
        lanczos_tol: relative tolerance of eigsh.
        maxiter: Lanczos iteration cap.
    """
    times: dict[str, float] = {}
    n3 = S.shape[0]
    t0 = time.perf_counter()
    A = (S + eta * sp.identity(n3, format="csc")).tocsc()
    lu, n_neg, msg = ldl_inertia(A)
    times["factor_s"] = time.perf_counter() - t0
    if msg:
        return EigenResult(False, -1, np.nan, np.nan, None, np.nan, msg, times)
    Qy, _ = np.linalg.qr(Y)  # orthonormal basis of span(Y)
    t1 = time.perf_counter()
    if n_neg == 0:
        lam_nt, res = np.nan, np.nan
        if k_margin > 0 and n3 > 3 + k_margin + 1:
            def proj(v: np.ndarray) -> np.ndarray:
                return v - Qy @ (Qy.T @ v)

            op = sla.LinearOperator((n3, n3), matvec=lambda v: proj(lu.solve(proj(np.asarray(v, float).ravel()))),
                                    dtype=np.float64)
            rng = np.random.default_rng(0)
            try:
                mu, V = sla.eigsh(op, k=k_margin, which="LA", tol=lanczos_tol, maxiter=maxiter,
                                  v0=proj(rng.standard_normal(n3)))
                lam = 1.0 / mu - eta
                kk = int(np.argmin(lam))
                v = V[:, kk]
                lam_nt = float(v @ (S @ v))  # Rayleigh quotient, exact up to rounding
                res = float(np.linalg.norm(S @ v - lam_nt * v))
            except sla.ArpackNoConvergence:
                pass  # the inertia already decided; the margin is informative only
        times["lanczos_s"] = time.perf_counter() - t1
        return EigenResult(True, 0, lam_nt, lam_nt, None, res, "", times)
    # Negative pivots: find an explicit negative eigenpair (the witness).
    try:
        if n3 <= DENSE_MAX:  # Lanczos on a tiny, badly scaled matrix can take seconds; eigh is exact
            lam, V = np.linalg.eigh(S.toarray())
        else:
            rng = np.random.default_rng(1)
            lam, V = sla.eigsh(S, k=1, which="SA", tol=lanczos_tol, maxiter=maxiter,
                               v0=rng.standard_normal(n3))
        v = V[:, 0] / np.linalg.norm(V[:, 0])
        rq = float(v @ (S @ v))
        res = float(np.linalg.norm(S @ v - rq * v))
        ok = rq < -eta
        message = "" if ok else f"Lanczos found no eigenvalue below −η (Rayleigh quotient {rq:.3g})"
    except sla.ArpackNoConvergence as exc:
        v, rq, res, ok, message = None, np.nan, np.nan, False, f"Lanczos did not converge ({exc})"
    times["lanczos_s"] = time.perf_counter() - t1
    return EigenResult(ok, n_neg, rq, np.nan, v, res, message, times)
