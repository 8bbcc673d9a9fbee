"""The truth picture: the perfect air picture, evaluation only.

Conflict prediction run on it (the same configuration, confirmation and look-ahead as on the
system's pictures) raises the alerts a perfect tracker would cause; an alert of a system
picture that the truth picture does not raise for that pair at that time is the picture's
doing, one the truth picture raises too is the predictor's (:mod:`safety.alerts.attribution`).
This is the *test predictor on truth data* of Torres & McKay (2009, "Assessing tactical alert
function accuracy performance").

Sampled like the picture: each aircraft the radars observe is in the truth picture at every
epoch of the picture's grid within its observed spans — from an observed epoch to the next one
while they are at most :data:`SPAN_GAP_S` apart (a system track lives between reports too, but
none coasts through minutes without one) — with its true state interpolated at the epoch
(:func:`tertiary.evaluation.reference.interpolate_reference`) and a zero covariance — the
estimation term of the thresholds is nil, the piloting term and the look-ahead are the
configuration's.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from tertiary.contract import TIME
from tertiary.core.units import US
from tertiary.evaluation.reference import interpolate_reference

__all__ = ["SPAN_GAP_S", "extend_spans", "first_observed", "observed_spans", "truth_picture"]

_STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")

#: an aircraft without a report for longer than this leaves the truth picture until its next
#: one (s): two minutes is ten en-route scans or more, well past any tracker's coasting
SPAN_GAP_S = 120.0


def extend_spans(spans: pl.DataFrame, observed: pl.DataFrame, gap_s: float = SPAN_GAP_S) -> pl.DataFrame:
    """``spans`` (run, truth_id, first, last: :func:`observed_spans`) extended by more observed
    epochs (run, epoch, truth_id): an epoch within ``gap_s`` of a span, or of another epoch,
    joins it; spans that come within ``gap_s`` of each other merge. Sorted by run, truth_id,
    first."""
    pts = observed.select(pl.col("run").cast(pl.UInt32), pl.col("truth_id").cast(pl.Int64),
                          pl.col("epoch").cast(TIME).alias("first"), pl.col("epoch").cast(TIME).alias("last"))
    both = pl.concat([spans.select(pts.columns).cast(pts.schema), pts]).sort("run", "truth_id", "first")
    keys = ["run", "truth_id"]
    reach = pl.col("last").dt.epoch("us").cum_max().shift(1).over(keys)
    starts = (reach.is_null() | (pl.col("first").dt.epoch("us") - reach > int(gap_s * US))).cum_sum().over(keys)
    return (both.with_columns(starts.alias("__k")).group_by(*keys, "__k")
            .agg(pl.col("first").min(), pl.col("last").max()).drop("__k").sort("run", "truth_id", "first"))


def observed_spans(observed: pl.DataFrame, gap_s: float = SPAN_GAP_S) -> pl.DataFrame:
    """(run, truth_id, first, last) of each aircraft's observed spans (an aircraft may have
    several: :func:`extend_spans`), from ``observed`` (run, epoch, truth_id:
    :func:`tertiary.pipeline.scoring.observed_aircraft`)."""
    empty = pl.DataFrame(schema={"run": pl.UInt32, "truth_id": pl.Int64, "first": TIME, "last": TIME})
    return extend_spans(empty, observed, gap_s)


def first_observed(observed: pl.DataFrame) -> pl.DataFrame:
    """(run, truth_id, first) of each aircraft's first observed epoch, from ``observed``: what
    tells a loss under way when first observed (:func:`safety.alerts.attribute_los`)."""
    return (observed.group_by(pl.col("run").cast(pl.UInt32), pl.col("truth_id").cast(pl.Int64))
            .agg(pl.col("epoch").min().cast(TIME).alias("first")).sort("run", "truth_id"))


def _requests(spans: pl.DataFrame, epochs: pl.DataFrame) -> pl.DataFrame:
    """(run, epoch, truth_id) of every grid epoch inside each aircraft's span: per run one
    ``searchsorted`` of the span ends in the run's sorted epochs, then the index ranges."""
    out = []
    for (run,), ep in epochs.partition_by("run", as_dict=True, maintain_order=True).items():
        grid = ep["epoch"].unique().sort()
        us = grid.dt.epoch("us").to_numpy()
        sp = spans.filter(pl.col("run") == run)
        if not sp.height or not len(us):
            continue
        lo = np.searchsorted(us, sp["first"].dt.epoch("us").to_numpy(), side="left")
        hi = np.searchsorted(us, sp["last"].dt.epoch("us").to_numpy(), side="right")
        rows = (pl.DataFrame({"truth_id": sp["truth_id"], "__k": pl.int_ranges(pl.Series(lo), pl.Series(hi),
                                                                                   eager=True)})
                .explode("__k").drop_nulls("__k"))
        out.append(rows.select(pl.lit(run, pl.UInt32).alias("run"),
                               pl.Series("epoch", grid).gather(rows["__k"]).cast(TIME), pl.col("truth_id")))
    if not out:
        return pl.DataFrame(schema={"run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64})
    return pl.concat(out)


def truth_picture(truth: pl.DataFrame, spans: pl.DataFrame, epochs: pl.DataFrame, name: str,
                  id_col: str = "track_id", max_gap_s: float = 10.0) -> pl.DataFrame:
    """The truth picture at ``epochs`` (run, epoch: the picture's grid) for the aircraft and
    spans of ``spans`` (:func:`observed_spans`): columns run, epoch, method (``name``;
    :data:`safety.alerts.TRUTH_PICTURE` in a run),
    ``id_col`` (the truth id), the system-frame state, ``alt_m``/``alt_rate_mps`` when the truth
    has a height channel, ``cov_diag`` (zeros) and ``mode_s`` (the ICAO address when known).
    Epochs where the truth has no sample within ``max_gap_s`` are left out."""
    req = _requests(spans.with_columns(pl.col("truth_id").cast(pl.Int64)), epochs)
    req = req.with_columns(pl.col("epoch").alias("time"))
    ref = interpolate_reference(truth.with_columns(pl.col("truth_id").cast(pl.Int64)), req, max_gap_s)
    ref = ref.filter(pl.col("status") == "evaluated")
    has_alt = "alt_m" in truth.columns
    cols = [pl.col("run"), pl.col("epoch"), pl.lit(name).alias("method"),
            pl.col("truth_id").cast(pl.UInt64).alias(id_col),
            *[pl.col(f"true_{c}").alias(c) for c in _STATE]]
    if has_alt:
        cols += [pl.col("true_alt_m").alias("alt_m"), pl.col("true_alt_rate_mps").alias("alt_rate_mps")]
    cols.append(pl.lit([0.0] * 6, pl.Array(pl.Float64, 6)).alias("cov_diag"))
    out = ref.select(cols)
    if "icao24" in truth.columns:
        ident = (truth.select(pl.col("truth_id").cast(pl.UInt64).alias(id_col), pl.col("icao24").alias("mode_s"))
                 .unique(id_col, keep="first"))
        out = out.join(ident, on=id_col, how="left")
    return out.sort("run", "epoch", id_col)
