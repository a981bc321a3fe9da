"""What the two stages of this room share: readers of their files that fail in one line, and the command line.

Every reader here turns a missing, truncated or malformed file into one
:class:`~pipeline.core.errors.CacheError` (or, for a stage that has not run,
:class:`~pipeline.core.errors.InputFileError`) whose message names the file:
never a ``BadZipFile``, ``KeyError`` or ``TypeError`` traceback.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any, ClassVar, Sequence, TypeVar

import numpy as np

from pipeline.core.cli import add_config_args, config_from_args, run_cli
from pipeline.core.errors import CacheError, InputFileError, PipelineError
from pipeline.core.readers import read_npz as core_read_npz
from pipeline.core.viewgraph import ViewGraph
from pipeline.core.config import Config
from pipeline.stage import RECORD_SUFFIX, Stage, StageRecord, check_output, read_record

__all__ = ["PairStage", "read_npz", "read_viewgraph", "recorded_output", "rerun_hint", "stage_cli"]

C = TypeVar("C", bound=Config)


def read_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file ``path``; :class:`CacheError` naming it if unreadable.

    Args:
        path: the file.
        what: what it should hold, for the message (``"correspondences file"``).
    """
    return core_read_npz(path, what, CacheError)


def read_viewgraph(path: Path) -> ViewGraph:
    """The view graph in ``path`` (cameras without edges allowed); :class:`CacheError` naming it if damaged."""
    try:
        return ViewGraph.load(path, allow_isolated=True)
    except PipelineError as exc:  # InputFileError, ViewGraphError: both name the file
        raise CacheError(" ".join(str(exc).split()).replace("; re-run the stage that wrote it", "")) from None


def rerun_hint(command: str, work: Path) -> str:
    return f"re-run `python -m {command} --work {work}` (it recomputes a damaged result)"


def recorded_output(work: Path, stage: str, name: str, command: str) -> tuple[StageRecord, Path]:
    """The record of ``stage`` in ``work`` and its output ``name``, checked against the recorded size.

    Raises:
        InputFileError: the stage has not run in ``work``.
        CacheError: the record or the output is damaged or missing.
    """
    work = Path(work)
    rec = read_record(work, stage)
    if rec is None:
        raise InputFileError(f"{work / (stage + RECORD_SUFFIX)} not found: run `python -m {command} --work {work}` "
                             "first")
    path = work / name
    if name not in rec.outputs:
        raise CacheError(f"the record of {stage} in {work} does not list {name}; {rerun_hint(command, work)}")
    try:
        check_output(path, rec.outputs[name], rec.digests.get(name))
    except CacheError as exc:
        raise CacheError(f"{exc}; {rerun_hint(command, work)}") from None
    return rec, path


class PairStage(Stage[C]):
    """A stage whose per-pair results live in the item store ``<folder>/<store>``.

    ``run(overwrite=True)`` empties the store first, so that every pair is
    computed again (a plain re-run reuses the pairs already done).
    """

    store: ClassVar[str]

    def run(self, overwrite: bool = False) -> StageRecord:
        if overwrite:
            shutil.rmtree(self.folder / self.store, ignore_errors=True)
        return super().run(overwrite)


def stage_cli(stage_cls: type[Stage], prog: str, description: str, output: str,
              argv: Sequence[str] | None = None) -> int:
    """``python -m <prog> --work WORK [--config YAML] [options of the config] [--overwrite]``.

    Runs the stage in WORK and prints the path of its ``output``.
    """
    cfg_cls: Any = stage_cls.config_cls
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--work", type=Path, required=True, help="the WORK folder of the front end")
    p.add_argument("--config", type=Path, default=None, help=f"YAML config; its '{cfg_cls.SECTION}' section is used")
    add_config_args(p, cfg_cls, exclude=("progress",))
    p.add_argument("--overwrite", action="store_true", help="recompute even if an intact, up-to-date result exists")

    def body(a: argparse.Namespace) -> int:
        cfg = config_from_args(cfg_cls, a, a.config, progress=False if a.quiet else None)
        stage_cls(a.work, cfg).run(overwrite=a.overwrite)
        print(Path(a.work) / output)
        return 0

    return run_cli(body, p, argv)
