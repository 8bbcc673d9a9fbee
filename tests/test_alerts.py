"""STCA scoring against real losses of separation: closed-form LoS intervals, alert episodes per
pair of aircraft (genuine / nuisance / false), missed losses, warning time, flicker, metrics,
trade-off curves — on hand-built truth with known answers."""

from __future__ import annotations

import dataclasses
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from safety.alerts import (ALERT_METRICS, ALERTS_SCHEMA, AlertConfig, alert_episodes, compare_at_equal_nuisance,
                           los_episodes, loss_of_separation, score_alerts, scored_ids, separation_intervals,
                           stca_tradeoff, tradeoff_metrics, truth_ends, truth_intervals)
from safety.conflicts import AerodromeZone, ConflictConfig, predict_conflicts
from tertiary.core.errors import ResourceError
from tertiary.core.geo import LocalFrame
from tertiary.contract import validate

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
GRID = [T0 + timedelta(seconds=s) for s in range(0, 301, 5)]       # picture epochs, every 5 s
SEP_H = 3 * 1852.0
CFG = AlertConfig()


def _t(s: float) -> datetime:
    return T0 + timedelta(seconds=s)


def _aircraft(tid: int, x0: float, vx: float, y: float, z: float = 3000.0, vz: float = 0.0,
              step: float = 1.0) -> pl.DataFrame:
    t = np.arange(0.0, 300.0 + step / 2, step)
    h = z + vz * t
    return pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": x0 + vx * t, "y_m": float(y),
                         "z_m": h, "vx_mps": float(vx), "vy_mps": 0.0, "vz_mps": float(vz), "alt_m": h}
                        ).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def _truth(step: float = 1.0) -> pl.DataFrame:
    """1–2 head-on, 1 km miss at t = 200 s (LoS for |60000 − 300 t| < √(5556² − 1000²));
    3–4 pass 7 km apart (no LoS, inside 1.5× the minima: proximity); 5–6 stay 30 km apart;
    7–8 a climbing pair (CPA 0 m at t = 100 s, 8 is 300 m above 7 and climbs
    10 m/s: 1 300 m apart at the CPA, never a LoS, never within 1.5× the minima)."""
    return pl.concat([
        _aircraft(1, -30000.0, 150.0, 0.0, step=step), _aircraft(2, 30000.0, -150.0, 1000.0, step=step),
        _aircraft(3, -30000.0, 150.0, 50000.0, step=step), _aircraft(4, 30000.0, -150.0, 57000.0, step=step),
        _aircraft(5, -30000.0, 150.0, 100000.0, step=step), _aircraft(6, 30000.0, -150.0, 130000.0, step=step),
        _aircraft(7, -10000.0, 100.0, -60000.0, 3000.0, step=step),
        _aircraft(8, 10000.0, -100.0, -60000.0, 3300.0, 10.0, step=step),
    ])


LOS_12 = (200.0 - math.sqrt(SEP_H ** 2 - 1000.0 ** 2) / 300.0, 200.0 + math.sqrt(SEP_H ** 2 - 1000.0 ** 2) / 300.0)


@pytest.fixture(scope="module")
def truth() -> pl.DataFrame:
    return _truth()


def _id_map(extra: dict[int, int | None] | None = None, runs=(0,)) -> pl.DataFrame:
    """Picture ids 11..18 ↔ truth 1..8 at every grid epoch (plus ``extra`` id → truth)."""
    mapping = {10 + k: k for k in range(1, 9)} | (extra or {})
    rows = [{"run": r, "epoch": e, "id": i, "truth_id": t} for r in runs for e in GRID for i, t in mapping.items()]
    return pl.DataFrame(rows, schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "id": pl.UInt64,
                                      "truth_id": pl.Int64})


def _alerts(pairs: dict[tuple[int, int], list[float]], method: str = "m", run: int = 0) -> pl.DataFrame:
    rows = [{"run": run, "epoch": _t(s), "method": method, "id_a": a, "id_b": b, "alert": True, "r_min_m": 1000.0,
             "dz_min_m": 0.0, "t_min_s": 200.0 - s} for (a, b), times in pairs.items() for s in times]
    return pl.DataFrame(rows, schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "method": pl.String,
                                      "id_a": pl.UInt64, "id_b": pl.UInt64, "alert": pl.Boolean,
                                      "r_min_m": pl.Float64, "dz_min_m": pl.Float64, "t_min_s": pl.Float64})


def _metrics(m: pl.DataFrame, method: str = "m") -> dict[str, float]:
    return dict(m.filter(pl.col("method") == method).select("metric", "value").iter_rows())


def _s(col: pl.Series) -> list[float]:
    return [(v - T0).total_seconds() if v is not None else None for v in col.to_list()]


# --------------------------------------------------------------------------- truth: losses of separation


@pytest.mark.parametrize("step", [1.0, 10.0, 30.0])
def test_loss_of_separation_closed_form(step):
    """Exact LoS interval of 1–2 whatever the truth sampling (linear motion between samples);
    no LoS for the 7 km pass and for the climbing pair."""
    los = loss_of_separation(_truth(step))
    assert los.select("truth_a", "truth_b").rows() == [(1, 2)]
    s, e = _s(los["t_start"])[0], _s(los["t_end"])[0]
    assert s == pytest.approx(LOS_12[0], abs=1e-5) and e == pytest.approx(LOS_12[1], abs=1e-5)


def test_proximity_intervals_use_the_factor(truth):
    los, prox = separation_intervals(truth, SEP_H, 304.8, (1.0, 1.5))
    assert set(prox.select("truth_a", "truth_b").rows()) == {(1, 2), (3, 4)}
    half = math.sqrt((1.5 * SEP_H) ** 2 - 7000.0 ** 2) / 300.0        # 3–4: |60000 − 300 t| < that·300
    row = prox.filter(pl.col("truth_a") == 3)
    assert (row["t_start_us"][0] / 1e6 - T0.timestamp()) == pytest.approx(200.0 - half, abs=1e-5)


def test_brief_loss_between_samples_is_found():
    """A 0.4 s graze between two 10 s truth samples: sampling the truth would miss it."""
    # crossing at right angles: 1 flies east, 2 north; horizontal miss of 5 540 m (< 5 556)
    t = np.arange(0.0, 301.0, 10.0)
    a = pl.DataFrame({"truth_id": 1, "time": [_t(s) for s in t], "x_m": -30000 + 200.0 * t, "y_m": 0.0, "z_m": 3000.0,
                      "vx_mps": 200.0, "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": 3000.0})
    d = 5540.0 * math.sqrt(2)                                          # perpendicular offset → CPA distance 5 540 m
    b = pl.DataFrame({"truth_id": 2, "time": [_t(s) for s in t], "x_m": 0.0 + d, "y_m": -30000 + 200.0 * t,
                      "z_m": 3000.0, "vx_mps": 0.0, "vy_mps": 200.0, "vz_mps": 0.0, "alt_m": 3000.0})
    tr = pl.concat([a, b]).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))
    los = loss_of_separation(tr)
    assert los.height == 1
    dur = (los["t_end"][0] - los["t_start"][0]).total_seconds()
    # relative motion: separation (d − 200 t', 200 t') from the common reference; exact duration
    # of |·| < 5556: the chord of a line at distance d/√2·... computed independently below
    tt = np.linspace(0, 300, 3_000_001)
    sep = np.hypot((-30000 + 200 * tt) - d, 0 - (-30000 + 200 * tt))
    inside = tt[sep < SEP_H]
    assert 0.0 < dur < 10.0 and dur == pytest.approx(inside.max() - inside.min(), abs=2e-4)


