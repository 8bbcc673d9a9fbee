"""Every named report in sql/: columns and values against hand computations on a tiny hand-built
run database (exact values), cross-checks against independent polars computations on a small
simulated run, the read-only rules and the ``tertiary sql`` command."""

from __future__ import annotations

import dataclasses
import json
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from tertiary import pipeline
from tertiary.store import sql_reports
from tertiary.cli.commands import app
from tertiary.core.errors import OptionError
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore

T0 = datetime(2021, 1, 1, tzinfo=timezone.utc)
TIME = pl.Datetime("us", "UTC")
NAN = float("nan")
runner = CliRunner()


def ts(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


# --------------------------------------------------------------------------- the hand-built run

# reports: run, radar_id, local_track_id, truth_id, time_s, est_range_m, est_range_rate_mps, res_range_m, var
REPORTS = [
    (0, 1, 1, 7, 0.5, 1000.0, 0.0, NAN, NAN),
    (0, 1, 1, 7, 1.5, 1010.0, 10.0, 3.0, 4.0),
    (0, 1, 1, 7, 2.5, 1030.0, 20.0, -4.0, 4.0),
    (0, 1, 1, 7, 3.5, 1060.0, 30.0, 5.0, 4.0),
    (0, 2, 5, 7, 0.5, 2000.0, 0.0, NAN, NAN),
    (0, 2, 5, 7, 2.5, 1990.0, -5.0, 8.0, 16.0),
    (0, 2, 5, 7, 4.5, 1970.0, -10.0, -12.0, 9.0),
    (0, 1, 2, 8, 0.5, 5000.0, 0.0, NAN, NAN),
    (0, 1, 2, 8, 1.5, 5005.0, 5.0, 1.0, 1.0),
    (0, 1, 3, None, 2.5, 7000.0, 0.0, NAN, NAN),
    (1, 1, 1, 7, 0.5, 1001.0, 0.0, NAN, NAN),
    (1, 1, 1, 7, 1.5, 1012.0, 11.0, 2.0, 4.0),
]


def truth_pos(truth_id: int, t: float) -> tuple[float, float, float]:
    return (100.0 * t, 0.0, 1000.0) if truth_id == 7 else (0.0, 50.0 * t, 2000.0)


# aligned: run, radar_id, local_track_id, truth_id, epoch_s, error (dx, dy, dz) added to truth
ALIGNED = [
    (0, 1, 1, 7, 1, (30.0, 40.0, 0.0)),
    (0, 1, 1, 7, 2, (-10.0, 0.0, 20.0)),
    (0, 1, 1, 7, 3, (5.0, 5.0, 5.0)),
    (0, 2, 5, 7, 1, (100.0, 0.0, 0.0)),
    (0, 2, 5, 7, 3, (0.0, 0.0, -50.0)),
    (0, 1, 2, 8, 1, (0.0, 12.0, 0.0)),
    (0, 1, 2, 8, 2, (7.0, 0.0, 0.0)),
    (1, 1, 1, 7, 1, (-20.0, 0.0, 0.0)),
    (1, 1, 1, 7, 2, (0.0, 0.0, 9.0)),
    (0, 1, 3, None, 3, (0.0, 0.0, 0.0)),
]

# accuracy_by_epoch rmse_range_m per method at epochs 1, 2, 3 s (rmse_pos_m = twice these); N_k per epoch
# (epoch 3 is a thin, pooled epoch: one sample)
BY_EPOCH_N = [4, 4, 1]
BY_EPOCH = {"apriori": [10.0, 20.0, 40.0], "arithmetic": [20.0, 20.0, 20.0], "aposteriori": [5.0, 25.0, 20.0],
            "aposteriori_seed": [10.0, 10.0, 10.0], "information": [1.0, 1.0, 1.0]}

METRICS = [
    ("fusion", "apriori", "rmse_pos_m", "all", 90.0, 2),
    ("fusion", "apriori", "rmse_horizontal_m", "all", 54.0, 2),
    ("fusion", "apriori", "rmse_height_m", "all", 72.0, 2),
    ("fusion", "apriori", "rmse_pos_m", "straight", 80.0, 2),
    ("fusion", "apriori", "rmse_pos_m", "turn", 150.0, 2),
    ("fusion", "apriori", "rmse_range_m", "all", 40.0, 2),
    ("fusion", "apriori", "rmse_vel_mps", "all", 9.0, 2),
    ("fusion", "aposteriori", "rmse_pos_m", "all", 100.0, 2),
    ("fusion", "information", "rmse_range_m", "all", 31.0, 2),
    ("fusion", "arithmetic", "nees_mean", "all", 6.2, 2),      # no rmse_ row: arithmetic is only a known method
    ("tracker", "information+singer", "rmse_range_m", "all", 33.0, 2),
    ("tracker", "apriori+singer", "rmse_pos_m", "all", 70.0, 2),
    ("tracker", "apriori+singer", "rmse_vel_mps", "all", 12.0, 2),
    ("tracker", "apriori+singer", "tracks", "all", 10.0, 2),
    ("tracker", "apriori+singer", "completeness", "all", 0.9, 2),
    ("tracker", "apriori+singer", "breaks", "all", 1.0, 2),
    ("tracker", "apriori+singer", "swaps", "all", 0.0, 2),
    ("tracker", "apriori+singer", "spurious_tracks", "all", 2.0, 2),
    ("tracker", "apriori+singer", "potential_pos_m", "all", 50.0, 2),
    ("tracker", "apriori+singer", "nees_mean", "all", 3.1, 2),
    ("tracker", "apriori+singer", "nis_mean", "all", 1.2, 2),
    ("tracker", "apriori+singer", "nis_mean", "turn", 9.9, 2),
    ("tracker", "apriori+imm", "rmse_pos_m", "all", 60.0, 2),
    ("tracker", "apriori+imm", "tracks", "all", 11.0, 2),
    ("association", "assignment", "assoc_correct_frac", "all", 0.95, 2),
    ("association", "assignment", "swaps", "all", 1.0, 2),
    ("safety", "apriori", "episodes", "all", 5.0, 2),
    ("safety", "apriori", "hits", "all", 4.0, 2),
    ("safety", "apriori", "misses", "all", 1.0, 2),
    ("safety", "apriori", "false_alerts", "all", 7.0, 2),
    ("safety", "apriori", "mean_warning_s", "all", 60.5, 2),
    ("safety", "apriori", "flicker", "all", 2.0, 2),
    ("safety", "apriori", "flicker_per_hit", "all", 0.5, 2),
    ("safety", "apriori", "los_episodes", "all", 3.0, 2),
    ("safety", "apriori", "alerted_los", "all", 2.0, 2),
    ("safety", "apriori", "missed_los", "all", 1.0, 2),
    ("safety", "apriori", "genuine_alerts", "all", 2.0, 2),
    ("safety", "apriori", "nuisance_alerts", "all", 4.0, 2),
    ("safety", "apriori", "alerts_per_hour", "all", 12.5, 2),
    ("safety", "apriori", "warning_median_s", "all", 45.0, 2),
    ("safety", "apriori", "warning_p05_s", "all", 20.0, 2),
    ("safety", "apriori", "alerts_picture_induced", "all", 6.0, 2),
    ("safety", "apriori", "false_alerts_picture_induced", "all", 5.0, 2),
    ("safety", "apriori", "nuisance_alerts_picture_induced", "all", 1.0, 2),
    ("safety", "apriori", "missed_los_picture_induced", "all", 0.0, 2),
    ("safety", "apriori", "missed_los_under_way", "all", 1.0, 2),
    ("safety", "apriori", "valid_alerts", "all", 2.0, 2),
    ("safety", "apriori", "alert_episodes", "all", 14.0, 2),
    ("safety", "apriori", "undetermined_alerts", "all", 1.0, 2),
    ("safety", "apriori", "nuisance_false_per_hour", "all", 11.0, 2),
    ("safety", "apriori", "alert_duration_median_s", "all", 30.0, 2),
    ("safety", "apriori", "flicker_per_alert", "all", 0.25, 2),
    ("safety", "apriori", "picture_hours", "all", 1.04, 2),
    ("safety_tradeoff", "apriori", "nuisance_false_per_hour", "mode=covariance;p=0.95;T=120;X=30", 6.0, 2),
    ("safety_tradeoff", "apriori", "alerted_fraction", "mode=covariance;p=0.95;T=120;X=30", 0.75, 2),
    ("safety_tradeoff", "apriori", "nuisance_false_per_hour", "mode=fixed;p=300;T=120;X=30", 9.0, 2),
    ("safety_tradeoff", "apriori", "alerted_fraction", "mode=fixed;p=300;T=120;X=30", 0.5, 2),
    ("safety", "apriori", "capacity_n_1e-6", "all", 3.0, 2),
    ("safety", "apriori", "capacity_n_1e-6_sound", "all", 4.0, 2),
    ("safety", "apriori+singer", "capacity_n_1e-6", "all", 5.0, 2),
    ("safety", "apriori+singer", "capacity_n_1e-6_sound", "all", 6.0, 2),
    ("safety", "fusion/information", "capacity_n_1e-6", "all", 7.0, 2),
    ("safety", "fusion/information", "capacity_n_1e-6_sound", "all", 8.0, 2),
    ("evaluation", "ours", "rmse_horizontal_m", "all", 44.0, 1),
    ("evaluation", "ours", "p95_horizontal_m", "all", 80.0, 1),
    ("evaluation", "ours", "prob_update", "all", 0.98, 1),
    ("evaluation", "ours", "rmse_horizontal_m", "phase:turn", 70.0, 1),
    ("evaluation", "ours", "ospa_m", "all", 120.0, 1),
    ("evaluation", "ours", "gospa_m", "all", 300.0, 1),
    ("evaluation", "ours", "siap_completeness", "all", 0.97, 1),
    ("evaluation", "ours", "multitarget_epochs", "all", 50.0, 1),
    ("evaluation", "theirs", "rmse_horizontal_m", "all", 99.0, 1),
    ("evaluation", "theirs", "id_changes_per_hour", "all", 1.5, 1),
]

REQUIREMENTS = pl.DataFrame({
    "requirement": ["H-RMS", "H-RMS", "PUPD"], "method": ["ours", "theirs", "ours"],
    "metric": ["rmse_horizontal_m", "rmse_horizontal_m", "prob_update"], "breakdown": ["all", "all", "all"],
    "op": ["<=", "<=", ">="], "threshold": [60.0, 60.0, 0.97], "value": [44.0, 99.0, 0.98],
    "bound": [49.0, 105.0, 0.96], "n_samples": [1000.0, 1000.0, 500.0], "verdict": ["pass", "fail", "insufficient"],
})

# conflicts: run, epoch_s, method, id_a, id_b, r_min_m, t_min_s, dz_m, alert, severity
CONFLICTS = [
    (0, 1, "apriori", 1, 2, 500.0, 60.0, -300.0, True, 0.5),
    (0, 2, "apriori", 1, 2, 300.0, 50.0, 200.0, True, 0.7),
    (0, 3, "apriori", 1, 2, 900.0, 40.0, 100.0, False, 0.0),
    (0, 2, "apriori", 1, 3, 100.0, 80.0, 50.0, True, 0.9),
    (0, 1, "arithmetic", 1, 2, 800.0, 70.0, 10.0, False, 0.0),
]

# clusters: run, epoch_s, method, cluster_id, lead_target_id, count
CLUSTERS = [
    (0, 1, "apriori", 1, 10, 3),
    (0, 2, "apriori", 1, 10, 3),
    (0, 3, "apriori", 1, 11, 2),
    (0, 3, "apriori", 2, 20, 2),
    (1, 1, "apriori", 1, 10, 4),
    (0, 1, "arithmetic", 1, 10, 2),
]

# associations: run, epoch_s, target_id, radar_id, cost
ASSOCIATIONS = [(0, 1, 1, 1, 1.0), (0, 1, 1, 2, 3.0), (0, 1, 2, 1, 2.0), (1, 1, 1, 1, 0.0)]

REJECTS = [
    ("reports", "ingest", 100, 5, "range_m: negative value -1.0"),
    ("reports", "ingest", 101, 3, "range_m: negative value -1.0"),
    ("reports", "align", 102, 9, "stale report"),
    ("radars", "ingest", None, 0, "lat_deg: NaN"),
]

RUN_RECORD = {"scenario": "hand", "rows": {"reports_in": 15}, "timings": {"validate_s": 0.5, "track_s": 2.0,
                                                                          "total_s": 3.0}}


def _radars() -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": [1, 2], "name": ["A", "B"], "lat_deg": [50.0, 50.1], "lon_deg": [30.0, 30.1],
        "alt_m": [0.0, 10.0], "scan_period_s": [1.0, 2.0], "sigma_range_m": [50.0, 60.0],
        "sigma_azimuth_deg": [0.1, 0.2], "sigma_elevation_deg": [0.1, 0.1], "max_range_m": [1e5, 2e5],
    }, schema_overrides={"radar_id": pl.UInt32})


