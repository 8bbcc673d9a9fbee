"""Posterior Cramér–Rao lower bound (PCRB) for the simulated truth (evaluation, stage ``bound``).

What is bounded
---------------
The mean-square error of **any** estimator of an aircraft's state at an epoch k that uses the
radar measurements up to k is bounded below by the inverse of the posterior Fisher information
J_k (Tichavský, Muravchik, Nehorai 1998, IEEE TSP 46(5), eq. (21)):

    J_{k+1} = D22 − D21 (J_k + D11)⁻¹ D12 + J_Z(k+1)                                 (T21)

For linear-Gaussian dynamics x_{k+1} = Φ x_k + w, w ~ N(0, Q), the D terms reduce the recursion
to the Kalman covariance recursion run on the *expected* measurement information (Tichavský
eq. (34); no measurement values enter):

    P⁻ = Φ P Φᵀ + Q,     P = (P⁻⁻¹ + J_Z)⁻¹,     PCRB_k = P_k                          (T34)

Dynamics: the simulator's own process model — the Singer model of its radars' channels,
per Cartesian axis of the system frame, state (p, v, a), Φ(τ) and Q(τ) = diag(0, 0, D_a) from
:func:`tertiary.filters.singer.singer_phi` / ``singer_q`` with the scenario's ``[tracker]``
α, σ_m and variant (monograph (2.49)–(2.63), tertiary (4.46)). Prior at an aircraft's first
event: position σ ``p0_sigma_m`` (diffuse), velocity σ ``v0_sigma_mps``, acceleration σ_m.

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
simulator). s_0 is recovered from the radar's own reports (every report, target or clutter,
is stamped s_k + T·β/360 + ``time_offset_s``): the circular median of the report times minus
that, modulo T. The aircraft is covered when its range is at most ``max_range_m`` and its
elevation within [``min_elevation_deg``, max elevation (the scenario's, else 90°)] and the
truth exists (no truth gap) at that instant. Truth between samples is the cubic Hermite
interpolation of the truth positions and velocities (the simulator's interpolation).

What is not in the bound (so a method may legitimately sit below it there): the Mode C
altitude channel (a quantised measurement — it has no Fisher information in the regular
sense; the height metric ``rmse_height_m`` uses it, so no height bound is given), and the
truth's actual motion: the simulator flies deterministic straight legs and coordinated turns,
while the bound averages over Singer trajectories. Radar biases, clock offsets, clutter and
association errors only add error, so leaving them out keeps the bound a lower bound.

Metrics (stage ``bound``, one block per picture)
------------------------------------------------
Over the *same scored samples* (run, epoch, truth_id) as a picture's accuracy rows, the bound is
pooled as the RMSE is: ``pcrb_pos_m`` = sqrt(mean_k mean_{j∈k} tr P_pos), ``pcrb_horizontal_m``
(P_xx + P_yy), ``pcrb_vel_mps`` (tr P_vel), and the signed gaps ``gap_pos_m`` =
``rmse_pos_m`` − ``pcrb_pos_m``, ``gap_horizontal_m``, ``gap_vel_mps`` (> 0: above the bound),
per segment all/straight/turn. The bound is the same in every Monte-Carlo run (the geometry
and the expected information do not depend on the noise draw), so it is computed once per
(truth_id, epoch).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.core.jit import arg, ready_for
from tertiary.core.units import US
from tertiary.evaluation.bound_kernel import pcrb_singer9
from tertiary.filters.singer import Variant, singer_phi, singer_q
from tertiary.contract import TABLES, TIME

__all__ = ["BoundConfig", "pcrb_linear", "illuminations", "pcrb_at", "bound_metrics", "BOUND_METRICS"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: metric → (bound column, accuracy metric it is compared with)
BOUND_METRICS: dict[str, tuple[str, str]] = {
    "pcrb_pos_m": ("b2_pos", "rmse_pos_m"),
    "pcrb_horizontal_m": ("b2_horizontal", "rmse_horizontal_m"),
    "pcrb_vel_mps": ("b2_vel", "rmse_vel_mps"),
}
_GAP = {"pcrb_pos_m": "gap_pos_m", "pcrb_horizontal_m": "gap_horizontal_m", "pcrb_vel_mps": "gap_vel_mps"}
#: 9-state (x, vx, ax, y, vy, ay, z, vz, az) indices of the positions and velocities
POS = np.array([0, 3, 6])
VEL = np.array([1, 4, 7])
#: drop the scans that cannot bring an aircraft within a rotating radar's range before the
#: beam-passage iterations (:func:`_radar_events`; the same events, found sooner)
RANGE_SCREEN = True


@dataclass(frozen=True)
class BoundConfig:
    """The process model of the bound (the scenario's ``[tracker]``: Singer α, σ_m, variant),
    the prior (``p0_sigma_m``, ``v0_sigma_mps``) and the elevation limit used when the
    scenario does not give one per radar (``max_elevation_deg``)."""

    alpha: float = 1.0 / 30.0
    sigma_m: float = 2.0
    variant: Variant = "printed"
    p0_sigma_m: float = 10_000.0
    v0_sigma_mps: float = 300.0
    max_elevation_deg: float = 90.0

    @classmethod
    def from_scenario(cls, scenario) -> "BoundConfig":
        """The bound for a scenario's own Singer model (its ``tracker`` section)."""
        t = getattr(scenario, "tracker", None)
        if t is None:
            return cls()
        return cls(alpha=float(t.alpha), sigma_m=float(t.sigma_m), variant=t.variant,
                   v0_sigma_mps=float(t.v0_sigma_mps))


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
    ``phi_q(tau)`` returns Φ(τ), Q(τ) stacked (n, d, d); ``p0`` (d, d) is the prior at a
    sequence's first event. Returns the bound P (n_record, d, d) at the ``record`` rows,
    in row order — or, with ``summary`` (stacked P (m, d, d) → (m, s)), only what it keeps of
    each (n_record, s): the recorded bounds of a long recording are never held whole. The
    loop runs over the event rank, batched over the sequences.
    """
    n, d = len(t), p0.shape[0]
    slot = np.full(n, -1)
    slot[record] = np.arange(int(record.sum()))
    keep = summary or (lambda pk: pk)
    out = np.full((int(record.sum()), *keep(p0[None]).shape[1:]), np.nan)
    order = np.argsort(-np.asarray(lengths), kind="stable")
    st, ln = np.asarray(starts)[order], np.asarray(lengths)[order]
    p = np.broadcast_to(p0, (len(st), d, d)).copy()
    tau = np.zeros(n)
    tau[1:] = np.diff(t)
    alive = np.searchsorted(-ln, -np.arange(ln.max(initial=0)), side="left")   # sequences longer than k
    has = ~np.isnan(r_eq[:, 0, 0])
    for k, m in enumerate(alive):
        idx = st[:m] + k
        pk = p[:m]
        if k:
            phi, q = phi_q(tau[idx])
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


@dataclass
class _Truth:
    """Truth samples sorted by (aircraft index, time), times in seconds from ``t0_us``; ``key`` =
    index · span + t is increasing, so one ``searchsorted`` brackets every query."""

    ids: NDArray[np.int64]
    first: I64
    count: I64
    t: F64
    pos: F64
    vel: F64
    span: float
    key: F64
    gap_s: F64

    @classmethod
    def of(cls, truth: pl.DataFrame, t0_us: int) -> "_Truth":
        tr = (truth.select(pl.col("truth_id").cast(pl.Int64), pl.col("time").cast(TIME).dt.epoch("us").alias("us"),
                           "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
              .drop_nulls().unique(["truth_id", "us"], keep="first").sort("truth_id", "us"))
        ids, first, count = np.unique(tr["truth_id"].to_numpy(), return_index=True, return_counts=True)
        t = (tr["us"].to_numpy() - t0_us) / US
        span = 2.0 * float(np.abs(t).max(initial=0.0)) + 10.0
        owner = np.repeat(np.arange(len(ids)), count)
        d = np.diff(t)
        same = owner[1:] == owner[:-1]
        gap = np.full(len(ids), np.inf)       # largest spacing that is not a truth gap: 1.5 × median
        if same.any():
            g = pl.DataFrame({"a": owner[1:][same], "d": d[same]}).group_by("a").agg(pl.col("d").median())
            gap[g["a"].to_numpy()] = 1.5 * g["d"].to_numpy()
        return cls(ids, first, count, t, tr.select("x_m", "y_m", "z_m").to_numpy(),
                   tr.select("vx_mps", "vy_mps", "vz_mps").to_numpy(), span, owner * span + t, gap)

    @functools.cached_property
    def top_speed(self) -> float:
        """The fastest any aircraft moves (m/s): its largest velocity sample, or the chord
        between two consecutive samples (gaps included) when that is faster."""
        same = np.repeat(np.arange(len(self.ids)), self.count)
        one = same[1:] == same[:-1]
        dt = np.diff(self.t)[one]
        chord = np.linalg.norm(np.diff(self.pos, axis=0)[one], axis=1) / np.where(dt > 0, dt, np.inf)
        return float(max(np.linalg.norm(self.vel, axis=1).max(initial=0.0), chord.max(initial=0.0)))

    def at(self, a: I64, t: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Cubic Hermite position of aircraft index ``a`` at ``t`` (the simulator's
        interpolation) and its validity: inside the aircraft's span and not across a truth gap."""
        lo, hi = self.first[a], self.first[a] + self.count[a] - 1
        j = np.searchsorted(self.key, a * self.span + t, side="right") - 1
        ok = (j >= lo) & (j <= hi)
        j = np.clip(j, lo, np.maximum(hi - 1, lo))
        j1 = np.minimum(j + 1, hi)
        h = self.t[j1] - self.t[j]
        ok &= ((h > 0) & (h <= self.gap_s[a]) & (t <= self.t[j1])) | (j1 == j)
        s = np.clip((t - self.t[j]) / np.where(h > 0, h, 1.0), 0.0, 1.0)[:, None]
        p0, p1, v0, v1 = self.pos[j], self.pos[j1], self.vel[j] * h[:, None], self.vel[j1] * h[:, None]
        s2, s3 = s * s, s * s * s
        pos = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * v0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * v1
        return pos, ok & (np.abs(t - self.t[j]) <= np.maximum(h, 0.0) + 1e-9)


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


def _radar_events(tr: _Truth, row: dict, s0: float, origin: geo.LocalFrame, max_el: float
                  ) -> tuple[I64, F64, F64]:
    """(aircraft index, time, R_eq = G R_polar Gᵀ / Pd) of every illumination of one radar that
    covers an aircraft (module docstring)."""
    T = float(row["scan_period_s"])
    pd = float(row.get("pd") if row.get("pd") is not None else 1.0)
    if not (T > 0 and pd > 0):
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3, 3))
    lo_t, hi_t = tr.t[tr.first], tr.t[tr.first + tr.count - 1]
    k_lo = np.ceil((lo_t - T - s0) / T).astype(np.int64)
    k_hi = np.floor((hi_t - s0) / T).astype(np.int64)
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
    a, t, rng, az, el = a[ok], t[ok], rng[ok], az[ok], el[ok]
    var = np.array([float(row["sigma_range_m"]) ** 2, np.radians(float(row["sigma_azimuth_deg"])) ** 2,
                    np.radians(float(row["sigma_elevation_deg"])) ** 2])
    g = rot.T @ geo.polar_jacobian(rng, az, el)                       # ∂p_sys/∂(r, β, ε)
    r_eq = (g * var[None, None, :]) @ g.swapaxes(1, 2) / pd
    return a, t, r_eq


