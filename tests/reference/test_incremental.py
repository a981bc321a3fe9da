"""pipeline.reference.incremental: the pycolmap incremental reconstruction used as a reference (a stage)."""

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
from pipeline.core.errors import InputFileError, PipelineError  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import summarize  # noqa: E402
from pipeline.reference import database  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402
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
    res = reference.load_reference(ref6)
    s = res.info
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
    a = reference.load_reference(out)
    b = reference.load_reference(ref6)
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
        reference.known_intrinsics(np.eye(2), ["a.png", "b.png"])


def test_K_file_missing_an_image(tmp_path):
    p = tmp_path / "cams.txt"
    p.write_text("a.png 100 100 50 40\n")
    with pytest.raises(InputFileError, match="no intrinsics for"):
        reference.known_intrinsics(p, ["a.png", "b.png"])


def test_K_forms(tmp_path):
    p = tmp_path / "K.txt"
    np.savetxt(p, np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]))
    K = reference.known_intrinsics(p, ["a.png", "b.png"])
    assert K.shape == (2, 3, 3) and K[1, 0, 0] == 100.0
    q = tmp_path / "cams.txt"
    q.write_text("b 200 200 50 40\na 100 100 50 40\n")  # matched by stem, any order
    K = reference.known_intrinsics(q, ["a.png", "b.png"])
    assert K[0, 0, 0] == 100.0 and K[1, 0, 0] == 200.0


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
    res = reference.load_reference(reference.main(scene6, tmp_path / "ref", config=cfg, work=work))
    assert res.info["config"]["use_our_matches"] is True
    assert res.info["n_registered"] == 6
    truth = read_reference(scene6 / "cameras.txt")
    R_ref, mask = match_reference(res.names, truth.names, truth.R)
    assert summarize(res.R, R_ref, mask)["median_deg"] < 0.5


@pytest.mark.slow
def test_our_matches_of_images_named_with_spaces_are_verified(scene6, tmp_path):
    """COLMAP's pairs file is 'NAME1 NAME2' lines: verified through one, every pair of 'view 001 (copy).png' was
    dropped ("Image view does not exist") and the image left without a verified pair."""
    import pycolmap

    from pipeline import features, matching

    images = tmp_path / "images"
    images.mkdir()
    for k, p in enumerate(sorted(scene6.glob("*.png"))):
        shutil.copy(p, images / (f"view {k:03d} (copy).png" if k % 2 else p.name))
    work = tmp_path / "work"
    features.main(images, work, progress=False)
    matching.main(work, progress=False)
    names = sorted(p.name for p in images.glob("*.png"))
    db = tmp_path / "db.db"
    database.build_database(pycolmap, db, images, names, None, database.DatabaseConfig(use_our_matches=True), work)
    degree, _ = database.verified_degree(pycolmap, db)
    assert all(degree[nm] >= 3 for nm in names), degree


def test_reuse_our_matches_needs_work(scene6, tmp_path):
    from pipeline.core.errors import PipelineError

    with pytest.raises(PipelineError, match="needs the WORK folder"):
        reference.main(scene6, tmp_path / "ref", config=reference.ReferenceConfig(use_our_matches=True))


