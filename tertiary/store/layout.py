"""The lean layout of a run database: how the run's large tables are stored (covariances as
their upper triangle, floats narrowed, arrays split, repeated columns factored out) behind views
that give every reader the table it was given.

The run's large tables are stored in a lean physical layout ``_lean_<name>`` (+ ``_lean_<name>__shared``)
behind a view ``<name>`` with the original column names, order and types, so every SQL report
and reader sees the table it always saw. What the layout drops is exactly recoverable (to float32
round-off where a column is narrowed); each rule is checked on the data before it is applied and
a column that fails its check is stored as it came:

``conflicts`` (already slim: alerts and near pairs only) stays a plain table: tools drop it with
DROP TABLE to test a run without safety, and float32 would save little there.

* RESIDUAL: the absolute positions of ``tracks`` and ``fused`` (x, y, z, altitude; the measurement
  positions of ``fused``) are narrowed to float32 and keep, beside it, their remainder
  ``<name>__res``: (value − float32 value) in units of 0.1 mm, truncated toward zero (BIGINT,
  bit-packed into a few bits: ±39 units at 100 km, ±625 at 2 000 km). The view adds it back:
  within 0.1 mm at any range (float32 alone: up to 4 mm at 100 km, 31 mm at 1 000 km, 62 mm at
  2 000 km), never further from the value than its float32 (so a reader that casts to FLOAT, as
  the report's figures do, gets the float32 of the value), for a few bits more than float32.
* NARROW: float64 columns holding velocities, weights, variances, innovations, NIS and
  probabilities stored as float32 (7 significant digits: 2e-5 m/s at 300 m/s, 1e-7 relative on
  a variance) — far below any radar's metres-scale error; the view casts them back to DOUBLE. The
  altitude of ``fused`` (a SHARED column, below) is float32 alone in every row: ≤ 0.5 mm below
  16 384 m. Inputs (``reports``, ``truth``) are never narrowed.
* fixed-size float arrays (``cov_ut`` FLOAT[21], ``meas_cov``, ``nominal_var``) stored as one
  column per element: each element column is homogeneous in scale, so DuckDB's ALP/ALPRD
  compress it (a FLOAT[21] column interleaves variances and cross terms and barely compresses).
* DERIVED: ``tracks.cov_diag`` is the diagonal of ``cov``; ``aligned.age_s`` is epoch − time.
* FROM_REPORTS: ``aligned`` repeats each report's columns (run, radar_id, local_track_id, time,
  residuals, mode_s, truth_id, altitude_m) on every epoch it is aligned to; the view joins them
  from ``reports`` by ``report_id`` (checked equal before they are dropped).
* SHARED: in ``fused`` the columns that do not depend on the fusion method (the vertical
  channel, freshness, identity, sources) are stored once per (run, epoch, target_id) in
  ``_lean_fused__shared`` for the rows of every method but ``centralized``, for each key whose
  rows agree on all of them (checked; the rows of a key that does not keep their own values).
"""

from __future__ import annotations

import contextlib
import secrets
from collections.abc import Iterator
from contextlib import contextmanager

import duckdb
import numpy as np
import polars as pl

__all__ = ["COV_SUFFIX", "LEAN_PREFIX", "RESIDUAL", "RESIDUAL_SUFFIX", "RESIDUAL_UNITS", "compact_covariances",
           "expand_covariances", "Layout", "lean_layout", "view_sql", "layout_signature", "column_types",
           "arrow_view", "sql_literal", "quote"]

#: a 6×6 covariance column (row-major Array(Float64, 36)) is stored as its upper triangle
#: ``<name>_ut`` Array(Float32, 21) — symmetric, so 15 of the 36 doubles are repeats, and float32
#: keeps 7 significant digits (0.001 m² on a 10⁴ m² variance); :meth:`RunStore.read` gives
#: the full Float64 matrix back. A column holding a non-symmetric matrix is stored whole.
COV_SUFFIX = "_ut"
_IU = np.triu_indices(6)
_FULL_FROM_UT = np.empty(36, np.int64)
_FULL_FROM_UT[_IU[0] * 6 + _IU[1]] = np.arange(21)
_FULL_FROM_UT[_IU[1] * 6 + _IU[0]] = np.arange(21)


def _is_cov(dtype: pl.DataType) -> bool:
    return isinstance(dtype, pl.Array) and dtype.size == 36 and dtype.inner == pl.Float64