def illuminations(truth: pl.DataFrame, radars: pl.DataFrame, reports: pl.DataFrame, origin: geo.LocalFrame,
                  cfg: BoundConfig = BoundConfig(), max_elevation: dict[str, float] | None = None,
                  t0_us: int | None = None, origins: dict[int, float] | None = None) -> pl.DataFrame:
    """Every (truth_id, radar_id, time) at which a radar's beam covers an aircraft, with the
    expected measurement information as its inverse ``r_eq`` (flattened 3×3, m²) — the
    events of the bound (module docstring). ``max_elevation``: per radar name (the scenario's);
    ``origins``: :func:`scan_origins` of ``t0_us``, when known (else read from ``reports``)."""
    t0 = int(truth["time"].cast(TIME).dt.epoch("us").min()) if t0_us is None else t0_us
    tr = _Truth.of(truth, t0)
    parts = []
    origins = scan_origins(radars, reports, t0) if origins is None else origins
    for row in radars.iter_rows(named=True):          # a handful of radars
        s0 = origins.get(row["radar_id"])
        if s0 is None:
            continue
        max_el = (max_elevation or {}).get(row.get("name"), cfg.max_elevation_deg)
        a, t, r_eq = _radar_events(tr, row, s0, origin, max_el)
        parts.append(pl.DataFrame({
            "truth_id": tr.ids[a], "radar_id": pl.Series(np.full(len(a), row["radar_id"]), dtype=pl.UInt32),
            "t_s": t, "r_eq": pl.Series(r_eq.reshape(-1, 9), dtype=pl.Array(pl.Float64, 9))}))
    schema = {"truth_id": pl.Int64, "radar_id": pl.UInt32, "t_s": pl.Float64, "r_eq": pl.Array(pl.Float64, 9)}
    out = pl.concat(parts) if parts else pl.DataFrame(schema=schema)
    return out.with_columns((pl.lit(t0) + (pl.col("t_s") * US).round().cast(pl.Int64)).cast(TIME).alias("time"))


