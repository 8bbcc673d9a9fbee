"""Radar registration: estimation (reference and radar to radar), correction, step detection."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary.stages import align
from tertiary.core import geo
from tertiary.sensors import registration as reg
from tertiary.core.errors import DataError
from tertiary.simulate import load_scenario, simulate

US = 1_000_000
ORIGIN = geo.LocalFrame(48.85, 2.35, 0.0)
SITES = [(49.0, 2.55, 120.0), (48.72, 2.38, 95.0), (48.77, 1.78, 180.0)]
BIAS = np.array([[12.0, 0.02, 0.02], [-15.0, -0.03, -0.03], [20.0, 0.04, 0.01]])   # m, deg, s (Σδ = 0)


def _radars() -> pl.DataFrame:
    return pl.DataFrame({
        "radar_id": pl.Series([1, 2, 3], dtype=pl.UInt32), "name": ["A", "B", "C"],
        "lat_deg": [s[0] for s in SITES], "lon_deg": [s[1] for s in SITES], "alt_m": [s[2] for s in SITES],
        "scan_period_s": [4.0, 5.0, 6.0], "sigma_range_m": [30.0, 40.0, 60.0],
        "sigma_azimuth_deg": [0.06, 0.07, 0.08], "sigma_elevation_deg": [0.15, 0.15, 0.2],
        "max_range_m": [2.5e5] * 3})


def _hand_case(gain: np.ndarray | None = None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """Six aircraft (straight lines and a 3°/s turn) seen by three radars with known biases and
    no noise: every plot computed independently with geo.frame_to_frame + geo.enu_to_polar."""
    rng = np.random.default_rng(3)
    t_truth = np.arange(0.0, 601.0, 1.0)
    truth, reports = [], []
    for k in range(6):
        p0 = rng.uniform(-40e3, 40e3, 2)
        speed, heading = rng.uniform(100, 200), rng.uniform(0, 2 * np.pi)
        omega = np.radians(3.0) if k == 0 else 0.0
        hdg = heading + omega * t_truth
        if omega:
            e = p0[0] + speed / omega * (np.cos(heading) - np.cos(hdg))
            n = p0[1] + speed / omega * (np.sin(hdg) - np.sin(heading))
        else:
            e, n = p0[0] + speed * np.sin(heading) * t_truth, p0[1] + speed * np.cos(heading) * t_truth
        ve, vn = speed * np.sin(hdg), speed * np.cos(hdg)
        h = 3000.0 + 500.0 * k + 2.0 * t_truth                      # climbing: the altitude moves too
        # the system-frame z of a geodetic height h at (e, n)
        z = h - (e ** 2 + n ** 2) / (2 * geo.EARTH_RADIUS_M)
        for _ in range(3):
            z += h - ORIGIN.to_geodetic(e, n, z)[2]
        vz = np.gradient(z, t_truth)
        truth.append(pl.DataFrame({"truth_id": k, "t": t_truth, "x_m": e, "y_m": n, "z_m": z,
                                   "vx_mps": ve, "vy_mps": vn, "vz_mps": vz}))
        for i, site in enumerate(SITES):
            t_true = np.arange(5.0 + i, 590.0, 4.0 + i)
            pe, pn = np.interp(t_true, t_truth, e), np.interp(t_true, t_truth, n)
            if omega:
                hd = heading + omega * t_true
                pe = p0[0] + speed / omega * (np.cos(heading) - np.cos(hd))
                pn = p0[1] + speed / omega * (np.sin(hd) - np.sin(heading))
            else:
                pe, pn = p0[0] + speed * np.sin(heading) * t_true, p0[1] + speed * np.cos(heading) * t_true
            ph = 3000.0 + 500.0 * k + 2.0 * t_true
            pz = ph - (pe ** 2 + pn ** 2) / (2 * geo.EARTH_RADIUS_M)
            for _ in range(3):
                pz += ph - ORIGIN.to_geodetic(pe, pn, pz)[2]
            q, _, _ = geo.frame_to_frame(np.stack([pe, pn, pz], 1), ORIGIN, geo.LocalFrame(*site))
            r, az, _el = geo.enu_to_polar(*q.T)
            g = 0.0 if gain is None else gain[i]
            reports.append(pl.DataFrame({
                "run": 0, "radar_id": i + 1, "t": t_true + BIAS[i, 2], "range_m": r * (1 + g) + BIAS[i, 0],
                "azimuth_deg": np.mod(az + BIAS[i, 1], 360.0), "altitude_m": ph, "truth_id": k,
                "mode_s": f"a{k:05x}", "local_track_id": k + 1}))
    epoch = 1_633_600_000 * US

    def stamp(df):
        return df.with_columns((pl.col("t") * US).round(0).cast(pl.Int64).add(epoch)
                               .cast(pl.Datetime("us", "UTC")).alias("time")).drop("t")

    rep = stamp(pl.concat(reports)).with_columns(pl.col("radar_id").cast(pl.UInt32), pl.col("run").cast(pl.UInt32),
                                                 pl.col("local_track_id").cast(pl.UInt32))
    return rep, stamp(pl.concat(truth)), _radars()


def _errors(table: pl.DataFrame, injected: np.ndarray) -> np.ndarray:
    got = table.sort("radar_id").select("range_bias_m", "azimuth_bias_deg", "time_offset_s").to_numpy()
    return got - injected


def test_reference_recovers_hand_biases_exactly():
    rep, truth, radars = _hand_case()
    out = reg.estimate(rep, radars, ORIGIN, truth, reg.RegistrationConfig(method="reference"))
    assert out.table["method"].to_list() == ["reference"] * 3
    err = _errors(out.table, BIAS)
    assert np.all(np.abs(err[:, 0]) < 1e-3) and np.all(np.abs(err[:, 1]) < 1e-6) and np.all(np.abs(err[:, 2]) < 1e-5)
    assert out.table["n_reports"].min() > 100


def test_multi_radar_recovers_hand_biases_without_reference():
    """Radar to radar, jointly with per-target B-spline trajectories: exact up to the spline's
    approximation of the turn (sub-metre), clock offsets relative (Σδ = 0 holds here)."""
    rep, _truth, radars = _hand_case()
    out = reg.estimate(rep, radars, ORIGIN, None, reg.RegistrationConfig(method="multi", knot_s=4.0))
    err = _errors(out.table, BIAS)
    assert np.all(np.abs(err[:, 0]) < 0.5), err
    assert np.all(np.abs(err[:, 1]) < 5e-4), err
    assert np.all(np.abs(err[:, 2]) < 5e-3), err


def test_range_gain_is_recovered_when_asked():
    gain = np.array([1e-4, -2e-4, 0.0])
    rep, truth, radars = _hand_case(gain)
    out = reg.estimate(rep, radars, ORIGIN, truth, reg.RegistrationConfig(method="reference", gain=True))
    assert np.allclose(out.table.sort("radar_id")["range_gain"].to_numpy(), gain, atol=1e-7)
    assert np.all(np.abs(_errors(out.table, BIAS)[:, 0]) < 1e-2)
    plain = reg.estimate(rep, radars, ORIGIN, truth, reg.RegistrationConfig(method="reference"))
    assert np.abs(_errors(plain.table, BIAS)[0, 0]) > 0.1     # a gain left out biases the range bias


def test_apply_registration_undoes_the_biases():
    rep, truth, radars = _hand_case()
    table = pl.DataFrame({"radar_id": pl.Series([1, 2, 3], dtype=pl.UInt32), "range_bias_m": BIAS[:, 0],
                          "azimuth_bias_deg": BIAS[:, 1], "time_offset_s": BIAS[:, 2]})
    fixed = align.apply_registration(rep, table)
    assert fixed.columns == rep.columns and fixed.height == rep.height
    again = reg.estimate(fixed, radars, ORIGIN, truth, reg.RegistrationConfig(method="reference"))
    assert np.all(np.abs(_errors(again.table, np.zeros((3, 3)))) < np.array([1e-3, 1e-6, 1e-5]))


def test_apply_registration_turns_the_local_state():
    radars = _radars()
    p = np.array([30_000.0, 40_000.0, 3_000.0])
    v = np.array([100.0, 0.0, 0.0])
    r, az, el = geo.enu_to_polar(*p)
    cov = np.diag([100.0, 400.0, 900.0, 4.0, 9.0, 1.0])
    rep = pl.DataFrame({"radar_id": pl.Series([1], dtype=pl.UInt32),
                        "time": pl.Series([1_633_600_000 * US]).cast(pl.Datetime("us", "UTC")),
                        "range_m": [float(r)], "azimuth_deg": [float(az)], "est_range_m": [float(r)],
                        "est_azimuth_deg": [float(az)], **{k: [float(x)] for k, x in zip(align.STATE, [*p, *v])},
                        "est_cov": pl.Series([cov.ravel()], dtype=pl.Array(pl.Float64, 36))})
    table = pl.DataFrame({"radar_id": pl.Series([1], dtype=pl.UInt32), "range_bias_m": [50.0],
                          "azimuth_bias_deg": [1.0], "time_offset_s": [0.5]})
    out = align.apply_registration(rep, table)
    q = out.select("x_m", "y_m", "z_m").to_numpy()[0]
    r2, az2, el2 = geo.enu_to_polar(*q)
    assert r2 == pytest.approx(r - 50.0, abs=1e-6) and az2 == pytest.approx(az - 1.0, abs=1e-9)
    assert el2 == pytest.approx(el, abs=1e-9)
    vel = out.select("vx_mps", "vy_mps", "vz_mps").to_numpy()[0]
    assert np.degrees(np.arctan2(vel[0], vel[1])) == pytest.approx(89.0) and np.linalg.norm(vel) == pytest.approx(100.0)
    c = np.asarray(out["est_cov"][0]).reshape(6, 6)
    assert np.trace(c) == pytest.approx(np.trace(cov)) and not np.allclose(c, cov)
    assert (out["time"][0] - rep["time"][0]).total_seconds() == pytest.approx(-0.5)
    assert out["range_m"][0] == pytest.approx(r - 50.0) and out["azimuth_deg"][0] == pytest.approx(az - 1.0)


def test_apply_registration_needs_its_columns():
    with pytest.raises(DataError, match="azimuth_bias_deg"):
        align.apply_registration(_hand_case()[0], pl.DataFrame({"radar_id": [1], "range_bias_m": [1.0],
                                                                "time_offset_s": [0.0]}))


def test_reference_needs_truth():
    rep, _truth, radars = _hand_case()
    with pytest.raises(DataError, match="truth"):
        reg.estimate(rep, radars, ORIGIN, None, reg.RegistrationConfig(method="reference"))


@pytest.fixture(scope="module")
def terminal():
    """Terminal area (its built-in biases and clock offsets), 60 aircraft for 20 min."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=1200.0, traffic=dataclasses.replace(cfg.traffic, aircraft=60))
    return simulate(cfg)


