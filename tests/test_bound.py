"""The posterior Cramér–Rao bound: closed forms, a Monte-Carlo check, the model fitted to the truth and the
simulated truth."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pymap3d as pm
import pytest
from polars.testing import assert_frame_equal
from scipy.linalg import solve_discrete_are

from tertiary.core import geo
from tertiary.evaluation.bound import BoundConfig, bound_metrics, illuminations, pcrb_at, pcrb_linear

from apart import Apart

T0 = datetime(2021, 10, 7, 8, 0, tzinfo=timezone.utc)


def _cv(q: float):
    """1-D constant velocity with white-noise acceleration (continuous-time q)."""
    def phi_q(tau):
        tau = np.asarray(tau, float)
        phi = np.zeros(tau.shape + (2, 2))
        phi[..., 0, 0] = phi[..., 1, 1] = 1.0
        phi[..., 0, 1] = tau
        qq = np.empty(tau.shape + (2, 2))
        qq[..., 0, 0] = q * tau ** 3 / 3
        qq[..., 0, 1] = qq[..., 1, 0] = q * tau ** 2 / 2
        qq[..., 1, 1] = q * tau
        return phi, qq
    return phi_q


def _run(n: int, r: float, phi_q, p0, pd: float = 1.0, dt: float = 1.0, seqs: int = 1):
    t = np.tile(np.arange(n) * dt, seqs)
    r_eq = np.full((n * seqs, 1, 1), r / pd)
    starts = np.arange(seqs) * n
    return pcrb_linear(t, r_eq, starts, np.full(seqs, n), phi_q, p0, np.array([0]), np.ones(n * seqs, bool))


def test_static_parameter_bound_is_sigma2_over_n():
    """Q = 0, Φ = I (a constant measured n times, diffuse prior): PCRB_n = σ²/n exactly."""
    static = lambda tau: (np.ones(np.shape(tau) + (1, 1)), np.zeros(np.shape(tau) + (1, 1)))  # noqa: E731
    p = _run(50, 4.0, static, np.array([[1e12]]))
    assert p[:, 0, 0] == pytest.approx(4.0 / np.arange(1, 51), rel=1e-9)


@pytest.mark.parametrize("pd", [1.0, 0.7])
def test_cv_steady_state_is_the_riccati_solution(pd):
    """1-D CV: the bound converges to the filtering Riccati solution, with R/Pd for Pd < 1
    (information-reduction factor); several sequences of different lengths at once."""
    q, r = 0.5, 100.0
    phi_q = _cv(q)
    phi, qq = phi_q(np.array(1.0))
    pred = solve_discrete_are(phi.T, np.array([[1.0], [0.0]]), qq, np.array([[r / pd]]))
    s = pred[0, 0] + r / pd
    post = pred - pred[:, [0]] @ pred[[0], :] / s
    p = _run(400, r, phi_q, np.diag([1e8, 1e6]), pd=pd, seqs=3)
    assert p[-1] == pytest.approx(post, rel=1e-6)
    assert p[399] == pytest.approx(post, rel=1e-6)


def test_kalman_filter_attains_the_bound_on_a_linear_simulation():
    """A Kalman filter matched to a linear-Gaussian model is efficient: its Monte-Carlo MSE
    equals the PCRB (here within the 99.9 % sampling error of 2000 runs)."""
    rng = np.random.default_rng(3)
    q, r, n, runs = 0.5, 100.0, 60, 2000
    phi_q = _cv(q)
    phi, qq = phi_q(np.array(1.0))
    p0 = np.diag([400.0, 25.0])
    x = rng.multivariate_normal([0.0, 50.0], p0, runs)
    xe, pe = np.tile([0.0, 50.0], (runs, 1)), p0.copy()
    err2 = np.empty(n)
    for k in range(n):
        if k:
            x = x @ phi.T + rng.multivariate_normal([0, 0], qq, runs)
            xe, pe = xe @ phi.T, phi @ pe @ phi.T + qq
        z = x[:, 0] + rng.normal(0, np.sqrt(r), runs)
        gain = pe[:, 0] / (pe[0, 0] + r)
        xe = xe + gain[None, :] * (z - xe[:, 0])[:, None]
        pe = pe - np.outer(gain, pe[0])
        err2[k] = np.mean((xe[:, 0] - x[:, 0]) ** 2)
    bound = _run(n, r, phi_q, p0)[:, 0, 0]
    # MSE/PCRB ~ chi2(runs)/runs at each epoch (sd sqrt(2/runs)); the mean over correlated epochs varies less
    ratio = err2[10:] / bound[10:]
    print(ratio.mean())
    assert abs(ratio.mean() - 1.0) < 3 * np.sqrt(2.0 / runs)   # one epoch's sd bounds the mean's


def _one_radar_truth():
    origin = geo.LocalFrame(48.0, 2.0, 0.0)
    t = np.arange(0, 301, 1.0)
    x, y = 20_000.0 + 0 * t, 10_000.0 + 100.0 * t
    truth = pl.DataFrame({"truth_id": 7, "time": pl.Series((t * 1e6).astype(np.int64) + 1_600_000_000_000_000)
                          .cast(pl.Datetime("us", "UTC")),
                          "x_m": x, "y_m": y, "z_m": np.full_like(t, 3000.0), "vx_mps": 0.0, "vy_mps": 100.0,
                          "vz_mps": 0.0})
    radars, reports = _radar(truth, 4.0, 200_000.0, "synchronous")
    return origin, truth, radars, reports


def _radar(truth: pl.DataFrame, period_s: float, max_range_m: float, timing: str) -> tuple[pl.DataFrame, pl.DataFrame]:
    """One radar at (48° N, 2° E) and two of its reports (its scan phase)."""
    radars = pl.DataFrame({"radar_id": pl.Series([1], dtype=pl.UInt32), "name": ["R"], "lat_deg": [48.0],
                           "lon_deg": [2.0], "alt_m": [0.0], "scan_period_s": [period_s], "sigma_range_m": [50.0],
                           "sigma_azimuth_deg": [0.1], "sigma_elevation_deg": [0.1], "max_range_m": [max_range_m],
                           "scan_phase_s": [1.0], "min_elevation_deg": [0.0], "pd": [1.0],
                           "time_offset_s": [0.0], "timing": [timing]})
    reports = pl.DataFrame({"radar_id": pl.Series([1, 1], dtype=pl.UInt32),
                            "time": truth["time"].gather([1, 5]), "azimuth_deg": [10.0, 50.0]})
    return radars, reports


def test_scan_schedule_and_single_scan_information():
    """Events at the radar's scan times (phase from its reports), and one scan's information
    equals the converted polar covariance at the true point (independent computation)."""
    origin, truth, radars, reports = _one_radar_truth()
    ev = illuminations(truth, radars, reports, origin)
    t = ev["t_s"].to_numpy()
    assert t == pytest.approx(1.0 + 4.0 * np.arange(len(t)))
    assert len(t) == 75
    r_eq = ev["r_eq"].to_numpy()[3].reshape(3, 3)
    pos = np.array([20_000.0, 10_000.0 + 100.0 * 13.0, 3000.0])
    rng, az, el = geo.enu_to_polar(*pos)          # site = origin: system frame is the site frame
    expect = geo.polar_sigmas_to_enu_cov(rng, az, el, 50.0, 0.1, 0.1)
    assert r_eq == pytest.approx(expect, rel=1e-6)
    # with the plot's barometric height: the information (R⁻¹ + e eᵀ/V) written out, e the local
    # vertical at the aircraft (by pymap3d)
    from tertiary.evaluation.bound_measurements import HEIGHT_VAR_M2
    with_h = illuminations(truth, radars, reports, origin, BoundConfig(mode_c_height=True))["r_eq"].to_numpy()[3]
    with_h = with_h.reshape(3, 3)
    lat, lon, _ = pm.enu2geodetic(*pos, origin.lat_deg, origin.lon_deg, origin.alt_m)
    up = np.array(pm.uvw2enu(*pm.enu2uvw(0.0, 0.0, 1.0, lat, lon), origin.lat_deg, origin.lon_deg))
    want = np.linalg.inv(np.linalg.inv(expect) + np.outer(up, up) / HEIGHT_VAR_M2)
    assert with_h == pytest.approx(want, rel=1e-6, abs=1e-9)
    assert with_h[2, 2] < 1.01 * HEIGHT_VAR_M2 < expect[2, 2]          # the local vertical is near the z axis here


def test_bound_rows_pool_like_rmse_and_gap_is_signed():
    origin, truth, radars, reports = _one_radar_truth()
    ev = illuminations(truth, radars, reports, origin)
    samples = truth.select("truth_id", pl.col("time").alias("epoch")).slice(40, 200)
    b = pcrb_at(samples, ev, BoundConfig(), truth=truth)
    assert b.height == 200 and (b["b2_pos"] > b["b2_horizontal"]).all()
    # between scans the bound grows (prediction), at a scan it drops
    v = b["b2_pos"].to_numpy()
    assert v[1] < v[0] or v[2] < v[1] or v[3] < v[2]
    scored = samples.with_columns(pl.lit("m").alias("method"), pl.lit(0).alias("run"),
                                  pl.lit(None, pl.String).alias("seg_class"))
    acc = pl.DataFrame({"stage": "fusion", "method": "m", "metric": "rmse_pos_m", "segment": "all",
                        "value": 100.0, "n_runs": 1})
    rows = bound_metrics(scored, acc, b)
    got = {r["metric"]: r["value"] for r in rows.iter_rows(named=True)}
    assert got["pcrb_pos_m"] == pytest.approx(np.sqrt(v.mean()))
    assert got["gap_pos_m"] == pytest.approx(100.0 - got["pcrb_pos_m"])
    assert "gap_horizontal_m" not in got          # no accuracy row to compare with


def test_a_summary_keeps_what_it_takes_of_each_recorded_bound():
    """``pcrb_at`` records only (tr P_pos, P_xx + P_yy, tr P_vel) of each bound (memory): a
    summary gives, at the recorded rows only and in row order, exactly what it takes of the full
    bounds. Fails if a summary row lands on another row or is skipped."""
    rng = np.random.default_rng(3)
    n, seqs = 40, 3
    t = np.tile(np.cumsum(rng.uniform(0.5, 4.0, n)), seqs)
    r_eq = np.full((n * seqs, 1, 1), 25.0)
    r_eq[rng.random(n * seqs) < 0.3] = np.nan                 # epochs without a measurement
    record = rng.random(n * seqs) < 0.5
    args = (t, r_eq, np.arange(seqs) * n, np.full(seqs, n), _cv(0.3), np.diag([1e4, 1e2]), np.array([0]), record)
    full = pcrb_linear(*args)
    got = pcrb_linear(*args, summary=lambda p: np.column_stack([p[:, 0, 0], p[:, 0, 0] + p[:, 1, 1]]))
    assert got.shape == (record.sum(), 2)
    np.testing.assert_allclose(got, np.column_stack([full[:, 0, 0], full[:, 0, 0] + full[:, 1, 1]]), rtol=0, atol=0)


@pytest.mark.parametrize("size", [50, 300, 700])
def test_the_bound_computed_a_block_of_aircraft_at_a_time_equals_the_whole(monkeypatch, size):
    """``pcrb_at`` runs the recursion a block of whole aircraft at a time (memory).
    Three aircraft seen by one radar, each sequence longer than a block of 50 rows, two to a
    block of 300, all in one of 700: the bounds equal one block's, row for row. Fails if a
    block cuts an aircraft's sequence, gathers another block's measurements, or puts its rows
    out of order."""
    from tertiary.evaluation import bound
    origin, truth, radars, reports = _one_radar_truth()
    many = pl.concat([truth.with_columns(pl.lit(k, pl.Int64).alias("truth_id"),
                                         pl.col("x_m") + 5_000.0 * k, pl.col("y_m") - 3_000.0 * k) for k in (7, 8, 9)])
    ev = illuminations(many, radars, reports, origin)
    samples = many.select("truth_id", pl.col("time").alias("epoch")).gather_every(2)
    whole = pcrb_at(samples, ev, BoundConfig(), truth=many)
    monkeypatch.setattr(bound, "BOUND_BLOCK_ROWS", size)
    blocks = bound._aircraft_blocks(np.array([0, 200, 350]), 500, size)
    assert len(blocks) == {50: 3, 300: 2, 700: 1}[size]
    got = pcrb_at(samples, ev, BoundConfig(), truth=many)
    assert whole.height == samples.height and whole["truth_id"].n_unique() == 3
    assert_frame_equal(got, whole, check_exact=False, rel_tol=1e-12, abs_tol=0.0)


@pytest.mark.parametrize("aircraft", [1, 2])
def test_the_bound_stage_pooled_a_block_of_aircraft_at_a_time_equals_the_whole(monkeypatch, aircraft):
    """``bound_stage`` makes the illuminations and bounds of a block of aircraft at a time and
    pools per-epoch sums over the blocks (memory): the bound rows equal one block's.
    Two pictures (methods) share the epochs of three aircraft, so an epoch's mean takes samples
    from several blocks. Fails if a block's sums are pooled as a mean of means, a block drops
    another's aircraft, or the blocks read different scan origins."""
    from types import SimpleNamespace

    from tertiary.evaluation import bound
    origin, truth, radars, reports = _one_radar_truth()
    many = pl.concat([truth.with_columns(pl.lit(k, pl.Int64).alias("truth_id"),
                                         pl.col("x_m") + 5_000.0 * k, pl.col("y_m") - 3_000.0 * k) for k in (7, 8, 9)])
    base = many.select("truth_id", pl.col("time").alias("epoch"), pl.lit(0, pl.UInt32).alias("run"))
    k = pl.int_range(pl.len()).over("truth_id")          # the same epochs of every aircraft
    scored = pl.concat([base.filter(k % 2 == 0).with_columns(pl.lit("a").alias("method")),
                        base.filter(k % 3 == 0).with_columns(pl.lit("b").alias("method"))])
    seg = pl.when(pl.col("truth_id") == 8).then(pl.lit("turn")).otherwise(pl.lit("straight"))
    scored = scored.with_columns(seg.alias("seg_class")).select("method", "run", "epoch", "truth_id", "seg_class")
    acc = pl.DataFrame({"stage": "fusion", "method": ["a", "b"], "metric": "rmse_pos_m", "segment": "all",
                        "value": [100.0, 90.0], "n_runs": 1})
    ds = SimpleNamespace(origin=origin, scenario=None)
    whole = bound.bound_stage(ds, many, radars, reports, scored, acc, [])
    monkeypatch.setattr(bound, "BOUND_AIRCRAFT", aircraft)
    got = bound.bound_stage(ds, many, radars, reports, scored, acc, [])
    assert set(whole["segment"]) == {"all", "straight", "turn"} and set(whole["method"]) == {"a", "b"}
    assert_frame_equal(got, whole, check_exact=False, rel_tol=1e-12, abs_tol=0.0)
    # the pooling is over every sample of an epoch: a mean of the blocks' means would differ
    one = bound.bound_metrics(scored, acc, pcrb_at(scored, illuminations(many, radars, reports, origin),
                                                   BoundConfig.from_scenario(None), truth=many))
    assert_frame_equal(got, one, check_exact=False, rel_tol=1e-9, abs_tol=0.0)


