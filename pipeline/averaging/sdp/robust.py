"""The robust certified SDP: SDP-cSO(3) on the edges the robust stage keeps, with a certificate that says what it proves.

SDP-cSO(3) (paper 2) is a least-squares method. On castle-P30 (266 pairs, 46 more than
5° wrong, from the repeated walls of the courtyard) it returned 15° "certified": the
certificate was right (the global optimum of the anisotropic least-squares cost on
*all* edges) and misleading (that cost is the wrong one when edges are outliers). Here:

1. **The robust stage picks the edges** (``robust_method``): calibrated IRLS-H
   (anisotropic variants with H) or IRLS (isotropic). An edge is kept when its inlier
   posterior under the fitted t + Haar mixture is ≥ 0.5 (``keep="posterior"``), and with
   ``keep="weight"`` also when its normalized residual is ≤ 3 (with ν ≈ 1 the t tail
   keeps 10–70° edges as low-weight inliers, which a least-squares cost with the raw H
   must not see). If the kept edges do not connect the cameras, rejected edges are
   re-admitted by increasing residual until they do (a minimum spanning tree over the
   components; reported).
2. **The cost** on the kept edges (anisotropic variants, ``cost``): ``"calibrated"`` (the
   default), the robust stage's final precisions ``γ u P / s²`` (its metric P, inlier
   posterior γ, t-weight u, scale s), so that the SDP proves the robust answer the
   *global* optimum of its own final problem; or ``"raw"``, paper 2's cost with the
   two-view H. Isotropic variants use paper 2's isotropic cost (M = I).
3. **Certified** only when the rank is 3 and the gap is small against what the cost
   can resolve (:func:`pipeline.averaging.sdp.certificate.resolution_check`); an uncertified
   small problem is re-solved by Clarabel at 1e-12 (``fallback``).
4. **The statement** names the cost, the edge set and the rejected edges, e.g.
   "globally optimal for … on 234 of 266 edges; 32 rejected by irls-h (…; their
   residuals 78°–176°)". It proves optimality for that cost on that edge set, never
   accuracy.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import minimum_spanning_tree

from pipeline.averaging.calibration import shape_metric
from pipeline.averaging.irls import IRLSConfig, irls
from pipeline.averaging.irls_h import IRLSHConfig, irls_h
from pipeline.averaging.result import AveragingResult
from pipeline.averaging.sdp.conic import VARIANTS
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph

__all__ = ["solve_robust", "connect_kept", "T_MAX"]

logger = logging.getLogger(__name__)

#: ``keep="weight"``: largest normalized residual (in units of the fitted scale s) kept.
T_MAX = 3.0


def connect_kept(vg: ViewGraph, keep: np.ndarray, residual_rad: np.ndarray) -> tuple[np.ndarray, int]:
    """``keep`` (M,) made connected: rejected edges re-admitted by increasing residual (Kruskal).

    A minimum spanning tree with weight 1 on kept edges and ``2 + rank`` on rejected ones
    (rank by residual) contains a spanning forest of the kept edges and joins its pieces
    with the cheapest rejected edges, in the order Kruskal's algorithm takes them.

    Returns:
        The new mask and the number of edges re-admitted.
    """
    keep = np.asarray(keep, dtype=bool).copy()
    sub = ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep], allow_isolated=True)
    if sub.n_edges and sub.is_connected():
        return keep, 0
    rank = np.empty(vg.n_edges)
    rank[np.argsort(residual_rad, kind="stable")] = np.arange(vg.n_edges)
    w = np.where(keep, 1.0, 2.0 + rank)
    i, j = vg.edges.T
    T = minimum_spanning_tree(sp.coo_matrix((w, (i, j)), shape=(vg.n_cameras,) * 2).tocsr()).tocoo()
    key = vg.edges[:, 0] * vg.n_cameras + vg.edges[:, 1]
    tkey = np.minimum(T.row, T.col).astype(np.int64) * vg.n_cameras + np.maximum(T.row, T.col)
    in_tree = np.isin(key, tkey)
    added = in_tree & ~keep
    return keep | added, int(added.sum())


def _robust_stage(vg: ViewGraph, name: str) -> AveragingResult:
    if name == "irls-h":
        return irls_h(vg, IRLSHConfig(certify=False))
    return irls(vg, IRLSConfig(certify=False))


def _final_precisions(vg: ViewGraph, robust: AveragingResult) -> np.ndarray:
    """``w_e P_e`` (M, 3, 3): the precisions of the robust stage's final weighted problem."""
    sel = robust.stats.get("selected")
    P = shape_metric(vg, sel) if sel else np.broadcast_to(np.eye(3), (vg.n_edges, 3, 3))
    return np.asarray(robust.weights, dtype=np.float64)[:, None, None] * P


