"""ADS-B as a sensor: σ from NACp, the fusion quality minimum, a simulated ground station, and a
radar + ADS-B dataset end to end (datasets/terminal-area-mixed.toml without its WAM: 20 aircraft
over 300 s seen by two radars and one station), against the same traffic without the station."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

import tertiary
from tertiary.core import geo
from tertiary.evaluation.radar_eval import radar_metrics
from tertiary.sensors import adsb, mlat
from tertiary.simulate import load_scenario, simulate
from tertiary.simulate.adsb_observe import aircraft_quality

WEIGHTED = ("information", "centralized", "information+singer")


def test_sigma_from_nacp_is_the_epu_over_the_radial_95_percent_point():
    """(ADSB-1): σ = EPU/√(−2 ln 0.05); NACp 0, null and out of range have none."""
    got = adsb.sigma_from_nacp([8, 10, 0, 12, np.nan])
    assert got[0] == pytest.approx(92.6 / np.sqrt(-2 * np.log(0.05)))
    assert got[1] == pytest.approx(10.0 / 2.4477, rel=1e-4)
    assert np.isnan(got[2:]).all()


def test_a_circular_gaussian_with_that_sigma_stays_inside_the_epu_95_percent_of_the_time():
    rng = np.random.default_rng(3)
    s = adsb.sigma_from_nacp([9])[0]
    inside = np.hypot(*rng.standard_normal((2, 200_000)) * s) <= adsb.NACP_EPU95_M[9]
    assert inside.mean() == pytest.approx(0.95, abs=0.003)


def _frame(nacp, nic, sil):
    return pl.DataFrame({"radar_id": [7, 7, 7, 1], "adsb_nacp": nacp, "adsb_nic": nic, "adsb_sil": sil},
                        schema_overrides={c: pl.UInt8 for c in adsb.QUALITY_COLUMNS})


def test_reports_below_the_fusion_minimum_are_named_by_their_indicator():
    radars = pl.DataFrame({"radar_id": [1, 7], "kind": ["radar", "adsb"]})
    why = adsb.fusion_rejects(_frame([3, 9, None, 2], [8, 0, 8, 8], [3, 3, None, 0]), radars, adsb.AdsbQuality())
    assert why[0] == "ADS-B quality below the fusion minimum (NACp 3 < 5)"
    assert why[1] == "ADS-B quality below the fusion minimum (NIC 0 < 1)"
    assert why[2] is None          # indicators not broadcast are not a failure
    assert why[3] is None          # a radar's row, whatever its columns say
    lax = adsb.fusion_rejects(_frame([3, 9, None, 2], [8, 0, 8, 8], [3, 3, None, 0]), radars,
                              adsb.AdsbQuality(min_nacp=1, min_nic=0, min_sil=0))
    assert all(w is None for w in lax)


def test_a_report_without_stated_sigma_takes_its_nacp_sigma_as_its_covariance():
    """(MLAT-1) with (ADSB-1): R_xy = σ(NACp)² I for an ADS-B plot without plot σ, the station's
    nominal σ without NACp either."""
    radars = pl.DataFrame({"radar_id": [7], "kind": ["adsb"], "lat_deg": [49.0], "lon_deg": [2.5], "alt_m": [40.0],
                           "sigma_range_m": [50.0]})
    reports = pl.DataFrame({"radar_id": [7, 7], "plot_x_m": [1000.0, 2000.0], "plot_y_m": [500.0, 0.0],
                            "altitude_m": [3000.0, 3000.0], "adsb_nacp": [8, None]},
                           schema_overrides={"adsb_nacp": pl.UInt8})
    z, r = mlat.local_plots(reports, radars, altitude_sigma_m=7.6)
    s8 = adsb.sigma_from_nacp([8])[0]
    np.testing.assert_allclose(r[0, :2, :2], np.diag([s8 ** 2, s8 ** 2]))
    np.testing.assert_allclose(r[1, :2, :2], np.diag([2500.0, 2500.0]))
    assert z[0, 0] == 1000.0 and z[0, 1] == 500.0


def _scenario(with_station: bool):
    cfg = load_scenario("terminal-area-mixed")
    cfg = dataclasses.replace(cfg, radars=cfg.radars[:2], mlat=None, duration_s=300.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=20))
    return cfg if with_station else dataclasses.replace(cfg, adsb_station=None)


@pytest.fixture(scope="module")
def runs():
    out = {}
    for name in ("with", "without"):
        ds = simulate(_scenario(name == "with"))
        out[name] = (ds, tertiary.process(ds, tertiary.PipelineConfig(methods=("arithmetic", "information"),
                                                                      filters=("singer",))))
    return out


def test_an_aircraft_keeps_its_equipage_and_nacp_whatever_the_block():
    """Drawn from the aircraft's id and the seed, not from a block's random stream."""
    st = _scenario(True).adsb_station[0]
    ids = np.arange(1000)
    a = aircraft_quality(st, ids, np.ones(1000, bool), 7)
    b = aircraft_quality(st, ids[::-1].copy(), np.ones(1000, bool), 7)
    assert np.array_equal(a[0], b[0][::-1]) and np.array_equal(a[1], b[1][::-1])
    assert 0.85 < a[0].mean() < 0.95
    assert set(np.unique(a[1])) <= {3.0, 7.0, 8.0, 9.0, 10.0, 11.0} and (a[1] == 10).mean() > 0.4


def test_the_station_reports_what_its_aircraft_declare(runs):
    """Every report carries the address, NACp, NIC and SIL; its position error is consistent with
    the NACp's σ (normalised squared error ≈ 2 on two axes) and its altitude is 25 ft steps."""
    ds, _ = runs["with"]
    rep = ds.reports.filter(pl.col("radar_id") == 3)
    assert rep.height > 500 and rep["mode_s"].null_count() == 0
    assert rep["adsb_nic"].unique().to_list() == [8] and rep["adsb_sil"].unique().to_list() == [3]
    site = geo.LocalFrame(*ds.radars.filter(pl.col("radar_id") == 3).select("lat_deg", "lon_deg", "alt_m").row(0))
    both = rep.filter(pl.col("truth_id").is_not_null())
    t = both["time"].dt.epoch("us").to_numpy() / 1e6
    true = np.full((both.height, 3), np.nan)
    for tid in both["truth_id"].unique().to_list():             # the truth interpolated at each report
        tr = ds.truth.filter(pl.col("truth_id") == tid)
        tt, rows = tr["time"].dt.epoch("us").to_numpy() / 1e6, (both["truth_id"] == tid).to_numpy()
        true[rows] = np.column_stack([np.interp(t[rows], tt, tr[c].to_numpy()) for c in ("x_m", "y_m", "z_m")])
    x, y = geo.frame_to_frame(true, ds.origin, site)[0][:, :2].T
    s = adsb.sigma_from_nacp(both["adsb_nacp"].to_numpy())
    nees = ((both["plot_x_m"].to_numpy() - x) ** 2 + (both["plot_y_m"].to_numpy() - y) ** 2) / s ** 2
    assert 1.7 < np.mean(nees) < 2.3
    ft25 = 25 * 0.3048
    alt = rep["altitude_m"].to_numpy()
    np.testing.assert_allclose(alt / ft25, np.round(alt / ft25), atol=1e-6)


