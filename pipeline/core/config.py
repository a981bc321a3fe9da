"""Typed, frozen configuration: validated in full when it is built, before any work.

Every stage and every averaging method has one frozen, keyword-only dataclass
derived from :class:`Config`. Its fields are declared with :func:`option`, which
carries the help text, the bounds and whether the option affects the result::

    @dataclass(frozen=True, kw_only=True)
    class MatchingConfig(Config):
        ratio: float = option(0.8, "Lowe's ratio test", gt=0, le=1)
        mutual: bool = option(True, "keep mutual nearest neighbours only")
        workers: int = option(2, "threads", ge=1, runtime=True)

What the type annotation says is enforced strictly, because YAML is forgiving:

- ``bool`` accepts only ``true``/``false``; the string ``"false"`` is an error
  (it would otherwise be truthy);
- ``int`` accepts integers (not booleans, not ``1.5``; an integral number such as
  ``8192.0`` or ``1e3`` is accepted as 8192 and 1000);
- ``float`` accepts finite numbers only (no ``.nan``/``.inf``), and not strings
  such as ``"1e-0"`` (which YAML 1.1 reads as a string);
- ``Literal[...]`` accepts one of its values; ``tuple[str, ...]`` accepts a list,
  or a comma-separated string (``methods: irls, sdp``) but never splits a scalar
  into characters; ``X | None`` accepts ``null``.

An unknown key is an error whose message lists the allowed keys. Options marked
``runtime=True`` (workers, progress) never enter :meth:`Config.fingerprint`, so
changing them never invalidates a cache.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import types
import typing
from pathlib import Path
from typing import Any, ClassVar, Literal, TypeVar, Union, get_args, get_origin

import yaml

from pipeline.core.errors import ConfigError, InputFileError

__all__ = ["Config", "option", "load_yaml", "config_from_dict", "stage_config", "check_sections"]

C = TypeVar("C", bound="Config")
_FLOAT = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
_MISSING = dataclasses.MISSING
_MAX_INT = 2 ** 31 - 1


def option(default: Any = _MISSING, help: str = "", *, ge: float | None = None, gt: float | None = None,
           le: float | None = None, lt: float | None = None, runtime: bool = False,
           default_factory: Any = _MISSING) -> Any:
    """A config field with its help text, bounds and fingerprint role.

    Args:
        default: the default value.
        help: one line for ``--help`` and error messages.
        ge, gt, le, lt: numeric bounds (inclusive / exclusive).
        runtime: True for options that only change how work runs (workers,
            progress): they never enter the fingerprint.
        default_factory: as in :func:`dataclasses.field`.
    """
    meta = {"help": help, "ge": ge, "gt": gt, "le": le, "lt": lt, "runtime": runtime}
    if default_factory is not _MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin is tuple:
        return f"a list of {_type_name(get_args(tp)[0])}"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """``value`` as type ``tp``, or :class:`ConfigError` saying what was expected."""
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}={value!r} but expected {_type_name(tp)}")
    if origin is Literal:
        allowed = get_args(tp)
        if isinstance(value, str) and value.strip().lower() in [str(a).lower() for a in allowed]:
            return next(a for a in allowed if str(a).lower() == value.strip().lower())
        if not isinstance(value, bool) and value in allowed:
            return value
        # YAML 1.1 reads an unquoted off / on (no / yes) as a boolean: give back the word where it is a choice
        words = ({False: ("off", "no", "false"), True: ("on", "yes", "true")}[value] if isinstance(value, bool)
                 else ())
        for word in words:
            if word in allowed:
                return word
        raise ConfigError(f"{where}={value!r} but expected one of {', '.join(repr(a) for a in allowed)}")
    if origin is tuple:
        (elem, *rest) = get_args(tp)
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if value is None:
            value = []
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}={value!r} but expected a list ({_type_name(tp)})")
        return tuple(_coerce(v, elem, f"{where}[{k}]") for k, v in enumerate(value))
    if tp is bool:
        if isinstance(value, bool):
            return value
        hint = " (write true or false without quotes)" if isinstance(value, str) else ""
        raise ConfigError(f"{where}={value!r} but expected true or false{hint}")
    if tp is int:
        given = value
        if isinstance(value, str) and _FLOAT.match(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e3 as a string; an integral number is accepted below
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}={given!r} but expected an integer")
        if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
            raise ConfigError(f"{where}={given!r} but expected an integer")
        if abs(value) > _MAX_INT:  # C libraries (OpenCV, pycolmap) take 32-bit integers
            raise ConfigError(f"{where}={given!r} but expected an integer of magnitude at most {_MAX_INT}")
        return int(value)
    if tp is float:
        if isinstance(value, str) and _FLOAT.match(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e-3 (no decimal point) as a string
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}={value!r} but expected a number")
        if not math.isfinite(value):
            raise ConfigError(f"{where}={value!r} but expected a finite number")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}={value!r} but expected a string")
        return value
    if tp is Path:
        if not isinstance(value, (str, os.PathLike)):
            raise ConfigError(f"{where}={value!r} but expected a path")
        return Path(value)
    raise ConfigError(f"{where}: unsupported option type {tp!r}")  # a programming error in a Config class


@dataclasses.dataclass(frozen=True, kw_only=True)
class Config:
    """Base of every typed, frozen configuration.

    Subclasses declare fields with :func:`option` and may add cross-field checks
    in :meth:`check`. ``SECTION`` names the YAML section (used in messages).
    """

    SECTION: ClassVar[str] = "config"

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            where = f"[{self.SECTION}] {f.name}"
            value = _coerce(getattr(self, f.name), hints[f.name], where)
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                m = f.metadata
                bad = ((m.get("ge") is not None and value < m["ge"], f">= {m.get('ge')}"),
                       (m.get("gt") is not None and value <= m["gt"], f"> {m.get('gt')}"),
                       (m.get("le") is not None and value > m["le"], f"<= {m.get('le')}"),
                       (m.get("lt") is not None and value >= m["lt"], f"< {m.get('lt')}"))
                for failed, what in bad:
                    if failed:
                        raise ConfigError(f"{where}={value!r} but expected {what}"
                                          + (f" ({m['help']})" if m.get("help") else ""))
            object.__setattr__(self, f.name, value)
        self.check()

    def check(self) -> None:
        """Cross-field checks; raise :class:`ConfigError`. Override where needed."""

    # ----------------------------------------------------------------- helpers
    @classmethod
    def from_dict(cls: type[C], data: dict[str, Any] | None, where: str | None = None) -> C:
        """Build from a mapping; an unknown key raises with the allowed list."""
        where = where or f"[{cls.SECTION}]"
        if data is not None and not isinstance(data, dict):
            raise ConfigError(f"{where}: expected a mapping of options, got {type(data).__name__}")
        data = dict(data or {})
        allowed = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(data) - set(allowed))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed keys are {allowed}")
        return cls(**data)

    def replace(self: C, **changes: Any) -> C:
        """A copy with ``changes`` applied (``None`` values are ignored) and validated."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def as_dict(self) -> dict[str, Any]:
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def result_dict(self) -> dict[str, Any]:
        """The options that affect the result (no runtime options)."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)
                if not f.metadata.get("runtime", False)}

    def fingerprint(self) -> str:
        """A stable hash of :meth:`result_dict` (and the class name)."""
        blob = json.dumps([type(self).__name__, self.result_dict()], sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:16]

    @classmethod
    def options(cls) -> list[dataclasses.Field]:
        return list(dataclasses.fields(cls))


def _plain(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    if isinstance(v, Path):
        return str(v)
    return v


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (plain YAML keeps the last one silently: a
    second ``matching:`` section would drop the first one's options)."""


