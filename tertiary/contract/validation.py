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

import os
import warnings
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
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
    "as_frame", "sort_tracks", "streamed_median_time", "table_median_time", "table_order", "unsorted_groups",
    "unsorted_message", "validate",
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
    repeat_of: tuple[str, ...] = ()  # a check of rows repeating an earlier row's values of these columns


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
    col = pl.col(name)
    cast = orig != dtype      # a column already of its dtype loses nothing (see _cast_frame)
    checks = []
    if cast:
        value = _as_text(pl.col(_orig(name)), orig)
        checks.append(_Check(
            (name,),
            f"cannot cast to {dtype_label(dtype)}",
            pl.col(_lost(name)),
            pl.format(f"{name}: cannot cast {{}} to {dtype_label(dtype)}", value),
        ))
    required = name in schema.required
    identifying = required or name in schema.key or name == "report_id"
    if identifying and name not in schema.nullable:
        null = col.is_null() & ~pl.col(_lost(name)) if cast else col.is_null()
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
    """range_m <= max_range_m x margin of the report's radar (null for a radar not in ``radars``)."""
    cap = radars.select(
        pl.col("radar_id").cast(U32, strict=False),
        (pl.col("max_range_m").cast(F64, strict=False) * limits.range_margin).alias("rmax"),
    ).drop_nulls("radar_id").unique("radar_id", keep="first")
    rng = pl.col("range_m")
    rmax = pl.col("radar_id").replace_strict(cap["radar_id"], cap["rmax"], default=None, return_dtype=F64)
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
    time = frame["time"]
    return time.filter(time.is_between(lo, hi, closed="left").fill_null(False)).median()


#: buckets of the streamed median's middle pass (:func:`streamed_median_time`)
_MEDIAN_BUCKETS = 1 << 20


