"""The linear filter family of monograph chapter 2, batched over tracks and decoupled per axis.

Every filter here treats the three Cartesian axes (x, y, z = E, N, U of the system frame) of a
fused plot as independent scalar-measurement channels — the monograph's single-channel filters
(range, azimuth, elevation) applied to each coordinate — with measurement variance ``r[:, axis]``.
All arithmetic is elementwise over arrays of shape (B, 3) (tracks × axes): no Python loop over
tracks and no per-track matrices.

State layout (track axis first, as :mod:`tertiary.stages.tracking.filters.base` requires):

``x``  (B, 3, n)  per-axis state, n = 2 ([p, v]) or 3 ([p, v, a])
``P``  (B, 3, m)  per-axis covariance, packed upper triangle: (P00, P01, P11) for n = 2,
                  (P00, P01, P02, P11, P12, P22) for n = 3 (:func:`full_covariance` unpacks)

plus filter-specific keys documented on each class. Internally the component axis is moved to
the front — (n, B, 3) contiguous arrays — so each component is one flat array (see
:func:`tertiary.stages.tracking.filters.singer.predict_elementwise`).

Filters (registry names):

``cv``                constant velocity (2.17)–(2.31)             :class:`CVFilter`
``alpha_beta``        α-β (2.32)–(2.36), (2.47)–(2.48)            :class:`AlphaBetaFilter`
``alpha_beta_gamma``  α-β-γ (2.37)–(2.46)                         :class:`AlphaBetaGammaFilter`
``singer``            Singer (2.49)–(2.63) / seed (4.46)           :class:`SingerFilter`
``adaptive``          hybrid adaptive Singer (2.64)–(2.91)        :class:`AdaptiveSingerFilter`
``two_model``         random-structure two-model (2.92)–(2.137)   :class:`TwoModelFilter`

Common conventions:

* ``init`` starts from the first plot: position = plot (variance r), velocity 0 with variance
  ``v0_sigma**2`` (default (300 m/s)²), acceleration 0 with variance σ_m² (Singer channels).
  The init plot produces no innovation.
* ``predict`` never modifies its input; ``update`` keeps the prediction (x⁺ = x⁻, P⁺ = P⁻,
  "memory mode" §2.1) where ``mask`` is False. Measurements and variances of masked-out tracks
  are ignored (they may be NaN).
* :class:`~tertiary.stages.tracking.filters.base.Innovation`: ν = z − Hx⁻ and S = HP⁻Hᵀ + R per axis, NaN for
  tracks without a plot; NIS = Σ_axes ν²/S.
* Per-axis parameters (q, σ_m, …) accept a scalar (all axes) or a 3-sequence (x, y, z).
"""

from __future__ import annotations

from abc import abstractmethod

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.stages.tracking.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.stages.tracking.filters.singer import (Variant, predict_elementwise, singer_coefficients, update_elementwise)

__all__ = [
    "CVFilter", "AlphaBetaFilter", "AlphaBetaGammaFilter", "SingerFilter", "AdaptiveSingerFilter",
    "TwoModelFilter", "full_covariance", "kalata_alpha_beta", "kalata_beta", "steady_state_abg",
    "abg_gamma", "two_model_weights",
]

PerAxis = float | Sequence[float]

#: packed upper-triangle index pairs of a symmetric n×n matrix (row-major)
PAIRS = {2: ((0, 0), (0, 1), (1, 1)), 3: ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))}


# ----------------------------------------------------------------------------- layout helpers

def full_covariance(p: ArrayLike) -> F64:
    """Unpack a packed covariance (..., 3) or (..., 6) into full matrices (..., n, n)."""
    p = np.asarray(p, float)
    n = {3: 2, 6: 3}[p.shape[-1]]
    out = np.empty(p.shape[:-1] + (n, n))
    for m, (i, j) in enumerate(PAIRS[n]):
        out[..., i, j] = out[..., j, i] = p[..., m]
    return out


def _axes(value: PerAxis, name: str, *, positive: bool = False) -> F64:
    a = np.broadcast_to(np.asarray(value, float), (3,)).copy()
    if not np.all(np.isfinite(a)) or np.any(a < 0) or (positive and np.any(a <= 0)):
        raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'} per axis, got {value!r}")
    return a


def _bc(v: F64, b: int) -> float | F64:
    """A per-axis parameter (3,) for (B, 3) arithmetic: a scalar when the axes agree, else a
    contiguous (B, 3) tile (broadcasting a (3,) row runs numpy's slow 3-element inner loop)."""
    return float(v[0]) if v[0] == v[1] == v[2] else np.tile(v, (b, 1))


