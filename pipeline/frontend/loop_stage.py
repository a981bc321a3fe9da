"""The loop-closure round of the front end: a stage, and the front end's rounds around it.

With retrieval or sequential pairs, the front end runs in two rounds (:func:`run_front_end`):

1. matching of the selected pairs, cameras, two-view geometry, two-view BA (the first round);
2. the loop-closure stage: the first round's verified graph is averaged (IRLS-ℓ½ on its
   largest component), and the pairs that would close its longest loops are chosen among
   each image's next-ranked retrieval neighbours (:func:`pipeline.frontend.loop_closure.loop_candidates`;
   with sequential pairs the first round ranks them too, as COLMAP's sequential matcher's loop detection does);
   where retrieval chose k itself and the first round verified almost every pair, also the further ranked
   neighbours (not looking apart) of the images whose lower-ranked candidates all verified (k was short of
   their overlap: :func:`pipeline.frontend.loop_closure.saturated_candidates`); and the unmatched pairs whose
   images the first round's verified inliers chain through enough keypoints of other images
   (:func:`pipeline.frontend.loop_closure.transitive_candidates`);
3. matching, two-view geometry and two-view BA again, on the first round's pairs and those
   (the second round). Every pair is cached by its own key, so only the added pairs are computed.

The cameras are the first round's: the loop's pairs are chosen to close loops, not to
estimate intrinsics, and a second estimate would redo every pair's geometry.

A re-run reuses the loop-closure result while the first round's selection and every
option of the rounds are unchanged, without running the first round again; otherwise the
first round runs first. With exhaustive pairs, a pairs file or a database's matches, or
with ``loop_closure.enabled: false``, there is one round.

WORK/loop_closure.json: the first round's pairs and the pairs added (each with its hop
distance, angle and retrieval similarity), and the counts. Command line::

    python -m pipeline.loop_closure --work WORK [--config YAML] [--min-hops 5] [--max-fraction 0.1]

runs the front end's rounds in WORK (each stage reused where it is done).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.core.atomic import write_json
from pipeline.core.config import Config, option
from pipeline.core.errors import CacheError, InputFileError, ViewGraphError
from pipeline.core.names import positions
from pipeline.core.readers import read_json
from pipeline.core.viewgraph import ViewGraph, pair_keys
from pipeline.frontend import feature_stage, matching_stage
from pipeline.frontend.camera_stage import CamerasConfig, CamerasStage
from pipeline.frontend.loop_closure import loop_candidates, saturated_candidates, transitive_candidates
from pipeline.frontend.matching import MatchingConfig
from pipeline.frontend.pairs import parse_selector, resolve_auto, selection_summary
from pipeline.geometry.ba_solver import BAConfig
from pipeline.geometry.ba_stage import TwoViewBAStage, load_ba_viewgraph
from pipeline.geometry.ransac import TwoViewConfig
from pipeline.geometry.two_view_stage import TwoViewStage, load_two_view
from pipeline.stage import Stage, StageRecord, read_record

logger = logging.getLogger(__name__)

__all__ = ["LoopClosureConfig", "LoopClosureStage", "FrontEnd", "run_front_end", "first_round_rotations", "loop_note",
           "main", "main_cli", "OUTPUT"]

OUTPUT = "loop_closure.json"


@dataclass(frozen=True, kw_only=True)
class LoopClosureConfig(Config):
    """Options of the loop-closure round (YAML section ``loop_closure``)."""

    SECTION = "loop_closure"

    enabled: bool = option(True, "with retrieval or sequential pairs, match a second round of pairs that close "
                           "the first round's loops")
    min_hops: int = option(5, "a pair is matched only if its images are at least this many verified pairs apart "
                           "(also through each loop-closure pair taken before it)", ge=2)
    max_angle_deg: float = option(60.0, "a pair whose viewing directions (by the first round's rotations) are "
                                        "further apart is not matched", gt=0, le=180)
    max_fraction: float = option(0.1, "the second round matches at most this fraction of the first round's pairs",
                                 ge=0)
    saturated_share: float = option(0.95, "with retrieval whose k was chosen automatically, an image whose "
                                    "candidates ranked k/2 to k verified at least at this share gets its further ranked "
                                    "neighbours matched too, those not looking more than max_angle_deg apart "
                                    "(above 1: never)", ge=0)
    saturated_max_fraction: float = option(1.0, "those pairs are at most this fraction of the first round's", ge=0)
    transitive_min_matches: int = option(15, "an unmatched pair whose images the first round's verified pairs' "
                                         "inliers chain through this many keypoints of other images is matched "
                                         "(the view graph's own least inliers of a pair; 0: never)", ge=0)
    transitive_max_fraction: float = option(0.25, "those pairs are at most this fraction of the first round's, the "
                                            "most chained first", ge=0)


@dataclass(frozen=True)
class FrontEnd:
    """The configs of the front end's rounds (progress applied where a config has it)."""

    matching: MatchingConfig
    cameras: CamerasConfig
    two_view: TwoViewConfig
    two_view_ba: BAConfig
    loop_closure: LoopClosureConfig
    progress: bool = True

    def stages(self, work: Path, loop: LoopClosureStage | None, rank: bool = False) -> list[Stage]:
        """Matching (with the loop's pairs when ``loop`` is given; ranked for a loop-closure round with ``rank``),
        cameras, two-view, two-view BA."""
        return [matching_stage.MatchingStage(work, self.matching, progress=self.progress, loop=loop, rank=rank),
                CamerasStage(work, self.cameras), TwoViewStage(work, self.two_view),
                TwoViewBAStage(work, self.two_view_ba)]


