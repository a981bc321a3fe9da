"""Block Laplacian of the anisotropic methods (IRLS-H and its calibration): 3×3 edge blocks, SO(3) Jacobian.

Shared by :mod:`~pipeline.averaging.irls_h` and :mod:`~pipeline.averaging.calibration`;
see :mod:`~pipeline.averaging.irls_h` for the step's derivation. Pure functions and
classes on arrays: no I/O, no logging.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pipeline.averaging.iterative import solve_without_factoring
from pipeline.averaging.kernel import REUSE_MIN_N, FactorState, LaplacianSolver, effective_weights, graph_residuals
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["BlockLaplacianSolver", "edge_metric", "jl_inv", "left_errors", "anisotropic_step"]


class BlockLaplacianSolver(FactorState):
    """Factor and solve gauge-fixed block Laplacians ``Σ_k A_kᵀ B_k A_k`` with 3×3 edge blocks.

    The (3N, 3N) sparsity pattern and the map from the (M, 3, 3) blocks to matrix
    entries are built once; :meth:`factor` scatters the blocks with
    ``np.bincount`` and factors it once (SuperLU, or a dense Cholesky on a dense graph:
    :class:`~pipeline.averaging.kernel.SymmetricFactorizer`). The gauge is fixed as in
    :class:`pipeline.averaging.kernel.LaplacianSolver`: one pinned camera per
    connected component of the edges with a nonzero block.

    Args:
        edges: (M, 2) camera indices.
        n: number of cameras N.
        ref: the camera pinned when the weighted graph is connected.
        dense: the factorization (:class:`~pipeline.averaging.kernel.SymmetricFactorizer`; None: decided by fill).
    """

    def __init__(self, edges: np.ndarray, n: int, ref: int = 0, dense: bool | None = None) -> None:
        edges = np.asarray(edges, dtype=np.int64)
        M = edges.shape[0]
        self.n, self.edges = int(n), edges
        self._pins = LaplacianSolver(edges, n, ref=ref)._pins  # the same gauge rule
        i, j = edges[:, 0], edges[:, 1]
        p, q = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        p, q = p.ravel(), q.ravel()  # the 9 entries of a block, row-major
        # 4 blocks per edge: (i,i) +B, (j,j) +B, (i,j) −B, (j,i) −B; then N identity-diagonal slots.
        bi = np.concatenate([i, j, i, j])
        bj = np.concatenate([i, j, j, i])
        rows = np.concatenate([(3 * bi[:, None] + p).ravel(), 3 * np.arange(n)[:, None].repeat(3, 1).ravel()
                               + np.tile(np.arange(3), n)])
        cols = np.concatenate([(3 * bj[:, None] + q).ravel(), 3 * np.arange(n)[:, None].repeat(3, 1).ravel()
                               + np.tile(np.arange(3), n)])
        N3 = 3 * n
        keys = cols * N3 + rows  # CSC order
        ukeys, inv = np.unique(keys, return_inverse=True)
        n_blk = 4 * M * 9
        self._pos = inv[:n_blk]
        self._sign = np.repeat([1.0, 1.0, -1.0, -1.0], M * 9)
        # block entry (edge, p, q) in the flattened (M·9,) array of blocks
        self._src = np.tile((np.arange(M)[:, None] * 9 + np.arange(9)).ravel(), 4)
        self._row, self._col = ukeys % N3, ukeys // N3
        self._diag = inv[n_blk:].reshape(n, 3)
        self._nnz = ukeys.size
        self._indptr = np.searchsorted(self._col, np.arange(N3 + 1)).astype(np.int32)
        self._indices = self._row.astype(np.int32)
        self._init_factor(n, dense)

    def matrix(self, B: np.ndarray) -> sp.csc_matrix:
        """The gauge-fixed (3N, 3N) block Laplacian for edge blocks ``B`` (M, 3, 3)."""
        B = np.asarray(B, dtype=np.float64)
        tr = effective_weights(np.trace(B, axis1=1, axis2=2))
        B = B * (tr > 0)[:, None, None]  # negligible blocks count as 0 (kernel.NEGLIGIBLE_WEIGHT)
        self.pinned = self._pins(tr)
        data = np.bincount(self._pos, weights=self._sign * B.reshape(-1)[self._src], minlength=self._nnz)
        if self.pinned.any():
            cam_row, cam_col = self._row // 3, self._col // 3
            data *= ~(self.pinned[cam_row] | self.pinned[cam_col])
            data[self._diag[self.pinned].ravel()] = 1.0
        return sp.csc_matrix((data, self._indices, self._indptr), shape=(3 * self.n, 3 * self.n))

    def factor(self, B: np.ndarray) -> None:
        """Factor the gauge-fixed block Laplacian for edge blocks ``B`` (M, 3, 3)."""
        self._factorize(self.matrix(B))

    def _factorize(self, A: sp.csc_matrix) -> None:
        self._lu = self._factor(A)
        self._lu_pinned = self.pinned.copy()
        self.n_factorizations += 1

    def solve_reusing(self, B: np.ndarray, b: np.ndarray, rtol: float = 1e-7, max_cg: int = 15) -> np.ndarray:
        """Solve the system of blocks ``B`` for ``b`` (N, 3), reusing the last factor when it serves.

        IRLS weights change little from one iteration to the next, so the factor of the
        previous matrix is a near-exact preconditioner for the current one: conjugate
        gradients on the current matrix, preconditioned by it, reach ``rtol`` in a few
        matrix-vector products. When they do not within ``max_cg`` iterations, or when the
        gauge (the pinned cameras) changed, the current matrix is factored instead; on a well-connected graph,
        block-Jacobi conjugate gradients come first (:func:`~pipeline.averaging.iterative.solve_iteratively`). The
        solution is that of the current matrix either way (to ``rtol``).
        """
        A = self.matrix(B)  # sets self.pinned for B
        pinned = self.pinned
        if self._lu is not None:
            bb = np.array(b, dtype=np.float64, copy=True)
            bb[pinned] = 0.0
            x, n_it = solve_without_factoring(self._factor, A, bb.reshape(-1), self._lu,
                                              np.array_equal(pinned, self._lu_pinned), rtol, max_cg, block=3,
                                              min_n=REUSE_MIN_N)
            self.n_cg_iterations += n_it
            if x is not None:
                x = x.reshape(self.n, 3)
                x[pinned] = 0.0
                return x
        self._factorize(A)
        return self.solve(b)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the current factor; ``b`` (N, 3) → (N, 3), 0 at pinned cameras."""
        if self._lu is None:
            raise RuntimeError("BlockLaplacianSolver.solve called before factor()")
        b = np.array(b, dtype=np.float64, copy=True)
        b[self.pinned] = 0.0
        x = self._lu.solve(b.reshape(-1)).reshape(self.n, 3)
        x[self.pinned] = 0.0
        return x

    def rhs(self, g: np.ndarray) -> np.ndarray:
        """``Σ_k A_kᵀ g_k`` for per-edge vectors ``g`` (M, 3): −g at camera i, +g at camera j."""
        i, j = self.edges[:, 0], self.edges[:, 1]
        return np.stack([np.bincount(j, g[:, a], self.n) - np.bincount(i, g[:, a], self.n) for a in range(3)], axis=1)


