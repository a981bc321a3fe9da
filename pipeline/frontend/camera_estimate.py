"""Unknown intrinsics from the view graph: one radial distortion parameter, then the focal length.

The estimation behind the cameras stage (:mod:`pipeline.frontend.camera_stage`), on
arrays: the pairs' putative matches in, a focal length (and κ) out. Per-pair work
goes through a ``pmap(tag, tasks, worker)`` the caller provides (the stage runs it
on an executor with an item store, so that it resumes per pair; tests pass
:func:`serial_map`). The kernels are :mod:`pipeline.frontend.focal` and
:mod:`pipeline.frontend.radial`.

Focal (:func:`estimate_focal`), a focal shared by a group of images:

1. F per pair (pycolmap LO-RANSAC at ``threshold_px``); pairs with fewer than
   ``min_inliers`` inliers, or a homography explaining ``max_h_ratio`` of them, are left out;
2. each pair's profile over a coarse log grid of focal lengths, the joint
   ``profile+rotcons`` cost (or ``profile``), its minimum;
3. the profiles again on finer grids between the neighbours of the minimum
   (``refine_levels``), and the joint minimum over all grids (with the coarse grid's
   weighting), refined by a parabola.

An EXIF focal is a prior, not the truth: the search is first confined to
``[f/exif_range, f·exif_range]``; a minimum at its edge means the view graph
disagrees with EXIF, and the whole range is searched instead.

Radial (:func:`estimate_radial`): a loose F-RANSAC on the measured pixels and κ on a
coarse grid; κ is kept only if a quasi-likelihood ratio test (the drop discounted by the
pairs' disagreement beyond their noise) prefers it to κ = 0; then F
again on the points undistorted with it and κ on a fine grid around it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Callable, Literal, Sequence

import numpy as np

from pipeline.core.config import Config, option
from pipeline.frontend import focal as fk
from pipeline.frontend import radial as rk
from pipeline.frontend.distortion import radial_undistort

__all__ = ["CamerasConfig", "FocalEstimate", "RadialEstimate", "estimate_focal", "estimate_radial", "serial_map",
           "PairMap"]

logger = logging.getLogger(__name__)

PairMap = Callable[[str, list[tuple], Callable[[list[tuple]], list[dict[str, Any]]]], list[dict[str, Any]]]


@dataclass(frozen=True, kw_only=True)
class CamerasConfig(Config):
    """Options of the cameras stage (YAML section ``cameras``)."""

    SECTION = "cameras"

    estimate_focal: bool = option(True, "estimate the focal length of images that no K file describes (EXIF is a "
                                        "prior); false keeps the EXIF or default focal")
    focal_method: Literal["profile+rotcons", "profile", "poselib"] = option(
        "profile+rotcons", "profile+rotcons: the pairs' Sampson profile likelihood plus rotation consistency "
                           "around the graph's cycles; profile: the first alone; poselib: the median of PoseLib's "
                           "6-point shared-focal solver over the pairs")
    radial: Literal["auto", "estimate", "off"] = option(
        "auto", "one radial distortion parameter: auto estimates it for images no camera file describes; estimate "
                "also for images with a K file that gives no distortion; off never (given distortion is still used)")
    evidence: Literal["normal", "features"] = option(
        "normal", "what the focal and distortion are estimated from: normal re-detects the images whose contrast "
                  "threshold the features stage lowered (low texture) at the normal threshold and matches their "
                  "pairs again; features: the features stage's keypoints and matches as they are")
    threshold_px: float = option(1.0, "F-RANSAC inlier threshold (px at the feature-extraction size)", gt=0)
    max_trials: int = option(10000, "F-RANSAC iteration cap per pair", ge=100)
    min_inliers: int = option(30, "pairs with fewer F inliers are not used", ge=8)
    max_h_ratio: float = option(0.8, "pairs whose homography explains this share of the F inliers are not used "
                                     "(planar or zero baseline: their F says nothing about f)", gt=0, le=1)
    max_points: int = option(600, "inliers per pair used in the profiles (a seeded random subset)", ge=20)
    focal_range: tuple[float, ...] = option((0.3, 5.0), "focal search range, as factors of max(w, h)")
    grid_points: int = option(25, "points of the coarse log grid of focal lengths", ge=5)
    refine_points: int = option(9, "points of each finer grid, between the neighbours of the current minimum", ge=3)
    refine_levels: int = option(2, "finer grids after the coarse one (each narrows the spacing ~5×)", ge=0)
    exif_range: float = option(1.5, "an EXIF focal confines the search to [f/exif_range, f·exif_range]", gt=1)
    loss_px: float = option(2.0, "Cauchy scale of the Sampson distances (px)", gt=0)
    cap: float = option(25.0, "a pair's Δχ² counts fully up to about this, then logarithmically", gt=0)
    rotation_loss_deg: float = option(2.0, "Cauchy scale of the rotation-consistency residuals (deg)", gt=0)
    max_focal_sd: float = option(0.05, "an estimated focal whose leave-one-image-out (jackknife) relative sd "
                                       "exceeds this is flagged as poorly determined (the jackknife is "
                                       "conservative: 1.6% on a clean 6-view graph whose error is 0.8%)", gt=0)
    min_pairs: int = option(3, "fewer usable pairs leave a camera group's focal at its prior", ge=1)
    per_image_focal: Literal["auto", "off"] = option(
        "auto", "auto: pycolmap's view-graph calibration also gives every estimated image its own focal, from all "
                "its pairs (images of different cameras or zooms); those replace the group focal lengths where "
                "the pairs' rotations are more consistent around the graph with them; off: group focal lengths only")
    per_image_level: float = option(0.999, "per-image focal lengths replace the group ones only where they lower "
                                           "the rotation-consistency cost significantly at this level (an F test "
                                           "for their extra parameters: on one camera they fit a little better by "
                                           "chance)", gt=0, lt=1)
    radial_range: float = option(0.4, "κ searched in [-radial_range, radial_range] (κ at the scale max(w, h))", gt=0)
    radial_grid_points: int = option(33, "points of the coarse κ grid", ge=5)
    radial_refine: tuple[float, ...] = option((0.05, 21), "half-width and points of the fine κ grid")
    radial_loose_px: float = option(3.0, "F-RANSAC threshold before κ is known (px at extraction size)", gt=0)
    radial_chi2: float = option(10.83, "κ is kept when its drop of the joint cost, divided by the pairs' "
                                       "dispersion, passes F(1, pairs − 1) at the level this χ²₁ quantile has "
                                       "(10.83: 99.9%)", gt=0)
    seed: int = option(0, "RANSAC and subset seed")
    workers: int = option(2, "processes estimating pairs (1 = in this process)", ge=1, runtime=True)
    chunk_size: int = option(4, "pairs per task sent to a worker (and per resumable chunk)", ge=1, runtime=True)
    progress: bool = option(True, "show a progress bar", runtime=True)

    def check(self) -> None:
        from pipeline.core.errors import ConfigError  # noqa: PLC0415

        lo_hi = self.focal_range
        if len(lo_hi) != 2 or not 0 < lo_hi[0] < lo_hi[1]:
            raise ConfigError(f"[cameras] focal_range={list(lo_hi)} but expected two factors 0 < lo < hi")
        if len(self.radial_refine) != 2 or self.radial_refine[0] <= 0 or self.radial_refine[1] < 3:
            raise ConfigError(f"[cameras] radial_refine={list(self.radial_refine)} but expected a half-width > 0 "
                              "and >= 3 points")


def serial_map(tag: str, tasks: list[tuple], worker: Callable[[list[tuple]], list[dict[str, Any]]]
               ) -> list[dict[str, Any]]:
    """A :data:`PairMap` that runs everything here, with no cache."""
    return worker(tasks)


# ----------------------------------------------------------------- per-pair workers
def f_ransac_chunk(tasks: list[tuple], config: CamerasConfig) -> list[dict[str, Any]]:
    """Worker: F of each ``(x1, x2, threshold_px, seed)`` and the homography ratio of its inliers."""
    out = []
    for x1, x2, thr, seed in tasks:
        r = fk.fundamental_ransac(x1, x2, float(thr), int(seed), config.max_trials, config.min_inliers)
        if r is None:
            out.append({"ok": False, "F": np.zeros((3, 3)), "inliers": np.zeros(0, np.int64), "h_ratio": 1.0})
            continue
        h = fk.homography_ratio(x1[r.inliers], x2[r.inliers], float(thr), int(seed))
        out.append({"ok": True, "F": r.F, "inliers": r.inliers.astype(np.int64), "h_ratio": h})
    return out


def focal_profile_chunk(tasks: list[tuple], config: CamerasConfig) -> list[dict[str, Any]]:
    """Worker: :func:`pipeline.frontend.focal.pair_profile` of each ``(x1, x2, F, pp1, pp2, f1, f2[, ends])``
    (``ends``: (2, 3, 4) the poses ``[R | t]`` just before and after the path)."""
    out = []
    for x1, x2, F, pp1, pp2, f1, f2, *rest in tasks:
        ends = tuple((P[:, :3], P[:, 3]) for P in rest[0]) if rest else None
        cost, R, s2, t = fk.pair_profile(x1, x2, F, pp1, pp2, f1, f2, config.loss_px, ends=ends)
        out.append({"cost": cost, "R": R, "sigma2": s2, "t": t})
    return out


def radial_profile_chunk(tasks: list[tuple], config: CamerasConfig) -> list[dict[str, Any]]:
    """Worker: :func:`pipeline.frontend.radial.radial_profile` of each ``(x1, x2, F, c, s, grid, g0)``."""
    out = []
    for x1, x2, F, c, s, grid, g0 in tasks:
        cost, s2 = rk.radial_profile(x1, x2, F, c, float(s), grid, config.loss_px, start=int(g0))
        out.append({"cost": cost, "sigma2": s2})
    return out


def poselib_chunk(tasks: list[tuple], config: CamerasConfig) -> list[dict[str, Any]]:
    """Worker: PoseLib's shared-focal solver on each ``(x1, x2, pp, threshold_px, seed)``."""
    out = []
    for x1, x2, pp, thr, seed in tasks:
        f, n = fk.poselib_shared_focal(x1, x2, pp, float(thr), int(seed), config.max_trials)
        out.append({"f": f, "n_inliers": n})
    return out


