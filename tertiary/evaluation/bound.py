"""Posterior Cramér–Rao lower bound (PCRB) for the truth's own motion (evaluation, stage ``bound``).

What is bounded
---------------
Model M, per Cartesian axis of the system frame, state (p, v, a): between consecutive events
t_{k−1} < t_k (an aircraft's illuminations and scored epochs, τ = t_k − t_{k−1})

    x_k = Φ(τ) x_{k−1} + ξ_k d_k,   Φ(τ) = [[1, τ, τ²/2], [0, 1, τ], [0, 0, 1]],   ξ_k ~ N(0, 1)   (M1)
    d_k = Σ_{s_m ∈ (t_{k−1}, t_k]} Δa_m (½(t_k − s_m)², t_k − s_m, 1)                           (M2)

i.i.d. per axis and interval: Q_k = d_k d_kᵀ. The truth's acceleration is piecewise constant
between its samples s_m, ā_m = (v(s_{m+W}) − v(s_{m−W})) / (s_{m+W} − s_{m−W}) (centred
velocity difference over ± ``accel_half_window_s``, clipped to the aircraft's span: it
reproduces the simulator's piecewise-constant commands up to a spread of each onset over the
window, and averages out the quantised, jittery velocities of ADS-B truth rather than taking
them for manoeuvres — a jitter taken for manoeuvres would dilute the bound with independent
random-sign steps, a random walk the truth's mean-reverting jitter does not make), and
Δa_m = ā_m − ā_{m−1} are its steps; d_k is the deviation of that
trajectory from the constant-acceleration prediction over the interval. The truth (its
fitted acceleration profile) is the realisation ξ ≡ 1 of M. Prior at an aircraft's first event:
p σ ``p0_sigma_m`` (diffuse), v σ ``v0_sigma_mps``, a ~ N(0, diag(ā²)) of the truth there.

So d_k = 0 wherever the truth's acceleration is constant — straight legs, steady climbs and
descents, a constant deceleration: no process noise, the bound integrates every plot since the
last manoeuvre — and at a manoeuvre (turn entry and exit, a vertical-rate or speed change,
the rotation of the acceleration inside a turn) the information about (p, v, a) is diluted by
exactly that manoeuvre's size along its own profile.

Why it is a lower bound: the MSE of **any** estimator of x_k from the radar measurements up to
k, averaged over M, is bounded below by J_k⁻¹ (Tichavský, Muravchik, Nehorai 1998, IEEE TSP
46(5), eq. (21)):

    J_{k+1} = D22 − D21 (J_k + D11)⁻¹ D12 + J_Z(k+1)                                 (T21)

and for linear-Gaussian M the D terms reduce (T21) to the Kalman covariance recursion on the
*expected* measurement information (Tichavský eq. (34); no measurement values enter; in this
covariance form it holds for the singular Q = d dᵀ and Q = 0 of M, where the information form's
Q⁻¹ does not exist):

    P⁻ = Φ P Φᵀ + Q,     P = (P⁻⁻¹ + J_Z)⁻¹,     PCRB_k = P_k                          (T34)

The optimal estimator under M is told the instant, the axis and the time profile of every
manoeuvre and that nothing happens between them; only the sign and scale ξ of each are
unknown. It is an estimator that knew the manoeuvres' onsets but not their magnitudes, with
every plot's expected information and no bias, clutter or misassociation. The pipeline's
estimators know none of this — they must detect each manoeuvre from the plots, and carry
process noise on straight legs against manoeuvres to come — so their MSE on the truth lies
above M's optimum, which (T34) gives. (A Bayesian bound averages over M's ensemble; on the
single realisation ξ ≡ 1, each manoeuvre exactly one σ, an estimator could sit below it only
by being biased towards that realisation, i.e. knowing the manoeuvres before their plots.)

Measurements: each radar measures (range, azimuth, elevation) with independent Gaussian errors
of its nominal σ (``radars`` table; the simulator's noise, :mod:`tertiary.simulate.radar`).
The information of one plot about the system-frame position p is

    J_Z = Pd · Aᵀ R_polar⁻¹ A,   A = ∂(r, β, ε)/∂p = J_polar⁻¹ M,   i.e.  J_Z⁻¹ = G R_polar Gᵀ / Pd,
    G = Mᵀ J_polar                                                                     (seed 002 eq. 12)

with J_polar = ∂(e, n, u)/∂(r, β, ε) at the **true** position (:func:`tertiary.core.geo.polar_jacobian`)
and M the system-to-site rotation. Detection with probability Pd and no clutter: the expected
information is Pd times the detected one (the information-reduction-factor bound, Niu et al.
2001; without clutter the factor is exactly Pd), summed over every radar that illuminates the
aircraft at that instant (sequential updates at equal times = the stacked update).

When a radar illuminates an aircraft: the simulator's scan schedule. Scan k starts at
s_k = s_0 + k·T (T = ``scan_period_s``); a ``synchronous`` radar samples at s_k, a rotating one
at s_k + T·β/360 (β the aircraft's azimuth from the site; two fixed-point iterations, as the
simulator). s_0 is recovered from the radar's own reports in the recording (every report,
target or clutter, is stamped s_k + T·β/360 + ``time_offset_s``): the circular median of the
report times minus that, modulo T, over every report with a time and an azimuth, read before
the first window. The aircraft is covered when its range is at most ``max_range_m`` and its
elevation within [``min_elevation_deg``, max elevation (the scenario's, else 90°)] and the
truth exists (no truth gap) at that instant. Truth between samples is the cubic Hermite
interpolation of the truth positions and velocities (the simulator's interpolation).

MLAT / WAM (a ``radars`` row of kind ``mlat``, :mod:`tertiary.sensors.mlat`): a Cartesian plot
z = H p + w in the site's horizontal plane, H = the first two rows of the system-to-site
rotation, w ~ N(0, R_xy); its Fisher information is the linear model's

    J_Z = Hᵀ R_xy⁻¹ H + e_u e_uᵀ/V,     i.e.  R_eq = M diag(R_xy, V) Mᵀ                (MLAT-3)

(M the site-to-system rotation, e_u the site's vertical). Its events are its plots on the
aircraft (report times less its clock offset), each with the covariance the plot states (else
the sensor's nominal ``sigma_range_m`` per axis — a lower bound on the achieved accuracy keeps
J_Z an upper bound on the information and the PCRB a lower bound): the information of the
plots received, no Pd factor. The plot's height is its Mode C reply, which the pictures' z then
carries; V = (25 ft)²/12, the finest quantisation's variance, gives it at least the information
of any reply (a Gaussian stand-in: a quantised reply has no regular Fisher information; the
stand-in's is the larger, so the bound stays below).

Downlinked velocity: a Mode S aircraft's ground speed and true track (BDS 5,0), which the
trackers take as a velocity measurement, carry information the plots do not. At every
illumination of an aircraft from its first report that carries a Mode S address on (less the
longest scan period and clock offset, :func:`mode_s_lead_s`: the illumination that made the
report counts; before it no report of the aircraft carries a velocity), each radar adds a measurement
of the velocity, H selecting (v_x, v_y, v_z), with R = Lᵀ diag(R_h, V) L: L the system-to-local
rotation at the aircraft, R_h σ ``ehs_speed_sigma_mps`` along the truth's track and its speed ×
``ehs_track_sigma_deg`` across it (the registers' noise; the quantisation is left out, which
only adds information), V = :data:`VELOCITY_VERTICAL_VAR` (no vertical information), times 1/Pd
as a plot. Every radar and every illumination counts, even where a radar did not extract the
register: more information than the data hold keeps the bound below.

Barometric height: with ``mode_c_height`` each radar plot also measures the height along the
local vertical at the aircraft, with the 25 ft quantum's variance (a Gaussian stand-in with at
least any reply's information, as for MLAT; :mod:`tertiary.evaluation.bound_measurements`).
It is off by default: the pictures' system-frame z is estimated from the radars' elevations (their
height is the separate channel), so with it the 3-D bound falls far below every picture's 3-D
error while the horizontal bound hardly moves.

What is not in the bound: radar biases, clock offsets, clutter and association errors, which
only add error, so leaving them out keeps the bound a lower bound. The run's notes state the model (:meth:`BoundConfig.describe`, :data:`MODEL`).

Metrics (stage ``bound``, one block per picture)
------------------------------------------------
Over the *same scored samples* (run, epoch, truth_id) as a picture's accuracy rows, the bound is
pooled as the RMSE is: ``pcrb_pos_m`` = sqrt(mean_k mean_{j∈k} tr P_pos), ``pcrb_horizontal_m``
(P_xx + P_yy), ``pcrb_vel_mps`` (tr P_vel), and the signed gaps ``gap_pos_m`` =
``rmse_pos_m`` − ``pcrb_pos_m``, ``gap_horizontal_m``, ``gap_vel_mps`` (> 0: above the bound),
per segment all/straight/turn. A sample at an epoch before its aircraft's first measurement
holds only the prior; the accuracy scores an aircraft from its first reported epoch on, so such a
sample is rare (a plot stamped just before an epoch that the radar's clock offset puts just after
it) and is counted in ``bound_unmeasured_samples``, not pooled. The bound is the same in every
Monte-Carlo run (the geometry,
the truth and the expected information do not depend on the noise draw), so it is computed
once per (truth_id, epoch).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.jit import arg, ready_for
from tertiary.core.units import FT, US
from tertiary.evaluation.bound_kernel import pcrb_ca9
from tertiary.evaluation.bound_pooling import BOUND_METRICS, UNMEASURED, bound_metrics, bound_rows, bound_sums
from tertiary.evaluation.bound_measurements import (VELOCITY_VERTICAL_VAR, mode_s_first, velocity_covariance,
                                                    with_height)
from tertiary.evaluation.bound_truth import ACCEL_HALF_WINDOW_S, Truth
from tertiary.contract import TABLES, TIME
from tertiary.contract.cast import cast_column
from tertiary.sensors import mlat
from tertiary.sensors.adsb import sigma_from_nacp

__all__ = ["BoundConfig", "CARRIED", "pcrb_linear", "illuminations", "pcrb_at", "pcrb_carried", "mode_s_lead_s",
           "bound_metrics", "BOUND_METRICS", "UNMEASURED",
           "MODEL", "bound_setup", "block_sums", "read_sums", "bound_stage", "scan_origins"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: 9-state (x, vx, ax, y, vy, ay, z, vz, az) indices of the positions and velocities
POS = np.array([0, 3, 6])
VEL = np.array([1, 4, 7])
#: drop the scans that cannot bring an aircraft within a rotating radar's range before the
#: beam-passage iterations (:func:`_radar_events`; the same events, found sooner)
RANGE_SCREEN = True
#: variance (m²) along the site's vertical of an MLAT plot in the bound: the plot is placed at its
#: Mode C height, so the pictures' z takes that reply's information; the finest quantisation's
#: q²/12 (25 ft, Mode S) gives it at least the information any reply holds (module docstring)
MLAT_VERTICAL_VAR_M2 = (25.0 * FT) ** 2 / 12.0


@dataclass(frozen=True)
class BoundConfig:
    """The bound's model M (module docstring): the half-width of the centred velocity
    difference that gives the truth's acceleration (``accel_half_window_s``), whether a radar
    plot's barometric height counts (``mode_c_height``), whether a Mode S
    aircraft's downlinked ground velocity counts (``downlinked_velocity``; off: the bound of an
    estimator of the radar plots alone) and its noise (``ehs_speed_sigma_mps``,
    ``ehs_track_sigma_deg``: the simulator's register noise, :class:`tertiary.simulate.ehs.EhsConfig`), the prior
    (``p0_sigma_m``, ``v0_sigma_mps``; the acceleration's is the truth's own) and the elevation
    limit used when the scenario does not give one per radar (``max_elevation_deg``)."""

    accel_half_window_s: float = ACCEL_HALF_WINDOW_S
    mode_c_height: bool = False
    downlinked_velocity: bool = True
    ehs_speed_sigma_mps: float = 0.5
    ehs_track_sigma_deg: float = 0.2
    p0_sigma_m: float = 10_000.0
    v0_sigma_mps: float = 300.0
    max_elevation_deg: float = 90.0

    def __post_init__(self) -> None:
        # a zero σ makes a velocity event's covariance singular (the recursion's Cholesky gives NaN)
        if not (self.ehs_speed_sigma_mps > 0 and self.ehs_track_sigma_deg > 0):          # NaN fails too
            raise ValueError(f"need ehs_speed_sigma_mps and ehs_track_sigma_deg > 0, got {self.ehs_speed_sigma_mps}, "
                             f"{self.ehs_track_sigma_deg}")

    @classmethod
    def from_scenario(cls, scenario) -> "BoundConfig":
        """The bound of a scenario: M is fitted to the truth, whatever the scenario's filters
        assume, so every scenario has the defaults."""
        return cls()

    def describe(self) -> str:
        """The motion model the bound assumes, one line (the run's note)."""
        return (f"motion model of the bound: the truth's own piecewise-constant acceleration (per axis "
                f"(p, v, a), acceleration from ±{self.accel_half_window_s:g} s velocity differences of the "
                f"truth); process noise per interval = the truth's deviation from the constant-acceleration "
                f"prediction (rank one, sign unknown): none on straight legs and steady climbs, each "
                f"manoeuvre's onset known, not its magnitude; prior σ_p {self.p0_sigma_m:g} m, "
                f"σ_v {self.v0_sigma_mps:g} m/s; radar plots (nominal σ, Pd, scan schedule"
                + (", with their barometric height at the 25 ft quantum's variance)" if self.mode_c_height else ")")
                + (f" and, for a Mode S aircraft, a downlinked ground velocity at every illumination from its first "
                   f"Mode S report on "
                   f"(σ {self.ehs_speed_sigma_mps:g} m/s along the track, {self.ehs_track_sigma_deg:g}° across)"
                   if self.downlinked_velocity else " only"))


#: the motion model of the default bound, as the run's notes state it
MODEL = BoundConfig().describe()


# --------------------------------------------------------------------------- recursion


def _blockdiag3(b: F64) -> F64:
    out = np.zeros(b.shape[:-2] + (9, 9))
    for a in range(3):
        out[..., 3 * a:3 * a + 3, 3 * a:3 * a + 3] = b
    return out


def pcrb_linear(t: F64, r_eq: F64, starts: I64, lengths: I64, phi_q, p0: F64, obs: I64,
                record: NDArray[np.bool_], summary: Callable[[F64], F64] | None = None) -> F64:
    """The recursion (T34) over many independent event sequences at once.

    Sequence g owns rows ``starts[g] : starts[g] + lengths[g]`` (time order ``t``); row i
    carries the inverse of its measurement information about the observed states ``obs``,
    ``r_eq[i]`` (m, m), or NaN for an event without a measurement (an output epoch).
    ``phi_q(tau)`` returns Φ(τ), Q(τ) stacked (n, d, d), or ``phi_q`` is that pair per row
    already (Φ, Q of row i from the previous row); ``p0`` (d, d), or (n_sequences, d, d) one per
    sequence, is the prior at a sequence's first event. Returns the bound P (n_record, d, d) at
    the ``record`` rows, in row order — or, with ``summary`` (stacked P (m, d, d) → (m, s)), only
    what it keeps of each (n_record, s): the recorded bounds of a long recording are never held
    whole. The loop runs over the event rank, batched over the sequences.
    """
    n, d = len(t), p0.shape[-1]
    slot = np.full(n, -1)
    slot[record] = np.arange(int(record.sum()))
    keep = summary or (lambda pk: pk)
    out = np.full((int(record.sum()), *keep(np.zeros((1, d, d))).shape[1:]), np.nan)
    order = np.argsort(-np.asarray(lengths), kind="stable")
    st, ln = np.asarray(starts)[order], np.asarray(lengths)[order]
    p = (np.asarray(p0)[order] if np.ndim(p0) == 3 else np.broadcast_to(p0, (len(st), d, d))).copy()
    tau = np.zeros(n)
    tau[1:] = np.diff(t)
    alive = np.searchsorted(-ln, -np.arange(ln.max(initial=0)), side="left")   # sequences longer than k
    has = ~np.isnan(r_eq[:, 0, 0])
    for k, m in enumerate(alive):
        idx = st[:m] + k
        pk = p[:m]
        if k:
            phi, q = phi_q(tau[idx]) if callable(phi_q) else (phi_q[0][idx], phi_q[1][idx])
            pk = phi @ pk @ phi.swapaxes(1, 2) + q
        u = has[idx]
        if u.any():
            pk[u] = _update(pk[u], r_eq[idx[u]], obs)
        p[:m] = pk
        sl = slot[idx]
        hit = sl >= 0
        if hit.any():
            out[sl[hit]] = keep(pk[hit])
    return out


def _update(p: F64, r: F64, obs: I64) -> F64:
    """P − P Hᵀ (H P Hᵀ + R)⁻¹ H P for H selecting ``obs`` (= (P⁻¹ + Hᵀ R⁻¹ H)⁻¹), symmetrised."""
    ph = p[:, :, obs]
    s = ph[:, obs, :] + r
    k = np.linalg.solve(s, ph.swapaxes(1, 2)).swapaxes(1, 2)
    out = p - k @ ph.swapaxes(1, 2)
    return 0.5 * (out + out.swapaxes(1, 2))


# --------------------------------------------------------------------------- truth and scans


def _scan_origin(times_s: F64, az_deg: F64, period: float, rotating: bool) -> float | None:
    """s_0 mod T from a radar's report times (true seconds): the circular median of
    (t − T·β/360) mod T (rotating) or t mod T (synchronous)."""
    if len(times_s) == 0:
        return None
    s = times_s - (period * np.mod(az_deg, 360.0) / 360.0 if rotating else 0.0)
    r = np.mod(s, period)
    # unwrap around the first value so that a phase near 0 ≡ T is not split in two
    r = np.mod(r - r[0] + period / 2, period) - period / 2 + r[0]
    return float(np.mod(np.median(r), period))


def _radar_events(tr: Truth, row: dict, s0: float, origin: geo.LocalFrame, max_el: float, height: bool = True,
                  between: tuple[float, float] | None = None) -> tuple[I64, F64, F64]:
    """(aircraft index, time, R_eq = G R_polar Gᵀ / Pd) of every illumination of one radar that
    covers an aircraft (module docstring); with ``height``, the plot's barometric height too
    (:func:`tertiary.evaluation.bound_measurements.with_height`); ``between``: the scans that
    can illuminate in [lo, hi) s only (those starting in [lo − T, hi])."""
    T = float(row["scan_period_s"])
    pd = float(row.get("pd") if row.get("pd") is not None else 1.0)
    if not (T > 0 and pd > 0):
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3, 3))
    lo_t, hi_t = tr.t[tr.first], tr.t[tr.first + tr.count - 1]
    k_lo = np.ceil((lo_t - T - s0) / T).astype(np.int64)
    k_hi = np.floor((hi_t - s0) / T).astype(np.int64)
    if between is not None:
        k_lo = np.maximum(k_lo, int(np.ceil((between[0] - T - s0) / T)))
        k_hi = np.minimum(k_hi, int(np.floor((between[1] - s0) / T)))
    n = np.maximum(k_hi - k_lo + 1, 0)
    a = np.repeat(np.arange(len(tr.ids)), n)
    k = np.repeat(k_lo, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
    start = s0 + k * T
    site = geo.LocalFrame(float(row["lat_deg"]), float(row["lon_deg"]), float(row["alt_m"]))
    rot, off = origin.rotation_to(site), origin.offset_in(site)
    t = start.astype(float)
    rotating = (row.get("timing") or "rotating") == "rotating"
    pos, ok = tr.at(a, t)
    if rotating and RANGE_SCREEN:
        # scans that cannot bring the aircraft within range are dropped before the beam-passage
        # iterations: the beam passes within T s of the scan's start, and an aircraft moves at
        # most its top speed × T meanwhile (× 2 for the interpolation, + 1 km); an aircraft with
        # no position at the scan's start (a truth gap, outside its span) is kept
        reach = float(row["max_range_m"]) + 2.0 * tr.top_speed * T + 1000.0
        keep = ~ok | (np.linalg.norm(pos @ rot.T + off, axis=1) <= reach)
        a, start, t, pos, ok = a[keep], start[keep], t[keep], pos[keep], ok[keep]
    if rotating:                      # beam passage: two fixed-point iterations, as the simulator
        for _ in range(2):
            e, nn, _u = (pos @ rot.T + off).T
            t = start + T * np.mod(np.degrees(np.arctan2(e, nn)), 360.0) / 360.0
            pos, ok = tr.at(a, t)
    rng, az, el = geo.enu_to_polar(*(pos @ rot.T + off).T)
    min_el = float(row.get("min_elevation_deg") if row.get("min_elevation_deg") is not None else -90.0)
    ok &= (rng <= float(row["max_range_m"])) & (el >= min_el) & (el <= max_el) & (rng > 0)
    a, t, rng, az, el, pos = a[ok], t[ok], rng[ok], az[ok], el[ok], pos[ok]
    var = np.array([float(row["sigma_range_m"]) ** 2, np.radians(float(row["sigma_azimuth_deg"])) ** 2,
                    np.radians(float(row["sigma_elevation_deg"])) ** 2])
    g = rot.T @ geo.polar_jacobian(rng, az, el)                       # ∂p_sys/∂(r, β, ε)
    r_eq = (g * var[None, None, :]) @ g.swapaxes(1, 2)
    if height:
        r_eq = with_height(r_eq, pos, origin)
    return a, t, r_eq / pd


def _mlat_events(tr: Truth, row: dict, reports: pl.DataFrame, origin: geo.LocalFrame, t0_us: int
                 ) -> tuple[I64, F64, F64]:
    """(aircraft index, time, R_eq) of every plot of an MLAT sensor on an aircraft of ``tr``
    or an ADS-B station (module docstring, "MLAT / WAM"): R_eq = M R_local Mᵀ with the plot's stated
    horizontal covariance (MLAT-1), else its NACp's σ (ADSB-1), else the sensor's nominal ``sigma_range_m`` on each axis, and
    :data:`MLAT_VERTICAL_VAR_M2` along the site's vertical."""
    cols = [c for c in ("truth_id", "time", "plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m", "adsb_nacp")
            if c in reports.columns]
    rep = reports.filter((pl.col("radar_id") == row["radar_id"]) & pl.col("truth_id").is_not_null()).select(cols) \
        if "truth_id" in reports.columns else reports.clear().select("time")
    if rep.height == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3, 3))
    tid = rep["truth_id"].cast(pl.Int64).to_numpy()
    pos = np.searchsorted(tr.ids, tid)
    known = (pos < len(tr.ids)) & (tr.ids[np.minimum(pos, len(tr.ids) - 1)] == tid)
    a = np.where(known, pos, 0)
    t = (rep["time"].cast(TIME).dt.epoch("us").to_numpy() - t0_us) / US - float(row.get("time_offset_s") or 0.0)
    ok = known & tr.at(a, t)[1]
    declared = sigma_from_nacp(rep["adsb_nacp"].cast(pl.Float64).fill_null(np.nan).to_numpy()
                               if "adsb_nacp" in rep.columns else np.full(rep.height, np.nan))
    nominal = np.where(np.isfinite(declared), declared, float(row["sigma_range_m"]))    # (ADSB-1)
    sig = [rep[c].cast(pl.Float64).fill_null(np.nan).to_numpy() if c in rep.columns else np.full(rep.height, np.nan)
           for c in ("plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m")]
    stated = np.isfinite(sig[0]) & np.isfinite(sig[1])
    r = np.zeros((rep.height, 3, 3))
    r[:, :2, :2] = mlat.plot_cov_xy(np.where(stated, sig[0], nominal), np.where(stated, sig[1], nominal),
                                    np.where(stated & np.isfinite(sig[2]), sig[2], 0.0))
    r[:, 2, 2] = MLAT_VERTICAL_VAR_M2
    site = geo.LocalFrame(float(row["lat_deg"]), float(row["lon_deg"]), float(row["alt_m"]))
    return a[ok], t[ok], geo.congruence(site.rotation_to(origin), r[ok])


