"""Guided matching: re-match a pair's descriptors inside the epipolar band of its own estimated pose.

For a pair whose RANSAC found a pose (possibly a weak one, below ``min_inliers``),
:func:`estimate_pair_guided`

1. takes the seed pose ``(R, t)``, ``x_j = R x_i + t``, i.e. ``F = K_j⁻ᵀ [t]× R K_i⁻¹``;
2. lets every keypoint ``a`` of image i match only keypoints ``b`` of image j whose
   symmetric epipolar distance ``max(d(x_b, F x_a), d(x_a, Fᵀ x_b))`` is at most
   ``guided_band_px`` and whose triangulation lies in front of both cameras; the match is
   the nearest RootSIFT candidate, with Lowe's ratio test taken *among the candidates*
   and the mutual check restricted the same way (COLMAP's ``guided_matching``), plus an
   a-contrario gate per match (``guided_nfa``): with ``k`` candidates in the band and the
   match's similarity reached by ``r`` of the ``n_j`` keypoints of image j, the expected
   number of band candidates that good by chance is ``k·r/n_j`` (research r13-lowtex §3:
   without it the band of a wrong pose harvests as much as the right one);
3. **tests the seed against nearby wrong poses** before using its harvest: the same
   harvest under the seed rotated about its baseline by ±δ and ±2δ (``guided_null_deg``):
   those poses turn every epipolar plane about the baseline, so each band moves across
   its line and misses the true matches, but the poses are as plausible as the seed in
   every other respect. Their largest harvest is the chance level λ; the seed's harvest
   ``h`` must be improbable under it, ``P(Poisson(λ) ≥ h) ≤ guided_alpha``. A wrong seed
   explains the descriptors no better than its neighbours and is left as it was: guided
   matching never creates a pair from its own prediction. (It cannot see a wrong pose
   that fits *another* real structure, a repeated one: notes/issue-13.md, guided matching);
4. re-estimates the pair from scratch (:func:`~pipeline.geometry.ransac.estimate_pair`:
   RANSAC, cheirality, refinement, zero-motion test) on its putative matches plus the
   harvest, so the measured rotation comes from the pair's own matches, and the two-view
   BA and the view graph's checks judge the result as any other pair. The new rotation
   must agree with the seed's within ``guided_max_change_deg``: both solutions of E's
   twisted pair share one band, so a harvest can support a pose the seed never claimed.

Everything is vectorised over row blocks of the (n_i, n_j) similarity matrix, which is
formed once per pair for every pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import poisson

from pipeline.core import so3
from pipeline.geometry.epipolar import essential_from_Rt, normalize, triangulation_depths
from pipeline.geometry.ransac import PairGeometry, TwoViewConfig, estimate_pair

__all__ = ["GuidedOutcome", "epipolar_distances", "estimate_pair_guided", "fundamental_from_pose",
           "guided_matches", "harvest", "null_poses"]

_BLOCK_BYTES = 1 << 25


def fundamental_from_pose(R: np.ndarray, t: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> np.ndarray:
    """``F = K_j⁻ᵀ [t]× R K_i⁻¹`` (3, 3), with ``x_jᵀ F x_i = 0`` for pixels (``x_j = R x_i + t``)."""
    return np.linalg.inv(K_j).T @ essential_from_Rt(R, np.asarray(t, float)) @ np.linalg.inv(K_i)


def epipolar_distances(F: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """(n_i, n_j) symmetric epipolar distances in pixels, ``max(d(x_j, F x_i), d(x_i, Fᵀ x_j))``.

    Args:
        F: (3, 3) fundamental matrix; x_i: (n_i, 2), x_j: (n_j, 2) pixels.
    """
    hi = np.column_stack([x_i, np.ones(len(x_i))])
    hj = np.column_stack([x_j, np.ones(len(x_j))])
    li, lj = hi @ F.T, hj @ F  # epipolar lines of x_i in image j, of x_j in image i
    a = np.abs(li @ hj.T)
    ni = np.maximum(np.hypot(li[:, 0], li[:, 1]), 1e-12)[:, None]
    nj = np.maximum(np.hypot(lj[:, 0], lj[:, 1]), 1e-12)[None, :]
    return a / np.minimum(ni, nj)


def guided_matches(x_i: np.ndarray, q_i: np.ndarray, x_j: np.ndarray, q_j: np.ndarray,
                   poses: list[tuple[np.ndarray, np.ndarray]], K_i: np.ndarray, K_j: np.ndarray, *, band_px: float,
                   ratio: float, nfa_max: float, max_distance: float = 0.7, mutual: bool = True) -> list[np.ndarray]:
    """Matches restricted to the epipolar band of each pose (pure function; module docstring, step 2).

    Args:
        x_i: (n_i, 2) keypoints of image i (pixels); q_i: (n_i, 128) RootSIFT rows (unit norm, float32).
        x_j, q_j: the same for image j.
        poses: P poses ``(R (3, 3), t (3,))`` with ``x_j = R x_i + t``, t nonzero.
        K_i, K_j: (3, 3) intrinsics.
        band_px: half-width of the band (pixels of x).
        ratio: ratio test among the candidates in the band (one candidate: no second to compare).
        nfa_max: a-contrario gate ``k·r/n_j`` per match (inf: off).
        max_distance: RootSIFT L2 distance above which nothing is matched.
        mutual: keep only matches that are also b's best candidate.
    Returns:
        P arrays (m_p, 2) int32 keypoint indices ``(in i, in j)``.
    """
    n_i, n_j, P = len(x_i), len(x_j), len(poses)
    if n_i == 0 or n_j == 0:
        return [np.zeros((0, 2), np.int32) for _ in range(P)]
    Fs = [fundamental_from_pose(R, t / np.linalg.norm(t), K_i, K_j) for R, t in poses]
    y_i, y_j = normalize(x_i, K_i), normalize(x_j, K_j)
    block = max(64, _BLOCK_BYTES // (8 * n_j))
    best = np.full((P, n_i), 0, np.int64)
    s1 = np.full((P, n_i), -np.inf, np.float32)
    s2 = np.full((P, n_i), -np.inf, np.float32)
    nfa = np.full((P, n_i), np.inf)
    col_best = np.full((P, n_j), -np.inf, np.float32)
    for s in range(0, n_i, block):
        e = min(n_i, s + block)
        S_all = q_i[s:e] @ q_j.T  # (b, n_j) cosine similarities, shared by every pose
        r = np.arange(e - s)
        for p, ((R, t), F) in enumerate(zip(poses, Fs)):  # a handful of poses, not a loop over matches
            ok = epipolar_distances(F, x_i[s:e], x_j) <= band_px
            rr, cc = np.nonzero(ok)  # the band holds ~2·band/height of the pairs: cheirality on those only
            zi, zj = triangulation_depths(R, t, y_i[s + rr], y_j[cc])
            ok[rr, cc] = (zi > 0) & (zj > 0)
            S = np.where(ok, S_all, -np.inf).astype(np.float32)
            a = S.argmax(1)
            best[p, s:e], s1[p, s:e] = a, S[r, a]
            rank = (S_all >= S[r, a][:, None]).sum(1)  # keypoints of j at least as similar: the match's global rank
            nfa[p, s:e] = ok.sum(1) * rank / n_j
            np.maximum(col_best[p], S.max(0), out=col_best[p])
            S[r, a] = -np.inf
            s2[p, s:e] = S.max(1)
    d1 = np.sqrt(np.maximum(2 - 2 * np.where(np.isfinite(s1), s1, -1), 0))
    has2 = np.isfinite(s2)
    d2 = np.where(has2, np.sqrt(np.maximum(2 - 2 * np.where(has2, s2, -1), 0)), np.inf)
    keep = np.isfinite(s1) & (d1 <= max_distance) & ((d1 < ratio * d2) | ~has2) & (nfa <= nfa_max)
    if mutual:
        keep &= s1 >= np.take_along_axis(col_best, best, axis=1)
    return [np.stack([np.flatnonzero(k), b[k]], 1).astype(np.int32) for k, b in zip(keep, best)]


def null_poses(R: np.ndarray, t: np.ndarray, angle_deg: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Four wrong poses near the seed: R rotated about the baseline ``t`` (camera j's frame) by ±δ, ±2δ; t kept.

    A rotation about the baseline maps each epipolar plane to another one, so every
    epipolar line moves across itself (a rotation about another axis may slide points
    along their lines, e.g. about the vertical for a turntable, and keep the true matches
    in the band).
    """
    u = t / np.linalg.norm(t)
    w = np.deg2rad(angle_deg) * np.array([1.0, -1.0, 2.0, -2.0])[:, None] * u[None, :]
    return [(Rp @ R, t) for Rp in so3.exp(w)]


