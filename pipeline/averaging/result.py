"""What every averaging method takes (a typed config) and returns (:class:`AveragingResult`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping, TypeVar

import numpy as np

from pipeline.core.config import Config
from pipeline.core.errors import ConfigError

__all__ = ["AveragingResult", "method_config", "start_of"]

C = TypeVar("C", bound=Config)


def method_config(cls: type[C], config: C | None, options: Mapping[str, Any], init: Any = None,
                  bare: Mapping[str, Any] | None = None) -> C:
    """The typed config of one call of a method: ``config`` (or the defaults) with ``options`` applied.

    Every method takes ``(vg, config=None, *, init=None, init_weights=None, **options)``;
    ``options`` are fields of ``cls`` and are checked by it, so an unknown or
    ill-typed option is a :class:`ConfigError` naming the allowed keys.

    Args:
        cls: the method's config class.
        config: a config to start from, or None for the class defaults.
        options: field overrides.
        init: the ``init`` argument of the call: a string (``"mst"``, ``"random"``)
            sets the config's ``init``; an array is the caller's business.
        bare: overrides applied before ``options`` when ``config`` is None: the
            defaults of the function called bare where they differ from the
            product's (e.g. ``irls()`` alone is paper 1's Algorithm 3, no polish).
    """
    if config is not None and not isinstance(config, cls):
        raise ConfigError(f"expected a {cls.__name__}, got {type(config).__name__}")
    opts = dict(options)
    if isinstance(init, str):
        opts["init"] = init
    if config is None:
        return cls.from_dict({**(bare or {}), **opts})
    if not opts:
        return config
    base = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    return cls.from_dict({**base, **opts})


def start_of(init: Any, config: Config) -> Any:
    """What a method starts from: the caller's (N, 3, 3) rotations, else the config's ``init`` tree kind."""
    return config.init if init is None or isinstance(init, str) else init  # type: ignore[attr-defined]


@dataclass
class AveragingResult:
    """Absolute rotations estimated from a view graph.

    Attributes:
        method: a short label, e.g. ``"irls-l0.5"`` or ``"sdp-cso3"``.
        names: names of the cameras solved for (the largest connected component).
        R: (n, 3, 3) cam_from_world rotations, in the order of ``names``.
        time_s: solver wall time in seconds.
        iterations: iterations taken (0 where the notion does not apply).
        dropped_names: cameras of the input outside the solved component.
        edge_index: (m,) index into the input graph's edges of each edge used.
        residuals_rad: (m,) final residual angle of each edge used, or None.
        weights: (m,) weight of each edge used in the method's final problem, or None.
        kept: (m,) bool, the edges the result relies on (the rest were rejected as
            outliers or kept only a negligible weight), or None (every edge).
        history: per-iteration records (dicts with at least ``cost``,
            ``mean_step_rad`` and ``time_s``), possibly empty.
        stats: method-specific figures (gradient norm, SDP certificate, ...),
            JSON-serializable.
    """

    method: str
    names: list[str]
    R: np.ndarray
    time_s: float
    iterations: int = 0
    dropped_names: list[str] = field(default_factory=list)
    edge_index: np.ndarray | None = None
    residuals_rad: np.ndarray | None = None
    weights: np.ndarray | None = None
    kept: np.ndarray | None = None
    history: list[dict[str, float]] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary: method, sizes, time, iterations and ``stats``."""
        return {
            "method": self.method,
            "n_cameras": len(self.names),
            "n_edges": None if self.edge_index is None else int(len(self.edge_index)),
            "n_kept": None if self.kept is None else int(np.sum(self.kept)),
            "n_dropped": len(self.dropped_names),
            "dropped_names": list(self.dropped_names),
            "time_s": float(self.time_s),
            "iterations": int(self.iterations),
            **self.stats,
        }