def illuminations(truth: pl.DataFrame | Truth, radars: pl.DataFrame, reports: pl.DataFrame, origin: geo.LocalFrame,
                  cfg: BoundConfig = BoundConfig(), max_elevation: dict[str, float] | None = None,
                  t0_us: int | None = None, origins: dict[int, float] | None = None,
                  mode_s: pl.DataFrame | None = None, between: tuple[float, float] | None = None,
                  gaps: pl.DataFrame | None = None) -> pl.DataFrame:
    """Every (truth_id, radar_id, time) at which a radar's beam covers an aircraft, with the
    expected measurement information as its inverse ``r_eq`` (flattened 3×3, m²) — the
    events of the bound (module docstring). ``max_elevation``: per radar name (the scenario's);
    ``origins``: :func:`scan_origins` of ``t0_us``, when known (else read from ``reports``);
    ``mode_s``: each aircraft's first Mode S report (:func:`~tertiary.evaluation.bound_measurements.mode_s_first`),
    when known (else read from ``reports``, which then need only hold the Cartesian sensors'
    plots); ``between``: (lo, hi) s from ``t0_us``: only the scans that can illuminate in [lo, hi)
    are made (every event there, a few beside it); ``gaps``: the truth's
    (:meth:`~tertiary.evaluation.bound_truth.Truth.of`) when ``truth`` is a part of it. ``truth``
    may be made already (a :class:`~tertiary.evaluation.bound_truth.Truth` from ``t0_us``)."""
    if isinstance(truth, Truth):
        tr, t0 = truth, truth.t0_us
    else:
        t0 = int(truth["time"].cast(TIME).dt.epoch("us").min()) if t0_us is None else t0_us
        tr = Truth.of(truth, t0, gaps=gaps)
    parts = []
    origins = scan_origins(radars, reports, t0) if origins is None else origins
    velocity_from = _velocity_from(tr, radars, mode_s_first(reports) if mode_s is None else mode_s, t0, cfg)
    for row in radars.iter_rows(named=True):          # a handful of radars
        s0 = origins.get(row["radar_id"])
        n_vel = 0
        if row.get("kind") in mlat.CARTESIAN_KINDS:
            a, t, r_eq = _mlat_events(tr, row, reports, origin, t0)
        elif s0 is None:
            continue
        else:
            max_el = (max_elevation or {}).get(row.get("name"), cfg.max_elevation_deg)
            a, t, r_eq = _radar_events(tr, row, s0, origin, max_el, cfg.mode_c_height, between)
            # the downlinked velocity of a Mode S aircraft at each illumination (Pd as the plot)
            v = t >= velocity_from[a]
            pd = float(row.get("pd") if row.get("pd") is not None else 1.0)
            a = np.r_[a, a[v]]
            av, tv = a[len(v):], t[v]
            r_v = velocity_covariance(tr.at(av, tv)[0], tr.velocity_at(av, tv), origin, cfg.ehs_speed_sigma_mps,
                                      cfg.ehs_track_sigma_deg)
            r_eq = np.concatenate([r_eq, r_v / pd])
            t = np.r_[t, t[v]]
            n_vel = int(v.sum())
        n_pos = len(a) - n_vel
        parts.append(pl.DataFrame({
            "truth_id": tr.ids[a], "radar_id": pl.Series(np.full(len(a), row["radar_id"]), dtype=pl.UInt32),
            "t_s": t, "r_eq": pl.Series(r_eq.reshape(-1, 9), dtype=pl.Array(pl.Float64, 9)),
            "velocity": np.arange(len(a)) >= n_pos}))
    schema = {"truth_id": pl.Int64, "radar_id": pl.UInt32, "t_s": pl.Float64, "r_eq": pl.Array(pl.Float64, 9),
              "velocity": pl.Boolean}
    out = pl.concat(parts) if parts else pl.DataFrame(schema=schema)
    return out.with_columns((pl.lit(t0) + (pl.col("t_s") * US).round().cast(pl.Int64)).cast(TIME).alias("time"))


