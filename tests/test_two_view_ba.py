"""Tests of the two-view bundle adjustment and its rotation Hessian (issue 6)."""

from __future__ import annotations

import json
import subprocess
import sys
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pipeline.core import so3
from pipeline import two_view_ba as tb
from pipeline.core.viewgraph import ViewGraph


def _skewed_K(f: float, cx: float, cy: float, aspect: float = 1.02, skew: float = 0.7) -> np.ndarray:
    return np.array([[f, skew, cx], [0.0, f * aspect, cy], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def pair200() -> tb.SyntheticPair:
    return tb.synthetic_pair(200, sigma_px=1.0, outlier_frac=0.0, seed=3)


# ------------------------------------------------------------------ Jacobians
def test_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(0)
    n = 25
    Ki, Kj = _skewed_K(500.0, 320.0, 240.0), _skewed_K(650.0, 300.0, 250.0, aspect=0.97, skew=-1.3)
    R = so3.exp(np.array([0.1, -0.25, 0.05]))
    t = np.array([0.8, 0.1, -0.2])
    t /= np.linalg.norm(t)
    P = np.column_stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.05, 0.3, n)])
    x_i = rng.uniform(0, 640, (n, 2))
    x_j = rng.uniform(0, 480, (n, 2))
    r0, J = tb.residuals_and_jacobian(R, t, P, x_i, x_j, Ki, Kj)
    assert r0.shape == (n, 4) and J.shape == (n, 4, 8)
    B = tb.tangent_basis(t)
    eps = 1e-6
    J_fd = np.zeros_like(J)
    for k in range(8):
        rs = []
        for sgn in (1.0, -1.0):
            Rk, tk, Pk = R, t, P.copy()
            if k < 3:
                Rk = so3.exp(sgn * eps * np.eye(3)[k]) @ R  # left perturbation
            elif k < 5:
                tk = t + sgn * eps * B[:, k - 3]
                tk = tk / np.linalg.norm(tk)
            else:
                Pk[:, k - 5] += sgn * eps
            rs.append(tb.residuals_and_jacobian(Rk, tk, Pk, x_i, x_j, Ki, Kj)[0])
        J_fd[:, :, k] = (rs[0] - rs[1]) / (2 * eps)
    scale = np.abs(J_fd).max()
    np.testing.assert_allclose(J, J_fd, atol=1e-6 * scale, rtol=1e-5)


def test_tangent_basis_is_orthonormal_and_tangent() -> None:
    for t in (np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), np.array([0.3, -0.4, 0.866])):
        t = t / np.linalg.norm(t)
        B = tb.tangent_basis(t)
        np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-12)
        np.testing.assert_allclose(B.T @ t, 0.0, atol=1e-12)


def test_closed_form_schur_equals_block_schur(pair200: tb.SyntheticPair) -> None:
    """The rank-one elimination in refine_pair equals U − Σ W V⁻¹ Wᵀ with batched 3×3 inverses."""
    sp = pair200
    Kj = _skewed_K(610.0, 330.0, 235.0, skew=0.5)
    # Re-project image j with a skewed K_j so the skew paths are exercised.
    xj_n = np.column_stack([sp.x_j, np.ones(len(sp.x_j))]) @ np.linalg.inv(sp.K_j).T
    x_j = (xj_n @ Kj.T)[:, :2]
    res = tb.refine_pair(sp.x_i, x_j, sp.K_i, Kj, sp.R0, sp.t0, tb.BAConfig(tol=1e-12))
    _, J = tb.residuals_and_jacobian(res.R, res.t, res.point_params, sp.x_i, x_j, sp.K_i, Kj)
    J = J[res.inlier_mask]  # H is built from the inliers (unit weights)
    U, V, Wm = tb.normal_equation_blocks(J)
    H_block, S_block = tb.rotation_hessian(U, V, Wm)
    np.testing.assert_allclose(H_block / res.sigma2, res.H, rtol=1e-8)
    np.testing.assert_allclose(S_block / res.sigma2, res.H_pose, rtol=1e-7, atol=1e-9 * np.abs(res.H_pose).max())
    # Also against a dense inverse of the full (3n+5) information: the rotation block of its inverse.
    Jf = np.zeros((4 * len(J), 5 + 3 * len(J)))
    for k in range(len(J)):
        Jf[4 * k : 4 * k + 4, :5] = J[k, :, :5]
        Jf[4 * k : 4 * k + 4, 5 + 3 * k : 8 + 3 * k] = J[k, :, 5:]
    info = Jf.T @ Jf
    cov = np.linalg.inv(info)
    np.testing.assert_allclose(np.linalg.inv(cov[:3, :3]) / res.sigma2, res.H, rtol=1e-5)


