"""A run on ``dask.distributed``: partitions in parallel, each writing its own output, then the whole-run stages.

Partitions
    * every Monte-Carlo run is one partition (runs never interact in any stage);
    * with ``slice_s``, a run is also cut into time slices [s_k, s_k+1) on the grid from the
      recording's origin. A slice's task reads the reports with time in
      [s_k - overlap_s, s_k+1 + lookahead_s): the warm-up [s_k - overlap_s, s_k) rebuilds the
      carried state (local tracks, target ids, fusion recursions, trackers, episodes) and its
      outputs are discarded (kept aside for stitching only); rows are kept when their epoch is in
      [s_k, s_k+1) (``reports``/``rejects``: when the report's time is).

Every task reads the dataset itself (paths are shipped, never frames), runs
:func:`tertiary.pipeline.stream` with the whole recording's epoch grid origin and writes Parquet
parts under ``OUT/slices/<i>/{kept,overlap}/<table>/w=<k>.parquet``.

Ids. ``target_id`` is numbered per run in the local engine (:func:`tertiary.stages.association.associate.carry_step`),
``track_id`` per (run, method, filter) from 1 and ``cluster_id`` per (run, method): a run
partition gets exactly the local engine's ids, and a time slice's ids are local to it: they are
stitched to the previous slice's by matching in the overlap (:mod:`tertiary.pipeline.stitching`;
each boundary's matching a task, the threading of ids on the client), then every partition's
parts are relabelled in place by a task (atomic rewrites).

Evaluation. A partition that is a whole run validates the truth and its windows match the
pictures to it, step their metrics and sum the consistency lags, as a local run's do; it returns
those states, the client merges the runs' (:mod:`tertiary.pipeline.partition_states`) and the
finalize only finishes them. A time slice's pictures are matched after the stitching. The
finalize stage (alert scoring, …) runs on the client over the union of the partitions, its
independent pieces (the pictures' matching by stretch of windows, the truth's intervals and
picture by time chunk, the bound by block of aircraft) as tasks of the same cluster, and
``results.duckdb`` is built
as :func:`tertiary.pipeline.run` builds it, with a ``partitions`` table registering every output
partition (its span, rows, wall time, worker, id changes at its start boundary).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import polars as pl

from tertiary import pipeline
from tertiary.io.dataset import read_dataset
from tertiary.pipeline.stitch_effects import boundary_utc, parse_utc, stitching_effects  # noqa: F401 (re-exported)
from tertiary.store.run_store import RunStore, record_run, write_parquet_atomic
from tertiary.core.stage import T_MAX_US, T_MIN_US
from tertiary.runtime.windows import (DEFAULT_WINDOW_S, US, ReportSource, check_window, peak_rss_mib)
from tertiary.pipeline.clock import StageClock
from tertiary.pipeline.ingestion import ValidTruth, first_truth
from tertiary.core.errors import DataError, OptionError
from tertiary.pipeline.partition_states import merged_evaluation, merged_lags, merged_scores
from tertiary.pipeline.partition_writer import SCRATCH, SLICES, PartitionWriter, read_part, slice_files
from tertiary.pipeline.stitching import relabel_partition, stitch
from tertiary.runtime.fanout import DaskFanout

#: default warm-up before each time slice (s): several scans of the slowest radar, the tracker's
#: confirmation and the fusion recursions' memory (measured in benchmarks/bench_dask.py)
DEFAULT_OVERLAP_S = 120.0
#: gate of the positional match of tracks in the overlap (m)
DEFAULT_GATE_M = 500.0


@dataclass(frozen=True)
class Partition:
    """One task: a run (or every run) and a time slice of it."""

    index: int
    run: Any                 # the run value its reports have (None: the dataset has no run column)
    first_run: bool          # also takes the rows whose run is null
    slice: int               # slice index within its run
    t0_us: int               # kept span [t0_us, t1_us) (T_MIN_US / T_MAX_US: open)
    t1_us: int
    warm_us: int             # warm-up before t0_us (0 for the first slice)
    ahead_us: int            # reports after t1_us also read (0 for the last slice)

    @property
    def first_slice(self) -> bool:
        return self.t0_us <= T_MIN_US

    @property
    def whole_run(self) -> bool:
        """The partition is a run (or every run) from its first report to its last: its windows
        can evaluate what they make, as the local engine's do."""
        return self.first_slice and self.t1_us >= T_MAX_US

    def input_expr(self) -> pl.Expr:
        """The partition's input rows (null times go to the first slice, null runs to the first run)."""
        cond = pl.lit(True)
        if self.run is not None:
            cond = pl.col("run") == self.run
            if self.first_run:
                cond = cond | pl.col("run").is_null()
        t = pl.col("time").dt.epoch("us")
        if not self.first_slice:
            cond = cond & (t >= self.t0_us - self.warm_us)
        if self.t1_us < T_MAX_US:
            tc = t < self.t1_us + self.ahead_us
            cond = cond & (tc | pl.col("time").is_null() if self.first_slice else tc)
        return cond

    def coarse_expr(self, time_dtype: pl.DataType) -> pl.Expr:
        """A superset of :meth:`input_expr`'s times that a Parquet scan can take: the column
        compared with literals of its own type (a test on an expression of the column is not
        pushed into the scan), 1 ms wide of each bound."""
        lit = lambda us: pl.lit(us, pl.Int64).cast(pl.Datetime("us")).cast(time_dtype)  # noqa: E731
        cond = pl.lit(True)
        if not self.first_slice:
            cond = pl.col("time") >= lit(self.t0_us - self.warm_us - 1000)
        if self.t1_us < T_MAX_US and not self.first_slice:     # the first slice also takes null times
            cond = cond & (pl.col("time") < lit(self.t1_us + self.ahead_us + 1000))
        return cond

    def run_expr(self) -> pl.Expr:
        """The partition's rows by run only (an input without timestamps is never sliced)."""
        if self.run is None:
            return pl.lit(True)
        cond = pl.col("run") == self.run
        return cond | pl.col("run").is_null() if self.first_run else cond


