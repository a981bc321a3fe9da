"""Certifiable SDP rotation averaging, isotropic and anisotropic (paper 2).

Four relaxations (paper 2, §3–§5), all over ``X = Y Yᵀ`` with ``Y = [R_1; …; R_N]``
so that ``X_ji = R_j R_iᵀ`` (DESIGN.md conventions):

==============  ==============  =============================================
variant         cost weight     constraints
==============  ==============  =============================================
``o3-iso``      ``M_ij = I``    ``X ⪰ 0``, ``X_ii = I``  (SDP-O(3)-ISO)
``o3-aniso``    ``M_ij`` eq. 5  same                     (SDP-O(3)-ANISO)
``cso3-iso``    ``M_ij = I``    + ``𝒜(X_ji) + I ⪰ 0`` on every edge (eq. 27)
``cso3``        ``M_ij`` eq. 5  + ``𝒜(X_ji) + I ⪰ 0`` on every edge (SDP-cSO(3))
==============  ==============  =============================================

The cost is ``−Σ_edges ⟨M_ij R̃_ij, X_ji⟩`` (paper 2, eq. 11, one term per edge).
For the anisotropic variants it is divided by ``s`` = the mean over edges of the
largest eigenvalue of ``H_ij`` before solving (paper 2, §5); every reported cost is
multiplied back, i.e. in the units of the unscaled cost above.

Two equivalent conic statements are built, in the standard form shared by SCS and
Clarabel, ``min cᵀx  s.t.  A x + s = b,  s ∈ K`` (:func:`build_conic`):

``form="primal"`` (default for SCS, which converges in far fewer iterations on it; it
is also what JuMP hands SCS for paper 2): ``x = svec X``, rows ``X_ii = I`` (zero
cone), ``s = x`` (the 3N×3N PSD cone) and ``s_e = svec(𝒜(X_ji) + I)`` (4×4 PSD cones).

``form="dual"`` (default for Clarabel): the Lagrange dual (paper 2, eq. 24 with the
conv(SO(3)) conjugate written as 4×4 LMIs),

    variables  x = [υ (6 per camera: the symmetric Υ_ii),  ŵ (10 per edge: svec W_e)]
    minimize   Σ_i tr Υ_ii + Σ_e tr W_e
    subject to S = blkdiag(Υ) − Ñ − Σ_e E_e(𝒜*(W_e)) ⪰ 0     (one 3N×3N PSD cone)
               W_e ⪰ 0                                        (4×4 PSD cones, cSO(3) only)

where ``Ñ`` is the symmetric cost matrix with blocks ``Ñ_ji = ½ C_e`` and ``E_e``
places ``½ 𝒜*(W_e)`` at block ``(j, i)`` and its transpose at ``(i, j)``. The solver's
dual variable of the big cone is then ``svec(X)``. It has 6N + 10M variables and no
equality rows, and its PSD slack has the graph's sparsity, which Clarabel's chordal
decomposition can exploit. Either way a dual-feasible point is recovered and turned
into a rigorous lower bound (:func:`_extract`). The readable primal statement is
:mod:`pipeline.averaging.sdp_cvxpy`; the tests check all reach the same optimum.

Assembly is vectorized index arithmetic over edges (no Python loop over edges).
Each solver's svec convention is handled by :func:`svec_index`:

* SCS: lower triangle, column-major, off-diagonal entries scaled by √2;
* Clarabel: upper triangle, column-major (= lower triangle row-major), √2 scaling.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from pipeline.core import so3
from pipeline.core.errors import PipelineError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph
from pipeline.averaging.certificate import (
    edge_cost,
    numerical_rank,
    relative_gap,
    round_to_rotations,
    weight_matrices,
)
from pipeline.averaging.result import AveragingResult

__all__ = [
    "VARIANTS",
    "SOLVERS",
    "ConicProblem",
    "solve_sdp",
    "build_conic",
    "edge_weights",
    "svec_index",
    "conv_so3_lmi",
]

logger = logging.getLogger(__name__)

#: variant -> (anisotropic cost, conv(SO(3)) constraints)
VARIANTS: dict[str, tuple[bool, bool]] = {
    "o3-iso": (False, False),
    "o3-aniso": (True, False),
    "cso3-iso": (False, True),
    "cso3": (True, True),
}
SOLVERS = ("scs", "clarabel")
SQRT2 = np.sqrt(2.0)
#: Largest N for which an uncertified solve is retried with Clarabel at FALLBACK_EPS. Its cost
#: grows fast: with one huge H, N = 30 (M = 160) took 17 s CPU and 0.43 GB, N = 50 (M ≈ 370)
#: over 47 s CPU and 3.5 GB without finishing (notes/issue-4.md, "Temple: heterogeneous H").
FALLBACK_MAX_CAMERAS = 30
FALLBACK_EPS = 1e-12
FALLBACK_MAX_ITERS = 400
#: SCS iteration cap when the Clarabel fallback is available (N ≤ FALLBACK_MAX_CAMERAS) and the
#: caller set none. Well-conditioned problems need a few hundred iterations (fountain-P11: 600,
#: rendered scenes: ~300); templeSparseRing's one huge H took SCS 46 850 iterations (34 s) to a
#: rank-24 uncertified answer that Clarabel then fixed in 0.1 s. A capped SCS run that has not
#: converged is handed to the fallback (Clarabel at N ≤ 30: at most a few seconds).
FALLBACK_SCS_MAX_ITERS = 2000
#: A solve whose gap exceeds this share of the residual cost (plus the requested relative
#: accuracy of |d*|) is re-solved as an uncertified one is.
FALLBACK_RESIDUAL_GAP = 1e-2
_SCS_SETTINGS = {
    "normalize", "scale", "adaptive_scale", "rho_x", "max_iters", "eps_abs", "eps_rel", "eps_infeas",
    "alpha", "time_limit_secs", "verbose", "acceleration_lookback", "acceleration_interval",
    "warm_start", "write_data_filename", "log_csv_filename", "use_indirect", "mkl",
}

# 𝒜(Y) of paper 2, eq. 27, as a (4, 4, 3, 3) tensor: 𝒜(Y)_kl = Σ_ab T[k,l,a,b] Y_ab.
# Entries are (k, l, a, b, sign) with 0-based indices; Y11 of the paper is Y[0, 0].
_A_TERMS = [
    (0, 0, 0, 0, -1), (0, 0, 1, 1, -1), (0, 0, 2, 2, 1),
    (0, 1, 0, 2, 1), (0, 1, 2, 0, 1),
    (0, 2, 0, 1, 1), (0, 2, 1, 0, -1),
    (0, 3, 1, 2, 1), (0, 3, 2, 1, 1),
    (1, 1, 0, 0, 1), (1, 1, 1, 1, -1), (1, 1, 2, 2, -1),
    (1, 2, 1, 2, 1), (1, 2, 2, 1, -1),
    (1, 3, 0, 1, 1), (1, 3, 1, 0, 1),
    (2, 2, 0, 0, 1), (2, 2, 1, 1, 1), (2, 2, 2, 2, 1),
    (2, 3, 2, 0, 1), (2, 3, 0, 2, -1),
    (3, 3, 0, 0, -1), (3, 3, 1, 1, 1), (3, 3, 2, 2, -1),
]
_T = np.zeros((4, 4, 3, 3))
for _k, _l, _a, _b, _s in _A_TERMS:
    _T[_k, _l, _a, _b] = _s
    _T[_l, _k, _a, _b] = _s
del _k, _l, _a, _b, _s


def conv_so3_lmi(Y: np.ndarray) -> np.ndarray:
    """``𝒜(Y) + I`` of paper 2, eq. 27: PSD iff ``Y ∈ conv(SO(3))``.

    Args:
        Y: (..., 3, 3) matrices.

    Returns:
        (..., 4, 4) symmetric matrices; rank 1 when ``Y`` is a rotation.
    """
    return np.einsum("klab,...ab->...kl", _T, np.asarray(Y, dtype=np.float64)) + np.eye(4)


def svec_index(p: np.ndarray, q: np.ndarray, n: int, solver: str) -> np.ndarray:
    """Position of entry ``(p, q)``, ``p >= q``, of an n×n symmetric matrix in svec.

    Args:
        p, q: integer arrays of row and column indices with ``p >= q``.
        n: matrix size.
        solver: ``"scs"`` (lower triangle, column-major) or ``"clarabel"``
            (upper triangle, column-major, i.e. lower triangle row-major).
    """
    p = np.asarray(p, dtype=np.int64)
    q = np.asarray(q, dtype=np.int64)
    if solver == "scs":
        return q * n - (q * (q - 1)) // 2 + (p - q)
    return (p * (p + 1)) // 2 + q


def _svec_pairs(n: int, solver: str) -> tuple[np.ndarray, np.ndarray]:
    """(p, q) with p >= q of every svec entry, in the solver's order."""
    p, q = np.tril_indices(n)
    order = np.argsort(svec_index(p, q, n, solver), kind="stable")
    return p[order], q[order]


