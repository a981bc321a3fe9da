"""pycolmap's multi-view steps after rotation averaging, in GLOMAP's order (``src/colmap/sfm/global_mapper.cc``).

pycolmap 4.2.1 does not expose the C++ ``GlobalMapper`` and its ``GlobalPipeline``
cannot start from given rotations (with ``skip_rotation_averaging`` no frame is
registered and track establishment fails), so the steps are called one by one:

1. :func:`global_positioning`: ``run_global_positioning`` (rotations fixed, positions and
   points from random starts), then GLOMAP's filters (angular error, triangulation
   angle, normalized error) and ``normalize``;
2. :func:`iterative_bundle_adjustment`: rounds of a positions-only and a joint
   ``bundle_adjustment`` with the normalized-error filter tightening;
3. :func:`retriangulate`: every point deleted and re-triangulated from the
   correspondence graph (``IncrementalMapper.triangulate_image``),
   ``iterative_global_refinement``, a filter and the final bundle adjustment.

Known intrinsics stay constant (``set_constant_cam_intrinsics`` and
``constant_cameras``); unknown ones get their focal length refined, and their principal
point where :mod:`pipeline.refine.refine` asks for it. No step raises
on a numerical failure: each returns ``(ok, why)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["ba_options", "ba_config", "run_bundle_adjustment", "global_positioning", "iterative_bundle_adjustment",
           "retriangulate"]


def ba_options(pc: Any, cfg: Any, known: np.ndarray, principal_point: bool = False, radial: bool = False) -> Any:
    """GLOMAP's bundle-adjustment options (Huber loss), focal (and, with ``principal_point``, the principal point;
    with ``radial``, the radial term) refined only when some K is unknown; known cameras are constant in
    :func:`ba_config`."""
    ba = pc.GlobalMapperOptions().get_bundle_adjustment()
    ba.print_summary = False
    ba.refine_principal_point = bool(principal_point) and not bool(np.all(known))
    ba.refine_extra_params = bool(radial) and not bool(np.all(known))
    ba.refine_focal_length = not bool(np.all(known))
    ba.ceres.loss_function_type = pc.LossFunctionType.HUBER
    ba.ceres.loss_function_scale = cfg.huber_px
    ba.ceres.solver_options.num_threads = cfg.num_threads
    ba.ceres.use_gpu = False
    if cfg.dense_solver_max_images > 0:  # ceres' dense Schur for small problems (pycolmap's own switch)
        ba.ceres.auto_select_solver_type = True
        ba.ceres.max_num_images_direct_dense_cpu_solver = cfg.dense_solver_max_images
    return ba


def _known_cameras(rec: Any, known_images: np.ndarray) -> set[int]:
    """COLMAP camera ids of the registered images whose intrinsics are known (image ``k`` = id ``k + 1``)."""
    return {int(rec.image(iid).camera_id) for iid in rec.reg_image_ids() if known_images[iid - 1]}


def ba_config(pc: Any, rec: Any, known: np.ndarray) -> Any:
    """Every registered image, known cameras constant, the two-cameras gauge."""
    cfg = pc.BundleAdjustmentConfig()
    for iid in rec.reg_image_ids():
        cfg.add_image(iid)
    for cid in sorted(_known_cameras(rec, known)):
        cfg.set_constant_cam_intrinsics(cid)
    cfg.fix_gauge(pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    return cfg


def run_bundle_adjustment(pc: Any, rec: Any, ba: Any, known: np.ndarray) -> bool:
    """One bundle adjustment of every registered image; False when it cannot run or its solution is unusable."""
    if rec.num_points3D() == 0 or rec.num_reg_images() < 2:
        return False
    summary = pc.create_default_bundle_adjuster(ba, ba_config(pc, rec, known), rec).solve()
    return bool(summary.is_solution_usable())


def _filter_normalized(pc: Any, rec: Any, max_error: float, min_tri_angle_deg: float | None = None) -> int:
    om = pc.ObservationManager(rec)
    n = om.filter_points3D_with_large_reprojection_error(max_error, rec.point3D_ids(),
                                                         pc.ReprojectionErrorType.NORMALIZED)
    if min_tri_angle_deg is not None:
        n += om.filter_points3D_with_small_triangulation_angle(min_tri_angle_deg, rec.point3D_ids())
    return int(n)


def global_positioning(pc: Any, rec: Any, pose_graph: Any, cfg: Any) -> tuple[bool, str]:
    """Positions and points with the rotations held fixed, then GLOMAP's filters."""
    gp = pc.GlobalMapperOptions().get_global_positioning()
    gp.random_seed = cfg.seed
    gp.use_gpu = False
    gp.min_num_view_per_track = cfg.min_track_views
    if not pc.run_global_positioning(gp, pose_graph, rec):
        return False, "global positioning failed"
    om = pc.ObservationManager(rec)
    om.filter_points3D_with_large_reprojection_error(cfg.max_angular_error_deg, rec.point3D_ids(),
                                                     pc.ReprojectionErrorType.ANGULAR)
    om.filter_points3D_with_small_triangulation_angle(cfg.min_tri_angle_deg, rec.point3D_ids())
    om.filter_points3D_with_large_reprojection_error(10 * cfg.max_normalized_error, rec.point3D_ids(),
                                                     pc.ReprojectionErrorType.NORMALIZED)
    if rec.num_points3D() == 0:
        return False, "global positioning left no 3D point after its filters"
    rec.normalize()
    return True, ""


