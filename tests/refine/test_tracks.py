"""pipeline.refine.tracks, the gauge projector and the binary starting model, on hand-made inputs."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.refine.covariance import gauge_fixed_rotation_covariance, rotation_gauge_projection
from pipeline.refine.tracks import Tracks, build_tracks, filter_edges, long_tracks, restrict_tracks, \
    select_matches, select_tracks, subset_tracks


def _as_sets(tr: Tracks) -> list[tuple[tuple[int, int], ...]]:
    return sorted(tuple(zip(tr.image[s:e].tolist(), tr.keypoint[s:e].tolist()))
                  for s, e in zip(tr.offsets[:-1], tr.offsets[1:]))


def test_tracks_components_consistency_and_min_views():
    # track A: (0,0)-(1,0)-(2,0); B: (0,1)-(1,1), two views only; C: holds keypoints 2 and 3 of image 0,
    # 100 px apart -> inconsistent; D: (1,4)-(2,4)-(3,4)-(3,5), keypoints 4 and 5 of image 3 close -> one kept
    kp = [np.zeros((6, 2)) for _ in range(4)]
    kp[0][3] = [100, 100]
    kp[3][5] = [1, 1]
    edges = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [1, 3]])
    pairs = [[[0, 0], [1, 1], [2, 2]], [[0, 0], [2, 2], [4, 4]], [[3, 2]], [[4, 4]], [[4, 5]]]
    matches = np.concatenate([np.array(p) for p in pairs])
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in pairs])])
    tr = build_tracks(kp, edges, offsets, matches, min_views=3, consistency_px=10)
    assert _as_sets(tr) == [((0, 0), (1, 0), (2, 0)), ((1, 4), (2, 4), (3, 4))]
    assert tr.n_inconsistent == 1 and tr.n_short == 1 and tr.n_components == 4
    assert tr.observations_per_image(4).tolist() == [1, 2, 2, 1]


def test_tracks_of_no_match_and_bad_index():
    kp = [np.zeros((3, 2)), np.zeros((3, 2))]
    assert build_tracks(kp, np.array([[0, 1]]), np.array([0, 0]), np.zeros((0, 2), int)).n_tracks == 0
    with pytest.raises(ValueError, match="outside its image's keypoints"):
        build_tracks(kp, np.array([[0, 1]]), np.array([0, 1]), np.array([[0, 7]]))


def test_select_subset_and_restrict():
    # image 0 sees tracks of length 5, 4, 3; a budget of 1 keeps the length-5 track for image 0, and
    # the length-3 track survives through images 5 and 9, which no other track sees
    tr = Tracks(offsets=np.array([0, 5, 9, 12]), image=np.array([0, 1, 2, 3, 4, 0, 1, 2, 3, 0, 5, 9]),
                keypoint=np.arange(12))
    keep = select_tracks(tr, 10, per_image=1)
    assert keep.tolist() == [True, False, True]
    sub = subset_tracks(tr, keep)
    assert sub.offsets.tolist() == [0, 5, 8] and sub.image.tolist() == [0, 1, 2, 3, 4, 0, 5, 9]
    active = np.ones(10, bool)
    active[[5, 9]] = False  # the third track loses two of its three views
    r = restrict_tracks(tr, active, min_views=3)
    assert r.offsets.tolist() == [0, 5, 9] and 5 not in r.image and 9 not in r.image


def test_long_tracks_keep_the_short_tracks_of_an_image_that_has_too_few_long_ones():
    # images 0-2 share two 3-view tracks; image 3 (a pan: every point it sees is seen from one centre) is only in
    # 2-view tracks, with image 2 (twice) and with image 0; images 0 and 1 also share a 2-view track
    tr = Tracks(offsets=np.array([0, 3, 6, 8, 10, 12, 14]),
                image=np.array([0, 1, 2, 0, 1, 2, 2, 3, 2, 3, 0, 3, 0, 1]), keypoint=np.arange(14), n_short=4)
    out, starved = long_tracks(tr, 4, min_views=3, min_observations=2)
    assert starved.tolist() == [False, False, False, True]
    # the 3-view tracks, and the three 2-view tracks of image 3; not the 2-view track of images 0 and 1
    assert out.offsets.tolist() == [0, 3, 6, 8, 10, 12] and out.image[6:].tolist() == [2, 3, 2, 3, 0, 3]
    assert out.n_short == 5 and out.observations_per_image(4).tolist() == [3, 2, 4, 3]
    # no starved image: exactly the tracks of at least min_views images
    no_pan = subset_tracks(tr, np.array([True, True, False, False, False, True]))
    out, starved = long_tracks(no_pan, 3, min_views=3, min_observations=2)
    assert not starved.any() and out.offsets.tolist() == [0, 3, 6]
    assert long_tracks(subset_tracks(tr, np.zeros(6, bool)), 4, 3, 2)[0].n_tracks == 0


def test_filter_edges_and_select_matches():
    rng = np.random.default_rng(0)
    R = so3.random_rotations(5, rng)
    edges = np.array([[0, 1], [1, 2], [2, 4], [0, 3]])
    R_rel = so3.relative(R, edges)
    R_rel[2] = so3.exp(np.radians([0, 0, 7.0])) @ R_rel[2]
    keep, res = filter_edges(edges, R_rel, R, 5.0)
    assert keep.tolist() == [True, True, False, True] and abs(res[2] - 7.0) < 1e-9
    R_nan = R.copy()
    R_nan[3] = np.nan  # a camera without a rotation: its pairs are not used, whatever the threshold
    keep, res = filter_edges(edges, R_rel, R_nan, None)
    assert keep.tolist() == [True, True, True, False] and np.isnan(res[3])
    off, m = select_matches(np.array([0, 2, 3, 6, 7]), np.arange(14).reshape(7, 2), np.array([True, False, True, False]))
    assert off.tolist() == [0, 2, 5] and m[:, 0].tolist() == [0, 2, 6, 8, 10]


def test_gauge_projection_removes_a_global_rotation():
    rng = np.random.default_rng(1)
    R = so3.random_rotations(5, rng)
    P = rotation_gauge_projection(R)
    W = so3.exp(1e-6 * rng.normal(size=3))
    d = so3.log(R @ W.T @ np.swapaxes(R, 1, 2)).reshape(-1)  # the left perturbations of R_i Wᵀ
    assert np.linalg.norm(P @ d) < 1e-6 * np.linalg.norm(d)
    np.testing.assert_allclose(P @ P, P, atol=1e-12)
    np.testing.assert_allclose(P, P.T, atol=1e-12)
    blocks = gauge_fixed_rotation_covariance(np.eye(15), R, 2.0)
    assert blocks.shape == (5, 3, 3)
    np.testing.assert_allclose(blocks, 2.0 * P.reshape(5, 3, 5, 3)[np.arange(5), :, np.arange(5), :], atol=1e-12)
    # a joint covariance that is not a multiple of the identity: the projection on both sides, block by block
    X = rng.normal(size=(15, 15))
    S = X @ X.T + np.eye(15)
    want = np.empty((5, 3, 3))
    for k in range(5):
        Pk = P[3 * k:3 * k + 3]  # camera k's rows of P
        want[k] = 0.5 * Pk @ S @ Pk.T
    np.testing.assert_allclose(gauge_fixed_rotation_covariance(S, R, 0.5), want, atol=1e-10)
    joint = np.eye(15)
    joint[4, 4] = np.nan  # one camera the problem does not determine: no covariance, not NaN in every camera
    with pytest.raises(ValueError, match="not finite"):
        gauge_fixed_rotation_covariance(joint, R, 2.0)
    with pytest.raises(ValueError, match="not finite"):
        gauge_fixed_rotation_covariance(np.eye(15), R, np.inf)


def test_binary_starting_model_round_trip(tmp_path):
    """The numpy-written model reads back in pycolmap with our rotations, shifted keypoints and tracks."""
    import pycolmap

    from pipeline.refine.model import starting_reconstruction

    rng = np.random.default_rng(2)
    R = so3.random_rotations(3, rng)
    K = np.broadcast_to(np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]]), (3, 3, 3)).copy()
    K[2, 0, 0] = 600.0  # its own camera
    kp = [rng.uniform(0, 600, (n, 2)) for n in (7, 5, 6)]
    tr = Tracks(np.array([0, 3, 5]), np.array([0, 1, 2, 0, 2]), np.array([6, 4, 0, 2, 5]))
    rec = starting_reconstruction(pycolmap, ["a", "b", "c"], K, np.array([[640, 480]] * 3), np.ones(3, bool), kp,
                                  np.arange(3), R, tr, scratch=tmp_path)
    assert not list(tmp_path.iterdir())  # the temporary model is gone
    assert rec.num_reg_images() == 3 and rec.num_points3D() == 2 and rec.num_cameras() == 2
    for k in range(3):
        img = rec.image(k + 1)
        np.testing.assert_allclose(img.cam_from_world().rotation.matrix(), R[k], atol=1e-12)
        np.testing.assert_allclose(np.array([p.xy for p in img.points2D]), kp[k] + 0.5)
        np.testing.assert_allclose(rec.camera(img.camera_id).params[2:], [320.0, 240.0])
    tracks = sorted(sorted((e.image_id, e.point2D_idx) for e in p.track.elements) for p in rec.points3D.values())
    assert tracks == [[(1, 2), (3, 5)], [(1, 6), (2, 4), (3, 0)]]
    assert rec.image(1).points2D[6].point3D_id != rec.image(1).points2D[2].point3D_id
