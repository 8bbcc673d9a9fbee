"""The secondary tracker as a step function (docs: notes/stream_contract.md).

Oracle: the whole-run :func:`track_methods` on the same fused pictures. Expected: the windowed
steps' tracks, concatenated, equal it row for row (same ids, values to 1e-9) for any cut of the
run into consecutive windows — including windows shorter than the slowest scan period (12 s
here) and windows holding no plot — with the state pickled between windows as the engine
checkpoints it.
"""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary import pipeline
from tertiary.filters import make_filter
from tertiary.contract import TIME
from tertiary.simulate import load_scenario, simulate
from tertiary.stages.tracking.tracker import (TrackerConfig, TrackState, init_track_state, track_methods, track_step)

FILTERS = ("singer", "imm_sym", "cv")
KEYS = ["method", "filter", "run", "epoch", "track_id"]
S = 1_000_000                                  # µs per second


@pytest.fixture(scope="module")
def pictures() -> pl.DataFrame:
    """Every fusion method's picture (no centralised reference) of a small terminal area, 2 runs."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, runs=2, traffic=dataclasses.replace(cfg.traffic, aircraft=20))
    ds = simulate(cfg)
    assert ds.radars["scan_period_s"].max() == 12.0
    res = pipeline.process(ds, pipeline.PipelineConfig(filters=(), safety=False, evaluation=False,
                                                       centralized=False))
    return res.fused.filter(pl.col("method") != "centralized")


@pytest.fixture(scope="module")
def filters() -> dict:
    return {name: make_filter(name) for name in FILTERS}


@pytest.fixture(scope="module")
def whole(pictures, filters) -> pl.DataFrame:
    out = track_methods(pictures, filters, TrackerConfig())
    assert set(out["filter"].unique()) == set(FILTERS) and out["run"].n_unique() == 2
    assert (out["status"] == "coasting").any()       # the carry of misses is exercised
    return out


def _epochs_us(fused: pl.DataFrame) -> np.ndarray:
    return np.unique(fused["epoch"].cast(TIME).dt.epoch("us").to_numpy())


def _windowed(fused: pl.DataFrame, filters, cfg: TrackerConfig, cuts: list[int],
              state: TrackState | None = None) -> tuple[pl.DataFrame, list[int], TrackState]:
    """Steps over consecutive windows [cuts[k], cuts[k+1]) with the state pickled in between;
    the tracks concatenated, the number of fused rows of each window and the final state."""
    state = init_track_state(filters) if state is None else state
    us = fused["epoch"].cast(TIME).dt.epoch("us")
    parts, counts = [], []
    for t0, t1 in zip(cuts[:-1], cuts[1:]):
        win = fused.filter((us >= t0) & (us < t1))
        out, state = track_step(state, win, filters, cfg, t0, t1)
        state = pickle.loads(pickle.dumps(state))
        parts.append(out)
        counts.append(win.height)
    return pl.concat(parts, how="vertical"), counts, state


def _assert_same(got: pl.DataFrame, want: pl.DataFrame) -> None:
    assert got.height == want.height
    assert_frame_equal(got.sort(KEYS), want.sort(KEYS), check_exact=False, rel_tol=1e-9, abs_tol=1e-9)


def _cuts(fused: pl.DataFrame, kind: str) -> list[int]:
    ep = _epochs_us(fused)
    first, last = int(ep[0]), int(ep[-1]) + 1
    if kind == "halves":                          # one cut between two epochs mid-run
        return [first, int(ep[len(ep) // 2]) - S // 2, last]
    if kind == "short":                           # 7 s windows < the 12 s slowest scan, from a grid origin
        return list(range(first - 3 * S, last + 7 * S, 7 * S))
    if kind == "empty":                           # a leading, an interior and a trailing window with no plot
        k = len(ep) // 3
        return [first - 60 * S, first, int(ep[k]) + 1, int(ep[k + 1]), int(ep[2 * k]), last, last + 60 * S]
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["halves", "short", "empty"])
def test_windowed_tracks_equal_the_whole_run(pictures, filters, whole, kind):
    cuts = _cuts(pictures, kind)
    got, counts, state = _windowed(pictures, filters, TrackerConfig(), cuts)
    if kind == "short":
        assert max(np.diff(cuts)) < 12 * S and len(counts) > 40
    if kind == "empty":
        assert counts[0] == 0 and counts[2] == 0 and counts[-1] == 0 and min(counts[1], counts[3]) > 0
    _assert_same(got, whole)
    # and the state at the end: objects, counters, plot uids, ids, filter states
    ep = _epochs_us(pictures)
    _, one = track_step(init_track_state(filters), pictures, filters, TrackerConfig(), int(ep[0]), int(ep[-1]) + 1)
    _same_state(state, one, exact=False)


def test_windowed_m_of_n_nearest_equals_the_whole_run(pictures, filters):
    """The other initiation and assignment carry their tentatives and counters too."""
    cfg = TrackerConfig(initiation="m_of_n", assignment="nearest")
    sub = {k: filters[k] for k in ("singer", "imm_sym")}
    got, _, _ = _windowed(pictures, sub, cfg, _cuts(pictures, "short"))
    _assert_same(got, track_methods(pictures, sub, cfg))


def test_a_given_time_origin_changes_only_round_off(pictures, filters, whole):
    """Object times are seconds since a fixed origin: an origin an hour before the data (the
    engine's grid origin) gives the same tracks to round-off, so dt is absolute."""
    cuts = _cuts(pictures, "halves")
    origin = cuts[0] - 3600 * S
    got, _, _ = _windowed(pictures, filters, TrackerConfig(), cuts, init_track_state(filters, origin_us=origin))
    _assert_same(got, whole)


def _mid_state(pictures, filters) -> tuple[TrackState, list[int]]:
    """The state of the run cut between two epochs, as near the middle as possible where every
    bank holds confirmed and tentative objects (new targets are confirmed in a few epochs)."""
    ep = _epochs_us(pictures)
    us = pictures["epoch"].cast(TIME).dt.epoch("us")
    for k in sorted(range(1, len(ep) - 1), key=lambda k: abs(k - len(ep) // 2)):
        cuts = [int(ep[0]), int(ep[k]) - S // 2, int(ep[-1]) + 1]
        _, state = track_step(init_track_state(filters), pictures.filter(us < cuts[1]), filters, TrackerConfig(),
                              cuts[0], cuts[1])
        if all(len(b.i) and (b.i[:, 1] == 2).any() and (b.i[:, 1] == 0).any() for b in state.banks.values()):
            return state, cuts
    raise AssertionError("no cut with confirmed and tentative objects in every bank")


def _same_state(a: TrackState, b: TrackState, exact: bool = True) -> None:
    """Equal states except ``reached_us``; floats to 1e-9 unless ``exact``."""
    assert a.keys == b.keys and a.origin_us == b.origin_us and a.next_uid == b.next_uid
    assert a.banks.keys() == b.banks.keys()
    for name in a.banks:
        x, y = a.banks[name], b.banks[name]
        np.testing.assert_array_equal(x.i, y.i)
        np.testing.assert_array_equal(x.next_id, y.next_id)
        pairs = [(x.f, y.f)] + [(x.filt_state[k], y.filt_state[k]) for k in y.filt_state]
        assert x.filt_state.keys() == y.filt_state.keys()
        for u, v in pairs:
            if exact:
                np.testing.assert_array_equal(u, v)
            else:
                np.testing.assert_allclose(u, v, rtol=1e-9, atol=1e-9)


def test_a_window_of_tentative_rows_only_changes_only_the_time_reached(pictures, filters):
    """Tentative rows (clutter) are no plots: such a window is an empty one."""
    state, cuts = _mid_state(pictures, filters)
    _, after = track_step(state, pl.DataFrame(), filters, TrackerConfig(), cuts[1], cuts[1] + 30 * S)
    _same_state(after, state)
    us = pictures["epoch"].cast(TIME).dt.epoch("us")
    clutter = pictures.filter(us >= cuts[1]).with_columns(pl.lit(True).alias("tentative"))
    _, after = track_step(state, clutter, filters, TrackerConfig(), cuts[1], cuts[2])
    _same_state(after, state)




def test_bad_windows_are_refused(pictures, filters):
    state, cuts = _mid_state(pictures, filters)
    us = pictures["epoch"].cast(TIME).dt.epoch("us")
    rest = pictures.filter(us >= cuts[1])
    with pytest.raises(ValueError, match="not after"):           # overlaps the previous window
        track_step(state, rest, filters, TrackerConfig(), cuts[1] - S, cuts[2])
    with pytest.raises(ValueError, match="filters"):
        track_step(state, rest, ("singer",), TrackerConfig(), cuts[1], cuts[2])
