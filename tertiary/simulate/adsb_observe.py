"""ADS-B ground station observations (:mod:`tertiary.simulate.adsb_station` states the model):
every update of every equipped aircraft the station hears, as plots
(:class:`tertiary.simulate.radar.Plots` with ``cart``). One call covers all aircraft, updates
and Monte-Carlo runs."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.sensors.adsb import sigma_from_nacp
from tertiary.simulate.adsb_station import AdsbStationConfig, station_site
from tertiary.simulate.mlat import visible
from tertiary.simulate.radar import Plots, Transponders, illumination, scan_starts, transponder_altitude

__all__ = ["aircraft_quality", "observe_adsb"]

F64 = NDArray[np.float64]


def _uniform(ids: NDArray[np.int64], seed: int, salt: int) -> F64:
    """A uniform number in [0, 1) per aircraft id, fixed by (id, seed, salt) (SplitMix64)."""
    z = (ids.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
         + np.uint64((seed * 1_000_003 + salt) & 0xFFFFFFFFFFFFFFFF))
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def aircraft_quality(s: AdsbStationConfig, truth_id: NDArray[np.int64], has_mode_s: NDArray[np.bool_], seed: int
                     ) -> tuple[NDArray[np.bool_], F64]:
    """(equipped, NACp) per aircraft (module docstring): fixed by its id and the seed."""
    with np.errstate(over="ignore"):
        equipped = has_mode_s & (_uniform(truth_id, seed, 1) < s.equipage)
        u = _uniform(truth_id, seed, 2)
    nacp = np.array([p for p, _ in s.nacp_weights], float)
    w = np.array([w for _, w in s.nacp_weights], float)
    return equipped, nacp[np.minimum(np.searchsorted(np.cumsum(w) / w.sum(), u, side="right"), len(nacp) - 1)]


def observe_adsb(traj, s: AdsbStationConfig, system: geo.LocalFrame, runs: int, rng: np.random.Generator,
                 tx: Transponders, seed: int) -> Plots:
    """Every update of ``s`` over ``traj`` for ``runs`` runs (module docstring), not yet numbered.
    ``cart`` holds x, y (station ENU), σx, σy, the x-y term (0), NACp, NIC, SIL."""
    site = station_site(s, system)
    rot_t, offset = system.rotation_to(site).T, system.offset_in(site)

    def sys_to_site(q):
        q = q @ rot_t + offset
        return q[..., 0], q[..., 1], q[..., 2]

    equipped, nacp_ac = aircraft_quality(s, np.asarray(traj.truth_id, np.int64), tx.address >= 0, seed)
    ia, ik, t, pos, *_ = illumination(traj, s, sys_to_site, scan_starts(s, traj.duration))
    local = pos @ rot_t + offset
    height = system.to_geodetic(*pos.T)[2]
    heard = visible(local, height, np.zeros((1, 3)), np.array([site.alt_m]), s.range_m)[:, 0] & equipped[ia]
    ia, ik, t, local, height = ia[heard], ik[heard], t[heard], local[heard], height[heard]
    n = len(ia)
    r_idx, p_idx = np.nonzero(rng.random((runs, n)) < s.pd)
    nacp = nacp_ac[ia[p_idx]]
    sigma = sigma_from_nacp(nacp)
    xy = local[p_idx, :2] + (s.error_scale * sigma)[:, None] * rng.standard_normal((len(p_idx), 2))
    ac = ia[p_idx].astype(np.int64)
    mode_s, mode_3a = tx.reply(ac, t[p_idx], rng)
    mode_s = tx.address[ac]                                  # every squitter carries the address
    alt = transponder_altitude(height[p_idx], tx.quantum_m()[ac], rng, garble_rate=0.0, missing_rate=0.0)
    up = geo.up_at_height(site, xy[:, 0], xy[:, 1], alt) if len(ac) else np.zeros(0)
    rng_m, az, _ = geo.enu_to_polar(xy[:, 0], xy[:, 1], up)
    k = len(ac)
    cart = np.column_stack([xy, sigma, sigma, np.zeros(k), nacp, np.full(k, float(s.nic)), np.full(k, float(s.sil))])
    return Plots(run=r_idx.astype(np.uint32), t_true=t[p_idx], t_report=t[p_idx] + s.time_offset_s, aircraft=ac,
                 range_m=rng_m, azimuth_deg=az, elevation_deg=np.full(k, np.nan), altitude_m=alt,
                 local_track_id=np.zeros(k, np.uint32), scan=ik[p_idx].astype(np.int64), mode_s=mode_s,
                 mode_3a=mode_3a, track_life=np.zeros(k, np.int64), ehs=np.zeros((k, 0)), cart=cart)
