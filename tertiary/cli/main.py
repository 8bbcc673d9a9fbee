"""Command line: a thin layer over the public API (typer + rich).

One error boundary (:class:`_Boundary`) turns every expected failure (:mod:`tertiary.core.errors`,
file-system errors) into one line on stderr and an exit code — 2 for a bad option, 3 for bad
input data, 4 for a refused allocation, 1 for an internal error — with the traceback only under
``tertiary --debug``. Nothing a user typed or a dataset holds is ever read as rich markup: every
console here has markup switched off, and help text is printed as plain text.
"""

from __future__ import annotations

import ctypes
import dataclasses
import json
import math
import os
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Annotated, Any, Optional

import polars as pl
import typer
from rich.console import Console
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table
from typer.core import TyperGroup

from tertiary.pipeline import job as pipeline
from tertiary.runtime.windows import AUTO_WINDOW, DEFAULT_WINDOW_S, check_window, is_auto
from tertiary.core.errors import DataError, OptionError, TertiaryError
from tertiary.stages.tracking.filters import REGISTRY
from tertiary.stages.fusion.fuse import ALL_METHODS, METHODS
from tertiary.sensors.local_tracks import ESTIMATE_COLUMNS
from tertiary.simulate import (builtin_scenarios, load_scenario, read_dataset, simulate as _simulate, write_dataset, write_stream)
from tertiary.simulate.config import ScenarioConfig, check_scenario, with_radar_count

# markup off everywhere: dataset text, reject reasons and query results may contain "[/...]"
console = Console(markup=False, highlight=False, soft_wrap=False)
err_console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)


def _batch_width() -> None:
    """A batch log or a pipe: tables as wide as COLUMNS says, else 160 — read at each command,
    not once at import, so a program that invokes several commands gets each one's width."""
    if not console.is_terminal:
        console.width = int(os.environ["COLUMNS"]) if os.environ.get("COLUMNS", "").isdigit() else 160


_batch_width()

DEFAULT_SCENARIO = "terminal-area"
DEFAULT_METHODS = ",".join(METHODS)
DEFAULT_FILTERS = "singer,imm_sym"
RUNS_DIR = Path("runs")


def _failure(exc: BaseException) -> tuple[int, str]:
    """Exit code and one-line message of an exception that reached the boundary."""
    if isinstance(exc, TertiaryError):
        return exc.exit_code, str(exc)
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return 3, f"{where}{exc.strerror or exc}"
    if isinstance(exc, MemoryError):
        return 4, "out of memory (reduce the input or the number of methods/filters)"
    return 1, (f"internal error ({type(exc).__name__}: {exc}); "
               "run again with `tertiary --debug ...` for the traceback and report it")


try:
    from polars.exceptions import PanicException as _PANIC
except ImportError:  # pragma: no cover - older polars
    _PANIC = Exception


class _Boundary(TyperGroup):
    """The one error boundary of every command (see the module docstring)."""

    def invoke(self, ctx: typer.Context) -> Any:
        try:
            return super().invoke(ctx)
        except (typer.TyperException, typer.Exit, typer.Abort):
            raise
        except KeyboardInterrupt:
            err_console.print("interrupted")
            raise typer.Exit(130) from None
        except (Exception, _PANIC) as exc:   # a Rust panic (polars) is a BaseException
            if (ctx.obj or {}).get("debug"):
                raise
            code, message = _failure(exc)
            err_console.print(f"error: {message}")
            raise typer.Exit(code) from None


app = typer.Typer(cls=_Boundary, add_completion=False, no_args_is_help=False, rich_markup_mode=None,
                  pretty_exceptions_enable=False, context_settings={"max_content_width": 120},
                  help="Tertiary processing of multi-radar surveillance data and safety evaluation.")