def _comp(a: NDArray) -> NDArray:
    """State array (B, 3, n) → a fresh contiguous component-first copy (n, B, 3)."""
    return a.transpose(2, 0, 1).copy()


def _store(a: NDArray) -> NDArray:
    """Component-first (n, B, 3) → state layout (B, 3, n) (a view)."""
    return a.transpose(1, 2, 0)


def _tau(dt: ArrayLike) -> F64:
    """Per-track intervals (B,) → contiguous (B, 3): same-shape elementwise operations are several
    times faster than broadcasting a (B, 1) column."""
    dt = np.asarray(dt, float).reshape(-1, 1)
    return np.repeat(dt, 3, axis=1)


def _mask3(mask: ArrayLike) -> NDArray[np.bool_]:
    """Plot mask (B,) → contiguous (B, 3)."""
    return np.repeat(np.asarray(mask, bool).reshape(-1, 1), 3, axis=1)


def _nu(z: F64, x0: F64, m3: NDArray[np.bool_]) -> F64:
    """Innovation ν (B, 3), NaN where the track has no plot (``m3`` from :func:`_mask3`)."""
    return np.where(m3, np.asarray(z, float) - x0, np.nan)


def _r(r: F64, m3: NDArray[np.bool_]) -> F64:
    """Measurement variances with masked-out (possibly NaN) rows replaced by 1."""
    return np.where(m3, np.asarray(r, float), 1.0)


def _innovation(nu: F64, s: F64) -> Innovation:
    s = np.where(np.isfinite(nu), s, np.nan)
    return Innovation(nu=nu, s=s, nis=np.sum(nu * nu / s, axis=1))


def _init_state(z: F64, r: F64, n: int, v0_var: float, a_var: F64 | None = None) -> tuple[F64, F64]:
    """x (B, 3, n), packed P (B, 3, m) from the first plots."""
    z = np.asarray(z, float)
    b = len(z)
    x = np.zeros((b, 3, n))
    x[..., 0] = z
    p = np.zeros((b, 3, len(PAIRS[n])))
    p[..., 0] = np.asarray(r, float)
    p[..., PAIRS[n].index((1, 1))] = v0_var
    if n == 3:
        p[..., 5] = a_var
    return x, p


def _output(x: NDArray, p: NDArray) -> Output:
    """6-state (x, y, z, vx, vy, vz) from per-axis [p, v, …] state and packed covariance."""
    vv = 2 if p.shape[-1] == 3 else 3            # index of P11 in the packed layout
    var = np.concatenate([p[..., 0], p[..., vv]], axis=1)
    cov = np.zeros((len(p), 6, 6))
    ax = np.arange(3)
    cov[:, ax, ax] = p[..., 0]
    cov[:, ax + 3, ax + 3] = p[..., vv]
    cov[:, ax, ax + 3] = cov[:, ax + 3, ax] = p[..., 1]   # per-axis position–velocity terms
    return Output(x=np.concatenate([x[..., 0], x[..., 1]], axis=1), var=var, cov=cov)


# ----------------------------------------------------------------------------- elementwise kernels

def _predict2(x: F64, p: F64, tau: F64, f11: F64 | float, q: tuple) -> None:
    """In place x ← Φx, P ← ΦPΦᵀ + Q for Φ = [[1, τ], [0, f11]], packed Q = (q00, q01, q11)."""
    x[0] += tau * x[1]
    x[1] *= f11
    p00, p01, p11 = p
    a0 = p00 + tau * p01                    # row 0 of ΦP
    a1 = p01 + tau * p11
    n00 = a0 + tau * a1 + q[0]
    n01 = f11 * a1 + q[1]
    n11 = f11 * f11 * p11 + q[2]
    p[0], p[1], p[2] = n00, n01, n11


def _update2(x: F64, p: F64, nu: F64, r: F64) -> F64:
    """In place scalar Kalman update with H = [1, 0]; returns S = P00 + R (no-op where ν is NaN)."""
    s = p[0] + r
    ok = np.isfinite(nu)
    g = np.where(ok, 1.0 / s, 0.0)
    nu0 = np.where(ok, nu, 0.0)
    c0, c1 = p[0].copy(), p[1].copy()
    x[0] += c0 * g * nu0
    x[1] += c1 * g * nu0
    p[0] -= c0 * c0 * g
    p[1] -= c0 * c1 * g
    p[2] -= c1 * c1 * g
    return s


