"""picture_accuracy_buckets: the seed metrics of a matched picture read in buckets of whole
tracks / aircraft are those of picture_accuracy on the whole picture (same rows, order, types;
values to round-off), and no bucket reads much more than its share of the rows."""

from __future__ import annotations

import math
import tempfile
from unittest import mock
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.evaluation import buckets as B
from tertiary.evaluation.accuracy import (ROW_SCORES, AccuracyConfig, picture_accuracy, row_scores)
from tertiary.evaluation.accuracy_buckets import picture_accuracy_buckets

# rows whose full covariance is null: the reference's determinant check sees NaN (it skips them)
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered in det:RuntimeWarning")

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
SEGMENTS = ["straight", "climb", "descent", "turn", "hold", None]
BUCKETS = (1, 2, 3, 7)
CFGS = (AccuracyConfig(), AccuracyConfig(skip_first_s=0.0), AccuracyConfig(skip_first_s=8.0, denominator="n"))


def _assert_same(got: tuple[pl.DataFrame, ...], want: tuple[pl.DataFrame, ...]) -> None:
    for g, w in zip(got, want, strict=True):
        assert_frame_equal(g, w, check_exact=False, rel_tol=1e-9, abs_tol=1e-12)


def _check(matched: pl.DataFrame, observed: pl.DataFrame | None, cfg: AccuracyConfig,
           buckets=BUCKETS) -> tuple[pl.DataFrame, ...]:
    want = picture_accuracy(matched, "tracker", cfg, observed)
    for b in buckets:
        _assert_same(picture_accuracy_buckets(matched.lazy(), "tracker", cfg, observed, buckets=b), want)
        # the rows filed by bucket once (in slices of 37 rows: the slices' order kept in a bucket)
        with tempfile.TemporaryDirectory() as tmp, mock.patch.object(B, "FILE_SLICE_ROWS", 37):
            _assert_same(picture_accuracy_buckets(matched.lazy(), "tracker", cfg, observed, buckets=b,
                                                  scratch=Path(tmp)), want)
    return want



# --------------------------------------------------------------------------- hand-built pictures


