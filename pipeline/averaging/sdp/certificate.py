"""Certificate of an SDP rotation-averaging solution: rank, rounding, costs, gap, and the test it must pass.

Conventions (``../shared/DESIGN.md``): ``Y = [R_1; …; R_N]`` (3N, 3) stacks the
cam_from_world rotations and ``X = Y Yᵀ``, so the block ``X_ji = R_j R_iᵀ`` is the
relative rotation an edge ``(i, j)`` measures. The anisotropic cost (paper 2,
eq. 11, summed once per edge) is

    f(R) = −Σ_edges ⟨M_ij R̃_ij, R_j R_iᵀ⟩,   M_ij = tr(H_ij)/2 · I − H_ij  (eq. 5),

and the isotropic cost is the same with ``M_ij = I``. All costs here are in these
unscaled units (the solver works on a cost divided by a positive constant, see
:mod:`pipeline.averaging.sdp.solve`).
"""

from __future__ import annotations

import numpy as np

from pipeline.core import so3

__all__ = [
    "weight_matrices",
    "edge_cost",
    "numerical_rank",
    "round_to_rotations",
    "relative_gap",
    "resolution_check",
    "CERT_KAPPA",
    "COST_ROUNDING",
]

#: Fraction of the trace the leading eigenvalues must exceed (paper 2, footnote 3).
RANK_FRACTION = 0.999
#: Certified: the gap is at most this share of the cost's resolution (:func:`resolution_check`).
CERT_KAPPA = 0.01
#: The cost cannot be judged below its own rounding: 1e3·ε of Σ|tr M_e| (as the IRLS certificate).
COST_ROUNDING = 1e3 * np.finfo(float).eps


def weight_matrices(H: np.ndarray) -> np.ndarray:
    """Paper 2, eq. 5: ``M = tr(H)/2 · I − H``.

    Args:
        H: (M, 3, 3) precisions of the left perturbation ``Δω`` (1/rad²).

    Returns:
        (M, 3, 3) symmetric weights, in general indefinite (paper 2, Lemma 1).
    """
    H = np.asarray(H, dtype=np.float64)
    tr = np.trace(H, axis1=-2, axis2=-1)
    return 0.5 * tr[..., None, None] * np.eye(3) - H


def edge_cost(edges: np.ndarray, C: np.ndarray, R: np.ndarray) -> float:
    """``−Σ_e ⟨C_e, R_j R_iᵀ⟩`` for edge weights ``C_e = M_e R̃_e`` (paper 2, eq. 11).

    Args:
        edges: (M, 2) camera indices ``(i, j)``.
        C: (M, 3, 3) weighted measurements ``M_ij R̃_ij`` (``R̃_ij`` when isotropic).
        R: (N, 3, 3) cam_from_world rotations (or any 3×3 blocks).

    Returns:
        The cost, a float.
    """
    Rij = so3.relative(R, edges)
    return float(-np.sum(C * Rij))


def numerical_rank(eigvals: np.ndarray, fraction: float = RANK_FRACTION) -> int:
    """Smallest k whose k leading eigenvalues sum to more than ``fraction`` of the total.

    Paper 2, footnote 3. Negative eigenvalues (solver round-off on a PSD matrix)
    are clipped to 0 first.

    Args:
        eigvals: (n,) eigenvalues of the PSD solution, any order.
        fraction: share of the trace to exceed, 0.999 in the paper.

    Returns:
        The rank, between 1 and n (0 for an all-zero input).
    """
    lam = np.sort(np.clip(np.asarray(eigvals, dtype=np.float64), 0.0, None))[::-1]
    total = lam.sum()
    if total <= 0:
        return 0
    csum = np.cumsum(lam)
    return int(min(np.searchsorted(csum, fraction * total, side="right") + 1, lam.size))