def mode_s_lead_s(radars: pl.DataFrame) -> float:
    """How long (s) before an aircraft's first Mode S report its downlinked velocity counts: the
    longest scan period and clock offset of the radars, so that the illumination which made the
    report counts whatever the radar and its clock."""
    def most(col: str) -> float:
        return float(radars[col].cast(pl.Float64).abs().max() or 0.0) if col in radars.columns else 0.0
    return most("scan_period_s") + most("time_offset_s")


def _velocity_from(tr: Truth, radars: pl.DataFrame, first: pl.DataFrame, t0_us: int, cfg: BoundConfig) -> F64:
    """Per aircraft of ``tr``, the time (s from ``t0_us``) from which its downlinked velocity is
    a measurement: its first Mode S report less :func:`mode_s_lead_s`; never (inf) without one,
    or when the model counts no downlinked velocity. Before its first Mode S report no report of
    it carries a velocity, so leaving those illuminations out keeps the bound below any estimator."""
    never = np.full(len(tr.ids), np.inf)
    if not cfg.downlinked_velocity or first.is_empty():
        return never
    got = (pl.DataFrame({"truth_id": tr.ids}).join(first, on="truth_id", how="left", maintain_order="left")
           ["first_us"].to_numpy())
    got = np.asarray(got, dtype=float)
    return np.where(np.isfinite(got), (got - t0_us) / US - mode_s_lead_s(radars), never)


