"""The refine stage on a rendered scene: accuracy, the COLMAP model, caching, failures kept visible, CLI."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.atomic import write_json
from pipeline.core.errors import InputFileError, PipelineError
from pipeline.io.rotations import read_rotations
from pipeline.refine.refine import RefineConfig
from pipeline.refine.stage import RefineStage, recommended_start, refine_notes, run_refine


@pytest.fixture(scope="session")
def rendered_run(tmp_path_factory) -> Path:
    """run.py on 8 rendered views (truth known), IRLS-H only, no pycolmap peers, no plots: refined by default."""
    from pipeline import run
    from pipeline.synthetic.render import render_scene

    root = tmp_path_factory.mktemp("refine")
    render_scene(8, 0, root / "scene")
    cfg = root / "noplots.yaml"
    cfg.write_text("run:\n  plots: false\n")
    run.main(root / "scene", root / "out", config=cfg, methods=["irls-h"], gt=root / "scene" / "cameras.txt",
             reference=False, quiet=True)
    return root / "out"


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


@pytest.mark.slow
def test_rendered_scene_refines_below_a_hundredth_of_a_degree(rendered_run):
    m = json.loads((rendered_run / "metrics.json").read_text())
    r = m["methods"]["irls-h-l0.5+refine"]
    assert r["status"] == "ok" and r["n_refined"] == r["n_cameras"] == 8 and r["start"] == "irls-h-l0.5"
    assert r["median_deg"] <= 0.01, r["median_deg"]
    assert r["median_deg"] <= m["methods"]["irls-h-l0.5"]["median_deg"]
    assert 0 < r["sigma_median_deg"] < 0.05 and len(r["uncertainty_deg"]) == 8
    assert m["stages"]["refine"] > 0 and "refine" in m["stages"]
    text = (rendered_run / "report.md").read_text()
    assert "## Refinement (irls-h-l0.5+refine)" in text and "refine ok (8/8 refined)" in text


@pytest.mark.slow
def test_the_model_opens_in_pycolmap_with_every_registered_image_and_a_point_cloud(rendered_run):
    import pycolmap

    from pipeline.reference.truth import read_reference

    rec = pycolmap.Reconstruction(rendered_run / "sparse")
    names, _ = read_rotations(rendered_run / "rotations" / "irls-h-l0.5+refine.txt")
    assert sorted(rec.images[i].name for i in rec.reg_image_ids()) == sorted(names)
    assert rec.num_points3D() > 500 and rec.compute_mean_reprojection_error() < 1.0
    K = read_reference(rendered_run.parent / "scene" / "cameras.txt").K
    for cam in rec.cameras.values():  # the known K, constant, in COLMAP's pixel convention
        np.testing.assert_allclose(cam.params, [K[0][0, 0], K[0][1, 1], K[0][0, 2] + 0.5, K[0][1, 2] + 0.5])
    s = json.loads((rendered_run / "rotations" / "irls-h-l0.5+refine.json").read_text())
    cov = np.array(s["cameras"][names[0]]["cov_rad2"]).reshape(3, 3)
    assert np.all(np.linalg.eigvalsh(cov) > 0) and s["model"] == "sparse"


@pytest.mark.slow
def test_reused_when_intact_recomputed_when_damaged(rendered_run, tmp_path, monkeypatch, caplog):
    out = _copy(rendered_run, tmp_path / "out")
    assert RefineStage(out, RefineConfig(num_threads=1)).run().reused  # runtime option: nothing to redo
    path = out / "rotations" / "irls-h-l0.5+refine.txt"
    before = read_rotations(path)[1]
    path.write_text("\n".join(path.read_text().splitlines()[:-3]) + "\n")  # cut to 5 cameras
    with caplog.at_level("WARNING"):
        rec = RefineStage(out, RefineConfig(preset="glomap")).run()
    assert not rec.reused and "damaged" in caplog.text
    np.testing.assert_allclose(read_rotations(path)[1], before, atol=1e-9)


@pytest.mark.slow
def test_bundle_adjustment_made_to_fail_is_reported_and_the_averaged_rotations_kept(
        rendered_run, tmp_path, points_removed_after_positioning):
    out = _copy(rendered_run, tmp_path / "out")
    res = run_refine(out, RefineConfig(preset="fast"), ["irls-h-l0.5"], overwrite=True)
    s = res["irls-h-l0.5+refine"]["stats"]
    assert s["status"] == "failed" and s["n_refined"] == 0 and s["model"] is None
    assert any("bundle adjustment failed" in w and "averaged rotations are kept" in w for w in s["warnings"])
    n1, R1 = read_rotations(out / "rotations" / "irls-h-l0.5+refine.txt")
    n0, R0 = read_rotations(out / "rotations" / "irls-h-l0.5.txt")
    assert n1 == n0 and np.array_equal(R1, R0)  # the averaged rotations, and the averaged file untouched
    assert not (out / "sparse").exists()  # no model that would not match these rotations
    notes = refine_notes(res)
    assert any("status failed" in n for n in notes) and any("the refinement failed" in n for n in notes)


@pytest.mark.slow
def test_change_guard_keeps_both(rendered_run, tmp_path):
    out = _copy(rendered_run, tmp_path / "out")
    res = run_refine(out, RefineConfig(preset="fast", max_change_deg=1e-6), ["irls-h-l0.5"], overwrite=True)
    s = json.loads((out / "rotations" / "irls-h-l0.5+refine.json").read_text())
    assert s["status"] == "partial" and s["n_refined"] == 0 and len(s["kept_averaged"]) == 8
    assert all("max_change_deg" in why for why in s["kept_averaged"].values())
    assert s["anchored"] == []  # a camera the guard keeps is not chained from its neighbours: it keeps the averaged
    n1, R1 = read_rotations(out / "rotations" / "irls-h-l0.5+refine.txt")
    _, R0 = read_rotations(out / "rotations" / "irls-h-l0.5.txt")
    assert np.array_equal(R1, R0)
    both = [np.array(c["refined_cam_from_world"]).reshape(3, 3) for c in s["cameras"].values()]
    assert len(both) == 8 and all(abs(np.linalg.det(R) - 1) < 1e-9 for R in both)  # the refined ones, reported
    assert len(refine_notes(res)) == 1 + 8


def test_recommended_start():
    assert recommended_start(["irls-l0.5", "irls-h-l0.5", "sdp-cso3"])[0] == "irls-h-l0.5"
    assert recommended_start(["sdp-cso3", "irls-l0.5"])[0] == "irls-l0.5"
    label, why = recommended_start(["weiszfeld"])
    assert label == "weiszfeld" and "first method run" in why
    with pytest.raises(PipelineError, match="no averaged rotations to refine"):
        recommended_start([])


def test_a_start_that_did_not_run_is_named(tmp_path):
    (tmp_path / "rotations").mkdir()
    with pytest.raises(InputFileError, match="has no rotations of 'sdp-cso3', the refinement's start"):
        RefineStage(tmp_path, RefineConfig(start="sdp-cso3")).run()


def test_help_and_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pipeline.refine", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--max-change-deg" in r.stdout and "--preset" in r.stdout
    r = subprocess.run([sys.executable, "-m", "pipeline.refine", "--out", str(tmp_path / "none")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("error:") and len(r.stderr.strip().splitlines()) == 1


def test_no_rotations_to_refine_names_the_folder_and_how_to_fill_it(tmp_path):
    """The README's stage chain writes `pipeline.average ... --out irls.txt`; `pipeline.refine --out OUT` then said
    only 'no averaged rotations to refine: run an averaging method first', not where it looked nor how to put a
    method's rotations there."""
    r = subprocess.run([sys.executable, "-m", "pipeline.refine", "--out", str(tmp_path / "OUT"), "--work",
                        str(tmp_path / "work")], capture_output=True, text=True)
    line = r.stderr.strip()
    assert r.returncode == 2 and len(line.splitlines()) == 1, r.stderr
    assert str(tmp_path / "OUT" / "rotations") in line and "pipeline.average" in line and "irls-l0.5.txt" in line, line


