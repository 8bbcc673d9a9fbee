"""ADS-B reference quality, interpolation limits, and the RTS smoother."""

from __future__ import annotations

import dataclasses
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from filterpy.kalman import KalmanFilter

from tertiary.core import geo
from tertiary.evaluation.reference import (K95_2D, ReferenceConfig, SmootherConfig, _fq, adsb_reference, interpolate_reference, plot_measurements, reconstruct_reference, rts_smooth)
from tertiary.simulate import load_scenario, simulate

ORIGIN = geo.LocalFrame(48.9, 2.4, 0.0)
T0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)


def _adsb(icao: str, n: int, lat0: float, extra: dict | None = None) -> pl.DataFrame:
    """A straight eastbound flight at 200 kt, one fix a second."""
    t = np.arange(n)
    v = 200 * 1852 / 3600
    lon = 2.4 + v * t / (111_320 * np.cos(np.radians(lat0)))
    return pl.DataFrame({"timestamp": [T0 + timedelta(seconds=int(s)) for s in t], "icao24": [icao] * n,
                         "latitude": np.full(n, lat0), "longitude": lon, "altitude": np.full(n, 10_000.0),
                         "groundspeed": np.full(n, 200.0), "track": np.full(n, 90.0),
                         "vertical_rate": np.zeros(n), **(extra or {})})


def test_declared_quality_filters_and_states_the_reference_error():
    good = _adsb("aaaaaa", 120, 48.9, {"nacp": np.full(120, 9)})
    poor = _adsb("bbbbbb", 120, 48.95, {"nacp": np.full(120, 6)})
    points, removed = adsb_reference(pl.concat([good, poor]), ORIGIN)
    assert set(points["icao24"]) == {"aaaaaa"} and points.height == 120
    assert points["sigma_h_m"][0] == pytest.approx(30.0 / 2.4477, rel=1e-4)
    assert K95_2D == pytest.approx(np.sqrt(-2 * np.log(0.05)))
    assert points["quality_declared"].all()
    assert removed.filter(pl.col("reason").str.contains("NACP 6 < 8")).height == 120
    assert points.height + removed.height == 240                      # every row accounted for
    # without a declared quality the assumed bound is stated, and flagged
    points, _ = adsb_reference(_adsb("cccccc", 120, 48.9), ORIGIN, ReferenceConfig(default_epu95_m=50.0))
    assert not points["quality_declared"].any() and points["epu95_m"][0] == 50.0


def test_jumps_and_stale_positions_are_not_reference():
    f = _adsb("aaaaaa", 120, 48.9)
    lat = f["latitude"].to_numpy().copy()
    lon = f["longitude"].to_numpy().copy()
    lat[50] += 0.2                                      # a 22 km jump for one fix
    lon[80], lat[80] = lon[79], lat[79]                # a re-stamped (stale) position
    points, removed = adsb_reference(f.with_columns(pl.Series("latitude", lat), pl.Series("longitude", lon)), ORIGIN)
    reasons = removed["reason"].to_list()
    assert any("position jump" in r for r in reasons) and any("stale" in r for r in reasons)
    assert points.height == 118


def test_interpolation_only_across_short_gaps_and_not_evaluated_otherwise():
    f = _adsb("aaaaaa", 200, 48.9).filter((pl.col("timestamp") < T0 + timedelta(seconds=50))
                                          | (pl.col("timestamp") >= T0 + timedelta(seconds=80)))
    f = f.filter(pl.col("timestamp") != T0 + timedelta(seconds=20))          # a 2 s gap
    points, _ = adsb_reference(f, ORIGIN)
    req = pl.DataFrame({"truth_id": pl.Series([0, 0, 0, 0, 7], dtype=pl.Int64),
                        "time": [T0 + timedelta(seconds=s) for s in (20.0, 10.25, 65.0, 500.0, 10.0)]})
    out = interpolate_reference(points, req, max_gap_s=10.0)
    assert out["status"].to_list() == [
        "evaluated", "evaluated", "not evaluated: reference gap longer than the interpolation limit",
        "not evaluated: outside the aircraft's reference", "not evaluated: no reference for the aircraft"]
    p = points.filter(pl.col("time") == T0 + timedelta(seconds=10))
    q = points.filter(pl.col("time") == T0 + timedelta(seconds=11))
    assert out["true_x_m"][1] == pytest.approx(0.75 * p["x_m"][0] + 0.25 * q["x_m"][0])
    assert out["true_vx_mps"][1] == pytest.approx(200 * 1852 / 3600, rel=1e-3)      # reported velocity
    assert out["true_x_m"][2] is None and out["ref_sigma_h_m"][0] == pytest.approx(30 / K95_2D)


