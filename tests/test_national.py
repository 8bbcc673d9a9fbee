"""The national scenario: listed, valid, and its traffic looks like a day's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tertiary.core import geo
from tertiary.simulate import builtin_scenarios, load_scenario
from tertiary.simulate.config import check_scenario
from tertiary.simulate.traffic import national as traffic
from tertiary.simulate.traffic import FT, national_flights
from tertiary.simulate import NATIONAL_EPOCH


_PLANNED: list[tuple] = []


@pytest.fixture(scope="module")
def day():
    cfg = check_scenario(load_scenario("national"))
    frame = geo.LocalFrame(*cfg.origin)
    compiled = traffic.allocate_levels_compiled

    def kept(*args):                 # the day's planning inputs, for the reference below
        _PLANNED.append(args)
        return compiled(*args)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(traffic, "allocate_levels_compiled", kept)
        return cfg, frame, national_flights(cfg.national, cfg.duration_s, cfg.dt,
                                            np.random.default_rng(1), frame, NATIONAL_EPOCH,
                                            cfg.traffic.selected_alt_fraction)


def test_the_compiled_plan_is_the_reference_plan(day):
    """The day's level and delay plan (:func:`~tertiary.simulate.traffic.national.allocate_levels`, sequential: each flight against
    those planned before it) compiled gives the Python reference's plan, flight for flight, on
    the day's first 2 500 flights in order of entry (domestic and overflights, runway spacing,
    flights left in conflict). Fails if a choice is tested against another set of flights, a
    conflict key differs or the order of choices changes."""
    (route, entry, land, *rest), = _PLANNED
    first = np.sort(np.argsort(entry, kind="stable")[:2500])
    args = (route[first], entry[first], land[first], *rest)
    want = traffic.allocate_levels(*args)
    got = traffic.allocate_levels_compiled(*args)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]) and got[2] == want[2]
    assert (got[0] != route[first]).sum() > 50 and (got[1] != entry[first]).sum() > 50   # levels and delays changed


def test_listed_and_sized():
    assert "national" in builtin_scenarios()
    cfg = check_scenario(load_scenario("national"))
    assert 12 <= len(cfg.radars) <= 20
    periods = {r.scan_period_s for r in cfg.radars}
    assert min(periods) <= 5 and max(periods) >= 10            # terminal and en-route radars
    frame = geo.LocalFrame(*cfg.origin)
    e, n, _ = frame.from_geodetic([a.lat_deg for a in cfg.national.airports],
                                  [a.lon_deg for a in cfg.national.airports], 0.0)
    assert 700e3 <= np.ptp(e) <= 1200e3 and 600e3 <= np.ptp(n) <= 1200e3
    assert cfg.duration_s == 86400.0


def test_daily_curve_peaks_near_1500(day):
    cfg, _, tr = day
    k = np.arange(0, 86400, 300)
    airborne = tr.airborne(k)
    assert 1350 <= airborne.max() <= 1650
    hour = lambda h: airborne[(k >= h * 3600) & (k < (h + 1) * 3600)].mean()
    assert hour(3) < 0.15 * airborne.max()                  # night trough
    assert hour(9) > 0.8 * airborne.max() and hour(18) > 0.8 * airborne.max()


def test_domestic_flights_take_off_and_land_at_airports(day):
    """A domestic flight starts and ends within a few hundred metres of an airport threshold
    (horizontally), low; cruises level at a semicircular flight level."""
    cfg, frame, tr = day
    sites = np.column_stack(frame.from_geodetic([a.lat_deg for a in cfg.national.airports],
                                                [a.lon_deg for a in cfg.national.airports], 0.0)[:2])
    dom = np.flatnonzero(tr.role == "domestic")[:300]
    r = tr.route[dom]
    ends = [tr.tpos[r, 0], tr.tpos[r, tr.length[r]]]
    for p in ends:
        d = np.linalg.norm(p[:, None, :2] - sites[None], axis=2).min(axis=1)
        assert d.max() < 100.0
        h = frame.to_geodetic(*p.T)[2]
        assert np.all(h < 20.0)
    from tertiary.simulate.trajectory import SEG_STRAIGHT
    level = tr.tseg[r, tr.length[r] // 2] == SEG_STRAIGHT        # cruising at mid-flight (long routes)
    assert level.mean() > 0.7
    mid = tr.tpos[r[level], tr.length[r[level]] // 2]
    h = frame.to_geodetic(*mid.T)[2]
    fl = h / (1000 * FT + 1.0) * 10
    assert np.all(np.abs(fl - np.round(fl / 10) * 10) < 0.05)     # on a flight level (FL to 0.05)
    assert np.all((fl > 145) & (fl < 415))


def test_take_offs_and_landings_fly_the_runway_in_use(day):
    """Each airport has one runway direction in use: every take-off climbs out along it and
    every landing comes in along it, whatever the flight's course (a flight taking the runway
    end closer to its course met landings head-on on the same runway)."""
    cfg, _, tr = day
    runway = {a.name: a.runway_deg for a in cfg.national.airports}
    dom = np.flatnonzero(tr.role == "domestic")
    r, end = tr.route[dom], tr.length[tr.route[dom]]
    out = tr.tpos[r, 60, :2] - tr.tpos[r, 0, :2]                 # the first minute after take-off
    last = tr.tpos[r, end, :2] - tr.tpos[r, end - 60, :2]         # the last minute before touch-down
    for d, names in ((out, tr.meta["origin"][dom]), (last, tr.meta["destination"][dom])):
        heading = np.degrees(np.arctan2(d[:, 0], d[:, 1])) % 360.0
        want = np.array([runway[n] for n in names])
        assert np.abs((heading - want + 180.0) % 360.0 - 180.0).max() < 1.0
    # and the runway is flown against the course too (over a fifth of the flights turn back
    # through a crosswind point), not only by flights whose course happens to match it
    course = np.degrees(np.arctan2(*(tr.tpos[r, end, :2] - tr.tpos[r, 0, :2]).T)) % 360.0
    rwy = np.array([runway[n] for n in tr.meta["origin"][dom]])
    assert (np.abs((course - rwy + 180.0) % 360.0 - 180.0) > 90.0).mean() > 0.2


def test_window_lookup_matches_the_template(day):
    """The truth of a window is the template looked up at (k − entry): a flight's position is
    the same in two overlapping windows."""
    _, _, tr = day
    a, b = tr.window(30000, 600), tr.window(30300, 600)
    common = np.intersect1d(a.truth_id, b.truth_id)
    ia, ib = np.searchsorted(a.truth_id, common), np.searchsorted(b.truth_id, common)
    assert len(common) > 500
    assert np.array_equal(a.pos[ia, 300:], b.pos[ib, :300])
    assert np.array_equal(a.active[ia, 300:], b.active[ib, :300])
    # speeds of airliners, and positions change by the velocity
    v = np.linalg.norm(a.vel[a.active], axis=1)
    assert 60 < v.min() and v.max() < 260
    both = a.active[:, 1:] & a.active[:, :-1]
    step = np.linalg.norm(np.diff(a.pos, axis=1), axis=2)[both]
    assert np.percentile(np.abs(step - np.linalg.norm(a.vel[:, :-1], axis=2)[both]), 99) < 1.0



def test_crews_select_their_planned_level_then_the_approach_altitude(day):
    """The selected altitude (Mode S BDS 4,0) of a window's flights: the level a cruising
    aircraft flies, the level a climbing one climbs to, and below a descending one (the
    approach altitude from its top of descent); the declared fraction downlinks it, and a
    flight's selection is the same in two overlapping windows."""
    cfg, frame, tr = day
    a, b = tr.window(30000, 600), tr.window(30300, 600)
    n, k = a.active.shape
    ac, step = np.nonzero(a.active)
    sel = a.selected_at(ac, step * a.dt)
    h, hdot, _ = geo.height_and_rate(a.pos[ac, step], a.vel[ac, step], frame)
    has = np.isfinite(sel)
    flights = np.isfinite(a.selected_alt_m)
    assert abs(flights.mean() - cfg.traffic.selected_alt_fraction) < 0.03
    level = has & (np.abs(hdot) < 0.1)
    climb, descent = has & (hdot > 1.0), has & (hdot < -1.0)
    assert level.sum() > 10_000 and climb.sum() > 500 and descent.sum() > 500
    assert np.percentile(np.abs(sel[level] - h[level]), 99) < 5.0           # the 16 ft field's rounding
    assert (sel[climb] > h[climb]).all()
    above_approach = descent & (h > traffic.APPROACH_SELECTED_M + 50.0)
    assert (sel[above_approach] < h[above_approach]).mean() > 0.99
    # the same selection whatever the window
    common = np.intersect1d(a.truth_id, b.truth_id)
    ia, ib = np.searchsorted(a.truth_id, common), np.searchsorted(b.truth_id, common)
    t_a = np.full(len(common), 450.0)
    np.testing.assert_array_equal(a.selected_at(ia, t_a), b.selected_at(ib, t_a - 300.0))


