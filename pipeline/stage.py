"""The stage contract: every stage of the pipeline answers the same questions the same way.

A stage (:class:`Stage`) has

- a typed, frozen config (:class:`pipeline.core.config.Config`), validated when
  it is built, before any work;
- inputs: the fingerprints of the stages it reads and of the user's files
  (:meth:`Stage.inputs`);
- a fingerprint: a hash of its name, version, the result-affecting options and
  its inputs only, so that ``workers`` or progress never invalidate a cache, and
  a changed option recomputes exactly the stages downstream of it;
- outputs, written atomically, and a sidecar record ``<folder>/<name>.record.json``
  that holds the fingerprint, the options, the inputs, the size and CRC-32 of every
  output and a summary (counts, time);
- :meth:`Stage.verify`, which checks a cached output when it is read (its size and
  checksum, its arrays, its camera count). A damaged output, even one damaged without a
  change of size, is recomputed with a one-line warning, never reused and never fatal;
- skip or overwrite: :meth:`Stage.run` reuses an intact cached result unless
  ``overwrite``;
- a command line built from the config (:func:`pipeline.core.cli.add_config_args`).

Stages chain through their records: a stage reads its upstream record's
fingerprint, so a re-run after any change upstream recomputes it.
"""

from __future__ import annotations

import abc
import contextlib
import hashlib
import json
import logging
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar

from pipeline.core.atomic import check_writable, remove_stale_temporaries, write_json
from pipeline.core.config import Config
from pipeline.core.errors import CacheError, InputFileError
from pipeline.core.readers import read_json

__all__ = ["Stage", "StageRecord", "read_record", "fingerprint_of", "file_fingerprint", "output_digest", "check_output",
           "RECORD_SUFFIX"]

logger = logging.getLogger(__name__)

RECORD_SUFFIX = ".record.json"
RECORD_FORMAT = "rotavg-stage-record"
C = TypeVar("C", bound=Config)


def fingerprint_of(*parts: Any) -> str:
    """A stable 16-hex-digit hash of JSON-serializable parts."""
    blob = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


def output_digest(path: Path) -> str:
    """The CRC-32 of a file's bytes (8 hex digits): what a record keeps of each output, to catch damage that keeps
    its size (a byte overwritten in a JSON, a COLMAP model or a rotations file). CRC-32 reads at disk speed (4 GB/s
    here against 1.8 for SHA-1) and is meant for exactly this: accidental damage, not tampering."""
    crc = 0
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            crc = zlib.crc32(block, crc)
    return f"{crc & 0xFFFFFFFF:08x}"


def check_output(path: Path, size: int, digest: str | None) -> None:
    """An output as its record describes it: present, of its recorded size and, where one is recorded, of its CRC-32
    (:func:`output_digest`); :class:`CacheError` naming it otherwise."""
    if not path.is_file():
        raise CacheError(f"{path} is missing")
    if path.stat().st_size != size:
        raise CacheError(f"{path} has {path.stat().st_size} bytes, not the {size} recorded (truncated or overwritten)")
    if digest is not None and output_digest(path) != digest:
        raise CacheError(f"{path} has changed since it was written (its CRC-32 is not the one recorded)")


def file_fingerprint(path: Path) -> str:
    """A 16-hex-digit hash of a file's bytes: the fingerprint of a user file a stage reads.

    Raises:
        InputFileError: the file is missing or unreadable.
    """
    path = Path(path)
    h = hashlib.sha1()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise InputFileError(f"cannot read {path} ({exc.strerror or exc})") from None
    return h.hexdigest()[:16]


