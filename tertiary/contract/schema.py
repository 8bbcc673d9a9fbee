"""Data contract of the tertiary-processing pipeline.

Every table that enters or leaves a pipeline stage is described by a
:class:`TableSchema` in :data:`TABLES`.  Units are SI (metres, seconds,
m/s; angles in degrees where the column name says ``_deg``) and times are
stored as ``pl.Datetime("us", "UTC")``.

:func:`validate` casts an input frame to its schema and checks it with
vectorised polars expressions.  Rows that break the contract either raise a
:class:`SchemaError` (``strict=True``) or are returned separately as
*rejects* (``strict=False``).  Each rejected row appears once; its
``reason`` is every row-level problem found, in schema-column order, joined
by ``"; "``.  Duplicates are looked for only among rows without other
problems, so a good row is never rejected as the copy of a bad one.

Reason strings (``<value>`` is the offending value as text, strings quoted)::

    "<col>: cannot cast <value> to <dtype>"
    "<col>: null"
    "<col>: NaN"
    "<col>: infinite value <value>"
    "<col>: negative value <value>"             # bound [0, inf]
    "<col>: non-positive value <value>"         # bound (0, inf]
    "<col>: outside [lo, hi], got <value>"      # any other bound
    "<col>: invalid value <value>, expected one of a, b"
    "radar_id: unknown radar <value>"
    "report_id: duplicate value <value>"
    "duplicate of report_id <id> (run, radar_id, local_track_id, time)"
    "duplicate of row_index <i> (<key columns>)"   # tables without report_id
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core.errors import DataError, OptionError

__all__ = [
    "TABLES",
    "FUSED_EXTRA",
    "TURN_RATE_COLUMN",
    "CLEARED_ALT_COLUMN",
    "Limits",
    "RULES",
    "as_frame",
    "Rule",
    "contract_rules",
    "rules_markdown",
    "SchemaError",
    "TableSchema",
    "UnsortedTimeWarning",
    "empty_frame",
    "rejects_table",
    "validate",
    "sort_tracks",
    "table_median_time",
    "INPUT_ROW",
]

# ---------------------------------------------------------------------------
# dtypes and table schemas
# ---------------------------------------------------------------------------

TIME = pl.Datetime("us", "UTC")
F64 = pl.Float64()
U32 = pl.UInt32()
U64 = pl.UInt64()
I64 = pl.Int64()
STR = pl.String()
BOOL = pl.Boolean()
COV = pl.Array(pl.Float64, 36)
STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")

ROW_INDEX = "row_index"
REASON = "reason"
_IDX = "__row_index"  # internal input position, exposed as ``row_index`` in rejects
#: the rows' positions in the whole input, on a part of it (a window, a group of aircraft)
INPUT_ROW = "__input_row"
_INTERNAL = ("__row_index", "__orig__", "__lost__", "__bad", "__reason", "__first_id", "__ctx_")


@dataclass(frozen=True)
class TableSchema:
    """Columns and dtypes of one table.

    ``key`` identifies a row (duplicates are rejected), ``nullable`` lists
    required columns that may hold nulls, ``finite`` demands finite values
    in required float columns and ``order`` is the sort key whose last
    column must increase within the groups given by the others.
    """

    name: str
    required: dict[str, pl.DataType]
    optional: dict[str, pl.DataType] = field(default_factory=dict)
    key: tuple[str, ...] = ()
    nullable: frozenset[str] = frozenset()
    finite: bool = False
    order: tuple[str, ...] = ()

    @property
    def columns(self) -> dict[str, pl.DataType]:
        """All columns, required first."""
        return {**self.required, **self.optional}


def _floats(*names: str) -> dict[str, pl.DataType]:
    return dict.fromkeys(names, F64)


#: the vertical channel of ``fused`` and ``tracks`` (same names as tertiary.stages.tracking.altitude.ALT_COLUMNS)
_ALT = _floats("alt_m", "alt_rate_mps", "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps")

_RADARS = TableSchema(
    name="radars",
    required={
        "radar_id": U32,
        "name": STR,
        **_floats(
            "lat_deg", "lon_deg", "alt_m", "scan_period_s", "sigma_range_m",
            "sigma_azimuth_deg", "sigma_elevation_deg", "max_range_m",
        ),
    },
    optional={
        **_floats(
            "scan_phase_s", "min_elevation_deg", "pd", "clutter_rate",
            "bias_range_m", "bias_azimuth_deg", "time_offset_s",
        ),
        "timing": STR,
    },
    key=("radar_id",),
    finite=True,
)

#: Mode S enhanced-surveillance parameters extracted with a report (BDS 5,0 ground speed, true
#: track angle (° clockwise from north), track-angle rate (°/s), roll angle (°, right wing down
#: positive); BDS 6,0 inertial vertical rate (m/s)); null without a Mode S reply or not extracted.
#: Inputs of the chapter 3 range channels (:mod:`tertiary.stages.tracking.filters.kinematic`).
EHS_REPORT_COLUMNS = ("ehs_gs_mps", "ehs_track_deg", "ehs_track_rate_dps", "ehs_roll_deg", "ehs_vrate_mps")
#: Mode S EHS BDS 4,0 MCP/FCU selected altitude (m, 16 ft quantum, the pressure-altitude reference
#: of ``altitude_m``): the level the crew selected, null without one. Carried reports → aligned →
#: fused (the target's latest) → tracks, where conflict prediction stops a climb or descent at it
#: (:mod:`safety.conflicts`).
SELECTED_ALT_COLUMN = "selected_alt_m"
#: Mode S EHS BDS 5,0 track-angle rate (°/s, clockwise positive), carried like
#: :data:`SELECTED_ALT_COLUMN` reports → aligned → fused (the target's newest) → tracks, where
#: conflict prediction follows a turn along an arc (:mod:`safety.conflicts`, "Turning aircraft")
TURN_RATE_COLUMN = "ehs_track_rate_dps"
#: the controller's cleared level (m, pressure-altitude reference of ``altitude_m``) from flight
#: data, correlated with each report by its Mode 3/A code (:mod:`tertiary.stages.flight_data`), null
#: without a unique flight plan. Carried like :data:`SELECTED_ALT_COLUMN`; conflict prediction
#: uses it where no selected level is downlinked (a Mode C-only aircraft, say)
CLEARED_ALT_COLUMN = "cleared_alt_m"

_REPORTS = TableSchema(
    name="reports",
    required={
        "radar_id": U32,
        "time": TIME,
        "local_track_id": U32,
        "range_m": F64,
        "azimuth_deg": F64,
    },
    optional={
        "report_id": U64,
        "run": U32,
        "elevation_deg": F64,
        "altitude_m": F64,
        "mode_s": STR,
        "mode_3a": STR,
        "callsign": STR,
        **_floats(
            "est_range_m", "est_range_rate_mps", "est_azimuth_deg",
            "est_elevation_deg", "est_range_var_m2", "est_azimuth_var_deg2",
            "est_elevation_var_deg2", *STATE,
        ),
        "est_cov": COV,
        "res_range_m": F64,
        "res_range_var_m2": F64,
        "truth_id": I64,
        **_floats(*EHS_REPORT_COLUMNS),
        SELECTED_ALT_COLUMN: F64,
    },
    key=("run", "radar_id", "local_track_id", "time"),
    finite=True,
    order=("run", "radar_id", "local_track_id", "time"),
)

_TRUTH = TableSchema(
    name="truth",
    required={"truth_id": I64, "time": TIME, **_floats(*STATE)},
    optional={
        **_floats("ax_mps2", "ay_mps2", "az_mps2"),
        "segment": STR,
        # alt_m: pressure altitude (= geodetic height, ISA without QNH deviation), alt_rate_mps its rate
        **_floats("lat_deg", "lon_deg", "alt_m", "alt_rate_mps"),
        "callsign": STR,
        "icao24": STR,
    },
    key=("truth_id", "time"),
    finite=True,
    order=("truth_id", "time"),
)

_ALIGNED = TableSchema(
    name="aligned",
    required={
        "report_id": U64,
        "run": U32,
        "radar_id": U32,
        "local_track_id": U32,
        "epoch": TIME,
        "time": TIME,
        **_floats(*STATE),
        "cov": COV,
        "res_range_m": F64,
        "res_range_var_m2": F64,
        "mode_s": STR,
        "truth_id": I64,
    },
    # the report's barometric altitude as replied (null without Mode C), at ``time``; its
    # selected altitude (BDS 4,0, null without)
    optional={"altitude_m": F64, SELECTED_ALT_COLUMN: F64, TURN_RATE_COLUMN: F64, CLEARED_ALT_COLUMN: F64},
    key=("run", "epoch", "report_id"),
    nullable=frozenset({"res_range_m", "res_range_var_m2", "mode_s", "truth_id"}),
)

_ASSOCIATIONS = TableSchema(
    name="associations",
    required={
        "run": U32,
        "epoch": TIME,
        "radar_id": U32,
        "local_track_id": U32,
        "report_id": U64,
        "target_id": U64,
        "cost": F64,
    },
    key=("run", "epoch", "report_id"),
)

_FUSED = TableSchema(
    name="fused",
    required={
        "run": U32,
        "epoch": TIME,
        "target_id": U64,
        "method": STR,
        **_floats(*STATE),
        "cov": COV,
        "weights": pl.List(pl.Float64),
        "radar_ids": pl.List(pl.UInt32),
        "n_sources": U32,
    },
    # the vertical channel (tertiary.stages.tracking.altitude.ALT_COLUMNS): Mode C height or geodetic fallback
    optional=_ALT,
    key=("run", "epoch", "method", "target_id"),
)

#: columns the fusion stage (tertiary.stages.fusion.fuse.fuse) adds to ``fused`` for the secondary tracker and
#: the target count: ``mode_s`` the Mode S address most of the target's reports carry (null
#: without one), ``n_fresh`` fresh measurements in the fused plot, ``age_s`` age of the newest
#: of them (s, epoch − report time; the measurement time; without a fresh plot the newest
#: report of any source), ``tentative`` (a target only ever made of one radar's unconfirmed
#: one-plot local tracks), and the plot-level fusion of the fresh measured plots at time
#: epoch − ``age_s``: ``meas_x_m``…``meas_z_m`` with its full 3×3 covariance ``meas_cov``
#: (row-major, null without a fresh plot); ``selected_alt_m`` the selected altitude of the
#: target's newest report carrying one (:data:`SELECTED_ALT_COLUMN`). Not in ``_FUSED.optional``
#: while the centralised stage (which emits every ``fused`` column) does not produce them.
FUSED_EXTRA: dict[str, pl.DataType] = {
    "n_fresh": U32, "age_s": F64, "tentative": BOOL, "mode_s": STR, SELECTED_ALT_COLUMN: F64,
    TURN_RATE_COLUMN: F64, CLEARED_ALT_COLUMN: F64,
    **_floats("meas_x_m", "meas_y_m", "meas_z_m"), "meas_cov": pl.Array(pl.Float64, 9),
}

_CLUSTERS = TableSchema(
    name="clusters",
    required={
        "run": U32,
        "epoch": TIME,
        "method": STR,
        "cluster_id": U64,
        "lead_target_id": U64,
        "members": pl.List(pl.UInt64),
        "count": U32,
    },
    key=("run", "epoch", "method", "cluster_id"),
)

_TRACKS = TableSchema(
    name="tracks",
    required={
        "run": U32,
        "epoch": TIME,
        "track_id": U64,
        "filter": STR,
        "method": STR,
        **_floats(*STATE),
        "cov_diag": pl.Array(pl.Float64, 6),
        "innovation": pl.List(pl.Float64),
        "nis": F64,
        "model_probs": pl.List(pl.Float64),
    },
    # cov: the full 6×6 position–velocity covariance, row-major (x y z vx vy vz)
    # mode_s: the Mode S address of the target the track was last updated with (identity);
    # selected_alt_m: that target's selected altitude (latest known, carried while coasting)
    # ehs_track_rate_dps: that target's downlinked track-angle rate (latest known, likewise)
    # cleared_alt_m: that target's cleared level from flight data (latest known, likewise)
    optional={**_ALT, "cov": COV, "mode_s": STR, SELECTED_ALT_COLUMN: F64, TURN_RATE_COLUMN: F64,
              CLEARED_ALT_COLUMN: F64},
    key=("run", "epoch", "filter", "method", "track_id"),
    nullable=frozenset({"innovation", "nis", "model_probs"}),
)

_CONFLICTS = TableSchema(
    name="conflicts",
    required={
        "run": U32,
        "epoch": TIME,
        "method": STR,
        "id_a": U64,
        "id_b": U64,
        **_floats(
            "r_min_m", "t_min_s", "dz_m", "dz_min_m", "closure_mps",
            "r_thr_m", "t_thr_s", "z_thr_m",
        ),
        "alert": BOOL,
        "severity": F64,
    },
    # t_in_s: start of the predicted conflict interval (NaN without alert); near: within the near
    # margins of both thresholds at one predicted time (what the slim table keeps besides alerts)
    # raw_alert: the conflict condition before alert confirmation (alert = confirmed, m of n epochs)
    optional={"t_in_s": F64, "near": BOOL, "raw_alert": BOOL},
    key=("run", "epoch", "method", "id_a", "id_b"),
)

_ALERTS = TableSchema(
    name="alerts",
    required={
        "run": U32, "method": STR, "id_a": U64, "id_b": U64, "truth_a": pl.Int64(), "truth_b": pl.Int64(),
        "t_start": TIME, "t_end": TIME, "duration_s": F64, "alert_epochs": U32, "flicker": U32,
        "r_min_pred_m": F64, "dz_min_pred_m": F64, "t_min_first_s": F64, "los_start": TIME, "warning_s": F64,
        "classification": STR,
    },
    nullable=frozenset({"truth_a", "truth_b", "r_min_pred_m", "dz_min_pred_m", "t_min_first_s", "los_start",
                        "warning_s"}),
    key=("run", "method", "id_a", "id_b", "t_start"),
)

_REJECTS = TableSchema(
    name="rejects",
    required={
        "input_table": STR,
        "stage": STR,
        "report_id": U64,
        ROW_INDEX: U64,
        REASON: STR,
        "detail": STR,
    },
    nullable=frozenset({"report_id"}),
)

_METRICS = TableSchema(
    name="metrics",
    required={
        "stage": STR,
        "method": STR,
        "metric": STR,
        "segment": STR,
        "value": F64,
        "n_runs": U32,
    },
    key=("stage", "method", "metric", "segment"),
    nullable=frozenset({"segment"}),
)

_RUN = TableSchema(name="run", required={"key": STR, "value": STR}, key=("key",))

TABLES: dict[str, TableSchema] = {
    s.name: s
    for s in (
        _RADARS, _REPORTS, _TRUTH, _ALIGNED, _ASSOCIATIONS, _FUSED,
        _CLUSTERS, _TRACKS, _CONFLICTS, _ALERTS, _REJECTS, _METRICS, _RUN,
    )
}

# ---------------------------------------------------------------------------
# errors, warnings and limits
# ---------------------------------------------------------------------------


class SchemaError(DataError):
    """A frame breaks its table contract (a :class:`tertiary.core.errors.DataError`).

    ``rows`` holds the input row indices of every offending row (empty for
    table-level problems such as a missing column).
    """

    def __init__(
        self,
        message: str,
        *,
        table: str,
        column: str | None = None,
        problem: str = "",
        rows: Iterable[int] = (),
    ) -> None:
        super().__init__(message)
        self.table = table
        self.column = column
        self.problem = problem
        self.rows = list(rows)


class UnsortedTimeWarning(UserWarning):
    """Times were not increasing within a track; the frame was sorted."""


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
        Rule("radars", "alt_m", f"[{_num(limits.site_alt_m[0])}, {_num(limits.site_alt_m[1])}] m",
             "a ground site (Dead Sea to the highest radar sites)"),
        Rule("radars", "scan_period_s", f"[{_num(limits.scan_period_s[0])}, {_num(limits.scan_period_s[1])}] s",
             "rotating surveillance radars scan in 1-12 s; the epoch grid is sized by the fastest scan"),
        Rule("radars", "sigma_range_m", f"(0, {_num(limits.sigma_range_m[1])}] m",
             "a-priori weights divide by sigma^2; a zero or huge sigma is not a sensor"),
        Rule("radars", "sigma_azimuth_deg, sigma_elevation_deg",
             f"(0, {_num(limits.sigma_angle_deg[1])}] deg", "as for sigma_range_m"),
        Rule("radars", "max_range_m", f"[{_num(limits.max_range_m[0])}, {_num(limits.max_range_m[1])}] m",
             "bounds every report's range (instrumented range of real radars < 500 km)"),
        Rule("radars", "pd, clutter_rate, scan_phase_s, min_elevation_deg",
             "[0, 1], [0, 1e4] per scan, [0, max scan period] s, [-90, 90] deg", "their physical domains"),
        Rule("radars", "radar_id", "unique", "reports refer to radars by id"),
        Rule("radars", "the table", "at least one valid radar",
             "every report needs its radar; with none, all reports are rejected", "all reports to rejects"),
        Rule("reports", "radar_id", "a valid radar of the radars table",
             "reports of an unknown or rejected radar cannot be placed in space"),
        Rule("reports", "range_m", f"(0, max_range_m x {limits.range_margin:g}] of its radar (without a radars "
             f"table: (0, {_num(limits.max_range_m[1] * limits.range_margin)}] m)",
             "beyond the radar's instrumented range the report is a decoding error"),
        Rule("reports", "azimuth_deg, est_azimuth_deg", "[0, 360)", "angle domain (clockwise from north)"),
        Rule("reports", "elevation_deg, est_elevation_deg", "[-90, 90]", "angle domain"),
        Rule("reports, truth", "altitude_m / alt_m", f"[{_num(limits.altitude_m[0])}, {_num(limits.altitude_m[1])}] m",
             "civil air traffic"),
        Rule("reports, truth", "time", f"[{lo_y}-01-01, {hi_y}-01-01) UTC",
             "a time outside is a unit or epoch error (0, 1970, 9999)"),
        Rule("reports, truth", "time", f"within +-{span_h / 2:g} h of the table's median time",
             "grids in time (epochs, alert ticks) are sized by the span; a stray date would allocate "
             "terabytes"),
        Rule("truth", "time", f"within the span of the valid reports +- {_num(limits.truth_pad_s)} s",
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
    )


#: the rules with the default :class:`Limits` (quoted by the documentation)
RULES: tuple[Rule, ...] = ()  # filled below, once the helpers exist


def rules_markdown(limits: Limits = Limits()) -> str:
    """:func:`contract_rules` as a Markdown table (table, columns, rule, reason, action)."""
    lines = ["| table | columns | rule | reason | if broken |", "|---|---|---|---|---|"]
    lines += [f"| {r.table} | {r.columns} | {r.rule} | {r.reason} | {r.action} |" for r in contract_rules(limits)]
    return "\n".join(lines)


# ---------------------------------------------------------------------------
# value rules
# ---------------------------------------------------------------------------


def _num(x: float) -> str:
    if math.isfinite(x) and float(x).is_integer() and abs(x) < 1e7:
        return str(int(x))
    return f"{x:g}"


@dataclass(frozen=True)
class _Range:
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
        return f"outside {left}{_num(self.lo)}, {_num(self.hi)}{right}"

    def bad(self, col: pl.Expr) -> pl.Expr:
        return ~col.is_between(self.lo, self.hi, closed=self.closed) & col.is_not_nan()

    def reason(self, name: str, value: pl.Expr) -> pl.Expr:
        sep = " " if self.problem.endswith("value") else ", got "
        return pl.format(f"{name}: {self.problem}{sep}{{}}", value)


@dataclass(frozen=True)
class _OneOf:
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


_Rule = _Range | _OneOf
_NONNEG = _Range(0.0, math.inf)
_POSITIVE = _Range(0.0, math.inf, closed="right")
_LAT = _Range(-90.0, 90.0)
_LON = _Range(-180.0, 180.0)
_AZIMUTH = _Range(0.0, 360.0, closed="left")


def _rules(kind: str, limits: Limits) -> dict[str, _Rule]:
    """Value rules of a table; they skip nulls and NaNs (see :func:`contract_rules`)."""
    pos, vel = _Range(-limits.position_m, limits.position_m), _Range(-limits.speed_mps, limits.speed_mps)
    state = {**dict.fromkeys(STATE[:3], pos), **dict.fromkeys(STATE[3:], vel)}
    variance = _Range(0.0, limits.variance_max, closed="right")
    if kind == "radars":
        return {
            "lat_deg": _LAT,
            "lon_deg": _LON,
            "alt_m": _Range(*limits.site_alt_m),
            "scan_period_s": _Range(*limits.scan_period_s),
            "sigma_range_m": _Range(*limits.sigma_range_m, closed="right"),
            "sigma_azimuth_deg": _Range(*limits.sigma_angle_deg, closed="right"),
            "sigma_elevation_deg": _Range(*limits.sigma_angle_deg, closed="right"),
            "max_range_m": _Range(*limits.max_range_m),
            "scan_phase_s": _Range(0.0, limits.scan_period_s[1]),
            "min_elevation_deg": _LAT,
            "pd": _Range(0.0, 1.0),
            "clutter_rate": _Range(*limits.clutter_rate),
            "timing": _OneOf(("rotating", "synchronous")),
        }
    if kind == "reports":
        return {
            "range_m": _Range(*limits.range_m, closed="right" if limits.range_m[0] == 0 else "both"),
            "azimuth_deg": _AZIMUTH,
            "elevation_deg": _LAT,
            "altitude_m": _Range(*limits.altitude_m),
            "est_range_m": _Range(-limits.position_m, limits.position_m),
            "est_range_rate_mps": vel,
            "est_azimuth_deg": _AZIMUTH,
            "est_elevation_deg": _LAT,
            "est_range_var_m2": variance,
            "est_azimuth_var_deg2": variance,
            "est_elevation_var_deg2": variance,
            **state,
            "res_range_m": _Range(-limits.position_m, limits.position_m),
            "res_range_var_m2": variance,
        }
    if kind == "truth":
        acc = _Range(-limits.accel_mps2, limits.accel_mps2)
        return {**state, "ax_mps2": acc, "ay_mps2": acc, "az_mps2": acc,
                "lat_deg": _LAT, "lon_deg": _LON, "alt_m": _Range(*limits.altitude_m)}
    return {}


# ---------------------------------------------------------------------------
# casting
# ---------------------------------------------------------------------------

_ISO_FORMATS = (
    "%Y-%m-%dT%H:%M:%S%.f%#z",
    "%Y-%m-%dT%H:%M:%S%.f",
    "%Y-%m-%dT%H:%M%#z",
    "%Y-%m-%dT%H:%M",
    "%Y-%m-%d",
)


def _label(dtype: pl.DataType) -> str:
    if isinstance(dtype, pl.Datetime):
        tz = f", {dtype.time_zone}" if dtype.time_zone else ""
        return f"Datetime[{dtype.time_unit}{tz}]"
    if isinstance(dtype, pl.Array):
        return f"Array({_label(dtype.inner)}, {dtype.size})"
    return str(dtype)


def _parse_iso(s: pl.Series) -> pl.Series:
    """Parse ISO-8601 strings to UTC datetimes; naive strings are UTC."""
    text = s.str.strip_chars().str.replace(" ", "T", literal=True)
    parsed = [
        text.str.to_datetime(fmt, time_unit="us", time_zone="UTC", strict=False)
        for fmt in _ISO_FORMATS
    ]
    return pl.select(pl.coalesce(parsed)).to_series().alias(s.name)


def _to_time(s: pl.Series, table: str) -> pl.Series:
    if isinstance(s.dtype, pl.Datetime):
        if s.dtype.time_zone is None:
            s = s.dt.replace_time_zone("UTC")
        return s.dt.convert_time_zone("UTC").dt.cast_time_unit("us")
    if s.dtype == pl.String:
        return _parse_iso(s)
    if s.dtype == pl.Null:
        return s.cast(TIME)
    hint = (
        f" (hint: epoch seconds can be converted with "
        f"pl.from_epoch('{s.name}', time_unit='s'))"
        if s.dtype.is_numeric()
        else ""
    )
    raise SchemaError(
        f"{table}: column '{s.name}' has dtype {s.dtype}; expected Datetime "
        f"or ISO-8601 strings{hint}",
        table=table,
        column=s.name,
        problem="uncastable dtype",
    )


def _to_array(s: pl.Series, dtype: pl.Array) -> pl.Series:
    """Cast list/array values; rows of the wrong width or with null items become null."""
    if s.dtype == pl.Null:
        return s.cast(dtype)
    items = s.cast(pl.List(dtype.inner), strict=False)
    wrong = items.list.drop_nulls().list.len() != dtype.size
    return pl.select(pl.when(wrong).then(None).otherwise(items)).to_series().cast(dtype)


def _castable(src: pl.DataType, dtype: pl.DataType) -> bool:
    """Source dtypes accepted for a target dtype (polars would cast more, silently: a Boolean
    to 0/1, a Date to days, a Struct to a Struct of numbers)."""
    if src == pl.Null or src == dtype:
        return True
    if dtype.is_numeric():
        return (src.is_numeric() and src != pl.Boolean) or src == pl.String
    if dtype == pl.String:
        return src.is_numeric() or isinstance(src, (pl.Categorical, pl.Enum))
    if dtype == pl.Boolean:
        return src == pl.String
    if isinstance(dtype, (pl.List, pl.Array)):
        return isinstance(src, (pl.List, pl.Array)) and _castable(src.inner, dtype.inner)
    return True


def _cast_values(s: pl.Series, dtype: pl.DataType, table: str) -> pl.Series:
    if isinstance(dtype, pl.Datetime):
        return _to_time(s, table)
    if not _castable(s.dtype, dtype):
        raise pl.exceptions.InvalidOperationError(f"{s.dtype} to {dtype}")
    if isinstance(dtype, pl.Array):
        return _to_array(s, dtype)
    if s.dtype == pl.String and dtype != pl.String:
        s = s.str.strip_chars()
    return s.cast(dtype, strict=False)


def _cast(s: pl.Series, dtype: pl.DataType, table: str) -> tuple[pl.Series, pl.Series]:
    """Cast ``s`` to ``dtype``; also return a mask of values the cast lost."""
    if s.dtype == dtype:
        return s, pl.repeat(False, len(s), eager=True)
    try:
        out = _cast_values(s, dtype, table)
    except pl.exceptions.PolarsError as exc:
        raise SchemaError(
            f"{table}: column '{s.name}' has dtype {s.dtype} which cannot be "
            f"cast to {_label(dtype)}",
            table=table,
            column=s.name,
            problem="uncastable dtype",
        ) from exc
    lost = s.is_not_null() & out.is_null()
    if dtype.is_integer() and s.dtype.is_float():
        lost = lost | (s.is_not_null() & (s != s.floor()).fill_null(False))
    return out.alias(s.name), lost.fill_null(False)


# ---------------------------------------------------------------------------
# checks
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Check:
    """A row-level check: ``bad`` flags offending rows, ``reason`` explains."""

    columns: tuple[str, ...]
    problem: str
    bad: pl.Expr
    reason: pl.Expr
    context: dict[str, pl.Expr] = field(default_factory=dict)  # whole-frame columns for ``reason``


def _orig(name: str) -> str:
    return f"__orig__{name}"


def _lost(name: str) -> str:
    return f"__lost__{name}"


def _as_text(col: pl.Expr, dtype: pl.DataType) -> pl.Expr:
    """Values rendered as text for reasons (strings quoted)."""
    if dtype == pl.String:
        return pl.format("'{}'", col)
    if isinstance(dtype, (pl.List, pl.Array)) and not dtype.inner.is_nested():
        return pl.format("[{}]", col.cast(pl.List(pl.String)).list.join(", "))
    if dtype.is_nested() or dtype == pl.Object:
        return pl.lit(f"<{dtype}>")
    return col.cast(pl.String)


def _column_checks(
    name: str, schema: TableSchema, orig: pl.DataType, rule: _Rule | None
) -> list[_Check]:
    """Cast, null, finiteness and value checks of one column."""
    dtype = schema.columns[name]
    col, value = pl.col(name), _as_text(pl.col(_orig(name)), orig)
    checks = [
        _Check(
            (name,),
            f"cannot cast to {_label(dtype)}",
            pl.col(_lost(name)),
            pl.format(f"{name}: cannot cast {{}} to {_label(dtype)}", value),
        )
    ]
    required = name in schema.required
    identifying = required or name in schema.key or name == "report_id"
    if identifying and name not in schema.nullable:
        null = col.is_null() & ~pl.col(_lost(name))
        checks.append(_Check((name,), "null", null, pl.lit(f"{name}: null")))
    finite = required and schema.finite and dtype.is_float()
    if finite:
        inf_reason = pl.format(f"{name}: infinite value {{}}", col.cast(pl.String))
        checks.append(_Check((name,), "NaN", col.is_nan(), pl.lit(f"{name}: NaN")))
        checks.append(_Check((name,), "infinite value", col.is_infinite(), inf_reason))
    if rule is not None:
        bad = rule.bad(col) & col.is_finite() if finite else rule.bad(col)
        checks.append(_Check((name,), rule.problem, bad, rule.reason(name, _as_text(col, dtype))))
    return checks


def _radar_check(radars: pl.DataFrame, table: str, rejected: Iterable[int] = ()) -> _Check:
    """Reports must name a valid radar; a radar rejected itself takes its reports along."""
    if "radar_id" not in radars.columns:
        raise SchemaError(
            f"{table}: the radars frame has no 'radar_id' column",
            table="radars",
            column="radar_id",
            problem="missing column",
        )
    known = radars["radar_id"].cast(pl.UInt32, strict=False).drop_nulls()
    gone = pl.Series(list(rejected), dtype=pl.Int64).cast(pl.UInt32, strict=False).drop_nulls()
    col = pl.col("radar_id")
    return _Check(
        ("radar_id",),
        "unknown radar",
        ~col.is_in(known.implode()),
        pl.when(col.is_in(gone.implode()))
        .then(pl.format("radar_id: radar {} was rejected (see the radars rejects)", col))
        .otherwise(pl.format("radar_id: unknown radar {}", col)),
    )


def _range_check(work: pl.DataFrame, radars: pl.DataFrame, limits: Limits) -> tuple[pl.DataFrame, _Check]:
    """range_m <= max_range_m x margin of the report's radar (joined as ``__ctx_rmax``)."""
    cap = radars.select(
        pl.col("radar_id").cast(U32, strict=False),
        (pl.col("max_range_m").cast(F64, strict=False) * limits.range_margin).alias("__ctx_rmax"),
    ).drop_nulls("radar_id").unique("radar_id", keep="first")
    work = work.join(cap, on="radar_id", how="left", maintain_order="left")
    rng, rmax = pl.col("range_m"), pl.col("__ctx_rmax")
    return work, _Check(
        ("range_m",),
        f"beyond max_range_m x {limits.range_margin:g} of its radar",
        (rng > rmax) & rng.is_finite(),
        pl.format(f"range_m: beyond max_range_m x {limits.range_margin:g} = {{}} of radar {{}}, got {{}}",
                  rmax.cast(pl.String), pl.col("radar_id"), rng.cast(pl.String)),
    )


