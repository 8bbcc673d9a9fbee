"""En-route airspace: a pair of aircraft is separated by 5 NM unless both are below the floor of
the en-route airspace (in the terminal area, 3 NM) — in conflict prediction and in the
loss-of-separation scoring of the truth; the national scenario's airspace has its floor at
FL150, the level above which its traffic is planned 5 NM apart."""

from __future__ import annotations

import dataclasses
from datetime import timedelta

import numpy as np
import polars as pl
import pytest

from safety.alerts import AlertConfig, loss_of_separation, separation_intervals
from safety.conflicts import FT_M, NM_M, ConflictConfig, predict_conflicts
from tertiary.pipeline import PipelineConfig, adapt_to_scenario

from test_approach_volumes import T0, _picture     # one track table for the STCA's airspace tests

FIXED = ConflictConfig(threshold_mode="fixed")          # terminal: R_thr = 5 556 + 500 + 300 = 6 356 m
FL150 = 15_000 * FT_M
EN_ROUTE = dataclasses.replace(FIXED, enroute_above_m=FL150)   # en-route: 9 260 + 800 = 10 060 m
FL300, FT3000 = 30_000 * FT_M, 3_000 * FT_M


def _crossing(h_a: float, h_b: float, miss_m: float = 4.5 * NM_M) -> pl.DataFrame:
    """Two aircraft at 230 m/s on tracks crossing at right angles, closest approach ``miss_m``
    60 s ahead: a east through the origin, b north along x = miss/√2 (at 60 s the pair is
    miss·(1, 1)/√2 apart, perpendicular to their relative velocity (−230, 230))."""
    off = miss_m / np.sqrt(2.0)
    return _picture([[-230.0 * 60, 0.0, h_a], [off, off - 230.0 * 60, h_b]],
                    [[230.0, 0.0, 0.0], [0.0, 230.0, 0.0]])


def _alert(df: pl.DataFrame, cfg: ConflictConfig) -> bool:
    out = predict_conflicts(df, cfg)
    return bool(out["alert"].any()) if out.height else False


def test_pair_above_the_floor_is_decided_by_the_en_route_minimum():
    """A 4.5 NM (8.3 km) pass at FL300: inside the en-route threshold (10.1 km), outside the
    terminal one (6.4 km); the threshold columns are the en-route ones."""
    df = _crossing(FL300, FL300)
    assert not _alert(df, FIXED)
    out = predict_conflicts(df, EN_ROUTE)
    assert out["alert"].to_list() == [True]
    assert out["r_thr_m"][0] == pytest.approx(5 * NM_M + FIXED.pilot_h_m + FIXED.fixed_est_h_m)


def test_pair_below_the_floor_keeps_the_configured_minimum_and_across_it_takes_the_en_route_one():
    """The same pass at 3 000 ft: terminal minimum, no alert; a real 2 NM pass at 3 000 ft alerts
    with or without the en-route floor, with the same row. Across the floor (one 200 ft above
    FL150, one 300 ft below): only one of them is in the terminal area, 5 NM, an alert."""
    assert not _alert(_crossing(FT3000, FT3000), EN_ROUTE)
    low = _crossing(FT3000, FT3000, 2 * NM_M)
    assert _alert(low, EN_ROUTE) and predict_conflicts(low, EN_ROUTE).equals(predict_conflicts(low, FIXED))
    across = _crossing(FL150 + 200 * FT_M, FL150 - 300 * FT_M)
    assert not _alert(across, FIXED) and _alert(across, EN_ROUTE)


def test_floor_above_every_track_changes_nothing():
    """Several pairs at mixed heights: a floor above all of them gives the table of no floor."""
    rng = np.random.default_rng(4)
    n = 30
    pos = np.column_stack([rng.uniform(-12e3, 12e3, n), rng.uniform(-12e3, 12e3, n),
                           rng.choice([FT3000, FL300, FL300 + 300.0], n)])
    vel = np.column_stack([rng.uniform(-230, 230, n), rng.uniform(-230, 230, n), np.zeros(n)])
    df = _picture(pos, vel)
    high = dataclasses.replace(FIXED, enroute_above_m=20_000.0)
    assert predict_conflicts(df, high).equals(predict_conflicts(df, FIXED))
    # and with a real floor, the pairs of two tracks below it are those of no floor
    h = pl.DataFrame({"id": np.arange(1, n + 1, dtype=np.uint64), "h": pos[:, 2]})

    def both_low(out: pl.DataFrame) -> pl.DataFrame:
        return (out.join(h.rename({"id": "id_a", "h": "ha"}), on="id_a").join(h.rename({"id": "id_b", "h": "hb"}),
                                                                            on="id_b")
                .filter((pl.col("ha") < FL150) & (pl.col("hb") < FL150)).drop("ha", "hb"))
    assert both_low(predict_conflicts(df, FIXED)).height
    assert both_low(predict_conflicts(df, EN_ROUTE)).equals(both_low(predict_conflicts(df, FIXED)))


