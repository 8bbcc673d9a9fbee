"""The secondary tracker's options (:class:`TrackerConfig`) and its output columns."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import polars as pl

from tertiary.contract import TABLES
from tertiary.core.units import FT
from tertiary.stages.tracking.altitude import ALT_COLUMNS, AltitudeConfig

__all__ = ["STATUS", "TRACK_COLUMNS", "TrackerConfig"]

#: a track row's status (tentative tracks are not emitted)
STATUS = ("tentative", "confirmed", "coasting")

#: the ``tracks`` table columns plus the tracker's extra columns
TRACK_COLUMNS: dict[str, pl.DataType] = {
    **TABLES["tracks"].required,
    **{c: TABLES["tracks"].optional[c] for c in ALT_COLUMNS},
    "cov": TABLES["tracks"].optional["cov"],
    "status": pl.String(),
    "plot_target_id": pl.UInt64(),
}


@dataclass(frozen=True)
class TrackerConfig:
    """Track management options (the rules: :mod:`tertiary.stages.tracking.tracker`).

    * ``initiation``: ``"three_scan"`` (annulus S₁ then circle S₂) or ``"m_of_n"``.
    * ``v_min_mps``, ``v_max_mps``: annulus radii R_min = v_min·T, R_max = v_max·T (1.1).
    * ``confirm_gate_m``: radius of the scan-3 circle S₂.
    * ``m``, ``n``: M-of-N confirmation (``m`` plots within the first ``n`` scans).
    * ``gate_sigma``, ``gate_min_m``: tracking gate half-width per axis
      gate_sigma·sqrt(P⁻_ii + r_i) + gate_min_m.
    * ``assignment``: ``"hungarian"`` (global, per ambiguous gate component) or ``"nearest"``.
    * ``max_misses``: a track is deleted at this many consecutive epochs without a plot.
    * ``initiation_gap_s`` (``"three_scan"``): a tentative or a scan-2 hypothesis waits this long
      after its last measured plot for the next (the fused rows between a radar's scans are
      extrapolations, which the test does not count); default two scans of a 12 s en-route radar.
    * ``use_mode_s``: a track, tentative or initiation hypothesis holds the Mode S address of the
      plots it took and never takes a plot with another address (a plot or object without one
      is gated on position).
    * ``alt_gate_m``: a plot whose barometric altitude lies further than gate_sigma·σ +
      ``alt_gate_m`` from an object's predicted altitude (its altitude filter, σ of both) is not
      in its gates, and within them the altitude's d²/S adds to the assignment cost; None: the
      altitude is not used in association. Default 500 ft, half the 1 000 ft between adjacent
      flight levels: the gate never reaches the aircraft one level above or below.
    * ``use_turn_rate``: a plot's downlinked turn rate (Mode S BDS 5,0 track-angle rate) is
      handed to the filter after its position update
      (:meth:`tertiary.filters.base.TrackFilter.observe_turn_rate`).
    * ``use_velocity``: a plot's downlinked ground velocity (Mode S BDS 5,0 ground speed and
      true track, in the system frame: the fused ``meas_vx_mps``, ``meas_vy_mps``) is handed to
      the filter after its position update
      (:meth:`tertiary.filters.base.TrackFilter.observe_velocity`), and to a new track's filter
      at its first plot. Its covariance: ``velocity_speed_sigma_mps`` along the track;
      across it the track angle's error ``velocity_track_sigma_deg`` at the ground speed, and the
      turn the aircraft makes while its register may be ``velocity_refresh_s`` older than the
      plot (uniform age: (ω v)² τ²/3). A velocity whose NIS against the track's estimate exceeds
      ``velocity_gate`` (χ², 2 degrees of freedom) is not used; the gate's covariance adds
      (a Δt)² per axis, a = ``velocity_accel_mps2`` (a 30° banked turn) over the Δt since the
      track's previous update, so that a manoeuvre's onset, which the track cannot yet know,
      is not refused.
    * ``use_vertical_rate``: a plot's downlinked vertical rate (Mode S BDS 6,0, the fused
      ``meas_vrate_mps``) updates the altitude filter's rate after the plot's vertical channel,
      with σ ``vertical_rate_sigma_mps`` (the register's noise and LSB, and the rate's change
      over the plot's age at a level-off), unless its NIS exceeds ``vertical_rate_gate`` (χ², 1
      degree of freedom; the gate's variance adds (a Δt)², a = ``vertical_accel_mps2``, for the
      onset of a climb or a level-off).
    * ``calibrate_downlinks``: the σ of the downlinked ground speed, true track and vertical
      rate above (and of the altitude channels' rate) are measured from the recording's replies
      before the first window (:mod:`tertiary.stages.tracking.downlinks`); False: as configured.
      Off by default: with the measured σ the tracks' position covariance becomes optimistic,
      because the fused plots' errors are correlated over scans and the filters take them as
      white (docs/methods.md). ``measured_downlinks`` says what was measured (empty: nothing).
    * ``altitude``: the vertical-channel filter (q_a of (A1)).
    """

    initiation: Literal["three_scan", "m_of_n"] = "three_scan"
    v_min_mps: float = 30.0
    v_max_mps: float = 350.0
    confirm_gate_m: float = 1500.0
    m: int = 3
    n: int = 4
    gate_sigma: float = 4.0
    gate_min_m: float = 500.0
    assignment: Literal["nearest", "hungarian"] = "hungarian"
    max_misses: int = 3
    initiation_gap_s: float = 25.0
    use_mode_s: bool = True
    alt_gate_m: float | None = 500.0 * FT
    use_turn_rate: bool = True
    use_velocity: bool = True
    velocity_speed_sigma_mps: float = 1.0
    velocity_track_sigma_deg: float = 0.5
    velocity_refresh_s: float = 1.0
    velocity_gate: float = 13.82
    velocity_accel_mps2: float = 6.0
    use_vertical_rate: bool = True
    vertical_rate_sigma_mps: float = 1.0
    vertical_rate_gate: float = 10.83
    vertical_accel_mps2: float = 2.0
    calibrate_downlinks: bool = False
    measured_downlinks: str = ""
    altitude: AltitudeConfig = AltitudeConfig()

    def __post_init__(self) -> None:
        if self.initiation not in ("three_scan", "m_of_n"):
            raise ValueError(f"initiation must be 'three_scan' or 'm_of_n', got {self.initiation!r}")
        if self.assignment not in ("nearest", "hungarian"):
            raise ValueError(f"assignment must be 'nearest' or 'hungarian', got {self.assignment!r}")
        if not 0 <= self.v_min_mps < self.v_max_mps:
            raise ValueError(f"need 0 <= v_min_mps < v_max_mps, got {self.v_min_mps}, {self.v_max_mps}")
        if not 1 <= self.m <= self.n:
            raise ValueError(f"need 1 <= m <= n, got m={self.m}, n={self.n}")
        if self.max_misses < 1:
            raise ValueError(f"max_misses must be >= 1, got {self.max_misses}")
        if not self.initiation_gap_s > 0:                                    # NaN fails too
            raise ValueError(f"initiation_gap_s must be > 0, got {self.initiation_gap_s}")
        if self.alt_gate_m is not None and not self.alt_gate_m >= 0:          # NaN fails too
            raise ValueError(f"alt_gate_m must be >= 0 or None, got {self.alt_gate_m}")
        if not (self.velocity_speed_sigma_mps > 0 and self.velocity_track_sigma_deg > 0
                and self.velocity_refresh_s >= 0 and self.velocity_gate > 0):       # NaN fails too
            raise ValueError("velocity_speed_sigma_mps, velocity_track_sigma_deg and velocity_gate must be > 0, "
                             "velocity_refresh_s >= 0")
        if not (self.vertical_rate_sigma_mps > 0 and self.vertical_rate_gate > 0 and self.vertical_accel_mps2 >= 0
                and self.velocity_accel_mps2 >= 0):                                  # NaN fails too
            raise ValueError("vertical_rate_sigma_mps and vertical_rate_gate must be > 0, vertical_accel_mps2 "
                             "and velocity_accel_mps2 >= 0")
        if self.confirm_gate_m <= 0 or self.gate_sigma <= 0 or self.gate_min_m < 0:
            raise ValueError("confirm_gate_m and gate_sigma must be > 0, gate_min_m >= 0")


# --------------------------------------------------------------------------- object bookkeeping

