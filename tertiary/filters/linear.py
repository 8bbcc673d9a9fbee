"""The linear filter family of monograph chapter 2, batched over tracks and decoupled per axis:
the constant-velocity and fixed-gain filters here, the manoeuvring-target ones (Singer, adaptive
Singer, two-model) in :mod:`.manoeuvring`, their shared layout and kernels in :mod:`.axes`.

Every filter here treats the three Cartesian axes (x, y, z = E, N, U of the system frame) of a
fused plot as independent scalar-measurement channels — the monograph's single-channel filters
(range, azimuth, elevation) applied to each coordinate — with measurement variance ``r[:, axis]``.
All arithmetic is elementwise over arrays of shape (B, 3) (tracks × axes): no Python loop over
tracks and no per-track matrices.

State layout (track axis first, as :mod:`tertiary.filters.base` requires):

``x``  (B, 3, n)  per-axis state, n = 2 ([p, v]) or 3 ([p, v, a])
``P``  (B, 3, m)  per-axis covariance, packed upper triangle: (P00, P01, P11) for n = 2,
                  (P00, P01, P02, P11, P12, P22) for n = 3 (:func:`full_covariance` unpacks)

plus filter-specific keys documented on each class. Internally the component axis is moved to
the front — (n, B, 3) contiguous arrays — so each component is one flat array (see
:func:`tertiary.filters.singer.predict_elementwise`).

Filters (registry names):

``cv``                constant velocity (2.17)–(2.31)             :class:`CVFilter`
``alpha_beta``        α-β (2.32)–(2.36), (2.47)–(2.48)            :class:`AlphaBetaFilter`
``alpha_beta_gamma``  α-β-γ (2.37)–(2.46)                         :class:`AlphaBetaGammaFilter`
``singer``            Singer (2.49)–(2.63) / seed (4.46)           :class:`~.manoeuvring.SingerFilter`
``adaptive``          hybrid adaptive Singer (2.64)–(2.91)        :class:`~.manoeuvring.AdaptiveSingerFilter`
``two_model``         random-structure two-model (2.92)–(2.137)   :class:`~.manoeuvring.TwoModelFilter`

Common conventions:

* ``init`` starts from the first plot: position = plot (variance r), velocity 0 with variance
  ``v0_sigma**2`` (default (300 m/s)²), acceleration 0 with variance σ_m² (Singer channels).
  The init plot produces no innovation.
* ``predict`` never modifies its input; ``update`` keeps the prediction (x⁺ = x⁻, P⁺ = P⁻,
  "memory mode" §2.1) where ``mask`` is False. Measurements and variances of masked-out tracks
  are ignored (they may be NaN).
* :class:`~tertiary.filters.base.Innovation`: ν = z − Hx⁻ and S = HP⁻Hᵀ + R per axis, NaN for
  tracks without a plot; NIS = Σ_axes ν²/S.
* Per-axis parameters (q, σ_m, …) accept a scalar (all axes) or a 3-sequence (x, y, z).
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.filters.axes import (PAIRS, PerAxis, axis_param, components, gain_update, init_state,
                                                    innovation, mask3, masked_innovation, masked_variance, output6,
                                                    per_axis, predict2, state_layout, tau3, update2)
from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.filters.singer import predict_elementwise

__all__ = ["CVFilter", "AlphaBetaFilter", "AlphaBetaGammaFilter", "kalata_alpha_beta", "kalata_beta", "steady_state_abg",
           "abg_gamma"]


# ----------------------------------------------------------------------------- α-β(-γ) gain design

def kalata_beta(alpha: ArrayLike) -> F64:
    """β = 2(2 − α) − 4√(1 − α): Kalata's relation between the steady-state gains of the Kalman
    filter for the CV model with piecewise-constant white acceleration (Q = σ_a²ΓΓᵀ,
    Γ = [τ²/2, τ]ᵀ); printed convention v⁺ = v⁻ + (β/τ)ν. It holds for α-β-γ too (WPA model)."""
    alpha = np.asarray(alpha, float)
    return 2.0 * (2.0 - alpha) - 4.0 * np.sqrt(1.0 - alpha)


def abg_gamma(alpha: ArrayLike, beta: ArrayLike) -> F64:
    """γ = β²/(2α), printed convention a⁺ = a⁻ + (γ/τ²)ν: steady-state Kalman gains of the
    constant-acceleration model with acceleration-increment noise Γ = [τ²/2, τ, 1]ᵀ."""
    return np.asarray(beta, float) ** 2 / (2.0 * np.asarray(alpha, float))


def kalata_alpha_beta(lam: ArrayLike) -> tuple[F64, F64]:
    """Steady-state (α, β) of the CV Kalman filter for tracking index Λ = σ_a τ²/σ_r (Kalata 1984):
    Λ² = β²/(1 − α), β = 2(2 − α) − 4√(1 − α); printed convention."""
    lam = np.asarray(lam, float)
    root = np.sqrt(lam * lam + 8.0 * lam)
    alpha = -(lam * lam + 8.0 * lam - (lam + 4.0) * root) / 8.0
    beta = (lam * lam + 4.0 * lam - lam * root) / 4.0
    return alpha, beta


def steady_state_abg(lam: ArrayLike, iterations: int = 12) -> tuple[F64, F64, F64]:
    """Steady-state (α, β, γ) of the constant-acceleration Kalman filter with acceleration-increment
    noise (Γ = [τ²/2, τ, 1]ᵀ, std σ_j per step) for Λ = σ_j τ²/σ_r, printed convention.

    The relations Λ² = γ²/(1 − α), β = 2(2 − α) − 4√(1 − α), γ = β²/(2α) (all checked against the
    Riccati recursion) reduce, with s = √(1 − α), to the cubic 2s³ − (6 − Λ)s² + (6 + Λ)s − 2 = 0,
    which is increasing on (0, 1) with a single root there; solved by safeguarded Newton."""
    lam = np.asarray(lam, float)
    lo, hi = np.zeros_like(lam), np.ones_like(lam)
    s = np.full_like(lam, 0.5)
    for _ in range(iterations):
        f = ((2.0 * s - (6.0 - lam)) * s + (6.0 + lam)) * s - 2.0
        lo = np.where(f < 0, s, lo)
        hi = np.where(f >= 0, s, hi)
        fp = 6.0 * (1.0 - s) ** 2 + lam * (2.0 * s + 1.0)
        step = s - f / fp
        s = np.where((step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
    alpha = 1.0 - s * s
    beta = 2.0 * (1.0 - s) ** 2
    gamma = 2.0 * (1.0 - s) ** 3 / (1.0 + s)
    return alpha, beta, gamma


# ----------------------------------------------------------------------------- CV

@register
@dataclass(frozen=True)
class CVFilter(TrackFilter):
    """Constant-velocity Kalman filter per axis (2.17)–(2.31): x = [p, v], Φ = [[1, τ], [0, 1]],
    H = [1, 0], R = r[:, axis].

    Process noise (``noise``):

    * ``"cwna"`` (default): continuous white-noise acceleration of spectral density ``q``
      (m²/s³, default 1), Q = q[[τ³/3, τ²/2], [τ²/2, τ]] — consistent for irregular τ and gives the
      velocity a steady-state gain.
    * ``"printed"``: the text's Q = diag(D_Dx, 0) (2.18)–(2.19) with D_Dx = ``q`` (m² per step).
      The velocity is then an unforced constant: P₂₂ → 0 and K₂ → 0, so this
      variant cannot follow speed changes; kept for reproduction only.
    """

    name: ClassVar[str] = "cv"
    q: PerAxis = 1.0
    noise: Literal["cwna", "printed"] = "cwna"
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "_q", per_axis(self.q, "q"))
        if self.noise not in ("cwna", "printed"):
            raise ValueError(f"unknown noise {self.noise!r}; use 'cwna' or 'printed'")

    def process_noise(self, tau: F64) -> tuple[F64, F64, F64]:
        """Packed Q (q00, q01, q11), each broadcast to (B, 3)."""
        q = axis_param(self._q, len(tau))
        if self.noise == "printed":
            return q + np.zeros_like(tau), 0.0, 0.0
        q1 = q * tau
        q2 = q1 * tau
        return q2 * tau / 3.0, 0.5 * q2, q1

    def init(self, z: F64, r: F64) -> State:
        x, p = init_state(z, r, 2, self.v0_sigma**2)
        return {"x": x, "P": p}

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = components(state["x"]), components(state["P"]), tau3(dt)
        predict2(x, p, tau, 1.0, self.process_noise(tau))
        return {"x": state_layout(x), "P": state_layout(p)}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p, m3 = components(state["x"]), components(state["P"]), mask3(mask)
        nu = masked_innovation(z, x[0], m3)
        s = update2(x, p, nu, masked_variance(r, m3))
        return {"x": state_layout(x), "P": state_layout(p)}, innovation(nu, s)

    def output(self, state: State) -> Output:
        return output6(state["x"], state["P"])


# ----------------------------------------------------------------------------- α-β, α-β-γ

class _FixedGain(TrackFilter):
    """Shared α-β / α-β-γ machinery: frozen-gain correction, Joseph-form covariance."""

    n: ClassVar[int]

    @abstractmethod
    def _gains(self, tau: F64, r: F64) -> list[F64]:
        """The filter's gains per state component for steps ``tau`` and variances ``r``."""

    @abstractmethod
    def _q(self, tau: F64) -> tuple[F64, ...]:
        """The design-model process noise used to propagate the error covariance."""

    def init(self, z: F64, r: F64) -> State:
        x, p = init_state(z, r, self.n, self.v0_sigma**2, 0.0 if self.n == 3 else None)
        if self.n == 3:
            p[..., 5] = self.a0_sigma**2
        return {"x": x, "P": p, "tau": np.zeros(len(x))}

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = components(state["x"]), components(state["P"]), tau3(dt)
        q = self._q(tau)
        if self.n == 2:
            predict2(x, p, tau, 1.0, q)
        else:
            predict_elementwise(x, p, tau, (0.5 * tau * tau, tau, 1.0, 0.0))
            for m in range(6):
                p[m] += q[m]
        return {"x": state_layout(x), "P": state_layout(p), "tau": np.asarray(dt, float).copy()}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p = components(state["x"]), components(state["P"])
        tau = tau3(state["tau"])
        m3 = mask3(mask)
        rr = masked_variance(r, m3)
        nu = masked_innovation(z, x[0], m3)
        s = gain_update(x, p, nu, rr, self._gains(tau, rr))
        return {"x": state_layout(x), "P": state_layout(p), "tau": state["tau"].copy()}, innovation(nu, s)

    def output(self, state: State) -> Output:
        return output6(state["x"], state["P"])