def test_truth_heights_are_geodetic_far_from_centre():
    """Aircraft over ground points 100 km and 103 km east of the centre: at equal geodetic height
    a LoS; 310 m apart in height not — although their ENU z differ by only ~262 m (curvature
    ρ²/2R differs by 48 m), which taken as height would be a false LoS."""
    frame = LocalFrame(48.7, 2.4, 0.0)

    def truth(h2: float) -> pl.DataFrame:
        rows = []
        for tid, (x, h) in enumerate([(100e3, 9000.0), (103e3, h2)], start=1):
            lat, lon, _ = frame.to_geodetic(x, 0.0, 0.0)
            e, n, u = frame.from_geodetic(lat, lon, h)
            rows += [{"truth_id": tid, "time": _t(s), "x_m": float(e), "y_m": float(n), "z_m": float(u),
                      "vx_mps": 0.0, "vy_mps": 0.0, "vz_mps": 0.0} for s in range(0, 61, 10)]
        return pl.DataFrame(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))

    assert loss_of_separation(truth(9000.0), frame=frame).height == 1
    apart = truth(9310.0)
    assert loss_of_separation(apart, frame=frame).height == 0
    assert loss_of_separation(apart).height == 0                     # the spherical fallback agrees
    z = apart.group_by("truth_id").agg(pl.col("z_m").first()).sort("truth_id")["z_m"].to_list()
    assert 250.0 < z[1] - z[0] < 270.0
    as_if_z = apart.with_columns(pl.col("z_m").alias("alt_m"))        # z taken for height: a false LoS
    assert loss_of_separation(as_if_z, frame=frame).height == 1


def test_truth_heights_in_blocks_are_the_heights_of_every_sample(monkeypatch):
    """The truth is converted to geodetic height a block of samples at a time (memory):
    with blocks of 7 samples (a ragged last block) every height equals the conversion of the
    whole at once, in the output's (truth_id, time) order. Fails if a block is skipped, written
    at the wrong rows or converted twice."""
    import safety.alerts.separation as alerts
    from safety.conflicts import height_and_rate
    frame = LocalFrame(48.7, 2.4, 0.0)
    rng = np.random.default_rng(3)
    n = 40
    truth = pl.DataFrame({"truth_id": rng.integers(1, 4, n), "time": [_t(float(s)) for s in rng.permutation(n)],
                          "x_m": rng.uniform(-2e5, 2e5, n), "y_m": rng.uniform(-2e5, 2e5, n),
                          "z_m": rng.uniform(0, 1e4, n)}).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))
    monkeypatch.setattr(alerts, "HEIGHT_BLOCK", 7)
    got = alerts.truth_heights(truth, frame)
    rows = truth.sort("truth_id", "time")
    pos = rows.select("x_m", "y_m", "z_m").to_numpy()
    want, _, _ = height_and_rate(pos, np.zeros_like(pos), frame)
    assert got.height == n and np.array_equal(got["h_m"].to_numpy(), want)


def test_grid_is_bounded_before_allocation(truth):
    """``max_grid_rows`` bounds the resampled rows held at once: a grid larger than it is
    resampled in blocks (same losses), and two union times that alone need more raise."""
    whole = loss_of_separation(truth)
    assert whole.height
    assert loss_of_separation(truth, AlertConfig(max_grid_rows=50)).equals(whole)
    with pytest.raises(ResourceError, match="max_grid_rows"):
        loss_of_separation(truth, AlertConfig(max_grid_rows=1))


# --------------------------------------------------------------------------- alert episodes


def test_genuine_nuisance_false_and_warning(truth):
    alerts = _alerts({(11, 12): [100, 105, 110, 115, 120], (13, 14): [150, 155], (15, 16): [150],
                      (17, 18): [60, 65, 70], (11, 99): [40]})
    ep = alert_episodes(alerts, _id_map({99: None}), truth, CFG)
    validate_cols = set(ALERTS_SCHEMA)
    assert set(ep.columns) == validate_cols and ep.schema == pl.Schema(ALERTS_SCHEMA)
    got = {(r["id_a"], r["id_b"]): r for r in ep.to_dicts()}
    assert got[(11, 12)]["classification"] == "genuine"
    assert got[(11, 12)]["warning_s"] == pytest.approx(LOS_12[0] - 100.0, abs=1e-5)
    assert got[(11, 12)]["truth_a"] == 1 and got[(11, 12)]["truth_b"] == 2
    assert got[(11, 12)]["duration_s"] == 20.0 and got[(11, 12)]["alert_epochs"] == 5
    assert got[(13, 14)]["classification"] == "nuisance"
    assert got[(15, 16)]["classification"] == "false"
    assert got[(17, 18)]["classification"] == "false"                  # the climbing pair never lost separation
    assert got[(11, 99)]["classification"] == "false" and got[(11, 99)]["truth_a"] is None
    los = los_episodes(alerts, _id_map({99: None}), truth, CFG)
    assert los.height == 1 and los["alerted"][0]
    assert los["warning_s"][0] == pytest.approx(LOS_12[0] - 100.0, abs=1e-5)


def test_an_early_alert_links_to_the_encounter_it_predicted(truth):
    """An alert at 20 s on the head-on pair that predicts its closest approach at 200 s (an entry
    into a widened threshold within T^пор = 105 s) names the LoS starting at ~182 s: genuine,
    warning ~162 s. The fixed window (20 + 105 s) called it false and the LoS missed; so does a
    reach capped before the LoS, or an alert whose own predicted approach is long past."""
    early = _alerts({(11, 12): [20]})                                    # t_min_s = 180
    ep = alert_episodes(early, _id_map(), truth, CFG)
    assert ep["classification"].to_list() == ["genuine"]
    assert ep["warning_s"][0] == pytest.approx(LOS_12[0] - 20.0, abs=1e-5)
    assert los_episodes(early, _id_map(), truth, CFG)["alerted"].to_list() == [True]
    fixed = dataclasses.replace(CFG, link_to_cpa=False)
    assert alert_episodes(early, _id_map(), truth, fixed)["classification"].to_list() == ["false"]
    assert los_episodes(early, _id_map(), truth, fixed)["alerted"].to_list() == [False]
    capped = dataclasses.replace(CFG, max_link_s=120.0)
    assert alert_episodes(early, _id_map(), truth, capped)["classification"].to_list() == ["false"]
    soon = early.with_columns(pl.lit(30.0).alias("t_min_s"))            # predicted closest at 50 s
    assert alert_episodes(soon, _id_map(), truth, CFG)["classification"].to_list() == ["false"]
    # the pair passing 7 km apart at 200 s (within 1.5× the minima from ~185 s): a nuisance
    near = alert_episodes(_alerts({(13, 14): [20]}), _id_map(), truth, CFG)
    assert near["classification"].to_list() == ["nuisance"]


def test_alerts_after_the_reference_ends_are_not_scored(truth):
    """Truth ends at 300 s: an alert at 305–310 s (tracks coasting past the recording's end)
    cannot be judged and is left out; the same pair alerting at 150 s is a false alert."""
    late = alert_episodes(_alerts({(15, 16): [305, 310]}), _id_map(), truth, CFG)
    assert late.height == 0
    early = alert_episodes(_alerts({(15, 16): [150]}), _id_map(), truth, CFG)
    assert early["classification"].to_list() == ["false"]


