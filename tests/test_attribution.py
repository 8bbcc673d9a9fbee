"""Which alerts the picture causes: the truth picture (conflict prediction on the true states,
sampled like the picture) and the attribution of each system picture's alert episodes and
missed losses to the picture or the predictor; Torres & McKay's valid alerts."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from safety.alerts import (ALERTS_SCHEMA, AlertConfig, LOS_SCHEMA, attribute_alerts, attribute_los,
                           attribution_metrics, manoeuvre_onsets, valid_alerts)
from safety.conflicts import ConflictConfig, conflicts_step, init_conflict_state, predict_conflicts
from tertiary.evaluation.truth_picture import SPAN_GAP_S, extend_spans, observed_spans, truth_picture

from apart import Apart

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
TIME = pl.Datetime("us", "UTC")


def _t(s: float) -> datetime:
    return T0 + timedelta(seconds=s)


def _episode(method: str, a: int | None, b: int | None, s0: float, s1: float, cls: str, run: int = 0) -> dict:
    return {"run": run, "method": method, "id_a": 1, "id_b": 2, "truth_a": a, "truth_b": b, "t_start": _t(s0),
            "t_end": _t(s1), "duration_s": s1 - s0, "alert_epochs": 1, "flicker": 0, "r_min_pred_m": None,
            "dz_min_pred_m": None, "t_min_first_s": None, "los_start": None, "warning_s": None,
            "classification": cls}


def _alerts(rows: list[dict]) -> pl.DataFrame:
    return pl.DataFrame(rows, schema=ALERTS_SCHEMA)


def test_an_alert_the_truth_picture_also_raises_is_the_predictors():
    cfg = AlertConfig()                                  # merge gap 15 s
    alerts = _alerts([
        _episode("truth", 1, 2, 100, 120, "false"),
        _episode("p", 1, 2, 130, 140, "false"),          # 10 s after the truth's: within the merge gap
        _episode("p", 1, 2, 200, 210, "false"),          # 80 s later: the picture's own
        _episode("p", 1, 3, 100, 120, "nuisance"),       # a pair the truth picture never alerts
        _episode("p", None, None, 100, 120, "false"),    # no two aircraft: made up by the picture
        _episode("p", 1, 2, 100, 120, "false", run=1),   # same pair and time, another run
    ])
    got = attribute_alerts(alerts, cfg)
    assert got["induced"].to_list() == [None, "predictor", "picture", "picture", "picture", "picture"]
    assert got.drop("induced").equals(alerts)
    # without a truth picture nothing is attributed
    assert attribute_alerts(alerts.filter(pl.col("method") != "truth"), cfg)["induced"].null_count() == 5


def test_a_missed_loss_the_truth_picture_alerted_is_the_pictures():
    los = pl.DataFrame([
        {"run": 0, "method": "truth", "truth_a": 1, "truth_b": 2, "t_start": _t(100), "t_end": _t(150),
         "alerted": True, "first_alert": _t(40), "warning_s": 60.0},
        {"run": 0, "method": "truth", "truth_a": 3, "truth_b": 4, "t_start": _t(100), "t_end": _t(150),
         "alerted": False, "first_alert": None, "warning_s": None},
        {"run": 0, "method": "p", "truth_a": 1, "truth_b": 2, "t_start": _t(100), "t_end": _t(150),
         "alerted": False, "first_alert": None, "warning_s": None},
        {"run": 0, "method": "p", "truth_a": 3, "truth_b": 4, "t_start": _t(100), "t_end": _t(150),
         "alerted": False, "first_alert": None, "warning_s": None},
        {"run": 0, "method": "q", "truth_a": 1, "truth_b": 2, "t_start": _t(100), "t_end": _t(150),
         "alerted": True, "first_alert": _t(50), "warning_s": 50.0},
    ], schema=LOS_SCHEMA)
    got = attribute_los(los)
    assert got["induced"].to_list() == [None, None, "picture", "predictor", None]
    alerts = _alerts([_episode("p", 1, 2, 10, 20, "false"), _episode("truth", 1, 2, 10, 20, "false")])
    m = attribution_metrics(attribute_alerts(alerts), got)
    val = dict(m.filter(pl.col("method") == "p").select("metric", "value").iter_rows())
    assert val["missed_los_picture_induced"] == 1 and val["missed_los_predictor_induced"] == 1
    assert val["false_alerts_predictor_induced"] == 1 and val["false_alerts_picture_induced"] == 0
    assert set(m["method"]) == {"p", "q"}                # the truth picture is the yardstick, not scored



def test_a_missed_loss_under_way_when_its_aircraft_were_first_observed_is_put_down_to_that():
    """A loss the recording starts inside (or an aircraft enters coverage inside) cannot be
    alerted beforehand by any picture: its own class, not the predictor's."""
    row = lambda m, a, b, s0: {"run": 0, "method": m, "truth_a": a, "truth_b": b, "t_start": _t(s0),  # noqa: E731
                               "t_end": _t(s0 + 30), "alerted": False, "first_alert": None, "warning_s": None}
    los = pl.DataFrame([row("truth", 1, 2, 0), row("truth", 3, 4, 100), row("truth", 5, 6, 100),
                        row("p", 1, 2, 0), row("p", 3, 4, 100), row("p", 5, 6, 100)], schema=LOS_SCHEMA)
    # 1 and 2 seen from 0 s (the recording's start, inside the loss); 3 from 0 s, 4 only from
    # 104 s (it enters coverage in loss); 5 and 6 from 0 s (the loss begins at 100 s: alertable)
    spans = pl.DataFrame({"run": [0] * 6, "truth_id": [1, 2, 3, 4, 5, 6],
                          "first": [_t(0), _t(0), _t(0), _t(104), _t(0), _t(0)]},
                         schema={"run": pl.UInt32, "truth_id": pl.Int64, "first": TIME})
    got = attribute_los(los, spans=spans)
    assert got["induced"].to_list() == [None, None, None, "under_way", "under_way", "predictor"]
    assert attribute_los(los)["induced"].to_list()[3:] == ["predictor"] * 3     # no spans: not known
    m = dict(attribution_metrics(attribute_alerts(_alerts([])), got).filter(pl.col("method") == "p")
             .select("metric", "value").iter_rows())
    assert m["missed_los_under_way"] == 2 and m["missed_los_predictor_induced"] == 1

