"""Linear filter family (tertiary.filters.linear, .manoeuvring): filterpy equality, closed forms, adaptivity,
two-model weights, state plumbing, speed."""

from __future__ import annotations

import time

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from tertiary.filters.base import REGISTRY, concat, make_filter, size, take
from tertiary.filters.axes import full_covariance
from tertiary.filters.linear import (AlphaBetaFilter, AlphaBetaGammaFilter, CVFilter, abg_gamma, kalata_alpha_beta, kalata_beta, steady_state_abg)
from tertiary.filters.manoeuvring import AdaptiveSingerFilter, SingerFilter, TwoModelFilter, two_model_weights
from tertiary.filters.singer import singer_phi, singer_q

NAMES = ["cv", "alpha_beta", "alpha_beta_gamma", "singer", "adaptive", "two_model"]


def _scenario(seed: int, b: int = 40, steps: int = 60, p_detect: float = 0.7):
    """Irregular dt, random-walk measurements, per-plot r, missed plots."""
    rng = np.random.default_rng(seed)
    dt = rng.uniform(0.5, 12.0, (steps, b))
    z = rng.normal(0, 5e3, (b, 3)) + np.cumsum(rng.normal(0, 150.0, (steps, b, 3)), axis=0)
    r = rng.uniform(20.0, 120.0, (steps, b, 3)) ** 2
    mask = rng.random((steps, b)) < p_detect
    mask[0] = True
    return dt, z, r, mask


def _run(f, dt, z, r, mask):
    """Our filter over the scenario; per step the posterior state and the innovation."""
    st = f.init(z[0], r[0])
    states, innovs = [st], [None]
    for k in range(1, len(dt)):
        st = f.predict(st, dt[k])
        st, inn = f.update(st, z[k], r[k], mask[k])
        states.append(st)
        innovs.append(inn)
    return states, innovs


def _filterpy_matrices(f, tau: float, axis: int):
    """(F, Q) of our filter's model for one axis, built independently of linear.py."""
    if isinstance(f, CVFilter):
        q = np.broadcast_to(np.asarray(f.q, float), (3,))[axis]
        F = np.array([[1.0, tau], [0.0, 1.0]])
        if f.noise == "printed":
            return F, np.diag([q, 0.0])
        return F, q * np.array([[tau**3 / 3, tau**2 / 2], [tau**2 / 2, tau]])
    sm = np.broadcast_to(np.asarray(f.sigma_m, float), (3,))[axis]
    return singer_phi(tau, f.alpha, f.variant), singer_q(tau, f.alpha, sm, f.variant)


FILTERPY_CASES = [
    CVFilter(),
    CVFilter(q=(0.5, 2.0, 0.1)),
    CVFilter(q=400.0, noise="printed"),
    SingerFilter(variant="printed"),
    SingerFilter(variant="exact", sigma_m=(3.0, 2.0, 0.5), alpha=0.1),
    AdaptiveSingerFilter(mode="none"),
    AdaptiveSingerFilter(mode="fading", lambda_max=1.0),          # λ ≡ 1, nominal R
    AdaptiveSingerFilter(mode="r_window", window=1000),           # never N innovations: nominal R
    AdaptiveSingerFilter(mode="hybrid", window=1000, lambda_max=1.0, variant="exact"),
]


FILTERPY_IDS = ["cv", "cv-per-axis-q", "cv-printed-Q", "singer-printed", "singer-exact-per-axis",
                "adaptive-none", "adaptive-fading-lambda1", "adaptive-r_window-unfilled", "adaptive-hybrid-off"]


