"""The streamed stages: every window of a run through ingest → align → associate → fuse (+ the
centralised reference) → cluster → track → conflicts (:func:`process_step`), then its evaluation
(:mod:`tertiary.pipeline.window_evaluation`), each stage's state carried from window to window
(:class:`StreamState`), and the loop over the windows that stores each one as it completes
(:func:`stream_windows`; :func:`stream` for one slice of a distributed run)."""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import polars as pl

from safety import alerts as safety_alerts
from safety import conflicts as safety_conflicts
from tertiary import contract
from tertiary.core import geo
from tertiary.core.errors import DataError
from tertiary.core.memory import release_freed_memory
from tertiary.core.stage import Stage
from tertiary.core.units import US
from tertiary.evaluation.association import AssociationScore, score_associations
from tertiary.evaluation.bound_streamed import BoundSetup, BoundState, bound_setup
from tertiary.evaluation.lags_streamed import LagState
from tertiary.evaluation.evaluate import Reference
from tertiary.evaluation.requirements import Requirements
from tertiary.evaluation.streamed import SCORED, MatchState
from tertiary.io.dataset import Dataset
from tertiary.pipeline.clock import Progress, StageClock
from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario, check_config
from tertiary.pipeline.ingestion import (Ingested, ValidTruth, first_truth, no_rejects, registered, stage_rejects_table,
                                         truth_lazy, valid_flight_plans, validate_table)
from tertiary.pipeline.pictures import safety_picture
from tertiary.pipeline.plan import build_stages, stca_settings
from tertiary.pipeline.scoring import run_requirements
from tertiary.pipeline.stca_scoring import TruthIntervals, time_span
from tertiary.pipeline.tables import SCORED_CONFLICTS, SinkThread, facts_table, window_facts
from tertiary.pipeline.truth_alerts import TruthPictureState, TruthSlice, reference_slice
from tertiary.pipeline.window_evaluation import Handoff, Overlap, evaluate_step
from tertiary.runtime.fanout import Fanout
from tertiary.runtime.windows import (DEFAULT_WINDOW_S, Meter, PartStore, ReportSource, Window, check_window,
                                      utc_text, windows)
from tertiary.sensors.collection import collection_stage
from tertiary.stages import align as align_stage
from tertiary.stages.align import AlignState
from tertiary.stages.association.associate import AssociateState, associate_step, init_associate_state
from tertiary.stages.clustering import ClusterState, cluster_step, init_cluster_state
from tertiary.stages.flight_data import (DepartureState, correlate, departure_plans, departure_step,
                                         init_departure_state)
from tertiary.stages.fusion import FuseState, fuse_step, init_fuse_state, measured_plots
from tertiary.stages.fusion.centralized import CentralizedState, centralized_step, init_centralized_state
from tertiary.filters import TrackFilter
from tertiary.stages.tracking.intent import reached_column, withhold_left_levels
from tertiary.stages.tracking.tracker import TrackState, filter_dict, init_track_state, track_step

__all__ = ["RunContext", "StreamState", "WindowStore", "init_stream_state", "pipeline_step", "stream",
           "stream_windows", "track_identity", "windowable"]

# `safety` is imported as modules, not names: `import safety` first imports `tertiary` (whose
# package imports this one) while `safety` is half initialised, and only a module binding
# survives that


