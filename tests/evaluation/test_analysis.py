"""pipeline.evaluation.analysis: the accuracy bound (used by benchmarks/temple_limit.py), checked against Monte Carlo.

The benchmark's claim "an efficient estimator from these edges reaches X° on average" rests on
its information matrix (the signs and frames of ``A_e``) and on its aligned draws. Here the edges
are drawn exactly from the model (``R̃_ij = exp(Δω) R_ij``, ``Δω ~ N(0, H⁻¹)``), solved by ℓ2
in the H metric (the maximum-likelihood estimate), and scored as the evaluation scores: the
median over trials of the median camera error must match the bound's. The pose bound's
Jacobian (rotations and camera centres → a pair's rotation and translation direction) is
checked by finite differences, and its information by its 7-dimensional similarity gauge.
"""

from __future__ import annotations

import numpy as np

from pipeline.core import so3
from pipeline.averaging.irls_h import irls_h
from pipeline.evaluation import analysis
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.synthetic.graphs import paper2_graph, sample_left_noise
from pipeline.core.viewgraph import ViewGraph

def test_information_matches_a_dense_assembly_and_has_the_rotation_gauge():
    g = paper2_graph(7, 0.6, eig_range=(10.0, 1e4), seed=3)
    vg, R = g.vg, g.R_true
    J = analysis.information(vg, R, vg.H)
    ref = np.zeros_like(J)
    for k, (i, j) in enumerate(vg.edges):  # the textbook assembly, one edge at a time
        A = np.zeros((3, 3 * vg.n_cameras))
        A[:, 3 * i:3 * i + 3] = -so3.relative(R, vg.edges)[k]
        A[:, 3 * j:3 * j + 3] = np.eye(3)
        ref += A.T @ vg.H[k] @ A
    np.testing.assert_allclose(J, ref, rtol=1e-12, atol=1e-9)
    # a common rotation of the world, ω_i = R_i v, changes no relative rotation: J's null space
    G = R.reshape(-1, 3)
    assert np.abs(J @ G).max() < 1e-9 * np.abs(J).max()
    assert np.linalg.matrix_rank(J, tol=1e-9 * np.abs(J).max()) == 3 * vg.n_cameras - 3


def test_bound_matches_monte_carlo_of_the_maximum_likelihood_estimate():
    g = paper2_graph(12, 0.35, eig_range=(300.0, 3e5), seed=1)  # strongly anisotropic, ~0.1–3° noise
    vg, R = g.vg, g.R_true
    mask = np.ones(vg.n_cameras, dtype=bool)
    mask[:3] = False  # score a subset, aligned on it, as the benchmark scores pycolmap's images
    pred = analysis.predicted_errors(analysis.information(vg, R, vg.H), R, mask, draws=4000, seed=0)
    rng = np.random.default_rng(7)
    Rrel = so3.relative(R, vg.edges)
    got = []
    for _ in range(120):
        meas = so3.exp(sample_left_noise(vg.H, rng)) @ Rrel
        res = irls_h(ViewGraph(vg.names, vg.edges, meas, H=vg.H), loss="l2", refine=False)
        got.append(np.nanmedian(rotation_errors_deg(res.R, R, mask)))
    ratio = np.median(got) / np.median(pred)
    assert 0.9 < ratio < 1.1, f"Monte Carlo median {np.median(got):.4f}° vs bound {np.median(pred):.4f}°"
    # and the bound is not loose: isotropic weights (ignoring H) do measurably worse
    iso = []
    for _ in range(60):
        meas = so3.exp(sample_left_noise(vg.H, rng)) @ Rrel
        res = irls_h(ViewGraph(vg.names, vg.edges, meas, H=np.broadcast_to(np.eye(3), vg.H.shape).copy()),
                     loss="l2", refine=False)
        iso.append(np.nanmedian(rotation_errors_deg(res.R, R, mask)))
    assert np.median(iso) > 1.2 * np.median(pred)


def _pose_measurement(R, C, edges):
    """What the model predicts a pair measures: ``R_ij`` and ``t = normalize(R_j (c_i − c_j))``."""
    u = np.einsum("mab,mb->ma", R[edges[:, 1]], C[edges[:, 0]] - C[edges[:, 1]])
    t = u / np.linalg.norm(u, axis=1, keepdims=True)
    return so3.relative(R, edges), t


def test_pose_jacobian_matches_finite_differences():
    from pipeline.geometry.ba_model import tangent_basis

    rng = np.random.default_rng(4)
    g = paper2_graph(6, 0.7, seed=2)
    vg, R = g.vg, g.R_true
    C = rng.normal(size=(vg.n_cameras, 3))
    Rij, t = _pose_measurement(R, C, vg.edges)
    B = np.stack([tangent_basis(v) for v in t])
    A = analysis.pose_jacobian(vg, R, C, B)
    i, j = vg.edges.T
    h = 1e-6
    for var in range(4):  # ω_i, ω_j, δc_i, δc_j
        for a in range(3):
            d = np.zeros(3)
            d[a] = h
            # perturb, per edge, the camera that block `var` refers to
            for k in range(vg.n_edges):
                cam = (i, j)[var % 2][k]
                R3, C3 = R.copy(), C.copy()
                if var < 2:
                    R3[cam] = so3.exp(d) @ R[cam]
                else:
                    C3[cam] = C[cam] + d
                Rk, tk = _pose_measurement(R3, C3, vg.edges[k:k + 1])
                dd = so3.log(Rk[0] @ Rij[k].T) / h
                dt = B[k].T @ (tk[0] - t[k]) / h
                np.testing.assert_allclose(np.concatenate([dd, dt]), A[k, :, var, a], atol=2e-5)


def test_pose_information_has_the_similarity_gauge():
    from pipeline.geometry.ba_model import tangent_basis

    rng = np.random.default_rng(5)
    g = paper2_graph(8, 0.6, seed=4)
    vg, R = g.vg, g.R_true
    N = vg.n_cameras
    C = rng.normal(size=(N, 3))
    _, t = _pose_measurement(R, C, vg.edges)
    B = np.stack([tangent_basis(v) for v in t])
    L = rng.normal(size=(vg.n_edges, 5, 5))
    S = L @ np.swapaxes(L, 1, 2) + 0.1 * np.eye(5)
    J = analysis.pose_information(vg, R, C, B, S)
    gauge = []
    for a in range(3):
        v = np.eye(3)[a]
        gauge.append(np.concatenate([-(R @ v).ravel(), np.cross(v, C).ravel()]))  # world rotation
        gauge.append(np.concatenate([np.zeros(3 * N), np.tile(v, N)]))  # world translation
    gauge.append(np.concatenate([np.zeros(3 * N), C.ravel()]))  # world scale
    Gm = np.array(gauge).T
    assert np.abs(J @ Gm).max() < 1e-10 * np.abs(J).max()
    assert np.linalg.matrix_rank(J, tol=1e-9 * np.abs(J).max()) == 6 * N - 7
    # with no translation information it is the rotation-only information
    S0 = S.copy()
    S0[:, 3:, :] = 0.0
    S0[:, :, 3:] = 0.0
    np.testing.assert_allclose(analysis.pose_information(vg, R, C, B, S0)[:3 * N, :3 * N],
                               analysis.information(vg, R, S[:, :3, :3]), rtol=1e-10, atol=1e-9)
