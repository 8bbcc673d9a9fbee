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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import duckdb
import polars as pl
import pyarrow.parquet as pq

from tertiary.store.files import atomic_path, remove_path, write_parquet_atomic, write_text_atomic
from tertiary.store.layout import (FROM_REPORTS, LEAN_PREFIX, NARROW, ROWS_FLAG, SHARED, SPLIT, arrow_view,
                                   column_types, compact_covariances, expand_covariances, layout_signature,
                                   lean_layout, quote, sql_literal, view_sql)

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
#: the pool a checkpoint runs in (:meth:`RunStore._commit`, :meth:`RunStore.checkpoint`): only what it
#: uses is taken, and the writer's pool is set back after
CHECKPOINT_MEMORY_MB = 512


def _connect(db_file: Path, read_only: bool, spill_dir: Path) -> duckdb.DuckDBPyConnection:
    """A fresh in-memory connection with ``db_file`` attached as the default catalog."""
    con = duckdb.connect(":memory:", config={"temp_directory": str(spill_dir)})
    try:
        con.execute("SET TimeZone = 'UTC'")
        con.execute("SET enable_progress_bar = false")   # the CLI draws its own progress
        # registered tables are views over files named relative to the run directory; a relative
        # path in a query is still found from the working directory (searched second)
        search = ",".join((str(db_file.resolve().parent), os.getcwd()))
        con.execute(f"SET file_search_path = {sql_literal(search)}")
        if not read_only:
            # a writer keeps every block it wrote in its buffer pool (default: 80 % of RAM), so
            # without a cap the process grows by the database's size; written blocks are on disk,
            # and larger work spills to temp_directory. The pool stays full while the run's
            # evaluation runs beside the open store, so its size adds to the run's peak: kept small
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




@dataclass(frozen=True)
class _Appending:
    """A table written a part at a time (:meth:`RunStore.append_parts`): what its first part
    fixed — its physical table (and shared one), its layout's signature, whether it is lean."""

    phys: str
    shared: str | None
    sign: Any
    lean: bool


