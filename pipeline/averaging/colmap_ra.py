"""COLMAP's rotation averaging as a method of ours (``colmap-ra``): the like-for-like comparison in every report.

It runs pycolmap's ``run_rotation_averaging`` (COLMAP's C++ ℓ1 + IRLS with the
Geman–McClure loss) on *our* view graph, with ``num_matches`` from our inlier counts, so
that both methods see the same edges. pycolmap 4.2.1 facts used here:

- ``run_rotation_averaging(options: RotationEstimatorOptions, pose_graph: PoseGraph,
  reconstruction: Reconstruction, pose_priors: list[PosePrior]) -> bool``;
- ``RotationEstimatorOptions`` defaults: ``max_num_l1_iterations=5``,
  ``l1_step_convergence_threshold=1e-3``, ``max_num_irls_iterations=100``,
  ``irls_step_convergence_threshold=1e-3``, ``irls_loss_parameter_sigma=5.0`` (degrees),
  ``weight_type=GEMAN_MCCLURE``, ``use_stratified=True``;
- an edge is ``PoseGraphEdge(Rigid3d(Rotation3d(R_ij), t))`` with ``num_matches`` (COLMAP
  weights its spanning tree by it), added by ``PoseGraph.add_edge(id1, id2, edge)`` with
  1-based image ids; ``R_ij = R_j R_iᵀ`` is pycolmap's ``cam2_from_cam1``;
- on a disconnected graph it returns True and poses one component only: the caller
  (:func:`pipeline.averaging.average`) hands it the largest component, as every method.

Cameras pycolmap leaves unposed, a False return or an exception make the method fail
with one :class:`ViewGraphError` line (a method returns a rotation for every camera of
its component). pycolmap is optional (the ``bench`` extra): :func:`have_pycolmap`.
The loops over edges here are glue for pycolmap's one-object-per-edge API.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.averaging.result import AveragingResult, method_config
from pipeline.core import so3
from pipeline.core.config import Config, option
from pipeline.core.errors import ConfigError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["ColmapRAConfig", "colmap_ra", "have_pycolmap", "run_pycolmap"]

logger = logging.getLogger(__name__)


def have_pycolmap() -> bool:
    """Whether pycolmap (with ``run_rotation_averaging``) can be imported."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    os.environ.setdefault("GLOG_minloglevel", "1")  # COLMAP's INFO lines would drown ours
    try:
        import pycolmap
    except ImportError:
        return False
    return hasattr(pycolmap, "run_rotation_averaging")


def _version() -> str:
    import pycolmap

    return str(getattr(pycolmap, "__version__", "?"))


def run_pycolmap(vg: ViewGraph, options: Any) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """``pycolmap.run_rotation_averaging`` on ``vg`` with ``RotationEstimatorOptions`` ``options``.

    Returns:
        R: (N, 3, 3) cam_from_world rotations (identity where not posed); registered: (N,)
        bool; seconds: the wall time of ``run_rotation_averaging`` alone; ok: its return value.
    """
    import pycolmap

    N = vg.n_cameras
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 500.0, 640, 480))
    for i in range(N):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=vg.names[i], camera_id=1, image_id=i + 1))
    pg = pycolmap.PoseGraph()
    nm = np.maximum(np.asarray(vg.inliers, dtype=np.int64), 1) if vg.inliers is not None else np.full(vg.n_edges, 100)
    for (a, b), Rr, n in zip(vg.edges, vg.R_rel, nm):  # pycolmap takes one object per edge
        e = pycolmap.PoseGraphEdge(pycolmap.Rigid3d(pycolmap.Rotation3d(Rr), np.zeros(3)))
        e.num_matches = int(n)
        pg.add_edge(int(a) + 1, int(b) + 1, e)
    # COLMAP's INFO lines would drown ours (shown when debugging, as the other stages do): GLOG_minloglevel
    # (have_pycolmap) acts only if set before glog starts, and another stage may have imported pycolmap first
    level = pycolmap.logging.minloglevel
    if not logger.isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = max(level, 1)
    t = time.perf_counter()
    try:
        ok = bool(pycolmap.run_rotation_averaging(options, pg, rec, []))
    finally:
        dt = time.perf_counter() - t
        pycolmap.logging.minloglevel = level
    R = np.tile(np.eye(3), (N, 1, 1))
    registered = np.zeros(N, dtype=bool)
    for iid, im in rec.images.items():
        if im.has_pose:
            R[iid - 1] = im.cam_from_world().rotation.matrix()
            registered[iid - 1] = True
    return R, registered, dt, ok


