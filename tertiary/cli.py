"""Command line: a thin layer over the public API (typer + rich)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Annotated, Optional

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
from tertiary.simulate.config import Anomalies, ScenarioConfig, with_radar_count

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
) -> None:
    """The main job: (simulate,) validate, align, associate, fuse, cluster, track, evaluate and
    store everything in RUN_DIR/results.duckdb."""
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
    console.print(f"[green]done[/] in {time.perf_counter() - t:.1f} s: {db}")


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
