"""The simulator: truth trajectories observed by simulated radars, MLAT / WAM systems
(``[[mlat]]``, :mod:`tertiary.simulate.mlat_observe`: ``radars`` rows of kind ``mlat`` after the
radars, their own random streams) and ADS-B ground stations (``[[adsb_station]]``,
:mod:`tertiary.simulate.adsb_station`: kind ``adsb``, after the MLAT systems) with their own secondary processing, producing a dataset's
``radars``, ``reports``, ``truth`` and ``flight_plans`` tables — whole (:func:`simulate`) or
window by window (:func:`simulate_windows`, :func:`write_stream`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
import dataclasses
import json
import math
from dataclasses import dataclass, field
from fractions import Fraction
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import ADSB_QUALITY_COLUMNS
from tertiary.core import geo
from tertiary.core.errors import OptionError
from tertiary.core.units import US
from tertiary.io import adsb
from tertiary.io.dataset import PARTITIONED, PARTS_MANIFEST, ROW_GROUPS, Dataset, dataset_dir
from tertiary.sensors.local_tracks import track_reports
from tertiary.simulate import radar_tracker as rt
from tertiary.simulate.config import Anomalies, ScenarioConfig, auto_radars, check_scenario, resolve_data_path, scenario_toml
from tertiary.simulate.ehs import SIMULATED_COLUMNS, EhsConfig, ehs_report_columns, ehs_rng
from tertiary.sensors.mlat import plot_cov_xy
from tertiary.simulate.adsb_observe import observe_adsb
from tertiary.simulate.adsb_station import AdsbStationConfig, station_site
from tertiary.simulate.mlat_observe import mlat_site, observe_mlat
from tertiary.simulate.radar import (Plots, Transponders, merge_plots, number_plots, numbered_by_truth, observe, octal_codes,
                                     scan_starts, site_frame, take_plots, transponders)
from tertiary.simulate.traffic import TerminalTraffic, big_box, national_flights, terminal_traffic
from tertiary.simulate.trajectory import Trajectories
from tertiary.store.run_store import write_parquet_atomic, write_text_atomic

__all__ = ["simulate", "simulate_windows", "write_stream", "SimWindow", "block_s", "radars_frame", "flight_plans",
           "NATIONAL_EPOCH", "STREAMED"]

Progress = Callable[[str], None]


def _truth(cfg: ScenarioConfig, rng: np.random.Generator) -> tuple[ScenarioConfig, Trajectories, pl.DataFrame]:
    """Truth trajectories; for ADS-B also resolves an automatic origin and radar layout."""
    if cfg.kind == "big-box":
        return cfg, big_box(cfg.dt), pl.DataFrame()
    if cfg.kind == "adsb":
        frame = adsb.read_truth_file(resolve_data_path(cfg.adsb.truth_file))
        t0 = frame["timestamp"].min().replace(microsecond=0)
        start = t0 + timedelta(seconds=cfg.adsb.start_s)
        frame = frame.filter((pl.col("timestamp") >= start) &
                             (pl.col("timestamp") <= start + timedelta(seconds=cfg.duration_s)))
        if cfg.origin is None:
            ok = frame.filter(pl.col("latitude").is_not_null() & pl.col("longitude").is_not_null())
            cfg = dataclasses.replace(cfg, origin=(float(ok["latitude"].median()), float(ok["longitude"].median()), 0.0))
        if not cfg.radars:
            cfg = dataclasses.replace(cfg, radars=auto_radars())
        cleaning = adsb.AdsbCleaning(max_alt_m=cfg.adsb.max_alt_m, max_gap_s=cfg.adsb.max_gap_s, dt=cfg.dt,
                                     min_nacp=cfg.adsb.min_nacp)
        traj, removed = adsb.adsb_to_trajectories(frame, geo.LocalFrame(*cfg.origin), cleaning, epoch=start)
        return cfg, traj, removed
    raise ValueError(f"unknown scenario kind {cfg.kind!r}")


def sensors(cfg: ScenarioConfig) -> tuple:
    """The scenario's sensors in ``radar_id`` order: its radars, then its MLAT systems, then its
    ADS-B ground stations."""
    return (*cfg.radars, *cartesian_sensors(cfg))


def cartesian_sensors(cfg: ScenarioConfig) -> tuple:
    """The sensors whose reports are Cartesian plots: MLAT systems, then ADS-B stations."""
    return (*(cfg.mlat or ()), *(cfg.adsb_station or ()))


def _site(sensor, system: geo.LocalFrame) -> geo.LocalFrame:
    """A Cartesian sensor's local frame (its plots' x, y)."""
    return station_site(sensor, system) if isinstance(sensor, AdsbStationConfig) else mlat_site(sensor, system)


def radars_frame(cfg: ScenarioConfig) -> pl.DataFrame:
    system = geo.LocalFrame(*cfg.origin)
    sites = [site_frame(r, system) for r in cfg.radars]
    frame = pl.DataFrame({
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
    if not cartesian_sensors(cfg):
        return frame
    return pl.concat([frame.with_columns(pl.lit("radar").alias("kind")), mlat_frame(cfg, len(cfg.radars))],
                     how="vertical_relaxed")


def mlat_frame(cfg: ScenarioConfig, first: int) -> pl.DataFrame:
    """The ``radars`` rows of the scenario's MLAT sensors (kind ``mlat``) and ADS-B stations (kind
    ``adsb``), ids after ``first``: site = the reference point, ``scan_period_s`` = the update
    period, ``sigma_range_m`` = an MLAT's accuracy floor (:func:`tertiary.simulate.mlat.nominal_sigma_m`)
    or a station's most common NACp's σ, ``max_range_m`` = the receiver range beyond the farthest
    receiver (a station's own range); the angle σ the table requires, read by no stage for them."""
    system = geo.LocalFrame(*cfg.origin)
    ms = cartesian_sensors(cfg)
    sites = [_site(m, system) for m in ms]
    station = [isinstance(m, AdsbStationConfig) for m in ms]
    reach = [m.range_m if st else m.receiver_range_m + float(np.linalg.norm(
        np.asarray(m.receivers_enu_m) - np.asarray(m.site), axis=1).max()) for m, st in zip(ms, station)]
    return pl.DataFrame({
        "radar_id": pl.Series(np.arange(first + 1, first + len(ms) + 1), dtype=pl.UInt32),
        "name": [m.name for m in ms], "lat_deg": [s.lat_deg for s in sites], "lon_deg": [s.lon_deg for s in sites],
        "alt_m": [s.alt_m for s in sites], "scan_period_s": [m.update_period_s for m in ms],
        "sigma_range_m": [m.sigma_range_m for m in ms], "sigma_azimuth_deg": [m.sigma_azimuth_deg for m in ms],
        "sigma_elevation_deg": [m.sigma_elevation_deg for m in ms], "max_range_m": reach,
        "scan_phase_s": [m.update_phase_s for m in ms], "min_elevation_deg": [-90.0] * len(ms),
        "pd": [m.pd for m in ms], "clutter_rate": [0.0] * len(ms), "bias_range_m": [0.0] * len(ms),
        "bias_azimuth_deg": [0.0] * len(ms), "time_offset_s": [m.time_offset_s for m in ms],
        "timing": ["synchronous"] * len(ms), "kind": ["adsb" if st else "mlat" for st in station]})


def _mlat_columns(frame: pl.DataFrame, plots: Plots, site: geo.LocalFrame) -> pl.DataFrame:
    """An MLAT sensor's or ADS-B station's report frame with its Cartesian plot
    (:data:`tertiary.contract.MLAT_PLOT_COLUMNS` but ``plot_height_m``: the height is not measured),
    no elevation, and a station's quality indicators (:data:`tertiary.contract.ADSB_QUALITY_COLUMNS`)."""
    x, y, sx, sy, sxy = plots.cart[:, :5].T
    up = np.zeros(len(x))
    has = np.isfinite(plots.altitude_m)
    if has.any():
        up[has] = geo.up_at_height(site, x[has], y[has], plots.altitude_m[has])
    lat, lon, _ = site.to_geodetic(x, y, up)
    if plots.cart.shape[1] >= 8 and np.isfinite(plots.cart[:, 5]).any():
        frame = frame.with_columns(pl.Series(c, plots.cart[:, 5 + i]).fill_nan(None).cast(pl.UInt8)
                                   for i, c in enumerate(ADSB_QUALITY_COLUMNS))
    return frame.with_columns(pl.lit(None, pl.Float64).alias("elevation_deg"), *(
        pl.Series(c, v) for c, v in (("plot_x_m", x), ("plot_y_m", y), ("plot_lat_deg", lat), ("plot_lon_deg", lon),
                                     ("plot_sigma_x_m", sx), ("plot_sigma_y_m", sy), ("plot_sigma_xy_m", sxy))))


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
    epoch_us = int(traj.epoch.timestamp() * US)
    if ehs is None and plots.ehs.shape[1]:
        ehs = dict(zip(SIMULATED_COLUMNS, plots.ehs.T))
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


def _ehs_columns(plots: Plots, index: int, traj: Trajectories, seed: int, cfg: EhsConfig | None,
                 system: geo.LocalFrame) -> dict[str, NDArray[np.float64]] | None:
    """The EHS report columns of radar ``index``'s plots (replies with a decoded Mode S
    address), from the radar's own EHS noise stream; None when EHS is off."""
    if cfg is None:
        return None
    return ehs_report_columns(traj, plots.aircraft, plots.t_true, plots.mode_s >= 0, ehs_rng(seed, index), cfg,
                              system)


def _simulate_whole(cfg: ScenarioConfig, progress: Progress | None = None, ehs: EhsConfig | None = EhsConfig()
                    ) -> Dataset:
    """Simulate a scenario in one piece: truth, every radar's scans for ``cfg.runs`` runs, and each
    radar's own Singer-channel secondary processing. Same config (incl. seed) → identical tables.

    ``ehs``: Mode S reports carry the enhanced-surveillance parameters
    (:data:`tertiary.contract.EHS_REPORT_COLUMNS`, :mod:`tertiary.simulate.ehs`); None leaves the
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
    parts = [_reports_frame(p, i + 1, traj, tx, _ehs_columns(p, i, traj, cfg.seed, ehs, system))
             for i, p in enumerate(plots)]
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


def flight_plans(traffic: TerminalTraffic, tx: Transponders) -> pl.DataFrame:
    """The ``flight_plans`` table (:mod:`tertiary.stages.flight_data`) of terminal-area traffic, which
    carries cleared levels (:attr:`TerminalTraffic.cleared_alt_m`): per aircraft, the code ATC
    assigned it and its cleared level, valid over its time in the scenario — two rows when ATC
    changed its code (the transponder's ``t_change``: the flight data follow the instruction).
    The assigned code is the traffic's squawk, not what the transponder replies: a crew squawking
    another aircraft's code (``duplicate_code_fraction``) is not correlated by code, as in reality.
    A departure's plan also names its aerodrome and its ATD to the minute (the tower's departure
    message), with which :func:`tertiary.stages.flight_data.departure_step` pairs a departure that
    squawks the wrong code. Known from the schedule before the aircraft fly (filed plans) and
    the tower's message. Never the truth id."""
    cleared = traffic.cleared_alt_m
    squawk = octal_codes(np.asarray(traffic.meta["squawk"], dtype=str))
    assigned = np.where(squawk >= 0, squawk, tx.code_a)
    k_first, k_last = traffic.span()
    first, last = k_first * traffic.dt, k_last * traffic.dt
    ok = (k_first <= k_last) & np.isfinite(cleared)
    change = ok & (tx.t_change > first) & (tx.t_change < last)
    a = np.concatenate([np.flatnonzero(ok), np.flatnonzero(change)])
    code = np.concatenate([assigned[ok], tx.code_b[change]])
    t_from = np.concatenate([first[ok], tx.t_change[change]])
    t_to = np.concatenate([np.where(change[ok], tx.t_change[ok], last[ok]), last[change]])
    epoch_us = int(traffic.epoch.timestamp() * US)
    when = lambda t: pl.Series(np.round(t * 1e6).astype(np.int64) + epoch_us).cast(pl.Datetime("us", "UTC"))  # noqa: E731
    # a departure's plan names its aerodrome (the runway's midpoint, the system origin) and its
    # ATD as the tower's departure message gives it: lift-off floored to the minute (HHMM).
    # Only the plan row holding the code it took off with carries them.
    departs = (np.asarray(traffic.meta["role"]) == "departure")[a] & (np.arange(len(a)) < int(ok.sum()))
    frame = traffic.frame or geo.LocalFrame(0.0, 0.0)
    # departures are procedural aircraft (numbered first): one airborne at the start lifted off before it
    routed = a < len(traffic.route)
    lift_s = t_from.copy()
    lift_s[routed] = traffic.entry[a[routed]] * traffic.dt
    atd_us = (np.round(lift_s * 1e6).astype(np.int64) + epoch_us) // 60_000_000 * 60_000_000
    atd = pl.Series(np.where(departs, atd_us, 0)).cast(pl.Datetime("us", "UTC"))
    return pl.DataFrame({"mode_3a": [f"{v:04o}" for v in code], "callsign": np.asarray(traffic.meta["callsign"])[a],
                         "valid_from": when(t_from), "valid_to": when(t_to),
                         "cleared_alt_m": np.asarray(cleared, float)[a],
                         "departure_lat_deg": np.where(departs, frame.lat_deg, np.nan),
                         "departure_lon_deg": np.where(departs, frame.lon_deg, np.nan),
                         "departure_time": atd}).with_columns(
        pl.col("departure_lat_deg", "departure_lon_deg").fill_nan(None),
        pl.when(pl.Series(departs)).then(pl.col("departure_time"))).sort("valid_from", "mode_3a")


# --------------------------------------------------------------------------- streamed simulation
#
# Terminal-area traffic and the national day are simulated window by window: truth is looked up
# from the scenario's schedule for the window only, each radar observes it block by block (random
# draws keyed by the block, so the data do not depend on the window), the radars' plot-to-track
# association carries its state (tracks, numbers, held numbers) across windows, and the rows of
# local tracks still alive at a window's end wait for the next window before their secondary
# processing (it filters a track from its first plot: deferred, not restarted, so the result
# equals a single-window run's exactly). Memory is bounded by the window and by the live tracks,
# not by the length of the scenario.

NATIONAL_EPOCH = datetime(2021, 10, 7, 0, 0, 0, tzinfo=timezone.utc)
#: scenario kinds simulated from a schedule, block by block
STREAMED = ("terminal-area", "national")
#: a terminal-area block is the first common multiple of the time step and every scan period
#: from this length on (long enough that the margin looked up past a block's end is small)
TERMINAL_BLOCK_S = 600.0


@dataclass
class SimWindow:
    """One window of a streamed simulation: reports of the local tracks that ended in it (all
    remaining ones in the last window) and truth samples with t0 ≤ t < t1 (≤ t1 in the last)."""

    index: int
    t0_s: float
    t1_s: float
    reports: pl.DataFrame
    truth: pl.DataFrame
    #: flight plans first known in this window (a whole-simulated scenario: all in window 0)
    flight_plans: pl.DataFrame = field(default_factory=pl.DataFrame)


def block_s(cfg: ScenarioConfig) -> float:
    """The length of the blocks a scenario's radar draws are keyed by (a window is a whole
    number of them): ``national.block_s``; for terminal-area the first common multiple of
    ``dt`` and every scan period ≥ :data:`TERMINAL_BLOCK_S` (the whole duration when the
    periods have none within a day); other kinds ``dt`` (simulated whole, cut by time)."""
    if cfg.kind == "national":
        return cfg.national.block_s
    if cfg.kind != "terminal-area":
        return cfg.dt
    periods = (cfg.dt, *(r.scan_period_s for r in sensors(cfg)))
    steps = [Fraction(v).limit_denominator(1000) for v in periods]
    if any(abs(float(f) - v) > 1e-9 for f, v in zip(steps, periods)):
        return cfg.duration_s
    den = math.lcm(*(f.denominator for f in steps))
    common = Fraction(math.lcm(*(int(f * den) for f in steps)), den)
    block = float(common * math.ceil(TERMINAL_BLOCK_S / common))
    return block if block <= 86400.0 else cfg.duration_s


def _shift_anomalies(anom: Anomalies, t0: float) -> Anomalies:
    """Anomaly windows (seconds from the run start) in a block's time (seconds from ``t0``)."""
    move = lambda w: None if w is None else (w[0] - t0, w[1] - t0)
    return dataclasses.replace(anom, noise_window_s=move(anom.noise_window_s),
                               dropout_window_s=move(anom.dropout_window_s),
                               bias_step_time_s=None if anom.bias_step_time_s is None else anom.bias_step_time_s - t0)


@dataclass
class _Schedule:
    """What a streamed simulation looks its windows up from: the system frame, the traffic
    schedule (``window(k0, n)``), every aircraft's transponder, a zero-stride stand-in of the
    whole scenario's truth grid (epoch, identities) and the scenario's first sample of the day."""

    system: geo.LocalFrame
    traffic: object
    tx: Transponders
    ghost: Trajectories
    k_start: int


def _schedule(cfg: ScenarioConfig) -> _Schedule:
    """The scenario's schedule and every aircraft's transponder (global aircraft index)."""
    system = geo.LocalFrame(*cfg.origin)
    traffic_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(1)[0])
    steps = int(round(cfg.duration_s / cfg.dt))
    if cfg.kind == "national":
        traffic = national_flights(cfg.national, cfg.duration_s, cfg.dt, traffic_rng, system, NATIONAL_EPOCH,
                                   cfg.traffic.selected_alt_fraction)
        epoch, k_start = NATIONAL_EPOCH + timedelta(seconds=cfg.national.start_s), int(round(cfg.national.start_s / cfg.dt))
        tx_seed = np.random.SeedSequence(cfg.seed).spawn(2)[1]
    else:
        traffic = terminal_traffic(cfg.traffic, cfg.duration_s, cfg.dt, traffic_rng, system)
        epoch, k_start = traffic.epoch, 0
        tx_seed = np.random.SeedSequence(cfg.seed).spawn(1)[0]
    # transponders() reads the aircraft count, meta and duration only: a zero-stride position grid
    n = traffic.n_flights
    ghost = Trajectories(dt=cfg.dt, pos=np.broadcast_to(np.zeros(3), (n, steps + 1, 3)),
                         vel=np.broadcast_to(np.zeros(3), (n, steps + 1, 3)),
                         active=np.broadcast_to(np.zeros(1, bool), (n, steps + 1)),
                         segment=np.zeros((n, 1), np.int8), truth_id=np.arange(n, dtype=np.int64), epoch=epoch,
                         meta=traffic.meta)
    tx = transponders(ghost, cfg.transponders, np.random.default_rng(tx_seed.spawn(1)[0]))
    return _Schedule(system=system, traffic=traffic, tx=tx, ghost=ghost, k_start=k_start)


