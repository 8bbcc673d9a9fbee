"""Scenario definitions: frozen dataclasses loaded from / written to TOML (``datasets/*.toml``)."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
import re
import types
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

from tertiary.contract import Limits
from tertiary.core.errors import DataError, OptionError, ResourceError
from tertiary.filters.singer import SingerModel
from tertiary.sensors.local_tracks import LocalTrackerConfig
from tertiary.simulate.adsb_station import AdsbStationConfig, check_adsb_station
from tertiary.simulate.mlat import MlatConfig, check_mlat
from tertiary.simulate.radar_tracker import RadarTrackerConfig

Kind = Literal["big-box", "terminal-area", "adsb", "national"]


@dataclass(frozen=True)
class RadarConfig:
    """One simulated sensor. Site either geodetic (lat/lon/alt) or ``site_enu_m`` in the
    system frame (converted with the scenario origin)."""

    name: str
    scan_period_s: float
    sigma_range_m: float
    sigma_azimuth_deg: float
    sigma_elevation_deg: float
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float = 0.0
    site_enu_m: tuple[float, float, float] | None = None
    scan_phase_s: float = 0.0
    max_range_m: float = 250_000.0
    min_elevation_deg: float = 0.0
    max_elevation_deg: float = 40.0      # cone of silence above the antenna
    pd: float = 1.0
    clutter_rate: float = 0.0            # false reports per scan (Poisson mean)
    bias_range_m: float = 0.0
    bias_azimuth_deg: float = 0.0
    time_offset_s: float = 0.0           # radar clock minus true time
    timing: Literal["rotating", "synchronous"] = "rotating"
    track_drop_scans: float = 3.5        # a gap longer than this many scans starts a new local track


@dataclass(frozen=True)
class Anomalies:
    """Anomaly injection applicable to any scenario (seed 003 noise inflation 3×/5×/6×, ...).

    ``radars`` limits noise inflation, outliers and the bias step to those radar names (empty =
    all); windows are (start_s, end_s) from the run start.
    """

    noise_factor: float = 1.0
    noise_window_s: tuple[float, float] | None = None
    radars: tuple[str, ...] = ()
    dropout_radar: str | None = None
    dropout_window_s: tuple[float, float] | None = None
    outlier_fraction: float = 0.0
    outlier_sigma_factor: float = 20.0
    bias_step_time_s: float | None = None
    bias_step_range_m: float = 0.0
    bias_step_azimuth_deg: float = 0.0


@dataclass(frozen=True)
class TrafficConfig:
    """Terminal-area traffic generator (procedures: :func:`tertiary.simulate.traffic.terminal.terminal_area`).

    ``aircraft`` is the number that fly during the scenario (they enter and leave over it).
    After ``conflict_pairs`` designed losses of separation and ``near_miss_pairs`` designed
    near misses (pairs at 1.15–1.45× the horizontal minimum), the rest is split into holding
    (``holding_fraction``), arrivals, departures and overflights (the remainder); arrivals and
    departures are capped by the runway slots (``arrival_spacing_s``). ``sep_h_m`` /
    ``sep_v_m`` are the minima the procedures keep (those of safety.SEPARATION_MINIMA
    "terminal"); ``level_buffer_m`` is added per 1 000 ft of flight level (geometric height of
    a pressure level in an atmosphere ~1 K warmer than ISA) so that adjacent levels are never
    exactly on the strict loss-of-separation boundary.

    ``area_radius_m`` … ``lifetime_s`` are kept for compatibility (the procedure generator
    does not use them; routes are fixed by the procedure design).

    Selected altitude (Mode S EHS BDS 4,0, :class:`tertiary.simulate.traffic.base.TrafficTrajectories`):
    ``selected_alt_fraction`` of the aircraft downlink the level their crew selected;
    ``bust_selected`` is what a level-bust aircraft selected: ``"flown"`` (the wrong level it
    then climbs to — the common real cause) or ``"cleared"`` (its cleared level, below).
    The selection changes during a flight where the crew's procedure changes it: an arrival
    selects the approach altitude (3 000 ft) and, once established on the glide path (a delay
    drawn in ``missed_approach_delay_s`` after the glide-path descent begins), the
    missed-approach altitude ``missed_approach_ft``.
    """

    aircraft: int = 200
    area_radius_m: float = 60_000.0
    speed_mps: tuple[float, float] = (90.0, 200.0)
    altitude_m: tuple[float, float] = (900.0, 7500.0)
    turn_rate_dps: tuple[float, float] = (1.5, 3.0)
    straight_s: tuple[float, float] = (60.0, 360.0)
    vertical_rate_mps: tuple[float, float] = (4.0, 12.0)
    lifetime_s: tuple[float, float] = (1800.0, 3600.0)
    holding_fraction: float = 0.08
    conflict_pairs: int = 10
    conflict_miss_m: tuple[float, float] = (0.0, 1500.0)
    mode_s_fraction: float = 0.95
    near_miss_pairs: int = 5
    arrival_fraction: float = 0.22
    departure_fraction: float = 0.2
    arrival_spacing_s: float = 105.0
    overflight_spacing_s: float = 300.0
    sep_h_m: float = 5556.0
    sep_v_m: float = 304.8
    level_buffer_m: float = 1.0
    selected_alt_fraction: float = 0.95
    bust_selected: str = "flown"
    missed_approach_ft: float = 4000.0
    missed_approach_delay_s: tuple[float, float] = (5.0, 15.0)


@dataclass(frozen=True)
class TrackerParams:
    """Per-radar secondary processing (Singer channels, seed (4.50)–(4.71))."""

    alpha: float = 1.0 / 30.0
    sigma_m: float = 2.0
    cross_sigma_m: float = 2.0
    variant: Literal["printed", "exact"] = "printed"
    v0_sigma_mps: float = 300.0

    def local_tracker(self) -> LocalTrackerConfig:
        return LocalTrackerConfig(range_model=SingerModel(self.alpha, self.sigma_m, self.variant),
                                  cross_sigma_m=self.cross_sigma_m, v0_sigma_mps=self.v0_sigma_mps)


@dataclass(frozen=True)
class TransponderConfig:
    """What the aircraft's transponders reply (:func:`tertiary.simulate.radar.transponders`).

    * ``mode_s_fraction``: fraction of aircraft with a Mode S address; ``None`` = as the
      traffic says (terminal-area: ``traffic.mode_s_fraction``; big-box and ADS-B: all).
    * ``mode_s_missing_rate`` / ``mode_3a_missing_rate``: fraction of replies whose address /
      code is not decoded (the report carries none).
    * ``duplicate_code_fraction``: fraction of aircraft squawking another aircraft's code.
    * ``code_change_fraction``: fraction of aircraft changing code once during the scenario.
    """

    mode_s_fraction: float | None = None
    mode_s_missing_rate: float = 0.02
    mode_3a_missing_rate: float = 0.02
    duplicate_code_fraction: float = 0.03
    code_change_fraction: float = 0.1


@dataclass(frozen=True)
class AdsbConfig:
    truth_file: str = ""
    start_s: float = 0.0                 # offset into the recording
    max_alt_m: float = 15_000.0
    max_gap_s: float = 60.0
    min_nacp: int = 8                    # fixes declaring a lower NACp are not truth (when declared)


@dataclass(frozen=True)
class Airport:
    """An airport of the national scenario: threshold position and the direction of the runway
    in use (deg true: every take-off and landing of the day flies it)."""

    name: str
    lat_deg: float
    lon_deg: float
    runway_deg: float
    weight: float = 1.0                  # share of the domestic flights starting or ending here


@dataclass(frozen=True)
class NationalConfig:
    """National traffic (:func:`tertiary.simulate.traffic.national.national_flights`): domestic flights
    between ``airports`` (SID climb, cruise at a semicircular flight level, descent and a
    straight-in final) and overflights on ``airways`` across the area, entering over a day
    whose airborne count follows ``hourly_curve`` (relative weights per UTC hour, scaled so
    that the peak is ``peak_airborne``). ``landing_spacing_s`` separates landings at an
    airport, ``departure_spacing_s`` its take-offs, ``lane_spacing_s`` entries on one (route,
    level) lane; each flight's level and delay are planned so that flights keep 5 NM and a
    buffer, or 1 000 ft, apart above FL150 (:func:`tertiary.simulate.traffic.national.allocate_levels`).
    Random draws of the radar scans are made per ``block_s`` of time, so the data do not depend
    on the window the simulation is written in (a window must be a multiple of ``block_s``).
    The run covers [``start_s``, ``start_s`` + duration) of the day (the schedule is the whole
    day's, the draws are keyed by the block of the day: an hour is the same whatever the run's
    start).
    ``enroute_floor_fl``: the floor of the area's en-route airspace (0: none): two aircraft
    both below it may be 3 NM apart (the terminal area), any other pair needs 5 NM (its traffic
    is planned so above FL150); the pipeline's STCA and its loss-of-separation scoring take it
    (:func:`tertiary.pipeline.adapt_to_scenario`)."""

    airports: tuple[Airport, ...] = ()
    peak_airborne: int = 1500
    hourly_curve: tuple[float, ...] = (0.08, 0.05, 0.04, 0.04, 0.08, 0.3, 0.7, 0.95, 1.0, 0.95, 0.9, 0.88,
                                       0.9, 0.92, 0.9, 0.88, 0.92, 0.98, 1.0, 0.9, 0.7, 0.5, 0.3, 0.15)
    overflight_fraction: float = 0.35
    min_route_km: float = 150.0
    landing_spacing_s: float = 90.0
    departure_spacing_s: float = 90.0
    lane_spacing_s: float = 120.0
    area_half_width_km: float = 500.0
    block_s: float = 600.0
    start_s: float = 0.0                 # the run starts this long after 00:00 UTC (a multiple of block_s)
    enroute_floor_fl: float = 150.0      # en-route airspace (5 NM) from this level up; 0: none


@dataclass(frozen=True)
class ScenarioConfig:
    name: str
    kind: Kind
    seed: int = 0
    runs: int = 1
    duration_s: float = 3600.0
    dt: float = 1.0
    origin: tuple[float, float, float] | None = None     # None (adsb only): centre of the traffic
    radars: tuple[RadarConfig, ...] = ()                   # empty (adsb only): placed around the traffic
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    anomalies: Anomalies = field(default_factory=Anomalies)
    tracker: TrackerParams = field(default_factory=TrackerParams)
    adsb: AdsbConfig = field(default_factory=AdsbConfig)
    transponders: TransponderConfig = field(default_factory=TransponderConfig)
    radar_tracker: RadarTrackerConfig = field(default_factory=RadarTrackerConfig)
    national: NationalConfig | None = None                 # kind "national" only (omitted elsewhere)
    mlat: tuple[MlatConfig, ...] | None = None             # MLAT / WAM sensors ([[mlat]]), after the radars
    adsb_station: tuple[AdsbStationConfig, ...] | None = None   # ADS-B ground stations, after the MLAT

    def replace(self, **changes: Any) -> "ScenarioConfig":
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


# --------------------------------------------------------------------------- dict <-> dataclass


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _type_error(where: str, expected: str, value: Any) -> OptionError:
    return OptionError(f"expected {expected}, got {type(value).__name__} {_show(value)}", option=where)


def _convert(tp: Any, value: Any, where: str = "") -> Any:
    """``value`` as type ``tp`` (TOML types are checked, not trusted: a string is never a number)."""
    origin = get_origin(tp)
    if is_dataclass(tp):
        if not isinstance(value, dict):
            raise _type_error(where, "a table", value)
        return from_dict(tp, value, where)
    if origin is Literal:
        if value not in get_args(tp):
            raise OptionError(f"expected one of {', '.join(map(repr, get_args(tp)))}, got {_show(value)}",
                              option=where)
        return value
    if origin in (Union, types.UnionType):  # Optional[...]
        if value is None and type(None) in get_args(tp):
            return None
        inner = [a for a in get_args(tp) if a is not type(None)]
        return _convert(inner[0], value, where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise _type_error(where, "an array", value)
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise OptionError(f"expected {len(args)} values, got {len(value)}: {_show(value)}", option=where)
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _type_error(where, "a number", value)
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _type_error(where, "an integer", value)
        return value
    if tp is str and not isinstance(value, str):
        raise _type_error(where, "a string", value)
    if tp is bool and not isinstance(value, bool):
        raise _type_error(where, "true or false", value)
    return value


def from_dict(cls: type, data: dict[str, Any], where: str = "") -> Any:
    """Build a (nested) frozen dataclass from a TOML-like dict; unknown keys and values of the
    wrong type are an :class:`OptionError` naming the key (e.g. ``radars[1].scan_period_s``)."""
    hints = get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise OptionError(f"unknown key(s) {', '.join(sorted(map(str, unknown)))}; allowed: {', '.join(sorted(names))}",
                          option=where or cls.__name__)
    required = [f.name for f in fields(cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    missing = [n for n in required if n not in data]
    if missing:
        raise OptionError(f"missing key(s) {', '.join(missing)}", option=where or cls.__name__)
    return cls(**{k: _convert(hints[k], v, f"{where}.{k}" if where else k) for k, v in data.items()})


def to_dict(obj: Any) -> Any:
    if is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, tuple):
        return [to_dict(v) for v in obj]
    return obj


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError("TOML cannot hold non-finite numbers")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(data: dict[str, Any], prefix: str = "") -> str:
    """Serialise nested dicts / arrays of tables (None values are omitted)."""
    lines, tables, arrays = [], [], []
    for k, v in data.items():
        if v is None:
            continue
        if isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((k, v))
        else:
            lines.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        out += f"\n[{prefix}{k}]\n" + to_toml(v, f"{prefix}{k}.")
    for k, items in arrays:
        for item in items:
            out += f"\n[[{prefix}{k}]]\n" + to_toml(item, f"{prefix}{k}.")
    return out


def builtin_dir() -> Path:
    """Where the built-in scenario TOML files live: ``tertiary/datasets`` inside an installed
    wheel, or the repository's ``datasets/`` in a source checkout."""
    package = Path(__file__).resolve().parents[1]
    installed = package / "datasets"
    return installed if any(installed.glob("*.toml")) else package.parent / "datasets"