def one_malloc_arena() -> bool:
    """One glibc malloc arena for the process (True when set; False off glibc). Worker threads
    (the STCA curves predict two settings at a time) would each get an arena whose freed memory
    glibc keeps: on the default job the peak was 1 222 MiB with them, 1 040 MiB with one arena
    set here (977 MiB before the threads), at the same speed. Polars and DuckDB allocate with
    their own allocators, untouched."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_ARENA_MAX, 1))
    except (OSError, AttributeError):      # not glibc (macOS, musl): nothing to set
        return False


_M_ARENA_MAX = -8          # glibc's malloc.h


@app.callback()
def _root(ctx: typer.Context,
          debug: Annotated[bool, typer.Option("--debug", help="show the full traceback of an error")] = False) -> None:
    """Tertiary processing of multi-radar surveillance data and safety evaluation.

    Exit codes: 0 success, 1 internal error, 2 bad option, 3 bad input data or file, 4 refused
    (a limit would be exceeded). Add --debug before the command for a traceback."""
    ctx.obj = {"debug": debug}
    _LOG["mode"] = "text"             # per invocation (run/simulate may change it)
    _batch_width()
    one_malloc_arena()                # the process is the command's: before any worker thread


# --------------------------------------------------------------------------- progress


#: progress output of this command: "text" (a status line in a terminal, time-stamped lines
#: otherwise), "json" (one JSON object per line, for schedulers) or "quiet" (none)
_LOG = {"mode": "text"}


def _set_log(quiet: bool, log_format: str) -> None:
    if log_format not in ("text", "json"):
        raise OptionError(f"choose text or json, got {log_format!r}", option="--log-format")
    _LOG["mode"] = "quiet" if quiet else log_format


def _peak_rss_mib() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _Steps:
    """Stage progress: a transient status line in a terminal, plain time-stamped lines in a batch
    log (no spinner glyphs, one line per stage, flushed as it happens, with the peak memory so
    far), JSON lines with ``--log-format json``, nothing with ``--quiet``."""

    def __init__(self, title: str) -> None:
        self.title, self.t0 = title, time.perf_counter()
        self._prog: Progress | None = None
        self._task: Any = None

    def __enter__(self) -> _Steps:
        if console.is_terminal and _LOG["mode"] == "text":
            self._prog = Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                                  console=console, transient=True)
            self._prog.__enter__()
            self._task = self._prog.add_task(self.title, total=None)
        return self

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
                                         "peak_rss_mib": round(_peak_rss_mib(), 1)}) + "\n")
            sys.stdout.flush()
        elif self._prog is not None:
            self._prog.update(self._task, description=f"{self.title}: {message}")
        else:
            console.print(f"[{elapsed:7.1f} s] {self.title}: {message} (peak {_peak_rss_mib():,.0f} MiB)",
                          soft_wrap=True)
            sys.stdout.flush()


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


def _window_option(text: str, engine: str) -> float | str | None:
    """``--window``: seconds (0: one window) or ``auto``, which the local engine sizes from the
    dataset (:func:`tertiary.runtime.windows.auto_window_s`) and the Dask engine reads as
    :data:`~tertiary.runtime.windows.DEFAULT_WINDOW_S` (its slices and overlaps are multiples of it)."""
    if is_auto(text):
        return DEFAULT_WINDOW_S if engine == "dask" else AUTO_WINDOW
    (value,) = _floats(text, 1, "--window", "SECONDS or auto")
    return None if value == 0 else check_window(value)


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
    return check_scenario(dataclasses.replace(cfg, anomalies=anom))


def _names(text: str, known: tuple[str, ...] | list[str], option: str) -> tuple[str, ...]:
    chosen = tuple(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    bad = [m for m in chosen if m not in known]
    if bad:
        raise OptionError(f"unknown {', '.join(bad)}; choose from {', '.join(known)}", option=option)
    return chosen


def _origin(text: str | None) -> tuple[float, float, float] | None:
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


def _writable_dir(path: Path, option: str) -> None:
    """Refuse --out values that cannot become a directory, before any work is done."""
    if path.exists() and not path.is_dir():
        raise OptionError(f"{path} is a file, not a directory", option=option)
    parent = path if path.exists() else next((p for p in path.parents if p.exists()), Path("."))
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise OptionError(f"cannot create or write {path} ({parent} is not writable)", option=option)


def holds_run(path: Path) -> bool:
    """True when ``path`` already holds a run (its database, report or a windowed run's manifest)."""
    return any((path / f).exists() for f in ("results.duckdb", "report.html", "manifest.json"))


def _refuse_incomplete(run_dir: Path) -> None:
    """A :class:`DataError` when ``run_dir`` holds a windowed run that is not complete."""
    from tertiary.runtime.windows import incomplete_message
    text = incomplete_message(run_dir)
    if text:
        raise DataError(text, path=str(run_dir))


def choose_run_dir(out: Path | None, scenario_name: str, force: bool) -> tuple[Path, str | None]:
    """Where this run goes, and a note when it is not where the user may expect.

    An explicit ``--out`` that already holds a run is refused unless ``force``; without ``--out``
    the run goes to ``runs/<scenario>``, or to the first free ``runs/<scenario>-N`` when that holds
    an earlier run, so that no run is ever overwritten silently."""
    if out is not None:
        _writable_dir(out, "--out")
        if holds_run(out) and not force:
            raise OptionError(f"{out} already holds a run; give --force to replace it, or another --out",
                              option="--out")
        return out, None
    if not scenario_name.replace("-", "_").isidentifier():
        raise OptionError(f"scenario name {scenario_name!r} cannot name a run directory; give --out", option="--out")
    base = RUNS_DIR / scenario_name
    _writable_dir(base, "--out")
    if force or not holds_run(base):
        return base, None
    n = 2
    while holds_run(RUNS_DIR / f"{scenario_name}-{n}"):
        n += 1
    new = RUNS_DIR / f"{scenario_name}-{n}"
    return new, f"{base} holds an earlier run; this run goes to {new} (--force replaces {base})"


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
QuietOpt = Annotated[bool, typer.Option("--quiet", help="print no progress (the final summary only)")]
LogFormatOpt = Annotated[str, typer.Option(help="progress lines: text, or json (one object per line: t_s, "
                                                "task, step, peak_rss_mib) for schedulers")]


@app.command()
def simulate(
    scenario: Annotated[str, typer.Argument(help="built-in scenario name (see `tertiary scenarios`) or a TOML file")],
    out: Annotated[Path, typer.Option("--out", "-o", help="output dataset directory")],
    runs: RunsOpt = None, seed: SeedOpt = None, aircraft: AircraftOpt = None, radars: RadarsOpt = None,
    duration: DurationOpt = None, truth: TruthOpt = None, noise_factor: NoiseOpt = None,
    noise_window: NoiseWinOpt = None, dropout: DropoutOpt = None, outliers: OutliersOpt = None,
    bias_step: BiasStepOpt = None,
    force: Annotated[bool, typer.Option(help="replace a dataset already in OUT")] = False,
    quiet: QuietOpt = False, log_format: LogFormatOpt = "text",
    fmt: Annotated[str, typer.Option("--format", help="parquet, or asterix: also recording.ast (CAT048, CAT034, "
                                                      "CAT021) and sites.toml")] = "parquet",
    window: Annotated[Optional[float], typer.Option(help="write window by window (SECONDS each) into "
                                                         "reports/part-NNNN.parquet and truth/part-NNNN.parquet "
                                                         "[default: national: its block; others: single files]")] = None,
) -> None:
    """Simulate SCENARIO and write radars/reports/truth Parquet files and scenario.toml to OUT."""
    _set_log(quiet, log_format)
    if fmt not in ("parquet", "asterix"):
        raise OptionError(f"use parquet or asterix, got {fmt!r}", option="--format")
    if scenario == "adsb" and truth is None:
        raise OptionError("the adsb scenario needs --truth FILE (an OpenSky/traffic-schema Parquet file)",
                          option="--truth")
    _writable_dir(out, "--out")
    if ((out / "reports.parquet").exists() or (out / "parts.json").exists()) and not force:
        raise OptionError(f"{out} already holds a dataset; give --force to replace it", option="--out")
    cfg = build_scenario(scenario, runs=runs, seed=seed, aircraft=aircraft, radars=radars, duration=duration,
                         truth=truth, noise_factor=noise_factor, noise_window=noise_window, dropout=dropout,
                         outliers=outliers, bias_step=bias_step)
    t = time.perf_counter()
    if window is not None or cfg.kind == "national":
        if fmt != "parquet":
            raise OptionError("a windowed simulation writes Parquet parts only", option="--format")
        with _Steps(f"simulate {cfg.name}") as say:
            done = write_stream(cfg, out, window if window is not None else
                                (cfg.national.block_s if cfg.national else None), progress=say)
        console.print(f"wrote {out}/ ({done['reports']:,} reports, {done['truth_rows']:,} truth rows in "
                      f"{len(done['parts'])} parts, {len(cfg.radars)} radars, {cfg.runs} run(s)) in "
                      f"{time.perf_counter() - t:.1f} s", soft_wrap=True)
        return
    with _Steps(f"simulate {cfg.name}") as say:
        ds = _simulate(cfg, progress=say)
    write_dataset(ds, out)
    console.print(f"wrote {out}/ ({ds.reports.height:,} reports, {ds.truth.height:,} truth rows, "
                  f"{len(cfg.radars)} radars, {cfg.runs} run(s)) in {time.perf_counter() - t:.1f} s", soft_wrap=True)
    if ds.removed.height:
        console.print(f"ADS-B cleaning removed {ds.removed.height:,} rows (truth_removed.parquet)")
    if fmt == "asterix":
        from tertiary.io.asterix.encode import write_recording
        rec, sites, day = write_recording(ds, out)
        runs_note = f" (run 0 of {cfg.runs})" if cfg.runs > 1 else ""
        console.print(f"wrote {rec}{runs_note} and {sites}; import with: tertiary import asterix {rec} "
                      f"--sites {sites} --date {day} --out DATASET_DIR", soft_wrap=True)


@app.command()
def validate(
    dataset: Annotated[Path, typer.Argument(help="dataset directory: radars.parquet, reports.parquet, "
                                                 "optional truth.parquet and scenario.toml")],
    strict: Annotated[bool, typer.Option(help="fail (exit 3) on the first problem instead of listing rejects")] = False,
    origin: Annotated[Optional[str], typer.Option(help="LAT,LON[,ALT_M] processing centre when the dataset has no "
                                                       "scenario.toml [default: mean of the radar sites]")] = None,
) -> None:
    """Print, stage by stage, every report `tertiary run` will reject, and why (same rules, same counts)."""
    ds = read_dataset(dataset, origin=_origin(origin))
    screened = pipeline.screen(ds, pipeline.PipelineConfig(strict=strict))
    for note in screened.notes:
        console.print(f"note: {note}", soft_wrap=True)
    rejects = screened.rejects
    n_reports = ds.reports.height
    n_rej = int(rejects.filter(pl.col("input_table") == "reports").height) if rejects.height else 0
    if rejects.height == 0:
        console.print(f"valid: {n_reports:,} reports, {ds.radars.height} radars, {ds.truth.height:,} truth rows; "
                      "run will reject nothing")
        return
    summary = (rejects.group_by("stage", "input_table", "reason").len()
               .sort(["stage", "len"], descending=[False, True]))
    table = Table(title=f"run will reject {rejects.height:,} rows ({n_rej:,} of {n_reports:,} reports)")
    for col, justify in (("stage", "left"), ("input table", "left"), ("reason", "left"), ("rows", "right")):
        table.add_column(col, justify=justify, overflow="fold")
    for stage, tab, reason, n in summary.iter_rows():
        table.add_row(str(stage), str(tab), str(reason), f"{n:,}")
    console.print(table)


@app.command()
def run(
    dataset: Annotated[Optional[Path], typer.Argument(help="dataset directory [default: simulate --scenario]")] = None,
    scenario: Annotated[str, typer.Option(help="scenario simulated when no DATASET is given")] = DEFAULT_SCENARIO,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="run directory [default: runs/<scenario>, or "
                                                                     "runs/<scenario>-N when that holds a run]")] = None,
    force: Annotated[bool, typer.Option(help="replace a run already in --out")] = False,
    methods: Annotated[str, typer.Option(help="comma-separated fusion methods")] = DEFAULT_METHODS,
    filters: Annotated[str, typer.Option(help="comma-separated secondary tracker filters ('' for none); choose "
                                              f"from {', '.join(sorted(REGISTRY))}")] = DEFAULT_FILTERS,
    centralized: Annotated[bool, typer.Option(help="also run the centralised measurement-level reference")] = True,
    strict: Annotated[bool, typer.Option(help="stop (exit 3) on the first invalid input row")] = False,
    report: Annotated[bool, typer.Option("--report/--no-report",
                                         help="also write RUN_DIR/report.html (plotly, self-contained)")] = True,
    safety_picture: Annotated[str, typer.Option(help="picture conflict prediction runs on: tracks (the tracker's "
                                                     "confirmed tracks, per method+filter) or fused")] = "tracks",
    origin: Annotated[Optional[str], typer.Option(help="LAT,LON[,ALT_M] processing centre for a dataset without "
                                                       "scenario.toml [default: mean of the radar sites]")] = None,
    runs: RunsOpt = None, seed: SeedOpt = None, aircraft: AircraftOpt = None, radars: RadarsOpt = None,
    duration: DurationOpt = None, truth: TruthOpt = None, noise_factor: NoiseOpt = None,
    noise_window: NoiseWinOpt = None, dropout: DropoutOpt = None, outliers: OutliersOpt = None,
    bias_step: BiasStepOpt = None,
    quiet: QuietOpt = False, log_format: LogFormatOpt = "text",
    register: Annotated[bool, typer.Option("--register/--no-register",
                                           help="correct each radar's range/azimuth bias and clock offset before "
                                                "alignment: DATASET/registration.parquet (from `tertiary register`) "
                                                "when present, else estimated radar to radar")] = False,
    indicators: Annotated[bool, typer.Option(help="also write the §1.7/§5.1 indicators of every tracker picture "
                                                  "(metrics stage 'indicators'; needs truth)")] = False,
    assignment: Annotated[str, typer.Option(help="association with >= 3 radars: pairwise (to the reference "
                                                 "radar) or joint (multi-dimensional minimum)")] = "pairwise",
    gate: Annotated[str, typer.Option(help="association gate: box, mahalanobis or bayes (minimum-error "
                                           "H1/H2 threshold)")] = "box",
    radar_health: Annotated[bool, typer.Option(help="also write each radar's health (windowed-NIS divergence "
                                                    "alarm, adaptive R; metrics stage 'radar_health')")] = False,
    collection: Annotated[Optional[str], typer.Option(help="report collection queue ahead of alignment (§1.4): "
                                                           "refusals, waiting or limited; lost reports go to "
                                                           "rejects [default: none]")] = None,
    service_time: Annotated[float, typer.Option(help="mean processing time of one report (s), with --collection")] = 0.01,
    service_model: Annotated[str, typer.Option(help="processing time: exponential or deterministic")] = "exponential",
    max_wait: Annotated[float, typer.Option(help="T_wait of --collection limited (s)")] = 0.1,
    range_channel: Annotated[Optional[str], typer.Option(help="recompute the radars' local tracks with this range "
                                                              "channel: singer, kinematic or kinematic_dynamic "
                                                              "(chapter 3, needs Mode S EHS report columns; Singer "
                                                              "for tracks without) [default: the dataset's "
                                                              "estimates]")] = None,
    range_variant: Annotated[str, typer.Option(help="(3.11)/(3.62) of --range-channel: corrected or printed")]
        = "corrected",
    window: Annotated[str, typer.Option("--window", metavar="SECONDS|auto",
                                        help="process the recording in time windows of this many seconds (>= 1; "
                                             "0: one window; auto: about 50 000 reports in the busiest window divided by "
                                             "the number of fusion methods, 60 s to 1 h, "
                                             "300 s with --engine dask), carrying every stage's state; each "
                                             "window is stored as it completes")]
        = AUTO_WINDOW,
    resume: Annotated[Optional[Path], typer.Option("--resume", help="continue the killed run in RUN_DIR from its "
                                                                    "last complete window (same options and "
                                                                    "dataset)")] = None,
    engine: Annotated[str, typer.Option(help="local (this process) or dask (dask.distributed: Monte-Carlo runs "
                                             "and, with --slice, time slices in parallel)")] = "local",
    workers: Annotated[Optional[int], typer.Option(help="--engine dask: workers of the LocalCluster "
                                                        "[default: one per core]")] = None,
    scheduler: Annotated[Optional[str], typer.Option(help="--engine dask: address of a running scheduler "
                                                          "(tcp://host:8786) instead of a LocalCluster")] = None,
    slice_s: Annotated[Optional[float], typer.Option("--slice", help="--engine dask: cut each run into time slices "
                                                                     "of this many seconds")] = None,
    overlap_s: Annotated[Optional[float], typer.Option("--overlap", help="--engine dask: warm-up before each slice "
                                                                         "(s, a multiple of --window; its outputs "
                                                                         "are discarded, ids stitched in it) "
                                                                         "[default: one window]")] = None,
    tables: Annotated[str, typer.Option("--tables", help="database: copy the streamed tables into "
                                                          "results.duckdb; parquet: keep them as Parquet in "
                                                          "RUN_DIR/tables with views over them in the database "
                                                          "(no copy: long recordings)")] = "database",
) -> None:
    """The main job: (simulate,) validate, align, associate, fuse, cluster, track, predict conflicts,
    evaluate and store everything in RUN_DIR/results.duckdb, then write RUN_DIR/report.html.

    Scenario options (--runs ... --bias-step) apply when the job simulates (no DATASET)."""
    _set_log(quiet, log_format)
    window_s = _window_option(window, engine)
    if engine not in ("local", "dask"):
        raise OptionError(f"choose local or dask, got {engine!r}", option="--engine")
    # before any simulation; the run directory, when not given, is made under this one
    pipeline.check_tables(tables, out if out is not None else resume if resume is not None else Path.cwd())
    if engine == "local":
        for name, value in (("--workers", workers), ("--scheduler", scheduler), ("--slice", slice_s),
                            ("--overlap", overlap_s)):
            if value is not None:
                raise OptionError("applies with --engine dask only", option=name)
    elif resume is not None:
        raise OptionError("a Dask run is not resumable; rerun it", option="--resume")
    elif range_channel is not None:
        raise OptionError("the Dask workers read the dataset's own estimates; use --engine local",
                          option="--range-channel")
    if resume is not None:
        if out is not None and out.resolve() != resume.resolve():
            raise OptionError("--resume names the run directory; omit --out or give the same directory",
                              option="--resume")
        if not (resume / "manifest.json").is_file():
            raise OptionError(f"{resume} holds no windowed run to resume (no manifest.json)", option="--resume")
        out, force = resume, True
    cfg = pipeline.PipelineConfig(methods=_names(methods, ALL_METHODS, "--methods"),
                                  filters=_names(filters, sorted(REGISTRY), "--filters"),
                                  centralized=centralized, strict=strict, safety_picture=safety_picture,
                                  indicators=indicators, association=_association(assignment, gate),
                                  radar_health=radar_health)
    if collection is not None:   # checked here, before any simulation
        from tertiary.sensors.collection import CollectionConfig
        cfg = dataclasses.replace(cfg, collection=CollectionConfig(collection, service_time, service_model, max_wait))
    if range_channel is not None:
        cfg = _local_range_channel(cfg, range_channel, range_variant)
    pipeline.check_config(cfg)
    # a fresh install compiles the kernels in the background from here, while the job simulates
    # or reads its input (the pipeline would start it only once the input is read)
    from tertiary.runtime.warmup import kernels_for, warm
    warm(kernels_for(cfg.filters))
    sim = dict(runs=runs, seed=seed, aircraft=aircraft, radars=radars, duration=duration, truth=truth,
               noise_factor=noise_factor, noise_window=noise_window, dropout=dropout, outliers=outliers,
               bias_step=bias_step)
    given = [k for k, v in sim.items() if v is not None]
    if dataset is not None:
        if given:
            raise OptionError(f"--{given[0].replace('_', '-')} applies only when the job simulates; "
                              "omit DATASET or the option", option=f"--{given[0].replace('_', '-')}")
        ds = read_dataset(dataset, origin=_origin(origin), lazy=True)   # read window by window
        run_dir, note = choose_run_dir(out, ds.scenario.name, force)
    else:
        scen = build_scenario(scenario, **sim)
        run_dir, note = choose_run_dir(out, scen.name, force)   # refused before simulating, not after
        with _Steps(f"simulate {scen.name}") as say:
            ds = _simulate(scen, progress=say)
    if note:
        console.print(f"note: {note}", soft_wrap=True)
    if register:
        cfg = dataclasses.replace(cfg, register=True, registration=_stored_registration(dataset))
    if range_channel is not None:   # alignment recomputes every local track with the chosen channel
        ds = dataclasses.replace(ds, reports=ds.reports.drop([c for c in ESTIMATE_COLUMNS if c in ds.reports.columns]))
    if engine == "dask":
        from tertiary.runtime.dask_engine import run_dask
        source = dataset
        if source is None:     # the workers read the dataset from disk
            source = write_dataset(ds, run_dir / "input")
        with _Steps("pipeline (dask)") as say:
            overlap = overlap_s if overlap_s is not None else (window_s or 120.0)
            db = run_dask(source, run_dir, cfg, workers=workers, scheduler=scheduler, window_s=window_s,
                          slice_s=slice_s, overlap_s=overlap, progress=say, tables=tables)
    else:
        with _Steps("pipeline") as say:
            db = pipeline.run(ds, run_dir, cfg, progress=say, window_s=window_s, resume=resume is not None,
                              dataset_label=str(dataset) if dataset is not None else "", tables=tables)
    html_path = None
    if report:
        from tertiary.report.html import build_report
        with _Steps("report") as say:
            html_path = build_report(run_dir, progress=say)
    print_summary(db, html_path)