def unsvec(v: np.ndarray, n: int, solver: str) -> np.ndarray:
    """Symmetric (n, n) matrix from its svec in the solver's convention."""
    p, q = np.tril_indices(n)
    vals = np.asarray(v)[svec_index(p, q, n, solver)]
    vals = np.where(p == q, vals, vals / SQRT2)
    X = np.zeros((n, n))
    X[p, q] = vals
    X[q, p] = vals
    return X


@dataclass
class ConicProblem:
    """``min cᵀx  s.t.  A x + s = b,  s ∈ K``, K = {0}^n_zero × PSD(n_big) × PSD(4)^n_small.

    Attributes:
        A: (m, n_var) sparse CSC.
        b: (m,) right-hand side.
        c: (n_var,) objective.
        n_big: size of the big PSD cone (3N).
        n_small: number of 4×4 PSD cones (edges when cSO(3), else 0).
        n_zero: number of equality rows (6N in the primal form, 0 in the dual form).
        form: ``"dual"`` (variables Υ, W) or ``"primal"`` (variables svec X).
        solver: the svec convention the rows follow.
    """

    A: sp.csc_matrix
    b: np.ndarray
    c: np.ndarray
    n_big: int
    n_small: int
    n_zero: int
    form: str
    solver: str

    @property
    def m_big(self) -> int:
        return self.n_big * (self.n_big + 1) // 2


