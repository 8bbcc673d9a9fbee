"""Named SQL reports over a run database (the ``sql/`` directory, shipped as ``tertiary/sql``).

One report per ``NAME.sql`` file. Each file starts with a header comment: what the report
answers, its columns, and one ``-- param: NAME = DEFAULT  description`` line per parameter
(``DEFAULT`` is a JSON literal: ``null``, a number, ``"text"``). Queries use DuckDB named
parameters ``$NAME``; values are always **bound**, never formatted into the SQL text. A
parameter left out by the caller takes its default (``null`` usually means "no filter"), so
``run_report(store, "accuracy_over_time", method="apriori")`` works.

Every query runs through :func:`query` on a read-only store: only ``SELECT``-type statements
(``SELECT``, ``WITH … SELECT``, ``FROM …``, ``VALUES``, ``SHOW``, ``DESCRIBE``, ``SUMMARIZE``,
``PIVOT``/``UNPIVOT``), ``EXPLAIN`` and the informational ``PRAGMA`` statements (``table_info`` …) are
accepted, the database is attached ``READ_ONLY``, file-system access from SQL (``COPY … TO``,
``read_csv`` …) is switched off and the configuration locked for the connection, and a statement
that runs longer than its timeout is interrupted.

Parameter values are checked against their domain before a report runs: a parameter that names
something in the run (``method``, ``segment``, ``stage``, ``filter``, ``radar_id``, ``run``,
``metric``) must name something the run holds — otherwise the error lists what it holds, instead
of an empty answer — and numeric parameters must be finite numbers.
"""

from __future__ import annotations

import io
import json
import os
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import duckdb
import polars as pl

from tertiary.core.errors import DataError, OptionError, ResourceError
from tertiary.store.files import write_parquet_atomic, write_text_atomic
from tertiary.store.run_store import RunStore, utc_times

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
#: PRAGMAs that only describe the database (the configuration is locked anyway)
_READ_PRAGMAS = {"table_info", "show_tables", "show_tables_expanded", "database_list", "database_size",
                 "storage_info", "show", "version", "platform", "functions", "collations", "metadata_info"}
#: what a report parameter of this name may take: a query over the run giving the allowed values
_DOMAINS = {
    "method": "SELECT DISTINCT split_part(method, '+', 1) FROM metrics UNION SELECT DISTINCT method FROM metrics",
    "segment": "SELECT DISTINCT segment FROM metrics",
    "stage": "SELECT DISTINCT stage FROM metrics",
    "filter": "SELECT DISTINCT split_part(method, '+', 2) FROM metrics WHERE stage = 'tracker'",
    "metric": "SELECT DISTINCT metric FROM accuracy_by_epoch",
    "radar_id": "SELECT DISTINCT radar_id FROM radars",
    "run": "SELECT DISTINCT run FROM reports",
    "verdict": "SELECT DISTINCT verdict FROM requirements",
}


class ReadOnlyQueryError(OptionError):
    """A query that would change something (or read files) was refused."""


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
            raise OptionError(f"report {self.name!r} has no parameter(s) {', '.join(unknown)}; its parameters: {known}",
                              option="--param")
        for key, value in given.items():
            default = self.params[key]
            numeric = isinstance(default, (int, float)) and not isinstance(default, bool)
            if numeric and value is not None and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                                      and abs(value) < float("inf")):
                raise OptionError(f"{key} must be a finite number, got {value!r}", option="--param")
        return {**self.params, **given}


def sql_dir() -> Path:
    """Directory of the named reports: ``tertiary/sql`` in an installed package, the repository's
    ``sql/`` in a source checkout."""
    package = Path(__file__).resolve().parents[1]
    for candidate in (package / "sql", package.parent / "sql"):
        if candidate.is_dir() and any(candidate.glob("*.sql")):
            return candidate
    raise FileNotFoundError(f"no SQL report directory in or beside {package}")


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
    names = ", ".join(p.stem for p in sorted(sql_dir().glob("*.sql")))
    path = sql_dir() / f"{name}.sql"
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", name or "") or not path.is_file():
        raise OptionError(f"no SQL report {name!r}; available: {names}")
    return _parse(path)


def open_read_only(run_dir: str | os.PathLike[str]) -> RunStore:
    """Open a run database read-only, with file-system access from SQL switched off."""
    try:
        store = RunStore.open(run_dir, read_only=True)
    except FileNotFoundError as exc:
        raise DataError(f"{exc} (give a run directory written by `tertiary run`)") from None
    except duckdb.Error as exc:
        raise DataError(f"cannot open the run database: {exc}", path=str(run_dir)) from None
    try:
        store.con.execute("SET enable_external_access = false")
        store.con.execute("SET lock_configuration = true")
    except BaseException:
        store.close()
        raise
    return store


def _allowed(st: Any) -> bool:
    kind = str(st.type).rsplit(".", 1)[-1]
    text = _strip_comments(st.query).lstrip().upper()
    if kind in _READ_TYPES:
        return True
    if kind == "MULTI":   # DuckDB expands PIVOT/UNPIVOT into several statements
        return text.startswith(("PIVOT", "UNPIVOT"))
    if kind == "PRAGMA":
        m = re.match(r"PRAGMA\s+([A-Z_]+)", text)
        return bool(m) and m.group(1).lower() in _READ_PRAGMAS
    return False


