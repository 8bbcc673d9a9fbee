"""Chapter 3 range channels driven by onboard parameters, batched over tracks / Monte-Carlo runs.

Two per-radar range channels that sit beside the Singer channel (:mod:`tertiary.filters.singer`):

``kinematic``          §3.4, (3.12)–(3.58): base filter x = [D, V, a] whose acceleration is the
                       kinematic LOS acceleration u = a_L (3.11)/(3.32) computed from five
                       auxiliary two-state filters (V_ц, θ, φ from the datalink; ε_B, ε_Г from
                       the radar).                                   :class:`KinematicRangeChannel`
``kinematic_dynamic``  §3.5, (3.59)–(3.127): the same base filter with u from load factors
                       (3.61)–(3.62) and eight auxiliary filters (n_y, n_z, n_x, γ_v, θ, φ from
                       the datalink; ε_B, ε_Г from the radar); (3.62) ``variant="printed"``
                       (u = g n_XL) or ``"corrected"`` (u = g(n_XL − sin ε_B) + (V² − V_L²)/D,
                       V from a ninth auxiliary filter on V_ц).     :class:`KinematicDynamicRangeChannel`

Base filter (3.27)–(3.33)/(3.81)–(3.87): H = [1, 0, 0], R = σ_D², Q = diag(0, 0, D_a) and

    x⁻(k+1) = Φ_b x⁺(k) + b u(k),  Φ_b = [[1, τ, τ²/2], [0, 1, τ], [0, 0, 0]],  b = [0, 0, 1]ᵀ

so the predicted acceleration *is* u(k) with variance D_a (P⁻ third row [0, 0, D_a]): the base
filter is the printed Singer recursion (2.49)–(2.63) with Φ₃₃ = 0 plus the input, and reuses its
elementwise kernels. Auxiliary filters (3.34)–(3.58)/(3.88)–(3.127): x_i = [p_i, ṗ_i],
Φ_i = [[1, τ], [0, 1 − α_i τ]], Q_i = diag(0, D_i), H = [1, 0], R_i, with
D_i = σ_i²(2α_i τ − α_i²τ²) (stationary rate variance σ_i², as :func:`~tertiary.filters.singer.singer_q`).

Per-step order: u(k) from the auxiliary x⁺(k); base predict + update with D(k+1);
auxiliary predict + update with their measurements at k+1. Angle innovations are wrapped to
(−π, π] (the source does not say so). A NaN measurement means "no measurement": that filter
coasts (x⁺ = x⁻, P⁺ = P⁻, memory mode §2.1).

State (a :data:`~tertiary.filters.base.State`, track axis first so ``take``/``concat`` apply):
``x`` (B, 3) base [D, V, a]; ``P`` (B, 6) packed (P00, P01, P02, P11, P12, P22);
``ax`` (B, n, 2) auxiliary [p, ṗ]; ``aP`` (B, n, 3) packed (P00, P01, P11); ``u`` (B,) the input
used for the next prediction.

Inputs are a dict of (B,) arrays (:func:`channel_inputs` builds it from radar plots and Mode S
EHS parameters): ``range_m``, ``eps_b`` (elevation, rad), ``eps_g`` (azimuth counter-clockwise
from north, rad = −radar azimuth), ``speed`` (V_ц, m/s), ``theta`` (flight-path angle, rad),
``phi`` (path angle = −true track, rad), ``gamma`` (bank, rad), ``n_x``, ``n_y``, ``n_z``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.filters import kinematic_los as los
from tertiary.filters.base import F64, State
from tertiary.filters.singer import predict_elementwise, update_elementwise

__all__ = ["AuxFilter", "KinematicRangeChannel", "KinematicDynamicRangeChannel", "channel_inputs",
           "RANGE_CHANNELS", "make_range_channel"]

Variant = Literal["printed", "corrected"]


@dataclass(frozen=True)
class AuxFilter:
    """One auxiliary filter: measured input key, α_i (s⁻¹), stationary rate σ_i, measurement σ
    (R_i = σ²) and whether the parameter is an angle (wrapped innovations)."""

    key: str
    alpha: float
    sigma_rate: float
    sigma_meas: float
    angle: bool = False


# Defaults (documented choices; the source gives none):
#  * datalink σ: Mode S EHS resolution and onboard-sensor noise of tertiary.simulate.ehs
#    combined (noise² + LSB²/12): ground speed 0.5 m/s & 2 kt, track 0.2° & 90/512°,
#    roll 0.3° & 45/256°, vertical rate 0.3 m/s & 32 ft/min (θ = atan(ḣ/V) ⇒ σ_θ ≈ σ_ḣ/V).
#  * radar σ: the big-box radars (σ_ε = 0.1°), set per channel with ``sigma_angle_rad``.
#  * α_i = 1/20 s⁻¹ (rates persist over a turn, 26–30 s) for flight parameters; 1/60 s⁻¹ for the
#    LOS angles, whose rates change only smoothly (velocity is continuous).
#  * σ_i: V̇ 1 m/s²; ω_θ 0.02 rad/s; ω_φ 0.06 rad/s (the 300 m/s, R = 5 km turn); ω_γ 0.1 rad/s
#    (roll-in in 5–10 s); load-factor rates 0.1 /s; LOS rates 0.01 rad/s.
_DEG = np.pi / 180.0
SIGMA_SPEED = float(np.hypot(0.5, 2 * 0.514444 / np.sqrt(12)))
SIGMA_TRACK = float(np.hypot(0.2, 90 / 512 / np.sqrt(12)) * _DEG)
SIGMA_ROLL = float(np.hypot(0.3, 45 / 256 / np.sqrt(12)) * _DEG)
SIGMA_VRATE = float(np.hypot(0.3, 32 * 0.3048 / 60 / np.sqrt(12)))


def _los_aux(sigma_angle_rad: float, sigma_rate: float) -> tuple[AuxFilter, AuxFilter]:
    return (AuxFilter("eps_b", 1 / 60, sigma_rate, sigma_angle_rad, angle=True),
            AuxFilter("eps_g", 1 / 60, sigma_rate, sigma_angle_rad, angle=True))


def kinematic_aux(sigma_angle_rad: float = 0.1 * _DEG, speed_mps: float = 100.0,
                  los_rate_sigma: float = 0.01) -> tuple[AuxFilter, ...]:
    """Filters 1–5 of §3.4 (3.34)–(3.58): V_ц, θ, φ (datalink), ε_B, ε_Г (radar)."""
    return (AuxFilter("speed", 1 / 20, 1.0, SIGMA_SPEED),
            AuxFilter("theta", 1 / 20, 0.02, SIGMA_VRATE / max(speed_mps, 1.0), angle=True),
            AuxFilter("phi", 1 / 20, 0.06, SIGMA_TRACK, angle=True),
            *_los_aux(sigma_angle_rad, los_rate_sigma))


def dynamic_aux(sigma_angle_rad: float = 0.1 * _DEG, speed_mps: float = 100.0,
                los_rate_sigma: float = 0.01) -> tuple[AuxFilter, ...]:
    """Filters 1–8 of §3.5 (3.88)–(3.127) (n_y, n_z, n_x, γ_v, θ, φ, ε_B, ε_Г) and a ninth on V_ц
    (the corrected (3.62) needs V). Load factors derived from EHS under coordinated flight:
    σ(n_y) ≈ tan γ/cos γ · σ_γ ≤ 0.03 up to 60° bank."""
    s_th = SIGMA_VRATE / max(speed_mps, 1.0)
    return (AuxFilter("n_y", 1 / 20, 0.1, 0.03), AuxFilter("n_z", 1 / 20, 0.1, 0.01),
            AuxFilter("n_x", 1 / 20, 0.1, s_th), AuxFilter("gamma", 1 / 20, 0.1, SIGMA_ROLL, angle=True),
            AuxFilter("theta", 1 / 20, 0.02, s_th, angle=True), AuxFilter("phi", 1 / 20, 0.06, SIGMA_TRACK, angle=True),
            *_los_aux(sigma_angle_rad, los_rate_sigma), AuxFilter("speed", 1 / 20, 1.0, SIGMA_SPEED))


# ----------------------------------------------------------------------------- auxiliary kernels

def _aux_predict(x: F64, p: F64, tau: F64, alpha: F64, d: F64) -> None:
    """In place x ← Φ_i x, P ← Φ_i P Φ_iᵀ + Q_i on component-first arrays x (2, B, n), p (3, B, n),
    Φ_i = [[1, τ], [0, f]], f = 1 − α_i τ, Q_i = diag(0, D_i) ((3.34)–(3.38) etc.)."""
    f = 1.0 - alpha * tau
    x[0] += tau * x[1]
    x[1] *= f
    p00, p01, p11 = p[0].copy(), p[1].copy(), p[2].copy()
    p[0] = p00 + 2.0 * tau * p01 + tau * tau * p11
    p[1] = f * (p01 + tau * p11)
    p[2] = f * f * p11 + d


def _aux_update(x: F64, p: F64, z: F64, r: F64, angle: NDArray[np.bool_]) -> None:
    """In place scalar update with H = [1, 0]; no-op where z is NaN; angle innovations wrapped."""
    nu = z - x[0]
    nu = np.where(angle, los.wrap_pi(nu), nu)
    ok = np.isfinite(nu)
    s = p[0] + r
    g = np.where(ok, 1.0 / s, 0.0)
    nu = np.where(ok, nu, 0.0)
    k0, k1 = p[0] * g, p[1] * g
    x[0] += k0 * nu
    x[1] += k1 * nu
    p[2] -= k1 * p[1]
    p[1] -= k0 * p[1]
    p[0] -= k0 * p[0]


# ----------------------------------------------------------------------------- channels

@dataclass(frozen=True)
class _Channel:
    """Shared base-filter + auxiliary-filter machinery; subclasses define :meth:`acceleration`."""

    name: ClassVar[str]
    sigma_range_m: float = 50.0
    sigma_u: float = 1.0           # √D_a: σ of the input acceleration's error (m/s²)
    v0_sigma_mps: float = 300.0    # one-point initiation, as the Singer channel (LocalTrackerConfig)
    aux: tuple[AuxFilter, ...] = ()

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(a.key for a in self.aux)

    def _vec(self, attr: str) -> F64:
        return np.array([getattr(a, attr) for a in self.aux], float)

    def init(self, z: dict[str, F64]) -> State:
        """Start B tracks from their first measurements: every position = its measurement
        (variance R), every rate 0 with its stationary variance (σ_i², base (v0)²); a⁺(0) = u(0)."""
        d = np.asarray(z["range_m"], float)
        b, n = len(d), len(self.aux)
        x = np.zeros((b, 3))
        x[:, 0] = d
        p = np.zeros((b, 6))
        p[:, 0], p[:, 3], p[:, 5] = self.sigma_range_m**2, self.v0_sigma_mps**2, self.sigma_u**2
        ax = np.zeros((b, n, 2))
        z0 = np.stack([np.asarray(z[k], float) for k in self.keys], axis=1)
        ax[..., 0] = np.nan_to_num(z0)
        ap = np.zeros((b, n, 3))
        ap[..., 0] = np.where(np.isfinite(z0), self._vec("sigma_meas") ** 2, 1e6)   # unmeasured: uninformative
        ap[..., 2] = self._vec("sigma_rate") ** 2
        state = {"x": x, "P": p, "ax": ax, "aP": ap}
        state["u"] = self.acceleration(state)
        x[:, 2] = state["u"]
        return state

    def step(self, state: State, z: dict[str, F64], tau: ArrayLike) -> tuple[State, F64, F64, F64]:
        """One step k → k+1 (the order above); returns (state, range innovation ν, its variance S,
        the base gain K (B, 3) = P⁻Hᵀ/S (K₃ ≡ 0: P⁻₀₂ = 0))."""
        b = len(state["x"])
        tau = np.broadcast_to(np.asarray(tau, float), (b,))
        xb, pb = state["x"].T.copy(), state["P"].T.copy()
        coeffs = (0.5 * tau * tau, tau, np.zeros(b), np.full(b, self.sigma_u**2))
        predict_elementwise(xb, pb, tau, coeffs)          # Φ_b with zero third row, (3.27)–(3.31)
        xb[2] = state["u"]                                # + b u(k), (3.32)
        nu = np.asarray(z["range_m"], float) - xb[0]      # (2.28)/(3.28)
        gain_num = pb[:3].copy()
        s = update_elementwise(xb, pb, nu, np.full(b, self.sigma_range_m**2))
        ax, ap = state["ax"].transpose(2, 0, 1).copy(), state["aP"].transpose(2, 0, 1).copy()
        tau_n = np.repeat(tau[:, None], len(self.aux), axis=1)
        alpha = self._vec("alpha")
        sig = self._vec("sigma_rate")
        at = alpha * tau_n
        _aux_predict(ax, ap, tau_n, alpha, sig**2 * (2.0 * at - at * at))
        zz = np.stack([np.asarray(z[k], float) for k in self.keys], axis=1)
        _aux_update(ax, ap, zz, self._vec("sigma_meas") ** 2, np.array([a.angle for a in self.aux]))
        new = {"x": xb.T.copy(), "P": pb.T.copy(), "ax": ax.transpose(1, 2, 0).copy(),
               "aP": ap.transpose(1, 2, 0).copy()}
        new["u"] = self.acceleration(new)
        ok = np.isfinite(nu)
        return new, np.where(ok, nu, np.nan), np.where(ok, s, np.nan), np.where(ok, gain_num / s, np.nan).T

    def aux_estimate(self, state: State, key: str, rate: bool = False) -> F64:
        """The auxiliary estimate of ``key`` (or its rate) per track."""
        return state["ax"][:, self.keys.index(key), 1 if rate else 0]

    def acceleration(self, state: State) -> F64:  # pragma: no cover - abstract
        raise NotImplementedError

    def run(self, z: dict[str, F64], tau: ArrayLike) -> dict[str, F64]:
        """Filter whole sequences: ``z`` arrays (T, B) (first row initiates), ``tau`` (T,) or
        (T, B). Returns (T, B) arrays of D⁺, V⁺, a⁺, P00, P11, P22, u and the gains K₁, K₂."""
        t_n = len(z["range_m"])
        tau = np.asarray(tau, float)
        tau = np.broadcast_to(tau.reshape(t_n, -1) if tau.ndim else tau, (t_n, z["range_m"].shape[1]))
        state = self.init({k: v[0] for k, v in z.items()})
        names = ("D", "V", "a", "P00", "P11", "P22", "u", "K1", "K2")
        out = {k: np.empty((t_n,) + z["range_m"].shape[1:]) for k in names}
        k1 = k2 = np.full(z["range_m"].shape[1], np.nan)
        for k in range(t_n):
            if k:
                state, _, _, gain = self.step(state, {kk: v[k] for kk, v in z.items()}, tau[k])
                k1, k2 = gain[:, 0], gain[:, 1]
            for i, key in enumerate(("D", "V", "a")):
                out[key][k] = state["x"][:, i]
            out["P00"][k], out["P11"][k], out["P22"][k] = state["P"][:, 0], state["P"][:, 3], state["P"][:, 5]
            out["u"][k], out["K1"][k], out["K2"][k] = state["u"], k1, k2
        return out


@dataclass(frozen=True)
class KinematicRangeChannel(_Channel):
    """§3.4 kinematic-parameter range channel (3.12)–(3.58); u = a_L of (3.11)/(3.32) from the
    corrected auxiliary estimates (V_ц⁺, θ⁺, ω_θ⁺, φ⁺, ω_φ⁺, ε_B⁺, ω_B⁺, ε_Г⁺, ω_Г⁺)(k).
    ``variant="printed"`` uses (3.11) with the V bracket closed early as printed (see
    :func:`~tertiary.filters.kinematic_los.los_acceleration`); ``"corrected"`` as (3.12)/(3.15)."""

    name: ClassVar[str] = "kinematic"
    variant: Variant = "corrected"
    aux: tuple[AuxFilter, ...] = field(default_factory=kinematic_aux)

    def __post_init__(self) -> None:
        if self.variant not in ("printed", "corrected"):
            raise ValueError(f"unknown (3.11) variant {self.variant!r}; use 'printed' or 'corrected'")

    def acceleration(self, state: State) -> F64:
        e = lambda k, r=False: self.aux_estimate(state, k, r)  # noqa: E731
        return los.los_acceleration(e("speed"), e("theta"), e("theta", True), e("phi"), e("phi", True),
                                    e("eps_b"), e("eps_b", True), e("eps_g"), e("eps_g", True), variant=self.variant)


@dataclass(frozen=True)
class KinematicDynamicRangeChannel(_Channel):
    """§3.5 kinematic + dynamic range channel (3.59)–(3.127); u from the load factors:
    (3.62) ``variant="printed"``: u = g n_XL; ``"corrected"``: u = g(n_XL − sin ε_B) + (V² − V_L²)/D
    with V from the V_ц filter and V_L, D the base filter's V⁺(k), D⁺(k)."""

    name: ClassVar[str] = "kinematic_dynamic"
    variant: Variant = "corrected"
    aux: tuple[AuxFilter, ...] = field(default_factory=dynamic_aux)

    def __post_init__(self) -> None:
        if self.variant not in ("printed", "corrected"):
            raise ValueError(f"unknown (3.62) variant {self.variant!r}; use 'printed' or 'corrected'")

    def acceleration(self, state: State) -> F64:
        e = lambda k: self.aux_estimate(state, k)  # noqa: E731
        n_xl = los.los_load_factor(e("n_x"), e("n_y"), e("n_z"), e("gamma"), e("theta"), e("phi"),
                                   e("eps_b"), e("eps_g"))
        return los.range_acceleration(n_xl, e("eps_b"), e("speed"), state["x"][:, 1], state["x"][:, 0],
                                      self.variant)


