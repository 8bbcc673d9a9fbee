"""Seed metrics of a matched picture: hand-computable real accuracy ((2.15)/(4.84)),
consistency, continuity; and the association stage's report-label metrics."""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from scipy.stats import chi2

from tertiary.evaluation.accuracy import (AccuracyConfig, accuracy_by_epoch_from_matched, accuracy_from_matched, picture_accuracy, scored_rows)
from tertiary.evaluation.association import association_metrics
from tertiary.evaluation.matching import match_to_reference
from tertiary.contract import TABLES, validate

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
NO_SKIP = AccuracyConfig(skip_first_s=0.0)


def _matched(fused: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """The one matcher on a fused-style picture (id column target_id)."""
    return match_to_reference(fused, truth, id_col="target_id").rename({"target_id": "track_id"})


def accuracy(fused: pl.DataFrame, truth: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig()) -> pl.DataFrame:
    return accuracy_from_matched(scored_rows(_matched(fused, truth), cfg), cfg)


def accuracy_by_epoch(fused: pl.DataFrame, truth: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig()) -> pl.DataFrame:
    return accuracy_by_epoch_from_matched(scored_rows(_matched(fused, truth), cfg), cfg)


def _t(s: float) -> datetime:
    return T0 + timedelta(seconds=s)


def _truth(n_s: int = 10, segments: dict[int, str] | None = None, truth_id: int = 7) -> pl.DataFrame:
    """One aircraft flying east at 100 m/s along y = 1000 m, z = 500 m, sampled every 1 s."""
    t = np.arange(n_s + 1, dtype=float)
    seg = [(segments or {}).get(int(k), "straight") for k in t]
    return pl.DataFrame({
        "truth_id": truth_id, "time": [_t(s) for s in t],
        "x_m": 100.0 * t, "y_m": 1000.0, "z_m": 500.0,
        "vx_mps": 100.0, "vy_mps": 0.0, "vz_mps": 0.0, "segment": seg,
    }).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def _fused(truth: pl.DataFrame, offsets: dict[int, tuple[float, ...]], method: str = "m",
           target_id: int = 1, epochs=None) -> pl.DataFrame:
    """Fused rows = truth + a constant per-run offset (dx, dy, dz, dvx, dvy, dvz)."""
    rows = []
    for run, off in offsets.items():
        off = tuple(off) + (0.0,) * (6 - len(off))
        for r in truth.iter_rows(named=True):
            if epochs is not None and (r["time"] - T0).total_seconds() not in epochs:
                continue
            rows.append({"run": run, "epoch": r["time"], "target_id": target_id, "method": method,
                         **{c: r[c] + o for c, o in zip(("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"), off)}})
    return pl.DataFrame(rows).with_columns(pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64),
                                           pl.col("epoch").cast(pl.Datetime("us", "UTC")))


def _assoc(fused: pl.DataFrame, truth_of=lambda run, epoch, target: 7) -> tuple[pl.DataFrame, pl.DataFrame]:
    """One report per (run, epoch, target) whose truth is ``truth_of(...)``."""
    keys = fused.select("run", "epoch", "target_id").unique().sort("run", "epoch", "target_id")
    assoc = keys.with_columns(
        pl.lit(1, pl.UInt32).alias("radar_id"), pl.lit(1, pl.UInt32).alias("local_track_id"),
        pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"), pl.lit(0.0).alias("cost"))
    tid = [truth_of(r, e, t) for r, e, t in keys.iter_rows()]
    reports = assoc.select("run", "report_id", pl.Series("truth_id", tid, dtype=pl.Int64))
    return assoc.select(list(TABLES["associations"].required)), reports


def _value(metrics: pl.DataFrame, metric: str, segment: str = "all", method: str = "m") -> float:
    row = metrics.filter((pl.col("metric") == metric) & (pl.col("segment") == segment) & (pl.col("method") == method))
    assert row.height == 1, (metric, segment, method, row)
    return row["value"].item()


def test_constant_offsets_give_hand_rmse_with_n_minus_1():
    truth = _truth()
    fused = _fused(truth, {0: (1.0, 0, 0, 0.5), 1: (2.0, 0, 0, 0.5), 2: (3.0, 0, 0, 0.5)})
    m = accuracy(fused, truth, NO_SKIP)
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt((1 + 4 + 9) / 2))
    assert _value(m, "rmse_y_m") == pytest.approx(0.0)
    assert _value(m, "rmse_pos_m") == pytest.approx(math.sqrt(7.0))
    assert _value(m, "rmse_vel_mps") == pytest.approx(math.sqrt(3 * 0.25 / 2))
    assert m["n_runs"].unique().to_list() == [3]
    mn = accuracy(fused, truth, AccuracyConfig(skip_first_s=0.0, denominator="n"))
    assert _value(mn, "rmse_x_m") == pytest.approx(math.sqrt(14 / 3))
    assert m.schema == pl.Schema(TABLES["metrics"].required)
    validate(m, "metrics")


def test_pooled_is_root_of_mean_per_epoch_square():
    """σ²(k) differs per epoch: the pooled value is sqrt(mean_k σ²(k))."""
    truth = _truth(3)
    fused = _fused(truth, {0: (0.0,), 1: (2.0,)})
    fused = fused.with_columns(pl.when(pl.col("epoch") == _t(0)).then(pl.col("x_m") + 4.0 * pl.col("run").cast(pl.Float64))
                               .otherwise(pl.col("x_m")).alias("x_m"))
    # epoch 0: errors 0 and 6 → σ² = 36; epochs 1..3: errors 0 and 2 → σ² = 4
    m = accuracy(fused, truth, NO_SKIP)
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt((36 + 3 * 4) / 4))
    by = accuracy_by_epoch(fused, truth, NO_SKIP).filter(pl.col("metric") == "rmse_x_m")
    assert by["value"].to_list() == pytest.approx([6.0, 2.0, 2.0, 2.0])
    assert by["n_runs"].to_list() == [2, 2, 2, 2]
    assert by.columns == ["method", "epoch", "metric", "value", "n_runs", "n", "pooled"]
    assert by["n"].to_list() == [2, 2, 2, 2] and not by["pooled"].any()


