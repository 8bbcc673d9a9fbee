"""The windowed engine: a run cut into time windows on the absolute epoch grid, each stage a step
function of (state, window) → (outputs, state), outputs appended per window, resumable.

Layout of a run directory while it runs (``RUN_DIR``)::

    parts/<table>/w=<k>.parquet   each window's rows of the streamed tables (atomic files)
    state.pkl                      every stage's state after the last complete window (atomic)
    manifest.json                  the commit point: windows done, config hash, status (atomic)

A window is complete when its manifest line is written (parts first, then the state, then the
manifest), so a reader or ``--resume`` never sees a half-written window: parts of a later
window are deleted on resume and rewritten. When every window is done, the finalize stage (the
whole-run evaluation: matching, accuracy, continuity, alert scoring, STCA curves, bounds,
requirements) reads the parts back, ``results.duckdb`` is built from them (lean layout, written
atomically), the manifest says ``complete`` and the parts and the state are removed.

Why Parquet parts and not appends to DuckDB: a DuckDB append of a lean-layout table rewrites it
(its layout is decided on the whole table), a Parquet part is written once and never touched
again, so a kill costs at most one window, and a Dask worker can write its own part without a
shared database writer.

What streams and what does not (measured in ``benchmarks/bench_memory.py``): ingest, align,
associate, fuse, the centralised reference, clustering, the trackers and conflict prediction
carry explicit state (the :class:`tertiary.core.stage.Stage` contract) and see one window at a
time; the finalize stage holds the streamed tables of the whole run.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import hashlib
import json
import math
import pickle
import resource
import shutil
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields, is_dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import polars as pl

from tertiary import contract as schema
from tertiary.store.run_store import atomic_path, write_parquet_atomic, write_text_atomic
from tertiary.core.errors import DataError, OptionError
from tertiary.core.units import US
from tertiary.core.stage import T_MIN_US, T_MAX_US, Window

T = TypeVar("T")

#: window length (s) of the API's windowed functions, and of ``--window auto`` when the input
#: has no usable time span (or with ``--engine dask``, whose slices are multiples of it)
DEFAULT_WINDOW_S = 300.0
#: ``tertiary run``'s default: windows sized by the recording's report rate
AUTO_WINDOW = "auto"
#: reports a window holds on average under ``--window auto``, for one fusion method (divided by
#: the number of methods: each adds its picture and its trackers' tracks to every window). A
#: window's memory grows with its rows, and every window costs a fixed overhead (about a second of
#: small table operations on the 2-core machine), so a busy recording gets short windows and a
#: sparse one long ones. Parts above DuckDB's row group (122 880 rows) are written to the run
#: database optimistically and leave free blocks in it, which the division by the methods avoids.
WINDOW_REPORTS = 50_000
#: the bounds (s) of an automatic window
AUTO_WINDOW_BOUNDS_S = (60.0, 3600.0)
#: the streamed tables, in the order they are written to the run database
STREAMED = ("reports", "rejects", "aligned", "associations", "fused", "clusters", "tracks", "conflicts")
MANIFEST = "manifest.json"
STATE_FILE = "state.pkl"
PARTS = "parts"
ENGINE_VERSION = 1

Progress = Callable[[str], None]


def windows(origin_us: int, t_last_us: int, window_s: float | None, start: int = 0,
            t_first_us: int | None = None, occupied: set[int] | None = None, carry_us: int = 0
            ) -> Iterator[Window]:
    """Windows of ``window_s`` seconds on the grid from ``origin_us``: from the one holding
    ``t_first_us`` (default: the origin), which is open to the past, to the one holding
    ``t_last_us``, which is open to the future; indices count from the origin, so a slice of a
    longer recording numbers its windows like the whole run (None: one window over everything).
    With ``occupied`` (indices of windows holding data), a window is skipped when neither it nor
    any of the windows within ``carry_us`` before it holds data: nothing can come out of it and
    no stage's state changes in it (a silence of hours costs nothing)."""
    if window_s is None:
        if start == 0:
            yield Window.unbounded()
        return
    w = int(round(window_s * US))
    first = max(0, ((t_first_us if t_first_us is not None else origin_us) - origin_us) // w)
    n = max(first + 1, (t_last_us - origin_us) // w + 1)
    reach = -(-carry_us // w) + 1
    live = None
    if occupied is not None:
        live = {k + j for k in occupied for j in range(reach + 1)}
    for k in range(max(start, first), n):
        if live is not None and k not in live and k not in (first, n - 1):
            continue
        yield Window(k, T_MIN_US if k == first else origin_us + k * w,
                     T_MAX_US if k == n - 1 else origin_us + (k + 1) * w)


def auto_window_s(source: "ReportSource", reports_per_window: int = WINDOW_REPORTS) -> float:
    """The ``--window auto`` length: about ``reports_per_window`` reports in the recording's
    *busiest* window, in whole minutes within :data:`AUTO_WINDOW_BOUNDS_S`;
    :data:`DEFAULT_WINDOW_S` when the input has no plausible time span.

    A window's memory grows with its rows, so the budget is held by the busiest stretch of the
    recording, not by its mean: a day with a midday peak gets shorter windows than an hour of
    the same mean rate. The length is the fixed point of w ← budget / peak rate over
    w (:meth:`ReportSource.minute_counts`), from the mean-rate length; a uniform recording gets
    the mean-rate length."""
    if not source.windowable or source.n_rows == 0:
        return DEFAULT_WINDOW_S
    lo, hi = AUTO_WINDOW_BOUNDS_S
    counts = source.minute_counts()
    total = max(int(counts.sum()), 1)
    span_s = max((source.last_us - source.first_us) / US, 1.0)

    def whole(raw: float) -> float:
        return float(min(max(60.0 * round(raw / 60.0), lo), hi))

    w = whole(reports_per_window * span_s / total)
    cum = np.concatenate([[0], np.cumsum(counts)])
    for _ in range(4):                       # converges in one or two steps (whole minutes)
        m = int(w // 60)
        busiest = int((cum[m:] - cum[:-m]).max()) if m < len(cum) else total
        nxt = whole(reports_per_window * w / max(busiest, 1))
        if nxt == w:
            break
        w = nxt
    return w


def is_auto(window_s: object) -> bool:
    """True for ``"auto"`` (any case, surrounding blanks ignored): :func:`auto_window_s` decides."""
    return isinstance(window_s, str) and window_s.strip().lower() == AUTO_WINDOW


def resolve_window(window_s: "float | str | None", reports: "pl.DataFrame | pl.LazyFrame",
                   limits: schema.Limits = schema.Limits(), methods: int = 1) -> float | None:
    """``window_s`` checked (:func:`check_window`), ``"auto"`` replaced by :func:`auto_window_s`
    of ``reports`` (one scan of its time column) for a run of ``methods`` fusion methods."""
    if is_auto(window_s):
        return auto_window_s(ReportSource(reports, limits), max(1, WINDOW_REPORTS // max(1, int(methods))))
    return check_window(window_s)


def check_window(window_s: float | None) -> float | None:
    if window_s is None:
        return None
    if not (isinstance(window_s, (int, float)) and math.isfinite(window_s) and window_s >= 1.0):
        raise OptionError(f"must be a number of seconds >= 1, got {window_s}", option="--window")
    return float(window_s)


# --------------------------------------------------------------------------- input


INPUT_ROW = schema.INPUT_ROW


class ReportSource:
    """The input reports read window by window: a window's rows are those whose ``time`` falls in
    it (a scan of the Parquet files with the time predicate pushed down when the dataset came from
    files). The windows span the *plausible* times only — in the contract's years and within half
    the maximum span of the whole table's median (``schema.Limits``), the median every window is
    validated against — so one report dated year 1 or 9999 neither stretches the grid nor moves
    its origin: such rows, and rows without a time, go to the first window, where ingest rejects
    them with the whole-run reason. A ``time`` column that is not a timestamp at all makes the run
    one window (nothing can be cut).

    ``clock_offsets`` (radar_id → µs, a registration's clock offsets δ_r): a report belongs to the
    window of its corrected time t − δ_r, the time it carries once registered, so that the
    registration can be applied window by window."""

    def __init__(self, reports: pl.DataFrame | pl.LazyFrame, limits: schema.Limits = schema.Limits(),
                 clock_offsets: dict[int, int] | None = None) -> None:
        self.offsets = {int(k): int(v) for k, v in (clock_offsets or {}).items() if int(v) != 0}
        self.reach_us = max((abs(v) for v in self.offsets.values()), default=0)
        lf = reports.lazy() if isinstance(reports, pl.DataFrame) else reports
        # the row index straight on the scan (nothing resolved before it, not even the schema):
        # a time filter is then pushed into the scan, which skips the files outside a window
        try:
            names = lf.with_row_index(INPUT_ROW).collect_schema()
            lf = lf.with_row_index(INPUT_ROW)
        except pl.exceptions.DuplicateError:    # an input that has the column: ours replaces it
            lf = lf.drop(INPUT_ROW).with_row_index(INPUT_ROW)
            names = lf.collect_schema()
        self.time_dtype = names.get("time")
        self.timed = isinstance(self.time_dtype, pl.Datetime)
        self.lf = lf
        self.median = None
        self.first_us = self.last_us = None
        self.n_rows = int(self.lf.select(pl.len()).collect().item())
        if not self.timed:
            return
        lo, hi = (int(datetime(y, 1, 1, tzinfo=timezone.utc).timestamp()) * US for y in limits.years)
        t = pl.col("time").dt.epoch("us")
        med = self.lf.filter((t >= lo) & (t < hi)).select(t.median()).collect().item()
        if med is None:
            return
        half = int(limits.max_span_s / 2.0 * US)
        med = int(round(med))
        self.median = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=med)
        self.lo_us, self.hi_us = max(lo, med - half), min(hi - 1, med + half)
        tc = self._time()
        span = self.lf.filter((t >= self.lo_us) & (t <= self.hi_us)).select(tc.min().alias("a"), tc.max().alias("b")
                                                                           ).collect()
        self.first_us, self.last_us = span["a"][0], span["b"][0]

    def _time(self) -> pl.Expr:
        """The time (µs) a report is windowed by: its own, less its radar's clock offset."""
        t = pl.col("time").dt.epoch("us")
        if not self.offsets:
            return t
        return t - pl.col("radar_id").cast(pl.Int64).replace_strict(self.offsets, default=0, return_dtype=pl.Int64)

    @property
    def windowable(self) -> bool:
        return self.timed and self.first_us is not None

    def minute_counts(self) -> np.ndarray:
        """Reports with a plausible time in each whole minute from the first such report (one
        scan of the time column; :func:`auto_window_s`)."""
        t, tc = pl.col("time").dt.epoch("us"), self._time()
        k = (self.lf.filter((t >= self.lo_us) & (t <= self.hi_us))
             .select(((tc - self.first_us) // (60 * US)).alias("k")).collect()["k"].to_numpy())
        return np.bincount(k.astype(np.int64)) if len(k) else np.zeros(1, np.int64)

    def occupied(self, origin_us: int, window_s: float) -> set[int]:
        """Indices of the windows holding at least one plausible report."""
        w = int(round(window_s * US))
        t = pl.col("time").dt.epoch("us")
        k = self.lf.filter((t >= self.lo_us) & (t <= self.hi_us)).select(((self._time() - origin_us) // w).unique()
                                                                          ).collect()
        return set(k.to_series().to_list())

    def rows(self, w: Window) -> pl.DataFrame:
        if not self.windowable or (w.open_start and w.open_end):
            return self.lf.collect()
        t, tc = pl.col("time").dt.epoch("us"), self._time()
        plausible = (t >= self.lo_us) & (t <= self.hi_us)
        cond = (tc >= w.t0_us) & (tc < w.t1_us) & plausible
        if w.open_start:   # the first window also takes the rows without a plausible time
            return self.lf.filter(cond | pl.col("time").is_null() | (t < self.lo_us) | (t > self.hi_us)).collect()
        # the same rows, with a coarse test on the column itself first: a scan skips the files
        # and row groups whose time statistics lie outside it (a test on an expression of the
        # column cannot), so a window reads its own part of the input, not all of it
        # (collected before the exact test: a predicate the scan cannot take keeps it from taking any)
        near = self._near(max(w.t0_us - self.reach_us, self.lo_us), min(w.t1_us + self.reach_us, self.hi_us + 1))
        return self.lf.filter(near).collect().filter(cond)

    def _near(self, t0_us: int, t1_us: int) -> pl.Expr:
        """``time`` within [t0 − 1 ms, t1 + 1 ms), compared in the column's own type (any unit)."""
        dtype = self.time_dtype
        lit = lambda us: pl.lit(us, pl.Int64).cast(pl.Datetime("us")).cast(dtype)  # noqa: E731
        return (pl.col("time") >= lit(t0_us - 1000)) & (pl.col("time") < lit(t1_us + 1000))


# --------------------------------------------------------------------------- parts, state, manifest


def config_dict(cfg: Any) -> Any:
    """A configuration (nested frozen dataclasses) as plain dicts and lists, as the run record
    stores it and :func:`config_hash` hashes it."""
    if is_dataclass(cfg):
        return {f.name: config_dict(getattr(cfg, f.name)) for f in fields(cfg)}
    if isinstance(cfg, tuple):
        return [config_dict(x) for x in cfg]
    return cfg


def config_hash(cfg: Any, window_s: float | None, dataset: str) -> str:
    text = json.dumps({"config": config_dict(cfg), "window_s": window_s, "dataset": dataset,
                       "engine": ENGINE_VERSION}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def read_manifest(run_dir: str | Path) -> dict | None:
    """The run's manifest, or None (a run written before the windowed engine, or no run)."""
    path = Path(run_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"unreadable run manifest: {exc}", path=str(path)) from exc


def incomplete_message(run_dir: str | Path) -> str | None:
    """A one-line statement that the run in ``run_dir`` is incomplete, or None when it is complete
    (or was written before manifests existed)."""
    m = read_manifest(run_dir)
    if m is None or m.get("status") == "complete":
        return None
    done = int(m.get("windows_done", 0))
    state = "failed" if m.get("status") == "failed" else "incomplete (running, or killed)"
    return (f"run {state}: {done} window(s) of {m.get('window_s')} s done, up to "
            f"{m.get('time_done', '?')}; continue it with `tertiary run {m.get('dataset', 'DATASET')} "
            f"--resume {run_dir}`")


class PartStore:
    """Per-window Parquet parts, the carried state and the manifest of one run directory.
    ``trim(name, frame)``: what of a window's table is written (None: all of it); the header's
    ``parts`` names it, and a run is resumed only with the same."""

    def __init__(self, run_dir: Path, manifest: dict,
                 trim: Callable[[str, pl.DataFrame], pl.DataFrame] | None = None) -> None:
        self.dir, self.manifest, self.trim = run_dir, manifest, trim
        #: windows whose parts are written: the checkpointed ones (``windows_done``, where a
        #: resume starts) and any after them stored without a state
        self.written = int(manifest.get("windows_done", 0))

    @classmethod
    def start(cls, run_dir: Path, header: dict,
              trim: Callable[[str, pl.DataFrame], pl.DataFrame] | None = None) -> PartStore:
        for old in (run_dir / PARTS, run_dir / STATE_FILE):
            shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink(missing_ok=True)
        store = cls(run_dir, {**header, "status": "running", "windows_done": 0, "tables": {}}, trim)
        store._commit()
        return store

    @classmethod
    def resume(cls, run_dir: Path, header: dict,
               trim: Callable[[str, pl.DataFrame], pl.DataFrame] | None = None) -> tuple[PartStore, Any]:
        """The store and the state after the last complete window; parts of later windows are dropped."""
        m = read_manifest(run_dir)
        if m is None:
            raise DataError("nothing to resume: no manifest.json (not a windowed run directory)", path=str(run_dir))
        if m.get("status") == "complete":
            raise DataError("the run is already complete", path=str(run_dir))
        if m.get("config_hash") != header["config_hash"]:
            raise OptionError(f"the run in {run_dir} was started with another configuration, window or dataset "
                              f"(hash {m.get('config_hash')} != {header['config_hash']}; its windows: "
                              f"{m.get('window_s')} s, now {header.get('window_s')} s); give the same options",
                              option="--resume")
        if m.get("parts", "full") != header.get("parts", "full"):
            raise OptionError(f"the run in {run_dir} wrote {m.get('parts', 'full')} parts, this one would write "
                              f"{header.get('parts', 'full')}: give the same --tables", option="--resume")
        done = int(m.get("windows_done", 0))
        state = None
        if done:
            try:
                with open(run_dir / STATE_FILE, "rb") as fh:
                    saved = pickle.load(fh)
            except (OSError, pickle.UnpicklingError, EOFError) as exc:
                raise DataError(f"unreadable carried state: {exc}", path=str(run_dir / STATE_FILE)) from exc
            if saved.get("windows_done") != done:
                raise DataError(f"state is of window {saved.get('windows_done')}, manifest says {done}",
                                path=str(run_dir / STATE_FILE))
            state = saved["state"]
        store = cls(run_dir, m, trim)
        for part in (run_dir / PARTS).glob("*/w=*.parquet"):
            if int(part.stem.split("=")[1]) >= done:       # a killed window's leftovers
                part.unlink()
        store.manifest["status"] = "running"
        return store, state

    def write(self, w: Window, outputs: dict[str, pl.DataFrame]) -> None:
        for name, frame in outputs.items():
            # an empty window's frame is kept only while the table has no part at all (its schema)
            if frame.width == 0 or (frame.height == 0 and self.manifest["tables"].get(name) is not None):
                continue
            if self.trim is not None:
                frame = self.trim(name, frame)
            d = self.dir / PARTS / name
            d.mkdir(parents=True, exist_ok=True)
            # lz4: the parts are scratch (read back once, removed when the run completes), so
            # writing fast matters more than a few more bytes
            write_parquet_atomic(frame, d / f"w={w.index:06d}.parquet", compression="lz4")
            self.manifest["tables"][name] = self.manifest["tables"].get(name, 0) + frame.height
        self.written = max(self.written, w.index + 1)

    def checkpoint(self, w: Window, state: Any, **info: Any) -> None:
        """Carried state, then the manifest: the window is complete."""
        self.commit(w, self.state_bytes(w, state), **info)

    @staticmethod
    def state_bytes(w: Window, state: Any) -> bytes:
        """The carried state after window ``w`` as :meth:`checkpoint` stores it."""
        return pickle.dumps({"windows_done": w.index + 1, "state": state}, protocol=pickle.HIGHEST_PROTOCOL)

    def commit(self, w: Window, state: bytes, **info: Any) -> None:
        """:meth:`checkpoint` of a state already pickled (:meth:`state_bytes`)."""
        with atomic_path(self.dir / STATE_FILE) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(state)
        self.manifest.update(windows_done=w.index + 1, **info)
        self._commit()

    def finish(self, status: str, **info: Any) -> None:
        self.manifest.update(status=status, **info)
        self._commit()
        if status == "complete":
            shutil.rmtree(self.dir / PARTS, ignore_errors=True)
            (self.dir / STATE_FILE).unlink(missing_ok=True)

    def scratch(self) -> Path:
        """A directory for the whole-run stages' scratch files (removed with the parts)."""
        d = self.dir / PARTS / "_scratch"
        d.mkdir(parents=True, exist_ok=True)
        return d

    def table(self, name: str, columns: list[str] | None = None) -> pl.DataFrame | None:
        """Every complete window's rows of ``name`` in window order (None: no part); ``columns``:
        only those that the table has."""
        files = self._files(name)
        if not files:
            return None
        return concat_parts([pl.scan_parquet(f).select(_present(f, columns)).collect() if columns else pl.read_parquet(f)
                        for f in files])

    def iter_parts(self, name: str) -> Iterator[pl.DataFrame]:
        """Each stored window's part of ``name`` in window order, read as it is needed."""
        for f in self._files(name):
            yield pl.read_parquet(f)

    def part_files(self, name: str) -> list[Path]:
        """The files of every stored window's part of ``name``, in window order."""
        return self._files(name)

    def _files(self, name: str) -> list[Path]:
        files = sorted((self.dir / PARTS / name).glob("w=*.parquet"))
        return [f for f in files if int(f.stem.split("=")[1]) < self.written]

    def _commit(self) -> None:
        write_text_atomic(self.dir / MANIFEST, json.dumps(self.manifest, indent=1, default=str))


class MemoryParts:
    """The in-memory sink of :func:`tertiary.pipeline.process`: every window's rows kept."""

    def __init__(self) -> None:
        self.frames: dict[str, list[pl.DataFrame]] = {}

    def write(self, w: Window, outputs: dict[str, pl.DataFrame]) -> None:
        for name, frame in outputs.items():
            if frame.width and (frame.height or name not in self.frames):
                self.frames.setdefault(name, []).append(frame)

    def checkpoint(self, w: Window, state: Any, **info: Any) -> None:
        pass

    def table(self, name: str) -> pl.DataFrame | None:
        parts = self.frames.get(name)
        return concat_parts(parts) if parts else None


_END = object()


def prefetched(items: Iterable[T]) -> Iterator[T]:
    """``items`` in order, the next one produced in a background thread while the caller handles
    the current one: reading and preparing a window's part (polars, which releases the GIL)
    overlaps with storing the previous one (DuckDB, likewise) on the second core. One item
    ahead: two windows' parts in memory at most. An exception while producing an item is
    raised where that item is taken."""
    it = iter(items)
    with ThreadPoolExecutor(1, thread_name_prefix="prefetch") as pool:
        ahead = pool.submit(next, it, _END)
        while True:
            item = ahead.result()
            if item is _END:
                return
            ahead = pool.submit(next, it, _END)
            yield item


def _present(path: Path, columns: list[str]) -> list[str]:
    have = pl.read_parquet_schema(path)
    return [c for c in columns if c in have]


#: window parts :func:`read_part_groups` reads in one call (the reader's threads read them at once)
PART_GROUP = 32


def read_part_groups(files: list[Path], columns: list[str] | None = None, group: int = PART_GROUP
                     ) -> Iterator[pl.DataFrame]:
    """The rows (their ``columns``) of the window parts ``files`` in file order, ``group`` files
    read at a time as one frame: a long run's parts are hundreds of small files, whose reads one
    at a time cost more than their rows. A group whose files do not share those columns' types
    (or lack one) comes a file at a time, each with the ``columns`` it has."""
    for i in range(0, len(files), group):
        chunk = files[i:i + group]
        try:
            got = pl.read_parquet(chunk, columns=columns)
        except (pl.exceptions.SchemaError, pl.exceptions.ColumnNotFoundError, pl.exceptions.ComputeError):
            for f in chunk:
                have = pl.read_parquet_schema(f)
                yield pl.read_parquet(f, columns=None if columns is None else [c for c in columns if c in have])
            continue
        yield got


def window_blocks(files: Iterable[Path], columns: list[str], rows: int) -> Iterator[pl.DataFrame]:
    """Window parts ``files`` (in window order) read in blocks of whole windows, each of at
    least ``rows`` rows but the last."""
    held, n = [], 0
    for f in files:
        held.append(pl.read_parquet(f, columns=columns))
        n += held[-1].height
        if n >= rows:
            yield concat_parts(held)
            held, n = [], 0
    if held:
        yield concat_parts(held)


def concat_parts(frames: list[pl.DataFrame]) -> pl.DataFrame:
    """Windows' rows of one table: empty windows' frames dropped (they may lack optional columns)."""
    full = [f for f in frames if f.height] or frames[:1]
    if len(full) == 1:
        return full[0]
    try:
        return pl.concat(full, how="vertical")
    except (pl.exceptions.ShapeError, pl.exceptions.SchemaError, pl.exceptions.ComputeError):
        return pl.concat(full, how="diagonal_relaxed")


def peak_rss_mib() -> float:
    """The process's peak resident set size so far (MiB; ``ru_maxrss``, KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), "malloc_trim") if name else None
    except (OSError, AttributeError):        # not glibc (musl, macOS): nothing to hand back
        return None


def release_memory() -> None:
    """Hand the heap's freed pages back to the system (glibc ``malloc_trim``). numpy's freed
    arrays stay in the heap, fragmented, after each window: a 12-hour run's windows left 170 MiB
    of them under the whole-run stages' own peak. A no-op without glibc."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def rss_mib() -> float:
    """Current resident set size (MiB; peak where the current one is not readable)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * resource.getpagesize() / 2**20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class Meter:
    """Per-window progress: one line per window (time span, reports so far, reports/s, RSS)."""

    say: Progress
    n_windows: int
    t_start: float = field(default_factory=time.perf_counter)
    reports: int = 0

    def window(self, w: Window, t0_us: int, t1_us: int, n: int) -> None:
        self.reports += n
        dt = max(time.perf_counter() - self.t_start, 1e-9)
        fmt = utc_text
        self.say(f"window {w.index + 1}/{self.n_windows} done, {fmt(t0_us)} – {fmt(t1_us)}: {self.reports:,} reports "
                 f"so far, {self.reports / dt:,.0f} reports/s, RSS {rss_mib():,.0f} MiB")


def utc_text(us: int) -> str:
    """A grid time (µs since the Unix epoch) as ``YYYY-MM-DD HH:MM:SS`` UTC."""
    return datetime.fromtimestamp(us / US, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


#: the old private name, still imported by :mod:`tertiary.pipeline.tables`