def table_median_time(frame: pl.DataFrame, limits: Limits = Limits()) -> datetime | None:
    """The median of ``frame``'s times in the configured years: what a time is judged near (a
    table validated in parts is given its whole median)."""
    lo, hi = (datetime(y, 1, 1, tzinfo=timezone.utc) for y in limits.years)
    return frame.filter(pl.col("time").is_between(lo, hi, closed="left").fill_null(False))["time"].median()


def _time_checks(
    work: pl.DataFrame, limits: Limits, window: tuple[datetime, datetime, str] | None,
    median: datetime | None = None,
) -> list[_Check]:
    """Times in the configured years, near the table's median (``median``: the whole table's,
    when ``work`` is one window of it), and inside ``window``."""
    lo, hi = (datetime(y, 1, 1, tzinfo=timezone.utc) for y in limits.years)
    t = pl.col("time")
    in_years = t.is_between(lo, hi, closed="left")
    text = t.dt.strftime("%Y-%m-%dT%H:%M:%S%.fZ")
    checks = [_Check(("time",), f"outside [{lo:%Y-%m-%d}, {hi:%Y-%m-%d})", ~in_years,
                     pl.format(f"time: outside [{lo:%Y-%m-%d}, {hi:%Y-%m-%d}) UTC, got {{}}", text))]
    med = median if median is not None else table_median_time(work, limits)
    if med is not None:
        half = timedelta(seconds=limits.max_span_s / 2.0)
        far = in_years & ((t < pl.lit(med - half)) | (t > pl.lit(med + half)))
        what = f"more than {limits.max_span_s / 7200.0:g} h from the table's median time {med:%Y-%m-%dT%H:%M:%S}Z"
        checks.append(_Check(("time",), what, far, pl.format(f"time: {what}, got {{}}", text)))
    if window is not None:
        a, b, label = window
        outside = in_years & ~t.is_between(pl.lit(a), pl.lit(b))
        what = f"outside {label} [{a:%Y-%m-%dT%H:%M:%S}Z, {b:%Y-%m-%dT%H:%M:%S}Z]"
        checks.append(_Check(("time",), what, outside, pl.format(f"time: {what}, got {{}}", text)))
    return checks