def _tx_subset(tx: Transponders, ids: NDArray[np.int64], t0: float) -> Transponders:
    """The transponders of flights ``ids`` in a block starting at ``t0`` s (addresses stay
    indices into the day's address table)."""
    return dataclasses.replace(tx, address=tx.address[ids], code_a=tx.code_a[ids], code_b=tx.code_b[ids],
                               t_change=tx.t_change[ids] - t0, callsign=tx.callsign[ids])


def _observe_block(cfg: ScenarioConfig, sched: _Schedule, b: int, t_win0: float, ehs: EhsConfig | None
                   ) -> list[Plots]:
    """Every radar's plots of block ``b`` (random draws keyed by (seed, block of the day,
    radar)), in the scenario's time, global aircraft indices and scan numbers counted from the
    window start; with ``ehs`` the EHS columns of each reply (noise keyed the same way)."""
    blk = block_s(cfg)
    tb0 = b * blk
    nb = min(blk, cfg.duration_s - tb0)
    margin = max(r.scan_period_s for r in sensors(cfg)) + 2 * cfg.dt
    k0 = sched.k_start + int(round(tb0 / cfg.dt))
    traj = sched.traffic.window(k0, int(round((nb + margin) / cfg.dt)) + 1)
    sub = _tx_subset(sched.tx, traj.truth_id, tb0)
    anom = _shift_anomalies(cfg.anomalies, tb0)
    day_block = b + int(round(sched.k_start * cfg.dt / blk))
    out = []
    for i, radar in enumerate(cfg.radars):
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(7, day_block, i)))
        p = observe(traj, radar, sched.system, cfg.runs, rng, anom, sub)
        p = take_plots(p, np.flatnonzero(p.scan < len(scan_starts(radar, nb))))
        if ehs is not None:
            # a register sampled in the first half step of a block differences the velocity one-sided
            cols = ehs_report_columns(traj, p.aircraft, p.t_true, p.mode_s >= 0, ehs_rng(cfg.seed, i, day_block), ehs,
                                      sched.system)
            p.ehs = np.column_stack([cols[c] for c in SIMULATED_COLUMNS])
        out.append(_to_window(p, traj, tb0, t_win0, radar.scan_period_s))
    for j, m in enumerate(cfg.mlat or ()):
        # keyed apart from the radars' draws: adding an MLAT sensor leaves the radars' plots as they were
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(8, day_block, j)))
        p = observe_mlat(traj, m, sched.system, cfg.runs, rng, sub)
        p = take_plots(p, np.flatnonzero(p.scan < len(scan_starts(m, nb))))
        out.append(_to_window(p, traj, tb0, t_win0, m.scan_period_s))
    for j, st in enumerate(cfg.adsb_station or ()):
        rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(9, day_block, j)))
        p = observe_adsb(traj, st, sched.system, cfg.runs, rng, sub, cfg.seed)
        p = take_plots(p, np.flatnonzero(p.scan < len(scan_starts(st, nb))))
        out.append(_to_window(p, traj, tb0, t_win0, st.scan_period_s))
    return out


