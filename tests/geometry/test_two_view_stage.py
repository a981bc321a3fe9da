"""The two-view stage: accuracy on rendered scenes, ViewGraph output, resume, healing, readers, command line."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys

import numpy as np
import pytest

from pipeline import features, matching
from pipeline.core import so3
from pipeline.core.errors import CacheError, InputFileError, PipelineError
from pipeline.geometry.epipolar import essential_from_Rt
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.geometry.two_view_stage import CORRESPONDENCES, VIEWGRAPH, TwoViewStage, load_two_view
from pipeline.stage import output_digest
from pipeline.synthetic.render import SceneConfig, render_scene

CFG = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)
Q = TwoViewConfig(progress=False)


def _deg(Ra, Rb):
    return float(np.degrees(so3.angle_between(Ra, Rb)))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    scene = render_scene(n_views=4, seed=5, out=tmp_path_factory.mktemp("scene"), config=CFG)
    w = tmp_path_factory.mktemp("work")
    features.main(scene.out, w, progress=False)
    matching.main(w, progress=False)
    TwoViewStage(w, Q).run()
    return scene, w


@pytest.fixture
def work_copy(work, tmp_path):
    """A copy of the module's WORK folder with the default two-view result, for tests that damage it."""
    w = tmp_path / "w"
    shutil.copytree(work[1], w)
    TwoViewStage(w, Q).run()
    return w


def _snapshot(w):
    d = load_two_view(w)
    return [d.vg.R_rel, d.vg.stats["t"], d.vg.inliers, d.x_i, d.x_j, d.kp_i, d.offsets, d.K]


def test_rendered_pair_essential_matrix_agrees_with_truth(work):
    scene, w = work
    d = load_two_view(w)
    k = int(np.flatnonzero((d.vg.edges[:, 0] == 0) & (d.vg.edges[:, 1] == 2))[0])
    R_true, t_true = scene.relative_pose(0, 2)
    R, t = d.vg.R_rel[k], d.vg.stats["t"][k]
    assert _deg(R, R_true) < 0.3
    assert np.degrees(np.arccos(np.clip(t @ t_true, -1, 1))) < 2.0
    E_true, E = essential_from_Rt(R_true, t_true), essential_from_Rt(R, t)
    E_true, E = E_true / np.linalg.norm(E_true), E / np.linalg.norm(E)
    assert min(np.linalg.norm(E - E_true), np.linalg.norm(E + E_true)) < 0.02
    # the stored inlier correspondences satisfy the true epipolar constraint to sub-pixel
    x_i, x_j = d.correspondences(k)
    y_i = np.column_stack([x_i, np.ones(len(x_i))]) @ np.linalg.inv(scene.K[0]).T
    y_j = np.column_stack([x_j, np.ones(len(x_j))]) @ np.linalg.inv(scene.K[2]).T
    Ex, Etx = y_i @ E_true.T, y_j @ E_true
    s = np.abs(np.sum(y_j * Ex, 1)) / np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2)
    assert np.median(s * scene.K[0][0, 0]) < 0.5 and len(x_i) == d.vg.inliers[k]


@pytest.mark.slow
def test_rendered_12_view_ring_median_error(tmp_path):
    """Acceptance (issue 5) at reduced size: RANSAC alone, median relative-rotation error ≤ 0.3°."""
    cfg = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=120.0)
    scene = render_scene(n_views=12, seed=0, out=tmp_path / "scene", config=cfg)
    w = tmp_path / "w"
    features.main(scene.out, w, progress=False)
    matching.main(w, progress=False)
    TwoViewStage(w, Q).run()
    d = load_two_view(w)
    vg = d.vg
    assert vg.n_edges >= 60  # nearly all 66 pairs of the ring overlap and are accepted
    R_true = np.einsum("mij,mkj->mik", scene.R[vg.edges[:, 1]], scene.R[vg.edges[:, 0]])
    err = np.degrees(so3.angle_between(vg.R_rel, R_true))
    assert np.median(err) < 0.3


def test_viewgraph_convention_and_contents(work):
    scene, w = work
    d = load_two_view(w)
    vg = d.vg
    assert vg.names == scene.names and vg.n_edges == 6 and not d.rejected
    R_true = np.einsum("mij,mkj->mik", scene.R[vg.edges[:, 1]], scene.R[vg.edges[:, 0]])  # R_j R_iᵀ
    err = np.degrees(so3.angle_between(vg.R_rel, R_true))
    assert np.median(err) < 0.3 and err.max() < 1.0
    assert vg.stats["t"].shape == (6, 3)
    np.testing.assert_allclose(np.linalg.norm(vg.stats["t"], axis=1), 1.0, atol=1e-9)
    for key in ("n_matches", "degenerate", "small_baseline", "planar", "median_triangulation_deg"):
        assert vg.stats[key].shape == (6,)
    assert np.all(vg.inliers <= vg.stats["n_matches"])
    np.testing.assert_allclose(d.K, scene.K)
    with pytest.raises(IndexError, match="out of range"):
        d.correspondences(6)


