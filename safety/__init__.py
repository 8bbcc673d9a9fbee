"""Safety evaluation of the merged air picture (monograph chapter 5), the last stage after the
pictures are built and matched: conflict prediction with accuracy-aware thresholds
(:mod:`safety.conflicts`, (5.1)–(5.17); method in docs/methods.md, "Conflict prediction
(STCA)"), m-of-n alert confirmation (:mod:`safety.confirmation`), STCA performance against the
truth's losses of separation with trade-off curves (:mod:`safety.alerts`), and accuracy versus
capacity (:mod:`safety.capacity`, (5.18)–(5.21)). It builds on :mod:`tertiary.core` and
:mod:`tertiary.contract` only.
"""

from safety.alerts import (ALERT_METRICS, ALERTS_SCHEMA, LOS_SCHEMA, AlertConfig, alert_episodes,
                           compare_at_equal_nuisance, loss_of_separation, los_episodes, score_alerts,
                           separation_intervals, stca_tables, stca_tables_by_picture, stca_tradeoff, tradeoff_metrics,
                           truth_heights, truth_intervals)
from safety.capacity import (V_BC_M3, V_ZO_M3, SeedRisk, capacity_curve, capacity_from_metrics,
                             conflict_radius, nmax_seed, nmax_sound, p_np, p_pij, ppob_curves, ppob_seed,
                             ppob_sound, rate_per_hour, v_ob)
from safety.conflicts import (ALT_COLUMNS, CONFLICT_EXTRA, FT_M, NM_M, SEPARATION_MINIMA, AerodromeZone, ApproachVolume,
                              ConflictConfig, ConflictState, PairGeometry, approach_membership, arc_offsets,
                              conflict_candidates, conflict_interval, conflict_interval_arc, conflict_interval_levelled,
                              conflicts_step, height_and_rate, init_conflict_state, level_off_times, pair_geometry,
                              pair_thresholds, predict_conflicts, slim_conflicts, tangent_plane_error_bound,
                              vertical_state, zone_index)

__all__ = [
    # conflicts
    "ConflictConfig", "PairGeometry", "predict_conflicts", "pair_geometry", "pair_thresholds",
    "conflict_candidates", "conflict_interval", "height_and_rate", "vertical_state", "slim_conflicts",
    "tangent_plane_error_bound", "SEPARATION_MINIMA", "NM_M", "FT_M", "ALT_COLUMNS", "CONFLICT_EXTRA",
    "ConflictState", "conflicts_step", "init_conflict_state", "conflict_interval_levelled", "level_off_times",
    "arc_offsets", "conflict_interval_arc", "ApproachVolume", "approach_membership",
    "AerodromeZone", "zone_index",
    # alerts
    "AlertConfig", "score_alerts", "alert_episodes", "los_episodes", "loss_of_separation", "separation_intervals",
    "truth_heights", "truth_intervals", "stca_tables", "stca_tables_by_picture", "stca_tradeoff",
    "compare_at_equal_nuisance", "tradeoff_metrics",
    "ALERT_METRICS", "ALERTS_SCHEMA", "LOS_SCHEMA",
    # capacity
    "SeedRisk", "v_ob", "p_pij", "p_np", "ppob_seed", "nmax_seed", "conflict_radius", "ppob_sound",
    "nmax_sound", "rate_per_hour", "ppob_curves", "capacity_curve", "capacity_from_metrics",
    "V_BC_M3", "V_ZO_M3",
]
