"""The checks of a view graph before averaging: which pairs it keeps, and why each other pair goes.

:func:`check_view_graph` is a pure function on a :class:`ViewGraph` with H (the two-view
BA's). In order:

1. evidence tiers (:mod:`pipeline.graph.tiers`): gates on inliers, inlier ratio and the
   conditioning of H; strong, normal and provisional pairs;
2. co-location (:func:`~pipeline.graph.loops.colocation_check`): a small-baseline pair's claim
   that its cameras share a centre, tested by third cameras;
3. short cycles (:func:`~pipeline.graph.loops.cycle_filter`): triangles and 4-cycles, the
   edge most cycles disagree with removed first, with per-edge σ = ``max(σ_weak, sigma_floor_deg)``;
4. longer cycles (:func:`~pipeline.graph.loops.cycle_check`): each edge in no short cycle
   against the cheapest other path, σ = ``max(h_inflation·σ_weak, sigma_floor_deg)`` (an edge
   whose short cycles are inconsistent is not confirmed by a longer, looser one);
5. pairs still unconfirmed are dropped unless strong (provisional ones always), except
   where dropping would lose cameras: an unconfirmed *standalone* pair (strong but for its
   parallax: a pan on the spot, a low-parallax step) whose two cameras the kept pairs leave in
   different components is kept (``keep_bridges``), and :func:`pipeline.graph.flags.graph_flags`
   flags the cameras it joins. A walk that turns on the spot (a rendered street's 30° pan
   steps, each view overlapping only its two neighbours) is joined only by such pairs;
   dropping them split a 300-view street in two halves of 148;
6. the robust solution: IRLS-ℓ½ on each component of the kept graph, with the pairs step 5
   dropped as unconfirmed weighed too (``robust_unconfirmed``); a kept edge whose residual
   exceeds ``max(robust_floor_deg, robust_k_sigma·h_inflation·σ_weak)`` is rejected. It sees
   what only long cycles see (a repeated structure's pair whose cycles it makes consistent).

What they did (research r13-lowtex, 8 rendered low-texture scenes, temple, castle-P30):
castle-P30's 46 pairs > 5° off were all removed by steps 3–6 alone, 2 good ones lost (12
with triangles only); the gates remove most wrong pairs on weak data. The thresholds are
trade-offs measured there, not tuned on a benchmark's truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from pipeline.core.config import Config, option
from pipeline.core.errors import ConfigError
from pipeline.core.viewgraph import ViewGraph
from pipeline.graph.loops import colocation_check, cycle_check, cycle_filter
from pipeline.graph.tiers import evidence_tiers, pair_evidence

__all__ = ["ViewGraphConfig", "GraphChecks", "check_view_graph", "REJECTION_STEPS"]

REJECTION_STEPS = ("acceptance", "colocation", "cycles", "path", "unconfirmed", "robust")


@dataclass(frozen=True, kw_only=True)
class ViewGraphConfig(Config):
    """Options of the view-graph stage (YAML section ``viewgraph``): its checks (module docstring)."""

    SECTION = "viewgraph"

    checks: bool = option(True, "accept pairs by their evidence and the graph's cycles (false: every pair, as before)")
    min_inliers: int = option(15, "gate: RANSAC inliers among the putative matches (COLMAP: 15)", ge=5)
    min_inlier_ratio: float = option(0.25, "gate: inliers / matches (COLMAP: 0.25)", ge=0, le=1)
    provisional_min_inliers: int = option(12, "pairs with this many inliers, fewer than min_inliers, are kept only "
                                              "when a cycle confirms them", ge=5)
    h_inflation: float = option(3.0, "H's overconfidence on real images: σ_weak = 1/√λ_min(H) is multiplied by it",
                                gt=0)
    max_sigma_deg: float = option(3.0, "gate: h_inflation·σ_weak at most this, degrees", gt=0)
    strong_min_inliers: int = option(30, "strong pair (kept unconfirmed): inliers", ge=0)
    strong_min_ratio: float = option(0.4, "strong pair: inlier ratio", ge=0, le=1)
    strong_max_sigma_deg: float = option(3.0, "strong pair: h_inflation·σ_weak at most this, degrees", gt=0)
    strong_max_cond: float = option(50.0, "strong pair: √(λ_max/λ_min) of H at most this", gt=0)
    min_parallax_deg: float = option(5.0, "strong pair: median triangulation angle at least this, degrees", ge=0)
    keep_bridges: bool = option(True, "keep a pair confirmed by no cycle, strong but for its parallax, where it alone "
                                      "joins cameras to the rest (they are flagged); false: drop it, and them")
    wide_parallax_deg: float = option(75.0, "weak or strong pairs whose rays meet at more than this are not kept "
                                            "(confirmed normal pairs are)", gt=0)
    max_cycle_length: int = option(4, "short cycles checked: 3 (triangles) or 4 (also 4-cycles)", ge=3, le=4)
    max_four_cycles: int = option(2_000_000, "budget of 4-cycles (dense graphs of thousands of cameras have "
                                             "millions): beyond it each diagonal keeps its first few", ge=0)
    cycle_k_sigma: float = option(3.0, "a cycle is consistent when its angle <= k·κ·σ_C", gt=0)
    cycle_min_deg: float = option(1.0, "a cycle below this angle is always consistent, degrees", ge=0)
    cycle_max_deg: float = option(10.0, "a cycle above this angle is never consistent, degrees", gt=0)
    confirm_max_deg: float = option(5.0, "a camera with a pair that only cycles (or paths) closing above this confirm "
                                         "is flagged: such agreement does not vouch for a degree or two, degrees",
                                    gt=0)
    max_bad_fraction: float = option(0.5, "an edge is removed when more than this share of its cycles is bad", ge=0,
                                     lt=1)
    sigma_floor_deg: float = option(0.5, "floor of every edge's σ, degrees (H is most overconfident where strongest)",
                                    gt=0)
    path_k_sigma: float = option(3.0, "an edge in no short cycle is consistent with a path when within k·σ", gt=0)
    path_min_deg: float = option(2.0, "... or within this many degrees", ge=0)
    path_max_deg: float = option(15.0, "paths whose threshold would exceed this check nothing, degrees", gt=0)
    colocation_max_deg: float = option(10.0, "a small-baseline pair whose third cameras see its two centres this "
                                             "far apart (median, degrees) is rejected", gt=0)
    colocation_min_parallax_deg: float = option(3.0, "a third camera witnesses a small-baseline pair only through "
                                                     "pairs with at least this median triangulation angle, degrees",
                                                ge=0)
    robust_filter: bool = option(True, "reject the edges the robust solution (IRLS-ℓ½) leaves far off")
    robust_floor_deg: float = option(5.0, "robust filter: reject residuals above max(this, k·h_inflation·σ_weak)",
                                     gt=0)
    robust_k_sigma: float = option(4.0, "robust filter: k", gt=0)
    robust_unconfirmed: bool = option(True, "robust filter: its solution also weighs the pairs dropped only as "
                                            "unconfirmed (never judged by it, never kept by it)")
    components: int = option(8, "connected components solved, largest first, each in its own frame: the largest in "
                                "OUT, the k-th in OUT/component-k/ (1: the largest only)", ge=1)
    min_component_images: int = option(3, "a component of fewer images is left out (with why), not solved", ge=2)

    def check(self) -> None:
        if self.provisional_min_inliers > self.min_inliers:
            raise ConfigError(f"[viewgraph] provisional_min_inliers={self.provisional_min_inliers} but expected <= "
                              f"min_inliers={self.min_inliers}")
        if self.cycle_min_deg > self.cycle_max_deg:
            raise ConfigError(f"[viewgraph] cycle_min_deg={self.cycle_min_deg} but expected <= "
                              f"cycle_max_deg={self.cycle_max_deg}")


@dataclass
class GraphChecks:
    """Result of :func:`check_view_graph`, per edge of the input graph (all (M,)).

    Attributes:
        kept: the edges averaging may use.
        reason: why an edge was rejected ("" if kept).
        step: the step that rejected it (one of :data:`REJECTION_STEPS`, "" if kept).
        tier: "strong", "normal", "provisional" or "" (not a candidate).
        confirmed: kept edges in a consistent cycle (short, or a longer path).
        inconsistent: edges rejected because they disagree with the others (steps 2–4, 6).
        bridged: kept edges confirmed by no cycle that step 5 kept only because they join cameras to the rest.
        info: counts and figures of each step (JSON-ready).
        confirm_deg: how closely each confirmed edge is checked, degrees: the angle of its tightest consistent
            short cycle, or its disagreement with the path that confirmed it (inf: not confirmed).
    """

    kept: np.ndarray
    reason: np.ndarray
    step: np.ndarray
    tier: np.ndarray
    confirmed: np.ndarray
    inconsistent: np.ndarray
    bridged: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)
    confirm_deg: np.ndarray | None = None


def _reject(chk: GraphChecks, mask: np.ndarray, step: str, why: Callable[[np.ndarray], list[str]] | np.ndarray) -> int:
    """Reject the kept edges of ``mask`` at ``step``; ``why(indices)`` words the reasons (only theirs)."""
    mask = mask & chk.kept
    idx = np.flatnonzero(mask)
    chk.reason[idx] = why(idx) if callable(why) else np.asarray(why, object)[idx]
    chk.step[idx] = step
    chk.kept = chk.kept & ~mask
    if step != "unconfirmed" and step != "acceptance":
        chk.inconsistent |= mask
    return int(mask.sum())


def check_view_graph(vg: ViewGraph, config: ViewGraphConfig | None = None) -> GraphChecks:
    """Every check of the module docstring on ``vg`` (pure function)."""
    cfg = config or ViewGraphConfig()
    M, N = vg.n_edges, vg.n_cameras
    ev = pair_evidence(vg)
    tiers = evidence_tiers(ev, cfg)
    tier = np.where(tiers.strong, "strong", np.where(tiers.provisional, "provisional",
                                                     np.where(tiers.candidate, "normal", ""))).astype(object)
    chk = GraphChecks(np.ones(M, bool), np.full(M, "", object), np.full(M, "", object), tier, np.zeros(M, bool),
                      np.zeros(M, bool), np.zeros(M, bool))
    info: dict[str, Any] = {"n_pairs": M, "tiers": {t: int((tier == t).sum()) for t in ("strong", "normal",
                                                                                       "provisional")}}
    info["acceptance"] = _reject(chk, ~tiers.candidate, "acceptance", tiers.reason)
    sw = np.nan_to_num(ev.sigma_weak_deg, nan=cfg.sigma_floor_deg)
    t = np.asarray(vg.stats.get("t", np.ones((M, 3))), float).reshape(M, 3)
    n_wit, med, bad = colocation_check(vg.edges, vg.R_rel, t, ev.small_baseline, chk.kept, N, cfg.colocation_max_deg,
                                       witness=ev.triangulation_deg >= cfg.colocation_min_parallax_deg)
    info["colocation"] = _reject(chk, bad, "colocation", lambda ix: [
        f"its small baseline claims one camera centre; {n_wit[k]} third camera(s) see the two centres "
        f"{med[k]:.0f}° apart (median)" for k in ix])
    cf = cycle_filter(vg.edges, vg.R_rel, N, np.maximum(sw, cfg.sigma_floor_deg), max_len=cfg.max_cycle_length,
                      k_sigma=cfg.cycle_k_sigma, min_deg=cfg.cycle_min_deg, max_deg=cfg.cycle_max_deg,
                      max_bad_fraction=cfg.max_bad_fraction, active=chk.kept, max_four_cycles=cfg.max_four_cycles)
    info["cycles"] = _reject(chk, ~cf.kept, "cycles", lambda ix: [
        f"{cf.n_bad[k]} of its {cf.n_cycles[k]} short cycles are inconsistent" for k in ix])
    info["kappa2"], info["n_short_cycles"] = float(cf.kappa2), len(cf.cycles)
    confirmed = cf.confirmed.copy()
    sig_path = np.maximum(cfg.h_inflation * sw, cfg.sigma_floor_deg)
    # only edges in no short cycle: one whose short cycles disagree is not confirmed by a longer, looser one
    pc = cycle_check(vg.edges, vg.R_rel, N, chk.kept, chk.kept & ~confirmed & (cf.n_cycles == 0), sig_path, confirmed,
                     k_sigma=cfg.path_k_sigma, min_deg=cfg.path_min_deg, max_path_deg=cfg.path_max_deg)
    info["path"] = _reject(chk, pc.checked & ~pc.consistent & pc.path_confirmed, "path", lambda ix: [
        f"disagrees by {pc.discrepancy_deg[k]:.1f}° (threshold {pc.threshold_deg[k]:.1f}°) with the path of "
        f"{pc.path_length[k]} confirmed pairs between its cameras" for k in ix])
    by_path = pc.checked & pc.consistent  # edges in no short cycle only: none has a cycle's figure
    confirmed |= by_path
    confirm_deg = cf.confirm_deg.copy()
    confirm_deg[by_path] = pc.discrepancy_deg[by_path]
    unconf = chk.kept & ~confirmed & ((tier != "strong") | tiers.provisional)
    info["unconfirmed"] = _reject(chk, unconf, "unconfirmed", np.where(
        tiers.provisional, "provisional (few inliers) and confirmed by no cycle",
        "confirmed by no cycle and not strong enough to stand alone").astype(object))
    if cfg.keep_bridges:
        chk.bridged = _keep_bridges(vg, chk, unconf & tiers.standalone & ~tiers.provisional)
    info["bridged"] = int(chk.bridged.sum())
    info["robust"] = _robust_filter(vg, chk, sw, cfg) if cfg.robust_filter else 0
    if chk.bridged.any():
        info["bridged_dropped"] = _drop_disputed_bridges(vg, chk)
    chk.confirmed = confirmed & chk.kept
    chk.bridged = chk.bridged & chk.kept
    chk.confirm_deg = np.where(chk.confirmed, confirm_deg, np.inf)
    info["n_kept"], info["n_confirmed"] = int(chk.kept.sum()), int(chk.confirmed.sum())
    chk.info = info
    return chk


def _keep_bridges(vg: ViewGraph, chk: GraphChecks, eligible: np.ndarray) -> np.ndarray:
    """Step 5's exception: the ``eligible`` rejected edges whose two cameras the kept edges leave in different
    components are kept again (all of them, so that two such pairs between the same parts check each other in
    step 6). Returns the (M,) mask of the edges kept again."""
    labels = ViewGraph(vg.names, vg.edges[chk.kept], vg.R_rel[chk.kept], allow_isolated=True).components()
    back = eligible & (labels[vg.edges[:, 0]] != labels[vg.edges[:, 1]])
    chk.kept |= back
    chk.reason[back], chk.step[back] = "", ""
    return back


def _drop_disputed_bridges(vg: ViewGraph, chk: GraphChecks) -> int:
    """After step 6: where it rejected a pair kept by the bridge exception, the loop that showed the error holds the
    other such pairs between the same parts, and which of them is wrong cannot be told; they are dropped too."""
    rest = chk.kept & ~chk.bridged
    parts = ViewGraph(vg.names, vg.edges[rest], vg.R_rel[rest], allow_isolated=True).components()
    pe = parts[vg.edges[chk.bridged]]  # the parts each bridged pair joins
    n = int(parts.max()) + 1
    _, group = connected_components(sp.csr_matrix((np.ones(len(pe)), (pe[:, 0], pe[:, 1])), shape=(n, n)),
                                    directed=False)
    bad = np.unique(group[pe[~chk.kept[chk.bridged], 0]])
    idx = np.flatnonzero(chk.bridged)
    drop = np.zeros(vg.n_edges, bool)
    drop[idx[np.isin(group[pe[:, 0]], bad) & chk.kept[idx]]] = True
    return _reject(chk, drop, "robust", lambda ix: [
        "kept only to join cameras to the rest, but in a loop with another such pair that the robust solution "
        "rejected: which of them is wrong cannot be told" for _ in ix])


def _robust_subgraph(vg: ViewGraph, chk: GraphChecks, cfg: ViewGraphConfig) -> tuple[np.ndarray, ViewGraph]:
    """The edges the robust solution weighs (indices into ``vg``) and their graph.

    The kept pairs, and those dropped only because no cycle confirmed them (when robust_unconfirmed): a pair whose
    one triangle is inconsistent because of *another* pair of it is such a pair, and without it that other pair's
    error has only long loops to go to, which IRLS-ℓ½ spreads below its threshold and the polish may then put on
    any pair of the loop (a rendered 500-view street: a correct pan pair rejected at 26°, the wrong pair kept, half
    the street lost). Only kept pairs are judged.
    """
    keep = np.flatnonzero(chk.kept | (cfg.robust_unconfirmed & (chk.step == "unconfirmed")))
    return keep, ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep],
                           inliers=None if vg.inliers is None else vg.inliers[keep], allow_isolated=True)


def _robust_filter(vg: ViewGraph, chk: GraphChecks, sigma_weak_deg: np.ndarray, cfg: ViewGraphConfig) -> int:
    """Step 6: reject the kept edges whose IRLS-ℓ½ residual is far beyond their σ, in every component with a cycle."""
    from pipeline.averaging.irls import IRLSConfig  # noqa: PLC0415 - the graph checks use one averaging method
    from pipeline.averaging.solve import average  # noqa: PLC0415

    if not chk.kept.any():
        return 0
    keep, sub = _robust_subgraph(vg, chk, cfg)
    labels = sub.components()
    r = np.full(vg.n_edges, np.nan)
    n_comp = int(labels.max()) + 1
    n_cams, n_edges = np.bincount(labels, minlength=n_comp), np.bincount(labels[sub.edges[:, 0]], minlength=n_comp)
    # one solve per component with a cycle (a few): the left-out ones are checked too; a tree (every lone camera is
    # one) has no residual to judge
    for c in np.flatnonzero(n_edges >= n_cams).tolist():
        comp, restr = sub.subgraph(labels == c)
        res = average(comp, "irls", IRLSConfig(certify=False))
        r[keep[restr.edge_kept[res.edge_index]]] = np.degrees(res.residuals_rad)
    thr = np.maximum(cfg.robust_floor_deg, cfg.robust_k_sigma * cfg.h_inflation * sigma_weak_deg)
    bad = chk.kept & np.isfinite(r) & (r > thr)
    return _reject(chk, bad, "robust", lambda ix: [
        f"the robust solution (IRLS-ℓ½) leaves it {r[k]:.1f}° off (threshold {thr[k]:.1f}°)" for k in ix])
