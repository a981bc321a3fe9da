"""The principal points of cameras with too few images to refine them by default: a probe, and a refinement where the
image centre is a misfit (part of :func:`pipeline.refine.refine.refine_rotations`).

With ``principal_point: auto`` a camera needs ``min_principal_point_images`` images before its principal point is
refined (one image cannot always tell its principal point from its pose). Internet photos are one image per camera,
and are often cropped off their centre: held at the image centre, a principal point 3% off makes the bundle
adjustment trade it against the focal length and the rotation (an imitation on castle-P30: focal lengths 90% off and
rotations 4.2° off, where the true principal points give 0.075°).

After such a run (principal points held), the probe runs the refinement once more with every principal point refined
(and the radial term that run kept, which its own check drops where the model does not determine it), and compares:

1. **The misfit.** The residual standard deviation σ with the principal points held, over σ with them refined. If
   the centre were right, the ratio would be 1 within the few parameters added; ``principal_point_misfit`` (1.3)
   asks for a misfit that keypoint noise does not explain. The ratio is the test, not the covariance: where the
   centre is right to a few pixels, the refined principal points absorb what the model does not fit (Strecha's
   non-square pixels, the truth's own error) and their covariance claims 3 px where they are 20 px off.
2. **Per camera.** A principal point is refined where its standard deviation is within ``max_principal_point_sd``
   of the image side and it is significantly off the held one (its Mahalanobis distance above χ²₂'s 99.9% point);
   every other camera is held at the held run's intrinsics (its refined focal length, the held principal point).

If the misfit and at least one such camera are found, the refinement runs again that way (or the probe's own result
is taken, where every camera qualified); otherwise the held run stands. ``stats["principal_point_probe"]`` records
the figures either way.

**A cheap screen first.** The probe's run is as long as the held run (1–9 s on 10 images, twice that where its own
checks run it again), and on most collections the centre is no misfit. So the misfit is first screened by one bundle
adjustment of the held run's final model with every principal point free (the same points and observations, the
radial term the held run kept; :func:`free_sigma`); below ``principal_point_misfit`` the held run stands without the
probe's run. On the 22 internet imitations of ``benchmarks/real_photos.py`` the screen's ratio was within 0.12 of
the run's (most within 0.01) and on the same side of 1.3 on all 22. It does not replace the run where the centre is
a misfit: there its per-camera choice differed from the run's on 3 of 9 imitations, and the refined rotations were
worse on 2 of those 3 (``notes/issue-13.md``).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any, Callable, Sequence

import numpy as np

from pipeline.refine.covariance import camera_covariances_and_sigma, principal_point_sd, residual_sigma_px

__all__ = ["probe_principal_points", "free_sigma", "principal_point_check", "principal_point_entry", "CHI2_2DOF_999"]

logger = logging.getLogger(__name__)

#: χ²₂'s 99.9% point: a principal point this far (squared Mahalanobis distance) from the held one is off it.
CHI2_2DOF_999 = 13.8155


def principal_point_entry(cam: Any, sd: float, limit: float, cov: np.ndarray | None) -> dict[str, Any]:
    """One camera's entry of ``stats["principal_point"]``: the principal point in our convention (pixel centres at
    integers), its worst-direction standard deviation and limit, and its 2×2 covariance (px², None if unknown)."""
    idx = list(cam.principal_point_idxs())
    C = None if cov is None else cov[np.ix_(idx, idx)]
    return {"px": [cam.principal_point_x - 0.5, cam.principal_point_y - 0.5], "sd_px": sd, "max_sd_px": limit,
            "cov_px2": C.tolist() if C is not None and np.all(np.isfinite(C)) else None}


def principal_point_check(pc: Any, rec: Any, ba: Any, const: np.ndarray, cfg: Any, radial: bool,
                          stats: dict[str, Any]) -> tuple[dict[int, Any] | None, tuple[str, str, Any, Any] | None]:
    """After a run that refined the principal points: is each determined, and far enough from the image centre?

    Fills ``stats["principal_point"]`` (and ``residual_sigma_px``). With ``principal_point: auto``, a camera whose
    principal point the model does not determine (standard deviation over ``max_principal_point_sd`` of the side)
    sends the refinement again without the radial term that trades against it, then with it fixed at the image
    centre; and where every camera's refined principal point is within ``min_principal_point_offset`` of the side
    of the centre, they are all held there, as COLMAP's mappers hold them. That test is on the offset itself, not
    on pycolmap's covariance: copies of fountain-P11's and castle-P30's images resampled so that their principal
    point *is* the centre refined it 3.9 / 6.3 px (fountain, without and with a lens) and 0.95 px (castle) off it, 8–9 of the
    standard deviations pycolmap's covariance claims, and those offsets cost fountain's rotations 1.5–2.3× (0.029
    → 0.045°, 0.032 → 0.074°); Strecha's true principal points are 0.7% of the side off the centre, temple's 2.7%
    (``notes/issue-13.md``).

    Returns:
        the cameras' covariances (None where they failed) and None to keep the run, or the arguments of its
        ``again(message, stats key, rejected, config)``.
    """
    try:
        covs, stats["residual_sigma_px"] = camera_covariances_and_sigma(pc, rec, ba, const)
        sd = principal_point_sd(pc, rec, ba, const, covs)
    except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # no covariance: not shown to be determined
        logger.warning("refine: the principal points' covariance failed (%s)", " ".join(str(exc).split())[:100])
        covs = None
        sd = {int(rec.image(i).camera_id): float("inf") for i in rec.reg_image_ids() if not const[i - 1]}
    cams = {cid: rec.camera(cid) for cid in sd}
    limit = {cid: cfg.max_principal_point_sd * max(c.width, c.height) for cid, c in cams.items()}
    entries = {str(cid): principal_point_entry(c, sd[cid], limit[cid], (covs or {}).get(cid))
               for cid, c in cams.items()}  # our pixel convention (centres at integers)
    stats["principal_point"] = entries
    if cfg.principal_point != "auto" or not cams:
        return covs, None
    loose = [cid for cid in sd if not sd[cid] <= limit[cid]]
    if loose:  # not determined: again, without what trades against it (the radial term first, then it)
        msg = (f"the principal point of {len(loose)} camera(s) is not determined by the model (standard deviation "
               f"{max(sd[c] for c in loose):.1f} px > {min(limit[c] for c in loose):.1f} px)" +
               (" with a radial term: refined again without one (SIMPLE_PINHOLE)" if radial else
                ": every principal point kept at the image centre"))
        return covs, (msg, "principal_point_rejected", entries,
                      replace(cfg, radial="off") if radial else replace(cfg, principal_point="fixed"))
    off = {cid: float(np.hypot(entries[str(cid)]["px"][0] - (c.width - 1) / 2.0,
                               entries[str(cid)]["px"][1] - (c.height - 1) / 2.0)) for cid, c in cams.items()}
    near = {cid: off[cid] <= cfg.min_principal_point_offset * max(c.width, c.height) for cid, c in cams.items()}
    for cid in cams:
        entries[str(cid)]["offset_px"] = off[cid]
    if all(near.values()):
        msg = (f"the principal point of every camera was refined to within {max(off.values()):.1f} px of the image "
               f"centre (≤ {cfg.min_principal_point_offset:g} of the side; pycolmap's covariance claims "
               f"{max(sd.values()):.2g} px, a small share of its real error): held at the centre, as COLMAP's "
               "mappers hold it")
        return covs, (msg, "principal_point_near_centre", entries, replace(cfg, principal_point="fixed"))
    return covs, None


def _mahalanobis2(d: np.ndarray, C: Any) -> float:
    if C is None:
        return 0.0
    C = np.asarray(C, float)
    try:
        return float(d @ np.linalg.solve(0.5 * (C + C.T), d))
    except np.linalg.LinAlgError:
        return 0.0


def free_sigma(pc: Any, rec: Any, ba: Any, const: np.ndarray) -> float:
    """The screen's residual σ (px): a copy of the held run's final model ``rec`` bundle-adjusted with every principal
    point free (the cameras ``const`` held, the radial term as that run had it)."""
    free = pc.BundleAdjustmentOptions(ba.todict())
    free.refine_principal_point = True
    return residual_sigma_px(pc, rec, free, const)


def probe_principal_points(pc: Any, rec: Any, ba: Any, const: np.ndarray, K: np.ndarray, known: np.ndarray,
                           hold: np.ndarray, cfg: Any, names: Sequence[str],
                           run: Callable[[np.ndarray, np.ndarray, Any], Any]) -> tuple[Any | None, dict[str, Any]]:
    """The probe after a run with the principal points held (module docstring).

    Args:
        pc: pycolmap.
        rec, ba, const: that run's final reconstruction (image ``k`` = COLMAP image ``k + 1``), its bundle-adjustment
            options and its constant cameras.
        K: (N, 3, 3) its starting intrinsics; known: (N,) cameras with a K file; hold: (N,) cameras it held.
        cfg: its :class:`~pipeline.refine.refine.RefineConfig`.
        names: the N image names.
        run: ``run(K, hold, config)`` → the refinement from ``K`` with ``config``, holding ``hold``.
    Returns:
        the result to use instead (None: the held run stands) and the probe's figures.
    """
    try:
        sigma_held = residual_sigma_px(pc, rec, ba, const)
    except (RuntimeError, ValueError) as exc:  # no residuals to compare: the held run stands
        return None, {"decision": f"held at the image centres: no residual σ ({' '.join(str(exc).split())[:80]})"}
    info: dict[str, Any] = {"sigma_held_px": sigma_held, "misfit_limit": cfg.principal_point_misfit}
    try:  # the screen (module docstring): no misfit even with every principal point free, no probe run
        sigma_screen = free_sigma(pc, rec, ba, const)
        info["screen_ratio"] = sigma_held / sigma_screen if sigma_screen > 0 else float("inf")
    except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # not screened: the probe runs
        info["screen_failed"] = " ".join(str(exc).split())[:100]
    if not info.get("screen_ratio", float("inf")) >= cfg.principal_point_misfit:
        info.update(ratio=info["screen_ratio"], sigma_refined_px=sigma_screen, decision=(
            f"held at the image centres: the residuals with them held are {info['screen_ratio']:.2f}× those with them "
            f"freed in one bundle adjustment of the held run's model (< principal_point_misfit = "
            f"{cfg.principal_point_misfit:g}); the probe's run was not needed"))
        return None, info
    # the probe models what the held run modelled: without the lens the held run fits, the ratio would hide the
    # principal points' misfit (an internet imitation with a lens per image: 1.17 without, 1.57 with; 0.82° → 0.16°)
    probe = run(K, hold, replace(cfg, principal_point="refined"))
    if probe.reconstruction is None or "principal_point" not in probe.stats:
        info["decision"] = f"held at the image centres: the probe failed ({(probe.warnings or ['?'])[-1][:100]})"
        return None, info
    sigma_free = float(probe.stats["residual_sigma_px"])
    ratio = sigma_held / sigma_free if sigma_free > 0 else float("inf")
    info.update(sigma_refined_px=sigma_free, ratio=ratio)
    prec = probe.reconstruction
    free = np.zeros(len(names), bool)
    cams: dict[str, dict[str, Any]] = {}
    for iid in prec.reg_image_ids():
        k = iid - 1
        entry = probe.stats["principal_point"].get(str(prec.image(iid).camera_id))
        if entry is None or not rec.exists_image(iid) or not rec.image(iid).has_pose:
            continue
        held_cam = rec.camera(rec.image(iid).camera_id)
        d = np.asarray(entry["px"]) - [held_cam.principal_point_x - 0.5, held_cam.principal_point_y - 0.5]
        z2 = _mahalanobis2(d, entry["cov_px2"])
        determined = bool(entry["sd_px"] <= entry["max_sd_px"])
        free[k] = determined and z2 > CHI2_2DOF_999
        cams[names[k]] = {"offset_px": d.tolist(), "sd_px": entry["sd_px"], "chi2": z2, "determined": determined,
                          "refined": bool(free[k])}
    info["cameras"] = cams
    if not ratio >= cfg.principal_point_misfit or not free.any():
        why = (f"the residuals with them held are {ratio:.2f}× those with them refined (< principal_point_misfit = "
               f"{cfg.principal_point_misfit:g})" if not ratio >= cfg.principal_point_misfit else
               "no camera's principal point is both determined and significantly off the image centre")
        info["decision"] = f"held at the image centres: {why}"
        return None, info
    held = np.zeros(len(names), bool)
    for iid in rec.reg_image_ids():  # the others: held at the held run's intrinsics
        held[iid - 1] = not free[iid - 1] and not known[iid - 1]
    n_free, n_cams = int(free.sum()), len(cams)
    msg = (f"principal points refined for {n_free} of {n_cams} image(s) (with them held at the image centres the "
           f"residuals were {ratio:.2f}× those with them refined, σ {sigma_held:.3f} → {sigma_free:.3f} px, above "
           f"principal_point_misfit = {cfg.principal_point_misfit:g})")
    if held.any():
        K2 = K.copy()
        for k in np.flatnonzero(held):
            f = float(rec.camera(rec.image(int(k) + 1).camera_id).mean_focal_length())
            K2[k, 0, 0] = K2[k, 1, 1] = f
        msg += (f"; {int(held.sum())} held at the refinement's intrinsics with their principal point at the centre, "
                f"where it is not determined or not significantly off it "
                f"({', '.join(names[k] for k in np.flatnonzero(held)[:5])})")
        result = run(K2, hold | held, replace(cfg, principal_point="refined"))
        if result.reconstruction is None:  # that run failed: the held run stands
            info["decision"] = (f"held at the image centres: {msg}, but the refinement that way failed "
                                f"({(result.warnings or ['?'])[-1][:100]})")
            return None, info
    else:  # every camera refined: the probe is that run
        result = probe
    info["decision"] = msg
    result.warnings.insert(0, msg)
    return result, info
