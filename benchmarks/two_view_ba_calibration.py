"""Calibration of the two-view rotation Hessian H_ij (issue 6, acceptance item 2; item 5 on synthetic pairs).

Monte-Carlo over pixel-noise draws on fixed synthetic scenes (``pipeline.synthetic.pairs.synthetic_pair``):

* mean NEES ``Δωᵀ H Δω`` with ``R_true = exp([Δω]×) R̂`` (target [2.8, 3.2]);
* ratio of the sample covariance of Δω to ``mean(H)⁻¹`` along each eigen-direction of
  ``mean(H)⁻¹`` (target within 10%), plus the generalized eigenvalues of the pair
  (the extreme ratios over *all* directions, a stricter figure);
* with σ known and σ estimated; then with 10% outlier matches under several losses;
* anisotropy: angle between H's least-certain direction and the principal axis of the
  Monte-Carlo spread.

Statistical resolution: with D draws a variance ratio along a fixed direction has sd
√(2/D) (6.3% at D = 500), so "within 10%" is a 1.6-sd band per direction; the mean NEES
has sd √(6/D) (0.11 at D = 500). Several scene seeds are run to show the spread.

Usage: ``python benchmarks/two_view_ba_calibration.py [--quick] [--draws D] [--scenes S]``.
Writes ``benchmarks/results/two_view_ba_calibration.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from pipeline.core import so3  # noqa: E402
from pipeline.geometry.ba_solver import BAConfig, TwoViewBAError, refine_pair  # noqa: E402
from pipeline.synthetic.pairs import synthetic_pair  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "two_view_ba_calibration.json"


def monte_carlo(scene_seed: int, draws: int, cfg: BAConfig, n_points: int = 200, sigma: float = 1.0,
                outlier_frac: float = 0.0, seed0: int = 10_000) -> dict:
    dws, Hs, s2, fails, iters = [], [], [], 0, []
    t0 = time.perf_counter()
    for d in range(draws):
        sp = synthetic_pair(n_points, sigma_px=sigma, outlier_frac=outlier_frac, seed=seed0 + d, scene_seed=scene_seed)
        try:
            res = refine_pair(sp.x_i, sp.x_j, sp.K_i, sp.K_j, sp.R0, sp.t0, cfg)
        except TwoViewBAError:
            fails += 1
            continue
        dws.append(so3.log(sp.R @ res.R.T))
        Hs.append(res.H)
        s2.append(res.sigma2)
        iters.append(res.iterations)
    elapsed = time.perf_counter() - t0
    dws, Hs = np.array(dws), np.array(Hs)
    nees = np.einsum("ni,nij,nj->n", dws, Hs, dws)
    C = np.cov(dws.T)
    Cinv_H = np.linalg.inv(Hs.mean(axis=0))
    lam, Q = np.linalg.eigh(Cinv_H)
    ratios = np.einsum("ik,ij,jk->k", Q, C, Q) / lam
    # Generalized eigenvalues of (C, mean(H)⁻¹): extreme ratios over all directions.
    L = np.linalg.cholesky(Cinv_H)
    Li = np.linalg.inv(L)
    gen = np.linalg.eigvalsh(Li @ C @ Li.T)
    # Anisotropy: least-certain direction of H vs the principal axis of the spread.
    lamC, QC = np.linalg.eigh(C)
    cos = abs(float(Q[:, -1] @ QC[:, -1]))
    bias_sd = np.abs(dws.mean(axis=0) @ Q) / np.sqrt(lam / len(dws))
    return {
        "scene_seed": scene_seed, "draws": draws, "failed": fails, "n_points": n_points, "sigma_px": sigma,
        "outlier_frac": outlier_frac,
        "mean_nees": float(nees.mean()), "median_nees": float(np.median(nees)),
        "nees_ok_2.8_3.2": bool(2.8 <= nees.mean() <= 3.2),
        "ratios_along_eig_H": ratios.tolist(), "ratios_ok_10pct": bool(np.all(np.abs(ratios - 1) <= 0.1)),
        "generalized_ratios": gen.tolist(),
        "eig_meanHinv_deg2": (lam * np.rad2deg(1) ** 2).tolist(),
        "cond_mean_H": float(lam[-1] / lam[0]),
        "angle_least_certain_vs_largest_spread_deg": float(np.rad2deg(np.arccos(min(1.0, cos)))),
        "mean_bias_in_sd_along_eig": bias_sd.tolist(),
        "rms_rot_err_deg": float(np.rad2deg(np.sqrt(np.mean(np.sum(dws**2, axis=1))))),
        "mean_sigma2": float(np.mean(s2)),
        "median_iterations": float(np.median(iters)),
        "time_per_pair_ms": 1e3 * elapsed / draws,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="100 draws, one scene")
    ap.add_argument("--draws", type=int, default=None)
    ap.add_argument("--scenes", type=int, default=None, help="number of scene seeds for the clean case")
    a = ap.parse_args(argv)
    draws = a.draws or (100 if a.quick else 500)
    n_scenes = a.scenes or (1 if a.quick else 4)
    out: dict = {"draws": draws, "clean": [], "outliers": []}
    rows = []
    print(f"{'case':44s} {'NEES':>6s} {'ratios along eig(mean H)^-1':>30s} {'gen. ratios':>22s} {'ok':>5s}")
    for scene in range(n_scenes):
        for known in (True, False):
            cfg = BAConfig(sigma_px=1.0 if known else None)
            r = monte_carlo(scene, draws, cfg)
            r["sigma"] = "known" if known else "estimated"
            out["clean"].append(r)
            ok = r["nees_ok_2.8_3.2"] and r["ratios_ok_10pct"]
            name = f"scene {scene}, σ {r['sigma']}, 0% outliers"
            print(f"{name:44s} {r['mean_nees']:6.3f} {np.array2string(np.array(r['ratios_along_eig_H']), precision=3):>30s} "
                  f"{np.array2string(np.array(r['generalized_ratios']), precision=3):>22s} {str(ok):>5s}")
            rows.append(r)
    # 10% outlier matches: how each loss (and the inlier refit) keeps the NEES near 3.
    variants = [
        ("none, no refit", BAConfig(loss="none", refit_inliers=False)),
        ("huber, no refit", BAConfig(loss="huber", refit_inliers=False)),
        ("cauchy, no refit", BAConfig(loss="cauchy", refit_inliers=False)),
        ("none + refit", BAConfig(loss="none", refit_inliers=True)),
        ("huber + refit", BAConfig(loss="huber", refit_inliers=True)),
        ("cauchy + refit (default)", BAConfig(loss="cauchy", refit_inliers=True)),
        ("cauchy + refit, σ known", BAConfig(loss="cauchy", refit_inliers=True, sigma_px=1.0)),
    ]
    print(f"\n{'10% outliers, scene 0':30s} {'mean NEES':>9s} {'median':>7s} {'ratios':>24s} {'rms err °':>9s} {'σ̂²':>7s}")
    for name, cfg in variants:
        r = monte_carlo(0, draws, cfg, outlier_frac=0.10)
        r["variant"] = name
        out["outliers"].append(r)
        print(f"{name:30s} {r['mean_nees']:9.3f} {r['median_nees']:7.3f} "
              f"{np.array2string(np.array(r['ratios_along_eig_H']), precision=3):>24s} {r['rms_rot_err_deg']:9.4f} {r['mean_sigma2']:7.3f}")
    clean = out["clean"]
    all_ratios = np.array([r["ratios_along_eig_H"] for r in clean])
    # Under perfect calibration a ratio is ≈ χ²_{D−1}/(D−1): the share expected inside ±10%.
    from scipy.stats import chi2

    nu = draws - 1
    p_in = float(chi2.cdf(1.1 * nu, nu) - chi2.cdf(0.9 * nu, nu))
    out["summary"] = {
        "mean_nees_sigma_known": float(np.mean([r["mean_nees"] for r in clean if r["sigma"] == "known"])),
        "mean_nees_sigma_estimated": float(np.mean([r["mean_nees"] for r in clean if r["sigma"] == "estimated"])),
        "pooled_mean_ratio": float(all_ratios.mean()),
        "share_of_ratios_within_10pct": float(np.mean(np.abs(all_ratios - 1) <= 0.1)),
        "share_expected_within_10pct_if_perfect": p_in,
        "nees_all_in_2.8_3.2": all(r["nees_ok_2.8_3.2"] for r in clean),
        "ratios_all_within_10pct": all(r["ratios_ok_10pct"] for r in clean),
        "n_cases": len(clean),
        "n_cases_fully_ok": sum(r["nees_ok_2.8_3.2"] and r["ratios_ok_10pct"] for r in clean),
        "max_abs_ratio_dev": max(float(np.max(np.abs(np.array(r["ratios_along_eig_H"]) - 1))) for r in clean),
        "expected_sd_of_ratio": float(np.sqrt(2.0 / draws)),
        "anisotropy_angle_deg": [r["angle_least_certain_vs_largest_spread_deg"] for r in clean],
        "cond_mean_H": [r["cond_mean_H"] for r in clean],
    }
    write_json(RESULTS, out)
    print(f"\nsummary: {out['summary']}\nwrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
