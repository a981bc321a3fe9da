"""Shared pieces of the SDP benchmarks: import fix, GTSAM peers, timing helpers.

GTSAM's Rot3 is world_from_cam, so camera i is ``X_i = R_iᵀ`` and its
``between(X_i, X_j) = X_iᵀ X_j = R_i R_jᵀ``: the GTSAM measurement of our edge is
``R̃_ijᵀ``. Its BetweenFactor error ``Log(measuredᵀ X_iᵀ X_j)`` equals ``−Δω`` of our
left perturbation, so our precision ``H_ij`` is the factor's information matrix as is.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# benchmarks/pipeline.py (another benchmark) would shadow the package when run as a script
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]

import numpy as np  # noqa: E402

from pipeline.core.viewgraph import ViewGraph  # noqa: E402

RESULTS = _HERE / "results"


def have_gtsam() -> bool:
    try:
        import gtsam  # noqa: F401
    except ImportError:
        return False
    return True


def shonan(vg: ViewGraph, seed: int = 0) -> tuple[np.ndarray, float, float]:
    """GTSAM ShonanAveraging3 (isotropic, certifiable). Returns (R (N,3,3), λ_min certificate, wall s)."""
    import gtsam

    t0 = time.perf_counter()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    meas = gtsam.BinaryMeasurementsRot3()
    for (i, j), R in zip(vg.edges, vg.R_rel):  # benchmark glue: GTSAM takes one object per edge
        meas.append(gtsam.BinaryMeasurementRot3(int(i), int(j), gtsam.Rot3(R.T), noise))
    params = gtsam.ShonanAveragingParameters3(gtsam.LevenbergMarquardtParams.CeresDefaults())
    sa = gtsam.ShonanAveraging3(meas, params)
    values, lam = sa.run(sa.initializeRandomly(), 3, 10)
    R = np.array([values.atRot3(i).matrix().T for i in range(vg.n_cameras)])
    return R, float(lam), time.perf_counter() - t0


def lm_anisotropic(vg: ViewGraph, R0: np.ndarray) -> tuple[np.ndarray, float, int]:
    """GTSAM BetweenFactorRot3 + Gaussian.Information(H) refined by Levenberg–Marquardt (local).

    Returns (R (N,3,3), wall s, iterations).
    """
    import gtsam

    t0 = time.perf_counter()
    graph = gtsam.NonlinearFactorGraph()
    for (i, j), R, H in zip(vg.edges, vg.R_rel, vg.H):
        graph.add(gtsam.BetweenFactorRot3(int(i), int(j), gtsam.Rot3(R.T), gtsam.noiseModel.Gaussian.Information(H)))
    graph.add(gtsam.PriorFactorRot3(0, gtsam.Rot3(R0[0].T), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    init = gtsam.Values()
    for i in range(vg.n_cameras):
        init.insert(i, gtsam.Rot3(R0[i].T))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, init, gtsam.LevenbergMarquardtParams())
    values = opt.optimize()
    R = np.array([values.atRot3(i).matrix().T for i in range(vg.n_cameras)])
    return R, time.perf_counter() - t0, int(opt.iterations())
