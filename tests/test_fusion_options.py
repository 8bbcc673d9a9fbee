"""Optional fusion methods and the NIS gate against hand computations."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest
from scipy.stats import multivariate_normal, norm

from tertiary.core.units import STATE
from tertiary.core import geo
from tertiary import pipeline
from tertiary.stages.fusion import (ALL_METHODS, EXTRA_METHODS, METHODS, FusionConfig, chi2_threshold, coord_loglik, fuse, gate_pass, los_innovation, mv_loglik, trace_test)

T0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
SIGMA_R = 50.0
ORIGIN = geo.LocalFrame(45.0, 5.0, 0.0)
SITES = {1: (0.0, 0.0, 0.0), 2: (30_000.0, 0.0, 0.0), 3: (0.0, -25_000.0, 0.0)}


def _radars() -> pl.DataFrame:
    rows = []
    for rid, enu in SITES.items():
        lat, lon, alt = ORIGIN.to_geodetic(*enu)
        rows.append({"radar_id": rid, "lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt),
                     "sigma_range_m": SIGMA_R})
    return pl.DataFrame(rows, schema={"radar_id": pl.UInt32, "lat_deg": pl.Float64, "lon_deg": pl.Float64,
                                      "alt_m": pl.Float64, "sigma_range_m": pl.Float64})


RADARS = _radars()
SCHEMA = {
    "run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "target_id": pl.UInt64,
    "radar_id": pl.UInt32, "local_track_id": pl.UInt32, "report_id": pl.UInt64,
    **dict.fromkeys(STATE, pl.Float64), "cov": pl.Array(pl.Float64, 36),
    "res_range_m": pl.Float64, "res_range_var_m2": pl.Float64, "fresh": pl.Boolean,
    "nominal_var": pl.Array(pl.Float64, 3),
}


def report(k=0, radar=1, x=(0, 0, 0, 0, 0, 0), cov=1.0, res=0.0, var=SIGMA_R**2 + 100.0, fresh=True,
           nominal=(1.0, 1.0, 1.0)) -> dict:
    c = np.diag(np.broadcast_to(np.asarray(cov, float), 6)) if np.ndim(cov) <= 1 else np.asarray(cov)
    return {"run": 0, "epoch": T0 + timedelta(seconds=k), "target_id": 1, "radar_id": radar,
            "local_track_id": radar, "report_id": 1000 * k + radar, **dict(zip(STATE, map(float, x))),
            "cov": c.reshape(36).tolist(), "res_range_m": res, "res_range_var_m2": var, "fresh": fresh,
            "nominal_var": list(map(float, nominal))}


def frame(rows: list[dict]) -> pl.DataFrame:
    return pl.DataFrame(rows, schema=SCHEMA).sort(["run", "epoch", "target_id", "radar_id"])


def at(out: pl.DataFrame, method: str, k: int = 0) -> dict:
    sel = out.filter((pl.col("method") == method) & (pl.col("epoch") == T0 + timedelta(seconds=k)))
    assert sel.height == 1
    row = sel.row(0, named=True)
    row["x"] = np.array([row[c] for c in STATE])
    row["P"] = np.asarray(row["cov"]).reshape(6, 6)
    return row


def res_for_nis(v: float, var: float = SIGMA_R**2 + 100.0) -> float:
    return float(np.sqrt(v * var))


# ---------------------------------------------------------------------------- selection

def test_optional_methods_are_selectable_but_not_default():
    assert set(EXTRA_METHODS).isdisjoint(METHODS)
    assert pipeline.PipelineConfig().methods == METHODS
    cfg = pipeline.check_config(pipeline.PipelineConfig(methods=EXTRA_METHODS))
    assert cfg.methods == EXTRA_METHODS
    out = fuse(frame([report(radar=1, x=(0, 20_000, 3000, 0, 0, 0)), report(radar=2, x=(10, 20_000, 3000, 0, 0, 0))]),
               RADARS, ALL_METHODS, origin=ORIGIN)
    assert out["method"].unique(maintain_order=True).to_list() == list(ALL_METHODS)
    assert np.allclose([sum(w) for w in out["weights"].to_list()], 1.0)


def test_los_methods_need_the_origin():
    with pytest.raises(ValueError, match="aposteriori_mv: needs the system frame origin"):
        fuse(frame([report(radar=1), report(radar=2)]), RADARS, ["aposteriori_mv"])


# ---------------------------------------------------------------------------- best source

def test_best_source_picks_min_position_trace():
    c2 = np.diag([1.0, 1.0, 1.0, 900.0, 900.0, 900.0])        # best position, worst velocity
    rows = [report(radar=1, x=(1, 2, 3, 4, 5, 6), cov=2.0), report(radar=2, x=(7, 8, 9, 1, 2, 3), cov=c2),
            report(radar=3, x=(0, 0, 0, 0, 0, 0), cov=[1.5, 1.5, 1.5, 0.1, 0.1, 0.1])]
    r = at(fuse(frame(rows), RADARS, ["best_source"]), "best_source")
    np.testing.assert_array_equal(r["x"], [7, 8, 9, 1, 2, 3])
    np.testing.assert_array_equal(r["P"], c2)
    assert r["weights"] == [0.0, 1.0, 0.0] and r["radar_ids"] == [1, 2, 3]


# ---------------------------------------------------------------------------- invcov_nis

@pytest.mark.parametrize("window,lam1", [(5, 10.0), (1, 16.0)])
def test_invcov_nis_inflates_by_windowed_nis(window, lam1):
    # radar 1: NIS 4 then 16 -> λ = mean = 10 (window 5) or 16 (window 1); radar 2: NIS 0.25 -> λ = 1
    rows = [report(k=k, radar=1, x=(100.0,) * 6, cov=2.0, res=res_for_nis(v)) for k, v in ((0, 4.0), (1, 16.0))]
    rows += [report(k=k, radar=2, x=(0.0,) * 6, cov=3.0, res=res_for_nis(0.25)) for k in (0, 1)]
    out = fuse(frame(rows), RADARS, ["invcov_nis", "information"], FusionConfig(nis_window=window))
    r = at(out, "invcov_nis", k=1)
    c1, c2 = 2.0 * lam1, 3.0
    p = 1.0 / (1.0 / c1 + 1.0 / c2)
    np.testing.assert_allclose(r["x"], p * 100.0 / c1)
    np.testing.assert_allclose(r["P"], p * np.eye(6))
    r0 = at(out, "invcov_nis", k=0)                                   # epoch 0: λ₁ = 4
    np.testing.assert_allclose(r0["x"], (1 / (1 / 8 + 1 / 3)) * 100.0 / 8)
    info = at(out, "information", k=1)                                # λ = 1 would be plain information
    np.testing.assert_allclose(info["x"], (1 / (1 / 2 + 1 / 3)) * 100.0 / 2)


def test_invcov_nis_never_deflates():
    rows = [report(radar=r, x=(float(r),) * 6, cov=float(r), res=res_for_nis(0.01)) for r in (1, 2)]
    out = fuse(frame(rows), RADARS, ["invcov_nis", "information"])
    np.testing.assert_allclose(at(out, "invcov_nis")["x"], at(out, "information")["x"])


# ---------------------------------------------------------------------------- seed prior with S(k)

def test_aposteriori_seed_s_two_steps_by_hand():
    s = {1: 900.0, 2: 2500.0}
    nu = {(0, 1): 10.0, (0, 2): 60.0, (1, 1): 40.0, (1, 2): 5.0}
    rows = [report(k=k, radar=r, x=(float(r),) * 6, res=nu[k, r], var=s[r]) for k in (0, 1) for r in (1, 2)]
    out = fuse(frame(rows), RADARS, ["aposteriori_seed_S"])
    L = {key: norm.pdf(v, scale=np.sqrt(s[key[1]])) for key, v in nu.items()}
    b1 = L[0, 1] * 0.5 / (L[0, 1] * 0.5 + L[0, 2] * 0.5)                       # (4.73), b(0) = 1/2
    assert at(out, "aposteriori_seed_S", 0)["weights"] == pytest.approx([b1, 1 - b1])
    n1, n2 = L[1, 1] * (1 - b1), L[1, 2] * b1                                  # prior 1 − b(k−1)
    b1k = n1 / (n1 + n2)
    r = at(out, "aposteriori_seed_S", 1)
    assert r["weights"] == pytest.approx([b1k, 1 - b1k])
    np.testing.assert_allclose(r["x"], b1k * 1 + (1 - b1k) * 2)


# ---------------------------------------------------------------------------- §6.1 innovations

def _los_rows(nu1=30.0, nu2=-80.0):
    p = (12_000.0, 18_000.0, 4_000.0)
    return [report(radar=1, x=(*p, 100, 0, 0), cov=4.0, res=nu1, var=SIGMA_R**2 + 400.0, nominal=(900, 1600, 2500)),
            report(radar=2, x=(p[0] + 20, p[1] - 10, p[2] + 5, 110, 5, 0), cov=9.0, res=nu2,
                   var=SIGMA_R**2 + 900.0, nominal=(2500, 400, 3600))], p


def _u(site, p):
    d = np.asarray(p) - np.asarray(site)
    return d / np.linalg.norm(d)


def test_mv_loglik_equals_scipy():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(5, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a, d, res = rng.uniform(10, 500, 5), rng.uniform(100, 3000, (5, 3)), rng.normal(0, 40, 5)
    ref = [multivariate_normal(np.zeros(3), a[i] * np.outer(u[i], u[i]) + np.diag(d[i])).logpdf(u[i] * res[i])
           for i in range(5)]
    np.testing.assert_allclose(mv_loglik(res, u, a, d), ref, rtol=1e-12)


def test_aposteriori_mv_one_epoch_by_hand():
    rows, p = _los_rows()
    out = fuse(frame(rows), RADARS, ["aposteriori_mv"], FusionConfig(b_min=0.0), origin=ORIGIN)
    ll = []
    for row, site in zip(rows, (SITES[1], SITES[2])):
        u = _u(site, (row["x_m"], row["y_m"], row["z_m"]))
        s = (row["res_range_var_m2"] - SIGMA_R**2) * np.outer(u, u) + np.diag(row["nominal_var"])
        ll.append(multivariate_normal(np.zeros(3), s).logpdf(u * row["res_range_m"]))
    b1 = 1.0 / (1.0 + np.exp(ll[1] - ll[0]))                      # equal priors 1/2 cancel
    r = at(out, "aposteriori_mv")
    assert r["weights"] == pytest.approx([b1, 1 - b1], rel=1e-9)
    assert 0.05 < b1 < 0.95                                        # an informative, non-degenerate case


def test_aposteriori_coord_one_epoch_by_hand():
    rows, p = _los_rows()
    out = fuse(frame(rows), RADARS, ["aposteriori_coord"], FusionConfig(b_min=0.0), origin=ORIGIN)
    lik = []
    for row, site in zip(rows, (SITES[1], SITES[2])):
        u = _u(site, (row["x_m"], row["y_m"], row["z_m"]))
        s_c = (row["res_range_var_m2"] - SIGMA_R**2) * u**2 + np.asarray(row["nominal_var"])
        lik.append(norm.pdf(u * row["res_range_m"], scale=np.sqrt(s_c)))   # N(ν_c; 0, S_c) per axis
    b1 = lik[0] / (lik[0] + lik[1])                                        # (3,)
    x1 = np.array([rows[0][c] for c in STATE])
    x2 = np.array([rows[1][c] for c in STATE])
    w1 = np.tile(b1, 2)
    r = at(out, "aposteriori_coord")
    np.testing.assert_allclose(r["x"], w1 * x1 + (1 - w1) * x2, rtol=1e-12)
    np.testing.assert_allclose(np.diag(r["P"]), w1**2 * 4.0 + (1 - w1) ** 2 * 9.0, rtol=1e-12)
    assert r["weights"] == pytest.approx([b1.mean(), 1 - b1.mean()])
    assert np.ptp(b1) > 0.05                                                # the axes really differ


def test_coord_loglik_is_the_diagonal_of_the_mv_model():
    u = np.array([[0.6, 0.8, 0.0]])
    ll, s = coord_loglik(np.array([10.0]), u, np.array([50.0]), np.array([[100.0, 200.0, 300.0]]))
    np.testing.assert_allclose(s, [[50 * 0.36 + 100, 50 * 0.64 + 200, 300]])
    np.testing.assert_allclose(ll, norm.logpdf([6.0, 8.0, 0.0], scale=np.sqrt(s[0]))[None])
    u2, a2, d2 = los_innovation(np.array([[3.0, 4.0, 0.0, 0, 0, 0]]), np.zeros(3), np.array([2600.0]),
                                np.array([2500.0]), np.array([[1.0, 2.0, 3.0]]))
    np.testing.assert_allclose(u2, [[0.6, 0.8, 0.0]]) and np.testing.assert_allclose(a2, [100.0])


# ---------------------------------------------------------------------------- NIS gate

def _gate_rows():
    return [report(radar=1, x=(0.0,) * 6, cov=1.0, res=res_for_nis(8.9)),      # passes χ²₁(0.9973) = 9
            report(radar=2, x=(100.0,) * 6, cov=1.0, res=res_for_nis(9.1)),    # fails
            report(radar=3, x=(10.0,) * 6, cov=2.0, res=res_for_nis(1.0))]


def test_chi2_threshold_is_three_sigma():
    assert chi2_threshold(FusionConfig().nis_gate_prob) == pytest.approx(9.0, abs=1e-9)
    assert chi2_threshold(0.9973, 2) == pytest.approx(11.83, abs=0.01)
    ok, v, thr = gate_pass(np.array([res_for_nis(8.9), res_for_nis(9.1), np.nan]),
                           np.full(3, SIGMA_R**2 + 100.0), FusionConfig())
    assert ok.tolist() == [True, False, True] and v[:2] == pytest.approx([8.9, 9.1])


def test_gate_reject_drops_the_failing_source():
    out = fuse(frame(_gate_rows()), RADARS, ["information"], FusionConfig(nis_gate="reject"))
    r = at(out, "information")
    assert r["radar_ids"] == [1, 3] and r["n_sources"] == 2
    np.testing.assert_allclose(r["x"], (0.0 / 1 + 10.0 / 2) / (1 + 0.5))     # sources 1 and 3 only


def test_gate_reject_keeps_a_group_whose_every_source_fails():
    rows = [report(radar=r, x=(float(r),) * 6, res=res_for_nis(20.0)) for r in (1, 2)]
    r = at(fuse(frame(rows), RADARS, ["arithmetic"], FusionConfig(nis_gate="reject")), "arithmetic")
    assert r["n_sources"] == 2 and r["x"][0] == pytest.approx(1.5)


def test_gate_downweight_inflates_by_nis_over_threshold():
    out = fuse(frame(_gate_rows()), RADARS, ["information"], FusionConfig(nis_gate="downweight"))
    c2 = 9.1 / 9.0
    info = 1 / 1.0 + 1 / c2 + 1 / 2.0
    r = at(out, "information")
    np.testing.assert_allclose(r["x"], (0.0 + 100.0 / c2 + 10.0 / 2.0) / info)
    np.testing.assert_allclose(r["P"], np.eye(6) / info)


def test_gate_flag_leaves_fusion_unchanged():
    plain = fuse(frame(_gate_rows()), RADARS, ["information", "arithmetic"])
    flagged = fuse(frame(_gate_rows()), RADARS, ["information", "arithmetic"], FusionConfig(nis_gate="flag"))
    assert plain.equals(flagged)


def test_trace_test_by_hand():
    nu = np.array([[3.0, 4.0]])                               # νᵀν = 25, tr S = 10
    s = np.array([[[4.0, 1.0], [1.0, 6.0]]])
    assert trace_test(nu, s, 3.0).tolist() == [True] and trace_test(nu, s, 2.0).tolist() == [False]
    assert trace_test(nu, np.array([[4.0, 6.0]]), 2.4).tolist() == [False]
    # m = 1: the printed γ = 3 gate rejects NIS 4 (not a 3σ test); as a fusion gate
    out = fuse(frame([report(radar=1, res=res_for_nis(2.9)), report(radar=2, x=(100.0,) * 6, res=res_for_nis(4.0))]),
               RADARS,
               ["arithmetic"], FusionConfig(nis_gate="reject", gate_test="trace", trace_gamma=3.0))
    assert at(out, "arithmetic")["radar_ids"] == [1]


# ---------------------------------------------------------------------------- radar health

from tertiary.contract import validate  # noqa: E402
from tertiary.sensors.radar_health import HealthConfig, adaptive_r, nis_samples, radar_health, windowed_nis  # noqa: E402
from scipy.stats import chi2  # noqa: E402


def health_rows(nu, s, radar=1, track=1, dt=1.0, run=0) -> pl.DataFrame:
    n = len(nu)
    return pl.DataFrame({
        "run": pl.Series([run] * n, dtype=pl.UInt32), "radar_id": pl.Series([radar] * n, dtype=pl.UInt32),
        "local_track_id": pl.Series([track] * n, dtype=pl.UInt32),
        "time": [T0 + timedelta(seconds=dt * i) for i in range(n)],
        "res_range_m": np.asarray(nu, float), "res_range_var_m2": np.broadcast_to(np.asarray(s, float), n),
        "fresh": [True] * n})


def test_windowed_nis_by_hand():
    w = windowed_nis(nis_samples(health_rows([1.0, 1.0, 2.2, 2.2], 1.0)), HealthConfig(window_s=2.0, hold_s=0.0))
    np.testing.assert_allclose(w["nis_window"].to_numpy(), [1.0, 1.0, 2.92, 4.84])   # window (t − 2, t]
    np.testing.assert_allclose(w["k"].to_numpy(), [1, 2, 2, 2])
    np.testing.assert_allclose(w["bound"].to_numpy(), chi2.ppf(0.99, [1, 2, 2, 2]) / [1, 2, 2, 2])
    assert w["above"].to_list() == [False, False, False, True]                      # bound(k=2) = 9.21/2 = 4.61


def test_alarm_needs_the_exceedance_held():
    nu = [1.0] * 5 + [10.0] * 8                                # NIS 100 from t = 5 s on
    w = windowed_nis(nis_samples(health_rows(nu, 1.0)), HealthConfig(window_s=3.0, hold_s=4.0))
    assert w["above"].to_list() == [False] * 5 + [True] * 8
    assert w["alarm"].to_list() == [False] * 9 + [True] * 4    # alarm at t = 9 s = first exceedance + 4 s


def test_divergence_alarm_detects_a_noise_step_per_radar():
    rng = np.random.default_rng(5)
    nu1 = rng.normal(0, 1, 900)
    nu1[450:] *= 6.0                                         # radar 1: 6× noise (std) from t = 450 s
    rows = pl.concat([health_rows(nu1, 1.0, radar=1), health_rows(rng.normal(0, 1, 900), 1.0, radar=2)])
    radars = pl.DataFrame({"radar_id": pl.Series([1, 2], dtype=pl.UInt32), "sigma_range_m": [1.0, 1.0]})
    m = radar_health(rows, radars, HealthConfig(window_s=60.0, hold_s=20.0))
    validate(m, "metrics", strict=True)
    v = {(r, k): x for r, k, x in m.select("method", "metric", "value").iter_rows()}
    assert 450 < v["1", "first_alarm_s"] <= 450 + 20 + 30      # held 20 s after the window mean crosses
    assert v["1", "alarm_episodes"] >= 1 and np.isnan(v["2", "first_alarm_s"]) and v["2", "alarm_episodes"] == 0
    assert v["1", "nis_mean"] == pytest.approx((1 + 36) / 2, rel=0.15) and v["2", "nis_mean"] == pytest.approx(1, rel=0.15)
    assert v["1", "gate_flag_share"] > 0.2 and v["2", "gate_flag_share"] < 0.01
    assert set(m["method"]) == {"1", "2"} and set(m["stage"]) == {"radar_health"}


@pytest.mark.parametrize("bias", [0.0, 30.0])
def test_adaptive_r_variant_a_ignores_a_bias_b_does_not(bias):
    # nominal σ_r = 5 m (25 m²), true R = 36 × 25 = 900 m², H P⁻ Hᵀ = 100 m² (S as reported = 125)
    rng = np.random.default_rng(7)
    nu = bias + rng.normal(0, np.sqrt(100.0 + 900.0), 3000)
    s = nis_samples(health_rows(nu, 125.0))
    r = adaptive_r(s, pl.DataFrame({"radar_id": pl.Series([1], dtype=pl.UInt32), "sigma_r2": [25.0]}),
                   HealthConfig(r_window=50, r_min_samples=10))
    assert r["r_a"][:9].null_count() == 9 and r["r_a"][9] is not None
    ra, rb = r["r_a"].drop_nulls().median(), r["r_b"].drop_nulls().median()
    assert ra == pytest.approx(900.0, rel=0.15)                           # A: mean removed
    assert rb == pytest.approx(900.0 + bias**2, rel=0.15)                 # B: bias becomes variance
