"""Truth trajectory generators: the seed's big box (§4.2.1) and terminal-area traffic.

Routes are flown as piecewise-constant command arrays (speed, turn rate, vertical rate)
integrated exactly with :func:`tertiary.simulate.trajectory.integrate_commands`. Terminal-area
and national traffic fly each route once as a template; an aircraft's truth is that template
looked up from its entry time (:meth:`TerminalTraffic.window`, :meth:`NationalTraffic.window`),
so a stretch of time is built without integrating or holding the whole scenario.

Terminal area (DESIGN §5, issue 11 item 6) — traffic that flies procedures
--------------------------------------------------------------------------
System frame x east, y north; runway 27 at the origin (threshold (1 500, 0), landing west).

* **Arrivals**: three STAR branches (NE, E, SE entries 58–60 km out) merge at the intercept
  point I = (40 km, 0) and fly one final approach: 3 000 ft level, then a 3° glide path to
  the threshold (h = 15 m + s·tan 3°, s the distance to go), speed 130 → 75 m/s between 30
  and 10 km to go. Speed and height are functions of the distance to go only, so every
  arrival passes a point of the common path at (landing time − T(s)): arrivals landing
  ``arrival_spacing_s`` apart are ≥ 75 m/s × spacing apart in trail, and on converging
  branches the distance is ≥ v·Δt as they meet the merge point (minimum at the merge).
* **Departures**: lift off 20 s after a landing slot, climb at 7.5 % (130 → 180 m/s) on three
  SIDs (W, NW, SW) to the SID top FL70; in trail ≥ 80 m/s × slot apart.
* **Overflights**: four airways across the area, levels by the semicircular rule (tracks
  000–179° odd thousands of feet, 180–359° even), FL150–FL390, each level used by one airway
  only (crossing airways are ≥ 1 000 ft apart); in a lane (airway, level) the speed is
  constant and entries are ≥ ``overflight_spacing_s`` apart.
* **Holding**: two stacks (north and north-west fixes), FL110–FL140 at 1 000 ft, right-hand
  race-tracks (60 s legs, 3°/s turns at 110 m/s); each level holds one aircraft at a time
  (feeder in from the north, 1–3 laps, exit east).
* **Designed pairs** in three zones in the south at FL110–FL140 (nothing else flies there at
  those levels): ``conflict_pairs`` crossing / converging (same level, horizontal miss in
  ``conflict_miss_m``) or level bust (climbs from the level below and levels off 100–250 ft
  under the occupied level); ``near_miss_pairs`` at the same level with a miss of
  1.15–1.45 × the horizontal minimum. Each pair has its own (zone, level, time) slot.

Vertical bands: departures ≤ FL70, arrivals ≤ FL100, holding and pairs FL110–FL140 (north /
south), overflights ≥ FL150 — so the only losses of separation are the designed conflicts.

Selected altitude (what the crew set on the MCP/FCU, downlinked in Mode S EHS BDS 4,0:
:class:`TrafficTrajectories`). It is the clearance the generator flies each aircraft to —
never read off the future trajectory: departures the SID top (FL70), arrivals 3 000 ft (the
level they descend to) and, once established on the glide path (a crew delay of
``missed_approach_delay_s`` after the descent begins), the missed-approach altitude
``missed_approach_ft`` (4 000 ft) — what crews set after glide-slope capture, so that a go-around
climbs to it (:meth:`TrafficTrajectories.selected_at`); overflights, holding aircraft and
designed pairs their level. A level bust is modelled with its most common
real cause, a wrong level selected: by default (``TrafficConfig.bust_selected = "flown"``) the
busting aircraft's selected altitude is the level it climbs to (100–250 ft under the occupied
level); ``"cleared"`` keeps the level it was cleared to (the one below: an autopilot/handling
bust with a correct selection). A fraction ``1 − selected_alt_fraction`` of the aircraft do not
downlink it (NaN).
Heights are geodetic (= pressure altitude in a standard atmosphere) and converted to the
tangent-plane z exactly (:func:`heights_to_enu`), level flight is level in height.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from datetime import datetime

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.errors import OptionError
from tertiary.simulate.config import TrafficConfig
from tertiary.simulate.trajectory import (DEFAULT_EPOCH, SEG_CLIMB, SEG_DESCENT, SEG_HOLD, SEG_STRAIGHT, SEG_TURN, Trajectories, integrate_commands)



@dataclass
class TrafficTrajectories(Trajectories):
    """Truth plus each aircraft's selected altitude ``selected_alt_m`` (A,) and cleared level
    ``cleared_alt_m`` (A,). The selected altitude is the MCP/FCU level
    its crew set (pressure-altitude reference of the truth's ``alt_m``, m; NaN: none downlinked).
    The aircraft's intent, not its future: the level the generator clears it to (module
    docstring), changed during the flight only where the crew's procedure changes it
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
    """The monograph's §4.2.1 circuit as fixed in DESIGN §5: 71 km, 852 s at 300 km/h, 500 m.

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


# --------------------------------------------------------------------------- terminal area

FT = 0.3048
THRESHOLD = (1500.0, 0.0)             # runway 27 threshold (landing west), elevation 0
TCH_M = 15.0                          # threshold crossing height
GLIDE_DEG = 3.0
TURN_RADIUS_M = 3000.0                # fly-by turns on STARs / SIDs
HOLD_SPEED = 110.0
HOLD_RATE_DPS = 3.0
HOLD_LEG_S = 60.0
PAIR_LEAD_S, PAIR_TRAIL_S = 200.0, 60.0
ARRIVALS = (((42_000.0, 42_000.0), (48_000.0, 14_000.0), (40_000.0, 0.0), THRESHOLD),
            ((60_000.0, 3_000.0), (40_000.0, 0.0), THRESHOLD),
            ((42_000.0, -42_000.0), (48_000.0, -14_000.0), (40_000.0, 0.0), THRESHOLD))
DEPARTURES = (((-1000.0, 0.0), (-62_000.0, 0.0)),
              ((-1000.0, 0.0), (-12_000.0, 0.0), (-45_000.0, 42_000.0)),
              ((-1000.0, 0.0), (-12_000.0, 0.0), (-45_000.0, -42_000.0)))
DEPARTURE_DELAY_S = 20.0              # lift-off after the landing of the same slot
SID_TOP_FL = 70
ARRIVAL_TOP_FL = 100
#: arrivals are cleared to 3 000 ft (the level segment before the glide path; once established on
#: the glide path the crew selects the missed-approach altitude, ``TrafficConfig.missed_approach_ft``)
ARRIVAL_CLEARED_M = 3000.0 * 0.3048
#: airways: (track deg, a point on it, speed m/s, flight levels) — odd FL eastbound, even westbound
AIRWAYS = ((75.0, (0.0, 10_000.0), 230.0, (150, 190, 230, 270, 310, 350, 390)),
           (120.0, (0.0, -10_000.0), 220.0, (170, 210, 250, 290, 330, 370)),
           (255.0, (5_000.0, 14_000.0), 235.0, (160, 200, 240, 280, 320, 360)),
           (300.0, (-5_000.0, -5_000.0), 225.0, (180, 220, 260, 300, 340, 380)))
OVERFLIGHT_RING_M = 90_000.0
HOLD_FIXES = ((0.0, 45_000.0), (-45_000.0, 25_000.0))
HOLD_LEVELS = (110, 120, 130, 140)
HOLD_FEEDER_M = 40_000.0
HOLD_EXIT_M = 40_000.0
HOLD_LAPS = (1, 2, 3)
PAIR_ZONES = ((-40_000.0, -40_000.0), (40_000.0, -40_000.0), (0.0, -95_000.0))
PAIR_LEVELS = (110, 120, 130, 140)
PAIR_SPEED = (100.0, 140.0)


def _u(rng: np.random.Generator, lo_hi: tuple[float, float], size) -> NDArray[np.float64]:
    return rng.uniform(lo_hi[0], lo_hi[1], size)


def _wrap180(a: NDArray[np.float64]) -> NDArray[np.float64]:
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
    :func:`safety.conflicts.height_and_rate` uses without a frame).

    Sphere: z = √((R+h)² − x² − y²) − R, ż = ((R+h)ḣ − x·vx − y·vy)/(R + z). With a frame,
    Newton steps z ← z + (h − h(z)) (∂h/∂z = cos of the normal's tilt ≈ 1 − ρ²/2R²) from the
    sphere, then ż from n̂·v = ḣ (n̂ the ellipsoid normal at the point); only ``active``
    samples (all if None) get the WGS-84 refinement."""
    from safety.conflicts import height_and_rate   # safety builds on tertiary: import late
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


