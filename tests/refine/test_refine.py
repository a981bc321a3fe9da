"""refine_rotations on pycolmap's synthetic datasets (exact truth, Gaussian pixel noise of known σ).

Feature tests: the truth recovered from a perturbed start; the rotation covariance calibrated
(Monte Carlo over noise draws, in the gauge of the ℓ2-aligned evaluation). Failure tests: no
matches, every point removed before bundle adjustment, a camera moved more than the guard.
Exception tests: bad inputs and options, each with its message.
"""

from __future__ import annotations

import dataclasses



import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import ConfigError
from pipeline.refine import mapper
from pipeline.refine.refine import RefineConfig, refine_rotations

from .conftest import aligned_residuals, deep_problem, perturbed, synthetic_problem

ONE_THREAD = RefineConfig(num_threads=1, min_image_observations=10)


@pytest.mark.slow
def test_truth_recovered_and_covariance_calibrated():
    """12 noise draws × 8 cameras: the error ≪ the start's, and Σ|δ|² / Σ tr Σ ≈ 1 (pycolmap's covariance
    scaled by 4σ² and moved to the minimum-norm gauge; without the 4 the ratio is ≈ 3.6)."""
    rng = np.random.default_rng(1)
    ratios, errs, starts = [], [], []
    for seed in range(12):
        inp, R_true = synthetic_problem(seed)
        R0 = perturbed(R_true, 0.5, rng)
        res = refine_rotations(**inp, R_init=R0, config=ONE_THREAD)
        assert res.status == "ok" and res.refined.all() and res.cov is not None, res.warnings
        d = aligned_residuals(res.R, R_true)
        errs.append(np.degrees(np.linalg.norm(d, axis=1)))
        starts.append(np.degrees(np.linalg.norm(aligned_residuals(R0, R_true), axis=1)))
        ratios.append(np.sum(d ** 2) / np.sum(np.trace(res.cov, axis1=1, axis2=2)))
        assert abs(res.stats["sigma_px"] - 0.5) < 0.1  # the residual σ estimates the pixel noise
    ratio = float(np.mean(ratios))
    assert np.median(np.concatenate(errs)) < 0.1 * np.median(np.concatenate(starts))
    assert 0.6 < ratio < 1.6, ratio


def test_no_matches_fails_and_keeps_the_averaged(problem0):
    inp, R_true = problem0
    inp = dict(inp, match_offsets=np.zeros_like(inp["match_offsets"]), matches=np.zeros((0, 2), np.int64))
    res = refine_rotations(**inp, R_init=R_true, config=ONE_THREAD)
    assert res.status == "failed" and not res.refined.any() and np.array_equal(res.R, R_true)
    assert any("nothing to refine" in w for w in res.warnings) and all("0 track observations" in w for w in res.why)


def test_bundle_adjustment_failure_is_reported_and_the_averaged_kept(problem0, points_removed_after_positioning):
    """Every point removed after positioning: bundle adjustment cannot run; the averaged rotations stay."""
    inp, R_true = problem0
    R0 = perturbed(R_true, 0.3, np.random.default_rng(2))
    res = refine_rotations(**inp, R_init=R0, config=ONE_THREAD)
    assert res.status == "failed" and np.array_equal(res.R, R0) and res.reconstruction is None
    assert any("bundle adjustment failed" in w and "averaged rotations are kept" in w for w in res.warnings)


def test_a_raising_pycolmap_step_is_a_failure_not_a_crash(problem0, monkeypatch):
    inp, R_true = problem0

    def boom(*a, **k):
        raise RuntimeError("[global_mapper.cc:1] Check failed")

    monkeypatch.setattr(mapper, "retriangulate", boom)
    res = refine_rotations(**inp, R_init=R_true, config=ONE_THREAD)
    assert res.status == "failed" and np.array_equal(res.R, R_true)
    assert "retriangulation raised RuntimeError" in res.warnings[-1]


def test_change_guard_keeps_both():
    """A start camera 3° off is pulled back by BA: above a 1° guard it keeps its averaged rotation."""
    inp, R_true = synthetic_problem(3)
    R0 = R_true.copy()
    R0[2] = so3.exp(np.radians([0.0, 3.0, 0.0])) @ R0[2]
    cfg = ONE_THREAD.replace(edge_filter_deg=None, max_change_deg=1.0)
    res = refine_rotations(**inp, R_init=R0, config=cfg)
    assert res.status == "partial" and not res.refined[2] and res.refined[np.arange(len(R0)) != 2].all()
    assert np.array_equal(res.R[2], R0[2]) and 2.5 < res.change_deg[2] < 3.5
    assert np.degrees(np.linalg.norm(aligned_residuals(res.R_refined, R_true), axis=1)).max() < 0.1
    assert "max_change_deg" in res.why[2] and any("keeps its averaged rotation" in w for w in res.warnings)