def _track(tid: int, t: np.ndarray, heading_deg: np.ndarray, speed: float = 100.0, vz: np.ndarray | None = None
           ) -> pl.DataFrame:
    h = np.radians(heading_deg)
    vx, vy = speed * np.sin(h), speed * np.cos(h)
    vz = np.zeros_like(t) if vz is None else vz
    return pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": np.cumsum(vx), "y_m": np.cumsum(vy),
                         "z_m": 3000.0 + np.cumsum(vz), "vx_mps": vx, "vy_mps": vy, "vz_mps": vz}
                        ).with_columns(pl.col("time").cast(TIME))


def test_manoeuvre_onsets_are_where_a_new_motion_lasts():
    t = np.arange(0.0, 300.0)
    turn = np.where(t < 100, 0.0, np.where(t < 160, (t - 100) * 3.0, 180.0))     # 3°/s from 100 s to 160 s
    blip = np.where((t >= 200) & (t < 203), 1.0, 0.0).cumsum() * 2.0               # a 3 s wobble: no onset
    climb = np.where((t >= 50) & (t < 120), 10.0, 0.0)                              # climb 50–120 s
    truth = pl.concat([_track(1, t, turn + blip), _track(2, t, np.zeros_like(t), vz=climb)])
    on = manoeuvre_onsets(truth)
    got = {k: sorted(v) for k, v in on.group_by("truth_id").agg(((pl.col("t_us") - int(_t(0).timestamp() * 1e6))
                                                                 / 1e6).alias("s")).iter_rows()}
    # the turn's start and end (a new state each), the climb's start and level-off; never the wobble
    assert got[1] == pytest.approx([101.0, 160.0], abs=1.0)
    assert got[2] == pytest.approx([50.0, 120.0], abs=1.0)


def test_a_nuisance_alert_followed_by_a_manoeuvre_is_valid():
    cfg = AlertConfig()                                   # look-ahead 105 s
    onsets = pl.DataFrame({"truth_id": [2, 5], "t_us": [int(_t(150).timestamp() * 1e6),
                                                        int(_t(500).timestamp() * 1e6)]})
    alerts = _alerts([_episode("p", 1, 2, 100, 120, "nuisance"), _episode("p", 4, 5, 100, 120, "false"),
                      _episode("p", 1, 2, 100, 120, "genuine"), _episode("p", None, None, 100, 120, "false")])
    assert valid_alerts(alerts, onsets, cfg)["valid"].to_list() == [True, False, False, False]


