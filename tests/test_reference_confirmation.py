"""The centralised reference confirms targets as the fused pictures do: a clutter-only target
the pictures keep tentative is tentative in the reference too, so the reference's false-track
rate is no worse than the best picture's."""

from __future__ import annotations

import dataclasses

import polars as pl
import pytest

from tertiary import pipeline
from tertiary.pipeline.pictures import confirmed_only
from tertiary.stages.fusion.centralized import CentralizedConfig, centralized_fusion
from tertiary.simulate import load_scenario, simulate

KEYS = ["run", "epoch", "target_id"]
METHODS = ("information", "arithmetic")


@pytest.fixture(scope="module")
def processed():
    """Terminal-area (clutter on every radar), 20 aircraft, 5 minutes, through the pipeline."""
    sc = load_scenario("terminal-area")
    sc = dataclasses.replace(sc, duration_s=300.0, traffic=dataclasses.replace(sc.traffic, aircraft=20))
    ds = simulate(sc)
    return ds, pipeline.process(ds, pipeline.PipelineConfig(methods=METHODS, filters=(), safety=False))


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


def test_reference_tentative_rows_are_the_pictures(processed):
    """Same rule, same parameter, same rows: the flag of every (run, epoch, target_id) the
    reference estimates equals the pictures'."""
    _, run = processed
    pic = run.fused.filter(pl.col("method") == "information").select(*KEYS, pl.col("tentative").alias("pic"))
    cen = run.fused.filter(pl.col("method") == "centralized").select(*KEYS, "tentative")
    both = cen.join(pic, on=KEYS, how="inner")
    assert both.height == cen.height and both["tentative"].sum() > 0
    assert (both["tentative"] == both["pic"]).all()


def test_reference_false_track_rate_is_at_most_the_best_pictures(processed):
    _, run = processed
    m = run.metrics.filter((pl.col("stage") == "evaluation") & (pl.col("metric") == "false_tracks_per_hour")
                           & (pl.col("segment") == "all"))
    rate = dict(zip(m["method"], m["value"]))
    assert set(METHODS) | {"centralized"} <= set(rate)
    assert rate["centralized"] <= min(rate[k] for k in METHODS)


def test_min_plots_is_the_confirmation_parameter(processed):
    """A stricter confirmation holds more of the reference's targets tentative; min_plots = 1
    confirms every target at its first plot."""
    ds, run = processed
    rep, radars = run.ingested.reports, run.ingested.radars
    assoc = run.associations.filter(pl.col("run") == 0)
    keys = assoc.select(*KEYS).unique()
    n_tent = {k: centralized_fusion(rep, radars, assoc, keys, ds.origin, CentralizedConfig(min_plots=k))["tentative"]
              .sum() for k in (1, 2, 3)}
    assert n_tent[1] == 0 < n_tent[2] < n_tent[3]
