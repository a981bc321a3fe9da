"""Lens distortion: camera files read (COLMAP, OpenCV), keypoints undistorted, one radial parameter estimated."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.frontend import distortion as D
from pipeline.frontend import radial as rk
from pipeline.frontend.camera_estimate import CamerasConfig, estimate_radial
from pipeline.frontend.intrinsics import camera_models_for_names, read_intrinsics, resolve_intrinsics


def test_radial_undistort_matches_pycolmap_and_its_jacobian() -> None:
    c, s, kappa = np.array([511.5, 383.5]), 1024.0, -0.2
    cam = D.simple_radial(s, c, kappa, 1024, 768)  # f = s: κ is COLMAP's k1
    x = np.random.default_rng(0).uniform([0, 0], [1024, 768], (500, 2))
    xu, J = D.radial_undistort(x, c, s, kappa)
    np.testing.assert_allclose(xu, D.undistort_points(cam, x), atol=1e-6)
    np.testing.assert_allclose(D.distort_points(cam, xu), x, atol=1e-6)
    e = 1e-5
    for a in range(2):
        d = np.zeros(2)
        d[a] = e
        fd = (D.radial_undistort(x + d, c, s, kappa)[0] - D.radial_undistort(x - d, c, s, kappa)[0]) / (2 * e)
        np.testing.assert_allclose(J[:, :, a], fd, atol=1e-6)


def test_opencv_model_agrees_with_cv2() -> None:
    import cv2

    K = np.array([[700.0, 0, 320.0], [0, 710.0, 240.0], [0, 0, 1]])
    for dist in ([-0.2, 0.05, 0.001, -0.002], [-0.2, 0.05, 0.001, -0.002, 0.01]):
        cam = D.opencv_model(K, dist, 640, 480)
        assert cam.model == ("OPENCV" if len(dist) == 4 else "FULL_OPENCV") and cam.has_distortion
        np.testing.assert_allclose(D.pinhole_K(cam), K)
        x = np.random.default_rng(1).uniform([0, 0], [640, 480], (200, 2))
        ref = cv2.undistortPoints(x.reshape(-1, 1, 2), K, np.array(dist), None, K,
                                  criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
        np.testing.assert_allclose(D.undistort_points(cam, x), ref, atol=1e-3)
    with pytest.raises(InputFileError, match="6 distortion coefficients"):
        D.opencv_model(K, [0.1] * 6, 640, 480)


def _write_colmap_text(folder: Path, two_cameras: bool) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]", "1 SIMPLE_RADIAL 640 480 500 320.5 240.5 -0.1"]
    if two_cameras:
        lines.append("2 OPENCV 320 240 300 301 160 120 -0.05 0.01 0 0")
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    if two_cameras:
        (folder / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 2 b.png\n\n")


def test_colmap_text_and_binary_cameras(tmp_path: Path) -> None:
    _write_colmap_text(tmp_path / "one", False)
    m = D.read_camera_models(tmp_path / "one" / "cameras.txt")
    assert list(m) == ["*"] and m["*"].model == "SIMPLE_RADIAL" and m["*"].params == (500.0, 320.5, 240.5, -0.1)
    np.testing.assert_allclose(read_intrinsics(tmp_path / "one" / "cameras.txt"),
                               [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    _write_colmap_text(tmp_path / "two", True)
    m2 = D.read_camera_models(tmp_path / "two")
    assert m2["a.png"].model == "SIMPLE_RADIAL" and m2["b.png"].model == "OPENCV"
    models = camera_models_for_names(tmp_path / "two", ["b.png", "a.png", "c.png"])
    assert models[0].model == "OPENCV" and models[1].model == "SIMPLE_RADIAL" and models[2] is None
    # binary: cameras.bin written by hand in COLMAP's layout
    blob = struct.pack("<Q", 1) + struct.pack("<iiQQ", 7, 2, 640, 480) + struct.pack("<4d", 500, 320.5, 240.5, -0.1)
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "cameras.bin").write_bytes(blob)
    assert D.read_camera_models(tmp_path / "bin")["*"] == m["*"]
    (tmp_path / "bin" / "cameras.bin").write_bytes(blob[:-8])
    with pytest.raises(InputFileError, match="truncated"):
        D.read_camera_models(tmp_path / "bin")


def test_colmap_model_written_by_pycolmap(tmp_path: Path) -> None:
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera(pycolmap.Camera(model="RADIAL", width=400, height=300, params=[350, 200, 150, -0.1, 0.02],
                                   camera_id=1))
    rec.write(str(tmp_path))
    m = D.read_camera_models(tmp_path)
    assert m["*"].model == "RADIAL" and m["*"].params == (350.0, 200.0, 150.0, -0.1, 0.02)


def test_colmap_model_of_several_cameras_written_by_pycolmap(tmp_path: Path) -> None:
    """Per-image cameras (as the refinement writes OUT/sparse for images without a K): images.bin says which
    image has which camera; its records are packed (a native-aligned read of ``i7d`` slips 4 bytes per image)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cams = [pycolmap.Camera(model="SIMPLE_RADIAL", width=400, height=300, params=[350, 200, 150, -0.05], camera_id=1),
            pycolmap.Camera(model="SIMPLE_PINHOLE", width=300, height=400, params=[410, 150, 200], camera_id=2)]
    for cam in cams:
        rec.add_camera_with_trivial_rig(cam)
    for k, (name, cid) in enumerate([("a.png", 2), ("b.png", 1), ("c.png", 2)]):
        im = pycolmap.Image(name=name, camera_id=cid, image_id=k + 1,
                            points2D=pycolmap.Point2DList([pycolmap.Point2D(np.array([10.0 * k, 5.0]))] * (k + 1)))
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d())
    rec.write(str(tmp_path))
    m = D.read_camera_models(tmp_path)
    assert sorted(m) == ["a.png", "b.png", "c.png"]
    assert m["a.png"] == m["c.png"] and m["a.png"].model == "SIMPLE_PINHOLE" and m["a.png"].params == (410.0, 150.0, 200.0)
    assert m["b.png"].model == "SIMPLE_RADIAL" and m["b.png"].params == (350.0, 200.0, 150.0, -0.05)


