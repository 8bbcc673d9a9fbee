"""Ingest: the data contract applied to a dataset's tables (:func:`ingest`), every rule of the job
that can reject a report (:func:`screen`, what ``tertiary validate`` reports) and the validation
of the truth, whole or from disk to disk (:func:`validate_truth`, :func:`stream_truth`)."""

from __future__ import annotations

import shutil
import warnings
from collections.abc import Iterator
from itertools import chain
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import polars as pl

from tertiary import contract
from tertiary.core import geo
from tertiary.core.errors import DataError
from tertiary.evaluation.evaluate import (NEIGHBOUR_COLUMNS, Reference, reference_files, write_reference,
                                          write_reference_pieces)
from tertiary.evaluation.matching import neighbour_times
from tertiary.io.dataset import Dataset
from tertiary.pipeline.config import PipelineConfig, check_config
from tertiary.pipeline.tables import StreamedTable
from tertiary.runtime.windows import ReportSource
from tertiary.sensors import registration
from tertiary.sensors.collection import collection_stage
from tertiary.stages import align as align_stage
from tertiary.stages.align import AlignPlan
from tertiary.stages.flight_data import check_flight_plans, empty_flight_plans

__all__ = ["Ingested", "StreamedTruth", "ValidTruth", "first_truth", "truth_table", "plausible_span",
           "report_span_window", "ingest",
           "screen", "validate_table", "validate_truth", "stream_truth",
           "truth_lazy", "span_window", "truth_window", "no_rejects", "registered", "valid_flight_plans",
           "stage_rejects_table",
           "TRUTH_PART_ROWS", "TRUTH_WHOLE_ROWS", "TRUTH_BATCH_ROWS"]


@dataclass
class Ingested:
    """Validated input tables and every rejected row with its reason.

    ``report_rows`` maps each valid report's ``report_id`` to its input row; ``plan`` holds the
    align stage's decisions once :func:`screen` has run."""

    radars: pl.DataFrame
    reports: pl.DataFrame
    truth: pl.DataFrame
    rejects: pl.DataFrame
    notes: list[str] = field(default_factory=list)
    report_rows: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(
        schema={"report_id": pl.UInt64, "row_index": pl.UInt64}))
    plan: AlignPlan | None = None

    @property
    def valid_reports(self) -> int:
        """Reports the job will align (0: ``run`` stops with "no valid report left")."""
        return int(self.plan.keep.sum()) if self.plan is not None else 0