def _gain_update(x: F64, p: F64, nu: F64, r: F64, gains: Sequence[F64]) -> F64:
    """In place update with a given (not necessarily optimal) gain K and H = [1, 0, …]:
    x ← x + Kν, P ← (I − KH)P(I − KH)ᵀ + KRKᵀ (Joseph form, valid for any gain).

    Elementwise, P⁺ᵢⱼ = Pᵢⱼ − KᵢP₀ⱼ − KⱼP₀ᵢ + KᵢKⱼS with S = P00 + R. Returns S."""
    n = len(gains)
    s = p[0] + r
    ok = np.isfinite(nu)
    nu0 = np.where(ok, nu, 0.0)
    k = [np.where(ok, g, 0.0) for g in gains]
    row0 = [p[j].copy() for j in range(n)]      # P0j are the first n packed entries
    for i in range(n):
        x[i] += k[i] * nu0
    for m, (i, j) in enumerate(PAIRS[n]):
        p[m] += k[i] * k[j] * s - k[i] * row0[j] - k[j] * row0[i]
    return s


def _singer_coeffs(tau: F64, alpha: F64, sigma_m: F64, variant: Variant) -> tuple[F64, F64, F64, F64]:
    """Singer (Φ₁₃, Φ₂₃, Φ₃₃, D_a) with the printed-variant guard: for α_фτ > 1 the printed AR(1)
    would have Φ₃₃ = 1 − α_фτ < 0 (and D_a < 0 beyond α_фτ = 2), so Φ₃₃ and D_a are taken at
    α_фτ = 1 (Φ₃₃ = 0, D_a = σ_m²: the acceleration is forgotten, its stationary variance kept)."""
    a, b, f, q = singer_coefficients(tau, alpha, sigma_m, variant)
    if variant == "printed":
        long = alpha * tau > 1.0
        if np.any(long):
            f = np.where(long, 0.0, f)
            q = np.where(long, np.broadcast_to(sigma_m**2, q.shape), q)
    return a, b, f, q


def _check_variant(variant: str) -> None:
    if variant not in ("printed", "exact"):
        raise ValueError(f"unknown variant {variant!r}; use 'printed' or 'exact'")


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
      The velocity is then an unforced constant: P₂₂ → 0 and K₂ → 0 (digest §3), so this
      variant cannot follow speed changes; kept for reproduction only.
    """

    name: ClassVar[str] = "cv"
    q: PerAxis = 1.0
    noise: Literal["cwna", "printed"] = "cwna"
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "_q", _axes(self.q, "q"))
        if self.noise not in ("cwna", "printed"):
            raise ValueError(f"unknown noise {self.noise!r}; use 'cwna' or 'printed'")

    def process_noise(self, tau: F64) -> tuple[F64, F64, F64]:
        """Packed Q (q00, q01, q11), each broadcast to (B, 3)."""
        q = _bc(self._q, len(tau))
        if self.noise == "printed":
            return q + np.zeros_like(tau), 0.0, 0.0
        q1 = q * tau
        q2 = q1 * tau
        return q2 * tau / 3.0, 0.5 * q2, q1

    def init(self, z: F64, r: F64) -> State:
        x, p = _init_state(z, r, 2, self.v0_sigma**2)
        return {"x": x, "P": p}

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = _comp(state["x"]), _comp(state["P"]), _tau(dt)
        _predict2(x, p, tau, 1.0, self.process_noise(tau))
        return {"x": _store(x), "P": _store(p)}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p, m3 = _comp(state["x"]), _comp(state["P"]), _mask3(mask)
        nu = _nu(z, x[0], m3)
        s = _update2(x, p, nu, _r(r, m3))
        return {"x": _store(x), "P": _store(p)}, _innovation(nu, s)

    def output(self, state: State) -> Output:
        return _output(state["x"], state["P"])


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
        x, p = _init_state(z, r, self.n, self.v0_sigma**2, 0.0 if self.n == 3 else None)
        if self.n == 3:
            p[..., 5] = self.a0_sigma**2
        return {"x": x, "P": p, "tau": np.zeros(len(x))}

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = _comp(state["x"]), _comp(state["P"]), _tau(dt)
        q = self._q(tau)
        if self.n == 2:
            _predict2(x, p, tau, 1.0, q)
        else:
            predict_elementwise(x, p, tau, (0.5 * tau * tau, tau, 1.0, 0.0))
            for m in range(6):
                p[m] += q[m]
        return {"x": _store(x), "P": _store(p), "tau": np.asarray(dt, float).copy()}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p = _comp(state["x"]), _comp(state["P"])
        tau = _tau(state["tau"])
        m3 = _mask3(mask)
        rr = _r(r, m3)
        nu = _nu(z, x[0], m3)
        s = _gain_update(x, p, nu, rr, self._gains(tau, rr))
        return {"x": _store(x), "P": _store(p), "tau": state["tau"].copy()}, _innovation(nu, s)

    def output(self, state: State) -> Output:
        return _output(state["x"], state["P"])


def _per_tau(g: F64, tau: F64, power: int) -> F64:
    """g / τ^power, 0 where τ ≤ 0 (an update straight after init: position gain only)."""
    safe = np.where(tau > 0, tau, 1.0)
    return np.where(tau > 0, g / safe**power, 0.0)


@register
@dataclass(frozen=True)
class AlphaBetaFilter(_FixedGain):
    """α-β filter per axis (2.32)–(2.36), (2.47)–(2.48): x⁻ = Φx⁺ (CV), ν = z − p⁻,
    p⁺ = p⁻ + αν, v⁺ = v⁻ + (β/τ)ν — a Kalman recursion with the frozen gain K = [α, β/τ]ᵀ.

    The text gives no gain values and no k-dependent schedule (digest §4): the gains are fixed.

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
        object.__setattr__(self, "_sa", _axes(self.sigma_a, "sigma_a"))

    def _q(self, tau: F64) -> tuple[F64, ...]:
        t2 = tau * tau
        v = _bc(self._sa**2, len(tau)) * t2
        return 0.25 * v * t2, 0.5 * v * tau, v

    def _gains(self, tau: F64, r: F64) -> list[F64]:
        if self.gains == "steady_state":
            a, b = kalata_alpha_beta(_bc(self._sa, len(tau)) * tau * tau / np.sqrt(r))
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
        object.__setattr__(self, "_sj", _axes(self.sigma_j, "sigma_j"))

    def _q(self, tau: F64) -> tuple[F64, ...]:
        s = _bc(self._sj, len(tau))
        g = (0.5 * s * tau * tau, s * tau, s + np.zeros_like(tau))
        return tuple(g[i] * g[j] for i, j in PAIRS[3])

    def _gains(self, tau: F64, r: F64) -> list[F64]:
        if self.gains == "steady_state":
            a, b, g = steady_state_abg(_bc(self._sj, len(tau)) * tau * tau / np.sqrt(r))
        else:
            a, b, g = (np.full_like(r, v) for v in (self.alpha, self._beta, self._gamma))
        return [a, _per_tau(b, tau, 1), _per_tau(g, tau, 2)]


