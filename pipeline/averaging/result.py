"""The result every averaging method returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


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
        weights: (m,) final IRLS weight of each edge used, or None.
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
    history: list[dict[str, float]] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary: method, sizes, time, iterations and ``stats``."""
        return {
            "method": self.method,
            "n_cameras": len(self.names),
            "n_edges": None if self.edge_index is None else int(len(self.edge_index)),
            "n_dropped": len(self.dropped_names),
            "dropped_names": list(self.dropped_names),
            "time_s": float(self.time_s),
            "iterations": int(self.iterations),
            **self.stats,
        }
