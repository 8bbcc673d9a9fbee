"""Conflict-prediction settings: the separation minima, the designated volumes with their own
treatment (final approaches, aerodrome zones) and :class:`ConflictConfig`, (5.15)–(5.17)
(docs/methods.md, "Conflict prediction (STCA)")."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from tertiary.core.distributions import chi2_ppf, norm_ppf
from tertiary.core.units import FT

__all__ = ["NM_M", "FT_M", "SEPARATION_MINIMA", "ApproachVolume", "AerodromeZone", "zone_index", "ConflictConfig",
           "STCA_CONFIRMATION"]

NM_M = 1852.0


FT_M = 0.3048


#: (horizontal, vertical) separation minima in metres per airspace class
SEPARATION_MINIMA: dict[str, tuple[float, float]] = {
    "terminal": (3.0 * NM_M, 1000.0 * FT_M),
    "en-route": (5.0 * NM_M, 1000.0 * FT_M),
}


@dataclass(frozen=True)
class ApproachVolume:
    """A final approach with its own STCA parameters (docs/methods.md "Final-approach volumes").

    Geometry in the system frame: the runway threshold (``threshold_x_m``, ``threshold_y_m``), the
    final approach course ``course_deg`` (true, the direction arrivals fly), the volume along the
    extended centreline from the threshold out to ``length_m``, ``half_width_m`` either side,
    below ``ceiling_m`` (height, the channel conflict prediction uses); a track is established
    on it when its ground track is within ``track_tolerance_deg`` of the course. Parameters of
    pairs established on it: ``dr_h_m`` (horizontal minimum; 2.5 NM, the reduced in-trail
    minimum on final of ICAO Doc 4444 §8.7.3.2) and ``t_thr_s`` (look-ahead).

    The defaults were measured on the default scenario (``aposteriori+imm_sym``, velocity-σ
    limit 50 m/s; nuisance / false alerts, 10 of 10 losses alerted in every case): no volume 92 / 8;
    (3 NM, 105 s) in the volume 92 / 8; (2.5 NM, 105 s) 48 / 4; (3 NM, 60 s) 13 / 2;
    (2.5 NM, 60 s) 7 / 2; (2.5 NM, 45 s) 7 / 2."""

    threshold_x_m: float
    threshold_y_m: float
    course_deg: float
    length_m: float = 40_000.0
    half_width_m: float = 1_000.0
    ceiling_m: float = 1_500.0
    track_tolerance_deg: float = 15.0
    dr_h_m: float = 2.5 * NM_M
    t_thr_s: float = 60.0
    name: str = "final"

    def __post_init__(self) -> None:
        vals = (self.threshold_x_m, self.threshold_y_m, self.course_deg, self.length_m, self.half_width_m,
                self.ceiling_m, self.track_tolerance_deg, self.dr_h_m, self.t_thr_s)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"approach volume {self.name!r}: every value must be finite")
        if min(self.length_m, self.half_width_m, self.dr_h_m, self.t_thr_s) <= 0:
            raise ValueError(f"approach volume {self.name!r}: length_m, half_width_m, dr_h_m and t_thr_s "
                             "must be positive")
        if not 0 < self.track_tolerance_deg < 90:
            raise ValueError(f"approach volume {self.name!r}: track_tolerance_deg must be in (0, 90), "
                             f"got {self.track_tolerance_deg}")

    def contains(self, pos: NDArray[np.float64], vel: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Rows (x, y, h) / (vx, vy, ḣ) established on this final."""
        c = math.radians(self.course_deg)
        ux, uy = math.sin(c), math.cos(c)                 # unit vector of the course (x east, y north)
        dx, dy = pos[:, 0] - self.threshold_x_m, pos[:, 1] - self.threshold_y_m
        to_go = -(dx * ux + dy * uy)                      # distance before the threshold along the course
        cross = np.abs(dx * uy - dy * ux)
        speed = np.hypot(vel[:, 0], vel[:, 1])
        along = (vel[:, 0] * ux + vel[:, 1] * uy) >= speed * math.cos(math.radians(self.track_tolerance_deg))
        return ((to_go >= 0.0) & (to_go <= self.length_m) & (cross <= self.half_width_m)
                & (pos[:, 2] <= self.ceiling_m) & along & (speed > 0.0))

    def parameters(self, cfg: "ConflictConfig") -> "ConflictConfig":
        """``cfg`` with this volume's minimum and look-ahead (and no volumes of its own)."""
        return dataclasses.replace(cfg, dr_h_m=self.dr_h_m, t_delays_s=(), t_man_s=self.t_thr_s, t_margin_s=0.0,
                                   approach_volumes=())