def scan_origins(radars: pl.DataFrame, reports: pl.DataFrame | pl.LazyFrame, t0_us: int) -> dict[int, float]:
    """radar_id → s_0 (seconds from ``t0_us``, mod T) recovered from each radar's reports with a
    time and an azimuth (:func:`_scan_origin`); a radar without any has none. ``reports`` may be
    a scan of the input: in the contract's dtypes it is read a radar at a time, two columns (a
    long recording's times are not held); in others its three columns are cast as validation
    casts them, a value that cannot be cast left out."""
    lf = _origin_columns(reports.lazy())
    if lf is None:
        return {}
    us = pl.col("time").dt.epoch("us")
    out = {}
    for row in radars.iter_rows(named=True):
        if row.get("kind") in mlat.CARTESIAN_KINDS:   # no scan: its plots are its events (_mlat_events)
            continue
        mine = (lf.filter((pl.col("radar_id") == row["radar_id"]) & pl.col("time").is_not_null()
                          & pl.col("azimuth_deg").is_finite())
                .select(us.alias("us"), "azimuth_deg").collect())
        rotating = (row.get("timing") or "rotating") == "rotating"
        off = float(row.get("time_offset_s") or 0.0)
        s0 = _scan_origin((mine["us"].to_numpy() - t0_us) / US - off, mine["azimuth_deg"].to_numpy(),
                          float(row["scan_period_s"]), rotating)
        if s0 is not None:
            out[row["radar_id"]] = s0
    return out