def validate_table(frame: pl.DataFrame, kind: str, strict: bool, notes: list[str], **kw: Any
                   ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(clean, packed rejects, raw rejects) of one input table; its unsorted-time warnings go to
    ``notes``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", contract.UnsortedTimeWarning)
        out = contract.validate(frame, kind, strict=strict, **kw)
    notes.extend(str(w.message) for w in caught if issubclass(w.category, contract.UnsortedTimeWarning))
    if strict:
        return out, contract.empty_frame("rejects"), pl.DataFrame()
    clean, rejects = out
    if contract.INPUT_ROW in rejects.columns:      # a window's rows: their position in the whole input
        rejects = rejects.with_columns(pl.col(contract.INPUT_ROW).cast(pl.UInt64).alias(contract.ROW_INDEX))
    rejects = rejects.drop(contract.INPUT_ROW, strict=False)
    return clean, contract.rejects_table(rejects, kind, "ingest"), rejects


#: truth rows validated at a time (whole aircraft) in finalize when the truth is longer than
#: TRUTH_WHOLE_ROWS: each part is gathered, validated and put back in input order (memory); a
#: part's rejects are packed together (a float column holding a NaN anywhere in them is spelt
#: as text in their details)
TRUTH_PART_ROWS = 250_000
#: truth rows validated in one call (its rejects still packed part by part): validation holds
#: about one copy of the table beside the input, the parts' gathers and reordering cost more
#: time than the checks
TRUTH_WHOLE_ROWS = 2_000_000


def validate_truth(ds: Dataset, cfg: PipelineConfig, notes: list[str], window) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(clean truth, packed rejects): :func:`validate_table` of the whole truth, computed in one
    call up to TRUTH_WHOLE_ROWS rows and a few aircraft at a time above. Every truth check is
    row-wise or within one aircraft (its key and its order are (truth_id, time)), the table's
    median time is taken once from the whole and each part carries its rows' input positions,
    so the clean table (in input order), its rejects and the notes are those of one call on the
    whole; a truth longer than TRUTH_PART_ROWS has its rejects packed part by part either way."""
    truth = contract.as_frame(ds.truth, "truth")
    kw = dict(limits=cfg.limits, time_window=window)
    if truth.height == 0:
        return truth, no_rejects()
    if (cfg.strict or truth.height <= TRUTH_PART_ROWS or truth.schema.get("truth_id") is None
            or truth.schema.get("time") != contract.TIME or contract.INPUT_ROW in truth.columns):
        clean, rej, _ = validate_table(truth, "truth", cfg.strict, notes, **kw)
        return clean, rej
    med = contract.table_median_time(truth, cfg.limits)
    # a group-by on the frame would first copy every column into one chunk: on the key alone
    sizes = truth.select("truth_id").group_by("truth_id").len().sort("truth_id", nulls_last=True)
    part_of = sizes.select("truth_id", (pl.col("len").cum_sum() // TRUTH_PART_ROWS).alias("__part"))
    where = truth.select("truth_id").join(part_of, on="truth_id", how="left", nulls_equal=True,
                                          maintain_order="left")["__part"]
    if truth.height <= TRUTH_WHOLE_ROWS:
        clean, _, raw = validate_table(truth, "truth", False, notes, median_time=med, **kw)
        return clean, _pack_by_part(raw, where)
    cleans, rejs = [], []
    for k in range(int(part_of["__part"].max()) + 1):
        rows = (where == k).arg_true()
        # a part of consecutive rows (a truth in aircraft order) is a slice, not a copy
        run = rows.len() and int(rows[-1]) - int(rows[0]) + 1 == rows.len()
        part = truth.slice(int(rows[0]), rows.len()) if run else truth[rows]
        part = part.with_columns(rows.cast(pl.UInt64).alias(contract.INPUT_ROW))
        # the parts' unsorted-time notes are left out: the whole table's is taken below
        clean, rej, _ = validate_table(part, "truth", False, [], median_time=med, **kw)
        cleans.append(clean)
        rejs.append(rej)
    del truth, where
    clean = pl.concat(cleans, how="vertical")
    del cleans
    in_order = clean[contract.INPUT_ROW].is_sorted()
    order = None if in_order else clean[contract.INPUT_ROW].arg_sort()
    clean = clean.drop(contract.INPUT_ROW)
    if order is not None:
        # back in input order a column at a time, each source column released once gathered:
        # the table is never held twice (a whole-frame sort would)
        gathered = {}
        for name in clean.columns:
            gathered[name] = clean[name].gather(order)
            clean = clean.drop(name)
        clean = pl.DataFrame(gathered)
        del gathered
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", contract.UnsortedTimeWarning)
        clean = contract.sort_tracks(clean, "truth")
    notes.extend(str(w.message) for w in caught if issubclass(w.category, contract.UnsortedTimeWarning))
    return clean, pl.concat(rejs, how="vertical_relaxed").sort("row_index", maintain_order=True)


def _pack_by_part(raw: pl.DataFrame, where: pl.Series) -> pl.DataFrame:
    """The raw truth rejects packed as :func:`validate_truth`'s parts pack them (``where``: each
    input row's part), in row order."""
    if raw.height == 0:
        return contract.rejects_table(raw, "truth", "ingest")
    return _pack_parts(raw, where.gather(raw[contract.ROW_INDEX].cast(pl.UInt64)))


def _pack_parts(raw: pl.DataFrame, part: pl.Series) -> pl.DataFrame:
    """The raw truth rejects packed part by part (``part``: each reject's), in row order."""
    if raw.height == 0:
        return contract.rejects_table(raw, "truth", "ingest")
    packed = [contract.rejects_table(rows.drop("__part"), "truth", "ingest")
              for _, rows in raw.with_columns(part.alias("__part")).group_by("__part", maintain_order=True)]
    return pl.concat(packed, how="vertical_relaxed").sort("row_index", maintain_order=True)


#: input truth rows read at a time by :func:`stream_truth`, and the rows of each file of the
#: reference it writes in input order
TRUTH_BATCH_ROWS = 262_144
#: rows per row group of a validated part's scratch file (:func:`stream_truth`)
OUT_GROUP_ROWS = 16_384


@dataclass
class StreamedTruth:
    """The validated truth of an on-disk run, on disk (:func:`stream_truth`): its reference
    directory (None when no row is clean), its number of clean rows and its schema (``empty``)."""

    reference: Path | None
    rows: int
    empty: pl.DataFrame

    def pieces(self) -> Iterator[pl.DataFrame]:
        """The clean truth, in order, a reference file at a time (for the run database)."""
        for f in reference_files(self.reference):
            yield pl.read_parquet(f, columns=list(self.empty.columns))


def truth_lazy(ds: Dataset) -> pl.LazyFrame | None:
    """The dataset's truth as a lazy frame (None: it has none in a frame)."""
    truth = ds.truth
    return truth if isinstance(truth, pl.LazyFrame) else truth.lazy() if isinstance(truth, pl.DataFrame) else None


def stream_truth(ds: Dataset, cfg: PipelineConfig, notes: list[str], window,
                 scratch: Path) -> tuple[StreamedTruth, pl.DataFrame] | None:
    """(the clean truth on disk, packed rejects): :func:`validate_truth` from disk to disk, so
    neither the input truth nor the clean one is ever held whole (memory). None where
    :func:`validate_truth` validates the table in one call (strict mode, a small or malformed table): the caller does that.

    A truth whose aircraft's times increase across the input batches (a recording written a time
    span per file) is validated in one pass (:func:`_stream_in_order`). Otherwise one streaming
    pass reads the input ``TRUTH_BATCH_ROWS`` at a time and files each batch's rows
    by aircraft part (:func:`validate_truth`'s parts); each part is validated, put back in input
    order, given its samples' neighbour times and kept as one scratch file, from which each input
    batch reads its own row groups; the clean rows are then written as a reference
    (:func:`write_reference_pieces`) in :func:`validate_truth`'s order — input order, or
    (truth_id, time) when some aircraft's times decrease — a file per input batch or per part.
    Every check is row-wise or within one aircraft, the median time is the whole table's (read a
    batch at a time: :func:`~tertiary.contract.validation.streamed_median_time`) and
    the unsorted-time note adds the parts' counts, so the rows, rejects and notes are
    :func:`validate_truth`'s."""
    lf = truth_lazy(ds)
    if lf is None or cfg.strict:
        return None
    sch = lf.collect_schema()
    if sch.get("truth_id") is None or sch.get("time") != contract.TIME or contract.INPUT_ROW in sch:
        return None
    n = lf.select(pl.len()).collect().item()
    if n <= TRUTH_PART_ROWS:
        return None
    kw = dict(limits=cfg.limits, time_window=window)

    def batches() -> Iterator[pl.Series]:
        # one streaming pass: a slice of the scan per batch would read every input file's footer
        for b in lf.select("time").collect_batches(chunk_size=TRUTH_BATCH_ROWS):
            yield b["time"]
    med = contract.streamed_median_time(batches, cfg.limits)
    if "run" not in sch:
        in_order = _stream_in_order(lf, med, kw, scratch)
        if in_order is not None:
            return in_order
    sizes = lf.select("truth_id").group_by("truth_id").len().sort("truth_id", nulls_last=True).collect()
    part_of = sizes.select("truth_id", (pl.col("len").cum_sum() // TRUTH_PART_ROWS).alias("__part"))
    n_parts = int(part_of["__part"].max()) + 1
    work = scratch / "truth"
    shutil.rmtree(work, ignore_errors=True)        # a resumed finalize's leftovers
    n_batches = -(-n // TRUTH_BATCH_ROWS)
    _file_by_part(lf, part_of, work)
    rejs, n_bad, n_groups, clean_rows, empty = [], 0, 0, 0, None
    reach: dict[int, tuple[int, int]] = {}           # each part's first and last input batch
    for k in range(n_parts):
        src = work / f"in-{k:06d}"
        part = pl.read_parquet(sorted(src.glob("*.parquet")))
        shutil.rmtree(src)
        # the parts' unsorted-time notes are left out: the whole table's is made below
        clean, rej, _ = validate_table(part, "truth", False, [], median_time=med, **kw)
        del part
        rejs.append(rej)
        clean = clean.sort(contract.INPUT_ROW)                 # input order (validation may have sorted)
        empty = clean.drop(contract.INPUT_ROW).clear()
        bad, groups = contract.unsorted_groups(clean, "truth")
        n_bad, n_groups, clean_rows = n_bad + bad, n_groups + groups, clean_rows + clean.height
        if not clean.height:
            continue
        times = neighbour_times(clean)
        # one file a part, in input order, its row groups small enough that an input batch's
        # read skips the rest: a file per (batch, part) would cost a write each, thousands a day
        clean.with_columns(times["__prev"], times["__next"]).write_parquet(
            work / f"out-{k:06d}.parquet", compression="lz4", row_group_size=OUT_GROUP_ROWS)
        reach[k] = (int(clean[contract.INPUT_ROW][0]) // TRUTH_BATCH_ROWS,
                    int(clean[contract.INPUT_ROW][-1]) // TRUTH_BATCH_ROWS)
    rejects = pl.concat(rejs, how="vertical_relaxed").sort("row_index", maintain_order=True)
    if n_bad:
        notes.append(contract.unsorted_message("truth", n_bad, n_groups))
    if clean_rows == 0:
        shutil.rmtree(work, ignore_errors=True)
        return StreamedTruth(None, 0, empty), rejects

    def by_part() -> Iterator[pl.DataFrame]:
        # the parts hold whole aircraft, in truth_id order
        for k in reach:
            f = work / f"out-{k:06d}.parquet"
            yield pl.read_parquet(f).sort(list(contract.table_order("truth")), maintain_order=True).drop(
                contract.INPUT_ROW)
            f.unlink()

    def by_batch() -> Iterator[pl.DataFrame]:
        row = pl.col(contract.INPUT_ROW)
        for b in range(n_batches):
            # an input batch's rows are in the files of the parts whose rows it spans
            mine = [k for k, (first, last) in reach.items() if first <= b <= last]
            if not mine:
                continue
            piece = (pl.scan_parquet([work / f"out-{k:06d}.parquet" for k in mine])
                     .filter(row.is_between(b * TRUTH_BATCH_ROWS, (b + 1) * TRUTH_BATCH_ROWS, closed="left"))
                     .collect().sort(contract.INPUT_ROW))
            if piece.height:
                yield piece.drop(contract.INPUT_ROW)
            for k in mine:
                if reach[k][1] == b:
                    (work / f"out-{k:06d}.parquet").unlink()

    path = write_reference_pieces(by_part() if n_bad else by_batch(), scratch / "reference")
    shutil.rmtree(work, ignore_errors=True)
    return StreamedTruth(path, clean_rows, empty), rejects


def _exact_batches(lf: pl.LazyFrame, rows: int) -> Iterator[pl.DataFrame]:
    """``lf`` in consecutive batches of exactly ``rows`` rows (the last one shorter): batch b holds
    input rows [b·rows, (b+1)·rows), whatever sizes the scan's batches come in."""
    held: list[pl.DataFrame] = []
    have = 0
    for batch in lf.collect_batches(chunk_size=rows):
        held.append(batch)
        have += batch.height
        while have >= rows:
            joined = pl.concat(held, rechunk=False) if len(held) > 1 else held[0]
            yield joined.slice(0, rows)
            rest = joined.slice(rows)
            held, have = ([rest] if rest.height else []), rest.height
    if have:
        yield pl.concat(held) if len(held) > 1 else held[0]


class _NotInOrder(Exception):
    """A rejected row decides a neighbour time across input batches: :func:`_stream_in_order`
    cannot give :func:`validate_truth`'s reference in one pass."""


@dataclass
class _Order:
    """What one pass over (truth_id, time) says of the input batches (:func:`_batch_order`):
    each aircraft's rows per batch (``sizes``: rows per aircraft; ``firsts``: per batch, each
    aircraft's first time in it; ``nexts``: per (aircraft, batch) its first time in the next
    batch that holds it)."""

    sizes: pl.DataFrame
    firsts: list[pl.DataFrame]
    nexts: pl.DataFrame


def _batch_order(lf: pl.LazyFrame) -> _Order | None:
    """:class:`_Order` of the input batches, or None unless every aircraft's times increase in
    input order across batches (within one, they may repeat: validation keeps the first) and no
    id or time is missing. Then every check, neighbour time and first row of a repeated key is
    within a batch or carried from the one before, and one pass gives :func:`validate_truth`'s
    result. Reads two columns."""
    t = pl.col("time")
    sizes, firsts, nexts = [], [], []
    last: pl.DataFrame | None = None           # each aircraft's last time so far and its batch
    for b, batch in enumerate(_exact_batches(lf.select("truth_id", "time"), TRUTH_BATCH_ROWS)):
        if batch["truth_id"].null_count() or batch["time"].null_count():
            return None
        per = batch.group_by("truth_id").agg(t.first().alias("__first"), t.last().alias("__last"),
                                             (t.diff() >= timedelta(0)).all().alias("__sorted"), pl.len())
        if not per["__sorted"].all():
            return None
        if last is not None:
            seen = per.join(last, on="truth_id", how="inner")
            if seen.height and (seen["__first"] <= seen["__was"]).any():
                return None
            nexts.append(seen.select("truth_id", "__b", pl.col("__first").alias("__next")))
            last = pl.concat([last.join(per, on="truth_id", how="anti"),
                              per.select("truth_id", pl.col("__last").alias("__was"), pl.lit(b).alias("__b"))])
        else:
            last = per.select("truth_id", pl.col("__last").alias("__was"), pl.lit(b).alias("__b"))
        sizes.append(per.select("truth_id", "len"))
        firsts.append(per.select("truth_id", "__first"))
    if last is None:
        return None
    no_next = last.clear().select("truth_id", "__b", pl.col("__was").alias("__next"))
    return _Order(pl.concat(sizes).group_by("truth_id").agg(pl.col("len").sum()).sort("truth_id"), firsts,
                  pl.concat(nexts) if nexts else no_next)


def _stream_in_order(lf: pl.LazyFrame, med: datetime | None, kw: dict, scratch: Path
                     ) -> tuple[StreamedTruth, pl.DataFrame] | None:
    """:func:`stream_truth`'s result in one pass over the input, when its aircraft's times
    increase across input batches (:func:`_batch_order`; a recording written a time span per
    file, each sorted by aircraft, is): each batch validated as read, its samples' neighbour times
    within it, from the aircraft's last clean sample before (carried) and from its first time
    in its next batch (the order pass), written as that batch's reference file. None: another
    order, or a rejected row on which a neighbour time across batches turns (the caller's parts
    then do it)."""
    order = _batch_order(lf)
    if order is None:
        return None
    raws: list[pl.DataFrame] = []
    got = {"rows": 0, "empty": None}

    def pieces() -> Iterator[pl.DataFrame]:
        before: pl.DataFrame | None = None     # each aircraft's last clean time so far
        for b, batch in enumerate(_exact_batches(lf, TRUTH_BATCH_ROWS)):
            lo = b * TRUTH_BATCH_ROWS
            batch = batch.with_columns(pl.int_range(lo, lo + batch.height, dtype=pl.UInt64).alias(contract.INPUT_ROW))
            clean, _, raw = validate_table(batch, "truth", False, [], median_time=med, **kw)
            del batch
            clean = clean.sort(contract.INPUT_ROW)
            if got["empty"] is None:
                got["empty"] = clean.drop(contract.INPUT_ROW).clear()
            raws.append(raw)
            if raw.height and before is not None:
                _check_edges(clean, order.firsts[b], before)
            if not clean.height:
                continue
            got["rows"] += clean.height
            piece = _with_neighbours(clean, before, order.nexts.filter(pl.col("__b") == b))
            per = clean.group_by("truth_id").agg(pl.col("time").last().alias("__was"))
            before = per if before is None else pl.concat([before.join(per, on="truth_id", how="anti"), per])
            yield piece.drop(contract.INPUT_ROW)

    try:
        each = pieces()
        first = next(each, None)                 # None: no clean row, nothing to write
        path = None if first is None else write_reference_pieces(chain([first], each), scratch / "reference")
    except _NotInOrder:
        return None
    raw = pl.concat(raws, how="vertical_relaxed")
    part_of = order.sizes.select("truth_id", (pl.col("len").cum_sum() // TRUTH_PART_ROWS).alias("__part"))
    where = raw.select("truth_id").join(part_of, on="truth_id", how="left", maintain_order="left")["__part"]
    return StreamedTruth(path, got["rows"], got["empty"]), _pack_parts(raw, where)


def _check_edges(clean: pl.DataFrame, firsts: pl.DataFrame, before: pl.DataFrame) -> None:
    """Raise :class:`_NotInOrder` if an aircraft with a clean sample in an earlier batch lost its
    first row of this batch to validation: the earlier batch's last sample already took that
    row's time as its next (:func:`_batch_order`)."""
    kept = clean.group_by("truth_id").agg(pl.col("time").first().alias("__kept"))
    edge = firsts.join(before.select("truth_id"), on="truth_id").join(kept, on="truth_id", how="left")
    if edge.height and edge.select((pl.col("__kept").is_null() | (pl.col("__kept") != pl.col("__first"))).any()).item():
        raise _NotInOrder


def _with_neighbours(clean: pl.DataFrame, before: pl.DataFrame | None, nexts: pl.DataFrame) -> pl.DataFrame:
    """A batch's clean rows (times increasing per aircraft) with ``__prev`` and ``__next``: within
    the batch, and at each aircraft's first and last row from ``before`` (its last clean time
    in earlier batches) and ``nexts`` (its first time in its next batch)."""
    times = neighbour_times(clean)
    out = clean.with_columns(times["__prev"], times["__next"])
    tid = pl.col("truth_id")
    if before is not None:
        out = out.join(before, on="truth_id", how="left", maintain_order="left").with_columns(
            pl.when(tid.is_first_distinct()).then(pl.col("__was")).otherwise(pl.col("__prev")).alias("__prev")
        ).drop("__was")
    if nexts.height:
        out = out.join(nexts.select("truth_id", pl.col("__next").alias("__then")), on="truth_id", how="left",
                       maintain_order="left").with_columns(
            pl.when(tid.is_last_distinct()).then(pl.col("__then")).otherwise(pl.col("__next")).alias("__next")
        ).drop("__then")
    return out


def _file_by_part(lf: pl.LazyFrame, part_of: pl.DataFrame, work: Path) -> None:
    """Every input row of ``lf`` with its input position, filed by aircraft part (``part_of``) in
    ``work/in-<part>/<batch>.parquet``: one streaming pass over the input (a slice of a scan per
    batch would read every input file's footer each time)."""
    offset = 0
    for b, batch in enumerate(lf.collect_batches(chunk_size=TRUTH_BATCH_ROWS)):
        batch = batch.with_columns(
            pl.int_range(offset, offset + batch.height, dtype=pl.UInt64).alias(contract.INPUT_ROW),
            batch.select("truth_id").join(part_of, on="truth_id", how="left", nulls_equal=True,
                                          maintain_order="left")["__part"])
        offset += batch.height
        for (k,), rows in batch.partition_by("__part", as_dict=True, maintain_order=True).items():
            (work / f"in-{k:06d}").mkdir(parents=True, exist_ok=True)
            rows.drop("__part").write_parquet(work / f"in-{k:06d}" / f"{b:06d}.parquet", compression="lz4")


@dataclass
class ValidTruth:
    """The truth validated before the windows (:func:`first_truth`): whole (``frame``) or on disk
    (``on_disk``), its packed rejects, and the reference file the windows match their pictures
    to (None: no clean row)."""

    frame: pl.DataFrame | None
    on_disk: StreamedTruth | None
    rejects: pl.DataFrame
    reference: Path | None

    def matcher(self) -> Reference | None:
        """The reference the evaluation's window stage reads its time slices from."""
        return Reference(self.reference) if self.reference is not None else None

    def table(self) -> "pl.DataFrame | StreamedTable":
        """The run's ``truth`` table for a sink (:func:`truth_table`)."""
        return truth_table(self.frame if self.on_disk is None else self.on_disk.empty, self.on_disk)


def truth_table(truth: pl.DataFrame, on_disk: StreamedTruth | None) -> "pl.DataFrame | StreamedTable":
    """The run's ``truth`` table for a sink: an on-disk truth with rows as its reference files
    (which a sink may copy as they are) without the neighbour times the matcher reads, else
    ``truth`` (the clean truth, or the empty schema of one without rows)."""
    if on_disk is not None and on_disk.rows:
        return StreamedTable(on_disk.pieces, tuple(reference_files(on_disk.reference)), NEIGHBOUR_COLUMNS)
    return truth


def first_truth(ds: Dataset, cfg: PipelineConfig, notes: list[str], source: Any, parts: Any,
                clock: Any) -> ValidTruth | None:
    """The truth validated before the first window of a run on disk (``parts`` with a scratch
    directory), so that every window can match its pictures to it: :func:`stream_truth`, or
    :func:`validate_truth` for a small truth. Its time window is the span of the reports'
    plausible times (``source``: :class:`~tertiary.runtime.windows.ReportSource`) ± the pad, known
    before any report is validated. None: nothing to score on here (no truth, reports without
    ``truth_id``, a run in memory) — finalize then validates the truth itself."""
    lf = truth_lazy(ds)
    if (lf is None or not hasattr(parts, "scratch") or cfg.strict
            or source.first_us is None or "truth_id" not in source.lf.collect_schema().names()):
        return None
    if lf.select(pl.len()).collect().item() == 0:
        return None
    clock.stage("validate_truth")
    window = report_span_window((source.first_us, source.last_us), cfg.limits)
    scratch = parts.scratch()
    streamed = stream_truth(ds, cfg, notes, window, scratch)
    if streamed is not None:
        on_disk, rejects = streamed
        return ValidTruth(None, on_disk, rejects, on_disk.reference)
    truth, rejects = validate_truth(ds, cfg, notes, window)
    ref = write_reference(truth, scratch / "reference.parquet") if truth.height else None
    return ValidTruth(truth, None, rejects, ref)


def no_rejects() -> pl.DataFrame:
    """An empty ``rejects`` table."""
    return contract.empty_frame("rejects")


def ingest(ds: Dataset, strict: bool = False, limits: contract.Limits = contract.Limits()) -> Ingested:
    """Validate radars, reports (against the valid radars) and truth (against the reports' span:
    their plausible times, :func:`report_span_window`).

    Strict mode raises :class:`tertiary.contract.SchemaError` on the first problem; lenient mode
    moves bad rows to ``rejects`` with a reason (a rejected radar takes its reports along).
    """
    notes: list[str] = []
    radars, rej_r, raw_r = validate_table(contract.as_frame(ds.radars, "radars"), "radars", strict, notes,
                                          limits=limits)
    gone = (raw_r["radar_id"].cast(pl.UInt32, strict=False).drop_nulls().to_list()
            if "radar_id" in raw_r.columns else [])
    if radars.height == 0:
        notes.append("radars: no valid radar; every report is rejected")
    raw = contract.as_frame(ds.reports, "reports")
    raw = raw.drop(contract.INPUT_ROW, strict=False).with_row_index(contract.INPUT_ROW)
    reports, rej_p, _ = validate_table(raw, "reports", strict, notes, radars=radars, limits=limits,
                                       rejected_radars=gone)
    rows = reports.select("report_id", pl.col(contract.INPUT_ROW).cast(pl.UInt64).alias("row_index"))
    reports = reports.drop(contract.INPUT_ROW)
    truth_in = contract.as_frame(ds.truth, "truth")
    truth, rej_t = truth_in, no_rejects()
    if truth_in.height:
        span = plausible_span(ds.reports, limits)
        window = (report_span_window(span, limits) if span is not None and reports.height
                  else truth_window(reports, limits))
        truth, rej_t, _ = validate_table(truth_in, "truth", strict, notes, limits=limits, time_window=window)
    rejects = pl.concat([r for r in (rej_r, rej_p, rej_t) if r.height] or [no_rejects()],
                        how="vertical_relaxed")
    return Ingested(radars, reports, truth, rejects, notes, rows)


def truth_window(reports: pl.DataFrame, limits: contract.Limits):
    """(start, end, label) the truth must fall in: the valid reports' span ± the pad."""
    if reports.height == 0:
        return None
    return span_window(reports["time"].min(), reports["time"].max(), limits)


def span_window(first, last, limits: contract.Limits):
    """:func:`truth_window` of reports from ``first`` to ``last``."""
    pad = timedelta(seconds=limits.truth_pad_s)
    return first - pad, last + pad, f"the reports' span +- {limits.truth_pad_s:g} s"


def plausible_span(reports: pl.DataFrame | pl.LazyFrame, limits: contract.Limits) -> tuple[int, int] | None:
    """(first, last) µs of the reports' plausible times (:class:`~tertiary.runtime.windows.ReportSource`);
    None: no report has one."""
    source = ReportSource(reports, limits)
    return None if source.first_us is None else (source.first_us, source.last_us)


def report_span_window(span_us: tuple[int, int], limits: contract.Limits):
    """:func:`span_window` of the reports' plausible times (first, last µs: those of
    :class:`~tertiary.runtime.windows.ReportSource`), known before any report is validated: the
    truth window of a run's truth, whichever engine validates it."""
    epoch = datetime(1970, 1, 1, tzinfo=timezone.utc)
    return span_window(epoch + timedelta(microseconds=span_us[0]), epoch + timedelta(microseconds=span_us[1]), limits)


def screen(ds: Dataset, cfg: PipelineConfig | None = None) -> Ingested:
    """Every rule of the job that can reject a report, applied without running the job.

    Ingest (the data contract) and the align stage's rejections (its plan: unusable estimate,
    implausible speed, superseded, too old); ``rejects`` then holds exactly the rows — reasons,
    stages and input row indices — that :func:`run` rejects. :func:`process` uses it, so
    ``tertiary validate`` and ``tertiary run`` cannot disagree."""
    cfg = check_config(cfg)
    ing = ingest(ds, strict=cfg.strict, limits=cfg.limits)
    ing.notes[:0] = getattr(ds, "notes", [])
    _, rej_f = valid_flight_plans(ds, cfg, ing.notes)        # the same rows `run` rejects
    if rej_f.height:
        ing.rejects = pl.concat([ing.rejects, rej_f], how="vertical_relaxed")
    if _height(ds.reports) == 0:
        raise DataError("reports: the table has no rows; nothing to process")
    if ing.reports.height == 0:
        ing.notes.append(f"no valid report left: all {_height(ds.reports):,} reports rejected")
        return ing
    if cfg.register:
        ing.reports = registered(ing, ds.origin, cfg)
    if cfg.collection is not None:   # report collection queue (§1.4): lost reports -> rejects
        ing.reports, lost, collected = collection_stage(ing.reports, ing.report_rows, cfg.collection)
        ing.rejects = pl.concat([ing.rejects, lost], how="vertical_relaxed")
        ing.notes.extend(collected)
    ing.plan = align_stage.plan(ing.reports, ing.radars, ds.origin, cfg.align)
    align_rej = stage_rejects_table(ing.plan.rejects, ing.reports, ing.report_rows, "align")
    ing.rejects = pl.concat([ing.rejects, align_rej], how="vertical_relaxed")
    if int(ing.plan.keep.sum()) == 0:
        ing.notes.append(f"no valid report left: all {_height(ds.reports):,} reports rejected")
    return ing


def registered(ing: Ingested, origin: geo.LocalFrame, cfg: PipelineConfig) -> pl.DataFrame:
    """The valid reports with each radar's registration applied (``cfg.registration`` rows,
    else estimated radar to radar from these reports — never from the truth that scores the run)."""
    if cfg.registration:
        table = pl.DataFrame([list(map(float, row)) for row in cfg.registration], orient="row",
                             schema=["radar_id", "range_bias_m", "azimuth_bias_deg", "time_offset_s", "range_gain"])
        table = table.with_columns(pl.col("radar_id").cast(pl.UInt32))
        source = "given"
    else:
        table = registration.estimate(ing.reports, ing.radars, origin, None,
                                      registration.RegistrationConfig(method="multi")).table
        source = "estimated radar to radar"
    for row in table.iter_rows(named=True):       # one note per radar (a handful), once per run
        note = (f"registration ({source}) radar {row['radar_id']}: range {row['range_bias_m']:+.2f} m, "
                f"azimuth {row['azimuth_bias_deg']:+.4f} deg, clock {row['time_offset_s']:+.4f} s")
        if note not in ing.notes:                 # a given table is applied again in every window
            ing.notes.append(note)
    return align_stage.apply_registration(ing.reports, table)


def _height(frame) -> int:
    return frame.height if isinstance(frame, pl.DataFrame) else len(contract.as_frame(frame, "reports"))


def valid_flight_plans(ds: Dataset, cfg: PipelineConfig, notes: list[str]) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The dataset's valid flight plans and the rejects of the others (strict: the first bad row
    is a :class:`DataError`)."""
    if ds.flight_plans is None or ds.flight_plans.height == 0:
        return empty_flight_plans(), no_rejects()
    plans, rej = check_flight_plans(ds.flight_plans, cfg.limits)
    if rej.height:
        text = f"flight_plans: {rej.height} row(s) rejected (first: row {rej['row_index'][0]}, {rej['reason'][0]})"
        if cfg.strict:
            raise DataError(text)
        notes.append(text)
    return plans, rej


def stage_rejects_table(stage_rejects: pl.DataFrame, reports: pl.DataFrame, report_rows: pl.DataFrame,
                        stage: str) -> pl.DataFrame:
    """A stage's (report_id, reason) rejects in the canonical ``rejects`` schema; ``row_index``
    is the report's row in the input table (``report_rows``), the detail its validated row."""
    if stage_rejects.height == 0:
        return contract.empty_frame("rejects", False)
    rows = (reports.join(report_rows, on="report_id", how="inner")
            .join(stage_rejects, on="report_id", how="inner").sort("row_index"))
    return contract.rejects_table(rows, "reports", stage)