def _truth(h_a: float, h_b: float, miss_m: float) -> pl.DataFrame:
    """The two aircraft of :func:`_crossing` flown for 120 s, sampled every second."""
    t = np.arange(121.0)
    times = [T0 + timedelta(seconds=float(s)) for s in t]
    off = miss_m / np.sqrt(2.0)
    a = dict(truth_id=1, x_m=-230.0 * 60 + 230.0 * t, y_m=np.zeros_like(t), vx_mps=230.0, vy_mps=0.0, alt_m=h_a)
    b = dict(truth_id=2, x_m=np.full_like(t, off), y_m=off - 230.0 * 60 + 230.0 * t, vx_mps=0.0, vy_mps=230.0,
             alt_m=h_b)
    frames = [pl.DataFrame({"truth_id": np.full(len(t), d["truth_id"], np.int64), "time": times,
                            "x_m": d["x_m"], "y_m": d["y_m"], "z_m": np.full(len(t), d["alt_m"]),
                            "vx_mps": np.full(len(t), d["vx_mps"]), "vy_mps": np.full(len(t), d["vy_mps"]),
                            "vz_mps": np.zeros(len(t)), "alt_m": np.full(len(t), d["alt_m"])})
              for d in (a, b)]
    return pl.concat(frames).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def test_loss_of_separation_of_the_truth_follows_the_airspace():
    """A 4.5 NM pass at FL300 is a loss of separation en-route (closed form: |r| < 5 NM for
    2·sqrt((5 NM)² − (4.5 NM)²)/(230·√2) s around the closest approach), none at 3 000 ft or
    without the floor; across the floor it is one (one aircraft is not in the terminal area);
    with proximity factor 1.5 a 6.5 NM pass at FL300 is near, judged by 3 NM it is not."""
    en = AlertConfig(conflict=EN_ROUTE)
    los = loss_of_separation(_truth(FL300, FL300, 4.5 * NM_M), en)
    assert los.height == 1
    half = np.sqrt((5 * NM_M) ** 2 - (4.5 * NM_M) ** 2) / (230.0 * np.sqrt(2.0))
    dur = (los["t_end"][0] - los["t_start"][0]).total_seconds()
    assert dur == pytest.approx(2 * half, abs=1e-3)
    assert loss_of_separation(_truth(FL300, FL300, 4.5 * NM_M), AlertConfig(conflict=FIXED)).height == 0
    assert loss_of_separation(_truth(FT3000, FT3000, 4.5 * NM_M), en).height == 0
    assert loss_of_separation(_truth(FL150 + 200 * FT_M, FL150 - 300 * FT_M, 4.5 * NM_M), en).height == 1
    assert loss_of_separation(_truth(FT3000, FT3000, 2 * NM_M), en).height == 1
    tr = _truth(FL300, FL300, 6.5 * NM_M)
    near = separation_intervals(tr, 3 * NM_M, 1000 * FT_M, (1.0, 1.5), enroute=(FL150, 5 * NM_M, 1000 * FT_M))
    assert (near[0].height, near[1].height) == (0, 1)
    assert separation_intervals(tr, 3 * NM_M, 1000 * FT_M, (1.0, 1.5))[1].height == 0


def test_validation():
    with pytest.raises(ValueError, match="enroute_above_m"):
        ConflictConfig(enroute_above_m=float("nan"))
    with pytest.raises(ValueError, match="enroute_h_m"):
        ConflictConfig(enroute_h_m=0.0)
    assert EN_ROUTE.enroute().sep_h_m == pytest.approx(5 * NM_M) and EN_ROUTE.enroute().enroute_above_m is None


def test_pipeline_takes_the_floor_from_the_national_scenario(small_terminal):
    """national: FL150 (its traffic is planned 5 NM apart above it); terminal-area: none; off, or
    configured, it is left alone."""
    from tertiary.simulate import load_scenario

    class _Ds:
        scenario = load_scenario("national")
        origin = None
    cfg = adapt_to_scenario(PipelineConfig(stca_approach_volumes=False), _Ds())
    assert cfg.conflicts.enroute_above_m == pytest.approx(FL150 - 500 * FT_M)     # FL150 level is in it
    assert adapt_to_scenario(PipelineConfig(), small_terminal).conflicts.enroute_above_m is None
    off = PipelineConfig(stca_approach_volumes=False, stca_enroute_floor=False)
    assert adapt_to_scenario(off, _Ds()).conflicts.enroute_above_m is None
    mine = PipelineConfig(stca_approach_volumes=False, conflicts=dataclasses.replace(FIXED, enroute_above_m=9000.0))
    assert adapt_to_scenario(mine, _Ds()).conflicts.enroute_above_m == 9000.0


