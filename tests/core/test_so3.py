"""pipeline.core.so3: round trips (hypothesis), stability near 0 and π, projections, means."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from pipeline.core import so3

RTOL = 1e-12

unit_axes = st.tuples(
    st.floats(-1, 1, allow_nan=False), st.floats(-1, 1, allow_nan=False), st.floats(-1, 1, allow_nan=False)
).filter(lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: np.asarray(v) / np.linalg.norm(v))

# Angles spread over (0, π), with extra weight within 1e-8 of 0 and of π. Closer to π
# than ~1e-14 the sign of the axis is not representable: sin θ (the antisymmetric part
# of R) is below the rounding error of R's entries, and w and −w are the same rotation
# to 1e-14 rad. That band has its own test below.
angles = st.one_of(
    st.floats(1e-300, 1e-8),
    st.floats(1e-8, np.pi - 1e-8),
    st.floats(1e-13, 1e-8).map(lambda d: np.pi - d),
)


def _rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


@settings(max_examples=400, deadline=None)
@given(axis=unit_axes, theta=angles)
def test_log_exp_round_trip(axis: np.ndarray, theta: float) -> None:
    w = theta * axis
    assert _rel_err(so3.log(so3.exp(w)), w) < RTOL


@settings(max_examples=200, deadline=None)
@given(axis=unit_axes, d=st.floats(0.0, 1e-13))
def test_log_at_pi_returns_w_or_its_antipode(axis: np.ndarray, d: float) -> None:
    theta = np.nextafter(np.pi, 0.0) - d
    w = theta * axis
    got = so3.log(so3.exp(w))
    assert min(_rel_err(got, w), _rel_err(got, -w)) < RTOL
    assert abs(np.linalg.norm(got) - theta) < 1e-14


@settings(max_examples=200, deadline=None)
@given(axis=unit_axes, theta=angles)
def test_exp_log_round_trip_matrices(axis: np.ndarray, theta: float) -> None:
    R = so3.exp(theta * axis)
    assert np.abs(so3.exp(so3.log(R)) - R).max() < 1e-13


# Below ~1e-154 rad the squared norm underflows; no rotation in this project is that small.
angles_above_underflow = angles.filter(lambda t: t > 1e-150)


@settings(max_examples=200, deadline=None)
@given(axis=unit_axes, theta=angles_above_underflow)
def test_angle_is_accurate_for_tiny_and_large_angles(axis: np.ndarray, theta: float) -> None:
    assert abs(so3.angle(so3.exp(theta * axis)) - theta) <= RTOL * theta + 1e-300


def test_batched_round_trip_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    R = so3.random_rotations(5000, rng)
    w = so3.log(R)
    np.testing.assert_allclose(w, Rotation.from_matrix(R).as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(so3.exp(w), R, atol=1e-13)
    assert w.shape == (5000, 3) and so3.exp(w.reshape(50, 100, 3)).shape == (50, 100, 3, 3)


def test_exp_matches_scipy_and_hat_vee() -> None:
    rng = np.random.default_rng(1)
    w = rng.normal(size=(100, 3))
    np.testing.assert_allclose(so3.exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-13)
    v = rng.normal(size=(100, 3))
    np.testing.assert_allclose(so3.hat(w) @ v[..., None], np.cross(w, v)[..., None], atol=1e-14)
    np.testing.assert_array_equal(so3.vee(so3.hat(w)), w)


def test_log_at_exactly_pi_gives_angle_pi() -> None:
    for axis in np.eye(3):
        w = so3.log(so3.exp(np.pi * axis))
        assert abs(np.linalg.norm(w) - np.pi) < 1e-12
        assert abs(abs(w @ axis) - np.pi) < 1e-12


def test_project_to_so3_fixes_determinant() -> None:
    rng = np.random.default_rng(2)
    M = rng.normal(size=(200, 3, 3))
    R = so3.project_to_so3(M)
    assert np.all(so3.is_rotation(R, 1e-12))
    # The nearest rotation: no random rotation is closer in Frobenius norm.
    Q = so3.random_rotations(200, rng)
    assert np.all(np.linalg.norm(M - R, axis=(1, 2)) <= np.linalg.norm(M - Q, axis=(1, 2)) + 1e-12)
    # A reflection projects to a proper rotation.
    assert np.linalg.det(so3.project_to_so3(np.diag([1.0, 1.0, -1.0]))) > 0


def test_chordal_distance_and_angle_between() -> None:
    R1 = so3.exp(np.array([0.3, 0.0, 0.0]))
    np.testing.assert_allclose(so3.angle_between(R1, np.eye(3)), 0.3, rtol=1e-14)
    np.testing.assert_allclose(so3.chordal_distance(R1, np.eye(3)), 2 * np.sqrt(2) * np.sin(0.15), rtol=1e-13)


def test_quaternion_round_trip_and_scipy_order() -> None:
    rng = np.random.default_rng(3)
    R = so3.random_rotations(1000, rng)
    q = so3.quat_from_matrix(R)
    np.testing.assert_allclose(so3.matrix_from_quat(q), R, atol=1e-14)
    xyzw = Rotation.from_matrix(R).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1) * np.sign(xyzw[:, 3:])
    np.testing.assert_allclose(q, wxyz, atol=1e-13)
    with pytest.raises(ValueError, match="finite and non-zero"):
        so3.matrix_from_quat(np.zeros(4))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 4\)"):
        so3.matrix_from_quat(np.zeros(3))


def test_chordal_and_karcher_means() -> None:
    rng = np.random.default_rng(4)
    S = so3.random_rotations(1, rng)[0]
    w = rng.normal(scale=0.2, size=(50, 3))
    w -= w.mean(axis=0)  # zero-mean tangent perturbations: S is close to both means
    R = so3.exp(w) @ S
    K = so3.karcher_mean(R)
    # First-order optimality of the Karcher mean: the tangent residuals sum to zero.
    assert np.linalg.norm(so3.log(R @ K.T).mean(axis=0)) < 1e-12
    assert so3.angle_between(so3.chordal_mean(R), S) < 0.01
    # Exact on identical samples.
    assert so3.angle_between(so3.karcher_mean(np.repeat(S[None], 4, 0)), S) < 1e-12


def test_is_rotation_and_bad_shapes() -> None:
    assert not so3.is_rotation(np.diag([1.0, 1.0, -1.0]))
    assert not so3.is_rotation(np.full((3, 3), np.nan))
    assert not so3.is_rotation(1.001 * np.eye(3))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 3, 3\)"):
        so3.log(np.eye(2))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 3\)"):
        so3.exp(np.zeros(4))
    with pytest.raises(TypeError, match="not supported"):
        so3.exp(np.array(["a", "b", "c"]))


def test_benchmark_script_runs(tmp_path, repo_root) -> None:
    import json
    import subprocess
    import sys

    script = repo_root / "benchmarks" / "so3.py"
    out = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--quick" in out.stdout
    js = tmp_path / "so3.json"
    out = subprocess.run([sys.executable, str(script), "--n", "2000", "--repeats", "1", "--out", str(js)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    data = json.loads(js.read_text())
    assert {r["op"] for r in data["results"]} == {"exp", "log"}
    assert data["max_abs_diff"]["exp"] < 1e-12 and data["max_abs_diff"]["log"] < 1e-12


def test_relative_is_rj_ri_transpose_per_edge():
    rng = np.random.default_rng(11)
    R = so3.random_rotations(5, rng)
    edges = np.array([[0, 1], [3, 2], [4, 0]])
    got = so3.relative(R, edges)
    for k, (i, j) in enumerate(edges):
        np.testing.assert_allclose(got[k], R[j] @ R[i].T, atol=1e-15)
    with pytest.raises(ValueError, match="expected"):
        so3.relative(np.zeros((5, 3)), edges)


def _quat_of_vector(w: np.ndarray) -> np.ndarray:
    """The unit quaternion of a rotation vector, built directly (not through a matrix)."""
    th = np.linalg.norm(w, axis=-1, keepdims=True)
    return np.concatenate([np.cos(th / 2), np.sinc(th / (2 * np.pi)) / 2 * w], -1)  # sin(θ/2)/θ·w


@settings(max_examples=400, deadline=None)
@given(axis=unit_axes, theta=angles)
def test_log_quat_inverts_the_quaternion_of_a_rotation_vector(axis: np.ndarray, theta: float) -> None:
    w = theta * axis
    q = _quat_of_vector(w)
    assert _rel_err(so3.log_quat(q), w) < RTOL
    assert _rel_err(so3.log_quat(-q), w) < RTOL  # q and −q are the same rotation


def test_log_quat_and_quat_multiply_agree_with_the_matrix_maps() -> None:
    rng = np.random.default_rng(7)
    A, B = so3.random_rotations(2000, rng), so3.random_rotations(2000, rng)
    qa, qb = so3.quat_from_matrix(A), so3.quat_from_matrix(B)
    assert np.abs(so3.matrix_from_quat(so3.quat_multiply(qa, qb)) - A @ B).max() < 1e-14
    w = so3.log(A)
    ok = np.linalg.norm(w, axis=1) < np.pi - 1e-6  # at π, w and −w are the same rotation
    assert np.abs(so3.log_quat(qa)[ok] - w[ok]).max() < 1e-14
    assert np.abs(np.linalg.norm(so3.log_quat(qa), axis=1) - np.linalg.norm(w, axis=1)).max() < 1e-14
    tiny = rng.standard_normal((50, 3)) * 1e-12
    assert np.abs(so3.log_quat(so3.quat_from_matrix(so3.exp(tiny))) - tiny).max() < 1e-24