def test_the_compiled_recursion_equals_the_vectorised_reference():
    """``pcrb_at`` runs (T34) compiled (:mod:`tertiary.evaluation.bound_kernel`: per-axis blocks of Φ and
    Q = d dᵀ, Cholesky-solved update). Against :func:`pcrb_linear` with the 9×9 block-diagonal model
    M: sequences of different lengths (one of a single row), irregular times, events without a
    measurement, full 3×3 measurement covariances as a rotated radar gives, deviations on some rows
    only (other axes' differ), a prior acceleration per sequence, recorded and unrecorded rows — the
    same (tr P_pos, P_xx + P_yy, tr P_vel) to round-off. Fails if the prediction skips a block or
    mixes the axes' deviations, the update drops the cross-axis terms or a record lands elsewhere."""
    from tertiary.evaluation.bound import POS, _bound_summary, _ca9, _pcrb_block, _prior9
    rng = np.random.default_rng(7)
    lengths = np.array([1, 37, 5, 120, 60])
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    n = int(lengths.sum())
    t = np.concatenate([np.cumsum(rng.uniform(0.2, 6.0, k)) for k in lengths])
    a = rng.normal(size=(n, 3, 3))
    r_eq = a @ a.swapaxes(1, 2) * 400.0 + np.eye(3) * 100.0      # full, positive definite
    r_eq[rng.random(n) < 0.35] = np.nan
    record = rng.random(n) < 0.6
    dev = rng.normal(size=(n, 3, 3)) * np.array([20.0, 5.0, 1.0])
    dev[rng.random(n) < 0.6] = 0.0                                # straight stretches: no process noise
    acc0 = rng.normal(size=(len(lengths), 3))
    cfg = BoundConfig()
    tau = np.r_[0.0, np.diff(t)]
    want = pcrb_linear(t, r_eq, starts, lengths, _ca9(tau, dev), _prior9(cfg, acc0), POS, record, _bound_summary)
    got = _pcrb_block(t, r_eq, starts, lengths, record, cfg, dev, acc0)
    assert got.shape == (record.sum(), 3) and np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert got[:, 0].min() < 0.01 * got[:, 0].max()             # updates pulled some far below the prior
    swapped = _pcrb_block(t, r_eq, starts, lengths, record, cfg, dev[:, ::-1], acc0)
    assert not np.allclose(swapped, want, rtol=1e-6)