def read_scenario_toml(path: str | Path) -> ScenarioConfig:
    """A scenario from a TOML file; an unreadable, non-UTF-8 or malformed file, an unknown key or
    a value of the wrong type is a :class:`DataError` naming the file and the key."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror or exc}", path=str(p)) from exc
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        hint = " (UTF-16?)" if raw[:2] in (b"\xff\xfe", b"\xfe\xff") or b"\x00" in raw[:64] else ""
        raise DataError(f"not UTF-8 text{hint}: byte {exc.start}", path=str(p)) from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"not valid TOML: {exc}", path=str(p)) from exc
    try:
        return from_dict(ScenarioConfig, data)
    except OptionError as exc:
        raise DataError(str(exc), path=str(p)) from exc
    except (TypeError, ValueError) as exc:
        raise DataError(f"invalid scenario: {exc}", path=str(p)) from exc


def load_scenario(name_or_path: str | Path) -> ScenarioConfig:
    """A scenario by built-in name (``big-box``, ``terminal-area``, ``adsb-paris``) or TOML path.

    An unknown name is an :class:`OptionError` listing the built-ins; a bad file a
    :class:`DataError` (see :func:`read_scenario_toml`)."""
    path = Path(name_or_path)
    if not (path.suffix == ".toml" and path.is_file()):
        path = builtin_dir() / f"{name_or_path}.toml"
        if not (_NAME.fullmatch(str(name_or_path)) and path.is_file()):
            raise OptionError(f"unknown scenario {str(name_or_path)!r} (not a built-in name or an existing .toml "
                              f"file); built-in: {', '.join(builtin_scenarios())}", option="scenario")
    return read_scenario_toml(path)


def builtin_scenarios() -> list[str]:
    return sorted(p.stem for p in builtin_dir().glob("*.toml"))


def scenario_toml(cfg: ScenarioConfig) -> str:
    return to_toml(to_dict(cfg))


def with_radar_count(cfg: ScenarioConfig, m: int) -> ScenarioConfig:
    """Keep the first ``m`` radars, or add sites on a ring around the origin that cycle through
    the defined radars' parameters with scan periods 4–12 s and distinct phases."""
    if isinstance(m, bool) or not isinstance(m, int) or m < 1:
        raise OptionError(f"need at least one radar, got {m!r}", option="radars (--radars)")
    if not cfg.radars:
        raise OptionError(f"scenario {cfg.name!r} defines no radar to scale from", option="radars (--radars)")
    if m <= len(cfg.radars):
        return dataclasses.replace(cfg, radars=cfg.radars[:m])
    periods = (4.0, 5.0, 6.0, 8.0, 10.0, 12.0)
    extra = []
    for i in range(len(cfg.radars), m):
        base = cfg.radars[i % len(cfg.radars)]
        ang = math.radians(137.508 * i)          # golden-angle spread of sites
        ring = 40_000.0 + 15_000.0 * (i % 3)
        period = periods[i % len(periods)]
        extra.append(dataclasses.replace(
            base, name=f"AUX-{i + 1}", lat_deg=None, lon_deg=None, alt_m=100.0,
            site_enu_m=(ring * math.sin(ang), ring * math.cos(ang), 100.0),
            scan_period_s=period, scan_phase_s=(0.37 * i * period) % period))
    return dataclasses.replace(cfg, radars=cfg.radars + tuple(extra))


