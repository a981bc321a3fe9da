"""Files users bring, as other tools write them: the cases a reader or command got wrong (audit of the formats)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.g2o import read_g2o, write_g2o
from pipeline.io.glomap import read_glomap_relpose, write_glomap_relpose
from pipeline.io.onedsfm import read_1dsfm, read_1dsfm_reference
from pipeline.synthetic.files import make_synthetic_1dsfm


def _one_line(exc_info, path) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def _graph(names, edges, seed=0):
    R = so3.random_rotations(len(names), np.random.default_rng(seed))
    edges = np.asarray(edges)
    return ViewGraph(list(names), edges, so3.relative(R, edges)), R


# ----------------------------------------------------------------------------- a pair given twice
def test_1dsfm_pair_given_twice_is_named_by_its_list_indices_and_lines(tmp_path):
    make_synthetic_1dsfm(tmp_path / "ds", n=8, p=0.6, seed=4, n_extra_images=2)
    egs = tmp_path / "ds" / "EGs.txt"
    lines = egs.read_text().splitlines()
    cc = [int(x) for x in (tmp_path / "ds" / "cc.txt").read_text().split()]
    k, first = next((k, ln.split()) for k, ln in enumerate(lines, 1)
                    if set(map(int, ln.split()[:2])) <= set(cc) and int(ln.split()[0]) != cc.index(int(ln.split()[0])))
    egs.write_text("\n".join(lines + [" ".join([first[1], first[0]] + first[2:])]) + "\n")
    with pytest.raises(InputFileError) as ei:
        read_1dsfm(tmp_path / "ds")
    msg = _one_line(ei, egs)
    # the file's own indices (list.txt lines), not the cc.txt renumbering, and both lines
    assert f"images {first[1]} and {first[0]}" in msg and f":{len(lines) + 1}:" in msg and f"line {k}" in msg, msg


def test_g2o_pair_given_twice_is_named_by_its_vertex_ids_and_lines(tmp_path):
    vg, _ = _graph(["a", "b", "c"], [(0, 1), (1, 2), (0, 2)])
    p = tmp_path / "g.g2o"
    write_g2o(p, vg, ids=np.array([10, 11, 12]))
    lines = p.read_text().splitlines()
    e = next(ln.split() for ln in lines if ln.startswith("EDGE") and ln.split()[1:3] == ["11", "12"])
    p.write_text("\n".join(lines + [" ".join([e[0], e[2], e[1]] + e[3:])]) + "\n")
    with pytest.raises(InputFileError) as ei:
        read_g2o(p)
    msg = _one_line(ei, p)
    assert "vertices 12 and 11" in msg and f":{len(lines) + 1}:" in msg, msg


def test_glomap_pair_given_twice_is_named_by_its_image_names(tmp_path):
    vg, _ = _graph(["x.jpg", "y.jpg", "z.jpg"], [(0, 1), (1, 2), (0, 2)])
    p = tmp_path / "rel.txt"
    write_glomap_relpose(p, vg)
    lines = p.read_text().splitlines()
    f = lines[1].split()
    p.write_text("\n".join(lines + [" ".join([f[1], f[0]] + f[2:])]) + "\n")
    with pytest.raises(InputFileError) as ei:
        read_glomap_relpose(p)
    msg = _one_line(ei, p)
    assert f"images {f[1]} and {f[0]}" in msg and ":4:" in msg and "line 2" in msg, msg


# ----------------------------------------------------------------------------- a UTF-8 byte-order mark (Windows editors)
def _with_bom(path) -> None:
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())


def test_text_files_saved_with_a_byte_order_mark_read_as_without(tmp_path):
    from pipeline.io.glomap import read_glomap_rotations, write_glomap_rotations
    from pipeline.io.rotations import read_rotations, write_rotations

    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=5, n_extra_images=1)
    plain = read_1dsfm(tmp_path / "ds")
    for name in ("list.txt", "cc.txt", "EGs.txt", "gt_bundle.out"):
        _with_bom(tmp_path / "ds" / name)
    bom = read_1dsfm(tmp_path / "ds")
    assert bom.vg.names == plain.vg.names and np.array_equal(bom.vg.edges, plain.vg.edges)
    assert np.array_equal(bom.gt_mask, plain.gt_mask)

    vg, R = _graph(["x.jpg", "y.jpg", "z.jpg"], [(0, 1), (1, 2), (0, 2)])
    readers = [(write_glomap_relpose, (vg,), lambda p: read_glomap_relpose(p).names),
               (write_g2o, (vg,), lambda p: read_g2o(p).vg.names),
               (write_glomap_rotations, (vg.names, R), lambda p: read_glomap_rotations(p)[0]),
               (write_rotations, (vg.names, R), lambda p: read_rotations(p)[0])]
    for k, (write, args, names_of) in enumerate(readers):
        p = tmp_path / f"f{k}{'.g2o' if write is write_g2o else '.txt'}"
        write(p, *args)
        expected = names_of(p)
        _with_bom(p)
        assert names_of(p) == expected, write.__name__


# ----------------------------------------------------------------------------- the ℓ1 .mat layout
def test_l1_mat_with_I_stored_M_by_2_reads_as_2_by_M(tmp_path):
    import scipy.io as sio

    from pipeline.io.mat import read_l1_mat

    vg, R = _graph([str(k) for k in range(5)], [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4)])
    RR = np.moveaxis(vg.R_rel, 0, 2)
    I = (vg.edges + 1).T
    sio.savemat(tmp_path / "a.mat", {"RR": RR, "I": I.astype(float), "Rgt": np.moveaxis(R, 0, 2)})
    sio.savemat(tmp_path / "b.mat", {"RR": RR, "I": I.T.astype(np.uint32), "Rgt": np.moveaxis(R, 0, 2)})
    a, b = read_l1_mat(tmp_path / "a.mat"), read_l1_mat(tmp_path / "b.mat")
    assert np.array_equal(a.vg.edges, b.vg.edges) and np.allclose(a.vg.R_rel, b.vg.R_rel, atol=0)
    assert np.allclose(a.vg.R_rel, so3.relative(R, a.vg.edges), atol=1e-12)


# ----------------------------------------------------------------------------- names with '#' or spaces
def test_glomap_files_keep_image_names_with_a_hash(tmp_path):
    """GLOMAP writes names as they are (no comments in its files): 'IMG#12.jpg' is one name, not a comment."""
    from pipeline.io.graphs import read_input_graph
    from pipeline.io.glomap import read_glomap_rotations, write_glomap_rotations
    from pipeline.io.rotations import read_rotations

    vg, R = _graph(["IMG#1.jpg", "b.jpg", "c#.jpg"], [(0, 1), (1, 2), (0, 2)])
    rel = write_glomap_relpose(tmp_path / "rel.txt", vg)
    assert read_glomap_relpose(rel).names == vg.names and read_input_graph(rel).vg.names == vg.names
    rot = write_glomap_rotations(tmp_path / "rot.txt", vg.names, R)
    assert read_glomap_rotations(rot)[0] == vg.names and read_rotations(rot)[0] == vg.names


def test_convert_recognises_our_rotations_file_with_quoted_names(tmp_path, capsys):
    from pipeline.io.convert import main_cli as convert_cli
    from pipeline.io.rotations import read_rotations, write_rotations

    names = ["IMG 1.jpg", "b#2.jpg", "c.jpg"]
    R = so3.random_rotations(3, np.random.default_rng(2))
    src = write_rotations(tmp_path / "r.txt", names, R)
    assert convert_cli([str(src), str(tmp_path / "copy.txt"), "--to", "rotations"]) == 0, capsys.readouterr().err
    n2, R2 = read_rotations(tmp_path / "copy.txt")
    assert n2 == names and np.allclose(R2, R, atol=1e-15)


# ----------------------------------------------------------------------------- Bundler's gt_bundle.out
def _bundle(path, cams) -> None:
    """cams: (f, R (3, 3), t (3,)) per camera, written as Bundler v0.3 with no points."""
    rows = ["# Bundle file v0.3", f"{len(cams)} 0"]
    for f, R, t in cams:
        rows += [f"{f} 0 0"] + [" ".join(map(str, r)) for r in np.asarray(R)] + [" ".join(map(str, t))]
    path.write_text("\n".join(rows) + "\n")


def test_bundler_camera_with_focal_zero_is_unregistered_whatever_its_rotation(tmp_path):
    """Bundler (and Theia's reader) register a camera by its focal length: f <= 0 is not reconstructed."""
    from pipeline.io.onedsfm import read_bundler

    R = so3.random_rotations(2, np.random.default_rng(3))
    _bundle(tmp_path / "b.out", [(900.0, R[0], [0, 0, 1]), (0, np.eye(3), [0, 0, 0]), (-1.0, R[1], [1, 0, 0]),
                                 (0, np.zeros((3, 3)), [0, 0, 0])])
    _, _, _, registered = read_bundler(tmp_path / "b.out")
    assert registered.tolist() == [True, False, False, False]


def test_a_bundle_file_with_more_cameras_than_list_txt_is_refused(tmp_path):
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=1)
    gt = tmp_path / "ds" / "gt_bundle.out"
    lines = gt.read_text().splitlines()
    assert lines[1] == "7 0"  # 6 cameras in cc.txt and 1 extra image, no points
    gt.write_text("\n".join([lines[0], "8 0"] + lines[2:] + ["0 0 0"] + ["0 0 0"] * 4) + "\n")  # one camera more
    with pytest.raises(InputFileError) as ei:
        read_1dsfm(tmp_path / "ds")
    msg = _one_line(ei, gt)
    assert "8 cameras" in msg and "7 images" in msg, msg
    with pytest.raises(InputFileError) as ei:  # the same file as the evaluator's reference
        read_1dsfm_reference(gt)
    assert "8 cameras" in _one_line(ei, gt)


