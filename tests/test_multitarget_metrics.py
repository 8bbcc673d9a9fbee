"""OSPA, GOSPA and SIAP (tertiary.evaluation.multitarget): hand-computed small cases, the
evaluation stage's rows, and the same values as Stone Soup's own metric generators."""

from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.contract import TIME
from tertiary.evaluation.evaluate import EvaluationConfig, evaluate_pictures
from tertiary.evaluation.matching import reference_at_epochs
from tertiary.evaluation.multitarget import METRICS, MultiTargetConfig, multitarget_by_epoch, multitarget_metrics

T0 = datetime(2024, 5, 1, 12, tzinfo=timezone.utc)


def _frame(rows: list[tuple], cols: tuple[str, ...]) -> pl.DataFrame:
    f = pl.DataFrame(rows, schema=["k", "id", "x", "y", "z"], orient="row")
    return f.select(pl.lit(0, pl.UInt32).alias("run"),
                    (pl.lit(T0) + pl.duration(seconds=pl.col("k"))).cast(TIME).alias("epoch"),
                    pl.col("id").alias(cols[0]), *[pl.col(a).cast(pl.Float64).alias(b) for a, b in zip("xyz", cols[1:])])


def tracks(*rows: tuple) -> pl.DataFrame:
    """(epoch s, track_id, x, y, z) rows."""
    return _frame(list(rows), ("track_id", "x_m", "y_m", "z_m"))


def truth(*rows: tuple) -> pl.DataFrame:
    """(epoch s, truth_id, x, y, z) rows: the truth at the picture's epochs."""
    return _frame(list(rows), ("truth_id", "true_x_m", "true_y_m", "true_z_m"))


def one(tr: pl.DataFrame, ref: pl.DataFrame, c: float, p: float) -> dict:
    return multitarget_by_epoch(tr, ref, MultiTargetConfig(c_m=c, p=p)).row(0, named=True)


# --------------------------------------------------------------------------- hand-computed


def test_two_truths_one_track_gospa_alpha_2():
    # the track 50 m from truth 1; truth 2 missed: OSPA pays c for the missing one out of
    # n = 2, GOSPA (alpha = 2) pays c^p / 2 for it, not c^p
    tr, ref = tracks((0, 1, 30, 40, 0)), truth((0, 1, 0, 0, 0), (0, 2, 1000, 0, 0))
    e1, e2 = one(tr, ref, 100.0, 1.0), one(tr, ref, 100.0, 2.0)
    assert e1["ospa_m"] == pytest.approx((50 + 100) / 2, rel=1e-12)
    assert e2["ospa_m"] == pytest.approx(math.sqrt((50**2 + 100**2) / 2), rel=1e-12)
    assert (e2["gospa_localisation"], e2["gospa_missed"], e2["gospa_false"]) == pytest.approx((2500.0, 5000.0, 0.0))
    assert e2["gospa_m"] == pytest.approx(math.sqrt(7500.0), rel=1e-12)
    assert e1["gospa_m"] == pytest.approx(50 + 50, rel=1e-12)


def test_cut_off_saturates():
    # 500 m apart with c = 100: no localisation, one missed and one false; OSPA is c at any p
    tr, ref = tracks((0, 1, 500, 0, 0)), truth((0, 1, 0, 0, 0))
    for p in (1.0, 2.0, 3.0):
        e = one(tr, ref, 100.0, p)
        assert e["ospa_m"] == pytest.approx(100.0, rel=1e-12)
        assert e["gospa_localisation"] == 0.0
        assert e["gospa_missed"] == e["gospa_false"] == pytest.approx(100.0**p / 2)
        assert e["gospa_m"] == pytest.approx(100.0, rel=1e-12)
    # exactly at the cut-off is no localisation either (Stone Soup: d < c)
    assert one(tracks((0, 1, 100, 0, 0)), ref, 100.0, 2.0)["gospa_localisation"] == 0.0


