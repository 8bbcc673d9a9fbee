"""The vertical channel: height and its rate as a state of their own.

Height is never the ENU ``z`` of the system tangent plane (z = h − ρ²/2R + …, 785 m low at
ρ = 100 km). Two sources, in order of preference:

1. **Mode C / Mode S pressure altitude** reported by the transponder, quantised to q = 25 ft
   (Mode S, ``mode_s`` present) or q = 100 ft (Mode C only). A per-track two-state Kalman
   filter (h, ḣ) with white-noise vertical acceleration runs over each track's replies:

       x = [h, ḣ]ᵀ,  F(τ) = [[1, τ], [0, 1]],  Q(τ) = q_a [[τ³/3, τ²/2], [τ²/2, τ]]       (A1)
       P⁻ = F P Fᵀ + Q                                                                   (A2)
       ν = z − h⁻,  S = P⁻_hh + R,  R = q²/12 (uniform quantisation error)               (A3)
       K = P⁻ Hᵀ / S,  x⁺ = x⁻ + K ν,  P⁺ = (I − K H) P⁻,  H = [1, 0]                      (A4)

   A reply with |ν| > g·√S + f (``gate_sigma`` g, ``gate_floor_m`` f) is a **garble** (a
   wrong code) and is not used; the ``max_rejects``-th consecutive reply outside the gate
   restarts the filter on itself (a real altitude jump persists, independent garbles do
   not). A refused reply leaves the filter's state as predicted, but the row's output height
   variance takes the refused residual ν² as well: the reply was a garble or the aircraft has
   left the filter's motion (a level-off, the onset of a climb), and until the next reply decides
   the filter's height is no better than the residual it could not explain. Where several
   radars see the aircraft, a source whose filter used (or restarted on) its reply then wins
   the minimum-variance choice over one that is extrapolating a climb the aircraft no longer
   flies. A refused reply whose own downlinked vertical rate (Mode S BDS 6,0, a Comm-B reply
   of its own, which a garbled altitude code does not corrupt) differs from the filter's rate,
   (r_reg − ḣ⁻)² > g_v (P⁻_ḣḣ + σ_v²), says the aircraft has changed its vertical motion (a
   level-off, the onset of a climb): the filter restarts on that reply at once, with the
   register's rate (variance σ_v²), instead of extrapolating the old motion until
   ``max_rejects`` replies have been refused. Any other reply's register (one whose altitude
   was used, refused or missing) then updates every model's rate (H = [0, 1], σ_v²; its
   likelihood updates μ), within the gate g_v of the combined estimate grown by (a_v τ)² (τ the
   time since the previous reply, a_v ``vertical_accel_mps2``): a rate outside the plain gate is
   the onset of a level-off or a climb, which a quantised altitude reply inside the garble gate
   cannot show, and each model's rate variance takes that allowance before the update. Missing
   altitude (null) only predicts. Like an SSR's Mode C validation, a filter is
   *confirmed* once a second reply falls inside the gate of its first; an unconfirmed filter
   restarts on any reply outside its gate, and is output only with an inflated σ
   (``unconfirmed_sigma_m``), so a garbled first reply never outweighs a confirmed source. A
   reply whose Mode S address differs from the filter's (a radar track that swapped aircraft)
   restarts it at once.

   With ``model="imm"`` (default) the filter is an interacting multiple model (Blom &
   Bar-Shalom 1988) of two such filters that differ only in q_a: **level** (q_L, height
   keeping) and **manoeuvre** (q_M, climbs, descents and their level-offs). A level aircraft's
   rate is then known to a few cm/s instead of ~1 m/s, which is what lets a conflict probe
   tell two aircraft 1 000 ft or 2 000 ft apart from a climb into the other's level:

       p_ij(τ) = 1 − exp(−τ/s_i) (i ≠ j),  c_j = Σ_i p_ij μ_i,  μ_i|j = p_ij μ_i / c_j      (A5)
       x0_j = Σ_i μ_i|j x_i,  P0_j = Σ_i μ_i|j [P_i + (x_i − x0_j)(x_i − x0_j)ᵀ]           (A6)
       each model: (A1)–(A4) from (x0_j, P0_j) with q_j; Λ_j = N(ν_j; 0, S_j)              (A7)
       μ_j ∝ Λ_j c_j                                                                      (A8)
       x = Σ_j μ_j x_j,  P = Σ_j μ_j [P_j + (x_j − x)(x_j − x)ᵀ]  (the reported channel)   (A9)

   The garble gate uses the combined prediction; a rejected or missing reply leaves μ = c.

   **Held replies.** A garbled code one low bit off (100 or 200 ft) passes the garble gate of a
   level aircraft, and the manoeuvre model then turns that one reply into a climb or descent of
   5–10 m/s, which a conflict probe extrapolates by half a kilometre over its look-ahead. A
   confirmed filter in level flight (c_level ≥ ½) therefore holds a reply that it would accept
   but that lies beyond ``hold_sigma`` of the level model's prediction: the row outputs the
   prediction, and the next reply decides. Within ``hold_sigma`` of the level prediction, it
   says the aircraft is still level and the held reply is dropped as a garble; otherwise the
   held reply is applied at its own time and then the new one. A real climb or descent
   therefore starts in the estimate one reply later. A garble does not start one at all. A
   reply whose downlinked vertical rate says the vertical motion changed (outside g_v, above)
   is not held: a garbled altitude code does not change the register.
2. **Geodetic height** of an ENU state (elevation-based, the fallback for targets without
   Mode C): h = height above the WGS-84 ellipsoid of the point, ḣ = n̂·v with n̂ the
   ellipsoid normal at the target; variances from the position–velocity covariance along
   n̂: var h = n̂ᵀP_pp n̂, var ḣ = n̂ᵀP_vv n̂, cov = n̂ᵀP_pv n̂ (:func:`geodetic_channel`).

Simulated truth uses the same reference: the pressure altitude of a standard atmosphere with
no QNH and no temperature deviation equals the geodetic height (the geoid undulation and the
geopotential/geometric difference, ≤ h²/R ≈ 8 m at 7 km, are neglected), so barometric and
geodetic heights are directly comparable.

The channel's five columns (:data:`ALT_COLUMNS`) are those the safety stage reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.core import geo
from tertiary.core.jit import arg, ready_for
from tertiary.core.units import FT
from tertiary.stages.tracking.altitude_kernel import filter_recursion

__all__ = ["ALT_COLUMNS", "FT_M", "QUANTUM_MODE_S_M", "QUANTUM_MODE_C_M", "AltitudeConfig", "AltState",
           "quantisation_variance", "predict", "mixture_q", "predict_combined", "update", "update2", "filter_tracks", "filter_tracks_carry",
           "FilterCarry", "geodetic_height_rate",
           "geodetic_channel", "combine_min_variance", "superseded"]

F64 = NDArray[np.float64]
#: metres per foot (:data:`tertiary.core.units.FT`)
FT_M = FT
QUANTUM_MODE_S_M = 25.0 * FT_M
QUANTUM_MODE_C_M = 100.0 * FT_M
#: the vertical channel of ``fused`` and ``tracks`` (safety.conflicts.ALT_COLUMNS)
ALT_COLUMNS = ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_rate_var_m2ps2", "alt_cov_m2ps")


@dataclass(frozen=True)
class AltitudeConfig:
    """Altitude filter settings (module docstring, (A1)–(A4), (A5)–(A9)).

    * ``model``: ``"imm"`` — two models, level flight and vertical manoeuvre (A5)–(A9);
      ``"cv"`` — the single (A1)–(A4) filter with ``q_m2ps3``.
    * ``q_m2ps3``: white-noise vertical-acceleration intensity q_a (m²/s³) of the single
      filter and of the IMM's manoeuvre model.
    * ``q_level_m2ps3``: q_a of the IMM's level model (height keeping: a few ft over minutes).
    * ``level_sojourn_s`` / ``manoeuvre_sojourn_s``: mean time in each mode; the switching
      probability over an interval τ is 1 − exp(−τ / sojourn).
    * ``v0_sigma_mps``: initial ḣ standard deviation (one-point initiation at ḣ = 0).
    * ``gate_sigma``, ``gate_floor_m``: garble gate |ν| ≤ g·√S + f.
    * ``max_rejects``: the this-many-th consecutive reply outside the gate restarts the filter.
    * ``hold_sigma``: the manoeuvre-onset hold of the IMM (module docstring, "Held replies");
      0 disables it.
    * ``vertical_rate_sigma_mps``, ``vertical_rate_gate``, ``vertical_accel_mps2``: σ_v of a
      downlinked vertical rate (BDS 6,0), the χ²(1) gate g_v beyond which it restarts a filter
      that refused the reply, and the vertical acceleration a_v whose (a_v τ)² grows that gate
      for a rate update.
    * ``unconfirmed_sigma_m``: a filter not yet confirmed by a second consistent reply is output
      with at least this height σ (and its initial rate σ), so that any confirmed channel of
      another source wins (minimum variance) but a lone reply still beats the elevation-based
      fallback — which, on a radar track that has just swapped aircraft, is far worse; None:
      unconfirmed filters are not output.
    """

    model: str = "imm"
    unconfirmed_sigma_m: float | None = 60.0
    q_m2ps3: float = 0.5
    q_level_m2ps3: float = 1e-4
    level_sojourn_s: float = 300.0
    manoeuvre_sojourn_s: float = 60.0
    v0_sigma_mps: float = 15.0
    gate_sigma: float = 5.0
    gate_floor_m: float = 45.0
    max_rejects: int = 2
    hold_sigma: float = 3.0
    vertical_rate_sigma_mps: float = 1.0
    vertical_rate_gate: float = 10.83
    vertical_accel_mps2: float = 2.0

    def __post_init__(self) -> None:
        if self.model not in ("imm", "cv"):
            raise ValueError(f"altitude filter: model must be 'imm' or 'cv', got {self.model!r}")
        if not (self.q_m2ps3 > 0 and self.q_level_m2ps3 > 0 and self.v0_sigma_mps > 0 and self.gate_sigma > 0
                and self.gate_floor_m >= 0 and self.level_sojourn_s > 0 and self.manoeuvre_sojourn_s > 0):
            raise ValueError("altitude filter: q_m2ps3, q_level_m2ps3, sojourn times, v0_sigma_mps, gate_sigma "
                             "must be > 0, gate_floor_m >= 0")
        if not self.hold_sigma >= 0:
            raise ValueError(f"altitude filter: hold_sigma must be >= 0, got {self.hold_sigma}")
        if not (self.vertical_rate_sigma_mps > 0 and self.vertical_rate_gate > 0 and self.vertical_accel_mps2 >= 0):
            raise ValueError("altitude filter: vertical_rate_sigma_mps and vertical_rate_gate must be > 0, "
                             "vertical_accel_mps2 >= 0")
        if self.max_rejects < 1:
            raise ValueError("altitude filter: max_rejects must be >= 1")


@dataclass
class AltState:
    """Batch of (h, ḣ) estimates: h, r = ḣ and the covariance entries phh, phr, prr (arrays)."""

    h: F64
    r: F64
    phh: F64
    phr: F64
    prr: F64

    def take(self, idx: NDArray) -> "AltState":
        return AltState(self.h[idx], self.r[idx], self.phh[idx], self.phr[idx], self.prr[idx])

    def put(self, idx: NDArray, other: "AltState") -> None:
        for name in ("h", "r", "phh", "phr", "prr"):
            getattr(self, name)[idx] = getattr(other, name)

    @staticmethod
    def full(n: int, value: float = np.nan) -> "AltState":
        return AltState(*(np.full(n, value) for _ in range(5)))

    def columns(self) -> dict[str, F64]:
        """The :data:`ALT_COLUMNS` arrays."""
        return dict(zip(ALT_COLUMNS, (self.h, self.r, self.phh, self.prr, self.phr)))


def quantisation_variance(quantum_m: ArrayLike) -> F64:
    """R = q²/12: variance of a uniform rounding error of step q (A3)."""
    q = np.asarray(quantum_m, np.float64)
    return q * q / 12.0


def predict(s: AltState, tau: ArrayLike, q: ArrayLike) -> AltState:
    """(A1)–(A2) over ``tau`` seconds with intensity ``q`` (scalars or per row)."""
    t = np.asarray(tau, np.float64)
    t2 = t * t
    phh = s.phh + 2.0 * t * s.phr + t2 * s.prr + q * t2 * t / 3.0
    phr = s.phr + t * s.prr + q * t2 / 2.0
    return AltState(s.h + t * s.r, s.r.copy(), phh, phr, s.prr + q * t)


def mixture_q(mu_last: ArrayLike, tau: ArrayLike, cfg: AltitudeConfig = AltitudeConfig()) -> F64:
    """The intensity the IMM's combined estimate (A9) is extrapolated with over ``tau``:
    Σ_j c_j(τ) q_j with c_j(τ) = Σ_i p_ij(τ) μ_i (A5), ``mu_last`` the manoeuvre model's μ
    after the last reply (NaN: unknown, the manoeuvre model's q). Extrapolating a level
    aircraft's estimate with the manoeuvre model's q alone adds q_M·τ to its rate variance —
    ~1 m/s of rate σ after a scan — and a conflict probe then sees a climb into every
    neighbouring level; the mixture weighs q_M by the probability of a manoeuvre."""
    qs, sojourn = _models(cfg)
    tau = np.asarray(tau, np.float64)
    if len(qs) == 1:
        return np.full(tau.shape, qs[0])
    mu_m = np.asarray(mu_last, np.float64)
    p_lm, p_ml = 1.0 - np.exp(-tau / sojourn[0]), 1.0 - np.exp(-tau / sojourn[1])
    c_m = np.where(np.isfinite(mu_m), mu_m * (1.0 - p_ml) + (1.0 - mu_m) * p_lm, 1.0)
    return (1.0 - c_m) * qs[0] + c_m * qs[1]


def predict_combined(s: AltState, tau: ArrayLike, mu_last: ArrayLike, cfg: AltitudeConfig = AltitudeConfig()
                     ) -> AltState:
    """The combined estimate ``s`` (A9) extrapolated over ``tau`` by :func:`predict` with
    :func:`mixture_q` (the model-mean spread over τ is neglected: the models share the reply
    history, their means differ by far less than their common covariance)."""
    return predict(s, tau, mixture_q(mu_last, tau, cfg))


def update(s: AltState, z: F64, var: F64) -> tuple[AltState, F64, F64]:
    """(A3)–(A4) with a height measurement z of variance ``var``; returns (posterior, ν, S)."""
    nu = z - s.h
    sv = s.phh + var
    kh, kr = s.phh / sv, s.phr / sv
    out = AltState(s.h + kh * nu, s.r + kr * nu, s.phh - kh * s.phh, s.phr - kh * s.phr, s.prr - kr * s.phr)
    return out, nu, sv


def update_rate(s: AltState, z: F64, var: F64) -> tuple[AltState, F64, F64]:
    """Kalman update with a measurement z of the rate ḣ alone (H = [0, 1]) of variance ``var``;
    returns (posterior, ν, S)."""
    nu = z - s.r
    sv = s.prr + var
    kh, kr = s.phr / sv, s.prr / sv
    out = AltState(s.h + kh * nu, s.r + kr * nu, s.phh - kh * s.phr, s.phr - kh * s.prr, s.prr - kr * s.prr)
    return out, nu, sv


def update2(s: AltState, z: AltState) -> AltState:
    """Kalman update with a measurement of both h and ḣ (H = I), R = the covariance of ``z``:
    K = P⁻(P⁻ + R)⁻¹, x⁺ = x⁻ + K(z − x⁻), P⁺ = (I − K)P⁻ (2×2 closed form)."""
    a, b, d = s.phh + z.phh, s.phr + z.phr, s.prr + z.prr
    det = a * d - b * b
    ia, ib, id_ = d / det, -b / det, a / det                         # (P⁻ + R)⁻¹
    k11 = s.phh * ia + s.phr * ib
    k12 = s.phh * ib + s.phr * id_
    k21 = s.phr * ia + s.prr * ib
    k22 = s.phr * ib + s.prr * id_
    dh, dr = z.h - s.h, z.r - s.r
    phh = (1 - k11) * s.phh - k12 * s.phr
    phr = (1 - k11) * s.phr - k12 * s.prr
    prr = -k21 * s.phr + (1 - k22) * s.prr
    return AltState(s.h + k11 * dh + k12 * dr, s.r + k21 * dh + k22 * dr, phh, phr, prr)


def _init(z: F64, var: F64, cfg: AltitudeConfig) -> AltState:
    n = len(z)
    return AltState(z.copy(), np.zeros(n), var.copy(), np.zeros(n), np.full(n, cfg.v0_sigma_mps ** 2))


def _mix(states: list[AltState], w: list[F64]) -> AltState:
    """Moment-matched combination Σ w_i N(x_i, P_i) (A6)/(A9); weights sum to one per row."""
    h = sum(wi * si.h for wi, si in zip(w, states))
    r = sum(wi * si.r for wi, si in zip(w, states))
    phh = sum(wi * (si.phh + (si.h - h) ** 2) for wi, si in zip(w, states))
    phr = sum(wi * (si.phr + (si.h - h) * (si.r - r)) for wi, si in zip(w, states))
    prr = sum(wi * (si.prr + (si.r - r) ** 2) for wi, si in zip(w, states))
    return AltState(h, r, phh, phr, prr)


def _select(cond: NDArray[np.bool_], a: AltState, b: AltState) -> AltState:
    return AltState(*(np.where(cond, getattr(a, f), getattr(b, f)) for f in ("h", "r", "phh", "phr", "prr")))


def _models(cfg: AltitudeConfig) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(q of each model, sojourn of each model): one model for "cv", level + manoeuvre for "imm"."""
    if cfg.model == "cv":
        return (cfg.q_m2ps3,), (np.inf,)
    return (cfg.q_level_m2ps3, cfg.q_m2ps3), (cfg.level_sojourn_s, cfg.manoeuvre_sojourn_s)


def _mix_predict(models: list[AltState], mu: F64, tau: F64, qs, sojourn) -> tuple[list[AltState], F64]:
    """(A5)–(A6) and each model's prediction over ``tau``: (predictions, c) with ``mu``/c (k, n)."""
    if len(models) == 1:
        return [predict(models[0], tau, qs[0])], np.ones((1, len(tau)))
    p_sw = [1.0 - np.exp(-tau / s) for s in sojourn]
    pij = [[1.0 - p_sw[0], p_sw[0]], [p_sw[1], 1.0 - p_sw[1]]]
    c = np.maximum(np.array([pij[0][j] * mu[0] + pij[1][j] * mu[1] for j in range(2)]), 1e-300)
    preds = [predict(_mix(models, [pij[i][j] * mu[i] / c[j] for i in range(2)]), tau, qs[j]) for j in range(2)]
    return preds, c


def _update_models(preds: list[AltState], c: F64, z: F64, var: F64) -> tuple[list[AltState], F64, AltState]:
    """(A7)–(A9): (updated models, μ, combined posterior)."""
    upd, lik = [], []
    for pj in preds:
        u, nu, sv = update(pj, z, var)
        upd.append(u)
        lik.append(np.exp(-0.5 * nu * nu / sv) / np.sqrt(2 * np.pi * sv))
    w = np.array(lik) * c
    tot = w.sum(axis=0)
    mu = np.where(tot > 0, w / np.where(tot > 0, tot, 1.0), c)
    return upd, mu, _mix(upd, list(mu))


@dataclass(frozen=True)
class FilterCarry:
    """Recursion state of :func:`filter_tracks` after each of k tracks' last reply, so that a
    track's later replies continue the same filter (windowed processing): per model j the
    state ``models[j]`` (5, k) = (h, ḣ, P_hh, P_hḣ, P_ḣḣ), the model probabilities ``mu``
    (n_models, k), the last reply time ``t_last`` (k,) (seconds on the caller's time base),
    ``ok`` (running), ``conf`` (confirmed), ``miss`` (consecutive garbles), ``last_id`` (the
    last identity seen, −1 none), the output after the last reply: ``post`` (5, k) and
    ``has`` (k,), and a reply held for the next one's verdict: ``held`` (3, k) = (t, z, R), NaN
    none, with its identity ``held_id``."""

    models: F64
    mu: F64
    t_last: F64
    ok: NDArray[np.bool_]
    conf: NDArray[np.bool_]
    miss: NDArray[np.int64]
    last_id: NDArray[np.int64]
    post: F64
    has: NDArray[np.bool_]
    held: F64
    held_id: NDArray[np.int64]

    @staticmethod
    def fresh(k: int, cfg: AltitudeConfig = AltitudeConfig()) -> "FilterCarry":
        """The state of k tracks that have seen no reply (what :func:`filter_tracks` starts from)."""
        nm = len(_models(cfg)[0])
        return FilterCarry(np.full((nm, 5, k), np.nan), np.full((nm, k), 1.0 / nm), np.zeros(k),
                           np.zeros(k, bool), np.zeros(k, bool), np.zeros(k, np.int64), np.full(k, -1, np.int64),
                           np.full((5, k), np.nan), np.zeros(k, bool), np.full((3, k), np.nan),
                           np.full(k, -1, np.int64))

    def columns(self) -> dict[str, NDArray]:
        """Flat named columns (k values each), e.g. for a polars frame keyed by track."""
        out: dict[str, NDArray] = {}
        for j in range(len(self.models)):
            out.update({f"af_m{j}_{f}": self.models[j, i] for i, f in enumerate(_FIELDS)})
            out[f"af_mu{j}"] = self.mu[j]
        out.update(af_t_last=self.t_last, af_ok=self.ok, af_conf=self.conf, af_miss=self.miss,
                   af_last_id=self.last_id, af_has=self.has)
        out.update({f"af_post_{f}": self.post[i] for i, f in enumerate(_FIELDS)})
        out.update({f"af_held_{f}": self.held[i] for i, f in enumerate(_HELD)})
        out["af_held_id"] = self.held_id
        return out

    @staticmethod
    def from_columns(cols: dict[str, NDArray], cfg: AltitudeConfig = AltitudeConfig()) -> "FilterCarry":
        """Inverse of :meth:`columns`."""
        nm = len(_models(cfg)[0])
        f64 = lambda c: np.asarray(cols[c], np.float64)  # noqa: E731
        return FilterCarry(
            np.stack([np.stack([f64(f"af_m{j}_{f}") for f in _FIELDS]) for j in range(nm)]),
            np.stack([f64(f"af_mu{j}") for j in range(nm)]), f64("af_t_last"),
            np.asarray(cols["af_ok"], bool), np.asarray(cols["af_conf"], bool),
            np.asarray(cols["af_miss"], np.int64), np.asarray(cols["af_last_id"], np.int64),
            np.stack([f64(f"af_post_{f}") for f in _FIELDS]), np.asarray(cols["af_has"], bool),
            np.stack([f64(f"af_held_{f}") for f in _HELD]), np.asarray(cols["af_held_id"], np.int64))

    def take(self, idx: NDArray) -> "FilterCarry":
        return FilterCarry(self.models[:, :, idx], self.mu[:, idx], self.t_last[idx], self.ok[idx], self.conf[idx],
                           self.miss[idx], self.last_id[idx], self.post[:, idx], self.has[idx], self.held[:, idx],
                           self.held_id[idx])


_FIELDS = ("h", "r", "phh", "phr", "prr")
_HELD = ("t", "z", "var")


def _as_state(a: F64) -> AltState:
    return AltState(*(np.array(a[i], np.float64) for i in range(5)))


def _as_array(s: AltState) -> F64:
    return np.stack([getattr(s, f) for f in _FIELDS])


def filter_tracks(t: F64, z: F64, var: F64, starts: NDArray[np.int64], lengths: NDArray[np.int64],
                  cfg: AltitudeConfig = AltitudeConfig(), ident: NDArray[np.int64] | None = None
                  ) -> tuple[AltState, NDArray[np.bool_], NDArray[np.bool_]]:
    """Run the altitude filter ((A1)–(A4), or the IMM (A5)–(A9)) with the garble gate over
    every track's replies.

    ``t`` (n,) seconds, ``z`` (n,) altitudes (NaN = missing), ``var`` (n,) their R, sorted so
    that track g owns rows ``starts[g] : starts[g] + lengths[g]`` in time order. Returns the
    (combined) estimate at each row's time after its update (NaN before the track's first
    altitude), a mask of the rows that have an estimate (confirmed by two consistent replies,
    or unconfirmed with the inflated σ of ``cfg.unconfirmed_sigma_m``),
    and a mask of the replies rejected as garbles. ``ident`` (n,), optional: an identity code
    per reply (e.g. the Mode S address as an integer, < 0 = none); a reply whose identity
    differs from the last one the filter saw restarts it at once — a radar track that swapped
    aircraft must not carry the other aircraft's altitude. The loop runs over the rank within a track, vectorised over tracks (lengths
    sorted descending, so the tracks with more than k rows are a prefix)."""
    out, has, rejected, _ = filter_tracks_carry(t, z, var, starts, lengths, cfg, ident)
    return out, has, rejected


def filter_tracks_carry(t: F64, z: F64, var: F64, starts: NDArray[np.int64], lengths: NDArray[np.int64],
                        cfg: AltitudeConfig = AltitudeConfig(), ident: NDArray[np.int64] | None = None,
                        init: FilterCarry | None = None, compiled: bool = True, with_mu: bool = False,
                        vrate: F64 | None = None) -> tuple:
    """:func:`filter_tracks` continued from ``init`` (one entry per track, in ``starts`` order;
    :meth:`FilterCarry.fresh` entries for tracks never seen; ``t`` on the same time base as
    ``init.t_last``), also returning each track's state after its last row. Running a track's
    replies in two calls, the second from the first's carry, gives the one-call results.
    ``compiled``: the recursion compiled per track (:mod:`tertiary.stages.tracking.altitude_kernel`, the same
    equations); False: the loop below, vectorised over tracks per reply rank (the reference).
    ``with_mu``: a fifth element, the last model's probability after each row (the manoeuvre
    model's for ``"imm"``, 1 for ``"cv"``), what :func:`predict_combined` extrapolates with.
    ``vrate`` (n,), optional: each reply's downlinked vertical rate, NaN where none (module
    docstring)."""
    vr_all = np.full(len(t), np.nan) if vrate is None else np.asarray(vrate, np.float64)
    if compiled and len(starts) and np.min(lengths) >= 1:
        res = _filter_compiled(t, z, var, starts, lengths, cfg, ident, init, vr_all)
        return res if with_mu else res[:4]
    qs, sojourn = _models(cfg)
    nm = len(qs)
    n = len(t)
    out, has, rejected = AltState.full(n), np.zeros(n, bool), np.zeros(n, bool)
    mu_rows = np.full(n, np.nan)
    order = np.argsort(-np.asarray(lengths), kind="stable")
    st, ln = np.asarray(starts)[order], np.asarray(lengths)[order]
    c0 = FilterCarry.fresh(len(st), cfg) if init is None else init.take(order)
    cur = [_as_state(c0.models[j]) for j in range(nm)]
    mu = c0.mu.copy()
    t_last = c0.t_last.copy()
    ok = c0.ok.copy()
    miss = c0.miss.copy()
    conf = c0.conf.copy()
    ids = np.full(n, -1, np.int64) if ident is None else np.asarray(ident, np.int64)
    last_id = c0.last_id.copy()
    held, held_id = c0.held.copy(), c0.held_id.copy()
    holding = cfg.hold_sigma > 0 and nm == 2

    var_v = cfg.vertical_rate_sigma_mps ** 2

    def step(sel, zk, vk, tk, idk, last_pass, vrk):
        """One reply per track of ``sel`` (positions in the sorted order); what the row records."""
        valid = np.isfinite(zk)
        tau = tk - t_last[sel]
        models = [c.take(sel) for c in cur]
        preds, c = _mix_predict(models, mu[:, sel], tau, qs, sojourn)
        upd, mu_u, u = _update_models(preds, c, np.where(valid, zk, 0.0), vk)
        s = _mix(preds, list(c))                                  # combined prediction
        nu, sv = np.where(valid, zk, 0.0) - s.h, s.phh + vk
        inside = np.abs(nu) <= cfg.gate_sigma * np.sqrt(np.maximum(sv, 0.0)) + cfg.gate_floor_m
        run = ok[sel]
        swapped = valid & run & (idk >= 0) & (last_id[sel] >= 0) & (idk != last_id[sel])   # another aircraft
        last_id[sel] = np.where(valid & (idk >= 0), idk, last_id[sel])
        accept = run & valid & inside & ~swapped
        bad = run & valid & ~inside & ~swapped
        hold = np.zeros(len(sel), bool)
        with np.errstate(invalid="ignore"):
            # a register that says the vertical motion changed: the reply is no garble to hold
            changed = np.isfinite(vrk) & ((vrk - s.r) ** 2 > cfg.vertical_rate_gate * (s.prr + var_v))
        if holding and last_pass:
            # a level filter's reply beyond hold_sigma of the level model waits for the next one
            off = np.abs(np.where(valid, zk, 0.0) - preds[0].h) > cfg.hold_sigma * np.sqrt(
                np.maximum(preds[0].phh + vk, 0.0))
            hold = accept & conf[sel] & (c[0] >= 0.5) & off & ~changed
            accept &= ~hold
            held[:, sel] = np.where(hold, np.stack([tk, zk, vk]), held[:, sel])
            held_id[sel] = np.where(hold, idk, held_id[sel])
        miss[sel] = np.where(accept, 0, np.where(bad, miss[sel] + 1, miss[sel]))
        # an unconfirmed filter restarts on any reply outside its gate (a garbled first reply
        # must not hold the channel for max_rejects replies)
        moved = bad & changed
        restart = (valid & ~run) | (bad & ((miss[sel] >= cfg.max_rejects) | ~conf[sel])) | swapped | moved
        held[1, sel] = np.where(restart, np.nan, held[1, sel])
        new = _init(np.where(valid, zk, 0.0), vk, cfg)
        new.r, new.prr = np.where(moved, vrk, new.r), np.where(moved, var_v, new.prr)
        # a reply not used (missing, garble, held): each model keeps its prediction and μ = c
        for j in range(nm):
            cur[j].put(sel, _select(restart, new, _select(accept, upd[j], preds[j])))
        mu[:, sel] = np.where(restart, 1.0 / nm, np.where(accept, mu_u, c))
        nxt = _select(restart, new, _select(accept, u, s))
        refused = bad & ~restart
        nxt.phh = np.where(refused, s.phh + nu ** 2, nxt.phh)       # the refused residual (module docstring)
        miss[sel] = np.where(restart, 0, miss[sel])
        conf[sel] = np.where(restart, False, conf[sel] | accept)
        ok[sel] |= restart
        if last_pass:
            rate = ok[sel] & np.isfinite(vrk) & ~moved & ~hold
            if rate.any():
                nxt = _rate_rows(sel, np.flatnonzero(rate), vrk, tau, nxt, refused, nu)
        t_last[sel] = tk
        return nxt, bad & ~restart

    def _rate_rows(sel, rows, vrk, tau, nxt, refused, nu):
        """:func:`tertiary.stages.tracking.altitude_kernel._rate_step` on the tracks ``sel[rows]``
        (the reference's vectorised form): their models, μ and the rows' output updated."""
        idx = sel[rows]
        models = [c.take(idx) for c in cur]
        w = mu[:, idx]
        comb = _mix(models, list(w))
        z, allow = vrk[rows], (cfg.vertical_accel_mps2 * tau[rows]) ** 2
        d2 = (z - comb.r) ** 2
        onset = d2 > cfg.vertical_rate_gate * (comb.prr + var_v)
        inside = d2 <= cfg.vertical_rate_gate * (comb.prr + var_v + allow)
        lik = []
        for j in range(nm):
            m = models[j]
            new, v, sv = update_rate(AltState(m.h, m.r, m.phh, m.phr, np.where(onset, m.prr + allow, m.prr)),
                                     z, var_v)
            cur[j].put(idx[inside], new.take(inside))
            lik.append(np.exp(-0.5 * v * v / sv) / np.sqrt(2 * np.pi * sv) * w[j])
        tot = sum(lik)
        if nm > 1:
            upd_mu = np.where(tot > 0, np.stack(lik) / np.where(tot > 0, tot, 1.0), w)
            mu[:, idx[inside]] = upd_mu[:, inside]
        done = _mix([c.take(idx) for c in cur], list(mu[:, idx]))
        at = rows[inside]
        out = AltState(nxt.h.copy(), nxt.r.copy(), nxt.phh.copy(), nxt.phr.copy(), nxt.prr.copy())
        out.put(at, done.take(inside))
        out.phh[at] = np.where(refused[at], out.phh[at] + nu[at] ** 2, out.phh[at])
        return out

    alive = np.searchsorted(-ln, -np.arange(ln.max(initial=0)), side="left")
    for k, m in enumerate(alive):
        idx = st[:m] + k
        sel = np.arange(m)
        zk, vk, tk, idk = z[idx], var[idx], t[idx], ids[idx]
        pending = np.isfinite(held[1, :m]) & np.isfinite(zk)
        if pending.any():
            # a held reply is dropped (a garble) when this reply says the track is level, else
            # applied just before it (at the last time when rows without altitude came between)
            p = np.flatnonzero(pending)
            lvl = _mix_predict([c.take(p) for c in cur], mu[:, p], tk[p] - t_last[p], qs, sojourn)[0][0]
            level = np.abs(zk[p] - lvl.h) <= cfg.hold_sigma * np.sqrt(np.maximum(lvl.phh + vk[p], 0.0))
            apply = p[~level]
            hz = held[:, apply].copy()
            held[1, p] = np.nan
            if apply.size:
                step(apply, hz[1], hz[2], np.maximum(hz[0], t_last[apply]), held_id[apply], False,
                     np.full(apply.size, np.nan))
        nxt, rej = step(sel, zk, vk, tk, idk, True, vr_all[idx])
        if cfg.unconfirmed_sigma_m is not None:
            weak = ok[:m] & ~conf[:m]
            nxt.phh = np.where(weak, np.maximum(nxt.phh, cfg.unconfirmed_sigma_m ** 2), nxt.phh)
            has[idx] = ok[:m]
        else:
            has[idx] = ok[:m] & conf[:m]
        out.put(idx, nxt)
        mu_rows[idx] = mu[nm - 1, :m]
        rejected[idx] = rej
    last = st + ln - 1
    final = FilterCarry(np.stack([_as_array(cj) for cj in cur]), mu, t_last, ok, conf, miss, last_id,
                        _as_array(out.take(last)), has[last], held, held_id)
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    return (out, has, rejected, final.take(inv)) + ((mu_rows,) if with_mu else ())


def _filter_compiled(t: F64, z: F64, var: F64, starts: NDArray[np.int64], lengths: NDArray[np.int64],
                     cfg: AltitudeConfig, ident: NDArray[np.int64] | None, init: FilterCarry | None,
                     vrate: F64) -> tuple[AltState, NDArray[np.bool_], NDArray[np.bool_], FilterCarry]:
    """:func:`filter_tracks_carry` by :func:`tertiary.stages.tracking.altitude_kernel.filter_recursion`."""
    qs, sojourn = _models(cfg)
    n, k = len(t), len(starts)
    c0 = FilterCarry.fresh(k, cfg) if init is None else init
    # C-ordered copies: a carry taken from another window's state can be F-ordered or strided,
    # and each layout would be a compiled signature of its own
    carry = FilterCarry(*(np.array(a, d, order="C") for a, d in (
        (c0.models, np.float64), (c0.mu, np.float64), (c0.t_last, np.float64), (c0.ok, bool),
        (c0.conf, bool), (c0.miss, np.int64), (c0.last_id, np.int64), (c0.post, np.float64),
        (c0.has, bool), (c0.held, np.float64), (c0.held_id, np.int64))))
    out = np.full((6, n), np.nan)          # the state and the last model's probability
    has, rejected = np.zeros(n, bool), np.zeros(n, bool)
    ids = np.full(n, -1, np.int64) if ident is None else arg(ident, np.int64)
    weak = -1.0 if cfg.unconfirmed_sigma_m is None else float(cfg.unconfirmed_sigma_m) ** 2
    ready_for("altitude")
    # every array writable and contiguous (jit.arg): one compiled signature, not one per
    # read-only column the caller happens to pass
    filter_recursion(arg(t), arg(z), arg(var), arg(vrate), ids, arg(starts, np.int64), arg(lengths, np.int64),
            arg(qs), arg(sojourn),
            float(cfg.gate_sigma), float(cfg.gate_floor_m), int(cfg.max_rejects), float(cfg.v0_sigma_mps), weak,
            float(cfg.hold_sigma), float(cfg.vertical_rate_sigma_mps) ** 2, float(cfg.vertical_rate_gate),
            float(cfg.vertical_accel_mps2), carry.models, carry.mu, carry.t_last, carry.ok, carry.conf, carry.miss,
            carry.last_id, carry.post, carry.has, carry.held, carry.held_id, out, has, rejected)
    return _as_state(out), has, rejected, carry, np.array(out[5])


def geodetic_height_rate(pos: ArrayLike, vel: ArrayLike, frame: geo.LocalFrame | None
                         ) -> tuple[F64, F64, F64]:
    """Height above the WGS-84 ellipsoid, its rate and the unit normal n̂ (in the system ENU
    axes) of system-frame positions/velocities (n, 3): h of frame.to_ecef(p), ḣ = n̂·v.

    ``frame=None``: a sphere of radius :data:`tertiary.core.geo.EARTH_RADIUS_M` through the origin
    (h from the origin's height; ≤ 9 m off the ellipsoid at ρ = 150 km, ≤ 4 m at 100 km, from
    the ±0.5 % variation of the radius of curvature)."""
    p = np.asarray(pos, np.float64).reshape(-1, 3)
    v = np.asarray(vel, np.float64).reshape(-1, 3)
    if frame is None:
        c = p + np.array([0.0, 0.0, geo.EARTH_RADIUS_M])
        norm = np.sqrt(np.einsum("ij,ij->i", c, c))
        up = c / norm[:, None]
        h = norm - geo.EARTH_RADIUS_M
    else:
        lat, lon, h = geo.ecef_to_geodetic(*frame.to_ecef(p[:, 0], p[:, 1], p[:, 2]))
        la, lo = np.radians(lat), np.radians(lon)
        n_ecef = np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
        up = n_ecef @ frame.rotation.T
        h = np.asarray(h, np.float64)
    return h, np.einsum("ij,ij->i", up, v), up


def geodetic_channel(x6: F64, cov66: F64, frame: geo.LocalFrame | None) -> AltState:
    """The vertical channel of ENU states x6 (n, 6) with covariances (n, 6, 6): geodetic h, ḣ
    (:func:`geodetic_height_rate`) and var h = n̂ᵀP_pp n̂, cov = n̂ᵀP_pv n̂, var ḣ = n̂ᵀP_vv n̂."""
    h, hdot, up = geodetic_height_rate(x6[:, :3], x6[:, 3:], frame)
    quad = lambda blk: np.einsum("ni,nij,nj->n", up, blk, up)  # noqa: E731
    return AltState(h, hdot, quad(cov66[:, :3, :3]), quad(cov66[:, :3, 3:]), quad(cov66[:, 3:, 3:]))


def superseded(s: AltState, valid: NDArray[np.bool_], group: NDArray[np.int64], t_reply: NDArray[np.int64],
               cfg: AltitudeConfig) -> NDArray[np.bool_]:
    """Per source row, whether the group's source with the latest reply contradicts it: its
    height, both extrapolated to the epoch, lies beyond the garble gate of their combined
    variance (|Δh| > g·√(P_a + P_b) + f, ``gate_sigma`` g, ``gate_floor_m`` f). The older
    source is extrapolating a motion that a newer reply of the same transponder no longer shows
    (the first replies after a level-off or a climb's onset): in a steady climb its filter is
    confident, and the newer source, restarted on its reply, is not yet, so the minimum-variance
    choice alone would keep the obsolete climb. A garble accepted by a filter moves it by less
    than its gate, and an unconfirmed restart carries an inflated σ: neither supersedes."""
    out = np.zeros(len(valid), bool)
    rows = np.flatnonzero(valid)
    if rows.size == 0:
        return out
    order = rows[np.lexsort((s.phh[rows], -t_reply[rows], group[rows]))]      # newest first, then best
    g = group[order]
    first = np.r_[True, g[1:] != g[:-1]]
    newest = np.empty(int(group.max()) + 1, np.int64)
    newest[g[first]] = order[first]
    f = newest[group[rows]]
    gate = cfg.gate_sigma * np.sqrt(s.phh[rows] + s.phh[f]) + cfg.gate_floor_m
    out[rows] = np.abs(s.h[rows] - s.h[f]) > gate
    return out


def combine_min_variance(s: AltState, valid: NDArray[np.bool_], group: NDArray[np.int64], n_groups: int
                         ) -> tuple[AltState, NDArray[np.bool_]]:
    """Per group, the valid source with the smallest var h. Every radar decodes the same
    transponder reply (same code, same quantisation error), so their estimates are strongly
    correlated: averaging them as independent would understate the variance; the best one is
    kept instead. Returns the per-group state (NaN where no valid source) and its mask."""
    out = AltState.full(n_groups)
    rows = np.flatnonzero(valid)
    if rows.size == 0:
        return out, np.zeros(n_groups, bool)
    order = rows[np.lexsort((s.phh[rows], group[rows]))]
    g = group[order]
    first = np.r_[True, g[1:] != g[:-1]]
    pick = order[first]
    out.put(group[pick], s.take(pick))
    has = np.zeros(n_groups, bool)
    has[group[pick]] = True
    return out, has