# --------------------------------------------------------------- refinement
def test_noise_free_pair_recovers_truth_from_rough_start() -> None:
    sp = tb.synthetic_pair(80, sigma_px=0.0, seed=5, init_perturb_deg=3.0)
    res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(sigma_px=1.0))
    assert np.rad2deg(so3.angle_between(res.R, sp.R)) < 1e-6
    assert np.rad2deg(np.arccos(min(1.0, res.t @ sp.t))) < 1e-5
    np.testing.assert_allclose(res.points, sp.points, rtol=1e-6)
    assert res.converged and res.iterations <= 12


def test_result_fields_and_convention(pair200: tb.SyntheticPair) -> None:
    sp = pair200
    res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
    n = len(sp.x_i)
    assert res.R.shape == (3, 3) and res.t.shape == (3,) and res.points.shape == (n, 3)
    assert res.residuals.shape == (n, 4) and res.inlier_mask.shape == (n,)
    assert abs(np.linalg.norm(res.t) - 1.0) < 1e-12
    np.testing.assert_allclose(res.H, res.H.T, atol=0)
    assert np.linalg.eigvalsh(res.H)[0] > 0
    # BA lowers the error of the 1° perturbed start to a small fraction of it.
    assert np.rad2deg(so3.angle_between(res.R, sp.R)) < 0.5
    assert res.cost_history[0] > res.cost_history[-1]
    # x_j = R x_i + t holds for the refined points (projected), within the noise.
    Xj = res.points @ res.R.T + res.t
    proj = (Xj @ sp.K_j.T)[:, :2] / Xj[:, 2:3]
    assert np.sqrt(np.mean(np.sum((proj - sp.x_j) ** 2, axis=1))) < 2.0
    assert 0.7 < res.sigma2 < 1.4 and res.sigma2_estimated


def test_known_sigma_is_used_verbatim(pair200: tb.SyntheticPair) -> None:
    sp = pair200
    # Plain least squares: the fit itself does not depend on σ, only H's scale does.
    a = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(sigma_px=2.0, loss="none", refit_inliers=False))
    b = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(sigma_px=1.0, loss="none", refit_inliers=False))
    assert a.sigma2 == 4.0 and not a.sigma2_estimated
    np.testing.assert_allclose(a.H * 4.0, b.H, rtol=1e-6)


def test_ba_off_keeps_ransac_pose(pair200: tb.SyntheticPair) -> None:
    sp = pair200
    res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(enabled=False))
    np.testing.assert_allclose(res.R, sp.R0, atol=1e-12)
    np.testing.assert_allclose(res.t, sp.t0, atol=1e-12)
    assert res.iterations >= 1 and np.linalg.eigvalsh(res.H)[0] > 0
    # A 1° wrong pose leaves larger residuals than the refined one.
    on = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
    assert res.sigma2 > 2.0 * on.sigma2


def test_robust_loss_and_refit_reject_outliers() -> None:
    sp = tb.synthetic_pair(200, sigma_px=1.0, outlier_frac=0.15, seed=11)
    err = {}
    for loss in ("none", "cauchy", "huber"):
        res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(loss=loss))
        err[loss] = np.rad2deg(so3.angle_between(res.R, sp.R))
        if loss == "cauchy":
            # Outliers found: few of them survive and almost no inlier is lost.
            assert np.mean(res.inlier_mask[sp.outlier_mask]) < 0.2
            assert np.mean(res.inlier_mask[~sp.outlier_mask]) > 0.97
            assert 0.7 < res.sigma2 < 1.4
    assert err["cauchy"] < 0.3 and err["huber"] < 0.3
    # Plain least squares without the robust start is visibly hurt.
    no_refit = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(loss="none", refit_inliers=False))
    assert no_refit.sigma2 > 10.0


