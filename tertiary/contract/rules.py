"""The rules of the data contract: the plausible value bands (:class:`Limits`), the documented
rules with their reasons (:func:`contract_rules`, :data:`RULES`) and the per-column value rules
:func:`tertiary.contract.validation.validate` applies (:func:`value_rules`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import polars as pl

from tertiary.core.units import STATE

__all__ = [
    "Interval", "Limits", "OneOf", "RULES", "Range", "Rule", "ValueRule", "contract_rules", "num_text", "rules_markdown",
    "value_rules",
]

Interval = tuple[float, float]


@dataclass(frozen=True)
class Limits:
    """Plausible value bands (inclusive unless stated) for physically bounded columns.

    Every band is a rule of the data contract; :data:`RULES` states each with its reason.
    """

    altitude_m: Interval = (-500.0, 20000.0)
    range_m: Interval = (0.0, math.inf)          # absolute band, beside the per-radar rule
    range_margin: float = 1.2                    # range_m <= max_range_m x margin of its radar
    site_alt_m: Interval = (-500.0, 9000.0)
    scan_period_s: Interval = (0.1, 60.0)
    max_range_m: Interval = (100.0, 2_000_000.0)
    sigma_range_m: Interval = (0.0, 10_000.0)    # open at 0
    sigma_angle_deg: Interval = (0.0, 10.0)      # open at 0
    clutter_rate: Interval = (0.0, 10_000.0)
    position_m: float = 1e7                      # |x|, |y|, |z| (10 000 km)
    speed_mps: float = 1e4                       # |vx|, |vy|, |vz|
    accel_mps2: float = 1e3
    variance_max: float = 1e14                   # variances in (0, 1e14] (sigma <= 10 000 km)
    years: tuple[int, int] = (1990, 2100)        # times in [1 Jan lo, 1 Jan hi) UTC
    max_span_s: float = 7 * 86400.0              # a table's times within +- span/2 of its median
    truth_pad_s: float = 3600.0                  # truth times within the reports' span +- pad
    cov_rel_tol: float = 1e-6                    # est_cov symmetry/PSD tolerance, x largest diagonal


@dataclass(frozen=True)
class Rule:
    """One documented rule of the data contract: what it demands, why, and what breaks."""

    table: str
    columns: str
    rule: str
    reason: str
    action: str = "row to rejects"


def contract_rules(limits: Limits = Limits()) -> tuple[Rule, ...]:
    """The physical-range and consistency rules :func:`validate` applies, with their reasons."""
    lo_y, hi_y = limits.years
    span_h = limits.max_span_s / 3600.0
    return (
        Rule("any", "required columns", "present, castable to the schema dtype (Boolean is never a number, "
             "text never a time or covariance)", "a table without them cannot be processed", "table: DataError"),
        Rule("any", "required float columns", "not null, not NaN, finite", "arithmetic on them is undefined"),
        Rule("radars", "lat_deg, lon_deg", "[-90, 90], [-180, 180]", "sites are on the globe"),
        Rule("radars", "alt_m", f"[{num_text(limits.site_alt_m[0])}, {num_text(limits.site_alt_m[1])}] m",
             "a ground site (Dead Sea to the highest radar sites)"),
        Rule("radars", "scan_period_s", f"[{num_text(limits.scan_period_s[0])}, {num_text(limits.scan_period_s[1])}] s",
             "rotating surveillance radars scan in 1-12 s; the epoch grid is sized by the fastest scan"),
        Rule("radars", "sigma_range_m", f"(0, {num_text(limits.sigma_range_m[1])}] m",
             "a-priori weights divide by sigma^2; a zero or huge sigma is not a sensor"),
        Rule("radars", "sigma_azimuth_deg, sigma_elevation_deg",
             f"(0, {num_text(limits.sigma_angle_deg[1])}] deg", "as for sigma_range_m"),
        Rule("radars", "max_range_m", f"[{num_text(limits.max_range_m[0])}, {num_text(limits.max_range_m[1])}] m",
             "bounds every report's range (instrumented range of real radars < 500 km)"),
        Rule("radars", "pd, clutter_rate, scan_phase_s, min_elevation_deg",
             "[0, 1], [0, 1e4] per scan, [0, max scan period] s, [-90, 90] deg", "their physical domains"),
        Rule("radars", "radar_id", "unique", "reports refer to radars by id"),
        Rule("radars", "the table", "at least one valid radar",
             "every report needs its radar; with none, all reports are rejected", "all reports to rejects"),
        Rule("reports", "radar_id", "a valid radar of the radars table",
             "reports of an unknown or rejected radar cannot be placed in space"),
        Rule("reports", "range_m", f"(0, max_range_m x {limits.range_margin:g}] of its radar (without a radars "
             f"table: (0, {num_text(limits.max_range_m[1] * limits.range_margin)}] m)",
             "beyond the radar's instrumented range the report is a decoding error"),
        Rule("reports", "azimuth_deg, est_azimuth_deg", "[0, 360)", "angle domain (clockwise from north)"),
        Rule("reports", "elevation_deg, est_elevation_deg", "[-90, 90]", "angle domain"),
        Rule("reports, truth", "altitude_m / alt_m", f"[{num_text(limits.altitude_m[0])}, {num_text(limits.altitude_m[1])}] m",
             "civil air traffic"),
        Rule("reports, truth", "time", f"[{lo_y}-01-01, {hi_y}-01-01) UTC",
             "a time outside is a unit or epoch error (0, 1970, 9999)"),
        Rule("reports, truth", "time", f"within +-{span_h / 2:g} h of the table's median time",
             "grids in time (epochs, alert ticks) are sized by the span; a stray date would allocate "
             "terabytes"),
        Rule("truth", "time", "within the span of the reports' times that pass the two rules above "
             f"+- {num_text(limits.truth_pad_s)} s",
             "truth scores the reports; truth far from them cannot be matched and would size the grids"),
        Rule("reports", "est_range_var_m2, est_azimuth_var_deg2, est_elevation_var_deg2, res_range_var_m2",
             f"(0, {limits.variance_max:g}], not infinite (NaN = no value)", "a variance is positive and finite"),
        Rule("reports", "est_cov", f"finite, symmetric and positive semi-definite (tolerance "
             f"{limits.cov_rel_tol:g} x largest diagonal), diagonal <= {limits.variance_max:g}",
             "a covariance that is not one makes fusion weights singular or negative"),
        Rule("reports, truth", "x_m, y_m, z_m / vx_mps, vy_mps, vz_mps",
             f"|value| <= {limits.position_m:g} m / {limits.speed_mps:g} m/s",
             "values like 1e300 overflow distances, KD-trees and conflict geometry"),
        Rule("reports, truth", "key columns", "unique", "a duplicate would be counted twice"),
        Rule("radars", "kind", "radar, mlat or adsb (null = radar)", "the measurement model of the sensor's reports"),
        Rule("reports", "plot_lat_deg, plot_lon_deg", "[-90, 90], [-180, 180]", "an MLAT or ADS-B plot is on the globe"),
        Rule("reports", "plot_x_m, plot_y_m / plot_height_m", f"|value| <= {limits.position_m:g} m / "
             f"[{num_text(limits.altitude_m[0])}, {num_text(limits.altitude_m[1])}] m", "as for x_m and altitude_m"),
        Rule("reports", "plot_sigma_x_m, plot_sigma_y_m, plot_sigma_xy_m",
             f"(0, {num_text(limits.position_m)}] m, |plot_sigma_xy_m| <= sqrt(plot_sigma_x_m x plot_sigma_y_m) "
             "(NaN = no value)", "a Cartesian measurement covariance must be positive semi-definite"),
        Rule("reports", "plot_x_m, plot_y_m", "present on every report of a sensor of kind mlat or adsb",
             "an MLAT or ADS-B report is a Cartesian plot; without it there is no measurement"),
        Rule("reports", "adsb_nacp, adsb_nic, adsb_sil", "[0, 11], [0, 11], [0, 3] (null = not broadcast)",
             "the DO-260B ranges of the quality indicators"),
    )


def rules_markdown(limits: Limits = Limits()) -> str:
    """:func:`contract_rules` as a Markdown table (table, columns, rule, reason, action)."""
    lines = ["| table | columns | rule | reason | if broken |", "|---|---|---|---|---|"]
    lines += [f"| {r.table} | {r.columns} | {r.rule} | {r.reason} | {r.action} |" for r in contract_rules(limits)]
    return "\n".join(lines)


# ---------------------------------------------------------------------------
# value rules
# ---------------------------------------------------------------------------


def num_text(x: float) -> str:
    """A bound as text: integers without a decimal point, others in ``%g``."""
    if math.isfinite(x) and float(x).is_integer() and abs(x) < 1e7:
        return str(int(x))
    return f"{x:g}"


@dataclass(frozen=True)
class Range:
    """Value must lie in ``[lo, hi]``; ``closed`` as in ``is_between``."""

    lo: float
    hi: float
    closed: str = "both"

    @property
    def problem(self) -> str:
        if self.lo == 0 and self.hi == math.inf:
            return "negative value" if self.closed == "both" else "non-positive value"
        left = "[" if self.closed in ("both", "left") else "("
        right = "]" if self.closed in ("both", "right") else ")"
        return f"outside {left}{num_text(self.lo)}, {num_text(self.hi)}{right}"

    def bad(self, col: pl.Expr) -> pl.Expr:
        return ~col.is_between(self.lo, self.hi, closed=self.closed) & col.is_not_nan()

    def reason(self, name: str, value: pl.Expr) -> pl.Expr:
        sep = " " if self.problem.endswith("value") else ", got "
        return pl.format(f"{name}: {self.problem}{sep}{{}}", value)


@dataclass(frozen=True)
class OneOf:
    """Value must be one of ``values``."""

    values: tuple[str, ...]

    @property
    def problem(self) -> str:
        return f"invalid value, expected one of {', '.join(self.values)}"

    def bad(self, col: pl.Expr) -> pl.Expr:
        return ~col.is_in(pl.Series(self.values, dtype=pl.String).implode())

    def reason(self, name: str, value: pl.Expr) -> pl.Expr:
        expected = ", ".join(self.values)
        return pl.format(f"{name}: invalid value {{}}, expected one of {expected}", value)


ValueRule = Range | OneOf
_LAT = Range(-90.0, 90.0)
_LON = Range(-180.0, 180.0)
_AZIMUTH = Range(0.0, 360.0, closed="left")


def value_rules(kind: str, limits: Limits) -> dict[str, ValueRule]:
    """Value rules of a table; they skip nulls and NaNs (see :func:`contract_rules`)."""
    pos, vel = Range(-limits.position_m, limits.position_m), Range(-limits.speed_mps, limits.speed_mps)
    state = {**dict.fromkeys(STATE[:3], pos), **dict.fromkeys(STATE[3:], vel)}
    variance = Range(0.0, limits.variance_max, closed="right")
    if kind == "radars":
        return {
            "lat_deg": _LAT,
            "lon_deg": _LON,
            "alt_m": Range(*limits.site_alt_m),
            "scan_period_s": Range(*limits.scan_period_s),
            "sigma_range_m": Range(*limits.sigma_range_m, closed="right"),
            "sigma_azimuth_deg": Range(*limits.sigma_angle_deg, closed="right"),
            "sigma_elevation_deg": Range(*limits.sigma_angle_deg, closed="right"),
            "max_range_m": Range(*limits.max_range_m),
            "scan_phase_s": Range(0.0, limits.scan_period_s[1]),
            "min_elevation_deg": _LAT,
            "pd": Range(0.0, 1.0),
            "clutter_rate": Range(*limits.clutter_rate),
            "timing": OneOf(("rotating", "synchronous")),
            "kind": OneOf(("radar", "mlat", "adsb")),
        }
    if kind == "reports":
        return {
            "range_m": Range(*limits.range_m, closed="right" if limits.range_m[0] == 0 else "both"),
            "azimuth_deg": _AZIMUTH,
            "elevation_deg": _LAT,
            "altitude_m": Range(*limits.altitude_m),
            "est_range_m": Range(-limits.position_m, limits.position_m),
            "est_range_rate_mps": vel,
            "est_azimuth_deg": _AZIMUTH,
            "est_elevation_deg": _LAT,
            "est_range_var_m2": variance,
            "est_azimuth_var_deg2": variance,
            "est_elevation_var_deg2": variance,
            **state,
            "res_range_m": Range(-limits.position_m, limits.position_m),
            "res_range_var_m2": variance,
            "plot_lat_deg": _LAT,
            "plot_lon_deg": _LON,
            "plot_x_m": pos,
            "plot_y_m": pos,
            "plot_height_m": Range(*limits.altitude_m),
            "plot_sigma_x_m": Range(0.0, limits.position_m, closed="right"),
            "plot_sigma_y_m": Range(0.0, limits.position_m, closed="right"),
            "plot_sigma_xy_m": pos,
            "adsb_nacp": Range(0, 11),
            "adsb_nic": Range(0, 11),
            "adsb_sil": Range(0, 3),
        }
    if kind == "truth":
        acc = Range(-limits.accel_mps2, limits.accel_mps2)
        return {**state, "ax_mps2": acc, "ay_mps2": acc, "az_mps2": acc,
                "lat_deg": _LAT, "lon_deg": _LON, "alt_m": Range(*limits.altitude_m)}
    return {}


#: the rules with the default :class:`Limits` (quoted by the documentation)
RULES: tuple[Rule, ...] = contract_rules()
