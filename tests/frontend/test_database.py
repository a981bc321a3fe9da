"""COLMAP databases in: a pycolmap database of a rendered scene through ``run.py --database``, and bad databases."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pycolmap  # a hard dependency: a broken install fails here, it is not skipped
import pytest

from pipeline.core.errors import ConfigError, InputFileError
from pipeline.frontend import colmap_db
from pipeline.frontend.database_stage import check_database, database_pairs
from pipeline.frontend.feature_stage import load_features
from pipeline.frontend.matching_stage import load_matches
from pipeline.frontend.pairs import select_pairs
from pipeline.reference.database import pinhole_params
from pipeline.run import main as run_main
from pipeline.run import main_cli as run_cli
from pipeline.synthetic.render import SceneConfig, render_scene

SCENE = SceneConfig(width=320, height=240, focal=280.0, texture_px_per_unit=150.0)


def _database(db: Path, images: Path, K: np.ndarray | None, match: bool = True, names: list[str] | None = None) -> Path:
    """What a user brings: pycolmap.extract_features (+ match_exhaustive) on the image folder."""
    reader = pycolmap.ImageReaderOptions()
    if K is not None:
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(f"{v:.10g}" for v in pinhole_params(K))
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = 1
    pycolmap.extract_features(db, images, image_names=names or [], camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
    if match:
        opt = pycolmap.FeatureMatchingOptions()
        opt.num_threads = 1
        pycolmap.match_exhaustive(db, matching_options=opt, device=pycolmap.Device.cpu)
    return db


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return render_scene(n_views=6, seed=3, out=tmp_path_factory.mktemp("scene"), config=SCENE)


@pytest.fixture(scope="module")
def db(scene, tmp_path_factory):
    return _database(tmp_path_factory.mktemp("db") / "database.db", scene.out, scene.K[0])


@pytest.fixture(scope="module")
def run_db(scene, db, tmp_path_factory, fast_config):
    out = tmp_path_factory.mktemp("run")
    metrics = run_main(scene.out, out, fast_config, gt=scene.out / "cameras.txt", reference=False, quiet=True,
                       database=db)
    return out, metrics


def _verified_in_sqlite(path: Path) -> dict[tuple[int, int], int]:
    """``(image_id1, image_id2) → inlier count`` of the pairs with inlier matches, read from the database file's own
    ``two_view_geometries`` table with sqlite3 (COLMAP's pair id: ``id1 · 2147483647 + id2``, ``id1 < id2``): a
    reference that shares nothing with the reader under test."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT pair_id, rows FROM two_view_geometries WHERE rows > 0").fetchall()
    finally:
        con.close()
    return {(int(pid) // 2147483647, int(pid) % 2147483647): int(n) for pid, n in rows}


def _median_error(metrics: Path) -> dict[str, float]:
    import json

    m = json.loads(metrics.read_text())
    return {k: v["median_deg"] for k, v in m["methods"].items()}


def test_run_from_database_gives_rotations_close_to_truth(run_db, db):
    out, metrics = run_db
    err = _median_error(metrics)
    assert err and max(err.values()) < 0.3, err
    work = out / "work"
    fs, ms = load_features(work, descriptors=False), load_matches(work)
    assert len(fs.names) == 6 and all(s.startswith("database:PINHOLE") for s in fs.K_source)
    np.testing.assert_allclose(fs.K[0], [[280, 0, 159.5], [0, 280, 119.5], [0, 0, 1]], atol=1e-9)
    # the matches are the database's verified inliers, pair for pair
    verified = _verified_in_sqlite(db)
    assert len(ms.pairs) == len(verified) > 0
    assert sorted(len(m) for m in ms.matches) == sorted(verified.values())
    rec = __import__("json").loads((work / "features.record.json").read_text())
    assert rec["inputs"]["database"] == colmap_db.database_fingerprint(db)


def test_database_run_resumes_and_reading_leaves_the_database_unchanged(run_db, scene, db, fast_config):
    out, _ = run_db
    raw, mtime = db.read_bytes(), db.stat().st_mtime_ns
    check_database(db, scene.out)
    before = {p: p.stat().st_mtime_ns for p in (out / "work").glob("*.npz")}
    run_main(scene.out, out, fast_config, gt=scene.out / "cameras.txt", reference=False, quiet=True, database=db)
    assert {p: p.stat().st_mtime_ns for p in (out / "work").glob("*.npz")} == before
    assert db.read_bytes() == raw and db.stat().st_mtime_ns == mtime  # pycolmap only ever opens a private copy


def test_a_sqlite_file_that_is_not_colmap_is_left_as_it_was(tmp_path):
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as con:
        con.execute("CREATE TABLE notes (x INTEGER)")
    con.close()
    raw = other.read_bytes()
    try:
        images = colmap_db.read_images(other)
    except InputFileError as exc:
        assert str(other) in str(exc)
        images = []
    assert images == []  # nothing COLMAP's in it (check_database refuses it: test_bad_database_...)
    assert other.read_bytes() == raw  # pycolmap would have added COLMAP's tables to it


def test_database_pair_selector_with_our_features(db, scene, tmp_path):
    names = sorted(p.name for p in scene.out.glob("*.png"))
    # a copy in which one pair's geometry holds no inlier match: it is not a verified pair
    copy = Path(shutil.copy(db, tmp_path / "one_empty.db"))
    with sqlite3.connect(copy) as con:
        pid = con.execute("SELECT pair_id FROM two_view_geometries WHERE rows > 0 ORDER BY pair_id LIMIT 1").fetchone()[0]
        con.execute("UPDATE two_view_geometries SET rows = 0, data = NULL WHERE pair_id = ?", (pid,))
    con.close()
    for path, n_empty in ((db, 0), (copy, 1)):
        pairs = select_pairs(f"database:{path}", names)
        verified = {tuple(sorted((a - 1, b - 1))) for a, b in _verified_in_sqlite(path)}  # ids 1.. in name order
        assert {tuple(p) for p in pairs.tolist()} == verified and len(verified) == 15 - n_empty
        np.testing.assert_array_equal(database_pairs(path, names), pairs)
    with pytest.raises(ConfigError, match="--database DB"):
        select_pairs("database", names)


def test_distorted_keypoints_are_undistorted_by_the_camera_model(db, tmp_path):
    copy = shutil.copy(db, tmp_path / "radial.db")
    d = pycolmap.Database.open(str(copy))
    cam = d.read_all_cameras()[0]
    radial = pycolmap.Camera.create_from_model_name(cam.camera_id, "SIMPLE_RADIAL", 280.0, cam.width, cam.height)
    radial.params = [280.0, 160.0, 120.0, 0.08]
    d.update_camera(radial)
    d.close()
    image = colmap_db.read_images(copy)[0]
    raw = np.asarray(pycolmap.Database.open(str(copy)).read_keypoints(image.image_id), np.float64)[:, :2]
    with colmap_db.open_database(copy) as d:
        und = colmap_db.keypoints_for_image(d, copy, image)["keypoints"].astype(np.float64)
    K = colmap_db.pinhole_K(image.model, image.params, "test")
    xy = (und - K[:2, 2]) / K[0, 0]
    back = radial.img_from_cam(np.c_[xy, np.ones(len(xy))])  # distort again with pycolmap's model
    np.testing.assert_allclose(back, raw, atol=2e-3)
    corner = np.argmax(np.linalg.norm(raw - [160, 120], axis=1))
    assert np.linalg.norm(und[corner] - (raw[corner] - 0.5)) > 1.0  # the distortion was really removed


@pytest.fixture(scope="module")
def bad_dbs(scene, tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    (d / "text.db").write_text("not a database\n")
    con = sqlite3.connect(d / "other.db")
    con.execute("CREATE TABLE t (x INTEGER)")
    con.commit()
    con.close()
    other = d / "other_images"
    other.mkdir()
    for k, n in enumerate(scene.names[:3]):
        shutil.copy(scene.out / n, other / f"photo_{k}.png")
    _database(d / "elsewhere.db", other, scene.K[0])
    _database(d / "unmatched.db", scene.out, scene.K[0], match=False, names=scene.names[:3])
    return d


@pytest.mark.parametrize("name, needle", [
    ("missing.db", "does not exist"),
    ("text.db", "not a COLMAP database (not an SQLite file)"),
    ("other.db", "holds 0 image(s)"),
    ("elsewhere.db", "but 0 of them are in"),
    ("unmatched.db", "has no verified matches"),
])
def test_bad_database_is_one_line_up_front(bad_dbs, scene, tmp_path, capsys, name, needle):
    rc = run_cli([str(scene.out), "--database", str(bad_dbs / name), "--out", str(tmp_path / "o"), "-q",
                  "--no-reference"])
    text = capsys.readouterr().err
    err = [ln for ln in text.splitlines() if ln.startswith("error:")]
    assert rc == 2 and len(err) == 1 and needle in err[0] and "Traceback" not in text, text
    assert str(bad_dbs / name) in err[0]
    assert not (tmp_path / "o" / "work").exists()  # refused before any stage ran


def test_database_needs_an_image_folder_and_no_K(db, scene, tmp_path, capsys):
    assert run_cli(["--database", str(db), "--out", str(tmp_path / "o"), "-q"]) == 2
    assert run_cli([str(scene.out), "--database", str(db), "--K", str(scene.out / "cameras.txt"), "--out",
                    str(tmp_path / "o"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 2 and "drop --K" in err
    with pytest.raises(InputFileError, match="not an SQLite file"):
        colmap_db.read_images(scene.out / "cameras.txt")


def test_database_run_on_a_local_dask_cluster_gives_the_same_view_graph(run_db, scene, db, fast_config, tmp_path):
    import psutil

    before = {p.pid for p in psutil.Process().children(recursive=True)}
    metrics = run_main(scene.out, tmp_path / "dask", fast_config, gt=scene.out / "cameras.txt", reference=False,
                       quiet=True, database=db, executor="dask")
    left = [p for p in psutil.Process().children(recursive=True) if p.pid not in before  # Python's own
            and "multiprocessing.resource_tracker" not in " ".join(p.cmdline())]  # tracker lives with this process
    assert not left, [" ".join(p.cmdline())[:300] for p in left]  # workers gone
    assert not any(p.name.startswith("dask-") for p in tmp_path.rglob("*"))  # no scratch space in the output
    for out in ("two_view.npz", "viewgraph.npz"):
        with np.load(run_db[0] / "work" / out) as a, np.load(tmp_path / "dask" / "work" / out) as b:
            assert a.files == b.files
            for k in a.files:
                np.testing.assert_array_equal(a[k], b[k], err_msg=f"{out} {k}")
    got, want = _median_error(metrics), _median_error(run_db[1])
    exact = {m for m in want if not m.endswith("+refine")}  # pycolmap's BA threads vary in the last digits
    assert {m: got[m] for m in exact} == {m: want[m] for m in exact} and got.keys() == want.keys()
    assert all(got[m] == pytest.approx(want[m], rel=1e-9) for m in want)
