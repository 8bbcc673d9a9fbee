"""Turn-aware conflict prediction (safety.conflicts, "Turning aircraft"): the bounded arc, the
grid decision against a brute-force reference, and the two pictures it exists for."""

from __future__ import annotations

import math
from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safety.conflicts import (ConflictConfig, arc_offsets, conflict_interval_arc, predict_conflicts)
from tertiary.contract import TURN_RATE_COLUMN

T0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)
CFG = ConflictConfig(threshold_mode="fixed", fixed_est_h_m=0.0, fixed_est_v_m=0.0, pilot_h_m=0.0, pilot_v_m=0.0,
                     level_pair_tolerance_m=None, use_selected_level=False, use_turn_rate=True)


def _integrate(p, v, w, t_end, max_turn, dt=1e-3):
    """Reference trajectory by explicit small-step integration of the heading (independent of
    the closed form): the track angle grows at ω until |turned| reaches max_turn."""
    n = int(round(t_end / dt))
    speed = math.hypot(*v)
    chi0 = math.atan2(v[0], v[1])
    t = np.arange(n + 1) * dt
    turned = np.clip(w * t, -max_turn, max_turn)
    chi = chi0 + turned
    # trapezoidal integration of the velocity along the heading
    ve, vn = speed * np.sin(chi), speed * np.cos(chi)
    x = p[0] + np.concatenate([[0.0], np.cumsum(0.5 * (ve[1:] + ve[:-1]) * dt)])
    y = p[1] + np.concatenate([[0.0], np.cumsum(0.5 * (vn[1:] + vn[:-1]) * dt)])
    return t, x, y


def test_arc_offsets_against_integration():
    for w_dps in (3.0, -1.5, 0.0):
        w = math.radians(w_dps)
        t, x, y = _integrate((0.0, 0.0), (60.0, 110.0), w, 105.0, math.pi / 2)
        k = np.arange(0, len(t), 5000)
        dx, dy = arc_offsets(60.0, 110.0, w, t[k], math.pi / 2)
        assert np.allclose(dx, x[k], atol=0.05) and np.allclose(dy, y[k], atol=0.05)
    # clockwise positive: heading north, a right turn goes east
    dx, dy = arc_offsets(0.0, 100.0, math.radians(3.0), 10.0, math.pi / 2)
    assert dx > 0 and dy > 0
    # bounded: after 90° at 3°/s (30 s) the aircraft flies straight east
    dx1, dy1 = arc_offsets(0.0, 100.0, math.radians(3.0), np.array([30.0, 60.0]), math.pi / 2)
    assert dy1[1] == pytest.approx(dy1[0]) and dx1[1] - dx1[0] == pytest.approx(3000.0)


pair = st.tuples(
    st.floats(-30_000, 30_000), st.floats(-30_000, 30_000),                 # relative position
    st.floats(-250, 250), st.floats(-250, 250), st.floats(-250, 250), st.floats(-250, 250),   # velocities
    st.sampled_from([0.0, 0.0, 0.7, -1.5, 3.0, -3.0]), st.sampled_from([0.0, 1.0, -2.5, 3.0]),  # ω (°/s)
    st.floats(-600, 600), st.floats(-15, 15), st.floats(-15, 15))           # Δh, ḣ_i, ḣ_j


@settings(max_examples=150, deadline=None)
@given(pair)
def test_grid_decision_agrees_with_brute_force(args):
    """The grid rule against a 1 ms brute-force reference of independently integrated arcs: a
    grid alert is a true alert (the grid times are true times); a reference alert that enters
    the thresholds by more than the documented error bound is found, and t_in is late by < Δt."""
    rx, ry, vix, viy, vjx, vjy, wi_d, wj_d, dz, vzi, vzj = args
    r_thr, z_thr, t_thr, dt, max_turn = 5556.0, 300.0, 105.0, 0.5, math.radians(30.0)
    wi, wj = math.radians(wi_d), math.radians(wj_d)
    t_in, t_out, d_min, t_star = conflict_interval_arc([[0.0, 0.0]], [[vix, viy]], wi, [[rx, ry]], [[vjx, vjy]], wj,
                                                       dz, vzi, vzj, r_thr, z_thr, t_thr, dt, max_turn)
    t, xi, yi = _integrate((0.0, 0.0), (vix, viy), wi, t_thr, max_turn)
    _, xj, yj = _integrate((rx, ry), (vjx, vjy), wj, t_thr, max_turn)
    d = np.hypot(xj - xi, yj - yi)
    h = np.abs(dz + (vzj - vzi) * t)
    assert d_min >= d.min() - 0.05                     # the grid cannot beat the true minimum
    assert d_min <= d.min() + 0.5 * math.hypot(vix, viy) * dt + 0.5 * math.hypot(vjx, vjy) * dt + 0.05
    if t_in[0] <= t_out[0]:                            # a grid alert is a true alert at t_in
        k = int(round(t_in[0] / 1e-3))
        assert d[k] <= r_thr + 0.05 and h[k] <= z_thr + 1e-6
    # margin of the documented bound: (|v_i| + |v_j|)·Δt/2 horizontally, |Δḣ|·Δt/2 vertically
    mh = (math.hypot(vix, viy) + math.hypot(vjx, vjy)) * dt / 2 + 0.05
    mv = abs(vzj - vzi) * dt / 2 + 1e-6
    deep = (d <= r_thr - mh) & (h <= z_thr - mv)
    if deep.any():
        assert t_in[0] <= t_out[0]
        assert t_in[0] <= t[np.argmax(deep)] + dt