def _reports() -> pl.DataFrame:
    cols = list(zip(*REPORTS))
    return pl.DataFrame({
        "run": pl.Series(cols[0], dtype=pl.UInt32), "radar_id": pl.Series(cols[1], dtype=pl.UInt32),
        "local_track_id": pl.Series(cols[2], dtype=pl.UInt32), "truth_id": pl.Series(cols[3], dtype=pl.Int64),
        "time": pl.Series([ts(t) for t in cols[4]], dtype=TIME),
        "est_range_m": cols[5], "est_range_rate_mps": cols[6], "res_range_m": cols[7], "res_range_var_m2": cols[8],
    }).with_columns(pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"),
                    pl.col("est_range_m").alias("range_m"), pl.lit(45.0).alias("azimuth_deg"))


def _truth() -> pl.DataFrame:
    rows = [(7, t, *truth_pos(7, t), "straight" if t < 3 else "turn") for t in range(7)]
    rows += [(8, t, *truth_pos(8, t), "straight") for t in range(3)]
    c = list(zip(*rows))
    return pl.DataFrame({"truth_id": pl.Series(c[0], dtype=pl.Int64), "time": pl.Series([ts(t) for t in c[1]], dtype=TIME),
                         "x_m": c[2], "y_m": c[3], "z_m": c[4], "vx_mps": 0.0, "vy_mps": 0.0, "vz_mps": 0.0,
                         "segment": c[5]})


