"""run.py tried as a new user would (issue 7, acceptance item 5)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline.synthetic.render import SceneConfig, render_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SMALL = SceneConfig(width=320, height=240, focal=280.0, supersample=1)




from pipeline import run  # noqa: E402


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "run.py"), *args, "-q"], capture_output=True, text=True)


def assert_one_line_error(r: subprocess.CompletedProcess, pattern: str) -> None:
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip()
    assert err.startswith("error:") and len(err.splitlines()) == 1, err
    assert pattern in err, err


@pytest.fixture(scope="session")
def messy(tmp_path_factory) -> Path:
    """5 rendered views, no K file (PNGs carry no EXIF), plus a text file named .jpg and a truncated JPEG."""
    src = tmp_path_factory.mktemp("src")
    render_scene(5, 2, src, config=SMALL)
    folder = tmp_path_factory.mktemp("messy")
    for p in sorted(src.glob("*.png")):
        shutil.copy(p, folder / p.name)
    (folder / "notes.jpg").write_text("this is not an image\n")
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.imread(str(src / "view_000.png")))
    (folder / "truncated.jpg").write_bytes(buf.tobytes()[: len(buf) // 3])
    (folder / "README.txt").write_text("not an image either\n")
    return folder


@pytest.fixture(scope="session")
def messy_run(messy, fast_config, tmp_path_factory):
    out = tmp_path_factory.mktemp("messy_out")
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    h = Keep(level=logging.WARNING)
    logging.getLogger().addHandler(h)
    try:
        run.main(messy, out, config=fast_config, quiet=True, reference=False)
    finally:
        logging.getLogger().removeHandler(h)
    return out, [r.getMessage() for r in records if r.levelno >= logging.WARNING]


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_one_line_error(run_cli(str(tmp_path / "empty"), "--out", str(tmp_path / "o")), "at least 2")


@pytest.fixture(scope="session")
def two_views(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("two_views")
    render_scene(2, 0, out, config=SMALL)
    return out


def test_single_image(tmp_path, two_views):
    folder = tmp_path / "one"
    folder.mkdir()
    shutil.copy(two_views / "view_000.png", folder)
    assert_one_line_error(run_cli(str(folder), "--out", str(tmp_path / "o")), "at least 2")


def test_folder_swallowed_by_methods_is_named_before_any_work(tmp_path, two_views):
    out = tmp_path / "o"
    r = run_cli("--methods", "irls", "sdp", str(two_views), "--out", str(out))
    assert_one_line_error(r, "put IMAGE_DIR before --methods")
    assert not out.exists(), "nothing is rendered or computed before the methods are checked"


def test_unknown_method_is_named_before_any_work(tmp_path, two_views):
    out = tmp_path / "o"
    assert_one_line_error(run_cli(str(two_views), "--methods", "irls,nope", "--out", str(out)), "unknown method 'nope'")
    assert not out.exists()


def test_missing_folder(tmp_path):
    assert_one_line_error(run_cli(str(tmp_path / "nope"), "--out", str(tmp_path / "o")), "does not exist")


def test_output_folder_not_writable(tmp_path, two_views):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")  # a folder cannot be created under a file, even by root
    assert_one_line_error(run_cli(str(two_views), "--out", str(blocker / "out")), "cannot write")
    # a read-only folder: permissions do not bind root, a read-only file system does (/proc even for root)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    target = ro / "out" if os.geteuid() != 0 else Path("/proc/rotavg-test-out")
    assert_one_line_error(run_cli(str(two_views), "--out", str(target)), "cannot write")


def test_bad_gt(tmp_path, two_views):
    (tmp_path / "gt.txt").write_text("garbage line\n")
    r = run_cli(str(two_views), "--out", str(tmp_path / "o"), "--gt", str(tmp_path / "gt.txt"))
    assert_one_line_error(r, "unrecognised reference")
    assert str(tmp_path / "gt.txt") in r.stderr and "expected 10" in r.stderr, r.stderr  # names the file and the layouts
    assert not (tmp_path / "o").exists(), "refused before any work"


@pytest.mark.slow
def test_unreadable_files_are_skipped_and_named(messy_run):
    out, warnings = messy_run
    m = json.loads((out / "metrics.json").read_text())
    assert m["input"]["n_images"] == 5  # the 5 good views, not notes.jpg nor truncated.jpg
    assert any("notes.jpg" in w for w in warnings) and any("truncated.jpg" in w for w in warnings), warnings
    assert m["methods"]["irls-l0.5"]["n_cameras"] == 5
    # every image of the folder is accounted for in metrics.json, the skipped ones with why
    assert m["input"]["n_skipped"] == 2 and {"notes.jpg", "truncated.jpg"} <= set(m["input"]["left_out"])
    assert "truncated JPEG" in m["input"]["left_out_why"]["truncated.jpg"]
    assert m["input"]["left_out_why"]["notes.jpg"].startswith("skipped by the features stage: it ")


def test_a_resumed_quiet_run_still_names_the_images_it_did_not_solve(messy, messy_run, fast_config, capsys):
    out, _ = messy_run
    run.main(messy, out, config=fast_config, quiet=True, reference=False)  # every stage reused
    err = capsys.readouterr().err
    (line,) = [ln for ln in err.splitlines() if "not solved" in ln]
    assert line.startswith("WARNING: 2 image(s) not solved in this frame: ") and "notes.jpg" in line
    assert "truncated.jpg" in line and line.endswith("(why: metrics.json input.left_out_why)")


@pytest.mark.slow
def test_no_K_no_exif_warns_and_estimates_the_focal(messy_run):
    out, warnings = messy_run
    assert any("focal" in w.lower() for w in warnings), warnings
    man = json.loads((out / "work" / "features.json").read_text())
    assert set(man["K_source"]) == {"default"}  # the start value: 1.2·max(w, h)
    K = np.array(man["K"])
    np.testing.assert_allclose(K[:, 0, 0], 1.2 * 320)
    m = json.loads((out / "metrics.json").read_text())
    assert any("estimated from the view graph (cameras stage)" in n for n in m["notes"])
    cams = json.loads((out / "work" / "cameras.json").read_text())  # where each focal used came from
    assert all(s.startswith("estimated:") for s in cams["K_source"]), cams["K_source"]
    np.testing.assert_allclose(np.array(cams["K"])[:, 0, 0], SMALL.focal, rtol=0.03)  # the rendered focal, not 384
    assert [f["source"] for f in m["intrinsics"]["focal"]] == sorted(set(cams["K_source"]), key=cams["K_source"].index)
    # no reference was asked for: the run still succeeds and says so
    assert any("no reference" in n for n in m["notes"])


@pytest.mark.slow
def test_two_groups_without_overlap(tmp_path_factory, fast_config):
    """Two scenes in one folder: the largest component is solved in OUT, the other in OUT/component-2/ (its own
    frame, its own metrics and report); a message names every image outside the largest and where it is solved."""
    folder = tmp_path_factory.mktemp("groups")
    for prefix, n, seed in (("a", 5, 3), ("b", 3, 11)):
        src = tmp_path_factory.mktemp(f"g{prefix}")
        render_scene(n, seed, src, config=SMALL)
        for p in sorted(src.glob("*.png")):
            shutil.copy(p, folder / f"{prefix}_{p.name}")
    np.savetxt(folder / "K.txt", [[280.0, 0, 159.5], [0, 280.0, 119.5], [0, 0, 1]])
    out = tmp_path_factory.mktemp("groups_out")
    r = subprocess.run([sys.executable, str(REPO / "run.py"), str(folder), "--out", str(out), "--config",
                        str(fast_config)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    b_names = [f"b_view_{k:03d}.png" for k in range(3)]
    assert sorted(m["input"]["left_out"]) == b_names
    assert all(m["input"]["left_out_why"][n] for n in b_names)  # each with its reason
    assert m["methods"]["irls-l0.5"]["n_cameras"] == 5
    assert "not connected" in r.stderr and all(n in r.stderr for n in b_names)
    assert any(all(n in note for n in b_names) for note in m["notes"])
    assert all("solved as component 2 (component-2/" in m["input"]["left_out_why"][n] for n in b_names)
    assert [c["names"] for c in m["components"]] == [b_names] and m["components"][0]["folder"] == "component-2"
    m2 = json.loads((out / "component-2" / "metrics.json").read_text())
    assert m2["methods"]["irls-l0.5"]["n_cameras"] == 3 and m2["input"]["n_cameras_graph"] == 3
    assert (out / "component-2" / "rotations" / "irls-l0.5.txt").is_file() and (out / "component-2" / "report.md").is_file()
    assert "component 2 of the view graph" in r.stderr
    comp = r.stderr.split("component 2 of the view graph", 1)[1]  # its console lines skip no number
    assert "[10/13] pycolmap reference: not run (ran once, on every image, above)" in comp
    # the peers ran once, on every image: component 2 is compared with the model of theirs that holds its images
    for label in ("pycolmap", "glomap"):
        assert m2["peers"][label]["n_registered"] == 3 and m2["peers"][label]["n_images"] == 3, m2["peers"][label]
        assert m2["methods"]["irls-l0.5"]["references"][label]["n_evaluated"] == 3
    # a component's graph lost: the view-graph stage's cache is damaged, so it is recomputed, not trusted
    (out / "component-2" / "viewgraph.npz").unlink()
    r = subprocess.run([sys.executable, str(REPO / "run.py"), str(folder), "--out", str(out), "--config",
                        str(fast_config), "--no-reference"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "component-2" / "viewgraph.npz").is_file()
    assert r.stderr.count("[11/13] pycolmap global (GLOMAP): not run (--no-reference)") == 2  # the run's, component 2's
    assert json.loads((out / "component-2" / "metrics.json").read_text())["methods"]["irls-l0.5"]["n_cameras"] == 3


def test_feature_notes_name_the_low_texture_images():
    """The report's notes say which images were detected differently for low texture (and once only)."""
    from types import SimpleNamespace

    from pipeline.plan import Plan

    plan = SimpleNamespace(notes=[])
    manifest = {"names": [f"v{i}.png" for i in range(8)], "skipped": [{"name": "x.png", "reason": "is empty"}],
                "lowered": {"v1.png": {"affine": False}, "v2.png": {"affine": True}}}
    Plan.note_features(plan, manifest)
    Plan.note_features(plan, manifest)  # a resumed run adds nothing twice
    assert plan.notes == [
        "image x.png left out: it is empty",
        "low texture: the contrast threshold was lowered for 2 of 8 images (v1.png, v2.png)",
        "texture-starved: 1 image(s) detected over simulated viewpoints (ASIFT): v2.png; expect fewer, less "
        "certain pairs there"]
    Plan.note_features(plan := SimpleNamespace(notes=[]), {"names": ["a.png"], "skipped": [], "lowered": {}})
    assert plan.notes == []



