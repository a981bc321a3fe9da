"""Real-like synthetic protocols (issue 15): heavy-tailed noise, repeated-structure outliers, miscalibrated H."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core import so3
from pipeline.synthetic.protocols import PROTOCOLS, dense_graph, heavy_tailed_noise, make_protocol, miscalibrated_h_graph


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


def test_dense_graph_is_dense_seeded_and_its_cameras_differ():
    g, sig = dense_graph(n=120, target_edges=4000, seed=2)
    assert np.array_equal(g.vg.R_rel, dense_graph(n=120, target_edges=4000, seed=2)[0].vg.R_rel)
    assert abs(g.vg.n_edges - 4000) < 200 and g.vg.inliers is None and g.vg.H is None  # as 1DSfM's files
    err = np.rad2deg(so3.angle_between(so3.relative(g.R_true, g.vg.edges), g.vg.R_rel))
    good = ~g.outlier_mask
    assert 0.1 < g.outlier_mask.mean() < 0.5 and np.median(err[g.outlier_mask]) > 60  # Haar outliers
    # the noise scale is per camera: the edges of the noisiest camera are noisier than those of the cleanest
    s = np.full(120, np.nan)
    for k in range(120):  # per camera, in a test
        at = np.any(g.vg.edges == k, axis=1) & good
        s[k] = np.median(err[at]) if at.sum() > 5 else np.nan
    assert np.nanmax(s) > 3 * np.nanmin(s)
    assert np.corrcoef(np.log(sig[good]), np.log(err[good] + 1e-9))[0, 1] > 0.3
    degree = np.bincount(g.vg.edges.ravel(), minlength=120)
    assert degree.max() > 3 * max(np.percentile(degree, 10), 1)  # popular and rare cameras


def test_dense_graph_symmetric_building_is_one_wrong_rotation():
    """The symmetric pairs are all wrong by one half turn S about a common axis: S = R_jᵀ R̃ R_i agrees among them."""
    g, _ = dense_graph(n=100, target_edges=3000, symmetric_cams=15, seed=4)
    plain, _ = dense_graph(n=100, target_edges=3000, seed=4)
    mirror = g.outlier_mask & ~plain.outlier_mask
    assert mirror.sum() > 20
    e = g.vg.edges[mirror]
    S = np.swapaxes(g.R_true[e[:, 1]], 1, 2) @ g.vg.R_rel[mirror] @ g.R_true[e[:, 0]]
    ang = np.rad2deg(so3.angle_between(S, np.broadcast_to(S[0], S.shape)))
    assert np.median(ang) < 3.0 and abs(np.rad2deg(so3.angle_between(S[:1], np.eye(3)[None]))[0] - 180) < 5
