"""Cleared levels from flight data (tertiary.stages.flight_data): validated with reasons, correlated with
reports by Mode 3/A code (unique plan only), simulated from the clearances (never from the truth
or from what transponders reply), carried to the tracks, and used by conflict prediction where no
selected level is downlinked."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safety.conflicts import ConflictConfig, predict_conflicts
from tertiary.core.errors import DataError
from tertiary.stages.flight_data import FLIGHT_PLANS_SCHEMA, check_flight_plans, correlate
from tertiary.simulate.traffic import ARRIVAL_CLEARED_M, SID_TOP_FL, flight_level_m

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
MIN = timedelta(minutes=1)


def _plans(rows) -> pl.DataFrame:
    return pl.DataFrame(rows, schema={"mode_3a": pl.String, "valid_from": pl.Datetime("us", "UTC"),
                                      "valid_to": pl.Datetime("us", "UTC"), "cleared_alt_m": pl.Float64}, orient="row")


def test_bad_flight_plans_are_rejected_with_their_reason():
    plans = _plans([("1234", T0, T0 + MIN, 2000.0), ("8123", T0, T0 + MIN, 2000.0), ("12", T0, T0 + MIN, 2000.0),
                    (None, T0, T0 + MIN, 2000.0), ("1235", T0 + MIN, T0, 2000.0), ("1236", T0, T0 + MIN, float("nan")),
                    ("1237", T0, T0 + MIN, 30_000.0), ("1240", None, T0 + MIN, 2000.0)])
    good, rej = check_flight_plans(plans)
    assert good["mode_3a"].to_list() == ["1234"] and good.schema == pl.Schema(FLIGHT_PLANS_SCHEMA)
    assert rej["input_table"].unique().to_list() == ["flight_plans"]
    assert rej["row_index"].to_list() == [1, 2, 3, 4, 5, 6, 7]
    reasons = rej["reason"].to_list()
    assert reasons[:3] == ["mode_3a: not four octal digits"] * 2 + ["mode_3a: missing"]
    assert reasons[3] == "valid_to: before valid_from" and "not finite" in reasons[4] and "outside" in reasons[5]
    assert reasons[6] == "valid_from/valid_to: missing"
    with pytest.raises(DataError, match="cleared_alt_m"):
        check_flight_plans(plans.drop("cleared_alt_m"))


def test_correlation_needs_one_plan_holding_the_code_at_the_report_time():
    plans, _ = check_flight_plans(_plans([
        ("1234", T0, T0 + 10 * MIN, 2000.0),
        ("4321", T0, T0 + 10 * MIN, 3000.0), ("4321", T0 + 5 * MIN, T0 + 10 * MIN, 3300.0),   # code given twice
        ("5555", T0 + 20 * MIN, T0 + 30 * MIN, 1000.0)]))
    reports = pl.DataFrame({"run": [0, 0, 0, 0, 0, 1], "mode_3a": ["1234", "1234", "4321", "4321", None, "5555"],
                            "time": [T0 + MIN, T0 + 11 * MIN, T0 + MIN, T0 + 6 * MIN, T0 + MIN, T0 + 25 * MIN],
                            "x": [1, 2, 3, 4, 5, 6]}).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))
    out = correlate(reports, plans)
    assert out["x"].to_list() == [1, 2, 3, 4, 5, 6]                       # rows and order kept
    assert out["cleared_alt_m"].to_list() == [2000.0, None, 3000.0, None, None, 1000.0]
    # a plan naming a run applies to that run only
    own = plans.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    assert correlate(reports, own)["cleared_alt_m"].to_list()[-1] is None


def test_simulated_plans_come_from_the_clearances(small_terminal):
    ds = small_terminal
    fp = ds.flight_plans
    assert "truth_id" not in fp.columns and fp.height >= ds.truth["truth_id"].n_unique()
    first = fp.sort("valid_from").group_by("callsign", maintain_order=True).first()
    truth = ds.truth.group_by("truth_id").agg(pl.col("callsign").first(), pl.col("squawk").first(),
                                              pl.col("role").first())
    j = truth.join(first, on="callsign", how="inner")
    assert j.height == truth.height
    assert (j["squawk"] == j["mode_3a"]).all()              # the assigned code, whatever is replied
    dep = j.filter(pl.col("role") == "departure")["cleared_alt_m"]
    arr = j.filter(pl.col("role") == "arrival")["cleared_alt_m"]
    assert dep.len() and (dep == flight_level_m(SID_TOP_FL, 1.0)).all()
    assert arr.len() and (arr == ARRIVAL_CLEARED_M).all()


def test_tracks_carry_the_cleared_level(small_terminal):
    from tertiary.pipeline import PipelineConfig, process
    res = process(small_terminal, PipelineConfig(methods=("information",), filters=("imm_sym",), evaluation=False,
                                                 safety=False, centralized=False))
    assert "cleared_alt_m" in res.tracks.columns and res.tracks["cleared_alt_m"].is_not_null().mean() > 0.8
    levels = set(small_terminal.flight_plans["cleared_alt_m"].to_list())
    assert set(res.tracks["cleared_alt_m"].drop_nulls().unique().to_list()) <= levels


# head-on, CPA 0 m at t = 100 s; A level at 3 600 m, B (Mode C only) climbing 12 m/s from 2 400 m
POS = np.array([[0.0, 0.0, 3600.0], [20000.0, 0.0, 2400.0]])
VEL = np.array([[100.0, 0.0, 0.0], [-100.0, 0.0, 12.0]])


def _picture(selected=None, cleared=None) -> pl.DataFrame:
    df = pl.DataFrame({"run": np.zeros(2, np.uint32), "epoch": [T0] * 2, "track_id": np.array([1, 2], np.uint64),
                       "x_m": POS[:, 0], "y_m": POS[:, 1], "z_m": POS[:, 2], "vx_mps": VEL[:, 0],
                       "vy_mps": VEL[:, 1], "vz_mps": VEL[:, 2], "alt_m": POS[:, 2], "alt_rate_mps": VEL[:, 2]}
                      ).with_columns(pl.col("epoch").cast(pl.Datetime("us", "UTC")))
    if selected is not None:
        df = df.with_columns(pl.Series("selected_alt_m", selected, dtype=pl.Float64))
    if cleared is not None:
        df = df.with_columns(pl.Series("cleared_alt_m", cleared, dtype=pl.Float64))
    return df


def _alert(df: pl.DataFrame) -> bool:
    return bool(predict_conflicts(df, ConflictConfig(threshold_mode="fixed"))["alert"].any())


def test_cleared_level_stops_a_climb_when_no_selected_level_is_known():
    """B cleared to 2 750 m (the level below A): no alert; without a cleared level it alerts;
    a downlinked selected level wins over the clearance (a bust selected at A's level alerts)."""
    assert _alert(_picture())
    assert not _alert(_picture(cleared=[3600.0, 2750.0]))
    assert _alert(_picture(selected=[3600.0, 3550.0], cleared=[3600.0, 2750.0]))
    assert not _alert(_picture(selected=[3600.0, None], cleared=[3600.0, 2750.0]))


def test_dataset_round_trip_keeps_the_flight_plans(small_terminal, tmp_path):
    from tertiary.io.dataset import read_dataset, write_dataset
    write_dataset(small_terminal, tmp_path / "ds")
    back = read_dataset(tmp_path / "ds")
    assert back.flight_plans.equals(small_terminal.flight_plans)
    # a dataset without the file has none
    (tmp_path / "ds" / "flight_plans.parquet").unlink()
    assert read_dataset(tmp_path / "ds").flight_plans.height == 0


def test_validate_and_run_reject_the_same_flight_plan_rows(small_terminal, tmp_path):
    import dataclasses
    from tertiary.pipeline import PipelineConfig, process, screen
    bad = small_terminal.flight_plans.with_columns(
        pl.when(pl.int_range(pl.len()) == 2).then(pl.lit("9999")).otherwise(pl.col("mode_3a")).alias("mode_3a"))
    ds = dataclasses.replace(small_terminal, flight_plans=bad)
    cfg = PipelineConfig(methods=("information",), filters=(), evaluation=False, safety=False, centralized=False)
    screened = screen(ds, cfg).rejects.filter(pl.col("input_table") == "flight_plans")
    ran = process(ds, cfg).rejects.filter(pl.col("input_table") == "flight_plans")
    assert screened.select("row_index", "reason").rows() == ran.select("row_index", "reason").rows() \
        == [(2, "mode_3a: not four octal digits")]
    with pytest.raises(DataError, match="flight_plans"):
        process(ds, dataclasses.replace(cfg, strict=True))


def test_partitioned_dataset_keeps_the_flight_plans(small_terminal, tmp_path):
    from tertiary.io.dataset import read_dataset
    from tertiary.simulate import write_stream
    write_stream(small_terminal.scenario, tmp_path / "parts", 600.0)          # one block
    assert read_dataset(tmp_path / "parts").flight_plans.equals(small_terminal.flight_plans)


_VALUES = {
    "mode_3a": st.one_of(st.none(), st.sampled_from(["1234", "7777", "0000", "8000", "12", "abcd", "", "12345"])),
    "valid_from": st.one_of(st.none(), st.datetimes(min_value=datetime(2000, 1, 1), max_value=datetime(2040, 1, 1))),
    "valid_to": st.one_of(st.none(), st.datetimes(min_value=datetime(2000, 1, 1), max_value=datetime(2040, 1, 1))),
    "cleared_alt_m": st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)),
}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.fixed_dictionaries(_VALUES), max_size=12))
def test_hostile_flight_plans_give_rejects_with_reasons_and_lose_nothing(rows):
    plans = pl.DataFrame(rows, schema={"mode_3a": pl.String, "valid_from": pl.Datetime("us"),
                                       "valid_to": pl.Datetime("us"), "cleared_alt_m": pl.Float64})
    good, rej = check_flight_plans(plans)
    assert good.height + rej.height == plans.height
    assert rej["reason"].is_not_null().all()
    assert good["mode_3a"].str.contains(r"^[0-7]{4}$").all() and good["cleared_alt_m"].is_finite().all()
    assert (good["valid_to"] >= good["valid_from"]).all()


