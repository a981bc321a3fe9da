"""Shared Lie-algebra kernel of the iterative methods: residuals, update, Laplacian solver, graph checks.

Residual convention (``../shared/DESIGN.md``): for edge ``(i, j)`` carrying
``R_ij ≈ R_j R_iᵀ``,

    ΔR_ij = R_jᵀ R_ij R_i,    r_ij = log(ΔR_ij)            (paper 1, eq. 7)

and every camera is updated on the right, ``R_i ← R_i exp([Δω_i]×)``. After the
update ``ΔR_ij ← exp(−[Δω_j]×) ΔR_ij exp([Δω_i]×)``, whose log is, to first order
(paper 1, eqs. 19 and 34), ``r_ij + Δω_i − Δω_j``. With the incidence matrix
``A`` of :meth:`ViewGraph.incidence` (−1 at ``i``, +1 at ``j``) the stacked
linearized residual is therefore ``r − A ΔΩ``: paper 1's ``A ΔΩ_V + ΔΩ_E`` with its
``A`` (+I at ``i``, −I at ``j``) equal to minus ours.

The residuals themselves are computed in :mod:`~pipeline.averaging.residuals` (re-exported here).

Used by :mod:`~pipeline.averaging.l1`, :mod:`~pipeline.averaging.irls`,
:mod:`~pipeline.averaging.irls_h` and :mod:`~pipeline.averaging.weiszfeld`. Pure
functions and classes on arrays: no I/O, no logging.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from typing import Any

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from pipeline.averaging.iterative import ITERATIVE_FILL, JacobiPreconditioner, cg_with_factor, solve_without_factoring
from pipeline.averaging.residuals import edge_residuals, graph_residuals
from pipeline.core import so3
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

#: Fewest cameras for which reusing a factor as a CG preconditioner beats refactoring (measured:
#: castle-P30, N = 30, CG made the polish 2× slower; kNN N = 2000, 30% faster).
REUSE_MIN_N = 300
#: An edge weight below this fraction of the largest is lost to rounding in the factor: the pivot
#: of a camera held by such an edge is a difference of numbers 1e16 times larger, an exact zero
#: ("Factor is exactly singular"; seen on a triangle with pendant edges, whose ℓ1 start leaves
#: most residuals at zero and the robust scale with them). Such an edge counts as weight 0.
NEGLIGIBLE_WEIGHT = 1e-12
#: A sparse factor with more nonzeros than this share of the matrix's n² is a dense one in effect, and a dense
#: Cholesky is then several times faster (measured, one core: a 247-camera graph with 20k edges, as 1DSfM's Ellis
#: Island, fills SuperLU's factor to 95%: 10.6 ms against 1.4 ms; 2000 random cameras at 0.7% density fill it to
#: 38%: 260 ms against 90 ms; a kNN graph of 2000 cameras fills it to 2.7%, where SuperLU is 35× faster).
DENSE_FILL = 0.2
#: A matrix with more nonzeros than this share of its n² is factored densely from the first factor on: such a
#: view graph's factor fills (1DSfM-like graphs: 10–65% of the matrix nonzero), and SuperLU's first factor of it
#: costs more than all the dense ones of the run (measured: 2000 cameras, 200k edges, 10% of the Laplacian
#: nonzero: 6.2 s against 0.43 s for a dense Cholesky). kNN graphs (0.6% at 2000 cameras) stay with SuperLU.
DENSE_PATTERN = 0.05
#: Largest matrix (rows) factored densely (6000²·8 bytes = 288 MB).
DENSE_MAX_SIZE = 6000
#: Below this many rows the dense factor runs with one BLAS thread: OpenBLAS's threads gain nothing on a small
#: matrix and then spin, taking the core from the rest of the iteration (measured, 2 cores, the 247-camera graph
#: above: the whole IRLS run 0.89 s with threaded BLAS against 0.44 s with one thread). On an idle machine two
#: threads factor faster from about 1500 rows on, but on a shared one a thread that waits for a core another job
#: holds makes the factor 10–20 times slower (measured, 2 cores, one busy: 2000 rows 0.06–0.13 s with one thread,
#: 0.2–2.8 s with two; 4000 rows 0.44–0.67 s against 5.8–6.0 s). Every dense factor of the averaging itself
#: (:data:`DENSE_MAX_SIZE`) and the certificate bound's N×N Cholesky up to this size take one thread; the
#: certificate's larger 3N-row factors keep the threads (a Piccadilly-size graph's: 7500 rows).
DENSE_SINGLE_THREAD_SIZE = 6500
#: Above this many rows a dense factor runs with one BLAS thread too: OpenBLAS's threaded Cholesky (its ``dsyrk``
#: threads) dies with a segmentation fault on this machine from about 16,000 rows (scipy's and numpy's builds alike:
#: 16,000 and 16,300 rows crash, 15,500 and below do not), where one thread factors 16,300 rows in 28–32 s. The
#: certificate of a Trafalgar-size graph (16,197 rows) is such a factor.
BLAS_THREADS_MAX_SIZE = 12000
#: From this many rows, a first matrix whose pattern is not dense is probed before its first factor: where
#: conjugate gradients with its diagonal as the preconditioner solve it to :data:`FILL_PROBE_RTOL` within
#: :data:`FILL_PROBE_STEPS` steps, its condition number is below ~50, which for a graph Laplacian means an
#: expander (random pairs, an unordered collection's 1DSfM graph), whose factor fills whatever the ordering: the
#: factorizer goes dense from the first factor instead of learning it from SuperLU's (measured: 5400 cameras and
#: 680k edges, 4.7% nonzero, SuperLU's first factor 10.7 s and its ℓ1 solves 81 ms each, against 1.4 s and ~5 ms
#: dense). Streets, rings, grids and kNN graphs of points in space are conditioned far worse (their κ grows with
#: N) and keep SuperLU. The probe costs 50 sparse products at most.
FILL_PROBE_MIN_N = 1000
FILL_PROBE_STEPS = 50
FILL_PROBE_RTOL = 1e-6

__all__ = ["REUSE_MIN_N", "NEGLIGIBLE_WEIGHT", "DENSE_FILL", "DENSE_PATTERN", "DENSE_MAX_SIZE", "FILL_PROBE_MIN_N",
           "FILL_PROBE_STEPS", "FILL_PROBE_RTOL", "DENSE_SINGLE_THREAD_SIZE", "BLAS_THREADS_MAX_SIZE", "blas_threads",
           "well_conditioned", "effective_weights", "edge_residuals", "graph_residuals", "apply_update",
           "LaplacianSolver", "check_graph", "factor_symmetric", "DenseCholesky", "SymmetricFactorizer", "FactorState"]

_BLAS_LIBS: list[Any] | None = None  # the BLAS libraries' threadpoolctl controllers, found at the first use
_BLAS_MODULES = -1  # len(sys.modules) when they were found: a module imported since may have brought another


@contextlib.contextmanager
def _one_blas_thread() -> Iterator[None]:
    """One BLAS thread within it, each library's own count restored after: the libraries' controllers set directly
    (under 1 µs) rather than through threadpoolctl's ``limit`` (15 µs a call, a fifth of a 247-row solve). They are
    looked up again after any import (OpenCV, for one, brings an OpenBLAS of its own when it is first imported)."""
    global _BLAS_LIBS, _BLAS_MODULES
    if _BLAS_LIBS is None or len(sys.modules) != _BLAS_MODULES:
        from threadpoolctl import ThreadpoolController  # noqa: PLC0415

        _BLAS_LIBS = list(ThreadpoolController().select(user_api="blas").lib_controllers)
        _BLAS_MODULES = len(sys.modules)
    libs = _BLAS_LIBS
    before = [lib.get_num_threads() for lib in libs]
    for lib in libs:
        lib.set_num_threads(1)
    try:
        yield
    finally:
        for lib, k in zip(libs, before):
            lib.set_num_threads(k)


def blas_threads(n: int) -> contextlib.AbstractContextManager[Any]:
    """The BLAS threads for a dense factor of n rows (its solves take one, :meth:`DenseCholesky.solve`): one below
    :data:`DENSE_SINGLE_THREAD_SIZE` (threads gain little there, and lose much on a shared machine) and above
    :data:`BLAS_THREADS_MAX_SIZE` (threads crash there), all of them between."""
    one = n < DENSE_SINGLE_THREAD_SIZE or n > BLAS_THREADS_MAX_SIZE
    return _one_blas_thread() if one else contextlib.nullcontext()


def apply_update(R: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """``R_i exp([Δω_i]×)`` for every camera (right update, paper 1 Alg. 1 step 6).

    Args:
        R: (N, 3, 3) rotations.
        dw: (N, 3) updates in radians.
    """
    return R @ so3.exp(dw)


def check_graph(vg: ViewGraph, connected: bool = True) -> None:
    """Reject graphs no averaging method can use (raises :class:`ViewGraphError`).

    Args:
        vg: the view graph.
        connected: also require one connected component (every solver needs it;
            :func:`pipeline.averaging.solve.average` checks without it, then solves
            the largest component).
    """
    if vg.n_cameras == 0:
        raise ViewGraphError("the view graph is empty (no cameras); nothing to average")
    if vg.n_edges == 0:
        raise ViewGraphError(
            f"the view graph has {vg.n_cameras} camera(s) but no edge; rotation averaging needs relative rotations"
        )
    if not np.all(np.isfinite(vg.R_rel)):
        raise ViewGraphError("R_rel contains NaN or inf; fix or drop those edges before averaging")
    if connected and not vg.is_connected():
        raise ViewGraphError(
            f"the view graph is not connected ({int(vg.components().max()) + 1} components); "
            "use pipeline.averaging.average(), which solves the largest component and reports the rest, "
            "or restrict it with vg.largest_component()"
        )


def effective_weights(w: np.ndarray) -> np.ndarray:
    """``w`` (M,) with the weights below :data:`NEGLIGIBLE_WEIGHT` of the largest set to 0 (others unchanged)."""
    w = np.asarray(w, dtype=np.float64)
    top = float(w.max()) if w.size else 0.0
    return np.where(w > NEGLIGIBLE_WEIGHT * top, w, 0.0)


def factor_symmetric(A: sp.spmatrix) -> sla.SuperLU:
    """SuperLU factor of a symmetric positive-definite matrix: symmetric mode, minimum degree on
    ``A + Aᵀ``, diagonal pivots only (an LDLᵀ in effect)."""
    return sla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                    options=dict(SymmetricMode=True))


class DenseCholesky:
    """Cholesky factor of a symmetric positive-definite matrix held dense, with SuperLU's ``solve``.

    Raises ``numpy.linalg.LinAlgError`` (from LAPACK) where the matrix is not positive-definite to rounding.
    """

    def __init__(self, A: sp.spmatrix | np.ndarray) -> None:
        # LAPACK works in place on a Fortran-ordered array: asked for one, the factor needs no copy (2.6× faster on
        # 2500 rows: 0.07 s against 0.19 s). The transpose of a C-ordered array is one, but CSC gives Fortran order
        # and its transpose is C-ordered: the certificate's 7500-row CSC matrix took 5.6 s against 1.6 s in place.
        dense = A.toarray(order="F") if sp.issparse(A) else np.array(A, dtype=np.float64, order="F")
        self.shape = dense.shape
        with blas_threads(dense.shape[0]):
            self._c = la.cho_factor(dense, lower=True, overwrite_a=True, check_finite=False)

    def solve(self, b: np.ndarray) -> np.ndarray:
        # One thread whatever the size: the two triangular solves read the factor once for a few right-hand sides
        # (memory-bound), and a woken thread waits for a core a shared machine's other jobs hold (2000 rows, two
        # cores, one busy: 23 ms a solve against 5 ms). The solution does not depend on the thread count (tested).
        with _one_blas_thread():
            return la.cho_solve(self._c, np.asarray(b, dtype=np.float64), check_finite=False)


def well_conditioned(A: sp.spmatrix) -> bool:
    """Whether diagonal-preconditioned conjugate gradients solve ``A x = b`` (a fixed random b) to
    :data:`FILL_PROBE_RTOL` within :data:`FILL_PROBE_STEPS` steps: a symmetric positive-definite ``A`` whose
    condition number (after the diagonal scaling) is below ~50."""
    b = np.random.default_rng(0).standard_normal(A.shape[0])
    x, _ = cg_with_factor(A, b, JacobiPreconditioner(A), FILL_PROBE_RTOL, FILL_PROBE_STEPS)
    return x is not None


class SymmetricFactorizer:
    """Factors a sequence of symmetric positive-definite matrices of one sparsity pattern (an IRLS run's).

    SuperLU (:func:`factor_symmetric`) while its factor stays sparse; once a factor has more nonzeros than
    :data:`DENSE_FILL` of the matrix (a dense view graph), a dense Cholesky from then on, up to
    :data:`DENSE_MAX_SIZE` rows; from the first factor on where the matrix itself has more than
    :data:`DENSE_PATTERN` of its entries nonzero. Both solve the same system to rounding. A matrix that the dense
    Cholesky finds not positive-definite (weights near the rounding floor) is factored by SuperLU.

    The first factor's fill also decides whether the run's systems are tried first by (block-)Jacobi conjugate
    gradients (``jacobi``, :func:`~pipeline.averaging.iterative.solve_iteratively`): a fill beyond
    :data:`~pipeline.averaging.iterative.ITERATIVE_FILL`, or a matrix dense from
    the start.

    ``fills`` says, once a matrix has been factored, whether the pattern's factor fills (a dense pattern, a first
    matrix of :data:`FILL_PROBE_MIN_N` rows or more that :func:`well_conditioned` finds an expander's, or a first
    sparse factor with more than :data:`DENSE_FILL` of n² nonzero), whatever the size: the certificate's matrix, of
    the same graph, is then factored densely too. A probed expander is factored densely from the first factor
    (up to :data:`DENSE_MAX_SIZE` rows) and its systems tried by Jacobi conjugate gradients, as a dense pattern's.

    Args:
        dense: True / False forces one factorization; None (default) decides from the first factor's fill.
    """

    def __init__(self, dense: bool | None = None) -> None:
        self.dense = dense
        self.jacobi: bool | None = None
        self.fills: bool | None = None

    def __call__(self, A: sp.spmatrix) -> sla.SuperLU | DenseCholesky:
        n = A.shape[0]
        # a dense pattern, or (first matrix only) an expander's, whose factor fills as a dense pattern's does
        dense_like = A.nnz > DENSE_PATTERN * n * n or (self.fills is None and n >= FILL_PROBE_MIN_N
                                                       and well_conditioned(A))
        if self.fills is None and dense_like:
            self.fills = True
        if self.dense is None and n <= DENSE_MAX_SIZE and dense_like:
            self.dense = True
        if self.dense:
            if self.jacobi is None:
                self.jacobi = dense_like
            try:
                return DenseCholesky(A)
            except np.linalg.LinAlgError:
                pass
        lu = factor_symmetric(A)
        fill = (lu.L.nnz + lu.U.nnz) / (n * n)
        if self.fills is None:
            self.fills = fill > DENSE_FILL
        if self.jacobi is None:
            self.jacobi = fill > ITERATIVE_FILL
        if self.dense is None and n <= DENSE_MAX_SIZE:
            self.dense = fill > DENSE_FILL
        return lu


class FactorState:
    """What the Laplacian solvers share: their factorizer, the last factor and the gauge it was made for, counters."""

    _lu: sla.SuperLU | DenseCholesky | None

    def _init_factor(self, n: int, dense: bool | None) -> None:
        self._lu = None
        self._factor = SymmetricFactorizer(dense)
        self.pinned = np.zeros(n, dtype=bool)
        self._lu_pinned = self.pinned
        self.n_factorizations = 0
        self.n_cg_iterations = 0

    @property
    def fills(self) -> bool | None:
        """Whether this graph's factor fills (:class:`SymmetricFactorizer`); None before the first factor."""
        return self._factor.fills


