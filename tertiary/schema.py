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
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import timedelta

import numpy as np
import polars as pl

__all__ = [
    "TABLES",
    "Limits",
    "SchemaError",
    "TableSchema",
    "UnsortedTimeWarning",
    "empty_frame",
    "rejects_table",
    "validate",
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
_INTERNAL = ("__row_index", "__orig__", "__lost__", "__bad", "__reason", "__first_id")


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
        **_floats("lat_deg", "lon_deg", "alt_m"),
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
    key=("run", "epoch", "method", "target_id"),
)

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
    key=("run", "epoch", "method", "id_a", "id_b"),
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
        _CLUSTERS, _TRACKS, _CONFLICTS, _REJECTS, _METRICS, _RUN,
    )
}

# ---------------------------------------------------------------------------
# errors, warnings and limits
# ---------------------------------------------------------------------------


class SchemaError(ValueError):
    """A frame breaks its table contract.

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
    """Plausible value bands (inclusive) for physically bounded columns."""

    altitude_m: Interval = (-500.0, 20000.0)
    range_m: Interval = (0.0, math.inf)
    site_alt_m: Interval = (-500.0, 9000.0)


# ---------------------------------------------------------------------------
# value rules
# ---------------------------------------------------------------------------


def _num(x: float) -> str:
    return str(int(x)) if math.isfinite(x) and float(x).is_integer() else str(x)


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
    """Value rules of a table; they skip nulls and NaNs."""
    if kind == "radars":
        return {
            "lat_deg": _LAT,
            "lon_deg": _LON,
            "alt_m": _Range(*limits.site_alt_m),
            "scan_period_s": _POSITIVE,
            "sigma_range_m": _NONNEG,
            "sigma_azimuth_deg": _NONNEG,
            "sigma_elevation_deg": _NONNEG,
            "max_range_m": _POSITIVE,
            "scan_phase_s": _NONNEG,
            "min_elevation_deg": _LAT,
            "pd": _Range(0.0, 1.0),
            "clutter_rate": _NONNEG,
            "timing": _OneOf(("rotating", "synchronous")),
        }
    if kind == "reports":
        return {
            "range_m": _Range(*limits.range_m),
            "azimuth_deg": _AZIMUTH,
            "elevation_deg": _LAT,
            "altitude_m": _Range(*limits.altitude_m),
            "est_range_var_m2": _NONNEG,
            "est_azimuth_var_deg2": _NONNEG,
            "est_elevation_var_deg2": _NONNEG,
            "res_range_var_m2": _NONNEG,
        }
    if kind == "truth":
        return {"lat_deg": _LAT, "lon_deg": _LON, "alt_m": _Range(*limits.altitude_m)}
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


def _cast_values(s: pl.Series, dtype: pl.DataType, table: str) -> pl.Series:
    if isinstance(dtype, pl.Datetime):
        return _to_time(s, table)
    if isinstance(dtype, pl.Array):
        return _to_array(s, dtype)
    if (dtype.is_numeric() or dtype == pl.Boolean) and s.dtype.is_temporal():
        raise pl.exceptions.InvalidOperationError("temporal to numeric")
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


def _radar_check(radars: pl.DataFrame, table: str) -> _Check:
    if "radar_id" not in radars.columns:
        raise SchemaError(
            f"{table}: the radars frame has no 'radar_id' column",
            table="radars",
            column="radar_id",
            problem="missing column",
        )
    known = radars["radar_id"].cast(pl.UInt32, strict=False).drop_nulls()
    col = pl.col("radar_id")
    return _Check(
        ("radar_id",),
        "unknown radar",
        ~col.is_in(known.implode()),
        pl.format("radar_id: unknown radar {}", col),
    )


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
        ident, ident_col = ("report_id",) * 2 if "report_id" in columns else (ROW_INDEX, _IDX)
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
            f"row {r}: " + ", ".join(f"{c}={v!r}" for c, v in zip(check.columns, vals))
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
        raise ValueError(f"unknown table kind {kind!r}; expected one of {known}") from None


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


def _sort_tracks(clean: pl.DataFrame, schema: TableSchema) -> pl.DataFrame:
    """Sort by ``schema.order`` if times decrease within any group, with a warning."""
    if not schema.order or not all(c in clean.columns for c in schema.order):
        return clean
    *group, time = schema.order
    decreasing = pl.col(time).diff() < pl.lit(timedelta(0))
    per_group = clean.group_by(group).agg(decreasing.any().alias("__unsorted"))
    n_bad = int(per_group["__unsorted"].sum())
    if n_bad == 0:
        return clean
    what = "tracks" if schema.name == "reports" else f"({', '.join(group)}) groups"
    warnings.warn(
        f"{schema.name}: {time} out of order in {n_bad} of {per_group.height} {what}; "
        f"sorted by ({', '.join(schema.order)})",
        UnsortedTimeWarning,
        stacklevel=3,
    )
    return clean.sort(list(schema.order), maintain_order=True)


def _row_checks(
    prepared: pl.DataFrame, schema: TableSchema, radars: pl.DataFrame | None, limits: Limits
) -> list[_Check]:
    rules = _rules(schema.name, limits)
    checks = [
        check
        for name in schema.columns
        if name in prepared.columns
        for check in _column_checks(name, schema, prepared[name].dtype, rules.get(name))
    ]
    if radars is not None and schema.name != "radars" and "radar_id" in prepared.columns:
        checks.append(_radar_check(radars, schema.name))
    return checks


def validate(
    frame: pl.DataFrame,
    kind: str,
    *,
    strict: bool = True,
    radars: pl.DataFrame | None = None,
    limits: Limits = Limits(),
) -> pl.DataFrame | tuple[pl.DataFrame, pl.DataFrame]:
    """Cast ``frame`` to the ``kind`` schema and check it row by row (vectorised).

    Returns the clean frame (``strict=True``, raising :class:`SchemaError` on
    the first failing check) or ``(clean, rejects)`` (``strict=False``).  A
    missing required column or an uncastable column dtype raises in both
    modes.  Reports without ``report_id`` get the row position, without
    ``run`` get run 0; ``radars`` enables the unknown-radar check.  Frames
    whose times decrease within a track are sorted with an
    :class:`UnsortedTimeWarning`.
    """
    schema = _schema(kind)
    _require(frame, schema)
    prepared = _prepare(frame, schema)
    checks = _row_checks(prepared, schema, radars, limits)
    ok, bad = _split(_cast_frame(prepared, schema), checks)
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


def _json_safe(frame: pl.DataFrame) -> list[pl.Expr]:
    """Columns for JSON: floats holding NaN/inf become strings (JSON has no NaN)."""
    exprs = []
    for name, dtype in frame.schema.items():
        col = pl.col(name)
        if dtype.is_float() and not frame[name].drop_nulls().is_finite().all():
            col = col.cast(pl.String)
        exprs.append(col)
    return exprs


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