def _local_range_channel(cfg: pipeline.PipelineConfig, channel: str, variant: str) -> pipeline.PipelineConfig:
    """``--range-channel``/``--range-variant`` into ``cfg.align.local_tracker`` (the reports' own
    estimates are then dropped, so alignment recomputes every local track with it)."""
    try:
        tracker = dataclasses.replace(cfg.align.local_tracker, range_channel=channel, range_variant=variant)
    except OptionError as exc:
        option = "--range-channel" if "channel" in str(exc) else "--range-variant"
        raise OptionError(str(exc).split(": ", 1)[-1], option=option) from exc
    return dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, local_tracker=tracker))


def _association(assignment: str, gate: str) -> "AssociationConfig":
    """The association options of ``tertiary run`` (--assignment, --gate)."""
    from tertiary.stages.association.associate import AssociationConfig
    from tertiary.stages.association.gating import GatingConfig
    if assignment not in ("pairwise", "joint"):
        raise OptionError(f"choose pairwise or joint, got {assignment!r}", option="--assignment")
    if gate not in ("box", "mahalanobis", "bayes"):
        raise OptionError(f"choose box, mahalanobis or bayes, got {gate!r}", option="--gate")
    return AssociationConfig(assignment=assignment, gating=GatingConfig(method=gate))  # type: ignore[arg-type]


