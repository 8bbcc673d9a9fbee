"""Named SQL reports over a run database (the ``sql/`` directory, shipped as ``tertiary/sql``).

One report per ``NAME.sql`` file. Each file starts with a header comment: what the report
answers, its columns, and one ``-- param: NAME = DEFAULT  description`` line per parameter
(``DEFAULT`` is a JSON literal: ``null``, a number, ``"text"``). Queries use DuckDB named
parameters ``$NAME``; values are always **bound**, never formatted into the SQL text. A
parameter left out by the caller takes its default (``null`` usually means "no filter"), so
``run_report(store, "accuracy_over_time", method="apriori")`` works.

Every query runs through :func:`query` on a read-only store: only ``SELECT``-type statements
(``SELECT``, ``WITH … SELECT``, ``FROM …``, ``VALUES``, ``SHOW``, ``DESCRIBE``, ``SUMMARIZE``)
and ``EXPLAIN`` are accepted, the database is attached ``READ_ONLY`` and file-system access
from SQL (``COPY … TO``, ``read_csv`` …) is switched off for the connection.
"""

from __future__ import annotations

import io
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import duckdb
import polars as pl

from tertiary.store import RunStore, write_parquet_atomic, write_text_atomic

__all__ = [
    "ReadOnlyQueryError",
    "SqlReport",
    "sql_dir",
    "list_reports",
    "load_report",
    "run_report",
    "query",
    "open_read_only",
    "export_frame",
    "frame_to_csv",
]

_PARAM_LINE = re.compile(r"^--\s*param:\s*([A-Za-z_][A-Za-z0-9_]*)\s*=\s*(.+?)(?:\s{2,}(.*))?$")
_PARAM_USE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
_READ_TYPES = {"SELECT", "EXPLAIN"}


class ReadOnlyQueryError(ValueError):
    """A query that would change something was refused."""


@dataclass(frozen=True)
class SqlReport:
    """One named report: its SQL text, header description and parameter defaults."""

    name: str
    path: Path
    sql: str
    description: str
    params: dict[str, Any] = field(default_factory=dict)
    param_help: dict[str, str] = field(default_factory=dict)

    @property
    def summary(self) -> str:
        """The first sentence of the description (up to the first colon or full stop)."""
        first = self.description.split("\n\n")[0].replace("\n", " ")
        m = re.match(r"(.+?[.:])(\s|$)", first)
        return (m.group(1) if m else first).rstrip(":.")

    def bind(self, params: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Parameter values for this query: defaults updated by ``params``; unknown names are an
        error (they would otherwise be silently ignored)."""
        given = dict(params or {})
        unknown = sorted(set(given) - set(self.params))
        if unknown:
            known = ", ".join(self.params) or "none"
            raise KeyError(f"report {self.name!r} has no parameter(s) {', '.join(unknown)}; its parameters: {known}")
        return {**self.params, **given}


def sql_dir() -> Path:
    """Directory of the named reports: ``tertiary/sql`` in an installed package, the repository's
    ``sql/`` in a source checkout."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "sql", here.parent / "sql"):
        if candidate.is_dir() and any(candidate.glob("*.sql")):
            return candidate
    raise FileNotFoundError(f"no SQL report directory next to {here}")


def _parse(path: Path) -> SqlReport:
    text = path.read_text(encoding="utf-8")
    header: list[str] = []
    params: dict[str, Any] = {}
    helps: dict[str, str] = {}
    for line in text.splitlines():
        if not line.startswith("--"):
            break
        m = _PARAM_LINE.match(line.strip())
        if m:
            name, default, helptext = m.group(1), m.group(2).strip(), (m.group(3) or "").strip()
            try:
                params[name] = json.loads(default)
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path.name}: default of parameter {name!r} is not a JSON literal: {default}") from exc
            helps[name] = helptext
        else:
            header.append(line[2:].strip())
    used = set(_PARAM_USE.findall(_strip_comments(text)))
    if used != set(params):
        raise ValueError(f"{path.name}: parameters used {sorted(used)} but declared {sorted(params)} "
                         "(declare each as '-- param: NAME = DEFAULT')")
    description = "\n".join(header).strip()
    return SqlReport(path.stem, path, text, description, params, helps)


