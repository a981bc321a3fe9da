"""Per-camera rotation covariance from pycolmap's bundle-adjustment covariance, in the evaluation's gauge.

pycolmap's ``BACovariance`` gives covariances in the tangent space of ceres'
``EigenQuaternionManifold`` (``q ← [cos|δ|, sin|δ| δ/|δ|] ⊗ q``: a left rotation of
cam_from_world by the angle ``2|δ|``), with the residuals taken as unit-variance
pixels. So the rotation-vector covariance is ``4 σ² Σ_δ``, with ``σ²`` the residual
variance ``2·cost / (n_residuals − n_parameters)`` of the final problem.

BA fixes its gauge by holding two cameras (``TWO_CAMS_FROM_WORLD``); the evaluation
aligns the whole set to the reference with one global rotation (ℓ2). The joint
3N×3N rotation covariance is therefore moved to the minimum-norm gauge with the
projector of :func:`rotation_gauge_projection`, the linearization of that alignment.

Calibrated on synthetic truth (``tests/refine``): Σ|δ|² / Σ tr Σ ≈ 1 over noise draws.
Convention of the result: ``R_true = exp([δ]×) R̂`` (left perturbation), rad².
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.refine.mapper import ba_config

__all__ = ["rotation_gauge_projection", "gauge_fixed_rotation_covariance", "rotation_covariance",
           "camera_covariances", "camera_covariances_and_sigma", "residual_sigma_px", "param_sd", "principal_point_sd",
           "radial_corner_sd", "focal_corner_sd"]


def rotation_gauge_projection(cam_from_world: np.ndarray) -> np.ndarray:
    """(3N, 3N) orthogonal projector removing the global-rotation gauge from stacked left perturbations.

    A rotation ``W`` of the world moves ``R_i`` to ``R_i Wᵀ = exp([−R_i w]×) R_i``: the
    stacked perturbation ``−B w`` with ``B = [R_1; …; R_N]`` (3N, 3) and ``BᵀB = N·I``.
    ``P = I − B Bᵀ / N``.

    Args:
        cam_from_world: (N, 3, 3) rotations.
    """
    B = np.asarray(cam_from_world, float).reshape(-1, 3)
    return np.eye(B.shape[0]) - B @ B.T / len(cam_from_world)


def gauge_fixed_rotation_covariance(joint: np.ndarray, cam_from_world: np.ndarray, scale: float) -> np.ndarray:
    """(N, 3, 3) per-camera blocks of ``scale · P S P``: the joint covariance ``S`` (3N, 3N) in the minimum-norm gauge.

    Raises:
        ValueError: ``S`` or ``scale`` not finite (pycolmap's estimate of a problem that does not determine some
            camera): the gauge projection would spread it to every camera.
    """
    if not (np.all(np.isfinite(joint)) and np.isfinite(scale)):
        raise ValueError("pycolmap's BA covariance is not finite (the final problem does not determine every camera)")
    P = rotation_gauge_projection(cam_from_world)
    S = scale * (P @ joint @ P)
    n = len(cam_from_world)
    idx = np.arange(n)
    return S.reshape(n, 3, n, 3)[idx, :, idx, :]


def _final_problem(pc: Any, rec: Any, ba: Any, known: np.ndarray) -> tuple[Any, float]:
    """A ceres bundle adjuster of the final problem, solved again (at its optimum: a few iterations), and the
    residual variance ``σ²`` (px²) its covariance is scaled by."""
    adjuster = pc.create_default_ceres_bundle_adjuster(ba, ba_config(pc, rec, known), rec)
    cs = adjuster.solve().ceres_summary
    dof = max(int(cs.num_residuals_reduced) - int(cs.num_effective_parameters_reduced), 1)
    return adjuster, 2.0 * float(cs.final_cost) / dof


def camera_covariances(pc: Any, rec: Any, ba: Any, known: np.ndarray) -> dict[int, np.ndarray | None]:
    """Camera id → the covariance (σ²-scaled as the rotations') of each refined camera's parameters, in COLMAP's
    parameter order, NaN in the rows and columns of the parameters the BA held constant.

    From pycolmap's BA covariance of every variable block (points eliminated); ``None`` where pycolmap cannot
    estimate it (a singular problem: the parameters are not determined).
    """
    return camera_covariances_and_sigma(pc, rec, ba, known)[0]


def camera_covariances_and_sigma(pc: Any, rec: Any, ba: Any, known: np.ndarray
                                 ) -> tuple[dict[int, np.ndarray | None], float]:
    """:func:`camera_covariances` and the residual standard deviation σ (px) of the final problem they are scaled by
    (``√(2·cost / (residuals − parameters))``)."""
    adjuster, sigma2 = _final_problem(pc, rec, ba, known)
    opts = pc.BACovarianceOptions()
    opts.params = pc.BACovarianceOptionsParams.ALL
    bacov = pc.estimate_ba_covariance(opts, rec, adjuster)
    known_ids = {int(rec.image(i).camera_id) for i in rec.reg_image_ids() if known[i - 1]}
    out: dict[int, np.ndarray | None] = {}
    for cid in sorted({int(rec.image(i).camera_id) for i in rec.reg_image_ids()} - known_ids):  # per camera: few
        cam = rec.camera(cid)
        C = bacov.get_other_params_cov(cam.params) if bacov is not None else None
        # pycolmap returns the covariance of the parameters the BA refined (a constant principal point is left out)
        free = [i for i in range(len(cam.params))
                if (i in cam.focal_length_idxs() and ba.refine_focal_length)
                or (i in cam.principal_point_idxs() and ba.refine_principal_point)
                or (i in cam.extra_params_idxs() and ba.refine_extra_params)]
        if C is None or np.shape(C) not in ((len(free),) * 2, (len(cam.params),) * 2) or not np.all(np.isfinite(C)):
            out[cid] = None
            continue
        full = np.full((len(cam.params),) * 2, np.nan)  # NaN: a constant parameter
        at = free if len(C) == len(free) else list(range(len(cam.params)))
        full[np.ix_(at, at)] = sigma2 * np.asarray(C)
        out[cid] = full
    return out, float(np.sqrt(sigma2))


def residual_sigma_px(pc: Any, rec: Any, ba: Any, known: np.ndarray) -> float:
    """The residual standard deviation σ (px) of the final problem, ``√(2·cost / (residuals − parameters))``, on
    a copy of ``rec`` (the solve at the optimum moves it by a few iterations; ``rec`` stays as it is)."""
    return float(np.sqrt(_final_problem(pc, pc.Reconstruction(rec), ba, known)[1]))


def param_sd(C: np.ndarray | None, idx: list[int]) -> float:
    """Standard deviation along the worst direction of the parameters ``idx`` of a camera covariance (inf if None
    or if one of them was constant)."""
    if C is None:
        return float("inf")
    S = C[np.ix_(idx, idx)]
    if not np.all(np.isfinite(S)):
        return float("inf")
    return float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (S + S.T))[-1], 0.0)))


def principal_point_sd(pc: Any, rec: Any, ba: Any, known: np.ndarray,
                       covs: dict[int, np.ndarray | None] | None = None) -> dict[int, float]:
    """Camera id → the standard deviation (px, along its worst direction) of each refined camera's principal point
    (``inf`` where it is not determined); ``covs``: :func:`camera_covariances`, computed here if None."""
    covs = camera_covariances(pc, rec, ba, known) if covs is None else covs
    return {cid: param_sd(C, list(rec.camera(cid).principal_point_idxs())) for cid, C in covs.items()}


def radial_corner_sd(rec: Any, covs: dict[int, np.ndarray | None]) -> dict[int, float]:
    """Camera id → the standard deviation (px) of the radial term's displacement at the image corner.

    SIMPLE_RADIAL moves a point at normalized radius ``r`` by ``k1 r³`` focal lengths; at the corner
    (``r = d/f``, ``d`` the half-diagonal in pixels) that is ``k1 d³/f²`` px, so ``sd(k1) d³/f²``.
    Cameras without a radial term are left out.
    """
    out = {}
    for cid, C in covs.items():
        cam = rec.camera(cid)
        idx = list(cam.extra_params_idxs())
        if len(idx) != 1:
            continue
        d = 0.5 * float(np.hypot(cam.width, cam.height))
        out[cid] = param_sd(C, idx) * d**3 / float(cam.mean_focal_length()) ** 2
    return out


def focal_corner_sd(rec: Any, covs: dict[int, np.ndarray | None]) -> dict[int, float]:
    """Camera id → the standard deviation (px) of the image corner's displacement by the focal length's.

    A point at ``d`` px from the principal point moves by ``δf · d / f`` when the focal length moves by ``δf``; at
    the corner (``d`` the half-diagonal) that is ``sd(f) d / f``: ``inf`` where the focal is not determined.
    """
    out = {}
    for cid, C in covs.items():
        cam = rec.camera(cid)
        d = 0.5 * float(np.hypot(cam.width, cam.height))
        out[cid] = param_sd(C, list(cam.focal_length_idxs())) * d / float(cam.mean_focal_length())
    return out


def rotation_covariance(pc: Any, rec: Any, ba: Any, known: np.ndarray, n: int) -> tuple[np.ndarray | None, dict]:
    """(n, 3, 3) rotation covariance of image ``k`` = COLMAP image ``k + 1`` (rad²; NaN if not registered).

    Runs the final problem once more through a ceres bundle adjuster (at its optimum:
    a few iterations) to get its cost and sizes, then ``estimate_ba_covariance`` on it.

    Returns:
        the covariances (None if pycolmap's estimation failed) and ``{"sigma_px": σ}``.
    """
    adjuster, sigma2 = _final_problem(pc, rec, ba, known)
    info = {"sigma_px": float(np.sqrt(sigma2))}
    opts = pc.BACovarianceOptions()
    opts.params = pc.BACovarianceOptionsParams.POSES
    bacov = pc.estimate_ba_covariance(opts, rec, adjuster)
    if bacov is None:
        return None, info
    reg = sorted(rec.reg_image_ids())
    m = len(reg)
    variable = [bacov.get_cam_cov_from_world(iid) is not None for iid in reg]
    joint = np.zeros((m, 3, m, 3))
    # pycolmap 4.2.1 returns the cross covariance one pair of cameras per call: the upper triangle only
    for a in range(m):
        if not variable[a]:
            continue
        for b in range(a, m):
            C = bacov.get_cam_cross_cov_from_world(reg[a], reg[b]) if variable[b] else None
            if C is not None:
                joint[a, :, b, :] = C[:3, :3]
                joint[b, :, a, :] = C[:3, :3].T
    R = np.stack([rec.image(iid).cam_from_world().rotation.matrix() for iid in reg])
    blocks = gauge_fixed_rotation_covariance(joint.reshape(3 * m, 3 * m), R, 4.0 * sigma2)
    cov = np.full((n, 3, 3), np.nan)
    cov[np.asarray(reg) - 1] = blocks
    info["n_fixed_in_gauge"] = int(m - sum(variable))
    return cov, info