def test_one_aircraft_one_run_pools_epochs_instead_of_dropping_them():
    """N_k = 1 at every epoch: the epochs are pooled into one (2.15) sample, never an empty table.
    Hand computation: errors (dx, dy, dz) = (3, 4, 12), (0, 0, 0), (6, 8, 0), (0, 0, 5) at t = 0..3;
    M = 4 samples, denominator M − 1 = 3."""
    truth = _truth(3)
    errs = [(3.0, 4.0, 12.0), (0.0, 0.0, 0.0), (6.0, 8.0, 0.0), (0.0, 0.0, 5.0)]
    fused = _fused(truth, {0: (0.0,)})
    fused = fused.with_columns(*[pl.col(c) + pl.Series([e[i] for e in errs]) for i, c in enumerate(("x_m", "y_m", "z_m"))])
    m = accuracy(fused, truth, NO_SKIP)
    assert not m.is_empty()
    assert _value(m, "rmse_horizontal_m") == pytest.approx(math.sqrt((25 + 0 + 100 + 0) / 3))
    assert _value(m, "rmse_height_m") == pytest.approx(math.sqrt((144 + 0 + 0 + 25) / 3))
    assert _value(m, "rmse_pos_m") == pytest.approx(math.sqrt((169 + 0 + 100 + 25) / 3))
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt((9 + 36) / 3))
    by = accuracy_by_epoch(fused, truth, NO_SKIP)
    h = by.filter(pl.col("metric") == "rmse_horizontal_m")
    # each pooled epoch: |e_k| · sqrt(M / (M − 1)); the mean of their squares is the pool's (2.15)
    assert h["value"].to_list() == pytest.approx([5.0 * math.sqrt(4 / 3), 0.0, 10.0 * math.sqrt(4 / 3), 0.0])
    assert h["pooled"].all() and h["n"].to_list() == [1, 1, 1, 1]
    assert by.filter(pl.col("metric") == "rmse_height_m")["value"].to_list() == pytest.approx(
        [12.0 * math.sqrt(4 / 3), 0.0, 0.0, 5.0 * math.sqrt(4 / 3)])
    mn = accuracy(fused, truth, AccuracyConfig(skip_first_s=0.0, denominator="n"))
    assert _value(mn, "rmse_horizontal_m") == pytest.approx(math.sqrt(125 / 4))
    # a single sample in all has no N − 1 estimate at all
    one = fused.head(1)
    assert accuracy(one, truth, NO_SKIP).is_empty()


def test_thin_epochs_pool_beside_well_sampled_ones():
    """Two runs at t = 0..2, one run only at t = 3: epoch 3 (N_k = 1) is pooled alone — M = 1 —
    so it is dropped; with two thin epochs (t = 3, 4) it is pooled with M = 2."""
    truth = _truth(4)
    both = _fused(truth, {0: (1.0,), 1: (3.0,)}, epochs={0.0, 1.0, 2.0})
    thin = _fused(truth, {0: (2.0,)}, epochs={3.0})
    fused = pl.concat([both, thin])
    by = accuracy_by_epoch(fused, truth, NO_SKIP).filter(pl.col("metric") == "rmse_x_m")
    assert by["value"].to_list() == pytest.approx([math.sqrt(10.0)] * 3)
    thin2 = pl.concat([thin, _fused(truth, {1: (4.0,)}, epochs={4.0})])
    fused2 = pl.concat([both, thin2])
    by2 = accuracy_by_epoch(fused2, truth, NO_SKIP).filter(pl.col("metric") == "rmse_x_m")
    assert by2["pooled"].to_list() == [False, False, False, True, True]
    assert by2["value"].to_list()[3:] == pytest.approx([2.0 * math.sqrt(2.0), 4.0 * math.sqrt(2.0)])
    m = accuracy(fused2, truth, NO_SKIP)
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt((3 * 10.0 + 8.0 + 32.0) / 5))


def test_horizontal_and_height_split_the_3d_error():
    """3 runs with offsets (dx, dy, dz): horizontal² + height² = 3-D², each by hand."""
    truth = _truth()
    fused = _fused(truth, {0: (3.0, 4.0, 1.0), 1: (0.0, 0.0, 2.0), 2: (6.0, 8.0, -3.0)})
    m = accuracy(fused, truth, NO_SKIP)
    h, v, p = (_value(m, k) for k in ("rmse_horizontal_m", "rmse_height_m", "rmse_pos_m"))
    assert h == pytest.approx(math.sqrt((25 + 0 + 100) / 2))
    assert v == pytest.approx(math.sqrt((1 + 4 + 9) / 2))
    assert h * h + v * v == pytest.approx(p * p)
    assert _value(m, "rmse_height_m") == pytest.approx(_value(m, "rmse_z_m"))


def test_skip_first_seconds_per_target():
    truth = _truth(30)
    fused = _fused(truth, {0: (1.0,), 1: (3.0,)})
    # a large error during the first 20 s only
    fused = fused.with_columns(pl.when(pl.col("epoch") < _t(20)).then(pl.col("x_m") + 1000.0)
                               .otherwise(pl.col("x_m")).alias("x_m"))
    m = accuracy(fused, truth)            # default skip 20 s
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt(10 / 1))
    by = accuracy_by_epoch(fused, truth)
    assert by["epoch"].min() == _t(20)


def test_segment_split_and_hold_only_in_all():
    segs = {k: "turn" for k in (3, 4)} | {k: "hold" for k in (5, 6)} | {7: "climb"}
    truth = _truth(8, segs)
    fused = _fused(truth, {0: (1.0,), 1: (3.0,)})
    # straight epochs: error (1, 3); turn epochs: (1+9, 3+9); hold epochs: (1+20, 3+20)
    bump = (pl.when(pl.col("epoch").is_in([_t(3), _t(4)])).then(9.0)
            .when(pl.col("epoch").is_in([_t(5), _t(6)])).then(20.0).otherwise(0.0))
    fused = fused.with_columns((pl.col("x_m") + bump).alias("x_m"))
    m = accuracy(fused, truth, NO_SKIP)
    straight = (1 + 9) / 1
    turn = (10**2 + 12**2) / 1
    hold = (21**2 + 23**2) / 1
    assert _value(m, "rmse_x_m", "straight") == pytest.approx(math.sqrt(straight))
    assert _value(m, "rmse_x_m", "turn") == pytest.approx(math.sqrt(turn))
    assert _value(m, "rmse_x_m", "all") == pytest.approx(math.sqrt((5 * straight + 2 * turn + 2 * hold) / 9))
    assert set(m["segment"]) == {"all", "straight", "turn"}
    # a dataset without turns has no turn rows
    m2 = accuracy(fused.filter(~pl.col("epoch").is_in([_t(3), _t(4)])), truth, NO_SKIP)
    assert set(m2["segment"]) == {"all", "straight"}