# ----------------------------------------------------------------------------- translations: one convention
def test_translations_follow_the_pipeline_convention_across_formats(tmp_path):
    """``stats["t"]`` is the pipeline's unit t of cam2_from_cam1 (x_j = R_ij x_i + t, t ∝ R_j (c_i − c_j)) whatever the
    file: 1DSfM's EGs give camera j's position in camera i's frame, which must be turned into it, and GLOMAP's
    relative poses written from a 1DSfM folder or from the pipeline's view graph must carry it."""
    truth = make_synthetic_1dsfm(tmp_path / "ds", n=10, p=0.6, sigma_deg=0.0, digits=None, seed=6)
    d = read_1dsfm(tmp_path / "ds")
    C = truth["C"][d.index]
    Rt = truth["R_cv"][d.index]
    i, j = d.vg.edges.T
    t_true = np.einsum("mab,mb->ma", Rt[j], C[i] - C[j])
    t_true /= np.linalg.norm(t_true, axis=1, keepdims=True)
    np.testing.assert_allclose(d.vg.stats["t"], t_true, atol=1e-10)
    rel = write_glomap_relpose(tmp_path / "rel.txt", d.vg)
    back = read_glomap_relpose(rel, names=d.vg.names)
    np.testing.assert_allclose(back.stats["t"], t_true, atol=1e-10)
    from pipeline.io.onedsfm import write_1dsfm

    write_1dsfm(tmp_path / "again", d.vg)
    np.testing.assert_allclose(read_1dsfm(tmp_path / "again").vg.stats["t"], t_true, atol=1e-10)
    # a view graph of the pipeline (two-view geometry writes stats["t"]) keeps its translations in GLOMAP's file
    vg = ViewGraph(d.vg.names, d.vg.edges, d.vg.R_rel, stats={"t": t_true})
    vals = np.array([ln.split()[6:] for ln in write_glomap_relpose(tmp_path / "p.txt", vg).read_text().splitlines()],
                    float)
    np.testing.assert_allclose(vals, t_true, atol=1e-15)