@dataclass
class RunContext:
    """What every window of a run shares: the validated radars (and the ids of rejected ones), the
    system frame, the epoch grid origin and how long validated reports stay at hand."""

    radars: pl.DataFrame
    gone: list[int]
    origin: geo.LocalFrame
    grid_origin_us: int | None
    keep_us: int
    filters: dict[str, TrackFilter] = field(default_factory=dict)   # the tracker's filters, built once per run
    median: datetime | None = None    # the whole input's median report time (windows are validated against it)
    flight_plans: pl.DataFrame = field(default_factory=pl.DataFrame)   # valid rows (tertiary.stages.flight_data)
    departure_plans: pl.DataFrame = field(default_factory=pl.DataFrame)   # flight_data.departure_plans
    #: the declared stages (:data:`tertiary.pipeline.plan.STAGES`) built on this context once it
    #: is final (:func:`stream_windows`)
    stages: dict[str, Stage] = field(default_factory=dict)
    #: the windows predict every point of the STCA curves (a run with curve settings and a truth
    #: to score them on)
    curves: bool = False
    #: each window writes its block of the safety pictures' reduced id map (:data:`ID_ROWS`)
    id_rows: bool = False
    #: the windows' parts go to a run directory, which the end reads back: each window also
    #: writes what the end reads of its parts (:func:`~tertiary.pipeline.tables.window_facts`, …)
    on_disk: bool = False
    #: the requirements the run is judged against, read before its first window (a bad file
    #: fails the run then, not after its last); None: not read yet
    requirements: Requirements | None = None
    #: the epochs [t0_us, t1_us) whose association rows are scored as the run goes (None: all):
    #: a time slice of a distributed run scores its kept span, not its warm-up
    scored_span: tuple[int, int] | None = None
    #: the input reports' plausible times (first, last µs): the truth's time window
    #: (:func:`~tertiary.pipeline.ingestion.report_span_window`); None: the valid reports' span
    report_span: tuple[int, int] | None = None
    #: the truth validated before the windows (:func:`first_truth`); None: finalize validates it
    truth: ValidTruth | None = None
    #: the reference the windows match their pictures to (the evaluation stage); None: the
    #: whole-run evaluation matches them
    reference: Reference | None = None
    #: each run's first and last truth sample (:func:`time_span`) when the windows compute the
    #: truth's separation intervals as they pass (a run with safety and its reference on disk)
    truth_span: pl.DataFrame | None = None
    #: the truth samples the truth picture reads, by time, when the windows predict it as they
    #: pass (a run with safety and its reference on disk)
    truth_slice: TruthSlice | None = None
    #: what the windows' bound fixes before the first of them (a run on disk with truth whose
    #: bound can be made); None: the end of the run bounds the whole recording
    bound: BoundSetup | None = None
    #: the scored samples of the windows done, as stored (the bound and the lag sums read them back)
    stored_scored: Callable[[], list[Path]] | None = None
    #: the windows sum the consistency statistics' lags of each whole series (a run on disk with truth)
    lags: bool = False
    #: the ``truth`` table was handed to the run's sink before the windows (it is written while
    #: they run): finalize does not hand it again
    truth_sunk: bool = False
    #: where the end's independent pieces run (:mod:`tertiary.runtime.fanout`: the matching of
    #: pictures no window matched by stretch of windows, the truth's intervals and picture by
    #: time chunk, the bound by block of aircraft); None: here, in turn
    fanout: Fanout | None = None


@dataclass(frozen=True)
class StreamState:
    """Every streamed stage's carried state after a window (pickled by the engine's checkpoint)."""

    align: AlignState
    associate: AssociateState
    fuse: FuseState
    centralized: CentralizedState
    cluster: ClusterState
    track: TrackState
    conflicts: safety_conflicts.ConflictState
    identity: pl.DataFrame          # last Mode S address per (run, filter, method, track_id)
    recent: pl.DataFrame            # validated reports still needed by a later window (plots)
    #: the association statistics summed over windows, and ``_rows``: the input rows of the
    #: reports kept in ``recent``
    counts: dict[str, Any] = field(default_factory=dict)
    departures: DepartureState | None = None      # None: initial
    #: the association metrics' accumulators (a Dask partition's: of its kept span, in its own
    #: ids); None: not carried, so finalize scores the association rows read back
    scores: AssociationScore | None = None
    #: one conflict prediction state per point of the STCA curves (None: initial)
    curves: tuple | None = None
    #: the evaluation's matching state (None: initial, or not matched in the windows)
    evaluation: MatchState | None = None
    #: the truth's separation intervals of the chunks the windows have passed (None: initial, or
    #: not computed in the windows)
    intervals: TruthIntervals | None = None
    #: the bound's carried aircraft, plots and sums (None: initial, or not bounded in the windows)
    bound: BoundState | None = None
    #: the truth picture's prediction (None: initial, or not predicted in the windows)
    truth_picture: TruthPictureState | None = None
    #: the consistency statistics' lag sums of the series retired (None: initial, or not summed
    #: in the windows)
    lags: LagState | None = None
    #: every window evaluated wrote its block of the safety pictures' reduced id map (None:
    #: initial, or not written; False: a window did not, so the end reads the matched rows)
    id_rows: bool | None = None