# ----------------------------------------------------------------------------- Singer

@register
@dataclass(frozen=True)
class SingerFilter(TrackFilter):
    """Singer Kalman filter per axis (2.49)–(2.63) / seed (4.46): x = [p, v, a],
    Φ from :func:`tertiary.stages.tracking.filters.singer.singer_phi`, Q = diag(0, 0, D_a), H = [1, 0, 0].

    ``alpha`` is α_ф (s⁻¹, inverse manoeuvre time constant; default 1/30), ``sigma_m`` the
    stationary acceleration std (m/s², default 2; per axis allowed), ``variant`` "printed"
    (Φ₃₃ = 1 − α_фτ, D_a = σ_m²(2α_фτ − α_φ²τ²)) or "exact" (e^{−α_фτ}, σ_m²(1 − e^{−2α_фτ})).
    Printed-variant guard: for α_фτ > 1 (long coasts) Φ₃₃ = 0 and D_a = σ_m².
    """

    name: ClassVar[str] = "singer"
    alpha: float = 1.0 / 30.0
    sigma_m: PerAxis = 2.0
    variant: Variant = "printed"
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        _check_variant(self.variant)
        if not self.alpha >= 0:
            raise ValueError(f"alpha must be >= 0, got {self.alpha}")
        object.__setattr__(self, "_sm", _axes(self.sigma_m, "sigma_m"))

    def coefficients(self, tau: F64) -> tuple[F64, F64, F64, F64]:
        return _singer_coeffs(tau, self.alpha, _bc(self._sm, len(tau)), self.variant)

    def init(self, z: F64, r: F64) -> State:
        x, p = _init_state(z, r, 3, self.v0_sigma**2, self._sm**2)
        return {"x": x, "P": p}

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = _comp(state["x"]), _comp(state["P"]), _tau(dt)
        predict_elementwise(x, p, tau, self.coefficients(tau))
        return {"x": _store(x), "P": _store(p)}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p, m3 = _comp(state["x"]), _comp(state["P"]), _mask3(mask)
        nu = _nu(z, x[0], m3)
        s = update_elementwise(x, p, nu, _r(r, m3))
        return {"x": _store(x), "P": _store(p)}, _innovation(nu, s)

    def output(self, state: State) -> Output:
        return _output(state["x"], state["P"])


# ----------------------------------------------------------------------------- adaptive Singer

