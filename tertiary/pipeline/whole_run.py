"""The whole-run stages: once every window is stored, the truth is validated (unless the local run
validated it before its first window), every streamed table sunk, and the one evaluation stage,
alert scoring and STCA curves, the posterior Cramér–Rao bound, capacity and requirements run on
the whole run (:func:`finalize`). An on-disk run keeps its pictures on disk; where its windows
matched them to the truth (and stepped their seed and surveillance metrics), the evaluation
only finishes those, else it reads each picture back, one at a time."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polars as pl

from safety import alerts as safety_alerts
from safety import capacity as safety_capacity
from tertiary import contract
from tertiary.core.errors import DataError
from tertiary.evaluation.accuracy import BY_EPOCH_SCHEMA
from tertiary.evaluation.bound import bound_setup, bound_stage, scan_origins
from tertiary.evaluation.bound_pooling import pool_rows
from tertiary.evaluation.bound_fanout import bound_stage_apart
from tertiary.evaluation.bound_streamed import BoundSetup, PartFiles, bound_finish
from tertiary.evaluation.streamed import SCORED
from tertiary.evaluation.requirements import Requirements
from tertiary.evaluation.association import AssociationScore, association_metrics, association_score
from tertiary.evaluation.evaluate import Evaluation, Matched, read_reference, reference_files, write_reference
from tertiary.evaluation.indicators import indicators
from tertiary.evaluation.truth_picture import first_observed, observed_spans
from tertiary.io.dataset import Dataset
from tertiary.pipeline.clock import Progress, StageClock
from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario, check_config
from tertiary.pipeline.ingestion import (Ingested, StreamedTruth, no_rejects, report_span_window, span_window,
                                         stream_truth, truth_table, truth_window, validate_truth)
from tertiary.pipeline.pictures import safety_id_column, safety_names
from tertiary.pipeline.plan import CURVE_ROWS
from tertiary.pipeline.scoring import (aligned_facts, association_blocks, association_stage_metrics, distinct_targets,
                                       observed_aircraft, score_pictures, scored_blocks, WindowedPictures)
from tertiary.pipeline.safety_scoring import TruthSource, score_safety
from tertiary.pipeline.stca_scoring import TruthIntervals
from tertiary.pipeline.streaming import RunContext, StreamState
from tertiary.pipeline.truth_alerts import TruthPictureState
from tertiary.pipeline.tables import (ALIGNED_COLUMNS, ASSOCIATION_COLUMNS, BOUND_TRUTH, REPORT_COLUMNS,
                                      SCORED_CONFLICTS, DeferredTable, OnDiskTable, Sink, SinkThread,
                                      confirmed_targets, for_sink, part_rows, read_table, table_columns, target_counts,
                                      whole_table)
from tertiary.runtime.fanout import Fanout
from tertiary.runtime.windows import concat_parts, read_part_groups, release_memory
from tertiary.sensors.radar_health import radar_health
from tertiary.stages import align as align_stage
from tertiary.stages.association.associate import AssociationStats

__all__ = ["Results", "RunTables", "evaluate_run", "finalize", "finalize_stages"]

# `safety` is imported as modules, not names: `import safety` first imports `tertiary` (whose
# package imports this one) while `safety` is half initialised, and only a module binding
# survives that


@dataclass
class Results:
    """Every table of a run (also written to ``results.duckdb``)."""

    ingested: Ingested
    aligned: pl.DataFrame
    associations: pl.DataFrame
    fused: pl.DataFrame
    clusters: pl.DataFrame
    tracks: pl.DataFrame
    conflicts: pl.DataFrame
    rejects: pl.DataFrame
    metrics: pl.DataFrame
    accuracy_by_epoch: pl.DataFrame
    timings: dict[str, float]
    counts: dict[str, int]
    alerts: pl.DataFrame = field(default_factory=pl.DataFrame)
    #: the process's peak resident memory (MiB) by the end of each stage (streamed stages over
    #: every window; ``finalize:<stage>`` for the whole-run stages): where a run's memory goes
    memory_mib: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class RunTables:
    """The streamed tables as finalize hands them to the whole-run stages, with what was taken of
    them on the way. An on-disk run hands ``aligned`` and ``reports`` as :class:`DeferredTable`
    and ``observed`` (:func:`observed_aircraft`) computed before, its fused and tracks as
    :class:`OnDiskTable`; ``scratch`` is its scratch directory and ``on_disk`` its truth
    validated to disk (:func:`stream_truth`)."""

    aligned: pl.DataFrame | DeferredTable
    associations: pl.DataFrame | DeferredTable
    stats: AssociationStats
    fused: pl.DataFrame | OnDiskTable
    clusters: pl.DataFrame
    tracks: pl.DataFrame | OnDiskTable
    conflicts: pl.DataFrame
    n_in: int                   # input reports
    t_all: float                # when the run started (``time.perf_counter()``)
    conversion_invalid: int = 0
    observed: pl.DataFrame | None = None
    reports: DeferredTable | None = None
    scratch: Path | None = None
    on_disk: StreamedTruth | None = None
    scores: AssociationScore | None = None
    #: a reader of each point's rows of the STCA curves as the windows predicted them (by its
    #: index: :class:`~tertiary.pipeline.plan.StcaCurvesStage`); None: not predicted on the way,
    #: so the curves predict them here
    curve_rows: Callable[[int], pl.DataFrame] | None = None
    #: (run, method, epoch, id) of every alert row of the safety picture and of its curve
    #: points: the only ids whose id-map rows the alert scoring reads (:func:`safety.alerts.id_rows`);
    #: None: the whole id map is kept
    alert_keys: pl.DataFrame | None = None
    #: the pictures as the windows matched them, by name (:class:`WindowedPictures`); None: the
    #: evaluation matches them itself
    matched: Callable[[str], Matched | None] | None = None
    #: the truth's separation intervals of the chunks the windows passed, with the reference file
    #: they read (None: none computed in the windows)
    intervals: tuple[TruthIntervals, Path] | None = None
    #: the bound as the windows made it: its setup, and the sums of every aircraft as
    #: :func:`bound_finish` makes them from the windows' state, on a thread of its own beside the
    #: evaluation (None: the end bounds the whole recording)
    bound: tuple[BoundSetup, "Future[pl.DataFrame]", PartFiles] | None = None
    #: the truth picture's prediction as the windows carried it, and a reader of their stored
    #: rows by table name (None: the end predicts the whole truth picture)
    truth_picture: tuple[TruthPictureState, Callable[[str], pl.DataFrame | None]] | None = None
    #: the requirements read when the run started (None: read here)
    requirements: Requirements | None = None


def finalize(ds: Dataset, cfg: PipelineConfig, ctx: RunContext, st: StreamState, parts: Any, n_reports: int,
             progress: Progress | None = None, sink: Sink | None = None, notes: list[str] | None = None) -> Results:
    """The whole-run stages on streamed tables held by ``parts`` (see :func:`stream`)."""
    return finalize_stages(ds, adapt_to_scenario(check_config(cfg), ds), ctx, st, parts,
                           StageClock(progress or (lambda _m: None)), sink or (lambda _n, _f: None),
                           [] if notes is None else notes, n_reports, time.perf_counter())


def finalize_stages(ds: Dataset, cfg: PipelineConfig, ctx: RunContext, st: StreamState, parts: Any,
                    clock: StageClock, sink: Sink, notes: list[str], n_in: int, t_all: float) -> Results:
    """The whole-run stages on the streamed tables: truth validation, the one evaluation stage,
    alert scoring and STCA curves, the bound, capacity, requirements — and every table sunk."""
    clock.stage(None)
    clock.prefix = "finalize:"
    clock.stage("validate")      # the truth, and the whole run's accounting
    release_memory()             # what the windows freed, before the whole-run stages
    if cfg.tracker.measured_downlinks:
        notes.append(f"tracker: {cfg.tracker.measured_downlinks}")
    if isinstance(sink, SinkThread):        # the run's own, which its caller closes
        return _finalize_tables(ds, cfg, ctx, st, parts, clock, sink, notes, n_in, t_all)
    writer = SinkThread(sink)
    try:
        return _finalize_tables(ds, cfg, ctx, st, parts, clock, writer, notes, n_in, t_all)
    finally:
        writer.close()


def _finalize_tables(ds: Dataset, cfg: PipelineConfig, ctx: RunContext, st: StreamState, parts: Any,
                     clock: StageClock, sink: SinkThread, notes: list[str], n_in: int, t_all: float) -> Results:
    """Truth validation and the run's accounting, every streamed table sunk, then
    :func:`evaluate_run` on them."""
    # an on-disk run keeps in memory only what the whole-run stages read, and its streamed tables
    # go to the database one window's part at a time (memory)
    lean = hasattr(parts, "iter_parts")
    # an on-disk run's aligned rows and reports are not read whole here: what the stages take of
    # them is read a part at a time (memory), unless radar health reads every aligned column
    facts = aligned_facts(parts.part_files("aligned")) if lean and not cfg.radar_health else None
    empty_reports = contract.empty_frame("reports", False)
    if facts:
        # the reports' count and span, a part at a time (memory: a day's times are 280 MB); the
        # count alone, from the parts' footers, when the span is the windows' (below)
        n_reports, window = ((part_rows(parts.part_files("reports")), None) if ctx.report_span is not None
                             else _report_span(parts.part_files("reports"), cfg))
        reports = _report_schema(parts, empty_reports)
    else:
        reports = (read_table(parts, "reports", empty_reports) if not lean else
                   table_columns(parts, "reports", REPORT_COLUMNS, empty_reports))
        n_reports, window = reports.height, truth_window(reports, cfg.limits)
    if ctx.report_span is not None and n_reports:
        window = report_span_window(ctx.report_span, cfg.limits)      # as the windows' engine knew it
    rejects = read_table(parts, "rejects", no_rejects()).sort("input_table", "row_index", nulls_last=True,
                                                              maintain_order=True)
    scratch = parts.scratch() if lean else None
    first = ctx.truth           # validated before the windows, which matched their pictures to it
    # an on-disk run validates the truth from disk to disk: the whole-run stages read it there
    streamed = ((first.on_disk, first.rejects) if first is not None and first.on_disk is not None
                else stream_truth(ds, cfg, notes, window, scratch) if lean and first is None else None)
    on_disk = None
    if streamed is None:
        truth, rej_t = ((first.frame, first.rejects) if first is not None
                        else validate_truth(ds, cfg, notes, window))
    else:
        on_disk, rej_t = streamed
        truth = on_disk.empty
    release_memory()             # the validation's scratch
    if rej_t.height:
        rejects = pl.concat([rejects, rej_t], how="vertical_relaxed")
    ing = Ingested(ctx.radars, reports, truth, rejects, notes)
    sink("radars", ing.radars)
    sink("reports", for_sink(parts, "reports", empty_reports) if lean else reports)
    if not ctx.truth_sunk:
        sink("truth", truth_table(truth, on_disk))
    del truth                   # held by ``ing`` alone: the evaluation may release it
    sink("rejects", rejects)
    empty_aligned = align_stage.empty_aligned()
    aligned = (empty_aligned if facts else
               table_columns(parts, "aligned", None if cfg.radar_health else ALIGNED_COLUMNS, empty_aligned)
               if lean else read_table(parts, "aligned", empty_aligned))
    n_aligned, n_ok = (facts.rows, facts.reports) if facts else (aligned.height, None)
    if n_aligned == 0:
        top = (rejects.group_by("reason").len().sort("len", descending=True).head(3)
               if rejects.height else pl.DataFrame({"reason": [], "len": []}))
        why = "; ".join(f"{n:,} × {r}" for r, n in top.iter_rows())
        raise DataError(f"no valid report left: all {n_in:,} reports rejected"
                        + (f" (most common: {why})" if why else ""))
    n_ok = aligned["report_id"].n_unique() if n_ok is None else n_ok
    _check_accounting(n_in, n_ok, rejects)
    sink("aligned", for_sink(parts, "aligned", empty_aligned) if lean else aligned)
    release_memory()             # the scratch of the reports' and aligned rows' copies to the database
    observed, later = None, None
    if lean:
        # the evaluation and the alert scoring read neither the reports nor the aligned rows, only
        # which aircraft had a report at which epoch: both are read back after them (memory)
        if facts is not None and facts.observed is not None:
            observed = facts.observed
        else:
            both = reports if not facts else table_columns(parts, "reports", REPORT_COLUMNS, empty_reports)
            observed = observed_aircraft(aligned if not facts else table_columns(
                parts, "aligned", ALIGNED_COLUMNS, empty_aligned), both)
            del both
        cols = None if cfg.radar_health else ALIGNED_COLUMNS
        aligned = DeferredTable(lambda: table_columns(parts, "aligned", cols, empty_aligned), n_aligned, reports=n_ok)
        later = DeferredTable(lambda: table_columns(parts, "reports", REPORT_COLUMNS, empty_reports), n_reports)
        ing.reports = reports.clear()         # its schema until then: what the stages test for
        del reports
    tables = {}
    for name in ("associations", "fused", "clusters", "tracks", "conflicts"):
        empty = (contract.empty_frame(name, False) if name in ("tracks", "conflicts") else pl.DataFrame())
        if lean and name == "associations":
            # read back after the evaluation and the alert scoring, which do not read it: its
            # rows are not held through their peak (memory)
            sink(name, for_sink(parts, name, empty))
            n_rows, n_targets = distinct_targets(parts.part_files(name))
            # what the association metrics read (the rows are in the database)
            frame = DeferredTable(lambda: table_columns(parts, "associations", ASSOCIATION_COLUMNS, pl.DataFrame()),
                                  n_rows, blocks=lambda: association_blocks(parts), targets=n_targets)
        elif not lean:
            frame = read_table(parts, name, empty)
            sink(name, frame)
        elif name == "conflicts":
            sink(name, for_sink(parts, name, empty))
            # read back where the alerts are scored, not held through the evaluation (memory: a
            # day's conflict rows are 1.2 GB)
            rows, alerts, scored = _scored_conflict_parts(parts)
            frame = DeferredTable(lambda e=empty: read_table(parts, "conflicts", e), rows,
                                  blocks=lambda s=scored: iter(s), alerts=alerts)
        else:
            sink(name, for_sink(parts, name, empty))
            if name == "clusters":
                frame = table_columns(parts, name, ["run", "method"], empty)
            else:
                # left on disk: evaluation and the STCA curves read one picture at a time
                frame = OnDiskTable(parts, name, empty)
        tables[name] = frame
    associations, fused, clusters, tracks, conflicts = (tables[k] for k in ("associations", "fused", "clusters",
                                                                            "tracks", "conflicts"))
    stats = AssociationStats(pairs=st.counts.get("pairs", 0), components=st.counts.get("components", 0),
                             ambiguous_components=st.counts.get("ambiguous_components", 0),
                             targets=(associations.facts["targets"] if isinstance(associations, DeferredTable) else
                                      associations.select("run", "target_id").n_unique() if associations.height
                                      else 0),
                             reassignments=st.counts.get("reassignments", 0))
    curves = curve_reader(parts) if ctx.curves else None
    # the evaluation keeps only the id-map rows the alert scoring reads when it knows every alert
    # beforehand: the conflicts' and, with curves, the windows' curve points' (memory)
    keys = (_alert_keys(conflicts, parts, safety_id_column(cfg))
            if lean and cfg.safety and isinstance(conflicts, DeferredTable)
            and (curves is not None or not cfg.stca_lookaheads_s)
            else None)
    bound = _windows_bound(ctx, st, parts)
    # the scored samples are read back for the bound only: not when the windows made it (memory)
    # the id map of the alerts as the windows reduced it, a block each, when every window did
    reduced = safety_id_column(cfg) if keys is not None and getattr(st, "id_rows", None) is True else None
    matched = (WindowedPictures(parts, st.evaluation, cfg.evaluation, samples=bound is None,
                                lags=getattr(st, "lags", None), id_rows=reduced)
               if st.evaluation is not None else None)
    done = getattr(st, "intervals", None)
    run = RunTables(aligned, associations, stats, fused, clusters, tracks, conflicts, n_in, t_all,
                    int(getattr(st.align, "conversion_invalid", 0)), observed, later, scratch, on_disk,
                    getattr(st, "scores", None), curves, keys, matched,
                    (done, ctx.reference.path) if done is not None and ctx.reference is not None else None,
                    bound, _windows_truth_picture(st, parts), getattr(ctx, "requirements", None))
    return evaluate_run(ds, cfg, ing, run, clock, sink, getattr(ctx, "fanout", None))


def _windows_bound(ctx: RunContext, st: StreamState, parts: Any
                   ) -> tuple[BoundSetup, "Future[pl.DataFrame]", PartFiles] | None:
    """The bound the windows carried, when they made it for every window: its setup and the
    aircraft still flying at the end taken through their last rows, started now on a thread
    of its own (numpy, mostly one core) so that it runs beside the evaluation's polars work; the
    windows' stored samples."""
    state = getattr(st, "bound", None)
    setup = getattr(ctx, "bound", None)
    if setup is None or state is None or not state.complete or not hasattr(state, "aircraft"):
        return None
    stored = functools.partial(parts.part_files, SCORED)
    pool = ThreadPoolExecutor(1, thread_name_prefix="bound")
    try:
        return setup, pool.submit(bound_finish, setup, state, stored), stored
    finally:
        pool.shutdown(wait=False)


