"""Conflict prediction on the truth picture (:mod:`tertiary.evaluation.truth_picture`), stepped
in time blocks with its state carried (:func:`safety.conflicts.conflicts_step`), and the
attribution of every system picture's alerts to the picture or the predictor
(:mod:`safety.alerts.attribution`)."""

from __future__ import annotations

from collections.abc import Callable

import polars as pl

from safety import alerts as safety_alerts
from safety import conflicts as safety_conflicts
from tertiary.core import geo
from tertiary.core.units import US
from tertiary.evaluation.truth_picture import truth_picture

__all__ = ["TRUTH_BLOCK_S", "TRUTH_STEP_S", "TRUTH_PICTURE_COLUMNS", "truth_conflicts", "attributed"]

#: the time block of truth read at once (s): a national hour's truth is 5 M samples ...
TRUTH_BLOCK_S = 900.0
#: ... and the step in which its picture is made and predicted, the state carried (s): the
#: prediction's pairs grow with the epochs predicted at once
TRUTH_STEP_S = 300.0
#: what the truth picture reads of the truth
TRUTH_PICTURE_COLUMNS = ["truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "alt_m",
                         "alt_rate_mps", "icao24"]
#: truth read on either side of a block: the interpolation's bracketing samples, and the
#: stretch a manoeuvre onset needs before it
_MARGIN_S = 60.0

TruthSlice = Callable[[int, int], pl.DataFrame]


def truth_conflicts(cc: safety_conflicts.ConflictConfig, truth_slice: TruthSlice, spans: pl.DataFrame,
                    epochs: pl.DataFrame, id_col: str, frame: geo.LocalFrame, block_s: float = TRUTH_BLOCK_S,
                    step_s: float = TRUTH_STEP_S) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(conflicts, id map, manoeuvre onsets) of the truth picture at the picture grid
    ``epochs`` (run, epoch) for the observed ``spans``; ``truth_slice(t0_us, t1_us)`` returns the
    truth's :data:`TRUTH_PICTURE_COLUMNS` (those it has) with samples in [t0_us, t1_us], read
    ``block_s`` at a time; the picture is made and predicted ``step_s`` at a time, the
    prediction's state carried, so the rows equal one step's over the whole span. The
    conflicts and id map hold the rows the alert scoring reads
    (:func:`safety.alerts.scored_conflicts`, :func:`safety.alerts.scored_ids`)."""
    state = safety_conflicts.init_conflict_state()
    out, ids, onsets = [], [], []
    if not epochs.height:
        return pl.DataFrame(), pl.DataFrame(), pl.DataFrame(schema={"truth_id": pl.Int64, "t_us": pl.Int64})
    us = epochs["epoch"].dt.epoch("us")
    lo, hi = int(us.min()), int(us.max()) + 1
    block, margin = max(int(block_s * US), 1), int(_MARGIN_S * US)
    step = max(int(step_s * US), 1)
    for a in range(lo, hi, block):
        b = min(a + block, hi)
        truth = truth_slice(a - margin, b + margin)
        for c in range(a, b, step):
            d = min(c + step, b)
            ep = epochs.filter(us.is_between(c, d, closed="left"))
            if not ep.height:
                continue
            pic = truth_picture(truth, spans, ep, safety_alerts.TRUTH_PICTURE, id_col)
            rows, state = safety_conflicts.conflicts_step(state, pic, cc, id_col, frame, c, d)
            # only the rows the alert scoring reads are kept: a day's truth picture has tens of
            # millions of conflict and id rows, a few thousand of them alerts (memory)
            rows = safety_alerts.scored_conflicts(rows)
            out.append(rows)
            pid = pic.select("run", "method", "epoch", id_col, pl.col(id_col).cast(pl.Int64).alias("truth_id"))
            ids.append(safety_alerts.scored_ids(pid, rows, id_col))
            del pic
        if truth.height:
            on = safety_alerts.manoeuvre_onsets(truth)
            onsets.append(on.filter(pl.col("t_us").is_between(a, b, closed="left")))
        del truth
    return (pl.concat(out, how="vertical_relaxed"), pl.concat(ids, how="vertical_relaxed"),
            pl.concat(onsets) if onsets else pl.DataFrame(schema={"truth_id": pl.Int64, "t_us": pl.Int64}))


def attributed(alerts: pl.DataFrame, los: pl.DataFrame, onsets: pl.DataFrame, acfg: safety_alerts.AlertConfig,
               spans: pl.DataFrame | None = None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(alerts with ``induced`` and ``valid``, losses with ``induced`` (a missed loss's cause;
    ``spans``: the aircraft's observed spans, which tell a loss under way when first observed),
    the attribution metrics per system picture)."""
    alerts = safety_alerts.valid_alerts(safety_alerts.attribute_alerts(alerts, acfg), onsets, acfg)
    los = safety_alerts.attribute_los(los, spans=spans)
    return alerts, los, safety_alerts.attribution_metrics(alerts, los)