def test_reports_below_the_quality_minimum_are_rejected_with_the_reason_and_the_rest_fused(runs):
    ds, res = runs["with"]
    rep = ds.reports.filter(pl.col("radar_id") == 3)
    low = set(rep.filter(pl.col("adsb_nacp") < 5)["report_id"].to_list())
    assert low, "the scenario's NACp 3 aircraft were not seen"
    why = res.rejects.filter(pl.col("reason").str.contains("NACp"))
    assert set(why["report_id"].to_list()) == low
    assert why["reason"].unique().to_list() == ["ADS-B quality below the fusion minimum (NACp 3 < 5)"]
    assert not low & set(res.aligned["report_id"].to_list())
    info = res.fused.filter(pl.col("method") == "information")
    assert info["radar_ids"].list.contains(3).mean() > 0.5
    per = radar_metrics(ds.reports, ds.radars, ds.truth, ds.origin).filter(pl.col("segment") == "all")
    station = dict(per.filter(pl.col("method") == "3").select("metric", "value").iter_rows())
    # Pd counts every aircraft in coverage, the unequipped ones too (equipage 0.9 of Mode S aircraft)
    assert station["mode_s_correct_frac"] == 1.0 and station["pd"] > 0.6


def _metric(res, stage: str, metric: str) -> dict[str, float]:
    m = res.metrics.filter((pl.col("stage") == stage) & (pl.col("metric") == metric) & (pl.col("segment") == "all"))
    return dict(zip(m["method"].to_list(), m["value"].to_list()))


def test_the_station_improves_the_weighted_pictures_and_the_bound_still_bounds(runs):
    for metric in ("rmse_pos_m", "rmse_horizontal_m"):
        got = {**_metric(runs["with"][1], "fusion", metric), **_metric(runs["with"][1], "tracker", metric)}
        base = {**_metric(runs["without"][1], "fusion", metric), **_metric(runs["without"][1], "tracker", metric)}
        for method in WEIGHTED:
            assert got[method] < 0.8 * base[method], (metric, method, got[method], base[method])
    gaps = runs["with"][1].metrics.filter((pl.col("stage") == "bound") & pl.col("metric").str.starts_with("gap_"))
    assert gaps.height >= 10 and (gaps["value"] >= 0).all(), gaps.filter(pl.col("value") < 0)


def _paris_flight() -> pl.DataFrame:
    from tertiary.io.adsb import read_adsb
    from tertiary.simulate.config import resolve_data_path
    raw = read_adsb(resolve_data_path("adsb_paris_2021-10-07.parquet"))
    first = raw.filter(~pl.col("onground").fill_null(False))["icao24"].drop_nulls()[0]
    return raw.filter(pl.col("icao24") == first).head(400)


def test_ads_b_truth_below_the_reference_quality_is_removed_with_the_reason():
    """OpenSky-format fixes declaring NACp 6 are not truth (NACp >= 8 by default), each with its
    reason; a lower minimum keeps them; the reference's own NACp rule is not applied twice."""
    from tertiary.evaluation.reference import ReferenceConfig, adsb_reference
    from tertiary.io.adsb import AdsbCleaning, clean_adsb
    flight = _paris_flight()
    nacp = np.where(np.arange(flight.height) % 10 == 3, 6, 9)
    frame = flight.with_columns(pl.Series("nacp", nacp))
    _, removed = clean_adsb(frame, AdsbCleaning())
    low = removed.filter(pl.col("reason") == "declared quality below the reference bound (NACp 6)")
    assert low.height == int((nacp == 6).sum())
    _, kept = clean_adsb(frame, AdsbCleaning(min_nacp=6))
    assert not kept["reason"].str.contains("NACp").any()
    points, _ = adsb_reference(frame, geo.LocalFrame(48.85, 2.35, 0.0), ReferenceConfig(min_nacp=6))
    assert (points["epu95_m"] == adsb.NACP_EPU95_M[6]).sum() >= 0.8 * low.height     # some fail other rules