#: template for radars placed automatically around ADS-B traffic (a terminal SSR/PSR pair)
AUTO_RADAR = RadarConfig(name="AUTO-1", scan_period_s=4.0, sigma_range_m=40.0, sigma_azimuth_deg=0.07,
                         sigma_elevation_deg=0.15, site_enu_m=(0.0, 30_000.0, 100.0), scan_phase_s=0.5,
                         max_range_m=200_000.0, min_elevation_deg=0.1, pd=0.95, clutter_rate=1.0)


def auto_radars(n: int = 4) -> tuple[RadarConfig, ...]:
    """``n`` radars on rings 30–60 km around the system origin (used when a scenario has none)."""
    return with_radar_count(ScenarioConfig(name="auto", kind="adsb", radars=(AUTO_RADAR,)), n).radars


# --------------------------------------------------------------------------- validation

#: a scenario name: run directories are built from it, so never a path
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")

#: command-line flag of each checked field (named in the error beside the field)
_FLAGS = {"runs": "--runs", "seed": "--seed", "duration_s": "--duration", "traffic.aircraft": "--aircraft",
          "adsb.truth_file": "--truth", "anomalies.noise_factor": "--noise-factor",
          "anomalies.noise_window_s": "--noise-window", "anomalies.dropout_radar": "--dropout",
          "anomalies.dropout_window_s": "--dropout", "anomalies.outlier_fraction": "--outliers",
          "anomalies.bias_step_time_s": "--bias-step", "anomalies.bias_step_range_m": "--bias-step",
          "anomalies.bias_step_azimuth_deg": "--bias-step"}