def _stored_registration(dataset: Path | None) -> tuple[tuple[float, ...], ...]:
    """Rows of DATASET/registration.parquet for PipelineConfig.registration (() = estimate)."""
    from tertiary.sensors.registration import read_table
    path = None if dataset is None else dataset / "registration.parquet"
    if path is None or not path.exists():
        return ()
    table = read_table(path)
    gain = table["range_gain"].fill_nan(0.0).fill_null(0.0) if "range_gain" in table.columns else \
        pl.Series([0.0] * table.height)
    return tuple(zip(table["radar_id"].cast(pl.Float64).to_list(), table["range_bias_m"].to_list(),
                     table["azimuth_bias_deg"].to_list(), table["time_offset_s"].to_list(), gain.to_list()))


@app.command("register")
def register_cmd(
    dataset: Annotated[Path, typer.Argument(help="dataset directory (radars.parquet, reports.parquet, optional "
                                                 "truth.parquet); registration.parquet is written there")],
    method: Annotated[str, typer.Option(help="auto (reference when truth is present, else multi), reference "
                                             "(against truth/ADS-B positions) or multi (radar to radar by Mode S)")] = "auto",
    gain: Annotated[bool, typer.Option(help="also estimate a range gain per radar")] = False,
    steps: Annotated[bool, typer.Option("--steps/--no-steps", help="also test each radar for a bias step "
                                                                   "(windowed innovation-mean test)")] = True,
    window: Annotated[int, typer.Option(help="reports per window of the step test")] = 60,
    origin: Annotated[Optional[str], typer.Option(help="LAT,LON[,ALT_M] processing centre for a dataset without "
                                                       "scenario.toml [default: mean of the radar sites]")] = None,
) -> None:
    """Estimate each radar's range bias, azimuth bias and clock offset (with 1-sigma) and write
    DATASET/registration.parquet; signs as the simulator's bias_range_m, bias_azimuth_deg, time_offset_s."""
    from tertiary.sensors import registration
    from tertiary.store.run_store import write_parquet_atomic
    if method not in ("auto", "reference", "multi"):
        raise OptionError(f"choose auto, reference or multi, got {method!r}", option="--method")
    if window < 5:
        raise OptionError(f"must be at least 5, got {window}", option="--window")
    ds = read_dataset(dataset, origin=_origin(origin))
    ing = pipeline.ingest(ds)
    res = registration.estimate(ing.reports, ing.radars, ds.origin, ing.truth,
                                registration.RegistrationConfig(method=method, gain=gain))
    for note in ds.notes + res.notes:
        console.print(f"note: {note}", soft_wrap=True)
    table = Table(title=f"registration ({res.table['method'][0] if res.table.height else method})")
    for col in ("radar", "name", "range bias m", "azimuth bias deg", "clock offset s", "range gain", "reports"):
        table.add_column(col, justify="left" if col == "name" else "right")
    for r in res.table.iter_rows(named=True):
        g = "–" if not math.isfinite(r["range_gain"]) else f"{r['range_gain']:+.2e} ± {r['range_gain_sigma']:.1e}"
        table.add_row(str(r["radar_id"]), str(r["name"]), f"{r['range_bias_m']:+.2f} ± {r['range_bias_sigma_m']:.2f}",
                      f"{r['azimuth_bias_deg']:+.4f} ± {r['azimuth_bias_sigma_deg']:.4f}",
                      f"{r['time_offset_s']:+.4f} ± {r['time_offset_sigma_s']:.4f}", g, f"{r['n_reports']:,}")
    console.print(table)
    if steps:
        found = registration.detect_steps(res.residuals, window=window)
        for r in found.iter_rows(named=True):
            console.print(f"bias step: radar {r['radar_id']} {r['channel']} {r['step']:+.3f} at "
                          f"t = {r['alarm_t_s']:.1f} s (alarm, z = {r['z']:+.1f})")
        if found.height == 0:
            console.print("no bias step detected")
    path = dataset / "registration.parquet"
    write_parquet_atomic(res.table, path)
    console.print(f"wrote {path}", soft_wrap=True)


