"""Comparisons: every method against every reference, like for like, and the ``evaluate`` command.

References are :class:`pipeline.reference.Reference` objects; image names are
matched by :func:`pipeline.core.names.match_names` (exact, then stem; an
ambiguous stem is an error). pycolmap's errors are over the images it registers
and ours over every image of the view graph, so when pycolmap leaves some out,
the truth restricted to its images (:func:`truth_on_registered`) is the
like-for-like reference.

Command line::

    python -m pipeline.evaluate --rotations EST.txt --reference REF [--align l2|l1|none] [--json OUT]
    python -m pipeline.evaluate --viewgraph VG.npz --reference REF [--json OUT]

REF is anything :func:`pipeline.reference.truth.read_reference` reads. With both
``--rotations`` and ``--viewgraph`` the summary also has the Mahalanobis error
(when the view graph has H) and the edge statistics.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.config import Config, option
from pipeline.core.names import match_names, positions
from pipeline.core.viewgraph import ViewGraph
from pipeline.evaluation import metrics as mt
from pipeline.reference.types import Reference

logger = logging.getLogger(__name__)

__all__ = ["SUBSET_PREFIX", "EvaluationConfig", "match_reference", "summarize_against", "truth_on_registered",
           "subset_prefix", "subset_label", "peer_metrics", "evaluate_all", "evaluate_files", "too_few_in_common",
           "main_cli"]

CERTIFICATE_KEYS = ("certified", "rank", "gap", "gap_residual", "lower_bound", "primal_cost", "cost_offset", "status",
                    "solver", "fallback")


@dataclass(frozen=True, kw_only=True)
class EvaluationConfig(Config):
    """Options of the evaluation (YAML section ``evaluation``)."""

    SECTION = "evaluation"

    align: Literal["l2", "l1", "none"] = option("l2", "global alignment: l2 (Karcher mean), l1 (geodesic median) "
                                                      "or none")


def match_reference(names: list[str], ref_names: list[str], R_ref: np.ndarray, what: str = "the reference"
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Reference rotation for each camera name, matched by :func:`pipeline.core.names.match_names`.

    Args:
        names: N camera names of the estimate.
        ref_names: K reference names.
        R_ref: (K, 3, 3) reference rotations.
        what: how to call the reference in messages.

    Returns:
        (N, 3, 3) reference rotations (identity where missing) and (N,) bool mask.
    Raises:
        InputFileError: a name matches several reference names by its stem.
    """
    R_ref = np.asarray(R_ref, dtype=np.float64)
    if R_ref.shape != (len(ref_names), 3, 3):
        raise ValueError(f"R_ref.shape={R_ref.shape} but expected ({len(ref_names)}, 3, 3)")
    idx = match_names(list(names), list(ref_names), what=what)
    mask = idx >= 0
    out = np.broadcast_to(np.eye(3), (len(names), 3, 3)).copy()
    out[mask] = R_ref[idx[mask]]
    return out, mask


def _rows(names: list[str], ref: Reference) -> tuple[np.ndarray, np.ndarray]:
    return match_reference(names, ref.names, ref.R, what=f"the reference '{ref.label or ref.source}'")


def too_few_in_common(n: int) -> str:
    """Why no error is given where ``n`` (< 2) cameras are in common with a reference."""
    return ("no camera in common with the reference" if n == 0 else "only one camera in common with the reference: "
            "the global alignment makes its error 0 by construction")


