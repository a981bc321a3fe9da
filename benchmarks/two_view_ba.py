"""Two-view BA benchmark (issue 6): speed vs scipy, accuracy vs RANSAC, anisotropy of H.

Sections (all in one run, peers in the same run):

1. **speed** — one synthetic pair with 1000 points (σ = 1 px, 1° initial error):
   ``refine_pair`` (default robust config, and plain least squares) vs
   ``scipy.optimize.least_squares`` (TRF, sparse finite-difference Jacobian through
   ``jac_sparsity``, ``tr_solver='lsmr'``) on the same residuals, from the same start.
   Times are medians of repeats; wall time, its minimum (the least-contended run) and
   this thread's CPU time are given (the machine is shared, so CPU time is the fairer
   "one core" figure). Then both
   are converged tightly and their rotation Hessians compared: scipy's from its own
   finite-difference Jacobian at its optimum, marginalized by a generic sparse solve.
2. **accuracy** — for each WORK folder (rendered 12-view scene, Strecha fountain-P11,
   Middlebury templeSparseRing) built with the front end: median relative-rotation
   error of the RANSAC graph vs the BA graph against the reference cameras
   (``pipeline.evaluation.metrics.edge_stats``).
3. **anisotropy** — the distribution of cond(H) over the pairs of each dataset, and on
   rendered pairs a Monte-Carlo check: the inlier correspondences are made exact with
   the true cameras (triangulated with the true pose, re-projected), 200 draws of
   σ = 1 px noise are added and refined; the least-certain eigenvector of mean(H) is
   compared with the principal axis of the spread of Δω.

Usage: ``python benchmarks/two_view_ba.py [--quick] [--work-root DIR] [--skip-real]``.
Writes ``benchmarks/results/two_view_ba.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import scipy.sparse as sps  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.optimize._numdiff import approx_derivative  # noqa: E402
from scipy.sparse.linalg import splu  # noqa: E402

from pipeline.core import so3  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.geometry.ba_model import project, tangent_basis, triangulate  # noqa: E402
from pipeline.geometry.ba_solver import BAConfig, refine_pair  # noqa: E402
from pipeline.geometry.ba_stage import TwoViewBAStage  # noqa: E402
from pipeline.synthetic.pairs import synthetic_pair  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "two_view_ba.json"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
DATASETS = {
    "rendered12": (None, None),  # rendered on demand into WORK_ROOT/rendered12/images
    "fountain-P11": (SHARED / "strecha" / "fountain-P11" / "images", SHARED / "strecha" / "fountain-P11" / "gt_dense_cameras"),
    "templeSparseRing": (SHARED / "middlebury-templeSparseRing", SHARED / "middlebury-templeSparseRing" / "templeSR_par.txt"),
}


# ----------------------------------------------------------------- scipy peer
class ScipyPair:
    """The same two-view problem for ``least_squares``: x = (δ (3), δt (2), (a, b, ρ) per point)."""

    def __init__(self, x_i, x_j, K_i, K_j, R_base, t_base):
        self.xi, self.xj = np.ascontiguousarray(x_i.T), np.ascontiguousarray(x_j.T)
        self.Ki, self.Kj = K_i, K_j
        self.rebase(R_base, t_base)
        n = x_i.shape[0]
        rows, cols = [], []
        for c in range(5):  # pose columns touch image-j rows of every point
            rows.append(4 * np.arange(n) + 2)
            rows.append(4 * np.arange(n) + 3)
            cols += [np.full(n, c)] * 2
        for r in range(4):
            for c in range(3):
                rows.append(4 * np.arange(n) + r)
                cols.append(5 + 3 * np.arange(n) + c)
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self.sparsity = sps.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(4 * n, 5 + 3 * n))

    def rebase(self, R, t):
        self.R_b, self.t_b, self.B = R.copy(), t / np.linalg.norm(t), tangent_basis(t / np.linalg.norm(t))

    def pose(self, x):
        t = self.t_b + self.B @ x[3:5]
        return so3.exp(x[:3]) @ self.R_b, t / np.linalg.norm(t)

    def fun(self, x):
        R, t = self.pose(x)
        P = x[5:].reshape(-1, 3).T
        r, _, _ = project(R, t, P, self.xi, self.xj, self.Ki, self.Kj)
        return r.T.ravel()

    def hessian(self, x, sigma2):
        """Rotation precision from a 3-point sparse FD Jacobian at x (rebased to δ = 0)."""
        R, t = self.pose(x)
        self.rebase(R, t)
        x0 = np.concatenate([np.zeros(5), x[5:]])
        J = sps.csc_matrix(approx_derivative(self.fun, x0, method="3-point", sparsity=self.sparsity))
        I = (J.T @ J).tocsc()
        A = I[:5, :5].toarray()
        Bm = I[:5, 5:].toarray()
        D = splu(I[5:, 5:].tocsc())
        S = A - Bm @ D.solve(Bm.T)
        cov = np.linalg.inv(S)
        return np.linalg.inv(cov[:3, :3]) / sigma2, R, t


def speed_section(quick: bool) -> dict:
    sp = synthetic_pair(1000, sigma_px=1.0, seed=1)
    reps = 10 if quick else 30
    out: dict = {"n_points": 1000}

    def timed(f, reps):
        walls, cpus, res = [], [], None
        for _ in range(reps):
            w0, c0 = time.perf_counter(), time.thread_time()
            res = f()
            cpus.append(time.thread_time() - c0)
            walls.append(time.perf_counter() - w0)
        mins["last"] = float(np.min(walls))
        return float(np.median(walls)), float(np.median(cpus)), res

    mins: dict = {}

    cfgs = {"ours default (cauchy + refit)": BAConfig(), "ours least squares": BAConfig(loss="none", refit_inliers=False)}
    for name, cfg in cfgs.items():
        w, c, res = timed(lambda: refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, cfg), reps)
        out[name] = {"wall_ms": 1e3 * w, "cpu_ms": 1e3 * c, "min_wall_ms": 1e3 * mins["last"], "iterations": res.iterations,
                     "rot_err_deg": float(np.rad2deg(so3.angle_between(res.R, sp.R)))}
    P0 = triangulate(sp.R0, sp.t0, np.ascontiguousarray(sp.x_i.T), np.ascontiguousarray(sp.x_j.T), sp.K_i, sp.K_j)
    x0 = np.concatenate([np.zeros(5), P0.T.ravel()])

    def run_scipy(loss: str = "linear", tol: float = 1e-8):
        prob = ScipyPair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0)
        return prob, least_squares(prob.fun, x0, jac_sparsity=prob.sparsity, method="trf", tr_solver="lsmr",
                                   x_scale="jac", loss=loss, f_scale=3.0, ftol=tol, xtol=tol, gtol=tol)

    sreps = 3 if quick else 5
    for name, loss in (("scipy least squares", "linear"), ("scipy cauchy", "cauchy")):
        w, c, (prob, res) = timed(lambda: run_scipy(loss), sreps)
        R, _ = prob.pose(res.x)
        out[name] = {"wall_ms": 1e3 * w, "cpu_ms": 1e3 * c, "min_wall_ms": 1e3 * mins["last"], "nfev": int(res.nfev), "njev": int(res.njev or 0),
                     "rot_err_deg": float(np.rad2deg(so3.angle_between(R, sp.R)))}
    out["ratio_wall_scipy_ls_over_ours_ls"] = out["scipy least squares"]["wall_ms"] / out["ours least squares"]["wall_ms"]
    out["ratio_cpu_scipy_ls_over_ours_ls"] = out["scipy least squares"]["cpu_ms"] / out["ours least squares"]["cpu_ms"]
    out["ratio_wall_scipy_cauchy_over_ours_default"] = out["scipy cauchy"]["wall_ms"] / out["ours default (cauchy + refit)"]["wall_ms"]
    out["ratio_cpu_scipy_cauchy_over_ours_default"] = out["scipy cauchy"]["cpu_ms"] / out["ours default (cauchy + refit)"]["cpu_ms"]
    # Same Hessian: both converged tightly on the same least-squares problem, σ = 1 px.
    ours = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0,
                          BAConfig(loss="none", refit_inliers=False, sigma_px=1.0, tol=1e-15, max_iterations=100))
    prob, res = run_scipy("linear", 1e-15)
    H_s, R_s, _ = prob.hessian(res.x, 1.0)
    ours_default_tol = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0,
                                      BAConfig(loss="none", refit_inliers=False, sigma_px=1.0))
    rel = lambda A, B: float(np.linalg.norm(A - B) / np.linalg.norm(B))  # noqa: E731
    out["hessian"] = {
        "rel_diff_ours_tight_vs_scipy": rel(ours.H, H_s),
        "rel_diff_ours_default_tol_vs_scipy": rel(ours_default_tol.H, H_s),
        "rotation_diff_deg": float(np.rad2deg(so3.angle_between(ours.R, R_s))),
        "eig_H_ours": np.linalg.eigvalsh(ours.H).tolist(),
        "eig_H_scipy": np.linalg.eigvalsh(H_s).tolist(),
    }
    print("\n== speed: one pair, 1000 points ==")
    print(f"{'method':34s} {'wall ms':>9s} {'min wall':>9s} {'cpu ms':>9s} {'rot err °':>10s}")
    for name in list(cfgs) + ["scipy least squares", "scipy cauchy"]:
        r = out[name]
        print(f"{name:34s} {r['wall_ms']:9.2f} {r['min_wall_ms']:9.2f} {r['cpu_ms']:9.2f} {r['rot_err_deg']:10.5f}")
    print(f"scipy/ours (least squares): wall ×{out['ratio_wall_scipy_ls_over_ours_ls']:.1f}, cpu ×{out['ratio_cpu_scipy_ls_over_ours_ls']:.1f};"
          f" scipy cauchy / ours default: wall ×{out['ratio_wall_scipy_cauchy_over_ours_default']:.1f},"
          f" cpu ×{out['ratio_cpu_scipy_cauchy_over_ours_default']:.1f}")
    print(f"H relative difference ours vs scipy: {out['hessian']['rel_diff_ours_tight_vs_scipy']:.2e} (tight), "
          f"{out['hessian']['rel_diff_ours_default_tol_vs_scipy']:.2e} (our default tol)")
    return out


# ------------------------------------------------------------- real WORK folders
def run_ba(work: Path, cfg: BAConfig) -> Path:
    """The BA stage on ``work`` from scratch; the path of its view graph."""
    TwoViewBAStage(work, cfg.replace(progress=False)).run(overwrite=True)
    return work / "viewgraph.npz"


def build_work(name: str, root: Path) -> tuple[Path, Path]:
    """WORK folder and reference of a dataset, running the front end if needed."""
    from pipeline import features, matching
    from pipeline.geometry.two_view_stage import TwoViewConfig, TwoViewStage

    images, ref = DATASETS[name]
    base = root / name
    if name == "rendered12":
        from pipeline.synthetic import render

        images = base / "images"
        if not (images / "cameras.txt").is_file():
            render.render_scene(12, 0, images)
        ref = images / "cameras.txt"
    work = base / "work"
    if not (work / "two_view.record.json").is_file():
        features.main(images, work, progress=False)
        matching.main(work, progress=False)
        TwoViewStage(work, TwoViewConfig(progress=False)).run()
    return work, ref


def true_pairs(data, ref) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True R_ij, unit t_ij (NaN where unknown) and a mask, per edge."""
    from pipeline.evaluation.compare import match_reference

    R_ref, mask = match_reference(data.vg.names, ref.names, ref.R)
    i, j = data.vg.edges.T
    R_ij = R_ref[j] @ np.swapaxes(R_ref[i], 1, 2)
    t_ij = np.full((data.vg.n_edges, 3), np.nan)
    if ref.centers is not None:
        C, cmask = match_reference(data.vg.names, ref.names, np.asarray(ref.centers)[:, :, None] * np.ones((1, 1, 3)))
        C = C[:, :, 0]
        d = -(R_ref[j] @ (C[j] - C[i])[:, :, None])[:, :, 0]
        t_ij = d / np.linalg.norm(d, axis=1, keepdims=True)
    return R_ij, t_ij, mask[i] & mask[j]