def test_tracks_come_only_from_the_pairs_the_checked_view_graph_kept(rendered_run, tmp_path):
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.refine.stage import load_inputs

    rot = rendered_run / "rotations" / "irls-h-l0.5.txt"
    checked = ViewGraph.load(rendered_run / "viewgraph.npz", allow_isolated=True)
    every, _, _ = load_inputs(rendered_run / "work", rot)  # no checked graph: every two-view BA pair
    kept, _, _ = load_inputs(rendered_run / "work", rot, rendered_run / "viewgraph.npz", weak_pairs=False)
    assert len(kept["edges"]) == checked.n_edges <= len(every["edges"])
    a, b = checked.edges[0]
    fewer = ViewGraph(checked.names, checked.edges[1:], checked.R_rel[1:], H=checked.H[1:],
                      inliers=None if checked.inliers is None else checked.inliers[1:],
                      stats={k: np.asarray(v)[1:] for k, v in checked.stats.items()}, allow_isolated=True)
    fewer.save(tmp_path / "viewgraph.npz")
    got, _, _ = load_inputs(rendered_run / "work", rot, tmp_path / "viewgraph.npz")
    names = every["names"]
    pairs = {(names[i], names[j]) for i, j in got["edges"].tolist()}
    assert len(got["edges"]) == checked.n_edges - 1 and (checked.names[a], checked.names[b]) not in pairs
    assert got["match_offsets"][-1] == len(got["matches"]) < kept["match_offsets"][-1]
    # the intrinsics are the cameras stage's, K from the rendered scene's file: known, kept constant
    assert kept["known_K"].all()


