"""The national day: domestic flights between the scenario's airports and overflights across
the area, over a day (:func:`national_flights`), flown from templates looked up window by window
(:func:`NationalTraffic.window`): the schedule of the whole day is a few arrays per flight, the
(aircraft × samples) truth exists only for the window being simulated.

The schedule is deconflicted as a controller's strategic plan would be: the flights are
planned in order of entry, each at the first flight level of its route and the shortest delay
(a departure held on the ground, an overflight held before it enters) at which it stays 5 NM and
a buffer, or 1 000 ft, from every flight already planned above FL150 (:func:`conflict_offsets`,
:func:`allocate_levels`). Without it (two fixed levels per route, no plan) the peak hour
holds thousands of pairs of aircraft within 3 NM and 1 000 ft, most of them crossing at one
level: the alert list of such a day is not that of any airspace. Below FL150 the runways' spacing
orders the traffic (take-offs, landings); departures and arrivals of one runway are not
sequenced against each other (mixed mode), which leaves pairs near the runways (see
``datasets/national.toml``): the tower's to separate, so the pipeline's aerodrome zones
(:func:`aerodromes`) inhibit the STCA there and count no loss of separation.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from datetime import datetime, timedelta
from types import SimpleNamespace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tertiary.core import geo
from tertiary.core.units import FT
from tertiary.simulate.plan_kernel import plan
from tertiary.simulate.trajectory import SEG_DESCENT, Trajectories
from tertiary.simulate.traffic.base import (GLIDE_DEG, TCH_M, THRESHOLD, TrafficTrajectories, constant, flight_level_m,
                                            fly, flyby, heights_to_enu, level_segments, template_grid,
                                            vertical_segments)
from tertiary.simulate.traffic.terminal import ARRIVALS

NATIONAL_EPOCH_HOUR = 0               # the day starts at 00:00 UTC (the hourly curve is in UTC)
DEP_LEG_M = 10_000.0                  # runway heading after take-off before turning on course
FINAL_M = 30_000.0                    # straight-in final from the initial approach fix
TURN_LEG_M = 15_000.0                 # crosswind / downwind offset of a flight turning back
CLIMB_GRADIENT = 0.075                # 7.5 % climb to the cruise level
DESCENT_GRADIENT = 0.052              # ~3° descent from cruise, then the 3° glide path
#: what an arrival's crew selects at the top of descent: the 3 000 ft at which the descent joins
#: the glide path (:func:`_domestic_profiles`)
APPROACH_SELECTED_M = 3000.0 * FT
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
    heights converted once), velocities and segment codes, and its ``length`` in steps.
    The crews' selected altitudes (Mode S BDS 4,0; :class:`~tertiary.simulate.traffic.base.TrafficTrajectories`):
    per flight ``selected_alt_m`` (its planned flight level, NaN for an aircraft that does not
    downlink it), and per template ``tod`` (the top of descent, in steps from the entry; the
    length + 1 for a flight that never descends), where an arrival's crew selects
    :data:`APPROACH_SELECTED_M`."""

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
    selected_alt_m: NDArray[np.float64] | None = None   # (F,)
    tod: NDArray[np.int64] | None = None                # (R,)

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
        common = dict(dt=self.dt, pos=pos, vel=vel, active=inside, segment=seg.astype(np.int8),
                      truth_id=ids.astype(np.int64), epoch=self.epoch + timedelta(seconds=k0 * self.dt),
                      meta={k: v[ids] for k, v in self.meta.items()})
        if self.selected_alt_m is None or self.tod is None:
            return Trajectories(**common)
        sel = self.selected_alt_m[ids]
        change = np.where(np.isfinite(sel), (self.entry[ids] + self.tod[r] - k0) * self.dt, np.inf)
        return TrafficTrajectories(**common, selected_alt_m=sel, selected_change_s=change,
                                   selected_next_m=np.where(np.isfinite(sel), APPROACH_SELECTED_M, np.nan))


def _national_templates(cfg, sites: NDArray[np.float64], dt: float, frame: geo.LocalFrame | None):
    """Every route flown at each of its flight levels: a domestic airport pair at the semicircular
    levels of :data:`DOMESTIC_LEVELS_SHORT` under 400 km, :data:`DOMESTIC_LEVELS_LONG` beyond;
    each airway direction at those of :data:`AIRWAY_LEVELS`. Returns the templates and, per
    template, (kind, origin airport, destination, route, flight level): the templates of one
    route differ by their level only, which :func:`allocate_levels` chooses per flight."""
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
                hdg, ln, cv = flyby(wp)
                tpl.append(fly(wp[0], hdg, ln, cv, sp, hp, vertical_segments(hp), dt))
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
                hdg, ln, cv = flyby(wp)
                spd = 225.0 + 2.0 * (fl - 310) / 10.0
                tpl.append(fly(wp[0], hdg, ln, cv, constant(spd), constant(h), level_segments, dt))
                info.append(("overflight", -1, -1, group, int(fl)))
    return tpl, info


