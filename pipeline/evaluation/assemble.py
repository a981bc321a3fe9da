"""The evaluation of one run of ``run.py``: every method against every reference, then metrics.json and the report.

:func:`evaluate_run` scores every averaging method against the truth (when given),
the truth restricted to the images each pycolmap peer registered (when it left some
out: the like-for-like comparison) and the peers' reconstructions (incremental, GLOMAP). :func:`write_report_md`
adds the error-against-time curves, writes ``OUT/report.md`` (and its plots);
:func:`write_metrics` writes ``OUT/metrics.json`` (atomically) and prints the summary table.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.averaging.convergence import error_vs_time_curves
from pipeline.core.atomic import finite_json, write_json
from pipeline.core.errors import PipelineError
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation.compare import evaluate_all, truth_on_registered
from pipeline.evaluation.flags import evidence_console, method_disagreement, run_evidence
from pipeline.evaluation.console import intrinsics_console, summary_table
from pipeline.evaluation.report import report_data, write_report
from pipeline.reference.types import Reference

__all__ = ["RunEvaluation", "evaluate_run", "write_report_md", "write_metrics", "withdraw_reports", "pairs_section",
           "finite_json", "OUR_PATH", "UNITS"]

# the stages of our own path, from images to the refined rotations (what a time ratio against a peer counts)
OUR_PATH = ("features", "matching", "cameras", "two_view", "two_view_ba", "loop_closure", "viewgraph", "averaging",
            "refine")


#: metrics.json's ``units``: what the figures whose key carries no unit are in (a key ending in _deg is in degrees,
#: _s in seconds, _px in pixels; n_... is a count). A method's own stats (methods.<m> beyond its summary) are those
#: of rotations/<m>.json, their certificate worded by its statement.
UNITS = {
    "_deg": "degrees", "_s": "seconds", "_px": "pixels", "n_": "a count",
    "stages": "seconds of wall time per stage (a reused stage: the time to check and load its result)",
    "pct_below": "percent of the evaluated cameras whose error is under that many degrees",
    "pct_above": "percent of the evaluated pairs whose relative-rotation error is above that many degrees",
    "frobenius": "√Σ‖R_i − R_i*‖²_F after the best alignment, dimensionless (rotation matrices)",
    "mahalanobis": "paper 2's eq. C.13, dimensionless (rotation errors in radians weighed by the precisions H)",
    "methods": "each method's summary against each reference (the keys here) beside the averaging stage's own "
    "stats of it (rotations/<method>.json; its certificate in words: certificate.statement)",
    "sigma_median_deg": "degrees predicted by pycolmap's BA covariance (√tr Σ, median over the cameras; per "
    "camera: uncertainty_deg): a precision under the model, not an accuracy",
    "pairs": "counts of image pairs", "gap": "relative to the cost's magnitude (its statement gives the "
    "gap against the cost's resolution, what the verdict rests on)", "rank": "of the SDP solution",
}


def _intrinsics(work: Path) -> dict[str, Any]:
    """The cameras stage's summary (focal used, its source, distortion); empty if the stage has not run."""
    from pipeline.frontend.camera_stage import intrinsics_summary, load_cameras  # noqa: PLC0415

    try:
        return intrinsics_summary(load_cameras(work))
    except (PipelineError, OSError):
        return {}


def _guessed_focal(intrinsics: dict[str, Any]) -> list[str]:
    """The images whose focal length is only the default guess (source ``default`` in the cameras summary)."""
    return [n for n, v in intrinsics.get("per_image", {}).items() if v.get("source") == "default"]


@dataclass
class RunEvaluation:
    """The evaluation of a run: metrics, per-camera and per-edge errors, the references used, and the cameras
    stage's summary (:func:`_intrinsics`, read once for the evidence, the report and metrics.json)."""

    metrics: dict[str, Any]
    camera_errors: dict[str, Any]
    edge_errors: dict[str, Any]
    refs: list[Reference]
    intrinsics: dict[str, Any]


