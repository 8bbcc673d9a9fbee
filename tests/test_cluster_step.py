"""Clustering as a step function: any cut of a run into epoch windows gives the
whole-run ``clusters`` table (same ids, leads and members)."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.stages import align as A
from tertiary.stages.association.associate import associate
from tertiary.stages.clustering import (ClusteringConfig, ClusterState, cluster, cluster_step, init_cluster_state)
from tertiary.core.errors import OptionError
from tertiary.core.stage import T_MAX_US, T_MIN_US
from tertiary.stages.fusion import fuse
from tertiary.pipeline import PipelineConfig, screen
from tertiary.simulate import load_scenario, simulate

CONFIGS = {
    "dbscan": ClusteringConfig(always=True),
    # some pictures above the capacity, some not: an unclustered picture breaks continuity
    "capacity": ClusteringConfig(display_capacity=12),
    "strobe": ClusteringConfig(algorithm="strobe", always=True),
}


@pytest.fixture(scope="module")
def fused() -> pl.DataFrame:
    """Terminal-area, 20 aircraft, 300 s, two runs, fused by two methods."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, runs=2,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=20))
    ds = simulate(cfg)
    pc = PipelineConfig()
    ing = screen(ds, pc)
    aligned = A.expand(ing.plan, pc.align)
    assoc, _ = associate(aligned, pc.association)
    rows = aligned.with_columns(assoc["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    return fuse(rows, ing.radars, ("arithmetic", "information"), pc.fusion, origin=ds.origin)


@pytest.fixture(scope="module")
def holed(fused) -> pl.DataFrame:
    """``fused`` without a few whole pictures of one stream: its "previous epoch" is then not the
    previous grid epoch, and windows are cut right at the holes."""
    e = np.unique(fused["epoch"].dt.epoch("us").to_numpy())
    gone = pl.col("epoch").dt.epoch("us").is_in([int(e[10]), int(e[11]), int(e[30])])
    return fused.filter(~(gone & (pl.col("run") == 0) & (pl.col("method") == "information")))


def cuts(frame: pl.DataFrame, kind: str) -> list[int]:
    """Window edges (µs) covering every epoch; the grid origin is not the first epoch."""
    ep = frame["epoch"].dt.epoch("us").to_numpy()
    lo, hi = int(ep.min()), int(ep.max()) + 1
    e = np.unique(ep)
    if kind == "short":               # 3 s < the 4 s epoch period: many windows hold no row
        return list(range(lo - 1_700_000, hi + 3_000_000, 3_000_000))
    if kind == "sub_scan":            # 10 s < the slowest scan period (12 s); the first is empty
        return list(range(lo - 14_300_000, hi + 10_000_000, 10_000_000))
    if kind == "irregular":           # uneven, cut at the holes of ``holed``, one empty window
        return [lo, int(e[3]), int(e[3]) + 1, int(e[4]), int(e[10]), int(e[12]), int(e[30]) + 5,
                int(e[41]) + 7, hi, hi + 5_000_000]
    raise ValueError(kind)


def run_windows(fused: pl.DataFrame, edges: list[int], cfg: ClusteringConfig
                ) -> tuple[pl.DataFrame, list[int], ClusterState]:
    """Step through consecutive windows [edges[i], edges[i+1]), carrying the state (checked once:
    handing every window the initial state instead fails every equality case). Returns the
    concatenated clusters, the row count of each window's input and the last state."""
    ep = pl.col("epoch").dt.epoch("us")
    state = init_cluster_state()
    outs, sizes = [], []
    for t0, t1 in zip(edges[:-1], edges[1:]):
        win = fused.filter((ep >= t0) & (ep < t1))
        out, state = cluster_step(state, win, t0, t1, cfg)
        outs.append(out)
        sizes.append(win.height)
    return pl.concat(outs), sizes, state


KEY = ["run", "epoch", "method", "cluster_id"]


@pytest.mark.parametrize("config", list(CONFIGS))
@pytest.mark.parametrize("kind", ["short", "sub_scan", "irregular"])
@pytest.mark.parametrize("table", ["fused", "holed"])
def test_windowed_equals_whole_run(request, table, kind, config):
    frame = request.getfixturevalue(table)
    cfg = CONFIGS[config]
    whole = cluster(frame, cfg)
    windowed, sizes, _ = run_windows(frame, cuts(frame, kind), cfg)
    assert 0 in sizes, "the cut must include an empty window"
    # continuity exercised: clusters keep their ids over epochs, some ids > 1
    assert whole.height > 50 and whole["cluster_id"].max() > 1
    assert whole.group_by("run", "method", "cluster_id").len()["len"].max() > 5
    assert_frame_equal(windowed.sort(KEY), whole.sort(KEY), rel_tol=1e-9, abs_tol=1e-9)


def test_holes_are_bridged_as_in_the_whole_run(fused, holed):
    """Continuity is "the previous epoch of the (run, method) in fused", not of the grid: with
    three pictures of one stream missing, a cluster on both sides keeps its id."""
    cfg = CONFIGS["dbscan"]
    c = cluster(holed, cfg).filter((pl.col("run") == 0) & (pl.col("method") == "information"))
    e = np.unique(fused["epoch"].dt.epoch("us").to_numpy())
    ep = pl.col("epoch").dt.epoch("us")
    before = c.filter(ep == int(e[9])).select("cluster_id", "lead_target_id")
    after = c.filter(ep == int(e[12])).select("cluster_id", "lead_target_id")
    assert before.height and before.join(after, on=["cluster_id", "lead_target_id"]).height






def test_state_holds_the_last_clustered_picture_by_natural_keys(fused):
    """The carried targets are exactly the members of the clusters at each stream's last epoch
    (cluster id 0-based, lead flag), and next_id is the number of ids created so far."""
    cfg = CONFIGS["dbscan"]
    edges = cuts(fused, "sub_scan")
    out, _, state = run_windows(fused, edges[:8], cfg)
    ep = out["epoch"].dt.epoch("us")
    last = out.filter(ep == ep.max())
    expect = (last.explode("members")
              .select(pl.col("run").cast(pl.Int64), "method", target_id="members",
                      cluster_id=pl.col("cluster_id").cast(pl.Int64) - 1,
                      lead=pl.col("members") == pl.col("lead_target_id")))
    key = ["run", "method", "target_id"]
    assert_frame_equal(state.targets.sort(key), expect.sort(key))
    n_ids = out.group_by("run", "method").agg(next_id=pl.col("cluster_id").max().cast(pl.Int64))
    got = state.streams.select(pl.col("run"), "method", "next_id")
    assert_frame_equal(got.sort("run", "method"), n_ids.with_columns(pl.col("run").cast(pl.Int64)).sort("run", "method"))
    assert (state.streams["last_us"] == int(fused["epoch"].dt.epoch("us").filter(
        fused["epoch"].dt.epoch("us") < edges[7]).max())).all()


def test_a_window_before_the_state_end_is_refused(fused):
    lo = int(fused["epoch"].dt.epoch("us").min())
    _, state = cluster_step(init_cluster_state(), fused.clear(), T_MIN_US, lo)
    with pytest.raises(OptionError, match="does not follow"):
        cluster_step(state, fused.clear(), lo - 10, lo)
    _, state = cluster_step(init_cluster_state(), fused, T_MIN_US, T_MAX_US, CONFIGS["dbscan"])
    assert state.t_us == T_MAX_US