def edge_metric(vg: ViewGraph, R: np.ndarray) -> np.ndarray:
    """``W_ij = R_jᵀ H_ij R_j`` (M, 3, 3): H in the frame of the residual ``log(R_jᵀ R̃_ij R_i)``."""
    Rj = R[vg.edges[:, 1]]
    return np.swapaxes(Rj, 1, 2) @ vg.H @ Rj


def jl_inv(w: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian of SO(3), (M, 3) → (M, 3, 3):
    ``log(exp([a]×) exp([w]×)) = w + J_l⁻¹(w) a + O(|a|²)``.

    ``J_l⁻¹(w) = I − ½[w]× + c(θ)[w]×²`` with ``c = 1/θ² − cot(θ/2)/(2θ)`` (finite at θ = π;
    its series ``1/12 + θ²/720 + θ⁴/30240`` below 1e-3 rad).
    """
    th = np.sqrt(np.einsum("ma,ma->m", w, w))
    small = th < 1e-3
    ts = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th**2 / 720.0 + th**4 / 30240.0,
                 1.0 / ts**2 - 1.0 / (2.0 * ts * np.tan(0.5 * ts)))
    K = so3.hat(w)
    return np.eye(3) - 0.5 * K + c[:, None, None] * (K @ K)


def left_errors(vg: ViewGraph, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per edge: the residual ``r = log(R_jᵀ R̃ R_i)`` (M, 3), ``R_j`` (M, 3, 3) and ``Δω = −R_j r`` (M, 3),
    the left perturbation of ``R_j R_iᵀ = exp([Δω]×) R̃`` in which H is a precision."""
    r = graph_residuals(vg, R)
    Rj = R[vg.edges[:, 1]]
    return r, Rj, -np.einsum("mab,mb->ma", Rj, r)


def anisotropic_step(vg: ViewGraph, R: np.ndarray, solver: BlockLaplacianSolver, P: np.ndarray, w: np.ndarray,
                     reuse: bool = True) -> np.ndarray:
    """One Gauss–Newton step of ``Σ w_e Δω_eᵀ P_e Δω_e`` (the block IRLS step of :mod:`~pipeline.averaging.irls_h`).

    ``Δω ← Δω + G (δ_j − δ_i)`` with ``G = J_l⁻¹(Δω) R_j``, so the step solves
    ``(Σ A_kᵀ w_k G_kᵀ P_k G_k A_k) ΔΩ = −Σ A_kᵀ w_k G_kᵀ P_k Δω_k``.

    Args:
        vg: the view graph.
        R: (N, 3, 3) current rotations.
        solver: the block solver of ``vg``'s edges.
        P: (M, 3, 3) edge precisions (H, or a calibrated metric).
        w: (M,) edge weights.
        reuse: reuse the previous factor as a CG preconditioner.

    Returns:
        (N, 3) the update ``Δω_i`` of ``R_i ← R_i exp([Δω_i]×)``.
    """
    _, Rj, dom = left_errors(vg, R)
    G = jl_inv(dom) @ Rj
    PG = P @ G
    ww = np.asarray(w, dtype=np.float64)[:, None, None]
    B = ww * (np.swapaxes(G, 1, 2) @ PG)
    g = solver.rhs(-np.einsum("mba,mb->ma", ww * PG, dom))
    if reuse:
        return solver.solve_reusing(B, g)
    solver.factor(B)
    return solver.solve(g)
