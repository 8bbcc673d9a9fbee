"""The MLAT / WAM sensor: its accuracy model (tertiary.simulate.mlat (G1)–(G2)), its Cartesian
measurement model (tertiary.sensors.mlat (MLAT-1)–(MLAT-2)) against pymap3d, and the covariance
alignment and the centralised reference take for an MLAT report."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import polars as pl
import pymap3d
import pytest

from tertiary.contract import MLAT_PLOT_COLUMNS
from tertiary.core import geo
from tertiary.sensors import mlat as sm
from tertiary.sensors import registration
from tertiary.simulate import load_scenario, simulate
from tertiary.simulate.mlat import LIGHT_MPS, MlatConfig, accuracy, nominal_sigma_m, visible
from tertiary.stages import align
from tertiary.stages.fusion.plots import converted_plots
from tertiary.evaluation.reference import plot_measurements

SIGMA_T = 50e-9
ORIGIN = geo.LocalFrame(48.85, 2.35, 0.0)


def _ring(n: int, radius: float, height: float = 0.0) -> np.ndarray:
    ang = 2 * np.pi * np.arange(n) / n
    return np.column_stack([radius * np.sin(ang), radius * np.cos(ang), np.full(n, height)])


def test_gdop_of_a_ring_of_receivers_is_the_closed_form():
    """(G2): N receivers on a circle around the aircraft, slant elevation ε: σ² = 2 (cσ_t)²/(N cos²ε)."""
    for n, radius, h in ((4, 20_000.0, 3_000.0), (6, 30_000.0, 9_000.0), (9, 15_000.0, 600.0)):
        rec = _ring(n, radius)
        p, count = accuracy(np.array([[0.0, 0.0, h]]), rec, np.ones((1, n), bool), SIGMA_T)
        cos2 = radius ** 2 / (radius ** 2 + h ** 2)
        want = 2 * (LIGHT_MPS * SIGMA_T) ** 2 / (n * cos2)
        assert count[0] == n
        np.testing.assert_allclose(np.diag(p[0]), [want, want], rtol=1e-9)
        assert abs(p[0, 0, 1]) < 1e-9 * want


def test_gdop_equals_the_time_difference_model():
    """(G1) with the emission time unknown equals the TDOA solution: differences to receiver 0,
    ρ_i − ρ_0 with noise covariance (cσ_t)²(I + 11ᵀ), Jacobian rows (û_i − û_0)_h — for
    asymmetric geometries, inside and outside the hull."""
    rng = np.random.default_rng(4)
    rec = np.column_stack([rng.uniform(-30e3, 30e3, (5, 2)), rng.uniform(0, 200, 5)])
    pos = np.array([[2e3, -5e3, 4e3], [70e3, 20e3, 8e3], [-15e3, 25e3, 1e3]])
    p, _ = accuracy(pos, rec, np.ones((3, 5), bool), SIGMA_T)
    for k, x in enumerate(pos):
        u = (x - rec) / np.linalg.norm(x - rec, axis=1)[:, None]
        jac = (u[1:] - u[0])[:, :2]
        cov = (LIGHT_MPS * SIGMA_T) ** 2 * (np.eye(4) + np.ones((4, 4)))
        np.testing.assert_allclose(p[k], np.linalg.inv(jac.T @ np.linalg.solve(cov, jac)), rtol=1e-8)


def test_accuracy_grows_outside_the_receiver_hull():
    """Inside the hull the error ellipse is small and round; outside, the receivers bunch up and
    the larger axis grows with the distance; the floor c σ_t/√N holds everywhere."""
    rec = _ring(6, 30_000.0)
    pos = np.array([[0.0, 0.0, 3000.0], [0.0, 60_000.0, 3000.0], [0.0, 120_000.0, 3000.0]])
    p, _ = accuracy(pos, rec, np.ones((3, 6), bool), SIGMA_T)
    worst = np.sqrt(np.linalg.eigvalsh(p)[:, -1])
    best = np.sqrt(np.linalg.eigvalsh(p)[:, 0])
    assert worst[0] < 15.0 and worst[0] / best[0] < 1.1
    assert worst[1] > 5 * worst[0] and worst[2] > 3 * worst[1]
    floor = LIGHT_MPS * SIGMA_T / math.sqrt(6)
    assert np.all(best >= floor * (1 - 1e-9))
    cfg = MlatConfig(name="W", receivers_enu_m=tuple(map(tuple, rec)), timing_sigma_ns=50.0)
    assert nominal_sigma_m(cfg) == pytest.approx(floor)


def test_receivers_see_within_range_and_radio_horizon():
    rec = np.array([[0.0, 0.0, 0.0]])
    pos = np.array([[100_000.0, 0.0, 300.0], [100_000.0, 0.0, 9000.0], [10_000.0, 0.0, 100.0]])
    seen = visible(pos, pos[:, 2], rec, np.array([10.0]), 150_000.0)
    assert seen[:, 0].tolist() == [False, True, True]          # 300 m at 100 km is below the horizon
    assert not visible(pos[1:2], pos[1:2, 2], rec, np.array([10.0]), 50_000.0).any()


def _mlat_radars(sigma_azimuth_deg: float = 0.1) -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": pl.Series([1, 7], dtype=pl.UInt32), "name": ["R", "W"], "lat_deg": [49.0, 48.70],
        "lon_deg": [2.55, 2.10], "alt_m": [120.0, 60.0], "scan_period_s": [4.0, 1.0], "sigma_range_m": [30.0, 8.0],
        "sigma_azimuth_deg": [0.06, sigma_azimuth_deg], "sigma_elevation_deg": [0.15, 1.0],
        "max_range_m": [150_000.0, 200_000.0], "kind": ["radar", "mlat"]})


def _mlat_reports() -> pl.DataFrame:
    x = np.array([12_000.0, -40_000.0, 65_000.0])
    y = np.array([-3_000.0, 52_000.0, 8_000.0])
    return pl.DataFrame({
        "radar_id": pl.Series([7, 7, 7], dtype=pl.UInt32), "plot_x_m": x, "plot_y_m": y,
        "altitude_m": [3000.0, 9500.0, 1200.0], "plot_sigma_x_m": [20.0, 35.0, 80.0],
        "plot_sigma_y_m": [25.0, 60.0, 40.0], "plot_sigma_xy_m": [10.0, -30.0, 0.0],
        "range_m": np.hypot(x, y), "azimuth_deg": np.mod(np.degrees(np.arctan2(x, y)), 360.0)})


def test_the_plot_goes_to_the_system_frame_as_pymap3d_places_it():
    """(MLAT-1)–(MLAT-2) against pymap3d: the plot at its Mode C height on WGS-84, then ENU at
    the origin; the covariance rotated by the same ENU-to-ENU rotation (columns from pymap3d's
    enu2uvw / uvw2enu of the site's unit vectors)."""
    radars, rep = _mlat_radars(), _mlat_reports()
    z, r, ok = sm.system_plots(rep, radars, ORIGIN, 30.0)
    assert ok.all()
    site = radars.row(1, named=True)
    zl, rl = sm.local_plots(rep, radars, 30.0)
    for i in range(rep.height):
        lat, lon, h = pymap3d.enu2geodetic(*zl[i], site["lat_deg"], site["lon_deg"], site["alt_m"])
        assert h == pytest.approx(rep["altitude_m"][i], abs=1e-3)     # the plot sits at its Mode C height
        want = pymap3d.geodetic2enu(lat, lon, h, ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m)
        np.testing.assert_allclose(z[i], want, atol=1e-3)
    cols = [pymap3d.uvw2enu(*pymap3d.enu2uvw(*e, site["lat_deg"], site["lon_deg"]), ORIGIN.lat_deg, ORIGIN.lon_deg)
            for e in np.eye(3)]
    m = np.array(cols).T
    np.testing.assert_allclose(r, m @ rl @ m.T, atol=1e-9)
    cxy = rep["plot_sigma_xy_m"].to_numpy()
    np.testing.assert_allclose(rl[:, 0, 1], np.sign(cxy) * cxy ** 2)          # covariance = sign · term²


def test_alignment_takes_the_plot_covariance_and_no_polar_gate():
    """The a-priori variance alignment gives an MLAT report is its own plot covariance in the
    system frame, not its sensor's polar sigmas; and the polar validity gate (seed 002 (13))
    never rejects it, even where its sensor's nominal angle sigma would fail the gate."""
    radars, rep = _mlat_radars(sigma_azimuth_deg=2.0), _mlat_reports()
    rep = rep.with_columns(elevation_deg=pl.lit(None, pl.Float64))
    n = rep.height
    local = sm.local_plots(rep, radars, 30.0)[0]
    rep = rep.with_columns(
        pl.Series("x_m", local[:, 0]), pl.Series("y_m", local[:, 1]), pl.Series("z_m", local[:, 2]),
        *(pl.Series(c, np.zeros(n)) for c in ("vx_mps", "vy_mps", "vz_mps")),
        pl.Series("est_cov", np.tile(np.eye(6).ravel() * 100.0, (n, 1)), dtype=pl.Array(pl.Float64, 36)))
    _, _, nominal = align.to_system_frame(rep, radars, ORIGIN, 30.0)
    _, r, _ = sm.system_plots(rep, radars, ORIGIN, 30.0)
    np.testing.assert_allclose(nominal, np.diagonal(r, axis1=1, axis2=2), rtol=1e-12)
    polar = geo.polar_sigmas_to_enu_cov(rep["range_m"].to_numpy(), rep["azimuth_deg"].to_numpy(), np.zeros(n),
                                        8.0, 2.0, 1.0)
    assert not np.allclose(nominal[:, :2], np.diagonal(polar, axis1=1, axis2=2)[:, :2], rtol=0.5)
    gate = geo.conversion_valid(rep["range_m"].to_numpy(), 8.0, np.radians(2.0))
    assert not gate.any()                                    # the polar rule would reject them all
    assert align.report_conversion_valid(rep, radars).all()


def test_the_centralised_reference_filters_the_cartesian_plot():
    """converted_plots (the centralised filter's and the trackers' measurement) gives an MLAT
    report (MLAT-2), neither converted from range/azimuth nor gated."""
    radars, rep = _mlat_radars(sigma_azimuth_deg=2.0), _mlat_reports()
    z, r, ok = converted_plots(rep, radars, ORIGIN, 30.0, gate=True)
    zc, rc, okc = sm.system_plots(rep, radars, ORIGIN, 30.0)
    assert ok.all() and okc.all()
    np.testing.assert_allclose(z, zc)
    np.testing.assert_allclose(r, rc)


def test_the_reconstructed_reference_takes_the_cartesian_plot():
    """The offline reference (``--reference reconstruct``) measures an MLAT report at its plot,
    with its covariance, not converted from range/azimuth with the sensor's angle σ."""
    radars, rep = _mlat_radars(sigma_azimuth_deg=2.0), _mlat_reports()
    rep = rep.with_columns(pl.int_range(pl.len()).alias("truth_id"), pl.lit(0.0).alias("time"))
    meas = plot_measurements(rep, radars, ORIGIN, sigma_alt_m=30.0)
    z, r, ok = sm.system_plots(rep, radars, ORIGIN, 30.0)
    assert ok.all()
    np.testing.assert_allclose(meas.select("mx_m", "my_m").to_numpy(), z[:, :2], rtol=0, atol=1e-6)
    cov = meas["r_cov"].to_numpy().reshape(-1, 3, 3)[:, :2, :2]
    np.testing.assert_allclose(cov, r[:, :2, :2], rtol=1e-12)


@pytest.fixture(scope="module")
def small_mlat():
    cfg = load_scenario("terminal-area-mlat")
    cfg = dataclasses.replace(cfg, radars=cfg.radars[:1], duration_s=120.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=6),
                              mlat=(dataclasses.replace(cfg.mlat[0], update_phase_s=0.0),))  # updates on the truth grid
    return simulate(cfg)


