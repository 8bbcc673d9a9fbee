"""Conflict prediction (5.10)–(5.17): geometry against an independent exact computation, the
worked example, thresholds, KD-tree candidates against brute force, output contract."""

from __future__ import annotations

import dataclasses
import itertools
import math
from datetime import datetime, timedelta, timezone
from fractions import Fraction

import numpy as np
import pymap3d
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import chi2, norm

from safety.conflicts import (CONFLICT_EXTRA, ConflictConfig, conflict_candidates, conflict_interval,
                              conflict_interval_levelled, height_and_rate, pair_geometry, predict_conflicts,
                              slim_conflicts, tangent_plane_error_bound)
from tertiary.core.geo import EARTH_RADIUS_M, LocalFrame
from tertiary.contract import TABLES, validate

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
FIXED = ConflictConfig(threshold_mode="fixed", dr_v_m=300.0)      # the seed's fixed thresholds


def _frame(pos, vel, ids=None, run=0, epoch=T0, method=None, cov=None, cov_diag=None, alt=True) -> pl.DataFrame:
    """A picture; ``alt=True`` also gives the height channel alt_m = z, alt_rate_mps = vz (the
    worked example's flat (x, y, h) geometry); ``alt=False`` leaves heights to the geodetic conversion."""
    pos, vel = np.asarray(pos, float).reshape(-1, 3), np.asarray(vel, float).reshape(-1, 3)
    n = len(pos)
    data = {"run": np.full(n, run, np.uint32), "epoch": [epoch] * n,
            "track_id": np.arange(1, n + 1, dtype=np.uint64) if ids is None else np.asarray(ids, np.uint64),
            "x_m": pos[:, 0], "y_m": pos[:, 1], "z_m": pos[:, 2],
            "vx_mps": vel[:, 0], "vy_mps": vel[:, 1], "vz_mps": vel[:, 2]}
    if alt:
        data.update(alt_m=pos[:, 2], alt_rate_mps=vel[:, 2])
    df = pl.DataFrame(data).with_columns(pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    if method is not None:
        df = df.with_columns(pl.lit(method).alias("method"))
    if cov is not None:
        df = df.with_columns(pl.Series("cov", np.asarray(cov, float).reshape(n, 36), dtype=pl.Array(pl.Float64, 36)))
    if cov_diag is not None:
        df = df.with_columns(pl.Series("cov_diag", np.asarray(cov_diag, float).reshape(n, 6),
                                       dtype=pl.Array(pl.Float64, 6)))
    return df


# --------------------------------------------------------------------------- worked example


def test_worked_example_geometry():
    g = pair_geometry([0, 0, 3000], [120, 0, 0], [15000, 6000, 3600], [-100, -40, -5])
    assert float(g.r_min) == pytest.approx(3219.9, abs=0.05)
    assert float(g.t_min) == pytest.approx(70.80, abs=0.005)
    assert float(g.dz_min_seed) == pytest.approx(246.0, abs=0.05)
    assert float(g.r0) == pytest.approx(16155.5, abs=0.05)
    assert float(g.dz) == 600.0


@pytest.mark.parametrize("mode", ["seed", "corrected"])
def test_worked_example_decision(mode):
    cfg = ConflictConfig(threshold_mode="fixed", dr_v_m=300.0, mode=mode)
    assert cfg.t_thr_s == 105.0
    df = _frame([[0, 0, 3000], [15000, 6000, 3600]], [[120, 0, 0], [-100, -40, -5]])
    out = predict_conflicts(df, cfg)
    assert out.height == 1
    row = out.row(0, named=True)
    assert row["alert"]
    assert row["r_thr_m"] == pytest.approx(6356.0) and row["z_thr_m"] == pytest.approx(410.0)
    assert row["t_thr_s"] == 105.0
    assert row["r_min_m"] == pytest.approx(3219.9, abs=0.05) and row["t_min_s"] == pytest.approx(70.8)
    # seed: (5.13) 600 − 5·70.8; corrected: |Δh| at clip(T_min, 0, T) — the same number here
    assert row["dz_min_m"] == pytest.approx(246.0)
    assert row["severity"] == pytest.approx(1 - row["r_min_m"] / 6356.0)
    # vz_2 = 0: the vertical separation stays 600 m > 410 m → no conflict (no candidate at all)
    level = predict_conflicts(df.with_columns(pl.lit(0.0).alias("vz_mps"), pl.lit(0.0).alias("alt_rate_mps")), cfg)
    assert level.height == 0 or not level["alert"].any()


# --------------------------------------------------------------------------- geometry vs exact


def _exact(p_i, v_i, p_j, v_j, t_thr, eps=1e-6):
    """Independent exact computation in rationals from the (float) differences d0 = p_j − p_i and
    w = v_j − v_i: minimise |d0 + w t|² by setting its derivative to zero, then evaluate the
    distance at the minimiser (no cross product, no (5.10)/(5.11))."""
    d0 = [Fraction(float(p_j[k] - p_i[k])) for k in range(3)]
    w = [Fraction(float(v_j[k] - v_i[k])) for k in range(3)]
    ww = w[0] * w[0] + w[1] * w[1]
    if math.sqrt(float(ww)) < eps:
        r_min, t_min, ts = math.sqrt(float(d0[0] ** 2 + d0[1] ** 2)), math.inf, None
    else:
        ts = -(d0[0] * w[0] + d0[1] * w[1]) / ww
        dm = [d0[k] + w[k] * ts for k in range(2)]
        r_min, t_min = math.sqrt(float(dm[0] ** 2 + dm[1] ** 2)), float(ts)
    dh, dvz = d0[2], w[2]
    # corrected vertical: |Δh + Δvz t| over [0, T]: the ends, or 0 if the root lies inside
    T = Fraction(float(t_thr))
    cands = [abs(dh), abs(dh + dvz * T)]
    if dvz != 0 and 0 <= -dh / dvz <= T:
        cands.append(Fraction(0))
    dz_min = float(min(cands))
    # seed (5.13) is the signed vertical separation at T_min: sign(Δh)·(Δh + Δvz T_min)
    sgn = (dh > 0) - (dh < 0)
    seed = None if ts is None else (float(sgn * (dh + dvz * ts)) if sgn else 0.0)
    return r_min, t_min, dz_min, seed, math.sqrt(float(ww))


coord = st.floats(-2e5, 2e5, allow_nan=False, allow_infinity=False)
height = st.floats(0.0, 13000.0, allow_nan=False, allow_infinity=False)
speed = st.floats(-300.0, 300.0, allow_nan=False, allow_infinity=False)
vspeed = st.floats(-30.0, 30.0, allow_nan=False, allow_infinity=False)
pos3 = st.tuples(coord, coord, height)
vel3 = st.tuples(speed, speed, vspeed)


@st.composite
def pair_states(draw):
    """Random pairs plus the special geometries: parallel, head-on, overtaking, diverging."""
    kind = draw(st.sampled_from(["random", "parallel", "head-on", "overtaking", "diverging"]))
    p_i, v_i, p_j, v_j = draw(pos3), draw(vel3), draw(pos3), draw(vel3)
    if kind == "parallel":                      # zero relative velocity
        v_j = (v_i[0], v_i[1], draw(vspeed))
    elif kind == "head-on":                     # on a collision line, opposite directions
        dist = draw(st.floats(1000.0, 1e5))
        p_i, p_j = (0.0, 0.0, p_i[2]), (dist, 0.0, p_j[2])
        v_i, v_j = (draw(st.floats(50.0, 300.0)), 0.0, v_i[2]), (-draw(st.floats(50.0, 300.0)), 0.0, v_j[2])
    elif kind == "overtaking":                  # same track, faster one behind
        p_i, p_j = (0.0, 1000.0, p_i[2]), (draw(st.floats(1000.0, 5e4)), 1000.0, p_j[2])
        v_i, v_j = (draw(st.floats(200.0, 300.0)), 0.0, v_i[2]), (draw(st.floats(50.0, 190.0)), 0.0, v_j[2])
    elif kind == "diverging":                   # moving apart: T_min < 0
        p_i, p_j = (0.0, 0.0, p_i[2]), (draw(st.floats(1000.0, 5e4)), draw(st.floats(-5e3, 5e3)), p_j[2])
        v_i, v_j = (-draw(st.floats(50.0, 300.0)), 0.0, v_i[2]), (draw(st.floats(50.0, 300.0)), 0.0, v_j[2])
    return kind, p_i, v_i, p_j, v_j


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pair_states(), st.floats(10.0, 600.0))
def test_geometry_matches_exact_minimisation(case, t_thr):
    kind, p_i, v_i, p_j, v_j = case
    g = pair_geometry(p_i, v_i, p_j, v_j, t_thr=t_thr)
    r_min, t_min, dz_min, seed, speed = _exact(p_i, v_i, p_j, v_j, t_thr)
    r0 = math.hypot(p_j[0] - p_i[0], p_j[1] - p_i[1])
    # relative 1e-9; the absolute floors are the float rounding of the printed formulas
    # (cross/dot products of r and v lose ~1e-16·|r| absolutely; T_min then ~1e-16·|r|/|v|)
    assert float(g.r_min) == pytest.approx(r_min, rel=1e-9, abs=1e-12 * (r0 + 1.0))
    if math.isinf(t_min):
        assert math.isinf(float(g.t_min)) and float(g.r_min) == float(g.r0)
    else:
        assert float(g.t_min) == pytest.approx(t_min, rel=1e-9, abs=1e-12 * (r0 + 1.0) / speed)
    assert float(g.dz_min) == pytest.approx(dz_min, rel=1e-9, abs=1e-12 * (abs(p_j[2] - p_i[2]) + 1.0))
    if seed is not None:
        vscale = abs(p_j[2] - p_i[2]) + abs(v_j[2] - v_i[2]) * abs(t_min) + 1.0
        assert float(g.dz_min_seed) == pytest.approx(seed, rel=1e-9, abs=1e-12 * vscale)
    if kind == "parallel":
        assert math.isinf(float(g.t_min))
    if kind == "diverging":
        assert float(g.t_min) < 0
    if kind in ("head-on", "overtaking"):     # collinear: collision course ahead
        assert float(g.t_min) > 0 and float(g.r_min) == 0.0