def _ends_at(truth: pl.DataFrame, tid: int, end_s: float, height_m: float | None = None) -> pl.DataFrame:
    """``truth`` with aircraft ``tid``'s samples after ``end_s`` dropped (and, with ``height_m``,
    flown at that height throughout: a landing)."""
    t = truth.filter((pl.col("truth_id") != tid) | (pl.col("time") <= _t(end_s)))
    if height_m is None:
        return t
    low = pl.col("truth_id") == tid
    return t.with_columns(*(pl.when(low).then(height_m).otherwise(pl.col(c)).alias(c) for c in ("z_m", "alt_m")))


def test_an_alert_whose_outcome_is_not_observed_is_undetermined(truth):
    """The 30-km pair (5, 6) never comes close. An alert at 150 s, whose link window closes at
    255 s, is false while both aircraft are recorded to the end (300 s); it is undetermined when
    6 leaves the recording airborne at 200 s, and false again when 6 lands then (100 m). An alert
    at 250 s reaches past the end of the truth itself: undetermined, even when both aircraft are
    low at the end (the recording stops, not the aircraft). A genuine or nuisance alert
    stays what it is, whatever the ends."""
    at150, at250 = _alerts({(15, 16): [150]}), _alerts({(15, 16): [250]})
    cls = lambda a, t, cfg=CFG: alert_episodes(a, _id_map(), t, cfg)["classification"].to_list()  # noqa: E731
    assert cls(at150, truth) == ["false"]
    assert cls(at150, _ends_at(truth, 6, 200.0)) == ["undetermined"]
    assert cls(at150, _ends_at(truth, 6, 200.0, 100.0)) == ["false"]
    assert cls(at150, _ends_at(truth, 6, 200.0, 700.0)) == ["undetermined"]      # above 2 000 ft
    assert cls(at150, _ends_at(truth, 6, 200.0, 700.0), dataclasses.replace(CFG, landed_below_m=800.0)) == ["false"]
    assert cls(at250, truth) == ["undetermined"]
    low = _ends_at(_ends_at(truth, 5, 300.0, 100.0), 6, 300.0, 100.0)        # low to the end: still recorded
    assert cls(at150, low) == ["false"] and cls(at250, low) == ["undetermined"]
    assert cls(_alerts({(11, 12): [150]}), _ends_at(truth, 2, 230.0)) == ["genuine"]        # LoS seen by 218 s
    assert cls(_alerts({(13, 14): [150]}), _ends_at(truth, 4, 230.0)) == ["nuisance"]
    m = _metrics(score_alerts(pl.concat([at150, at250]), _id_map(), truth, CFG))
    assert m["undetermined_alerts"] == 1 and m["false_alerts"] == 1 and m["alert_episodes"] == 2
    assert m["nuisance_false_per_hour"] == pytest.approx(1 / m["picture_hours"])


def test_each_aircrafts_last_sample_and_whether_it_ended_airborne(truth):
    """``truth_ends``: one row per aircraft, its last sample's time, airborne above 2 000 ft;
    the same from the frame and from a scan of it, whatever the rows' order."""
    t = _ends_at(_ends_at(truth, 6, 200.0, 100.0), 5, 250.0)
    got = truth_ends(t.sample(fraction=1.0, shuffle=True, seed=1), CFG)
    want = {k: (_t(300.0), True) for k in range(1, 9)} | {6: (_t(200.0), False), 5: (_t(250.0), True)}
    assert {r["truth_id"]: (r["time"], r["airborne"]) for r in got.to_dicts()} == want
    assert got.equals(truth_ends(t.lazy(), CFG))
    runs = pl.concat([t.with_columns(pl.lit(r, pl.UInt32).alias("run")) for r in (0, 1)])
    assert truth_ends(runs, CFG).height == 16 and truth_ends(runs, CFG)["run"].to_list() == [0] * 8 + [1] * 8


def test_a_track_coasting_after_its_aircraft_left_alerts_about_that_aircraft(truth):
    """Aircraft 6's truth ends at 150 s and the matcher maps its track 16 no further; the
    track coasts on and alerts with 15 at 155–160 s. The episode is about aircraft (5, 6):
    undetermined when 6 left airborne, false when it landed (a track coasting after a
    landing alerts about nothing). A track never mapped to an aircraft stays unknown: false."""
    # the matcher's rows of 16 after 150 s name no aircraft (as a coasting track's do)
    ids = _id_map({17: None}).with_columns(
        pl.when((pl.col("id") == 16) & (pl.col("epoch") > _t(150.0))).then(None).otherwise(pl.col("truth_id"))
        .alias("truth_id"))
    late = _alerts({(15, 16): [155, 160], (15, 17): [155, 160]})
    ep = {(r["id_a"], r["id_b"]): r for r in alert_episodes(late, ids, _ends_at(truth, 6, 150.0), CFG).to_dicts()}
    assert (ep[(15, 16)]["truth_a"], ep[(15, 16)]["truth_b"]) == (5, 6)
    assert ep[(15, 16)]["classification"] == "undetermined"
    assert ep[(15, 17)]["truth_a"] is None and ep[(15, 17)]["classification"] == "false"
    landed = alert_episodes(late, ids, _ends_at(truth, 6, 150.0, 100.0), CFG)
    assert landed.filter(pl.col("id_b") == 16).select("truth_b", "classification").row(0) == (6, "false")
    # the id map's rows the pipeline keeps for the scoring (memory) keep that last mapping
    kept = scored_ids(ids, late, "id")
    assert kept.height < ids.height
    assert alert_episodes(late, kept, _ends_at(truth, 6, 150.0), CFG).equals(
        alert_episodes(late, ids, _ends_at(truth, 6, 150.0), CFG))
    # while the aircraft is still in the truth, an unmapped row is not given its identity
    early = alert_episodes(_alerts({(15, 16): [155, 160]}), ids, truth, CFG)
    assert early["truth_a"].to_list() == [None] and early["classification"].to_list() == ["false"]


def test_an_id_map_reduced_window_by_window_keeps_what_the_whole_maps_reduction_keeps(truth):
    """The windows reduce their block of the id map with their own alerts only
    (:func:`block_id_rows`); the end reduces the blocks' union with every alert (:func:`id_rows`):
    the same rows as the whole map's reduction, and the same episodes. Track 16 is mapped to
    aircraft 6 only in the first block and alerts in the last, coasting: its last mapping lives
    in a block without its alert. Fails if a block keeps the last mapping of its alert ids
    only, or no row per picture epoch."""
    from safety.alerts import alert_ids, block_id_rows, id_rows
    rng = np.random.default_rng(7)
    ids = _id_map({17: None}).with_columns(
        pl.when((pl.col("id") == 16) & (pl.col("epoch") > _t(90.0))).then(None).otherwise(pl.col("truth_id"))
        .alias("truth_id"))
    # duplicates of some rows (the first of them stays first) and rows in no particular id order
    ids = pl.concat([ids, ids.sample(40, seed=3)]).sort("epoch", maintain_order=True)
    pairs = {(15, 16): [255, 260], (11, 12): [100, 105, 110], (13, 14): [150]}
    draws = zip(rng.choice([11, 13, 15], 6), rng.choice([12, 14, 17], 6), rng.choice(np.arange(0, 301, 5), 6))
    pairs.update({(int(a), int(b)): [int(t)] for a, b, t in draws})
    late = _alerts(pairs)
    whole = id_rows(ids, alert_ids(late, "id"), "id")
    cuts = [_t(s) for s in (-1, 97, 181, 242, 400)]
    blocks = []
    for lo, hi in zip(cuts, cuts[1:]):
        mine = pl.col("epoch").is_between(lo, hi, closed="left")
        blocks.append(block_id_rows(ids.filter(mine), alert_ids(late.filter(mine), "id"), "id"))
    reduced = pl.concat(blocks)
    assert reduced.height < ids.height
    assert id_rows(reduced, alert_ids(late, "id"), "id").equals(whole)
    assert alert_episodes(late, id_rows(reduced, alert_ids(late, "id"), "id"), _ends_at(truth, 6, 90.0), CFG).equals(
        alert_episodes(late, ids, _ends_at(truth, 6, 90.0), CFG))