def test_anchor_rotations_chain_the_refined_neighbours_through_the_pairs():
    """Exact pairs and exact neighbours give the truth; two pairs of opposite 2° errors average out; a target with
    no refined neighbour (or only another target) gets none; the convention R_ij = R_j R_iᵀ both ways round."""
    from pipeline.refine.checks import anchor_rotations

    rng = np.random.default_rng(4)
    R = so3.random_rotations(6, rng)
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 5], [4, 5], [1, 4]])
    R_rel = R[edges[:, 1]] @ np.swapaxes(R[edges[:, 0]], 1, 2)
    refined = np.array([True, False, True, True, False, False])
    targets = ~refined
    out, count = anchor_rotations(edges, R_rel, R, refined, targets)
    assert count.tolist() == [0, 2, 0, 0, 0, 1]  # 1: from 0 and 2; 5: from 3 (4 is a target, not a source)
    np.testing.assert_allclose(out[[1, 5]], R[[1, 5]], atol=1e-12)
    assert np.isnan(out[[0, 2, 3, 4]]).all()
    tilt = so3.exp(np.radians([2.0, 0.0, 0.0]))
    noisy = R_rel.copy()
    noisy[0] = tilt @ R_rel[0]  # R_1 = R_01 R_0 predicted as T R_1 ...
    noisy[1] = R_rel[1] @ tilt  # ... and R_1 = R_12ᵀ R_2 as Tᵀ R_1: their chordal mean is R_1
    out, _ = anchor_rotations(edges, noisy, R, refined, targets)
    assert np.degrees(so3.angle_between(out[1:2], R[1:2]))[0] < 1e-9
    one, _ = anchor_rotations(edges[:1], noisy[:1], R, refined, targets)  # one pair: its error, 2°
    assert abs(np.degrees(so3.angle_between(one[1:2], R[1:2]))[0] - 2.0) < 1e-9


def test_an_image_the_final_model_loses_is_chained_from_its_refined_neighbours(problem0, monkeypatch):
    """An image lost by the final model (here: taken out of it) keeps no averaged rotation 5° off: it is chained from
    its refined neighbours through its kept pairs, back near the truth, and says so."""
    from pipeline.refine import checks

    inp, R_true = problem0
    R0 = R_true.copy()
    R0[3] = so3.exp(np.radians([0.0, 0.0, 4.0])) @ R0[3]  # the averaging's error at this image
    real = checks.model_rotations

    def lose_3(rec, n):  # image 3 (id 4) leaves the final model, with its points
        rec.deregister_frame(rec.image(4).frame_id)
        return real(rec, n)

    monkeypatch.setattr(checks, "model_rotations", lose_3)
    res = refine_rotations(**inp, R_init=R0, config=ONE_THREAD.replace(edge_filter_deg=None))
    assert res.status == "partial" and not res.refined[3] and res.anchored.tolist() == [k == 3 for k in range(len(R0))]
    err = np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1))
    assert err[3] < 0.2 and err.max() < 0.2, err
    assert "chained from refined neighbours" in res.why[3] and res.stats["anchored"] == {inp["names"][3]: 7}
    monkeypatch.setattr(checks, "model_rotations", real)  # without the loss: nothing anchored
    res = refine_rotations(**inp, R_init=R0, config=ONE_THREAD.replace(edge_filter_deg=None))
    assert not res.anchored.any() and "anchored" not in res.stats


def test_an_image_with_too_few_tracks_is_chained_from_its_refined_neighbours(problem0):
    """An image whose pairs keep only 2 matches each (too few track observations to enter the model) and whose
    averaged rotation is 4° off: chained from its refined neighbours through those pairs, back near the truth."""
    inp, R_true = problem0
    off, m = inp["match_offsets"], inp["matches"]
    keep_rows = np.concatenate([np.arange(off[e], off[e + 1])[: 2 if 3 in inp["edges"][e] else None]
                                for e in range(len(inp["edges"]))])
    counts = np.array([min(off[e + 1] - off[e], 2) if 3 in inp["edges"][e] else off[e + 1] - off[e]
                       for e in range(len(inp["edges"]))])
    thin = dict(inp, match_offsets=np.r_[0, np.cumsum(counts)], matches=m[keep_rows])
    R0 = R_true.copy()
    R0[3] = so3.exp(np.radians([0.0, 4.0, 0.0])) @ R0[3]
    res = refine_rotations(**thin, R_init=R0, config=ONE_THREAD.replace(edge_filter_deg=None))
    assert res.status == "partial" and not res.refined[3] and res.anchored[3] and res.refined[np.arange(8) != 3].all()
    assert "track observations" in res.why[3] and "chained from refined neighbours" in res.why[3]
    err = np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1))
    assert err[3] < 0.2 and err.max() < 0.2, err


