"""Alert scoring against truth: hand-built truth/alert sequences with known hits, misses,
false alerts, warning times and flicker."""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from safety.alerts import (AlertConfig, alert_episodes, loss_of_separation, score_alerts, true_conflicts,
                           truth_at)
from safety.conflicts import ConflictConfig, predict_conflicts
from tertiary.schema import TABLES, validate

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
GRID = [T0 + timedelta(seconds=s) for s in range(0, 301, 5)]       # picture epochs, every 5 s
LOS_CFG = AlertConfig(truth_rule="los")


def _t(s: float) -> datetime:
    return T0 + timedelta(seconds=s)


def _aircraft(tid: int, x0: float, vx: float, y: float, z: float = 3000.0) -> pl.DataFrame:
    t = np.arange(0.0, 301.0)
    return pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": x0 + vx * t, "y_m": float(y),
                         "z_m": float(z), "vx_mps": float(vx), "vy_mps": 0.0, "vz_mps": 0.0}
                        ).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


@pytest.fixture(scope="module")
def truth() -> pl.DataFrame:
    """1 and 2 meet head-on with a 1 km miss at t = 200 s (closing 300 m/s); 3 and 4 pass 30 km apart."""
    return pl.concat([_aircraft(1, -30000.0, 150.0, 0.0), _aircraft(2, 30000.0, -150.0, 1000.0),
                      _aircraft(3, -30000.0, 150.0, 50000.0), _aircraft(4, 30000.0, -150.0, 80000.0)])


def _id_map(extra: dict[int, int | None] | None = None, runs=(0,)) -> pl.DataFrame:
    """Picture ids 11..14 ↔ truth 1..4 at every grid epoch (plus ``extra`` id → truth)."""
    mapping = {11: 1, 12: 2, 13: 3, 14: 4, **(extra or {})}
    rows = [{"run": r, "epoch": e, "id": i, "truth_id": t} for r in runs for e in GRID for i, t in mapping.items()]
    return pl.DataFrame(rows, schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "id": pl.UInt64,
                                      "truth_id": pl.Int64})


def _alerts(pairs: dict[tuple[int, int], list[float]], method: str = "m", run: int = 0) -> pl.DataFrame:
    rows = [{"run": run, "epoch": _t(s), "method": method, "id_a": a, "id_b": b, "alert": True}
            for (a, b), times in pairs.items() for s in times]
    return pl.DataFrame(rows, schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "method": pl.String,
                                      "id_a": pl.UInt64, "id_b": pl.UInt64, "alert": pl.Boolean})


def _metrics(m: pl.DataFrame, method: str = "m") -> dict[str, float]:
    return dict(m.filter(pl.col("method") == method).select("metric", "value").iter_rows())


def _span(df: pl.DataFrame) -> tuple[float, float]:
    s = df["epoch"].dt.epoch("us") / 1e6 - T0.timestamp()
    return float(s.min()), float(s.max())


# --------------------------------------------------------------------------- truth side


def test_truth_at_interpolates(truth):
    st = truth_at(truth, pl.DataFrame({"epoch": [_t(10.5)]}))
    one = st.filter(pl.col("truth_id") == 1)
    assert one["x_m"][0] == pytest.approx(-30000 + 150 * 10.5)
    assert truth_at(truth, pl.DataFrame({"epoch": [_t(400.0)]})).height == 0     # beyond the span


def test_loss_of_separation_interval(truth):
    los = loss_of_separation(truth)
    assert los.height == 1
    r = los.row(0, named=True)
    # |Δx| = |60000 − 300 t| < sqrt(5556² − 1000²) = 5465.3 m ⇔ 181.78 < t < 218.22
    assert (r["truth_a"], r["truth_b"]) == (1, 2)
    assert r["t_start"] == _t(182) and r["t_end"] == _t(218)


