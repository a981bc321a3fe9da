"""``python -m pipeline.average`` and ``python -m pipeline.convert`` on the inputs and outputs users give them."""

from __future__ import annotations

import numpy as np

from pipeline.averaging.cli import main_cli as average_cli
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.convert import main_cli as convert_cli
from pipeline.io.onedsfm import read_1dsfm
from pipeline.synthetic.files import make_synthetic_1dsfm


def _err_line(capsys) -> str:
    """The command's stderr, which must be exactly one 'error:' line."""
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def _npz(tmp_path, name="g.npz"):
    R = so3.random_rotations(4, np.random.default_rng(0))
    vg = ViewGraph.from_absolute(["a", "b", "c", "d"], R, [[0, 1], [1, 2], [2, 3], [0, 3]])
    return vg.save(tmp_path / name)


# ----------------------------------------------------------------------------- inputs
def test_a_2d_g2o_file_is_refused_in_one_line_that_says_so(tmp_path, capsys):
    p = tmp_path / "m.g2o"
    p.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    assert average_cli([str(p), "--out", str(tmp_path / "r.txt")]) == 2
    line = _err_line(capsys)
    assert "2D" in line and "EDGE_SE2" in line and "EDGE_SE3:QUAT" in line, line
    p.write_text("")
    assert average_cli([str(p), "--out", str(tmp_path / "r.txt")]) == 2
    line = _err_line(capsys)
    assert "2D" not in line and "no EDGE_SE3:QUAT" in line, line


def test_a_folder_that_is_not_a_1dsfm_dataset_says_what_inputs_are(tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    (tmp_path / "graph.mat").mkdir()
    for folder in ("photos", "graph.mat"):
        assert average_cli([str(tmp_path / folder), "--out", str(tmp_path / "r.txt")]) == 2
        line = _err_line(capsys)
        assert "is a folder but not a 1DSfM dataset" in line, line


def test_a_file_of_a_1dsfm_folder_other_than_egs_points_to_the_folder(tmp_path, capsys):
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=1)
    for name in ("list.txt", "cc.txt", "gt_bundle.out"):
        assert average_cli([str(tmp_path / "ds" / name), "--out", str(tmp_path / "r.txt")]) == 2
        line = _err_line(capsys)
        assert f"give the folder {tmp_path / 'ds'}" in line, line


# ----------------------------------------------------------------------------- outputs of convert
def test_convert_onto_an_existing_folder_is_refused_before_reading(tmp_path, capsys):
    (tmp_path / "out").mkdir()
    bad = tmp_path / "bad.g2o"
    bad.write_text("EDGE_SE3:QUAT 0 1 nonsense\n")  # never read: the output is checked first
    for fmt in ("npz", "mat", "g2o", "glomap-relpose"):
        assert convert_cli([str(bad), str(tmp_path / "out"), "--to", fmt]) == 2
        line = _err_line(capsys)
        assert "out is a folder" in line and "Errno" not in line, line


def test_convert_refuses_to_write_over_its_input(tmp_path, capsys):
    p = _npz(tmp_path)
    before = p.read_bytes()
    assert convert_cli([str(p), str(p)]) == 2
    assert "is the input" in _err_line(capsys)
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=1)
    assert convert_cli([str(tmp_path / "ds"), str(tmp_path / "ds"), "--to", "1dsfm"]) == 2
    assert "is the input" in _err_line(capsys)
    assert p.read_bytes() == before


def test_convert_to_1dsfm_replaces_its_own_folder_whole_and_spares_others(tmp_path, capsys):
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=1)
    out = tmp_path / "out"
    assert convert_cli([str(tmp_path / "ds"), str(out), "--to", "1dsfm", "-q"]) == 0
    assert (out / "gt_bundle.out").is_file()
    # a graph without truth into the same folder: the first graph's gt_bundle.out must not stay as its truth
    assert convert_cli([str(_npz(tmp_path)), str(out), "--to", "1dsfm", "-q"]) == 0
    d = read_1dsfm(out)
    assert d.vg.names == ["a", "b", "c", "d"] and d.R_gt is None and not (out / "gt_bundle.out").exists()
    # a folder with files this writer does not write (a published dataset's coords.txt, tracks.txt) is left alone
    (out / "coords.txt").write_text("#index = 0\n")
    before = {f.name: f.read_bytes() for f in out.iterdir()}
    capsys.readouterr()
    assert convert_cli([str(tmp_path / "ds"), str(out), "--to", "1dsfm"]) == 2
    line = _err_line(capsys)
    assert "coords.txt" in line and "new or empty folder" in line, line
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before


