"""How far can rotation averaging of our pairwise rotations go on temple? (issue 7, item 3)

    python benchmarks/temple_limit.py [--keep DIR] [--only temple,fountain]

On templeSparseRing, pycolmap's incremental reconstruction (multi-view bundle
adjustment over tracks) is at about 0.25° median against the calibrated cameras
and our rotation averaging at about 0.40° (``benchmarks/end_to_end.py``). This
benchmark measures where the gap comes from, on the view graph of a ``run.py``
run (made here, or reused from ``--keep DIR``), for temple and, as a contrast,
fountain-P11. Every figure is on the images pycolmap registers, aligned on them.

1. **Edges.** The relative rotations against the truth: ours after RANSAC, ours
   after two-view BA, and the relative rotations of pycolmap's final model on the
   same pairs (multi-view BA), with the share of our error along the weakest
   direction of H.
2. **What pairwise rotations carry.** The Cramér–Rao bound of rotation averaging
   on these edges: the edges are modelled as Gaussian with covariance
   ``s²·H⁻¹`` (s² calibrated on the edges within 1.5° of the truth, the median
   NEES over median χ²₃), the information ``Σ Aᵀ (H/s²) A`` is inverted, and the
   median camera error of 4000 draws from that covariance (aligned as the
   evaluation aligns) is reported with its 10–90% range. It is what an efficient
   estimator of the rotations from these measurements reaches on average. A
   second bound adds each pair's translation direction (the two-view BA's 5×5
   pose precision, camera centres as unknowns): what a global SfM without tracks
   (rotations and translations from pairs only) could gain.
3. **Solvers on the same edges.** IRLS-H-ℓ½ (the pipeline's), and ℓ2 in the H
   metric on the edges within 1.5° of the truth (an oracle no method has).
4. **Knobs tuned with the truth, not shipped.** H raised to a power p (p < 1 less
   anisotropic, p > 1 more) in IRLS-H. A single exponent picked on the truth
   moves temple by ±0.2°: this is how a target is met by fitting the test set,
   so the pipeline keeps p = 1, the H that the two-view BA derives.

Results: ``benchmarks/results/temple_limit.json`` (atomic) and a table.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MPLBACKEND", "Agg")

import argparse  # noqa: E402
import atexit  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
RESULTS = REPO / "benchmarks" / "results" / "temple_limit.json"
CASES = {
    "temple": (DATA / "middlebury-templeSparseRing", DATA / "middlebury-templeSparseRing" / "templeSR_par.txt",
               DATA / "middlebury-templeSparseRing" / "templeSR_par.txt"),
    "fountain": (DATA / "strecha" / "fountain-P11" / "images", DATA / "strecha" / "fountain-P11" / "gt_dense_cameras",
                 DATA / "strecha" / "fountain-P11" / "images" / "K.txt"),
}
ORACLE_DEG = 1.5  # edges within this of the truth count as inliers for the oracle and the calibration
CHI2_1_MEDIAN = 0.455  # median of χ²₁ (0.4549), for the per-direction NEES
EXPONENTS = (0.5, 0.75, 1.0, 1.25, 1.5)

from pipeline.averaging.irls_h import CHI2_3_MEDIAN, irls_h  # noqa: E402
from pipeline.core import so3  # noqa: E402
from pipeline.core.atomic import write_json  # noqa: E402
from pipeline.core.names import match_names  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.evaluation.analysis import information, pose_information, predicted_errors  # noqa: E402
from pipeline.evaluation.compare import match_reference  # noqa: E402
from pipeline.evaluation.metrics import edge_errors_deg, rotation_errors_deg  # noqa: E402
from pipeline.reference.truth import read_reference  # noqa: E402


def ensure_run(name: str, out: Path) -> Path:
    """A ``run.py`` output folder for the case at ``out`` (reused when its metrics exist)."""
    if not (out / "metrics.json").is_file():
        from pipeline import run  # noqa: PLC0415

        images, gt, K = CASES[name]
        print(f"  running run.py on {name} into {out} ...", flush=True)
        run.main(images, out, methods=["irls-h"], gt=gt, K=K, quiet=True)
    return out


def median_on(R_est: np.ndarray, R_ref: np.ndarray, mask: np.ndarray) -> float:
    return float(np.nanmedian(rotation_errors_deg(R_est, R_ref, mask)))


def solve_on(vg: ViewGraph, R_ref: np.ndarray, mask: np.ndarray, **kw) -> float:
    """Median error (deg) of IRLS-H on ``vg`` against ``R_ref``, on ``mask``, every camera solved."""
    res = irls_h(vg, **kw)
    if len(res.names) != vg.n_cameras:
        raise RuntimeError(f"IRLS-H left out {res.dropped_names}: the graph is not connected")
    order = [res.names.index(n) for n in vg.names]
    return median_on(res.R[order], R_ref, mask)


def pose_bound(work: Path, sub: ViewGraph, R: np.ndarray, truth, s2: float, mask: np.ndarray, draws: int) -> np.ndarray:
    """Bound draws with each pair's translation direction too (see :func:`pose_information`).

    The view graph keeps H, not the 5×5 pose precision, so each pair of ``sub`` is refined
    again from its RANSAC pose and inliers with the run's BA configuration (deterministic:
    the same R and H as the run, to rounding). Calibrated with the rotations' ``s2``, which
    trusts the translation directions more than their own NEES would: an optimistic bound.
    """
    from pipeline.geometry.ba_solver import BAConfig, refine_pair  # noqa: PLC0415
    from pipeline.geometry.two_view_stage import load_two_view  # noqa: PLC0415
    from pipeline.stage import read_record  # noqa: PLC0415

    data = load_two_view(work)
    cfg = BAConfig.from_dict(read_record(work, "two_view_ba").config)
    index = {(data.vg.names[a], data.vg.names[b]): k for k, (a, b) in enumerate(data.vg.edges)}
    t_in = np.asarray(data.vg.stats["t"], dtype=np.float64)
    S, B = [], []
    for a, b in sub.edges:  # one BA per pair: the stage's own per-pair loop
        k = index[(sub.names[a], sub.names[b])]
        xi, xj = data.correspondences(k)
        ia, ib = data.vg.edges[k]
        res = refine_pair(np.asarray(xi, float), np.asarray(xj, float), data.K[ia], data.K[ib], data.vg.R_rel[k],
                          t_in[k], cfg)
        S.append(res.H_pose)
        B.append(res.t_basis)
    idx = match_names(sub.names, truth.names, what="the truth")
    if truth.centers is None or (idx < 0).any():
        raise RuntimeError("the truth has no centre for some camera: no pose bound")
    C = truth.centers[idx]
    baseline = np.linalg.norm(C[sub.edges[:, 0]] - C[sub.edges[:, 1]], axis=1)
    J = pose_information(sub, R, C, np.array(B), np.array(S) / s2, 1e-3 * np.median(baseline))
    return predicted_errors(J, R, mask, draws, seed=0)


def analyse(name: str, out: Path, draws: int) -> dict:
    gt = CASES[name][1]
    vg = ViewGraph.load(out / "viewgraph.npz")
    truth = read_reference(gt)
    R, has_truth = match_reference(vg.names, truth.names, truth.R)
    model = read_reference(out / "reference" / "model")
    Rp, in_model = match_reference(vg.names, model.names, model.R)
    mask = has_truth & in_model
    both = mask[vg.edges[:, 0]] & mask[vg.edges[:, 1]]
    R = np.where(has_truth[:, None, None], R, np.eye(3))

    # 1. edges
    e_ba = edge_errors_deg(vg, R, mask)
    e_ransac = edge_errors_deg(ViewGraph(vg.names, vg.edges, vg.stats["R_ransac"]), R, mask)
    e_pyc = edge_errors_deg(ViewGraph(vg.names, vg.edges, so3.relative(np.where(in_model[:, None, None], Rp, np.eye(3)),
                                                                    vg.edges)), R, mask)
    r = so3.log(vg.R_rel @ np.swapaxes(so3.relative(R, vg.edges), 1, 2))  # our edge error, camera j's frame
    lam, V = np.linalg.eigh(vg.H)
    weak = np.abs(np.einsum("na,na->n", V[:, :, 0], r)) / np.maximum(np.linalg.norm(r, axis=1), 1e-300)
    nees_dir = np.einsum("nab,na->nb", V, r) ** 2 * lam  # (M, 3): weak, middle, strong

    # 2. the bound, on the oracle's inlier edges (every camera with a truth, scored on pycolmap's)
    inl = edge_errors_deg(vg, R, has_truth) < ORACLE_DEG  # NaN (no truth) compares False
    q = nees_dir.sum(axis=1)
    s2 = float(np.median(q[inl]) / CHI2_3_MEDIAN)
    sub = ViewGraph(vg.names, vg.edges[inl], vg.R_rel[inl], H=vg.H[inl], allow_isolated=True)
    J = information(sub, R, sub.H / s2)
    pred = predicted_errors(J, R, mask, draws, seed=0)
    pred_pose = pose_bound(out / "work", sub, R, truth, s2, mask, draws)

    # 3. solvers; 4. exponents of H
    achieved = solve_on(vg, R, mask)
    oracle_l2 = solve_on(sub, R, mask, loss="l2", refine=False)
    powers = {}
    for p in EXPONENTS:
        Hp = np.einsum("nab,nb,ncb->nac", V, lam**p, V)
        powers[str(p)] = solve_on(vg.with_H(Hp), R, mask)

    return {
        "case": name, "run": str(out), "n_cameras": vg.n_cameras, "n_edges": vg.n_edges,
        "n_scored_cameras": int(mask.sum()), "n_scored_edges": int(both.sum()),
        "edges_median_deg": {"ours_ransac": float(np.nanmedian(e_ransac[both])),
                             "ours_ba": float(np.nanmedian(e_ba[both])),
                             "pycolmap_model": float(np.nanmedian(e_pyc[both]))},
        "share_of_edge_error_along_weakest_H_direction_median": float(np.median(weak[inl])),
        "nees_per_H_direction_over_chi2_1_median": (np.median(nees_dir[inl], axis=0) / CHI2_1_MEDIAN).tolist(),
        "calibration_s2": s2, "n_oracle_edges": int(inl.sum()),
        "bound_median_deg": float(np.median(pred)),
        "bound_p10_p90_deg": np.percentile(pred, [10, 90]).tolist(),
        "bound_with_translation_directions_median_deg": float(np.median(pred_pose)),
        "bound_with_translation_directions_p10_p90_deg": np.percentile(pred_pose, [10, 90]).tolist(),
        "bound_share_at_or_below_pycolmap": float(np.mean(pred <= median_on(Rp, R, mask))),
        "irls_h_median_deg": achieved,
        "oracle_l2_h_median_deg": oracle_l2,
        "pycolmap_median_deg": median_on(Rp, R, mask),
        "irls_h_with_H_power_p_median_deg": powers,
    }


def table(rows: list[dict]) -> str:
    lines = ["| | " + " | ".join(r["case"] for r in rows) + " |", "|---" * (len(rows) + 1) + "|"]

    def add(label, f):
        lines.append(f"| {label} | " + " | ".join(f(r) for r in rows) + " |")

    add("cameras scored (pycolmap's) / edges", lambda r: f"{r['n_scored_cameras']} / {r['n_scored_edges']}")
    add("edges: ours RANSAC, median °", lambda r: f"{r['edges_median_deg']['ours_ransac']:.3f}")
    add("edges: ours two-view BA, median °", lambda r: f"{r['edges_median_deg']['ours_ba']:.3f}")
    add("edges: pycolmap's model (multi-view BA), median °", lambda r: f"{r['edges_median_deg']['pycolmap_model']:.3f}")
    add("share of our edge error along H's weakest direction", lambda r: f"{r['share_of_edge_error_along_weakest_H_direction_median']:.2f}")
    add("NEES/χ²₁ per H direction (weak, mid, strong)",
        lambda r: ", ".join(f"{v:.1f}" for v in r["nees_per_H_direction_over_chi2_1_median"]))
    add("bound: efficient estimator from these edges, median ° (10–90%)",
        lambda r: f"{r['bound_median_deg']:.3f} ({r['bound_p10_p90_deg'][0]:.3f}–{r['bound_p10_p90_deg'][1]:.3f})")
    add("bound with the pairs' translation directions too, median ° (10–90%)",
        lambda r: f"{r['bound_with_translation_directions_median_deg']:.3f} "
                  f"({r['bound_with_translation_directions_p10_p90_deg'][0]:.3f}–{r['bound_with_translation_directions_p10_p90_deg'][1]:.3f})")
    add("share of bound draws at or below pycolmap", lambda r: f"{r['bound_share_at_or_below_pycolmap']:.2f}")
    add("IRLS-H-ℓ½ (ours, shipped), median °", lambda r: f"**{r['irls_h_median_deg']:.3f}**")
    add("ℓ2-H on truth-filtered edges (oracle), median °", lambda r: f"{r['oracle_l2_h_median_deg']:.3f}")
    add("pycolmap incremental, median °", lambda r: f"**{r['pycolmap_median_deg']:.3f}**")
    for p in EXPONENTS:
        add(f"IRLS-H with H^{p} (truth-tuned knob, not shipped)", lambda r, p=p: f"{r['irls_h_with_H_power_p_median_deg'][str(p)]:.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", type=Path, default=None,
                    help="run folders (reused if present, e.g. benchmarks/end_to_end.py --keep DIR); default a temp folder")
    ap.add_argument("--only", default="temple,fountain", help="comma-separated subset of temple,fountain")
    ap.add_argument("--draws", type=int, default=4000, help="Monte Carlo draws for the bound")
    a = ap.parse_args(argv)
    names = [n for n in a.only.split(",") if n]
    unknown = sorted(set(names) - set(CASES))
    if unknown:
        ap.error(f"unknown case(s) {unknown}; choose from {sorted(CASES)}")
    root = a.keep or Path(tempfile.mkdtemp(prefix="bench_temple_limit_"))
    if a.keep is None:  # a temp folder of runs is removed at exit (--keep keeps them)
        atexit.register(shutil.rmtree, root, True)
    folder = {"temple": "temple", "fountain": "fountain-P11"}
    rows = [analyse(n, ensure_run(n, root / folder[n]), a.draws) for n in names]
    print(table(rows))
    write_json(RESULTS, {"benchmark": "temple_limit", "oracle_deg": ORACLE_DEG, "draws": a.draws, "cases": rows})
    print(f"\nwrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