@register
@dataclass(frozen=True)
class AdaptiveSingerFilter(SingerFilter):
    """Adaptive Singer filter per axis (2.64)–(2.91), the range-channel hybrid of §2.6.

    Modes (``mode``):

    * ``"hybrid"`` (default, the text's range-channel filter): fading factor λ and windowed R̂.
    * ``"fading"``: λ only, R = the plot's nominal r (2.66)–(2.68).
    * ``"r_window"``: R̂ only, λ ≡ 1 (2.64).
    * ``"none"``: λ ≡ 1, nominal R — the text's non-adaptive reference (= :class:`SingerFilter`).

    Recursion for step k (digest §6, intended indices):

    * C₀(k) = λ(k−1)ν²(k−1)/(1 + λ(k−1))  — (2.87) as printed (``c0="printed"``), a single
      lagged sample; ``c0="smoothed"`` uses the fading-memory C₀(k) = [ρC₀(k−1) + ν²(k−1)]/(1+ρ)
      (not in the text; ρ = ``rho``).
    * λ(k) = max{1, [C₀(k) − R̂(k−1) − HQHᵀ] / HΦP⁺(k−1)ΦᵀHᵀ}  — (2.88) with R̂(k−1) in the
      numerator (R̂(k) would be circular) and Hᵀ in the denominator; capped at ``lambda_max``
      (default ∞, i.e. no cap, as in the text). HQHᵀ = 0 for the Singer Q.
    * P⁻_λ(k) = λ(k)ΦP⁺(k−1)Φᵀ + Q  — (2.86).
    * R̂(k) = (1/N)Σ_{i=k−N}^{k−1} ν²(i) − HP⁻_λ(k)Hᵀ  — (2.89) with the window ending at k−1
      (ν(k) does not exist yet when K(k) is formed), N = ``window``. ``r_sub="faded"``
      (default) subtracts P⁻_λ as the step list orders it (R̂ after P⁻_λ); ``"unfaded"``
      subtracts HΦP⁺ΦᵀHᵀ + HQHᵀ (before λ) — not in the text; it breaks the feedback loop below.
    * K(k) from P⁻_λ(k) and R̂(k)  — (2.90); P⁺ = P⁻_λ − KHP⁻_λ  — (2.91).

    Safeguards the text lacks:

    * λ(0) = 1, and λ(k) = 1 whenever there is no previous innovation (after init — the init
      plot yields no innovation, so the text's ν(0) = 0 never enters C₀ — and after a coast).
    * The nominal R (the plot's r) is used until N innovations of the track exist.
    * R̂ ≥ R_min = ``r_floor`` × nominal r (default 0.1), since the difference can go negative.

    Behaviour of the text's hybrid (found in testing): C₀ is one lagged sample, so λ > 1 on
    about a quarter of the steps even with a matched model, with spikes of 10–10³. A spike in
    λ(k) inflates P⁻_λ(k), which drives R̂(k) = mean ν² − HP⁻_λH down to the floor, and the small
    R̂(k) raises the next λ(k+1) (its numerator is C₀ − R̂(k)): R̂ becomes heavy-tailed (median
    ≈ the true R, time mean up to ≈ 2× it). ``r_sub="unfaded"`` or ``c0="smoothed"`` damp this;
    ``mode="r_window"`` alone estimates R without it.

    Extra state keys: ``lam`` (B, 3) λ of the last prediction; ``r_hat`` (B, 3) the R used at
    the last update; ``c0`` (B, 3) C₀ memory (smoothed mode); ``hph0`` (B, 3) the un-faded
    prediction variance; ``nu2_last`` (B, 3) ν² of the last update (NaN once consumed or after a
    coast); ``win`` (B, 3, N) ring buffer of ν²; ``count`` (B,) number of innovations seen.
    """

    name: ClassVar[str] = "adaptive"
    mode: Literal["hybrid", "fading", "r_window", "none"] = "hybrid"
    window: int = 20
    c0: Literal["printed", "smoothed"] = "printed"
    rho: float = 4.0
    r_sub: Literal["faded", "unfaded"] = "faded"
    r_floor: float = 0.1
    lambda_max: float = np.inf

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mode not in ("hybrid", "fading", "r_window", "none"):
            raise ValueError(f"unknown mode {self.mode!r}; use 'hybrid', 'fading', 'r_window' or 'none'")
        if self.c0 not in ("printed", "smoothed"):
            raise ValueError(f"unknown c0 {self.c0!r}; use 'printed' or 'smoothed'")
        if self.r_sub not in ("faded", "unfaded"):
            raise ValueError(f"unknown r_sub {self.r_sub!r}; use 'faded' or 'unfaded'")
        if self.window < 1 or not self.r_floor > 0 or not self.lambda_max >= 1 or not self.rho >= 0:
            raise ValueError("need window >= 1, r_floor > 0, lambda_max >= 1, rho >= 0")

    @property
    def fading(self) -> bool:
        return self.mode in ("hybrid", "fading")

    @property
    def windowed(self) -> bool:
        return self.mode in ("hybrid", "r_window")

    def init(self, z: F64, r: F64) -> State:
        st = super().init(z, r)
        b = len(st["x"])
        st.update(lam=np.ones((b, 3)), r_hat=np.asarray(r, float).copy(), c0=np.zeros((b, 3)),
                  hph0=np.zeros((b, 3)), nu2_last=np.full((b, 3), np.nan),
                  win=np.zeros((b, 3, self.window)), count=np.zeros(b, np.int64))
        return st

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = _comp(state["x"]), _comp(state["P"]), _tau(dt)
        a, b, f, q = self.coefficients(tau)
        predict_elementwise(x, p, tau, (a, b, f, 0.0))            # ΦP⁺Φᵀ
        hph0 = p[0].copy()                                          # + HQHᵀ = 0 for the Singer Q
        c0 = state["c0"]
        nu2 = state["nu2_last"]
        if self.fading:
            if self.c0 == "printed":
                lam_prev = state["lam"]
                c0 = lam_prev * nu2 / (1.0 + lam_prev)
            else:
                c0 = np.where(np.isfinite(nu2), (self.rho * c0 + nu2) / (1.0 + self.rho), c0)
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = (c0 - state["r_hat"]) / hph0
            lam = np.minimum(np.where(np.isfinite(ratio) & (ratio > 1.0), ratio, 1.0), self.lambda_max)
            p *= lam
            c0 = np.where(np.isfinite(c0), c0, state["c0"])
        else:
            lam = np.ones_like(state["lam"])
        p[5] += q
        out = dict(state)
        out.update(x=_store(x), P=_store(p), lam=lam, c0=c0, hph0=hph0, nu2_last=np.full_like(nu2, np.nan))
        return out

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        mask = np.asarray(mask, bool)
        x, p = _comp(state["x"]), _comp(state["P"])
        m3 = _mask3(mask)
        r_nom = _r(r, m3)
        count = state["count"]
        if self.windowed:
            hph = p[0] if self.r_sub == "faded" else state["hph0"]
            est = state["win"].sum(axis=2) / self.window - hph
            est = np.maximum(est, self.r_floor * r_nom)
            r_use = np.where((count >= self.window)[:, None], est, r_nom)
        else:
            r_use = r_nom
        nu = _nu(z, x[0], m3)
        s = update_elementwise(x, p, nu, r_use)
        nu2 = nu * nu
        win = state["win"]
        if self.windowed and mask.any():
            rows = np.flatnonzero(mask)
            win = win.copy()
            win[rows, :, count[rows] % self.window] = nu2[rows]
        out = dict(state)
        out.update(x=_store(x), P=_store(p), win=win, count=count + mask, nu2_last=nu2,
                   r_hat=np.where(m3, r_use, state["r_hat"]))
        return out, _innovation(nu, s)