def edge_weights(vg: ViewGraph, anisotropic: bool) -> tuple[np.ndarray, float]:
    """Weighted measurements ``C_e`` and the cost scale ``s`` (paper 2, eq. 11 and §5).

    Args:
        vg: the view graph; needs ``H`` when ``anisotropic``.
        anisotropic: use ``M_ij = tr(H)/2 I − H`` (eq. 5); else ``M_ij = I``.

    Returns:
        C: (M, 3, 3) ``M_ij R̃_ij / s``.
        s: the scale: the mean largest eigenvalue of the ``H_ij`` (1 when isotropic).
    """
    if not anisotropic:
        return vg.R_rel.copy(), 1.0
    H = 0.5 * (vg.H + np.swapaxes(vg.H, 1, 2))
    scale = float(np.mean(np.linalg.eigvalsh(H)[:, -1]))
    return weight_matrices(H) @ vg.R_rel / scale, scale


def build_conic(
    n_cameras: int,
    edges: np.ndarray,
    C: np.ndarray,
    cso3: bool,
    solver: str = "scs",
    form: str = "primal",
    lmi_edges: np.ndarray | None = None,
) -> ConicProblem:
    """Assemble the SDP as sparse ``(A, b, c)`` in the solver's svec convention.

    Args:
        n_cameras: N.
        edges: (M, 2) camera indices ``i < j``.
        C: (M, 3, 3) (scaled) weighted measurements; cost ``−Σ ⟨C_e, X_ji⟩``.
        cso3: add the 4×4 conv(SO(3)) LMIs on every edge.
        solver: svec convention, ``"scs"`` or ``"clarabel"``.
        form: ``"primal"`` (variables ``svec X``; what a modelling layer such as
            JuMP hands SCS, as in paper 2) or ``"dual"`` (variables ``Υ, W``; see
            the module docstring). Same SDP, different solver behaviour.
        lmi_edges: (K, 2) pairs ``i < j`` that get the conv(SO(3)) LMI when ``cso3``
            (default: ``edges``, the observed ones, as specified; paper 2's derivation
            has one for every pair, which is stronger and costlier).

    Returns:
        The :class:`ConicProblem`.
    """
    if form not in ("primal", "dual"):
        raise ValueError(f"unknown conic form {form!r}; expected 'primal' or 'dual'")
    N = int(n_cameras)
    n = 3 * N
    m_big = n * (n + 1) // 2
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    i_e, j_e = edges[:, 0], edges[:, 1]
    a3, b3 = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")  # (3, 3) block entry (a, b)
    # svec position of every entry of every edge block X_ji (strictly below the diagonal: j > i)
    idx_blk = svec_index(3 * j_e[:, None, None] + a3, 3 * i_e[:, None, None] + b3, n, solver)
    # svec position of the 6 upper-triangle entries (a <= b) of each diagonal block, as (3i+b, 3i+a)
    ua, ub = np.triu_indices(3)
    cam = np.repeat(np.arange(N), 6)
    pa, pb = np.tile(ua, N), np.tile(ub, N)
    idx_diag = svec_index(3 * cam + pb, 3 * cam + pa, n, solver)
    is_diag = pa == pb
    # 4×4 svec order of the small cones and 𝒜 in those coordinates: D[t,a,b] = σ_t T[k,l,a,b]
    pk, pl = _svec_pairs(4, solver)
    D = np.where((pk != pl)[:, None, None], SQRT2, 1.0) * _T[pk, pl]  # (10, 3, 3)
    t_nz, a_nz, b_nz = np.nonzero(D)
    d_nz = D[t_nz, a_nz, b_nz]
    lmi = edges if lmi_edges is None else np.asarray(lmi_edges, dtype=np.int64).reshape(-1, 2)
    K = lmi.shape[0]
    idx_lmi = svec_index(3 * lmi[:, 1, None] + a_nz, 3 * lmi[:, 0, None] + b_nz, n, solver)  # (K, nnz)
    n_small = K if cso3 else 0

    if form == "primal":
        # x = svec X (off-diagonal entries hold √2 X_pq).
        c = np.zeros(m_big)
        np.add.at(c, idx_blk.ravel(), (-C / SQRT2).ravel())  # −⟨C_e, X_ji⟩
        # rows: X_ii = I (zero cone) | s = x ∈ PSD | s_e = svec(𝒜(X_ji) + I) ∈ PSD(4)
        rows = [np.arange(6 * N), 6 * N + np.arange(m_big)]
        cols = [idx_diag, np.arange(m_big)]
        vals = [np.ones(6 * N), -np.ones(m_big)]
        b = np.zeros(6 * N + m_big + 10 * n_small)
        b[: 6 * N] = is_diag
        if cso3:
            r0 = 6 * N + m_big + 10 * np.arange(K)[:, None] + t_nz
            rows.append(r0.ravel())
            cols.append(idx_lmi.ravel())
            vals.append(np.broadcast_to(-d_nz / SQRT2, r0.shape).ravel())
            b[6 * N + m_big:] = np.tile((pk == pl).astype(float), K)
        A = sp.csc_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(b.size, m_big),
        )
        return ConicProblem(A, b, c, n, n_small, 6 * N, form, solver)

    # dual form: x = [υ (Υ_ii entries a <= b, 6 per camera), ŵ (svec W_e, 10 per edge)]
    # Big cone s = svec(S): S_{3i+b,3i+a} = υ  ⇒  A = −σ;  b = svec(−Ñ), Ñ_ji = ½ C_e.
    b = np.zeros(m_big + 10 * n_small)
    np.add.at(b, idx_blk.ravel(), (-C / SQRT2).ravel())
    rows, cols = [idx_diag], [np.arange(6 * N)]
    vals = [np.where(is_diag, -1.0, -SQRT2)]
    c_parts = [is_diag.astype(float)]
    if cso3:
        # S_{(j,a),(i,b)} −= ½ 𝒜*(W)_ab = ½ Σ_t ŵ_t D[t,a,b]  ⇒  A = +D/√2.
        col_w = 6 * N + 10 * np.arange(K)[:, None] + t_nz
        rows.append(idx_lmi.ravel())
        cols.append(col_w.ravel())
        vals.append(np.broadcast_to(d_nz / SQRT2, idx_lmi.shape).ravel())
        # Small cones: s_e = svec(W_e) = ŵ_e  ⇒  A = −I, b = 0.
        rows.append(m_big + np.arange(10 * K))
        cols.append(6 * N + np.arange(10 * K))
        vals.append(-np.ones(10 * K))
        c_parts.append(np.tile((pk == pl).astype(float), K))
    A = sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(b.size, 6 * N + 10 * n_small),
    )
    return ConicProblem(A, b, np.concatenate(c_parts), n, n_small, 0, form, solver)


