"""Seed 004 spherical EKF and seed 001 quasi-optimal filter: Jacobians vs finite differences,
filter vs filterpy, printed-vs-corrected comparisons, seed reproduction targets."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from tertiary.filters.base import make_filter
from tertiary.filters.ekf import (enu_to_measurement, phi, phi_jacobian, run_seed004, state_to_enu, wrap_pi)
from tertiary.filters import quasi_optimal as qo
from tertiary.core.geo import enu_to_polar, polar_to_enu


def _central_jacobian(f, x, h):
    cols = []
    for j in range(x.shape[-1]):
        e = np.zeros_like(x)
        e[..., j] = h[..., j]
        num = f(x + e) - f(x - e)
        cols.append(num / (2 * h[..., j]).reshape(h.shape[:-1] + (1,) * (num.ndim - h.ndim + 1)))
    return np.stack(cols, axis=-1)


def _rel_err(a, b):
    """Entrywise error relative to the largest entry of the same row (scale of the row)."""
    scale = np.maximum(np.abs(b).max(axis=-1, keepdims=True), 1e-300)
    return (np.abs(a - b) / scale).max()


def _cov_err(a, b):
    """Covariance difference in correlation units: |a − b|_ij / √(b_ii b_jj)."""
    d = np.sqrt(np.abs(np.diagonal(b, axis1=-2, axis2=-1)))
    return (np.abs(a - b) / (d[..., :, None] * d[..., None, :])).max()


def _random_states(rng, n):
    return np.column_stack([rng.uniform(2e3, 6e4, n), rng.uniform(0, 2 * np.pi, n), rng.uniform(-0.3, 0.8, n),
                            rng.uniform(50, 450, n), rng.uniform(0, 2 * np.pi, n), rng.uniform(-0.2, 0.2, n)])


# --------------------------------------------------------------------------- seed 004 EKF


def test_phi_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    x = _random_states(rng, 400)
    t = rng.uniform(0.01, 5.0, 400)
    f = phi_jacobian(x, t)
    fd = _central_jacobian(lambda y: phi(y, t), x, 1e-5 * np.maximum(np.abs(x), 1.0))
    print(f"\nF vs central differences {_rel_err(fd, f):.2e}")
    assert _rel_err(fd, f) < 1e-6
    # complex step (digest target 1): exact to rounding
    cs = np.stack([phi(x + 1j * 1e-30 * np.eye(6)[j], t).imag / 1e-30 for j in range(6)], axis=-1)
    print(f"F vs complex step {_rel_err(cs, f):.2e}")
    assert _rel_err(cs, f) < 1e-12


def test_measurement_and_output_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    x = _random_states(rng, 200)
    # covariance of the (D, α, γ) measurement from an ENU plot: J⁻¹ R J⁻ᵀ with J⁻¹ = ∂(D,α,γ)/∂(e,n,u)
    pos = np.column_stack(polar_to_enu(x[:, 0], np.degrees(x[:, 1]), np.degrees(x[:, 2])))
    r = rng.uniform(100, 2500, (200, 3))
    _, cov = enu_to_measurement(pos, r)

    def to_polar(p):
        d, a, e = enu_to_polar(p[:, 0], p[:, 1], p[:, 2])
        return np.column_stack([d, np.unwrap(np.radians(a) - x[:, 1]) + x[:, 1], np.radians(e)])

    jinv = _central_jacobian(to_polar, pos, np.full_like(pos, 1e-3))
    assert _cov_err(cov, jinv @ (r[:, :, None] * np.eye(3)) @ jinv.transpose(0, 2, 1)) < 1e-6
    # output map: X → (e, n, u, ė, ṅ, u̇), its covariance J P Jᵀ with P = I equals the FD Jacobian squared
    def out_map(y):
        p, v, _ = state_to_enu(y)
        return np.concatenate([p, v], axis=1)

    j = _central_jacobian(out_map, x, 1e-6 * np.maximum(np.abs(x), 1.0))
    _, _, c = state_to_enu(x, np.broadcast_to(np.eye(6), (200, 6, 6)))
    assert _cov_err(c, j @ j.transpose(0, 2, 1)) < 1e-6


class _PhiEKF(ExtendedKalmanFilter):
    """filterpy EKF whose state propagation is Φ (filterpy's default is F x)."""

    def predict_x(self, u=0):
        self.x = phi(self.x, self.T)


def test_ekf_equals_filterpy_step_for_step():
    rng = np.random.default_rng(2)
    b, steps = 5, 60
    filt = make_filter("ekf_spherical", q=(1.0, 1e-8, 1e-8, 0.5, 1e-4, 1e-5))
    # straight level inbound flights with ENU plot noise
    start = np.column_stack([rng.uniform(-2e4, 2e4, b), rng.uniform(1.5e4, 4e4, b), rng.uniform(1e3, 8e3, b)])
    vel = np.column_stack([rng.uniform(-50, 50, b), rng.uniform(-250, -150, b), np.zeros(b)])
    dts = rng.uniform(0.5, 4.0, (steps, b))
    tt = np.cumsum(dts, axis=0) - dts[0]
    r = np.column_stack([np.full(b, 60.0**2), np.full(b, 60.0**2), np.full(b, 120.0**2)])
    z = start + vel * tt[..., None] + np.sqrt(r) * rng.standard_normal((steps, b, 3))
    state = filt.init(z[0], r)
    refs = []
    for i in range(b):
        ekf = _PhiEKF(dim_x=6, dim_z=3)
        ekf.x, ekf.P = state["x"][i].copy(), state["P"][i].copy()
        refs.append(ekf)
    h = np.hstack([np.eye(3), np.zeros((3, 3))])

    def residual(a, c):
        d = a - c
        d[1] = wrap_pi(d[1])
        return d

    worst = 0.0
    for k in range(1, steps):
        state = filt.predict(state, dts[k])
        state, innov = filt.update(state, z[k], r, np.ones(b, bool))
        zm, rm = enu_to_measurement(z[k], r)
        for i, ekf in enumerate(refs):
            ekf.T = dts[k, i]
            ekf.F = phi_jacobian(ekf.x, ekf.T)
            ekf.Q = np.diag(filt.q) * ekf.T
            ekf.predict()
            ekf.update(zm[i], lambda x: h, lambda x: x[:3], R=rm[i], residual=residual)
            ekf.x[1] = np.mod(ekf.x[1], 2 * np.pi)
            ekf.x[4] = np.mod(ekf.x[4], 2 * np.pi)
            worst = max(worst, (np.abs(state["x"][i] - ekf.x) / np.abs(ekf.x)).max(), _cov_err(state["P"][i], ekf.P))
            np.testing.assert_allclose(state["x"][i], ekf.x, rtol=1e-9)
            assert _cov_err(state["P"][i], ekf.P) < 1e-9
            assert innov.nis[i] == pytest.approx(float(ekf.y @ ekf.SI @ ekf.y), rel=1e-9)
    print(f"\nspherical EKF vs filterpy: worst relative difference {worst:.2e}")
    assert worst < 1e-9
    out = filt.output(state)
    assert np.all(np.isfinite(out.x)) and np.all(out.var > 0)
    # the output roughly reproduces the flown horizontal velocity (the model's cos² e azimuth-rate
    # factor and the 60 m plot noise limit the agreement)
    assert np.all(np.linalg.norm(out.x[:, 3:5] - vel[:, :2], axis=1) < 0.2 * np.linalg.norm(vel[:, :2], axis=1))


def test_coasting_keeps_prediction():
    filt = make_filter("ekf_spherical")
    z = np.array([[1e3, 2e4, 3e3], [-5e3, 1e4, 2e3]])
    r = np.full((2, 3), 900.0)
    s = filt.predict(filt.init(z, r), np.array([2.0, 2.0]))
    s2, inn = filt.update(s, np.array([[1e3, 19_700.0, 3e3], [np.nan, np.nan, np.nan]]), r, np.array([True, True]))
    np.testing.assert_array_equal(s2["x"][1], s["x"][1])
    assert np.isnan(inn.nis[1]) and np.isfinite(inn.nis[0])


def test_angle_reference_sign_check():
    """Digest §3.7 row 2 / target 6: with γ = elevation, Γ = 0 (level) the test target closes
    (Ḋ < 0); the literal zenith-angle reading (γ = 90° − e, Γ = 270°) makes it recede."""
    e = np.radians(5.74)
    intended = np.array([1e4, np.radians(2.0), e, 416.67, np.pi, 0.0])
    literal = np.array([1e4, np.radians(2.0), np.pi / 2 - e, 416.67, np.pi, np.radians(270.0)])
    assert (phi(intended, 1.0) - intended)[0] < 0
    assert (phi(literal, 1.0) - literal)[0] > 0


def test_seed004_reproduction_targets():
    """Digest §3.11 targets 2–4 (N = 100 runs here; expected ≈ 104 → 6 m, ≤ 0.2°, V ≤ 5 m/s)."""
    err, _ = run_seed004(100, 1000, sigma_d=100.0, sigma_ang_deg=0.3)
    assert err[-1, 0] <= err[0, 0] / 6
    err, _ = run_seed004(100, 1000, sigma_d=10.0, sigma_ang_deg=1.0)
    assert np.degrees(err[-1, 1:3]).max() <= 0.2
    err, _ = run_seed004(100, 1000, sigma_d=50.0, sigma_ang_deg=1.0)
    assert err[-1, 3] <= 5.0
    assert np.degrees(err[-1, 4]) <= 0.7 and np.degrees(err[-1, 5]) <= 0.3


# --------------------------------------------------------------------------- seed 001 quasi-optimal


def _points(rng, n):
    return np.column_stack([rng.uniform(-3e4, 3e4, n), rng.uniform(-3e4, 3e4, n), rng.uniform(200, 1e4, n)])


def test_quasi_optimal_derivatives_match_finite_differences():
    rng = np.random.default_rng(3)
    lam = _points(rng, 300)
    radar = np.array([150.0, -80.0, 0.0])
    w = qo.jacobian(lam, radar)
    fd = _central_jacobian(lambda p: qo.primary(p, radar), lam, np.full_like(lam, 1e-2))
    print(f"\nW vs central differences {_rel_err(fd, w):.2e}")
    assert _rel_err(fd, w) < 1e-6
    hs = qo.hessians(lam, radar)                               # (B, 3 [β, ε, R], 3, 3)
    fd2 = _central_jacobian(lambda p: qo.jacobian(p, radar), lam, np.full_like(lam, 1e-2))  # (B, j, i, k)
    for j in range(3):
        print(f"Hessian {j} vs central differences {_rel_err(fd2[:, j], hs[:, j]):.2e}")
        assert _rel_err(fd2[:, j], hs[:, j]) < 1e-6
        np.testing.assert_allclose(hs[:, j], hs[:, j].transpose(0, 2, 1), rtol=1e-12, atol=1e-20)
    # the printed ε row (17) equals the correct one × 2z/ρ on x and y, and ∂ε/∂z = 0
    wp = qo.jacobian(lam, radar, printed=True)
    d = lam - radar
    rho = np.hypot(d[:, 0], d[:, 1])
    np.testing.assert_allclose(wp[:, 1, :2], w[:, 1, :2] * (2 * d[:, 2] / rho)[:, None], rtol=1e-12)
    assert np.all(wp[:, 1, 2] == 0)
    np.testing.assert_array_equal(wp[:, [0, 2]], w[:, [0, 2]])


def test_gradient_and_observed_information_are_loglikelihood_derivatives():
    """G = ∇F and J = −∇²F for F = −½ rᵀ K_q⁻¹ r (digest §1.5 steps 4–5)."""
    rng = np.random.default_rng(4)
    lam = _points(rng, 50)
    radar = np.zeros(3)
    kq = np.diag([np.radians(0.1) ** 2, np.radians(0.1) ** 2, 50.0**2])
    q_hat = qo.primary(lam + rng.normal(0, 100, lam.shape), radar)
    kqi = np.broadcast_to(np.linalg.inv(kq), (50, 3, 3))

    def loglik(p):
        r = q_hat - qo.primary(p, radar)
        r[:, 0] = wrap_pi(r[:, 0])
        return -0.5 * np.einsum("bi,bij,bj->b", r, kqi, r)

    g, j = qo.gradient_information(lam, q_hat, kqi, radar, "newton")
    h = np.full_like(lam, 1e-2)
    g_fd = _central_jacobian(lambda p: loglik(p)[:, None], lam, h)[:, 0]
    np.testing.assert_allclose(g, g_fd, rtol=1e-5, atol=1e-7 * np.abs(g).max())
    hess_fd = _central_jacobian(lambda p: qo.gradient_information(p, q_hat, kqi, radar, "newton")[0], lam, h)
    np.testing.assert_allclose(-j, hess_fd, rtol=1e-5, atol=1e-6 * np.abs(j).max())


def _straight_segment(rng, b=4, steps=60):
    start = np.column_stack([rng.uniform(5e3, 1e4, b), rng.uniform(3e3, 6e3, b), rng.uniform(800, 1200, b)])
    vel = np.column_stack([rng.uniform(-5, 5, b), rng.uniform(-5, 5, b), rng.uniform(-1, 1, b)])
    truth = start + vel * np.arange(steps)[:, None, None]
    d, a, e = enu_to_polar(truth[..., 0], truth[..., 1], truth[..., 2])
    sig = np.array([50.0, np.radians(0.1), np.radians(0.1)])
    pol = np.stack([d, np.radians(a), np.radians(e)], axis=-1) + sig * rng.standard_normal(truth.shape)
    z = np.stack(polar_to_enu(pol[..., 0], np.degrees(pol[..., 1]), np.degrees(pol[..., 2])), axis=-1)
    r = np.full((steps, b, 3), 30.0**2)
    return truth, z, r


def test_gauss_newton_quasi_optimal_equals_filterpy_ekf():
    """Digest §1.11 target 1: the corrected filter (Gauss–Newton information form) equals an
    independent EKF to ≤ 1e-9 on a straight segment; report the Newton and printed variants."""
    rng = np.random.default_rng(5)
    truth, z, r = _straight_segment(rng)
    b, steps = truth.shape[1], truth.shape[0]
    filt = make_filter("quasi_optimal", variant="gauss_newton")
    state = filt.init(z[0], r[0])
    refs = []
    for i in range(b):
        ekf = ExtendedKalmanFilter(dim_x=3, dim_z=3)
        ekf.x, ekf.P = state["x"][i].copy(), state["P"][i].copy()
        ekf.F = np.eye(3)
        refs.append(ekf)

    def residual(a, c):
        d = a - c
        d[0] = wrap_pi(d[0])
        return d

    radar = np.zeros(3)
    worst = 0.0
    for k in range(1, steps):
        state = filt.predict(state, np.ones(b))
        state, innov = filt.update(state, z[k], r[k], np.ones(b, bool))
        qm, kq = qo.enu_to_primary(z[k], r[k], radar)
        for i, ekf in enumerate(refs):
            ekf.Q = np.diag(filt.d_rate)
            ekf.predict()
            ekf.update(qm[i], lambda x: qo.jacobian(x[None], radar)[0], lambda x: qo.primary(x[None], radar)[0],
                       R=kq[i], residual=residual)
            worst = max(worst, np.abs(state["x"][i] - ekf.x).max() / np.abs(ekf.x).max(),
                        np.abs(state["P"][i] - ekf.P).max() / np.abs(ekf.P).max())
            assert innov.nis[i] == pytest.approx(float(ekf.y @ ekf.SI @ ekf.y), rel=1e-9)
    print(f"\nquasi-optimal (Gauss-Newton) vs filterpy EKF: worst relative difference {worst:.2e}")
    assert worst < 1e-9, worst


def test_newton_and_printed_variants_vs_corrected():
    """Newton ≈ Gauss–Newton (second order in the residual); the printed derivatives are far off."""
    rng = np.random.default_rng(6)
    truth, z, r = _straight_segment(rng, b=200, steps=120)
    res = {}
    for variant in ("gauss_newton", "newton", "printed"):
        filt = make_filter("quasi_optimal", variant=variant)
        s = filt.init(z[0], r[0])
        est = [s["x"]]
        for k in range(1, len(z)):
            s, _ = filt.update(filt.predict(s, np.ones(200)), z[k], r[k], np.ones(200, bool))
            est.append(s["x"])
        res[variant] = np.array(est)
    rmse = {v: np.sqrt(np.mean((e - truth) ** 2, axis=(0, 1))) for v, e in res.items()}
    diff_newton = np.abs(res["newton"] - res["gauss_newton"]).max()
    print(f"\nRMSE (x, y, z): {rmse}; max |Newton - Gauss-Newton| = {diff_newton:.3g} m; "
          f"max |printed - Gauss-Newton| = {np.abs(res['printed'] - res['gauss_newton']).max():.3g} m")
    assert diff_newton < 0.05 * rmse["gauss_newton"].min()
    np.testing.assert_allclose(rmse["newton"], rmse["gauss_newton"], rtol=0.05)
    # printed (17) + transposed gradient (26)–(29): much larger errors
    assert np.linalg.norm(rmse["printed"]) > 3 * np.linalg.norm(rmse["gauss_newton"])


def test_printed_sign_pairing_gives_non_pd_covariance():
    """Digest §1.7 row 6 / §1.11 target 2: K_ps = [K_э⁻¹ − H_λ]⁻¹ with the printed H_λ = −∇²F
    subtracts information; the corrected pairing stays positive definite."""
    lam = np.array([[8000.0, 5000.0, 1000.0]])
    radar = np.zeros(3)
    kq = np.diag([np.radians(0.1) ** 2, np.radians(0.1) ** 2, 50.0**2])[None]
    k_pred = np.diag([1e4, 1e4, 1e4])[None]        # prior weaker than the plot
    q_hat = qo.primary(lam, radar)
    _, j = qo.gradient_information(lam, q_hat, np.linalg.inv(kq), radar, "newton")
    k_ok = np.linalg.inv(np.linalg.inv(k_pred) + j)
    k_bad = np.linalg.inv(np.linalg.inv(k_pred) - j)
    assert np.linalg.eigvalsh(k_ok).min() > 0
    assert np.linalg.eigvalsh(k_bad).min() < 0
