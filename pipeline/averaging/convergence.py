"""Error against time of the iterative methods (paper 1, Fig. 5c), for the report.

The solvers keep no per-iteration rotations, so a run is repeated with budgets of
1..L ℓ1 steps, then L ℓ1 + 1..K IRLS steps (L and K: what the full run took), without
the final polish; each point is placed at the full run's cumulative time of that
iteration (its ``history``), and the last point is the full run's own result. Which
methods allow this is the registry's ``Method.error_vs_time``.
"""

from __future__ import annotations

import logging
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from pipeline.averaging.registry import MethodSpec
from pipeline.core.errors import PipelineError
from pipeline.core.viewgraph import ViewGraph
from pipeline.io.rotations import read_rotations

__all__ = ["error_vs_time", "error_vs_time_curves"]


class Reference(Protocol):
    names: list[str]
    R: np.ndarray


def error_vs_time(vg: ViewGraph, spec: MethodSpec, stats: Mapping[str, Any], R_final: np.ndarray, ref: Reference,
                  align: str, max_n: int = 300) -> list[dict[str, float]]:
    """Median error against ``ref`` after each iteration of one run of ``spec`` (module docstring).

    Args:
        vg: the (connected) view graph the run solved.
        spec: the method and options of the run.
        stats: the run's stats (``history``, ``l1_iterations``, ``irls_iterations``, ``time_s``).
        R_final: (N, 3, 3) the run's rotations, in ``vg`` order.
        ref: a reference with ``names`` and ``R``.
        align: the evaluation's global alignment (``"l2"`` or ``"l1"``).
        max_n: larger graphs get no curve (each point is a solve).

    Returns:
        ``[{"time_s", "median_deg", "l1_iterations", "irls_iterations"}, ..., {..., "final": True}]``,
        or ``[]`` when the method has no such curve or fewer than 2 cameras are in ``ref``.
    """
    method = spec.method
    if not method.error_vs_time or vg.n_cameras > max_n:
        return []
    from pipeline.evaluation import compare, metrics  # noqa: PLC0415

    R_ref, mask = compare.match_reference(list(vg.names), ref.names, ref.R)
    if mask.sum() < 2:
        return []
    hist = list(stats.get("history") or [])
    L = int(stats.get("l1_iterations", 0) or 0)
    K = int(stats.get("irls_iterations", 0) or 0)
    budgets = [(l, 0) for l in range(1, L + 1)] + [(L, k) for k in range(1, K + 1)]
    fields = spec.method.fields()
    extra: dict[str, Any] = {"certify": False} if "certify" in fields else {}
    if "start" in fields and stats.get("start_used") in ("tree", "l1"):
        extra["start"] = stats["start_used"]  # the branch the full run kept, alone
    quiet = logging.getLogger("pipeline.averaging")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # each truncated run would warn that it hit its (deliberate) cap
    curve = []
    try:
        for n_done, (l, k) in enumerate(budgets):
            try:
                cfg = spec.config.replace(refine=False, l1_iterations=l, max_iterations=k, **extra)
                r = method.solve(vg, config=cfg)
            except (PipelineError, ValueError, IndexError, TypeError):
                continue
            e = metrics.rotation_errors_deg(r.R, R_ref, mask, align=align)
            t = hist[n_done]["time_s"] if n_done < len(hist) and "time_s" in hist[n_done] else r.time_s
            curve.append({"time_s": float(t), "median_deg": float(np.nanmedian(e)), "l1_iterations": l,
                          "irls_iterations": k})
    finally:
        quiet.setLevel(level)
    e = metrics.rotation_errors_deg(R_final, R_ref, mask, align=align)
    curve.append({"time_s": float(stats.get("time_s", curve[-1]["time_s"] if curve else 0.0)),
                  "median_deg": float(np.nanmedian(e)), "l1_iterations": L, "irls_iterations": K, "final": True})
    return curve


def error_vs_time_curves(vg: ViewGraph, specs: Sequence[MethodSpec], results: Mapping[str, Mapping[str, Any]],
                         ref: Reference, align: str, max_n: int = 300) -> dict[str, list[dict[str, float]]]:
    """``{label: curve}`` of every method in ``specs`` that has one (``results[label]``: rotations, stats)."""
    curves = {}
    for spec in specs:
        if not spec.method.error_vs_time or spec.label not in results:
            continue
        names, R = read_rotations(results[spec.label]["rotations"])
        if list(names) != list(vg.names):
            continue
        c = error_vs_time(vg, spec, results[spec.label]["stats"], np.asarray(R), ref, align, max_n)
        if c:
            curves[spec.label] = c
    return curves