def test_simulated_mlat_reports_are_noisy_cartesian_plots_with_their_sigma(small_mlat):
    """The simulator's MLAT reports: a sensor of kind mlat, Cartesian plots whose errors against
    the truth match the σ they state (normalised error ~ χ²(2)), no truth column but truth_id,
    polar columns = the plot seen from the site, and the sensor's own tracks (local ENU state)."""
    ds = small_mlat
    assert ds.radars["kind"].to_list() == ["radar", "mlat"]
    rep = ds.reports.filter(pl.col("radar_id") == 2)
    assert rep.height > 100 and rep["plot_x_m"].is_not_null().all() and rep["elevation_deg"].is_null().all()
    site = geo.LocalFrame(*ds.radars.select("lat_deg", "lon_deg", "alt_m").row(1))
    joined = rep.join(ds.truth, on=["truth_id", "time"], suffix="_t")
    assert joined.height == rep.height
    tx, ty, _ = geo.frame_to_frame(joined.select("x_m_t", "y_m_t", "z_m_t").to_numpy(), ORIGIN, site)[0].T
    d = np.column_stack([joined["plot_x_m"] - tx, joined["plot_y_m"] - ty])
    cov = sm.plot_cov_xy(*(joined[c].to_numpy() for c in ("plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m")))
    nees = np.einsum("ni,nij,nj->n", d, np.linalg.inv(cov), d)
    assert 1.6 < nees.mean() < 2.4                             # E χ²(2) = 2
    ground = np.hypot(rep["plot_x_m"].to_numpy(), rep["plot_y_m"].to_numpy())
    assert np.all(rep["range_m"].to_numpy() >= ground - 1e-6)          # slant range to the Mode C height
    assert np.abs(rep["x_m"] - rep["plot_x_m"]).median() < 3 * rep["plot_sigma_x_m"].median()


