"""Refine averaged rotations with pycolmap's multi-view machinery: :func:`refine_rotations` (arrays in, result out).

From OUR averaged cam_from_world rotations, pycolmap does every multi-view step,
as GLOMAP does after its own rotation averaging (:mod:`pipeline.refine.mapper`):

1. edge filter: the pairs whose measured ``R_ij`` agrees with ``R_j R_iᵀ`` of the averaged
   rotations within ``edge_filter_deg`` (our robust averaging's verdict on each pair);
2. tracks from the kept inlier matches (:func:`pipeline.refine.tracks.build_tracks`); an
   image with fewer than ``min_image_observations`` track observations is not refined;
3. an in-memory COLMAP database and the starting reconstruction (:mod:`pipeline.refine.model`);
4. global positioning, iterative bundle adjustment, retriangulation and a final BA;
5. checks (:mod:`pipeline.refine.checks`): an image of known K refined more than ``max_change_deg`` from
   its averaged rotation (after one global alignment) keeps the averaged one (one without a K file keeps the
   refined one: ``max_change_known_only``); one the final model lost is chained from its refined neighbours;
6. the per-camera rotation covariance (:mod:`pipeline.refine.covariance`).

**Unknown intrinsics** (estimated, EXIF or default focal lengths; a K read from a file is
constant). Each such camera has one focal length and one radial term k1 (COLMAP's SIMPLE_RADIAL, as its
mappers model an unknown camera; ``radial: off`` gives SIMPLE_PINHOLE), k1 from 0 on the cameras stage's
undistorted keypoints, or, where that stage estimated a lens, from its k1 on the measured keypoints (``lens:
measured``: the lens about the principal point BA refines, not the image centre). With ``principal_point: auto``
the principal point is refined when every such camera has ``min_principal_point_images`` images and kept where
the model determines it (``max_principal_point_sd``) and it lies more than ``min_principal_point_offset`` off the
image centre, else fixed at the image centre; cameras of fewer images
(internet photos) are probed (:mod:`pipeline.refine.principal`). With them held, a focal length COLMAP's test
calls bogus is held at the cameras stage's estimate in a second run; one merely weakly determined
(``max_focal_sd``) stays refined, with a warning. Figures: ``notes/issue-13.md``.

**Images left out of the view graph** (``place_left_out``): one whose pairs make tracks (rejected only as weak) is
started from them (``R_start``, chained from the averaged rotations by :func:`pipeline.refine.checks.chain_starts`)
and refined with the others; it does not enter the alignment to the averaged frame, and where the final model
does not support it, it gets no rotation.

It never raises on a pycolmap failure: the status says ``failed`` and the averaged rotations are returned.
Conventions: ``R`` is cam_from_world; edge ``(i, j)``, ``i < j``, carries ``R_ij = R_j R_iᵀ`` and ``t_ij`` with
``x_j = R_ij x_i + t_ij`` (pycolmap's ``cam2_from_cam1``); pixel centres at integers (+0.5 into pycolmap).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

from pipeline.core.config import Config, option
from pipeline.core.errors import ConfigError
from pipeline.refine import mapper
from pipeline.refine.checks import checked_rotations, focal_check, kept_averaged
from pipeline.refine.covariance import camera_covariances, radial_corner_sd
from pipeline.refine.principal import principal_point_check, probe_principal_points
from pipeline.refine.model import (camera_groups, check_inputs, correspondence_cache, radial_terms,
                                   starting_reconstruction)
from pipeline.refine import tracks as tk

logger = logging.getLogger(__name__)

__all__ = ["RefineConfig", "RefineResult", "refine_rotations", "PRESETS"]

#: The schedules: GLOMAP's own (every track in positioning, 5 refinement rounds), and a
#: fast one (500 tracks per image in positioning, 1 round: about 3× less CPU).
PRESETS = {"glomap": {"positioning_tracks_per_image": 0, "refinement_rounds": 5},
           "fast": {"positioning_tracks_per_image": 500, "refinement_rounds": 1}}


@dataclass(frozen=True, kw_only=True)
class RefineConfig(Config):
    """Options of the refinement (YAML section ``refine``)."""

    SECTION = "refine"

    start: str = option("auto", "averaged rotations to start from: a method label (irls-h-l0.5, irls-l0.5, ...) "
                                "or auto (IRLS-H-l0.5 when it ran, else IRLS-l0.5, else the first method)")
    preset: Literal["glomap", "fast"] = option("glomap", "schedule: glomap (GLOMAP's) or fast (fewer tracks in "
                                                         "positioning, one refinement round)")
    positioning_tracks_per_image: int | None = option(None, "tracks per image in global positioning (0: all; "
                                                            "null: the preset's)", ge=0)
    refinement_rounds: int | None = option(None, "iterative_global_refinement rounds after retriangulation "
                                                 "(null: the preset's)", ge=0)
    max_change_deg: float = option(5.0, "a refined rotation farther than this from the averaged one keeps the "
                                        "averaged one (both are reported)", gt=0)
    max_change_known_only: bool = option(True, "max_change_deg only for images with a K file: an image whose "
                                               "intrinsics the refinement estimated keeps its refined rotation (its "
                                               "averaged one rested on the cameras stage's focal); warnings say so")
    radial: Literal["auto", "off"] = option("auto", "cameras without a K file: auto = SIMPLE_RADIAL, one k1 refined "
                                                    "from 0 on the cameras stage's undistorted keypoints (the lens "
                                                    "that stage left; as COLMAP's mappers do), off = SIMPLE_PINHOLE")
    lens: Literal["measured", "undistorted"] = option(
        "measured", "cameras whose lens the cameras stage estimated: measured = the measured keypoints, with COLMAP's "
                    "SIMPLE_RADIAL from the stage's k1 (the lens about the principal point the BA refines); "
                    "undistorted = the stage's keypoints undistorted about the image centre, k1 from 0")
    edge_filter_deg: float | None = option(5.0, "pairs farther than this from the averaged rotations are not "
                                                "used (null: every pair)", gt=0)
    weak_pairs: bool = option(True, "the inlier matches of the pairs the view graph rejected only because their "
                                    "rotation is poorly determined (weak H) also make tracks (edge_filter_deg applies)")
    place_left_out: bool = option(True, "an image the view graph left out whose pairs make tracks (weak_pairs) is "
                                        "started from them, chained from the averaged rotations, and refined; "
                                        "flagged (nothing but the refinement vouches for it)")
    min_track_views: int = option(3, "images a track must be seen in (a starved image keeps its shorter ones)", ge=2)
    track_consistency_px: float = option(10.0, "a track with two keypoints of one image farther apart is dropped",
                                         gt=0)
    min_image_observations: int = option(20, "an image with fewer track observations (or final 3D points) is "
                                             "not refined", ge=1)
    ba_iterations: int = option(3, "rounds of positions-only + joint bundle adjustment", ge=1)
    retriangulate: bool = option(True, "re-triangulate every image and refine before the final BA")
    dense_solver_max_images: int = option(50, "ceres' dense Schur solver up to this many images (0: sparse)", ge=0)
    max_angular_error_deg: float = option(1.0, "GLOMAP's angular reprojection filter after positioning", gt=0)
    max_normalized_error: float = option(0.01, "GLOMAP's normalized reprojection filter", gt=0)
    min_tri_angle_deg: float = option(1.0, "points triangulated under a smaller angle are removed", ge=0)
    huber_px: float = option(1.0, "Huber loss scale of the bundle adjustment, pixels", gt=0)
    principal_point: Literal["auto", "refined", "fixed"] = option(
        "auto", "principal points of cameras without a K file: auto (refined, kept where the model determines "
                "them, else fixed at the image centre), refined, or fixed")
    min_principal_point_images: int = option(3, "principal_point auto: refined only when every camera without a K "
                                                "file has at least this many images", ge=1)
    max_radial_sd: float = option(0.01, "radial auto: largest standard deviation of the radial term's displacement "
                                        "at the image corner, as a fraction of the image's longest side; above "
                                        "it the refinement runs again without one", gt=0)
    principal_point_misfit: float | None = option(
        1.3, "principal_point auto, a camera with fewer than min_principal_point_images images: after the run with "
             "the principal points held, a probe refines them all; they are refined (where determined and "
             "significantly off the centre) when the residual σ with them held is at least this many times σ with "
             "them refined (a misfit keypoint noise does not explain; null: no probe). On 20 internet imitations, "
             "refining helped at every ratio from 1.41 up (1.41–2.72) and cost at 6 of the 8 ratios of 1.02–1.21 "
             "(notes/issue-13.md)", ge=1)
    max_principal_point_sd: float = option(0.01, "principal_point auto: largest standard deviation of a refined "
                                                 "principal point, as a fraction of the image's longest side", gt=0)
    min_principal_point_offset: float = option(
        0.004, "principal_point auto: a refined principal point nearer the image centre than this fraction of the "
               "image's longest side is held at the centre, as COLMAP's mappers hold it (0: kept wherever determined); "
               "its real error is several times what pycolmap's covariance claims (notes/issue-13.md)", ge=0)
    max_focal_sd: float = option(0.01, "principal points not refined: a focal length whose one standard deviation "
                                        "moves the image corner by more than this share of the image's longest side "
                                        "is weakly determined (a warning, stats['focal_loose']); it stays refined", gt=0)
    min_focal_ratio: float = option(0.1, "principal points not refined: intrinsics with a focal length below this "
                                         "multiple of the image's longest side are bogus (COLMAP's test): the camera is "
                                         "held at the cameras stage's estimate in a second run", gt=0)
    max_focal_ratio: float = option(10.0, "the same test, above this multiple (COLMAP's max_focal_length_ratio)", gt=0)
    max_extra_param: float = option(1.0, "the same test: |k1| above this is bogus (COLMAP's max_extra_param)", gt=0)
    covariance: bool = option(True, "estimate each camera's rotation covariance")
    seed: int = option(0, "random seed of positioning and triangulation", ge=0)
    num_threads: int = option(-1, "threads for pycolmap (-1: all cores)", ge=-1, runtime=True)

    def check(self) -> None:
        if self.num_threads == 0:
            raise ConfigError("[refine] num_threads=0 but expected a positive count or -1 (all cores)")
        if not self.start.strip() or any(c.isspace() or c in "/\\" for c in self.start):
            raise ConfigError(f"[refine] start={self.start!r} but expected 'auto' or a method label such as irls-h-l0.5")
        if not self.min_focal_ratio < self.max_focal_ratio:
            raise ConfigError(f"[refine] min_focal_ratio={self.min_focal_ratio:g} is not below max_focal_ratio="
                              f"{self.max_focal_ratio:g}")

    def schedule(self) -> dict[str, int]:
        """The preset's values, overridden by the options given explicitly."""
        out = dict(PRESETS[self.preset])
        for k in out:
            if getattr(self, k) is not None:
                out[k] = int(getattr(self, k))
        return out