def _windowed_id_map(cfg: PipelineConfig, run: RunTables) -> pl.DataFrame | None:
    """The safety picture's id map as the evaluation would give it, from the blocks the windows
    reduced (:meth:`WindowedPictures.id_map`); None when they did not reduce it."""
    fused, tracks, matched = run.fused, run.tracks, run.matched
    if (not isinstance(matched, WindowedPictures) or run.alert_keys is None
            or not isinstance(fused, OnDiskTable) or not isinstance(tracks, OnDiskTable)):
        return None
    id_col = safety_names(cfg, fused, tracks)[1]
    # the pictures in the order the evaluation scores them (:func:`score_pictures`)
    names = ([f"{m}+{f}" for m, f in tracks.pictures] if id_col == "track_id" else [key[0] for key in fused.shown])
    return matched.id_map(names, run.alert_keys, id_col)


def _windows_truth_picture(st: StreamState, parts: Any
                           ) -> tuple[TruthPictureState, Callable[[str], pl.DataFrame | None]] | None:
    """The truth picture's prediction the windows carried, when they saw every window."""
    state = getattr(st, "truth_picture", None)
    if state is None or not state.complete:
        return None
    return state, parts.table


def _bound_rows(ds: Dataset, run: RunTables, truth: "pl.DataFrame | pl.LazyFrame", ing: Ingested,
                scored: pl.DataFrame, metrics: pl.DataFrame, apart: tuple[Fanout, Path] | None = None
                ) -> pl.DataFrame:
    """The bound's metrics rows: from the sums the windows carried (the aircraft still flying at
    the end finished on the thread :func:`_windows_bound` started; ``scored`` not read), else over the whole recording from ``scored``; the
    radars' scan origins from the input reports either way
    (:func:`tertiary.evaluation.bound.scan_origins`). ``apart`` (a fanout and the reference on
    disk): the whole recording's blocks of aircraft are its pieces."""
    if run.bound is not None:
        setup, finished, stored = run.bound
        names = truth.collect_schema().names() if isinstance(truth, pl.LazyFrame) else truth.columns
        files = stored()          # the scored samples are not read back: whether there are any
        some = bool(files) and pl.scan_parquet(files).select(pl.len()).collect().item() > 0
        pools = finished.result()
        if bound_setup(ds, names, ing.radars, ing.notes, some) is None:
            return pl.DataFrame(schema=contract.TABLES["metrics"].required)
        return pool_rows(pools, metrics)
    t0 = truth.lazy().select(pl.col("time").cast(contract.TIME).dt.epoch("us").min()).collect().item()
    reports = ds.reports if isinstance(ds.reports, (pl.DataFrame, pl.LazyFrame)) else ing.reports
    origins = scan_origins(ing.radars, reports, int(t0)) if t0 is not None else {}
    if apart is not None:
        return bound_stage_apart(ds, apart[0], reference_files(apart[1]), BOUND_TRUTH, ing.radars, ing.reports,
                                 scored, metrics, ing.notes, origins)
    return bound_stage(ds, truth, ing.radars, ing.reports, scored, metrics, ing.notes, origins)


