"""The run report (``OUT/report.md`` with one table per reference, and PNG plots); the console tables are
:mod:`pipeline.evaluation.console` (re-exported here).

:func:`write_report` takes plain arrays and dicts (:class:`ReportData`) so that
anything (run.py, a benchmark, a notebook) can call it; :func:`report_data`
assembles them from the metrics of :func:`pipeline.evaluation.compare.evaluate_all`.
The plots are :mod:`pipeline.evaluation.plots`.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.atomic import atomic_open
from pipeline.core.names import rows_by_name
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation import plots
from pipeline.evaluation.compare import subset_prefix
from pipeline.evaluation.console import (  # noqa: F401 (the console's, re-exported)
    PEER_ROWS, _finite, _peers, console_table, edge_rows, intrinsics_console, peer_row, summary_rows, summary_table)
from pipeline.evaluation.flags import CERTIFICATE_NOTE, certificate_cell, certificate_statements, evidence_markdown
from pipeline.reference.types import Reference

logger = logging.getLogger(__name__)

__all__ = ["ReportData", "metrics_table", "report_data", "write_report", "summary_table", "console_table",
           "summary_rows", "edge_rows", "intrinsics_lines", "intrinsics_console", "peer_row"]

TABLE_KEYS = [("n_evaluated", "cams", "{:d}"), ("median_deg", "median °", "{:.3f}"), ("mean_deg", "mean °", "{:.3f}"),
              ("rms_deg", "RMS °", "{:.3f}"), ("max_deg", "max °", "{:.3f}"), ("frobenius", "‖R−R*‖_F", "{:.4f}")]
METHOD_EXTRAS = ("time_s", "certified", "rank", "gap", "method", "status", "n_refined", "sigma_median_deg",
                 "certificate", "n_edges", "n_dropped", "dropped_names")
#: The table's key (and title) in a run with no reference: the methods without errors.
NO_REFERENCE = "Methods (no reference: no errors)"


@dataclass
class ReportData:
    """Everything the report shows.

    Attributes:
        metrics: ``{reference: {method: summary}}``, summaries as returned by
            :func:`pipeline.evaluation.metrics.summarize` (plus optional ``time_s``,
            ``certified``, ``rank``, ``gap``).
        camera_errors: ``{reference: {method: (N,) degrees, NaN = unevaluated}}``.
        edge_errors: ``{reference: {label: (M,) degrees}}``, labels such as
            ``"ransac"`` and ``"ba"``.
        histories: ``{method: [{"time_s", "cost", optional "median_deg"}, ...]}``
            of the iterative methods.
        vg_edges: (M, 2) edges of the view graph, or None.
        vg_names: camera names of the view graph.
        edge_values: ``{label: (M,)}`` values to colour edges by (error, weight).
        positions: (N, 2 or 3) camera positions for the picture, or None.
        notes: free lines appended under "Notes" (unregistered images, dropped
            cameras, warnings).
        sections: ``{title: markdown lines}`` shown before the notes (the refinement's
            per-camera table).
        stages: ``{stage: seconds}``.
        evidence: the "Evidence" section (markdown lines, :func:`pipeline.evaluation.flags.evidence_markdown`):
            graph messages, flagged cameras with the reason, what a certificate proves.
        certificates: ``{method: statement}``: what each certificate proves, for which cost on which edges.
        n_images: the run's images (the tables' cameras are counted of these), or None.
        ref_notes: ``{reference: line}`` under its table's title (a peer's own error against the truth).
        title: report title.
    """

    metrics: dict[str, dict[str, dict[str, Any]]]
    camera_errors: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    edge_errors: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    histories: dict[str, list[dict[str, float]]] = field(default_factory=dict)
    vg_edges: np.ndarray | None = None
    vg_names: list[str] = field(default_factory=list)
    edge_values: dict[str, np.ndarray] = field(default_factory=dict)
    positions: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)
    sections: dict[str, list[str]] = field(default_factory=dict)
    stages: dict[str, float] = field(default_factory=dict)
    not_run: dict[str, str] = field(default_factory=dict)  # step → why it did not run
    evidence: list[str] = field(default_factory=list)
    certificates: dict[str, str] = field(default_factory=dict)
    n_images: int | None = None
    ref_notes: dict[str, str] = field(default_factory=dict)
    title: str = "Rotation averaging report"
    intrinsics: dict[str, Any] = field(default_factory=dict)


def _slug(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in s)


def _fmt(v: Any, f: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    try:
        return f.format(int(v) if f == "{:d}" else float(v))
    except (TypeError, ValueError):
        return str(v)


def metrics_table(rows: dict[str, dict[str, Any]], n_images: int | None = None) -> list[str]:
    """Markdown table lines of ``{method: summary}``; ``n_images``: the run's images (the cameras column says of
    how many)."""
    keys = [h if k != "n_evaluated" or not n_images else f"{h} of {n_images}" for k, h, _ in TABLE_KEYS]
    head = ["method", *keys, "≤1°", "≤5°", "time s", "BA σ ° ‡", "certificate / status"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, m in rows.items():
        pct = m.get("pct_below", {}) or {}
        m = m if "n_evaluated" in m else m | {"n_evaluated": m.get("n_cameras")}  # no reference: the cameras solved
        cert = certificate_cell(m)  # † : for which cost (section "Certificates") and what it does not prove
        if m.get("method") == "refine":  # ok, partial (some cameras kept averaged) or failed (all kept)
            cert = f"refine {m['status']} ({m.get('n_refined')}/{m.get('n_cameras')} refined)"
        cert = "; ".join(x for x in (cert, *_fewer(m)) if x)
        cells = [name, *[_fmt(m.get(k), f) for k, _, f in TABLE_KEYS], _fmt(pct.get("1"), "{:.0f}%"),
                 _fmt(pct.get("5"), "{:.0f}%"), _fmt(m.get("time_s"), "{:.2f}"), _fmt(m.get("sigma_median_deg"), "{:.4f}"),
                 cert]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def peer_time_note(rows: dict[str, dict[str, Any]]) -> list[str]:
    """A line under a table with pycolmap rows: what their time counts (extraction, matching, mapping)."""
    parts = []
    for name, m in rows.items():
        t = m.get("times") if name.startswith("pycolmap") else None
        if isinstance(t, dict) and t:
            steps = [f"{t[k]:.2f} s {w}" for k, w in (("extract_s", "extraction"), ("match_s", "matching"),
                                                      ("map_s", "mapping")) if _finite(t.get(k))]
            parts.append(f"{name} {' + '.join(steps)}")
    return [f"time s of a pycolmap row, from the images: {'; '.join(parts)}.", ""] if parts else []


def _fewer(m: dict[str, Any]) -> list[str]:
    """Why a row scored fewer cameras: those outside the method's solved component, those the reference lacks."""
    def few(names: list[str]) -> str:
        return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")

    out = []
    if m.get("n_dropped"):
        out.append(f"{m['n_dropped']} camera(s) outside its solved component ({few(m.get('dropped_names') or [])})")
    if m.get("not_in_reference"):
        out.append(f"{len(m['not_in_reference'])} not in the reference ({few(m['not_in_reference'])})")
    return out


