"""``tertiary validate`` and ``tertiary register``: what a dataset holds before a run."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import polars as pl
import typer
from rich.table import Table

from tertiary.cli.common import OriginOpt, console, parse_origin, print_note
from tertiary.core.errors import OptionError
from tertiary.io.dataset import read_dataset
from tertiary.pipeline import PipelineConfig, ingest, screen
from tertiary.sensors import registration
from tertiary.store.run_store import write_parquet_atomic


def validate(
    dataset: Annotated[Path, typer.Argument(help="dataset directory: radars.parquet, reports.parquet, "
                                                 "optional truth.parquet and scenario.toml")],
    strict: Annotated[bool, typer.Option(help="fail (exit 3) on the first problem instead of listing rejects")] = False,
    origin: Annotated[Optional[str], typer.Option(help="LAT,LON[,ALT_M] processing centre when the dataset has no "
                                                       "scenario.toml [default: mean of the radar sites]")] = None,
) -> None:
    """Print, stage by stage, every report `tertiary run` will reject, and why (same rules, same counts)."""
    ds = read_dataset(dataset, origin=parse_origin(origin))
    screened = screen(ds, PipelineConfig(strict=strict))
    for note in screened.notes:
        print_note(note)
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


def _print_registration(res: registration.Registration, method: str) -> None:
    table = Table(title=f"registration ({res.table['method'][0] if res.table.height else method})")
    for col in ("radar", "name", "range bias m", "azimuth bias deg", "clock offset s", "range gain", "reports"):
        table.add_column(col, justify="left" if col == "name" else "right")
    for r in res.table.iter_rows(named=True):
        g = "–" if not math.isfinite(r["range_gain"]) else f"{r['range_gain']:+.2e} ± {r['range_gain_sigma']:.1e}"
        table.add_row(str(r["radar_id"]), str(r["name"]), f"{r['range_bias_m']:+.2f} ± {r['range_bias_sigma_m']:.2f}",
                      f"{r['azimuth_bias_deg']:+.4f} ± {r['azimuth_bias_sigma_deg']:.4f}",
                      f"{r['time_offset_s']:+.4f} ± {r['time_offset_sigma_s']:.4f}", g, f"{r['n_reports']:,}")
    console.print(table)


def register(
    dataset: Annotated[Path, typer.Argument(help="dataset directory (radars.parquet, reports.parquet, optional "
                                                 "truth.parquet); registration.parquet is written there")],
    method: Annotated[str, typer.Option(help="auto (reference when truth is present, else multi), reference "
                                             "(against truth/ADS-B positions) or multi (radar to radar by Mode S)")] = "auto",
    gain: Annotated[bool, typer.Option(help="also estimate a range gain per radar")] = False,
    steps: Annotated[bool, typer.Option("--steps/--no-steps", help="also test each radar for a bias step "
                                                                   "(windowed innovation-mean test)")] = True,
    window: Annotated[int, typer.Option(help="reports per window of the step test")] = 60,
    origin: OriginOpt = None,
) -> None:
    """Estimate each radar's range bias, azimuth bias and clock offset (with 1-sigma) and write
    DATASET/registration.parquet; signs as the simulator's bias_range_m, bias_azimuth_deg, time_offset_s."""
    if method not in ("auto", "reference", "multi"):
        raise OptionError(f"choose auto, reference or multi, got {method!r}", option="--method")
    if window < 5:
        raise OptionError(f"must be at least 5, got {window}", option="--window")
    ds = read_dataset(dataset, origin=parse_origin(origin))
    ing = ingest(ds)
    res = registration.estimate(ing.reports, ing.radars, ds.origin, ing.truth,
                                registration.RegistrationConfig(method=method, gain=gain))
    for note in ds.notes + res.notes:
        print_note(note)
    _print_registration(res, method)
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