def _to_window(p: Plots, traj: Trajectories, tb0: float, t_win0: float, period: float) -> Plots:
    """A block's plots in the scenario's time, global aircraft indices and scan numbers counted
    from the window start."""
    p.aircraft = np.where(p.aircraft >= 0, traj.truth_id[np.maximum(p.aircraft, 0)], -1)
    p.t_true, p.t_report = p.t_true + tb0, p.t_report + tb0
    p.scan = p.scan + int(round((tb0 - t_win0) / period))
    return p


def _number_window(cfg: ScenarioConfig, plots: list[Plots], n_scans: list[int], state, job_plots: int | None = None):
    """:func:`tertiary.simulate.radar.number_plots` for one window, carrying the association
    state (``state`` None: the first window). Sets each plot's track number and life in place.
    Ideal radar trackers (``radar_tracker.ideal``, one window only) number from the truth.
    ``job_plots``: the whole simulation's plots (estimated), for the compiled loop's decision."""
    if cfg.radar_tracker.ideal:
        plots = [numbered_by_truth(p, r) for p, r in zip(plots, sensors(cfg))]
    idx = np.concatenate([np.full(len(p), i, np.int64) for i, p in enumerate(plots)])
    allp = plots[0] if len(plots) == 1 else merge_plots(plots)
    if cfg.radar_tracker.ideal:
        return allp, idx, None
    radars = sensors(cfg)
    sig = np.array([[r.sigma_range_m, r.sigma_azimuth_deg, r.sigma_elevation_deg] for r in radars])[idx]
    z, cov = rt.ground_plots(allp.range_m, allp.azimuth_deg, allp.elevation_deg, sig[:, 0], sig[:, 1], sig[:, 2])
    if allp.cart.shape[1]:           # an MLAT sensor's tracker associates its Cartesian plots as stated
        c = np.flatnonzero(np.isfinite(allp.cart[:, 0]))
        z[c], cov[c] = allp.cart[c, :2], plot_cov_xy(*allp.cart[c, 2:5].T)
    period = np.array([r.scan_period_s for r in radars])
    drop = np.array([rt.drop_misses(r.track_drop_scans) for r in radars], np.int64)
    scan = rt.ScanPlots(part=idx * cfg.runs + allp.run.astype(np.int64), t=allp.t_report, z=z, r=cov,
                        mode_s=allp.mode_s, mode_3a=allp.mode_3a, period=period[idx], drop_misses=drop[idx],
                        scanned=np.zeros(0, np.int64))
    numbers, state = rt.run_scans(cfg.radar_tracker, allp.scan, scan, np.repeat(np.array(n_scans, np.int64), cfg.runs),
                                  state, job_plots=job_plots)
    allp.local_track_id, allp.track_life = numbers[:, 0].astype(np.uint32), numbers[:, 1]
    return allp, idx, state