def test_an_unknown_camera_keeps_its_refined_rotation_however_far_it_moved():
    """Without a K file the averaged rotation rested on the cameras stage's focal: a camera the model moves 3°
    (above a 1° guard) keeps the refined rotation, back at the truth, and the warning names both focal lengths;
    with ``max_change_known_only: false`` it keeps the averaged one, as a camera of known K does."""
    inp, R_true = synthetic_problem(3)
    R0 = R_true.copy()
    R0[2] = so3.exp(np.radians([0.0, 3.0, 0.0])) @ R0[2]
    cfg = ONE_THREAD.replace(edge_filter_deg=None, max_change_deg=1.0, principal_point="fixed")
    res = refine_rotations(**inp, R_init=R0, known_K=False, config=cfg)
    assert res.status == "ok" and res.refined.all() and res.stats["n_moved_refined"] == 1
    assert np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1)).max() < 0.1
    (w,) = [w for w in res.warnings if "max_change_deg" in w]
    assert w.startswith(f"{inp['names'][2]}: refined rotation") and "its K is not known" in w and "px" in w
    strict = refine_rotations(**inp, R_init=R0, known_K=False, config=cfg.replace(max_change_known_only=False))
    assert strict.status == "partial" and not strict.refined[2] and np.array_equal(strict.R[2], R0[2])


def test_radial_off_gives_one_focal_length_and_no_lens(problem0):
    inp, _ = problem0
    res = refine_rotations(**dict(inp, K=_shifted_intrinsics(inp)), R_init=problem0[1], known_K=False,
                           config=ONE_THREAD.replace(radial="off", principal_point="fixed"))
    (cam,) = res.reconstruction.cameras.values()
    assert res.status == "ok" and cam.model.name == "SIMPLE_PINHOLE" and "radial" not in res.stats


def test_undetermined_radial_term_is_dropped(problem0):
    """A radial term whose corner displacement the model does not determine (here: a limit no estimate meets) is
    not kept: the refinement runs again without one, says so, and records what was rejected."""
    inp, R_true = problem0
    res = refine_rotations(**dict(inp, K=_shifted_intrinsics(inp)), R_init=R_true, known_K=False,
                           config=ONE_THREAD.replace(principal_point="fixed", max_radial_sd=1e-9))
    (cam,) = res.reconstruction.cameras.values()
    assert res.status == "ok" and cam.model.name == "SIMPLE_PINHOLE" and "radial" not in res.stats
    assert any("radial term of 1 camera(s) is not determined" in w for w in res.warnings), res.warnings
    rej = res.stats["radial_rejected"]["1"]
    assert rej["corner_sd_px"] > rej["max_sd_px"]


def test_the_fast_preset_and_an_image_without_a_start(problem0):
    inp, R_true = problem0
    R0 = R_true.copy()
    R0[5] = np.nan  # not in the averaged component: not refined, named
    res = refine_rotations(**inp, R_init=R0, config=ONE_THREAD.replace(preset="fast"))
    assert res.stats["schedule"] == {"positioning_tracks_per_image": 500, "refinement_rounds": 1}
    assert res.status == "ok" and not res.refined[5] and res.why[5] == "no averaged rotation"
    assert np.isnan(res.R[5]).all() and res.refined.sum() == len(R0) - 1



def test_a_k_file_for_the_refined_images_and_an_unknown_image_without_a_start(problem0):
    """A K file for every image but one, which the view graph left out (no averaged rotation): the images refined
    all have known K, so no principal point is refined or probed (it used to stop on an empty minimum)."""
    inp, R_true = problem0
    R0 = perturbed(R_true, 0.3, np.random.default_rng(4))
    R0[5] = np.nan
    known = np.ones(len(R0), bool)
    known[5] = False
    res = refine_rotations(**inp, R_init=R0, known_K=known, config=ONE_THREAD)
    assert res.status == "ok" and not res.refined[5] and res.refined.sum() == len(R0) - 1
    assert "principal_point" not in res.stats and "principal_point_probe" not in res.stats
    assert all(c.model.name == "PINHOLE" for c in res.reconstruction.cameras.values())
    err = np.degrees(np.linalg.norm(aligned_residuals(np.delete(res.R, 5, 0), np.delete(R_true, 5, 0)), axis=1))
    assert err.max() < 0.1, err


def test_chain_starts_reach_targets_through_other_targets_in_rounds():
    """Exact pairs: a target two pairs away from every image with a rotation gets its start in the second round,
    through the first; a target joined to none gets none; the other images get none."""
    from pipeline.refine.checks import chain_starts

    R = so3.exp(np.random.default_rng(3).normal(size=(6, 3)))
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 4]])  # 3 only through 2; 5 joined to nothing
    R_rel = R[edges[:, 1]] @ np.swapaxes(R[edges[:, 0]], 1, 2)
    targets = np.array([False, False, True, True, False, True])
    R_in = np.where(targets[:, None, None], np.nan, R)
    out, count = chain_starts(edges, R_rel, R_in, targets)
    np.testing.assert_allclose(out[[2, 3]], R[[2, 3]], atol=1e-12)
    assert count.tolist() == [0, 0, 1, 1, 0, 0] and np.isnan(out[[0, 1, 4, 5]]).all()


