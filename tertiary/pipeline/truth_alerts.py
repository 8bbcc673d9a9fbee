"""Conflict prediction on the truth picture (:mod:`tertiary.evaluation.truth_picture`), stepped
in time blocks with its state carried (:func:`safety.conflicts.conflicts_step`), and the
attribution of every system picture's alerts to the picture or the predictor
(:mod:`safety.alerts.attribution`).

The windows of a run predict it as they pass (:func:`truth_picture_step`): an aircraft's
observed span (:func:`~tertiary.evaluation.truth_picture.observed_spans`) is closed by
:data:`~tertiary.evaluation.truth_picture.SPAN_GAP_S` without a report, so every grid epoch more
than that before a window's end lies in spans no later report can change, and is predicted then.
The end of the run predicts the rest (:func:`truth_picture_finish`); the rows equal those of the
whole run predicted at once (:func:`truth_conflicts`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import polars as pl

from safety import alerts as safety_alerts
from safety import conflicts as safety_conflicts
from tertiary.contract import TIME
from tertiary.core import geo
from tertiary.core.stage import T_MAX_US
from tertiary.core.units import US
from tertiary.evaluation.reference_spans import files_between, read_spans
from tertiary.evaluation.truth_picture import SPAN_GAP_S, extend_spans, truth_picture
from tertiary.runtime.fanout import Fanout

__all__ = ["TRUTH_BLOCK_S", "TRUTH_STEP_S", "TRUTH_PICTURE_COLUMNS", "TRUTH_TABLES", "TruthPictureState",
           "truth_conflicts", "truth_picture_step", "truth_picture_finish", "reference_slice", "attributed"]

#: the time block of truth read at once (s): a national hour's truth is 5 M samples ...
TRUTH_BLOCK_S = 900.0
#: ... and the step in which its picture is made and predicted, the state carried (s): the
#: prediction's pairs grow with the epochs predicted at once
TRUTH_STEP_S = 300.0
#: what the truth picture reads of the truth
TRUTH_PICTURE_COLUMNS = ["truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "alt_m",
                         "alt_rate_mps", "icao24"]
#: the window outputs of the truth picture's prediction: the conflict rows and id rows the alert
#: scoring reads, and the manoeuvre onsets of the time predicted
TRUTH_TABLES = ("truth_conflicts", "truth_ids", "truth_onsets")
#: truth read on either side of a block: the interpolation's bracketing samples, and the
#: stretch a manoeuvre onset needs before it
_MARGIN_S = 60.0

TruthSlice = Callable[[int, int], pl.DataFrame]
_ONSETS = {"truth_id": pl.Int64, "t_us": pl.Int64}


def _no_spans() -> pl.DataFrame:
    return pl.DataFrame(schema={"run": pl.UInt32, "truth_id": pl.Int64, "first": TIME, "last": TIME})


def _no_epochs() -> pl.DataFrame:
    return pl.DataFrame(schema={"run": pl.UInt32, "epoch": TIME})


@dataclass(frozen=True)
class TruthPictureState:
    """The truth picture's prediction carried from window to window: the observed spans that
    may still hold a grid epoch not predicted (run, truth_id, first, last), the grid epochs not
    predicted yet (run, epoch), the time from which they are (µs; None: nothing predicted yet)
    and the prediction's state. ``complete`` False: a window was not seen (a resumed checkpoint
    that carried none), so the end of the run predicts the whole truth picture."""

    spans: pl.DataFrame = field(default_factory=_no_spans)
    pending: pl.DataFrame = field(default_factory=_no_epochs)
    done_us: int | None = None
    conflicts: safety_conflicts.ConflictState = field(default_factory=safety_conflicts.init_conflict_state)
    complete: bool = True


def reference_slice(files: Sequence[Path]) -> TruthSlice:
    """A :data:`TruthSlice` of the reference files: the samples of [t0_us, t1_us], the
    :data:`TRUTH_PICTURE_COLUMNS` they have, in the files' order."""
    spans = read_spans(files)

    def between(t0_us: int, t1_us: int) -> pl.DataFrame:
        lf = pl.scan_parquet(files_between(files, spans, t0_us, t1_us))
        have = lf.collect_schema().names()
        return (lf.select(c for c in TRUTH_PICTURE_COLUMNS if c in have)
                .filter(pl.col("time").dt.epoch("us").is_between(t0_us, t1_us)).collect())
    return between