def _secondary(frame: pl.DataFrame, radars: pl.DataFrame, cfg: ScenarioConfig, first_id: int) -> pl.DataFrame:
    """Each radar's Singer secondary processing of whole local-track lives (as :func:`simulate`)."""
    columns = [c for c in frame.columns if c != "__life"]
    out = track_reports(frame.rename({"local_track_id": "__number"})
                        .with_columns(pl.col("__life").cast(pl.UInt32).alias("local_track_id")),
                        radars, cfg.tracker.local_tracker())
    out = out.with_columns(pl.col("__number").alias("local_track_id")).drop("__number", "__life")
    out = out.select([c for c in columns if c in out.columns] + [c for c in out.columns if c not in columns])
    return out.with_columns((pl.int_range(pl.len(), dtype=pl.UInt64) + first_id).alias("report_id"))


def _merged(parts: list[Plots]) -> Plots:
    return parts[0] if len(parts) == 1 else merge_plots(parts)


def _window_bounds(cfg: ScenarioConfig, window_s: float | None) -> list[tuple[float, float]]:
    """Windows [t0, t1) covering the scenario; a window is a whole number of blocks."""
    blk = block_s(cfg)
    w = cfg.duration_s if window_s is None else float(window_s)
    if window_s is not None:
        if not (math.isfinite(w) and w > 0):
            raise OptionError(f"must be a positive number of seconds, got {window_s!r}", option="--window")
        k = w / blk
        if abs(k - round(k)) > 1e-9:
            raise OptionError(f"must be a multiple of the scenario's block of {blk:g} s, got {w:g}", option="--window")
    w = max(blk, math.ceil(w / blk - 1e-9) * blk)
    edges = list(np.arange(0.0, cfg.duration_s, w)) + [cfg.duration_s]
    return [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]


