"""The certificate's verdict: :class:`Certificate`, :func:`certify` and :func:`certify_weights` (for IRLS results)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from pipeline.averaging.certificate.bound import perturbation_bound
from pipeline.averaging.certificate.eigen import min_eigenvalue
from pipeline.averaging.certificate.newton import polish
from pipeline.averaging.certificate.problem import (certificate_matrix, chordal_weights, connection_laplacian,
                                                    diag_blocks, lagrange_multipliers, lmi_apply, lmi_ascent,
                                                    lmi_multipliers, rounding_floor, sym)
from pipeline.averaging.kernel import DENSE_PATTERN
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["Certificate", "certify", "certify_weights", "VERIFIED", "NOT_VERIFIED", "UNDECIDED"]

VERIFIED = "verified"
NOT_VERIFIED = "not verified"
UNDECIDED = "could not decide"
#: Share of the cost's resolution (the cost of one standard error) the proven gap may reach.
KAPPA = 0.01
#: Eigenvalue tests the search for better conv(SO(3)) multipliers may take when the smallest ones leave a negative
#: direction (:func:`~.problem.lmi_ascent`; only anisotropic costs).
LMI_ASCENT_EVALS = 24
#: Eigenvectors of the negative eigenvalues the search moves together.
LMI_WITNESSES = 6


@dataclass
class Certificate:
    """Verdict and the numbers behind it (all costs in the units of (1)).

    Attributes:
        verdict: "verified", "not verified" or "could not decide".
        cost: f(Y) of (1) at the certified rotations.
        lambda_min: estimate of λ_min(S): 0 when S ⪰ −ηI (the Y directions), else the
            Rayleigh quotient of the negative witness (an upper bound on λ_min).
        lambda_min_lower: proven lower bound −η on λ_min(S) (NaN unless S ⪰ −ηI).
        lambda_nontrivial: smallest eigenvalue of S on span(Y)⊥ found near 0 (the margin;
            > 0 means X = YYᵀ is the unique SDP solution).
        n_below: eigenvalues of S below −η (inertia).
        eta, eta_numerical: tolerance used and its numerical floor.
        gap_bound, rel_gap_bound: proven bound on f(Y) − f* (absolute, relative to f(Y)).
        stationarity, stationarity_bound: ‖SY‖_F and ‖SY‖_F/√N.
        lmi_edges, lmi_trace: edges whose weight the conv(SO(3)) multipliers changed, Σ tr W_e.
        lmi_steps: supergradient steps taken on those multipliers (:func:`~.problem.lmi_ascent`).
        polish: Newton polish report (iterations, max_move_rad, ...).
        times: seconds per step; ``total_s``.
        message: why "could not decide" (or solver notes).
        witness_cameras: cameras carrying most of the negative eigenvector ("not verified").
    """

    verdict: str
    cost: float
    lambda_min: float
    lambda_min_lower: float
    lambda_nontrivial: float
    n_below: int
    eta: float
    eta_numerical: float
    gap_bound: float
    rel_gap_bound: float
    gap_tol: float
    stationarity: float
    stationarity_bound: float
    n_cameras: int
    n_edges: int
    n_weighted_edges: int
    lmi_edges: int
    lmi_trace: float
    polish: dict[str, Any]
    times: dict[str, float]
    message: str = ""
    witness_cameras: list[int] = field(default_factory=list)
    lmi_steps: int = 0

    def summary(self) -> str:
        return (f"{self.verdict}: λ_min(S) ≈ {self.lambda_min:.3g}, ≥ {self.lambda_min_lower:.3g} "
                f"(η {self.eta:.3g}; {self.n_below} eigenvalues below −η), "
                f"first non-trivial {self.lambda_nontrivial:.3g}, f(Y) {self.cost:.6g}, "
                f"gap ≤ {self.gap_bound:.3g} ({self.rel_gap_bound:.2g} rel.), ‖SY‖ {self.stationarity:.2g}, "
                f"{self.times.get('total_s', np.nan):.3f} s")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["polish"] = {k: v for k, v in self.polish.items() if k != "history"}
        return d


def certify(n: int, edges: np.ndarray, R_rel: np.ndarray, R: np.ndarray, w: np.ndarray,
            M: np.ndarray | None = None, *, gap_tol: float = 1e-6, do_polish: bool | str = "auto",
            use_lmi: bool | None = None, polish_iterations: int = 20, k_margin: int = 1, fills: bool | None = None
            ) -> tuple[Certificate, np.ndarray]:
    """Certify (or refute) global optimality of R for the fixed-weight problem (1).

    ``do_polish="auto"`` (default) first tests R as given (bound (2) needs no stationarity) and
    polishes and tests again only if that is not "verified"; ``True`` always polishes first;
    ``False`` never does. See :func:`_certify_once` for the other arguments.
    """
    if do_polish == "auto":
        cert, Rc = _certify_once(n, edges, R_rel, R, w, M, gap_tol=gap_tol, do_polish=False, use_lmi=use_lmi,
                                 polish_iterations=polish_iterations, k_margin=k_margin, fills=fills)
        if cert.verdict == VERIFIED:
            return cert, Rc
        t_first = cert.times.get("total_s", 0.0)
        cert, Rc = _certify_once(n, edges, R_rel, R, w, M, gap_tol=gap_tol, do_polish=True, use_lmi=use_lmi,
                                 polish_iterations=polish_iterations, k_margin=k_margin, fills=fills)
        cert.times["unpolished_attempt_s"] = t_first
        cert.times["total_s"] += t_first
        return cert, Rc
    return _certify_once(n, edges, R_rel, R, w, M, gap_tol=gap_tol, do_polish=bool(do_polish), use_lmi=use_lmi,
                         polish_iterations=polish_iterations, k_margin=k_margin, fills=fills)


def _certify_once(n: int, edges: np.ndarray, R_rel: np.ndarray, R: np.ndarray, w: np.ndarray,
                  M: np.ndarray | None = None, *, gap_tol: float = 1e-6, do_polish: bool = True,
                  use_lmi: bool | None = None, polish_iterations: int = 20, k_margin: int = 1,
                  fills: bool | None = None) -> tuple[Certificate, np.ndarray]:
    """Certify (or refute) global optimality of R for the fixed-weight problem (1).

    Args:
        n: number of cameras N.
        edges: (M, 2) ``(i, j)``, i < j.
        R_rel: (M, 3, 3) measurements ``R̃_e``.
        R: (N, 3, 3) candidate rotations (e.g. the IRLS output).
        w: (M,) weights ≥ 0 (0: edge ignored).
        M: (M, 3, 3) symmetric edge metrics (None: isotropic, M = I).
        gap_tol: relative suboptimality accepted as "verified".
        do_polish: first refine R by Newton on (1) (a critical point makes the test sharp).
        use_lmi: apply the conv(SO(3)) LMI multipliers (default: only when M is given).
        polish_iterations: Newton iteration cap.
        k_margin: non-trivial eigenvalues to report near 0.
        fills: whether the graph's sparse factor fills, when the caller's averaging knows (its factorizer's
            ``fills``): the certificate's matrices are then factored densely (:func:`~.eigen.ldl_inertia`).

    Returns:
        (Certificate, the rotations that were certified: polished R or R itself).
    """
    t0 = time.perf_counter()
    edges = np.asarray(edges, dtype=np.int64)
    w = np.asarray(w, dtype=np.float64)
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights must be finite and >= 0")
    keep = w > 0
    e, Rt, ww = edges[keep], np.asarray(R_rel, float)[keep], w[keep]
    if M is None:
        Mk = np.broadcast_to(np.eye(3), (e.shape[0], 3, 3))
        if use_lmi is None:
            use_lmi = False
    else:
        Mk = sym(np.asarray(M, float)[keep])
        if use_lmi is None:
            use_lmi = True
    # Isotropic edge metrics (M_e ∝ I): the certificate's multipliers are all fixed by stationarity.
    iso_part = np.trace(Mk, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
    isotropic = M is None or not len(Mk) or bool(np.all(np.abs(Mk - iso_part) <= 1e-9 * np.abs(iso_part).max()))
    WM = ww[:, None, None] * Mk
    C = WM @ Rt
    D = diag_blocks(n, e, WM)
    times: dict[str, float] = {}
    pinfo: dict[str, Any] = {"iterations": 0}
    if do_polish:
        t = time.perf_counter()
        R, pinfo = polish(n, e, C, D, R, max_iterations=polish_iterations, fills=fills)
        times["polish_s"] = time.perf_counter() - t
    t = time.perf_counter()
    Y = R.reshape(3 * n, 3)
    L_cost = connection_laplacian(n, e, C, D)
    cost = float(np.einsum("ab,ab->", Y, (L_cost @ Y)))
    eps = np.finfo(float).eps
    # f(Y) is a difference of terms of size Σ_i tr D_i; below this it is rounding noise.
    cost_floor = 1e3 * eps * float(np.abs(np.trace(D, axis1=1, axis2=2)).sum())
    target = gap_tol * max(cost, 0.0) + cost_floor
    n_witness = LMI_WITNESSES if use_lmi and not isotropic else 1

    def test(V: np.ndarray | None) -> tuple[Any, ...]:
        """With the multipliers V (None: none): SY's blocks, S's rounding floor, η, and S ⪰ −ηI decided."""
        L = L_cost if V is None else connection_laplacian(n, e, lmi_apply(e, C, R, V), D)
        Lam, G_v = lagrange_multipliers(L, R)
        S_v = certificate_matrix(L, Lam)
        floor = rounding_floor(S_v)
        eta_v = max(target / (3 * n), floor)
        if V is None and M is None and k_margin == 0 and (S_v.nnz > DENSE_PATTERN * (3 * n) ** 2 if fills is None
                                                          else fills):
            # S's own factor would be dense: a bound from the consistent problem decides with an N×N factor (its
            # weights are ww: M = I; an M given, even ∝ I, keeps the inertia)
            bound = perturbation_bound(n, e, ww, Rt, R, Lam, G_v, S_v, eta_v)
            if bound is not None:
                return G_v, floor, eta_v, bound
        return G_v, floor, eta_v, min_eigenvalue(S_v, Y, eta_v, k_margin=k_margin, fills=fills, n_witness=n_witness)

    V = lmi_multipliers(e, C, R) if use_lmi else None
    G, eta_num, eta, eig = test(V)
    times["build_s"] = time.perf_counter() - t - sum(eig.times.values())
    times.update(eig.times)
    stat = float(np.sqrt(np.square(G).sum()))
    stat_bound = stat / np.sqrt(n)
    steps = evals = 0
    # The conv(SO(3)) multipliers are the certificate's choice: where the smallest ones leave a negative direction,
    # better ones are searched for (λ_min is concave in them), as SDP-cSO(3)'s solver would: supergradient steps,
    # each the longest of 2, 8, 32, ... × Polyak's that still raises λ_min
    while (V is not None and not isotropic and eig.ok and eig.n_below > 0 and eig.witnesses is not None
           and evals < LMI_ASCENT_EVALS):
        steps += 1
        best = None
        for factor in 2.0 * 4.0 ** np.arange(LMI_ASCENT_EVALS - evals):
            evals += 1
            V_try = lmi_ascent(e, R, V, eig.witnesses, eig.lambda_min, factor)
            trial = (V_try, *test(V_try))
            times["lmi_ascent_s"] = times.get("lmi_ascent_s", 0.0) + sum(trial[-1].times.values())
            eig_try, last = trial[-1], (eig if best is None else best[-1]).lambda_min
            if not eig_try.ok or (eig_try.n_below > 0 and not eig_try.lambda_min > last):
                break  # longer steps raise λ_min no further
            best = trial
            if eig_try.n_below == 0:
                break
        if best is None:
            break  # no step raises λ_min: the last multipliers stand
        V, _, eta_num, eta, eig = best
    trV = np.zeros(0) if V is None else np.trace(V, axis1=1, axis2=2)
    lmi_edges, lmi_trace = int(np.sum(trV > 0)), float(trV.sum())
    msg = eig.message
    witness: list[int] = []
    if not eig.ok:
        verdict = UNDECIDED
        lam_lo = np.nan
        gap = np.nan
    elif eig.n_below == 0:
        lam_lo = -eta
        gap = min(max(cost, 0.0), 3 * n * eta)
        verdict = VERIFIED if gap <= target * (1 + 1e-12) else UNDECIDED
        if verdict == UNDECIDED:
            msg = (f"tolerance below numerical accuracy: η_num {eta_num:.3g} gives a gap bound {gap:.3g} "
                   f"> gap_tol·f + rounding {target:.3g}")
    else:
        lam_lo = eig.lambda_min
        gap = min(max(cost, 0.0), 3 * n * max(0.0, -eig.lambda_min))
        if eig.lambda_min < -max(eta, stat_bound) and not isotropic:
            # The Lagrange multipliers of R_iR_iᵀ = I are fixed by stationarity, but those of the
            # conv(SO(3)) LMIs are this certificate's own choice (lmi_multipliers): a negative
            # direction refutes that choice, not the point. SDP-cSO(3) optimizes them.
            verdict = UNDECIDED
            msg = (f"λ_min(S) = {eig.lambda_min:.3g} < 0 with this certificate's choice of the conv(SO(3)) "
                   f"multipliers ({steps} supergradient step(s) on them); for an anisotropic cost that refutes "
                   "nothing (SDP-cSO(3), which optimizes them fully, decides this cost)")
        elif eig.lambda_min < -max(eta, stat_bound):
            verdict = NOT_VERIFIED
            v = eig.witness.reshape(n, 3)
            mass = np.square(v).sum(axis=1)
            witness = [int(k) for k in np.argsort(-mass)[:10]]
        else:
            verdict = UNDECIDED
            msg = (f"λ_min {eig.lambda_min:.3g} is within what inexact stationarity explains "
                   f"(‖SY‖/√N {stat_bound:.3g}); polish further")
    times["total_s"] = time.perf_counter() - t0
    if eig.ok and eig.n_below == 0:
        # S Y = G ≈ 0 and YᵀSY = 0 exactly, so the Y directions have Rayleigh quotient 0:
        # λ_min(S) ∈ [−η, 0].
        lam_est, lam_lower = 0.0, -eta
    else:
        lam_est, lam_lower = float(eig.lambda_min), np.nan
    rel = float(gap / cost) if (cost > 0 and np.isfinite(gap)) else (0.0 if gap == 0 else np.nan)
    cert = Certificate(
        verdict=verdict, cost=cost, lambda_min=lam_est, lambda_min_lower=float(lam_lower),
        lambda_nontrivial=float(eig.lambda_nontrivial), n_below=eig.n_below, eta=float(eta),
        eta_numerical=float(eta_num), gap_bound=float(gap), rel_gap_bound=rel,
        gap_tol=gap_tol, stationarity=stat, stationarity_bound=float(stat_bound), n_cameras=n,
        n_edges=int(edges.shape[0]), n_weighted_edges=int(e.shape[0]), lmi_edges=lmi_edges, lmi_trace=lmi_trace,
        polish=pinfo, times=times, message=msg, witness_cameras=witness, lmi_steps=steps,
    )
    return cert, R


def certify_weights(vg: ViewGraph, R: np.ndarray, w: np.ndarray, kept: np.ndarray | None = None, *,
                    M: np.ndarray | None = None, chordal: bool | None = None, what: str = "the final weighted cost",
                    method: str = "IRLS", gap_tol: float | None = None, kappa: float = KAPPA,
                    k_margin: int = 0, theta: np.ndarray | None = None, fills: bool | None = None) -> dict[str, Any]:
    """The certificate of an IRLS result's final fixed-weight problem, JSON-ready, with its statement.

    Isotropic (``M`` None): IRLS's last step solves the geodesic problem ``Σ w_e θ_e²``;
    the chordal problem (1) with ``w_e θ_e / (2 sin θ_e)`` (:func:`chordal_weights`) has
    the same stationary points at ``R``, and is what is certified. Anisotropic (``M``: the
    edge metrics ``tr(P)/2·I − P`` of the final precisions ``P``): ``w`` as given.

    Args:
        vg: the connected view graph the result was computed on.
        R: (N, 3, 3) the result's rotations.
        w: (M,) the final problem's weights (≥ 0).
        kept: (M,) bool, the edges the result relies on (for the statement; default w > 0).
        M: (M, 3, 3) edge metrics, or None (isotropic).
        chordal: convert geodesic weights to chordal ones (default: when isotropic).
        what: the final problem in words ("the trimmed least-squares cost of IRLS-l0.5").
        method: who kept the edges ("IRLS-l0.5").
        gap_tol: relative suboptimality accepted as "verified"; None: ``kappa · ρ`` with the
            redundancy ``ρ = (N − 1)/(K − N + 1)`` of the K kept edges. A change of the
            rotations by one standard error costs about ``ρ f`` (χ² with 3(N − 1) against
            3(K − N + 1) degrees of freedom), so the default is a gap within ``kappa`` (1%)
            of that: the optimum is found to within ~10% of a standard error, the same
            criterion as the SDP's (:func:`pipeline.averaging.sdp.certificate.resolution_check`).
        kappa: see ``gap_tol``.
        k_margin: non-trivial eigenvalues near 0 to report (0: skip; they cost a Lanczos run).
        theta: (M,) the residual angles at ``R`` when the caller has them (radians).
        fills: whether the graph's sparse factor fills, when the caller's solver knows (:func:`certify`).

    Returns:
        :meth:`Certificate.to_dict` plus ``statement``, ``n_kept``, ``n_rejected``,
        ``rejected_min_residual_deg``, ``rejected_weight_ratio`` and ``max_move_deg``.
    """
    w = np.asarray(w, dtype=np.float64)
    if theta is None:
        theta = so3.angle_between(so3.relative(R, vg.edges), vg.R_rel)
    kept = (w > 0) if kept is None else np.asarray(kept, dtype=bool)
    if chordal is None:
        chordal = M is None
    wc = chordal_weights(theta, w) if chordal else w
    n_k, n_all = int(kept.sum()), vg.n_edges
    if gap_tol is None:
        gap_tol = max(kappa * (vg.n_cameras - 1) / max(n_k - vg.n_cameras + 1, 1), 1e-6)
    cert, Rc = certify(vg.n_cameras, vg.edges, vg.R_rel, R, np.maximum(wc, 0.0), M, gap_tol=gap_tol,
                       k_margin=k_margin, fills=fills)
    rej = ~kept
    rej_min = float(np.rad2deg(theta[rej].min())) if rej.any() else None
    med_kept = float(np.median(w[kept])) if kept.any() else 1.0
    ratio = float(w[rej].max() / med_kept) if rej.any() and med_kept > 0 else 0.0
    move = float(np.rad2deg(cert.polish.get("max_move_rad", 0.0))) if cert.polish.get("iterations") else 0.0
    edges = f"on {n_k} of {n_all} edges"
    if rej.any():
        edges += (f"; {int(rej.sum())} rejected by {method} (residuals from {rej_min:.2g}°, "
                  f"weights ≤ {ratio:.1g} of the kept median)")
    if cert.verdict == VERIFIED:
        head = f"verified: globally optimal for {what} {edges} (proven relative gap ≤ {cert.rel_gap_bound:.1g})"
        if move > 0:
            head += f"; certified after a Newton polish that moved the rotations by ≤ {move:.2g}°"
    elif cert.verdict == NOT_VERIFIED:
        # A negative direction of S off span(Y) proves that the convex relaxation goes lower than this
        # point; on SO(3)^N it proves nothing more unless the relaxation is tight for this cost.
        head = (f"NOT verified: not shown to be the global minimum of {what} {edges}: its convex relaxation "
                f"has a lower value (λ_min(S) = {cert.lambda_min:.3g} < 0, direction led by cameras "
                f"{[vg.names[k] for k in cert.witness_cameras[:5]]}), so either this point is a local minimum "
                "or the relaxation is not tight for this cost")
    else:
        head = f"could not decide whether this is the global minimum of {what} {edges}: {cert.message}"
    return {**cert.to_dict(), "statement": head + "; it proves optimality for that cost on that edge set, "
            "not accuracy", "n_kept": n_k, "n_rejected": int(rej.sum()), "rejected_min_residual_deg": rej_min,
            "rejected_weight_ratio": ratio, "max_move_deg": move}