@pytest.mark.slow
def test_calibration_small_monte_carlo() -> None:
    """100 noise draws on one scene: mean NEES ≈ 3 and covariance ≈ mean(H)⁻¹.

    Bounds: with 100 draws the mean of χ²₃ has sd √(6/100) ≈ 0.245, so [2.3, 3.7]
    is ≈ ±2.9 sd; a variance ratio along a fixed direction has sd √(2/100) ≈ 0.14,
    so [0.6, 1.5] is ≈ 2.9 sd below and 3.5 sd above.
    """
    for sigma_known in (True, False):
        cfg = tb.BAConfig(sigma_px=1.0 if sigma_known else None)
        dws, Hs = [], []
        for d in range(100):
            sp = tb.synthetic_pair(200, sigma_px=1.0, seed=1000 + d, scene_seed=42)
            res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, cfg)
            dws.append(so3.log(sp.R @ res.R.T))  # R_true = exp([Δω]×) R̂
            Hs.append(res.H)
        dws, Hs = np.array(dws), np.array(Hs)
        nees = np.einsum("ni,nij,nj->n", dws, Hs, dws)
        assert 2.3 < nees.mean() < 3.7, (sigma_known, nees.mean())
        C = np.cov(dws.T, bias=True) + np.outer(dws.mean(0), dws.mean(0))
        lam, Q = np.linalg.eigh(np.linalg.inv(Hs.mean(0)))
        ratios = np.einsum("ik,ij,jk->k", Q, C, Q) / lam
        assert np.all((ratios > 0.6) & (ratios < 1.5)), (sigma_known, ratios)


def test_least_certain_direction_is_the_weak_one() -> None:
    """H's smallest eigenvector points where a perturbation changes the residuals least."""
    sp = tb.synthetic_pair(150, sigma_px=0.5, seed=9)
    res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(sigma_px=0.5))
    lam, Q = np.linalg.eigh(res.H)
    assert lam[-1] / lam[0] > 3.0  # two-view rotation precision is anisotropic
    cfg = tb.BAConfig(sigma_px=0.5, enabled=False)
    costs = []
    for k in (0, 2):
        R_pert = so3.exp(1e-3 * Q[:, k]) @ res.R
        # Best translation is not re-fitted here: compare the points-only fits.
        r = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, R_pert, res.t, cfg)
        costs.append(np.sum(r.residuals[r.inlier_mask] ** 2))
    assert costs[0] < costs[1]


# ------------------------------------------------------------------ rejects
@pytest.mark.parametrize(
    "kw, match",
    [
        ({"loss": "tukey"}, "loss='tukey' is not supported"),
        ({"sigma_px": -1.0}, "sigma_px=-1.0"),
        ({"loss_scale_px": 0.0}, "loss_scale_px=0.0"),
        ({"loss_scale_sigmas": 0.0}, "loss_scale_sigmas=0.0"),
        ({"inlier_chi2": -2.0}, "inlier_chi2=-2.0"),
        ({"max_iterations": 0}, "max_iterations=0"),
        ({"min_points": 3}, "min_points=3"),
        ({"workers": 0}, "workers=0"),
    ],
)
def test_config_rejects_bad_values(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        tb.BAConfig(**kw)


def test_refine_pair_rejects_bad_inputs(pair200: tb.SyntheticPair) -> None:
    sp = pair200
    args = [sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0]
    with pytest.raises(ValueError, match=r"x_i.shape=\(200, 2\), x_j.shape=\(199, 2\)"):
        tb.refine_pair(sp.x_i, sp.x_j[:-1], *args[2:])
    bad = sp.x_i.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        tb.refine_pair(bad, *args[1:])
    with pytest.raises(ValueError, match=r"K_j.shape=\(2, 3\)"):
        tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j[:2], sp.R0, sp.t0)
    Kbad = sp.K_i.copy()
    Kbad[2] = [0.0, 0.0, 2.0]
    with pytest.raises(ValueError, match="K_i must be an upper-triangular pinhole"):
        tb.refine_pair(sp.x_i, sp.x_j, Kbad, sp.K_j, sp.R0, sp.t0)
    with pytest.raises(ValueError, match="R0 must be a"):
        tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, 2.0 * sp.R0, sp.t0)
    with pytest.raises(ValueError, match="R0 must be a"):
        tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, -sp.R0, sp.t0)
    with pytest.raises(ValueError, match="t0 must be a finite"):
        tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, np.array([np.nan, 0.0, 1.0]))
    with pytest.raises(tb.TwoViewBAError, match="pair has 8 correspondences but min_points=12"):
        tb.refine_pair(sp.x_i[:8], sp.x_j[:8], sp.K_i, sp.K_j, sp.R0, sp.t0)


