"""Another system's alert list (CAT004 → ``alerts``, ``external:SAC/SIC``): its aircraft
identified in the truth by Mode S, callsign or Mode 3/A, scored by the pictures' rules, and
shown beside the pictures in a run."""

from __future__ import annotations

import dataclasses
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from safety.alerts import AlertConfig, identify_aircraft, loss_of_separation, score_external
from tertiary import pipeline
from tertiary.contract import TABLES
from tertiary.io.dataset import read_dataset, write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore
from tertiary.store.sql_reports import run_report

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
SEP_H = 3 * 1852.0
#: the loss of the head-on pair 1–2 (1 km miss at t = 200 s)
LOS_START = 200.0 - math.sqrt(SEP_H ** 2 - 1000.0 ** 2) / 300.0
ALERT_COLUMNS = dict(TABLES["alerts"].required) | {c: t for c, t in TABLES["alerts"].optional.items()
                                                   if c not in ("induced", "valid")}


def _t(s: float) -> datetime:
    return T0 + timedelta(seconds=s)


def _aircraft(tid: int, x0: float, vx: float, y: float, t0: float = 0.0, t1: float = 300.0, **ident: str
              ) -> pl.DataFrame:
    t = np.arange(t0, t1 + 0.5, 1.0)
    return pl.DataFrame({"truth_id": tid, "time": [_t(s) for s in t], "x_m": x0 + vx * t, "y_m": float(y),
                         "z_m": 3000.0, "vx_mps": float(vx), "vy_mps": 0.0, "vz_mps": 0.0, "alt_m": 3000.0,
                         "icao24": f"abc{tid:03d}", "callsign": f"AFR{tid}", **ident}
                        ).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def _truth() -> pl.DataFrame:
    """1–2 and 3–4 head-on, each losing separation from LOS_START; 5–6 stay 30 km apart; 7 and 8
    squawk 4321 one after the other (the code reused), 9 and 10 squawk 7000 at once."""
    return pl.concat([
        _aircraft(1, -30000.0, 150.0, 0.0, squawk="1001"), _aircraft(2, 30000.0, -150.0, 1000.0, squawk="1002"),
        _aircraft(3, -30000.0, 150.0, 50000.0, squawk="1003"), _aircraft(4, 30000.0, -150.0, 51000.0, squawk="1004"),
        _aircraft(5, -30000.0, 150.0, 100000.0, squawk="1005"), _aircraft(6, 30000.0, -150.0, 130000.0, squawk="1006"),
        _aircraft(7, 0.0, 100.0, -90000.0, 0.0, 120.0, squawk="4321"),
        _aircraft(8, 0.0, 100.0, -120000.0, 150.0, 300.0, squawk="4321"),
        _aircraft(9, 0.0, 100.0, -150000.0, squawk="7000"), _aircraft(10, 0.0, 100.0, -180000.0, squawk="7000"),
    ])


def _alerts(*rows: dict, origin: datetime = T0) -> pl.DataFrame:
    """External alert rows as the import writes them (unscored, truth_a/_b null); ``s``, ``e``:
    start and end, seconds after ``origin``."""
    base = {"run": 0, "method": "external:1/2", "alert_epochs": 3, "flicker": 0, "classification": "unscored"}
    out = []
    for k, r in enumerate(rows):
        s, e = r.pop("s"), r.pop("e")
        out.append(base | {"id_a": 100 + 2 * k, "id_b": 101 + 2 * k, "alert_id": k, "duration_s": e - s,
                           "t_start": origin + timedelta(seconds=s), "t_end": origin + timedelta(seconds=e)} | r)
    return pl.DataFrame(out, schema=ALERT_COLUMNS)


def test_aircraft_identified_by_mode_s_then_callsign_then_mode_3a_alive_at_the_alert():
    """Mode S address first (case-insensitive; a conflicting callsign loses), then the callsign
    (blanks, case), then the Mode 3/A code of the aircraft holding it during the alert: 4321
    is 7's at 50 s and 8's at 200 s; 7000 held by two aircraft at once identifies neither."""
    al = _alerts(
        {"s": 10, "e": 20, "mode_s_ident_a": "ABC001", "mode_s_ident_b": "abc002", "callsign_a": "AFR3"},
        {"s": 10, "e": 20, "mode_s_ident_a": "ffffff", "callsign_a": "afr 3", "callsign_b": "AFR4"},
        {"s": 40, "e": 60, "mode_3a_a": "4321", "mode_3a_b": "1005"},
        {"s": 190, "e": 210, "mode_3a_a": "4321", "mode_3a_b": "1005"},
        {"s": 40, "e": 60, "mode_3a_a": "7000", "mode_3a_b": "1005"},
        {"s": 10, "e": 20, "callsign_a": "AFR1", "callsign_b": "AFR1"},
    )
    got = identify_aircraft(al, _truth()).select("truth_a", "truth_b").rows()
    assert got == [(1, 2), (3, 4), (5, 7), (5, 8), (None, None), (None, None)]


