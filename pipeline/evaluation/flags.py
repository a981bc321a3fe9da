"""What vouches for each camera of a run: the view graph's flags, each method's support, and what a certificate is.

:func:`run_evidence` joins the view-graph stage's flags and messages
(:mod:`pipeline.graph.stage`) with each method's per-camera support
(:mod:`pipeline.averaging.evidence`: "single edge", "rejected edges only", "minority") into
``metrics.json``'s ``evidence``; :func:`evidence_markdown` and :func:`evidence_console`
word it for the report and the console. A certificate is never shown alone: every
place that shows one also says what it proves (optimality of a cost on the edges the
method used) and what it does not (that those pairs are right).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.core.names import positions

__all__ = ["CERTIFICATE_NOTE", "DISAGREEMENT_DEG", "GUESSED_FOCAL", "method_disagreement", "run_evidence",
           "evidence_markdown", "evidence_console", "certificate_cell", "certificate_statements"]

#: Methods that disagree by more than this on a camera (degrees) flag it: at least one of them is wrong there by
#: half as much or more, so the camera's rotation is not known to this accuracy. It is the accuracy an unflagged
#: camera claims (issue 13, item 4: no reported camera more than 1° off). On a low-texture turntable the
#: isotropic methods (IRLS-ℓ½, colmap-ra) are 1.0–2.2° off exactly where they disagree with IRLS-H by 1.0–2.3°;
#: on fountain and castle no camera's methods disagree by more than 0.7°.
DISAGREEMENT_DEG = 1.0

CERTIFICATE_NOTE = ("a certificate proves that a method's rotations are optimal for its cost on the pairs it used; "
                    "it does not check that those pairs are right")
_SUPPORT = {"single edge": "rests on one pair the method kept, the others down-weighted or rejected",
            "rejected edges only": "the method rejected or down-weighted every pair of it",
            "minority": "the method kept fewer than a quarter of its pairs: most of them disagree with its rotation"}


def method_disagreement(rotations: dict[str, tuple[list[str], np.ndarray]]) -> dict[str, tuple[float, str]]:
    """Per camera, the largest angle between two methods' rotations, and which two (no truth involved).

    Each pair of methods is aligned on the cameras they share by the geodesic median (robust to a few
    cameras one method got wrong), then compared camera by camera.

    Args:
        rotations: ``{label: (names, (n, 3, 3) cam_from_world)}``.
    Returns:
        ``{name: (degrees, "a vs b")}`` for every camera two methods solved.
    """
    from pipeline.evaluation.metrics import rotation_errors_deg  # noqa: PLC0415

    out: dict[str, tuple[float, str]] = {}
    labels = list(rotations)
    for a in range(len(labels)):
        for b in range(a + 1, len(labels)):
            na, Ra = rotations[labels[a]]
            in_b = positions(rotations[labels[b]][0], na, missing=-1)
            common = np.flatnonzero(in_b >= 0)
            if len(common) < 2:
                continue
            Rb = np.asarray(rotations[labels[b]][1])[in_b[common]]
            d = rotation_errors_deg(np.asarray(Ra)[common], Rb, align="l1")
            for k, x in zip(common, d):
                if x > out.get(na[k], (-1.0, ""))[0]:
                    out[na[k]] = (float(x), f"{labels[a]} vs {labels[b]}")
    return out


#: The flag of an image whose focal length is only the default guess (no K file, no EXIF, no estimate).
GUESSED_FOCAL = ("its focal length is only the default guess 1.2·max(w, h) (no K file, no EXIF, and the view graph "
                 "did not determine it): the averaged rotations rest on it, and a focal 10% off bends them by degrees "
                 "(the refinement estimates its own)")


def run_evidence(graph: dict[str, Any], methods: dict[str, dict[str, Any]],
                 disagreement: dict[str, tuple[float, str]] | None = None,
                 guessed_focal: list[str] | None = None, placed: dict[str, str] | None = None) -> dict[str, Any]:
    """The ``evidence`` entry of metrics.json.

    Args:
        graph: the view-graph stage's summary (``flags``, ``messages``, ``left_out``, ``names``, ``pairs``, ...).
        methods: metrics.json's ``methods`` (each with the ``evidence`` the averaging stage wrote).
        disagreement: :func:`method_disagreement` of the methods' rotations; cameras beyond
            :data:`DISAGREEMENT_DEG` are flagged.
        guessed_focal: the images whose focal length is the default guess (:data:`GUESSED_FOCAL`); flagged.
        placed: ``{name: why}`` of images the view graph left out that a refinement placed (``placed`` in its
            stats): flagged with why, after the graph's reason for leaving them out.
    Returns:
        ``{"messages", "flags": {name: [reasons]}, "cameras": {name: {"status", "flags"}}, "n_flagged",
        "n_cycles", "left_out", "pairs": counts by status and step, "n_confirmed_cameras" (cameras with a kept pair
        a consistent cycle confirms), "n_cameras", "certificate_note"}``.
    """
    flags: dict[str, list[str]] = {n: list(v) for n, v in (graph.get("flags") or {}).items()}
    support: dict[tuple[str, str], list[str]] = {}
    for label, m in methods.items():
        for cam in (m.get("evidence") or {}).get("cameras", []):
            if cam.get("support", "") in _SUPPORT:
                support.setdefault((cam["name"], cam["support"]), []).append(label)
    for (name, kind), labels in support.items():
        if kind == "single edge" and any(w.startswith("rests on a single pair") for w in flags.get(name, [])):
            continue  # the graph has one pair there: every method rests on it
        flags.setdefault(name, []).append(f"{_SUPPORT[kind]} ({', '.join(labels)})")
    for n, (deg, which) in (disagreement or {}).items():
        if deg > DISAGREEMENT_DEG:
            flags.setdefault(n, []).append(f"the methods disagree by {deg:.1f}° on it ({which}): at least one is "
                                           "wrong there")
    in_graph = set(graph.get("names", []))
    for n in guessed_focal or []:
        if n in in_graph:
            flags.setdefault(n, []).append(GUESSED_FOCAL)
    cameras: dict[str, dict[str, Any]] = {}
    for n in graph.get("names", []):
        cameras[n] = {"status": "flagged" if n in flags else "checked", "flags": flags.get(n, [])}
        if disagreement and n in disagreement:
            cameras[n]["methods_disagree_deg"] = round(disagreement[n][0], 4)
    for n, why in (graph.get("left_out") or {}).items():
        cameras[n] = {"status": "left out", "flags": [why]}
    for n, why in (placed or {}).items():
        flags[n] = [*cameras.get(n, {}).get("flags", []), why]
        cameras[n] = {"status": "flagged", "flags": flags[n]}
    counts: dict[str, int] = {}
    for p in graph.get("pairs", []):
        key = p.get("status", "?") if p.get("status") == "kept" else f"rejected at {p.get('step', '?')}"
        counts[key] = counts.get(key, 0) + 1
    confirmed = {n for p in graph.get("pairs", []) if p.get("status") == "kept" and p.get("confirmed")
                 for n in p.get("pair", [])} & set(graph.get("names", []))
    certified = [k for k, m in methods.items() if certificate_cell(m)]
    return {"messages": list(graph.get("messages", [])), "flags": {n: flags[n] for n in sorted(flags)},
            "cameras": cameras, "n_flagged": len(flags), "n_cycles": graph.get("n_cycles"),
            "left_out": dict(graph.get("left_out") or {}), "pairs": counts,
            "n_confirmed_cameras": len(confirmed), "n_cameras": len(graph.get("names", [])),
            "certificate_note": CERTIFICATE_NOTE if certified else ""}


#: A flag reason shared by this many cameras or more is said once, with their names (two cameras' alike reasons,
#: such as "1 of its 5 pairs disagree", stay in each camera's row).
SHARED_BY = 3


def _lines(ev: dict[str, Any], limit: int | None) -> tuple[list[str], list[tuple[str, str]]]:
    """The messages, and ``(cameras, why)`` items: a reason shared by :data:`SHARED_BY` cameras or more once, with
    their names and count, then each camera's other reasons."""
    msgs = list(ev.get("messages", []))
    if ev.get("n_flagged"):
        msgs.append(f"{ev['n_flagged']} camera(s) flagged: unconfirmed or disputed evidence (below)")
    flags = ev.get("flags", {})
    who: dict[str, list[str]] = {}
    for n, ws in flags.items():
        for w in ws:
            who.setdefault(w, []).append(n)
    shared = {w: ns for w, ns in who.items() if len(ns) >= SHARED_BY}
    items = [(f"{', '.join(ns)} ({len(ns)})", w) for w, ns in shared.items()]
    items += [(n, "; ".join(own)) for n, ws in flags.items() if (own := [w for w in ws if w not in shared])]
    if limit is not None and len(items) > limit:
        items = items[:limit] + [("...", f"and {len(items) - limit} more (metrics.json: evidence.flags)")]
    return msgs, items


