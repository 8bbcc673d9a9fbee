"""MLAT / WAM observations: every update of every aircraft the receivers see, its position drawn
around the truth with the covariance of the receiver geometry (:mod:`tertiary.simulate.mlat`,
(G1)), as plots (:class:`tertiary.simulate.radar.Plots`) that the sensor's own tracker numbers
like a radar's. One call covers all aircraft, updates and Monte-Carlo runs — no Python loop
over them.

What a plot carries comes from the measurement: the noisy (x, y) in the sensor's local ENU, the
σ it states (the geometry's, as a real system computes it), the transponder's Mode S address,
Mode 3/A code and Mode C altitude; its range/azimuth are that point seen from the site at the
Mode C altitude (the ground plane without one), as the data contract asks.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.simulate.mlat import MlatConfig, accuracy, visible
from tertiary.simulate.radar import Plots, Transponders, illumination, scan_starts, transponder_altitude

__all__ = ["mlat_site", "observe_mlat"]

F64 = NDArray[np.float64]


def mlat_site(m: MlatConfig, system: geo.LocalFrame) -> geo.LocalFrame:
    """The sensor's local frame: ENU at its reference point (``m.site`` in the system frame)."""
    lat, lon, alt = system.to_geodetic(*m.site)
    return geo.LocalFrame(float(lat), float(lon), float(alt))


def _geometry(m: MlatConfig, system: geo.LocalFrame, site: geo.LocalFrame, pos_sys: F64
              ) -> tuple[F64, F64, NDArray[np.int64], F64]:
    """Aircraft positions in the site frame (n, 3), their horizontal covariance (G1) (n, 2, 2),
    the number of receivers that see them and their heights."""
    rot_t, off = system.rotation_to(site).T, system.offset_in(site)
    rec = np.asarray(m.receivers_enu_m, float)
    rec_h = system.to_geodetic(*rec.T)[2]
    local = pos_sys @ rot_t + off
    height = system.to_geodetic(*pos_sys.T)[2]
    seen = visible(local, height, rec @ rot_t + off, rec_h, m.receiver_range_m)
    p, count = accuracy(local, rec @ rot_t + off, seen, m.timing_sigma_ns * 1e-9)
    return local, p, count, height


def _draw(p: F64, rng: np.random.Generator, runs: int) -> F64:
    """(runs, n, 2) Gaussian errors with covariance ``p`` (n, 2, 2), by its Cholesky factor."""
    chol = np.linalg.cholesky(p)
    return np.einsum("nij,rnj->rni", chol, rng.standard_normal((runs, len(p), 2)))


def observe_mlat(traj, m: MlatConfig, system: geo.LocalFrame, runs: int, rng: np.random.Generator,
                 tx: Transponders) -> Plots:
    """Every update of ``m`` over ``traj`` for ``runs`` runs: the plots it outputs (covered by at
    least ``min_receivers`` receivers, σ within ``max_sigma_m``, output with probability ``pd``),
    not yet numbered."""
    site = mlat_site(m, system)
    rot_t, offset = system.rotation_to(site).T, system.offset_in(site)

    def sys_to_site(q):
        q = q @ rot_t + offset
        return q[..., 0], q[..., 1], q[..., 2]

    ia, ik, t, pos, *_ = illumination(traj, m, sys_to_site, scan_starts(m, traj.duration))
    local, p, count, height = _geometry(m, system, site, pos)
    worst = np.sqrt(np.maximum(p[:, 0, 0], p[:, 1, 1]))
    covered = (count >= m.min_receivers) & np.isfinite(worst) & (worst <= m.max_sigma_m)
    ia, ik, t, local, p, height = ia[covered], ik[covered], t[covered], local[covered], p[covered], height[covered]
    n = len(ia)
    noise = _draw(p, rng, runs) if n else np.zeros((runs, 0, 2))
    r_idx, p_idx = np.nonzero(rng.random((runs, n)) < m.pd)
    xy = local[p_idx, :2] + noise[r_idx, p_idx]
    ac = ia[p_idx].astype(np.int64)
    tx_rng = rng.spawn(2)
    mode_s, mode_3a = tx.reply(ac, t[p_idx], tx_rng[1])
    alt = transponder_altitude(height[p_idx], tx.quantum_m()[ac], tx_rng[0])
    up = np.zeros(len(ac))
    has = np.isfinite(alt)
    if has.any():
        up[has] = geo.up_at_height(site, xy[has, 0], xy[has, 1], alt[has])
    rng_m, az, _ = geo.enu_to_polar(xy[:, 0], xy[:, 1], up)
    sig = p[p_idx]
    cxy = sig[:, 0, 1]
    cart = np.column_stack([xy, np.sqrt(sig[:, 0, 0]), np.sqrt(sig[:, 1, 1]), np.sign(cxy) * np.sqrt(np.abs(cxy))])
    k = len(ac)
    return Plots(run=r_idx.astype(np.uint32), t_true=t[p_idx], t_report=t[p_idx] + m.time_offset_s, aircraft=ac,
                 range_m=rng_m, azimuth_deg=az, elevation_deg=np.full(k, np.nan), altitude_m=alt,
                 local_track_id=np.zeros(k, np.uint32), scan=ik[p_idx].astype(np.int64), mode_s=mode_s,
                 mode_3a=mode_3a, track_life=np.zeros(k, np.int64), ehs=np.zeros((k, 0)), cart=cart)