@pytest.mark.parametrize("column, values", [("valid_from", ["noon", "one"]), ("cleared_alt_m", ["high", "low"]),
                                            ("mode_3a", [True, False])])
def test_a_wrongly_typed_flight_plan_column_is_named(column, values):
    plans = _plans([("1234", T0, T0 + MIN, 2000.0), ("1235", T0, T0 + MIN, 2000.0)])
    with pytest.raises(DataError, match=column):
        check_flight_plans(plans.with_columns(pl.Series(column, values)))


# ----------------------------------------------------------------- departure correlation
from tertiary.core import geo  # noqa: E402
from tertiary.stages.flight_data import DepartureConfig, departure_plans, departure_step, init_departure_state  # noqa: E402

FRAME = geo.LocalFrame(48.85, 2.35)
S = timedelta(seconds=1)


def _dep_plans(rows) -> pl.DataFrame:
    """(code, ATD or None, valid_from, valid_to, level) → valid plans; a departure names the
    aerodrome at the frame's origin."""
    plans = pl.DataFrame(
        [(c, f, t, lvl, 48.85 if atd else None, 2.35 if atd else None, atd) for c, atd, f, t, lvl in rows],
        schema={"mode_3a": pl.String, "valid_from": pl.Datetime("us", "UTC"), "valid_to": pl.Datetime("us", "UTC"),
                "cleared_alt_m": pl.Float64, "departure_lat_deg": pl.Float64, "departure_lon_deg": pl.Float64,
                "departure_time": pl.Datetime("us", "UTC")}, orient="row")
    good, rej = check_flight_plans(plans)
    assert rej.height == 0
    return good