def test_the_compiled_recursion_updates_the_velocities_at_velocity_events():
    """Rows flagged ``vel`` update (v_x, v_y, v_z) instead of the positions: against the same
    recursion written out with numpy, one event at a time (H the velocity rows there). Fails
    when the flag is ignored."""
    from tertiary.evaluation.bound import POS, VEL, _bound_summary, _ca9, _pcrb_block, _prior9
    rng = np.random.default_rng(8)
    lengths = np.array([12, 40])
    starts = np.r_[0, lengths[0]]
    n = int(lengths.sum())
    t = np.concatenate([np.cumsum(rng.uniform(0.5, 5.0, k)) for k in lengths])
    a = rng.normal(size=(n, 3, 3))
    r_eq = a @ a.swapaxes(1, 2) + np.eye(3)
    vel = rng.random(n) < 0.5
    r_eq[~vel] *= 400.0
    r_eq[rng.random(n) < 0.2] = np.nan
    dev = rng.normal(size=(n, 3, 3)) * np.array([20.0, 5.0, 1.0]) * (rng.random(n) < 0.3)[:, None, None]
    acc0 = rng.normal(size=(2, 3))
    cfg = BoundConfig()
    record = np.ones(n, bool)
    got = _pcrb_block(t, r_eq, starts, lengths, record, cfg, dev, acc0, vel)
    tau = np.r_[0.0, np.diff(t)]
    phi, q = _ca9(tau, dev)
    p0 = _prior9(cfg, acc0)
    want = []
    for g, (s0, k) in enumerate(zip(starts, lengths)):
        p = p0[g].copy()
        for i in range(s0, s0 + k):
            if i > s0:
                p = phi[i] @ p @ phi[i].T + q[i]
            if not np.isnan(r_eq[i, 0, 0]):
                h = np.zeros((3, 9))
                h[np.arange(3), VEL if vel[i] else POS] = 1.0
                gain = p @ h.T @ np.linalg.inv(h @ p @ h.T + r_eq[i])
                p = p - gain @ h @ p
            want.append(p)
    np.testing.assert_allclose(got, _bound_summary(np.array(want)), rtol=1e-8)


