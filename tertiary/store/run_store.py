"""Run store: one embedded DuckDB database per run (``RUN_DIR/results.duckdb``).

Every write is atomic at file level: writers build a new database in a temp file
next to ``results.duckdb`` and ``os.replace`` it into place only on success, so a
reader sees either the old or the new database, never a half-written one.

Usage::

    with RunStore.create(run_dir) as store:      # brand-new database
        store.write("reports", reports)
    with RunStore.update(run_dir) as store:      # copy, modify, replace
        store.write("tracks", tracks)
    with RunStore.open(run_dir) as store:        # read-only
        df = store.sql("SELECT * FROM tracks WHERE track_id = ?", [7])

Polars <-> DuckDB goes through Arrow. Dtype round trips (duckdb 2.0, polars 2.1):

* ``Datetime(us, "UTC")`` -> ``TIMESTAMP WITH TIME ZONE`` -> ``Datetime(us, "UTC")``.
  The connection's ``TimeZone`` is pinned to ``'UTC'``; otherwise DuckDB labels
  the column with the machine's zone (e.g. ``'Etc/UTC'``). Any other zone, or
  ``ms`` unit, comes back as ``Datetime(us, "UTC")`` (same instants);
  ``Datetime(ns, "UTC")`` stays ``ns`` (``TIMESTAMPTZ_NS``). Naive datetimes keep
  their unit and stay naive.
* ``Array(Float64, 36)`` -> ``DOUBLE[36]`` -> ``Array(Float64, 36)`` (not List).
* ``List(Float64)`` / ``List(UInt64)`` -> ``DOUBLE[]`` / ``UBIGINT[]`` -> unchanged.
* Unsigned ints, NaN, nulls, Struct, Decimal, Binary, Time round-trip exactly.
* ``Categorical`` / ``Enum`` come back as ``String``.
* ``Duration`` is rejected on write: DuckDB stores it as ``INTERVAL``, which
  polars cannot read back. ``Int128`` cannot be exported to Arrow by polars.

The database is ATTACHed to a fresh in-memory connection rather than opened with
``duckdb.connect(path)``: DuckDB caches instances by path within a process, so a
second ``connect`` to a replaced file would silently see the old database while
any earlier connection to that path is still open.

A table may also be *registered* rather than copied (:meth:`RunStore.register_parquet`,
``tertiary run --tables parquet``): its Parquet files are kept in ``RUN_DIR/tables/<name>/`` and
the database holds a view reading them in place, by a path relative to the run directory. Every
connection made here searches the run directory for it (DuckDB's ``file_search_path``); a DuckDB
shell opened elsewhere needs ``SET file_search_path = 'RUN_DIR'`` first.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import duckdb
import numpy as np
import polars as pl

try:  # POSIX only; on other platforms writers are not serialised across processes.
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "DB_FILENAME",
    "RunStore",
    "atomic_path",
    "export_parquet",
    "record_run",
    "validate_name",
    "write_parquet_atomic",
    "write_text_atomic",
]

DB_FILENAME = "results.duckdb"
_ALIAS = "run"
#: the directory of a run's registered Parquet tables (:meth:`RunStore.register_parquet`)
TABLES_DIR = "tables"
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_HELD_LOCKS: set[str] = set()
_HELD_GUARD = threading.Lock()

Params = Sequence[Any] | Mapping[str, Any] | None
_T = TypeVar("_T")


# --------------------------------------------------------------------------- files


def _temp_sibling(path: Path) -> Path:
    """A fresh temp name in ``path``'s directory: ``<name>.tmp-<pid>-<random>``."""
    return path.with_name(f"{path.name}.tmp-{os.getpid()}-{secrets.token_hex(6)}")


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    if os.name != "posix":  # pragma: no cover - directories cannot be opened on Windows
        return
    _fsync_file(path)


