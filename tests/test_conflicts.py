"""Conflict prediction (5.10)–(5.17): geometry against an independent exact computation, the
digest worked example, thresholds, KD-tree candidates against brute force, output contract."""

from __future__ import annotations

import itertools
import math
from datetime import datetime, timedelta, timezone
from fractions import Fraction

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import chi2, norm

from safety.conflicts import ConflictConfig, candidate_pairs, pair_geometry, predict_conflicts
from tertiary.schema import TABLES, validate

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
FIXED = ConflictConfig(threshold_mode="fixed", dr_v_m=300.0)      # digest §7.2 thresholds


def _frame(pos, vel, ids=None, run=0, epoch=T0, method=None, cov=None, cov_diag=None) -> pl.DataFrame:
    pos, vel = np.asarray(pos, float).reshape(-1, 3), np.asarray(vel, float).reshape(-1, 3)
    n = len(pos)
    data = {"run": np.full(n, run, np.uint32), "epoch": [epoch] * n,
            "track_id": np.arange(1, n + 1, dtype=np.uint64) if ids is None else np.asarray(ids, np.uint64),
            "x_m": pos[:, 0], "y_m": pos[:, 1], "z_m": pos[:, 2],
            "vx_mps": vel[:, 0], "vy_mps": vel[:, 1], "vz_mps": vel[:, 2]}
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


def test_digest_worked_example_geometry():
    g = pair_geometry([0, 0, 3000], [120, 0, 0], [15000, 6000, 3600], [-100, -40, -5])
    assert float(g.r_min) == pytest.approx(3219.9, abs=0.05)
    assert float(g.t_min) == pytest.approx(70.80, abs=0.005)
    assert float(g.dz_min_seed) == pytest.approx(246.0, abs=0.05)
    assert float(g.r0) == pytest.approx(16155.5, abs=0.05)
    assert float(g.dz) == 600.0


@pytest.mark.parametrize("mode", ["seed", "corrected"])
def test_digest_worked_example_decision(mode):
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
    assert row["dz_min_m"] == pytest.approx(246.0 if mode == "seed" else 75.0)
    assert row["severity"] == pytest.approx(1 - row["r_min_m"] / 6356.0)
    # vz_2 = 0: the vertical separation stays 600 m > 410 m → no conflict (no candidate at all)
    level = predict_conflicts(df.with_columns(pl.lit(0.0).alias("vz_mps")), cfg)
    assert level.height == 0 or not level["alert"].any()


# --------------------------------------------------------------------------- geometry vs exact


def _exact(p_i, v_i, p_j, v_j, t_thr):
    """Independent exact computation in rationals: minimise |d(t)|², d(t) = (p_j − p_i) + (v_j − v_i)t
    by setting the derivative to zero, then evaluate the distance at the minimiser."""
    P_i, V_i, P_j, V_j = ([Fraction(float(c)) for c in a] for a in (p_i, v_i, p_j, v_j))
    d0 = [P_j[k] - P_i[k] for k in range(2)]
    w = [V_j[k] - V_i[k] for k in range(2)]
    ww = w[0] * w[0] + w[1] * w[1]
    if ww == 0:
        r_min, t_min = math.sqrt(float(d0[0] ** 2 + d0[1] ** 2)), math.inf
    else:
        ts = -(d0[0] * w[0] + d0[1] * w[1]) / ww
        dm = [d0[k] + w[k] * ts for k in range(2)]
        r_min, t_min = math.sqrt(float(dm[0] ** 2 + dm[1] ** 2)), float(ts)
    dh, dvz = P_j[2] - P_i[2], V_j[2] - V_i[2]
    # corrected vertical: |Δh + Δvz t| over [0, T]: candidates are the ends and the root
    T = Fraction(float(t_thr))
    cands = [abs(dh), abs(dh + dvz * T)]
    if dvz != 0 and 0 <= -dh / dvz <= T:
        cands.append(Fraction(0))
    dz_min = float(min(cands))
    # seed (5.13) is the signed separation at T_min: sign(Δh)·(Δh + Δvz T_min)
    if ww == 0:
        seed = None
    else:
        sgn = (dh > 0) - (dh < 0)
        seed = float(sgn * (dh + dvz * ts)) if sgn else 0.0
    return r_min, t_min, dz_min, seed


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
        u = draw(st.floats(50.0, 300.0))
        dist = draw(st.floats(1000.0, 1e5))
        p_i, p_j = (0.0, 0.0, p_i[2]), (dist, 0.0, p_j[2])
        v_i, v_j = (u, 0.0, v_i[2]), (-draw(st.floats(50.0, 300.0)), 0.0, v_j[2])
        del u
    elif kind == "overtaking":                  # same track, faster one behind
        p_i, p_j = (0.0, 1000.0, p_i[2]), (draw(st.floats(1000.0, 5e4)), 1000.0, p_j[2])
        v_i, v_j = (draw(st.floats(200.0, 300.0)), 0.0, v_i[2]), (draw(st.floats(50.0, 190.0)), 0.0, v_j[2])
    elif kind == "diverging":                   # moving apart: T_min < 0
        p_i, p_j = (0.0, 0.0, p_i[2]), (draw(st.floats(1000.0, 5e4)), draw(st.floats(-5e3, 5e3)), p_j[2])
        v_i, v_j = (-draw(st.floats(50.0, 300.0)), 0.0, v_i[2]), (draw(st.floats(50.0, 300.0)), 0.0, v_j[2])
    return kind, p_i, v_i, p_j, v_j


