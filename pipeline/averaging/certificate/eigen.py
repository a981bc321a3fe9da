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
import scipy.linalg.lapack as lapack
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from pipeline.averaging.kernel import DENSE_PATTERN, DenseCholesky, factor_symmetric

__all__ = ["EigenResult", "DenseLDL", "ldl_inertia", "dense_inertia", "min_eigenvalue", "DENSE_MAX",
           "DENSE_INERTIA_MAX"]

#: Largest S (3N) whose witness eigenpair is found by a dense eigendecomposition instead of Lanczos.
DENSE_MAX = 600
#: Largest S (3N) of a dense view graph factored densely (8000²·8 bytes = 512 MB a copy): 1DSfM's
#: Piccadilly (2508 cameras, 7524 rows) still is.
DENSE_INERTIA_MAX = 8000


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


class DenseLDL:
    """LAPACK's Bunch–Kaufman ``A = P L D Lᵀ Pᵀ`` of a dense symmetric matrix (``sytrf``), its inertia and solves.

    D is block-diagonal (1×1 and 2×2 blocks); by Sylvester's law of inertia A has as many negative eigenvalues as
    D. A 2×2 block ``[[a, b], [b, c]]`` has one of each sign when ``ac − b² < 0``, else two of the sign of ``a``.

    Attributes:
        ok: the factorization succeeded, finite, and A is not exactly singular; n_negative: negative eigenvalues
            of A (−1 when not ``ok``).
    """

    def __init__(self, A: np.ndarray) -> None:
        self._ldu, self._ipiv, info = lapack.dsytrf(np.array(A, dtype=np.float64, order="F"), lower=1,
                                                    overwrite_a=1)
        # info > 0: an exactly zero pivot (singular: no solves); < 0: a bad argument; non-finite: overflow
        self.ok = info == 0 and bool(np.isfinite(self._ldu).all())
        self.n_negative = self._count() if self.ok else -1

    def _count(self) -> int:
        ldu, ipiv = self._ldu, np.asarray(self._ipiv)
        k = np.arange(ipiv.size)
        two = ipiv < 0  # rows of 2×2 blocks (LAPACK, lower: both rows carry the same negative pivot)
        # a run of such rows is a sequence of 2×2 blocks: each starts at an even offset from its run's first row
        run_start = np.maximum.accumulate(np.where(two & ~np.r_[False, two[:-1]], k, 0))
        first = np.flatnonzero(two & ((k - run_start) % 2 == 0))
        d = np.diagonal(ldu)
        a, b, c = d[first], ldu[first + 1, first], d[first + 1]
        return int(np.sum(d[~two] < 0) + np.sum(np.where(a * c - b * b < 0, 1, 2 * (a < 0))))

    def solve(self, b: np.ndarray) -> np.ndarray:
        x, info = lapack.dsytrs(self._ldu, self._ipiv, np.asarray(b, dtype=np.float64), lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"LAPACK dsytrs failed (info {info})")
        return x


def dense_inertia(A: np.ndarray) -> int:
    """Number of negative eigenvalues of the symmetric ``A`` (:class:`DenseLDL`); −1 when the factorization fails
    or A is exactly singular."""
    return DenseLDL(A).n_negative


def ldl_inertia(A: sp.csc_matrix) -> tuple[sla.SuperLU | DenseCholesky | DenseLDL | None, int, str]:
    """LDLᵀ-equivalent SuperLU factor (symmetric mode, no off-diagonal pivoting).

    A matrix with more nonzeros than :data:`~pipeline.averaging.kernel.DENSE_PATTERN` of its n² (a dense view
    graph's), up to :data:`DENSE_INERTIA_MAX` rows, is first tried by a dense Cholesky: where it succeeds the
    matrix is positive-definite, no pivot is negative, and that factor serves (ten times faster on a 247-camera
    graph of 20,000 edges); where it fails (an eigenvalue below 0, or one at the rounding level), a pivoted
    dense LDLᵀ (:class:`DenseLDL`) counts the negative eigenvalues and serves as the factor (SuperLU took
    7.5 s on a 2000-camera graph with 200k edges where the dense LDLᵀ takes 0.6 s).

    Returns the factor, the number of negative pivots and an error message ("" if fine).
    """
    n = A.shape[0]
    if n <= DENSE_INERTIA_MAX and A.nnz > DENSE_PATTERN * n * n:
        try:
            return DenseCholesky(A), 0, ""
        except np.linalg.LinAlgError:  # not positive-definite to rounding: a pivoted dense LDLᵀ decides
            ldl = DenseLDL(A.toarray())
            if ldl.ok:
                return ldl, ldl.n_negative, ""
    try:
        lu = factor_symmetric(A)
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