# ----------------------------------------------------------------------------- outputs of average
def test_average_refuses_outputs_that_would_overwrite_its_input(tmp_path, capsys):
    from pipeline.io.glomap import write_glomap_relpose

    vg = ViewGraph.from_absolute(["a", "b", "c"], so3.random_rotations(3, np.random.default_rng(1)), [[0, 1], [1, 2]])
    rel = write_glomap_relpose(tmp_path / "rel.txt", vg)
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=1)
    egs = tmp_path / "ds" / "EGs.txt"
    kept = {p: p.read_bytes() for p in (rel, egs)}
    for args in ([rel, "--out", rel], [rel, "--out", tmp_path / "r.txt", "--json", rel],
                 [tmp_path / "ds", "--out", egs], [tmp_path / "ds", "--out", tmp_path / "ds" / "cc.txt"]):
        assert average_cli([str(a) for a in args]) == 2
        line = _err_line(capsys)
        assert "would overwrite the input" in line, line
    assert {p: p.read_bytes() for p in kept} == kept


def test_convert_says_in_one_warning_what_the_target_format_cannot_hold(tmp_path, caplog):
    import logging

    from pipeline.io.convert import main as convert

    R = so3.random_rotations(3, np.random.default_rng(2))
    vg = ViewGraph.from_absolute(["x.jpg", "y.jpg", "z.jpg"], R, [[0, 1], [1, 2], [0, 2]])
    vg = ViewGraph(vg.names, vg.edges, vg.R_rel, H=np.broadcast_to(100.0 * np.eye(3), (3, 3, 3)).copy())
    src = vg.save(tmp_path / "g.npz")
    cases = {"g.g2o": ("camera names",), "g.mat": ("camera names",), "rel.txt": ("precisions H",),
             "ds": ("precisions H",)}
    for out, lost in cases.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            convert(src, tmp_path / "o" / out, to={"rel.txt": "glomap-relpose", "ds": "1dsfm"}.get(out))
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and all(w in warnings[0] for w in lost), (out, warnings)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        convert(src, tmp_path / "o" / "same.npz")
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]


def test_an_egs_file_without_list_txt_says_what_is_missing(tmp_path, capsys):
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=1)
    (tmp_path / "ds" / "list.txt").unlink()
    for given in (tmp_path / "ds", tmp_path / "ds" / "EGs.txt"):
        assert average_cli([str(given), "--out", str(tmp_path / "r.txt")]) == 2
        line = _err_line(capsys)
        assert "list.txt" in line and "none in" in line, line


def test_convert_into_a_folder_that_is_a_file_is_refused_in_one_line(tmp_path, capsys):
    src = _npz(tmp_path)
    (tmp_path / "plain").write_text("a file\n")
    for out, fmt in ((tmp_path / "plain" / "x.g2o", "g2o"), (tmp_path / "plain" / "sub" / "ds", "1dsfm")):
        assert convert_cli([str(src), str(out), "--to", fmt]) == 2
        line = _err_line(capsys)
        assert f"{tmp_path / 'plain'} is a file" in line and "Errno" not in line, line


def test_convert_rotations_option_is_checked_first_and_by_its_own_name(tmp_path, capsys):
    src = _npz(tmp_path)
    (tmp_path / "folder").mkdir()
    for rot in (tmp_path / "none.txt", tmp_path / "folder"):
        assert convert_cli([str(src), str(tmp_path / "o.g2o"), "--rotations", str(rot)]) == 2
        line = _err_line(capsys)
        assert line.startswith(f"error: --rotations {rot}") and "--init" not in line, line
    rot = tmp_path / "r.txt"
    rot.write_text("a 1 0 0 0 1 0 0 0 1\n")
    assert convert_cli([str(src), str(tmp_path / "o.mat"), "--rotations", str(rot)]) == 2
    assert "--rotations is for --to g2o" in _err_line(capsys)