def test_order_p_changes_the_optimal_assignment():
    # distances track→truth: [[0, 300], [300, 500]]. p = 1: the diagonal (0 + 500 < 300 + 300);
    # p = 2: the cross (300² + 300² < 0 + 500²). The assignment minimises Σ d^p, not Σ d.
    x, y = -700.0 / 6.0, math.sqrt(90000.0 - (700.0 / 6.0) ** 2)
    tr = tracks((0, 1, 0, 0, 0), (0, 2, x, y, 0))
    ref = truth((0, 1, 0, 0, 0), (0, 2, 300, 0, 0))
    assert math.hypot(x - 300, y) == pytest.approx(500.0)
    assert one(tr, ref, 1000.0, 1.0)["ospa_m"] == pytest.approx(250.0, rel=1e-12)
    assert one(tr, ref, 1000.0, 2.0)["ospa_m"] == pytest.approx(300.0, rel=1e-12)
    assert one(tr, ref, 1000.0, 2.0)["gospa_localisation"] == pytest.approx(2 * 300.0**2, rel=1e-12)


def test_siap_counts_and_continuity():
    # truth 1: track 1 at epochs 0-4, then track 2 at 5-9 (one track number change; 8 s
    # tracked: the 4-5 s step is in no segment; longest 4 s of a 9 s life); a duplicate track
    # 3 on truth 1 at epochs 0-2 (ambiguity, and an overlap the time tracked counts once); a
    # false track 4 at epoch 0; truth 2 alive at epochs 0-1, never tracked
    rows = [(k, 1 if k < 5 else 2, k * 100.0 + 10.0, 0.0, 0.0) for k in range(10)]
    dup = [(k, 3, k * 100.0 - 20.0, 0.0, 0.0) for k in range(3)]
    tr = tracks(*rows, *dup, (0, 4, 50_000.0, 0.0, 0.0))
    ref = truth(*[(k, 1, k * 100.0, 0.0, 0.0) for k in range(10)], (0, 2, 0.0, 9_000.0, 0.0),
                (1, 2, 0.0, 9_000.0, 0.0))
    m = dict(multitarget_metrics(tr, ref, "p", MultiTargetConfig(siap_threshold_m=500.0)).select("metric", "value")
             .iter_rows())
    assert m["siap_completeness"] == pytest.approx(10 / 12)             # ΣJT / ΣJ
    assert m["siap_ambiguity"] == pytest.approx(13 / 10)                # ΣNA / ΣJT: the duplicate
    assert m["siap_spuriousness"] == pytest.approx(1 / 14)              # Σ(N − NA) / ΣN: the false track
    assert m["siap_position_accuracy_m"] == pytest.approx((10 * 10 + 3 * 20) / 13)
    assert m["siap_track_changes_per_hour"] == pytest.approx(3600 * 1 / 8)   # (NU − 1) / TT
    assert m["siap_longest_segment_frac"] == pytest.approx(4 / (9 + 1))      # ΣTL / ΣT (truth 2 lives 1 s)
    assert m["multitarget_epochs"] == 10


def test_siap_track_changes_follow_stone_soups_cover():
    # track 1 on the truth at epochs 0-3 and 6-9 (away at 4-5), track 2 at 0-5. A track's
    # segments with a truth are one association: at 0 the cover takes track 1 (its association
    # ends last, at 9) up to 3, then track 2 to 5, then track 1 again — NU = 3 in 8 s tracked
    away = {4: 5_000.0, 5: 5_000.0}
    tr = tracks(*[(k, 1, k * 100.0 + away.get(k, 10.0), 0.0, 0.0) for k in range(10)],
                *[(k, 2, k * 100.0 - 10.0, 0.0, 0.0) for k in range(6)])
    ref = truth(*[(k, 1, k * 100.0, 0.0, 0.0) for k in range(10)])
    m = dict(multitarget_metrics(tr, ref, "p", MultiTargetConfig(siap_threshold_m=500.0)).select("metric", "value")
             .iter_rows())
    assert m["siap_track_changes_per_hour"] == pytest.approx(3600 * 2 / 8)
    assert m["siap_longest_segment_frac"] == pytest.approx(6 / 9)       # track 1: 3 s + 3 s


def test_siap_associates_the_nearest_truth():
    # both truths are within the threshold; the track is truth 2's (100 m), not truth 1's (400 m)
    tr, ref = tracks((0, 1, 0, 0, 0)), truth((0, 1, 400, 0, 0), (0, 2, -100, 0, 0))
    e = multitarget_by_epoch(tr, ref, MultiTargetConfig(siap_threshold_m=500.0)).row(0, named=True)
    assert (e["siap_tracks_assoc"], e["siap_truths_assoc"], e["siap_error_sum_m"]) == (1, 1, pytest.approx(100.0))


