"""A mixed radar + MLAT dataset end to end: 20 aircraft over 300 s of the terminal area seen by two
radars and one WAM (datasets/terminal-area-mlat.toml), run through every stage, and the same
traffic and radar plots without the WAM."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

import tertiary
from tertiary.evaluation.radar_eval import radar_metrics
from tertiary.simulate import load_scenario, simulate

METHODS = ("arithmetic", "information")
#: the pictures that weight the sources by their covariances, where a better sensor must help
WEIGHTED = ("information", "centralized", "information+singer")


def _scenario(with_mlat: bool):
    cfg = load_scenario("terminal-area-mlat")
    cfg = dataclasses.replace(cfg, radars=cfg.radars[:2], duration_s=300.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=20))
    return cfg if with_mlat else dataclasses.replace(cfg, mlat=None)


@pytest.fixture(scope="module")
def runs():
    out = {}
    for name in ("with", "without"):
        ds = simulate(_scenario(name == "with"))
        out[name] = (ds, tertiary.process(ds, tertiary.PipelineConfig(methods=METHODS, filters=("singer",))))
    return out


def _metric(res, stage: str, metric: str) -> dict[str, float]:
    m = res.metrics.filter((pl.col("stage") == stage) & (pl.col("metric") == metric) & (pl.col("segment") == "all"))
    return dict(zip(m["method"].to_list(), m["value"].to_list()))


def test_the_radars_plots_are_the_same_with_and_without_the_mlat(runs):
    a, b = runs["with"][0].reports, runs["without"][0].reports
    cols = ["radar_id", "time", "local_track_id", "range_m", "azimuth_deg", "x_m", "y_m", "z_m"]
    assert a.filter(pl.col("radar_id") <= 2).select(cols).equals(b.select(cols))


def test_the_mlat_is_evaluated_and_contributes_to_the_pictures(runs):
    """Per-sensor evaluation sees the WAM as a sensor with its detections and identities, its
    reports are aligned (none rejected) and the fused targets take it among their sources."""
    ds, res = runs["with"]
    per = radar_metrics(ds.reports, ds.radars, ds.truth, ds.origin).filter(pl.col("segment") == "all")
    wam = dict(per.filter(pl.col("method") == "3").select("metric", "value").iter_rows())
    assert wam["n_reports"] > 500 and wam["pd"] > 0.9 and wam["mode_s_correct_frac"] > 0.99
    aligned = res.aligned.filter(pl.col("radar_id") == 3)
    assert aligned["report_id"].n_unique() >= 0.95 * ds.reports.filter(pl.col("radar_id") == 3).height
    info = res.fused.filter(pl.col("method") == "information")
    with_wam = info["radar_ids"].list.contains(3).mean()
    assert with_wam > 0.5


def test_the_mlat_improves_the_weighted_pictures(runs):
    """On the same traffic and radar plots, the pictures that weight by covariance are at least
    as accurate with the WAM (3-D and horizontal)."""
    for metric in ("rmse_pos_m", "rmse_horizontal_m"):
        got = {**_metric(runs["with"][1], "fusion", metric), **_metric(runs["with"][1], "tracker", metric)}
        base = {**_metric(runs["without"][1], "fusion", metric), **_metric(runs["without"][1], "tracker", metric)}
        for method in WEIGHTED:
            assert got[method] <= base[method], (metric, method, got[method], base[method])


def test_the_bound_bounds_every_picture_with_the_mlat(runs):
    """The posterior Cramér–Rao bound with the WAM's Cartesian information (MLAT-3) stays below
    every picture's RMSE (every gap ≥ 0), and it is lower than without the WAM."""
    res = runs["with"][1]
    gaps = res.metrics.filter((pl.col("stage") == "bound") & pl.col("metric").str.starts_with("gap_"))
    assert gaps.height >= 15 and (gaps["value"] >= 0).all(), gaps.filter(pl.col("value") < 0)
    with_b = _metric(res, "bound", "pcrb_horizontal_m")
    without_b = _metric(runs["without"][1], "bound", "pcrb_horizontal_m")
    assert all(with_b[m] < without_b[m] for m in with_b)
