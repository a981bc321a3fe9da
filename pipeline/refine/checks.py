"""Step 5 and 6 of :func:`pipeline.refine.refine.refine_rotations`: which images keep a refined rotation, and
their covariance."""

from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np

from pipeline.core import so3
from pipeline.refine.covariance import rotation_covariance
from pipeline.refine.model import model_rotations

__all__ = ["checked_rotations"]


def checked_rotations(pc: Any, rec: Any, ba: Any, const: np.ndarray, known: np.ndarray, K: np.ndarray, cfg: Any,
                      names: Sequence[str], R_init: np.ndarray, has_R: np.ndarray, active: np.ndarray, why: list[str],
                      warnings: list[str], stats: dict[str, Any], times: dict[str, float], result: Any) -> Any:
    """Step 5 and 6: which images keep a refined rotation (lost, moved too far), and their covariance.

    ``const``: images whose intrinsics the bundle adjustments held (a K file, or held by the refinement's checks);
    ``known``: those with a K file. ``max_change_deg`` guards only the latter (``max_change_known_only``): a held
    camera's averaged rotation rests on estimated intrinsics, its own and its pairs', as a refined camera's does.
    """
    n = len(names)
    R_model = model_rotations(rec, n)
    in_model = np.all(np.isfinite(R_model), axis=(1, 2))
    n_points = np.zeros(n, np.int64)
    for iid in rec.reg_image_ids():  # per image: pycolmap's count of its 3D points
        n_points[iid - 1] = rec.image(iid).num_points3D
    supported = in_model & (n_points >= cfg.min_image_observations)
    for k in np.flatnonzero(active & ~supported):
        why[k] = f"{n_points[k]} 3D points in the final model (< {cfg.min_image_observations})"
        warnings.append(f"{names[k]}: {why[k]}; keeps its averaged rotation")
    if supported.sum() < 2:
        warnings.append("fewer than 2 images are supported by the final model; the averaged rotations are kept")
        return result("failed")
    # R_model ≈ R_init G (chordal ℓ2 over the supported images); the refined set in the averaged frame
    G = so3.project_to_so3(np.einsum("nji,njk->ik", R_init[supported], R_model[supported]))
    R_ref = R_model @ G.T
    change = np.full(n, np.nan)
    change[in_model] = np.degrees(so3.angle_between(R_ref[in_model], R_init[in_model]))
    far = supported & (change > cfg.max_change_deg)
    # an unknown camera's averaged rotation rests on the cameras stage's focal, which the model re-estimated
    moved = far & (known if cfg.max_change_known_only else True)
    for k in np.flatnonzero(moved):
        why[k] = (f"refined rotation {change[k]:.2f}° from the averaged one (> max_change_deg = "
                  f"{cfg.max_change_deg}°)")
        warnings.append(f"{names[k]}: {why[k]}; keeps its averaged rotation (both are reported)")
    for k in np.flatnonzero(far & ~moved):
        f0, f1 = float(K[k, 0, 0]), float(rec.camera(rec.image(int(k) + 1).camera_id).mean_focal_length())
        warnings.append(f"{names[k]}: refined rotation {change[k]:.2f}° from the averaged one (> max_change_deg = "
                        f"{cfg.max_change_deg}°); its K is not known and the averaged rotation rested on the cameras "
                        f"stage's focal {f0:.0f} px, which the bundle adjustment moved to {f1:.0f} px "
                        f"({100 * (f1 / f0 - 1):+.1f}%): the refined rotation is kept (both are reported)")
    stats["n_moved_refined"] = int(np.sum(far & ~moved))
    refined = supported & ~moved
    stats["change_deg_median"] = float(np.median(change[supported]))
    stats["change_deg_max"] = float(np.max(change[supported]))
    cov = None
    if cfg.covariance:
        t0 = time.perf_counter()
        try:
            cov, info = rotation_covariance(pc, rec, ba, const, n)
            stats.update(info)
            if cov is None:
                warnings.append("pycolmap's estimate_ba_covariance failed: no rotation uncertainty")
            else:  # into the averaged frame: δ' = G δ for R' = R Gᵀ
                cov = np.einsum("ij,njk,lk->nil", G, cov, G)
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # the refinement stands without it
            warnings.append(f"rotation covariance failed ({type(exc).__name__}: {' '.join(str(exc).split())[:100]})")
        times["covariance"] = time.perf_counter() - t0
    status = "ok" if refined[has_R].all() else "partial"
    return result(status, rec, R_ref, refined, change, cov)