@dataclass
class GuidedOutcome:
    """What guided matching did for one pair.

    Attributes:
        used: the harvest was significant and the pair was re-estimated with it.
        n_harvest: guided matches under the (last) seed pose; n_null: the chance level λ
            (largest harvest of the null poses); p_value: ``P(Poisson(λ) ≥ n_harvest)``.
        n_added: matches the harvest added to the putative ones.
        reason: why it was not used ("" if used).
    """

    used: bool = False
    n_harvest: int = 0
    n_null: int = 0
    p_value: float = 1.0
    n_added: int = 0
    reason: str = ""


def _seed(x_i: np.ndarray, x_j: np.ndarray, K_i: np.ndarray, K_j: np.ndarray, g: PairGeometry, config: TwoViewConfig,
          pixel_scale: float) -> PairGeometry:
    """The pose that seeds the band: the pair's own, or for a weak pair its RANSAC model with fewer inliers."""
    if g.ok or len(x_i) < 5:
        return g
    k = config.guided_seed_min_inliers
    return estimate_pair(x_i, x_j, K_i, K_j, config.replace(min_inliers=k, min_matches=max(k, 5)), pixel_scale)


def harvest(kp_i: np.ndarray, q_i: np.ndarray, kp_j: np.ndarray, q_j: np.ndarray, R: np.ndarray, t: np.ndarray,
            K_i: np.ndarray, K_j: np.ndarray, config: TwoViewConfig, pixel_scale: float = 1.0
            ) -> tuple[np.ndarray, int, float]:
    """The guided matches of the pose ``(R, t)`` and their significance (module docstring, steps 2–3).

    Returns:
        (m, 2) int32 matches in the band of ``(R, t)``; the chance level λ (the largest
        harvest of the :func:`null_poses`, at least 1); ``P(Poisson(λ) ≥ m)``.
    """
    found = guided_matches(kp_i, q_i, kp_j, q_j, [(R, t), *null_poses(R, t, config.guided_null_deg)], K_i, K_j,
                           band_px=config.guided_band_px * pixel_scale, ratio=config.guided_ratio,
                           nfa_max=config.guided_nfa)
    lam = max(max(len(x) for x in found[1:]), 1)
    return found[0], lam, float(poisson.sf(len(found[0]) - 1, lam))