def _aligned() -> pl.DataFrame:
    rows = []
    for i, (run, rid, lt, tid, e, (dx, dy, dz)) in enumerate(ALIGNED):
        x, y, z = truth_pos(tid if tid is not None else 7, e)
        rows.append((run, rid, lt, tid, ts(e), x + dx, y + dy, z + dz, 200 + i))
    rows.append((0, 2, 5, 7, ts(4), 0.0, 0.0, 0.0, 102))          # also rejected: breaks the accounting
    c = list(zip(*rows))
    return pl.DataFrame({"run": pl.Series(c[0], dtype=pl.UInt32), "radar_id": pl.Series(c[1], dtype=pl.UInt32),
                         "local_track_id": pl.Series(c[2], dtype=pl.UInt32), "truth_id": pl.Series(c[3], dtype=pl.Int64),
                         "epoch": pl.Series(c[4], dtype=TIME), "x_m": c[5], "y_m": c[6], "z_m": c[7],
                         "report_id": pl.Series(c[8], dtype=pl.UInt64)})


def _by_epoch() -> pl.DataFrame:
    rows = []
    for m, vals in BY_EPOCH.items():
        for e, v, n in zip((1, 2, 3), vals, BY_EPOCH_N):
            rows += [(m, ts(e), "rmse_range_m", v, 2, n), (m, ts(e), "rmse_pos_m", 2 * v, 2, n)]
    c = list(zip(*rows))
    return pl.DataFrame({"method": c[0], "epoch": pl.Series(c[1], dtype=TIME), "metric": c[2], "value": c[3],
                         "n_runs": pl.Series(c[4], dtype=pl.UInt32), "n": pl.Series(c[5], dtype=pl.UInt32),
                         "pooled": [n < 2 for n in c[5]]})


def _metrics() -> pl.DataFrame:
    c = list(zip(*METRICS))
    return pl.DataFrame({"stage": c[0], "method": c[1], "metric": c[2], "segment": c[3], "value": c[4],
                         "n_runs": pl.Series(c[5], dtype=pl.UInt32)})


def _conflicts() -> pl.DataFrame:
    c = list(zip(*CONFLICTS))
    return pl.DataFrame({"run": pl.Series(c[0], dtype=pl.UInt32), "epoch": pl.Series([ts(e) for e in c[1]], dtype=TIME),
                         "method": c[2], "id_a": pl.Series(c[3], dtype=pl.UInt64), "id_b": pl.Series(c[4], dtype=pl.UInt64),
                         "r_min_m": c[5], "t_min_s": c[6], "dz_m": c[7], "alert": c[8], "severity": c[9]})


# alerts: run, method, id_a, id_b, truth_a, truth_b, start_s, end_s, r_min, los_start_s, warning_s, class
ALERTS = [
    (0, "apriori+singer", 1, 2, 7, 8, 10.0, 40.0, 120.0, 70.0, 60.0, "genuine"),
    (0, "apriori+singer", 3, 4, None, None, 15.0, 20.0, 800.0, None, None, "false"),
    (1, "apriori+imm", 1, 2, 7, 8, 12.0, 30.0, 900.0, None, None, "nuisance"),
]


def _alerts() -> pl.DataFrame:
    c = list(zip(*ALERTS))
    opt = lambda v: None if v is None else ts(v)  # noqa: E731
    return pl.DataFrame({
        "run": pl.Series(c[0], dtype=pl.UInt32), "method": c[1], "id_a": pl.Series(c[2], dtype=pl.UInt64),
        "id_b": pl.Series(c[3], dtype=pl.UInt64), "truth_a": pl.Series(c[4], dtype=pl.Int64),
        "truth_b": pl.Series(c[5], dtype=pl.Int64), "t_start": pl.Series([ts(v) for v in c[6]], dtype=TIME),
        "t_end": pl.Series([ts(v) for v in c[7]], dtype=TIME), "duration_s": [b - a for a, b in zip(c[6], c[7])],
        "alert_epochs": pl.Series([4, 2, 3], dtype=pl.UInt32), "flicker": pl.Series([0, 0, 1], dtype=pl.UInt32),
        "r_min_pred_m": c[8], "dz_min_pred_m": [50.0, 10.0, 200.0], "t_min_first_s": [60.0, 5.0, 30.0],
        "los_start": pl.Series([opt(v) for v in c[9]], dtype=TIME), "warning_s": c[10], "classification": c[11]})


def _clusters() -> pl.DataFrame:
    c = list(zip(*CLUSTERS))
    return pl.DataFrame({"run": pl.Series(c[0], dtype=pl.UInt32), "epoch": pl.Series([ts(e) for e in c[1]], dtype=TIME),
                         "method": c[2], "cluster_id": pl.Series(c[3], dtype=pl.UInt64),
                         "lead_target_id": pl.Series(c[4], dtype=pl.UInt64), "count": pl.Series(c[5], dtype=pl.UInt32)})


def _associations() -> pl.DataFrame:
    c = list(zip(*ASSOCIATIONS))
    return pl.DataFrame({"run": pl.Series(c[0], dtype=pl.UInt32), "epoch": pl.Series([ts(e) for e in c[1]], dtype=TIME),
                         "target_id": pl.Series(c[2], dtype=pl.UInt64), "radar_id": pl.Series(c[3], dtype=pl.UInt32),
                         "cost": c[4]})


def _rejects() -> pl.DataFrame:
    c = list(zip(*REJECTS))
    return pl.DataFrame({"input_table": c[0], "stage": c[1], "report_id": pl.Series(c[2], dtype=pl.UInt64),
                         "row_index": pl.Series(c[3], dtype=pl.UInt64), "reason": c[4], "detail": ""})


@pytest.fixture(scope="module")
def hand_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("hand_run")
    with RunStore.create(out) as store:
        store.write("radars", _radars())
        store.write("reports", _reports())
        store.write("truth", _truth())
        store.write("aligned", _aligned())
        store.write("associations", _associations())
        store.write("fused", pl.DataFrame({"run": pl.Series([0, 0, 0], dtype=pl.UInt32), "method": ["a", "a", "b"]}))
        store.write("clusters", _clusters())
        store.write("tracks", pl.DataFrame({"run": pl.Series([0, 0], dtype=pl.UInt32)}))
        store.write("conflicts", _conflicts())
        store.write("alerts", _alerts())
        store.write("rejects", _rejects())
        store.write("metrics", _metrics())
        store.write("accuracy_by_epoch", _by_epoch())
        store.write("requirements", REQUIREMENTS)
        store.write("run", pl.DataFrame({"key": list(RUN_RECORD), "value": [v if isinstance(v, str) else json.dumps(v)
                                                                           for v in RUN_RECORD.values()]}))
    return out


@pytest.fixture
def q(hand_run):
    store = sql_reports.open_read_only(hand_run)
    yield lambda name, **params: sql_reports.run_report(store, name, params)
    store.close()


def rows(frame: pl.DataFrame, *cols: str) -> list[tuple]:
    return [tuple(r) for r in frame.select(cols or frame.columns).iter_rows()]


TESTED: set[str] = set()


def covers(*names: str):
    TESTED.update(names)
    return lambda f: f


# --------------------------------------------------------------------------- the report files