def _context(ds: Dataset, cfg: PipelineConfig, notes: list[str], source: ReportSource) -> tuple[RunContext, pl.DataFrame]:
    """The run's shared context and the radar rejects."""
    radars, rej_r, raw_r = validate_table(contract.as_frame(ds.radars, "radars"), "radars", cfg.strict, notes,
                                          limits=cfg.limits)
    gone = (raw_r["radar_id"].cast(pl.UInt32, strict=False).drop_nulls().to_list()
            if "radar_id" in raw_r.columns else [])
    if radars.height == 0:
        notes.append("radars: no valid radar; every report is rejected")
    if "kind" in radars.columns and (radars["kind"] == "adsb").any():
        q = cfg.align.adsb_quality
        notes.append(f"ADS-B fused when its declared quality is NACp >= {max(q.min_nacp, 1)}, NIC >= {q.min_nic} "
                     f"and SIL >= {q.min_sil} (sigma from NACp, EPU/2.448 per axis); reports below it are rejected "
                     f"with the indicator as the reason")
    period = radars["scan_period_s"].max() if radars.height else None
    slowest = float(period) if period is not None and math.isfinite(period) else 12.0
    hold_s = cfg.align.max_age_scans * slowest + 4 * slowest + _max_delay_s(cfg)
    origin_us = (source.first_us // US) * US if source.windowable else None
    plans, rej_f = valid_flight_plans(ds, cfg, notes)
    rejects = pl.concat([r for r in (rej_r, rej_f) if r.height] or [rej_r], how="vertical_relaxed")
    return RunContext(radars, gone, ds.origin, origin_us, int(hold_s * US), filter_dict(cfg.filters),
                      flight_plans=plans, departure_plans=departure_plans(plans, ds.origin)), rejects


def _max_delay_s(cfg: PipelineConfig) -> float:
    """How long the report collection queue may hold a report back (s)."""
    return 60.0 if cfg.collection is not None else 0.0


def _ingest_window(raw: pl.DataFrame, ctx: RunContext, cfg: PipelineConfig, notes: list[str]
                   ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(valid reports, their input rows, ingest rejects) of one window's input rows (``raw``
    carries each row's input position in ``__input_row``)."""
    if raw.height == 0:
        return raw.drop(contract.INPUT_ROW), pl.DataFrame(schema={"report_id": pl.UInt64, "row_index": pl.UInt64}), \
            no_rejects()
    kw = {"median_time": ctx.median} if ctx.median is not None else {}
    reports, rej_p, _ = validate_table(raw, "reports", cfg.strict, notes, radars=ctx.radars, limits=cfg.limits,
                                       rejected_radars=ctx.gone, **kw)
    rows = reports.select("report_id", pl.col(contract.INPUT_ROW).cast(pl.UInt64).alias("row_index"))
    return reports.drop(contract.INPUT_ROW), rows, rej_p


def init_stream_state(cfg: PipelineConfig) -> StreamState:
    """Every streamed stage's state before the first window."""
    return StreamState(align=align_stage.init_align_state(), associate=init_associate_state(),
                       fuse=init_fuse_state(), centralized=init_centralized_state(), cluster=init_cluster_state(),
                       track=init_track_state(cfg.filters), conflicts=safety_conflicts.init_conflict_state(),
                       identity=pl.DataFrame(schema={"run": pl.UInt32, "filter": pl.String, "method": pl.String,
                                                     "track_id": pl.UInt64, "mode_s": pl.String}),
                       recent=pl.DataFrame(), scores=AssociationScore())


def pipeline_step(cfg: PipelineConfig, ctx: RunContext, st: StreamState, raw: pl.DataFrame, w: Window,
                  clock: StageClock, notes: list[str]) -> tuple[dict[str, pl.DataFrame], StreamState]:
    """One window through every streamed stage: its processing (:func:`process_step`), then its
    evaluation (:func:`~tertiary.pipeline.window_evaluation.evaluate_step`). Outputs hold the
    window's epochs only (``reports``/``rejects``: the window's input rows)."""
    out, st, hand = process_step(cfg, ctx, st, raw, w, clock, notes)
    if hand is None:
        return out, st
    more, st = evaluate_step(cfg, ctx, st, hand, w, clock)
    return {**out, **more}, st


def process_step(cfg: PipelineConfig, ctx: RunContext, st: StreamState, raw: pl.DataFrame, w: Window,
                 clock: StageClock, notes: list[str]) -> tuple[dict[str, pl.DataFrame], StreamState, Handoff | None]:
    """Window ``w`` through ingest → align → associate → fuse (+ the centralised reference) →
    cluster → track → conflicts: its tables, the state with these stages' fields advanced, and
    what its evaluation reads (None: nothing to evaluate, no radar is valid)."""

    clock.stage("validate")
    reports, report_rows, rejects = _ingest_window(raw, ctx, cfg, notes)
    if cfg.register and reports.height:      # whole-run options: their runs are one window (windowable)
        reports = registered(Ingested(ctx.radars, reports, pl.DataFrame(), rejects, notes), ctx.origin, cfg)
    if cfg.collection is not None and reports.height:   # report collection queue (§1.4): lost reports -> rejects
        reports, lost, collected = collection_stage(reports, report_rows, cfg.collection)
        rejects = pl.concat([rejects, lost], how="vertical_relaxed")
        notes.extend(collected)
    if ctx.radars.height == 0:     # no valid radar: every report was rejected, nothing can be aligned
        return {"reports": reports, "rejects": rejects}, st, None
    recent = reports if st.recent.width == 0 else pl.concat([st.recent, reports], how="diagonal_relaxed")
    to_align = reports
    if ctx.flight_plans.height:     # each report's cleared level, by its Mode 3/A code (tertiary.stages.flight_data)
        to_align = correlate(reports, ctx.flight_plans)
    stages = ctx.stages
    clock.stage("align")
    out, s_align = stages["align"].step(st.align, {"reports": to_align}, w)
    aligned, align_rej = out["aligned"], out["rejects"]
    s_dep = st.departures
    if ctx.departure_plans.height and "mode_3a" in recent.columns:   # uncorrelated by code: by aerodrome and time
        codes = recent.select("run", "report_id", "mode_3a")
        out, s_dep = stages["departures"].step(s_dep or stages["departures"].init(),
                                               {"aligned": aligned, "reports": reports, "codes": codes}, w)
        aligned = out["aligned"]
    rows_in = pl.concat([st.counts.get("_rows", pl.DataFrame(schema=report_rows.schema)), report_rows])
    rejects = pl.concat([rejects, stage_rejects_table(align_rej, recent, rows_in, "align")], how="vertical_relaxed")
    clock.stage("associate")
    out, s_assoc = stages["associate"].step(st.associate, {"aligned": aligned}, w)
    associations, stats = out["associations"], out["stats"].row(0, named=True)
    s_scores = st.scores
    if s_scores is not None and "truth_id" in recent.columns:
        clock.stage("score_associations")
        # scored as the run goes (evaluation-only labels): finalize does not read the rows back;
        # ``recent`` holds the reports of every row the window associates (as the fusion reads them)
        scored = associations
        if ctx.scored_span is not None and associations.height:
            e = pl.col("epoch").dt.epoch("us")
            scored = associations.filter((e >= ctx.scored_span[0]) & (e < ctx.scored_span[1]))
        s_scores = score_associations(s_scores, scored, recent.select("run", "report_id", "truth_id"))
    clock.stage("fuse")
    rows = aligned.with_columns(associations["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    fresh = recent.join(aligned.filter(pl.col("fresh")).select("run", "report_id"), on=["run", "report_id"],
                        how="semi") if aligned.height else recent.clear()
    plots = measured_plots(fresh, ctx.radars, ctx.origin, cfg.align.local_tracker.altitude_sigma_m)
    out, s_fuse = stages["fuse"].step(st.fuse, {"rows": rows, "plots": plots}, w)
    fused = out["fused"]
    s_central = st.centralized
    if cfg.centralized:
        clock.stage("centralized")
        keys = rows.select("run", "epoch", "target_id").unique(maintain_order=True)
        out, s_central = stages["centralized"].step(
            st.centralized, {"reports": recent, "associations": associations, "keys": keys,
                             "live": s_assoc.live_targets()}, w)
        fused = pl.concat([fused, out["centralized"]], how="diagonal_relaxed")
    clock.stage("cluster")
    out, s_cluster = stages["cluster"].step(st.cluster, {"fused": fused}, w)
    clusters = out["clusters"]
    clock.stage("track")
    pictures = fused.filter(pl.col("method") != "centralized")
    out, s_track = stages["track"].step(st.track, {"fused": pictures}, w)
    tracks, identity = _identity_step(st.identity, out["tracks"], pictures)
    conflicts, s_conf = contract.empty_frame("conflicts", False), st.conflicts
    if cfg.safety:
        clock.stage("conflicts")
        picture, _ = safety_picture(cfg, fused, tracks, notes)
        out, s_conf = stages["conflicts"].step(st.conflicts, {"picture": picture}, w)
        conflicts = out["conflicts"]
    hand = Handoff(reports, aligned, fused, tracks, picture if cfg.safety else None, "truth_id" in recent.columns,
                   conflicts if cfg.safety else None)
    keep_from = w.t1_us - ctx.keep_us
    recent = recent.filter(pl.col("time").dt.epoch("us") >= keep_from) if recent.height else recent
    counts = _add_counts(st.counts, stats, rows_in.filter(pl.col("report_id").is_in(recent["report_id"].implode()))
                         if recent.height else rows_in.clear())
    out = {"reports": reports, "rejects": rejects, "aligned": aligned, "associations": associations, "fused": fused,
           "clusters": clusters, "tracks": tracks, "conflicts": conflicts}
    if ctx.on_disk:
        # what the end reads of the fused and tracks parts, and of the conflicts the rows the alert
        # scoring reads, made while the window is in memory: the end does not read every part again
        out.update({facts_table(name): window_facts(out[name]) for name in ("fused", "tracks")})
        if cfg.safety:
            out[SCORED_CONFLICTS] = safety_alerts.scored_conflicts(conflicts)
    return out, dataclasses.replace(st, align=s_align, associate=s_assoc, fuse=s_fuse, centralized=s_central,
                                    cluster=s_cluster, track=s_track, conflicts=s_conf, identity=identity,
                                    recent=recent, counts=counts, departures=s_dep, scores=s_scores), hand


def _add_counts(counts: dict, stats: dict[str, Any], rows: pl.DataFrame) -> dict:
    """Association statistics summed over windows; ``_rows`` the input rows of the reports kept."""
    out = dict(counts)
    for k in ("pairs", "components", "ambiguous_components", "reassignments"):
        out[k] = out.get(k, 0) + int(stats.get(k, 0) or 0)
    out["_rows"] = rows
    return out


#: what a track carries from the target it was last updated with, besides its Mode S address
_CARRIED = (contract.SELECTED_ALT_COLUMN, contract.TURN_RATE_COLUMN, contract.CLEARED_ALT_COLUMN)

#: the carried levels a track withholds once its aircraft has left them (:mod:`tertiary.stages.tracking.intent`)
_LEVELS = (contract.SELECTED_ALT_COLUMN, contract.CLEARED_ALT_COLUMN)


def _identity_step(last: pl.DataFrame, tracks: pl.DataFrame, pictures: pl.DataFrame
                   ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`track_identity` carried across windows: each track's Mode S address and selected
    altitude (and track-angle rate) continue from their last values of the previous windows while
    it coasts (``last`` gains the :data:`_CARRIED` columns it lacks), each level withheld where the
    track has left it (:func:`~tertiary.stages.tracking.intent.withhold_left_levels`, its reached
    flags carried in ``last``)."""
    if tracks.height == 0 or "mode_s" not in pictures.columns or "plot_target_id" not in tracks.columns:
        return tracks, last
    keys = ["run", "filter", "method", "track_id"]
    opt = [c for c in _CARRIED if c in pictures.columns]
    carried_cols = ["mode_s", *opt]
    levels = [c for c in _LEVELS if c in opt]
    for c in opt:
        if c not in last.columns:
            last = last.with_columns(pl.lit(None, pl.Float64).alias(c))
    for c in levels:
        if reached_column(c) not in last.columns:
            last = last.with_columns(pl.lit(None, pl.Boolean).alias(reached_column(c)))
    ident = pictures.select("run", "epoch", "method", pl.col("target_id").alias("plot_target_id"), *carried_cols)
    t = (tracks.drop(*carried_cols, strict=False)
         .join(ident, on=["run", "epoch", "method", "plot_target_id"], how="left", maintain_order="left")
         .with_row_index("__i"))
    first = t.group_by(keys).agg(pl.col("__i").min())
    seed = first.join(last.select(*keys, *(pl.col(c).alias(f"__last_{c}") for c in carried_cols)),
                      on=keys, how="inner").select("__i", *(f"__last_{c}" for c in carried_cols))
    t = (t.join(seed, on="__i", how="left", maintain_order="left")
         .with_columns(pl.coalesce(c, f"__last_{c}").alias(c) for c in carried_cols)
         .drop(*(f"__last_{c}" for c in carried_cols))
         .with_columns(pl.col(c).forward_fill().over(keys, order_by="epoch") for c in carried_cols))
    now = (t.sort("epoch").group_by(keys).agg(pl.col(c).last() for c in carried_cols)
           .filter(pl.any_horizontal(pl.col(c).is_not_null() for c in carried_cols)))
    t, reached = withhold_left_levels(t.drop("__i"), last, keys, levels)
    now = now.join(reached.select(*keys, *(reached_column(c) for c in levels if reached_column(c) in reached.columns)),
                   on=keys, how="left")
    now = now.with_columns(pl.lit(None, last.schema[c]).alias(c) for c in last.columns if c not in now.columns)
    carried = pl.concat([last.join(now.select(keys), on=keys, how="anti"), now.select(last.columns).cast(last.schema)])
    return t, carried


def stream(ds: Dataset, cfg: PipelineConfig, parts, window_s: float | None = DEFAULT_WINDOW_S,
           progress: Progress | None = None, notes: list[str] | None = None, grid_origin_us: int | None = None,
           scored_span: tuple[int, int] | None = None, match: bool = False) -> tuple[RunContext, StreamState]:
    """The streamed stages only (ingest → the STCA curves), window by window into ``parts`` —
    what one slice of a distributed run does (:mod:`tertiary.pipeline.dask_engine`);
    ``grid_origin_us`` puts the epochs on a grid given from outside (the whole recording's), not
    this input's first second. The association metrics are scored on the way for the epochs of
    ``scored_span`` (the slice's kept span) with the slice's own ids (``StreamState.scores``:
    the client relabels and merges them); None: not scored. ``match``: the truth is validated
    first and the windows match the pictures to it, step their metrics and sum the consistency
    lags (``StreamState.evaluation`` and ``lags``, which the client merges), ``parts`` giving a
    scratch directory and its stored windows' files."""
    cfg = adapt_to_scenario(check_config(cfg), ds)
    start = dataclasses.replace(init_stream_state(cfg), scores=None if scored_span is None else AssociationScore())
    ctx, st, _ = stream_windows(ds, cfg, StageClock(progress or (lambda _m: None)), [] if notes is None else notes,
                                check_window(window_s), parts, start, 0, grid_origin_us, scored_span,
                                evaluate="match" if match else False)
    return ctx, st


def stream_windows(ds: Dataset, cfg: PipelineConfig, clock: StageClock, notes: list[str], window_s: float | None,
                   parts: Any, resume_state: StreamState | None, start: int, grid_origin_us: int | None = None,
                   scored_span: tuple[int, int] | None = None, evaluate: bool | str = False,
                   sink: SinkThread | None = None) -> tuple[RunContext, StreamState, ReportSource]:
    """Every window from ``start`` through :func:`pipeline_step` (from ``resume_state``, else the
    initial state), each stored in ``parts`` as it completes; the run's context, its last state
    and its report source. ``evaluate``: a run on disk with truth validates the truth first and
    matches its pictures to it in the windows (:func:`first_truth`). ``sink``, the run's writer,
    gets the tables known before the end while the windows run: the ``truth`` once validated, and
    the stored windows' parts after every window (:meth:`SinkThread.catch_up`). ``evaluate`` "match":
    the windows run the evaluation stage and the lag sums only (the truth's intervals, the truth
    picture and the bound are left to the end)."""
    notes.extend(getattr(ds, "notes", []))
    clock.stage("validate")
    source = ReportSource(ds.reports, cfg.limits, clock_offsets(cfg))
    if source.n_rows == 0:
        raise DataError("reports: the table has no rows; nothing to process")
    window_s = windowable(cfg, source, window_s, notes)
    ctx, rej_radars = _context(ds, cfg, notes, source)
    if window_s is None:      # one window: the grid starts at the first *valid* report, as it always did
        ctx.grid_origin_us = None
    else:
        ctx.median = source.median
    if grid_origin_us is not None:
        ctx.grid_origin_us = grid_origin_us
    if source.first_us is not None:
        ctx.report_span = (source.first_us, source.last_us)
    if cfg.evaluation:
        ctx.requirements = run_requirements(cfg)
    if evaluate:
        ctx.truth = first_truth(ds, cfg, notes, source, parts, clock)
        ctx.reference = ctx.truth.matcher() if ctx.truth is not None else None
        if ctx.truth is not None and sink is not None:
            sink("truth", ctx.truth.table())
            ctx.truth_sunk = True
        if cfg.safety and ctx.reference is not None and ctx.reference.path is not None and evaluate != "match":
            ctx.truth_span = time_span(pl.scan_parquet(ctx.reference.files), safety_alerts.AlertConfig(cfg.conflicts),
                                       ctx.origin)
            ctx.truth_slice = reference_slice(ctx.reference.files)
        if ctx.reference is not None and ctx.reference.path is not None and hasattr(parts, "part_files"):
            if evaluate != "match":
                ctx.bound = bound_setup(ds, ctx.radars, ctx.origin, ctx.reference.path, source.lf)
            ctx.lags = True
    ctx.stages = build_stages(cfg, ctx)        # once the context (the grid origin, the reference) is final
    ctx.curves = bool(stca_settings(cfg)) and truth_lazy(ds) is not None
    # the end reduces the safety pictures' id map to the run's alerts when it knows them all
    # (an on-disk run's, :func:`~tertiary.pipeline.whole_run._alert_keys`): each window its block
    ctx.on_disk = hasattr(parts, "iter_parts")
    ctx.id_rows = (cfg.safety and ctx.reference is not None and ctx.on_disk
                   and (ctx.curves or not cfg.stca_lookaheads_s))
    ctx.scored_span = scored_span
    st = resume_state or init_stream_state(cfg)
    if resume_state is not None and start > 0 and ctx.bound is not None and resume_state.bound is None:
        # a checkpoint that carried no bound knows nothing of the aircraft scored before it
        st = dataclasses.replace(st, bound=BoundState(complete=False))
    if resume_state is not None and start > 0 and ctx.truth_slice is not None \
            and getattr(resume_state, "truth_picture", None) is None:
        # nor one that carried no truth picture of the grid epochs before it
        st = dataclasses.replace(st, truth_picture=TruthPictureState(complete=False))
    if resume_state is not None and start > 0 and ctx.id_rows and getattr(resume_state, "id_rows", None) is not True:
        # nor one whose windows did not all write their block of the id map
        st = dataclasses.replace(st, id_rows=False)
    if resume_state is not None and start > 0 and ctx.lags and getattr(resume_state, "lags", None) is None:
        # nor one that carried no lag sums of the series before it
        st = dataclasses.replace(st, lags=LagState(complete=False))
    if start == 0:
        parts.write(Window(-1, 0, 0), {"radars": ctx.radars, "rejects": rej_radars})
    occupied = source.occupied(ctx.grid_origin_us, window_s) if window_s is not None else None
    ws = list(windows(ctx.grid_origin_us or 0, source.last_us or 0, window_s, start,
                      source.first_us if source.windowable else None, occupied, ctx.keep_us))
    meter = Meter(clock.say, (ws[-1].index + 1) if ws else start)
    store = WindowStore(parts)
    if ctx.bound is not None or ctx.lags:
        ctx.stored_scored = functools.partial(store.stored, SCORED)
    overlap = Overlap(lambda st_, h, w_, c: evaluate_step(cfg, ctx, st_, h, w_, c), clock.say) \
        if store.threaded and len(ws) > 1 else None
    pace = CheckpointPace()
    done: list[tuple[Window, int]] = []      # windows stored (or in flight) and not yet said
    processed, reports_seen = st, meter.reports

    def tell() -> None:
        """One progress line per window once it is whole (evaluated and stored)."""
        for w_, n in done:
            if window_s is not None:
                meter.window(w_, max(w_.t0_us, source.first_us), min(w_.t1_us, source.last_us + 1), n)
        done.clear()
        if sink is not None:
            sink.catch_up(parts)

    try:
        for w in ws:
            clock.stage("read_window", say=False)     # timed apart: not the last stage's time
            raw = source.rows(w)
            reports_seen += raw.height
            info = {"time_done": _span_text(w, source), "reports_done": reports_seen}
            if overlap is None:
                out, st = pipeline_step(cfg, ctx, st, raw, w, clock, notes)
                clock.stage("write_window", say=False)    # the window's parts, carried state and manifest
                store.put(w, out, st, **info)
            else:
                # window k processed from its processing state while window k - 1 is evaluated
                out, processed, hand = process_step(cfg, ctx, processed, raw, w, clock, notes)
                clock.stage("wait_evaluation", say=False)   # the previous window's evaluation, still running
                st = overlap.result() or st
                tell()
                due = pace.due(w is ws[-1], overlap.pickle_s + store.checkpoint_s + store.commit_s)
                overlap.submit(w, out, processed, hand, st, functools.partial(store.put, **info), checkpoint=due)
            done.append((w, raw.height))
            if overlap is None:
                tell()
            release_freed_memory()        # glibc keeps pages freed below live blocks: over a long run they add up
        if overlap is not None:
            clock.stage("wait_evaluation", say=False)
            st = overlap.result() or st
            tell()
        store.join()
    finally:
        if overlap is not None:
            overlap.close()
            overlap.timings(clock)
        store.close()
    return ctx, st, source


#: the share of a run's wall time its checkpoints may take, and the cost (s) below which every
#: window is checkpointed (:class:`CheckpointPace`)
CHECKPOINT_SHARE = 0.02
CHECKPOINT_FREE_S = 0.05


@dataclass
class CheckpointPace:
    """Which windows' states are checkpointed (a resume starts after the last): the last window,
    every window while a checkpoint costs less than :data:`CHECKPOINT_FREE_S`, and otherwise a
    window once the time since the previous checkpoint is at least the last one's cost over
    :data:`CHECKPOINT_SHARE`. A day's state, tens of MB pickled and written, is then
    checkpointed every few windows: a killed run loses seconds of work, and a long one spends
    no more than that share of its time on them."""

    last_t: float = float("-inf")

    def due(self, final: bool, cost_s: float) -> bool:
        now = time.perf_counter()
        if final or cost_s < CHECKPOINT_FREE_S or now - self.last_t >= cost_s / CHECKPOINT_SHARE:
            self.last_t = now
            return True
        return False


class WindowStore:
    """A window's parts, carried state and manifest written to a run directory on a thread of
    their own while the next window computes. One
    window in flight: :meth:`put` waits for the previous one first, so the manifest names a
    window complete only once its parts and state are on disk, in window order. The state is
    pickled by the caller before the next window runs (a stage may reuse its state's arrays).
    Other part stores (in memory, the Dask engine's) are written at once."""

    def __init__(self, parts) -> None:
        self.parts = parts
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="window-store") if isinstance(parts, PartStore) else None
        self._pending: Future | None = None
        #: seconds the last checkpoint took to pickle, and to write with the manifest
        self.checkpoint_s = self.commit_s = 0.0

    @property
    def threaded(self) -> bool:
        """Whether windows are written on a thread of their own (a run directory's part store)."""
        return self._pool is not None

    def put(self, w: Window, out: dict[str, pl.DataFrame], st: StreamState | None, **info: Any) -> None:
        """Store window ``w``'s tables and state (``info``: the manifest's progress fields; ``st``
        None: its tables only, the window is complete at the next checkpoint)."""
        if self._pool is None:
            self.parts.write(w, out)
            self.parts.checkpoint(w, st, **info)
            return
        state = None
        if st is not None:
            t = time.perf_counter()
            state = PartStore.state_bytes(w, st)
            self.checkpoint_s = time.perf_counter() - t
        self.join()
        self._pending = self._pool.submit(self._store, w, out, state, info)

    def _store(self, w: Window, out: dict[str, pl.DataFrame], state: bytes | None, info: dict) -> None:
        self.parts.write(w, out)
        if state is not None:
            t = time.perf_counter()
            self.parts.commit(w, state, **info)
            self.commit_s = time.perf_counter() - t

    def stored(self, name: str) -> list[Path]:
        """The files of table ``name`` of every window stored, the one in flight included."""
        self.join()
        return self.parts.part_files(name)

    def join(self) -> None:
        """Wait for the window in flight; its failure raised here."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def close(self) -> None:
        """Wait for the writes in flight (a failing run's stored windows are read back next)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)


def _span_text(w: Window, source: ReportSource) -> str:
    """How far the input is processed once window ``w`` is (for the manifest)."""
    return utc_text(min(w.t1_us, (source.last_us or 0) + 1)) if source.windowable else "end"


def clock_offsets(cfg: PipelineConfig) -> dict[int, int] | None:
    """radar_id → µs of a given registration's clock offsets (rounded as
    :func:`tertiary.stages.align.apply_registration` rounds them), which decide a report's window."""
    if not (cfg.register and cfg.registration):
        return None
    rows = [(int(r[0]), float(r[3])) for r in cfg.registration]
    us = (pl.Series([d for _, d in rows], dtype=pl.Float64).fill_nan(0.0) * US).round(0).cast(pl.Int64)
    return {rid: int(v) for (rid, _), v in zip(rows, us)}


def windowable(cfg: PipelineConfig, source: ReportSource, window_s: float | None, notes: list[str]) -> float | None:
    """``window_s``, or None (one window) with a note when the run cannot be cut in time."""
    if window_s is None:
        return None
    why = ("the reports' time column is not a timestamp" if not source.windowable else
           "radar registration is estimated from the whole recording" if cfg.register and not cfg.registration else
           "the report collection queue is simulated over the whole recording" if cfg.collection is not None else
           "strict mode stops at the first invalid row of the whole input" if cfg.strict else None)
    if why:
        notes.append(f"processed as one window: {why}")
        return None
    return window_s


def track_identity(tracks: pl.DataFrame, fused: pl.DataFrame) -> pl.DataFrame:
    """``tracks`` with ``mode_s``: the Mode S address of the fused target each track was last
    updated with (carried while it coasts), so that a controller's picture has an identity —
    what identity correctness is scored on and what tells a duplicate track of one aircraft
    from a second aircraft — and likewise ``selected_alt_m`` (the target's Mode S selected
    altitude, latest known), ``ehs_track_rate_dps`` (its BDS 5,0 track-angle rate, latest
    known: conflict prediction follows a turn with it) and ``cleared_alt_m`` (its cleared level
    from flight data, latest known) when ``fused`` carries them; a level the track has left is
    withheld (:mod:`tertiary.stages.tracking.intent`)."""
    if tracks.height == 0 or "mode_s" not in fused.columns or "plot_target_id" not in tracks.columns:
        return tracks
    cols = ["mode_s", *(c for c in _CARRIED if c in fused.columns)]
    ident = fused.select("run", "epoch", "method", pl.col("target_id").alias("plot_target_id"), *cols)
    keys = ["run", "filter", "method", "track_id"]
    out = (tracks.drop(*cols, strict=False)
           .join(ident, on=["run", "epoch", "method", "plot_target_id"], how="left", maintain_order="left")
           .with_columns(pl.col(c).forward_fill().over(keys, order_by="epoch") for c in cols))
    return withhold_left_levels(out, out.select(keys).clear(), keys, _LEVELS)[0]
