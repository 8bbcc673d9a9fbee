"""The run's tables between the windows and the run database: the tables finalize leaves on disk
(:class:`OnDiskTable`) or reads back late (:class:`DeferredTable`), the sink that writes them
(:func:`store_sink`; on a thread of its own through the run: :class:`SinkThread`), the columns each
``--tables`` mode stores (:data:`LEAN_COLUMNS`) and what DuckDB can store (:func:`make_storable`)."""

from __future__ import annotations

import functools
import shutil
import tempfile
import threading
import time
import weakref
from collections.abc import Callable, Collection, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

from tertiary import contract
from tertiary.core.errors import OptionError
from tertiary.pipeline.clock import StageClock
from tertiary.runtime.windows import PARTS, PartStore, prefetched
from tertiary.runtime.windows import concat_parts, read_part_groups, window_blocks
from tertiary.store.run_store import TABLES_DIR, RunStore

__all__ = ["Sink", "OnDiskTable", "DeferredTable", "StreamedTable", "SinkThread", "StoreSink", "TABLE_MODES",
           "LIVE_TABLES", "LIVE_FLUSH_ROWS", "check_tables", "store_sink", "for_sink", "confirmed_targets",
           "read_table", "table_columns", "whole_table", "target_counts",
           "make_storable", "storable_as_is", "EVAL_BLOCK_ROWS", "LEAN_COLUMNS", "lean_columns", "REPORT_COLUMNS",
           "ALIGNED_COLUMNS", "ASSOCIATION_COLUMNS", "ALERT_TRUTH", "BOUND_TRUTH", "NOT_SCORED", "PartTrim",
           "part_trim"]


#: where a run's tables go: a frame whole, or a streamed table part by part (:class:`StreamedTable`)
Sink = Callable[[str, "pl.DataFrame | StreamedTable"], None]


#: the window output of the conflict rows the alert scoring reads (:func:`safety.alerts.scored_conflicts`)
SCORED_CONFLICTS = "conflicts.scored"


def part_rows(files: Collection[Path]) -> int:
    """The rows of the Parquet ``files``, from their footers (no column read)."""
    return sum(pq.ParquetFile(f).metadata.num_rows for f in files)


def facts_table(name: str) -> str:
    """The window output of table ``name``'s facts (:func:`window_facts`)."""
    return f"{name}.facts"


def window_facts(frame: pl.DataFrame) -> pl.DataFrame:
    """A window's rows of ``fused`` or ``tracks`` reduced to what :class:`OnDiskTable` reads of
    them: each (run, method, filter, target_id, tentative) once, in order of first appearance.
    The facts of the run's windows in window order give the facts of the whole table."""
    return frame.select(c for c in OnDiskTable.SLIM if c in frame.columns).unique(maintain_order=True)


