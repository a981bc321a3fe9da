"""Paper 2, supplement C.1: three cameras, one edge noisy along a single axis.

Edges (0,1) and (0,2) are "certain": Δω ~ N(0, εI), ε = 1e-3 (the paper's value,
a covariance in rad²). Edge (1,2) has covariance diag(σ, ε, ε) rotated to the x, y
or z axis, σ from 0.01 to 0.3 (rad², as the paper writes it). H is the inverse
covariance. Reported: paper 2's error √Σ‖R_i − R_i*‖²_F (after the best global
rotation), median over ``--seeds`` draws, for SDP-cSO(3) (anisotropic) and
SDP-O(3)-ISO. Expected: the anisotropic error stays flat, the isotropic error grows.

    python benchmarks/sdp_c1.py [--quick]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from pipeline.averaging.sdp import solve_sdp
from pipeline.core import so3
from pipeline.core.atomic import save_figure, write_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.metrics import frobenius_error

RESULTS = Path(__file__).resolve().parent / "results"
OUT = RESULTS / "sdp_c1.json"
PNG = RESULTS / "sdp_c1.png"
EPS = 1e-3


def instance(sigma: float, axis: int, seed: int) -> tuple[ViewGraph, np.ndarray]:
    rng = np.random.default_rng([seed, axis, int(sigma * 1e6)])
    R = so3.random_rotations(3, rng)
    E = np.array([[0, 1], [0, 2], [1, 2]])
    d = np.full(3, EPS)
    d[axis] = sigma
    cov = np.array([np.eye(3) * EPS, np.eye(3) * EPS, np.diag(d)])
    dw = (np.linalg.cholesky(cov) @ rng.standard_normal((3, 3, 1)))[..., 0]
    R_rel = so3.exp(dw) @ R[E[:, 1]] @ np.swapaxes(R[E[:, 0]], 1, 2)
    return ViewGraph(["0", "1", "2"], E, R_rel, H=np.linalg.inv(cov)), R


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=50)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    seeds = 10 if args.quick else args.seeds
    sigmas = np.round(np.linspace(0.01, 0.3, 6 if args.quick else 12), 4)
    variants = ["cso3", "o3-iso", "cso3-iso", "o3-aniso"]
    res = {v: np.zeros((3, sigmas.size)) for v in variants}
    for axis in range(3):
        for k, s in enumerate(sigmas):
            errs = {v: [] for v in variants}
            for seed in range(seeds):
                vg, R = instance(float(s), axis, seed)
                for v in variants:
                    errs[v].append(frobenius_error(solve_sdp(vg, v).R, R))
            for v in variants:
                res[v][axis, k] = np.median(errs[v])
    print(f"{'axis':4s} {'sigma':>6s} " + " ".join(f"{v:>9s}" for v in variants) + "  iso/aniso")
    for axis in range(3):
        for k, s in enumerate(sigmas):
            row = " ".join(f"{res[v][axis, k]:9.4f}" for v in variants)
            print(f"{'xyz'[axis]:4s} {s:6.3f} {row}  {res['o3-iso'][axis, k] / res['cso3'][axis, k]:8.2f}")
    flat = {v: float(res[v][:, -1].mean() / res[v][:, 0].mean()) for v in variants}
    out = {"eps": EPS, "sigmas": sigmas.tolist(), "seeds": seeds,
           "median_frobenius_error": {v: res[v].tolist() for v in variants},
           "growth_ratio_last_over_first_sigma": flat,
           "aniso_flat": bool(flat["cso3"] < 1.5), "iso_grows": bool(flat["o3-iso"] > 2.0)}
    write_json(OUT, out)
    print(f"error growth from σ={sigmas[0]} to σ={sigmas[-1]}: {flat}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5), sharey=True)
    for axis, ax in enumerate(axes):
        for v, style in zip(variants, ["-o", "-s", "--", ":"]):
            ax.plot(sigmas, res[v][axis], style, label=f"SDP-{v}")
        ax.set_title(f"noise along {'xyz'[axis]}")
        ax.set_xlabel("σ (covariance, rad²)")
    axes[0].set_ylabel("median √Σ‖R_i − R_i*‖²_F")
    axes[0].legend()
    fig.suptitle("Paper 2, supplement C.1: three cameras, one edge noisy along one axis")
    fig.tight_layout()
    save_figure(fig, PNG)
    print(f"wrote {OUT} and {PNG}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