def sigma_note(rows: dict[str, dict[str, Any]]) -> list[str]:
    """The ‡ line under a table with a predicted σ: what it is, and how the measured median error compares."""
    have = {k: m for k, m in rows.items() if _finite(m.get("sigma_median_deg")) and m["sigma_median_deg"] > 0}
    if not have:
        return []
    ratios = [f"{m['median_deg'] / m['sigma_median_deg']:.2g}× it" + (f" ({k})" if len(have) > 1 else "")
              for k, m in have.items() if _finite(m.get("median_deg"))]
    return ["‡ BA σ: a precision under pycolmap's model, not an accuracy"
            + (f"; measured median error {', '.join(ratios)}." if ratios else ".") + " (\"Refinement\")", ""]


def report_data(metrics: dict[str, Any], refs: list[Reference], camera_errors: dict, edge_errors: dict,
                histories: dict[str, list[dict[str, float]]], vg: ViewGraph, notes: list[str],
                stages: dict[str, float], title: str, plots_on: bool = True) -> ReportData:
    """The report's content from :func:`pipeline.evaluation.compare.evaluate_all`'s results.

    One table per reference (each method's summary with its time and certificate;
    pycolmap's own row under the truth and its like-for-like subset); the view graph
    coloured by its edges' errors against the first reference and by inliers, placed
    at the first reference's centres when it has them. ``plots_on=False`` keeps the
    tables and notes only.
    """
    table = {r.label: {k: m["references"][r.label] | {kk: m.get(kk) for kk in METHOD_EXTRAS if kk in m}
                       for k, m in metrics["methods"].items()} for r in refs}
    if not refs:  # no errors, but the methods still: their cameras, time, certificate, the refinement's status
        table = {NO_REFERENCE: {k: {kk: m.get(kk) for kk in (*METHOD_EXTRAS, "n_cameras") if kk in m}
                                for k, m in metrics["methods"].items()}}
    ref_notes = {}
    for label, p in _peers(metrics).items():
        row = peer_row(label)
        if label in table and _finite(p.get("median_deg")):  # a peer as a reference: how far it is from the truth
            ref_notes[label] = (f"A reference, not the truth: {row} is itself {p['median_deg']:.3f}° (median) from "
                                f"the truth on its {p.get('n_evaluated')} images.")
        if "median_deg" in p:  # against the truth: on all its images, and on the subset of its images
            for r in refs:
                if r.label == "truth" or r.label.startswith(subset_prefix(label)):
                    table[r.label][row] = p
        for other, s in (p.get("references") or {}).items():  # against the other peers, on the images both register
            if other in table and "median_deg" in s:  # not where fewer than 2 images are in common
                table[other][row] = s | {"time_s": p.get("time_s"), "times": p.get("times")}
    edge_vals: dict[str, np.ndarray] = {}
    if refs and refs[0].label in edge_errors and "ba" in edge_errors[refs[0].label]:
        edge_vals[f"error_vs_{refs[0].label}"] = edge_errors[refs[0].label]["ba"]
    if vg.inliers is not None:
        edge_vals["inliers"] = np.asarray(vg.inliers, float)
    pos = None
    if refs and refs[0].centers is not None:
        pos = rows_by_name(list(vg.names), refs[0].names, np.asarray(refs[0].centers),
                           what=f"the reference '{refs[0].label}'")
    data = ReportData(
        metrics=table, camera_errors=camera_errors, edge_errors=edge_errors, histories=histories,
        vg_edges=vg.edges, vg_names=list(vg.names), edge_values=edge_vals if plots_on else {}, positions=pos,
        notes=notes, sections=_refine_sections(metrics, refs, camera_errors), stages=stages,
        evidence=evidence_markdown(metrics.get("evidence") or {}),
        certificates=certificate_statements(metrics["methods"]), ref_notes=ref_notes, title=title)
    if not plots_on:
        data.camera_errors, data.edge_errors, data.histories, data.vg_edges = {}, {}, {}, None
    return data