def test_fragmented_ids_make_one_episode(truth):
    """Track 12 is replaced by 22 (same aircraft 2) mid-alert, and 11's map is wrong at one epoch:
    one episode on the aircraft pair (1, 2), not two or three."""
    idm = _id_map({22: 2})
    wrong = idm.with_columns(pl.when((pl.col("id") == 11) & (pl.col("epoch") == _t(110))).then(5)
                             .otherwise(pl.col("truth_id")).alias("truth_id"))
    alerts = _alerts({(11, 12): [100, 105, 110], (11, 22): [115, 120, 125]})
    ep = alert_episodes(alerts, wrong, truth, CFG)
    assert ep.height == 1 and ep["classification"][0] == "genuine" and ep["alert_epochs"][0] == 6
    assert (ep["truth_a"][0], ep["truth_b"][0]) == (1, 2) and ep["flicker"][0] == 0
    m = _metrics(score_alerts(alerts, wrong, truth, CFG))
    assert m["alert_episodes"] == 1 and m["alerted_los"] == 1 and m["los_episodes"] == 1


def test_flicker_and_merge_gap(truth):
    alerts = _alerts({(11, 12): [100, 105, 115, 120, 150, 155]})        # dropout at 110 (flicker), gap 30 s
    ep = alert_episodes(alerts, _id_map(), truth, CFG)
    assert ep.height == 2 and ep["flicker"].to_list() == [1, 0]
    assert (ep["classification"] == "genuine").all()
    assert _s(ep["t_start"]) == [100.0, 150.0]
    merged = alert_episodes(alerts, _id_map(), truth, dataclasses.replace(CFG, merge_gap_s=30.0))
    assert merged.height == 1 and merged["flicker"][0] == 2
    m = _metrics(score_alerts(alerts, _id_map(), truth, CFG))
    assert m["flicker_per_alert"] == 0.5 and m["warning_median_s"] == pytest.approx(LOS_12[0] - 100, abs=1e-5)


def test_missed_and_late_alerts(truth):
    m = _metrics(score_alerts(_alerts({(13, 14): [150]}), _id_map(), truth, CFG))
    assert m["los_episodes"] == 1 and m["missed_los"] == 1 and m["alerted_los"] == 0
    assert math.isnan(m["warning_median_s"])
    # an alert after the LoS ended is not a warning of it: missed, and the alert is false (with a
    # link window that closes before the truth ends; the default one reaches past it)
    late = _alerts({(11, 12): [250, 255]})
    short = dataclasses.replace(CFG, link_s=20.0)
    ep = alert_episodes(late, _id_map(), truth, short)
    assert ep["classification"].to_list() == ["false"]
    assert alert_episodes(late, _id_map(), truth, CFG)["classification"].to_list() == ["undetermined"]
    m = _metrics(score_alerts(late, _id_map(), truth, CFG))
    assert m["missed_los"] == 1
    # an alert during the LoS counts, with a negative warning
    during = _alerts({(11, 12): [190, 195]})
    m = _metrics(score_alerts(during, _id_map(), truth, CFG))
    assert m["alerted_los"] == 1 and m["warning_median_s"] == pytest.approx(LOS_12[0] - 190.0, abs=1e-5)


def test_metrics_names_rates_and_methods(truth):
    alerts = pl.concat([_alerts({(11, 12): [100, 105], (15, 16): [150], (13, 14): [150]}, method="a"),
                        _alerts({(15, 16): [150]}, method="b")])
    m = score_alerts(alerts, _id_map(), truth, CFG)
    validate(m, "metrics")
    assert set(m["stage"]) == {"safety"}
    for meth in ("a", "b"):
        assert set(_metrics(m, meth)) == set(ALERT_METRICS)
    a, b = _metrics(m, "a"), _metrics(m, "b")
    hours = 300.0 / 3600.0
    assert a["alerts_per_hour"] == pytest.approx(3 / hours) and a["nuisance_false_per_hour"] == pytest.approx(2 / hours)
    assert (a["genuine_alerts"], a["nuisance_alerts"], a["false_alerts"]) == (1, 1, 1)
    assert (b["genuine_alerts"], b["false_alerts"], b["missed_los"]) == (0, 1, 1)
    assert a["picture_hours"] == pytest.approx(hours)
    # p05 of one warning is that warning
    assert a["warning_p05_s"] == pytest.approx(a["warning_median_s"])
    # one pass gives the same three tables
    from safety.alerts import stca_tables
    m3, al3, los3 = stca_tables(alerts, _id_map(), truth, CFG)
    assert m3.equals(m) and al3.equals(alert_episodes(alerts, _id_map(), truth, CFG))
    assert los3.equals(los_episodes(alerts, _id_map(), truth, CFG))
    # a method without alerts (listed) still reports its missed LoS
    none = score_alerts(alerts.filter(pl.col("method") == "a"), _id_map(), truth, CFG, methods=["a", "c"])
    assert _metrics(none, "c")["missed_los"] == 1


@pytest.mark.parametrize("budget", [0, 2_000, 10**9], ids=["picture-each", "some-together", "one-pass"])
def test_tables_one_picture_at_a_time_equal_one_call(truth, budget, monkeypatch):
    """The pipeline scores alerts a few pictures at a time, up to a row budget (memory: not
    every picture's joins at once): the metrics, alerts and LoS tables equal one call's, with an
    id map per picture or shared, and a listed picture without alerts. Fails if a picture's
    rows are scored against another's id map, a pass scores a picture not its own, or the
    union is not in one call's order."""
    from safety.alerts import episodes, stca_tables, stca_tables_by_picture
    monkeypatch.setattr(episodes, "PASS_ROWS", budget)
    passes = []
    monkeypatch.setattr(episodes, "stca_tables", lambda *a, f=episodes.stca_tables, **k: passes.append(a[5]) or f(*a, **k))
    alerts = pl.concat([_alerts({(11, 12): [100, 105], (15, 16): [150], (13, 14): [150]}, method="b"),
                        _alerts({(15, 16): [150], (11, 12): [104]}, method="a"),
                        _alerts({(11, 12): [150], (13, 14): [120, 125]}, method="d"),
                        _alerts({(13, 14): [110]}, method="a", run=1), _alerts({(11, 12): [90]}, method="b", run=1)])
    shared = _id_map(runs=(0, 1))
    per = pl.concat([shared.with_columns(pl.lit(m).alias("method")) for m in ("a", "b", "c", "d")])
    # picture d's ids 11 and 12 stand for other aircraft: only its own map gives its classification
    per = per.with_columns(pl.when((pl.col("method") == "d") & pl.col("id").is_in([11, 12]))
                           .then(pl.col("truth_id") + 4).otherwise(pl.col("truth_id")).alias("truth_id"))
    for ids in (shared, per):
        for methods in (None, ["a", "b", "c", "d"]):
            want = stca_tables(alerts, ids, truth, CFG, methods=methods)
            got = stca_tables_by_picture(alerts, ids, truth, CFG, methods=methods)
            assert want[1].height == 9 and want[0].height > 10 and want[1]["run"].n_unique() == 2
            for a, b in zip(got, want):
                assert a.equals(b)
    # 3 + 4 + 4 + 4 pictures scored: one pass each, two to a pass (a picture's id map is 976
    # rows), or one pass per call
    assert len(passes) == {0: 15, 2_000: 8, 10**9: 4}[budget]
    d = stca_tables(alerts, per, truth, CFG)[1].filter(pl.col("method") == "d")
    assert d["truth_a"].to_list() != stca_tables(alerts, shared, truth, CFG)[1].filter(
        pl.col("method") == "d")["truth_a"].to_list()


