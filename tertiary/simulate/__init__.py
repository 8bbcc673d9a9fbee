"""Scenario simulation: truth trajectories observed by simulated radars with their own
secondary processing, producing the ``radars``, ``reports`` and ``truth`` tables."""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
import re
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary import geo
from tertiary.errors import DataError, OptionError
from tertiary.local_tracks import track_reports
from tertiary.simulate.config import (AdsbConfig, Anomalies, RadarConfig, RadarTrackerConfig, ScenarioConfig,
                                      TrackerParams, TrafficConfig, TransponderConfig, auto_radars, builtin_scenarios, check_name, check_origin,
                                      check_scenario, load_scenario, read_scenario_toml, resolve_data_path,
                                      scenario_toml)
from tertiary.simulate.ehs import EhsConfig, ehs_report_columns, ehs_rng
from tertiary.simulate.radar import Plots, Transponders, number_plots, observe, site_frame, transponders
from tertiary.simulate.traffic import big_box, terminal_area
from tertiary.simulate.trajectory import Trajectories
from tertiary.store import write_parquet_atomic, write_text_atomic

__all__ = ["Dataset", "simulate", "write_dataset", "read_dataset", "load_scenario", "builtin_scenarios",
           "ScenarioConfig", "RadarConfig", "Anomalies", "TrafficConfig", "TrackerParams", "AdsbConfig",
           "TransponderConfig", "RadarTrackerConfig",
           "Trajectories", "big_box", "terminal_area", "resolve_data_path", "check_scenario",
           "read_scenario_toml"]

Progress = Callable[[str], None]


@dataclass
class Dataset:
    """A simulated (or loaded) dataset: the three input tables and the scenario definition."""

    radars: pl.DataFrame
    reports: pl.DataFrame
    truth: pl.DataFrame
    scenario: ScenarioConfig
    removed: pl.DataFrame = field(default_factory=pl.DataFrame)   # truth rows dropped by ADS-B cleaning
    notes: list[str] = field(default_factory=list)                # how the dataset was completed on load

    @property
    def origin(self) -> geo.LocalFrame:
        """The system frame (ENU at the scenario origin); a missing or invalid origin is a
        :class:`DataError` (the frame of every report depends on it)."""
        try:
            return geo.LocalFrame(*check_origin(self.scenario.origin))
        except OptionError as exc:
            raise DataError(f"scenario {self.scenario.name!r}: {exc} (give --origin LAT,LON)") from exc


def _read_truth_file(path: Path) -> pl.DataFrame:
    """The ADS-B truth file, or a :class:`DataError` naming it and what is wrong."""
    from tertiary.simulate import adsb
    try:
        frame = adsb.read_adsb(path)
    except (OSError, ValueError, pl.exceptions.PolarsError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"not a readable ADS-B trajectory table (OpenSky/traffic schema): {first}",
                        path=str(path)) from exc
    if frame.filter(pl.col("timestamp").is_not_null()).height == 0:
        raise DataError("no ADS-B row with a timestamp", path=str(path))
    return frame


def _truth(cfg: ScenarioConfig, rng: np.random.Generator) -> tuple[ScenarioConfig, Trajectories, pl.DataFrame]:
    """Truth trajectories; for ADS-B also resolves an automatic origin and radar layout."""
    if cfg.kind == "big-box":
        return cfg, big_box(cfg.dt), pl.DataFrame()
    if cfg.kind == "terminal-area":
        return cfg, terminal_area(cfg.traffic, cfg.duration_s, cfg.dt, rng,
                                   frame=geo.LocalFrame(*cfg.origin)), pl.DataFrame()
    if cfg.kind == "adsb":
        from tertiary.simulate import adsb
        frame = _read_truth_file(resolve_data_path(cfg.adsb.truth_file))
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


#: Mode 3/A codes 0…4095 as their four octal digits
_CODES = pl.Series("mode_3a", [f"{v:04o}" for v in range(4096)], dtype=pl.String)


def _gather(table: pl.Series, index: NDArray[np.int64], name: str) -> pl.Series:
    """``table[index]`` with null where ``index`` < 0 (no reply, clutter) or the value is empty."""
    return table.replace("", None).gather(pl.Series(index).replace(-1, None)).alias(name)


