"""The batch job: dataset in, one DuckDB run database out.

Stages are composed here and nowhere else: ingest/validate → align → gate + associate → fuse
(every selected method, plus the centralised measurement-level reference) → cluster → secondary
trackers on every fusion method's picture → conflict prediction on every picture → evaluate
(accuracy, consistency, association, trackers, the posterior Cramér–Rao bound beside every
picture, alerts against truth, capacity from the measured accuracy)
→ store. Every input report ends up in ``aligned`` or ``rejects`` (checked, not assumed).

:func:`screen` applies every rule that can reject a report (the data contract and the align
stage's plan) and is the first step of :func:`process`, so ``tertiary validate`` reports exactly
what ``tertiary run`` rejects. :func:`run` stores each stage's tables as soon as the stage
completes; a failing stage (or "no valid report left") still leaves the completed tables, the
rejects and a run record with ``status``, ``failed_stage`` and ``error`` before the error is raised.
"""

from __future__ import annotations

import hashlib
import math
import platform
import shutil
import tempfile
import time
import warnings
import weakref
from collections.abc import Callable, Collection, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import dataclasses
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import polars as pl

from tertiary.stages import align as align_stage
from tertiary.core import geo
from tertiary.contract import schema
from tertiary.stages.align import AlignConfig, AlignPlan
from tertiary.stages.association.associate import AssociationConfig, AssociationStats, associate
from tertiary.stages.fusion.centralized import CentralizedConfig, centralized_fusion
from tertiary.evaluation.indicators import indicators
from tertiary.stages.clustering import ClusteringConfig, cluster
from tertiary.sensors.collection import CollectionConfig
from tertiary.evaluation.bound import bound_stage
from tertiary.evaluation.accuracy import BY_EPOCH_SCHEMA
from tertiary.evaluation.evaluate import (NEIGHBOUR_COLUMNS, AssociationScore, Evaluation, EvaluationConfig, association_metrics, association_score, evaluate_each, score_associations, read_reference, reference_files, write_reference, write_reference_pieces)
from tertiary.stages.tracking.filters import REGISTRY
from tertiary.stages.flight_data import DepartureConfig, departure_plans, departure_step, init_departure_state
from tertiary.stages.fusion.fuse import ALL_METHODS, METHODS, FusionConfig, fuse, measured_plots
from tertiary.simulate import Dataset, scenario_toml
from tertiary.runtime.windows import (AUTO_WINDOW, DEFAULT_WINDOW_S, END_US, PARTS, STREAMED, US, MemoryParts, Meter, PartStore, ReportSource, Window, check_window, config_hash, is_auto, peak_rss_mib, prefetched, release_memory, resolve_window, windows)
from tertiary.runtime.windows import _concat as _concat_parts
from tertiary.core.errors import DataError, OptionError, TertiaryError
from tertiary.stages.tracking.tracker import TrackerConfig, track_methods
from tertiary.runtime.warmup import kernels_for
from tertiary.runtime.warmup import warm as warm_kernels
from tertiary.evaluation.matching import neighbour_times
from tertiary.store.run_store import TABLES_DIR, RunStore, record_run

if TYPE_CHECKING:  # `safety` builds on `tertiary`; at run time it is imported where it is used
    from safety.conflicts import ConflictConfig

Progress = Callable[[str], None]


def _default_conflict_config() -> "ConflictConfig":
    """The seed's rule with a controller's alert confirmation (m of n picture epochs)."""
    from safety.conflicts import STCA_CONFIRMATION, ConflictConfig
    m, n = STCA_CONFIRMATION
    return ConflictConfig(confirm_m=m, confirm_n=n)


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


_INPUT_ROW = schema.INPUT_ROW