def real_section(root: Path, quick: bool, datasets: list[str]) -> dict:
    from pipeline.evaluation.compare import match_reference
    from pipeline.evaluation.metrics import edge_stats
    from pipeline.geometry.two_view_stage import load_two_view
    from pipeline.reference.truth import read_reference
    from pipeline.core.viewgraph import ViewGraph

    out: dict = {}
    print("\n== accuracy (median relative-rotation error vs reference) and anisotropy of H ==")
    print(f"{'dataset':18s} {'pairs':>6s} {'RANSAC °':>9s} {'BA °':>9s} {'BA-off °':>9s} {'ms/pair':>8s} "
          f"{'cond(H) p10/p50/p90':>22s}")
    for name in datasets:
        try:
            work, ref_path = build_work(name, root)
        except Exception as exc:  # a dataset that cannot be built is reported, not fatal
            out[name] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"{name:18s} could not be built: {exc}")
            continue
        ref = read_reference(ref_path)
        data = load_two_view(work)
        R_ref, mask = match_reference(data.vg.names, ref.names, ref.R)
        t0 = time.perf_counter()
        vg_path = run_ba(work, BAConfig())
        t_ba = time.perf_counter() - t0
        vg = ViewGraph.load(vg_path, allow_isolated=True)
        # The RANSAC graph restricted to the same (kept) edges, for a like-for-like comparison.
        vg_ransac = ViewGraph(vg.names, vg.edges, vg.stats["R_ransac"], allow_isolated=True)
        off = run_ba(work, BAConfig(enabled=False))
        vg_off = ViewGraph.load(off, allow_isolated=True)
        run_ba(work, BAConfig())  # leave the default result in WORK
        s_r, s_b, s_o = edge_stats(vg_ransac, R_ref, mask), edge_stats(vg, R_ref, mask), edge_stats(vg_off, R_ref, mask)
        cond = vg.stats["ba_cond_H"]
        r = {
            "work": str(work), "reference": str(ref_path), "n_pairs_in": data.vg.n_edges, "n_pairs_ba": vg.n_edges,
            "ransac": s_r, "ba": s_b, "ba_off": s_o,
            "ba_time_s": t_ba, "ms_per_pair_wall_2_workers": 1e3 * t_ba / max(vg.n_edges, 1),
            "median_inliers": float(np.median(vg.inliers)),
            "median_ba_inlier_fraction": float(np.median(vg.stats["ba_n_inliers"] / vg.stats["ba_n_points"])),
            "median_sigma_px": float(np.sqrt(np.median(vg.stats["ba_sigma2"]))),
            "cond_H_percentiles_10_50_90": np.percentile(cond, [10, 50, 90]).tolist(),
            "cond_H_min_max": [float(cond.min()), float(cond.max())],
        }
        # Calibration on real pairs: NEES of the BA rotations against the reference.
        i, j = vg.edges.T
        ok = mask[i] & mask[j]
        R_true = R_ref[j] @ np.swapaxes(R_ref[i], 1, 2)
        dw = so3.log(R_true[ok] @ np.swapaxes(vg.R_rel[ok], 1, 2))
        nees = np.einsum("ni,nij,nj->n", dw, vg.H[ok], dw)
        r["nees_vs_reference_median_mean"] = [float(np.median(nees)), float(np.mean(nees))]
        out[name] = r
        p = r["cond_H_percentiles_10_50_90"]
        print(f"{name:18s} {vg.n_edges:6d} {s_r['median_deg']:9.4f} {s_b['median_deg']:9.4f} {s_o['median_deg']:9.4f} "
              f"{r['ms_per_pair_wall_2_workers']:8.1f} {p[0]:6.1f}/{p[1]:6.1f}/{p[2]:6.1f}")
        if name == "rendered12":
            out["rendered_monte_carlo"] = rendered_monte_carlo(data, ref, vg, quick)
    return out