#: refuse simulations estimated beyond this many truth or report rows (memory grows with them)
MAX_SIM_ROWS = 400_000_000


def _opt(field_name: str) -> str:
    flag = _FLAGS.get(field_name)
    return f"{field_name} ({flag})" if flag else field_name


def check_name(name: Any, option: str = "name") -> str:
    """``name`` if it is a scenario identifier (letters, digits, '-', '_'; never a path)."""
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise OptionError(f"must be an identifier (letters, digits, '-' and '_', at most 64, "
                          f"not a path), got {_show(name)}", option=option)
    return name


def _number(where: str, value: Any, lo: float = -math.inf, hi: float = math.inf, *, integer: bool = False,
            open_lo: bool = False) -> None:
    """A finite number (an integer if asked) in [lo, hi] (or (lo, hi] with ``open_lo``)."""
    kind = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind):
        raise _type_error(_opt(where), "an integer" if integer else "a number", value)
    if not math.isfinite(value) or value < lo or value > hi or (open_lo and value == lo):
        left = "(" if open_lo else "["
        raise OptionError(f"must be finite and in {left}{lo:g}, {hi:g}], got {value!r}", option=_opt(where))


def _window(where: str, value: Any) -> None:
    if value is None:
        return
    if not isinstance(value, tuple) or len(value) != 2:
        raise _type_error(_opt(where), "two numbers (start, end)", value)
    for v in value:
        _number(where, v, 0.0)
    if not value[0] < value[1]:
        raise OptionError(f"start must be before end, got {value[0]:g} to {value[1]:g}", option=_opt(where))


