"""Peer rotation-averaging implementations, measured against ours in the benchmarks.

- :func:`run_colmap`: ``pycolmap.run_rotation_averaging`` (COLMAP's C++ L1 + IRLS), also the
  registered method ``colmap-ra``;
- :func:`shonan`: GTSAM's ``ShonanAveraging3`` (certifiable, isotropic);
- :func:`lm_anisotropic`: GTSAM ``BetweenFactorRot3`` with ``Gaussian.Information(H)``
  refined by Levenberg–Marquardt (local, anisotropic), optionally with one of GTSAM's robust
  kernels on the whitened error (what a GTSAM user does with our view graph: Shonan's isotropic
  solution as the start, then robust anisotropic LM).

GTSAM is optional (the ``bench`` extra): :func:`have_gtsam` tells whether it is there.
GTSAM's Rot3 is world_from_cam, so camera i is ``X_i = R_iᵀ`` and its
``between(X_i, X_j) = X_iᵀ X_j = R_i R_jᵀ``: the GTSAM measurement of our edge is
``R̃_ijᵀ``. Its BetweenFactor error ``Log(measuredᵀ X_iᵀ X_j)`` equals ``−Δω`` of our
left perturbation, so our precision ``H_ij`` is the factor's information matrix as is.
Both peers take one object per edge: these loops are glue for the peers' APIs.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from pipeline.averaging.colmap_ra import run_pycolmap
from pipeline.core.viewgraph import ViewGraph

__all__ = ["run_colmap", "have_gtsam", "shonan", "lm_anisotropic", "ROBUST_KERNELS"]


def run_colmap(vg: ViewGraph, **opts: Any) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """pycolmap rotation averaging; ``opts`` set ``RotationEstimatorOptions`` fields.

    The ``colmap-ra`` method (:mod:`pipeline.averaging.colmap_ra`) is the same call as a
    registered method; this keeps every option of pycolmap open to the benchmarks.

    Returns:
        R: (N, 3, 3) cam_from_world rotations (identity where not registered).
        registered: (N,) bool.
        seconds: wall time of ``run_rotation_averaging``.
        ok: its return value.
    """
    import pycolmap

    o = pycolmap.RotationEstimatorOptions()
    for k, v in opts.items():
        setattr(o, k, v)
    return run_pycolmap(vg, o)


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
    for (i, j), R in zip(vg.edges, vg.R_rel):
        meas.append(gtsam.BinaryMeasurementRot3(int(i), int(j), gtsam.Rot3(R.T), noise))
    params = gtsam.ShonanAveragingParameters3(gtsam.LevenbergMarquardtParams.CeresDefaults())
    sa = gtsam.ShonanAveraging3(meas, params)
    values, lam = sa.run(sa.initializeRandomly(), 3, 10)
    R = np.array([values.atRot3(i).matrix().T for i in range(vg.n_cameras)])
    return R, float(lam), time.perf_counter() - t0


#: GTSAM's robust kernels by name, as ``lm_anisotropic(robust=(name, k))`` takes them.
ROBUST_KERNELS = ("huber", "cauchy", "geman-mcclure", "tukey")


def lm_anisotropic(vg: ViewGraph, R0: np.ndarray, robust: tuple[str, float] | None = None) -> tuple[np.ndarray, float, int]:
    """GTSAM BetweenFactorRot3 + Gaussian.Information(H) refined by Levenberg–Marquardt (local).

    ``robust=(kernel, k)`` wraps each factor's noise model in GTSAM's robust kernel of that name
    (:data:`ROBUST_KERNELS`) with threshold ``k`` in whitened units (standard deviations of H).
    Returns (R (N,3,3), wall s, iterations).
    """
    import gtsam

    make = None
    if robust is not None:
        kernels = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy,
                   "geman-mcclure": gtsam.noiseModel.mEstimator.GemanMcClure,
                   "tukey": gtsam.noiseModel.mEstimator.Tukey}
        if robust[0] not in kernels:
            raise ValueError(f"unknown robust kernel {robust[0]!r}; expected one of {', '.join(ROBUST_KERNELS)}")
        make = kernels[robust[0]].Create
    t0 = time.perf_counter()
    graph = gtsam.NonlinearFactorGraph()
    for (i, j), R, H in zip(vg.edges, vg.R_rel, vg.H):
        noise = gtsam.noiseModel.Gaussian.Information(H)
        if make is not None:
            noise = gtsam.noiseModel.Robust.Create(make(float(robust[1])), noise)
        graph.add(gtsam.BetweenFactorRot3(int(i), int(j), gtsam.Rot3(R.T), noise))
    graph.add(gtsam.PriorFactorRot3(0, gtsam.Rot3(R0[0].T), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    init = gtsam.Values()
    for i in range(vg.n_cameras):
        init.insert(i, gtsam.Rot3(R0[i].T))
    opt = gtsam.LevenbergMarquardtOptimizer(graph, init, gtsam.LevenbergMarquardtParams())
    values = opt.optimize()
    R = np.array([values.atRot3(i).matrix().T for i in range(vg.n_cameras)])
    return R, time.perf_counter() - t0, int(opt.iterations())
