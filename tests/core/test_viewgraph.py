"""pipeline.core.viewgraph: every validation error, H flipping, components, save/load."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.core.errors import InputFileError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph


def _triangle(rng: np.random.Generator, **kw) -> tuple[ViewGraph, np.ndarray]:
    R = so3.random_rotations(3, rng)
    return ViewGraph.from_absolute(["a", "b", "c"], R, [(0, 1), (1, 2), (0, 2)], **kw), R


def _rels(n: int, seed: int = 0) -> np.ndarray:
    return so3.random_rotations(n, np.random.default_rng(seed))


# ---------------------------------------------------------------- validation errors
def test_not_a_rotation() -> None:
    R = _rels(2)
    R[1] = R[1] * 1.01
    with pytest.raises(ViewGraphError, match=r"edge 1 \(1, 2\) is not a rotation"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], R)


def test_reflection_is_not_a_rotation() -> None:
    R = _rels(2)
    R[0] = R[0] @ np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ViewGraphError, match=r"not a rotation \(det=-1"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], R)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_or_inf_rotation(bad: float) -> None:
    R = _rels(2)
    R[0, 1, 2] = bad
    with pytest.raises(ViewGraphError, match="has NaN or inf"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], R)


def test_nan_in_H() -> None:
    H = np.repeat(np.eye(3)[None], 2, axis=0)
    H[1, 0, 0] = np.nan
    with pytest.raises(ViewGraphError, match=r"H of edge 1 .* has NaN or inf"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(2), H=H)


def test_self_edge() -> None:
    with pytest.raises(ViewGraphError, match="self-edge"):
        ViewGraph(["a", "b", "c"], [(0, 1), (2, 2)], _rels(2))


def test_duplicate_edge() -> None:
    with pytest.raises(ViewGraphError, match=r"duplicate edge \(0, 1\)"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2), (0, 1)], _rels(3))


def test_duplicate_edge_in_reverse_orientation() -> None:
    with pytest.raises(ViewGraphError, match=r"duplicate edge \(0, 1\).*either orientation"):
        ViewGraph.from_edges(["a", "b", "c"], [(0, 1), (1, 2), (1, 0)], _rels(3))


def test_edge_not_stored_with_i_below_j() -> None:
    with pytest.raises(ViewGraphError, match="not stored with i < j.*from_edges"):
        ViewGraph(["a", "b", "c"], [(0, 1), (2, 1)], _rels(2))


@pytest.mark.parametrize("edge", [(0, 3), (-1, 2)])
def test_index_out_of_range(edge: tuple[int, int]) -> None:
    with pytest.raises(ViewGraphError, match=r"out of range \[0, 3\)"):
        ViewGraph(["a", "b", "c"], [(0, 1), edge], _rels(2))


def test_H_not_positive_definite() -> None:
    H = np.repeat(np.eye(3)[None], 2, axis=0)
    H[1] = np.diag([1.0, 0.0, 2.0])
    with pytest.raises(ViewGraphError, match=r"H of edge 1 \(1, 2\) is not positive definite"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(2), H=H)


def test_H_not_symmetric() -> None:
    H = np.repeat(np.eye(3)[None], 2, axis=0)
    H[0, 0, 1] = 0.5
    with pytest.raises(ViewGraphError, match="is not symmetric"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(2), H=H)


def test_camera_with_no_edge() -> None:
    with pytest.raises(ViewGraphError, match=r"1 camera\(s\) have no edge, e.g. \['d'\]"):
        ViewGraph(["a", "b", "c", "d"], [(0, 1), (1, 2)], _rels(2))
    vg = ViewGraph(["a", "b", "c", "d"], [(0, 1), (1, 2)], _rels(2), allow_isolated=True)
    assert vg.degrees().tolist() == [1, 2, 1, 0]


def test_shape_errors_and_repeated_names() -> None:
    with pytest.raises(ViewGraphError, match=r"R_rel.shape=\(1, 3, 3\) but expected \(2, 3, 3\)"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(1))
    with pytest.raises(ViewGraphError, match=r"H.shape=\(1, 3, 3\) but expected \(2, 3, 3\)"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(2), H=np.eye(3)[None])
    with pytest.raises(ViewGraphError, match=r"inliers.shape=\(3,\) but expected \(2,\)"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(2), inliers=[1, 2, 3])
    with pytest.raises(ViewGraphError, match=r"stats\['t'\].shape"):
        ViewGraph(["a", "b", "c"], [(0, 1), (1, 2)], _rels(2), stats={"t": np.zeros((3, 3))})
    with pytest.raises(ViewGraphError, match=r"names must be unique; repeated: \['a'\]"):
        ViewGraph(["a", "b", "a"], [(0, 1), (1, 2)], _rels(2))


# ------------------------------------------------------------------ construction
def test_from_edges_flips_rotation_and_sorts() -> None:
    rng = np.random.default_rng(5)
    R = so3.random_rotations(4, rng)
    edges = np.array([(3, 1), (0, 2), (2, 1)])
    R_rel = R[edges[:, 1]] @ np.swapaxes(R[edges[:, 0]], 1, 2)  # R_b R_aᵀ for (a, b) as given
    vg = ViewGraph.from_edges(list("abcd"), edges, R_rel)
    assert vg.edges.tolist() == [[0, 2], [1, 2], [1, 3]]
    np.testing.assert_allclose(vg.R_rel, R[vg.edges[:, 1]] @ np.swapaxes(R[vg.edges[:, 0]], 1, 2), atol=1e-14)


def test_from_edges_flips_H_exactly() -> None:
    """Δω' of the flipped edge is −R̃ᵀΔω, so Δω'ᵀ H' Δω' must equal Δωᵀ H Δω for every Δω."""
    rng = np.random.default_rng(6)
    R_meas = so3.random_rotations(1, rng)  # R̃_10 ≈ R_0 R_1ᵀ
    Q = so3.random_rotations(1, rng)[0]
    H = Q @ np.diag([4.0, 100.0, 900.0]) @ Q.T
    vg = ViewGraph.from_edges(["a", "b"], [(1, 0)], R_meas, H=H[None])
    Hf, Rf = vg.H[0], vg.R_rel[0]
    np.testing.assert_allclose(Rf, R_meas[0].T, atol=1e-15)
    # True relative rotations drawn around the measurement: R_0 R_1ᵀ = exp(Δω) R̃_10.
    L = np.linalg.cholesky(H)
    dw = np.linalg.solve(L.T, rng.standard_normal((3, 20000))).T  # Δω ~ N(0, H⁻¹)
    true_10 = so3.exp(dw) @ R_meas[0]
    dw_flip = so3.log(np.swapaxes(true_10, 1, 2) @ Rf.T)  # R_1 R_0ᵀ = exp(Δω') R̃_01
    q = np.einsum("na,ab,nb->n", dw, H, dw)
    q_flip = np.einsum("na,ab,nb->n", dw_flip, Hf, dw_flip)
    np.testing.assert_allclose(q_flip, q, rtol=1e-8)
    # And the sample covariance of Δω' is H'⁻¹ (the flipped precision is calibrated).
    C = np.cov(dw_flip.T)
    Cf = np.linalg.inv(Hf)
    assert np.abs(C - Cf).max() < 0.05 * np.abs(Cf).max()
    assert abs(q_flip.mean() - 3.0) < 0.1
    # The unflipped H would be wrong (a test that can fail).
    assert abs(np.einsum("na,ab,nb->n", dw_flip, H, dw_flip).mean() - 3.0) > 0.3


def test_from_absolute_is_consistent() -> None:
    vg, R = _triangle(np.random.default_rng(7))
    i, j = vg.edges.T
    np.testing.assert_allclose(vg.R_rel, R[j] @ np.swapaxes(R[i], 1, 2), atol=1e-14)
    inc = vg.incidence().toarray()
    assert inc.shape == (3, 3) and np.all(inc[np.arange(3), i] == -1) and np.all(inc[np.arange(3), j] == 1)
    A = vg.adjacency().toarray()
    assert np.array_equal(A, A.T) and A.sum() == 6


# ----------------------------------------------------------------- components
def test_components_and_largest_component_maps() -> None:
    names = ["a", "b", "c", "d", "e", "f", "g"]
    # Component {1, 3, 5, 6} (4 cameras), {0, 4} (2 cameras), isolated camera 2.
    edges = [(1, 3), (3, 5), (5, 6), (1, 6), (0, 4)]
    R_rel = _rels(5, seed=8)
    H = np.stack([np.eye(3) * (k + 1) for k in range(5)])
    vg = ViewGraph(names, edges, R_rel, H=H, inliers=np.arange(5) + 10, stats={"x": np.arange(5.0)}, allow_isolated=True)
    labels = vg.components()
    assert labels.tolist() == [1, 0, 2, 0, 1, 0, 0]
    assert not vg.is_connected()
    sub, res = vg.largest_component()
    assert sub.names == ["b", "d", "f", "g"]
    assert res.kept.tolist() == [1, 3, 5, 6]
    assert res.old_to_new.tolist() == [-1, 0, -1, 1, -1, 2, 3]
    assert res.edge_kept.tolist() == [0, 1, 2, 3]
    assert res.dropped_names == ["a", "c", "e"]
    np.testing.assert_array_equal(sub.R_rel, R_rel[:4])
    np.testing.assert_array_equal(sub.H, H[:4])
    np.testing.assert_array_equal(sub.inliers, [10, 11, 12, 13])
    np.testing.assert_array_equal(sub.stats["x"], [0.0, 1.0, 2.0, 3.0])
    # Maps both ways are inverse of each other.
    assert np.all(res.old_to_new[res.kept] == np.arange(sub.n_cameras))
    assert np.all(vg.edges[res.edge_kept] == res.kept[sub.edges])
    assert sub.is_connected()


# ------------------------------------------------------------------ save / load
def test_save_load_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(9)
    vg, _ = _triangle(rng)
    H = np.stack([q @ np.diag(rng.uniform(1, 9, 3)) @ q.T for q in so3.random_rotations(3, rng)])
    vg = ViewGraph(vg.names, vg.edges, vg.R_rel, H=H, inliers=np.array([5, 6, 7]), stats={"t": rng.normal(size=(3, 3))})
    path = vg.save(tmp_path / "vg.npz")
    assert path == tmp_path / "vg.npz" and not list(tmp_path.glob(".vg.npz*"))  # no temp file left
    back = ViewGraph.load(path)
    assert back.names == vg.names
    for a, b in [(back.edges, vg.edges), (back.R_rel, vg.R_rel), (back.H, vg.H), (back.inliers, vg.inliers), (back.stats["t"], vg.stats["t"])]:
        np.testing.assert_array_equal(a, b)


def test_load_malformed_files(tmp_path) -> None:
    with pytest.raises(InputFileError, match="does not exist"):
        ViewGraph.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip file")
    with pytest.raises(InputFileError, match="not a readable view-graph .npz"):
        ViewGraph.load(junk)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(InputFileError, match="missing format tag"):
        ViewGraph.load(other)
    partial = tmp_path / "partial.npz"
    np.savez(partial, format=np.array("rotavg-viewgraph"), format_version=np.array(1), names=np.array(["a", "b"]))
    with pytest.raises(InputFileError, match="lacks the array 'edges'"):
        ViewGraph.load(partial)
    noversion = tmp_path / "noversion.npz"
    np.savez(noversion, format=np.array("rotavg-viewgraph"))
    with pytest.raises(InputFileError, match="lacks the array 'format_version'"):
        ViewGraph.load(noversion)
    future = tmp_path / "future.npz"
    np.savez(future, format=np.array("rotavg-viewgraph"), format_version=np.array(99))
    with pytest.raises(InputFileError, match="format_version 99"):
        ViewGraph.load(future)
    bad = tmp_path / "bad.npz"
    np.savez(bad, format=np.array("rotavg-viewgraph"), format_version=np.array(1), names=np.array(["a", "b"]),
             edges=np.array([[0, 1]]), R_rel=2 * np.eye(3)[None])
    with pytest.raises(ViewGraphError, match="not a rotation"):
        ViewGraph.load(bad)


def test_with_H_replaces_precisions() -> None:
    vg, _ = _triangle(np.random.default_rng(10))
    H = np.repeat(2 * np.eye(3)[None], 3, axis=0)
    assert vg.with_H(H).H is not None and vg.H is None
    with pytest.raises(ViewGraphError, match="not positive definite"):
        vg.with_H(-H)
