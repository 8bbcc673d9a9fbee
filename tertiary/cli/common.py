"""What every command shares: the consoles, the progress lines, the option parsers and option types,
the table printer.

Nothing a user typed or a dataset holds is ever read as rich markup: every console here has markup
switched off, and help text is printed as plain text.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any, Optional

import polars as pl
import typer
from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.table import Table

from tertiary.core.errors import DataError, OptionError
from tertiary.runtime.windows import (AUTO_WINDOW, DEFAULT_WINDOW_S, check_window, incomplete_message, is_auto,
                                      peak_rss_mib)
from tertiary.simulate import load_scenario
from tertiary.simulate.config import ScenarioConfig, check_scenario, with_radar_count
from tertiary.stages.fusion import METHODS

# markup off everywhere: dataset text, reject reasons and query results may contain "[/...]"
console = Console(markup=False, highlight=False, soft_wrap=False)
err_console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)

DEFAULT_SCENARIO = "terminal-area"
DEFAULT_METHODS = ",".join(METHODS)
DEFAULT_FILTERS = "singer,imm_sym"


def batch_width() -> None:
    """A batch log or a pipe: tables as wide as COLUMNS says, else 160 — read at each command,
    not once at import, so a program that invokes several commands gets each one's width."""
    if not console.is_terminal:
        console.width = int(os.environ["COLUMNS"]) if os.environ.get("COLUMNS", "").isdigit() else 160


batch_width()


# --------------------------------------------------------------------------- progress


#: progress output of this command: "text" (a status line in a terminal, time-stamped lines
#: otherwise), "json" (one JSON object per line, for schedulers) or "quiet" (none)
_LOG = {"mode": "text"}


def reset_output() -> None:
    """Text progress and the batch width, at the start of each invocation (run/simulate may
    change the progress mode)."""
    _LOG["mode"] = "text"
    batch_width()


def set_log(quiet: bool, log_format: str) -> None:
    """The progress mode of ``--quiet`` and ``--log-format``."""
    if log_format not in ("text", "json"):
        raise OptionError(f"choose text or json, got {log_format!r}", option="--log-format")
    _LOG["mode"] = "quiet" if quiet else log_format


#: a step of a counted loop: "window 3/12" (running) or "window 3/12 done"; "part" and "block" too
_COUNTED = re.compile(r"\b(?:window|part|block) (\d+)/(\d+)( done)?")
_RATE = re.compile(r"([\d,]+) reports/s")


def counted_step(message: str) -> tuple[int, int, str] | None:
    """(done, total, rate) of a counted step's message: a step K/N running has K − 1 done, one that
    says ``done`` K; the rate is its "N reports/s" (else ""); None for any other message."""
    m = _COUNTED.search(message)
    if m is None:
        return None
    k, n = int(m.group(1)), int(m.group(2))
    rate = _RATE.search(message)
    return (k if m.group(3) else k - 1), n, (f"{rate.group(1)} reports/s" if rate else "")


