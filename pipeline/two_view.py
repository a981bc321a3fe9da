"""Two-view geometry: 5-point RANSAC on the essential matrix, cheirality, degeneracy flags.

Stage 3 of the image front end. For each matched pair ``(i, j)``, ``i < j``:

1. Keypoints are normalized with each image's own K (``x̂ = K⁻¹ x``), so images
   with different intrinsics are handled; the pixel threshold becomes
   ``threshold_px / f`` with f the mean focal length of the two cameras.
2. ``cv2.findEssentialMat`` (5-point solver inside USAC-MAGSAC++ or RANSAC)
   estimates E with the configured confidence.
3. The cheirality check picks, of E's four decompositions, the (R, t) that puts
   the most inliers in front of both cameras (as ``cv2.recoverPose`` does, but
   without its 50-baseline depth cut, which rejects every match of a
   small-baseline pair). ``x_j = R_ij x_i + t_ij``, i.e. ``R_ij = R_j R_iᵀ``, the
   view graph's convention. (R, t) is then polished on the inliers by minimizing
   the robust Sampson error (``refine``).
4. Pairs are rejected, with the reason and counts recorded, when they have too
   few matches, when E cannot be estimated, or when fewer than ``min_inliers``
   inliers survive the cheirality check.
5. Near-degenerate pairs are kept but flagged:

   - *small baseline*: the median triangulation angle of the inliers is below
     ``min_triangulation_deg``, or a rotation-only homography ``K_j R K_i⁻¹``
     explains the matches as well as E does. The rotation is still well defined,
     the translation direction is not: for a rotation-only pair R comes from the
     rotation-only fit (Kabsch on the bearing vectors) and ``t`` is stored as zeros;
   - *dominant plane*: a homography (RANSAC, same threshold) explains at least
     ``planar_ratio`` of the E inliers; E from a plane has a two-fold ambiguity.

The threshold is in pixels of the image *at the feature-extraction size*: with
``max_image_size = 1600`` and a 3072-pixel image, 1 px becomes 1.92 full-size px.

WORK folder layout written by this stage::

    WORK/two_view.json              manifest: files, digest, config, counts, rejected pairs
                                    ({pair, names, n_matches, n_inliers, reason})
    WORK/two_view-<hash>.npz        the ViewGraph (allow_isolated=True): edges, R_rel = R_j R_iᵀ,
                                    inliers, stats "t" (M, 3) unit translation (x_j = R_ij x_i + t),
                                    "n_matches", "n_inliers_E", "n_inliers_H", "h_ratio",
                                    "median_triangulation_deg", "median_parallax_px",
                                    "small_baseline", "planar", "degenerate" (M,) bool
    WORK/two_view-<hash>-corr.npz   K (N, 3, 3), sizes (N, 2), offsets (M+1,), inlier pixel
                                    coordinates x_i (total, 2), x_j (total, 2), keypoint indices

Command line::

    python -m pipeline.two_view --work WORK [--method magsac|ransac] [--threshold 1.0]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pipeline.core.atomic import save_npz, write_json
from pipeline.core.config import config_hash
from pipeline.core.errors import InputFileError
from pipeline.features import load_features
from pipeline.matching import load_matches
from pipeline.core.viewgraph import ViewGraph

logger = logging.getLogger(__name__)

__all__ = ["TwoViewConfig", "PairGeometry", "TwoViewData", "estimate_pair", "main", "load_two_view", "main_cli",
           "MANIFEST"]

MANIFEST = "two_view.json"
_METHODS = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}


@dataclass(frozen=True, kw_only=True)
class TwoViewConfig:
    """Relative-pose estimation options.

    Attributes:
        method: ``"magsac"`` (USAC-MAGSAC++) or ``"ransac"`` (OpenCV's classic RANSAC), 5-point solver.
        threshold_px: inlier threshold in pixels at the feature-extraction image size.
        confidence: RANSAC confidence.
        max_iters: RANSAC iteration cap.
        min_matches: pairs with fewer matches are rejected without RANSAC.
        min_inliers: pairs with fewer inliers after the cheirality check are rejected.
        min_triangulation_deg: median triangulation angle below this flags a small baseline.
        planar_ratio: homography inliers / E inliers at or above this flags a dominant plane.
        rotation_only_ratio: when a pure rotation ``x_j ~ K_j R K_i⁻¹ x_i`` explains at
            least this fraction of the E inliers (within the threshold), the pair is
            a zero-baseline pair: R comes from the rotation-only fit, ``t`` is stored
            as zeros and the pair is flagged ``small_baseline``.
        refine: polish (R, t) on the RANSAC inliers by minimizing the robust (soft-ℓ1)
            Sampson error; OpenCV's RANSAC returns the best minimal-sample model, whose
            rotation is off by tenths of a degree even with 0.1 px matches.
        seed: RANSAC random seed (per pair, for reproducible results).
        workers: pairs processed concurrently (threads: OpenCV releases the GIL).
    """

    method: str = "magsac"
    threshold_px: float = 1.0
    confidence: float = 0.999
    max_iters: int = 2000
    min_matches: int = 20
    min_inliers: int = 20
    min_triangulation_deg: float = 1.0
    planar_ratio: float = 0.9
    rotation_only_ratio: float = 0.9
    refine: bool = True
    seed: int = 0
    workers: int = 2

    def __post_init__(self) -> None:
        if self.method not in _METHODS:
            raise ValueError(f"method={self.method!r} but expected one of {sorted(_METHODS)}")
        if not self.threshold_px > 0:
            raise ValueError(f"threshold_px={self.threshold_px} but expected > 0 pixels")
        if not 0 < self.confidence < 1:
            raise ValueError(f"confidence={self.confidence} but expected 0 < confidence < 1 (e.g. 0.9999)")
        if self.min_inliers < 5 or self.min_matches < 5:
            raise ValueError(f"min_inliers={self.min_inliers}, min_matches={self.min_matches} but the 5-point solver needs >= 5")
        if self.workers < 1:
            raise ValueError(f"workers={self.workers} but expected >= 1")

    def key(self) -> str:
        return config_hash(self, exclude=("workers",))


@dataclass
class PairGeometry:
    """Result of :func:`estimate_pair`.

    Attributes:
        ok: accepted.
        reason: why it was rejected ("" if accepted).
        R: (3, 3) ``R_ij`` with ``x_j = R_ij x_i + t_ij``.
        t: (3,) unit ``t_ij``.
        inlier_mask: (n,) bool over the input matches (RANSAC inlier and in front of both cameras).
        n_matches, n_inliers_E (RANSAC inliers), n_inliers (after cheirality), n_inliers_H: counts.
        median_triangulation_deg: median angle between the two rays of the inliers.
        median_parallax_px: median distance, in image j, between x_j and x_i mapped by the
            rotation-only homography ``K_j R_ij K_i⁻¹`` (pixels at extraction size).
        small_baseline, planar: degeneracy flags.
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


def _normalize(x: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n, 2) pixels → (n, 2) normalized image coordinates ``K⁻¹ x``."""
    xh = np.column_stack([x, np.ones(len(x))])
    y = xh @ np.linalg.inv(K).T
    return y[:, :2] / y[:, 2:3]


def sampson_distance(R: np.ndarray, t: np.ndarray, y_i: np.ndarray, y_j: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (normalized units) of matches under ``E = [t]× R``.

    Args:
        R: (3, 3); t: (3,); y_i, y_j: (n, 2) normalized coordinates.
    Returns:
        (n,) distances; multiply by the focal length for pixels.
    """
    E = np.cross(t[None, :], R.T).T  # [t]× R, column by column
    hi = np.column_stack([y_i, np.ones(len(y_i))])
    hj = np.column_stack([y_j, np.ones(len(y_j))])
    Ex = hi @ E.T
    Etx = hj @ E
    num = np.sum(hj * Ex, axis=1)
    den = Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-30))