def simulate_windows(cfg: ScenarioConfig, window_s: float | None = None, progress: Progress | None = None,
                     ehs: EhsConfig | None = EhsConfig()) -> tuple[ScenarioConfig, pl.DataFrame, Iterator[SimWindow]]:
    """A scenario simulated window by window: (checked config, radars table, windows).

    ``terminal-area`` and ``national``: streamed in bounded memory (module comment above); the
    tables do not depend on ``window_s`` (a multiple of :func:`block_s`; None: one window).
    Their Mode S reports carry the EHS columns (``ehs``; None: without). Other kinds are
    simulated whole (:func:`simulate`) and cut into windows by time."""
    cfg = check_scenario(cfg)
    if cfg.kind not in STREAMED:
        ds = simulate(cfg, progress, ehs)
        return ds.scenario, ds.radars, _cut(ds, _window_bounds(ds.scenario, window_s))
    bounds = _window_bounds(cfg, window_s)
    if cfg.radar_tracker.ideal and len(bounds) > 1:
        raise OptionError("ideal radar trackers number plots from a whole run's truth; a windowed simulation "
                          "streams: use the radars' own association or one window", option="radar_tracker.ideal")
    return cfg, radars_frame(cfg), _streamed_windows(cfg, bounds, progress, ehs)