class Steps:
    """Stage progress: in a terminal a transient status line, which becomes a bar (done of total,
    reports/s, elapsed and remaining time) as soon as a step is counted (:func:`counted_step`);
    plain time-stamped lines in a batch log (no glyphs, one line per stage or window, flushed as it
    happens, with the peak memory so far), JSON lines with ``--log-format json``, nothing with
    ``--quiet``."""

    def __init__(self, title: str) -> None:
        self.title, self.t0 = title, time.perf_counter()
        self._prog: Progress | None = None
        self._task: Any = None
        self._counted = False

    def __enter__(self) -> Steps:
        if console.is_terminal and _LOG["mode"] == "text":
            self._start(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn())
        return self

    def _start(self, *columns: Any, total: int | None = None) -> None:
        """A transient status line with these columns (replacing the one shown)."""
        if self._prog is not None:
            self._prog.__exit__(None, None, None)
        self._prog = Progress(*columns, console=console, transient=True)
        self._prog.__enter__()
        self._task = self._prog.add_task(self.title, total=total, rate="")

    def _bar(self, total: int) -> None:
        """From the first counted step on: done of total, reports/s, elapsed and remaining time."""
        self._start(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(bar_width=30), MofNCompleteColumn(),
                    TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                    total=total)
        self._counted = True

    def __exit__(self, *exc: Any) -> None:
        if self._prog is not None:
            self._prog.__exit__(*exc)

    def __call__(self, message: str) -> None:
        message = message.removeprefix(f"{self.title}: ")
        elapsed = time.perf_counter() - self.t0
        if _LOG["mode"] == "quiet":
            return
        if _LOG["mode"] == "json":
            sys.stdout.write(json.dumps({"t_s": round(elapsed, 3), "task": self.title, "step": message,
                                         "peak_rss_mib": round(peak_rss_mib(), 1)}) + "\n")
            sys.stdout.flush()
        elif self._prog is not None:
            counted = counted_step(message)
            if counted is None:
                self._prog.update(self._task, description=f"{self.title}: {message}")
            else:
                done, total, rate = counted
                if not self._counted:
                    self._bar(total)
                end = _COUNTED.search(message).end()              # "window 3/12 done", "part 1/4 decoding"
                label = message[:end] + re.split(r"[,:]", message[end:], maxsplit=1)[0]
                self._prog.update(self._task, description=f"{self.title}: {label}",
                                  completed=done, total=total, rate=rate or self._prog.tasks[0].fields["rate"])
        else:
            console.print(f"[{elapsed:7.1f} s] {self.title}: {message} (peak {peak_rss_mib():,.0f} MiB)",
                          soft_wrap=True)
            sys.stdout.flush()


def print_note(note: str) -> None:
    """A note on the run, one line."""
    console.print(f"note: {note}", soft_wrap=True)


# --------------------------------------------------------------------------- options


def _floats(text: str, n: int, option: str, form: str) -> list[float]:
    parts = text.split(":")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = []
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise OptionError(f"expected {form} with finite numbers, got {text!r}", option=option)
    return values


def _window(text: str | None, option: str) -> tuple[float, float] | None:
    if text is None:
        return None
    lo, hi = _floats(text, 2, option, "T0:T1")
    return lo, hi


def window_option(text: str, engine: str) -> float | str | None:
    """``--window``: seconds (0: one window) or ``auto``, which the local engine sizes from the
    dataset (:func:`tertiary.runtime.windows.auto_window_s`) and the Dask engine reads as
    :data:`~tertiary.runtime.windows.DEFAULT_WINDOW_S` (its slices and overlaps are multiples of it)."""
    if is_auto(text):
        return DEFAULT_WINDOW_S if engine == "dask" else AUTO_WINDOW
    (value,) = _floats(text, 1, "--window", "SECONDS or auto")
    return None if value == 0 else check_window(value)


def _anomalies(cfg: ScenarioConfig, noise_factor: float | None, noise_window: str | None, dropout: str | None,
               outliers: float | None, bias_step: str | None) -> ScenarioConfig:
    """The anomaly options of a scenario."""
    anom = cfg.anomalies
    if noise_window is not None and noise_factor is None:
        raise OptionError("needs --noise-factor", option="--noise-window")
    if noise_factor is not None:
        anom = dataclasses.replace(anom, noise_factor=noise_factor,
                                   noise_window_s=_window(noise_window, "--noise-window"))
    if dropout is not None:  # NAME:T0:T1
        name, sep, rest = dropout.partition(":")
        if not sep or not name:
            raise OptionError(f"expected RADAR:T0:T1, got {dropout!r}", option="--dropout")
        lo, hi = _floats(rest, 2, "--dropout", "RADAR:T0:T1")
        anom = dataclasses.replace(anom, dropout_radar=name, dropout_window_s=(lo, hi))
    if outliers is not None:
        anom = dataclasses.replace(anom, outlier_fraction=outliers)
    if bias_step is not None:  # T:DR_M:DAZ_DEG
        t, dr, daz = _floats(bias_step, 3, "--bias-step", "T:DRANGE_M:DAZ_DEG")
        anom = dataclasses.replace(anom, bias_step_time_s=t, bias_step_range_m=dr, bias_step_azimuth_deg=daz)
    return dataclasses.replace(cfg, anomalies=anom)