class _LayoutChanged(Exception):
    """A part whose lean layout is not its table's (:meth:`RunStore.append_parts`)."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


class RunStore:
    """One run's DuckDB database. Build with ``create``, ``update`` or ``open``."""

    def __init__(self, db_file: Path, *, read_only: bool, lean: bool = True) -> None:
        self.path = Path(db_file)
        self.read_only = read_only
        #: write the run's large tables in the lean layout (False: every table stored as given)
        self.lean = lean
        self._spill = Path(tempfile.gettempdir()) / f"tertiary-duckdb-{os.getpid()}-{secrets.token_hex(6)}"
        self._con = _connect(self.path, read_only, self._spill)
        self._pool_mb = WRITER_MEMORY_MB        # the writer's buffer pool now (:meth:`_sized`)
        #: the tables being written a part at a time (:meth:`append_parts`)
        self._appending: dict[str, _Appending] = {}

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
                    store.checkpoint()
                finally:
                    store.close()
                if sidecars[0].exists():
                    raise RuntimeError(f"write-ahead log left after checkpoint: {sidecars[0]}")
            finally:
                for extra in sidecars:
                    remove_path(extra)

    # ---- lifecycle

    @property
    def con(self) -> duckdb.DuckDBPyConnection:
        """The DuckDB connection (the run database is its default catalog)."""
        return self._con

    def checkpoint(self) -> None:
        """Write every committed change into the database file, in :meth:`_checkpoint_pool`."""
        with self._checkpoint_pool():
            self._con.execute(f"CHECKPOINT {_ALIAS}")

    @contextmanager
    def _checkpoint_pool(self) -> Iterator[None]:
        """A checkpoint that runs out of the writer's small pool fails and invalidates the
        database, with nothing to retry: inside, the pool is at least
        :data:`CHECKPOINT_MEMORY_MB` (more if :meth:`_sized` raised it), set back after (only
        what the checkpoint uses is taken)."""
        self._con.execute(f"SET memory_limit = '{max(CHECKPOINT_MEMORY_MB, self._pool_mb)}MB'")
        try:
            yield
        finally:
            self._con.execute(f"SET memory_limit = '{self._pool_mb}MB'")

    def close(self) -> None:
        """Close the connection and drop its spill directory."""
        self._con.close()
        remove_path(self._spill)

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
        self._appending.pop(name, None)
        self._sized(lambda: self._write(name, frame))

    def _write(self, name: str, frame: pl.DataFrame) -> None:
        frame = compact_covariances(frame)
        table = self._writable(name, frame)
        lay = lean_layout(name, frame, self._con, self._reports_for(name)) if self.lean else None
        drops = self._drop_statements(name)
        if lay is None or not lay.changed:
            with self._registered(frame) as src:
                self._transaction(*drops, f"CREATE TABLE {table} AS SELECT * FROM {src}")
            return
        phys = LEAN_PREFIX + name
        shared = f"{phys}{ROWS_FLAG}" if lay.shared is not None else None
        view = view_sql(lay, column_types(self._con, frame), phys, shared)
        with self._registered(lay.phys) as src, self._registered(
                lay.shared if lay.shared is not None else pl.DataFrame({"x": [0]})) as src_s:
            stmts = [*drops, f"CREATE TABLE {quote(phys)} AS SELECT * FROM {src}"]
            if shared is not None:
                stmts.append(f"CREATE TABLE {quote(shared)} AS SELECT * FROM {src_s}")
            self._transaction(*stmts, f"CREATE VIEW {table} AS {view}")

    def write_files(self, name: str, files: Sequence[str | os.PathLike[str]], drop: Sequence[str] = ()) -> bool:
        """Create or replace table ``name`` with the rows of the Parquet ``files`` in order,
        without the ``drop`` columns, in one statement read by DuckDB itself: a long table
        written from disk is never held in memory and is written in one pass (a table appended a
        part at a time leaves freed blocks in the database). False, and
        nothing written, for a table with a lean layout rule or one too wide for the writer's
        buffer pool (:meth:`write_parts` then)."""
        if self.lean and any(name in rules for rules in (NARROW, SPLIT, FROM_REPORTS, SHARED)):
            return False
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        table = f'"{validate_name(name)}"'
        self._appending.pop(name, None)
        paths = [str(Path(f)) for f in files]
        exclude = f" EXCLUDE ({', '.join(quote(c) for c in drop)})" if drop else ""
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
        is copied into the database (a long run's streamed tables are large, and a copy would
        nearly double them and be the run's longest write).
        The files are hard-linked there (copied where the file system cannot link), numbered in
        order; a previous registration's files are replaced. Files without rows are left out
        (an empty window may lack optional columns); the view keeps the files' column types,
        fixed-size arrays as arrays. Returns the number of rows."""
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        table = f'"{validate_name(name)}"'
        self._appending.pop(name, None)
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
        scan = f"read_parquet({sql_literal(glob)}, union_by_name = true)"
        cols = []
        for c, kind, *_ in self._con.execute(f"DESCRIBE SELECT * FROM {scan}").fetchall():
            if c in drop:
                continue
            t = fixed.get(c)
            if t is not None and kind.endswith("[]"):
                cols.append(f"CAST({quote(c)} AS {kind[:-2]}[{t.size}]) AS {quote(c)}")
            else:
                cols.append(quote(c))
        self._transaction(*self._drop_statements(name),
                          f"CREATE VIEW {table} AS SELECT {', '.join(cols)} FROM {scan}")
        return int(sum(rows))

    def write_parts(self, name: str, parts: Callable[[], Iterable[pl.DataFrame]]) -> None:
        """:meth:`write` of the concatenation of the frames ``parts()`` yields, holding one part
        in memory at a time (a streamed table, window by window).

        Each part gets its own lean layout; when every part's layout is the first one's (the
        layout rules are row-wise checks, so this is exactly when the whole table's layout is
        that one) the parts are appended to it in order, in one transaction: the same table as
        :meth:`write` of the whole. Otherwise the parts are concatenated and written whole."""
        self._appending.pop(name, None)
        try:
            done = self._sized(lambda: self._transacted(lambda: self._add_rows(name, parts, None) is not None))
        except _LayoutChanged:
            done = False
        if not done:
            frames = [f for f in parts() if f.width]
            if frames:
                self.write(name, pl.concat(frames, how="diagonal_relaxed") if len(frames) > 1 else frames[0])

    def append_parts(self, tables: Mapping[str, Callable[[], Iterable[pl.DataFrame]]]) -> str | None:
        """For each ``name``, the frames ``tables[name]()`` yields appended to table ``name`` as
        the earlier calls of this method left it (the first part of the first call creates it,
        replacing any table of that name): a table written as a run goes is then the table
        :meth:`write_parts` makes of all its parts. One transaction for all the tables. The name
        of the first table one of whose parts has a lean layout other than the table's: the
        whole call is then rolled back (append the others again, and write that one whole). A
        write of ``name`` by any other method ends its appending."""
        made: dict[str, _Appending] = {}

        def add() -> bool:
            made.clear()
            for name, parts in tables.items():
                table = self._add_rows(name, parts, self._appending.get(name))
                if table is not None:
                    made[name] = table
            return True
        try:
            self._sized(lambda: self._transacted(add))
        except _LayoutChanged as exc:
            return exc.name
        self._appending.update(made)
        return None

    def _transacted(self, write: Callable[[], bool]) -> bool:
        """``write()`` in one transaction, committed when it returns True, else rolled back."""
        self._con.begin()
        try:
            keep = write()
        except BaseException:
            self._con.rollback()
            raise
        if keep:
            self._commit()
        else:
            self._con.rollback()
        return keep

    def _add_rows(self, name: str, parts: Callable[[], Iterable[pl.DataFrame]],
                  table: _Appending | None) -> _Appending | None:
        """Inside the open transaction: every part with rows added by :meth:`_add_part`; the
        table (None: no row and no table yet)."""
        for part in parts():
            if part.width and part.height:
                table = self._add_part(name, part, table)
        return table

    def _add_part(self, name: str, part: pl.DataFrame, table: _Appending | None) -> _Appending:
        """Inside the open transaction: ``part`` appended to ``table``, or (None) the table
        created from it in place of any of that name, with its lean layout and view;
        :class:`_LayoutChanged` when the part's layout is not the table's."""
        frame = compact_covariances(part)
        if table is None:
            view = self._writable(name, frame)
            lay = lean_layout(name, frame, self._con, self._reports_for(name)) if self.lean else None
            lean = lay is not None and lay.changed
            phys = LEAN_PREFIX + name if lean else validate_name(name)
            shared = f"{phys}{ROWS_FLAG}" if lean and lay.shared is not None else None
            for stmt in self._drop_statements(name):
                self._con.execute(stmt)
            self._insert(phys, lay.phys if lean else frame, create=True)
            if shared is not None:
                self._insert(shared, lay.shared, create=True)
            if lean:
                self._con.execute(f"CREATE VIEW {view} AS "
                                  + view_sql(lay, column_types(self._con, frame), phys, shared))
            return _Appending(phys, shared, layout_signature(lay) if lean else frame.schema, lean)
        _check_frame(part)
        lp = lean_layout(name, frame, self._con, self._reports_for(name)) if table.lean else None
        if (layout_signature(lp) if table.lean else frame.schema) != table.sign:
            raise _LayoutChanged(name)
        self._insert(table.phys, lp.phys if table.lean else frame, create=False)
        if table.shared is not None:
            self._insert(table.shared, lp.shared, create=False)
        return table

    def _insert(self, table: str, frame: pl.DataFrame, create: bool) -> None:
        with self._registered(frame) as src:
            self._con.execute(f"CREATE TABLE {quote(table)} AS SELECT * FROM {src}" if create
                              else f"INSERT INTO {quote(table)} SELECT * FROM {src}")

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
        DuckDB builds a row group of 122 880 rows in the pool before writing it, so a wide table
        (reports with many extra columns) can exceed the default pool, and a larger pool for every table would hold the blocks written
        in it (the run's peak)."""
        mb = WRITER_MEMORY_MB
        try:
            while True:
                try:
                    return write()
                except duckdb.OutOfMemoryException:
                    if mb >= WRITER_MEMORY_MAX_MB:
                        raise
                    mb = self._pool_mb = min(4 * mb, WRITER_MEMORY_MAX_MB)
                    self._con.execute(f"SET memory_limit = '{mb}MB'")
        finally:
            if mb != WRITER_MEMORY_MB:
                self._pool_mb = WRITER_MEMORY_MB
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
        out = [f"DROP VIEW {quote(name)}"] if kind == "VIEW" else [f"DROP TABLE {quote(name)}"] if kind else []
        phys = LEAN_PREFIX + name
        return out + [f"DROP TABLE IF EXISTS {quote(phys)}", f"DROP TABLE IF EXISTS {quote(phys + ROWS_FLAG)}"]

    def _reports_for(self, name: str) -> str | None:
        """The ``reports`` table a lean ``name`` may join its report columns from (None: none)."""
        return "reports" if name in FROM_REPORTS and self._kind("reports") else None

    def _writable(self, name: str, frame: pl.DataFrame) -> str:
        if self.read_only:
            raise PermissionError(f"{self.path} is open read-only")
        _check_frame(frame)
        return f'"{validate_name(name)}"'

    def _registered(self, frame: pl.DataFrame) -> contextlib.AbstractContextManager[str]:
        """Register ``frame`` (as Arrow) under a unique temp view name (:func:`arrow_view`)."""
        return arrow_view(self._con, frame, "src")

    def _commit(self) -> None:
        """Commit the open transaction, in :meth:`_checkpoint_pool`: a commit checkpoints the
        database when its write-ahead log has grown past the threshold."""
        with self._checkpoint_pool():
            self._con.commit()

    def _transaction(self, *statements: str | tuple[str, Params]) -> None:
        """Run ``statements`` (SQL, or (SQL, parameters)) in one transaction."""
        self._con.begin()
        try:
            for stmt in statements:
                self._con.execute(*((stmt,) if isinstance(stmt, str) else stmt))
        except BaseException:
            self._con.rollback()
            raise
        self._commit()


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