def _unique_keys(keys: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` of integer keys in [0, size): the same two arrays; where the range is
    small against the keys (a dense view graph's Laplacian pattern: 247 cameras, 80k keys), by a mask and its running
    count instead of a sort (1 ms against 9 ms)."""
    if size > 16 * keys.size:
        return np.unique(keys, return_inverse=True)
    present = np.zeros(size, dtype=bool)
    present[keys] = True
    rank = np.cumsum(present, dtype=np.intp)
    rank -= 1
    return np.flatnonzero(present), rank[keys]


class LaplacianSolver(FactorState):
    """Factor and solve gauge-fixed weighted Laplacians ``Aᵀ diag(w) A`` on a fixed pattern.

    The sparsity pattern and the map from edge weights to matrix entries are
    built once; each :meth:`factor` only scatters the weights (``np.bincount``)
    and calls SuperLU once, in symmetric mode with a minimum-degree ordering on
    ``A + Aᵀ`` and no pivoting (the pinned Laplacian is positive definite). The
    factor is shared by the three axes: :meth:`solve` takes an (N, 3) right-hand
    side.

    The gauge is fixed by pinning one camera per connected component of the
    graph of positive-weight edges (its row and column are replaced by the
    identity and its right-hand side by 0): with a single component this pins
    ``ref`` only; redescending losses (Talwar, bisquare, Andrews) can cut the
    weighted graph, and then each piece gets its own pinned camera, so the system
    stays nonsingular and a camera whose edges all have weight 0 does not move.

    Args:
        edges: (M, 2) camera indices.
        n: number of cameras N.
        ref: the camera pinned when the weighted graph is connected.
        dense: the factorization (:class:`SymmetricFactorizer`): None (default) sparse unless its factor fills.
    """

    def __init__(self, edges: np.ndarray, n: int, ref: int = 0, dense: bool | None = None) -> None:
        edges = np.asarray(edges, dtype=np.int64)
        self.edges = edges
        self.n = int(n)
        self.ref = int(ref)
        M = edges.shape[0]
        i, j = edges[:, 0], edges[:, 1]
        # The 4 contributions of edge k: (i,i) +w, (j,j) +w, (i,j) −w, (j,i) −w.
        rows = np.concatenate([i, j, i, j, np.arange(n)])
        cols = np.concatenate([i, j, j, i, np.arange(n)])
        keys = cols * n + rows  # CSC order: by column, then row
        ukeys, inv = _unique_keys(keys, n * n)
        self._pos = inv[: 4 * M]
        self._sign = np.repeat([1.0, 1.0, -1.0, -1.0], M)
        self._edge_of = np.tile(np.arange(M), 4)
        self._row = ukeys % n
        self._col = ukeys // n
        self._diag = inv[4 * M :]
        self._nnz = ukeys.size
        # Where no two edges join the same cameras (no parallel edge), each off-diagonal entry is one edge's −w
        # and each diagonal one the sum of its camera's weights, in the order of (i, j)'s concatenation: written so
        # (``_off``, ``_ends``) the entries are those of the full scatter below to the bit, in half its time.
        self._off = inv[2 * M : 4 * M] if M == 0 or np.bincount(inv[2 * M : 4 * M]).max() == 1 else None
        self._ends = np.concatenate([i, j])
        self._w2 = np.empty(2 * M)
        self._keep: tuple[bytes, np.ndarray] | None = None
        self._indptr = np.searchsorted(self._col, np.arange(n + 1)).astype(np.int32)
        self._indices = self._row.astype(np.int32)
        A = sp.csr_matrix((np.tile([-1.0, 1.0], M), (np.repeat(np.arange(M), 2), edges.ravel())), shape=(M, n))
        self.A = A
        self.AT = A.T.tocsr()
        self._init_factor(n, dense)

    def _pins(self, w: np.ndarray) -> np.ndarray:
        pinned = np.zeros(self.n, dtype=bool)
        pos = w > 0
        if np.all(pos):
            pinned[self.ref] = True
            return pinned
        from scipy.sparse.csgraph import connected_components

        e = self.edges[pos]
        G = sp.coo_matrix((np.ones(e.shape[0]), (e[:, 0], e[:, 1])), shape=(self.n, self.n))
        ncomp, labels = connected_components(G, directed=False)
        # Pin the reference camera in its own piece, the first camera elsewhere.
        first = np.full(ncomp, -1, dtype=np.int64)
        order = np.r_[self.ref, np.arange(self.n)]
        lab = labels[order]
        _, idx = np.unique(lab, return_index=True)
        first[lab[idx]] = order[idx]
        pinned[first] = True
        return pinned

    def matrix(self, w: np.ndarray) -> sp.csc_matrix:
        """The gauge-fixed (N, N) Laplacian ``Aᵀ diag(w) A`` for edge weights ``w`` (M,)."""
        w = effective_weights(w)
        self.pinned = self._pins(w)
        if self._off is None:
            data = np.bincount(self._pos, weights=self._sign * w[self._edge_of], minlength=self._nnz)
        else:
            M = w.size
            data = np.empty(self._nnz)
            # 0 − w: what the scatter's 0 + (−1 · w) is, a zero weight's entry +0 included
            np.subtract(0.0, w, out=self._w2[:M])
            self._w2[M:] = self._w2[:M]
            data[self._off] = self._w2
            self._w2[:M] = w
            self._w2[M:] = w
            data[self._diag] = np.bincount(self._ends, weights=self._w2, minlength=self.n)
        if self.pinned.any():
            key = self.pinned.tobytes()
            if self._keep is None or self._keep[0] != key:  # the gauge seldom changes between iterations
                self._keep = (key, ~(self.pinned[self._row] | self.pinned[self._col]))
            data *= self._keep[1]
            data[self._diag[self.pinned]] = 1.0
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))

    def factor(self, w: np.ndarray) -> None:
        """Factor the gauge-fixed Laplacian for edge weights ``w`` (M,)."""
        self._factorize(self.matrix(w))

    def _factorize(self, L: sp.csc_matrix) -> None:
        self._lu = self._factor(L)
        self._lu_pinned = self.pinned.copy()
        self.n_factorizations += 1

    def solve_reusing(self, w: np.ndarray, b: np.ndarray, rtol: float = 1e-8, max_cg: int = 12) -> np.ndarray:
        """Solve the system of weights ``w`` (M,) for ``b`` (N, 3), reusing the last factor when it serves.

        On a well-connected graph (:func:`~pipeline.averaging.iterative.solve_iteratively`) conjugate
        gradients with a diagonal preconditioner come first. Otherwise, IRLS weights change little between
        iterations, so conjugate gradients on the current matrix, preconditioned by the previous SuperLU
        factor, converge in a few steps; when they do not within ``max_cg``, or the gauge changed, the current matrix
        is factored, as it always is below :data:`REUSE_MIN_N` cameras, where a factorization
        is cheaper than a few preconditioned products. The answer is the current matrix's
        either way (to ``rtol``). The
        scalar twin of :meth:`pipeline.averaging.block.BlockLaplacianSolver.solve_reusing`.
        """
        L = self.matrix(w)  # sets self.pinned
        if self.n >= REUSE_MIN_N and self._lu is not None:
            bb = np.array(b, dtype=np.float64, copy=True)
            bb[self.pinned] = 0.0
            same_gauge = np.array_equal(self.pinned, self._lu_pinned)
            x, n_it = solve_without_factoring(self._factor, L, bb, self._lu, same_gauge, rtol, max_cg)
            self.n_cg_iterations += n_it
            if x is not None:
                x[self.pinned] = 0.0
                return x
        self._factorize(L)
        return self.solve(b)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the current factor; ``b`` (N, 3) → (N, 3), 0 at pinned cameras."""
        if self._lu is None:
            raise RuntimeError("LaplacianSolver.solve called before factor()")
        b = np.array(b, dtype=np.float64, order="F", copy=True)
        b[self.pinned] = 0.0
        x = self._lu.solve(b)
        x[self.pinned] = 0.0
        return x