def _streamed_windows(cfg: ScenarioConfig, bounds: list[tuple[float, float]], progress: Progress | None,
                      ehs: EhsConfig | None) -> Iterator[SimWindow]:
    say = progress or (lambda _msg: None)
    say("truth schedule")
    sched = _schedule(cfg)
    radars = radars_frame(cfg)
    plans = flight_plans(sched.traffic, sched.tx) if isinstance(sched.traffic, TerminalTraffic) else pl.DataFrame()
    blk = block_s(cfg)
    state, carry, next_id = None, None, 0
    for w, (t0, t1) in enumerate(bounds):
        say(f"radar scans window {w + 1}/{len(bounds)}")
        blocks = [_observe_block(cfg, sched, b, t0, ehs)
                  for b in range(int(round(t0 / blk)), int(math.ceil(t1 / blk - 1e-9)))]
        plots = [_merged([bl[i] for bl in blocks]) for i in range(len(sensors(cfg)))]
        n_scans = [len(scan_starts(r, t1 - t0)) for r in sensors(cfg)]
        say(f"radar plot-to-track window {w + 1}/{len(bounds)}")
        # the job's plots, estimated from this window's, decide whether compiling the loop pays
        job = sum(len(p) for p in plots) * (len(bounds) - w)
        allp, idx, state = _number_window(cfg, plots, n_scans, state, job)
        parts = [_reports_frame(take_plots(allp, np.flatnonzero(idx == i)), i + 1, sched.ghost, sched.tx)
                 for i in range(len(cfg.radars))]
        parts += [_mlat_columns(_reports_frame(p, len(cfg.radars) + j + 1, sched.ghost, sched.tx), p,
                                _site(m, sched.system))
                  for j, m in enumerate(cartesian_sensors(cfg))
                  for p in [take_plots(allp, np.flatnonzero(idx == len(cfg.radars) + j))]]
        frame = pl.concat(([carry] if carry is not None else []) + parts,
                          how="diagonal_relaxed" if cartesian_sensors(cfg) else "vertical")
        last = w == len(bounds) - 1
        live = state.life if state is not None and not last else np.zeros(0, np.int64)
        alive = pl.Series(np.isin(frame["__life"].to_numpy(), live))
        carry = frame.filter(alive)
        say(f"radar secondary window {w + 1}/{len(bounds)}")
        reports = _secondary(frame.filter(~alive), radars, cfg, next_id)
        next_id += reports.height
        # a part holds the local tracks that ended in its window, so its reports go back in time:
        # in time order, the row groups' statistics let a reader of one time window skip the rest
        reports = reports.sort("time", maintain_order=True)
        k0, k1 = int(round(t0 / cfg.dt)), int(round(t1 / cfg.dt)) + (1 if last else 0)
        truth = sched.traffic.window(sched.k_start + k0, k1 - k0).to_frame(frame=sched.system)
        yield SimWindow(index=w, t0_s=t0, t1_s=t1, reports=reports, truth=truth,
                        flight_plans=plans if w == 0 else plans.clear())
        # released before the next window is made, not when its names are bound again: the
        # last window's plots and tables beside the next one's would double the peak memory
        del blocks, plots, allp, idx, parts, frame, alive, reports, truth