#: the dtypes :func:`scan_origins` reads its columns in (the reports contract's)
_ORIGIN_DTYPES = {"radar_id": pl.UInt32, "time": TIME, "azimuth_deg": pl.Float64}


def _origin_columns(lf: pl.LazyFrame) -> pl.LazyFrame | None:
    """The reports' radar_id, time and azimuth_deg in :data:`_ORIGIN_DTYPES` (None without one of
    them): selected as they are when already so, else read and cast by the contract's
    :func:`~tertiary.contract.cast.cast_column` (a column that cannot be cast at all raises
    its one-line :class:`~tertiary.contract.errors.SchemaError`)."""
    schema = lf.collect_schema()
    if not set(_ORIGIN_DTYPES) <= set(schema.names()):
        return None
    cols = lf.select(list(_ORIGIN_DTYPES))
    if all(schema[c] == t for c, t in _ORIGIN_DTYPES.items()):
        return cols
    frame = cols.collect()
    return pl.DataFrame([cast_column(frame[c], t, "reports")[0] for c, t in _ORIGIN_DTYPES.items()]).lazy()


def _ca9(tau: F64, dev: F64) -> tuple[F64, F64]:
    """Φ(τ), Q = blockdiag(d dᵀ per axis) of model M (M1) as 9×9 stacks for :func:`pcrb_linear`:
    with :func:`_bound_summary`, the reference :func:`_pcrb_block`'s compiled kernel is tested
    against (the run calls the kernel only)."""
    phi3 = np.zeros((len(tau), 3, 3))
    phi3[:, 0, 0] = phi3[:, 1, 1] = phi3[:, 2, 2] = 1.0
    phi3[:, 0, 1] = phi3[:, 1, 2] = tau
    phi3[:, 0, 2] = 0.5 * tau * tau
    q = np.zeros((len(tau), 9, 9))
    for ax in range(3):
        q[:, 3 * ax:3 * ax + 3, 3 * ax:3 * ax + 3] = dev[:, ax, :, None] * dev[:, ax, None, :]
    return _blockdiag3(phi3), q


