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

from pipeline.averaging.kernel import DENSE_PATTERN, DenseCholesky, blas_threads, factor_symmetric

__all__ = ["EigenResult", "DenseLDL", "ldl_inertia", "dense_inertia", "min_eigenvalue", "DENSE_MAX",
           "DENSE_INERTIA_BYTES", "dense_inertia_fits"]

#: Largest S (3N) whose witness eigenpair is found by a dense eigendecomposition instead of Lanczos.
DENSE_MAX = 600
#: Most memory the dense inertia test of a dense view graph's S may take (two n×n float64 copies at most: the
#: failed Cholesky's and the LDLᵀ's): 8 GB, 22,000 rows. 1DSfM's largest graph (Trafalgar: 5433 cameras, 680k
#: edges) has 16,299. Past it, or past half the memory the machine has free, SuperLU factors S, as for a sparse
#: graph. SuperLU gains nothing on such a matrix (its factor fills): 21.7 s on 9000 rows of 5% nonzeros, where
#: the dense Cholesky takes 4.5 s (measured, 2 cores).
DENSE_INERTIA_BYTES = 8 * 1024**3


def _free_bytes() -> float:
    """Memory available now: Linux's ``MemAvailable`` (free pages plus the page cache it can drop), else the free
    pages (``sysconf``), else infinity where the system says neither."""
    import os  # noqa: PLC0415

    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except (OSError, ValueError, IndexError):
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES")) * float(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return float("inf")