def test_the_run_notes_say_which_minima_the_alerts_are_scored_on():
    from tertiary.pipeline import note_minima
    notes: list[str] = []
    note_minima(FIXED, notes)
    assert notes == []
    note_minima(EN_ROUTE, notes)
    note_minima(EN_ROUTE, notes)
    assert len(notes) == 1
    assert "3 NM / 1,000 ft for pairs both below 15,000 ft (terminal), 5 NM / 1,000 ft otherwise" in notes[0]


def test_each_pair_is_predicted_once_by_the_airspace_that_decides_it(monkeypatch):
    """Tracks above and below the floor, some established on a final, some in an aerodrome zone,
    predicted under two settings at once: every (setting, pair) reaches the pair geometry once,
    by the prediction that decides it, and the table is that of the settings one at a time.
    Fails if the en-route pass, the general pass or the zone's setting also predicts the pairs
    another one decides (their rows were dropped afterwards)."""
    from safety.conflicts import AerodromeZone, ApproachVolume, conflicts_steps, init_conflict_state
    from safety.conflicts import pairs as pairs_mod
    rng = np.random.default_rng(11)
    n = 40
    pos = np.column_stack([rng.uniform(-15e3, 15e3, n), rng.uniform(-2e3, 2e3, n),
                           rng.choice([900.0, 1_200.0, FL300, FL150 - 100.0], n)])
    vel = np.column_stack([rng.choice([-120.0, 120.0], n), rng.uniform(-5, 5, n), np.zeros(n)])
    df = _picture(pos, vel)
    final = ApproachVolume(-16e3, 0.0, 270.0, length_m=38_500.0)       # arrivals fly west
    zone = AerodromeZone(10e3, 0.0, name="LFXX")
    cfgs = [dataclasses.replace(EN_ROUTE, mode="corrected", approach_volumes=(final,), aerodrome_zones=(zone,)),
            dataclasses.replace(EN_ROUTE, mode="corrected", approach_volumes=(final,))]
    seen: list[tuple] = []

    def counted(cfg, st, terms, i, j, *a, f=pairs_mod._evaluate_pairs, **k):
        seen.extend((cfg.aerodrome_zones != (), *sorted([(st[0, p], st[1, p]), (st[0, q], st[1, q])]))
                    for p, q in zip(i, j))
        return f(cfg, st, terms, i, j, *a, **k)
    monkeypatch.setattr(pairs_mod, "_evaluate_pairs", counted)
    got = conflicts_steps([init_conflict_state()] * 2, df, cfgs, slim=False)
    assert len(seen) > 100 and len(seen) == len(set(seen))
    for (out, _), cfg in zip(got, cfgs):
        alone = conflicts_steps([init_conflict_state()], df, [cfg], slim=False)[0][0]
        assert out.equals(alone) and out.height


def test_settings_that_leave_the_same_pairs_out_test_them_once(monkeypatch):
    """Settings of one screen with the same en-route floor drop the pairs below it with one test
    per screen chunk, however many settings there are."""
    from safety.conflicts import conflicts_steps, init_conflict_state
    from safety.conflicts import pairs as pairs_mod
    rng = np.random.default_rng(5)
    n = 40
    pos = np.column_stack([rng.uniform(-15e3, 15e3, n), rng.uniform(-2e3, 2e3, n),
                           rng.choice([900.0, FL300], n)])
    vel = np.column_stack([rng.choice([-120.0, 120.0], n), rng.uniform(-5, 5, n), np.zeros(n)])
    df = _picture(pos, vel)
    calls: list[int] = []
    monkeypatch.setattr(pairs_mod, "in_one_group", lambda *a, f=pairs_mod.in_one_group: calls.append(1) or f(*a))

    def tests_for(cfgs: list[ConflictConfig]) -> int:
        calls.clear()
        conflicts_steps([init_conflict_state()] * len(cfgs), df, cfgs, slim=False)
        return len(calls)
    one = tests_for([EN_ROUTE])
    assert one > 0
    assert tests_for([dataclasses.replace(EN_ROUTE, fixed_est_h_m=e) for e in (0.0, 300.0, 900.0)]) == one
