"""The truth's separation intervals from an on-disk reference, a time chunk at a time (memory:
a national day's truth held whole for them takes ~16 GB): equal to the whole
truth's, with chunk edges anywhere, irregular sample times, several runs and the segment-end
rules (level pairs, en-route floor, aerodrome zone) in force."""

from __future__ import annotations

import dataclasses
from datetime import timedelta

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from safety import AlertConfig
from safety.alerts import merge_intervals, merge_pair_intervals, observed_until, truth_intervals
from safety.conflicts import AerodromeZone, ConflictConfig
from tertiary import pipeline
from tertiary.evaluation.evaluate import write_reference
from tertiary.simulate import load_scenario, simulate

from apart import Apart


@pytest.fixture(scope="module")
def truth():
    """Two runs of terminal traffic with designed conflicts; in each run each aircraft's samples
    are shifted by its own fraction of a second and a third of them dropped: no two aircraft
    share a sample time, so a chunk edge falls inside segments (the case a naive cut gets
    wrong), and the runs' sample grids differ."""
    cfg = load_scenario("terminal-area")
    ds = simulate(dataclasses.replace(cfg, duration_s=600.0,
                                      traffic=dataclasses.replace(cfg.traffic, aircraft=40, conflict_pairs=6)))
    rng = np.random.default_rng(3)
    ids = ds.truth["truth_id"].unique().sort()
    runs = []
    for run in range(2):
        shift = pl.DataFrame({"truth_id": ids, "__us": rng.integers(1, 999_999, len(ids))})
        t = (ds.truth.join(shift, on="truth_id")
             .with_columns(pl.col("time") + pl.duration(microseconds=pl.col("__us")), pl.lit(run, pl.UInt32)
                           .alias("run")).drop("__us"))
        runs.append(t.filter(pl.Series(rng.random(t.height) > 0.33)))
    return pl.concat(runs).sort("run", "truth_id", "time"), ds.origin


def _config() -> AlertConfig:
    # an en-route floor low enough to split the terminal traffic, and one aerodrome zone
    cc = ConflictConfig(enroute_above_m=1500.0, aerodrome_zones=(AerodromeZone(0.0, 0.0),))
    return AlertConfig(conflict=cc)


@pytest.mark.parametrize("chunk_s", [37.3, 120.0])
def test_chunked_intervals_equal_the_whole_truths(truth, tmp_path, chunk_s):
    t, frame = truth
    acfg = _config()
    whole = truth_intervals(t, acfg, frame)
    assert whole[0].height and whole[1].height           # losses and proximities to compare
    ref = write_reference(t, tmp_path / "ref.parquet")
    (los, prox), span = pipeline.reference_intervals(ref, acfg, frame, chunk_s=chunk_s)
    assert_frame_equal(los, whole[0])
    assert_frame_equal(prox, whole[1])
    ends = t.group_by("run").agg(pl.col("time").min().alias("a"), pl.col("time").max().alias("b"))
    runs = span.filter(pl.col("truth_id").is_null())
    assert runs.height == 2 * ends.height
    assert set(runs["time"].to_list()) == set(ends["a"].to_list()) | set(ends["b"].to_list())


def test_the_span_of_a_reference_on_disk_tells_the_scoring_what_the_truth_in_memory_does(truth, tmp_path):
    """Each aircraft's last sample and whether it ended airborne travel with the span of an
    on-disk reference: until when each aircraft's future is observed (the alerts' undetermined
    class) is the same as from the whole truth — some aircraft leave the recording airborne
    before its end, the others are seen to it."""
    t, frame = truth
    acfg = _config()
    ref = write_reference(t, tmp_path / "ref.parquet")
    _, span = pipeline.reference_intervals(ref, acfg, frame, chunk_s=120.0)
    keys = ["run", "truth_id"]
    got, want = observed_until(span, acfg, frame).sort(keys), observed_until(t, acfg, frame).sort(keys)
    assert_frame_equal(got, want)
    run_end = t.group_by("run").agg(pl.col("time").max().dt.epoch("us").alias("__end"))
    early = got.join(run_end, on="run")["__obs_us"] < got.join(run_end, on="run")["__end"]
    assert 0 < early.sum() < got.height