def _check_inputs(vg: ViewGraph, variant: str, solver: str) -> tuple[bool, bool]:
    if variant not in VARIANTS:
        raise ValueError(f"unknown SDP variant {variant!r}; expected one of {sorted(VARIANTS)}")
    if solver not in SOLVERS:
        raise ValueError(f"unknown SDP solver {solver!r}; expected one of {list(SOLVERS)}")
    aniso, cso3 = VARIANTS[variant]
    if aniso and vg.H is None:
        raise ViewGraphError(
            f"variant {variant!r} is anisotropic and needs a precision H_ij on every edge, "
            "but the view graph has no H; run the two-view bundle adjustment stage, or use "
            "an isotropic variant ('cso3-iso' or 'o3-iso')"
        )
    if vg.n_cameras < 2 or vg.n_edges == 0:
        raise ViewGraphError(f"the SDP needs at least 2 cameras and 1 edge; got {vg.n_cameras} and {vg.n_edges}")
    labels = vg.components()
    if labels.max() > 0:
        sizes = np.bincount(labels)
        raise ViewGraphError(
            f"the view graph is not connected ({sizes.size} components, sizes {sizes[:5].tolist()}...): "
            "the SDP fixes only one global rotation; restrict it with vg.largest_component() "
            "(pipeline.average does this) and solve each component separately"
        )
    return aniso, cso3