def _prior9(cfg: BoundConfig, accel: F64) -> F64:
    """The prior (n_sequences, 9, 9) at each sequence's first row: p σ ``p0_sigma_m``, v σ
    ``v0_sigma_mps``, a ~ N(0, diag(ā²)) with ā (n_sequences, 3) the truth's acceleration there."""
    p = np.zeros((len(accel), 9, 9))
    p[:, POS, POS] = cfg.p0_sigma_m ** 2
    p[:, VEL, VEL] = cfg.v0_sigma_mps ** 2
    p[:, POS + 2, POS + 2] = np.asarray(accel) ** 2
    return p


def pcrb_at(samples: pl.DataFrame, events: pl.DataFrame, cfg: BoundConfig = BoundConfig(),
            truth: pl.DataFrame | None = None, t0_us: int | None = None) -> pl.DataFrame:
    """The bound at each distinct (truth_id, epoch) of ``samples``: columns truth_id, epoch and
    ``b2_pos`` (tr P_pos, m²), ``b2_horizontal`` (P_xx + P_yy), ``b2_vel`` (tr P_vel) — the
    recursion (T34) of model M fitted to ``truth`` (its samples' velocities; module docstring)
    over :func:`illuminations` ``events`` and the requested epochs of each aircraft in time
    order (a measurement at an epoch counts at that epoch); times in s from ``t0_us`` (else the
    first row's)."""
    return pcrb_carried(samples, events, cfg, truth, t0_us)[0]


#: the recursion of an aircraft between two calls of :func:`pcrb_carried`: its last row's time,
#: whether it had a measurement, and P there (row-major 9×9)
CARRIED = {"truth_id": pl.Int64, "last_us": pl.Int64, "seen": pl.Boolean, "p": pl.Array(pl.Float64, 81)}