class OnDiskTable:
    """A streamed table finalize leaves on disk once stored (memory): evaluation reads
    it back one picture at a time, so the whole-run stages never hold every picture at once.
    What finalize needs of the whole table (height, pictures in order of appearance, confirmed
    pictures, target counts) is read from a few columns of each part. The parts are regrouped
    by picture (one part in memory at a time) only when a picture is first read, so a run whose
    windows evaluated every picture never copies the table."""

    def __init__(self, parts, name: str, empty: pl.DataFrame) -> None:
        self.parts, self.name = parts, name
        self.keys = ["method", "filter"] if name == "tracks" else ["method"]
        # beside the parts (removed with them when the run completes), else in the temp directory
        base = parts.dir / PARTS if isinstance(parts, PartStore) else None
        self.dir = Path(tempfile.mkdtemp(prefix=f"_by_picture_{name}_", dir=base))
        weakref.finalize(self, shutil.rmtree, self.dir, True)
        self.index: dict[tuple, int] = {}
        #: the picture's files when every part holds that one picture: read in place, not copied
        self.direct: list[Path] | None = None
        self._grouped = threading.Lock()
        self._regrouped = False
        # the facts each window wrote of its rows (:func:`window_facts`), when every window did;
        # else each part's columns they come from
        carried = self._carried(empty)
        if carried is not None:
            got, whole, height = carried
        else:
            got = [(f, part) for f, part in self._slim_parts(empty) if part.height]
            whole = concat_parts([part for _, part in got]) if got else pl.DataFrame()
            height = whole.height
        if whole.height:
            self.index = {k: i for i, k in enumerate(whole.select(self.keys).unique(maintain_order=True).rows())}
        if len(self.index) == 1 and got[0][0] is not None:
            # every part with rows holds one and the same picture (a run of one fusion method
            # and one filter): read where they are, never copied (disk and a rewrite of the table)
            self.direct = [f for f, _ in got]
        self._facts(whole, height)

    SLIM = ("run", "method", "filter", "target_id", "tentative")

    def _carried(self, empty: pl.DataFrame) -> tuple[list[tuple[Path, None]], pl.DataFrame, int] | None:
        """(the parts with rows, the windows' facts of them, the table's rows) when every window
        with rows wrote its facts; None: some did not (a run resumed from an older checkpoint)."""
        if not hasattr(self.parts, "part_files"):
            return None
        files = self.parts.part_files(self.name)
        rows = {f: pq.ParquetFile(f).metadata.num_rows for f in files}
        with_rows = [f for f in files if rows[f]]
        facts = self.parts.part_files(facts_table(self.name))
        if not {f.name for f in with_rows} <= {f.name for f in facts}:
            return None
        first = next(iter(with_rows or files), None)
        self.empty = empty if first is None else pl.DataFrame(schema=pl.read_parquet_schema(first))
        whole = concat_parts(list(read_part_groups(facts))) if facts else pl.DataFrame()
        return [(f, None) for f in with_rows], whole, sum(rows.values())

    def _slim_parts(self, empty: pl.DataFrame) -> Iterator[tuple[Path | None, pl.DataFrame]]:
        """Each part's file (None when the parts are not files) and its (run, method, filter,
        target_id, tentative) columns; ``empty`` takes the schema of the first part with rows."""
        schema, rows = None, False
        if hasattr(self.parts, "part_files"):
            each = ((f, pl.read_parquet_schema(f)) for f in self.parts.part_files(self.name))
            got = ((f, have, pl.read_parquet(f, columns=[c for c in self.SLIM if c in have])) for f, have in each)
        else:
            got = ((None, part.schema, part.select(c for c in self.SLIM if c in part.columns))
                   for part in self.parts.iter_parts(self.name))
        for f, have, part in got:
            if schema is None or (part.height and not rows):
                schema, rows = have, part.height > 0
            yield f, part
        self.empty = empty if schema is None else pl.DataFrame(schema=schema)

    def _regroup(self) -> None:
        """The windows' parts copied once into a directory per picture (one part in memory at a
        time; the next part read meanwhile)."""
        with self._grouped:
            if self._regrouped:
                return
            for w, part in enumerate(prefetched(self.parts.iter_parts(self.name))):
                if part.height == 0:
                    continue
                for key, rows in part.partition_by(self.keys, as_dict=True, maintain_order=True).items():
                    d = self.dir / str(self.index[key])
                    d.mkdir(exist_ok=True)
                    # a scratch copy read back once or twice: fast compression, not small files
                    rows.write_parquet(d / f"w={w:06d}.parquet", compression="lz4")
            self._regrouped = True

    def _facts(self, frame: pl.DataFrame, height: int) -> None:
        """What finalize needs of the whole table (of ``height`` rows), from its (run, method,
        filter, target_id, tentative) columns (each combination once is enough)."""
        self.height = height
        self.pictures = list(self.index)                            # in order of appearance
        shown = frame.filter(~pl.col("tentative").fill_null(False)) if "tentative" in frame.columns else frame
        self.shown = shown.select(self.keys).unique(maintain_order=True).rows() if shown.height else []
        self.target_counts = target_counts(frame) if self.name == "fused" else {}
        self.confirmed = _confirmed(frame) if self.name == "fused" else None

    def picture(self, key: tuple, skip: Collection[str] = ()) -> pl.DataFrame:
        """One picture's rows, without the columns in ``skip``."""
        files, cols = self._files(key, skip)
        return (concat_parts([pl.read_parquet(f, columns=cols) for f in files]) if files
                else self.empty.select(cols))

    def blocks(self, key: tuple, skip: Collection[str] = (), rows: int | None = None) -> Iterator[pl.DataFrame]:
        """One picture's rows (as :meth:`picture`) in blocks of whole windows, in time order, each
        of at least ``rows`` rows (default :data:`EVAL_BLOCK_ROWS`) but the last."""
        files, cols = self._files(key, skip)
        yield from window_blocks(files, cols, EVAL_BLOCK_ROWS if rows is None else rows)

    def picture_files(self, key: tuple, skip: Collection[str] = ()) -> tuple[list[Path], list[str]]:
        """A picture's window files in window order, and the columns to read (all but ``skip``):
        what a reader elsewhere (a cluster's worker) needs to read it as :meth:`blocks` does."""
        return self._files(key, skip)

    def _files(self, key: tuple, skip: Collection[str]) -> tuple[list[Path], list[str]]:
        """A picture's window files in window order, and the columns read (all but ``skip``)."""
        k = self.index.get(tuple(key))
        if k is not None and self.direct is not None:
            return self.direct, [c for c in self.empty.columns if c not in skip]
        if k is not None:
            self._regroup()
        files = [] if k is None else sorted((self.dir / str(k)).glob("w=*.parquet"))
        return files, [c for c in self.empty.columns if c not in skip]

    def collect(self) -> pl.DataFrame:
        """The whole table (every picture), read back."""
        got = self.parts.table(self.name)
        return self.empty if got is None else got


