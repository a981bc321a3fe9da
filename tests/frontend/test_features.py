"""SIFT features: resizing and scaling back, cache and resume, intrinsics sources, CLI."""

from __future__ import annotations

import json
import logging
import shutil

import cv2
import numpy as np
import pytest

from pipeline import features
from pipeline.core.errors import InputFileError
from pipeline.frontend.feature_stage import load_features
from pipeline.frontend import features as features_kernel
from pipeline.frontend.features import FeatureConfig, extract_sift, extract_sift_adaptive
from pipeline.frontend.intrinsics import parse_intrinsics_file
from pipeline.frontend.matching import match_descriptors
from pipeline.synthetic.render import SceneConfig, render_scene

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    return render_scene(n_views=3, seed=7, out=out, config=CFG)


def test_keypoints_are_scaled_back_to_full_resolution(scene):
    gray = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in scene.images[:2]]
    cfg = FeatureConfig(max_image_size=160)  # half size
    k0, k1 = extract_sift(gray[0], cfg), extract_sift(gray[1], cfg)
    assert k0.xy[:, 0].max() > 200  # full-resolution frame, not the 160-pixel copy
    m = match_descriptors(k0.descriptors, k1.descriptors)
    assert len(m) > 20
    err = scene.epipolar_distance_px(0, 1, k0.xy[m[:, 0]], k1.xy[m[:, 1]])
    # true epipolar geometry holds in full-resolution pixels (a wrong scale gives tens of px)
    assert np.median(err) < 1.0


def test_max_keypoints_is_respected(scene):
    gray = cv2.cvtColor(scene.images[0], cv2.COLOR_RGB2GRAY)
    k = extract_sift(gray, FeatureConfig(max_keypoints=100))
    assert 50 < len(k.xy) <= 100
    assert k.descriptors.shape == (len(k.xy), 128) and k.descriptors.dtype == np.uint8


def test_rejects_bad_config_and_input():
    with pytest.raises(ValueError, match="max_image_size"):
        FeatureConfig(max_image_size=10)
    with pytest.raises(ValueError, match="max_keypoints"):
        FeatureConfig(max_keypoints=0)
    with pytest.raises(ValueError, match="expected \\(h, w\\) uint8"):
        extract_sift(np.zeros((10, 10, 3), np.uint8))


def test_response_cut_is_a_higher_threshold(scene):
    # the low-texture rule rests on this: OpenCV keeps |D| >= contrastThreshold / nOctaveLayers and reports
    # |D| as the response, so a detection at a low threshold cut at a response is a detection at that threshold
    gray = cv2.cvtColor(scene.images[0], cv2.COLOR_RGB2GRAY)
    a = cv2.SIFT_create(contrastThreshold=0.02, enable_precise_upscale=True).detect(gray, None)
    b = cv2.SIFT_create(contrastThreshold=0.0025, enable_precise_upscale=True).detect(gray, None)
    key = lambda k: (round(k.pt[0], 3), round(k.pt[1], 3), round(k.size, 3))  # noqa: E731
    assert sorted(map(key, a)) == sorted(key(k) for k in b if k.response >= 0.02 / 3)
    assert len(b) > len(a)


def test_textured_image_keeps_the_features_of_one_detection(scene):
    gray = cv2.cvtColor(scene.images[0], cv2.COLOR_RGB2GRAY)
    k, info = extract_sift_adaptive(gray)
    plain = extract_sift(gray, FeatureConfig(min_keypoints=0))
    assert not info.lowered and info.n_normal == len(k.xy) >= info.target == 500  # 320x240: 2000 / 4
    for a, b in zip((k.xy, k.scales, k.orientations, k.responses, k.descriptors),
                    (plain.xy, plain.scales, plain.orientations, plain.responses, plain.descriptors)):
        np.testing.assert_array_equal(a, b)


