"""The STCA's scoring against the truth beyond the alert list: the truth's separation intervals
read from a reference on disk a chunk at a time, as the windows pass (:func:`intervals_step`) and
at the end (:func:`reference_intervals`), the note of the
separation minima the alerts follow (:func:`note_minima`) and the trade-off curves of the safety
picture (:func:`stca_curves`)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import polars as pl

from safety import alerts as safety_alerts
from safety import conflicts as safety_conflicts
from safety.alerts.tradeoff import curve_settings, tradeoff_from_rows as curve_from_rows
from tertiary.core import geo
from tertiary.core.units import FT, US
from tertiary.evaluation.evaluate import reference_files
from tertiary.evaluation.reference_spans import files_between, read_spans
from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.pictures import NOT_SCORED, as_picture, confirmed_only, safety_picture
from tertiary.pipeline.tables import ALERT_TRUTH, OnDiskTable
from tertiary.runtime.fanout import Fanout, serial
from tertiary.runtime.windows import release_memory

__all__ = ["TRUTH_CHUNK_S", "CURVE_BLOCK_ROWS", "TruthIntervals", "intervals_step", "note_minima",
           "reference_intervals", "stca_curves", "time_span"]

# `safety` is imported as modules, not names: `import safety` first imports `tertiary` (whose
# package imports this one) while `safety` is half initialised, and only a module binding
# survives that


#: the time chunk in which :func:`reference_intervals` reads an on-disk truth (s): the
#: separation intervals' geodesy holds a dozen arrays the length of the chunk's samples
TRUTH_CHUNK_S = 900.0


#: each run's first and last truth sample and, with an alert configuration, each aircraft's last
#: (:func:`safety.alerts.truth_span`): what the alert scoring reads of the truth beside its intervals
time_span = safety_alerts.truth_span


def _per_run(lf: pl.LazyFrame, agg: pl.Expr) -> pl.LazyFrame:
    """``agg`` of each run (of the whole frame without a ``run`` column)."""
    return lf.group_by("run").agg(agg) if "run" in lf.collect_schema() else lf.select(agg)


@dataclass(frozen=True)
class TruthIntervals:
    """The truth's separation intervals of the chunks of :func:`reference_intervals` done so
    far, merged (None: none yet), the start of the next chunk (µs; None: the first) and the
    truth's :func:`time_span` they were cut from (None: not yet read)."""

    merged: tuple[pl.DataFrame, pl.DataFrame] | None = None
    next_us: int | None = None
    span: pl.DataFrame | None = None


def intervals_step(state: TruthIntervals, reference: Path, span: pl.DataFrame, acfg: safety_alerts.AlertConfig,
                   frame: geo.LocalFrame, until_us: int | None = None, chunk_s: float = TRUTH_CHUNK_S,
                   fanout: Fanout = serial) -> TruthIntervals:
    """``state`` with the chunks of the truth's span (:func:`time_span` ``span``) that end by
    ``until_us`` (None: every chunk left) done and merged in: the windows compute the chunks
    their progress has passed, the end of the run the rest. The chunks are
    :func:`reference_intervals`'s whatever the windows, so the result is the same. Each chunk
    reads its own truth, so ``fanout`` may compute them apart; they are merged in time order."""
    if not span.height:
        return dataclasses.replace(state, span=span)
    files = reference_files(reference)
    schema = pl.scan_parquet(files).collect_schema()
    cols = [c for c in ALERT_TRUTH if c in schema]
    # one run: each file's time range bounds a chunk's reads (runs have grids of their own)
    spans = read_spans(files) if "run" not in schema else None
    lo, hi = (int(span["time"].dt.epoch("us").min()), int(span["time"].dt.epoch("us").max()) + 1)
    step = max(int(chunk_s * US), 1)
    a = lo if state.next_us is None else state.next_us
    chunks = []
    while a < hi and (until_us is None or min(a + step, hi) <= until_us):
        chunks.append((files, cols, acfg, frame, a, min(a + step, hi), spans))
        a = chunks[-1][5]
    merged = state.merged
    for chunk in fanout(_chunk_task, chunks):
        merged = chunk if merged is None else safety_alerts.merge_intervals([merged, chunk], acfg)
    return TruthIntervals(merged, a, span)