def _per_tau(g: F64, tau: F64, power: int) -> F64:
    """g / τ^power, 0 where τ ≤ 0 (an update straight after init: position gain only)."""
    safe = np.where(tau > 0, tau, 1.0)
    return np.where(tau > 0, g / safe**power, 0.0)


@register
@dataclass(frozen=True)
class AlphaBetaFilter(_FixedGain):
    """α-β filter per axis (2.32)–(2.36), (2.47)–(2.48): x⁻ = Φx⁺ (CV), ν = z − p⁻,
    p⁺ = p⁻ + αν, v⁺ = v⁻ + (β/τ)ν — a Kalman recursion with the frozen gain K = [α, β/τ]ᵀ.

    The text gives no gain values and no k-dependent schedule: the gains are fixed.

    * ``gains="fixed"`` (default): α = ``alpha`` (0.5), β = ``beta`` or, if None, Kalata's
      β = 2(2 − α) − 4√(1 − α) (:func:`kalata_beta`) — i.e. the steady-state Kalman gains of the
      CV model for which that α is optimal.
    * ``gains="steady_state"``: each step uses the steady-state Kalman gain for that step's
      tracking index Λ = σ_a τ²/√r (:func:`kalata_alpha_beta`), so the gain follows irregular τ
      and plot accuracy; ``alpha``/``beta`` are ignored.

    Covariance: the text propagates none. ``P`` is the error covariance of this (generally
    sub-optimal) linear filter under the design model — CV with piecewise-constant white
    acceleration, Q = σ_a²[[τ⁴/4, τ³/2], [τ³/2, τ²]] (σ_a = ``sigma_a``, m/s²) and R = r:
    P⁻ = ΦP⁺Φᵀ + Q, P⁺ = (I − KH)P⁻(I − KH)ᵀ + KRKᵀ. With steady-state gains it converges to the
    Kalman filter's P, so ``Output.var`` is meaningful; it does not affect the estimate.

    State keys: ``x`` (B, 3, 2), ``P`` (B, 3, 3) packed, ``tau`` (B,) the last prediction
    interval (for β/τ; 0 after init).
    """

    name: ClassVar[str] = "alpha_beta"
    n: ClassVar[int] = 2
    alpha: float = 0.5
    beta: float | None = None
    gains: Literal["fixed", "steady_state"] = "fixed"
    sigma_a: PerAxis = 2.0
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        if self.gains not in ("fixed", "steady_state"):
            raise ValueError(f"unknown gains {self.gains!r}; use 'fixed' or 'steady_state'")
        beta = float(kalata_beta(self.alpha)) if self.beta is None else float(self.beta)
        if not (0 < self.alpha <= 1 and 0 < beta < 4 - 2 * self.alpha):
            raise ValueError(f"α-β gains outside the stable region: α={self.alpha}, β={beta}")
        object.__setattr__(self, "_beta", beta)
        object.__setattr__(self, "_sa", per_axis(self.sigma_a, "sigma_a"))

    def _q(self, tau: F64) -> tuple[F64, ...]:
        t2 = tau * tau
        v = axis_param(self._sa**2, len(tau)) * t2
        return 0.25 * v * t2, 0.5 * v * tau, v

    def _gains(self, tau: F64, r: F64) -> list[F64]:
        if self.gains == "steady_state":
            a, b = kalata_alpha_beta(axis_param(self._sa, len(tau)) * tau * tau / np.sqrt(r))
        else:
            a, b = np.full_like(r, self.alpha), np.full_like(r, self._beta)
        return [a, _per_tau(b, tau, 1)]