def test_geometry_sampling_cross_check():
    """R_min/T_min by zooming dense sampling of |r(t)|² plus a parabola polish, random states."""
    rng = np.random.default_rng(4)
    p_i, p_j = rng.uniform(-5e4, 5e4, (200, 3)), rng.uniform(-5e4, 5e4, (200, 3))
    v_i, v_j = rng.uniform(-250, 250, (200, 3)), rng.uniform(-250, 250, (200, 3))
    g = pair_geometry(p_i, v_i, p_j, v_j)
    for k in range(200):
        d0, w = p_j[k, :2] - p_i[k, :2], v_j[k, :2] - v_i[k, :2]
        lo, hi = -1e6, 1e6
        for _ in range(3):                         # zoom in on the sampled minimum
            ts = np.linspace(lo, hi, 2001)
            d = d0[None, :] + w[None, :] * ts[:, None]
            m = int(np.clip(np.argmin(np.einsum("ij,ij->i", d, d)), 1, len(ts) - 2))
            lo, hi = ts[m - 1], ts[m + 1]
        t3 = ts[m - 1:m + 2]
        f3 = np.einsum("ij,ij->i", d[m - 1:m + 2], d[m - 1:m + 2])
        a, b, c = np.polyfit(t3 - t3[1], f3, 2)
        t_star = t3[1] - b / (2 * a)
        assert g.t_min[k] == pytest.approx(t_star, rel=1e-7, abs=1e-7)
        assert g.r_min[k] == pytest.approx(math.sqrt(max(c - b * b / (4 * a), 0.0)), rel=1e-6, abs=1e-3)


def test_parallel_tracks_defined():
    g = pair_geometry([0, 0, 0], [200, 10, 0], [3000, 4000, 0], [200, 10, 0])
    assert float(g.r_min) == 5000.0 and math.isinf(float(g.t_min))
    inside = _frame([[0, 0, 0], [3000, 4000, 0]], [[200, 10, 0], [200, 10, 0]])
    # 5 km apart side by side, co-level: inside both thresholds all the time → the same-time rule
    # alerts (they are losing separation now); (5.14) needs T_min ≤ T and does not
    out = predict_conflicts(inside, FIXED)
    assert out.height == 1 and out["alert"][0] and math.isinf(out["t_min_s"][0]) and out["t_in_s"][0] == 0.0
    assert not predict_conflicts(inside, dataclasses.replace(FIXED, mode="seed"))["alert"][0]
    far = _frame([[0, 0, 0], [6000, 8000, 0]], [[200, 10, 0], [200, 10, 0]])      # 10 km: outside R + margin
    assert predict_conflicts(far, FIXED).height == 0


def test_sign_convention_approaching_positive():
    g = pair_geometry([0, 0, 0], [100, 0, 0], [10000, 0, 0], [0, 0, 0])
    assert float(g.t_min) == pytest.approx(100.0) and float(g.closure) == pytest.approx(100.0)
    g = pair_geometry([0, 0, 0], [-100, 0, 0], [10000, 0, 0], [0, 0, 0])
    assert float(g.t_min) == pytest.approx(-100.0) and float(g.closure) == pytest.approx(-100.0)


# --------------------------------------------------------------------------- decision rules


def test_seed_flags_passed_pairs_corrected_does_not():
    # passed each other 30 s ago at 1 km miss, now 7.2 km apart horizontally, co-level
    df = _frame([[-3600, 0, 3000], [3600, 1000, 3000]], [[-120, 0, 0], [120, 0, 0]])
    seed = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="seed"))
    corr = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="corrected"))
    assert seed["alert"].to_list() == [True]
    assert seed["t_min_s"][0] == pytest.approx(-30.0)
    assert not corr["alert"].any()
    # never within R_thr + margin during [0, T] → not even a candidate
    assert predict_conflicts(df, ConflictConfig(threshold_mode="fixed", near_margin_h_m=0.0)).height == 0