def _chunk_task(files: list[Path], cols: list[str], acfg: safety_alerts.AlertConfig, frame: geo.LocalFrame,
                a: int, b: int, spans: list | None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`_chunk_intervals` of one chunk, from the reference's files (a piece of a :data:`Fanout`);
    with their time ranges (``spans``) it scans only the files that can hold its samples."""
    lf = pl.scan_parquet(files) if spans is None else None
    return _chunk_intervals(lf, cols, acfg, frame, a, b, (files, spans))


def _chunk_intervals(lf: pl.LazyFrame | None, cols: list[str], acfg: safety_alerts.AlertConfig, frame: geo.LocalFrame,
                     a: int, b: int, spanned: tuple[list[Path], list | None] | None = None
                     ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The truth's intervals in [a, b) µs (module :func:`reference_intervals`) of the scan ``lf``.
    ``spanned``: the reference's files and their time ranges
    (:func:`~tertiary.evaluation.reference_spans.read_spans`; None: scan every file); with
    ranges, the files that can hold the chunk's samples are scanned instead (``lf`` may be None)."""
    t = pl.col("time")
    if spanned is not None and spanned[1] is not None:
        files, spans = spanned
        p_us, q_us = _edges(files, spans, a, b)
        lf = pl.scan_parquet(files_between(files, spans, p_us, q_us, reach=True))
        p, q = (None if v is None else _at(v) for v in (p_us, q_us))
    else:
        ta, tb = _at(a), _at(b)
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
    return safety_alerts.truth_intervals(truth, acfg, frame, clip_us=(a, b))


def _edges(files: list[Path], spans: list, a: int, b: int) -> tuple[int | None, int | None]:
    """(the last sample time before ``a``, the first from ``b``), µs, of one run's reference:
    a file wholly before ``a`` (after ``b``) gives its last (first) time from its span, and only
    the files whose range holds ``a`` or ``b`` are read. Scanning every file for them costs a
    national day's chunk a read of the day's times."""
    t = pl.col("time")
    timed = [(f, s) for f, s in zip(files, spans) if s[0] is not None]
    before = [s[1] for _, s in timed if s[1] < a]
    after = [s[0] for _, s in timed if s[0] >= b]
    for edge, cut, agg, out in ((a, t < _at(a), t.max(), before), (b, t >= _at(b), t.min(), after)):
        held = [f for f, s in timed if s[0] < edge <= s[1]]
        if held:
            v = pl.scan_parquet(held).filter(cut).select(agg.dt.epoch("us")).collect().item()
            if v is not None:
                out.append(int(v))
    return max(before, default=None), min(after, default=None)


def _at(us: int) -> pl.Expr:
    """``us`` (µs since the epoch) as a UTC time literal."""
    return pl.lit(us, pl.Int64).cast(pl.Datetime("us", "UTC"))


def reference_intervals(reference: Path, acfg: safety_alerts.AlertConfig, frame: geo.LocalFrame,
                        chunk_s: float = TRUTH_CHUNK_S, state: TruthIntervals | None = None,
                        fanout: Fanout = serial) -> tuple[tuple[pl.DataFrame, pl.DataFrame], pl.DataFrame]:
    """(the truth's (LoS, proximity) intervals, its :func:`time_span`) from a reference on disk
    (:func:`tertiary.evaluation.evaluate.write_reference`), ``chunk_s`` of truth at a time, each
    merged into those before by :func:`safety.alerts.merge_intervals`: the whole truth's. A
    chunk [a, b) reads every sample from the last sample time before a to the first after b,
    and each aircraft's neighbours of those: inside, the union sample grid and so the segment
    pairs are the whole truth's, and each chunk keeps the part of its intervals in [a, b).
    ``state``: the chunks the windows did (:func:`intervals_step`), finished here; ``fanout``: where
    the chunks left are computed."""
    state = state or TruthIntervals()
    span = (state.span if state.span is not None
            else time_span(pl.scan_parquet(reference_files(reference)), acfg, frame))
    done = intervals_step(state, reference, span, acfg, frame, None, chunk_s, fanout)
    return (safety_alerts.merge_intervals([], acfg) if done.merged is None else done.merged), span


def note_minima(cc: safety_conflicts.ConflictConfig, notes: list[str]) -> None:
    """A note of the separation minima of the alerts and their scoring when they are not one
    set everywhere (an en-route floor, aerodrome zones): the reader of an alert list must know
    its rule."""
    if cc.aerodrome_zones:
        radii = sorted({z.radius_m for z in cc.aerodrome_zones})
        ceilings = sorted({z.ceiling_m for z in cc.aerodrome_zones})
        text = (f"aerodrome zones: no STCA alert and no loss of separation scored between two aircraft both "
                f"within {'/'.join(f'{r / safety_conflicts.NM_M:g}' for r in radii)} NM and below "
                f"{'/'.join(f'{c / FT:,.0f}' for c in ceilings)} ft of one of {len(cc.aerodrome_zones)} "
                "aerodromes (aerodrome control, not radar separation)")
        if text not in notes:
            notes.append(text)
    if cc.enroute_above_m is None:
        return
    nm = safety_conflicts.NM_M
    text = (f"separation minima: {cc.sep_h_m / nm:g} NM / {cc.sep_v_m / FT:,.0f} ft for pairs both below "
            f"{cc.enroute_above_m / FT:,.0f} ft (terminal), {cc.enroute_h_m / nm:g} NM / "
            f"{cc.enroute_v_m / FT:,.0f} ft otherwise (en-route) — in the alerts and in the losses of "
            "separation they are scored on")
    if text not in notes:
        notes.append(text)


def _scored_curves(cfg: PipelineConfig, rows: Callable[[int], pl.DataFrame], id_map: pl.DataFrame,
                   truth: pl.DataFrame, acfg: safety_alerts.AlertConfig, id_col: str, frame: geo.LocalFrame,
                   methods: list[str], intervals: tuple[pl.DataFrame, pl.DataFrame]) -> pl.DataFrame:
    """The curves from the windows' ``curve_rows``, one point's rows read at a time: each scored
    as :func:`safety.alerts.stca_tradeoff` scores its own predictions."""
    settings = curve_settings(acfg.conflict, cfg.stca_confidences, cfg.stca_fixed_m, cfg.stca_lookaheads_s)
    scored = [functools.partial(rows, k) for k in range(len(settings))]
    return curve_from_rows(scored, settings, id_map, truth, acfg, id_col, methods, frame, intervals=intervals)


#: rows of an on-disk picture the STCA curves read at a time (whole windows)
CURVE_BLOCK_ROWS = 200_000


def stca_curves(cfg: PipelineConfig, fused: "pl.DataFrame | OnDiskTable", tracks: "pl.DataFrame | OnDiskTable",
                id_map: pl.DataFrame, truth: pl.DataFrame, acfg: safety_alerts.AlertConfig, id_col: str,
                frame: geo.LocalFrame, methods: list[str], intervals: tuple[pl.DataFrame, pl.DataFrame],
                spill: Path | None = None, rows: Callable[[int], pl.DataFrame] | None = None) -> pl.DataFrame:
    """The STCA trade-off curves of the safety picture. ``rows``: a reader of each point's
    predicted rows (by its index) as the run's windows made them (``curve_rows``,
    :class:`~tertiary.pipeline.plan.StcaCurvesStage`): only their scoring is left. Without
    them the prediction runs here: in one call when the picture is in memory, a picture at a
    time (read from disk) when the run is on disk — each picture's curve depends on that
    picture alone. ``intervals``: :func:`safety.alerts.truth_intervals` of ``truth``;
    ``spill``: scratch for each setting's predicted rows (:func:`safety.stca_tradeoff`)."""
    if rows is not None:
        return _scored_curves(cfg, rows, id_map, truth, acfg, id_col, frame, methods, intervals)
    kw = dict(id_col=id_col, frame=frame, lookaheads_s=cfg.stca_lookaheads_s, confidences=cfg.stca_confidences,
              fixed_est_h_m=cfg.stca_fixed_m, intervals=intervals, spill=spill)
    on_disk = tracks if id_col == "track_id" else fused
    if not isinstance(on_disk, OnDiskTable) or not (on_disk.pictures if id_col == "track_id" else on_disk.shown):
        picture, _ = safety_picture(cfg, fused, tracks, [])
        return safety_alerts.stca_tradeoff(picture, id_map, truth, acfg, methods=methods, **kw)
    curves = []
    # read without the columns conflict prediction does not read either, in time blocks: a
    # tracker picture whole, with its covariances, is the largest table of a run (memory)
    keys = on_disk.pictures if id_col == "track_id" else on_disk.shown
    show = as_picture if id_col == "track_id" else confirmed_only
    for key in keys:
        name = "+".join(key)
        blocks = (show(b) for b in on_disk.blocks(key, NOT_SCORED, rows=CURVE_BLOCK_ROWS))
        curves.append(safety_alerts.stca_tradeoff(blocks, id_map.filter(pl.col("method") == name), truth, acfg,
                                                  methods=[name], **kw))
        release_memory()
    curve = pl.concat(curves, how="vertical_relaxed")
    return curve.sort("method", "t_thr_s", "warning_s", "threshold_mode", "parameter")