def test_a_chunk_that_reads_only_its_own_samples_differs(truth, tmp_path, monkeypatch):
    """The check above can fail: chunks cut without the samples before their edge lose the
    pieces of the segments that straddle it."""
    t, frame = truth
    acfg = _config()
    whole = truth_intervals(t, acfg, frame)
    us = t["time"].dt.epoch("us")
    lo, hi = int(us.min()), int(us.max()) + 1
    edges = [*range(lo, hi, 45_000_000), hi]
    chunks = []
    for a, b in zip(edges[:-1], edges[1:]):
        own = t.filter(us.is_between(a, b, closed="left"))
        chunks.append(truth_intervals(own, acfg, frame, clip_us=(a, b)))
    naive = merge_intervals(chunks, acfg)
    assert not (naive[1].equals(whole[1]) and naive[0].equals(whole[0]))


def test_merge_intervals_joins_pieces_cut_at_an_edge():
    schema = {"run": pl.UInt32, "truth_a": pl.Int64, "truth_b": pl.Int64, "t_start_us": pl.Int64,
              "t_end_us": pl.Int64}
    def piece(s_us: int, e_us: int) -> pl.DataFrame:
        return merge_pair_intervals(np.array([0]), np.array([1]), np.array([2]), np.array([s_us]), np.array([e_us]),
                                    schema)
    one = piece(0, 100)
    cut = [(piece(0, 40),) * 2, (piece(40, 100),) * 2]
    los, prox = merge_intervals(cut, AlertConfig(merge_gap_s=0.0))
    assert_frame_equal(los, one)
    assert_frame_equal(prox, one)


def _edge_truth() -> pl.DataFrame:
    """Three aircraft, one run, times in s from 0: A (far away) ends at 9.5 s, just before the
    chunk edge at 10 s; B and C fly side by side 7.4 km apart (between the terminal 3 NM and the
    en-route 5 NM) at one height, sampled at 0, 9, 11, 20 s, descending through the 1 500 m
    en-route floor at 9.1 s. On the whole truth's sample grid the segment pair [9, 9.5] has an
    end above the floor (en-route minima: a loss) and [9.5, 11] none (terminal minima: no loss),
    so the loss ends at 9.5 s. A chunk from 10 s that reads only from its edge back to each
    aircraft's previous sample misses A's 9.5 s sample, judges [9, 11] whole by the en-route
    minima and finds a loss in [10, 11]."""
    t0 = 1_700_000_000_000_000
    rows = [(1, s, 50_000.0, 50_000.0, 3_000.0) for s in (0.0, 9.5)]
    for tid, y in ((2, 0.0), (3, 7_400.0)):
        rows += [(tid, s, 200.0 * s, y, 1_502.0 - 20.0 * (s - 9.0)) for s in (0.0, 9.0, 11.0, 20.0)]
    f = pl.DataFrame(rows, schema={"truth_id": pl.Int64, "s": pl.Float64, "x_m": pl.Float64, "y_m": pl.Float64,
                                   "alt_m": pl.Float64}, orient="row")
    return (f.with_columns((pl.lit(t0) + (pl.col("s") * 1e6).cast(pl.Int64)).cast(pl.Datetime("us", "UTC"))
                           .alias("time"), pl.lit(0.0).alias("z_m"), pl.lit(0, pl.UInt32).alias("run"))
            .drop("s").sort("run", "truth_id", "time"))


def test_a_chunk_reads_from_the_last_sample_before_its_edge(truth, tmp_path):
    """The union sample grid inside a chunk is the whole truth's only when the chunk reads from
    the last sample time before its edge (of any aircraft, here one that ends there): the
    en-route rule judges a segment pair by its ends, so a coarser grid changes the losses."""
    _, frame = truth
    t = _edge_truth()
    acfg = AlertConfig(conflict=ConflictConfig(enroute_above_m=1_500.0))
    whole = truth_intervals(t, acfg, frame)
    t0 = int(t["time"].dt.epoch("us").min())
    assert whole[0].select("truth_a", "truth_b", "t_start_us", "t_end_us").rows() == [(2, 3, t0, t0 + 9_500_000)]
    ref = write_reference(t, tmp_path / "ref.parquet")
    (los, prox), _ = pipeline.reference_intervals(ref, acfg, frame, chunk_s=10.0)
    assert_frame_equal(los, whole[0])
    assert_frame_equal(prox, whole[1])