#: strategic deconfliction of the schedule (:func:`allocate_levels`) above FL150 (below, the
#: runways' spacing orders the traffic): flights planned 5 NM + 4 km or 1 000 ft apart, positions
#: compared every ``DECONFLICT_STRIDE_S``. Two aircraft close by at most 2 × 250 m/s × 4 s = 2 km
#: between samples, so planned pairs keep 5 NM — the en-route minimum the national airspace is
#: scored with above FL150 (``NationalConfig.enroute_floor_fl``) — and a controller's buffer above
#: it. The buffer is what an STCA with the en-route minimum sees: with a smaller one the planned
#: pairs pass at its threshold (5 NM plus margins) and raise nuisance alerts.
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
    key (a·T + b)·2^15 + m + 2^14 (:func:`conflict_key`). ``pos_h``: templates' (x, y, height)
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
    for b, ia in by_band.items():
        ib = np.concatenate([ia, by_band.get(b + 1, np.zeros(0, np.int64))])
        got = cKDTree(p[ia, :2]).sparse_distance_matrix(cKDTree(p[ib, :2]), r_m, output_type="ndarray")
        i, j = ia[got["i"]], ib[got["j"]]
        ok = np.abs(p[i, 2] - p[j, 2]) < dz_m
        i, j = i[ok], j[ok]
        other = got["j"][ok] >= len(ia)              # pairs with the band above: add their mirror
        keys.append(conflict_key(tid[i], tid[j], (ks[j] - ks[i]) // stride, T))
        keys.append(conflict_key(tid[j[other]], tid[i[other]], (ks[i[other]] - ks[j[other]]) // stride, T))
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)


def conflict_key(a: NDArray[np.int64], b: NDArray[np.int64], m: NDArray[np.int64], T: int) -> NDArray[np.int64]:
    return (a * T + b) * (1 << _OFFSET_BITS) + np.clip(m, -(1 << (_OFFSET_BITS - 1)) + 1,
                                                         (1 << (_OFFSET_BITS - 1)) - 1) + (1 << (_OFFSET_BITS - 1))


#: the delays a flight may take (s) when every level of its route conflicts: a departure held on
#: the ground, an overflight held before it enters (the area's neighbours regulating the flow)
DECONFLICT_DELAYS_S = (0.0, 60.0, 120.0, 180.0, 300.0, 420.0, 600.0, 900.0, 1200.0, 1500.0, 1800.0, 2400.0)


def allocate_levels(route: NDArray[np.int64], entry: NDArray[np.int64], land: NDArray[np.int64],
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
                q = conflict_key(np.full(len(rel), cand[c]), out_r[rel],
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


def allocate_levels_compiled(route: NDArray[np.int64], entry: NDArray[np.int64], land: NDArray[np.int64],
                              levels: list[NDArray[np.int64]], group: NDArray[np.int64], length: NDArray[np.int64],
                              keys: NDArray[np.int64], stride: int, origin: NDArray[np.int64],
                              dest: NDArray[np.int64], take_off_gap: int, landing_gap: int, delays: NDArray[np.int64]
                              ) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """:func:`allocate_levels`, the same plan, compiled
    (:func:`tertiary.simulate.plan_kernel.plan`)."""
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
    """The national templates in the system frame (:func:`template_grid`, tangent-plane z), their
    (kind, origin, destination, route, level) and :func:`conflict_offsets`: what the schedule
    flies and is planned on. They depend on the airports and the area only (not on the traffic's
    amount or draws), so a process simulating the scenario again reuses them (read-only)."""
    cfg = SimpleNamespace(airports=airports, min_route_km=min_route_km, area_half_width_km=half_width_km)
    sites = np.column_stack(frame.from_geodetic([a.lat_deg for a in airports],
                                                [a.lon_deg for a in airports], 0.0)[:2])
    tpl, info = _national_templates(cfg, sites, dt, frame)
    tpos, tvel, tseg, length = template_grid(tpl)
    keys = conflict_offsets(tpos, length, stride)          # positions are (x, y, height) here
    # a template's padding (its last sample repeated) is never flown: the sphere's z is enough there
    heights_to_enu(tpos, tvel, frame, active=np.arange(tpos.shape[1])[None, :] <= length[:, None])
    for a in (tpos, tvel, tseg, length, keys):
        a.flags.writeable = False
    return tpos, tvel, tseg, length, info, keys


def national_flights(cfg, duration_s: float, dt: float, rng: np.random.Generator, frame: geo.LocalFrame,
                     epoch, selected_alt_fraction: float = 0.0) -> NationalTraffic:
    """The day's traffic (:class:`tertiary.simulate.config.NationalConfig`): domestic flights
    between airports chosen by weight (pairs closer than ``min_route_km`` excluded), landings
    at an airport ≥ ``landing_spacing_s`` apart; overflights on the airways, entries on a
    (route, level) lane ≥ ``lane_spacing_s`` apart. Entry times follow the hourly curve; the
    number of flights is scaled so that the airborne count peaks at ``peak_airborne``
    (computed on the schedule, one rescaling pass). Then each flight's level and delay are
    planned (:func:`allocate_levels`): apart from the flights planned before it above FL150,
    take-offs ≥ ``departure_spacing_s`` and landings ≥ ``landing_spacing_s`` apart where the
    runways allow. A fraction ``selected_alt_fraction`` of the flights downlink their crew's
    selected altitude: the planned flight level, then :data:`APPROACH_SELECTED_M` from the top
    of descent on (:class:`NationalTraffic`)."""
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
    route, entry, _ = allocate_levels_compiled(route, entry, land, levels, group, length, keys, stride, orig, dest,
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
    # drawn last: every earlier draw (and so every other column) is the same as without it
    downlinks = rng.random(n) < selected_alt_fraction
    level_m = flight_level_m(np.array([i[4] for i in info]), 1.0)
    return NationalTraffic(dt, route, entry, role, meta, tpos, tvel, tseg, length, epoch,
                           selected_alt_m=np.where(downlinks, level_m[route], np.nan), tod=_top_of_descent(tseg, length))


def _top_of_descent(tseg: NDArray[np.int8], length: NDArray[np.int64]) -> NDArray[np.int64]:
    """Per template, the first step of its descent (its length + 1 when it never descends)."""
    down = (tseg == SEG_DESCENT) & (np.arange(tseg.shape[1])[None, :] <= length[:, None])
    return np.where(down.any(axis=1), np.argmax(down, axis=1), length + 1).astype(np.int64)


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
