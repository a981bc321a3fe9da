"""Relative pose of one matched pair: 5-point RANSAC on E, cheirality, refinement, degeneracy flags.

For a pair ``(i, j)``, ``i < j`` (:func:`estimate_pair`):

1. Keypoints are normalized with each image's own K (``x̂ = K⁻¹ x``), so images
   with different intrinsics are handled; the pixel threshold becomes
   ``threshold_px / f`` with f the mean focal length of the two cameras.
2. E is estimated with the configured confidence by the 5-point solver inside
   PoseLib's LO-RANSAC (``poselib.estimate_relative_pose``, the default: adaptive
   stopping, local optimisation, the GIL released so that threads run pairs in
   parallel) or OpenCV's ``cv2.findEssentialMat`` (USAC-MAGSAC++ or RANSAC).
   PoseLib's iterations are capped at the number that finds, with the configured
   confidence, an all-inlier sample of a model with ``min_inliers`` inliers: a pair
   that could be accepted is found, and a pair of random matches is not sampled
   2000 times in vain (:func:`iteration_cap`).
3. The cheirality check picks, of E's four decompositions, the (R, t) that puts
   the most inliers in front of both cameras (as ``cv2.recoverPose`` does, but
   without its 50-baseline depth cut, which rejects every match of a
   small-baseline pair). ``x_j = R_ij x_i + t_ij``, i.e. ``R_ij = R_j R_iᵀ``
   (pycolmap's ``cam2_from_cam1``), the view graph's convention. (R, t) is then
   polished on the inliers by minimizing the robust Sampson error (``refine``): PoseLib's own
   refinement (Cauchy loss at the threshold), or soft-ℓ1 least squares after OpenCV's estimators;
   the inliers are then selected again under the polished model.
4. Pairs are rejected, with the reason and counts recorded, when they have too
   few matches, when E cannot be estimated, or when fewer than ``min_inliers``
   inliers survive the cheirality check.
5. **Zero motion** (``static_px``): when at least ``static_fraction`` of the inliers moved
   less than ``static_px`` pixels between the two images, the model describes content that
   is static in the image (a static object beside a turntable, a watermark, a duplicate
   image), not the cameras' motion. Those matches (motion below ``2·static_px``) are
   removed and the pose is estimated again from the rest; if nothing is left the pair is
   rejected ("no image motion"). COLMAP's ``filter_stationary_matches`` (off by default)
   drops every slow match before estimation; this test only acts when the static matches
   dominate, so a real small-motion pair keeps its slow points.
6. Near-degenerate pairs are kept but flagged:

   - *small baseline*: the median triangulation angle of the inliers is below
     ``min_triangulation_deg``, or a rotation-only homography ``K_j R K_i⁻¹``
     explains the matches as well as E does. The rotation is still well defined,
     the translation direction is not: for a rotation-only pair R comes from the
     rotation-only fit (Kabsch on the bearing vectors) and ``t`` is stored as zeros;
   - *dominant plane*: a homography (RANSAC, same threshold) explains at least
     ``planar_ratio`` of the E inliers; E from a plane has a two-fold ambiguity.

The threshold is in pixels of the image *at the feature-extraction size*: with
``max_image_size = 1600`` and a 3072-pixel image, 1 px becomes 1.92 full-size px.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
import poselib

from pipeline.core.config import option
from pipeline.core.parallel import ExecutorOptions
from pipeline.geometry.epipolar import (essential_from_Rt, normalize, pose_from_essential, refine_pose,
                                        rotation_from_bearings, rotation_only_residual_px, sampson_distance,
                                        triangulation_depths)

__all__ = ["TwoViewConfig", "PairGeometry", "estimate_pair", "iteration_cap", "trials", "METHODS"]

METHODS = {"poselib": None, "magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}
_UNIT_CAMERA = {"model": "PINHOLE", "width": 2, "height": 2, "params": [1.0, 1.0, 0.0, 0.0]}  # normalized coords


@dataclass(frozen=True, kw_only=True)
class TwoViewConfig(ExecutorOptions):
    """Relative-pose estimation options (YAML section ``two_view``)."""

    SECTION = "two_view"

    method: Literal["poselib", "magsac", "ransac"] = option(
        "poselib", "robust estimator around the 5-point solver: PoseLib's LO-RANSAC, OpenCV's USAC-MAGSAC++ or "
                   "OpenCV's classic RANSAC")
    threshold_px: float = option(1.0, "inlier threshold in pixels at the feature-extraction image size", gt=0)
    confidence: float = option(0.999, "RANSAC confidence", gt=0, lt=1)
    max_iterations: int = option(2000, "RANSAC iteration cap (poselib: lowered to the iterations that find a model "
                                       "with min_inliers inliers at the configured confidence)", ge=1)
    min_matches: int = option(12, "pairs with fewer matches are rejected without RANSAC (the 5-point solver "
                                  "needs >= 5)", ge=5)
    min_inliers: int = option(12, "pairs with fewer inliers after the cheirality check are rejected; the view "
                                  "graph's checks keep a pair below its own min_inliers (15) only when a cycle "
                                  "confirms it (provisional)", ge=5)
    static_px: float = option(1.0, "zero-motion test: when static_fraction of the inliers moved less than this "
                                   "(px at extraction size), the static matches are removed and the pair estimated "
                                   "again (0: off)", ge=0)
    static_fraction: float = option(0.5, "zero-motion test: fraction of static inliers that triggers it", gt=0, le=1)
    min_triangulation_deg: float = option(1.0, "a median triangulation angle below this flags a small baseline",
                                          ge=0)
    planar_ratio: float = option(0.9, "homography inliers / E inliers at or above this flags a dominant plane",
                                 ge=0)
    rotation_only_ratio: float = option(
        0.9, "when a pure rotation K_j R K_i⁻¹ explains this fraction of the E inliers, the pair has zero "
             "baseline: R from the rotation-only fit, t stored as zeros, flagged small_baseline", ge=0)
    refine: bool = option(True, "polish (R, t) on the inliers by minimizing a robust Sampson error (PoseLib's "
                                "Cauchy; soft-ℓ1 after OpenCV's); RANSAC's best minimal-sample model is off by "
                                "tenths of a degree")
    seed: int = option(0, "RANSAC random seed (set before each pair: reproducible results)")
    guided: bool = option(False, "guided matching (pipeline.geometry.guided): a weak pair is matched again inside "
                                 "the epipolar band of its own pose and re-estimated, when that harvest is above "
                                 "the chance level of nearby wrong poses")
    guided_max_inliers: int = option(50, "guided matching: pairs with fewer inliers (or rejected) are weak", ge=0)
    guided_seed_min_inliers: int = option(8, "guided matching: a rejected pair's RANSAC model seeds the band when "
                                             "it has this many inliers", ge=5)
    guided_band_px: float = option(2.0, "guided matching: half-width of the epipolar band (px at extraction size)",
                                   gt=0)
    guided_ratio: float = option(0.8, "guided matching: ratio test among the candidates in the band", gt=0, le=1)
    guided_nfa: float = option(0.03, "guided matching: a-contrario gate per match, candidates · global rank / "
                                     "keypoints of the other image", gt=0)
    guided_null_deg: float = option(3.0, "guided matching: the null poses turn the seed about its baseline by "
                                         "this and twice this, degrees", gt=0)
    guided_alpha: float = option(1e-6, "guided matching: the harvest is used when P(Poisson(chance level) >= "
                                       "harvest) is at most this", gt=0, lt=1)
    guided_rounds: int = option(2, "guided matching: harvest and re-estimate this many times", ge=1)
    guided_max_change_deg: float = option(5.0, "guided matching: the re-estimated rotation must be within this of "
                                               "its seed's, degrees", gt=0)
    workers: int = option(2, "processes estimating pairs (1 = in this process)", ge=1, runtime=True)
    chunk_size: int = option(8, "pairs per task sent to a worker (and per resumable chunk)", ge=1, runtime=True)
    progress: bool = option(True, "show a progress bar", runtime=True)


@dataclass
class PairGeometry:
    """Result of :func:`estimate_pair`.

    Attributes:
        ok: accepted.
        reason: why it was rejected ("" if accepted).
        R: (3, 3) ``R_ij`` (cam2_from_cam1) with ``x_j = R_ij x_i + t_ij``.
        t: (3,) unit ``t_ij``.
        inlier_mask: (n,) bool over the input matches (RANSAC inlier and in front of both cameras).
        n_matches, n_inliers_E (RANSAC inliers), n_inliers (after cheirality): counts; n_inliers_H: the
            homography inliers found in the iterations that decide the planar flag (a lower bound when it is off).
        median_triangulation_deg: median angle between the two rays of the inliers.
        median_parallax_px: median distance, in image j, between x_j and x_i mapped by the
            rotation-only homography ``K_j R_ij K_i⁻¹`` (pixels at extraction size).
        small_baseline, planar: degeneracy flags.
        n_static: matches removed by the zero-motion test (0: it did not act); ``n_matches``
            then counts the other matches, the ones the pose was estimated from.
        n_guided: matches guided matching added to the putative ones (0: not used).
    """

    ok: bool
    reason: str = ""
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    n_matches: int = 0
    n_inliers_E: int = 0
    n_inliers: int = 0
    n_inliers_H: int = 0
    median_triangulation_deg: float = float("nan")
    median_parallax_px: float = float("nan")
    small_baseline: bool = False
    planar: bool = False
    n_static: int = 0
    n_guided: int = 0


def estimate_pair(x_i: np.ndarray, x_j: np.ndarray, K_i: np.ndarray, K_j: np.ndarray,
                  config: TwoViewConfig | None = None, pixel_scale: float = 1.0) -> PairGeometry:
    """Relative pose of one pair from matched pixels (pure function), with the zero-motion test.

    Args:
        x_i, x_j: (n, 2) matched pixel coordinates in images i and j.
        K_i, K_j: (3, 3) intrinsics.
        config: options.
        pixel_scale: full-resolution pixels per extraction-size pixel (threshold scaling).
    Returns:
        :class:`PairGeometry`; its ``inlier_mask`` is over the n input matches.
    """
    config = config or TwoViewConfig()
    geom = _estimate(x_i, x_j, K_i, K_j, config, pixel_scale)
    if not geom.ok or config.static_px <= 0:
        return geom
    thr = config.static_px * pixel_scale
    moved = np.linalg.norm(np.asarray(x_i, np.float64) - np.asarray(x_j, np.float64), axis=1)
    if np.mean(moved[geom.inlier_mask] < thr) < config.static_fraction:
        return geom
    moving = moved >= 2.0 * thr
    n, n_static = len(x_i), int(np.sum(~moving))
    geom = _estimate(x_i[moving], x_j[moving], K_i, K_j, config, pixel_scale)
    mask = np.zeros(n, bool)
    if geom.inlier_mask.shape == (int(moving.sum()),):
        mask[moving] = geom.inlier_mask
    geom.inlier_mask, geom.n_static = mask, n_static
    if not geom.ok:
        geom.reason = (f"no image motion: {n_static} of {n} matches did not move (static content: a static object, "
                       f"a watermark, a duplicate image); the others: {geom.reason}")
    return geom


def trials(inlier_share: float, sample_size: int, confidence: float, cap: int) -> int:
    """RANSAC iterations that draw, with probability ``confidence``, one all-inlier sample of ``sample_size``
    when ``inlier_share`` of the points are inliers; at least 1, at most ``cap``."""
    w = min(max(inlier_share, 0.0), 1.0)
    if w >= 1.0:
        return 1
    miss = np.log1p(-w ** sample_size)
    k = np.log1p(-confidence) / miss if miss < 0 else np.inf
    return int(min(cap, max(np.ceil(k), 1)))


def iteration_cap(n: int, config: TwoViewConfig) -> int:
    """RANSAC iterations that draw, with probability ``config.confidence``, one all-inlier 5-point sample from
    ``n`` matches of which ``min_inliers`` are inliers, at most ``max_iterations``.

    A pair with more inliers is found sooner (the adaptive stop); a pair that after this many iterations has not
    reached ``min_inliers`` inliers is rejected by step 4 anyway, up to the confidence.
    """
    return trials(config.min_inliers / max(n, 1), 5, config.confidence, config.max_iterations)


def _essential(y_i: np.ndarray, y_j: np.ndarray, thr: float, config: TwoViewConfig) -> tuple[np.ndarray | None,
                                                                                              np.ndarray]:
    """E and its inlier mask from normalized coordinates at threshold ``thr`` (normalized units); E is None when
    no model was found."""
    n = len(y_i)
    if config.method == "poselib":
        cap = iteration_cap(n, config)
        pose, info = poselib.estimate_relative_pose(
            y_i, y_j, _UNIT_CAMERA, _UNIT_CAMERA,
            {"max_epipolar_error": thr, "max_iterations": cap, "min_iterations": min(50, cap),
             "success_prob": config.confidence, "seed": config.seed},
            # step 3's polish: PoseLib's own robust Sampson refinement (Cauchy at the threshold) on its inliers
            {"max_iterations": 100, "loss_type": "CAUCHY", "loss_scale": thr} if config.refine else
            {"max_iterations": 0})
        mask = np.asarray(info.get("inliers", []), bool).reshape(-1)
        if mask.shape != (n,) or not mask.any():
            return None, np.zeros(n, bool)
        return essential_from_Rt(np.asarray(pose.R), np.asarray(pose.t)), mask
    cv2.setRNGSeed(config.seed)
    E, mask = cv2.findEssentialMat(y_i, y_j, np.eye(3), method=METHODS[config.method], prob=config.confidence,
                                   threshold=thr, maxIters=config.max_iterations)
    if E is None or mask is None or E.shape[0] < 3:
        return None, np.zeros(n, bool)
    return E[:3], mask.ravel().astype(bool)  # several solutions may be stacked; the first is the best scoring


def _estimate(x_i: np.ndarray, x_j: np.ndarray, K_i: np.ndarray, K_j: np.ndarray, config: TwoViewConfig,
              pixel_scale: float) -> PairGeometry:
    """Steps 1–4 and 6 of the module docstring (no zero-motion test)."""
    n = len(x_i)
    if x_i.shape != (n, 2) or x_j.shape != (n, 2):
        raise ValueError(f"x_i.shape={x_i.shape}, x_j.shape={x_j.shape} but expected two (n, 2) arrays")
    if n < config.min_matches:
        return PairGeometry(False, f"too few matches ({n} < min_matches={config.min_matches})", n_matches=n)
    y_i = normalize(x_i.astype(np.float64), K_i)
    y_j = normalize(x_j.astype(np.float64), K_j)
    f = 0.25 * (K_i[0, 0] + K_i[1, 1] + K_j[0, 0] + K_j[1, 1])
    thr_px = config.threshold_px * pixel_scale
    E, mask = _essential(y_i, y_j, thr_px / f, config)
    if E is None:
        return PairGeometry(False, "essential matrix estimation failed (no model found)", n_matches=n)
    n_E = int(mask.sum())
    if n_E < config.min_inliers:
        return PairGeometry(False, f"too few RANSAC inliers ({n_E} < min_inliers={config.min_inliers})", n_matches=n,
                            n_inliers_E=n_E)
    # rotation-only model (zero baseline): if it explains the E inliers as well, the
    # translation is undefined and E's decomposition is unstable, but R is not
    R_rot = rotation_from_bearings(y_i[mask], y_j[mask])
    for _ in range(3):  # re-fit on the matches it explains
        ok_rot = mask & (rotation_only_residual_px(R_rot, x_i, x_j, K_i, K_j) < thr_px)
        if ok_rot.sum() < 3:
            break
        R_rot = rotation_from_bearings(y_i[ok_rot], y_j[ok_rot])
    ok_rot = mask & (rotation_only_residual_px(R_rot, x_i, x_j, K_i, K_j) < thr_px)
    if ok_rot.sum() >= config.rotation_only_ratio * n_E:
        par = rotation_only_residual_px(R_rot, x_i[ok_rot], x_j[ok_rot], K_i, K_j) / pixel_scale
        geom = PairGeometry(True, "", R_rot, np.zeros(3), ok_rot, n, n_E, int(ok_rot.sum()), 0, 0.0,
                            float(np.median(par)), small_baseline=True, planar=False)
        if geom.n_inliers < config.min_inliers:
            geom.ok = False
            geom.reason = f"too few inliers of the rotation-only model ({geom.n_inliers} < min_inliers={config.min_inliers})"
        return geom
    R, t, inl = pose_from_essential(E, y_i, y_j, mask)
    if config.refine and inl.sum() >= 5:
        # PoseLib's pose is refined already; OpenCV's is RANSAC's best minimal-sample model
        R_r, t_r = (R, t) if config.method == "poselib" else refine_pose(R, t, y_i[inl], y_j[inl], thr_px / f)
        # re-select the inliers under the refined model, then re-check cheirality
        in_r = mask & (np.abs(sampson_distance(R_r, t_r, y_i, y_j)) * f < thr_px)
        zi, zj = triangulation_depths(R_r, t_r, y_i, y_j)
        front = in_r & (zi > 0) & (zj > 0)
        # keep the refinement unless it lost the cheirality consensus (a flipped solution)
        if front.sum() >= 0.9 * inl.sum():
            R, t, inl = R_r, t_r, front
    n_in = int(inl.sum())
    # ray angles of the inliers: rays b_i = R_ij ŷ_i and b_j = ŷ_j in camera j's frame
    bi = np.column_stack([y_i[inl], np.ones(n_in)]) @ R.T
    bj = np.column_stack([y_j[inl], np.ones(n_in)])
    cosang = np.sum(bi * bj, 1) / (np.linalg.norm(bi, axis=1) * np.linalg.norm(bj, axis=1))
    tri = float(np.degrees(np.median(np.arccos(np.clip(cosang, -1, 1))))) if n_in else float("nan")
    # parallax left after removing the rotation (infinite homography), in extraction pixels
    Hinf = K_j @ R @ np.linalg.inv(K_i)
    p = np.column_stack([x_i[inl], np.ones(n_in)]) @ Hinf.T
    par = np.linalg.norm(p[:, :2] / p[:, 2:3] - x_j[inl], axis=1) / pixel_scale
    parallax = float(np.median(par)) if n_in else float("nan")
    n_H = 0
    if n_E >= 4:
        # the transfer error |x_j − H x_i| carries the noise of both images in 2-D,
        # about twice the Sampson distance E is judged by: threshold 2·thr
        # the planar flag needs planar_ratio of the E inliers on one homography: the iterations that find such a
        # homography at the confidence suffice (n_H is then a lower bound when the flag is off)
        h_iters = trials(config.planar_ratio, 4, config.confidence, 2000)
        Hm, hmask = cv2.findHomography(x_i[mask].astype(np.float64), x_j[mask].astype(np.float64), cv2.RANSAC,
                                       2.0 * thr_px, maxIters=h_iters, confidence=config.confidence)
        n_H = int(hmask.sum()) if hmask is not None else 0
    geom = PairGeometry(True, "", R, t, inl, n, n_E, n_in, n_H, tri, parallax,
                        small_baseline=bool(tri < config.min_triangulation_deg),
                        planar=bool(n_H >= config.planar_ratio * max(n_E, 1)))
    if n_in < config.min_inliers:
        geom.ok = False
        geom.reason = f"too few inliers in front of both cameras ({n_in} < min_inliers={config.min_inliers})"
    return geom