def summarize_against(names: list[str], R: np.ndarray, ref: Reference, align: str, vg: ViewGraph | None = None
                      ) -> tuple[dict[str, Any], np.ndarray]:
    """The :func:`pipeline.evaluation.metrics.summarize` of (N, 3, 3) ``R`` against ``ref`` and the (N,) errors (deg).

    The Mahalanobis error is added when ``vg`` has H and the same cameras in the
    same order; cameras the reference lacks are listed under ``not_in_reference``.
    """
    R_ref, mask = _rows(names, ref)
    if mask.sum() < 2:  # one camera's error is 0 after the alignment, by construction: no figure to give
        return {"n_cameras": len(names), "n_evaluated": int(mask.sum()), "note": too_few_in_common(int(mask.sum()))}, \
            np.full(len(names), np.nan)
    use_vg = vg if (vg is not None and vg.H is not None and list(vg.names) == list(names)) else None
    s = mt.summarize(R, R_ref, mask, align=align, vg=use_vg)
    errs = mt.rotation_errors_deg(R, R_ref, mask, align=align)
    missing = [n for n, m in zip(names, mask) if not m]
    if missing:
        s["not_in_reference"] = missing
    return s, errs


def subset_prefix(peer: str) -> str:
    """How the labels of the truth restricted to the images of the peer labelled ``peer`` begin."""
    return f"truth, {peer}'s "


SUBSET_PREFIX = subset_prefix("pycolmap").rstrip()  # the truth on the incremental peer's images


def subset_label(peer: str, n: int) -> str:
    """The label of the truth restricted to the ``n`` images the peer labelled ``peer`` registered."""
    return f"{subset_prefix(peer)}{n} images"


def truth_on_registered(truth: Reference | None, pyc: Reference, vg: ViewGraph) -> Reference | None:
    """The truth restricted to the images a pycolmap peer registered, when it left out some of ours.

    A peer's errors are over the images it registers; ours over every image of the
    view graph. Scoring our methods on the peer's images too (aligned on them) is the
    like-for-like comparison; None when the peer registered all of ours or there is no truth.
    Labelled :func:`subset_label` of the peer's label.
    """
    if truth is None:
        return None
    _, in_pyc = _rows(list(vg.names), pyc)
    if in_pyc.all():
        return None
    R_t, mask = _rows(list(pyc.names), truth)
    if mask.sum() < 2:
        return None
    names = [n for n, m in zip(pyc.names, mask) if m]
    return Reference(names, np.asarray(R_t)[mask], source=truth.source, label=subset_label(pyc.label or "pycolmap",
                                                                                           len(names)))


