"""The view-graph stage: the checked view graph that every averaging method reads, in OUT.

Reads the two-view BA's view graph (with H) from WORK, runs the checks of
:mod:`pipeline.graph.checks` (evidence tiers, co-location, short and long cycles, the
robust filter), keeps the largest connected component of the pairs that pass, and flags
the cameras whose rotation rests on evidence nothing checks (:mod:`pipeline.graph.flags`).
Each other component of at least ``min_component_images`` images (up to ``components`` in all, largest
first) goes to ``OUT/component-k/`` (its graph and a summary of the same format, its images' flags), where
``run.py`` solves it in a frame of its own, as COLMAP's mappers make a model of each component.
Writes

- ``OUT/viewgraph.npz``: the checked graph (stat ``confirmed``: the edge is in a consistent cycle);
- ``OUT/viewgraph.json``: counts; ``left_out`` (every image outside it, with why);
  ``pairs`` (every pair that was estimated or rejected: its status, the step that rejected
  it and why, its tier, and ``tracks``: whether its matches may make the refinement's tracks,
  :func:`track_pairs`; ``confirm_deg``: the angle of the tightest cycle, or the path's disagreement, that
  confirmed it, null if none); ``flags`` (``{camera: [reasons]}``); ``messages`` (graph-level,
  e.g. no cycle: the result cannot be verified; cycles that close wider than H claims,
  :func:`overconfidence_message`); the checks' figures.

With ``checks: false`` every pair of the BA graph is kept, as before this stage checked them.
Command line::

    python -m pipeline.viewgraph --work WORK --out OUT [--config YAML] [--min-inliers 15] ...
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.errors import CacheError, PipelineError
from pipeline.core.readers import name_list, read_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.geometry.ba_stage import load_ba_viewgraph
from pipeline.geometry.two_view_stage import load_two_view
from pipeline.graph.checks import GraphChecks, ViewGraphConfig, check_view_graph
from pipeline.graph.components import (COMPONENT_DIR, left_out_reasons, other_components, remove_stale_components,
                                       write_component)
from pipeline.graph.flags import graph_flags
from pipeline.graph.tiers import WEAK_H
from pipeline.stage import Stage, StageRecord

logger = logging.getLogger(__name__)

__all__ = ["ViewGraphConfig", "ViewGraphStage", "load_graph_summary", "track_pairs", "main_cli", "GRAPH", "SUMMARY"]

GRAPH = "viewgraph.npz"
SUMMARY = "viewgraph.json"


def _unchecked(vg: ViewGraph) -> GraphChecks:
    M = vg.n_edges
    return GraphChecks(np.ones(M, bool), np.full(M, "", object), np.full(M, "", object), np.full(M, "", object),
                       np.zeros(M, bool), np.zeros(M, bool), np.zeros(M, bool), {"checks": False})


def _pair_rows(vg: ViewGraph, chk: GraphChecks, two_view_rejected: list[dict], ba_dropped: list[dict]
               ) -> list[dict[str, Any]]:
    """One row per pair: two-view rejections, BA failures, then every pair of the BA graph."""
    rows = [{"pair": list(r.get("names", [])), "status": "rejected", "step": "two_view", "reason": r.get("reason", ""),
             "n_inliers": r.get("n_inliers")} for r in two_view_rejected]
    rows += [{"pair": list(d.get("pair", [])), "status": "rejected", "step": "two_view_ba", "reason": d.get("reason", "")}
             for d in ba_dropped]
    n_in = np.asarray(vg.stats.get("n_inliers_E", vg.inliers if vg.inliers is not None else np.zeros(vg.n_edges)))
    tracks = track_pairs(chk)
    for k, (a, b) in enumerate(vg.edges.tolist()):  # one JSON row per pair: I/O, not a hot path
        rows.append({"pair": [vg.names[a], vg.names[b]], "status": "kept" if chk.kept[k] else "rejected",
                     "step": str(chk.step[k]), "reason": str(chk.reason[k]), "tier": str(chk.tier[k]),
                     "confirmed": bool(chk.confirmed[k]), "confirm_deg": _finite(chk.confirm_deg, k),
                     "n_inliers": int(n_in[k]),
                     "bridged": bool(chk.bridged[k]), "tracks": bool(tracks[k])})
    return rows


def overconfidence_message(kappa2: float | None, cfg: ViewGraphConfig) -> list[str]:
    """The scene's warning when its pairs' short cycles close wider than their H claim by more than the checks assume
    (κ > ``h_inflation``): the cycle tests widen with κ, so their confirmation is looser there."""
    if kappa2 is None or not np.isfinite(kappa2) or np.sqrt(kappa2) <= cfg.h_inflation:
        return []
    return [f"the pairs' short cycles close {np.sqrt(kappa2):.1f}× wider than their two-view precisions (H) claim, "
            f"beyond the {cfg.h_inflation:g}× the checks assume: their cycle tests widened with it (to at most "
            f"{cfg.cycle_max_deg:g}°). Pairs that share a bias do this (focal lengths only guessed, a lens left "
            "unmodelled, surfaces whose look changes with the view: light that moves with the camera, highlights; "
            "repeated structure), and cycles of such pairs confirm little"]


def _finite(a: np.ndarray | None, k: int) -> float | None:
    """``a[k]`` rounded for JSON, None where undefined (no array, inf, NaN)."""
    return round(float(a[k]), 4) if a is not None and np.isfinite(a[k]) else None


def track_pairs(chk: GraphChecks) -> np.ndarray:
    """(M,) the pairs whose inlier matches may make the refinement's tracks: the kept ones, and those rejected only
    because their rotation is poorly determined (weak H). Such a pair passed the inlier gates: its matches are
    sound, only the rotation it alone gives is not, and the bundle adjustment does not read that rotation (the
    refinement's edge filter still compares it with the averaged rotations)."""
    return chk.kept | ((chk.step == "acceptance") & (chk.reason == WEAK_H))


class ViewGraphStage(Stage[ViewGraphConfig]):
    """The checked view graph of WORK's BA graph, its largest component, written to OUT (folder = OUT)."""

    name = "viewgraph"
    title = "view graph and its checks"
    config_cls = ViewGraphConfig
    # 4: pairs[].tracks; 5: the other components (OUT/component-k/); 6: loosely confirmed cameras; 7: bridges in
    # series; 8: a removed edge's cycles leave the counts once each (a walk through a pair measured twice); 9: a core
    # that more than half its component's cameras hang off through one bridge is flagged; 10: that bridge is named;
    # 11: not a tree's one-camera 'core'; 12: each of several equally large blocks (or parts joined by bridged pairs) is
    # flagged, whatever the labels, and the bridged pairs are judged per component
    version = 12

    def __init__(self, out: Path, config: ViewGraphConfig | None = None, *, work: Path) -> None:
        super().__init__(out, config)
        self.work = Path(work)

    def inputs(self) -> dict[str, str]:
        return {"two_view_ba": self.upstream("two_view_ba", self.work).fingerprint,
                "two_view": self.upstream("two_view", self.work).fingerprint}

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        vg_all = load_ba_viewgraph(self.work)
        if vg_all.n_edges == 0:
            raise PipelineError(f"no pair of the {vg_all.n_cameras} images has enough geometrically consistent "
                                "matches; the images must overlap (see the warnings above for each pair's reason)")
        chk = check_view_graph(vg_all, self.config) if self.config.checks else _unchecked(vg_all)
        if not chk.kept.any():
            steps = {s: int((chk.step == s).sum()) for s in set(chk.step.tolist())}
            raise PipelineError(f"the checks rejected all {vg_all.n_edges} pairs ({steps}); nothing can be averaged. "
                                f"See {self.folder / SUMMARY} for each pair's reason, or set viewgraph.checks: false")
        kept = ViewGraph(vg_all.names, vg_all.edges[chk.kept], vg_all.R_rel[chk.kept], H=vg_all.H[chk.kept],
                         inliers=None if vg_all.inliers is None else vg_all.inliers[chk.kept],
                         stats={**{k: v[chk.kept] for k, v in vg_all.stats.items()},
                                "confirmed": chk.confirmed[chk.kept]}, allow_isolated=True)
        sub, info = kept.largest_component()
        others = other_components(kept, self.config.components, self.config.min_component_images)
        two_view = load_two_view(self.work)
        ba_dropped = list(self.upstream("two_view_ba", self.work).summary.get("dropped", []))
        rejected = list(two_view.rejected) + [
            {"names": [vg_all.names[a], vg_all.names[b]], "reason": str(r)}
            for (a, b), r in zip(vg_all.edges[~chk.kept].tolist(), chk.reason[~chk.kept])]
        left_out = left_out_reasons(kept, rejected) if info.dropped_names else {}
        for k, cams in enumerate(others, start=2):  # solved in a folder of their own: said where
            for c in cams:
                left_out[kept.names[c]] = (f"solved as component {k} ({COMPONENT_DIR.format(k=k)}/, {cams.size} "
                                           f"images, in a frame of its own): no pair links it to the largest")
        solved = np.zeros(vg_all.n_cameras, bool)
        solved[np.concatenate([info.kept, *others])] = True
        fl = graph_flags(vg_all.edges, vg_all.n_cameras, chk.kept, chk.confirmed, chk.inconsistent, vg_all.names,
                         cameras=solved, cycles_checked=self.config.checks, bridged=chk.bridged,
                         confirm_deg=chk.confirm_deg, confirm_max_deg=self.config.confirm_max_deg)
        flags = {vg_all.names[k]: v for k, v in sorted(fl.cameras.items())}
        messages = list(fl.messages) + overconfidence_message(chk.info.get("kappa2"), self.config)
        self._log(vg_all, sub, chk, left_out, flags, messages)
        path = sub.save(self.folder / GRAPH)
        summary = {"n_images": vg_all.n_cameras, "n_cameras": sub.n_cameras, "n_edges": sub.n_edges,
                   "names": list(sub.names), "left_out": left_out, "flags": flags, "messages": messages,
                   "n_cycles": fl.n_cycles, "n_bridges": int(fl.bridge.sum()) if fl.bridge is not None else 0,
                   "checks": {k: v for k, v in chk.info.items()},
                   "pairs": _pair_rows(vg_all, chk, list(two_view.rejected), ba_dropped)}
        paths, components = [path], []
        remove_stale_components(self.folder, keep=len(others) + 1)
        for k, cams in enumerate(others, start=2):
            written, entry = write_component(self.folder, k, kept.subgraph(cams)[0], summary, GRAPH, SUMMARY)
            paths += written
            components.append(entry)
        main = set(sub.names)
        summary["flags"] = {n: w for n, w in flags.items() if n in main}
        summary["components"] = components
        counts = {k: summary[k] for k in ("n_images", "n_cameras", "n_edges", "n_cycles")}
        return [*paths, write_json(self.folder / SUMMARY, summary)], {**counts, "n_flagged": len(summary["flags"]),
                                                                      "n_components": 1 + len(components)}

    @staticmethod
    def _log(vg_all: ViewGraph, sub: ViewGraph, chk: GraphChecks, left_out: dict[str, str],
             flags: dict[str, list[str]], messages: list[str]) -> None:
        if chk.info.get("checks", True):
            steps = {s: int((chk.step == s).sum()) for s in ("acceptance", "colocation", "cycles", "path",
                                                            "unconfirmed", "robust")}
            logger.info("view graph checks: %d of %d pairs kept, %d confirmed by a cycle; rejected by step: %s",
                        int(chk.kept.sum()), vg_all.n_edges, int(chk.confirmed.sum()),
                        ", ".join(f"{k} {v}" for k, v in steps.items() if v) or "none")
            if chk.info.get("bridged"):
                logger.warning("view graph checks: %d pair(s) confirmed by no cycle kept only because they alone join "
                               "cameras to the rest (a pan on the spot, a low-parallax step); the cameras they join "
                               "are flagged", chk.info["bridged"])
        if left_out:
            logger.warning("the view graph is not connected: its largest component (%d of %d images) is solved here; "
                           "outside it: %s", sub.n_cameras, vg_all.n_cameras,
                           "; ".join(f"{n}: {w}" for n, w in left_out.items()))
        for m in messages:
            logger.warning("%s", m)
        if flags:
            logger.warning("%d camera(s) flagged (unconfirmed or disputed evidence): %s", len(flags),
                           "; ".join(f"{n}: {w[0]}" for n, w in list(flags.items())[:5])
                           + (" ..." if len(flags) > 5 else ""))

    def verify(self, record: StageRecord) -> None:
        s = load_graph_summary(self.folder)
        vg = ViewGraph.load(self.folder / GRAPH)
        if list(vg.names) != list(s["names"]) or vg.n_edges != s["n_edges"]:
            raise CacheError(f"{self.folder / GRAPH} does not hold the {s['n_cameras']} cameras its summary lists")
        for c in s.get("components", []):  # each other component's graph, as listed
            path = self.folder / str(c.get("folder", "")) / GRAPH
            try:
                ok = list(ViewGraph.load(path).names) == list(c["names"])
            except (PipelineError, OSError, KeyError, ValueError):
                ok = False
            if not ok:
                raise CacheError(f"{path} does not hold the component its summary lists")

    def load(self) -> ViewGraph:
        return ViewGraph.load(self.folder / GRAPH)


def load_graph_summary(out: Path) -> dict[str, Any]:
    """The summary written beside the view graph (names, counts, images left out and why, flags, pairs)."""
    path = Path(out) / SUMMARY
    s = read_json(path, "the view-graph summary", CacheError)
    try:
        n = len(name_list(s["names"], "names"))
        left_out = s["left_out"]
        if not (isinstance(left_out, dict) and all(isinstance(v, str) for v in left_out.values())):
            raise ValueError("left_out is not a mapping of names to reasons")
        if s["n_cameras"] != n or not (isinstance(s["n_edges"], int) and s["n_edges"] >= 0):
            raise ValueError("its counts disagree with its names")
        s.setdefault("flags", {})
        s.setdefault("messages", [])
        if not isinstance(s["flags"], dict) or not isinstance(s["messages"], list):
            raise ValueError("flags or messages of the wrong type")
        return s
    except (ValueError, TypeError, KeyError) as exc:
        raise CacheError(f"{path} is missing or damaged ({' '.join(str(exc).split())[:80]})") from None


def main_cli(argv: Sequence[str] | None = None) -> int:
    """``python -m pipeline.viewgraph --work WORK --out OUT``: check WORK's BA graph, write OUT/viewgraph.npz."""
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m pipeline.viewgraph",
                                description="Check the two-view BA's view graph of WORK (pair evidence, cycles, "
                                            "robust filter), keep its largest component, flag the cameras nothing "
                                            "checks; writes OUT/viewgraph.npz and OUT/viewgraph.json, and each other "
                                            "component of at least min_component_images images to "
                                            "OUT/component-k/.")
    p.add_argument("--work", type=Path, required=True, help="the WORK folder of the front end")
    p.add_argument("--out", type=Path, required=True, help="where viewgraph.npz and viewgraph.json go")
    p.add_argument("--config", type=Path, default=None, help="YAML config; its 'viewgraph' section is used")
    add_config_args(p, ViewGraphConfig)
    p.add_argument("--overwrite", action="store_true", help="recompute even if an intact, up-to-date result exists")

    def body(a: argparse.Namespace) -> int:
        ViewGraphStage(a.out, config_from_args(ViewGraphConfig, a, a.config), work=a.work).run(a.overwrite)
        print(Path(a.out) / GRAPH)
        return 0

    return run_cli(body, p, argv)
