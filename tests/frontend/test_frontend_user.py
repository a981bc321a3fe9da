"""The front end tried as a new user would, through the command lines.

Each case gives a clear one-line message (exit code 2), or a warning and a correct result.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.core import so3
from pipeline.synthetic.render import SceneConfig, render_scene
from pipeline.two_view import load_two_view

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)


def _run(module: str, *args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True, timeout=300)


def _one_line_error(r: subprocess.CompletedProcess, *needles: str) -> None:
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return render_scene(n_views=3, seed=21, out=tmp_path_factory.mktemp("scene"), config=CFG)


def _copy_images(scene, dst: Path, names=None) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for n in names or scene.names:
        shutil.copy(scene.out / n, dst / n)
    return dst


def _pair_errors_deg(scene, d) -> np.ndarray:
    """Each pair's relative rotation of the two-view result ``d`` against the scene's truth (degrees)."""
    R_true = np.einsum("mij,mkj->mik", scene.R[d.vg.edges[:, 1]], scene.R[d.vg.edges[:, 0]])
    return np.degrees(so3.angle_between(d.vg.R_rel, R_true))


def test_empty_folder(tmp_path):
    (tmp_path / "img").mkdir()
    _one_line_error(_run("pipeline.features", "--images", tmp_path / "img", "--work", tmp_path / "w"), "0 image file(s)", "at least 2")


def test_missing_folder(tmp_path):
    _one_line_error(_run("pipeline.features", "--images", tmp_path / "nope", "--work", tmp_path / "w"), "does not exist")


def test_one_image(scene, tmp_path):
    img = _copy_images(scene, tmp_path / "img", scene.names[:1])
    _one_line_error(_run("pipeline.features", "--images", img, "--work", tmp_path / "w"), "1 image file(s)", "at least 2")


def test_matching_before_features(tmp_path):
    _one_line_error(_run("pipeline.matching", "--work", tmp_path / "w"), "pipeline.features")


@pytest.mark.slow
def test_non_image_and_truncated_jpeg_are_skipped_with_warning(scene, tmp_path):
    img = _copy_images(scene, tmp_path / "img")
    (img / "notes.txt").write_text("not an image")
    (img / "fake.jpg").write_text("this is text, not a JPEG")
    # a truncated JPEG: the first half of a real one
    bgr = cv2.cvtColor(scene.images[0], cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    (img / "cut.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    w = tmp_path / "w"
    r = _run("pipeline.features", "--images", img, "--work", w, "--K", scene.out / "cameras.txt")
    assert r.returncode == 0, r.stderr
    assert "fake.jpg" in r.stderr and "cut.jpg" in r.stderr and "truncated" in r.stderr
    assert "WARNING" in r.stderr
    for mod in ("pipeline.matching", "pipeline.two_view"):
        r = _run(mod, "--work", w, "-q")
        assert r.returncode == 0, r.stderr
    d = load_two_view(w)
    assert d.vg.names == scene.names and d.vg.n_edges == 3


def test_only_unreadable_images(tmp_path):
    img = tmp_path / "img"
    img.mkdir()
    (img / "a.jpg").write_text("x")
    (img / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 20)
    _one_line_error(_run("pipeline.features", "--images", img, "--work", tmp_path / "w"), "only 0 of 2 images", "a.jpg")


def test_images_in_subfolders_are_listed_by_their_relative_paths(tmp_path):
    """As COLMAP's image reader: subfolders are read and an image is named by its path from the folder; hidden
    folders, a folder of our own outputs (a stage record beside its plots) and a second link to one folder are not."""
    from pipeline.frontend.images import list_images

    img = tmp_path / "img"
    for d in ("cam0", "cam1/deep", ".cache", "out/run", "out/run/work"):
        (img / d).mkdir(parents=True)
    for f in ("top.jpg", "cam0/b.png", "cam0/a.png", "cam1/deep/c.JPG", ".cache/x.png", "out/run/errors_truth.png",
              "out/run/work/features.record.json", "cam0/notes.txt"):
        (img / f).write_bytes(b"x")
    (img / "out/run/viewgraph.record.json").write_text("{}")
    (img / "cam1/up").symlink_to(img, target_is_directory=True)  # a loop: read once
    (img / "cam0_again").symlink_to(img / "cam0", target_is_directory=True)
    names, other = list_images(img)
    assert names == ["cam0/a.png", "cam0/b.png", "cam1/deep/c.JPG", "top.jpg"]
    assert other == ["cam0/notes.txt"]


def test_a_subfolder_that_cannot_be_read_is_said(tmp_path, monkeypatch, caplog):
    """A subfolder the walk cannot list (permissions) leaves its images out with a warning that names it."""
    import os

    from pipeline.frontend.images import list_images

    img = tmp_path / "img"
    (img / "locked").mkdir(parents=True)
    (img / "locked" / "a.png").write_bytes(b"x")
    (img / "top.png").write_bytes(b"x")
    real = os.scandir

    def scandir(path="."):
        if Path(path).name == "locked":
            raise PermissionError(13, "Permission denied", str(path))
        return real(path)

    monkeypatch.setattr(os, "scandir", scandir)
    with caplog.at_level("WARNING"):
        names, _ = list_images(img)
    assert names == ["top.png"]
    assert "locked" in caplog.text and "left out" in caplog.text


@pytest.mark.slow
def test_images_in_subfolders_go_through_the_front_end(scene, tmp_path):
    """Two subfolders of one scene: the stages name the images by their relative paths, a cameras file naming them
    by their file names gives their K, and the pairs' rotations are right."""
    img = tmp_path / "img"
    _copy_images(scene, img / "left", scene.names[:2])
    _copy_images(scene, img / "right", scene.names[2:])
    w = tmp_path / "w"
    for args in (("pipeline.features", "--images", img, "--work", w, "--K", scene.out / "cameras.txt", "-q"),
                 ("pipeline.matching", "--work", w, "-q"), ("pipeline.two_view", "--work", w, "-q")):
        r = _run(*args)
        assert r.returncode == 0, r.stderr
    d = load_two_view(w)
    assert d.vg.names == [f"left/{n}" for n in scene.names[:2]] + [f"right/{n}" for n in scene.names[2:]]
    assert d.vg.n_edges == 3
    err = _pair_errors_deg(scene, d)
    assert err.max() < 1.0, err