def _remove(path: Path) -> None:
    """Remove a file or directory if present; never raise for a missing one."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temp path next to ``path``; on success fsync and rename it onto ``path``.

    On an exception the temp file is removed and ``path`` is left untouched.
    The parent directory is created if missing.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(final)
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, final)
    except BaseException:
        _remove(tmp)
        raise
    _fsync_dir(final.parent)


def write_parquet_atomic(frame: pl.DataFrame, path: str | os.PathLike[str], **kwargs: Any) -> Path:
    """Write ``frame`` to ``path`` as Parquet atomically; kwargs go to ``write_parquet``."""
    with atomic_path(path) as tmp:
        frame.write_parquet(tmp, **kwargs)
    return Path(path)


def write_text_atomic(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(path)


# --------------------------------------------------------------------------- helpers


def validate_name(name: str) -> str:
    """Return ``name`` if it is a plain SQL identifier, else raise ValueError."""
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f"invalid table name {name!r}: use letters, digits and '_' only")
    return name


def _has_duration(dtype: pl.DataType) -> bool:
    if isinstance(dtype, pl.Duration):
        return True
    if isinstance(dtype, pl.List | pl.Array):
        return _has_duration(dtype.inner)
    if isinstance(dtype, pl.Struct):
        return any(_has_duration(f.dtype) for f in dtype.fields)
    return False


def _check_frame(frame: pl.DataFrame) -> None:
    if frame.width == 0:
        raise ValueError("cannot store a frame with no columns")
    bad = [c for c, t in frame.schema.items() if _has_duration(t)]
    if bad:
        raise TypeError(f"Duration columns {bad} cannot be read back from DuckDB; cast to Int64 first")


def utc_times(frame: pl.DataFrame) -> pl.DataFrame:
    """Relabel top-level tz-aware columns to 'UTC' (in case the session zone changed)."""
    fix = [
        pl.col(c).dt.convert_time_zone("UTC")
        for c, t in frame.schema.items()
        if isinstance(t, pl.Datetime) and t.time_zone not in (None, "UTC")
    ]
    return frame.with_columns(fix) if fix else frame


def _db_file(path: str | os.PathLike[str]) -> Path:
    """``path`` itself if it is a file, else ``path/results.duckdb``."""
    p = Path(path)
    return p if p.is_file() else p / DB_FILENAME


#: the buffer pool of a connection that writes a run database (MiB) ...
WRITER_MEMORY_MB = 64
WRITER_MEMORY_LIMIT = f"{WRITER_MEMORY_MB}MB"
#: ... and the most it is raised to for a table too wide for it (:meth:`RunStore._sized`)
WRITER_MEMORY_MAX_MB = 4096


def _connect(db_file: Path, read_only: bool, spill_dir: Path) -> duckdb.DuckDBPyConnection:
    """A fresh in-memory connection with ``db_file`` attached as the default catalog."""
    con = duckdb.connect(":memory:", config={"temp_directory": str(spill_dir)})
    try:
        con.execute("SET TimeZone = 'UTC'")
        con.execute("SET enable_progress_bar = false")   # the CLI draws its own progress
        # registered tables are views over files named relative to the run directory; a relative
        # path in a query is still found from the working directory (searched second)
        search = ",".join((str(db_file.resolve().parent), os.getcwd()))
        con.execute(f"SET file_search_path = {_literal(search)}")
        if not read_only:
            # a writer keeps every block it wrote in its buffer pool (default: 80 % of RAM), so
            # without a cap the process grows by the database's size (~275 MB for a 4 h
            # production run); written blocks are on disk, and larger work spills to temp_directory.
            # The pool stays full while the run's evaluation runs beside the open store, so its
            # size adds to the run's peak: 64 MB (was 256: 4 h production peak 1 312 -> 1 141 MiB,
            # same wall time)
            con.execute(f"SET memory_limit = '{WRITER_MEMORY_LIMIT}'")
        mode = " (READ_ONLY)" if read_only else ""
        con.execute(f"ATTACH ? AS {_ALIAS}{mode}", [str(db_file)])
        con.execute(f"USE {_ALIAS}")
    except BaseException:
        con.close()
        raise
    return con


@contextmanager
def _writer_lock(run_dir: Path) -> Iterator[None]:
    """Serialise writers of one run directory (flock across processes, error within one)."""
    key = str(run_dir.resolve())
    with _HELD_GUARD:
        if key in _HELD_LOCKS:
            raise RuntimeError(f"a RunStore writer is already open on {run_dir} in this process")
        _HELD_LOCKS.add(key)
    fd = os.open(run_dir, os.O_RDONLY) if fcntl is not None else None
    try:
        if fd is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        if fd is not None:
            os.close(fd)  # releases the flock
        with _HELD_GUARD:
            _HELD_LOCKS.discard(key)


# --------------------------------------------------------------------------- store


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


# --------------------------------------------------------------------------- lean layout
#
# The run's large tables are stored in a lean physical layout ``_lean_<name>`` (+ ``_lean_<name>__shared``)
# behind a view ``<name>`` with the original column names, order and types, so every SQL report
# and reader sees the table it always saw. What the layout drops is exactly recoverable (to float32
# round-off where a column is narrowed); each rule is checked on the data before it is applied and
# a column that fails its check is stored as it came:
#
# ``conflicts`` (already slim: alerts and near pairs only) stays a plain table: tools drop it with
# DROP TABLE to test a run without safety, and float32 would save only 2.6 MB on the default job.
#
# * NARROW: float64 columns holding metres / m/s / s-scale quantities, variances, weights and
#   probabilities stored as float32 (7 significant digits: 0.008 m at 100 km, 0.06 m at 1 000 km,
#   3e-5 m/s at 300 m/s, 1e-7 relative on a variance) — far below any radar's metres-scale error;
#   the view casts them back to DOUBLE. Inputs (``reports``, ``truth``) are never narrowed.
# * fixed-size float arrays (``cov_ut`` FLOAT[21], ``meas_cov``, ``nominal_var``) stored as one
#   column per element: each element column is homogeneous in scale, so DuckDB's ALP/ALPRD
#   compress it (a FLOAT[21] column interleaves variances and cross terms and barely compresses).
# * DERIVED: ``tracks.cov_diag`` is the diagonal of ``cov``; ``aligned.age_s`` is epoch − time.
# * FROM_REPORTS: ``aligned`` repeats each report's columns (run, radar_id, local_track_id, time,
#   residuals, mode_s, truth_id, altitude_m) on every epoch it is aligned to; the view joins them
#   from ``reports`` by ``report_id`` (checked equal before they are dropped).
# * SHARED: in ``fused`` the columns that do not depend on the fusion method (the vertical
#   channel, freshness, identity, sources) are stored once per (run, epoch, target_id) in
#   ``_lean_fused__shared`` for the rows of every method but ``centralized`` (checked constant).

LEAN_PREFIX = "_lean_"
_ROWS_FLAG = "__shared"
_F32_RTOL = 2e-7      # float32 keeps 24 bits: relative round-off ≤ 2⁻²⁴ ≈ 6e-8 (with margin)

_NARROW: dict[str, tuple[str, ...]] = {
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
_SPLIT = ("reports", "aligned", "fused", "tracks")
_FROM_REPORTS = {"aligned": ("run", "radar_id", "local_track_id", "time", "res_range_m", "res_range_var_m2",
                             "mode_s", "truth_id", "altitude_m")}
_SHARED = {"fused": (("run", "epoch", "target_id"), "method", "centralized",
                     ("n_sources", "radar_ids", "mode_s", "n_fresh", "age_s", "tentative", "alt_m", "alt_rate_mps",
                      "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps"))}
_DIAG_UT = [0, 6, 11, 15, 18, 20]       # positions of the diagonal in a row-major 6×6 upper triangle


def _literal(text: str) -> str:
    """``text`` as an SQL string literal."""
    return "'" + text.replace("'", "''") + "'"


def _q(name: str) -> str:
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


class _Layout:
    """The physical frame(s) of one lean table and the view's select list over them."""

    def __init__(self, name: str, frame: pl.DataFrame) -> None:
        self.name, self.orig = name, frame
        self.phys = frame
        self.exprs: dict[str, str] = {c: f"p.{_q(c)}" for c in frame.columns}
        self.shared: pl.DataFrame | None = None
        self.shared_keys: tuple[str, ...] = ()
        self.joins_reports: str | None = None

    @property
    def changed(self) -> bool:
        return self.phys.schema != self.orig.schema or self.shared is not None or self.joins_reports