#: The per-pair profile's version, part of its cache keys: 2 sweeps both ways and returns the translations.
PROFILE_VERSION = "sweep2"


# ------------------------------------------------------------------------ helpers
def _subset(x1: np.ndarray, x2: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    if len(x1) <= n:
        return x1, x2
    sel = np.sort(np.random.default_rng([seed, 4099]).choice(len(x1), n, replace=False))
    return x1[sel], x2[sel]


def _verified(x1s: Sequence[np.ndarray], x2s: Sequence[np.ndarray], thr: np.ndarray, config: CamerasConfig,
              pmap: PairMap, tag: str) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """F of every pair; returns the mask of usable pairs and the results."""
    import functools  # noqa: PLC0415

    tasks = [(np.asarray(a, np.float64), np.asarray(b, np.float64), float(t), config.seed + k)
             for k, (a, b, t) in enumerate(zip(x1s, x2s, thr))]
    res = pmap(tag, tasks, functools.partial(f_ransac_chunk, config=config))
    ok = np.array([bool(r["ok"]) and float(r["h_ratio"]) < config.max_h_ratio for r in res], bool)
    return ok, res


# -------------------------------------------------------------------------- focal
@dataclass
class FocalEstimate:
    """A group's focal estimate and what it rests on.

    Attributes:
        f: the focal length (px), or NaN if it could not be estimated.
        method: the method used.  prior: ``"exif <f> px"`` or ``""``.
        n_pairs: pairs used.  grid: (G,) focal grid.  cost: (G,) joint cost on it.
        per_pair: (n_pairs,) each pair's own best grid focal.
        note: why the prior was overruled, why no estimate was made, or why it is poorly determined.
        sd_rel: leave-one-image-out (jackknife) sd of log f (≈ relative sd).
        determined: False when ``sd_rel`` exceeds ``max_focal_sd`` (a flag for the report); the summary says False
            too where no estimate was made (``f`` NaN).
    """

    f: float
    method: str
    prior: str = ""
    n_pairs: int = 0
    grid: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cost: np.ndarray = field(default_factory=lambda: np.zeros(0))
    per_pair: np.ndarray = field(default_factory=lambda: np.zeros(0))
    note: str = ""
    sd_rel: float = float("nan")
    determined: bool = True

    def summary(self) -> dict[str, Any]:
        return {"f": self.f, "method": self.method, "prior": self.prior, "n_pairs": self.n_pairs, "note": self.note,
                "sd_rel": self.sd_rel, "determined": bool(self.determined and np.isfinite(self.f)),  # none: not
                "grid": self.grid.tolist(), "cost": self.cost.tolist(),
                "per_pair_median": float(np.median(self.per_pair)) if len(self.per_pair) else None}


def _profiles(x1s: list, x2s: list, Fs: list, pp: np.ndarray, grid: np.ndarray, config: CamerasConfig,
              pmap: PairMap, tag: str, ends: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every pair's profile on ``grid``: cost (M, G), rotations (M, G, 3, 3), σ² (M,), translations (M, G, 3).

    ``ends`` (M, 2, 3, 4): each pair's poses ``[R | t]`` at the points just outside ``grid`` (a finer grid's
    coarse neighbours), where its sweeps start from too."""
    import functools  # noqa: PLC0415

    tag = f"{tag}-{PROFILE_VERSION}"  # results of an earlier sweep (no translations) are not reused
    tasks = [(a, b, F, pp, pp, grid, grid) + (() if ends is None else (ends[k],))
             for k, (a, b, F) in enumerate(zip(x1s, x2s, Fs))]
    res = pmap(tag, tasks, functools.partial(focal_profile_chunk, config=config))
    return (np.array([r["cost"] for r in res]).reshape(-1, len(grid)),
            np.array([r["R"] for r in res]).reshape(-1, len(grid), 3, 3), np.array([float(r["sigma2"]) for r in res]),
            np.array([r["t"] for r in res]).reshape(-1, len(grid), 3))


def _joint(grid, cost, R, s2, edges, n, config, scales=None) -> tuple[float, np.ndarray, tuple[float, float]]:
    prof = fk.profile_cost(cost, s2, config.cap)
    rot = (fk.rotation_consistency_cost(R, edges, n, config.rotation_loss_deg)
           if config.focal_method == "profile+rotcons" else None)
    return fk.joint_focal(grid, prof, rot, scales)


def _jackknife_sd(grid, cost, R, s2, edges, n, config, scales) -> float:
    """Leave-one-image-out (jackknife) standard deviation of log f: how much the focal rests on single images.

    Each image with pairs is left out in turn with all its pairs, and the joint minimum is found again on the
    same grid and weighting; ``sd = sqrt((m − 1)/m Σ (log f₍ᵢ₎ − mean)²)`` over the m images with pairs (Efron
    & Stein). A focal fixed by one loop, one pair or a cut vertex moves when it goes, however sharp the full
    cost's minimum. Infinite when leaving an image out leaves fewer than ``min_pairs`` pairs.
    """
    imgs = np.unique(edges)
    logs = []
    for i in imgs:  # one joint minimum per image (the averaging inside is vectorized over edges)
        keep = (edges != i).all(axis=1)
        if keep.sum() < config.min_pairs:
            return float("inf")
        logs.append(np.log(_joint(grid, cost[keep], R[keep], s2[keep], edges[keep], n, config, scales)[0]))
    m = len(logs)
    return float(np.sqrt((m - 1) / m * np.sum((np.array(logs) - np.mean(logs)) ** 2))) if m > 1 else float("inf")


def _search(x1s, x2s, Fs, edges, n, pp, lo, hi, config, pmap, tag) -> tuple[float, np.ndarray, np.ndarray, np.ndarray,
                                                                            float]:
    """Coarse grid, then finer grids between the neighbours of the minimum; returns f, the merged grid, its cost,
    the pairs' own argmins and the jackknife sd of log f."""
    grid = fk.log_grid(lo, hi, config.grid_points)
    cost, R, s2, t = _profiles(x1s, x2s, Fs, pp, grid, config, pmap, f"{tag}-coarse")
    f, J, scales = _joint(grid, cost, R, s2, edges, n, config)
    for level in range(config.refine_levels):  # each level narrows the spacing by (refine_points + 1) / 2
        k = int(np.argmin(J))
        lo_k, hi_k = max(k - 1, 0), min(k + 1, len(grid) - 1)
        fine = fk.log_grid(grid[lo_k], grid[hi_k], config.refine_points + 2)[1:-1]
        fine = fine[np.abs(np.log(fine[:, None] / grid[None, :])).min(axis=1) > 1e-9]  # no point twice
        ends = np.concatenate([R[:, [lo_k, hi_k]], t[:, [lo_k, hi_k], :, None]], axis=3)  # (M, 2, 3, 4)
        c2, R2, _, t2 = _profiles(x1s, x2s, Fs, pp, fine, config, pmap, f"{tag}-fine{level}", ends)
        grid = np.concatenate([grid, fine])
        order = np.argsort(grid, kind="stable")
        grid, cost = grid[order], np.concatenate([cost, c2], 1)[:, order]
        R, t = np.concatenate([R, R2], 1)[:, order], np.concatenate([t, t2], 1)[:, order]
        f, J, _ = _joint(grid, cost, R, s2, edges, n, config, scales)
    sd = _jackknife_sd(grid, cost, R, s2, edges, n, config, scales)
    return f, grid, J, grid[np.argmin(cost, axis=1)], sd


def estimate_focal(x1s: Sequence[np.ndarray], x2s: Sequence[np.ndarray], pairs: np.ndarray, n_images: int,
                   size: tuple[int, int], thr: np.ndarray, config: CamerasConfig, pmap: PairMap = serial_map,
                   prior: float | None = None, tag: str = "focal") -> FocalEstimate:
    """One focal length shared by ``n_images`` images of one size, from their pairs' matches.

    Args:
        x1s, x2s: per pair (n_k, 2) putative matches (px, undistorted).
        pairs: (M, 2) image indices in ``[0, n_images)``.
        size: (w, h) of the images.  thr: (M,) F-RANSAC threshold of each pair (px, full size).
        config: options.  pmap: where per-pair work runs.
        prior: an EXIF focal (px), or None.  tag: prefix of the per-pair work's keys.
    Returns:
        :class:`FocalEstimate` (``f`` NaN when fewer than ``config.min_pairs`` pairs are usable).
    """
    w, h = size
    pp = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    prior_txt = f"exif {prior:.1f} px" if prior else ""
    if config.focal_method == "poselib":
        return _poselib(x1s, x2s, pp, thr, config, pmap, prior_txt, tag)
    ok, res = _verified(x1s, x2s, thr, config, pmap, f"{tag}-F")
    idx = np.flatnonzero(ok)
    if len(idx) < config.min_pairs:
        return FocalEstimate(float("nan"), config.focal_method, prior_txt, len(idx),
                             note=f"{len(idx)} usable pairs < min_pairs={config.min_pairs}")
    x1u, x2u = zip(*[_subset(x1s[k][res[k]["inliers"]], x2s[k][res[k]["inliers"]], config.max_points,
                             config.seed + int(k)) for k in idx])
    Fs = [res[k]["F"] for k in idx]
    edges, s = np.asarray(pairs)[idx], float(max(w, h))
    lo, hi = config.focal_range[0] * s, config.focal_range[1] * s
    note = ""
    if prior:
        f, grid, J, per, sd = _search(list(x1u), list(x2u), Fs, edges, n_images, pp, prior / config.exif_range,
                                  prior * config.exif_range, config, pmap, f"{tag}-exif")
        at_edge = min(f / grid[0], grid[-1] / f) < 1.0 + 1e-9 or int(np.argmin(J)) in (0, len(J) - 1)
        if not at_edge:
            return _flagged(FocalEstimate(f, config.focal_method, prior_txt, len(idx), grid, J, per, sd_rel=sd),
                            config)
        note = (f"the view graph disagrees with the EXIF focal {prior:.1f} px (its minimum is at the edge of "
                f"[f/{config.exif_range:g}, f·{config.exif_range:g}]); searched {config.focal_range[0]:g}–"
                f"{config.focal_range[1]:g} × max(w, h)")
        logger.warning("cameras: %s", note)
    f, grid, J, per, sd = _search(list(x1u), list(x2u), Fs, edges, n_images, pp, lo, hi, config, pmap, tag)
    return _flagged(FocalEstimate(f, config.focal_method, prior_txt, len(idx), grid, J, per, note, sd), config)


def _flagged(est: FocalEstimate, config: CamerasConfig) -> FocalEstimate:
    """Mark a focal whose jackknife sd exceeds ``max_focal_sd`` as poorly determined, with the reason."""
    if est.sd_rel > config.max_focal_sd:
        est.determined = False
        why = (f"focal poorly determined: leaving one image out moves it by {100 * est.sd_rel:.1f}% (jackknife sd; "
               f"max_focal_sd {100 * config.max_focal_sd:g}%); the rotations may be off by degrees with no "
               f"inconsistency to show it; give a K for these images")
        est.note = f"{est.note}; {why}" if est.note else why
    return est


def _poselib(x1s, x2s, pp, thr, config, pmap, prior_txt, tag) -> FocalEstimate:
    import functools  # noqa: PLC0415

    tasks = [(np.asarray(a, np.float64), np.asarray(b, np.float64), pp, float(t), config.seed + k)
             for k, (a, b, t) in enumerate(zip(x1s, x2s, thr))]
    res = pmap(f"{tag}-poselib", tasks, functools.partial(poselib_chunk, config=config))
    f = np.array([float(r["f"]) for r in res])
    good = np.isfinite(f) & (np.array([int(r["n_inliers"]) for r in res]) >= config.min_inliers)
    if good.sum() < config.min_pairs:
        return FocalEstimate(float("nan"), "poselib", prior_txt, int(good.sum()),
                             note=f"{int(good.sum())} usable pairs < min_pairs={config.min_pairs}")
    return FocalEstimate(float(np.median(f[good])), "poselib", prior_txt, int(good.sum()), per_pair=f[good])


# ------------------------------------------------------------------------- radial
@dataclass
class RadialEstimate:
    """κ of the one-parameter radial family at scale ``s`` (see :mod:`pipeline.frontend.radial`).

    Attributes:
        kappa: κ (0 when not significant).  kappa_raw: the minimizer before the test.
        significant: the quasi-likelihood ratio test kept it (:func:`pipeline.frontend.radial.kappa_test`).
        delta_chi2: its drop of the joint cost.  dispersion: the pairs' disagreement φ the drop is divided by.
        critical: the threshold ``delta_chi2 / max(φ, 1)`` had to pass.
        s: nominal scale (px).  c: (2,) centre.  n_pairs: pairs used.  note: why no estimate.
    """

    kappa: float
    kappa_raw: float
    significant: bool
    delta_chi2: float
    s: float
    c: np.ndarray
    n_pairs: int
    note: str = ""
    dispersion: float = 1.0
    critical: float = float("nan")

    def summary(self) -> dict[str, Any]:
        return {"kappa": self.kappa, "kappa_raw": self.kappa_raw, "significant": self.significant,
                "delta_chi2": self.delta_chi2, "dispersion": self.dispersion, "critical": self.critical,
                "scale_px": self.s, "centre": self.c.tolist(), "n_pairs": self.n_pairs, "note": self.note}


def _radial_round(x1s, x2s, thr, c, s, kappa0, grid, config, pmap, tag
                  ) -> tuple[float, np.ndarray, int, np.ndarray, np.ndarray]:
    import functools  # noqa: PLC0415

    u1 = [radial_undistort(a, c, s, kappa0)[0] for a in x1s]
    u2 = [radial_undistort(b, c, s, kappa0)[0] for b in x2s]
    ok, res = _verified(u1, u2, thr, config, pmap, f"{tag}-F")
    idx = np.flatnonzero(ok)
    if len(idx) < config.min_pairs:
        return float("nan"), np.zeros(len(grid)), len(idx), np.zeros((0, len(grid))), np.zeros(0)
    g0 = int(np.argmin(np.abs(grid - kappa0)))
    tasks = []
    for k in idx:
        a, b = _subset(x1s[k][res[k]["inliers"]], x2s[k][res[k]["inliers"]], config.max_points, config.seed + int(k))
        tasks.append((a, b, res[k]["F"], c, s, grid, g0))
    out = pmap(f"{tag}-profile", tasks, functools.partial(radial_profile_chunk, config=config))
    cost = np.array([r["cost"] for r in out]).reshape(-1, len(grid))
    s2 = np.array([float(r["sigma2"]) for r in out])
    kappa, J = rk.joint_kappa(grid, cost, s2, config.cap)
    return kappa, J, len(idx), cost, s2


def estimate_radial(x1s: Sequence[np.ndarray], x2s: Sequence[np.ndarray], size: tuple[int, int], scale: np.ndarray,
                    config: CamerasConfig, pmap: PairMap = serial_map, tag: str = "radial") -> RadialEstimate:
    """κ of one camera group from its pairs' putative matches (measured pixels); no focal length needed.

    Args:
        x1s, x2s: per pair (n_k, 2) measured pixels.  size: (w, h).
        scale: (M,) full-size pixels per extraction pixel of each pair (thresholds).
        config: options.  pmap: where per-pair work runs.  tag: prefix of the work's keys.
    """
    w, h = size
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    s = float(max(w, h))
    x1s = [np.asarray(a, np.float64) for a in x1s]
    x2s = [np.asarray(b, np.float64) for b in x2s]
    r = config.radial_range
    coarse = np.linspace(-r, r, config.radial_grid_points)
    k0, _, n0, cost0, s20 = _radial_round(x1s, x2s, config.radial_loose_px * scale, c, s, 0.0, coarse, config, pmap,
                               f"{tag}-coarse")
    if not np.isfinite(k0):
        return RadialEstimate(0.0, float("nan"), False, 0.0, s, c, n0,
                              f"{n0} usable pairs < min_pairs={config.min_pairs}")
    significant, drop, phi, crit = rk.kappa_test(coarse, cost0, s20, k0, config.radial_chi2, config.cap)
    if not significant:
        return RadialEstimate(0.0, k0, False, drop, s, c, n0, dispersion=phi, critical=crit)
    half, n_fine = config.radial_refine
    fine = k0 + np.linspace(-half, half, int(n_fine))
    k1, _, n1, _, _ = _radial_round(x1s, x2s, config.threshold_px * scale, c, s, k0, fine, config, pmap, f"{tag}-fine")
    kappa = k1 if np.isfinite(k1) else k0
    return RadialEstimate(kappa, kappa, True, drop, s, c, n1 if np.isfinite(k1) else n0, dispersion=phi,
                          critical=crit)
