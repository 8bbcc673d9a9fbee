"""Converted-measurement validity gate (seed 002 (13)–(14)) in alignment and the centralised
reference, and the debiased conversion option."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from tertiary.stages import align
from tertiary.core import geo
from tertiary.stages.fusion.plots import converted_plots, debias_enu, plot_validity

US = 1_000_000


def test_range_limit_is_39_39_km_for_30_m_and_1_deg():
    # (14): r < 0.4 σ_r / σ_θ² = 0.4 · 30 / (π/180)² = 39 393.7 m
    assert align.validity_range_limit(30.0, np.radians(1.0)) == pytest.approx(12.0 / (np.pi / 180) ** 2)
    assert align.validity_range_limit(30.0, np.radians(1.0)) == pytest.approx(39_390.0, abs=5.0)


def test_gate_flags_exactly_where_condition_fails():
    s_r, s_az = 30.0, np.radians(1.0)
    lim = 0.4 * s_r / s_az**2
    r = np.array([1000.0, lim * 0.999, lim * 1.001, 80_000.0, 50.0, 50.0, 5000.0])   # σ 0.41 vs 0.39 rad at 50 m: only the σ < 0.4 clause differs
    s_az_v = np.array([s_az, s_az, s_az, s_az, 0.41, 0.39, s_az])
    s_el_v = np.array([np.nan, np.nan, np.nan, np.nan, np.nan, np.nan, 0.1])   # 5000·0.01/30 = 1.67 ≥ 0.4
    # the condition written out independently, per case
    want = [r[i] * s_az_v[i] ** 2 / s_r < 0.4 and s_az_v[i] < 0.4
            and (np.isnan(s_el_v[i]) or (r[i] * s_el_v[i] ** 2 / s_r < 0.4 and s_el_v[i] < 0.4))
            for i in range(len(r))]
    assert want == [True, True, False, False, False, True, False]
    got = align.conversion_valid(r, np.full(len(r), s_r), s_az_v, s_el_v)
    assert got.tolist() == want
    # a missing range or range sigma fails, a missing angle sigma does not
    assert align.conversion_valid([np.nan, 1000.0], [30.0, np.nan], [s_az, s_az]).tolist() == [False, False]


def _radars() -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": pl.Series([1, 2], dtype=pl.UInt32), "name": ["A", "B"],
        "lat_deg": [48.9, 48.6], "lon_deg": [2.3, 2.7], "alt_m": [100.0, 50.0],
        "scan_period_s": [4.0, 4.0], "sigma_range_m": [30.0, 30.0], "sigma_azimuth_deg": [1.0, 0.05],
        "sigma_elevation_deg": [0.1, 0.1], "max_range_m": [3e5, 3e5]})


def _reports() -> tuple[pl.DataFrame, list[bool]]:
    """Radar 1 (σ_θ = 1°, limit 39.39 km) at 20, 39, 40, 60 km; radar 2 (σ_θ = 0.05°) at 60 km."""
    rows, want = [], []
    for i, (radar, rng) in enumerate([(1, 20e3), (1, 39e3), (1, 40e3), (1, 60e3), (2, 60e3)]):
        az = 30.0 + 10 * i
        e, n, u = geo.polar_to_enu(rng, az, 1.0)
        rows.append({"run": 0, "radar_id": radar, "local_track_id": i, "time": 1_633_608_000 * US,
                     "x_m": float(e), "y_m": float(n), "z_m": float(u), "vx_mps": 100.0, "vy_mps": 0.0,
                     "vz_mps": 0.0, "est_cov": np.diag([100.0, 100, 400, 4, 4, 1]).ravel().tolist(),
                     "range_m": rng, "azimuth_deg": az, "elevation_deg": 1.0, "est_elevation_deg": 1.0,
                     "res_range_m": 1.0, "res_range_var_m2": 2.0})
        s_az = np.radians(1.0 if radar == 1 else 0.05)
        want.append(rng * s_az**2 / 30.0 < 0.4)
    df = pl.DataFrame(rows).with_columns(
        pl.col("time").cast(pl.Datetime("us", "UTC")), pl.col("radar_id").cast(pl.UInt32),
        pl.col("local_track_id").cast(pl.UInt32), pl.col("run").cast(pl.UInt32),
        pl.col("est_cov").cast(pl.Array(pl.Float64, 36)), pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"))
    return df, want


def test_alignment_counts_flags_and_rejects_the_failing_reports():
    reports, want = _reports()
    assert want == [True, True, False, False, True]
    origin = geo.LocalFrame(48.75, 2.5, 0.0)
    bad_ids = {i for i, w in enumerate(want) if not w}

    p = align.plan(reports, _radars(), origin, align.AlignConfig())
    assert p.conversion_invalid == 2
    assert "conv_valid" not in align.expand(p).columns                    # default: count only
    # row accounting unchanged by the count-only default
    assert set(p.df.filter(pl.Series(p.keep))["report_id"].to_list()) == set(range(5))

    cfg = align.AlignConfig(conversion_gate="flag")
    aligned, rejects = align.align(reports, _radars(), origin, cfg)
    flags = dict(zip(aligned["report_id"].to_list(), aligned["conv_valid"].to_list()))
    assert flags == {i: w for i, w in enumerate(want)}
    assert rejects.height == 0

    cfg = align.AlignConfig(conversion_gate="reject")
    aligned, rejects = align.align(reports, _radars(), origin, cfg)
    assert set(rejects["report_id"].to_list()) == bad_ids
    assert all("seed 002 (13)" in r for r in rejects["reason"].to_list())
    assert set(aligned["report_id"].to_list()) == set(range(5)) - bad_ids


def test_centralised_plots_gate_the_same_reports():
    reports, want = _reports()
    origin = geo.LocalFrame(48.75, 2.5, 0.0)
    assert plot_validity(reports, _radars()).tolist() == want
    _, _, ok_all = converted_plots(reports, _radars(), origin)
    _, _, ok_gated = converted_plots(reports, _radars(), origin, gate=True)
    assert ok_all.all()
    assert ok_gated.tolist() == want


def test_debiased_conversion_removes_the_mean_bias():
    """Monte Carlo at 50 km with σ_β = 6°, σ_ε = 3°: the plain conversion is shrunk towards the
    radar by λ_β λ_ε (horizontal) — a bias of ~300 m — the debiased one is not."""
    rng = np.random.default_rng(7)
    n, r0, az0, el0 = 400_000, 50e3, 40.0, 5.0
    s_r, s_b, s_e = 30.0, np.radians(6.0), np.radians(3.0)
    truth = np.array(geo.polar_to_enu(r0, az0, el0))
    meas = np.stack(geo.polar_to_enu(r0 + s_r * rng.standard_normal(n),
                                     az0 + np.degrees(s_b * rng.standard_normal(n)),
                                     el0 + np.degrees(s_e * rng.standard_normal(n))), axis=-1)
    plain = meas.mean(axis=0)
    lam_b, lam_e = np.exp(-s_b**2 / 2), np.exp(-s_e**2 / 2)
    # the plain mean is the shrunk truth (E cos(β+w) = λ cos β), independently of the code under test
    np.testing.assert_allclose(plain[:2], truth[:2] * lam_b * lam_e, atol=40.0)
    assert np.linalg.norm(plain[:2] - truth[:2]) > 200.0
    deb = debias_enu(meas, np.full(n, s_b**2), np.full(n, s_e**2)).mean(axis=0)
    np.testing.assert_allclose(deb, truth, atol=40.0)


def test_centralised_debiased_option_scales_the_local_plot():
    reports, _ = _reports()
    origin = geo.LocalFrame(48.9, 2.3, 100.0)          # radar 1's site: system frame = its ENU frame
    one = reports.filter(pl.col("radar_id") == 1)
    z_lin, _, _ = converted_plots(one, _radars(), origin)
    z_deb, _, _ = converted_plots(one, _radars(), origin, conversion="debiased")
    lam_b, lam_e = np.exp(-np.radians(1.0) ** 2 / 2), np.exp(-np.radians(0.1) ** 2 / 2)
    np.testing.assert_allclose(z_deb[:, :2], z_lin[:, :2] / (lam_b * lam_e), rtol=1e-9)
    np.testing.assert_allclose(z_deb[:, 2], z_lin[:, 2] / lam_e, rtol=1e-9, atol=1e-6)