# ----------------------------------------------------------------------------- messages say what to do
_EG = "1 0 0 0 1 0 0 0 1 0 0 1"


@pytest.mark.parametrize("name,content,remedy", [
    ("EGs.txt", f"0 0 {_EG}\n", "delete the line"),
    ("EGs.txt", f"0 1 nan {_EG[2:]}\n", "fix or delete the line"),
    ("g.g2o", "EDGE_SO3:QUAT 2 2 0 0 0 1 1 0 0 1 0 1\n", "delete the line"),
    ("g.g2o", "EDGE_SO3:QUAT 1 2 0 0 0 nan 1 0 0 1 0 1\n", "fix or delete the line"),
    ("rel.txt", "a.jpg a.jpg 1 0 0 0 0 0 1\n", "delete the line"),
    ("rel.txt", "a.jpg b.jpg 1 0 0 0 0 0 inf\n", "fix or delete the line"),
    ("empty.txt", "\n\n", "is empty"),
])
def test_a_bad_line_says_what_to_do(tmp_path, name, content, remedy):
    from pipeline.io.graphs import read_input_graph

    if name == "EGs.txt":
        make_synthetic_1dsfm(tmp_path / "ds", n=4, p=0.6, seed=1, n_extra_images=0)
        path = tmp_path / "ds" / name
    else:
        path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputFileError) as ei:
        read_input_graph(path)
    assert remedy in _one_line(ei, path)


