"""Guided matching (pipeline.geometry.guided) against known truth: synthetic pairs, a rendered low-texture pair."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.core import so3
from pipeline.frontend.features import FeatureConfig, extract_sift_adaptive
from pipeline.frontend.matching import match_descriptors, root_sift
from pipeline.geometry.guided import (
    epipolar_distances,
    estimate_pair_guided,
    fundamental_from_pose,
    guided_matches,
    harvest,
)
from pipeline.geometry.ransac import TwoViewConfig, estimate_pair
from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex
from pipeline.synthetic.pairs import synthetic_pair

GUIDED = TwoViewConfig(guided=True)


def _deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(so3.angle_between(Ra, Rb)))


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def test_epipolar_distance_is_zero_on_true_correspondences_and_pixels_off_the_line():
    p = synthetic_pair(50, sigma_px=0.0, outlier_frac=0.0, seed=1)
    F = fundamental_from_pose(p.R, p.t, p.K_i, p.K_j)
    d = epipolar_distances(F, p.x_i, p.x_j)
    assert d.shape == (50, 50)
    assert np.abs(np.diag(d)).max() < 1e-6
    line = F @ np.append(p.x_i[0], 1.0)  # moving x_j[0] 3 px along the line's normal puts it 3 px off that line
    moved = p.x_j[:1] + 3.0 * line[:2] / np.linalg.norm(line[:2])
    back = np.append(moved[0], 1.0) @ F  # and some distance off in image i: the symmetric distance is the larger
    d_i = abs(back @ np.append(p.x_i[0], 1.0)) / np.linalg.norm(back[:2])
    assert epipolar_distances(F, p.x_i[:1], moved)[0, 0] == pytest.approx(max(3.0, d_i), rel=1e-6)
    assert 3.0 <= epipolar_distances(F, p.x_i[:1], moved)[0, 0] < 4.0


def test_guided_matches_recover_the_planted_correspondences_that_a_global_ratio_test_loses():
    """Descriptors that are only relatively distinctive: each true partner is nearest, but a decoy elsewhere in the
    image is nearly as close, so the global ratio test drops the match; inside the band the decoy is no candidate."""
    rng = np.random.default_rng(0)
    p = synthetic_pair(300, sigma_px=0.3, outlier_frac=0.0, seed=4)
    q_i = _unit(rng.normal(size=(300, 128)))
    q_j = _unit(q_i + 0.03 * rng.normal(size=q_i.shape))
    decoys = _unit(q_i + 0.031 * rng.normal(size=q_i.shape))  # as close as the partner, at random pixels
    x_dec = rng.uniform([0, 0], [640, 480], (300, 2))
    xj, qj = np.concatenate([p.x_j, x_dec]), np.concatenate([q_j, decoys])
    glob = match_descriptors(q_i, qj)
    assert np.sum(glob[:, 1] == glob[:, 0]) < 0.5 * 300  # the global ratio test loses most of them
    got = guided_matches(p.x_i, q_i, xj, qj, [(p.R, p.t)], p.K_i, p.K_j, band_px=2.0, ratio=0.8, nfa_max=np.inf)[0]
    right = got[:, 1] == got[:, 0]
    assert right.sum() >= 0.9 * 300 and (~right).sum() <= 3


@pytest.fixture(scope="module")
def rendered():
    """Eight views of the rendered low-texture turntable (45° apart), their SIFT and a truth for each match."""
    scene = render_lowtex(LowTexConfig(n_views=8, contrast=8.0), seed=0)
    # plain SIFT (no affine simulation): guided matching is what adds matches here
    feats = [extract_sift_adaptive(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im,
                                   FeatureConfig(affine_below=0.0))[0] for im in scene.images]

    def correct(a: int, b: int, m: np.ndarray) -> np.ndarray:
        """(m,) bool: keypoint a, lifted with view a's depth map and projected into view b, lands within 3 px."""
        return scene.transfer_error_px(a, b, feats[a].xy[m[:, 0]], feats[b].xy[m[:, 1]]) < 3.0

    def pair(a: int, b: int) -> dict:
        R = scene.R[b] @ scene.R[a].T
        return dict(kp_i=feats[a].xy, q_i=root_sift(feats[a].descriptors), kp_j=feats[b].xy,
                    q_j=root_sift(feats[b].descriptors), K_i=scene.K[a], K_j=scene.K[b], R=R,
                    t=scene.t[b] - R @ scene.t[a], matches=match_descriptors(feats[a].descriptors, feats[b].descriptors))

    return pair, correct