@pytest.mark.parametrize("f", FILTERPY_CASES, ids=FILTERPY_IDS)
def test_equals_filterpy_step_by_step(f):
    """Per axis, x, P, ν, S and NIS equal filterpy KalmanFilter with the same F, Q, H, R, x0, P0
    on irregular dt with missed plots (mask False → predict only)."""
    dt, z, r, mask = _scenario(7)
    states, innovs = _run(f, dt, z, r, mask)
    n = states[0]["x"].shape[-1]
    for j in range(0, dt.shape[1], 3):
        for axis in range(3):
            kf = KalmanFilter(dim_x=n, dim_z=1)
            kf.x = np.zeros(n)
            kf.x[0] = z[0, j, axis]
            p0 = np.zeros((n, n))
            p0[0, 0], p0[1, 1] = r[0, j, axis], f.v0_sigma**2
            if n == 3:
                p0[2, 2] = np.broadcast_to(np.asarray(f.sigma_m, float), (3,))[axis] ** 2
            kf.P = p0
            kf.H = np.eye(1, n)
            for k in range(1, len(dt)):
                kf.F, kf.Q = _filterpy_matrices(f, dt[k, j], axis)
                kf.predict()
                inn = innovs[k]
                if mask[k, j]:
                    kf.R = np.array([[r[k, j, axis]]])
                    kf.update(np.array([z[k, j, axis]]))
                    np.testing.assert_allclose(inn.nu[j, axis], kf.y[0], rtol=1e-9, atol=1e-9)
                    np.testing.assert_allclose(inn.s[j, axis], kf.S[0, 0], rtol=1e-9)
                else:
                    assert np.isnan(inn.nu[j, axis]) and np.isnan(inn.s[j, axis]) and np.isnan(inn.nis[j])
                st = states[k]
                np.testing.assert_allclose(st["x"][j, axis], kf.x, rtol=1e-9, atol=1e-6)
                np.testing.assert_allclose(full_covariance(st["P"][j, axis]), kf.P, rtol=1e-9, atol=1e-6)
    ok = mask[1:]
    nis = np.array([i.nis for i in innovs[1:]])
    manual = np.array([np.sum(i.nu**2 / i.s, axis=1) for i in innovs[1:]])
    np.testing.assert_allclose(nis[ok], manual[ok], rtol=1e-12)


def test_singer_printed_long_coast_guard():
    """α_фτ > 1: the printed Φ₃₃ = 1 − α_фτ would go negative; the guard forgets the
    acceleration (Φ₃₃ = 0) and keeps Var(a) = σ_m² stationary."""
    f = SingerFilter(alpha=0.1, sigma_m=2.0)
    st = f.init(np.zeros((1, 3)), np.ones((1, 3)))
    st["x"][..., 2] = 5.0
    st2 = f.predict(st, np.array([30.0]))
    assert np.all(st2["x"][..., 2] == 0.0)
    assert np.allclose(st2["P"][..., 5], 4.0)
    assert np.all(np.linalg.eigvalsh(full_covariance(st2["P"])) > 0)


# ----------------------------------------------------------------------------- α-β, α-β-γ

def _noise_free(f, truth_p, tau):
    """Run on exact positions with constant τ; returns (x⁺, x⁻) histories (steps, 3, n)."""
    b = 1
    r = np.full((b, 3), 50.0**2)
    st = f.init(truth_p[0][None], r)
    post, prior = [st["x"][0].copy()], [st["x"][0].copy()]
    for k in range(1, len(truth_p)):
        st = f.predict(st, np.full(b, tau))
        prior.append(st["x"][0].copy())
        st, _ = f.update(st, truth_p[k][None], r, np.ones(b, bool))
        post.append(st["x"][0].copy())
    return np.array(post), np.array(prior)


