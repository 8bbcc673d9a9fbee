"""The errors and warnings of the data contract."""

from __future__ import annotations

from collections.abc import Iterable

from tertiary.core.errors import DataError

__all__ = ["SchemaError", "UnsortedTimeWarning"]


class SchemaError(DataError):
    """A frame breaks its table contract (a :class:`tertiary.core.errors.DataError`).

    ``rows`` holds the input row indices of every offending row (empty for
    table-level problems such as a missing column).
    """

    def __init__(
        self,
        message: str,
        *,
        table: str,
        column: str | None = None,
        problem: str = "",
        rows: Iterable[int] = (),
    ) -> None:
        super().__init__(message)
        self.table = table
        self.column = column
        self.problem = problem
        self.rows = list(rows)


class UnsortedTimeWarning(UserWarning):
    """Times were not increasing within a track; the frame was sorted."""