def test_a_pair_rejected_only_as_weak_makes_tracks_and_no_other_rejected_pair_does(rendered_run, tmp_path):
    # The view graph's summary says which rejected pairs' matches may make tracks (``tracks``: those rejected only
    # because their rotation is poorly determined). Take a kept pair out of the checked graph and mark it rejected
    # in a copy of the summary: as weak (tracks true) its matches come back; as rejected for another reason
    # (tracks false) they do not; with weak_pairs off neither does.
    import json

    from pipeline.core.viewgraph import ViewGraph
    from pipeline.refine.stage import load_inputs

    rot = rendered_run / "rotations" / "irls-h-l0.5.txt"
    checked = ViewGraph.load(rendered_run / "viewgraph.npz", allow_isolated=True)
    a, b = checked.edges[0]
    pair = [checked.names[a], checked.names[b]]
    fewer = ViewGraph(checked.names, checked.edges[1:], checked.R_rel[1:], H=checked.H[1:],
                      inliers=None if checked.inliers is None else checked.inliers[1:],
                      stats={k: np.asarray(v)[1:] for k, v in checked.stats.items()}, allow_isolated=True)
    summary = json.loads((rendered_run / "viewgraph.json").read_text())
    assert all("tracks" in r for r in summary["pairs"] if r["step"] not in ("two_view", "two_view_ba"))

    def inputs(tracks: bool, weak_pairs: bool = True) -> set:
        out = tmp_path / f"out-{tracks}-{weak_pairs}"
        out.mkdir()
        fewer.save(out / "viewgraph.npz")
        rows = [r for r in summary["pairs"] if r["pair"] != pair and r["pair"] != pair[::-1]]
        rows.append({"pair": pair, "status": "rejected", "step": "acceptance", "tracks": tracks,
                     "reason": "rotation poorly determined (weak H)" if tracks else "inlier ratio too low"})
        (out / "viewgraph.json").write_text(json.dumps({**summary, "pairs": rows}))
        got, _, _ = load_inputs(rendered_run / "work", rot, out / "viewgraph.npz", weak_pairs=weak_pairs)
        return {(got["names"][i], got["names"][j]) for i, j in got["edges"].tolist()}

    base = {(checked.names[i], checked.names[j]) for i, j in checked.edges[1:].tolist()}
    extra = {(r["pair"][0], r["pair"][1]) for r in summary["pairs"] if r.get("tracks") and r["status"] == "rejected"}
    assert inputs(True) == base | extra | {tuple(pair)}
    assert inputs(False) == base | extra
    assert inputs(True, weak_pairs=False) == base



