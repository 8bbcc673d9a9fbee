"""STCA performance against what really happened, the last step of the safety evaluation: it
reads the ``conflicts`` of :mod:`safety.conflicts`, the matcher's id map and the truth, and
gives losses of separation in the truth (:mod:`.separation`), alert episodes per pair of
aircraft classified genuine / nuisance / undetermined / false with the STCA metrics per picture
(:mod:`.episodes`), which of them the picture causes (:mod:`.attribution`), another system's
alert list scored the same way (:mod:`.external`), and trade-off curves of the threshold settings (:mod:`.tradeoff`);
options in :class:`AlertConfig` (:mod:`.config`).
"""

from safety.alerts.attribution import (ATTRIBUTION_METRICS, TRUTH_PICTURE, attribute_alerts, attribute_los,
                                       attribution_metrics, manoeuvre_onsets, valid_alerts)
from safety.alerts.config import AlertConfig
from safety.alerts.episodes import (ALERT_METRICS, ALERTS_SCHEMA, LOS_SCHEMA, SCORED_CONFLICT_COLUMNS, alert_episodes,
                                    alert_ids, block_id_rows, id_rows, los_episodes, observed_until, score_alerts,
                                    scored_conflicts, scored_ids, stca_tables, stca_tables_by_picture)
from safety.alerts.external import EXTERNAL_METRICS, EXTERNAL_PREFIX, identify_aircraft, score_external
from safety.alerts.separation import (loss_of_separation, merge_intervals, merge_pair_intervals, separation_intervals,
                                      truth_ends, truth_heights, truth_intervals, truth_span)
from safety.alerts.tradeoff import compare_at_equal_nuisance, stca_tradeoff, tradeoff_metrics

__all__ = [
    "AlertConfig", "ALERT_METRICS", "ALERTS_SCHEMA", "LOS_SCHEMA", "truth_heights", "truth_ends", "truth_span",
    "observed_until", "separation_intervals", "loss_of_separation", "truth_intervals", "merge_intervals",
    "merge_pair_intervals", "alert_episodes",
    "los_episodes", "score_alerts", "SCORED_CONFLICT_COLUMNS", "scored_conflicts", "scored_ids", "alert_ids",
    "id_rows", "block_id_rows", "stca_tables", "stca_tables_by_picture", "stca_tradeoff",
    "compare_at_equal_nuisance", "tradeoff_metrics", "ATTRIBUTION_METRICS", "TRUTH_PICTURE", "attribute_alerts",
    "attribute_los", "attribution_metrics", "manoeuvre_onsets", "valid_alerts", "EXTERNAL_METRICS", "EXTERNAL_PREFIX",
    "identify_aircraft", "score_external",
]