def check_origin(origin: Any, option: str = "origin") -> tuple[float, float, float]:
    """``origin`` as (lat, lon, alt) on the globe (alt 0 when two values are given)."""
    if not isinstance(origin, (tuple, list)) or len(origin) not in (2, 3):
        raise _type_error(option, "(lat_deg, lon_deg[, alt_m])", origin)
    values = tuple(origin) + ((0.0,) if len(origin) == 2 else ())
    for name, v, lo, hi in zip(("lat_deg", "lon_deg", "alt_m"), values, (-90, -180, -500), (90, 180, 9000)):
        _number(f"{option}.{name}", v, lo, hi)
    return tuple(float(v) for v in values)  # type: ignore[return-value]


def _check_radar(where: str, r: Any) -> None:
    lim = Limits()
    if not isinstance(r, RadarConfig):
        raise _type_error(where, "a radar table", r)
    if not isinstance(r.name, str) or not r.name.strip():
        raise OptionError("a radar needs a name", option=f"{where}.name")
    _number(f"{where}.scan_period_s", r.scan_period_s, *lim.scan_period_s)
    _number(f"{where}.sigma_range_m", r.sigma_range_m, *lim.sigma_range_m, open_lo=True)
    for k in ("sigma_azimuth_deg", "sigma_elevation_deg"):
        _number(f"{where}.{k}", getattr(r, k), *lim.sigma_angle_deg, open_lo=True)
    _number(f"{where}.max_range_m", r.max_range_m, *lim.max_range_m)
    if r.site_enu_m is None:
        if r.lat_deg is None or r.lon_deg is None:
            raise OptionError("give lat_deg and lon_deg, or site_enu_m", option=where)
        check_origin((r.lat_deg, r.lon_deg, r.alt_m), f"{where}.site")
    else:
        if not isinstance(r.site_enu_m, tuple) or len(r.site_enu_m) != 3:
            raise _type_error(f"{where}.site_enu_m", "three numbers", r.site_enu_m)
        for v in r.site_enu_m:
            _number(f"{where}.site_enu_m", v, -2e6, 2e6)
    _number(f"{where}.scan_phase_s", r.scan_phase_s, 0.0, lim.scan_period_s[1])
    _number(f"{where}.min_elevation_deg", r.min_elevation_deg, -90.0, 90.0)
    _number(f"{where}.max_elevation_deg", r.max_elevation_deg, r.min_elevation_deg, 90.0, open_lo=True)
    _number(f"{where}.pd", r.pd, 0.0, 1.0)
    _number(f"{where}.clutter_rate", r.clutter_rate, *lim.clutter_rate)
    _number(f"{where}.bias_range_m", r.bias_range_m, -1e4, 1e4)
    _number(f"{where}.bias_azimuth_deg", r.bias_azimuth_deg, -180.0, 180.0)
    _number(f"{where}.time_offset_s", r.time_offset_s, -3600.0, 3600.0)
    _number(f"{where}.track_drop_scans", r.track_drop_scans, 0.0, 1e3, open_lo=True)
    if r.timing not in ("rotating", "synchronous"):
        raise OptionError(f"expected 'rotating' or 'synchronous', got {_show(r.timing)}", option=f"{where}.timing")


