"""Mode S selected altitude (EHS BDS 4,0): simulated from the crews' clearances, carried reports →
aligned → fused → tracks, and used by conflict prediction to stop a climb or descent at the
selected level (safety.conflicts, "Selected level")."""

from __future__ import annotations

import dataclasses
from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest

from safety.conflicts import ConflictConfig, level_off_times, predict_conflicts
from tertiary.simulate.config import TrafficConfig
from tertiary.simulate.ehs import SELECTED_ALT_RESOLUTION, EhsConfig, ehs_report_columns, selected_altitude
from tertiary.simulate.traffic import ARRIVAL_CLEARED_M, SID_TOP_FL, flight_level_m, terminal_area

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
FIXED = ConflictConfig(threshold_mode="fixed")
FT = 0.3048


def _picture(pos, vel, selected=None) -> pl.DataFrame:
    """Tracks with the barometric channel alt_m = z, alt_rate_mps = vz and optional SFL."""
    pos, vel = np.asarray(pos, float), np.asarray(vel, float)
    n = len(pos)
    df = pl.DataFrame({"run": np.zeros(n, np.uint32), "epoch": [T0] * n, "track_id": np.arange(1, n + 1, dtype=np.uint64),
                       "x_m": pos[:, 0], "y_m": pos[:, 1], "z_m": pos[:, 2], "vx_mps": vel[:, 0], "vy_mps": vel[:, 1],
                       "vz_mps": vel[:, 2], "alt_m": pos[:, 2], "alt_rate_mps": vel[:, 2]}
                      ).with_columns(pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    if selected is not None:
        df = df.with_columns(pl.Series("selected_alt_m", selected, dtype=pl.Float64))
    return df


# head-on, horizontal CPA 0 m at t = 100 s; A level at 3 600 m, B climbing 12 m/s from 2 400 m:
# linearly B reaches A's level exactly at the CPA
POS = [[0.0, 0.0, 3600.0], [20000.0, 0.0, 2400.0]]
VEL = [[100.0, 0.0, 0.0], [-100.0, 0.0, 12.0]]


def _alert(selected, cfg=FIXED) -> bool:
    out = predict_conflicts(_picture(POS, VEL, selected), cfg)
    return bool(out["alert"].any())


def test_climb_stopped_below_an_occupied_level_does_not_alert():
    """B selected 2 750 m (850 m under A, the next level below): no alert; without a selected
    altitude (column absent or null), or one the climb is moving away from, or in seed mode:
    the linear prediction alerts."""
    assert not _alert([3600.0, 2750.0])
    assert _alert(None)
    assert _alert([None, None])
    assert _alert([3600.0, 2000.0])                       # climbing away from its selection: a bust
    assert _alert([3600.0, 2750.0], ConflictConfig(threshold_mode="fixed", use_selected_level=False))
    seed = ConflictConfig(threshold_mode="fixed", mode="seed")
    assert predict_conflicts(_picture(POS, VEL, [3600.0, 2750.0]), seed).equals(predict_conflicts(_picture(POS, VEL), seed))


def test_level_bust_with_the_occupied_level_selected_still_alerts():
    """Selected level = the occupied level (or 150 ft under it, the designed busts), or above it:
    the predicted paths meet → alert, with the full threshold while B climbs."""
    assert _alert([3600.0, 3600.0])
    assert _alert([3600.0, 3600.0 - 150 * FT])
    assert _alert([3600.0, 4500.0])
    # a level-off 1 000 ft under A, reached (t = 41 s) before the pair closes horizontally
    # (68–132 s): separated, the level-pair threshold applies once both are level
    pos = [[0.0, 0.0, 3600.0], [20000.0, 0.0, 2800.0]]
    sel = [3600.0, 3600.0 - 1000 * FT]
    assert not predict_conflicts(_picture(pos, VEL, sel), FIXED)["alert"].any()
    off = ConflictConfig(threshold_mode="fixed", level_pair_tolerance_m=None)
    assert predict_conflicts(_picture(pos, VEL, sel), off)["alert"].any()
    # still climbing (full threshold) while the pair is inside horizontally: an alert (the rule)
    assert _alert([3600.0, 3600.0 - 1000 * FT])


def test_descent_stopped_above_an_occupied_level():
    pos = [[0.0, 0.0, 1000.0], [20000.0, 0.0, 2200.0]]
    vel = [[100.0, 0.0, 0.0], [-100.0, 0.0, -12.0]]
    assert predict_conflicts(_picture(pos, vel), FIXED)["alert"].any()
    out = predict_conflicts(_picture(pos, vel, [1000.0, 1900.0]), FIXED)
    assert not out["alert"].any()
    # the vertical separation at the CPA is that of the levels, not the extrapolated 0 m
    assert out.height == 0 or out["dz_min_m"][0] == pytest.approx(900.0)


def test_level_off_times():
    h = np.array([1000.0, 1000.0, 1000.0, 1000.0, 1000.0, 1000.0, 1000.0])
    hdot = np.array([10.0, 10.0, 10.0, -5.0, -5.0, 0.0, 10.0])
    sel = np.array([1500.0, 990.0, 900.0, 500.0, 1100.0, 1500.0, np.nan])
    tau = level_off_times(h, hdot, sel, np.ones(7, bool), 30.48)
    assert tau[0] == pytest.approx(50.0)          # climbing to 1 500 m at 10 m/s
    assert tau[1] == 0.0                          # 10 m over its selection: capturing, level now
    assert np.isinf(tau[2])                       # 100 m over it and climbing: a bust, ignored
    assert tau[3] == pytest.approx(100.0)
    assert np.isinf(tau[4]) and np.isinf(tau[5]) and np.isinf(tau[6])
    assert np.isinf(level_off_times(h[:1], hdot[:1], sel[:1], np.zeros(1, bool), 30.48)[0])  # no baro channel


def _clamped_heights(h0, hdot, sel, t, tol=100 * FT):
    """Independent form of the clamped prediction: the linear height clipped at the level."""
    lin = h0 + hdot * t
    if not np.isfinite(sel) or hdot == 0:
        return lin
    if hdot > 0 and sel >= h0 - tol:
        return np.minimum(lin, max(sel, h0))
    if hdot < 0 and sel <= h0 + tol:
        return np.maximum(lin, min(sel, h0))
    return lin


def test_decision_matches_sampled_clamped_tracks_on_random_pictures():
    """The corrected rule with selected levels against the predicted tracks sampled every 0.05 s
    (heights clipped at the selected levels), on random pictures: an alert wherever a sample is
    inside both thresholds (shrunk), none where no sample is inside (widened by the motion)."""
    rng = np.random.default_rng(5)
    n = 120
    pos = np.column_stack([rng.uniform(-25e3, 25e3, n), rng.uniform(-25e3, 25e3, n), rng.uniform(2000, 4000, n)])
    vel = np.column_stack([rng.uniform(-150, 150, n), rng.uniform(-150, 150, n),
                           rng.choice([0.0, 1.0], n) * rng.uniform(-15, 15, n)])
    sel = np.where(rng.random(n) < 0.8, pos[:, 2] + rng.uniform(-900, 900, n), np.nan)
    df = _picture(pos, vel, sel)
    cfg = ConflictConfig(threshold_mode="fixed", level_pair_tolerance_m=None)
    out = predict_conflicts(df, cfg)
    T = cfg.t_thr_s
    t = np.arange(0.0, T + 0.025, 0.05)
    rows = {r["track_id"]: r for r in df.to_dicts()}
    levelled = 0
    for r in out.to_dicts():
        a, b = rows[r["id_a"]], rows[r["id_b"]]
        dz = (_clamped_heights(b["alt_m"], b["alt_rate_mps"], b["selected_alt_m"] or np.nan, t)
              - _clamped_heights(a["alt_m"], a["alt_rate_mps"], a["selected_alt_m"] or np.nan, t))
        dx = (b["x_m"] - a["x_m"]) + (b["vx_mps"] - a["vx_mps"]) * t
        dy = (b["y_m"] - a["y_m"]) + (b["vy_mps"] - a["vy_mps"]) * t
        dh = np.hypot(dx, dy)
        sh = np.hypot(b["vx_mps"] - a["vx_mps"], b["vy_mps"] - a["vy_mps"]) * 0.05
        sv = (abs(a["alt_rate_mps"]) + abs(b["alt_rate_mps"])) * 0.05
        inner = ((dh <= r["r_thr_m"] * (1 - 1e-6)) & (np.abs(dz) <= r["z_thr_m"] * (1 - 1e-6))).any()
        outer = ((dh <= r["r_thr_m"] + sh + 1e-6) & (np.abs(dz) <= r["z_thr_m"] + sv + 1e-6)).any()
        assert (not inner or r["alert"]) and (outer or not r["alert"]), r
        lin = (b["alt_m"] - a["alt_m"]) + (b["alt_rate_mps"] - a["alt_rate_mps"]) * t
        levelled += int(np.abs(lin - dz).max() > 1.0)
    assert out["alert"].sum() > 5 and levelled > 5
    # the screen stays conservative: every alert of the brute force is in the output set
    for ia in range(n):
        for ib in range(ia + 1, n):
            a, b = rows[ia + 1], rows[ib + 1]
            dz = (_clamped_heights(b["alt_m"], b["alt_rate_mps"], b["selected_alt_m"] or np.nan, t)
                  - _clamped_heights(a["alt_m"], a["alt_rate_mps"], a["selected_alt_m"] or np.nan, t))
            if np.abs(dz).min() > 415.0 + 1.0:
                continue
            dx = (b["x_m"] - a["x_m"]) + (b["vx_mps"] - a["vx_mps"]) * t
            dy = (b["y_m"] - a["y_m"]) + (b["vy_mps"] - a["vy_mps"]) * t
            if ((np.hypot(dx, dy) <= 5556.0 + 800.0 - 1.0) & (np.abs(dz) <= 304.8 + 110.0 - 1.0)).any():
                assert out.filter((pl.col("id_a") == ia + 1) & (pl.col("id_b") == ib + 1))["alert"].any()


# --------------------------------------------------------------------------- simulator


@pytest.fixture(scope="module")
def traffic():
    cfg = TrafficConfig(aircraft=60, conflict_pairs=4, near_miss_pairs=1)
    return cfg, terminal_area(cfg, 1800.0, 1.0, np.random.default_rng(3))


def test_selected_altitude_is_the_clearance(traffic):
    """Departures select the SID top, arrivals 3 000 ft, level traffic its level; a level bust
    selects the level it climbs to ("flown") — never anything read off the future trajectory
    beyond that; a fraction of aircraft downlink none."""
    cfg, traj = traffic
    sel, role = traj.selected_alt_m, traj.meta["role"]
    has = np.isfinite(sel)
    assert 0 < (~has).sum() < 0.2 * len(sel)
    dep, arr = has & (role == "departure"), has & (role == "arrival")
    assert dep.any() and arr.any()
    assert np.allclose(sel[dep], flight_level_m(SID_TOP_FL, cfg.level_buffer_m))
    assert np.allclose(sel[arr], ARRIVAL_CLEARED_M)
    # level traffic: the selection is the height it flies at (start = end)
    from tertiary.stages.tracking.altitude import geodetic_height_rate  # noqa: F401  (heights: the sphere, frame None)
    r = 6_371_000.0
    h = np.sqrt(traj.pos[..., 0] ** 2 + traj.pos[..., 1] ** 2 + (r + traj.pos[..., 2]) ** 2) - r
    top = np.where(traj.active, h, -np.inf).max(axis=1)
    for kind in ("overflight", "holding", "conflict-crossing", "conflict-converging"):
        m = has & (role == kind)
        assert np.allclose(sel[m], top[m], atol=1.5), kind
    # a designed level bust: the selected level is where the climb stops (its highest point)
    bust = has & (role == "conflict-level-bust")
    climbers = bust & (np.where(traj.active, traj.vel[..., 2], 0.0).max(axis=1) > 1.0)
    assert climbers.any()
    assert np.allclose(sel[climbers], top[climbers], atol=1.5)


def test_arrivals_select_the_missed_approach_altitude_once_on_the_glide_path(traffic):
    """An arrival's selection changes during its flight: 3 000 ft until a crew delay
    (``missed_approach_delay_s``) after its glide-path descent begins, the missed-approach
    altitude after — the procedure's event, never before the descent has begun. Nobody else's
    selection changes; BDS 4,0 extraction follows the selection at the reply time."""
    cfg, traj = traffic
    role = traj.meta["role"]
    r = 6_371_000.0
    h = np.sqrt(traj.pos[..., 0] ** 2 + traj.pos[..., 1] ** 2 + (r + traj.pos[..., 2]) ** 2) - r
    t = np.arange(traj.pos.shape[1]) * traj.dt
    arr = np.flatnonzero((role == "arrival") & np.isfinite(traj.selected_alt_m))
    lo, hi = cfg.missed_approach_delay_s
    checked = 0
    for a in arr:                       # a loop over a dozen aircraft in a test
        act = np.flatnonzero(traj.active[a])
        at_3000 = act[h[a, act] >= ARRIVAL_CLEARED_M - 0.5]
        below = act[h[a, act] < ARRIVAL_CLEARED_M - 0.5]
        if not len(at_3000) or not len(below) or at_3000[-1] == act[-1]:
            continue
        t_gs = t[at_3000[-1]]           # the last sample at the approach altitude
        assert t_gs + lo - 1e-6 <= traj.selected_change_s[a] <= t_gs + hi + 1e-6
        checked += 1
        before = traj.selected_at(np.array([a, a]), np.array([t_gs - 30.0, t_gs]))
        after = traj.selected_at(np.array([a]), np.array([t_gs + hi + 1.0]))
        assert np.allclose(before, ARRIVAL_CLEARED_M) and np.allclose(after, cfg.missed_approach_ft * FT)
    assert checked >= 3
    others = np.isfinite(traj.selected_alt_m) & (role != "arrival")
    assert np.all(np.isinf(traj.selected_change_s[others]))
    # extraction at the reply time: before / after the change
    a = arr[np.isfinite(traj.selected_change_s[arr])][0]
    tc = traj.selected_change_s[a]
    got = selected_altitude(traj, np.array([a, a]), np.random.default_rng(0), missing=0.0,
                            t=np.array([tc - 1.0, tc + 1.0]))
    lsb = SELECTED_ALT_RESOLUTION[0]
    assert np.allclose(got, np.round(np.array([ARRIVAL_CLEARED_M, cfg.missed_approach_ft * FT]) / lsb) * lsb)


def test_bust_selected_cleared_keeps_the_level_below():
    cfg = TrafficConfig(aircraft=60, conflict_pairs=4, near_miss_pairs=1, bust_selected="cleared")
    traj = terminal_area(cfg, 1800.0, 1.0, np.random.default_rng(3))
    role = traj.meta["role"]
    climbers = (role == "conflict-level-bust") & (np.where(traj.active, traj.vel[..., 2], 0.0).max(axis=1) > 1.0)
    r = 6_371_000.0
    h = np.sqrt(traj.pos[..., 0] ** 2 + traj.pos[..., 1] ** 2 + (r + traj.pos[..., 2]) ** 2) - r
    start = np.array([h[a, np.flatnonzero(traj.active[a])[0]] for a in np.flatnonzero(climbers)])
    got = traj.selected_alt_m[climbers]
    ok = np.isfinite(got)
    assert ok.any() and np.allclose(got[ok], start[ok], atol=1.5)


def test_bds40_extraction_quantised_and_missing(traffic):
    _, traj = traffic
    rng = np.random.default_rng(0)
    a = np.repeat(np.arange(traj.n_aircraft), 40)
    t = np.tile(np.linspace(0, 1700, 40), traj.n_aircraft)
    got = selected_altitude(traj, a, rng, missing=0.1)
    want = traj.selected_alt_m[a]
    lsb = SELECTED_ALT_RESOLUTION[0]
    both = np.isfinite(got)
    assert np.allclose(np.round(got[both] / lsb) * lsb, got[both])            # 16 ft quantum
    assert np.all(np.abs(got[both] - want[both]) <= lsb / 2 + 1e-9)
    assert not np.isfinite(got[~np.isfinite(want)]).any()
    lost = np.isfinite(want) & ~both
    assert 0.05 < lost.sum() / np.isfinite(want).sum() < 0.15
    # report columns: only with a decoded Mode S reply; the BDS 5,0/6,0 columns are unchanged by it
    replied = rng.random(len(a)) < 0.7
    cols = ehs_report_columns(traj, a, t, replied, np.random.default_rng(1), EhsConfig())
    cols0 = ehs_report_columns(traj, a, t, replied, np.random.default_rng(1), EhsConfig(selected_alt_missing=0.5))
    assert not np.isfinite(cols["selected_alt_m"][~replied]).any()
    valid = replied & np.isfinite(cols["ehs_gs_mps"]) & np.isfinite(want)     # on the trajectory, selecting
    assert valid.sum() > 100 and np.isfinite(cols["selected_alt_m"][valid]).mean() > 0.9
    assert not np.isfinite(cols["selected_alt_m"][~np.isfinite(cols["ehs_gs_mps"])]).any()
    for c in cols:
        if c != "selected_alt_m":
            assert np.array_equal(cols[c], cols0[c], equal_nan=True)


# --------------------------------------------------------------------------- pipeline carry


def test_selected_altitude_reaches_the_tracks(tmp_path):
    """A small simulated run: reports → aligned → fused → tracks carry selected_alt_m; a track's
    value is one its aircraft selected."""
    from tertiary.pipeline import PipelineConfig, process
    from tertiary.simulate import load_scenario, simulate
    scen = load_scenario("terminal-area")
    scen = dataclasses.replace(scen, duration_s=600.0, runs=1,
                               traffic=dataclasses.replace(scen.traffic, aircraft=24, conflict_pairs=2,
                                                           near_miss_pairs=0))
    ds = simulate(scen)
    assert ds.reports["selected_alt_m"].is_not_null().mean() > 0.5
    res = process(ds, PipelineConfig(methods=("aposteriori",), filters=("imm_sym",), centralized=False))
    for name in ("aligned", "fused", "tracks"):
        frame = getattr(res, name)
        assert frame["selected_alt_m"].is_not_null().mean() > 0.3, name
        # the BDS 5,0 track-angle rate rides along (conflict prediction follows turns with it)
        assert frame["ehs_track_rate_dps"].is_not_null().mean() > 0.3, name
    # a turning aircraft's track carries a turn rate of its turn (STAR / holding turns ≈ 2.5–3 °/s)
    turning = res.tracks.filter(pl.col("ehs_track_rate_dps").abs() >= 1.0)
    assert turning.height and turning["ehs_track_rate_dps"].abs().median() == pytest.approx(2.7, abs=0.6)