def compact_covariances(frame: pl.DataFrame) -> pl.DataFrame:
    """Each Array(Float64, 36) column ``c`` replaced by ``c_ut`` (upper triangle, float32)."""
    out = frame
    for name, dtype in frame.schema.items():
        if _is_cov(dtype):
            c = pl.col(name)
            lower = [(i, j) for i in range(6) for j in range(i)]
            asym = pl.max_horizontal(*[(c.arr.get(i * 6 + j) - c.arr.get(j * 6 + i)).abs() for i, j in lower])
            scale = pl.max_horizontal(*[c.arr.get(k * 7).abs() for k in range(6)])
            bad = frame.select((asym > 1e-9 * scale.clip(lower_bound=1e-300)).fill_null(False).any()).item()
            if bad:
                continue                  # not a covariance: kept whole rather than symmetrised
            # polars expressions, column by column: no (n, 36) float64 copies of a large table
            ut = pl.concat_arr([c.arr.get(int(k)).cast(pl.Float32) for k in _IU[0] * 6 + _IU[1]])
            series = frame.select(pl.when(c.is_null()).then(None).otherwise(ut)
                                  .alias(name + COV_SUFFIX)).to_series()
            order = [c if c != name else series.name for c in out.columns]
            out = out.with_columns(series).select(order)
    return out


def expand_covariances(frame: pl.DataFrame) -> pl.DataFrame:
    """Inverse of :func:`compact_covariances` (float32 precision)."""
    out = frame
    for name, dtype in frame.schema.items():
        if name.endswith(COV_SUFFIX) and isinstance(dtype, pl.Array) and dtype.size == 21:
            ut = frame[name].to_numpy().reshape(-1, 21).astype(np.float64)
            full = pl.Series(name[: -len(COV_SUFFIX)], ut[:, _FULL_FROM_UT], dtype=pl.Array(pl.Float64, 36))
            if frame[name].null_count():
                full = pl.select(pl.when(frame[name].is_null()).then(None).otherwise(full)
                                 .alias(full.name)).to_series()
            order = [c if c != name else full.name for c in out.columns]
            out = out.with_columns(full).select(order)
    return out



LEAN_PREFIX = "_lean_"
ROWS_FLAG = "__shared"
_F32_RTOL = 2e-7      # float32 keeps 24 bits: relative round-off ≤ 2⁻²⁴ ≈ 6e-8 (with margin)

NARROW: dict[str, tuple[str, ...]] = {
    # aligned's state stays float64: the radar accuracy figures of the HTML report are computed
    # from it and must not move (they embed the values at full precision)
    "aligned": ("nominal_var",),
    "fused": ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "weights", "age_s", "meas_x_m", "meas_y_m",
              "meas_z_m", "meas_cov", "alt_m", "alt_rate_mps", "alt_var_m2", "alt_rate_var_m2ps2",
              "alt_cov_m2ps"),
    "tracks": ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "innovation", "nis", "model_probs", "alt_m",
               "alt_rate_mps", "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps"),
}
#: tables whose fixed-size float arrays are stored one column per element
SPLIT = ("reports", "aligned", "fused", "tracks")
FROM_REPORTS = {"aligned": ("run", "radar_id", "local_track_id", "time", "res_range_m", "res_range_var_m2",
                             "mode_s", "truth_id", "altitude_m")}
SHARED = {"fused": (("run", "epoch", "target_id"), "method", "centralized",
                     ("n_sources", "radar_ids", "mode_s", "n_fresh", "age_s", "tentative", "alt_m", "alt_rate_mps",
                      "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps"))}
#: narrowed absolute positions stored with their remainder (``<name>__res``, see RESIDUAL above)
_POSITIONS = ("x_m", "y_m", "z_m", "alt_m")
RESIDUAL: dict[str, tuple[str, ...]] = {"tracks": _POSITIONS,
                                        "fused": (*_POSITIONS, "meas_x_m", "meas_y_m", "meas_z_m")}
RESIDUAL_SUFFIX = "__res"
#: remainder units per metre (0.1 mm)
RESIDUAL_UNITS = 10_000
_DIAG_UT = [0, 6, 11, 15, 18, 20]       # positions of the diagonal in a row-major 6×6 upper triangle


def sql_literal(text: str) -> str:
    """``text`` as an SQL string literal."""
    return "'" + text.replace("'", "''") + "'"


def quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _narrowed(dtype: pl.DataType) -> pl.DataType | None:
    """The float32 twin of a float64 (list/array) dtype, else None."""
    if dtype == pl.Float64:
        return pl.Float32()
    if isinstance(dtype, pl.List) and dtype.inner == pl.Float64:
        return pl.List(pl.Float32)
    if isinstance(dtype, pl.Array) and dtype.inner == pl.Float64:
        return pl.Array(pl.Float32, dtype.size)
    return None


def _splittable(frame: pl.DataFrame, name: str) -> bool:
    """A float array column whose null rows are whole (no null element inside a non-null array)."""
    dtype = frame.schema[name]
    if not (isinstance(dtype, pl.Array) and dtype.inner in (pl.Float32, pl.Float64)):
        return False
    col = frame[name]
    inner_nulls = col.arr.explode().null_count() if frame.height else 0
    return inner_nulls == col.null_count() * dtype.size


class Layout:
    """The physical frame(s) of one lean table and the view's select list over them."""

    def __init__(self, name: str, frame: pl.DataFrame) -> None:
        self.name, self.orig = name, frame
        self.phys = frame
        self.exprs: dict[str, str] = {c: f"p.{quote(c)}" for c in frame.columns}
        self.shared: pl.DataFrame | None = None
        self.shared_keys: tuple[str, ...] = ()
        self.joins_reports: str | None = None

    @property
    def changed(self) -> bool:
        return self.phys.schema != self.orig.schema or self.shared is not None or self.joins_reports


def lean_layout(name: str, frame: pl.DataFrame, con: duckdb.DuckDBPyConnection,
                 reports_table: str | None) -> Layout:
    lay = Layout(name, frame)
    if name in FROM_REPORTS and reports_table is not None:
        _drop_report_columns(lay, con, reports_table)
    if name in SHARED:
        _factor_shared(lay, *SHARED[name])
    if name == "tracks":
        _drop_cov_diag(lay)
    narrow = [c for c in NARROW.get(name, ()) if c in lay.phys.columns and _narrowed(lay.phys.schema[c])]
    lay.phys = lay.phys.with_columns(pl.col(c).cast(_narrowed(lay.phys.schema[c])) for c in narrow)
    if name in RESIDUAL:
        _add_residuals(lay, RESIDUAL[name])
    if lay.shared is not None:
        sn = [c for c in narrow if c in lay.shared.columns]
        lay.shared = lay.shared.with_columns(pl.col(c).cast(_narrowed(lay.shared.schema[c])) for c in sn)
    if name in SPLIT:
        _split_arrays(lay)
    return lay


def _split_arrays(lay: Layout) -> None:
    """Fixed-size float arrays -> one column per element (nulls kept as a null first element)."""
    for c, dtype in list(lay.phys.schema.items()):
        if c not in lay.orig.columns or not _splittable(lay.phys, c):
            continue
        parts = [f"{c}__{k}" for k in range(dtype.size)]
        cols = [pl.col(c).arr.get(k).alias(p) for k, p in enumerate(parts)]
        order = [x for col in lay.phys.columns for x in (parts if col == c else [col])]
        lay.phys = lay.phys.with_columns(cols).select(order)
        arr = "[" + ", ".join(f"p.{quote(x)}" for x in parts) + "]"
        lay.exprs[c] = f"CASE WHEN p.{quote(parts[0])} IS NULL THEN NULL ELSE {arr} END"
        if lay.exprs.get("cov_diag", "").startswith("DIAG:") and c == "cov_ut":
            diag = "[" + ", ".join(f"p.{quote(parts[k])}" for k in _DIAG_UT) + "]"
            lay.exprs["cov_diag"] = f"CASE WHEN p.{quote(parts[0])} IS NULL THEN NULL ELSE {diag} END"
    if lay.exprs.get("cov_diag", "").startswith("DIAG:"):          # cov_ut kept whole
        lay.exprs["cov_diag"] = "list_select(p.cov_ut, [1, 7, 12, 16, 19, 21])"


