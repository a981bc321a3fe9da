"""pipeline.graph.checks._robust_filter: solving only the components with a cycle (found by counting cameras and
pairs per component) rejects exactly what one subgraph per component did, trees included (the definition here)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.averaging.irls import IRLSConfig
from pipeline.averaging.solve import average
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph
from pipeline.graph.checks import GraphChecks, ViewGraphConfig, _reject, _robust_filter


def _reference(vg, chk, sigma_weak_deg, cfg):
    """The step before: a subgraph for every component, trees (lone cameras too) skipped after it was built."""
    if not chk.kept.any():
        return 0
    # the pairs the robust solution weighs, by their definition: kept, or left unconfirmed when robust_unconfirmed
    keep = np.array([k for k in range(vg.n_edges) if chk.kept[k]
                     or (cfg.robust_unconfirmed and chk.step[k] == "unconfirmed")], dtype=np.int64)
    sub = ViewGraph(vg.names, vg.edges[keep], vg.R_rel[keep], inliers=None if vg.inliers is None else vg.inliers[keep],
                    allow_isolated=True)
    labels = sub.components()
    r = np.full(vg.n_edges, np.nan)
    for c in range(int(labels.max()) + 1):
        comp, restr = sub.subgraph(labels == c)
        if comp.n_edges < comp.n_cameras:
            continue
        res = average(comp, "irls", IRLSConfig(certify=False))
        r[keep[restr.edge_kept[res.edge_index]]] = np.degrees(res.residuals_rad)
    thr = np.maximum(cfg.robust_floor_deg, cfg.robust_k_sigma * cfg.h_inflation * sigma_weak_deg)
    bad = chk.kept & np.isfinite(r) & (r > thr)
    return _reject(chk, bad, "robust", lambda ix: [
        f"the robust solution (IRLS-ℓ½) leaves it {r[k]:.1f}° off (threshold {thr[k]:.1f}°)" for k in ix])


def _checks(M, rng, kept_share=0.9, unconfirmed_share=0.05):
    kept = rng.random(M) < kept_share
    step = np.where(kept, "", np.where(rng.random(M) < unconfirmed_share / (1 - kept_share), "unconfirmed", "cycles"))
    return GraphChecks(kept, np.full(M, "", object), step.astype(object), np.full(M, "normal", object),
                       np.zeros(M, bool), np.zeros(M, bool), np.zeros(M, bool))


def _graph(rng, n_blocks, block, n_lone, n_chain, n_out):
    """Dense blocks (cycles), a chain (a tree), lone cameras; Haar outliers in the blocks."""
    n = n_blocks * block + n_chain + n_lone
    R = so3.random_rotations(n, rng)
    E = [np.stack(np.triu_indices(block, 1), 1) + b * block for b in range(n_blocks)]
    E = np.concatenate(E + [np.stack([np.arange(n_chain - 1), np.arange(1, n_chain)], 1) + n_blocks * block])
    E = E[np.lexsort((E[:, 1], E[:, 0]))]
    Rm = so3.exp(np.deg2rad(0.5) * rng.standard_normal((len(E), 3))) @ (R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2))
    out = rng.choice(len(E), min(n_out, len(E)), replace=False)
    Rm[out] = so3.random_rotations(len(out), rng)
    return ViewGraph([f"c{k}" for k in range(n)], E, Rm, inliers=rng.integers(30, 500, len(E)), allow_isolated=True)


def _same(vg, seed, sw=None, **kw):
    rng = np.random.default_rng(seed)
    a, b = _checks(vg.n_edges, rng, **kw), None
    b = GraphChecks(*(np.copy(getattr(a, f)) for f in ("kept", "reason", "step", "tier", "confirmed", "inconsistent",
                                                       "bridged")))
    sw = rng.uniform(0.2, 2.0, vg.n_edges) if sw is None else sw
    cfg = ViewGraphConfig()
    n_new, n_ref = _robust_filter(vg, a, sw, cfg), _reference(vg, b, sw, cfg)
    assert n_new == n_ref
    for f in ("kept", "reason", "step", "inconsistent"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    return n_new


@pytest.mark.parametrize("seed", range(6))
def test_blocks_chains_and_lone_cameras(seed):
    rng = np.random.default_rng(seed)
    vg = _graph(rng, n_blocks=int(rng.integers(1, 4)), block=int(rng.integers(4, 9)), n_lone=int(rng.integers(0, 30)),
                n_chain=int(rng.integers(2, 6)), n_out=int(rng.integers(0, 6)))
    _same(vg, seed)


def test_outliers_are_rejected_as_before():
    vg = _graph(np.random.default_rng(11), n_blocks=2, block=8, n_lone=20, n_chain=4, n_out=6)
    assert _same(vg, 11, kept_share=0.97) > 0


@pytest.mark.parametrize("case", ["nothing kept", "one pair", "one camera and lone ones", "a triangle beside a pair"])
def test_edge_cases(case):
    rng = np.random.default_rng(5)
    R = so3.random_rotations(6, rng)
    E = {"nothing kept": [[0, 1], [1, 2], [0, 2]], "one pair": [[0, 1]], "one camera and lone ones": [[0, 1]],
         "a triangle beside a pair": [[0, 1], [0, 2], [1, 2], [3, 4]]}[case]  # 3 pairs on 3 cameras: solved
    E = np.array(E)
    Rm = R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    Rm[:1] = so3.exp(np.deg2rad([0.0, 0.0, 40.0])) @ Rm[:1]  # a triangle that does not close: a residual to judge
    vg = ViewGraph([f"c{k}" for k in range(6)], E, Rm, allow_isolated=True)
    n_rejected = _same(vg, 0, sw=np.full(len(E), 0.5), kept_share=0.0 if case == "nothing kept" else 1.0 - 1e-12)
    assert n_rejected == (3 if case == "a triangle beside a pair" else 0)  # its 40° spread: 13.3° on each pair