def test_national_needs_its_table():
    cfg = load_scenario("national")
    from tertiary.core.errors import OptionError
    with pytest.raises(OptionError, match="national"):
        check_scenario(dataclasses.replace(cfg, national=None))
    with pytest.raises(OptionError, match="national.block_s"):
        check_scenario(dataclasses.replace(cfg, national=dataclasses.replace(cfg.national, block_s=601.0)))


def _close_pairs(tr, frame, k0: int, n: int, h_min_m: float, step: int = 2) -> int:
    """Pairs of flights that come within 3 NM and 1 000 ft of each other, both above ``h_min_m``,
    in samples k0 … k0+n−1 (every ``step``-th): brute force on the truth, heights geodetic."""
    from scipy.spatial import cKDTree
    w = tr.window(k0, n)
    h = np.full(w.active.shape, np.nan)
    h[w.active] = frame.to_geodetic(*w.pos[w.active].T)[2]
    pairs = set()
    for k in range(0, n, step):
        a = np.flatnonzero(w.active[:, k] & (h[:, k] > h_min_m))
        got = cKDTree(w.pos[a, k, :2]).query_pairs(3 * 1852.0, output_type="ndarray")
        i, j = a[got[:, 0]], a[got[:, 1]]
        close = np.abs(h[i, k] - h[j, k]) < 1000 * FT
        pairs.update(zip(w.truth_id[i[close]].tolist(), w.truth_id[j[close]].tolist()))
    return len(pairs)


def test_flights_are_planned_apart_en_route(day):
    """The day's flights keep 3 NM or 1 000 ft apart above FL150, as a controller's plan keeps
    them (5 NM in the plan): 20 minutes of the morning peak, brute force on the truth. With two
    fixed levels per route and no plan the same minutes held over 400 such pairs, most of them
    level at one flight level where two routes cross."""
    cfg, frame, tr = day
    assert tr.airborne(np.array([8 * 3600]))[0] > 1200
    assert _close_pairs(tr, frame, 8 * 3600, 1200, 150 * 100 * FT) <= 5