def evaluate_run(plan: Any, vg: ViewGraph, results: dict[str, dict], peer: Reference | list[Reference] | None
                 ) -> RunEvaluation:
    """Every method of ``results`` against the truth of ``plan`` and the pycolmap peers (incremental, GLOMAP).

    Each peer that leaves images out adds the truth restricted to its images (the like-for-like comparison).
    """
    from pipeline.geometry.two_view_stage import load_two_view  # noqa: PLC0415

    try:
        ransac_vg = load_two_view(plan.work).vg
    except (PipelineError, OSError):
        ransac_vg = None
    refs: list[Reference] = [plan.truth] if plan.truth is not None else []
    peers = [] if peer is None else [peer] if isinstance(peer, Reference) else list(peer)
    for p in peers:
        if len(p.names) >= 2:
            sub = truth_on_registered(plan.truth, p, vg)
            refs += ([sub] if sub is not None else []) + [p]
    metrics, cam_err, edge_err = evaluate_all(vg, ransac_vg, results, refs, peers, plan.run.align)
    intrinsics = _intrinsics(plan.work)
    metrics["evidence"] = _evidence(plan.out, intrinsics, metrics["methods"], results)
    guessed = _guessed_focal(intrinsics)  # a note of report.md too: said before the report is written
    if guessed:
        plan.notes.append(f"{len(guessed)} image(s) kept the default focal guess 1.2·max(w, h): nothing "
                          "determined theirs (cameras.json: estimate); they are flagged")
    if not refs:
        plan.notes.append("no reference: pass --gt REF or enable the pycolmap reference to get errors")
    return RunEvaluation(metrics, cam_err, edge_err, refs, intrinsics)


def _evidence(out: Path, intrinsics: dict[str, Any], methods: dict[str, Any], results: dict[str, dict]
              ) -> dict[str, Any]:
    """The view graph's flags and messages joined with each method's per-camera support, the methods'
    disagreement and the images whose focal length is only a guess ({} without a view-graph summary)."""
    from pipeline.graph.stage import load_graph_summary  # noqa: PLC0415
    from pipeline.io.rotations import read_rotations  # noqa: PLC0415

    try:
        graph = load_graph_summary(out)
    except PipelineError:
        return {}
    rots = {label: read_rotations(r["rotations"]) for label, r in results.items()}
    placed = {n: f"{why} ({label})" for label, r in results.items()
              for n, why in ((r.get("stats") or {}).get("placed") or {}).items()}
    ev = run_evidence(graph, methods, method_disagreement(rots), _guessed_focal(intrinsics), placed)
    ev["messages"] += _weak_focal_messages(intrinsics)
    return ev


def _weak_focal_messages(intrinsics: dict[str, Any]) -> list[str]:
    """One message per camera group whose estimated focal length is poorly determined (its jackknife sd)."""
    out = []
    for g in intrinsics.get("estimates", []):
        f = g.get("focal") or {}
        if f.get("determined") is False and isinstance(f.get("f"), float) and math.isfinite(f["f"]):
            sd = f", jackknife sd {100 * f['sd_rel']:.1f}%" if isinstance(f.get("sd_rel"), float) else ""
            out.append(f"the focal length of {g.get('n_images')} image(s) is poorly determined ({f['f']:.1f} px{sd}): "
                       "the averaged rotations rest on it and may be off by degrees with no inconsistency to show it")
    return out


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
    data.intrinsics = ev.intrinsics
    data.n_images = _n_images(plan.work)
    data.not_run = dict(getattr(runner, "not_run", {}))
    return write_report(plan.out, data)