def test_a_rotations_file_given_as_the_view_graph_says_what_it_is(tmp_path, capsys):
    from pipeline.io.glomap import write_glomap_rotations
    from pipeline.io.rotations import write_rotations

    R = so3.random_rotations(2, np.random.default_rng(0))
    for f in (write_rotations(tmp_path / "ours.txt", ["a", "b"], R),
              write_glomap_rotations(tmp_path / "glomap.txt", ["a", "b"], R)):
        assert average_cli([str(f), "--out", str(tmp_path / "r.txt")]) == 2
        line = _err_line(capsys)
        assert "holds rotations, not a view graph" in line and "--init" in line, line


def test_a_folder_of_1dsfm_datasets_names_them(tmp_path, capsys):
    for name in ("Alamo", "Ellis_Island"):
        make_synthetic_1dsfm(tmp_path / "datasets" / name, n=4, p=0.6, seed=1, n_extra_images=0)
    assert average_cli([str(tmp_path / "datasets"), "--out", str(tmp_path / "r.txt")]) == 2
    line = _err_line(capsys)
    assert "Alamo, Ellis_Island" in line and "give one of them" in line, line


def test_a_method_needing_h_on_a_format_without_h_is_refused_before_reading(tmp_path, capsys):
    from pipeline.io.glomap import write_glomap_relpose

    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, digits=7)  # read, it would warn about its 7 digits
    vg = ViewGraph.from_absolute(["a", "b", "c"], so3.random_rotations(3, np.random.default_rng(1)), [[0, 1], [1, 2]])
    rel = write_glomap_relpose(tmp_path / "rel.txt", vg)
    for given, method in ((tmp_path / "ds", "irls-h"), (rel, "sdp")):
        assert average_cli([str(given), "--method", method, "--out", str(tmp_path / "r.txt")]) == 2
        line = _err_line(capsys)  # one line: nothing was read
        assert "needs a view graph with H" in line and "cannot hold H" in line, line


def test_convert_rotations_missing_cameras_says_so_in_convert_terms(tmp_path, capsys):
    from pipeline.io.rotations import write_rotations

    src = _npz(tmp_path)
    rot = write_rotations(tmp_path / "r.txt", ["a", "b"], so3.random_rotations(2, np.random.default_rng(3)))
    assert convert_cli([str(src), str(tmp_path / "o.g2o"), "--rotations", str(rot)]) == 2
    line = _err_line(capsys)  # one line, before the warning about what g2o cannot hold
    assert "--init" not in line and "lacks rotations for 2 camera(s)" in line and "drop --rotations" in line, line


def test_convert_writes_and_reads_g2o_in_either_information_convention(tmp_path):
    """GTSAM reads the rotation block as H, g2o's own SE3 edges as 4H: --g2o-info chooses, both ways."""
    R = so3.random_rotations(4, np.random.default_rng(0))
    H = np.stack([np.diag([1.0, 2.0, 3.0]) * (k + 1) for k in range(4)])
    vg = ViewGraph.from_absolute(["a", "b", "c", "d"], R, [[0, 1], [1, 2], [2, 3], [0, 3]]).with_H(H)
    src = vg.save(tmp_path / "g.npz")
    gtsam, g2o = tmp_path / "gtsam.g2o", tmp_path / "g2o.g2o"
    assert convert_cli([str(src), str(gtsam), "-q"]) == 0
    assert convert_cli([str(src), str(g2o), "--g2o-info", "g2o", "-q"]) == 0
    block = [np.array(ln.split()[-21:], float) for ln in (gtsam.read_text(), g2o.read_text())]  # last edge's info
    assert not np.allclose(block[0], block[1])
    for path, conv in ((gtsam, "gtsam"), (g2o, "g2o")):
        back = tmp_path / f"back_{conv}.npz"
        assert convert_cli([str(path), str(back), "--g2o-info", conv, "-q"]) == 0
        np.testing.assert_allclose(ViewGraph.load(back).H, H, rtol=1e-6)
    assert convert_cli([str(g2o), str(tmp_path / "wrong.npz"), "-q"]) == 0  # read as GTSAM's: 4× the precision
    np.testing.assert_allclose(ViewGraph.load(tmp_path / "wrong.npz").H, 4 * H, rtol=1e-6)
