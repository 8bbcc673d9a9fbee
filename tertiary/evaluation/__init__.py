"""Evaluation of any air picture against a reference: matching to truth, accuracy, consistency and
surveillance metrics, indicators, radar evaluation, the posterior Cramér–Rao bound, and the
requirements judged from the metrics."""

from tertiary.evaluation.accuracy import (AccuracyConfig, accuracy_by_epoch_from_matched, accuracy_from_matched,
                                          continuity_metrics, picture_accuracy, row_scores, scored_rows)
from tertiary.evaluation.accuracy_buckets import picture_accuracy_buckets
from tertiary.evaluation.consistency import add_nees, chi2_band, consistency_metrics, integrated_autocorrelation
from tertiary.evaluation.picture_buckets import picture_metrics_buckets
from tertiary.evaluation.picture_metrics import MetricsConfig, picture_metrics

__all__ = ["AccuracyConfig", "accuracy_by_epoch_from_matched", "accuracy_from_matched", "continuity_metrics",
           "picture_accuracy", "row_scores", "scored_rows", "picture_accuracy_buckets", "add_nees", "chi2_band",
           "consistency_metrics", "integrated_autocorrelation", "picture_metrics_buckets", "MetricsConfig",
           "picture_metrics"]