def pcrb_carried(samples: pl.DataFrame, events: pl.DataFrame, cfg: BoundConfig, truth: pl.DataFrame | Truth | None,
                 t0_us: int | None = None, carried: pl.DataFrame | None = None,
                 gaps: pl.DataFrame | None = None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`pcrb_at`, each aircraft of ``carried`` (:data:`CARRIED`) going on from its P at its
    last row (its rows here all later), the others from the prior at their first row; ``truth``
    may then be a part of the truth holding each aircraft's samples from its last row (and
    :func:`~tertiary.evaluation.bound_truth.Truth.of`'s margin) on, with the whole truth's
    ``gaps``, or a :class:`~tertiary.evaluation.bound_truth.Truth` made from ``t0_us`` with
    ``cfg``'s half-width. Returns the bounds and every aircraft's :data:`CARRIED` after its last row here:
    split anywhere in time, the calls make the rows of one call over the whole."""
    if truth is None:
        raise ValueError("pcrb_at: the bound's motion model is fitted to the truth; give truth=")
    carried = pl.DataFrame(schema=CARRIED) if carried is None else carried
    want = samples.select(pl.col("truth_id").cast(pl.Int64), pl.col("epoch").cast(TIME)).unique()
    out_schema = {"truth_id": pl.Int64, "epoch": TIME, "b2_pos": pl.Float64, "b2_horizontal": pl.Float64,
                  "b2_vel": pl.Float64}
    if want.is_empty() and events.is_empty():
        return pl.DataFrame(schema=out_schema), carried
    # the keys are sorted, each event's r_eq gathered by its row: the requested epochs carry none,
    # a carried aircraft's last row (k −1) comes first and starts its sequence from its P
    ev = events.select("truth_id", pl.col("time").cast(TIME).alias("epoch"), pl.lit(0, pl.Int8).alias("__k"),
                       pl.int_range(pl.len(), dtype=pl.Int64).alias("__ev"))
    anchors = carried.select("truth_id", pl.col("last_us").cast(TIME).alias("epoch"), pl.lit(-1, pl.Int8).alias("__k"),
                             pl.int_range(pl.len(), dtype=pl.Int64).alias("__ev"))
    rows = (pl.concat([anchors, ev, want.with_columns(pl.lit(1, pl.Int8).alias("__k"),
                                                      pl.lit(-1, pl.Int64).alias("__ev"))])
            .sort("truth_id", "epoch", "__k"))
    tid = rows["truth_id"].to_numpy()
    us = rows["epoch"].dt.epoch("us").to_numpy()
    base = int(us.min()) if t0_us is None else t0_us
    t = (us - base) / US
    new = np.ones(len(tid), bool)
    new[1:] = tid[1:] != tid[:-1]
    starts = np.flatnonzero(new)
    lengths = np.diff(np.append(starts, len(tid)))
    kind = rows["__k"].to_numpy()
    record, event = kind == 1, kind == 0
    src = rows["__ev"].to_numpy()
    if isinstance(truth, Truth):
        if truth.t0_us != base or truth.half_window_s != cfg.accel_half_window_s:
            raise ValueError("pcrb_carried: the truth given is made from another time or half-width")
        tr = truth
    else:
        tr = Truth.of(truth.filter(pl.col("truth_id").cast(pl.Int64).is_in(np.unique(tid).tolist())), base,
                      cfg.accel_half_window_s, gaps)
    pos = np.searchsorted(tr.ids, tid)
    a = np.where((pos < len(tr.ids)) & (tr.ids[np.minimum(pos, len(tr.ids) - 1)] == tid), pos, -1)
    # each sequence's start: a carried aircraft's P and whether it was measured, else the prior
    anchored = kind[starts] == -1
    p_carried = carried["p"].to_numpy().reshape(-1, 9, 9) if carried.height else np.zeros((0, 9, 9))
    seen0 = np.zeros(len(starts), bool)
    seen0[anchored] = carried["seen"].to_numpy()[src[starts[anchored]]]
    out, ends = [], []
    # aircraft a block at a time (each sequence is independent): the events' 3x3 matrices and the
    # model's deviations are gathered for a block, never for the whole recording (the stage's peak)
    for lo, hi, g0, g1 in _aircraft_blocks(starts, len(tid), BOUND_BLOCK_ROWS):
        s = np.where(event[lo:hi], src[lo:hi], -1)
        r_eq = np.full((hi - lo, 3, 3), np.nan)
        vel = np.zeros(hi - lo, bool)
        if (s >= 0).any():
            r_eq[s >= 0] = events["r_eq"].gather(s[s >= 0]).to_numpy().reshape(-1, 3, 3)
            if "velocity" in events.columns:
                vel[s >= 0] = events["velocity"].gather(s[s >= 0]).to_numpy()
        dev, acc = tr.deviations(a[lo:hi], t[lo:hi], new[lo:hi])
        st = starts[g0:g1] - lo
        p0 = _prior9(cfg, acc[st])
        mine = anchored[g0:g1]
        p0[mine] = p_carried[src[starts[g0:g1][mine]]]
        b, p_end = _pcrb_block(t[lo:hi], r_eq, st, lengths[g0:g1], record[lo:hi], cfg, dev, vel=vel, p0=p0)
        out.append(b)
        ends.append(p_end)
        del r_eq, dev
    b = np.concatenate(out)
    # an epoch before its aircraft's first measurement holds the prior alone: a sample scored
    # there is not an estimate of that aircraft (tertiary.evaluation.accuracy, "Scored rows"),
    # so it has no bound (NaN: counted, not pooled, by bound_metrics)
    count = np.cumsum(event)
    seen = (count - np.repeat(count[starts] - event[starts], lengths) > 0) | np.repeat(seen0, lengths)
    b[~seen[record]] = np.nan
    last = np.append(starts[1:], len(tid)) - 1
    end = pl.DataFrame({"truth_id": tid[starts], "last_us": us[last], "seen": seen[last],
                        "p": pl.Series(np.concatenate(ends).reshape(-1, 81), dtype=pl.Array(pl.Float64, 81))})
    return (rows.filter(record).select("truth_id", "epoch").with_columns(
        pl.Series("b2_pos", b[:, 0]), pl.Series("b2_horizontal", b[:, 1]), pl.Series("b2_vel", b[:, 2])
    ).cast(out_schema), end.cast(CARRIED))


#: rows (events and requested epochs) of the aircraft whose bounds are computed at a time
BOUND_BLOCK_ROWS = 262_144
#: aircraft whose illuminations are made and bounds pooled at a time (:func:`bound_stage`)
BOUND_AIRCRAFT = 256
#: aircraft whose truth :func:`bound_stage` reads at a time from a reference on disk: a long
#: recording's aircraft in a few reads, its truth never held whole
BOUND_READ_AIRCRAFT = 4_096


def _pcrb_block(t: F64, r_eq: F64, starts: I64, lengths: I64, record: NDArray[np.bool_], cfg: BoundConfig,
                dev: F64 | None = None, accel0: F64 | None = None, vel: NDArray[np.bool_] | None = None,
                p0: F64 | None = None) -> F64 | tuple[F64, F64]:
    """:func:`pcrb_linear` on model M (9 states; ``dev`` (n, 3, 3) the deviations d of (M2)
    per row and axis, none if not given; ``accel0`` (n_sequences, 3) the truth's ā at each
    sequence's first row, 0 if not given; ``vel``: the rows whose ``r_eq`` is a velocity
    measurement's, none if not given) with :func:`_bound_summary`, compiled
    (:func:`tertiary.evaluation.bound_kernel.pcrb_ca9`): (n_record, 3) in row order. With ``p0``
    (n_sequences, 9, 9), each sequence starts from it instead of the prior, and P after each
    sequence's last row is returned too."""
    tau = np.zeros(len(t))
    tau[1:] = np.diff(t)                 # a sequence's first row has none: it starts from the prior
    slot = np.full(len(t), -1, np.int64)
    slot[record] = np.arange(int(record.sum()))
    out = np.full((int(record.sum()), 3), np.nan)
    dev = np.zeros((len(t), 3, 3)) if dev is None else dev
    accel0 = np.zeros((len(starts), 3)) if accel0 is None else accel0
    ready_for("pcrb")
    vel = np.zeros(len(t), bool) if vel is None else vel
    start = _prior9(cfg, accel0) if p0 is None else np.ascontiguousarray(p0, dtype=np.float64)
    p_end = np.empty((len(starts), 9, 9))
    pcrb_ca9(arg(tau), arg(dev), arg(r_eq), arg(~np.isnan(r_eq[:, 0, 0]), np.bool_), arg(vel, np.bool_),
             arg(starts, np.int64), arg(lengths, np.int64), arg(start), slot, out, p_end)
    return out if p0 is None else (out, p_end)


def _aircraft_blocks(starts: I64, n: int, size: int) -> list[tuple[int, int, int, int]]:
    """(first row, end row, first sequence, end sequence) of blocks of whole sequences: those
    starting in each ``size`` rows (a block may end up to one sequence past it)."""
    bucket = np.asarray(starts) // size
    first = np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]])
    seq = np.append(first, len(starts))
    rows = np.append(np.asarray(starts)[first], n)
    return [(int(rows[i]), int(rows[i + 1]), int(seq[i]), int(seq[i + 1])) for i in range(len(first))]


def _bound_summary(p: F64) -> F64:
    """(tr P_pos, P_xx + P_yy, tr P_vel) of stacked 9-state bounds (m, 9, 9): what the compiled
    kernel records, for :func:`pcrb_linear` as its reference (:func:`_ca9`)."""
    pos = p[:, POS[:, None], POS[None, :]]
    return np.column_stack([np.trace(pos, axis1=1, axis2=2), pos[:, 0, 0] + pos[:, 1, 1],
                            p[:, VEL, VEL].sum(axis=1)])


