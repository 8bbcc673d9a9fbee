"""Terminal-area traffic that flies procedures (:func:`terminal_traffic`).

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
  1.15–1.45 × the horizontal minimum. Each pair has its own (zone, level, time) slot; a short
  or small scenario gets as many pairs as are sure to fit (:func:`pair_counts`), conflicts
  before near misses.

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
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.errors import OptionError
from tertiary.core.units import FT
from tertiary.simulate.config import TrafficConfig
from tertiary.simulate.trajectory import DEFAULT_EPOCH, SEG_CLIMB, SEG_HOLD, SEG_STRAIGHT
from tertiary.simulate.traffic.base import (GLIDE_DEG, TCH_M, THRESHOLD, TrafficTrajectories, constant, flight_level_m, fly,
                                            flyby, heights_to_enu, level_segments, template_grid, uniform,
                                            vertical_segments)

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
ARRIVAL_CLEARED_M = 3000.0 * FT
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
        hdg, ln, cv = flyby(wp)
        kinds["arrival"].append(len(out))
        t = fly(wp[0], hdg, ln, cv, sp, hp, vertical_segments(hp), dt)
        # the glide-path descent begins after the last sample at the 3 000 ft approach altitude
        t["k_gs"] = int(np.flatnonzero(t["pos"][:, 2] >= ARRIVAL_CLEARED_M - 0.01)[-1])
        out.append(t)
    sp, hp = _departure_profiles(cfg.level_buffer_m)
    for wp in DEPARTURES:
        hdg, ln, cv = flyby(wp)
        kinds["departure"].append(len(out))
        out.append(fly(wp[0], hdg, ln, cv, sp, hp, vertical_segments(hp), dt))
    for track, point, speed, _levels in AIRWAYS:
        a, b = _airway(track, point)
        hdg, ln, cv = flyby((a, b))
        kinds["airway"].append(len(out))
        out.append(fly(a, hdg, ln, cv, constant(speed), constant(0.0), level_segments, dt))
    for fix in HOLD_FIXES:
        for laps in HOLD_LAPS:
            start, hdg, ln, cv, hold = _holding_route(fix, laps)
            bounds = np.concatenate([[0.0], np.cumsum(ln)])

            def seg(u, total, bounds=bounds, hold=hold):
                piece = np.clip(np.searchsorted(bounds, u, "right") - 1, 0, len(hold) - 1)
                return np.where(hold[piece] == 1, SEG_HOLD, SEG_STRAIGHT).astype(np.int8)
            t = fly(start, hdg, ln, cv, constant(HOLD_SPEED), constant(0.0), seg, dt)
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


#: time a designed pair holds its (zone, level) lane: its active span and a minute either side
PAIR_SLOT_S = PAIR_LEAD_S + PAIR_TRAIL_S + 120.0
#: spread of the conflicts' closest approaches over the run (fractions of the duration) and their jitter (s)
CONFLICT_SPAN, PAIR_JITTER_S = (0.2, 0.8), 20.0


def _conflicts_together(n_conf: int, duration_s: float) -> int:
    """Most conflicts whose lanes can be busy at the same time: their closest approaches are
    evenly spread over :data:`CONFLICT_SPAN`, each moved by up to the jitter (and a sample's
    rounding), and two overlap when less than :data:`PAIR_SLOT_S` apart."""
    if n_conf <= 1:
        return n_conf
    spacing = (CONFLICT_SPAN[1] - CONFLICT_SPAN[0]) * duration_s / (n_conf - 1)
    if spacing <= 0.0:
        return n_conf
    reach = 2.0 * (PAIR_SLOT_S + 2.0 * PAIR_JITTER_S) + 60.0      # + 60 s: rounding to the sample grid
    return min(n_conf, int(reach // spacing) + 1)


def pair_counts(conflicts: int, near_misses: int, aircraft: int, duration_s: float) -> tuple[int, int]:
    """The designed (conflict, near-miss) pairs a scenario gets: what the aircraft allow and what
    is sure to find a lane. First-fit placement (:func:`_place_pairs`) only fails a pair when every
    one of the zone × level lanes holds an overlapping pair, so it always succeeds when no pair
    overlaps more than ``lanes − 1`` others: near misses are drawn anywhere (count them all as
    overlapping), conflicts are evenly spread. Near misses are dropped first, then conflicts."""
    lanes = len(PAIR_ZONES) * len(PAIR_LEVELS)
    n_conf = min(conflicts, aircraft // 2)
    n_near = min(near_misses, (aircraft - 2 * n_conf) // 2)
    while n_conf + n_near > 0 and _conflicts_together(n_conf, duration_s) + n_near > lanes:
        if n_near:
            n_near -= 1
        else:
            n_conf -= 1
    return n_conf, n_near


def _counts(cfg: TrafficConfig, duration_s: float) -> dict[str, int]:
    n = cfg.aircraft
    pairs, near = pair_counts(cfg.conflict_pairs, cfg.near_miss_pairs, n, duration_s)
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
        lo, hi = t_c[p] - PAIR_LEAD_S - 60.0, t_c[p] + PAIR_TRAIL_S + 60.0     # PAIR_SLOT_S long
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
    t_c = np.concatenate([np.linspace(*CONFLICT_SPAN, n_conf) if n_conf > 1 else np.full(n_conf, 0.5),
                          rng.uniform(0.15, 0.85, n_near)]) * duration_s + rng.uniform(-PAIR_JITTER_S,
                                                                                       PAIR_JITTER_S, n_p)
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
    miss = np.where(kind == 3, rng.uniform(1.15, 1.45, n_p) * cfg.sep_h_m, uniform(rng, cfg.conflict_miss_m, n_p))
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
    tpos, tvel, tseg, length = template_grid(tpl)
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
