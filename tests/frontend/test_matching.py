"""Matching: correctness on rendered pairs, mutual/ratio checks, FLANN vs brute force, pairs files, resume."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from pipeline import features, matching
from pipeline.core.errors import InputFileError
from pipeline.frontend.features import extract_sift
from pipeline.frontend.matching import MatchingConfig, match_descriptors
from pipeline.frontend.matching_stage import load_matches
from pipeline.frontend.pairs import exhaustive_pairs, read_pairs
from pipeline.synthetic.render import SceneConfig, render_scene

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return render_scene(n_views=3, seed=11, out=tmp_path_factory.mktemp("scene"), config=CFG)


@pytest.fixture(scope="module")
def kps(scene):
    return [extract_sift(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)) for im in scene.images]


@pytest.mark.parametrize("method", ["bf", "flann"])
def test_matches_follow_true_geometry_and_are_one_to_one(scene, kps, method):
    m = match_descriptors(kps[0].descriptors, kps[1].descriptors, MatchingConfig(method=method))
    assert len(m) > 100
    assert len(np.unique(m[:, 0])) == len(m) and len(np.unique(m[:, 1])) == len(m)  # mutual check: one-to-one
    err = scene.epipolar_distance_px(0, 1, kps[0].xy[m[:, 0]], kps[1].xy[m[:, 1]])
    assert np.mean(err < 2.0) > 0.9


def test_flann_agrees_with_brute_force(kps):
    bf = match_descriptors(kps[0].descriptors, kps[1].descriptors, MatchingConfig(method="bf"))
    fl = match_descriptors(kps[0].descriptors, kps[1].descriptors, MatchingConfig(method="flann"))
    common = len({tuple(r) for r in bf} & {tuple(r) for r in fl})
    assert common > 0.9 * min(len(bf), len(fl))


def test_ratio_and_mutual_filter(kps):
    d0, d1 = kps[0].descriptors, kps[1].descriptors
    loose = match_descriptors(d0, d1, MatchingConfig(method="bf", ratio=0.9, mutual=False))
    strict = match_descriptors(d0, d1, MatchingConfig(method="bf", ratio=0.6, mutual=False))
    mutual = match_descriptors(d0, d1, MatchingConfig(method="bf", ratio=0.9, mutual=True))
    s_loose = {tuple(r) for r in loose}
    assert len(strict) < len(loose) and {tuple(r) for r in strict} <= s_loose
    assert len(mutual) < len(loose) and {tuple(r) for r in mutual} <= s_loose
    # without the mutual check some images-b keypoints are matched twice
    assert len(np.unique(loose[:, 1])) < len(loose)


def test_brute_force_is_exact(kps):
    """The BLAS brute force finds the same nearest neighbours as OpenCV's exhaustive matcher."""
    from pipeline.frontend.matching import root_sift

    qa, qb = root_sift(kps[0].descriptors), root_sift(kps[1].descriptors)
    ref = cv2.BFMatcher(cv2.NORM_L2).knnMatch(qa, qb, k=2)
    keep = [(r[0].queryIdx, r[0].trainIdx) for r in ref if r[0].distance < 0.8 * r[1].distance]
    ours = match_descriptors(kps[0].descriptors, kps[1].descriptors, MatchingConfig(method="bf", mutual=False))
    assert {tuple(r) for r in ours} == set(keep)


def test_config_validation():
    with pytest.raises(ValueError, match="ratio"):
        MatchingConfig(ratio=1.5)
    with pytest.raises(ValueError, match="method"):
        MatchingConfig(method="kdtree")


def test_exhaustive_pairs():
    p = exhaustive_pairs(4)
    assert p.shape == (6, 2) and np.all(p[:, 0] < p[:, 1])


def test_pairs_file(tmp_path):
    names = ["a.jpg", "b.jpg", "c.jpg"]
    f = tmp_path / "pairs.txt"
    f.write_text("b.jpg a.jpg\n# comment\nc a\na.jpg b.jpg\n")
    np.testing.assert_array_equal(read_pairs(f, names), [[0, 1], [0, 2]])
    f.write_text("a.jpg z.jpg\n")
    with pytest.raises(InputFileError, match="'z.jpg' is not among"):
        read_pairs(f, names)
    f.write_text("a.jpg\n")
    with pytest.raises(InputFileError, match="expected 'name_a name_b'"):
        read_pairs(f, names)
    f.write_text("a.jpg a.jpg\n")
    with pytest.raises(InputFileError, match="no pair"):
        read_pairs(f, names)
    with pytest.raises(InputFileError, match="does not exist"):
        read_pairs(tmp_path / "none.txt", names)


def test_pairs_file_with_an_unquoted_name_holding_spaces(tmp_path):
    """'IMG 0001.jpg b.jpg' is four fields; the error said only that image 'IMG' is not among the images."""
    names = ["IMG 0001.jpg", "b.jpg"]
    f = tmp_path / "pairs.txt"
    f.write_text("IMG 0001.jpg b.jpg\n")
    with pytest.raises(InputFileError, match=r"'IMG' is not among .*double quotes"):
        read_pairs(f, names)
    f.write_text('"IMG 0001.jpg" b.jpg\n')
    np.testing.assert_array_equal(read_pairs(f, names), [[0, 1]])