def scan_origins(radars: pl.DataFrame, reports: pl.DataFrame, t0_us: int) -> dict[int, float]:
    """radar_id → s_0 (seconds from ``t0_us``, mod T) recovered from each radar's reports
    (:func:`_scan_origin`); a radar without reports has none."""
    rep = reports.select("radar_id", pl.col("time").cast(TIME).dt.epoch("us").alias("us"), "azimuth_deg")
    out = {}
    for row in radars.iter_rows(named=True):
        mine = rep.filter(pl.col("radar_id") == row["radar_id"])
        rotating = (row.get("timing") or "rotating") == "rotating"
        off = float(row.get("time_offset_s") or 0.0)
        s0 = _scan_origin((mine["us"].to_numpy() - t0_us) / US - off, mine["azimuth_deg"].to_numpy(),
                          float(row["scan_period_s"]), rotating)
        if s0 is not None:
            out[row["radar_id"]] = s0
    return out


def _singer9(cfg: BoundConfig):
    """Φ(τ), Q(τ) of the 9-state Singer model for :func:`pcrb_linear`: with
    :func:`_bound_summary`, the reference :func:`_pcrb_block`'s compiled kernel is tested
    against (the run calls the kernel only)."""
    def phi_q(tau: F64) -> tuple[F64, F64]:
        return (_blockdiag3(singer_phi(tau, cfg.alpha, cfg.variant)),
                _blockdiag3(singer_q(tau, cfg.alpha, cfg.sigma_m, cfg.variant)))
    return phi_q