def _head_on() -> pl.DataFrame:
    """Aircraft 1 and 2 head-on at one level, closest (0 m) at 200 s; 3 far away."""
    t = np.arange(0.0, 301.0)
    rows = []
    for tid, x0, vx, y in ((1, -40_000.0, 200.0, 0.0), (2, 40_000.0, -200.0, 0.0), (3, 0.0, 200.0, 80_000.0)):
        rows.append(pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": x0 + vx * t, "y_m": y,
                                  "z_m": 3000.0, "vx_mps": vx, "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": 3000.0,
                                  "alt_rate_mps": 0.0}))
    return pl.concat(rows).with_columns(pl.col("time").cast(TIME))


def _turning(tid: int, at_s: int) -> pl.DataFrame:
    """Aircraft ``tid`` far south, flying east at 150 m/s, turning left at 3 °/s for 30 s from
    ``at_s``."""
    t = np.arange(0.0, 301.0)
    rate = np.where((t >= at_s) & (t < at_s + 30), np.radians(3.0), 0.0)
    hdg = np.concatenate([[0.0], np.cumsum(rate[:-1])])
    vx, vy = 150.0 * np.cos(hdg), 150.0 * np.sin(hdg)
    x, y = np.concatenate([[0.0], np.cumsum(vx[:-1])]), -80_000.0 + np.concatenate([[0.0], np.cumsum(vy[:-1])])
    return pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": x, "y_m": y, "z_m": 3000.0,
                         "vx_mps": vx, "vy_mps": vy, "vz_mps": 0.0, "alt_m": 3000.0,
                         "alt_rate_mps": 0.0}).with_columns(pl.col("time").cast(TIME))


def test_the_truth_picture_is_the_truth_at_the_grid_within_the_observed_spans():
    truth = _head_on()
    grid = pl.DataFrame({"run": pl.Series([0] * 60, dtype=pl.UInt32),
                         "epoch": [_t(s + 0.5) for s in range(0, 300, 5)]}).with_columns(pl.col("epoch").cast(TIME))
    observed = pl.DataFrame({"run": pl.Series([0, 0, 0, 0, 0, 0, 0], dtype=pl.UInt32),
                             "epoch": [_t(10.5), _t(120.5), _t(200.5), _t(50.5), _t(60.5), _t(5.5), _t(130.5)],
                             "truth_id": [1, 1, 1, 2, 2, 3, 3]}).with_columns(pl.col("epoch").cast(TIME))
    spans = observed_spans(observed)
    pic = truth_picture(truth, spans, grid, "truth", "target_id")
    per = dict(pic.group_by("target_id").agg(pl.len()).iter_rows())
    # 10.5 … 200.5 (gaps of 110 and 80 s bridged) and 50.5 … 60.5 every 5 s; 3 observed 125 s
    # apart (more than SPAN_GAP_S): two spans of one epoch each, nothing between them
    assert SPAN_GAP_S == 120.0 and per == {1: 39, 2: 3, 3: 2}
    assert spans.filter(pl.col("truth_id") == 3).height == 2
    one = pic.filter(pl.col("target_id") == 1).sort("epoch")
    s = np.array([(e - T0).total_seconds() for e in one["epoch"].to_list()])
    np.testing.assert_allclose(one["x_m"].to_numpy(), -40_000.0 + 200.0 * s, atol=1e-6)   # between samples
    assert (np.stack(pic["cov_diag"].to_numpy()) == 0).all() and set(pic["method"]) == {"truth"}


def test_the_truth_picture_alerts_a_real_conflict_and_steps_like_one_call():
    truth = _head_on()
    grid = pl.DataFrame({"run": pl.Series([0] * 60, dtype=pl.UInt32),
                         "epoch": [_t(s) for s in range(0, 300, 5)]}).with_columns(pl.col("epoch").cast(TIME))
    observed = grid.join(pl.DataFrame({"truth_id": [1, 2, 3]}), how="cross")
    pic = truth_picture(truth, observed_spans(observed), grid, "truth", "target_id")
    cc = ConflictConfig(confirm_m=3, confirm_n=4)
    whole = predict_conflicts(pic, cc, id_col="target_id")
    alerts = whole.filter(pl.col("alert"))
    assert set(zip(alerts["id_a"], alerts["id_b"])) == {(1, 2)}
    first = (alerts["epoch"].min() - T0).total_seconds()
    # the perfect picture alerts as the pair enters threshold + look-ahead: 80 km closing at 400 m/s
    # reaches 3 NM + 500 m at ≈ 185 s, so the raw condition holds from ≈ 80 s, confirmed 3 epochs later
    assert 75.0 <= first <= 100.0
    # two time blocks with the state carried give the same alerts
    state, parts = init_conflict_state(), []
    us = pic["epoch"].dt.epoch("us")
    cut = int(_t(150).timestamp() * 1e6)
    lo, hi = int(us.min()), int(us.max()) + 1
    for a, b in ((lo, cut), (cut, hi)):
        out, state = conflicts_step(state, pic.filter(us.is_between(a, b, closed="left")), cc, "target_id",
                                    None, a, b, slim=False)
        parts.append(out)
    stepped = pl.concat(parts)
    assert stepped.filter(pl.col("alert")).select("epoch", "id_a", "id_b").equals(
        alerts.select("epoch", "id_a", "id_b"))


