"""Checks of :func:`pipeline.refine.refine.refine_rotations`: bogus and weakly determined focal lengths; step 5 and
6, which images keep a refined rotation, and their covariance."""

from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np

from pipeline.core import so3
from pipeline.refine.covariance import camera_covariances, focal_corner_sd, rotation_covariance
from pipeline.refine.model import model_rotations

__all__ = ["checked_rotations", "focal_check", "anchor_rotations", "chain_starts", "kept_averaged"]


def checked_rotations(pc: Any, rec: Any, ba: Any, const: np.ndarray, known: np.ndarray, K: np.ndarray, cfg: Any,
                      names: Sequence[str], R_init: np.ndarray, has_R: np.ndarray, active: np.ndarray, why: list[str],
                      warnings: list[str], stats: dict[str, Any], times: dict[str, float], result: Any,
                      pairs: tuple[np.ndarray, np.ndarray] | None = None) -> Any:
    """Step 5 and 6: which images keep a refined rotation (lost, moved too far), and their covariance.

    ``const``: images whose intrinsics the bundle adjustments held (a K file, or held by the refinement's checks);
    ``known``: those with a K file. ``max_change_deg`` guards only the latter (``max_change_known_only``): a held
    camera's averaged rotation rests on estimated intrinsics, its own and its pairs', as a refined camera's does.
    ``pairs``: the edges the refinement kept and their relative rotations. An image the final model does not
    support (lost, or too few track observations to enter it) is chained from its refined neighbours through those
    pairs (:func:`anchor_rotations`)
    where it has any: its averaged rotation carries the averaging's error of its whole neighbourhood, which the
    refinement removed from the others (an internet imitation: a one-pair image 17.4° off as averaged, 3.9° chained).
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
    lost = has_R & ~supported  # and those with too few track observations to enter the model
    if supported.sum() < 2:
        warnings.extend(kept_averaged(names, why, lost))
        warnings.append("fewer than 2 images are supported by the final model; the averaged rotations are kept")
        return result("failed")
    # R_model ≈ R_init G (chordal ℓ2 over the supported images that have an averaged rotation); the refined set
    # in the averaged frame (an image started from its pairs, R_start, is refined but does not align)
    aligned = supported & has_R
    G = so3.project_to_so3(np.einsum("nji,njk->ik", R_init[aligned], R_model[aligned]))
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
    stats["change_deg_median"] = float(np.median(change[aligned]))
    stats["change_deg_max"] = float(np.max(change[aligned]))
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
    R_anchor, n_pairs = None, np.zeros(n, np.int64)
    if pairs is not None and lost.any():
        R_anchor, n_pairs = anchor_rotations(*pairs, R_ref, refined, lost)
        stats["anchored"] = {names[k]: int(n_pairs[k]) for k in np.flatnonzero(n_pairs)}
    for k in np.flatnonzero(lost):
        if n_pairs[k]:
            why[k] += f"; its rotation is chained from refined neighbours through its {n_pairs[k]} kept pair(s)"
        warnings.append(f"{names[k]}: {why[k]}" + ("" if n_pairs[k] else "; keeps its averaged rotation"))
    status = "ok" if refined[has_R].all() else "partial"
    return result(status, rec, R_ref, refined, change, cov, R_anchor)


def kept_averaged(names: Sequence[str], why: list[str], mask: np.ndarray) -> list[str]:
    """One warning per image of ``mask`` (N,) that keeps its averaged rotation, with its ``why``."""
    return [f"{names[k]}: {why[k]}; keeps its averaged rotation" for k in np.flatnonzero(mask)]


def anchor_rotations(edges: np.ndarray, R_rel: np.ndarray, R: np.ndarray, refined: np.ndarray, targets: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Rotations of the ``targets`` chained from their ``refined`` neighbours: the chordal mean of the predictions
    ``R_i = R_ijᵀ R_j`` and ``R_j = R_ij R_i`` (docs/CONVENTIONS.md: ``R_ij = R_j R_iᵀ``) over the pairs (M, 2) that
    join a target to a refined image.

    Returns:
        (N, 3, 3) rotations (NaN where a target has no such pair, and for every other image); (N,) pair counts.
    """
    n = len(R)
    i, j = np.asarray(edges, np.int64).reshape(-1, 2).T
    a = targets[i] & refined[j]  # i predicted from j
    b = targets[j] & refined[i]  # j predicted from i
    S = np.zeros((n, 3, 3))
    np.add.at(S, i[a], np.swapaxes(R_rel[a], 1, 2) @ R[j[a]])
    np.add.at(S, j[b], R_rel[b] @ R[i[b]])
    count = np.bincount(np.concatenate([i[a], j[b]]), minlength=n)
    out = np.full((n, 3, 3), np.nan)
    ok = count > 0
    out[ok] = so3.project_to_so3(S[ok])
    return out, count