def _unique_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            first = seen.setdefault(key, key_node.start_mark.line + 1)
        except TypeError:  # an unhashable key: the constructor below names it
            continue
        if first != key_node.start_mark.line + 1:
            raise yaml.constructor.ConstructorError(
                None, None, f"{key!r} is given twice in one mapping (lines {first} and {key_node.start_mark.line + 1}); "
                "YAML would keep only the last: merge them", None)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def load_yaml(path: str | os.PathLike | None) -> dict[str, dict[str, Any]]:
    """Read a YAML config file into ``{section: {key: value}}``; ``None`` gives ``{}``."""
    if path is None:
        return {}
    path = Path(path)
    if path.is_dir():
        raise InputFileError(f"config file {path} is a folder, not a file")
    if not path.is_file():
        raise InputFileError(f"config file {path} does not exist")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader) or {}  # noqa: S506 - a SafeLoader
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except yaml.YAMLError as exc:
        raise InputFileError(f"{path} is not valid YAML: {' '.join(str(exc).split())[:160]}") from None
    except RecursionError:
        raise InputFileError(f"{path} is not a config: it is nested too deeply") from None
    if not isinstance(data, dict):
        raise InputFileError(f"{path}: expected a mapping of section name to a mapping of options, "
                             f"got a {type(data).__name__}")
    for k, v in data.items():
        if not (isinstance(v, dict) or v is None):
            raise InputFileError(f"{path}: section {str(k)!r} must be a mapping of options (key: value), "
                                 f"got {type(v).__name__} {str(v)[:40]!r}")
    return {str(k): (v or {}) for k, v in data.items()}


def check_sections(yaml_data: dict[str, Any], allowed: list[str] | tuple[str, ...], path: Any = "config") -> None:
    """An unknown section is an error that lists the allowed ones."""
    unknown = sorted(set(yaml_data) - set(allowed))
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; allowed sections are {sorted(allowed)}")


def config_from_dict(cls: type[C], data: dict[str, Any] | None, where: str | None = None) -> C:
    """``cls.from_dict(data, where)``; plain dataclasses (not yet migrated) get the unknown-key check only."""
    if isinstance(cls, type) and issubclass(cls, Config):
        return cls.from_dict(data, where)
    data = dict(data or {})
    allowed = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed keys are {allowed}")
    return cls(**data)


def config_hash(cfg: Any, n: int = 8, exclude: tuple[str, ...] = ()) -> str:
    """Short stable hash of a dataclass config (TRANSITIONAL: replaced by Config.fingerprint)."""
    d = dataclasses.asdict(cfg)
    for k in exclude:
        d.pop(k, None)
    blob = json.dumps(d, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:n]


def stage_config(cls: type[C], yaml_data: dict[str, Any], section: str | None = None, **overrides: Any) -> C:
    """The config of one section from loaded YAML, with non-None overrides applied."""
    section = section or cls.SECTION
    d = dict(yaml_data.get(section) or {})
    d.update({k: v for k, v in overrides.items() if v is not None})
    return config_from_dict(cls, d, where=f"[{section}]")
