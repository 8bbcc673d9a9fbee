"""Truth trajectories of generated traffic: each aircraft's selections and clearances beside its
truth (:class:`TrafficTrajectories`), the monograph's big box (§4.2.1), and the flight geometry
every generator flies its routes with.

Routes are flown as piecewise-constant command arrays (speed, turn rate, vertical rate)
integrated exactly with :func:`tertiary.simulate.trajectory.integrate_commands`. Terminal-area
(:mod:`.terminal`) and national (:mod:`.national`) traffic fly each route once as a template
(:func:`fly`, :func:`template_grid`); an aircraft's truth is that template looked up from its
entry time, so a stretch of time is built without integrating or holding the whole scenario.
Heights are geodetic (= pressure altitude in a standard atmosphere) and converted to the
tangent-plane z exactly (:func:`heights_to_enu`), level flight is level in height.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.geo import height_and_rate
from tertiary.core.units import FT
from tertiary.simulate.trajectory import (SEG_CLIMB, SEG_DESCENT, SEG_STRAIGHT, SEG_TURN, Trajectories,
                                          integrate_commands)


@dataclass
class TrafficTrajectories(Trajectories):
    """Truth plus each aircraft's selected altitude ``selected_alt_m`` (A,) and cleared level
    ``cleared_alt_m`` (A,). The selected altitude is the MCP/FCU level
    its crew set (pressure-altitude reference of the truth's ``alt_m``, m; NaN: none downlinked).
    The aircraft's intent, not its future: the level the generator clears it to
    (:mod:`tertiary.simulate.traffic.terminal`), changed during the flight only where the crew's procedure changes it
    (:meth:`selected_at`). Read by the EHS simulator (:mod:`tertiary.simulate.ehs`, BDS 4,0) only."""

    selected_alt_m: NDArray[np.float64] | None = None
    #: per aircraft, when (s after the epoch; +inf: never) the crew changes the selection, and the
    #: level it selects then (NaN: none) — e.g. an arrival's missed-approach altitude once
    #: established on the glide path
    selected_change_s: NDArray[np.float64] | None = None
    selected_next_m: NDArray[np.float64] | None = None
    #: per aircraft, the level the controller cleared it to (m, same reference; NaN: none): what
    #: flight data hold (:func:`tertiary.simulate.flight_plans`). A level bust's is the level it
    #: was cleared to keep, whatever its crew selected.
    cleared_alt_m: NDArray[np.float64] | None = None

    def selected_at(self, aircraft: NDArray[np.int64], t: NDArray[np.float64]) -> NDArray[np.float64]:
        """The selected altitude of ``aircraft`` (indices) at times ``t`` (s after the epoch):
        the initial selection, or the next one from its change time on (NaN: none)."""
        a = np.asarray(aircraft, np.int64)
        first = (np.full(len(a), np.nan) if self.selected_alt_m is None
                 else np.asarray(self.selected_alt_m, float)[a])
        if self.selected_change_s is None or self.selected_next_m is None:
            return first
        changed = np.asarray(t, float) >= self.selected_change_s[a]
        return np.where(changed, self.selected_next_m[a], first)


# --------------------------------------------------------------------------- big box

BIG_BOX_SPEED = 300.0 / 3.6          # V = 300 km/h
BIG_BOX_ALT = 500.0                  # H = 500 m
BIG_BOX_LEGS = (15_000.0, 8_000.0, 20_000.0, 8_000.0, 10_000.0)
BIG_BOX_TURN_RATE = -3.0             # 90° left turns at 3°/s (negative = counter-clockwise)
BIG_BOX_START = (4000.0, -12000.0)   # heading north


def big_box(dt: float = 1.0) -> Trajectories:
    """The monograph's §4.2.1 circuit: 71 km, 852 s at 300 km/h, 500 m.

    Legs 15, 8, 20, 8, 10 km joined by four 90° left turns at 3°/s (radius V/ω ≈ 1591.5 m,
    30 s and 2500 m each).
    """
    turn_s = 90.0 / abs(BIG_BOX_TURN_RATE)
    durations, rates = [], []
    for i, leg in enumerate(BIG_BOX_LEGS):
        durations.append(leg / BIG_BOX_SPEED)
        rates.append(0.0)
        if i < len(BIG_BOX_LEGS) - 1:
            durations.append(turn_s)
            rates.append(BIG_BOX_TURN_RATE)
    steps = np.round(np.array(durations) / dt).astype(int)
    if not np.allclose(steps * dt, durations, atol=1e-9):
        raise ValueError(f"big-box needs dt dividing the leg and turn durations {durations} s; got dt={dt}")
    turn = np.repeat(np.array(rates), steps)[None, :]
    speed = np.full_like(turn, BIG_BOX_SPEED)
    pos, vel = integrate_commands(np.array([[*BIG_BOX_START, BIG_BOX_ALT]]), np.array([0.0]),
                                  speed, turn, np.zeros_like(turn), dt)
    seg = np.where(np.append(turn[0], turn[0, -1]) != 0, SEG_TURN, SEG_STRAIGHT).astype(np.int8)[None, :]
    return Trajectories(dt=dt, pos=pos, vel=vel, active=np.ones(pos.shape[:2], bool), segment=seg,
                        truth_id=np.array([0], np.int64),
                        meta={"callsign": np.array(["BOX001"]), "icao24": np.array(["508c01"])})


# --------------------------------------------------------------------------- procedure geometry

THRESHOLD = (1500.0, 0.0)             # runway 27 threshold (landing west), elevation 0
TCH_M = 15.0                          # threshold crossing height
GLIDE_DEG = 3.0
TURN_RADIUS_M = 3000.0                # fly-by turns on STARs / SIDs


def uniform(rng: np.random.Generator, lo_hi: tuple[float, float], size) -> NDArray[np.float64]:
    """``size`` draws uniform in ``lo_hi`` = (lo, hi)."""
    return rng.uniform(lo_hi[0], lo_hi[1], size)


def wrap180(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angles (deg) wrapped to [−180, 180)."""
    return np.mod(a + 180.0, 360.0) - 180.0


def flight_level_m(fl: NDArray | float, buffer_m: float) -> NDArray[np.float64]:
    """Geometric height of flight level ``fl`` (hundreds of feet): FL·100 ft plus ``buffer_m``
    per 1 000 ft (a pressure level in a slightly warm atmosphere; keeps adjacent levels off the
    strict < 1 000 ft boundary of the loss-of-separation rule)."""
    return np.asarray(fl, np.float64) / 10.0 * (1000.0 * FT + buffer_m)


def heights_to_enu(pos: NDArray[np.float64], vel: NDArray[np.float64], frame: geo.LocalFrame | None = None,
                   active: NDArray[np.bool_] | None = None) -> None:
    """In place: z and vz of (…, 3) positions/velocities given as (x, y, height, vx, vy, ḣ)
    become tangent-plane z and ż such that the geodetic height of the point is the height
    (WGS-84 with ``frame``, else the sphere of :data:`tertiary.core.geo.EARTH_RADIUS_M` that
    :func:`tertiary.core.geo.height_and_rate` uses without a frame).

    Sphere: z = √((R+h)² − x² − y²) − R, ż = ((R+h)ḣ − x·vx − y·vy)/(R + z). With a frame,
    Newton steps z ← z + (h − h(z)) (∂h/∂z = cos of the normal's tilt ≈ 1 − ρ²/2R²) from the
    sphere, then ż from n̂·v = ḣ (n̂ the ellipsoid normal at the point); only ``active``
    samples (all if None) get the WGS-84 refinement."""
    shape = pos.shape
    p, v = pos.reshape(-1, 3), vel.reshape(-1, 3)
    h, hdot = p[:, 2].copy(), v[:, 2].copy()
    r = geo.EARTH_RADIUS_M
    # a sample outside its aircraft's flight is extrapolated along the route and, on a long
    # recording, can lie beyond the sphere (thousands of km out): its z is NaN and never read
    with np.errstate(invalid="ignore"):
        p[:, 2] = np.sqrt((r + h) ** 2 - p[:, 0] ** 2 - p[:, 1] ** 2) - r
    v[:, 2] = ((r + h) * hdot - p[:, 0] * v[:, 0] - p[:, 1] * v[:, 1]) / (r + p[:, 2])
    if frame is not None:
        sel = np.ones(len(p), bool) if active is None else active.reshape(-1)
        q, w = p[sel], v[sel]
        for _ in range(2):          # the sphere is within ~10 m: two Newton steps reach < 1 µm
            hz, _, up = height_and_rate(q, w, frame)
            q[:, 2] += (h[sel] - hz) / up[:, 2]
        w[:, 2] = (hdot[sel] - up[:, 0] * w[:, 0] - up[:, 1] * w[:, 1]) / up[:, 2]
        p[sel], v[sel] = q, w
    assert pos.shape == shape


# ------------------------------------------------------------------ routes flown as templates


def flyby(waypoints, radius: float = TURN_RADIUS_M) -> tuple[float, NDArray, NDArray]:
    """Start heading (deg) and pieces (lengths, curvatures 1/m, + = right) of a polyline flown
    with fly-by turns of ``radius`` (each corner cut by r·tan(|Δψ|/2) on both legs)."""
    w = np.asarray(waypoints, np.float64)
    d = np.diff(w, axis=0)
    leg = np.hypot(d[:, 0], d[:, 1])
    hdg = np.degrees(np.arctan2(d[:, 0], d[:, 1]))
    turn = wrap180(np.diff(hdg))
    cut = radius * np.tan(np.radians(np.abs(turn)) / 2)
    straight = leg - np.append(0.0, cut) - np.append(cut, 0.0)
    if np.any(straight < 0):
        raise ValueError(f"route legs too short for {radius} m turns: {waypoints}")
    lengths = np.empty(2 * len(leg) - 1)
    curv = np.zeros_like(lengths)
    lengths[0::2] = straight
    lengths[1::2] = radius * np.radians(np.abs(turn))
    curv[1::2] = np.sign(turn) / radius
    return float(hdg[0]), lengths, curv


def fly(start, hdg0: float, lengths, curv, speed_of, height_of, seg_of, dt: float) -> dict[str, NDArray]:
    """A route flown from its start: per step speed, turn rate, vertical rate (piecewise
    constant, the distance / heading / height change of the step) and per sample heading,
    segment code and the integrated position (x, y, height). ``speed_of``, ``height_of``,
    ``seg_of`` are functions of the distance u flown along the route (and its length L)."""
    bounds = np.concatenate([[0.0], np.cumsum(lengths)])
    total = bounds[-1]
    u = np.linspace(0.0, total, int(total / 5.0) + 2)
    v = speed_of(u, total)
    t_u = np.concatenate([[0.0], np.cumsum(np.diff(u) * 0.5 * (1 / v[1:] + 1 / v[:-1]))])
    k = int(np.floor(t_u[-1] / dt))
    uk = np.interp(np.arange(k + 1) * dt, t_u, u)
    psi_b = hdg0 + np.degrees(np.concatenate([[0.0], np.cumsum(np.asarray(lengths) * np.asarray(curv))]))
    psi = np.interp(uk, bounds, psi_b)
    hk = height_of(uk, total)
    cmd = {"speed": np.diff(uk) / dt, "turn": np.diff(psi) / dt, "vz": np.diff(hk) / dt}
    pos, _ = integrate_commands(np.array([[start[0], start[1], hk[0]]]), np.array([hdg0]), cmd["speed"][None],
                                cmd["turn"][None], cmd["vz"][None], dt)
    turning = np.append(cmd["turn"], 0.0) != 0
    return {**cmd, "hdg": psi, "pos": pos[0], "seg": np.where(turning, SEG_TURN, seg_of(uk, total)).astype(np.int8)}


def level_segments(u, total, vz_sign=None):
    """Segment codes of a level route: straight everywhere (turns are marked by :func:`fly`)."""
    return np.full(len(u), SEG_STRAIGHT, np.int8)


def vertical_segments(height_of):
    """Segment codes along a route of height profile ``height_of``: climb, descent or straight."""
    def seg(u, total):
        dh = np.diff(height_of(u, total), append=height_of(u[-1:] + 1.0, total))
        return np.where(dh > 1e-6, SEG_CLIMB, np.where(dh < -1e-6, SEG_DESCENT, SEG_STRAIGHT)).astype(np.int8)
    return seg


def constant(value: float):
    """A profile (speed or height) of ``value`` along the whole route."""
    return lambda u, total: np.full(len(u), value)


def template_grid(tpl: list[dict]):
    """Templates padded to one length (last sample repeated), velocities from the commands
    (the step that starts at a sample; the last repeats); positions (x, y, height)."""
    length = np.array([len(t["speed"]) for t in tpl], np.int64)
    kk = int(length.max()) + 1
    pos = np.empty((len(tpl), kk, 3))
    vel = np.empty((len(tpl), kk, 3))
    seg = np.empty((len(tpl), kk), np.int8)
    for i, t in enumerate(tpl):          # a loop over routes (tens to hundreds), not aircraft
        k = len(t["speed"])
        spd = np.append(t["speed"], t["speed"][-1])
        vz = np.append(t["vz"], t["vz"][-1])
        psi = np.radians(t["hdg"])
        pos[i, :k + 1], seg[i, :k + 1] = t["pos"], t["seg"]
        vel[i, :k + 1] = np.column_stack([spd * np.sin(psi), spd * np.cos(psi), vz])
        pos[i, k + 1:], vel[i, k + 1:], seg[i, k + 1:] = pos[i, k], vel[i, k], seg[i, k]
    return pos, vel, seg, length
