"""The reference's three-scan test: a target is confirmed at the third of three successive scans
that move like an aircraft, with carried state equal to one whole-run call."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings, strategies as st

from tertiary.stages.fusion.scan_confirm import ScanState, scans_of, three_scan_step

V_MIN, V_MAX, GATE = 30.0, 350.0, 1500.0
T0 = datetime(2024, 1, 1, tzinfo=timezone.utc)


def _scans(target: int, xy: list[tuple[float, float]], period_s: float = 4.0, start: int = 0) -> pl.DataFrame:
    """One scan per epoch (every ``period_s``), its plot half a second before the epoch."""
    ep = [T0 + timedelta(seconds=period_s * (start + k)) for k in range(len(xy))]
    return pl.DataFrame({"run": [0] * len(xy), "target_id": [target] * len(xy), "epoch": ep,
                         "time": [e - timedelta(milliseconds=500) for e in ep],
                         "x": [p[0] for p in xy], "y": [p[1] for p in xy]})


def _flags(scans: pl.DataFrame) -> list[bool]:
    out, _ = three_scan_step(ScanState.empty(), scans, V_MIN, V_MAX, GATE)
    return out.sort("target_id", "epoch")["tentative"].to_list()


def test_an_aircraft_is_confirmed_at_its_third_scan():
    line = [(200.0 * 4 * k, 0.0) for k in range(5)]          # 200 m/s east
    assert _flags(_scans(1, line)) == [True, True, False, False, False]


@pytest.mark.parametrize("why, xy", [
    ("too slow for an aircraft", [(0.0, 0.0), (50.0, 0.0), (100.0, 0.0), (150.0, 0.0)]),
    ("too fast for an aircraft", [(0.0, 0.0), (3000.0, 0.0), (6000.0, 0.0), (9000.0, 0.0)]),
    ("third plot off the line", [(0.0, 0.0), (800.0, 0.0), (1600.0, 2000.0), (0.0, 5000.0)]),
])
def test_clutter_stays_tentative(why, xy):
    assert _flags(_scans(1, xy)) == [True] * len(xy), why


def test_a_targets_scans_are_never_another_targets_predecessors():
    """Target 2's two scans continue target 1's line: taken with target 1's scans before them
    they would pass, but a target needs three scans of its own."""
    one = _scans(1, [(0.0, 0.0), (800.0, 0.0), (1600.0, 0.0)])
    two = _scans(2, [(2400.0, 0.0), (3200.0, 0.0)], start=3)
    assert _flags(pl.concat([one, two])) == [True, True, False, True, True]


def test_the_extrapolation_uses_the_scans_times():
    """Scans 4 s then 8 s apart (a missed scan): the third plot lies 1 600 m on, twice the first
    step, which only the time-scaled extrapolation predicts (a per-scan one misses by 800 m >
    a 500 m circle)."""
    s = _scans(1, [(0.0, 0.0), (800.0, 0.0), (2400.0, 0.0)])
    s = s.with_columns(pl.Series("epoch", [T0, T0 + timedelta(seconds=4), T0 + timedelta(seconds=12)]))
    s = s.with_columns((pl.col("epoch") - timedelta(milliseconds=500)).alias("time"))
    out, _ = three_scan_step(ScanState.empty(), s, V_MIN, V_MAX, 500.0)
    assert out["tentative"].to_list() == [True, True, False]


def test_scans_of_takes_each_epochs_last_plot():
    ep = T0 + timedelta(seconds=4)
    plots = pl.DataFrame({"run": [0, 0, 0], "target_id": [1, 1, 1], "epoch": [ep, ep, ep],
                          "time": [T0 + timedelta(seconds=1), T0 + timedelta(seconds=3), T0 + timedelta(seconds=3)],
                          "radar_id": [2, 1, 2], "report_id": [7, 9, 8], "x": [1.0, 2.0, 3.0], "y": [0.0, 0.0, 0.0]})
    assert scans_of(plots)["x"].to_list() == [3.0]            # the latest time, then radar 2 after radar 1


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(1, 11), max_size=3, unique=True), seed=st.integers(0, 2**31))
def test_windows_give_the_whole_run_flags_and_the_state_stays_small(cuts, seed):
    rng = np.random.default_rng(seed)
    parts = []
    for tg in range(6):                                   # aircraft, clutter and mixtures
        speed = rng.choice([0.0, 150.0, 250.0, 900.0])
        xy = [(speed * 4 * k + rng.normal(0, 300), rng.normal(0, 300)) for k in range(12)]
        parts.append(_scans(tg, xy).sample(fraction=0.8, seed=int(rng.integers(1 << 30))))
    scans = pl.concat(parts).sort("epoch", "target_id")
    whole, _ = three_scan_step(ScanState.empty(), scans, V_MIN, V_MAX, GATE)
    state, got = ScanState.empty(), []
    edges = [T0 + timedelta(seconds=4 * c) for c in sorted(cuts)]
    for lo, hi in zip([None, *edges], [*edges, None]):
        sel = scans.filter((pl.col("epoch") >= lo if lo else pl.lit(True)) & (pl.col("epoch") < hi if hi else pl.lit(True)))
        out, state = three_scan_step(state, sel, V_MIN, V_MAX, GATE)
        got.append(out)
        assert (state.scans.group_by("run", "target_id").len()["len"].max() or 0) <= 2
        assert state.scans.join(state.targets, on=["run", "target_id"], how="semi").is_empty()
    key = ["target_id", "epoch"]
    assert pl.concat(got).sort(key).equals(whole.sort(key))