def _picture(rows: list[dict]) -> pl.DataFrame:
    df = pl.DataFrame(rows).with_columns(pl.lit(T0).cast(pl.Datetime("us", "UTC")).alias("epoch"),
                                         pl.lit(0, pl.UInt32).alias("run"))
    return df.with_columns(pl.col("track_id").cast(pl.UInt64))


def _ac(tid, x, y, hdg_deg, speed, rate_dps, alt=3000.0):
    h = math.radians(hdg_deg)
    return {"track_id": tid, "x_m": x, "y_m": y, "z_m": alt, "vx_mps": speed * math.sin(h),
            "vy_mps": speed * math.cos(h), "vz_mps": 0.0, "alt_m": alt, "alt_rate_mps": 0.0,
            TURN_RATE_COLUMN: rate_dps}


def test_turning_onto_parallel_tracks_alerts_linearly_but_not_with_turns():
    """Two aircraft 9 km apart turning (3°/s) from converging headings (±30°) onto parallel
    northbound tracks: the tangents cross (straight-line prediction alerts), the arcs never come
    within the 3 NM minimum (and the brute-force integration of the arcs agrees)."""
    a = _ac(1, -4500.0, 0.0, 30.0, 130.0, -3.0)        # heading 030, turning left onto north
    b = _ac(2, 4500.0, 0.0, -30.0, 130.0, 3.0)         # heading 330, turning right onto north
    pic = _picture([a, b])
    lin = predict_conflicts(pic.drop(TURN_RATE_COLUMN), CFG)
    arc = predict_conflicts(pic, CFG)
    assert lin["alert"].to_list() == [True]
    assert not arc["alert"].any()
    bound = math.radians(CFG.max_turn_deg)
    t, xa, ya = _integrate((a["x_m"], a["y_m"]), (a["vx_mps"], a["vy_mps"]), math.radians(-3.0), 105.0, bound)
    _, xb, yb = _integrate((b["x_m"], b["y_m"]), (b["vx_mps"], b["vy_mps"]), math.radians(3.0), 105.0, bound)
    d = np.hypot(xb - xa, yb - ya)
    assert d.min() > CFG.sep_h_m
    # the arc's closest approach is what the row reports (kept with wide near margins)
    wide = ConflictConfig(**{**CFG.__dict__, "near_margin_h_m": 5000.0})
    row = predict_conflicts(pic, wide)
    assert row["r_min_m"][0] == pytest.approx(d.min(), abs=35.0)    # ≤ (|v_i| + |v_j|)·Δt/2 = 65 m
    # without the EHS rate (null) or below the significance threshold the line is used again
    nul = pic.with_columns(pl.lit(None, pl.Float64).alias(TURN_RATE_COLUMN))
    assert predict_conflicts(nul, CFG)["alert"].to_list() == [True]
    small = pic.with_columns((pl.col(TURN_RATE_COLUMN) * 0.1).alias(TURN_RATE_COLUMN))
    assert predict_conflicts(small, CFG)["alert"].to_list() == [True]


def test_turning_into_a_conflict_still_alerts():
    """An aircraft turning right (3°/s) from north onto 030 towards another one flying the
    reciprocal of that track: the straight line misses by ~8 km, the arc meets it head-on —
    alert with the turn, none without it."""
    a = _ac(1, 0.0, 0.0, 0.0, 130.0, 3.0)              # north, turning right onto 030 (30° bound)
    dx, dy = arc_offsets(0.0, 130.0, math.radians(3.0), 10.0, math.radians(30.0))   # end of the turn
    u = np.array([math.sin(math.radians(30.0)), math.cos(math.radians(30.0))])
    start = np.array([float(dx), float(dy)]) + 22_000.0 * u          # on a's new track, 22 km on
    b = _ac(2, float(start[0]), float(start[1]), 210.0, 130.0, 0.0)  # flying the reciprocal
    pic = _picture([a, b])
    arc = predict_conflicts(pic, CFG)
    lin = predict_conflicts(pic.drop(TURN_RATE_COLUMN), CFG)
    assert arc["alert"].to_list() == [True]
    assert not lin.filter(pl.col("alert")).height
    assert 0.0 <= arc["t_in_s"][0] <= CFG.t_thr_s


