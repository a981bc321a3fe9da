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
           "principal_point_sd"]


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
    """(N, 3, 3) per-camera blocks of ``scale · P S P``: the joint covariance ``S`` (3N, 3N) in the minimum-norm gauge."""
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


def principal_point_sd(pc: Any, rec: Any, ba: Any, known: np.ndarray) -> dict[int, float]:
    """Camera id → the standard deviation (px, along its worst direction) of each refined camera's principal point.

    From pycolmap's BA covariance of the camera parameters (every variable block, points
    eliminated), scaled by the residual variance as the rotations' is; ``inf`` where
    pycolmap cannot estimate it (a singular problem: the point is not determined).
    """
    adjuster, sigma2 = _final_problem(pc, rec, ba, known)
    opts = pc.BACovarianceOptions()
    opts.params = pc.BACovarianceOptionsParams.ALL
    bacov = pc.estimate_ba_covariance(opts, rec, adjuster)
    known_ids = {int(rec.image(i).camera_id) for i in rec.reg_image_ids() if known[i - 1]}
    out: dict[int, float] = {}
    for cid in sorted({int(rec.image(i).camera_id) for i in rec.reg_image_ids()} - known_ids):  # per camera: few
        cam = rec.camera(cid)
        C = bacov.get_other_params_cov(cam.params) if bacov is not None else None
        idx = list(cam.principal_point_idxs())
        if C is None or C.shape != (len(cam.params), len(cam.params)):
            out[cid] = float("inf")
            continue
        S = sigma2 * C[np.ix_(idx, idx)]
        out[cid] = float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (S + S.T))[-1], 0.0))) if np.all(np.isfinite(S)) \
            else float("inf")
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