def estimate_pair_guided(kp_i: np.ndarray, q_i: np.ndarray, kp_j: np.ndarray, q_j: np.ndarray, matches: np.ndarray,
                         K_i: np.ndarray, K_j: np.ndarray, config: TwoViewConfig, pixel_scale: float = 1.0
                         ) -> tuple[PairGeometry, np.ndarray, GuidedOutcome]:
    """Estimate a pair, then (weak pairs only) again with the guided harvest of its own pose (module docstring).

    Args:
        kp_i, kp_j: (n_i, 2), (n_j, 2) keypoints (pixels, undistorted); q_i, q_j: their RootSIFT descriptors.
        matches: (m, 2) putative matches (keypoint indices in i, in j).
        K_i, K_j: (3, 3) intrinsics; config: options (``guided_*``); pixel_scale: as for estimate_pair.
    Returns:
        the geometry (``n_guided``: matches the harvest added), the matches it was estimated from (its
        ``inlier_mask`` indexes them), and the outcome.
    """
    matches = np.asarray(matches)
    if matches.ndim != 2 or matches.shape[1] != 2 or matches.dtype.kind not in "iu":
        raise ValueError(f"matches.shape={matches.shape}, dtype={matches.dtype} but expected (m, 2) integer indices")
    g = estimate_pair(kp_i[matches[:, 0]], kp_j[matches[:, 1]], K_i, K_j, config, pixel_scale)
    out = GuidedOutcome(reason="off")
    if not config.guided:
        return g, matches, out
    if g.ok and g.n_inliers >= config.guided_max_inliers:
        return g, matches, GuidedOutcome(reason=f"not weak ({g.n_inliers} >= guided_max_inliers inliers)")
    seed = _seed(kp_i[matches[:, 0]], kp_j[matches[:, 1]], K_i, K_j, g, config, pixel_scale)
    best_g, best_m, why = g, matches, ""
    for _ in range(config.guided_rounds):
        if not seed.ok or seed.small_baseline or not np.linalg.norm(seed.t) > 0:
            why = "no seed pose with a baseline"
            break
        found, out.n_null, out.p_value = harvest(kp_i, q_i, kp_j, q_j, seed.R, seed.t, K_i, K_j, config, pixel_scale)
        out.n_harvest = len(found)
        if out.p_value > config.guided_alpha:
            why = f"harvest {len(found)} not above chance (λ = {out.n_null}, p = {out.p_value:.2g})"
            break
        union = np.unique(np.concatenate([matches, found]), axis=0)
        g2 = estimate_pair(kp_i[union[:, 0]], kp_j[union[:, 1]], K_i, K_j, config, pixel_scale)
        if not g2.ok:
            why = f"re-estimation failed: {g2.reason}"
            break
        change = float(np.degrees(so3.angle_between(g2.R, seed.R)))
        if change > config.guided_max_change_deg:  # E's twisted pair shares the band: the pose must agree too
            why = f"re-estimated rotation {change:.1f}° from its seed"
            break
        out.used, out.n_added = True, len(union) - len(matches)
        g2.n_guided = out.n_added
        best_g, best_m, seed = g2, union, g2
    out.reason = "" if out.used else why  # a later round's stop does not undo an earlier round's use
    return best_g, best_m, out
