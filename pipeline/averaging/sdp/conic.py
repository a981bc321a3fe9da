"""The SDPs of paper 2 as sparse conic programs ``(A, b, c, K)`` for SCS and Clarabel.

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
into a rigorous lower bound (:func:`pipeline.averaging.sdp.solve.extract`). The readable primal
statement is :mod:`pipeline.averaging.sdp.cvxpy_ref`; the tests check all reach the same optimum.

Assembly is vectorized index arithmetic over edges (no Python loop over edges).
Each solver's svec convention is handled by :func:`svec_index`:

* SCS: lower triangle, column-major, off-diagonal entries scaled by √2;
* Clarabel: upper triangle, column-major (= lower triangle row-major), √2 scaling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pipeline.averaging.sdp.certificate import weight_matrices
from pipeline.core.errors import ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["VARIANTS", "SOLVERS", "ConicProblem", "build_conic", "edge_weights", "svec_index", "unsvec",
           "conv_so3_lmi", "check_inputs"]

#: variant -> (anisotropic cost, conv(SO(3)) constraints)
VARIANTS: dict[str, tuple[bool, bool]] = {
    "o3-iso": (False, False),
    "o3-aniso": (True, False),
    "cso3-iso": (False, True),
    "cso3": (True, True),
}
SOLVERS = ("scs", "clarabel")
SQRT2 = np.sqrt(2.0)

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


def check_inputs(vg: ViewGraph, variant: str, solver: str) -> tuple[bool, bool]:
    """``(anisotropic, cso3)`` of ``variant`` after checking it, ``solver`` and the graph.

    Raises:
        ValueError: unknown variant or solver.
        ViewGraphError: an anisotropic variant without H, fewer than 2 cameras or
            no edge, a disconnected graph.
    """
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
            "(pipeline.averaging.average does this) and solve each component separately"
        )
    return aniso, cso3
