"""Stage configuration: one frozen dataclass per stage, loadable from YAML.

A YAML config file has one mapping per stage, keyed by the stage name
(``features``, ``matching``, ``two_view``, ``two_view_ba``, ``averaging``,
``sdp``, ``reference``, ``run``). An unknown stage or key is an error whose
message lists the allowed ones.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any, TypeVar

import yaml

from .errors import InputFileError

T = TypeVar("T")


def config_from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "config") -> T:
    """Build the dataclass ``cls`` from a mapping; unknown keys raise with the allowed list."""
    data = dict(data or {})
    allowed = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise InputFileError(f"{where}: unknown key(s) {unknown}; allowed keys are {allowed}")
    return cls(**data)


def load_yaml(path: str | os.PathLike | None) -> dict[str, Any]:
    """Read a YAML config file into ``{stage: {key: value}}``; ``None`` gives ``{}``."""
    if path is None:
        return {}
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"config file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputFileError(f"{path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or not all(isinstance(v, dict) or v is None for v in data.values()):
        raise InputFileError(f"{path}: expected a mapping of stage name to a mapping of options")
    return {k: (v or {}) for k, v in data.items()}


def stage_config(cls: type[T], yaml_data: dict[str, Any], stage: str, **overrides: Any) -> T:
    """The config of one stage from loaded YAML, with non-None overrides applied."""
    d = dict(yaml_data.get(stage, {}))
    d.update({k: v for k, v in overrides.items() if v is not None})
    return config_from_dict(cls, d, where=f"[{stage}]")


def config_hash(cfg: Any, n: int = 8, exclude: tuple[str, ...] = ()) -> str:
    """A short stable hash of a dataclass config, for cache file names.

    Args:
        cfg: a dataclass instance.
        n: hex digits kept.
        exclude: fields that do not change the result (e.g. ``workers``).
    """
    d = dataclasses.asdict(cfg)
    for k in exclude:
        d.pop(k, None)
    blob = json.dumps(d, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:n]
