"""The centralised reference confirms targets as a track manager does: the fused pictures' plot
count, then the secondary tracker's three-scan test on the target's own plots. A clutter-only
target the pictures keep tentative is tentative in the reference too, and so is a radar's false
local track the count lets through, so the reference's false-track rate is no worse than the
best picture's, trackers included."""

from __future__ import annotations

import dataclasses

import polars as pl
import pytest

from tertiary import pipeline
from tertiary.pipeline.pictures import confirmed_only
from tertiary.stages.fusion.centralized import CentralizedConfig, centralized_fusion
from tertiary.stages.fusion.config import FusionConfig
from tertiary.simulate import load_scenario, simulate

KEYS = ["run", "epoch", "target_id"]
METHODS = ("information", "arithmetic")


@pytest.fixture(scope="module")
def data():
    """Terminal-area (clutter on every radar), 20 aircraft, 5 minutes."""
    sc = load_scenario("terminal-area")
    return simulate(dataclasses.replace(sc, duration_s=300.0, traffic=dataclasses.replace(sc.traffic, aircraft=20)))


@pytest.fixture(scope="module")
def processed(data):
    """``data`` through the pipeline."""
    return data, pipeline.process(data, pipeline.PipelineConfig(methods=METHODS, filters=(), safety=False))


@pytest.fixture(scope="module")
def counted(data):
    """``data`` through the pipeline with a plot count that lets a primary-only track of two
    plots confirm its target, as it does a track with a transponder reply."""
    cfg = pipeline.PipelineConfig(methods=METHODS, filters=(), safety=False, fusion=FusionConfig(min_plots_primary=2))
    return data, pipeline.process(data, cfg)


def _clutter_only(res) -> pl.DataFrame:
    """(run, target_id) of the targets every aligned row of which is a clutter plot (no truth)."""
    rows = res.aligned.select("run", "truth_id").with_columns(res.associations["target_id"])
    return (rows.group_by("run", "target_id").agg(pl.col("truth_id").is_null().all().alias("clutter"))
            .filter("clutter").select("run", "target_id"))


def _published(res, method: str) -> pl.DataFrame:
    return confirmed_only(res.fused.filter(pl.col("method") == method)).select("run", "target_id").unique()


def test_reference_publishes_no_clutter_only_target_the_pictures_hold_tentative(processed):
    _, run = processed
    clutter = _clutter_only(run)
    cen = run.fused.filter(pl.col("method") == "centralized")
    assert cen["tentative"].null_count() == 0
    held = clutter.join(_published(run, "information"), on=["run", "target_id"], how="anti")
    assert held.height > 100                           # the clutter the pictures never publish
    assert held.join(_published(run, "centralized"), on=["run", "target_id"], how="semi").height == 0
    # every target the reference publishes, the pictures publish too (the same rule on the same rows)
    assert _published(run, "centralized").join(_published(run, "information"), on=["run", "target_id"],
                                               how="anti").height == 0


def test_reference_tentative_rows_hold_the_pictures(processed):
    """Every (run, epoch, target_id) the pictures hold tentative the reference holds tentative
    too; the three-scan test holds more."""
    _, run = processed
    pic = run.fused.filter(pl.col("method") == "information").select(*KEYS, pl.col("tentative").alias("pic"))
    cen = run.fused.filter(pl.col("method") == "centralized").select(*KEYS, "tentative")
    both = cen.join(pic, on=KEYS, how="inner")
    assert both.height == cen.height and both["pic"].sum() > 0
    assert not (both["pic"] & ~both["tentative"]).any()
    assert (both["tentative"] & ~both["pic"]).sum() > 0


def test_counting_plots_alone_gives_the_pictures_flags(processed):
    """``confirmation="plots"``: same rule, same parameter, same rows as the pictures, so the flag
    of every (run, epoch, target_id) the reference estimates equals the pictures'."""
    ds, run = processed
    assoc = run.associations.filter(pl.col("run") == 0)
    keys = assoc.select(*KEYS).unique()
    cen = centralized_fusion(run.ingested.reports, run.ingested.radars, assoc, keys, ds.origin,
                             CentralizedConfig(confirmation="plots"))
    pic = run.fused.filter(pl.col("method") == "information").select(*KEYS, pl.col("tentative").alias("pic"))
    both = cen.select(*KEYS, "tentative").join(pic, on=KEYS, how="inner")
    assert both.height == cen.height and both["tentative"].sum() > 0
    assert (both["tentative"] == both["pic"]).all()