def rendered_monte_carlo(data, ref, vg, quick: bool, n_pairs: int = 6, draws: int = 200) -> dict:
    """H's least-certain direction vs the Monte-Carlo spread on rendered pairs' geometry."""
    R_ij, t_ij, ok = true_pairs(data, ref)
    draws = 60 if quick else draws
    rng = np.random.default_rng(0)
    # Pairs with the most inliers and a known truth.
    order = [k for k in np.argsort(-data.vg.inliers) if ok[k] and np.all(np.isfinite(t_ij[k]))][:n_pairs]
    rows = []
    for k in order:
        i, j = data.vg.edges[k]
        xi, xj = data.correspondences(k)
        Ki, Kj = data.K[i], data.K[j]
        # Exact correspondences: triangulate with the true pose, re-project.
        P = triangulate(R_ij[k], t_ij[k], np.ascontiguousarray(xi.T), np.ascontiguousarray(xj.T), Ki, Kj)
        keep = P[2] > 0
        P = P[:, keep]
        m = np.vstack([P[:2], np.ones(P.shape[1])])
        xi0 = (Ki @ m)[:2].T
        pj = R_ij[k] @ m + t_ij[k][:, None] * P[2]
        xj0 = ((Kj @ pj)[:2] / pj[2]).T
        dws, Hs = [], []
        for _ in range(draws):
            res = refine_pair(xi0 + rng.standard_normal(xi0.shape), xj0 + rng.standard_normal(xj0.shape),
                                 Ki, Kj, data.vg.R_rel[k], data.vg.stats["t"][k], BAConfig())
            dws.append(so3.log(R_ij[k] @ res.R.T))
            Hs.append(res.H)
        dws, Hs = np.array(dws), np.array(Hs)
        C = np.cov(dws.T)
        lam, Q = np.linalg.eigh(np.linalg.inv(Hs.mean(0)))
        lamC, QC = np.linalg.eigh(C)
        ang = float(np.rad2deg(np.arccos(min(1.0, abs(Q[:, -1] @ QC[:, -1])))))
        ratios = np.einsum("ik,ij,jk->k", Q, C, Q) / lam
        nees = np.einsum("ni,nij,nj->n", dws, Hs, dws)
        rows.append({"edge": [int(i), int(j)], "n_points": int(keep.sum()), "cond_H": float(lam[-1] / lam[0]),
                     "angle_least_certain_vs_largest_spread_deg": ang, "ratios_along_eig": ratios.tolist(),
                     "mean_nees": float(nees.mean()),
                     "std_deg_along_eig_H": np.rad2deg(np.sqrt(lam)).tolist(),
                     "std_deg_along_eig_mc": np.rad2deg(np.sqrt(lamC)).tolist()})
    print(f"\n== rendered pairs: least-certain direction of H vs largest Monte-Carlo spread ({draws} draws) ==")
    print(f"{'edge':>8s} {'points':>6s} {'cond H':>7s} {'angle °':>8s} {'NEES':>6s} {'sd along eig(H⁻¹) °':>26s} {'MC sd °':>26s}")
    for r in rows:
        print(f"{str(tuple(r['edge'])):>8s} {r['n_points']:6d} {r['cond_H']:7.1f} {r['angle_least_certain_vs_largest_spread_deg']:8.2f} "
              f"{r['mean_nees']:6.2f} {np.array2string(np.array(r['std_deg_along_eig_H']), precision=4):>26s} "
              f"{np.array2string(np.array(r['std_deg_along_eig_mc']), precision=4):>26s}")
    return {"draws": draws, "pairs": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and draws; rendered scene only")
    ap.add_argument("--work-root", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "two_view_ba_bench",
                    help="where WORK folders are built (outside the repository)")
    ap.add_argument("--skip-real", action="store_true", help="only the speed section")
    ap.add_argument("--datasets", nargs="*", default=None, help=f"subset of {list(DATASETS)}")
    a = ap.parse_args(argv)
    out = {"speed": speed_section(a.quick)}
    if not a.skip_real:
        names = a.datasets or (["rendered12"] if a.quick else list(DATASETS))
        out["real"] = real_section(a.work_root, a.quick, names)
    write_json(RESULTS, out)
    print(f"\nwrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