@pytest.mark.slow
def test_an_image_the_view_graph_left_out_with_weak_pairs_is_placed_refined_and_said_so(rendered_run, tmp_path,
                                                                                          monkeypatch):
    # The last image taken out of the checked graph and of the averaged rotations, its pairs marked rejected as weak
    # (their matches make tracks) and itself left out: the refinement starts it from those pairs and refines it,
    # after the start's cameras in its rotations file, and its stats say so; place_left_out false leaves it out.
    from pipeline.core.viewgraph import ViewGraph
    from pipeline.evaluation.compare import match_reference
    from pipeline.evaluation.metrics import rotation_errors_deg
    from pipeline.io.rotations import write_rotations
    from pipeline.reference.truth import read_reference

    out = _copy(rendered_run, tmp_path / "out")
    checked = ViewGraph.load(out / "viewgraph.npz", allow_isolated=True)
    gone = checked.names[-1]
    keep = ~np.any(checked.edges == len(checked.names) - 1, axis=1)
    ViewGraph(checked.names, checked.edges[keep], checked.R_rel[keep], H=checked.H[keep],
              inliers=None if checked.inliers is None else checked.inliers[keep],
              stats={k: np.asarray(v)[keep] for k, v in checked.stats.items()}, allow_isolated=True
              ).save(out / "viewgraph.npz")
    summary = json.loads((out / "viewgraph.json").read_text())
    for r in summary["pairs"]:
        if gone in r["pair"]:
            r.update(status="rejected", step="acceptance", tracks=True, reason="rotation poorly determined (weak H)")
    summary["left_out"] = {gone: "no accepted image pair (7 pair(s) rejected: rotation poorly determined ×7)"}
    (out / "viewgraph.json").write_text(json.dumps(summary))
    names, R = read_rotations(out / "rotations" / "irls-h-l0.5.txt")
    write_rotations(out / "rotations" / "irls-h-l0.5.txt", names[:-1], R[:-1])
    monkeypatch.setattr(RefineStage, "inputs", lambda self: {"edited": "by this test"})  # upstream records as they were
    stage = RefineStage(out, RefineConfig(num_threads=1))
    rec = stage.run(overwrite=True)
    got, R_got = read_rotations(stage.rotations_path)
    assert list(got) == list(names[:-1]) + [gone] and rec.summary["n_cameras"] == 8
    s = json.loads(stage.stats_path.read_text())
    assert list(s["placed"]) == [gone] and "placed by the refinement alone" in s["placed"][gone]
    assert s["cameras"][gone]["refined"] and s["n_refined"] == 8
    truth = read_reference(rendered_run.parent / "scene" / "cameras.txt")
    R_true, mask = match_reference(list(got), truth.names, truth.R)
    assert rotation_errors_deg(R_got, R_true, mask).max() < 0.05
    assert RefineStage(out, RefineConfig(num_threads=1)).run().reused  # its own verify accepts the placed image
    assert any(gone in n and "placed by the refinement alone" in n for n in refine_notes(run_refine(out, RefineConfig(num_threads=1))))
    RefineStage(out, RefineConfig(place_left_out=False)).run()
    assert list(read_rotations(stage.rotations_path)[0]) == list(names[:-1])
    assert json.loads(stage.stats_path.read_text())["placed"] == {}