@pytest.mark.parametrize("block_s, step_s", [(300.0, 17.0), (120.0, 45.0), (45.0, 300.0)])
def test_the_truth_pictures_alerts_read_in_blocks_and_stepped_equal_one_step(block_s, step_s):
    """The pipeline reads the truth in blocks and makes and predicts the truth picture a step
    at a time (a national hour's picture at once held 1.4 GB): the conflict rows the scoring
    reads, the id map and the manoeuvre onsets equal those of one block and one step. Fails if
    a step's prediction does not carry the state of the one before (confirmation restarts) or
    a step reads epochs of another."""
    from tertiary.pipeline.truth_alerts import truth_conflicts
    truth = _head_on()
    grid = pl.DataFrame({"run": pl.Series([0] * 60, dtype=pl.UInt32),
                         "epoch": [_t(s) for s in range(0, 300, 5)]}).with_columns(pl.col("epoch").cast(TIME))
    spans = observed_spans(grid.join(pl.DataFrame({"truth_id": [1, 2, 3]}), how="cross"))
    t_us = pl.col("time").dt.epoch("us")

    def truth_slice(a: int, b: int) -> pl.DataFrame:
        return truth.filter(t_us.is_between(a, b))
    cc = ConflictConfig(confirm_m=3, confirm_n=4)
    whole = truth_conflicts(cc, truth_slice, spans, grid, "target_id", None, block_s=3600.0, step_s=3600.0)
    got = truth_conflicts(cc, truth_slice, spans, grid, "target_id", None, block_s=block_s, step_s=step_s)
    assert whole[0]["alert"].sum() > 3
    for a, b in zip(got, whole):
        assert a.equals(b)


@pytest.mark.parametrize("block_s", [12.0, 45.0, 120.0])
def test_the_truth_picture_predicted_in_pieces_apart_equals_one_prediction(block_s, tmp_path):
    """A distributed run's end predicts each block of the grid as a piece of its cluster, from
    a fresh state warmed on the grid epochs before the block that its confirmation reads, and
    keeps the block's rows: the rows of one prediction. Fails if a piece confirms afresh from
    its block's first epoch (an alert confirmed across the edge is lost) or keeps the rows of
    its warm-up."""
    from tertiary.evaluation.evaluate import reference_files, write_reference
    from tertiary.pipeline.truth_alerts import reference_slice, truth_conflicts
    files = reference_files(write_reference(_head_on(), tmp_path / "ref.parquet"))
    # a gap in the grid longer than a block: a piece with no epoch of its own
    grid = pl.DataFrame({"run": pl.Series([0] * 48, dtype=pl.UInt32),
                         "epoch": [_t(s) for s in [*range(0, 120, 5), *range(180, 300, 5)]]}
                        ).with_columns(pl.col("epoch").cast(TIME))
    spans = observed_spans(grid.join(pl.DataFrame({"truth_id": [1, 2, 3]}), how="cross"))
    cc = ConflictConfig(confirm_m=3, confirm_n=4)
    whole = truth_conflicts(cc, reference_slice(files), spans, grid, "target_id", None)
    fanout = Apart()
    got = truth_conflicts(cc, reference_slice(files), spans, grid, "target_id", None, block_s=block_s,
                          parts=(fanout, files))
    assert whole[0]["alert"].sum() > 3 and fanout.pieces == {"_predict_part": int(np.ceil(300 / block_s))}
    for a, b in zip(got, whole):
        assert a.equals(b)