def test_an_image_without_an_averaged_rotation_is_refined_from_its_start(problem0):
    """An image the averaging left out, started 3° off (R_start): refined back to the truth with the others, kept
    out of the alignment to the averaged frame (whose other rotations it does not move), and without a change from
    an averaged rotation; started without tracks, it gets no rotation and says why."""
    inp, R_true = problem0
    R0 = R_true.copy()
    R0[5] = np.nan
    R_start = np.full_like(R_true, np.nan)
    R_start[5] = so3.exp(np.radians([3.0, 0.0, 0.0])) @ R_true[5]
    res = refine_rotations(**inp, R_init=R0, R_start=R_start, config=ONE_THREAD)
    assert res.status == "ok" and res.refined.all() and res.why[5] == "" and np.isnan(res.change_deg[5])
    err = np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1))
    assert err.max() < 0.1, err
    without = refine_rotations(**inp, R_init=R0, config=ONE_THREAD)
    assert not without.refined[5] and np.isnan(without.R[5]).all()
    others = np.arange(8) != 5
    assert np.degrees(so3.angle_between(res.R[others], without.R[others])).max() < 0.02
    off, m = inp["match_offsets"], inp["matches"]
    keep = [e for e in range(len(inp["edges"])) if 5 not in inp["edges"][e]]
    rows = np.concatenate([np.arange(off[e], off[e + 1]) for e in keep])
    counts = [off[e + 1] - off[e] if e in keep else 0 for e in range(len(inp["edges"]))]
    bare = refine_rotations(**dict(inp, match_offsets=np.r_[0, np.cumsum(counts)], matches=m[rows]), R_init=R0,
                            R_start=R_start, config=ONE_THREAD)
    assert bare.status == "ok" and not bare.refined[5] and np.isnan(bare.R[5]).all()
    assert "track observations" in bare.why[5]
    with pytest.raises(ValueError, match=r"R_start.shape=\(3, 3, 3\) but expected \(8, 3, 3\)"):
        refine_rotations(**inp, R_init=R0, R_start=R_start[:3], config=ONE_THREAD)

@pytest.mark.parametrize("kw, match", [
    ({"max_change_deg": 0}, r"\[refine\] max_change_deg=0.0 but expected > 0"),
    ({"preset": "slow"}, r"\[refine\] preset='slow' but expected one of 'glomap', 'fast'"),
    ({"start": "a b"}, r"\[refine\] start='a b' but expected 'auto' or a method label"),
    ({"num_threads": 0}, r"num_threads=0"),
    ({"min_track_views": 1}, r"min_track_views=1 but expected >= 2"),
])
def test_bad_options(kw, match):
    with pytest.raises(ConfigError, match=match):
        RefineConfig(**kw)


def test_bad_inputs(problem0):
    inp, R_true = problem0
    with pytest.raises(ValueError, match=r"R_init.shape=\(3, 3, 3\) but expected \(8, 3, 3\)"):
        refine_rotations(**inp, R_init=R_true[:3])
    with pytest.raises(ValueError, match=r"edges must be pairs \(i, j\) with 0 <= i < j < 8"):
        refine_rotations(**dict(inp, edges=inp["edges"][:, ::-1]), R_init=R_true)


def _shifted_intrinsics(inp: dict) -> np.ndarray:
    """The true K with the focal 3% off and the principal point 20 px right and 15 px up: a K estimated without one
    (principal point at a wrong place such as the image centre)."""
    K = inp["K"].copy()
    K[:, 0, 0] *= 1.03
    K[:, 1, 1] *= 1.03
    K[:, 0, 2] += 20.0
    K[:, 1, 2] -= 15.0
    return K


def test_unknown_principal_point_is_refined_where_the_model_determines_it(problem0):
    """Unknown K, the true principal point 25 px off the image centre (every keypoint moved by (20, −15) px), the
    start at the centre with the focal 3% off: one focal length and k1 (SIMPLE_RADIAL; no lens, so k1 stays near 0)
    and the principal point refined to the truth, kept because its standard deviation is small and it is off the
    centre by more than min_principal_point_offset; fixed at the centre, the rotations are worse."""
    inp, R_true = problem0
    shift = np.array([20.0, -15.0])
    inp = dict(inp, keypoints=[k + shift for k in inp["keypoints"]])
    K = inp["K"].copy()
    K[:, 0, 0] *= 1.03
    K[:, 1, 1] *= 1.03
    true_pp = inp["K"][0, :2, 2] + shift
    err = lambda res: np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1)).max()  # noqa: E731
    auto = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False, config=ONE_THREAD)
    fixed = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False,
                             config=RefineConfig(num_threads=1, min_image_observations=10, principal_point="fixed"))
    assert auto.status == fixed.status == "ok" and not auto.warnings, auto.warnings
    (cam,) = auto.reconstruction.cameras.values()
    assert cam.model.name == "SIMPLE_RADIAL"  # one focal length: fx and fy cannot trade against the rotations
    # no lens: k1 within what 0.5 px noise allows (under 1 px at the corners; a real lens is 0.02–0.2)
    assert abs(cam.params[3]) < 0.005 and auto.stats["radial"]["1"]["k1"] == cam.params[3]
    assert 0 < auto.stats["radial"]["1"]["corner_sd_px"] < auto.stats["radial"]["1"]["max_sd_px"] == 0.01 * 1024
    pp = auto.stats["principal_point"]["1"]
    assert np.abs(np.array(pp["px"]) - true_pp).max() < 2.0, pp  # 20 and 15 px off at the start
    assert 0 < pp["sd_px"] < pp["max_sd_px"] == pytest.approx(0.01 * 1024)
    assert pp["offset_px"] > 0.004 * 1024 and "principal_point_near_centre" not in auto.stats
    (cam_fixed,) = fixed.reconstruction.cameras.values()
    np.testing.assert_allclose([cam_fixed.principal_point_x - 0.5, cam_fixed.principal_point_y - 0.5], K[0, :2, 2])
    assert "principal_point" not in fixed.stats
    assert err(auto) < 0.5 * err(fixed)