def _validate_table(frame: pl.DataFrame, kind: str, strict: bool, notes: list[str], **kw):
    """(clean, packed rejects, raw rejects) of one input table."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", schema.UnsortedTimeWarning)
        out = schema.validate(frame, kind, strict=strict, **kw)
    notes.extend(str(w.message) for w in caught if issubclass(w.category, schema.UnsortedTimeWarning))
    if strict:
        return out, schema.empty_frame("rejects"), pl.DataFrame()
    clean, rejects = out
    if _INPUT_ROW in rejects.columns:      # a window's rows: their position in the whole input
        rejects = rejects.with_columns(pl.col(_INPUT_ROW).cast(pl.UInt64).alias(schema.ROW_INDEX))
    rejects = rejects.drop(_INPUT_ROW, strict=False)
    return clean, schema.rejects_table(rejects, kind, "ingest"), rejects


#: truth rows validated at a time (whole aircraft) in finalize: the checks copy every column
#: several times, so a long recording's truth is validated in parts (issue 16, memory)
TRUTH_PART_ROWS = 250_000


def _validate_truth(ds: Dataset, cfg: "PipelineConfig", notes: list[str], window) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(clean truth, packed rejects): :func:`_validate_table` of the whole truth, computed a few
    aircraft at a time. Every truth check is row-wise or within one aircraft (its key and its
    order are (truth_id, time)), the table's median time is taken once from the whole and each
    part carries its rows' input positions, so the clean table (in input order), its rejects
    and the notes are those of one call on the whole."""
    truth = schema.as_frame(ds.truth, "truth")
    kw = dict(limits=cfg.limits, time_window=window)
    if truth.height == 0:
        return truth, _no_rejects()
    if (cfg.strict or truth.height <= TRUTH_PART_ROWS or truth.schema.get("truth_id") is None
            or truth.schema.get("time") != schema.TIME or _INPUT_ROW in truth.columns):
        clean, rej, _ = _validate_table(truth, "truth", cfg.strict, notes, **kw)
        return clean, rej
    med = schema.table_median_time(truth, cfg.limits)
    # a group-by on the frame would first copy every column into one chunk: on the key alone
    sizes = truth.select("truth_id").group_by("truth_id").len().sort("truth_id", nulls_last=True)
    part_of = sizes.select("truth_id", (pl.col("len").cum_sum() // TRUTH_PART_ROWS).alias("__part"))
    where = truth.select("truth_id").join(part_of, on="truth_id", how="left", nulls_equal=True,
                                          maintain_order="left")["__part"]
    cleans, rejs = [], []
    for k in range(int(part_of["__part"].max()) + 1):
        rows = (where == k).arg_true()
        part = truth[rows].with_columns(rows.cast(pl.UInt64).alias(_INPUT_ROW))
        # the parts' unsorted-time notes are left out: the whole table's is taken below
        clean, rej, _ = _validate_table(part, "truth", False, [], median_time=med, **kw)
        cleans.append(clean)
        rejs.append(rej)
    del truth, where
    clean = pl.concat(cleans, how="vertical")
    del cleans
    order = clean[_INPUT_ROW].arg_sort()
    clean = clean.drop(_INPUT_ROW)
    # back in input order a column at a time, each source column released once gathered: the
    # table is never held twice (a whole-frame sort would)
    gathered = {}
    for name in clean.columns:
        gathered[name] = clean[name].gather(order)
        clean = clean.drop(name)
    clean = pl.DataFrame(gathered)
    del gathered
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", schema.UnsortedTimeWarning)
        clean = schema.sort_tracks(clean, "truth")
    notes.extend(str(w.message) for w in caught if issubclass(w.category, schema.UnsortedTimeWarning))
    return clean, pl.concat(rejs, how="vertical_relaxed").sort("row_index", maintain_order=True)


#: input truth rows read at a time by :func:`_stream_truth` (then split into aircraft parts)
TRUTH_BATCH_ROWS = 262_144


@dataclass
class StreamedTruth:
    """The validated truth of an on-disk run, on disk (:func:`_stream_truth`): its reference
    directory (None when no row is clean), its number of clean rows and its schema (``empty``)."""

    reference: Path | None
    rows: int
    empty: pl.DataFrame

    def pieces(self) -> Iterator[pl.DataFrame]:
        """The clean truth, in order, a reference file at a time (for the run database)."""
        for f in reference_files(self.reference):
            yield pl.read_parquet(f, columns=list(self.empty.columns))


def _truth_lazy(ds: Dataset) -> pl.LazyFrame | None:
    truth = ds.truth
    return truth if isinstance(truth, pl.LazyFrame) else truth.lazy() if isinstance(truth, pl.DataFrame) else None


def _stream_truth(ds: Dataset, cfg: "PipelineConfig", notes: list[str], window,
                  scratch: Path) -> tuple[StreamedTruth, pl.DataFrame] | None:
    """(the clean truth on disk, packed rejects): :func:`_validate_truth` from disk to disk, so
    neither the input truth nor the clean one is ever held whole (a national hour's truth is
    5 M rows, 549 MiB: issue 18, memory). None where :func:`_validate_truth` validates the
    table in one call (strict mode, a small or malformed table): the caller does that.

    One pass reads the input ``TRUTH_BATCH_ROWS`` at a time and files each batch's rows by
    aircraft part (:func:`_validate_truth`'s parts); each part is validated, put back in input
    order and given its samples' neighbour times; the clean rows are then written as a reference
    (:func:`write_reference_pieces`) in :func:`_validate_truth`'s order — input order, or
    (truth_id, time) when some aircraft's times decrease — a file per input batch or per part.
    Every check is row-wise or within one aircraft, the median time is the whole table's and
    the unsorted-time note adds the parts' counts, so the rows, rejects and notes are
    :func:`_validate_truth`'s."""
    lf = _truth_lazy(ds)
    if lf is None or cfg.strict:
        return None
    sch = lf.collect_schema()
    if sch.get("truth_id") is None or sch.get("time") != schema.TIME or _INPUT_ROW in sch:
        return None
    n = lf.select(pl.len()).collect().item()
    if n <= TRUTH_PART_ROWS:
        return None
    kw = dict(limits=cfg.limits, time_window=window)
    med = schema.table_median_time(lf.select("time").collect(), cfg.limits)
    sizes = lf.select("truth_id").group_by("truth_id").len().sort("truth_id", nulls_last=True).collect()
    part_of = sizes.select("truth_id", (pl.col("len").cum_sum() // TRUTH_PART_ROWS).alias("__part"))
    n_parts = int(part_of["__part"].max()) + 1
    work = scratch / "truth"
    shutil.rmtree(work, ignore_errors=True)        # a resumed finalize's leftovers
    n_batches = -(-n // TRUTH_BATCH_ROWS)
    for b in range(n_batches):
        off = b * TRUTH_BATCH_ROWS
        batch = lf.slice(off, TRUTH_BATCH_ROWS).collect()
        batch = batch.with_columns(pl.int_range(off, off + batch.height, dtype=pl.UInt64).alias(_INPUT_ROW),
                                   batch.select("truth_id").join(part_of, on="truth_id", how="left", nulls_equal=True,
                                                                 maintain_order="left")["__part"])
        for (k,), rows in batch.partition_by("__part", as_dict=True, maintain_order=True).items():
            (work / f"in-{k:06d}").mkdir(parents=True, exist_ok=True)
            rows.drop("__part").write_parquet(work / f"in-{k:06d}" / f"{b:06d}.parquet", compression="lz4")
        del batch
    rejs, n_bad, n_groups, clean_rows, empty = [], 0, 0, 0, None
    for k in range(n_parts):
        src = work / f"in-{k:06d}"
        part = pl.read_parquet(sorted(src.glob("*.parquet")))
        shutil.rmtree(src)
        # the parts' unsorted-time notes are left out: the whole table's is made below
        clean, rej, _ = _validate_table(part, "truth", False, [], median_time=med, **kw)
        del part
        rejs.append(rej)
        clean = clean.sort(_INPUT_ROW)                 # input order (validation may have sorted)
        empty = clean.drop(_INPUT_ROW).clear()
        bad, groups = schema.unsorted_groups(clean, "truth")
        n_bad, n_groups, clean_rows = n_bad + bad, n_groups + groups, clean_rows + clean.height
        times = neighbour_times(clean)
        clean = clean.with_columns(times["__prev"], times["__next"],
                                   (pl.col(_INPUT_ROW) // TRUTH_BATCH_ROWS).alias("__batch"))
        for (b,), rows in clean.partition_by("__batch", as_dict=True, maintain_order=True).items():
            rows.drop("__batch").write_parquet(work / f"out-{b:06d}-{k:06d}.parquet", compression="lz4")
    rejects = pl.concat(rejs, how="vertical_relaxed").sort("row_index", maintain_order=True)
    if n_bad:
        notes.append(schema.unsorted_message("truth", n_bad, n_groups))
    if clean_rows == 0:
        shutil.rmtree(work, ignore_errors=True)
        return StreamedTruth(None, 0, empty), rejects

    def ordered() -> Iterator[pl.DataFrame]:
        # an input batch's rows are in these files only, a part's in these
        groups = ([sorted(work.glob(f"out-{b:06d}-*.parquet")) for b in range(n_batches)] if not n_bad else
                  [sorted(work.glob(f"out-*-{k:06d}.parquet")) for k in range(n_parts)])
        for files in groups:
            if not files:
                continue
            piece = pl.read_parquet(files).sort(_INPUT_ROW)
            if n_bad:       # the parts hold whole aircraft, in truth_id order
                piece = piece.sort(list(schema.table_order("truth")), maintain_order=True)
            yield piece.drop(_INPUT_ROW)
            for f in files:
                f.unlink()

    path = write_reference_pieces(ordered(), scratch / "reference")
    shutil.rmtree(work, ignore_errors=True)
    return StreamedTruth(path, clean_rows, empty), rejects


def _no_rejects() -> pl.DataFrame:
    return schema.empty_frame("rejects")


def ingest(ds: Dataset, strict: bool = False, limits: schema.Limits = schema.Limits()) -> Ingested:
    """Validate radars, reports (against the valid radars) and truth (against the reports' span).

    Strict mode raises :class:`tertiary.contract.schema.SchemaError` on the first problem; lenient mode
    moves bad rows to ``rejects`` with a reason (a rejected radar takes its reports along).
    """
    notes: list[str] = []
    radars, rej_r, raw_r = _validate_table(schema.as_frame(ds.radars, "radars"), "radars", strict, notes,
                                           limits=limits)
    gone = (raw_r["radar_id"].cast(pl.UInt32, strict=False).drop_nulls().to_list()
            if "radar_id" in raw_r.columns else [])
    if radars.height == 0:
        notes.append("radars: no valid radar; every report is rejected")
    raw = schema.as_frame(ds.reports, "reports")
    raw = raw.drop(_INPUT_ROW, strict=False).with_row_index(_INPUT_ROW)
    reports, rej_p, _ = _validate_table(raw, "reports", strict, notes, radars=radars, limits=limits,
                                        rejected_radars=gone)
    rows = reports.select("report_id", pl.col(_INPUT_ROW).cast(pl.UInt64).alias("row_index"))
    reports = reports.drop(_INPUT_ROW)
    truth_in = schema.as_frame(ds.truth, "truth")
    truth, rej_t = truth_in, _no_rejects()
    if truth_in.height:
        truth, rej_t, _ = _validate_table(truth_in, "truth", strict, notes, limits=limits,
                                          time_window=_truth_window(reports, limits))
    rejects = pl.concat([r for r in (rej_r, rej_p, rej_t) if r.height] or [_no_rejects()],
                        how="vertical_relaxed")
    return Ingested(radars, reports, truth, rejects, notes, rows)


def _truth_window(reports: pl.DataFrame, limits: schema.Limits):
    """(start, end, label) the truth must fall in: the valid reports' span ± the pad."""
    if reports.height == 0:
        return None
    pad = timedelta(seconds=limits.truth_pad_s)
    return (reports["time"].min() - pad, reports["time"].max() + pad,
            f"the reports' span +- {limits.truth_pad_s:g} s")


def screen(ds: Dataset, cfg: "PipelineConfig | None" = None) -> Ingested:
    """Every rule of the job that can reject a report, applied without running the job.

    Ingest (the data contract) and the align stage's rejections (its plan: unusable estimate,
    implausible speed, superseded, too old); ``rejects`` then holds exactly the rows — reasons,
    stages and input row indices — that :func:`run` rejects. :func:`process` uses it, so
    ``tertiary validate`` and ``tertiary run`` cannot disagree."""
    cfg = check_config(cfg)
    ing = ingest(ds, strict=cfg.strict, limits=cfg.limits)
    ing.notes[:0] = getattr(ds, "notes", [])
    _, rej_f = _flight_plans(ds, cfg, ing.notes)        # the same rows `run` rejects
    if rej_f.height:
        ing.rejects = pl.concat([ing.rejects, rej_f], how="vertical_relaxed")
    if _height(ds.reports) == 0:
        raise DataError("reports: the table has no rows; nothing to process")
    if ing.reports.height == 0:
        ing.notes.append(f"no valid report left: all {_height(ds.reports):,} reports rejected")
        return ing
    if cfg.register:
        ing.reports = _registered(ing, ds.origin, cfg)
    if cfg.collection is not None:   # report collection queue (§1.4): lost reports -> rejects
        from tertiary.sensors.collection import collection_stage
        ing.reports, lost, collected = collection_stage(ing.reports, ing.report_rows, cfg.collection)
        ing.rejects = pl.concat([ing.rejects, lost], how="vertical_relaxed")
        ing.notes.extend(collected)
    ing.plan = align_stage.plan(ing.reports, ing.radars, ds.origin, cfg.align)
    align_rej = _stage_rejects(ing.plan.rejects, ing.reports, ing.report_rows, "align")
    ing.rejects = pl.concat([ing.rejects, align_rej], how="vertical_relaxed")
    if int(ing.plan.keep.sum()) == 0:
        ing.notes.append(f"no valid report left: all {_height(ds.reports):,} reports rejected")
    return ing


def _registered(ing: Ingested, origin: geo.LocalFrame, cfg: "PipelineConfig") -> pl.DataFrame:
    """The valid reports with each radar's registration applied (``cfg.registration`` rows,
    else estimated radar to radar from these reports — never from the truth that scores the run)."""
    from tertiary.sensors import registration
    if cfg.registration:
        table = pl.DataFrame([list(map(float, row)) for row in cfg.registration], orient="row",
                             schema=["radar_id", "range_bias_m", "azimuth_bias_deg", "time_offset_s", "range_gain"])
        table = table.with_columns(pl.col("radar_id").cast(pl.UInt32))
        source = "given"
    else:
        table = registration.estimate(ing.reports, ing.radars, origin, None,
                                      registration.RegistrationConfig(method="multi")).table
        source = "estimated radar to radar"
    for row in table.iter_rows(named=True):       # one note per radar (a handful)
        ing.notes.append(f"registration ({source}) radar {row['radar_id']}: range {row['range_bias_m']:+.2f} m, "
                         f"azimuth {row['azimuth_bias_deg']:+.4f} deg, clock {row['time_offset_s']:+.4f} s")
    return align_stage.apply_registration(ing.reports, table)


def _height(frame) -> int:
    return frame.height if isinstance(frame, pl.DataFrame) else len(schema.as_frame(frame, "reports"))


def fingerprint(frame: pl.DataFrame) -> str:
    """A content hash of a table (row hashes combined), for the run record."""
    if frame.height == 0:
        return "empty"
    h = frame.hash_rows(seed=0)
    return hashlib.sha256(h.to_numpy().tobytes()).hexdigest()[:16]


@dataclass(frozen=True)
class PipelineConfig:
    """Configuration of every stage (each stage's own frozen dataclass)."""

    methods: tuple[str, ...] = METHODS
    filters: tuple[str, ...] = ("singer", "imm_sym")
    centralized: bool = True
    strict: bool = False
    limits: schema.Limits = field(default_factory=schema.Limits)
    align: AlignConfig = field(default_factory=AlignConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    centralized_cfg: CentralizedConfig = field(default_factory=CentralizedConfig)
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    safety: bool = True
    #: the picture conflict prediction runs on: "tracks" — the secondary tracker's confirmed tracks,
    #: one picture per fusion method × filter (what a controller sees); "fused" — the fused plot
    #: sets. Without filters, "tracks" falls back to "fused" (with a note).
    safety_picture: Literal["tracks", "fused"] = "tracks"
    conflicts: ConflictConfig = field(default_factory=_default_conflict_config)
    #: departure correlation by aerodrome and time (tertiary.stages.flight_data, "Departure correlation"):
    #: a departing track whose code correlates with no plan gets its plan's cleared level
    departures: DepartureConfig = field(default_factory=DepartureConfig)
    #: STCA final-approach volumes (safety.conflicts.ApproachVolume) from the scenario's runways
    #: (terminal-area, national) when ``conflicts`` configures none: the pairs established on
    #: one final are decided with the reduced in-trail minimum and a shorter look-ahead
    stca_approach_volumes: bool = True
    #: STCA and loss-of-separation scoring with the en-route minima above the scenario's en-route
    #: floor (safety.conflicts "En-route airspace"; national: FL150)
    stca_enroute_floor: bool = True
    #: STCA inhibited, and no loss of separation scored, between two aircraft both in one of the
    #: scenario's aerodrome zones (safety.conflicts "Aerodrome zones"; national: its airports)
    stca_aerodrome_zones: bool = True
    #: STCA trade-off curves (metrics stage "safety_tradeoff"): losses alerted with ≥ X s warning
    #: against nuisance + false alerts per hour as the threshold confidence (covariance
    #: thresholds), the fixed estimation term (m) and the look-ahead (s) vary; each point is one
    #: conflict prediction + scoring of every picture (~1 s on the default job), so the default
    #: is the configured look-ahead only; () skips the curves. Needs truth.
    stca_lookaheads_s: tuple[float, ...] = (105.0,)
    stca_confidences: tuple[float, ...] = (0.5, 0.8, 0.95, 0.99)
    stca_fixed_m: tuple[float, ...] = (0.0, 300.0, 600.0, 1200.0)
    #: the one evaluation stage (tertiary.evaluation.evaluate) scores every picture — each fusion method's
    #: confirmed targets and the centralised reference (seed stage "fusion"), each tracker picture
    #: (seed stage "tracker") — when there is a reference. ``evaluation`` adds the surveillance
    #: metrics (stage "evaluation") and the ``requirements`` table judged against
    #: ``requirements_file`` (None: the shipped example, datasets/requirements/example.toml)
    evaluation: bool = True
    requirements_file: str | None = None
    scoring: EvaluationConfig = field(default_factory=EvaluationConfig)
    #: radar registration before alignment (:func:`tertiary.stages.align.apply_registration`): with
    #: ``register``, rows (radar_id, range_bias_m, azimuth_bias_deg, time_offset_s, range_gain) of
    #: ``registration``, or when empty estimated from the reports radar to radar
    #: (:func:`tertiary.sensors.registration.estimate`, method "multi"; the truth is never used)
    register: bool = False
    registration: tuple[tuple[float, float, float, float, float], ...] = ()
    #: §1.7/§5.1/§2.2–2.3 indicators of every tracker picture (tertiary.evaluation.indicators; metrics stage
    #: "indicators"); needs truth. Off by default (one more matching per picture).
    indicators: bool = False
    #: per-radar health from the range innovations (tertiary.sensors.radar_health; metrics stage
    #: "radar_health"): windowed-NIS divergence alarm, adaptive-R estimates. Off by default.
    radar_health: bool = False
    #: report collection ahead of alignment (:mod:`tertiary.sensors.collection`, §1.4): the queue
    #: discipline and processing-time model; lost reports go to ``rejects`` (stage "collection")
    collection: CollectionConfig | None = None


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


class StageError(TertiaryError):
    """A stage failed unexpectedly; the completed stages and a run record were stored first."""

    def __init__(self, stage: str, cause: BaseException, db: Path) -> None:
        text = str(cause).strip().splitlines()[0] if str(cause).strip() else ""
        super().__init__(f"stage '{stage}' failed ({type(cause).__name__}: {text}); the completed stages "
                         f"and a run record saying so are in {db}")
        self.stage, self.db = stage, db


def adapt_to_scenario(cfg: PipelineConfig, ds: Dataset) -> PipelineConfig:
    """``cfg`` with the airspace adaptation an STCA is installed with, taken from the dataset's
    scenario unless ``cfg.conflicts`` already has it: the final-approach volumes of its runways
    (:func:`tertiary.simulate.traffic.final_approaches`; off with ``stca_approach_volumes``) and
    the floor of its en-route airspace (``national.enroute_floor_fl``; off with
    ``stca_enroute_floor``) and its aerodrome zones (:func:`tertiary.simulate.traffic.aerodromes`;
    off with ``stca_aerodrome_zones``)."""
    scen = getattr(ds, "scenario", None)
    if scen is None:
        return cfg
    conflicts = cfg.conflicts
    try:
        frame = ds.origin
    except DataError:
        frame = None
    if cfg.stca_approach_volumes and not conflicts.approach_volumes:
        from safety.conflicts import ApproachVolume
        from tertiary.simulate.traffic import final_approaches
        vols = tuple(ApproachVolume(x, y, course, length_m=length, name=f"final {course:05.1f}")
                     for x, y, course, length in final_approaches(scen, frame))
        if vols:
            conflicts = dataclasses.replace(conflicts, approach_volumes=vols)
    floor_fl = getattr(getattr(scen, "national", None), "enroute_floor_fl", 0.0)
    if cfg.stca_enroute_floor and conflicts.enroute_above_m is None and floor_fl > 0:
        from safety.conflicts import FT_M
        # half a level below it: an aircraft level at the floor is in it, whatever its altitude noise
        conflicts = dataclasses.replace(conflicts, enroute_above_m=(float(floor_fl) * 100.0 - 500.0) * FT_M)
    if cfg.stca_aerodrome_zones and not conflicts.aerodrome_zones:
        from safety.conflicts import AerodromeZone
        from tertiary.simulate.traffic import aerodromes
        zones = tuple(AerodromeZone(x, y, name=name) for name, x, y in aerodromes(scen, frame))
        if zones:
            conflicts = dataclasses.replace(conflicts, aerodrome_zones=zones)
    return cfg if conflicts is cfg.conflicts else dataclasses.replace(cfg, conflicts=conflicts)


def check_config(cfg: PipelineConfig | None) -> PipelineConfig:
    """``cfg`` (None = the defaults) after checking its names and numbers (:class:`OptionError`)."""
    cfg = cfg or PipelineConfig()
    unknown = sorted(set(cfg.methods) - set(ALL_METHODS))   # the optional methods too (not in the default)
    if unknown:
        raise OptionError(f"unknown fusion method(s) {', '.join(unknown)}; choose from {', '.join(ALL_METHODS)}",
                          option="methods")
    bad = sorted(set(cfg.filters) - set(REGISTRY))
    if bad:
        raise OptionError(f"unknown filter(s) {', '.join(bad)}; choose from {', '.join(sorted(REGISTRY))}",
                          option="filters")
    a = cfg.align
    if a.period_s is not None and not (isinstance(a.period_s, (int, float)) and 0 < a.period_s < float("inf")):
        raise OptionError(f"must be finite and > 0, got {a.period_s}", option="align.period_s")
    if cfg.safety_picture not in ("tracks", "fused"):
        raise OptionError(f"choose tracks or fused, got {cfg.safety_picture!r}", option="safety_picture")
    if (cfg.association.mode_3a != "off" or cfg.association.callsign != "off") and not cfg.align.identity:
        cfg = dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, identity=True))  # fine identification
    return cfg


class _Clock:
    def __init__(self, say: Progress):
        self.say, self.timings, self._t = say, {}, time.perf_counter()
        self.name: str | None = None
        self.memory: dict[str, float] = {}
        #: "finalize:" once the whole-run stages start (their memory is told apart from the windows')
        self.prefix = ""

    def stage(self, name: str | None, say: bool = True) -> None:
        """Start stage ``name`` (None: stop). A stage's time adds up over windows; its name is
        said the first time only (a window says one line of its own, :class:`tertiary.runtime.windows.Meter`),
        never with ``say=False`` (the engine's own reading and writing of each window).
        The peak resident memory reached by the end of a stage is kept in ``memory``."""
        now = time.perf_counter()
        if self.name is not None:
            key = f"{self.name}_s"
            self.timings[key] = self.timings.get(key, 0.0) + now - self._t
            # re-inserted: the record lists the stages in the order they last ended, so its
            # peaks-so-far read in increasing order even for a stage met again (write_tables)
            self.memory.pop(self.prefix + self.name, None)
            self.memory[self.prefix + self.name] = round(peak_rss_mib(), 1)
        self.name, self._t = name, now
        if say and name and f"{name}_s" not in self.timings and name != getattr(self, "_said", None):
            self._said = name
            self.say(name)


#: where a run's tables go: a frame whole, or a streamed table part by part (:class:`StreamedTable`)
Sink = Callable[[str, "pl.DataFrame | StreamedTable"], None]


def process(ds: Dataset, cfg: PipelineConfig | None = None, progress: Progress | None = None,
            sink: Sink | None = None, notes: list[str] | None = None, window_s: float | None = None,
            parts=None, resume_state: "StreamState | None" = None, start: int = 0) -> Results:
    """Run every stage and return the tables (``cfg`` None = the defaults).

    The streamed stages see the run in windows of ``window_s`` seconds (None: one window) and
    carry their state across them (:mod:`tertiary.runtime.windows`); ``parts`` receives each window's rows
    (default: kept in memory), then the whole-run stages (evaluation, alert scoring) run on them.
    ``sink(name, frame)`` receives each table once it is final; ``notes`` (if given) collects the
    run's notes as they arise, so they survive a failure. An exception carries the failing
    stage's name in ``exc.tertiary_stage``. No valid report left → :class:`DataError` after the
    rejects are sunk.
    """
    cfg = adapt_to_scenario(check_config(cfg), ds)
    window_s = check_window(window_s)
    # a fresh install compiles the kernels on the other core while the first stages run
    warm_kernels(kernels_for(cfg.filters, bound=_truth_lazy(ds) is not None))
    clock = _Clock(progress or (lambda _m: None))
    sink = sink or (lambda _n, _f: None)
    parts = parts if parts is not None else MemoryParts()
    try:
        return _process(ds, cfg, clock, sink, notes, window_s, parts, resume_state, start)
    except Exception as exc:
        # a write's failure is raised in a later stage's time: it names its own
        stage = getattr(exc, "tertiary_stage", None) or clock.name or "validate"
        exc.tertiary_stage = stage  # type: ignore[attr-defined]
        if not getattr(exc, "_sunk", False):
            _sink_partial(parts, sink)
        raise


def _sink_partial(parts, sink: Sink) -> None:
    """After a failure: every streamed table of the windows that completed."""
    for name in ("radars", *STREAMED):
        try:
            frame = parts.table(name)
        except Exception:  # a part that cannot be read back: the record says the run failed anyway
            continue
        if frame is not None:
            sink(name, frame)


@dataclass
class RunContext:
    """What every window of a run shares: the validated radars (and the ids of rejected ones), the
    system frame, the epoch grid origin and how long validated reports stay at hand."""

    radars: pl.DataFrame
    gone: list[int]
    origin: geo.LocalFrame
    grid_origin_us: int | None
    keep_us: int
    filters: dict = field(default_factory=dict)   # the tracker's filters, built once per run
    median: Any = None          # the whole input's median report time (windows are validated against it)
    flight_plans: pl.DataFrame = field(default_factory=pl.DataFrame)   # valid rows (tertiary.stages.flight_data)
    departure_plans: pl.DataFrame = field(default_factory=pl.DataFrame)   # flight_data.departure_plans


@dataclass(frozen=True)
class StreamState:
    """Every streamed stage's carried state after a window (pickled by the engine's checkpoint)."""

    align: Any
    associate: Any
    fuse: Any
    centralized: Any
    cluster: Any
    track: Any
    conflicts: Any
    identity: pl.DataFrame          # last Mode S address per (run, filter, method, track_id)
    recent: pl.DataFrame            # validated reports still needed by a later window (plots)
    counts: dict = field(default_factory=dict)
    departures: Any = None          # tertiary.stages.flight_data.DepartureState (None: initial)
    #: the association metrics' accumulators (tertiary.evaluation.evaluate.AssociationScore); None: not
    #: carried (a state from before them, or the Dask engine's relabelled partitions), so
    #: finalize scores the association rows read back
    scores: Any = None


def _context(ds: Dataset, cfg: PipelineConfig, notes: list[str], source: ReportSource) -> tuple[RunContext, pl.DataFrame]:
    """The run's shared context and the radar rejects."""
    radars, rej_r, raw_r = _validate_table(schema.as_frame(ds.radars, "radars"), "radars", cfg.strict, notes,
                                           limits=cfg.limits)
    gone = (raw_r["radar_id"].cast(pl.UInt32, strict=False).drop_nulls().to_list()
            if "radar_id" in raw_r.columns else [])
    if radars.height == 0:
        notes.append("radars: no valid radar; every report is rejected")
    period = radars["scan_period_s"].max() if radars.height else None
    slowest = float(period) if period is not None and math.isfinite(period) else 12.0
    hold_s = cfg.align.max_age_scans * slowest + 4 * slowest + _max_delay_s(cfg)
    origin_us = (source.first_us // US) * US if source.windowable else None
    from tertiary.stages.tracking.tracker import _filter_dict
    plans, rej_f = _flight_plans(ds, cfg, notes)
    rejects = pl.concat([r for r in (rej_r, rej_f) if r.height] or [rej_r], how="vertical_relaxed")
    return RunContext(radars, gone, ds.origin, origin_us, int(hold_s * US), _filter_dict(cfg.filters),
                      flight_plans=plans, departure_plans=departure_plans(plans, ds.origin)), rejects


def _flight_plans(ds: Dataset, cfg: PipelineConfig, notes: list[str]) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The dataset's valid flight plans and the rejects of the others (strict: the first bad row
    is a :class:`DataError`)."""
    from tertiary.stages.flight_data import check_flight_plans, empty_flight_plans
    if ds.flight_plans is None or ds.flight_plans.height == 0:
        return empty_flight_plans(), _no_rejects()
    plans, rej = check_flight_plans(ds.flight_plans, cfg.limits)
    if rej.height:
        text = f"flight_plans: {rej.height} row(s) rejected (first: row {rej['row_index'][0]}, {rej['reason'][0]})"
        if cfg.strict:
            raise DataError(text)
        notes.append(text)
    return plans, rej


def _max_delay_s(cfg: PipelineConfig) -> float:
    return 60.0 if cfg.collection is not None else 0.0


def _ingest_window(raw: pl.DataFrame, ctx: RunContext, cfg: PipelineConfig, notes: list[str]
                   ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(valid reports, their input rows, ingest rejects) of one window's input rows (``raw``
    carries each row's input position in ``__input_row``)."""
    if raw.height == 0:
        return raw.drop(_INPUT_ROW), pl.DataFrame(schema={"report_id": pl.UInt64, "row_index": pl.UInt64}), \
            _no_rejects()
    kw = {"median_time": ctx.median} if ctx.median is not None else {}
    reports, rej_p, _ = _validate_table(raw, "reports", cfg.strict, notes, radars=ctx.radars, limits=cfg.limits,
                                        rejected_radars=ctx.gone, **kw)
    rows = reports.select("report_id", pl.col(_INPUT_ROW).cast(pl.UInt64).alias("row_index"))
    return reports.drop(_INPUT_ROW), rows, rej_p


def init_stream_state(cfg: PipelineConfig) -> StreamState:
    from safety.conflicts import init_conflict_state
    from tertiary.stages.association.associate import init_associate_state
    from tertiary.stages.fusion.centralized import init_centralized_state
    from tertiary.stages.clustering import init_cluster_state
    from tertiary.stages.fusion.fuse import init_fuse_state
    from tertiary.stages.tracking.tracker import init_track_state
    return StreamState(align=align_stage.init_align_state(), associate=init_associate_state(),
                       fuse=init_fuse_state(), centralized=init_centralized_state(), cluster=init_cluster_state(),
                       track=init_track_state(cfg.filters), conflicts=init_conflict_state(),
                       identity=pl.DataFrame(schema={"run": pl.UInt32, "filter": pl.String, "method": pl.String,
                                                     "track_id": pl.UInt64, "mode_s": pl.String}),
                       recent=pl.DataFrame(), scores=AssociationScore())


def pipeline_step(cfg: PipelineConfig, ctx: RunContext, st: StreamState, raw: pl.DataFrame, w: Window,
                  clock: "_Clock", notes: list[str]) -> tuple[dict[str, pl.DataFrame], StreamState]:
    """One window through every streamed stage: ingest → align → associate → fuse (+ the
    centralised reference) → cluster → track → conflicts. Outputs hold the window's epochs only
    (``reports``/``rejects``: the window's input rows)."""
    from safety.conflicts import conflicts_step
    from tertiary.stages.association.associate import associate_step
    from tertiary.stages.fusion.centralized import centralized_step
    from tertiary.stages.clustering import cluster_step
    from tertiary.stages.fusion.fuse import fuse_step
    from tertiary.stages.tracking.tracker import track_step

    clock.stage("validate")
    reports, report_rows, rejects = _ingest_window(raw, ctx, cfg, notes)
    if cfg.register and reports.height:      # whole-run options: their runs are one window (_windowable)
        reports = _registered(Ingested(ctx.radars, reports, pl.DataFrame(), rejects, notes), ctx.origin, cfg)
    if cfg.collection is not None and reports.height:   # report collection queue (§1.4): lost reports -> rejects
        from tertiary.sensors.collection import collection_stage
        reports, lost, collected = collection_stage(reports, report_rows, cfg.collection)
        rejects = pl.concat([rejects, lost], how="vertical_relaxed")
        notes.extend(collected)
    if ctx.radars.height == 0:     # no valid radar: every report was rejected, nothing can be aligned
        return {"reports": reports, "rejects": rejects}, st
    recent = reports if st.recent.width == 0 else pl.concat([st.recent, reports], how="diagonal_relaxed")
    to_align = reports
    if ctx.flight_plans.height:     # each report's cleared level, by its Mode 3/A code (tertiary.stages.flight_data)
        from tertiary.stages.flight_data import correlate
        to_align = correlate(reports, ctx.flight_plans)
    clock.stage("align")
    t0 = None if w.t0_us <= -END_US else w.t0_us     # None: unbounded (the last window flushes held rows)
    t1 = None if w.last else w.t1_us
    g0 = ctx.grid_origin_us if ctx.grid_origin_us is not None else align_stage.epoch_grid(reports, ctx.radars, cfg.align)[0] \
        if reports.height else 0
    (aligned, align_rej), s_align = align_stage.align_step(st.align, to_align, ctx.radars, ctx.origin, t0, t1, g0,
                                                           cfg.align)
    s_dep = st.departures
    if ctx.departure_plans.height and "mode_3a" in recent.columns:   # uncorrelated by code: by aerodrome and time
        codes = recent.select("run", "report_id", "mode_3a")
        aligned, s_dep = departure_step(s_dep or init_departure_state(), aligned, reports, codes,
                                        ctx.departure_plans, cfg.departures)
    rows_in = pl.concat([st.counts.get("_rows", pl.DataFrame(schema=report_rows.schema)), report_rows])
    rejects = pl.concat([rejects, _stage_rejects(align_rej, recent, rows_in, "align")], how="vertical_relaxed")
    clock.stage("associate")
    (associations, stats), s_assoc = associate_step(st.associate, aligned, w.t0_us, w.t1_us, cfg.association)
    s_scores = st.scores
    if s_scores is not None and "truth_id" in recent.columns:
        clock.stage("score_associations")
        # scored as the run goes (evaluation-only labels): finalize does not read the rows back;
        # ``recent`` holds the reports of every row the window associates (as the fusion reads them)
        s_scores = score_associations(s_scores, associations, recent.select("run", "report_id", "truth_id"))
    clock.stage("fuse")
    rows = aligned.with_columns(associations["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    fresh = recent.join(aligned.filter(pl.col("fresh")).select("run", "report_id"), on=["run", "report_id"],
                        how="semi") if aligned.height else recent.clear()
    plots = measured_plots(fresh, ctx.radars, ctx.origin, cfg.align.local_tracker.altitude_sigma_m)
    fused, s_fuse = fuse_step(st.fuse, rows, ctx.radars, cfg.methods, cfg.fusion, ctx.origin, plots,
                              w.t0_us, w.t1_us)
    s_central = st.centralized
    if cfg.centralized:
        clock.stage("centralized")
        keys = rows.select("run", "epoch", "target_id").unique(maintain_order=True)
        central, s_central = centralized_step(st.centralized, recent, ctx.radars, associations, keys, ctx.origin,
                                              cfg.centralized_cfg, w.t0_us, w.t1_us, live=s_assoc.live_targets())
        fused = pl.concat([fused, central], how="diagonal_relaxed")
    clock.stage("cluster")
    clusters, s_cluster = cluster_step(st.cluster, fused, w.t0_us, w.t1_us, cfg.clustering)
    clock.stage("track")
    pictures = fused.filter(pl.col("method") != "centralized")
    tracks, s_track = schema.empty_frame("tracks", False), st.track
    if cfg.filters:
        tracks, s_track = track_step(st.track, pictures, ctx.filters, cfg.tracker, w.t0_us, w.t1_us)
    tracks, identity = _identity_step(st.identity, tracks, pictures)
    conflicts, s_conf = schema.empty_frame("conflicts", False), st.conflicts
    if cfg.safety:
        clock.stage("conflicts")
        picture, id_col = _safety_picture(cfg, fused, tracks, notes)
        conflicts, s_conf = conflicts_step(st.conflicts, picture, cfg.conflicts, id_col, ctx.origin, w.t0_us, w.t1_us)
    keep_from = (w.t1_us if w.t1_us < END_US else END_US) - ctx.keep_us
    recent = recent.filter(pl.col("time").dt.epoch("us") >= keep_from) if recent.height else recent
    counts = _add_counts(st.counts, stats, rows_in.filter(pl.col("report_id").is_in(recent["report_id"].implode()))
                         if recent.height else rows_in.clear())
    out = {"reports": reports, "rejects": rejects, "aligned": aligned, "associations": associations, "fused": fused,
           "clusters": clusters, "tracks": tracks, "conflicts": conflicts}
    return out, StreamState(s_align, s_assoc, s_fuse, s_central, s_cluster, s_track, s_conf, identity, recent, counts,
                            s_dep, s_scores)


def _add_counts(counts: dict, stats, rows: pl.DataFrame) -> dict:
    """Association statistics summed over windows; ``_rows`` the input rows of the reports kept."""
    out = dict(counts)
    for k in ("pairs", "components", "ambiguous_components", "reassignments"):
        out[k] = out.get(k, 0) + int(getattr(stats, k, 0) or 0)
    out["_rows"] = rows
    return out


#: what a track carries from the target it was last updated with, besides its Mode S address
_CARRIED = (schema.SELECTED_ALT_COLUMN, schema.TURN_RATE_COLUMN, schema.CLEARED_ALT_COLUMN)


def _identity_step(last: pl.DataFrame, tracks: pl.DataFrame, pictures: pl.DataFrame
                   ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`track_identity` carried across windows: each track's Mode S address and selected
    altitude (and track-angle rate) continue from their last values of the previous windows while
    it coasts (``last`` gains the :data:`_CARRIED` columns it lacks)."""
    if tracks.height == 0 or "mode_s" not in pictures.columns or "plot_target_id" not in tracks.columns:
        return tracks, last
    keys = ["run", "filter", "method", "track_id"]
    opt = [c for c in _CARRIED if c in pictures.columns]
    carried_cols = ["mode_s", *opt]
    for c in opt:
        if c not in last.columns:
            last = last.with_columns(pl.lit(None, pl.Float64).alias(c))
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
    now = now.with_columns(pl.lit(None, last.schema[c]).alias(c) for c in last.columns if c not in now.columns)
    carried = pl.concat([last.join(now.select(keys), on=keys, how="anti"), now.select(last.columns).cast(last.schema)])
    return t.drop("__i"), carried


def _process(ds: Dataset, cfg: PipelineConfig, clock: _Clock, sink: Sink, notes: list[str] | None,
             window_s: float | None = None, parts=None, resume_state: StreamState | None = None,
             start: int = 0) -> Results:
    """Stream every window through :func:`pipeline_step`, then finalize on the whole run."""
    t_all = time.perf_counter()
    notes = [] if notes is None else notes
    parts = parts if parts is not None else MemoryParts()
    ctx, st, source = _stream(ds, cfg, clock, notes, window_s, parts, resume_state, start)
    return _finalize(ds, cfg, ctx, st, parts, clock, sink, notes, source.n_rows, t_all)


def stream(ds: Dataset, cfg: PipelineConfig, parts, window_s: float | None = DEFAULT_WINDOW_S,
           progress: Progress | None = None, notes: list[str] | None = None, grid_origin_us: int | None = None
           ) -> tuple["RunContext", "StreamState"]:
    """The streamed stages only (ingest → conflicts), window by window into ``parts`` — what one
    slice of a distributed run does (:mod:`tertiary.runtime.dask_engine`); ``grid_origin_us`` puts the
    epochs on a grid given from outside (the whole recording's), not this input's first second.
    The association metrics are not scored on the way (``StreamState.scores`` None): a slice's
    ids are its own until stitched, so the finalize scores the relabelled rows."""
    cfg = adapt_to_scenario(check_config(cfg), ds)
    start = dataclasses.replace(init_stream_state(cfg), scores=None)
    ctx, st, _ = _stream(ds, cfg, _Clock(progress or (lambda _m: None)), [] if notes is None else notes,
                         check_window(window_s), parts, start, 0, grid_origin_us)
    return ctx, st


def finalize(ds: Dataset, cfg: PipelineConfig, ctx: "RunContext", st: "StreamState", parts, n_reports: int,
             progress: Progress | None = None, sink: Sink | None = None, notes: list[str] | None = None) -> Results:
    """The whole-run stages on streamed tables held by ``parts`` (see :func:`stream`)."""
    return _finalize(ds, adapt_to_scenario(check_config(cfg), ds), ctx, st, parts, _Clock(progress or (lambda _m: None)),
                     sink or (lambda _n, _f: None), [] if notes is None else notes, n_reports, time.perf_counter())


def _stream(ds: Dataset, cfg: PipelineConfig, clock: _Clock, notes: list[str], window_s: float | None, parts,
            resume_state: "StreamState | None", start: int, grid_origin_us: int | None = None):
    notes.extend(getattr(ds, "notes", []))
    clock.stage("validate")
    source = ReportSource(ds.reports, cfg.limits)
    if source.n_rows == 0:
        raise DataError("reports: the table has no rows; nothing to process")
    window_s = _windowable(cfg, source, window_s, notes)
    ctx, rej_radars = _context(ds, cfg, notes, source)
    if window_s is None:      # one window: the grid starts at the first *valid* report, as it always did
        ctx.grid_origin_us = None
    else:
        ctx.median = source.median
    if grid_origin_us is not None:
        ctx.grid_origin_us = grid_origin_us
    st = resume_state or init_stream_state(cfg)
    if start == 0:
        parts.write(Window(-1, 0, 0), {"radars": ctx.radars, "rejects": rej_radars})
    occupied = source.occupied(ctx.grid_origin_us, window_s) if window_s is not None else None
    ws = list(windows(ctx.grid_origin_us or 0, source.last_us or 0, window_s, start,
                      source.first_us if source.windowable else None, occupied, ctx.keep_us))
    meter = Meter(clock.say, (ws[-1].index + 1) if ws else start)
    store = _WindowStore(parts)
    try:
        for w in ws:
            clock.stage("read_window", say=False)     # timed apart: not the last stage's time
            raw = source.rows(w)
            out, st = pipeline_step(cfg, ctx, st, raw, w, clock, notes)
            clock.stage("write_window", say=False)    # the window's parts, carried state and manifest
            store.put(w, out, st, time_done=_span_text(w, source), reports_done=meter.reports + raw.height)
            if window_s is not None:
                meter.window(w, max(w.t0_us, source.first_us), min(w.t1_us, source.last_us + 1), raw.height)
        store.join()
    finally:
        store.close()
    return ctx, st, source


class _WindowStore:
    """A window's parts, carried state and manifest written to a run directory on a thread of
    their own while the next window computes (issue 18, speed: the windows kept 1.2 of the 2
    cores busy). One window in flight: :meth:`put` waits for the previous one first, so the
    manifest names a window complete only once its parts and state are on disk, in window
    order, as before. The state is pickled by the caller before the next window runs (a stage
    may reuse its state's arrays). Other part stores (in memory, the Dask engine's) are written
    at once."""

    def __init__(self, parts) -> None:
        self.parts = parts
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="window-store") if isinstance(parts, PartStore) else None
        self._pending: Future | None = None

    def put(self, w: Window, out: dict[str, pl.DataFrame], st: StreamState, **info: Any) -> None:
        if self._pool is None:
            self.parts.write(w, out)
            self.parts.checkpoint(w, st, **info)
            return
        state = PartStore.state_bytes(w, st)
        self.join()
        self._pending = self._pool.submit(self._store, w, out, state, info)

    def _store(self, w: Window, out: dict[str, pl.DataFrame], state: bytes, info: dict) -> None:
        self.parts.write(w, out)
        self.parts.commit(w, state, **info)

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
    from tertiary.runtime.windows import _utc
    return _utc(min(w.t1_us, (source.last_us or 0) + 1)) if source.windowable else "end"


def _windowable(cfg: PipelineConfig, source: ReportSource, window_s: float | None, notes: list[str]) -> float | None:
    """``window_s``, or None (one window) with a note when the run cannot be cut in time."""
    if window_s is None:
        return None
    why = ("the reports' time column is not a timestamp" if not source.windowable else
           "radar registration is estimated from the whole recording" if cfg.register else
           "the report collection queue is simulated over the whole recording" if cfg.collection is not None else
           "strict mode stops at the first invalid row of the whole input" if cfg.strict else None)
    if why:
        notes.append(f"processed as one window: {why}")
        return None
    return window_s


class _OnDisk:
    """A streamed table finalize leaves on disk once stored (issue 16, memory): evaluation reads
    it back one picture at a time, so the whole-run stages never hold every picture at once.
    The windows' parts are regrouped once by picture (one part in memory at a time), so reading
    a picture reads that picture only; the same pass takes what finalize needs of the whole
    table (height, pictures in order of appearance, confirmed pictures, target counts)."""

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
        if self._in_place(parts, name):
            return
        first, slim = None, []
        for w, part in enumerate(prefetched(parts.iter_parts(name))):   # one pass; the next part read meanwhile
            first = part.clear() if first is None else first
            slim.append(part.select(c for c in ("run", "method", "filter", "target_id", "tentative")
                                    if c in part.columns))
            if part.height == 0:
                continue
            for key, rows in part.partition_by(self.keys, as_dict=True, maintain_order=True).items():
                d = self.dir / str(self.index.setdefault(key, len(self.index)))
                d.mkdir(exist_ok=True)
                # a scratch copy read back once or twice: fast compression, not small files
                rows.write_parquet(d / f"w={w:06d}.parquet", compression="lz4")
        self.empty = empty if first is None else first
        self._facts(_concat_parts(slim) if slim else pl.DataFrame())

    _SLIM = ("run", "method", "filter", "target_id", "tentative")

    def _in_place(self, parts, name: str) -> bool:
        """Whether every part with rows holds one and the same picture (a run of one fusion
        method and one filter): the parts are then read where they are, without the regrouping
        copy (a national day's fused and tracks: ~14 GB of disk and a rewrite; issue 18)."""
        if not hasattr(parts, "part_files"):
            return False
        files, slim, keys = [], [], set()
        for f in parts.part_files(name):
            have = pl.read_parquet_schema(f)
            part = pl.read_parquet(f, columns=[c for c in self._SLIM if c in have])
            if part.height == 0:
                continue
            keys.update(part.select(self.keys).unique().rows())
            if len(keys) > 1:
                return False
            files.append(f)
            slim.append(part)
        if not files:
            return False
        self.direct = files
        self.index = {keys.pop(): 0}
        self.empty = pl.DataFrame(schema=pl.read_parquet_schema(files[0]))
        self._facts(_concat_parts(slim))
        return True

    def _facts(self, frame: pl.DataFrame) -> None:
        """What finalize needs of the whole table, from its (run, method, filter, target_id,
        tentative) columns."""
        self.height = frame.height
        self.pictures = list(self.index)                            # in order of appearance
        shown = frame.filter(~pl.col("tentative").fill_null(False)) if "tentative" in frame.columns else frame
        self.shown = shown.select(self.keys).unique(maintain_order=True).rows() if shown.height else []
        self.target_counts = _target_counts(frame) if self.name == "fused" else {}

    def picture(self, key: tuple, skip: Collection[str] = ()) -> pl.DataFrame:
        """One picture's rows, without the columns in ``skip``."""
        files, cols = self._files(key, skip)
        return (_concat_parts([pl.read_parquet(f, columns=cols) for f in files]) if files
                else self.empty.select(cols))

    def blocks(self, key: tuple, skip: Collection[str] = (), rows: int | None = None) -> Iterator[pl.DataFrame]:
        """One picture's rows (as :meth:`picture`) in blocks of whole windows, in time order, each
        of at least ``rows`` rows (default :data:`EVAL_BLOCK_ROWS`) but the last."""
        rows = EVAL_BLOCK_ROWS if rows is None else rows
        files, cols = self._files(key, skip)
        held, n = [], 0
        for f in files:
            held.append(pl.read_parquet(f, columns=cols))
            n += held[-1].height
            if n >= rows:
                yield _concat_parts(held)
                held, n = [], 0
        if held:
            yield _concat_parts(held)

    def _files(self, key: tuple, skip: Collection[str]) -> tuple[list[Path], list[str]]:
        """A picture's window files in window order, and the columns read (all but ``skip``)."""
        k = self.index.get(tuple(key))
        if k is not None and self.direct is not None:
            return self.direct, [c for c in self.empty.columns if c not in skip]
        files = [] if k is None else sorted((self.dir / str(k)).glob("w=*.parquet"))
        return files, [c for c in self.empty.columns if c not in skip]

    def collect(self) -> pl.DataFrame:
        got = self.parts.table(self.name)
        return self.empty if got is None else got


class _Deferred:
    """A whole-run table of an on-disk run read back (``read``) only where it is used, not held
    through the evaluation's peak: ``associations`` (``facts``: its number of targets, distinct
    (run, target_id)) and ``reports`` (issue 16, memory). Its height is taken now."""

    def __init__(self, read: Callable[[], pl.DataFrame], height: int,
                 blocks: Callable[[], Iterator[pl.DataFrame]] | None = None, **facts: int) -> None:
        #: ``blocks()``: the rows again, as frames of whole epochs in time order (each run's)
        self.read, self.height, self.blocks, self.facts = read, height, blocks, facts


def _whole(table: "pl.DataFrame | _OnDisk") -> pl.DataFrame:
    return table.collect() if isinstance(table, _OnDisk) else table


def _table(parts, name: str, empty: pl.DataFrame) -> pl.DataFrame:
    t = parts.table(name)
    return empty if t is None else t


#: what the whole-run stages read of ``reports`` and ``aligned`` (an on-disk run holds no more)
_REPORT_COLUMNS = ["run", "report_id", "radar_id", "time", "azimuth_deg", "truth_id", "mode_s"]
_ALIGNED_COLUMNS = ["run", "epoch", "report_id", "radar_id", "local_track_id"]
_ASSOCIATION_COLUMNS = ["run", "epoch", "target_id", "report_id"]
#: what the stages after the evaluation read of the truth (an on-disk run reads them from its
#: reference): the separation intervals (``truth_heights``) and the bound
_ALERT_TRUTH = ["run", "truth_id", "time", "x_m", "y_m", "z_m", "alt_m", "alt_rate_mps"]
_BOUND_TRUTH = ["run", "truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]


def _table_columns(parts, name: str, columns: list[str] | None, empty: pl.DataFrame) -> pl.DataFrame:
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


def _streamed(parts, name: str, empty: pl.DataFrame) -> "StreamedTable | pl.DataFrame":
    """``name`` for a sink: its parts one at a time, or ``empty`` when no window wrote any."""
    if next(iter(parts.iter_parts(name)), None) is None:
        return empty
    files = tuple(parts.part_files(name)) if hasattr(parts, "part_files") else ()
    return StreamedTable(lambda: parts.iter_parts(name), parts_files=files)


#: where a run's streamed tables go: copied into the database, or kept as Parquet files beside it
#: with views over them (:meth:`RunStore.register_parquet`)
TABLE_MODES = ("database", "parquet")


def check_tables(tables: str, out_dir: str | Path) -> None:
    """``--tables``: a known mode, and a run directory DuckDB's file search path can name."""
    if tables not in TABLE_MODES:
        raise OptionError(f"choose {' or '.join(TABLE_MODES)}, got {tables!r}", option="--tables")
    if tables == "parquet" and "," in str(Path(out_dir).resolve()):
        # the search path is a comma-separated list: the views could not find their files
        raise OptionError("the run directory's path must not contain a comma to register Parquet tables",
                          option="--tables")


def store_sink(store: RunStore, notes: list[str], tables: str = "database") -> Sink:
    """The sink that writes a run's tables to ``store``: a frame whole, a :class:`StreamedTable`
    part by part (:meth:`RunStore.write_parts`), or with ``tables="parquet"`` its window parts
    registered where they are (:meth:`RunStore.register_parquet`) when they are storable as
    they are."""
    check_tables(tables, store.path.parent)
    def storable(frame: pl.DataFrame, name: str) -> pl.DataFrame:
        said: list[str] = []
        out = _storable(frame, name, said)
        notes.extend(n for n in said if n not in notes)      # once per table, not once per window
        return out

    def sink(name: str, frame: "pl.DataFrame | StreamedTable") -> None:
        # the windows' parts, or files that are exactly the table (the truth's reference files)
        own = (frame.parts_files or frame.files) if isinstance(frame, StreamedTable) else ()
        if tables == "parquet" and own and _storable_as_is(own[0], name, frame.drop):
            store.register_parquet(name, own, frame.drop)
            return
        if isinstance(frame, StreamedTable):
            # the files as they are, when no column of theirs needs making storable
            if (frame.files and _storable_as_is(frame.files[0], name, frame.drop)
                    and store.write_files(name, frame.files, frame.drop)):
                return
            # the next window's part is read while this one is inserted
            store.write_parts(name, lambda: prefetched(storable(f, name) for f in frame.parts()))
        elif frame.width:
            store.write(name, storable(frame, name))
    return sink


def _finalize(ds: Dataset, cfg: PipelineConfig, ctx: RunContext, st: StreamState, parts, clock: _Clock,
              sink: Sink, notes: list[str], n_in: int, t_all: float) -> Results:
    """The whole-run stages on the streamed tables: truth validation, the one evaluation stage,
    alert scoring and STCA curves, the bound, capacity, requirements — and every table sunk."""
    clock.stage(None)
    clock.prefix = "finalize:"
    clock.stage("validate")      # the truth, and the whole run's accounting
    release_memory()             # what the windows freed, before the whole-run stages
    writer = _SinkThread(sink)
    try:
        return _finalize_tables(ds, cfg, ctx, st, parts, clock, writer, notes, n_in, t_all)
    finally:
        writer.close()


def _finalize_tables(ds: Dataset, cfg: PipelineConfig, ctx: RunContext, st: StreamState, parts, clock: _Clock,
                     sink: "_SinkThread", notes: list[str], n_in: int, t_all: float) -> Results:
    # an on-disk run keeps in memory only what the whole-run stages read, and its streamed tables
    # go to the database one window's part at a time (issue 16, memory)
    lean = hasattr(parts, "iter_parts")
    empty_reports = schema.empty_frame("reports", False)
    reports = (_table_columns(parts, "reports", _REPORT_COLUMNS, empty_reports) if lean
               else _table(parts, "reports", empty_reports))
    rejects = _table(parts, "rejects", _no_rejects()).sort("input_table", "row_index", nulls_last=True,
                                                           maintain_order=True)
    scratch = parts.scratch() if lean else None
    window = _truth_window(reports, cfg.limits)
    # an on-disk run validates the truth from disk to disk: the whole-run stages read it there
    streamed = _stream_truth(ds, cfg, notes, window, scratch) if lean else None
    on_disk = None
    if streamed is None:
        truth, rej_t = _validate_truth(ds, cfg, notes, window)
    else:
        on_disk, rej_t = streamed
        truth = on_disk.empty
    release_memory()             # the validation's scratch
    if rej_t.height:
        rejects = pl.concat([rejects, rej_t], how="vertical_relaxed")
    ing = Ingested(ctx.radars, reports, truth, rejects, notes)
    sink("radars", ing.radars)
    sink("reports", _streamed(parts, "reports", empty_reports) if lean else reports)
    sink("truth", StreamedTable(on_disk.pieces, tuple(reference_files(on_disk.reference)), NEIGHBOUR_COLUMNS)
         if on_disk is not None and on_disk.rows else truth)
    del truth                   # held by ``ing`` alone: the evaluation may release it
    sink("rejects", rejects)
    empty_aligned = align_stage.empty_aligned()
    aligned = (_table_columns(parts, "aligned", None if cfg.radar_health else _ALIGNED_COLUMNS, empty_aligned)
               if lean else _table(parts, "aligned", empty_aligned))
    if aligned.height == 0:
        top = (rejects.group_by("reason").len().sort("len", descending=True).head(3)
               if rejects.height else pl.DataFrame({"reason": [], "len": []}))
        why = "; ".join(f"{n:,} × {r}" for r, n in top.iter_rows())
        raise DataError(f"no valid report left: all {n_in:,} reports rejected"
                        + (f" (most common: {why})" if why else ""))
    _check_accounting(n_in, aligned, rejects)
    sink("aligned", _streamed(parts, "aligned", empty_aligned) if lean else aligned)
    release_memory()             # the scratch of the reports' and aligned rows' copies to the database
    observed, later = None, None
    if lean:
        # the evaluation and the alert scoring read neither the reports nor the aligned rows, only
        # which aircraft had a report at which epoch: both are read back after them (memory)
        observed = _observed(aligned, reports)
        cols = None if cfg.radar_health else _ALIGNED_COLUMNS
        aligned = _Deferred(lambda: _table_columns(parts, "aligned", cols, empty_aligned), aligned.height,
                            reports=aligned["report_id"].n_unique())
        later = _Deferred(lambda: _table_columns(parts, "reports", _REPORT_COLUMNS, empty_reports), reports.height)
        ing.reports = reports.clear()         # its schema until then: what the stages test for
        del reports
    tables = {}
    for name in ("associations", "fused", "clusters", "tracks", "conflicts"):
        empty = (schema.empty_frame(name, False) if name in ("tracks", "conflicts") else pl.DataFrame())
        if lean and name == "associations":
            # read back after the evaluation and the alert scoring, which do not read it: its
            # rows are not held through their peak (issue 16, memory)
            sink(name, _streamed(parts, name, empty))
            keys = _table_columns(parts, name, ["run", "target_id"], empty)
            # what the association metrics read (the rows are in the database)
            frame = _Deferred(lambda: _table_columns(parts, "associations", _ASSOCIATION_COLUMNS, pl.DataFrame()),
                              keys.height, blocks=lambda: _association_blocks(parts),
                              targets=keys.n_unique() if keys.height else 0)
            del keys
        elif not lean or name == "conflicts":
            frame = _table(parts, name, empty)
            sink(name, _streamed(parts, name, empty) if lean else frame)
        else:
            sink(name, _streamed(parts, name, empty))
            if name == "clusters":
                frame = _table_columns(parts, name, ["run", "method"], empty)
            else:
                # left on disk: evaluation and the STCA curves read one picture at a time
                frame = _OnDisk(parts, name, empty)
        tables[name] = frame
    associations, fused, clusters, tracks, conflicts = (tables[k] for k in ("associations", "fused", "clusters",
                                                                            "tracks", "conflicts"))
    stats = AssociationStats(pairs=st.counts.get("pairs", 0), components=st.counts.get("components", 0),
                             ambiguous_components=st.counts.get("ambiguous_components", 0),
                             targets=(associations.facts["targets"] if isinstance(associations, _Deferred) else
                                      associations.select("run", "target_id").n_unique() if associations.height
                                      else 0),
                             reassignments=st.counts.get("reassignments", 0))
    return _evaluate_run(ds, cfg, ing, aligned, associations, stats, fused, clusters, tracks, conflicts, clock,
                         sink, n_in, t_all, int(getattr(st.align, "conversion_invalid", 0)), observed, later,
                         scratch, on_disk, getattr(st, "scores", None))


class _SinkThread:
    """The finalize's tables handed to ``sink`` on a thread of their own, in the order they
    come, while the whole-run stages go on (issue 18, speed: a national hour's tables took
    47-66 s to copy into the run database, on the one core the evaluation also used). The
    streamed tables are read from their parts on disk and the frames given are never changed
    after, so the stages and the writes share nothing but the disk. A write's failure stops
    the later writes and is raised, as a failure of ``write_tables``, at the next table given
    or at :meth:`join`."""

    def __init__(self, sink: Sink) -> None:
        self.sink = sink
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="finalize-sink")
        self._pending: list[Future] = []
        self._error: BaseException | None = None
        #: seconds the writes took (beside the stages)
        self.busy_s = 0.0

    def __call__(self, name: str, frame: "pl.DataFrame | StreamedTable") -> None:
        self._raise()
        self._pending = [f for f in self._pending if not f.done()]
        self._pending.append(self._pool.submit(self._write, name, frame))

    def _write(self, name: str, frame: "pl.DataFrame | StreamedTable") -> None:
        if self._error is not None:
            return
        t = time.perf_counter()
        try:
            self.sink(name, frame)
        except BaseException as exc:  # raised in the stages' thread
            exc.add_note(f"while writing table {name!r} to the run database")
            self._error = exc
        finally:
            self.busy_s += time.perf_counter() - t

    def _raise(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            err.tertiary_stage = "write_tables"  # type: ignore[attr-defined]
            raise err

    def join(self, clock: _Clock) -> None:
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


def _evaluate_run(ds: Dataset, cfg: PipelineConfig, ing: Ingested, aligned: "pl.DataFrame | _Deferred",
                  associations: "pl.DataFrame | _Deferred",
                  stats: AssociationStats, fused: pl.DataFrame, clusters: pl.DataFrame, tracks: pl.DataFrame,
                  conflicts: pl.DataFrame, clock: _Clock, sink: Sink, n_in: int, t_all: float,
                  conversion_invalid: int = 0, observed: pl.DataFrame | None = None,
                  reports: "_Deferred | None" = None, scratch: Path | None = None,
                  on_disk: StreamedTruth | None = None, scores: "AssociationScore | None" = None) -> Results:
    """The whole-run stages after the tables are sunk. An on-disk run hands ``aligned`` and the
    ``reports`` (then ``ing.reports`` has no row) as :class:`_Deferred` and ``observed``
    (:func:`_observed`) computed before: both are read back after the evaluation's peak. With a
    ``scratch`` directory the evaluation reads the truth from reference files there, and the
    truth is not held through it; ``on_disk`` (:func:`_stream_truth`): the truth is already
    there. The stages after the evaluation then read the truth's columns they use from the
    reference, and ``ing.truth`` keeps no row (the whole truth when the indicators run)."""
    # imported here: `safety` builds on `tertiary` (schema), so a module-level import would be
    # circular when a program imports `safety` first
    from safety import AlertConfig, capacity_from_metrics, stca_tables_by_picture, tradeoff_metrics
    from safety.alerts import truth_intervals

    alerts = pl.DataFrame()
    truth_rows = on_disk.rows if on_disk is not None else ing.truth.height
    has_truth = bool(truth_rows) and "truth_id" in ing.reports.columns
    empty = Evaluation(pl.DataFrame(), pl.DataFrame(), pl.DataFrame(), pl.DataFrame())
    ev_fused, ev_tracks = empty, empty
    truth_file: Path | None = None
    if has_truth:
        clock.stage("evaluation")
        if observed is None:
            observed = _observed(aligned, ing.reports)
        reference: "pl.DataFrame | Path" = ing.truth
        if on_disk is not None:
            reference = on_disk.reference
        elif scratch is not None:
            reference = write_reference(ing.truth, scratch / "reference.parquet")
            ing.truth = ing.truth.clear()
        ev_fused, ev_tracks = _score_pictures(cfg, fused, tracks, observed, reference, ing, ds,
                                              None if scratch is None else scratch / "evaluation")
        del observed
        if scratch is not None:
            release_memory()
            if cfg.indicators:          # they match the picture again: the whole truth
                ing.truth = read_reference(reference)
            else:
                # the later stages each read the columns they use from the reference, and the
                # truth is not held between them (issue 18, memory)
                truth_file = reference
    elif on_disk is not None and on_disk.rows:
        ing.truth = read_reference(on_disk.reference)      # nothing scored against it: as it came

    def truth_columns(columns: list[str]) -> pl.DataFrame:
        return ing.truth if truth_file is None else read_reference(truth_file, columns)

    def truth_scan(columns: list[str]) -> "pl.DataFrame | pl.LazyFrame":
        """The truth's ``columns`` (those it has), as a scan of the reference when on disk."""
        if truth_file is None:
            return ing.truth
        lf = pl.scan_parquet(reference_files(truth_file))
        return lf.select(c for c in columns if c in lf.collect_schema())
    if cfg.safety and has_truth:
        clock.stage("score_alerts")
        methods, id_col = _safety_names(cfg, fused, tracks)
        # which aircraft each picture row represents: the one matcher's answer
        id_map = (ev_tracks if id_col == "track_id" else ev_fused).id_map
        if id_map.width == 0:           # nothing scored (e.g. every target tentative)
            id_map = pl.DataFrame(schema={"run": pl.UInt32, "method": pl.String, "epoch": schema.TIME,
                                          id_col: pl.UInt64, "truth_id": pl.Int64})
        acfg = AlertConfig(conflict=cfg.conflicts)
        _note_minima(cfg.conflicts, ing.notes)
        # the truth's LoS and proximity intervals, computed once for the alerts and every curve
        # setting (they depend on the separation minima, which the curves do not vary)
        if truth_file is not None:
            # an hour of truth at a time: a national day's truth held whole for them peaked at
            # ~16 GB (issue 18, memory)
            intervals, span = reference_intervals(truth_file, acfg, ds.origin)
        else:
            truth = truth_columns(_ALERT_TRUTH)
            intervals, span = truth_intervals(truth, acfg, ds.origin), _time_span(truth)
            del truth
        release_memory()
        # a picture at a time: the same tables, with one picture's rows in the scoring's joins
        safety_metrics, alerts, _los = stca_tables_by_picture(conflicts, id_map, span, acfg, id_col=id_col,
                                                               methods=methods, frame=ds.origin,
                                                               intervals=intervals)
        sink("alerts", alerts)
        if cfg.stca_lookaheads_s:
            clock.stage("stca_curves")
            curve = _stca_curves(cfg, fused, tracks, id_map, span, acfg, id_col, ds.origin, methods, intervals,
                                 None if scratch is None else scratch / "curves")
            safety_metrics = pl.concat([safety_metrics, tradeoff_metrics(curve)], how="vertical_relaxed")
    clock.stage("evaluate")
    release_memory()
    # the association metrics scored window by window when every row was (issue 16); else from
    # the rows read back
    carried = has_truth and scores is not None and scores.rows == associations.height
    blocks = associations.blocks if isinstance(associations, _Deferred) and has_truth and not carried else None
    if isinstance(associations, _Deferred):
        # on disk, in the database; scored from there a block at a time when not carried
        associations = pl.DataFrame() if carried or blocks is not None else associations.read()
    if reports is not None:
        ing.reports = reports.read()
    if blocks is not None:
        scores = _scored_blocks(blocks(), ing.reports)
    if carried or blocks is not None:
        metrics = _association_metrics(scores.runs.height if scores.rows else 0, stats, association_score(scores))
    else:
        report_truth = ing.reports.select("run", "report_id", "truth_id") if has_truth else None
        metrics = _association_metrics(int(associations["run"].n_unique()) if associations.height else 0, stats,
                                       association_metrics(associations, report_truth) if report_truth is not None
                                       else None)
    release_memory()
    by_epoch = pl.DataFrame(schema=BY_EPOCH_SCHEMA)
    if has_truth:
        metrics = pl.concat([metrics, *[e.metrics for e in (ev_fused, ev_tracks) if e.metrics.height]],
                            how="vertical_relaxed")
        by_epoch = ev_fused.by_epoch
        samples = [e.samples for e in (ev_fused, ev_tracks) if e.samples.height]
        scored = pl.concat(samples, how="vertical_relaxed") if samples else pl.DataFrame()
        # the posterior Cramér–Rao bound beside every picture's accuracy (tertiary.evaluation.bound)
        # read by blocks of aircraft from the reference, never whole (79 M rows on a national day)
        extra = [bound_stage(ds, truth_scan(_BOUND_TRUTH), ing.radars, ing.reports, scored, metrics, ing.notes)]
        if cfg.safety:
            extra.append(safety_metrics)
        metrics = pl.concat([metrics, *extra], how="vertical_relaxed")
        if cfg.safety:
            metrics = pl.concat([metrics, capacity_from_metrics(metrics, notes=ing.notes)], how="vertical_relaxed")
        if cfg.evaluation:
            reqs = [e.requirements for e in (ev_fused, ev_tracks) if e.requirements.height]
            if reqs:
                sink("requirements", pl.concat(reqs, how="vertical_relaxed"))
    aligned_rows, aligned_reports = ((aligned.height, aligned.facts["reports"]) if isinstance(aligned, _Deferred)
                                     else (aligned.height, aligned["report_id"].n_unique()))
    if cfg.radar_health and aligned.height:
        from tertiary.sensors.radar_health import radar_health
        if isinstance(aligned, _Deferred):
            aligned = aligned.read()
        metrics = pl.concat([metrics, radar_health(aligned, ing.radars)], how="vertical_relaxed")
    if has_truth and cfg.indicators and tracks.height:
        clock.stage("indicators")
        metrics = pl.concat([metrics, indicators(_whole(tracks), ing.truth)], how="vertical_relaxed")
    sink("metrics", metrics)
    sink("accuracy_by_epoch", by_epoch)
    clock.stage(None)
    if isinstance(sink, _SinkThread):
        sink.join(clock)
        # the writes' own time, beside the stages; the stages' wait for the last ones apart
        clock.timings["write_tables_wait_s"] = clock.timings.pop("write_tables_s", 0.0)
        clock.timings["write_tables_s"] = sink.busy_s
    clock.timings["alignment_to_clustering_s"] = sum(
        clock.timings.get(f"{k}_s", 0.0) for k in ("align", "associate", "fuse", "centralized", "cluster"))
    clock.timings["total_s"] = time.perf_counter() - t_all
    rejects = ing.rejects
    counts = {"reports_in": n_in, "reports_aligned": int(aligned_reports),
              "reports_rejected": int(rejects.filter(pl.col("input_table") == "reports").height),
              "aligned_rows": aligned_rows, "gated_pairs": stats.pairs, "components": stats.components,
              "ambiguous_components": stats.ambiguous_components, "targets": stats.targets,
              "reassignments": stats.reassignments, "fused_rows": fused.height, "clusters": clusters.height,
              "conversion_invalid": conversion_invalid,
              "track_rows": tracks.height, "conflict_rows": conflicts.height,
              "alert_rows": int(conflicts["alert"].sum()) if conflicts.height else 0,
              "alert_episodes": alerts.height,
              "aircraft": truth_columns(["truth_id"])["truth_id"].n_unique() if has_truth else 0,
              **_target_counts(fused)}
    # an on-disk run's fused and tracks are in its database only (empty frames here), and so are
    # its aligned rows when they were not read back
    fused, tracks = (t.empty if isinstance(t, _OnDisk) else t for t in (fused, tracks))
    if isinstance(aligned, _Deferred):
        aligned = align_stage.empty_aligned()
    return Results(ing, aligned, associations, fused, clusters, tracks, conflicts, rejects, metrics, by_epoch,
                   clock.timings, counts, alerts, dict(clock.memory))


#: the time chunk in which :func:`reference_intervals` reads an on-disk truth (s)
TRUTH_CHUNK_S = 3600.0


def _time_span(truth: "pl.DataFrame | pl.LazyFrame") -> pl.DataFrame:
    """What the alert scoring reads of the truth besides its intervals: each run's first and
    last sample time (``run`` and ``time``; no ``run`` column without one)."""
    keys = ["run"] if "run" in truth.collect_schema() else []
    ends = [truth.group_by(keys).agg(f(pl.col("time"))) if keys else truth.select(f(pl.col("time")))
            for f in (pl.Expr.min, pl.Expr.max)]
    out = pl.concat([e.collect() if isinstance(e, pl.LazyFrame) else e for e in ends])
    return out.sort(*keys, "time") if keys else out.sort("time")


def _per_run(lf: pl.LazyFrame, agg: pl.Expr) -> pl.LazyFrame:
    return lf.group_by("run").agg(agg) if "run" in lf.collect_schema() else lf.select(agg)


def reference_intervals(reference: Path, acfg, frame: geo.LocalFrame, chunk_s: float = TRUTH_CHUNK_S
                        ) -> tuple[tuple[pl.DataFrame, pl.DataFrame], pl.DataFrame]:
    """(the truth's (LoS, proximity) intervals, its :func:`_time_span`) from a reference on disk
    (:func:`tertiary.evaluation.evaluate.write_reference`), ``chunk_s`` of truth at a time, merged by
    :func:`safety.alerts.merge_intervals`: the whole truth's. A chunk [a, b) reads every sample
    from the last sample time before a to the first after b, and each aircraft's neighbours of
    those: inside, the union sample grid and so the segment pairs are the whole truth's, and
    each chunk keeps the part of its intervals in [a, b)."""
    from safety.alerts import merge_intervals, truth_intervals
    lf = pl.scan_parquet(reference_files(reference))
    span = _time_span(lf)
    cols = [c for c in _ALERT_TRUTH if c in lf.collect_schema()]
    t = pl.col("time")
    lo, hi = (int(span["time"].dt.epoch("us").min()), int(span["time"].dt.epoch("us").max()) + 1)
    step = max(int(chunk_s * US), 1)
    chunks = []
    for a in range(lo, hi, step):
        b = min(a + step, hi)
        ta, tb = (pl.lit(v, pl.Int64).cast(pl.Datetime("us", "UTC")) for v in (a, b))
        # per run (each has its own sample grid): the earliest of the runs' last times before a,
        # the latest of their first times from b
        p = _per_run(lf.filter(t < ta), t.max()).select(t.min()).collect().item()
        q = _per_run(lf.filter(t >= tb), t.min()).select(t.max()).collect().item()
        near = pl.lit(True)
        if p is not None:
            near = near & ((t >= p) | (pl.col("__next") >= p))
        if q is not None:
            near = near & ((t <= q) | (pl.col("__prev") <= q))
        truth = lf.filter(near).select(cols).collect()
        chunks.append(truth_intervals(truth, acfg, frame, clip_us=(a, b)))
        del truth
    return merge_intervals(chunks, acfg), span


def _note_minima(cc: "ConflictConfig", notes: list[str]) -> None:
    """A note of the separation minima of the alerts and their scoring when they are not one
    set everywhere (an en-route floor, aerodrome zones): the reader of an alert list must know
    its rule."""
    if cc.aerodrome_zones:
        from safety.conflicts import FT_M, NM_M
        radii = sorted({z.radius_m for z in cc.aerodrome_zones})
        ceilings = sorted({z.ceiling_m for z in cc.aerodrome_zones})
        text = (f"aerodrome zones: no STCA alert and no loss of separation scored between two aircraft both "
                f"within {'/'.join(f'{r / NM_M:g}' for r in radii)} NM and below "
                f"{'/'.join(f'{c / FT_M:,.0f}' for c in ceilings)} ft of one of {len(cc.aerodrome_zones)} "
                "aerodromes (aerodrome control, not radar separation)")
        if text not in notes:
            notes.append(text)
    if cc.enroute_above_m is None:
        return
    from safety.conflicts import FT_M, NM_M
    text = (f"separation minima: {cc.sep_h_m / NM_M:g} NM / {cc.sep_v_m / FT_M:,.0f} ft for pairs both below "
            f"{cc.enroute_above_m / FT_M:,.0f} ft (terminal), {cc.enroute_h_m / NM_M:g} NM / "
            f"{cc.enroute_v_m / FT_M:,.0f} ft otherwise (en-route) — in the alerts and in the losses of "
            "separation they are scored on")
    if text not in notes:
        notes.append(text)


def track_identity(tracks: pl.DataFrame, fused: pl.DataFrame) -> pl.DataFrame:
    """``tracks`` with ``mode_s``: the Mode S address of the fused target each track was last
    updated with (carried while it coasts), so that a controller's picture has an identity —
    what identity correctness is scored on and what tells a duplicate track of one aircraft
    from a second aircraft — and likewise ``selected_alt_m`` (the target's Mode S selected
    altitude, latest known), ``ehs_track_rate_dps`` (its BDS 5,0 track-angle rate, latest
    known: conflict prediction follows a turn with it) and ``cleared_alt_m`` (its cleared level
    from flight data, latest known) when ``fused`` carries them."""
    if tracks.height == 0 or "mode_s" not in fused.columns or "plot_target_id" not in tracks.columns:
        return tracks
    cols = ["mode_s", *(c for c in _CARRIED if c in fused.columns)]
    ident = fused.select("run", "epoch", "method", pl.col("target_id").alias("plot_target_id"), *cols)
    keys = ["run", "filter", "method", "track_id"]
    return (tracks.drop(*cols, strict=False)
            .join(ident, on=["run", "epoch", "method", "plot_target_id"], how="left", maintain_order="left")
            .with_columns(pl.col(c).forward_fill().over(keys, order_by="epoch") for c in cols))


#: aligned rows joined to their reports' aircraft at a time (:func:`_observed`)
OBSERVED_BLOCK_ROWS = 262_144


def _report_truth(truth_of: pl.DataFrame) -> Callable[[pl.DataFrame], pl.Series] | None:
    """A lookup of the ``truth_id`` of each (run, report_id) of a frame in ``truth_of`` (one row
    per report; null where absent), through a table indexed by run × (largest report_id + 1) +
    report_id; None when the ids are too sparse for it (the table would be over four times the
    reports). A join of each block of aligned rows with every report rebuilt its hash table a
    block at a time: 6.4 s a block, 255 blocks on a national day's 34.5 M reports (issue 18)."""
    if truth_of.height == 0 or truth_of["run"].null_count() or truth_of["report_id"].null_count():
        return None
    top, runs = int(truth_of["report_id"].max()) + 1, int(truth_of["run"].max()) + 1
    if top * runs > 4 * truth_of.height + (1 << 20):
        return None
    key = truth_of["run"].cast(pl.UInt64).to_numpy() * top + truth_of["report_id"].cast(pl.UInt64).to_numpy()
    tid = truth_of["truth_id"]
    known = tid.is_not_null().to_numpy()
    table, have = np.zeros(top * runs, np.int64), np.zeros(top * runs, np.bool_)
    table[key[known]] = tid.fill_null(0).cast(pl.Int64).to_numpy()[known]
    have[key[known]] = True

    def lookup(frame: pl.DataFrame) -> pl.Series:
        run, rid = (frame[c].cast(pl.UInt64).fill_null(np.iinfo(np.uint64).max).to_numpy()
                    for c in ("run", "report_id"))
        inside = (run < runs) & (rid < top)
        k = np.where(inside, run * top + np.where(inside, rid, 0), 0)
        found = pl.Series(inside & have[k])
        return pl.select(pl.when(found).then(pl.Series(table[k])).cast(tid.dtype).alias("truth_id")).to_series()
    return lookup


#: association rows scored at a time when read back (:func:`_scored_blocks`)
ASSOCIATION_BLOCK_ROWS = 2_000_000


def _association_blocks(parts) -> Iterator[pl.DataFrame]:
    """The association rows of ``parts``' windows (what the metrics read), in window order."""
    for f in parts.iter_parts("associations"):
        yield f.select(c for c in _ASSOCIATION_COLUMNS if c in f.columns)


def _scored_blocks(blocks: Iterable[pl.DataFrame], reports: pl.DataFrame) -> AssociationScore:
    """:class:`AssociationScore` of association rows given as frames of whole epochs in time order
    (each run's), gathered to about :data:`ASSOCIATION_BLOCK_ROWS` rows and each scored with its
    reports' aircraft (:func:`_report_truth`): a run's rows read back are never held, nor joined,
    whole. Whole at once, a national day's 66.9 M rows with the 34.5 M reports took the Dask
    client to 22 623 MiB and 718 s (issue 18); a step per block is what the local engine does
    per window, so the metrics are the same."""
    truth_of = reports.select("run", "report_id", "truth_id")
    look = _report_truth(truth_of)
    state = AssociationScore()

    def step(frames: list[pl.DataFrame]) -> None:
        nonlocal state
        block = pl.concat(frames, how="vertical_relaxed")
        label = (block.select("run", "report_id").with_columns(look(block)) if look is not None
                 else truth_of)
        state = score_associations(state, block, label)
    pending, rows = [], 0
    for frame in blocks:
        if frame.height:
            pending.append(frame)
            rows += frame.height
        if rows >= ASSOCIATION_BLOCK_ROWS:
            step(pending)
            pending, rows = [], 0
    if pending:
        step(pending)
    return state


def _observed(aligned: pl.DataFrame, reports: pl.DataFrame) -> pl.DataFrame:
    """(run, epoch, truth_id) of every aircraft with a report aligned at the epoch: what
    continuity expects covered. Joined a block of aligned rows at a time: a long run's join is
    not held whole (memory, issue 16)."""
    truth_of = reports.select("run", "report_id", "truth_id")
    keys = aligned.select("run", "epoch", "report_id")
    look = _report_truth(truth_of)

    def aircraft(block: pl.DataFrame) -> pl.DataFrame:
        if look is not None:
            return block.with_columns(look(block))
        return block.join(truth_of, on=["run", "report_id"], how="left")
    blocks = [aircraft(keys.slice(k, OBSERVED_BLOCK_ROWS)).select("run", "epoch", "truth_id").drop_nulls().unique()
              for k in range(0, keys.height, OBSERVED_BLOCK_ROWS)]
    if not blocks:
        none = pl.lit(None, truth_of.schema["truth_id"]).alias("truth_id")
        return keys.select("run", "epoch").with_columns(none).clear()
    return pl.concat(blocks).unique()


def _score_pictures(cfg: PipelineConfig, fused: "pl.DataFrame | _OnDisk", tracks: "pl.DataFrame | _OnDisk",
                    observed: pl.DataFrame, reference: "pl.DataFrame | Path", ing: Ingested, ds: Dataset,
                    spill: Path | None = None) -> tuple[Evaluation, Evaluation]:
    """Every picture scored by the one evaluation stage against the truth: each fusion method's
    confirmed targets and the centralised reference (seed stage "fusion", id ``target_id``),
    each tracker picture "<fusion>+<filter>" (seed stage "tracker"). Continuity expects every
    aircraft covered at the epochs it had a report (``observed``). Pictures are read one at a
    time; ``reference``: the truth, or its reference file (:func:`write_reference`); ``spill``: a
    scratch directory where a picture of several blocks is matched to disk and scored in
    buckets (:func:`tertiary.evaluation.evaluate.evaluate_each`)."""
    from tertiary.evaluation.requirements import example_path, load_requirements
    reqs = load_requirements(cfg.requirements_file or example_path()) if cfg.evaluation else None
    kw = dict(radars=ing.radars, frame=ds.origin, requirements=reqs, cfg=cfg.scoring, observed=observed,
              keep_matched=False, surveillance=cfg.evaluation, spill=spill)
    none = Evaluation(pl.DataFrame(), pl.DataFrame(), pl.DataFrame(), pl.DataFrame())
    # the id map of the safety picture only: the alert scoring reads no other (memory)
    safety_ids = _safety_names(cfg, fused, tracks)[1] if cfg.safety else None
    fused_pictures = list(_fused_pictures(fused, _NOT_SCORED, blocks=True))
    # the heap the last picture freed is handed back before the next is read (memory)
    ev_fused = (evaluate_each((_released(get) for get in fused_pictures), reference, id_col="target_id",
                              seed_stage="fusion", id_map=safety_ids == "target_id", **kw)
                if fused_pictures else none)
    track_pictures = list(_track_pictures(tracks, _NOT_SCORED, blocks=True))
    if not track_pictures:
        return ev_fused, none
    return ev_fused, evaluate_each((_released(get) for get in track_pictures), reference, seed_stage="tracker",
                                   id_map=safety_ids == "track_id", **kw)


def _released(get: Callable[[], Any]) -> Any:
    """``get()`` after the heap's freed pages are handed back."""
    release_memory()
    return get()


def _shown(fused: pl.DataFrame) -> pl.DataFrame:
    """Confirmed targets only: clutter-only (tentative) targets are never scored or screened."""
    return fused.filter(~pl.col("tentative").fill_null(False)) if "tentative" in fused.columns else fused


#: rows of an on-disk picture matched and row-scored at a time (whole windows): the evaluation's
#: scratch and a picture's covariances are held a block at a time (issue 16, memory)
EVAL_BLOCK_ROWS = 200_000

#: what no evaluation metric (nor conflict prediction) reads of a picture (the fusion's inputs
#: and the tracker's diagnostics): an on-disk picture is scored without them (issue 16, memory)
_NOT_SCORED = ("meas_cov", "weights", "radar_ids", "innovation", "model_probs", "meas_x_m", "meas_y_m",
               "meas_z_m", "n_fresh", "age_s")


def _fused_pictures(fused: "pl.DataFrame | _OnDisk", skip: Collection[str] = (), blocks: bool = False
                    ) -> Iterator[Callable[[], "pl.DataFrame | Iterator[pl.DataFrame]"]]:
    """A reader per fused picture (its confirmed targets), in order of appearance; an on-disk
    picture is read without the columns in ``skip``, and with ``blocks`` as time blocks
    (:meth:`_OnDisk.blocks`)."""
    if isinstance(fused, _OnDisk):
        for key in fused.shown:
            if blocks:
                yield lambda key=key: (_shown(b) for b in fused.blocks(key, skip))
            else:
                yield lambda key=key: _shown(fused.picture(key, skip))
        return
    shown = _shown(fused)
    for part in (shown.partition_by("method", maintain_order=True) if shown.height else []):
        yield lambda part=part: part


def _as_picture(tracks: pl.DataFrame) -> pl.DataFrame:
    """A tracker picture named "<fusion method>+<filter>" in ``method``."""
    return tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method")).drop("filter")


def _track_pictures(tracks: "pl.DataFrame | _OnDisk", skip: Collection[str] = (), blocks: bool = False
                    ) -> Iterator[Callable[[], "pl.DataFrame | Iterator[pl.DataFrame]"]]:
    """A reader per tracker picture, in order of appearance (``skip``, ``blocks``: as for fused)."""
    if isinstance(tracks, _OnDisk):
        for key in tracks.pictures:
            if blocks:
                yield lambda key=key: (_as_picture(b) for b in tracks.blocks(key, skip))
            else:
                yield lambda key=key: _as_picture(tracks.picture(key, skip))
        return
    if tracks.height:
        for part in _as_picture(tracks).partition_by("method", maintain_order=True):
            yield lambda part=part: part


def _safety_picture(cfg: PipelineConfig, fused: "pl.DataFrame | _OnDisk", tracks: "pl.DataFrame | _OnDisk",
                    notes: list[str]) -> tuple[pl.DataFrame, str]:
    """The picture conflict prediction runs on, with its id column; every picture is named in
    ``method`` ("<fusion method>+<filter>" for tracks), so every alert names where it came from."""
    if cfg.safety_picture == "tracks":
        # decided by the configuration, never by the rows: a window without tracks must not
        # switch a run's picture (windowed engine)
        if cfg.filters and cfg.methods:
            # tentative tracks are never emitted by the tracker: every row is a confirmed track
            return _whole(tracks).with_columns(pl.format("{}+{}", "method", "filter").alias("method")), "track_id"
        text = "conflict prediction ran on the fused pictures: no tracker filter was configured"
        if text not in notes:
            notes.append(text)
    return _shown(_whole(fused)), "target_id"      # clutter-only targets never reach safety


#: rows of an on-disk picture the STCA curves read at a time (whole windows)
CURVE_BLOCK_ROWS = 200_000


def _stca_curves(cfg: PipelineConfig, fused: "pl.DataFrame | _OnDisk", tracks: "pl.DataFrame | _OnDisk",
                 id_map: pl.DataFrame, truth: pl.DataFrame, acfg, id_col: str, frame: geo.LocalFrame,
                 methods: list[str], intervals: tuple[pl.DataFrame, pl.DataFrame],
                 spill: Path | None = None) -> pl.DataFrame:
    """The STCA trade-off curves of the safety picture: in one call when it is in memory, a
    picture at a time (read from disk) when the run is on disk — each picture's curve depends
    on that picture alone. ``intervals``: :func:`safety.alerts.truth_intervals` of ``truth``;
    ``spill``: scratch for each setting's predicted rows (:func:`safety.stca_tradeoff`)."""
    from safety import stca_tradeoff
    kw = dict(id_col=id_col, frame=frame, lookaheads_s=cfg.stca_lookaheads_s, confidences=cfg.stca_confidences,
              fixed_est_h_m=cfg.stca_fixed_m, intervals=intervals, spill=spill)
    on_disk = tracks if id_col == "track_id" else fused
    if not isinstance(on_disk, _OnDisk) or not (on_disk.pictures if id_col == "track_id" else on_disk.shown):
        picture, _ = _safety_picture(cfg, fused, tracks, [])
        return stca_tradeoff(picture, id_map, truth, acfg, methods=methods, **kw)
    curves = []
    # read without the columns conflict prediction does not read either, in time blocks: a
    # national day's tracker picture whole, with its covariances, was ~10 GB (memory, issue 18)
    keys = on_disk.pictures if id_col == "track_id" else on_disk.shown
    show = _as_picture if id_col == "track_id" else _shown
    for key in keys:
        name = "+".join(key)
        blocks = (show(b) for b in on_disk.blocks(key, _NOT_SCORED, rows=CURVE_BLOCK_ROWS))
        curves.append(stca_tradeoff(blocks, id_map.filter(pl.col("method") == name), truth, acfg, methods=[name],
                                    **kw))
        release_memory()
    curve = pl.concat(curves, how="vertical_relaxed")
    return curve.sort("method", "t_thr_s", "warning_s", "threshold_mode", "parameter")


def _safety_names(cfg: PipelineConfig, fused: "pl.DataFrame | _OnDisk", tracks: "pl.DataFrame | _OnDisk"
                  ) -> tuple[list[str], str]:
    """The sorted picture names of :func:`_safety_picture`'s picture and its id column, without
    reading the picture."""
    if cfg.safety_picture == "tracks" and cfg.filters and cfg.methods:
        if isinstance(tracks, _OnDisk):
            return sorted({f"{m}+{f}" for m, f in tracks.pictures}), "track_id"
        return sorted(_as_picture(tracks)["method"].unique().to_list()), "track_id"
    if isinstance(fused, _OnDisk):
        return sorted({m for (m,) in fused.shown}), "target_id"
    return sorted(_shown(fused)["method"].unique().to_list()), "target_id"


def _target_counts(fused: "pl.DataFrame | _OnDisk") -> dict[str, int]:
    """System targets (run, target_id) that were ever confirmed, and those only ever tentative."""
    if isinstance(fused, _OnDisk):
        return fused.target_counts
    if "tentative" not in fused.columns or fused.height == 0:
        return {"confirmed_targets": 0, "tentative_targets": 0}
    ever = (fused.filter(pl.col("tentative").is_not_null()).group_by("run", "target_id")
            .agg(pl.col("tentative").all().alias("t")))
    n_tent = int(ever["t"].sum())
    return {"confirmed_targets": ever.height - n_tent, "tentative_targets": n_tent}


def _stage_rejects(stage_rejects: pl.DataFrame, reports: pl.DataFrame, report_rows: pl.DataFrame,
                   stage: str) -> pl.DataFrame:
    """A stage's (report_id, reason) rejects in the canonical ``rejects`` schema; ``row_index``
    is the report's row in the input table (``report_rows``), the detail its validated row."""
    if stage_rejects.height == 0:
        return schema.empty_frame("rejects", False)
    rows = (reports.join(report_rows, on="report_id", how="inner")
            .join(stage_rejects, on="report_id", how="inner").sort("row_index"))
    return schema.rejects_table(rows, "reports", stage)


def _check_accounting(n_in: int, aligned: pl.DataFrame, rejects: pl.DataFrame) -> None:
    n_ok = aligned["report_id"].n_unique()
    n_rej = rejects.filter(pl.col("input_table") == "reports").height
    if n_ok + n_rej != n_in:
        raise RuntimeError(f"row accounting broken: {n_in} reports in, {n_ok} aligned + {n_rej} rejected")


def _association_metrics(n_runs: int, stats, scored: pl.DataFrame | None) -> pl.DataFrame:
    """The association stage's counts over ``n_runs`` runs, after its correctness rows
    (``scored``: :func:`tertiary.evaluation.evaluate.association_metrics`) when the run has truth labels."""
    counts = pl.DataFrame({
        "stage": "association", "method": "assignment",
        "metric": ["gated_pairs", "ambiguous_components", "targets", "reassignments"],
        "segment": "all", "value": [float(stats.pairs), float(stats.ambiguous_components), float(stats.targets),
                                    float(stats.reassignments)],
        "n_runs": n_runs,
    }).with_columns(pl.col("n_runs").cast(pl.UInt32))
    if scored is None:
        return counts
    return pl.concat([scored, counts], how="vertical_relaxed")


def _storable_as_is(file: Path, name: str, drop: Collection[str] = ()) -> bool:
    """Whether :func:`_storable` leaves the columns of Parquet ``file`` (but ``drop``) as is."""
    probe = pl.DataFrame(schema=pl.read_parquet_schema(file)).drop(drop, strict=False)
    return _storable(probe, name, []).schema == probe.schema


def _storable(frame: pl.DataFrame, name: str, notes: list[str]) -> pl.DataFrame:
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
        elif schema._has(dtype, (pl.Object, pl.Duration)) or dtype in (pl.Int128, pl.UInt128):
            drop.append(col)
    if drop:
        notes.append(f"{name}: column(s) {', '.join(drop)} not stored (Object/nested Duration values)")
    return frame.with_columns(fix).drop(drop)


def _scenario_text(ds: Dataset, notes: list[str]) -> str:
    try:
        return scenario_toml(ds.scenario)
    except (ValueError, TypeError) as exc:
        notes.append(f"scenario.toml not recorded: {exc}")
        return ""


def _run_window(window_s: float | str | None, ds: Dataset, cfg: PipelineConfig) -> float | None:
    """:func:`tertiary.runtime.windows.resolve_window`; an input whose reports cannot even be scanned gets
    the default window, and the run itself then reports what is wrong with them (in the run
    record and the rejects, not as an error before the run directory exists)."""
    if not is_auto(window_s):
        return check_window(window_s)
    try:
        return resolve_window(window_s, ds.reports, cfg.limits, len(cfg.methods))
    except (pl.exceptions.PolarsError, OSError, ValueError, TypeError):  # fails again in validate, recorded there
        return DEFAULT_WINDOW_S


def run(ds: Dataset, out_dir: str | Path, cfg: PipelineConfig | None = None, *,
        progress: Progress | None = None, window_s: float | str | None = AUTO_WINDOW, resume: bool = False,
        dataset_label: str = "", tables: str = "database") -> Path:
    """Run the job on a dataset in windows of ``window_s`` seconds (``"auto"``: sized by the
    recording's report rate, :func:`tertiary.runtime.windows.auto_window_s`; None: one window) and write
    ``out_dir/results.duckdb`` atomically.

    Each window's streamed tables are written to ``out_dir/parts`` as it completes, with the
    carried state and a manifest (:mod:`tertiary.runtime.windows`); ``resume`` continues a killed run from
    its last complete window (same configuration, window and dataset, else :class:`OptionError`).
    The database is built at the end and the manifest marked complete; ``tables="parquet"``
    keeps the streamed tables' window parts as Parquet in ``out_dir/tables`` with views over
    them in the database instead of copying them in (:meth:`RunStore.register_parquet`). If a
    stage fails (including "no valid report left"), the database still holds every completed
    window's tables, the rejects and a run record with ``failed_stage`` and ``error``; then a
    :class:`TertiaryError` is raised (the original one, or :class:`StageError` wrapping an
    unexpected exception).
    """
    t_wall = time.perf_counter()
    cfg = adapt_to_scenario(check_config(cfg), ds)
    check_tables(tables, out_dir)
    # before anything reads the input (process: again, a no-op)
    warm_kernels(kernels_for(cfg.filters, bound=_truth_lazy(ds) is not None))
    window_s = _run_window(window_s, ds, cfg)
    say = progress or (lambda _m: None)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create the run directory: {exc.strerror or exc}", path=str(out)) from exc
    notes: list[str] = []
    failure: Exception | None = None
    res: Results | None = None
    header = {"dataset": dataset_label or ds.scenario.name, "window_s": window_s,
              "config_hash": config_hash(cfg, window_s, _input_identity(ds, dataset_label))}
    state, start = None, 0
    if resume:
        parts, state = PartStore.resume(out, header)
        start = int(parts.manifest["windows_done"])
        say(f"resuming after window {start} ({parts.manifest.get('time_done', '?')})")
    else:
        parts = PartStore.start(out, header)
        shutil.rmtree(out / TABLES_DIR, ignore_errors=True)     # a replaced run's registered tables
    with RunStore.create(out) as store:
        sink = store_sink(store, notes, tables)
        try:
            res = process(ds, cfg, say, sink=sink, notes=notes, window_s=window_s, parts=parts,
                          resume_state=state, start=start)
        except Exception as exc:  # recorded, then re-raised below
            failure = exc
        say("store")
        t = time.perf_counter()
        if isinstance(ds.removed, pl.DataFrame) and ds.removed.height:
            store.write("truth_removed", _storable(ds.removed, "truth_removed", notes))
        info = {
            "scenario": ds.scenario.name,
            "scenario_toml": _scenario_text(ds, notes),
            "config": _config_dict(cfg),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": _versions(),
            "fingerprints": {k: _fingerprint_any(getattr(ds, k)) for k in ("radars", "reports", "truth")},
            "window_s": window_s,
            "tables": tables,
        }
        if res is not None:
            res.timings["store_s"] = time.perf_counter() - t
            # the run's one wall time: validate → store, measured once; the CLI summary and the
            # report header both show this figure
            res.timings["wall_s"] = time.perf_counter() - t_wall
            info.update(rows=res.counts, notes=notes, timings=res.timings, memory_mib=res.memory_mib,
                        status="completed")
        else:
            stage = getattr(failure, "tertiary_stage", "validate")
            info.update(status="failed", failed_stage=stage, error=f"{type(failure).__name__}: {failure}",
                        notes=notes)
        record_run(store, info)
    parts.finish("complete" if failure is None else "failed")
    if failure is not None:
        db = out / "results.duckdb"
        if isinstance(failure, TertiaryError):
            failure.add_note(f"the completed stages, the rejects and a run record are in {db}")
            raise failure
        raise StageError(getattr(failure, "tertiary_stage", "validate"), failure, db) from failure
    return out / "results.duckdb"


def _input_identity(ds: Dataset, label: str) -> str:
    """What a resumed run must be given again: the dataset's name and its reports' size and span."""
    try:
        lf = ds.reports.lazy() if isinstance(ds.reports, (pl.DataFrame, pl.LazyFrame)) else None
        span = (lf.select(pl.len(), pl.col("time").cast(pl.String).min(), pl.col("time").cast(pl.String).max())
                .collect().row(0) if lf is not None else ())
    except Exception:  # an unreadable time column: the size alone
        span = ()
    return f"{label or ds.scenario.name}|{span}"


def _fingerprint_any(frame) -> str:
    try:
        if isinstance(frame, pl.LazyFrame):   # hashed without holding the table
            h = frame.select(pl.struct(pl.all()).hash(seed=0)).collect().to_series()
            return hashlib.sha256(h.to_numpy().tobytes()).hexdigest()[:16]
        return fingerprint(schema.as_frame(frame, "table"))
    except Exception:  # an unhashable column type: the record says so instead of failing
        return "unavailable"


def _config_dict(cfg: PipelineConfig) -> dict:
    def conv(v):
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v
    return conv(cfg)


def _versions() -> dict[str, str]:
    from importlib import metadata
    names = ["tertiary", "polars", "numpy", "scipy", "duckdb", "filterpy", "scikit-learn", "plotly", "pymap3d"]
    out = {"python": platform.python_version()}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            out[n] = "not installed"
    return out