@pytest.mark.parametrize("window_s", [7.0, 13.0, 45.0, 130.0, 1000.0])
def test_the_truth_picture_predicted_as_the_windows_pass_equals_the_whole_run(window_s, monkeypatch):
    """The windows extend each aircraft's observed spans and predict every grid epoch more than
    SPAN_GAP_S before their end; the end predicts the rest. The conflict rows, id map and
    manoeuvre onsets equal those of the whole run at once, with an aircraft seen again after a
    gap longer than SPAN_GAP_S (two spans) and the last window open-ended. Fails if a window
    predicts an epoch a later report still changes, drops a span too early, or the end forgets
    what the windows left."""
    from tertiary.core.stage import T_MAX_US
    from tertiary.core.units import US
    from tertiary.pipeline import truth_alerts as ta
    truth = pl.concat([_head_on(), _turning(4, 100)])
    t_us = pl.col("time").dt.epoch("us")
    grid = pl.DataFrame({"run": pl.Series([0] * 150, dtype=pl.UInt32),
                         "epoch": [_t(s) for s in range(0, 300, 2)]}).with_columns(pl.col("epoch").cast(TIME))
    seen = grid.join(pl.DataFrame({"truth_id": [1, 2, 3, 4]}), how="cross")
    # aircraft 1 observed every 50 s only (one span: its alerts need the gaps bridged), 2
    # unobserved 150–270 s, in conflict with 1 (two spans), 4 turning 101–131 s (onsets between grid epochs)
    s = (pl.col("epoch") - pl.lit(T0).cast(TIME)).dt.total_seconds()
    seen = seen.filter(~((pl.col("truth_id") == 2) & s.is_between(150, 270))
                       & ((pl.col("truth_id") != 1) | (s % 50 == 0)))
    spans = observed_spans(seen)
    assert spans.group_by("truth_id").len().sort("truth_id")["len"].to_list() == [1, 2, 1, 1]

    def truth_slice(a: int, b: int) -> pl.DataFrame:
        return truth.filter(t_us.is_between(a, b))
    cc = ConflictConfig(confirm_m=3, confirm_n=4)
    whole = ta.truth_conflicts(cc, truth_slice, spans, seen.select("run", "epoch").unique().sort("run", "epoch"),
                               "target_id", None)
    # steps of 20 s at least: several in this 300 s run (a run's are 300 s)
    monkeypatch.setattr(ta, "TRUTH_STEP_S", 20.0)
    state, stored = ta.TruthPictureState(), {k: [] for k in ta.TRUTH_TABLES}
    lo, step = int(_t(0).timestamp() * US), int(window_s * US)
    e, steps = pl.col("epoch").dt.epoch("us"), 0
    for a in range(lo, lo + 300 * US, step):
        b = a + step if a + step < lo + 300 * US else T_MAX_US          # the last window: open-ended
        out, state = ta.truth_picture_step(state, seen.filter(e.is_between(a, b, closed="left")), b, cc, truth_slice,
                                           "target_id", None)
        for k, v in out.items():
            stored[k].append(v)
        steps += bool(out)
    assert steps > (1 if window_s < 300 else 0)
    got = ta.truth_picture_finish(state, lambda k: pl.concat(stored[k]) if stored[k] else None, cc, truth_slice,
                                  "target_id", None)
    assert whole[0]["alert"].sum() > 3 and whole[2]["t_us"].to_list() == [int(_t(x).timestamp() * US)
                                                                                  for x in (101, 131)]
    for g, w in zip(got, whole):
        assert g.sort(g.columns).equals(w.sort(w.columns))
    # with a wider gap the two spans of aircraft 2 are one: what the windows predict follows it
    wide = ta.truth_conflicts(cc, truth_slice, observed_spans(seen, gap_s=200.0),
                              seen.select("run", "epoch").unique().sort("run", "epoch"), "target_id", None)
    assert wide[0]["alert"].sum() > whole[0]["alert"].sum()


def test_spans_extended_window_by_window_equal_the_spans_of_the_whole():
    """:func:`extend_spans` over the observed epochs in any chunks equals :func:`observed_spans`
    of them all: a chunk's epoch within SPAN_GAP_S of a span extends it, farther starts another."""
    rng = np.random.default_rng(3)
    t = np.sort(rng.choice(np.arange(0, 3000, 4), 300, replace=False)).astype(float)
    ids = rng.integers(1, 5, len(t))
    seen = pl.DataFrame({"run": pl.Series(np.zeros(len(t), int), dtype=pl.UInt32),
                         "epoch": [_t(x) for x in t], "truth_id": ids}).with_columns(pl.col("epoch").cast(TIME))
    whole = observed_spans(seen, gap_s=60.0)
    assert whole.group_by("truth_id").len()["len"].max() > 1
    spans = observed_spans(seen.clear(), gap_s=60.0)
    for k in range(0, len(t), 37):
        spans = extend_spans(spans, seen.slice(k, 37), gap_s=60.0)
    assert spans.equals(whole)