@dataclass
class DaskRun:
    """What :func:`run_dask` measured (also in ``results.duckdb``'s run record)."""

    db: Path
    partitions: pl.DataFrame
    stitching: pl.DataFrame
    timings: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------- planning


def plan(dataset_dir: str | Path, cfg: pipeline.PipelineConfig, window_s: float | None, slice_s: float | None,
         overlap_s: float, lookahead_s: float | None = None, notes: list[str] | None = None
         ) -> tuple[int | None, int, list[Partition]]:
    """(grid origin µs, input rows, partitions) of a dataset: one per run × time slice."""
    notes = [] if notes is None else notes
    ds = read_dataset(dataset_dir, lazy=True)
    source = ReportSource(ds.reports, clock_offsets=pipeline.streaming.clock_offsets(cfg))   # as the windows read
    if source.n_rows == 0:
        raise DataError("reports: the table has no rows; nothing to process", path=str(dataset_dir))
    origin = (source.first_us // US) * US if source.windowable else None
    lf = source.lf
    runs: list[Any] = [None]
    if "run" in lf.collect_schema():
        runs = sorted(lf.select(pl.col("run").drop_nulls().unique()).collect()["run"].to_list()) or [None]
    bounds = _slice_bounds(cfg, source, origin, window_s, slice_s, overlap_s, notes)
    warm = int(round(overlap_s * US))
    ahead = int(round((lookahead_s if lookahead_s is not None else (0.0 if window_s else overlap_s)) * US))
    parts = []
    for r_i, run in enumerate(runs):
        for k, (t0, t1) in enumerate(bounds):
            parts.append(Partition(len(parts), run, r_i == 0, k, t0, t1, 0 if t0 <= T_MIN_US else warm,
                                   0 if t1 >= T_MAX_US else ahead))
    return origin, source.n_rows, parts


def _slice_bounds(cfg, source: ReportSource, origin: int | None, window_s: float | None, slice_s: float | None,
                  overlap_s: float, notes: list[str]) -> list[tuple[int, int]]:
    """Kept spans of the time slices on the grid from ``origin`` (one open span: no slicing)."""
    if slice_s is None:
        return [(T_MIN_US, T_MAX_US)]
    if not (math.isfinite(slice_s) and slice_s > 0):
        raise OptionError(f"must be a number of seconds > 0, got {slice_s}", option="--slice")
    if not (math.isfinite(overlap_s) and overlap_s >= 0):
        raise OptionError(f"must be a number of seconds >= 0, got {overlap_s}", option="--overlap")
    if window_s is not None:
        for name, v in (("--slice", slice_s), ("--overlap", overlap_s)):
            if abs(v / window_s - round(v / window_s)) > 1e-9:
                raise OptionError(f"{v} s is not a multiple of the window ({window_s} s): slices must start on "
                                  "window boundaries", option=name)
    if pipeline.windowable(cfg, source, 1.0, notes) is None or cfg.register:   # slices read the reports' own times
        why = "clock offsets move reports across their edges" if cfg.register else "the run cannot be cut in time"
        notes.append(f"not cut into time slices: {why}")
        return [(T_MIN_US, T_MAX_US)]
    s = int(round(slice_s * US))
    n = max(1, (source.last_us - origin) // s + 1)
    edges = [T_MIN_US] + [origin + j * s for j in range(1, n)] + [T_MAX_US]
    return list(zip(edges[:-1], edges[1:]))


# --------------------------------------------------------------------------- the partition task


def run_partition(dataset_dir: str, part: Partition, cfg: pipeline.PipelineConfig, window_s: float | None,
                  grid_origin_us: int | None, out_dir: str, tables: str = "full") -> dict:
    """The task of one partition (runs on a worker): read its reports, stream, write its parts
    (what ``tables`` stores and the whole-run stages read: :func:`~tertiary.pipeline.part_trim`)."""
    t_start = time.perf_counter()
    ds = read_dataset(dataset_dir, lazy=True)
    lf = ds.reports.lazy()
    timed = isinstance(lf.collect_schema().get("time"), pl.Datetime)
    cond = part.input_expr() if timed else part.run_expr()
    tcol = pl.col("time").dt.epoch("us") if timed else pl.lit(None, pl.Int64)
    rowmap = lf.with_row_index("__g").filter(cond).select("__g", tcol.alias("__t")).collect()
    out = Path(out_dir) / SLICES / str(part.index)
    writer = PartitionWriter(out, part, rowmap, window_s is not None, pipeline.part_trim(tables, cfg.radar_health))
    info = {"index": part.index, "n_input": rowmap.height, "worker": os.getpid(), "notes": []}
    if rowmap.height:
        source = out.parent / f"{part.index}.input.parquet"
        source.parent.mkdir(parents=True, exist_ok=True)
        try:
            reports = partition_input(lf, part, source) if timed else lf.filter(cond)
            # a whole run's windows match its pictures to the truth and step their metrics; a
            # time slice's do not (its ids are stitched afterwards): the client evaluates those
            sub = dataclasses.replace(ds, reports=reports, truth=ds.truth if part.whole_run else pl.DataFrame())
            ctx, st = pipeline.stream(sub, cfg, writer, window_s, notes=info["notes"],
                                      grid_origin_us=grid_origin_us, scored_span=(part.t0_us, part.t1_us),
                                      match=part.whole_run)
        finally:
            source.unlink(missing_ok=True)
            shutil.rmtree(out / SCRATCH, ignore_errors=True)
        info["radars"] = ctx.radars
        info["curves"] = ctx.curves         # the windows predicted the STCA curves' points
        info["scores"] = st.scores          # the kept span's association metrics, the slice's own ids
        info["evaluation"] = st.evaluation  # the run's evaluation state (None: not evaluated here)
        info["lags"] = st.lags              # its consistency statistics' lag sums (None: likewise)
    info.update(counts=writer.counts(), rows=writer.rows, seconds=time.perf_counter() - t_start,
                peak_rss_mib=round(peak_rss_mib(), 1))
    return info


def partition_input(lf: pl.LazyFrame, part: Partition, path: Path) -> pl.LazyFrame:
    """The partition's input rows (:meth:`Partition.input_expr`, in input order) written to
    ``path`` and scanned from there. The windows of the partition then read their rows from a
    plain scan, which takes their time test: on ``lf.filter(...)`` the row index the stream
    puts on its input came after the filter and kept every window's test out of the scan, so
    each window would read the whole partition again."""
    coarse = part.coarse_expr(lf.collect_schema()["time"])
    lf.filter(coarse).filter(part.input_expr()).sink_parquet(path, compression="lz4", maintain_order=True)
    return pl.scan_parquet(path)


# --------------------------------------------------------------------------- reading partitions back


class UnionParts:
    """The finalize stage's view of every partition: ``table(name)`` concatenates them."""

    def __init__(self, out: Path, n: int) -> None:
        self.out, self.n = out, n

    def table(self, name: str, columns: list[str] | None = None) -> pl.DataFrame | None:
        """Every partition's rows of ``name`` (``columns``: only those, where a partition has them;
        only those are read: the whole of a large table would not fit the client's memory)."""
        frames = [f for i in range(self.n) if (f := read_part(self.out, i, name, columns=columns)) is not None]
        if not frames:
            return None
        # a partition may lack an optional column (null there)
        return frames[0] if len(frames) == 1 else pl.concat(frames, how="diagonal_relaxed")

    def part_files(self, name: str) -> list[Path]:
        """The files of every partition's rows of ``name``, in partition and window order."""
        return [f for i in range(self.n) for f in slice_files(self.out, i, "kept", name)]

    def iter_parts(self, name: str) -> Iterator[pl.DataFrame]:
        """Each partition's rows of ``name``, read as they are needed."""
        for i in range(self.n):
            for f in slice_files(self.out, i, "kept", name):
                yield pl.read_parquet(f)

    def scratch(self) -> Path:
        """A directory for the finalize stage's scratch files (removed when it ends)."""
        d = self.out / SLICES / SCRATCH
        d.mkdir(parents=True, exist_ok=True)
        return d


# --------------------------------------------------------------------------- the run


def run_dask(dataset_dir: str | Path, out_dir: str | Path, cfg: pipeline.PipelineConfig | None = None, *,
             workers: int | None = None, scheduler: str | None = None, client: Any = None,
             window_s: float | None = DEFAULT_WINDOW_S, slice_s: float | None = None,
             overlap_s: float = DEFAULT_OVERLAP_S, lookahead_s: float | None = None,
             gate_m: float = DEFAULT_GATE_M, progress: pipeline.Progress | None = None,
             tables: str = "database") -> Path:
    """Run the job on ``dask.distributed`` and write ``out_dir/results.duckdb``; returns its path.

    ``client``: an existing :class:`distributed.Client`; else ``Client(scheduler)`` when an address
    is given, else a ``LocalCluster(n_workers=workers, threads_per_worker=1, processes=True)``.
    Partitions: every Monte-Carlo run, and with ``slice_s`` every time slice of it (warm-up
    ``overlap_s`` before each slice, ``lookahead_s`` after it: default 0 with windows — a window's
    outputs depend on no later report — else ``overlap_s``). ``window_s``: the windows each task
    streams in (slice and overlap must be multiples of it). ``tables="parquet"``: the
    partitions' parts are registered in the database, not copied (:func:`tertiary.pipeline.run`).
    See the module docstring."""
    res = run_dask_detailed(dataset_dir, out_dir, cfg, workers=workers, scheduler=scheduler, client=client,
                            window_s=window_s, slice_s=slice_s, overlap_s=overlap_s, lookahead_s=lookahead_s,
                            gate_m=gate_m, progress=progress, tables=tables)
    return res.db


def _client(workers: int | None, scheduler: str | None, client: Any):
    """(client, closer) for the run."""
    from distributed import Client, LocalCluster
    if client is not None:
        return client, lambda: None
    if scheduler:
        try:
            c = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise OptionError(f"cannot reach the Dask scheduler at {scheduler}: {exc}", option="--scheduler") from exc
        return c, c.close
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise OptionError(f"must be an integer >= 1, got {workers}", option="--workers")
    cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                           dashboard_address=":0")     # any free port: two clusters at once do not collide
    c = Client(cluster)
    return c, lambda: (c.close(), cluster.close())


def run_dask_detailed(dataset_dir: str | Path, out_dir: str | Path, cfg: pipeline.PipelineConfig | None = None, *,
                      workers: int | None = None, scheduler: str | None = None, client: Any = None,
                      window_s: float | None = DEFAULT_WINDOW_S, slice_s: float | None = None,
                      overlap_s: float = DEFAULT_OVERLAP_S, lookahead_s: float | None = None,
                      gate_m: float = DEFAULT_GATE_M, progress: pipeline.Progress | None = None,
                      tables: str = "database") -> DaskRun:
    """:func:`run_dask` returning what it measured (partitions, stitching, timings)."""
    t_wall = time.perf_counter()
    say = progress or (lambda _m: None)
    cfg = pipeline.adapt_to_scenario(pipeline.check_config(cfg), read_dataset(dataset_dir, lazy=True))
    window_s = check_window(window_s)
    out = Path(out_dir)
    pipeline.check_tables(tables, out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create the run directory: {exc.strerror or exc}", path=str(out)) from exc
    shutil.rmtree(out / SLICES, ignore_errors=True)
    notes: list[str] = []
    timings: dict[str, float] = {}
    t = time.perf_counter()
    origin, n_rows, parts = plan(dataset_dir, cfg, window_s, slice_s, overlap_s, lookahead_s, notes)
    timings["plan_s"] = time.perf_counter() - t
    say(f"{len(parts)} partition(s)")
    c, close = _client(workers, scheduler, client)
    try:
        return _run_on(c, dataset_dir, out, cfg, parts, window_s, origin, n_rows, gate_m, timings, say, tables,
                       slice_s, overlap_s, notes, t_wall)
    finally:
        close()


def _run_on(c: Any, dataset_dir: str | Path, out: Path, cfg: pipeline.PipelineConfig, parts: list[Partition],
            window_s: float | None, origin: int | None, n_rows: int, gate_m: float, timings: dict, say,
            tables: str, slice_s: float | None, overlap_s: float, notes: list[str], t_wall: float) -> DaskRun:
    """The partitions on the cluster of client ``c``, then the finalize on the client, whose
    independent pieces (:data:`~tertiary.pipeline.streaming.RunContext.fanout`) are tasks of the
    same cluster."""
    ds = read_dataset(dataset_dir, lazy=True)
    source = ReportSource(ds.reports, cfg.limits)
    span = None if source.first_us is None else (source.first_us, source.last_us)   # the truth's window
    # the truth is validated on the client while the partitions run (it waits for them otherwise)
    truth_notes: list[str] = []
    with ThreadPoolExecutor(1) as early:
        truth = early.submit(_validated_truth, ds, cfg, truth_notes, source, UnionParts(out, len(parts)))
        infos, maps, stitching = _distribute(c, str(Path(dataset_dir).resolve()), str(out.resolve()), parts, cfg,
                                             window_s, origin, gate_m, timings, say, tables)
        first, timings["truth_early_s"] = truth.result()
    say("finalize")
    radars = next((i["radars"] for i in infos if "radars" in i), None)
    fanout = DaskFanout(c)
    ctx = pipeline.RunContext(radars if radars is not None else pl.DataFrame(), [], ds.origin, origin, 0,
                              curves=all(i.get("curves", True) for i in infos if i["n_input"]), report_span=span,
                              truth=first, fanout=fanout)
    counts: dict[str, int] = {}
    for i in infos:
        for k, v in i["counts"].items():
            counts[k] = counts.get(k, 0) + v
        notes.extend(n for n in i["notes"] if n not in notes)
    notes.extend(n for n in truth_notes if n not in notes)
    # the association metrics the partitions scored, in the run's ids and merged
    st = dataclasses.replace(pipeline.init_stream_state(cfg), counts=counts,
                             scores=merged_scores(parts, infos, maps), evaluation=merged_evaluation(parts, infos),
                             lags=merged_lags(parts, infos))
    table = _partition_table(parts, infos, stitching, out)
    with RunStore.create(out) as store:
        sink = pipeline.store_sink(store, notes, tables)

        t = time.perf_counter()
        failure: Exception | None = None
        res = None
        try:
            # each whole-run stage said as it starts, as the local engine does: the client's
            # finalize is long, and silent it looks stuck
            res = pipeline.finalize(ds, cfg, ctx, st, UnionParts(out, len(parts)), n_rows, progress=say,
                                    sink=sink, notes=notes)
        except Exception as exc:  # recorded, then re-raised
            failure = exc
        timings["finalize_s"] = time.perf_counter() - t
        # the finalize's pieces on the workers: the client waited for them (wall) while they worked
        shipped = [r for r in fanout.record if r["where"] == "workers"]
        timings["fanout_wall_s"] = sum(r["wall_s"] for r in shipped)
        timings["fanout_task_s_sum"] = sum(sum(r["task_s"]) for r in shipped)
        timings["fanout_task_s_max"] = max((max(r["task_s"]) for r in shipped), default=0.0)
        shutil.rmtree(out / SLICES / SCRATCH, ignore_errors=True)
        store.write("partitions", table)
        if stitching.height:
            store.write("stitching", stitching)
        timings["wall_s"] = time.perf_counter() - t_wall
        info = {"scenario": ds.scenario.name, "scenario_toml": pipeline.scenario_text(ds, notes),
                "config": pipeline.config_dict(cfg), "created_utc": datetime.now(timezone.utc).isoformat(
                    timespec="seconds"), "versions": pipeline.versions(), "window_s": window_s,
                "engine": "dask", "slice_s": slice_s, "overlap_s": overlap_s, "partitions": len(parts),
                "notes": notes, "timings": {**(res.timings if res else {}), **timings},
                "fanout": [{**r, "wall_s": round(r["wall_s"], 3), "task_s": [round(x, 3) for x in r["task_s"]]}
                           for r in fanout.record]}
        if res is not None:
            # the client's memory by stage; each worker's is in the partitions table
            info.update(rows=res.counts, memory_mib=res.memory_mib, status="completed")
        else:
            info.update(status="failed", failed_stage=getattr(failure, "tertiary_stage", "finalize"),
                        error=f"{type(failure).__name__}: {failure}")
        record_run(store, info)
    if failure is not None:
        raise failure
    return DaskRun(out / "results.duckdb", table, stitching, timings)


def _validated_truth(ds: Any, cfg: pipeline.PipelineConfig, notes: list[str], source: ReportSource,
                     parts: UnionParts) -> tuple[ValidTruth | None, float]:
    """(the truth validated into the finalize's scratch as a local run's before its windows, or
    None: the finalize validates it; seconds)."""
    t = time.perf_counter()
    got = first_truth(ds, cfg, notes, source, parts, StageClock(lambda _m: None))
    return got, time.perf_counter() - t


def _distribute(c: Any, dataset: str, out: str, parts: list[Partition], cfg: pipeline.PipelineConfig,
                window_s: float | None, origin: int | None, gate_m: float, timings: dict, say,
                tables: str = "full") -> tuple[list[dict], dict, pl.DataFrame]:
    """The partitions' tasks, the stitching (its pieces as tasks, threaded on the client), the
    relabelling tasks."""
    from distributed import as_completed
    t = time.perf_counter()
    futs = [c.submit(run_partition, dataset, p, cfg, window_s, origin, out, tables, pure=False,
                     key=f"tertiary-partition-{p.index}-{time.time_ns()}") for p in parts]
    infos: dict[int, dict] = {}
    for fut in as_completed(futs):
        info = fut.result()                       # a failed task raises here, with its traceback
        info["done_s"] = time.perf_counter() - t
        infos[info["index"]] = info
        say(f"partition {info['index'] + 1}/{len(parts)} done in {info['seconds']:.1f} s")
    timings["partitions_s"] = time.perf_counter() - t
    timings["partition_task_s_sum"] = sum(i["seconds"] for i in infos.values())
    t = time.perf_counter()
    pieces = DaskFanout(c)
    maps, stitching = stitch(Path(out), parts, gate_m, pieces) if len(parts) > 1 else ({}, pl.DataFrame())
    timings["stitch_s"] = time.perf_counter() - t
    # the boundaries' pieces on the workers; the rest of stitch_s is the client's threading of them
    timings["stitch_pieces_wall_s"] = sum(r["wall_s"] for r in pieces.record)
    timings["stitch_task_s_sum"] = sum(sum(r["task_s"]) for r in pieces.record)
    timings["stitch_task_s_max"] = max((max(r["task_s"]) for r in pieces.record), default=0.0)
    # each boundary's continuity as soon as it is known (a long run's log tells it before the
    # whole-run stages end; the stitching table holds the same rows)
    for row in stitching.iter_rows(named=True) if stitching.height else ():
        say(f"stitched at {row['boundary_utc']}: targets {row['targets_continued']}/{row['targets']}, "
            f"tracks {row['tracks_continued']}/{row['tracks']}, clusters {row['clusters_continued']}/"
            f"{row['clusters']} continued")
    t = time.perf_counter()
    if maps:
        c.gather([c.submit(relabel_partition, out, i, m, pure=False) for i, m in maps.items()])
    timings["relabel_s"] = time.perf_counter() - t
    return [infos[p.index] for p in parts], maps, stitching


def _partition_table(parts: list[Partition], infos: list[dict], stitching: pl.DataFrame, out: Path) -> pl.DataFrame:
    """The ``partitions`` table: every output partition, its span, rows, time and worker."""
    return pl.DataFrame({
        "partition": [p.index for p in parts], "run": [None if p.run is None else int(p.run) for p in parts],
        "slice": [p.slice for p in parts],
        "kept_from_utc": [boundary_utc(p.t0_us) for p in parts],
        "kept_to_utc": [boundary_utc(p.t1_us) for p in parts],
        "warmup_s": [p.warm_us / US for p in parts],
        "input_rows": [i["n_input"] for i in infos],
        "rows": [json.dumps(i["rows"]) for i in infos],
        "task_s": [i["seconds"] for i in infos],
        "worker_pid": [i["worker"] for i in infos],
        # the worker process's peak resident memory by the end of this task (a worker runs several)
        "worker_peak_rss_mib": [i.get("peak_rss_mib") for i in infos],
        "path": [str((out / SLICES / str(p.index)).resolve()) for p in parts],
    }, schema_overrides={"run": pl.Int64})