def _predict(state: safety_conflicts.ConflictState, cc: safety_conflicts.ConflictConfig, truth_slice: TruthSlice,
             spans: pl.DataFrame, epochs: pl.DataFrame, id_col: str, frame: geo.LocalFrame, lo: int, hi: int,
             block_s: float, step_s: float) -> tuple[list[pl.DataFrame], list[pl.DataFrame], list[pl.DataFrame],
                                                    safety_conflicts.ConflictState]:
    """The truth picture of ``epochs`` in [lo, hi) µs predicted from ``state``: each step's
    scored conflict rows, id rows and the manoeuvre onsets in [lo, hi); the state after."""
    out, ids, onsets = [], [], []
    us = epochs["epoch"].dt.epoch("us")
    block, margin, step = max(int(block_s * US), 1), int(_MARGIN_S * US), max(int(step_s * US), 1)
    for a in range(lo, hi, block):
        b = min(a + block, hi)
        truth = truth_slice(a - margin, b + margin)
        for c in range(a, b, step):
            d = min(c + step, b)
            ep = epochs.filter(us.is_between(c, d, closed="left"))
            if not ep.height:
                continue
            pic = truth_picture(truth, spans, ep, safety_alerts.TRUTH_PICTURE, id_col)
            rows, state = safety_conflicts.conflicts_step(state, pic, cc, id_col, frame, c, d, scored_only=True)
            # only the rows the alert scoring reads are kept: a day's truth picture has tens of
            # millions of conflict and id rows, a few thousand of them alerts (memory)
            rows = safety_alerts.scored_conflicts(rows)
            out.append(rows)
            pid = pic.select("run", "method", "epoch", id_col, pl.col(id_col).cast(pl.Int64).alias("truth_id"))
            # the truth picture's ids are the aircraft: none outlives its own truth
            ids.append(safety_alerts.scored_ids(pid, rows, id_col, last=False))
            del pic
        if truth.height:
            on = safety_alerts.manoeuvre_onsets(truth)
            onsets.append(on.filter(pl.col("t_us").is_between(a, b, closed="left")))
        del truth
    return out, ids, onsets, state