def test_true_conflicts_prediction_rule(truth):
    tc = true_conflicts(truth, pl.DataFrame({"epoch": GRID}))
    assert set(zip(tc["truth_a"], tc["truth_b"])) == {(1, 2)}
    # zero-error rule: R_min = 1000 ≤ 6056, 0 ≤ T_min = 200 − t ≤ 105 ⇔ 95 ≤ t ≤ 200
    assert _span(tc) == (95.0, 200.0) and tc.height == 22


def test_true_conflicts_los_rule(truth):
    tc = true_conflicts(truth, pl.DataFrame({"epoch": GRID}), LOS_CFG)
    # a LOS sample in [t, t + 105] ⇔ 77 ≤ t ≤ 218 → grid 80 … 215
    assert _span(tc) == (80.0, 215.0) and tc.height == 28


# --------------------------------------------------------------------------- scoring


@pytest.mark.parametrize("cfg", [AlertConfig(), LOS_CFG], ids=["prediction", "los"])
def test_hit_with_warning_time_flicker_and_false_alert(truth, cfg):
    on = [s for s in range(120, 201, 5) if s not in (130, 150)]           # drops out twice
    conflicts = _alerts({(11, 12): on, (13, 14): [50, 55, 60]})
    m = score_alerts(conflicts, _id_map(), truth, cfg)
    got = _metrics(m)
    assert got["hits"] == 1 and got["misses"] == 0 and got["episodes"] == 1
    assert got["mean_warning_s"] == pytest.approx(182 - 120)           # LOS at 182 s, first alert 120 s
    assert got["flicker"] == 2 and got["flicker_per_hit"] == 2
    assert got["false_alerts"] == 1                                     # the 3–4 pair, one run of alerts
    validate(m, "metrics")
    assert m.schema == pl.Schema(TABLES["metrics"].required)
    assert set(m["stage"]) == {"safety"} and set(m["segment"]) == {"all"}


def test_miss_when_no_alert(truth):
    got = _metrics(score_alerts(_alerts({(13, 14): [50.0]}), _id_map(), truth))
    assert got["hits"] == 0 and got["misses"] == 1 and got["false_alerts"] == 1
    assert math.isnan(got["mean_warning_s"]) and math.isnan(got["flicker_per_hit"])


def test_alert_after_loss_of_separation_is_a_miss_not_a_false_alert(truth):
    got = _metrics(score_alerts(_alerts({(11, 12): [185, 190, 195, 200]}), _id_map(), truth))
    assert got["hits"] == 0 and got["misses"] == 1 and got["false_alerts"] == 0


def test_early_alert_counts_and_late_run_is_false(truth):
    # alerts at 0–20 s: before the true episode (95 s) but within early_s = T = 105 s → hit
    conflicts = _alerts({(11, 12): [0, 5, 10, 15, 20, 250, 255]})
    ep = alert_episodes(conflicts, _id_map(), truth)
    true_ep = ep.filter(pl.col("kind") == "truth").row(0, named=True)
    assert true_ep["hit"] and true_ep["first_alert"] == _t(0) and true_ep["warning_s"] == pytest.approx(182)
    assert true_ep["t_start"] == _t(95) and true_ep["t_end"] == _t(200) and true_ep["t_los"] == _t(182)
    assert true_ep["flicker"] == 0                       # off at 25 s, never back on before t_end
    fa = ep.filter(pl.col("kind") == "false_alert")
    assert fa.height == 1 and fa["t_start"][0] == _t(250) and fa["t_end"][0] == _t(255)
    # with no early allowance the 0–20 s run is a false alert and the episode a miss
    got = _metrics(score_alerts(conflicts, _id_map(), truth, AlertConfig(early_s=0.0)))
    assert got["hits"] == 0 and got["misses"] == 1 and got["false_alerts"] == 2


