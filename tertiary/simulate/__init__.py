"""Scenario simulation: truth trajectories observed by simulated radars with their own
secondary processing, producing the ``radars``, ``reports`` and ``truth`` tables."""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path

import numpy as np
import polars as pl

from tertiary import geo
from tertiary.local_tracks import track_reports
from tertiary.simulate.config import (AdsbConfig, Anomalies, RadarConfig, ScenarioConfig, TrackerParams,
                                      TrafficConfig, auto_radars, builtin_scenarios, load_scenario,
                                      scenario_toml)
from tertiary.simulate.radar import Plots, observe, site_frame
from tertiary.simulate.traffic import big_box, terminal_area
from tertiary.simulate.trajectory import Trajectories
from tertiary.store import write_parquet_atomic, write_text_atomic

__all__ = ["Dataset", "simulate", "write_dataset", "read_dataset", "load_scenario", "builtin_scenarios",
           "ScenarioConfig", "RadarConfig", "Anomalies", "TrafficConfig", "TrackerParams", "AdsbConfig",
           "Trajectories", "big_box", "terminal_area", "resolve_data_path"]

Progress = Callable[[str], None]


@dataclass
class Dataset:
    """A simulated (or loaded) dataset: the three input tables and the scenario definition."""

    radars: pl.DataFrame
    reports: pl.DataFrame
    truth: pl.DataFrame
    scenario: ScenarioConfig
    removed: pl.DataFrame = field(default_factory=pl.DataFrame)   # truth rows dropped by ADS-B cleaning

    @property
    def origin(self) -> geo.LocalFrame:
        return geo.LocalFrame(*self.scenario.origin)


def resolve_data_path(path: str) -> Path:
    """A data file path: absolute, relative to the working directory, or to the repository."""
    p = Path(path).expanduser()
    candidates = [p] if p.is_absolute() else [Path.cwd() / p, Path(__file__).resolve().parents[2] / p]
    for c in candidates:
        if c.exists():
            return c
    raise FileNotFoundError(f"data file {path!r} not found (looked in: {', '.join(map(str, candidates))})")


def _truth(cfg: ScenarioConfig, rng: np.random.Generator) -> tuple[ScenarioConfig, Trajectories, pl.DataFrame]:
    """Truth trajectories; for ADS-B also resolves an automatic origin and radar layout."""
    if cfg.kind == "big-box":
        return cfg, big_box(cfg.dt), pl.DataFrame()
    if cfg.kind == "terminal-area":
        return cfg, terminal_area(cfg.traffic, cfg.duration_s, cfg.dt, rng), pl.DataFrame()
    if cfg.kind == "adsb":
        from tertiary.simulate import adsb
        frame = adsb.read_adsb(resolve_data_path(cfg.adsb.truth_file))
        t0 = frame["timestamp"].min().replace(microsecond=0)
        start = t0 + timedelta(seconds=cfg.adsb.start_s)
        frame = frame.filter((pl.col("timestamp") >= start) &
                             (pl.col("timestamp") <= start + timedelta(seconds=cfg.duration_s)))
        if cfg.origin is None:
            ok = frame.filter(pl.col("latitude").is_not_null() & pl.col("longitude").is_not_null())
            cfg = dataclasses.replace(cfg, origin=(float(ok["latitude"].median()), float(ok["longitude"].median()), 0.0))
        if not cfg.radars:
            cfg = dataclasses.replace(cfg, radars=auto_radars())
        cleaning = adsb.AdsbCleaning(max_alt_m=cfg.adsb.max_alt_m, max_gap_s=cfg.adsb.max_gap_s, dt=cfg.dt)
        traj, removed = adsb.adsb_to_trajectories(frame, geo.LocalFrame(*cfg.origin), cleaning, epoch=start)
        return cfg, traj, removed
    raise ValueError(f"unknown scenario kind {cfg.kind!r}")


def radars_frame(cfg: ScenarioConfig) -> pl.DataFrame:
    system = geo.LocalFrame(*cfg.origin)
    sites = [site_frame(r, system) for r in cfg.radars]
    return pl.DataFrame({
        "radar_id": pl.Series(np.arange(1, len(cfg.radars) + 1), dtype=pl.UInt32),
        "name": [r.name for r in cfg.radars],
        "lat_deg": [s.lat_deg for s in sites], "lon_deg": [s.lon_deg for s in sites],
        "alt_m": [s.alt_m for s in sites],
        **{k: [float(getattr(r, k)) for r in cfg.radars] for k in (
            "scan_period_s", "sigma_range_m", "sigma_azimuth_deg", "sigma_elevation_deg", "max_range_m",
            "scan_phase_s", "min_elevation_deg", "pd", "clutter_rate", "bias_range_m", "bias_azimuth_deg",
            "time_offset_s")},
        "timing": [r.timing for r in cfg.radars],
    })