def _track(radar: int, lt: int, code, t0: timedelta, n: int, x0: float, h0: float, dt: float = 5.0,
           climb: float = 10.0) -> list[tuple]:
    """A radar local track: n plots every dt s from t0, flying west from x0 and climbing."""
    return [(radar, lt, code, T0 + t0 + i * dt * S, x0 - 90.0 * dt * i, 0.0, h0 + climb * dt * i) for i in range(n)]


def _aligned(plots: list[tuple], plans: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(aligned rows with their code correlation, the reports they come from)."""
    rep = pl.DataFrame(plots, schema={"radar_id": pl.UInt32, "local_track_id": pl.UInt32, "mode_3a": pl.String,
                                      "time": pl.Datetime("us", "UTC"), "x_m": pl.Float64, "y_m": pl.Float64,
                                      "altitude_m": pl.Float64}, orient="row").sort("time")
    rep = rep.with_columns(pl.lit(0, pl.UInt32).alias("run"),
                           pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"))
    rep = correlate(rep, plans)
    return rep.with_columns(pl.col("time").alias("epoch")), rep


def _run(plots, plans, cuts=(), cfg=DepartureConfig()) -> pl.DataFrame:
    """cleared_alt_m of every aligned row after departure correlation, in windows cut at ``cuts``."""
    aligned, reports = _aligned(plots, plans)
    dep = departure_plans(plans, FRAME)
    edges = [T0 - MIN, *(T0 + c for c in cuts), T0 + 10_000 * MIN]
    state, out = init_departure_state(), []
    for a, b in zip(edges[:-1], edges[1:]):
        win = aligned.filter((pl.col("time") >= a) & (pl.col("time") < b))
        rep = reports.filter((pl.col("time") >= a) & (pl.col("time") < b))
        got, state = departure_step(state, win, rep, reports.select("run", "report_id", "mode_3a"), dep, cfg)
        assert got.drop("cleared_alt_m").equals(win.drop("cleared_alt_m"))       # rows and order kept
        out.append(got)
    return pl.concat(out).sort("report_id")


def test_a_departure_squawking_a_wrong_code_gets_its_plan_by_aerodrome_and_time():
    plans = _dep_plans([("1111", T0, T0, T0 + 30 * MIN, 2140.0),              # A's plan, never replied
                        ("2222", T0 + 5 * MIN, T0 + 5 * MIN, T0 + 30 * MIN, 2440.0),   # B's, replied by B
                        ("3333", None, T0, T0 + 30 * MIN, 9000.0)])            # an overflight's
    plots = (_track(1, 10, "5555", 40 * S, 30, 3000.0, 200.0)                 # A: wrong code, near, low, soon
             + _track(2, 7, "5555", 45 * S, 30, 2500.0, 250.0)                # A seen by a second radar
             + _track(1, 11, "2222", 330 * S, 10, 3000.0, 200.0)              # B: its own code
             + _track(2, 8, "6666", 350 * S, 10, 3000.0, 200.0)               # C: wrong code, only B's plan near
             + _track(3, 1, "5555", 30 * S, 5, 40_000.0, 200.0)               # D: far from the aerodrome
             + _track(4, 1, "4444", 30 * S, 5, 3000.0, 3000.0)                # E: near but high
             + _track(1, 10, "5555", 20 * MIN, 5, 3000.0, 200.0)              # A's number reused much later
             + _track(3, 2, "3333", 40 * S, 5, 3000.0, 9000.0)                # the overflight, by code
             + _track(2, None, "5555", 35 * S, 5, 3000.0, 200.0))             # plots without a track number, first
    out = _run(plots, plans)
    lvl = {k: out.filter((pl.col("radar_id") == k[0]) & (pl.col("local_track_id") == k[1])
                         & (pl.col("time") < T0 + 15 * MIN if k == (1, 10) else True))["cleared_alt_m"].to_list()
           for k in [(1, 10), (2, 7), (1, 11), (2, 8), (3, 1), (4, 1), (3, 2)]}
    assert lvl[(1, 10)] == [2140.0] * 30 and lvl[(2, 7)] == [2140.0] * 30       # paired, on every radar
    assert lvl[(1, 11)] == [2440.0] * 10 and lvl[(3, 2)] == [9000.0] * 5        # by code, untouched
    assert lvl[(2, 8)] == [None] * 10          # B's plan was replied before C appeared; A's ATD is too old
    assert lvl[(3, 1)] == [None] * 5 and lvl[(4, 1)] == [None] * 5
    assert out.filter(pl.col("local_track_id").is_null())["cleared_alt_m"].is_null().all()
    reused = out.filter((pl.col("local_track_id") == 10) & (pl.col("time") >= T0 + 15 * MIN))["cleared_alt_m"]
    assert reused.is_null().all()              # a new track under a reused number inherits nothing
    # the same answer whatever the windows, even cutting through the tracks' first plots
    for cuts in [(41 * S,), (2 * MIN, 5 * MIN + 40 * S), tuple(k * 20 * S for k in range(1, 70))]:
        assert _run(plots, plans, cuts)["cleared_alt_m"].to_list() == out["cleared_alt_m"].to_list()
    assert _run(plots, plans, cfg=DepartureConfig(enabled=False))["cleared_alt_m"].to_list() == \
        correlate(_aligned(plots, plans)[1], plans).sort("report_id")["cleared_alt_m"].to_list()


def test_an_ambiguous_departure_is_not_correlated():
    """Two unreplied departure plans whose ATDs fit the track: no correlation; a plan a radar's
    earlier track took is not given to its second track, but another radar may take it."""
    two = _dep_plans([("1111", T0, T0, T0 + 30 * MIN, 2140.0), ("1112", T0 + MIN, T0 + MIN, T0 + 30 * MIN, 2440.0)])
    plots = _track(1, 10, "5555", 90 * S, 5, 3000.0, 200.0)
    assert _run(plots, two)["cleared_alt_m"].is_null().all()
    one = _dep_plans([("1111", T0, T0, T0 + 30 * MIN, 2140.0)])
    plots = (_track(1, 10, "5555", 40 * S, 5, 3000.0, 200.0) + _track(1, 12, "5556", 60 * S, 5, 3000.0, 200.0)
             + _track(2, 3, "5556", 65 * S, 5, 3000.0, 200.0))
    out = _run(plots, one)
    by = out.group_by("radar_id", "local_track_id").agg(pl.col("cleared_alt_m").first()).sort("radar_id",
                                                                                              "local_track_id")
    assert by["cleared_alt_m"].to_list() == [2140.0, None, 2140.0]


@pytest.mark.parametrize("field", ["radius_m", "max_alt_m", "window_s", "max_gap_s"])
def test_departure_config_is_checked(field):
    with pytest.raises(ValueError, match=field):
        DepartureConfig(**{field: float("nan")})
    with pytest.raises(ValueError, match=field):
        DepartureConfig(**{field: -1.0})


def test_departure_columns_are_validated():
    plans = pl.DataFrame({"mode_3a": ["1234"] * 4, "valid_from": [T0] * 4, "valid_to": [T0 + MIN] * 4,
                          "cleared_alt_m": [2000.0] * 4, "departure_lat_deg": [48.8, None, 95.0, 48.8],
                          "departure_lon_deg": [2.3, 2.3, 2.3, 2.3],
                          "departure_time": [T0, T0, T0, T0 + 2 * MIN]}).with_columns(
        pl.col("valid_from", "valid_to", "departure_time").cast(pl.Datetime("us", "UTC")))
    good, rej = check_flight_plans(plans)
    assert good.height == 1 and rej["row_index"].to_list() == [1, 2, 3]
    assert "all three or none" in rej["reason"][0] and "globe" in rej["reason"][1]
    assert rej["reason"][2] == "departure_time: after valid_to"
    assert '"departure_lat_deg"' in rej["detail"][0]                # the row as given, nothing lost


def test_simulated_departure_plans_name_the_aerodrome_and_the_atd_to_the_minute(small_terminal):
    ds = small_terminal
    truth = (ds.truth.sort("time").group_by("truth_id").agg(pl.col("callsign").first(), pl.col("role").first(),
                                                            pl.col("time").first().alias("first"))
             .join(ds.flight_plans.sort("valid_from").group_by("callsign", maintain_order=True).first(),
                   on="callsign"))
    dep = truth.filter(pl.col("role") == "departure")
    assert dep.height and truth.filter(pl.col("role") != "departure")["departure_time"].is_null().all()
    assert (dep["departure_lat_deg"] == ds.origin.lat_deg).all() and (dep["departure_lon_deg"] == ds.origin.lon_deg).all()
    # lift-off inside the scenario: the ATD is its minute; airborne at the start: an earlier minute
    lifted = dep.filter(pl.col("first") > ds.truth["time"].min())
    assert lifted.height
    assert (lifted["departure_time"] == lifted["first"].dt.truncate("1m")).all()
    assert (dep["departure_time"].dt.second() == 0).all() and (dep["departure_time"] <= dep["first"]).all()


def test_run_pairs_a_wrongly_squawking_departure_with_its_plan(small_terminal):
    """A departure whose crew squawks a code no plan holds: by code it has no cleared level; the
    run pairs it with its plan by aerodrome and time, so its tracks carry the SID top."""
    import dataclasses
    from tertiary.pipeline import PipelineConfig, process
    ds = small_terminal
    first = ds.truth.sort("time").group_by("truth_id").agg(pl.col("role").first(), pl.col("time").first())
    lifted = first.filter((pl.col("role") == "departure") & (pl.col("time") > ds.truth["time"].min()))
    victim = int(lifted.sort("time")["truth_id"][0])
    used = set(ds.flight_plans["mode_3a"].to_list())
    wrong = next(f"{v:04o}" for v in range(0o1000, 0o7777) if f"{v:04o}" not in used)
    reports = ds.reports.with_columns(pl.when(pl.col("truth_id") == victim).then(pl.lit(wrong))
                                      .otherwise(pl.col("mode_3a")).alias("mode_3a"))
    bad = dataclasses.replace(ds, reports=reports)
    cfg = PipelineConfig(methods=("information",), filters=(), evaluation=False, safety=False, centralized=False)
    sid_top = flight_level_m(SID_TOP_FL, 1.0)

    def levels(c):
        aligned = process(bad, c).aligned.filter(pl.col("truth_id") == victim)
        return aligned["cleared_alt_m"]
    paired = levels(cfg)
    assert paired.is_not_null().mean() > 0.9 and (paired.drop_nulls() == sid_top).all()
    assert levels(dataclasses.replace(cfg, departures=DepartureConfig(enabled=False))).is_null().all()