def _flyby(waypoints, radius: float = TURN_RADIUS_M) -> tuple[float, NDArray, NDArray]:
    """Start heading (deg) and pieces (lengths, curvatures 1/m, + = right) of a polyline flown
    with fly-by turns of ``radius`` (each corner cut by r·tan(|Δψ|/2) on both legs)."""
    w = np.asarray(waypoints, np.float64)
    d = np.diff(w, axis=0)
    leg = np.hypot(d[:, 0], d[:, 1])
    hdg = np.degrees(np.arctan2(d[:, 0], d[:, 1]))
    turn = _wrap180(np.diff(hdg))
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


def _fly(start, hdg0: float, lengths, curv, speed_of, height_of, seg_of, dt: float) -> dict[str, NDArray]:
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


def _level_seg(u, total, vz_sign=None):
    return np.full(len(u), SEG_STRAIGHT, np.int8)


def _vertical_seg(height_of):
    def seg(u, total):
        dh = np.diff(height_of(u, total), append=height_of(u[-1:] + 1.0, total))
        return np.where(dh > 1e-6, SEG_CLIMB, np.where(dh < -1e-6, SEG_DESCENT, SEG_STRAIGHT)).astype(np.int8)
    return seg


def _arrival_profiles(buffer_m: float):
    tan = np.tan(np.radians(GLIDE_DEG))
    h3000 = 3000.0 * FT
    s_gs = (h3000 - TCH_M) / tan
    top = float(flight_level_m(ARRIVAL_TOP_FL, buffer_m))

    def height(u, total):
        s = total - u
        return np.where(s <= s_gs, TCH_M + s * tan, np.minimum(h3000 + np.maximum(s - 30_000.0, 0.0) * 0.052, top))

    def speed(u, total):
        return np.interp(total - u, [10_000.0, 30_000.0], [75.0, 130.0])
    return speed, height


def _departure_profiles(buffer_m: float):
    top = float(flight_level_m(SID_TOP_FL, buffer_m))

    def height(u, total):
        return np.minimum(10.0 + 0.075 * u, top)

    def speed(u, total):
        return np.interp(u, [0.0, 12_000.0, 40_000.0], [80.0, 150.0, 180.0])
    return speed, height


def _const(value: float):
    return lambda u, total: np.full(len(u), value)


def _airway(track: float, point, ring: float = OVERFLIGHT_RING_M) -> tuple[tuple, tuple]:
    """Entry and exit of a straight airway on the ring."""
    d = np.array([np.sin(np.radians(track)), np.cos(np.radians(track))])
    p = np.asarray(point)
    b = p @ d
    c = p @ p - ring ** 2
    t0, t1 = -b - np.sqrt(b * b - c), -b + np.sqrt(b * b - c)
    return tuple(p + t0 * d), tuple(p + t1 * d)


def _holding_route(fix, laps: int) -> tuple[tuple, float, NDArray, NDArray, NDArray]:
    """Feeder south to the fix, ``laps`` right-hand race-tracks, exit east. Returns start,
    heading, lengths, curvatures and per-piece hold flags."""
    r = HOLD_SPEED / np.radians(HOLD_RATE_DPS)
    leg = HOLD_SPEED * HOLD_LEG_S
    lengths = [HOLD_FEEDER_M] + [np.pi * r, leg, np.pi * r, leg] * laps + [np.pi / 2 * r, HOLD_EXIT_M]
    curv = [0.0] + [1 / r, 0.0, 1 / r, 0.0] * laps + [-1 / r, 0.0]
    hold = [0] + [1, 1, 1, 1] * laps + [0, 0]
    return (fix[0], fix[1] + HOLD_FEEDER_M), 180.0, np.array(lengths), np.array(curv), np.array(hold)


def _templates(cfg: TrafficConfig, dt: float) -> tuple[list[dict], dict[str, list[int]]]:
    """Every route flown once (a loop over ~30 routes): arrivals, departures, airways, holds."""
    out: list[dict] = []
    kinds: dict[str, list[int]] = {"arrival": [], "departure": [], "airway": [], "hold": []}
    sp, hp = _arrival_profiles(cfg.level_buffer_m)
    for wp in ARRIVALS:
        hdg, ln, cv = _flyby(wp)
        kinds["arrival"].append(len(out))
        t = _fly(wp[0], hdg, ln, cv, sp, hp, _vertical_seg(hp), dt)
        # the glide-path descent begins after the last sample at the 3 000 ft approach altitude
        t["k_gs"] = int(np.flatnonzero(t["pos"][:, 2] >= ARRIVAL_CLEARED_M - 0.01)[-1])
        out.append(t)
    sp, hp = _departure_profiles(cfg.level_buffer_m)
    for wp in DEPARTURES:
        hdg, ln, cv = _flyby(wp)
        kinds["departure"].append(len(out))
        out.append(_fly(wp[0], hdg, ln, cv, sp, hp, _vertical_seg(hp), dt))
    for track, point, speed, _levels in AIRWAYS:
        a, b = _airway(track, point)
        hdg, ln, cv = _flyby((a, b))
        kinds["airway"].append(len(out))
        out.append(_fly(a, hdg, ln, cv, _const(speed), _const(0.0), _level_seg, dt))
    for fix in HOLD_FIXES:
        for laps in HOLD_LAPS:
            start, hdg, ln, cv, hold = _holding_route(fix, laps)
            bounds = np.concatenate([[0.0], np.cumsum(ln)])

            def seg(u, total, bounds=bounds, hold=hold):
                piece = np.clip(np.searchsorted(bounds, u, "right") - 1, 0, len(hold) - 1)
                return np.where(hold[piece] == 1, SEG_HOLD, SEG_STRAIGHT).astype(np.int8)
            t = _fly(start, hdg, ln, cv, _const(HOLD_SPEED), _const(0.0), seg, dt)
            t["seg"] = np.where(seg(np.interp(np.arange(len(t["hdg"])) * dt * HOLD_SPEED, [0, bounds[-1]],
                                                [0, bounds[-1]]), 0) == SEG_HOLD, SEG_HOLD, t["seg"]).astype(np.int8)
            t["t_fix"] = HOLD_FEEDER_M / HOLD_SPEED
            t["t_leave"] = bounds[-3] / HOLD_SPEED
            kinds["hold"].append(len(out))
            out.append(t)
    return out, kinds


# ------------------------------------------------------------------ schedules (who flies when)


def _slots(rng, n: int, lo: float, hi: float, gap: float) -> NDArray[np.float64]:
    """``n`` times in [lo, hi] at least ``gap`` apart (random order-preserving spread)."""
    if n == 0:
        return np.zeros(0)
    free = hi - lo - (n - 1) * gap
    if free < 0:
        raise OptionError(f"traffic: {n} aircraft do not fit {gap:g} s apart in {hi - lo:g} s", option="traffic")
    return lo + np.sort(rng.uniform(0.0, free, n)) + np.arange(n) * gap


