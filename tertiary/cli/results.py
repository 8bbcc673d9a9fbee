"""``tertiary report`` and ``tertiary sql``: the results of a run, as an HTML report or tables."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.table import Table

from tertiary.cli.common import Steps, checked_format, console, print_frame, refuse_incomplete
from tertiary.core.errors import DataError, OptionError
from tertiary.report.html import build_report
from tertiary.store import sql_reports


def report(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="HTML file [default: RUN_DIR/report.html]")] = None,
) -> None:
    """Write the self-contained HTML report of a run (figures from the sql/ reports)."""
    refuse_incomplete(run_dir)
    if not (run_dir / "results.duckdb").is_file():
        raise DataError("no run database here (expected results.duckdb)", path=str(run_dir))
    if out is not None and out.is_dir():
        raise OptionError(f"{out} is a directory; give a file name", option="--out")
    t = time.perf_counter()
    with Steps("report") as say:
        path = build_report(run_dir, out, progress=say)
    console.print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t:.1f} s",
                  soft_wrap=True)


def _param_value(text: str) -> Any:
    """A --param value: a JSON literal (number, null, true/false, "text") or else plain text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def sql(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    name: Annotated[Optional[str], typer.Argument(help="named report (see --list)")] = None,
    list_: Annotated[bool, typer.Option("--list", help="list the named reports and their parameters")] = False,
    query: Annotated[Optional[str], typer.Option("--query", "-q", help="ad-hoc read-only SQL")] = None,
    param: Annotated[Optional[list[str]], typer.Option("--param", "-p",
                                                       help="report parameter NAME=VALUE (repeatable)")] = None,
    fmt: Annotated[str, typer.Option("--format", "-f", help="table (print), csv or parquet")] = "table",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="export file, written atomically; never a file "
                                                                     "inside the run directory")] = None,
    columns: Annotated[Optional[str], typer.Option("--columns", "-c", help="comma-separated columns to keep, in "
                                                                           "this order [default: all]")] = None,
    limit: Annotated[int, typer.Option(help="rows printed in table format")] = 100,
    timeout: Annotated[float, typer.Option(help="statement timeout in seconds")] = 60.0,
) -> None:
    """Run a named SQL report (sql/NAME.sql) or an ad-hoc read-only query on a run database.

    tertiary sql RUN_DIR --list; tertiary sql RUN_DIR NAME [-p KEY=VALUE] [-c COL,COL] [--format csv|parquet --out FILE];
    tertiary sql RUN_DIR --query "SELECT ..."."""
    if sum([bool(list_), name is not None, query is not None]) != 1:
        raise OptionError("give exactly one of NAME, --list or --query")
    if list_:
        _print_report_list(sql_reports.list_reports())
        return
    if limit < 1:
        raise OptionError(f"must be at least 1, got {limit}", option="--limit")
    if not (math.isfinite(timeout) and timeout > 0):
        raise OptionError(f"must be a positive number of seconds, got {timeout}", option="--timeout")
    fmt = _export_format(fmt, out, run_dir)
    params: dict[str, Any] = {}
    for item in param or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise OptionError(f"expected NAME=VALUE, got {item!r}", option="--param")
        params[key.strip()] = _param_value(value)
    if query is not None and params:
        raise OptionError("applies to named reports only", option="--param")
    refuse_incomplete(run_dir)
    with sql_reports.open_read_only(run_dir) as store:
        if query is not None:
            frame, title = sql_reports.query(store, query, timeout_s=timeout), "query"
        else:
            frame, title = sql_reports.run_report(store, name, params, timeout_s=timeout), name
    if columns is not None:
        frame = _select_columns(frame, columns)
    if out is not None:
        path = sql_reports.export_frame(frame, out, fmt)
        console.print(f"wrote {path} ({frame.height:,} rows, {fmt})")
    elif fmt == "csv":
        sys.stdout.write(sql_reports.frame_to_csv(frame))
    else:       # what the run's stages filled: a column empty in every row is named, not printed
        print_frame(frame, title, limit, hide_empty=True)


def _select_columns(frame: Any, columns: str) -> Any:
    """``frame`` with the ``--columns`` list, in its order; an unknown name is an option error."""
    wanted = [c.strip() for c in columns.split(",") if c.strip()]
    unknown = [c for c in wanted if c not in frame.columns]
    if unknown or not wanted:
        raise OptionError(f"no column {', '.join(unknown) or '(none given)'}; this result has "
                          f"{', '.join(frame.columns)}", option="--columns")
    return frame.select(wanted)


def _export_format(fmt: str, out: Path | None, run_dir: Path) -> str:
    fmt = checked_format(fmt, out)
    if out is None:
        return fmt
    if out.resolve().parent == run_dir.resolve() or run_dir.resolve() in out.resolve().parents:
        raise OptionError(f"{out} is inside the run directory {run_dir}; write exports elsewhere", option="--out")
    if fmt == "table":
        fmt = {".csv": "csv", ".parquet": "parquet"}.get(out.suffix.lower(), "")
        if not fmt:
            raise OptionError("give --format csv|parquet (or a .csv/.parquet file name)", option="--out")
    return fmt


def _print_report_list(reports: list[Any]) -> None:
    table = Table(title="named SQL reports: tertiary sql RUN_DIR NAME [-p NAME=VALUE]")
    table.add_column("report", no_wrap=True)
    table.add_column("what it answers", overflow="fold", ratio=3)
    table.add_column("parameters (default)", overflow="fold", ratio=2)
    for rep in reports:
        params = "; ".join(f"{k} = {json.dumps(v)}" + (f": {rep.param_help[k]}" if rep.param_help.get(k) else "")
                           for k, v in rep.params.items())
        table.add_row(rep.name, rep.summary, params or "none")
    console.print(table)
