"""The averaging stage: one method on one view graph, under the stage contract (:mod:`pipeline.stage`).

Each method run is a stage instance with its own record, so methods are cached
independently: in ``OUT/rotations/`` (``run.py``) the method labelled ``irls-l0.5``
writes

- ``irls-l0.5.txt``: the rotations (:mod:`pipeline.io.rotations`), one line per
  camera of the solved component (a disconnected graph's largest component; the
  others are named in the header and in the stats);
- ``irls-l0.5.json``: the stats (:meth:`AveragingResult.summary`, options, history,
  most down-weighted edges, errors against the ground truth of a ``.mat`` input);
- ``irls-l0.5.record.json``: the record (fingerprint of the method, its options and
  its inputs: the view graph's content or its upstream record, and an init file).

A cached result is reused only when its fingerprint matches and :meth:`verify`
finds its rotations file intact: readable, and holding exactly the cameras of the
view graph's solved component. A damaged result (cut to 2 of 6 cameras, garbled) is
recomputed with a one-line warning.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.averaging import solve
from pipeline.averaging.registry import MethodSpec
from pipeline.averaging.result import AveragingResult
from pipeline.core.atomic import write_json
from pipeline.core.config import Config
from pipeline.core.errors import CacheError, InputFileError
from pipeline.core.names import positions
from pipeline.core.readers import read_json
from pipeline.core.viewgraph import ViewGraph
from pipeline.averaging.evidence import camera_evidence
from pipeline.io.graphs import GraphData, input_files, read_input_graph
from pipeline.io.near_rotation import DEFAULT_ROTATION_TOL
from pipeline.io.rotations import read_rotations, rotations_for, write_rotations
from pipeline.stage import Stage, StageRecord, file_fingerprint, fingerprint_of

__all__ = ["AveragingStage", "run_averaging", "load_init"]

logger = logging.getLogger(__name__)


class AveragingStage(Stage[Config]):
    """One averaging method on one view graph.

    Args:
        folder: where the outputs and the record go (``OUT/rotations``).
        spec: the method and its options (:func:`pipeline.averaging.registry.parse_method`).
        viewgraph: the view graph: any input of :mod:`pipeline.io.graphs` (``.npz``, ``.mat``,
            a 1DSfM folder, ``.g2o``, GLOMAP relative poses).
        label: the outputs' base name (default ``spec.label``).
        rotations: the rotations file (default ``folder/<label>.txt``); the stats are
            written beside it with the suffix ``.json``.
        init: a rotations file to start from (methods that take a start).
        upstream: ``(stage name, folder, record name)`` of the stage that wrote
            ``viewgraph``: its record's fingerprint is this stage's input. Without it
            the input is the content of the file(s).
        rotation_tol: input rotations within this of SO(3) are projected (one warning).
    """

    name = "averaging"
    title = "rotation averaging"
    config_cls = Config
    # 2: a g2o file's coupled information gives the rotation's marginal H; Bundler truth needs f > 0;
    # 3: the SDP's start certificate asks for its target less the cost's rounding level (fountain-P11 certified);
    # 4: the residual model is fitted to the edges on a cycle (a sparse graph's bridges collapsed its scale)
    version = 4

    def __init__(self, folder: Path, spec: MethodSpec, viewgraph: Path, *, label: str | None = None,
                 rotations: Path | None = None, init: Path | None = None,
                 upstream: tuple[str, Path | None, str | None] | None = None,
                 rotation_tol: float = DEFAULT_ROTATION_TOL) -> None:
        super().__init__(folder, spec.config, record_name=label or spec.label)
        self.rotation_tol = float(rotation_tol)
        self.spec = spec
        self.viewgraph = Path(viewgraph)
        self.rotations_path = Path(rotations) if rotations is not None else self.folder / f"{self.record_name}.txt"
        self.stats_path = self.rotations_path.with_suffix(".json")
        self.init_path = None if init is None else Path(init)
        self.upstream_ref = upstream

    # ------------------------------------------------------------ the contract
    def fingerprint(self, inputs: dict[str, str] | None = None) -> str:
        # the config's fingerprint names its class; two methods may share one
        return fingerprint_of(super().fingerprint(inputs), self.spec.name)

    def inputs(self) -> dict[str, str]:
        if self.upstream_ref is not None:
            vg_fp = self.upstream(*self.upstream_ref).fingerprint
        elif not self.viewgraph.exists():
            raise InputFileError(f"input view graph {self.viewgraph} does not exist")
        else:
            files = input_files(self.viewgraph)
            vg_fp = (file_fingerprint(files[0]) if len(files) == 1
                     else fingerprint_of(*[(f.name, file_fingerprint(f)) for f in files]))
        out = {"viewgraph": vg_fp}
        if self.rotation_tol != DEFAULT_ROTATION_TOL:
            out["rotation_tol"] = repr(self.rotation_tol)
        if self.init_path is not None:
            out["init"] = file_fingerprint(self.init_path)
        return out

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        data = read_input_graph(self.viewgraph, self.rotation_tol)
        vg = data.vg
        init = None if self.init_path is None else load_init(self.init_path, vg)
        logger.info("averaging %s with %s: %d cameras, %d edges, options %s", self.viewgraph, self.spec.label,
                    vg.n_cameras, vg.n_edges, self.config.as_dict())
        res = solve.average(vg, self.spec.name, self.config, init=init)
        header = f"rotation averaging of {self.viewgraph.name}: method={res.method} label={self.record_name}"
        if res.dropped_names:
            header = f"dropped (not in the largest component): {' '.join(res.dropped_names)}\n" + header
        write_rotations(self.rotations_path, res.names, res.R, header=header)
        write_json(self.stats_path, self._stats(res, vg, data))
        logger.info("%s: %d cameras in %.3f s, %d iterations -> %s", res.method, len(res.names), res.time_s,
                    res.iterations, self.rotations_path)
        return [self.rotations_path, self.stats_path], {
            "method": res.method, "n_cameras": len(res.names), "n_dropped": len(res.dropped_names),
            "iterations": res.iterations, "solve_s": res.time_s}

    def verify(self, record: StageRecord) -> None:
        names, R = read_rotations(self.rotations_path)
        expected = _solved_names(read_input_graph(self.viewgraph, self.rotation_tol).vg)
        if list(names) != expected:
            missing = [n for n in expected if n not in names]
            raise CacheError(f"{self.rotations_path} holds {len(names)} camera(s) but the solved component of "
                             f"{self.viewgraph} has {len(expected)}" + (f" (missing {missing[:3]})" if missing else ""))
        stats = read_json(self.stats_path, "the stats", CacheError)
        if not isinstance(stats, dict) or stats.get("n_cameras") != len(expected):
            raise CacheError(f"{self.stats_path} does not describe {len(expected)} cameras")

    # ----------------------------------------------------------------- helpers
    def _stats(self, res: AveragingResult, vg: ViewGraph, data: GraphData) -> dict[str, Any]:
        stats = res.summary()
        stats.update({"input": str(self.viewgraph), "label": self.record_name, "options": self.config.as_dict(),
                      "init": str(self.init_path) if self.init_path else getattr(self.config, "init", None),
                      "history": res.history})
        if res.weights is not None and res.residuals_rad is not None:
            w = res.weights / max(float(np.max(res.weights)), 1e-300)
            order = np.argsort(w)[:20]
            e = vg.edges[res.edge_index[order]]
            stats["n_edges_weight_below_1pct"] = int((w < 0.01).sum())
            stats["most_downweighted_edges"] = [
                {"i": vg.names[a], "j": vg.names[b], "residual_deg": float(np.rad2deg(res.residuals_rad[k])),
                 "relative_weight": float(w[k])} for (a, b), k in zip(e, order)
            ]
        stats["evidence"] = ev = camera_evidence(vg, res)
        weak = [c for c in ev["cameras"] if c["support"] != "redundant"]
        if weak:  # said on the console too: the stats file alone is easy to miss
            kinds = Counter(c["support"] for c in weak)
            logger.warning("%s: %d camera(s) rest on weak evidence (%s), e.g. %s; see 'evidence' in %s",
                           res.method, len(weak), ", ".join(f"{k}: {v}" for k, v in kinds.items()),
                           ", ".join(f"{c['name']} ({c['n_kept']} of {c['n_edges']} pairs kept)" for c in weak[:3]),
                           self.stats_path.name)
        if data.R_gt is not None:
            from pipeline.evaluation.metrics import summarize  # noqa: PLC0415 - only .mat inputs carry a ground truth

            kept = positions(vg.names, res.names)
            mask = None if data.gt_mask is None else data.gt_mask[kept]
            if mask is None or mask.any():
                stats["vs_ground_truth"] = summarize(res.R, data.R_gt[kept], mask)
        return stats


def _solved_names(vg: ViewGraph) -> list[str]:
    """The cameras every method solves for: the view graph's largest connected component."""
    if vg.n_cameras == 0 or vg.is_connected():
        return list(vg.names)
    return list(vg.largest_component()[0].names)


def load_init(path: Path, vg: ViewGraph) -> np.ndarray:
    """(N, 3, 3) start rotations for the cameras of ``vg`` from a rotations file (matched by name)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"--init {str(path)!r} is neither 'mst', 'random' nor an existing rotations file")
    return rotations_for(path, list(vg.names), f"{path} lacks initial rotations",
                         "give every camera of the view graph or use --init mst")


def run_averaging(folder: Path, spec: MethodSpec, viewgraph: Path, overwrite: bool = False,
                  upstream: tuple[str, Path | None, str | None] | None = None) -> dict[str, Any]:
    """Run (or reuse) one method into ``folder``: ``{"rotations": path, "stats": dict, "record": record}``."""
    stage = AveragingStage(folder, spec, viewgraph, upstream=upstream)
    record = stage.run(overwrite)
    stats = json.loads(stage.stats_path.read_text(encoding="utf-8"))
    return {"rotations": stage.rotations_path, "stats": stats, "record": record}