def _n_images(work: Path) -> int | None:
    """The run's images: those the features stage read and those it skipped (None without its manifest)."""
    from pipeline.frontend.feature_stage import load_manifest  # noqa: PLC0415

    try:
        m = load_manifest(work)
    except (PipelineError, OSError):
        return None
    return len(m["names"]) + len(m.get("skipped") or [])


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

    manifest = load_manifest(plan.work)
    names = manifest["names"]  # the images whose features were extracted
    # every image of the folder is accounted for: those the features stage skipped (unreadable, too small, ...) too
    skipped = {str(d["name"]): f"skipped by the features stage: it {d['reason']}" for d in manifest.get("skipped") or []
               if isinstance(d, dict) and "name" in d}
    left_out = {**skipped, **left_out}
    placed = {n: f"{why} ({label})" for label, m in metrics["methods"].items()  # solved after all, by a refinement
              for n, why in (m.get("placed") or {}).items() if n in left_out}
    left_out = {n: f"{w}; {placed[n]}" if n in placed else w for n, w in left_out.items()}
    metrics["stages"] = dict(runner.times)
    metrics["stages_reused"] = dict(runner.reused)
    metrics["steps_not_run"] = dict(getattr(runner, "not_run", {}))
    metrics["total_s"] = time.perf_counter() - t_start
    metrics["our_path_s"] = sum(runner.times.get(k, 0.0) for k in OUR_PATH)
    metrics["input"] = {"images": str(plan.images), "n_images": len(names), "n_skipped": len(skipped),
                        "n_cameras_graph": vg.n_cameras,
                        "n_edges": vg.n_edges, "left_out": list(left_out), "left_out_why": left_out,
                        "gt": None if plan.gt is None else str(plan.gt), "K": None if plan.K is None else str(plan.K),
                        "config": plan.run.as_dict()}
    metrics["intrinsics"] = ev.intrinsics
    metrics["pairs"] = pairs_section(plan.work)
    metrics["components"] = list(getattr(plan, "components", []))  # the view graph's other components, solved apart
    metrics["notes"] = plan.notes
    metrics["units"] = UNITS
    path = write_json(plan.out / "metrics.json", metrics)
    # every run says it, a resumed one too (the stages that found it may not run)
    unsolved = "\n".join(x for x in (_unsolved_line({n: w for n, w in left_out.items() if n not in placed}),
                                      _placed_line(placed)) if x)
    if not plan.quiet:
        print(summary_table(metrics), flush=True)
        if metrics["intrinsics"]:
            print(intrinsics_console(metrics["intrinsics"]), flush=True)
        lines = evidence_console(metrics.get("evidence") or {})
        if lines:
            print(lines, flush=True)
        if unsolved:
            print(unsolved, flush=True)
        print(f"report: {plan.out / 'report.md'}\nmetrics: {path}", flush=True)
    elif (metrics.get("evidence") or {}).get("n_flagged") or unsolved:  # -q: warnings only, and these are
        lines = [ln for ln in evidence_console(metrics.get("evidence") or {}).splitlines() if not ln.startswith("†")]
        print("\n".join(lines + ([unsolved] if unsolved else []) + [f"metrics: {path}"]), file=sys.stderr, flush=True)
    return path


def _placed_line(placed: dict[str, str]) -> str:
    """One console line naming the images outside the view graph that a refinement alone placed ("" when none)."""
    if not placed:
        return ""
    return (f"WARNING: {len(placed)} image(s) outside the view graph placed by a refinement alone (flagged): "
            + "; ".join(f"{n}: {w}" for n, w in placed.items()))


def _unsolved_line(left_out: dict[str, str], limit: int = 5) -> str:
    """One console line naming the images this run did not solve here ("" when none)."""
    if not left_out:
        return ""
    names = list(left_out)
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return (f"WARNING: {len(names)} image(s) not solved in this frame: {', '.join(names[:limit])}{more} (why: "
            "metrics.json input.left_out_why)")


def withdraw_reports(out: Path) -> None:
    """Remove the report and metrics of an earlier run in ``out`` (and in its component folders) as a run starts: one
    that does not finish then leaves none, rather than figures of files it has since replaced."""
    for folder in (Path(out), *sorted(Path(out).glob("component-*"))):
        for name in ("report.md", "metrics.json"):
            (folder / name).unlink(missing_ok=True)
