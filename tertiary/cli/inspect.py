"""``tertiary episodes`` and ``tertiary compare``: a run's alert episodes drawn one by one, and
runs side by side — thin commands over :mod:`tertiary.report.episodes` and
:mod:`tertiary.report.compare`."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import polars as pl
import typer

from tertiary.cli.common import checked_format, console, err_console, print_frame, refuse_incomplete
from tertiary.core.errors import DataError, OptionError
from tertiary.report import compare as cmp
from tertiary.report.episodes import DEFAULT_EPISODES, parse_pair, write_episodes
from tertiary.store import sql_reports


def episodes(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    picture: Annotated[Optional[str], typer.Option("--picture", help="picture, e.g. information+imm_sym "
                                                                             "[default: the best picture]")] = None,
    pair: Annotated[Optional[str], typer.Option("--pair", help="A,B: every episode of these two aircraft (truth "
                                                               "ids; picture ids for a pair without aircraft)")] = None,
    n: Annotated[int, typer.Option("-n", help="most severe alert episodes drawn (without --pair)")] = DEFAULT_EPISODES,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="HTML file [default: RUN_DIR/episodes.html]")]
    = None,
) -> None:
    """Draw a run's alert episodes: plan view and vertical profile of both tracks and truths, the
    predicted closest approach, the minima, the classification and the warning time.

    Without --pair: the N most severe alert episodes of the picture and every missed loss of
    separation (what the report shows); with --pair A,B: every episode of those two aircraft."""
    if n < 1:
        raise OptionError(f"must be at least 1, got {n}", option="-n")
    if out is not None and out.is_dir():
        raise OptionError(f"{out} is a directory; give a file name", option="--out")
    refuse_incomplete(run_dir)
    if not (run_dir / "results.duckdb").is_file():
        raise DataError("no run database here (expected results.duckdb)", path=str(run_dir))
    t = time.perf_counter()
    path, k, note = write_episodes(run_dir, out, picture, n, parse_pair(pair) if pair else None)
    console.print(note, soft_wrap=True)
    console.print(f"wrote {path} ({k} figure{'' if k == 1 else 's'}, {path.stat().st_size / 1e6:.1f} MB) in "
                  f"{time.perf_counter() - t:.1f} s", soft_wrap=True)


def _out_format(out: Path | None, fmt: str) -> str:
    """``html`` for an .html --out, else the table format (table, csv, parquet)."""
    fmt = checked_format(fmt, out)
    if out is None:
        return fmt
    suffix = {".html": "html", ".htm": "html", ".csv": "csv", ".parquet": "parquet"}.get(out.suffix.lower())
    if fmt != "table":
        return fmt
    if suffix is None:
        raise OptionError("name an .html, .csv or .parquet file (or give --format csv|parquet)", option="--out")
    return suffix


def compare(
    run_dirs: Annotated[list[Path], typer.Argument(help="two or more run directories; the first is the baseline")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="compare.html (the page), or a .csv/.parquet "
                                                                     "file (the table)")] = None,
    fmt: Annotated[str, typer.Option("--format", "-f", help="table (print), csv or parquet")] = "table",
    changed: Annotated[bool, typer.Option("--changed", help="only the rows that differ from the baseline")] = False,
    limit: Annotated[int, typer.Option(help="rows printed in table format")] = 200,
) -> None:
    """Compare runs: every picture's accuracy and safety figures and every requirement's verdict
    side by side, with the deltas to the first run and the changes of verdict; what differs
    between the runs (dataset, scenario, configuration) is said first.

    tertiary compare RUN_A RUN_B [RUN_C ...] [--out compare.html | --format csv [--out FILE]]."""
    kind = _out_format(out, fmt)
    if limit < 1:
        raise OptionError(f"must be at least 1, got {limit}", option="--limit")
    runs = cmp.load_runs(run_dirs)
    say = err_console if kind == "csv" and out is None else console     # CSV on stdout stays CSV
    if kind == "html":
        path, table, diff = cmp.write_compare(runs, out)
    else:
        table, diff = cmp.compare_table(runs), cmp.differences(runs)
    for line in cmp.summary_lines(diff):
        say.print(f"note: {line}", soft_wrap=True)
    if kind == "html":
        console.print(f"wrote {path} ({int(table['changed'].sum())} of {table.height} figures differ from "
                      f"{runs[0].label})", soft_wrap=True)
        return
    table = table.filter(pl.col("changed")) if changed else table
    if out is not None:
        path = sql_reports.export_frame(table, out, kind)
        console.print(f"wrote {path} ({table.height:,} rows, {kind})")
    elif kind == "csv":
        sys.stdout.write(sql_reports.frame_to_csv(table))
    else:
        print_frame(table, f"compare (baseline {runs[0].label}; Δ = run − baseline)", limit)

