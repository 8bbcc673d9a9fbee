"""Chapter 3 kinematics and range channels (tertiary.filters.kinematic_los / kinematic) and the
Mode S EHS simulator (tertiary.simulate.ehs), against brute-force numerics and independent
matrix-form references."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from tertiary.core.errors import DataError
from tertiary.filters import kinematic_los as los
from tertiary.filters.kinematic import (AuxFilter, KinematicDynamicRangeChannel, KinematicRangeChannel, channel_inputs, make_range_channel)
from tertiary.filters.singer import singer_phi, singer_q
from tertiary.simulate.ehs import RESOLUTION, EhsConfig, ehs_parameters, ehs_table, ehs_truth, quantise
from tertiary.simulate.traffic import big_box
from tertiary.simulate.trajectory import Trajectories, integrate_commands

G = los.G0
RADAR = np.array([1500.0, -800.0, 40.0])          # ENU site, off the origin and raised


def spiral(t):
    """Accelerating climbing right turn (ENU): analytic position, velocity, acceleration."""
    w, v0, vdot, climb = 0.05, 150.0, 2.0, 8.0
    s = v0 * t + 0.5 * vdot * t * t                 # path length along the horizontal
    # heading ψ = w t (clockwise from north); horizontal speed v0 + vdot t
    psi = w * t
    vh = v0 + vdot * t
    # position by exact integration is not needed: use a helix-like curve with known derivatives
    pos = np.stack([6000 + 3000 * np.sin(psi) + 0.01 * s, 4000 + 3000 * np.cos(psi), 800 + climb * t + 0.3 * t * t], -1)
    vel = np.stack([3000 * w * np.cos(psi) + 0.01 * vh, -3000 * w * np.sin(psi), climb + 0.6 * t], -1)
    acc = np.stack([-3000 * w * w * np.sin(psi) + 0.01 * vdot, -3000 * w * w * np.cos(psi), np.full_like(t, 0.6)], -1)
    return pos, vel, acc


def _num(f, t, h=1e-3):
    return (f(t + h) - f(t - h)) / (2 * h)


# ----------------------------------------------------------------------------- frames

def test_table_3_1_columns_orthonormal_and_first_is_velocity():
    th, ph = np.radians([7.0, -20.0, 45.0]), np.radians([30.0, 170.0, -95.0])
    m = los.trajectory_matrix(th, ph)
    assert np.allclose(np.einsum("...ji,...jk->...ik", m, m), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(m), 1.0)
    v = np.stack([np.cos(th) * np.cos(ph), np.sin(th), -np.cos(th) * np.sin(ph)], -1)   # (3.8) / V
    assert np.allclose(m[..., :, 0], v)


def test_table_3_2_erratum_printed_entry_only_and_not_orthonormal():
    eb, eg = np.radians(12.0), np.radians(-63.0)
    good, bad = los.beam_matrix(eb, eg), los.beam_matrix(eb, eg, "printed")
    assert np.allclose(good.T @ good, np.eye(3), atol=1e-12)
    assert not np.allclose(bad.T @ bad, np.eye(3), atol=1e-3)
    diff = np.argwhere(~np.isclose(good, bad))
    assert diff.tolist() == [[2, 0]]                      # (OZ_г, OX_л) only
    assert bad[2, 0] == pytest.approx(-np.sin(eb) * np.cos(eg))
    assert good[2, 0] == pytest.approx(-np.cos(eb) * np.sin(eg))
    # e_xL is the unit LOS vector of a target at those angles
    r = los.enu_to_normal(los.normal_to_enu(good[:, 0]) * 9000.0)
    d, b, g = los.los_angles(r)
    assert (d, b, g) == pytest.approx((9000.0, eb, eg))


def test_los_and_flight_rates_match_numeric_differentiation():
    t = np.linspace(0.0, 60.0, 13)
    rel = lambda tt: los.enu_to_normal(spiral(tt)[0] - RADAR)  # noqa: E731
    pos, vel, acc = spiral(t)
    r, v, a = los.enu_to_normal(pos - RADAR), los.enu_to_normal(vel), los.enu_to_normal(acc)
    d_dot, w_b, w_g = los.los_rates(r, v)
    assert np.allclose(d_dot, _num(lambda tt: los.los_angles(rel(tt))[0], t), atol=1e-6)
    assert np.allclose(w_b, _num(lambda tt: los.los_angles(rel(tt))[1], t), atol=1e-9)
    assert np.allclose(w_g, _num(lambda tt: los.los_angles(rel(tt))[2], t), atol=1e-9)
    v_dot, w_t, w_p = los.flight_rates(v, a)
    vn = lambda tt: los.enu_to_normal(spiral(tt)[1])  # noqa: E731
    for got, i in ((v_dot, 0), (w_t, 1), (w_p, 2)):
        assert np.allclose(got, _num(lambda tt: los.flight_angles(vn(tt))[i], t), atol=1e-7)
    # (3.5): the acceleration expressed in the trajectory frame (Table 3.1 transposed)
    speed, th, ph = los.flight_angles(v)
    a_t = np.einsum("...ji,...j->...i", los.trajectory_matrix(th, ph), a)
    assert np.allclose(los.trajectory_acceleration(speed, v_dot, w_t, w_p, th), a_t, atol=1e-9)
    # (3.9): V_L = Ḋ
    _, eb, eg = los.los_angles(r)
    assert np.allclose(los.los_velocity(speed, th, ph, eb, eg), d_dot, atol=1e-9)


def test_los_acceleration_3_11_equals_numeric_second_derivative_of_range():
    t = np.linspace(1.0, 50.0, 11)
    rng_t = lambda tt: np.linalg.norm(spiral(tt)[0] - RADAR, axis=-1)  # noqa: E731
    h = 1e-2
    d_dd = (rng_t(t + h) - 2 * rng_t(t) + rng_t(t - h)) / h**2
    pos, vel, acc = spiral(t)
    r, v, a = los.enu_to_normal(pos - RADAR), los.enu_to_normal(vel), los.enu_to_normal(acc)
    speed, th, ph = los.flight_angles(v)
    v_dot, w_t, w_p = los.flight_rates(v, a)
    _, eb, eg = los.los_angles(r)
    _, w_b, w_g = los.los_rates(r, v)
    got = los.los_acceleration(speed, th, w_t, ph, w_p, eb, w_b, eg, w_g, v_dot=v_dot)
    assert np.allclose(got, d_dd, atol=2e-4)
    assert np.allclose(los.range_acceleration_truth(r, v, a), d_dd, atol=2e-4)
    # (3.11) proper (V̇ = 0) misses exactly the along-track term V̇ c_x
    cx = los.los_cosines(th, ph, eb, eg)[0]
    assert np.allclose(got - los.los_acceleration(speed, th, w_t, ph, w_p, eb, w_b, eg, w_g), v_dot * cx)
    # printed (3.11): the third term loses its factor V, nothing else changes
    third = np.cos(th) * np.cos(eb) * np.sin(ph - eg) * (w_g - w_p)
    printed = los.los_acceleration(speed, th, w_t, ph, w_p, eb, w_b, eg, w_g, variant="printed")
    assert np.allclose(printed - los.los_acceleration(speed, th, w_t, ph, w_p, eb, w_b, eg, w_g), (1 - speed) * third)


def test_los_load_factor_is_projection_and_corrected_3_62_is_range_acceleration():
    rng = np.random.default_rng(3)
    n = 20
    th, ph, gm = rng.uniform(-0.3, 0.3, n), rng.uniform(-3, 3, n), rng.uniform(-1.1, 1.1, n)
    eb, eg = rng.uniform(0.0, 0.4, n), rng.uniform(-3, 3, n)
    nx, ny, nz = rng.uniform(-0.2, 0.2, n), rng.uniform(0.5, 2.5, n), rng.uniform(-0.1, 0.1, n)
    n_norm = np.einsum("...ij,...j->...i", los.trajectory_matrix(th, ph), los.trajectory_load_factor(nx, ny, nz, gm))
    e_l = los.beam_matrix(eb, eg)[..., :, 0]
    assert np.allclose(los.los_load_factor(nx, ny, nz, gm, th, ph, eb, eg), np.sum(n_norm * e_l, -1), atol=1e-12)
    # a = g n − g ŷ with any velocity: the corrected (3.62) is the exact D̈
    speed = rng.uniform(80, 300, n)
    v = speed[:, None] * los.trajectory_matrix(th, ph)[..., :, 0]
    a = G * n_norm - np.array([0.0, G, 0.0])
    d = rng.uniform(3e3, 2e4, n)
    r = d[:, None] * e_l
    v_l = np.sum(v * e_l, -1)
    nxl = los.los_load_factor(nx, ny, nz, gm, th, ph, eb, eg)
    corrected = los.range_acceleration(nxl, eb, speed, v_l, d, "corrected")
    assert np.allclose(corrected, los.range_acceleration_truth(r, v, a), atol=1e-9)
    printed = los.range_acceleration(nxl, eb, speed, v_l, d, "printed")
    assert np.allclose(printed - corrected, G * np.sin(eb) - (speed**2 - v_l**2) / d, atol=1e-12)


# ----------------------------------------------------------------------------- channels

def _inputs(b: int, rng: np.random.Generator, zero_load: bool = False) -> dict[str, np.ndarray]:
    z = {"range_m": rng.uniform(5e3, 9e3, b), "eps_b": rng.uniform(0.02, 0.2, b), "eps_g": rng.uniform(-3, 3, b),
         "speed": rng.uniform(90, 300, b), "theta": rng.uniform(-0.05, 0.05, b), "phi": rng.uniform(-3, 3, b),
         "gamma": rng.uniform(-0.5, 0.5, b), "n_x": rng.uniform(-0.05, 0.05, b), "n_y": rng.uniform(0.9, 1.5, b),
         "n_z": rng.uniform(-0.02, 0.02, b)}
    if zero_load:
        z["n_x"], z["n_y"], z["n_z"] = np.zeros(b), np.zeros(b), np.zeros(b)
    return z


def _kf(x, p, z, r, phi, q, b_u=None):
    """Textbook matrix Kalman step (2.6)–(2.14) with an optional known input."""
    x = phi @ x + (0 if b_u is None else b_u)
    p = phi @ p @ phi.T + q
    h = np.zeros(len(x))
    h[0] = 1.0
    s = h @ p @ h + r
    k = p @ h / s
    nu = z - x[0]
    return x + k * nu, p - np.outer(k, h @ p)


def _unpack3(v):
    return np.array([[v[0], v[1], v[2]], [v[1], v[3], v[4]], [v[2], v[4], v[5]]])


def test_kinematic_step_matches_matrix_form_reference():
    rng = np.random.default_rng(1)
    ch = KinematicRangeChannel(sigma_range_m=40.0, sigma_u=0.7)
    z0, z1 = _inputs(4, rng), _inputs(4, rng)
    tau = np.array([0.1, 0.5, 1.0, 4.0])
    state = ch.init(z0)
    state["ax"][..., 1] = rng.normal(0, 0.01, state["ax"].shape[:2])     # non-zero rates
    state["x"][:, 1:] = rng.normal(0, 5, (4, 2))
    state["u"] = ch.acceleration(state)
    new, nu, s, gain = ch.step(state, z1, tau)
    for i in range(4):
        phi_b = np.array([[1, tau[i], tau[i] ** 2 / 2], [0, 1, tau[i]], [0, 0, 0]])      # (3.27)
        x, p = _kf(state["x"][i], _unpack3(state["P"][i]), z1["range_m"][i], 40.0**2, phi_b,
                   np.diag([0, 0, 0.49]), np.array([0, 0, state["u"][i]]))
        assert np.allclose(new["x"][i], x) and np.allclose(_unpack3(new["P"][i]), p)
        assert gain[i, 2] == 0.0 and new["x"][i, 2] == pytest.approx(state["u"][i])   # a⁺ = u(k): K₃ = 0
        for j, a in enumerate(ch.aux):
            f = 1 - a.alpha * tau[i]
            pa = state["aP"][i, j]
            zz = z1[a.key][i]
            if a.angle:      # the reference wraps the measurement next to the prediction
                pred = state["ax"][i, j, 0] + tau[i] * state["ax"][i, j, 1]
                zz = pred + los.wrap_pi(zz - pred)
            xa, paa = _kf(state["ax"][i, j], np.array([[pa[0], pa[1]], [pa[1], pa[2]]]), zz, a.sigma_meas**2,
                          np.array([[1, tau[i]], [0, f]]),
                          np.diag([0, a.sigma_rate**2 * (2 * a.alpha * tau[i] - (a.alpha * tau[i]) ** 2)]))
            assert np.allclose(new["ax"][i, j], xa) and np.allclose(new["aP"][i, j], [paa[0, 0], paa[0, 1], paa[1, 1]])
    assert np.allclose(new["u"], ch.acceleration(new))


def test_zero_input_channel_reduces_to_printed_singer_with_unit_alpha_tau():
    """With u ≡ 0 (all load factors measured 0, printed (3.62)) the base filter is the printed
    Singer filter (2.49)–(2.63) with α_ф τ = 1 (Φ₃₃ = 0) and σ_m = √D_a."""
    rng = np.random.default_rng(2)
    tau, sig_u = 0.5, 1.3
    ch = KinematicDynamicRangeChannel(variant="printed", sigma_range_m=30.0, sigma_u=sig_u)
    state = ch.init(_inputs(3, rng, zero_load=True))
    x = state["x"].copy()
    p = np.stack([_unpack3(v) for v in state["P"]])
    phi, q = singer_phi(tau, 1 / tau), singer_q(tau, 1 / tau, sig_u)
    for _ in range(6):
        z = _inputs(3, rng, zero_load=True)
        state, *_ = ch.step(state, z, tau)
        assert np.all(state["u"] == 0.0)
        for i in range(3):
            x[i], p[i] = _kf(x[i], p[i], z["range_m"][i], 30.0**2, phi, q)
    assert np.allclose(state["x"], x)
    assert np.allclose(np.stack([_unpack3(v) for v in state["P"]]), p)


def test_printed_and_corrected_3_62_differ_exactly_by_gravity_and_los_rotation():
    rng = np.random.default_rng(4)
    z0, z1 = _inputs(5, rng), _inputs(5, rng)
    pr, co = (KinematicDynamicRangeChannel(variant=v) for v in ("printed", "corrected"))
    s_pr, s_co = pr.init(z0), co.init(z0)
    assert np.allclose(s_pr["ax"], s_co["ax"])
    s_pr, *_ = pr.step(s_pr, z1, 1.0)
    s_co["u"] = s_pr["u"] * 0 + co.acceleration(s_pr)     # same state, the other (3.62)
    e = lambda k: co.aux_estimate(s_pr, k)  # noqa: E731
    d, v_l = s_pr["x"][:, 0], s_pr["x"][:, 1]
    expected = G * np.sin(e("eps_b")) - (e("speed") ** 2 - v_l**2) / d
    assert np.allclose(s_pr["u"] - s_co["u"], expected, atol=1e-12)
    with pytest.raises(ValueError, match="variant"):
        KinematicDynamicRangeChannel(variant="exact")
    assert isinstance(make_range_channel("kinematic_dynamic", variant="printed"), KinematicDynamicRangeChannel)
    with pytest.raises(ValueError, match="unknown range channel"):
        make_range_channel("singer2")


def test_missing_measurement_coasts_and_angle_innovation_wraps():
    rng = np.random.default_rng(5)
    ch = KinematicRangeChannel(aux=(AuxFilter("eps_g", 0.0, 0.01, 0.01, angle=True),
                                    AuxFilter("speed", 0.1, 1.0, 1.0), AuxFilter("theta", 0.1, 0.01, 0.01),
                                    AuxFilter("phi", 0.1, 0.01, 0.01, angle=True), AuxFilter("eps_b", 0.1, 0.01, 0.01)))
    z0 = _inputs(2, rng)
    z0["eps_g"] = np.array([np.pi - 0.001, 0.3])
    state = ch.init(z0)
    z1 = {k: v.copy() for k, v in z0.items()}
    z1["eps_g"] = np.array([-np.pi + 0.001, 0.3])      # 0.002 rad across the ±π cut
    z1["range_m"] = np.array([np.nan, z0["range_m"][1]])
    new, nu, s, _ = ch.step(state, z1, 1.0)
    assert np.isnan(nu[0]) and np.isfinite(nu[1])
    assert abs(new["ax"][0, 0, 0] - state["ax"][0, 0, 0]) < 0.002          # moved across the cut, not by 2π
    assert new["x"][0, 0] == pytest.approx(state["x"][0, 0] + state["x"][0, 1] + 0.5 * state["x"][0, 2])


def test_noise_free_ehs_inputs_give_exact_range_acceleration_in_a_turn():
    """Signs end to end: a right turn's EHS truth (roll > 0, track increasing) through
    channel_inputs and the corrected (3.62) equals the true D̈."""
    dt = 0.5
    turn = np.concatenate([np.zeros(10), np.full(60, 3.0)])[None, :]
    pos, vel = integrate_commands(np.array([[5000.0, -3000.0, 900.0]]), np.array([20.0]), np.full_like(turn, 150.0),
                                  turn, np.zeros_like(turn), dt)
    traj = Trajectories(dt=dt, pos=pos, vel=vel, active=np.ones(pos.shape[:2], bool),
                        segment=np.zeros(pos.shape[:2], np.int8), truth_id=np.array([0]))
    t = np.arange(20, 60) * dt
    ehs, ok = ehs_truth(traj, np.zeros(len(t), int), t)
    assert ok.all() and np.all(ehs["roll_deg"] > 20)
    p, v, _ = traj.state_at(np.zeros(len(t), int), t)
    e, n, u = p.T
    d = np.linalg.norm(p, axis=1)
    z = channel_inputs(d, np.degrees(np.arctan2(e, n)), np.degrees(np.arcsin(u / d)), ehs["ground_speed_mps"],
                       ehs["true_track_deg"], ehs["vertical_rate_mps"], ehs["roll_deg"])
    nxl = los.los_load_factor(z["n_x"], z["n_y"], z["n_z"], z["gamma"], z["theta"], z["phi"], z["eps_b"], z["eps_g"])
    r_n, v_n = los.enu_to_normal(p), los.enu_to_normal(v)
    w = np.radians(3.0)
    a_n = los.enu_to_normal(np.stack([w * v[:, 1], -w * v[:, 0], 0 * v[:, 0]], 1))
    v_l = los.los_rates(r_n, v_n)[0]
    got = los.range_acceleration(nxl, z["eps_b"], z["speed"], v_l, d, "corrected")
    assert np.allclose(got, los.range_acceleration_truth(r_n, v_n, a_n), atol=2e-3)
    # (3.11) with the true rates gives the same
    _, w_b, w_g = los.los_rates(r_n, v_n)
    _, _, w_p = los.flight_rates(v_n, a_n)
    kin = los.los_acceleration(z["speed"], z["theta"], 0.0, z["phi"], w_p, z["eps_b"], w_b, z["eps_g"], w_g)
    assert np.allclose(kin, got, atol=2e-3)


# ----------------------------------------------------------------------------- EHS

def test_quantise_to_bds_resolutions():
    assert quantise([100.0], "ground_speed_mps")[0] == pytest.approx(97 * 2 * 1852 / 3600)   # 194 kt → 2-kt LSB
    assert quantise([30.0], "roll_deg")[0] == pytest.approx(171 * 45 / 256)
    assert quantise([120.0], "roll_deg")[0] == 90.0 and quantise([-40.0], "track_rate_dps")[0] == -16.0
    assert quantise([179.95], "true_track_deg")[0] == pytest.approx(-180.0)                  # wraps
    assert quantise([1.0], "vertical_rate_mps")[0] == pytest.approx(6 * 32 * 0.3048 / 60)
    for col, (lsb, lo, hi) in RESOLUTION.items():
        v = np.random.default_rng(0).uniform(lo / 2, hi / 2, 1000)
        q = quantise(v, col)
        assert np.allclose(q / lsb, np.round(q / lsb), atol=1e-9)
        assert np.max(np.abs(q - v)) <= lsb / 2 + 1e-9


def test_ehs_parameters_on_big_box_turn_and_noise_statistics():
    traj = big_box(1.0)
    t = np.full(4000, 200.0)                 # inside the first turn (straight 180 s, turn 180–210 s)
    clean, _ = ehs_parameters(traj, np.zeros(1, int), t[:1], np.random.default_rng(0),
                              EhsConfig(0, 0, 0, 0, 0))
    v, w = 300 / 3.6, np.radians(-3.0)
    assert clean["roll_deg"][0] == pytest.approx(np.degrees(np.arctan(v * w / G)), abs=45 / 512)
    assert clean["track_rate_dps"][0] == pytest.approx(-3.0, abs=1 / 64)
    assert clean["ground_speed_mps"][0] == pytest.approx(v, abs=1852 / 3600)
    noisy, ok = ehs_parameters(traj, np.zeros(len(t), int), t, np.random.default_rng(1))
    assert ok.all()
    true, _ = ehs_truth(traj, np.zeros(len(t), int), t)
    cfg = EhsConfig()
    for col in ("roll_deg", "ground_speed_mps"):
        err = noisy[col] - true[col]
        expect = np.hypot(getattr(cfg, col), RESOLUTION[col][0] / np.sqrt(12))
        assert np.std(err) == pytest.approx(expect, rel=0.08) and abs(np.mean(err)) < 0.1 * expect


def test_ehs_table_keys_mode_s_only_and_no_truth():
    traj = big_box(1.0)
    reports = pl.DataFrame({"run": pl.Series([0, 0, 0], dtype=pl.UInt32), "radar_id": pl.Series([1, 1, 1], dtype=pl.UInt32),
                            "local_track_id": pl.Series([3, 3, 9], dtype=pl.UInt32),
                            "time": pl.Series([traj.epoch] * 3).dt.offset_by("10s"),
                            "mode_s": ["508c01", None, None], "truth_id": pl.Series([0, 0, None], dtype=pl.Int64)})
    tab = ehs_table(reports, traj, np.random.default_rng(0))
    assert tab.height == 1 and "truth_id" not in tab.columns
    assert tab.columns[:5] == ["run", "radar_id", "local_track_id", "time", "mode_s"]
    assert tab["ground_speed_mps"][0] == pytest.approx(300 / 3.6, abs=3.0)
    with pytest.raises(DataError, match="truth_id"):
        ehs_table(reports.drop("truth_id"), traj, np.random.default_rng(0))