def _reports_frame(plots: Plots, radar_id: int, traj: Trajectories, tx: Transponders,
                   ehs: dict[str, NDArray[np.float64]] | None = None) -> pl.DataFrame:
    """One radar's reports. Every column comes from what the radar measured or was replied —
    the plot, the radar clock, its own track number, the transponder's address, code and
    altitude; the callsign rides on Mode S replies (ELS), so a report without an address has
    none; ``ehs`` the Comm-B enhanced-surveillance parameters (null without) — except
    ``truth_id`` (scoring only)."""
    epoch_us = int(traj.epoch.timestamp() * 1_000_000)
    real = plots.aircraft >= 0
    index = pl.Series(plots.aircraft).replace(-1, None)      # clutter gathers nulls
    tid = pl.Series(traj.truth_id).gather(index)
    by_address = np.where(plots.mode_s >= 0, plots.aircraft, -1)
    return pl.DataFrame({
        "run": plots.run,
        "radar_id": pl.Series(np.full(len(real), radar_id), dtype=pl.UInt32),
        "time": pl.Series(np.round(plots.t_report * 1e6).astype(np.int64) + epoch_us).cast(pl.Datetime("us", "UTC")),
        "local_track_id": plots.local_track_id,
        "range_m": plots.range_m, "azimuth_deg": plots.azimuth_deg, "elevation_deg": plots.elevation_deg,
        "altitude_m": pl.Series(plots.altitude_m).fill_nan(None),
        "mode_s": _gather(pl.Series(tx.addresses, dtype=pl.String), plots.mode_s, "mode_s"),
        "mode_3a": _gather(_CODES, plots.mode_3a, "mode_3a"),
        "callsign": _gather(pl.Series(tx.callsign, dtype=pl.String), by_address, "callsign"),
        "truth_id": tid.cast(pl.Int64),
        **{name: pl.Series(name, v).fill_nan(None) for name, v in (ehs or {}).items()},
        "__life": plots.track_life,
    })


def _ehs_columns(plots: Plots, index: int, traj: Trajectories, seed: int, cfg: EhsConfig | None
                 ) -> dict[str, NDArray[np.float64]] | None:
    """The EHS report columns of radar ``index``'s plots (replies with a decoded Mode S
    address), from the radar's own EHS noise stream; None when EHS is off."""
    if cfg is None:
        return None
    return ehs_report_columns(traj, plots.aircraft, plots.t_true, plots.mode_s >= 0, ehs_rng(seed, index), cfg)


