"""The evaluation of one run of ``run.py``: every method against every reference, then metrics.json and the report.

:func:`evaluate_run` scores every averaging method against the truth (when given),
the truth restricted to the images pycolmap registered (when it left some out:
the like-for-like comparison) and pycolmap's reconstruction. :func:`write_report_md`
adds the error-against-time curves, writes ``OUT/report.md`` (and its plots);
:func:`write_metrics` writes ``OUT/metrics.json`` (atomically) and prints the summary table.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.averaging.convergence import error_vs_time_curves
from pipeline.core.atomic import write_json
from pipeline.core.errors import PipelineError
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.compare import evaluate_all, truth_on_registered
from pipeline.evaluation.report import report_data, summary_table, write_report
from pipeline.reference.types import Reference

__all__ = ["RunEvaluation", "evaluate_run", "write_report_md", "write_metrics", "pairs_section", "OUR_PATH"]

# the stages of our own path, from images to rotations (what a time ratio against a peer counts)
OUR_PATH = ("features", "matching", "two_view", "two_view_ba", "viewgraph", "averaging")


@dataclass
class RunEvaluation:
    """The evaluation of a run: metrics, per-camera and per-edge errors, and the references used."""

    metrics: dict[str, Any]
    camera_errors: dict[str, Any]
    edge_errors: dict[str, Any]
    refs: list[Reference]


def evaluate_run(plan: Any, vg: ViewGraph, results: dict[str, dict], peer: Reference | None) -> RunEvaluation:
    """Every method of ``results`` against the truth of ``plan`` and the pycolmap ``peer``."""
    from pipeline.geometry.two_view_stage import load_two_view  # noqa: PLC0415

    try:
        ransac_vg = load_two_view(plan.work).vg
    except (PipelineError, OSError):
        ransac_vg = None
    refs: list[Reference] = [plan.truth] if plan.truth is not None else []
    if peer is not None and len(peer.names) >= 2:
        sub = truth_on_registered(plan.truth, peer, vg)
        refs += ([sub] if sub is not None else []) + [peer]
    metrics, cam_err, edge_err = evaluate_all(vg, ransac_vg, results, refs, peer, plan.run.align)
    if not refs:
        plan.notes.append("no reference: pass --gt REF or enable the pycolmap reference to get errors")
    return RunEvaluation(metrics, cam_err, edge_err, refs)


def write_report_md(plan: Any, ev: RunEvaluation, specs: list[Any], results: dict[str, dict], vg: ViewGraph,
                    runner: Any) -> Path:
    """Add the error-against-time curves to the metrics and write report.md (with plots)."""
    metrics, refs = ev.metrics, ev.refs
    histories = error_vs_time_curves(vg, specs, results, refs[0], plan.run.align) if refs else {}
    for label, c in histories.items():
        metrics["methods"][label]["error_vs_time"] = c
    stages = {k + (" (reused)" if runner.reused.get(k) else ""): v for k, v in runner.times.items()}
    data = report_data(metrics, refs, ev.camera_errors, ev.edge_errors, histories, vg, plan.notes, stages,
                       f"Rotations of {plan.images}", plan.run.plots)
    return write_report(plan.out, data)


def pairs_section(work: Path) -> dict[str, Any]:
    """How the matched pairs were chosen (the matching record's summary): selector, K, pairs vs exhaustive."""
    from pipeline.frontend.matching_stage import MatchingStage  # noqa: PLC0415
    from pipeline.stage import read_record  # noqa: PLC0415

    rec = read_record(Path(work), MatchingStage.name)
    return dict(rec.summary.get("pairs", {})) if rec is not None else {}


def write_metrics(plan: Any, ev: RunEvaluation, vg: ViewGraph, left_out: dict[str, str], runner: Any,
                  t_start: float) -> Path:
    """Write metrics.json (with every step's time) and print the summary table; returns its path."""
    metrics = ev.metrics
    from pipeline.frontend.feature_stage import load_manifest  # noqa: PLC0415

    names = load_manifest(plan.work)["names"]  # the images whose features were extracted
    metrics["stages"] = dict(runner.times)
    metrics["stages_reused"] = dict(runner.reused)
    metrics["total_s"] = time.perf_counter() - t_start
    metrics["our_path_s"] = sum(runner.times.get(k, 0.0) for k in OUR_PATH)
    metrics["input"] = {"images": str(plan.images), "n_images": len(names), "n_cameras_graph": vg.n_cameras,
                        "n_edges": vg.n_edges, "left_out": list(left_out), "left_out_why": left_out,
                        "gt": None if plan.gt is None else str(plan.gt), "K": None if plan.K is None else str(plan.K),
                        "config": plan.run.as_dict()}
    metrics["pairs"] = pairs_section(plan.work)
    metrics["notes"] = plan.notes
    path = write_json(plan.out / "metrics.json", metrics)
    if not plan.quiet:
        print(summary_table(metrics), flush=True)
        print(f"report: {plan.out / 'report.md'}\nmetrics: {path}", flush=True)
    return path