def build_scenario(scenario: str, *, runs: int | None = None, seed: int | None = None, aircraft: int | None = None,
                   radars: int | None = None, duration: float | None = None, truth: str | None = None,
                   noise_factor: float | None = None, noise_window: str | None = None,
                   dropout: str | None = None, outliers: float | None = None,
                   bias_step: str | None = None) -> ScenarioConfig:
    """A built-in scenario (or TOML file) with command-line overrides applied and checked."""
    cfg = load_scenario(scenario)
    cfg = cfg.replace(runs=runs, seed=seed, duration_s=duration)
    if aircraft is not None and cfg.kind == "national" and cfg.national is not None:
        # national traffic is a daily curve: --aircraft sets its peak airborne count
        cfg = dataclasses.replace(cfg, national=dataclasses.replace(cfg.national, peak_airborne=aircraft))
    elif aircraft is not None:
        cfg = dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, aircraft=aircraft))
    if truth is not None:
        cfg = dataclasses.replace(cfg, adsb=dataclasses.replace(cfg.adsb, truth_file=truth))
    if radars is not None:
        if radars < 1:
            raise OptionError(f"must be at least 1, got {radars}", option="--radars")
        cfg = with_radar_count(cfg, radars)
    return check_scenario(_anomalies(cfg, noise_factor, noise_window, dropout, outliers, bias_step))


def names(text: str, known: tuple[str, ...] | list[str], option: str) -> tuple[str, ...]:
    """The comma-separated names of ``text``, each one of ``known``, in order, without repeats."""
    chosen = tuple(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    bad = [m for m in chosen if m not in known]
    if bad:
        raise OptionError(f"unknown {', '.join(bad)}; choose from {', '.join(known)}", option=option)
    return chosen


def parse_origin(text: str | None) -> tuple[float, float, float] | None:
    """``--origin LAT,LON[,ALT_M]`` (degrees and metres; None when not given)."""
    if text is None:
        return None
    parts = text.replace(":", ",").split(",")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values) \
            or not (-90 <= values[0] <= 90 and -180 <= values[1] <= 180):
        raise OptionError(f"expected LAT,LON[,ALT_M] in degrees (and metres), got {text!r}", option="--origin")
    return (values[0], values[1], values[2] if len(values) == 3 else 0.0)


def refuse_incomplete(run_dir: Path) -> None:
    """A :class:`DataError` when ``run_dir`` holds a windowed run that is not complete."""
    text = incomplete_message(run_dir)
    if text:
        raise DataError(text, path=str(run_dir))


# --------------------------------------------------------------------------- shared option types

RunsOpt = Annotated[Optional[int], typer.Option(help="Monte-Carlo runs [default: the scenario's]")]
SeedOpt = Annotated[Optional[int], typer.Option(help="random seed; same seed, same data [default: the scenario's]")]
AircraftOpt = Annotated[Optional[int], typer.Option(help="number of aircraft (terminal-area) [default: the scenario's]")]
RadarsOpt = Annotated[Optional[int], typer.Option(help="number of radars [default: the scenario's]")]
DurationOpt = Annotated[Optional[float], typer.Option(help="duration in seconds [default: the scenario's]")]
TruthOpt = Annotated[Optional[str], typer.Option(help="ADS-B trajectory file (OpenSky/traffic schema) used as truth")]
NoiseOpt = Annotated[Optional[float], typer.Option(help="measurement noise inflation factor, e.g. 3, 5, 6")]
NoiseWinOpt = Annotated[Optional[str], typer.Option(help="T0:T1 seconds of the noise inflation [default: whole run]")]
DropoutOpt = Annotated[Optional[str], typer.Option(help="RADAR:T0:T1 radar dropout window (radar name, seconds)")]
OutliersOpt = Annotated[Optional[float], typer.Option(help="fraction of gross-error reports, in [0, 1]")]
BiasStepOpt = Annotated[Optional[str], typer.Option(help="T:DRANGE_M:DAZ_DEG range/azimuth bias step at T seconds")]
RequirementsOpt = Annotated[Optional[Path], typer.Option(help="requirements TOML with pass/fail thresholds "
                                                              "[default: the shipped example, "
                                                              "datasets/requirements/example.toml]")]