def test_reference_publishes_none_of_the_clutter_tracks_the_count_lets_through(counted):
    """Clutter-only targets the pictures publish (a radar's false local track of a few plots)
    are held tentative by the reference's three-scan test."""
    _, run = counted
    clutter = _clutter_only(run)
    passed = clutter.join(_published(run, "information"), on=["run", "target_id"], how="semi")
    assert passed.height > 0
    assert passed.join(_published(run, "centralized"), on=["run", "target_id"], how="semi").height == 0


def _false_track_rates(run) -> dict[str, float]:
    m = run.metrics.filter((pl.col("stage") == "evaluation") & (pl.col("metric") == "false_tracks_per_hour")
                           & (pl.col("segment") == "all"))
    return dict(zip(m["method"], m["value"]))


@pytest.mark.parametrize("which", ["processed", "counted"])
def test_reference_false_track_rate_is_at_most_the_best_pictures(which, request):
    _, run = request.getfixturevalue(which)
    rate = _false_track_rates(run)
    assert set(METHODS) | {"centralized"} <= set(rate)
    assert rate["centralized"] <= min(rate[k] for k in METHODS)
    if which == "counted":
        assert rate["centralized"] < max(rate[k] for k in METHODS)   # the pictures publish clutter here


def test_the_pictures_hold_a_primary_only_pair_of_plots_tentative(processed, counted):
    """The clutter targets a plain count of two plots publishes are one radar's primary-only
    tracks: with a third plot required of such a track, the pictures publish none of them and no
    false track here, and the count still confirms every aircraft (each replies)."""
    clutter = _clutter_only(counted[1])
    passed = clutter.join(_published(counted[1], "information"), on=["run", "target_id"], how="semi")
    assert passed.height > 0
    assert passed.join(_published(processed[1], "information"), on=["run", "target_id"], how="semi").height == 0
    assert all(_false_track_rates(processed[1])[k] == 0.0 < _false_track_rates(counted[1])[k] for k in METHODS)
    aircraft = processed[1].aligned.filter(pl.col("truth_id").is_not_null())["truth_id"].n_unique()
    published = (processed[1].associations.select("run", "target_id")
                 .with_columns(processed[1].aligned["truth_id"])
                 .join(_published(processed[1], "information"), on=["run", "target_id"], how="semi"))
    assert published["truth_id"].drop_nulls().n_unique() == aircraft


def test_min_plots_is_the_confirmation_parameter(processed):
    """A stricter confirmation holds more of the reference's targets tentative; min_plots = 1
    confirms every target at its first plot."""
    ds, run = processed
    rep, radars = run.ingested.reports, run.ingested.radars
    assoc = run.associations.filter(pl.col("run") == 0)
    keys = assoc.select(*KEYS).unique()
    n_tent = {k: centralized_fusion(rep, radars, assoc, keys, ds.origin,
                                    CentralizedConfig(min_plots=k, min_plots_primary=k, confirmation="plots"))
              ["tentative"].sum() for k in (1, 2, 3)}
    assert n_tent[1] == 0 < n_tent[2] < n_tent[3]


def test_the_reference_takes_the_trackers_initiation_parameters():
    """The pipeline hands the reference the tracker's annulus and circle (and the pictures'
    ``min_plots``), so changing the tracker's initiation changes the reference's with it."""
    from tertiary.pipeline.plan import reference_config
    from tertiary.stages.tracking.config import TrackerConfig
    cfg = pipeline.PipelineConfig(tracker=TrackerConfig(v_min_mps=45.0, v_max_mps=300.0, confirm_gate_m=900.0))
    ref = reference_config(cfg)
    assert (ref.v_min_mps, ref.v_max_mps, ref.confirm_gate_m) == (45.0, 300.0, 900.0)
    assert ref.min_plots == cfg.fusion.min_plots and ref.confirmation == "three_scan"
    strict = reference_config(pipeline.PipelineConfig(fusion=FusionConfig(min_plots_primary=4)))
    assert strict.min_plots_primary == 4