def test_mat_truth_with_fewer_cameras_than_I_says_what_to_do(tmp_path):
    import scipy.io as sio

    from pipeline.io.mat import read_l1_mat

    vg, R = _graph([str(k) for k in range(4)], [(0, 1), (1, 2), (2, 3)])
    sio.savemat(tmp_path / "a.mat", {"RR": np.moveaxis(vg.R_rel, 0, 2), "I": (vg.edges + 1).T.astype(float),
                                     "Rgt": np.moveaxis(R[:3], 0, 2)})
    with pytest.raises(InputFileError) as ei:
        read_l1_mat(tmp_path / "a.mat")
    assert "a 3×3 block for every camera" in _one_line(ei, tmp_path / "a.mat")


def test_1dsfm_with_no_eg_inside_cc_txt_names_the_files(tmp_path):
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.6, seed=1, n_extra_images=2)
    egs = tmp_path / "ds" / "EGs.txt"
    cc = [int(x) for x in (tmp_path / "ds" / "cc.txt").read_text().split()]
    lonely = cc[0]  # cc.txt keeps one image, and EGs.txt none of its pairs
    egs.write_text("".join(ln + "\n" for ln in egs.read_text().splitlines() if str(lonely) not in ln.split()[:2]))
    (tmp_path / "ds" / "cc.txt").write_text(f"{lonely}\n")
    with pytest.raises(InputFileError) as ei:
        read_1dsfm(tmp_path / "ds")
    msg = _one_line(ei, egs)
    assert "cc.txt" in msg and "none of its" in msg, msg


def test_bundler_reads_only_its_camera_section(tmp_path):
    """A published gt_bundle.out holds its points after the cameras (hundreds of MB): the reader stops at the cameras,
    in memory (here a peak under twice the file's size) and in what it decodes (a damaged point line is never read)."""
    import tracemalloc

    from pipeline.io.onedsfm import read_bundler

    R = so3.random_rotations(3, np.random.default_rng(4))
    path = tmp_path / "b.out"
    _bundle(path, [(900.0, R[k], [0, 0, k]) for k in range(3)])
    text = path.read_text().replace("3 0\n", "3 40000\n", 1)
    views = " ".join(f"{c} {5 * c} 12.5 -3.25" for c in range(3))
    path.write_bytes(text.encode() + b"1 2 3\n255 0 0\n3 " + views.encode() + b"\n"
                     + (b"1.5 2.5 3.5\n255 128 0\n3 " + views.encode() + b"\n") * 40000 + b"\xff\xfe damaged\n")
    tracemalloc.start()
    try:
        _, _, _, registered = read_bundler(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert registered.all()
    assert peak < 2 * path.stat().st_size, (peak, path.stat().st_size)


def test_g2o_printed_to_6_digits_is_read_with_one_warning(tmp_path, caplog):
    """GTSAM's writeG2o prints 6 significant digits: vertices and edges are near-unit quaternions, one warning."""
    import logging

    vg, R = _graph(["a", "b", "c", "d"], [(0, 1), (1, 2), (2, 3), (0, 3)])
    p = write_g2o(tmp_path / "g.g2o", vg, R)

    def six_digits(line):
        t = line.split()
        n_ids = 1 if t[0].startswith("VERTEX") else 2
        return " ".join(t[:1 + n_ids] + [f"{float(x):.6g}" for x in t[1 + n_ids:]])

    p.write_text("".join(six_digits(ln) + "\n" for ln in p.read_text().splitlines()))
    with caplog.at_level(logging.WARNING):
        d = read_g2o(p)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "normalized" in warnings[0], warnings
    assert np.abs(d.R_init - R).max() < 1e-5


def test_1dsfm_printed_to_7_digits_is_read_with_one_warning_for_its_rotations(tmp_path, caplog):
    import logging

    make_synthetic_1dsfm(tmp_path / "ds", n=8, p=0.6, seed=2, digits=7, n_extra_images=0)
    with caplog.at_level(logging.WARNING):
        read_1dsfm(tmp_path / "ds")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "SO(3)" in r.getMessage()]
    assert len(warnings) == 1 and "EGs.txt" in warnings[0] and "gt_bundle.out" in warnings[0], warnings