def _solve_scs(prob: ConicProblem, eps_abs: float, eps_rel: float, max_iters: int | None,
               verbose: bool, **kw: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, int]:
    import scs

    cone = {"z": prob.n_zero, "s": [prob.n_big] + [4] * prob.n_small}
    settings = dict(eps_abs=eps_abs, eps_rel=eps_rel, eps_infeas=1e-8, verbose=verbose,
                    max_iters=500_000 if max_iters is None else int(max_iters))
    unknown = sorted(set(kw) - _SCS_SETTINGS)
    if unknown:
        raise ValueError(f"unknown SCS setting(s) {unknown}; allowed: {sorted(_SCS_SETTINGS)}")
    settings.update(kw)
    solver = scs.SCS({"P": None, "A": prob.A, "b": prob.b, "c": prob.c}, cone, **settings)
    sol = solver.solve()
    info = sol["info"]
    return sol["x"], sol["y"], sol["s"], str(info["status"]), int(info["iter"])


def _solve_clarabel(prob: ConicProblem, eps_abs: float, eps_rel: float, max_iters: int | None,
                    verbose: bool, **kw: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, int]:
    import clarabel

    settings = clarabel.DefaultSettings()
    settings.verbose = verbose
    settings.tol_gap_abs = eps_abs
    settings.tol_gap_rel = eps_rel
    settings.tol_feas = eps_rel
    settings.max_iter = 200 if max_iters is None else int(max_iters)
    for key, value in kw.items():
        if not hasattr(settings, key):
            raise ValueError(f"unknown Clarabel setting {key!r}; see clarabel.DefaultSettings")
        setattr(settings, key, value)
    cones = [clarabel.ZeroConeT(prob.n_zero)] if prob.n_zero else []
    cones += [clarabel.PSDTriangleConeT(prob.n_big)] + [clarabel.PSDTriangleConeT(4)] * prob.n_small
    P = sp.csc_matrix((prob.A.shape[1], prob.A.shape[1]))
    solver = clarabel.DefaultSolver(P, prob.c, prob.A, prob.b, cones, settings)
    sol = solver.solve()
    return (np.asarray(sol.x), np.asarray(sol.z), np.asarray(sol.s), str(sol.status), int(sol.iterations))