def _z(table: pl.DataFrame, radars: pl.DataFrame) -> np.ndarray:
    t = table.join(radars, on="radar_id", suffix="_inj").sort("radar_id")
    return np.stack([(t["range_bias_m"] - t["bias_range_m"]) / t["range_bias_sigma_m"],
                     (t["azimuth_bias_deg"] - t["bias_azimuth_deg"]) / t["azimuth_bias_sigma_deg"],
                     (t["time_offset_s"] - t["time_offset_s_inj"]) / t["time_offset_sigma_s"]], 1)


def test_terminal_area_reference_within_two_sigma(terminal):
    ds = terminal
    assert (ds.radars["bias_range_m"].abs() > 0).all() and (ds.radars["time_offset_s"].abs() > 0).all()
    out = reg.estimate(ds.reports, ds.radars, ds.origin, ds.truth)
    assert out.table["method"][0] == "reference"
    z = _z(out.table, ds.radars)
    assert np.all(np.abs(z) < 2.0), z
    # σ is meaningful, not inflated: a few metres / milli-degrees / milliseconds
    assert out.table["range_bias_sigma_m"].max() < 3.0 and out.table["time_offset_sigma_s"].max() < 0.02


def test_terminal_area_multi_radar_close_to_injected(terminal):
    ds = terminal
    out = reg.estimate(ds.reports, ds.radars, ds.origin, None)
    assert out.table["method"][0] == "multi"
    z = _z(out.table, ds.radars)
    assert np.all(np.abs(z) < 3.5), z        # formal σ is ~1.4× optimistic radar to radar (docs/methods.md)
    assert abs(out.table["time_offset_s"].sum()) < 1e-6


