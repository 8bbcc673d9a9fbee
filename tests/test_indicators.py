"""§1.7 / §5.1 / §2.2–2.3 indicators against hand computations on a tiny picture.

Truth (run 0, samples every 10 s, z = 3000 m, 100 m/s north):
  aircraft 1 at x = 10 km, t = 0…100;  aircraft 2 at x = 50 km, t = 0…40;
  aircraft 3 at x = 30 km, t = 60…100; aircraft 4 at x = −120 km, t = 0…100 (never tracked).
Picture (epochs every 10 s; each true track offset by (+30, +40) m and (+3, +4) m/s):
  track 10 on aircraft 1, t = 20…100;  track 11 on aircraft 2, t = 0…20 (ends while it flies on);
  track 12 false, far from everything, t = 50…70;  track 13 on aircraft 3, t = 80…100.
"""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from tertiary.evaluation.indicators import (IndicatorConfig, gain_history, gain_metrics, indicators, picture_indicators)

T0 = 1_633_608_000 * 1_000_000
AIRCRAFT = {1: (10e3, 0, 100), 2: (50e3, 0, 40), 3: (30e3, 60, 100), 4: (-120e3, 0, 100)}
TRACKS = {10: (1, 20, 100), 11: (2, 0, 20), 12: (None, 50, 70), 13: (3, 80, 100)}


def _time(ts: list[float]) -> pl.Series:
    return pl.Series("time", [T0 + int(t * 1e6) for t in ts]).cast(pl.Datetime("us", "UTC"))


def _truth() -> pl.DataFrame:
    rows = [{"truth_id": k, "t": float(t), "x_m": x, "y_m": 100.0 * t, "z_m": 3000.0, "vx_mps": 0.0,
             "vy_mps": 100.0, "vz_mps": 0.0}
            for k, (x, a, b) in AIRCRAFT.items() for t in range(a, b + 1, 10)]
    df = pl.DataFrame(rows)
    return df.with_columns(_time(df["t"].to_list())).drop("t")


def _tracks(method="arith", filt="singer") -> pl.DataFrame:
    rows = []
    for tid, (ac, a, b) in TRACKS.items():
        for t in range(a, b + 1, 10):
            x = AIRCRAFT[ac][0] + 30.0 if ac else 200e3
            rows.append({"run": 0, "t": float(t), "track_id": tid, "filter": filt, "method": method,
                         "x_m": x, "y_m": 100.0 * t + 40.0, "z_m": 3000.0, "vx_mps": 3.0, "vy_mps": 104.0,
                         "vz_mps": 0.0, "cov_diag": [400.0, 500.0, 900.0, 4.0, 5.0, 1.0],
                         "innovation": None, "nis": None, "model_probs": None})
    df = pl.DataFrame(rows)
    return df.with_columns(_time(df["t"].to_list()).alias("epoch"), pl.col("run").cast(pl.UInt32),
                           pl.col("track_id").cast(pl.UInt64),
                           pl.col("cov_diag").cast(pl.Array(pl.Float64, 6))).drop("t")


def _value(df: pl.DataFrame, metric: str, segment: str = "all") -> float:
    v = df.filter((pl.col("metric") == metric) & (pl.col("segment") == segment))["value"]
    assert v.len() == 1, (metric, segment, v)
    return v[0]


@pytest.fixture(scope="module")
def result() -> pl.DataFrame:
    return picture_indicators(_tracks(), _truth(), "p", IndicatorConfig(time_bin_s=50.0))


def test_detection_against_range_and_time_to_detect(result):
    # alive samples 11 + 5 + 5 + 11 = 32; matched 9 (a/c 1) + 3 (a/c 2) + 3 (a/c 3) = 15
    assert _value(result, "p_detect_track") == pytest.approx(15 / 32)
    assert _value(result, "p_detect_track", "range_m=[0,20000)") == pytest.approx(9 / 11)
    assert _value(result, "p_detect_track", "range_m=[20000,40000)") == pytest.approx(3 / 5)
    assert _value(result, "p_detect_track", "range_m=[40000,60000)") == pytest.approx(3 / 5)
    assert _value(result, "p_detect_track", "range_m=[100000,150000)") == 0.0
    assert _value(result, "mean_time_to_detect_s") == pytest.approx((20 + 0 + 20) / 3)
    assert _value(result, "aircraft_never_detected") == 1


