"""Pair acceptance by the evidence each pair carries: inliers, inlier ratio, parallax and the conditioning of H.

Pure functions on the view graph's per-edge arrays (``stats``, ``inliers``, ``H``).

**Gates** (:func:`gate_pairs`), each with its reason:

- RANSAC inliers among the putative matches (``n_inliers_E``) at least ``min_inliers``
  (COLMAP's two-view ``min_num_inliers`` is 15) and an inlier ratio of at least
  ``min_inlier_ratio`` (COLMAP's ``ransac.min_inlier_ratio`` 0.25);
- the conditioning of H (two-view BA): ``h_inflation·σ_weak ≤ max_sigma_deg`` with
  ``σ_weak = 1/√λ_min(H)``, the standard deviation of the rotation along its weakest
  direction. H is overconfident on real images by a common factor (NEES 3–15 on temple),
  hence ``h_inflation``. A pair whose rotation is not determined to a few degrees cannot be
  told from a wrong one by the loop test either.

**Tiers** (:func:`evidence_tiers`): what a pair must carry on its own depends on what the
loop test can check.

- *strong*: at least ``strong_min_inliers`` inliers, ratio ≥ ``strong_min_ratio``,
  ``h_inflation·σ_weak ≤ strong_max_sigma_deg``, ``√(λ_max/λ_min) ≤ strong_max_cond`` and a
  median triangulation angle in [``min_parallax_deg``, ``wide_parallax_deg``], no small
  baseline. Kept even when no cycle confirms it (and then flagged). A rotation-only
  pair claims that its cameras share a centre; static content and repeated structure fit
  that model well, so it is never strong on its own;
- *standalone* (a wider set than strong): the same gates on inliers, ratio, σ_weak and
  conditioning, with any parallax up to ``wide_parallax_deg``, rotation-only pairs
  included (a pan on the spot). Such a pair, confirmed by no cycle, is kept only where it
  alone joins cameras to the rest (:func:`pipeline.graph.checks.check_view_graph`, step 5),
  and the cameras it joins are flagged;
- *normal*: passes the gates; kept only when a consistent cycle confirms it;
- *provisional*: ``provisional_min_inliers`` ≤ inliers < ``min_inliers``, the other gates
  passed, parallax at most ``wide_parallax_deg``: kept only when confirmed.

A pair whose rays meet at more than ``wide_parallax_deg`` is legitimate when cycles confirm
it (fountain-P11's correct (0, 8) triangulates at 87°), so that ceiling applies only to weak
pairs (turntable views 90–135° apart matched by chance) and to the strong tier.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.viewgraph import ViewGraph

__all__ = ["PairEvidence", "pair_evidence", "gate_pairs", "Tiers", "evidence_tiers"]


@dataclass
class PairEvidence:
    """Per-edge evidence (M,) of a view graph.

    Attributes:
        n_inliers: RANSAC inliers among the putative matches.
        inlier_ratio: n_inliers / matches given to RANSAC.
        triangulation_deg: median angle between the inliers' rays (0 for rotation-only pairs).
        small_baseline: the two-view stage's flag (rotation-only fit, or rays < 1° apart): the pair
            claims that its two cameras (nearly) share a centre.
        sigma_weak_deg: ``1/√λ_min(H)`` in degrees (NaN without H).
        cond: ``√(λ_max/λ_min)`` of H (NaN without H).
    """

    n_inliers: np.ndarray
    inlier_ratio: np.ndarray
    triangulation_deg: np.ndarray
    small_baseline: np.ndarray
    sigma_weak_deg: np.ndarray
    cond: np.ndarray


#: The acceptance gate's reason for a pair whose rotation is poorly determined (its matches pass the inlier gates).
WEAK_H = "rotation poorly determined (weak H)"


def pair_evidence(vg: ViewGraph) -> PairEvidence:
    """The evidence of every edge of ``vg`` from its stats (two-view stage) and H (two-view BA)."""
    M = vg.n_edges
    st = vg.stats
    inl = np.asarray(vg.inliers if vg.inliers is not None else np.zeros(M), float)
    n = np.asarray(st.get("n_inliers_E", inl), float)
    m = np.asarray(st.get("n_matches", np.maximum(n, 1)), float)
    sb = np.asarray(st.get("small_baseline", np.zeros(M, bool)), bool)
    sw, cond = np.full(M, np.nan), np.full(M, np.nan)
    if vg.H is not None and M:
        lam = np.linalg.eigvalsh(vg.H)
        sw = np.degrees(1.0 / np.sqrt(np.maximum(lam[:, 0], 1e-300)))
        cond = np.sqrt(lam[:, 2] / np.maximum(lam[:, 0], 1e-300))
    tri = np.nan_to_num(np.asarray(st.get("median_triangulation_deg", np.full(M, np.nan)), float))
    return PairEvidence(n, n / np.maximum(m, 1), tri, sb, sw, cond)


def gate_pairs(ev: PairEvidence, config: Any, min_inliers: int | None = None) -> np.ndarray:
    """(M,) reason each pair fails the gates ("" if it passes), the first failed gate.

    ``config``: the view-graph stage's :class:`~pipeline.graph.checks.ViewGraphConfig` (its gate options).
    """
    cfg = config
    k = cfg.min_inliers if min_inliers is None else min_inliers
    reason = np.full(len(ev.n_inliers), "", dtype=object)
    weak_h = cfg.h_inflation * ev.sigma_weak_deg > cfg.max_sigma_deg  # NaN (no H): passes
    for fail, why in ((weak_h, WEAK_H),
                      (ev.inlier_ratio < cfg.min_inlier_ratio, "inlier ratio too low"),
                      (ev.n_inliers < k, "too few inliers")):  # the last assigned is reported: the first gate
        reason = np.where(fail, why, reason)
    return reason


@dataclass
class Tiers:
    """Result of :func:`evidence_tiers` (all (M,)).

    Attributes:
        candidate: enters the loop test (normal or provisional).
        provisional: kept only when confirmed, as ``normal`` pairs are; counted apart.
        strong: kept even when unconfirmed.
        standalone: strong but for the parallax (low, or a rotation-only fit): kept unconfirmed only where
            it alone joins cameras to the rest.
        reason: why a pair is not a candidate ("" otherwise).
    """

    candidate: np.ndarray
    provisional: np.ndarray
    strong: np.ndarray
    standalone: np.ndarray
    reason: np.ndarray


def evidence_tiers(ev: PairEvidence, config: Any) -> Tiers:
    """The tier of every pair (module docstring); ``config``: a :class:`~pipeline.graph.checks.ViewGraphConfig`."""
    cfg = config
    reason = gate_pairs(ev, cfg)
    relaxed = gate_pairs(ev, cfg, cfg.provisional_min_inliers)
    ok, ok_relaxed = reason == "", relaxed == ""
    wide = ev.triangulation_deg > cfg.wide_parallax_deg
    provisional = ok_relaxed & ~ok & ~wide
    candidate = ok | provisional
    reason = np.where(candidate, "", np.where(ok_relaxed & wide, "weak and wide parallax", relaxed))
    tri = ev.triangulation_deg
    has_H = np.isfinite(ev.sigma_weak_deg)
    standalone = (ok & (ev.n_inliers >= cfg.strong_min_inliers) & (ev.inlier_ratio >= cfg.strong_min_ratio)
                  & (tri <= cfg.wide_parallax_deg)
                  & (~has_H | ((cfg.h_inflation * ev.sigma_weak_deg <= cfg.strong_max_sigma_deg)
                               & (ev.cond <= cfg.strong_max_cond))))
    strong = standalone & (tri >= cfg.min_parallax_deg) & ~ev.small_baseline
    return Tiers(candidate, provisional, strong, standalone, reason.astype(object))
