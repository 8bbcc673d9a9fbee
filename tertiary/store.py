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
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import tempfile
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

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
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_HELD_LOCKS: set[str] = set()
_HELD_GUARD = threading.Lock()

Params = Sequence[Any] | Mapping[str, Any] | None


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


def _connect(db_file: Path, read_only: bool, spill_dir: Path) -> duckdb.DuckDBPyConnection:
    """A fresh in-memory connection with ``db_file`` attached as the default catalog."""
    con = duckdb.connect(":memory:", config={"temp_directory": str(spill_dir)})
    try:
        con.execute("SET TimeZone = 'UTC'")
        con.execute("SET enable_progress_bar = false")   # the CLI draws its own progress
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


class RunStore:
    """One run's DuckDB database. Build with ``create``, ``update`` or ``open``."""

    def __init__(self, db_file: Path, *, read_only: bool) -> None:
        self.path = Path(db_file)
        self.read_only = read_only
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
    def create(cls, run_dir: str | os.PathLike[str]) -> Iterator[RunStore]:
        """Build a new ``run_dir/results.duckdb``; it replaces any old one only on success."""
        with cls._staged(Path(run_dir), seed=False) as store:
            yield store

    @classmethod
    @contextmanager
    def update(cls, run_dir: str | os.PathLike[str]) -> Iterator[RunStore]:
        """Copy the existing database, yield it for changes, atomically replace on success."""
        if not (Path(run_dir) / DB_FILENAME).is_file():
            raise FileNotFoundError(f"no run database at {Path(run_dir) / DB_FILENAME}")
        with cls._staged(Path(run_dir), seed=True) as store:
            yield store

    @classmethod
    @contextmanager
    def _staged(cls, run_dir: Path, *, seed: bool) -> Iterator[RunStore]:
        """Writer on a temp copy (empty or seeded) that is checkpointed and renamed on success."""
        run_dir.mkdir(parents=True, exist_ok=True)
        final = run_dir / DB_FILENAME
        with _writer_lock(run_dir), atomic_path(final) as tmp:
            sidecars = [Path(f"{tmp}.wal"), Path(f"{tmp}.tmp")]
            try:
                if seed:
                    _copy_database(final, tmp)
                store = cls(tmp, read_only=False)
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
        """Names of the run's tables, sorted."""
        rows = self._con.sql(
            "SELECT table_name FROM duckdb_tables() "
            "WHERE database_name = current_database() AND schema_name = 'main' AND NOT temporary "
            "ORDER BY table_name"
        ).fetchall()
        return [r[0] for r in rows]

    def write(self, name: str, frame: pl.DataFrame) -> None:
        """Create or replace table ``name`` with ``frame`` (one transaction); covariance
        columns are stored compactly (:func:`compact_covariances`)."""
        frame = compact_covariances(frame)
        table = self._writable(name, frame)
        with self._registered(frame) as src:
            self._transaction(f"CREATE OR REPLACE TABLE {table} AS SELECT * FROM {src}")

    def append(self, name: str, frame: pl.DataFrame) -> None:
        """Append ``frame`` to table ``name`` (matched by column name), creating it if absent."""
        frame = compact_covariances(frame)
        table = self._writable(name, frame)
        with self._registered(frame) as src:
            self._transaction(
                f"CREATE TABLE IF NOT EXISTS {table} AS SELECT * FROM {src} WITH NO DATA",
                f"INSERT INTO {table} BY NAME SELECT * FROM {src}",
            )

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

    def _writable(self, name: str, frame: pl.DataFrame) -> str:
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        _check_frame(frame)
        return f'"{validate_name(name)}"'

    @contextmanager
    def _registered(self, frame: pl.DataFrame) -> Iterator[str]:
        """Register ``frame`` (as Arrow) under a unique temp view name."""
        view = f"_tertiary_src_{secrets.token_hex(6)}"
        self._con.register(view, frame.to_arrow())
        try:
            yield view
        finally:
            self._con.unregister(view)

    def _transaction(self, *statements: str) -> None:
        self._con.begin()
        try:
            for stmt in statements:
                self._con.execute(stmt)
        except BaseException:
            self._con.rollback()
            raise
        self._con.commit()


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