def evaluate_run(ds: Dataset, cfg: PipelineConfig, ing: Ingested, run: RunTables, clock: StageClock,
                 sink: Sink, fanout: Fanout | None = None) -> Results:
    """The whole-run stages after the tables are sunk. The deferred tables and ``observed`` are
    read back after the evaluation's peak. With a ``scratch`` directory the evaluation reads the
    truth from reference files there, and the truth is not held through it (``on_disk``: it is
    already there). The stages after the evaluation then read the truth's columns they use from
    the reference, and ``ing.truth`` keeps no row (the whole truth when the indicators run).
    ``fanout``: where the pieces of the stages that split into independent ones run."""
    aligned, associations, stats, fused, clusters, tracks, conflicts = (
        run.aligned, run.associations, run.stats, run.fused, run.clusters, run.tracks, run.conflicts)
    observed, reports, scratch, on_disk, scores = run.observed, run.reports, run.scratch, run.on_disk, run.scores
    n_in, conversion_invalid = run.n_in, run.conversion_invalid
    alerts = pl.DataFrame()
    truth_rows = on_disk.rows if on_disk is not None else ing.truth.height
    has_truth = bool(truth_rows) and "truth_id" in ing.reports.columns
    empty = Evaluation(pl.DataFrame(), pl.DataFrame(), pl.DataFrame(), pl.DataFrame())
    ev_fused, ev_tracks = empty, empty
    truth_file: Path | None = None
    safety = cfg.safety and has_truth
    ids: pl.DataFrame | None = None
    if has_truth:
        clock.stage("evaluation")
        if observed is None:
            observed = observed_aircraft(aligned, ing.reports)
        reference: "pl.DataFrame | Path" = ing.truth
        if on_disk is not None:
            reference = on_disk.reference
        elif scratch is not None:
            reference = write_reference(ing.truth, scratch / "reference.parquet")
            ing.truth = ing.truth.clear()
        # what the truth picture is sampled on: the observed aircraft's spans, the picture grid
        # (the windows' truth picture leaves the attribution only each aircraft's first observation)
        spans = first_observed(observed) if run.truth_picture is not None else observed_spans(observed)
        grid = observed.select("run", "epoch").unique().sort("run", "epoch")
        if scratch is not None and not cfg.indicators:
            # the later stages each read the columns they use from the reference, and the truth is
            # not held between them (memory); the indicators match the pictures again: the whole truth
            truth_file = reference
        # the safety picture's id map as the windows reduced it, read once for every picture
        ids = _windowed_id_map(cfg, run) if safety else None
        ev_fused, ev_tracks = score_pictures(cfg, fused, tracks, observed, reference, ing, ds,
                                             None if scratch is None else scratch / "evaluation", run.alert_keys,
                                             run.matched, run.requirements, id_maps=ids is None,
                                             fanout=fanout)
        del observed
        if scratch is not None:
            release_memory()
            if cfg.indicators:
                ing.truth = read_reference(reference)
    elif on_disk is not None and on_disk.rows:
        ing.truth = read_reference(on_disk.reference)      # nothing scored against it: as it came
    truth = TruthSource(ing, truth_file)
    if safety:
        if ids is None:
            # which aircraft each picture row represents: the one matcher's answer
            ids = (ev_tracks if safety_names(cfg, fused, tracks)[1] == "track_id" else ev_fused).id_map
        got = score_safety(ds, cfg, run, ids, truth, spans, grid, clock.stage, fanout)
        ing.notes.extend(got.notes)
        alerts, safety_metrics = got.alerts, got.metrics
        sink("alerts", alerts)
        sink("losses", got.losses)          # each loss of separation per picture, alerted or missed
    clock.stage("evaluate")
    release_memory()
    # the association metrics scored window by window when every row was; else from
    # the rows read back
    carried = has_truth and scores is not None and scores.rows == associations.height
    blocks = associations.blocks if isinstance(associations, DeferredTable) and has_truth and not carried else None
    if isinstance(associations, DeferredTable):
        # on disk, in the database; scored from there a block at a time when not carried
        associations = pl.DataFrame() if carried or blocks is not None else associations.read()
    if reports is not None and (not carried or run.bound is None):
        # read back for what still reads them: association rows scored here, or the bound made here
        ing.reports = reports.read()
    if blocks is not None:
        scores = scored_blocks(blocks(), ing.reports)
    if carried or blocks is not None:
        metrics = association_stage_metrics(scores.runs.height if scores.rows else 0, stats,
                                            association_score(scores, confirmed_targets(fused)))
    else:
        report_truth = ing.reports.select("run", "report_id", "truth_id") if has_truth else None
        metrics = association_stage_metrics(int(associations["run"].n_unique()) if associations.height else 0, stats,
                                            association_metrics(associations, report_truth, confirmed_targets(fused))
                                            if report_truth is not None else None)
    release_memory()
    by_epoch = pl.DataFrame(schema=BY_EPOCH_SCHEMA)
    if has_truth:
        metrics = pl.concat([metrics, *[e.metrics for e in (ev_fused, ev_tracks) if e.metrics.height]],
                            how="vertical_relaxed")
        by_epoch = ev_fused.by_epoch
        samples = [e.samples for e in (ev_fused, ev_tracks) if e.samples.height]
        scored = pl.concat(samples, how="vertical_relaxed") if samples else pl.DataFrame()
        # the posterior Cramér–Rao bound beside every picture's accuracy (tertiary.evaluation.bound)
        # read by blocks of aircraft from the reference, never whole (memory)
        apart = (fanout, truth_file) if fanout is not None and truth_file is not None else None
        extra = [_bound_rows(ds, run, truth.scan(BOUND_TRUTH), ing, scored, metrics, apart)]
        if cfg.safety:
            extra.append(safety_metrics)
        metrics = pl.concat([metrics, *extra], how="vertical_relaxed")
        if cfg.safety:
            capacity = safety_capacity.capacity_from_metrics(metrics, notes=ing.notes)
            metrics = pl.concat([metrics, capacity], how="vertical_relaxed")
        if cfg.evaluation:
            reqs = [e.requirements for e in (ev_fused, ev_tracks) if e.requirements.height]
            if reqs:
                sink("requirements", pl.concat(reqs, how="vertical_relaxed"))
    aligned_rows, aligned_reports = ((aligned.height, aligned.facts["reports"]) if isinstance(aligned, DeferredTable)
                                     else (aligned.height, aligned["report_id"].n_unique()))
    if cfg.radar_health and aligned.height:
        if isinstance(aligned, DeferredTable):
            aligned = aligned.read()
        metrics = pl.concat([metrics, radar_health(aligned, ing.radars)], how="vertical_relaxed")
    if has_truth and cfg.indicators and tracks.height:
        clock.stage("indicators")
        metrics = pl.concat([metrics, indicators(whole_table(tracks), ing.truth)], how="vertical_relaxed")
    sink("metrics", metrics)
    sink("accuracy_by_epoch", by_epoch)
    clock.stage(None)
    if isinstance(sink, SinkThread):
        sink.join(clock)
        # the writes' own time, beside the stages; the stages' wait for the last ones apart
        clock.timings["write_tables_wait_s"] = clock.timings.pop("write_tables_s", 0.0)
        clock.timings["write_tables_s"] = sink.busy_s
    clock.timings["alignment_to_clustering_s"] = sum(
        clock.timings.get(f"{k}_s", 0.0) for k in ("align", "associate", "fuse", "centralized", "cluster"))
    clock.timings["total_s"] = time.perf_counter() - run.t_all
    rejects = ing.rejects
    counts = {"reports_in": n_in, "reports_aligned": int(aligned_reports),
              "reports_rejected": int(rejects.filter(pl.col("input_table") == "reports").height),
              "aligned_rows": aligned_rows, "gated_pairs": stats.pairs, "components": stats.components,
              "ambiguous_components": stats.ambiguous_components, "targets": stats.targets,
              "reassignments": stats.reassignments, "fused_rows": fused.height, "clusters": clusters.height,
              "conversion_invalid": conversion_invalid,
              "track_rows": tracks.height, "conflict_rows": conflicts.height,
              "alert_rows": (conflicts.facts["alerts"] if isinstance(conflicts, DeferredTable)
                             else int(conflicts["alert"].sum()) if conflicts.height else 0),
              "alert_episodes": (alerts.filter(
                  (pl.col("method") != safety_alerts.TRUTH_PICTURE)
                  & ~pl.col("method").str.starts_with(safety_alerts.EXTERNAL_PREFIX)).height if alerts.height else 0),
              "aircraft": truth.columns(["truth_id"])["truth_id"].n_unique() if has_truth else 0,
              **target_counts(fused)}
    # an on-disk run's fused and tracks are in its database only (empty frames here), and so are
    # its aligned rows when they were not read back
    fused, tracks = (t.empty if isinstance(t, OnDiskTable) else t for t in (fused, tracks))
    if isinstance(aligned, DeferredTable):
        aligned = align_stage.empty_aligned()
    if isinstance(conflicts, DeferredTable):
        conflicts = contract.empty_frame("conflicts", False)
    return Results(ing, aligned, associations, fused, clusters, tracks, conflicts, rejects, metrics, by_epoch,
                   clock.timings, counts, alerts, dict(clock.memory))