def test_a_downlinked_velocity_is_measured_along_and_across_the_track():
    """At the system origin (no change of axes) an aircraft flying north at 200 m/s: the
    velocity's covariance is σ_s² along y, (200 m/s · σ_χ)² along x and no vertical information;
    at 7° of longitude from the origin its axes are turned by the meridian convergence."""
    from tertiary.evaluation.bound_measurements import VELOCITY_VERTICAL_VAR, velocity_covariance
    origin = geo.LocalFrame(47.0, 2.0, 0.0)
    r = velocity_covariance(np.array([[0.0, 0.0, 9000.0]]), np.array([[0.0, 200.0, 0.0]]), origin, 0.5, 0.2)[0]
    cross = (200.0 * np.radians(0.2)) ** 2
    np.testing.assert_allclose(r[:2, :2], np.diag([cross, 0.25]), atol=1e-6)
    assert r[2, 2] > 1e9 * 0.25
    # far east: the aircraft's north is the system's north turned by the convergence
    e, n, u = origin.from_geodetic(47.0, 9.0, 9000.0)
    north = np.array(geo.local_vector_to_frame(0.0, 1.0, 0.0, 47.0, 9.0, origin)).ravel()
    r = velocity_covariance(np.array([[float(e), float(n), float(u)]]), 200.0 * north[None], origin, 0.5, 0.2)[0]
    w, v = np.linalg.eigh(r)
    along = v[:, np.argmin(np.abs(w - 0.25))]
    assert abs(abs(along @ north) - 1.0) < 1e-9 and abs(north[0]) > 0.08          # 5.1° from the system's y
    assert w.max() == pytest.approx(VELOCITY_VERTICAL_VAR, rel=1e-6)