def first_round_rotations(vg: ViewGraph) -> np.ndarray:
    """(N, 3, 3) IRLS-ℓ½ rotations of the largest component of a two-view BA graph; NaN elsewhere."""
    from pipeline.averaging.solve import average  # noqa: PLC0415 - the averaging package is heavy

    R = np.full((vg.n_cameras, 3, 3), np.nan)
    if vg.n_edges == 0:
        return R
    sub, _ = vg.largest_component()
    try:
        res = average(sub, "irls")
    except (ViewGraphError, ValueError) as exc:  # no angle test then: every far pair stays a candidate
        logger.warning("loop closure: the first round's graph could not be averaged (%s); pairs are chosen without "
                       "their rotations", " ".join(str(exc).split()))
        return R
    R[positions(vg.names, res.names)] = np.asarray(res.R)
    return R


class LoopClosureStage(Stage[LoopClosureConfig]):
    """The pairs of the loop-closure round, from the first round's result in WORK (folder = WORK)."""

    name = "loop_closure"
    title = "loop closure"
    config_cls = LoopClosureConfig

    def __init__(self, work: Path, front: FrontEnd) -> None:
        super().__init__(work, front.loop_closure)
        self.front = front
        self._why_not: str | None = None  # "" once decided that it applies

    def first_round(self) -> matching_stage.MatchingStage:
        return matching_stage.MatchingStage(self.folder, self.front.matching, progress=self.front.progress, rank=True)

    def applies(self) -> bool:
        """Whether the front end has a loop-closure round: enabled, our own features, retrieval or sequential pairs."""
        return self.why_not() is None

    def why_not(self) -> str | None:
        """Why the front end has no loop-closure round, in a few words (None: it has one)."""
        if self._why_not is None:
            fm = feature_stage.load_manifest(self.folder)
            kind, _ = parse_selector(self.front.matching.pairs)
            n, limit = len(fm["names"]), self.front.matching.exhaustive_max_images
            if fm.get("database"):
                why = "a database's matches"
            elif kind == "auto" and resolve_auto(n, limit) == "exhaustive":
                why = f"exhaustive pairs: {n} images, pairs=auto is exhaustive up to {limit}"
            elif kind not in ("auto", "retrieval", "sequential"):
                why = {"exhaustive": "exhaustive pairs", "file": "a pairs file", "database": "a database's pairs"}[kind]
            else:
                why = "" if self.config.enabled else "loop_closure.enabled: false"
            self._why_not = why
        return self._why_not or None

    def inputs(self) -> dict[str, str]:
        """The first round's selection and every option of the first round (not its records: the second round
        writes over them)."""
        cams = CamerasStage(self.folder, self.front.cameras)
        return {"matching": self.first_round().base_fingerprint(), "cameras": self.front.cameras.fingerprint(),
                **{f"cameras:{k}": v for k, v in cams.file_inputs().items()},
                "two_view": self.front.two_view.fingerprint(), "two_view_ba": self.front.two_view_ba.fingerprint()}

    def ready(self) -> StageRecord | None:
        """The cached result, or None (also when the first round has not run: nothing to be cached then)."""
        try:
            return self.cached()
        except InputFileError:
            return None

    def _check_first_round(self, base: str) -> None:
        """WORK's two-view BA graph is the first round's (the matches, two-view and BA records chain to ``base``)."""
        work = self.folder
        recs = {n: read_record(work, n) for n in ("matching", "two_view", "two_view_ba")}
        ok = (all(r is not None for r in recs.values()) and recs["matching"].fingerprint == base  # type: ignore[union-attr]
              and recs["two_view"].inputs.get("matching") == base  # type: ignore[union-attr]
              and recs["two_view_ba"].inputs.get("two_view") == recs["two_view"].fingerprint)  # type: ignore[union-attr]
        if not ok:
            raise InputFileError(f"{work} does not hold the first round's two-view BA (matching, two_view, "
                                 f"two_view_ba of the current selection); run `python -m pipeline.loop_closure "
                                 f"--work {work}`, which runs it first")

    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        cfg, work = self.config, self.folder
        base = self.first_round().base_fingerprint()
        self._check_first_round(base)
        mm = matching_stage.load_manifest(work)
        names, first = list(mm["names"]), np.asarray(mm["pairs"], np.int64).reshape(-1, 2)
        n = len(names)
        nb, sim = matching_stage.load_ranked(work, n)
        vg = load_ba_viewgraph(work)
        budget = int(math.floor(cfg.max_fraction * len(first)))
        R = first_round_rotations(vg)
        c = loop_candidates(n, first, vg.edges, nb, sim, R, min_hops=cfg.min_hops,
                            max_angle_deg=cfg.max_angle_deg, budget=budget)
        added = c["pairs"]
        sat = self._saturated(n, first, vg.edges, nb, sim, R, mm.get("selection") or {})
        new = ~np.isin(pair_keys(*sat["pairs"].T, n), pair_keys(*added.T, n))  # not a loop-closure pair already
        sat.update({k: sat[k][new] for k in ("pairs", "similarity", "angle_deg")})
        extended = sat["pairs"]
        tr = self._transitive(n, np.concatenate([first, added, extended]), vg, len(first))
        chained = tr["pairs"]
        pairs = np.unique(np.concatenate([first, added, extended, chained]), axis=0)
        counts = {k: v for k, v in c.items() if k.startswith("n_")}
        summary = {"base": base, "n_first": len(first), "n_added": len(added), "budget": budget,
                   "min_hops": cfg.min_hops, **counts, "n_saturated": sat["n_saturated"],
                   "n_extended": len(extended), "saturated_budget": sat["budget"], "n_transitive": len(chained),
                   "n_transitive_eligible": tr["n_eligible"], "transitive_budget": tr["budget"],
                   "transitive_min_matches": cfg.transitive_min_matches}
        sel = dict(mm.get("selection") or {})
        selection = selection_summary({**sel, "loop_closure": {"n_first": len(first), "n_added": len(added),
                                                               "n_saturated": sat["n_saturated"],
                                                               "n_extended": len(extended),
                                                               "n_transitive": len(chained)}},
                                      n, len(pairs))
        path = write_json(work / OUTPUT, {
            "format": "rotavg-loop-closure", "names": names, "pairs": pairs.tolist(), "selection": selection,
            "added": [{"pair": [names[a], names[b]], "hops": None if math.isinf(h) else int(h),
                       "angle_deg": None if math.isnan(g) else round(float(g), 3), "similarity": round(float(s), 4)}
                      for (a, b), h, g, s in zip(added.tolist(), c["hops"], c["angle_deg"], c["similarity"])],
            "extended": [{"pair": [names[a], names[b]], "angle_deg": None if math.isnan(g) else round(float(g), 3),
                          "similarity": round(float(s), 4)}
                         for (a, b), g, s in zip(extended.tolist(), sat["angle_deg"], sat["similarity"])],
            "transitive": [{"pair": [names[a], names[b]], "count": int(t)}
                           for (a, b), t in zip(chained.tolist(), tr["count"])],
            **summary})
        logger.info("loop closure: %d pairs added to the first round's %d (budget %d; of %d unmatched ranked pairs, "
                    "%d at least %d hops apart, %d of those looking apart)", len(added), len(first), budget,
                    c["n_candidates"], c["n_far"], cfg.min_hops, c["n_apart"])
        if sat["n_saturated"]:
            logger.info("retrieval's k was short of %d image(s) whose lower-ranked candidates verified too: %d of "
                        "their next-ranked pairs added (budget %d)", sat["n_saturated"], len(extended), sat["budget"])
        if len(chained):
            logger.info("%d pairs whose images the verified pairs' inliers chain through at least %d keypoints of "
                        "other images added (of %d; budget %d)", len(chained), cfg.transitive_min_matches,
                        tr["n_eligible"], tr["budget"])
        return [path], summary

    def _transitive(self, n: int, matched: np.ndarray, vg: ViewGraph, n_first: int) -> dict[str, Any]:
        """:func:`transitive_candidates` through the inliers of the first round's verified pairs (those of the
        two-view BA graph ``vg``), up to ``transitive_max_fraction`` of the first round's pairs."""
        cfg = self.config
        budget = int(math.floor(cfg.transitive_max_fraction * n_first))
        if cfg.transitive_min_matches <= 0 or budget <= 0 or vg.n_edges == 0:
            return {"pairs": np.zeros((0, 2), np.int64), "count": np.zeros(0, np.int64), "n_eligible": 0,
                    "budget": budget}
        try:
            offsets, kp = load_two_view(self.folder).inliers_of(vg.edges)
        except ValueError:
            raise CacheError(f"the two-view BA graph in {self.folder} has pairs the two-view result lacks; re-run "
                             f"`python -m pipeline.loop_closure --work {self.folder} --overwrite`") from None
        out = transitive_candidates(n, matched, vg.edges, offsets, kp[:, 0], kp[:, 1],
                                    min_count=cfg.transitive_min_matches, budget=budget)
        return {**out, "budget": budget}

    def _saturated(self, n: int, first: np.ndarray, verified: np.ndarray, nb: np.ndarray, sim: np.ndarray,
                   R: np.ndarray, selection: dict[str, Any]) -> dict[str, Any]:
        """:func:`saturated_candidates` where retrieval chose k itself (auto, or ``retrieval`` without K: a k the
        user gave is kept as given, as sequential's K is); no pairs otherwise."""
        cfg = self.config
        kind, arg = parse_selector(self.front.matching.pairs)
        k = selection.get("k")
        budget = int(math.floor(cfg.saturated_max_fraction * len(first)))
        if selection.get("selector") != "retrieval" or kind not in ("auto", "retrieval") or arg is not None or not k:
            return {"pairs": np.zeros((0, 2), np.int64), "similarity": np.zeros(0), "angle_deg": np.zeros(0),
                    "n_saturated": 0, "budget": 0}
        out = saturated_candidates(n, int(k), first, verified, nb, sim, R, share=cfg.saturated_share,
                                   max_angle_deg=cfg.max_angle_deg, budget=budget)
        return {**out, "budget": budget}

    @staticmethod
    def adds_pairs(record: StageRecord | None) -> bool:
        """Whether a loop-closure result adds pairs to the first round's (loop-closure, saturated images' or
        transitive pairs)."""
        return record is not None and any(record.summary.get(k, 0) > 0 for k in ("n_added", "n_extended",
                                                                                "n_transitive"))

    def verify(self, record: StageRecord) -> None:
        self.load_pairs(list(feature_stage.load_manifest(self.folder)["names"]))

    def load_pairs(self, names: list[str]) -> tuple[np.ndarray, dict[str, Any]]:
        """The second round's pairs (P, 2) and its selection summary, checked against the images ``names``."""
        path = self.folder / OUTPUT
        d = read_json(path, "the loop-closure result", CacheError)
        try:
            if list(d["names"]) != names:
                raise ValueError("other images than the current features")
            P = np.asarray(d["pairs"], np.int64).reshape(-1, 2)
            if P.size and (P.min() < 0 or P.max() >= len(names) or np.any(P[:, 0] >= P[:, 1])):
                raise ValueError("a pair is out of range or not (a, b) with a < b")
            return P, dict(d["selection"])
        except (KeyError, TypeError, ValueError) as exc:
            raise CacheError(f"{path} is damaged ({' '.join(str(exc).split())[:80]}); re-run "
                             f"`python -m pipeline.loop_closure --work {self.folder}`") from None