def _prior9(cfg: BoundConfig) -> F64:
    p = np.zeros((9, 9))
    p[POS, POS] = cfg.p0_sigma_m ** 2
    p[VEL, VEL] = cfg.v0_sigma_mps ** 2
    p[POS + 2, POS + 2] = cfg.sigma_m ** 2
    return p


def pcrb_at(samples: pl.DataFrame, events: pl.DataFrame, cfg: BoundConfig = BoundConfig()) -> pl.DataFrame:
    """The bound at each distinct (truth_id, epoch) of ``samples``: columns truth_id, epoch and
    ``b2_pos`` (tr P_pos, m²), ``b2_horizontal`` (P_xx + P_yy), ``b2_vel`` (tr P_vel) — the
    recursion (T34) over :func:`illuminations` ``events`` and the requested epochs of each
    aircraft in time order (a measurement at an epoch counts at that epoch)."""
    want = samples.select(pl.col("truth_id").cast(pl.Int64), pl.col("epoch").cast(TIME)).unique()
    out_schema = {"truth_id": pl.Int64, "epoch": TIME, "b2_pos": pl.Float64, "b2_horizontal": pl.Float64,
                  "b2_vel": pl.Float64}
    if want.is_empty():
        return pl.DataFrame(schema=out_schema)
    # the keys are sorted, each event's r_eq gathered by its row: the requested epochs carry none
    ev = events.select("truth_id", pl.col("time").cast(TIME).alias("epoch"), pl.lit(0, pl.Int8).alias("__k"),
                       pl.int_range(pl.len(), dtype=pl.Int64).alias("__ev"))
    rows = (pl.concat([ev, want.with_columns(pl.lit(1, pl.Int8).alias("__k"), pl.lit(-1, pl.Int64).alias("__ev"))])
            .sort("truth_id", "epoch", "__k"))
    tid = rows["truth_id"].to_numpy()
    us = rows["epoch"].dt.epoch("us").to_numpy()
    t = (us - us.min()) / US
    new = np.ones(len(tid), bool)
    new[1:] = tid[1:] != tid[:-1]
    starts = np.flatnonzero(new)
    lengths = np.diff(np.append(starts, len(tid)))
    record = rows["__k"].to_numpy() == 1
    src = rows["__ev"].to_numpy()
    out = []
    # aircraft a block at a time (each sequence is independent): the events' 3x3 matrices are
    # gathered for a block, never for the whole recording (the stage's peak)
    for lo, hi, g0, g1 in _aircraft_blocks(starts, len(tid), BOUND_BLOCK_ROWS):
        s = src[lo:hi]
        r_eq = np.full((hi - lo, 3, 3), np.nan)
        if (s >= 0).any():
            r_eq[s >= 0] = events["r_eq"].gather(s[s >= 0]).to_numpy().reshape(-1, 3, 3)
        out.append(_pcrb_block(t[lo:hi], r_eq, starts[g0:g1] - lo, lengths[g0:g1], record[lo:hi], cfg))
        del r_eq
    b = np.concatenate(out)
    return rows.filter(record).select("truth_id", "epoch").with_columns(
        pl.Series("b2_pos", b[:, 0]), pl.Series("b2_horizontal", b[:, 1]), pl.Series("b2_vel", b[:, 2])
    ).cast(out_schema)