def test_runs_shared_truth(truth):
    alerts = pl.concat([_alerts({(11, 12): [100]}, run=0), _alerts({(15, 16): [100]}, run=1)])
    m = _metrics(score_alerts(alerts, _id_map(runs=(0, 1)), truth, CFG))
    assert m["los_episodes"] == 2 and m["alerted_los"] == 1 and m["false_alerts"] == 1


# --------------------------------------------------------------------------- end to end with predictions


def _picture(truth: pl.DataFrame, cov: bool = True, noise: float = 0.0) -> pl.DataFrame:
    """Truth at the grid epochs as a picture (ids 10 + truth), heights in the alt_m channel."""
    rng = np.random.default_rng(0)
    p = truth.filter(pl.col("time").is_in(GRID)).rename({"time": "epoch"}).with_columns(
        (pl.col("truth_id") + 10).cast(pl.UInt64).alias("target_id"), pl.lit(0, pl.UInt32).alias("run"),
        pl.lit("m").alias("method"), pl.col("vz_mps").alias("alt_rate_mps"))
    p = p.with_columns(pl.col("x_m") + rng.normal(0, noise, p.height), pl.col("y_m") + rng.normal(0, noise, p.height))
    if cov:
        c = np.diag([50.0 ** 2, 50.0 ** 2, 30.0 ** 2, 3.0 ** 2, 3.0 ** 2, 1.0]).ravel()
        p = p.with_columns(pl.Series("cov", np.tile(c, (p.height, 1)), dtype=pl.Array(pl.Float64, 36)))
    return p


def test_end_to_end_seed_vs_corrected(truth):
    pic = _picture(truth)
    idm = _id_map()
    out = {}
    for mode in ("corrected", "seed"):
        cc = ConflictConfig(mode=mode)
        c = predict_conflicts(pic, cc, id_col="target_id")
        ep = alert_episodes(c, idm, truth, AlertConfig(conflict=cc), id_col="id")
        out[mode] = {(r["truth_a"], r["truth_b"]): r["classification"] for r in ep.to_dicts()}
        m = _metrics(score_alerts(c, idm, truth, AlertConfig(conflict=cc), id_col="id"))
        assert m["alerted_los"] == 1 and m["warning_median_s"] >= 30.0
    assert out["corrected"].get((1, 2)) == "genuine" and (7, 8) not in out["corrected"]
    assert out["seed"][(7, 8)] == "false"                               # the seed rule's false alert


def test_tradeoff_reads_each_aircrafts_end_once_and_scores_as_from_the_span(truth, monkeypatch):
    """The curves score every setting against the same ends and the same id map: each read once
    (not once per setting), and the curves equal those scored from the truth's span (the
    pipeline's) and from the id map given whole to each setting."""
    import safety.alerts.episodes as episodes
    import safety.alerts.separation as separation
    from safety.alerts import truth_span
    t = _ends_at(truth, 6, 200.0)
    pic = _picture(t)
    kw = dict(id_col="target_id", map_id_col="id", confidences=(0.5, 0.95), fixed_est_h_m=(0.0, 3000.0),
              lookaheads_s=(60.0, 105.0), warning_s=(0.0,))
    want = stca_tradeoff(pic, _id_map(), truth_span(t, CFG), CFG, intervals=truth_intervals(t, CFG), **kw)
    calls = []
    real = separation.truth_ends
    for mod in (separation, episodes):
        monkeypatch.setattr(mod, "truth_ends", lambda *a, **k: calls.append(1) or real(*a, **k))
    made = []
    monkeypatch.setattr(episodes, "_map_epochs", lambda m, f=episodes._map_epochs: made.append(1) or f(m))
    assert stca_tradeoff(pic, _id_map(), t, CFG, **kw).equals(want)
    assert len(calls) == 1 and len(made) == 1


def test_the_grid_of_an_id_map_read_once_is_the_grid_of_each_setting(truth):
    """:class:`IdMap` keeps the grid of the map's own epochs for every setting whose alert
    epochs it holds, and adds a setting's other epochs as :func:`picture_grid` of the map does.
    Fails if a setting's alert epoch outside the map's is left out of its grid."""
    from safety.alerts.episodes import IdMap, picture_grid
    idm = _id_map()
    ids = IdMap.of(idm, truth, "id")
    inside = _alerts({(11, 12): [100, 105], (13, 14): [150]})
    outside = _alerts({(11, 12): [102]})             # an epoch off the map's 5-s grid
    for conflicts in (inside, outside, inside, outside.with_columns(pl.lit("other").alias("method"))):
        for methods in (None, ["m", "other"]):
            want = picture_grid(conflicts, idm, methods)
            assert picture_grid(conflicts, ids, methods).equals(want)
    assert picture_grid(outside, ids, None).height == picture_grid(inside, ids, None).height + 1
    assert set(ids.grids) == {("m",), ("other",), ("m", "other")}         # one grid per set of pictures


def test_tradeoff_curves_and_equal_nuisance(truth):
    pic = _picture(truth)
    curve = stca_tradeoff(pic, _id_map(), truth, CFG, id_col="target_id", map_id_col="id",
                          confidences=(0.5, 0.95, 0.999), fixed_est_h_m=(0.0, 300.0, 3000.0),
                          lookaheads_s=(60.0, 105.0), warning_s=(0.0, 30.0))
    assert curve.height == 2 * 6 * 2
    assert set(curve["threshold_mode"]) == {"covariance", "fixed"}
    assert ((curve["alerted_fraction"] >= 0) & (curve["alerted_fraction"] <= 1)).all()
    fx = curve.filter((pl.col("threshold_mode") == "fixed") & (pl.col("t_thr_s") == 105.0)
                      & (pl.col("warning_s") == 0.0)).sort("parameter")
    assert fx["nuisance_false_per_hour"].to_list() == sorted(fx["nuisance_false_per_hour"].to_list())
    # more look-ahead → more warning: ≥ 30 s warning is reachable at T = 105 s
    w30 = curve.filter((pl.col("warning_s") == 30.0) & (pl.col("t_thr_s") == 105.0))
    assert w30["alerted_fraction"].max() == 1.0
    cmp = compare_at_equal_nuisance(curve, warning_s=30.0)
    assert cmp.height == 2 and cmp["t_thr_s"].to_list() == [105.0, 105.0]
    met = tradeoff_metrics(curve)
    validate(met, "metrics")
    assert set(met["metric"]) == {"alerted_fraction", "nuisance_false_per_hour"}
    assert met["segment"][0].startswith("mode=")