RANGE_CHANNELS = {"kinematic": KinematicRangeChannel, "kinematic_dynamic": KinematicDynamicRangeChannel}


def make_range_channel(name: str, **params) -> _Channel:
    """A chapter 3 range channel by name, e.g. ``make_range_channel("kinematic_dynamic", variant="printed")``."""
    if name not in RANGE_CHANNELS:
        raise ValueError(f"unknown range channel {name!r}; available: {', '.join(sorted(RANGE_CHANNELS))}")
    return RANGE_CHANNELS[name](**params)


def channel_inputs(range_m: ArrayLike, azimuth_deg: ArrayLike, elevation_deg: ArrayLike,
                   ground_speed_mps: ArrayLike, track_deg: ArrayLike, vertical_rate_mps: ArrayLike,
                   roll_deg: ArrayLike) -> dict[str, F64]:
    """Channel inputs from a radar plot (range, azimuth clockwise from north, elevation) and the
    Mode S EHS parameters (BDS 5,0 ground speed, true track, roll; BDS 6,0 vertical rate).

    V_ц = √(GS² + ḣ²), θ = atan2(ḣ, GS), φ = −track, γ_v = roll (positive right wing down turns
    right, i.e. φ decreasing: ω_φ = −(g/V) tan γ); load factors of coordinated flight with
    constant speed and flight-path angle (:func:`~tertiary.filters.kinematic_los.coordinated_load_factors`),
    since EHS carries no accelerometer data."""
    gs, vr = np.asarray(ground_speed_mps, float), np.asarray(vertical_rate_mps, float)
    theta = np.arctan2(vr, gs)
    gamma = np.radians(np.asarray(roll_deg, float))
    n_x, n_y, n_z = los.coordinated_load_factors(theta, gamma)
    return {"range_m": np.asarray(range_m, float), "eps_b": np.radians(np.asarray(elevation_deg, float)),
            "eps_g": -np.radians(np.asarray(azimuth_deg, float)), "speed": np.hypot(gs, vr), "theta": theta,
            "phi": los.wrap_pi(-np.radians(np.asarray(track_deg, float))), "gamma": gamma,
            "n_x": n_x, "n_y": n_y, "n_z": n_z}