@pytest.mark.parametrize("kw", [dict(ehs_speed_sigma_mps=0.0), dict(ehs_track_sigma_deg=float("nan"))])
def test_the_register_noise_of_the_bound_is_checked(kw):
    with pytest.raises(ValueError, match="ehs_"):
        BoundConfig(**kw)


def test_a_downlinked_velocity_lowers_the_bound_of_a_mode_s_aircraft():
    """The bound with the downlinked velocities is below the plots-only bound wherever an
    aircraft has a Mode S address, and equal elsewhere."""
    from tertiary import load_scenario
    from tertiary.simulate import simulate
    import dataclasses
    sc = load_scenario("terminal-area")
    ds = simulate(dataclasses.replace(sc, duration_s=300.0, traffic=dataclasses.replace(sc.traffic, aircraft=12)))
    # one aircraft without a Mode S transponder
    first = ds.reports["truth_id"].drop_nulls().min()
    ds = dataclasses.replace(ds, reports=ds.reports.with_columns(
        pl.when(pl.col("truth_id") == first).then(None).otherwise(pl.col("mode_s")).alias("mode_s")))
    samples = ds.truth.select("truth_id", pl.col("time").alias("epoch")).gather_every(7)
    both = []
    for on in (True, False):
        cfg = BoundConfig(downlinked_velocity=on)
        ev = illuminations(ds.truth, ds.radars, ds.reports, ds.origin, cfg)
        both.append(pcrb_at(samples, ev, cfg, truth=ds.truth).sort("truth_id", "epoch"))
    with_v, plots = both
    ms = ds.reports.filter(pl.col("mode_s").is_not_null())["truth_id"].unique().to_list()
    is_ms = with_v["truth_id"].is_in(ms).to_numpy()
    assert is_ms.any() and (~is_ms).any()
    assert (with_v["b2_vel"].to_numpy()[is_ms] < plots["b2_vel"].to_numpy()[is_ms]).mean() > 0.95
    np.testing.assert_allclose(with_v["b2_pos"].to_numpy()[~is_ms], plots["b2_pos"].to_numpy()[~is_ms])