def solve_robust(vg: ViewGraph, cfg: Any, settings: dict[str, Any],
                 solve_fn: Callable[[ViewGraph, Any, dict[str, Any], np.ndarray], AveragingResult]) -> AveragingResult:
    """The SDP on the robust stage's edges (module docstring); ``solve_fn`` solves one SDP (``solve._solve``) from
    the robust stage's rotations (which, with ``certify_start``, are tested first)."""
    t0 = time.perf_counter()
    aniso = VARIANTS[cfg.variant][0]
    name = cfg.robust_method if cfg.robust_method != "auto" else ("irls-h" if aniso and vg.H is not None else "irls")
    robust = _robust_stage(vg, name)
    t_robust = time.perf_counter() - t0
    theta = so3.angle_between(so3.relative(robust.R, vg.edges), vg.R_rel)
    keep_rule = cfg.keep if cfg.keep != "auto" else ("weight" if aniso and cfg.cost == "raw" else "posterior")
    mask = np.ones(vg.n_edges, bool) if robust.kept is None else np.asarray(robust.kept, bool).copy()
    why = "inlier posterior < 0.5"
    if keep_rule == "weight":
        t = np.asarray(robust.stats.get("normalized_residuals"), dtype=np.float64)
        mask &= t <= T_MAX
        why += f" or normalized residual > {T_MAX:g}"
    mask, readmitted = connect_kept(vg, mask, theta)
    H, cost_desc = None, "paper 2's isotropic cost (M = I)"
    if aniso and cfg.cost == "calibrated":
        H = _final_precisions(vg, robust)
        metric = robust.stats.get("selected", "iso")
        cost_desc = f"the anisotropic cost with {robust.method}'s final precisions (metric {metric}, t-weights)"
    elif aniso:
        H, cost_desc = vg.H, "paper 2's anisotropic cost with the two-view H"
    sub = ViewGraph(vg.names, vg.edges[mask], vg.R_rel[mask], H=None if H is None else H[mask],
                    inliers=None if vg.inliers is None else vg.inliers[mask])
    res = solve_fn(sub, cfg, settings, robust.R)
    st = res.stats
    G = so3.project_to_so3(np.sum(np.swapaxes(robust.R, 1, 2) @ res.R, axis=0))  # the gauge: R_sdp ≈ R_robust G
    agree = float(np.rad2deg(so3.angle_between(res.R, robust.R @ G).max()))
    n_rej = int((~mask).sum())
    rej = np.rad2deg(theta[~mask])
    text = (f" on {sub.n_edges} of {vg.n_edges} edges" + (
        f"; {n_rej} rejected by {name} ({why}; their residuals {rej.min():.2g}°–{rej.max():.3g}°)" if n_rej
        else "; no edge rejected") + (f"; {readmitted} rejected edge(s) re-admitted to connect the cameras"
                                      if readmitted else ""))
    by = f" (proven by {st['certified_by']})" if st.get("certified_by") else ""
    head = f"globally optimal{by}" if st["certified"] else (
        f"NOT certified (rank {st['rank']}, gap {st['gap_vs_resolution']:.2g}× the cost's resolution, "
        f"{cfg.cert_kappa:g}× needed): a rounding of the relaxation, not a proven optimum")
    gap = (f"proven suboptimality ≤ {st['gap_abs']:.3g} = {st['gap_vs_resolution']:.2g} × the cost's resolution"
           if np.isfinite(st["gap_vs_resolution"]) else
           f"proven suboptimality ≤ {st['gap_abs']:.3g}; the cost's resolution is 0 (no redundant edge, or every edge "
           "fitted exactly)")
    if st["certified"] and np.isfinite(st["gap_vs_resolution"]) and st["gap_vs_resolution"] > cfg.cert_kappa:
        gap += (f" (the data are fitted exactly: within the cost's rounding {st['cost_rounding']:.3g})"
                if cfg.cert_kappa * st["resolution"] <= 0.01 * st["cost_rounding"] else
                f" (within {cfg.cert_kappa:g}× the resolution plus the cost's rounding level {st['cost_rounding']:.3g}, "
                "below which its value is not resolved)")
    # On the calibrated cost the SDP solves the robust stage's own final problem: its optimum within a
    # hair of the robust rotations certifies those too (where the IRLS certificate's fixed multipliers cannot).
    same = (f"; {robust.method}'s own rotations are within {agree:.2g}° of this optimum"
            if st["certified"] and aniso and cfg.cost == "calibrated" else "")
    statement = f"{head} for {cost_desc}{text}; {gap}{same}" + (
        "; it proves optimality for that cost on that edge set, not accuracy" if st["certified"] else "")
    logger.info("sdp-%s (robust edges): %s", cfg.variant, statement)
    residuals = so3.angle_between(so3.relative(res.R, vg.edges), vg.R_rel)
    stats = {**st, "edges": "robust", "robust_method": name, "robust_s": t_robust, "cost": cfg.cost if aniso else "iso",
             "keep": keep_rule, "n_kept": int(sub.n_edges), "n_rejected": n_rej, "n_readmitted": readmitted,
             "agreement_deg": agree,
             "certificate": {"certified": st["certified"], "statement": statement, "rank": st["rank"],
                             "gap_abs": st["gap_abs"], "resolution": st["resolution"],
                             "gap_vs_resolution": st["gap_vs_resolution"], "kappa": cfg.cert_kappa,
                             "relative_gap": st["gap"], "n_kept": int(sub.n_edges), "n_rejected": n_rej}}
    return AveragingResult(method=res.method, names=list(vg.names), R=res.R, time_s=time.perf_counter() - t0,
                           iterations=res.iterations, edge_index=np.arange(vg.n_edges), residuals_rad=residuals,
                           kept=mask, stats=stats)
