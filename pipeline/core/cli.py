"""Command-line plumbing: logging, one-line errors, and options built from a config.

A failure on bad input prints ``error: <message>`` on one line and exits with
code 2; ``--verbose`` keeps the traceback. :func:`add_config_args` turns every
field of a :class:`pipeline.core.config.Config` into an option, so a stage's
command line and its YAML section always agree.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import sys
import typing
from pathlib import Path
from typing import Any, Callable, Literal, Sequence, get_args, get_origin

from pipeline.core.config import Config, load_yaml, stage_config
from pipeline.core.errors import PipelineError

__all__ = ["add_common_args", "setup_logging", "run_cli", "add_config_args", "config_from_args"]


def add_common_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging and full tracebacks")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only, no progress bars")


def setup_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr, force=True)


def run_cli(body: Callable[[argparse.Namespace], int | None], parser: argparse.ArgumentParser,
            argv: Sequence[str] | None = None) -> int:
    """Parse ``argv``, run ``body(args)`` and turn expected failures into one line + exit 2."""
    add_common_args(parser)
    args = parser.parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    previous = _terminate_as_interrupt()
    try:
        rc = body(args)
    except Terminated:
        print("error: terminated; finished stages are kept and a re-run resumes", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("error: interrupted; finished stages are kept and a re-run resumes", file=sys.stderr)
        return 130
    except (PipelineError, OSError, ValueError, MemoryError) as exc:
        if args.verbose:
            raise
        msg = " ".join(str(exc).split()) or type(exc).__name__
        if isinstance(exc, MemoryError):
            msg = f"out of memory ({msg}); the input is too large for this machine"
        print(f"error: {msg}", file=sys.stderr)
        return 2
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return int(rc or 0)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C's KeyboardInterrupt is: the same clean-up, then one line."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated()


def _terminate_as_interrupt() -> Any:
    """Make SIGTERM raise :class:`Terminated` in the main thread; returns the handler it replaced (None off the main
    thread). pycolmap's glog installs a handler that dumps a native stack trace on SIGTERM and leaves temporary
    files: it is imported first, so that this one comes after it."""
    try:
        import pycolmap  # noqa: F401, PLC0415 - its import installs glog's signal handlers
    except ImportError:  # pragma: no cover
        pass
    try:
        return signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread: signals cannot be handled here
        return None


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_config_args(parser: argparse.ArgumentParser, cls: type[Config], *, exclude: Sequence[str] = (),
                    group: str | None = None) -> None:
    """One option per field of ``cls`` (``--max-image-size``), defaulting to None (= keep the config's value).

    Values are parsed as strings and checked by the config itself, so the
    command line and YAML give the same messages.
    """
    target = parser.add_argument_group(group) if group else parser
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in exclude:
            continue
        tp = hints[f.name]
        help_ = f.metadata.get("help", "").replace("%", "%%")  # argparse formats help with %
        default = f.default if f.default is not dataclasses.MISSING else "…"
        kw: dict[str, Any] = {"default": None, "dest": f"cfg__{f.name}"}
        if tp is bool:
            kw["action"] = argparse.BooleanOptionalAction
            kw["help"] = f"{help_} (default {str(default).lower()})"
        else:
            choices = _choices(tp)
            if choices is not None:
                kw["choices"] = choices
            kw["type"] = _parse_scalar
            if get_origin(tp) is tuple:
                kw["help"] = f"{help_} (comma-separated; default {','.join(map(str, default)) or 'none'})"
            else:
                kw["help"] = f"{help_} (default {default})"
            kw["metavar"] = f.name.upper() if choices is None else None
        target.add_argument(_flag(f.name), **kw)


def _choices(tp: Any) -> list[Any] | None:
    if get_origin(tp) is Literal:
        return list(get_args(tp))
    return None


def _parse_scalar(s: str) -> Any:
    """Numbers become numbers; anything else stays a string for the config to check."""
    for conv in (int, float):
        try:
            return conv(s)
        except ValueError:
            pass
    if s.lower() in ("none", "null"):
        return None
    return s


def config_from_args(cls: type[Config], args: argparse.Namespace, config_path: Path | None = None,
                     section: str | None = None, **extra: Any) -> Config:
    """The config from an optional YAML file, overridden by the options given on the command line."""
    given = {k[len("cfg__"):]: v for k, v in vars(args).items() if k.startswith("cfg__") and v is not None}
    given.update({k: v for k, v in extra.items() if v is not None})
    return stage_config(cls, load_yaml(config_path), section or cls.SECTION, **given)