def simulate(cfg: ScenarioConfig, progress: Progress | None = None, ehs: EhsConfig | None = EhsConfig()
             ) -> Dataset:
    """Simulate a scenario: truth, every radar's scans for ``cfg.runs`` runs, and each radar's
    own Singer-channel secondary processing. Same config (incl. seed) → identical tables.

    ``ehs``: Mode S reports carry the enhanced-surveillance parameters
    (:data:`tertiary.schema.EHS_REPORT_COLUMNS`, :mod:`tertiary.simulate.ehs`); None leaves the
    columns out. Their noise comes from a stream of its own (:func:`~tertiary.simulate.ehs.ehs_rng`):
    every other column is bit-identical with EHS on or off."""
    cfg = check_scenario(cfg)
    say = progress or (lambda _msg: None)
    say("truth trajectories")
    cfg, traj, removed = _truth(cfg, np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(1)[0]))
    if cfg.origin is None or not cfg.radars:
        raise OptionError(f"scenario {cfg.name!r} needs an origin and at least one radar", option="origin")
    seeds = np.random.SeedSequence(cfg.seed).spawn(len(cfg.radars) + 1)
    system = geo.LocalFrame(*cfg.origin)
    radars = radars_frame(cfg)
    tx = transponders(traj, cfg.transponders, np.random.default_rng(seeds[0].spawn(1)[0]))
    plots = []
    for i, radar in enumerate(cfg.radars):
        say(f"radar scans {radar.name}")
        plots.append(observe(traj, radar, system, cfg.runs, np.random.default_rng(seeds[i + 1]), cfg.anomalies, tx))
    say("radar plot-to-track association")
    plots = number_plots(plots, list(cfg.radars), cfg.runs, traj.duration, cfg.radar_tracker)
    parts = [_reports_frame(p, i + 1, traj, tx, _ehs_columns(p, i, traj, cfg.seed, ehs)) for i, p in enumerate(plots)]
    reports = pl.concat(parts, how="vertical") if parts else pl.DataFrame()
    say("radar secondary processing")
    # each track life is filtered on its own (a reused number restarts the radar's filter)
    reports = track_reports(reports.rename({"local_track_id": "__number"})
                            .with_columns(pl.col("__life").cast(pl.UInt32).alias("local_track_id")),
                            radars, cfg.tracker.local_tracker())
    reports = reports.with_columns(pl.col("__number").alias("local_track_id")).drop("__number", "__life")
    reports = reports.select([c for c in parts[0].columns if c in reports.columns and c != "__life"]
                             + [c for c in reports.columns if c not in parts[0].columns])
    reports = reports.with_columns(pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"))
    return Dataset(radars=radars, reports=reports, truth=traj.to_frame(frame=system), scenario=cfg, removed=removed)


def write_dataset(ds: Dataset, out_dir: str | Path) -> Path:
    """Write radars/reports/truth Parquet files and ``scenario.toml`` atomically."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DataError("exists and is not a directory; give a dataset directory", path=str(out))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create the dataset directory: {exc.strerror or exc}", path=str(out)) from exc
    for name in ("radars", "reports", "truth"):
        write_parquet_atomic(getattr(ds, name), out / f"{name}.parquet")
    if ds.removed.height:
        write_parquet_atomic(ds.removed, out / "truth_removed.parquet")
    write_text_atomic(out / "scenario.toml", scenario_toml(ds.scenario))
    return out


def _read_table(path: Path, required: bool) -> pl.DataFrame:
    """One Parquet table of a dataset; a missing (when required) or unreadable file is a
    :class:`DataError` naming it."""
    if not path.exists():
        if required:
            raise DataError("missing (a dataset needs radars.parquet and reports.parquet)", path=str(path))
        return pl.DataFrame()
    if not path.is_file():
        raise DataError("not a file", path=str(path))
    try:
        return pl.read_parquet(path)
    except Exception as exc:  # polars, pyarrow and OS errors alike: the file is unusable
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        size = path.stat().st_size
        what = "empty file" if size == 0 else f"not a readable Parquet file ({type(exc).__name__}: {text[:160]})"
        raise DataError(what, path=str(path)) from exc


def _site_origin(radars: pl.DataFrame) -> tuple[float, float, float] | None:
    """Mean site of the radars whose lat/lon are valid numbers on the globe (alt 0), or None."""
    if not {"lat_deg", "lon_deg"} <= set(radars.columns):
        return None
    try:
        sites = radars.select(pl.col("lat_deg").cast(pl.Float64, strict=False),
                              pl.col("lon_deg").cast(pl.Float64, strict=False))
    except pl.exceptions.PolarsError:
        return None
    ok = sites.filter(pl.col("lat_deg").is_between(-90, 90) & pl.col("lon_deg").is_between(-180, 180))
    if ok.height == 0:
        return None
    return float(ok["lat_deg"].mean()), float(ok["lon_deg"].mean()), 0.0


def read_dataset(path: str | Path, origin: tuple[float, ...] | None = None) -> Dataset:
    """Load a dataset directory written by :func:`write_dataset` (or hand-made with the same files).

    ``origin`` (lat, lon[, alt]) overrides the scenario's system origin. Without
    ``scenario.toml`` the origin is ``origin`` or else the mean of the radar sites (a note in
    ``Dataset.notes`` says so; truth, whose ENU positions need the frame's origin, is then not
    used, with a note) and the scenario name is the directory name made an identifier.
    Every problem (missing or unreadable file, malformed TOML, bad origin or name) is a
    :class:`DataError` naming the file.
    """
    d = Path(path)
    if not d.is_dir():
        raise DataError("not a dataset directory" if d.exists() else "no such dataset directory", path=str(d))
    radars = _read_table(d / "radars.parquet", True)
    reports = _read_table(d / "reports.parquet", True)
    truth = _read_table(d / "truth.parquet", False)
    removed = _read_table(d / "truth_removed.parquet", False)
    notes: list[str] = []
    if origin is not None:
        try:
            origin = check_origin(origin)
        except OptionError as exc:
            raise OptionError(str(exc).split(": ", 1)[-1], option="origin (--origin)") from exc
    toml = d / "scenario.toml"
    if toml.exists():
        scen = read_scenario_toml(toml)
        try:
            check_name(scen.name)
            # the file is validated whole: a bad origin is an error even when --origin overrides it
            if scen.origin is not None:
                check_origin(scen.origin)
            elif origin is None:
                raise OptionError("missing (give origin = [lat, lon, alt] or --origin LAT,LON)", option="origin")
        except OptionError as exc:
            raise DataError(str(exc), path=str(toml)) from exc
    else:
        name = re.sub(r"[^A-Za-z0-9_-]", "_", d.resolve().name).lstrip("_-")[:64] or "dataset"
        scen = ScenarioConfig(name=name, kind="terminal-area")
        notes.append(f"{d}: no scenario.toml; scenario name {name!r}")
        if origin is None:
            origin = _site_origin(radars)
            if origin is None:
                raise DataError("no scenario.toml and no radar site to place the system origin: give the origin "
                                "(--origin LAT,LON)", path=str(d))
            notes.append(f"system origin = mean radar site ({origin[0]:.5f}, {origin[1]:.5f}, 0 m)")
            if truth.height:
                # truth holds ENU positions of a frame whose origin only scenario.toml (or the user)
                # knows; scored in a guessed frame it would give kilometre "errors" that are not
                notes.append(f"{d / 'truth.parquet'}: not used — its ENU positions are in a frame this dataset "
                             "does not name (no scenario.toml); give --origin LAT,LON of that frame to score "
                             "against it")
                truth = truth.clear()
    if origin is not None:
        scen = dataclasses.replace(scen, origin=tuple(origin))
    return Dataset(radars=radars, reports=reports, truth=truth, scenario=scen, removed=removed, notes=notes)