def test_screen_keeps_turning_pairs_and_straight_pairs_unchanged():
    """Pairs with no turning member keep the closed form exactly (same rows with or without the
    column), and a turning pair far outside the straight-line screen is still evaluated."""
    rng = np.random.default_rng(5)
    n = 60
    rows = [_ac(k + 1, *rng.uniform(-40_000, 40_000, 2), rng.uniform(0, 360), rng.uniform(100, 250), 0.0,
                alt=float(rng.choice([3000.0, 3150.0, 3300.0]))) for k in range(n)]
    pic = _picture(rows)
    with_col = predict_conflicts(pic, CFG)
    without = predict_conflicts(pic.drop(TURN_RATE_COLUMN), CFG)
    assert with_col.equals(without)
    # a pair whose straight lines diverge fast but whose arcs (U-turns, 180° bound) meet head-on
    cfg = ConflictConfig(**{**CFG.__dict__, "max_turn_deg": 180.0})
    a = _ac(1, -6000.0, 0.0, 270.0, 200.0, -3.0)       # west, turning left (south, then east)
    b = _ac(2, 6000.0, 0.0, 90.0, 200.0, 3.0)          # east, turning right (south, then west)
    got = predict_conflicts(_picture([a, b]), cfg)
    lin = predict_conflicts(_picture([a, b]).drop(TURN_RATE_COLUMN), cfg)
    assert not lin.height                               # the straight lines separate at 400 m/s
    assert got["alert"].to_list() == [True]             # the arcs bring them back within 3 NM


def test_chunked_grid_equals_one_chunk():
    rng = np.random.default_rng(2)
    n = 300
    args = ([np.zeros((n, 2)), rng.uniform(-200, 200, (n, 2)), np.radians(rng.choice([0.0, 2.0, -3.0], n)),
             rng.uniform(-20_000, 20_000, (n, 2)), rng.uniform(-200, 200, (n, 2)), np.radians(rng.choice([0.0, 3.0], n)),
             rng.uniform(-500, 500, n), rng.uniform(-10, 10, n), rng.uniform(-10, 10, n), 5556.0, 300.0, 105.0])
    tau_i = np.where(rng.random(n) < 0.3, rng.uniform(0, 100, n), np.inf)
    one = conflict_interval_arc(*args, tau_i=tau_i, max_elements=1 << 24)
    many = conflict_interval_arc(*args, tau_i=tau_i, max_elements=1000)      # 4 pairs per chunk
    for a, b in zip(one, many):
        assert np.array_equal(a, b)


def test_predict_conflicts_with_turns_against_brute_force():
    """Random pictures with 30 % of the aircraft turning: every alert is a true same-time
    conflict of the integrated arcs, and every arc conflict deeper than the grid bound alerts —
    the KD-tree screen and the staged bounds lose none."""
    rng = np.random.default_rng(11)
    n, t_thr = 40, CFG.t_thr_s
    th = math.radians(CFG.max_turn_deg)
    rows = []
    for k in range(n):
        rate = float(rng.choice([-3.0, -2.0, 2.5, 3.0])) if rng.random() < 0.3 else 0.0
        rows.append(_ac(k + 1, *rng.uniform(-20_000, 20_000, 2), rng.uniform(0, 360), rng.uniform(90, 200), rate,
                        alt=float(rng.choice([3000.0, 3200.0]))))
    got = predict_conflicts(_picture(rows), CFG)
    alerts = {(int(a), int(b)) for a, b in got.filter(pl.col("alert")).select("id_a", "id_b").rows()}
    traj = {}
    for r in rows:
        t, x, y = _integrate((r["x_m"], r["y_m"]), (r["vx_mps"], r["vy_mps"]), math.radians(r[TURN_RATE_COLUMN]),
                             t_thr, th, dt=0.01)
        traj[r["track_id"]] = (x, y, r["alt_m"], math.hypot(r["vx_mps"], r["vy_mps"]))
    r_thr, z_thr = CFG.sep_h_m, CFG.sep_v_m
    n_deep = 0
    for a in range(1, n + 1):
        for b in range(a + 1, n + 1):
            xa, ya, ha, sa = traj[a]
            xb, yb, hb, sb = traj[b]
            d = np.hypot(xb - xa, yb - ya)
            same_level = abs(hb - ha) <= z_thr
            true_alert = same_level and d.min() <= r_thr + 1.0
            deep = same_level and d.min() <= r_thr - (sa + sb) * CFG.turn_grid_s / 2
            if (a, b) in alerts:
                assert true_alert, (a, b)
            if deep:
                n_deep += 1
                assert (a, b) in alerts, (a, b)
    assert n_deep >= 3
