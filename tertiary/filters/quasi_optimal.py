"""Quasi-optimal secondary-processing filter — seed 001 (Azizov, Zaikin, Kalinichenko, Kotov).

State Λ = [x, y, z] (position only, random walk Φ = I, increments with variances
D = diag(D_x, D_y, D_z) per interval), measurements of azimuth β = atan2(Δy, Δx) (from +X towards
+Y), elevation ε = atan2(z − z₀, ρ) and slant range R. One Newton step of the
measurement log-likelihood F(Λ) = −½ rᵀ K_q⁻¹ r, r = Q̂ − q(Λ), from the predicted point, with
the covariance in information form:

    K_э = K_ps + D·Δt/t_ref                      (34) corrected: from the *posterior*
    G   = Wᵀ K_q⁻¹ r                             (11), W = ∂q/∂Λ (15) with corrected row ε (17)
    J   = Wᵀ K_q⁻¹ W − Σ_j (K_q⁻¹ r)_j ∇²q_j     observed information = −∇²F (39) with the
                                                 bracket and sign corrected (rows 6–7)
    K_ps = (K_э⁻¹ + J)⁻¹,   Λ̂ = Λ_э + K_ps G     (10), (32)–(33)

Variants (``variant=``):

* ``"newton"`` (default) — the corrected algorithm above; if K_э⁻¹ + J is not positive definite
  (large residuals) the track falls back to Gauss–Newton for that step.
* ``"gauss_newton"`` — J = Wᵀ K_q⁻¹ W (expected Fisher information): algebraically the EKF.
* ``"printed"`` — the as-printed derivatives, for comparison only: the ε row of W as printed in
  (17) (∂ε/∂x = −2Δx z²/(ρ⁴ + z²ρ²), ∂ε/∂y likewise, ∂ε/∂z = 0 — the correct x, y entries
  times 2z/ρ) and the transposed gradient of (26)–(29), G = W K_q⁻¹ r; the information is the
  Gauss–Newton one built from the printed W (the paper prints no second derivatives). The
  printed *sign pairing* of (39) with (10) (K_ps = [K_э⁻¹ − H_λ]⁻¹, which subtracts information
  and yields a non-positive-definite "covariance") is not a filter option at all; the test suite
  demonstrates it on a constructed case.

Fused plots: the radar is the processing centre (``radar`` = frame origin by default). Each ENU
plot z with variances r becomes Q̂ = q(z) with K_q = W(z) diag(r) W(z)ᵀ (full 3×3; the paper's
K_q is diagonal for independent β, ε, R meters). Process noise: the paper's D is per interval;
here ``b`` are the per-axis increment σ (m) over ``t_ref`` seconds, D = b²·Δt/t_ref, so the
default b = (5, 5, 1) m at 1 s is the paper's default scenario. The filter has no velocity:
:meth:`output` reports velocity 0 with infinite variance.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.core.geo import sandwich

Variant = Literal["newton", "gauss_newton", "printed"]


def _wrap(a: F64) -> F64:
    return np.mod(a + np.pi, 2.0 * np.pi) - np.pi


def _parts(lam: ArrayLike, radar: ArrayLike) -> tuple[F64, ...]:
    d = np.asarray(lam, float) - np.asarray(radar, float)
    dx, dy, z = d[..., 0], d[..., 1], d[..., 2]
    rho2 = dx * dx + dy * dy
    r2 = rho2 + z * z
    return dx, dy, z, rho2, np.sqrt(rho2), r2, np.sqrt(r2)


def primary(lam: ArrayLike, radar: ArrayLike = (0.0, 0.0, 0.0)) -> F64:
    """q(Λ) = (β, ε, R) (..., 3), (1)–(3)/(8) with atan2."""
    dx, dy, z, _, rho, _, r = _parts(lam, radar)
    return np.stack([np.arctan2(dy, dx), np.arctan2(z, rho), r], axis=-1)


def jacobian(lam: ArrayLike, radar: ArrayLike = (0.0, 0.0, 0.0), printed: bool = False) -> F64:
    """W = ∂(β, ε, R)/∂(x, y, z) (..., 3, 3) (``printed=True``: the ε row of (17))."""
    dx, dy, z, rho2, rho, r2, r = _parts(lam, radar)
    w = np.zeros(dx.shape + (3, 3))
    w[..., 0, 0] = -dy / rho2
    w[..., 0, 1] = dx / rho2
    if printed:
        den = rho2 * rho2 + z * z * rho2
        w[..., 1, 0] = -2.0 * dx * z * z / den
        w[..., 1, 1] = -2.0 * dy * z * z / den
    else:
        w[..., 1, 0] = -dx * z / (rho * r2)
        w[..., 1, 1] = -dy * z / (rho * r2)
        w[..., 1, 2] = rho / r2
    w[..., 2, 0] = dx / r
    w[..., 2, 1] = dy / r
    w[..., 2, 2] = z / r
    return w


def hessians(lam: ArrayLike, radar: ArrayLike = (0.0, 0.0, 0.0)) -> F64:
    """Second derivatives ∇²β, ∇²ε, ∇²R (..., 3, 3, 3) (index: quantity, λ_i, λ_k)."""
    dx, dy, z, rho2, rho, r2, r = _parts(lam, radar)
    h = np.zeros(dx.shape + (3, 3, 3))
    rho4 = rho2 * rho2
    h[..., 0, 0, 0] = 2.0 * dx * dy / rho4
    h[..., 0, 0, 1] = h[..., 0, 1, 0] = (dy * dy - dx * dx) / rho4
    h[..., 0, 1, 1] = -2.0 * dx * dy / rho4
    c = 3.0 * rho2 + z * z
    den = rho ** 3 * r2 * r2
    h[..., 1, 0, 0] = z * (dx * dx * c - rho2 * r2) / den
    h[..., 1, 1, 1] = z * (dy * dy * c - rho2 * r2) / den
    h[..., 1, 0, 1] = h[..., 1, 1, 0] = z * dx * dy * c / den
    h[..., 1, 0, 2] = h[..., 1, 2, 0] = -dx * (rho2 - z * z) / (rho * r2 * r2)
    h[..., 1, 1, 2] = h[..., 1, 2, 1] = -dy * (rho2 - z * z) / (rho * r2 * r2)
    h[..., 1, 2, 2] = -2.0 * z * rho / (r2 * r2)
    r3 = r ** 3
    h[..., 2, 0, 0] = (dy * dy + z * z) / r3
    h[..., 2, 1, 1] = (dx * dx + z * z) / r3
    h[..., 2, 2, 2] = rho2 / r3
    h[..., 2, 0, 1] = h[..., 2, 1, 0] = -dx * dy / r3
    h[..., 2, 0, 2] = h[..., 2, 2, 0] = -dx * z / r3
    h[..., 2, 1, 2] = h[..., 2, 2, 1] = -dy * z / r3
    return h


def enu_to_primary(z: F64, r: F64, radar: ArrayLike = (0.0, 0.0, 0.0)) -> tuple[F64, F64]:
    """ENU plots z (B, 3) with variances r (B, 3) or covariance (B, 3, 3) → Q̂ = (β, ε, R) and
    K_q = W R Wᵀ (B, 3, 3) with W at the plot."""
    r = np.asarray(r, float)
    rf = r if r.ndim == 3 else r[:, :, None] * np.eye(3)
    return primary(z, radar), sandwich(jacobian(z, radar), rf)


def gradient_information(lam: F64, q_hat: F64, kq_inv: F64, radar: ArrayLike = (0.0, 0.0, 0.0),
                         variant: Variant = "newton") -> tuple[F64, F64]:
    """Gradient G (B, 3) and information J (B, 3, 3) of the log-likelihood at Λ (§1.5 steps 2–5)."""
    res = q_hat - primary(lam, radar)
    res[:, 0] = _wrap(res[:, 0])
    w = np.einsum("bij,bj->bi", kq_inv, res)                 # (25)
    wm = jacobian(lam, radar, printed=(variant == "printed"))
    if variant == "printed":
        g = np.einsum("bji,bi->bj", wm, w)                   # (26)–(29): W K_q⁻¹ r (transposed)
    else:
        g = np.einsum("bji,bj->bi", wm, w)                   # (11): Wᵀ K_q⁻¹ r
    j = np.einsum("bji,bjk,bkl->bil", wm, kq_inv, wm)        # Wᵀ K_q⁻¹ W
    if variant == "newton":
        j = j - np.einsum("bj,bjik->bik", w, hessians(lam, radar))
    return g, 0.5 * (j + np.swapaxes(j, -1, -2))


@register
class QuasiOptimal(TrackFilter):
    """Seed 001 quasi-optimal (Newton / information-form) position filter on fused ENU plots.

    Parameters:
        b:       per-axis increment σ (m) over ``t_ref`` seconds (paper's B = diag(b)), default (5, 5, 1)
        t_ref:   interval the increments refer to (s), default 1
        variant: "newton" (corrected, default), "gauss_newton" (= EKF) or "printed" (as-printed
                 derivatives and gradient, for comparison)
        radar:   radar / processing-centre position in the frame (m), default origin
    """

    name = "quasi_optimal"
    full_r = True          # the primary-parameter conversion takes the full 3×3 plot covariance

    def __init__(self, b: Sequence[float] = (5.0, 5.0, 1.0), t_ref: float = 1.0, variant: Variant = "newton",
                 radar: Sequence[float] = (0.0, 0.0, 0.0)):
        if variant not in ("newton", "gauss_newton", "printed"):
            raise ValueError(f"unknown variant {variant!r}")
        self.d_rate = np.asarray(b, float) ** 2 / float(t_ref)
        self.variant: Variant = variant
        self.radar = np.asarray(radar, float)

    def init(self, z: F64, r: F64) -> State:
        """Λ from the first plot; K_ps⁽⁰⁾ = (Wᵀ K_q⁻¹ W)⁻¹ there, which is the plot covariance."""
        z = np.asarray(z, float)
        r = np.asarray(r, float)
        p = r.copy() if r.ndim == 3 else r[:, :, None] * np.eye(3)
        return {"x": z.copy(), "P": p, "n_fallback": np.zeros(len(z), np.int64)}

    def predict(self, state: State, dt: F64) -> State:
        dt = np.broadcast_to(np.asarray(dt, float), (len(state["x"]),))
        return {"x": state["x"].copy(), "P": state["P"] + dt[:, None, None] * np.diag(self.d_rate),
                "n_fallback": state["n_fallback"]}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        lam, kp = state["x"], state["P"]
        z, r = np.asarray(z, float), np.asarray(r, float)
        ok = np.asarray(mask, bool) & np.all(np.isfinite(z), axis=1)
        b = len(lam)
        zs = np.where(ok[:, None], z, lam + 1.0)
        rs = np.where(ok[:, None], r, 1.0) if r.ndim == 2 else np.where(ok[:, None, None], r, np.eye(3))
        q_hat, kq = enu_to_primary(zs, rs, self.radar)
        kq_inv = np.linalg.inv(kq)
        kp_inv = np.linalg.inv(kp)
        g, j = gradient_information(lam, q_hat, kq_inv, self.radar, self.variant)
        info = kp_inv + j
        fallback = np.zeros(b, bool)
        if self.variant == "newton":
            fallback = np.linalg.eigvalsh(info)[:, 0] <= 0
            if fallback.any():
                _, jg = gradient_information(lam[fallback], q_hat[fallback], kq_inv[fallback], self.radar,
                                             "gauss_newton")
                info[fallback] = kp_inv[fallback] + jg
        kps = np.linalg.inv(info)
        kps = 0.5 * (kps + np.swapaxes(kps, -1, -2))
        xu = lam + np.einsum("bij,bj->bi", kps, g)
        # NIS in the primary-parameter space, rᵀ (W K_э Wᵀ + K_q)⁻¹ r
        res = q_hat - primary(lam, self.radar)
        res[:, 0] = _wrap(res[:, 0])
        wm = jacobian(lam, self.radar, printed=(self.variant == "printed"))
        s = sandwich(wm, kp) + kq
        nis = np.einsum("bi,bij,bj->b", res, np.linalg.inv(s), res)
        rdiag = r if r.ndim == 2 else np.einsum("bii->bi", r)
        bad = ~ok
        innov = Innovation(np.where(bad[:, None], np.nan, z - lam),
                           np.where(bad[:, None], np.nan, np.einsum("bii->bi", kp) + rdiag),
                           np.where(bad, np.nan, nis))
        new = {"x": np.where(ok[:, None], xu, lam), "P": np.where(ok[:, None, None], kps, kp),
               "n_fallback": state["n_fallback"] + (fallback & ok)}
        return new, innov

    def output(self, state: State) -> Output:
        b = len(state["x"])
        x = np.concatenate([state["x"], np.zeros((b, 3))], axis=1)
        var = np.concatenate([np.einsum("bii->bi", state["P"]), np.full((b, 3), np.inf)], axis=1)
        return Output(x, var)
