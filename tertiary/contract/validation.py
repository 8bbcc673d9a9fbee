"""Validation of an input table against its contract (:mod:`tertiary.contract.tables`,
:mod:`tertiary.contract.rules`).

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

import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract.cast import cast_column, dtype_label
from tertiary.contract.errors import SchemaError, UnsortedTimeWarning
from tertiary.contract.rules import Limits, ValueRule, num_text, value_rules
from tertiary.contract.tables import F64, INPUT_ROW, REASON, ROW_INDEX, U32, TableSchema, table_schema
from tertiary.core.errors import DataError, OptionError

__all__ = [
    "as_frame", "sort_tracks", "table_median_time", "table_order", "unsorted_groups", "unsorted_message", "validate",
]

_IDX = "__row_index"  # internal input position, exposed as ``row_index`` in rejects
_INTERNAL = ("__row_index", "__orig__", "__lost__", "__bad", "__reason", "__first_id", "__ctx_")


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
    name: str, schema: TableSchema, orig: pl.DataType, rule: ValueRule | None
) -> list[_Check]:
    """Cast, null, finiteness and value checks of one column."""
    dtype = schema.columns[name]
    col, value = pl.col(name), _as_text(pl.col(_orig(name)), orig)
    checks = [
        _Check(
            (name,),
            f"cannot cast to {dtype_label(dtype)}",
            pl.col(_lost(name)),
            pl.format(f"{name}: cannot cast {{}} to {dtype_label(dtype)}", value),
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


def _mlat_cov_check() -> _Check:
    """The x-y term of an MLAT plot's accuracy within sqrt(sigma_x sigma_y) (|correlation| <= 1)."""
    sx, sy, sxy = pl.col("plot_sigma_x_m"), pl.col("plot_sigma_y_m"), pl.col("plot_sigma_xy_m")
    bad = (sxy.abs() > (sx * sy).sqrt() * (1 + 1e-9)).fill_null(False)
    return _Check(("plot_sigma_xy_m",), "not a covariance (|xy term| above sqrt(sigma_x sigma_y))", bad,
                  pl.format("plot_sigma_xy_m: |{}| above sqrt(plot_sigma_x_m x plot_sigma_y_m) = sqrt({} x {}): "
                            "not a covariance", sxy.cast(pl.String), sx.cast(pl.String), sy.cast(pl.String)))


def _mlat_plot_check(work: pl.DataFrame, radars: pl.DataFrame) -> tuple[pl.DataFrame, _Check]:
    """Reports of a sensor of kind mlat or adsb carry their Cartesian plot (plot_x_m, plot_y_m)."""
    mlat = radars.filter(pl.col("kind").is_in(("mlat", "adsb"))).select(pl.col("radar_id").cast(U32, strict=False)).to_series()
    have = [pl.col(c).is_not_null() & pl.col(c).is_not_nan() for c in ("plot_x_m", "plot_y_m") if c in work.columns]
    ok = pl.all_horizontal(have) if len(have) == 2 else pl.lit(False)
    bad = pl.col("radar_id").is_in(mlat.implode()) & ~ok
    return work, _Check(("plot_x_m",), "MLAT or ADS-B report without its Cartesian plot", bad,
                        pl.format("plot_x_m: radar {} is of kind mlat or adsb; its report has no plot_x_m, plot_y_m",
                                  pl.col("radar_id")))


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
    if schema.name == "reports" and {"plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m"} <= set(work.columns):
        checks.append(_mlat_cov_check())
    if schema.name == "reports" and radars is not None and {"kind", "radar_id"} <= set(radars.columns):
        work, check = _mlat_plot_check(work, radars)
        checks.append(check)
    if (schema.name == "reports" and radars is not None and "range_m" in work.columns
            and {"radar_id", "max_range_m"} <= set(radars.columns)):
        work, check = _range_check(work, radars, limits)
        checks.append(check)
    elif schema.name == "reports" and "range_m" in work.columns:
        # no radars to compare with: no radar sees beyond the largest plausible max_range_m x margin
        cap = limits.max_range_m[1] * limits.range_margin
        rng = pl.col("range_m")
        checks.append(_Check(("range_m",), f"beyond any radar's range ({num_text(cap)} m)", (rng > cap) & rng.is_finite(),
                             pl.format(f"range_m: beyond any radar's range ({num_text(cap)} m), got {{}}",
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
        cast, lost = cast_column(prepared[name], dtype, schema.name)
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
    return _sort_tracks(clean, table_schema(kind))


def table_order(kind: str) -> tuple[str, ...]:
    """The ``kind`` schema's row order (group columns, then time): what :func:`sort_tracks`
    sorts by."""
    return tuple(table_schema(kind).order)


def unsorted_groups(clean: pl.DataFrame, kind: str) -> tuple[int, int]:
    """(groups whose times decrease in row order, groups) of ``clean`` by the ``kind`` schema's
    order: what :func:`sort_tracks` counts (a table validated in parts adds its parts' counts)."""
    return _unsorted(clean, table_schema(kind))


def unsorted_message(kind: str, n_bad: int, n_groups: int) -> str:
    """The :class:`UnsortedTimeWarning` text of :func:`sort_tracks` for these counts."""
    return _unsorted_message(table_schema(kind), n_bad, n_groups)


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
    rules = value_rules(schema.name, limits)
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
    schema = table_schema(kind)
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


