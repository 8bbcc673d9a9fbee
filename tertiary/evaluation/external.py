"""An external picture (CAT062 system tracks) scored against an ADS-B truth (CAT021).

The picture goes through the project's one evaluation stage: the geometric matcher
(:func:`tertiary.evaluation.matching.match_to_reference`, one-to-one per epoch) and the seed metrics of
:mod:`tertiary.evaluation.accuracy` — the same matching rule, metrics and (2.15)/(4.84) pooling as the
pipeline's own pictures (``stage`` = ``external``, ``method`` = ``sdps-SAC-SIC``).
"""

from __future__ import annotations

import dataclasses

import polars as pl

from tertiary.evaluation.accuracy import AccuracyConfig, accuracy_from_matched, scored_rows
from tertiary.evaluation.matching import match_to_reference
from tertiary.io.asterix.dataset import ImportResult


def match_external(tracks: pl.DataFrame, truth: pl.DataFrame, skip_first_s: float = 0.0) -> pl.DataFrame:
    """The scored track rows: matched to a truth aircraft, after ``skip_first_s`` of each
    track's first epoch, with ``true_<state>`` and the squared errors (:func:`scored_rows`)."""
    if tracks.is_empty() or truth.is_empty():
        return pl.DataFrame()
    keep = ["run", "epoch", "track_id", "method", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
    keep += [c for c in ("alt_m", "mode_s") if c in tracks.columns]
    matched = match_to_reference(tracks.select(keep), truth)
    return scored_rows(matched, AccuracyConfig(skip_first_s=skip_first_s))


def external_metrics(tracks: pl.DataFrame, truth: pl.DataFrame, skip_first_s: float = 0.0) -> pl.DataFrame:
    """Pooled accuracy of each external picture (metrics schema, stage ``external``)."""
    cfg = AccuracyConfig(skip_first_s=skip_first_s)
    matched = match_external(tracks, truth, skip_first_s)
    return accuracy_from_matched(matched if matched.height else pl.DataFrame(), cfg, "external")


def score_import(result: ImportResult) -> ImportResult:
    """The import with its external picture (CAT062) scored against its ADS-B truth (CAT021)."""
    if not (result.external_tracks.height and result.truth.height):
        return result
    return dataclasses.replace(result, external_metrics=external_metrics(result.external_tracks, result.truth))