def test_every_report_parses_and_is_tested():
    reports = sql_reports.list_reports()
    names = {r.name for r in reports}
    assert {"rejects_by_reason", "reports_by_radar", "run_summary"} <= names
    for r in reports:
        assert r.sql.startswith("-- ") and r.description and r.summary, r.name
        assert "Columns:" in r.description, r.name
    assert names == TESTED, f"reports without a test: {sorted(names - TESTED)}"


def test_parameters_are_bound_not_formatted(tmp_path):
    rep = sql_reports.load_report("accuracy_over_time")
    assert rep.params == {"metric": "rmse_range_m", "method": None, "min_sample_frac": 0}
    assert "$method" in rep.sql and "{" not in sql_reports._strip_comments(rep.sql)
    with pytest.raises(OptionError, match="no parameter"):
        rep.bind({"nope": 1})
    with pytest.raises(OptionError, match="no SQL report"):
        sql_reports.load_report("nope")
    bad = tmp_path / "bad.sql"
    bad.write_text("-- Bad: uses an undeclared parameter.\nSELECT $x\n")
    with pytest.raises(ValueError, match="declare"):
        sql_reports._parse(bad)


def test_injection_is_data(q):
    evil = "apriori' OR '1'='1"
    # a value the run does not hold is refused with the allowed values, never formatted into SQL
    with pytest.raises(OptionError, match="not in this run; allowed: .*apriori"):
        q("accuracy_over_time", method=evil)
    assert q("accuracy_over_time", method="apriori").height == 3


# --------------------------------------------------------------------------- hand computations


@covers("accuracy_by_method")
def test_accuracy_by_method(q):
    df = q("accuracy_by_method")
    assert df.columns == ["stage", "method", "filter", "segment", "rmse_pos_m", "rmse_horizontal_m", "rmse_height_m",
                          "rmse_range_m", "rmse_x_m", "rmse_y_m", "rmse_z_m", "rmse_vel_mps", "pcrb_pos_m",
                          "gap_pos_m", "nees_mean", "nees_in_band_frac", "n_runs"]
    fusion_all = df.filter((pl.col("stage") == "fusion") & (pl.col("segment") == "all"))
    assert rows(fusion_all, "method", "rmse_pos_m", "rmse_horizontal_m", "rmse_height_m")[:2] == [
        ("apriori", 90.0, 54.0, 72.0), ("aposteriori", 100.0, None, None)]
    assert rows(fusion_all, "method", "filter", "rmse_pos_m", "rmse_range_m", "rmse_vel_mps") == [
        ("apriori", None, 90.0, 40.0, 9.0), ("aposteriori", None, 100.0, None, None),
        ("information", None, None, 31.0, None)]
    trk = df.filter(pl.col("stage") == "tracker")
    assert rows(trk, "method", "filter", "rmse_pos_m") == [("apriori", "imm", 60.0), ("apriori", "singer", 70.0),
                                                             ("information", "singer", None)]
    assert df["segment"].to_list()[:3] == ["all"] * 3
    turn = q("accuracy_by_method", stage="fusion", segment="turn")
    assert rows(turn, "method", "rmse_pos_m") == [("apriori", 150.0)]
    assert q("accuracy_by_method", method="aposteriori").height == 1


@covers("accuracy_over_time")
def test_accuracy_over_time(q):
    df = q("accuracy_over_time", method="apriori")
    assert df.columns == ["method", "metric", "epoch", "t_s", "value", "n_runs", "n", "pooled"]
    # t_s from the first report (0.5 s) truncated to the whole second
    assert rows(df, "t_s", "value", "n", "pooled") == [(1.0, 10.0, 4, False), (2.0, 20.0, 4, False),
                                                       (3.0, 40.0, 1, True)]
    # edge rule: N_k = 1 < 0.5 × median 4 is left out; 0.25 × 4 = 1 keeps it (the bound is inclusive)
    assert q("accuracy_over_time", method="apriori", min_sample_frac=0.5)["t_s"].to_list() == [1.0, 2.0]
    assert q("accuracy_over_time", method="apriori", min_sample_frac=0.25).height == 3
    assert q("accuracy_over_time", metric=None, min_sample_frac=0.5).height == 4 * len(BY_EPOCH)
    assert q("accuracy_over_time", metric="rmse_pos_m", method="apriori")["value"].to_list() == [20.0, 40.0, 80.0]
    assert q("accuracy_over_time").height == 3 * len(BY_EPOCH)
    assert q("accuracy_over_time", metric=None).height == 6 * len(BY_EPOCH)


def _radar_table(skip: float) -> list[tuple]:
    """Hand computation of radar_accuracy_over_time from the ALIGNED rows (and the extra epoch-4
    row of radar 2): per (radar, epoch) the errors against truth; σ²(k) = Σ e² / (N_k − 1), epochs
    with N_k = 1 pooled per radar (σ²(k) = e² · M / (M − 1), left out when M = 1).
    Rows: (radar_id, t_s, range, pos, horizontal, height, n, pooled)."""
    aligned = ALIGNED + [(0, 2, 5, 7, 4, (-400.0, 0.0, -1000.0))]          # the (0, 0, 0) row of _aligned()
    first: dict = {}
    for run, rid, lt, _tid, e, _err in aligned:
        first[(run, rid, lt)] = min(first.get((run, rid, lt), e), e)
    cells: dict = {}
    for run, rid, lt, tid, e, (dx, dy, dz) in aligned:
        if tid is None or e - first[(run, rid, lt)] < skip:
            continue
        x, y, z = truth_pos(tid, e)
        er = math.dist((0, 0, 0), (x + dx, y + dy, z + dz)) - math.dist((0, 0, 0), (x, y, z))
        cells.setdefault((rid, e), []).append((er * er, dx * dx + dy * dy, dz * dz))
    m = {}
    for (rid, _e), errs in cells.items():
        m[rid] = m.get(rid, 0) + (len(errs) if len(errs) == 1 else 0)
    out = []
    for (rid, e), errs in sorted(cells.items()):
        n = len(errs)
        if n == 1 and m[rid] < 2:
            continue
        dof = n - 1 if n > 1 else (m[rid] - 1) / m[rid]
        sr, sh, sv = (sum(v[i] for v in errs) for i in range(3))
        out.append((rid, float(e), math.sqrt(sr / dof), math.sqrt((sh + sv) / dof), math.sqrt(sh / dof),
                    math.sqrt(sv / dof), n, n == 1))
    return out