class DeferredTable:
    """A whole-run table of an on-disk run read back (``read``) only where it is used, not held
    through the evaluation's peak: ``associations`` (``facts``: its number of targets, distinct
    (run, target_id)), ``conflicts`` (``facts``: its alert rows) and ``reports`` (memory). Its
    height is taken now."""

    def __init__(self, read: Callable[[], pl.DataFrame], height: int,
                 blocks: Callable[[], Iterator[pl.DataFrame]] | None = None, **facts: int) -> None:
        #: ``blocks()``: the rows again, as frames of whole epochs in time order (each run's)
        self.read, self.height, self.blocks, self.facts = read, height, blocks, facts


def whole_table(table: "pl.DataFrame | OnDiskTable") -> pl.DataFrame:
    """The whole table, read back when it is on disk."""
    return table.collect() if isinstance(table, OnDiskTable) else table


def read_table(parts: Any, name: str, empty: pl.DataFrame) -> pl.DataFrame:
    """Table ``name`` of every window in ``parts`` (``empty`` when no window wrote it)."""
    t = parts.table(name)
    return empty if t is None else t


#: what the whole-run stages read of ``reports`` (with the Cartesian sensors' stated plot
#: accuracy: the bound's MLAT and ADS-B events) and ``aligned`` (an on-disk run holds no more)
REPORT_COLUMNS = ["run", "report_id", "radar_id", "time", "azimuth_deg", "truth_id", "mode_s", "plot_sigma_x_m",
                  "plot_sigma_y_m", "plot_sigma_xy_m", "adsb_nacp"]
ALIGNED_COLUMNS = ["run", "epoch", "report_id", "radar_id", "local_track_id"]
ASSOCIATION_COLUMNS = ["run", "epoch", "target_id", "report_id"]
#: what no evaluation metric (nor conflict prediction) reads of a picture (the fusion's inputs
#: and the tracker's diagnostics): an on-disk picture is scored without them (memory)
NOT_SCORED = ("meas_cov", "weights", "radar_ids", "innovation", "model_probs", "meas_x_m", "meas_y_m",
              "meas_z_m", "n_fresh", "age_s")