def _refine_sections(metrics: dict[str, Any], refs: list[Reference], camera_errors: dict) -> dict[str, list[str]]:
    """Per refined method: each camera's error against the first reference beside its predicted uncertainty."""
    out: dict[str, list[str]] = {}
    for label, m in metrics["methods"].items():
        sigma = m.get("uncertainty_deg")
        if not isinstance(sigma, dict):
            continue
        ref = refs[0].label if refs else None
        errs = camera_errors.get(ref, {}).get(label) if ref else None
        change, kept = m.get("change_from_averaged_deg") or {}, m.get("kept_averaged") or {}
        lines = [f"Start: {m.get('start_why', m.get('start'))}; status **{m.get('status')}**; "
                 "predicted σ = √tr Σ from pycolmap's BA covariance (minimum-norm gauge): how precise a rotation is "
                 "if the model (K, matches, kept pairs) is right, not an accuracy.", "",
                 f"| camera | error vs {ref or '–'} ° | predicted σ ° | change from averaged ° | not refined: why |",
                 "|---|---|---|---|---|"]
        over, n = 0, 0
        for k, nm in enumerate(sigma):
            e = errs[k] if errs is not None and k < len(errs) else None
            sd = None if nm in kept else sigma[nm]  # the model's σ is not that of a rotation it did not refine
            if _finite(e) and _finite(sd):
                n, over = n + 1, over + int(e > 3 * sd)
            lines.append(f"| {nm} | {_fmt(e, '{:.4f}')} | {_fmt(sd, '{:.4f}')} | "
                         f"{_fmt(change.get(nm), '{:.4f}')} | {kept.get(nm, '')} |")
        said = {f"{nm}: {why}" for nm, why in kept.items()}  # in the camera's row
        warns = [w for w in m.get("warnings") or [] if w not in said]
        if warns:
            lines += ["", "Warnings of the refinement:", "", *[f"- {w}" for w in warns]]
        if n:
            lines += ["", f"Measured: {over} of {n} refined cameras are more than 3σ off against {ref}."]
        out[f"Refinement ({label})"] = lines + [""]
    return out


