"""Safety evaluation of the merged air picture: conflict prediction with accuracy-aware
thresholds, STCA performance against real losses of separation and accuracy-versus-capacity
(monograph chapter 5).

* :mod:`safety.conflicts` — (5.1)–(5.17) on height (never ENU z): :func:`predict_conflicts`
  (KD-tree candidates, ``mode="seed"`` (5.14) as printed / ``"corrected"`` same-time rule,
  thresholds from the tracks' covariances at clip(T_min, 0, T) or fixed),
  :func:`conflict_interval`, with heights stopped at the Mode S selected level
  :func:`conflict_interval_levelled` / :func:`level_off_times`, along turns (optional)
  :func:`arc_offsets` / :func:`conflict_interval_arc`, :func:`height_and_rate`, :func:`slim_conflicts`,
  :func:`tangent_plane_error_bound`, :func:`pair_geometry`; final-approach volumes with their own
  minimum and look-ahead :class:`ApproachVolume` / :func:`approach_membership`; aerodrome
  traffic zones where STCA is inhibited :class:`AerodromeZone` / :func:`zone_index`.
* :mod:`safety.alerts` — losses of separation in the truth (closed form between samples),
  alert episodes per pair of aircraft classified genuine / nuisance / false
  (:func:`alert_episodes`, the ``alerts`` table), :func:`score_alerts` (STCA metrics per
  picture), trade-off curves :func:`stca_tradeoff` / :func:`compare_at_equal_nuisance`.
* :mod:`safety.capacity` — (5.18)–(5.21) as printed (``*_seed``) and a sounder probabilistic
  model (``*_sound``), curves for figs. 5.2/5.3 and :func:`capacity_from_metrics`.
"""

from safety.alerts import (ALERT_METRICS, ALERTS_SCHEMA, LOS_SCHEMA, AlertConfig, alert_episodes,
                           compare_at_equal_nuisance, loss_of_separation, los_episodes, score_alerts,
                           separation_intervals, stca_tables, stca_tables_by_picture, stca_tradeoff, tradeoff_metrics,
                           truth_heights, truth_intervals)
from safety.capacity import (V_BC_M3, V_ZO_M3, SeedRisk, capacity_curve, capacity_from_metrics,
                             conflict_radius, nmax_seed, nmax_sound, p_np, p_pij, ppob_curves, ppob_seed,
                             ppob_sound, rate_per_hour, v_ob)
from safety.conflicts import (ALT_COLUMNS, CONFLICT_EXTRA, FT_M, NM_M, SEPARATION_MINIMA, AerodromeZone, ApproachVolume,
                              ConflictConfig, PairGeometry, approach_membership, candidate_pairs, conflict_interval,
                              height_and_rate, pair_geometry, pair_thresholds, zone_index,
                              predict_conflicts, slim_conflicts, tangent_plane_error_bound, vertical_state,
                              ConflictState, conflicts_step, init_conflict_state, conflict_interval_levelled,
                              level_off_times, arc_offsets, conflict_interval_arc)

__all__ = [
    # conflicts
    "ConflictConfig", "PairGeometry", "predict_conflicts", "pair_geometry", "pair_thresholds",
    "candidate_pairs", "conflict_interval", "height_and_rate", "vertical_state", "slim_conflicts",
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
