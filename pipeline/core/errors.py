"""Exceptions a user can act on. The command lines print their message on one line."""


class PipelineError(Exception):
    """Base class: bad input or a state the user must fix. Exit code 2 on the CLI."""


class ViewGraphError(PipelineError, ValueError):
    """A view graph that breaks an invariant (see ``ViewGraph.validate``)."""


class InputFileError(PipelineError, ValueError):
    """A file that is missing, unreadable or malformed."""


class ConfigError(PipelineError, ValueError):
    """A configuration value of the wrong type, out of range, or an unknown key."""


class CacheError(PipelineError):
    """A cached output that is missing, truncated or inconsistent: it is recomputed, never trusted."""


class OutputError(PipelineError, OSError):
    """An output that cannot be written where it was asked for (a missing or read-only location), named."""