def test_range_error_is_from_the_system_origin():
    """A pure cross-range error leaves the range almost unchanged; a radial error does not."""
    truth = _truth(2)
    # radial offset: scale the position by (1 + ε) → range error ε|p|
    fused = _fused(truth, {0: (0.0,), 1: (0.0,)})
    eps = {0: 0.001, 1: -0.002}
    for c in ("x_m", "y_m", "z_m"):
        fused = fused.with_columns((pl.col(c) * (1 + pl.col("run").replace_strict(eps, return_dtype=pl.Float64))).alias(c))
    m = accuracy(fused, truth, NO_SKIP)
    rng = np.hypot(np.hypot(100.0 * np.arange(3), 1000.0), 500.0)
    expected = np.sqrt(np.mean([(0.001 * r) ** 2 + (0.002 * r) ** 2 for r in rng]))
    assert _value(m, "rmse_range_m") == pytest.approx(expected, rel=1e-9)
    assert _value(m, "rmse_pos_m") == pytest.approx(expected, rel=1e-9)
    # a pure cross-range (x) error of ±10 m at x = 0 changes the range only to second order
    truth0 = _truth(0)                                  # one epoch, p = (0, 1000, 500)
    fused_x = _fused(truth0, {0: (10.0,), 1: (-10.0,)})
    m = accuracy(fused_x, truth0, NO_SKIP)
    r0 = math.hypot(1000.0, 500.0)
    dr = math.hypot(10.0, r0) - r0                      # ≈ 0.045 m for both runs
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt(200.0))
    assert _value(m, "rmse_range_m") == pytest.approx(math.sqrt(2 * dr * dr), rel=1e-6)


def test_truth_is_interpolated_between_samples():
    truth = _truth(4)
    fused = _fused(truth, {0: (1.0,), 1: (-1.0,)}).with_columns(
        (pl.col("epoch") + pl.duration(milliseconds=500)).alias("epoch"),
        (pl.col("x_m") + 50.0).alias("x_m"))           # truth moves 50 m in 0.5 s
    fused = fused.filter(pl.col("epoch") < _t(4))      # the last half-second is outside truth
    matched = scored_rows(_matched(fused, truth), NO_SKIP)
    assert matched.height == 8
    np.testing.assert_allclose(matched["true_x_m"].to_numpy(), matched["x_m"].to_numpy() - np.where(
        matched["run"].to_numpy() == 0, 1.0, -1.0))
    assert _value(accuracy(fused, truth, NO_SKIP), "rmse_x_m") == pytest.approx(math.sqrt(2.0))


def test_methods_are_scored_separately():
    truth = _truth(4)
    fused = pl.concat([_fused(truth, {0: (1.0,), 1: (-1.0,)}, method="a"),
                       _fused(truth, {0: (5.0,), 1: (-5.0,)}, method="b")])
    m = accuracy(fused, truth, NO_SKIP)
    assert _value(m, "rmse_x_m", method="a") == pytest.approx(math.sqrt(2.0))
    assert _value(m, "rmse_x_m", method="b") == pytest.approx(math.sqrt(50.0))


def test_clutter_targets_are_not_scored():
    """A second target 800–900 m off the aircraft: the one-to-one matcher gives the aircraft to
    the close target; the other is unmatched and is not an accuracy sample."""
    truth = _truth(4)
    fused = _fused(truth, {0: (1.0,), 1: (-1.0,)})
    fused = pl.concat([fused, _fused(truth, {0: (900.0,), 1: (800.0,)}, target_id=2)])
    assoc, reports = _assoc(fused, truth_of=lambda r, e, t: 7 if t == 1 else None)
    m = accuracy(fused, truth, NO_SKIP)
    assert _value(m, "rmse_x_m") == pytest.approx(math.sqrt(2.0))
    a = association_metrics(assoc, reports)
    assert _value(a, "false_targets", method="assignment") == 2.0       # one per run