# --------------------------------------------------------------------------- result summary


def _metric(metrics: pl.DataFrame, stage: str, metric: str) -> pl.DataFrame:
    if metrics.height == 0:
        return metrics
    return metrics.filter((pl.col("stage") == stage) & (pl.col("metric") == metric) & (pl.col("segment") == "all"))


def _value(frame: pl.DataFrame, method: str) -> float | None:
    row = frame.filter(pl.col("method") == method)
    return float(row["value"][0]) if row.height else None


def _m(v: float | None, unit: str = " m") -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:,.1f}{unit}"


def _json_or_text(text: str) -> Any:
    try:
        return json.loads(text)
    except (json.JSONDecodeError, TypeError):
        return text


def run_summary(db: Path) -> list[str]:
    """The end-of-run summary as plain lines: input and rejects, targets against aircraft, the
    horizontal and vertical accuracy of every picture, alerts and losses of separation."""
    from tertiary.store.run_store import RunStore
    with RunStore.open(db.parent, read_only=True) as store:
        tables = set(store.tables())
        record = {k: _json_or_text(v) for k, v in store.sql("SELECT key, value FROM run").iter_rows()}
        metrics = store.sql("SELECT * FROM metrics") if "metrics" in tables else pl.DataFrame()
        aircraft = (int(store.sql("SELECT count(DISTINCT truth_id) AS n FROM truth")["n"][0])
                    if "truth" in tables else 0)
        n_runs = (int(store.sql("SELECT count(DISTINCT run) AS n FROM reports")["n"][0])
                  if "reports" in tables else 1)
    rows, timings = record.get("rows", {}), record.get("timings", {})
    wall = timings.get("wall_s", timings.get("total_s"))
    lines = [f"run {record.get('scenario', '?')}: {rows.get('reports_in', 0):,} reports in, "
             f"{rows.get('reports_rejected', 0):,} rejected; wall time {_m(wall, ' s')}"]
    runs_text = f" in each of {n_runs} Monte-Carlo runs" if n_runs > 1 else ""
    aircraft = f" for {aircraft} aircraft{runs_text}" if aircraft else ""
    if "confirmed_targets" in rows:
        over = " (summed over runs)" if n_runs > 1 else ""
        lines.append(f"system targets: {rows['confirmed_targets']} confirmed{over}{aircraft} "
                     f"({rows.get('tentative_targets', 0)} tentative, clutter-only, kept in fused with their flag)")
    else:
        lines.append(f"system targets (fused, clutter-only ones included): {rows.get('targets', '–')}{aircraft}")
    tracks = _metric(metrics, "tracker", "tracks")
    for stage in ("fusion", "tracker"):
        horiz, height = _metric(metrics, stage, "rmse_horizontal_m"), _metric(metrics, stage, "rmse_height_m")
        pos = _metric(metrics, stage, "rmse_pos_m")
        for method in sorted(pos["method"].unique().to_list() if pos.height else []):
            n = _value(tracks, method) if stage == "tracker" else None
            lines.append(f"  {stage:8s} {method:28s} RMSE horizontal {_m(_value(horiz, method)):>9s}, "
                         f"vertical {_m(_value(height, method)):>9s}, 3-D {_m(_value(pos, method)):>9s}"
                         + (f"; {n:,.0f} confirmed tracks" if n is not None else ""))
    per_hour = _metric(metrics, "safety", "alerts_per_hour")
    if per_hour.height:
        lines.append("safety (alert episodes per aircraft pair, scored against real losses of separation):")
    for method in sorted(per_hour["method"].unique().to_list() if per_hour.height else []):
        v = {k: _value(_metric(metrics, "safety", k), method) for k in
             ("genuine_alerts", "nuisance_alerts", "false_alerts", "los_episodes", "alerted_los", "missed_los",
              "warning_median_s")}
        count = lambda k: "–" if v[k] is None or not math.isfinite(v[k]) else f"{v[k]:,.0f}"  # noqa: E731
        lines.append(f"  safety   {method:28s} {_m(_value(per_hour, method), ' alerts/h')}: {count('genuine_alerts')} "
                     f"genuine, {count('nuisance_alerts')} nuisance, {count('false_alerts')} false; losses of "
                     f"separation {count('los_episodes')}, alerted {count('alerted_los')}, missed "
                     f"{count('missed_los')}; median warning {_m(v['warning_median_s'], ' s')}")
    if not per_hour.height and rows.get("alert_rows"):
        lines.append(f"alerts: {rows['alert_rows']:,} alert rows (no truth to score them against)")
    for note in record.get("notes", [])[:5]:
        lines.append(f"note: {note}")
    return lines