def curve_reader(parts: Any) -> Callable[[int], pl.DataFrame] | None:
    """A reader of one point's ``curve_rows`` (by its index) from the windows' parts; None when
    no window wrote any. Parts on disk are read one point at a time: every point's rows of a
    long run are never held together (memory)."""
    files = parts.part_files("curve_rows") if hasattr(parts, "part_files") else None
    if files is not None:
        if not files:
            return None
        return lambda k: (pl.scan_parquet(files).filter(pl.col("setting") == k).drop("setting")
                          .collect().cast(CURVE_ROWS_SCORED))
    rows = parts.table("curve_rows")
    if rows is None:
        return None
    return lambda k: rows.filter(pl.col("setting") == k).drop("setting")


#: the types of a point's curve rows without its index
CURVE_ROWS_SCORED = {k: v for k, v in CURVE_ROWS.items() if k != "setting"}


def _scored_conflict_parts(parts: Any) -> tuple[int, int, list[pl.DataFrame]]:
    """(rows, alert rows, each part's rows that the alert scoring reads:
    :func:`safety.alerts.scored_conflicts`) of the conflict parts: as the windows reduced them
    when every window with rows did, else read a part's columns at a time."""
    files = parts.part_files("conflicts")
    reduced = parts.part_files(SCORED_CONFLICTS)
    rows = {f.name: part_rows([f]) for f in files}
    if {name for name, n in rows.items() if n} <= {f.name for f in reduced}:
        scored = list(read_part_groups(reduced))
        return sum(rows.values()), sum(int(s["alert"].sum()) for s in scored), scored
    rows = alerts = 0
    scored = []
    for f in files:
        lf = pl.scan_parquet(f)
        have = lf.collect_schema()
        part = lf.select(c for c in safety_alerts.SCORED_CONFLICT_COLUMNS if c in have).collect()
        rows, alerts = rows + part.height, alerts + int(part["alert"].sum())
        scored.append(safety_alerts.scored_conflicts(part))
    return rows, alerts, scored