def _joined(out: list[pl.DataFrame], ids: list[pl.DataFrame], onsets: list[pl.DataFrame]
            ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    return (pl.concat(out, how="vertical_relaxed") if out else pl.DataFrame(),
            pl.concat(ids, how="vertical_relaxed") if ids else pl.DataFrame(),
            pl.concat(onsets) if onsets else pl.DataFrame(schema=_ONSETS))


def truth_conflicts(cc: safety_conflicts.ConflictConfig, truth_slice: TruthSlice, spans: pl.DataFrame,
                    epochs: pl.DataFrame, id_col: str, frame: geo.LocalFrame, block_s: float = TRUTH_BLOCK_S,
                    step_s: float = TRUTH_STEP_S, parts: tuple[Fanout, list[Path]] | None = None
                    ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(conflicts, id map, manoeuvre onsets) of the truth picture at the picture grid
    ``epochs`` (run, epoch) for the observed ``spans``; ``truth_slice(t0_us, t1_us)`` returns the
    truth's :data:`TRUTH_PICTURE_COLUMNS` (those it has) with samples in [t0_us, t1_us], read
    ``block_s`` at a time; the picture is made and predicted ``step_s`` at a time, the
    prediction's state carried, so the rows equal one step's over the whole span. The
    conflicts and id map hold the rows the alert scoring reads
    (:func:`safety.alerts.scored_conflicts`, :func:`safety.alerts.scored_ids`).

    ``parts`` (a fanout and the reference's files, which ``truth_slice`` reads): each block of
    ``block_s`` is predicted apart (:func:`_predict_part`), the pieces joined in time order."""
    if not epochs.height:
        return pl.DataFrame(), pl.DataFrame(), pl.DataFrame(schema=_ONSETS)
    us = epochs["epoch"].dt.epoch("us")
    lo, hi = int(us.min()), int(us.max()) + 1
    if parts is None:
        out, ids, onsets, _ = _predict(safety_conflicts.init_conflict_state(), cc, truth_slice, spans, epochs,
                                       id_col, frame, lo, hi, block_s, step_s)
        return _joined(out, ids, onsets)
    fanout, files = parts
    block = max(int(block_s * US), 1)
    pieces = [(cc, files, spans, epochs.filter(us.is_between(_warm_from(epochs, a, cc.confirm_n), min(a + block, hi),
                                                              closed="left")),
               id_col, frame, a, min(a + block, hi), block_s, step_s) for a in range(lo, hi, block)]
    got = list(fanout(_predict_part, pieces))
    return tuple(pl.concat([g[k] for g in got if g[k].height], how="vertical_relaxed")
                 if any(g[k].height for g in got) else got[0][k] for k in range(3))


def _warm_from(epochs: pl.DataFrame, a: int, n: int) -> int:
    """The earliest of each run's last ``n`` grid epochs before ``a`` (µs; ``a`` when none): the
    m-of-n confirmation carries no more than the last n epochs of a run's grid."""
    us = pl.col("epoch").dt.epoch("us")
    before = (epochs.filter(us < a).group_by("run").agg(us.sort().tail(n).min().alias("__w"))
              .select(pl.col("__w").min()).item())
    return a if before is None else int(before)


def _predict_part(cc: safety_conflicts.ConflictConfig, files: list[Path], spans: pl.DataFrame,
                  epochs: pl.DataFrame, id_col: str, frame: geo.LocalFrame, a: int, b: int, block_s: float,
                  step_s: float) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """The truth picture's three tables at the grid epochs in [a, b) (a piece of
    :func:`truth_conflicts`): ``epochs`` also holds the grid epochs before ``a`` that the m-of-n
    confirmation reads (:func:`_warm_from`), predicted from a fresh state and then dropped, so
    the rows from ``a`` on are those of the prediction carried from the start."""
    if not epochs.height:          # a block of the span in a gap of the grid
        return pl.DataFrame(), pl.DataFrame(), pl.DataFrame(schema=_ONSETS)
    us = epochs["epoch"].dt.epoch("us")
    lo = min(int(us.min()), a)
    out, ids, onsets, _ = _predict(safety_conflicts.init_conflict_state(), cc, reference_slice(files), spans,
                                   epochs, id_col, frame, lo, b, block_s, step_s)
    conflicts, idmap, onset = _joined(out, ids, onsets)
    at = pl.col("epoch").dt.epoch("us") >= a
    return (conflicts.filter(at) if conflicts.height else conflicts, idmap.filter(at) if idmap.height else idmap,
            onset.filter(pl.col("t_us") >= a))


def _advance(state: TruthPictureState, until_us: int, cc: safety_conflicts.ConflictConfig, truth_slice: TruthSlice,
             id_col: str, frame: geo.LocalFrame) -> tuple[dict[str, pl.DataFrame], TruthPictureState]:
    """Every pending grid epoch before ``until_us`` predicted; the spans that end before it dropped."""
    us = pl.col("epoch").dt.epoch("us")
    ready = state.pending.filter(us < until_us)
    if not ready.height:
        return {}, state
    t = ready["epoch"].dt.epoch("us")
    # to the last ready epoch, not further: the run's last block ends where the whole run's does
    lo, hi = (int(t.min()) if state.done_us is None else state.done_us), int(t.max()) + 1
    out, ids, onsets, conflicts = _predict(state.conflicts, cc, truth_slice, state.spans, ready, id_col, frame, lo,
                                           hi, TRUTH_BLOCK_S, TRUTH_STEP_S)
    rows = dict(zip(TRUTH_TABLES, _joined(out, ids, onsets)))
    # a span ended before ``until_us`` holds no epoch still pending, and no later report extends it
    spans = state.spans.filter(pl.col("last").dt.epoch("us") >= until_us)
    return ({k: v for k, v in rows.items() if v.height},
            TruthPictureState(spans, state.pending.filter(us >= until_us), hi, conflicts))


def truth_picture_step(state: TruthPictureState, observed: pl.DataFrame | None, t1_us: int,
                       cc: safety_conflicts.ConflictConfig, truth_slice: TruthSlice, id_col: str,
                       frame: geo.LocalFrame, gap_s: float = SPAN_GAP_S) -> tuple[dict[str, pl.DataFrame],
                                                                              TruthPictureState]:
    """One window of the truth picture's prediction: the window's observed aircraft (run, epoch,
    truth_id of its aligned reports; None: not known, so the end predicts it all) extend the
    spans and the grid, and every grid epoch before ``t1_us`` − ``gap_s`` is predicted once
    that is :data:`TRUTH_STEP_S` of them or more (the last window, ``t1_us`` at
    :data:`~tertiary.core.stage.T_MAX_US`, predicts every one). Outputs: :data:`TRUTH_TABLES`
    (those with rows)."""
    if not state.complete:
        return {}, state
    if observed is None:
        return {}, TruthPictureState(complete=False)
    seen = observed.select("run", "epoch", pl.col("truth_id").cast(pl.Int64)).drop_nulls().unique()
    grid = seen.select("run", "epoch").unique()
    state = TruthPictureState(extend_spans(state.spans, seen, gap_s),
                              pl.concat([state.pending, grid.cast(state.pending.schema)]), state.done_us,
                              state.conflicts)
    until = t1_us - int(gap_s * US)
    if not state.pending.height:
        return {}, state
    start = state.done_us if state.done_us is not None else int(state.pending["epoch"].dt.epoch("us").min())
    if until - start < int(TRUTH_STEP_S * US) and t1_us < T_MAX_US:
        # a step of TRUTH_STEP_S at least (or the last window's rest): each step reads its
        # truth with a margin either side, and short windows would read it several times over
        return {}, state
    return _advance(state, until, cc, truth_slice, id_col, frame)


def truth_picture_finish(state: TruthPictureState, stored: Callable[[str], pl.DataFrame | None],
                         cc: safety_conflicts.ConflictConfig, truth_slice: TruthSlice, id_col: str,
                         frame: geo.LocalFrame) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """:func:`truth_conflicts`'s three tables from the windows' stored outputs (``stored(name)``:
    every window's rows of a :data:`TRUTH_TABLES` name, None when none) and the grid epochs
    they left, predicted here."""
    last = {}
    if state.pending.height:
        end = int(state.pending["epoch"].dt.epoch("us").max()) + 1
        last, _ = _advance(state, end, cc, truth_slice, id_col, frame)
    tables = []
    for name in TRUTH_TABLES:
        got = [f for f in (stored(name), last.get(name)) if f is not None and f.height]
        tables.append(pl.concat(got, how="vertical_relaxed") if got else None)
    conflicts, ids, onsets = tables
    return (pl.DataFrame() if conflicts is None else conflicts, pl.DataFrame() if ids is None else ids,
            pl.DataFrame(schema=_ONSETS) if onsets is None else onsets.cast(_ONSETS))


def attributed(alerts: pl.DataFrame, los: pl.DataFrame, onsets: pl.DataFrame, acfg: safety_alerts.AlertConfig,
               spans: pl.DataFrame | None = None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(alerts with ``induced`` and ``valid``, losses with ``induced`` (a missed loss's cause;
    ``spans``: the aircraft's observed spans, which tell a loss under way when first observed),
    the attribution metrics per system picture)."""
    alerts = safety_alerts.valid_alerts(safety_alerts.attribute_alerts(alerts, acfg), onsets, acfg)
    los = safety_alerts.attribute_los(los, spans=spans)
    return alerts, los, safety_alerts.attribution_metrics(alerts, los)