#: radar columns the bound needs (the ``radars`` contract plus the simulator's ``pd``, scan timing)
NEEDED = ("radar_id", "lat_deg", "lon_deg", "alt_m", "scan_period_s", "sigma_range_m", "sigma_azimuth_deg",
          "sigma_elevation_deg", "max_range_m")


def bound_setup(ds, truth_columns: list[str], radars: pl.DataFrame, notes: list[str], scored: bool = True
                ) -> tuple[BoundConfig, dict[str, float]] | None:
    """The bound's model and each radar's elevation limit for a dataset ``ds`` whose truth has
    ``truth_columns``, the run's notes said; None (and a note saying why) without what the bound
    needs: radar columns, truth velocities, scored samples (``scored``). Missing ``pd`` counts as
    1, missing ``timing`` as rotating, missing ``min_elevation_deg`` as no limit (each with a note)."""
    missing = [c for c in NEEDED if c not in radars.columns]
    missing += [c for c in ("x_m", "vx_mps", "vy_mps", "vz_mps") if c not in truth_columns]
    if missing or not scored or radars.is_empty():
        why = f"missing column(s) {', '.join(missing)}" if missing else "nothing scored against truth"
        notes.append(f"bound: no posterior Cramér–Rao bound ({why})")
        return None
    for col, default in (("pd", "1"), ("timing", "rotating"), ("min_elevation_deg", "no limit")):
        if col not in radars.columns:
            notes.append(f"bound: radars has no {col}; taken as {default}")
    scen = getattr(ds, "scenario", None)
    cfg = BoundConfig.from_scenario(scen)
    max_el = {r.name: float(r.max_elevation_deg) for r in getattr(scen, "radars", ()) or ()}
    notes.append(f"bound: {cfg.describe()}")
    if "kind" in radars.columns and radars["kind"].is_in(mlat.CARTESIAN_KINDS).any():
        notes.append("bound: MLAT and ADS-B plots as Cartesian measurements (MLAT-3): their stated covariance, "
                     "else their NACp's sigma (ADSB-1), else the sensor's sigma_range_m per axis; height as a "
                     "Mode S reply")
    return cfg, max_el


def read_sums(held: pl.DataFrame, read: NDArray[np.int64], scored: pl.DataFrame, radars: pl.DataFrame,
              reports: pl.DataFrame, origin: geo.LocalFrame, cfg: BoundConfig, max_el: dict[str, float], t0_us: int,
              origins: dict[int, float], mode_s: pl.DataFrame | None = None) -> list[pl.DataFrame]:
    """:func:`block_sums` of the aircraft ``read`` (their truth ``held``), :data:`BOUND_AIRCRAFT`
    at a time."""
    sums = []
    for lo in range(0, len(read), BOUND_AIRCRAFT):
        block = pl.col("truth_id").cast(pl.Int64).is_in(read[lo:lo + BOUND_AIRCRAFT].tolist())
        sums.append(block_sums(held.filter(block), scored.filter(block), radars, reports, origin, cfg, max_el, t0_us,
                               origins, mode_s))
    return sums


def block_sums(truth: pl.DataFrame, scored: pl.DataFrame, radars: pl.DataFrame, reports: pl.DataFrame,
               origin: geo.LocalFrame, cfg: BoundConfig, max_el: dict[str, float], t0_us: int,
               origins: dict[int, float], mode_s: pl.DataFrame | None = None) -> pl.DataFrame:
    """:func:`bound_sums` of a block of aircraft: ``truth`` and ``scored`` hold theirs (each
    aircraft's bound is its own recursion over its truth and illuminations); ``mode_s``: their
    first Mode S reports, when known (else read from ``reports``)."""
    events = illuminations(truth, radars, reports, origin, cfg, max_el, t0_us=t0_us, origins=origins, mode_s=mode_s)
    return bound_sums(scored, pcrb_at(scored, events, cfg, truth=truth, t0_us=t0_us))


def bound_stage(ds, truth: pl.DataFrame | pl.LazyFrame, radars: pl.DataFrame, reports: pl.DataFrame,
                scored: pl.DataFrame, accuracy: pl.DataFrame, notes: list[str],
                origins: dict[int, float] | None = None) -> pl.DataFrame:
    """The pipeline's ``bound`` rows (:func:`bound_metrics`) for a dataset ``ds`` with truth;
    without what the bound needs no rows and a note saying why (:func:`bound_setup`). ``truth``
    may be a scan (of the reference on disk): it is then read :data:`BOUND_READ_AIRCRAFT`
    aircraft at a time, never whole. ``origins``: the radars' scan origins, when known (else
    read from ``reports``)."""
    names = truth.collect_schema().names() if isinstance(truth, pl.LazyFrame) else truth.columns
    setup = bound_setup(ds, names, radars, notes, not scored.is_empty())
    if setup is None:
        return pl.DataFrame(schema=TABLES["metrics"].required)
    cfg, max_el = setup
    t0 = int(truth.select(pl.col("time").cast(TIME).dt.epoch("us").min()).lazy().collect().item())
    origins = scan_origins(radars, reports, t0) if origins is None else origins
    mode_s = mode_s_first(reports)
    ids = np.sort(scored["truth_id"].drop_nulls().unique().cast(pl.Int64).to_numpy())
    sums = []
    # a block of aircraft at a time (each one's bound is its own recursion): the illuminations
    # and bounds of the whole recording are never held (the stage's peak on a long run)
    for read, held in _truth_reads(truth, ids):
        sums += read_sums(held, read, scored, radars, reports, ds.origin, cfg, max_el, t0, origins, mode_s)
        del held
    return bound_rows(pl.concat(sums) if sums else bound_sums(scored.clear(), pl.DataFrame()), accuracy)


def _truth_reads(truth: pl.DataFrame | pl.LazyFrame, ids: NDArray[np.int64]
                 ) -> Iterator[tuple[NDArray[np.int64], pl.DataFrame]]:
    """(aircraft ids, their truth rows) in reads of :data:`BOUND_READ_AIRCRAFT` aircraft from a
    scan; a frame already in memory in one read. Each read scans the whole reference (it is in
    time order, so no row group holds few aircraft): few reads of many aircraft keep that cost
    a few passes while the truth held is a fraction of a long recording's."""
    if isinstance(truth, pl.DataFrame):
        yield ids, truth
        return
    for lo in range(0, len(ids), BOUND_READ_AIRCRAFT):
        read = ids[lo:lo + BOUND_READ_AIRCRAFT]
        yield read, truth.filter(pl.col("truth_id").cast(pl.Int64).is_in(read.tolist())).collect()
