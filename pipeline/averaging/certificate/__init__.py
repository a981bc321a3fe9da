"""Dual certificate of global optimality for the final fixed-weight problem of IRLS / IRLS-H (issue 15, item 5).

Conventions (docs/CONVENTIONS.md): ``R_i`` cam_from_world, edge ``e = (i, j)``,
``i < j``, measures ``R̃_e ≈ R_j R_iᵀ``; ``Y = [R_1; …; R_N]`` (3N, 3) and ``Q_e = R_j R_iᵀ``.

The problem certified
---------------------
For fixed edge weights ``w_e ≥ 0`` and symmetric 3×3 edge metrics ``M_e`` (``M_e = I``:
isotropic; ``M_e = tr(H_e)/2·I − H_e``: paper 2, eq. 5)

    f(Y) = Σ_e 2 w_e (tr M_e − ⟨M_e R̃_e, R_j R_iᵀ⟩) = tr(Yᵀ L Y)                 (1)

with the (3N, 3N) connection Laplacian ``L``: off-diagonal blocks ``L_ji = −C_e``,
``L_ij = −C_eᵀ`` with ``C_e = w_e M_e R̃_e`` and diagonal blocks ``L_ii = Σ_{e∋i} w_e M_e``.
For ``M_e = I`` this is the weighted chordal cost ``Σ w_e ‖R_j − R̃_e R_i‖²_F``; for any
``M_e`` of paper 2's form it is ≥ 0 on SO(3) (paper 2, Corollary 1), so f is the
"residual" part of the cost, with no large constant.

Certificate (SE-Sync / Shonan style, Rosen et al. 2019; paper 2, §3–4.3)
----------------------------------------------------------------------
``Λ_i = sym((L Y)_i R_iᵀ)`` (the Lagrange multipliers of ``R_i R_iᵀ = I`` from the
first-order conditions) and ``S = L − blkdiag(Λ)``. Then, for every ``X ⪰ 0`` with
``X_ii = I`` (the SDP-O(3) relaxation, a fortiori every rotation set),

    tr(L X) = tr(S X) + Σ_i tr Λ_i ≥ 3N·λ_min(S) + f(Y),                          (2)

whatever Y is (``Σ tr Λ_i = tr(YᵀLY) = f(Y)``), so ``f(Y) − f* ≤ 3N·max(0, −λ_min(S))``.
``S ⪰ 0`` (``λ_min ≥ −η``) is the certificate; ``S Y = 0`` holds exactly at a
first-order critical point (``S Y`` is the Riemannian gradient, reported).

Anisotropic costs (IRLS-H): paper 2, Theorem 1 shows that with indefinite ``M_e`` the
O(3) relaxation is not tight, so (2) alone cannot certify. Paper 2's SDP-cSO(3) adds
``𝒜(X_ji) + I ⪰ 0`` per edge; its multipliers ``W_e ⪰ 0`` with complementary slackness
``W_e q̂_e = 0`` enter the Lagrangian as ``C_e → C_e + 𝒜*(W_e)``. We established (and
test, ``test_certificate.py::test_lmi_multiplier_identity``) that

    {𝒜*(W) Q_eᵀ : W ⪰ 0, W q̂(Q_e) = 0} = {−2·𝓜(V) : V ⪰ 0},  𝓜(V) = tr(V)/2·I − V,

with ``tr W = tr V``: the LMI multipliers may lower each edge's effective H by any PSD
``2V_e`` (in the frame of ``Q_e``) without changing the gradient. We choose the smallest
``V_e`` that makes the edge's effective weight ``sym(C_e Q_eᵀ) − 2𝓜(V_e)`` PSD
(``V_e = ½ max(0, η₁ − η₂ − η₃) u₁u₁ᵀ`` for the eigenpairs of its effective H), and the
same bound (2) holds over the SDP-cSO(3) feasible set. A verified anisotropic
certificate therefore proves Y globally optimal for (1) and SDP-cSO(3) tight.

Deciding ``S ⪰ −ηI`` (``min_eigenvalue``): one sparse LDLᵀ of ``S + ηI`` (SuperLU,
symmetric mode, diagonal pivots only, symmetric permutation checked): by Sylvester's law
of inertia the number of negative pivots is the number of eigenvalues of S below −η.
The same factor then drives a shift-invert Lanczos (``eigsh`` with ``OPinv``) on the
complement of ``span(Y)`` for the first non-trivial eigenvalue (the margin). When negative
pivots appear, Lanczos on S (smallest algebraic) returns the negative eigenpair, whose
Rayleigh quotient is an explicit witness.

Where S's own factor would be dense (a 1DSfM graph, an unordered collection's random pairs) and the cost is IRLS's
isotropic one (no M given), a perturbation bound is tried first (:mod:`~.bound`): S is the consistent problem's
connection Laplacian at Y (positive semidefinite, null space ``span(Y)``, spectrum that of the weighted graph's
Laplacian) plus a perturbation as small as the weighted residuals; after a diagonal scaling by the weighted degrees,
one dense Cholesky of an N×N matrix (instead of S's 3N×3N) proves the normalized Laplacian's λ₂ above the
perturbation's norm, and with it ``S ≻ −ηI``. Where it cannot (a ring's small λ₂, residuals as large as the graph's
connectivity, a point far from stationary), the inertia decides as above.

Tolerances (``certify``): ``η = (gap_tol · f(Y) + f_floor) / (3N)`` so that "verified"
means a relative suboptimality ≤ ``gap_tol`` by (2), where ``f_floor = 1e3·ε·Σ_i tr L_ii``
is the rounding level of f itself (exact data: f(Y) ≈ 1e-14 is 0); η is raised to a
numerical floor ``η_num = 1e3·ε·‖S‖₁`` (the accuracy of the LDLᵀ inertia), and if that
floor makes the bound exceed the target the verdict is "could not decide".
"not verified" requires an explicit eigenvector with Rayleigh quotient below
``−max(η, ‖S Y‖_F/√N)``: by a Schur-complement argument (with ``Q = Y/√N``, ``QᵀSQ = 0``,
``‖P⊥SQ‖ ≤ ‖SY‖_F/√N``), S restricted to ``span(Y)⊥`` then has a negative direction, so
the failure is not an artefact of an inexact stationary point. What that proves is that the
relaxation goes lower than Y; that a lower-cost set of rotations exists follows only where the
relaxation is tight, so the statement names both possibilities (a local minimum, or a relaxation
that is not tight for this cost). That holds only where every multiplier is fixed by
stationarity, i.e. for isotropic metrics. For anisotropic ones the conv(SO(3)) multipliers
``V_e`` are this certificate's choice, and a failure refutes the choice, not the point: the
verdict is then "could not decide" (SDP-cSO(3), which optimizes them, decides that cost; on
templeSparseRing it certifies a point this test fails on). Everything in between is "could
not decide".

What a "verified" answer proves for IRLS: the polished rotations are
the global minimizer, over all of SO(3)^N (indeed O(3)^N and the SDP), of the fixed-weight
chordal problem (1) with the weights IRLS ended with. It does not prove optimality of
the robust cost Σρ(θ_e), nor that IRLS chose the right weights (a wrongly trimmed edge
set is still "verified" if the kept edges are fitted globally).

Layout: :mod:`~.problem` (the Laplacian, multipliers, LMI terms), :mod:`~.eigen` (the
inertia test), :mod:`~.newton` (the polish), :mod:`~.certify` (the verdict and statement).
"""

from pipeline.averaging.certificate.certify import (NOT_VERIFIED, UNDECIDED, VERIFIED, Certificate, certify,
                                                    certify_weights)
from pipeline.averaging.certificate.problem import chordal_weights, metric_from_H

__all__ = ["Certificate", "certify", "certify_weights", "chordal_weights", "metric_from_H", "VERIFIED",
           "NOT_VERIFIED", "UNDECIDED"]