def _check_traffic(t: TrafficConfig) -> None:
    _number("traffic.aircraft", t.aircraft, 1, 1_000_000, integer=True)
    _number("traffic.area_radius_m", t.area_radius_m, 0.0, 2e6, open_lo=True)
    for k in ("speed_mps", "altitude_m", "turn_rate_dps", "straight_s", "vertical_rate_mps", "lifetime_s",
              "conflict_miss_m"):
        pair = getattr(t, k)
        if not isinstance(pair, tuple) or len(pair) != 2:
            raise _type_error(f"traffic.{k}", "two numbers (low, high)", pair)
        for v in pair:
            _number(f"traffic.{k}", v, -1e7, 1e7)
        if pair[0] > pair[1]:
            raise OptionError(f"low must not exceed high, got {pair}", option=f"traffic.{k}")
    _number("traffic.holding_fraction", t.holding_fraction, 0.0, 1.0)
    _number("traffic.conflict_pairs", t.conflict_pairs, 0, 1_000_000, integer=True)
    _number("traffic.mode_s_fraction", t.mode_s_fraction, 0.0, 1.0)
    _number("traffic.near_miss_pairs", t.near_miss_pairs, 0, 1_000_000, integer=True)
    for k in ("arrival_fraction", "departure_fraction"):
        _number(f"traffic.{k}", getattr(t, k), 0.0, 1.0)
    if t.holding_fraction + t.arrival_fraction + t.departure_fraction > 1.0:
        raise OptionError("holding_fraction + arrival_fraction + departure_fraction must not exceed 1",
                          option="traffic")
    _number("traffic.arrival_spacing_s", t.arrival_spacing_s, 80.0, 3600.0)
    _number("traffic.overflight_spacing_s", t.overflight_spacing_s, 60.0, 3600.0)
    _number("traffic.sep_h_m", t.sep_h_m, 0.0, 1e5, open_lo=True)
    _number("traffic.sep_v_m", t.sep_v_m, 0.0, 1e4, open_lo=True)
    _number("traffic.level_buffer_m", t.level_buffer_m, 0.0, 30.0)
    _number("traffic.selected_alt_fraction", t.selected_alt_fraction, 0.0, 1.0)
    _number("traffic.missed_approach_ft", t.missed_approach_ft, 0.0, 65520.0)
    lo_d, hi_d = t.missed_approach_delay_s
    _number("traffic.missed_approach_delay_s[0]", lo_d, 0.0, 600.0)
    _number("traffic.missed_approach_delay_s[1]", hi_d, lo_d, 600.0)
    if t.bust_selected not in ("flown", "cleared"):
        raise OptionError(f"expected 'flown' or 'cleared', got {_show(t.bust_selected)}", option="traffic.bust_selected")


def _check_anomalies(a: Anomalies, radar_names: list[str]) -> None:
    _number("anomalies.noise_factor", a.noise_factor, 0.0, 1e4, open_lo=True)
    _window("anomalies.noise_window_s", a.noise_window_s)
    known = ", ".join(radar_names) or "none"
    for name in a.radars:
        if name not in radar_names:
            raise OptionError(f"unknown radar {name!r}; radars: {known}", option="anomalies.radars")
    if a.dropout_radar is not None:
        if a.dropout_radar not in radar_names:
            raise OptionError(f"unknown radar {a.dropout_radar!r}; radars: {known}",
                              option=_opt("anomalies.dropout_radar"))
        if a.dropout_window_s is None:
            raise OptionError("a dropout needs its window T0:T1", option=_opt("anomalies.dropout_window_s"))
    _window("anomalies.dropout_window_s", a.dropout_window_s)
    _number("anomalies.outlier_fraction", a.outlier_fraction, 0.0, 1.0)
    _number("anomalies.outlier_sigma_factor", a.outlier_sigma_factor, 0.0, 1e4, open_lo=True)
    if a.bias_step_time_s is not None:
        _number("anomalies.bias_step_time_s", a.bias_step_time_s, 0.0)
    _number("anomalies.bias_step_range_m", a.bias_step_range_m, -1e5, 1e5)
    _number("anomalies.bias_step_azimuth_deg", a.bias_step_azimuth_deg, -180.0, 180.0)


def resolve_data_path(path: str) -> Path:
    """A data file path: absolute, or relative to the working directory, to the built-in
    scenarios' directory (the shipped samples sit beside their TOML) or to the repository (a
    missing file is a :class:`DataError` listing where it was looked for)."""
    p = Path(path).expanduser()
    candidates = [p] if p.is_absolute() else [Path.cwd() / p, builtin_dir() / p, Path(__file__).resolve().parents[2] / p]
    for c in candidates:
        if c.is_file():
            return c
    raise DataError(f"file not found (looked in: {', '.join(map(str, candidates))}); give an existing "
                    f"ADS-B trajectory file with --truth FILE", path=str(path))