def test_main_resume_and_incremental(scene, tmp_path):
    images = tmp_path / "img"
    shutil.copytree(scene.out, images)
    (images / "view_002.png").rename(tmp_path / "later.png")
    work = tmp_path / "w"
    features.main(images, work, progress=False)
    matching.main(work, progress=False)
    man = json.loads((work / "matches.json").read_text())
    assert man["n_computed"] == 1 and man["n_pairs"] == 1
    assert matching.MatchingStage(work, progress=False).run().reused  # resumed: nothing recomputed
    (tmp_path / "later.png").rename(images / "view_002.png")
    features.main(images, work, progress=False)
    matching.main(work, progress=False)
    man = json.loads((work / "matches.json").read_text())
    assert man["n_pairs"] == 3 and man["n_computed"] == 2 and man["n_reused"] == 1  # only the new pairs
    # an image file that changes (same name) gets new features: its 2 pairs are matched again
    import os

    st = (images / "view_001.png").stat()
    os.utime(images / "view_001.png", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    features.main(images, work, progress=False)
    matching.main(work, progress=False)
    man = json.loads((work / "matches.json").read_text())
    assert man["n_computed"] == 2 and man["n_reused"] == 1
    matching.main(work, overwrite=True, progress=False)
    assert json.loads((work / "matches.json").read_text())["n_computed"] == 3
    pf = tmp_path / "pairs.txt"
    pf.write_text("view_000.png view_002.png\n")
    out = matching.main(work, pairs_path=pf, progress=False)
    ms = load_matches(work)
    assert out.is_file() and ms.pairs.tolist() == [[0, 2]] and len(ms.matches[0]) > 50


def test_matching_without_features(tmp_path):
    with pytest.raises(InputFileError, match="pipeline.features"):
        matching.main(tmp_path, progress=False)


def test_flann_matches_do_not_depend_on_rng_state_or_threads():
    """FLANN's random kd-trees draw from OpenCV's per-thread RNG; the index is seeded where it is built."""
    import threading

    import cv2

    rng = np.random.default_rng(5)
    da = rng.integers(0, 255, (3000, 128)).astype(np.uint8)
    db = np.clip(da.astype(np.int16) + rng.integers(-20, 20, da.shape), 0, 255).astype(np.uint8)[rng.permutation(3000)]
    cfg = MatchingConfig(method="flann", flann_checks=8)
    ref = match_descriptors(da, db, cfg)
    assert len(ref) > 1000
    cv2.setRNGSeed(12345)  # another RNG state in this thread
    np.testing.assert_array_equal(match_descriptors(da, db, cfg), ref)
    out = []
    t = threading.Thread(target=lambda: out.append(match_descriptors(da, db, cfg)))
    t.start()
    t.join()
    np.testing.assert_array_equal(out[0], ref)


@pytest.mark.parametrize("path", ["reuse", "recompute"])
@pytest.mark.parametrize("bad_index", [-1, 10**6])
def test_matches_out_of_the_features_range_are_recomputed(scene, tmp_path, bad_index, path, damage_item):
    # A chunk that reads well but refers to keypoints the features lack (past the end, or negative, which numpy
    # would take from the end) is not trusted, whether the stage's output is intact (its check on reuse finds it)
    # or lost (the recompute checks what it would reuse): the stage recomputes it and the matches come back as
    # before.
    from pipeline.frontend.matching_stage import MANIFEST, STORE

    work = tmp_path / "w"
    features.main(scene.out, work, progress=False)
    matching.main(work, progress=False)
    before = load_matches(work)
    damage_item(work / STORE, lambda f: f["matches"].__setitem__((0, 1), bad_index))
    if path == "recompute":
        (work / MANIFEST).unlink()
    rec = matching.MatchingStage(work, progress=False).run()
    assert not rec.reused and rec.summary["n_computed"] >= 1  # the damaged pair's chunk
    after = load_matches(work)
    assert after.pairs.tolist() == before.pairs.tolist()
    assert all(np.array_equal(x, y) for x, y in zip(after.matches, before.matches))


@pytest.mark.parametrize("path", ["reuse", "recompute"])
def test_features_that_read_but_are_not_finite_are_recomputed(scene, tmp_path, path, damage_item):
    from pipeline.frontend.feature_stage import MANIFEST, STORE, FeaturesStage, load_features

    work = tmp_path / "w"
    features.main(scene.out, work, progress=False)
    before = load_features(work)
    damage_item(work / STORE, lambda f: f["keypoints"].__setitem__((3, 0), np.nan))
    if path == "recompute":
        (work / MANIFEST).unlink()
    rec = FeaturesStage(work, images=scene.out, progress=False).run()
    assert not rec.reused and rec.summary["n_extracted"] == 1
    after = load_features(work)
    assert all(np.array_equal(x, y) for x, y in zip(after.keypoints, before.keypoints))
    assert all(np.array_equal(x, y) for x, y in zip(after.descriptors, before.descriptors))