def test_bias_step_is_detected_with_its_delay():
    cfg = load_scenario("terminal-area")
    step_t = 600.0
    cfg = dataclasses.replace(cfg, duration_s=1200.0, traffic=dataclasses.replace(cfg.traffic, aircraft=40),
                              anomalies=dataclasses.replace(cfg.anomalies, radars=("TMA-N",), bias_step_time_s=step_t,
                                                            bias_step_range_m=60.0))
    ds = simulate(cfg)
    out = reg.estimate(ds.reports, ds.radars, ds.origin, ds.truth)
    steps = reg.detect_steps(out.residuals, window=40)
    t_step = step_t - (out.t0_us - int(ds.truth["time"].min().timestamp() * US)) / US
    assert steps.filter(pl.col("radar_id") != 1).height == 0          # no false alarm on the others
    hit = steps.filter((pl.col("radar_id") == 1) & (pl.col("channel") == "range"))
    assert hit.height == 1
    delay = hit["alarm_t_s"][0] - t_step
    assert 0.0 <= delay < 120.0, delay
    assert 30.0 < hit["step"][0] < 90.0
    # without the step, nothing alarms
    clean = simulate(dataclasses.replace(cfg, anomalies=dataclasses.replace(cfg.anomalies, bias_step_time_s=None)))
    quiet = reg.estimate(clean.reports, clean.radars, clean.origin, clean.truth)
    assert reg.detect_steps(quiet.residuals, window=40).height == 0


