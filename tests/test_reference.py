"""Tests of pipeline.reference: the pycolmap incremental reconstruction used as a reference."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline import reference  # noqa: E402
from pipeline.core.errors import InputFileError  # noqa: E402
from pipeline.evaluate import match_reference, summarize  # noqa: E402
from pipeline.io.references import read_reference  # noqa: E402
from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402

SMALL = SceneConfig(width=320, height=240, focal=280.0, supersample=1)


def render_small(out: Path, n: int, seed: int) -> Path:
    render_scene(n, seed, out, config=SMALL)
    return out


@pytest.fixture(scope="session")
def scene6(tmp_path_factory) -> Path:
    return render_small(tmp_path_factory.mktemp("scene6"), 6, 0)


@pytest.fixture(scope="session")
def ref6(scene6, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ref6")
    reference.main(scene6, out)
    return out


@pytest.fixture(scope="session")
def two_groups(tmp_path_factory) -> Path:
    """Two rendered scenes (different textures) in one folder: 5 + 4 images that do not overlap."""
    folder = tmp_path_factory.mktemp("two_groups")
    for prefix, n, seed in (("a", 5, 3), ("b", 4, 11)):
        src = render_small(tmp_path_factory.mktemp(f"g{prefix}"), n, seed)
        for p in sorted(src.glob("*.png")):
            shutil.copy(p, folder / f"{prefix}_{p.name}")
    K = read_reference(src / "cameras.txt").K
    np.savetxt(folder / "K.txt", K[0] if K.ndim == 3 else K)
    return folder


@pytest.mark.slow
def test_reconstruction_matches_truth(scene6, ref6):
    res = reference.load_reference_result(ref6)
    s = res.summary
    assert s["n_registered"] == 6 and s["unregistered"] == {}
    assert s["known_K"] is True  # cameras.txt in the folder was found and passed
    truth = read_reference(scene6 / "cameras.txt")
    R_ref, mask = match_reference(res.names, truth.names, truth.R)
    m = summarize(res.R, R_ref, mask)
    assert m["n_evaluated"] == 6
    assert m["median_deg"] < 0.5 and m["max_deg"] < 1.0
    # the COLMAP model has the known intrinsics, not refined (refine_known_intrinsics=False)
    model = read_reference(ref6 / "model")
    assert sorted(model.names) == sorted(res.names)
    import pycolmap

    cams = list(pycolmap.Reconstruction(ref6 / "model").cameras.values())
    # COLMAP's pixel centres are at +0.5
    np.testing.assert_allclose(cams[0].params, [280.0, 280.0, truth.K[0][0, 2] + 0.5, truth.K[0][1, 2] + 0.5], atol=1e-9)


@pytest.mark.slow
def test_resume_does_no_work(scene6, ref6, monkeypatch):
    import pycolmap

    def boom(*a, **k):
        raise AssertionError("pycolmap was called although the result is cached")

    monkeypatch.setattr(pycolmap, "extract_features", boom)
    monkeypatch.setattr(pycolmap, "incremental_mapping", boom)
    before = (ref6 / "reference.json").stat().st_mtime_ns
    reference.main(scene6, ref6)
    assert (ref6 / "reference.json").stat().st_mtime_ns == before


@pytest.mark.slow
def test_interrupted_mapping_resumes_from_database(scene6, ref6, tmp_path, monkeypatch):
    import pycolmap

    out = tmp_path / "ref"
    shutil.copytree(ref6, out)
    # simulate an interruption after the database was built: no models, no summary
    for d in out.glob("models-*"):
        shutil.rmtree(d)
    (out / "reference.json").unlink()
    calls = {"map": 0}
    real_map = pycolmap.incremental_mapping

    def no_extract(*a, **k):
        raise AssertionError("the finished database was rebuilt")

    def counting_map(*a, **k):
        calls["map"] += 1
        return real_map(*a, **k)

    monkeypatch.setattr(pycolmap, "extract_features", no_extract)
    monkeypatch.setattr(pycolmap, "incremental_mapping", counting_map)
    reference.main(scene6, out)
    assert calls["map"] == 1
    a = reference.load_reference_result(out)
    b = reference.load_reference_result(ref6)
    assert a.names == b.names


@pytest.mark.slow
def test_several_models_largest_used_others_reported(two_groups, tmp_path):
    cfg = reference.ReferenceConfig(min_model_size=3)
    s = json.loads(reference.main(two_groups, tmp_path / "ref", config=cfg).read_text())
    assert s["n_models"] >= 2, s["models"]
    assert s["n_registered"] == s["models"][0]["n_registered"] >= s["models"][1]["n_registered"]
    # the largest model is group a (5 views); group b's images are reported, each with why
    assert all(n.startswith("a_") for n in s["registered"])
    b_names = [n for n in s["images"] if n.startswith("b_")]
    assert set(b_names) <= set(s["unregistered"])
    assert all("smaller model" in s["unregistered"][n] or "verified" in s["unregistered"][n] for n in b_names)
    assert set(s["models"][1]["left_out"]) >= set(s["registered"])


def test_too_few_images(tmp_path):
    (tmp_path / "imgs").mkdir()
    with pytest.raises(InputFileError, match="at least 2"):
        reference.main(tmp_path / "imgs", tmp_path / "out")


def test_missing_folder(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        reference.main(tmp_path / "nope", tmp_path / "out")


def test_bad_K_shape():
    with pytest.raises(InputFileError, match=r"expected \(3, 3\) or \(2, 3, 3\)"):
        reference.load_known_K(np.eye(2), ["a.png", "b.png"])


def test_K_file_missing_an_image(tmp_path):
    p = tmp_path / "cams.txt"
    p.write_text("a.png 100 100 50 40\n")
    with pytest.raises(InputFileError, match="no intrinsics for"):
        reference.load_known_K(p, ["a.png", "b.png"])


def test_K_forms(tmp_path):
    p = tmp_path / "K.txt"
    np.savetxt(p, np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]))
    K = reference.load_known_K(p, ["a.png", "b.png"])
    assert K.shape == (2, 3, 3) and K[1, 0, 0] == 100.0
    q = tmp_path / "cams.txt"
    q.write_text("b 200 200 50 40\na 100 100 50 40\n")  # matched by stem, any order
    K = reference.load_known_K(q, ["a.png", "b.png"])
    assert K[0, 0, 0] == 100.0 and K[1, 0, 0] == 200.0


def test_help():
    r = subprocess.run([sys.executable, "-m", "pipeline.reference", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--images" in r.stdout and "--K" in r.stdout


def test_cli_bad_input_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pipeline.reference", "--images", str(tmp_path / "none"),
                        "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_reuse_our_matches(scene6, tmp_path):
    from pipeline import features, matching

    work = tmp_path / "work"
    features.main(scene6, work, progress=False)
    matching.main(work, progress=False)
    cfg = reference.ReferenceConfig(use_our_matches=True)
    res = reference.load_reference_result(reference.main(scene6, tmp_path / "ref", config=cfg, work=work))
    assert res.summary["config"]["use_our_matches"] is True
    assert res.summary["n_registered"] == 6
    truth = read_reference(scene6 / "cameras.txt")
    R_ref, mask = match_reference(res.names, truth.names, truth.R)
    assert summarize(res.R, R_ref, mask)["median_deg"] < 0.5


def test_reuse_our_matches_needs_work(scene6, tmp_path):
    from pipeline.core.errors import PipelineError

    with pytest.raises(PipelineError, match="needs the WORK folder"):
        reference.main(scene6, tmp_path / "ref", config=reference.ReferenceConfig(use_our_matches=True))


def test_database_progress_counts_rows_as_they_are_written(tmp_path):
    """pycolmap's extraction and matching have no callback: their bars poll the database."""
    import sqlite3
    import time

    from pipeline.reference import _DatabaseProgress

    db = tmp_path / "d.db"
    missing = _DatabaseProgress(db, "keypoints", 5, "x", enabled=False)
    assert missing.count() is None  # not created yet: the poll is skipped, nothing raises
    con = sqlite3.connect(db)
    con.execute("CREATE TABLE keypoints (image_id INTEGER)")
    con.commit()
    with _DatabaseProgress(db, "keypoints", 5, "x", enabled=True, period=0.01) as p:
        for k in range(4):
            con.execute("INSERT INTO keypoints VALUES (?)", (k,))
            con.commit()
            time.sleep(0.03)
        assert 1 <= p.bar.n <= 4
    assert p.bar.n == 4  # the final poll on exit
    con.close()


def test_progress_polling_never_blocks_pycolmap(scene6, tmp_path, monkeypatch):
    """Polling the database every 2 ms while pycolmap extracts and matches loses no image.

    A plain read-only SQLite connection takes SHARED locks; COLMAP's writer, finding the
    database busy, dropped an image or aborted. The bars' connection is lock-free.
    """
    import sqlite3

    init = reference._DatabaseProgress.__init__
    monkeypatch.setattr(reference._DatabaseProgress, "__init__",
                        lambda self, *a, **k: init(self, *a, **{**k, "period": 0.002}))
    s = json.loads(reference.main(scene6, tmp_path / "ref", progress=True).read_text())
    db = next((tmp_path / "ref").glob("database-*.db"))
    con = sqlite3.connect(db)
    try:
        n_kp = con.execute("SELECT COUNT(*) FROM keypoints").fetchone()[0]
        n_match_rows = con.execute("SELECT COUNT(*) FROM matches").fetchone()[0]
    finally:
        con.close()
    assert n_kp == 6 and n_match_rows == 15
    assert s["n_registered"] == 6