def test_database_progress_counts_rows_as_they_are_written(tmp_path):
    """pycolmap's extraction and matching have no callback: their bars poll the database."""
    import sqlite3
    import time

    from pipeline.reference.database import DatabaseProgress as _DatabaseProgress

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

    init = database.DatabaseProgress.__init__
    monkeypatch.setattr(database.DatabaseProgress, "__init__",
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


# ------------------------------------------------------------------ the stage contract and bad input
def _boom(*a, **k):
    raise AssertionError("pycolmap was called although the result is cached")


def _png_claiming(w: int, h: int) -> bytes:
    """A PNG whose header claims w×h pixels (8-bit grey) and whose data is one empty row."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * (w + 1))) + chunk(b"IEND", b""))


@pytest.mark.slow
def test_image_with_absurd_header_is_left_out_not_a_crash(scene6, tmp_path):
    """A PNG claiming 60000×60000 pixels made pycolmap abort (SIGABRT); it is left out, with why."""
    folder = tmp_path / "imgs"
    shutil.copytree(scene6, folder)
    (folder / "cameras.txt").unlink()  # pycolmap decodes every image itself (with a K file the K lookup failed first)
    (folder / "huge.png").write_bytes(_png_claiming(60000, 60000))
    r = subprocess.run([sys.executable, "-m", "pipeline.reference", "--images", str(folder), "--out",
                        str(tmp_path / "ref"), "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "ref" / "reference.json").read_text())
    assert s["n_registered"] == 6 and "huge.png" in s["images"]
    assert "60000x60000" in s["unregistered"]["huge.png"] and "not given to pycolmap" in s["unregistered"]["huge.png"]
    assert "huge.png" in r.stdout  # the command names it


def test_bad_reference_config_is_found_before_any_work(scene6, tmp_path):
    from pipeline import run
    from pipeline.core.errors import ConfigError

    for text, match in [("reference:\n  no_such_key: 1\n", r"\[reference\]: unknown key"),
                        ("reference:\n  max_image_size: many\n", r"\[reference\] max_image_size='many'"),
                        ("run:\n  reference: 'false'\n", r"\[run\] reference='false' but expected true or false"),
                        ("run:\n  plots: 'false'\n", r"\[run\] plots='false' but expected true or false")]:
        cfg = tmp_path / "bad.yaml"
        cfg.write_text(text)
        out = tmp_path / "out"
        with pytest.raises(ConfigError, match=match):
            run.main(scene6, out, config=cfg, quiet=True)
        assert not (out / "work").exists()  # nothing ran
    cfg.with_name("r.yaml").write_text("reference:\n  seed: -1\n")
    r = subprocess.run([sys.executable, "-m", "pipeline.reference", "--images", str(scene6), "--out",
                        str(tmp_path / "o"), "--config", str(cfg.with_name("r.yaml"))], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().startswith("error: [reference] seed=-1")
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


@pytest.mark.slow
def test_runtime_options_recompute_nothing_and_a_damaged_result_heals(scene6, ref6, tmp_path, monkeypatch, caplog):
    import pycolmap

    out = tmp_path / "ref"
    shutil.copytree(ref6, out)
    monkeypatch.setattr(pycolmap, "extract_features", _boom)
    monkeypatch.setattr(pycolmap, "incremental_mapping", _boom)
    before = (out / "reference.json").read_bytes()
    reference.main(scene6, out, config=reference.ReferenceConfig(num_threads=1), progress=False)  # runtime option
    assert (out / "reference.json").read_bytes() == before
    # a rotations file cut to 2 cameras is found, and rebuilt from the kept models (no pycolmap mapping)
    lines = (out / "rotations.txt").read_text().splitlines()
    (out / "rotations.txt").write_text("\n".join(lines[:-4]) + "\n")
    with caplog.at_level("WARNING"):
        res = reference.load_reference(reference.main(scene6, out, progress=False))
    assert "damaged" in caplog.text and len(res.names) == 6
    np.testing.assert_array_equal(res.R, reference.load_reference(ref6).R)
    # a result that disagrees with itself is not trusted by the reader either
    (out / "rotations.txt").write_text("\n".join(lines[:-4]) + "\n")
    with pytest.raises(PipelineError, match="disagree"):
        reference.load_reference(out)


_KILL = """
import os, signal, sys
import pycolmap
real = getattr(pycolmap, sys.argv[3])
def killed(*a, **k):
    db = pycolmap.Database.open(a[0])  # midway: the database is open, with its -wal and -shm
    if sys.argv[3] == "extract_features":
        db.write_camera(pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId.SIMPLE_PINHOLE, 1.0, 2, 2))
    os.kill(os.getpid(), signal.SIGKILL)
setattr(pycolmap, sys.argv[3], killed)
from pipeline.reference import main
main(sys.argv[1], sys.argv[2], progress=False)
"""


@pytest.mark.slow
def test_killed_reference_leaves_nothing_a_later_run_does_not_remove(scene6, tmp_path):
    from pipeline.core.atomic import TMP_TAG

    out = tmp_path / "ref"
    for step in ("extract_features", "incremental_mapping"):  # killed while building the database, then mapping
        r = subprocess.run([sys.executable, "-c", _KILL, str(scene6), str(out), step], capture_output=True, text=True)
        assert r.returncode == -9, r.stderr
        left = [p.name for p in out.iterdir()]
        assert any(TMP_TAG in n for n in left), left  # the kill did leave temporaries
        assert any(n.endswith("-wal") for n in left), left
    reference.main(scene6, out, progress=False)
    names = sorted(p.name for p in out.iterdir())
    assert not [n for n in names if TMP_TAG in n or n.startswith(".") or n.endswith(("-wal", "-shm"))], names
    key = lambda n: n.split("-", 1)[-1].split(".")[0]  # noqa: E731
    assert [n.split("-")[0] for n in names] == ["database", "database", "model", "models", "reference.json",
                                                 "reference.record.json", "rotations.txt"], names
    assert key(names[0]) == key(names[1])
    assert len(reference.load_reference(out).names) == 6
    # pycolmap killed with the finished database open (e.g. a run with --overwrite): a run that reuses
    # the result folds the database's -wal/-shm back into it
    opened = "import os, signal, sys, pycolmap; db = pycolmap.Database.open(sys.argv[1]); os.kill(os.getpid(), 9)"
    subprocess.run([sys.executable, "-c", opened, str(out / names[0])])
    assert (out / (names[0] + "-wal")).exists()
    reference.main(scene6, out, progress=False)
    assert sorted(p.name for p in out.iterdir()) == names