# ----------------------------------------------------------------------------- two-model

def _prior2(w1: F64, prior: str, p_stay: float) -> F64:
    """Prior c₁ of model 1 from W₁(k) (c₂ = 1 − c₁ in both forms)."""
    if prior == "printed":
        return 1.0 - w1                                   # c_j = 1 − W_j(k): c₁ = W₂(k)
    return p_stay * w1 + (1.0 - p_stay) * (1.0 - w1)     # Σᵢ π_i1 Wᵢ(k)


def _posterior2(c1: F64, ll1: F64, ll2: F64) -> F64:
    """W₁ = c₁L₁ / (c₁L₁ + c₂L₂), computed from log-likelihoods without overflow. Where both
    products vanish (a prior of 0 on the only model the data allow — possible with the printed
    prior once a weight reaches 1) the prior is kept."""
    m = np.maximum(ll1, ll2)
    u1 = c1 * np.exp(ll1 - m)
    u = u1 + (1.0 - c1) * np.exp(ll2 - m)
    ok = u > 0
    return np.where(ok, u1 / np.where(ok, u, 1.0), c1)


def two_model_weights(w: F64, log_lik: F64 | None, prior: Literal["printed", "corrected"],
                      p_stay: float) -> F64:
    """One weight step (…, 2) → (…, 2): prior c_j, then W_j ∝ c_j L_j.

    ``prior="printed"``: c_j = 1 − W_j(k) (2.130)–(2.131) — for two models the other model's
    weight, so with constant likelihoods the weights alternate with period 2.
    ``prior="corrected"``: Markov prediction c_j = Σᵢ π_ij W_i(k), π = [[p, 1−p], [1−p, p]],
    p = ``p_stay``. ``log_lik`` (…, 2) or None (no plot): corrected → c; printed → W unchanged.
    """
    w = np.asarray(w, float)
    c1 = _prior2(w[..., 0], prior, p_stay)
    if log_lik is None:
        w1 = c1 if prior == "corrected" else w[..., 0]
    else:
        w1 = _posterior2(c1, log_lik[..., 0], log_lik[..., 1])
    return np.stack([w1, 1.0 - w1], axis=-1)


