"""Per-image focal lengths from the whole view graph (pipeline.frontend.vg_calibration and the cameras stage).

Images of different cameras (sizes and zooms) have no group to share a focal with: pycolmap's view-graph
calibration gives each its own, and the rotation consistency of the pairs decides between those and the group
focal lengths.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.frontend import vg_calibration as vgc
from pipeline.frontend.camera_stage import PER_IMAGE_SOURCE, CamerasConfig, CamerasStage
from pipeline.frontend.focal import K_from_focal

SIZES = [(800, 600), (640, 480), (720, 540), (600, 800), (768, 576), (704, 528), (640, 480), (800, 600)]


def _cameras(seed: int = 0, sigma: float = 0.5, one_camera: bool = False):
    """8 cameras of different sizes and focal lengths around a point cloud: keypoints and matches of every pair.

    ``one_camera``: all 800×600 with one focal length instead.
    """
    rng = np.random.default_rng(seed)
    n = len(SIZES)
    X = rng.uniform(-2.0, 2.0, (1200, 3))
    sizes = np.array([(800, 600)] * n if one_camera else SIZES)
    f = sizes.max(1) * (np.full(n, 1.1) if one_camera else np.exp(rng.uniform(np.log(0.8), np.log(1.4), n)))
    K = np.array([K_from_focal(f[k], np.array([(w - 1) / 2, (h - 1) / 2])) for k, (w, h) in enumerate(sizes)])
    kps, vis = [], []
    for k in range(n):
        a = 1.1 * (k / (n - 1) - 0.5)
        C = 9.0 * np.array([np.sin(a), 0.2 * rng.standard_normal(), -np.cos(a)])
        z = rng.normal(0, 0.5, 3) - C
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        p = (X - C) @ R.T @ K[k].T
        uv = p[:, :2] / p[:, 2:]
        ok = (uv >= 0).all(1) & (uv < sizes[k]).all(1)
        kps.append(uv[ok] + sigma * rng.standard_normal((ok.sum(), 2)))
        vis.append(np.flatnonzero(ok))
    pairs, matches = [], []
    for i in range(n):
        for j in range(i + 1, n):
            common, a, b = np.intersect1d(vis[i], vis[j], return_indices=True)
            if len(common) >= 30:
                pairs.append((i, j))
                matches.append(np.column_stack([a, b]))
    start = np.array([K_from_focal(1.2 * max(w, h), np.array([(w - 1) / 2, (h - 1) / 2])) for w, h in sizes])
    return sizes, K, start, kps, np.array(pairs), matches


@pytest.fixture(scope="module")
def cams():
    return _cameras()


@pytest.fixture(scope="module")
def calibrated(cams, tmp_path_factory):
    sizes, K, start, kps, pairs, matches = cams
    names = [f"im{k}.png" for k in range(len(sizes))]
    return vgc.calibrate_focals(names, sizes, [start], np.zeros(len(sizes), bool), kps, pairs, matches,
                                tmp_path_factory.mktemp("vgc"))[0]


def test_every_image_gets_its_own_focal(cams, calibrated) -> None:
    sizes, K, start, *_ = cams
    assert calibrated.ok and len(calibrated.edges) >= 20
    err = calibrated.f / K[:, 0, 0] - 1
    assert np.all(np.abs(err) < 0.02), err
    # the start was 1.2·max(w, h): up to 50% off
    assert np.max(np.abs(start[:, 0, 0] / K[:, 0, 0] - 1)) > 0.2


def test_rotation_consistency_prefers_the_true_focal_lengths(cams, calibrated) -> None:
    sizes, K, start, kps, *_ = cams
    c_true = vgc.consistency_cost(calibrated, K, kps)
    c_start = vgc.consistency_cost(calibrated, start, kps)
    wrong = K.copy()
    wrong[:, :2, :2] *= 1.1  # every focal 10% long
    assert c_true < 0.1 * c_start and c_true < vgc.consistency_cost(calibrated, wrong, kps)


def test_F_is_in_our_pixels(cams, calibrated) -> None:
    """The database holds COLMAP pixels (+0.5); the F read back must fit our keypoints."""
    _, _, _, kps, *_ = cams
    (i, j), F, m = calibrated.edges[0], calibrated.F[0], calibrated.inliers[0]
    xi = np.column_stack([kps[i][m[:, 0]], np.ones(len(m))])
    xj = np.column_stack([kps[j][m[:, 1]], np.ones(len(m))])
    l = xi @ F.T  # epipolar lines in image j
    d = np.abs(np.sum(xj * l, 1)) / np.hypot(l[:, 0], l[:, 1])
    assert np.median(d) < 0.7, np.median(d)


def test_no_database_is_left_behind(cams, tmp_path) -> None:
    sizes, K, start, kps, pairs, matches = cams
    stale = tmp_path / f"{vgc.TMP_PREFIX}killed"
    stale.mkdir()
    (stale / "calibration.db").write_bytes(b"half")
    vgc.calibrate_focals([f"im{k}.png" for k in range(len(sizes))], sizes, [start], np.zeros(len(sizes), bool),
                         kps, pairs[:6], matches[:6], tmp_path)
    assert not list(tmp_path.glob(f"{vgc.TMP_PREFIX}*"))


def test_image_names_with_spaces_keep_their_pairs(cams, calibrated, tmp_path) -> None:
    """Names as users have them ('IMG 0001 (copy).JPG'): COLMAP's pairs file is 'NAME1 NAME2' lines, so pycolmap's
    verification through one dropped every pair of such an image ("Image IMG does not exist") and the calibrator
    gave it no focal."""
    sizes, K, start, kps, pairs, matches = cams
    names = [f"IMG {k} (copy) é.JPG" if k % 2 else f"im{k}.png" for k in range(len(sizes))]
    cal = vgc.calibrate_focals(names, sizes, [start], np.zeros(len(sizes), bool), kps, pairs, matches, tmp_path)[0]
    np.testing.assert_array_equal(cal.edges, calibrated.edges)
    np.testing.assert_array_equal(cal.F, calibrated.F)
    np.testing.assert_array_equal(cal.f, calibrated.f)


def _stage_call(cams, tmp_path, monkeypatch, focal: np.ndarray | None, group: np.ndarray | None = None):
    """The cameras stage's choice on these cameras; ``focal``: what the calibrator is made to return; ``group``:
    the group focal lengths (K) the stage holds (default: the start values)."""
    sizes, K, start, kps, pairs, matches = cams
    n = len(sizes)
    names = [f"im{k}.png" for k in range(n)]
    if focal is not None:
        real = vgc.calibrate_focals

        def fake(*args, **kwargs):
            cals = real(*args, **kwargs)
            for cal in cals:
                cal.f = focal.copy()
            return cals

        monkeypatch.setattr("pipeline.frontend.camera_stage.calibrate_focals", fake)
    stage = CamerasStage(tmp_path, CamerasConfig(progress=False, workers=1))
    fs = SimpleNamespace(names=names, sizes=sizes, K=start.copy())
    K_cur, sources, estimate = (start if group is None else group).copy(), ["default"] * n, {"groups": []}
    gkey = [tuple(sz) for sz in sizes.tolist()]
    stage._per_image_focal(fs, pairs, matches, kps, K_cur, sources, np.ones(n, bool), np.zeros(n, bool), gkey,
                           estimate)
    return K_cur, sources, estimate


def test_stage_keeps_per_image_focal_lengths_that_the_graph_prefers(cams, tmp_path, monkeypatch) -> None:
    K_cur, sources, est = _stage_call(cams, tmp_path, monkeypatch, None)
    K = cams[1]
    assert set(sources) == {PER_IMAGE_SOURCE} and est["per_image"]["chosen"].startswith("per-image")
    assert np.all(np.abs(K_cur[:, 0, 0] / K[:, 0, 0] - 1) < 0.02)
    np.testing.assert_array_equal(K_cur[:, :2, 2], cams[2][:, :2, 2])  # principal points untouched


def test_stage_keeps_the_group_focal_lengths_when_the_calibration_is_worse(cams, tmp_path, monkeypatch) -> None:
    sizes, K, start, *_ = cams
    bad = start[:, 0, 0] * np.where(np.arange(len(sizes)) % 2, 1.5, 0.6)  # further off than the start values
    K_cur, sources, est = _stage_call(cams, tmp_path, monkeypatch, bad)
    assert sources == ["default"] * len(sizes) and est["per_image"]["chosen"] == "group"
    np.testing.assert_array_equal(K_cur, start)
    assert est["per_image"]["calibrations"]["from_group"]["consistency"] > est["per_image"]["consistency_group"]


def test_rendered_images_of_different_cameras(tmp_path) -> None:
    """Rendered views of several sizes and zooms, no K and no EXIF: each image's focal within 6% of its own (median
    2%; the start values, 1.2·max(w, h), are up to 50% off). The two-view BA refines them further (``refine_focal:
    auto``)."""
    from pipeline import features, matching  # noqa: PLC0415
    from pipeline.frontend.camera_stage import load_cameras  # noqa: PLC0415
    from pipeline.synthetic.mixed import render_mixed_cameras  # noqa: PLC0415

    scene = render_mixed_cameras(tmp_path / "scene", n_views=8, seed=0)
    assert len({tuple(s) for s in scene.sizes}) >= 3  # no size group has enough pairs of its own
    work = tmp_path / "work"
    features.main(scene.images, work, progress=False)
    matching.main(work, progress=False)
    CamerasStage(work, CamerasConfig(progress=False, workers=1)).run()
    cams = load_cameras(work)
    assert set(cams.K_source) == {PER_IMAGE_SOURCE}
    err = cams.K[:, 0, 0] / scene.K[:, 0, 0] - 1
    assert np.all(np.abs(err) < 0.06) and np.median(np.abs(err)) < 0.02, err
    start = 1.2 * scene.sizes.max(1) / scene.K[:, 0, 0] - 1
    assert np.max(np.abs(start)) > 0.3
    # refine_focal: auto (the default) refines these focal lengths in the two-view BA, pair by pair
    from pipeline.geometry.ba_solver import BAConfig  # noqa: PLC0415
    from pipeline.geometry.ba_stage import TwoViewBAStage, load_ba_viewgraph  # noqa: PLC0415
    from pipeline.geometry.two_view_stage import TwoViewStage  # noqa: PLC0415

    TwoViewStage(work).run()
    TwoViewBAStage(work, BAConfig(progress=False, workers=1)).run()
    vg = load_ba_viewgraph(work)
    f_ba, f_in = vg.stats["ba_focal"], cams.K[vg.edges, 0, 0]
    assert np.median(np.abs(f_ba / f_in - 1)) > 1e-4  # moved
    assert np.median(np.abs(f_ba / scene.K[vg.edges, 0, 0] - 1)) < 0.03


def test_one_camera_keeps_its_shared_focal(tmp_path, monkeypatch) -> None:
    """One camera, its shared focal right: per-image focal lengths fit a little better or worse by chance, never
    significantly (the F test of ``per_image_level``)."""
    cams = _cameras(seed=1, one_camera=True)
    K = cams[1]
    K_cur, sources, est = _stage_call(cams, tmp_path, monkeypatch, None, group=K)
    pi = est["per_image"]
    assert sources == ["default"] * len(K) and pi["chosen"] == "group", pi
    assert not pi["F"] > pi["F_critical"]
    np.testing.assert_array_equal(K_cur, K)


def test_F_test_of_the_per_image_focal_lengths() -> None:
    # 40 pairs, 10 images: 120 − 27 − 5 = 88 degrees of freedom for 5 extra focal lengths
    assert vgc.per_image_test(0.050, 0.005, 40, 10, 5)[0]  # ten times more consistent
    sig, F, crit = vgc.per_image_test(0.0343, 0.0342, 55, 11, 10)  # fountain: 0.3% by chance
    assert not sig and F < crit
    assert not vgc.per_image_test(2.1e-6, 6.4e-7, 8, 5, 4)[0]  # 3× lower, but 8 pairs leave 7 degrees of freedom
    assert not vgc.per_image_test(0.01, 0.02, 40, 10, 5)[0] and not vgc.per_image_test(0.05, 0.005, 3, 4, 3)[0]
    assert not vgc.per_image_test(float("nan"), 0.005, 40, 10, 5)[0]


def test_guessed_focal_lengths_need_no_high_significance(cams, calibrated, monkeypatch) -> None:
    """Where the group focal lengths are only the default guess, the per-image set is tested at guess_level (better
    than chance), not at the level that protects an estimate."""
    sizes, K, start, kps, pairs, matches = cams
    names = [f"im{k}.png" for k in range(len(sizes))]
    args = ([calibrated], ["start"], [start], start, kps, names, np.ones(len(sizes), bool), [None] * len(sizes))
    levels = []
    real = vgc.per_image_test
    monkeypatch.setattr(vgc, "per_image_test", lambda *a: levels.append(a[-1]) or real(*a))
    strict = vgc.choose_focal_lengths(*args, level=0.999)
    assert levels == [0.999] and strict.record["level"] == 0.999 and strict.record["n_guessed"] == 0
    guessed = vgc.choose_focal_lengths(*args, level=0.999, guessed=np.ones(len(sizes), bool))
    assert levels[-1] == 0.5 and guessed.record["level"] == 0.5 and guessed.record["n_guessed"] == len(sizes)
    assert guessed.chosen and np.all(np.abs(guessed.K[:, 0, 0] / K[:, 0, 0] - 1) < 0.02)
    some = np.arange(len(sizes)) < 2  # a guess among estimates: the whole set is tested at guess_level
    assert vgc.choose_focal_lengths(*args, level=0.999, guessed=some).record["n_guessed"] == 2 and levels[-1] == 0.5
    none = vgc.choose_focal_lengths(*args, level=0.999, guessed=np.zeros(len(sizes), bool))
    assert levels[-1] == 0.999 and none.record["n_guessed"] == 0


def test_a_choice_without_an_F_test_says_why(cams, calibrated) -> None:
    """Where the per-image set is no more consistent than the group focal lengths there is no F to compare: the
    record (and the log line built from it, which printed 'F nan vs nan') says so in words."""
    sizes, K, start, kps, pairs, matches = cams
    names = [f"im{k}.png" for k in range(len(sizes))]
    tested = vgc.choose_focal_lengths([calibrated], ["start"], [start], start, kps, names, np.ones(len(sizes), bool),
                                      [None] * len(sizes))
    assert np.isfinite(tested.record["F"]) and tested.record["no_test"] is None
    worse = K.copy()  # the group focal lengths at the truth: the calibration's own set cannot be more consistent
    rec = vgc.choose_focal_lengths([calibrated], ["start"], [start], worse, kps, names, np.ones(len(sizes), bool),
                                   [None] * len(sizes)).record
    assert not np.isfinite(rec["F"]) and rec["chosen"] == "group"
    assert rec["no_test"].startswith("the per-image focal lengths are not more consistent"), rec["no_test"]