def chain_starts(edges: np.ndarray, R_rel: np.ndarray, R: np.ndarray, targets: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Starts of the ``targets`` (N,) bool, images without a rotation in ``R`` (N, 3, 3), chained through the pairs
    ``edges`` (M, 2) / ``R_rel`` from the images with one, in rounds (:func:`anchor_rotations`): a target joined to
    those only through other targets gets its start in a later round, from theirs.

    Returns:
        (N, 3, 3) starts (NaN where a target is joined to no image with a rotation, and for the other images);
        (N,) the pairs each start came through.
    """
    have = np.all(np.isfinite(R), axis=(1, 2)) & ~targets
    R = np.where(have[:, None, None], R, np.nan)
    out, count = np.full_like(R, np.nan), np.zeros(len(R), np.int64)
    todo = targets.copy()
    while todo.any():
        step, c = anchor_rotations(edges, R_rel, R, have, todo)
        new = c > 0
        if not new.any():
            break
        out[new], count[new], R[new] = step[new], c[new], step[new]
        have |= new
        todo &= ~new
    return out, count


def focal_check(pc: Any, rec: Any, ba: Any, const: np.ndarray, covs: dict[int, np.ndarray | None] | None,
                cfg: Any) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, float]]]:
    """The refined cameras whose intrinsics are bogus, and those whose focal length is weakly determined.

    Bogus is COLMAP's own test (``Camera.has_bogus_params``, as its incremental mapper filters cameras): a focal
    length outside ``min_focal_ratio``–``max_focal_ratio`` × the image's longest side, or ``|k1| > max_extra_param``.
    Weakly determined: one standard deviation of the focal (pycolmap's BA covariance) moves the image corner by more
    than ``max_focal_sd`` of that side. Held at a default 32% off, such a focal (1.8% sd, refined 3% off) cost its
    image 11° where refined it was 0.9° off; a bogus one (9.8× its true value) took the whole model to a wrong basin.

    Returns:
        ``(bogus, loose)``: camera id (str) → ``{"refined_px", "corner_sd_px"}`` (NaN where no covariance).
    """
    try:
        corner = focal_corner_sd(rec, camera_covariances(pc, rec, ba, const) if covs is None else covs)
    except (RuntimeError, ValueError, np.linalg.LinAlgError):  # no covariance: no camera shown to be loose
        corner = {}
    cams = {int(rec.image(i).camera_id) for i in rec.reg_image_ids() if not const[i - 1]}
    entry = {cid: {"refined_px": float(rec.camera(cid).mean_focal_length()),
                   "corner_sd_px": float(corner.get(cid, float("nan")))} for cid in sorted(cams)}
    bogus = {cid for cid in cams if rec.camera(cid).has_bogus_params(cfg.min_focal_ratio, cfg.max_focal_ratio,
                                                                      cfg.max_extra_param)}
    loose = {cid for cid in cams - bogus if cid in corner and not corner[cid] <= cfg.max_focal_sd * max(
        rec.camera(cid).width, rec.camera(cid).height)}
    return ({str(c): entry[c] for c in sorted(bogus)}, {str(c): entry[c] for c in sorted(loose)})