def _cut(ds: Dataset, bounds: list[tuple[float, float]]) -> Iterator[SimWindow]:
    """A whole dataset's reports and truth cut into time windows (report time, truth time)."""
    epoch = ds.truth["time"].min() if ds.truth.height else ds.reports["time"].min()
    for w, (t0, t1) in enumerate(bounds):
        last = w == len(bounds) - 1
        lo, hi = epoch + timedelta(seconds=t0), epoch + timedelta(seconds=t1)

        def part(df: pl.DataFrame) -> pl.DataFrame:
            if df.height == 0:
                return df
            keep = (pl.col("time") >= lo) if w else pl.lit(True)
            return df.filter(keep & ((pl.col("time") < hi) if not last else pl.lit(True)))
        yield SimWindow(index=w, t0_s=t0, t1_s=t1, reports=part(ds.reports), truth=part(ds.truth),
                        flight_plans=ds.flight_plans if w == 0 else ds.flight_plans.clear())


def simulate(cfg: ScenarioConfig, progress: Progress | None = None, ehs: EhsConfig | None = EhsConfig()
             ) -> Dataset:
    """Simulate a scenario: terminal-area and national streamed in one window and gathered
    (:func:`simulate_windows`; the national traffic without EHS columns), the others whole
    (:func:`_simulate_whole`). Same config (incl. seed) → identical tables."""
    if isinstance(cfg, ScenarioConfig) and cfg.kind in STREAMED:
        scen, radars, windows = simulate_windows(cfg, None, progress, ehs)
        got = list(windows)
        plans = [w.flight_plans for w in got if w.flight_plans.height]
        return Dataset(radars=radars, reports=pl.concat([w.reports for w in got]),
                       truth=pl.concat([w.truth for w in got]), scenario=scen,
                       flight_plans=pl.concat(plans) if plans else pl.DataFrame())
    return _simulate_whole(cfg, progress, ehs)


