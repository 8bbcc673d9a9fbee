"""Singer manoeuvre model for one coordinate channel, batched over tracks.

State x = [p, v, a]ᵀ (position, rate, acceleration) of one channel (range, azimuth or
elevation). Monograph (seed 000) eqs. (2.49)–(2.63) and the tertiary range channel
(4.46), (4.53)–(4.71):

    Φ(τ) = [[1, τ, τ²/2], [0, 1, τ], [0, 0, 1 − α_ф τ]]      (2.51)/(4.46) as printed
    Q    = diag(0, 0, D_a),   H = [1, 0, 0]

``variant="printed"`` uses Φ₃₃ = 1 − α_ф τ and D_a = σ_m²(2α_ф τ − α_ф²τ²), which keeps the
stationary acceleration variance at σ_m² for the printed AR(1) model; ``variant="exact"`` uses
the exact discretisation Φ₁₃ = (α_ф τ − 1 + e^{−α_ф τ})/α_ф², Φ₂₃ = (1 − e^{−α_ф τ})/α_ф,
Φ₃₃ = e^{−α_ф τ} and D_a = σ_m²(1 − e^{−2α_ф τ}). α_ф is the inverse manoeuvre time constant
(s⁻¹), though the text calls it the time constant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Variant = Literal["printed", "exact"]


def singer_phi(tau: ArrayLike, alpha: ArrayLike, variant: Variant = "printed") -> NDArray[np.float64]:
    """Transition matrices Φ(τ), shape (..., 3, 3), broadcast over τ and α_ф."""
    tau, alpha = np.broadcast_arrays(np.asarray(tau, float), np.asarray(alpha, float))
    phi = np.zeros(tau.shape + (3, 3))
    phi[..., 0, 0] = phi[..., 1, 1] = 1.0
    phi[..., 0, 1] = phi[..., 1, 2] = tau
    if variant == "printed":
        phi[..., 0, 2] = 0.5 * tau * tau
        phi[..., 2, 2] = 1.0 - alpha * tau
    elif variant == "exact":
        at = alpha * tau
        e = np.exp(-at)
        safe = np.where(alpha > 0, alpha, 1.0)
        phi[..., 0, 2] = np.where(alpha > 0, (at - 1.0 + e) / safe**2, 0.5 * tau * tau)
        phi[..., 1, 2] = np.where(alpha > 0, (1.0 - e) / safe, tau)
        phi[..., 2, 2] = e
    else:
        raise ValueError(f"unknown Singer variant {variant!r}; use 'printed' or 'exact'")
    return phi


def singer_q(tau: ArrayLike, alpha: ArrayLike, sigma_m: ArrayLike, variant: Variant = "printed") -> NDArray[np.float64]:
    """Process noise Q = diag(0, 0, D_a), shape (..., 3, 3); D_a keeps Var(a) = σ_m² stationary."""
    tau, alpha, sigma_m = np.broadcast_arrays(*(np.asarray(v, float) for v in (tau, alpha, sigma_m)))
    at = alpha * tau
    d_a = sigma_m**2 * ((2.0 * at - at * at) if variant == "printed" else (1.0 - np.exp(-2.0 * at)))
    q = np.zeros(tau.shape + (3, 3))
    q[..., 2, 2] = d_a
    return q


@dataclass(frozen=True)
class SingerModel:
    """Parameters of one Singer channel: α_ф (s⁻¹), σ_m (channel units / s²) and the variant."""

    alpha: float = 1.0 / 30.0
    sigma_m: float = 2.0
    variant: Variant = "printed"

    def phi(self, tau: ArrayLike) -> NDArray[np.float64]:
        return singer_phi(tau, self.alpha, self.variant)

    def q(self, tau: ArrayLike, sigma_m: ArrayLike | None = None) -> NDArray[np.float64]:
        return singer_q(tau, self.alpha, self.sigma_m if sigma_m is None else sigma_m, self.variant)


def singer_coefficients(tau: ArrayLike, alpha: ArrayLike, sigma_m: ArrayLike, variant: Variant = "printed"
                        ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The non-trivial entries (Φ₁₃, Φ₂₃, Φ₃₃, D_a) of :func:`singer_phi` / :func:`singer_q`, for
    elementwise filters that never build matrices (Φ₁₁ = Φ₂₂ = 1, Φ₁₂ = τ)."""
    tau, alpha, sigma_m = np.broadcast_arrays(*(np.asarray(v, float) for v in (tau, alpha, sigma_m)))
    at = alpha * tau
    if variant == "printed":
        return 0.5 * tau * tau, tau, 1.0 - at, sigma_m**2 * (2.0 * at - at * at)
    if variant != "exact":
        raise ValueError(f"unknown Singer variant {variant!r}; use 'printed' or 'exact'")
    e = np.exp(-at)
    safe = np.where(alpha > 0, alpha, 1.0)
    p13 = np.where(alpha > 0, (at - 1.0 + e) / safe**2, 0.5 * tau * tau)
    p23 = np.where(alpha > 0, (1.0 - e) / safe, tau)
    return p13, p23, e, sigma_m**2 * (1.0 - np.exp(-2.0 * at))


def predict_elementwise(x: NDArray[np.float64], p: NDArray[np.float64], tau: NDArray[np.float64],
                        coeffs: tuple[NDArray[np.float64], ...]) -> None:
    """In-place Singer prediction x ← Φx, P ← ΦPΦᵀ + Q on component arrays.

    ``x`` is (3, ...) = (pos, rate, acc); ``p`` is (6, ...) = (P00, P01, P02, P11, P12, P22) of
    the symmetric covariance; ``coeffs`` from :func:`singer_coefficients`. Same result as the
    matrix form, without building 3×3 matrices per track.
    """
    a, b, f, q = coeffs
    x[0] += tau * x[1] + a * x[2]
    x[1] += b * x[2]
    x[2] *= f
    p00, p01, p02, p11, p12, p22 = p
    a0 = p00 + tau * p01 + a * p02          # (P Φ₀ᵀ)
    a1 = p01 + tau * p11 + a * p12
    a2 = p02 + tau * p12 + a * p22
    b1 = p11 + b * p12                      # (P Φ₁ᵀ)
    b2 = p12 + b * p22
    b0 = p01 + b * p02
    p[0] = a0 + tau * a1 + a * a2
    p[1] = b0 + tau * b1 + a * b2
    p[2] = f * a2
    p[3] = b1 + b * b2
    p[4] = f * b2
    p[5] = f * f * p22 + q


def update_elementwise(x: NDArray[np.float64], p: NDArray[np.float64], nu: NDArray[np.float64],
                       r: NDArray[np.float64]) -> NDArray[np.float64]:
    """In-place scalar-measurement update with H = [1, 0, 0]; returns S = P00 + R.

    K = P Hᵀ / S, x ← x + K ν, P ← P − K S Kᵀ (monograph (2.10)–(2.14), seed (4.58)–(4.60)).
    Where ``nu`` is NaN (no measurement) nothing changes.
    """
    s = p[0] + r
    ok = np.isfinite(nu)
    g = np.where(ok, 1.0 / s, 0.0)
    nu0 = np.where(ok, nu, 0.0)
    c0, c1, c2 = p[0].copy(), p[1].copy(), p[2].copy()
    x[0] += c0 * g * nu0
    x[1] += c1 * g * nu0
    x[2] += c2 * g * nu0
    p[0] -= c0 * c0 * g
    p[1] -= c0 * c1 * g
    p[2] -= c0 * c2 * g
    p[3] -= c1 * c1 * g
    p[4] -= c1 * c2 * g
    p[5] -= c2 * c2 * g
    return s
