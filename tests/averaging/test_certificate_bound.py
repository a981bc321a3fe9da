"""The certificate's perturbation bound (``certificate/bound.py``): it proves ``S ⪰ −ηI`` only where the exact
spectrum agrees, and on a well-connected graph it decides as the dense inertia test did, with an N×N factor."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from pipeline.averaging.certificate import VERIFIED, certify
from pipeline.averaging.certificate.bound import perturbation_bound
from pipeline.averaging.certificate.newton import polish
from pipeline.averaging.certificate.problem import (certificate_matrix, connection_laplacian, diag_blocks,
                                                    lagrange_multipliers, rounding_floor)
from pipeline.core import so3
from pipeline.core.viewgraph import ViewGraph
from pipeline.synthetic.graphs import paper1_graph

CERTIFY = sys.modules["pipeline.averaging.certificate.certify"]


def _laplacian(vg: ViewGraph, w: np.ndarray):
    WM = w[:, None, None] * np.eye(3)
    return connection_laplacian(vg.n_cameras, vg.edges, WM @ vg.R_rel, diag_blocks(vg.n_cameras, vg.edges, WM))


def _parts(vg: ViewGraph, w: np.ndarray, R: np.ndarray):
    L = _laplacian(vg, w)
    Lam, G = lagrange_multipliers(L, R)
    return Lam, G, certificate_matrix(L, Lam)


@pytest.mark.parametrize("seed", range(4))
def test_the_bound_proves_only_what_the_spectrum_says(seed):
    """Random graphs (10–40 cameras, 30–90% of the pairs, 0.2–10° noise, up to 25% outliers, weights spread over
    two decades, the outliers' down-weighted by 1000 on half of them) at the minimum of their cost that Newton's
    method reaches from the truth, at the truth, at the truth moved by up to 3°, and at random rotations. Wherever
    the bound proves ``S ⪰ −ηI``, eigvalsh agrees; at an η of 0.5 or 0.99 of −λ_min(S) (false) it never proves,
    nor below S's rounding level; and it does prove on the clean instances, so the test can fail both ways."""
    rng = np.random.default_rng(seed)
    proved = refused = 0
    for _ in range(25):
        n = int(rng.integers(10, 41))
        sg = paper1_graph(n, float(rng.uniform(0.3, 0.9)), float(10 ** rng.uniform(-0.7, 1.0)),
                          float(rng.choice([0.0, 0.1, 0.25])), seed=int(rng.integers(1 << 30)))
        vg = sg.vg
        w = 10 ** rng.uniform(-1, 1, vg.n_edges)
        if rng.random() < 0.5:  # outliers down-weighted, as a robust method leaves them
            w[sg.outlier_mask] *= 1e-3
        move = rng.choice([0.0, 0.0, 0.3, 3.0])
        R = sg.R_true @ so3.exp(np.deg2rad(move) * rng.standard_normal((n, 3)))
        if rng.random() < 0.15:
            R = so3.random_rotations(n, rng)
        elif rng.random() < 0.5:  # a stationary point, as a certificate is asked about
            WM = w[:, None, None] * np.eye(3)
            R, _ = polish(n, vg.edges, WM @ vg.R_rel, diag_blocks(n, vg.edges, WM), sg.R_true, max_iterations=50)
        Lam, G, S = _parts(vg, w, R)
        lam_min = float(np.linalg.eigvalsh(S.toarray())[0])
        scale = float(np.abs(S).sum(axis=0).max())
        for eta in (1e-6 * scale, 1e-3 * scale, 0.5 * max(-lam_min, 0.0), 0.99 * max(-lam_min, 0.0)):
            if eta < rounding_floor(S):  # below S's rounding level nothing is proved
                assert perturbation_bound(n, vg.edges, w, vg.R_rel, R, Lam, G, S, eta) is None
                continue
            res = perturbation_bound(n, vg.edges, w, vg.R_rel, R, Lam, G, S, eta)
            if res is not None:
                assert res.ok and res.n_below == 0
                assert lam_min >= -eta, (lam_min, eta)
                proved += 1
            elif lam_min < -eta:
                refused += 1
    assert proved >= 5 and refused >= 5, (proved, refused)


def test_a_well_connected_graph_is_certified_by_the_bound_as_by_the_inertia(monkeypatch):
    """A 1DSfM-like graph (300 cameras, 12,000 pairs, about 30% of them outliers): IRLS's certificate decides by the
    bound (an N×N factor, ``bound_s``) and reaches the verdict, η and gap bound of the dense inertia test of S
    (``factor_s``), which decides where the bound is switched off."""
    from pipeline.averaging.solve import average
    from pipeline.synthetic.protocols import dense_graph

    g, _ = dense_graph(n=300, target_edges=12000, seed=3)
    vg, _ = g.vg.largest_component()
    res = average(vg, "irls")
    by_bound = res.stats["certificate"]
    monkeypatch.setattr(CERTIFY, "perturbation_bound", lambda *a, **k: None)
    again = average(vg, "irls").stats["certificate"]
    assert "bound_s" in by_bound["times"] and "factor_s" not in by_bound["times"]
    assert "factor_s" in again["times"] and "bound_s" not in again["times"]
    assert by_bound["verdict"] == again["verdict"] == VERIFIED
    for k in ("eta", "gap_bound", "cost", "n_kept"):
        assert by_bound[k] == pytest.approx(again[k], rel=1e-12), k


def test_a_local_minimum_is_not_proved_by_the_bound():
    """The 2π-twisted planar ring (a local minimum of the chordal cost; 12 cameras, whose S has a dense pattern,
    so the bound is tried first): the bound cannot prove it, and the exact test refutes it."""
    rng = np.random.default_rng(0)
    n = 12
    R = so3.exp(np.outer(rng.uniform(-3, 3, n), [0.0, 0.0, 1.0]))
    vg = ViewGraph.from_absolute([str(i) for i in range(n)], R, np.stack([np.arange(n), (np.arange(n) + 1) % n], 1))
    twisted = so3.exp(np.outer(2 * np.pi * np.arange(n) / n, [0.0, 0.0, 1.0])) @ R
    w = np.ones(vg.n_edges)
    Lam, G, S = _parts(vg, w, twisted)
    assert perturbation_bound(n, vg.edges, w, vg.R_rel, twisted, Lam, G, S, 1e-3) is None
    cert, _ = certify(n, vg.edges, vg.R_rel, twisted, w, do_polish=False, k_margin=0)  # k_margin 0, as IRLS's
    assert cert.verdict == "not verified" and "factor_s" in cert.times
    ok, _ = certify(n, vg.edges, vg.R_rel, R, w, do_polish=False, k_margin=0)  # the untwisted ring: by the bound
    assert ok.verdict == VERIFIED and "bound_s" in ok.times


def test_a_given_metric_keeps_the_inertia_test():
    """The bound is written for M = I with the weights as given; a metric M_e = c_e·I (isotropic, but weighing the
    edges by c_e) is decided by the inertia, with the verdict the same weights c_e·w_e give through the bound."""
    sg = paper1_graph(20, 0.6, 1.0, 0.0, seed=4)
    vg = sg.vg
    c = np.random.default_rng(4).uniform(0.5, 4.0, vg.n_edges)
    M = c[:, None, None] * np.eye(3)
    cert_m, _ = certify(vg.n_cameras, vg.edges, vg.R_rel, sg.R_true, np.ones(vg.n_edges), M, k_margin=0)
    cert_w, _ = certify(vg.n_cameras, vg.edges, vg.R_rel, sg.R_true, c, k_margin=0)
    assert "factor_s" in cert_m.times and "bound_s" not in cert_m.times
    assert "bound_s" in cert_w.times
    assert cert_m.verdict == cert_w.verdict == VERIFIED
    assert cert_m.cost == pytest.approx(cert_w.cost, rel=1e-9)


def test_the_bound_steps_aside_where_its_dense_copies_would_not_fit(monkeypatch):
    """The bound holds two N×N copies; where they would not fit (``dense_inertia_fits``) it proves nothing and the
    inertia decides, with the same verdict."""
    import pipeline.averaging.certificate.bound as bound_mod

    sg = paper1_graph(20, 0.6, 0.0, 0.0, seed=5)  # noise-free: the truth is the minimum
    vg = sg.vg
    w = np.ones(vg.n_edges)
    Lam, G, S = _parts(vg, w, sg.R_true)
    assert perturbation_bound(vg.n_cameras, vg.edges, w, vg.R_rel, sg.R_true, Lam, G, S, 1e-3) is not None
    monkeypatch.setattr(bound_mod, "dense_inertia_fits", lambda n: False)
    assert perturbation_bound(vg.n_cameras, vg.edges, w, vg.R_rel, sg.R_true, Lam, G, S, 1e-3) is None
    cert, _ = certify(vg.n_cameras, vg.edges, vg.R_rel, sg.R_true, w, k_margin=0)
    assert cert.verdict == VERIFIED and "factor_s" in cert.times
