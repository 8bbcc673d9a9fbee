"""The reported posterior Cramér–Rao bound bounds every picture of a pipeline run.

A terminal-area simulation (60 aircraft, 15 min, two Monte-Carlo runs: arrivals' fly-by turns
and decelerations, departures' climbs and level-offs, holding, overflights) through the
default pipeline: every fusion method's picture and every method × filter track picture.
For each picture, segment (all / straight / turn) and quantity (horizontal, position,
velocity) the RMSE must not lie below the bound beyond the Monte-Carlo error of the RMSE:

    rmse ≥ pcrb · (1 − 3 / √(2 n_eff))

— the relative standard error of an RMSE of n_eff independent Gaussian squared errors is
1/√(2 n_eff); n_eff is the picture's own effective sample size in that segment (``nees_n_eff``:
the samples discounted by the errors' autocorrelation along each track), 3 σ. The bound has no
Monte-Carlo error (the same expected information in every run). Fails on a bound computed for a
motion model the truth does not follow (Singer dynamics averaged over random accelerations:
the tracks on the straight legs beat it) and passes on the truth's own model.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary import PipelineConfig, load_scenario, process
from tertiary.simulate import simulate

PAIRS = {"pcrb_horizontal_m": "rmse_horizontal_m", "pcrb_pos_m": "rmse_pos_m", "pcrb_vel_mps": "rmse_vel_mps"}


@pytest.fixture(scope="module")
def run():
    sc = load_scenario("terminal-area")
    sc = dataclasses.replace(sc, runs=2, duration_s=900.0, seed=7,
                             traffic=dataclasses.replace(sc.traffic, aircraft=60))
    ds = simulate(sc)
    notes: list[str] = []
    res = process(ds, PipelineConfig(), notes=notes)
    return res.metrics, notes


def _table(metrics: pl.DataFrame) -> pl.DataFrame:
    """(method, segment, bound metric, bound, rmse, n_eff) for every picture with a bound."""
    b = metrics.filter((pl.col("stage") == "bound") & pl.col("metric").is_in(list(PAIRS))).select(
        "method", "segment", "metric", pl.col("value").alias("bound"))
    acc = metrics.filter(pl.col("stage").is_in(["fusion", "tracker"]))
    rmse = acc.filter(pl.col("metric").is_in(list(PAIRS.values()))).select(
        "method", "segment", pl.col("metric").replace_strict({v: k for k, v in PAIRS.items()}),
        pl.col("value").alias("rmse"))
    n_eff = acc.filter(pl.col("metric") == "nees_n_eff").select("method", "segment", pl.col("value").alias("n_eff"))
    return (b.join(rmse, on=["method", "segment", "metric"], how="inner")
            .join(n_eff, on=["method", "segment"], how="left"))


def test_no_picture_beats_the_bound(run):
    metrics, _ = run
    t = _table(metrics)
    pictures = metrics.filter(pl.col("stage").is_in(["fusion", "tracker"]) & (pl.col("metric") == "rmse_pos_m"))
    cfg = PipelineConfig()
    # every picture has its bound: each fusion method alone and with each filter
    assert t["method"].n_unique() == pictures["method"].n_unique() >= len(cfg.methods) * (1 + len(cfg.filters))
    assert set(t["segment"]) == {"all", "straight", "turn"}
    assert t.height == 3 * pictures.height and t["n_eff"].is_not_null().all()
    tol = 3.0 / np.sqrt(2.0 * t["n_eff"].to_numpy())
    below = t.filter(pl.Series(t["rmse"].to_numpy() < t["bound"].to_numpy() * (1.0 - tol)))
    assert below.is_empty(), f"pictures below their bound beyond the Monte-Carlo error:\n{below}"
    # a bound, not a zero: a sizeable part of the error somewhere
    assert (t["bound"] > 0).all() and (t["bound"] / t["rmse"]).max() > 0.5


def test_manoeuvres_dilute_the_bound(run):
    """The model's manoeuvres cost information: on every picture the horizontal and velocity
    bounds in turns lie well above those on the straight legs (the turn's onset, rotation and
    exit dilute (p, v, a); the downlinked velocities, which a turn does not dilute, keep the
    ratio near 1.5). Fails on a model without process noise at the manoeuvres."""
    metrics, _ = run
    b = metrics.filter(pl.col("stage") == "bound").pivot("segment", index=["method", "metric"], values="value")
    for metric in ("pcrb_horizontal_m", "pcrb_vel_mps"):
        m = b.filter(pl.col("metric") == metric)
        assert m.height and (m["turn"] > 1.3 * m["straight"]).all(), m


def test_the_run_states_the_motion_model_of_its_bound(run):
    from tertiary.evaluation.bound import MODEL
    _, notes = run
    assert f"bound: {MODEL}" in notes
