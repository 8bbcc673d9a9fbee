"""Chapter 3 range channels as per-radar local-track options and the simulated
Mode S EHS report columns that feed them."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary.core import geo
from tertiary.stages.align import AlignConfig, estimates_by_track_life
from tertiary.core.errors import OptionError
from tertiary.sensors.local_tracks import LocalTrackerConfig, track_reports
from tertiary.evaluation.reference import interpolate_reference
from tertiary.contract import EHS_REPORT_COLUMNS
from tertiary.simulate import load_scenario, simulate
from tertiary.simulate.ehs import RESOLUTION, REPORT_COLUMN


@pytest.fixture(scope="module")
def ds():
    cfg = load_scenario("terminal-area")
    return simulate(dataclasses.replace(cfg, duration_s=1200.0, traffic=dataclasses.replace(cfg.traffic, aircraft=40)))


def _true_range(ds, rep: pl.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Truth range seen by each report's radar at the true illumination time (report time minus
    the radar's clock offset) plus its injected range bias — what a perfect range filter of
    that radar's plots converges to — and the truth's 3-D acceleration magnitude there."""
    rad = ds.radars.select("radar_id", "time_offset_s", "bias_range_m", "lat_deg", "lon_deg", "alt_m")
    rep = rep.join(rad, on="radar_id", how="left", maintain_order="left")
    shift = pl.duration(microseconds=(pl.col("time_offset_s") * 1e6).round().cast(pl.Int64))
    req = rep.select("truth_id", (pl.col("time") - shift).alias("time"))
    ref = interpolate_reference(ds.truth, req)
    pos = ref.select("true_x_m", "true_y_m", "true_z_m").to_numpy()
    rng = np.full(rep.height, np.nan)
    rid = rep["radar_id"].to_numpy()
    for r in ds.radars.iter_rows(named=True):
        sel = rid == r["radar_id"]
        site = geo.LocalFrame(r["lat_deg"], r["lon_deg"], r["alt_m"])
        p, _, _ = geo.frame_to_frame(pos[sel], ds.origin, site)
        rng[sel] = np.linalg.norm(p, axis=1) + r["bias_range_m"]
    tr = ds.truth.sort("truth_id", "time").with_columns(
        ((pl.col("vx_mps").diff() ** 2 + pl.col("vy_mps").diff() ** 2 + pl.col("vz_mps").diff() ** 2).sqrt()
         / (pl.col("time").diff().dt.total_microseconds() * 1e-6)).over("truth_id").fill_null(0.0).alias("acc"))
    acc = (req.with_row_index("__i").sort("time")
           .join_asof(tr.select("truth_id", "time", "acc").sort("time"), on="time", by="truth_id", strategy="nearest",
                      check_sortedness=False)
           .sort("__i")["acc"].fill_null(0.0).to_numpy())
    ok = (ref["status"] == "evaluated").to_numpy()
    return np.where(ok, rng, np.nan), acc


def _range_errors(ds, cfg: LocalTrackerConfig) -> pl.DataFrame:
    """Local-track range error per scored Mode S (EHS) report, with the truth acceleration; the
    first three reports of each track life (initiation) are left out."""
    out = estimates_by_track_life(ds.reports.drop("report_id"), ds.radars, AlignConfig(local_tracker=cfg))
    out = out.filter(pl.col("truth_id").is_not_null() & pl.col("ehs_gs_mps").is_not_null())
    true, acc = _true_range(ds, out)
    per = out.select("radar_id").join(ds.radars.select("radar_id", "scan_period_s"), on="radar_id",
                                      how="left", maintain_order="left")["scan_period_s"]
    gap = out.select(pl.col("time").diff().over("run", "radar_id", "local_track_id").dt.total_microseconds() * 1e-6
                     ).to_series()
    life = np.cumsum((gap.is_null() | (gap > AlignConfig().restart_gap_scans * per)).to_numpy())
    rank = pl.DataFrame({"l": life}).select(pl.int_range(pl.len()).over("l")).to_series().to_numpy()
    err = out["est_range_m"].to_numpy() - true
    keep = np.isfinite(err) & (rank >= 3)
    return pl.DataFrame({"err": err[keep], "acc": acc[keep], "radar_id": out["radar_id"].to_numpy()[keep]})


