"""picture_metrics_buckets: the metrics of picture_metrics, computed one bucket of aircraft at a time."""

from __future__ import annotations

import math
import tempfile
from unittest import mock
from pathlib import Path
from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest
from polars.io.plugins import register_io_source
from polars.testing import assert_frame_equal

from apart import Apart
from tertiary.evaluation import buckets as filing
from tertiary.core.errors import OptionError
from tertiary.evaluation.picture_buckets import _aircraft_bucket, picture_metrics_buckets
from tertiary.evaluation.picture_metrics import MetricsConfig, picture_metrics

T0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)
STATE = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
TRUE = [f"true_{c}" for c in STATE] + ["true_alt_m"]
BUCKETS = (1, 2, 3, 7)
RADARS = np.array([[0.0, 0.0], [300_000.0, 0.0]])
#: the merge case: track 14 represents aircraft B while flying 300 m beside the untracked aircraft A
A, B = 31, 4


def _times(t: np.ndarray) -> pl.Series:
    us = np.round(np.asarray(t) * 1e6).astype(np.int64) + int(T0.timestamp() * 1e6)
    return pl.Series("epoch", us).cast(pl.Datetime("us", "UTC"))


def _straight(t: np.ndarray, speed=(100.0, 0.0), start=(0.0, 0.0), z=3000.0, vz=0.0) -> dict:
    return {"x": start[0] + speed[0] * t, "y": start[1] + speed[1] * t, "z": z + vz * t,
            "vx": np.full(t.size, speed[0]), "vy": np.full(t.size, speed[1]), "vz": np.full(t.size, vz)}


def _turn(t: np.ndarray, rate_dps=3.0, speed=100.0, z=5000.0) -> dict:
    w = np.radians(rate_dps)
    r = speed / w
    return {"x": r * np.sin(w * t), "y": r * (1 - np.cos(w * t)), "z": np.full(t.size, z),
            "vx": speed * np.cos(w * t), "vy": speed * np.sin(w * t), "vz": np.zeros(t.size)}


def _cut(ref: dict, keep: np.ndarray) -> dict:
    return {k: v[keep] for k, v in ref.items()}


def _reference(run: int, truth_id: int, t: np.ndarray, ref: dict) -> pl.DataFrame:
    """The expected rows of one aircraft (its pressure altitude = z)."""
    return pl.DataFrame({
        "run": pl.Series([run] * t.size, dtype=pl.UInt32), "truth_id": pl.Series([truth_id] * t.size, dtype=pl.Int64),
        "epoch": _times(t), **{f"true_{c}": ref[k] for c, k in zip(STATE, ("x", "y", "z", "vx", "vy", "vz"))},
    }).with_columns(pl.col("true_z_m").alias("true_alt_m"))


def _rows(method: str, run: int, track_id: int, truth_id: int | None, t: np.ndarray, ref: dict,
          dx=0.0, dy=0.0, dz=0.0) -> pl.DataFrame:
    """Track rows on the reference shifted by (dx, dy, dz), with identity items: Mode S right but
    for one row in 7, Mode 3/A wrong one row in 5, callsigns differing in blanks and case, and
    the flight level off by dz + 40 m every third row."""
    n = t.size
    i = np.arange(n)
    truth = _reference(run, -1 if truth_id is None else truth_id, t, ref)
    out = truth.with_columns(
        pl.lit(method).alias("method"), pl.Series("track_id", np.full(n, track_id, dtype=np.uint64)),
        *[(pl.col(f"true_{c}") + d).alias(c) for c, d in zip(STATE, (dx, dy, dz, 0.0, 0.0, 0.0))],
        (pl.col("true_z_m") + dz + pl.Series(np.where(i % 3 == 0, 40.0, 0.0))).alias("alt_m"),
        pl.Series("mode_s", np.where(i % 7 == 0, "FFFFFF", f"ABC{truth_id or 0:03d}")),
        pl.lit(f"abc{truth_id or 0:03d}").alias("icao24"),
        pl.Series("mode_3a", np.where(i % 5 == 0, "7000", "1234")), pl.lit("1234").alias("true_mode_3a"),
        pl.Series("callsign", np.where(i % 4 == 0, "afr 12", "AFR12")), pl.lit("AFR12").alias("true_callsign"))
    if truth_id is None:                                  # unmatched: no reference on the row
        out = out.with_columns(pl.lit(None, dtype=pl.Int64).alias("truth_id"),
                               *[pl.lit(None, dtype=pl.Float64).alias(c) for c in TRUE],
                               pl.lit(None, dtype=pl.String).alias("icao24"),
                               pl.lit(None, dtype=pl.String).alias("true_mode_3a"),
                               pl.lit(None, dtype=pl.String).alias("true_callsign"))
    return out