#: what the stages after the evaluation read of the truth (an on-disk run reads them from its
#: reference): the separation intervals (``truth_heights``) and the bound
ALERT_TRUTH = ["run", "truth_id", "time", "x_m", "y_m", "z_m", "alt_m", "alt_rate_mps"]
BOUND_TRUTH = ["run", "truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]


def table_columns(parts: Any, name: str, columns: list[str] | None, empty: pl.DataFrame) -> pl.DataFrame:
    """:func:`read_table` of ``columns`` only (None: all), read only those."""
    t = parts.table(name, columns=columns) if columns is not None else parts.table(name)
    if t is None:
        return empty.select([c for c in columns if c in empty.columns]) if columns is not None else empty
    return t


@dataclass(frozen=True)
class StreamedTable:
    """A streamed table handed to a sink window by window: ``parts()`` yields each window's
    frame, in order (an on-disk run never holds the whole table). ``files``: when given, the
    table is also exactly these Parquet files' rows in order without the ``drop`` columns, which
    a sink may read itself (:meth:`RunStore.write_files`)."""

    parts: Callable[[], Iterator[pl.DataFrame]]
    files: tuple[Path, ...] = ()
    drop: tuple[str, ...] = ()
    #: the windows' Parquet parts that are exactly the table's rows in order: a sink that
    #: registers tables (``tertiary run --tables parquet``) keeps these files instead of copying
    parts_files: tuple[Path, ...] = ()


def for_sink(parts, name: str, empty: pl.DataFrame) -> "StreamedTable | pl.DataFrame":
    """``name`` for a sink: its parts one at a time, or ``empty`` when no window wrote any."""
    if next(iter(parts.iter_parts(name)), None) is None:
        return empty
    files = tuple(parts.part_files(name)) if hasattr(parts, "part_files") else ()
    return StreamedTable(lambda: parts.iter_parts(name), parts_files=files)


#: where a run's streamed tables go: copied into the database with the columns its readers read
#: (:data:`LEAN_COLUMNS`), copied with every column (``full``), or kept as Parquet files beside it
#: with views over them (:meth:`RunStore.register_parquet`, the columns its readers read)
TABLE_MODES = ("database", "full", "parquet")

#: the columns ``--tables database`` (and ``parquet``) stores of the per-epoch tables: what the
#: HTML report (tertiary.report, its alert episodes included) and the named SQL (sql/*.sql) read,
#: with the keys that join them (``aligned`` takes its report columns from ``reports`` by
#: ``report_id``; ``associations``, whole, links each report to its system target). The other
#: columns (covariances, innovations, model probabilities, weights, the measurement columns of
#: ``fused``, the reports' raw plots and EHS, the conflicts' thresholds ...) are per-epoch detail
#: no reader of a run reads: ``--tables full`` stores them too. A table not named here is stored
#: whole; a run whose table lacks a listed column stores the ones it has.
LEAN_COLUMNS: dict[str, tuple[str, ...]] = {
    # alert episodes (tertiary.report.episodes): a picture's states around an episode; row_accounting:
    # its rows; the fused target a track's plots came from (a track picture's link to its method's)
    "tracks": ("run", "epoch", "track_id", "filter", "method", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps",
               "alt_m", "alt_rate_mps", "plot_target_id"),
    "fused": ("run", "epoch", "target_id", "method", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps",
              "alt_m", "alt_rate_mps"),
    # radar_accuracy_over_time, row_accounting
    "aligned": ("run", "epoch", "report_id", "radar_id", "local_track_id", "truth_id", "x_m", "y_m", "z_m"),
    # radar_kinematics, radar_residuals(_over_time), reports_by_radar, radar_sites, the runs' start
    # (min(time)), the report_id aligned joins on
    "reports": ("run", "report_id", "radar_id", "time", "local_track_id", "truth_id", "est_range_m",
                "est_range_rate_mps", "res_range_m", "res_range_var_m2"),
    # conflicts, conflict_timeline, alert episodes
    "conflicts": ("run", "epoch", "method", "id_a", "id_b", "r_min_m", "t_min_s", "dz_m", "alert", "severity"),
}


def lean_columns(tables: str) -> dict[str, tuple[str, ...]]:
    """The columns mode ``tables`` stores of each table it slims (empty: every column)."""
    return {} if tables == "full" else LEAN_COLUMNS


PartTrim = Callable[[str, pl.DataFrame], pl.DataFrame]


def part_trim(tables: str, whole_aligned: bool = False) -> PartTrim | None:
    """What a window writes of each table when the run stores lean tables: the columns the
    whole-run stages and the stored tables read, not the per-epoch detail that only ``--tables
    full`` keeps (disk: a day's parts would otherwise be several times its input, most of it
    covariances nobody reads back). ``aligned`` keeps its stored columns and the accounting's,
    every column when ``whole_aligned`` (radar health reads them); ``reports`` its stored columns
    and the truth window's; ``fused`` and ``tracks`` all but :data:`NOT_SCORED`. None (``full``):
    every column."""
    if tables == "full":
        return None
    keep = {"reports": (*LEAN_COLUMNS["reports"], *REPORT_COLUMNS)}
    if not whole_aligned:
        keep["aligned"] = (*LEAN_COLUMNS["aligned"], *ALIGNED_COLUMNS)
    drop = {name: tuple(c for c in NOT_SCORED if c not in LEAN_COLUMNS[name]) for name in ("fused", "tracks")}

    def trim(name: str, frame: pl.DataFrame) -> pl.DataFrame:
        if name in keep:
            return frame.select(c for c in frame.columns if c in keep[name])
        return frame.drop(drop.get(name, ()), strict=False)
    return trim


def check_tables(tables: str, out_dir: str | Path) -> None:
    """``--tables``: a known mode, and a run directory DuckDB's file search path can name."""
    if tables not in TABLE_MODES:
        raise OptionError(f"choose database or parquet, or full (every column in the database), got {tables!r}",
                          option="--tables")
    if tables == "parquet" and "," in str(Path(out_dir).resolve()):
        # the search path is a comma-separated list: the views could not find their files
        raise OptionError("the run directory's path must not contain a comma to register Parquet tables",
                          option="--tables")


def _tables_dir(store: RunStore) -> Path:
    d = store.path.parent / TABLES_DIR
    d.mkdir(parents=True, exist_ok=True)
    return d


def _slim_copy(src: Path, drop: Collection[str], out: Path) -> Path:
    """Parquet ``src`` without the ``drop`` columns, written to ``out`` (zstd) with min/max
    statistics on its non-float columns only: DuckDB's Parquet scan takes ``NOT isnan(x)`` as
    always true on a row group whose float statistics (which leave NaN out) are finite, and keeps
    its NaN rows (the named SQL over ``reports`` filter NaN residuals so)."""
    keep = [c for c in pl.read_parquet_schema(src) if c not in drop]
    table = pq.read_table(src, columns=keep)
    stats = [f.name for f in table.schema if not pa.types.is_floating(f.type)]
    pq.write_table(table, out, compression="zstd", write_statistics=stats)
    return out


#: the streamed tables a run's sink appends to the database as its windows are stored
#: (:meth:`StoreSink.catch_up`), in the order they are appended: ``aligned``'s lean layout joins
#: the ``reports`` rows already there
LIVE_TABLES = ("reports", "aligned", "associations", "fused", "clusters", "tracks", "conflicts")
#: rows of the stored windows' parts of :data:`LIVE_TABLES` gathered before they are appended: a
#: few windows at a time, so that the transactions are few and the row groups they leave mostly full
LIVE_FLUSH_ROWS = 1_000_000


def store_sink(store: RunStore, notes: list[str], tables: str = "database") -> StoreSink:
    """The sink that writes a run's tables to ``store`` (:class:`StoreSink`)."""
    return StoreSink(store, notes, tables)


class StoreSink:
    """Writes a run's tables to ``store``: a frame whole, a :class:`StreamedTable` part by part
    (:meth:`RunStore.write_parts`), or with ``tables="parquet"`` its window parts registered
    where they are (:meth:`RunStore.register_parquet`) when they are storable as they are.
    ``database`` and ``parquet`` store only the :data:`LEAN_COLUMNS` of the tables named there
    (``parquet``: the parts' read columns copied to Parquet files of their own, which are
    registered); ``full`` every column.

    With ``database`` or ``full``, :meth:`catch_up` appends the windows' parts to the database
    as they are stored, so that the end of the run has only the last ones left to append: a
    streamed table handed over whole then gets only its parts not yet appended."""

    def __init__(self, store: RunStore, notes: list[str], tables: str = "database") -> None:
        check_tables(tables, store.path.parent)
        self.store, self.notes, self.tables = store, notes, tables
        self.keep = lean_columns(tables)
        #: the part files appended so far, by table (:meth:`catch_up`), and their rows
        self.live: dict[str, list[Path]] = {}
        self.rows: dict[str, int] = {}
        #: the tables whose parts changed layout: written whole at the end
        self.broken: set[str] = set()
        #: the windows whose parts are appended (the first ``through``)
        self.through = 0

    def catch_up(self, parts: PartStore) -> None:
        """Append to the database the parts of :data:`LIVE_TABLES` of the windows ``parts`` has
        stored since the last call, once they hold :data:`LIVE_FLUSH_ROWS` rows: every table
        through the same window, in that order. A table whose parts do not keep its first
        part's layout is left to be written whole at the end."""
        if self.tables == "parquet":
            return
        done = parts.written
        new = {name: [f for f in parts.part_files(name) if self.through <= _window_of(f) < done]
               for name in LIVE_TABLES}
        rows = {name: sum(pq.ParquetFile(f).metadata.num_rows for f in files) for name, files in new.items()}
        if sum(rows.values()) < LIVE_FLUSH_ROWS:
            return
        self._append(new, rows)
        self.through = done

    def _append(self, files: dict[str, list[Path]], rows: dict[str, int]) -> None:
        """Each table's ``files`` (of ``rows`` rows) appended after its earlier ones, in one
        transaction (files without rows only counted); a table whose layout changed is
        appended no more, and the others go again without it."""
        todo = [name for name in files if name not in self.broken and files[name]]
        while True:
            given = {name: functools.partial(self._read, name, files[name]) for name in todo if rows[name]}
            broke = self.store.append_parts(given) if given else None
            if broke is None:
                break
            self.broken.add(broke)
            todo.remove(broke)
        for name in todo:
            self.live.setdefault(name, []).extend(files[name])
            self.rows[name] = self.rows.get(name, 0) + rows[name]

    def _read(self, name: str, files: list[Path]) -> Iterator[pl.DataFrame]:
        """The storable frames of ``name``'s part ``files``, the next read while one is taken."""
        return prefetched(self._storable(pl.read_parquet(f), name) for f in files)

    def __call__(self, name: str, frame: "pl.DataFrame | StreamedTable") -> None:
        store, tables = self.store, self.tables
        # the windows' parts, or files that are exactly the table (the truth's reference files)
        own = (frame.parts_files or frame.files) if isinstance(frame, StreamedTable) else ()
        if tables == "parquet" and own and storable_as_is(own[0], name, frame.drop):
            gone = {c for f in own for c in self._unkept(pl.read_parquet_schema(f), name)}   # an empty part has fewer
            if not gone:
                store.register_parquet(name, own, frame.drop)
                return
            # the read columns only, copied beside the registered tables (the same file system:
            # registering links them) and registered; the scratch copies' names then go
            scratch = Path(tempfile.mkdtemp(prefix=f".slim-{name}-", dir=_tables_dir(store)))
            try:
                gone_or_dropped = {*frame.drop, *gone}
                slim_files = [_slim_copy(f, gone_or_dropped, scratch / f"part-{i:06d}.parquet")
                              for i, f in enumerate(own)]
                store.register_parquet(name, slim_files)
            finally:
                shutil.rmtree(scratch, ignore_errors=True)
            return
        if isinstance(frame, StreamedTable):
            if self._rest_appended(name, frame.parts_files):
                return
            # the files as they are, when no column of theirs needs making storable
            drop = (*frame.drop, *self._unkept(pl.read_parquet_schema(frame.files[0]), name)) if frame.files else ()
            if (frame.files and storable_as_is(frame.files[0], name, drop)
                    and store.write_files(name, frame.files, drop)):
                return
            # the next window's part is read while this one is inserted
            store.write_parts(name, lambda: prefetched(self._storable(f, name) for f in frame.parts()))
        elif frame.width:
            store.write(name, self._storable(frame, name))

    def _rest_appended(self, name: str, files: tuple[Path, ...]) -> bool:
        """Whether ``files``, the whole table's parts, now are in the database: the ones
        :meth:`catch_up` appended begin them (with a row), and the rest append."""
        have = self.live.get(name)
        if not have or name in self.broken or list(files[:len(have)]) != have:
            return False
        rest = list(files[len(have):])
        self._append({name: rest}, {name: sum(pq.ParquetFile(f).metadata.num_rows for f in rest)})
        return name not in self.broken and self.rows[name] > 0

    def _storable(self, frame: pl.DataFrame, name: str) -> pl.DataFrame:
        said: list[str] = []
        drop = self._unkept(frame.schema, name)
        out = make_storable(frame.drop(drop) if drop else frame, name, said)
        self.notes.extend(n for n in said if n not in self.notes)      # once per table, not once per window
        return out

    def _unkept(self, schema: Any, name: str) -> list[str]:
        return [c for c in schema if name in self.keep and c not in self.keep[name]]


def _window_of(part: Path) -> int:
    """The window index of a part file (``w=000012.parquet``)."""
    return int(part.stem.split("=")[1])


class SinkThread:
    """A run's tables handed to ``sink`` on a thread of their own, in the order they come, while
    the stages go on: the truth and the stored windows' parts (:meth:`catch_up`) while the
    windows run, the rest while the whole-run stages do (speed: copying the tables into the run
    database would otherwise hold up the stages). The
    streamed tables are read from their parts on disk and the frames given are never changed
    after, so the stages and the writes share nothing but the disk. A write's failure stops
    the later writes and is raised, as a failure of ``write_tables``, at the next table given
    or at :meth:`join`."""

    def __init__(self, sink: Sink) -> None:
        self.sink = sink
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="finalize-sink")
        self._pending: list[Future] = []
        self._error: BaseException | None = None
        self._catching: Future | None = None
        #: seconds the writes took (beside the stages)
        self.busy_s = 0.0

    def __call__(self, name: str, frame: "pl.DataFrame | StreamedTable") -> None:
        self._submit(f"table {name!r}", lambda: self.sink(name, frame))

    def catch_up(self, parts: Any) -> None:
        """The sink's ``catch_up(parts)`` (:meth:`StoreSink.catch_up`: the windows' parts
        stored so far appended to the database), after the tables given before; nothing when
        the sink has none, ``parts`` are not on disk, or the last one has not run yet (the
        next takes its windows too)."""
        if not hasattr(self.sink, "catch_up") or not hasattr(parts, "part_files"):
            return
        if self._catching is not None and not self._catching.done():
            return
        self._catching = self._submit("the stored windows' tables", lambda: self.sink.catch_up(parts))

    def _submit(self, what: str, write: Callable[[], None]) -> Future:
        self._raise()
        self._pending = [f for f in self._pending if not f.done()]
        self._pending.append(self._pool.submit(self._write, what, write))
        return self._pending[-1]

    def _write(self, what: str, write: Callable[[], None]) -> None:
        if self._error is not None:
            return
        t = time.perf_counter()
        try:
            write()
        except BaseException as exc:  # raised in the stages' thread
            exc.add_note(f"while writing {what} to the run database")
            self._error = exc
        finally:
            self.busy_s += time.perf_counter() - t

    def _raise(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            err.tertiary_stage = "write_tables"  # type: ignore[attr-defined]
            raise err

    def join(self, clock: StageClock) -> None:
        """Wait for every table given (counted as ``write_tables``); a failure raised here."""
        clock.stage("write_tables", say=False)
        for f in self._pending:
            f.result()
        self._pending = []
        clock.stage(None)
        self._raise()

    def close(self) -> None:
        """Wait for the writes in flight (after a failure the caller writes what it has)."""
        self._pool.shutdown(wait=True)


#: rows of an on-disk picture matched and row-scored at a time (whole windows): the evaluation's
#: scratch and a picture's covariances are held a block at a time (memory)
EVAL_BLOCK_ROWS = 200_000


def target_counts(fused: "pl.DataFrame | OnDiskTable") -> dict[str, int]:
    """System targets (run, target_id) that were ever confirmed, and those only ever tentative."""
    if isinstance(fused, OnDiskTable):
        return fused.target_counts
    if "tentative" not in fused.columns or fused.height == 0:
        return {"confirmed_targets": 0, "tentative_targets": 0}
    ever = (fused.filter(pl.col("tentative").is_not_null()).group_by("run", "target_id")
            .agg(pl.col("tentative").all().alias("t")))
    n_tent = int(ever["t"].sum())
    return {"confirmed_targets": ever.height - n_tent, "tentative_targets": n_tent}


def confirmed_targets(fused: "pl.DataFrame | OnDiskTable") -> pl.DataFrame:
    """(run, target_id) of every system target a fusion method showed confirmed at least once
    (the centralised reference's own targets left out)."""
    return fused.confirmed if isinstance(fused, OnDiskTable) else _confirmed(fused)


def _confirmed(frame: pl.DataFrame) -> pl.DataFrame:
    if frame.height == 0 or "target_id" not in frame.columns:
        return pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64})
    shown = frame.filter(~pl.col("tentative").fill_null(False)) if "tentative" in frame.columns else frame
    if "method" in shown.columns:
        shown = shown.filter(pl.col("method") != "centralized")
    return shown.select(pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64)).unique()