def test_rts_smoother_matches_filterpy_on_a_linear_case():
    rng = np.random.default_rng(1)
    a, k, dt = 3, 40, 4.0
    cfg = SmootherConfig(q=(2.0, 0.5, 0.1))
    t = np.broadcast_to(np.arange(k) * dt, (a, k)).copy()
    z = rng.normal(0, 50, (a, k, 3)) + np.arange(k)[None, :, None] * dt * np.array([120.0, -80.0, 5.0])
    r = np.broadcast_to(np.diag([50.0 ** 2, 40.0 ** 2, 20.0 ** 2]), (a, k, 3, 3)).copy()
    valid = np.ones((a, k), bool)
    valid[2, 30:] = False                               # a shorter aircraft, padded
    f, q = _fq(np.array([dt]), np.asarray(cfg.q))
    x_prior, p_prior = np.zeros(6), np.diag([1e6] * 3 + [1e4] * 3)
    x0 = np.broadcast_to(f[0] @ x_prior, (a, 6)).copy()
    p0 = np.broadcast_to(f[0] @ p_prior @ f[0].T + q[0], (a, 6, 6)).copy()
    xf, pf, xs, ps = rts_smooth(t, z, r, valid, cfg, x0=x0, p0=p0)
    for i in range(a):
        n = int(valid[i].sum())
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.F, kf.Q, kf.R, kf.x, kf.P = f[0], q[0], r[0, 0], x_prior.copy(), p_prior.copy()
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        mu, cov, _, _ = kf.batch_filter(list(z[i, :n]))
        ms, cs, _, _ = kf.rts_smoother(mu, cov)
        np.testing.assert_allclose(xf[i, :n], mu, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(xs[i, :n], ms, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(ps[i, :n], cs, rtol=1e-7, atol=1e-6)
        np.testing.assert_allclose(xs[i, n:], np.broadcast_to(xs[i, n - 1], (k - n, 6)))


@pytest.fixture(scope="module")
def simulated():
    cfg = load_scenario("terminal-area").replace(runs=1, duration_s=600.0, seed=3)
    return simulate(dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, aircraft=20)))


def test_smoothed_reference_beats_the_online_filter_against_truth(simulated):
    ds = simulated
    meas = plot_measurements(ds.reports.filter(pl.col("truth_id").is_not_null()), ds.radars, ds.origin)
    ref = reconstruct_reference(meas)
    truth = interpolate_reference(ds.truth, ref.select("truth_id", "time"), max_gap_s=2.0)
    j = pl.concat([ref, truth.drop("truth_id", "time")], how="horizontal").filter(pl.col("status") == "evaluated")
    j = j.filter(pl.int_range(pl.len()).over("truth_id") >= 5)            # past the filter's initiation
    def rms(p: str) -> tuple[float, float]:
        eh = np.hypot(j[f"{p}x_m"] - j["true_x_m"], j[f"{p}y_m"] - j["true_y_m"]).to_numpy()
        return float(np.sqrt(np.mean(eh ** 2))), float(np.sqrt(np.mean((j[f"{p}alt_m"] - j["true_alt_m"]).to_numpy() ** 2)))
    (sh, sv), (fh, fv) = rms(""), rms("filt_")
    # height: a level aircraft's Mode C quantisation error is constant (a bias no smoother removes)
    assert sh < 0.7 * fh and sv < fv, (sh, fh, sv, fv)
    # the stated covariance is of the right size (radar biases make the error a little larger)
    sig = float(np.sqrt(np.mean(j["sigma_h_m"].to_numpy() ** 2)) * np.sqrt(2))
    assert 0.5 * sh < sig < 1.5 * sh, (sig, sh)