@settings(max_examples=400, deadline=None)
@given(pair_states(), st.floats(10.0, 600.0))
def test_geometry_matches_exact_minimisation(case, t_thr):
    kind, p_i, v_i, p_j, v_j = case
    g = pair_geometry(p_i, v_i, p_j, v_j, t_thr=t_thr, eps=0.0 if kind != "parallel" else 1e-6)
    r_min, t_min, dz_min, seed = _exact(p_i, v_i, p_j, v_j, t_thr)
    scale = math.hypot(p_j[0] - p_i[0], p_j[1] - p_i[1]) + 1.0
    # relative 1e-9; the absolute floor covers the rounding of |r| itself (R_min ≪ |r|)
    assert float(g.r_min) == pytest.approx(r_min, rel=1e-9, abs=1e-12 * scale)
    if math.isinf(t_min):
        assert math.isinf(float(g.t_min))
        assert float(g.r_min) == pytest.approx(float(g.r0), rel=1e-12)
    else:
        assert float(g.t_min) == pytest.approx(t_min, rel=1e-9, abs=1e-12 * scale)
    assert float(g.dz_min) == pytest.approx(dz_min, rel=1e-9, abs=1e-9)
    if seed is not None:
        vscale = abs(p_j[2] - p_i[2]) + abs(v_j[2] - v_i[2]) * abs(t_min) + 1.0
        assert float(g.dz_min_seed) == pytest.approx(seed, rel=1e-9, abs=1e-12 * vscale)
    if kind == "diverging":
        assert float(g.t_min) < 0
    if kind in ("head-on", "overtaking"):
        assert float(g.t_min) > 0 and float(g.r_min) == pytest.approx(0.0, abs=1e-6) if kind == "head-on" else True


def test_geometry_sampling_cross_check():
    """R_min/T_min by dense sampling of |r(t)| plus a quadratic polish on random states."""
    rng = np.random.default_rng(4)
    p_i, p_j = rng.uniform(-5e4, 5e4, (200, 3)), rng.uniform(-5e4, 5e4, (200, 3))
    v_i, v_j = rng.uniform(-250, 250, (200, 3)), rng.uniform(-250, 250, (200, 3))
    g = pair_geometry(p_i, v_i, p_j, v_j)
    for k in range(200):
        ts = np.linspace(-2000, 2000, 400_001)
        d = (p_j[k, :2] - p_i[k, :2])[None, :] + (v_j[k, :2] - v_i[k, :2])[None, :] * ts[:, None]
        m = np.argmin(np.einsum("ij,ij->i", d, d))
        # polish: fit a parabola through the three samples around the minimum
        t3 = ts[m - 1:m + 2]
        f3 = np.einsum("ij,ij->i", d[m - 1:m + 2], d[m - 1:m + 2])
        a, b, c = np.polyfit(t3 - t3[1], f3, 2)
        t_star = t3[1] - b / (2 * a)
        assert g.t_min[k] == pytest.approx(t_star, rel=1e-6, abs=1e-6)
        assert g.r_min[k] == pytest.approx(math.sqrt(max(c - b * b / (4 * a), 0.0)), rel=1e-5, abs=1e-3)


def test_parallel_tracks_defined():
    g = pair_geometry([0, 0, 0], [200, 10, 0], [3000, 4000, 0], [200, 10, 0])
    assert float(g.r_min) == 5000.0 and math.isinf(float(g.t_min))
    out = predict_conflicts(_frame([[0, 0, 0], [3000, 4000, 0]], [[200, 10, 0], [200, 10, 0]]), FIXED)
    assert out.height == 1 and not out["alert"][0] and math.isinf(out["t_min_s"][0])


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
    assert corr.height == 0                       # never within R_thr during [0, T] → not a candidate


