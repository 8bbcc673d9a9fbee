"""An external picture (CAT062 system tracks) scored against an ADS-B truth (CAT021).

Each track row is matched to the truth aircraft with its Mode S address (I062/380 ADR = the
CAT021 address = ``truth_id``), the truth is interpolated to the track's epoch and the errors
and pooled RMSE come from :mod:`tertiary.evaluate` — the same functions, the same metrics and
the same (2.15)/(4.84) pooling as the pipeline's own pictures (``stage`` = ``external``,
``method`` = ``sdps-SAC-SIC``).
"""

from __future__ import annotations

import polars as pl

from tertiary.evaluate import EvaluateConfig, accuracy_from_matched, error_columns, truth_at


def match_external(tracks: pl.DataFrame, truth: pl.DataFrame, skip_first_s: float = 0.0) -> pl.DataFrame:
    """Track rows with ``truth_id`` (by Mode S address), ``true_<state>`` and squared errors.

    Rows without an address, with an address not in the truth, outside the truth's span, or
    within ``skip_first_s`` of their track's first epoch are dropped.
    """
    if tracks.is_empty() or truth.is_empty() or "mode_s" not in tracks.columns:
        return pl.DataFrame()
    t = tracks.with_columns(pl.col("mode_s").str.to_integer(base=16, strict=False).cast(pl.Int64).alias("truth_id"))
    t = t.filter(pl.col("truth_id").is_in(truth["truth_id"].unique().implode()))
    if skip_first_s > 0:
        first = pl.col("epoch").min().over(["run", "method", "track_id"])
        t = t.filter((pl.col("epoch") - first).dt.total_microseconds() >= round(skip_first_s * 1e6))
    keep = ["run", "epoch", "track_id", "method", "truth_id", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
    keep += ["alt_m"] if "alt_m" in t.columns else []
    matched = truth_at(t.select(keep), truth)
    return matched.with_columns(error_columns("true_alt_m" in matched.columns))


def external_metrics(tracks: pl.DataFrame, truth: pl.DataFrame, skip_first_s: float = 0.0) -> pl.DataFrame:
    """Pooled accuracy of each external picture (metrics schema, stage ``external``)."""
    matched = match_external(tracks, truth, skip_first_s)
    cfg = EvaluateConfig(skip_first_s=skip_first_s, stage="external")
    if matched.is_empty():
        return accuracy_from_matched(pl.DataFrame(), cfg)
    return accuracy_from_matched(matched, cfg)