def loop_note(work: Path) -> str | None:
    """One line for the report on the loop-closure round of WORK's current matches (None: there was none)."""
    m = matching_stage.load_manifest(work).get("selection") or {}
    if "loop_closure" not in m:
        return None
    d = read_json(Path(work) / OUTPUT, "the loop-closure result", CacheError)
    idx = {nm: k for k, nm in enumerate(d["names"])}
    n = len(idx)
    edges = load_ba_viewgraph(work).edges

    def verified(rows: list[dict[str, Any]]) -> tuple[int, int]:
        P = np.array([sorted((idx[a["pair"][0]], idx[a["pair"][1]])) for a in rows], np.int64).reshape(-1, 2)
        return len(P), int(np.isin(pair_keys(*P.T, n), pair_keys(*edges.T, n)).sum())

    n_added, n_ok = verified(d["added"])
    note = (f"loop closure: {n_added} pairs added to the first round's {d['n_first']} (their images at least "
            f"{d['min_hops']} verified pairs apart), {n_ok} of them verified")
    if d.get("n_saturated"):
        n_ext, n_ext_ok = verified(d.get("extended", []))
        note += (f"; {n_ext} next-ranked pairs of the {d['n_saturated']} images whose lower-ranked retrieval "
                 f"candidates verified too (k was short for them), {n_ext_ok} of them verified")
    if d.get("n_transitive"):
        n_tr, n_tr_ok = verified(d.get("transitive", []))
        note += (f"; {n_tr} pairs whose images the verified pairs' inliers chain through at least "
                 f"{d['transitive_min_matches']} keypoints of other images, {n_tr_ok} of them verified")
    return note


