"""Near-rotations in every reader, input detection, and the commands that read the new formats (issue 15)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import scipy.io as sio

from pipeline.averaging.cli import main_cli as average_cli
from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.io.convert import main_cli as convert_cli
from pipeline.io.g2o import write_g2o
from pipeline.io.glomap import write_glomap_relpose, write_glomap_rotations
from pipeline.io.graphs import input_files, read_input_graph
from pipeline.io.mat import read_l1_mat, read_lu_sphinx, write_l1_mat
from pipeline.io.rotations import read_rotations, write_rotations
from pipeline.synthetic.files import make_synthetic_1dsfm
from pipeline.synthetic.graphs import paper1_graph, paper2_graph


def _max_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.rad2deg(so3.angle_between(A, B).max()))


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


@pytest.fixture()
def l1_mat_1e6(tmp_path):
    """An ℓ1-RA ``.mat`` whose RR and Rgt are stored to 6 decimals (max|RᵀR−I| ≈ 1e-6), as public sets."""
    sg = paper1_graph(15, 0.5, 3.0, 0.0, seed=1)
    p = tmp_path / "l1.mat"
    write_l1_mat(p, sg.vg, R_gt=sg.R_true)
    d = {k: v for k, v in sio.loadmat(p).items() if not k.startswith("__")}
    d["RR"], d["Rgt"] = np.round(d["RR"], 6), np.round(d["Rgt"], 6)
    sio.savemat(p, d)
    return p, sg, d


def test_l1_mat_with_rotations_to_1e6_is_read_with_one_warning(l1_mat_1e6, caplog):
    """Acceptance 1: the layout of the public ℓ1 code with rotations stored to ~1e-6."""
    p, sg, _ = l1_mat_1e6
    with caplog.at_level(logging.WARNING):
        md = read_l1_mat(p)
    (msg,) = _warnings(caplog)  # ONE warning for the file, with the count and the largest deviation
    assert str(p) in msg and f"{sg.vg.n_edges} of {sg.vg.n_edges} RR blocks" in msg and "Rgt blocks" in msg
    assert "largest max|RᵀR−I| " in msg and "projected onto SO(3)" in msg
    assert _max_angle_deg(md.vg.R_rel, sg.vg.R_rel) < 2e-4 and _max_angle_deg(md.R_gt, sg.R_true) < 2e-4
    assert so3.is_rotation(md.vg.R_rel, 1e-12).all()


def test_l1_mat_beyond_the_tolerance_is_refused_in_one_line(l1_mat_1e6):
    p, _, d = l1_mat_1e6
    d["RR"][:, :, 4] *= 1.05
    sio.savemat(p, d)
    with pytest.raises(InputFileError, match=r"RR block 5 \(1-based\) is not a rotation: .* > tolerance 0.001") as ei:
        read_l1_mat(p)
    assert "\n" not in str(ei.value) and str(p) in str(ei.value)
    md = read_l1_mat(p, rotation_tol=0.2)  # a looser tolerance is the user's call
    assert md.vg.n_edges == d["RR"].shape[2]


def test_average_command_reads_the_1e6_mat(l1_mat_1e6, tmp_path, capsys):
    p, sg, _ = l1_mat_1e6
    out = tmp_path / "rot.txt"
    assert average_cli([str(p), "--out", str(out), "-q"]) == 0
    assert capsys.readouterr().err.count("projected onto SO(3)") == 1  # the one warning, even with -q
    stats = json.loads(out.with_suffix(".json").read_text())
    assert stats["vs_ground_truth"]["median_deg"] < 3.0
    assert average_cli([str(p), "--rotation-tol", "1e-9", "--out", str(tmp_path / "r2.txt"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "tolerance 1e-09" in err and "\n" not in err


def test_lu_sphinx_layout_projects_near_rotations(tmp_path, caplog):
    g = paper2_graph(6, 1.0, eig_range=(10.0, 100.0), seed=2)
    n = g.vg.n_cameras
    Rrel = np.zeros((3 * n, 3 * n))
    for (i, j), Rk in zip(g.vg.edges, g.vg.R_rel):
        Rrel[3 * i:3 * i + 3, 3 * j:3 * j + 3] = np.round(Rk, 6)
    p = tmp_path / "lu.mat"
    sio.savemat(p, {"Rrel": Rrel, "Rgt": np.round(g.R_true.reshape(-1, 3), 6)})
    with caplog.at_level(logging.WARNING):
        md = read_lu_sphinx(p)
    assert len(_warnings(caplog)) == 1 and "Rrel blocks" in _warnings(caplog)[0]
    assert _max_angle_deg(md.vg.R_rel, g.vg.R_rel) < 2e-4


def test_rotations_file_to_6_digits_and_glomap_rotations(tmp_path, caplog):
    R = so3.random_rotations(8, np.random.default_rng(0))
    names = [f"im{k}.jpg" for k in range(8)]
    p = tmp_path / "r6.txt"
    p.write_text("".join(f"{n} " + " ".join(f"{x:.6f}" for x in Rk.ravel()) + "\n" for n, Rk in zip(names, R)))
    with caplog.at_level(logging.WARNING):
        n2, R2 = read_rotations(p)
    assert n2 == names and len(_warnings(caplog)) == 1 and _max_angle_deg(R2, R) < 2e-4
    exact = write_rotations(tmp_path / "r.txt", names, R)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        read_rotations(exact)
    assert _warnings(caplog) == []  # our own files are exact: no warning
    g = write_glomap_rotations(tmp_path / "glomap.txt", names, R)
    n3, R3 = read_rotations(g)  # GLOMAP's NAME QW QX QY QZ, recognised by its 5 fields
    assert n3 == names and _max_angle_deg(R3, R) < 1e-10
    bad = tmp_path / "bad.txt"
    bad.write_text("a " + " ".join(["0.5"] * 9) + "\n")
    with pytest.raises(InputFileError, match="not a rotation") as ei:
        read_rotations(bad)
    assert str(bad) in str(ei.value)


@pytest.fixture()
def formats(tmp_path):
    """One 12-camera graph with H, written in every input format."""
    g = paper2_graph(12, 0.6, eig_range=(10.0, 100.0), seed=3)
    d = tmp_path / "ds"
    make_synthetic_1dsfm(d, n=12, p=0.6, sigma_deg=0.5, seed=4)
    return {"g": g, "npz": g.vg.save(tmp_path / "vg.npz"), "g2o": write_g2o(tmp_path / "vg.g2o", g.vg),
            "relpose": write_glomap_relpose(tmp_path / "relpose.txt", g.vg), "1dsfm": d}


def _same_graph(vg, ref) -> bool:
    """Same cameras and relative rotations, whatever the camera order (GLOMAP's is of first appearance)."""
    pos = {n: k for k, n in enumerate(ref.names)}
    idx = np.array([pos[n] for n in vg.names])
    other = type(ref).from_edges(ref.names, idx[vg.edges], vg.R_rel)
    return bool(np.array_equal(other.edges, ref.edges) and _max_angle_deg(other.R_rel, ref.R_rel) < 1e-8)


def test_inputs_are_recognised_by_name_extension_and_layout(formats, tmp_path):
    g = formats["g"]
    for key in ("npz", "g2o", "relpose"):
        assert _same_graph(read_input_graph(formats[key]).vg, g.vg), key
    assert np.allclose(read_input_graph(formats["g2o"]).vg.H, g.vg.H)
    d = read_input_graph(formats["1dsfm"])
    assert d.R_gt is not None and d.gt_mask.sum() == 10  # two cameras unregistered in gt_bundle.out
    assert read_input_graph(formats["1dsfm"] / "EGs.txt").vg.n_edges == d.vg.n_edges
    assert [f.name for f in input_files(formats["1dsfm"])] == ["list.txt", "EGs.txt", "cc.txt", "gt_bundle.out"]
    (tmp_path / "empty").mkdir()
    for path, match in ((tmp_path / "empty", "not a 1DSfM dataset"), (tmp_path / "nothing.npz", "does not exist")):
        with pytest.raises(InputFileError, match=match):
            read_input_graph(path)
    odd = tmp_path / "odd.txt"
    odd.write_text("a b c\n")
    with pytest.raises(InputFileError, match=r"unsupported view-graph input \(3 fields a line\); expected") as ei:
        read_input_graph(odd)
    assert "\n" not in str(ei.value)


def test_average_and_evaluate_read_the_new_formats(formats, tmp_path):
    from pipeline.evaluation.compare import evaluate_files as evaluate

    for key in ("1dsfm", "g2o", "relpose"):
        out = tmp_path / "est" / f"{key}.txt"  # not beside the inputs: relpose.txt is one
        assert average_cli([str(formats[key]), "--out", str(out), "-q"]) == 0, key
    stats = json.loads((tmp_path / "est" / "1dsfm.json").read_text())
    assert stats["vs_ground_truth"]["median_deg"] < 1.0  # gt_bundle.out is the 1DSfM folder's truth
    # GLOMAP rotations as the estimate, the 1DSfM folder (its gt_bundle.out) as the reference
    names, R = read_rotations(tmp_path / "est" / "1dsfm.txt")
    write_glomap_rotations(tmp_path / "est_glomap.txt", names, R)
    s = evaluate(formats["1dsfm"], rotations=tmp_path / "est_glomap.txt", print_table=False)
    assert s["n_evaluated"] == 10 and s["median_deg"] < 1.0
    s2 = evaluate(formats["1dsfm"] / "gt_bundle.out", rotations=tmp_path / "est" / "1dsfm.txt",
                  viewgraph=formats["1dsfm"], print_table=False)
    assert s2["median_deg"] == pytest.approx(s["median_deg"], abs=1e-6) and "edges" in s2


def test_convert_command_round_trips(formats, tmp_path, capsys):
    g = formats["g"]
    assert convert_cli([str(formats["npz"]), str(tmp_path / "a.g2o"), "-q"]) == 0
    assert convert_cli([str(tmp_path / "a.g2o"), str(tmp_path / "b.npz"), "-q"]) == 0
    vg = read_input_graph(tmp_path / "b.npz").vg
    assert _max_angle_deg(vg.R_rel, g.vg.R_rel) < 1e-8 and np.allclose(vg.H, g.vg.H)
    assert convert_cli([str(formats["1dsfm"]), str(tmp_path / "c.mat"), "-q"]) == 0
    src, mat = read_input_graph(formats["1dsfm"]), read_input_graph(tmp_path / "c.mat")
    assert mat.R_gt is not None and mat.gt_mask.tolist() == src.gt_mask.tolist() and src.gt_mask.any()
    assert _max_angle_deg(mat.R_gt[mat.gt_mask], src.R_gt[src.gt_mask]) < 1e-8  # the truth of the same cameras
    assert convert_cli([str(formats["npz"]), str(tmp_path / "d"), "-q"]) == 0  # a folder: 1DSfM
    assert read_input_graph(tmp_path / "d").vg.n_edges == g.vg.n_edges
    write_rotations(tmp_path / "r.txt", g.vg.names, g.R_true)
    assert convert_cli([str(tmp_path / "r.txt"), str(tmp_path / "q.txt"), "--to", "glomap-rotations", "-q"]) == 0
    assert _max_angle_deg(read_rotations(tmp_path / "q.txt")[1], g.R_true) < 1e-10
    assert convert_cli([str(formats["npz"]), str(tmp_path / "x.txt"), "-q"]) == 2
    assert "give --to" in capsys.readouterr().err