def test_opencv_files(tmp_path: Path) -> None:
    import cv2

    K = np.array([[700.0, 0, 320.0], [0, 700.0, 240.0], [0, 0, 1]])
    (tmp_path / "k_dist.txt").write_text("700 0 320\n0 700 240\n0 0 1\n-0.2 0.05 0 0\n")
    assert D.is_camera_model_file(tmp_path / "k_dist.txt")
    m = D.read_camera_models(tmp_path / "k_dist.txt")["*"]
    assert m.model == "OPENCV" and m.params[4:] == (-0.2, 0.05, 0.0, 0.0)
    np.testing.assert_allclose(read_intrinsics(tmp_path / "k_dist.txt"), K)
    fs = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([[-0.2, 0.05, 0.0, 0.0, 0.01]]))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    y = D.read_camera_models(tmp_path / "calib.yaml")["*"]
    assert y.model == "FULL_OPENCV" and (y.width, y.height) == (640, 480) and y.params[8] == 0.01
    (tmp_path / "K.txt").write_text("700 0 320\n0 700 240\n0 0 1\n")  # a plain K: no camera model
    assert not D.is_camera_model_file(tmp_path / "K.txt")
    (tmp_path / "bad.txt").write_text("700 0 320\n0 700 240\n0 0 1\n0.1 0.2 0.3\n")
    with pytest.raises(InputFileError, match="3 distortion coefficients"):
        read_intrinsics(tmp_path / "bad.txt")


def test_bad_colmap_files(tmp_path: Path) -> None:
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 640 480 500 320 240\n")
    with pytest.raises(InputFileError, match="SIMPLE_RADIAL takes 4 parameters, got 3"):
        D.read_camera_models(tmp_path / "cameras.txt")
    (tmp_path / "cameras.txt").write_text("1 WEIRD 640 480 500 320 240\n")
    with pytest.raises(InputFileError, match="camera model 'WEIRD' is not supported"):
        D.read_camera_models(tmp_path / "cameras.txt")
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 500 -1 320 240\n2 PINHOLE 640 480 500 500 320 240\n")
    with pytest.raises(InputFileError, match="positive focal"):
        D.read_camera_models(tmp_path / "cameras.txt")
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE 640 480 500 500 320 240\n")
    with pytest.raises(InputFileError, match="no images.bin/.txt beside it"):
        D.read_camera_models(tmp_path / "cameras.txt")


def test_resolve_intrinsics_reads_the_pinhole_part(tmp_path: Path) -> None:
    _write_colmap_text(tmp_path / "m", True)
    K, src = resolve_intrinsics(tmp_path, ["a.png", "b.png"], np.array([[640, 480], [320, 240]]), tmp_path / "m")
    np.testing.assert_allclose(K[1], [[300, 0, 159.5], [0, 301, 119.5], [0, 0, 1]])
    assert src == [f"file:{tmp_path / 'm'}"] * 2