def test_a_principal_point_refined_to_near_the_image_centre_is_held_there(problem0):
    """The true principal point at the image centre, the start 25 px off it: refined, it comes back to within
    min_principal_point_offset (0.4% of the side) of the centre, so it is held at the centre, as COLMAP's mappers
    hold it (its real error would be several times what the covariance claims), with a note and no warning; the
    rotations are as good as the refined run's. With the offset test off (0) it stays refined."""
    inp, R_true = problem0
    K = _shifted_intrinsics(inp)
    err = lambda res: np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1)).max()  # noqa: E731
    held = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False, config=ONE_THREAD)
    free = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False,
                            config=dataclasses.replace(ONE_THREAD, min_principal_point_offset=0.0))
    assert held.status == free.status == "ok" and not held.warnings, held.warnings
    near = held.stats["principal_point_near_centre"]["1"]
    assert near["offset_px"] < 0.004 * 1024 and "principal_point" not in held.stats
    (cam,) = held.reconstruction.cameras.values()
    np.testing.assert_allclose([cam.principal_point_x - 0.5, cam.principal_point_y - 0.5], [511.5, 383.5])
    assert "principal_point_near_centre" not in free.stats and free.stats["principal_point"]["1"]["offset_px"] < 4
    assert err(held) <= 1.2 * err(free) + 1e-3


def test_undetermined_principal_point_is_kept_at_the_given_one(problem0):
    """A principal point whose standard deviation exceeds the limit is not kept: the refinement runs again with it
    fixed, says so, and records what was rejected."""
    inp, R_true = problem0
    K = _shifted_intrinsics(inp)
    res = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False,
                           config=RefineConfig(num_threads=1, min_image_observations=10, max_principal_point_sd=1e-6))
    assert res.status == "ok" and res.refined.all()
    assert any("not determined by the model" in w for w in res.warnings), res.warnings
    (cam,) = res.reconstruction.cameras.values()
    np.testing.assert_allclose([cam.principal_point_x - 0.5, cam.principal_point_y - 0.5], K[0, :2, 2])
    assert res.stats["principal_point_rejected"]["1"]["sd_px"] > res.stats["principal_point_rejected"]["1"]["max_sd_px"]
    with pytest.raises(ValueError, match="principal_point"):
        RefineConfig(principal_point="free")


def test_principal_point_of_a_one_image_camera_is_not_refined(problem0):
    """Every image its own camera (a K each, as internet photos without EXIF): on this scene one image does not
    separate its principal point from its pose (standard deviations near 100 px), and refining them barely lowers
    the residuals, so 'auto' keeps every principal point after its probe's screen; 'refined' still refines them."""
    inp, R_true = problem0
    K = _shifted_intrinsics(inp)
    K[:, 0, 0] += np.arange(len(K))  # a different focal per image: one camera each
    K[:, 1, 1] = K[:, 0, 0]
    auto = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False, config=ONE_THREAD)
    assert auto.status == "ok" and "principal_point" not in auto.stats
    assert "1 image(s)" in auto.stats["principal_point_fixed_why"]
    probe = auto.stats["principal_point_probe"]
    assert probe["ratio"] < 1.3 and probe["decision"].startswith("held at the image centres")
    assert "the probe's run was not needed" in probe["decision"]  # its screen found no misfit
    for cid, cam in auto.reconstruction.cameras.items():
        assert cam.model.name == "SIMPLE_RADIAL"  # one focal length and k1 per image, as COLMAP's mappers
        np.testing.assert_allclose([cam.principal_point_x - 0.5, cam.principal_point_y - 0.5], K[0, :2, 2])
    forced = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False,
                              config=RefineConfig(num_threads=1, min_image_observations=10, principal_point="refined"))
    assert len(forced.stats["principal_point"]) == len(K)


def test_principal_point_whose_covariance_fails_is_kept_at_the_given_one(problem0, monkeypatch):
    """pycolmap's covariance raising is no proof that the principal point is determined: it is fixed, not a crash."""
    from pipeline.refine import principal as principal_module

    def failing(*args, **kwargs):
        raise RuntimeError("Ceres: the problem is rank deficient")

    monkeypatch.setattr(principal_module, "principal_point_sd", failing)
    inp, R_true = problem0
    K = _shifted_intrinsics(inp)
    res = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False, config=ONE_THREAD)
    assert res.status == "ok" and res.refined.all()
    assert any("not determined by the model" in w for w in res.warnings), res.warnings
    (cam,) = res.reconstruction.cameras.values()
    np.testing.assert_allclose([cam.principal_point_x - 0.5, cam.principal_point_y - 0.5], K[0, :2, 2])