def evidence_markdown(ev: dict[str, Any]) -> list[str]:
    """The report's "Evidence" section (markdown lines); empty when there is nothing to say."""
    if not ev:
        return []
    msgs, items = _lines(ev, None)
    out = ["## Evidence behind the rotations", ""]
    out += [f"**{m}.**" for m in msgs] + ([""] if msgs else [])
    pairs = ev.get("pairs") or {}
    if pairs:
        out += ["Pairs: " + ", ".join(f"{v} {k}" for k, v in sorted(pairs.items())) + " (viewgraph.json lists each "
                "with its reason).", ""]
    if items:
        out += ["| camera | why it is flagged |", "|---|---|"]
        out += [f"| {n} | {w} |" for n, w in items]
        out.append("")
    elif not msgs and ev.get("n_confirmed_cameras", ev.get("n_cameras")) == ev.get("n_cameras"):
        out += ["Every camera's rotation is checked by a cycle of consistent pairs.", ""]
    elif not msgs:
        out += [f"No camera is flagged, but {ev.get('n_confirmed_cameras')} of {ev.get('n_cameras')} cameras have a "
                "pair that a consistent cycle confirms.", ""]
    if ev.get("certificate_note"):
        out += [f"† {ev['certificate_note'][0].upper()}{ev['certificate_note'][1:]}; the flags above are what "
                "vouches, or fails to vouch, for the input.", ""]
    return out