def test_a_downlinked_velocity_counts_from_the_aircrafts_first_mode_s_report():
    """An aircraft whose reports carry its Mode S address only 100 s into its flight: its velocity is a
    measurement from then (less a scan period and the clocks' offsets) and not before, when no
    report of it carries one. Its bound equals the plots-only bound until then and is below it
    after. Fails if the address counts for the whole flight, or not at all."""
    from tertiary import load_scenario
    from tertiary.simulate import simulate
    from tertiary.evaluation.bound import mode_s_lead_s
    import dataclasses
    sc = load_scenario("terminal-area")
    ds = simulate(dataclasses.replace(sc, duration_s=400.0, traffic=dataclasses.replace(sc.traffic, aircraft=6)))
    ms = ds.reports.filter(pl.col("mode_s").is_not_null())["truth_id"].drop_nulls().unique()
    span = (ds.truth.filter(pl.col("truth_id").is_in(ms.implode())).group_by("truth_id")
            .agg(pl.col("time").min().alias("t0"), (pl.col("time").max() - pl.col("time").min()).alias("d"))
            .sort("d", "truth_id", descending=True))
    tid, t0 = span["truth_id"][0], span["t0"][0]
    assert span["d"][0].total_seconds() > 200
    late = t0 + timedelta(seconds=100)
    reports = ds.reports.with_columns(pl.when((pl.col("truth_id") == tid) & (pl.col("time") < late)).then(None)
                                      .otherwise(pl.col("mode_s")).alias("mode_s"))
    truth = ds.truth.filter(pl.col("truth_id") == tid)
    samples = truth.select("truth_id", pl.col("time").alias("epoch")).gather_every(3)
    got = []
    for cfg, rep in ((BoundConfig(), reports), (BoundConfig(downlinked_velocity=False), reports)):
        ev = illuminations(truth, ds.radars, rep, ds.origin, cfg)
        got.append(pcrb_at(samples, ev, cfg, truth=truth).sort("epoch"))
    with_v, plots = got
    s = (with_v["epoch"] - t0).dt.total_seconds().to_numpy()
    before, after = s < 100.0 - mode_s_lead_s(ds.radars), s > 130.0
    assert before.any() and after.any()
    np.testing.assert_allclose(with_v["b2_vel"].to_numpy()[before], plots["b2_vel"].to_numpy()[before], rtol=1e-12)
    assert (with_v["b2_vel"].to_numpy()[after] < plots["b2_vel"].to_numpy()[after]).all()


def test_without_manoeuvres_the_bound_is_the_regression_bound():
    """No deviation and a known zero acceleration (a straight leg): M is a deterministic line, and
    after n plots of σ² per axis at unit spacing (diffuse prior) the bound is the least-squares
    line's: position at the last plot σ²(4n − 2)/(n(n + 1)), velocity 12σ²/(n(n² − 1)) per axis."""
    from tertiary.evaluation.bound import POS, _ca9, _prior9
    n, sig2 = 30, 400.0
    t = np.arange(n, dtype=float)
    cfg = BoundConfig(p0_sigma_m=1e7, v0_sigma_mps=1e5)
    p = pcrb_linear(t, np.tile(np.eye(3) * sig2, (n, 1, 1)), np.array([0]), np.array([n]),
                    _ca9(np.r_[0.0, np.ones(n - 1)], np.zeros((n, 3, 3))), _prior9(cfg, np.zeros((1, 3))), POS,
                    np.ones(n, bool))
    k = np.arange(2, n + 1)
    assert p[1:, 0, 0] == pytest.approx(sig2 * (4 * k - 2) / (k * (k + 1)), rel=1e-6)
    assert p[1:, 1, 1] == pytest.approx(12 * sig2 / (k * (k * k - 1)), rel=1e-6)
    assert p[1:, 6, 6] == pytest.approx(p[1:, 0, 0], rel=1e-12)