def _picture() -> tuple[pl.DataFrame, pl.DataFrame]:
    """(matched, expected) of two pictures (p: runs 0 and 1; q: run 0 only) over six aircraft:
    1 turning and 2 straight, whose tracks 10 and 11 swap halfway; 3 climbing 80 km out, with a
    62 s break in run 1 and a few unmatched rows; a second track 13 on 2, later on 1 (split); B
    tracked by 14 beside the bare A (merged; A tracked in its second half in run 1); 6 never
    tracked; the false track 99. Picture q does not track 3."""
    t = np.arange(0.0, 400.0, 2.0)
    half, late = t < 200, (t >= 300) & (t < 340)
    matched, expected = [], []
    for run in (0, 1):
        air = {1: _turn(t), 2: _straight(t, start=(0.0, 2000.0)),
               3: _straight(t, start=(80_000.0, 0.0), z=1000.0, vz=10.0),
               B: _straight(t, speed=(0.0, 120.0), start=(20_000.0, -30_000.0), z=7000.0),
               A: _straight(t, speed=(0.0, 120.0), start=(20_300.0, -30_000.0), z=7100.0),
               6: _straight(t, speed=(-150.0, 0.0), start=(200_000.0, 50_000.0), z=11000.0)}
        expected += [_reference(run, k, t, ref) for k, ref in air.items()]
        keep3 = (t < 200) | (t >= 262) if run else np.full(t.size, True)
        p = [_rows("p", run, 10, 1, t[half], _cut(air[1], half), dx=30.0),
             _rows("p", run, 11, 2, t[half], _cut(air[2], half), dy=-20.0, dz=15.0),
             _rows("p", run, 11, 1, t[~half], _cut(air[1], ~half), dx=-25.0),
             _rows("p", run, 10, 2, t[~half], _cut(air[2], ~half), dy=40.0),
             _rows("p", run, 12, 3, t[keep3], _cut(air[3], keep3), dx=60.0, dz=-80.0),
             _rows("p", run, 12, None, t[::50] + 1.0, _cut(air[3], np.arange(t.size) % 50 == 0), dx=5e3),
             _rows("p", run, 13, 2, t[t < 40], _cut(air[2], t < 40), dx=50.0),
             _rows("p", run, 13, 1, t[late], _cut(air[1], late), dy=50.0),
             _rows("p", run, 14, B, t, air[B], dx=10.0),
             _rows("p", run, 99, None, t, air[1], dx=4e4, dy=-4e4)]
        if run:
            p.append(_rows("p", run, 15, A, t[~half], _cut(air[A], ~half), dx=-15.0))
        matched += p
        if run == 0:
            matched += [_rows("q", run, 20, 1, t, air[1], dx=80.0), _rows("q", run, 21, 2, t, air[2], dy=-90.0),
                        _rows("q", run, 22, B, t, air[B], dx=-30.0)]
    return pl.concat(matched, how="vertical"), pl.concat(expected, how="vertical")


@pytest.fixture(scope="module")
def picture() -> tuple[pl.DataFrame, pl.DataFrame]:
    return _picture()