def test_plot_only_mlat_reports_get_cartesian_tracks_window_by_window_as_whole(small_mlat):
    """Plot-only input (as imported from CAT020: no estimate columns): alignment's own local
    tracker runs Cartesian channels on the MLAT plots — within a few σ of the plot, not the
    polar channels' — and the windowed steps give the whole run's rows."""
    ds = small_mlat
    keep = ["report_id", "run", "radar_id", "time", "local_track_id", "range_m", "azimuth_deg", "elevation_deg",
            "altitude_m", "mode_s", "truth_id", *MLAT_PLOT_COLUMNS]
    rep = ds.reports.select([c for c in keep if c in ds.reports.columns])
    est = align.estimates_by_track_life(rep, ds.radars)
    wam = est.filter(pl.col("radar_id") == 2)
    assert (np.abs(wam["x_m"] - wam["plot_x_m"]) / wam["plot_sigma_x_m"]).median() < 1.5
    cfg = align.AlignConfig()
    whole, _ = align.align(rep, ds.radars, ds.origin, cfg)
    t = rep["time"].dt.epoch("us").to_numpy()
    grid = align.grid_origin_us(int(t.min()))
    state, parts = align.init_align_state(), []
    for lo, hi in ((None, grid + 40 * 10**6), (grid + 40 * 10**6, grid + 80 * 10**6), (grid + 80 * 10**6, None)):
        win = rep.filter(pl.Series((t >= (lo or -2**62)) & (t < (hi or 2**62))))
        (got, _), state = align.align_step(state, win, ds.radars, ds.origin, lo, hi, grid, cfg)
        parts.append(got)
    step = pl.concat(parts).sort("run", "epoch", "radar_id", "local_track_id", "report_id")
    whole = whole.sort("run", "epoch", "radar_id", "local_track_id", "report_id")
    assert step.height == whole.height
    cols = ["x_m", "y_m", "vx_mps"]
    np.testing.assert_allclose(step.select(cols).to_numpy(), whole.select(cols).to_numpy(), rtol=1e-9, atol=1e-6)


def test_registration_leaves_the_mlat_sensor_out(small_mlat):
    """An MLAT sensor has no range or azimuth bias to estimate: registration gives it no row,
    so alignment leaves its reports as they are."""
    ds = small_mlat
    reg = registration.estimate(ds.reports, ds.radars, ds.origin, ds.truth)
    assert reg.table["radar_id"].to_list() == [1]
    fixed = align.apply_registration(ds.reports, reg.table)
    wam = pl.col("radar_id") == 2
    assert fixed.filter(wam).select("range_m", "x_m").equals(ds.reports.filter(wam).select("range_m", "x_m"))