def test_unknown_intrinsics_are_refined_known_ones_kept(problem0):
    """A focal 3% off: kept constant when 'known', refined toward the truth when not."""
    inp, R_true = problem0
    K = inp["K"].copy()
    K[:, 0, 0] *= 1.03
    K[:, 1, 1] *= 1.03
    kept = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=True, config=ONE_THREAD)
    free = refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False, config=ONE_THREAD)
    f = lambda res: np.array([c.params[0] for c in res.reconstruction.cameras.values()])  # noqa: E731
    np.testing.assert_allclose(f(kept), 1280.0 * 1.03)
    (cam,) = kept.reconstruction.cameras.values()  # known: PINHOLE, every parameter constant
    assert cam.model.name == "PINHOLE" and "principal_point" not in kept.stats
    assert np.all(np.abs(f(free) - 1280.0) < 0.3 * 1280.0 * 0.03)
    assert free.status == "ok" and free.stats["mean_reprojection_error_px"] < kept.stats["mean_reprojection_error_px"]


def test_a_bogus_focal_length_is_held_and_a_weakly_determined_one_stays_refined(problem0):
    """COLMAP's bogus-camera test (here: a focal-length range no estimate meets) holds a camera at the cameras
    stage's estimate: the refinement runs again with it constant, says so and records what it refined before. A
    focal length the model determines poorly (here: a limit no estimate meets) stays as refined, with a warning and
    its standard deviation on record; with the defaults neither happens (the focal lengths are determined)."""
    inp, R_true = problem0
    K = _shifted_intrinsics(inp)
    K[:, 0, 0] = K[:, 1, 1] = K[:, 0, 0] * (1.04 + 0.002 * np.arange(len(K)))  # 4-6% off, one camera per image
    run = lambda **kw: refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False,  # noqa: E731
                                        config=ONE_THREAD.replace(**kw))
    side = float(np.max(inp["sizes"]))
    held = run(min_focal_ratio=0.01, max_focal_ratio=0.5 * K[:, 0, 0].min() / side)
    loose = run(max_focal_sd=1e-9)
    free = run()
    assert held.status == loose.status == free.status == "ok" and held.refined.all() and loose.refined.all()
    assert any(f"intrinsics of {len(K)} camera(s) are bogus" in w for w in held.warnings), held.warnings
    assert any(f"focal length of {len(K)} camera(s) is weakly determined" in w for w in loose.warnings), loose.warnings
    assert len(held.stats["focal_held"]) == len(loose.stats["focal_loose"]) == len(K)
    assert all(v["corner_sd_px"] > 0 for v in loose.stats["focal_loose"].values())
    assert not {"focal_held", "focal_loose"} & (set(free.stats) | set(loose.stats) - {"focal_loose"})
    for res, same in ((held, True), (loose, False), (free, False)):
        for iid, im in res.reconstruction.images.items():
            f = res.reconstruction.cameras[im.camera_id].mean_focal_length()
            assert np.isclose(f, K[iid - 1, 0, 0], rtol=1e-9) == same, (iid, f, K[iid - 1, 0, 0])
    free_f = {i: free.reconstruction.cameras[im.camera_id].mean_focal_length()
              for i, im in free.reconstruction.images.items()}
    for i, im in loose.reconstruction.images.items():  # the warning changes nothing
        assert loose.reconstruction.cameras[im.camera_id].mean_focal_length() == pytest.approx(free_f[i], rel=1e-9)


def test_without_a_covariance_the_bogus_test_still_holds_and_no_focal_is_called_weak(problem0, monkeypatch):
    """pycolmap's covariance can fail (castle's weak internet graphs): then no focal length is said to be weakly
    determined (nothing shows it), while COLMAP's bogus test, which needs none, still holds a camera."""
    from pipeline.refine import checks
    from pipeline.refine import refine as refine_module

    def fail(*a, **k):
        raise RuntimeError("[covariance.cc:1] rank deficient")

    monkeypatch.setattr(checks, "camera_covariances", fail)
    monkeypatch.setattr(refine_module, "camera_covariances", fail)  # the radial check's: it drops the radial term
    inp, R_true = problem0
    K = _shifted_intrinsics(inp)
    K[:, 0, 0] = K[:, 1, 1] = K[:, 0, 0] * (1.04 + 0.002 * np.arange(len(K)))  # one camera per image, so
    side = float(np.max(inp["sizes"]))  # principal points held and the focal check made
    run = lambda **kw: refine_rotations(**dict(inp, K=K), R_init=R_true, known_K=False,  # noqa: E731
                                        config=ONE_THREAD.replace(covariance=False, **kw))
    loose = run(max_focal_sd=1e-9)
    held = run(min_focal_ratio=0.01, max_focal_ratio=0.5 * K[:, 0, 0].min() / side)
    assert "focal_loose" not in loose.stats and "focal_held" not in loose.stats
    assert len(held.stats["focal_held"]) == len(K)
    assert all(np.isnan(v["corner_sd_px"]) for v in held.stats["focal_held"].values())