@covers("radar_accuracy_over_time")
def test_radar_accuracy_over_time(q):
    assert q("radar_accuracy_over_time").height == 0          # every hand track is younger than 20 s
    df = q("radar_accuracy_over_time", skip_first_s=0)
    assert df.columns == ["radar_id", "name", "epoch", "t_s", "rmse_range_m", "rmse_pos_m", "rmse_horizontal_m",
                          "rmse_height_m", "n", "n_runs", "pooled"]
    # radar 1: epochs 1 and 2 have 3 scored rows; epoch 3 has 1 (clutter unmatched), alone in its pool
    # -> left out; radar 2: one row at each of epochs 1, 3, 4 -> pooled (M = 3)
    assert rows(df, "radar_id", "name", "t_s", "n", "n_runs", "pooled") == [
        (1, "A", 1.0, 3, 2, False), (1, "A", 2.0, 3, 2, False),
        (2, "B", 1.0, 1, 1, True), (2, "B", 3.0, 1, 1, True), (2, "B", 4.0, 1, 1, True)]
    hand = _radar_table(0.0)
    got = rows(df, "radar_id", "t_s", "rmse_range_m", "rmse_pos_m", "rmse_horizontal_m", "rmse_height_m", "n",
               "pooled")
    assert [g[:2] for g in got] == [h[:2] for h in hand]
    for g, h in zip(got, hand):
        assert g[2:6] == pytest.approx(h[2:6], rel=1e-12) and g[6:] == h[6:]
    # epoch-1 position: errors 30,40,0 / 0,12,0 / -20,0,0 -> sqrt((2500 + 144 + 400) / 2); all horizontal
    assert df["rmse_pos_m"][0] == pytest.approx(math.sqrt(3044 / 2))
    assert df["rmse_horizontal_m"][0] == pytest.approx(math.sqrt(3044 / 2)) and df["rmse_height_m"][0] == 0.0
    # radar 2 epoch 1: error (100, 0, 0) alone, pooled with M = 3: σ² = 100² · 3 / 2
    assert df["rmse_horizontal_m"][2] == pytest.approx(100.0 * math.sqrt(1.5))
    late = q("radar_accuracy_over_time", skip_first_s=1)
    assert rows(late, "radar_id", "t_s", "n") == [(r[0], r[1], r[6]) for r in _radar_table(1.0)] == [
        (1, 2.0, 3), (2, 3.0, 1), (2, 4.0, 1)]
    assert q("radar_accuracy_over_time", skip_first_s=0, radar_id=2).height == 3
    # edge rule: radar 1's median n is 3, radar 2's 1 — a fraction 0.5 keeps both radars' epochs
    assert q("radar_accuracy_over_time", skip_first_s=0, min_sample_frac=0.5).height == 5
    assert q("radar_accuracy_over_time", skip_first_s=0, min_sample_frac=1.5).height == 0


@covers("aposteriori_vs_apriori")
def test_aposteriori_vs_apriori(q):
    df = q("aposteriori_vs_apriori")
    assert df.columns == ["posterior", "prior", "epoch", "t_s", "sigma_post", "sigma_prior", "gain"]
    assert df.height == 2 * 2 * 3
    part = df.filter((pl.col("posterior") == "aposteriori") & (pl.col("prior") == "apriori"))
    assert rows(part, "t_s", "sigma_post", "sigma_prior") == [(1.0, 5.0, 10.0), (2.0, 25.0, 20.0), (3.0, 20.0, 40.0)]
    assert part["gain"].to_list() == pytest.approx([0.5, -0.25, 0.5])
    pos = q("aposteriori_vs_apriori", metric="rmse_pos_m")
    assert pos.filter(pl.col("posterior") == "aposteriori")["sigma_post"].to_list()[:3] == [10.0, 50.0, 40.0]
    # edge rule: epoch 3 has N_k = 1 < 0.5 × median 4 for every method -> left out
    edge = q("aposteriori_vs_apriori", min_sample_frac=0.5)
    assert edge.height == 2 * 2 * 2 and sorted(set(edge["t_s"])) == [1.0, 2.0]


@covers("aposteriori_gain")
def test_aposteriori_gain(q):
    df = q("aposteriori_gain")
    assert df.columns == ["posterior", "prior", "epochs", "max_gain", "max_gain_manoeuvre", "manoeuvre_epochs",
                          "mean_gain", "pooled_gain"]
    assert rows(df, "posterior", "prior") == [("aposteriori", "apriori"), ("aposteriori", "arithmetic"),
                                              ("aposteriori_seed", "apriori"), ("aposteriori_seed", "arithmetic")]
    a = dict(zip(df.columns, df.row(0)))
    # gains 0.5, -0.25, 0.5; only epoch 3 is a manoeuvre (aircraft 7 turns from 3 s, aircraft 8 flies straight)
    assert a["epochs"] == 3 and a["manoeuvre_epochs"] == 1
    assert a["max_gain"] == pytest.approx(0.5) and a["max_gain_manoeuvre"] == pytest.approx(0.5)
    assert a["mean_gain"] == pytest.approx(0.25)
    assert a["pooled_gain"] == pytest.approx(1 - math.sqrt((25 + 625 + 400) / (100 + 400 + 1600)))
    b = dict(zip(df.columns, df.row(1)))             # vs arithmetic: 0.75, -0.25, 0
    assert b["max_gain"] == pytest.approx(0.75) and b["max_gain_manoeuvre"] == pytest.approx(0.0)
    assert b["mean_gain"] == pytest.approx(0.5 / 3)
    edge = dict(zip(df.columns, q("aposteriori_gain", min_sample_frac=0.5).row(0)))    # epoch 3 left out
    assert edge["epochs"] == 2 and edge["manoeuvre_epochs"] == 0 and edge["mean_gain"] == pytest.approx(0.125)
    assert edge["pooled_gain"] == pytest.approx(1 - math.sqrt((25 + 625) / (100 + 400)))


@covers("radar_residuals")
def test_radar_residuals(q):
    df = q("radar_residuals")
    assert df.columns == ["radar_id", "name", "n", "mean_m", "sd_m", "rms_m", "mean_abs_m", "p95_abs_m", "max_abs_m",
                          "nis_mean", "frac_beyond_3sd"]
    r1, r2 = (dict(zip(df.columns, r)) for r in df.iter_rows())
    res1 = np.array([3.0, -4.0, 5.0, 1.0, 2.0])
    assert r1["n"] == 5 and r1["mean_m"] == pytest.approx(1.4)
    assert r1["sd_m"] == pytest.approx(np.std(res1, ddof=1)) and r1["rms_m"] == pytest.approx(math.sqrt(11.0))
    assert r1["mean_abs_m"] == pytest.approx(3.0) and r1["max_abs_m"] == 5.0
    assert r1["nis_mean"] == pytest.approx((9 / 4 + 16 / 4 + 25 / 4 + 1 + 4 / 4) / 5)
    assert r1["frac_beyond_3sd"] == 0.0
    assert r2["n"] == 2 and r2["mean_m"] == pytest.approx(-2.0) and r2["sd_m"] == pytest.approx(math.sqrt(200.0))
    assert r2["p95_abs_m"] == pytest.approx(8 + 0.95 * 4) and r2["nis_mean"] == pytest.approx(10.0)
    assert r2["frac_beyond_3sd"] == pytest.approx(0.5)           # |−12| > 3·3
    one = q("radar_residuals", run=1)
    assert rows(one, "radar_id", "n", "mean_m") == [(1, 1, 2.0)]


@covers("radar_residuals_over_time")
def test_radar_residuals_over_time(q):
    df = q("radar_residuals_over_time", bin_s=2)
    assert df.columns == ["radar_id", "name", "t_s", "n", "mean_abs_res_m", "rms_res_m", "pred_sd_m"]
    assert rows(df, "radar_id", "t_s", "n") == [(1, 0.0, 3), (1, 2.0, 2), (2, 2.0, 1), (2, 4.0, 1)]
    first = dict(zip(df.columns, df.row(0)))         # residuals 3, 1, 2 with variances 4, 1, 4
    assert first["mean_abs_res_m"] == pytest.approx(2.0)
    assert first["rms_res_m"] == pytest.approx(math.sqrt(14 / 3))
    assert first["pred_sd_m"] == pytest.approx(5 / 3)
    assert df["mean_abs_res_m"].to_list()[1:] == pytest.approx([4.5, 8.0, 12.0])
    assert q("radar_residuals_over_time").height == 2           # default 10 s bins: one per radar