def test_the_default_scene_is_rendered_again_when_its_settings_change_or_a_view_is_damaged(tmp_path):
    """OUT/scene is a cache of the rendered default scene: other settings (fewer views), a damaged view or
    --overwrite render it again, with no view of the earlier scene left beside the new ones."""
    from pipeline.plan import SCENE_RECORD, prepare

    def plan_with(views: int, overwrite: bool = False):
        cfg = tmp_path / f"v{views}.yaml"
        cfg.write_text(f"run:\n  scene_views: {views}\n  plots: false\n")
        return prepare(None, tmp_path / "out", cfg, overwrite=overwrite, quiet=True)

    scene = tmp_path / "out" / "scene"
    p8 = plan_with(8)
    assert "render" in p8.times and len(list(scene.glob("view_*.png"))) == 8
    assert "render" not in plan_with(8).times  # intact and of these settings: reused
    p6 = plan_with(6)
    assert "render" in p6.times and sorted(q.name for q in scene.glob("view_*.png")) == [
        f"view_{k:03d}.png" for k in range(6)]
    assert json.loads((scene / SCENE_RECORD).read_text())["views"] == 6
    view = scene / "view_003.png"
    data = bytearray(view.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one byte, the size kept
    view.write_bytes(bytes(data))
    assert "render" in plan_with(6).times and "render" not in plan_with(6).times
    assert "render" in plan_with(6, overwrite=True).times