def test_corrected_vertical_uses_min_over_lookahead():
    # horizontal conflict at T_min = 50 s; aircraft 2 descends 1500 m → crosses 1000 ft band late
    df = _frame([[0, 0, 3000], [10000, 0, 4500]], [[100, 0, 0], [-100, 0, -10]])
    seed = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="seed"))
    corr = predict_conflicts(df, ConflictConfig(threshold_mode="fixed", mode="corrected"))
    # seed: R_v_min = 1500 − 10·50 = 1000 > 354.8 → no alert; corrected: |1500 − 10 t| reaches 450 at T=105
    assert seed["dz_min_m"][0] == pytest.approx(1000.0)
    assert not seed["alert"][0]
    assert corr["dz_min_m"][0] == pytest.approx(450.0)
    assert not corr["alert"][0] and corr.height == 0 or not corr["alert"][0]
    df2 = df.with_columns(pl.Series("vz_mps", [0.0, -14.0]))
    corr2 = predict_conflicts(df2, ConflictConfig(threshold_mode="fixed", mode="corrected"))
    assert corr2["alert"][0] and corr2["dz_min_m"][0] == pytest.approx(30.0)


def test_thresholds_fixed_and_airspace():
    cfg = ConflictConfig(threshold_mode="fixed")
    assert cfg.sep_h_m == pytest.approx(5556.0) and cfg.sep_v_m == pytest.approx(304.8)
    en = ConflictConfig(threshold_mode="fixed", airspace="en-route")
    assert en.sep_h_m == pytest.approx(9260.0)
    df = _frame([[0, 0, 3000], [20000, 0, 3000]], [[100, 0, 0], [-100, 0, 0]])
    out = predict_conflicts(df, en)
    assert out["r_thr_m"][0] == pytest.approx(9260 + 300 + 500)
    assert out["z_thr_m"][0] == pytest.approx(304.8 + 50 + 60)
    explicit = ConflictConfig(threshold_mode="fixed", dr_h_m=1000.0, t_delays_s=(5.0,), t_man_s=10.0,
                              pilot_h_m=100.0, pilot_h_rate_mps=2.0)
    assert explicit.t_thr_s == 15.0
    out = predict_conflicts(_frame([[0, 0, 0], [1500, 0, 0]], [[50, 0, 0], [-50, 0, 0]]), explicit)
    assert out["r_thr_m"][0] == pytest.approx(1000 + 300 + 100 + 2.0 * 15)


def test_covariance_thresholds_diag_and_full():
    T = 105.0
    var = [100.0 ** 2, 100.0 ** 2, 30.0 ** 2, 2.0 ** 2, 2.0 ** 2, 1.0 ** 2]
    df = _frame([[0, 0, 3000], [20000, 0, 3100]], [[100, 0, 0], [-100, 0, 0]], cov_diag=[var, var])
    cfg = ConflictConfig()
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
    dfc = df.drop("cov_diag").with_columns(pl.Series("cov", np.stack(covs).reshape(2, 36),
                                                     dtype=pl.Array(pl.Float64, 36)))
    outc = predict_conflicts(dfc, cfg)
    F = np.hstack([np.eye(3), T * np.eye(3)])        # position at T = F·state
    rel = sum(F @ c @ F.T for c in covs)
    lam = np.linalg.eigvalsh(rel[:2, :2]).max()
    assert outc["r_thr_m"][0] == pytest.approx(5556 + 500 + k_h * math.sqrt(lam), rel=1e-10)
    assert outc["z_thr_m"][0] == pytest.approx(304.8 + 60 + k_v * math.sqrt(rel[2, 2]), rel=1e-10)
    fixed = predict_conflicts(dfc, ConflictConfig(threshold_mode="fixed"))
    assert fixed["r_thr_m"][0] == pytest.approx(5556 + 300 + 500)


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
        vel = np.column_stack([spd * np.sin(hdg), spd * np.cos(hdg), rng.choice([0.0, -10.0, 10.0], n)])
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