@pytest.mark.slow
def test_images_of_different_sizes(scene, tmp_path):
    """A half-size copy of one view: its own size and K, and the right rotations."""
    img = _copy_images(scene, tmp_path / "img")
    small = cv2.resize(cv2.cvtColor(scene.images[2], cv2.COLOR_RGB2BGR), (240, 180), interpolation=cv2.INTER_AREA)
    (img / scene.names[2]).unlink()
    cv2.imwrite(str(img / "view_002_small.png"), small)
    # per-image intrinsics: the small image's K is the original scaled by 0.75
    K = scene.K.copy()
    K[2, :2, :2] *= 0.75
    K[2, :2, 2] = 0.75 * (scene.K[2, :2, 2] + 0.5) - 0.5  # pixel centres at integers: c' = s(c + ½) − ½
    names = [scene.names[0], scene.names[1], "view_002_small.png"]
    lines = [f"{n} {k[0, 0]} {k[1, 1]} {k[0, 2]} {k[1, 2]}" for n, k in zip(names, K)]
    (tmp_path / "cams.txt").write_text("\n".join(lines) + "\n")
    w = tmp_path / "w"
    for args in (("pipeline.features", "--images", img, "--work", w, "--K", tmp_path / "cams.txt", "-q"),
                 ("pipeline.matching", "--work", w, "-q"), ("pipeline.two_view", "--work", w, "-q")):
        r = _run(*args)
        assert r.returncode == 0, r.stderr
    d = load_two_view(w)
    np.testing.assert_array_equal(d.sizes, [[320, 240], [320, 240], [240, 180]])
    assert d.vg.n_edges == 3
    err = _pair_errors_deg(scene, d)
    assert err.max() < 1.0, err


@pytest.mark.slow
def test_resume_through_the_command_line(scene, tmp_path):
    img = _copy_images(scene, tmp_path / "img")
    w = tmp_path / "w"
    assert _run("pipeline.features", "--images", img, "--work", w, "-q").returncode == 0
    r = _run("pipeline.features", "--images", img, "--work", w)
    assert "features: up to date, nothing to compute" in r.stderr
    assert _run("pipeline.matching", "--work", w, "-q").returncode == 0
    r = _run("pipeline.matching", "--work", w)
    assert "skipping" in r.stderr
    r = _run("pipeline.matching", "--work", w, "--overwrite")
    assert "3 matched, 0 reused" in r.stderr


def test_an_exif_rotated_photo_is_read_as_stored_as_colmap_reads_it(tmp_path):
    """A phone photo taken upright carries EXIF orientation 6 (rotate 90° to display). COLMAP and pycolmap read the
    pixels as stored and ignore the tag; so do we, so that our keypoints, K and rotations are in the frame of the
    peers' and of a COLMAP model used as the truth (the displayed frame differs by a 90° roll)."""
    import pycolmap
    from PIL import Image

    from pipeline.frontend.images import image_size, read_gray

    rng = np.random.default_rng(0)
    stored = cv2.GaussianBlur((rng.random((120, 200)) * 255).astype(np.uint8), (5, 5), 0)
    folder = tmp_path / "images"
    folder.mkdir()
    im = Image.fromarray(stored)
    exif = im.getexif()
    exif[0x0112] = 6  # Orientation: the displayed image is the stored one turned 90° clockwise
    im.save(folder / "phone.jpg", exif=exif.tobytes(), quality=95)
    with Image.open(folder / "phone.jpg") as check:
        assert check.getexif()[0x0112] == 6 and check.size == (200, 120)
    gray, why = read_gray(folder / "phone.jpg")
    assert why == "" and gray.shape == (120, 200)  # not the displayed 200 × 120
    assert np.abs(gray.astype(int) - stored.astype(int)).mean() < 3  # the stored pixels (up to JPEG)
    assert image_size(folder / "phone.jpg") == (200, 120)
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, folder)
    with pycolmap.Database.open(db) as d:
        cams = d.read_all_cameras()
    assert [(c.width, c.height) for c in cams] == [(200, 120)]