QuietOpt = Annotated[bool, typer.Option("--quiet", help="print no progress (the final summary only)")]
LogFormatOpt = Annotated[str, typer.Option(help="progress lines: text, or json (one object per line: t_s, "
                                                "task, step, peak_rss_mib) for schedulers")]
OriginOpt = Annotated[Optional[str], typer.Option(help="LAT,LON[,ALT_M] processing centre for a dataset without "
                                                       "scenario.toml [default: mean of the radar sites]")]


def checked_format(fmt: str, out: Path | None) -> str:
    """A table output's ``--format`` (table, csv or parquet) checked against its ``--out``: parquet
    needs a file, and a file is never a directory."""
    if fmt not in ("table", "csv", "parquet"):
        raise OptionError(f"use table, csv or parquet, got {fmt!r}", option="--format")
    if out is None and fmt == "parquet":
        raise OptionError("parquet needs --out FILE", option="--out")
    if out is not None and out.is_dir():
        raise OptionError(f"{out} is a directory; give a file name", option="--out")
    return fmt


# --------------------------------------------------------------------------- tables

_PLAIN_INT = ("id", "run", "epoch", "sic", "sac", "mode_3a", "year")


def cell(value: Any, column: str) -> str:
    """A value as printed in a terminal table: identifiers plain, counts with separators."""
    if isinstance(value, bool) or value is None:
        return "" if value is None else ("yes" if value else "no")
    if isinstance(value, int):
        plain = column == "id" or column.endswith(("_id", "_ids")) or column in _PLAIN_INT
        return str(value) if plain else f"{value:,}"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        return f"{value:,.4g}" if abs(value) < 1e6 else f"{value:,.1f}"
    if isinstance(value, datetime):
        return value.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] if value.tzinfo else str(value)
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value, default=str)
    return str(value)


def print_frame(frame: pl.DataFrame, title: str, limit: int, *, hide_empty: bool = False) -> None:
    """``frame``'s first ``limit`` rows with a caption of the row count: a table when its columns fit
    the terminal at their natural width, else one record per row (column, value), as psql's
    expanded display; with ``hide_empty`` the columns without a value in any row are left out
    (and named in the caption)."""
    empty = [c for c in frame.columns if frame.height and frame[c].null_count() == frame.height] if hide_empty else []
    frame = frame.drop(empty)
    cols = frame.columns
    rows = [[cell(v, c) for v, c in zip(row, cols)] for row in frame.head(limit).iter_rows()]
    shown = f" (first {limit:,} shown; --limit to change, --format csv for all)" if frame.height > limit else ""
    caption = f"{frame.height:,} row{'' if frame.height == 1 else 's'}{shown}"
    if empty:
        caption += f"; left out, empty in this run: {', '.join(empty)}"
    widths = [max([len(c), *(len(r[i]) for r in rows)]) for i, c in enumerate(cols)]
    if sum(w + 3 for w in widths) + 1 <= console.width:
        table = Table(title=title, caption=caption)
        for col, dtype in frame.schema.items():
            table.add_column(col, justify="right" if dtype.is_numeric() else "left", no_wrap=True)
        for r in rows:
            table.add_row(*r)
        console.print(table)
        return
    _print_records(title, cols, rows, frame.height, caption)


def _print_records(title: str, cols: list[str], rows: list[list[str]], height: int, caption: str) -> None:
    """One block per row, a line per column: what a wide result looks like in a narrow terminal."""
    name_w = max(map(len, cols), default=0)
    lines = [f"{title} (one record per row: the columns do not fit a {console.width}-column terminal)"]
    for i, r in enumerate(rows, 1):
        lines.append(f"-[ {title} row {i} of {height:,} ]" + "-" * max(0, name_w - len(title)))
        lines += [f"{c:<{name_w}} | {v}" for c, v in zip(cols, r)]
    lines.append(caption)
    console.print("\n".join(lines), soft_wrap=True)