def _extract(prob: ConicProblem, x: np.ndarray, y: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The SDP solution ``X`` and a dual-feasible lower bound from the solver's output.

    The dual point ``(Υ, W)`` is read from the solver (``W_e`` from a cone vector,
    PSD by construction), the slack ``S = blkdiag(Υ) − Ñ − Σ E_e(𝒜*(W_e))`` is
    recomputed exactly, and if ``λ_min(S) < 0`` every ``Υ_ii`` is raised by
    ``|λ_min|`` so that ``S ⪰ 0``. The dual objective of that point,
    ``−tr Υ − Σ tr W_e``, is a lower bound on the SDP optimum and so on the
    rotation-averaging cost (weak duality), whatever the solver's accuracy.

    Returns:
        X: (3N, 3N) primal solution.
        lower_bound: in the solver's (scaled) units.
        lam_min: ``λ_min(S)`` before the shift (≈ 0 at an accurate solution).
    """
    n, m_big, z = prob.n_big, prob.m_big, prob.n_zero
    if prob.form == "dual":
        X = unsvec(y[:m_big], n, prob.solver)
        xd = np.array(x, dtype=np.float64)
        if prob.n_small:
            xd[2 * n:] = s[m_big:]  # the 6N Υ entries come first (n = 3N)
        S_vec = prob.b[:m_big] - prob.A[:m_big] @ xd
        dual_obj = -(prob.c @ xd)
    else:
        X = unsvec(x, n, prob.solver)
        yd = np.array(y, dtype=np.float64)
        # Dual feasibility Aᵀy + c = 0 with A_big = −I gives svec(S) = y_big exactly:
        S_vec = prob.A[:z].T @ yd[:z] + prob.c
        if prob.n_small:
            S_vec = S_vec + prob.A[z + m_big:].T @ yd[z + m_big:]
        dual_obj = -(prob.b[:z] @ yd[:z]) - prob.b[z + m_big:] @ yd[z + m_big:]
    lam_min = float(np.linalg.eigvalsh(unsvec(S_vec, n, prob.solver))[0])
    return X, float(dual_obj + n * min(0.0, lam_min)), lam_min


def solve_sdp(
    vg: ViewGraph,
    variant: str = "cso3",
    solver: str = "scs",
    eps_abs: float = 1e-5,
    eps_rel: float = 1e-6,
    max_iters: int | None = None,
    verbose: bool = False,
    **kw: Any,
) -> AveragingResult:
    """Certifiable SDP rotation averaging (paper 2), solved directly with SCS or Clarabel.

    Args:
        vg: a connected view graph; ``H`` on every edge for the anisotropic variants.
        variant: ``"cso3"`` (SDP-cSO(3), default), ``"cso3-iso"``, ``"o3-iso"`` or
            ``"o3-aniso"`` (see the module docstring).
        solver: ``"scs"`` or ``"clarabel"``.
        eps_abs, eps_rel: solver tolerances (paper 2, §5: 1e-5 and 1e-6). For SCS they
            are ``eps_abs``/``eps_rel``; for Clarabel ``tol_gap_abs`` and
            ``tol_gap_rel``/``tol_feas``.
        max_iters: iteration cap (default 500 000 for SCS as in paper 2, 200 for Clarabel).
        verbose: print the solver's log.
        **kw: ``cert_tol`` (relative gap below which a rank-3 solution is certified,
            default 1e-4); ``form`` (``"primal"`` or ``"dual"`` conic statement, see
            :func:`build_conic`; default primal for SCS, dual for Clarabel);
            ``lmi_pairs`` (``"edges"``, default, or ``"all"`` camera pairs);
            ``fallback_scs_max_iters`` (default None; ``run.py`` passes
            :data:`FALLBACK_SCS_MAX_ITERS`): when the fallback applies and no
            ``max_iters`` is given, cap SCS at this many iterations and leave a
            problem SCS has not solved by then to Clarabel;
            ``fallback`` (default True) and ``fallback_max_cameras`` (default
            :data:`FALLBACK_MAX_CAMERAS`): when ``N`` is at most that and the solve is
            not certified, or its gap exceeds :data:`FALLBACK_RESIDUAL_GAP` of the
            residual cost ``f + Σ tr M_e`` (beyond ``eps_rel·|d*|``), the same SDP is
            solved again by Clarabel (dual form) at tolerance :data:`FALLBACK_EPS` and the
            better certificate is kept. This matters when one edge's ``H`` is orders of
            magnitude above the others (the cost's constant ``−Σ tr M_e`` then hides the
            residual part below a first-order solver's accuracy; see notes/issue-4.md,
            "Temple: heterogeneous H"). The problem itself is never changed. Any other
            key is passed to the solver as a setting
            (e.g. ``chordal_decomposition_enable=True`` for Clarabel,
            ``time_limit_secs`` for SCS).

    Returns:
        An :class:`AveragingResult` named ``"sdp-<variant>"``; ``stats`` holds
        ``build_s``, ``solve_s``, ``rank``, ``eigenvalues`` (top 6), ``lower_bound``,
        ``sdp_value``, ``primal_cost``, ``gap`` (relative: ``(primal_cost −
        lower_bound)/|lower_bound|``), ``gap_abs``, ``certified``, ``status``,
        ``solver_iterations``, ``cost_scale``, ``variant``, ``solver``, ``gap_residual``
        (``gap_abs / (primal_cost + cost_offset)``, the gap as a share of the part of
        the cost the rotations change; ``cost_offset = Σ tr M_e``, or ``3M`` when
        isotropic), ``fallback`` (the reported solve is the Clarabel re-solve) and
        ``first_attempt`` (summary of the replaced solve, or None). ``solver``,
        ``form``, ``status``, ``eps_*`` describe the reported solve. Costs are in
        the unscaled units of ``−Σ_edges ⟨M_ij R̃_ij, R_j R_iᵀ⟩``.

    Raises:
        ValueError: unknown variant or solver.
        ViewGraphError: anisotropic variant without ``H``; a disconnected graph.
        PipelineError: the solver failed to return a solution.
    """
    cert_tol = float(kw.pop("cert_tol", 1e-4))
    fallback = bool(kw.pop("fallback", True))
    fallback_max_cameras = int(kw.pop("fallback_max_cameras", FALLBACK_MAX_CAMERAS))
    # SCS converges in fewer iterations on the primal form (as JuMP states it for
    # paper 2); Clarabel on the dual form, whose slack carries the graph's sparsity
    # that its chordal decomposition exploits.
    form = kw.pop("form", None) or ("primal" if solver == "scs" else "dual")
    lmi_pairs = kw.pop("lmi_pairs", "edges")
    if lmi_pairs not in ("edges", "all"):
        raise ValueError(f"lmi_pairs={lmi_pairs!r} but expected 'edges' (observed pairs) or 'all'")
    aniso, cso3 = _check_inputs(vg, variant, solver)
    t0 = time.perf_counter()
    C, scale = edge_weights(vg, aniso)
    # Σ_e tr M_e: the cost of a perfect fit is −offset, and f + offset ≥ 0 is the part of the
    # cost that depends on the residuals (f_e + tr M_e = (1 − cos θ_e) u_eᵀ H_e u_e ≥ 0).
    offset = float(np.sum(np.trace(weight_matrices(0.5 * (vg.H + np.swapaxes(vg.H, 1, 2))),
                                   axis1=1, axis2=2))) if aniso else 3.0 * vg.n_edges
    lmi_edges = np.argwhere(np.triu(np.ones((vg.n_cameras,) * 2, bool), 1)) if lmi_pairs == "all" else None
    common = dict(vg=vg, C=C, scale=scale, offset=offset, cso3=cso3, lmi_edges=lmi_edges, cert_tol=cert_tol)
    scs_cap = kw.pop("fallback_scs_max_iters", None)
    if (scs_cap is not None and solver == "scs" and max_iters is None and fallback
            and vg.n_cameras <= fallback_max_cameras):
        max_iters = int(scs_cap)
    att = _attempt(solver=solver, form=form, eps_abs=eps_abs, eps_rel=eps_rel, max_iters=max_iters,
                   verbose=verbose, kw=kw, **common)
    first = att
    tight = min(eps_abs, eps_rel) <= FALLBACK_EPS and solver == "clarabel"
    used_fallback = False
    # Refine also a "certified" solve whose gap, beyond the requested relative accuracy, is a
    # sizeable share of the residual cost: the relative gap divides by |d*| ≈ offset, which
    # one edge with a huge H can make so large that a 1e-4 test is met by poor rotations.
    loose = att["gap_abs"] > (FALLBACK_RESIDUAL_GAP * max(att["primal_cost"] + offset, 0.0)
                              + eps_rel * abs(att["lower_bound"]))
    if (not att["certified"] or loose) and fallback and not tight and vg.n_cameras <= fallback_max_cameras:
        # The SDP value is dominated by the constant −Σ tr M_e; when one edge's H is orders of
        # magnitude above the others (e.g. a zero-baseline pair), the residual part that fixes
        # the rotations sits below a first-order solver's 1e-6 relative accuracy, and an
        # interior-point method at its default tolerance stops on the interior of the optimal
        # face (high rank). The same SDP solved by Clarabel to FALLBACK_EPS is cheap at small N.
        logger.info(
            "sdp-%s: %s (%s form) gave rank %d, relative gap %.3g, gap %.3g of the residual cost "
            "(certified: %s, status %s); re-solving the same SDP with Clarabel at tolerance %.0e",
            variant, solver, form, att["rank"], att["gap"], att["gap_residual"], att["certified"],
            att["status"], FALLBACK_EPS,
        )
        try:
            att2 = _attempt(solver="clarabel", form="dual", eps_abs=FALLBACK_EPS, eps_rel=FALLBACK_EPS,
                            max_iters=FALLBACK_MAX_ITERS, verbose=verbose, kw={}, **common)
        except PipelineError as err:  # keep the first solve; the warning below still reports it
            logger.warning("sdp-%s: the Clarabel re-solve failed (%s); keeping the %s result", variant, err, solver)
            att2 = None
        if att2 is not None:
            same = att2["certified"] == att["certified"]
            if (att2["gap_abs"] < att["gap_abs"]) if same else att2["certified"]:
                att, used_fallback = att2, True
    t3 = time.perf_counter()

    method = f"sdp-{variant}"
    if not att["certified"]:
        logger.warning(
            "%s is NOT certified optimal: rank %d (need 3), relative gap %.3g (tolerance %.1g), "
            "solver status %s; the rotations are a rounding of the relaxation, not a proven optimum",
            method, att["rank"], att["gap"], cert_tol, att["status"],
        )
    R = att["R"]
    resid = so3.angle_between(so3.relative(R, vg.edges), vg.R_rel)
    stats = {
        "variant": variant,
        "solver": att["solver"],
        "build_s": att["build_s"],
        "solve_s": att["solve_s"],
        "certificate_s": att["certificate_s"],
        "rank": att["rank"],
        "eigenvalues": att["eigenvalues"],
        "lower_bound": att["lower_bound"],
        "sdp_value": att["sdp_value"],
        "primal_cost": att["primal_cost"],
        "gap": att["gap"],
        "gap_abs": att["gap_abs"],
        "gap_residual": att["gap_residual"],
        "cost_offset": offset,
        "cert_tol": cert_tol,
        "certified": att["certified"],
        "status": att["status"],
        "solver_iterations": att["iterations"],
        "dual_lambda_min": att["dual_lambda_min"],
        "cost_scale": scale,
        "cost_units": "-sum_edges <M_ij R~_ij, R_j R_i^T>, unscaled (M_ij = I when isotropic)",
        "form": att["form"],
        "lmi_pairs": lmi_pairs,
        "n_variables": att["n_variables"],
        "n_constraints": att["n_constraints"],
        "eps_abs": att["eps_abs"],
        "eps_rel": att["eps_rel"],
        "fallback": used_fallback,
        "first_attempt": None if first is att else {
            k: first[k] for k in ("solver", "form", "status", "rank", "gap", "gap_residual", "certified",
                                  "solve_s", "iterations")
        },
    }
    return AveragingResult(
        method=method,
        names=list(vg.names),
        R=R,
        time_s=t3 - t0,
        iterations=int(att["iterations"] + (first["iterations"] if used_fallback else 0)),
        edge_index=np.arange(vg.n_edges),
        residuals_rad=resid,
        stats=stats,
    )


def _attempt(vg: ViewGraph, C: np.ndarray, scale: float, offset: float, cso3: bool,
             lmi_edges: np.ndarray | None, cert_tol: float, solver: str, form: str, eps_abs: float,
             eps_rel: float, max_iters: int | None, verbose: bool, kw: dict[str, Any]) -> dict[str, Any]:
    """Build, solve, round and certify once with one solver setting; see :func:`solve_sdp`."""
    t0 = time.perf_counter()
    prob = build_conic(vg.n_cameras, vg.edges, C, cso3, solver, form, lmi_edges)
    t1 = time.perf_counter()
    run = _solve_scs if solver == "scs" else _solve_clarabel
    x, y, s, status, iters = run(prob, eps_abs, eps_rel, max_iters, verbose, **kw)
    t2 = time.perf_counter()
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.any(x != 0)):
        raise PipelineError(
            f"{solver} returned no usable solution (status {status!r}); try the other solver "
            "or looser tolerances"
        )
    X, lb_scaled, lam_min_S = _extract(prob, x, y, s)
    R, lam = round_to_rotations(X)
    rank = numerical_rank(lam)
    lower_bound = lb_scaled * scale
    sdp_value = float(-np.sum(C * X.reshape(vg.n_cameras, 3, vg.n_cameras, 3)
                              .transpose(0, 2, 1, 3)[vg.edges[:, 1], vg.edges[:, 0]])) * scale
    primal_cost = edge_cost(vg.edges, C, R) * scale
    gap = relative_gap(primal_cost, lower_bound)
    gap_abs = primal_cost - lower_bound
    return {
        "solver": solver, "form": form, "R": R, "rank": rank,
        "eigenvalues": [float(v) for v in lam[:6]],
        "lower_bound": lower_bound, "sdp_value": sdp_value, "primal_cost": primal_cost,
        "gap": gap, "gap_abs": gap_abs,
        # gap relative to the residual part of the cost rather than to |d*|, which the
        # constant −Σ tr M_e can dominate (one edge with a huge H); informative only.
        "gap_residual": float(gap_abs / max(primal_cost + offset, 1e-300)),
        "certified": bool(rank == 3 and gap < cert_tol), "status": status, "iterations": iters,
        "dual_lambda_min": lam_min_S, "build_s": t1 - t0, "solve_s": t2 - t1,
        "certificate_s": time.perf_counter() - t2,
        "n_variables": int(prob.A.shape[1]), "n_constraints": int(prob.A.shape[0]),
        "eps_abs": eps_abs, "eps_rel": eps_rel,
    }