@register
@dataclass(frozen=True)
class AlphaBetaGammaFilter(_FixedGain):
    """α-β-γ filter per axis (2.37)–(2.46): constant-acceleration Φ, frozen gain
    K = [α, β/τ, γ/τ²]ᵀ (printed convention (2.39); other texts use 2γ/τ² or γ/(2τ²)).

    * ``gains="fixed"`` (default): α = ``alpha`` (0.5); β = ``beta`` or Kalata's relation;
      γ = ``gamma`` or γ = β²/(2α) (:func:`abg_gamma`) — the steady-state Kalman gains of the CA
      model with acceleration-increment noise for which that α is optimal.
    * ``gains="steady_state"``: per step, the steady-state gains for Λ = σ_j τ²/√r
      (:func:`steady_state_abg`).

    Covariance as for :class:`AlphaBetaFilter`, with the design model's Q = σ_j²ΓΓᵀ,
    Γ = [τ²/2, τ, 1]ᵀ (σ_j = ``sigma_j``, m/s² of acceleration change per step). Initial
    acceleration 0 with variance ``a0_sigma**2``.

    State keys: ``x`` (B, 3, 3), ``P`` (B, 3, 6) packed, ``tau`` (B,).
    """

    name: ClassVar[str] = "alpha_beta_gamma"
    n: ClassVar[int] = 3
    alpha: float = 0.5
    beta: float | None = None
    gamma: float | None = None
    gains: Literal["fixed", "steady_state"] = "fixed"
    sigma_j: PerAxis = 0.5
    v0_sigma: float = 300.0
    a0_sigma: float = 2.0

    def __post_init__(self) -> None:
        if self.gains not in ("fixed", "steady_state"):
            raise ValueError(f"unknown gains {self.gains!r}; use 'fixed' or 'steady_state'")
        if not 0 < self.alpha <= 1:
            raise ValueError(f"α must be in (0, 1], got {self.alpha}")
        beta = float(kalata_beta(self.alpha)) if self.beta is None else float(self.beta)
        gamma = float(abg_gamma(self.alpha, beta)) if self.gamma is None else float(self.gamma)
        object.__setattr__(self, "_beta", beta)
        object.__setattr__(self, "_gamma", gamma)
        object.__setattr__(self, "_sj", per_axis(self.sigma_j, "sigma_j"))

    def _q(self, tau: F64) -> tuple[F64, ...]:
        s = axis_param(self._sj, len(tau))
        g = (0.5 * s * tau * tau, s * tau, s + np.zeros_like(tau))
        return tuple(g[i] * g[j] for i, j in PAIRS[3])

    def _gains(self, tau: F64, r: F64) -> list[F64]:
        if self.gains == "steady_state":
            a, b, g = steady_state_abg(axis_param(self._sj, len(tau)) * tau * tau / np.sqrt(r))
        else:
            a, b, g = (np.full_like(r, v) for v in (self.alpha, self._beta, self._gamma))
        return [a, _per_tau(b, tau, 1), _per_tau(g, tau, 2)]