def _check_read_only(con: duckdb.DuckDBPyConnection, sql: str) -> None:
    try:
        sql.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise OptionError(f"the query is not valid UTF-8 text ({exc.reason} at position {exc.start})",
                          option="--query") from None
    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as exc:
        raise OptionError(f"SQL error: {' '.join(str(exc).split())}", option="--query") from None
    if not statements:
        raise ReadOnlyQueryError("empty query")
    for st in statements:
        if not _allowed(st):
            kind = str(st.type).rsplit(".", 1)[-1]
            raise ReadOnlyQueryError(
                f"refused a {kind} statement: the run database is opened read-only and only queries "
                "(SELECT, WITH … SELECT, FROM, VALUES, SHOW, DESCRIBE, SUMMARIZE, PIVOT, EXPLAIN, "
                "informational PRAGMAs) may run")


def _interruptible(con: duckdb.DuckDBPyConnection, timeout_s: float | None):
    """A timer that interrupts ``con`` after ``timeout_s`` seconds (None: no timeout)."""
    if timeout_s is None:
        return None
    timer = threading.Timer(timeout_s, con.interrupt)
    timer.daemon = True
    timer.start()
    return timer


_AS_TEXT = ("INTERVAL", "BIT", "UNION", "BLOB", "MAP", "VARINT", "BIGNUM")
_TEMPORAL = ("DATE", "TIMESTAMP")


def _column(name: str, dtype: str) -> str:
    """The projection of one result column into something polars imports, prints and writes to
    CSV: binary, map, union, bit and interval values as DuckDB's text; dates and times that no
    calendar type can hold (infinite, or outside the years 1–9999) as null."""
    q = '"' + name.replace('"', '""') + '"'
    if dtype.startswith(_AS_TEXT):
        return f"CAST({q} AS VARCHAR) AS {q}"
    if dtype.startswith(_TEMPORAL):
        return f"CASE WHEN isfinite({q}) AND year({q}) BETWEEN 1 AND 9999 THEN {q} END AS {q}"
    return q


def _fetch(rel: duckdb.DuckDBPyRelation) -> pl.DataFrame:
    """A relation as polars, with the column types polars cannot hold made printable."""
    types = [str(t).upper() for t in rel.types]
    if any(t.startswith(_AS_TEXT + _TEMPORAL) for t in types):
        rel = rel.project(", ".join(_column(c, t) for c, t in zip(rel.columns, types)))
    return rel.pl()


def query(store: RunStore, sql: str, params: Mapping[str, Any] | None = None, *,
          timeout_s: float | None = None) -> pl.DataFrame:
    """Run read-only ``sql`` with bound ``params`` and return the last statement's result.

    ``timeout_s`` interrupts a statement that runs longer (:class:`~tertiary.core.errors.ResourceError`);
    a SQL error is an :class:`~tertiary.core.errors.OptionError` (the query is the user's input)."""
    _check_read_only(store.con, sql)
    timer = _interruptible(store.con, timeout_s)
    try:
        rel = store.con.sql(sql, params=dict(params) if params else None)
        frame = pl.DataFrame() if rel is None else _fetch(rel)
    except duckdb.InterruptException:
        raise ResourceError(f"the query ran longer than its {timeout_s:g} s timeout (--timeout) and was stopped") \
            from None
    except duckdb.Error as exc:
        if timer is not None and not timer.is_alive() and "interrupt" in str(exc).lower():
            raise ResourceError(f"the query ran longer than its {timeout_s:g} s timeout (--timeout) and was "
                                "stopped") from None
        raise OptionError(f"SQL error: {' '.join(str(exc).split())}", option="--query") from None
    finally:
        if timer is not None:
            timer.cancel()
    return utc_times(frame)


def allowed_values(store: RunStore, name: str) -> list[Any] | None:
    """The values report parameter ``name`` may take in this run (None: no named domain)."""
    sql = _DOMAINS.get(name)
    if sql is None:
        return None
    try:
        values = store.con.sql(sql).fetchall()
    except duckdb.Error:   # the table is not in this run: nothing to choose from
        return []
    return sorted({v[0] for v in values if v[0] not in (None, "")}, key=str)


def check_values(store: RunStore, report: SqlReport, given: Mapping[str, Any]) -> None:
    """Refuse a parameter value the run does not hold, listing the values it does."""
    for key, value in given.items():
        if value is None or key not in report.params:
            continue
        allowed = allowed_values(store, key)
        if allowed is not None and value not in allowed:
            shown = ", ".join(map(str, allowed[:40])) + (" …" if len(allowed) > 40 else "")
            raise OptionError(f"report {report.name!r}: {key}={value!r} is not in this run; allowed: "
                              f"{shown or 'none (the run has no such data)'}, or null for all", option="--param")


def run_report(store: RunStore, name: str | SqlReport, params: Mapping[str, Any] | None = None, *,
               timeout_s: float | None = None, **kwargs: Any) -> pl.DataFrame:
    """Run the named report on ``store`` with its defaults overridden by ``params``/``kwargs``."""
    report = name if isinstance(name, SqlReport) else load_report(name)
    given = {**(params or {}), **kwargs}
    values = report.bind(given)
    check_values(store, report, given)
    return query(store, report.sql, values or None, timeout_s=timeout_s)


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