def test_epoch_means_and_rows():
    tr = tracks((0, 1, 0, 0, 0), (1, 1, 10, 0, 0))
    ref = truth((0, 1, 0, 0, 0), (1, 1, 0, 0, 0))
    out = multitarget_metrics(tr, ref, "pic", MultiTargetConfig(c_m=100.0, p=2.0))
    assert out["metric"].to_list() == list(METRICS)
    assert set(out["stage"]) == {"evaluation"} and set(out["segment"]) == {"all"} and set(out["method"]) == {"pic"}
    m = dict(out.select("metric", "value").iter_rows())
    assert m["ospa_m"] == pytest.approx(5.0) and m["gospa_localisation"] == pytest.approx(50.0)


def test_the_evaluation_stage_writes_them():
    epochs = [T0 + timedelta(seconds=4 * k) for k in range(5)]
    true = pl.DataFrame({"truth_id": [1] * 5, "time": epochs, "x_m": [100.0 * k for k in range(5)], "y_m": 0.0,
                         "z_m": 3000.0, "vx_mps": 25.0, "vy_mps": 0.0, "vz_mps": 0.0}).with_columns(
        pl.col("time").cast(TIME))
    pic = true.rename({"time": "epoch", "truth_id": "track_id"}).with_columns(
        pl.col("x_m") + 30.0, pl.lit(0, pl.UInt32).alias("run"), pl.lit("mine").alias("method"),
        pl.col("track_id").cast(pl.UInt64))
    cfg = EvaluationConfig(multitarget=MultiTargetConfig(c_m=1000.0, p=1.0))
    ev = evaluate_pictures(pic, true, cfg=cfg, keep_matched=False)
    got = ev.metrics.filter(pl.col("metric").is_in(list(METRICS)) & (pl.col("method") == "mine"))
    assert got.height == len(METRICS)
    assert dict(got.select("metric", "value").iter_rows())["ospa_m"] == pytest.approx(30.0)


# --------------------------------------------------------------------------- Stone Soup


