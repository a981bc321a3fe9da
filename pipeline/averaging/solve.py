"""One entry point for every registered method: solve the largest connected component, name the rest."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from pipeline.averaging.kernel import check_graph
from pipeline.averaging.registry import get_method
from pipeline.averaging.residuals import held_measurements
from pipeline.averaging.result import AveragingResult, method_config
from pipeline.core.config import Config
from pipeline.core.errors import ConfigError, ViewGraphError
from pipeline.core.viewgraph import ViewGraph

__all__ = ["average"]

logger = logging.getLogger(__name__)


def average(vg: ViewGraph, method: str = "irls", config: Config | None = None, *,
            init: str | np.ndarray | None = None, init_weights: np.ndarray | None = None,
            **options: Any) -> AveragingResult:
    """Average the relative rotations of a view graph with a registered method.

    Disconnected graphs: the largest connected component is solved; the other
    cameras are listed by name in ``dropped_names`` and a warning is logged. They are
    never silently dropped.

    Args:
        vg: the view graph.
        method: a registered method name (:mod:`pipeline.averaging.registry`):
            ``"irls"``, ``"irls-h"``, ``"l1"``, ``"weiszfeld"``, ``"sdp"``, ...
        config: the method's options (its config class); the registry's defaults if None.
        init: ``"mst"``, ``"random"`` or (N, 3, 3) initial rotations for every camera
            of ``vg``, in ``vg`` order (methods that take a start).
        init_weights: (M,) edge weights of the ``"mst"`` spanning tree.
        **options: fields of the method's config, overriding ``config`` (e.g.
            ``loss``, ``alpha_deg``, ``max_iterations``, ``tol_rad``, ``variant``).
            These are the product defaults: IRLS with the trimmed-ℓ2 polish, the SDP
            with its SCS cap before the Clarabel fallback.

    Returns:
        :class:`AveragingResult` for the solved component; ``edge_index`` indexes
        ``vg.edges``; ``dropped_names`` lists the cameras left out.

    Raises:
        ConfigError: unknown method or option, a bad option value (a ``ValueError``).
        ViewGraphError: an empty graph, a graph without edges, NaN rotations, no H
            for a method that needs it.
    """
    m = get_method(method)
    cfg = method_config(m.config_cls, config, options, init if m.takes_init else None)
    if not m.takes_init and (init is not None or init_weights is not None):
        raise ConfigError(f"method {method!r} takes no start (init, init_weights)")
    if m.requires_H(cfg) and vg.H is None:
        raise ViewGraphError(f"method {m.label(cfg)!r} needs a view graph with H (two-view BA precisions); "
                             "run the two-view BA stage or use a method without H (e.g. 'irls')")
    check_graph(vg, connected=False)
    sub, edge_kept, dropped = vg, np.arange(vg.n_edges), []
    if init is not None and not isinstance(init, str):
        init = np.asarray(init, dtype=np.float64)
        if init.shape != (vg.n_cameras, 3, 3):
            raise ValueError(f"init rotations have shape {init.shape} but expected ({vg.n_cameras}, 3, 3)")
    if not vg.is_connected():
        sub, res = vg.largest_component()
        edge_kept, dropped = res.edge_kept, res.dropped_names
        logger.warning(
            "view graph has %d components; solving the largest (%d of %d cameras); dropped: %s%s",
            int(vg.components().max()) + 1, sub.n_cameras, vg.n_cameras,
            ", ".join(dropped[:10]), " ..." if len(dropped) > 10 else "",
        )
        if init is not None and not isinstance(init, str):
            init = init[res.kept]
        if init_weights is not None:
            init_weights = np.asarray(init_weights)[edge_kept]
    with held_measurements(sub):  # the graph is not changed during the solve: its residual memo is validated once
        if m.takes_init:
            out = m.solve(sub, config=cfg, init=None if isinstance(init, str) else init, init_weights=init_weights)
        else:
            out = m.solve(sub, config=cfg)
    if out.edge_index is None:
        out.edge_index = np.arange(sub.n_edges)
    out.edge_index = np.asarray(edge_kept)[out.edge_index]
    out.dropped_names = list(dropped) + [n for n in out.dropped_names if n not in dropped]
    return out