def write_report(out: str | os.PathLike, data: ReportData) -> Path:
    """Write ``out/report.md`` and its PNGs; returns the report path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# {data.title}", ""]
    lines += intrinsics_lines(data.intrinsics)
    if data.stages:
        total = sum(data.stages.values())
        lines += ["## Stages", "", "| stage | wall time (s) |", "|---|---|"]
        lines += [f"| {k} | {v:.2f} |" for k, v in data.stages.items()]
        lines += [f"| **sum of the stages above** | {total:.2f} |", "",
                  "(The report's own stage and the start are not in it: the whole run's wall time is metrics.json's "
                  "total_s.)", ""]
    if data.not_run:
        lines += ["Not run: " + "; ".join(f"{k} ({why})" for k, why in data.not_run.items()) + ".", ""]
    lines += data.evidence
    if data.certificates:
        lines += ["## Certificates", "", f"{CERTIFICATE_NOTE[0].upper()}{CERTIFICATE_NOTE[1:]}: each below says for "
                  "which cost on which edges.", "", "| method | what its certificate proves (cost, edges) |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in data.certificates.items()] + [""]
    timed: set[str] = set()
    for ref, rows in data.metrics.items():
        lines += [f"## {ref}" if ref == NO_REFERENCE else f"## Against {ref}", ""]
        lines += [data.ref_notes[ref], ""] if ref in data.ref_notes else []
        lines += [*metrics_table(rows, data.n_images),
                  "", *sigma_note(rows)]
        lines += peer_time_note({k: m for k, m in rows.items() if k not in timed})  # each peer's once
        timed |= set(rows)
        if any(certificate_cell(m) for m in rows.values()):
            lines += ["† for which cost and edges, and what it does not prove: \"Certificates\".", ""]
        errs = data.camera_errors.get(ref)
        if errs:
            p = plots.plot_error_distribution(errs, out / f"errors_{_slug(ref)}.png", ref)
            lines += [f"![camera errors vs {ref}]({p.name})", ""]
        e = data.edge_errors.get(ref)
        if e:
            p = plots.plot_edge_errors(e, out / f"edge_errors_{_slug(ref)}.png", ref)
            if p is not None:
                lines += [f"![edge errors vs {ref}]({p.name})", ""]
    p = plots.plot_convergence(data.histories, out / "convergence.png")
    if p is not None:
        lines += ["## Convergence", "", f"![convergence]({p.name})", ""]
    if data.vg_edges is not None and len(data.vg_names):
        for label, vals in (data.edge_values or {"edge": None}).items():
            p = plots.plot_viewgraph(len(data.vg_names), np.asarray(data.vg_edges, int), vals,
                                     out / f"viewgraph_{_slug(label)}.png", label, data.positions, data.vg_names)
            lines += [f"## View graph ({label})", "", f"![view graph]({p.name})", ""]
    for title, body in data.sections.items():
        lines += [f"## {title}", "", *body]
    if data.notes:
        lines += ["## Notes", "", *[f"- {n}" for n in data.notes], ""]
    path = out / "report.md"
    with atomic_open(path) as f:
        f.write("\n".join(lines))
    logger.info("report: %s", path)
    return path


def intrinsics_lines(intr: dict[str, Any]) -> list[str]:
    """The report's "Intrinsics" section: the focal used, where it came from, and the distortion."""
    if not intr or not intr.get("focal"):
        return []
    lines = ["## Intrinsics", "", "| focal (px) | images | source |", "|---|---|---|"]
    for f in intr["focal"]:
        rng = "" if f["min_px"] == f["max_px"] else f" ({f['min_px']:.1f}–{f['max_px']:.1f})"
        lines.append(f"| {f['median_px']:.1f}{rng} | {f['n_images']} | {f['source']} |")
    lines.append("")
    for d in intr.get("distortion", []):
        if d["source"] != "none":
            lines.append(f"- distortion of {d['n_images']} image(s): {', '.join(d['models'])} "
                         f"{[list(p) for p in d['extra_params']]} ({d['source']})")
    said: dict[tuple[str, str], list[int]] = {}  # one line per statement, with how many cameras (groups) it is of
    for g in intr.get("estimates", []):
        for key in ("focal", "radial"):
            text = _estimate_text(key, g.get(key) or {})
            if text:
                said.setdefault((key, text), []).append(int(g.get("n_images", 0)))
    for (key, text), sizes in said.items():
        lines.append(f"- {key} of {len(sizes)} camera{'s' if len(sizes) > 1 else ''} ({sum(sizes)} images): {text}")
    for f in intr["focal"]:  # how well determined: the view-graph calibration gives no uncertainty
        if f["source"] == "estimated:view-graph":
            lines.append(f"- focal of {f['n_images']} images from the view-graph calibration: no uncertainty is "
                         "estimated for it")
    return lines + ([""] if lines[-1] else [])


def _estimate_text(key: str, e: dict[str, Any]) -> str:
    """What the cameras stage's estimate of ``key`` (focal or radial) of one camera says: its value, how many pairs
    and how well determined (the jackknife sd); "not estimated" when it made none."""
    note = e.get("note") or ""
    if key == "focal" and e:
        if not _finite(e.get("f")) and e.get("group_note"):  # another estimate replaced this one (its note says)
            return f"{note} (each camera's own estimate: {e['group_note']})"
        if not _finite(e.get("f")):
            return f"not estimated: {note}" if note else "not estimated"
        sd = f", jackknife sd {100 * e['sd_rel']:.1f}%" if _finite(e.get("sd_rel")) else ""
        return f"{e['f']:.1f} px from {e.get('n_pairs')} pairs{sd}" + (f": {note}" if note else "")
    if not note:
        return ""
    return f"not estimated: {note}" if e.get("n_pairs") == 0 else note