def _lean_layout(name: str, frame: pl.DataFrame, con: duckdb.DuckDBPyConnection,
                 reports_table: str | None) -> _Layout:
    lay = _Layout(name, frame)
    if name in _FROM_REPORTS and reports_table is not None:
        _drop_report_columns(lay, con, reports_table)
    if name in _SHARED:
        _factor_shared(lay, *_SHARED[name])
    if name == "tracks":
        _drop_cov_diag(lay)
    narrow = [c for c in _NARROW.get(name, ()) if c in lay.phys.columns and _narrowed(lay.phys.schema[c])]
    lay.phys = lay.phys.with_columns(pl.col(c).cast(_narrowed(lay.phys.schema[c])) for c in narrow)
    if lay.shared is not None:
        sn = [c for c in narrow if c in lay.shared.columns]
        lay.shared = lay.shared.with_columns(pl.col(c).cast(_narrowed(lay.shared.schema[c])) for c in sn)
    if name in _SPLIT:
        _split_arrays(lay)
    return lay


def _split_arrays(lay: _Layout) -> None:
    """Fixed-size float arrays -> one column per element (nulls kept as a null first element)."""
    for c, dtype in list(lay.phys.schema.items()):
        if c not in lay.orig.columns or not _splittable(lay.phys, c):
            continue
        parts = [f"{c}__{k}" for k in range(dtype.size)]
        cols = [pl.col(c).arr.get(k).alias(p) for k, p in enumerate(parts)]
        order = [x for col in lay.phys.columns for x in (parts if col == c else [col])]
        lay.phys = lay.phys.with_columns(cols).select(order)
        arr = "[" + ", ".join(f"p.{_q(x)}" for x in parts) + "]"
        lay.exprs[c] = f"CASE WHEN p.{_q(parts[0])} IS NULL THEN NULL ELSE {arr} END"
        if lay.exprs.get("cov_diag", "").startswith("DIAG:") and c == "cov_ut":
            diag = "[" + ", ".join(f"p.{_q(parts[k])}" for k in _DIAG_UT) + "]"
            lay.exprs["cov_diag"] = f"CASE WHEN p.{_q(parts[0])} IS NULL THEN NULL ELSE {diag} END"
    if lay.exprs.get("cov_diag", "").startswith("DIAG:"):          # cov_ut kept whole
        lay.exprs["cov_diag"] = "list_select(p.cov_ut, [1, 7, 12, 16, 19, 21])"


