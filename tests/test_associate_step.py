"""Association as a step function: any cut of a run into epoch windows gives the
whole-run ``associations`` and ``AssociationStats``."""

from __future__ import annotations

import dataclasses
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.stages import align as A
from tertiary.stages.association.associate import (AssociateState, AssociationConfig, AssociationStats, associate, associate_step, init_associate_state)
from tertiary.core.errors import OptionError
from tertiary.core.stage import T_MAX_US, T_MIN_US
from tertiary.pipeline import PipelineConfig, screen
from tertiary.simulate import load_scenario, simulate

SLOWEST_SCAN_S = 12.0                       # ENR-E of the terminal-area scenario
CONFIGS = {
    "default": AssociationConfig(),
    # fine identification on, a short carry gap (state pruning matters), Mahalanobis joint assignment
    "fine_joint": AssociationConfig(mode_3a="penalise", callsign="forbid", carry_gap_s=10.0,
                                    assignment="joint", cost="mahalanobis"),
}


@pytest.fixture(scope="module")
def aligned() -> pl.DataFrame:
    """Terminal-area, 20 aircraft, 300 s, two Monte-Carlo runs, identity columns aligned."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, runs=2,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=20))
    assert max(r.scan_period_s for r in cfg.radars) == SLOWEST_SCAN_S
    ds = simulate(cfg)
    pc = PipelineConfig(align=dataclasses.replace(PipelineConfig().align, identity=True))
    return A.expand(screen(ds, pc).plan, pc.align)


def _epoch_us(frame: pl.DataFrame) -> np.ndarray:
    return frame["epoch"].dt.epoch("us").to_numpy()


def cuts(aligned: pl.DataFrame, kind: str) -> list[int]:
    """Window edges (µs) covering every epoch; the grid origin is not the first epoch."""
    ep = _epoch_us(aligned)
    lo, hi = int(ep.min()), int(ep.max()) + 1
    if kind == "short":               # 3 s < the 4 s epoch period: many windows hold no row
        return list(range(lo - 1_700_000, hi + 3_000_000, 3_000_000))
    if kind == "sub_scan":            # 10 s < the slowest scan period (12 s)
        return list(range(lo - 14_300_000, hi + 10_000_000, 10_000_000))   # first: empty
    if kind == "irregular":           # uneven windows plus one strictly between two epochs (empty)
        e = np.unique(ep)
        return [lo, int(e[3]), int(e[3]) + 1, int(e[4]), int(e[4]) + 1_000_000, int(e[40]), int(e[41]) + 7,
                hi, hi + 5_000_000]
    raise ValueError(kind)


def run_windows(aligned: pl.DataFrame, edges: list[int], cfg: AssociationConfig
                ) -> tuple[pl.DataFrame, list[AssociationStats], AssociateState]:
    """Step through consecutive windows [edges[i], edges[i+1]), carrying the state (checked once:
    handing every window the initial state instead fails every equality case)."""
    ep = pl.col("epoch").dt.epoch("us")
    state = init_associate_state()
    outs, stats = [], []
    for t0, t1 in zip(edges[:-1], edges[1:]):
        win = aligned.filter((ep >= t0) & (ep < t1))
        (out, st), new = associate_step(state, win, t0, t1, cfg)
        state = new
        outs.append(out)
        stats.append(st)
    return pl.concat(outs), stats, state


def _sorted(frame: pl.DataFrame) -> pl.DataFrame:
    return frame.sort("run", "epoch", "radar_id", "local_track_id", "report_id")


@pytest.mark.parametrize("config", list(CONFIGS))
@pytest.mark.parametrize("kind", ["short", "sub_scan", "irregular"])
def test_windowed_equals_whole_run(aligned, kind, config):
    cfg = CONFIGS[config]
    whole, whole_stats = associate(aligned, cfg)
    edges = cuts(aligned, kind)
    windowed, stats, _ = run_windows(aligned, edges, cfg)
    assert any(s.reports == 0 for s in stats), "the cut must include an empty window"
    assert whole_stats.reassignments > 0 and whole_stats.ambiguous_components > 0   # carry and rules 3-4 exercised
    assert_frame_equal(_sorted(windowed), _sorted(whole), rel_tol=1e-9, abs_tol=1e-9)
    assert AssociationStats.merge(stats) == whole_stats
    assert sum(stats, AssociationStats()) == whole_stats
    if config == "fine_joint":
        assert whole_stats.identity_conflicts > 0 and whole_stats.joint_components > 0


def test_whole_run_targets_count_distinct_ids(aligned):
    out, stats = associate(aligned, AssociationConfig())
    assert stats.targets == out.select("run", "target_id").n_unique()
    assert stats.reports == aligned.height






def test_state_keys_are_natural_and_bounded_by_the_carry_gap(aligned):
    cfg = AssociationConfig(carry_gap_s=10.0)
    edges = cuts(aligned, "sub_scan")
    whole, _ = associate(aligned, cfg)
    _, _, state = run_windows(aligned, edges[:10], cfg)
    ep = _epoch_us(aligned)
    latest = int(ep[ep < edges[9]].max())
    tr = state.tracks
    assert tr.columns == ["run", "radar_id", "local_track_id", "target_id", "seen_us"]
    assert (tr["seen_us"] >= latest - 10_000_000).all() and tr["seen_us"].max() == latest
    # each carried id is the one that local track had at its last epoch so far
    last = (whole.filter(pl.col("epoch").dt.epoch("us") < edges[9])
            .sort("epoch").group_by("run", "radar_id", "local_track_id").last()
            .select(pl.col("run", "radar_id", "local_track_id").cast(pl.Int64),
                    pl.col("target_id").cast(pl.Int64), seen_us=pl.col("epoch").dt.epoch("us")))
    assert_frame_equal(tr.sort("run", "radar_id", "local_track_id"),
                       last.join(tr.select("run", "radar_id", "local_track_id"),
                                 on=["run", "radar_id", "local_track_id"]).sort("run", "radar_id", "local_track_id"))


def test_a_window_before_the_state_end_is_refused(aligned):
    lo = int(_epoch_us(aligned).min())
    _, state = associate_step(init_associate_state(), aligned.clear(), T_MIN_US, lo, AssociationConfig())
    with pytest.raises(OptionError, match="does not follow"):
        associate_step(state, aligned.clear(), lo - 10, lo, AssociationConfig())
    _, state = associate_step(init_associate_state(), aligned, T_MIN_US, T_MAX_US, AssociationConfig())
    assert state.t_us == T_MAX_US


def test_live_targets_hold_every_id_that_can_return():
    """A target id is only continued from a carried local track, so ``live_targets`` after a
    window holds every id a later window can give again: here a local track silent for 15 s
    (within the 30 s carry gap) across a window boundary at 40 s, while another track runs on,
    comes back with its target id — which was live at the boundary although its track was not
    seen at the window's last epoch. A track silent for 39 s (longer than the gap) at the
    boundary is not live, and its id is not given again."""
    from tertiary.stages.association.associate import carry_step, init_associate_state
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)

    def rows(spec):   # (radar_id, local_track_id, seconds)
        return pl.DataFrame({"run": [0] * len(spec), "radar_id": [r for r, _, _ in spec],
                             "local_track_id": [k for _, k, _ in spec],
                             "epoch": [t0 + timedelta(seconds=s) for _, _, s in spec]}).with_columns(
            pl.col("run").cast(pl.UInt32), pl.col("radar_id").cast(pl.UInt32), pl.col("local_track_id").cast(pl.UInt32))
    w1 = [(1, 7, s) for s in range(0, 31)] + [(2, 3, s) for s in range(0, 40)] + [(3, 5, 0)]
    w2 = [(1, 7, s) for s in range(45, 60)] + [(2, 3, s) for s in range(40, 60)] + [(3, 5, 50)]
    w1, w2 = rows(w1), rows(w2)
    label1 = (w1["radar_id"].cast(pl.Int64) * 100 + w1["local_track_id"].cast(pl.Int64)).to_numpy()
    ids1, _, st = carry_step(init_associate_state(), w1, label1, 30.0)
    live = set(st.live_targets()["target_id"].to_list())
    first = dict(zip(zip(w1["radar_id"], w1["local_track_id"]), ids1))
    assert first[(1, 7)] in live and first[(2, 3)] in live and first[(3, 5)] not in live
    label2 = (w2["radar_id"].cast(pl.Int64) * 100 + w2["local_track_id"].cast(pl.Int64)).to_numpy()
    ids2, _, _ = carry_step(st, w2, label2, 30.0)
    second = dict(zip(zip(w2["radar_id"], w2["local_track_id"]), ids2))
    assert second[(1, 7)] == first[(1, 7)] and second[(2, 3)] == first[(2, 3)]
    assert second[(3, 5)] not in set(ids1.tolist())
    assert set(ids2.tolist()) & set(ids1.tolist()) <= live


def _identity_rows(spec, t0):
    """(radar_id, local_track_id, seconds, mode_s) → aligned-like rows for :func:`carry_step`."""
    return pl.DataFrame({"run": [0] * len(spec), "radar_id": [r for r, _, _, _ in spec],
                         "local_track_id": [k for _, k, _, _ in spec],
                         "epoch": [t0 + timedelta(seconds=s) for _, _, s, _ in spec],
                         "mode_s": [m for _, _, _, m in spec]},
                        schema_overrides={"mode_s": pl.String}).with_columns(
        pl.col("run").cast(pl.UInt32), pl.col("radar_id").cast(pl.UInt32), pl.col("local_track_id").cast(pl.UInt32))


def _carry(rows, state=None, gap=30.0, address_gap=None):
    from tertiary.stages.association.associate import carry_step
    label = (rows["radar_id"].cast(pl.Int64) * 1000 + rows["local_track_id"].cast(pl.Int64)).to_numpy()
    ids, _, st = carry_step(state or init_associate_state(), rows, label, gap, address_gap)
    return dict(zip(zip(rows["radar_id"].to_list(), rows["local_track_id"].to_list(), rows["epoch"].to_list()),
                    ids.tolist())), st


def test_a_mode_s_aircraft_handed_to_another_radar_stays_one_target():
    """Radar 1 sees the aircraft until 20 s, radar 2 (a new local track, nothing shared) from
    28 s: the Mode S address carries the system target id across the handover, also across a
    window boundary and only within the carry gap; without an address, or with another one, the
    new local track is a new target."""
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    at = lambda r, k, s: (r, k, t0 + timedelta(seconds=s))    # noqa: E731
    spec = lambda ms2, start=28: ([(1, 7, s, "4ca1b2") for s in range(0, 21, 4)]     # noqa: E731
                                  + [(2, 3, s, ms2) for s in range(start, 70, 4)])
    ids, _ = _carry(_identity_rows(spec("4ca1b2"), t0))
    assert ids[at(2, 3, 28)] == ids[at(1, 7, 0)]
    for other in (None, "3c6544"):
        ids, _ = _carry(_identity_rows(spec(other), t0))
        assert ids[at(2, 3, 28)] != ids[at(1, 7, 0)]
    ids, _ = _carry(_identity_rows(spec("4ca1b2", start=56), t0))     # silent 36 s > the 30 s gap
    assert ids[at(2, 3, 56)] != ids[at(1, 7, 0)]
    # across a window boundary: the address and its id are carried state, and live
    rows = _identity_rows(spec("4ca1b2"), t0)
    first, st = _carry(rows.filter(pl.col("epoch") < t0 + timedelta(seconds=24)))
    assert first[at(1, 7, 0)] in set(st.live_targets()["target_id"].to_list())
    second, _ = _carry(rows.filter(pl.col("epoch") >= t0 + timedelta(seconds=24)), st)
    assert second[at(2, 3, 28)] == first[at(1, 7, 0)]


def test_a_mode_s_address_keeps_its_target_through_a_coverage_gap_longer_than_a_local_track():
    """The aircraft leaves every radar's coverage after 20 s and comes back under a new local
    track: within ``address_gap_s`` of its last report (here 180 s later, and across a window
    boundary in the silence) it is the same system target; after longer, a new one. A local
    track number reused after ``carry_gap_s`` still hands nothing on."""
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    at = lambda r, k, s: (r, k, t0 + timedelta(seconds=s))    # noqa: E731
    spec = lambda back, ms2="4ca1b2": ([(1, 7, s, "4ca1b2") for s in range(0, 21, 4)]     # noqa: E731
                                       + [(2, 3, s, ms2) for s in range(back, back + 20, 4)])
    for back, same in ((56, True), (200, True), (400, False)):
        ids, _ = _carry(_identity_rows(spec(back), t0), address_gap=300.0)
        assert (ids[at(2, 3, back)] == ids[at(1, 7, 0)]) is same, back
    # another aircraft flies on to 96 s in the first window: the state outlives the local tracks' gap
    rows = _identity_rows(spec(200) + [(3, 9, s, "3c6544") for s in range(0, 97, 4)], t0)
    first, st = _carry(rows.filter(pl.col("epoch") < t0 + timedelta(seconds=100)), address_gap=300.0)
    second, _ = _carry(rows.filter(pl.col("epoch") >= t0 + timedelta(seconds=100)), st, address_gap=300.0)
    assert second[at(2, 3, 200)] == first[at(1, 7, 0)]
    ids, _ = _carry(_identity_rows(spec(56, None), t0), address_gap=300.0)       # no address: a new target
    assert ids[at(2, 3, 56)] != ids[at(1, 7, 0)]
    reused = _identity_rows([(1, 7, s, None) for s in (0, 4, 8)] + [(1, 7, s, None) for s in (60, 64)], t0)
    ids, _ = _carry(reused, address_gap=300.0)
    assert ids[at(1, 7, 60)] != ids[at(1, 7, 0)]


def test_a_radars_superseded_track_does_not_take_the_aircrafts_target_from_its_newer_one():
    """Radars 1 and 2 see the aircraft as one target; at 12 s radar 1 has started a new local
    track (9) on it while still extrapolating the old one (7, report from 8 s). The group of
    the newer track and radar 2's keeps the aircraft's target; the superseded row, alone, gets
    another id (counted as a row of the address, it would keep the target: the vote's tie goes to
    its lower radar)."""
    from tertiary.stages.association.associate import carry_step
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    spec = [(1, 7, s, "4ca1b2") for s in (0, 4, 8)] + [(2, 3, s, "4ca1b2") for s in (0, 4, 8)] \
        + [(1, 7, 12, "4ca1b2"), (1, 9, 12, "4ca1b2"), (2, 3, 12, "4ca1b2")]
    rows = _identity_rows(spec, t0).with_columns(
        pl.Series("time", [t0 + timedelta(seconds=s) for s in (0, 4, 8, 0, 4, 8, 8, 11.5, 11)]))
    label = np.array([0, 0, 0, 0, 0, 0, 1, 2, 2])          # epochs 0-8: one group; 12: {7}, {9, 3}
    ids, _, _ = carry_step(init_associate_state(), rows, label, 30.0)
    assert ids[7] == ids[8] == ids[0] and ids[6] != ids[0]


def test_an_address_id_held_by_another_group_is_not_given_twice():
    """Radar 1's track of the aircraft runs on while radar 2's plot of the same address forms a
    group of its own (outside the gate): the id stays with the group that holds it, the other
    group is a new target — one id is never two groups at one epoch."""
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    spec = [(1, 7, s, "4ca1b2") for s in range(0, 41, 4)] + [(2, 3, s, "4ca1b2") for s in range(28, 41, 4)]
    ids, _ = _carry(_identity_rows(spec, t0))
    at = lambda r, k, s: ids[(r, k, t0 + timedelta(seconds=s))]     # noqa: E731
    assert all(at(1, 7, s) == at(1, 7, 0) for s in range(0, 41, 4))
    assert at(2, 3, 28) != at(1, 7, 28)


def test_a_split_of_one_address_returns_to_the_older_id_when_the_older_part_ends():
    """Radar 2's new local track of the aircraft forms a group of its own (a new id) while
    radar 1's track still holds the aircraft's id; when radar 1's track ends, the group takes
    the address's id back instead of living on as a second target of one aircraft."""
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    spec = [(1, 7, s, "4ca1b2") for s in range(0, 29, 4)] + [(2, 3, s, "4ca1b2") for s in range(24, 49, 4)]
    ids, _ = _carry(_identity_rows(spec, t0))
    at = lambda r, k, s: ids[(r, k, t0 + timedelta(seconds=s))]     # noqa: E731
    assert at(2, 3, 24) != at(1, 7, 24)                  # beside each other: two groups, two ids
    assert all(at(2, 3, s) == at(1, 7, 0) for s in range(32, 49, 4))


@pytest.mark.parametrize("other", [None, "3c6544"])
def test_an_id_carried_to_another_aircraft_goes_back_to_its_address(other):
    """Radar 1's local track 7 follows the aircraft 4ca1b2 until 20 s, then swaps to another
    aircraft (no address, or another one) while radar 2 picks 4ca1b2 up under a new local
    track: the system target id stays with the aircraft, the swapped track's group is a new
    target."""
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    spec = ([(1, 7, s, "4ca1b2") for s in range(0, 21, 4)] + [(1, 7, s, other) for s in range(24, 41, 4)]
            + [(2, 3, s, "4ca1b2") for s in range(24, 41, 4)])
    ids, _ = _carry(_identity_rows(spec, t0))
    at = lambda r, k, s: ids[(r, k, t0 + timedelta(seconds=s))]     # noqa: E731
    assert all(at(2, 3, s) == at(1, 7, 0) for s in range(24, 41, 4))
    assert all(at(1, 7, s) != at(1, 7, 0) for s in range(24, 41, 4))
