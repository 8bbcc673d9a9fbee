"""Scenario definitions: frozen dataclasses loaded from / written to TOML (``datasets/*.toml``)."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, get_args, get_origin, get_type_hints

from tertiary.filters.singer import SingerModel
from tertiary.local_tracks import LocalTrackerConfig

Kind = Literal["big-box", "terminal-area", "adsb"]


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
    """Terminal-area traffic generator."""

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
class AdsbConfig:
    truth_file: str = ""
    start_s: float = 0.0                 # offset into the recording
    max_alt_m: float = 15_000.0
    max_gap_s: float = 60.0


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

    def replace(self, **changes: Any) -> "ScenarioConfig":
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


# --------------------------------------------------------------------------- dict <-> dataclass


def _convert(tp: Any, value: Any) -> Any:
    origin = get_origin(tp)
    if is_dataclass(tp) and isinstance(value, dict):
        return from_dict(tp, value)
    if origin is tuple and isinstance(value, (list, tuple)):
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v) for v in value)
        return tuple(_convert(a, v) for a, v in zip(args, value))
    if origin is not None and type(None) in get_args(tp):  # Optional[...]
        inner = [a for a in get_args(tp) if a is not type(None)]
        return None if value is None else _convert(inner[0], value)
    if tp is float and isinstance(value, int):
        return float(value)
    return value


def from_dict(cls: type, data: dict[str, Any]) -> Any:
    """Build a (nested) frozen dataclass from a TOML-like dict; unknown keys are an error."""
    hints = get_type_hints(cls)
    names = {f.name for f in fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown keys {sorted(unknown)}; allowed: {sorted(names)}")
    return cls(**{k: _convert(hints[k], v) for k, v in data.items()})


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


def load_scenario(name_or_path: str | Path) -> ScenarioConfig:
    """A scenario by built-in name (``big-box``, ``terminal-area``, ``adsb-paris``) or TOML path."""
    path = Path(name_or_path)
    if not (path.suffix == ".toml" and path.exists()):
        path = builtin_dir() / f"{name_or_path}.toml"
        if not path.exists():
            raise ValueError(f"unknown scenario {str(name_or_path)!r}; built-in: {', '.join(builtin_scenarios())}")
    return from_dict(ScenarioConfig, tomllib.loads(path.read_text()))


def builtin_scenarios() -> list[str]:
    return sorted(p.stem for p in builtin_dir().glob("*.toml"))


def scenario_toml(cfg: ScenarioConfig) -> str:
    return to_toml(to_dict(cfg))


def with_radar_count(cfg: ScenarioConfig, m: int) -> ScenarioConfig:
    """Keep the first ``m`` radars, or add sites on a ring around the origin that cycle through
    the defined radars' parameters with scan periods 4–12 s and distinct phases."""
    if m < 1:
        raise ValueError("need at least one radar")
    if not cfg.radars:
        raise ValueError(f"scenario {cfg.name!r} defines no radar to scale from")
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