def test_chunks_done_as_the_windows_pass_and_finished_at_the_end_equal_the_whole_truths(truth, tmp_path,
                                                                                        monkeypatch):
    """The windows compute the chunks their progress has passed (with holes where no window
    ran); the end computes only the rest, and the result is the whole truth's."""
    from tertiary.pipeline import stca_scoring
    t, frame = truth
    acfg = _config()
    whole = truth_intervals(t, acfg, frame)
    ref = write_reference(t, tmp_path / "ref.parquet")
    span = stca_scoring.time_span(pl.scan_parquet(ref))
    lo = int(t["time"].dt.epoch("us").min())
    calls = []
    real = stca_scoring._chunk_intervals
    monkeypatch.setattr(stca_scoring, "_chunk_intervals", lambda *a: calls.append(a[-2:]) or real(*a))
    state = stca_scoring.TruthIntervals()
    for end_s in (30, 60, 90, 250, 260, 400):           # window ends, a hole from 90 to 250 s
        state = stca_scoring.intervals_step(state, ref, span, acfg, frame, lo + end_s * 1_000_000, chunk_s=37.3)
    in_windows = len(calls)
    assert in_windows == int(400 // 37.3) and state.next_us == lo + in_windows * 37_300_000
    (los, prox), _ = pipeline.reference_intervals(ref, acfg, frame, chunk_s=37.3, state=state)
    assert len(calls) - in_windows == int(np.ceil((int(span["time"].dt.epoch("us").max()) + 1 - state.next_us)
                                                  / 37_300_000))
    assert_frame_equal(los, whole[0])
    assert_frame_equal(prox, whole[1])


def test_chunks_computed_apart_equal_the_whole_truths(truth, tmp_path):
    """A distributed run's end computes each chunk as a piece of its cluster (its arguments
    shipped, the pieces in any order) and merges them in time order: the whole truth's
    intervals. Fails if a chunk is lost or computed over another's span."""
    t, frame = truth
    acfg = _config()
    whole = truth_intervals(t, acfg, frame)
    ref = write_reference(t, tmp_path / "ref.parquet")
    fanout = Apart()
    (los, prox), _ = pipeline.reference_intervals(ref, acfg, frame, chunk_s=37.3, fanout=fanout)
    span_s = (t["time"].max() - t["time"].min()).total_seconds()
    assert fanout.pieces == {"_chunk_task": int(np.ceil((span_s + 1e-6) / 37.3))}
    assert_frame_equal(los, whole[0])
    assert_frame_equal(prox, whole[1])


@pytest.mark.parametrize("layout", ["time", "aircraft"])
def test_a_chunk_of_a_reference_in_pieces_reads_only_the_files_its_samples_are_in(truth, tmp_path, monkeypatch,
                                                                                    layout):
    """A reference written in pieces keeps each file's time range: a chunk finds its edge
    samples from the ranges and the files that hold an edge, and reads only the files that can
    hold its samples — the intervals are still the whole truth's, with the pieces in time order
    (ranges side by side) or by aircraft (ranges overlapping). Fails if a chunk starts after the
    last sample before its edge (an edge file's last time taken for it) or misses a neighbour."""
    from tertiary.evaluation.evaluate import write_reference_pieces
    from tertiary.evaluation.matching import neighbour_times
    from tertiary.pipeline import stca_scoring
    t, frame = truth
    one = t.filter(pl.col("run") == 0).drop("run")
    # half the aircraft unseen for 150 s, longer than a piece: their samples either side of the
    # gap are neighbours that files apart
    t0 = one["time"].min()
    gap = (pl.col("truth_id") % 2 == 0) & pl.col("time").is_between(t0 + timedelta(seconds=200),
                                                                     t0 + timedelta(seconds=350))
    one = one.filter(~gap)
    one = one.sort("time", maintain_order=True) if layout == "time" else one
    acfg = _config()
    whole = truth_intervals(one, acfg, frame)
    assert whole[0].height and whole[1].height
    times = neighbour_times(one)
    rows = one.with_columns(times["__prev"], times["__next"])
    step = -(-rows.height // 9)
    ref = write_reference_pieces((rows.slice(k, step) for k in range(0, rows.height, step)), tmp_path / "ref")
    scanned: list[int] = []
    monkeypatch.setattr(stca_scoring.pl, "scan_parquet", lambda files, *a, f=pl.scan_parquet, **k:
                        scanned.append(len(files) if isinstance(files, list) else 1) or f(files, *a, **k))
    edges: list[int] = []
    monkeypatch.setattr(stca_scoring, "_edges", lambda *a, f=stca_scoring._edges: edges.append(1) or f(*a))
    (los, prox), _ = pipeline.reference_intervals(ref, acfg, frame, chunk_s=37.3)
    assert_frame_equal(los, whole[0])
    assert_frame_equal(prox, whole[1])
    assert len(edges) > 10
    if layout == "time":      # side by side: beyond the span's and the schema's, no read holds all nine
        assert scanned.count(9) == 2 and len(scanned) > 2 * len(edges)