def _counts(cfg: TrafficConfig, duration_s: float) -> dict[str, int]:
    n = cfg.aircraft
    pairs = min(cfg.conflict_pairs, n // 2)
    near = min(cfg.near_miss_pairs, (n - 2 * pairs) // 2)
    rest = n - 2 * (pairs + near)
    arr_cap = int((duration_s + 400.0) // cfg.arrival_spacing_s)
    hold_cap = len(HOLD_FIXES) * len(HOLD_LEVELS) * max(1, int((duration_s + 600.0) // 900.0))
    hold = min(int(round(cfg.holding_fraction * rest)), hold_cap)
    arr = min(int(round(cfg.arrival_fraction * rest)), arr_cap)
    dep = min(int(round(cfg.departure_fraction * rest)), arr_cap)
    return {"pairs": pairs, "near": near, "hold": hold, "arrival": arr, "departure": dep,
            "overflight": rest - hold - arr - dep}


def _route_aircraft(rng, cfg: TrafficConfig, tpl: list[dict], kinds: dict, counts: dict, duration_s: float,
                    dt: float) -> dict[str, NDArray]:
    """Route, entry time, height offset and role of every procedural aircraft."""
    dur = np.array([len(t["speed"]) * dt for t in tpl])
    route, entry, zoff, role = [], [], [], []
    # arrivals and departures share the runway slot grid
    n_slot = int((duration_s + 400.0) // cfg.arrival_spacing_s)
    base = rng.uniform(60.0, 60.0 + cfg.arrival_spacing_s)
    slots = base + np.arange(n_slot) * cfg.arrival_spacing_s
    arr_r = np.array(kinds["arrival"])[rng.integers(0, len(kinds["arrival"]), counts["arrival"])]
    land = np.sort(rng.choice(slots, counts["arrival"], replace=False))
    route.append(arr_r), entry.append(land - dur[arr_r]), zoff.append(np.zeros(len(arr_r)))
    role += ["arrival"] * len(arr_r)
    dep_slots = np.concatenate([slots[0] - cfg.arrival_spacing_s * np.arange(1, 8)[::-1], slots]) + DEPARTURE_DELAY_S
    dep_min = min(dur[k] for k in kinds["departure"])
    dep_slots = dep_slots[(dep_slots < duration_s - 30.0) & (dep_slots > 60.0 - dep_min)]
    lift = np.sort(rng.choice(dep_slots, min(counts["departure"], len(dep_slots)), replace=False))
    dep_r = np.array(kinds["departure"])[rng.integers(0, len(kinds["departure"]), len(lift))]
    route.append(dep_r), entry.append(lift), zoff.append(np.zeros(len(dep_r)))
    role += ["departure"] * len(dep_r)
    spare = counts["departure"] - len(lift)
    route_h, entry_h, zoff_h = _holding_aircraft(rng, cfg, tpl, kinds, counts["hold"], duration_s)
    route.append(route_h), entry.append(entry_h), zoff.append(zoff_h)
    role += ["holding"] * len(route_h)
    route_o, entry_o, zoff_o = _overflights(rng, cfg, kinds, dur, counts["overflight"] + spare, duration_s)
    route.append(route_o), entry.append(entry_o), zoff.append(zoff_o)
    role += ["overflight"] * len(route_o)
    return {"route": np.concatenate(route).astype(np.int64), "entry": np.concatenate(entry),
            "zoff": np.concatenate(zoff), "role": np.array(role)}


def _holding_aircraft(rng, cfg, tpl, kinds, n: int, duration_s: float):
    """Each (fix, level) holds one aircraft at a time: the next reaches the fix ≥ 240 s after
    the previous left it. Aircraft are dealt to (fix, level) lanes round robin."""
    lanes = [(f, lv) for lv in HOLD_LEVELS for f in range(len(HOLD_FIXES))]
    route, entry, zoff = [], [], []
    for i, (f, lv) in enumerate(lanes):
        m = len(range(i, n, len(lanes)))
        if not m:
            continue
        laps = rng.integers(0, len(HOLD_LAPS), m)
        r = np.array(kinds["hold"])[f * len(HOLD_LAPS) + laps]
        t_fix = np.array([tpl[k]["t_fix"] for k in r])
        busy = np.array([tpl[k]["t_leave"] - tpl[k]["t_fix"] for k in r]) + 240.0
        start = rng.uniform(-0.5 * busy[0], max(duration_s - busy.sum(), 0.0) * 0.5)
        arrive = start + np.concatenate([[0.0], np.cumsum(busy[:-1])]) + rng.uniform(0, 60, m).cumsum()
        route.append(r), entry.append(arrive - t_fix), zoff.append(np.full(m, flight_level_m(lv, cfg.level_buffer_m)))
    if not route:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    return np.concatenate(route), np.concatenate(entry), np.concatenate(zoff)


def _overflights(rng, cfg, kinds, dur, n: int, duration_s: float):
    """Dealt to (airway, level) lanes round robin; in a lane entries ≥ overflight_spacing_s
    apart (tightened to fit, never below 60 s) within [−route time + 60 s, duration − 60 s] so
    that each flies in the scenario."""
    lanes = [(w, fl) for w, (_, _, _, levels) in enumerate(AIRWAYS) for fl in levels]
    order = rng.permutation(len(lanes))
    route, entry, zoff = [], [], []
    for i, li in enumerate(order):
        w, fl = lanes[li]
        m = len(range(i, n, len(lanes)))
        if not m:
            continue
        r = kinds["airway"][w]
        route.append(np.full(m, r))
        lo, hi = -dur[r] + 60.0, duration_s - 60.0
        # dense traffic tightens the lane down to 60 s (≥ 13 km at airway speeds, > 2× the minimum)
        gap = min(cfg.overflight_spacing_s, max(60.0, 0.9 * (hi - lo) / max(m - 1, 1)))
        entry.append(_slots(rng, m, lo, hi, gap))
        zoff.append(np.full(m, flight_level_m(fl, cfg.level_buffer_m)))
    if not route:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    return np.concatenate(route), np.concatenate(entry), np.concatenate(zoff)


# ------------------------------------------------------------------ designed pairs


def _pair_slots(rng, kinds: NDArray, t_c: NDArray, duration_s: float) -> tuple[NDArray, NDArray, NDArray]:
    """(zone, level index, kind) per pair: a pair needs its level (a level bust also the one
    below) free in its zone over [t_c − lead, t_c + trail] (+ 60 s); when the pairs do not fit,
    level busts become crossings (one level each). A loop over pairs (tens), not aircraft."""
    try:
        return _place_pairs(kinds, t_c, duration_s)
    except OptionError:
        return _place_pairs(np.where(kinds == 2, 0, kinds), t_c, duration_s)


def _place_pairs(kinds: NDArray, t_c: NDArray, duration_s: float) -> tuple[NDArray, NDArray, NDArray]:
    """First-fit placement for :func:`_pair_slots`."""
    busy: dict[tuple[int, int], list[tuple[float, float]]] = {}
    zone = np.zeros(len(t_c), np.int64)
    level = np.zeros(len(t_c), np.int64)
    kinds = kinds.copy()
    for p in range(len(t_c)):
        lo, hi = t_c[p] - PAIR_LEAD_S - 60.0, t_c[p] + PAIR_TRAIL_S + 60.0
        free = lambda z, lv: all(hi <= a or lo >= b for a, b in busy.get((z, lv), []))
        options = [(z, lv) for z in range(len(PAIR_ZONES)) for lv in range(len(PAIR_LEVELS))]
        found = None
        if kinds[p] == 2:
            found = next(((z, lv) for z, lv in options if lv > 0 and free(z, lv) and free(z, lv - 1)), None)
            if found is None:
                kinds[p] = 0
        if found is None:
            found = next(((z, lv) for z, lv in options if free(z, lv)), None)
        if found is None:
            raise OptionError(f"{len(t_c)} designed conflict and near-miss pairs do not fit in {duration_s:g} s of "
                              "traffic: give a longer --duration or fewer --aircraft (or lower conflict_pairs / "
                              "near_miss_pairs in the scenario TOML)", option="--duration")
        z, lv = found
        for used in ([lv, lv - 1] if kinds[p] == 2 else [lv]):
            busy.setdefault((z, used), []).append((lo, hi))
        zone[p], level[p] = z, lv
    return zone, level, kinds


def _pairs(rng, cfg: TrafficConfig, n_conf: int, n_near: int, dt: float, duration_s: float) -> dict[str, NDArray]:
    """Designed pairs, straight with constant speed (kinds 0 crossing, 1 converging, 2 level
    bust, 3 near miss): per aircraft (pair i = aircraft i and n_pairs + i) the plan flown in
    closed form by :func:`_pair_states` — heading, speed, the point ``anchor`` passed at sample
    ``k_c``, level ``z`` (height, m), the bust's climb (``rate`` m/s from sample ``k_climb``
    for ``n_climb`` steps), the active span [``t0``, ``t1``] (s), role, selected altitude and
    cleared level (height, m)."""
    n_p = n_conf + n_near
    if n_p == 0:
        f, i = np.zeros(0), np.zeros(0, np.int64)
        return {"heading": f, "speed": f, "anchor": np.zeros((0, 2)), "k_c": i, "z": f, "rate": f, "k_climb": i,
                "n_climb": i, "t0": f, "t1": f, "role": np.zeros(0, str), "selected": f, "cleared": f}
    t_c = np.concatenate([np.linspace(0.2, 0.8, n_conf) if n_conf > 1 else np.full(n_conf, 0.5),
                          rng.uniform(0.15, 0.85, n_near)]) * duration_s + rng.uniform(-20, 20, n_p)
    t_c = np.clip(np.round(t_c / dt) * dt, dt, duration_s - dt)
    kind = np.concatenate([rng.integers(0, 3, n_conf), np.full(n_near, 3)])
    kind = np.where((kind == 2) & (t_c < 100.0), 0, kind)      # a bust needs its climb inside the run
    zone, lvl, kind = _pair_slots(rng, kind, t_c, duration_s)
    kind = np.asarray(kind)
    delta = np.choose(np.minimum(kind, 2), [rng.uniform(60, 120, n_p), rng.uniform(15, 40, n_p),
                                            rng.uniform(60, 120, n_p)])
    delta = np.where(kind == 3, np.where(rng.random(n_p) < 0.5, rng.uniform(60, 120, n_p), rng.uniform(20, 40, n_p)),
                     delta) * rng.choice([-1, 1], n_p)
    h_a = rng.uniform(0, 360, n_p)
    h_b = np.mod(h_a + delta, 360.0)
    sa, sb = rng.uniform(*PAIR_SPEED, n_p), rng.uniform(*PAIR_SPEED, n_p)
    unit = lambda h: np.stack([np.sin(np.radians(h)), np.cos(np.radians(h))], axis=1)
    rel = sa[:, None] * unit(h_a) - sb[:, None] * unit(h_b)
    perp = np.stack([-rel[:, 1], rel[:, 0]], axis=1) / np.linalg.norm(rel, axis=1, keepdims=True)
    miss = np.where(kind == 3, rng.uniform(1.15, 1.45, n_p) * cfg.sep_h_m, _u(rng, cfg.conflict_miss_m, n_p))
    meet = np.asarray(PAIR_ZONES)[zone] + rng.uniform(-5000, 5000, (n_p, 2))
    fl = np.asarray(PAIR_LEVELS)[lvl]
    z_a = flight_level_m(fl, cfg.level_buffer_m)
    bust_ft = rng.uniform(100, 250, n_p)
    z_b = np.where(kind == 2, flight_level_m(fl - 10, cfg.level_buffer_m), z_a)
    # level bust: climb at 8 m/s from the level below, starting 90 s before t_c, to bust_ft under A
    climb = np.where(kind == 2, z_a - bust_ft * FT - z_b, 0.0)
    n_climb = np.maximum(np.ceil(climb / 8.0 / dt), 1).astype(np.int64)
    k_climb = np.round((t_c - 90.0) / dt).astype(np.int64)
    k_c = np.round(t_c / dt).astype(np.int64)
    names = np.array(["conflict-crossing", "conflict-converging", "conflict-level-bust", "near-miss"])
    # selected altitude: each aircraft's level; a bust selected wrong (the level it climbs to) or
    # right (its cleared level below), TrafficConfig.bust_selected
    bust_sel = z_b + climb if cfg.bust_selected == "flown" else z_b
    zero = np.zeros(n_p, np.int64)
    return {"heading": np.concatenate([h_a, h_b]), "speed": np.concatenate([sa, sb]),
            "anchor": np.concatenate([meet, meet + miss[:, None] * perp]), "k_c": np.concatenate([k_c, k_c]),
            "z": np.concatenate([z_a, z_b]), "rate": np.concatenate([np.zeros(n_p), climb / (n_climb * dt)]),
            "k_climb": np.concatenate([zero, k_climb]), "n_climb": np.concatenate([zero, n_climb]),
            "t0": np.concatenate([t_c, t_c]) - PAIR_LEAD_S, "t1": np.concatenate([t_c, t_c]) + PAIR_TRAIL_S,
            "role": np.concatenate([names[kind], names[kind]]),
            "selected": np.concatenate([z_a, np.where(kind == 2, bust_sel, z_b)]),
            # cleared levels: each its own level; a bust was cleared to keep the level below
            "cleared": np.concatenate([z_a, z_b])}


def _pair_states(plan: dict[str, NDArray], ids: NDArray[np.int64], k: NDArray[np.int64], dt: float
                 ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Positions (x, y, height), velocities, activity and segment codes of pair aircraft ``ids``
    at samples ``k``: straight at constant speed through ``anchor`` at ``k_c``; the bust climbs
    at ``rate`` over steps ``k_climb`` … ``k_climb + n_climb − 1`` (the exact integral of the
    piecewise-constant commands)."""
    g = {key: v[ids] for key, v in plan.items()}
    psi = np.radians(g["heading"])
    ground = np.stack([np.sin(psi), np.cos(psi)], axis=1) * g["speed"][:, None]          # (P, 2)
    since = (k[None, :] - g["k_c"][:, None]) * dt                                          # (P, n)
    climbed = np.clip(k[None, :] - g["k_climb"][:, None], 0, g["n_climb"][:, None])
    climbing = (k[None, :] >= g["k_climb"][:, None]) & (k[None, :] < (g["k_climb"] + g["n_climb"])[:, None])
    pos = np.empty((len(ids), len(k), 3))
    pos[..., :2] = g["anchor"][:, None, :] + since[..., None] * ground[:, None, :]
    pos[..., 2] = g["z"][:, None] + g["rate"][:, None] * dt * climbed
    vel = np.empty_like(pos)
    vel[..., :2] = ground[:, None, :]
    vel[..., 2] = np.where(climbing, g["rate"][:, None], 0.0)
    t = k[None, :] * dt
    active = (t >= g["t0"][:, None]) & (t <= g["t1"][:, None])
    seg = np.where(vel[..., 2] > 0, SEG_CLIMB, SEG_STRAIGHT).astype(np.int8)
    return pos, vel, active, seg


@dataclass
class TerminalTraffic:
    """Terminal-area traffic as a schedule (:func:`terminal_traffic`): who flies which route
    template from which sample, the designed pairs' plans, identities and clearances — a few
    arrays per aircraft. The (aircraft × samples) truth of a stretch of time is looked up from
    the templates by :meth:`window` (no integration): identical whatever the window, so a long
    scenario is simulated window by window in memory bounded by the window."""

    dt: float
    steps: int                         # the scenario's last sample (duration / dt)
    frame: geo.LocalFrame | None
    tpos: NDArray[np.float64]          # (R, K+1, 3) template positions (x, y, height)
    tvel: NDArray[np.float64]          # (R, K+1, 3) template velocities (vx, vy, ḣ)
    tseg: NDArray[np.int8]             # (R, K+1)
    length: NDArray[np.int64]          # (R,) template steps
    route: NDArray[np.int64]           # (M,) procedural aircraft: template,
    entry: NDArray[np.int64]           # first template sample's global sample (may be < 0),
    zoff: NDArray[np.float64]          # height added (holding and airway levels)
    pairs: dict[str, NDArray]          # designed pairs' plans (aircraft M …, :func:`_pairs`)
    meta: dict[str, NDArray]
    selected_alt_m: NDArray[np.float64]
    selected_change_s: NDArray[np.float64]
    selected_next_m: NDArray[np.float64]
    cleared_alt_m: NDArray[np.float64]
    epoch: datetime = DEFAULT_EPOCH

    @property
    def n_flights(self) -> int:
        return len(self.route) + len(self.pairs["t0"])

    def span(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Each aircraft's first and last active sample within the scenario (0 … steps); an
        aircraft not flying in it has first > last."""
        first_r = np.maximum(self.entry, 0)
        last_r = np.minimum(self.entry + self.length[self.route], self.steps)
        t0, t1 = self.pairs["t0"], self.pairs["t1"]
        first_p = np.maximum(np.ceil(t0 / self.dt - 1e-9), 0).astype(np.int64)
        last_p = np.minimum(np.floor(t1 / self.dt + 1e-9), self.steps).astype(np.int64)
        return np.concatenate([first_r, first_p]), np.concatenate([last_r, last_p])

    def window(self, k0: int, n: int, every: bool = False) -> TrafficTrajectories:
        """Truth of the aircraft flying during samples k0 … k0+n-1 (``every``: all aircraft), on
        that grid (epoch and selection change times shifted by k0·dt); ``truth_id`` is the
        aircraft number of the scenario."""
        first, last = self.span()
        ids = np.arange(self.n_flights) if every else np.flatnonzero((first <= k0 + n - 1) & (last >= k0) &
                                                                      (first <= last))
        m = len(self.route)
        k = np.arange(k0, k0 + n)
        pos_r, vel_r, act_r, seg_r = self._routed(ids[ids < m], k)
        pos_p, vel_p, act_p, seg_p = _pair_states(self.pairs, ids[ids >= m] - m, k, self.dt)
        pos, vel = np.concatenate([pos_r, pos_p]), np.concatenate([vel_r, vel_p])
        active = np.concatenate([act_r, act_p]) & (k >= 0)[None, :] & (k <= self.steps)[None, :]
        heights_to_enu(pos, vel, self.frame, active)
        from datetime import timedelta
        return TrafficTrajectories(
            dt=self.dt, pos=pos, vel=vel, active=active, segment=np.concatenate([seg_r, seg_p]),
            truth_id=ids.astype(np.int64), epoch=self.epoch + timedelta(seconds=k0 * self.dt),
            meta={key: v[ids] for key, v in self.meta.items()}, selected_alt_m=self.selected_alt_m[ids],
            selected_change_s=self.selected_change_s[ids] - k0 * self.dt, selected_next_m=self.selected_next_m[ids],
            cleared_alt_m=self.cleared_alt_m[ids])

    def _routed(self, ids: NDArray[np.int64], k: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Procedural aircraft ``ids`` at samples ``k``: their template looked up at k − entry
        (heights + ``zoff``); outside the template the nearest end (inactive)."""
        r = self.route[ids]
        j = k[None, :] - self.entry[ids, None]
        inside = (j >= 0) & (j <= self.length[r][:, None])
        kk = self.tpos.shape[1]
        flat = (r[:, None] * kk + np.clip(j, 0, kk - 1)).reshape(-1)
        pos = self.tpos.reshape(-1, 3).take(flat, axis=0).reshape(len(ids), len(k), 3)
        vel = self.tvel.reshape(-1, 3).take(flat, axis=0).reshape(len(ids), len(k), 3)
        pos[..., 2] += self.zoff[ids, None]
        seg = np.where(inside, self.tseg.reshape(-1).take(flat).reshape(len(ids), len(k)), SEG_STRAIGHT)
        return pos, vel, inside, seg.astype(np.int8)


def terminal_traffic(cfg: TrafficConfig, duration_s: float, dt: float, rng: np.random.Generator,
                     frame: geo.LocalFrame | None = None) -> TerminalTraffic:
    """The terminal-area schedule (module docstring): arrivals, departures, overflights,
    holding stacks, designed conflict and near-miss pairs, drawn from ``rng`` (per aircraft,
    never per sample); heights become tangent-plane z for ``frame`` (WGS-84; None: the sphere)
    when a window is looked up."""
    steps = int(round(duration_s / dt))
    counts = _counts(cfg, duration_s)
    tpl, kinds = _templates(cfg, dt)
    ra = _route_aircraft(rng, cfg, tpl, kinds, counts, duration_s, dt)
    entry = np.round(ra["entry"] / dt).astype(np.int64)
    pairs = _pairs(rng, cfg, counts["pairs"], counts["near"], dt, duration_s)
    n = len(entry) + len(pairs["t0"])
    role = np.concatenate([ra["role"], pairs["role"]])
    icao = np.array([f"{v:06x}" for v in rng.choice(0xFFFFFF, n, replace=False)])
    has_mode_s = rng.random(n) < cfg.mode_s_fraction
    callsign = np.array([f"{p}{v:04d}" for p, v in zip(rng.choice(["AFR", "EZY", "RYR", "DLH", "BAW", "TVF"], n),
                                                         rng.integers(1, 9999, n))])
    squawk = np.array([f"{v:04o}" for v in rng.integers(0o1000, 0o7777, n)])
    # drawn last: every earlier draw (and so every other column) is the same as without it
    downlinks = rng.random(n) < cfg.selected_alt_fraction
    selected = np.where(downlinks, np.concatenate([_routed_selected(cfg, ra), pairs["selected"]]), np.nan)
    change, nxt = _selected_changes(rng, cfg, tpl, ra, entry, n, dt)
    tpos, tvel, tseg, length = _template_grid(tpl)
    return TerminalTraffic(dt=dt, steps=steps, frame=frame, tpos=tpos, tvel=tvel, tseg=tseg, length=length,
                           route=ra["route"], entry=entry, zoff=ra["zoff"], pairs=pairs,
                           meta={"icao24": np.where(has_mode_s, icao, ""), "callsign": callsign, "role": role,
                                 "squawk": squawk},
                           selected_alt_m=selected, selected_change_s=np.where(downlinks, change, np.inf),
                           selected_next_m=np.where(downlinks, nxt, np.nan),
                           cleared_alt_m=np.concatenate([_routed_selected(cfg, ra), pairs["cleared"]]))


def terminal_area(cfg: TrafficConfig, duration_s: float, dt: float, rng: np.random.Generator,
                  frame: geo.LocalFrame | None = None) -> TrafficTrajectories:
    """Terminal-area traffic (:func:`terminal_traffic`) over the whole scenario, every aircraft
    (``truth_id`` = its index). Heights are converted to tangent-plane z for ``frame``.

    ``meta["role"]`` names each aircraft's kind; the designed losses of separation are the
    pairs whose role starts with ``conflict-``."""
    traffic = terminal_traffic(cfg, duration_s, dt, rng, frame)
    return traffic.window(0, traffic.steps + 1, every=True)


def _selected_changes(rng, cfg: TrafficConfig, tpl: list[dict], ra: dict[str, NDArray], entry: NDArray[np.int64],
                      n: int, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """When each aircraft's crew changes its selected altitude and to what (+inf / NaN: never):
    an arrival selects the missed-approach altitude once established on the glide path — a crew
    delay (``missed_approach_delay_s``) after its glide-path descent begins (the procedure's
    event, not read off the aircraft's future). The designed pairs and every other role keep
    their selection (level-bust semantics unchanged). One draw per aircraft, after every other."""
    delay = rng.uniform(*cfg.missed_approach_delay_s, n)
    change = np.full(n, np.inf)
    nxt = np.full(n, np.nan)
    m = len(ra["route"])
    arr = np.flatnonzero(ra["role"] == "arrival")
    k_gs = np.array([tpl[r].get("k_gs", 0) for r in ra["route"][arr]], np.int64)
    change[arr] = (entry[arr] + k_gs) * dt + delay[:m][arr]
    nxt[arr] = cfg.missed_approach_ft * FT
    return change, nxt


def _routed_selected(cfg: TrafficConfig, ra: dict[str, NDArray]) -> NDArray[np.float64]:
    """Selected altitude (height, m) of the procedural aircraft: the level each is cleared to —
    departures the SID top, arrivals 3 000 ft (:func:`_arrival_profiles`), holding aircraft and
    overflights the level they fly (their height offset ``zoff``)."""
    role = ra["role"]
    return np.where(role == "departure", float(flight_level_m(SID_TOP_FL, cfg.level_buffer_m)),
                    np.where(role == "arrival", ARRIVAL_CLEARED_M, ra["zoff"]))


# --------------------------------------------------------------------------- national day
#
# Domestic flights between the scenario's airports and overflights across the area, over a
# day (:func:`national_flights`), flown from templates looked up window by window
# (:func:`NationalTraffic.window`): the schedule of the whole day is a few arrays per flight,
# the (aircraft × samples) truth exists only for the window being simulated.
#
# The schedule is deconflicted as a controller's strategic plan would be: the flights are
# planned in order of entry, each at the first flight level of its route and the shortest delay
# (a departure held on the ground, an overflight held before it enters) at which it stays 5 NM and
# a buffer, or 1 000 ft, from every flight already planned above FL150 (:func:`conflict_offsets`,
# :func:`_allocate_levels`). Without it (two fixed levels per route, no plan) the peak hour
# held ~3 000 pairs of aircraft within 3 NM and 1 000 ft, most of them crossing at one level:
# the alert list of such a day is not that of any airspace. Below FL150 the runways' spacing
# orders the traffic (take-offs, landings); departures and arrivals of one runway are not
# sequenced against each other (mixed mode), which leaves pairs near the runways (see
# ``datasets/national.toml``): the tower's to separate, so the pipeline's aerodrome zones
# (:func:`aerodromes`) inhibit the STCA there and count no loss of separation.

NATIONAL_EPOCH_HOUR = 0               # the day starts at 00:00 UTC (the hourly curve is in UTC)
DEP_LEG_M = 10_000.0                  # runway heading after take-off before turning on course
FINAL_M = 30_000.0                    # straight-in final from the initial approach fix
TURN_LEG_M = 15_000.0                 # crosswind / downwind offset of a flight turning back
CLIMB_GRADIENT = 0.075                # 7.5 % climb to the cruise level
DESCENT_GRADIENT = 0.052              # ~3° descent from cruise, then the 3° glide path
CRUISE_SPEED = (210.0, 240.0)         # m/s true airspeed ≈ ground speed (no wind)
#: flight levels (hundreds of feet) a route's flights are planned at, by the semicircular rule:
#: domestic routes under 400 km, longer ones, the airways across the area
DOMESTIC_LEVELS_SHORT = (150, 270)
DOMESTIC_LEVELS_LONG = (250, 410)
AIRWAY_LEVELS = (250, 410)
#: overflight airways: entry bearing from the origin (deg) and lateral offset (km) of a straight
#: track across the area to the opposite side
NATIONAL_AIRWAYS = ((0.0, -120.0), (20.0, 60.0), (45.0, -40.0), (70.0, 150.0), (95.0, -200.0),
                    (120.0, 30.0), (150.0, -80.0), (165.0, 200.0))


def _semicircular_levels(track_deg: float, lo_fl: int, hi_fl: int) -> NDArray[np.int64]:
    """Flight levels of the semicircular rule between ``lo_fl`` and ``hi_fl``: odd thousands
    of feet for tracks 000–179°, even thousands for 180–359°."""
    odd = (track_deg % 360.0) < 180.0
    fls = np.arange(lo_fl - lo_fl % 10, hi_fl + 1, 10)
    return fls[(fls // 10) % 2 == (1 if odd else 0)]


def _domestic_profiles(cruise_m: float):
    """Speed and height along a domestic route of length L: 7.5 % climb from the runway,
    cruise, a 5.2 % descent joining the 3° glide path at 3 000 ft (as the terminal-area
    arrivals); speed 80 → 150 → cruise m/s climbing, cruise → 130 → 75 m/s descending."""
    tan = np.tan(np.radians(GLIDE_DEG))
    h3000 = 3000.0 * FT
    s_gs = (h3000 - TCH_M) / tan
    cruise_speed = 150.0 + 0.0085 * cruise_m          # ~220 m/s at FL270, ~245 at FL370

    def height(u, total):
        s = total - u
        down = np.where(s <= s_gs, TCH_M + s * tan, h3000 + (s - s_gs) * DESCENT_GRADIENT)
        return np.minimum(np.minimum(10.0 + CLIMB_GRADIENT * u, cruise_m), down)

    def speed(u, total):
        up = np.interp(u, [0.0, 12_000.0, 60_000.0], [80.0, 150.0, cruise_speed])
        down = np.interp(total - u, [10_000.0, 30_000.0, 120_000.0], [75.0, 130.0, cruise_speed])
        return np.minimum(up, down)
    return speed, height


def _domestic_route(a, b, rwy_a: float, rwy_b: float) -> tuple:
    """Waypoints A → runway heading 10 km → initial approach fix 30 km before B on its final → B.
    Each airport has one runway direction in use (``runway_deg``), for its take-offs and its
    landings alike: with each flight taking the end closer to its course, take-offs and
    landings met head-on on one runway."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    course = float(np.degrees(np.arctan2(*(b - a))))
    ua = np.array([np.sin(np.radians(rwy_a)), np.cos(np.radians(rwy_a))])
    ub = np.array([np.sin(np.radians(rwy_b)), np.cos(np.radians(rwy_b))])
    out, iaf = a + DEP_LEG_M * ua, b - FINAL_M * ub
    # a flight leaving or joining against the runway direction turns through a point abeam
    # (a departure's crosswind turn, an arrival's downwind and base): no turn over 90°
    base = [iaf + TURN_LEG_M * _side(ub, out - iaf)] if np.dot(iaf - out, ub) < 0 else []
    first = base[0] if base else iaf
    cross = [out + TURN_LEG_M * _side(ua, first - out)] if np.dot(first - out, ua) < 0 else []
    return tuple(map(tuple, (a, out, *cross, *base, iaf, b))), course


def _side(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """The unit normal of direction ``u`` on the side of vector ``v``."""
    n = np.array([u[1], -u[0]])
    return n if np.dot(n, v) >= 0 else -n


@dataclass
class NationalTraffic:
    """The day's schedule and the route templates it flies (see :func:`national_flights`).

    Per flight: template ``route``, ``entry`` sample (k = entry is the template's first
    sample), identity and ``role``; per template: padded (x, y, z) positions (tangent-plane z,
    heights converted once), velocities and segment codes, and its ``length`` in steps."""

    dt: float
    route: NDArray[np.int64]
    entry: NDArray[np.int64]
    role: NDArray[np.str_]
    meta: dict[str, NDArray]
    tpos: NDArray[np.float64]          # (R, K+1, 3)
    tvel: NDArray[np.float64]          # (R, K+1, 3)
    tseg: NDArray[np.int8]             # (R, K+1)
    length: NDArray[np.int64]          # (R,)
    epoch: datetime

    @property
    def n_flights(self) -> int:
        return len(self.route)

    def airborne(self, k: NDArray[np.int64]) -> NDArray[np.int64]:
        """Number of flights airborne at samples ``k``."""
        start, end = np.sort(self.entry), np.sort(self.entry + self.length[self.route])
        return np.searchsorted(start, k, "right") - np.searchsorted(end, k, "left")

    def window(self, k0: int, n: int) -> Trajectories:
        """Truth of the flights airborne during samples k0 … k0+n-1, on that grid (epoch
        shifted by k0·dt); ``truth_id`` is the flight number of the day. Looked up from the
        templates (no integration): identical whatever the window."""
        end = self.entry + self.length[self.route]
        ids = np.flatnonzero((self.entry <= k0 + n - 1) & (end >= k0))
        r = self.route[ids]
        j = np.arange(k0, k0 + n)[None, :] - self.entry[ids, None]
        inside = (j >= 0) & (j <= self.length[r][:, None])
        kk = self.tpos.shape[1]
        flat = r[:, None] * kk + np.clip(j, 0, kk - 1)
        pos = self.tpos.reshape(-1, 3).take(flat.reshape(-1), axis=0).reshape(len(ids), n, 3)
        vel = self.tvel.reshape(-1, 3).take(flat.reshape(-1), axis=0).reshape(len(ids), n, 3)
        seg = self.tseg.reshape(-1).take(flat)
        from datetime import timedelta
        return Trajectories(dt=self.dt, pos=pos, vel=vel, active=inside, segment=seg.astype(np.int8),
                            truth_id=ids.astype(np.int64), epoch=self.epoch + timedelta(seconds=k0 * self.dt),
                            meta={k: v[ids] for k, v in self.meta.items()})


def _national_templates(cfg, sites: NDArray[np.float64], dt: float, frame: geo.LocalFrame | None):
    """Every route flown at each of its flight levels: a domestic airport pair at the semicircular
    levels of :data:`DOMESTIC_LEVELS_SHORT` under 400 km, :data:`DOMESTIC_LEVELS_LONG` beyond;
    each airway direction at those of :data:`AIRWAY_LEVELS`. Returns the templates and, per
    template, (kind, origin airport, destination, route, flight level): the templates of one
    route differ by their level only, which :func:`_allocate_levels` chooses per flight."""
    tpl, info = [], []
    levels_short, levels_long = DOMESTIC_LEVELS_SHORT, DOMESTIC_LEVELS_LONG
    for i in range(len(sites)):
        for j in range(len(sites)):
            dist = float(np.hypot(*(sites[j] - sites[i])))
            if i == j or dist < cfg.min_route_km * 1000.0:
                continue
            wp, course = _domestic_route(sites[i], sites[j], cfg.airports[i].runway_deg, cfg.airports[j].runway_deg)
            lo, hi = levels_short if dist < 400_000.0 else levels_long
            group = info[-1][3] + 1 if info else 0
            for fl in _semicircular_levels(course, lo, hi):
                sp, hp = _domestic_profiles(float(flight_level_m(fl, 1.0)))
                hdg, ln, cv = _flyby(wp)
                tpl.append(_fly(wp[0], hdg, ln, cv, sp, hp, _vertical_seg(hp), dt))
                info.append(("domestic", i, j, group, int(fl)))
    half = cfg.area_half_width_km * 1000.0
    for bearing, offset_km in NATIONAL_AIRWAYS:
        for sign in (1.0, -1.0):
            b = np.radians(bearing + (0.0 if sign > 0 else 180.0))
            d = np.array([np.sin(b), np.cos(b)])
            p = -half * d + offset_km * 1000.0 * sign * np.array([d[1], -d[0]])
            wp = (tuple(p), tuple(p + 2 * half * d))
            track = float(np.degrees(b)) % 360.0
            group = info[-1][3] + 1 if info else 0
            for fl in _semicircular_levels(track, *AIRWAY_LEVELS):
                h = float(flight_level_m(fl, 1.0))
                hdg, ln, cv = _flyby(wp)
                spd = 225.0 + 2.0 * (fl - 310) / 10.0
                tpl.append(_fly(wp[0], hdg, ln, cv, _const(spd), _const(h), _level_seg, dt))
                info.append(("overflight", -1, -1, group, int(fl)))
    return tpl, info


#: strategic deconfliction of the schedule (:func:`_allocate_levels`) above FL150 (below, the
#: runways' spacing orders the traffic): flights planned 5 NM + 4 km or 1 000 ft apart, positions
#: compared every ``DECONFLICT_STRIDE_S``. Two aircraft close by at most 2 × 250 m/s × 4 s = 2 km
#: between samples, so planned pairs keep 5 NM — the en-route minimum the national airspace is
#: scored with above FL150 (``NationalConfig.enroute_floor_fl``) — and a controller's buffer above
#: it. Test seed, 08:00–09:00, pairs of aircraft both above FL145 within 5 NM / 3 NM: planned
#: 5 NM apart with delays up to 1 200 s, 64 / 16; 5 NM + 2 km, same delays, 52 / 27 (more flights
#: left unplaced); 5 NM + 2 km with delays up to 2 400 s, 5 / 1; 5 NM + 4 km, 7 / 4. The buffer
#: is what an STCA with the en-route minimum sees: at 5 NM + 2 km the pairs pass at its threshold
#: (5 NM plus margins) and the hour had 3 872 nuisance alerts, at 5 NM + 4 km 1 329.
DECONFLICT_R_M = 5 * 1852.0 + 4000.0
DECONFLICT_DZ_M = 1000 * FT
DECONFLICT_H_MIN_M = 150 * 100 * FT
DECONFLICT_STRIDE_S = 8.0
#: offsets (in strides) a conflict key holds: ± 2^14 strides, more than any flight's length
_OFFSET_BITS = 15


def conflict_offsets(pos_h: NDArray[np.float64], length: NDArray[np.int64], stride: int,
                     r_m: float = DECONFLICT_R_M, dz_m: float = DECONFLICT_DZ_M,
                     h_min_m: float = DECONFLICT_H_MIN_M) -> NDArray[np.int64]:
    """The sorted keys of every (template a, template b, entry offset) at which two flights
    would conflict: a flight on ``a`` entering at e and one on ``b`` entering at e' meet within
    ``r_m`` horizontally and ``dz_m`` vertically (above ``h_min_m``) when e − e' ≈ m·stride,
    key (a·T + b)·2^15 + m + 2^14 (:func:`_conflict_key`). ``pos_h``: templates' (x, y, height)
    samples (T, K+1, 3), read every ``stride`` samples. A flight at sample k_a of ``a`` meets one at
    k_b of ``b`` when e + k_a = e' + k_b, so the offsets are k_b − k_a over close sample pairs.
    The pairs are found per 1 000 ft band (a loop over bands, tens), against the band and the
    next one up."""
    T = len(length)
    kk = [np.arange(0, int(n) + 1, stride) for n in length]       # a loop over templates (hundreds)
    tid = np.repeat(np.arange(T), [len(k) for k in kk])
    ks = np.concatenate(kk)
    p = pos_h[tid, ks]
    up = p[:, 2] > h_min_m
    tid, ks, p = tid[up], ks[up], p[up]
    band = np.floor(p[:, 2] / dz_m).astype(np.int64)
    keys = []
    by_band = {int(b): np.flatnonzero(band == b) for b in np.unique(band)}
    from scipy.spatial import cKDTree
    for b, ia in by_band.items():
        ib = np.concatenate([ia, by_band.get(b + 1, np.zeros(0, np.int64))])
        got = cKDTree(p[ia, :2]).sparse_distance_matrix(cKDTree(p[ib, :2]), r_m, output_type="ndarray")
        i, j = ia[got["i"]], ib[got["j"]]
        ok = np.abs(p[i, 2] - p[j, 2]) < dz_m
        i, j = i[ok], j[ok]
        other = got["j"][ok] >= len(ia)              # pairs with the band above: add their mirror
        keys.append(_conflict_key(tid[i], tid[j], (ks[j] - ks[i]) // stride, T))
        keys.append(_conflict_key(tid[j[other]], tid[i[other]], (ks[i[other]] - ks[j[other]]) // stride, T))
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)


def _conflict_key(a: NDArray[np.int64], b: NDArray[np.int64], m: NDArray[np.int64], T: int) -> NDArray[np.int64]:
    return (a * T + b) * (1 << _OFFSET_BITS) + np.clip(m, -(1 << (_OFFSET_BITS - 1)) + 1,
                                                         (1 << (_OFFSET_BITS - 1)) - 1) + (1 << (_OFFSET_BITS - 1))


#: the delays a flight may take (s) when every level of its route conflicts: a departure held on
#: the ground, an overflight held before it enters (the area's neighbours regulating the flow)
DECONFLICT_DELAYS_S = (0.0, 60.0, 120.0, 180.0, 300.0, 420.0, 600.0, 900.0, 1200.0, 1500.0, 1800.0, 2400.0)


def _allocate_levels(route: NDArray[np.int64], entry: NDArray[np.int64], land: NDArray[np.int64],
                     levels: list[NDArray[np.int64]], group: NDArray[np.int64], length: NDArray[np.int64],
                     keys: NDArray[np.int64], stride: int, origin: NDArray[np.int64], dest: NDArray[np.int64],
                     take_off_gap: int, landing_gap: int, delays: NDArray[np.int64]
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """Each flight's level and delay, as a controller's strategic plan would give them: flights
    in order of entry, each takes the first (delay, level) of its route (``levels[group]``, its
    drawn level first, the shortest delay first) at which it conflicts with no flight already
    planned (``keys``: :func:`conflict_offsets`) and keeps its runways' spacing (``origin`` /
    ``dest``: airport per template, −1 for an overflight; take-offs ``take_off_gap``, landings
    ``landing_gap`` samples apart), else the one with the fewest conflicts. A domestic flight keeps
    its landing time (``land``; −1 for an overflight) plus its delay and takes off earlier or later
    by its level's flight time. Returns (template, entry, flights left in conflict). Sequential by
    nature (each choice depends on the earlier ones): a loop over flights, each tested at once
    against the flights airborne with it."""
    T = len(length)
    order = np.argsort(entry, kind="stable")
    out_r, out_e = route.copy(), entry.copy()
    big = np.iinfo(np.int64).max // 4
    ends = np.full(len(route), -big)            # planned flights' last sample (unplanned: never)
    lands = np.full(len(route), -big)           # planned flights' landing sample (overflight: never)
    done_e = np.zeros(len(route), np.int64)
    reach = int(length.max()) + int(delays.max()) + 3600
    sorted_entries = entry[order]
    pair_any = np.zeros(T * T, bool)
    pair_any[np.unique(keys >> _OFFSET_BITS)] = True
    left = 0
    for rank, f in enumerate(order):
        lv = levels[group[route[f]]]
        lv = np.concatenate([[route[f]], lv[lv != route[f]]])
        cand = np.tile(lv, len(delays))                     # (delay, level), shortest delay first
        d = np.repeat(delays, len(lv))
        domestic = land[f] >= 0
        e = (land[f] + d - length[cand]) if domestic else entry[f] + d
        lo = np.searchsorted(sorted_entries, e.min() - reach, "left")
        near = order[lo:rank]
        near = near[ends[near] >= e.min()]
        ok = np.ones(len(cand), bool)
        if domestic and len(near):                  # the runways' spacing at both ends
            o, g = origin[cand[0]], dest[cand[0]]
            ro, rd = origin[out_r[near]], dest[out_r[near]]
            ok &= np.all(np.abs(e[:, None] - done_e[near[ro == o]][None, :]) >= take_off_gap, axis=1)
            ok &= np.all(np.abs((land[f] + d)[:, None] - lands[near[rd == g]][None, :]) >= landing_gap, axis=1)
        hits = np.zeros(len(cand), np.int64)
        for c in range(len(cand)):                  # a route's (delay, level) choices (tens)
            rel = near[pair_any[cand[c] * T + out_r[near]]]
            if len(rel):
                q = _conflict_key(np.full(len(rel), cand[c]), out_r[rel],
                                  np.rint((e[c] - done_e[rel]) / stride).astype(np.int64), T)
                at = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
                hits[c] = int((keys[at] == q).sum())
            if hits[c] == 0 and ok[c]:
                break
        # the first free choice; else the fewest conflicts, keeping the runways' spacing if any can
        score = hits + np.where(ok, 0, 1 << 20)
        score[c + 1:] = big                          # untried choices
        best = int(np.argmin(score))
        left += int(hits[best] > 0)
        out_r[f], out_e[f] = cand[best], e[best]
        done_e[f], ends[f] = e[best], e[best] + length[cand[best]]
        lands[f] = land[f] + d[best] if domestic else -big
    return out_r, out_e, left


def _allocate_levels_compiled(route: NDArray[np.int64], entry: NDArray[np.int64], land: NDArray[np.int64],
                              levels: list[NDArray[np.int64]], group: NDArray[np.int64], length: NDArray[np.int64],
                              keys: NDArray[np.int64], stride: int, origin: NDArray[np.int64],
                              dest: NDArray[np.int64], take_off_gap: int, landing_gap: int, delays: NDArray[np.int64]
                              ) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """:func:`_allocate_levels`, the same plan, compiled
    (:func:`tertiary.simulate.plan_kernel.plan`)."""
    from tertiary.simulate.plan_kernel import plan
    T = len(length)
    i64 = lambda a: np.ascontiguousarray(a, np.int64)        # noqa: E731 - one signature
    pair_any = np.zeros(T * T, np.bool_)
    pair_any[np.unique(keys >> _OFFSET_BITS)] = True
    lv_ptr = np.concatenate([[0], np.cumsum([len(v) for v in levels])])
    lv_idx = np.concatenate(levels) if levels else np.zeros(0, np.int64)
    out_r, out_e = i64(route).copy(), i64(entry).copy()
    reach = int(length.max()) + int(np.max(delays)) + 3600
    left = plan(i64(np.argsort(entry, kind="stable")), i64(route), i64(entry), i64(land), i64(lv_ptr), i64(lv_idx),
                i64(group), i64(length), i64(keys), pair_any, int(stride), i64(origin), i64(dest),
                int(take_off_gap), int(landing_gap), i64(delays), reach, _OFFSET_BITS, out_r, out_e)
    return out_r, out_e, int(left)


def _template_grid(tpl: list[dict]):
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


def _spaced(t: NDArray[np.float64], lane: NDArray[np.int64], gap: float) -> NDArray[np.float64]:
    """Times pushed later so that within a lane consecutive times are ≥ ``gap`` apart, each
    moved as little as possible: t'_i = i·gap + max_{j≤i}(t_j − j·gap) (vectorised recurrence
    t'_i = max(t_i, t'_{i−1} + gap))."""
    order = np.lexsort((t, lane))
    ts, ls = t[order], lane[order]
    first = np.searchsorted(ls, ls, "left")
    rank = np.arange(len(ts)) - first
    shifted = ts - rank * gap
    # running max restarted per lane: offset each lane above all earlier ones
    span = (np.abs(shifted).max() + 1.0) * 4.0 if len(ts) else 1.0
    lane_rank = np.cumsum(np.r_[0, ls[1:] != ls[:-1]]) if len(ts) else ls
    run = np.maximum.accumulate(shifted + lane_rank * span) - lane_rank * span
    out = np.empty_like(t)
    out[order] = run + rank * gap
    return out


def _entry_times(rng, weights: NDArray[np.float64], n: int, duration_s: float) -> NDArray[np.float64]:
    """``n`` times over the day with a density following the hourly weights (piecewise linear
    between hour centres, periodic), by inverse transform sampling; an hour before the start
    too, so that the day opens with traffic airborne."""
    hours = np.arange(-2, 27) + 0.5
    w = np.asarray(weights)[np.mod(np.floor(hours), 24).astype(int)]
    grid = np.linspace(-3600.0, duration_s, 4000)
    dens = np.interp(grid / 3600.0, hours, w)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    return np.interp(rng.uniform(0.0, cdf[-1], n), cdf, grid)


@functools.lru_cache(maxsize=2)
def _national_routes(airports: tuple, min_route_km: float, half_width_km: float, dt: float,
                     frame: geo.LocalFrame, stride: int) -> tuple:
    """The national templates in the system frame (:func:`_template_grid`, tangent-plane z), their
    (kind, origin, destination, route, level) and :func:`conflict_offsets`: what the schedule
    flies and is planned on. They depend on the airports and the area only (not on the traffic's
    amount or draws), so a process simulating the scenario again reuses them (read-only)."""
    from types import SimpleNamespace
    cfg = SimpleNamespace(airports=airports, min_route_km=min_route_km, area_half_width_km=half_width_km)
    sites = np.column_stack(frame.from_geodetic([a.lat_deg for a in airports],
                                                [a.lon_deg for a in airports], 0.0)[:2])
    tpl, info = _national_templates(cfg, sites, dt, frame)
    tpos, tvel, tseg, length = _template_grid(tpl)
    keys = conflict_offsets(tpos, length, stride)          # positions are (x, y, height) here
    # a template's padding (its last sample repeated) is never flown: the sphere's z is enough there
    heights_to_enu(tpos, tvel, frame, active=np.arange(tpos.shape[1])[None, :] <= length[:, None])
    for a in (tpos, tvel, tseg, length, keys):
        a.flags.writeable = False
    return tpos, tvel, tseg, length, info, keys


def national_flights(cfg, duration_s: float, dt: float, rng: np.random.Generator, frame: geo.LocalFrame,
                     epoch) -> NationalTraffic:
    """The day's traffic (:class:`tertiary.simulate.config.NationalConfig`): domestic flights
    between airports chosen by weight (pairs closer than ``min_route_km`` excluded), landings
    at an airport ≥ ``landing_spacing_s`` apart; overflights on the airways, entries on a
    (route, level) lane ≥ ``lane_spacing_s`` apart. Entry times follow the hourly curve; the
    number of flights is scaled so that the airborne count peaks at ``peak_airborne``
    (computed on the schedule, one rescaling pass). Then each flight's level and delay are
    planned (:func:`_allocate_levels`): apart from the flights planned before it above FL150,
    take-offs ≥ ``departure_spacing_s`` and landings ≥ ``landing_spacing_s`` apart where the
    runways allow."""
    stride = max(1, int(round(DECONFLICT_STRIDE_S / dt)))
    tpos, tvel, tseg, length, info, keys = _national_routes(cfg.airports, cfg.min_route_km, cfg.area_half_width_km,
                                                            dt, frame, stride)
    kind = np.array([k for k, *_ in info])
    orig, dest = np.array([i[1] for i in info]), np.array([i[2] for i in info])
    group = np.array([i[3] for i in info])
    levels = [np.flatnonzero(group == g) for g in range(int(group.max()) + 1)]
    dom, ovf = np.flatnonzero(kind == "domestic"), np.flatnonzero(kind == "overflight")
    w = np.array([a.weight for a in cfg.airports])
    # an airport pair's share by its airports' weights, spread over its levels
    p_dom = w[orig[dom]] * w[dest[dom]] / np.array([len(levels[g]) for g in group[dom]])
    p_dom = p_dom / p_dom.sum()
    seeds = rng.spawn(2)
    day = max(duration_s, 86400.0)      # the whole day is scheduled: a shorter run is its first hours

    def schedule(n: int, r: np.random.Generator):
        n_ovf = int(round(cfg.overflight_fraction * n))
        route = np.concatenate([r.choice(dom, n - n_ovf, p=p_dom), r.choice(ovf, n_ovf)])
        t = _entry_times(r, cfg.hourly_curve, n, day)
        is_dom = kind[route] == "domestic"
        land = t + length[route] * dt
        land = np.where(is_dom, _spaced(land, np.where(is_dom, dest[route], -1), cfg.landing_spacing_s), land)
        t = np.where(is_dom, land - length[route] * dt, _spaced(t, route, cfg.lane_spacing_s))
        return route, np.round(t / dt).astype(np.int64)

    n = 20_000
    probe_rng = np.random.default_rng(seeds[0].integers(2 ** 63))
    for _ in range(2):        # spacing delays flights at busy hours: scale twice to reach the peak
        route, entry = schedule(n, probe_rng)
        probe = NationalTraffic(dt, route, entry, np.zeros(0, str), {}, tpos, tvel, tseg, length, epoch)
        peak = probe.airborne(np.arange(0, int(day / dt) + 1, max(1, int(60 / dt)))).max()
        n = max(2, int(round(n * cfg.peak_airborne / max(peak, 1))))
    route, entry = schedule(n, seeds[1])
    land = np.where(kind[route] == "domestic", entry + length[route], -1)
    route, entry, _ = _allocate_levels_compiled(route, entry, land, levels, group, length, keys, stride, orig, dest,
                                                int(round(cfg.departure_spacing_s / dt)),
                                                int(round(cfg.landing_spacing_s / dt)),
                                                np.rint(np.asarray(DECONFLICT_DELAYS_S) / dt).astype(np.int64))
    order = np.argsort(entry, kind="stable")          # flight numbers in order of entry
    route, entry = route[order], entry[order]
    role = np.where(kind[route] == "domestic", "domestic", "overflight")
    names = np.array([a.name for a in cfg.airports])
    icao = np.array([f"{v:06x}" for v in rng.choice(np.arange(0x380000, 0x3C0000), n, replace=False)])
    has_s = rng.random(n) < 0.97
    airline = rng.choice(["AFR", "EZY", "RYR", "DLH", "BAW", "TVF", "VLG", "KLM", "SWR", "HOP"], n)
    meta = {"icao24": np.where(has_s, icao, ""),
            "callsign": np.char.add(airline, np.char.zfill(rng.integers(1, 9999, n).astype(str), 4)),
            "role": role, "squawk": np.array([f"{v:04o}" for v in rng.integers(0o1000, 0o7777, n)]),
            "origin": np.where(orig[route] >= 0, names[np.maximum(orig[route], 0)], ""),
            "destination": np.where(dest[route] >= 0, names[np.maximum(dest[route], 0)], "")}
    return NationalTraffic(dt, route, entry, role, meta, tpos, tvel, tseg, length, epoch)


def final_approaches(scenario, frame: "geo.LocalFrame | None" = None) -> list[tuple[float, float, float, float]]:
    """The scenario's final approaches as (threshold x, threshold y, final course deg true, length m)
    in the system frame — what an STCA is adapted with (``safety.conflicts.ApproachVolume``):
    terminal-area, runway 27 from the intercept point I; national, both ends of every airport's
    runway out to the initial approach fix (``frame``: the system frame). Other kinds: none."""
    if scenario.kind == "terminal-area":
        return [(THRESHOLD[0], THRESHOLD[1], 270.0, ARRIVALS[0][-2][0] - THRESHOLD[0])]
    return [(x, y, (a.runway_deg + end) % 360.0, FINAL_M)
            for a, x, y in _airports_xy(scenario, frame) for end in (0.0, 180.0)]


def _airports_xy(scenario, frame: "geo.LocalFrame | None") -> list[tuple]:
    """(airport, x, y) of a national scenario's airports in the system frame; none otherwise."""
    if scenario.kind != "national" or scenario.national is None or frame is None:
        return []
    aps = scenario.national.airports
    x, y, _ = frame.from_geodetic([a.lat_deg for a in aps], [a.lon_deg for a in aps], 0.0)
    return [(a, float(xi), float(yi)) for a, xi, yi in zip(aps, np.atleast_1d(x), np.atleast_1d(y))]


def aerodromes(scenario, frame: "geo.LocalFrame | None" = None) -> list[tuple[str, float, float]]:
    """The scenario's aerodromes as (name, x, y) in the system frame (``frame``), where the
    aerodrome controller separates its departures and arrivals (``safety.conflicts.AerodromeZone``):
    national, every airport (its flights take off from and land at its reference point). Other
    kinds: none (terminal-area's planted encounters are radar-controlled ones)."""
    return [(a.name, x, y) for a, x, y in _airports_xy(scenario, frame)]
