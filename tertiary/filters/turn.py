"""IMM of a constant-velocity model and a nearly-constant-turn model whose turn rate is estimated.

Horizontal state of both models ``[x, vx, y, vy, ω]`` (x = east, y = north of the system ENU
frame; positive ω turns the velocity from +X towards +Y, the convention of
:mod:`tertiary.filters.imm`); the vertical axis is the separate CV channel ``[z, vz]`` of
:class:`tertiary.filters.imm.IMMFilter`.

* **CT-EKF** (Bar-Shalom, Li & Kirubarajan 2001, §11.7.2, eqs. 11.7.2-4 and its Jacobian
  11.7.2-8): the position–velocity part moves with A_ct(ω̂, Δt) (:func:`tertiary.filters.imm.a_ct`),
  ω is a random walk, ω' = ω + w_ω. The prediction is linearised at the mixed estimate:
  F = [[A_ct(ω̂), ∂(A_ct x)/∂ω], [0, 1]]; the process noise is the exact CT white-acceleration
  noise at ω̂ (:func:`tertiary.filters.imm.q_ct`, PSD ``q_ct``) plus ``q_omega``·Δt on ω. One
  model follows any turn rate, left or right, gentle or tight, without a grid of fixed rates.
* **CV**: A_cv, Q_cv (PSD ``q``) and ω ≡ 0 (its ω row and column are zero): the straight-leg
  model, with low noise, so on straight legs the velocity covariance is that of a CV filter
  (consistent) and is not widened by mixing with a fixed high-rate turn model.

The IMM cycle (mixing, model-conditioned update with H = [[1,0,0,0,0],[0,0,1,0,0]], Gaussian
likelihoods, moment-matched output) is that of :mod:`tertiary.filters.imm` (:func:`imm_mix`,
:func:`imm_update`, :func:`imm_combine`, which are written for any state size). Measurements
are fused ENU plots with a (B, 3, 3) or diagonal (B, 3) covariance whose horizontal 2×2 block is
used in full (``full_r``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.filters.imm import (a_ct, a_cv, cv1_predict, cv1_update, imm_combine, imm_mix, imm_update,
                                  imm_velocity_update, innovation, q_ct, q_cv, split_r)

__all__ = ["ct_jacobian_omega", "ct_ekf_predict", "IMMCTFilter"]

_H = np.array([0, 2])                 # measured components of [x, vx, y, vy, ω]
_N = 5


def _dsinc_terms(omega: F64, dt: F64) -> tuple[F64, F64]:
    """d/dω of sin(ωΔt)/ω and of (1 − cos ωΔt)/ω, exact at ω → 0 (series below |ωΔt| = 0.3,
    error < 1e-15 relative): Δt²·(u cos u − sin u)/u² and Δt²·(u sin u − 1 + cos u)/u², u = ωΔt."""
    u = omega * dt
    small = np.abs(u) < 0.3
    us = np.where(small, 1.0, u)
    u2 = u * u
    g1 = np.where(small, -u / 3.0 * (1.0 - u2 / 10.0 * (1.0 - u2 / 28.0 * (1.0 - u2 / 54.0))),
                  (us * np.cos(us) - np.sin(us)) / (us * us))
    g2 = np.where(small, 0.5 - u2 / 8.0 * (1.0 - u2 / 18.0 * (1.0 - u2 / 40.0 * (1.0 - u2 / 70.0))),
                  (us * np.sin(us) - 1.0 + np.cos(us)) / (us * us))
    return dt * dt * g1, dt * dt * g2


def ct_jacobian_omega(x: F64, dt: F64) -> F64:
    """∂(A_ct(ω, Δt) [x, vx, y, vy])/∂ω (B, 4) at the states x (B, 5) (last column ω)."""
    vx, vy, w = x[:, 1], x[:, 3], x[:, 4]
    d1, d2 = _dsinc_terms(w, dt)
    s, c = np.sin(w * dt), np.cos(w * dt)
    return np.stack([d1 * vx - d2 * vy, -dt * (s * vx + c * vy), d2 * vx + d1 * vy, dt * (c * vx - s * vy)], axis=1)


def ct_ekf_predict(x: F64, p: F64, dt: F64, q: float, q_omega: float) -> tuple[F64, F64]:
    """EKF prediction of the nearly-constant-turn model: x (B, 5), P (B, 5, 5), Δt (B,)."""
    a = a_ct(x[:, 4], dt)                                       # (B, 4, 4)
    f = np.zeros((len(x), _N, _N))
    f[:, :4, :4] = a
    f[:, :4, 4] = ct_jacobian_omega(x, dt)
    f[:, 4, 4] = 1.0
    xp = np.empty_like(x)
    xp[:, :4] = np.einsum("bij,bj->bi", a, x[:, :4])
    xp[:, 4] = x[:, 4]
    pp = f @ p @ np.swapaxes(f, -1, -2)
    pp[:, :4, :4] += q_ct(x[:, 4], dt, q)
    pp[:, 4, 4] += q_omega * dt
    return xp, 0.5 * (pp + np.swapaxes(pp, -1, -2))


def _cv_predict(x: F64, p: F64, dt: F64, q: float) -> tuple[F64, F64]:
    """CV prediction in the 5-state layout, ω set to 0 with no uncertainty."""
    a = a_cv(dt)
    xp = np.zeros_like(x)
    xp[:, :4] = np.einsum("bij,bj->bi", a, x[:, :4])
    pp = np.zeros_like(p)
    p4 = a @ p[:, :4, :4] @ np.swapaxes(a, -1, -2) + q_cv(dt, q)
    pp[:, :4, :4] = 0.5 * (p4 + np.swapaxes(p4, -1, -2))
    return xp, pp


@register
class IMMCTFilter(TrackFilter):
    """IMM {CV, CT-EKF with estimated ω} + vertical CV channel, batched over tracks.

    Parameters:
        q:             CV model white-acceleration PSD (m²/s³), default 0.1
        q_ct:          CT model white-acceleration PSD (m²/s³), default 0.5
        q_omega:       CT model turn-rate random-walk PSD (rad²/s³), default 1e-5
                       (σ_ω grows by 0.006 rad/s in 4 s: a roll-in is followed in a few scans)
        tpm:           row-stochastic mode transition matrix (CV, CT) per step
        mu0:           initial mode probabilities
        sigma_v0:      horizontal velocity σ (m/s) of a track started from one plot
        sigma_omega0:  turn-rate σ (rad/s) of a new track's CT model, default 0.05 (≈ 3°/s)
        q_z:           vertical CV channel PSD (m²/s³)
        mu_floor:      floor on μ after each update (renormalised)
    """

    name = "imm_ct"
    full_r = True

    def __init__(self, q: float = 0.1, q_ct: float = 0.5, q_omega: float = 1e-5,
                 tpm: ArrayLike = ((0.97, 0.03), (0.03, 0.97)), mu0: Sequence[float] = (0.8, 0.2),
                 sigma_v0: float = 150.0, sigma_omega0: float = 0.05, q_z: float = 1.0, mu_floor: float = 1e-6):
        self.q, self.q_ct, self.q_omega = float(q), float(q_ct), float(q_omega)
        self.tpm = np.asarray(tpm, float)
        mu0 = np.asarray(mu0, float)
        self.mu0 = mu0 / mu0.sum()
        if self.tpm.shape != (2, 2) or self.mu0.shape != (2,) or not np.allclose(self.tpm.sum(axis=1), 1.0):
            raise ValueError("tpm must be a row-stochastic 2×2 matrix and mu0 (2,) (models CV, CT)")
        self.sigma_v0, self.sigma_omega0 = float(sigma_v0), float(sigma_omega0)
        self.q_z, self.mu_floor = float(q_z), float(mu_floor)

    def init(self, z: F64, r: F64) -> State:
        z = np.asarray(z, float)
        rh, rz = split_r(np.asarray(r, float))
        b = len(z)
        x = np.zeros((b, 2, _N))
        x[:, :, 0], x[:, :, 2] = z[:, None, 0], z[:, None, 1]
        p = np.zeros((b, 2, _N, _N))
        p[:, :, [0, 0, 2, 2], [0, 2, 0, 2]] = rh.reshape(b, 1, 4)
        p[:, :, 1, 1] = p[:, :, 3, 3] = self.sigma_v0 ** 2
        p[:, 1, 4, 4] = self.sigma_omega0 ** 2
        xv = np.stack([z[:, 2], np.zeros(b)], axis=1)
        pv = np.zeros((b, 2, 2))
        pv[:, 0, 0], pv[:, 1, 1] = rz, self.sigma_v0 ** 2 / 100.0
        return {"x": x, "P": p, "mu": np.broadcast_to(self.mu0, (b, 2)).copy(), "xv": xv, "Pv": pv}

    def predict(self, state: State, dt: F64) -> State:
        dt = np.broadcast_to(np.asarray(dt, float), (len(state["mu"]),))
        cbar, xm, pm = imm_mix(state["x"], state["P"], state["mu"], self.tpm)
        x0, p0 = _cv_predict(xm[:, 0], pm[:, 0], dt, self.q)
        x1, p1 = ct_ekf_predict(xm[:, 1], pm[:, 1], dt, self.q_ct, self.q_omega)
        xv, pv = cv1_predict(state["xv"], state["Pv"], dt, self.q_z)
        return {"x": np.stack([x0, x1], axis=1), "P": np.stack([p0, p1], axis=1), "mu": cbar, "xv": xv, "Pv": pv}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        z, mask = np.asarray(z, float), np.asarray(mask, bool)
        rh, rz = split_r(np.asarray(r, float))
        ok = mask & np.all(np.isfinite(z), axis=1)
        zz = np.where(ok[:, None], z, 0.0)
        rh = np.where(ok[:, None, None], rh, np.eye(2))
        rz = np.where(ok, rz, 1.0)
        xc, pc = imm_combine(state["x"], state["P"], state["mu"])
        nu_h = zz[:, :2] - xc[:, _H]
        s_h = pc[:, _H][:, :, _H] + rh
        nu_z = zz[:, 2] - state["xv"][:, 0]
        s_z = state["Pv"][:, 0, 0] + rz
        nis = np.einsum("bi,bij,bj->b", nu_h, np.linalg.inv(s_h), nu_h) + nu_z ** 2 / s_z
        x, p, mu, _ = imm_update(state["x"], state["P"], state["mu"], zz[:, :2], rh, ok, self.mu_floor)
        xv, pv = cv1_update(state["xv"], state["Pv"], nu_z, s_z, ok)
        return {"x": x, "P": p, "mu": mu, "xv": xv, "Pv": pv}, innovation(nu_h, nu_z, s_h, s_z, nis, ok)

    def observe_velocity(self, state: State, v: F64, r: F64, mask: NDArray[np.bool_]) -> State:
        """Both models updated with the measured horizontal velocity, the mode probabilities with
        its likelihood (:func:`tertiary.filters.imm.imm_velocity_update`); in the CT-EKF the
        velocity is linear in the state, and its correlation with ω corrects the turn rate."""
        return imm_velocity_update(state, v, r, mask, self.mu_floor)

    def combined(self, state: State) -> tuple[F64, F64]:
        """Combined horizontal estimate (B, 5) = [x, vx, y, vy, ω] and its covariance (B, 5, 5)."""
        return imm_combine(state["x"], state["P"], state["mu"])

    def output(self, state: State) -> Output:
        xc, pc = self.combined(state)
        xv, pv = state["xv"], state["Pv"]
        out = np.stack([xc[:, 0], xc[:, 2], xv[:, 0], xc[:, 1], xc[:, 3], xv[:, 1]], axis=1)
        cov = np.zeros((len(xc), 6, 6))
        h = np.array([0, 3, 1, 4])                      # (x, vx, y, vy) → their places in (x y z vx vy vz)
        cov[:, h[:, None], h[None, :]] = pc[:, :4, :4]
        v = np.array([2, 5])
        cov[:, v[:, None], v[None, :]] = pv
        return Output(out, np.einsum("bii->bi", cov), state["mu"].copy(), cov)
