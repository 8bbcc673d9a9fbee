"""Safety evaluation of the merged air picture: conflict prediction with accuracy-aware
thresholds, alert scoring and accuracy-versus-capacity (monograph chapter 5).

* :mod:`safety.conflicts` — (5.1)–(5.17): :func:`predict_conflicts` (KD-tree candidates,
  ``mode="seed"`` faithful / ``"corrected"`` sounder rule, thresholds from the tracks'
  covariances or fixed), :func:`pair_geometry`.
* :mod:`safety.alerts` — :func:`score_alerts` / :func:`alert_episodes`: hits, misses, false
  alerts, warning time and flicker against truth (zero-error prediction rule or actual loss of
  separation).
* :mod:`safety.capacity` — (5.18)–(5.21) as printed (``*_seed``) and a sounder probabilistic
  model (``*_sound``), curves for figs. 5.2/5.3 and :func:`capacity_from_metrics`.
"""

from safety.alerts import (ALERT_METRICS, AlertConfig, alert_episodes, loss_of_separation, score_alerts,
                           true_conflicts, truth_at)
from safety.capacity import (V_BC_M3, V_ZO_M3, SeedRisk, capacity_curve, capacity_from_metrics,
                             conflict_radius, nmax_seed, nmax_sound, p_np, p_pij, ppob_curves, ppob_seed,
                             ppob_sound, rate_per_hour, v_ob)
from safety.conflicts import (FT_M, NM_M, SEPARATION_MINIMA, ConflictConfig, PairGeometry, candidate_pairs,
                              pair_geometry, pair_thresholds, predict_conflicts)

__all__ = [
    # conflicts
    "ConflictConfig", "PairGeometry", "predict_conflicts", "pair_geometry", "pair_thresholds",
    "candidate_pairs", "SEPARATION_MINIMA", "NM_M", "FT_M",
    # alerts
    "AlertConfig", "score_alerts", "alert_episodes", "true_conflicts", "loss_of_separation", "truth_at",
    "ALERT_METRICS",
    # capacity
    "SeedRisk", "v_ob", "p_pij", "p_np", "ppob_seed", "nmax_seed", "conflict_radius", "ppob_sound",
    "nmax_sound", "rate_per_hour", "ppob_curves", "capacity_curve", "capacity_from_metrics",
    "V_BC_M3", "V_ZO_M3",
]
