"""Trackers through turns of any rate: the CT-EKF IMM (``imm_ct``, turn rate in the state) and
the symmetric turn-rate grid of ``imm_sym``, on simulated constant-turn and straight tracks.

Oracles: finite differences and the closed-form circle for the CT-EKF prediction, filterpy's
Kalman update for the model-conditioned update, a CV Kalman filter for accuracy, and the χ²
expectation of the velocity NEES (2 dof) on truth drawn from the filter's own straight-leg
model for consistency.
"""

from __future__ import annotations

import numpy as np
import pytest

from tertiary.filters import REGISTRY, make_filter
from tertiary.filters.base import concat, size, take
from tertiary.filters.imm import a_ct, imm_update, q_ct
from tertiary.filters.turn import ct_ekf_predict, ct_jacobian_omega

DT = 4.0


def _circle(omega: float, speed: float, steps: int, b: int, sigma: float, seed: int, straight_s: float = 0.0):
    """``b`` aircraft flying straight for ``straight_s`` seconds, then a constant turn at ``omega``
    (rad/s, + = left), integrated exactly; plots every DT with white noise σ (m) per axis."""
    rng = np.random.default_rng(seed)
    heading = rng.uniform(0.0, 2.0 * np.pi, b)             # of the velocity, from +X towards +Y
    pos = np.zeros((b, steps + 1, 2))
    vel = np.zeros((b, steps + 1, 2))
    vel[:, 0] = speed * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    for k in range(steps):
        w = omega if k * DT >= straight_s else 0.0
        h1 = heading + w * DT
        if w == 0.0:
            pos[:, k + 1] = pos[:, k] + vel[:, k] * DT
        else:
            pos[:, k + 1, 0] = pos[:, k, 0] + speed / w * (np.sin(h1) - np.sin(heading))
            pos[:, k + 1, 1] = pos[:, k, 1] - speed / w * (np.cos(h1) - np.cos(heading))
        heading = h1
        vel[:, k + 1] = speed * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    z = np.concatenate([pos, np.full((b, steps + 1, 1), 6000.0)], axis=2) + rng.normal(0.0, sigma, (b, steps + 1, 3))
    return pos, vel, z


def _straight_cwna(b: int, steps: int, q: float, speed: float, sigma: float, seed: int, sub: int = 20):
    """Straight legs whose truth is the CV model itself: white acceleration of PSD q (m²/s³),
    integrated in ``sub`` sub-steps per DT; plots with white noise σ."""
    rng = np.random.default_rng(seed)
    h = DT / sub
    p = np.zeros((b, 2))
    v = np.stack([np.full(b, speed), np.zeros(b)], axis=1)
    pos, vel = [p], [v]
    for _ in range(steps):
        for _ in range(sub):
            a = rng.normal(0.0, np.sqrt(q / h), (b, 2))
            p, v = p + v * h + 0.5 * a * h * h, v + a * h
        pos.append(p)
        vel.append(v)
    pos, vel = np.stack(pos, axis=1), np.stack(vel, axis=1)
    z = np.concatenate([pos, np.full((b, steps + 1, 1), 6000.0)], axis=2) + rng.normal(0.0, sigma, (b, steps + 1, 3))
    return pos, vel, z


def _run(filt, pos, vel, z, sigma, skip=25):
    """Position RMSE (m, horizontal) and mean velocity NEES (2 dof) after ``skip`` scans."""
    b = len(z)
    r = np.full((b, 3), sigma ** 2)
    st = filt.init(z[:, 0], r)
    e2, nees = [], []
    for k in range(1, z.shape[1]):
        st = filt.predict(st, np.full(b, DT))
        st, _ = filt.update(st, z[:, k], r, np.ones(b, bool))
        if k >= skip:
            out = filt.output(st)
            e2.append(((out.x[:, :2] - pos[:, k]) ** 2).sum(axis=1))
            dv = out.x[:, 3:5] - vel[:, k]
            pvv = out.cov[:, 3:5, 3:5] if out.cov is not None else out.var[:, 3:5, None] * np.eye(2)
            nees.append(np.einsum("bi,bij,bj->b", dv, np.linalg.inv(pvv), dv))
    return float(np.sqrt(np.mean(e2))), float(np.mean(nees))