#: rows (events and requested epochs) of the aircraft whose bounds are computed at a time
BOUND_BLOCK_ROWS = 262_144
#: aircraft whose illuminations are made and bounds pooled at a time (:func:`bound_stage`)
BOUND_AIRCRAFT = 256
#: aircraft whose truth :func:`bound_stage` reads at a time from a reference on disk: a long
#: recording's aircraft in a few reads, its truth never held whole
BOUND_READ_AIRCRAFT = 4_096


def _pcrb_block(t: F64, r_eq: F64, starts: I64, lengths: I64, record: NDArray[np.bool_], cfg: BoundConfig) -> F64:
    """:func:`pcrb_linear` on the 9-state Singer model with :func:`_bound_summary`, compiled
    (:func:`tertiary.evaluation.bound_kernel.pcrb_singer9`): (n_record, 3) in row order."""
    tau = np.zeros(len(t))
    tau[1:] = np.diff(t)                 # a sequence's first row has none: it starts from the prior
    slot = np.full(len(t), -1, np.int64)
    slot[record] = np.arange(int(record.sum()))
    out = np.full((int(record.sum()), 3), np.nan)
    ready_for("pcrb")
    pcrb_singer9(arg(singer_phi(tau, cfg.alpha, cfg.variant)), arg(singer_q(tau, cfg.alpha, cfg.sigma_m, cfg.variant)),
                 arg(r_eq), arg(~np.isnan(r_eq[:, 0, 0]), np.bool_), arg(starts, np.int64), arg(lengths, np.int64),
                 arg(_prior9(cfg)), slot, out)
    return out


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
    kernel records, for :func:`pcrb_linear` as its reference (:func:`_singer9`)."""
    pos = p[:, POS[:, None], POS[None, :]]
    return np.column_stack([np.trace(pos, axis1=1, axis2=2), pos[:, 0, 0] + pos[:, 1, 1],
                            p[:, VEL, VEL].sum(axis=1)])


def bound_metrics(scored: pl.DataFrame, accuracy: pl.DataFrame, bound: pl.DataFrame) -> pl.DataFrame:
    """Metrics rows (stage ``bound``): per picture (``scored.method``) and segment, the bound
    pooled over that picture's scored samples like its RMSE — sqrt(mean_k mean_{j∈k} b²) —
    and the signed gap to the picture's accuracy row (``accuracy``: metrics rows of stages
    fusion/tracker). ``scored``: method, run, epoch, truth_id, seg_class; ``bound``: from
    :func:`pcrb_at`."""
    return _bound_rows(_bound_sums(scored, bound), accuracy)


def _bound_sums(scored: pl.DataFrame, bound: pl.DataFrame) -> pl.DataFrame:
    """Per (method, segment, epoch, run): the sums of each bound column over the scored samples
    and their count — what :func:`bound_metrics` pools, summable over blocks of aircraft."""
    cols = [c for c, _ in BOUND_METRICS.values()]
    if scored.is_empty() or bound.is_empty():
        return pl.DataFrame(schema={"method": pl.String, "segment": pl.String, "epoch": TIME, "run": pl.UInt32,
                                    **{c: pl.Float64 for c in cols}, "__n": pl.UInt32})
    s = scored.select("method", pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                      pl.col("truth_id").cast(pl.Int64), "seg_class")
    s = s.join(bound, on=["truth_id", "epoch"], how="inner")
    aggs = [*[pl.col(c).sum() for c in cols], pl.len().cast(pl.UInt32).alias("__n")]
    # segment "all" and each sample's straight/turn class grouped in place: the samples of every
    # picture are not copied once per segment (the stage's peak on a long run)
    return pl.concat([s.group_by("method", pl.lit("all").alias("segment"), "epoch", "run").agg(*aggs),
                      s.group_by("method", pl.col("seg_class").alias("segment"), "epoch", "run").agg(*aggs)
                      .filter(pl.col("segment").is_not_null())])


def _bound_rows(sums: pl.DataFrame, accuracy: pl.DataFrame) -> pl.DataFrame:
    """:func:`bound_metrics` rows from the :func:`_bound_sums` of every sample."""
    spec = TABLES["metrics"].required
    if sums.is_empty():
        return pl.DataFrame(schema=spec)
    cols = [c for c, _ in BOUND_METRICS.values()]
    per = sums.group_by("method", "segment", "epoch").agg(*[(pl.col(c).sum() / pl.col("__n").sum()).alias(c)
                                                            for c in cols],
                                                          pl.col("run").n_unique().alias("__runs"))
    pooled = per.group_by("method", "segment").agg(*[pl.col(c).mean().sqrt() for c in cols],
                                                   pl.col("__runs").max().alias("n_runs"))
    long = pooled.unpivot(index=["method", "segment", "n_runs"], on=cols, variable_name="col", value_name="value")
    name = {c: m for m, (c, _) in BOUND_METRICS.items()}
    long = long.with_columns(pl.col("col").replace_strict(name, return_dtype=pl.String).alias("metric"))
    if "stage" in accuracy.columns:      # the seed accuracy rows (not the surveillance stage's)
        accuracy = accuracy.filter(pl.col("stage").is_in(["fusion", "tracker"]))
    acc = accuracy.filter(pl.col("metric").is_in([a for _, a in BOUND_METRICS.values()])).select(
        "method", "segment", pl.col("metric").alias("__acc"), pl.col("value").alias("__rmse"))
    acc_of = {m: a for m, (_, a) in BOUND_METRICS.items()}
    gap = (long.with_columns(pl.col("metric").replace_strict(acc_of, return_dtype=pl.String).alias("__acc"))
           .join(acc, on=["method", "segment", "__acc"], how="inner")
           .with_columns((pl.col("__rmse") - pl.col("value")).alias("value"),
                         pl.col("metric").replace_strict(_GAP, return_dtype=pl.String).alias("metric")))
    out = pl.concat([long.select("method", "metric", "segment", "value", "n_runs"),
                     gap.select("method", "metric", "segment", "value", "n_runs")])
    order = {m: i for i, m in enumerate([*BOUND_METRICS, *_GAP.values()])}
    seg = pl.col("segment").replace_strict({"all": 0, "straight": 1, "turn": 2}, default=3, return_dtype=pl.Int8)
    return (out.with_columns(pl.lit("bound").alias("stage"))
            .sort(pl.col("method"), seg, pl.col("metric").replace_strict(order, return_dtype=pl.Int8))
            .select([pl.col(c).cast(t) for c, t in spec.items()]))


#: radar columns the bound needs (the ``radars`` contract plus the simulator's ``pd``, scan timing)
NEEDED = ("radar_id", "lat_deg", "lon_deg", "alt_m", "scan_period_s", "sigma_range_m", "sigma_azimuth_deg",
          "sigma_elevation_deg", "max_range_m")


def bound_stage(ds, truth: pl.DataFrame | pl.LazyFrame, radars: pl.DataFrame, reports: pl.DataFrame,
                scored: pl.DataFrame, accuracy: pl.DataFrame, notes: list[str]) -> pl.DataFrame:
    """The pipeline's ``bound`` rows (:func:`bound_metrics`) for a dataset ``ds`` with truth;
    without what the bound needs (radar columns, truth velocities, scored samples) no rows and
    a note saying why. Missing ``pd`` counts as 1, missing ``timing`` as rotating, missing
    ``min_elevation_deg`` as no limit (each with a note). ``truth`` may be a scan (of the
    reference on disk): it is then read :data:`BOUND_READ_AIRCRAFT` aircraft at a time, never
    whole."""
    spec = TABLES["metrics"].required
    names = truth.collect_schema().names() if isinstance(truth, pl.LazyFrame) else truth.columns
    missing = [c for c in NEEDED if c not in radars.columns]
    missing += [c for c in ("x_m", "vx_mps", "vy_mps", "vz_mps") if c not in names]
    if missing or scored.is_empty() or radars.is_empty():
        why = f"missing column(s) {', '.join(missing)}" if missing else "nothing scored against truth"
        notes.append(f"bound: no posterior Cramér–Rao bound ({why})")
        return pl.DataFrame(schema=spec)
    for col, default in (("pd", "1"), ("timing", "rotating"), ("min_elevation_deg", "no limit")):
        if col not in radars.columns:
            notes.append(f"bound: radars has no {col}; taken as {default}")
    scen = getattr(ds, "scenario", None)
    cfg = BoundConfig.from_scenario(scen)
    max_el = {r.name: float(r.max_elevation_deg) for r in getattr(scen, "radars", ()) or ()}
    t0 = int(truth.select(pl.col("time").cast(TIME).dt.epoch("us").min()).lazy().collect().item())
    origins = scan_origins(radars, reports, t0)
    ids = np.sort(scored["truth_id"].drop_nulls().unique().cast(pl.Int64).to_numpy())
    sums = []
    # a block of aircraft at a time (each one's bound is its own recursion): the illuminations
    # and bounds of the whole recording are never held (the stage's peak on a long run)
    for read, held in _truth_reads(truth, ids):
        for lo in range(0, len(read), BOUND_AIRCRAFT):
            block = read[lo:lo + BOUND_AIRCRAFT].tolist()
            mine = scored.filter(pl.col("truth_id").cast(pl.Int64).is_in(block))
            events = illuminations(held.filter(pl.col("truth_id").cast(pl.Int64).is_in(block)), radars, reports,
                                   ds.origin, cfg, max_el, t0_us=t0, origins=origins)
            sums.append(_bound_sums(mine, pcrb_at(mine, events, cfg)))
            del mine, events
        del held
    return _bound_rows(pl.concat(sums) if sums else _bound_sums(scored.clear(), pl.DataFrame()), accuracy)


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