@dataclass(frozen=True, kw_only=True)
class ColmapRAConfig(Config):
    """Options of the ``colmap-ra`` method: pycolmap's ``RotationEstimatorOptions`` we expose."""

    SECTION = "averaging.colmap-ra"
    weight_type: str = option("GEMAN_MCCLURE", "COLMAP's IRLS weight (a RotationWeightType name)")
    irls_loss_parameter_sigma: float = option(5.0, "COLMAP's loss scale, degrees", gt=0)
    max_num_l1_iterations: int = option(5, "COLMAP's ℓ1 iterations", ge=0)
    max_num_irls_iterations: int = option(100, "COLMAP's IRLS iteration cap", ge=0)
    irls_step_convergence_threshold: float = option(1e-3, "COLMAP's IRLS stop on the mean update", gt=0)
    use_stratified: bool = option(True, "COLMAP's stratified (gravity-free) start")

    def check(self) -> None:
        if not self.weight_type.replace("_", "").isalpha():
            raise ConfigError(f"[averaging.colmap-ra] weight_type={self.weight_type!r}; expected a "
                              "pycolmap.RotationWeightType name such as GEMAN_MCCLURE or HALF_NORM")


def _options(cfg: ColmapRAConfig) -> Any:
    import pycolmap

    o = pycolmap.RotationEstimatorOptions()
    wt = getattr(pycolmap, "RotationWeightType", None)
    if wt is not None and hasattr(wt, cfg.weight_type):
        o.weight_type = getattr(wt, cfg.weight_type)
    elif wt is not None:
        names = [n for n in dir(wt) if n.isupper()]
        raise ConfigError(f"[averaging.colmap-ra] weight_type={cfg.weight_type!r}; pycolmap knows {names}")
    for key in ("irls_loss_parameter_sigma", "max_num_l1_iterations", "max_num_irls_iterations",
                "irls_step_convergence_threshold", "use_stratified"):
        if hasattr(o, key):
            setattr(o, key, getattr(cfg, key))
    return o


def colmap_ra(vg: ViewGraph, config: ColmapRAConfig | None = None, *, init: Any = None,
              init_weights: np.ndarray | None = None, **options: Any) -> AveragingResult:
    """COLMAP's ℓ1 + IRLS rotation averaging of a connected view graph (module docstring).

    Args:
        vg: a connected view graph; ``inliers`` become COLMAP's ``num_matches`` (100 without).
        config: the options (:class:`ColmapRAConfig`); ``**options`` override its fields.
        init, init_weights: not supported (COLMAP makes its own start); must be None.

    Returns:
        :class:`AveragingResult` ``"colmap-ra"`` with ``residuals_rad`` and ``stats``
        (``colmap_s``: the time of ``run_rotation_averaging`` alone, ``options``).

    Raises:
        ViewGraphError: pycolmap is missing, fails, or leaves cameras unposed.
    """
    cfg = method_config(ColmapRAConfig, config, options)
    if init is not None or init_weights is not None:
        raise ConfigError("method 'colmap-ra' makes its own start; drop init / init_weights")
    if not have_pycolmap():
        raise ViewGraphError("method 'colmap-ra' needs pycolmap (pip install pycolmap, the bench extra)")
    t0 = time.perf_counter()
    N = vg.n_cameras
    try:
        R, registered, t_colmap, ok = run_pycolmap(vg, _options(cfg))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises on degenerate input (e.g. a Cholesky failure)
        raise ViewGraphError(f"pycolmap's run_rotation_averaging failed: {' '.join(str(exc).split())[:200]}") from None
    R[~registered] = np.nan
    unposed = [vg.names[k] for k in np.flatnonzero(~np.isfinite(R).all(axis=(1, 2)))]
    if not ok or unposed:
        raise ViewGraphError(f"pycolmap's rotation averaging returned {ok} and left {len(unposed)} of {N} cameras "
                             f"unposed (e.g. {unposed[:3]})")
    R = so3.project_to_so3(R)
    theta = so3.angle_between(so3.relative(R, vg.edges), vg.R_rel)
    return AveragingResult(
        method="colmap-ra", names=list(vg.names), R=R, time_s=time.perf_counter() - t0, iterations=0,
        edge_index=np.arange(vg.n_edges), residuals_rad=theta,
        stats={"colmap_s": t_colmap, "pycolmap": _version(),
               "options": {k: getattr(cfg, k) for k in cfg.as_dict()},
               "num_matches": "inliers" if vg.inliers is not None else "100 (no inlier counts)"})