def test_dark_image_is_lowered_and_its_matches_hold(scene):
    gray = [(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) // 12).astype(np.uint8) for im in scene.images[:2]]  # dark, flat
    (k0, i0), (k1, _) = (extract_sift_adaptive(g) for g in gray)
    plain = [extract_sift(g, FeatureConfig(min_keypoints=0)) for g in gray]
    assert i0.lowered and i0.n_normal == len(plain[0].xy) < 500 <= len(k0.xy)
    assert 0.0025 <= i0.contrast_used < 0.02 and i0.preblur_sigma == 1.0
    m, m_plain = (match_descriptors(a.descriptors, b.descriptors) for a, b in ((k0, k1), plain))
    err = scene.epipolar_distance_px(0, 1, k0.xy[m[:, 0]], k1.xy[m[:, 1]])
    err_plain = scene.epipolar_distance_px(0, 1, plain[0].xy[m_plain[:, 0]], plain[1].xy[m_plain[:, 1]])
    assert (err < 1.0).sum() > 2 * (err_plain < 1.0).sum()  # more correct matches (true geometry, px)
    with pytest.raises(ValueError, match="contrast_floor"):
        FeatureConfig(contrast_floor=0.05)


@pytest.mark.parametrize("dark", [False, True], ids=["textured", "dark"])
def test_detecting_first_gives_the_same_features_bit_for_bit(scene, monkeypatch, dark):
    # the order of work chosen from the odds of low texture (detect only, describe if not lowered) changes
    # nothing but the time
    gray = cv2.cvtColor(scene.images[1], cv2.COLOR_RGB2GRAY)
    gray = (gray // 12).astype(np.uint8) if dark else gray
    out = {}
    for likely in (False, True):
        monkeypatch.setattr(features_kernel.LOW_TEXTURE_ODDS, "likely", lambda likely=likely: likely)
        out[likely] = extract_sift_adaptive(gray)
    (k0, i0), (k1, i1) = out[False], out[True]
    assert i0 == i1 and i0.lowered == dark
    for f in ("xy", "scales", "orientations", "responses", "descriptors"):
        np.testing.assert_array_equal(getattr(k0, f), getattr(k1, f), err_msg=f)


def _lowered_uncut(img, cfg, target):
    """The lowered detection as first written: everything at the floor described, then cut at the target."""
    blurred = cv2.GaussianBlur(img, (0, 0), cfg.preblur_sigma)
    kps, desc = cv2.SIFT_create(nfeatures=0, contrastThreshold=cfg.contrast_floor, enable_precise_upscale=True,
                                sigma=cfg.sigma, edgeThreshold=cfg.edge_threshold).detectAndCompute(blurred, None)
    xy, size, ori, resp, desc = features_kernel._arrays(kps, desc)
    L = cfg.n_octave_layers
    thr = max(cfg.contrast_floor / L, np.sort(resp)[::-1][target - 1]) if len(resp) >= target else cfg.contrast_floor / L
    keep = resp >= min(thr, cfg.contrast_threshold / L)
    return xy[keep], size[keep], ori[keep], resp[keep], desc[keep]


@pytest.mark.parametrize("dark, target", [(True, 500), (True, 100000), (False, 50)],
                         ids=["cut-at-target", "fewer-than-target", "normal-threshold-keeps-more"])
def test_lowered_detection_cut_by_opencv_is_the_uncut_one(scene, dark, target):
    # OpenCV cuts at the target before describing: the same keypoints, descriptors and order as describing
    # everything and cutting after; when more than the target reach the normal threshold, all of them stay
    gray = cv2.cvtColor(scene.images[1], cv2.COLOR_RGB2GRAY)
    gray = (gray // 12).astype(np.uint8) if dark else gray
    cfg = FeatureConfig(affine_below=0.0)  # the cut alone (the affine detection is tested below)
    info = features_kernel.Extraction(n_normal=0)
    got = features_kernel._lowered(gray, cfg, target, info)
    want = _lowered_uncut(gray, cfg, target)
    assert info.lowered and len(want[0]) > 0
    if target == 50:
        assert len(want[0]) > 2 * target and np.all(want[3] >= cfg.contrast_threshold / cfg.n_octave_layers)
    elif target == 500:
        assert target <= len(want[0]) < target + 10  # cut at the target (ties: a point's orientations)
    for name, a, b in zip(("xy", "scales", "orientations", "responses", "descriptors"), got, want):
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_texture_starved_image_is_detected_over_simulated_viewpoints():
    """The rendered low-texture turntable, two views 45° apart: at the contrast floor SIFT still finds
    fewer than half its target, so the floor detection runs over simulated tilts (ASIFT); it gives
    several times more correct matches (true depth and poses). Textured and merely dark images never
    reach this branch (tests above: their features are unchanged)."""
    from pipeline.synthetic.lowtex import LowTexConfig, render_lowtex

    scene = render_lowtex(LowTexConfig(n_views=8, contrast=8.0), seed=0)
    gray = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in scene.images[2:4]]

    def correct(ka, kb, m):
        return int((scene.transfer_error_px(2, 3, ka.xy[m[:, 0]], kb.xy[m[:, 1]]) < 3.0).sum())

    n_correct = {}
    for below in (0.0, FeatureConfig().affine_below):
        (ka, ia), (kb, ib) = (extract_sift_adaptive(g, FeatureConfig(affine_below=below)) for g in gray)
        assert ia.lowered and ib.lowered and ia.affine == ib.affine == (below > 0)
        n_correct[below] = correct(ka, kb, match_descriptors(ka.descriptors, kb.descriptors))
        if below > 0:
            again = extract_sift_adaptive(gray[0], FeatureConfig(affine_below=below))[0]
            np.testing.assert_array_equal(again.descriptors, ka.descriptors)  # deterministic
            # the identity view reuses the floor detection: the same as detecting it afresh
            fresh = features_kernel._affine(cv2.GaussianBlur(gray[0], (0, 0), FeatureConfig().preblur_sigma),
                                            FeatureConfig(), features_kernel.Extraction(n_normal=0))
            np.testing.assert_array_equal(fresh[0], ka.xy)
            np.testing.assert_array_equal(fresh[4], ka.descriptors)
            assert ia.contrast_used == FeatureConfig().contrast_floor
    plain, affine = n_correct[0.0], n_correct[FeatureConfig().affine_below]
    assert affine >= 20 and affine >= 3 * plain, n_correct


def test_low_texture_odds_follow_the_images_seen():
    odds = features_kernel._LowTextureOdds()
    assert not odds.likely()
    odds.record(True)
    assert not odds.likely()  # one image is no evidence
    odds.record(True)
    assert odds.likely()
    odds.record(False), odds.record(False)
    assert not odds.likely()


def test_stage_records_the_lowered_images(scene, tmp_path):
    images = tmp_path / "img"
    images.mkdir()
    for k, n in enumerate(scene.names):
        im = cv2.imread(str(scene.out / n))
        cv2.imwrite(str(images / n), im // 12 if k == 1 else im)
    shutil.copy(scene.out / "cameras.txt", images)
    m = json.loads(features.main(images, tmp_path / "work", progress=False).read_text())
    assert list(m["lowered"]) == [scene.names[1]]
    r = m["lowered"][scene.names[1]]
    assert r["n_normal"] < 500 <= r["n_keypoints"] and r["preblur_sigma"] == 1.0
    assert r["affine"] is False  # dark, but it reaches its target at the floor: no simulated views
    assert load_features(tmp_path / "work").lowered == m["lowered"]
    (tmp_path / "work" / "features.record.json").unlink()  # the manifest again, every image from the store
    m = json.loads(features.main(images, tmp_path / "work", progress=False).read_text())
    assert m["n_cached"] == 3 and list(m["lowered"]) == [scene.names[1]]


def test_main_cache_and_resume(scene, tmp_path):
    images = tmp_path / "img"
    shutil.copytree(scene.out, images)
    (images / "view_002.png").rename(tmp_path / "later.png")
    work = tmp_path / "work"
    m = json.loads(features.main(images, work, progress=False).read_text())
    assert m["n_extracted"] == 2 and m["n_cached"] == 0
    chunks = {c: c.stat().st_mtime_ns for c in (work / "features").glob("chunk-*.npz")}
    rec = features.FeaturesStage(work, images=images, progress=False).run()
    assert rec.reused  # resumed: nothing recomputed
    assert {c: c.stat().st_mtime_ns for c in (work / "features").glob("chunk-*.npz")} == chunks
    (tmp_path / "later.png").rename(images / "view_002.png")
    m = json.loads(features.main(images, work, progress=False).read_text())
    assert m["n_extracted"] == 1 and m["n_cached"] == 2  # only the new image
    m = json.loads(features.main(images, work, FeatureConfig(max_keypoints=500), progress=False).read_text())
    assert m["n_extracted"] == 3  # another config never reads a stale cache
    m = json.loads(features.main(images, work, FeatureConfig(max_keypoints=500), overwrite=True, progress=False).read_text())
    assert m["n_extracted"] == 3
    fs = load_features(work)
    assert fs.names == scene.names
    # intrinsics from the rendered cameras.txt found in the image folder
    np.testing.assert_allclose(fs.K, scene.K)
    assert all(s.startswith("file:") for s in fs.K_source)
    assert all(len(k) <= 500 for k in fs.keypoints)


def test_an_image_replaced_by_another_of_the_same_size_and_time_is_extracted_again(scene, tmp_path):
    import os

    images = tmp_path / "img"
    shutil.copytree(scene.out, images)
    a = images / "view_000.png"
    img = cv2.imread(str(a))
    cv2.imwrite(str(a), img, [cv2.IMWRITE_PNG_COMPRESSION, 0])  # stored, not deflated: its size is its shape's
    work = tmp_path / "work"
    features.main(images, work, progress=False)
    st = a.stat()
    img[:, : img.shape[1] // 2] = img[:, : img.shape[1] // 2] // 2  # another picture in its place
    cv2.imwrite(str(a), img, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    os.utime(a, ns=(st.st_atime_ns, st.st_mtime_ns))  # its time put back, as a copy that keeps times does
    assert a.stat().st_size == st.st_size and a.stat().st_mtime_ns == st.st_mtime_ns
    m = json.loads(features.main(images, work, progress=False).read_text())
    assert m["n_extracted"] == 1 and m["n_cached"] == 2 and not m["skipped"], m  # only it


def test_intrinsics_K_txt_default_and_exif(scene, tmp_path, caplog):
    images = tmp_path / "img"
    images.mkdir()
    for n in scene.names[:2]:
        shutil.copy(scene.out / n, images / n)
    work = tmp_path / "w"
    with caplog.at_level(logging.WARNING):
        features.main(images, work, progress=False)
    assert "f = 1.2" in caplog.text
    fs = load_features(work)
    np.testing.assert_allclose(fs.K[0][0, 0], 1.2 * 320)
    assert fs.K_source == ["default", "default"]
    Kfile = tmp_path / "K.txt"
    Kfile.write_text("300 0 160\n0 301 120\n0 0 1\n")
    features.main(images, work, K_path=Kfile, progress=False)
    fs = load_features(work)
    assert fs.K[1][1, 1] == 301
    # a JPEG with EXIF focal length
    from PIL import Image

    ex = Image.Exif()
    ex[0x010F], ex[0x0110] = "Canon", "Canon EOS 5D"
    ex.get_ifd(0x8769).update({0xA405: 50, 0x920A: (24, 1)})
    Image.open(images / scene.names[0]).convert("RGB").save(images / "exif.jpg", exif=ex.tobytes(), quality=95)
    features.main(images, work, progress=False)
    fs = load_features(work)
    k = fs.names.index("exif.jpg")
    assert fs.K_source[k] == "exif"
    assert 400 < fs.K[k][0, 0] < 520  # 24-50 mm equivalent focal on a 320-px-wide image, not 384 (default)


def test_intrinsics_file_formats(tmp_path):
    p = tmp_path / "cams.txt"
    p.write_text("# comment\na.png 100 101 50 40\n")
    assert parse_intrinsics_file(p)["a.png"][1, 1] == 101
    p.write_text("1 2 3\n")
    with pytest.raises(InputFileError, match="exactly 9"):
        parse_intrinsics_file(p)
    p.write_text("a.png 1 2 3\n")
    with pytest.raises(InputFileError, match="expected 4 or 16"):
        parse_intrinsics_file(p)
    p.write_text("1 0 0\n0 1 0\n0 0 0\n")
    with pytest.raises(InputFileError, match="not a pinhole K"):
        parse_intrinsics_file(p)
    with pytest.raises(InputFileError, match="does not exist"):
        parse_intrinsics_file(tmp_path / "nope.txt")


def test_load_features_without_run(tmp_path):
    with pytest.raises(InputFileError, match="run `python -m pipeline.features"):
        load_features(tmp_path)


def test_missing_folder(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        features.main(tmp_path / "nope", tmp_path / "w", progress=False)



def test_keypoints_are_unbiased_at_known_blob_centres():
    """OpenCV's default SIFT upscale shifts keypoints by +0.25 px; ours must not.

    Gaussian blobs with known sub-pixel centres: the median keypoint offset must be
    below 0.05 px on each axis (OpenCV's default gives about 0.25 px).
    """
    from pipeline.features import FeatureConfig, extract_sift

    rng = np.random.default_rng(0)
    h, w = 240, 320
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    centres = np.c_[rng.uniform(30, w - 30, 30), rng.uniform(30, h - 30, 30)]
    sig = rng.uniform(2, 4, 30)
    img = np.exp(-((xx[..., None] - centres[:, 0]) ** 2 + (yy[..., None] - centres[:, 1]) ** 2) / (2 * sig**2)).sum(-1)
    gray = (255 * img / img.max()).astype(np.uint8)

    def median_offset(cfg: FeatureConfig) -> np.ndarray:
        xy = extract_sift(gray, cfg).xy
        d = xy[:, None, :] - centres[None]
        near = d[np.arange(len(xy)), np.argmin(np.linalg.norm(d, axis=2), axis=1)]
        near = near[np.linalg.norm(near, axis=1) < 1.0]
        assert len(near) >= 20
        return np.median(near, axis=0)

    # 30 blobs on black are texture-starved: the default detection is the affine one (our own warps)
    assert extract_sift_adaptive(gray)[1].affine
    assert np.all(np.abs(median_offset(FeatureConfig())) < 0.05)
    assert np.all(np.abs(median_offset(FeatureConfig(affine_below=0.0))) < 0.05)
    # the check can fail: OpenCV's default upscale is biased
    assert np.all(median_offset(FeatureConfig(precise_upscale=False, affine_below=0.0)) > 0.15)
    # and so is OpenCV's AffineFeature (nearest-neighbour compression), which is why the warps are ours
    det = cv2.AffineFeature_create(cv2.SIFT_create(contrastThreshold=0.0025, enable_precise_upscale=True), maxTilt=2,
                                   minTilt=0, tiltStep=float(np.sqrt(2.0)), rotateStepBase=72.0)
    xy = cv2.KeyPoint_convert(det.detect(gray, None)).reshape(-1, 2)
    d = xy[:, None, :] - centres[None]
    near = d[np.arange(len(xy)), np.argmin(np.linalg.norm(d, axis=2), axis=1)]
    assert np.abs(np.median(near[np.linalg.norm(near, axis=1) < 1.0], axis=0)).max() > 0.1


def test_an_exif_rotated_photo_is_read_in_its_stored_frame_as_colmap_reads_it(tmp_path):
    """A phone photo stored landscape with EXIF Orientation 6 (show rotated 90°): COLMAP/pycolmap read the stored
    pixels, so our cameras must too, or every rotation differs from the peers' and a COLMAP-made truth by a 90° roll.
    (OpenCV's IMREAD_GRAYSCALE would apply the tag: this test fails with it.)"""
    from PIL import Image
    import pycolmap

    from pipeline.frontend.images import image_size, read_gray

    pixels = (np.random.default_rng(0).random((120, 200)) * 255).astype(np.uint8)
    im = Image.fromarray(pixels)
    exif = im.getexif()
    exif[0x0112] = 6  # Orientation: rotate 90° clockwise to display
    path = tmp_path / "portrait.jpg"
    im.save(path, exif=exif.tobytes(), quality=95)
    img, why = read_gray(path)
    assert why == "" and img.shape == (120, 200)
    assert image_size(path) == (200, 120)
    bitmap = pycolmap.Bitmap.read(str(path), as_rgb=False)
    assert (bitmap.width, bitmap.height) == (200, 120)
    assert np.abs(img.astype(int) - pixels.astype(int)).mean() < 3  # the same pixels, not a transpose


def test_an_exif_orientation_is_said_and_the_stored_pixels_are_used(scene, tmp_path, caplog):
    """COLMAP reads the stored pixels whatever the EXIF orientation; so do we, and the warning says so (a K or a
    truth made for the turned picture would not fit them)."""
    from PIL import Image

    from pipeline.frontend.images import check_headers, read_gray

    im = Image.fromarray(np.asarray(scene.images[0], np.uint8)).convert("RGB")
    exif = Image.Exif()
    exif[0x0112] = 6  # displayed turned by 90°
    im.save(tmp_path / "turned.jpg", exif=exif.tobytes())
    im.save(tmp_path / "plain.jpg")
    with caplog.at_level(logging.WARNING, logger="pipeline.frontend.images"):
        sizes, bad = check_headers(tmp_path, ["plain.jpg", "turned.jpg"])
    assert sizes["turned.jpg"] == sizes["plain.jpg"] == im.size and not bad
    (msg,) = [r.getMessage() for r in caplog.records]
    assert msg.startswith("1 image(s) carry an EXIF orientation tag (e.g. turned.jpg: 6)") and "as stored" in msg
    assert read_gray(tmp_path / "turned.jpg")[0].shape == im.size[::-1]  # not turned on reading


def test_a_png_header_is_read_without_decoding_its_pixels_and_its_exif_orientation_still_said(tmp_path, caplog):
    """Pillow's getexif of a PNG decoded the whole image: a 150 kB PNG of 12000×12000 pixels took 0.4 s and 137 MB
    in the header check that is there to refuse such sizes before any decoding."""
    import resource
    import time

    from PIL import Image

    from pipeline.frontend.images import check_headers

    Image.new("L", (12000, 12000)).save(tmp_path / "huge.png")
    im = Image.new("L", (200, 120), 128)
    exif = Image.Exif()
    exif[0x0112] = 6
    im.save(tmp_path / "turned.png", exif=exif.tobytes())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with caplog.at_level(logging.WARNING, logger="pipeline.frontend.images"):
        sizes, bad = check_headers(tmp_path, ["huge.png", "turned.png"])
    dt = time.perf_counter() - t0
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak) / 1024
    assert sizes == {"huge.png": (12000, 12000), "turned.png": (200, 120)} and not bad
    assert dt < 0.1 and grown_mb < 50, (dt, grown_mb)  # 144 Mpx decoded would be 0.4 s and 137 MB
    (msg,) = [r.getMessage() for r in caplog.records]
    assert msg.startswith("1 image(s) carry an EXIF orientation tag (e.g. turned.png: 6)")