def test_corrected_rule_needs_both_at_the_same_time():
    # head-on, R_min = 0 at T_min = 50 s, horizontally inside R_thr for t ∈ [18.2, 81.8] s;
    # aircraft 2 is 1000 m higher and descends at 6 m/s: vertically inside only for t ≥ 97.5 s
    df = _frame([[0, 0, 3000], [10000, 0, 4000]], [[100, 0, 0], [-100, 0, -6]])
    seed = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="seed"))
    corr = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="corrected"))
    z_thr = 304.8 + 50 + 60
    # seed (5.13) looks at T_min only: 1000 − 6·50 = 700 > 414.8 → no alert
    assert seed["dz_min_m"][0] == pytest.approx(700.0) and seed["z_thr_m"][0] == pytest.approx(z_thr)
    assert not seed["alert"][0]
    # corrected: the two intervals do not overlap → no alert; |Δh| at the CPA is 700 m
    assert corr["dz_min_m"][0] == pytest.approx(700.0) and not corr["alert"][0]
    # descending at 15 m/s instead: vertically inside from 39.0 s → overlap [39.0, 81.8] → alert
    fast = df.with_columns(pl.Series("vz_mps", [0.0, -15.0]), pl.Series("alt_rate_mps", [0.0, -15.0]))
    out = predict_conflicts(fast, ConflictConfig(threshold_mode="fixed", mode="corrected"))
    assert out["alert"][0] and out["dz_min_m"][0] == pytest.approx(250.0)
    assert out["t_in_s"][0] == pytest.approx((1000 - z_thr) / 15.0)
    # climbing away instead: neither rule alerts, and the pair is not even a candidate
    away = df.with_columns(pl.Series("vz_mps", [0.0, 6.0]), pl.Series("alt_rate_mps", [0.0, 6.0]))
    assert predict_conflicts(away, ConflictConfig(threshold_mode="fixed", mode="corrected")).height == 0


def test_climbing_pair_issue_11():
    """Horizontal CPA 0 m at t = 100 s, B 300 m above A and climbing 10 m/s (1 300 m apart at the
    CPA, never losing separation): no alert in corrected mode, an alert in seed mode (co-level
    now, |Δh| = 300 ≤ R_в^пор)."""
    df = _frame([[-10000, 0, 3000], [10000, 0, 3300]], [[100, 0, 0], [-100, 0, 10]])
    corr = predict_conflicts(df, ConflictConfig(threshold_mode="fixed"))
    seed = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="seed"))
    assert corr.height == 1 and not corr["alert"][0] and corr["dz_min_m"][0] == pytest.approx(1300.0)
    assert seed["alert"][0]
    # the same with heights from geodesy far from the centre (100 km east, equal start heights)
    frame = LocalFrame(48.7, 2.4, 0.0)
    x0, y0 = 100_000.0, 0.0
    e, n, u = frame.from_geodetic(*frame.to_geodetic(np.array([x0 - 10000, x0 + 10000]), np.array([y0, y0]),
                                                     np.zeros(2))[:2], np.array([3000.0, 3300.0]))
    geo_df = _frame(np.column_stack([e, n, u]), [[100, 0, 0], [-100, 0, 10]], alt=False)
    assert not predict_conflicts(geo_df, ConflictConfig(threshold_mode="fixed"), frame=frame)["alert"].any()


def test_thresholds_fixed_and_airspace():
    cfg = ConflictConfig(threshold_mode="fixed")
    assert cfg.sep_h_m == pytest.approx(5556.0) and cfg.sep_v_m == pytest.approx(304.8)
    en = ConflictConfig(threshold_mode="fixed", airspace="en-route")
    assert en.sep_h_m == pytest.approx(9260.0)
    df = _frame([[0, 0, 3000], [20000, 0, 3000]], [[100, 0, 0], [-100, 0, 0]])
    out = predict_conflicts(df, en)
    assert out["r_thr_m"][0] == pytest.approx(9260 + 300 + 500)
    # both level: the level-pair threshold Δr_в − 100 ft (corrected rule); climbing: (5.16)
    assert out["z_thr_m"][0] == pytest.approx(304.8 - 30.48)
    climb = predict_conflicts(_frame([[0, 0, 3000], [20000, 0, 3000]], [[100, 0, 5], [-100, 0, 0]]), en)
    assert climb["z_thr_m"][0] == pytest.approx(304.8 + 50 + 60)
    explicit = ConflictConfig(threshold_mode="fixed", dr_h_m=1000.0, t_delays_s=(5.0,), t_man_s=10.0,
                              pilot_h_m=100.0, pilot_h_rate_mps=2.0)
    assert explicit.t_thr_s == 15.0
    out = predict_conflicts(_frame([[0, 0, 0], [1500, 0, 0]], [[50, 0, 0], [-50, 0, 0]]), explicit)
    assert out["r_thr_m"][0] == pytest.approx(1000 + 300 + 100 + 2.0 * 15)


def test_covariance_thresholds_diag_and_full():
    T = 100.0                                        # evaluated at clip(T_min, 0, 105) = 100 s
    var = [100.0 ** 2, 100.0 ** 2, 30.0 ** 2, 2.0 ** 2, 2.0 ** 2, 1.0 ** 2]
    df = _frame([[0, 0, 3000], [20000, 0, 3100]], [[100, 0, 0], [-100, 0, 0]], cov_diag=[var, var])
    # the height channel with its own variances (a barometric channel): q = var_h + t²·var_ḣ
    df = df.with_columns(pl.lit(var[2]).alias("alt_var_m2"), pl.lit(var[5]).alias("alt_rate_var_m2ps2"))
    cfg = ConflictConfig(level_pair_tolerance_m=None)      # (5.16) itself, not the level-pair rule
    out = predict_conflicts(df, cfg)
    k_h, k_v = math.sqrt(chi2.ppf(0.95, 2)), norm.ppf(0.975)
    rel_h = 2 * (1e4 + T * T * 4.0)
    rel_v = 2 * (900.0 + T * T * 1.0)
    assert out["r_thr_m"][0] == pytest.approx(5556 + 500 + k_h * math.sqrt(rel_h), rel=1e-12)
    assert out["z_thr_m"][0] == pytest.approx(304.8 + 60 + k_v * math.sqrt(rel_v), rel=1e-12)
    # a full covariance with position–velocity cross terms and an anisotropic shape
    rng = np.random.default_rng(1)
    covs = []
    for _ in range(2):
        a = rng.normal(size=(6, 6)) * np.array([80, 60, 30, 3, 2, 1])[:, None]
        covs.append(a @ a.T)
    # geodetic heights 100 km from the centre: the height variance is along the local up at
    # each target (pymap3d's normal, independent of tertiary.core.geo), not along ENU z
    frame = LocalFrame(48.7, 2.4, 0.0)
    pos = np.array([[100_000.0, 0, 3000], [120_000.0, 0, 3100]])
    dfc = (_frame(pos, [[100, 0, 0], [-100, 0, 0]], alt=False)
           .with_columns(pl.Series("cov", np.stack(covs).reshape(2, 36), dtype=pl.Array(pl.Float64, 36))))
    outc = predict_conflicts(dfc, cfg, frame=frame)
    F = np.hstack([np.eye(3), T * np.eye(3)])        # position at T = F·state
    rel = sum(F @ c @ F.T for c in covs)
    lam = np.linalg.eigvalsh(rel[:2, :2]).max()
    lat, lon, _ = pymap3d.enu2geodetic(pos[:, 0], pos[:, 1], pos[:, 2], 48.7, 2.4, 0.0)
    ups = [np.array(pymap3d.ecef2enuv(math.cos(math.radians(la)) * math.cos(math.radians(lo)),
                                      math.cos(math.radians(la)) * math.sin(math.radians(lo)),
                                      math.sin(math.radians(la)), 48.7, 2.4)) for la, lo in zip(lat, lon)]
    q = sum(u @ F @ c @ F.T @ u for u, c in zip(ups, covs))
    assert outc["r_thr_m"][0] == pytest.approx(5556 + 500 + k_h * math.sqrt(lam), rel=1e-10)
    assert outc["z_thr_m"][0] == pytest.approx(304.8 + 60 + k_v * math.sqrt(q), rel=1e-9)
    assert abs(q - rel[2, 2]) > 1.0                  # the tilt matters: ENU z would be a different number
    fixed = predict_conflicts(dfc, ConflictConfig(threshold_mode="fixed"))
    assert fixed["r_thr_m"][0] == pytest.approx(5556 + 300 + 500)


