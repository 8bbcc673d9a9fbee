"""Geometric matching of any picture to a reference (tertiary.evaluation.matching)."""

from __future__ import annotations

import tempfile
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl

from tertiary.evaluation.matching import MatchConfig, match_to_reference

T0 = datetime(2021, 10, 7, 12, 0, 0, tzinfo=timezone.utc)


def _truth(n_t=31):
    """Aircraft 1 flies east along y = 0, aircraft 2 west along y = 600 m; they cross x at t = 60 s."""
    rows = []
    for k in range(n_t):
        t = 4.0 * k
        rows.append((1, T0 + timedelta(seconds=t), -12000 + 200 * t, 0.0, 3000.0, 200.0, 0.0, 0.0))
        rows.append((2, T0 + timedelta(seconds=t), 12000 - 200 * t, 600.0, 3000.0, -200.0, 0.0, 0.0))
    return pl.DataFrame(rows, schema=["truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"],
                        orient="row")


def _tracks(truth, swap_at=None, offset=(0.0, 0.0), every=2.0, extra=False):
    """Track 10 on aircraft 1, 20 on 2 (ids exchanged from ``swap_at`` s); sampled every 2 s
    (between truth samples: interpolation needed)."""
    rows = []
    for k in range(60):
        t = every * k
        for tid, (x, y) in ((1, (-12000 + 200 * t, 0.0)), (2, (12000 - 200 * t, 600.0))):
            track = 10 if tid == 1 else 20
            if swap_at is not None and t >= swap_at:
                track = 30 - track
            rows.append((0, T0 + timedelta(seconds=t), track, x + offset[0], y + offset[1], 3000.0,
                         200.0 if tid == 1 else -200.0, 0.0, 0.0))
        if extra:   # a duplicate of aircraft 1, 50 m off, and a false track far away
            rows.append((0, T0 + timedelta(seconds=t), 11, -12000 + 200 * t + 50, 0.0, 3000.0, 200.0, 0.0, 0.0))
            rows.append((0, T0 + timedelta(seconds=t), 99, 50000.0, 50000.0, 3000.0, 0.0, 0.0, 0.0))
    return pl.DataFrame(rows, schema=["run", "epoch", "track_id", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"],
                        orient="row")


def test_each_track_row_is_its_aircraft_with_the_interpolated_reference():
    truth = _truth()
    m = match_to_reference(_tracks(truth, offset=(30.0, -40.0)), truth)
    assert m["truth_id"].null_count() == 0
    assert (m.filter(pl.col("track_id") == 10)["truth_id"] == 1).all()
    err = np.hypot((m["x_m"] - m["true_x_m"]).to_numpy(), (m["y_m"] - m["true_y_m"]).to_numpy())
    np.testing.assert_allclose(err, 50.0, atol=1e-6)            # the 30/40 m offset, at odd seconds too


def test_a_swap_follows_the_geometry():
    truth = _truth()
    m = match_to_reference(_tracks(truth, swap_at=80.0), truth)
    t10 = m.filter(pl.col("track_id") == 10).sort("epoch")
    assert t10.filter(pl.col("epoch") < T0 + timedelta(seconds=80))["truth_id"].unique().to_list() == [1]
    assert t10.filter(pl.col("epoch") >= T0 + timedelta(seconds=80))["truth_id"].unique().to_list() == [2]


def test_one_to_one_duplicates_and_false_tracks_stay_unmatched():
    truth = _truth()
    m = match_to_reference(_tracks(truth, extra=True), truth)
    per_epoch = m.filter(pl.col("truth_id").is_not_null()).group_by("epoch", "truth_id").len()
    assert per_epoch["len"].max() == 1                          # never two tracks on one aircraft
    assert m.filter(pl.col("track_id") == 99)["truth_id"].null_count() == 60
    dup = m.filter(pl.col("track_id") == 11)
    assert dup["truth_id"].null_count() == dup.height           # the closer track 10 keeps aircraft 1


def test_outside_the_gate_or_the_reference_span_is_unmatched():
    truth = _truth(n_t=10)                                      # reference ends at 36 s
    m = match_to_reference(_tracks(truth, offset=(0.0, 2500.0)), truth, MatchConfig(gate_h_m=3000.0))
    late = m.filter(pl.col("epoch") > T0 + timedelta(seconds=36))
    assert late["truth_id"].null_count() == late.height         # never extrapolated
    far = match_to_reference(_tracks(truth, offset=(0.0, 2500.0)), truth)   # 2.5 km > 1 NM gate
    assert far["truth_id"].null_count() == far.height


def test_a_reference_with_nothing_alive_leaves_every_row_unmatched():
    """Found by the fuzz campaign: a one-sample truth gave an out-of-bounds gather."""
    truth = _truth().head(1)
    m = match_to_reference(_tracks(_truth()), truth)
    assert m.height == 120 and "true_x_m" in m.columns
    assert m["truth_id"].null_count() == 119             # aircraft 1 exists at its single sample only
    empty = match_to_reference(_tracks(_truth()), truth.filter(pl.col("truth_id") < 0))
    assert empty["truth_id"].null_count() == 120


def test_a_reference_gap_longer_than_allowed_is_not_interpolated():
    """An ADS-B reference is interpolated only across short gaps."""
    truth = _truth().filter(~((pl.col("truth_id") == 1) & pl.col("time").is_between(
        T0 + timedelta(seconds=30), T0 + timedelta(seconds=70))))          # a 48 s hole for aircraft 1
    loose = match_to_reference(_tracks(truth), truth)
    strict = match_to_reference(_tracks(truth), truth, MatchConfig(max_gap_s=10.0))
    hole = (pl.col("track_id") == 10) & pl.col("epoch").is_between(T0 + timedelta(seconds=28),
                                                                     T0 + timedelta(seconds=72), closed="none")
    assert loose.filter(hole)["truth_id"].null_count() == 0
    assert strict.filter(hole)["truth_id"].null_count() == strict.filter(hole).height > 0
    assert strict.filter(~hole)["truth_id"].null_count() == loose.filter(~hole)["truth_id"].null_count()


def test_candidate_pairs_are_every_gated_pair_of_an_epoch_in_row_order():
    """The gate search against brute force over every (track row, reference row) pair: same
    (run, method, epoch), horizontal distance ≤ the gate, height difference ≤ the vertical gate
    — each once, sorted by (track row, reference row), with its cost. Many rows near one
    another at each epoch, so that a row has several candidates."""
    from tertiary.evaluation.matching import _candidates
    rng = np.random.default_rng(5)
    cfg = MatchConfig(gate_h_m=1000.0, gate_v_m=200.0)
    n_t, n_r = 900, 700
    ep = [T0 + timedelta(seconds=4 * k) for k in range(6)]
    tr = pl.DataFrame({"run": rng.integers(0, 2, n_t).astype(np.uint32), "method": rng.choice(["a", "b"], n_t),
                       "epoch": [ep[k] for k in rng.integers(0, len(ep), n_t)], "x_m": rng.uniform(0, 4000, n_t), "y_m": rng.uniform(0, 4000, n_t),
                       "z_m": rng.uniform(2800, 3200, n_t)})
    ref = pl.DataFrame({"run": rng.integers(0, 2, n_r).astype(np.uint32), "method": rng.choice(["a", "b"], n_r),
                        "epoch": [ep[k] for k in rng.integers(0, len(ep), n_r)], "true_x_m": rng.uniform(0, 4000, n_r),
                        "true_y_m": rng.uniform(0, 4000, n_r), "true_z_m": rng.uniform(2800, 3200, n_r)})
    i, j, cost = _candidates(tr, ref, cfg)
    a = tr.with_row_index("i").join(ref.with_row_index("j"), on=["run", "method", "epoch"])
    dh2 = ((a["x_m"] - a["true_x_m"]) ** 2 + (a["y_m"] - a["true_y_m"]) ** 2).to_numpy()
    dv = (a["z_m"] - a["true_z_m"]).abs().to_numpy()
    keep = (dh2 <= cfg.gate_h_m ** 2) & (dv <= cfg.gate_v_m)
    want = np.lexsort((a["j"].to_numpy()[keep], a["i"].to_numpy()[keep]))
    wi, wj = a["i"].to_numpy()[keep][want], a["j"].to_numpy()[keep][want]
    assert len(wi) > n_t                      # several candidates per row: the test has teeth
    np.testing.assert_array_equal(i, wi)
    np.testing.assert_array_equal(j, wj)
    np.testing.assert_allclose(cost, dh2[keep][want] / cfg.gate_h_m ** 2 + (dv[keep][want] / cfg.gate_v_m) ** 2,
                               rtol=1e-9)


def test_the_reference_height_comes_with_its_rate():
    """A level flight far from the frame's origin: its ENU vz is not zero (the earth curves away
    from the tangent plane) but its altitude rate is. The matched rows and the reference at the
    epochs carry the altitude rate beside the altitude, so the flight phase is level."""
    from tertiary.evaluation.matching import reference_at_epochs
    from tertiary.evaluation.picture_metrics import reference_labels
    truth = _truth().with_columns(pl.lit(9000.0).alias("alt_m"), pl.lit(0.0).alias("alt_rate_mps"),
                                  pl.lit(7.0).alias("vz_mps"))
    tracks = _tracks(truth).with_columns(pl.lit(9000.0).alias("alt_m"), pl.lit(0.0).alias("alt_rate_mps"))
    m = match_to_reference(tracks, truth)
    assert (m["true_alt_rate_mps"] == 0.0).all()
    ref = reference_at_epochs(tracks.select("run", "epoch"), truth)
    assert (ref["true_alt_rate_mps"] == 0.0).all()
    assert set(reference_labels(ref)["phase"].cast(pl.String)) == {"phase:level"}


def test_a_reference_made_once_for_several_pictures_is_cut_to_each_ones_epochs():
    """The reference at the epochs of several pictures, interpolated once, gives each picture
    what its own epochs give it: the matched rows and the expected rows (the reference at its
    epochs, no other epoch's). Fails if the shared reference is not cut to the picture's epochs."""
    from polars.testing import assert_frame_equal
    from tertiary.evaluation.matching import match_with_reference, picture_epochs, reference_at_epochs
    truth = _truth()
    every_2s = _tracks(truth, extra=True)
    every_6s = _tracks(truth, every=6.0).with_columns(pl.col("track_id") + 100)
    shared = reference_at_epochs(pl.concat([picture_epochs(every_2s), picture_epochs(every_6s)]).unique(), truth)
    for picture in (every_2s, every_6s):
        alone, expected_alone = match_with_reference(picture, truth)
        got, expected = match_with_reference(picture, truth, expected=shared)
        assert expected.height < shared.height
        keys = ["run", "epoch", "truth_id"]
        assert_frame_equal(expected.sort(keys), expected_alone.sort(keys))
        assert_frame_equal(got, alone)


def _after_the_end(truth: pl.DataFrame) -> pl.DataFrame:
    """Aircraft 1's reference cut at 36 s; a track 40 confirmed after it, from 38 s to 52 s,
    along its dead-reckoned path (a radar coasting it on; aircraft 2 still more than a gate
    away), and a track 98 far from everything."""
    rows = []
    for k in range(8):
        t = 38.0 + 2.0 * k
        rows.append((0, T0 + timedelta(seconds=t), 40, -12000 + 200 * t + 30.0, 20.0, 3010.0, 200.0, 0.0, 0.0))
        rows.append((0, T0 + timedelta(seconds=t), 98, 40000.0, 40000.0, 3000.0, 0.0, 0.0, 0.0))
    return pl.DataFrame(rows, schema=["run", "epoch", "track_id", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"],
                        orient="row")


def test_a_track_beyond_its_aircrafts_reference_is_unassessed_not_false():
    """Rule 4: rows within ``ended_s`` after an aircraft's last sample and in the gates of that
    sample dead-reckoned carry it as ``beyond_truth_id``: the track is unassessed, not false. The
    reference a window reads (:meth:`Reference.between`) keeps that last sample, in memory and on
    disk, so a window's match is the whole reference's."""
    from tertiary.evaluation.evaluate import Reference, write_reference
    from tertiary.evaluation.picture_metrics import picture_rows, track_table
    truth = _truth().filter((pl.col("truth_id") == 2) | (pl.col("time") <= T0 + timedelta(seconds=36)))
    tracks = _after_the_end(truth)

    def counts(m: pl.DataFrame) -> dict[str, float]:
        rows = picture_rows(track_table(m.with_columns(pl.lit("p").alias("method"))))
        return dict(zip(rows["metric"], rows["value"]))
    m = match_to_reference(tracks, truth)
    beyond = m.group_by("track_id").agg(pl.col("beyond_truth_id").unique()).sort("track_id")
    assert beyond.rows() == [(40, [1]), (98, [None])]
    assert m["truth_id"].null_count() == m.height and m["gated_truth_id"].null_count() == m.height
    assert {k: counts(m)[k] for k in ("false_tracks", "unassessed_tracks", "duplicate_tracks")} == {
        "false_tracks": 1.0, "unassessed_tracks": 1.0, "duplicate_tracks": 0.0}
    never = match_to_reference(tracks, truth, MatchConfig(ended_s=0.0))
    assert never["beyond_truth_id"].null_count() == never.height and counts(never)["false_tracks"] == 2.0
    short = match_to_reference(tracks, truth, MatchConfig(ended_s=12.0))      # 38-48 s only
    assert short.filter(pl.col("beyond_truth_id").is_not_null())["epoch"].max() == T0 + timedelta(seconds=48)
    # a window from 38 s reads the ended aircraft's last sample, whether the reference is in memory or on disk
    with tempfile.TemporaryDirectory() as d:
        for ref in (Reference(truth), Reference(write_reference(truth, Path(d) / "ref.parquet"))):
            part = ref.between(T0 + timedelta(seconds=38), T0 + timedelta(seconds=52), 30.0)
            assert part.filter(pl.col("truth_id") == 1)["time"].to_list() == [T0 + timedelta(seconds=36)]
            assert ref.between(T0 + timedelta(seconds=38), T0 + timedelta(seconds=52)).filter(
                pl.col("truth_id") == 1).height == 0
            windowed = match_to_reference(tracks, part)
            assert windowed["beyond_truth_id"].to_list() == m["beyond_truth_id"].to_list()


def _ended_scene(seed: int) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Aircraft that end at random times (fast ones, some without a velocity, two runs, pairs
    with the same last state) and free rows near their dead-reckoned paths, some at the far end."""
    rng = np.random.default_rng(seed)
    n = 80
    run = rng.integers(0, 2, n)
    end = rng.integers(0, 60, n).astype(float)
    p = rng.uniform(-20_000, 20_000, (n, 2))
    v = rng.uniform(-300, 300, (n, 2))
    v[rng.random(n) < 0.05, 0] = np.nan
    z, vz = rng.uniform(3000, 9000, n), rng.uniform(-10, 10, n)
    twin = np.flatnonzero(np.arange(n) % 10 == 9)     # the same last state as the aircraft before
    for a in (run, end, p, v, z, vz):
        a[twin] = a[twin - 1]
    truth = pl.DataFrame({
        "truth_id": np.repeat(np.arange(n) + 1, 3), "run": np.repeat(run, 3).astype(np.uint32),
        "time": [T0 + timedelta(seconds=float(e + s)) for e in end for s in (-8.0, -4.0, 0.0)],
        "x_m": np.repeat(p[:, 0], 3), "y_m": np.repeat(p[:, 1], 3), "z_m": np.repeat(z, 3),
        "vx_mps": np.repeat(v[:, 0], 3), "vy_mps": np.repeat(v[:, 1], 3), "vz_mps": np.repeat(vz, 3)})
    k = rng.integers(0, n, 600)
    dt = np.where(rng.random(600) < 0.3, rng.uniform(25, 30, 600), rng.uniform(-5, 35, 600))
    at = p[k] + np.nan_to_num(v[k]) * dt[:, None] + rng.normal(0, 900, (600, 2))
    tr = pl.DataFrame({
        "run": np.where(rng.random(600) < 0.1, 1 - run[k], run[k]).astype(np.uint32),
        "epoch": [T0 + timedelta(seconds=float(end[i] + d)) for i, d in zip(k, np.round(dt, 3))],
        "x_m": at[:, 0], "y_m": at[:, 1], "z_m": z[k] + vz[k] * dt + rng.normal(0, 200, 600)}).with_row_index("__row")
    return tr, truth


def _beyond_every_pair(tr: pl.DataFrame, truth: pl.DataFrame, cfg: MatchConfig) -> list:
    """Rule 4 by testing every (row, ended aircraft) pair: the oracle of :func:`_beyond`."""
    last = truth.sort("time").group_by("truth_id", maintain_order=True).last()
    last = last.filter(pl.col("time") < tr["epoch"].max())
    rt, lt = tr["epoch"].dt.epoch("us").to_numpy()[:, None], last["time"].dt.epoch("us").to_numpy()[None, :]
    dt = (rt - lt) / 1e6

    def col(frame: pl.DataFrame, c: str) -> np.ndarray:
        """A column of the rows down, of the aircraft across."""
        return frame[c].to_numpy()[:, None] if frame is tr else frame[c].to_numpy()[None, :]
    d = np.sqrt((col(tr, "x_m") - col(last, "x_m") - col(last, "vx_mps") * dt) ** 2
                + (col(tr, "y_m") - col(last, "y_m") - col(last, "vy_mps") * dt) ** 2)
    dv = np.abs(col(tr, "z_m") - col(last, "z_m") - col(last, "vz_mps") * dt)
    ok = ((rt > lt) & (dt <= cfg.ended_s) & (col(tr, "run") == col(last, "run"))
          & (d <= cfg.gate_h_m) & (dv <= cfg.gate_v_m))
    ids = last["truth_id"].to_numpy()
    out = []
    for r in range(tr.height):
        hits = np.flatnonzero(ok[r])
        out.append(None if not len(hits) else int(ids[hits[np.lexsort((ids[hits], d[r, hits]))[0]]]))
    return out


def test_ended_aircraft_found_for_every_free_row_as_by_testing_every_pair():
    """Rule 4 searches the ended aircraft near each free row (a KD-tree over the midpoints of
    their dead-reckoned paths, radius gate + |v|·ended_s/2): the same aircraft as testing every
    pair, nearest first and the smaller id on a tie, rows at the far end of a fast aircraft's
    path included. The last window of a recording, where every aircraft ends, no longer tests
    every free row against every aircraft."""
    from tertiary.evaluation.matching import _beyond
    for seed in range(6):
        tr, truth = _ended_scene(seed)
        for cfg in (MatchConfig(), MatchConfig(ended_s=12.0, gate_h_m=900.0)):
            got = _beyond(tr, np.ones(tr.height, bool), truth, cfg).to_list()
            want = _beyond_every_pair(tr, truth, cfg)
            assert got == want
            assert sum(g is not None for g in got) > 20        # the scene exercises the rule
        free = np.arange(tr.height) % 3 == 0
        got = _beyond(tr, free, truth, MatchConfig()).to_list()
        assert [g for g, f in zip(got, free) if not f] == [None] * int((~free).sum())
        assert [g for g, f in zip(got, free) if f] == [w for w, f in zip(_beyond_every_pair(tr, truth, MatchConfig()),
                                                                             free) if f]