def round_to_rotations(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Round an SDP solution to rotations (DESIGN.md, "Rank and rounding").

    1. ``V`` = top-3 eigenvectors of ``X`` scaled by √λ, so ``X ≈ V Vᵀ``.
    2. ``V`` is defined up to a right 3×3 orthogonal factor; flip its sign when
       most 3×3 blocks have a negative determinant (a sign flip of V negates every
       block's determinant), so the blocks are close to SO(3) rather than O(3)∖SO(3).
    3. Project each block onto SO(3).

    The result is ``R_i G`` for an unknown global rotation ``G``: the gauge of
    cam_from_world rotations, which every ``X_ji = R_j R_iᵀ`` is blind to.

    Args:
        X: (3N, 3N) symmetric PSD solution with identity diagonal blocks.

    Returns:
        R: (N, 3, 3) rotations.
        eigvals: (3N,) eigenvalues of ``X`` in decreasing order.
    """
    X = np.asarray(X, dtype=np.float64)
    n = X.shape[0]
    if X.ndim != 2 or X.shape != (n, n) or n % 3:
        raise ValueError(f"X.shape={X.shape} but expected (3N, 3N)")
    lam, U = np.linalg.eigh(0.5 * (X + X.T))
    lam, U = lam[::-1], U[:, ::-1]
    V = U[:, :3] * np.sqrt(np.clip(lam[:3], 0.0, None))
    blocks = V.reshape(n // 3, 3, 3)
    if np.sum(np.linalg.det(blocks) > 0) < 0.5 * blocks.shape[0]:
        blocks = -blocks
    return so3.project_to_so3(blocks), lam


def relative_gap(primal_cost: float, lower_bound: float) -> float:
    """Relative duality gap ``(f(R̂) − d*) / |d*|``.

    ``f(R̂)`` is the cost at the rounded rotations and ``d*`` the SDP lower bound,
    both in the same (unscaled) units; the gap is ≥ 0 up to solver accuracy and
    near 0 exactly when the relaxation is tight and the rounding recovered its
    minimizer.
    """
    return float((primal_cost - lower_bound) / max(abs(lower_bound), 1e-300))


def resolution_check(gap_abs: float, primal_cost: float, offset: float, n_cameras: int, n_edges: int, rank: int,
                     kappa: float = CERT_KAPPA) -> dict[str, float | bool]:
    """Is the gap small against the accuracy the cost can resolve? (``certified`` of every SDP solve).

    ``f_res = f(R̂) + Σ tr M_e ≥ 0`` is the part of the cost the rotations change; with the
    redundancy ``ρ = (N − 1)/(M − N + 1)``, moving the rotations by one standard error costs
    about ``ρ · f_res`` (a χ² with 3(N − 1) degrees of freedom against 3(M − N + 1) for the
    residual), the cost's *resolution*. A rank-3 solution is certified when its gap is at
    most ``kappa`` (1%) of that, i.e. within ~10% of a standard error (the cost is
    quadratic there): ``gap_residual ≤ kappa · ρ``. The relative gap ``gap/|d*|`` cannot
    tell: ``|d*| ≈ Σ tr M_e``, which one edge with a huge H makes as large as it likes (a
    noise-free 5-camera graph with one H 1e5× the others: SCS 6.13° off at a relative gap
    of 5e-7). Below the rounding of the cost itself (:data:`COST_ROUNDING` of ``|offset|``)
    nothing can be told apart, so that much gap is always allowed; exact data, whose
    resolution is 0, are certified only when solved to that rounding.

    Returns:
        ``{"certified", "resolution", "gap_vs_resolution", "gap_residual", "cost_rounding"}``.
    """
    f_res = max(float(primal_cost + offset), 0.0)
    resolution = (n_cameras - 1) / max(n_edges - n_cameras + 1, 1) * f_res
    ratio = gap_abs / resolution if resolution > 0 else float("inf")
    floor = COST_ROUNDING * abs(offset)
    return {"certified": bool(rank == 3 and gap_abs <= kappa * resolution + floor), "resolution": resolution,
            "gap_vs_resolution": float(ratio), "gap_residual": float(gap_abs / max(f_res, 1e-300)),
            "cost_rounding": floor}
