"""pipeline.io: rotations files, .mat layouts (LU Sphinx, ℓ1), reference readers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io as sio

from pipeline.core import so3
from pipeline.core.errors import InputFileError
from pipeline.io.mat import MatData, read_input_graph, read_l1_mat, read_lu_sphinx, read_mat, write_l1_mat
from pipeline.io.rotations import read_rotations, write_rotations
from pipeline.core.viewgraph import ViewGraph


# ------------------------------------------------------------------ rotations files
def test_rotations_round_trip(tmp_path) -> None:
    R = so3.random_rotations(5, np.random.default_rng(0))
    names = [f"cam{k}.jpg" for k in range(5)]
    p = write_rotations(tmp_path / "r.txt", names, R, header="made by a test\nsecond line")
    text = p.read_text()
    assert text.startswith("# made by a test\n# second line\n")
    n2, R2 = read_rotations(p)
    assert n2 == names
    np.testing.assert_array_equal(R2, R)  # %.17g is exact for float64


@pytest.mark.parametrize(
    "content, match",
    [
        ("a 1 0 0 0 1 0 0 0\n", r":1: expected 'name r11 \.\.\. r33' \(10 fields\), got 9"),
        ("# c\na 1 0 0 0 1 0 0 0 x\n", r":2: rotation entries must be numbers"),
        ("a 1 0 0 0 1 0 0 0 1\na 1 0 0 0 1 0 0 0 1\n", r"camera names repeat: \['a'\]"),
        ("a 1 0 0 0 1 0 0 0 -1\n", r"camera 'a' is not a rotation"),
        ("a 1 0 0 0 1 0 0 0 nan\n", r"is not a rotation \(or has NaN\)"),
        ("# only a comment\n\n", r"holds no rotations"),
    ],
)
def test_rotations_malformed(tmp_path, content: str, match: str) -> None:
    p = tmp_path / "bad.txt"
    p.write_text(content)
    with pytest.raises(InputFileError, match=match):
        read_rotations(p)


def test_rotations_missing_file_and_bad_names(tmp_path) -> None:
    with pytest.raises(InputFileError, match="does not exist"):
        read_rotations(tmp_path / "nope.txt")
    # a name with whitespace (or '#') is quoted, and read back as written (issue 12: names with spaces work)
    write_rotations(tmp_path / "r.txt", ["a b", "c#d", "e"], np.stack([np.eye(3)] * 3))
    assert read_rotations(tmp_path / "r.txt")[0] == ["a b", "c#d", "e"]
    with pytest.raises(ValueError, match="empty"):
        write_rotations(tmp_path / "r.txt", [""], np.eye(3)[None])
    with pytest.raises(ValueError, match=r"R.shape=\(1, 3, 3\) but expected \(2, 3, 3\)"):
        write_rotations(tmp_path / "r.txt", ["a", "b"], np.eye(3)[None])


# ---------------------------------------------------------------------- LU Sphinx
@pytest.fixture(scope="module")
def sphinx(shared_data) -> MatData:
    return read_lu_sphinx(shared_data / "lu_sphinx" / "lu_sphinx.mat")


@pytest.mark.data
def test_lu_sphinx_counts_errors_and_H(sphinx: MatData) -> None:
    vg = sphinx.vg
    assert vg.n_cameras == 70 and vg.n_edges == 1207
    assert vg.names[:3] == ["0", "1", "2"]
    assert sphinx.gt_mask.all() and vg.is_connected()
    i, j = vg.edges.T
    err = np.degrees(so3.angle_between(vg.R_rel, sphinx.R_gt[j] @ np.swapaxes(sphinx.R_gt[i], 1, 2)))
    assert abs(np.median(err) - 0.30) < 0.005  # data README and paper 2: 0.30° median
    assert np.all(np.linalg.eigvalsh(vg.H)[:, 0] > 0)  # all 1207 H positive definite


@pytest.mark.data
def test_lu_sphinx_block_convention(sphinx: MatData) -> None:
    """Pin the conventions: Rrel blocks are R_j R_iᵀ, and H is the precision of the LEFT perturbation."""
    vg, R = sphinx.vg, sphinx.R_gt
    i, j = vg.edges.T
    T = lambda X: np.swapaxes(X, 1, 2)  # noqa: E731
    true_rel = R[j] @ T(R[i])
    # The other orderings of the blocks are far off.
    for wrong in (R[i] @ T(R[j]), T(R[i]) @ R[j]):
        assert np.degrees(np.median(so3.angle_between(vg.R_rel, wrong))) > 5.0

    def loglik(r: np.ndarray) -> float:
        q = np.einsum("na,nab,nb->n", r, vg.H, r)
        s = 3 * q.size / q.sum()  # H is stored up to a global scale: use the ML scale
        return float(0.5 * np.linalg.slogdet(s * vg.H)[1].sum() - 0.5 * s * q.sum())

    left = loglik(so3.log(true_rel @ T(vg.R_rel)))  # R_j R_iᵀ = exp([Δω]×) R̃_ij
    right = loglik(so3.log(T(vg.R_rel) @ true_rel))  # R_j R_iᵀ = R̃_ij exp([Δω]×)
    r_iso = so3.log(true_rel @ T(vg.R_rel))
    s_iso = 3 * r_iso.shape[0] / np.sum(r_iso**2)
    iso = float(1.5 * r_iso.shape[0] * np.log(s_iso) - 0.5 * s_iso * np.sum(r_iso**2))
    assert left > right + 500 and left > iso + 500


# ----------------------------------------------------------------------- ℓ1 layout
def _l1_fixture(tmp_path, n: int = 5):
    rng = np.random.default_rng(1)
    R = so3.random_rotations(n, rng)
    # Edges in both orientations, 1-based: RR[:, :, k] = R_b R_aᵀ for (a, b) = I[:, k].
    pairs = np.array([(0, 1), (2, 1), (2, 3), (4, 3), (0, 4)])
    RR = R[pairs[:, 1]] @ np.swapaxes(R[pairs[:, 0]], 1, 2)
    Rgt = R.copy()
    Rgt[3] = 0.0  # no ground truth for camera 3
    path = tmp_path / "l1.mat"
    sio.savemat(path, {"RR": np.moveaxis(RR, 0, 2), "I": (pairs.T + 1).astype(float), "Rgt": np.moveaxis(Rgt, 0, 2)})
    return path, R


def test_read_l1_mat(tmp_path) -> None:
    path, R = _l1_fixture(tmp_path)
    for data in (read_l1_mat(path), read_mat(path), read_input_graph(path)):
        vg = data.vg
        assert vg.names == ["0", "1", "2", "3", "4"]
        assert vg.edges.tolist() == [[0, 1], [0, 4], [1, 2], [2, 3], [3, 4]]
        i, j = vg.edges.T
        np.testing.assert_allclose(vg.R_rel, R[j] @ np.swapaxes(R[i], 1, 2), atol=1e-14)
        assert data.gt_mask.tolist() == [True, True, True, False, True]
        np.testing.assert_array_equal(data.R_gt[3], np.eye(3))
        np.testing.assert_allclose(data.R_gt[data.gt_mask], R[data.gt_mask], atol=1e-15)


def test_write_l1_mat_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(2)
    R = so3.random_rotations(4, rng)
    H = np.stack([q @ np.diag(rng.uniform(1, 9, 3)) @ q.T for q in so3.random_rotations(4, rng)])
    vg = ViewGraph.from_absolute(["0", "1", "2", "3"], R, [(0, 1), (1, 2), (2, 3), (0, 3)], H=H)
    R_gt = R.copy()
    R_gt[2] = np.nan
    p = write_l1_mat(tmp_path / "out.mat", vg, R_gt)
    raw = sio.loadmat(p)
    assert raw["RR"].shape == (3, 3, 4) and raw["I"].min() == 1 and raw["Rgt"].shape == (3, 3, 4)
    back = read_l1_mat(p)
    np.testing.assert_array_equal(back.vg.edges, vg.edges)
    np.testing.assert_allclose(back.vg.R_rel, vg.R_rel, atol=1e-15)
    np.testing.assert_allclose(back.vg.H, vg.H, atol=1e-15)
    assert back.gt_mask.tolist() == [True, True, False, True]
    np.testing.assert_allclose(back.R_gt[back.gt_mask], R[back.gt_mask], atol=1e-15)  # each camera's own truth


def test_l1_mat_single_edge_keeps_3d_layout(tmp_path) -> None:
    # MATLAB drops a trailing singleton dimension: RR of one edge is 3×3.
    p = tmp_path / "one.mat"
    R = so3.random_rotations(1, np.random.default_rng(3))[0]
    sio.savemat(p, {"RR": R, "I": np.array([[1.0], [2.0]])})
    vg = read_l1_mat(p).vg
    assert vg.n_cameras == 2 and vg.n_edges == 1
    np.testing.assert_allclose(vg.R_rel[0], R)


@pytest.mark.parametrize(
    "arrays, match",
    [
        ({"RR": np.eye(3)[:, :, None]}, r"missing \['I'\]"),
        ({"RR": np.eye(3)[:, :, None], "I": np.array([[1.0, 2.0, 3.0]])}, r"I.shape=\(1, 3\) but expected \(2, M\)"),
        ({"RR": np.eye(3)[:, :, None], "I": np.array([[0.0], [1.0]])}, r"1-based integer camera indices"),
        ({"RR": np.eye(3)[:, :, None], "I": np.array([[1.5], [2.0]])}, r"1-based integer camera indices"),
        ({"RR": np.repeat(np.eye(3)[:, :, None], 2, 2), "I": np.array([[1.0], [2.0]])}, r"I has 1 columns but RR has 2 blocks"),
        ({"RR": np.eye(3)[:, :, None], "I": np.array([[1.0], [3.0]]), "Rgt": np.repeat(np.eye(3)[:, :, None], 2, 2)},
         r"I refers to camera 3 but Rgt has only 2 cameras"),
        ({"RR": 2 * np.eye(3)[:, :, None], "I": np.array([[1.0], [2.0]])}, r"is not a rotation"),
        ({"RR": np.eye(3)[:, :, None], "I": np.array([[1.0], [1.0]])}, r"self-edge"),
        ({"RR": np.eye(3)[:, :, None], "I": np.array([[1.0], [2.0]]), "Rgt": np.stack([np.eye(3), 2 * np.eye(3)], 2)},
         r"Rgt block of camera 1 is not a rotation"),
        ({"RR": np.ones((2, 3, 1)), "I": np.array([[1.0], [2.0]])}, r"RR.shape=\(2, 3, 1\) but expected \(3, 3, K\)"),
        ({"RR": np.full((3, 3, 1), np.nan), "I": np.array([[1.0], [2.0]])}, r"'RR' has NaN or inf"),
    ],
)
def test_l1_mat_malformed(tmp_path, arrays, match) -> None:
    p = tmp_path / "bad.mat"
    sio.savemat(p, arrays)
    with pytest.raises(InputFileError, match=match):
        read_l1_mat(p)


def test_lu_layout_malformed(tmp_path) -> None:
    p = tmp_path / "lu.mat"
    sio.savemat(p, {"Rrel": np.zeros((5, 5))})
    with pytest.raises(InputFileError, match=r"Rrel.shape=\(5, 5\) but expected \(3N, 3N\)"):
        read_lu_sphinx(p)
    sio.savemat(p, {"Rrel": np.eye(6)})
    with pytest.raises(InputFileError, match=r"non-zero diagonal block \(0, 0\)"):
        read_lu_sphinx(p)
    sio.savemat(p, {"Rrel": np.zeros((6, 6))})
    with pytest.raises(InputFileError, match="holds no edges"):
        read_lu_sphinx(p)
    Rrel = np.zeros((6, 6))
    Rrel[0:3, 3:6] = np.eye(3)
    sio.savemat(p, {"Rrel": Rrel, "Alpha": np.zeros((3, 3))})
    with pytest.raises(InputFileError, match=r"Alpha.shape=\(3, 3\) but expected Rrel's shape"):
        read_lu_sphinx(p)
    Alpha = np.zeros((6, 6))
    Alpha[0:3, 3:6] = np.diag([1.0, 0.0, 5.0])  # H = tr(M)·I − M = diag(5, 6, 1)
    sio.savemat(p, {"Rrel": Rrel, "Alpha": Alpha})
    np.testing.assert_allclose(read_lu_sphinx(p).vg.H[0], np.diag([5.0, 6.0, 1.0]))
    Alpha[0:3, 3:6] = np.diag([1.0, 1.0, -3.0])  # H = diag(-2, -2, 2): not positive definite
    sio.savemat(p, {"Rrel": Rrel, "Alpha": Alpha})
    with pytest.raises(InputFileError, match="not positive definite"):
        read_lu_sphinx(p)
    sio.savemat(p, {"Rrel": Rrel, "Rgt": np.eye(3)})
    with pytest.raises(InputFileError, match=r"Rgt.shape=\(3, 3\) but expected \(6, 3\)"):
        read_lu_sphinx(p)
    sio.savemat(p, {"Alpha": Rrel})
    with pytest.raises(InputFileError, match="no variable 'Rrel'"):
        read_lu_sphinx(p)


def test_lu_layout_lower_block_is_flipped(tmp_path) -> None:
    rng = np.random.default_rng(4)
    R = so3.random_rotations(2, rng)
    Rrel = np.zeros((6, 6))
    Rrel[3:6, 0:3] = R[0] @ R[1].T  # block (1, 0) = R_0 R_1ᵀ
    p = tmp_path / "lower.mat"
    sio.savemat(p, {"Rrel": Rrel})
    vg = read_lu_sphinx(p).vg
    assert vg.edges.tolist() == [[0, 1]]
    np.testing.assert_allclose(vg.R_rel[0], R[1] @ R[0].T, atol=1e-15)


def test_read_mat_and_input_graph_errors(tmp_path) -> None:
    p = tmp_path / "x.mat"
    sio.savemat(p, {"foo": np.eye(3)})
    with pytest.raises(InputFileError, match=r"unknown .mat layout with variables \['foo'\]"):
        read_mat(p)
    junk = tmp_path / "junk.mat"
    junk.write_bytes(b"\x00garbage" * 20)
    with pytest.raises(InputFileError, match="not a readable .mat file"):
        read_mat(junk)
    with pytest.raises(InputFileError, match="does not exist"):
        read_mat(tmp_path / "missing.mat")
    with pytest.raises(InputFileError, match="does not exist"):  # a .txt may be GLOMAP relative poses (issue 15)
        read_input_graph(tmp_path / "graph.txt")
    (tmp_path / "graph.txt").write_text("a b\n")
    with pytest.raises(InputFileError, match="unsupported view-graph input"):
        read_input_graph(tmp_path / "graph.txt")
    vg = ViewGraph.from_absolute(["a", "b"], so3.random_rotations(2, np.random.default_rng(5)), [(0, 1)])
    data = read_input_graph(vg.save(tmp_path / "g.npz"))
    assert data.R_gt is None and data.vg.names == ["a", "b"]