@dataclass
class RefineResult:
    """What :func:`refine_rotations` returns.

    Attributes:
        status: "ok" (every image with a start refined), "partial" (some kept the averaged
            rotation) or "failed" (none refined; ``R`` is the averaged set).
        R: (N, 3, 3) the rotations to use: refined where ``refined``, chained from refined neighbours where
            ``anchored``, averaged elsewhere, in the averaged rotations' world frame.
        R_init: (N, 3, 3) the averaged rotations (NaN for images without one).
        R_refined: (N, 3, 3) pycolmap's rotations aligned to the averaged frame, before the
            change check (NaN where the image is not in the final model).
        refined: (N,) bool.
        anchored: (N,) bool: not refined (lost by the final model) and chained from refined neighbours in ``R``.
        change_deg: (N,) angle between R_refined and R_init (NaN where not in the model).
        cov: (N, 3, 3) rotation covariance, rad², left perturbation ``R = exp([δ]×) R̂``,
            minimum-norm gauge; NaN where unavailable; None when not estimated.
        why: (N,) why each image kept its averaged rotation ("" where refined).
        reconstruction: the final pycolmap Reconstruction (None when a step failed).
        warnings: one line per problem.
        stats: counts, per-step times (``times``), σ of the reprojection error.
    """

    status: str
    R: np.ndarray
    R_init: np.ndarray
    R_refined: np.ndarray
    refined: np.ndarray
    change_deg: np.ndarray
    cov: np.ndarray | None
    why: list[str]
    reconstruction: Any = None
    warnings: list[str] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    anchored: np.ndarray | None = None


