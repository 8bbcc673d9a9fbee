"""The whole-run safety scoring: the alert episodes of every safety picture and of the truth
picture scored against the truth's separation intervals, each picture's alerts attributed, the
external alert list beside them, and the STCA trade-off curves (:func:`score_safety`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polars as pl

from safety import alerts as safety_alerts
from tertiary import contract
from tertiary.evaluation.evaluate import read_reference, reference_files
from tertiary.io.dataset import Dataset
from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.ingestion import Ingested
from tertiary.pipeline.pictures import safety_names
from tertiary.pipeline.stca_scoring import note_minima, reference_intervals, stca_curves, time_span
from tertiary.pipeline.tables import ALERT_TRUTH, DeferredTable
from tertiary.pipeline.truth_alerts import (TRUTH_PICTURE_COLUMNS, attributed, reference_slice, truth_conflicts,
                                            truth_picture_finish)
from tertiary.runtime.fanout import Fanout, serial
from tertiary.runtime.windows import release_memory

__all__ = ["EXTERNAL_TRUTH", "SafetyTables", "TruthSource", "empty_id_map", "score_safety"]

# `safety` is imported as modules, not names, for the reason whole_run.py gives

#: what the scoring of an external alert list reads of the truth besides its intervals
EXTERNAL_TRUTH = ["run", "truth_id", "time", "icao24", "callsign", "mode_3a", "squawk"]


@dataclass(frozen=True)
class TruthSource:
    """The truth as the stages after the evaluation read it: ``ing.truth`` when ``file`` is None,
    else the columns each stage uses, read from the reference ``file`` and not held between
    stages (memory)."""

    ing: Ingested
    file: Path | None

    def columns(self, columns: list[str]) -> pl.DataFrame:
        """The truth's ``columns`` (all of them when held)."""
        return self.ing.truth if self.file is None else read_reference(self.file, columns)

    def between(self, t0_us: int, t1_us: int) -> pl.DataFrame:
        """The truth picture's columns of the samples in [t0_us, t1_us] (as the windows read them)."""
        if self.file is not None:
            return reference_slice(reference_files(self.file))(t0_us, t1_us)
        t = pl.col("time").dt.epoch("us")
        return self.scan(TRUTH_PICTURE_COLUMNS).lazy().filter(t.is_between(t0_us, t1_us)).collect()

    def scan(self, columns: list[str]) -> "pl.DataFrame | pl.LazyFrame":
        """The truth's ``columns`` (those it has), as a scan of the reference when on disk."""
        if self.file is None:
            return self.ing.truth
        lf = pl.scan_parquet(reference_files(self.file))
        return lf.select(c for c in columns if c in lf.collect_schema())


@dataclass
class SafetyTables:
    """What the safety scoring gives: its metrics, the alert episodes and the losses of separation,
    and the notes it wrote."""

    metrics: pl.DataFrame
    alerts: pl.DataFrame
    losses: pl.DataFrame
    notes: list[str] = field(default_factory=list)


def empty_id_map(id_col: str) -> pl.DataFrame:
    """An id map without rows (nothing scored, e.g. every target tentative)."""
    return pl.DataFrame(schema={"run": pl.UInt32, "method": pl.String, "epoch": contract.TIME,
                                id_col: pl.UInt64, "truth_id": pl.Int64})


