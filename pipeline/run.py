"""The whole pipeline on an image folder: a list of stages.

The implementation behind the top-level ``run.py``; also ``python -m pipeline.run``::

    python run.py [IMAGE_DIR] [--out DIR] [--config configs/NAME.yaml] [--methods M ...]
                  [--gt REF] [--K FILE | --database DB] [--executor E] [--scheduler ADDRESS]
                  [--no-reference] [--overwrite] [-v | -q]

Every input is checked first (:func:`pipeline.plan.prepare`: the whole config, the
methods, ``--K``, ``--gt``, the output folder, every image's header). Then the
stages run, each under the stage contract (:mod:`pipeline.stage`: a fingerprint of
its options and inputs, a record, an intact cached result reused, a damaged one
recomputed), each also a command of its own:

1. features      ``python -m pipeline.features``     → OUT/work/features.json + features/
2. matching      ``python -m pipeline.matching``     → OUT/work/matches.json + matches/
3. cameras       ``python -m pipeline.cameras``      → OUT/work/cameras.json (K, distortion, their sources)
4. two-view      ``python -m pipeline.two_view``     → OUT/work/two_view.npz (RANSAC view graph)
5. two-view BA   ``python -m pipeline.two_view_ba``  → OUT/work/viewgraph.npz (with H)
   loop closure  ``python -m pipeline.loop_closure`` → OUT/work/loop_closure.json; with retrieval pairs, matching,
                 two-view and two-view BA run again with the pairs that close the first round's loops
6. view graph    ``python -m pipeline.viewgraph``     → OUT/viewgraph.npz: the checked pairs' largest component
                 (+ viewgraph.json: every pair's fate and reason, why each image is left out, flagged cameras);
                 each other component of at least 3 images in OUT/component-k/, where steps 7, 8 and 11 run
                 for it too (its rotations in a frame of their own; compared with the peers' model that holds most
                 of its images)
7. averaging     ``python -m pipeline.average``      → OUT/rotations/<method>.txt + .json, one per method
8. refine        ``python -m pipeline.refine``       → OUT/sparse/ (COLMAP model), OUT/rotations/<method>+refine.txt
9. reference     ``python -m pipeline.reference``    → OUT/reference/ (pycolmap incremental)
10. GLOMAP       ``python -m pipeline.reference.global_mapping`` → OUT/reference-global/ (pycolmap global)
11. evaluation and report                             → OUT/metrics.json, OUT/report.md

On the console each step is numbered by its place among the 13 of ``STEPS`` (loop closure
6, refine 9, the two peers 10 and 11, evaluation 12, report 13); a step that does not run
says so and why, e.g. ``[6/13] loop closure: not run (exhaustive pairs: ...)`` or
``[10/13] pycolmap reference: not run (--no-reference)``.

Methods come from the registry (:mod:`pipeline.averaging.registry`). With no
IMAGE_DIR a small scene is rendered into OUT/scene and its cameras are the truth.
A re-run with the same ``--out`` reuses every finished stage; ``--overwrite`` redoes
everything. One run at a time holds an output folder; temporary files an
interrupted run left there are removed.
"""

from __future__ import annotations

import os

# pycolmap's OpenMP runtime busy-waits otherwise (15-60x slower on 2 shared cores)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Callable  # noqa: E402

from pipeline.averaging import registry  # noqa: E402
from pipeline.averaging.stage import run_averaging  # noqa: E402
from pipeline.core.atomic import remove_stale_temporaries  # noqa: E402
from pipeline.core.errors import PipelineError  # noqa: E402
from pipeline.core.lock import folder_lock  # noqa: E402
from pipeline.core.parallel import BACKENDS  # noqa: E402
from pipeline.core.viewgraph import ViewGraph  # noqa: E402
from pipeline.evaluation.assemble import evaluate_run, withdraw_reports, write_metrics, write_report_md  # noqa: E402
from pipeline.evaluation.flags import DISAGREEMENT_DEG  # noqa: E402
from pipeline.frontend.feature_stage import load_manifest  # noqa: E402
from pipeline.frontend.loop_stage import FrontEnd, loop_note, run_front_end  # noqa: E402
from pipeline.graph.stage import ViewGraphStage, load_graph_summary  # noqa: E402
from pipeline.plan import Plan, prepare  # noqa: E402
from pipeline.reference.global_mapping import LABEL as GLOBAL_LABEL  # noqa: E402
from pipeline.reference.global_mapping import GlobalReferenceStage, load_global_reference  # noqa: E402
from pipeline.reference.incremental import IncrementalReferenceStage  # noqa: E402
from pipeline.reference.models import load_reference, model_reference  # noqa: E402
from pipeline.refine.stage import refine_for_run  # noqa: E402
from pipeline.stage import Stage, StageRecord  # noqa: E402

