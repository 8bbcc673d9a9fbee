"""The tables of the data contract: every table that enters or leaves a pipeline stage is described
by a :class:`TableSchema` in :data:`TABLES`. Units are SI (metres, seconds, m/s; angles in degrees
where the column name says ``_deg``) and times are stored as ``pl.Datetime("us", "UTC")``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl

from tertiary.core.errors import OptionError
from tertiary.core.units import STATE

__all__ = [
    "BOOL", "CLEARED_ALT_COLUMN", "COV", "EHS_REPORT_COLUMNS", "F64", "FUSED_EXTRA", "I64", "INPUT_ROW",
    "MLAT_PLOT_COLUMNS", "REASON",
    "ROW_INDEX", "SELECTED_ALT_COLUMN", "STR", "TABLES", "TIME", "TURN_RATE_COLUMN", "TableSchema", "U32", "U64",
    "empty_frame", "is_sorted_by", "table_schema",
]

TIME = pl.Datetime("us", "UTC")
F64 = pl.Float64()
U32 = pl.UInt32()
U64 = pl.UInt64()
I64 = pl.Int64()
STR = pl.String()
BOOL = pl.Boolean()
COV = pl.Array(pl.Float64, 36)

ROW_INDEX = "row_index"
REASON = "reason"
#: the rows' positions in the whole input, on a part of it (a window, a group of aircraft)
INPUT_ROW = "__input_row"


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
        # "radar" (default when absent or null), "mlat": a multilateration / WAM system, or
        # "adsb": an ADS-B ground station; the site of either is its reference point and its
        # reports carry a Cartesian plot (MLAT_PLOT_COLUMNS)
        "kind": STR,
    },
    key=("radar_id",),
    finite=True,
)

#: Mode S enhanced-surveillance parameters extracted with a report (BDS 5,0 ground speed, true
#: track angle (° clockwise from north), track-angle rate (°/s), roll angle (°, right wing down
#: positive); BDS 6,0 inertial vertical rate (m/s)); null without a Mode S reply or not extracted.
#: Inputs of the chapter 3 range channels (:mod:`tertiary.filters.kinematic`).
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

#: the Cartesian plot of a report of a sensor of kind "mlat" (CAT020): east/north in the
#: sensor's local ENU frame at its site (m), the same point in WGS-84, its geometric height (m),
#: and its accuracy: standard deviations along x and y (m) and the x-y term (m; covariance =
#: sign · term², the ASTERIX convention); the polar range_m/azimuth_deg of such a report are
#: the same point seen from the site
MLAT_PLOT_COLUMNS = ("plot_x_m", "plot_y_m", "plot_lat_deg", "plot_lon_deg", "plot_height_m", "plot_sigma_x_m",
                     "plot_sigma_y_m", "plot_sigma_xy_m")
#: the quality indicators of an ADS-B report (sensor of kind "adsb", CAT021 I021/090): NACp
#: (its σ where no plot σ is stated), NIC and SIL (its eligibility for fusion); null = not broadcast
ADSB_QUALITY_COLUMNS = ("adsb_nacp", "adsb_nic", "adsb_sil")

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
        **_floats(*MLAT_PLOT_COLUMNS),
        **dict.fromkeys(ADSB_QUALITY_COLUMNS, pl.UInt8),
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

#: columns the fusion stage (tertiary.stages.fusion.fuse) adds to ``fused`` for the secondary tracker and
#: the target count: ``mode_s`` the Mode S address most of the target's reports carry (null
#: without one), ``n_fresh`` fresh measurements in the fused plot, ``age_s`` age of the newest
#: of them (s, epoch − report time; the measurement time; without a fresh plot the newest
#: report of any source), ``tentative`` (a target only ever made of one radar's unconfirmed
#: one-plot local tracks), and the plot-level fusion of the fresh measured plots at time
#: epoch − ``age_s``: ``meas_x_m``…``meas_z_m`` with its full 3×3 covariance ``meas_cov``
#: (row-major, null without a fresh plot), ``meas_vx_mps``, ``meas_vy_mps`` the downlinked
#: ground velocity (Mode S BDS 5,0) of its newest fresh plot carrying one, in the system frame
#: at that time, ``meas_vrate_mps`` the downlinked vertical rate (BDS 6,0) of its newest fresh
#: plot carrying one (null without); ``selected_alt_m`` the selected altitude of the
#: target's newest report carrying one (:data:`SELECTED_ALT_COLUMN`). Not in ``_FUSED.optional``:
#: the centralised stage (which emits every ``fused`` column) produces only ``tentative`` of them.
FUSED_EXTRA: dict[str, pl.DataType] = {
    "n_fresh": U32, "age_s": F64, "tentative": BOOL, "mode_s": STR, SELECTED_ALT_COLUMN: F64,
    TURN_RATE_COLUMN: F64, CLEARED_ALT_COLUMN: F64,
    **_floats("meas_x_m", "meas_y_m", "meas_z_m"), "meas_cov": pl.Array(pl.Float64, 9),
    **_floats("meas_vx_mps", "meas_vy_mps", "meas_vrate_mps"),
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
    # selected_alt_m: that target's selected altitude (latest known, carried while coasting;
    #   null on a row moving away from it after the track was level there: tracking.intent)
    # ehs_track_rate_dps: that target's downlinked track-angle rate (latest known, likewise)
    # cleared_alt_m: that target's cleared level from flight data (as selected_alt_m)
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
    # induced: "picture" / "predictor" (null on the truth picture's own episodes); valid: a
    # nuisance or false alert followed by a manoeuvre within the look-ahead; an external alert
    # list (CAT004) adds its alert identifier and the identities of the two aircraft
    optional={"induced": STR, "valid": pl.Boolean(), "alert_id": U32, "callsign_a": STR, "callsign_b": STR,
              "mode_s_ident_a": STR, "mode_s_ident_b": STR, "mode_3a_a": STR, "mode_3a_b": STR},
    nullable=frozenset({"truth_a", "truth_b", "r_min_pred_m", "dz_min_pred_m", "t_min_first_s", "los_start",
                        "warning_s", "induced"}),
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


def table_schema(kind: str) -> TableSchema:
    """The :class:`TableSchema` of table ``kind`` (OptionError for an unknown kind)."""
    try:
        return TABLES[kind]
    except KeyError:
        known = ", ".join(TABLES)
        raise OptionError(f"unknown table kind {kind!r}; expected one of {known}") from None


def empty_frame(kind: str, optional: bool = True) -> pl.DataFrame:
    """An empty frame with the ``kind`` schema (optional columns too by default)."""
    schema = table_schema(kind)
    return pl.DataFrame(schema=schema.columns if optional else schema.required)


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