def _bucket_of(run: int, truth_id: int, buckets: int) -> int:
    key = pl.DataFrame({"run": pl.Series([run], dtype=pl.UInt32), "truth_id": pl.Series([truth_id], dtype=pl.Int64)})
    return key.select(_aircraft_bucket(key.schema, buckets)).item()


def _check(matched: pl.DataFrame, expected: pl.DataFrame | None, buckets=BUCKETS, **kw) -> pl.DataFrame:
    """picture_metrics_buckets = picture_metrics for every bucket count; the reference back."""
    want = picture_metrics(matched, expected=expected, **kw)
    for b in buckets:
        got = picture_metrics_buckets(matched.lazy(), expected=None if expected is None else expected.lazy(),
                                      buckets=b, **kw)
        assert_frame_equal(got, want, check_exact=False, rel_tol=1e-9)
        # the rows filed by bucket once (in slices of 29 rows: the slices' order kept in a bucket)
        with tempfile.TemporaryDirectory() as tmp, mock.patch.object(filing, "FILE_SLICE_ROWS", 29):
            got = picture_metrics_buckets(matched.lazy(), expected=None if expected is None else expected.lazy(),
                                          buckets=b, scratch=Path(tmp), **kw)
        assert_frame_equal(got, want, check_exact=False, rel_tol=1e-9)
    return want



def _value(metrics: pl.DataFrame, metric: str, method: str = "p", segment: str = "all") -> float:
    row = metrics.filter((pl.col("metric") == metric) & (pl.col("method") == method) & (pl.col("segment") == segment))
    assert row.height == 1, (metric, segment, row)
    return row["value"][0]


def test_a_second_track_left_unmatched_in_a_gate_is_a_split_in_every_bucket(picture):
    """The matching is one to one: a second track of an aircraft is an unmatched row with its
    ``gated_truth_id``. Track 78 in the gate of aircraft 6 (which no track represents) is no
    split; 77 beside B (represented by 14) is one, in whichever bucket B falls, filed or not."""
    matched, expected = picture
    t = np.arange(0.0, 40.0, 2.0)
    air = _straight(t, speed=(0.0, 120.0), start=(20_000.0, -30_000.0), z=7000.0)
    base = matched.with_columns(pl.lit(None, pl.Int64).alias("gated_truth_id"))
    second = _rows("p", 0, 77, None, t, air, dx=300.0).with_columns(pl.lit(B, pl.Int64).alias("gated_truth_id"))
    lone = second.with_columns(pl.lit(78, pl.UInt64).alias("track_id"), pl.lit(6, pl.Int64).alias("gated_truth_id"))
    before = _value(_check(base, expected, radar_xy=RADARS), "split_tracks")
    after = _check(pl.concat([base, second.select(base.columns), lone.select(base.columns)]), expected,
                   radar_xy=RADARS)
    assert _value(after, "split_tracks") == before + 1
    assert _value(after, "duplicate_tracks") == 2


def test_the_hand_built_picture_exercises_every_case(picture):
    """The cases the equality tests rely on are there: A and B in different buckets, a merged
    track, a split, a swap, a break, false tracks, and q untracked aircraft 3."""
    for run in (0, 1):
        for one, other in ((A, B), (1, 2)):               # merged, split across buckets
            assert any(_bucket_of(run, one, b) != _bucket_of(run, other, b) for b in BUCKETS[1:])
    met = picture_metrics(picture[0], expected=picture[1], radar_xy=RADARS)
    assert _value(met, "merged_tracks") == 2 and _value(met, "merged_tracks", "q") == 1
    assert _value(met, "split_tracks") == 2 and _value(met, "track_breaks") == 1
    assert _value(met, "false_tracks") == 2 and _value(met, "id_changes_per_hour") > 0
    assert {"range:0-50km", "range:50-100km", "phase:turn", "phase:climb-descent"} <= set(met["segment"])
    assert {"mode_s_correct_frac", "mode_3a_correct_frac", "callsign_correct_frac",
            "flight_level_correct_frac"} <= set(met["metric"])