logger = logging.getLogger("run")

REFINE_TITLE = "refine (pycolmap)"
STEPS = ("features", "matching", "cameras", "two_view", "two_view_ba", "loop_closure", "viewgraph", "averaging",
         "refine", "reference", "global_reference", "evaluation", "report")


def _reused(res: Any) -> bool | None:
    """Whether a step reused its result: a stage's record, or ``{label: {"record": ...}}`` of several (the averaging
    methods, the refinement); None where the step says nothing of it."""
    if isinstance(res, StageRecord):
        return res.reused
    if isinstance(res, dict) and res and all(isinstance(v, dict) and isinstance(v.get("record"), StageRecord)
                                             for v in res.values()):
        return all(v["record"].reused for v in res.values())
    return None


def _number(name: str) -> str:
    """``[k/13]``: the step's place in ``STEPS``."""
    return f"[{STEPS.index(name) + 1}/{len(STEPS)}]"


class Runner:
    """Runs the steps in order: one progress line each, its wall time, whether it reused its result."""

    def __init__(self, plan: Plan) -> None:
        self.plan = plan
        self.times: dict[str, float] = dict(plan.times)
        self.reused: dict[str, bool] = {}
        self.not_run: dict[str, str] = {}  # step → why it did not run (metrics.json: steps_not_run)

    def step(self, name: str, title: str, fn: Callable[[], Any], again: bool = False) -> Any:
        """Run one step, numbered by its place in ``STEPS``; ``again``: its second round (loop closure)."""
        k = _number(name)
        if again:
            title = f"{title} (loop-closure round)"
        if not self.plan.quiet:
            print(f"{k} {title} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        res = fn()
        dt = time.perf_counter() - t0
        self.times[name] = self.times.get(name, 0.0) + dt  # both rounds of a step
        reused = _reused(res)
        if reused is not None:
            self.reused[name] = reused and self.reused.get(name, True)
        if not self.plan.quiet:
            print(f"{k} {title}: {dt:.2f} s{' (reused)' if reused else ''}", file=sys.stderr, flush=True)
        return res

    def skip(self, name: str, title: str, why: str) -> None:
        """Say, in its place in ``STEPS``, that a step does not run and why (the progress lines skip no number)."""
        self.not_run[name] = why
        if not self.plan.quiet:
            print(f"{_number(name)} {title}: not run ({why})", file=sys.stderr, flush=True)

    def say(self, name: str, what: str) -> None:
        """A line in the place of step ``name`` (a default method it leaves out: ``[8/13] SDP-cSO(3) not run ...``)."""
        if not self.plan.quiet:
            print(f"{_number(name)} {what}", file=sys.stderr, flush=True)

    def skipped(self, name: str, title: str) -> bool:
        """Whether the plan leaves the step out (``plan.skipped``); if it does, :meth:`skip` says so."""
        why = self.plan.skipped.get(name)
        if why is not None:
            self.skip(name, title, why)
        return why is not None

    def stage(self, stage: Stage, overwrite: bool | None = None, again: bool = False) -> StageRecord:
        ow = self.plan.overwrite if overwrite is None else overwrite
        return self.step(stage.name, stage.title, lambda: stage.run(ow), again)

    def front_end(self) -> None:
        """Matching, cameras, two-view, two-view BA, and the loop-closure round where it applies."""
        plan, progress = self.plan, {"progress": self.plan.progress}
        front = FrontEnd(plan.config("matching"), plan.config("cameras", **progress), plan.config("two_view", **progress),
                         plan.config("two_view_ba", **progress), plan.config("loop_closure"), plan.progress)
        run_front_end(plan.work, front, lambda st, ow, again: self.stage(st, ow, again), plan.overwrite,
                      lambda st, why: self.skip(st.name, st.title, why))
        note = loop_note(plan.work)
        if note:
            plan.notes.append(note)


def _averaging(plan: Plan, runner: Runner, vg: Any, upstream: tuple[str, Path, None] | None = None
               ) -> tuple[list[Any], dict[str, dict]]:
    """Every method on ``vg`` (OUT/viewgraph.npz); its input is the view-graph stage's record (``upstream``: where
    that stage ran in OUT), else the file's content (another component's graph)."""
    specs = list(plan.methods)
    if not specs:
        specs, why = registry.default_methods(vg, plan.run, plan.yaml, plan.overrides)
        plan.notes.extend(why)
        for w in why:
            runner.say("averaging", w)

    def solve_all() -> dict[str, dict]:
        from tqdm import tqdm  # noqa: PLC0415

        res = {}
        for spec in tqdm(specs, desc="averaging", unit="method", disable=plan.quiet):
            res[spec.label] = run_averaging(plan.out / "rotations", spec, plan.out / "viewgraph.npz",
                                            plan.overwrite, upstream=upstream)
        return res

    results = runner.step("averaging", "rotation averaging", solve_all)
    return specs, results


def _refine(plan: Plan, runner: Runner, results: dict[str, dict]) -> None:
    """The recommended method's rotations finished by pycolmap (rows ``<method>+refine``), when the run refines."""
    if not runner.skipped("refine", REFINE_TITLE):
        results.update(runner.step("refine", REFINE_TITLE, lambda: refine_for_run(
            plan.out, plan.configs["refine"], list(results), plan.work, plan.overwrite, plan.notes)))


#: The second opinion of a run with one method (``run.second_opinion``): IRLS-ℓ½, or colmap-ra where IRLS-ℓ½ is the one.
SECOND_OPINION = ("irls", "colmap-ra")


def _second_opinion(plan: Plan, runner: Runner, specs: list[Any], results: dict[str, dict],
                    upstream: tuple[str, Path, None] | None = None, refined: bool = True) -> None:
    """A second method where only one set of rotations came out of averaging and refinement.

    Cameras are flagged where the methods disagree by more than ``DISAGREEMENT_DEG`` (1°,
    :mod:`pipeline.evaluation.flags`); with one set of rotations nothing can disagree, and a camera a method puts
    degrees off where the graph's evidence is consistent (H's weights on biased pairs, a robust loss in the wrong
    basin) would go unflagged. The second method is run, reported as a row of its own, and said in the notes.
    Called before the refinement (``refined=False``: only where none will run) and after it (where it gave no
    row)."""
    if not plan.run.second_opinion or len(results) != 1 or (not refined and plan.run.refine):
        return
    only = next(iter(results))
    for token in SECOND_OPINION:
        spec = registry.parse_method(token, plan.yaml, plan.overrides)
        if spec.label != only:
            break
    results.update(runner.step("averaging", f"rotation averaging, second opinion ({spec.label})", lambda: {
        spec.label: run_averaging(plan.out / "rotations", spec, plan.out / "viewgraph.npz", plan.overwrite,
                                  upstream=upstream)}))
    specs.append(spec)
    plan.notes.append(f"one set of rotations ({only}): {spec.label} was run as a second opinion, so that the cameras "
                      f"where the two disagree by more than {DISAGREEMENT_DEG:g}° are flagged (run.second_opinion: false to "
                      "skip it)")


def _report(plan: Plan, runner: Runner, vg: ViewGraph, specs: list[Any], results: dict[str, dict], peers: list[Any],
            left_out: dict[str, str], t_start: float) -> tuple[Any, Path]:
    """Evaluation, report.md and metrics.json of the run in ``plan.out``; returns the evaluation and the metrics' path."""
    ev = runner.step("evaluation", "evaluation", lambda: evaluate_run(plan, vg, results, peers))
    runner.step("report", "report", lambda: write_report_md(plan, ev, specs, results, vg, runner))
    return ev, write_metrics(plan, ev, vg, left_out, runner, t_start)


def _components(plan: Plan, t_start: float, peers: list[Any]) -> None:
    """The view graph's other components (OUT/component-k/), each averaged, refined, evaluated against the truth and
    against the peers' model that holds most of its images, and reported in its own folder, in a frame of its own;
    listed in ``plan.components`` for metrics.json."""
    folders = {"pycolmap": plan.out / "reference", GLOBAL_LABEL: plan.out / "reference-global"}
    for c in load_graph_summary(plan.out).get("components", []):
        k = int(c["component"])
        sub = plan.for_component(plan.out / c["folder"], k)
        if not plan.quiet:
            print(f"component {k} of the view graph ({c['n_cameras']} images, {sub.out}):", file=sys.stderr,
                  flush=True)
        runner = Runner(sub)
        vg = ViewGraph.load(sub.out / "viewgraph.npz")
        specs, results = _averaging(sub, runner, vg)
        _second_opinion(sub, runner, specs, results, refined=False)
        _refine(sub, runner, results)
        _second_opinion(sub, runner, specs, results)
        runner.skipped("reference", IncrementalReferenceStage.title)  # the peers ran once, on every image
        runner.skipped("global_reference", GlobalReferenceStage.title)
        models = [model_reference(folders[p.label], list(vg.names), p.label) for p in peers if p.label in folders]
        ev, _ = _report(sub, runner, vg, specs, results, [m for m in models if m], {}, t_start)
        medians = {m: (v.get("references") or {}).get("truth", {}).get("median_deg")
                   for m, v in ev.metrics.get("methods", {}).items()}
        plan.components.append({**{key: c[key] for key in ("component", "folder", "n_cameras", "n_edges", "names")},
                                "median_deg_vs_truth": medians})
        plan.notes.append(f"component {k} of the view graph ({c['n_cameras']} images: {', '.join(c['names'][:4])}"
                          f"{'...' if len(c['names']) > 4 else ''}) solved in {c['folder']}/, in a frame of its own")


def _reference(plan: Plan, runner: Runner, names: list[str]) -> Any:
    """The pycolmap reference; its failure is reported and never throws our result away."""
    if runner.skipped("reference", IncrementalReferenceStage.title):
        return None
    stage = IncrementalReferenceStage(plan.out / "reference", plan.configs["reference"], images=plan.images,
                                      names=names, K=plan.K, work=plan.work, progress=plan.progress)
    try:
        runner.stage(stage)
        ref = load_reference(plan.out / "reference")
    except (PipelineError, RuntimeError, ValueError, OSError) as exc:
        msg = " ".join(str(exc).split())
        logger.warning("the pycolmap reference failed (%s); continuing without it", msg)
        plan.notes.append(f"pycolmap reference failed: {msg}")
        return None
    if not ref.names:
        plan.notes.append("pycolmap registered no image")
    plan.notes.extend(f"pycolmap did not register {nm}: {why}" for nm, why in ref.unregistered.items())
    return ref


def _global_reference(plan: Plan, runner: Runner, names: list[str]) -> Any:
    """The GLOMAP peer, in OUT/reference-global on OUT/reference's database; its failure is reported and never throws
    our result away."""
    if runner.skipped("global_reference", GlobalReferenceStage.title):
        return None
    stage = GlobalReferenceStage(plan.out / "reference-global", plan.configs["global_reference"], images=plan.images,
                                 names=names, K=plan.K, work=plan.work, progress=plan.progress,
                                 database_dir=plan.out / "reference")
    try:
        runner.stage(stage)
        glo = load_global_reference(plan.out / "reference-global")
    except (PipelineError, RuntimeError, ValueError, OSError) as exc:
        plan.notes.append(f"pycolmap global (GLOMAP) failed: {' '.join(str(exc).split())}")
        logger.warning("%s; continuing without it", plan.notes[-1])
        return None
    plan.notes.extend(f"GLOMAP did not register {nm}: {why}" for nm, why in glo.unregistered.items())
    return glo


def main(images: Path | None = None, out: Path | None = None, config: Path | None = None,
         methods: list[str] | None = None, gt: Path | None = None, K: Path | None = None,
         reference: bool | None = None, overwrite: bool = False, quiet: bool = False,
         database: Path | None = None, executor: str | None = None, scheduler: str | None = None) -> Path:
    """Run the whole pipeline; returns the path of ``OUT/metrics.json``."""
    t_start = time.perf_counter()
    plan = prepare(images, out, config, methods, gt, K, reference, overwrite, quiet, database, executor, scheduler)
    with folder_lock(plan.out), plan.executors():
        remove_stale_temporaries(plan.out)
        withdraw_reports(plan.out)
        runner = Runner(plan)
        work = plan.work
        runner.stage(plan.features)
        plan.note_features(load_manifest(work))
        runner.front_end()
        graph = ViewGraphStage(plan.out, plan.config("viewgraph"), work=work)
        runner.stage(graph)
        vg = graph.load()
        left_out = load_graph_summary(plan.out)["left_out"]
        if left_out:
            plan.notes.append(f"view graph not connected: its largest component ({vg.n_cameras} images) is solved here; "
                              f"outside it: {', '.join(left_out)}")
            plan.notes.extend(f"outside the view graph's largest component: {n}: {w}" for n, w in left_out.items())
        specs, results = _averaging(plan, runner, vg, ("viewgraph", plan.out, None))
        _second_opinion(plan, runner, specs, results, ("viewgraph", plan.out, None), refined=False)
        _refine(plan, runner, results)
        _second_opinion(plan, runner, specs, results, ("viewgraph", plan.out, None))
        names = list(load_manifest(work)["names"])
        peer = _reference(plan, runner, names)
        glomap = _global_reference(plan, runner, names)
        peers = [p for p in (peer, glomap) if p is not None]
        _components(plan, t_start, peers)
        _, path = _report(plan, runner, vg, specs, results, peers, left_out, t_start)
        if not plan.quiet:
            for c in plan.components:
                print(f"component {c['component']} of the view graph ({c['n_cameras']} images, a frame of its own): "
                      f"{plan.out / c['folder'] / 'report.md'}", flush=True)
        return path


def _folder_arg(text: str) -> Path:
    """A path argument that is not empty (``--out ""`` would write the whole run into the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; pass a folder")
    return Path(text)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="run.py", description="Rotation averaging from images, evaluated and reported. "
                                "With no IMAGE_DIR, runs on a rendered default scene.")
    p.add_argument("images", nargs="?", type=Path, default=None, help="folder of images (default: render a scene)")
    p.add_argument("--out", type=_folder_arg, default=None, help="output folder (default: out/<folder name>)")
    p.add_argument("--config", type=Path, default=None, help="YAML config (default: configs/default.yaml)")
    p.add_argument("--methods", nargs="+", default=None, metavar="M",
                   help=f"averaging methods: {registry.tokens_help()}; put IMAGE_DIR first or separate methods "
                        "by commas")
    p.add_argument("--gt", type=Path, default=None, help="true cameras (cameras file, gt_dense_cameras/, *_par.txt, "
                   "COLMAP model, rotations file)")
    p.add_argument("--K", type=Path, default=None, help="intrinsics: K.txt (3×3) or a per-image cameras file")
    p.add_argument("--database", type=Path, default=None, metavar="DB",
                   help="a COLMAP database (COLMAP, pycolmap, hloc, GLOMAP) of IMAGE_DIR: its cameras, keypoints and "
                        "verified matches replace our features and matching")
    p.add_argument("--executor", choices=BACKENDS, default=None,
                   help="where the per-image and per-pair stages run (default: each section's 'executor')")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of an existing Dask scheduler for the per-image and per-pair stages")
    p.add_argument("--no-reference", action="store_true", help="skip the pycolmap reference")
    p.add_argument("--overwrite", action="store_true", help="redo every stage")
    return p


def main_cli(argv: list[str] | None = None) -> int:
    from pipeline.core.cli import run_cli  # noqa: PLC0415

    def body(a: argparse.Namespace) -> int:
        main(a.images, a.out, a.config, a.methods, a.gt, a.K, False if a.no_reference else None, a.overwrite, a.quiet,
             a.database, a.executor, a.scheduler)
        return 0

    return run_cli(body, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main_cli())