def _add_residuals(lay: Layout, columns: tuple[str, ...]) -> None:
    """Each narrowed column of ``columns`` read from the physical table alone gets its remainder
    ``<name>__res`` = trunc((value − float32 value) · RESIDUAL_UNITS) beside it, 0 where the
    float32 is not finite (NaN, ±inf, a value beyond float32's range: the float32 as it is), null
    where the value is null; the view adds it back."""
    for c in columns:
        if (c not in lay.orig.columns or lay.orig.schema[c] != pl.Float64 or lay.phys.schema.get(c) != pl.Float32
                or lay.exprs.get(c) != f"p.{quote(c)}"):
            continue
        hi = lay.phys[c].cast(pl.Float64)
        diff = (lay.orig[c] - hi) * RESIDUAL_UNITS
        res = pl.select(pl.when(hi.is_finite()).then(diff).otherwise(pl.when(hi.is_null()).then(None)
                                                                     .otherwise(0.0))
                        .fill_nan(0.0).cast(pl.Int64).alias(c + RESIDUAL_SUFFIX)).to_series()
        order = [x for col in lay.phys.columns for x in ((col, res.name) if col == c else (col,))]
        lay.phys = lay.phys.with_columns(res).select(order)
        lay.exprs[c] = (f"CAST(p.{quote(c)} AS DOUBLE) + CAST(p.{quote(res.name)} AS DOUBLE) "
                        f"/ CAST({RESIDUAL_UNITS} AS DOUBLE)")


def _drop_cov_diag(lay: Layout) -> None:
    """``cov_diag`` dropped when it is the diagonal of the (float32) ``cov_ut``, to round-off."""
    f = lay.phys
    if not {"cov_diag", "cov_ut"} <= set(f.columns) or f.schema["cov_ut"] != pl.Array(pl.Float32, 21) \
            or not isinstance(f.schema["cov_diag"], pl.Array) or f.schema["cov_diag"].size != 6:
        return
    d = f["cov_diag"].to_numpy().reshape(-1, 6) if f.height else np.empty((0, 6))
    ut = f["cov_ut"].to_numpy().reshape(-1, 21) if f.height else np.empty((0, 21))
    if f.height and (f["cov_diag"].null_count() or f["cov_ut"].null_count()):
        return
    diag = ut[:, _DIAG_UT].astype(np.float64)
    if not np.allclose(d, diag, rtol=_F32_RTOL, atol=0.0, equal_nan=True):
        return
    lay.phys = f.drop("cov_diag")
    lay.exprs["cov_diag"] = "DIAG:"


def _drop_report_columns(lay: Layout, con: duckdb.DuckDBPyConnection, reports_table: str) -> None:
    """Columns equal to the report's own (joined by report_id) dropped; ``age_s`` = epoch − time."""
    f = lay.phys
    have = {r[0] for r in con.execute(
        "SELECT column_name FROM duckdb_columns() WHERE database_name = current_database() "
        "AND schema_name = 'main' AND table_name = ?", [reports_table]).fetchall()}
    cols = [c for c in FROM_REPORTS[lay.name] if c in f.columns and c in have]
    if "report_id" not in f.columns or "report_id" not in have or not cols:
        return
    rt = quote(reports_table)
    probe = f.select("report_id", *cols, *(["epoch"] if "epoch" in f.columns else []),
                     *(["age_s"] if "age_s" in f.columns else []))
    # one pass for every column, over the reports this part names (a semi-join, not a report_id
    # range: a window's ids need not be contiguous, and a range spanning nearly the whole table
    # would make each part re-read it)
    tests = [f"count(*) FILTER (WHERE r.report_id IS NULL OR a.{quote(c)} IS DISTINCT FROM r.{quote(c)})" for c in cols]
    age_test = {"age_s", "epoch"} <= set(f.columns) and f.schema["age_s"] == pl.Float64
    if age_test:
        tests.append("count(*) FILTER (WHERE r.report_id IS NOT NULL AND NOT "
                     "(abs(a.age_s - date_diff('microsecond', r.time, a.epoch) / 1e6) <= 1e-9 "
                     "OR (a.age_s IS NULL AND r.time IS NULL)))")
    read = ", ".join(quote(c) for c in dict.fromkeys(["report_id", *cols, *(["time"] if age_test else [])]))
    with arrow_view(con, probe, "chk") as view:
        got = con.execute(f"SELECT count(*), {', '.join(tests)} FROM {view} a LEFT JOIN "
                          f"(SELECT {read} FROM {rt} WHERE report_id IN (SELECT report_id FROM {view})) r "
                          "USING (report_id)").fetchall()[0] if f.height else [0] * (len(tests) + 1)
    # the view's join is one to one for these rows when the left join kept their number: no
    # report_id of the part names two reports
    if got[0] != f.height:
        return
    bad = got[1:]
    same = [c for c, k in zip(cols, bad) if k == 0]
    age_ok = "time" in same and age_test and bad[-1] == 0
    if not same:
        return
    for c in same:
        lay.exprs[c] = f"r.{quote(c)}"
    if age_ok:
        lay.exprs["age_s"] = "date_diff('microsecond', r.time, p.epoch) / 1e6"
        same.append("age_s")
    lay.phys = f.drop(same)
    lay.joins_reports = reports_table