@register
@dataclass(frozen=True)
class TwoModelFilter(TrackFilter):
    """Random-structure two-model filter per axis (2.92)–(2.137) with Bayesian weights.

    * Model 1: Singer 3-state [p, v, a] (``alpha`` α_ф, ``sigma_m``, ``variant``), as
      :class:`SingerFilter`.
    * Model 2: Gauss–Markov rate 2-state [p, v], Φ₂ = [[1, Φ₁₂], [0, Φ₂₂]] with printed
      Φ₁₂ = τ, Φ₂₂ = 1 − α₂τ or exact (1 − e^{−α₂τ})/α₂, e^{−α₂τ}; Q₂ = diag(0, D_ω2) with
      D_ω2 = q₂(τ − α₂τ²/2) printed / q₂(1 − e^{−2α₂τ})/(2α₂) exact (stationary rate variance
      q₂/(2α₂); → q₂τ as α₂ → 0). Defaults α₂ = ``alpha2`` = 0 (a Cartesian velocity is not
      zero-mean, so it is not pulled to 0: model 2 is then a nearly-constant-velocity model with
      velocity random walk ``q2`` = 0.05 m²/s³).
    * Both run the §3 recursion independently on the same plot (no state mixing); weights per
      axis W (B, 3, 2), W(0) = ``w0``.
    * Likelihood ``likelihood="intended"`` (default): L_j = N(ν_j; 0, D_j), D_j = HP⁻_jHᵀ + R.
      ``"printed"``: (2.134)–(2.137) D_j = HP⁺_jHᵀ + R_j with the single-sample
      R_j = ν_j² − HP⁻_jHᵀ, floored at ``d_floor`` × r (it can be ≤ 0).
    * Prior ``prior="corrected"`` (default): Markov c_j = Σᵢπ_ijW_i, p_stay = ``p_stay`` (0.95);
      ``"printed"``: c_j = 1 − W_j(k) (see :func:`two_model_weights`).

    Output: per axis, the weighted position and velocity x̂ = ΣW_j x_j⁺ (the text combines only
    the measured coordinate; velocity is combined the same way) with mixture variance
    ΣW_j(P_j + (x_j − x̂)²); ``Output.probs`` (B, 2) = W averaged over ``prob_axes`` (default the
    horizontal axes (0, 1): turns show there, and level flight would dilute them via z).
    Innovation: ν = z − Σc_j x⁻_j,0 and S = Σc_j(P⁻_j,00 + (x⁻_j,0 − ẑ)²) + r with the prior c.

    State keys: ``x1`` (B, 3, 3), ``P1`` (B, 3, 6), ``x2`` (B, 3, 2), ``P2`` (B, 3, 3),
    ``w`` (B, 3, 2).
    """

    name: ClassVar[str] = "two_model"
    alpha: float = 1.0 / 30.0
    sigma_m: PerAxis = 2.0
    variant: Variant = "printed"
    alpha2: float = 0.0
    q2: PerAxis = 0.05
    prior: Literal["printed", "corrected"] = "corrected"
    p_stay: float = 0.95
    likelihood: Literal["intended", "printed"] = "intended"
    d_floor: float = 1e-3
    w0: tuple[float, float] = (0.5, 0.5)
    prob_axes: tuple[int, ...] = (0, 1)
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        _check_variant(self.variant)
        if self.prior not in ("printed", "corrected"):
            raise ValueError(f"unknown prior {self.prior!r}; use 'printed' or 'corrected'")
        if self.likelihood not in ("intended", "printed"):
            raise ValueError(f"unknown likelihood {self.likelihood!r}; use 'intended' or 'printed'")
        if not (0 <= self.p_stay <= 1 and self.alpha >= 0 and self.alpha2 >= 0 and self.d_floor > 0):
            raise ValueError("need 0 <= p_stay <= 1, alpha >= 0, alpha2 >= 0, d_floor > 0")
        w0 = np.asarray(self.w0, float)
        if w0.shape != (2,) or np.any(w0 < 0) or not np.isclose(w0.sum(), 1.0):
            raise ValueError(f"w0 must be two non-negative weights summing to 1, got {self.w0!r}")
        object.__setattr__(self, "_sm", _axes(self.sigma_m, "sigma_m"))
        object.__setattr__(self, "_q2", _axes(self.q2, "q2"))

    def model2_coefficients(self, tau: F64) -> tuple[F64, F64, F64]:
        """(Φ₁₂, Φ₂₂, D_ω2) of model 2, broadcast to (B, 3)."""
        a, q = self.alpha2, _bc(self._q2, len(tau))
        if a == 0:
            return tau, np.ones_like(tau), q * tau
        if self.variant == "printed":
            at = np.minimum(a * tau, 1.0)                   # same long-coast guard as Singer
            return tau, 1.0 - at, q * (2.0 * at - at * at) / (2.0 * a)
        e = np.exp(-a * tau)
        return (1.0 - e) / a, e, q * (1.0 - e * e) / (2.0 * a)

    def init(self, z: F64, r: F64) -> State:
        x1, p1 = _init_state(z, r, 3, self.v0_sigma**2, self._sm**2)
        x2, p2 = _init_state(z, r, 2, self.v0_sigma**2)
        w = np.broadcast_to(np.asarray(self.w0, float), (len(x1), 3, 2)).copy()
        return {"x1": x1, "P1": p1, "x2": x2, "P2": p2, "w": w}

    def predict(self, state: State, dt: F64) -> State:
        tau = _tau(dt)
        x1, p1 = _comp(state["x1"]), _comp(state["P1"])
        predict_elementwise(x1, p1, tau, _singer_coeffs(tau, self.alpha, _bc(self._sm, len(tau)), self.variant))
        x2, p2 = _comp(state["x2"]), _comp(state["P2"])
        phi12, phi22, d = self.model2_coefficients(tau)
        # model 2: x ← [p + Φ₁₂v, Φ₂₂v]; reuse _predict2 with τ → Φ₁₂
        _predict2(x2, p2, phi12, phi22, (0.0, 0.0, d))
        return {"x1": _store(x1), "P1": _store(p1), "x2": _store(x2), "P2": _store(p2),
                "w": state["w"].copy()}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        mask = np.asarray(mask, bool)
        m3 = _mask3(mask)
        rr = _r(r, m3)
        x1, p1 = _comp(state["x1"]), _comp(state["P1"])
        x2, p2 = _comp(state["x2"]), _comp(state["P2"])
        w1 = state["w"][..., 0].copy()
        c1 = _prior2(w1, self.prior, self.p_stay)
        c2 = 1.0 - c1
        # mixture innovation under the prior
        zp = c1 * x1[0] + c2 * x2[0]
        sp = c1 * (p1[0] + (x1[0] - zp) ** 2) + c2 * (p2[0] + (x2[0] - zp) ** 2) + rr
        nu = _nu(z, zp, m3)
        nu1, nu2 = _nu(z, x1[0], m3), _nu(z, x2[0], m3)
        pm1, pm2 = p1[0].copy(), p2[0].copy()
        s1 = update_elementwise(x1, p1, nu1, rr)
        s2 = _update2(x2, p2, nu2, rr)
        if self.likelihood == "intended":
            d1, d2 = s1, s2
        else:
            floor = self.d_floor * rr
            d1 = np.maximum(p1[0] + nu1 * nu1 - pm1, floor)
            d2 = np.maximum(p2[0] + nu2 * nu2 - pm2, floor)
        ll1 = -0.5 * (np.log(d1) + nu1 * nu1 / d1)      # the common −½log 2π cancels
        ll2 = -0.5 * (np.log(d2) + nu2 * nu2 / d2)
        w1_new = np.where(m3, _posterior2(c1, ll1, ll2), c1 if self.prior == "corrected" else w1)
        w_new = np.stack([w1_new, 1.0 - w1_new], axis=-1)
        out = {"x1": _store(x1), "P1": _store(p1), "x2": _store(x2), "P2": _store(p2), "w": w_new}
        return out, _innovation(nu, sp)

    def combined(self, state: State) -> tuple[F64, F64]:
        """Per-axis weighted (position, velocity) (B, 3, 2) and mixture variances (B, 3, 2)."""
        w1, w2 = state["w"][..., :1], state["w"][..., 1:]
        m1, m2 = state["x1"][..., :2], state["x2"]
        v1 = state["P1"][..., [0, 3]]
        v2 = state["P2"][..., [0, 2]]
        m = w1 * m1 + w2 * m2
        var = w1 * (v1 + (m1 - m) ** 2) + w2 * (v2 + (m2 - m) ** 2)
        return m, var

    def output(self, state: State) -> Output:
        m, var = self.combined(state)
        probs = state["w"][:, list(self.prob_axes), :].mean(axis=1)
        return Output(x=np.concatenate([m[..., 0], m[..., 1]], axis=1),
                      var=np.concatenate([var[..., 0], var[..., 1]], axis=1), probs=probs)
