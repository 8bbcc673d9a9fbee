"""``tertiary simulate`` and ``tertiary scenarios``: simulated datasets."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import polars as pl
import typer

from tertiary.cli.common import (AircraftOpt, BiasStepOpt, DropoutOpt, DurationOpt, LogFormatOpt, NoiseOpt,
                                 NoiseWinOpt, OutliersOpt, QuietOpt, RadarsOpt, RunsOpt, SeedOpt, Steps, TruthOpt,
                                 build_scenario, console, set_log)
from tertiary.core.errors import OptionError
from tertiary.io.asterix.encode import write_recording
from tertiary.io.dataset import write_dataset
from tertiary.pipeline.workflows import check_writable_dir
from tertiary.simulate import ScenarioConfig, builtin_scenarios, load_scenario, simulate as simulate_dataset, write_stream


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
    set_log(quiet, log_format)
    if fmt not in ("parquet", "asterix"):
        raise OptionError(f"use parquet or asterix, got {fmt!r}", option="--format")
    if scenario == "adsb" and truth is None:
        raise OptionError("the adsb scenario needs --truth FILE (an OpenSky/traffic-schema Parquet file)",
                          option="--truth")
    check_writable_dir(out, "--out")
    if ((out / "reports.parquet").exists() or (out / "parts.json").exists()) and not force:
        raise OptionError(f"{out} already holds a dataset; give --force to replace it", option="--out")
    cfg = build_scenario(scenario, runs=runs, seed=seed, aircraft=aircraft, radars=radars, duration=duration,
                         truth=truth, noise_factor=noise_factor, noise_window=noise_window, dropout=dropout,
                         outliers=outliers, bias_step=bias_step)
    t = time.perf_counter()
    if window is not None or cfg.kind == "national":
        if fmt != "parquet":
            raise OptionError("a windowed simulation writes Parquet parts only", option="--format")
        with Steps(f"simulate {cfg.name}") as say:
            done = write_stream(cfg, out, window if window is not None else
                                (cfg.national.block_s if cfg.national else None), progress=say)
        console.print(f"wrote {out}/ ({done['reports']:,} reports, {done['truth_rows']:,} truth rows in "
                      f"{len(done['parts'])} parts, {done['radars']} radars, {cfg.runs} run(s)) in "
                      f"{time.perf_counter() - t:.1f} s", soft_wrap=True)
        return
    with Steps(f"simulate {cfg.name}") as say:
        ds = simulate_dataset(cfg, progress=say)
    write_dataset(ds, out)
    console.print(f"wrote {out}/ ({ds.reports.height:,} reports, {ds.truth.height:,} truth rows, "
                  f"{ds.radars.height} radars, {cfg.runs} run(s)) in {time.perf_counter() - t:.1f} s", soft_wrap=True)
    if designed := designed_pairs(ds.truth, cfg):
        console.print(designed, soft_wrap=True)
    if ds.removed.height:
        low = ds.removed.filter(pl.col("reason").str.starts_with("declared quality")).height
        console.print(f"ADS-B cleaning removed {ds.removed.height:,} rows (truth_removed.parquet), {low:,} of them "
                      f"below the reference quality (NACp >= {cfg.adsb.min_nacp} where declared)", soft_wrap=True)
    if fmt == "asterix":
        rec, sites, day = write_recording(ds, out)
        runs_note = f" (run 0 of {cfg.runs})" if cfg.runs > 1 else ""
        console.print(f"wrote {rec}{runs_note} and {sites}; import with: tertiary import asterix {rec} "
                      f"--sites {sites} --date {day} --out DATASET_DIR", soft_wrap=True)


def designed_pairs(truth: pl.DataFrame, cfg: ScenarioConfig) -> str:
    """What the simulation placed of the designed losses of separation and near misses ("" when the
    scenario designs none): fewer than asked when the duration or the aircraft do not hold them."""
    asked = (cfg.traffic.conflict_pairs, cfg.traffic.near_miss_pairs) if cfg.kind == "terminal-area" else (0, 0)
    if "role" not in truth.columns or not any(asked):
        return ""
    first = truth.filter(pl.col("run") == pl.col("run").min()) if "run" in truth.columns else truth
    roles = first.group_by("truth_id").agg(pl.col("role").first())["role"]
    placed = (int(roles.str.starts_with("conflict-").sum()) // 2, int((roles == "near-miss").sum()) // 2)
    text = (f"designed pairs: {placed[0]} losses of separation and {placed[1]} near misses per run")
    if placed != asked:
        text += (f" (the scenario asks for {asked[0]} and {asked[1]}; as many as fit in {cfg.duration_s:g} s "
                 f"with {cfg.traffic.aircraft} aircraft)")
    return text


def scenarios() -> None:
    """List the built-in scenarios."""
    for name in builtin_scenarios():
        cfg = load_scenario(name)
        console.print(f"{name} ({cfg.kind}): {len(cfg.radars)} radars, {cfg.duration_s:.0f} s, {cfg.runs} run(s)")