def _drop_cov_diag(lay: _Layout) -> None:
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


def _drop_report_columns(lay: _Layout, con: duckdb.DuckDBPyConnection, reports_table: str) -> None:
    """Columns equal to the report's own (joined by report_id) dropped; ``age_s`` = epoch − time."""
    f = lay.phys
    have = {r[0] for r in con.execute(
        "SELECT column_name FROM duckdb_columns() WHERE database_name = current_database() "
        "AND schema_name = 'main' AND table_name = ?", [reports_table]).fetchall()}
    cols = [c for c in _FROM_REPORTS[lay.name] if c in f.columns and c in have]
    if "report_id" not in f.columns or "report_id" not in have or not cols:
        return
    rt = _q(reports_table)
    probe = f.select("report_id", *cols, *(["epoch"] if "epoch" in f.columns else []),
                     *(["age_s"] if "age_s" in f.columns else []))
    # one pass for every column, over the reports this part names (a semi-join, not a report_id
    # range: a window's ids need not be contiguous — the national scenario's span nearly the
    # whole table, and a range made each part re-read it: 32 s of its hour, issue 18)
    tests = [f"count(*) FILTER (WHERE r.report_id IS NULL OR a.{_q(c)} IS DISTINCT FROM r.{_q(c)})" for c in cols]
    age_test = {"age_s", "epoch"} <= set(f.columns) and f.schema["age_s"] == pl.Float64
    if age_test:
        tests.append("count(*) FILTER (WHERE r.report_id IS NOT NULL AND NOT "
                     "(abs(a.age_s - date_diff('microsecond', r.time, a.epoch) / 1e6) <= 1e-9 "
                     "OR (a.age_s IS NULL AND r.time IS NULL)))")
    read = ", ".join(_q(c) for c in dict.fromkeys(["report_id", *cols, *(["time"] if age_test else [])]))
    with _arrow_view(con, probe, "chk") as view:
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
        lay.exprs[c] = f"r.{_q(c)}"
    if age_ok:
        lay.exprs["age_s"] = "date_diff('microsecond', r.time, p.epoch) / 1e6"
        same.append("age_s")
    lay.phys = f.drop(same)
    lay.joins_reports = reports_table


def _factor_shared(lay: _Layout, keys: tuple[str, ...], by: str, own: str, candidates: tuple[str, ...]) -> None:
    """Columns constant within each key among the rows whose ``by`` is not ``own`` stored once per key."""
    f = lay.phys
    if not set(keys) | {by} <= set(f.columns) or f.height == 0:
        return
    mask = f[by] != own
    sub = f.filter(mask.fill_null(True))
    cols = [c for c in candidates if c in f.columns]
    if not cols or sub.height == 0:
        return
    # a column is shared when every key holds one value (nulls included) among those rows
    per_key = sub.select(*keys, *[pl.col(c).hash().alias(c) for c in cols]).group_by(keys).agg(
        [pl.col(c).n_unique().alias(c) for c in cols])
    cols = [c for c in cols if per_key.height == 0 or per_key[c].max() == 1]
    if not cols:
        return
    shared_rows = mask.fill_null(True)
    lay.shared = sub.select(*keys, *cols).unique(subset=list(keys), keep="first", maintain_order=True)
    lay.shared_keys = keys
    lay.phys = f.with_columns(
        *[pl.when(shared_rows).then(None).otherwise(pl.col(c)).alias(c) for c in cols],
        shared_rows.alias(_ROWS_FLAG))
    for c in cols:
        lay.exprs[c] = f"CASE WHEN p.{_q(_ROWS_FLAG)} THEN s.{_q(c)} ELSE p.{_q(c)} END"


def _column_types(con: duckdb.DuckDBPyConnection, frame: pl.DataFrame) -> dict[str, str]:
    """DuckDB's type name for each column of ``frame`` (as a plain table would store it)."""
    with _arrow_view(con, frame.head(0), "typ") as view:
        return {r[0]: r[1] for r in con.execute(f"DESCRIBE SELECT * FROM {view}").fetchall()}


@contextmanager
def _arrow_view(con: duckdb.DuckDBPyConnection, frame: pl.DataFrame, kind: str) -> Iterator[str]:
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