def test_the_true_pose_harvests_more_correct_matches_than_sift_and_above_chance(rendered):
    pair, correct = rendered
    for a, b in ((2, 3), (3, 4)):  # a 45° pair SIFT matches well, and one RANSAC rejects (8 inliers of 21)
        d = pair(a, b)
        found, lam, p = harvest(d["kp_i"], d["q_i"], d["kp_j"], d["q_j"], d["R"], d["t"], d["K_i"], d["K_j"], GUIDED)
        ok = correct(a, b, found)
        assert p <= GUIDED.guided_alpha, (a, b, len(found), lam)
        assert ok.sum() > 1.5 * correct(a, b, d["matches"]).sum() and ok.mean() >= 0.5, (a, b, ok.sum(), len(found))


@pytest.mark.parametrize("axis", [(0, 10, 0), (10, 0, 0), (0, 0, 10), (4, -4, 0)])
def test_a_wrong_pose_harvests_no_more_than_chance(rendered, axis):
    pair, _ = rendered
    d = pair(2, 3)
    R_wrong = so3.exp(np.deg2rad(np.array(axis, float))) @ d["R"]
    _, _, p = harvest(d["kp_i"], d["q_i"], d["kp_j"], d["q_j"], R_wrong, d["t"], d["K_i"], d["K_j"], GUIDED)
    assert p > GUIDED.guided_alpha


def test_a_weak_rendered_pair_is_re_estimated_from_its_own_matches_more_precisely(rendered):
    pair, correct = rendered
    d = pair(2, 3)
    plain = estimate_pair(d["kp_i"][d["matches"][:, 0]], d["kp_j"][d["matches"][:, 1]], d["K_i"], d["K_j"])
    g, m, how = estimate_pair_guided(d["kp_i"], d["q_i"], d["kp_j"], d["q_j"], d["matches"], d["K_i"], d["K_j"], GUIDED)
    assert plain.ok and plain.n_inliers < GUIDED.guided_max_inliers  # a weak pair
    assert how.used and g.ok and g.inlier_mask.shape == (len(m),)
    assert g.n_guided == how.n_added == len(m) - len(d["matches"])
    assert correct(2, 3, m[g.inlier_mask]).sum() >= 2 * correct(2, 3, d["matches"][plain.inlier_mask]).sum()
    assert _deg(g.R, d["R"]) < 1.5
    off, m_off, how_off = estimate_pair_guided(d["kp_i"], d["q_i"], d["kp_j"], d["q_j"], d["matches"], d["K_i"],
                                               d["K_j"], TwoViewConfig())
    assert not how_off.used and m_off is d["matches"] and off.n_inliers == plain.n_inliers


@pytest.mark.parametrize("seed", range(4))
def test_a_wrong_seed_on_views_that_do_not_overlap_gives_no_accepted_pair(rendered, seed):
    """Views 0 and 4 face each other across the turntable: random putative matches always hold a 5-inlier RANSAC
    model (a wrong seed); its harvest must not turn it into an accepted pair."""
    pair, _ = rendered
    d = pair(0, 4)
    rng = np.random.default_rng(seed)
    m = np.stack([rng.choice(len(d["kp_i"]), 60, replace=False), rng.choice(len(d["kp_j"]), 60, replace=False)], 1)
    cfg = GUIDED.replace(guided_seed_min_inliers=5, seed=seed)
    g, _, how = estimate_pair_guided(d["kp_i"], d["q_i"], d["kp_j"], d["q_j"], m.astype(np.int32), d["K_i"], d["K_j"],
                                     cfg)
    assert not g.ok and not how.used, (g.n_inliers, how)


def test_matches_of_the_wrong_shape_are_refused(rendered):
    pair, _ = rendered
    d = pair(2, 3)
    with pytest.raises(ValueError, match=r"expected \(m, 2\) integer indices"):
        estimate_pair_guided(d["kp_i"], d["q_i"], d["kp_j"], d["q_j"], d["matches"][:, :1], d["K_i"], d["K_j"],
                             GUIDED)