def test_false_tracks_durations_and_loss(result):
    hours = 100 / 3600
    assert _value(result, "false_tracks") == 1 and _value(result, "true_tracks") == 3
    assert _value(result, "false_tracks_per_hour") == pytest.approx(1 / hours)
    assert _value(result, "mean_false_track_lifetime_s") == pytest.approx(20.0)
    assert _value(result, "mean_track_duration_s") == pytest.approx((80 + 20 + 20) / 3)
    # only track 11 ends (t = 20) while its aircraft flies on (to t = 40)
    assert _value(result, "tracks_lost") == 1
    assert _value(result, "p_track_loss") == pytest.approx(1 / 3)


def test_traffic_intensity_and_zone_load(result):
    hours = 100 / 3600
    assert _value(result, "traffic_intensity_per_h", "truth") == pytest.approx(4 / hours)
    assert _value(result, "traffic_intensity_per_h", "picture") == pytest.approx(3 / hours)
    # tracks on aircraft per epoch 0…100: 1 1 2 1 1 1 1 1 2 2 2; aircraft alive: 3 3 3 3 3 2 3 3 3 3 3
    assert _value(result, "zone_load_mean", "picture") == pytest.approx(15 / 11)
    assert _value(result, "zone_load_max", "picture") == 2
    assert _value(result, "zone_load_mean", "truth") == pytest.approx(32 / 11)
    assert _value(result, "zone_load_max", "truth") == 3
    assert _value(result, "zone_load", "picture t_s=[0,50)") == pytest.approx(6 / 5)
    assert _value(result, "zone_load", "picture t_s=[50,100)") == pytest.approx(7 / 5)
    assert _value(result, "zone_load", "picture t_s=[100,150)") == pytest.approx(2.0)
    assert _value(result, "zone_load", "truth t_s=[50,100)") == pytest.approx(14 / 5)


def test_real_against_potential_accuracy(result):
    # error (30, 40) m and (3, 4) m/s on every matched row; P = (400 + 500) m², (4 + 5) (m/s)²
    assert _value(result, "rmse_pos_h_m") == pytest.approx(50.0)
    assert _value(result, "potential_pos_h_m") == pytest.approx(30.0)
    assert _value(result, "real_to_potential_pos_h") == pytest.approx(5 / 3)
    assert _value(result, "rmse_vel_h_mps") == pytest.approx(5.0)
    assert _value(result, "real_to_potential_vel_h") == pytest.approx(5 / 3)
    assert _value(result, "real_to_potential_pos_h", "t_s=[0,50)") == pytest.approx(5 / 3)


def test_rows_are_metrics_rows_one_per_picture():
    both = pl.concat([_tracks("arith", "singer"), _tracks("invcov", "imm_sym")])
    out = indicators(both, _truth(), IndicatorConfig(time_bin_s=50.0))
    assert out.schema["value"] == pl.Float64 and set(out["stage"].unique()) == {"indicators"}
    assert set(out["method"].unique()) == {"arith+singer", "invcov+imm_sym"}
    assert out.filter(pl.col("method") == "arith+singer").height == out.filter(pl.col("method") == "invcov+imm_sym").height
    assert out.select("stage", "method", "metric", "segment").is_unique().all()


def test_gain_history_scalar_random_walk():
    q, r, p0 = 1.0, 4.0, 10.0
    k = gain_history(1.0, q, 1.0, r, p0, 60)[:, 0, 0]
    assert k[0] == pytest.approx(11.0 / 15.0)              # P⁻ = 11, K = 11 / (11 + 4)
    p1 = (1 - 11 / 15) * 11
    assert k[1] == pytest.approx((p1 + q) / (p1 + q + r))
    pm = (q + np.sqrt(q * q + 4 * q * r)) / 2              # steady-state Riccati root
    assert k[-1] == pytest.approx(pm / (pm + r), rel=1e-9)
    rows = gain_metrics(gain_history(np.array([[1, 1], [0, 1]]), np.diag([0.0, 0.1]), [[1, 0]], [[4.0]],
                                     np.eye(2) * 100, 30), "cv", every=10)
    assert set(rows["metric"]) == {"gain_K11", "gain_K21"} and "steady" in rows["segment"].to_list()