def peer_metrics(peers: list[Reference], truth: Reference | None, align: str,
                 cam_errors: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    """Each pycolmap peer against the truth (top level) and against every other peer (``references``).

    Each pair of peers is scored on the images both register (the summary's mask).
    The per-camera errors against the truth go to ``cam_errors["truth"][peer label]``.
    """
    out: dict[str, dict[str, Any]] = {}
    for p in peers:
        m = {"time_s": p.info.get("time_s"), "n_images": p.info.get("n_images"), "mapping": p.info.get("mapping"),
             "n_registered": p.info.get("n_registered"), "unregistered": p.info.get("unregistered", {}),
             "n_models": p.info.get("n_models"), "times": p.info.get("times"), "references": {}}
        if truth is not None and len(p.names):
            s, e = summarize_against(p.names, p.R, truth, align)
            m.update(s)
            cam_errors.setdefault("truth", {})[p.label] = e
        for q in peers:
            if q is not p and len(p.names) and len(q.names):
                m["references"][q.label] = summarize_against(p.names, p.R, q, align)[0]
        out[p.label] = m
    return out


def evaluate_all(vg: ViewGraph, ransac_vg: ViewGraph | None, results: dict[str, dict], refs: list[Reference],
                 pyc: Reference | list[Reference] | None, align: str) -> tuple[dict, dict, dict]:
    """Every method against every reference; the view graph's edges; the pycolmap peers against the truth.

    Args:
        vg: the view graph the methods averaged (after two-view BA).
        ransac_vg: the view graph before BA (RANSAC rotations), or None.
        results: ``{label: {"rotations": path, "stats": dict}}`` of every method.
        refs: the references, the first one the main one (its figures are copied to
            the top level of each method's entry).
        pyc: the pycolmap peers (the incremental reference, GLOMAP), one or a list, or None.
        align: "l2", "l1" or "none".

    Returns:
        ``{"methods", "edges", "pycolmap", "peers"}`` metrics (``pycolmap``: the first
        peer; ``peers``: every peer by label, see :func:`peer_metrics`),
        ``{reference: {label: (N,) errors}}`` and ``{reference: {"ransac" | "ba": (M,)
        edge errors}}``, in degrees.
    """
    from pipeline.io.rotations import read_rotations  # noqa: PLC0415

    methods: dict[str, Any] = {}
    cam_errors: dict[str, dict[str, np.ndarray]] = {r.label: {} for r in refs}
    for label, res in results.items():
        names, R = read_rotations(res["rotations"])
        entry: dict[str, Any] = {k: v for k, v in res["stats"].items() if k not in ("history",)}
        if "certified" in entry:
            entry["certificate"] = ({k: entry.get(k) for k in CERTIFICATE_KEYS if k in entry}
                                    | (entry.get("certificate") or {}))
        entry["references"] = {}
        for r in refs:
            s, e = summarize_against(list(names), np.asarray(R), r, align, vg)
            entry["references"][r.label] = s
            cam_errors[r.label][label] = e
        if refs:
            entry.update({k: v for k, v in entry["references"][refs[0].label].items()})
            entry["reference"] = refs[0].label
        methods[label] = entry
    edges: dict[str, Any] = {}
    edge_err: dict[str, dict[str, np.ndarray]] = {}
    for r in refs:
        edge_err[r.label] = {}
        for tag, g in (("ransac", ransac_vg), ("ba", vg)):
            if g is None:
                continue
            R_ref, mask = _rows(list(g.names), r)
            if r is refs[0]:
                edges[tag] = {**mt.edge_stats(g, R_ref, mask), "reference": r.label}
            edge_err[r.label][tag] = mt.edge_errors_deg(g, R_ref, mask)
    peers = [] if pyc is None else [pyc] if isinstance(pyc, Reference) else list(pyc)
    truth = next((r for r in refs if r.label == "truth"), None)
    by_peer = peer_metrics(peers, truth, align, cam_errors)
    first = {k: v for k, v in by_peer[peers[0].label].items() if k not in ("mapping", "times", "references")} \
        if peers else {}
    return {"methods": methods, "edges": edges, "pycolmap": first, "peers": by_peer}, cam_errors, edge_err


def _reindexed(vg: ViewGraph, names: list[str]) -> ViewGraph | None:
    """``vg`` with its cameras in the order of ``names``; edges to cameras not in ``names`` are left out."""
    idx = positions(names, vg.names, missing=-1)
    ok = (idx[vg.edges] >= 0).all(axis=1)
    if not np.any(ok):
        return None
    return ViewGraph.from_edges(names, idx[vg.edges[ok]], vg.R_rel[ok], H=vg.H[ok], allow_isolated=True)


def evaluate_files(reference: str | os.PathLike, rotations: str | os.PathLike | None = None,
                   viewgraph: str | os.PathLike | None = None, config: EvaluationConfig | None = None,
                   json_path: str | os.PathLike | None = None, print_table: bool = True) -> dict[str, Any]:
    """Evaluate a rotations file and/or a view graph file against a reference.

    Args:
        reference: anything :func:`pipeline.reference.truth.read_reference` reads.
        rotations: a rotations file (``pipeline.io.rotations``).
        viewgraph: a view graph (``.npz`` from ``ViewGraph.save`` or a ``.mat``).
        config: options (the alignment).
        json_path: where to write the result as JSON (atomically).
        print_table: print the tables to stdout.

    Returns:
        With ``rotations``: the :func:`pipeline.evaluation.metrics.summarize` dict plus
        ``n_reference`` and, with ``viewgraph``, ``edges`` (the edge statistics). With
        only ``viewgraph``: the edge statistics.
    """
    from pipeline.evaluation.report import console_table, edge_rows, summary_rows  # noqa: PLC0415
    from pipeline.io.mat import read_input_graph  # noqa: PLC0415
    from pipeline.io.rotations import read_rotations  # noqa: PLC0415
    from pipeline.reference.truth import read_reference  # noqa: PLC0415

    align = (config or EvaluationConfig()).align
    if rotations is None and viewgraph is None:
        raise ValueError("nothing to evaluate: give --rotations FILE and/or --viewgraph FILE")
    ref = read_reference(reference)
    vg = read_input_graph(viewgraph).vg if viewgraph is not None else None
    out: dict[str, Any]
    edge_summary = None
    if vg is not None:
        R_vg, m_vg = match_reference(vg.names, ref.names, ref.R, what=str(reference))
        if not np.any(m_vg):
            raise ValueError(f"no camera of {viewgraph} matches a name in {reference} (e.g. {vg.names[:3]} vs {ref.names[:3]})")
        edge_summary = mt.edge_stats(vg, R_vg, m_vg)
        if not edge_summary["n_evaluated"]:
            raise ValueError(f"no edge of {viewgraph} has both its cameras in {reference} (which holds "
                             f"{int(m_vg.sum())} of its {len(vg.names)} cameras); give a reference of its cameras")
    if rotations is not None:
        names, R_est = read_rotations(rotations)
        R_ref, m = match_reference(names, ref.names, ref.R, what=str(reference))
        if not np.any(m):
            raise ValueError(f"no camera of {rotations} matches a name in {reference} (e.g. {names[:3]} vs {ref.names[:3]})")
        if m.sum() < 2:
            raise ValueError(f"only one camera of {rotations} ({names[int(np.flatnonzero(m)[0])]}) is in {reference}: "
                             "the global alignment makes one camera's error 0 by construction; give a reference "
                             "holding at least two of its cameras")
        vg_ordered = _reindexed(vg, names) if vg is not None and vg.H is not None else None
        out = mt.summarize(R_est, R_ref, m, align, vg=vg_ordered)
        out["n_reference"] = len(ref.names)
        if edge_summary is not None:
            out["edges"] = edge_summary
        if print_table:
            print(console_table(f"rotations {rotations} vs {reference} ({ref.source})", summary_rows(out)))
            if edge_summary is not None:
                print()
                print(console_table(f"view graph {viewgraph} edges vs {reference}", edge_rows(edge_summary)))
    else:
        out = dict(edge_summary or {})
        if print_table:
            print(console_table(f"view graph {viewgraph} edges vs {reference} ({ref.source})", edge_rows(out)))
    if json_path is not None:
        write_json(json_path, out)
        logger.info("wrote %s", json_path)
    return out


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    parser = argparse.ArgumentParser(
        prog="python -m pipeline.evaluate",
        description="Evaluate estimated rotations (and/or a view graph's edges) against reference cameras.",
    )
    parser.add_argument("--rotations", type=Path, help="rotations file to evaluate (name r11 ... r33)")
    parser.add_argument("--viewgraph", type=Path, help="view graph (.npz or .mat) whose edges to evaluate (paper 1, Table 2)")
    parser.add_argument(
        "--reference", type=Path, required=True,
        help="rotations file, .mat with Rgt, Strecha gt_dense_cameras/, Middlebury *_par.txt, cameras file, or COLMAP model folder",
    )
    parser.add_argument("--json", type=Path, dest="json_path", help="write the result as JSON here")
    parser.add_argument("--config", type=Path, default=None, help="YAML config; its 'evaluation' section is used")
    add_config_args(parser, EvaluationConfig)

    def body(a: argparse.Namespace) -> int:
        cfg = config_from_args(EvaluationConfig, a, a.config)
        evaluate_files(a.reference, a.rotations, a.viewgraph, cfg, a.json_path)
        return 0

    return run_cli(body, parser, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