def test_zero_translation_start_is_recovered(pair200: tb.SyntheticPair) -> None:
    """A front end may report t = 0 (pure rotation); the BA then starts from the epipolar t."""
    sp = pair200
    res = tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, np.zeros(3))
    assert np.rad2deg(np.arccos(min(1.0, res.t @ sp.t))) < 2.0
    assert np.rad2deg(so3.angle_between(res.R, sp.R)) < 0.5


def test_pure_rotation_pair_gives_finite_H() -> None:
    """Zero baseline: t is unobservable, the rotation is not; H must stay finite and PD."""
    rng = np.random.default_rng(4)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    R = so3.exp(np.array([0.02, -0.05, 0.01]))
    x_i = rng.uniform([0, 0], [640, 480], (150, 2))
    m = np.column_stack([x_i, np.ones(150)]) @ np.linalg.inv(K).T
    q = m @ R.T @ K.T
    x_j = q[:, :2] / q[:, 2:] + 0.3 * rng.standard_normal((150, 2))
    x_i = x_i + 0.3 * rng.standard_normal((150, 2))
    res = tb.refine_pair(x_i, x_j, K, K, so3.exp(np.array([0.0, 0.003, 0.0])) @ R, np.zeros(3))
    assert np.rad2deg(so3.angle_between(res.R, R)) < 0.05
    lam = np.linalg.eigvalsh(res.H)
    assert np.all(np.isfinite(lam)) and lam[0] > 0


def test_mostly_outliers_is_rejected_with_reason() -> None:
    sp = tb.synthetic_pair(40, sigma_px=1.0, outlier_frac=0.8, seed=2)
    with pytest.raises(tb.TwoViewBAError, match="inliers"):
        tb.refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, tb.BAConfig(sigma_px=1.0, min_points=20))


def test_synthetic_pair_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="outlier_frac=1.5"):
        tb.synthetic_pair(10, outlier_frac=1.5)


# ---------------------------------------------------------------- the stage
@dataclass
class _FakeTwoView:
    vg: ViewGraph
    K: np.ndarray
    sizes: np.ndarray
    corr: list
    rejected: list

    def correspondences(self, k: int):
        return self.corr[k]


def _fake_work(tmp_path: Path, n_cams: int = 4, with_bad_pair: bool = True):
    """A WORK folder stand-in: three-plus synthetic pairs, one of them hopeless."""
    rng = np.random.default_rng(1)
    R_abs = so3.random_rotations(n_cams, rng)
    edges, R_rel, ts, corr, truth = [], [], [], [], []
    K = None
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            sp = tb.synthetic_pair(60, sigma_px=0.5, seed=10 * i + j)
            K = sp.K_i
            edges.append((i, j))
            R_rel.append(sp.R0)
            ts.append(sp.t0)
            corr.append((sp.x_i, sp.x_j))
            truth.append(sp.R)
    if with_bad_pair:
        corr[-1] = (corr[-1][0][:5], corr[-1][1][:5])
    vg = ViewGraph([f"im{k}.png" for k in range(n_cams)], np.array(edges), np.array(R_rel),
                   inliers=np.array([len(c[0]) for c in corr]), stats={"t": np.array(ts)}, allow_isolated=True)
    data = _FakeTwoView(vg, np.repeat(K[None], n_cams, 0), np.tile([640, 480], (n_cams, 1)), corr, [])
    return data, np.array(truth), R_abs