@covers("radar_kinematics")
def test_radar_kinematics(q):
    df = q("radar_kinematics")
    assert df.columns == ["radar_id", "name", "truth_id", "local_track_id", "time", "t_s", "est_range_m",
                          "est_range_rate_mps", "accel_mps2"]
    # run 0; aircraft 7 (two radars) before aircraft 8 (one radar); clutter never picked
    assert df["truth_id"].to_list() == [7] * 7 + [8] * 2
    r1 = df.filter((pl.col("truth_id") == 7) & (pl.col("radar_id") == 1))
    assert rows(r1, "t_s", "est_range_m") == [(0.5, 1000.0), (1.5, 1010.0), (2.5, 1030.0), (3.5, 1060.0)]
    assert r1["accel_mps2"].to_list() == [None, None, 10.0, 10.0]
    r2 = df.filter((pl.col("truth_id") == 7) & (pl.col("radar_id") == 2))
    assert r2["accel_mps2"].to_list() == [None, None, pytest.approx(-2.5)]          # (−10 − −5) / 2 s
    assert q("radar_kinematics", max_aircraft=1)["truth_id"].unique().to_list() == [7]
    assert rows(q("radar_kinematics", run=1), "est_range_m") == [(1001.0,), (1012.0,)]


@covers("trajectories")
def test_trajectories(q):
    df = q("trajectories", step_s=2)
    assert df.columns == ["truth_id", "time", "t_s", "x_m", "y_m", "z_m"]
    assert rows(df, "truth_id", "t_s") == [(7, 0.0), (7, 2.0), (7, 4.0), (7, 6.0), (8, 0.0), (8, 2.0)]
    assert rows(df.head(2), "x_m", "z_m") == [(0.0, 1000.0), (200.0, 1000.0)]
    assert rows(q("trajectories", step_s=4, max_aircraft=1), "t_s") == [(0.0,), (4.0,), (6.0,)]   # last kept
    assert q("trajectories").height == 2 + 2                     # 10 s bins: first and last sample


@covers("radar_sites")
def test_radar_sites(q):
    df = q("radar_sites")
    assert df.columns == ["radar_id", "name", "lat_deg", "lon_deg", "alt_m", "scan_period_s", "sigma_range_m",
                          "sigma_azimuth_deg", "max_range_m", "reports"]
    assert rows(df, "name", "lat_deg", "reports") == [("A", 50.0, 9), ("B", 50.1, 3)]


@covers("association_quality")
def test_association_quality(q):
    df = q("association_quality")
    assert df.columns == ["metric", "value", "n_runs", "source"]
    got = {m: v for m, v in zip(df["metric"], df["value"])}
    assert got["assoc_correct_frac"] == 0.95 and got["swaps"] == 1.0
    assert got["association_rows"] == 4.0
    assert got["mean_cost"] == pytest.approx(6.0 / 4)
    assert got["reports_per_target_epoch"] == pytest.approx(4 / 3)
    assert got["radars_per_target_epoch"] == pytest.approx(4 / 3)
    assert df.filter(pl.col("source") == "associations")["n_runs"].to_list() == [2] * 4


@covers("track_quality")
def test_track_quality(q):
    df = q("track_quality")
    assert df.columns == ["method", "filter", "tracks", "completeness", "breaks", "swaps", "spurious_tracks",
                          "rmse_pos_m", "rmse_vel_mps", "potential_pos_m", "nees_mean", "nis_mean",
                          "nees_in_band_frac", "nis_in_band_frac", "n_runs"]
    assert rows(df, "method", "filter", "tracks", "rmse_pos_m") == [
        ("apriori", "imm", 11.0, 60.0), ("apriori", "singer", 10.0, 70.0), ("information", "singer", None, None)]
    singer = dict(zip(df.columns, df.row(1)))
    assert singer["nis_mean"] == 1.2 and singer["completeness"] == 0.9 and singer["spurious_tracks"] == 2.0
    assert q("track_quality", filter="imm").height == 1


@covers("cluster_statistics")
def test_cluster_statistics(q):
    df = q("cluster_statistics")
    assert df.columns == ["method", "clusters", "cluster_rows", "epochs", "mean_clusters_per_epoch",
                          "max_clusters_per_epoch", "mean_members", "max_members", "lead_changes", "n_runs"]
    a = dict(zip(df.columns, df.row(0)))
    assert a["method"] == "apriori"
    assert (a["clusters"], a["cluster_rows"], a["epochs"], a["max_clusters_per_epoch"]) == (3, 5, 4, 2)
    assert a["mean_clusters_per_epoch"] == pytest.approx(5 / 4)
    assert a["mean_members"] == pytest.approx(14 / 5) and a["max_members"] == 4
    assert a["lead_changes"] == 1 and a["n_runs"] == 2
    assert q("cluster_statistics", method="arithmetic")["clusters"].to_list() == [1]


@covers("conflicts")
def test_conflicts(q):
    df = q("conflicts")
    assert df.columns == ["method", "run", "id_a", "id_b", "first_epoch", "last_epoch", "alert_epochs",
                          "min_r_min_m", "min_t_min_s", "min_abs_dz_m", "max_severity"]
    assert rows(df, "method", "id_a", "id_b", "alert_epochs", "min_r_min_m", "min_t_min_s", "min_abs_dz_m",
                "max_severity") == [("apriori", 1, 3, 1, 100.0, 80.0, 50.0, 0.9),
                                    ("apriori", 1, 2, 2, 300.0, 50.0, 200.0, 0.7)]
    assert df["first_epoch"][1] == ts(1) and df["last_epoch"][1] == ts(2)
    assert q("conflicts", min_severity=0.8).height == 1
    assert q("conflicts", method="arithmetic").height == 0


@covers("conflict_timeline")
def test_conflict_timeline(q):
    df = q("conflict_timeline")
    assert df.columns == ["method", "epoch", "t_s", "pairs", "alerts", "new_alerts", "max_severity",
                          "mean_severity"]
    # new alerts: pair (1, 2) starts alerting at 1 s and stays in alert at 2 s; pair (1, 3) starts at 2 s
    assert rows(df, "method", "t_s", "pairs", "alerts", "new_alerts", "max_severity") == [
        ("apriori", 1.0, 1, 1, 1, 0.5), ("apriori", 2.0, 2, 2, 1, 0.9), ("apriori", 3.0, 1, 0, 0, None),
        ("arithmetic", 1.0, 1, 0, 0, None)]
    assert df["mean_severity"][1] == pytest.approx(0.8)
    assert q("conflict_timeline", method="arithmetic").height == 1


@covers("alert_scores")
def test_alert_scores(q):
    df = q("alert_scores")
    assert df.columns == ["method", "los_episodes", "alerted_los", "missed_los", "genuine_alerts", "nuisance_alerts",
                          "false_alerts", "undetermined_alerts", "alerts_per_hour", "warning_median_s",
                          "warning_p05_s", "alerts_picture_induced", "false_alerts_picture_induced",
                          "nuisance_alerts_picture_induced", "missed_los_picture_induced", "missed_los_under_way",
                          "valid_alerts", "n_runs"]
    assert rows(df) == [("apriori", 3.0, 2.0, 1.0, 2.0, 4.0, 7.0, 1.0, 12.5, 45.0, 20.0, 6.0, 5.0, 1.0, 0.0, 1.0,
                         2.0, 2)]
    # capacity rows (apriori+singer, fusion/information) are not scores


