"""A simulated multilateration / WAM sensor: its configuration and its accuracy from the receiver
geometry.

The ground receivers time-stamp each reply; the position is the solution of the time differences
of arrival, the aircraft's height taken from its Mode C reply (altitude-aided, the usual WAM
solution). Linearised at the aircraft, receiver i measures the pseudo-range
ρ_i = |p − r_i| + c·b (b the unknown emission time) with error c·σ_t, so with the unit vectors
û_i = (p − r_i)/|p − r_i| of the receivers that see the aircraft

    H_i = [û_i,x, û_i,y, 1],      P_xy = (c σ_t)² [(Σ_i H_iᵀ H_i)⁻¹]_{xy}                  (G1)

(the horizontal block; the height is known). A receiver sees the aircraft when the slant range
is at most ``receiver_range_m`` and it is within the radio horizon (4/3 Earth); at least
``min_receivers`` must. Inside the receivers' hull the û_i surround the aircraft and P_xy is
about (c σ_t)²·2/N; outside they bunch up and the cross-range variance grows with the distance.
For N receivers on a circle around the aircraft at slant elevation ε (|û_h| = cos ε) the cross
terms vanish and

    σ_x² = σ_y² = 2 (c σ_t)² / (N cos² ε)                                             (G2)

Whatever the geometry, λ_max(Σ û_h û_hᵀ) ≤ N, so every direction has variance ≥ (c σ_t)²/N:
the sensor's nominal ``sigma_range_m`` (:func:`nominal_sigma_m`) is that floor, a lower bound
on its accuracy (the posterior Cramér–Rao bound may use it, :mod:`tertiary.evaluation.bound`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.errors import OptionError

__all__ = ["LIGHT_MPS", "MlatConfig", "PeriodicSensor", "accuracy", "check_mlat", "nominal_sigma_m", "visible"]

F64 = NDArray[np.float64]

#: speed of light (m/s)
LIGHT_MPS = 299_792_458.0


class PeriodicSensor:
    """What a sensor that outputs every aircraft at once each ``update_period_s`` (an MLAT / WAM
    system, an ADS-B station) shows the radar-shaped code: its plot numbering
    (:mod:`tertiary.simulate.radar_tracker`) and the ``radars`` table read a scan period and
    phase, a timing, and the angle σ every row must have (no stage reads them for these kinds:
    their plots carry their own Cartesian σ)."""

    update_period_s: float
    update_phase_s: float
    sigma_azimuth_deg = 0.1
    sigma_elevation_deg = 1.0
    #: every aircraft's update at the same instant (the radars' synchronous timing)
    timing = "synchronous"

    @property
    def scan_period_s(self) -> float:
        return self.update_period_s

    @property
    def scan_phase_s(self) -> float:
        return self.update_phase_s


@dataclass(frozen=True)
class MlatConfig(PeriodicSensor):
    """One simulated MLAT / WAM system (a ``[[mlat]]`` table of a scenario).

    ``receivers_enu_m``: the ground receivers in the system frame (east, north, up; m).
    ``site_enu_m``: its reference point (the local frame of its plots), default the receivers'
    centroid. ``update_period_s`` / ``update_phase_s``: when it outputs a position of every
    aircraft it sees; ``timing_sigma_ns``: each receiver's time-of-arrival error (ns);
    ``max_sigma_m``: a solution whose larger horizontal σ exceeds this is not output; ``pd``:
    probability that an update of a covered aircraft is output; ``time_offset_s``: its clock
    minus true time; ``track_drop_scans``: missed updates after which its tracker drops a track.
    """

    name: str
    receivers_enu_m: tuple[tuple[float, float, float], ...]
    site_enu_m: tuple[float, float, float] | None = None
    update_period_s: float = 1.0
    update_phase_s: float = 0.0
    timing_sigma_ns: float = 20.0
    receiver_range_m: float = 150_000.0
    min_receivers: int = 4
    max_sigma_m: float = 1500.0
    pd: float = 0.98
    time_offset_s: float = 0.0
    track_drop_scans: float = 5.0

    @property
    def site(self) -> tuple[float, float, float]:
        """Its reference point in the system frame (ENU, m)."""
        if self.site_enu_m is not None:
            return tuple(float(v) for v in self.site_enu_m)
        return tuple(float(v) for v in np.mean(np.asarray(self.receivers_enu_m, float), axis=0))

    @property
    def sigma_range_m(self) -> float:
        return nominal_sigma_m(self)


def nominal_sigma_m(cfg: MlatConfig) -> float:
    """The accuracy floor c σ_t/√N along any direction (module docstring)."""
    return LIGHT_MPS * cfg.timing_sigma_ns * 1e-9 / math.sqrt(len(cfg.receivers_enu_m))


def check_mlat(where: str, m: MlatConfig, number) -> None:
    """The options of one ``[[mlat]]`` table (``number`` the scenario checker's range check)."""
    if not isinstance(m, MlatConfig):
        raise OptionError(f"expected an [[mlat]] table, got {m!r}", option=where)
    if not isinstance(m.name, str) or not m.name.strip():
        raise OptionError("an MLAT sensor needs a name", option=f"{where}.name")
    if len(m.receivers_enu_m) < max(3, m.min_receivers):
        raise OptionError(f"needs at least max(3, min_receivers) receivers, got {len(m.receivers_enu_m)}",
                          option=f"{where}.receivers_enu_m")
    for v in (*np.ravel(m.receivers_enu_m), *(m.site_enu_m or ())):
        number(f"{where}.receivers_enu_m", v, -2e6, 2e6)
    number(f"{where}.update_period_s", m.update_period_s, 0.1, 60.0)
    number(f"{where}.update_phase_s", m.update_phase_s, 0.0, 60.0)
    number(f"{where}.timing_sigma_ns", m.timing_sigma_ns, 0.0, 1e4, open_lo=True)
    number(f"{where}.receiver_range_m", m.receiver_range_m, 0.0, 1e6, open_lo=True)
    number(f"{where}.min_receivers", m.min_receivers, 3, 1000, integer=True)
    number(f"{where}.max_sigma_m", m.max_sigma_m, 0.0, 1e5, open_lo=True)
    number(f"{where}.pd", m.pd, 0.0, 1.0)
    number(f"{where}.time_offset_s", m.time_offset_s, -3600.0, 3600.0)
    number(f"{where}.track_drop_scans", m.track_drop_scans, 0.0, 1e3, open_lo=True)


def visible(pos: F64, height_m: F64, receivers: F64, receiver_height_m: F64, range_m: float) -> NDArray[np.bool_]:
    """(n, M): which receivers see each aircraft — slant range ≤ ``range_m`` and the horizontal
    distance within the radio horizon √(2kRh_a) + √(2kRh_r) (4/3 Earth). ``pos`` (n, 3) and
    ``receivers`` (M, 3) in one frame; heights above the ellipsoid (m)."""
    d = pos[:, None, :] - receivers[None, :, :]
    k_r = 2.0 * geo.EARTH_RADIUS_M * geo.REFRACTION_K
    horizon = (np.sqrt(k_r * np.maximum(height_m, 0.0))[:, None]
               + np.sqrt(k_r * np.maximum(receiver_height_m, 1.0))[None])
    return (np.linalg.norm(d, axis=2) <= range_m) & (np.hypot(d[..., 0], d[..., 1]) <= horizon)


def accuracy(pos: F64, receivers: F64, seen: NDArray[np.bool_], timing_sigma_s: float
             ) -> tuple[F64, NDArray[np.int64]]:
    """(G1): the horizontal covariance P_xy (n, 2, 2) of each aircraft at ``pos`` (n, 3) from the
    receivers (M, 3) it is ``seen`` by (n, M), all in one local frame, and the count of those
    receivers. NaN where the geometry gives no solution (fewer than three, or singular)."""
    d = pos[:, None, :] - receivers[None, :, :]
    u = d / np.linalg.norm(d, axis=2, keepdims=True)
    h = np.concatenate([u[..., :2], np.ones(u.shape[:2] + (1,))], axis=2) * seen[..., None]    # (n, M, 3)
    info = np.einsum("nmi,nmj->nij", h, h)
    count = seen.sum(axis=1)
    ok = (count >= 3) & (np.abs(np.linalg.det(info)) > 1e-12 * np.maximum(count, 1) ** 3)
    p = np.full((len(pos), 2, 2), np.nan)
    if ok.any():
        p[ok] = np.linalg.inv(info[ok])[:, :2, :2] * (LIGHT_MPS * timing_sigma_s) ** 2
    return p, count