def test_l1_mat_with_quaternions_4_by_M_as_AverageSO3Graph_takes_them(tmp_path):
    """The public ℓ1/IRLS code (AverageSO3Graph) takes RR as 3×3×M matrices OR 4×M quaternions (scalar first, its
    q2R), and returns R in the same form; Rgt may come as 4×N too."""
    import scipy.io as sio

    from pipeline.io.mat import read_l1_mat

    vg, R = _graph([str(k) for k in range(5)], [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4)])
    q = np.round(so3.quat_from_matrix(vg.R_rel), 6)  # (w, x, y, z), printed to 6 digits
    I = (vg.edges + 1).T.astype(float)
    sio.savemat(tmp_path / "q.mat", {"RR": q.T, "I": I, "Rgt": so3.quat_from_matrix(R).T})
    d = read_l1_mat(tmp_path / "q.mat")
    assert np.allclose(d.vg.R_rel, so3.relative(R, d.vg.edges), atol=1e-5)
    assert np.allclose(d.R_gt, R, atol=1e-12) and d.gt_mask.all()


def test_l1_mat_truth_with_nan_blocks_marks_those_cameras_unknown(tmp_path):
    """AverageSO3Graph writes NaN for the cameras outside its largest component; as Rgt they have no truth."""
    import scipy.io as sio

    from pipeline.io.mat import read_l1_mat

    vg, R = _graph([str(k) for k in range(4)], [(0, 1), (1, 2), (2, 3)])
    Rgt = np.moveaxis(R, 0, 2).copy()
    Rgt[:, :, 2] = np.nan
    sio.savemat(tmp_path / "a.mat", {"RR": np.moveaxis(vg.R_rel, 0, 2), "I": (vg.edges + 1).T.astype(float),
                                     "Rgt": Rgt})
    d = read_l1_mat(tmp_path / "a.mat")
    assert d.gt_mask.tolist() == [True, True, False, True] and np.allclose(d.R_gt[[0, 1, 3]], R[[0, 1, 3]])
    Rgt[0, 0, 1] = np.nan  # a block partly NaN is damaged, not unknown
    sio.savemat(tmp_path / "b.mat", {"RR": np.moveaxis(vg.R_rel, 0, 2), "I": (vg.edges + 1).T.astype(float),
                                     "Rgt": Rgt})
    with pytest.raises(InputFileError) as ei:
        read_l1_mat(tmp_path / "b.mat")
    assert "camera 1" in _one_line(ei, tmp_path / "b.mat")