def test_the_bogus_focal_range_is_checked():
    from pipeline.core.errors import ConfigError

    with pytest.raises(ConfigError, match="min_focal_ratio=2 is not below max_focal_ratio=1"):
        ONE_THREAD.replace(min_focal_ratio=2.0, max_focal_ratio=1.0).check()


def test_focal_corner_sd_is_the_corner_displacement_of_one_standard_deviation():
    from types import SimpleNamespace

    from pipeline.refine.covariance import focal_corner_sd

    cam = SimpleNamespace(width=800, height=600, focal_length_idxs=lambda: [0], mean_focal_length=lambda: 1000.0)
    rec = SimpleNamespace(camera=lambda cid: cam)
    C = np.diag([4.0, np.nan, np.nan, 1e-6])  # sd(f) = 2 px; the constant principal point is NaN
    out = focal_corner_sd(rec, {1: C, 2: None})
    assert out[1] == pytest.approx(2.0 * 500.0 / 1000.0) and out[2] == float("inf")


def _errors(res, R_true):
    return np.degrees(np.linalg.norm(aligned_residuals(res.R, R_true), axis=1))


def test_principal_points_off_the_centre_are_refined_where_the_centre_is_a_misfit():
    """One camera per image, principal points up to 3% of the width off the centre, a deep scene that determines
    them: held at the centres, the residuals are well above the pixel noise's; the probe sees it, the principal
    points are refined back to the truth, and the rotations are far better than with them held (no probe)."""
    inp, R_true, K_true = deep_problem(0)
    auto = refine_rotations(**inp, R_init=R_true, known_K=False, config=ONE_THREAD)
    held = refine_rotations(**inp, R_init=R_true, known_K=False,
                            config=dataclasses.replace(ONE_THREAD, principal_point_misfit=None))
    assert auto.status == held.status == "ok" and "principal_point_probe" not in held.stats
    probe = auto.stats["principal_point_probe"]
    assert probe["ratio"] >= 1.3 and probe["sigma_refined_px"] == pytest.approx(0.5, rel=0.2)
    assert all(c["refined"] for c in probe["cameras"].values()) and len(probe["cameras"]) == len(R_true)
    assert auto.warnings[0].startswith(f"principal points refined for {len(R_true)} of {len(R_true)} image(s)")
    for iid, im in auto.reconstruction.images.items():
        cam = auto.reconstruction.cameras[im.camera_id]
        pp = np.array([cam.principal_point_x, cam.principal_point_y]) - 0.5
        assert np.abs(pp - K_true[iid - 1, :2, 2]).max() < 3.0  # up to 31 px off at the start
    assert np.median(_errors(auto, R_true)) < 0.1 * np.median(_errors(held, R_true))


def test_a_principal_point_at_the_centre_is_held_while_the_others_are_refined():
    """One image's principal point is at the centre: not significantly off it, so that camera is held at the held
    run's intrinsics (its refined focal length, the centre) while the others' principal points are refined."""
    inp, R_true, K_true = deep_problem(1, centred=(3,))
    R0 = perturbed(R_true, 0.5, np.random.default_rng(8))  # a start the refinement has to move from
    res = refine_rotations(**inp, R_init=R0, known_K=False, config=ONE_THREAD)
    probe = res.stats["principal_point_probe"]
    assert [nm for nm, c in probe["cameras"].items() if not c["refined"]] == [inp["names"][3]]
    assert probe["cameras"][inp["names"][3]]["determined"]  # determined, and at the centre
    assert "1 held at the refinement's intrinsics" in res.warnings[0] and inp["names"][3] in res.warnings[0]
    for iid, im in res.reconstruction.images.items():
        cam = res.reconstruction.cameras[im.camera_id]
        pp = np.array([cam.principal_point_x, cam.principal_point_y]) - 0.5
        assert np.abs(pp - K_true[iid - 1, :2, 2]).max() < (1e-9 if iid == 4 else 3.0), iid
    start = np.degrees(np.linalg.norm(aligned_residuals(R0, R_true), axis=1))
    assert np.median(_errors(res, R_true)) < 0.1 < np.median(start)


def test_principal_points_at_the_centre_stay_held_and_the_result_is_the_held_run():
    """Principal points at the centres: refining them lowers the residuals by nothing the noise does not explain;
    the held run stands as it was (to ceres' own run-to-run rounding, 1e-15), and the probe's figures are recorded."""
    inp, R_true, _ = deep_problem(0, pp_shift=0.0)
    auto = refine_rotations(**inp, R_init=R_true, known_K=False, config=ONE_THREAD)
    held = refine_rotations(**inp, R_init=R_true, known_K=False,
                            config=dataclasses.replace(ONE_THREAD, principal_point_misfit=None))
    probe = auto.stats["principal_point_probe"]
    assert probe["ratio"] < 1.1 and "principal_point_misfit = 1.3" in probe["decision"]
    assert probe["screen_ratio"] == probe["ratio"] and "the probe's run was not needed" in probe["decision"]
    np.testing.assert_allclose(auto.R, held.R, rtol=0, atol=1e-12)
    assert auto.warnings == held.warnings