def _aircraft(rng: np.random.Generator, n: int, epochs: int) -> dict[int, tuple[int, int]]:
    """truth_id → (first, last) epoch index it is alive."""
    out = {}
    for tid in range(1, n + 1):
        a = int(rng.integers(0, epochs // 2))
        out[tid] = (a, int(rng.integers(a + 3, epochs)))
    return out


def _track_rows(rng: np.random.Generator, method: str, run: int, tid: int, tracks: dict,
                epochs: int, cov: str) -> list[dict]:
    """One track's rows: AR(1) errors (correlated NEES), following ``tracks[tid]`` = list of
    (aircraft or None, first, last) legs: a swap when two legs have two aircraft, a spurious
    track when every leg is None; a row now and then left unmatched."""
    rows, e = [], rng.normal(0, 30.0, 6)
    for truth, a, b in tracks[tid]:
        for k in range(a, b + 1):
            e = 0.7 * e + rng.normal(0, 20.0, 6)
            true = np.array([1000.0 * (truth or 0) + 100.0 * k, 500.0 * run, 3000.0, 100.0, 0.0, 0.0])
            matched = truth is not None and rng.random() > 0.05
            row = {"run": run, "epoch": T0 + timedelta(seconds=4 * k), "track_id": tid, "method": method,
                   **dict(zip(STATE, (true + e).tolist())),
                   "truth_id": truth if matched else None, "gated_truth_id": truth,
                   **{f"true_{c}": (v if matched else None) for c, v in zip(STATE, true.tolist())},
                   "segment": SEGMENTS[int(rng.integers(len(SEGMENTS)))] if matched else None,
                   "nis": float(rng.chisquare(3)) if rng.random() > 0.1 else None}
            sd = rng.uniform(10.0, 40.0, 6)
            if cov == "cov":
                m = rng.normal(size=(6, 6))
                p = np.diag(sd ** 2) + 50.0 * m @ m.T
                row["cov"] = p.ravel().tolist() if rng.random() > 0.1 else None
                row["cov_diag"] = (sd ** 2).tolist()
            elif cov == "cov_diag":
                row["cov_diag"] = (sd ** 2).tolist() if rng.random() > 0.1 else None
            rows.append(row)
    return rows


def _legs(rng: np.random.Generator, alive: dict[int, tuple[int, int]], n_tracks: int, run: int) -> dict[int, list]:
    """track id → legs: most follow one aircraft, some swap to another, some are spurious, one
    lone track runs past every aircraft (epochs with a single sample: pooled under n − 1)."""
    legs, ids = {}, list(alive)
    for tid in range(1, n_tracks + 1):
        kind = rng.random()
        a = ids[int(rng.integers(len(ids)))]
        lo, hi = alive[a]
        if kind < 0.15:
            s = int(rng.integers(0, 20))
            legs[tid] = [(None, s, s + int(rng.integers(1, 8)))]
        elif kind < 0.4 and hi - lo > 4:
            b = ids[int(rng.integers(len(ids)))]
            mid = (lo + hi) // 2
            legs[tid] = [(a, lo, mid), (b, mid + 1, max(mid + 1, alive[b][1]))]
        else:
            legs[tid] = [(a, lo + int(rng.integers(0, 2)), hi)]
    legs[n_tracks + 1] = [(ids[0], 40 + 10 * run, 46 + 10 * run)]
    return legs


def _hand_picture(seed: int, cov: str = "cov", nis: bool = True, methods=("a", "b"),
                  runs=(0, 1)) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(matched rows, observed aircraft-epochs) of several methods and runs."""
    rng = np.random.default_rng(seed)
    rows, observed = [], []
    for run in runs:
        alive = _aircraft(rng, 9, 36)
        observed += [(run, k, tid) for tid, (a, b) in alive.items() for k in range(a, b + 1) if rng.random() > 0.1]
        observed.append((run, 3, 99))                        # an aircraft no picture sees
        for method in methods:
            legs = _legs(rng, alive, 14, run)
            for tid in legs:
                rows += _track_rows(rng, method, run, tid, legs, 36, cov)
    schema = {"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "track_id": pl.UInt64, "method": pl.String,
              **{c: pl.Float64 for c in STATE}, "truth_id": pl.Int64, "gated_truth_id": pl.Int64,
              **{f"true_{c}": pl.Float64 for c in STATE}, "segment": pl.String, "nis": pl.Float64}
    if cov == "cov":
        schema |= {"cov": pl.Array(pl.Float64, 36), "cov_diag": pl.Array(pl.Float64, 6)}
    elif cov == "cov_diag":
        schema["cov_diag"] = pl.Array(pl.Float64, 6)
    matched = pl.DataFrame(rows, schema=schema).sort("run", "epoch", "method", "track_id")
    if not nis:
        matched = matched.drop("nis")
    obs = pl.DataFrame({"run": [o[0] for o in observed],
                        "epoch": [T0 + timedelta(seconds=4 * o[1]) for o in observed],
                        "truth_id": [o[2] for o in observed]},
                       schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "truth_id": pl.Int64})
    return matched, obs


@pytest.mark.parametrize("cov", ["cov", "cov_diag", "none"])
@pytest.mark.parametrize("scored", [False, True], ids=["raw", "row_scored"])
def test_hand_pictures_equal_the_whole_picture(cov, scored):
    """Two methods, two runs, swaps, spurious tracks, thin epochs, straight/turn segments; the
    full covariance, its diagonal or none; with and without the row scores carried."""
    matched, observed = _hand_picture(3, cov)
    if scored:
        matched = row_scores(matched)
    for cfg in CFGS:
        metrics, by_epoch, samples = _check(matched, observed, cfg)
        names = set(metrics["metric"])
        assert {"completeness", "breaks", "swaps", "spurious_tracks", "rmse_pos_m", "nis_mean"} <= names
        assert ("nees_band_lo" in names) == (cov != "none") and ("nees6_mean" in names) == (cov == "cov")
        assert set(metrics["method"]) == {"a", "b"} and set(metrics["segment"]) == {"all", "straight", "turn"}
        assert metrics.filter(pl.col("metric") == "swaps")["value"].min() > 0
        assert metrics.filter(pl.col("metric") == "spurious_tracks")["value"].min() > 0
        if cfg.denominator == "n-1":
            assert by_epoch["pooled"].any() and not by_epoch["pooled"].all()
    assert samples["run"].n_unique() == 2
    _check(matched, None, AccuracyConfig())


def test_without_observed_or_nis():
    matched, _ = _hand_picture(4, "cov", nis=False)
    metrics = _check(matched, None, AccuracyConfig())[0]
    assert "completeness" not in set(metrics["metric"]) and "nis_mean" not in set(metrics["metric"])


def test_one_method_one_run_and_more_buckets_than_tracks():
    matched, observed = _hand_picture(5, "cov_diag", methods=("a",), runs=(0,))
    n_tracks = matched.select("method", "run", "track_id").n_unique()
    for cfg in CFGS:
        _check(matched, observed, cfg, buckets=(1, n_tracks + 5, 4 * n_tracks))


def test_edge_pictures():
    """Empty picture; only spurious tracks (no scored row); a single track."""
    matched, observed = _hand_picture(6, "cov")
    _check(matched.clear(), observed, AccuracyConfig())
    _check(matched.clear(), None, AccuracyConfig())
    spurious = matched.with_columns(pl.lit(None, pl.Int64).alias("truth_id"))
    metrics, by_epoch, samples = _check(spurious, observed, AccuracyConfig())
    assert by_epoch.is_empty() and samples.is_empty() and set(metrics["metric"]) >= {"completeness", "tracks"}
    one = matched.filter((pl.col("track_id") == 1) & (pl.col("run") == 0) & (pl.col("method") == "a"))
    _check(one, observed, AccuracyConfig(skip_first_s=0.0))
    _check(matched, observed.clear(), AccuracyConfig())


def test_observed_may_be_lazy_and_buckets_must_be_positive():
    matched, observed = _hand_picture(7, "cov")
    want = picture_accuracy(matched, "tracker", AccuracyConfig(), observed)
    _assert_same(picture_accuracy_buckets(matched.lazy(), "tracker", AccuracyConfig(), observed.lazy(), buckets=3),
                 want)
    with pytest.raises(ValueError):
        picture_accuracy_buckets(matched.lazy(), "tracker", buckets=0)


# --------------------------------------------------------------------------- a simulated picture


@pytest.fixture(scope="module")
def terminal_picture(small_terminal):
    """A tracker picture of the small simulated terminal area, matched and row-scored as the
    evaluation stage does it (one block: match_with_reference then row_scores), and observed =
    the reference aircraft at its epochs. The "plots" are the radars' measured plots in the
    system frame with their covariance and Mode C height, epochs on a 4 s grid, radars 1/3 and
    2/4 as two runs; two pictures: the singer and cv filters."""
    from tertiary.filters import make_filter
    from tertiary.stages.fusion import measured_plots
    from tertiary.evaluation.matching import MatchConfig, match_with_reference, reference_identity
    from tertiary.stages.tracking.tracker import track_methods

    ds = small_terminal
    plots = ds.reports.select("run", "report_id", "radar_id", "time", "altitude_m").join(
        measured_plots(ds.reports, ds.radars, ds.origin), on=["run", "report_id"])
    xyz = ("plot_x_m", "plot_y_m", "plot_z_m")
    plots = plots.filter(pl.all_horizontal(pl.col(c).is_finite() for c in (*xyz, "altitude_m")))
    cov = np.zeros((plots.height, 6, 6))
    cov[:, :3, :3] = plots["plot_cov"].to_numpy().reshape(-1, 3, 3)
    cov[:, [3, 4, 5], [3, 4, 5]] = 100.0 ** 2
    plots = plots.select(
        (pl.col("radar_id") % 2).cast(pl.UInt32).alias("run"), pl.col("time").dt.truncate("4s").alias("epoch"),
        pl.col("report_id").alias("target_id"), pl.lit("radar").alias("method"),
        *(pl.col(p).alias(c) for p, c in zip(xyz, STATE)),
        *(pl.lit(0.0).alias(c) for c in STATE[3:]),
        pl.Series("cov", cov.reshape(-1, 36), dtype=pl.Array(pl.Float64, 36)),
        # the vertical channel: the report's height (the matcher gates on it), a rough variance
        pl.col("altitude_m").alias("alt_m"), pl.lit(0.0).alias("alt_rate_mps"), pl.lit(900.0).alias("alt_var_m2"),
        pl.lit(0.0).alias("alt_cov_m2ps"), pl.lit(25.0).alias("alt_rate_var_m2ps2"))
    tracks = track_methods(plots, {f: make_filter(f) for f in ("singer", "cv")})
    tracks = tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method")).drop("filter")
    matched, ref = match_with_reference(tracks, ds.truth, MatchConfig(), "track_id", reference_identity(ds.truth))
    return matched, ref.select("run", "epoch", "truth_id")


def test_simulated_picture_equals_the_whole_picture(terminal_picture):
    raw, observed = terminal_picture
    scored = row_scores(raw)
    assert raw["truth_id"].null_count() > 0 and raw.select("method", "run", "track_id").n_unique() > 60
    for cfg in CFGS:
        want = _check(scored, observed, cfg)
        assert {"nees_n_eff", "nees6_mean", "nis_band_hi", "completeness"} <= set(want[0]["metric"])
    # not yet row-scored: each bucket is (cov consumed per bucket)
    _check(raw, observed, AccuracyConfig(), buckets=(3,))
    _check(scored, None, AccuracyConfig(), buckets=(2,))


def test_consistency_band_uses_cross_bucket_lag_sums(terminal_picture):
    """The NEES autocorrelation time comes from long correlated series whose pairs are spread
    over every bucket: n_eff well below n, and equal to the whole picture's."""
    raw, observed = terminal_picture
    want = picture_accuracy(row_scores(raw), "tracker", AccuracyConfig(), observed)[0]
    got = picture_accuracy_buckets(row_scores(raw).lazy(), "tracker", AccuracyConfig(), observed, buckets=5)[0]
    pick = (pl.col("metric") == "nees_n_eff") & (pl.col("segment") == "all")
    n = row_scores(raw).filter(pl.col("truth_id").is_not_null() & pl.col("nees_pos").is_finite()).height
    assert want.filter(pick)["value"].max() < 0.5 * n
    assert_frame_equal(got.filter(pick), want.filter(pick), check_exact=False, rel_tol=1e-9, abs_tol=1e-12)


# --------------------------------------------------------------------------- per bucket


def _balanced_picture(n_aircraft: int = 300, epochs: int = 40) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Many short tracks on many aircraft (hash-balanced buckets), every row scored."""
    rng = np.random.default_rng(11)
    n = n_aircraft * epochs
    truth = np.repeat(np.arange(n_aircraft), epochs)
    k = np.tile(np.arange(epochs), n_aircraft)
    track = truth * 2 + (k >= epochs // 2)                  # two tracks per aircraft
    err = rng.normal(0, 30.0, (n, 6))
    frame = pl.DataFrame({
        "run": np.zeros(n, np.uint32), "epoch": [T0 + timedelta(seconds=4 * int(j)) for j in k],
        "track_id": track.astype(np.uint64), "method": "m", "truth_id": truth.astype(np.int64),
        **{c: err[:, i] + 100.0 * i for i, c in enumerate(STATE)},
        **{f"true_{c}": np.full(n, 100.0 * i) for i, c in enumerate(STATE)},
        "segment": np.where(k % 3 == 0, "turn", "straight"), "nis": rng.chisquare(3, n),
        "cov_diag": np.full((n, 6), 900.0)}).with_columns(pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    return frame, frame.select("run", "epoch", "truth_id")


def test_each_collect_reads_about_one_bucket_of_rows(tmp_path: Path, monkeypatch):
    """Every collect that reads the picture's (or observed's) Parquet file returns at most
    1.5 × its share of the rows: the whole picture is never collected (observed is aggregated
    once whole, to one row per aircraft)."""
    matched, observed = _balanced_picture()
    mp, op = tmp_path / "matched.parquet", tmp_path / "observed.parquet"
    matched.write_parquet(mp)
    observed.write_parquet(op)
    seen: list[tuple[str, int]] = []
    collect = pl.LazyFrame.collect

    def counting(self, *args, **kwargs):
        out = collect(self, *args, **kwargs)
        plan = self.explain(optimized=False)
        seen.extend((name, out.height) for name in (mp.name, op.name) if name in plan)
        return out

    buckets = 8
    monkeypatch.setattr(pl.LazyFrame, "collect", counting)
    got = picture_accuracy_buckets(pl.scan_parquet(mp), "tracker", AccuracyConfig(), pl.scan_parquet(op),
                                   buckets=buckets)
    monkeypatch.undo()
    share = {mp.name: math.ceil(matched.height / buckets), op.name: math.ceil(observed.height / buckets)}
    assert sum(1 for name, _ in seen if name == mp.name) >= buckets
    # observed: once per bucket by the coverage walk, and once whole for each aircraft's first
    # reported epoch, an aggregate of one row per aircraft (bounded by the check below)
    assert sum(1 for name, _ in seen if name == op.name) == buckets + 1
    for name, height in seen:
        assert height <= 1.5 * share[name], (name, height, share[name])
    _assert_same(got, picture_accuracy(matched, "tracker", AccuracyConfig(), observed))


def test_row_scores_columns_are_what_the_buckets_read():
    """The bucketed path reads a picture's columns by name: a row-scored picture needs all of
    ROW_SCORES (else it is row-scored per bucket)."""
    matched, observed = _hand_picture(8, "cov")
    partial = row_scores(matched).drop(ROW_SCORES[-1])      # not all scores: scored again
    _check(partial, observed, AccuracyConfig(), buckets=(2,))


def test_filing_by_bucket_refuses_a_slice_read_short(tmp_path: Path):
    """Every slice's rows are filed, in order, and a slice that files fewer rows than it was
    given (its input changed under it) stops the filing instead of scoring a part of it."""
    lf = pl.LazyFrame({"k": np.arange(100) % 3, "v": np.arange(100)})
    got = B.file_buckets(lf, pl.col("k"), 3, tmp_path / "a", slice_rows=30)
    assert [f.collect()["v"].to_list() for f in got] == [list(range(k, 100, 3)) for k in range(3)]

    def short(fn, args):                      # the last slice's piece files nothing
        return [fn(*a) if i < len(args) - 1 else 0 for i, a in enumerate(args)]
    with pytest.raises(RuntimeError, match="read 90 of 100 rows"):
        B.file_buckets(lf, pl.col("k"), 3, tmp_path / "b", slice_rows=30, fanout=short)
