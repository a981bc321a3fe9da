"""The check of a stored per-pair result of the cameras stage before it is reused (the cache contract).

The cameras stage keeps each pair's F, focal profile, radial profile or PoseLib focal in its item store
(:meth:`pipeline.frontend.camera_stage.CamerasStage._pmap`). An item that reads well but is not what its
worker writes (a field missing or of another shape, a value out of its range) is recomputed, never reused:
:func:`check_item` says what is wrong with it.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from pipeline.core import so3
from pipeline.core.errors import CacheError
from pipeline.frontend.camera_estimate import f_ransac_chunk, focal_profile_chunk, poselib_chunk, radial_profile_chunk

__all__ = ["check_item"]


def _shape(item: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    v = item[name] if name in item else None
    if v is None or v.shape != shape or v.dtype.kind not in "biuf":
        raise CacheError(f"its {name!r} is missing or not of shape {shape}")
    return v


def _finite(v: np.ndarray, name: str) -> None:
    if not np.isfinite(v).all():
        raise CacheError(f"its {name!r} has NaN or inf")


def check_item(worker: Callable[..., Any], task: tuple, item: dict[str, np.ndarray]) -> None:
    """:class:`CacheError` where ``item`` cannot be what ``worker`` (one of the module's chunk workers, or a
    ``functools.partial`` of one) writes for ``task``."""
    fn = getattr(worker, "func", worker)
    if fn is f_ransac_chunk:  # task: (x1, x2, threshold_px, seed)
        _shape(item, "ok", ())
        _finite(_shape(item, "F", (3, 3)), "F")
        h = _shape(item, "h_ratio", ())
        inl = item["inliers"] if "inliers" in item else None
        if inl is None or inl.ndim != 1 or inl.dtype.kind not in "iu":
            raise CacheError("its 'inliers' are missing or not indices")
        if len(inl) and (inl.min() < 0 or inl.max() >= len(task[0])):
            raise CacheError(f"its inliers refer to matches outside the pair's {len(task[0])}")
        if not (np.isfinite(h) and h >= 0):
            raise CacheError("its homography ratio is out of its range")
    elif fn is focal_profile_chunk:  # task: (x1, x2, F, pp1, pp2, grid1, grid2[, ends])
        g = len(task[5])
        _finite(_shape(item, "cost", (g,)), "cost")
        R = _shape(item, "R", (g, 3, 3))
        _finite(_shape(item, "t", (g, 3)), "t")
        if not so3.is_rotation(R).all():
            raise CacheError("its profile holds a matrix that is not a rotation")
        _positive_sigma2(item)
    elif fn is radial_profile_chunk:  # task: (x1, x2, F, c, s, grid, g0)
        _finite(_shape(item, "cost", (len(task[5]),)), "cost")
        _positive_sigma2(item)
    elif fn is poselib_chunk:  # task: (x1, x2, pp, threshold_px, seed); f is NaN where the solver failed
        f, n = _shape(item, "f", ()), _shape(item, "n_inliers", ())
        if not (np.isnan(f) or (np.isfinite(f) and f > 0)) or not 0 <= n <= len(task[0]):
            raise CacheError("its focal or inlier count is out of its range")
    else:
        raise ValueError(f"no check for the worker {fn!r}")


def _positive_sigma2(item: dict[str, np.ndarray]) -> None:
    s2 = _shape(item, "sigma2", ())
    if not (np.isfinite(s2) and s2 > 0):
        raise CacheError("its σ² is out of its range")