def storable_as_is(file: Path, name: str, drop: Collection[str] = ()) -> bool:
    """Whether :func:`make_storable` leaves the columns of Parquet ``file`` (but ``drop``) as is."""
    probe = pl.DataFrame(schema=pl.read_parquet_schema(file)).drop(drop, strict=False)
    return make_storable(probe, name, []).schema == probe.schema


def make_storable(frame: pl.DataFrame, name: str, notes: list[str]) -> pl.DataFrame:
    """``frame`` with columns DuckDB cannot hold or give back made storable (with a note):
    Duration as Int64 microseconds, 128-bit integers as text, Object columns dropped."""
    fix, drop = [], []
    for col, dtype in frame.schema.items():
        if isinstance(dtype, pl.Duration):
            fix.append(pl.col(col).dt.total_microseconds())
            notes.append(f"{name}.{col}: Duration stored as Int64 microseconds")
        elif dtype in (pl.Int128, pl.UInt128):
            fix.append(pl.col(col).cast(pl.String))
            notes.append(f"{name}.{col}: 128-bit integers stored as text")
        elif contract.has_dtype(dtype, (pl.Object, pl.Duration)) or dtype in (pl.Int128, pl.UInt128):
            drop.append(col)
    if drop:
        notes.append(f"{name}: column(s) {', '.join(drop)} not stored (Object/nested Duration values)")
    return frame.with_columns(fix).drop(drop)
