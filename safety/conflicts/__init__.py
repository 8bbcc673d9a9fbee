"""Short-term conflict prediction (STCA) with accuracy-aware thresholds, monograph §5.2
(5.1)–(5.17): the stage of the safety evaluation that reads an air picture's tracks (their
heights and covariances) and gives the ``conflicts`` table that :mod:`safety.alerts` scores. The
method is described in docs/methods.md, "Conflict prediction (STCA)". Modules: :mod:`.config`
(settings and designated volumes), :mod:`.geometry` (vertical channel, closest approach,
same-time intervals), :mod:`.turns` (turning aircraft), :mod:`.thresholds` (5.15)–(5.17),
:mod:`.screen` (KD-tree candidate pairs), :mod:`.pairs` (the decision of screened pairs),
:mod:`.airspace` (final approaches, en-route airspace, aerodrome zones) and :mod:`.step` (the
windowed stage, :func:`predict_conflicts`).
"""

from safety.conflicts.airspace import approach_membership
from safety.conflicts.config import (FT_M, NM_M, SEPARATION_MINIMA, STCA_CONFIRMATION, AerodromeZone, ApproachVolume,
                                     ConflictConfig, zone_index)
from safety.conflicts.geometry import (ALT_COLUMNS, PairGeometry, conflict_interval, conflict_interval_levelled,
                                       height_and_rate, level_off_times, pair_geometry, tangent_plane_error_bound,
                                       vertical_state)
from safety.conflicts.pairs import CONFLICT_EXTRA
from safety.conflicts.screen import conflict_candidates
from safety.conflicts.step import (T_MAX_US, T_MIN_US, ConflictState, conflicts_step, conflicts_steps,
                                   init_conflict_state, predict_conflicts, slim_conflicts)
from safety.conflicts.thresholds import pair_thresholds, threshold_time
from safety.conflicts.turns import arc_offsets, conflict_interval_arc, turn_rates
from tertiary.contract import SELECTED_ALT_COLUMN, TURN_RATE_COLUMN

__all__ = [
    "NM_M", "FT_M", "SEPARATION_MINIMA", "STCA_CONFIRMATION", "ConflictConfig", "ApproachVolume", "AerodromeZone",
    "zone_index", "approach_membership", "PairGeometry", "pair_geometry", "pair_thresholds", "conflict_candidates",
    "predict_conflicts", "conflict_interval", "conflict_interval_levelled", "level_off_times", "arc_offsets",
    "conflict_interval_arc", "turn_rates", "TURN_RATE_COLUMN", "SELECTED_ALT_COLUMN", "vertical_state",
    "height_and_rate", "slim_conflicts", "ALT_COLUMNS", "CONFLICT_EXTRA", "tangent_plane_error_bound",
    "threshold_time", "ConflictState", "init_conflict_state", "conflicts_step", "conflicts_steps", "T_MIN_US",
    "T_MAX_US",
]
