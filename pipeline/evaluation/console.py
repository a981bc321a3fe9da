"""The console's tables and lines of a run: the summary table, the focal line, ``name  value`` tables.

Split from :mod:`pipeline.evaluation.report` (which re-exports them); they say what report.md says, in short.
"""

from __future__ import annotations

import math
from typing import Any

from pipeline.evaluation.flags import certificate_cell

__all__ = ["summary_table", "console_table", "summary_rows", "edge_rows", "intrinsics_console", "peer_row",
           "PEER_ROWS"]

#: The report's row of each pycolmap peer (by its label in the metrics), beside our methods' rows.
PEER_ROWS = {"pycolmap": "pycolmap (incremental)", "glomap": "pycolmap (global, GLOMAP)"}


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def _peers(metrics: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The pycolmap peers' metrics by label (older metrics: the incremental one only)."""
    if metrics.get("peers"):
        return metrics["peers"]
    return {"pycolmap": metrics["pycolmap"]} if metrics.get("pycolmap") else {}


def peer_row(label: str, short: bool = False) -> str:
    """The row naming the pycolmap peer labelled ``label`` (the incremental one, GLOMAP) beside our methods' rows:
    report.md's (``pycolmap (global, GLOMAP)``), or the console table's ``short`` one (``pycolmap-glomap``)."""
    if short:
        return "pycolmap" if label == "pycolmap" else f"pycolmap-{label}"
    return PEER_ROWS.get(label, f"pycolmap ({label})")


def intrinsics_console(intr: dict[str, Any]) -> str:
    """One console line: the focal used (its median and, where the images' differ, their range) and its source."""
    parts = [f"{f['median_px']:.1f} px" + ("" if f["min_px"] == f["max_px"] else f" ({f['min_px']:.1f}–{f['max_px']:.1f})")
             + f" ({f['source']}, {f['n_images']} images)" for f in intr.get("focal", [])]
    est = [g["focal"] for g in intr.get("estimates", []) if g.get("focal")]
    weak = [e for e in est if e.get("determined") is False and _finite(e.get("f"))]
    # an sd that is not finite (leaving one image out leaves too few pairs) reads back from cameras.json as null
    sds = ", ".join(f"{100 * w['sd_rel']:.1f}%" if _finite(w.get("sd_rel")) else "–" for w in weak)
    parts += [f"POORLY DETERMINED for {len(weak)} camera group(s) (jackknife sd {sds})"] if weak else []
    none = sum(f["n_images"] for f in intr.get("focal", []) if f["source"] == "default")  # nothing replaced the guess
    parts += [f"NOT ESTIMATED for {none} image(s) (the default guess 1.2·max(w, h) kept)"] if none else []
    return "focal: " + "; ".join(parts) if parts else ""


def _f(v: Any, nd: int = 3) -> str:
    try:
        return f"{float(v):.{nd}f}"
    except (TypeError, ValueError):
        return "–"


def summary_table(metrics: dict[str, Any]) -> str:
    """The final console table of a run: one row per method and reference, and each pycolmap peer's own."""
    inp = metrics.get("input") or {}  # every image of the folder: those the features stage skipped too
    n = inp["n_images"] + (inp.get("n_skipped") or 0) if inp.get("n_images") else None
    rows = [("method", "reference", f"cams/{n}" if n else "cams", "median°", "mean°", "max°", "time s", "note")]
    for label, m in metrics["methods"].items():
        note = certificate_cell(m, short=True)  # † : optimal for its cost, not a check of the pairs (under the table)
        if m.get("method") == "refine":
            note = f"refine {m['status']}"
        for rname, s in m.get("references", {}).items():
            rows.append((label, rname, f"{s.get('n_evaluated', 0)}", _f(s.get("median_deg")), _f(s.get("mean_deg")),
                         _f(s.get("max_deg")), _f(m.get("time_s"), 2), note))
        if not m.get("references"):
            rows.append((label, "–", str(m.get("n_cameras", "")), "–", "–", "–", _f(m.get("time_s"), 2), note))
    for label, p in _peers(metrics).items():
        if "median_deg" in p:
            rows.append((peer_row(label, short=True), "truth", f"{p.get('n_evaluated', 0)}", _f(p.get("median_deg")),
                         _f(p.get("mean_deg")), _f(p.get("max_deg")), _f(p.get("time_s"), 2),
                         f"{p.get('n_registered')}/{p.get('n_images')} reg."))
    w = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w[k]) for k, c in enumerate(r)) for r in rows]
    lines.insert(1, "  ".join("-" * x for x in w))
    return "\n".join(lines)


def console_table(title: str, rows: list[tuple[str, Any]]) -> str:
    """A two-column ``name  value`` table under ``title`` (floats with 4 significant digits)."""
    width = max(len(k) for k, _ in rows)
    lines = [title, "-" * max(len(title), width + 14)]
    for k, v in rows:
        if isinstance(v, float):
            v = f"{v:.4g}"
        lines.append(f"{k:<{width}}  {v}")
    return "\n".join(lines)


def summary_rows(s: dict[str, Any]) -> list[tuple[str, Any]]:
    """Rows of a :func:`pipeline.evaluation.metrics.summarize` dict for :func:`console_table`."""
    rows: list[tuple[str, Any]] = [
        ("cameras", s["n_cameras"]),
        ("evaluated", s["n_evaluated"]),
        ("alignment", s["align"]),
        ("median error (deg)", s["median_deg"]),
        ("mean error (deg)", s["mean_deg"]),
        ("RMS error (deg)", s["rms_deg"]),
        ("max error (deg)", s["max_deg"]),
        ("sqrt(sum ||R-R*||_F^2)", s["frobenius"]),
    ]
    rows += [(f"% under {t} deg", v) for t, v in s["pct_below"].items()]
    if "mahalanobis" in s:
        rows.append(("Mahalanobis (C.13)", s["mahalanobis"]))
    return rows


def edge_rows(s: dict[str, Any]) -> list[tuple[str, Any]]:
    """Rows of a :func:`pipeline.evaluation.metrics.edge_stats` dict for :func:`console_table`."""
    rows: list[tuple[str, Any]] = [
        ("edges", s["n_edges"]),
        ("evaluated", s["n_evaluated"]),
        ("mean error (deg)", s["mean_deg"]),
        ("median error (deg)", s["median_deg"]),
        ("RMS error (deg)", s["rms_deg"]),
    ]
    rows += [(f"% above {t} deg", v) for t, v in s["pct_above"].items()]
    return rows