def _meta(traj: Trajectories, name: str, index: pl.Series) -> pl.Series:
    """Per-aircraft metadata gathered per report (null for clutter or empty values)."""
    values = traj.meta.get(name)
    if values is None:
        return pl.Series(name, [None] * len(index), dtype=pl.String)
    table = pl.Series(name, np.asarray(values, dtype=str), dtype=pl.String).replace("", None)
    return table.gather(index)


def _reports_frame(plots: Plots, radar_id: int, traj: Trajectories) -> pl.DataFrame:
    epoch_us = int(traj.epoch.timestamp() * 1_000_000)
    real = plots.aircraft >= 0
    index = pl.Series(plots.aircraft).replace(-1, None)      # clutter gathers nulls
    tid = pl.Series(traj.truth_id).gather(index)
    return pl.DataFrame({
        "run": plots.run,
        "radar_id": pl.Series(np.full(len(real), radar_id), dtype=pl.UInt32),
        "time": pl.Series(np.round(plots.t_report * 1e6).astype(np.int64) + epoch_us).cast(pl.Datetime("us", "UTC")),
        "local_track_id": plots.local_track_id,
        "range_m": plots.range_m, "azimuth_deg": plots.azimuth_deg, "elevation_deg": plots.elevation_deg,
        "altitude_m": pl.Series(plots.altitude_m).fill_nan(None),
        "mode_s": _meta(traj, "icao24", index), "mode_3a": _meta(traj, "squawk", index),
        "callsign": _meta(traj, "callsign", index),
        "truth_id": tid.cast(pl.Int64),
    })


def simulate(cfg: ScenarioConfig, progress: Progress | None = None) -> Dataset:
    """Simulate a scenario: truth, every radar's scans for ``cfg.runs`` runs, and each radar's
    own Singer-channel secondary processing. Same config (incl. seed) → identical tables."""
    say = progress or (lambda _msg: None)
    say("truth trajectories")
    cfg, traj, removed = _truth(cfg, np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(1)[0]))
    if cfg.origin is None or not cfg.radars:
        raise ValueError(f"scenario {cfg.name!r} needs an origin and at least one radar")
    seeds = np.random.SeedSequence(cfg.seed).spawn(len(cfg.radars) + 1)
    system = geo.LocalFrame(*cfg.origin)
    radars = radars_frame(cfg)
    parts = []
    for i, radar in enumerate(cfg.radars):
        say(f"radar scans {radar.name}")
        plots = observe(traj, radar, system, cfg.runs, np.random.default_rng(seeds[i + 1]), cfg.anomalies)
        parts.append(_reports_frame(plots, i + 1, traj))
    reports = pl.concat(parts, how="vertical") if parts else pl.DataFrame()
    say("radar secondary processing")
    reports = track_reports(reports, radars, cfg.tracker.local_tracker())
    reports = reports.with_columns(pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"))
    return Dataset(radars=radars, reports=reports, truth=traj.to_frame(), scenario=cfg, removed=removed)


def write_dataset(ds: Dataset, out_dir: str | Path) -> Path:
    """Write radars/reports/truth Parquet files and ``scenario.toml`` atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("radars", "reports", "truth"):
        write_parquet_atomic(getattr(ds, name), out / f"{name}.parquet")
    if ds.removed.height:
        write_parquet_atomic(ds.removed, out / "truth_removed.parquet")
    write_text_atomic(out / "scenario.toml", scenario_toml(ds.scenario))
    return out


def read_dataset(path: str | Path) -> Dataset:
    """Load a dataset directory written by :func:`write_dataset` (or hand-made with the same files)."""
    d = Path(path)
    missing = [f for f in ("radars.parquet", "reports.parquet") if not (d / f).exists()]
    if missing:
        raise FileNotFoundError(f"{d}: missing {', '.join(missing)}")
    truth = pl.read_parquet(d / "truth.parquet") if (d / "truth.parquet").exists() else pl.DataFrame()
    removed = pl.read_parquet(d / "truth_removed.parquet") if (d / "truth_removed.parquet").exists() else pl.DataFrame()
    scen = load_scenario(d / "scenario.toml") if (d / "scenario.toml").exists() else \
        ScenarioConfig(name=d.name, kind="terminal-area")
    return Dataset(radars=pl.read_parquet(d / "radars.parquet"), reports=pl.read_parquet(d / "reports.parquet"),
                   truth=truth, scenario=scen, removed=removed)