# --------------------------------------------------------------------------- the CT-EKF model


@pytest.mark.parametrize("omega", [0.0, 1e-7, 0.01, -0.05, 0.2])
@pytest.mark.parametrize("dt", [0.5, 4.0, 12.0])
def test_ct_jacobian_is_the_derivative_of_the_turn_transition(omega, dt):
    """∂(A_ct(ω) x)/∂ω (11.7.2-8) against central differences, across the series/closed-form
    switch at |ωΔt| = 0.3 and at ω = 0 (where ∂x/∂ω = −vy Δt²/2, ∂y/∂ω = vx Δt²/2)."""
    x = np.array([[100.0, 210.0, -50.0, -120.0, omega]])
    h = 1e-6

    def moved(w):
        return a_ct(np.array([w]), np.array([dt]))[0] @ x[0, :4]

    fd = (moved(omega + h) - moved(omega - h)) / (2 * h)
    jac = ct_jacobian_omega(x, np.array([dt]))[0]
    np.testing.assert_allclose(jac, fd, rtol=1e-7, atol=1e-6 * np.abs(fd).max())


def test_ct_ekf_prediction_is_the_exact_turn_and_its_linearisation():
    """The mean moves along the exact circle (closed form), and P⁻ = F P Fᵀ + Q (filterpy's
    prediction with the Jacobian F) with Q the CT white-acceleration noise plus q_ω Δt on ω."""
    from filterpy.kalman import predict as fp_predict

    rng = np.random.default_rng(5)
    b = 6
    x = np.column_stack([rng.normal(0, 1e4, b), rng.normal(0, 150, b), rng.normal(0, 1e4, b),
                         rng.normal(0, 150, b), rng.uniform(-0.1, 0.1, b)])
    a = rng.normal(size=(b, 5, 5))
    p = a @ np.swapaxes(a, 1, 2) + np.eye(5)
    dt = rng.uniform(0.5, 12.0, b)
    q, q_w = 0.7, 2e-5
    xp, pp = ct_ekf_predict(x, p, dt, q, q_w)
    for i in range(b):
        w, t = x[i, 4], dt[i]
        speed, head = np.hypot(x[i, 1], x[i, 3]), np.arctan2(x[i, 3], x[i, 1])
        ex = x[i, 0] + speed / w * (np.sin(head + w * t) - np.sin(head))
        ey = x[i, 2] - speed / w * (np.cos(head + w * t) - np.cos(head))
        np.testing.assert_allclose(xp[i, [0, 2]], [ex, ey], rtol=1e-10)
        np.testing.assert_allclose(np.hypot(xp[i, 1], xp[i, 3]), speed, rtol=1e-12)
        f = np.eye(5)
        f[:4, :4] = a_ct(np.array([w]), np.array([t]))[0]
        f[:4, 4] = ct_jacobian_omega(x[i:i + 1], np.array([t]))[0]
        qq = np.zeros((5, 5))
        qq[:4, :4] = q_ct(np.array([w]), np.array([t]), q)[0]
        qq[4, 4] = q_w * t
        _, p_ref = fp_predict(x[i], p[i], f, qq)
        np.testing.assert_allclose(pp[i], p_ref, rtol=1e-10, atol=1e-9)


