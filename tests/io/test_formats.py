"""File formats users have (issue 15, item 7): 1DSfM, g2o, GLOMAP; round trips, conventions, malformed input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.g2o import read_g2o, write_g2o
from pipeline.io.glomap import read_glomap_relpose, read_glomap_rotations, write_glomap_relpose, write_glomap_rotations
from pipeline.io.near_rotation import NearRotationError, OneWarning, project_near_rotations
from pipeline.io.onedsfm import BUNDLER_TO_CV, read_1dsfm, read_bundler, write_1dsfm
from pipeline.synthetic.files import make_synthetic_1dsfm


def _one_line_error(exc_info, path) -> None:
    msg = str(exc_info.value)
    assert "\n" not in msg and str(path) in msg, msg


def _graph(n=12, p=0.5, seed=0, with_H=False):
    from pipeline.synthetic.graphs import paper1_graph, paper2_graph

    return (paper2_graph(n, p, seed=seed) if with_H else paper1_graph(n, p, 3.0, 0.0, seed=seed))


def _max_angle(A, B):
    return float(np.max(so3.angle(np.swapaxes(A, -1, -2) @ B)))


def _aligned_max_angle(A, B):
    """Largest camera angle after one global rotation (gauge) aligning B to A."""
    G = so3.project_to_so3(np.sum(np.swapaxes(B, 1, 2) @ A, axis=0))
    return _max_angle(A, B @ G)


# ----------------------------------------------------------------------------- near rotations
def test_near_rotation_projection_and_refusal():
    rng = np.random.default_rng(0)
    R = so3.random_rotations(50, rng)
    out, rep = project_near_rotations(R)
    assert rep.n_projected == 0 and np.array_equal(out, R)
    Rn = np.round(R, 6)
    out, rep = project_near_rotations(Rn, source="f.txt")
    assert rep.n_projected == 50 and 1e-7 < rep.max_deviation < 1e-5
    assert so3.is_rotation(out, 1e-12).all() and _max_angle(out, R) < 2e-6
    with pytest.raises(NearRotationError, match=r"f.txt: rotation #3 is not a rotation: max\|RᵀR−I\|=.*tolerance 0.001"):
        bad = Rn.copy()
        bad[3] *= 1.01
        project_near_rotations(bad, source="f.txt")
    with pytest.raises(NearRotationError, match="det=-1"):
        project_near_rotations(-R[:2], source="f.txt")
    with pytest.raises(NearRotationError, match="NaN"):
        bad = R.copy()
        bad[0, 0, 0] = np.nan
        project_near_rotations(bad, source="f.txt")


def test_an_input_read_in_parts_warns_once_with_every_part_and_the_largest_deviation(caplog):
    """OneWarning, as the .mat readers (one variable at a time) and read_1dsfm (EGs.txt, then gt_bundle.out) use it:
    each part projected as read, one warning naming them all when the input is read, none for exact rotations."""
    rng = np.random.default_rng(0)
    R = so3.random_rotations(5, rng)
    near = OneWarning("ds", 1e-3, advise=True)
    with caplog.at_level(logging.WARNING):
        near.rotations(R, "RR block")  # exact: not counted
        out = near.rotations(np.round(R[:3], 6), "camera rotation", [f"camera {k}" for k in range(3)],
                             source=Path("ds") / "gt_bundle.out")
        qn = near.quaternions(np.array([[1.0 + 2e-7, 0, 0, 0], [0, 1.0, 0, 0]]), "Rgt")
        assert not caplog.records  # nothing said before the input is read
        near.warn()
    (msg,) = [r.getMessage() for r in caplog.records]
    worst = max(float(np.abs(np.swapaxes(A, -1, -2) @ A - np.eye(3)).max()) for A in np.round(R[:3], 6))
    assert msg == ("ds: 3 of 3 camera rotations of gt_bundle.out and 1 of 2 Rgt quaternions (| |q| − 1 |) deviate "
                   f"from SO(3) (largest max|RᵀR−I| {worst:.3g}, tolerance 0.001); projected onto SO(3)")
    assert so3.is_rotation(out, 1e-12).all() and np.allclose(np.linalg.norm(qn, axis=1), 1.0, atol=1e-15)
    with pytest.raises(InputFileError, match=r"^ds: RR block 1 \(1-based\) is not a rotation: .* tolerance 0.001; "
                                             r"expected rotations \(raise --rotation-tol to accept coarser ones\)$"):
        near.rotations(1.01 * R[:1], "RR block", ["1 (1-based)"])
    with pytest.raises(InputFileError, match=r"^ds: quaternion of camera 0 has norm 1.1, not within 0.001 of 1$"):
        OneWarning("ds", 1e-3).quaternions(np.array([[1.1, 0, 0, 0]]), "Rgt", ["of camera 0"])
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        exact = OneWarning("ds", 1e-3)
        exact.rotations(R, "EG rotation", source="ds/EGs.txt")
        exact.warn()
    assert not caplog.records


# ----------------------------------------------------------------------------- GLOMAP
def test_glomap_rotations_round_trip_and_glomap_precision(tmp_path, caplog):
    rng = np.random.default_rng(0)
    R = so3.random_rotations(20, rng)
    names = [f"img{k:03d}.jpg" for k in range(20)]
    p = write_glomap_rotations(tmp_path / "rot.txt", names, R)
    n2, R2 = read_glomap_rotations(p)
    assert n2 == names and _max_angle(R, R2) < 1e-14
    # GLOMAP writes 6 significant digits and (older versions) a trailing space, w first
    q = so3.quat_from_matrix(R)
    p6 = tmp_path / "rot6.txt"
    p6.write_text("".join(f"{n} " + " ".join(f"{v:.6g}" for v in qi) + " \n" for n, qi in zip(names, q)))
    with caplog.at_level(logging.WARNING):
        n3, R3 = read_glomap_rotations(p6)
    assert _max_angle(R, R3) < 1e-5
    assert sum(r.levelno == logging.WARNING for r in caplog.records) <= 1


def test_glomap_relpose_round_trip(tmp_path):
    sg = _graph(10, 0.6, seed=2)
    t = np.random.default_rng(0).standard_normal((sg.vg.n_edges, 3))
    vg = ViewGraph(sg.vg.names, sg.vg.edges, sg.vg.R_rel, stats={"t": t})
    p = write_glomap_relpose(tmp_path / "relpose.txt", vg)
    vg2 = read_glomap_relpose(p, names=vg.names)
    assert np.array_equal(vg2.edges, vg.edges)
    assert _max_angle(vg2.R_rel, vg.R_rel) < 1e-14 and np.allclose(vg2.stats["t"], t, atol=1e-12)
    # a pair written in the other order (cam1_from_cam2) is oriented back with the inverse transform
    lines = p.read_text().splitlines()
    a, b, *vals = lines[0].split()
    qw, qx, qy, qz, tx, ty, tz = map(float, vals)
    Rinv = so3.matrix_from_quat(np.array([qw, qx, qy, qz])).T
    tinv = -Rinv @ np.array([tx, ty, tz])
    qi = so3.quat_from_matrix(Rinv)
    lines[0] = f"{b} {a} " + " ".join(f"{v:.17g}" for v in (*qi, *tinv))
    p.write_text("\n".join(lines) + "\n")
    vg3 = read_glomap_relpose(p, names=vg.names)
    assert _max_angle(vg3.R_rel, vg.R_rel) < 1e-13 and np.allclose(vg3.stats["t"], t, atol=1e-12)


@pytest.mark.parametrize("content,match", [
    ("a 1 0 0\n", "5 fields"),
    ("a 1 0 0 x\n", "numbers"),
    ("a 2 0 0 0\n", "norm 2"),
    ("a 1 0 0 0\na 1 0 0 0\n", "repeat"),
    ("# only a comment\n", "no rotations"),
    ("a nan 0 0 0\n", "NaN"),
])
def test_glomap_rotations_malformed(tmp_path, content, match):
    p = tmp_path / "bad.txt"
    p.write_text(content)
    with pytest.raises(InputFileError, match=match) as ei:
        read_glomap_rotations(p)
    _one_line_error(ei, p)


def test_glomap_binary_and_missing(tmp_path):
    p = tmp_path / "bin.txt"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InputFileError) as ei:
        read_glomap_rotations(p)
    _one_line_error(ei, p)
    with pytest.raises(InputFileError, match="does not exist"):
        read_glomap_relpose(tmp_path / "none.txt")


# ----------------------------------------------------------------------------- 1DSfM
def test_1dsfm_synthetic_folder_conventions(tmp_path, caplog):
    truth = make_synthetic_1dsfm(tmp_path / "ds", n=30, sigma_deg=0.0, digits=None, seed=0)
    with caplog.at_level(logging.WARNING):
        d = read_1dsfm(tmp_path / "ds")
    cc = truth["cc"]
    assert list(d.index) == list(cc) and d.vg.n_cameras == 30
    assert d.info["n_egs_outside_cc"] == 1  # the planted EG to an image outside cc
    assert d.vg.names == [truth["names"][k] for k in cc]
    # noise-free: every edge is R_j R_iᵀ of the true OpenCV cameras
    Rt = truth["R_cv"][cc]
    assert _max_angle(d.vg.R_rel, so3.relative(Rt, d.vg.edges)) < 1e-10
    # truth from gt_bundle.out, converted from Bundler's −z camera
    assert _max_angle(d.R_gt[d.gt_mask], Rt[d.gt_mask]) < 1e-10
    assert (~d.gt_mask).sum() == 2 and np.allclose(d.R_gt[~d.gt_mask], np.eye(3))
    # t: the pipeline's cam2_from_cam1 translation, x_j = R_ij x_i + t, t ∝ R_j (c_i − c_j)
    C = truth["C"][cc]
    i, j = d.vg.edges.T
    tdir = np.einsum("mab,mb->ma", Rt[j], C[i] - C[j])
    tdir /= np.linalg.norm(tdir, axis=1, keepdims=True)
    assert np.allclose(d.vg.stats["t"], tdir, atol=1e-10)
    # the cameras look at the origin: +z in OpenCV (and −z in the Bundler file)
    z_cv = np.einsum("nab,nb->na", Rt, -C)[:, 2]
    assert np.all(z_cv > 0)
    Rb, tb, f, reg = read_bundler(tmp_path / "ds" / "gt_bundle.out")
    assert np.all((BUNDLER_TO_CV @ np.einsum("nab,nb->na", Rt, -C).T)[2] < 0)
    # the Bundler reader itself: every camera of the file, back in the OpenCV frame (R, t = −R C), and which are
    # registered (f = 0 and a zero R mark the others)
    np.testing.assert_array_equal(reg, truth["registered"])
    assert _max_angle(Rb[reg], truth["R_cv"][reg]) < 1e-10
    np.testing.assert_allclose(tb[reg], truth["t_cv"][reg], atol=1e-9)
    assert np.all(f[reg] > 0) and np.all(f[~reg] == 0) and np.allclose(Rb[~reg], np.eye(3))


def test_1dsfm_averaging_recovers_truth_with_file_precision(tmp_path, caplog):
    from pipeline.averaging import average

    make_synthetic_1dsfm(tmp_path / "ds", n=40, p=0.3, sigma_deg=1.0, digits=7, seed=1)
    with caplog.at_level(logging.WARNING):
        d = read_1dsfm(tmp_path / "ds")
    assert any("projected onto SO(3)" in r.getMessage() for r in caplog.records)  # 7 digits: near-rotations
    res = average(d.vg, "irls")
    m = d.gt_mask
    G = so3.project_to_so3(np.sum(np.swapaxes(d.R_gt[m], 1, 2) @ res.R[m], 0))  # R_est ≈ R_gt G
    err = np.rad2deg(so3.angle(np.swapaxes(res.R[m], 1, 2) @ d.R_gt[m] @ G))
    assert np.median(err) < 1.0  # ~σ/√degree


def test_1dsfm_write_read_round_trip(tmp_path):
    sg = _graph(12, 0.5, seed=3)
    t = np.random.default_rng(1).standard_normal((sg.vg.n_edges, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    vg = ViewGraph(sg.vg.names, sg.vg.edges, sg.vg.R_rel, stats={"t": t})
    names = [f"im{k}.jpg" for k in range(12)] + ["other.jpg"]
    vg = ViewGraph(names[:12], vg.edges, vg.R_rel, stats=vg.stats)
    R_gt = np.concatenate([sg.R_true, np.eye(3)[None]])
    write_1dsfm(tmp_path / "o", vg, list_names=names, focal=np.r_[np.full(12, 800.0), np.nan], R_gt=R_gt,
                gt_mask=np.r_[np.ones(12, bool), False])
    d = read_1dsfm(tmp_path / "o")
    assert d.vg.names == vg.names and np.array_equal(d.vg.edges, vg.edges)
    assert _max_angle(d.vg.R_rel, vg.R_rel) < 1e-13 and np.allclose(d.vg.stats["t"], t, atol=1e-13)
    assert _max_angle(d.R_gt, sg.R_true) < 1e-13 and d.gt_mask.all() and np.allclose(d.focal, 800.0)


@pytest.mark.parametrize("fname,content,match", [
    ("EGs.txt", "0 1 1 0 0 0 1 0 0 0 1 0 0\n", "14 fields"),
    ("EGs.txt", "0 99 1 0 0 0 1 0 0 0 1 0 0 1\n", "not in"),
    ("EGs.txt", "0 1 1 0 0 0 1 0 0 0 x 0 0 1\n", "numbers"),
    ("EGs.txt", "0 1 2 0 0 0 1 0 0 0 1 0 0 1\n", "not a rotation"),
    ("EGs.txt", "0 0 1 0 0 0 1 0 0 0 1 0 0 1\n", "itself"),
    ("EGs.txt", "", "no EGs"),
    ("cc.txt", "0\n1\n77\n", "not in"),
    ("list.txt", "a.jpg 0\n", "1 or 3 fields"),
    ("gt_bundle.out", "# Bundle file v0.3\n3 0\n100 0 0\n1 0 0\n", "complete camera blocks"),
])
def test_1dsfm_malformed(tmp_path, fname, content, match):
    make_synthetic_1dsfm(tmp_path / "ds", n=6, p=0.5, seed=2, n_extra_images=1)
    (tmp_path / "ds" / fname).write_text(content)
    with pytest.raises(InputFileError, match=match) as ei:
        read_1dsfm(tmp_path / "ds")
    _one_line_error(ei, tmp_path / "ds" / fname)


def test_1dsfm_missing_files(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        read_1dsfm(tmp_path / "nothing")
    (tmp_path / "e").mkdir()
    with pytest.raises(InputFileError, match="list"):
        read_1dsfm(tmp_path / "e")


# ----------------------------------------------------------------------------- g2o
@pytest.mark.parametrize("conv", ["gtsam", "g2o"])
@pytest.mark.parametrize("so3_edges", [False, True])
def test_g2o_round_trip(tmp_path, conv, so3_edges):
    sg = _graph(10, 0.5, seed=4, with_H=True)
    R0 = so3.random_rotations(10, np.random.default_rng(0))
    p = write_g2o(tmp_path / "g.g2o", sg.vg, R0, info_convention=conv, so3_edges=so3_edges, ids=np.arange(10) * 3 + 7)
    d = read_g2o(p, info_convention=conv)
    assert d.vg.names == [str(k * 3 + 7) for k in range(10)] and np.array_equal(d.vg.edges, sg.vg.edges)
    assert _max_angle(d.vg.R_rel, sg.vg.R_rel) < 1e-13 and _max_angle(d.R_init, R0) < 1e-13
    assert np.allclose(d.vg.H, sg.vg.H, rtol=1e-13)


def test_g2o_reversed_edge_transforms_H(tmp_path):
    sg = _graph(6, 0.8, seed=5, with_H=True)
    p = write_g2o(tmp_path / "g.g2o", sg.vg)
    lines = p.read_text().splitlines()
    k = next(n for n, ln in enumerate(lines) if ln.startswith("EDGE"))
    parts = lines[k].split()
    i, j = parts[1], parts[2]
    e = int(np.flatnonzero((sg.vg.edges[:, 0] == int(i)) & (sg.vg.edges[:, 1] == int(j)))[0])
    # the same measurement written as (j, i): rotation Z̃ᵀ, H in the reversed edge's convention
    Rji = sg.vg.R_rel[e].T                          # R̃_ji = R̃_ijᵀ
    H_ji = sg.vg.R_rel[e].T @ sg.vg.H[e] @ sg.vg.R_rel[e]  # from_edges: H_ij = R̃_jiᵀ H_ji R̃_ji
    qv = so3.quat_from_matrix(Rji.T)
    info = np.zeros((6, 6))
    info[:3, :3] = np.eye(3)
    info[3:, 3:] = H_ji
    lines[k] = (f"EDGE_SE3:QUAT {j} {i} 0 0 0 {qv[1]:.17g} {qv[2]:.17g} {qv[3]:.17g} {qv[0]:.17g} "
                + " ".join(f"{v:.17g}" for v in info[np.triu_indices(6)]))
    p.write_text("\n".join(lines) + "\n")
    d = read_g2o(p)
    assert _max_angle(d.vg.R_rel, sg.vg.R_rel) < 1e-13
    assert np.allclose(d.vg.H, sg.vg.H, rtol=1e-10, atol=1e-10)


def test_g2o_gtsam_reads_our_file_and_solves_our_anisotropic_problem(tmp_path):
    import gtsam  # in the test extra: this check must run, not skip
    from pipeline.averaging.irls_h import irls_h

    sg = _graph(15, 0.5, seed=6, with_H=True)
    vg = sg.vg
    ours = irls_h(vg, loss="l2", refine=False, tol_rad=1e-12, max_iterations=200)
    p = write_g2o(tmp_path / "g.g2o", vg, sg.R_true)
    graph, initial = gtsam.readG2o(str(p), True)
    assert graph.size() == vg.n_edges and initial.size() == vg.n_cameras
    f0 = graph.at(0)
    i, j = vg.edges[0]
    assert np.allclose(f0.measured().rotation().matrix(), vg.R_rel[0].T, atol=1e-12)
    assert np.allclose(f0.noiseModel().information()[:3, :3], vg.H[0], rtol=1e-12)  # rotation block = H
    graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(200)
    out = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    R_g = np.stack([out.atPose3(k).rotation().matrix().T for k in range(vg.n_cameras)])  # cam_from_world
    assert _aligned_max_angle(ours.R, R_g) < 1e-6
    # and 4·H in g2o's own convention changes nothing but the scale: same minimizer
    p4 = write_g2o(tmp_path / "g4.g2o", vg, sg.R_true, info_convention="g2o")
    g4, i4 = gtsam.readG2o(str(p4), True)
    assert np.allclose(g4.at(0).noiseModel().information()[:3, :3], 4 * vg.H[0], rtol=1e-12)


@pytest.mark.parametrize("content,match", [
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1" + " 1" * 21 + "\n", "undeclared"),
    ("EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1 1 2 3\n", "needs 30 values"),
    ("EDGE_SO3:QUAT 0 1 0 0 0 1 -1 0 0 1 0 1\n", "not positive definite"),
    ("EDGE_SO3:QUAT 0 1 0 0 0 3 1 0 0 1 0 1\n", "norm 3"),
    ("EDGE_SO3:QUAT 0 1 0 0 0 1 1 0 0 1 0 1\nEDGE_SO3:QUAT 1 0 0 0 0 1 1 0 0 1 0 1\n", "already have an edge on line 1"),
    ("EDGE_SO3:QUAT a 1 0 0 0 1 1 0 0 1 0 1\n", "integers"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n", "2D pose graph"),
    ("EDGE_SO3:QUAT 2 2 0 0 0 1 1 0 0 1 0 1\n", "itself"),
])
def test_g2o_malformed(tmp_path, content, match):
    p = tmp_path / "bad.g2o"
    p.write_text(content)
    with pytest.raises(InputFileError, match=match) as ei:
        read_g2o(p)
    _one_line_error(ei, p)