def streamed_median_time(batches: Callable[[], Iterable[pl.Series]], limits: Limits = Limits()) -> datetime | None:
    """:func:`table_median_time` of the times ``batches()`` yields (called once per pass;
    microseconds, UTC), exactly, holding one batch and a histogram, never the column (memory: a
    day's truth times are hundreds of MB, their median's sort several times that). Three
    passes: the count and range; a histogram of ``_MEDIAN_BUCKETS`` buckets locating the middle
    rank(s); those buckets' values, whose middle one or two the polars median of the whole
    takes."""
    lo, hi = (datetime(y, 1, 1, tzinfo=timezone.utc) for y in limits.years)

    def kept() -> Iterable[NDArray[np.int64]]:
        for s in batches():
            s = s.filter(s.is_between(lo, hi, closed="left").fill_null(False))
            if s.len():
                yield s.dt.epoch("us").to_numpy()
    n, first, last = 0, None, None
    for v in kept():
        n, first, last = n + v.size, v.min() if first is None else min(first, v.min()), (
            v.max() if last is None else max(last, v.max()))
    if n == 0:
        return None
    shift = max(0, int(last - first).bit_length() - _MEDIAN_BUCKETS.bit_length() + 1)
    counts = np.zeros(_MEDIAN_BUCKETS, np.int64)
    for v in kept():
        counts += np.bincount((v - first) >> shift, minlength=_MEDIAN_BUCKETS)
    ranks = sorted({(n - 1) // 2, n // 2})
    ends = np.cumsum(counts)
    where = np.searchsorted(ends, ranks, side="right")       # the bucket holding each rank
    values = np.sort(np.concatenate([v[np.isin((v - first) >> shift, where)] for v in kept()]))
    before = ends[where.min()] - counts[where.min()]           # rows below the first such bucket
    middle = values[[r - before for r in ranks]]
    return pl.Series(middle).cast(pl.Datetime("us", "UTC")).median()


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


#: matrices checked at a time: the block's 36 entries are rows of contiguous numbers (each step of
#: the checks is one numpy operation over the block) and its temporaries stay in cache
_COV_BLOCK = 8_192
_DIAG = tuple(range(0, 36, 7))
_PAIRS = tuple((i * 6 + j, j * 6 + i) for i in range(6) for j in range(i + 1, 6))


def _cov_codes(cov: pl.Series, limits: Limits) -> NDArray[np.int8]:
    """Per row 0 (a covariance, or NaN/null: left to the align stage) or the _COV_PROBLEMS code."""
    n = len(cov)
    code = np.zeros(n, np.int8)
    if n == 0:
        return code
    a = cov.to_numpy().reshape(n, 36)

    def block(lo: int) -> None:
        code[lo:lo + _COV_BLOCK] = _cov_block(np.ascontiguousarray(a[lo:lo + _COV_BLOCK].T), limits)

    starts = range(0, n, _COV_BLOCK)
    workers = min(len(starts), os.cpu_count() or 1, 4)
    if workers > 1:         # numpy works on a block without the GIL: blocks side by side
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(block, starts))
    else:
        for lo in starts:
            block(lo)
    return code


def _cov_block(flat: NDArray[np.float64], limits: Limits) -> NDArray[np.int8]:
    """:func:`_cov_codes` of the matrices whose entry (i, j) is row 6·i + j of ``flat``."""
    m = flat.shape[1]
    with np.errstate(all="ignore"):
        finite = np.isfinite(flat).all(axis=0)
        nan, inf = np.zeros(m, bool), np.zeros(m, bool)
        odd = np.flatnonzero(~finite)
        if len(odd):
            nan[odd] = np.isnan(flat[:, odd]).any(axis=0)
            inf[odd] = ~nan[odd]
        scale = np.abs(flat[_DIAG, :]).max(axis=0)
        big = finite & (scale > limits.variance_max)
        tol = limits.cov_rel_tol * scale
        # the lower triangle of the symmetric part, (P + P^T) / 2 (what the factorisation reads),
        # and |P - P^T|, largest off the diagonal (0 on it)
        sym = np.empty_like(flat)
        skew, diff = np.zeros(m), np.empty(m)
        for d in _DIAG:
            sym[d] = 0.5 * (flat[d] + flat[d])
        for ij, ji in _PAIRS:
            np.subtract(flat[ij], flat[ji], out=diff)
            np.maximum(skew, np.abs(diff, out=diff), out=skew)
            np.add(flat[ji], flat[ij], out=sym[ji])
            sym[ji] *= 0.5
        asym = finite & ~big & (skew > tol)
        test = finite & ~big & ~asym
        if limits.cov_rel_tol >= _PSD_FAST_MIN_TOL:
            # the eigenvalues only of the matrices a factorisation cannot clear at once
            rows = np.flatnonzero(test & ~_cholesky_flat(sym, 0.5 * tol))
        else:
            rows = np.flatnonzero(test)
        not_psd = np.zeros(m, bool)
        if len(rows):
            part = np.ascontiguousarray(flat[:, rows].T).reshape(-1, 6, 6)
            mats = 0.5 * (part + part.transpose(0, 2, 1))
            not_psd[rows] = np.linalg.eigvalsh(mats)[:, 0] < -tol[rows]
    code = np.zeros(m, np.int8)
    code[not_psd], code[asym], code[big], code[inf] = 4, 3, 2, 1
    return code


#: the PSD test clears matrices by factorisation when its margin (half the tolerance) is far
#: above the factorisation's round-off (~1e-13 of the largest diagonal, 6×6)
_PSD_FAST_MIN_TOL = 1e-10


def _cholesky_ok(sym: NDArray[np.float64], shift: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Per matrix of ``sym`` (m × k × k): ``sym + shift·I`` has a Cholesky factor (every pivot > 0),
    over the batch at once (:func:`_cholesky_flat`)."""
    m, k = sym.shape[0], sym.shape[1]
    return _cholesky_flat(np.ascontiguousarray(sym.reshape(m, k * k).T), shift)


def _cholesky_flat(flat: NDArray[np.float64], shift: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Per matrix (entry (i, j) of matrix c at ``flat[i·k + j, c]``): ``sym + shift·I`` has a
    Cholesky factor (every pivot > 0), column by column with numpy over the matrices
    (``np.linalg.cholesky`` stops the whole batch at the first failure). A factor means
    λmin(sym) ≥ −shift − ~1e-13·max|diag| (the factorisation's backward error), so with
    ``shift`` half the tolerance such a matrix is surely not below −tolerance and its eigenvalues
    need not be computed. False only means "not cleared": the caller computes them."""
    k = int(round(np.sqrt(flat.shape[0])))
    low: dict[tuple[int, int], NDArray[np.float64]] = {}
    ok = np.ones(flat.shape[1], bool)
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
                repeat_of=("report_id",),
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
                repeat_of=schema.key,
            )
        )
    return checks


def _split(work: pl.DataFrame, checks: list[_Check]) -> tuple[pl.Series, pl.DataFrame]:
    """(mask of the rows failing any check, those rows).

    The checks are evaluated once over the whole frame, as boolean columns only; the flagged
    rows alone are then taken with every column, their ``__bad{i}`` masks and the joined
    ``__reason`` (reasons are formatted for flagged rows only; a check's ``context`` is
    computed over the whole frame, for the checks that flag a row).
    """
    names = [f"__bad{i}" for i in range(len(checks))]
    none = pl.Series("__flagged", [], dtype=pl.Boolean).extend_constant(False, work.height)
    if not checks:
        return none, work.clear().with_columns(pl.lit(None, pl.String).alias("__reason"))
    masks = work.select(c.bad.fill_null(False).alias(n) for c, n in zip(checks, names))
    counts = masks.select(pl.col(names).sum()).row(0)
    hit = [(c, n) for c, n, count in zip(checks, names, counts) if count]
    if not hit:
        return none, work.clear().with_columns(pl.lit(None, pl.String).alias("__reason"))
    flagged = masks.select(pl.any_horizontal([n for _, n in hit]).alias("__flagged")).to_series()
    bad = pl.concat([work.filter(flagged), masks.filter(flagged)], how="horizontal")
    context = {k: e for c, _ in hit for k, e in c.context.items()}
    if context:
        bad = pl.concat([bad, work.select(**context).filter(flagged)], how="horizontal")
    reasons = [pl.when(pl.col(n)).then(c.reason) for c, n in hit]
    joined = pl.concat_str(reasons, separator="; ", ignore_nulls=True)
    return flagged, bad.with_columns(joined.alias("__reason"))