def test_the_truth_is_the_unit_realisation_of_the_model():
    """The model's deviation d over an interval (M2) is exactly the truth's departure from the
    constant-acceleration prediction: a truth whose acceleration steps on (10 s, 25 s) between its
    1 s samples, rows at irregular times — d = x(t_k) − Φ(τ) x(t_{k−1}) of the analytic (p, v, a),
    and ā at each row the truth's. Zero on the straight stretches before and after. Fails if a step
    is counted in the wrong interval, weighted by the wrong lever arm or taken from the wrong axis."""
    from tertiary.evaluation.bound_truth import Truth
    a_on = np.array([1.5, -0.5, 0.2])

    def state(t):
        t = np.asarray(t, float)[:, None]
        dt = np.clip(t - 10.0, 0.0, 15.0)
        v = np.array([100.0, 20.0, 0.0]) + a_on * dt
        p = np.array([1e4, -2e3, 3e3]) + np.array([100.0, 20.0, 0.0]) * t + a_on * dt ** 2 / 2 + a_on * 15.0 * np.clip(
            t - 25.0, 0.0, None)
        acc = np.where((t >= 10.0) & (t < 25.0), a_on, 0.0)
        return p, v, acc
    ts = np.arange(0.0, 41.0)
    p, v, _ = state(ts)
    truth = pl.DataFrame({"truth_id": 3, "time": pl.Series((ts * 1e6).astype(np.int64)).cast(pl.Datetime("us", "UTC")),
                          "x_m": p[:, 0], "y_m": p[:, 1], "z_m": p[:, 2], "vx_mps": v[:, 0], "vy_mps": v[:, 1],
                          "vz_mps": v[:, 2]})
    tr = Truth.of(truth, 0, half_window_s=0.0)
    rows = np.array([1.3, 3.3, 7.1, 10.0, 12.6, 18.0, 24.5, 27.4, 31.9, 39.0])
    first = np.zeros(len(rows), bool)
    first[0] = True
    dev, acc = tr.deviations(np.zeros(len(rows), np.int64), rows, first)
    p, v, a = state(rows)
    x = np.stack([p, v, a], axis=-1)                                  # (n, axis, (p, v, a))
    tau = np.diff(rows)
    phi = np.zeros((len(tau), 3, 3))
    phi[:, 0, 0] = phi[:, 1, 1] = phi[:, 2, 2] = 1.0
    phi[:, 0, 1] = phi[:, 1, 2] = tau
    phi[:, 0, 2] = tau ** 2 / 2
    want = x[1:] - np.einsum("nij,nkj->nki", phi, x[:-1])
    np.testing.assert_allclose(dev[1:], want, rtol=1e-9, atol=1e-9)
    # only the intervals holding the onset (10 s) and the end (25 s) deviate; none at constant acceleration
    assert (dev[[0, 1, 2, 8, 9]] == 0).all() and np.abs(dev[[4, 5, 6]]).max() < 1e-9
    assert np.abs(dev[3]).max() > 1.0 and np.abs(dev[7]).max() > 1.0
    np.testing.assert_allclose(acc, a, atol=1e-12)


def test_the_range_screen_keeps_every_illumination(monkeypatch):
    """A rotating radar (12 s, 30 km) and 40 fast aircraft (250 m/s) crossing its range in and
    out on straight lines, two with a 40 s truth gap across the boundary: the scans dropped
    before the beam-passage iterations (``RANGE_SCREEN``) hold no illumination — the events
    equal those without the screen, while the iterations see fewer scans. A screen without
    the motion margin loses illuminations (checked here: the test can tell)."""
    from tertiary.evaluation import bound
    origin = geo.LocalFrame(48.0, 2.0, 0.0)
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 601.0)
    rows = []
    for k in range(40):
        heading = rng.uniform(0, 2 * np.pi)
        miss = rng.uniform(-20_000, 20_000)                  # closest approach to the site
        along = 250.0 * (t - rng.uniform(100, 500))
        x = along * np.sin(heading) + miss * np.cos(heading)
        y = along * np.cos(heading) - miss * np.sin(heading)
        keep = np.ones(len(t), bool)
        if k < 2:                                             # a gap where it crosses 30 km
            cross = int(np.argmin(np.abs(np.hypot(x, y) - 30_000.0)))
            keep[max(cross - 20, 1):cross + 20] = False
        us = (t[keep] * 1e6).astype(np.int64) + 1_600_000_000_000_000
        rows.append(pl.DataFrame({"truth_id": k, "time": pl.Series(us).cast(pl.Datetime("us", "UTC")),
                                  "x_m": x[keep], "y_m": y[keep], "z_m": 3000.0,
                                  "vx_mps": 250.0 * np.sin(heading), "vy_mps": 250.0 * np.cos(heading),
                                  "vz_mps": 0.0}))
    truth = pl.concat(rows)
    radars, reports = _radar(truth, 12.0, 30_000.0, "rotating")
    seen = []
    at = bound.Truth.at
    monkeypatch.setattr(bound.Truth, "at", lambda self, a, tt: seen.append(len(a)) or at(self, a, tt))
    monkeypatch.setattr(bound, "RANGE_SCREEN", False)
    want = illuminations(truth, radars, reports, origin)
    unscreened = sum(seen[1:])
    seen.clear()
    monkeypatch.setattr(bound, "RANGE_SCREEN", True)
    got = illuminations(truth, radars, reports, origin)
    assert want.height > 200 and sum(seen[1:]) < 0.7 * unscreened
    assert_frame_equal(got, want)
    tight = bound.Truth.top_speed
    monkeypatch.setattr(bound.Truth, "top_speed", property(lambda self: -500.0 / 12.0))   # no motion margin
    assert illuminations(truth, radars, reports, origin).height < want.height
    monkeypatch.setattr(bound.Truth, "top_speed", tight)


def _three_aircraft():
    """(a dataset's origin holder, the truth of three aircraft seen by one radar, the radars,
    the reports, every truth sample scored, an accuracy row): the bound stage's inputs."""
    from types import SimpleNamespace
    origin, truth, radars, reports = _one_radar_truth()
    many = pl.concat([truth.with_columns(pl.lit(k, pl.Int64).alias("truth_id"),
                                         pl.col("x_m") + 5_000.0 * k, pl.col("y_m") - 3_000.0 * k) for k in (7, 8, 9)])
    scored = many.select(pl.lit("a").alias("method"), pl.lit(0, pl.UInt32).alias("run"),
                         pl.col("time").alias("epoch"), "truth_id", pl.lit("straight").alias("seg_class"))
    acc = pl.DataFrame({"stage": "fusion", "method": ["a"], "metric": "rmse_pos_m", "segment": "all",
                        "value": [100.0], "n_runs": 1})
    return SimpleNamespace(origin=origin, scenario=None), many, radars, reports, scored, acc


