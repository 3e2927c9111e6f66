"""The exception hierarchy. The CLI turns any ClcgraphError into one line on stderr.

Messages name the file, topic or sensor involved and, where it helps, what to do.
This module imports nothing, so every module may import it (config.py's ConfigError is an
InputError; the layering test allows errors.py where it allows nothing else of ours).
"""


class ClcgraphError(Exception):
    """Base of every error clcgraph raises on purpose."""

    exit_code = 2


class InputError(ClcgraphError):
    """Bad user input: a missing file, a wrong option, an unknown config key."""


class DataError(ClcgraphError):
    """Input data that cannot be decoded or makes no sense (bag, message, model)."""


class DegenerateError(ClcgraphError):
    """The data cannot determine the answer: a disconnected sensor, an unobservable direction."""


class SolveError(ClcgraphError):
    """The optimization failed to produce a trustworthy answer."""


class DependencyError(ClcgraphError):
    """A required external tool or library is missing or broken."""