def test_genuine_with_its_warning_false_and_a_missed_loss():
    """An alert 80 s before the loss of 1–2 is genuine with 80 s warning; one on 5–6 (30 km
    apart) is false; the loss of 3–4, never alerted, is missed; one unknown aircraft → false,
    counted unidentified. Alerts per hour over the truth's 300 s."""
    al = _alerts({"s": LOS_START - 80.0, "e": LOS_START - 50.0, "mode_s_ident_a": "abc001", "mode_s_ident_b": "abc002"},
                 {"s": 100.0, "e": 120.0, "callsign_a": "AFR5", "callsign_b": "AFR6"},
                 {"s": 100.0, "e": 120.0, "callsign_a": "XYZ9", "callsign_b": "AFR6"})
    metrics, alerts, los = score_external(al, _truth(), AlertConfig())
    by_pair = {(r["truth_a"], r["truth_b"]): r for r in alerts.iter_rows(named=True)}
    assert by_pair[(1, 2)]["classification"] == "genuine"
    assert by_pair[(1, 2)]["warning_s"] == pytest.approx(80.0)
    assert by_pair[(5, 6)]["classification"] == "false"
    assert by_pair[(None, None)]["classification"] == "false"
    assert alerts["induced"].is_null().all() and sorted(alerts["alert_id"]) == [0, 1, 2]
    m = dict(metrics.select("metric", "value").rows())
    assert set(metrics["method"]) == {"external:1/2"}
    assert (m["los_episodes"], m["alerted_los"], m["missed_los"]) == (2.0, 1.0, 1.0)
    assert (m["genuine_alerts"], m["nuisance_alerts"], m["false_alerts"]) == (1.0, 0.0, 2.0)
    assert m["warning_median_s"] == pytest.approx(80.0) and m["unidentified_alerts"] == 1.0
    assert m["alerts_per_hour"] == pytest.approx(3 / (300.0 / 3600.0))
    missed = los.filter(~pl.col("alerted")).select("truth_a", "truth_b").rows()
    assert missed == [(3, 4)]


def test_episodes_of_one_pair_within_the_merge_gap_are_one():
    """Two alerts of the same aircraft pair (other track numbers) 10 s apart are one episode
    with one flicker; 40 s later a third is another episode."""
    ids = {"mode_s_ident_a": "abc001", "mode_s_ident_b": "abc002"}
    al = _alerts({"s": 100, "e": 110, **ids}, {"s": 120, "e": 130, **ids}, {"s": 170, "e": 180, **ids})
    _, alerts, _ = score_external(al, _truth(), AlertConfig())
    assert alerts.select("flicker", "alert_epochs", "duration_s").rows() == [(1, 6, 30.0), (0, 3, 10.0)]


def test_a_run_scores_the_datasets_external_alerts_beside_its_pictures(tmp_path):
    """A dataset directory with alerts.parquet: ``tertiary run`` scores the list on the truth
    beside its own picture, and the ``alert_scores`` report has both rows."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=180.0, traffic=dataclasses.replace(cfg.traffic, aircraft=8,
                                                                                conflict_pairs=2))
    ds = simulate(cfg)
    los = loss_of_separation(ds.truth, AlertConfig(), ds.origin).sort("t_start")
    assert los.height >= 2
    ident = dict(ds.truth.group_by("truth_id").agg(pl.col("icao24").first()).rows())
    first = ds.truth["time"].min()
    rows = [{"s": max((t - first).total_seconds() - 60.0, 0.0), "e": (t - first).total_seconds(),
             "mode_s_ident_a": ident[a], "mode_s_ident_b": ident[b]}
            for a, b, t in los.select("truth_a", "truth_b", "t_start").rows()[1:]]
    d = write_dataset(ds, tmp_path / "ds")
    _alerts(*rows, origin=first).write_parquet(d / "alerts.parquet")
    back = read_dataset(d)
    assert back.external_alerts.height == len(rows)
    pipeline.run(back, tmp_path / "run", pipeline.PipelineConfig(methods=("information",), filters=("singer",),
                                                                 centralized=False, stca_lookaheads_s=()))
    with RunStore.open(tmp_path / "run", read_only=True) as store:
        scores = run_report(store, "alert_scores")
    ext = scores.filter(pl.col("method") == "external:1/2").row(0, named=True)
    assert len(scores.filter(~pl.col("method").is_in(["external:1/2", "truth"]))) >= 1
    assert ext["los_episodes"] == los.height and ext["missed_los"] == 1
    assert ext["genuine_alerts"] == len(rows) and ext["false_alerts"] == 0
    assert ext["alerts_picture_induced"] is None