@dataclass
class StageRecord:
    """The sidecar record of one finished stage.

    Attributes:
        stage: the stage name.
        version: the stage's algorithm version (bumped when results change).
        fingerprint: hash of name, version, result-affecting options and inputs.
        config: every option, runtime ones included (for the reader).
        inputs: ``{input name: fingerprint}``.
        outputs: ``{output path relative to the folder: size in bytes}``.
        digests: ``{output path relative to the folder: CRC-32}`` (:func:`output_digest`; empty in a record
            of an older version, which is then recomputed).
        summary: counts and figures of the run.
        time_s: wall time of the computation.
        reused: True when this run reused the cached result (not stored).
    """

    stage: str
    version: int
    fingerprint: str
    config: dict[str, Any]
    inputs: dict[str, str]
    outputs: dict[str, int]
    summary: dict[str, Any] = field(default_factory=dict)
    time_s: float = 0.0
    reused: bool = False
    digests: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"format": RECORD_FORMAT, "stage": self.stage, "version": self.version,
                "fingerprint": self.fingerprint, "config": self.config, "inputs": self.inputs,
                "outputs": self.outputs, "digests": self.digests, "summary": self.summary, "time_s": self.time_s}


def read_record(folder: Path, name: str, record_name: str | None = None) -> StageRecord | None:
    """The record of stage ``name`` in ``folder``; None if absent; :class:`CacheError` if unreadable.

    ``record_name`` names the file when one stage has several records in a folder
    (one per averaging method); it defaults to ``name``.
    """
    path = Path(folder) / f"{record_name or name}{RECORD_SUFFIX}"
    if not path.is_file():
        return None
    d = read_json(path, "the record", CacheError)
    try:
        if not isinstance(d, dict) or d.get("format") != RECORD_FORMAT or d.get("stage") != name:
            raise ValueError("not a stage record")
        outputs = {str(k): int(v) for k, v in dict(d["outputs"]).items()}
        digests = {str(k): str(v) for k, v in dict(d.get("digests") or {}).items()}
        return StageRecord(stage=name, version=int(d["version"]), fingerprint=str(d["fingerprint"]),
                           config=dict(d.get("config") or {}), inputs={str(k): str(v) for k, v in dict(d["inputs"]).items()},
                           outputs=outputs, summary=dict(d.get("summary") or {}), time_s=float(d.get("time_s", 0.0)),
                           digests=digests)
    except (ValueError, KeyError, TypeError, OverflowError) as exc:
        raise CacheError(f"the record {path} is damaged ({' '.join(str(exc).split())[:80]})") from None