def print_summary(db: Path, html_path: Path | None) -> None:
    for line in run_summary(db):
        console.print(line, soft_wrap=True)
    console.print(f"results: {db}", soft_wrap=True)
    if html_path is not None:
        console.print(f"report:  {html_path} ({html_path.stat().st_size / 1e6:.1f} MB)", soft_wrap=True)


@app.command("evaluate")
def evaluate_cmd(
    tracks: Annotated[list[Path], typer.Argument(help="picture file(s): Parquet in the tracks schema (epoch, "
                                                       "track_id, x_m ... vz_mps in the reference's ENU frame); "
                                                       "several files give a comparison")],
    out: Annotated[Path, typer.Option("--out", "-o", help="run directory for results.duckdb and report.html")],
    truth: Annotated[Optional[Path], typer.Option(help="reference: Parquet in the truth schema (truth_id, time, "
                                                       "x_m ... vz_mps[, alt_m]) in the same frame")] = None,
    dataset: Annotated[Optional[Path], typer.Option(help="dataset directory whose truth.parquet is the reference "
                                                         "(its radars give the range rings)")] = None,
    requirements: Annotated[Optional[Path], typer.Option(help="requirements TOML with pass/fail thresholds "
                                                              "[default: none; see datasets/requirements]")] = None,
    reference: Annotated[str, typer.Option(help="with --dataset: truth (the dataset's truth.parquet), "
                                                "reconstruct (smoothed offline from every radar plot; scored "
                                                "against the truth too when there is one) or adsb (the --adsb "
                                                "recording, quality-filtered)")] = "truth",
    adsb: Annotated[Optional[Path], typer.Option(help="ADS-B recording (OpenSky/traffic-schema Parquet) for "
                                                      "--reference adsb")] = None,
    force: Annotated[bool, typer.Option(help="replace a run already in --out")] = False,
    report: Annotated[bool, typer.Option("--report/--no-report", help="also write RUN_DIR/report.html")] = True,
) -> None:
    """Score pictures that tertiary did not produce (or did) against a reference: one geometric
    matching, the surveillance metrics (accuracy, along/across track, latency, update
    probability, continuity, false/split/merged tracks, identity) by altitude band, range ring
    and flight phase, and requirements with pass/fail."""
    from tertiary.evaluation.evaluate import evaluate_pictures, read_parquet_file, read_pictures
    from tertiary.evaluation.requirements import load_requirements
    from tertiary.store.run_store import RunStore, record_run
    if (truth is None) == (dataset is None):
        raise OptionError("give the reference with exactly one of --truth FILE or --dataset DIR", option="--truth")
    if reference not in ("truth", "reconstruct", "adsb"):
        raise OptionError(f"choose truth, reconstruct or adsb, got {reference!r}", option="--reference")
    if reference in ("reconstruct", "adsb") and dataset is None:
        raise OptionError(f"--reference {reference} needs --dataset DIR (its frame and radars)", option="--reference")
    if (reference == "adsb") != (adsb is not None):
        raise OptionError("--adsb FILE goes with --reference adsb", option="--adsb")
    from tertiary.evaluation.evaluate import EvaluationConfig, reference_error_metrics
    from tertiary.evaluation.matching import MatchConfig
    ecfg = EvaluationConfig()
    radars, frame, reports, truth_ref = None, None, None, None
    if dataset is not None:
        ds = read_dataset(dataset)
        ref, radars, frame, reports = ds.truth, ds.radars, ds.origin, ds.reports
        if reference == "reconstruct":
            from tertiary.evaluation.evaluate import reconstructed_reference
            key = "truth_id" if "truth_id" in reports.columns and reports["truth_id"].null_count() < reports.height \
                else "mode_s"
            truth_ref, ref = ref, reconstructed_reference(reports, radars, frame, key=key)
        elif reference == "adsb":
            from tertiary.evaluation.evaluate import adsb_reference_table
            raw = read_parquet_file(adsb)
            truth_ref, (ref, _removed) = ref, adsb_reference_table(raw, frame)
            ecfg = EvaluationConfig(match=MatchConfig(max_gap_s=10.0))   # short gaps only
        if ref.height == 0:
            raise DataError("the dataset has no usable truth.parquet to evaluate against", path=str(dataset))
    else:
        ref = read_parquet_file(truth)
    reqs = load_requirements(requirements) if requirements is not None else None
    if out.exists() and (out / "results.duckdb").exists() and not force:
        raise OptionError(f"{out} already holds a run; choose another --out or add --force", option="--out")
    pictures = read_pictures(tracks)
    t = time.perf_counter()
    with _Steps("evaluate") as say:
        say("match and score")
        ev = evaluate_pictures(pictures, ref, radars=radars, frame=frame, requirements=reqs, cfg=ecfg)
        extra = [reference_error_metrics(ev.metrics, ref)]
        if reference == "reconstruct" and truth_ref is not None and truth_ref.height:
            from tertiary.evaluation.evaluate import RECONSTRUCTED
            say("reconstructed reference against the truth")
            as_picture = ref.with_columns(pl.lit(0, pl.UInt32).alias("run"), pl.col("time").alias("epoch"),
                                          pl.col("truth_id").cast(pl.UInt64).alias("track_id"),
                                          pl.lit(RECONSTRUCTED).alias("method"))
            extra.append(evaluate_pictures(as_picture, truth_ref, radars=radars, frame=frame).metrics)
        if reports is not None and "truth_id" in reports.columns and reports["truth_id"].null_count() < reports.height:
            from tertiary.evaluation.radar_eval import radar_metrics
            say("per-radar evaluation")
            extra.append(radar_metrics(reports, radars, truth_ref if truth_ref is not None else ref, frame))
        if extra:
            ev.metrics = pl.concat([ev.metrics, *extra], how="vertical_relaxed")
        say("store")
        with RunStore.create(out) as store:
            store.write("tracks", pictures)
            store.write("truth", ref)
            store.write("metrics", ev.metrics)
            store.write("evaluation_matched", ev.matched.select(
                "run", "epoch", "method", "track_id", "truth_id", "match_cost"))
            if reqs is not None:
                store.write("requirements", ev.requirements)
            record_run(store, {"kind": "evaluation", "scenario": "evaluation",
                               "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                               "pictures": sorted(pictures["method"].unique().to_list()),
                               "tracks_files": [str(p) for p in tracks],
                               "reference": f"{truth or dataset} ({reference})",
                               "requirements": str(requirements or ""),
                               "status": "complete", "timings": {"wall_s": time.perf_counter() - t}})
    console.print(f"evaluated {pictures['method'].n_unique()} picture(s), {pictures.height:,} track rows, "
                  f"against {ref['truth_id'].n_unique():,} reference aircraft in {time.perf_counter() - t:.1f} s")
    _print_frame(ev.comparison, "Pictures compared (segment all)", 50)
    if reqs is not None:
        _print_frame(ev.requirements.select("requirement", "method", "metric", "breakdown", "threshold", "value",
                                            "n_samples", "verdict"), "Requirements", 200)
    console.print(f"results: {out / 'results.duckdb'}", soft_wrap=True)
    if report:
        from tertiary.report.html import build_report
        with _Steps("report") as say:
            html = build_report(out, progress=say)
        console.print(f"report:  {html}", soft_wrap=True)