@pytest.mark.parametrize("alpha", [0.2, 0.5, 0.8])
def test_alpha_beta_tracks_cv_exactly_and_lags_under_acceleration(alpha):
    """Noise-free: CV is tracked exactly. Under constant acceleration a, with errors
    e = estimate − truth: e⁻ₚ(k+1) = e⁺ₚ + τe⁺ᵥ − aτ²/2, e⁻ᵥ(k+1) = e⁺ᵥ − aτ, e⁺ₚ = (1 − α)e⁻ₚ,
    e⁺ᵥ = e⁻ᵥ − (β/τ)e⁻ₚ; the fixed point is e⁻ₚ = −aτ²/β, e⁺ₚ = −(1 − α)aτ²/β,
    e⁺ᵥ = aτ(1/2 − α/β)."""
    f = AlphaBetaFilter(alpha=alpha)
    beta = kalata_beta(alpha)
    tau, steps = 2.0, 400
    t = np.arange(steps) * tau
    v = np.array([200.0, -120.0, 3.0])
    post, _ = _noise_free(f, t[:, None] * v, tau)
    np.testing.assert_allclose(post[-1, :, 0], t[-1] * v, atol=1e-6)
    np.testing.assert_allclose(post[-1, :, 1], v, atol=1e-6)
    # constant acceleration: steady-state lags
    a = np.array([3.0, -1.5, 0.2])
    post, prior = _noise_free(f, t[:, None] * v + 0.5 * t[:, None] ** 2 * a, tau)
    truth_p = t[-1] * v + 0.5 * t[-1] ** 2 * a
    truth_v = v + a * t[-1]
    np.testing.assert_allclose(prior[-1, :, 0] - truth_p, -a * tau**2 / beta, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(post[-1, :, 0] - truth_p, -(1 - alpha) * a * tau**2 / beta, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(post[-1, :, 1] - truth_v, a * tau * (0.5 - alpha / beta), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("gains", ["fixed", "steady_state"])
def test_alpha_beta_gamma_tracks_ca_exactly_and_lags_under_jerk(gains):
    f = AlphaBetaGammaFilter(alpha=0.6, gains=gains, sigma_j=0.3)
    tau, steps = 1.0, 600
    t = np.arange(steps) * tau
    v, a = np.array([200.0, -120.0, 3.0]), np.array([3.0, -1.5, 0.2])
    post, _ = _noise_free(f, t[:, None] * v + 0.5 * t[:, None] ** 2 * a, tau)
    np.testing.assert_allclose(post[-1, :, 0], t[-1] * v + 0.5 * t[-1] ** 2 * a, atol=1e-5)
    np.testing.assert_allclose(post[-1, :, 2], a, atol=1e-6)
    # constant jerk j: same fixed-point argument gives e⁻ₚ = −jτ³/γ, e⁺ₚ = −(1 − α)jτ³/γ
    # (printed γ convention a⁺ = a⁻ + (γ/τ²)ν)
    j = np.array([0.05, -0.02, 0.01])
    post, _ = _noise_free(f, t[:, None] ** 3 / 6 * j, tau)
    if gains == "fixed":
        al, ga = 0.6, abg_gamma(0.6, kalata_beta(0.6))
    else:
        al, _, ga = steady_state_abg(0.3 * tau**2 / 50.0)
    np.testing.assert_allclose(post[-1, :, 0] - t[-1] ** 3 / 6 * j, -(1 - al) * j * tau**3 / ga, rtol=1e-6)


def _riccati(F, Q, H, R, n=3000):
    kf = KalmanFilter(dim_x=F.shape[0], dim_z=1)
    kf.F, kf.Q, kf.H, kf.R = F, Q, H, np.array([[R]])
    kf.P = np.eye(F.shape[0]) * 1e6
    for _ in range(n):
        kf.predict()
        kf.update(np.array([0.0]))
    return kf.K.ravel(), kf.P.copy()


@pytest.mark.parametrize("lam", [0.02, 0.3, 1.0, 5.0])
def test_kalata_relations_match_steady_state_kalman(lam):
    """α-β: Kalman K∞ of CV with piecewise-constant white acceleration (Γ = [τ²/2, τ]) gives
    Λ² = β²/(1 − α) and β = 2(2 − α) − 4√(1 − α) (Kalata). α-β-γ: CA with acceleration-increment
    noise (Γ = [τ²/2, τ, 1]) gives the same β(α), γ = β²/(2α) and Λ² = γ²/(1 − α)."""
    tau, sr = 3.0, 40.0
    s = lam * sr / tau**2
    g = np.array([[tau**2 / 2], [tau]])
    k, p_inf = _riccati(np.array([[1, tau], [0, 1.0]]), s**2 * g @ g.T, np.array([[1.0, 0.0]]), sr**2)
    a, b = kalata_alpha_beta(lam)
    np.testing.assert_allclose([k[0], k[1] * tau], [a, b], rtol=1e-9)
    np.testing.assert_allclose(b, kalata_beta(a), rtol=1e-9)
    # our steady-state α-β: the gain applied, and its propagated covariance → the Kalman P∞
    f = AlphaBetaFilter(gains="steady_state", sigma_a=s)
    st = f.init(np.zeros((1, 3)), np.full((1, 3), sr**2))
    for k in range(301):
        st = f.predict(st, np.array([tau]))
        prior = st["x"].copy()
        st, inn = f.update(st, np.full((1, 3), 7.0 if k < 300 else 1e3), np.full((1, 3), sr**2), np.array([True]))
    np.testing.assert_allclose((st["x"] - prior)[0, 0] / inn.nu[0, 0], [a, b / tau], rtol=1e-9)
    np.testing.assert_allclose(full_covariance(st["P"][0, 0]), p_inf, rtol=1e-7)

    g3 = np.array([[tau**2 / 2], [tau], [1.0]])
    F3 = np.array([[1, tau, tau**2 / 2], [0, 1, tau], [0, 0, 1.0]])
    k3, p3 = _riccati(F3, s**2 * g3 @ g3.T, np.array([[1.0, 0, 0]]), sr**2)
    a3, b3, c3 = steady_state_abg(lam)
    np.testing.assert_allclose([k3[0], k3[1] * tau, k3[2] * tau**2], [a3, b3, c3], rtol=1e-9)
    np.testing.assert_allclose(b3, kalata_beta(a3), rtol=1e-9)
    np.testing.assert_allclose(c3, abg_gamma(a3, b3), rtol=1e-9)
    np.testing.assert_allclose(lam**2, c3**2 / (1 - a3), rtol=1e-9)
    f3 = AlphaBetaGammaFilter(gains="steady_state", sigma_j=s)
    st = f3.init(np.zeros((1, 3)), np.full((1, 3), sr**2))
    for _ in range(600):
        st = f3.predict(st, np.array([tau]))
        st, _ = f3.update(st, np.zeros((1, 3)), np.full((1, 3), sr**2), np.array([True]))
    np.testing.assert_allclose(full_covariance(st["P"][0, 1]), p3, rtol=1e-6)


def test_fixed_gain_covariance_is_joseph_propagation():
    """P of α-β-γ = (I − KH)(ΦPΦᵀ + Q)(I − KH)ᵀ + KRKᵀ with the frozen K, by matrices."""
    f = AlphaBetaGammaFilter(alpha=0.7, beta=0.4, gamma=0.05, sigma_j=(0.3, 0.5, 0.1))
    rng = np.random.default_rng(5)
    z0, r = rng.normal(0, 1e3, (4, 3)), rng.uniform(100, 900, (4, 3))
    st = f.init(z0, r)
    P = full_covariance(st["P"])
    H = np.eye(1, 3)
    for _ in range(6):
        dt = rng.uniform(0.5, 6.0, 4)
        mask = rng.random(4) < 0.7
        st = f.predict(st, dt)
        st, _ = f.update(st, z0, r, mask)
        for j in range(4):
            tau = dt[j]
            F = np.array([[1, tau, tau**2 / 2], [0, 1, tau], [0, 0, 1.0]])
            for ax in range(3):
                g = np.array([[tau**2 / 2], [tau], [1.0]]) * f.sigma_j[ax]
                Pm = F @ P[j, ax] @ F.T + g @ g.T
                if mask[j]:
                    K = np.array([[0.7], [0.4 / tau], [0.05 / tau**2]])
                    A = np.eye(3) - K @ H
                    Pm = A @ Pm @ A.T + K @ K.T * r[j, ax]
                P[j, ax] = Pm
        np.testing.assert_allclose(full_covariance(st["P"]), P, rtol=1e-10)


# ----------------------------------------------------------------------------- adaptive

def _noisy_cv(f, g, *, b=200, steps=250, tau=4.0, sig_nom=50.0, factor=6.0, seed=1, burn=100):
    rng = np.random.default_rng(seed)
    v = rng.normal(0, 150, (b, 3))
    p0 = rng.normal(0, 1e4, (b, 3))
    r = np.full((b, 3), sig_nom**2)
    z = p0 + rng.normal(0, factor * sig_nom, (b, 3))
    s, s2 = f.init(z, r), g.init(z, r)
    nis, nis2, r_hat = [], [], []
    ones, dt = np.ones(b, bool), np.full(b, tau)
    for k in range(1, steps):
        z = p0 + v * k * tau + rng.normal(0, factor * sig_nom, (b, 3))
        s = f.predict(s, dt)
        s, i = f.update(s, z, r, ones)
        s2 = g.predict(s2, dt)
        s2, i2 = g.update(s2, z, r, ones)
        if k > burn:
            nis.append(i.nu**2 / i.s)
            nis2.append(i2.nu**2 / i2.s)
            r_hat.append(s["r_hat"])
    return np.array(nis), np.array(nis2), np.array(r_hat) / (factor * sig_nom) ** 2


def test_adaptive_r_window_learns_six_times_the_noise():
    """Measurement noise std 6× nominal (R 36×): the windowed R̂ converges to within 20 % of the
    true R and the NIS per axis is ≈ 1, while the fixed-R Singer's NIS is ≫ 1."""
    nis, nis_singer, ratio = _noisy_cv(AdaptiveSingerFilter(mode="r_window", window=30), SingerFilter())
    assert abs(ratio.mean() - 1) < 0.2
    assert np.all(np.abs(nis.mean(axis=(0, 1)) - 1) < 0.25)
    assert np.all(nis_singer.mean(axis=(0, 1)) > 10)


def test_adaptive_hybrid_learns_six_times_the_noise():
    """The text's hybrid (λ and R̂, printed C₀): R̂ is heavy-tailed (λ spikes push it to the
    floor, then a small R̂ raises the next λ — see the class docstring), so its median is the
    converged value; NIS per axis ≈ 1; the non-adaptive Singer's NIS ≫ 1."""
    nis, nis_singer, ratio = _noisy_cv(AdaptiveSingerFilter(), SingerFilter())
    assert abs(np.median(ratio) - 1) < 0.2
    assert np.all(np.abs(nis.mean(axis=(0, 1)) - 1) < 0.25)
    assert np.all(nis_singer.mean(axis=(0, 1)) > 10)
    nis_u, _, ratio_u = _noisy_cv(AdaptiveSingerFilter(r_sub="unfaded"), SingerFilter())
    assert abs(np.median(ratio_u) - 1) < 0.2 and abs(ratio_u.mean() - 1) < abs(ratio.mean() - 1)


def test_adaptive_safeguards():
    f = AdaptiveSingerFilter(window=5, r_floor=0.1)
    rng = np.random.default_rng(2)
    b = 6
    r = np.full((b, 3), 100.0)
    st = f.init(rng.normal(0, 1e-3, (b, 3)), r)
    for k in range(1, 10):
        st = f.predict(st, np.full(b, 2.0))
        if k == 1:
            assert np.all(st["lam"] == 1.0)           # λ(1) = 1: the init plot gives no innovation
        if k == 2:
            assert np.all(st["lam"][0] == 1.0)        # λ = 1 after a coast
        mask = np.ones(b, bool)
        mask[0] = k != 1                              # track 0 coasts at step 1
        z = rng.normal(0, 1e-3, (b, 3))              # ~0 noise: the raw R̂ goes negative
        st, inn = f.update(st, z, r, mask)
        used_nominal = st["count"] <= 5               # R̂(k) needs N innovations before step k
        assert np.all(st["r_hat"][used_nominal] == 100.0)
        assert np.all(st["r_hat"] >= 0.1 * 100.0 - 1e-12)  # floor
        assert np.all(st["lam"] >= 1.0)
    assert st["count"][0] == 8 and np.all(st["count"][1:] == 9)
    assert np.all(st["r_hat"] == 10.0)                # the floor is active at the end


@pytest.mark.parametrize("r_sub", ["faded", "unfaded"])
@pytest.mark.parametrize("c0", ["printed", "smoothed"])
def test_adaptive_hybrid_against_matrix_reference(r_sub, c0):
    """Every step of the hybrid recursion (C₀, λ, P⁻_λ, windowed R̂ with its guards, K, P⁺)
    against a per-track matrix implementation of the documented formulas, one step at a time
    from the filter's own previous state."""
    f = AdaptiveSingerFilter(window=3, r_sub=r_sub, c0=c0, rho=2.0, r_floor=0.2, variant="exact")
    dt, z, r, mask = _scenario(21, b=5, steps=40, p_detect=0.8)
    z = z + np.random.default_rng(4).normal(0, 400.0, z.shape)          # noisier than r: λ, R̂ engage
    st = f.init(z[0], r[0])
    b = dt.shape[1]
    H = np.eye(1, 3)
    ref = [[dict(x=np.array([z[0, j, a], 0, 0]), P=np.diag([r[0, j, a], 300.0**2, 4.0]), lam=1.0,
                 r_prev=r[0, j, a], nu2=np.nan, c0=0.0, win=[]) for a in range(3)] for j in range(b)]
    lam_seen = rhat_seen = 0
    for k in range(1, len(dt)):
        st = f.predict(st, dt[k])
        st, inn = f.update(st, z[k], r[k], mask[k])
        for j in range(b):
            F, Q = singer_phi(dt[k, j], f.alpha, "exact"), singer_q(dt[k, j], f.alpha, 2.0, "exact")
            for a in range(3):
                e = ref[j][a]
                M = F @ e["P"] @ F.T
                if c0 == "printed":
                    C0 = e["lam"] * e["nu2"] / (1 + e["lam"])
                else:
                    C0 = e["c0"] if np.isnan(e["nu2"]) else (2.0 * e["c0"] + e["nu2"]) / 3.0
                    e["c0"] = C0
                ratio = (C0 - e["r_prev"]) / M[0, 0]
                lam = ratio if np.isfinite(ratio) and ratio > 1 else 1.0
                Pm = lam * M + Q
                x = F @ e["x"]
                e.update(lam=lam, nu2=np.nan)
                if mask[k, j]:
                    if len(e["win"]) >= 3:
                        sub = Pm[0, 0] if r_sub == "faded" else M[0, 0]
                        R = max(np.mean(e["win"][-3:]) - sub, 0.2 * r[k, j, a])
                        rhat_seen += R != r[k, j, a]
                    else:
                        R = r[k, j, a]
                    nu = z[k, j, a] - x[0]
                    S = Pm[0, 0] + R
                    K = Pm @ H.T / S
                    x = x + K[:, 0] * nu
                    Pm = Pm - K @ H @ Pm
                    e["win"].append(nu * nu)
                    e.update(nu2=nu * nu, r_prev=R)
                    np.testing.assert_allclose(inn.s[j, a], S, rtol=1e-9)
                e.update(x=x, P=Pm)
                lam_seen += lam > 1
                np.testing.assert_allclose(st["lam"][j, a], lam, rtol=1e-9)
                np.testing.assert_allclose(st["x"][j, a], x, rtol=1e-9, atol=1e-6)
                np.testing.assert_allclose(full_covariance(st["P"][j, a]), Pm, rtol=1e-8, atol=1e-6)
                # R̂ = mean ν² − HP⁻Hᵀ cancels large terms: a looser relative tolerance
                np.testing.assert_allclose(st["r_hat"][j, a], e["r_prev"], rtol=1e-7)
                # re-sync: the faded loop amplifies rounding, so compare step by step
                e.update(x=st["x"][j, a].copy(), P=full_covariance(st["P"][j, a]), lam=st["lam"][j, a],
                         r_prev=st["r_hat"][j, a], c0=st["c0"][j, a])
    assert lam_seen > 20 and rhat_seen > 20                             # both adaptations exercised


def test_two_model_against_filterpy_and_bayes():
    """Each model equals filterpy with independently built matrices (model 2: Φ₂ = [[1, τ],
    [0, 1 − α₂τ]], Q₂ = diag(0, q₂(τ − α₂τ²/2)), printed); weights W₁ = c₁L₁/(c₁L₁ + c₂L₂) with
    the Markov prior and Gaussian likelihoods N(ν_j; 0, S_j)."""
    from scipy.stats import norm

    f = TwoModelFilter(alpha2=0.02, q2=(0.5, 0.5, 0.1), p_stay=0.9)
    dt, z, r, mask = _scenario(13, b=6, steps=40, p_detect=0.8)
    dt = np.minimum(dt, 10.0)
    st = f.init(z[0], r[0])
    hist = [st]
    for k in range(1, len(dt)):
        st = f.predict(st, dt[k])
        st, _ = f.update(st, z[k], r[k], mask[k])
        hist.append(st)
    for j in range(6):
        for a in range(3):
            k1, k2 = KalmanFilter(dim_x=3, dim_z=1), KalmanFilter(dim_x=2, dim_z=1)
            k1.x, k1.P, k1.H = np.array([z[0, j, a], 0, 0]), np.diag([r[0, j, a], 300.0**2, 4.0]), np.eye(1, 3)
            k2.x, k2.P, k2.H = np.array([z[0, j, a], 0]), np.diag([r[0, j, a], 300.0**2]), np.eye(1, 2)
            w1 = 0.5
            for k in range(1, len(dt)):
                tau = dt[k, j]
                k1.F, k1.Q = singer_phi(tau, 1 / 30, "printed"), singer_q(tau, 1 / 30, 2.0, "printed")
                k2.F = np.array([[1.0, tau], [0.0, 1 - 0.02 * tau]])
                k2.Q = np.diag([0.0, f.q2[a] * (tau - 0.02 * tau**2 / 2)])
                k1.predict()
                k2.predict()
                c1 = 0.9 * w1 + 0.1 * (1 - w1)
                if mask[k, j]:
                    k1.R = k2.R = np.array([[r[k, j, a]]])
                    k1.update(np.array([z[k, j, a]]))
                    k2.update(np.array([z[k, j, a]]))
                    l1 = norm.pdf(k1.y[0], scale=np.sqrt(k1.S[0, 0]))
                    l2 = norm.pdf(k2.y[0], scale=np.sqrt(k2.S[0, 0]))
                    w1 = c1 * l1 / (c1 * l1 + (1 - c1) * l2)
                else:
                    w1 = c1
                s_k = hist[k]
                np.testing.assert_allclose(s_k["x1"][j, a], k1.x, rtol=1e-9, atol=1e-6)
                np.testing.assert_allclose(s_k["x2"][j, a], k2.x, rtol=1e-9, atol=1e-6)
                np.testing.assert_allclose(full_covariance(s_k["P2"][j, a]), k2.P, rtol=1e-9, atol=1e-6)
                np.testing.assert_allclose(s_k["w"][j, a], [w1, 1 - w1], rtol=1e-8, atol=1e-12)
    out = f.output(st)
    w = st["w"]
    np.testing.assert_allclose(out.x[:, :3], w[..., 0] * st["x1"][..., 0] + w[..., 1] * st["x2"][..., 0])
    np.testing.assert_allclose(out.probs, w[:, :2].mean(axis=1))


# ----------------------------------------------------------------------------- two-model

def test_two_model_printed_prior_flips_with_period_two():
    ll = np.log(np.array([0.8, 0.2]))
    w = np.array([0.5, 0.5])
    hist = [w]
    for _ in range(6):
        w = two_model_weights(w, ll, "printed", 0.95)
        hist.append(w)
    hist = np.array(hist)
    np.testing.assert_allclose(hist.sum(axis=1), 1.0)
    np.testing.assert_allclose(hist[2::2], np.broadcast_to(hist[0], (3, 2)), atol=1e-12)   # period 2
    np.testing.assert_allclose(hist[1::2], np.broadcast_to([0.8, 0.2], (3, 2)), atol=1e-12)
    assert abs(hist[1, 0] - hist[2, 0]) > 0.25                       # …and never accumulates evidence


@pytest.mark.parametrize("p_stay", [1.0, 0.95, 0.8])
def test_two_model_corrected_prior_converges(p_stay):
    ll = np.log(np.array([0.8, 0.2]))
    w = np.array([0.5, 0.5])
    for _ in range(200):
        w = two_model_weights(w, ll, "corrected", p_stay)
    w_next = two_model_weights(w, ll, "corrected", p_stay)
    np.testing.assert_allclose(w_next, w, atol=1e-12)
    assert w[0] > 0.8 and np.isclose(w.sum(), 1.0)
    if p_stay == 1.0:
        assert w[0] > 1 - 1e-12


def _turning(seed: int, b: int = 100, tau: float = 2.0, straight: int = 60, turn: int = 40):
    """Straight at 150 m/s, then a 3 g-ish horizontal coordinated turn; 30 m plot noise."""
    rng = np.random.default_rng(seed)
    n = straight + turn
    speed, omega = 150.0, np.deg2rad(6.0)                      # 15.7 m/s² centripetal
    t = np.arange(n) * tau
    head = np.where(t < straight * tau, 0.0, omega * (t - straight * tau))
    vx, vy = speed * np.cos(head), speed * np.sin(head)
    x = np.concatenate([[0.0], np.cumsum((vx[1:] + vx[:-1]) / 2 * tau)])
    y = np.concatenate([[0.0], np.cumsum((vy[1:] + vy[:-1]) / 2 * tau)])
    truth = np.stack([x, y, np.full(n, 3000.0)], axis=1)
    z = truth[:, None, :] + rng.normal(0, 30.0, (n, b, 3))
    return z, np.full((b, 3), 900.0), tau, straight


@pytest.mark.parametrize("prior,likelihood", [("corrected", "intended"), ("printed", "intended"),
                                              ("corrected", "printed")])
def test_two_model_weights_sum_to_one_and_follow_the_manoeuvre(prior, likelihood):
    f = TwoModelFilter(prior=prior, likelihood=likelihood)
    z, r, tau, straight = _turning(4)
    b = z.shape[1]
    rng = np.random.default_rng(9)
    st = f.init(z[0], r)
    probs = []
    for k in range(1, len(z)):
        st = f.predict(st, np.full(b, tau))
        st, inn = f.update(st, z[k], r, rng.random(b) < 0.95)
        out = f.output(st)
        np.testing.assert_allclose(st["w"].sum(axis=-1), 1.0, atol=1e-12)
        np.testing.assert_allclose(out.probs.sum(axis=1), 1.0, atol=1e-12)
        assert np.all((out.probs >= 0) & (out.probs <= 1)) and np.all(np.isfinite(out.x))
        probs.append(out.probs[:, 0])
    p1 = np.array(probs).mean(axis=1)                 # mean P(model 1 = Singer) over tracks
    straight_w = p1[straight // 2:straight - 1].mean()
    turn_w = p1[straight + 10:].mean()
    if prior == "corrected":
        assert straight_w < 0.4                        # straight: the rate model wins
        assert turn_w > 0.6                            # turn: the weight moves to Singer
        assert turn_w - straight_w > 0.3
    else:                                              # printed prior: flips, no accumulated evidence
        assert abs(straight_w - 0.5) < 0.1 and abs(turn_w - 0.5) < 0.1


# ----------------------------------------------------------------------------- plumbing

@pytest.mark.parametrize("name", NAMES)
def test_registry_take_concat_and_coasting(name):
    f = make_filter(name)
    assert name in REGISTRY and f.name == name
    rng = np.random.default_rng(3)
    b = 7
    z, r = rng.normal(0, 1e3, (b, 3)), np.full((b, 3), 400.0)
    st = f.init(z, r)
    for _ in range(3):
        st = f.predict(st, rng.uniform(1, 5, b))
        st, _ = f.update(st, z + rng.normal(0, 20, (b, 3)), r, rng.random(b) < 0.8)
    assert all(len(v) == b for v in st.values())
    idx = np.array([4, 0, 2])
    rest = np.setdiff1d(np.arange(b), idx)
    joined = concat(take(st, idx), take(st, rest))
    order = np.concatenate([idx, rest])
    assert size(joined) == b and set(joined) == set(st)
    for k in st:
        np.testing.assert_array_equal(joined[k], st[k][order])
    back = take(joined, np.argsort(order))
    for k in st:
        np.testing.assert_array_equal(back[k], st[k])
    # predict does not mutate its input; a track without a plot keeps the prediction
    before = {k: v.copy() for k, v in st.items()}
    pred = f.predict(st, np.full(b, 2.0))
    for k in st:
        np.testing.assert_array_equal(st[k], before[k])
    mask = np.ones(b, bool)
    mask[[1, 5]] = False
    z_nan = z.copy()
    z_nan[~mask] = np.nan
    r_nan = r.copy()
    r_nan[~mask] = np.nan
    post, inn = f.update(pred, z_nan, r_nan, mask)
    for k in (k for k in pred if k[0] in "xP"):
        np.testing.assert_array_equal(post[k][~mask], pred[k][~mask])
        assert not np.array_equal(post[k][mask], pred[k][mask])
    assert np.all(np.isnan(inn.nu[~mask])) and np.all(np.isnan(inn.s[~mask])) and np.all(np.isnan(inn.nis[~mask]))
    assert np.all(np.isfinite(inn.nis[mask])) and np.all(inn.s[mask] > 0)
    out = f.output(post)
    assert out.x.shape == (b, 6) and out.var.shape == (b, 6)
    assert np.all(np.isfinite(out.x)) and np.all(out.var > 0)
    assert (out.probs is not None) == (name == "two_model")
    # all-coasting and empty batches
    post, inn = f.update(pred, z_nan, r_nan, np.zeros(b, bool))
    assert np.all(np.isnan(inn.nis))
    empty = f.init(np.zeros((0, 3)), np.zeros((0, 3)))
    empty = f.predict(empty, np.zeros(0))
    empty, inn = f.update(empty, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, bool))
    assert f.output(empty).x.shape == (0, 6) and inn.nis.shape == (0,)


def test_output_maps_to_common_six_state():
    f = SingerFilter()
    st = f.init(np.array([[1.0, 2.0, 3.0]]), np.array([[4.0, 5.0, 6.0]]))
    st["x"][0, :, 1] = [7.0, 8.0, 9.0]
    out = f.output(st)
    np.testing.assert_array_equal(out.x, [[1, 2, 3, 7, 8, 9]])
    np.testing.assert_array_equal(out.var, [[4, 5, 6, 300.0**2, 300.0**2, 300.0**2]])


def test_bad_parameters_rejected():
    for bad in (dict(variant="x"), dict(sigma_m=-1.0), dict(sigma_m=(1.0, 2.0))):
        with pytest.raises(ValueError):
            SingerFilter(**bad)
    with pytest.raises(ValueError):
        AdaptiveSingerFilter(mode="bogus")
    with pytest.raises(ValueError):
        TwoModelFilter(w0=(0.7, 0.7))
    with pytest.raises(ValueError):
        AlphaBetaFilter(alpha=0.5, beta=3.5)


def test_speed_sanity_ten_thousand_tracks():
    """Not a timing assertion: one Singer predict + update for 10 000 tracks runs and is
    reported (target ≲ 10 ms, i.e. ≥ 10⁶ track-updates/s)."""
    b = 10_000
    rng = np.random.default_rng(0)
    f = SingerFilter()
    r = np.full((b, 3), 100.0**2)
    z = rng.normal(0, 1e4, (b, 3))
    st = f.init(z, r)
    mask, dt = rng.random(b) < 0.9, rng.uniform(1, 5, b)
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        st = f.predict(st, dt)
        st, _ = f.update(st, z, r, mask)
        best = min(best, time.perf_counter() - t0)
    print(f"singer: {best * 1e3:.2f} ms per predict+update of {b} tracks ({b / best / 1e6:.1f} M/s)")
    assert best < 1.0
