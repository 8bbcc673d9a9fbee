"""Bias-step detection radar to radar: innovations against the other radars' trajectory."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest
from test_registration import ORIGIN, _hand_case

from tertiary.sensors import registration as reg
from tertiary.simulate import load_scenario, simulate

US = 1_000_000


def test_bracketed_by_hand():
    # other radars' plots: target 0 at 0, 10, 30 s; target 1 at 6 s
    # this radar's plots: target 0 at 5 (between 0 and 10), 20 (10 s gaps), 31 (nothing after);
    # target 1 at 4 (nothing before), 8 (nothing after: 10 s belongs to target 0)
    tgt = np.array([0, 0, 0, 1, 0, 0, 0, 1, 1])
    t = np.array([0.0, 10.0, 30.0, 6.0, 5.0, 20.0, 31.0, 4.0, 8.0])
    other = np.array([True] * 4 + [False] * 5)
    got = reg._bracketed(tgt, t, other, gap_s=6.0)[~other]
    assert got.tolist() == [True, False, False, False, False]
    assert reg._bracketed(tgt, t, other, gap_s=10.0)[~other].tolist() == [True, True, False, False, False]
    assert not reg._bracketed(tgt, t, np.zeros(9, bool), gap_s=10.0).any()


def test_mean_shift_against_a_loop():
    """The cumulative-sum test against a plain loop over window pairs."""
    rng = np.random.default_rng(7)
    e = rng.normal(0.0, 1.0, 200) + np.where(np.arange(200) >= 120, 4.0, 0.0) + 25.0   # constant bias: ignored
    t = np.arange(200) * 2.0
    w = 15
    d = np.diff(e)
    sigma = 1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)
    z = [(e[k - w + 1:k + 1].mean() - e[k - 2 * w + 1:k - w + 1].mean()) / (sigma * np.sqrt(2 / w))
         for k in range(2 * w - 1, 200)]
    first = next(i for i, v in enumerate(z) if abs(v) > 6.0)
    peak = first + int(np.argmax(np.abs(z[first:first + w + 1])))
    hit = reg._mean_shift(e, t, window=w, z_alarm=6.0)
    assert hit["alarm_t_s"] == t[first + 2 * w - 1] and hit["z"] == pytest.approx(z[peak])
    assert hit["change_t_s"] == t[peak + w] and abs(hit["change_t_s"] - 240.0) <= 8.0
    assert hit["step"] == pytest.approx(4.0, abs=1.0)
    assert reg._mean_shift(e[:110], t[:110], window=w, z_alarm=6.0) is None


def test_isolate_keeps_the_strongest_of_one_event():
    found = pl.DataFrame({"radar_id": pl.Series([1, 2, 3], dtype=pl.UInt32), "channel": ["range"] * 3,
                          "alarm_t_s": [100.0, 110.0, 500.0], "change_t_s": [95.0, 96.0, 490.0],
                          "step": [60.0, -40.0, 30.0], "z": [9.0, -7.0, 6.5], "span_s": [30.0, 30.0, 30.0]})
    kept = reg._isolate(found)
    assert kept["radar_id"].to_list() == [1, 3]


def test_noise_free_innovations_vanish_and_see_a_step_whole():
    """Hand case (three radars, six aircraft, no noise): without a step every innovation is ~0;
    with a 50 m range step on radar 1 from t = 300 s, radar 1's innovations move by ~50 m while
    its fit residuals move by much less (the joint fit absorbs part of the step)."""
    rep, _truth, radars = _hand_case()
    cfg = reg.RegistrationConfig(method="multi", knot_s=4.0)
    clean = reg.estimate(rep, radars, ORIGIN, None, cfg).residuals
    innov = clean.filter(pl.col("innov_range_m").is_not_nan())
    assert innov.height > 0.9 * clean.height
    # sub-metre typically; a few metres where the spline misses the 3°/s turn (fit residuals too)
    a, b = innov["innov_range_m"].abs(), innov["innov_azimuth_deg"].abs()
    assert a.median() < 0.5 and a.quantile(0.95) < 5.0 and b.quantile(0.95) < 0.015
    t0 = rep["time"].min()
    stepped = rep.with_columns(pl.when((pl.col("radar_id") == 1) & ((pl.col("time") - t0).dt.total_seconds() >= 300))
                               .then(pl.col("range_m") + 50.0).otherwise(pl.col("range_m")).alias("range_m"))
    res = reg.estimate(stepped, radars, ORIGIN, None, cfg).residuals.filter(pl.col("radar_id") == 1)
    res = res.with_columns(pl.col("innov_range_m").fill_nan(None), (pl.col("t_s") >= 300).alias("after"))
    means = res.group_by("after").agg(pl.col("innov_range_m").mean(), pl.col("res_range_m").mean()).sort("after")
    jump_innov = float(np.diff(means["innov_range_m"].to_numpy())[0])
    jump_res = float(np.diff(means["res_range_m"].to_numpy())[0])
    assert 40.0 < jump_innov < 60.0, jump_innov
    assert abs(jump_res) < 0.7 * jump_innov, (jump_res, jump_innov)


@pytest.fixture(scope="module")
def stepped():
    """Terminal area, 40 aircraft, 20 min, seed 2: a 60 m range step on TMA-N at 600 s, and
    the same traffic without the step."""
    base = load_scenario("terminal-area")
    cfg = dataclasses.replace(base, seed=2, duration_s=1200.0, traffic=dataclasses.replace(base.traffic, aircraft=40),
                              anomalies=dataclasses.replace(base.anomalies, radars=("TMA-N",), bias_step_time_s=600.0,
                                                            bias_step_range_m=60.0))
    with_step = simulate(cfg)
    without = simulate(dataclasses.replace(cfg, anomalies=dataclasses.replace(cfg.anomalies, bias_step_time_s=None)))
    return with_step, without


def test_radar_to_radar_step_detected_with_bounded_delay(stepped):
    ds, _ = stepped
    out = reg.estimate(ds.reports, ds.radars, ds.origin, None)          # no truth: radar to radar
    assert out.table["method"][0] == "multi"
    t_step = 600.0 - (out.t0_us - int(ds.truth["time"].min().timestamp() * US)) / US
    steps = reg.detect_steps(out.residuals, window=60)
    assert steps.height == 1, steps                                    # isolated: TMA-N only
    hit = steps.row(0, named=True)
    assert hit["radar_id"] == 1 and hit["channel"] == "range"
    delay = hit["alarm_t_s"] - t_step
    assert 0.0 <= delay < 30.0, delay                                  # measured 9.9 s
    assert abs(hit["change_t_s"] - t_step) < 15.0
    assert 40.0 < hit["step"] < 80.0
    # the joint fit's own residuals see about half of it (the fit absorbs the rest into the
    # trajectories and the other radars): the motivation for the innovations
    fit_only = reg.detect_steps(out.residuals.drop("innov_range_m", "innov_azimuth_deg"), window=60)
    fit_only = fit_only.filter((pl.col("radar_id") == 1) & (pl.col("channel") == "range"))
    assert fit_only.height == 0 or (abs(fit_only["step"][0]) < 0.6 * hit["step"] and abs(fit_only["z"][0]) < hit["z"])


def test_radar_to_radar_no_alarm_without_step(stepped):
    _, ds = stepped
    out = reg.estimate(ds.reports, ds.radars, ds.origin, None)
    assert reg.detect_steps(out.residuals, window=60, isolate=False).height == 0
    assert reg.detect_steps(out.residuals, window=40, isolate=False).height == 0
