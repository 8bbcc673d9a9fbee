"""A simulated ADS-B ground station (a ``[[adsb_station]]`` table of a scenario): its
configuration. What it outputs (:mod:`tertiary.simulate.adsb_observe`): the 1090 MHz extended
squitters of the equipped aircraft it hears, as Cartesian plots that its own tracker numbers
like a radar's.

What an aircraft broadcasts it derives from its own navigation, not from the ground:

* **Equipage and quality** are properties of the aircraft. An aircraft with a Mode S address is
  equipped with probability ``equipage``; its NACp is drawn once from ``nacp_weights``; NIC and
  SIL are the station-wide ``nic`` and ``sil`` (typical of a certified GNSS source). Both draws
  come from a hash of the aircraft's id and the scenario seed, so a window or block of the
  simulation gives every aircraft the same answer.
* **Position error.** The broadcast position is the true one plus a Gaussian error of σ per axis
  ``error_scale`` × EPU(NACp)/2.448 (:mod:`tertiary.sensors.adsb`, (ADSB-1)): with the default
  ``error_scale`` = 1 the declared accuracy is the true one. The error is drawn afresh at each
  update (white); a real GNSS error is correlated over minutes, which this model leaves out.
* **Altitude** is the barometric altitude in 25 ft steps, without the garbling of a Mode C reply.
* **Reception.** The station hears an aircraft within ``range_m`` and its radio horizon (4/3
  Earth), each update with probability ``pd``, every ``update_period_s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.errors import OptionError
from tertiary.sensors.adsb import sigma_from_nacp
from tertiary.simulate.mlat import PeriodicSensor

__all__ = ["AdsbStationConfig", "check_adsb_station", "station_site"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class AdsbStationConfig(PeriodicSensor):
    """One ADS-B ground station (module docstring).

    ``site_enu_m``: its antenna in the system frame (east, north, up; m); ``update_period_s`` /
    ``update_phase_s``: when it outputs a position of every aircraft it hears; ``range_m``: its
    reception range; ``equipage``: the fraction of Mode S aircraft that broadcast;
    ``nacp_weights``: (NACp, weight) pairs the aircraft's NACp is drawn from; ``nic``, ``sil``:
    the integrity indicators broadcast; ``error_scale``: true error σ over declared σ;
    ``pd``: probability an update of a heard aircraft is output; ``time_offset_s``: its clock
    minus true time; ``track_drop_scans``: missed updates after which its tracker drops a track.
    """

    name: str
    site_enu_m: tuple[float, float, float] = (0.0, 0.0, 30.0)
    update_period_s: float = 1.0
    update_phase_s: float = 0.0
    range_m: float = 400_000.0
    equipage: float = 0.9
    nacp_weights: tuple[tuple[float, float], ...] = ((3.0, 0.02), (7.0, 0.03), (8.0, 0.05), (9.0, 0.3),
                                                     (10.0, 0.5), (11.0, 0.1))
    nic: int = 8
    sil: int = 3
    error_scale: float = 1.0
    pd: float = 0.98
    time_offset_s: float = 0.0
    track_drop_scans: float = 10.0

    @property
    def site(self) -> tuple[float, float, float]:
        return tuple(float(v) for v in self.site_enu_m)

    @property
    def sigma_range_m(self) -> float:
        """Nominal accuracy: the σ of the most common NACp (a report without NACp gets it)."""
        nacp, _ = max(self.nacp_weights, key=lambda p: p[1])
        return float(sigma_from_nacp([nacp])[0])


def check_adsb_station(where: str, s: AdsbStationConfig, number) -> None:
    """The options of one ``[[adsb_station]]`` table (``number`` the scenario checker's range check)."""
    if not isinstance(s, AdsbStationConfig):
        raise OptionError(f"expected an [[adsb_station]] table, got {s!r}", option=where)
    if not isinstance(s.name, str) or not s.name.strip():
        raise OptionError("an ADS-B station needs a name", option=f"{where}.name")
    for v in s.site_enu_m:
        number(f"{where}.site_enu_m", v, -2e6, 2e6)
    number(f"{where}.update_period_s", s.update_period_s, 0.1, 60.0)
    number(f"{where}.update_phase_s", s.update_phase_s, 0.0, 60.0)
    number(f"{where}.range_m", s.range_m, 0.0, 1e6, open_lo=True)
    number(f"{where}.equipage", s.equipage, 0.0, 1.0)
    if not s.nacp_weights:
        raise OptionError("needs at least one (NACp, weight) pair", option=f"{where}.nacp_weights")
    for nacp, w in s.nacp_weights:
        number(f"{where}.nacp_weights", nacp, 1, 11)
        if float(nacp) != int(nacp):
            raise OptionError(f"a NACp is an integer, got {nacp!r}", option=f"{where}.nacp_weights")
        number(f"{where}.nacp_weights", w, 0.0, 1e6)
    if sum(w for _, w in s.nacp_weights) <= 0:
        raise OptionError("the NACp weights sum to zero", option=f"{where}.nacp_weights")
    number(f"{where}.nic", s.nic, 0, 11, integer=True)
    number(f"{where}.sil", s.sil, 0, 3, integer=True)
    number(f"{where}.error_scale", s.error_scale, 0.0, 100.0)
    number(f"{where}.pd", s.pd, 0.0, 1.0)
    number(f"{where}.time_offset_s", s.time_offset_s, -3600.0, 3600.0)
    number(f"{where}.track_drop_scans", s.track_drop_scans, 0.0, 1e3, open_lo=True)


def station_site(s: AdsbStationConfig, system: geo.LocalFrame) -> geo.LocalFrame:
    """The station's local frame: ENU at its antenna."""
    lat, lon, alt = system.to_geodetic(*s.site)
    return geo.LocalFrame(float(lat), float(lon), float(alt))
