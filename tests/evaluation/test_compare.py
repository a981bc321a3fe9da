"""pipeline.evaluation.compare: name matching, every method against every reference, the evaluate command."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.compare import main_cli, match_reference, truth_on_registered
from pipeline.io.rotations import write_rotations
from pipeline.reference import Reference

SUMMARY_KEYS = {"n_cameras", "n_evaluated", "median_deg", "mean_deg", "rms_deg", "max_deg", "frobenius", "pct_below"}


def test_match_reference() -> None:
    R_ref = so3.random_rotations(4, np.random.default_rng(6))
    ref_names = ["0001.jpg", "0002.jpg", "x/0003.png", "0003.jpg"]
    R, m = match_reference(["0002.jpg", "0001", "img/0002.png", "0004.jpg"], ref_names, R_ref)
    assert m.tolist() == [True, True, True, False]  # "0004" missing
    np.testing.assert_array_equal(R[:3], R_ref[[1, 0, 1]])
    np.testing.assert_array_equal(R[3], np.eye(3))
    # "0003" matches two reference names by its stem: an error that names them, not a silent skip
    with pytest.raises(InputFileError, match=r"'0003' matches several names .*'x/0003.png', '0003.jpg'"):
        match_reference(["0002.jpg", "0003"], ref_names, R_ref)
    R, m = match_reference(["0003.jpg"], ref_names, R_ref)  # exact beats the ambiguous stem
    assert m.all() and np.array_equal(R[0], R_ref[3])


# ----------------------------------------------------------------------- command
def test_cli_rotations_and_viewgraph(tmp_path, capsys) -> None:
    rng = np.random.default_rng(7)
    R = so3.random_rotations(6, rng)
    names = [f"{k:04d}.jpg" for k in range(6)]
    ref = write_rotations(tmp_path / "ref.txt", names, R)
    R_est = so3.exp(rng.normal(scale=0.01, size=(6, 3))) @ R @ so3.random_rotations(1, rng)[0]
    est = write_rotations(tmp_path / "est.txt", [n[:4] for n in names[:5]], R_est[:5])  # stems, one camera missing
    H = np.repeat(np.eye(3)[None] * 1e4, 5, axis=0)
    vg = ViewGraph.from_absolute(names, R, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)], H=H)
    vg_path = vg.save(tmp_path / "vg.npz")
    out = tmp_path / "summary.json"
    assert main_cli(["--rotations", str(est), "--reference", str(ref), "--json", str(out), "--align", "l1"]) == 0
    s = json.loads(out.read_text())
    assert SUMMARY_KEYS <= set(s) and s["n_cameras"] == 5 and s["n_evaluated"] == 5 and s["n_reference"] == 6
    assert s["align"] == "l1" and set(s["pct_below"]) == {"1", "2", "5", "10"} and s["max_deg"] < 2.0
    assert "median error (deg)" in capsys.readouterr().out
    out2 = tmp_path / "edges.json"
    assert main_cli(["--viewgraph", str(vg_path), "--reference", str(ref), "--json", str(out2)]) == 0
    e = json.loads(out2.read_text())
    assert e["n_edges"] == 5 and e["median_deg"] < 1e-9 and set(e["pct_above"]) == {"10", "30", "60", "90"}
    out3 = tmp_path / "both.json"
    est6 = write_rotations(tmp_path / "est6.txt", names, R_est)
    assert main_cli(["--rotations", str(est6), "--viewgraph", str(vg_path), "--reference", str(ref), "--json", str(out3)]) == 0
    b = json.loads(out3.read_text())
    assert "mahalanobis" in b and b["mahalanobis"] > 0 and b["edges"]["n_edges"] == 5


def test_cli_errors_are_one_line(tmp_path) -> None:
    ref = write_rotations(tmp_path / "ref.txt", ["a"], np.eye(3)[None])
    est = write_rotations(tmp_path / "est.txt", ["b"], np.eye(3)[None])
    for args, match in [
        (["--rotations", str(est), "--reference", str(tmp_path / "missing.txt")], "error: reference .* does not exist"),
        (["--rotations", str(est), "--reference", str(ref)], "error: no camera of .* matches a name"),
        (["--reference", str(ref)], "error: nothing to evaluate"),
    ]:
        out = subprocess.run([sys.executable, "-m", "pipeline.evaluate", *args], capture_output=True, text=True, timeout=60)
        assert out.returncode == 2
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and re.search(match, lines[0]), out.stderr


def test_one_camera_in_common_is_no_evaluation(tmp_path) -> None:
    """The global alignment absorbs one camera's rotation: its error is 0 by construction. The command printed
    'evaluated 1, median error 0, 100% under 1°' for 12 estimated cameras and a reference holding one of them
    (run.py --gt refuses such a truth); a run's summary must not give such figures either."""
    from pipeline.evaluation.compare import summarize_against

    rng = np.random.default_rng(3)
    names = [f"{k:04d}.jpg" for k in range(5)]
    R = so3.random_rotations(5, rng)
    est = write_rotations(tmp_path / "est.txt", names, R)
    ref = write_rotations(tmp_path / "ref.txt", names[:1], so3.random_rotations(1, rng))
    out = subprocess.run([sys.executable, "-m", "pipeline.evaluate", "--rotations", str(est), "--reference", str(ref)],
                         capture_output=True, text=True, timeout=60)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "only one camera" in lines[0] and "ref.txt" in lines[0], \
        out.stderr + out.stdout
    vg = ViewGraph.from_absolute(names, R, [(0, 1), (1, 2), (2, 3), (3, 4)]).save(tmp_path / "vg.npz")
    out = subprocess.run([sys.executable, "-m", "pipeline.evaluate", "--viewgraph", str(vg), "--reference", str(ref)],
                         capture_output=True, text=True, timeout=60)  # no edge with both ends: it printed NaN, exit 0
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "no edge of" in lines[0], out.stderr + out.stdout
    s, errs = summarize_against(names, R, Reference(names[:1], so3.random_rotations(1, rng), source="rotations"), "l2")
    assert s["n_evaluated"] == 1 and "median_deg" not in s and "only one camera" in s["note"]
    assert np.isnan(errs).all()


@pytest.mark.data
def test_lu_sphinx_edge_table(shared_data, tmp_path) -> None:
    mat = shared_data / "lu_sphinx" / "lu_sphinx.mat"
    out = tmp_path / "e.json"
    assert main_cli(["--viewgraph", str(mat), "--reference", str(mat), "--json", str(out), "-q"]) == 0
    e = json.loads(out.read_text())
    assert e["n_edges"] == 1207 and abs(e["median_deg"] - 0.30) < 0.005


def test_truth_on_pycolmap_images_is_the_like_for_like_reference():
    rng = np.random.default_rng(0)
    names = [f"im{k}.png" for k in range(5)]
    R = so3.random_rotations(5, rng)
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    vg = ViewGraph.from_absolute(names, R, edges)
    truth = Reference(names, R, label="truth")
    pyc_all = Reference(names, R, label="pycolmap")
    assert truth_on_registered(truth, pyc_all, vg) is None  # pycolmap registered every image
    pyc = Reference(names[1:4], R[1:4], label="pycolmap")  # it left out im0 and im4
    sub = truth_on_registered(truth, pyc, vg)
    assert sub.label == "truth, pycolmap's 3 images" and sub.names == names[1:4]
    np.testing.assert_array_equal(sub.R, R[1:4])
    assert truth_on_registered(None, pyc, vg) is None
