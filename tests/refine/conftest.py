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


def deep_problem(seed: int, n_images: int = 8, n_points: int = 800, sigma_px: float = 0.5,
                 pp_shift: float = 0.03, centred: tuple[int, ...] = ()) -> tuple[dict, np.ndarray, np.ndarray]:
    """A wide-angle view of a deep scene, each image its own camera, as internet photos cropped off their centre.

    Cameras on a 60° arc of radius 6 look at a 6 × 4 × 6 box of points (depths 3–9: strong perspective, which a
    single image's principal point can be told from); focal lengths 600–614 px on 1024 × 768 images; each true
    principal point up to ``pp_shift`` of the width off the image centre in x and y (at it for the images
    ``centred``). The keyword inputs of
    ``refine_rotations`` start from the image centres and focal lengths 3% long (as a cameras stage would).

    Returns:
        the inputs (without ``R_init``), the (N, 3, 3) true rotations and the (N, 3, 3) true intrinsics.
    """
    rng = np.random.default_rng(seed)
    w, h = 1024, 768
    X = rng.uniform([-3, -2, -3], [3, 2, 3], size=(n_points, 3))
    R, C, K_true, kps, idx = [], [], [], [], []
    for k, a in enumerate(np.radians(np.linspace(-30, 30, n_images))):
        c = 6.0 * np.array([np.sin(a), 0.0, -np.cos(a)]) + rng.normal(scale=0.2, size=3)
        z = -c / np.linalg.norm(c)  # the optical axis, towards the box's centre
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        Rk = so3.exp(np.radians(rng.normal(scale=2.0, size=3))) @ np.stack([x, np.cross(z, x), z])
        f = 600.0 + 2.0 * k
        shift = pp_shift * w * rng.uniform(-1, 1, size=2) * (k not in centred)
        Kk = np.array([[f, 0, (w - 1) / 2 + shift[0]], [0, f, (h - 1) / 2 + shift[1]], [0, 0, 1]])
        p = (X - c) @ Rk.T @ Kk.T
        uv = p[:, :2] / p[:, 2:]
        seen = (p[:, 2] > 0.5) & np.all((uv >= 0) & (uv <= [w - 1, h - 1]), axis=1)
        kps.append(uv[seen] + rng.normal(scale=sigma_px, size=(int(seen.sum()), 2)))
        at = np.full(n_points, -1)
        at[seen] = np.arange(int(seen.sum()))
        idx.append(at)
        R.append(Rk)
        C.append(c)
        K_true.append(Kk)
    R, C, K_true = np.array(R), np.array(C), np.array(K_true)
    pairs = [(i, j) for i in range(n_images) for j in range(i + 1, n_images)]
    m = [np.stack([idx[i][(idx[i] >= 0) & (idx[j] >= 0)], idx[j][(idx[i] >= 0) & (idx[j] >= 0)]], axis=1)
         for i, j in pairs]
    edges = np.array(pairs)
    i, j = edges.T
    t = np.einsum("nij,nj->ni", R[j], C[i] - C[j])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    K0 = K_true.copy()
    K0[:, 0, 2], K0[:, 1, 2] = (w - 1) / 2, (h - 1) / 2
    K0[:, 0, 0] *= 1.03
    K0[:, 1, 1] *= 1.03
    return dict(names=[f"img{k:03d}.jpg" for k in range(n_images)], K=K0, sizes=np.tile([w, h], (n_images, 1)),
                keypoints=kps, edges=edges, match_offsets=np.concatenate([[0], np.cumsum([len(x) for x in m])]),
                matches=np.concatenate(m).astype(np.int64), cam2_from_cam1=so3.relative(R, edges),
                t_cam2_from_cam1=t), R, K_true
