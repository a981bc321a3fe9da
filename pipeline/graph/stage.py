"""The view-graph stage: the largest connected component of the two-view BA graph, in OUT.

Reads the two-view BA's view graph (with H) from WORK, keeps its largest
connected component and names every image left out with why. Writes
``OUT/viewgraph.npz`` (the graph every averaging method reads) and
``OUT/viewgraph.json`` (the images left out and why, counts).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.core.atomic import write_json
from pipeline.core.config import Config
from pipeline.core.errors import CacheError, PipelineError
from pipeline.core.readers import name_list, read_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.geometry.ba_stage import load_ba_viewgraph
from pipeline.geometry.two_view_stage import load_two_view
from pipeline.graph.components import left_out_reasons
from pipeline.stage import Stage, StageRecord

logger = logging.getLogger(__name__)

__all__ = ["ViewGraphConfig", "ViewGraphStage", "load_graph_summary", "GRAPH", "SUMMARY"]

GRAPH = "viewgraph.npz"
SUMMARY = "viewgraph.json"


@dataclass(frozen=True, kw_only=True)
class ViewGraphConfig(Config):
    """Options of the view-graph stage (YAML section ``viewgraph``)."""

    SECTION = "viewgraph"


class ViewGraphStage(Stage[ViewGraphConfig]):
    """The largest connected component of WORK's BA view graph, written to OUT (folder = OUT)."""

    name = "viewgraph"
    title = "view graph"
    config_cls = ViewGraphConfig

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
        sub, info = vg_all.largest_component()
        left_out: dict[str, str] = {}
        if info.dropped_names:
            left_out = left_out_reasons(vg_all, list(load_two_view(self.work).rejected))
            logger.warning("the view graph is not connected: using the largest component (%d of %d images); "
                           "left out: %s", sub.n_cameras, vg_all.n_cameras,
                           "; ".join(f"{n}: {w}" for n, w in left_out.items()))
        path = sub.save(self.folder / GRAPH)
        summary = {"n_images": vg_all.n_cameras, "n_cameras": sub.n_cameras, "n_edges": sub.n_edges,
                   "names": list(sub.names), "left_out": left_out}
        return [path, write_json(self.folder / SUMMARY, summary)], {k: summary[k] for k in
                                                                    ("n_images", "n_cameras", "n_edges")}

    def verify(self, record: StageRecord) -> None:
        s = load_graph_summary(self.folder)
        vg = ViewGraph.load(self.folder / GRAPH)
        if list(vg.names) != list(s["names"]) or vg.n_edges != s["n_edges"]:
            raise CacheError(f"{self.folder / GRAPH} does not hold the {s['n_cameras']} cameras its summary lists")

    def load(self) -> ViewGraph:
        return ViewGraph.load(self.folder / GRAPH)


def load_graph_summary(out: Path) -> dict[str, Any]:
    """The summary written beside the view graph (names, counts, images left out and why)."""
    path = Path(out) / SUMMARY
    s = read_json(path, "the view-graph summary", CacheError)
    try:
        n = len(name_list(s["names"], "names"))
        left_out = s["left_out"]
        if not (isinstance(left_out, dict) and all(isinstance(v, str) for v in left_out.values())):
            raise ValueError("left_out is not a mapping of names to reasons")
        if s["n_cameras"] != n or not (isinstance(s["n_edges"], int) and s["n_edges"] >= 0):
            raise ValueError("its counts disagree with its names")
        return s
    except (ValueError, TypeError, KeyError) as exc:
        raise CacheError(f"{path} is missing or damaged ({' '.join(str(exc).split())[:80]})") from None