def _factor_shared(lay: Layout, keys: tuple[str, ...], by: str, own: str, candidates: tuple[str, ...]) -> None:
    """The ``candidates`` stored once per key for the keys whose rows (those whose ``by`` is not
    ``own``) hold one value of each (nulls included); the rows of any other key keep their own.
    Which columns are factored depends on the schema alone, so every part of a streamed table
    gets the layout of the whole (a key whose methods disagree, e.g. a primary-only target's
    height from each method's own position, costs its rows the saving, not the table's parts)."""
    f = lay.phys
    cols = [c for c in candidates if c in f.columns]
    if not set(keys) | {by} <= set(f.columns) or not cols:
        return
    mask = (f[by] != own).fill_null(True)
    sub = f.filter(mask)
    per_key = sub.select(*keys, *[pl.col(c).hash().alias(c) for c in cols]).group_by(keys).agg(
        pl.all_horizontal([pl.col(c).n_unique() == 1 for c in cols]).alias("__one"))
    agree = (f.select(keys).join(per_key, on=list(keys), how="left", nulls_equal=True, maintain_order="left")
             ["__one"].fill_null(False))
    shared_rows = mask & agree
    lay.shared = (f.filter(shared_rows).select(*keys, *cols)
                  .unique(subset=list(keys), keep="first", maintain_order=True))
    lay.shared_keys = keys
    lay.phys = f.with_columns(
        *[pl.when(shared_rows).then(None).otherwise(pl.col(c)).alias(c) for c in cols],
        shared_rows.alias(ROWS_FLAG))
    for c in cols:
        lay.exprs[c] = f"CASE WHEN p.{quote(ROWS_FLAG)} THEN s.{quote(c)} ELSE p.{quote(c)} END"


def column_types(con: duckdb.DuckDBPyConnection, frame: pl.DataFrame) -> dict[str, str]:
    """DuckDB's type name for each column of ``frame`` (as a plain table would store it)."""
    with arrow_view(con, frame.head(0), "typ") as view:
        return {r[0]: r[1] for r in con.execute(f"DESCRIBE SELECT * FROM {view}").fetchall()}


@contextmanager
def arrow_view(con: duckdb.DuckDBPyConnection, frame: pl.DataFrame, kind: str) -> Iterator[str]:
    """``frame`` registered (as Arrow) under a unique view name for the block. When the block
    fails inside a transaction DuckDB refuses the unregistration, and its error ("Current
    transaction is aborted") hid the failure's own: it is not raised, and the rollback undoes
    the registration made inside the transaction."""
    view = f"_tertiary_{kind}_{secrets.token_hex(6)}"
    con.register(view, frame.to_arrow())
    try:
        yield view
    except BaseException:
        with contextlib.suppress(duckdb.Error):
            con.unregister(view)
        raise
    con.unregister(view)


def layout_signature(lay: Layout) -> tuple:
    """What decides a lean table's physical form and view: two parts with equal signatures can
    share one physical table."""
    return (lay.phys.schema, None if lay.shared is None else lay.shared.schema, tuple(lay.exprs.items()),
            lay.joins_reports, lay.shared_keys)


def view_sql(lay: Layout, types: dict[str, str], phys: str, shared: str | None) -> str:
    cols = ",\n       ".join(f"CAST({lay.exprs[c]} AS {types[c]}) AS {quote(c)}" for c in lay.orig.columns)
    sql = f"SELECT {cols}\nFROM {quote(phys)} AS p"
    if lay.joins_reports:
        sql += f"\nLEFT JOIN {quote(lay.joins_reports)} AS r ON r.report_id = p.report_id"
    if shared is not None:
        on = " AND ".join(f"s.{quote(k)} = p.{quote(k)}" for k in lay.shared_keys)
        sql += f"\nLEFT JOIN {quote(shared)} AS s ON p.{quote(ROWS_FLAG)} AND {on}"
    return sql + "\nORDER BY p.rowid"