RunStage = Callable[[Stage, bool, bool], Any]


def run_front_end(work: Path, front: FrontEnd, run: RunStage | None = None, overwrite: bool = False,
                  skip: Callable[[Stage, str], None] | None = None) -> None:
    """Matching, cameras, two-view and two-view BA in WORK, in two rounds around the loop-closure stage where it
    applies (see the module docstring).

    Args:
        run: ``run(stage, overwrite, again)`` runs a stage (``again``: its second round); default ``stage.run``.
        overwrite: recompute every stage once (the second round reuses the first round's pairs).
        skip: ``skip(stage, why)`` is told, after the one round, why the loop-closure stage did not run.
    """
    run = run or (lambda stage, ow, again: stage.run(ow))
    loop = LoopClosureStage(work, front)
    if not loop.applies():
        for st in front.stages(work, None):
            run(st, overwrite, False)
        if skip is not None:
            skip(loop, str(loop.why_not()))
        return
    first = overwrite or loop.ready() is None
    if first:
        for st in front.stages(work, None, rank=True):
            run(st, overwrite, False)
    run(loop, overwrite, False)
    for st in front.stages(work, loop, rank=True):
        run(st, overwrite and not first, first)


def main(work: Path, config: Path | None = None, loop_config: LoopClosureConfig | None = None,
         overwrite: bool = False, progress: bool = True) -> Path:
    """The front end's rounds in WORK with the sections of ``config`` (``loop_config`` replaces its loop_closure
    section); returns the loop-closure result's path."""
    from pipeline.core.config import load_yaml, stage_config  # noqa: PLC0415

    data = load_yaml(config)
    front = FrontEnd(stage_config(MatchingConfig, data), stage_config(CamerasConfig, data, progress=progress),
                     stage_config(TwoViewConfig, data, progress=progress),
                     stage_config(BAConfig, data, progress=progress),
                     loop_config or stage_config(LoopClosureConfig, data), progress)
    loop = LoopClosureStage(work, front)
    if not loop.applies():
        raise InputFileError(f"no loop-closure round in {work} ({loop.why_not()}): it follows retrieval or sequential "
                             f"pairs of our own features (matching.pairs={front.matching.pairs!r}) with "
                             "loop_closure.enabled")
    run_front_end(Path(work), front, overwrite=overwrite)
    return Path(work) / OUTPUT


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import add_config_args, config_from_args, run_cli  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m pipeline.loop_closure",
                                description="The front end's rounds in WORK: matching, cameras, two-view and "
                                "two-view BA of the retrieval or sequential pairs, then of the pairs that close the first round's "
                                "loops.")
    p.add_argument("--work", type=Path, required=True, help="WORK folder written by pipeline.features")
    p.add_argument("--config", type=Path, default=None, help="YAML config (its matching, cameras, two_view, "
                   "two_view_ba and loop_closure sections)")
    p.add_argument("--overwrite", action="store_true", help="recompute every stage")
    add_config_args(p, LoopClosureConfig)

    def body(a: argparse.Namespace) -> int:
        print(main(a.work, a.config, config_from_args(LoopClosureConfig, a, a.config), a.overwrite, not a.quiet))
        return 0

    return run_cli(body, p, argv)


if __name__ == "__main__":
    sys.exit(main_cli())