def check_scenario(cfg: ScenarioConfig) -> ScenarioConfig:
    """``cfg`` after checking every option before any work: counts ≥ 1, durations finite and
    positive, fractions in [0, 1], windows ordered, named radars existing, seed in range, the
    ADS-B truth file present, the estimated size bounded.

    Raises :class:`OptionError` naming the option (field and command-line flag),
    :class:`DataError` for a missing truth file, :class:`ResourceError` for a simulation
    estimated beyond :data:`MAX_SIM_ROWS` rows."""
    if not isinstance(cfg, ScenarioConfig):
        raise _type_error("scenario", "a ScenarioConfig", cfg)
    check_name(cfg.name)
    if cfg.kind not in get_args(Kind):
        raise OptionError(f"expected one of {', '.join(get_args(Kind))}, got {_show(cfg.kind)}", option="kind")
    _number("seed", cfg.seed, 0, 2 ** 63 - 1, integer=True)
    _number("runs", cfg.runs, 1, 100_000, integer=True)
    _number("duration_s", cfg.duration_s, 0.0, 366 * 86400.0, open_lo=True)
    _number("dt", cfg.dt, 0.0, cfg.duration_s, open_lo=True)
    if cfg.origin is not None or cfg.kind != "adsb":
        if cfg.origin is None:
            raise OptionError(f"a {cfg.kind} scenario needs an origin (lat, lon, alt)", option="origin")
        check_origin(cfg.origin)
    if not cfg.radars and cfg.kind != "adsb":
        raise OptionError("needs at least one radar", option="radars (--radars)")
    for i, r in enumerate(cfg.radars):
        _check_radar(f"radars[{i}]", r)
    names = [r.name for r in cfg.radars] or [r.name for r in auto_radars()]
    for i, m in enumerate(cfg.mlat or ()):
        check_mlat(f"mlat[{i}]", m, _number)
    for i, st in enumerate(cfg.adsb_station or ()):
        check_adsb_station(f"adsb_station[{i}]", st, _number)
    for key in ("mlat", "adsb_station"):
        if getattr(cfg, key) and cfg.kind not in ("terminal-area", "national"):
            raise OptionError(f"MLAT sensors and ADS-B stations are simulated in the streamed scenarios "
                              f"(terminal-area, national), not {cfg.kind!r}", option=key)
    extra = [m.name for m in (*(cfg.mlat or ()), *(cfg.adsb_station or ()))]
    if len(set(names + extra)) != len(names) + len(extra):
        raise OptionError(f"radar names must be unique, got {', '.join(names)}", option="radars")
    _check_traffic(cfg.traffic)
    _check_anomalies(cfg.anomalies, names)
    t = cfg.tracker
    for k in ("alpha", "sigma_m", "cross_sigma_m", "v0_sigma_mps"):
        _number(f"tracker.{k}", getattr(t, k), 0.0, 1e6, open_lo=True)
    _check_transponders(cfg.transponders)
    _check_radar_tracker(cfg.radar_tracker)
    if cfg.kind != "adsb" and cfg.adsb.truth_file:
        raise OptionError(f"an ADS-B truth file applies to the adsb scenarios only, not to {cfg.kind!r}",
                          option=_opt("adsb.truth_file"))
    if cfg.kind == "adsb":
        if not isinstance(cfg.adsb.truth_file, str) or not cfg.adsb.truth_file:
            raise OptionError("the adsb scenarios need an ADS-B trajectory file", option=_opt("adsb.truth_file"))
        resolve_data_path(cfg.adsb.truth_file)
        _number("adsb.start_s", cfg.adsb.start_s, 0.0)
        _number("adsb.max_alt_m", cfg.adsb.max_alt_m, 0.0, 1e5, open_lo=True)
        _number("adsb.max_gap_s", cfg.adsb.max_gap_s, 0.0, 86400.0, open_lo=True)
        _number("adsb.min_nacp", cfg.adsb.min_nacp, 0, 11, integer=True)
    if cfg.kind == "national":
        _check_national(cfg.national, cfg)
    elif cfg.national is not None:
        raise OptionError(f"a [national] table applies to the national scenario only, not to {cfg.kind!r}",
                          option="national")
    _check_size(cfg)
    return cfg