def test_the_probes_decision_and_a_failed_second_run(monkeypatch):
    """The probe's logic on stand-ins for pycolmap's objects: of two images, the one whose principal point is
    determined and 30 px off is refined, the other held at the held run's focal length; if that run fails, the held
    run stands and the decision says why."""
    from types import SimpleNamespace

    from pipeline.refine import principal

    monkeypatch.setattr(principal, "residual_sigma_px", lambda *a: 0.5)
    monkeypatch.setattr(principal, "free_sigma", lambda *a: 0.25)  # the screen: a misfit, so the probe runs
    cam = SimpleNamespace(principal_point_x=100.5, principal_point_y=80.5, mean_focal_length=lambda: 480.0)
    rec = SimpleNamespace(reg_image_ids=lambda: [1, 2], camera=lambda cid: cam, exists_image=lambda iid: True,
                          image=lambda iid: SimpleNamespace(camera_id=iid, has_pose=True))
    entry = lambda px: {"px": px, "sd_px": 1.0, "max_sd_px": 5.0, "cov_px2": [[1.0, 0.0], [0.0, 1.0]]}  # noqa: E731
    probe = SimpleNamespace(reconstruction=rec, warnings=[], stats={
        "residual_sigma_px": 0.25, "principal_point": {"1": entry([130.0, 80.0]), "2": entry([100.5, 80.0])}})
    calls = []

    def run(K, hold, cfg, second=None):
        calls.append((K.copy(), hold.copy(), cfg.principal_point))
        return probe if len(calls) == 1 else second

    K = np.tile(np.array([[500.0, 0, 100.0], [0, 500.0, 80.0], [0, 0, 1]]), (2, 1, 1))
    args = (None, rec, None, np.zeros(2, bool), K, np.zeros(2, bool), np.zeros(2, bool), RefineConfig(), ["a", "b"])
    done = SimpleNamespace(reconstruction=rec, warnings=["w"], stats={})
    res, info = principal.probe_principal_points(*args, lambda K, h, c: run(K, h, c, done))
    assert res is done and info["ratio"] == 2.0 and res.warnings[0].startswith("principal points refined for 1 of 2")
    assert [c["refined"] for c in info["cameras"].values()] == [True, False] and info["cameras"]["a"]["chi2"] == 900.0
    K2, hold2, pp = calls[1]
    assert pp == "refined" and hold2.tolist() == [False, True] and K2[1, 0, 0] == K2[1, 1, 1] == 480.0
    assert K2[0, 0, 0] == 500.0  # the refined camera starts where the probe did
    calls.clear()
    failed = SimpleNamespace(reconstruction=None,
                             warnings=["global positioning failed; the averaged rotations are kept"])
    res, info = principal.probe_principal_points(*args, lambda K, h, c: run(K, h, c, failed))
    assert res is None and "the refinement that way failed (global positioning failed" in info["decision"]
    assert info["decision"].startswith("held at the image centres")


def test_the_probes_screen_spares_its_run_where_the_centre_is_no_misfit(monkeypatch):
    """The screen (one bundle adjustment with every principal point free) below principal_point_misfit: the held run
    stands and the probe's run never starts; above it, or where the screen fails, the probe runs as before."""
    from types import SimpleNamespace

    from pipeline.refine import principal

    monkeypatch.setattr(principal, "residual_sigma_px", lambda *a: 0.5)
    calls = []
    probe = SimpleNamespace(reconstruction=None, warnings=["global positioning failed"], stats={})

    def run(K, hold, cfg):
        calls.append(cfg.principal_point)
        return probe

    args = (None, None, None, np.zeros(2, bool), np.tile(np.eye(3), (2, 1, 1)), np.zeros(2, bool), np.zeros(2, bool),
            RefineConfig(), ["a", "b"], run)
    monkeypatch.setattr(principal, "free_sigma", lambda *a: 0.45)  # 1.11× < 1.3
    res, info = principal.probe_principal_points(*args)
    assert res is None and not calls and info["screen_ratio"] == info["ratio"] == pytest.approx(0.5 / 0.45)
    assert info["decision"].startswith("held at the image centres: the residuals with them held are 1.11×")
    assert "the probe's run was not needed" in info["decision"]
    monkeypatch.setattr(principal, "free_sigma", lambda *a: 0.3)  # 1.67×: the probe's run decides
    res, info = principal.probe_principal_points(*args)
    assert res is None and calls == ["refined"] and "the probe failed (global positioning failed)" in info["decision"]

    def no_fit(*a):
        raise RuntimeError("ceres: the problem is not finite")

    monkeypatch.setattr(principal, "free_sigma", no_fit)  # not screened: the probe runs
    res, info = principal.probe_principal_points(*args)
    assert calls == ["refined", "refined"] and info["screen_failed"] == "ceres: the problem is not finite"
