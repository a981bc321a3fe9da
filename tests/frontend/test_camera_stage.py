"""The cameras stage: K from a file kept to the last digit, a focal estimated without K, distortion read, caches."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import features, matching
from pipeline.core.errors import InputFileError
from pipeline.frontend.camera_stage import KEYPOINTS, MANIFEST, CamerasConfig, CamerasStage, intrinsics_summary, load_cameras
from pipeline.frontend.distortion import undistort_points
from pipeline.geometry.two_view_stage import TwoViewStage, load_two_view
from pipeline.synthetic.distort import render_distorted_scene
from pipeline.synthetic.render import SceneConfig, render_scene

CFG = SceneConfig(width=480, height=360, focal=420.0, texture_px_per_unit=150.0, arc_deg=70.0)
Q = CamerasConfig(progress=False, workers=1, grid_points=13, refine_points=5, max_points=300, radial="off")


def _front(images: Path, work: Path, K: Path | None = None) -> Path:
    features.main(images, work, K_path=K, progress=False)
    matching.main(work, progress=False)
    return work


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return render_scene(n_views=6, seed=3, out=tmp_path_factory.mktemp("scene"), config=CFG)


@pytest.fixture(scope="module")
def no_K(scene, tmp_path_factory) -> Path:
    """The scene's images alone (no cameras.txt beside them): no K, no EXIF."""
    img = tmp_path_factory.mktemp("noK")
    for n in scene.names:
        shutil.copy(scene.out / n, img / n)
    work = _front(img, tmp_path_factory.mktemp("work_noK"))
    CamerasStage(work, Q).run()
    return work


def test_K_from_a_file_is_kept_to_the_last_digit(scene, tmp_path) -> None:
    work = _front(scene.out, tmp_path / "w")
    rec = CamerasStage(work, Q).run()
    cams = load_cameras(work)
    fs = features.load_features(work)
    assert np.array_equal(cams.K, fs.K) and cams.K_source == fs.K_source and cams.known.all()
    assert cams.keypoints is None and not (work / KEYPOINTS).exists()
    assert rec.summary["n_estimated"] == 0 and not list((work / "cameras_pairs").glob("chunk-*"))
    assert cams.distortion_source == ["none"] * 6 and cams.models[0].model == "PINHOLE"
    TwoViewStage(work).run()
    assert np.array_equal(load_two_view(work).K, fs.K)


def test_focal_estimated_without_K(scene, no_K) -> None:
    cams = load_cameras(no_K)
    assert set(cams.K_source) == {"estimated:profile+rotcons"} and not cams.known.any()
    err = cams.K[:, 0, 0] / CFG.focal - 1
    assert np.all(np.abs(err) < 0.03), err
    np.testing.assert_allclose(cams.K[0, :2, 2], [(CFG.width - 1) / 2, (CFG.height - 1) / 2])
    s = intrinsics_summary(cams)
    assert s["focal"][0]["source"] == "estimated:profile+rotcons" and s["focal"][0]["n_images"] == 6
    assert s["estimates"][0]["focal"]["n_pairs"] >= 5
    TwoViewStage(no_K).run()
    assert np.array_equal(load_two_view(no_K).K, cams.K)


def test_resumes_and_heals(no_K, tmp_path, caplog) -> None:
    w = tmp_path / "w"
    shutil.copytree(no_K, w)
    assert CamerasStage(w, Q).run().reused
    K = load_cameras(w).K
    (w / MANIFEST).write_text("{not json")
    with caplog.at_level(logging.WARNING):
        rec = CamerasStage(w, Q).run()
    assert not rec.reused and "damaged" in caplog.text
    assert np.array_equal(load_cameras(w).K, K)  # recomputed from the per-pair store: the same numbers
    with pytest.raises(InputFileError, match="python -m pipeline.cameras"):
        load_cameras(tmp_path)