def dense_inertia_fits(n: int) -> bool:
    """Whether the dense inertia test of an n-row matrix fits :data:`DENSE_INERTIA_BYTES` and half the free
    memory (two n×n float64 copies)."""
    need = 2.0 * 8.0 * float(n) ** 2
    return need <= DENSE_INERTIA_BYTES and need <= 0.5 * _free_bytes()


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
        witnesses: (3N, k) unit eigenvectors of the k ≤ ``n_witness`` smallest eigenvalues below −η, or None.
        residual: ‖S v − λ v‖ of the reported eigenpair.
        message: what failed, if anything.
        times: seconds per step.
    """

    ok: bool
    n_below: int
    lambda_min: float
    lambda_nontrivial: float
    witnesses: np.ndarray | None
    residual: float
    message: str = ""
    times: dict[str, float] = field(default_factory=dict)

    @property
    def witness(self) -> np.ndarray | None:
        """(3N,) unit eigenvector of ``lambda_min`` when n_below > 0 (the first of ``witnesses``), else None."""
        return None if self.witnesses is None else self.witnesses[:, 0]


class DenseLDL:
    """LAPACK's Bunch–Kaufman ``A = P L D Lᵀ Pᵀ`` of a dense symmetric matrix (``sytrf``), its inertia and solves.

    D is block-diagonal (1×1 and 2×2 blocks); by Sylvester's law of inertia A has as many negative eigenvalues as
    D. A 2×2 block ``[[a, b], [b, c]]`` has one of each sign when ``ac − b² < 0``, else two of the sign of ``a``.

    Attributes:
        ok: the factorization succeeded, finite, and A is not exactly singular; n_negative: negative eigenvalues
            of A (−1 when not ``ok``).
    """

    def __init__(self, A: np.ndarray, overwrite: bool = False) -> None:
        # overwrite: an n×n float64 Fortran array of the caller's is factored in place (no second n×n copy) and lost
        a = np.asarray(A, dtype=np.float64, order="F") if overwrite else np.array(A, dtype=np.float64, order="F")
        with blas_threads(a.shape[0]):  # threaded OpenBLAS crashes on the largest (kernel.BLAS_THREADS_MAX_SIZE)
            self._ldu, self._ipiv, info = lapack.dsytrf(a, lower=1, overwrite_a=1)
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
        with blas_threads(self._ldu.shape[0]):
            x, info = lapack.dsytrs(self._ldu, self._ipiv, np.asarray(b, dtype=np.float64), lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"LAPACK dsytrs failed (info {info})")
        return x


def dense_inertia(A: np.ndarray) -> int:
    """Number of negative eigenvalues of the symmetric ``A`` (:class:`DenseLDL`); −1 when the factorization fails
    or A is exactly singular."""
    return DenseLDL(A).n_negative


def ldl_inertia(A: sp.csc_matrix, fills: bool | None = None
                ) -> tuple[sla.SuperLU | DenseCholesky | DenseLDL | None, int, str]:
    """LDLᵀ-equivalent SuperLU factor (symmetric mode, no off-diagonal pivoting).

    A matrix whose sparse factor would fill, where its dense copies fit in memory (:func:`dense_inertia_fits`), is
    factored densely. It fills where ``fills`` says so (the averaging's own factor of the same graph filled:
    :attr:`~pipeline.averaging.kernel.SymmetricFactorizer.fills`; a Trafalgar-size graph, 5400 cameras and 680k
    edges, has 4.7% of its entries nonzero, and SuperLU took 165 s on its 16,197 rows where the dense factor takes
    35 s, on the one BLAS thread :func:`~pipeline.averaging.kernel.blas_threads` gives a matrix that size) or, with
    no such word, where more than :data:`~pipeline.averaging.kernel.DENSE_PATTERN` of its n² entries are nonzero (a
    dense view graph's). Such a matrix is first tried by a dense Cholesky: where it succeeds the matrix is
    positive-definite, no pivot is negative, and that factor serves (ten times faster on a 247-camera graph of
    20,000 edges); where it fails (an eigenvalue below 0, or one at the rounding level), a pivoted dense LDLᵀ
    (:class:`DenseLDL`) counts the negative eigenvalues and serves as the factor (SuperLU took 7.5 s on a
    2000-camera graph with 200k edges where the dense LDLᵀ takes 0.6 s).

    Returns the factor, the number of negative pivots and an error message ("" if fine).
    """
    n = A.shape[0]
    if (A.nnz > DENSE_PATTERN * n * n if fills is None else fills) and dense_inertia_fits(n):
        try:
            return DenseCholesky(A), 0, ""
        except np.linalg.LinAlgError:  # not positive-definite to rounding: a pivoted dense LDLᵀ decides
            pass  # (outside the handler: its traceback would hold the failed n×n copy while the LDLᵀ makes its own)
        ldl = DenseLDL(A.toarray(order="F"), overwrite=True)
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
                   lanczos_tol: float = 1e-8, maxiter: int = 3000, fills: bool | None = None,
                   n_witness: int = 1) -> EigenResult:
    """Decide ``S ⪰ −ηI`` and report the numbers behind it (module docstring).

    Args:
        S: (3N, 3N) symmetric certificate matrix.
        Y: (3N, 3) stacked rotations (S Y ≈ 0).
        eta: tolerance η > 0.
        k_margin: non-trivial eigenvalues to compute near 0 when S ⪰ −ηI (0 skips).
        lanczos_tol: relative tolerance of eigsh.
        maxiter: Lanczos iteration cap.
        fills: whether S's sparse factor fills, when the caller knows (:func:`ldl_inertia`).
        n_witness: eigenvectors below −η to return (``witnesses``) when there are negative ones.
    """
    times: dict[str, float] = {}
    n3 = S.shape[0]
    t0 = time.perf_counter()
    A = (S + eta * sp.identity(n3, format="csc")).tocsc()
    lu, n_neg, msg = ldl_inertia(A, fills)
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
            lam, V = sla.eigsh(S, k=max(1, min(n_witness, n_neg)), which="SA", tol=lanczos_tol, maxiter=maxiter,
                               v0=rng.standard_normal(n3))
            order = np.argsort(lam)
            lam, V = lam[order], V[:, order]
        k = max(1, min(n_witness, n_neg, int(np.sum(lam < -eta))))
        W = V[:, :k] / np.linalg.norm(V[:, :k], axis=0)
        v = W[:, 0]
        rq = float(v @ (S @ v))
        res = float(np.linalg.norm(S @ v - rq * v))
        ok = rq < -eta
        message = "" if ok else f"Lanczos found no eigenvalue below −η (Rayleigh quotient {rq:.3g})"
    except sla.ArpackNoConvergence as exc:
        W, rq, res, ok, message = None, np.nan, np.nan, False, f"Lanczos did not converge ({exc})"
    times["lanczos_s"] = time.perf_counter() - t1
    return EigenResult(ok, n_neg, rq, np.nan, W, res, message, times)