def _alert_keys(conflicts: DeferredTable, parts: Any, id_col: str) -> pl.DataFrame:
    """:func:`safety.alerts.alert_ids` of the conflicts' alert rows and the curve points' (all
    settings: an id is kept when any point alerts on it)."""
    # each block's alert rows alone put together: every block's rows at once are a copy of them all (memory)
    cols = ["run", "method", "epoch", "id_a", "id_b", "alert"]
    blocks = [b.filter(pl.col("alert")).select(cols) for b in conflicts.blocks()]
    keys = [safety_alerts.alert_ids(concat_parts(blocks), id_col)] if blocks else []
    files = parts.part_files("curve_rows")
    if files:
        rows = (pl.scan_parquet(files).filter(pl.col("alert"))
                .select("run", "method", "epoch", "id_a", "id_b", "alert").collect())
        keys.append(safety_alerts.alert_ids(rows, id_col))
    if not keys:        # no conflict part: no alert, the id map keeps a row per epoch
        return pl.DataFrame(schema={"run": pl.UInt32, "method": pl.String, "epoch": contract.TIME,
                                    id_col: pl.UInt64})
    return pl.concat(keys, how="vertical_relaxed").unique()


def _report_span(files: list[Path], cfg: PipelineConfig):
    """(rows, :func:`truth_window`) of the valid reports in ``files``, read a part at a time."""
    n, first, last = 0, None, None
    for f in files:
        got = pl.scan_parquet(f).select(pl.len(), pl.col("time").min().alias("a"), pl.col("time").max().alias("b"))
        k, a, b = got.collect().row(0)
        if k:
            n, first, last = n + k, a if first is None else min(first, a), b if last is None else max(last, b)
    return n, (span_window(first, last, cfg.limits) if n else None)


def _report_schema(parts: Any, empty: pl.DataFrame) -> pl.DataFrame:
    """The stored reports' :data:`REPORT_COLUMNS` (those they have), no row: read of one part."""
    first = next(iter(parts.part_files("reports")), None)
    if first is None:
        return empty.select(c for c in REPORT_COLUMNS if c in empty.columns)
    have = pl.read_parquet_schema(first)
    return pl.read_parquet(first, columns=[c for c in REPORT_COLUMNS if c in have], n_rows=0)


def _check_accounting(n_in: int, n_ok: int, rejects: pl.DataFrame) -> None:
    """Every input report is aligned (``n_ok`` distinct reports) or rejected, never both, never
    neither."""
    n_rej = rejects.filter(pl.col("input_table") == "reports").height
    if n_ok + n_rej != n_in:
        raise RuntimeError(f"row accounting broken: {n_in} reports in, {n_ok} aligned + {n_rej} rejected")