@pytest.mark.parametrize("fields, change", [
    (("F", "inliers"), lambda f: f["inliers"].__setitem__(0, 10**6)),        # a match the pair lacks
    (("F", "inliers"), lambda f: f.__setitem__("F", f["F"] * np.nan)),
    (("cost", "R", "t"), lambda f: f["cost"].__setitem__(0, np.nan)),      # the focal profile
    (("cost", "R", "t"), lambda f: f.__setitem__("R", f["R"] * 2.0)),      # not rotations
    (("cost", "R", "t"), lambda f: f.__setitem__("sigma2", np.array(-1.0))),
    (("cost", "R", "t"), lambda f: f.pop("t")),
], ids=["F-inlier-out-of-range", "F-nan", "profile-cost-nan", "profile-R", "profile-sigma2", "profile-t-missing"])
def test_a_stored_pair_that_reads_but_is_wrong_is_recomputed(no_K, tmp_path, fields, change, damage_item,
                                                           caplog) -> None:
    # The stage's output is lost and one stored pair result (its F, or its focal profile) reads well but is wrong:
    # it is recomputed, not reused, and the focal comes out as the first run's, to the last digit.
    from pipeline.frontend.camera_stage import STORE

    w = tmp_path / "w"
    shutil.copytree(no_K, w)
    before = load_cameras(w).K
    damage_item(w / STORE, change, which=lambda item: set(fields) <= set(item))
    (w / MANIFEST).unlink()
    with caplog.at_level(logging.WARNING):
        rec = CamerasStage(w, Q).run()
    warned = [r.getMessage() for r in caplog.records if "results in" in r.getMessage()]
    assert len(warned) == 1 and "1 pairs'" in warned[0] and "recomputed" in warned[0], warned
    assert not rec.reused
    assert np.array_equal(load_cameras(w).K, before)


def test_distortion_from_a_COLMAP_file(tmp_path) -> None:
    d = render_distorted_scene(3, 1, tmp_path / "img", -0.1, config=SceneConfig(width=320, height=240, focal=280.0,
                                                                                 texture_px_per_unit=150.0))
    (tmp_path / "img" / "cameras.txt").rename(tmp_path / "truth.txt")
    work = _front(d.out, tmp_path / "w", K=d.out / "lens.txt")
    CamerasStage(work, Q).run()
    cams = load_cameras(work)
    assert cams.known.all() and cams.models[0].model == "SIMPLE_RADIAL"
    assert cams.distortion_source == [f"file:{d.out / 'lens.txt'}"] * 3
    fs = features.load_features(work)
    np.testing.assert_allclose(cams.keypoints[1], undistort_points(cams.models[1], fs.keypoints[1]))
    np.testing.assert_allclose(cams.K[0], d.K[0], atol=1e-9)
    manifest = json.loads((work / MANIFEST).read_text())
    assert manifest["undistorted_keypoints"] and manifest["models"][0]["params"][3] == -0.1


def test_command_line(no_K, tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "pipeline.cameras", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--focal-method" in r.stdout and "--radial" in r.stdout
    r = subprocess.run([sys.executable, "-m", "pipeline.cameras", "--work", str(tmp_path / "nowhere")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "error:" in r.stderr


def test_exif_is_a_prior_not_the_truth(scene, tmp_path) -> None:
    """JPEGs whose EXIF says a focal ~9% too long: the view graph's estimate wins, and says it had the prior."""
    from PIL import Image

    img = tmp_path / "img"
    img.mkdir()
    for n in scene.names:
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0xA405] = 33  # FocalLengthIn35mmFilm
        Image.open(scene.out / n).convert("RGB").save(img / n.replace(".png", ".jpg"), exif=exif, quality=95)
    work = _front(img, tmp_path / "w")
    fs = features.load_features(work)
    assert set(fs.K_source) == {"exif"} and fs.K[0, 0, 0] > 1.05 * CFG.focal
    # the principal point at the image centre in OUR convention (pixel centres at integers): the renderer's
    # ((w − 1)/2, (h − 1)/2); w/2 would put every EXIF or default camera half a pixel off
    centre = [(CFG.width - 1) / 2, (CFG.height - 1) / 2]
    np.testing.assert_allclose(fs.K[:, :2, 2], np.broadcast_to(centre, (len(scene.names), 2)), atol=1e-12)
    CamerasStage(work, Q).run()
    cams = load_cameras(work)
    np.testing.assert_allclose(cams.K[:, :2, 2], np.broadcast_to(centre, (len(scene.names), 2)), atol=1e-12)
    assert len(set(cams.K_source)) == 1 and cams.K_source[0].startswith("estimated:profile+rotcons (exif ")
    assert cams.K_source[0].endswith(" px prior)") and not cams.known.any()
    assert np.all(np.abs(cams.K[:, 0, 0] / CFG.focal - 1) < 0.03), cams.K[:, 0, 0]