def _distorted_pairs(kappa: float | np.ndarray, n_pairs: int = 6, seed: int = 0):
    """Pairs of a SIMPLE_RADIAL camera (κ at scale 1024); ``kappa`` (n_pairs,) gives each pair its own lens."""
    rng = np.random.default_rng(seed)
    w, h, f, s = 1024, 768, 800.0, 1024.0
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    kappas = np.broadcast_to(np.asarray(kappa, float), (n_pairs,))
    K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1]])
    x1s, x2s = [], []
    for p in range(n_pairs):
        cam = D.simple_radial(s, c, float(kappas[p]), w, h)
        R = so3.exp(rng.normal(0, 0.15, 3))
        t = rng.normal(size=3)
        X = np.column_stack([rng.uniform(-4, 4, 400), rng.uniform(-3, 3, 400), rng.uniform(6, 14, 400)])
        p1 = X @ K.T
        p1 = p1[:, :2] / p1[:, 2:]
        p2 = (X @ R.T + t) @ K.T
        p2 = p2[:, :2] / p2[:, 2:]
        ok = (p1 > 0).all(1) & (p1 < [w, h]).all(1) & (p2 > 0).all(1) & (p2 < [w, h]).all(1)
        x1s.append(D.distort_points(cam, p1[ok]) + 0.5 * rng.standard_normal((ok.sum(), 2)))
        x2s.append(D.distort_points(cam, p2[ok]) + 0.5 * rng.standard_normal((ok.sum(), 2)))
    return x1s, x2s, (w, h)


def test_radial_estimated_without_the_focal() -> None:
    cfg = CamerasConfig(workers=1, radial_grid_points=17, radial_refine=(0.05, 11), max_points=300)
    x1s, x2s, size = _distorted_pairs(-0.09)
    est = estimate_radial(x1s, x2s, size, np.ones(len(x1s)), cfg)
    assert est.significant and abs(est.kappa + 0.09) < 0.01, est
    assert est.delta_chi2 > cfg.radial_chi2
    none = estimate_radial(*_distorted_pairs(0.0, seed=1)[:2], size, np.ones(6), cfg)
    assert not none.significant and none.kappa == 0.0
    assert rk.kappa_to_k1(-0.09, 1024.0, 512.0) == pytest.approx(-0.0225)


def test_a_radial_term_the_pairs_disagree_on_is_not_kept() -> None:
    """Each pair has its own lens: κ = 0.02 + 0.03·z over 12 pairs (z standardized), a mean about two
    standard errors of the pairs' spread from 0. The plain likelihood-ratio drop calls it significant, the
    quasi-likelihood test does not; κ = −0.12 + 0.03·z it still keeps."""
    cfg = CamerasConfig(workers=1, radial_grid_points=17, radial_refine=(0.05, 11), max_points=300)
    z = np.random.default_rng(7).standard_normal(12)
    z = (z - z.mean()) / z.std()
    x1s, x2s, size = _distorted_pairs(0.02 + 0.03 * z, n_pairs=12, seed=2)
    est = estimate_radial(x1s, x2s, size, np.ones(12), cfg)
    assert est.delta_chi2 > cfg.radial_chi2, est  # what the plain χ²₁ test would have kept
    assert est.dispersion > 2.0 and not est.significant and est.kappa == 0.0, est
    x1s, x2s, size = _distorted_pairs(-0.12 + 0.03 * z, n_pairs=12, seed=2)
    est = estimate_radial(x1s, x2s, size, np.ones(12), cfg)
    assert est.significant and abs(est.kappa + 0.12) < 0.03, est


def test_kappa_test_dispersion_is_one_under_the_model() -> None:
    """Pairs that share one lens and whose noise is their σ: φ ≈ 1 (Pearson χ²_{M−1}/(M−1), sd ≈ 0.3 at M = 12)."""
    cfg = CamerasConfig(workers=1, radial_grid_points=17, radial_refine=(0.05, 11), max_points=300)
    x1s, x2s, size = _distorted_pairs(-0.09, n_pairs=12, seed=3)
    est = estimate_radial(x1s, x2s, size, np.ones(12), cfg)
    assert 0.3 < est.dispersion < 2.0 and est.significant, est