def test_curves_predicted_in_windows_score_like_the_whole_picture(truth, monkeypatch):
    """The trade-off curves predict conflicts window by window (bounded memory) and keep only
    the alert rows and the epoch grid: the scores equal those of the whole screened table,
    with windows shorter than the confirmation's 4 epochs (20 s) and longer than the picture.
    Fails if the confirmation state is not carried across windows or the grid loses epochs."""
    import safety.alerts.tradeoff as alerts_mod
    from safety.alerts.episodes import picture_grid
    pic = _picture(truth, noise=400.0)
    ccs = (ConflictConfig(confirm_m=3, confirm_n=4),
           ConflictConfig(threshold_mode="fixed", fixed_est_h_m=3000.0, confirm_m=2, confirm_n=3))
    # every configuration predicted in one pass over the windows, each with its own state
    together = {w: alerts_mod.scored_rows(pic, ccs, "target_id", None, window_s=w) for w in (12.0, 20.0, 1e6)}
    for k, cc in enumerate(ccs):
        whole = predict_conflicts(pic, cc, id_col="target_id")
        assert whole.filter(~pl.col("alert")).height > 0 and whole["alert"].sum() > 0
        assert (whole["raw_alert"] & ~whole["alert"]).any()          # confirmation at work
        # an id map with holes (nothing matched) at epochs with screened rows but no alert: the
        # grid must still hold them
        quiet = whole.group_by("epoch").agg(pl.col("alert").any()).filter(~pl.col("alert"))["epoch"]
        assert quiet.len() > 0
        idm = _id_map().filter(~pl.col("epoch").is_in(quiet.implode()))
        want = alert_episodes(whole, idm, truth, AlertConfig(conflict=cc), id_col="id")
        for w in (12.0, 20.0, 1e6):
            rows = alerts_mod.scored_rows(pic, [cc], "target_id", None, window_s=w)[0]
            assert together[w][k].equals(rows)
            assert rows.height < whole.height
            assert picture_grid(rows, idm, None).equals(picture_grid(whole, idm, None))
            got = alert_episodes(rows, idm, truth, AlertConfig(conflict=cc), id_col="id")
            assert got.equals(want), (cc.threshold_mode, w)
    kw = dict(id_col="target_id", map_id_col="id", confidences=(0.5, 0.95), fixed_est_h_m=(300.0,))
    one = stca_tradeoff(pic, _id_map(), truth, CFG, **kw)
    monkeypatch.setattr(alerts_mod, "CURVE_WINDOW_S", 15.0)
    assert stca_tradeoff(pic, _id_map(), truth, CFG, **kw).equals(one)
    # a dense picture is cut by rows too: windows of a few rows, edges at a row's epoch
    monkeypatch.setattr(alerts_mod, "CURVE_WINDOW_S", 1e6)
    monkeypatch.setattr(alerts_mod, "CURVE_WINDOW_ROWS", 7)
    assert stca_tradeoff(pic, _id_map(), truth, CFG, **kw).equals(one)