def iterative_bundle_adjustment(pc: Any, rec: Any, ba: Any, known: np.ndarray, cfg: Any) -> tuple[bool, str]:
    """GLOMAP's iterative BA: positions only, then joint; the normalized-error filter tightens each round."""
    for it in range(cfg.ba_iterations):
        fixed = pc.BundleAdjustmentOptions(ba.todict())
        fixed.constant_rig_from_world_rotation = True
        if not run_bundle_adjustment(pc, rec, fixed, known):
            return False, f"positions-only bundle adjustment failed (round {it + 1})"
        if not run_bundle_adjustment(pc, rec, ba, known):
            return False, f"joint bundle adjustment failed (round {it + 1})"
        rec.normalize()
        n_points = max(rec.num_points3D(), 1)
        if _filter_normalized(pc, rec, max(3 - it, 1) * cfg.max_normalized_error) <= 1e-3 * n_points:
            break
    _filter_normalized(pc, rec, cfg.max_normalized_error, cfg.min_tri_angle_deg)
    return True, ""


def retriangulate(pc: Any, rec: Any, cache: Any, ba: Any, known: np.ndarray, cfg: Any,
                  refinement_rounds: int) -> tuple[bool, str]:
    """Delete every point, triangulate again from the correspondence graph, refine, final BA."""
    tri = pc.GlobalMapperOptions().get_retriangulation()
    tri.random_seed = cfg.seed
    rec.delete_all_points2D_and_points3D()
    mapper = pc.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    for iid in rec.reg_image_ids():  # per image: pycolmap triangulates one image's observations per call
        mapper.triangulate_image(tri, iid)
    if refinement_rounds > 0:
        mopts = pc.IncrementalMapperOptions()
        mopts.random_seed = cfg.seed
        mopts.num_threads = cfg.num_threads
        mopts.constant_cameras = _known_cameras(rec, known)
        ba_r = pc.BundleAdjustmentOptions(ba.todict())
        ba_r.ceres.solver_options.max_num_iterations = 50
        ba_r.ceres.solver_options.max_linear_solver_iterations = 100
        mapper.iterative_global_refinement(refinement_rounds, 0.0005, mopts, ba_r, tri, True)
    mapper.end_reconstruction(False)
    _filter_normalized(pc, rec, cfg.max_normalized_error)
    if not run_bundle_adjustment(pc, rec, ba, known):
        return False, "final bundle adjustment failed"
    rec.normalize()
    _filter_normalized(pc, rec, cfg.max_normalized_error, cfg.min_tri_angle_deg)
    return True, ""