@covers("alert_episodes")
def test_alert_episodes(q):
    df = q("alert_episodes")
    assert df.columns[:6] == ["method", "run", "id_a", "id_b", "truth_a", "truth_b"]
    assert rows(df, "method", "run", "id_a", "classification", "warning_s") == [
        ("apriori+imm", 1, 1, "nuisance", None), ("apriori+singer", 0, 1, "genuine", 60.0),
        ("apriori+singer", 0, 3, "false", None)]            # per picture and run, earliest first
    assert rows(q("alert_episodes", classification="genuine"), "id_a", "id_b") == [(1, 2)]
    assert q("alert_episodes", method="apriori+imm").height == 1


@covers("stca_performance")
def test_stca_performance(q):
    df = q("stca_performance")
    assert df["method"].to_list() == ["apriori"]          # capacity-only pictures have no STCA row
    r = df.row(0, named=True)
    assert (r["los_episodes"], r["alerted_los"], r["missed_los"]) == (3.0, 2.0, 1.0)
    assert r["alerted_fraction"] == pytest.approx(2 / 3)
    assert (r["genuine_alerts"], r["nuisance_alerts"], r["false_alerts"], r["undetermined_alerts"],
            r["alert_episodes"]) == (2.0, 4.0, 7.0, 1.0, 14.0)
    assert (r["warning_median_s"], r["warning_p05_s"], r["nuisance_false_per_hour"]) == (45.0, 20.0, 11.0)
    assert (r["alert_duration_median_s"], r["flicker_per_alert"], r["picture_hours"], r["n_runs"]) == (30.0, 0.25,
                                                                                                     1.04, 2)


@covers("stca_tradeoff")
def test_stca_tradeoff(q):
    df = q("stca_tradeoff")
    assert rows(df, "threshold_mode", "parameter", "t_thr_s", "warning_s", "nuisance_false_per_hour",
                "alerted_fraction") == [("covariance", 0.95, 120.0, 30.0, 6.0, 0.75),
                                        ("fixed", 300.0, 120.0, 30.0, 9.0, 0.5)]
    assert q("stca_tradeoff", warning_s=60).height == 0


@covers("multitarget_metrics")
def test_multitarget_metrics(q):
    df = q("multitarget_metrics")
    assert df.columns[:4] == ["method", "rmse_horizontal_m", "ospa_m", "gospa_m"] and df.columns[-1] == "epochs"
    # a picture without multi-target metrics (theirs) has no row
    assert rows(df, "method", "rmse_horizontal_m", "ospa_m", "gospa_m", "siap_completeness", "siap_ambiguity",
                "epochs") == [("ours", 44.0, 120.0, 300.0, 0.97, None, 50.0)]


@covers("picture_comparison")
def test_picture_comparison(q):
    df = q("picture_comparison")
    assert rows(df, "method", "segment", "rmse_horizontal_m", "p95_horizontal_m", "prob_update",
                "id_changes_per_hour") == [("ours", "all", 44.0, 80.0, 0.98, None),
                                           ("theirs", "all", 99.0, None, None, 1.5)]   # most accurate first
    assert rows(q("picture_comparison", segment="phase:turn"), "method", "rmse_horizontal_m") == [("ours", 70.0)]


@covers("requirements_verdicts")
def test_requirements_verdicts(q):
    df = q("requirements_verdicts")
    assert rows(df, "requirement", "method", "verdict") == [("H-RMS", "theirs", "fail"),   # failures first
                                                            ("PUPD", "ours", "insufficient"),
                                                            ("H-RMS", "ours", "pass")]
    assert q("requirements_verdicts", verdict="pass").height == 1


@covers("capacity_by_method")
def test_capacity_by_method(q):
    df = q("capacity_by_method")
    assert df.columns == ["method", "stage", "p_star", "sigma_metric", "sigma_m", "n_max_seed", "n_max_sound",
                          "n_aircraft", "p_conflict_seed", "p_conflict_sound", "n_runs"]
    assert rows(df, "method", "stage", "p_star", "sigma_metric", "sigma_m", "n_max_seed", "n_max_sound") == [
        ("fusion/information", "fusion", 1e-6, "rmse_range_m", 31.0, 7.0, 8.0),
        ("apriori", "fusion", 1e-6, "rmse_range_m", 40.0, 3.0, 4.0),        # rmse_range_m preferred to rmse_pos_m
        ("apriori+singer", "tracker", 1e-6, "rmse_pos_m", 70.0, 5.0, 6.0),  # no range RMSE: position
    ]


@covers("row_accounting")
def test_row_accounting(q):
    df = q("row_accounting")
    assert df.columns == ["item", "rows"]
    got = dict(zip(df["item"], df["rows"]))
    aligned_ids = len(ALIGNED) + 1
    assert got["reports_in"] == 15 and got["reports_valid"] == len(REPORTS)
    assert got["reports_rejected"] == 3
    assert got["reports_rejected_at_ingest"] == 2 and got["reports_rejected_at_align"] == 1
    assert got["reports_aligned"] == aligned_ids
    assert got["unaccounted"] == 15 - aligned_ids - 3
    assert got["both_aligned_and_rejected"] == 1                 # report 102 is in both
    assert (got["fused_rows"], got["tracks_rows"], got["conflicts_rows"]) == (3, 2, len(CONFLICTS))


@covers("stage_timings")
def test_stage_timings(q):
    df = q("stage_timings")
    assert df.columns == ["stage", "seconds"]
    assert rows(df) == [("total", 3.0), ("track", 2.0), ("validate", 0.5)]


@covers("run_summary")
def test_run_summary_hand(q):
    df = q("run_summary")
    assert df.columns == ["key", "value"]
    assert df["key"].to_list() == sorted(RUN_RECORD)
    assert json.loads(dict(rows(df))["rows"]) == {"reports_in": 15}


@covers("rejects_by_reason")
def test_rejects_by_reason_hand(q):
    df = q("rejects_by_reason")
    assert rows(df) == [("reports", "ingest", "range_m: negative value -1.0", 2, 3),
                        ("radars", "ingest", "lat_deg: NaN", 1, 0),
                        ("reports", "align", "stale report", 1, 9)]


@covers("reports_by_radar")
def test_reports_by_radar_hand(q):
    df = q("reports_by_radar")
    assert rows(df, "radar_id", "reports", "local_tracks", "reports_without_truth") == [(1, 9, 4, 1), (2, 3, 1, 0)]
    assert df["res_range_sd_m"][0] == pytest.approx(np.std([3.0, -4.0, 5.0, 1.0, 2.0], ddof=1))


# --------------------------------------------------------------------------- read-only