def _rmse(f: pl.DataFrame) -> float:
    return float(np.sqrt(np.mean(f["err"].to_numpy() ** 2)))


# ----------------------------------------------------------------------------- simulated EHS

def test_ehs_columns_on_mode_s_reports_only(ds):
    rep = ds.reports
    assert set(EHS_REPORT_COLUMNS) <= set(rep.columns)
    has = rep["ehs_gs_mps"].is_not_null()
    # only replies with a decoded Mode S address carry EHS; all five fields together
    assert not (has & rep["mode_s"].is_null()).any()
    assert (has == rep["mode_s"].is_not_null() & rep["truth_id"].is_not_null()).mean() > 0.99
    for c in EHS_REPORT_COLUMNS:
        assert (rep[c].is_not_null() == has).all(), c
    # values lie on the BDS 5,0 / 6,0 LSB grids
    for field, col in REPORT_COLUMN.items():
        lsb = RESOLUTION[field][0]
        v = rep[col].drop_nulls().to_numpy()
        off = (v - (-180.0 if field == "true_track_deg" else 0.0)) / lsb
        assert np.allclose(off, np.round(off), atol=1e-6), col


def test_ehs_ground_speed_matches_truth(ds):
    """An independent check of units and frame: EHS ground speed and track against the truth
    velocity at the illumination time (noise 0.5 m/s + 2 kt LSB; 0.2° + 90/512° LSB)."""
    rep = ds.reports.filter(pl.col("ehs_gs_mps").is_not_null())
    rad = ds.radars.select("radar_id", "time_offset_s")
    rep = rep.join(rad, on="radar_id", how="left", maintain_order="left")
    shift = pl.duration(microseconds=(pl.col("time_offset_s") * 1e6).round().cast(pl.Int64))
    ref = interpolate_reference(ds.truth, rep.select("truth_id", (pl.col("time") - shift).alias("time")))
    ok = (ref["status"] == "evaluated").to_numpy()
    ve, vn = ref["true_vx_mps"].to_numpy()[ok], ref["true_vy_mps"].to_numpy()[ok]
    gs_err = rep["ehs_gs_mps"].to_numpy()[ok] - np.hypot(ve, vn)
    trk_err = geo.wrap_deg(rep["ehs_track_deg"].to_numpy()[ok] - np.degrees(np.arctan2(ve, vn)))
    assert abs(np.median(gs_err)) < 0.3 and 0.4 < np.std(gs_err) < 1.5
    assert abs(np.median(trk_err)) < 0.1 and np.percentile(np.abs(trk_err), 90) < 1.0


def test_ehs_leaves_every_other_column_bit_identical():
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=240.0, runs=2, traffic=dataclasses.replace(cfg.traffic, aircraft=12))
    on, off = simulate(cfg), simulate(cfg, ehs=None)
    assert not set(EHS_REPORT_COLUMNS) & set(off.reports.columns)
    assert on.reports.drop([*EHS_REPORT_COLUMNS, "selected_alt_m"]).equals(off.reports)
    assert on.truth.equals(off.truth) and on.radars.equals(off.radars)
    # and the EHS stream is reproducible from the seed
    assert simulate(cfg).reports.select(EHS_REPORT_COLUMNS).equals(on.reports.select(EHS_REPORT_COLUMNS))


# ----------------------------------------------------------------------------- local range channels

