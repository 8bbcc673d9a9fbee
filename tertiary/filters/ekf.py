"""Six-state EKF in radar spherical coordinates — seed 004 (Masharov).

State X = [D, α, γ, V, B, Γ]: slant range (m), azimuth α (rad, clockwise from north), elevation
γ (rad above the horizon), speed V (m/s), course B (rad, clockwise from north) and "pitch" Γ (rad).
The paper's γ ("from the zenith") and Γ ("from the vertical", test case Γ = 270°) are stored in
the intended common reference: γ = elevation above the horizon and
Γ = Γ_printed − 270°, so that level flight has Γ = 0 and the model sees γ − Γ = e.

Model (1) discretised by Euler (3)/(5), T the step:

    D⁺ = D + T V cos(α−B) cos(γ−Γ)
    α⁺ = α − (T V/D) sin(α−B) cos(γ−Γ)
    γ⁺ = γ − (T V/D) sin(γ−Γ) cos(α−B)
    V⁺ = V,  B⁺ = B,  Γ⁺ = Γ

(the azimuth rate carries a cos² e factor vs exact level-flight kinematics — a model limitation
kept for fidelity). Measurement Z = [D, α, γ] + ε, H = [I₃ | 0]; EKF (6)–(7) with
the analytic Jacobian F = ∂Φ/∂X (:func:`phi_jacobian`), Joseph-form covariance
update, wrapped azimuth innovation.

For fused plots the "radar" is the system origin (the processing centre): each ENU plot z with
variances r is converted to (D, α, γ) with covariance R = J⁻¹ diag(r) J⁻ᵀ, J = ∂(e,n,u)/∂(D,α,γ)
at the plot (a full 3×3; the paper's R_ε is diagonal for a real radar). The filter is therefore
only meaningful for targets well away from the origin and from the zenith.

Process noise: the paper adds a diagonal R_w per step; here R_w = diag(q)·Δt so that variable
scan intervals work. The default q = (0, 0, 0, 10⁻², 10⁻⁸, 10⁻⁸) gives the paper's
R_w = diag(0, 0, 0, 10⁻⁴, 10⁻¹⁰, 10⁻¹⁰) at T = 10 ms.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.core.geo import enu_to_polar, polar_jacobian, polar_state_to_enu, sandwich

TWO_PI = 2.0 * np.pi


def phi(x: F64, t: ArrayLike) -> F64:
    """Euler transition Φ(X) (3)/(5) for states (..., 6) and steps T (...) (complex-step safe)."""
    x = np.asarray(x) * 1.0
    t = np.asarray(t, float)
    d, a, g, v, b, gg = np.moveaxis(x, -1, 0)
    ca, sa, cg, sg = np.cos(a - b), np.sin(a - b), np.cos(g - gg), np.sin(g - gg)
    rho = t * v / d
    out = x.copy()
    out[..., 0] = d + t * v * ca * cg
    out[..., 1] = a - rho * sa * cg
    out[..., 2] = g - rho * sg * ca
    return out


def phi_jacobian(x: F64, t: ArrayLike) -> F64:
    """F = ∂Φ/∂X (..., 6, 6), written out."""
    x = np.asarray(x, float)
    t = np.broadcast_to(np.asarray(t, float), x.shape[:-1])
    d, a, g, v, b, gg = np.moveaxis(x, -1, 0)
    ca, sa, cg, sg = np.cos(a - b), np.sin(a - b), np.cos(g - gg), np.sin(g - gg)
    rho = t * v / d
    f = np.zeros(x.shape + (6,))
    f[..., 0, 0] = 1.0
    f[..., 0, 1] = -t * v * sa * cg
    f[..., 0, 2] = -t * v * ca * sg
    f[..., 0, 3] = t * ca * cg
    f[..., 0, 4] = t * v * sa * cg
    f[..., 0, 5] = t * v * ca * sg
    f[..., 1, 0] = t * v * sa * cg / d ** 2
    f[..., 1, 1] = 1.0 - rho * ca * cg
    f[..., 1, 2] = rho * sa * sg
    f[..., 1, 3] = -t * sa * cg / d
    f[..., 1, 4] = rho * ca * cg
    f[..., 1, 5] = -rho * sa * sg
    f[..., 2, 0] = t * v * sg * ca / d ** 2
    f[..., 2, 1] = rho * sa * sg
    f[..., 2, 2] = 1.0 - rho * ca * cg
    f[..., 2, 3] = -t * sg * ca / d
    f[..., 2, 4] = -rho * sa * sg
    f[..., 2, 5] = rho * ca * cg
    f[..., 3, 3] = f[..., 4, 4] = f[..., 5, 5] = 1.0
    return f


def enu_to_measurement(z: F64, r: F64) -> tuple[F64, F64]:
    """ENU plots z (B, 3) with variances r (B, 3) or covariance (B, 3, 3) → (D, α, γ) (rad) and
    their covariance J⁻¹ R J⁻ᵀ (B, 3, 3), the radar being the frame origin."""
    z = np.asarray(z, float)
    rng, az, el = enu_to_polar(z[:, 0], z[:, 1], z[:, 2])
    jinv = np.linalg.inv(polar_jacobian(rng, az, el))
    r = np.asarray(r, float)
    rf = r if r.ndim == 3 else r[:, :, None] * np.eye(3)
    return np.stack([rng, np.radians(az), np.radians(el)], axis=1), sandwich(jinv, rf)


def wrap_pi(a: ArrayLike) -> F64:
    """Wrap angles to [−π, π)."""
    return np.mod(np.asarray(a, float) + np.pi, TWO_PI) - np.pi


def state_to_enu(x: F64, p: F64 | None = None) -> tuple[F64, F64, F64 | None]:
    """ENU position, velocity (the model's rates mapped through the polar Jacobian) and the
    6×6 covariance of (e, n, u, ė, ṅ, u̇) by first-order propagation of P."""
    x = np.asarray(x, float)
    rates = (phi(x, 1.0) - x)[..., :3]                 # (Ḋ, α̇, γ̇) of model (1)
    cov = None
    if p is not None:
        f1 = phi_jacobian(x, 1.0)
        m = np.zeros(x.shape + (6,))
        m[..., 0, 0] = m[..., 1, 1] = m[..., 2, 2] = 1.0
        m[..., 3:, :] = f1[..., :3, :] - np.eye(6)[:3]  # ∂(Ḋ, α̇, γ̇)/∂X
        cov = sandwich(m, p)
    pos, vel, c = polar_state_to_enu(x[..., 0], np.degrees(x[..., 1]), np.degrees(x[..., 2]),
                                     rates[..., 0], np.degrees(rates[..., 1]), np.degrees(rates[..., 2]), cov)
    return pos, vel, c


@register
class SphericalEKF(TrackFilter):
    """Seed 004 six-state spherical-coordinate EKF on fused ENU plots (radar = system origin).

    Parameters:
        q:            diagonal process-noise rates, R_w = diag(q)·Δt (units²/s), default
                      (0, 0, 0, 1e-2, 1e-8, 1e-8) = the paper's R_w at T = 10 ms
        v0:           initial speed when starting from a plot (m/s), default 150
        sigma_v0:     its σ (m/s), default 100
        course0_deg:  initial course (deg clockwise from north); None = inbound (towards the
                      origin), the paper's test geometry; default None
        sigma_course0_deg, sigma_pitch0_deg: initial σ of B and Γ, default 30° and 5°
    """

    name = "ekf_spherical"

    def __init__(self, q: Sequence[float] = (0.0, 0.0, 0.0, 1e-2, 1e-8, 1e-8), v0: float = 150.0,
                 sigma_v0: float = 100.0, course0_deg: float | None = None, sigma_course0_deg: float = 30.0,
                 sigma_pitch0_deg: float = 5.0):
        self.q = np.asarray(q, float)
        self.v0, self.sigma_v0 = float(v0), float(sigma_v0)
        self.course0 = None if course0_deg is None else np.radians(course0_deg)
        self.sig_b0, self.sig_g0 = np.radians(sigma_course0_deg), np.radians(sigma_pitch0_deg)

    def init(self, z: F64, r: F64) -> State:
        """Measurement initialisation (the conclusions' recommendation): D, α, γ and
        their covariance from the first plot; V, B, Γ from the constructor's priors."""
        zm, rm = enu_to_measurement(z, r)
        b = len(zm)
        x = np.zeros((b, 6))
        x[:, :3] = zm
        x[:, 3] = self.v0
        x[:, 4] = np.mod(zm[:, 1] + np.pi, TWO_PI) if self.course0 is None else self.course0
        p = np.zeros((b, 6, 6))
        p[:, :3, :3] = rm
        p[:, 3, 3], p[:, 4, 4], p[:, 5, 5] = self.sigma_v0 ** 2, self.sig_b0 ** 2, self.sig_g0 ** 2
        return {"x": x, "P": p}

    def init_state(self, x: F64, p: F64) -> State:
        return {"x": np.array(x, float), "P": np.array(p, float)}

    def predict(self, state: State, dt: F64) -> State:
        x, p = state["x"], state["P"]
        dt = np.broadcast_to(np.asarray(dt, float), (len(x),))
        f = phi_jacobian(x, dt)
        xn = phi(x, dt)
        pn = sandwich(f, p) + self.q * dt[:, None, None] * np.eye(6)
        return {"x": xn, "P": 0.5 * (pn + np.swapaxes(pn, -1, -2))}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        """Update with fused ENU plots: convert to (D, α, γ) and covariance, then
        :meth:`update_polar`. The innovation is reported in ENU (z − predicted position) with
        S mapped by the polar Jacobian at the prediction; NIS is the filter's own (polar) one."""
        x = state["x"]
        z = np.asarray(z, float)
        r = np.asarray(r, float)
        ok = np.asarray(mask, bool) & np.all(np.isfinite(z), axis=1)
        zs = np.where(ok[:, None], z, 1.0)                 # placeholder plots for coasting tracks
        rs = np.where(ok[:, None], r, 1.0) if r.ndim == 2 else np.where(ok[:, None, None], r, np.eye(3))
        zm, rm = enu_to_measurement(zs, rs)
        new, nis, s = self.update_polar(state, zm, rm, ok)
        pos_pred, _, _ = state_to_enu(x)
        jp = polar_jacobian(x[:, 0], np.degrees(x[:, 1]), np.degrees(x[:, 2]))
        s_enu = np.einsum("bii->bi", sandwich(jp, s))
        bad = ~ok
        innov = Innovation(np.where(bad[:, None], np.nan, z - pos_pred), np.where(bad[:, None], np.nan, s_enu),
                           np.where(bad, np.nan, nis))
        return new, innov

    def update_polar(self, state: State, zm: F64, rm: F64, mask: NDArray[np.bool_]) -> tuple[State, F64, F64]:
        """EKF update (6)–(7) with radar measurements zm = (D, α, γ) (B, 3) (rad) and covariance
        rm (B, 3, 3); returns the new state, NIS (NaN outside ``mask``) and S (B, 3, 3)."""
        x, p = state["x"], state["P"]
        ok = np.asarray(mask, bool)
        y = zm - x[:, :3]
        y[:, 1] = wrap_pi(y[:, 1])
        s = p[:, :3, :3] + rm
        si = np.linalg.inv(s)
        k = p[:, :, :3] @ si                                # (B, 6, 3)
        xu = x + np.einsum("bij,bj->bi", k, y)
        ikh = np.eye(6) - np.concatenate([k, np.zeros((len(x), 6, 3))], axis=2)
        pu = sandwich(ikh, p) + sandwich(k, rm)             # Joseph form
        pu = 0.5 * (pu + np.swapaxes(pu, -1, -2))
        xu[:, 1] = np.mod(xu[:, 1], TWO_PI)
        xu[:, 4] = np.mod(xu[:, 4], TWO_PI)
        nis = np.where(ok, np.einsum("bi,bij,bj->b", y, si, y), np.nan)
        new = {"x": np.where(ok[:, None], xu, x), "P": np.where(ok[:, None, None], pu, p)}
        return new, nis, s

    def output(self, state: State) -> Output:
        pos, vel, cov = state_to_enu(state["x"], state["P"])
        return Output(np.concatenate([pos, vel], axis=1), np.einsum("bii->bi", cov), None, cov)


# --------------------------------------------------------------------------- seed 004 test case


def simulate_seed004(n_runs: int = 300, steps: int = 1000, t: float = 0.01, sigma_d: float = 100.0,
                     sigma_ang_deg: float = 0.3, altitude: float = 1000.0, seed: int = 4
                     ) -> tuple[F64, F64, F64]:
    """The paper's test case: D(0) = 10 km, α(0) = 2°, level flight at ``altitude``
    heading south (B = 180°, Γ = 0 in the intended reference) at 1500 km/h, straight Cartesian
    truth with exact (D, α, e). Returns truth states (T, 6) (T = steps + 1), noisy measurements
    (N, T, 3) and the measurement covariance (3, 3)."""
    rng = np.random.default_rng(seed)
    v = 1500.0 / 3.6
    d0, a0 = 10_000.0, np.radians(2.0)
    h0 = np.sqrt(d0 ** 2 - altitude ** 2)
    tt = np.arange(steps + 1) * t
    e = np.full_like(tt, h0 * np.sin(a0))
    n = h0 * np.cos(a0) - v * tt
    rng_t, az_t, el_t = enu_to_polar(e, n, np.full_like(tt, altitude))
    truth = np.stack([rng_t, np.radians(az_t), np.radians(el_t), np.full_like(tt, v),
                      np.full_like(tt, np.pi), np.zeros_like(tt)], axis=1)
    sig = np.array([sigma_d, np.radians(sigma_ang_deg), np.radians(sigma_ang_deg)])
    meas = truth[None, :, :3] + sig * rng.standard_normal((n_runs, steps + 1, 3))
    return truth, meas, np.diag(sig ** 2)


#: assumed a-priori bounds of the midpoint initialisation (the paper gives none):
#: a short-range radar's instrumented range and a fast air target's speed
MIDPOINT_RANGE_M = (500.0, 30_000.0)
MIDPOINT_SPEED_MPS = (50.0, 700.0)


def initial_state_seed004(meas0: F64, truth0: F64, rm: F64, rng: np.random.Generator, init: str = "measurement",
                          range_bounds: tuple[float, float] = MIDPOINT_RANGE_M,
                          speed_bounds: tuple[float, float] = MIDPOINT_SPEED_MPS) -> tuple[F64, F64]:
    """X̂(0), P(0|0) (N, 6), (N, 6, 6) of the midpoint initialisation for the k = 0 measurements ``meas0`` (N, 3).

    * ``measurement`` (the conclusions' recommendation, the §3.8 default): D, α, γ = Z(0) with
      P = R_ε; V, B, Γ = truth + N(0, diag(50 m/s, 5°, 5°)²) with those variances.
    * ``midpoint`` (the text's proposal): D and V at the midpoints of the assumed ``range_bounds``
      and ``speed_bounds``, their variances those of a uniform prior over the bounds, (b − a)²/12;
      α, γ from Z(0) (the beam direction is known), B, Γ as above."""
    n = len(meas0)
    prior_sig = np.array([50.0, np.radians(5.0), np.radians(5.0)])
    x0 = np.concatenate([meas0, truth0[3:] + prior_sig * rng.standard_normal((n, 3))], axis=1)
    p0 = np.zeros((n, 6, 6))
    p0[:, :3, :3] = rm
    p0[:, [3, 4, 5], [3, 4, 5]] = prior_sig ** 2
    if init == "midpoint":
        for i, (lo, hi) in ((0, range_bounds), (3, speed_bounds)):
            x0[:, i] = 0.5 * (lo + hi)
            p0[:, i, :] = 0.0
            p0[:, :, i] = 0.0
            p0[:, i, i] = (hi - lo) ** 2 / 12.0
    elif init != "measurement":
        raise ValueError(f"init must be 'measurement' or 'midpoint', got {init!r}")
    return x0, p0


def run_seed004(n_runs: int = 300, steps: int = 1000, t: float = 0.01, sigma_d: float = 100.0,
                sigma_ang_deg: float = 0.3, seed: int = 4, filt: SphericalEKF | None = None,
                init: str = "measurement") -> tuple[F64, F64]:
    """Run the EKF on :func:`simulate_seed004` in the radar's own coordinates, initialised per
    ``init`` (:func:`initial_state_seed004`). Returns per-step RMSE (T, 6) of [D, α, γ, V, B, Γ]
    and the truth (T, 6)."""
    filt = filt or SphericalEKF()
    rng = np.random.default_rng(seed + 1000)
    truth, meas, rm = simulate_seed004(n_runs, steps, t, sigma_d, sigma_ang_deg, seed=seed)
    x0, p0 = initial_state_seed004(meas[:, 0], truth[0], rm, rng, init)
    state = filt.init_state(x0, p0)
    rmb = np.broadcast_to(rm, (n_runs, 3, 3))
    ok = np.ones(n_runs, bool)
    dt = np.full(n_runs, t)
    err = np.empty((steps + 1, 6))

    def rmse(x: F64, k: int) -> F64:
        d = x - truth[k]
        d[:, [1, 4, 5]] = wrap_pi(d[:, [1, 4, 5]])
        return np.sqrt(np.mean(d ** 2, axis=0))

    err[0] = rmse(state["x"], 0)
    for k in range(1, steps + 1):
        state = filt.predict(state, dt)
        state, _, _ = filt.update_polar(state, meas[:, k], rmb, ok)
        err[k] = rmse(state["x"], k)
    return err, truth