def test_main_writes_graph_with_H_resumes_and_reports_dropped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data, truth, _ = _fake_work(tmp_path)
    calls = {"n": 0}

    def load_two_view(work: Path):
        calls["n"] += 1
        return data

    fake = types.ModuleType("pipeline.two_view")
    fake.load_two_view = load_two_view
    monkeypatch.setitem(sys.modules, "pipeline.two_view", fake)
    work = tmp_path / "work"
    work.mkdir()
    cfg = tb.BAConfig(workers=2, chunk_size=2)
    out = tb.main(work, cfg, progress=False)
    assert out == work / "viewgraph.npz"
    vg = ViewGraph.load(out, allow_isolated=True)
    M = data.vg.n_edges
    assert vg.n_edges == M - 1 and vg.H is not None
    np.testing.assert_array_equal(vg.edges, data.vg.edges[:-1])
    for key in ("t", "t_ransac", "R_ransac", "ba_sigma2", "ba_n_inliers", "ba_iterations", "ba_cond_H"):
        assert key in vg.stats and len(vg.stats[key]) == vg.n_edges
    # BA beats the 1° perturbed "RANSAC" rotations.
    err_ba = np.rad2deg(so3.angle_between(vg.R_rel, truth[:-1]))
    err_in = np.rad2deg(so3.angle_between(vg.stats["R_ransac"], truth[:-1]))
    assert np.median(err_ba) < 0.5 * np.median(err_in)
    summary = json.loads((work / "viewgraph.json").read_text())
    assert summary["n_pairs_out"] == M - 1 and len(summary["dropped"]) == 1
    assert "min_points" in summary["dropped"][0]["reason"]
    # Resume: same config → no work (file untouched); new config → recomputed.
    mtime = out.stat().st_mtime_ns
    assert tb.main(work, cfg, progress=False) == out
    assert out.stat().st_mtime_ns == mtime
    tb.main(work, tb.BAConfig(workers=1, sigma_px=0.5), progress=False)
    assert out.stat().st_mtime_ns != mtime
    vg2 = ViewGraph.load(out, allow_isolated=True)
    np.testing.assert_allclose(vg2.stats["ba_sigma2"], 0.25)


def test_main_rejects_missing_work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake = types.ModuleType("pipeline.two_view")
    fake.load_two_view = lambda work: None
    monkeypatch.setitem(sys.modules, "pipeline.two_view", fake)
    with pytest.raises(Exception, match="does not exist"):
        tb.main(tmp_path / "nope", progress=False)


def test_main_rejects_graph_without_translations(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data, _, _ = _fake_work(tmp_path, n_cams=3, with_bad_pair=False)
    data.vg = ViewGraph(data.vg.names, data.vg.edges, data.vg.R_rel, allow_isolated=True)
    fake = types.ModuleType("pipeline.two_view")
    fake.load_two_view = lambda work: data
    monkeypatch.setitem(sys.modules, "pipeline.two_view", fake)
    with pytest.raises(Exception, match="no per-edge 't' statistic"):
        tb.main(tmp_path, progress=False)


def test_cli_help() -> None:
    out = subprocess.run([sys.executable, "-m", "pipeline.two_view_ba", "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--work" in out.stdout and "--sigma-px" in out.stdout


def test_cli_missing_work_is_one_line_error(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "pipeline.two_view_ba", "--work", str(tmp_path / "missing")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert out.stderr.strip().startswith("error:") and len(out.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_stage_on_rendered_front_end(tmp_path: Path) -> None:
    """End to end on the real front end: 3 rendered views → WORK → BA graph with H, better than RANSAC."""
    from pipeline import features, matching, two_view
    from pipeline.evaluate import edge_stats, match_reference
    from pipeline.io.references import read_reference
    from pipeline.synthetic.render import render_scene

    images, work = tmp_path / "images", tmp_path / "work"
    render_scene(3, seed=3, out=images)
    features.main(images, work, progress=False)
    matching.main(work, progress=False)
    two_view.main(work, progress=False)
    out = tb.main(work, tb.BAConfig(workers=2, chunk_size=2), progress=False)
    vg = ViewGraph.load(out, allow_isolated=True)
    data = two_view.load_two_view(work)
    assert vg.n_edges == data.vg.n_edges >= 2 and vg.H is not None
    ref = read_reference(images / "cameras.txt")
    R_ref, mask = match_reference(vg.names, ref.names, ref.R)
    ba = edge_stats(vg, R_ref, mask)["median_deg"]
    ransac = edge_stats(ViewGraph(vg.names, vg.edges, vg.stats["R_ransac"], allow_isolated=True), R_ref, mask)["median_deg"]
    # Both are a few hundredths of a degree here; on 3 edges their order is noise (the
    # benchmark compares them on 66 edges), so only a gross regression is a failure.
    assert ba < 0.1 and ba < 1.5 * ransac + 0.01
    assert np.all(np.linalg.eigvalsh(vg.H)[:, 0] > 0)
    assert np.all(vg.stats["ba_n_inliers"] > 0.8 * vg.stats["ba_n_points"])