def write_stream(cfg: ScenarioConfig, out_dir: str | Path, window_s: float | None = None,
                 progress: Progress | None = None) -> dict:
    """Simulate ``cfg`` window by window into a partitioned dataset: ``radars.parquet``,
    ``reports/part-NNNN.parquet``, ``truth/part-NNNN.parquet`` (one per window, each written
    atomically), ``scenario.toml`` and last ``parts.json`` (the parts and their row counts: a
    dataset without it is incomplete and :func:`read_dataset` refuses it). Returns the
    summary written to ``parts.json``."""
    out = dataset_dir(out_dir)
    (out / PARTS_MANIFEST).unlink(missing_ok=True)
    scen, radars, windows = simulate_windows(cfg, window_s, progress)
    for name in PARTITIONED:
        (out / name).mkdir(exist_ok=True)
        for old in (out / name).glob("part-*.parquet"):
            old.unlink()
    for name in ("reports.parquet", "truth.parquet", "flight_plans.parquet"):
        (out / name).unlink(missing_ok=True)
    write_parquet_atomic(radars, out / "radars.parquet")
    parts: list[dict] = []
    plans: list[pl.DataFrame] = []
    for win in windows:
        if win.flight_plans.height:
            plans.append(win.flight_plans)
        entry = {"window": win.index, "t0_s": win.t0_s, "t1_s": win.t1_s}
        for name in PARTITIONED:
            table = getattr(win, name)
            write_parquet_atomic(table, out / name / f"part-{win.index:04d}.parquet", **ROW_GROUPS)
            entry[f"{name}_rows"] = table.height
        parts.append(entry)
        del win, table          # not held while the next window is made (see _streamed_windows)
    if plans:
        write_parquet_atomic(pl.concat(plans), out / "flight_plans.parquet")
    write_text_atomic(out / "scenario.toml", scenario_toml(scen))
    summary = {"window_s": None if window_s is None else float(window_s), "parts": parts, "radars": radars.height,
               "reports": sum(p["reports_rows"] for p in parts), "truth_rows": sum(p["truth_rows"] for p in parts)}
    write_text_atomic(out / PARTS_MANIFEST, json.dumps(summary, indent=1) + "\n")
    return summary
