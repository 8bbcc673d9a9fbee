"""Truth trajectories on a regular time grid, shared by every scenario generator.

A :class:`Trajectories` holds A aircraft sampled every ``dt`` seconds on a common grid of T
epochs (system-frame ENU, metres and m/s), with an ``active`` mask for aircraft that enter or
leave. States between grid points come from cubic Hermite interpolation of position and
velocity, which is exact for straight flight and accurate to millimetres in coordinated turns
at 1 s sampling — the radar simulator needs truth at arbitrary beam-passage times.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.units import US
from tertiary.stages.tracking.altitude import geodetic_height_rate

#: manoeuvre segment codes stored per sample
SEGMENTS = ("straight", "turn", "climb", "descent", "hold")
SEG_STRAIGHT, SEG_TURN, SEG_CLIMB, SEG_DESCENT, SEG_HOLD = range(5)

DEFAULT_EPOCH = datetime(2021, 10, 7, 12, 0, 0, tzinfo=timezone.utc)
#: aircraft per block in :func:`integrate_commands`
AIRCRAFT_BLOCK = 16


@dataclass
class Trajectories:
    """Truth for A aircraft on a grid ``t[k] = k·dt`` seconds after ``epoch``."""

    dt: float
    pos: NDArray[np.float64]          # (A, T, 3)
    vel: NDArray[np.float64]          # (A, T, 3)
    active: NDArray[np.bool_]         # (A, T)
    segment: NDArray[np.int8]         # (A, T) codes into SEGMENTS
    truth_id: NDArray[np.int64]       # (A,)
    epoch: datetime = DEFAULT_EPOCH
    meta: dict[str, NDArray] = field(default_factory=dict)  # per-aircraft strings (callsign, icao24)

    @property
    def n_aircraft(self) -> int:
        return self.pos.shape[0]

    @property
    def n_times(self) -> int:
        return self.pos.shape[1]

    @property
    def times(self) -> NDArray[np.float64]:
        return np.arange(self.n_times) * self.dt

    @property
    def duration(self) -> float:
        return (self.n_times - 1) * self.dt

    def state_at(self, aircraft: NDArray[np.integer], t: NDArray[np.float64]
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Position, velocity and validity of ``aircraft[i]`` at time ``t[i]`` (seconds).

        Invalid where t is off the grid or either bracketing sample is inactive.
        """
        flat, s, ok = self._bracket(aircraft, t)
        p0, p1, v0, v1 = self._samples(flat)
        s2 = s * s
        pos = _hermite(s, p0, p1, v0, v1)
        vel = ((6 * s2 - 6 * s) * p0 + (3 * s2 - 4 * s + 1) * v0 + (-6 * s2 + 6 * s) * p1 + (3 * s2 - 2 * s) * v1) / self.dt
        return pos, vel, ok

    def velocity_at(self, aircraft: NDArray[np.integer], t: NDArray[np.float64]
                    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The sampled velocities of ``aircraft[i]`` interpolated linearly to ``t[i]`` and the
        validity (as :meth:`state_at`). Unlike the derivative of the position interpolant it
        never leaves the range of the samples: a trajectory made of recorded fixes (ADS-B) has
        positions and velocities that do not integrate into each other, and there the
        interpolant's derivative swings far from either sample."""
        flat, s, ok = self._bracket(aircraft, t)
        _, _, v0, v1 = self._samples(flat)
        return ((1.0 - s) * v0 + s * v1) / self.dt, ok

    def position_at(self, aircraft: NDArray[np.integer], t: NDArray[np.float64]
                    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Position and validity only (as :meth:`state_at`, without the velocity)."""
        flat, s, ok = self._bracket(aircraft, t)
        return _hermite(s, *self._samples(flat)), ok

    def _bracket(self, aircraft: NDArray[np.integer], t: NDArray[np.float64]
                 ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
        """Flat (aircraft, sample) index of the grid interval holding each time, the fraction
        s ∈ [0, 1] into it (repeated along a trailing axis of 3) and the validity."""
        u = np.asarray(t, dtype=np.float64) / self.dt
        u = np.where(np.isfinite(u), u, -1.0)      # undefined times are simply invalid
        k = np.floor(u).astype(np.int64)
        inside = (k >= 0) & (k < self.n_times - 1) | (u == self.n_times - 1)
        k = np.clip(k, 0, self.n_times - 2)
        s = np.clip(u - k, 0.0, 1.0)
        # repeated per component: (n, 1)·(n, 3) broadcasts run a 3-long inner loop per row
        s = np.repeat(s.reshape(-1), 3).reshape(s.shape + (3,))
        flat = np.asarray(aircraft).astype(np.int64) * self.n_times + k
        active = self.active.reshape(-1)
        return flat, s, inside & active.take(flat) & active.take(flat + 1)

    def _samples(self, flat: NDArray[np.int64]) -> tuple[NDArray[np.float64], ...]:
        """Positions and velocity·dt at both ends of each interval (``take`` on the flattened
        grid: several times faster than two-index fancy indexing)."""
        pos, vel = self.pos.reshape(-1, 3), self.vel.reshape(-1, 3)
        return (pos.take(flat, axis=0), pos.take(flat + 1, axis=0),
                vel.take(flat, axis=0) * self.dt, vel.take(flat + 1, axis=0) * self.dt)

    def path_length(self) -> NDArray[np.float64]:
        """Flown 3-D path length per aircraft: the speed integrated over active samples
        (trapezoid; exact for the piecewise-constant speeds of the generators, whereas chord
        sums fall short in turns)."""
        speed = np.linalg.norm(self.vel, axis=-1)
        step = 0.5 * (speed[:, 1:] + speed[:, :-1]) * self.dt
        both = self.active[:, 1:] & self.active[:, :-1]
        return np.where(both, step, 0.0).sum(axis=1)

    def to_frame(self, stride: int = 1, frame: geo.LocalFrame | None = None) -> pl.DataFrame:
        """The ``truth`` table (long form, active samples only).

        With the system ``frame`` the table also carries the vertical reference the
        transponders report: ``alt_m`` = pressure altitude = geodetic height of the position
        (standard atmosphere, no QNH or temperature deviation; :mod:`tertiary.stages.tracking.altitude`) and
        ``alt_rate_mps`` = its rate n̂·v (n̂ the ellipsoid normal at the aircraft) — never the
        ENU z, which falls away from the height by ρ²/2R."""
        a_idx, k_idx = np.nonzero(self.active[:, ::stride])
        k_idx = k_idx * stride
        flat = a_idx * self.n_times + k_idx
        pos, vel = self.pos.reshape(-1, 3).take(flat, axis=0), self.vel.reshape(-1, 3).take(flat, axis=0)
        t_us = np.round(k_idx * self.dt * 1e6).astype(np.int64)
        epoch_us = int(self.epoch.timestamp() * US)
        cols = {
            "truth_id": self.truth_id[a_idx],
            "time": pl.Series(t_us + epoch_us, dtype=pl.Int64).cast(pl.Datetime("us", "UTC")),
            "x_m": pos[:, 0], "y_m": pos[:, 1], "z_m": pos[:, 2],
            "vx_mps": vel[:, 0], "vy_mps": vel[:, 1], "vz_mps": vel[:, 2],
            "segment": pl.Series(SEGMENTS, dtype=pl.String).gather(self.segment.reshape(-1).take(flat)),
        }
        if frame is not None:
            h, hdot, _ = geodetic_height_rate(pos, vel, frame)
            cols["alt_m"], cols["alt_rate_mps"] = h, hdot
        for name, values in self.meta.items():
            cols[name] = pl.Series(name, np.asarray(values, dtype=str), dtype=pl.String).gather(a_idx)
        return pl.DataFrame(cols)


def _hermite(s: NDArray[np.float64], p0: NDArray[np.float64], p1: NDArray[np.float64], v0: NDArray[np.float64],
             v1: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cubic Hermite position at fraction s of a grid interval (v0, v1: velocity · dt)."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * v0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * v1


def integrate_commands(p0: NDArray[np.float64], heading0_deg: NDArray[np.float64], speed: NDArray[np.float64],
                       turn_rate_dps: NDArray[np.float64], vertical_rate: NDArray[np.float64],
                       dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact integration of piecewise-constant commands, vectorised over aircraft and time.

    Per aircraft a (A,) start position ``p0`` (A, 3) and heading (deg clockwise from north);
    per step (A, T-1) the ground speed (m/s), turn rate (deg/s, positive = right/clockwise)
    and vertical rate (m/s), held constant over each step. Horizontal motion over a step is the
    exact coordinated-turn arc, so path lengths and radii are exact. Returns pos, vel (A, T, 3).
    """
    a_n, steps = turn_rate_dps.shape
    pos, vel = np.empty((a_n, steps + 1, 3)), np.empty((a_n, steps + 1, 3))
    # blocks of aircraft keep the dozen (aircraft, step) temporaries in cache (twice as fast)
    for lo in range(0, a_n, AIRCRAFT_BLOCK):
        b = slice(lo, lo + AIRCRAFT_BLOCK)
        _integrate(np.asarray(p0)[b], np.asarray(heading0_deg)[b], speed[b], turn_rate_dps[b], vertical_rate[b], dt,
                   pos[b], vel[b])
    return pos, vel


def _integrate(p0: NDArray[np.float64], heading0_deg: NDArray[np.float64], speed: NDArray[np.float64],
               turn_rate_dps: NDArray[np.float64], vertical_rate: NDArray[np.float64], dt: float,
               pos: NDArray[np.float64], vel: NDArray[np.float64]) -> None:
    """:func:`integrate_commands` for a block of aircraft, into ``pos`` and ``vel``."""
    a_n = len(turn_rate_dps)
    w = np.radians(turn_rate_dps)
    psi = np.radians(heading0_deg)[:, None] + np.concatenate([np.zeros((a_n, 1)), np.cumsum(w * dt, axis=1)], axis=1)
    sin, cos = np.sin(psi), np.cos(psi)          # once: each step needs both ends
    small = np.abs(w) < 1e-12
    w_safe = np.where(small, 1.0, w)
    # ∫ v sinψ dt and ∫ v cosψ dt over the step (east, north)
    de = np.where(small, speed * sin[:, :-1] * dt, speed * (cos[:, :-1] - cos[:, 1:]) / w_safe)
    dn = np.where(small, speed * cos[:, :-1] * dt, speed * (sin[:, 1:] - sin[:, :-1]) / w_safe)
    du = vertical_rate * dt
    pos[:, 0] = p0
    pos[:, 1:, 0] = p0[:, None, 0] + np.cumsum(de, axis=1)
    pos[:, 1:, 1] = p0[:, None, 1] + np.cumsum(dn, axis=1)
    pos[:, 1:, 2] = p0[:, None, 2] + np.cumsum(du, axis=1)
    # velocity at each sample: the command of the step that starts there (last repeats)
    spd = np.concatenate([speed, speed[:, -1:]], axis=1)
    vz = np.concatenate([vertical_rate, vertical_rate[:, -1:]], axis=1)
    vel[..., 0], vel[..., 1], vel[..., 2] = spd * sin, spd * cos, vz