def test_the_inliers_of_given_pairs_in_their_order(work):
    d = load_two_view(work[1])
    pick = d.vg.edges[[4, 1, 5]]
    offsets, kp = d.inliers_of(pick)
    for q, k in enumerate([4, 1, 5]):
        s, e = d.offsets[k], d.offsets[k + 1]
        np.testing.assert_array_equal(kp[offsets[q]:offsets[q + 1]], np.stack([d.kp_i[s:e], d.kp_j[s:e]], 1))
    assert offsets[-1] == len(kp) == sum(d.offsets[k + 1] - d.offsets[k] for k in (4, 1, 5)) > 0
    o0, kp0 = d.inliers_of(np.zeros((0, 2), int))
    assert o0.tolist() == [0] and kp0.shape == (0, 2)
    missing = np.array([[0, 1], [2, 9]])  # image 9 is not in the scene
    with pytest.raises(ValueError, match="not among"):
        d.inliers_of(missing)


def test_resume_skips_finished_work(work):
    _, w = work
    rec1 = TwoViewStage(w, Q).run()
    assert rec1.reused
    rec2 = TwoViewStage(w, Q).run(overwrite=True)
    assert not rec2.reused and rec2.summary["n_computed"] == 6 and rec2.fingerprint == rec1.fingerprint
    rec3 = TwoViewStage(w, TwoViewConfig(threshold_px=2.0, progress=False)).run()
    assert rec3.fingerprint != rec1.fingerprint and rec3.summary["n_computed"] == 6
    rec4 = TwoViewStage(w, Q).run()  # back to the default options: recomputed, same result as before
    assert not rec4.reused and rec4.fingerprint == rec1.fingerprint


def test_guided_option_re_estimates_weak_pairs_resumably_and_keeps_them_true(work_copy):
    """Every pair counts as weak (guided_max_inliers above any count): each is matched again in its own band; the
    stage records what guided matching added, stays within 1° of the truth, and resumes per pair."""
    scene = render_scene(n_views=4, seed=5, config=CFG)  # the module's scene: same seed, same cameras
    plain = load_two_view(work_copy)
    cfg = TwoViewConfig(guided=True, guided_max_inliers=100_000, progress=False)
    rec = TwoViewStage(work_copy, cfg).run()
    assert rec.summary["n_computed"] == 6 and rec.summary["n_guided"] >= 1
    d = load_two_view(work_copy)
    vg = d.vg
    assert vg.stats["n_guided"].shape == (6,) and np.all(vg.stats["n_guided"] >= 0)
    assert np.all(vg.inliers >= plain.vg.inliers - 3) and vg.inliers.sum() > plain.vg.inliers.sum()
    R_true = np.einsum("mij,mkj->mik", scene.R[vg.edges[:, 1]], scene.R[vg.edges[:, 0]])
    err, err_plain = (np.degrees(so3.angle_between(R, R_true)) for R in (vg.R_rel, plain.vg.R_rel))
    print("errors (deg), guided:", err.round(2), "plain:", err_plain.round(2))
    assert err.max() < 1.5 and np.median(err) < 0.5
    assert TwoViewStage(work_copy, cfg).run().reused
    assert TwoViewStage(work_copy, cfg.replace(guided_band_px=3.0)).fingerprint() != rec.fingerprint


