"""Manoeuvring-target filters of the linear family (monograph chapter 2), batched over tracks and
decoupled per axis (layout: :mod:`.axes`; conventions: :mod:`.linear`):

``singer``            Singer (2.49)–(2.63) / seed (4.46)           :class:`SingerFilter`
``adaptive``          hybrid adaptive Singer (2.64)–(2.91)        :class:`AdaptiveSingerFilter`
``two_model``         random-structure two-model (2.92)–(2.137)   :class:`TwoModelFilter`
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

from tertiary.filters.axes import (PerAxis, axis_param, components, init_state, innovation, mask3,
                                                    masked_innovation, masked_variance, output6, per_axis, predict2,
                                                    state_layout, tau3, update2)
from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.filters.singer import (Variant, predict_elementwise, singer_coefficients, update_elementwise)

__all__ = ["SingerFilter", "AdaptiveSingerFilter", "TwoModelFilter", "two_model_weights"]


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



# ----------------------------------------------------------------------------- Singer

@register
@dataclass(frozen=True)
class SingerFilter(TrackFilter):
    """Singer Kalman filter per axis (2.49)–(2.63) / seed (4.46): x = [p, v, a],
    Φ from :func:`tertiary.filters.singer.singer_phi`, Q = diag(0, 0, D_a), H = [1, 0, 0].

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
        object.__setattr__(self, "_sm", per_axis(self.sigma_m, "sigma_m"))

    def coefficients(self, tau: F64) -> tuple[F64, F64, F64, F64]:
        return _singer_coeffs(tau, self.alpha, axis_param(self._sm, len(tau)), self.variant)

    def init(self, z: F64, r: F64) -> State:
        x, p = init_state(z, r, 3, self.v0_sigma**2, self._sm**2)
        return {"x": x, "P": p}

    def predict(self, state: State, dt: F64) -> State:
        x, p, tau = components(state["x"]), components(state["P"]), tau3(dt)
        predict_elementwise(x, p, tau, self.coefficients(tau))
        return {"x": state_layout(x), "P": state_layout(p)}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p, m3 = components(state["x"]), components(state["P"]), mask3(mask)
        nu = masked_innovation(z, x[0], m3)
        s = update_elementwise(x, p, nu, masked_variance(r, m3))
        return {"x": state_layout(x), "P": state_layout(p)}, innovation(nu, s)

    def output(self, state: State) -> Output:
        return output6(state["x"], state["P"])


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

    Recursion for step k (intended indices):

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
        x, p, tau = components(state["x"]), components(state["P"]), tau3(dt)
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
        out.update(x=state_layout(x), P=state_layout(p), lam=lam, c0=c0, hph0=hph0, nu2_last=np.full_like(nu2, np.nan))
        return out

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        mask = np.asarray(mask, bool)
        x, p = components(state["x"]), components(state["P"])
        m3 = mask3(mask)
        r_nom = masked_variance(r, m3)
        count = state["count"]
        if self.windowed:
            hph = p[0] if self.r_sub == "faded" else state["hph0"]
            est = state["win"].sum(axis=2) / self.window - hph
            est = np.maximum(est, self.r_floor * r_nom)
            r_use = np.where((count >= self.window)[:, None], est, r_nom)
        else:
            r_use = r_nom
        nu = masked_innovation(z, x[0], m3)
        s = update_elementwise(x, p, nu, r_use)
        nu2 = nu * nu
        win = state["win"]
        if self.windowed and mask.any():
            rows = np.flatnonzero(mask)
            win = win.copy()
            win[rows, :, count[rows] % self.window] = nu2[rows]
        out = dict(state)
        out.update(x=state_layout(x), P=state_layout(p), win=win, count=count + mask, nu2_last=nu2,
                   r_hat=np.where(m3, r_use, state["r_hat"]))
        return out, innovation(nu, s)


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
        object.__setattr__(self, "_sm", per_axis(self.sigma_m, "sigma_m"))
        object.__setattr__(self, "_q2", per_axis(self.q2, "q2"))

    def model2_coefficients(self, tau: F64) -> tuple[F64, F64, F64]:
        """(Φ₁₂, Φ₂₂, D_ω2) of model 2, broadcast to (B, 3)."""
        a, q = self.alpha2, axis_param(self._q2, len(tau))
        if a == 0:
            return tau, np.ones_like(tau), q * tau
        if self.variant == "printed":
            at = np.minimum(a * tau, 1.0)                   # same long-coast guard as Singer
            return tau, 1.0 - at, q * (2.0 * at - at * at) / (2.0 * a)
        e = np.exp(-a * tau)
        return (1.0 - e) / a, e, q * (1.0 - e * e) / (2.0 * a)

    def init(self, z: F64, r: F64) -> State:
        x1, p1 = init_state(z, r, 3, self.v0_sigma**2, self._sm**2)
        x2, p2 = init_state(z, r, 2, self.v0_sigma**2)
        w = np.broadcast_to(np.asarray(self.w0, float), (len(x1), 3, 2)).copy()
        return {"x1": x1, "P1": p1, "x2": x2, "P2": p2, "w": w}

    def predict(self, state: State, dt: F64) -> State:
        tau = tau3(dt)
        x1, p1 = components(state["x1"]), components(state["P1"])
        predict_elementwise(x1, p1, tau, _singer_coeffs(tau, self.alpha, axis_param(self._sm, len(tau)), self.variant))
        x2, p2 = components(state["x2"]), components(state["P2"])
        phi12, phi22, d = self.model2_coefficients(tau)
        # model 2: x ← [p + Φ₁₂v, Φ₂₂v]; reuse predict2 with τ → Φ₁₂
        predict2(x2, p2, phi12, phi22, (0.0, 0.0, d))
        return {"x1": state_layout(x1), "P1": state_layout(p1), "x2": state_layout(x2), "P2": state_layout(p2),
                "w": state["w"].copy()}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        mask = np.asarray(mask, bool)
        m3 = mask3(mask)
        rr = masked_variance(r, m3)
        x1, p1 = components(state["x1"]), components(state["P1"])
        x2, p2 = components(state["x2"]), components(state["P2"])
        w1 = state["w"][..., 0].copy()
        c1 = _prior2(w1, self.prior, self.p_stay)
        c2 = 1.0 - c1
        # mixture innovation under the prior
        zp = c1 * x1[0] + c2 * x2[0]
        sp = c1 * (p1[0] + (x1[0] - zp) ** 2) + c2 * (p2[0] + (x2[0] - zp) ** 2) + rr
        nu = masked_innovation(z, zp, m3)
        nu1, nu2 = masked_innovation(z, x1[0], m3), masked_innovation(z, x2[0], m3)
        pm1, pm2 = p1[0].copy(), p2[0].copy()
        s1 = update_elementwise(x1, p1, nu1, rr)
        s2 = update2(x2, p2, nu2, rr)
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
        out = {"x1": state_layout(x1), "P1": state_layout(p1), "x2": state_layout(x2), "P2": state_layout(p2), "w": w_new}
        return out, innovation(nu, sp)

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