@app.command("report")
def report_cmd(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="HTML file [default: RUN_DIR/report.html]")] = None,
) -> None:
    """Write the self-contained HTML report of a run (figures from the sql/ reports)."""
    _refuse_incomplete(run_dir)
    if not (run_dir / "results.duckdb").is_file():
        raise DataError("no run database here (expected results.duckdb)", path=str(run_dir))
    if out is not None and out.is_dir():
        raise OptionError(f"{out} is a directory; give a file name", option="--out")
    from tertiary.report.html import build_report
    t = time.perf_counter()
    with _Steps("report") as say:
        path = build_report(run_dir, out, progress=say)
    console.print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t:.1f} s",
                  soft_wrap=True)


# --------------------------------------------------------------------------- sql


def _param_value(text: str) -> Any:
    """A --param value: a JSON literal (number, null, true/false, "text") or else plain text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


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


def _print_frame(frame: pl.DataFrame, title: str, limit: int) -> None:
    shown = f" (first {limit:,} shown; --limit to change, --format csv for all)" if frame.height > limit else ""
    table = Table(title=title, caption=f"{frame.height:,} row{'' if frame.height == 1 else 's'}{shown}")
    for col, dtype in frame.schema.items():
        table.add_column(col, justify="right" if dtype.is_numeric() else "left", overflow="fold")
    cols = frame.columns
    for row in frame.head(limit).iter_rows():
        table.add_row(*[cell(v, c) for v, c in zip(row, cols)])
    console.print(table)


@app.command("sql")
def sql_cmd(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    name: Annotated[Optional[str], typer.Argument(help="named report (see --list)")] = None,
    list_: Annotated[bool, typer.Option("--list", help="list the named reports and their parameters")] = False,
    query: Annotated[Optional[str], typer.Option("--query", "-q", help="ad-hoc read-only SQL")] = None,
    param: Annotated[Optional[list[str]], typer.Option("--param", "-p",
                                                       help="report parameter NAME=VALUE (repeatable)")] = None,
    fmt: Annotated[str, typer.Option("--format", "-f", help="table (print), csv or parquet")] = "table",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="export file, written atomically; never a file "
                                                                     "inside the run directory")] = None,
    limit: Annotated[int, typer.Option(help="rows printed in table format")] = 100,
    timeout: Annotated[float, typer.Option(help="statement timeout in seconds")] = 60.0,
) -> None:
    """Run a named SQL report (sql/NAME.sql) or an ad-hoc read-only query on a run database.

    tertiary sql RUN_DIR --list; tertiary sql RUN_DIR NAME [-p KEY=VALUE] [--format csv|parquet --out FILE];
    tertiary sql RUN_DIR --query "SELECT ..."."""
    from tertiary.store import sql_reports

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
    _refuse_incomplete(run_dir)
    with sql_reports.open_read_only(run_dir) as store:
        if query is not None:
            frame, title = sql_reports.query(store, query, timeout_s=timeout), "query"
        else:
            frame, title = sql_reports.run_report(store, name, params, timeout_s=timeout), name
    if out is not None:
        path = sql_reports.export_frame(frame, out, fmt)
        console.print(f"wrote {path} ({frame.height:,} rows, {fmt})")
    elif fmt == "csv":
        sys.stdout.write(sql_reports.frame_to_csv(frame))
    else:
        _print_frame(frame, title, limit)


def _export_format(fmt: str, out: Path | None, run_dir: Path) -> str:
    if fmt not in ("table", "csv", "parquet"):
        raise OptionError(f"use table, csv or parquet, got {fmt!r}", option="--format")
    if out is None:
        if fmt == "parquet":
            raise OptionError("parquet needs --out FILE", option="--out")
        return fmt
    if out.is_dir():
        raise OptionError(f"{out} is a directory; give a file name", option="--out")
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


@app.command()
def scenarios() -> None:
    """List the built-in scenarios."""
    for name in builtin_scenarios():
        cfg = load_scenario(name)
        console.print(f"{name} ({cfg.kind}): {len(cfg.radars)} radars, {cfg.duration_s:.0f} s, {cfg.runs} run(s)")


from tertiary.cli.asterix import export_app, import_app  # noqa: E402  (sub-apps use this module's helpers)

app.add_typer(import_app, name="import")
app.add_typer(export_app, name="export")



def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
