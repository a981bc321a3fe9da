"""Fixtures of the refine tests: inputs of ``refine_rotations`` from pycolmap's synthetic datasets (exact truth)."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pipeline.core import so3  # noqa: E402
from pipeline.reference.database import COLMAP_PIXEL_OFFSET  # noqa: E402


def synthetic_problem(seed: int, n_images: int = 8, n_points: int = 400, sigma_px: float = 0.5) -> tuple[dict, np.ndarray]:
    """``refine_rotations`` keyword inputs (without ``R_init``) and the (N, 3, 3) true rotations.

    pycolmap's keypoints and principal points are in COLMAP's pixel convention (+0.5); they are
    shifted into ours here and back by the refinement.
    """
    import pycolmap as pc

    pc.logging.minloglevel = 2
    pc.set_random_seed(seed)
    o = pc.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig = n_images, 1, 1
    o.num_points3D = n_points
    o.camera_model_id = pc.CameraModelId.PINHOLE
    o.camera_params = [1280.0, 1280.0, 512.0, 384.0]
    o.camera_has_prior_focal_length = True
    o.num_points2D_without_point3D = 20
    o.sensor_from_rig_translation_stddev = 0.0
    o.sensor_from_rig_rotation_stddev = 0.0
    db = pc.Database.open(":memory:")
    rec = pc.synthesize_dataset(o, db)
    if sigma_px > 0:
        noise = pc.SyntheticNoiseOptions()
        noise.point2D_stddev = sigma_px
        pc.synthesize_noise(noise, rec, db)
    ids = sorted(rec.reg_image_ids())
    names, K, sizes, kps, R, C = [], [], [], [], [], []
    for i in ids:
        img = rec.image(i)
        cam = rec.camera(img.camera_id)
        Km = cam.calibration_matrix().copy()
        Km[:2, 2] -= COLMAP_PIXEL_OFFSET
        names.append(img.name)
        K.append(Km)
        sizes.append([cam.width, cam.height])
        kps.append(np.asarray(db.read_keypoints(i), float)[:, :2] - COLMAP_PIXEL_OFFSET)
        R.append(img.cam_from_world().rotation.matrix())
        C.append(img.projection_center())
    R, C = np.array(R), np.array(C)
    pos = {i: k for k, i in enumerate(ids)}
    pairs = []
    pair_ids, geoms = db.read_two_view_geometries()
    for pid, g in zip(pair_ids, geoms):
        a, b = pc.pair_id_to_image_pair(pid)
        m = np.asarray(g.inlier_matches, np.int64)
        i, j = pos[a], pos[b]
        if len(m) >= 15:
            pairs.append((min(i, j), max(i, j), m if i < j else m[:, ::-1]))
    db.close()
    pairs.sort(key=lambda p: (p[0], p[1]))
    edges = np.array([[i, j] for i, j, _ in pairs])
    matches = np.concatenate([m for _, _, m in pairs])
    offsets = np.concatenate([[0], np.cumsum([len(m) for _, _, m in pairs])])
    i, j = edges.T
    t = np.einsum("nij,nj->ni", R[j], C[i] - C[j])  # x_j = R_ij x_i + t_ij, t_ij = R_j (C_i − C_j)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return dict(names=names, K=np.array(K), sizes=np.array(sizes), keypoints=kps, edges=edges, match_offsets=offsets,
                matches=matches, cam2_from_cam1=so3.relative(R, edges), t_cam2_from_cam1=t), R


def perturbed(R: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    """``exp([w]×) R`` with w of RMS ``deg`` degrees per camera."""
    return so3.exp(np.radians(deg) * rng.normal(size=(len(R), 3)) / np.sqrt(3)) @ R


def aligned_residuals(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """(N, 3) left residuals ``log(R_est (R_true G)ᵀ)`` after the chordal ℓ2 alignment G."""
    G = so3.project_to_so3(np.einsum("nji,njk->ik", R_true, R_est))
    return so3.log(R_est @ np.swapaxes(R_true @ G, 1, 2))


@pytest.fixture(scope="session")
def problem0() -> tuple[dict, np.ndarray]:
    return synthetic_problem(0)


@pytest.fixture
def points_removed_after_positioning(monkeypatch):
    """Every 3D point deleted right after global positioning: bundle adjustment has nothing to run on."""
    from pipeline.refine import mapper

    original = mapper.global_positioning

    def drop_all_points(pc, rec, pose_graph, cfg):
        ok = original(pc, rec, pose_graph, cfg)
        for pid in list(rec.point3D_ids()):
            rec.delete_point3D(pid)
        return ok

    monkeypatch.setattr(mapper, "global_positioning", drop_all_points)