def test_default_config_is_singer_and_bit_identical(ds):
    """The default config runs the Singer range channel; asking for "singer" explicitly, or a
    chapter 3 channel on reports without EHS, changes nothing."""
    plain = ds.reports.drop(list(EHS_REPORT_COLUMNS))
    base = track_reports(plain, ds.radars)
    assert LocalTrackerConfig().range_channel == "singer"
    assert track_reports(ds.reports, ds.radars).drop(list(EHS_REPORT_COLUMNS)).equals(base)
    for ch in ("kinematic", "kinematic_dynamic"):
        assert track_reports(plain, ds.radars, LocalTrackerConfig(range_channel=ch)).equals(base)


def test_tracks_without_ehs_fall_back_to_singer(ds):
    """A chapter 3 channel replaces the range estimates of EHS tracks only: tracks whose reports
    carry no EHS (non-Mode-S aircraft, clutter) keep the Singer output exactly, angles too."""
    singer = track_reports(ds.reports, ds.radars)
    kin = track_reports(ds.reports, ds.radars, LocalTrackerConfig(range_channel="kinematic"))
    key = ["run", "radar_id", "local_track_id"]
    ehs_tracks = singer.group_by(key).agg(pl.col("ehs_gs_mps").is_not_null().any().alias("any_ehs"))
    flag = singer.join(ehs_tracks, on=key, how="left", maintain_order="left")["any_ehs"].to_numpy()
    assert (~flag).sum() > 50 and flag.sum() > 500
    cols = ["est_range_m", "est_range_var_m2", "res_range_m", "x_m", "y_m", "vx_mps"]
    a, b = singer.filter(pl.Series(~flag)), kin.filter(pl.Series(~flag))
    assert a.select(cols).equals(b.select(cols))
    # EHS tracks changed range estimates but identical angular channels
    a, b = singer.filter(pl.Series(flag)), kin.filter(pl.Series(flag))
    assert not np.allclose(a["est_range_m"].to_numpy(), b["est_range_m"].to_numpy())
    for c in ("est_azimuth_deg", "est_elevation_deg", "est_azimuth_var_deg2"):
        assert a[c].equals(b[c]), c


def test_kinematic_beats_singer_on_manoeuvring_segments(ds):
    """Range RMSE against truth of the local tracks of EHS aircraft: the chapter 3 channels
    (corrected) beat the Singer channel over all reports and on the manoeuvring (accelerating:
    speed or vertical-rate change, 0.02 < |a| ≤ 0.5 m/s²) segments."""
    singer = _range_errors(ds, LocalTrackerConfig())
    accel = (pl.col("acc") > 0.02) & (pl.col("acc") <= 0.5)
    assert singer.filter(accel).height > 100
    for ch in ("kinematic", "kinematic_dynamic"):
        kin = _range_errors(ds, LocalTrackerConfig(range_channel=ch))
        assert _rmse(kin) < 0.95 * _rmse(singer), ch
        assert _rmse(kin.filter(accel)) < _rmse(singer.filter(accel)), ch
        # steady flight: the known-input channel smooths far better than Singer
        steady = pl.col("acc") <= 0.02
        assert _rmse(kin.filter(steady)) < 0.92 * _rmse(singer.filter(steady)), ch


def test_speed_rate_term_matters_on_accelerating_segments(ds):
    """Without V̇ in u (the printed (3.11), V̇ = 0) the channel is biased while the aircraft
    accelerates: the V̇ term must reduce the error there."""
    accel = (pl.col("acc") > 0.02) & (pl.col("acc") <= 0.5)
    with_rate = _range_errors(ds, LocalTrackerConfig(range_channel="kinematic")).filter(accel)
    without = _range_errors(ds, LocalTrackerConfig(range_channel="kinematic", range_speed_rate=False)).filter(accel)
    assert _rmse(with_rate) < _rmse(without)


def test_bad_options_are_option_errors():
    with pytest.raises(OptionError, match="range_channel"):
        LocalTrackerConfig(range_channel="alpha_beta")
    with pytest.raises(OptionError, match="range_variant"):
        LocalTrackerConfig(range_channel="kinematic", range_variant="typo")