@pytest.fixture(scope="module")
def biased(tmp_path_factory):
    """Terminal area with five times the built-in biases and clock offsets, written to disk."""
    from tertiary.io.dataset import write_dataset
    cfg = load_scenario("terminal-area")
    radars = tuple(dataclasses.replace(r, bias_range_m=5 * r.bias_range_m, bias_azimuth_deg=5 * r.bias_azimuth_deg,
                                       time_offset_s=5 * r.time_offset_s) for r in cfg.radars)
    cfg = dataclasses.replace(cfg, radars=radars, duration_s=900.0, traffic=dataclasses.replace(cfg.traffic, aircraft=30))
    out = tmp_path_factory.mktemp("biased") / "ds"
    write_dataset(simulate(cfg), out)
    return out


def test_pipeline_register_improves_fused_accuracy(biased):
    from tertiary import pipeline
    from tertiary.io.dataset import read_dataset
    ds = read_dataset(biased)
    base = pipeline.PipelineConfig(methods=("information",), filters=(), centralized=False, safety=False)

    def rmse(cfg):
        m = pipeline.process(ds, cfg).metrics
        return m.filter((pl.col("stage") == "fusion") & (pl.col("metric") == "rmse_horizontal_m")
                        & (pl.col("segment") == "all"))["value"][0]

    off = rmse(base)
    on = rmse(dataclasses.replace(base, register=True))
    assert on < 0.85 * off, (on, off)


def test_cli_register_writes_the_table_and_run_applies_it(biased, tmp_path):
    from typer.testing import CliRunner
    from tertiary.cli.commands import app
    runner = CliRunner()
    res = runner.invoke(app, ["register", str(biased), "--no-steps"])
    assert res.exit_code == 0, res.output
    table = pl.read_parquet(biased / "registration.parquet")
    assert table.columns[:8] == ["radar_id", "name", "range_bias_m", "range_bias_sigma_m", "azimuth_bias_deg",
                                 "azimuth_bias_sigma_deg", "time_offset_s", "time_offset_sigma_s"]
    assert "TMA-N" in res.output and table.height == 4
    res = runner.invoke(app, ["run", str(biased), "--out", str(tmp_path / "run"), "--register", "--no-report",
                              "--methods", "information", "--filters", "", "--no-centralized"])
    assert res.exit_code == 0, res.output
    assert "registration (given) radar 1" in res.output
    bad = runner.invoke(app, ["register", str(biased), "--method", "nonsense"])
    assert bad.exit_code == 2


def test_bordered_solve_equals_a_dense_solve_and_inverse():
    """The joint normal equations (dense bias border around a block-diagonal trajectory block)
    solved by the Schur complement equal numpy's dense solve, and S⁻¹ is the bias block of the
    dense inverse: the σ of every bias rests on it."""
    import scipy.sparse as sp
    rng = np.random.default_rng(7)
    nb, blocks = 6, [rng.normal(size=(40, 9)) for _ in range(5)]
    traj = sp.block_diag([b.T @ b + 0.1 * np.eye(9) for b in blocks])
    border = rng.normal(size=(nb, traj.shape[0])) * (rng.random((nb, traj.shape[0])) < 0.5)
    j = np.hstack([rng.normal(size=(60, nb)), rng.normal(size=(60, traj.shape[0]))])
    full = np.block([[border @ border.T + 5 * np.eye(nb), border], [border.T, traj.toarray()]]) + j.T @ j
    g = rng.normal(size=full.shape[0])
    theta, s_inv = reg._solve_bordered(sp.csr_matrix(full), g, nb)
    np.testing.assert_allclose(theta, np.linalg.solve(full, g), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s_inv, np.linalg.inv(full)[:nb, :nb], rtol=1e-9, atol=1e-14)