def test_alerts_without_two_distinct_truths_are_false(truth):
    idm = _id_map({15: None, 16: 1})                     # 15: a false track; 16: a duplicate of 1
    conflicts = _alerts({(11, 15): [100, 105], (11, 16): [150], (11, 12): [150]})
    ep = alert_episodes(conflicts, idm, truth)
    fa = ep.filter(pl.col("kind") == "false_alert").sort("b")
    assert fa.select("a", "b").rows() == [(11, 15), (11, 16)]
    got = _metrics(score_alerts(conflicts, idm, truth))
    assert got["false_alerts"] == 2 and got["hits"] == 1


def test_methods_and_runs(truth):
    # two Monte-Carlo runs sharing one truth; method "good" alerts in both, "bad" only in run 0
    conflicts = pl.concat([_alerts({(11, 12): [150, 155]}, method="good", run=0),
                           _alerts({(11, 12): [160]}, method="good", run=1),
                           _alerts({(11, 12): [100]}, method="bad", run=0)])
    idm = _id_map(runs=(0, 1))
    idm = pl.concat([idm.with_columns(pl.lit(m).alias("method")) for m in ("good", "bad")])
    m = score_alerts(conflicts, idm, truth)
    good, bad = _metrics(m, "good"), _metrics(m, "bad")
    assert (good["hits"], good["misses"]) == (2, 0)
    assert good["mean_warning_s"] == pytest.approx(((182 - 150) + (182 - 160)) / 2)
    assert (bad["hits"], bad["misses"]) == (1, 1)
    assert set(m["n_runs"]) == {2}


def test_truth_with_run_column(truth):
    runs = pl.concat([truth.with_columns(pl.lit(r, pl.UInt32).alias("run")) for r in (0, 1)])
    # in run 1 aircraft 2 flies 20 km further north: no conflict there
    runs = runs.with_columns(pl.when((pl.col("run") == 1) & (pl.col("truth_id") == 2))
                             .then(pl.col("y_m") + 20000).otherwise(pl.col("y_m")).alias("y_m"))
    conflicts = pl.concat([_alerts({(11, 12): [150]}, run=0), _alerts({(11, 12): [150]}, run=1)])
    got = _metrics(score_alerts(conflicts, _id_map(runs=(0, 1)), runs))
    assert (got["hits"], got["misses"], got["false_alerts"]) == (1, 0, 1)
    assert loss_of_separation(runs).select("run").to_series().to_list() == [0]


@pytest.mark.parametrize("cfg", [AlertConfig(), LOS_CFG], ids=["prediction", "los"])
def test_end_to_end_with_predicted_conflicts(truth, cfg):
    """A perfect picture (truth states at the grid, fixed 300 m estimation margin): one hit,
    first alert at T_min = 105 s before the closest approach (t = 95 s), no false alert."""
    st = truth_at(truth, pl.DataFrame({"epoch": GRID}))
    picture = st.with_columns(pl.lit(0, pl.UInt32).alias("run"), (pl.col("truth_id") + 10).alias("track_id"))
    conflicts = predict_conflicts(picture, ConflictConfig(threshold_mode="fixed"))
    idm = picture.select("run", "epoch", pl.col("track_id").alias("id"), "truth_id")
    ep = alert_episodes(conflicts, idm, truth, cfg)
    hit = ep.filter(pl.col("kind") == "truth").row(0, named=True)
    assert hit["hit"] and hit["first_alert"] == _t(95) and hit["warning_s"] == pytest.approx(87.0)
    got = _metrics(score_alerts(conflicts, idm, truth, cfg), "none")
    assert (got["hits"], got["misses"], got["false_alerts"], got["flicker"]) == (1, 0, 0, 0)


def test_config_validation():
    with pytest.raises(ValueError):
        AlertConfig(truth_rule="maybe")
    with pytest.raises(ValueError):
        AlertConfig(early_s=-1.0)
    cfg = AlertConfig(conflict=ConflictConfig(mode="seed"))
    assert cfg.truth_conflict.mode == "corrected" and cfg.truth_conflict.fixed_est_h_m == 0.0
    assert AlertConfig(conflict=ConflictConfig(mode="seed"), truth_mode=None).truth_conflict.mode == "seed"
