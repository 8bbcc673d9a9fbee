"""Expected failures, each with a one-line message for the user.

The command line turns these into one line on stderr and an exit code (never a traceback,
unless ``--debug``); anything else is a bug and keeps its traceback.

Exit codes: 0 success, 1 unexpected internal error, 2 a bad option or argument
(:class:`OptionError`, and typer's own usage errors), 3 bad input data or an unreadable or
unwritable file (:class:`DataError`), 4 a refusal to allocate or run beyond a limit
(:class:`ResourceError`).
"""

from __future__ import annotations


class TertiaryError(Exception):
    """An expected failure; ``str(exc)`` is the one line shown to the user."""

    exit_code = 1


class OptionError(TertiaryError, ValueError):
    """A command-line option, configuration field or API argument is out of its domain."""

    exit_code = 2

    def __init__(self, message: str, *, option: str | None = None) -> None:
        super().__init__(f"{option}: {message}" if option else message)
        self.option = option


class DataError(TertiaryError, ValueError):
    """A dataset, table, column or file cannot be used (names which, and why)."""

    exit_code = 3

    def __init__(self, message: str, *, path: str | None = None) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


class ResourceError(TertiaryError, MemoryError):
    """A computation would exceed a configured bound (memory, cells, time); refused before it starts."""

    exit_code = 4
