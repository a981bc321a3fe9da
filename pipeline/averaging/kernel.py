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

Used by :mod:`~pipeline.averaging.l1`, :mod:`~pipeline.averaging.irls`,
:mod:`~pipeline.averaging.irls_h` and :mod:`~pipeline.averaging.weiszfeld`. Pure
functions and classes on arrays: no I/O, no logging.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from pipeline.core import so3
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["edge_residuals", "apply_update", "LaplacianSolver", "check_graph"]


def edge_residuals(edges: np.ndarray, R_rel: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Residual rotation vectors ``r_ij = log(R_jᵀ R_ij R_i)`` (paper 1, eq. 7).

    Args:
        edges: (M, 2) camera indices ``(i, j)``.
        R_rel: (M, 3, 3) measured ``R_ij ≈ R_j R_iᵀ``.
        R: (N, 3, 3) current cam_from_world rotations.

    Returns:
        (M, 3) residuals in radians.
    """
    Ri = R[edges[:, 0]]
    Rj = R[edges[:, 1]]
    return so3.log(np.swapaxes(Rj, 1, 2) @ R_rel @ Ri)


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


class LaplacianSolver:
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
    """

    def __init__(self, edges: np.ndarray, n: int, ref: int = 0) -> None:
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
        ukeys, inv = np.unique(keys, return_inverse=True)
        self._pos = inv[: 4 * M]
        self._sign = np.repeat([1.0, 1.0, -1.0, -1.0], M)
        self._edge_of = np.tile(np.arange(M), 4)
        self._row = ukeys % n
        self._col = ukeys // n
        self._diag = inv[4 * M :]
        self._nnz = ukeys.size
        self._indptr = np.searchsorted(self._col, np.arange(n + 1)).astype(np.int32)
        self._indices = self._row.astype(np.int32)
        A = sp.csr_matrix((np.tile([-1.0, 1.0], M), (np.repeat(np.arange(M), 2), edges.ravel())), shape=(M, n))
        self.A = A
        self.AT = A.T.tocsr()
        self._lu: sla.SuperLU | None = None
        self.pinned = np.zeros(n, dtype=bool)
        self.n_factorizations = 0

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
        w = np.asarray(w, dtype=np.float64)
        self.pinned = self._pins(w)
        data = np.bincount(self._pos, weights=self._sign * w[self._edge_of], minlength=self._nnz)
        if self.pinned.any():
            keep = ~(self.pinned[self._row] | self.pinned[self._col])
            data *= keep
            data[self._diag[self.pinned]] = 1.0
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(self.n, self.n))

    def factor(self, w: np.ndarray) -> None:
        """Factor the gauge-fixed Laplacian for edge weights ``w`` (M,)."""
        L = self.matrix(w)
        self._lu = sla.splu(
            L, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True)
        )
        self.n_factorizations += 1

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the current factor; ``b`` (N, 3) → (N, 3), 0 at pinned cameras."""
        if self._lu is None:
            raise RuntimeError("LaplacianSolver.solve called before factor()")
        b = np.array(b, dtype=np.float64, order="F", copy=True)
        b[self.pinned] = 0.0
        x = self._lu.solve(b)
        x[self.pinned] = 0.0
        return x
