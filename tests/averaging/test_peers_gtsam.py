"""The GTSAM peers of the benchmarks, against the truth: our edge convention as GTSAM reads it, the
anisotropic precision as its information, and its robust kernels on the whitened error."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.averaging.peers import ROBUST_KERNELS, have_gtsam, lm_anisotropic, shonan
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.metrics import rotation_errors_deg
from pipeline.synthetic.graphs import paper2_graph, with_outliers

pytestmark = pytest.mark.skipif(not have_gtsam(), reason="GTSAM is in the test extra: pip install -e '.[test]'")


def _noise_free(seed: int = 0) -> tuple[ViewGraph, np.ndarray]:
    g = paper2_graph(12, 0.5, seed=seed)
    true_rel = g.R_true[g.vg.edges[:, 1]] @ np.swapaxes(g.R_true[g.vg.edges[:, 0]], 1, 2)
    return ViewGraph(g.vg.names, g.vg.edges, true_rel, H=g.vg.H), g.R_true


def test_shonan_and_lm_recover_noise_free_rotations_in_our_convention():
    vg, R_true = _noise_free()
    R_sh, lam, _ = shonan(vg)
    assert np.max(rotation_errors_deg(R_sh, R_true)) < 1e-4
    # LM from a start 5° off every camera returns to the truth: the measurement R̃_ijᵀ and
    # the information H are read as our convention means them (R_ij = R_j R_iᵀ, left Δω)
    rng = np.random.default_rng(1)
    from pipeline.core import so3

    R0 = so3.exp(rng.normal(scale=np.deg2rad(5 / np.sqrt(3)), size=(vg.n_cameras, 3))) @ R_true
    R_lm, _, it = lm_anisotropic(vg, R0)
    assert it >= 1
    assert np.max(rotation_errors_deg(R_lm, R_true)) < 1e-4


def test_lm_weighs_edges_by_h_as_their_precision():
    """Two cameras, two parallel measurements 1° apart about the same axis, precisions 1 and 9
    along it: the MAP lies at 9/10 of the way towards the precise one, which only an information
    matrix read as H (not its inverse, not H's square root) gives."""
    from pipeline.core import so3

    axis = np.array([0.0, 0.0, 1.0])
    R_a, R_b = so3.exp(np.zeros((1, 3)))[0], so3.exp(np.deg2rad(1.0) * axis[None])[0]
    H_low, H_high = np.eye(3) * 1e4, np.eye(3) * 9e4
    # edges (0, 1) and (0, 2) with camera 2 tied to 1 by a stiff edge: two measurements of one rotation
    tie = np.eye(3) * 1e12
    vg = ViewGraph(["0", "1", "2"], np.array([[0, 1], [0, 2], [1, 2]]), np.stack([R_a, R_b, np.eye(3)]),
                   H=np.stack([H_low, H_high, tie]))
    R_lm, _, _ = lm_anisotropic(vg, np.stack([np.eye(3)] * 3))
    angle = np.rad2deg(so3.log(R_lm[1] @ R_lm[0].T))
    np.testing.assert_allclose(angle, [0.0, 0.0, 0.9], atol=1e-6)


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_a_robust_kernel_resists_outlier_edges_that_plain_lm_follows(kernel):
    """10% Haar outlier edges among edges of 0.6–1.8° noise, LM started at the truth: least squares
    follows the outliers degrees away; a robust kernel stays near the outlier-free answer."""
    g = paper2_graph(20, 0.5, eig_range=(1e3, 1e4), seed=3)
    vg, _ = with_outliers(g.vg, 0.1, seed=3)
    clean = np.median(rotation_errors_deg(lm_anisotropic(g.vg, g.R_true)[0], g.R_true))
    R_plain, _, _ = lm_anisotropic(vg, g.R_true)
    R_rob, _, _ = lm_anisotropic(vg, g.R_true, robust=(kernel, 1.345 if kernel == "huber" else 1.0))
    e_plain, e_rob = rotation_errors_deg(R_plain, g.R_true), rotation_errors_deg(R_rob, g.R_true)
    assert np.median(e_plain) > 5 * clean
    assert np.median(e_rob) < 1.5 * clean


def test_an_unknown_kernel_is_refused_with_the_choices():
    vg, R_true = _noise_free()
    with pytest.raises(ValueError, match="unknown robust kernel 'welsh'.*huber"):
        lm_anisotropic(vg, R_true, robust=("welsh", 1.0))
    assert "tukey" in ROBUST_KERNELS