def test_read_only(hand_run):
    with sql_reports.open_read_only(hand_run) as store:
        for bad in ("DELETE FROM metrics", "CREATE TABLE x AS SELECT 1", "INSERT INTO metrics SELECT * FROM metrics",
                    "SELECT 1; DROP TABLE metrics", "COPY metrics TO 'x.csv'", "ATTACH 'other.db'",
                    "SET threads = 1", "CHECKPOINT"):
            with pytest.raises(sql_reports.ReadOnlyQueryError, match="refused"):
                sql_reports.query(store, bad)
        with pytest.raises(Exception, match="disabled by configuration"):
            sql_reports.query(store, "SELECT * FROM read_csv('/etc/hostname')")
        # the attach itself is read-only too, whatever gets past the statement check
        with pytest.raises(Exception, match="read-only"):
            store.con.execute("DELETE FROM metrics")
        assert sql_reports.query(store, "SELECT count(*) AS n FROM metrics")["n"].item() == len(METRICS)
        assert sql_reports.query(store, "SHOW TABLES").height >= 10


# --------------------------------------------------------------------------- CLI


def test_cli_list(hand_run):
    res = runner.invoke(app, ["sql", str(hand_run), "--list"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    for rep in sql_reports.list_reports():
        assert rep.name in res.output
    assert "Accuracy by method and segment" in res.output


def test_cli_tables_take_the_width_of_each_command(hand_run):
    """In batch (not a terminal) a table is as wide as COLUMNS says when the command runs, not
    when the CLI module was imported: fails with the width read once at import."""
    widths = {}
    for cols in (70, 200):
        res = runner.invoke(app, ["sql", str(hand_run), "--list"], env={"COLUMNS": str(cols)})
        assert res.exit_code == 0, res.output
        widths[cols] = max(len(line) for line in res.output.splitlines())
    assert widths[70] <= 70 < widths[200] <= 200


def test_cli_named_report_table_and_params(hand_run):
    res = runner.invoke(app, ["sql", str(hand_run), "track_quality"], env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    assert "singer" in res.output and "3 rows" in res.output
    res = runner.invoke(app, ["sql", str(hand_run), "conflicts", "-p", "min_severity=0.8", "--format", "csv"])
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert lines[0].startswith("method,run,id_a,id_b") and len(lines) == 2 and ",0.9" in lines[1]
    res = runner.invoke(app, ["sql", str(hand_run), "conflicts", "-p", "nope=1"])
    assert res.exit_code == 2 and "no parameter" in res.output            # an option error
    res = runner.invoke(app, ["sql", str(hand_run), "no_such_report"])
    assert res.exit_code == 2 and "available" in res.output


def test_cli_export(hand_run, tmp_path):
    out = tmp_path / "x" / "acc.parquet"
    res = runner.invoke(app, ["sql", str(hand_run), "accuracy_over_time", "--format", "parquet", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert pl.read_parquet(out).height == 3 * len(BY_EPOCH)
    csv = tmp_path / "acc.csv"
    res = runner.invoke(app, ["sql", str(hand_run), "radar_sites", "--out", str(csv)])   # format from suffix
    assert res.exit_code == 0, res.output
    assert pl.read_csv(csv)["name"].to_list() == ["A", "B"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["acc.csv", "x"]        # no temp files left
    res = runner.invoke(app, ["sql", str(hand_run), "radar_sites", "--format", "parquet"])
    assert res.exit_code != 0


def test_cli_query_read_only(hand_run):
    res = runner.invoke(app, ["sql", str(hand_run), "--query", "SELECT method, count(*) AS n FROM fused GROUP BY 1 ORDER BY 1"])
    assert res.exit_code == 0, res.output
    assert "2 rows" in res.output
    res = runner.invoke(app, ["sql", str(hand_run), "--query", "DROP TABLE metrics"])
    assert res.exit_code == 2 and "read-only" in res.output and "DROP" in res.output
    res = runner.invoke(app, ["sql", str(hand_run), "--query", "SELECT nothing FROM nowhere"])
    assert res.exit_code == 2 and "SQL error" in res.output
    with RunStore.open(hand_run) as store:
        assert "metrics" in store.tables()
    res = runner.invoke(app, ["sql", str(hand_run)])
    assert res.exit_code == 2


# --------------------------------------------------------------------------- a simulated run


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20, conflict_pairs=3))
    ds = simulate(cfg)
    out = tmp_path_factory.mktemp("sim_run")
    pipeline.run(ds, out, pipeline.PipelineConfig(filters=("singer",)))
    return out


def test_simulated_radar_accuracy_matches_polars(sim_run):
    with sql_reports.open_read_only(sim_run) as store:
        df = sql_reports.run_report(store, "radar_accuracy_over_time")
        aligned, truth = store.read("aligned"), store.read("truth")
    first = pl.col("epoch").min().over("run", "radar_id", "local_track_id")
    a = aligned.filter((pl.col("epoch") - first).dt.total_seconds() >= 20)
    j = a.join(truth.rename({"time": "epoch"}), on=["truth_id", "epoch"], suffix="_t")
    r = lambda s="": (pl.col(f"x_m{s}") ** 2 + pl.col(f"y_m{s}") ** 2 + pl.col(f"z_m{s}") ** 2).sqrt()
    ref = (j.group_by("radar_id", "epoch")
           .agg(((r() - r("_t")) ** 2).sum().alias("s2"), pl.len().alias("n"))
           .filter(pl.col("n") >= 2)
           .with_columns((pl.col("s2") / (pl.col("n") - 1)).sqrt().alias("rmse_range_m"))
           .sort("radar_id", "epoch"))
    assert df.height == ref.height > 100
    assert np.allclose(df["rmse_range_m"].to_numpy(), ref["rmse_range_m"].to_numpy(), rtol=1e-9)
    assert df["n"].to_list() == ref["n"].cast(pl.Int64).to_list()


def test_simulated_reports_match_tables(sim_run):
    with sql_reports.open_read_only(sim_run) as store:
        q = lambda name, **p: sql_reports.run_report(store, name, p)
        metrics, conflicts = store.read("metrics"), store.read("conflicts")
        acc = q("accuracy_by_method", stage="fusion", segment="all")
        ref = metrics.filter((pl.col("stage") == "fusion") & (pl.col("segment") == "all")
                             & (pl.col("metric") == "rmse_pos_m")).sort("value", "method")   # the SQL's order
        assert acc["method"].to_list() == ref["method"].to_list()
        assert acc["rmse_pos_m"].to_list() == ref["value"].to_list()
        tl = q("conflict_timeline")
        ref = conflicts.group_by("method", "epoch").agg(pl.len().alias("pairs"), pl.col("alert").sum().alias("alerts"))
        assert tl.height == ref.height and tl["alerts"].sum() == conflicts["alert"].sum()
        acct = dict(q("row_accounting").iter_rows())
        assert acct["unaccounted"] == 0 and acct["both_aligned_and_rejected"] == 0
        cap = q("capacity_by_method")
        from safety.capacity import CAPACITY_P_STAR, CAPACITY_V_ZO_M3, nmax_seed
        fus = cap.filter(pl.col("stage") == "fusion")
        assert fus.height >= 6
        assert fus["n_max_seed"].to_list() == nmax_seed(fus["sigma_m"].to_numpy(), CAPACITY_P_STAR,
                                                        v_zo=CAPACITY_V_ZO_M3).astype(float).tolist()
        assert fus["n_max_seed"].n_unique() > 1 and fus["p_conflict_sound"].n_unique() == fus.height
        for rep in sql_reports.list_reports():                  # every report runs on a real run
            out = sql_reports.run_report(store, rep)
            cols = rep.description.split("Columns:")[1].split(".")[0]
            assert all(c in cols for c in out.columns), (rep.name, out.columns)