class Stage(abc.ABC, Generic[C]):
    """One stage: subclasses set ``name``, ``title``, ``config_cls`` and implement the four methods.

    Args:
        folder: where the stage writes its outputs and record (the WORK folder
            for the front end, OUT for the later stages).
        config: the stage's options.
    """

    name: ClassVar[str]
    title: ClassVar[str]
    config_cls: ClassVar[type[Config]]
    version: ClassVar[int] = 1

    def __init__(self, folder: Path, config: C | None = None, record_name: str | None = None) -> None:
        self.folder = Path(folder)
        self.record_name = record_name or self.name
        self.overwrite = False  # set by run(): per-item stages then recompute every item too
        self.config: C = config if config is not None else self.config_cls()  # type: ignore[assignment]
        if not isinstance(self.config, self.config_cls):
            raise TypeError(f"{type(self).__name__} needs a {self.config_cls.__name__}, got {type(self.config).__name__}")

    # ---------------------------------------------------------- to implement
    @abc.abstractmethod
    def inputs(self) -> dict[str, str]:
        """``{name: fingerprint}`` of everything this stage reads (upstream records, user files)."""

    @abc.abstractmethod
    def compute(self) -> tuple[list[Path], dict[str, Any]]:
        """Do the work; write the outputs atomically; return ``(output paths, summary)``."""

    def verify(self, record: StageRecord) -> None:
        """Check the cached outputs beyond their sizes (arrays, counts); raise :class:`CacheError`.

        The default checks nothing more; stages whose outputs others read override it.
        """

    # ------------------------------------------------------------ the contract
    @property
    def record_path(self) -> Path:
        return self.folder / f"{self.record_name}{RECORD_SUFFIX}"

    def fingerprint(self, inputs: dict[str, str] | None = None) -> str:
        inputs = self.inputs() if inputs is None else inputs
        return fingerprint_of(self.name, self.version, self.config.fingerprint(), sorted(inputs.items()))

    def upstream(self, name: str, folder: Path | None = None, record_name: str | None = None) -> StageRecord:
        """The record of the stage ``name`` that this one reads; a clear error if it has not run."""
        folder = self.folder if folder is None else Path(folder)
        try:
            rec = read_record(folder, name, record_name)
        except CacheError as exc:
            raise InputFileError(f"{exc}; re-run `python -m pipeline.{name}`") from None
        if rec is None:
            raise InputFileError(f"{folder} has no result of the '{name}' stage, which '{self.name}' needs; "
                                 f"run `python -m pipeline.{name}` on it first")
        return rec

    def cached(self, inputs: dict[str, str] | None = None) -> StageRecord | None:
        """The intact cached record whose fingerprint matches, else None (with why, logged)."""
        fp = self.fingerprint(inputs)
        try:
            rec = read_record(self.folder, self.name, self.record_name)
        except CacheError as exc:
            logger.warning("%s; recomputing %s", exc, self.name)
            return None
        if rec is None:
            return None
        if rec.fingerprint != fp:
            logger.info("%s: inputs or options changed since the cached result; recomputing", self.name)
            return None
        if set(rec.digests) != set(rec.outputs):
            logger.info("%s: the cached result was recorded without its outputs' checksums (an older version); "
                        "recomputing", self.name)
            return None
        try:
            for rel, size in rec.outputs.items():
                check_output(self.folder / rel, size, rec.digests[rel])
            self.verify(rec)
        except (CacheError, InputFileError, OSError, ValueError, KeyError) as exc:
            logger.warning("the cached result of %s is damaged (%s); recomputing it",
                           self.name, " ".join(str(exc).split()))
            return None
        rec.reused = True
        return rec

    def run(self, overwrite: bool = False) -> StageRecord:
        """Reuse the intact cached result, or compute and record a new one."""
        self.overwrite = overwrite
        inputs = self.inputs()
        if not overwrite:
            rec = self.cached(inputs)
            if rec is not None:
                logger.info("%s: up to date, nothing to compute; skipping (reusing %s; --overwrite redoes it)",
                            self.name, self.record_path)
                return rec
        made = [p for p in [self.folder, *self.folder.parents] if not p.exists()]
        blocking = next((p for p in [self.folder, *self.folder.parents] if p.exists() and not p.is_dir()), None)
        if blocking is not None:  # mkdir would say only "[Errno 17] File exists"
            raise InputFileError(f"{blocking} is a file, not a folder: {self.name} writes its results into "
                                 f"{self.folder}; pass a folder (or remove the file)")
        try:  # before the work: a result it could not write would be lost
            check_writable(self.folder, f"{self.name} writes its results there")
        except OSError:
            for p in made:
                with contextlib.suppress(OSError):
                    p.rmdir()
            raise
        remove_stale_temporaries(self.folder)
        t0 = time.perf_counter()
        try:
            paths, summary = self.compute()
        except BaseException:
            for p in made:  # a stage that failed on its input leaves no empty folder behind
                with contextlib.suppress(OSError):
                    p.rmdir()
            raise
        dt = time.perf_counter() - t0
        outputs, digests = {}, {}
        for p in paths:
            p = Path(p)
            rel = str(p.resolve().relative_to(self.folder.resolve()))
            outputs[rel], digests[rel] = p.stat().st_size, output_digest(p)
        rec = StageRecord(stage=self.name, version=self.version, fingerprint=self.fingerprint(inputs),
                          config=self.config.as_dict(), inputs=inputs, outputs=outputs, summary=summary, time_s=dt,
                          digests=digests)
        write_json(self.record_path, rec.to_json())
        return rec
