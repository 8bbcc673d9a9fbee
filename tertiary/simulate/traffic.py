"""Truth trajectory generators: the seed's big box (§4.2.1) and terminal-area traffic.

All generators build piecewise-constant command arrays (speed, turn rate, vertical rate) of
shape (aircraft, steps) without per-aircraft Python loops and integrate them exactly with
:func:`tertiary.simulate.trajectory.integrate_commands`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tertiary.simulate.config import TrafficConfig
from tertiary.simulate.trajectory import (SEG_CLIMB, SEG_DESCENT, SEG_HOLD, SEG_STRAIGHT, SEG_TURN,
                                          Trajectories, integrate_commands)

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


def _u(rng: np.random.Generator, lo_hi: tuple[float, float], size) -> NDArray[np.float64]:
    return rng.uniform(lo_hi[0], lo_hi[1], size)


def _wrap180(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.mod(a + 180.0, 360.0) - 180.0


def _expand(values: NDArray, durations: NDArray[np.int64], steps: int) -> NDArray:
    """Piecewise-constant (A, S) segment values with integer durations to (A, steps)."""
    cum = np.minimum(np.cumsum(durations, axis=1), steps)
    clipped = np.diff(np.concatenate([np.zeros((len(cum), 1), np.int64), cum], axis=1), axis=1)
    short = cum[:, -1] < steps          # pad with the last segment's value
    clipped[:, -1] += np.where(short, steps - cum[:, -1], 0)
    return np.repeat(values.ravel(), clipped.ravel()).reshape(len(values), steps)


def _horizontal_schedule(rng, cfg: TrafficConfig, start_xy, heading0, speed, steps, dt):
    """Alternating straight legs and coordinated turns steering toward random waypoints near
    the centre, so aircraft weave inside the terminal area. Segment-level loop (≤ ~2·T/60
    iterations), vectorised over aircraft."""
    n = len(speed)
    n_seg = int(np.ceil(steps * dt / cfg.straight_s[0])) + 2
    dur = np.zeros((n, 2 * n_seg), np.int64)
    rate = np.zeros((n, 2 * n_seg))
    pos = start_xy.copy()
    hdg = heading0.copy()
    for s in range(n_seg):
        d = np.round(_u(rng, cfg.straight_s, n) / dt).astype(np.int64)
        dur[:, 2 * s] = d
        rad = np.radians(hdg)
        pos = pos + (speed * d * dt)[:, None] * np.stack([np.sin(rad), np.cos(rad)], axis=1)
        wp = rng.normal(0.0, cfg.area_radius_m / 3, (n, 2))
        want = np.degrees(np.arctan2(wp[:, 0] - pos[:, 0], wp[:, 1] - pos[:, 1]))
        angle = _wrap180(want - hdg + rng.uniform(-20, 20, n))
        angle = np.where(np.abs(angle) < 10.0, 0.0, angle)
        w = _u(rng, cfg.turn_rate_dps, n) * np.sign(angle)
        td = np.round(np.abs(angle) / np.maximum(np.abs(w), 1e-9) / dt).astype(np.int64)
        dur[:, 2 * s + 1] = td
        rate[:, 2 * s + 1] = np.where(td > 0, angle / np.maximum(td * dt, 1e-9), 0.0)
        # chord of the arc, good enough for steering decisions
        mid = np.radians(hdg + angle / 2)
        r_turn = speed / np.radians(np.maximum(np.abs(w), 1e-9))
        chord = 2 * r_turn * np.abs(np.sin(np.radians(angle) / 2))
        pos = pos + chord[:, None] * np.stack([np.sin(mid), np.cos(mid)], axis=1)
        hdg = hdg + angle
    return _expand(rate, dur, steps)


def _holding_schedule(n: int, steps: int, dt: float, rate_dps: float = 3.0, leg_s: float = 60.0):
    """Standard right-hand racetrack: 60 s legs, 180° turns at 3°/s."""
    turn_s = 180.0 / rate_dps
    cycle = np.array([leg_s, turn_s, leg_s, turn_s])
    reps = int(np.ceil(steps * dt / cycle.sum())) + 1
    durations = np.round(np.tile(cycle, reps) / dt).astype(np.int64)
    rates = np.tile([0.0, rate_dps, 0.0, rate_dps], reps)
    return _expand(np.broadcast_to(rates, (n, len(rates))).copy(),
                   np.broadcast_to(durations, (n, len(durations))).copy(), steps)


def _vertical_schedule(rng, cfg: TrafficConfig, z0, steps, dt):
    """Level flight alternating with climbs/descents that stay inside the altitude band."""
    n = len(z0)
    lo, hi = cfg.altitude_m
    n_seg = int(np.ceil(steps * dt / 120.0)) + 2
    dur = np.zeros((n, 2 * n_seg), np.int64)
    vz = np.zeros((n, 2 * n_seg))
    z = z0.copy()
    for s in range(n_seg):
        dur[:, 2 * s] = np.round(rng.uniform(120, 600, n) / dt).astype(np.int64)
        rate = _u(rng, cfg.vertical_rate_mps, n)
        target = rng.uniform(lo, hi, n)
        signed = np.where(target > z, rate, -rate)
        d = np.floor(np.abs(target - z) / rate / dt).astype(np.int64)
        dur[:, 2 * s + 1] = d
        vz[:, 2 * s + 1] = signed
        z = z + signed * d * dt
    return _expand(vz, dur, steps)


def terminal_area(cfg: TrafficConfig, duration_s: float, dt: float, rng: np.random.Generator) -> Trajectories:
    """Terminal-area traffic: weaving transits with turns and level changes, holding stacks,
    and designed crossing / converging / head-on pairs that lose separation."""
    steps = int(round(duration_s / dt))
    n_pairs = min(cfg.conflict_pairs, cfg.aircraft // 2)
    n_conf = 2 * n_pairs
    n_hold = int(round(cfg.holding_fraction * (cfg.aircraft - n_conf)))
    n_free = cfg.aircraft - n_conf - n_hold
    n = cfg.aircraft

    speed = _u(rng, cfg.speed_mps, n)
    life = np.minimum(_u(rng, cfg.lifetime_s, n), duration_s)
    t_start = rng.uniform(0.0, 1.0, n) * (duration_s - life)

    # free aircraft: enter on a ring heading roughly inward
    bearing = rng.uniform(0, 360, n_free)
    ring = cfg.area_radius_m * np.sqrt(rng.uniform(0.3, 1.0, n_free))
    start_free = ring[:, None] * np.stack([np.sin(np.radians(bearing)), np.cos(np.radians(bearing))], axis=1)
    hdg_free = np.mod(bearing + 180.0 + rng.uniform(-45, 45, n_free), 360.0)
    turn_free = _horizontal_schedule(rng, cfg, start_free, hdg_free, speed[:n_free], steps, dt)
    z_free = _u(rng, cfg.altitude_m, n_free)
    vz_free = _vertical_schedule(rng, cfg, z_free, steps, dt)

    # holding aircraft: stacks over a few fixes, 1000 ft (304.8 m) apart
    n_fix = max(1, int(np.ceil(n_hold / 6)))
    fixes = rng.uniform(-0.6, 0.6, (n_fix, 2)) * cfg.area_radius_m
    fix_of = np.arange(n_hold) % n_fix
    level = np.arange(n_hold) // n_fix
    start_hold = fixes[fix_of] if n_hold else np.zeros((0, 2))
    hdg_hold = np.repeat(rng.uniform(0, 360, n_fix), np.bincount(fix_of, minlength=n_fix))[np.argsort(np.argsort(fix_of))] if n_hold else np.zeros(0)
    turn_hold = _holding_schedule(n_hold, steps, dt)
    z_hold = 1500.0 + 304.8 * level
    speed[n_free:n_free + n_hold] = np.minimum(speed[n_free:n_free + n_hold], 110.0)

    # conflict pairs: straight and level, meeting near a point at time t_c with a small miss
    t_c = rng.uniform(0.25, 0.75, n_pairs) * duration_s
    meet = rng.uniform(-0.5, 0.5, (n_pairs, 2)) * cfg.area_radius_m
    kind = rng.integers(0, 3, n_pairs)  # 0 crossing, 1 converging, 2 head-on
    delta = np.choose(kind, [rng.uniform(60, 120, n_pairs), rng.uniform(15, 40, n_pairs),
                             rng.uniform(170, 190, n_pairs)]) * rng.choice([-1, 1], n_pairs)
    h_a = rng.uniform(0, 360, n_pairs)
    h_b = np.mod(h_a + delta, 360.0)
    sa, sb = speed[n - n_conf:n - n_pairs], speed[n - n_pairs:]
    va = sa[:, None] * np.stack([np.sin(np.radians(h_a)), np.cos(np.radians(h_a))], axis=1)
    vb = sb[:, None] * np.stack([np.sin(np.radians(h_b)), np.cos(np.radians(h_b))], axis=1)
    rel = va - vb
    perp = np.stack([-rel[:, 1], rel[:, 0]], axis=1) / np.linalg.norm(rel, axis=1, keepdims=True)
    miss = _u(rng, cfg.conflict_miss_m, n_pairs)
    z_conf = rng.uniform(max(cfg.altitude_m[0], 2000.0), cfg.altitude_m[1], n_pairs)
    dz = rng.uniform(-150.0, 150.0, n_pairs)
    pair_life = np.minimum(rng.uniform(900, 1800, n_pairs), duration_s)
    t0_pair = np.clip(t_c - pair_life * rng.uniform(0.6, 0.8, n_pairs), 0.0, None)
    t1_pair = np.minimum(t0_pair + pair_life, duration_s)

    # assemble commands (A, steps)
    turn = np.zeros((n, steps))
    vz = np.zeros((n, steps))
    turn[:n_free], vz[:n_free] = turn_free, vz_free
    turn[n_free:n_free + n_hold] = turn_hold
    heading0 = np.concatenate([hdg_free, hdg_hold, h_a, h_b])
    z0 = np.concatenate([z_free, z_hold, z_conf, z_conf + dz])
    spd = np.broadcast_to(speed[:, None], (n, steps)).copy()
    pos, vel = integrate_commands(np.column_stack([np.zeros((n, 2)), z0]), heading0, spd, turn, vz, dt)

    # anchor each aircraft: free/holding at their start time, conflict pairs at t_c
    anchor_t = np.concatenate([t_start[:n_free + n_hold], t_c, t_c])
    anchor_xy = np.concatenate([start_free, start_hold, meet, meet + miss[:, None] * perp])
    k_anchor = np.clip(np.round(anchor_t / dt).astype(int), 0, steps)
    shift = anchor_xy - pos[np.arange(n), k_anchor, :2]
    for c in range(2):          # per component: a (n, 1, 2) broadcast runs 2-long inner loops
        pos[:, :, c] += shift[:, c:c + 1]

    t_grid = np.arange(steps + 1) * dt
    t_start = np.concatenate([t_start[:n_free + n_hold], t0_pair, t0_pair])
    t_end = np.concatenate([(t_start + life)[:n_free + n_hold], t1_pair, t1_pair])
    active = (t_grid[None, :] >= t_start[:, None]) & (t_grid[None, :] <= t_end[:, None])

    last_turn = np.concatenate([turn, turn[:, -1:]], axis=1)
    last_vz = np.concatenate([vz, vz[:, -1:]], axis=1)
    seg = np.full((n, steps + 1), SEG_STRAIGHT, np.int8)
    seg[last_vz > 0] = SEG_CLIMB
    seg[last_vz < 0] = SEG_DESCENT
    seg[last_turn != 0] = SEG_TURN
    seg[n_free:n_free + n_hold] = SEG_HOLD

    icao = np.array([f"{v:06x}" for v in rng.choice(0xFFFFFF, n, replace=False)])
    has_mode_s = rng.random(n) < cfg.mode_s_fraction
    callsign = np.array([f"{p}{v:04d}" for p, v in zip(rng.choice(["AFR", "EZY", "RYR", "DLH", "BAW", "TVF"], n),
                                                         rng.integers(1, 9999, n))])
    role = np.array(["transit"] * n_free + ["holding"] * n_hold + ["conflict"] * n_conf)
    return Trajectories(dt=dt, pos=pos, vel=vel, active=active, segment=seg, truth_id=np.arange(n, dtype=np.int64),
                        meta={"icao24": np.where(has_mode_s, icao, ""), "callsign": callsign, "role": role,
                              "squawk": np.array([f"{v:04o}" for v in rng.integers(0o1000, 0o7777, n)])})