def _signature(lay: _Layout) -> tuple:
    """What decides a lean table's physical form and view: two parts with equal signatures can
    share one physical table."""
    return (lay.phys.schema, None if lay.shared is None else lay.shared.schema, tuple(lay.exprs.items()),
            lay.joins_reports, lay.shared_keys)


def _view_sql(lay: _Layout, types: dict[str, str], phys: str, shared: str | None) -> str:
    cols = ",\n       ".join(f"CAST({lay.exprs[c]} AS {types[c]}) AS {_q(c)}" for c in lay.orig.columns)
    sql = f"SELECT {cols}\nFROM {_q(phys)} AS p"
    if lay.joins_reports:
        sql += f"\nLEFT JOIN {_q(lay.joins_reports)} AS r ON r.report_id = p.report_id"
    if shared is not None:
        on = " AND ".join(f"s.{_q(k)} = p.{_q(k)}" for k in lay.shared_keys)
        sql += f"\nLEFT JOIN {_q(shared)} AS s ON p.{_q(_ROWS_FLAG)} AND {on}"
    return sql + "\nORDER BY p.rowid"


class RunStore:
    """One run's DuckDB database. Build with ``create``, ``update`` or ``open``."""

    def __init__(self, db_file: Path, *, read_only: bool, lean: bool = True) -> None:
        self.path = Path(db_file)
        self.read_only = read_only
        #: write the run's large tables in the lean layout (False: every table stored as given)
        self.lean = lean
        self._spill = Path(tempfile.gettempdir()) / f"tertiary-duckdb-{os.getpid()}-{secrets.token_hex(6)}"
        self._con = _connect(self.path, read_only, self._spill)

    # ---- constructors

    @classmethod
    def open(cls, run_dir: str | os.PathLike[str], read_only: bool = True) -> RunStore:
        """Open an existing run database (``run_dir`` or the .duckdb file itself).

        ``read_only=False`` writes in place (not atomic): prefer ``update``.
        """
        db_file = _db_file(run_dir)
        if not db_file.is_file():
            raise FileNotFoundError(f"no run database at {db_file}")
        return cls(db_file, read_only=read_only)

    @classmethod
    @contextmanager
    def create(cls, run_dir: str | os.PathLike[str], *, lean: bool = True) -> Iterator[RunStore]:
        """Build a new ``run_dir/results.duckdb``; it replaces any old one only on success.

        ``lean=False`` stores every table as given (no lean layout: the reference it is checked against)."""
        with cls._staged(Path(run_dir), seed=False, lean=lean) as store:
            yield store

    @classmethod
    @contextmanager
    def update(cls, run_dir: str | os.PathLike[str], *, lean: bool = True) -> Iterator[RunStore]:
        """Copy the existing database, yield it for changes, atomically replace on success."""
        if not (Path(run_dir) / DB_FILENAME).is_file():
            raise FileNotFoundError(f"no run database at {Path(run_dir) / DB_FILENAME}")
        with cls._staged(Path(run_dir), seed=True, lean=lean) as store:
            yield store

    @classmethod
    @contextmanager
    def _staged(cls, run_dir: Path, *, seed: bool, lean: bool = True) -> Iterator[RunStore]:
        """Writer on a temp copy (empty or seeded) that is checkpointed and renamed on success."""
        run_dir.mkdir(parents=True, exist_ok=True)
        final = run_dir / DB_FILENAME
        with _writer_lock(run_dir), atomic_path(final) as tmp:
            sidecars = [Path(f"{tmp}.wal"), Path(f"{tmp}.tmp")]
            try:
                if seed:
                    _copy_database(final, tmp)
                store = cls(tmp, read_only=False, lean=lean)
                try:
                    yield store
                    store.con.execute(f"CHECKPOINT {_ALIAS}")
                finally:
                    store.close()
                if sidecars[0].exists():
                    raise RuntimeError(f"write-ahead log left after checkpoint: {sidecars[0]}")
            finally:
                for extra in sidecars:
                    _remove(extra)

    # ---- lifecycle

    @property
    def con(self) -> duckdb.DuckDBPyConnection:
        """The DuckDB connection (the run database is its default catalog)."""
        return self._con

    def close(self) -> None:
        """Close the connection and drop its spill directory."""
        self._con.close()
        _remove(self._spill)

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        mode = "ro" if self.read_only else "rw"
        return f"RunStore({str(self.path)!r}, {mode})"

    # ---- tables

    def tables(self) -> list[str]:
        """Names of the run's tables, sorted (a lean table's view, never its physical parts)."""
        rows = self._con.sql(
            "SELECT table_name FROM duckdb_tables() "
            "WHERE database_name = current_database() AND schema_name = 'main' AND NOT temporary "
            f"AND NOT starts_with(table_name, '{LEAN_PREFIX}') "
            "UNION SELECT view_name FROM duckdb_views() "
            "WHERE database_name = current_database() AND schema_name = 'main' AND NOT temporary AND NOT internal "
            "ORDER BY 1"
        ).fetchall()
        return [r[0] for r in rows]

    def write(self, name: str, frame: pl.DataFrame) -> None:
        """Create or replace table ``name`` with ``frame`` (one transaction); covariance
        columns are stored compactly (:func:`compact_covariances`) and the run's large tables
        in their lean layout behind a view of the same name (see "lean layout" above)."""
        self._sized(lambda: self._write(name, frame))

    def _write(self, name: str, frame: pl.DataFrame) -> None:
        frame = compact_covariances(frame)
        table = self._writable(name, frame)
        lay = _lean_layout(name, frame, self._con, self._reports_for(name)) if self.lean else None
        drops = self._drop_statements(name)
        if lay is None or not lay.changed:
            with self._registered(frame) as src:
                self._transaction(*drops, f"CREATE TABLE {table} AS SELECT * FROM {src}")
            return
        phys = LEAN_PREFIX + name
        shared = f"{phys}{_ROWS_FLAG}" if lay.shared is not None else None
        view = _view_sql(lay, _column_types(self._con, frame), phys, shared)
        with self._registered(lay.phys) as src, self._registered(
                lay.shared if lay.shared is not None else pl.DataFrame({"x": [0]})) as src_s:
            stmts = [*drops, f"CREATE TABLE {_q(phys)} AS SELECT * FROM {src}"]
            if shared is not None:
                stmts.append(f"CREATE TABLE {_q(shared)} AS SELECT * FROM {src_s}")
            self._transaction(*stmts, f"CREATE VIEW {table} AS {view}")

    def write_files(self, name: str, files: Sequence[str | os.PathLike[str]], drop: Sequence[str] = ()) -> bool:
        """Create or replace table ``name`` with the rows of the Parquet ``files`` in order,
        without the ``drop`` columns, in one statement read by DuckDB itself: a long table
        written from disk is never held in memory and is written in one pass (a table appended a
        part at a time left 155 MB of freed blocks in a national hour's database). False, and
        nothing written, for a table with a lean layout rule or one too wide for the writer's
        buffer pool (:meth:`write_parts` then)."""
        if self.lean and any(name in rules for rules in (_NARROW, _SPLIT, _FROM_REPORTS, _SHARED)):
            return False
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        table = f'"{validate_name(name)}"'
        paths = [str(Path(f)) for f in files]
        exclude = f" EXCLUDE ({', '.join(_q(c) for c in drop)})" if drop else ""
        try:
            self._transaction(*self._drop_statements(name),
                              (f"CREATE TABLE {table} AS SELECT *{exclude} FROM read_parquet(?)", [paths]))
        except duckdb.OutOfMemoryException:
            # DuckDB's scan builds a table's row groups in its buffer pool, a few MiB a column:
            # the writer's WRITER_MEMORY_LIMIT holds about 20 columns, and a truth with 30 extra
            # columns stopped the run here. Rolled back; the parts go through Arrow instead
            return False
        return True

    def register_parquet(self, name: str, files: Sequence[str | os.PathLike[str]],
                         drop: Sequence[str] = ()) -> int:
        """Table ``name`` as a view over the rows of the Parquet ``files`` in order (without the
        ``drop`` columns), which are kept in ``RUN_DIR/tables/<name>/`` and read in place: nothing
        is copied into the database (issue 18, scale: a national day's streamed tables are ~50 GB
        of Parquet that a copy would nearly double, and the copy was a run's longest write).
        The files are hard-linked there (copied where the file system cannot link), numbered in
        order; a previous registration's files are replaced. Files without rows are left out
        (an empty window may lack optional columns); the view keeps the files' column types,
        fixed-size arrays as arrays. Returns the number of rows."""
        import pyarrow.parquet as pq
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        table = f'"{validate_name(name)}"'
        rows = [pq.ParquetFile(f).metadata.num_rows for f in files]
        keep = [Path(f) for f, n in zip(files, rows) if n] or [Path(f) for f in files[:1]]
        if not keep:
            raise ValueError(f"no Parquet file to register as {name!r}")
        dest = self.path.parent / TABLES_DIR / name
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        for i, f in enumerate(keep):
            _link_or_copy(f, dest / f"part-{i:06d}.parquet")
        glob = f"{TABLES_DIR}/{name}/part-*.parquet"
        # DuckDB reads a fixed-size list from Parquet as a list: cast back to the array it was
        fixed = {c: t for f in keep for c, t in pl.read_parquet_schema(f).items() if isinstance(t, pl.Array)}
        scan = f"read_parquet({_literal(glob)}, union_by_name = true)"
        cols = []
        for c, kind, *_ in self._con.execute(f"DESCRIBE SELECT * FROM {scan}").fetchall():
            if c in drop:
                continue
            t = fixed.get(c)
            if t is not None and kind.endswith("[]"):
                cols.append(f"CAST({_q(c)} AS {kind[:-2]}[{t.size}]) AS {_q(c)}")
            else:
                cols.append(_q(c))
        self._transaction(*self._drop_statements(name),
                          f"CREATE VIEW {table} AS SELECT {', '.join(cols)} FROM {scan}")
        return int(sum(rows))

    def write_parts(self, name: str, parts: Callable[[], Iterable[pl.DataFrame]]) -> None:
        """:meth:`write` of the concatenation of the frames ``parts()`` yields, holding one part
        in memory at a time (a streamed table, window by window: issue 16, memory).

        Each part gets its own lean layout; when every part's layout is the first one's (the
        layout rules are row-wise checks, so this is exactly when the whole table's layout is
        that one) the parts are appended to it in order, in one transaction: the same table as
        :meth:`write` of the whole. Otherwise the parts are concatenated and written whole."""
        done = self._sized(lambda: self._try_parts(name, parts))
        if not done:
            frames = [f for f in parts() if f.width]
            if frames:
                self.write(name, pl.concat(frames, how="diagonal_relaxed") if len(frames) > 1 else frames[0])

    def _try_parts(self, name: str, parts: Callable[[], Iterable[pl.DataFrame]]) -> bool:
        it = iter(parts())
        first = next((f for f in it if f.height), None)
        if first is None:            # no rows: written whole (a schema-only frame, or nothing)
            return False
        frame = compact_covariances(first)
        table = self._writable(name, frame)
        lay = _lean_layout(name, frame, self._con, self._reports_for(name)) if self.lean else None
        lean = lay is not None and lay.changed
        phys = LEAN_PREFIX + name if lean else validate_name(name)
        shared = f"{phys}{_ROWS_FLAG}" if lean and lay.shared is not None else None
        sign = _signature(lay) if lean else frame.schema
        self._con.begin()
        try:
            for stmt in self._drop_statements(name):
                self._con.execute(stmt)
            self._insert(phys, lay.phys if lean else frame, create=True)
            if shared is not None:
                self._insert(shared, lay.shared, create=True)
            if lean:
                self._con.execute(f"CREATE VIEW {table} AS "
                                  + _view_sql(lay, _column_types(self._con, frame), phys, shared))
            del first, frame
            for part in it:
                if part.width == 0 or part.height == 0:
                    continue
                _check_frame(part)
                part = compact_covariances(part)
                lp = _lean_layout(name, part, self._con, self._reports_for(name)) if lean else None
                if (_signature(lp) if lean else part.schema) != sign:
                    self._con.rollback()
                    return False
                self._insert(phys, lp.phys if lean else part, create=False)
                if shared is not None:
                    self._insert(shared, lp.shared, create=False)
        except BaseException:
            self._con.rollback()
            raise
        self._con.commit()
        return True

    def _insert(self, table: str, frame: pl.DataFrame, create: bool) -> None:
        with self._registered(frame) as src:
            self._con.execute(f"CREATE TABLE {_q(table)} AS SELECT * FROM {src}" if create
                              else f"INSERT INTO {_q(table)} SELECT * FROM {src}")

    def append(self, name: str, frame: pl.DataFrame) -> None:
        """Append ``frame`` to table ``name`` (matched by column name), creating it if absent.

        A table in the lean layout is read back, extended and rewritten (its layout is decided
        on the whole table)."""
        if self._kind(name) == "VIEW":
            old = self.read(name)
            self.write(name, pl.concat([old, frame.select(old.columns) if set(frame.columns) == set(old.columns)
                                        else frame], how="diagonal_relaxed"))
            return
        frame = compact_covariances(frame)
        table = self._writable(name, frame)

        def append() -> None:
            with self._registered(frame) as src:
                self._transaction(
                    f"CREATE TABLE IF NOT EXISTS {table} AS SELECT * FROM {src} WITH NO DATA",
                    f"INSERT INTO {table} BY NAME SELECT * FROM {src}",
                )
        self._sized(append)

    def _sized(self, write: Callable[[], _T]) -> _T:
        """``write()`` (one transaction), again with a buffer pool four times larger each time
        DuckDB runs out of it, up to :data:`WRITER_MEMORY_MAX_MB`; the pool is then set back.
        DuckDB builds a row group of 122 880 rows in the pool before writing it: 64 MB held 80
        float64 columns but not 100 (reports with 70 extra columns stopped a run with
        OutOfMemoryException), and a larger pool for every table would hold the blocks written
        in it (the run's peak)."""
        mb = WRITER_MEMORY_MB
        try:
            while True:
                try:
                    return write()
                except duckdb.OutOfMemoryException:
                    if mb >= WRITER_MEMORY_MAX_MB:
                        raise
                    mb = min(4 * mb, WRITER_MEMORY_MAX_MB)
                    self._con.execute(f"SET memory_limit = '{mb}MB'")
        finally:
            if mb != WRITER_MEMORY_MB:
                self._con.execute(f"SET memory_limit = '{WRITER_MEMORY_LIMIT}'")

    def read(self, name: str) -> pl.DataFrame:
        """Table ``name`` as a polars DataFrame; KeyError if absent."""
        validate_name(name)
        if name not in self.tables():
            raise KeyError(f"no table {name!r} in {self.path}")
        return expand_covariances(utc_times(self._con.sql(f'SELECT * FROM "{name}"').pl()))

    def sql(self, query: str, params: Params = None) -> pl.DataFrame:
        """Run ``query`` with bound ``params`` (``?``/``$1`` list or ``$name`` dict).

        Returns the last statement's result; DDL/DML give DuckDB's one-row ``Count``
        frame, statements with no result (e.g. ``SET``) an empty frame.
        """
        rel = self._con.sql(query, params=params)
        return pl.DataFrame() if rel is None else utc_times(rel.pl())

    # ---- internals

    def _kind(self, name: str) -> str | None:
        """'BASE TABLE', 'VIEW' or None for ``name`` in the run database."""
        row = self._con.execute(
            "SELECT table_type FROM information_schema.tables WHERE table_catalog = current_database() "
            "AND table_schema = 'main' AND table_name = ?", [name]).fetchall()
        return row[0][0] if row else None

    def _drop_statements(self, name: str) -> list[str]:
        """Statements removing ``name`` (table or lean view with its physical parts)."""
        kind = self._kind(name)
        out = [f"DROP VIEW {_q(name)}"] if kind == "VIEW" else [f"DROP TABLE {_q(name)}"] if kind else []
        phys = LEAN_PREFIX + name
        return out + [f"DROP TABLE IF EXISTS {_q(phys)}", f"DROP TABLE IF EXISTS {_q(phys + _ROWS_FLAG)}"]

    def _reports_for(self, name: str) -> str | None:
        """The ``reports`` table a lean ``name`` may join its report columns from (None: none)."""
        return "reports" if name in _FROM_REPORTS and self._kind("reports") else None

    def _writable(self, name: str, frame: pl.DataFrame) -> str:
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        _check_frame(frame)
        return f'"{validate_name(name)}"'

    def _registered(self, frame: pl.DataFrame) -> contextlib.AbstractContextManager[str]:
        """Register ``frame`` (as Arrow) under a unique temp view name (:func:`_arrow_view`)."""
        return _arrow_view(self._con, frame, "src")

    def _transaction(self, *statements: str | tuple[str, Params]) -> None:
        """Run ``statements`` (SQL, or (SQL, parameters)) in one transaction."""
        self._con.begin()
        try:
            for stmt in statements:
                self._con.execute(*((stmt,) if isinstance(stmt, str) else stmt))
        except BaseException:
            self._con.rollback()
            raise
        self._con.commit()