def _scene(seed: int = 1) -> tuple[pl.DataFrame, pl.DataFrame]:
    """A truth table (6 aircraft) and a picture: noisy tracks, some aircraft handed from one
    track to another, a false track at random."""
    rng = np.random.default_rng(seed)
    truth_rows, track_rows, tid = [], [], 100
    for a in range(6):
        p0, v = rng.uniform(-5000, 5000, 3), rng.uniform(-150, 150, 3)
        v[2] = rng.uniform(-5, 5)
        ks = range(int(rng.integers(0, 10)), int(rng.integers(30, 41)))
        truth_rows += [(a, T0 + timedelta(seconds=4 * k), *(p0 + v * 4 * k), *v) for k in ks]
        ks = list(ks)
        for piece in ([ks[: len(ks) // 2], ks[len(ks) // 2:]] if a % 2 else [ks]):
            tid += 1
            track_rows += [(tid, T0 + timedelta(seconds=4 * k), *(p0 + v * 4 * k + rng.normal(0, [300, 300, 50])), *v)
                           for k in piece]
    track_rows += [(999, T0 + timedelta(seconds=4 * k), *rng.uniform(-8000, 8000, 2), 1000.0, 0.0, 0.0, 0.0)
                   for k in range(40) if rng.random() < 0.5]
    state = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
    true = pl.DataFrame(truth_rows, schema=["truth_id", "time", *state], orient="row").with_columns(
        pl.col("time").cast(TIME))
    pic = pl.DataFrame(track_rows, schema=["track_id", "epoch", *state], orient="row").with_columns(
        pl.col("epoch").cast(TIME), pl.lit(0, pl.UInt32).alias("run"), pl.lit("pic").alias("method"))
    return pic, true


def _ours(pic: pl.DataFrame, true: pl.DataFrame, cfg: MultiTargetConfig) -> tuple[pl.DataFrame, dict]:
    at = reference_at_epochs(pic.select("run", "epoch"), true)
    return (multitarget_by_epoch(pic, at, cfg),
            dict(multitarget_metrics(pic, at, "pic", cfg).select("metric", "value").iter_rows()))


def test_same_as_stone_soup():
    pytest.importorskip("stonesoup")
    from stonesoup.dataassociator.tracktotrack import TrackToTruth
    from stonesoup.measures import Euclidean
    from stonesoup.metricgenerator.manager import MultiManager
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric
    from stonesoup.metricgenerator.tracktotruthmetrics import SIAPMetrics

    from tertiary.interop import POSITION_MAPPING, VELOCITY_MAPPING, to_stonesoup

    pic, true = _scene()
    tracks_ss, truths_ss = to_stonesoup(pic, true)
    pos = Euclidean(mapping=POSITION_MAPPING)
    close = dict(rtol=1e-9, atol=1e-9)
    # Stone Soup's OSPA assigns by Σ min(d, c) whatever p: OSPA at p = 1 (where that is Σ d^p)
    for c, p in ((800.0, 1.0), (800.0, 2.0), (3000.0, 2.0)):
        gens = [GOSPAMetric(c=c, p=p, measure=pos)] + ([OSPAMetric(c=c, p=p, measure=pos)] if p == 1 else [])
        manager = MultiManager(gens)
        manager.add_data({"tracks": tracks_ss, "groundtruth_paths": truths_ss})
        got = manager.generate_metrics()
        ep, _ = _ours(pic, true, MultiTargetConfig(c_m=c, p=p))
        gospa = got["gospa_generator"]["GOSPA Metrics"].value
        assert [g.timestamp for g in gospa] == ep["epoch"].to_list()
        for theirs, ours in (("distance", "gospa_m"), ("localisation", "gospa_localisation"),
                             ("missed", "gospa_missed"), ("false", "gospa_false")):
            np.testing.assert_allclose(ep[ours].to_numpy(), [g.value[theirs] for g in gospa], **close)
        if p == 1:
            ospa = got["ospa_generator"]["OSPA distances"].value
            np.testing.assert_allclose(ep["ospa_m"].to_numpy(), [o.value for o in ospa], **close)
    # SIAP with Stone Soup's track-to-truth association, one state to confirm and one to end
    cfg = MultiTargetConfig(siap_threshold_m=900.0)
    siap = SIAPMetrics(position_measure=pos, velocity_measure=Euclidean(mapping=VELOCITY_MAPPING))
    manager = MultiManager([siap], associator=TrackToTruth(association_threshold=900.0, consec_pairs_confirm=1,
                                                           consec_misses_end=1, measure=pos))
    manager.add_data({"tracks": tracks_ss, "groundtruth_paths": truths_ss})
    got = manager.generate_metrics()["siap_generator"]
    _, ours = _ours(pic, true, cfg)
    for theirs, mine, scale in (("SIAP Completeness", "siap_completeness", 1.0),
                                ("SIAP Ambiguity", "siap_ambiguity", 1.0),
                                ("SIAP Spuriousness", "siap_spuriousness", 1.0),
                                ("SIAP Position Accuracy", "siap_position_accuracy_m", 1.0),
                                ("SIAP Rate of Track Number Change", "siap_track_changes_per_hour", 3600.0),
                                ("SIAP Longest Track Segment", "siap_longest_segment_frac", 1.0)):
        np.testing.assert_allclose(ours[mine], scale * got[theirs].value, **close, err_msg=theirs)
    # the scene exercises what is compared: misses, false tracks, hand-overs
    assert 0 < ours["siap_spuriousness"] and ours["siap_completeness"] < 1 and ours["siap_track_changes_per_hour"] > 0


def _picture_to_cut(seed: int):
    """A picture, the truth at its epochs, the config, its whole metrics, its SIAP segments (with
    their reach) and its epochs: what the tests of a picture stepped in pieces compare with."""
    from tertiary.evaluation import multitarget as mt
    pic, true = _scene(seed)
    at = reference_at_epochs(pic.select("run", "epoch"), true)
    cfg = MultiTargetConfig(c_m=800.0, p=2.0)
    whole = dict(multitarget_metrics(pic, at, "pic", cfg).select("metric", "value").iter_rows())
    sc = mt._scene(pic, at, cfg)
    segments = mt._with_reach(mt._segments(mt._associations(sc)), sc.truth).cast({"track_id": pl.UInt64})
    return pic, at, cfg, whole, segments, pic["epoch"].unique().sort()


@pytest.mark.parametrize("seed", range(1, 7))
def test_steps_over_any_split_of_the_epochs_equal_the_whole_picture(seed):
    """OSPA, GOSPA and SIAP stepped a block of epochs at a time (the state carrying the epoch
    sums, the truths' lifetimes and the open segments) equal the whole picture's to 1e-9,
    whatever the split — a block boundary inside a segment, before a truth's first epoch, or
    between a track's states with another truth."""
    from polars.testing import assert_frame_equal

    from tertiary.evaluation import multitarget as mt
    from tertiary.evaluation.multitarget import MultiTargetState, multitarget_result, multitarget_step
    pic, at, cfg, whole, segments, epochs = _picture_to_cut(seed)
    assert whole["siap_track_changes_per_hour"] > 0          # the split tracks change numbers
    rng = np.random.default_rng(seed)
    for _ in range(6):
        cuts = sorted(rng.choice(np.arange(1, len(epochs)), size=int(rng.integers(1, 9)), replace=False).tolist())
        state = MultiTargetState()
        for a, b in zip([0, *cuts], [*cuts, len(epochs)]):
            inside = pl.col("epoch").is_between(epochs[a], epochs[b - 1])
            state = multitarget_step(state, pic.filter(inside), at.filter(inside), cfg)
        got = dict(multitarget_result(state, "pic").select("metric", "value").iter_rows())
        assert got == pytest.approx(whole, rel=1e-9, abs=1e-9), cuts
        # the state's segments are the whole picture's, each reaching back to the same truth epoch
        key = ["run", "truth_id", "track_id", "start", "end", "reach"]
        assert_frame_equal(pl.concat([state.closed, state.open]).select(key).sort(key), segments.sort(key))


@pytest.mark.parametrize("seed", range(1, 7))
def test_stretches_stepped_apart_and_joined_equal_the_whole_picture(seed):
    """A distributed run's end steps each stretch of a picture's epochs apart (each a block or
    several, from :func:`started`) and joins them in time order (:func:`then`): the metrics and
    the segments are those of one state carried through, whatever the cuts. Fails if a segment
    open at a cut is not continued (a track number change counted at every cut), or a segment
    starting at a cut does not reach back to its truth's epoch before it."""
    from polars.testing import assert_frame_equal

    from tertiary.evaluation import multitarget as mt
    pic, at, cfg, whole, segments, epochs = _picture_to_cut(seed)
    rng = np.random.default_rng(seed)
    for _ in range(6):
        cuts = sorted(rng.choice(np.arange(1, len(epochs)), size=int(rng.integers(1, 9)), replace=False).tolist())
        joined = None
        for a, b in zip([0, *cuts], [*cuts, len(epochs)]):
            inside = pl.col("epoch").is_between(epochs[a], epochs[b - 1])
            # a stretch of one or two blocks, stepped alone
            mid = epochs[(a + b) // 2] if b - a > 1 else None
            state = mt.started()
            for part in ([inside] if mid is None else [inside & (pl.col("epoch") < mid),
                                                       inside & (pl.col("epoch") >= mid)]):
                state = mt.multitarget_step(state, pic.filter(part), at.filter(part), cfg)
            joined = state if joined is None else mt.then(joined, state)
        got = dict(mt.multitarget_result(joined, "pic").select("metric", "value").iter_rows())
        assert got == pytest.approx(whole, rel=1e-9, abs=1e-9), cuts
        key = ["run", "truth_id", "track_id", "start", "end", "reach"]
        assert_frame_equal(pl.concat([joined.closed, joined.open]).select(key).sort(key), segments.sort(key))


@pytest.mark.parametrize("seed", range(1, 4))
def test_pictures_stepped_together_equal_each_stepped_alone(seed):
    """:func:`multitarget_steps` (every picture of a window in one call, each keyed apart) leaves
    each picture the state :func:`multitarget_step` gives it alone, block after block, with
    pictures that start late, skip a block or have several runs."""
    from tertiary.evaluation.multitarget import (MultiTargetState, multitarget_result, multitarget_step,
                                                 multitarget_steps)
    cfg = MultiTargetConfig(c_m=800.0, p=2.0)
    scenes = {}
    for k in range(3):
        pic, true = _scene(seed + 10 * k)
        if k == 2:          # a second run, of another scene
            other, other_true = _scene(seed + 50)
            pic = pl.concat([pic, other.with_columns(pl.lit(1, pl.UInt32).alias("run"))])
            true = pl.concat([true.with_columns(pl.lit(0, pl.UInt32).alias("run")),
                              other_true.with_columns(pl.lit(1, pl.UInt32).alias("run"))])
        scenes[f"p{k}"] = (pic, reference_at_epochs(pic.select("run", "epoch"), true))
    epochs = pl.concat([p.select("epoch") for p, _ in scenes.values()]).unique().sort("epoch")["epoch"]
    cuts = [0, len(epochs) // 3, len(epochs) // 2, len(epochs)]
    alone = {n: MultiTargetState() for n in scenes}
    together: dict = {}
    for i, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
        inside = pl.col("epoch").is_between(epochs[a], epochs[b - 1])
        blocks = [(n, p.filter(inside), t.filter(inside)) for n, (p, t) in scenes.items()
                  if not (n == "p0" and i == 0) and not (n == "p1" and i == 1)]
        for n, p, t in blocks:
            alone[n] = multitarget_step(alone[n], p, t, cfg)
        together = multitarget_steps(together, blocks, cfg)
    assert set(together) == set(alone)
    for n in scenes:
        want = dict(multitarget_result(alone[n], n).select("metric", "value").iter_rows())
        got = dict(multitarget_result(together[n], n).select("metric", "value").iter_rows())
        assert got == pytest.approx(want, rel=1e-9, abs=1e-9), n
        key = ["run", "truth_id", "track_id", "start", "end", "reach"]
        for part in ("closed", "open", "life"):
            a, b = getattr(alone[n], part), getattr(together[n], part)
            cols = [c for c in key if c in a.columns] + [c for c in ("first", "last") if c in a.columns]
            assert a.sort(cols).equals(b.sort(cols)), (n, part)
    assert together["p2"].runs.sort().to_list() == [0, 1]


@pytest.mark.parametrize("seed", range(1, 4))
def test_every_pictures_result_finished_at_once_is_each_ones_alone(seed):
    """:func:`multitarget_results` (every picture's continuity in one pass, a picture a key beside
    each truth's) gives each picture the rows :func:`multitarget_result` gives it alone: pictures
    sharing truths and track numbers, one with two runs, one without a segment. Fails if the
    pictures' segments mix (a truth's cover or union taken over several pictures) or if their
    rows are given to another picture."""
    from tertiary.evaluation.multitarget import (MultiTargetState, multitarget_result, multitarget_results,
                                                 multitarget_step)
    cfg = MultiTargetConfig(c_m=800.0, p=2.0)
    states = {}
    for k in range(3):
        pic, true = _scene(seed + 10 * k)
        if k == 2:
            other, other_true = _scene(seed + 50)
            pic = pl.concat([pic, other.with_columns(pl.lit(1, pl.UInt32).alias("run"))])
            true = pl.concat([true.with_columns(pl.lit(0, pl.UInt32).alias("run")),
                              other_true.with_columns(pl.lit(1, pl.UInt32).alias("run"))])
        states[f"p{k}"] = multitarget_step(MultiTargetState(), pic, reference_at_epochs(pic.select("run", "epoch"),
                                                                                      true), cfg)
    far, true = _scene(seed + 90)      # every track too far from every truth: no segment
    far = far.with_columns(pl.col("x_m") + 1e6)
    states["far"] = multitarget_step(MultiTargetState(), far, reference_at_epochs(far.select("run", "epoch"), true),
                                     cfg)
    assert states["far"].closed.height + states["far"].open.height == 0
    got = multitarget_results(states)
    assert list(got) == list(states)
    for n, state in states.items():
        want = multitarget_result(state, n)
        assert_frame_equal(got[n], want, check_exact=False, rel_tol=1e-12)