# ----------------------------------------------------------------------------- 1DSfM as published, written here by hand
def test_1dsfm_written_by_the_readme_alone_averages_back_to_its_truth(tmp_path):
    """EGs.txt and gt_bundle.out written from the SfM_Init README and Bundler's format only (no code of the project's
    writers or constants): the exact relative rotations average back to the truth, and the evaluator agrees."""
    from pipeline.averaging.cli import main as average
    from pipeline.evaluation.compare import evaluate_files

    rng = np.random.default_rng(7)
    n = 9
    R = so3.random_rotations(n, rng)                     # cam_from_world, camera looks down +z
    C = rng.standard_normal((n, 3))
    Rb = np.diag([1.0, -1.0, -1.0]) @ R                  # Bundler: the camera looks down −z
    d = tmp_path / "ds"
    d.mkdir()
    (d / "list.txt").write_text("".join(f"images/{k:03d}.jpg 0 {900 + k}\r\n" for k in range(n)))  # Windows ends
    (d / "cc.txt").write_text("".join(f"{k}\n" for k in range(n)) + "\n\n")
    lines = []
    for a in range(n):
        for b in range(a + 1, n):
            if (a * 7 + b * 3) % 4 == 0 or b == a + 1:
                i, j = (b, a) if (a + b) % 3 == 0 else (a, b)  # some EGs written with i > j
                Rij = Rb[i] @ Rb[j].T                        # README: Rij = Ri * Rj'
                tij = Rb[i] @ (C[j] - C[i])                  # README: position of camera j in camera i's frame
                lines.append("\t".join(f"{v:.17g}" for v in (i, j, *Rij.ravel(), *tij)))
    (d / "EGs.txt").write_text("\n".join(lines) + "\n")
    cams = [f"{900 + k} 0 0\n" + "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in Rb[k])
            + " ".join(f"{v:.17g}" for v in -Rb[k] @ C[k]) + "\n" for k in range(n)]
    (d / "gt_bundle.out").write_text(f"# Bundle file v0.3\n{n} 0\n" + "".join(cams))
    out = average(d, tmp_path / "r.txt", method="irls")
    s = evaluate_files(d, rotations=out, print_table=False)
    assert s["n_evaluated"] == n and s["max_deg"] < 1e-7, s


def test_a_g2o_file_written_by_gtsam_reads_in_our_convention(tmp_path):
    """GTSAM's writeG2o (world_from_cam poses, measurement T_i⁻¹ T_j, information in g2o's (translation, rotation)
    order) read back: R_ij = R_j R_iᵀ of the cam_from_world R_i = (pose rotation)ᵀ, H = the marginal precision of
    GTSAM's rotation (its information coupled to the translation's: the Schur complement, not the rotation block)."""
    import gtsam  # in the test extra: this check must run, not skip

    n = 5
    R = so3.random_rotations(n, np.random.default_rng(8))
    C = np.random.default_rng(9).standard_normal((n, 3))
    T = [gtsam.Pose3(gtsam.Rot3(R[k].T), C[k]) for k in range(n)]
    graph, values, H = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
    rng = np.random.default_rng(10)
    for k in range(n):
        values.insert(k, T[k])
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4), (3, 1)]:
        A = rng.standard_normal((6, 6))
        info = A @ A.T + np.eye(6)  # GTSAM's order: rotation, then translation
        # the rotation's marginal precision: the Schur complement of the translation block
        H[tuple(sorted((i, j)))] = (i, j, info[:3, :3] - info[:3, 3:] @ np.linalg.solve(info[3:, 3:], info[3:, :3]))
        graph.add(gtsam.BetweenFactorPose3(i, j, T[i].between(T[j]), gtsam.noiseModel.Gaussian.Information(info)))
    gtsam.writeG2o(graph, values, str(tmp_path / "g.g2o"))
    d = read_g2o(tmp_path / "g.g2o")
    assert np.abs(d.vg.R_rel - so3.relative(R, d.vg.edges)).max() < 1e-5  # writeG2o prints 6 digits
    assert np.abs(d.R_init - R).max() < 1e-5
    for k, (a, b) in enumerate(d.vg.edges):
        i, j, Hg = H[(a, b)]
        Rij = R[j] @ R[i].T  # the edge as written; read as (a, b) = (j, i) it is reversed: R̃ᵀ H R̃
        expected = Hg if (i, j) == (a, b) else Rij.T @ Hg @ Rij
        assert np.abs(d.vg.H[k] - expected).max() < 1e-4 * np.abs(Hg).max(), (a, b)
