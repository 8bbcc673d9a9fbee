"""Tracker evaluation: every metric on small hand-built tracks / associations / truth frames."""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from scipy.stats import chi2

from tertiary.schema import TABLES, validate
from tertiary.track_metrics import TrackMetricsConfig, chi2_band, match_tracks, track_truth, tracker_metrics
from tertiary.tracker import TRACK_COLUMNS

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
NO_SKIP = TrackMetricsConfig(skip_first_s=0.0)
LANES = {7: 1000.0, 8: -1000.0}          # truth_id → y of its eastbound lane (100 m/s, z = 500 m)


def _t(s: float) -> datetime:
    return T0 + timedelta(seconds=s)


def _truth(n_s: int = 40, segments: dict[int, str] | None = None) -> pl.DataFrame:
    rows = []
    for tid, y in LANES.items():
        for s in range(n_s + 1):
            rows.append({"truth_id": tid, "time": _t(s), "x_m": 100.0 * s, "y_m": y, "z_m": 500.0,
                         "vx_mps": 100.0, "vy_mps": 0.0, "vz_mps": 0.0,
                         "segment": (segments or {}).get(s, "straight")})
    return pl.DataFrame(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def _true_pos(tid: int, s: float) -> np.ndarray:
    return np.array([100.0 * s, LANES[tid], 500.0, 100.0, 0.0, 0.0])


def _tracks(rows: list[dict], method="aposteriori", filt="singer") -> pl.DataFrame:
    """Track rows from dicts: run, s (epoch seconds), track_id, plot (fused target or None),
    at (truth_id whose position the row sits on), err (6-vector added), var (6), nis."""
    out = []
    for r in rows:
        state = _true_pos(r["at"], r["s"]) + np.asarray(r.get("err", np.zeros(6)), float)
        plot = r.get("plot")
        out.append({
            "run": r.get("run", 0), "epoch": _t(r["s"]), "track_id": r["track_id"], "filter": filt,
            "method": method, **dict(zip(("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"), state.tolist())),
            "cov_diag": list(r.get("var", [1.0] * 6)),
            "innovation": [0.0, 0.0, 0.0] if plot is not None else None,
            "nis": r.get("nis", 3.0) if plot is not None else None,
            "model_probs": None,
            "status": "confirmed" if plot is not None else "coasting",
            "plot_target_id": plot,
        })
    return pl.DataFrame(out, schema=TRACK_COLUMNS)


def _assoc(keys: list[tuple]) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Associations with one report per (run, s, target_id, truth_id or None) and its truth."""
    assoc = pl.DataFrame({
        "run": [k[0] for k in keys], "epoch": [_t(k[1]) for k in keys],
        "radar_id": 1, "local_track_id": 1, "report_id": list(range(len(keys))),
        "target_id": [k[2] for k in keys], "cost": 0.0,
    }).cast(TABLES["associations"].required)
    reports = pl.DataFrame({"run": [k[0] for k in keys], "report_id": list(range(len(keys))),
                            "truth_id": [k[3] for k in keys]},
                           schema={"run": pl.UInt32, "report_id": pl.UInt64, "truth_id": pl.Int64})
    return assoc, reports


def _value(m: pl.DataFrame, metric: str, segment: str = "all") -> float:
    row = m.filter((pl.col("metric") == metric) & (pl.col("segment") == segment))
    assert row.height == 1, (metric, segment, row)
    return row["value"][0]


# --------------------------------------------------------------------------- truth of tracks


def test_track_truth_is_the_plot_truth_carried_while_coasting():
    tracks = _tracks([
        dict(s=0, track_id=1, plot=10, at=7), dict(s=4, track_id=1, plot=None, at=7),
        dict(s=8, track_id=1, plot=11, at=7), dict(s=12, track_id=1, plot=None, at=7),
    ])
    assoc, rep = _assoc([(0, 0, 10, 7), (0, 8, 11, None)])       # second plot is clutter
    tt = track_truth(tracks, assoc, rep).sort("epoch")
    assert tt["truth_id"].to_list() == [7, 7, None, None]
    assert tt["label"].unique().to_list() == ["aposteriori+singer"]


# --------------------------------------------------------------------------- accuracy


def _two_run_rows(err0, err1, var=(1.0,) * 6, seconds=(0, 4, 8), nis=(3.0, 3.0)):
    rows = []
    for run, err, n in ((0, err0, nis[0]), (1, err1, nis[1])):
        rows += [dict(run=run, s=s, track_id=1, plot=10, at=7, err=err, var=var, nis=n) for s in seconds]
    keys = [(run, s, 10, 7) for run in (0, 1) for s in seconds]
    return _tracks(rows), *_assoc(keys)


def test_rmse_uses_n_minus_1_over_runs_per_epoch():
    tracks, assoc, rep = _two_run_rows([3, 0, 0, 1, 0, 0], [4, 0, 0, 0, 2, 0])
    m = tracker_metrics(tracks, assoc, rep, _truth(), NO_SKIP)
    assert _value(m, "rmse_pos_m") == pytest.approx(5.0)                  # (9 + 16)/(2 − 1)
    assert _value(m, "rmse_vel_mps") == pytest.approx(math.sqrt(5.0))     # (1 + 4)/1
    r_true = lambda s: math.hypot(100.0 * s, 1000.0, 500.0)               # noqa: E731
    r_est = lambda s, dx: math.hypot(100.0 * s + dx, 1000.0, 500.0)       # noqa: E731
    per_k = [((r_est(s, 3) - r_true(s)) ** 2 + (r_est(s, 4) - r_true(s)) ** 2) / 1 for s in (0, 4, 8)]
    assert _value(m, "rmse_range_m") == pytest.approx(math.sqrt(np.mean(per_k)))
    assert set(m["stage"]) == {"tracker"}
    assert set(m["method"]) == {"aposteriori+singer"}
    assert _value(m, "rmse_pos_m", "straight") == pytest.approx(5.0)
    assert m.filter(pl.col("segment") == "turn").height == 0
    validate(m, "metrics")


def test_rmse_denominator_n():
    tracks, assoc, rep = _two_run_rows([3, 0, 0, 0, 0, 0], [4, 0, 0, 0, 0, 0])
    m = tracker_metrics(tracks, assoc, rep, _truth(), TrackMetricsConfig(skip_first_s=0.0, denominator="n"))
    assert _value(m, "rmse_pos_m") == pytest.approx(math.sqrt(12.5))


def test_single_run_pools_its_epochs_for_the_n_minus_1_rmse():
    """One track, one run, N_k = 1 at each epoch: the two samples are pooled with the N − 1
    denominator (each σ² = e²·M/(M − 1), M = 2) instead of being dropped."""
    tracks = _tracks([dict(s=s, track_id=1, plot=10, at=7, err=[3, 0, 0, 0, 0, 0]) for s in (0, 4)])
    assoc, rep = _assoc([(0, 0, 10, 7), (0, 4, 10, 7)])
    m = tracker_metrics(tracks, assoc, rep, _truth(), NO_SKIP)
    assert _value(m, "rmse_pos_m") == pytest.approx(math.sqrt(18.0))
    assert _value(m, "rmse_horizontal_m") == pytest.approx(math.sqrt(18.0))
    assert _value(m, "rmse_height_m") == pytest.approx(0.0)
    assert _value(m, "nees_mean") == pytest.approx(9.0)


def test_segments_split_straight_and_turn():
    segments = {s: "turn" for s in range(6, 41)}
    tracks, assoc, rep = _two_run_rows([3, 0, 0, 0, 0, 0], [4, 0, 0, 0, 0, 0], seconds=(0, 4, 8))
    tracks = tracks.with_columns(pl.when(pl.col("epoch") == _t(8)).then(pl.col("x_m") + 1.0)
                                 .otherwise(pl.col("x_m")).alias("x_m"))
    m = tracker_metrics(tracks, assoc, rep, _truth(segments=segments), NO_SKIP)
    assert _value(m, "rmse_pos_m", "straight") == pytest.approx(5.0)
    assert _value(m, "rmse_pos_m", "turn") == pytest.approx(math.sqrt(16 + 25))
    assert _value(m, "rmse_pos_m", "all") == pytest.approx(math.sqrt((25 + 25 + 41) / 3))


def test_transient_after_the_first_epoch_is_skipped():
    tracks, assoc, rep = _two_run_rows([3, 0, 0, 0, 0, 0], [4, 0, 0, 0, 0, 0], seconds=(0, 4, 8, 12))
    tracks = tracks.with_columns(pl.when(pl.col("epoch") < _t(8)).then(pl.col("x_m") + 100.0)
                                 .otherwise(pl.col("x_m")).alias("x_m"))
    m = tracker_metrics(tracks, assoc, rep, _truth(), TrackMetricsConfig(skip_first_s=8.0))
    assert _value(m, "rmse_pos_m") == pytest.approx(5.0)


# --------------------------------------------------------------------------- consistency


def test_potential_accuracy_and_nees():
    var = (1.0, 4.0, 4.0, 1.0, 1.0, 1.0)                   # sqrt(1 + 4 + 4) = 3
    tracks, assoc, rep = _two_run_rows([1, 2, 0, 0, 0, 0], [0, 0, 4, 0, 0, 0], var=var)
    m = tracker_metrics(tracks, assoc, rep, _truth(), NO_SKIP)
    assert _value(m, "potential_pos_m") == pytest.approx(3.0)
    # run 0: 1/1 + 4/4 = 2; run 1: 16/4 = 4
    assert _value(m, "nees_mean") == pytest.approx(3.0)
    # each run's NEES is constant over its 3 epochs: the 6 samples are worth 2 independent ones
    # (τ = 1 + 2 (4/6 + 2/6) = 3), so the band of the mean is χ²(3·2)/2, not χ²(3·6)/6
    assert _value(m, "nees_n_eff") == pytest.approx(2.0)
    lo, hi = _value(m, "nees_band_lo"), _value(m, "nees_band_hi")
    assert lo == pytest.approx(chi2.ppf(0.025, 6) / 2) and hi == pytest.approx(chi2.ppf(0.975, 6) / 2)
    # per epoch: the mean of N_k = 2 runs, (2 + 4)/2 = 3, is inside χ²(6)/2 at every epoch
    assert _value(m, "nees_in_band_frac") == pytest.approx(1.0)


def test_nis_mean_ignores_coasting_rows():
    tracks, assoc, rep = _two_run_rows([0] * 6, [0] * 6, nis=(2.0, 5.0))
    coast = _tracks([dict(run=0, s=12, track_id=1, plot=None, at=7)])
    m = tracker_metrics(pl.concat([tracks, coast]), assoc, rep, _truth(), NO_SKIP)
    assert _value(m, "nis_mean") == pytest.approx(3.5)
    # constant per run over 3 updated epochs: 2 effective samples (coasting rows have no NIS)
    assert (_value(m, "nis_band_lo"), _value(m, "nis_band_hi")) == pytest.approx(chi2_band(2, 3))
    assert _value(m, "nis_n_eff") == pytest.approx(2.0)


def test_chi2_band_narrows_with_samples():
    lo1, hi1 = chi2_band(10, 3)
    lo2, hi2 = chi2_band(1000, 3)
    assert lo1 < lo2 < 3.0 < hi2 < hi1
    assert all(math.isnan(v) for v in chi2_band(0, 3))


# --------------------------------------------------------------------------- continuity


def test_completeness_breaks_swaps_spurious():
    # aircraft 7 observed (fused target 10) at 0..36 s; aircraft 8 (target 20) at 0..12 s;
    # clutter target 30 at 20..28 s
    keys = ([(0, s, 10, 7) for s in range(0, 40, 4)] + [(0, s, 20, 8) for s in range(0, 16, 4)]
            + [(0, s, 30, None) for s in (20, 24, 28)])
    assoc, rep = _assoc(keys)
    rows = (
        # track 1 covers aircraft 7 at 8, 12 (coasting at 16 carries 7), stops
        [dict(s=8, track_id=1, plot=10, at=7), dict(s=12, track_id=1, plot=10, at=7),
         dict(s=16, track_id=1, plot=None, at=7)]
        # gap at 20 → track 2 covers 7 from 24 on: one break (gap and new id count once)
        + [dict(s=s, track_id=2, plot=10, at=7) for s in (24, 28, 32, 36)]
        # track 3 follows aircraft 8 at 4, 8, then jumps to aircraft 7's plot at 20: a swap
        + [dict(s=4, track_id=3, plot=20, at=8), dict(s=8, track_id=3, plot=20, at=8),
           dict(s=20, track_id=3, plot=10, at=7)]
        # track 4 lives on clutter only: spurious
        + [dict(s=s, track_id=4, plot=30, at=8) for s in (20, 24, 28)]
    )
    m = tracker_metrics(_tracks(rows), assoc, rep, _truth(), NO_SKIP)
    # aircraft-epochs: 7 → 10 (0..36), 8 → 4 (0..12) = 14
    # covered: 7 at 8, 12, 16, 20 (track 3), 24, 28, 32, 36 = 8; 8 at 4, 8 = 2
    assert _value(m, "completeness") == pytest.approx(10 / 14)
    # aircraft 7: 8, 12, 16 (id 1) → 20 (id 3: id change) → 24 (id 2: id change) = 2 breaks
    assert _value(m, "breaks") == 2
    assert _value(m, "swaps") == 1
    assert _value(m, "spurious_tracks") == 1
    assert _value(m, "tracks") == 4


def test_break_on_coverage_gap_with_the_same_id():
    keys = [(0, s, 10, 7) for s in range(0, 24, 4)]
    assoc, rep = _assoc(keys)
    # covered at 0, 4, uncovered at 8, 12 (the track exists but on a clutter plot), covered 16, 20
    rows = ([dict(s=s, track_id=1, plot=10, at=7) for s in (0, 4)]
            + [dict(s=s, track_id=1, plot=99, at=7) for s in (8, 12)]
            + [dict(s=s, track_id=1, plot=10, at=7) for s in (16, 20)])
    m = tracker_metrics(_tracks(rows), assoc, rep, _truth(), NO_SKIP)
    assert _value(m, "breaks") == 1
    assert _value(m, "swaps") == 0                 # clutter rows have no truth: not a swap
    assert _value(m, "completeness") == pytest.approx(4 / 6)
    assert _value(m, "spurious_tracks") == 0


def test_duplicate_tracks_cover_with_the_oldest_id():
    keys = [(0, s, 10, 7) for s in range(0, 16, 4)] + [(0, s, 11, 7) for s in (4, 8)]
    assoc, rep = _assoc(keys)
    rows = ([dict(s=s, track_id=1, plot=10, at=7) for s in range(0, 16, 4)]
            + [dict(s=s, track_id=2, plot=11, at=7) for s in (4, 8)])
    m = tracker_metrics(_tracks(rows), assoc, rep, _truth(), NO_SKIP)
    assert _value(m, "breaks") == 0
    assert _value(m, "completeness") == 1.0


def test_runs_and_labels_are_separate():
    keys = [(run, s, 10, 7) for run in (0, 1) for s in range(0, 16, 4)]
    assoc, rep = _assoc(keys)
    rows0 = [dict(run=0, s=s, track_id=1, plot=10, at=7) for s in range(0, 16, 4)]
    rows1 = [dict(run=1, s=s, track_id=1, plot=10, at=7) for s in (0, 4)]
    a = _tracks(rows0 + rows1)
    b = _tracks(rows0, method="arithmetic", filt="cv")
    m = tracker_metrics(pl.concat([a, b]), assoc, rep, _truth(), NO_SKIP)
    assert set(m["method"]) == {"aposteriori+singer", "arithmetic+cv"}
    ma = m.filter(pl.col("method") == "aposteriori+singer")
    mb = m.filter(pl.col("method") == "arithmetic+cv")
    assert _value(ma, "completeness") == pytest.approx(6 / 8)
    assert _value(mb, "completeness") == pytest.approx(4 / 8)      # run 1 has no track at all
    assert _value(ma, "tracks") == 2 and _value(ma, "breaks") == 0
    assert ma["n_runs"].max() == 2 and mb["n_runs"].max() == 1


def test_empty_tracks_give_empty_metrics():
    assoc, rep = _assoc([(0, 0, 10, 7)])
    m = tracker_metrics(pl.DataFrame(schema=TRACK_COLUMNS), assoc, rep, _truth())
    assert m.height == 0 and m.schema == pl.Schema(TABLES["metrics"].required)


def test_match_tracks_columns():
    tracks, assoc, rep = _two_run_rows([3, 0, 0, 0, 0, 0], [4, 0, 0, 0, 0, 0])
    mt = match_tracks(tracks, assoc, rep, _truth(), NO_SKIP)
    assert mt.height == 6
    assert {"truth_id", "true_x_m", "e2_pos", "nees_pos", "sd_pos", "seg_class"} <= set(mt.columns)


# --------------------------------------------------------------------------- end to end


def test_end_to_end_on_a_small_terminal_area(small_terminal):
    """Simulated terminal area (30 aircraft, 10 min) → pipeline → tracker → metrics: the air
    picture is nearly complete, with few extra, spurious or swapped tracks."""
    from tertiary.filters import make_filter
    from tertiary.pipeline import PipelineConfig, process
    from tertiary.tracker import track

    res = process(small_terminal, PipelineConfig(methods=("aposteriori",), filters=(), centralized=False))
    fused = res.fused.filter(pl.col("method") == "aposteriori")
    tracks = track(fused, make_filter("singer"))
    validate(tracks, "tracks")
    report_truth = small_terminal.reports.select("run", "report_id", "truth_id")
    m = tracker_metrics(tracks, res.associations, report_truth, small_terminal.truth)
    validate(m, "metrics")
    assert set(m["method"]) == {"aposteriori+singer"}
    n_aircraft = small_terminal.truth["truth_id"].n_unique()
    assert _value(m, "completeness") > 0.95
    assert _value(m, "tracks") <= 1.5 * n_aircraft
    assert _value(m, "swaps") <= 0.2 * n_aircraft
    assert _value(m, "spurious_tracks") <= 0.2 * n_aircraft
    assert _value(m, "rmse_pos_m") < 500.0