_COV_PROBLEMS = {
    1: "est_cov: infinite value",
    2: "est_cov: variance larger than {big:g}",
    3: "est_cov: not symmetric (|P - P^T| > {tol:g} x largest diagonal)",
    4: "est_cov: not positive semi-definite (eigenvalue < -{tol:g} x largest diagonal)",
}


def _cov_codes(cov: pl.Series, limits: Limits) -> NDArray[np.int8]:
    """Per row 0 (a covariance, or NaN/null: left to the align stage) or the _COV_PROBLEMS code."""
    n = len(cov)
    code = np.zeros(n, np.int8)
    if n == 0:
        return code
    a = cov.to_numpy().reshape(n, 6, 6)
    with np.errstate(all="ignore"):
        nan = np.isnan(a).any(axis=(1, 2))
        inf = np.isinf(a).any(axis=(1, 2)) & ~nan
        diag = np.diagonal(a, axis1=1, axis2=2)
        scale = np.abs(diag).max(axis=1)
        big = ~nan & ~inf & (scale > limits.variance_max)
        tol = limits.cov_rel_tol * scale
        asym = ~nan & ~inf & ~big & (np.abs(a - a.transpose(0, 2, 1)).max(axis=(1, 2)) > tol)
        test = np.flatnonzero(~nan & ~inf & ~big & ~asym)
        not_psd = np.zeros(n, bool)
        for lo in range(0, len(test), 262_144):  # bounded temporaries
            rows = test[lo:lo + 262_144]
            sym = 0.5 * (a[rows] + a[rows].transpose(0, 2, 1))
            if limits.cov_rel_tol >= _PSD_FAST_MIN_TOL:
                # the eigenvalues only of the matrices a factorisation cannot clear at once
                sure = _cholesky_ok(sym, 0.5 * tol[rows])
                rows, sym = rows[~sure], sym[~sure]
            not_psd[rows] = np.linalg.eigvalsh(sym)[:, 0] < -tol[rows]
    code[not_psd], code[asym], code[big], code[inf] = 4, 3, 2, 1
    return code