def _link_or_copy(src: Path, dst: Path) -> None:
    """``dst`` as a hard link to ``src`` (no space taken), a copy where linking fails."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _copy_database(src: Path, dst: Path) -> None:
    """Copy a closed database file, plus any write-ahead log left beside it."""
    shutil.copyfile(src, dst)
    wal = Path(f"{src}.wal")
    if wal.exists():
        shutil.copyfile(wal, Path(f"{dst}.wal"))


# --------------------------------------------------------------------------- exports


def export_parquet(
    store_or_path: RunStore | str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    tables: Sequence[str] | None = None,
) -> list[Path]:
    """Write each table (default: all) to ``out_dir/<table>.parquet`` atomically."""
    if isinstance(store_or_path, RunStore):
        return _export(store_or_path, Path(out_dir), tables)
    with RunStore.open(store_or_path, read_only=True) as store:
        return _export(store, Path(out_dir), tables)


def _export(store: RunStore, out_dir: Path, tables: Sequence[str] | None) -> list[Path]:
    names = store.tables() if tables is None else [validate_name(t) for t in tables]
    return [write_parquet_atomic(store.read(t), out_dir / f"{t}.parquet") for t in names]


def record_run(store: RunStore, info: Mapping[str, Any]) -> None:
    """Replace the ``run`` table with ``info`` as key/value strings (non-str values JSON-encoded)."""
    keys = [str(k) for k in info]
    values = [v if isinstance(v, str) else json.dumps(v, default=str) for v in info.values()]
    store.write("run", pl.DataFrame({"key": keys, "value": values}, schema={"key": pl.String, "value": pl.String}))