def test_model_conditioned_update_of_the_five_state_models_is_filterpys():
    """:func:`imm_update` on the 5-state models: each model's x⁺, P⁺ is filterpy's Kalman
    update with H = [[1,0,0,0,0],[0,0,1,0,0]] and the full 2×2 R."""
    from filterpy.kalman import update as fp_update

    rng = np.random.default_rng(8)
    b, m = 4, 2
    x = rng.normal(0, 100, (b, m, 5))
    a = rng.normal(size=(b, m, 5, 5))
    p = a @ np.swapaxes(a, -1, -2) + 10 * np.eye(5)
    z = rng.normal(0, 100, (b, 2))
    r = np.tile(np.array([[900.0, 300.0], [300.0, 400.0]]), (b, 1, 1))
    mu = np.full((b, m), 0.5)
    xu, pu, _, _ = imm_update(x, p, mu, z, r, np.ones(b, bool))
    h = np.zeros((2, 5))
    h[0, 0] = h[1, 2] = 1.0
    for i in range(b):
        for j in range(m):
            x_ref, p_ref = fp_update(x[i, j], p[i, j], z[i], r[i], h)
            np.testing.assert_allclose(xu[i, j], x_ref, rtol=1e-10, atol=1e-9)
            np.testing.assert_allclose(pu[i, j], p_ref, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------- imm_ct on turns


@pytest.mark.parametrize(("omega", "speed", "straight_s"), [
    (0.0524, 110.0, 0.0),         # 3 °/s left, a tight circle
    (-0.0524, 110.0, 200.0),      # 3 °/s right after a straight leg: the roll-in
    (0.004, 140.0, 0.0),          # a wide circle of a few mrad/s
    (-0.008, 230.0, 200.0),       # a long gentle en-route turn
])
def test_imm_ct_follows_a_turn_of_any_rate_and_stays_consistent(omega, speed, straight_s):
    """On constant-turn tracks the estimated-ω IMM beats a CV Kalman filter, its position error
    stays below the plot noise, and its velocity covariance is consistent (mean 2-dof NEES
    within [0.5, 4]; the CV filter's is tens to thousands)."""
    sigma = 60.0
    pos, vel, z = _circle(omega, speed, 150, 80, sigma, seed=1, straight_s=straight_s)
    rmse_ct, nees_ct = _run(make_filter("imm_ct"), pos, vel, z, sigma)
    rmse_cv, _ = _run(make_filter("cv"), pos, vel, z, sigma)
    assert rmse_ct < 0.9 * rmse_cv
    assert rmse_ct < sigma * np.sqrt(2.0)
    assert 0.5 < nees_ct < 4.0


@pytest.mark.parametrize("q_true", [0.1, 0.3])
def test_imm_ct_velocity_nees_on_straight_legs(q_true):
    """On straight legs with white-acceleration truth of PSD 0.1 (its CV model's) or 0.3 m²/s³
    the combined velocity covariance stays within about a factor 2 of the error either way
    (mean 2-dof NEES in [0.8, 3]): the CT-EKF model follows ω ≈ 0 instead of adding the spread
    of a fixed-rate turn."""
    pos, vel, z = _straight_cwna(200, 120, q_true, 230.0, 80.0, seed=2)
    _, nees = _run(make_filter("imm_ct"), pos, vel, z, 80.0)
    assert 0.8 < nees < 3.0


# --------------------------------------------------------------------------- imm_sym


@pytest.mark.parametrize(("speed", "sigma"), [(120.0, 50.0), (230.0, 80.0)])
def test_imm_sym_velocity_nees_on_straight_legs(speed, sigma):
    """On straight legs drawn from imm_sym's own CV model (q = 0.3 m²/s³) the combined velocity
    covariance must not be widened far beyond the truth by the spread of the turn models
    (mean 2-dof NEES ≥ 1.5; one CT(±0.045) pair with CV → turn 0.02 per scan gives 1.14–1.29):
    the conflict prediction grows P_vv by t² up to 105 s."""
    pos, vel, z = _straight_cwna(200, 120, 0.3, speed, sigma, seed=1)
    _, nees = _run(make_filter("imm_sym"), pos, vel, z, sigma)
    assert 1.5 < nees < 2.6


@pytest.mark.parametrize(("omega", "speed", "straight_s", "ratio"), [
    (0.0524, 110.0, 0.0, 0.5),        # 3 °/s: above a single ±0.045 pair
    (0.0025, 120.0, 0.0, 0.97),       # a wide circle of 2.5 mrad/s
    (0.007, 230.0, 200.0, 0.97),      # 0.4 °/s en-route turn: 1.6 m/s², far below ±0.045's 10 m/s²
    (-0.1, 80.0, 200.0, 0.5),         # 5.7 °/s
])
def test_imm_sym_turn_grid_beats_the_single_fixed_rate_pair(omega, speed, straight_s, ratio):
    """The symmetric grid follows wide circles, gentle en-route turns and tight turns better
    than one CT(±0.045) pair with the same noise (RMSE below ``ratio`` times the pair's)."""
    sigma = 60.0
    pos, vel, z = _circle(omega, speed, 150, 80, sigma, seed=3, straight_s=straight_s)
    pair = make_filter("imm_sym", omegas=(0.045, -0.045, 0.0),
                       tpm=((0.98, 0.0, 0.02), (0.0, 0.98, 0.02), (0.01, 0.01, 0.98)), mu0=(0.25, 0.25, 0.5))
    rmse_grid, _ = _run(make_filter("imm_sym"), pos, vel, z, sigma)
    rmse_pair, _ = _run(pair, pos, vel, z, sigma)
    assert rmse_grid < ratio * rmse_pair


def test_imm_sym_turn_grid_covers_both_ways_up_to_six_degrees_per_second():
    from tertiary.filters.imm import SymmetricIMMFilter

    omegas = np.asarray(SymmetricIMMFilter().core.omegas)
    assert omegas[-1] == 0.0
    turn = omegas[:-1]
    np.testing.assert_array_equal(np.sort(turn[turn > 0]), np.sort(-turn[turn < 0]))
    # neighbouring rates within ×2.5 of each other, from a few mrad/s to beyond 6 °/s
    pos = np.sort(turn[turn > 0])
    assert pos[0] <= 0.005 and np.all(pos[1:] / pos[:-1] <= 2.5) and pos[-1] >= np.radians(6.0)


# --------------------------------------------------------------------------- plumbing


def test_imm_ct_is_registered_and_keeps_the_filter_contract():
    """The contract every tracker filter keeps: registered, take/concat round trip, predict does
    not mutate, a track without a plot keeps its prediction (NaN innovation), empty batches."""
    assert "imm_ct" in REGISTRY
    f = make_filter("imm_ct")
    assert f.name == "imm_ct" and f.full_r
    rng = np.random.default_rng(3)
    b = 7
    z = rng.normal(0, 1e3, (b, 3))
    r = np.tile(np.diag([400.0, 400.0, 900.0]), (b, 1, 1))
    st = f.init(z, r)
    for _ in range(3):
        st = f.predict(st, rng.uniform(1, 5, b))
        st, _ = f.update(st, z + rng.normal(0, 20, (b, 3)), r, rng.random(b) < 0.8)
    idx = np.array([4, 0, 2])
    rest = np.setdiff1d(np.arange(b), idx)
    joined = concat(take(st, idx), take(st, rest))
    order = np.concatenate([idx, rest])
    assert size(joined) == b
    for k in st:
        np.testing.assert_array_equal(joined[k], st[k][order])
    before = {k: v.copy() for k, v in st.items()}
    pred = f.predict(st, np.full(b, 2.0))
    for k in st:
        np.testing.assert_array_equal(st[k], before[k])
    mask = np.ones(b, bool)
    mask[[1, 5]] = False
    z_nan = np.where(mask[:, None], z, np.nan)
    post, inn = f.update(pred, z_nan, r, mask)
    for k in ("x", "P", "mu", "xv", "Pv"):
        np.testing.assert_array_equal(post[k][~mask], pred[k][~mask])
        assert not np.array_equal(post[k][mask], pred[k][mask])
    assert np.all(np.isnan(inn.nis[~mask])) and np.all(np.isfinite(inn.nis[mask]))
    out = f.output(post)
    assert out.x.shape == (b, 6) and out.cov.shape == (b, 6, 6) and np.all(out.var > 0)
    np.testing.assert_allclose(out.probs.sum(axis=1), 1.0)
    np.testing.assert_allclose(out.cov, np.swapaxes(out.cov, 1, 2))
    assert np.all(np.linalg.eigvalsh(out.cov) > 0)
    # a diagonal r (B, 3) is the same plot as its full diagonal covariance
    post_d, _ = f.update(pred, z_nan, np.einsum("bii->bi", r), mask)
    for k in post:
        np.testing.assert_allclose(post_d[k], post[k])
    empty = f.init(np.zeros((0, 3)), np.zeros((0, 3)))
    empty = f.predict(empty, np.zeros(0))
    empty, inn = f.update(empty, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, bool))
    assert f.output(empty).x.shape == (0, 6) and inn.nis.shape == (0,)
