"""Per-radar evaluation recovers what the simulator injected."""

from __future__ import annotations

import dataclasses

import polars as pl
import pytest

from tertiary.evaluation.radar_eval import radar_metrics
from tertiary.contract import validate
from tertiary.simulate import load_scenario, simulate


@pytest.fixture(scope="module")
def scored():
    cfg = load_scenario("terminal-area").replace(runs=2, duration_s=900.0, seed=11)
    radars = list(cfg.radars)
    radars[0] = dataclasses.replace(radars[0], bias_range_m=150.0, bias_azimuth_deg=0.2, time_offset_s=0.5)
    radars[1] = dataclasses.replace(radars[1], pd=0.8)
    cfg = dataclasses.replace(cfg, radars=tuple(radars),
                              traffic=dataclasses.replace(cfg.traffic, aircraft=30))
    ds = simulate(cfg)
    return ds, radar_metrics(ds.reports, ds.radars, ds.truth, ds.origin)


def _v(met: pl.DataFrame, radar: int, metric: str, segment: str = "all") -> float:
    row = met.filter((pl.col("method") == str(radar)) & (pl.col("metric") == metric) & (pl.col("segment") == segment))
    assert row.height == 1, (radar, metric, segment)
    return row["value"][0]


def test_injected_range_azimuth_bias_and_clock_offset_are_recovered(scored):
    ds, met = scored
    validate(met, "metrics", strict=True)
    assert set(met["stage"]) == {"radar"}
    assert _v(met, 1, "range_bias_m") == pytest.approx(150.0, abs=3.0)
    assert _v(met, 1, "azimuth_bias_deg") == pytest.approx(0.2, abs=0.01)
    assert _v(met, 1, "time_offset_s") == pytest.approx(0.5, abs=0.1)        # report time − true time
    for r in ds.radars.iter_rows(named=True):                                  # the small default biases too
        i = r["radar_id"]
        if i == 1:
            continue
        assert _v(met, i, "range_bias_m") == pytest.approx(r["bias_range_m"], abs=4.0)
        assert _v(met, i, "azimuth_bias_deg") == pytest.approx(r["bias_azimuth_deg"], abs=0.01)
        assert _v(met, i, "range_sigma_m") == pytest.approx(r["sigma_range_m"], rel=0.15)


def test_probability_of_detection_against_range_and_identity(scored):
    ds, met = scored
    assert _v(met, 2, "pd") == pytest.approx(0.8, abs=0.04)
    assert _v(met, 1, "pd") == pytest.approx(0.97, abs=0.04)
    rings = met.filter((pl.col("method") == "2") & (pl.col("metric") == "pd") & (pl.col("segment") != "all"))
    assert rings.height >= 3 and all(s.startswith("range:") for s in rings["segment"])
    big = met.filter((pl.col("method") == "2") & (pl.col("metric") == "n_expected") & (pl.col("segment") != "all")
                     & (pl.col("value") > 300))["segment"]
    for seg in big:
        assert _v(met, 2, "pd", seg) == pytest.approx(0.8, abs=0.06)
    assert _v(met, 1, "mode_s_correct_frac") == 1.0
    assert _v(met, 1, "mode_c_correct_frac") > 0.98                # 0.5 % garbled codes
