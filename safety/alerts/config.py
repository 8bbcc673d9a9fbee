"""Options of the STCA scoring (:class:`AlertConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from safety.conflicts import ConflictConfig
from tertiary.core.units import FT

__all__ = ["AlertConfig"]

@dataclass(frozen=True)
class AlertConfig:
    """Scoring options (:mod:`safety.alerts.separation`, :mod:`safety.alerts.episodes`).

    * ``conflict``: the prediction settings of the picture (minima Δr_г, Δr_в and T^пор).
    * ``proximity_factor``: a nuisance alert's pair came within this × both minima (1.5).
    * ``merge_gap_s``: alert epochs of one pair at most this far apart belong to one episode
      (the dropout is flicker); likewise the truth's loss (and proximity) intervals of a pair.
    * ``link_s``: how long after an alert episode ends a LoS still makes it genuine / alerted
      (None: T^пор).
    * ``link_to_cpa``: the link window also reaches the closest approach each alert epoch
      predicted (its ``t_min_s``), at most ``max_link_s`` (None: 2 T^пор) after that epoch: an
      alert raised when the pair enters the (uncertainty-widened) threshold within T^пор is about
      the encounter it predicted, which can come after T^пор (:mod:`safety.alerts.episodes`). False: the
      fixed window only.
    * ``max_grid_rows``: bound of the resampled truth rows held at once (aircraft × union sample
      times of a block of them; :func:`resampled_blocks`).
    * ``level_pairs``: the truth's losses and proximities use the prediction's level-pair
      threshold (``conflict.level_pair_tolerance_m`` / ``level_rate_mps``) where both aircraft
      are level (:mod:`safety.alerts.separation`, "Level pairs"); False: the full vertical minimum everywhere.
    * ``landed_below_m``: an aircraft whose truth ends below this height (2 000 ft, the aerodrome
      zones' ceiling) has landed; one whose truth ends above it left the recording airborne (it
      flew out of the recorded area, or the recording stopped), and what it did next is not
      observed. An alert whose link window reaches past that end, or past the end of the run's
      truth, with nothing close before, is **undetermined**, not false
      (:mod:`safety.alerts.episodes`).
    """

    conflict: ConflictConfig = ConflictConfig()
    proximity_factor: float = 1.5
    merge_gap_s: float = 15.0
    link_s: float | None = None
    link_to_cpa: bool = True
    max_link_s: float | None = None
    max_grid_rows: int = 50_000_000
    level_pairs: bool = True
    landed_below_m: float = 2000.0 * FT

    def __post_init__(self) -> None:
        if not self.proximity_factor >= 1.0:
            raise ValueError(f"proximity_factor must be >= 1, got {self.proximity_factor}")
        if self.merge_gap_s < 0:
            raise ValueError(f"merge_gap_s must be >= 0, got {self.merge_gap_s}")
        if self.link_s is not None and self.link_s < 0:
            raise ValueError(f"link_s must be >= 0, got {self.link_s}")
        if self.max_link_s is not None and self.max_link_s < 0:
            raise ValueError(f"max_link_s must be >= 0, got {self.max_link_s}")
        if not math.isfinite(self.landed_below_m):
            raise ValueError(f"landed_below_m must be finite, got {self.landed_below_m}")
        if self.max_grid_rows < 1:
            raise ValueError(f"max_grid_rows must be >= 1, got {self.max_grid_rows}")

    @property
    def link(self) -> float:
        return self.conflict.t_thr_s if self.link_s is None else float(self.link_s)

    @property
    def truth_level_pairs(self) -> tuple[float, float] | None:
        """(tolerance m, level rate m/s) of the truth's level pairs, None when off."""
        tol = self.conflict.level_pair_tolerance_m
        return None if not self.level_pairs or tol is None else (float(tol), float(self.conflict.level_rate_mps))

    @property
    def cpa_reach(self) -> float:
        """How far after an alert epoch its predicted closest approach can extend the link
        window (0 without ``link_to_cpa``)."""
        if not self.link_to_cpa:
            return 0.0
        return 2.0 * self.conflict.t_thr_s if self.max_link_s is None else float(self.max_link_s)
