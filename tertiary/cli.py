"""Command line: a thin layer over the public API (typer + rich)."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Annotated, Any, Optional

import polars as pl
import typer
from rich.console import Console
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from tertiary import pipeline, schema
from tertiary.filters import REGISTRY
from tertiary.fusion import METHODS
from tertiary.simulate import (Dataset, builtin_scenarios, load_scenario, read_dataset, simulate as _simulate,
                               write_dataset)
from tertiary.simulate.config import ScenarioConfig, with_radar_count

app = typer.Typer(add_completion=False, no_args_is_help=False,
                  help="Tertiary processing of multi-radar surveillance data and safety evaluation.")
console = Console()

DEFAULT_SCENARIO = "terminal-area"


def _progress() -> Progress:
    return Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console,
                    transient=False)


def _window(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    lo, hi = (float(v) for v in text.split(":"))
    return lo, hi


def build_scenario(scenario: str, *, runs: int | None = None, seed: int | None = None, aircraft: int | None = None,
                   radars: int | None = None, duration: float | None = None, truth: str | None = None,
                   noise_factor: float | None = None, noise_window: str | None = None,
                   dropout: str | None = None, outliers: float | None = None,
                   bias_step: str | None = None) -> ScenarioConfig:
    """A built-in scenario (or TOML file) with command-line overrides applied."""
    cfg = load_scenario(scenario)
    cfg = cfg.replace(runs=runs, seed=seed, duration_s=duration)
    if aircraft is not None:
        cfg = dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, aircraft=aircraft))
    if truth is not None:
        cfg = dataclasses.replace(cfg, adsb=dataclasses.replace(cfg.adsb, truth_file=truth))
    if radars is not None:
        cfg = with_radar_count(cfg, radars)
    anom = cfg.anomalies
    if noise_factor is not None:
        anom = dataclasses.replace(anom, noise_factor=noise_factor, noise_window_s=_window(noise_window))
    if dropout is not None:  # NAME:T0:T1
        name, lo, hi = dropout.split(":")
        anom = dataclasses.replace(anom, dropout_radar=name, dropout_window_s=(float(lo), float(hi)))
    if outliers is not None:
        anom = dataclasses.replace(anom, outlier_fraction=outliers)
    if bias_step is not None:  # T:DR_M:DAZ_DEG
        t, dr, daz = (float(v) for v in bias_step.split(":"))
        anom = dataclasses.replace(anom, bias_step_time_s=t, bias_step_range_m=dr, bias_step_azimuth_deg=daz)
    return dataclasses.replace(cfg, anomalies=anom)


def _simulate_with_progress(cfg: ScenarioConfig) -> Dataset:
    with _progress() as prog:
        task = prog.add_task(f"simulate {cfg.name}", total=None)
        ds = _simulate(cfg, progress=lambda m: prog.update(task, description=f"simulate {cfg.name}: {m}"))
        prog.update(task, description=f"simulate {cfg.name}: {ds.reports.height:,} reports")
    return ds


ScenarioOpt = Annotated[Optional[int], typer.Option(help="Monte-Carlo runs")]


@app.command()
def simulate(
    scenario: Annotated[str, typer.Argument(help="built-in scenario name or a TOML file")],
    out: Annotated[Path, typer.Option("--out", "-o", help="output dataset directory")],
    runs: ScenarioOpt = None,
    seed: Annotated[Optional[int], typer.Option(help="random seed (same seed, same files)")] = None,
    aircraft: Annotated[Optional[int], typer.Option(help="number of aircraft (terminal-area)")] = None,
    radars: Annotated[Optional[int], typer.Option(help="number of radars")] = None,
    duration: Annotated[Optional[float], typer.Option(help="duration in seconds")] = None,
    truth: Annotated[Optional[str], typer.Option(help="ADS-B trajectory file (OpenSky/traffic schema)")] = None,
    noise_factor: Annotated[Optional[float], typer.Option(help="measurement noise inflation (e.g. 3, 5, 6)")] = None,
    noise_window: Annotated[Optional[str], typer.Option(help="T0:T1 seconds for the noise inflation")] = None,
    dropout: Annotated[Optional[str], typer.Option(help="RADAR:T0:T1 radar dropout window")] = None,
    outliers: Annotated[Optional[float], typer.Option(help="fraction of gross-error reports")] = None,
    bias_step: Annotated[Optional[str], typer.Option(help="T:DRANGE_M:DAZ_DEG bias step")] = None,
) -> None:
    """Simulate SCENARIO and write radars/reports/truth Parquet files and scenario.toml to OUT."""
    if scenario == "adsb" and truth is None:
        raise typer.BadParameter("the adsb scenario needs --truth FILE", param_hint="--truth")
    cfg = build_scenario(scenario, runs=runs, seed=seed, aircraft=aircraft, radars=radars, duration=duration,
                         truth=truth, noise_factor=noise_factor, noise_window=noise_window, dropout=dropout,
                         outliers=outliers, bias_step=bias_step)
    t = time.perf_counter()
    ds = _simulate_with_progress(cfg)
    write_dataset(ds, out)
    console.print(f"[green]wrote[/] {out}/ ({ds.reports.height:,} reports, {ds.truth.height:,} truth rows, "
                  f"{len(cfg.radars)} radars, {cfg.runs} run(s)) in {time.perf_counter() - t:.1f} s")
    if ds.removed.height:
        console.print(f"ADS-B cleaning removed {ds.removed.height:,} rows (truth_removed.parquet)")


@app.command()
def validate(
    dataset: Annotated[Path, typer.Argument(help="dataset directory (radars/reports[/truth].parquet)")],
    strict: Annotated[bool, typer.Option(help="fail on the first problem instead of listing rejects")] = False,
) -> None:
    """Print what would be rejected, and why."""
    ds = read_dataset(dataset)
    try:
        ing = pipeline.ingest(ds, strict=strict)
    except schema.SchemaError as exc:
        console.print(f"[red]invalid:[/] {exc}")
        raise typer.Exit(1)
    for note in ing.notes:
        console.print(f"[yellow]note:[/] {note}")
    if ing.rejects.height == 0:
        console.print(f"[green]valid:[/] {ds.reports.height:,} reports, {ds.radars.height} radars, "
                      f"{ds.truth.height:,} truth rows; nothing rejected")
        return
    summary = ing.rejects.group_by("input_table", "reason").len().sort("len", descending=True)
    table = Table(title=f"{ing.rejects.height:,} rows would be rejected")
    for col in ("input table", "reason", "rows"):
        table.add_column(col)
    for row in summary.head(50).iter_rows():
        table.add_row(row[0], row[1], f"{row[2]:,}")
    console.print(table)
    raise typer.Exit(1 if strict else 0)


@app.command()
def run(
    dataset: Annotated[Optional[Path], typer.Argument(help="dataset directory; omitted = simulate --scenario")] = None,
    scenario: Annotated[str, typer.Option(help="scenario to simulate when no dataset is given")] = DEFAULT_SCENARIO,
    runs: ScenarioOpt = None,
    seed: Annotated[Optional[int], typer.Option()] = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="run directory (default runs/<scenario>)")] = None,
    strict: Annotated[bool, typer.Option(help="stop on the first invalid input row")] = False,
    methods: Annotated[str, typer.Option(help="comma-separated fusion methods")] = ",".join(METHODS),
    centralized: Annotated[bool, typer.Option(help="also run the centralised measurement-level bound")] = True,
    filters: Annotated[str, typer.Option(help="comma-separated secondary tracker filters ('' for none)")] = "singer,imm_sym",
    report: Annotated[bool, typer.Option("--report/--no-report",
                                         help="also write RUN_DIR/report.html (plotly, self-contained)")] = True,
) -> None:
    """The main job: (simulate,) validate, align, associate, fuse, cluster, track, evaluate and
    store everything in RUN_DIR/results.duckdb, then write the HTML report RUN_DIR/report.html."""
    t = time.perf_counter()
    chosen = tuple(m.strip() for m in methods.split(",") if m.strip())
    bad = [m for m in chosen if m not in METHODS]
    if bad:
        raise typer.BadParameter(f"unknown method(s) {', '.join(bad)}; choose from {', '.join(METHODS)}",
                                 param_hint="--methods")
    chosen_filters = tuple(f.strip() for f in filters.split(",") if f.strip())
    bad = [f for f in chosen_filters if f not in REGISTRY]
    if bad:
        raise typer.BadParameter(f"unknown filter(s) {', '.join(bad)}; choose from {', '.join(sorted(REGISTRY))}",
                                 param_hint="--filters")
    cfg = pipeline.PipelineConfig(methods=chosen, filters=chosen_filters, centralized=centralized, strict=strict)
    if dataset is None:
        ds = _simulate_with_progress(build_scenario(scenario, runs=runs, seed=seed))
    else:
        ds = read_dataset(dataset)
    run_dir = out or Path("runs") / ds.scenario.name
    with _progress() as prog:
        task = prog.add_task("pipeline", total=None)
        db = pipeline.run(ds, run_dir, cfg, progress=lambda m: prog.update(task, description=f"pipeline: {m}"))
        prog.update(task, description="pipeline: done")
    html_path = _report_with_progress(run_dir) if report else None
    console.print(f"[green]done[/] in {time.perf_counter() - t:.1f} s")
    console.print(f"  results: {db}")
    if html_path is not None:
        console.print(f"  report:  {html_path} ({html_path.stat().st_size / 1e6:.1f} MB)")


def _report_with_progress(run_dir: Path, out: Path | None = None) -> Path:
    from tertiary.report import build_report
    with _progress() as prog:
        task = prog.add_task("report", total=None)
        path = build_report(run_dir, out, progress=lambda m: prog.update(task, description=m))
        prog.update(task, description="report: written")
    return path


@app.command("report")
def report_cmd(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="HTML file (default RUN_DIR/report.html)")] = None,
) -> None:
    """Write the self-contained HTML report of a run (figures from the sql/ reports)."""
    if not (run_dir / "results.duckdb").is_file() and not run_dir.is_file():
        console.print(f"[red]error:[/] no run database at {run_dir / 'results.duckdb'}")
        raise typer.Exit(1)
    t = time.perf_counter()
    path = _report_with_progress(run_dir, out)
    console.print(f"[green]wrote[/] {path} ({path.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t:.1f} s")


def _param_value(text: str) -> Any:
    """A --param value: a JSON literal (number, null, true/false, "text") or else plain text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _print_frame(frame: pl.DataFrame, title: str, limit: int) -> None:
    from tertiary.report import _fmt
    table = Table(title=title, caption=(f"{frame.height:,} rows" + (f" (first {limit:,} shown)" if frame.height > limit
                                                                   else "")))
    for col, dtype in frame.schema.items():
        numeric = dtype.is_numeric()
        table.add_column(col, justify="right" if numeric else "left", overflow="fold")
    for row in frame.head(limit).iter_rows():
        table.add_row(*[_fmt(v) for v in row])
    console.print(table)