def _occurs_twice(values: pl.Series) -> pl.Series:
    """Per row: whether its value occurs in more than one row (found in a sorted copy; polars
    sorts on every core, several times faster than numpy's single-threaded sort)."""
    ordered = values.sort().to_numpy()
    twice = np.unique(ordered[1:][ordered[1:] == ordered[:-1]])
    return values.is_in(pl.Series(twice, dtype=values.dtype).implode())


def _split_repeats(work: pl.DataFrame, ok: pl.Series, dups: list[_Check]) -> tuple[pl.Series, pl.DataFrame]:
    """(mask of the rows of ``work`` that repeat an ``ok`` row's key, those rows): :func:`_split`
    of the ``ok`` rows by the duplicate checks, on the columns the checks read only."""
    used = {_IDX}
    for c in dups:
        for e in (c.bad, c.reason, *c.context.values()):
            used.update(e.meta.root_names())
    keys = work.select(c for c in work.columns if c in used).filter(ok)
    if dups and all(c.repeat_of for c in dups):
        # only rows whose key hash occurs twice can repeat a key, and every row of a repeated key
        # is among them (in order): the checks and their first rows are the same on these rows
        maybe = pl.repeat(False, keys.height, eager=True)
        for c in dups:
            maybe = maybe | _occurs_twice(keys.select(c.repeat_of).hash_rows())
        keys = keys.filter(maybe)
    flagged, rep = _split(keys, dups)
    if rep.height == 0:
        return flagged.clear().extend_constant(False, work.height), \
            work.clear().with_columns(pl.lit(None, pl.String).alias("__reason"))
    mask = np.zeros(work.height, bool)
    mask[rep[_IDX].to_numpy()] = True
    rows = pl.Series("__repeat", mask)
    extra = [c for c in rep.columns if c not in keys.columns or c.startswith(("__bad", "__reason"))]
    return rows, pl.concat([work.filter(rows), rep.select(extra)], how="horizontal")


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
    """Cast schema columns, keeping the originals and loss masks of the cast ones in ``__``
    columns (a column already of its dtype is its own original and loses nothing)."""
    columns = []
    for name, dtype in schema.columns.items():
        if name not in prepared.columns:
            continue
        src = prepared[name]
        if src.dtype == dtype:
            if name == "run":       # the rejects show a null run, the clean rows run 0
                columns.append(src.alias(_orig(name)))
            continue
        cast, lost = cast_column(src, dtype, schema.name)
        columns += [src.alias(_orig(name)), lost.alias(_lost(name)), cast]
    work = prepared.with_columns(columns) if columns else prepared
    if schema.name == "reports" and work[_orig("run")].null_count():  # a null run is the default run 0
        orig, run = work[_orig("run")], work["run"]
        default = pl.select(pl.when(orig.is_null()).then(0).otherwise(run).cast(pl.UInt32).alias("run"))
        work = work.with_columns(default.to_series())
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
    if clean[schema.order[-1]].is_sorted():      # in time order overall: in time order in every group
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
    # one copy into contiguous columns: a frame of many chunks (parquet row groups, concatenated
    # parts) would be copied so by each filter and each expression over it
    prepared = _prepare(frame.rechunk(), schema)
    checks = _row_checks(prepared, schema, radars, limits, rejected_radars)
    work, more = _context_checks(_cast_frame(prepared, schema), schema, radars, limits, time_window, median_time)
    checks += more
    flagged, bad = _split(work, checks)
    if strict:
        _raise_first(bad, checks, kind)
    own_ids = kind == "reports" and "report_id" in frame.columns
    dups = _duplicate_checks(schema, work.columns, own_ids)
    repeated, repeats = _split_repeats(work, ~flagged, dups)
    if strict:
        _raise_first(repeats, dups, kind)
    keep = ~(flagged | repeated)
    clean = work.select(_clean_columns(schema, work.columns))
    clean = _sort_tracks(clean if bad.height + repeats.height == 0 else clean.filter(keep), schema)
    if strict:
        return clean
    rejects = pl.concat([_rejects(bad, prepared), _rejects(repeats, prepared)]).sort(ROW_INDEX)
    return clean, rejects


