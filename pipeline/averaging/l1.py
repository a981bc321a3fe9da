"""Initial ℓ1 relative rotation averaging (paper 1, Algorithm 2) and shared Lie-algebra helpers.

Residual convention (``../shared/DESIGN.md``): for edge ``(i, j)`` carrying
``R_ij ≈ R_j R_iᵀ``,

    ΔR_ij = R_jᵀ R_ij R_i,    r_ij = log(ΔR_ij)            (paper 1, eq. 7)

and every camera is updated on the right, ``R_i ← R_i exp([Δω_i]×)``. After the
update ``ΔR_ij ← exp(−[Δω_j]×) ΔR_ij exp([Δω_i]×)``, whose log is, to first order
(paper 1, eqs. 19 and 34), ``r_ij + Δω_i − Δω_j``. With the incidence matrix
``A`` of :meth:`ViewGraph.incidence` (−1 at ``i``, +1 at ``j``) the stacked
linearized residual is therefore ``r − A ΔΩ``: paper 1's ``A ΔΩ_V + ΔΩ_E`` with its
``A`` (+I at ``i``, −I at ``j``) equal to minus ours. Algorithm 2 solves

    ΔΩ = argmin ‖A ΔΩ − r‖₁

(three independent LAD problems, one per axis, sharing ``A``) by ADMM with one
cached sparse factorization of the gauge-fixed ``AᵀA``. The x-update of ADMM for
least absolute deviations does not involve the penalty ρ, so ρ is adapted freely
(residual balancing) without refactoring.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = [
    "edge_residuals",
    "apply_update",
    "LaplacianSolver",
    "l1_step",
    "l1_averaging",
    "L1StepResult",
]

logger = logging.getLogger(__name__)


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


def _norm(x: np.ndarray) -> float:
    """Frobenius norm without BLAS (``np.linalg.norm`` calls a threaded ``dot``
    that stalls for milliseconds on a loaded machine)."""
    return float(np.sqrt(np.square(x).sum()))


def apply_update(R: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """``R_i exp([Δω_i]×)`` for every camera (right update, paper 1 Alg. 1 step 6).

    Args:
        R: (N, 3, 3) rotations.
        dw: (N, 3) updates in radians.
    """
    return R @ so3.exp(dw)


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


@dataclass
class L1StepResult:
    """One ℓ1 step: ``x = argmin ‖A x − r‖₁`` per axis.

    Attributes:
        x: (N, 3) camera updates (0 at the pinned camera).
        iterations: ADMM iterations.
        objective: ‖A x − r‖₁ (sum over the three axes).
        z: (M, 3) ADMM split variable (``≈ A x − r``), for warm starts.
        u: (M, 3) scaled dual variable, for warm starts.
        rho: final penalty.
    """

    x: np.ndarray
    iterations: int
    objective: float
    z: np.ndarray
    u: np.ndarray
    rho: float
    converged: bool = True
    history: list[float] = field(default_factory=list)


def l1_step(
    solver: LaplacianSolver,
    r: np.ndarray,
    max_iterations: int = 1000,
    eps_abs: float = 1e-7,
    eps_rel: float = 1e-5,
    rho: float | None = None,
    relax: float = 1.6,
    z0: np.ndarray | None = None,
    u0: np.ndarray | None = None,
    check_every: int = 5,
) -> L1StepResult:
    """Solve ``min_x ‖A x − r‖₁`` (three axes at once) by over-relaxed ADMM.

    ADMM for least absolute deviations (split ``z = A x − r``):

        x ← (AᵀA)⁻¹ Aᵀ (r + z − u)       (the cached factor; gauge pinned)
        z ← S_{1/ρ}(α A x + (1 − α)(z + r) − r + u)
        u ← u + α A x + (1 − α)(z_old + r) − r − z

    Args:
        solver: a :class:`LaplacianSolver` already factored with unit weights.
        r: (M, 3) residuals (right-hand side).
        max_iterations: ADMM iteration cap.
        eps_abs, eps_rel: primal/dual stopping tolerances (Boyd et al. §3.3).
        rho: initial penalty; default from the residual scale.
        relax: over-relaxation α in [1.5, 1.8].
        z0, u0: warm start of the split and dual variables, (M, 3).
        check_every: evaluate the stopping test every this many iterations.

    Returns:
        :class:`L1StepResult`.
    """
    A, AT = solver.A, solver.AT
    M = r.shape[0]
    z = np.zeros_like(r) if z0 is None else z0.copy()
    u = np.zeros_like(r) if u0 is None else u0.copy()
    if rho is None:
        # 1/ρ is the soft threshold on residuals; start near their typical size.
        med = float(np.median(np.abs(r))) if M else 1.0
        rho = 1.0 / max(med, 1e-6)
    sqrt_m = np.sqrt(3 * M)
    converged = False
    k = 0
    x = np.zeros((solver.n, 3))
    for k in range(1, max_iterations + 1):
        q = r + z
        q -= u
        x = solver.solve(AT @ q)
        Ax = A @ x
        # v = α(Ax − r) + (1 − α) z + u, built in place (these (M, 3) passes
        # dominate an iteration once the factor is cached).
        v = Ax - r
        v *= relax
        v += (1.0 - relax) * z
        v += u
        z_old = z
        # Soft threshold: z = S_{1/ρ}(v) and the new scaled dual u = v − z = clip(v).
        u = np.clip(v, -1.0 / rho, 1.0 / rho)
        z = v
        z -= u
        if k % check_every and k < max_iterations:
            continue
        # Boyd et al. (2011) §3.3 stopping criteria, with the unrelaxed Ax;
        # checked every few iterations since they cost two extra products.
        r_pri = _norm(Ax - z - r)
        s_dual = rho * _norm(AT @ (z - z_old))
        eps_pri = sqrt_m * eps_abs + eps_rel * max(_norm(Ax), _norm(z), _norm(r))
        eps_dual = np.sqrt(3 * solver.n) * eps_abs + eps_rel * rho * _norm(AT @ u)
        if r_pri <= eps_pri and s_dual <= eps_dual:
            converged = True
            break
        # Residual balancing (Boyd et al. §3.4.1); u is scaled, so rescale it.
        if r_pri > 10.0 * s_dual:
            rho *= 2.0
            u /= 2.0
        elif s_dual > 10.0 * r_pri:
            rho /= 2.0
            u *= 2.0
    obj = float(np.abs(A @ x - r).sum())
    return L1StepResult(x=x, iterations=k, objective=obj, z=z, u=u, rho=rho, converged=converged)


def l1_averaging(
    vg: ViewGraph,
    R0: np.ndarray,
    max_iterations: int = 5,
    tol_rad: float = 1e-3,
    admm_max_iterations: int = 1000,
    admm_eps_rel: float = 1e-4,
    solver: LaplacianSolver | None = None,
) -> tuple[np.ndarray, list[dict[str, float]]]:
    """Paper 1, Algorithm 2: repeated ℓ1 steps ``R_i ← R_i exp([Δω_i]×)``.

    Args:
        vg: a connected view graph.
        R0: (N, 3, 3) initial rotations.
        max_iterations: outer iterations (paper 1, Alg. 3, uses 5).
        tol_rad: stop when the mean camera update is below this (radians).
        admm_max_iterations: ADMM cap per step.
        admm_eps_rel: relative ADMM tolerance per step.
        solver: a :class:`LaplacianSolver` for ``vg`` (built if None).

    Returns:
        rotations (N, 3, 3) and per-iteration records (``cost`` = Σ‖r_ij‖,
        ``l1_objective``, ``mean_step_rad``, ``admm_iterations``, ``time_s``).
    """
    t0 = time.perf_counter()
    if solver is None:
        solver = LaplacianSolver(vg.edges, vg.n_cameras, ref=int(np.argmax(vg.degrees())))
    solver.factor(np.ones(vg.n_edges))
    R = R0.copy()
    history: list[dict[str, float]] = []
    z = u = None
    rho = None
    for _ in range(max_iterations):
        r = edge_residuals(vg.edges, vg.R_rel, R)
        # Warm start: after a step, the new optimum has x ≈ 0 and the same split.
        st = l1_step(solver, r, max_iterations=admm_max_iterations, eps_rel=admm_eps_rel, z0=z, u0=u, rho=rho)
        z, u, rho = st.z, st.u, st.rho
        R = apply_update(R, st.x)
        step = float(np.linalg.norm(st.x, axis=1).mean())
        history.append(
            {
                "stage": "l1",
                "cost": float(np.linalg.norm(r, axis=1).sum()),
                "l1_objective": st.objective,
                "mean_step_rad": step,
                "admm_iterations": st.iterations,
                "time_s": time.perf_counter() - t0,
            }
        )
        if step < tol_rad:
            break
    return R, history