def test_tentative_tracks_are_left_out():
    """A track whose velocity is still at its prior (σ_v = 300 m/s) raises no alert."""
    good = [50.0 ** 2, 50.0 ** 2, 30.0 ** 2, 3.0 ** 2, 3.0 ** 2, 1.0]
    prior = [50.0 ** 2, 50.0 ** 2, 30.0 ** 2, 300.0 ** 2, 300.0 ** 2, 100.0]
    df = _frame([[0, 0, 3000], [15000, 6000, 3600], [0, 3000, 3000]], [[120, 0, 0], [-100, -40, -5], [120, 0, 0]],
                cov_diag=[good, good, prior])
    for tm in ("covariance", "fixed"):
        out = predict_conflicts(df, ConflictConfig(threshold_mode=tm, dr_v_m=300.0))
        assert out.select("id_a", "id_b").rows() == [(1, 2)]
        kept = predict_conflicts(df, ConflictConfig(threshold_mode=tm, dr_v_m=300.0, max_vel_sigma_mps=None))
        assert kept.height == 3
    full = df.drop("cov_diag").with_columns(pl.Series("cov", [np.diag(v).ravel() for v in (good, good, prior)],
                                                      dtype=pl.Array(pl.Float64, 36)))
    assert predict_conflicts(full, ConflictConfig(dr_v_m=300.0)).select("id_a", "id_b").rows() == [(1, 2)]


def test_level_pairs_at_adjacent_levels_do_not_alert_but_level_busts_do():
    """Head-on, horizontal CPA 0 m at 100 s. Both level 1 000 ft apart (a holding stack): no
    alert in corrected mode (separated by their levels), an alert in seed mode; at the same
    level or 500 ft apart: an alert; one of them climbing 5 m/s from 1 000 ft below into the
    other's level (a level bust): an alert with the full (5.16) threshold."""
    pos = lambda dz: [[0, 0, 3000], [20000, 0, 3000 + dz]]          # noqa: E731
    head_on = [[100, 0, 0], [-100, 0, 0]]
    corr = ConflictConfig(threshold_mode="fixed")
    assert not predict_conflicts(_frame(pos(304.8), head_on), corr)["alert"].any()
    assert predict_conflicts(_frame(pos(304.8), head_on), ConflictConfig(threshold_mode="fixed", mode="seed"))["alert"].all()
    assert predict_conflicts(_frame(pos(0.0), head_on), corr)["alert"].all()
    assert predict_conflicts(_frame(pos(152.4), head_on), corr)["alert"].all()
    bust = predict_conflicts(_frame(pos(304.8), [[100, 0, 0], [-100, 0, -4.0]]), corr)
    assert bust["alert"].all() and bust["z_thr_m"][0] == pytest.approx(304.8 + 50 + 60)
    # disabled: the printed threshold applies to level pairs too
    off = ConflictConfig(threshold_mode="fixed", level_pair_tolerance_m=None)
    assert predict_conflicts(_frame(pos(304.8), head_on), off)["alert"].all()


def test_tracks_coasting_too_long_leave_the_prediction():
    """A track that lost its plots (plot_target_id null) keeps alerting for max_coast_s, then
    leaves; without the column every track stays."""
    rows = []
    for k in range(8):                                # epochs 0, 4, …, 28 s
        t = T0 + timedelta(seconds=4 * k)
        f = _frame([[0 + 400 * k, 0, 3000], [20000 - 400 * k, 0, 3000]], [[100, 0, 0], [-100, 0, 0]], epoch=t)
        rows.append(f.with_columns(pl.Series("plot_target_id", [1, 2 if k < 2 else None], dtype=pl.UInt64)))
    df = pl.concat(rows)
    out = predict_conflicts(df, ConflictConfig(threshold_mode="fixed"))
    # track 2 updated at 0, 4 s; coasting since 4 s: in at 8, 12 (≤ 10 s old), out from 16 s
    assert out["epoch"].to_list() == [T0 + timedelta(seconds=s) for s in (0, 4, 8, 12)]
    assert predict_conflicts(df.drop("plot_target_id"), ConflictConfig(threshold_mode="fixed")).height == 8
    assert predict_conflicts(df, ConflictConfig(threshold_mode="fixed", max_coast_s=None)).height == 8


def test_covariance_mode_needs_covariance():
    with pytest.raises(ValueError, match="cov"):
        predict_conflicts(_frame([[0, 0, 0], [100, 0, 0]], [[0, 0, 0], [0, 0, 0]]), ConflictConfig())


def test_config_validation():
    with pytest.raises(ValueError):
        ConflictConfig(mode="nope")
    with pytest.raises(ValueError):
        ConflictConfig(confidence=1.0)
    with pytest.raises(ValueError):
        ConflictConfig(airspace="oceanic")


# --------------------------------------------------------------------------- candidates vs brute force