@app.command("sql")
def sql_cmd(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    name: Annotated[Optional[str], typer.Argument(help="named report (see --list)")] = None,
    list_: Annotated[bool, typer.Option("--list", help="list the named reports")] = False,
    query: Annotated[Optional[str], typer.Option("--query", "-q", help="ad-hoc read-only SQL")] = None,
    param: Annotated[Optional[list[str]], typer.Option("--param", "-p",
                                                       help="report parameter NAME=VALUE (repeatable)")] = None,
    fmt: Annotated[str, typer.Option("--format", "-f", help="table (print), csv or parquet")] = "table",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="export file (written atomically)")] = None,
    limit: Annotated[int, typer.Option(help="rows printed in table format")] = 100,
) -> None:
    """Run a named SQL report (sql/NAME.sql) or an ad-hoc read-only query on a run database.

    tertiary sql RUN_DIR --list; tertiary sql RUN_DIR NAME [-p KEY=VALUE] [--format csv|parquet --out FILE];
    tertiary sql RUN_DIR --query "SELECT ..."."""
    import duckdb

    from tertiary import sql_reports

    chosen = sum([bool(list_), name is not None, query is not None])
    if chosen != 1:
        console.print("[red]error:[/] give exactly one of NAME, --list or --query")
        raise typer.Exit(2)
    if list_:
        table = Table(title=f"named SQL reports ({sql_reports.sql_dir()})")
        table.add_column("name", no_wrap=True)
        table.add_column("answers", overflow="fold", ratio=3)
        table.add_column("parameters", overflow="fold", ratio=1)
        for rep in sql_reports.list_reports():
            params = ", ".join(f"{k}={json.dumps(v)}" for k, v in rep.params.items())
            table.add_row(rep.name, rep.description.split("Columns:")[0].replace("\n", " ").strip(), params)
        console.print(table)
        return
    if fmt not in ("table", "csv", "parquet"):
        raise typer.BadParameter("use table, csv or parquet", param_hint="--format")
    if fmt == "table" and out is not None:
        fmt = {".csv": "csv", ".parquet": "parquet"}.get(out.suffix.lower(), "")
        if not fmt:
            raise typer.BadParameter("give --format csv|parquet (or an .csv/.parquet file name)", param_hint="--out")
    if fmt == "parquet" and out is None:
        raise typer.BadParameter("parquet needs --out FILE", param_hint="--out")
    params: dict[str, Any] = {}
    for item in param or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise typer.BadParameter(f"expected NAME=VALUE, got {item!r}", param_hint="--param")
        params[key.strip()] = _param_value(value)
    if query is not None and params:
        raise typer.BadParameter("--param applies to named reports only", param_hint="--param")
    try:
        with sql_reports.open_read_only(run_dir) as store:
            if query is not None:
                frame, title = sql_reports.query(store, query), "query"
            else:
                frame, title = sql_reports.run_report(store, name, params), name
    except FileNotFoundError as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(1)
    except sql_reports.ReadOnlyQueryError as exc:
        console.print(f"[red]read-only:[/] {exc}")
        raise typer.Exit(1)
    except KeyError as exc:
        console.print(f"[red]error:[/] {exc.args[0] if exc.args else exc}")
        raise typer.Exit(1)
    except duckdb.Error as exc:
        msg = str(exc)
        if "read-only" in msg or "read_only" in msg.lower():
            console.print(f"[red]read-only:[/] the run database is opened read-only: {msg}")
        else:
            console.print(f"[red]SQL error:[/] {msg}")
        raise typer.Exit(1)
    if out is not None:
        path = sql_reports.export_frame(frame, out, fmt)
        console.print(f"[green]wrote[/] {path} ({frame.height:,} rows, {fmt})")
    elif fmt == "csv":
        sys.stdout.write(sql_reports.frame_to_csv(frame))
    else:
        _print_frame(frame, title, limit)


@app.command()
def scenarios() -> None:
    """List the built-in scenarios."""
    for name in builtin_scenarios():
        cfg = load_scenario(name)
        console.print(f"[bold]{name}[/] ({cfg.kind}): {len(cfg.radars)} radars, {cfg.duration_s:.0f} s, "
                      f"{cfg.runs} run(s)")


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