def test_workers_recompute_nothing_and_change_no_result(work_copy):
    before = _snapshot(work_copy)
    assert TwoViewStage(work_copy, TwoViewConfig(workers=1, chunk_size=1, progress=False)).run().reused
    # every pair again in a pool of 2 processes, 2 pairs per chunk: the same arrays, bit for bit
    rec = TwoViewStage(work_copy, TwoViewConfig(workers=2, chunk_size=2, progress=False)).run(overwrite=True)
    assert rec.summary["n_computed"] == 6
    for a, b in zip(before, _snapshot(work_copy)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("damage", ["truncate", "garble"])
@pytest.mark.parametrize("name", [VIEWGRAPH, CORRESPONDENCES, "two_view.record.json"])
def test_damaged_result_is_healed_by_a_plain_rerun(work_copy, name, damage, caplog):
    before = _snapshot(work_copy)
    path = work_copy / name
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        del data[len(data) // 2:]
    else:  # same size: only the arrays (or the JSON) can tell
        mid = len(data) // 2
        data[mid:mid + 16] = bytes(b ^ 0x5A for b in data[mid:mid + 16])
    path.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        rec = TwoViewStage(work_copy, Q).run()
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and name in warnings[0] and "\n" not in warnings[0], warnings
    assert not rec.reused and rec.summary["n_computed"] == 0  # every pair came from the item store
    for a, b in zip(before, _snapshot(work_copy)):
        np.testing.assert_array_equal(a, b)
    caplog.clear()
    assert TwoViewStage(work_copy, Q).run().reused
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize("change", [
    lambda f: f.__setitem__("R", f["R"] * 0.5),                  # not a rotation
    lambda f: f.__setitem__("t", f["t"] * np.nan),
    lambda f: f["kp_i"].__setitem__(0, 10**6),                   # a keypoint the image lacks
    lambda f: f["kp_j"].__setitem__(0, -1),
    lambda f: f["x_i"].__setitem__((0, 0), np.nan),
    lambda f: f.__setitem__("n_inliers", f["n_inliers"] + 1),    # the inliers disagree with their count
    lambda f: f.__setitem__("kp_j", f["kp_j"][1:]),              # the inlier arrays disagree in length
    lambda f: f.pop("x_j"),                                      # a field missing
], ids=["R-scaled", "t-nan", "kp-past-the-end", "kp-negative", "x-nan", "count", "lengths", "x-missing"])
def test_a_stored_pair_that_reads_but_is_wrong_is_recomputed(work_copy, change, rerun_with_a_damaged_item):
    # The stage's output is lost and one stored pair reads well but is wrong: the recompute does not take it back
    # (it would crash, or hand the two-view BA and the tracks keypoints the image lacks), it estimates that pair
    # again, and every array is the first run's, bit for bit.
    from pipeline.geometry.two_view_stage import STORE

    cfg = TwoViewConfig(chunk_size=2, workers=1, progress=False)
    TwoViewStage(work_copy, cfg).run(overwrite=True)
    rerun_with_a_damaged_item(TwoViewStage(work_copy, cfg).run, lambda: _snapshot(work_copy), work_copy / STORE,
                              work_copy / VIEWGRAPH, change, "two-view results")


def test_readers_fail_in_one_line_naming_the_file(work_copy):
    record = work_copy / "two_view.record.json"
    kept = record.read_text()

    def record_agrees() -> None:  # the damage written into the record too: the reader must judge the content itself
        rec = json.loads(kept)
        rec["digests"] = {k: output_digest(work_copy / k) for k in rec["outputs"]}
        record.write_text(json.dumps(rec))

    for name in (VIEWGRAPH, CORRESPONDENCES):
        path = work_copy / name
        data = path.read_bytes()
        for bad, what, agree in ((data[: len(data) // 3], "bytes, not the", False),
                                 (b"x" * len(data), "has changed since it was written (its CRC-32", False),
                                 (b"x" * len(data), "is not an .npz archive", True),
                                 (b"PK\x03\x04" + bytes(len(data) - 4), "is not a", True)):
            path.write_bytes(bad)
            record_agrees() if agree else record.write_text(kept)
            with pytest.raises(CacheError) as e:
                load_two_view(work_copy)
            msg = str(e.value)
            assert str(path) in msg and what in msg and "\n" not in msg and "re-run" in msg, msg
            assert "pickle" not in msg
        path.write_bytes(data)
        record.write_text(kept)
    (work_copy / "two_view.record.json").write_text("{not json")
    with pytest.raises(CacheError, match="two_view.record.json is damaged"):
        load_two_view(work_copy)


def test_readers_survive_a_fuzzer(work_copy):
    """200 mutations of each file: the reader gives the same arrays or one project error, nothing else."""
    before = _snapshot(work_copy)
    rng = np.random.default_rng(12)
    for name in (VIEWGRAPH, CORRESPONDENCES):
        path = work_copy / name
        data = path.read_bytes()
        for _ in range(200):
            b = bytearray(data)
            kind = rng.integers(0, 10)
            if kind == 0:
                b = b[: rng.integers(0, len(b))]
            elif kind == 1:
                b += bytes(rng.integers(0, 256, rng.integers(1, 64), dtype=np.uint8))
            else:
                for pos in rng.integers(0, len(b), rng.integers(1, 5)):
                    b[pos] = int(rng.integers(0, 256))
            path.write_bytes(bytes(b))
            try:
                after = _snapshot(work_copy)
            except PipelineError as exc:
                assert "\n" not in str(exc)
                continue
            for x, y in zip(before, after):
                np.testing.assert_array_equal(x, y)
        path.write_bytes(data)


def test_two_view_without_matches(tmp_path):
    with pytest.raises(InputFileError, match="pipeline.features"):
        TwoViewStage(tmp_path, Q).run()
    with pytest.raises(InputFileError, match="pipeline.two_view"):
        load_two_view(tmp_path)


def test_cli_prints_the_view_graph_and_damage_is_one_line(work_copy):
    r = subprocess.run([sys.executable, "-m", "pipeline.two_view", "--work", str(work_copy), "-q"],
                       capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == str(work_copy / VIEWGRAPH), r.stderr
    r = subprocess.run([sys.executable, "-m", "pipeline.two_view", "--work", str(work_copy), "--threshold-px", "abc"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) == 1
    assert "threshold_px='abc' but expected a number" in r.stderr