def evidence_console(ev: dict[str, Any], limit: int = 10) -> str:
    """A few console lines: graph messages, flagged cameras with the reason, the certificate's meaning."""
    if not ev:
        return ""
    msgs, items = _lines(ev, limit)
    out = [f"WARNING: {m}" for m in msgs] + [f"  flagged {n}: {w}" for n, w in items]
    if ev.get("certificate_note"):
        out.append(f"† {ev['certificate_note']} (for which cost and edges: report.md, \"Certificates\")")
    return "\n".join(out)


def _edge_counts(m: dict[str, Any]) -> tuple[Any, Any]:
    """The edges a method's certificate is about: (how many it used, of how many)."""
    c = m.get("certificate") or {}
    used = c.get("n_weighted_edges", c.get("n_kept"))
    total = c.get("n_edges")
    if total is None and used is not None and c.get("n_rejected") is not None:
        total = used + c["n_rejected"]
    return used, total if total is not None else m.get("n_edges")


def certificate_cell(m: dict[str, Any], short: bool = False) -> str:
    """A method's certificate in a table cell: its verdict and the edges it is about (``short``: for the console);
    "" without one. Its cost is in its statement (:func:`certificate_statements`)."""
    c = m.get("certificate") or {}
    if "certified" in m:
        verdict = "certified" if m["certified"] else "NOT certified"
    elif c.get("verdict"):
        verdict = str(c["verdict"])
    else:
        return ""
    used, total = _edge_counts(m)
    if used is not None and total is not None:
        verdict += f" on {used}/{total} edges" if short else f" on {used} of {total} edges"
    if short:
        return verdict + " †"
    extra = []
    if "rank" in m or "rank" in c:
        extra.append(f"rank {m.get('rank', c.get('rank'))}")
    if isinstance(c.get("gap_vs_resolution"), (int, float)):  # what the verdict rests on (the relative gap is to
        extra.append(f"gap {c['gap_vs_resolution']:.2g}× the cost's resolution")  # a constant offset of the cost)
    return verdict + (f" ({', '.join(extra)})" if extra else "") + " †"


def certificate_statements(methods: dict[str, dict[str, Any]]) -> dict[str, str]:
    """``{method: statement}``: what each method's certificate proves, for which cost on which edges (the
    averaging stage's statement), for the methods that have one."""
    out = {}
    for label, m in methods.items():
        st = (m.get("certificate") or {}).get("statement") or (m.get("evidence") or {}).get("statement")
        if st and ("certificate" in m or "certified" in m):
            out[label] = str(st)
    return out