def test_the_report_says_what_the_principal_point_probe_decided():
    base = {"start_why": "the recommended method", "status": "ok", "n_refined": 9, "n_cameras": 9, "model": "sparse",
            "focal_refined": False, "kept_averaged": {}}
    held = dict(base, principal_point_fixed_why="a camera without a K file has 1 image(s) (< 3)",
                principal_point_probe={"decision": "held at the image centres: the residuals with them held are 1.02× "
                                                   "those with them refined (< principal_point_misfit = 1.3)"})
    refined = dict(base, principal_point_probe={"decision": "principal points refined for 7 of 8 image(s)"},
                   principal_point={"3": {"px": [560.0, 390.0], "sd_px": 2.1}})
    (n_held,) = [n for n in refine_notes({"a+refine": {"stats": held}}) if "principal point" in n]
    assert "kept at the image centres: a camera without a K file" in n_held and "probed: held" in n_held
    notes = refine_notes({"a+refine": {"stats": refined}})
    assert "a+refine: principal points refined for 7 of 8 image(s)" in notes
    assert "a+refine: principal point of camera 3 refined to (560.0, 390.0) px, standard deviation 2.10 px" in notes


def test_a_principal_point_sd_that_is_not_finite_is_said_so_when_read_back(tmp_path):
    """principal_point="refined" keeps a principal point whose covariance is singular (sd inf): the stats file (strict
    JSON) holds null for its sd, and the notes (which raised TypeError formatting it) say it has no finite one."""
    stats = {"start_why": "the recommended method", "status": "ok", "n_refined": 9, "n_cameras": 9, "model": "sparse",
             "kept_averaged": {}, "principal_point": {"3": {"px": [560.0, 390.0], "sd_px": float("inf")}}}
    back = json.loads(write_json(tmp_path / "a+refine.json", stats).read_text())
    assert back["principal_point"]["3"]["sd_px"] is None
    assert "a+refine: principal point of camera 3 refined to (560.0, 390.0) px, no finite standard deviation" in \
        refine_notes({"a+refine": {"stats": back}})


def test_a_camera_the_refinement_did_not_refine_has_no_ba_sigma_in_the_stats():
    """refine_stats: the BA covariance of a camera kept at its averaged (or chained) rotation is not its uncertainty:
    no σ, no covariance, and the median σ is of the refined cameras only (castle internet: 0026.jpg, chained from
    its neighbours, showed the model's 0.25°)."""
    from types import SimpleNamespace

    from pipeline.refine.refine import RefineConfig
    from pipeline.refine.stage import refine_stats

    n = 4
    cov = np.stack([np.eye(3) * np.deg2rad(s) ** 2 / 3 for s in (0.01, 0.02, 0.03, 0.9)])  # σ = 0.01 … 0.9°
    refined = np.array([True, True, True, False])
    res = SimpleNamespace(R=np.tile(np.eye(3), (n, 1, 1)), cov=cov, refined=refined, change_deg=np.zeros(n),
                          why=["", "", "", "0 3D points in the final model"], R_refined=np.full((n, 3, 3), np.nan),
                          reconstruction=None, status="partial", warnings=[], anchored=None,
                          stats={"times": {"total": 1.0}, "n_points": 10})
    stage = SimpleNamespace(label="irls+refine", start="irls", start_why="", placed={}, known_K=None,
                            config=RefineConfig())
    st = refine_stats(res, [f"v{k}" for k in range(n)], np.arange(n), stage)
    assert st["sigma_median_deg"] == pytest.approx(0.02)  # of 0.01, 0.02, 0.03: not 0.025 with the 0.9
    assert st["uncertainty_deg"]["v3"] is None and st["uncertainty_deg"]["v0"] == pytest.approx(0.01)
    assert st["cameras"]["v3"]["sigma_deg"] is None and "cov_rad2" not in st["cameras"]["v3"]
    assert "cov_rad2" in st["cameras"]["v2"] and st["kept_averaged"] == {"v3": "0 3D points in the final model"}