#: the PSD test clears matrices by factorisation when its margin (half the tolerance) is far
#: above the factorisation's round-off (~1e-13 of the largest diagonal, 6×6)
_PSD_FAST_MIN_TOL = 1e-10


def _cholesky_ok(sym: NDArray[np.float64], shift: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Per matrix: ``sym + shift·I`` has a Cholesky factor (every pivot > 0), over the batch at
    once (column by column, numpy over the matrices; ``np.linalg.cholesky`` stops the whole
    batch at the first failure). A factor means λmin(sym) ≥ −shift − ~1e-13·max|diag| (the
    factorisation's backward error), so with ``shift`` half the tolerance such a matrix is
    surely not below −tolerance and its eigenvalues need not be computed (they took 9.5 % of
    a national hour's windows). False only means "not cleared": the caller computes them."""
    m, k = sym.shape[0], sym.shape[1]
    # the lower triangle as rows of the batch: every step below is one numpy
    # operation over all the matrices (a 6×6 factor is ~100 of them)
    flat = sym.reshape(m, k * k).T
    low: dict[tuple[int, int], NDArray[np.float64]] = {}
    ok = np.ones(m, bool)
    for j in range(k):
        piv = flat[j * k + j] + shift
        for c in range(j):
            piv = piv - low[j, c] * low[j, c]
        ok &= piv > 0
        d = np.sqrt(np.where(piv > 0, piv, 1.0))
        for i in range(j + 1, k):
            v = flat[i * k + j]
            for c in range(j):
                v = v - low[i, c] * low[j, c]
            low[i, j] = v / d
        low[j, j] = d
    return ok


def _cov_check(work: pl.DataFrame, limits: Limits) -> tuple[pl.DataFrame, _Check]:
    work = work.with_columns(pl.Series("__ctx_cov", _cov_codes(work["est_cov"], limits)))
    texts = {k: v.format(big=limits.variance_max, tol=limits.cov_rel_tol) for k, v in _COV_PROBLEMS.items()}
    code = pl.col("__ctx_cov")
    return work, _Check(("est_cov",), "not a covariance matrix", code > 0,
                        code.replace_strict(texts, default=None, return_dtype=pl.String))


def _context_checks(
    work: pl.DataFrame,
    schema: TableSchema,
    radars: pl.DataFrame | None,
    limits: Limits,
    time_window: tuple[datetime, datetime, str] | None,
    median: datetime | None = None,
) -> tuple[pl.DataFrame, list[_Check]]:
    """Checks that need more than one value: times against the table, est_cov as a matrix,
    range against the radar's maximum range."""
    checks: list[_Check] = []
    if "time" in work.columns and schema.name in ("reports", "truth"):
        checks += _time_checks(work, limits, time_window, median)
    if schema.name == "reports" and "est_cov" in work.columns:
        work, check = _cov_check(work, limits)
        checks.append(check)
    if (schema.name == "reports" and radars is not None and "range_m" in work.columns
            and {"radar_id", "max_range_m"} <= set(radars.columns)):
        work, check = _range_check(work, radars, limits)
        checks.append(check)
    elif schema.name == "reports" and "range_m" in work.columns:
        # no radars to compare with: no radar sees beyond the largest plausible max_range_m x margin
        cap = limits.max_range_m[1] * limits.range_margin
        rng = pl.col("range_m")
        checks.append(_Check(("range_m",), f"beyond any radar's range ({_num(cap)} m)", (rng > cap) & rng.is_finite(),
                             pl.format(f"range_m: beyond any radar's range ({_num(cap)} m), got {{}}",
                                       rng.cast(pl.String))))
    return work, checks


def _is_repeat(key: list[str]) -> pl.Expr:
    """True for every row whose key already occurred earlier in the frame."""
    return ~(pl.col(key[0]) if len(key) == 1 else pl.struct(key)).is_first_distinct()


def _duplicate_checks(schema: TableSchema, columns: list[str], own_ids: bool) -> list[_Check]:
    """Key duplicates (and repeated user-given report_ids); the first row is kept."""
    checks = []
    if own_ids:
        checks.append(
            _Check(
                ("report_id",),
                "duplicate value",
                _is_repeat(["report_id"]),
                pl.format("report_id: duplicate value {}", pl.col("report_id")),
            )
        )
    if schema.key and all(c in columns for c in schema.key):
        key = list(schema.key)
        # a part of a table names the first row by its position in the whole input
        ident, ident_col = (("report_id",) * 2 if "report_id" in columns
                            else (ROW_INDEX, INPUT_ROW if INPUT_ROW in columns else _IDX))
        checks.append(
            _Check(
                schema.key,
                f"duplicate ({', '.join(key)})",
                _is_repeat(key),
                pl.format(f"duplicate of {ident} {{}} ({', '.join(key)})", pl.col("__first_id")),
                {"__first_id": pl.col(ident_col).first().over(key)},
            )
        )
    return checks


def _split(work: pl.DataFrame, checks: list[_Check]) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Split into rows passing all checks and flagged rows.

    Flagged rows carry the ``__bad{i}`` masks and the joined ``__reason``;
    reasons are only formatted for flagged rows.
    """
    names = [f"__bad{i}" for i in range(len(checks))]
    work = work.with_columns(c.bad.fill_null(False).alias(n) for c, n in zip(checks, names))
    counts = work.select(pl.col(names).sum()).row(0) if checks else ()
    hit = [(c, n) for c, n, count in zip(checks, names, counts) if count]
    if not hit:
        no_rows = work.clear().with_columns(pl.lit(None, pl.String).alias("__reason"))
        return work.drop(names), no_rows
    context = {k: e for c, _ in hit for k, e in c.context.items()}
    work = work.with_columns(**context)
    flagged = pl.any_horizontal(names)
    good = work.filter(~flagged).drop(*names, *context)
    reasons = [pl.when(pl.col(n)).then(c.reason) for c, n in hit]
    joined = pl.concat_str(reasons, separator="; ", ignore_nulls=True)
    return good, work.filter(flagged).with_columns(joined.alias("__reason"))


def _short(value: object, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _raise_first(bad: pl.DataFrame, checks: list[_Check], table: str) -> None:
    """Raise a SchemaError for the first check that flags any of the ``bad`` rows."""
    if bad.is_empty():
        return
    counts = bad.select(pl.col(f"__bad{i}").sum() for i in range(len(checks))).row(0)
    for i, (check, n) in enumerate(zip(checks, counts)):
        if not n:
            continue
        hits = bad.filter(pl.col(f"__bad{i}"))
        cols = [_orig(c) if _orig(c) in bad.columns else c for c in check.columns]
        examples = ", ".join(
            f"row {r}: " + ", ".join(f"{c}={_short(v)}" for c, v in zip(check.columns, vals))
            for r, *vals in hits.head(5).select(_IDX, *cols).iter_rows()
        )
        column, total, rows = ", ".join(check.columns), bad.height, hits[_IDX].to_list()
        raise SchemaError(
            f"{table}: column '{column}': {check.problem} in {n} row(s); "
            f"e.g. {examples} ({total} row(s) fail checks in all; "
            f"validate with strict=False to get the rejects)",
            table=table,
            column=column,
            problem=check.problem,
            rows=rows,
        )


# ---------------------------------------------------------------------------
# validate
# ---------------------------------------------------------------------------


def _schema(kind: str) -> TableSchema:
    try:
        return TABLES[kind]
    except KeyError:
        known = ", ".join(TABLES)
        raise OptionError(f"unknown table kind {kind!r}; expected one of {known}") from None


def _require(frame: pl.DataFrame, schema: TableSchema) -> None:
    missing = [c for c in schema.required if c not in frame.columns]
    if not missing:
        return
    names = ", ".join(f"'{c}'" for c in missing)
    verb = "column {} is" if len(missing) == 1 else "columns {} are"
    raise SchemaError(
        f"{schema.name}: required {verb.format(names)} missing "
        f"(have: {', '.join(frame.columns) or 'no columns'})",
        table=schema.name,
        column=missing[0],
        problem="missing column",
    )


def _prepare(frame: pl.DataFrame, schema: TableSchema) -> pl.DataFrame:
    """Add the row index and, for reports, a positional ``report_id`` and ``run`` = 0."""
    ids = [pl.int_range(pl.len(), dtype=pl.UInt64).alias(_IDX)]
    if schema.name == "reports" and "report_id" not in frame.columns:
        ids.append(pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"))
    if schema.name == "reports" and "run" not in frame.columns:
        ids.append(pl.lit(0, dtype=pl.UInt32).alias("run"))
    return frame.with_columns(ids)


def _cast_frame(prepared: pl.DataFrame, schema: TableSchema) -> pl.DataFrame:
    """Cast schema columns, keeping originals and loss masks in ``__`` columns."""
    work = prepared
    for name, dtype in schema.columns.items():
        if name not in prepared.columns:
            continue
        cast, lost = _cast(prepared[name], dtype, schema.name)
        work = work.with_columns(
            prepared[name].alias(_orig(name)), lost.alias(_lost(name)), cast
        )
    if schema.name == "reports":  # a null run is the default run 0
        default = pl.when(pl.col(_orig("run")).is_null()).then(0).otherwise(pl.col("run"))
        work = work.with_columns(default.cast(pl.UInt32).alias("run"))
    return work


def _clean_columns(schema: TableSchema, columns: list[str]) -> list[str]:
    known = [c for c in schema.columns if c in columns]
    extra = [c for c in columns if c not in schema.columns and not c.startswith(_INTERNAL)]
    return known + extra


def _rejects(bad: pl.DataFrame, prepared: pl.DataFrame) -> pl.DataFrame:
    """Flagged rows with their original values, ``row_index``, ``report_id`` and ``reason``."""
    lead = [pl.col(_IDX).alias(ROW_INDEX)]
    if "report_id" in prepared.columns:
        lead.append(pl.col("report_id"))
    lead.append(pl.col("__reason").alias(REASON))
    skip = {_IDX, ROW_INDEX, "report_id", REASON}
    body = [
        pl.col(_orig(c)).alias(c) if _orig(c) in bad.columns else pl.col(c)
        for c in prepared.columns
        if c not in skip
    ]
    return bad.select(*lead, *body)


def sort_tracks(clean: pl.DataFrame, kind: str) -> pl.DataFrame:
    """``clean`` sorted by the ``kind`` schema's order if times decrease within any group (with
    an :class:`UnsortedTimeWarning`), as :func:`validate` leaves it: for a table validated in parts."""
    return _sort_tracks(clean, _schema(kind))


def table_order(kind: str) -> tuple[str, ...]:
    """The ``kind`` schema's row order (group columns, then time): what :func:`sort_tracks`
    sorts by."""
    return tuple(_schema(kind).order)


def unsorted_groups(clean: pl.DataFrame, kind: str) -> tuple[int, int]:
    """(groups whose times decrease in row order, groups) of ``clean`` by the ``kind`` schema's
    order: what :func:`sort_tracks` counts (a table validated in parts adds its parts' counts)."""
    return _unsorted(clean, _schema(kind))


def unsorted_message(kind: str, n_bad: int, n_groups: int) -> str:
    """The :class:`UnsortedTimeWarning` text of :func:`sort_tracks` for these counts."""
    return _unsorted_message(_schema(kind), n_bad, n_groups)


def _unsorted(clean: pl.DataFrame, schema: TableSchema) -> tuple[int, int]:
    *group, time = schema.order
    decreasing = pl.col(time).diff() < pl.lit(timedelta(0))
    per_group = clean.group_by(group).agg(decreasing.any().alias("__unsorted"))
    return int(per_group["__unsorted"].sum()), per_group.height


def _unsorted_message(schema: TableSchema, n_bad: int, n_groups: int) -> str:
    *group, time = schema.order
    what = "tracks" if schema.name == "reports" else f"({', '.join(group)}) groups"
    return (f"{schema.name}: {time} out of order in {n_bad} of {n_groups} {what}; "
            f"sorted by ({', '.join(schema.order)})")


def _sort_tracks(clean: pl.DataFrame, schema: TableSchema) -> pl.DataFrame:
    """Sort by ``schema.order`` if times decrease within any group, with a warning."""
    if not schema.order or not all(c in clean.columns for c in schema.order):
        return clean
    n_bad, n_groups = _unsorted(clean, schema)
    if n_bad == 0:
        return clean
    warnings.warn(_unsorted_message(schema, n_bad, n_groups), UnsortedTimeWarning, stacklevel=3)
    return clean.sort(list(schema.order), maintain_order=True)


def _row_checks(
    prepared: pl.DataFrame,
    schema: TableSchema,
    radars: pl.DataFrame | None,
    limits: Limits,
    rejected_radars: Iterable[int] = (),
) -> list[_Check]:
    rules = _rules(schema.name, limits)
    checks = [
        check
        for name in schema.columns
        if name in prepared.columns
        for check in _column_checks(name, schema, prepared[name].dtype, rules.get(name))
    ]
    if radars is not None and schema.name != "radars" and "radar_id" in prepared.columns:
        checks.append(_radar_check(radars, schema.name, rejected_radars))
    return checks


def as_frame(frame: object, kind: str) -> pl.DataFrame:
    """A polars DataFrame from the accepted input types (else a clear error naming them)."""
    if isinstance(frame, pl.DataFrame):
        return frame
    try:
        if isinstance(frame, pl.LazyFrame):
            return frame.collect()
        if isinstance(frame, Mapping):
            return pl.DataFrame(dict(frame))
        if type(frame).__module__.startswith("pyarrow") and hasattr(frame, "schema"):
            out = pl.from_arrow(frame)
            if isinstance(out, pl.DataFrame):
                return out
    except Exception as exc:  # user data: any construction failure is a data problem
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{kind}: cannot make a table of the {type(frame).__name__} given: {first}") from exc
    raise OptionError(
        f"{kind}: expected a polars DataFrame or LazyFrame, a pyarrow Table or a dict of columns, "
        f"got {type(frame).__name__}"
    )


def validate(
    frame: pl.DataFrame | pl.LazyFrame | Mapping[str, object],
    kind: str,
    *,
    strict: bool = True,
    radars: pl.DataFrame | None = None,
    limits: Limits = Limits(),
    rejected_radars: Iterable[int] = (),
    time_window: tuple[datetime, datetime, str] | None = None,
    median_time: datetime | None = None,
) -> pl.DataFrame | tuple[pl.DataFrame, pl.DataFrame]:
    """Cast ``frame`` to the ``kind`` schema and check it row by row (vectorised).

    ``frame`` is a polars DataFrame or LazyFrame (collected), a pyarrow Table or a dict of
    columns. Returns the clean frame (``strict=True``, raising :class:`SchemaError` on
    the first failing check) or ``(clean, rejects)`` (``strict=False``).  A
    missing required column or an uncastable column dtype raises in both
    modes.  Reports without ``report_id`` get the row position, without
    ``run`` get run 0; ``radars`` (the valid radars) enables the unknown-radar and
    maximum-range checks, ``rejected_radars`` names ids whose reports are rejected with that
    reason; ``time_window`` = (start, end, label) rejects rows outside it (truth against the
    reports' span).  Frames whose times decrease within a track are sorted with an
    :class:`UnsortedTimeWarning`. The rules are :func:`contract_rules`.
    """
    schema = _schema(kind)
    frame = as_frame(frame, kind)
    if radars is not None:
        radars = as_frame(radars, "radars")
    _require(frame, schema)
    prepared = _prepare(frame, schema)
    checks = _row_checks(prepared, schema, radars, limits, rejected_radars)
    work, more = _context_checks(_cast_frame(prepared, schema), schema, radars, limits, time_window, median_time)
    checks += more
    ok, bad = _split(work, checks)
    if strict:
        _raise_first(bad, checks, kind)
    own_ids = kind == "reports" and "report_id" in frame.columns
    dups = _duplicate_checks(schema, ok.columns, own_ids)
    clean, repeats = _split(ok, dups)
    if strict:
        _raise_first(repeats, dups, kind)
    clean = _sort_tracks(clean.select(_clean_columns(schema, clean.columns)), schema)
    if strict:
        return clean
    rejects = pl.concat([_rejects(bad, prepared), _rejects(repeats, prepared)]).sort(ROW_INDEX)
    return clean, rejects


# ---------------------------------------------------------------------------
# helpers for other stages
# ---------------------------------------------------------------------------


def empty_frame(kind: str, optional: bool = True) -> pl.DataFrame:
    """An empty frame with the ``kind`` schema (optional columns too by default)."""
    schema = _schema(kind)
    return pl.DataFrame(schema=schema.columns if optional else schema.required)


def _has(dtype: pl.DataType, kinds: tuple[type, ...]) -> bool:
    if isinstance(dtype, kinds):
        return True
    if isinstance(dtype, (pl.List, pl.Array)):
        return _has(dtype.inner, kinds)
    if isinstance(dtype, pl.Struct):
        return any(_has(f.dtype, kinds) for f in dtype.fields)
    return False


def _json_expr(col: pl.Expr, dtype: pl.DataType, finite: bool) -> pl.Expr:
    """``col`` in a dtype the JSON writer handles: it panics on Binary and cannot write Object
    values, and JSON has no NaN (temporal, decimal and the rest it writes natively)."""
    if dtype.is_float():
        return col if finite else col.cast(pl.String)
    if dtype == pl.Binary:
        return col.bin.encode("hex")
    if isinstance(dtype, (pl.List, pl.Array)) and dtype.inner.is_float() and not finite:
        return col.cast(pl.List(dtype.inner)).list.eval(pl.element().cast(pl.String))
    if _has(dtype, (pl.Binary, pl.Object)):
        return pl.lit(f"<{dtype}>")
    return col


def _all_finite(series: pl.Series) -> bool:
    """No NaN/inf anywhere in a float (or list/array of float) column."""
    dtype = series.dtype
    if isinstance(dtype, (pl.List, pl.Array)) and dtype.inner.is_float():
        series = series.cast(pl.List(dtype.inner)).explode()
    elif not dtype.is_float():
        return True
    return bool(series.drop_nulls().is_finite().all())


def _json_safe(frame: pl.DataFrame) -> list[pl.Expr]:
    """Columns for JSON: every dtype made writable (binary as hex, durations as µs, temporal and
    decimal as text); floats holding NaN/inf become strings (JSON has no NaN)."""
    return [
        _json_expr(pl.col(name), dtype, _all_finite(frame[name])).alias(name)
        for name, dtype in frame.schema.items()
    ]


def rejects_table(rejects: pl.DataFrame, table: str, stage: str) -> pl.DataFrame:
    """Pack ``validate()`` rejects into the canonical ``rejects`` schema.

    ``detail`` is the rejected row (all its columns except ``row_index`` and
    ``reason``) as a JSON object; NaN/inf floats are written as strings.
    """
    missing = [c for c in (ROW_INDEX, REASON) if c not in rejects.columns]
    if missing:
        raise SchemaError(
            f"rejects: required column '{missing[0]}' is missing "
            f"(have: {', '.join(rejects.columns)})",
            table="rejects",
            column=missing[0],
            problem="missing column",
        )
    body = rejects.drop(ROW_INDEX, REASON)
    detail = (
        pl.struct(_json_safe(body)).struct.json_encode() if body.width else pl.lit("{}")
    )
    report_id = pl.col("report_id") if "report_id" in rejects.columns else pl.lit(None)
    out = rejects.select(
        pl.lit(table).alias("input_table"),
        pl.lit(stage).alias("stage"),
        report_id.cast(pl.UInt64).alias("report_id"),
        pl.col(ROW_INDEX).cast(pl.UInt64),
        pl.col(REASON).cast(pl.String),
        detail.alias("detail"),
    )
    return out.cast(TABLES["rejects"].required)


def is_sorted_by(frame: pl.DataFrame, by: list[str]) -> bool:
    """Whether ``frame`` is already in non-descending lexicographic order of ``by`` with no
    nulls in those columns: lets a stage skip re-sorting a large frame that arrives sorted."""
    if frame.height < 2:
        return True
    if frame.select(pl.any_horizontal(pl.col(by).is_null().any())).item():
        return False
    later = np.zeros(frame.height - 1, dtype=bool)   # row i+1 sorts after row i
    tie = np.ones_like(later)
    for c in by:
        k = frame[c].to_physical().to_numpy()
        later |= tie & (k[1:] > k[:-1])
        tie &= k[1:] == k[:-1]
    return bool(np.all(later | tie))


RULES = contract_rules()