def _pycolmap() -> Any:
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before pycolmap's OpenMP runtime starts
    import pycolmap  # noqa: PLC0415

    pycolmap.logging.minloglevel = 0 if logger.isEnabledFor(logging.DEBUG) else 2
    return pycolmap


def refine_rotations(names: Sequence[str], K: np.ndarray, sizes: np.ndarray, keypoints: Sequence[np.ndarray],
                     edges: np.ndarray, match_offsets: np.ndarray, matches: np.ndarray, cam2_from_cam1: np.ndarray,
                     t_cam2_from_cam1: np.ndarray, R_init: np.ndarray, known_K: np.ndarray | bool = True,
                     config: RefineConfig | None = None, scratch: Path | None = None,
                     k1: np.ndarray | None = None, hold: np.ndarray | None = None,
                     R_start: np.ndarray | None = None) -> RefineResult:
    """Refine averaged rotations with pycolmap's global positioning, bundle adjustment and retriangulation.

    Args:
        names: N image names.
        K: (N, 3, 3) intrinsics (pixel centres at integers); a starting guess where not known.
        sizes: (N, 2) image sizes (width, height).
        keypoints: N arrays (n_i, 2) keypoint pixel coordinates.
        edges: (M, 2) verified pairs, i < j.
        match_offsets: (M+1,) start of each pair's inlier matches in ``matches``.
        matches: (T, 2) inlier matches as keypoint indices (in image i, in image j).
        cam2_from_cam1: (M, 3, 3) relative rotations ``R_ij = R_j R_iᵀ``.
        t_cam2_from_cam1: (M, 3) relative translations (unit or zero).
        R_init: (N, 3, 3) averaged cam_from_world rotations (NaN for images without one).
        known_K: (N,) bool or one bool: intrinsics known (constant) or refined (focal).
        config: options (:class:`RefineConfig`).
        scratch: folder for the temporary binary model (default: system temp).
        k1: (N,) COLMAP's SIMPLE_RADIAL k1 of each unknown camera whose ``keypoints`` are the measured (distorted)
            ones, its starting value (0 or None: undistorted keypoints; a known camera must have 0). Refined with
            ``radial: auto``, else held.
        hold: (N,) bool: cameras without a K file whose intrinsics are held at ``K`` (and ``k1``) all the same; the
            refinement sets it itself for a focal length the model does not determine (``max_focal_sd``).
        R_start: (N, 3, 3) starts of images without an averaged rotation, to be refined all the same (NaN
            elsewhere; :func:`pipeline.refine.checks.chain_starts`); one the final model does not support gets none.
    Returns:
        :class:`RefineResult`.
    """
    cfg = config or RefineConfig()
    t_all = time.perf_counter()
    n = len(names)
    K, sizes, R_init = np.asarray(K, float), np.asarray(sizes), np.asarray(R_init, float)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    match_offsets = np.asarray(match_offsets, np.int64)
    cam2_from_cam1, t = np.asarray(cam2_from_cam1, float), np.asarray(t_cam2_from_cam1, float)
    check_inputs(n, K, sizes, keypoints, edges, match_offsets, cam2_from_cam1, t, R_init)
    known = np.broadcast_to(np.asarray(known_K, bool), (n,)).copy()
    hold = np.zeros(n, bool) if hold is None else np.asarray(hold, bool) & ~known
    const = known | hold  # intrinsics constant in the bundle adjustments
    k1 = radial_terms(n, k1)
    if np.any(known & (k1 != 0.0)):  # its keypoints would be measured ones, and a known camera has no lens here
        raise ValueError("a radial term k1 is given for a camera whose K is known; undistort its keypoints instead")
    schedule = cfg.schedule()
    warnings: list[str] = []
    times: dict[str, float] = {}
    stats: dict[str, Any] = {"times": times, "n_images": n, "n_pairs_in": len(edges), "schedule": schedule}
    has_R = np.all(np.isfinite(R_init), axis=(1, 2))
    if R_start is not None and np.shape(R_start) != R_init.shape:
        raise ValueError(f"R_start.shape={np.shape(R_start)} but expected {R_init.shape}, as R_init's")
    start = R_init if R_start is None else np.where(has_R[:, None, None], R_init, np.asarray(R_start, float))
    placed = np.all(np.isfinite(start), axis=(1, 2))  # averaged, or started from pairs to be refined (R_start)
    why = ["no averaged rotation" if not h else "" for h in placed]

    def result(status: str, rec: Any = None, R_ref: np.ndarray | None = None, refined: np.ndarray | None = None,
               change: np.ndarray | None = None, cov: np.ndarray | None = None,
               R_anchor: np.ndarray | None = None) -> RefineResult:
        refined = np.zeros(n, bool) if refined is None else refined
        R_ref = np.full((n, 3, 3), np.nan) if R_ref is None else R_ref
        R_out = R_init.copy()
        R_out[refined] = R_ref[refined]
        anchored = np.zeros(n, bool) if R_anchor is None else np.all(np.isfinite(R_anchor), axis=(1, 2)) & ~refined
        if anchored.any():
            R_out[anchored] = R_anchor[anchored]
        if status == "failed":
            for k in np.flatnonzero(placed):
                why[k] = why[k] or warnings[-1]
        times["total"] = time.perf_counter() - t_all
        stats["n_refined"] = int(refined.sum())
        for w in warnings:
            logger.warning("refine: %s", w)
        return RefineResult(status, R_out, R_init.copy(), R_ref, refined,
                            np.full(n, np.nan) if change is None else change, cov, list(why), rec, warnings, stats,
                            anchored)

    def rerun(K_again: np.ndarray, hold_again: np.ndarray, cfg_again: RefineConfig) -> RefineResult:
        """The same refinement from other intrinsics, holding other cameras, with other options."""
        return refine_rotations(names, K_again, sizes, keypoints, edges, match_offsets, matches, cam2_from_cam1, t,
                                R_init, known, cfg_again, scratch, k1, hold_again, R_start)

    def again(msg: str, key: str, rejected: Any, cfg_again: RefineConfig, hold_again: np.ndarray = hold,
              warn: bool = True, K_again: np.ndarray | None = None) -> RefineResult:
        """The refinement run again without what the model did not determine (``msg`` says what; ``stats[key]``;
        ``warn``: also a warning, else a note in the log and the record alone; ``K_again``: other starting K)."""
        res = rerun(K if K_again is None else K_again, hold_again, cfg_again)
        logger.log(logging.WARNING if warn else logging.INFO, "refine: %s", msg)
        if warn:
            res.warnings.insert(0, msg)
        res.stats[key] = rejected
        res.stats["times"]["total"] = time.perf_counter() - t_all
        return res

    # 1. edge filter from our averaged rotations; 2. tracks
    t0 = time.perf_counter()
    keep, residual = tk.filter_edges(edges, cam2_from_cam1, start, cfg.edge_filter_deg)
    stats["n_pairs_kept"] = int(keep.sum())
    if np.isfinite(residual).any():
        stats["pair_residual_deg_median"] = float(np.nanmedian(residual))
    if (~keep).any():
        warnings.append(f"{int((~keep).sum())} of {len(edges)} pairs disagree with the averaged rotations by more "
                        f"than {cfg.edge_filter_deg}° (or lack a rotation) and are not used")
    k_off, k_matches = tk.select_matches(match_offsets, matches, keep)
    built = tk.build_tracks(keypoints, edges[keep], k_off, k_matches, 2, cfg.track_consistency_px)
    tracks, starved = tk.long_tracks(built, n, cfg.min_track_views, cfg.min_image_observations)
    obs = tracks.observations_per_image(n)
    stats.update(n_tracks=tracks.n_tracks, n_track_components=tracks.n_components, n_images_short_tracks=int(
        starved.sum()), n_tracks_inconsistent=tracks.n_inconsistent, n_tracks_short=tracks.n_short)
    active = placed & (obs >= cfg.min_image_observations)
    for k in np.flatnonzero(placed & ~active):  # warned where its rotation is decided (checks.checked_rotations)
        why[k] = f"{obs[k]} track observations (< {cfg.min_image_observations}): not refined"
    times["tracks"] = time.perf_counter() - t0
    if active.sum() < 2:
        warnings.extend(kept_averaged(names, why, has_R & ~active))
        warnings.append(f"only {int(active.sum())} image(s) with enough tracks ({tracks.n_tracks} tracks): "
                        "nothing to refine; the averaged rotations are kept")
        return result("failed")
    tracks = tk.restrict_tracks(tracks, active, 2 if (starved & active).any() else cfg.min_track_views)

    # 3. the in-memory database (correspondence graph) and the starting reconstruction; 4. pycolmap's steps
    pc = _pycolmap()
    state: dict[str, Any] = {}
    radial = cfg.radial == "auto" and not known.all()

    def setup() -> tuple[bool, str]:
        images = np.flatnonzero(active)
        pair_ok = keep & active[edges[:, 0]] & active[edges[:, 1]]
        p_off, p_matches = tk.select_matches(match_offsets, matches, pair_ok)
        state["cache"] = correspondence_cache(pc, names, K, sizes, known, keypoints, images, edges[pair_ok], p_off,
                                              p_matches, cam2_from_cam1[pair_ok], t[pair_ok], radial=radial, k1=k1)
        state["pose_graph"] = pc.PoseGraph()
        state["pose_graph"].load(state["cache"].correspondence_graph)
        tr = tracks
        if schedule["positioning_tracks_per_image"] > 0:
            tr = tk.subset_tracks(tr, tk.select_tracks(tr, n, schedule["positioning_tracks_per_image"]))
        state["rec"] = starting_reconstruction(pc, names, K, sizes, known, keypoints, images, start, tr, scratch,
                                              radial=radial, k1=k1)
        stats["n_points_start"] = int(state["rec"].num_points3D())
        return True, ""

    refine_pp = cfg.principal_point != "fixed" and bool((active & ~known).any())  # an image without a K file
    probe_pp = False  # principal points held for too few images per camera: is the image centre a misfit?
    if refine_pp and cfg.principal_point == "auto":  # one image cannot separate its principal point from its pose
        cam_id, _ = camera_groups(K, sizes, known, k1)
        per_camera = np.bincount(cam_id[active & ~known])
        few = int(per_camera[per_camera > 0].min())
        if few < cfg.min_principal_point_images:
            refine_pp = False
            probe_pp = cfg.principal_point_misfit is not None
            stats["principal_point_fixed_why"] = (f"a camera without a K file has {few} image(s) "
                                                  f"(< min_principal_point_images = {cfg.min_principal_point_images})")
    ba = mapper.ba_options(pc, cfg, const, principal_point=refine_pp, radial=radial)
    steps = [("setup", setup),
             ("global_positioning", lambda: mapper.global_positioning(pc, state["rec"], state["pose_graph"], cfg)),
             ("bundle_adjustment", lambda: mapper.iterative_bundle_adjustment(pc, state["rec"], ba, const, cfg))]
    if cfg.retriangulate:
        steps.append(("retriangulation", lambda: mapper.retriangulate(pc, state["rec"], state["cache"], ba, const, cfg,
                                                                      schedule["refinement_rounds"])))
    for step, run in steps:
        t0 = time.perf_counter()
        try:
            ok, reason = run()
        except (RuntimeError, ValueError, MemoryError) as exc:  # pycolmap's failed checks raise these
            ok, reason = False, f"{step.replace('_', ' ')} raised {type(exc).__name__}: {' '.join(str(exc).split())[:120]}"
        times[step] = time.perf_counter() - t0
        if "rec" in state:
            stats[f"n_points_after_{step}"] = int(state["rec"].num_points3D())
        if not ok:
            warnings.append(f"{reason}; the averaged rotations are kept")
            return result("failed")
    rec = state["rec"]
    covs = None  # pycolmap's covariance of every refined camera, estimated once for the checks below
    if refine_pp:
        covs, verdict = principal_point_check(pc, rec, ba, const, cfg, radial, stats)
        if verdict is not None:  # not determined (a warning), or too near the image centre to be told from it
            msg, key, rejected, cfg_again = verdict
            if key == "principal_point_rejected":
                return again(msg, key, rejected, cfg_again)
            K_centre = K.copy()  # held at the image centre, whatever the start (the cameras stage's is the centre)
            K_centre[~known, 0, 2], K_centre[~known, 1, 2] = (sizes[~known, 0] - 1) / 2.0, (sizes[~known, 1] - 1) / 2.0
            return again(msg, key, rejected, cfg_again, warn=False, K_again=K_centre)
    if radial:  # k1 kept only where the model determines it
        try:
            covs = camera_covariances(pc, rec, ba, const) if covs is None else covs
            corner = radial_corner_sd(rec, covs)
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # no covariance: not shown to be determined
            logger.warning("refine: the radial terms' covariance failed (%s)", " ".join(str(exc).split())[:100])
            corner = {int(rec.image(i).camera_id): float("inf") for i in rec.reg_image_ids() if not const[i - 1]}
        cams = {cid: rec.camera(cid) for cid in corner}
        limit = {cid: cfg.max_radial_sd * max(c.width, c.height) for cid, c in cams.items()}
        stats["radial"] = {str(cid): {"k1": float(c.params[3]), "corner_sd_px": corner[cid],  # COLMAP's k1, on
                                      "max_sd_px": limit[cid]} for cid, c in cams.items()}  # the stage's lens
        loose = [cid for cid in corner if not corner[cid] <= limit[cid]]
        if loose:
            sd = max(corner[c] for c in loose)  # inf: the covariance is singular
            msg = (f"the radial term of {len(loose)} camera(s) is not determined by the model (its displacement at the "
                   f"image corner: {f'sd {sd:.1f} px' if np.isfinite(sd) else 'no finite sd'}, at most "
                   f"{min(limit[c] for c in loose):.1f} px): every camera refined without one")
            return again(msg, "radial_rejected", stats["radial"], replace(cfg, radial="off"))
    # a bogus focal length is held at the cameras stage's estimate; a weakly determined one stays (a refined
    # principal point trades against it: where one is refined and determined, so is the focal with it)
    if not const.all() and not refine_pp:
        bogus, loose = focal_check(pc, rec, ba, const, covs, cfg)
        if loose:
            stats["focal_loose"] = loose
            warnings.append(f"the focal length of {len(loose)} camera(s) is weakly determined by the model (one "
                            f"standard deviation moves the image corner by up to "
                            f"{max(v['corner_sd_px'] for v in loose.values()):.3g} px > {cfg.max_focal_sd:g} of the "
                            "image side), kept as refined: "
                            + ", ".join(f"{v['refined_px']:.0f} px" for v in loose.values()))
        if bogus:
            held = np.isin(camera_groups(K, sizes, known, k1)[0], [int(c) for c in bogus]) & ~known
            refined_f = ", ".join(f"{v['refined_px']:.0f}" for v in bogus.values())
            msg = (f"the intrinsics of {len(bogus)} camera(s) are bogus by COLMAP's test (focal length outside "
                   f"{cfg.min_focal_ratio:g}–{cfg.max_focal_ratio:g}× the image's longest side, or |k1| > "
                   f"{cfg.max_extra_param:g}; refined to {refined_f} px): refined again with them held at the "
                   "cameras stage's estimate "
                   f"({', '.join(names[k] for k in np.flatnonzero(held)[:5])})")
            return again(msg, "focal_held", bogus, cfg, hold | held)
    if probe_pp:  # a run with every principal point refined, taken where the image centre is a misfit
        probed, stats["principal_point_probe"] = probe_principal_points(pc, rec, ba, const, K, known, hold, cfg,
                                                                        names, rerun)
        if probed is not None:
            probed.stats["principal_point_probe"] = stats["principal_point_probe"]
            probed.stats["times"]["total"] = time.perf_counter() - t_all
            return probed
    rec.update_point_3d_errors()  # GLOMAP's filters leave the errors in normalized units
    stats.update(n_points=int(rec.num_points3D()), mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
                 mean_track_length=float(rec.compute_mean_track_length()))
    return checked_rotations(pc, rec, ba, const, known, K, cfg, names, R_init, has_R, active, why, warnings, stats,
                             times, result, (edges[keep], cam2_from_cam1[keep]))