@dataclass(frozen=True)
class AerodromeZone:
    """An aerodrome's traffic zone, where STCA is inhibited (docs/methods.md "Aerodrome zones"):
    a cylinder around the aerodrome reference point (``x_m``, ``y_m``, system frame) of radius
    ``radius_m`` from the ground up to ``ceiling_m`` (height, the channel conflict prediction
    uses). Defaults: 4 NM and 2 000 ft — an aerodrome traffic zone is 2–2.5 NM, but the tower
    works arrivals from about 4 NM on final, where it releases departures ahead of them. Measured
    on the national scenario's 08:00 hour (losses of separation in the truth, zones at its 13
    airports, 2 000 ft): none 180, 2.5 NM 69, 4 NM 43, 5 NM 42 — the 26 between 2.5 and 4 NM are
    pairs within 5.5 km of the airport: a departure at lift-off with an arrival 4.6–5.5 km out, or
    a departure 4.5 km out on its climb with an arrival about to land or a departure behind it."""

    x_m: float
    y_m: float
    radius_m: float = 4.0 * NM_M
    ceiling_m: float = 2000.0 * FT_M
    name: str = "aerodrome"

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.x_m, self.y_m, self.radius_m, self.ceiling_m)):
            raise ValueError(f"aerodrome zone {self.name!r}: every value must be finite")
        if self.radius_m <= 0 or self.ceiling_m <= 0:
            raise ValueError(f"aerodrome zone {self.name!r}: radius_m and ceiling_m must be positive")

    def contains(self, pos: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Rows (x, y, h) inside the zone."""
        return (np.hypot(pos[:, 0] - self.x_m, pos[:, 1] - self.y_m) <= self.radius_m) & (pos[:, 2] <= self.ceiling_m)


def zone_index(pos: NDArray[np.float64], zones: Sequence[AerodromeZone]) -> NDArray[np.int64]:
    """Per row (x, y, h): the index of the first zone of ``zones`` that contains it, −1 for none."""
    out = np.full(len(pos), -1, np.int64)
    for k in range(len(zones) - 1, -1, -1):
        out[zones[k].contains(pos)] = k
    return out


@dataclass(frozen=True)
class ConflictConfig:
    """Conflict-prediction settings (5.15)–(5.17); docs/methods.md, "Conflict prediction (STCA)".

    * ``airspace`` / ``dr_h_m`` / ``dr_v_m``: separation minima Δr_г, Δr_в (explicit values win).
    * ``t_delays_s`` (detection, command transmission, execution), ``t_man_s``, ``t_margin_s``:
      T^пор = Σ t_i + t_ман + margin (5.17); defaults give 105 s.
    * ``confidence``: probability content of the covariance-based estimation term.
    * ``pilot_h_m``, ``pilot_h_rate_mps``, ``pilot_v_m``, ``pilot_v_rate_mps``: piloting error
      |ΔR_п(T)| = base + rate·T.
    * ``threshold_mode``: ``"covariance"`` (per pair, from the tracks) or ``"fixed"``
      (``fixed_est_h_m``, ``fixed_est_v_m``).
    * ``mode``: ``"seed"`` (faithful (5.14), negative T_min passes) or ``"corrected"``.
    * ``max_vel_sigma_mps``: tracks whose velocity standard deviation (sqrt of the larger of
      var(vx), var(vy) in ``cov``/``cov_diag``) exceeds this are *not established* (e.g. a
      target's first epochs, velocity still at its prior) and are left out of the prediction —
      no controller alert is raised on a tentative track, and a 300 m/s velocity sigma would
      otherwise give a ~90 km threshold. Applied in both threshold modes whenever a covariance
      column is present; None keeps every track. Default 25 m/s, chosen on the two scoring
      cases (default scenario with its final-approach volume, and adsb-paris; aposteriori /
      information + imm_sym): 50 m/s gave 2 / 4 and 35 / 30 false alerts, 25 m/s gives 1 / 3 and
      33 / 29 at the same losses alerted (10 of 10; 43 of 45) and median warning; 15 m/s (where
      the 95 % estimation term at 105 s, k_h·√2·σ·T, reaches the 3 NM minimum itself) gave
      1 / 2 and 27 / 24 but missed 4 and 3 more real losses on adsb-paris and cost 4–10 s of
      warning on the default scenario.
    * ``max_coast_s``: tracks coasting (no plot) for longer than this are left out
      (docs/methods.md "Established tracks"); needs a ``plot_target_id`` column, None keeps every track.
    * ``level_pair_tolerance_m`` / ``level_rate_mps``: the level-pair vertical threshold of the
      corrected rule (docs/methods.md "Level pairs"); None disables it.
    * ``use_selected_level`` / ``selected_level_tolerance_m``: corrected mode stops a climb or
      descent at the row's Mode S selected altitude when consistent with the motion
      (docs/methods.md "Selected level"; the tolerance, 100 ft, is how far on the wrong side the
      selected level may be — a level-off capture or overshoot — before it is ignored).
    * ``use_turn_rate`` / ``turn_rate_min_dps`` / ``max_turn_deg`` / ``turn_grid_s``: corrected
      mode predicts rows whose downlinked track-angle rate (``ehs_track_rate_dps``, BDS 5,0)
      is at least ``turn_rate_min_dps`` in magnitude along a constant-turn-rate arc, bounded at
      ``max_turn_deg`` of turn, and decides pairs with such a member on a time grid of step
      ``turn_grid_s`` (docs/methods.md "Turning aircraft"). Off by default: on the default
      scenario it added one false alert per picture (aposteriori+imm_sym 8 → 9, information+imm_sym
      10 → 11) — a partner's later turn at a merge point cannot be known from its turn rate now.
    * ``v_max_mps``: speed bound of the KD-tree bulk radius (None: from the data); it only
      affects speed, never the result.
    * ``eps_mps``: |v| below this counts as parallel motion (R_min = |r|, T_min = ∞).
    * ``confirm_m`` / ``confirm_n``: an alert is raised only when the condition held on m of the
      pair's last n picture epochs (:mod:`safety.confirmation`; 1/1: every raw condition alerts,
      the seed's behaviour, the default here). The pipeline's default is 3 of 4
      (:data:`STCA_CONFIRMATION`): on the default scenario it removed more than half of the
      false alerts of 1/1 for 8 s of median warning (``benchmarks/safety_thresholds.py``).
      The unconfirmed condition is kept as ``raw_alert``.
    * ``same_identity_is_duplicate``: two tracks with the same Mode S address (column
      ``mode_s``) are one aircraft tracked twice, not a pair in conflict: they never alert
      (their rows are kept, with ``alert`` false).
    * ``near_margin_h_m`` / ``near_margin_v_m`` (1 NM / 300 ft): a pair is *near* when the
      same-time rule holds with both thresholds widened by these margins (column ``near``;
      :func:`slim_conflicts` keeps alert or near rows); the output set is screened with the
      widened thresholds.
    * ``approach_volumes``: final approaches whose established pairs are decided with their own
      minimum and look-ahead (:class:`ApproachVolume`, corrected mode; docs/methods.md
      "Final-approach volumes"). The pipeline fills them from the scenario's runways.
    * ``enroute_above_m`` / ``enroute_h_m`` / ``enroute_v_m``: en-route airspace from a floor up
      (height, the channel conflict prediction uses): the configured (terminal) minima decide
      the pairs whose two tracks are both below ``enroute_above_m``, the en-route minima (5 NM /
      1 000 ft) every other pair (docs/methods.md "En-route airspace"); the loss-of-separation
      scoring of :mod:`safety.alerts` applies the same minima to the truth. None (the default):
      one set of minima everywhere.
    * ``aerodrome_zones``: aerodrome traffic zones (:class:`AerodromeZone`): a pair whose two
      tracks are both in one zone is not predicted (STCA inhibition), and the scoring of
      :mod:`safety.alerts` counts no loss of separation between two aircraft both in one zone
      (docs/methods.md "Aerodrome zones"). The pipeline fills them from the scenario's airports.
    """

    airspace: Literal["terminal", "en-route"] = "terminal"
    dr_h_m: float | None = None
    dr_v_m: float | None = None
    t_delays_s: tuple[float, ...] = (10.0, 20.0, 15.0)
    t_man_s: float = 60.0
    t_margin_s: float = 0.0
    confidence: float = 0.95
    pilot_h_m: float = 500.0
    pilot_h_rate_mps: float = 0.0
    pilot_v_m: float = 60.0
    pilot_v_rate_mps: float = 0.0
    threshold_mode: Literal["covariance", "fixed"] = "covariance"
    fixed_est_h_m: float = 300.0
    fixed_est_v_m: float = 50.0
    mode: Literal["seed", "corrected"] = "corrected"
    max_vel_sigma_mps: float | None = 25.0
    max_coast_s: float | None = 10.0
    level_pair_tolerance_m: float | None = 100.0 * FT_M
    level_rate_mps: float = 1.0
    use_selected_level: bool = True
    selected_level_tolerance_m: float = 100.0 * FT_M
    use_turn_rate: bool = False
    turn_rate_min_dps: float = 0.5
    max_turn_deg: float = 30.0
    turn_grid_s: float = 0.5
    confirm_m: int = 1
    confirm_n: int = 1
    same_identity_is_duplicate: bool = True
    near_margin_h_m: float = NM_M
    near_margin_v_m: float = 300.0 * FT_M
    v_max_mps: float | None = None
    eps_mps: float = 1e-6
    bulk_quantile: float = 0.99
    chunk_pairs: int = 1 << 18
    block_points: int = 20_000
    approach_volumes: tuple[ApproachVolume, ...] = ()
    enroute_above_m: float | None = None
    enroute_h_m: float = SEPARATION_MINIMA["en-route"][0]
    enroute_v_m: float = SEPARATION_MINIMA["en-route"][1]
    aerodrome_zones: tuple[AerodromeZone, ...] = ()

    def __post_init__(self) -> None:
        if not all(isinstance(z, AerodromeZone) for z in self.aerodrome_zones):
            raise ValueError("aerodrome_zones must be AerodromeZone instances")
        if self.enroute_above_m is not None and not math.isfinite(self.enroute_above_m):
            raise ValueError(f"enroute_above_m must be finite or None, got {self.enroute_above_m}")
        if not (self.enroute_h_m > 0 and self.enroute_v_m > 0):
            raise ValueError(f"enroute_h_m and enroute_v_m must be positive, got {self.enroute_h_m}, "
                             f"{self.enroute_v_m}")
        if not all(isinstance(v, ApproachVolume) for v in self.approach_volumes):
            raise ValueError("approach_volumes must be ApproachVolume instances")
        if self.airspace not in SEPARATION_MINIMA:
            raise ValueError(f"airspace must be one of {list(SEPARATION_MINIMA)}, got {self.airspace!r}")
        if self.mode not in ("seed", "corrected"):
            raise ValueError(f"mode must be 'seed' or 'corrected', got {self.mode!r}")
        if self.threshold_mode not in ("covariance", "fixed"):
            raise ValueError(f"threshold_mode must be 'covariance' or 'fixed', got {self.threshold_mode!r}")
        if not 1 <= self.confirm_m <= self.confirm_n <= 63:
            raise ValueError(f"alert confirmation needs 1 <= confirm_m <= confirm_n <= 63, "
                             f"got {self.confirm_m} of {self.confirm_n}")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence}")
        if self.t_thr_s <= 0:
            raise ValueError(f"the look-ahead T^пор must be positive, got {self.t_thr_s}")
        for name in ("dr_h_m", "dr_v_m"):
            val = getattr(self, name)
            if val is not None and val <= 0:
                raise ValueError(f"{name} must be positive, got {val}")
        for name in ("pilot_h_m", "pilot_v_m", "fixed_est_h_m", "fixed_est_v_m", "eps_mps",
                     "pilot_h_rate_mps", "pilot_v_rate_mps", "near_margin_h_m", "near_margin_v_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.max_vel_sigma_mps is not None and self.max_vel_sigma_mps <= 0:
            raise ValueError(f"max_vel_sigma_mps must be positive, got {self.max_vel_sigma_mps}")
        if self.max_coast_s is not None and self.max_coast_s < 0:
            raise ValueError(f"max_coast_s must be >= 0, got {self.max_coast_s}")
        if self.level_pair_tolerance_m is not None and self.level_pair_tolerance_m < 0:
            raise ValueError(f"level_pair_tolerance_m must be >= 0, got {self.level_pair_tolerance_m}")
        if not self.selected_level_tolerance_m >= 0:
            raise ValueError(f"selected_level_tolerance_m must be >= 0, got {self.selected_level_tolerance_m}")
        if not (self.turn_rate_min_dps > 0 and 0 < self.max_turn_deg <= 360 and 0 < self.turn_grid_s <= 10):
            raise ValueError("turn prediction needs turn_rate_min_dps > 0, 0 < max_turn_deg <= 360 and "
                             f"0 < turn_grid_s <= 10 s, got {self.turn_rate_min_dps}, {self.max_turn_deg}, "
                             f"{self.turn_grid_s}")
        if not self.level_rate_mps >= 0:
            raise ValueError(f"level_rate_mps must be >= 0, got {self.level_rate_mps}")
        if self.v_max_mps is not None and self.v_max_mps <= 0:
            raise ValueError(f"v_max_mps must be positive, got {self.v_max_mps}")
        if self.chunk_pairs < 1 or self.block_points < 2:
            raise ValueError("chunk_pairs must be >= 1 and block_points >= 2")
        if not 0.0 < self.bulk_quantile <= 1.0:
            raise ValueError(f"bulk_quantile must be in (0, 1], got {self.bulk_quantile}")

    # ---- derived quantities
    @property
    def sep_h_m(self) -> float:
        """Horizontal separation minimum Δr_г (m)."""
        return float(self.dr_h_m) if self.dr_h_m is not None else SEPARATION_MINIMA[self.airspace][0]

    @property
    def sep_v_m(self) -> float:
        """Vertical separation minimum Δr_в (m)."""
        return float(self.dr_v_m) if self.dr_v_m is not None else SEPARATION_MINIMA[self.airspace][1]

    def enroute(self) -> "ConflictConfig":
        """This configuration with the en-route minima and no en-route floor of its own: what
        decides every pair of tracks but those both below ``enroute_above_m``."""
        return dataclasses.replace(self, dr_h_m=self.enroute_h_m, dr_v_m=self.enroute_v_m, enroute_above_m=None)

    @property
    def t_thr_s(self) -> float:
        """Look-ahead T^пор = Σ t_i + t_ман (+ margin), (5.17)."""
        return float(sum(self.t_delays_s)) + self.t_man_s + self.t_margin_s

    @property
    def k_h(self) -> float:
        """Horizontal confidence factor sqrt(χ²₂⁻¹(confidence))."""
        return float(math.sqrt(chi2_ppf(self.confidence, 2)))

    @property
    def k_v(self) -> float:
        """Vertical confidence factor Φ⁻¹((1 + confidence)/2)."""
        return float(norm_ppf(0.5 * (1.0 + self.confidence)))

    @property
    def pilot_h_at_t(self) -> float:
        """|ΔR_гп(T^пор)| (m)."""
        return self.pilot_h_m + self.pilot_h_rate_mps * self.t_thr_s

    @property
    def pilot_v_at_t(self) -> float:
        """|ΔR_вп(T^пор)| (m)."""
        return self.pilot_v_m + self.pilot_v_rate_mps * self.t_thr_s

    @property
    def window_s(self) -> tuple[float, float]:
        """Screening window W: [0, T] (corrected) or [−T, T] (seed)."""
        t = self.t_thr_s
        return (0.0, t) if self.mode == "corrected" else (-t, t)


#: the pipeline's alert confirmation (confirm_m, confirm_n): 3 of the last 4 picture epochs
STCA_CONFIRMATION = (3, 4)
