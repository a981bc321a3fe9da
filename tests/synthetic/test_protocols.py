"""Real-like synthetic protocols (issue 15): heavy-tailed noise, repeated-structure outliers, miscalibrated H."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.synthetic.protocols import PROTOCOLS, heavy_tailed_noise, make_protocol, miscalibrated_h_graph


@pytest.mark.parametrize("name", sorted(PROTOCOLS))
def test_protocols_are_seeded_connected_and_carry_their_outliers(name):
    a, blocks, sig = make_protocol(name, 150, seed=3)
    b, _, _ = make_protocol(name, 150, seed=3)
    assert np.array_equal(a.vg.R_rel, b.vg.R_rel) and a.vg.is_connected()
    assert 0.05 <= a.outlier_mask.mean() <= 0.16
    assert a.vg.inliers is not None and np.median(a.vg.inliers[a.outlier_mask]) < np.median(a.vg.inliers[~a.outlier_mask])
    err = np.rad2deg(so3.angle_between(so3.relative(a.R_true, a.vg.edges), a.vg.R_rel))
    assert np.median(err[~a.outlier_mask]) < 3.0
    if name.startswith("repeated"):
        assert blocks
        # a block's edges are all wrong by one rotation about one world axis: S = R_jᵀ R̃ R_i
        b0 = blocks[0]
        e = a.vg.edges[b0.edge_idx]
        S = np.swapaxes(a.R_true[e[:, 1]], 1, 2) @ a.vg.R_rel[b0.edge_idx] @ a.R_true[e[:, 0]]
        axes = so3.log(S)
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        assert np.abs(np.abs(axes @ axes[0]) - 1).max() < 0.2  # one axis (± the noise)


def test_heavy_tailed_noise_has_heavy_tails():
    rng = np.random.default_rng(0)
    t, _ = heavy_tailed_noise(20000, rng, "student-t", sigma_deg=1.0, nu=3.0)
    gauss, _ = heavy_tailed_noise(20000, rng, "gaussian", sigma_deg=1.0)
    nt, ng = np.linalg.norm(t, axis=1), np.linalg.norm(gauss, axis=1)
    assert np.quantile(nt, 0.99) / np.median(nt) > 1.5 * np.quantile(ng, 0.99) / np.median(ng)
    with pytest.raises(ValueError, match="unknown noise kind"):
        heavy_tailed_noise(3, rng, "cauchy")


def test_miscalibrated_h_is_overconfident_by_edge():
    g, H_true = miscalibrated_h_graph(80, seed=1)
    ok = ~g.outlier_mask
    ratio = np.trace(g.vg.H, axis1=1, axis2=2)[ok] / np.trace(H_true, axis1=1, axis2=2)[ok]
    assert np.median(ratio) > 5 and np.std(np.log10(ratio)) > 0.5