def _strip_comments(sql: str) -> str:
    return "\n".join(line.split("--", 1)[0] for line in sql.splitlines())


def list_reports() -> list[SqlReport]:
    """Every named report, sorted by name."""
    return [_parse(p) for p in sorted(sql_dir().glob("*.sql"))]


def load_report(name: str) -> SqlReport:
    """The report ``name`` (file ``sql/<name>.sql``); KeyError naming the choices if absent."""
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", name or ""):
        raise KeyError(f"invalid report name {name!r}")
    path = sql_dir() / f"{name}.sql"
    if not path.is_file():
        names = ", ".join(p.stem for p in sorted(sql_dir().glob("*.sql")))
        raise KeyError(f"no SQL report {name!r}; available: {names}")
    return _parse(path)


def open_read_only(run_dir: str | os.PathLike[str]) -> RunStore:
    """Open a run database read-only, with file-system access from SQL switched off."""
    store = RunStore.open(run_dir, read_only=True)
    try:
        store.con.execute("SET enable_external_access = false")
        store.con.execute("SET lock_configuration = true")
    except BaseException:
        store.close()
        raise
    return store


def _check_read_only(con: duckdb.DuckDBPyConnection, sql: str) -> None:
    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as exc:
        raise duckdb.ParserException(str(exc)) from exc
    if not statements:
        raise ReadOnlyQueryError("empty query")
    for st in statements:
        kind = str(st.type).rsplit(".", 1)[-1]
        if kind not in _READ_TYPES:
            raise ReadOnlyQueryError(
                f"refused a {kind} statement: the run database is opened read-only and only queries "
                "(SELECT, WITH … SELECT, FROM, VALUES, SHOW, DESCRIBE, SUMMARIZE, EXPLAIN) may run")


def query(store: RunStore, sql: str, params: Mapping[str, Any] | None = None) -> pl.DataFrame:
    """Run read-only ``sql`` with bound ``params`` and return the last statement's result."""
    _check_read_only(store.con, sql)
    return store.sql(sql, dict(params) if params else None)


def run_report(store: RunStore, name: str | SqlReport, params: Mapping[str, Any] | None = None,
               **kwargs: Any) -> pl.DataFrame:
    """Run the named report on ``store`` with its defaults overridden by ``params``/``kwargs``."""
    report = name if isinstance(name, SqlReport) else load_report(name)
    values = report.bind({**(params or {}), **kwargs})
    return query(store, report.sql, values or None)


# --------------------------------------------------------------------------- export


def _flat(frame: pl.DataFrame) -> pl.DataFrame:
    """Nested columns (lists, arrays, structs) as JSON text, for CSV."""
    nested = [c for c, t in frame.schema.items() if isinstance(t, (pl.List, pl.Array, pl.Struct))]
    if not nested:
        return frame
    return frame.with_columns(
        pl.Series(c, [None if v is None else json.dumps(v, default=str) for v in frame[c].to_list()], pl.String)
        for c in nested)


def frame_to_csv(frame: pl.DataFrame) -> str:
    """CSV text of ``frame`` (nested values as JSON)."""
    buf = io.StringIO()
    _flat(frame).write_csv(buf)
    return buf.getvalue()


def export_frame(frame: pl.DataFrame, path: str | os.PathLike[str], fmt: str) -> Path:
    """Write ``frame`` to ``path`` atomically as ``csv`` or ``parquet``."""
    if fmt == "csv":
        return write_text_atomic(path, frame_to_csv(frame))
    if fmt == "parquet":
        return write_parquet_atomic(frame, path)
    raise ValueError(f"unknown export format {fmt!r}; use csv or parquet")