def _check_national(n: NationalConfig | None, cfg: ScenarioConfig) -> None:
    """The national traffic options: airports on the globe, a 24-value curve, spacings, the
    RNG block a divisor of nothing in particular but a multiple of every scan period."""
    if n is None:
        raise OptionError("the national scenario needs a [national] table with its airports", option="national")
    if len(n.airports) < 2:
        raise OptionError(f"needs at least two airports, got {len(n.airports)}", option="national.airports")
    for i, a in enumerate(n.airports):
        check_origin((a.lat_deg, a.lon_deg, 0.0), f"national.airports[{i}]")
        _number(f"national.airports[{i}].runway_deg", a.runway_deg, 0.0, 360.0)
        _number(f"national.airports[{i}].weight", a.weight, 0.0, 1e6, open_lo=True)
    _number("national.peak_airborne", n.peak_airborne, 1, 100_000, integer=True)
    if len(n.hourly_curve) != 24:
        raise OptionError(f"needs 24 hourly weights, got {len(n.hourly_curve)}", option="national.hourly_curve")
    for v in n.hourly_curve:
        _number("national.hourly_curve", v, 0.0, 1e6)
    if max(n.hourly_curve) <= 0:
        raise OptionError("needs a positive weight", option="national.hourly_curve")
    _number("national.overflight_fraction", n.overflight_fraction, 0.0, 1.0)
    _number("national.min_route_km", n.min_route_km, 50.0, 5000.0)
    _number("national.landing_spacing_s", n.landing_spacing_s, 30.0, 3600.0)
    _number("national.departure_spacing_s", n.departure_spacing_s, 30.0, 3600.0)
    _number("national.lane_spacing_s", n.lane_spacing_s, 30.0, 3600.0)
    _number("national.area_half_width_km", n.area_half_width_km, 50.0, 3000.0)
    _number("national.block_s", n.block_s, cfg.dt, 86400.0)
    _number("national.start_s", n.start_s, 0.0, 86400.0)
    _number("national.enroute_floor_fl", n.enroute_floor_fl, 0.0, 600.0)
    if abs(n.start_s / n.block_s - round(n.start_s / n.block_s)) > 1e-9:
        raise OptionError(f"must be a multiple of block_s ({n.block_s:g} s), got {n.start_s:g}",
                          option="national.start_s")
    for r in cfg.radars:
        k = n.block_s / r.scan_period_s
        if abs(k - round(k)) > 1e-9:
            raise OptionError(f"must be a multiple of every scan period (radar {r.name}: {r.scan_period_s:g} s), "
                              f"got {n.block_s:g}", option="national.block_s")


def _check_transponders(t: TransponderConfig) -> None:
    if t.mode_s_fraction is not None:
        _number("transponders.mode_s_fraction", t.mode_s_fraction, 0.0, 1.0)
    for k in ("mode_s_missing_rate", "mode_3a_missing_rate", "duplicate_code_fraction", "code_change_fraction"):
        _number(f"transponders.{k}", getattr(t, k), 0.0, 1.0)


def _check_radar_tracker(r: RadarTrackerConfig) -> None:
    if not isinstance(r.ideal, bool):
        raise _type_error("radar_tracker.ideal", "true or false", r.ideal)
    if not isinstance(r.mode_s_gate, bool):
        raise _type_error("radar_tracker.mode_s_gate", "true or false", r.mode_s_gate)
    _number("radar_tracker.gate_chi2", r.gate_chi2, 0.0, 1e4, open_lo=True)
    _number("radar_tracker.q_m2s3", r.q_m2s3, 0.0, 1e6)
    _number("radar_tracker.v0_sigma_mps", r.v0_sigma_mps, 0.0, 1e4, open_lo=True)
    _number("radar_tracker.confirm_hits", r.confirm_hits, 1, 1000, integer=True)
    _number("radar_tracker.tentative_misses", r.tentative_misses, 1, 1000, integer=True)
    _number("radar_tracker.code_mismatch_cost", r.code_mismatch_cost, 0.0, 1e6)
    _number("radar_tracker.reuse_after_scans", r.reuse_after_scans, 0, 1_000_000, integer=True)


def _check_size(cfg: ScenarioConfig) -> None:
    """Refuse a simulation whose truth or report rows are estimated beyond MAX_SIM_ROWS."""
    if cfg.kind in ("adsb", "national"):
        return      # adsb: sized by the recording; national: simulated block by block in bounded memory
    aircraft = cfg.traffic.aircraft if cfg.kind == "terminal-area" else 2
    truth = aircraft * cfg.duration_s / cfg.dt
    reports = cfg.runs * sum(aircraft * cfg.duration_s / r.scan_period_s * (1.0 + r.clutter_rate / max(aircraft, 1))
                             for r in cfg.radars)
    worst = max(truth, reports)
    if worst > MAX_SIM_ROWS:
        raise ResourceError(f"simulate: about {worst:,.0f} rows estimated ({aircraft:,} aircraft, {cfg.duration_s:g} s, "
                            f"{cfg.runs} run(s), {len(cfg.radars)} radar(s)); the limit is {MAX_SIM_ROWS:,}: "
                            f"reduce --aircraft, --duration or --runs")