def score_safety(ds: Dataset, cfg: PipelineConfig, run: Any, id_map: pl.DataFrame, truth: TruthSource,
                 spans: pl.DataFrame, grid: pl.DataFrame, stage: Callable[[str], None] = lambda _name: None,
                 fanout: Fanout | None = None) -> SafetyTables:
    """The alerts of the safety pictures and of the truth picture scored, attributed and, with
    look-aheads, the trade-off curves (``run``: the streamed tables, :class:`RunTables`;
    ``id_map``: which aircraft each safety picture row is; ``spans``, ``grid``: what the truth
    picture is sampled on). ``stage`` is told each stage as it starts (the run's clock).
    ``fanout``: where the truth's intervals and the truth picture the windows left are computed,
    a time chunk a piece (None: here, in turn), when the truth is on disk."""
    out = SafetyTables(pl.DataFrame(), pl.DataFrame(), pl.DataFrame())
    stage("score_alerts")
    fused, tracks, conflicts = run.fused, run.tracks, run.conflicts
    methods, id_col = safety_names(cfg, fused, tracks)
    if id_map.width == 0:
        id_map = empty_id_map(id_col)
    acfg = safety_alerts.AlertConfig(conflict=cfg.conflicts)
    note_minima(cfg.conflicts, out.notes)
    # the truth's LoS and proximity intervals, computed once for the alerts and every curve
    # setting (they depend on the separation minima, which the curves do not vary)
    if truth.file is not None:
        # a chunk of truth at a time: a long recording's truth held whole would not fit (memory)
        # the chunks the windows did, if they read this reference, and the rest
        done = run.intervals[0] if run.intervals is not None and run.intervals[1] == truth.file else None
        intervals, span = reference_intervals(truth.file, acfg, ds.origin, state=done, fanout=fanout or serial)
    else:
        held = truth.columns(ALERT_TRUTH)
        intervals = safety_alerts.truth_intervals(held, acfg, ds.origin)
        span = time_span(held, acfg, ds.origin)
        del held
    release_memory()
    # the same prediction on the truth picture: which alerts the picture causes
    if run.truth_picture is not None:     # predicted in the windows but for their last stretch
        t_conf, t_ids, onsets = truth_picture_finish(*run.truth_picture, cfg.conflicts, truth.between, id_col,
                                                     ds.origin)
    else:
        parts = (fanout, reference_files(truth.file)) if fanout is not None and truth.file is not None else None
        t_conf, t_ids, onsets = truth_conflicts(cfg.conflicts, truth.between, spans, grid, id_col, ds.origin,
                                                parts=parts)
    # the rows the scoring reads: a day's conflict rows are 1.2 GB, its id map 40 M rows (memory)
    scored_rows = (list(conflicts.blocks()) if isinstance(conflicts, DeferredTable)
                   else [safety_alerts.scored_conflicts(conflicts)])
    conflicts_all = (pl.concat(scored_rows, how="vertical_relaxed") if scored_rows
                     else contract.empty_frame("conflicts", False))
    del scored_rows
    id_map_all, scored = safety_alerts.scored_ids(id_map, conflicts_all, id_col), methods
    if t_conf.height or t_ids.height:
        if t_conf.height:
            conflicts_all = pl.concat([conflicts_all, t_conf], how="diagonal_relaxed")
        id_map_all = pl.concat([id_map_all, t_ids.select(id_map.columns).cast(id_map.schema)])
        scored = [*methods, safety_alerts.TRUTH_PICTURE]
    # a picture at a time: the same tables, with one picture's rows in the scoring's joins
    metrics, alerts, los = safety_alerts.stca_tables_by_picture(
        conflicts_all, id_map_all, span, acfg, id_col=id_col, methods=scored, frame=ds.origin, intervals=intervals)
    del conflicts_all, id_map_all
    alerts, los, attribution = attributed(alerts, los, onsets, acfg, spans)
    metrics = pl.concat([metrics, attribution], how="vertical_relaxed")
    if ds.external_alerts.height:
        metrics, alerts, los = _with_external(ds, acfg, truth.scan(EXTERNAL_TRUTH), intervals,
                                              (metrics, alerts, los), out.notes)
    if cfg.stca_lookaheads_s:
        stage("score_curves")   # the points the windows predicted, scored
        release_memory()        # the alert scoring's scratch, before the points' reads (the end's peak)
        curve = stca_curves(cfg, fused, tracks, id_map, span, acfg, id_col, ds.origin, methods, intervals,
                            None if run.scratch is None else run.scratch / "curves", run.curve_rows)
        metrics = pl.concat([metrics, safety_alerts.tradeoff_metrics(curve)], how="vertical_relaxed")
    out.metrics, out.alerts, out.losses = metrics, alerts, los
    return out


def _with_external(ds: Dataset, acfg: "safety_alerts.AlertConfig", truth: "pl.DataFrame | pl.LazyFrame",
                   intervals: tuple[pl.DataFrame, pl.DataFrame], tables: tuple[pl.DataFrame, ...], notes: list[str]
                   ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(metrics, alerts, losses) with the dataset's external alert list scored beside the pictures
    on the same truth intervals (:func:`safety.alerts.score_external`)."""
    cols = [c for c in EXTERNAL_TRUTH if c in truth.collect_schema().names()]
    metrics, alerts, los = safety_alerts.score_external(ds.external_alerts, truth.lazy().select(cols), acfg,
                                                        ds.origin, intervals)
    lost = metrics.filter(pl.col("metric") == "unidentified_alerts")
    for method, n in lost.select("method", "value").iter_rows():
        if n:
            total = ds.external_alerts.filter(pl.col("method") == method).height
            notes.append(f"{method}: {int(n):,} of {total:,} alert(s) without two aircraft identified in the truth "
                         "(Mode S, callsign, Mode 3/A): scored false")
    return tuple(pl.concat([a, b], how=how) for a, b, how in zip(
        tables, (metrics, alerts, los), ("vertical_relaxed", "diagonal_relaxed", "diagonal_relaxed")))