def test_the_bound_stage_reads_a_truth_on_disk_a_block_of_aircraft_at_a_time(monkeypatch, tmp_path):
    """On an on-disk run the bound's truth is a scan of the reference (memory: the national
    day's 79 M truth rows held whole were ~5.7 GB), read ``BOUND_READ_AIRCRAFT`` aircraft at a
    time: the bound rows equal those of the truth in memory, and no read holds another read's
    aircraft. Fails if a read drops or repeats aircraft, or if the scan is read whole."""
    from tertiary.evaluation import bound
    from tertiary.evaluation.evaluate import write_reference
    ds, many, radars, reports, scored, acc = _three_aircraft()
    want = bound.bound_stage(ds, many, radars, reports, scored, acc, [])
    scan = pl.scan_parquet(write_reference(many, tmp_path / "ref.parquet")).drop("__prev", "__next")
    held: list[list[int]] = []
    real = bound._truth_reads

    def reads(t, ids):
        for read, rows in real(t, ids):
            held.append(sorted(set(rows["truth_id"].to_list())))
            assert read.tolist() == held[-1]
            yield read, rows
    monkeypatch.setattr(bound, "_truth_reads", reads)
    monkeypatch.setattr(bound, "BOUND_READ_AIRCRAFT", 2)
    got = bound.bound_stage(ds, scan, radars, reports, scored, acc, [])
    assert held == [[7, 8], [9]]
    assert want.height
    assert_frame_equal(got, want, check_exact=False, rel_tol=1e-12, abs_tol=0.0)


def test_the_bound_computed_apart_a_block_of_aircraft_a_piece_equals_the_stage(monkeypatch, tmp_path):
    """A distributed run's end computes the bound as pieces of its cluster, each reading its
    own aircraft's truth from the reference: the rows equal the stage's. Fails if a piece
    loses an aircraft."""
    from tertiary.evaluation import bound, bound_fanout
    from tertiary.evaluation.evaluate import reference_files, write_reference
    from tertiary.pipeline.tables import BOUND_TRUTH
    ds, many, radars, reports, scored, acc = _three_aircraft()
    want = bound.bound_stage(ds, many, radars, reports, scored, acc, [])
    files = reference_files(write_reference(many, tmp_path / "ref.parquet"))
    monkeypatch.setattr(bound_fanout, "PIECE_AIRCRAFT", 2)
    fanout = Apart()
    got = bound_fanout.bound_stage_apart(ds, fanout, files, BOUND_TRUTH, radars, reports, scored, acc, [])
    assert want.height and fanout.pieces == {"_piece": 2}
    assert_frame_equal(got, want, check_exact=False, rel_tol=1e-12, abs_tol=0.0)


def test_samples_before_the_first_measurement_have_no_bound_and_are_counted():
    """An epoch before an aircraft's first plot holds the prior alone: no bound there, and the
    pooled bound is that of the measured samples, the rest counted in
    ``bound_unmeasured_samples``. Fails when such samples keep the prior (its 10 km per axis
    would dominate the pooled figure)."""
    origin, truth, radars, reports = _one_radar_truth()
    ev = illuminations(truth, radars, reports, origin)
    first = ev["time"].min()
    samples = truth.select("truth_id", pl.col("time").alias("epoch")).head(60)
    before = samples.filter(pl.col("epoch") < first).height
    assert 0 < before < samples.height
    b = pcrb_at(samples, ev, BoundConfig(), truth=truth)
    unmeasured = b.filter(pl.col("epoch") < first)
    assert unmeasured.height == before and unmeasured["b2_pos"].is_nan().all()
    measured = b.filter(pl.col("epoch") >= first)
    assert measured["b2_pos"].is_not_nan().all() and (measured["b2_pos"] < 1e8).all()
    scored = samples.with_columns(pl.lit("m").alias("method"), pl.lit(0).alias("run"),
                                  pl.lit(None, pl.String).alias("seg_class"))
    acc = pl.DataFrame({"stage": "fusion", "method": "m", "metric": "rmse_pos_m", "segment": "all",
                        "value": 100.0, "n_runs": 1})
    got = {r["metric"]: r["value"] for r in bound_metrics(scored, acc, b).iter_rows(named=True)}
    assert got["pcrb_pos_m"] == pytest.approx(np.sqrt(measured["b2_pos"].mean()))
    assert got["bound_unmeasured_samples"] == before