def _random_picture(rng, n_per_group=40, groups=3, cov_kind="diag", wide=True):
    frames = []
    for gi in range(groups):
        n = n_per_group
        pos = np.column_stack([rng.uniform(-4e4, 4e4, n), rng.uniform(-4e4, 4e4, n), rng.uniform(500, 6000, n)])
        spd, hdg = rng.uniform(60, 250, n), rng.uniform(0, 2 * np.pi, n)
        vz = rng.choice([0.0, -10.0, 10.0], n) * rng.uniform(0.5, 1.5, n)       # level and climbing tiers
        vel = np.column_stack([spd * np.sin(hdg), spd * np.cos(hdg), vz])
        scale = rng.uniform(0.3, 3.0, n)
        if wide:                                  # outliers: very fast / very uncertain tracks
            vel[0, :2] *= 4.0
            scale[1] = 200.0
        var = np.array([60.0 ** 2, 60.0 ** 2, 40.0 ** 2, 4.0 ** 2, 4.0 ** 2, 1.5 ** 2])
        if cov_kind == "diag":
            kw = {"cov_diag": var[None, :] * scale[:, None]}
        else:
            a = rng.normal(size=(n, 6, 6)) * np.sqrt(var)[None, :, None] * np.sqrt(scale)[:, None, None] / 2
            kw = {"cov": np.einsum("nij,nkj->nik", a, a)}
        run, epoch = gi % 2, T0 + timedelta(seconds=5 * (gi // 2))
        ids = rng.permutation(1000)[:n] + 1
        frames.append(_frame(pos, vel, ids=ids, run=run, epoch=epoch, method="m", **kw))
    return pl.concat(frames)


def _up(r) -> np.ndarray:
    """Local vertical of the spherical fallback (no frame): the direction from the Earth's centre."""
    c = np.array([r["x_m"], r["y_m"], r["z_m"] + EARTH_RADIUS_M])
    return c / np.linalg.norm(c)


def _brute_force(df: pl.DataFrame, cfg: ConflictConfig):
    """Every same-group pair with its thresholds and window minima (the O(N²) reference);
    heights from the ``alt_m`` channel (= z), height variances along each track's local up."""
    T = cfg.t_thr_s
    w0, w1 = (0.0, T) if cfg.mode == "corrected" else (-T, T)
    k_h, k_v = math.sqrt(chi2.ppf(cfg.confidence, 2)), norm.ppf(0.5 + cfg.confidence / 2)
    mh, mv = cfg.near_margin_h_m, cfg.near_margin_v_m
    rows = df.to_dicts()
    out = {}
    for a, b in itertools.combinations(range(len(rows)), 2):
        ra, rb = rows[a], rows[b]
        if (ra["run"], ra["epoch"], ra["method"]) != (rb["run"], rb["epoch"], rb["method"]):
            continue
        if ra["track_id"] > rb["track_id"]:
            ra, rb = rb, ra
        s_a = np.array([ra[c] for c in ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")])
        s_b = np.array([rb[c] for c in ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")])
        d0, w = s_b[:3] - s_a[:3], s_b[3:] - s_a[3:]
        # |d0 + w t|² = A t² + B t + C on [w0, w1]
        A, B, C = w[:2] @ w[:2], 2 * d0[:2] @ w[:2], d0[:2] @ d0[:2]
        t_cpa = -B / (2 * A) if A >= 1e-12 else math.inf
        t_eval = T if (cfg.mode == "seed" or math.isinf(t_cpa)) else min(max(t_cpa, 0.0), T)
        F = np.hstack([np.eye(3), t_eval * np.eye(3)])
        if cfg.threshold_mode == "fixed":
            r_thr = cfg.sep_h_m + cfg.fixed_est_h_m + cfg.pilot_h_m
            z_thr = cfg.sep_v_m + cfg.fixed_est_v_m + cfg.pilot_v_m
        else:
            cov = lambda r: (np.diag(r["cov_diag"]) if "cov_diag" in r else np.asarray(r["cov"]).reshape(6, 6))  # noqa: E731
            rel = F @ (cov(ra) + cov(rb)) @ F.T
            q = sum(_up(r) @ F @ cov(r) @ F.T @ _up(r) for r in (ra, rb))
            r_thr = cfg.sep_h_m + cfg.pilot_h_m + k_h * math.sqrt(np.linalg.eigvalsh(rel[:2, :2]).max())
            z_thr = cfg.sep_v_m + cfg.pilot_v_m + k_v * math.sqrt(q)
        if cfg.mode == "corrected" and cfg.level_pair_tolerance_m is not None \
                and max(abs(s_a[5]), abs(s_b[5])) <= cfg.level_rate_mps:       # a level pair
            z_thr = min(z_thr, cfg.sep_v_m - cfg.level_pair_tolerance_m)
        cand = [w0, w1] + ([-B / (2 * A)] if A > 0 and w0 < -B / (2 * A) < w1 else [])
        h_min = math.sqrt(max(min(A * t * t + B * t + C for t in cand), 0.0))
        zc = [w0, w1] + ([-d0[2] / w[2]] if w[2] != 0 and w0 < -d0[2] / w[2] < w1 else [])
        v_min = min(abs(d0[2] + w[2] * t) for t in zc)
        if h_min <= r_thr + mh and v_min <= z_thr + mv:
            out[(ra["run"], ra["epoch"], ra["track_id"], rb["track_id"])] = (r_thr, z_thr)
    return out


@pytest.mark.parametrize("mode", ["corrected", "seed"])
@pytest.mark.parametrize("threshold_mode,cov_kind", [("fixed", "diag"), ("covariance", "diag"), ("covariance", "full")])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kdtree_candidates_equal_brute_force(mode, threshold_mode, cov_kind, seed):
    rng = np.random.default_rng(seed)
    df = _random_picture(rng, cov_kind=cov_kind)
    cfg = ConflictConfig(mode=mode, threshold_mode=threshold_mode, max_vel_sigma_mps=None)
    ref = _brute_force(df, cfg)
    out = predict_conflicts(df, cfg)
    got = {(r["run"], r["epoch"], r["id_a"], r["id_b"]): (r["r_thr_m"], r["z_thr_m"]) for r in out.to_dicts()}
    assert len(ref) > 10
    assert set(got) == set(ref)
    for k, (rh, rv) in ref.items():
        assert got[k][0] == pytest.approx(rh, rel=1e-9) and got[k][1] == pytest.approx(rv, rel=1e-9)
    # the screen is a superset of the brute-force set, within groups only
    i, j = conflict_candidates(df, cfg)
    ids = df["track_id"].to_numpy()
    runs, epochs = df["run"].to_list(), df["epoch"].to_list()
    assert all(runs[a] == runs[b] and epochs[a] == epochs[b] for a, b in zip(i, j))
    screened = {(runs[a], epochs[a], min(ids[a], ids[b]), max(ids[a], ids[b])) for a, b in zip(i, j)}
    assert set(ref) <= screened


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.sampled_from(["corrected", "seed"]), st.sampled_from(["fixed", "covariance"]),
       st.integers(2, 14), st.floats(5e3, 1e5))
def test_candidates_equal_brute_force_random_small(seed, mode, threshold_mode, n, box):
    """Small random pictures of any density, with extreme speeds and covariances mixed in."""
    rng = np.random.default_rng(seed)
    frames = []
    for gi in range(2):
        pos = np.column_stack([rng.uniform(-box, box, n), rng.uniform(-box, box, n), rng.uniform(0, 3000, n)])
        vel = rng.normal(0, 1, (n, 3)) * np.array([200.0, 200.0, 10.0]) * rng.choice([0.0, 1.0, 8.0], (n, 1))
        var = np.array([50.0 ** 2, 50.0 ** 2, 30.0 ** 2, 3.0 ** 2, 3.0 ** 2, 1.0]) * rng.choice([0.0, 1.0, 100.0], (n, 1))
        frames.append(_frame(pos, vel, ids=rng.permutation(50)[:n] + 1, run=gi, method="m", cov_diag=var))
    df = pl.concat(frames)
    cfg = ConflictConfig(mode=mode, threshold_mode=threshold_mode, max_vel_sigma_mps=None)
    ref = _brute_force(df, cfg)
    out = predict_conflicts(df, cfg)
    assert set(zip(out["run"], out["epoch"], out["id_a"], out["id_b"])) == set(ref)


def test_screen_is_sparse_on_large_pictures():
    """1 000 aircraft in a 200 km box: the screen examines a small fraction of all pairs."""
    rng = np.random.default_rng(3)
    n = 1000
    pos = np.column_stack([rng.uniform(-1e5, 1e5, n), rng.uniform(-1e5, 1e5, n), rng.uniform(300, 12000, n)])
    spd, hdg = rng.uniform(70, 250, n), rng.uniform(0, 2 * np.pi, n)
    vel = np.column_stack([spd * np.sin(hdg), spd * np.cos(hdg), rng.choice([0.0, 8.0, -8.0], n)])
    df = _frame(pos, vel, cov_diag=np.tile([2500.0, 2500.0, 6400.0, 25.0, 25.0, 4.0], (n, 1)))
    i, _ = conflict_candidates(df, ConflictConfig())
    assert len(i) < 0.05 * n * (n - 1) / 2


def test_v_max_setting_does_not_change_result():
    rng = np.random.default_rng(7)
    df = _random_picture(rng, n_per_group=60, groups=2)
    base = predict_conflicts(df, ConflictConfig())
    for v in (50.0, 150.0, 2000.0):
        assert predict_conflicts(df, ConflictConfig(v_max_mps=v)).equals(base)
    assert predict_conflicts(df, ConflictConfig(bulk_quantile=0.5, chunk_pairs=7)).equals(base)
    assert predict_conflicts(df, ConflictConfig(bulk_quantile=1.0, block_points=2)).equals(base)
    assert predict_conflicts(df.reverse(), ConflictConfig()).equals(base)     # row order is irrelevant


def _sampled(ra: dict, rb: dict, r_thr: float, z_thr: float, T: float, dt: float = 0.05) -> tuple[bool, bool]:
    """Brute force on the predicted tracks (heights = alt_m, rates = alt_rate_mps; with a
    ``level`` key, the height is held at that level once reached — the selected-level clamp),
    sampled every ``dt`` over [0, T]: (some sample inside both thresholds shrunk by 1e-6
    relative, some sample inside both widened by the motion over dt) — the closed form must
    alert in the first case and may alert only in the second."""
    t = np.arange(0.0, T + dt / 2, dt)

    def height(r):
        lin = r["alt_m"] + r["alt_rate_mps"] * t
        lv = r.get("level")
        if lv is None:
            return lin
        return np.minimum(lin, lv) if r["alt_rate_mps"] > 0 else np.maximum(lin, lv)
    dx = (rb["x_m"] - ra["x_m"]) + (rb["vx_mps"] - ra["vx_mps"]) * t
    dy = (rb["y_m"] - ra["y_m"]) + (rb["vy_mps"] - ra["vy_mps"]) * t
    dz = height(rb) - height(ra)
    dh = np.hypot(dx, dy)
    sh = math.hypot(rb["vx_mps"] - ra["vx_mps"], rb["vy_mps"] - ra["vy_mps"]) * dt
    sv = (abs(rb["alt_rate_mps"] - ra["alt_rate_mps"]) if "level" not in ra and "level" not in rb
          else abs(rb["alt_rate_mps"]) + abs(ra["alt_rate_mps"])) * dt
    inner = (dh <= r_thr * (1 - 1e-6)) & (np.abs(dz) <= z_thr * (1 - 1e-6))
    outer = (dh <= r_thr + sh + 1e-6) & (np.abs(dz) <= z_thr + sv + 1e-6)
    return bool(inner.any()), bool(outer.any())


@settings(max_examples=300, deadline=None)
@given(st.floats(-3e4, 3e4), st.floats(-3e4, 3e4), st.floats(-400, 400), st.floats(-400, 400),
       st.floats(-3000, 3000), st.floats(-40, 40), st.floats(100, 9000), st.floats(50, 1500), st.floats(1, 300))
def test_interval_intersection_matches_sampling(rx, ry, vx, vy, dz, dvz, r_thr, z_thr, t_thr):
    """The closed-form same-time rule (roots of the horizontal quadratic ∩ the linear vertical
    interval ∩ [0, T]) against brute-force sampling of the predicted separation."""
    t_in, t_out = conflict_interval(np.array([rx]), np.array([ry]), np.array([vx]), np.array([vy]),
                                    np.array([dz]), np.array([dvz]), r_thr, z_thr, t_thr, eps=1e-12)
    a = {"x_m": 0.0, "y_m": 0.0, "alt_m": 0.0, "vx_mps": vx, "vy_mps": vy, "alt_rate_mps": 0.0}
    b = {"x_m": rx, "y_m": ry, "alt_m": dz, "vx_mps": 0.0, "vy_mps": 0.0, "alt_rate_mps": dvz}
    dt = t_thr / 4000
    inner, outer = _sampled(a, b, r_thr, z_thr, t_thr, dt)
    alert = bool(t_in[0] <= t_out[0])
    assert (not inner or alert) and (outer or not alert)
    if alert:                                        # the interval's mid point is inside both
        tm = 0.5 * (t_in[0] + t_out[0])
        assert math.hypot(rx - vx * tm, ry - vy * tm) <= r_thr * (1 + 1e-9) + 1e-6
        assert abs(dz + dvz * tm) <= z_thr * (1 + 1e-9) + 1e-6
        assert 0.0 <= t_in[0] <= t_out[0] <= t_thr


@settings(max_examples=400, deadline=None)
@given(st.floats(-3e4, 3e4), st.floats(-3e4, 3e4), st.floats(-400, 400), st.floats(-400, 400),
       st.floats(-3000, 3000), st.floats(-30, 30), st.floats(-30, 30), st.floats(0, 400) | st.just(math.inf),
       st.floats(0, 400) | st.just(math.inf), st.floats(100, 9000), st.floats(50, 1500), st.floats(1, 300))
def test_levelled_interval_matches_sampling(rx, ry, vx, vy, dz, vz_a, vz_b, tau_a, tau_b, r_thr, z_thr, t_thr):
    """The same-time rule with each aircraft's height stopped at its selected level after τ
    (three linear pieces of Δh) against brute-force sampling of the clamped predicted tracks;
    with τ = ∞ it is :func:`conflict_interval` exactly."""
    args = [np.array([v]) for v in (rx, ry, vx, vy, dz, vz_a, vz_b, tau_a, tau_b)]
    t_in, t_out = conflict_interval_levelled(*args, r_thr, z_thr, t_thr, eps=1e-12)
    a = {"x_m": 0.0, "y_m": 0.0, "alt_m": 0.0, "vx_mps": vx, "vy_mps": vy, "alt_rate_mps": vz_a,
         "level": None if math.isinf(tau_a) else vz_a * tau_a}
    b = {"x_m": rx, "y_m": ry, "alt_m": dz, "vx_mps": 0.0, "vy_mps": 0.0, "alt_rate_mps": vz_b,
         "level": None if math.isinf(tau_b) else dz + vz_b * tau_b}
    inner, outer = _sampled(a, b, r_thr, z_thr, t_thr, t_thr / 4000)
    alert = bool(t_in[0] <= t_out[0])
    assert (not inner or alert) and (outer or not alert)
    if alert:                                        # the stretch's mid point is inside both
        tm = 0.5 * (t_in[0] + t_out[0])
        h = lambda h0, v, tau: h0 + v * min(tm, tau)    # noqa: E731
        assert math.hypot(rx - vx * tm, ry - vy * tm) <= r_thr * (1 + 1e-9) + 1e-6
        assert abs(h(dz, vz_b, tau_b) - h(0.0, vz_a, tau_a)) <= z_thr * (1 + 1e-9) + 1e-6
        assert 0.0 <= t_in[0] <= t_out[0] <= t_thr
    if math.isinf(tau_a) and math.isinf(tau_b):
        lin = conflict_interval(*args[:5], np.array([vz_b - vz_a]), r_thr, z_thr, t_thr, eps=1e-12)
        assert (t_in[0] <= t_out[0]) == (lin[0][0] <= lin[1][0])
        if t_in[0] <= t_out[0]:
            assert t_in[0] == pytest.approx(lin[0][0], abs=1e-9) and t_out[0] == pytest.approx(lin[1][0], abs=1e-9)


def test_decision_matches_rule_on_random_pictures():
    rng = np.random.default_rng(11)
    df = _random_picture(rng, n_per_group=80, groups=2)
    for mode in ("corrected", "seed"):
        cfg = ConflictConfig(mode=mode)
        out = predict_conflicts(df, cfg)
        T = cfg.t_thr_s
        if mode == "corrected":
            rule = pl.col("t_in_s").is_not_nan()
            # the same-time rule on the predicted tracks, sampled every 0.05 s (robust margins)
            st_ = {r["track_id"]: r for r in df.filter(pl.col("run") == 0).to_dicts()}
            for r in out.filter(pl.col("run") == 0).to_dicts():
                if r["epoch"] != df["epoch"][0]:
                    continue
                hit_in, hit_out = _sampled(st_[r["id_a"]], st_[r["id_b"]], r["r_thr_m"], r["z_thr_m"], T)
                assert (not hit_in or r["alert"]) and (hit_out or not r["alert"])
        else:
            rule = ((pl.col("r_min_m") <= pl.col("r_thr_m")) & (pl.col("t_min_s") <= T)
                    & ((pl.col("dz_m").abs() <= pl.col("z_thr_m")) | (pl.col("dz_min_m") <= pl.col("z_thr_m"))))
        chk = out.with_columns(rule.alias("expect"))
        assert (chk["expect"] == chk["alert"]).all()
        assert chk["alert"].sum() > 0
        assert ((out["severity"] >= 0) & (out["severity"] <= 1)).all()
        assert (out.filter(~pl.col("alert"))["severity"] == 0).all()


# --------------------------------------------------------------------------- output contract


def test_output_schema_order_and_ids():
    df = _frame([[15000, 6000, 3600], [0, 0, 3000]], [[-100, -40, -5], [120, 0, 0]], ids=[9, 4], method="invcov")
    out = predict_conflicts(df, FIXED)
    assert out.schema == pl.Schema({**TABLES["conflicts"].required, **CONFLICT_EXTRA})
    validate(out, "conflicts")
    assert out["id_a"].to_list() == [4] and out["id_b"].to_list() == [9] and out["method"][0] == "invcov"
    # same geometry as with the ids the other way round
    assert out["r_min_m"][0] == pytest.approx(3219.9, abs=0.05) and out["t_min_s"][0] == pytest.approx(70.8)


def test_groups_do_not_mix_and_id_col():
    a = _frame([[0, 0, 3000], [15000, 6000, 3600]], [[120, 0, 0], [-100, -40, -5]], method="a")
    b = a.with_columns(pl.lit("b").alias("method"))
    c = a.with_columns(pl.lit(1, pl.UInt32).alias("run"))
    d = a.with_columns((pl.col("epoch") + timedelta(seconds=1)))
    one = a.slice(0, 1)
    other = a.slice(1, 1).with_columns(pl.lit("y").alias("method"))
    out = predict_conflicts(pl.concat([a, b, c, d, one.with_columns(pl.lit("z").alias("method")), other]), FIXED)
    assert out.height == 4
    assert out.select("run", "epoch", "method").unique().height == 4
    fused = a.rename({"track_id": "target_id"})
    assert predict_conflicts(fused, FIXED, id_col="target_id").height == 1


def test_empty_and_single_and_duplicates():
    empty = predict_conflicts(_frame(np.zeros((0, 3)), np.zeros((0, 3))), FIXED)
    assert empty.height == 0 and empty.schema == pl.Schema({**TABLES["conflicts"].required, **CONFLICT_EXTRA})
    assert predict_conflicts(_frame([[0, 0, 0]], [[1, 0, 0]]), FIXED).height == 0
    with pytest.raises(ValueError, match="duplicate"):
        predict_conflicts(_frame([[0, 0, 0], [10, 0, 0]], [[0, 0, 0], [0, 0, 0]], ids=[3, 3]), FIXED)


def test_fast_outlier_pair_found():
    """One 1 500 m/s track (a bad velocity estimate) among slow ones is still screened exactly."""
    pos = [[0, 0, 3000], [150_000, 0, 3000]] + [[x, 60_000, 3000] for x in np.linspace(-1e5, 1e5, 50)]
    vel = [[1500, 0, 0], [0, 0, 0]] + [[100, 0, 0]] * 50
    out = predict_conflicts(_frame(pos, vel), FIXED)
    row = out.filter((pl.col("id_a") == 1) & (pl.col("id_b") == 2))
    assert row.height == 1 and row["alert"][0] and row["t_min_s"][0] == pytest.approx(100.0)


# --------------------------------------------------------------------------- vertical channel on height


FRAME = LocalFrame(48.7, 2.4, 0.0)


@pytest.mark.parametrize("frame", [FRAME, None])
def test_equal_height_far_from_centre_has_zero_vertical_separation(frame):
    """Two level aircraft at 9 000 m, 100 km and 150 km from the centre in different directions:
    zero vertical separation and zero vertical rate from geodesy (ENU z differs by ~1 km)."""
    pts = [(100e3, 0.0), (0.0, -150e3), (-70e3, 70e3)]
    if frame is None:                                # the spherical fallback: a sphere of radius R
        pos = np.array([_sphere_point(x, y, 9000.0, EARTH_RADIUS_M) for x, y in pts])
    else:
        pos = np.array([np.array(frame.from_geodetic(*frame.to_geodetic(x, y, 0.0)[:2], 9000.0)).ravel()
                        for x, y in pts])
    h, _, u = height_and_rate(pos, np.zeros_like(pos), frame)
    # level flight radially outwards at 230 m/s: horizontal at the target (⟂ its local up)
    radial = np.column_stack([pos[:, :2] / np.linalg.norm(pos[:, :2], axis=1)[:, None], np.zeros(3)])
    vel = radial - np.einsum("ij,ij->i", radial, u)[:, None] * u
    vel *= 230.0 / np.linalg.norm(vel, axis=1)[:, None]
    _, hdot, _ = height_and_rate(pos, vel, frame)
    assert np.ptp(h) < 0.01 and abs(h[0] - 9000.0) < 0.01
    assert np.max(np.abs(hdot)) < 1e-9
    assert np.ptp(pos[:, 2]) > 900.0                 # ENU z would show ~1 km
    assert abs(vel[0, 2]) > 3.0                      # and ~3.6 m/s of false vertical rate
    if frame is not None:                            # predict_conflicts sees such a pair co-level
        lat, lon, _ = frame.to_geodetic(np.array([100e3, 100e3]), np.array([0.0, 3e3]), np.zeros(2))
        p2 = np.column_stack(frame.from_geodetic(lat, lon, np.full(2, 9000.0)))
        out = predict_conflicts(_frame(p2, np.zeros((2, 3)), alt=False), FIXED, frame=frame)
        assert abs(out["dz_m"][0]) < 1e-6 and out["alert"][0]


def _sphere_point(x: float, y: float, h: float, R: float) -> np.ndarray:
    """The ENU point at height h above the sphere of radius R under the ground point (x, y)."""
    rho = math.hypot(x, y)
    th = rho / R
    return np.array([x / rho * (R + h) * math.sin(th), y / rho * (R + h) * math.sin(th), (R + h) * math.cos(th) - R])


def test_height_and_rate_against_pymap3d():
    rng = np.random.default_rng(5)
    pos = np.column_stack([rng.uniform(-150e3, 150e3, 200), rng.uniform(-150e3, 150e3, 200), rng.uniform(0, 12e3, 200)])
    vel = rng.normal(0, 150, (200, 3))
    h, hdot, _ = height_and_rate(pos, vel, FRAME)
    _, _, h_ref = pymap3d.enu2geodetic(pos[:, 0], pos[:, 1], pos[:, 2], FRAME.lat_deg, FRAME.lon_deg, FRAME.alt_m)
    assert np.max(np.abs(h - h_ref)) < 1e-3
    dt = 1e-3                                        # rate = finite difference of the height
    _, _, h2 = pymap3d.enu2geodetic(*(pos + vel * dt).T, FRAME.lat_deg, FRAME.lon_deg, FRAME.alt_m)
    _, _, h1 = pymap3d.enu2geodetic(*(pos - vel * dt).T, FRAME.lat_deg, FRAME.lon_deg, FRAME.alt_m)
    assert np.max(np.abs(hdot - (h2 - h1) / (2 * dt))) < 1e-3


def test_alt_channel_wins_where_present():
    df = _frame([[100e3, 0, 8000], [101e3, 0, 8000]], [[100, 0, 0], [-100, 0, 0]], alt=False)
    df = df.with_columns(pl.Series("alt_m", [9000.0, None]), pl.Series("alt_rate_mps", [1.0, None]))
    out = predict_conflicts(df, FIXED, frame=FRAME)
    h_geo, _, _ = height_and_rate(np.array([[101e3, 0, 8000]]), np.zeros((1, 3)), FRAME)
    assert out["dz_m"][0] == pytest.approx(h_geo[0] - 9000.0, abs=1e-6)


def test_tangent_plane_horizontal_error_bound():
    """Horizontal geometry stays on the system tangent plane. Against the geodesic distance of
    the two footprints on the ellipsoid (pymap3d Vincenty), for pairs ≤ 20 km apart anywhere
    within 150 km of the centre at 0–12 km height, with height differences ≤ 3 km: the error is
    below :func:`tangent_plane_error_bound` (d·(ρ²/2R² + h/R) + |Δh|·ρ/R + 1 m)."""
    from pymap3d.vincenty import vdist
    rng = np.random.default_rng(9)
    n = 400
    rho, az = 150e3 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    d, bz = rng.uniform(0, 20e3, n), rng.uniform(0, 2 * np.pi, n)
    ha = rng.uniform(0, 12e3, n)
    hb = np.clip(ha + rng.uniform(-3e3, 3e3, n), 0, 12e3)
    a_geo = FRAME.to_geodetic(rho * np.sin(az), rho * np.cos(az), np.zeros(n))
    pa = np.column_stack(FRAME.from_geodetic(a_geo[0], a_geo[1], ha))
    b_en = np.column_stack([rho * np.sin(az) + d * np.sin(bz), rho * np.cos(az) + d * np.cos(bz)])
    b_geo = FRAME.to_geodetic(b_en[:, 0], b_en[:, 1], np.zeros(n))
    pb = np.column_stack(FRAME.from_geodetic(b_geo[0], b_geo[1], hb))
    plane = np.hypot(*(pb[:, :2] - pa[:, :2]).T)
    ref = np.asarray(vdist(a_geo[0], a_geo[1], b_geo[0], b_geo[1])[0], float)
    err = np.abs(plane - ref)
    r_max = np.maximum(np.hypot(*pa[:, :2].T), np.hypot(*pb[:, :2].T))
    bound = tangent_plane_error_bound(ref, r_max, np.maximum(ha, hb), np.abs(hb - ha))
    assert np.all(err <= bound)
    assert err.max() > 1.0                           # the test can see an error at all
    assert tangent_plane_error_bound(10e3, 150e3, 12e3, 1000.0) < 47.0


def test_slim_conflicts_keeps_alerts_and_near_pairs():
    rng = np.random.default_rng(2)
    df = _random_picture(rng, n_per_group=80, groups=2)
    out = predict_conflicts(df, ConflictConfig())
    slim = slim_conflicts(out)
    assert slim["alert"].sum() == out["alert"].sum() and slim.height < out.height
    assert (slim["alert"] | slim["near"]).all()
    # near = the same-time rule with widened thresholds: a zero margin keeps the alerts only
    zero = predict_conflicts(df, ConflictConfig(near_margin_h_m=0.0, near_margin_v_m=0.0))
    assert slim_conflicts(zero).height == zero["alert"].sum()


def test_slim_conflicts_from_stored_geometry():
    """A table without the ``near`` column (or explicit margins) is slimmed on its stored geometry."""
    df = _frame([[0, 0, 3000], [20000, 7000, 3000], [0, 30000, 3000], [20000, 37000, 3400]],
                [[100, 0, 0], [-100, 0, 0], [100, 0, 0], [-100, 0, 10]])
    out = predict_conflicts(df, FIXED)
    # (1, 2): co-level, R_min 7 000 m > R_thr 6 356 m but within 1 NM → near; (3, 4): the same
    # horizontally, 400 m above and climbing away at 10 m/s → within the margins only apart in
    # time (vertically for t < 10.6 s, horizontally for t ∈ [78.6, 121] s) → screened, not near
    assert set(zip(out["id_a"], out["id_b"])) == {(1, 2), (3, 4)}
    got = slim_conflicts(out.drop("near"))
    assert set(zip(got["id_a"], got["id_b"])) == {(1, 2)} and not got["alert"].any()
    assert slim_conflicts(out.drop("near"), margin_h_m=100.0).height == 0
    assert set(zip(slim_conflicts(out)["id_a"], slim_conflicts(out)["id_b"])) == {(1, 2)}


def test_two_tracks_of_one_aircraft_are_a_duplicate_not_a_conflict():
    """Tracks with the same Mode S address are one aircraft tracked twice (a duplicate track):
    they must not alert; a different or missing address still does."""
    cfg = ConflictConfig(threshold_mode="fixed")
    pos, vel = [[0, 0, 3000], [400, 0, 3000], [0, 4000, 3000]], [[100, 0, 0], [100, 0, 0], [0, -100, 0]]
    for ident, alerting in ((["abc123", "abc123", "def456"], {(1, 3), (2, 3)}),
                            (["abc123", "abc124", None], {(1, 2), (1, 3), (2, 3)}),
                            ([None, None, None], {(1, 2), (1, 3), (2, 3)})):
        df = _frame(pos, vel).with_columns(pl.Series("mode_s", ident, dtype=pl.String))
        out = predict_conflicts(df, cfg)
        assert {(r["id_a"], r["id_b"]) for r in out.filter("alert").iter_rows(named=True)} == alerting, ident
    off = predict_conflicts(_frame(pos, vel).with_columns(pl.Series("mode_s", ["a", "a", "b"])),
                            ConflictConfig(threshold_mode="fixed", same_identity_is_duplicate=False))
    assert (1, 2) in {(r["id_a"], r["id_b"]) for r in off.filter("alert").iter_rows(named=True)}
    # the same three below an en-route floor, after two en-route aircraft in the table: the pairs
    # below the floor are predicted on a subset of the rows, whose addresses are those of its rows
    high = [[0, 60_000, 9000], [400, 60_000, 9000]]
    df = _frame(high + pos, [[100, 0, 0], [100, 0, 0]] + vel).with_columns(
        pl.Series("mode_s", ["h1", "h2", "abc123", "abc123", "def456"]))
    out = predict_conflicts(df, dataclasses.replace(cfg, enroute_above_m=5000.0))
    assert {(r["id_a"], r["id_b"]) for r in out.filter("alert").iter_rows(named=True)} == {(1, 2), (3, 5), (4, 5)}
