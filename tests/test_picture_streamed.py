"""The surveillance metrics stepped window by window equal those of the whole picture at once."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.evaluation.picture_metrics import MetricsConfig, picture_metrics
from tertiary.evaluation.picture_streamed import PictureStepState, picture_metrics_finish, picture_step

T0 = datetime(2026, 1, 1, tzinfo=timezone.utc)
RADARS = np.array([[0.0, 0.0], [60_000.0, 20_000.0]])
BREAKDOWN = ["alt", "range", "phase"]
CFG = MetricsConfig(expected_interval_s=10.0, merge_gate_m=2_000.0, merge_gate_v_m=500.0)


def _traffic(seed: int, pictures: tuple[str, ...] = ("a", "b")) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Matched rows and the reference of random traffic with every case the carry must handle:
    aircraft seen at one epoch only, gaps longer than the break gap, two tracks on one aircraft
    at some epochs (split, swaps), tracks lying on an aircraft with none of its own (merged),
    matched rows at epochs the reference lacks, false tracks, a track in an aircraft's gate only
    after its first rows (a duplicate, told in a later window), a second track the one-to-one
    matching leaves unmatched in an aircraft's gate (a split), a track in no gate that is beyond
    an aircraft's reference after its first rows (unassessed, told in a later window), and two
    runs."""
    rng = np.random.default_rng(seed)
    matched, expected = [], []
    for method in pictures:
        for run in (0, 1):
            for aircraft in range(12):
                if aircraft != 2:            # aircraft 2 flies as aircraft 1 does, 1 km aside
                    start = int(rng.integers(0, 40))
                    n = 1 if aircraft == 0 else int(rng.integers(2, 60))
                    epochs = start + np.arange(n) * 4 + np.where(rng.random(n) < 0.05, 40, 0).cumsum()
                # aircraft 1 and 2 fly close together so that one's track lies on the other
                base = np.array([1_000.0 * (aircraft % 3), 4_000.0 * (aircraft // 3)])
                vel = rng.normal(0, 150, 2) if aircraft != 2 else vel
                turn = rng.normal(0, 0.02) if aircraft != 2 else turn
                for k, e in enumerate(epochs):
                    v = np.array([vel[0] * np.cos(turn * k) - vel[1] * np.sin(turn * k),
                                  vel[0] * np.sin(turn * k) + vel[1] * np.cos(turn * k)])
                    pos = base + v * 4 * k
                    climbing = aircraft % 2 and aircraft != 1
                    alt = 2_000.0 + 1_500.0 * (aircraft if aircraft != 2 else 1) + 30.0 * k * climbing
                    truth = {"method": method, "run": run, "truth_id": aircraft, "epoch": int(e),
                             "true_x_m": pos[0], "true_y_m": pos[1], "true_z_m": alt, "true_alt_m": alt,
                             "true_vx_mps": v[0], "true_vy_mps": v[1], "true_vz_mps": 7.5 * climbing}
                    if rng.random() > 0.08:
                        expected.append(truth)
                    tracks = ([] if rng.random() < 0.15 else [aircraft * 10 + 1 + int(k > n // 2 and aircraft % 4 == 0)])
                    if rng.random() < 0.25:
                        tracks.append(aircraft * 10 + 5 + int(rng.integers(0, 2)))
                    for t in tracks:
                        noise = rng.normal(0, 80, 3)
                        matched.append({**truth, "track_id": t, "gated_truth_id": aircraft,
                                        "x_m": pos[0] + noise[0], "y_m": pos[1] + noise[1],
                                        "z_m": alt + noise[2], "alt_m": alt + noise[2], "vx_mps": v[0] + 2,
                                        "vy_mps": v[1] - 2, "vz_mps": 0.0})
                    if aircraft == 3 and tracks and k in (2, 3):     # 907: a second track the matching left unmatched
                        matched.append({**truth, **{c: None for c in truth if c.startswith("true_")},
                                        "truth_id": None, "track_id": 907, "gated_truth_id": aircraft,
                                        "x_m": pos[0] + 300.0, "y_m": pos[1], "z_m": alt, "alt_m": alt,
                                        "vx_mps": v[0], "vy_mps": v[1], "vz_mps": 0.0})
            for k in range(30):                      # false tracks; 906 a duplicate of aircraft 3 from 100 s on,
                e = int(rng.integers(0, 200))        # 905 beyond aircraft 4's reference from 120 s on
                matched.append({"method": method, "run": run, "truth_id": None, "epoch": e, "track_id": 900 + k % 7,
                                "gated_truth_id": 3 if k % 7 == 6 and e >= 100 else None,
                                "beyond_truth_id": 4 if k % 7 == 5 and e >= 120 else None,
                                "x_m": rng.normal(0, 9e3), "y_m": rng.normal(0, 9e3), "z_m": 3e3, "alt_m": 3e3,
                                "vx_mps": 100.0, "vy_mps": 0.0, "vz_mps": 0.0})
    time = pl.col("epoch").cast(pl.Int64) * 1_000_000
    at = pl.lit(T0) + pl.duration(microseconds=time)
    m = pl.DataFrame(matched, infer_schema_length=None).with_columns(
        at.alias("epoch"), pl.col("run").cast(pl.UInt32), pl.col("track_id").cast(pl.UInt64),
        pl.col("truth_id", "gated_truth_id", "beyond_truth_id").cast(pl.Int64))
    e = pl.DataFrame(expected).with_columns(at.alias("epoch"), pl.col("run").cast(pl.UInt32),
                                            pl.col("truth_id").cast(pl.Int64))
    return m, e


def _stepped(m: pl.DataFrame, e: pl.DataFrame, cuts: list[int]) -> pl.DataFrame:
    """The metrics of the windows [.., cut₀), [cut₀, cut₁), … [cutₖ, ..) (cuts in seconds from T0)."""
    state = PictureStepState()
    edges = [None, *(T0 + timedelta(seconds=c) for c in cuts), None]
    for lo, hi in zip(edges[:-1], edges[1:]):
        def part(f: pl.DataFrame) -> pl.DataFrame:
            keep = pl.lit(True)
            if lo is not None:
                keep = keep & (pl.col("epoch") >= lo)
            if hi is not None:
                keep = keep & (pl.col("epoch") < hi)
            return f.filter(keep)
        state = picture_step(state, part(m), part(e), RADARS, CFG)
    return picture_metrics_finish(state, RADARS, BREAKDOWN, CFG)


def _whole(m: pl.DataFrame, e: pl.DataFrame) -> pl.DataFrame:
    out = [picture_metrics(m.filter(pl.col("method") == p), expected=e.filter(pl.col("method") == p).drop("method"),
                           radar_xy=RADARS, breakdown=BREAKDOWN, cfg=CFG)
           for p in m["method"].unique().sort()]
    return pl.concat(out)


def _assert_same(whole: pl.DataFrame, stepped: pl.DataFrame) -> None:
    key = ["stage", "method", "metric", "segment"]
    j = whole.join(stepped, on=key, how="full", suffix="_s", coalesce=True)
    missing = j.filter(pl.col("value").is_null() | pl.col("value_s").is_null())
    assert missing.height == 0, missing
    off = j.filter(((pl.col("value") - pl.col("value_s")).abs() > 1e-9 * pl.col("value").abs().clip(1.0))
                   | (pl.col("n_runs") != pl.col("n_runs_s")))
    assert off.height == 0, off


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("cuts", [[], [61], [16, 17, 18, 60, 100, 101, 150], list(range(2, 260, 9))])
def test_windows_give_the_whole_pictures_metrics(seed: int, cuts: list[int]) -> None:
    m, e = _traffic(seed)
    _assert_same(_whole(m, e), _stepped(m, e, cuts))


def test_the_traffic_has_what_the_carry_must_handle() -> None:
    """The cases above are there (else the equality would not test them)."""
    m, e = _traffic(0)
    whole = _whole(m, e)
    got = {(r["metric"], r["segment"]): r["value"] for r in whole.filter(pl.col("method") == "a").iter_rows(named=True)}
    assert got[("split_tracks", "all")] > 0
    # 907, unmatched in aircraft 3's gate while 3 has its own track, is a split track too
    ungated = _whole(m.with_columns(pl.lit(None, pl.Int64).alias("gated_truth_id")), e)
    assert ungated.filter((pl.col("method") == "a") & (pl.col("metric") == "split_tracks")
                          & (pl.col("segment") == "all"))["value"].item() < got[("split_tracks", "all")]
    assert got[("merged_tracks", "all")] > 0
    assert got[("track_breaks", "all")] > 0
    assert got[("id_changes_per_hour", "all")] > 0
    assert 0 < got[("prob_update", "all")] < 1
    assert got[("false_tracks", "all")] > 0
    assert got[("duplicate_tracks", "all")] > 0
    assert got[("unassessed_tracks", "all")] > 0
    lone = e.group_by("method", "run", "truth_id").len().filter(pl.col("len") == 1)
    assert lone.height > 0


def test_pictures_of_two_schemas_step_together() -> None:
    """A window's pictures come as a frame per schema: a picture without ``alt_m`` is scored on
    its ENU height, beside one with it, as each is alone."""
    m, e = _traffic(1)
    b = m.filter(pl.col("method") == "b").drop("alt_m").with_columns(pl.col("z_m") + 150.0)
    a = m.filter(pl.col("method") == "a")
    state = PictureStepState()
    for lo, hi in ((0, 61), (61, 150), (150, 10_000)):
        def part(f: pl.DataFrame) -> pl.DataFrame:
            t = (pl.col("epoch") - pl.lit(T0)).dt.total_seconds()
            return f.filter((t >= lo) & (t < hi))
        state = picture_step(state, [part(a), part(b)], part(e), RADARS, CFG)
    whole = pl.concat([_whole(a, e.filter(pl.col("method") == "a")), _whole(b, e.filter(pl.col("method") == "b"))])
    _assert_same(whole, picture_metrics_finish(state, RADARS, BREAKDOWN, CFG))


def test_a_window_without_a_matched_row_represents_nobody() -> None:
    """A window whose rows are all unmatched (every track tentative or false then) adds exposure
    and missed updates, not represented epochs."""
    m, e = _traffic(2)
    t = (pl.col("epoch") - pl.lit(T0)).dt.total_seconds()
    quiet = (t >= 100) & (t < 130)
    m = m.with_columns(pl.when(quiet).then(None).otherwise(pl.col("truth_id")).alias("truth_id"))
    assert m.filter(quiet).height and e.filter(quiet).height
    _assert_same(_whole(m, e), _stepped(m, e, [100, 130]))