def refine_pose(R0: np.ndarray, t0: np.ndarray, y_i: np.ndarray, y_j: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimize the soft-ℓ1 Sampson error over (R, t) with ‖t‖ = 1 (5 dof).

    Args:
        R0, t0: initial pose (``x_j = R x_i + t``).
        y_i, y_j: (n, 2) normalized inlier coordinates.
        scale: soft-ℓ1 scale in normalized units (the inlier threshold).
    Returns:
        refined ``(R, t)``.
    """
    from scipy.optimize import least_squares

    from pipeline.core import so3

    t0 = t0 / np.linalg.norm(t0)
    # orthonormal basis of the tangent plane of the unit sphere at t0
    B = np.linalg.svd(t0[None, :])[2][1:].T  # (3, 2)

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = so3.exp(p[:3]) @ R0  # left perturbation, as in the view graph's convention
        t = t0 + B @ p[3:]
        return R, t / np.linalg.norm(t)

    res = least_squares(lambda p: sampson_distance(*unpack(p), y_i, y_j), np.zeros(5), loss="soft_l1", f_scale=scale,
                        method="trf", x_scale=1.0, max_nfev=50)
    return unpack(res.x)


def rotation_from_bearings(y_i: np.ndarray, y_j: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rotation with ``b_j ≈ R b_i`` for unit bearings of normalized points (Kabsch).

    Args:
        y_i, y_j: (n, 2) normalized coordinates; w: (n,) weights or None.
    Returns:
        (3, 3) rotation.
    """
    bi = np.column_stack([y_i, np.ones(len(y_i))])
    bj = np.column_stack([y_j, np.ones(len(y_j))])
    bi /= np.linalg.norm(bi, axis=1, keepdims=True)
    bj /= np.linalg.norm(bj, axis=1, keepdims=True)
    w = np.ones(len(bi)) if w is None else w
    U, _, Vt = np.linalg.svd((bj * w[:, None]).T @ bi)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_only_residual_px(R: np.ndarray, x_i: np.ndarray, x_j: np.ndarray, K_i: np.ndarray, K_j: np.ndarray) -> np.ndarray:
    """(n,) distances in image j between x_j and x_i mapped by ``K_j R K_i⁻¹`` (pixels)."""
    Hinf = K_j @ R @ np.linalg.inv(K_i)
    p = np.column_stack([x_i, np.ones(len(x_i))]) @ Hinf.T
    return np.linalg.norm(p[:, :2] / p[:, 2:3] - x_j, axis=1)


def triangulation_depths(R: np.ndarray, t: np.ndarray, y_i: np.ndarray, y_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths ``(z_i, z_j)`` (n,) of the midpoint triangulation of each match under ``x_j = R x_i + t``.

    Solves ``z_i R b_i + t ≈ z_j b_j`` in the least-squares sense, point by point in
    closed form (a 2×2 system), with ``b = (y, 1)`` so that z is the depth.
    """
    bi = np.column_stack([y_i, np.ones(len(y_i))]) @ R.T
    bj = np.column_stack([y_j, np.ones(len(y_j))])
    a11 = np.sum(bi * bi, 1)
    a12 = -np.sum(bi * bj, 1)
    a22 = np.sum(bj * bj, 1)
    r1 = -bi @ t
    r2 = bj @ t
    det = a11 * a22 - a12 * a12
    det = np.where(np.abs(det) < 1e-15, 1e-15, det)  # parallel rays: depth at "infinity", sign kept
    return (a22 * r1 - a12 * r2) / det, (a11 * r2 - a12 * r1) / det


def pose_from_essential(E: np.ndarray, y_i: np.ndarray, y_j: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The decomposition of E that puts the most masked matches in front of both cameras.

    Unlike ``cv2.recoverPose``, distant points are not discarded (OpenCV drops points
    farther than 50 baselines, which rejects every match of a small-baseline pair).

    Returns:
        R (3, 3), unit t (3,), and (n,) bool: masked matches with positive depths.
    """
    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.ravel()
    best = None
    for R, tt in ((R1, t), (R1, -t), (R2, t), (R2, -t)):
        zi, zj = triangulation_depths(R, tt, y_i, y_j)
        front = mask & (zi > 0) & (zj > 0)
        if best is None or front.sum() > best[2].sum():
            best = (R, tt / np.linalg.norm(tt), front)
    return best


def estimate_pair(x_i: np.ndarray, x_j: np.ndarray, K_i: np.ndarray, K_j: np.ndarray,
                  config: TwoViewConfig | None = None, pixel_scale: float = 1.0) -> PairGeometry:
    """Relative pose of one pair from matched pixels (pure function).

    Args:
        x_i, x_j: (n, 2) matched pixel coordinates in images i and j.
        K_i, K_j: (3, 3) intrinsics.
        config: options.
        pixel_scale: full-resolution pixels per extraction-size pixel (threshold scaling).
    Returns:
        :class:`PairGeometry`.
    """
    config = config or TwoViewConfig()
    n = len(x_i)
    if x_i.shape != (n, 2) or x_j.shape != (n, 2):
        raise ValueError(f"x_i.shape={x_i.shape}, x_j.shape={x_j.shape} but expected two (n, 2) arrays")
    if n < config.min_matches:
        return PairGeometry(False, f"too few matches ({n} < min_matches={config.min_matches})", n_matches=n)
    y_i = _normalize(x_i.astype(np.float64), K_i)
    y_j = _normalize(x_j.astype(np.float64), K_j)
    f = 0.25 * (K_i[0, 0] + K_i[1, 1] + K_j[0, 0] + K_j[1, 1])
    thr_px = config.threshold_px * pixel_scale
    cv2.setRNGSeed(config.seed)
    E, mask = cv2.findEssentialMat(y_i, y_j, np.eye(3), method=_METHODS[config.method], prob=config.confidence,
                                   threshold=thr_px / f, maxIters=config.max_iters)
    if E is None or mask is None or E.shape[0] < 3:
        return PairGeometry(False, "essential matrix estimation failed (no model found)", n_matches=n)
    E = E[:3]  # several solutions may be stacked; the first is the best scoring
    mask = mask.ravel().astype(bool)
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
        R_r, t_r = refine_pose(R, t, y_i[inl], y_j[inl], thr_px / f)
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
        Hm, hmask = cv2.findHomography(x_i[mask].astype(np.float64), x_j[mask].astype(np.float64), cv2.RANSAC,
                                       2.0 * thr_px, maxIters=2000, confidence=0.999)
        n_H = int(hmask.sum()) if hmask is not None else 0
    geom = PairGeometry(True, "", R, t, inl, n, n_E, n_in, n_H, tri, parallax,
                        small_baseline=bool(tri < config.min_triangulation_deg),
                        planar=bool(n_H >= config.planar_ratio * max(n_E, 1)))
    if n_in < config.min_inliers:
        geom.ok = False
        geom.reason = f"too few inliers in front of both cameras ({n_in} < min_inliers={config.min_inliers})"
    return geom


@dataclass
class TwoViewData:
    """The output of :func:`main` (see :func:`load_two_view`).

    Attributes:
        vg: ViewGraph (allow_isolated=True) with R_rel, inliers and per-edge stats.
        K: (N, 3, 3) intrinsics; sizes: (N, 2) image sizes (w, h).
        rejected: list of ``{pair, names, n_matches, n_inliers, reason}``.
        offsets: (M+1,) start of each edge's correspondences.
        x_i, x_j: (total, 2) inlier pixel coordinates (full resolution).
        kp_i, kp_j: (total,) keypoint indices of the inliers in the features.
    """

    vg: ViewGraph
    K: np.ndarray
    sizes: np.ndarray
    rejected: list[dict]
    offsets: np.ndarray
    x_i: np.ndarray
    x_j: np.ndarray
    kp_i: np.ndarray
    kp_j: np.ndarray

    def correspondences(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Inlier pixel coordinates ``(x_i (n, 2), x_j (n, 2))`` of edge k (i = edges[k, 0])."""
        if not 0 <= k < self.vg.n_edges:
            raise IndexError(f"edge index {k} out of range for {self.vg.n_edges} edges")
        s, e = int(self.offsets[k]), int(self.offsets[k + 1])
        return self.x_i[s:e], self.x_j[s:e]


def main(work: Path, config: TwoViewConfig | None = None, overwrite: bool = False, progress: bool = True) -> Path:
    """Estimate the relative pose of every matched pair of ``work``.

    Returns:
        path of the ViewGraph file ``WORK/two_view-<hash>.npz``.
    """
    config = config or TwoViewConfig()
    work = Path(work)
    t_start = time.perf_counter()
    logger.info("two_view: %s", config)
    fs = load_features(work)
    ms = load_matches(work)
    if ms.names != fs.names:
        raise InputFileError(f"{work}: the matches were computed for other images than the current features; "
                             f"re-run `python -m pipeline.matching --work {work}`")
    digest = hashlib.sha1(json.dumps([fs.digest, ms.digest, config.key()]).encode()).hexdigest()[:12]
    vg_path = work / f"two_view-{digest}.npz"
    corr_path = work / f"two_view-{digest}-corr.npz"
    man_path = work / MANIFEST
    if not overwrite and vg_path.is_file() and corr_path.is_file() and man_path.is_file():
        try:
            man = json.loads(man_path.read_text())
        except json.JSONDecodeError:
            man = {}
        if man.get("digest") == digest:
            logger.info("two_view: %s is up to date; skipping (use --overwrite to redo)", vg_path)
            write_json(man_path, {**man, "n_computed": 0})
            return vg_path
    max_size = fs.config.max_image_size if fs.config is not None else 0
    scale = np.ones(len(fs.names))
    if max_size > 0:
        scale = np.maximum(fs.sizes.max(axis=1) / max_size, 1.0)

    def job(p: int) -> PairGeometry:
        a, b = ms.pairs[p]
        m = ms.matches[p]
        return estimate_pair(fs.keypoints[a][m[:, 0]], fs.keypoints[b][m[:, 1]], fs.K[a], fs.K[b], config,
                             pixel_scale=float(0.5 * (scale[a] + scale[b])))

    with ThreadPoolExecutor(max_workers=config.workers) as pool:
        geoms = list(tqdm(pool.map(job, range(len(ms.pairs))), total=len(ms.pairs), desc="two-view", unit="pair",
                          disable=not progress))
    acc = [p for p, g in enumerate(geoms) if g.ok]
    rejected = [
        {"pair": [int(ms.pairs[p][0]), int(ms.pairs[p][1])], "names": [fs.names[ms.pairs[p][0]], fs.names[ms.pairs[p][1]]],
         "n_matches": g.n_matches, "n_inliers": g.n_inliers if g.n_inliers else g.n_inliers_E, "reason": g.reason}
        for p, g in enumerate(geoms) if not g.ok
    ]
    edges = ms.pairs[acc].reshape(-1, 2)
    G = [geoms[p] for p in acc]
    stats = {
        "t": np.array([g.t for g in G]).reshape(-1, 3),
        "n_matches": np.array([g.n_matches for g in G], np.int64),
        "n_inliers_E": np.array([g.n_inliers_E for g in G], np.int64),
        "n_inliers_H": np.array([g.n_inliers_H for g in G], np.int64),
        "h_ratio": np.array([g.n_inliers_H / max(g.n_inliers_E, 1) for g in G], float),
        "median_triangulation_deg": np.array([g.median_triangulation_deg for g in G], float),
        "median_parallax_px": np.array([g.median_parallax_px for g in G], float),
        "small_baseline": np.array([g.small_baseline for g in G], bool),
        "planar": np.array([g.planar for g in G], bool),
    }
    stats["degenerate"] = stats["small_baseline"] | stats["planar"]
    vg = ViewGraph(list(fs.names), edges, np.array([g.R for g in G]).reshape(-1, 3, 3),
                   inliers=np.array([g.n_inliers for g in G], np.int64), stats=stats, allow_isolated=True)
    kp_i, kp_j, xi, xj = [], [], [], []
    for p, g in zip(acc, G):
        a, b = ms.pairs[p]
        m = ms.matches[p][g.inlier_mask]
        kp_i.append(m[:, 0])
        kp_j.append(m[:, 1])
        xi.append(fs.keypoints[a][m[:, 0]])
        xj.append(fs.keypoints[b][m[:, 1]])
    counts = np.array([len(k) for k in kp_i], np.int64)

    def cat(arrs: list[np.ndarray], shape: tuple[int, ...], dtype) -> np.ndarray:
        return np.concatenate(arrs).astype(dtype) if arrs else np.zeros(shape, dtype)

    save_npz(corr_path, K=fs.K, sizes=fs.sizes, offsets=np.concatenate([[0], np.cumsum(counts)]),
             x_i=cat(xi, (0, 2), np.float64), x_j=cat(xj, (0, 2), np.float64),
             kp_i=cat(kp_i, (0,), np.int32), kp_j=cat(kp_j, (0,), np.int32))
    vg.save(vg_path)
    n_deg = int(stats["degenerate"].sum())
    reasons: dict[str, int] = {}
    for r in rejected:
        key = r["reason"].split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    write_json(man_path, {
        "format": "rotavg-two-view",
        "viewgraph": vg_path.name,
        "correspondences": corr_path.name,
        "digest": digest,
        "features_digest": fs.digest,
        "matches_digest": ms.digest,
        "config": dataclasses.asdict(config),
        "config_hash": config_hash(config),
        "n_pairs": int(len(ms.pairs)),
        "n_accepted": int(len(acc)),
        "n_rejected": len(rejected),
        "n_degenerate": n_deg,
        "n_small_baseline": int(stats["small_baseline"].sum()),
        "n_planar": int(stats["planar"].sum()),
        "n_computed": int(len(ms.pairs)),
        "isolated": [fs.names[k] for k in np.flatnonzero(vg.degrees() == 0)],
        "rejected": rejected,
    })
    logger.info("two_view: %d of %d pairs accepted (%d flagged near-degenerate), %d rejected %s in %.1f s",
                len(acc), len(ms.pairs), n_deg, len(rejected), reasons or "", time.perf_counter() - t_start)
    iso = np.flatnonzero(vg.degrees() == 0)
    if len(iso):
        logger.warning("%d camera(s) have no accepted pair: %s", len(iso), ", ".join(fs.names[k] for k in iso[:5]))
    return vg_path


def load_two_view(work: Path) -> TwoViewData:
    """Read the result of :func:`main`: ViewGraph, K, sizes, rejected pairs and correspondences."""
    work = Path(work)
    man_path = work / MANIFEST
    if not man_path.is_file():
        raise InputFileError(f"{man_path} not found: run `python -m pipeline.two_view --work {work}` first")
    man = json.loads(man_path.read_text())
    vg = ViewGraph.load(work / man["viewgraph"], allow_isolated=True)
    try:
        with np.load(work / man["correspondences"]) as d:
            arr = {k: d[k] for k in d.files}
    except (OSError, KeyError) as exc:
        raise InputFileError(f"{work / man['correspondences']} unreadable ({exc}); re-run pipeline.two_view --overwrite") from None
    return TwoViewData(vg, arr["K"], arr["sizes"], list(man["rejected"]), arr["offsets"], arr["x_i"], arr["x_j"],
                       arr["kp_i"], arr["kp_j"])


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli
    from pipeline.core.config import load_yaml, stage_config

    p = argparse.ArgumentParser(prog="python -m pipeline.two_view", description="5-point RANSAC relative poses of the matched pairs of WORK.")
    p.add_argument("--work", type=Path, required=True, help="WORK folder written by pipeline.features and pipeline.matching")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'two_view' section is used")
    p.add_argument("--method", choices=sorted(_METHODS), default=None, help="robust estimator (default magsac)")
    p.add_argument("--threshold", type=float, default=None, help="inlier threshold, pixels at extraction size (default 1.0)")
    p.add_argument("--confidence", type=float, default=None, help="RANSAC confidence (default 0.999)")
    p.add_argument("--min-inliers", type=int, default=None)
    p.add_argument("--overwrite", action="store_true", help="estimate all pairs again")

    def body(a: argparse.Namespace) -> int:
        cfg = stage_config(TwoViewConfig, load_yaml(a.config), "two_view", method=a.method, threshold_px=a.threshold,
                           confidence=a.confidence, min_inliers=a.min_inliers)
        print(main(a.work, cfg, overwrite=a.overwrite, progress=not a.quiet))
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