def test_random_case_matches_numpy_oracle():
    """Two aircraft, 6 runs, missing samples: pooled = sqrt(mean_k Σ_j e² / (N_k − 1))."""
    rng = np.random.default_rng(5)
    truths = pl.concat([_truth(12, truth_id=7), _truth(12, truth_id=8).with_columns(pl.col("y_m") + 5000.0)])
    rows, errs = [], {}
    for run in range(6):
        for tid, target in ((7, 1), (8, 2)):
            for k in range(13):
                if rng.random() < 0.2:
                    continue
                e = rng.normal(0, 30, 6)
                tr = truths.filter((pl.col("truth_id") == tid) & (pl.col("time") == _t(k))).row(0, named=True)
                rows.append({"run": run, "epoch": _t(k), "target_id": target, "method": "m",
                             **{c: tr[c] + e[i] for i, c in enumerate(("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"))}})
                errs.setdefault(k, []).append(e)
    fused = pl.DataFrame(rows).with_columns(pl.col("run").cast(pl.UInt32), pl.col("target_id").cast(pl.UInt64),
                                            pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    assoc, reports = _assoc(fused, truth_of=lambda r, e, t: 7 if t == 1 else 8)
    m = accuracy(fused, truths, NO_SKIP)
    per_k = [np.stack(v) for v in errs.values() if len(v) > 1]
    expect_pos = np.sqrt(np.mean([np.sum(e[:, :3] ** 2) / (len(e) - 1) for e in per_k]))
    expect_vel = np.sqrt(np.mean([np.sum(e[:, 3:] ** 2) / (len(e) - 1) for e in per_k]))
    expect_y = np.sqrt(np.mean([np.sum(e[:, 1] ** 2) / (len(e) - 1) for e in per_k]))
    assert _value(m, "rmse_pos_m") == pytest.approx(expect_pos, rel=1e-12)
    assert _value(m, "rmse_vel_mps") == pytest.approx(expect_vel, rel=1e-12)
    assert _value(m, "rmse_y_m") == pytest.approx(expect_y, rel=1e-12)


# --------------------------------------------------------------------------- association


def _assoc_rows(rows):
    """rows: (run, epoch_s, target_id, report_truth_id or None) → associations, reports."""
    df = pl.DataFrame(rows, schema=["run", "epoch", "target_id", "truth_id"], orient="row")
    df = df.with_columns(pl.col("epoch").map_elements(_t, return_dtype=pl.Datetime("us", "UTC")),
                         pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"),
                         pl.lit(1, pl.UInt32).alias("radar_id"), pl.lit(1, pl.UInt32).alias("local_track_id"),
                         pl.lit(0.0).alias("cost"))
    assoc = df.select(list(TABLES["associations"].required)).cast(TABLES["associations"].required)
    return assoc, df.select("report_id", pl.col("truth_id").cast(pl.Int64))


def test_majority_truth_and_swap_count():
    rows = [
        # target 1: truth 10, 10, then 20 (with one dissenting 10 report at epoch 2), then 20
        (0, 0, 1, 10), (0, 1, 1, 10), (0, 1, 1, 10), (0, 2, 1, 20), (0, 2, 1, 20), (0, 2, 1, 10), (0, 3, 1, 20),
        # target 2: clean truth 20 then 10 at epoch 3 — but only clutter at epoch 2
        (0, 0, 2, 20), (0, 1, 2, 20), (0, 2, 2, None), (0, 3, 2, 20),
    ]
    assoc, reports = _assoc_rows(rows)
    a = association_metrics(assoc, reports)
    assert _value(a, "swaps", method="assignment") == 1.0
    # 10 reports with a truth; wrong: the dissenting 10 at epoch 2 of target 1, and at epoch 3
    # truth 20 is split over targets 1 and 2, so one of its two reports is not on its main
    # target (the stricter rule of the erring-radar work) → 8/10
    assert _value(a, "assoc_correct_frac", method="assignment") == pytest.approx(8 / 10)
    # truth 10 got target 1; truth 20 got targets 1 and 2 → mean 1.5
    assert _value(a, "targets_per_truth", method="assignment") == pytest.approx(1.5)
    assert _value(a, "false_targets", method="assignment") == 0.0
    assert a["n_runs"].to_list() == [1] * 6          # + split_targets, merged_targets
    validate(a, "metrics")


def test_confirmed_targets_per_truth_leaves_out_targets_never_confirmed():
    """An aircraft whose stray plot started a tentative target that never confirmed has one
    target a controller sees, not two; an aircraft only ever in tentative targets has none."""
    rows = [(0, k, 1, 10) for k in range(4)] + [(0, 2, 7, 10)]          # aircraft 10: target 1, stray target 7
    rows += [(0, k, 2, 20) for k in range(4)] + [(0, k, 3, 20) for k in (2, 3)]    # aircraft 20: targets 2 and 3
    rows += [(0, 0, 9, 30)]                                               # aircraft 30: a tentative target only
    assoc, reports = _assoc_rows(rows)
    confirmed = pl.DataFrame({"run": [0, 0, 0], "target_id": [1, 2, 3]})
    a = association_metrics(assoc, reports, confirmed)
    assert _value(a, "targets_per_truth", method="assignment") == pytest.approx((2 + 2 + 1) / 3)
    assert _value(a, "confirmed_targets_per_truth", method="assignment") == pytest.approx((1 + 2 + 0) / 3)
    assert "confirmed_targets_per_truth" not in association_metrics(assoc, reports)["metric"].to_list()
    validate(a, "metrics")


def test_swaps_sum_over_runs_and_ignore_null_pairs():
    rows = [(r, k, 5, tid) for r in (0, 1) for k, tid in enumerate([1, 2, 2, 1])]      # 2 swaps per run
    rows += [(0, k, 6, tid) for k, tid in enumerate([3, None, 4])]                      # no non-null pair
    assoc, reports = _assoc_rows(rows)
    a = association_metrics(assoc, reports)
    assert _value(a, "swaps", method="assignment") == 4.0
    assert _value(a, "assoc_correct_frac", method="assignment") == 1.0


def test_tie_goes_to_smallest_truth_id():
    """Epoch 0 ties 9 and 4 → 4; epoch 1 is 4: no swap (a tie going to 9 would make one)."""
    assoc, reports = _assoc_rows([(0, 0, 1, 9), (0, 0, 1, 4), (0, 1, 1, 4)])
    assert _value(association_metrics(assoc, reports), "swaps", method="assignment") == 0.0
    assoc, reports = _assoc_rows([(0, 0, 1, 9), (0, 0, 1, 4), (0, 1, 1, 9)])
    assert _value(association_metrics(assoc, reports), "swaps", method="assignment") == 1.0


def _association_oracle(rows) -> dict[str, float]:
    """The association metrics by brute force over (run, epoch, target_id, truth_id) rows."""
    from collections import Counter, defaultdict
    votes, by_target, real = defaultdict(Counter), defaultdict(list), [r for r in rows if r[3] is not None]
    for run, k, tgt, tid in real:
        votes[run, k, tgt][tid] += 1
    maj = {key: min(c, key=lambda t: (-c[t], t)) for key, c in votes.items()}
    for run, k, tgt, _ in rows:
        by_target[run, tgt].append(k)
    swaps = 0
    for (run, tgt), ks in by_target.items():
        seq = [maj.get((run, k, tgt)) for k in sorted(set(ks))]
        swaps += sum(a is not None and b is not None and a != b for a, b in zip(seq, seq[1:]))
    held = defaultdict(Counter)
    for run, k, tgt, tid in real:
        held[run, k, tid][tgt] += 1
    principal = {key: min(c, key=lambda t: (-c[t], t)) for key, c in held.items()}
    correct = sum(maj.get((run, k, tgt)) == tid and principal[run, k, tid] == tgt for run, k, tgt, tid in real)
    truths = {(run, tid) for run, _, _, tid in real}
    targets = defaultdict(set)
    for (run, k, tgt), tid in maj.items():
        targets[run, tid].add(tgt)
    clutter = {(r[0], r[2]) for r in rows} - {(r[0], r[2]) for r in real}
    return {"assoc_correct_frac": correct / len(real), "swaps": swaps,
            "targets_per_truth": float(np.mean([len(targets[t]) for t in truths])), "false_targets": len(clutter),
            "split_targets": sum(len(c) > 1 for c in held.values()),
            "merged_targets": sum(len({tid for run2, k2, tgt2, tid in real if (run2, k2, tgt2) == key}) > 1
                                  for key in votes)}


def _random_association_rows(seed: int) -> list[tuple]:
    """(run, epoch index, target, truth_id or None) of association rows over 40 epochs and two
    runs: targets change aircraft now and then, some reports are clutter or another aircraft's;
    target 9 has a real report at epoch 3 only, target 10 never (one false target per run)."""
    rng = np.random.default_rng(seed)
    rows, flies = [], {}
    for run in (0, 1):
        for k in range(40):
            for tgt in range(1, 9):
                if rng.random() < 0.1:
                    continue
                if (run, tgt) not in flies or rng.random() < 0.08:
                    flies[run, tgt] = int(rng.integers(1, 6))
                for _ in range(int(rng.integers(1, 4))):
                    u = rng.random()
                    rows.append((run, k, tgt, flies[run, tgt] if u < 0.7 else int(rng.integers(1, 6)) if u < 0.85
                                 else None))
    return rows + [(run, k, tgt, 2 if (tgt, k) == (9, 3) else None)
                   for run in (0, 1) for k in range(40) for tgt in (9, 10)]


@pytest.mark.parametrize("cuts", [(), (7,), (1, 2, 3, 20, 21), tuple(range(1, 40))])
def test_association_metrics_scored_window_by_window_equal_the_whole_run(cuts):
    """evaluation accumulators: the association metrics of rows scored a block of
    epochs at a time (:func:`score_associations`, the pipeline's windows) equal those of the
    whole run at once, and a brute-force count. Targets change aircraft across the cuts and
    some epochs are clutter only. Fails if a target's majority aircraft is not carried to the
    next window (swaps), a target's reports are judged per window (false targets), or a
    target's aircraft are counted per window (targets per aircraft)."""
    from tertiary.evaluation.association import AssociationScore, association_score, score_associations
    rows = _random_association_rows(11)
    assoc, reports = _assoc_rows(rows)
    whole = association_metrics(assoc, reports)
    state, t = AssociationScore(), assoc["epoch"]
    for lo, hi in zip((0, *cuts), (*cuts, 40)):
        block = assoc.filter((t >= _t(lo)) & (t < _t(hi)))
        state = score_associations(state, block, reports)
    from polars.testing import assert_frame_equal
    assert_frame_equal(association_score(state), whole)
    want = _association_oracle(rows)
    for name, value in want.items():
        assert _value(whole, name, method="assignment") == pytest.approx(value, rel=1e-12), name
    assert want["swaps"] > 5 and want["false_targets"] == 2 and want["split_targets"] > 0


@pytest.mark.parametrize("cuts", [(7,), (1, 2, 3, 20, 21), tuple(range(1, 40))])
def test_association_scores_of_time_slices_merge_to_the_whole_run(cuts):
    """A distributed run scores each time slice apart, with its own target ids: the slices'
    states, relabelled to the run's ids and merged in time order
    (:func:`merge_association_scores`), give the whole run's metrics. Fails if a swap across a
    slice boundary is lost, a target of two slices is counted twice (targets per aircraft,
    false targets) or a slice's ids are not relabelled."""
    from tertiary.evaluation.association import (AssociationScore, association_score, merge_association_scores,
                                              relabel_association_score, score_associations)
    rows = _random_association_rows(5)
    assoc, reports = _assoc_rows(rows)
    whole = association_metrics(assoc, reports)
    t, merged = assoc["epoch"], None
    for i, (lo, hi) in enumerate(zip((0, *cuts), (*cuts, 40))):
        # each slice numbers its targets its own way: id + 1000 * (slice + 1)
        block = assoc.filter((t >= _t(lo)) & (t < _t(hi)))
        local = block.with_columns(pl.col("target_id") + 1000 * (i + 1))
        state = score_associations(AssociationScore(), local, reports)
        ids = local.select(pl.col("target_id").alias("old"), block["target_id"].alias("new")).unique()
        state = relabel_association_score(state, ids)
        merged = state if merged is None else merge_association_scores(merged, state)
    from polars.testing import assert_frame_equal
    assert_frame_equal(association_score(merged), whole)
    assert _value(whole, "swaps", method="assignment") > 5


def test_picture_accuracy_is_one_stage_in_the_metrics_schema():
    truth = _truth(4)
    fused = _fused(truth, {0: (1.0,), 1: (-1.0,), 2: (0.0,)})
    m, by, samples = picture_accuracy(_matched(fused, truth), "fusion", NO_SKIP)
    assert m.schema == pl.Schema(TABLES["metrics"].required)
    assert set(m["stage"]) == {"fusion"}
    assert m["n_runs"].unique().to_list() == [3]
    assert _value(m, "rmse_x_m") == pytest.approx(1.0)             # (1 + 1 + 0)/(3 − 1)
    assert by.height and samples.height == 15
    validate(m, "metrics")


# --------------------------------------------------------------------------- consistency

from tertiary.evaluation.consistency import chi2_band, consistency_metrics, integrated_autocorrelation  # noqa: E402


def _kf_nees(runs: int, epochs: int, r_scale: float = 1.0, seed: int = 5) -> pl.DataFrame:
    """A linear simulation (1 target per run, 3 independent CV axes, white-noise acceleration)
    and a Kalman filter that believes the measurement variance is ``r_scale`` × the true one:
    rows (method, run, epoch, target_id, seg_class, nees_pos) of its position NEES (3 dof)."""
    rng = np.random.default_rng(seed)
    q, r = 1.0, 400.0
    phi = np.array([[1.0, 1.0], [0.0, 1.0]])
    qq = q * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    x = np.zeros((runs, 3, 2))
    xe = x + rng.normal(0, 1, x.shape) * np.sqrt([r, 100.0])       # the prior draw
    pe = np.diag([r, 100.0]) * np.ones((3, 1, 1))
    nees = np.empty((epochs, runs))
    for k in range(epochs):
        if k:
            x = x @ phi.T + rng.multivariate_normal([0, 0], qq, (runs, 3))
            xe, pe = xe @ phi.T, phi @ pe @ phi.T + qq
        z = x[..., 0] + rng.normal(0, np.sqrt(r), (runs, 3))
        s = pe[:, 0, 0] + r * r_scale
        gain = pe[:, :, 0] / s[:, None]                            # (3, 2)
        xe = xe + gain[None] * (z - xe[..., 0])[..., None]
        pe = pe - gain[:, :, None] * pe[:, None, 0, :]
        e = xe[..., 0] - x[..., 0]
        nees[k] = (e ** 2 / pe[None, :, 0, 0]).sum(axis=1)
    epoch = pl.Series(np.repeat(np.arange(epochs), runs) * 1_000_000 + 1_600_000_000_000_000).cast(
        pl.Datetime("us", "UTC"))
    return pl.DataFrame({"method": "kf", "run": np.tile(np.arange(runs), epochs), "epoch": epoch,
                         "track_id": 1, "seg_class": None, "nees_pos": nees.reshape(-1)},
                        schema_overrides={"seg_class": pl.String})


def _cvalue(m: pl.DataFrame, metric: str) -> float:
    return m.filter((pl.col("metric") == metric) & (pl.col("segment") == "all"))["value"].item()


def test_consistent_kalman_filter_is_inside_the_monte_carlo_band():
    """NEES averaged over N = 50 runs at each epoch vs χ²(3N)/N: a consistent filter is inside
    on ~95 % of epochs; one whose covariance is 2x too small or too large is not."""
    m = consistency_metrics(_kf_nees(50, 120), "nees_pos", 3, "nees", "fusion")
    assert _cvalue(m, "nees_in_band_frac") >= 0.9
    assert _cvalue(m, "nees_band_lo") < _cvalue(m, "nees_mean") < _cvalue(m, "nees_band_hi")
    over = consistency_metrics(_kf_nees(50, 120, r_scale=0.3), "nees_pos", 3, "nees", "fusion")
    assert _cvalue(over, "nees_in_band_frac") < 0.5 and _cvalue(over, "nees_mean") > 4.0
    under = consistency_metrics(_kf_nees(50, 120, r_scale=4.0), "nees_pos", 3, "nees", "fusion")
    assert _cvalue(under, "nees_in_band_frac") < 0.5


def test_single_run_band_uses_the_effective_sample_size():
    """One run: the band of the mean comes from n/τ, wider than the naive χ²(3n)/n that treats
    the autocorrelated NEES as independent; a consistent filter's mean is inside it."""
    rows = _kf_nees(1, 3000, seed=11).filter(pl.col("epoch") >= pl.col("epoch").min() + pl.duration(seconds=30))
    m = consistency_metrics(rows, "nees_pos", 3, "nees", "fusion")
    n = rows.height
    naive = chi2_band(n, 3)
    lo, hi = _cvalue(m, "nees_band_lo"), _cvalue(m, "nees_band_hi")
    assert _cvalue(m, "nees_n_eff") < 0.8 * n
    assert lo < naive[0] and hi > naive[1]
    assert lo < _cvalue(m, "nees_mean") < hi
    # N_k = 1 at every epoch: the χ²(3) 95 % interval of one sample holds ~95 % of epochs
    assert 0.9 <= _cvalue(m, "nees_in_band_frac") <= 0.99


def test_integrated_autocorrelation_of_an_ar1_sequence():
    """AR(1) with coefficient φ: τ = (1 + φ)/(1 − φ) (3 for φ = 0.5); independent: 1; series
    boundaries are respected (two halves of one independent draw are not correlated)."""
    rng = np.random.default_rng(2)
    n, phi = 200_000, 0.5
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    assert integrated_autocorrelation(x, np.zeros(n, int)) == pytest.approx(3.0, rel=0.05)
    assert integrated_autocorrelation(e, np.zeros(n, int)) == pytest.approx(1.0, abs=0.03)
    # each value repeated in its own series of two: correlated only within a series
    pairs = np.repeat(e[:50_000], 2)
    assert integrated_autocorrelation(pairs, np.repeat(np.arange(50_000), 2)) == pytest.approx(2.0, rel=0.05)


def test_chi2_band_vectorised_and_for_a_fractional_sample_size():
    lo, hi = chi2_band(np.array([1, 10, 0]), 3)
    assert lo[0] == pytest.approx(chi2.ppf(0.025, 3)) and hi[1] == pytest.approx(chi2.ppf(0.975, 30) / 10)
    assert np.isnan(lo[2]) and np.isnan(hi[2])
    a, b = chi2_band(12.5, 3)
    assert a < 3 < b


# --------------------------------------------------------------------------- tracker pictures
# Track rows sit on an aircraft's lane (or on lane 9, where no aircraft flies: a false track);
# which aircraft a row is comes from the matcher's geometry only.

from tertiary.stages.tracking.tracker import TRACK_COLUMNS  # noqa: E402

LANES = {7: 1000.0, 8: -1000.0, 9: 30_000.0}      # truth_id → y of an eastbound lane (100 m/s)


def _lanes_truth(n_s: int = 40) -> pl.DataFrame:
    rows = [{"truth_id": tid, "time": _t(s), "x_m": 100.0 * s, "y_m": y, "z_m": 500.0, "vx_mps": 100.0,
             "vy_mps": 0.0, "vz_mps": 0.0, "segment": "straight"}
            for tid, y in LANES.items() if tid != 9 for s in range(n_s + 1)]
    return pl.DataFrame(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def _track_rows(rows: list[dict], method: str = "aposteriori+singer") -> pl.DataFrame:
    """rows: run, s, track_id, at (lane), err (6), var (6 diagonal), nis (None: coasting)."""
    out = []
    for r in rows:
        state = np.array([100.0 * r["s"], LANES[r["at"]], 500.0, 100.0, 0.0, 0.0]) + np.asarray(r.get("err", [0.0] * 6))
        out.append({"run": r.get("run", 0), "epoch": _t(r["s"]), "track_id": r["track_id"], "filter": "f",
                    "method": "m", **dict(zip(("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"), state.tolist())),
                    "cov_diag": list(r.get("var", [1.0] * 6)), "innovation": None, "nis": r.get("nis", 3.0),
                    "model_probs": None, "status": "confirmed", "plot_target_id": None})
    return pl.DataFrame(out, schema=TRACK_COLUMNS).drop("filter").with_columns(pl.lit(method).alias("method"))


def _observed(keys: list[tuple]) -> pl.DataFrame:
    """(run, s, truth_id) aircraft-epochs the picture should cover."""
    return pl.DataFrame({"run": [k[0] for k in keys], "epoch": [_t(k[1]) for k in keys],
                         "truth_id": [k[2] for k in keys]}).with_columns(
        pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(pl.Datetime("us", "UTC")), pl.col("truth_id").cast(pl.Int64))


def _tracker(rows: list[dict] | pl.DataFrame, observed=None, cfg=NO_SKIP) -> pl.DataFrame:
    tracks = rows if isinstance(rows, pl.DataFrame) else _track_rows(rows)
    return picture_accuracy(match_to_reference(tracks, _lanes_truth()), "tracker", cfg, observed)[0]


def _tv(m: pl.DataFrame, metric: str, segment: str = "all") -> float:
    row = m.filter((pl.col("metric") == metric) & (pl.col("segment") == segment))
    assert row.height == 1, (metric, segment, row)
    return row["value"][0]


def _two_runs(err0, err1, var=(1.0,) * 6, seconds=(0, 4, 8), nis=(3.0, 3.0)) -> list[dict]:
    return [dict(run=run, s=s, track_id=1, at=7, err=err, var=var, nis=n)
            for run, err, n in ((0, err0, nis[0]), (1, err1, nis[1])) for s in seconds]


def test_tracker_rmse_uses_n_minus_1_over_runs_per_epoch():
    m = _tracker(_two_runs([3, 0, 0, 1, 0, 0], [4, 0, 0, 0, 2, 0]))
    assert _tv(m, "rmse_pos_m") == pytest.approx(5.0)                  # (9 + 16)/(2 − 1)
    assert _tv(m, "rmse_vel_mps") == pytest.approx(math.sqrt(5.0))     # (1 + 4)/1
    assert set(m["stage"]) == {"tracker"}


def test_potential_accuracy_and_diagonal_nees():
    var = (1.0, 4.0, 4.0, 1.0, 1.0, 1.0)                   # sqrt(1 + 4 + 4) = 3
    m = _tracker(_two_runs([1, 2, 0, 0, 0, 0], [0, 0, 4, 0, 0, 0], var=var))
    assert _tv(m, "potential_pos_m") == pytest.approx(3.0)
    assert _tv(m, "nees_mean") == pytest.approx(3.0)       # run 0: 1/1 + 4/4 = 2; run 1: 16/4 = 4
    # each run's NEES is constant over its 3 epochs: 6 samples worth 2 independent ones
    assert _tv(m, "nees_n_eff") == pytest.approx(2.0)
    lo, hi = _tv(m, "nees_band_lo"), _tv(m, "nees_band_hi")
    assert lo == pytest.approx(chi2.ppf(0.025, 6) / 2) and hi == pytest.approx(chi2.ppf(0.975, 6) / 2)
    assert _tv(m, "nees_in_band_frac") == pytest.approx(1.0)


def test_nis_mean_ignores_coasting_rows():
    rows = _two_runs([0] * 6, [0] * 6, nis=(2.0, 5.0)) + [dict(run=0, s=12, track_id=1, at=7, nis=None)]
    m = _tracker(rows)
    assert _tv(m, "nis_mean") == pytest.approx(3.5)
    assert _tv(m, "nis_n_eff") == pytest.approx(2.0)


def test_completeness_breaks_swaps_spurious():
    observed = _observed([(0, s, 7) for s in range(0, 40, 4)] + [(0, s, 8) for s in range(0, 16, 4)])
    rows = (
        # track 1 covers aircraft 7 at 8, 12, 16, stops
        [dict(s=s, track_id=1, at=7) for s in (8, 12, 16)]
        # gap at 20 (taken by track 3) → track 2 covers 7 from 24 on
        + [dict(s=s, track_id=2, at=7) for s in (24, 28, 32, 36)]
        # track 3 follows aircraft 8 at 4, 8, then sits on aircraft 7 at 20: a swap
        + [dict(s=4, track_id=3, at=8), dict(s=8, track_id=3, at=8), dict(s=20, track_id=3, at=7)]
        # track 4 lies where no aircraft flies: spurious
        + [dict(s=s, track_id=4, at=9) for s in (20, 24, 28)]
    )
    m = _tracker(rows, observed)
    # aircraft-epochs 10 + 4 = 14; covered: 7 at 8..36 (8 epochs), 8 at 4, 8
    assert _tv(m, "completeness") == pytest.approx(10 / 14)
    assert _tv(m, "breaks") == 2                  # 7: id 1 → 3 at 20 → 2 at 24
    assert _tv(m, "swaps") == 1
    assert _tv(m, "spurious_tracks") == 1
    assert _tv(m, "tracks") == 4


def test_break_on_coverage_gap_with_the_same_id():
    observed = _observed([(0, s, 7) for s in range(0, 24, 4)])
    rows = ([dict(s=s, track_id=1, at=7) for s in (0, 4)] + [dict(s=s, track_id=1, at=9) for s in (8, 12)]
            + [dict(s=s, track_id=1, at=7) for s in (16, 20)])
    m = _tracker(rows, observed)
    assert _tv(m, "breaks") == 1
    assert _tv(m, "swaps") == 0                   # unmatched rows have no aircraft: not a swap
    assert _tv(m, "completeness") == pytest.approx(4 / 6)
    assert _tv(m, "spurious_tracks") == 0


def test_a_duplicate_track_is_unmatched_but_represents_its_aircraft():
    """Two tracks on one aircraft: the closer one is matched; the other is not a second match
    (continuity is untouched) but the matcher still says which aircraft it shows, so alert
    scoring sees a duplicate, not a second aircraft."""
    observed = _observed([(0, s, 7) for s in range(0, 16, 4)])
    rows = ([dict(s=s, track_id=1, at=7) for s in range(0, 16, 4)]
            + [dict(s=s, track_id=2, at=7, err=[40.0, 0, 0, 0, 0, 0]) for s in (4, 8)])
    tracks = _track_rows(rows)
    m = _tracker(tracks, observed)
    assert _tv(m, "breaks") == 0 and _tv(m, "completeness") == 1.0
    matched = match_to_reference(tracks, _lanes_truth())
    dup = matched.filter(pl.col("track_id") == 2)
    assert dup["truth_id"].null_count() == 2 and dup["gated_truth_id"].to_list() == [7, 7]
    assert matched.filter(pl.col("track_id") == 1)["truth_id"].to_list() == [7] * 4


def test_runs_and_pictures_are_separate():
    observed = _observed([(run, s, 7) for run in (0, 1) for s in range(0, 16, 4)])
    rows0 = [dict(run=0, s=s, track_id=1, at=7) for s in range(0, 16, 4)]
    rows1 = [dict(run=1, s=s, track_id=1, at=7) for s in (0, 4)]
    both = pl.concat([_track_rows(rows0 + rows1), _track_rows(rows0, method="arithmetic+cv")])
    m = _tracker(both, observed)
    ma, mb = (m.filter(pl.col("method") == k) for k in ("aposteriori+singer", "arithmetic+cv"))
    assert _tv(ma, "completeness") == pytest.approx(6 / 8)
    assert _tv(mb, "completeness") == pytest.approx(4 / 8)      # run 1 has no track at all
    assert _tv(ma, "tracks") == 2 and _tv(ma, "breaks") == 0


def test_empty_picture_gives_empty_metrics():
    m, by, samples = picture_accuracy(match_to_reference(_track_rows([]), _lanes_truth()), "tracker")
    assert m.height == 0 and m.schema == pl.Schema(TABLES["metrics"].required)
    assert by.height == 0 and samples.height == 0


def test_end_to_end_on_a_small_terminal_area(small_terminal):
    """Simulated terminal area → pipeline → tracker picture scored by the one evaluation stage:
    the picture is nearly complete, with few extra, spurious or swapped tracks."""
    from tertiary.evaluation.evaluate import evaluate_pictures
    from tertiary.filters import make_filter
    from tertiary.pipeline import PipelineConfig, process
    from tertiary.stages.tracking.tracker import track

    res = process(small_terminal, PipelineConfig(methods=("aposteriori",), filters=(), centralized=False))
    fused = res.fused.filter(pl.col("method") == "aposteriori")
    tracks = track(fused, make_filter("singer"))
    validate(tracks, "tracks")
    pictures = tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method")).drop("filter")
    m = evaluate_pictures(pictures, small_terminal.truth).metrics.filter(pl.col("stage") == "tracker")
    validate(m, "metrics")
    assert set(m["method"]) == {"aposteriori+singer"}
    n_aircraft = small_terminal.truth["truth_id"].n_unique()
    assert _tv(m, "completeness") > 0.9
    assert _tv(m, "tracks") <= 1.5 * n_aircraft
    assert _tv(m, "swaps") <= 0.2 * n_aircraft
    assert _tv(m, "spurious_tracks") <= 0.2 * n_aircraft
    assert _tv(m, "rmse_pos_m") < 500.0


def test_a_singular_full_covariance_blanks_only_its_own_nees():
    """The 6-state NEES of a row whose full covariance is singular is NaN (its position NEES
    stays); every other row of the same block keeps eᵀ P⁻¹ e. Before, one singular row made
    the whole 131 072-row block NaN, so the result depended on how rows were blocked."""
    from tertiary.evaluation.consistency import add_nees
    rng = np.random.default_rng(5)
    n = 6
    a = rng.normal(size=(n, 6, 6))
    p = a @ a.swapaxes(1, 2) + np.eye(6)
    p[3] = 0.0
    p[3, :3, :3] = 4.0 * np.eye(3)                     # velocity block zero: singular 6×6
    est = rng.normal(size=(n, 6))
    cols = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
    frame = pl.DataFrame({**{c: est[:, k] for k, c in enumerate(cols)},
                          **{f"true_{c}": np.zeros(n) for c in cols}})
    got = add_nees(frame, pl.Series("cov", p.reshape(n, 36), dtype=pl.Array(pl.Float64, 36)))
    nees, nees_pos = got["nees"].to_numpy(), got["nees_pos"].to_numpy()
    full = [est[i] @ np.linalg.solve(p[i], est[i]) for i in range(n) if i != 3]
    assert np.isnan(nees[3]) and nees_pos[3] == pytest.approx(est[3, :3] @ est[3, :3] / 4.0)
    np.testing.assert_allclose(np.delete(nees, 3), full, rtol=1e-10)


def test_an_aircraft_is_scored_from_its_first_reported_epoch():
    """A track matched to an aircraft before any sensor reported it is another object's inside
    the gate, not an estimate of it: those rows are no accuracy sample, in one piece or in
    buckets. Fails when ``observed`` does not cut the scored rows."""
    from tertiary.evaluation.accuracy_buckets import picture_accuracy_buckets
    rows = [dict(run=r, s=s, track_id=1, at=7, err=[e, 0, 0, 0, 0, 0])
            for r in (0, 1) for s, e in ((0, 900.0), (4, 900.0), (8, 3.0), (12, 3.0))]
    observed = _observed([(r, s, 7) for r in (0, 1) for s in (8, 12)])
    m = _tracker(rows, observed)
    assert _tv(m, "rmse_pos_m") == pytest.approx(math.sqrt(18.0))      # (9 + 9)/(2 − 1) at 8 and 12
    matched = match_to_reference(_track_rows(rows), _lanes_truth())
    _, by_epoch, samples = picture_accuracy(matched, "tracker", NO_SKIP, observed)
    assert sorted(samples["epoch"].unique().to_list()) == [_t(8), _t(12)]
    assert by_epoch["epoch"].min() == _t(8)
    buckets = picture_accuracy_buckets(matched.lazy(), "tracker", NO_SKIP, observed, buckets=2)[0]
    assert _tv(buckets, "rmse_pos_m") == pytest.approx(math.sqrt(18.0))
    # without the reports' epochs every matched row is scored, as for a picture judged alone
    assert _tv(_tracker(rows), "rmse_pos_m") > 600.0