def test_curves_spilled_setting_by_setting_score_like_held_ones(truth, tmp_path, monkeypatch):
    """With a spill directory each setting's predicted rows wait on disk and are read back one
    setting at a time (memory): the same rows in the same order, the same curves, and
    nothing left behind. Fails if a window's rows go to another setting or are read out of order."""
    import safety.alerts.tradeoff as alerts_mod
    from safety.alerts.episodes import picture_grid
    pic = _picture(truth, noise=400.0)
    ccs = [ConflictConfig(confirm_m=3, confirm_n=4),
           ConflictConfig(threshold_mode="fixed", fixed_est_h_m=3000.0, confirm_m=2, confirm_n=3)]
    held = alerts_mod.scored_rows(pic, ccs, "target_id", None, window_s=12.0)
    spilled = alerts_mod.scored_rows(pic, ccs, "target_id", None, window_s=12.0, spill=tmp_path / "s")
    assert held[0].height != held[1].height
    for rows, read in zip(held, spilled):
        assert read().equals(rows)
    assert not list((tmp_path / "s").rglob("*.parquet"))
    # the picture in time blocks (an on-disk picture): an epoch cut between two blocks, an empty
    # block; the same rows
    pic = pic.sort("epoch", maintain_order=True)
    cut = pic.height // 2 + 1
    assert pic["epoch"][cut - 1] == pic["epoch"][cut]
    blocks = [pic.slice(0, cut // 2), pic.clear(), pic.slice(cut // 2, cut - cut // 2), pic.slice(cut)]
    by_blocks = alerts_mod.scored_rows(iter(blocks), ccs, "target_id", None, window_s=12.0)
    whole = alerts_mod.scored_rows(pic, ccs, "target_id", None, window_s=12.0)
    for got, rows in zip(by_blocks, whole):
        assert got.sort(got.columns).equals(rows.sort(rows.columns))
    assert len(alerts_mod.scored_rows(iter([pic.clear()]), ccs, "target_id", None)) == 2
    kw = dict(id_col="target_id", map_id_col="id", confidences=(0.5, 0.95), fixed_est_h_m=(300.0,))
    monkeypatch.setattr(alerts_mod, "CURVE_WINDOW_S", 15.0)
    one = stca_tradeoff(pic, _id_map(), truth, CFG, **kw)
    assert stca_tradeoff(pic, _id_map(), truth, CFG, spill=tmp_path / "c", **kw).equals(one)


def test_config_validation():
    with pytest.raises(ValueError):
        AlertConfig(proximity_factor=0.9)
    with pytest.raises(ValueError):
        AlertConfig(merge_gap_s=-1)
    with pytest.raises(ValueError):
        AlertConfig(link_s=-1)
    with pytest.raises(ValueError, match="max_link_s"):
        AlertConfig(max_link_s=-1)
    assert AlertConfig().link == 105.0


def test_los_intervals_match_dense_sampling_on_irregular_truth():
    """Random piecewise-linear trajectories sampled at irregular, per-aircraft times (ADS-B-like),
    two runs: the closed-form LoS episodes equal those found by sampling the interpolated truth
    every 5 ms (to within the sampling step)."""
    rng = np.random.default_rng(4)
    rows = []
    for run in (0, 1):
        for tid in range(1, 9):
            t = np.sort(np.concatenate([[0.0, 120.0], rng.uniform(0, 120, rng.integers(2, 15))]))
            t = np.unique(np.round(t, 3)) + rng.uniform(0, 3) * (tid % 2)          # different spans
            x = np.cumsum(rng.normal(0, 1500, len(t)))
            y = np.cumsum(rng.normal(0, 1500, len(t)))
            h = 3000 + np.cumsum(rng.normal(0, 150, len(t)))
            rows += [{"run": run, "truth_id": tid, "time": _t(s), "x_m": a, "y_m": b, "z_m": c, "vx_mps": 0.0,
                      "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": c} for s, a, b, c in zip(t, x, y, h)]
    tr = pl.DataFrame(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")), pl.col("run").cast(pl.UInt32))
    cfg = AlertConfig(conflict=ConflictConfig(dr_h_m=2500.0, dr_v_m=300.0), level_pairs=False, merge_gap_s=0.0)
    got = loss_of_separation(tr, cfg)
    # reference: dense sampling of each aircraft's own linear interpolation
    dt = 0.005
    grid = np.arange(0.0, 124.0, dt)
    ref = []
    for run in (0, 1):
        tracks = {}
        for tid in range(1, 9):
            a = tr.filter((pl.col("run") == run) & (pl.col("truth_id") == tid)).sort("time")
            ts = np.array(_s(a["time"]))
            inside = (grid >= ts[0]) & (grid <= ts[-1])
            tracks[tid] = (inside, *(np.interp(grid, ts, a[c].to_numpy()) for c in ("x_m", "y_m", "alt_m")))
        for i in range(1, 9):
            for j in range(i + 1, 9):
                (mi, xi, yi, hi), (mj, xj, yj, hj) = tracks[i], tracks[j]
                los = mi & mj & (np.hypot(xj - xi, yj - yi) < 2500.0) & (np.abs(hj - hi) < 300.0)
                edges = np.flatnonzero(np.diff(np.concatenate([[0], los.astype(int), [0]])))
                ref += [(run, i, j, grid[s], grid[e - 1]) for s, e in zip(edges[::2], edges[1::2])]
    got_rows = [(r["run"], r["truth_a"], r["truth_b"], (r["t_start"] - T0).total_seconds(),
                 (r["t_end"] - T0).total_seconds()) for r in got.to_dicts()]
    assert len(ref) >= 5
    assert [g[:3] for g in got_rows] == [r[:3] for r in sorted(ref)]
    for g, r in zip(got_rows, sorted(ref)):
        assert g[3] == pytest.approx(r[3], abs=2 * dt) and g[4] == pytest.approx(r[4], abs=2 * dt)


def test_no_alerts_still_scores_missed_losses(truth):
    from tertiary import contract as schema
    empty = schema.empty_frame("conflicts", False)
    m = _metrics(score_alerts(empty, _id_map(), truth, CFG, methods=["m"]))
    assert m["los_episodes"] == 1 and m["missed_los"] == 1 and m["alert_episodes"] == 0
    assert m["alerts_per_hour"] == 0.0 and math.isnan(m["warning_median_s"])
    assert alert_episodes(empty, _id_map(), truth, CFG, methods=["m"]).schema == pl.Schema(ALERTS_SCHEMA)


def _two(h_a, h_b, rate_a=None, rate_b=None, x_b=None, step=1.0) -> pl.DataFrame:
    """Two aircraft sampled every ``step`` s: A at x = 0, B at ``x_b`` (default 1 km away), with
    the given height series and (optional) reported vertical rates."""
    n = len(h_a)
    x_b = np.full(n, 1000.0) if x_b is None else np.asarray(x_b, float)
    rows = []
    for tid, x, h, r in ((1, np.zeros(n), h_a, rate_a), (2, x_b, h_b, rate_b)):
        for k in range(n):
            row = {"truth_id": tid, "time": _t(k * step), "x_m": float(x[k]), "y_m": 0.0, "z_m": float(h[k]),
                   "vx_mps": 0.0, "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": float(h[k])}
            if r is not None:
                row["alt_rate_mps"] = float(r[k])
            rows.append(row)
    return pl.DataFrame(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def test_level_pairs_the_vertical_minimum_apart_are_separated_in_the_truth():
    """Adjacent levels 1 000 ft apart reported with a 25 ft quantum (975 ft now and then) are no
    loss when both aircraft are level; a bust levelling 150 ft under the other is; a climb through
    the other's level is, with the full minimum; without the aircraft's own rates the slope of
    the quantised altitude decides (the flips then count); the option off restores the plain rule."""
    ft = 0.3048
    n = 120
    flips = np.where(np.arange(n) % 10 == 5, 1000.0 - 25.0, 1000.0) * ft     # B flips 25 ft down every 10 s
    level = _two(np.full(n, 3000.0 * ft), 3000.0 * ft + flips, np.zeros(n), np.zeros(n))
    assert loss_of_separation(level).height == 0
    # the plain rule: exactly 1 000 ft is separated, each 975 ft flip (4 s → 6 s around it) a
    # "loss", the flips 10 s apart merged into one episode from the first to the last
    plain = loss_of_separation(level, AlertConfig(level_pairs=False))
    assert plain.height == 1 and (plain["t_end"][0] - plain["t_start"][0]).total_seconds() == pytest.approx(112.0)
    no_rate = _two(np.full(n, 3000.0 * ft), 3000.0 * ft + flips)
    assert loss_of_separation(no_rate).height >= 1
    bust = _two(np.full(n, 3000.0 * ft), np.full(n, 3150.0 * ft), np.zeros(n), np.zeros(n))
    assert loss_of_separation(bust).height == 1
    climb_h = 2000.0 * ft + 5.0 * np.arange(n)                                # 5 m/s through B's level
    climb = _two(climb_h, np.full(n, 2500.0 * ft), np.full(n, 5.0), np.zeros(n))
    got = loss_of_separation(climb)
    # the full minimum: |Δh| < 1 000 ft until h_a = 3 500 ft, t = (3 500 − 2 000) ft / 5 m/s = 91.44 s
    assert got.height == 1 and (got["t_end"][0] - T0).total_seconds() == pytest.approx(1500.0 * ft / 5.0, abs=1e-3)


def test_loss_intervals_a_few_seconds_apart_are_one_episode():
    """A pair that regains separation for 5 s in one encounter loses it once; 40 s apart, twice."""
    n = 200
    x = np.full(n, 1000.0)
    x[50:55] = 9000.0                    # 5 s apart horizontally beyond the minimum
    x[100:140] = 9000.0                  # 40 s
    tr = _two(np.full(n, 1000.0), np.full(n, 1000.0), np.zeros(n), np.zeros(n), x_b=x)
    assert loss_of_separation(tr).height == 2
    assert loss_of_separation(tr, AlertConfig(merge_gap_s=0.0)).height == 3


def _crowd(seed: int = 11, with_rate: bool = False) -> pl.DataFrame:
    """30 aircraft in a 30 km box, two runs, each with its own sample times and a ~75 s gap;
    levels 300 and 100 m apart (the level-pair tolerance matters) and, ``with_rate``, the
    truth's own vertical rate."""
    rng = np.random.default_rng(seed)
    rows = []
    for run in (0, 1):
        for tid in range(30):
            t = np.sort(rng.uniform(0.0, 400.0, 80))
            t = np.unique(np.round(np.concatenate([t[:30], t[45:]]), 2))        # a gap of ~75 s
            x = rng.uniform(-15e3, 15e3) + np.cumsum(rng.normal(0, 250, len(t)))
            y = rng.uniform(-15e3, 15e3) + np.cumsum(rng.normal(0, 250, len(t)))
            h = rng.choice([3000.0, 3300.0, 4600.0, 4700.0]) + np.cumsum(rng.normal(0, 20, len(t)))
            rate = rng.choice([0.0, 0.0, 4.0], len(t))
            rows += [{"run": run, "truth_id": tid, "time": _t(s), "x_m": a, "y_m": b, "z_m": c, "vx_mps": 0.0,
                      "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": c, **({"alt_rate_mps": v} if with_rate else {})}
                     for s, a, b, c, v in zip(t, x, y, h, rate)]
    return pl.DataFrame(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")),
                                           pl.col("run").cast(pl.UInt32))


@pytest.mark.parametrize("block", [1, 5, 32, 1000])
def test_the_boxed_screen_keeps_every_loss_an_unscreened_search_finds(block, monkeypatch):
    """The loss-of-separation screen (aircraft × block boxes, then segment boxes) against no
    screen at all (every pair of segments in the same union interval): the same LoS and
    proximity intervals, en-route minima included. 30 aircraft in a 30 km box, two runs, each
    aircraft with a few long gaps in its samples (the widest boxes, queried one by one) and
    its own sample times, and block sizes from one interval to more than the recording."""
    import safety.alerts.separation as al
    tr = _crowd()
    def every_pair(rs, reach_h, reach_v):
        seg = np.flatnonzero(rs["ac"][1:] == rs["ac"][:-1])
        seg = seg[np.argsort(rs["gk"][seg], kind="stable")]
        g = rs["gk"][seg]
        end = np.searchsorted(g, g, "right")                 # each segment with every later one of its group
        n = end - np.arange(len(seg)) - 1
        i = np.repeat(np.arange(len(seg)), n)
        j = i + 1 + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        return seg[i], seg[j]

    args = dict(dr_h_m=2000.0, dr_v_m=300.0, factors=(1.0, 1.5), enroute=(4500.0, 3000.0, 300.0))
    boxed = al.pair_segments
    monkeypatch.setattr(al, "pair_segments", lambda rs, rh, rv: boxed(rs, rh, rv, block))
    got = al.separation_intervals(tr, **args)
    monkeypatch.setattr(al, "pair_segments", every_pair)
    want = al.separation_intervals(tr, **args)
    assert want[0].height >= 10 and want[1].height > want[0].height
    for g, w in zip(got, want):
        assert g.equals(w)


@pytest.mark.parametrize("rows", [2, 7, 60, 900])
def test_the_truth_resampled_a_block_of_union_times_at_a_time_gives_the_whole_grids_intervals(rows, monkeypatch):
    """The truth's LoS and proximity intervals computed a block of union sample times at a time
    (down to one interval per block: 2 rows ask for the smallest block) equal those of the
    whole grid at once, and the pieces of an encounter cut by a block boundary are one episode.
    Two runs with their own sample times, gaps, level pairs with the truth's rates, en-route
    minima and an aerodrome zone. The whole grid is the blocks' union: the rows of every block
    are the whole-grid rows at its union times, and each segment is in exactly one block."""
    import safety.alerts.separation as al
    tr = _crowd(5, with_rate=True)
    args = dict(dr_h_m=2000.0, dr_v_m=300.0, factors=(1.0, 1.5), enroute=(4500.0, 3000.0, 300.0),
                level_pairs=(30.0, 2.5), merge_gap_s=15.0,
                zones=[AerodromeZone(x_m=0.0, y_m=0.0, radius_m=4000.0, ceiling_m=3200.0)])
    whole = al.separation_intervals(tr, **args)
    assert whole[0].height >= 5 and whole[1].height > whole[0].height
    blocks = al.resampled_blocks
    seen = []

    def recorded(tr_, max_rows, rows_=al.RESAMPLE_ROWS):
        for rs in blocks(tr_, max_rows, rows):
            seen.append(rs)
            yield rs
    monkeypatch.setattr(al, "resampled_blocks", recorded)
    got = al.separation_intervals(tr, **args)
    assert len(seen) > (1 if rows > 2 else 300)
    for g, w in zip(got, whole):
        assert g.equals(w)
    # segments (consecutive rows of one aircraft) of all blocks: each (run, aircraft, start) once
    starts = np.concatenate([np.column_stack([rs["run"][rs["ac"]], rs["tid"][rs["ac"]], rs["t"]])[
        np.flatnonzero(rs["ac"][1:] == rs["ac"][:-1])] for rs in seen])
    assert len(np.unique(starts, axis=0)) == len(starts)
    one = list(blocks(al.truth_heights(tr), 10**9, 10**9))
    want = sum(int(np.sum(rs["ac"][1:] == rs["ac"][:-1])) for rs in one)
    assert len(starts) == want


def test_quantised_altitudes_exactly_the_vertical_minimum_apart_are_separated():
    """Two aircraft crossing head-on 1 000 ft apart in quantised (25 ft) altitude, one of them
    jittering by a quantum between replies (so not "level" for the level-pair rule): the
    height difference is at, never below, the minimum — no loss of separation; 25 ft closer it
    is one."""
    t = np.arange(0.0, 301.0)
    jitter = np.where((t.astype(int) // 5) % 2 == 0, 0.0, 25.0 * 0.3048)     # 5 s at each code
    # FL280 over FL270: in metres their difference rounds to just under 304.8 m (the minimum)
    hi = 28000.0 * 0.3048 + jitter
    for low_ft, expect in ((27000.0, 0), (27025.0, 1)):
        low = np.full_like(t, low_ft * 0.3048)
        rows = []
        for tid, x0, vx, h in ((1, -30000.0, 150.0, low), (2, 30000.0, -150.0, hi)):
            rows.append(pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": x0 + vx * t, "y_m": 0.0,
                                      "z_m": h, "vx_mps": vx, "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": h}))
        truth = pl.concat(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))
        los = loss_of_separation(truth, AlertConfig(conflict=ConflictConfig(airspace="en-route")))
        assert los.height == expect, (low_ft, los)


def _random_scene(seed: int) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Conflict rows of two runs and three pictures, alert or not, some epochs with no alert;
    an id map per picture over other epochs too, missing some of the conflicts' epochs, some
    ids mapped twice at an epoch (to different aircraft) or not at all."""
    rng = np.random.default_rng(seed)
    rows, ids = [], []
    for run in (0, 1):
        for method in ("a", "b", "c"):
            epochs = sorted(rng.choice(len(GRID), size=30, replace=False))
            mapped = [e for e in range(len(GRID)) if rng.random() < 0.7]
            for e in epochs:
                for _ in range(rng.integers(1, 4)):
                    # the encounters of the truth (1-2 a loss, 3-4 a proximity) half of the time
                    a, b = ((11, 12), (13, 14))[int(rng.integers(2))] if rng.random() < 0.5 else sorted(
                        rng.choice(np.arange(11, 19), size=2, replace=False))
                    rows.append({"run": run, "epoch": GRID[e], "method": method, "id_a": a, "id_b": b,
                                 "alert": bool(rng.random() < 0.35), "r_min_m": float(rng.choice([500.0, 900.0])),
                                 "dz_min_m": float(rng.random() * 100), "t_min_s": float(rng.random() * 120),
                                 "severity": float(rng.random())})
            for e in mapped:
                for i in range(11, 19):
                    if rng.random() < 0.9:
                        ids.append({"run": run, "method": method, "epoch": GRID[e], "id": i,
                                    "truth_id": int(rng.choice([i - 10, i - 10, i - 10, rng.integers(1, 9)]))})
                    if rng.random() < 0.1:
                        ids.append({"run": run, "method": method, "epoch": GRID[e], "id": i,
                                    "truth_id": int(rng.integers(1, 9))})
    conflicts = pl.DataFrame(rows, schema={"run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "method": pl.String,
                                           "id_a": pl.UInt64, "id_b": pl.UInt64, "alert": pl.Boolean,
                                           "r_min_m": pl.Float64, "dz_min_m": pl.Float64, "t_min_s": pl.Float64,
                                           "severity": pl.Float64})
    id_map = pl.DataFrame(ids, schema={"run": pl.UInt32, "method": pl.String, "epoch": pl.Datetime("us", "UTC"),
                                       "id": pl.UInt64, "truth_id": pl.Int64})
    return conflicts, id_map


@pytest.mark.parametrize("seed", range(6))
def test_scoring_the_rows_it_reads_equals_scoring_every_row(truth, seed):
    """The pipeline scores the alerts from the conflict rows and id-map rows the scoring reads
    (a day's truth picture has tens of millions of each): the metrics, alerts and losses equal
    those of every row, also when the conflict rows are reduced part by part (an empty part
    among them). Fails if a picture epoch with no alert is dropped from the grid, from either
    table (flicker, adjacency and picture hours change), if an id-map row of an alerting id is
    dropped (the pair's aircraft change), or if an empty part keeps other columns."""
    from safety.alerts import scored_conflicts, scored_ids, stca_tables_by_picture
    conflicts, id_map = _random_scene(seed)
    want = stca_tables_by_picture(conflicts, id_map, truth, CFG, id_col="id")
    assert want[1]["flicker"].sum() > 0 and want[1]["classification"].n_unique() >= 2
    cut = GRID[30]
    # a part without rows (a block of a picture with no conflict) has the columns of the others
    parts = pl.concat([scored_conflicts(conflicts.filter(pl.col("epoch") < cut)), scored_conflicts(conflicts.clear()),
                       scored_conflicts(conflicts.filter(pl.col("epoch") >= cut))])
    for c in (scored_conflicts(conflicts), parts):
        ids = scored_ids(id_map, c, "id")
        assert c.height < conflicts.height and ids.height < id_map.height
        got = stca_tables_by_picture(c, ids, truth, CFG, id_col="id")
        for a, b in zip(got, want):
            assert a.equals(b)
