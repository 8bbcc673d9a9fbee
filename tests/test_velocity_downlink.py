"""The downlinked ground velocity (Mode S BDS 5,0 ground speed and true track) from the aircraft's
register to the secondary tracker's filter: the register's axes (true north at the aircraft) in
the simulator and in the system frame, the fused measurement's time, the IMM update, the gate
and the interface every registered filter keeps.

Oracles: pymap3d for every change of axes; filterpy's Kalman filter for each model's update;
the same tracker without the downlink on the same plots.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pymap3d as pm
import pytest
from filterpy.kalman import KalmanFilter
from scipy.stats import multivariate_normal

from tertiary.core import geo
from tertiary.filters import REGISTRY, TrackFilter, make_filter
from tertiary.filters.imm import imm_velocity_update
from tertiary.simulate.ehs import ehs_truth
from tertiary.simulate.trajectory import Trajectories
from tertiary.stages.fusion.measurement import downlinked_velocity, ehs_measurement
from tertiary.stages.tracking.altitude import AltState, update_rate
from tertiary.stages.tracking.config import TrackerConfig
from tertiary.stages.tracking.gating import velocity_covariance
from tertiary.stages.tracking.tracker import track_methods

SYSTEM = geo.LocalFrame(46.8, 2.5, 0.0)
DT = 4.0
T0 = datetime(2021, 10, 7, 8, 0, tzinfo=timezone.utc)


# --------------------------------------------------------------------------- axes


def _points(n: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return (rng.uniform(41.0, 52.0, n), rng.uniform(-5.0, 10.0, n), *rng.normal(0.0, 200.0, (3, n)))


def test_a_vector_at_a_point_turned_into_the_frame_equals_pymap3d_and_back():
    lat, lon, e, n, u = _points(200, 0)
    got = np.array(geo.local_vector_to_frame(e, n, u, lat, lon, SYSTEM))
    want = np.array(pm.uvw2enu(*pm.enu2uvw(e, n, u, lat, lon), SYSTEM.lat_deg, SYSTEM.lon_deg))
    np.testing.assert_allclose(got, want, atol=1e-9)
    back = np.array(geo.frame_vector_to_local(*got, lat, lon, SYSTEM))
    want_back = np.array(pm.uvw2enu(*pm.enu2uvw(*got, SYSTEM.lat_deg, SYSTEM.lon_deg), lat, lon))
    np.testing.assert_allclose(back, want_back, atol=1e-9)
    np.testing.assert_allclose(back, [e, n, u], atol=1e-9)


def _meridian_flight(lon_deg: float, speed: float = 230.0, alt_m: float = 10_000.0) -> Trajectories:
    """One aircraft flying due north along a meridian at constant geodetic altitude, sampled
    every second in the system frame (velocity: the local north vector turned by pymap3d)."""
    t = np.arange(0.0, 61.0)
    lat = 46.0 + speed * t / 111_200.0
    lon = np.full_like(t, lon_deg)
    pos = np.stack(pm.geodetic2enu(lat, lon, alt_m, SYSTEM.lat_deg, SYSTEM.lon_deg, SYSTEM.alt_m), axis=-1)
    vel = np.stack(pm.uvw2enu(*pm.enu2uvw(0.0, speed, 0.0, lat, lon), SYSTEM.lat_deg, SYSTEM.lon_deg), axis=-1)
    n = len(t)
    return Trajectories(dt=1.0, pos=pos[None], vel=vel[None], active=np.ones((1, n), bool),
                        segment=np.zeros((1, n), np.int8), truth_id=np.array([1], np.int64))


def test_the_simulated_register_is_over_true_north_and_the_local_vertical():
    traj = _meridian_flight(lon_deg=9.0)                 # ~500 km east of the system origin
    t = np.array([20.0, 30.0, 40.0])
    got, ok = ehs_truth(traj, np.zeros(3, np.int64), t, SYSTEM)
    assert ok.all()
    np.testing.assert_allclose(got["true_track_deg"], 0.0, atol=0.02)
    np.testing.assert_allclose(got["ground_speed_mps"], 230.0, atol=0.05)
    np.testing.assert_allclose(got["vertical_rate_mps"], 0.0, atol=0.05)
    # in the system frame's axes the same flight heads 4.7° west of north and climbs 3.8 m/s:
    # the register must not carry that
    flat, _ = ehs_truth(traj, np.zeros(3, np.int64), t)
    assert abs(flat["true_track_deg"][0]) > 4.0 and abs(flat["vertical_rate_mps"][0]) > 3.0


def test_the_register_of_recorded_fixes_is_their_reported_velocity():
    """A trajectory of recorded fixes (ADS-B): positions jittered by 50 m, the reported velocity
    steady at 200 m/s north. The register between two fixes is that velocity, not the derivative
    of the position interpolant, which swings by tens of m/s there."""
    rng = np.random.default_rng(3)
    n = 60
    t = np.arange(float(n))
    pos = np.stack([np.zeros(n), 200.0 * t, np.full(n, 9000.0)], axis=1) + rng.normal(0.0, 50.0, (n, 3))
    vel = np.tile([0.0, 200.0, 0.0], (n, 1))
    traj = Trajectories(dt=1.0, pos=pos[None], vel=vel[None], active=np.ones((1, n), bool),
                        segment=np.zeros((1, n), np.int8), truth_id=np.array([1], np.int64))
    q = np.arange(5.5, 50.0, 1.0)
    got, ok = ehs_truth(traj, np.zeros(len(q), np.int64), q)
    assert ok.all()
    np.testing.assert_allclose(got["ground_speed_mps"], 200.0, atol=1e-9)
    np.testing.assert_allclose(got["true_track_deg"], 0.0, atol=1e-9)
    np.testing.assert_allclose(got["vertical_rate_mps"], 0.0, atol=1e-9)


def test_the_plot_velocity_is_the_register_turned_into_the_system_frame():
    """Ground velocity and vertical rate together are the aircraft's velocity in its local axes:
    turned into the system frame, a climb far from the origin has a horizontal part there
    (the local vertical leans over the frame's). Without a vertical rate, the horizontal alone."""
    lat, lon, *_ = _points(50, 1)
    rng = np.random.default_rng(2)
    gs, track = rng.uniform(60.0, 280.0, 50), rng.uniform(-180.0, 180.0, 50)
    vrate = rng.uniform(-15.0, 25.0, 50)
    z = np.stack(pm.geodetic2enu(lat, lon, 9000.0, SYSTEM.lat_deg, SYSTEM.lon_deg, SYSTEM.alt_m), axis=-1)
    gs[3], track[4], z[5], vrate[6] = np.nan, np.nan, np.nan, np.nan
    reports = pl.DataFrame({"ehs_gs_mps": gs, "ehs_track_deg": track, "ehs_track_rate_dps": np.full(50, 1.5),
                            "ehs_vrate_mps": vrate})
    got = downlinked_velocity(reports, z, SYSTEM)
    ve, vn = gs * np.sin(np.radians(track)), gs * np.cos(np.radians(track))
    want = np.array(pm.uvw2enu(*pm.enu2uvw(ve, vn, np.nan_to_num(vrate), lat, lon), SYSTEM.lat_deg,
                               SYSTEM.lon_deg))[:2].T
    ok = np.ones(50, bool)
    ok[[3, 4, 5]] = False
    np.testing.assert_allclose(got[ok, :2], want[ok], atol=1e-6)
    assert np.isnan(got[~ok, :2]).all()
    # the points lie up to ~800 km out: the vertical rate moves them by up to ~3 m/s there
    level = np.array(pm.uvw2enu(*pm.enu2uvw(ve, vn, 0.0, lat, lon), SYSTEM.lat_deg, SYSTEM.lon_deg))[:2].T
    assert np.nanmax(np.abs(want[ok] - level[ok])) > 1.0
    np.testing.assert_allclose(got[:, 2], -np.radians(1.5))           # clockwise °/s → ω rad/s
    np.testing.assert_allclose(got[:, 3], vrate)                      # along the local vertical: as sent


def test_the_measurement_takes_the_newest_plot_with_a_velocity_turned_to_the_measurement_time():
    # group 0: plots aged 1.0 (vertical rate only), 2.5 and 3.0 s; group 1: no velocity, a rate
    ehs = np.array([[np.nan, np.nan, np.nan, -3.0], [100.0, 0.0, 0.02, np.nan], [0.0, 50.0, 0.0, 7.0],
                    [np.nan, np.nan, 0.01, 2.0], [np.nan, np.nan, np.nan, 4.0]])
    age = np.array([1.0, 2.5, 3.0, 1.5, 0.5])
    a0 = np.array([1.0, 0.5])
    got = ehs_measurement(ehs, age, a0, np.array([0, 3]))
    # by hand: the 2.5 s plot, turned by 0.02 rad/s over 1.5 s counter-clockwise; the vertical
    # rate of the 1.0 s plot (the newest carrying one)
    np.testing.assert_allclose(got[0], [100.0 * np.cos(0.03), 100.0 * np.sin(0.03), -3.0], atol=1e-12)
    assert np.isnan(got[1, :2]).all() and got[1, 2] == 4.0


# --------------------------------------------------------------------------- the filter update


def test_each_models_update_and_the_mode_probabilities_equal_filterpy():
    rng = np.random.default_rng(5)
    b, m = 4, 3
    x = rng.normal(0.0, 50.0, (b, m, 4))
    a = rng.normal(0.0, 1.0, (b, m, 4, 4))
    p = a @ np.swapaxes(a, -1, -2) + np.eye(4) * 4.0
    mu = rng.dirichlet(np.ones(m), b)
    v = rng.normal(0.0, 50.0, (b, 2))
    r = np.array([[[2.0, 0.3], [0.3, 1.0]]] * b)
    mask = np.array([True, True, False, True])
    out = imm_velocity_update({"x": x, "P": p, "mu": mu, "xv": np.zeros((b, 2))}, v, r, mask, 0.0)
    h = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    for i in range(b):
        lik = np.empty(m)
        for j in range(m):
            kf = KalmanFilter(dim_x=4, dim_z=2)
            kf.x, kf.P, kf.H, kf.R = x[i, j].copy(), p[i, j].copy(), h, r[i]
            lik[j] = multivariate_normal(h @ x[i, j], h @ p[i, j] @ h.T + r[i]).pdf(v[i])
            kf.update(v[i])
            want_x, want_p = (kf.x, kf.P) if mask[i] else (x[i, j], p[i, j])
            np.testing.assert_allclose(out["x"][i, j], want_x, rtol=1e-10, atol=1e-9)
            np.testing.assert_allclose(out["P"][i, j], want_p, rtol=1e-9, atol=1e-9)
        want_mu = mu[i] * lik / np.sum(mu[i] * lik) if mask[i] else mu[i]
        np.testing.assert_allclose(out["mu"][i], want_mu, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(out["xv"], 0.0)


def test_the_velocity_covariance_is_along_and_across_the_track():
    cfg = TrackerConfig(velocity_speed_sigma_mps=1.0, velocity_track_sigma_deg=0.5, velocity_refresh_s=1.0)
    v = np.array([[0.0, 200.0], [200.0, 0.0]])
    r = velocity_covariance(v, np.array([np.nan, 0.03]), cfg)
    cross0 = (200.0 * np.radians(0.5)) ** 2
    np.testing.assert_allclose(r[0], [[cross0, 0.0], [0.0, 1.0]], atol=1e-12)
    # turning: the register may be up to 1 s old, (ω v)² τ²/3 across
    np.testing.assert_allclose(r[1], [[1.0, 0.0], [0.0, cross0 + (0.03 * 200.0) ** 2 / 3.0]], atol=1e-12)


# --------------------------------------------------------------------------- through the tracker


def _fused_straight(velocity: str = "true", outlier_at: int | None = None, seed: int = 7):
    """A ``fused`` frame of 30 aircraft flying straight at 150–250 m/s, plots σ 80 m per axis
    every DT, and each row's downlinked velocity: the truth + 0.7 m/s noise ("true"), its
    opposite ("flipped") or none ("none"); ``outlier_at``: one scan's register 150 m/s off (no
    aircraft changes its velocity so fast)."""
    rng = np.random.default_rng(seed)
    b, n = 30, 30
    hdg = rng.uniform(0.0, 2.0 * np.pi, b)
    vel = rng.uniform(150.0, 250.0, b)[:, None] * np.stack([np.cos(hdg), np.sin(hdg)], axis=1)
    start = np.stack([np.arange(b) * 80_000.0, np.zeros(b)], axis=1)
    t = np.arange(n) * DT
    pos = start[:, None, :] + vel[:, None, :] * t[None, :, None]
    z = pos + rng.normal(0.0, 80.0, pos.shape)
    vm = vel[:, None, :] + rng.normal(0.0, 0.7, pos.shape)
    if velocity == "flipped":
        vm = -vm
    if outlier_at is not None:
        vm[:, outlier_at] += np.array([0.0, 150.0])
    cov = np.zeros(36)
    cov[[0, 7, 14]] = 80.0 ** 2
    cov[[21, 28, 35]] = 400.0
    cols = {
        "run": np.zeros(b * n, np.uint32), "epoch": [T0 + timedelta(seconds=DT * (i % n)) for i in range(b * n)],
        "target_id": np.repeat(np.arange(b), n).astype(np.uint64), "method": "information",
        "x_m": z[..., 0].ravel(), "y_m": z[..., 1].ravel(), "z_m": np.full(b * n, 9000.0),
        "vx_mps": 0.0, "vy_mps": 0.0, "vz_mps": 0.0, "cov": [cov.tolist()] * (b * n),
    }
    if velocity != "none":
        cols["meas_vx_mps"], cols["meas_vy_mps"] = vm[..., 0].ravel(), vm[..., 1].ravel()
    frame = pl.DataFrame(cols, schema_overrides={"run": pl.UInt32, "target_id": pl.UInt64,
                                                 "epoch": pl.Datetime("us", "UTC"), "cov": pl.Array(pl.Float64, 36)})
    return frame, pos, vel


def _errors(tracks: pl.DataFrame, pos: np.ndarray, vel: np.ndarray) -> tuple[float, float]:
    """Horizontal position and velocity RMSE over scans 10 on (each track's nearest truth)."""
    t = tracks.with_columns(k=((pl.col("epoch") - T0).dt.total_seconds() / DT).round().cast(pl.Int64))
    t = t.filter(pl.col("k") >= 10).sort("track_id", "k")
    k = t["k"].to_numpy()
    d = np.hypot(pos[:, k, 0] - t["x_m"].to_numpy(), pos[:, k, 1] - t["y_m"].to_numpy())
    ac = d.argmin(axis=0)
    dv = np.hypot(vel[ac, 0] - t["vx_mps"].to_numpy(), vel[ac, 1] - t["vy_mps"].to_numpy())
    return float(np.sqrt(np.mean(d.min(axis=0) ** 2))), float(np.sqrt(np.mean(dv ** 2)))


def test_the_tracker_hands_the_downlinked_velocity_to_the_filter():
    filters = {"imm_sym": make_filter("imm_sym")}
    given, pos, vel = _fused_straight("true")
    none, _, _ = _fused_straight("none")
    flipped, _, _ = _fused_straight("flipped")
    on = _errors(track_methods(given, filters), pos, vel)
    off = _errors(track_methods(given, filters, TrackerConfig(use_velocity=False)), pos, vel)
    absent = _errors(track_methods(none, filters), pos, vel)
    assert off == absent                          # switched off = not downlinked
    assert on[1] < 0.3 * off[1] and on[0] < 0.8 * off[0], (on, off)
    # a velocity of the wrong sense must not help (the axes are what the assert above rests on)
    assert _errors(track_methods(flipped, filters), pos, vel)[1] > 3.0 * on[1]


def test_a_register_far_from_the_tracks_velocity_is_left_out():
    filters = {"imm_sym": make_filter("imm_sym")}
    bad, pos, vel = _fused_straight("true", outlier_at=20)
    good, _, _ = _fused_straight("true")
    # the same run with that scan's register missing
    gap = good.with_columns(
        pl.when(pl.col("epoch") == T0 + timedelta(seconds=20 * DT)).then(None).otherwise(pl.col(c)).alias(c)
        for c in ("meas_vx_mps", "meas_vy_mps"))
    got = track_methods(bad, filters).select("epoch", "track_id", "x_m", "y_m", "vx_mps", "vy_mps")
    want = track_methods(gap, filters).select("epoch", "track_id", "x_m", "y_m", "vx_mps", "vy_mps")
    assert got.equals(want)
    # without the gate the outlier pulls every track
    loose = track_methods(bad, filters, TrackerConfig(velocity_gate=1e9))
    assert not loose.select("vx_mps", "vy_mps").equals(want.select("vx_mps", "vy_mps"))


@pytest.mark.parametrize("kw", [dict(velocity_speed_sigma_mps=0.0), dict(velocity_track_sigma_deg=float("nan")),
                                dict(velocity_refresh_s=-1.0), dict(velocity_gate=float("nan")),
                                dict(vertical_rate_sigma_mps=float("nan")), dict(vertical_rate_gate=0.0)])
def test_the_velocity_parameters_are_checked(kw):
    with pytest.raises(ValueError, match="velocity|vertical_rate"):
        TrackerConfig(**kw)


# --------------------------------------------------------------------------- the vertical rate


def test_a_rate_update_of_the_altitude_filter_equals_filterpy():
    rng = np.random.default_rng(9)
    n = 6
    h, r = rng.normal(9000.0, 100.0, n), rng.normal(0.0, 5.0, n)
    a = rng.normal(0.0, 1.0, (n, 2, 2))
    p = a @ np.swapaxes(a, -1, -2) + np.eye(2)
    z, var = rng.normal(0.0, 5.0, n), rng.uniform(0.1, 4.0, n)
    got, nu, sv = update_rate(AltState(h, r, p[:, 0, 0], p[:, 0, 1], p[:, 1, 1]), z, var)
    for i in range(n):
        kf = KalmanFilter(dim_x=2, dim_z=1)
        kf.x, kf.P, kf.H, kf.R = np.array([h[i], r[i]]), p[i].copy(), np.array([[0.0, 1.0]]), np.array([[var[i]]])
        kf.update(np.array([z[i]]))
        np.testing.assert_allclose([got.h[i], got.r[i]], kf.x, rtol=1e-12)
        np.testing.assert_allclose([[got.phh[i], got.phr[i]], [got.phr[i], got.prr[i]]], kf.P, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose([nu[i], sv[i]], [z[i] - r[i], p[i, 1, 1] + var[i]], rtol=1e-12)


def _fused_climb(rate: str = "true", outlier_at: int | None = None, seed: int = 11):
    """``_fused_straight`` aircraft that climb at 12 m/s from scan 15, with each plot's vertical
    channel a height σ 10 m and no rate knowledge (0 ± 30 m/s), and the downlinked vertical
    rate: truth + 0.3 m/s noise ("true") or none; ``outlier_at``: one scan's rate 40 m/s off."""
    frame, pos, vel = _fused_straight("none", seed=seed)
    b, n = len(pos), pos.shape[1]
    rng = np.random.default_rng(seed + 1)
    k = np.arange(n)
    true_rate = np.where(k >= 15, 12.0, 0.0)
    h = 9000.0 + np.r_[0.0, np.cumsum(true_rate[1:] * DT)]
    h = np.broadcast_to(h, (b, n))
    cols = {"alt_m": (h + rng.normal(0.0, 10.0, (b, n))).ravel(), "alt_rate_mps": np.zeros(b * n),
            "alt_var_m2": np.full(b * n, 100.0), "alt_cov_m2ps": np.zeros(b * n),
            "alt_rate_var_m2ps2": np.full(b * n, 900.0)}
    if rate != "none":
        vr = np.broadcast_to(true_rate, (b, n)) + rng.normal(0.0, 0.3, (b, n))
        if outlier_at is not None:
            vr = vr.copy()
            vr[:, outlier_at] += 40.0
        cols["meas_vrate_mps"] = vr.ravel()
    return frame.with_columns(pl.Series(c, v) for c, v in cols.items()), true_rate


def _rate_rmse(tracks: pl.DataFrame, true_rate: np.ndarray) -> float:
    """The altitude rate RMSE over the climb's first 6 scans."""
    t = tracks.with_columns(k=((pl.col("epoch") - T0).dt.total_seconds() / DT).round().cast(pl.Int64))
    t = t.filter((pl.col("k") >= 15) & (pl.col("k") < 21))
    return float(np.sqrt(np.mean((t["alt_rate_mps"].to_numpy() - true_rate[t["k"].to_numpy()]) ** 2)))


def test_the_tracker_hands_the_downlinked_vertical_rate_to_the_altitude_filter():
    filters = {"imm_sym": make_filter("imm_sym")}
    given, true_rate = _fused_climb("true")
    none, _ = _fused_climb("none")
    on = _rate_rmse(track_methods(given, filters), true_rate)
    off = _rate_rmse(track_methods(given, filters, TrackerConfig(use_vertical_rate=False)), true_rate)
    absent = _rate_rmse(track_methods(none, filters), true_rate)
    assert off == absent
    assert on < 0.3 * off, (on, off)


def test_a_vertical_rate_far_from_the_tracks_is_left_out():
    filters = {"imm_sym": make_filter("imm_sym")}
    bad, _ = _fused_climb("true", outlier_at=10)
    good, _ = _fused_climb("true")
    gap = good.with_columns(pl.when(pl.col("epoch") == T0 + timedelta(seconds=10 * DT)).then(None)
                            .otherwise(pl.col("meas_vrate_mps")).alias("meas_vrate_mps"))
    cols = ("epoch", "track_id", "alt_m", "alt_rate_mps")
    assert track_methods(bad, filters).select(cols).equals(track_methods(gap, filters).select(cols))
    loose = track_methods(bad, filters, TrackerConfig(vertical_rate_gate=1e9)).select(cols)
    assert not loose.equals(track_methods(gap, filters).select(cols))


# --------------------------------------------------------------------------- every filter


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_every_filter_takes_a_velocity_and_keeps_its_state_form(name):
    filt = make_filter(name)
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 1000.0, (5, 3))
    st = filt.init(z, np.full((5, 3), 50.0 ** 2))
    st = filt.predict(st, np.full(5, DT))
    r = np.broadcast_to(np.eye(2), (5, 2, 2)).copy()
    same = filt.observe_velocity(st, np.full((5, 2), np.nan), r, np.ones(5, bool))
    masked = filt.observe_velocity(st, np.full((5, 2), 100.0), r, np.zeros(5, bool))
    for other in (same, masked):
        assert other.keys() == st.keys()
        for key in st:
            np.testing.assert_array_equal(other[key], st[key])
    v = np.array([[100.0, 0.0], [0.0, -200.0], [np.nan, np.nan], [50.0, 50.0], [-10.0, 5.0]])
    used = filt.observe_velocity(st, v, r, np.ones(5, bool))
    assert used.keys() == st.keys()
    for key in st:
        assert used[key].shape == st[key].shape
        np.testing.assert_array_equal(np.isfinite(used[key]), np.isfinite(st[key]))
        np.testing.assert_array_equal(used[key][2], st[key][2])
    if type(filt).observe_velocity is not TrackFilter.observe_velocity:
        # a filter that takes it moves its velocity to the measurement (σ_v0 ≫ 1 m/s)
        np.testing.assert_allclose(filt.output(used).x[[0, 1, 3, 4], 3:5], v[[0, 1, 3, 4]], atol=1.0)
    if "mu" in used:
        np.testing.assert_allclose(used["mu"].sum(axis=1), 1.0)
