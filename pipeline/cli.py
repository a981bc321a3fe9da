"""Shared command-line plumbing: logging setup and one-line errors.

A failure on bad input prints ``error: <message>`` on one line and exits with
code 2; ``--verbose`` keeps the traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Callable, Sequence

from .errors import PipelineError


def add_common_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging and full tracebacks")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only, no progress bars")


def setup_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr, force=True)


def run_cli(body: Callable[[argparse.Namespace], int | None], parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> int:
    """Parse ``argv``, run ``body(args)`` and turn expected failures into one line + exit 2."""
    add_common_args(parser)
    args = parser.parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    try:
        rc = body(args)
    except KeyboardInterrupt:
        print("error: interrupted; finished stages are kept and a re-run resumes", file=sys.stderr)
        return 130
    except (PipelineError, OSError, ValueError) as exc:
        if args.verbose:
            raise
        msg = " ".join(str(exc).split()) or type(exc).__name__
        print(f"error: {msg}", file=sys.stderr)
        return 2
    return int(rc or 0)