def _brute_force(df: pl.DataFrame, cfg: ConflictConfig):
    """Every same-group pair with its thresholds and window minima (the O(N²) reference)."""
    T = cfg.t_thr_s
    w0, w1 = (0.0, T) if cfg.mode == "corrected" else (-T, T)
    F = np.hstack([np.eye(3), T * np.eye(3)])
    k_h, k_v = math.sqrt(chi2.ppf(cfg.confidence, 2)), norm.ppf(0.5 + cfg.confidence / 2)
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
        if cfg.threshold_mode == "fixed":
            r_thr = cfg.sep_h_m + cfg.fixed_est_h_m + cfg.pilot_h_m
            z_thr = cfg.sep_v_m + cfg.fixed_est_v_m + cfg.pilot_v_m
        else:
            cov = lambda r: (np.diag(r["cov_diag"]) if "cov_diag" in r else np.asarray(r["cov"]).reshape(6, 6))  # noqa: E731
            rel = F @ (cov(ra) + cov(rb)) @ F.T
            r_thr = cfg.sep_h_m + cfg.pilot_h_m + k_h * math.sqrt(np.linalg.eigvalsh(rel[:2, :2]).max())
            z_thr = cfg.sep_v_m + cfg.pilot_v_m + k_v * math.sqrt(rel[2, 2])
        d0, w = s_b[:3] - s_a[:3], s_b[3:] - s_a[3:]
        # |d0 + w t|² = A t² + B t + C on [w0, w1]
        A, B, C = w[:2] @ w[:2], 2 * d0[:2] @ w[:2], d0[:2] @ d0[:2]
        cand = [w0, w1] + ([-B / (2 * A)] if A > 0 and w0 < -B / (2 * A) < w1 else [])
        h_min = math.sqrt(max(min(A * t * t + B * t + C for t in cand), 0.0))
        zc = [w0, w1] + ([-d0[2] / w[2]] if w[2] != 0 and w0 < -d0[2] / w[2] < w1 else [])
        v_min = min(abs(d0[2] + w[2] * t) for t in zc)
        if h_min <= r_thr and v_min <= z_thr:
            out[(ra["run"], ra["epoch"], ra["track_id"], rb["track_id"])] = (r_thr, z_thr)
    return out


@pytest.mark.parametrize("mode", ["corrected", "seed"])
@pytest.mark.parametrize("threshold_mode,cov_kind", [("fixed", "diag"), ("covariance", "diag"), ("covariance", "full")])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kdtree_candidates_equal_brute_force(mode, threshold_mode, cov_kind, seed):
    rng = np.random.default_rng(seed)
    df = _random_picture(rng, cov_kind=cov_kind)
    cfg = ConflictConfig(mode=mode, threshold_mode=threshold_mode)
    ref = _brute_force(df, cfg)
    out = predict_conflicts(df, cfg)
    got = {(r["run"], r["epoch"], r["id_a"], r["id_b"]): (r["r_thr_m"], r["z_thr_m"]) for r in out.to_dicts()}
    assert len(ref) > 10
    assert set(got) == set(ref)
    for k, (rh, rv) in ref.items():
        assert got[k][0] == pytest.approx(rh, rel=1e-9) and got[k][1] == pytest.approx(rv, rel=1e-9)
    # the screen is a superset of the brute-force set and far from all pairs
    i, j = candidate_pairs(df, cfg)
    ids = df["track_id"].to_numpy()
    runs, epochs = df["run"].to_list(), df["epoch"].to_list()
    screened = {(runs[a], epochs[a], min(ids[a], ids[b]), max(ids[a], ids[b])) for a, b in zip(i, j)}
    assert set(ref) <= screened
    n_all = sum(len(g) * (len(g) - 1) // 2 for g in df.partition_by("run", "epoch"))
    assert len(screened) < n_all


def test_v_max_setting_does_not_change_result():
    rng = np.random.default_rng(7)
    df = _random_picture(rng, n_per_group=60, groups=2)
    base = predict_conflicts(df, ConflictConfig())
    for v in (50.0, 150.0, 2000.0):
        assert predict_conflicts(df, ConflictConfig(v_max_mps=v)).equals(base)
    assert predict_conflicts(df, ConflictConfig(bulk_quantile=0.5, chunk_pairs=7)).equals(base)


def test_decision_matches_rule_on_random_pictures():
    rng = np.random.default_rng(11)
    df = _random_picture(rng, n_per_group=80, groups=2)
    for mode in ("corrected", "seed"):
        cfg = ConflictConfig(mode=mode)
        out = predict_conflicts(df, cfg)
        T = cfg.t_thr_s
        if mode == "corrected":
            rule = ((pl.col("r_min_m") <= pl.col("r_thr_m")) & (pl.col("t_min_s") >= 0) & (pl.col("t_min_s") <= T)
                    & (pl.col("dz_min_m") <= pl.col("z_thr_m")))
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
    assert out.schema == pl.Schema(TABLES["conflicts"].required)
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
    other = a.slice(1, 1).with_columns(pl.lit("b").alias("method"))
    out = predict_conflicts(pl.concat([a, b, c, d, one.with_columns(pl.lit("z").alias("method")), other]), FIXED)
    assert out.height == 4
    assert out.select("run", "epoch", "method").unique().height == 4
    fused = a.rename({"track_id": "target_id"})
    assert predict_conflicts(fused, FIXED, id_col="target_id").height == 1


def test_empty_and_single_and_duplicates():
    empty = predict_conflicts(_frame(np.zeros((0, 3)), np.zeros((0, 3))), FIXED)
    assert empty.height == 0 and empty.schema == pl.Schema(TABLES["conflicts"].required)
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
