"""Picture metrics against hand computations."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.core.errors import OptionError
from tertiary.evaluation import sketch
from tertiary.evaluation.picture_metrics import MetricsConfig, picture_metrics
from tertiary.contract import validate

T0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)
STATE = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]


def _times(t: np.ndarray) -> pl.Series:
    us = np.round(np.asarray(t) * 1e6).astype(np.int64) + int(T0.timestamp() * 1e6)
    return pl.Series("epoch", us).cast(pl.Datetime("us", "UTC"))


def _straight(truth_id: int, t: np.ndarray, speed=(100.0, 0.0), start=(0.0, 0.0), z=3000.0) -> dict:
    return {"x": start[0] + speed[0] * t, "y": start[1] + speed[1] * t, "z": np.full(t.size, z),
            "vx": np.full(t.size, speed[0]), "vy": np.full(t.size, speed[1]), "vz": np.zeros(t.size)}


def _rows(method: str, track_id, truth_id, t: np.ndarray, ref: dict, dx=0.0, dy=0.0, dz=0.0,
          delay_s=0.0) -> pl.DataFrame:
    """Track rows = reference state at t − delay, shifted by (dx, dy, dz)."""
    n = t.size
    out = pl.DataFrame({
        "method": [method] * n, "run": pl.Series([0] * n, dtype=pl.UInt32),
        "epoch": _times(t),
        "track_id": pl.Series(np.broadcast_to(track_id, n).astype(np.uint64)),
        "truth_id": pl.Series(np.broadcast_to(truth_id, n).astype(np.int64)),
        "x_m": ref["x"] - ref["vx"] * delay_s + dx, "y_m": ref["y"] - ref["vy"] * delay_s + dy,
        "z_m": ref["z"] + dz, "vx_mps": ref["vx"], "vy_mps": ref["vy"], "vz_mps": ref["vz"],
        "true_x_m": ref["x"], "true_y_m": ref["y"], "true_z_m": ref["z"],
        "true_vx_mps": ref["vx"], "true_vy_mps": ref["vy"], "true_vz_mps": ref["vz"],
    })
    return out


def _value(metrics: pl.DataFrame, metric: str, method: str = "p", segment: str = "all") -> float:
    row = metrics.filter((pl.col("metric") == metric) & (pl.col("method") == method) & (pl.col("segment") == segment))
    assert row.height == 1, (metric, segment, row)
    return row["value"][0]


def test_known_along_track_delay_gives_the_latency():
    t = np.arange(600.0)
    ref = _straight(1, t, speed=(60.0, 80.0))            # 100 m/s towards 36.87°
    met = picture_metrics(_rows("p", 7, 1, t, ref, delay_s=2.5), breakdown=())
    assert _value(met, "latency_s") == pytest.approx(2.5, abs=1e-9)
    assert _value(met, "along_track_bias_m") == pytest.approx(-250.0, abs=1e-9)
    assert _value(met, "along_track_rms_m") == pytest.approx(250.0, abs=1e-9)
    assert _value(met, "across_track_rms_m") == pytest.approx(0.0, abs=1e-9)
    assert _value(met, "rmse_horizontal_m") == pytest.approx(250.0, abs=1e-9)


def test_constant_across_offset_gives_across_rms_and_zero_along():
    t = np.arange(300.0)
    ref = _straight(1, t, speed=(-150.0, 0.0))          # westbound: left of travel is south
    met = picture_metrics(_rows("p", 7, 1, t, ref, dy=-100.0, dz=30.0), breakdown=())
    assert _value(met, "across_track_rms_m") == pytest.approx(100.0, abs=1e-9)
    assert _value(met, "across_track_bias_m") == pytest.approx(100.0, abs=1e-9)   # positive = left
    assert _value(met, "along_track_rms_m") == pytest.approx(0.0, abs=1e-9)
    assert _value(met, "latency_s") == pytest.approx(0.0, abs=1e-12)
    assert _value(met, "rmse_height_m") == pytest.approx(30.0)
    # every error is 100 m: the sketch's percentile is within its relative accuracy of it
    assert _value(met, "p95_horizontal_m") == pytest.approx(100.0, rel=sketch.ALPHA)
    assert _value(met, "max_horizontal_m") == pytest.approx(100.0)


def test_track_swapping_two_aircraft_counts_one_id_change_each():
    t = np.arange(600.0)
    a, b = _straight(1, t), _straight(2, t, start=(0.0, 2000.0))
    first, second = t < 300, t >= 300
    rows = [_rows("p", 1, 1, t[first], {k: v[first] for k, v in a.items()}),
            _rows("p", 2, 2, t[first], {k: v[first] for k, v in b.items()}),
            _rows("p", 2, 1, t[second], {k: v[second] for k, v in a.items()}),   # swap at t = 300
            _rows("p", 1, 2, t[second], {k: v[second] for k, v in b.items()})]
    met = picture_metrics(pl.concat(rows), breakdown=())
    hours = 2 * 599 / 3600.0
    assert _value(met, "aircraft_hours") == pytest.approx(hours)
    assert _value(met, "id_changes_per_hour") == pytest.approx(2 / hours)
    assert _value(met, "track_breaks") == 0
    assert _value(met, "prob_update") == 1.0
    assert _value(met, "false_tracks_per_hour") == 0.0


def test_a_second_track_of_an_aircraft_is_a_duplicate_not_a_false_track():
    """Every track is real (matched at some epoch), a duplicate (never matched, but inside an
    aircraft's gate: ``gated_truth_id``, the second track the one-to-one matching leaves
    unmatched) or false (in no aircraft's gate). Fails if a duplicate counts as false, or as
    nothing."""
    t = np.arange(120.0)
    ref = _straight(1, t)
    real = _rows("p", 1, 1, t, ref).with_columns(pl.lit(1, pl.Int64).alias("gated_truth_id"))
    none = [pl.lit(None, dtype=pl.Int64).alias("truth_id"), *[pl.lit(None, dtype=pl.Float64).alias(f"true_{c}")
                                                              for c in STATE]]
    dup = _rows("p", 2, 1, t[:10], {k: v[:10] for k, v in ref.items()}, dx=300.0).with_columns(
        *none, pl.lit(1, pl.Int64).alias("gated_truth_id"))
    ghost = _rows("p", 99, 1, t, ref, dx=5e4).with_columns(*none, pl.lit(None, pl.Int64).alias("gated_truth_id"))
    met = picture_metrics(pl.concat([real, dup, ghost]), breakdown=())
    hours = 119 / 3600.0
    assert _value(met, "n_tracks") == 3
    assert _value(met, "false_tracks") == 1 and _value(met, "duplicate_tracks") == 1
    assert _value(met, "false_tracks_per_hour") == pytest.approx(1 / hours)
    assert _value(met, "duplicate_tracks_per_hour") == pytest.approx(1 / hours)


def test_breaks_reacquisition_update_probability_and_false_tracks():
    t = np.arange(600.0)
    keep = (t < 200) | (t >= 261)                        # updates at 199 then 261: a 62 s gap
    ref = _straight(1, t)
    real = _rows("p", 1, 1, t[keep], {k: v[keep] for k, v in ref.items()})
    ghost = _rows("p", 99, 1, t, ref, dx=5e4).with_columns(pl.lit(None, dtype=pl.Int64).alias("truth_id"),
                                                             *[pl.lit(None, dtype=pl.Float64).alias(f"true_{c}")
                                                               for c in STATE])
    met = picture_metrics(pl.concat([real, ghost]), breakdown=(), cfg=MetricsConfig(expected_interval_s=5.0))
    assert _value(met, "track_breaks") == 1
    assert _value(met, "mean_reacquire_s") == pytest.approx(62.0)
    # intervals [0,5) … [595,600): 120; [200,260) fully empty = 12 intervals, [260,265) holds 261
    assert _value(met, "n_update_intervals") == 120
    assert _value(met, "prob_update") == pytest.approx(108 / 120)
    assert _value(met, "false_tracks_per_hour") == pytest.approx(1 / (599 / 3600.0))
    assert _value(met, "n_tracks") == 2


def test_split_and_merged_tracks_and_mode_s():
    t = np.arange(100.0)
    a, c = _straight(1, t), _straight(3, t, start=(0.0, 300.0))     # c flies 300 m beside a
    main = _rows("p", 1, 1, t, a)
    dup = _rows("p", 2, 1, t[:20], {k: v[:20] for k, v in a.items()}, dx=50.0)   # a second track on a
    matched = pl.concat([main, dup]).with_columns(
        pl.when(pl.col("track_id") == 1).then(pl.lit("ABC123")).otherwise(pl.lit("ffffff")).alias("mode_s"),
        pl.lit("abc123").alias("icao24"))
    expected = pl.concat([
        main.select("run", "truth_id", "epoch", *[f"true_{c}" for c in STATE]),
        _rows("p", 0, 3, t, c).select("run", "truth_id", "epoch", *[f"true_{c}" for c in STATE])])
    met = picture_metrics(matched, expected=expected, breakdown=())
    assert _value(met, "split_tracks") == 1
    assert _value(met, "merged_tracks") == 1                    # track 1 sits on the bare aircraft 3
    assert _value(met, "mode_s_correct_frac") == pytest.approx(100 / 120)
    # aircraft 3 is expected but never tracked: half the aircraft-time without update
    assert _value(met, "prob_update") == pytest.approx(0.5)
    far = picture_metrics(matched, expected=expected, breakdown=(), cfg=MetricsConfig(merge_gate_m=200.0))
    assert _value(far, "merged_tracks") == 0


def test_breakdown_segments_and_metrics_schema():
    t = np.arange(400.0)
    w = np.radians(3.0)                                   # 3 °/s turn of radius 100/w
    r = 100.0 / w
    turn = {"x": r * np.sin(w * t), "y": r * (1 - np.cos(w * t)), "z": np.full(t.size, 5000.0),
            "vx": 100.0 * np.cos(w * t), "vy": 100.0 * np.sin(w * t), "vz": np.zeros(t.size)}
    climb = _straight(2, t, start=(80_000.0, 0.0), z=1000.0)
    climb["z"] = 1000.0 + 10.0 * t
    climb["vz"] = np.full(t.size, 10.0)
    m = pl.concat([_rows("p", 1, 1, t, turn, dx=10.0), _rows("p", 2, 2, t, climb, dx=20.0)])
    met = picture_metrics(m, radar_xy=np.array([[0.0, 0.0], [1e6, 0.0]]))
    validate(met, "metrics", strict=True)
    assert _value(met, "rmse_horizontal_m", segment="phase:turn") == pytest.approx(10.0)
    assert _value(met, "rmse_horizontal_m", segment="phase:climb-descent") == pytest.approx(20.0)
    assert _value(met, "rmse_horizontal_m", segment="range:50-100km") == pytest.approx(20.0)
    assert _value(met, "rmse_horizontal_m", segment="range:0-50km") == pytest.approx(10.0)
    assert _value(met, "n_points", segment="alt:3000-6000m") == 400 + (t >= 200).sum()
    assert set(met["stage"]) == {"evaluation"}
    with pytest.raises(OptionError, match="breakdown"):
        picture_metrics(m, breakdown=("weather",))


def test_flight_level_callsign_and_mode_3a_correctness():
    """Heights 50 m off for 30 rows and 70 m off for 10 (±200 ft = 60.96 m tolerance: 30/40
    correct); callsigns compared without blanks and case; Mode 3/A compared as codes."""
    t = np.arange(40.0)
    rows = _rows("p", 1, 1, t, _straight(1, t)).with_columns(
        pl.col("true_z_m").alias("true_alt_m"),
        (pl.col("true_z_m") + pl.Series(np.where(t < 30, 50.0, -70.0))).alias("alt_m"),
        pl.Series("callsign", np.where(t < 10, "afr 12", "AFR13")), pl.lit("AFR12").alias("true_callsign"),
        pl.lit("1000").alias("mode_3a"), pl.Series("true_mode_3a", np.where(t < 20, "1000", "7000")))
    met = picture_metrics(rows, breakdown=())
    assert _value(met, "flight_level_correct_frac") == pytest.approx(30 / 40)
    assert _value(met, "n_flight_level") == 40
    assert _value(met, "callsign_correct_frac") == pytest.approx(10 / 40)
    assert _value(met, "mode_3a_correct_frac") == pytest.approx(20 / 40)
    # without the items on both sides there is no such metric (never a silent 0 or 1)
    bare = picture_metrics(rows.drop("true_callsign", "true_mode_3a", "alt_m"), breakdown=())
    assert not bare["metric"].is_in(["callsign_correct_frac", "mode_3a_correct_frac",
                                     "flight_level_correct_frac"]).any()


def test_segments_label_every_expected_epoch_when_the_picture_carries_more_reference_columns():
    """A picture matched with a reference identity (``true_callsign``) that the expected rows do
    not carry is still labelled from the expected rows: the epochs without a track count in their
    segment (exposure, missed updates), not only in ``all``."""
    t = np.arange(0.0, 600.0, 5.0)
    ref = _straight(1, t)
    keep = (t < 200) | (t >= 300)
    m = _rows("p", 1, 1, t[keep], {k: v[keep] for k, v in ref.items()}).with_columns(
        pl.lit("ABC123").alias("true_callsign"))
    expected = pl.DataFrame({"run": pl.Series([0] * t.size, dtype=pl.UInt32), "truth_id": pl.Series([1] * t.size,
                                                                                                  dtype=pl.Int64),
                             "epoch": _times(t), **{f"true_{c}_m" if c in "xyz" else f"true_{c}_mps": ref[c]
                                                     for c in ("x", "y", "z", "vx", "vy", "vz")}})
    met = picture_metrics(m, expected=expected, breakdown=("alt", "phase"), cfg=MetricsConfig(expected_interval_s=5.0))
    for segment in ("all", "alt:3000-6000m", "phase:level"):
        assert _value(met, "prob_update", segment=segment) == pytest.approx(100 / 120), segment
        # 120 expected epochs 5 s apart: the last counts until no next one
        assert _value(met, "aircraft_hours", segment=segment) == pytest.approx(595 / 3600), segment