@pytest.mark.parametrize("with_expected", [True, False])
@pytest.mark.parametrize("radar_xy", [RADARS, None])
def test_equal_to_picture_metrics_on_the_hand_built_picture(picture, with_expected, radar_xy):
    matched, expected = picture
    _check(matched, expected if with_expected else None, radar_xy=radar_xy)


@pytest.mark.parametrize("buckets", [2, 3, 7])
def test_the_pieces_run_apart_equal_picture_metrics(picture, buckets, tmp_path, monkeypatch):
    """Each filed slice, bucket and merged-track pass a piece run apart (shipped, last first), as
    a distributed run's workers run them: the metrics of :func:`picture_metrics`. Fails if a
    piece's result is lost (the merged tracks span buckets here)."""
    matched, expected = picture
    want = picture_metrics(matched, expected=expected, radar_xy=RADARS)
    monkeypatch.setattr(filing, "FILE_SLICE_ROWS", -(-matched.height // 3))
    fanout = Apart()
    got = picture_metrics_buckets(matched.lazy(), expected=expected.lazy(), buckets=buckets, scratch=tmp_path,
                                  fanout=fanout, radar_xy=RADARS)
    assert_frame_equal(got, want, check_exact=False, rel_tol=1e-9)
    assert fanout.pieces["_file_slice"] >= 4
    assert fanout.pieces["_bucket_piece"] == fanout.pieces["_merged_piece"] == buckets


def test_more_buckets_than_aircraft_and_other_settings(picture):
    matched, expected = picture
    cfg = MetricsConfig(expected_interval_s=4.0, break_gap_s=30.0, merge_gate_m=400.0)
    _check(matched, expected, buckets=(50,), radar_xy=RADARS, cfg=cfg)
    _check(matched, expected, buckets=(5,), breakdown=("phase",))
    # labels from the matched rows (expected lacks a reference column the picture has)
    _check(matched, expected.drop("true_alt_m"), buckets=(3,), radar_xy=RADARS)
    # no merged tracks without the reference position
    _check(matched, expected.drop("true_x_m"), buckets=(3,))


def test_a_picture_without_any_matched_row(picture):
    """Only false tracks: no continuity group (and no accuracy or identity row)."""
    matched, expected = picture
    ghosts = matched.filter(pl.col("truth_id").is_null())
    met = _check(ghosts, expected, radar_xy=RADARS)
    assert set(met["metric"]) == {"picture_hours", "n_tracks", "false_tracks", "false_tracks_per_hour",
                                  "duplicate_tracks", "duplicate_tracks_per_hour", "unassessed_tracks"}
    _check(ghosts, None)


def test_a_picture_with_one_aircraft_and_an_empty_one(picture):
    matched, expected = picture
    one = matched.filter(pl.col("truth_id").is_null() | (pl.col("truth_id") == B))
    _check(one, expected)
    _check(one.clear(), expected.clear(), buckets=(1, 3))


def test_bad_bucket_count(picture):
    with pytest.raises(OptionError, match="buckets"):
        picture_metrics_buckets(picture[0].lazy(), buckets=0)


# --------------------------------------------------------------------------- realistic picture


@pytest.fixture(scope="module")
def terminal(small_terminal) -> tuple[pl.DataFrame, pl.DataFrame, np.ndarray]:
    """(matched, expected, radar sites) of two tracker pictures of the small terminal area."""
    from tertiary.evaluation.matching import match_with_reference
    from tertiary.pipeline import PipelineConfig, process

    ds = small_terminal
    res = process(ds, PipelineConfig(methods=("aposteriori", "information"), filters=("singer",), centralized=False,
                                     safety=False, evaluation=False))
    tracks = res.tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("method")).drop("filter")
    matched, expected = match_with_reference(tracks, ds.truth)
    e, n, _ = ds.origin.from_geodetic(ds.radars["lat_deg"].to_numpy(), ds.radars["lon_deg"].to_numpy(),
                                      ds.radars["alt_m"].to_numpy())
    return matched, expected, np.column_stack([e, n])


def _degraded(matched: pl.DataFrame) -> pl.DataFrame:
    """The picture with a 60 s gap on one aircraft in 5, one in 7 missing from the first picture
    (bare there) and a second track on one in 4 for 40 s: the breaks, merged and split tracks
    the clean picture of this short scenario lacks."""
    sec = (pl.col("epoch") - pl.col("epoch").min()).dt.total_seconds()
    gone = ((pl.col("truth_id") % 7 == 3) & (pl.col("method") == "aposteriori+singer")
            | (pl.col("truth_id") % 5 == 1) & sec.is_between(200, 260))
    dup = matched.filter((pl.col("truth_id") % 4 == 2) & sec.is_between(100, 140)).with_columns(
        pl.col("track_id") + 1000, pl.col("x_m") + 50.0)
    return pl.concat([matched.filter(~gone.fill_null(False)), dup])


def test_equal_to_picture_metrics_on_a_terminal_area_picture(terminal):
    matched, expected, radar_xy = terminal
    assert matched["method"].n_unique() == 2 and matched["truth_id"].null_count() > 0
    met = _check(matched, expected, radar_xy=radar_xy)
    assert met.height > 100 and {"merged_tracks", "split_tracks", "p95_horizontal_m"} <= set(met["metric"])
    _check(matched, None, buckets=(3,), radar_xy=radar_xy)
    cfg = MetricsConfig(merge_gate_m=5000.0, merge_gate_v_m=1000.0)
    met = _check(_degraded(matched), expected, radar_xy=radar_xy, cfg=cfg)
    for name in ("merged_tracks", "split_tracks", "track_breaks"):
        assert _value(met, name, "aposteriori+singer") > 0


# --------------------------------------------------------------------------- one bucket at a time


def _recording(frame: pl.DataFrame, log: list[tuple[tuple[str, ...], int]]) -> pl.LazyFrame:
    """``frame`` as a scan that logs (columns, rows) of every read: what a collect materialises."""
    def source(with_columns, predicate, n_rows, batch_size):
        out = frame if predicate is None else frame.filter(predicate)
        out = out if with_columns is None else out.select(with_columns)
        out = out if n_rows is None else out.head(n_rows)
        log.append((tuple(out.columns), out.height))
        yield out
    return register_io_source(source, schema=frame.schema)


def test_rows_are_read_one_bucket_at_a_time():
    """400 aircraft: every read of a wide projection (beyond the five columns of the track table)
    holds about one bucket's rows of ``matched`` and of ``expected``, never the whole picture."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 100.0, 5.0)
    matched, expected = [], []
    for k in range(400):
        ref = _straight(t, speed=tuple(rng.normal(0.0, 150.0, 2)), start=tuple(rng.uniform(-1e5, 1e5, 2)),
                        z=rng.uniform(500.0, 12_000.0))
        expected.append(_reference(k % 2, k, t, ref))
        if k % 10:                                        # one aircraft in 10 is bare
            matched.append(_rows("p", k % 2, k, k, t, ref, dx=rng.normal(0.0, 100.0)))
    matched, expected = pl.concat(matched), pl.concat(expected)
    buckets = 4
    logs: dict[str, list] = {"matched": [], "expected": []}
    got = picture_metrics_buckets(_recording(matched, logs["matched"]), expected=_recording(expected, logs["expected"]),
                                  radar_xy=RADARS, buckets=buckets)
    want = picture_metrics(matched, expected=expected, radar_xy=RADARS)
    assert_frame_equal(got, want, check_exact=False, rel_tol=1e-9)
    slim = {"method", "run", "track_id", "epoch", "truth_id"}
    for name, frame in (("matched", matched), ("expected", expected)):
        wide = [rows for cols, rows in logs[name] if not set(cols) <= slim]
        assert len(wide) >= buckets
        assert max(wide) <= 1.5 * math.ceil(frame.height / buckets), (name, wide, frame.height)
