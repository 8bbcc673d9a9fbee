"""The radar's own secondary processing: per-radar, per-local-track Singer channels.

Real radars send, with each plot, their track estimate, its covariance and the range
innovation. This module produces those columns — for the simulator (what a radar would send)
and for plot-only inputs (e.g. ASTERIX CAT048 plots) before tertiary processing.

Each local track is filtered in three decoupled polar channels (range, azimuth, elevation),
each a Singer Kalman filter (monograph eqs. (4.46), (4.53)–(4.71); range channel exactly as the
seed's per-radar range channel). As an option (``LocalTrackerConfig.range_channel``) the range
coordinate of tracks whose reports carry Mode S enhanced-surveillance parameters runs one of the
monograph's chapter 3 channels instead (:mod:`tertiary.filters.kinematic`: kinematic-parameter
(3.12)–(3.58) or kinematic + dynamic (3.59)–(3.127)); other tracks keep the Singer channel. Angular channels use the cross-range manoeuvre intensity
divided by the range, so one σ_m in m/s² describes the aircraft. The polar estimate with its
rates is converted to radar-local ENU position/velocity with the full 6×6 covariance J P Jᵀ.
The tracks of an MLAT / WAM sensor (:mod:`tertiary.sensors.mlat`) run the same Singer channels on
the east, north and up axes of its local ENU instead (its Cartesian plot at its Mode C height),
with the innovation along the line of sight from its site in place of the range innovation.

The recursion is vectorised across all local tracks of all radars and Monte-Carlo runs: the
Python loop runs over the report rank within a track (the scan count), never over reports.
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.sensors import mlat
from tertiary.sensors.mlat import radial_innovation
from tertiary.core.errors import OptionError
from tertiary.contract import EHS_REPORT_COLUMNS, is_sorted_by
from tertiary.filters import kinematic_los as los
from tertiary.filters.kinematic import (KinematicDynamicRangeChannel, KinematicRangeChannel, channel_inputs, dynamic_aux, kinematic_aux)
from tertiary.filters.singer import (SingerModel, predict_elementwise, singer_coefficients, update_elementwise)

TRACK_KEY = ["run", "radar_id", "local_track_id"]

#: columns produced by :func:`track_reports`
ESTIMATE_COLUMNS = [
    "est_range_m", "est_range_rate_mps", "est_azimuth_deg", "est_elevation_deg",
    "est_range_var_m2", "est_azimuth_var_deg2", "est_elevation_var_deg2",
    "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "est_cov",
    "res_range_m", "res_range_var_m2",
]


@dataclass(frozen=True)
class LocalTrackerConfig:
    """Parameters of the per-radar Singer channels (documented defaults).

    * ``range_model``: range channel, α_ф = 1/30 s⁻¹ (30 s manoeuvre time constant)
      and σ_m = 2 m/s² (a 3°/s turn at 80–150 m/s has 4–8 m/s² centripetal acceleration, of
      which the line-of-sight part is usually much smaller).
    * ``cross_sigma_m``: the same intensity across the line of sight, in m/s²; the angular
      channels use σ_m / range (rad/s²).
    * ``v0_sigma_mps``: initial rate uncertainty (one-point initiation; the first update acts
      like the two-point initiation of the text).
    * ``altitude_sigma_m``: accuracy of a Mode C altitude used to derive elevation.
    * ``reinit_gate``: a channel whose normalised squared innovation ν²/S exceeds this (5σ)
      is re-initiated on the plot, as a radar tracker restarts a track it has lost — needed
      where polar channels cannot follow (close passages with azimuth swings of tens of
      degrees per scan).
    * ``range_channel``: the range channel — ``"singer"`` (above), or the chapter 3
      ``"kinematic"`` (§3.4) / ``"kinematic_dynamic"`` (§3.5) channel driven by the Mode S EHS
      report columns (:data:`tertiary.contract.EHS_REPORT_COLUMNS`) for local tracks whose first
      report and at least ``ehs_min_fraction`` of all reports carry them (between EHS replies
      the auxiliary filters coast); other tracks keep the Singer channel.
    * ``range_variant``: (3.11) resp. (3.62) ``"corrected"`` or ``"printed"``.
    * ``range_speed_rate``: add the along-track acceleration V̇ (the rate of the V_ц auxiliary
      filter) to u — the term V̇ c_x of :func:`~tertiary.filters.kinematic_los.los_acceleration`
      (kinematic) resp. V̇/g in n_x (kinematic + dynamic). The monograph's (3.11) is the V̇ = 0
      case; terminal-area traffic accelerates and decelerates (departures 0.3 m/s² for minutes),
      which V̇ = 0 turns into a range-acceleration bias. False: as printed.
    * ``range_sigma_u``: √D_a, σ of the chapter 3 channels' input-acceleration error (m/s²).
      u is held over a scan (4–12 s): 0.5 m/s² covers the EHS noise carried into u in steady
      flight and part of the hold error at turn entry/exit (smaller is better in steady flight,
      larger in turns; 0.5 the compromise).
    """

    range_model: SingerModel = field(default_factory=lambda: SingerModel(alpha=1 / 30, sigma_m=2.0))
    cross_sigma_m: float = 2.0
    v0_sigma_mps: float = 300.0
    altitude_sigma_m: float = 30.0
    reinit_gate: float = 25.0
    range_channel: Literal["singer", "kinematic", "kinematic_dynamic"] = "singer"
    range_variant: Literal["corrected", "printed"] = "corrected"
    range_sigma_u: float = 0.5
    range_speed_rate: bool = True
    ehs_min_fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.range_channel not in RANGE_CHANNELS:
            raise OptionError(f"unknown range channel {self.range_channel!r}; use {', '.join(RANGE_CHANNELS)}",
                              option="local_tracker.range_channel")
        if self.range_variant not in ("corrected", "printed"):
            raise OptionError(f"unknown range variant {self.range_variant!r}; use corrected or printed",
                              option="local_tracker.range_variant")
        if not (self.range_sigma_u > 0 and 0.0 <= self.ehs_min_fraction <= 1.0):
            raise OptionError("range_sigma_u must be > 0 and ehs_min_fraction in [0, 1]",
                              option="local_tracker.range_sigma_u")


#: the range channels of :class:`LocalTrackerConfig`
RANGE_CHANNELS = ("singer", "kinematic", "kinematic_dynamic")
#: the EHS columns the chapter 3 channels need (the track-angle rate is not an input)
_EHS_NEEDED = ("ehs_gs_mps", "ehs_track_deg", "ehs_roll_deg", "ehs_vrate_mps")


def _seconds(time: pl.Series) -> tuple[NDArray[np.float64], int]:
    us = time.cast(pl.Datetime("us", "UTC")).dt.epoch("us").to_numpy()
    t0 = int(us.min()) if len(us) else 0
    return (us - t0) * 1e-6, t0


def measurement_polar(reports: pl.DataFrame, radars: pl.DataFrame, altitude_sigma_m: float
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Measured (range, az_rad, el_rad) and their variances per report; elevation derived from
    ``altitude_m`` (4/3-Earth geometry) where the report has none."""
    site = reports.select("radar_id").join(
        radars.select("radar_id", "alt_m", "sigma_range_m", "sigma_azimuth_deg", "sigma_elevation_deg"),
        on="radar_id", how="left", maintain_order="left")
    rng = reports["range_m"].to_numpy().astype(float)
    az = np.radians(reports["azimuth_deg"].to_numpy().astype(float))
    n = len(reports)
    el = (reports["elevation_deg"].fill_null(np.nan).to_numpy().astype(float)
          if "elevation_deg" in reports.columns else np.full(n, np.nan))
    el = np.radians(el)
    var_el = np.full(n, np.radians(1.0)) ** 2
    var_el = np.where(np.isfinite(el), np.radians(site["sigma_elevation_deg"].to_numpy()) ** 2, var_el)
    if "altitude_m" in reports.columns:
        alt = reports["altitude_m"].fill_null(np.nan).to_numpy().astype(float)
        use = ~np.isfinite(el) & np.isfinite(alt)
        if use.any():           # simulated plots all carry an elevation
            derived = np.radians(geo.elevation_from_altitude(rng, alt, site["alt_m"].to_numpy()))
            el = np.where(use, derived, el)
            var_el = np.where(use, (altitude_sigma_m / np.maximum(rng, 1.0)) ** 2, var_el)
    z = np.stack([rng, az, el], axis=1)
    r = np.stack([site["sigma_range_m"].to_numpy() ** 2,
                  np.radians(site["sigma_azimuth_deg"].to_numpy()) ** 2, var_el], axis=1)
    return z, r


def _rank_major(starts: NDArray[np.int64], lengths: NDArray[np.int64]
                ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Order putting the k-th report of every track together. Tracks are sorted by decreasing
    length, so the tracks alive at rank k are the first ``alive[k]``; rank k occupies
    ``offsets[k]:offsets[k + 1]`` and ``perm`` maps that layout to report rows."""
    alive = np.searchsorted(-lengths, -np.arange(lengths.max(initial=0)), side="left")
    offsets = np.concatenate([[0], np.cumsum(alive)])
    track = np.repeat(np.arange(len(starts)), lengths)
    rank = np.arange(len(track)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    perm = np.empty(len(track), np.int64)
    perm[offsets[rank] + track] = starts[track] + rank
    return perm, alive, offsets


def _sigma(rng_now: NDArray[np.float64], cfg: LocalTrackerConfig) -> NDArray[np.float64]:
    """Manoeuvre intensity per report and channel (interleaved): σ_m for the range, the
    cross-range intensity over the range for the angles."""
    cross = cfg.cross_sigma_m / rng_now
    return np.stack([np.full(len(rng_now), cfg.range_model.sigma_m), cross, cross], axis=1).ravel()


def _coefficients(tau: NDArray[np.float64], rng_now: NDArray[np.float64], cfg: LocalTrackerConfig):
    """Singer coefficients (4.46)/(4.53) for the step τ ending at each report, channels
    interleaved (3·reports,)."""
    model = cfg.range_model
    return singer_coefficients(np.repeat(tau, 3), model.alpha, _sigma(rng_now, cfg), model.variant)


def _initiation(z: NDArray[np.float64], r: NDArray[np.float64], rng_now: NDArray[np.float64],
                cfg: LocalTrackerConfig) -> tuple[NDArray[np.float64], ...]:
    """One-point initiation on the plots (channels interleaved), the non-zero state terms
    (x, P00, P11, P22): position = plot, rate and acceleration 0 with variances (v0/range)² and
    σ_m², the angular channels scaled by the range."""
    ok = np.isfinite(z)
    scale = np.stack([np.ones(len(rng_now)), rng_now, rng_now], axis=1).ravel()
    return np.where(ok, z, 0.0), np.where(ok, r, 1e12), (cfg.v0_sigma_mps / scale) ** 2, _sigma(rng_now, cfg) ** 2


#: columns of the filter's output table: x, ẋ, P00, P01, P11 per channel, then ν_r, S_r
OUT_X, OUT_RATE, OUT_P00, OUT_P01, OUT_P11, OUT_RES = 0, 3, 6, 9, 12, 15


def _filter(us: NDArray[np.int64], z: NDArray[np.float64], r: NDArray[np.float64],
            starts: NDArray[np.int64], lengths: NDArray[np.int64], cfg: LocalTrackerConfig,
            prior: "_Prior | None" = None, cartesian: bool = False):
    """Run the three channels over every track; returns, in report order, the estimates
    (2 (pos, rate), 3 channels, n), covariances (3 (P00, P01, P11), 3 channels, n), the range
    innovation and its variance, and the channel states after each track's last report:
    x (3, 3·tracks) and p (6, 3·tracks), tracks in the order of ``starts``.

    Reports are laid out rank-major (:func:`_rank_major`) with the channels interleaved, so
    the (track, channel) pairs alive at rank k are a prefix of the state and a contiguous
    slice of every per-report array: each step runs on contiguous 1-D arrays, never gathers.
    The Singer coefficients are computed for all reports before the recursion, and the
    results go to one table put back in report order by a single row gather. State: x
    (3 comps, 3·tracks) and the six unique covariance terms p (6, 3·tracks).

    ``us`` are the report times in integer µs: every step τ is a difference of two of them,
    so the result does not depend on which reports share the call. With ``prior`` the tracks
    it marks continue from its states (a windowed run): their first report here is a
    prediction + update from the prior state over τ = t − t_prior, not an initiation.

    ``cartesian``: the three channels are the east, north, up axes of an MLAT sensor's local
    ENU (:mod:`tertiary.sensors.mlat`): one manoeuvre intensity σ_m per axis (no range scaling, no
    angle wrap), and the innovation returned is the one along the line of sight from the site
    (:func:`tertiary.sensors.mlat.radial_innovation`), the range innovation's counterpart.
    """
    n, m_tracks = len(us), len(starts)
    perm, alive, offsets = _rank_major(starts, lengths)
    zr, rr = z[perm], r[perm]
    tau = (us[perm] - us[perm - 1]) * 1e-6     # previous report of the same track (unused at rank 0)
    cont = np.zeros(m_tracks, bool) if prior is None else prior.cont
    if cont.any():                             # rank 0 is the first m_tracks rows, tracks in order
        tau[:m_tracks][cont] = (us[perm[:m_tracks]][cont] - prior.t_us[cont]) * 1e-6
    missing = ~np.isfinite(zr[:, 0])           # no range: the channel scale comes from the state
    rng_now = np.ones(n) if cartesian else np.maximum(np.where(missing, 0.0, zr[:, 0]), 100.0)
    innovation = _cartesian_innovation if cartesian else _range_innovation
    coeffs = _coefficients(tau, rng_now, cfg)
    z3, r3, tau3 = zr.ravel(), rr.ravel(), np.repeat(tau, 3)
    has_missing = np.add.reduceat(missing, offsets[:-1]) > 0 if n else np.zeros(0, bool)
    x = np.zeros((3, 3 * m_tracks)) if prior is None else prior.x.copy()
    p = np.zeros((6, 3 * m_tracks)) if prior is None else prior.p.copy()
    out = np.empty((n, OUT_RES + 2))
    out[:alive[0] if n else 0, OUT_RES:] = np.nan     # first reports have no innovation
    for k, m in enumerate(alive):
        sl, rows = slice(3 * offsets[k], 3 * (offsets[k] + m)), slice(offsets[k], offsets[k] + m)
        xs, ps = x[:, :3 * m], p[:, :3 * m]
        if has_missing[k]:
            _patch_missing(coeffs[3], rng_now, offsets[k], missing[rows], xs, tau, cfg)
        zk, rk = z3[sl], r3[sl]
        if k == 0:
            init = _initiation(zk, rk, rng_now[rows], cfg)
            if cont.any():                     # continuing tracks: a normal step from the prior state
                c3 = (3 * np.flatnonzero(cont)[:, None] + np.arange(3)).ravel()
                xc, pc = xs[:, c3], ps[:, c3]
                nu, s = _step(xc, pc, zk[c3], rk[c3], tau3[sl][c3], tuple(c[sl][c3] for c in coeffs),
                              tuple(v[c3] for v in init), cfg, wrap=not cartesian)
                xs[:, c3], ps[:, c3] = xc, pc
                out[np.flatnonzero(cont), OUT_RES], out[np.flatnonzero(cont), OUT_RES + 1] = innovation(nu, s, zk[c3])
            fresh = ~np.repeat(cont, 3)
            xs[0], ps[0], ps[3], ps[5] = (np.where(fresh, v, old) for v, old in zip(init, (xs[0], ps[0], ps[3], ps[5])))
        else:
            nu, s = _step(xs, ps, zk, rk, tau3[sl], tuple(c[sl] for c in coeffs),
                          None, cfg, rng_rows=rng_now[rows], wrap=not cartesian)
            out[rows, OUT_RES], out[rows, OUT_RES + 1] = innovation(nu, s, zk)
        block = out[rows]
        for col, v in ((OUT_X, xs[0]), (OUT_RATE, xs[1]), (OUT_P00, ps[0]), (OUT_P01, ps[1]), (OUT_P11, ps[3])):
            block[:, col:col + 3] = v.reshape(m, 3)
    back = np.empty(n, np.int64)
    back[perm] = np.arange(n)
    out = out.take(back, axis=0).T             # (column, report)
    return (out[:OUT_P00].reshape(2, 3, n), out[OUT_P00:OUT_RES].reshape(3, 3, n), out[OUT_RES], out[OUT_RES + 1],
            x, p)


def _range_innovation(nu, s, zk) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The range channel's innovation and its variance per track (channels interleaved)."""
    return nu[0::3], s[0::3]


def _cartesian_innovation(nu, s, zk) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The Cartesian channels' innovation along the line of sight from the site (per track)."""
    return radial_innovation(nu.reshape(-1, 3), s.reshape(-1, 3), zk.reshape(-1, 3))


def _step(xs, ps, zk, rk, tau3, coeffs, init, cfg: LocalTrackerConfig, rng_rows=None, wrap: bool = True):
    """One Singer step of (track, channel) pairs in place: predict over τ, update on the plot,
    re-initiate the channels whose innovation fails ``cfg.reinit_gate``. ``init`` is the
    one-point initiation of these pairs (computed from ``rng_rows`` when None, only if a
    channel is lost). ``wrap``: the second channel is an azimuth. Returns the innovation and
    its variance."""
    predict_elementwise(xs, ps, tau3, coeffs)
    nu = zk - xs[0]
    if wrap:
        nu[1::3] = np.mod(nu[1::3] + np.pi, 2 * np.pi) - np.pi   # azimuth wraps
    lost = np.isfinite(nu) & (nu * nu > cfg.reinit_gate * (ps[0] + rk))
    s = update_elementwise(xs, ps, np.where(lost, np.nan, nu), rk)
    if lost.any():
        _reinitiate(xs, ps, lost, init if init is not None else _initiation(zk, rk, rng_rows, cfg))
    return nu, s


def _patch_missing(q, rng_now, lo: int, missing, xs, tau, cfg: LocalTrackerConfig) -> None:
    """Reports without a range scale the angular channels by the current range estimate."""
    j = np.flatnonzero(missing)
    rows = lo + j
    rng_now[rows] = np.maximum(xs[0, 3 * j], 100.0)
    q.reshape(-1, 3)[rows] = _coefficients(tau[rows], rng_now[rows], cfg)[3].reshape(-1, 3)


def _reinitiate(xs, ps, lost, init: tuple[NDArray[np.float64], ...]) -> None:
    """Channels whose innovation failed the gate restart on the plot (one-point initiation)."""
    np.copyto(xs, 0.0, where=lost)
    np.copyto(ps, 0.0, where=lost)
    for target, v in zip((xs[0], ps[0], ps[3], ps[5]), init):
        np.copyto(target, v, where=lost)


def _to_enu(est: NDArray[np.float64], cov: NDArray[np.float64], chunk: int = 8192):
    """Polar track states (2 (pos, rate), 3 channels, n) with per-channel (P00, P01, P11) to
    radar-local ENU position, velocity (n, 3) and flattened 6×6 covariance (n, 36).

    Converted in cache-sized chunks into preallocated outputs: whole-array temporaries of
    n × 36 doubles made this step slow and its timing erratic.
    """
    n = est.shape[-1]
    pos, vel, cov36 = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 36))

    def convert(lo: int) -> None:
        sl = slice(lo, min(lo + chunk, n))
        e, c = est[:, :, sl], cov[:, :, sl]
        p, v, cc = geo.polar_channels_to_enu(e[0, 0], np.degrees(e[0, 1]), np.degrees(e[0, 2]),
                                             e[1, 0], np.degrees(e[1, 1]), np.degrees(e[1, 2]), c[0], c[1], c[2])
        pos[sl], vel[sl], cov36[sl] = p, v, cc.reshape(-1, 36)

    # numpy releases the GIL inside these array operations: chunks convert in parallel
    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        list(pool.map(convert, range(0, n, chunk)))
    return pos, vel, cov36


def ehs_tracks(df: pl.DataFrame, starts: NDArray[np.int64], lengths: NDArray[np.int64],
               min_fraction: float) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per report, whether it carries the EHS parameters the chapter 3 channels need; per track,
    whether it can run them (its first report and ≥ ``min_fraction`` of all carry them)."""
    if not set(_EHS_NEEDED) <= set(df.columns) or not len(starts):
        return np.zeros(df.height, bool), np.zeros(len(starts), bool)
    vals = df.select(pl.col(c).cast(pl.Float64).fill_null(np.nan) for c in _EHS_NEEDED).to_numpy()
    has = np.isfinite(vals).all(axis=1)
    frac = np.add.reduceat(has.astype(float), starts) / lengths
    return has, has[starts] & (frac >= min_fraction)


def _chapter3_inputs(df: pl.DataFrame, z: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Channel inputs (:func:`~tertiary.filters.kinematic.channel_inputs`) of every report: the
    plot's range, azimuth, elevation and the EHS ground speed, track, vertical rate and roll."""
    e = {c: df[c].cast(pl.Float64).fill_null(np.nan).to_numpy() for c in _EHS_NEEDED}
    return channel_inputs(z[:, 0], np.degrees(z[:, 1]), np.degrees(z[:, 2]), e["ehs_gs_mps"], e["ehs_track_deg"],
                          e["ehs_vrate_mps"], e["ehs_roll_deg"])


@dataclass(frozen=True)
class KinematicSpeedRateChannel(KinematicRangeChannel):
    """§3.4 channel with u = a_L including the along-track term V̇ c_x, V̇ the V_ц filter's rate."""

    def acceleration(self, state) -> NDArray[np.float64]:
        e = lambda k, r=False: self.aux_estimate(state, k, r)  # noqa: E731
        return los.los_acceleration(e("speed"), e("theta"), e("theta", True), e("phi"), e("phi", True),
                                    e("eps_b"), e("eps_b", True), e("eps_g"), e("eps_g", True),
                                    v_dot=e("speed", True), variant=self.variant)


@dataclass(frozen=True)
class KinematicDynamicSpeedRateChannel(KinematicDynamicRangeChannel):
    """§3.5 channel with n_x = (coordinated-flight n_x) + V̇/g, V̇ the V_ц filter's rate (EHS
    carries no longitudinal acceleration; the n_x filter alone sees only sin θ)."""

    def acceleration(self, state) -> NDArray[np.float64]:
        e = lambda k, r=False: self.aux_estimate(state, k, r)  # noqa: E731
        n_x = e("n_x") + e("speed", True) / los.G0
        n_xl = los.los_load_factor(n_x, e("n_y"), e("n_z"), e("gamma"), e("theta"), e("phi"), e("eps_b"), e("eps_g"))
        return los.range_acceleration(n_xl, e("eps_b"), e("speed"), state["x"][:, 1], state["x"][:, 0], self.variant)


_CHANNEL_CLASSES = {(False, "kinematic"): KinematicRangeChannel, (True, "kinematic"): KinematicSpeedRateChannel,
                    (False, "kinematic_dynamic"): KinematicDynamicRangeChannel,
                    (True, "kinematic_dynamic"): KinematicDynamicSpeedRateChannel}


def _make_channel(cfg: LocalTrackerConfig, sigma_range_m: float, sigma_az_deg: float, sigma_el_deg: float,
                  speed_mps: float):
    """The configured chapter 3 channel for one radar: its σ_r, its azimuth and elevation σ in
    the LOS auxiliary filters (ε_Г, ε_B), θ's σ from the typical speed of its EHS tracks."""
    aux = (kinematic_aux if cfg.range_channel == "kinematic" else dynamic_aux)(np.radians(sigma_az_deg), speed_mps)
    sigma = {"eps_g": np.radians(sigma_az_deg), "eps_b": np.radians(sigma_el_deg)}
    aux = tuple(dataclasses.replace(a, sigma_meas=float(sigma[a.key])) if a.key in sigma else a for a in aux)
    cls = _CHANNEL_CLASSES[(cfg.range_speed_rate, cfg.range_channel)]
    return cls(variant=cfg.range_variant, sigma_range_m=sigma_range_m, sigma_u=cfg.range_sigma_u,
               v0_sigma_mps=cfg.v0_sigma_mps, aux=aux)


def _run_channel(channel, inputs: dict[str, NDArray[np.float64]], t: NDArray[np.float64],
                 starts: NDArray[np.int64], lengths: NDArray[np.int64], gate: float
                 ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Run a chapter 3 channel over the given tracks, vectorised across them (loop over the
    report rank, tracks sorted by decreasing length so the alive ones are a prefix). A track
    whose normalised squared innovation exceeds ``gate`` restarts on the plot, as the Singer
    channels do. Returns the report rows and, per row, (D, V, P00, P01, P11, ν, S)."""
    order = np.argsort(-lengths, kind="stable")
    starts, lengths = starts[order], lengths[order]
    alive = np.searchsorted(-lengths, -np.arange(lengths.max(initial=0)), side="left")
    rows = np.concatenate([starts[:m] + k for k, m in enumerate(alive)]) if len(alive) else np.zeros(0, np.int64)
    out = np.full((len(rows), 7), np.nan)
    state = channel.init({key: v[starts] for key, v in inputs.items()})
    lo = 0
    for k, m in enumerate(alive):
        idx = starts[:m] + k
        if k:
            state = {key: v[:m] for key, v in state.items()}
            zk = {key: v[idx] for key, v in inputs.items()}
            state, nu, s, _ = channel.step(state, zk, t[idx] - t[idx - 1])
            lost = np.flatnonzero(np.isfinite(nu) & (nu * nu > gate * s))
            if lost.size:
                fresh = channel.init({key: v[lost] for key, v in zk.items()})
                for key in state:
                    state[key][lost] = fresh[key]
            out[lo:lo + m, 5], out[lo:lo + m, 6] = nu, s
        x, p = state["x"], state["P"]
        out[lo:lo + m, :5] = np.stack([x[:, 0], x[:, 1], p[:, 0], p[:, 1], p[:, 3]], axis=1)
        lo += m
    return rows, out


def _chapter3_range(df: pl.DataFrame, radars: pl.DataFrame, t, z, starts, lengths, cfg: LocalTrackerConfig,
                    est, cov, res, res_var) -> None:
    """Replace, in place, the Singer range channel's outputs (``est[:, 0]``, ``cov[:, 0]``, the
    range innovation) by the configured chapter 3 channel's, for the tracks with EHS; run per
    radar (each has its own σ_r and angle σ)."""
    has, ok = ehs_tracks(df, starts, lengths, cfg.ehs_min_fraction)
    if not ok.any():
        return
    inputs = _chapter3_inputs(df, z)
    track_radar = df["radar_id"].to_numpy()[starts]
    sig = radars.select("radar_id", "sigma_range_m", "sigma_azimuth_deg", "sigma_elevation_deg")
    for rid, s_r, s_a, s_e in sig.iter_rows():
        sel = ok & (track_radar == rid)
        if not sel.any():
            continue
        mine = np.repeat(sel, lengths) & has
        speed = float(np.median(inputs["speed"][mine])) if mine.any() else 100.0
        rows, out = _run_channel(_make_channel(cfg, float(s_r), float(s_a), float(s_e), speed), inputs, t,
                                 starts[sel], lengths[sel], cfg.reinit_gate)
        est[0, 0, rows], est[1, 0, rows] = out[:, 0], out[:, 1]
        cov[0, 0, rows], cov[1, 0, rows], cov[2, 0, rows] = out[:, 2], out[:, 3], out[:, 4]
        res[rows], res_var[rows] = out[:, 5], out[:, 6]


#: schema of the local-tracker carry (:func:`track_reports_step`): one row per local track, the
#: time of its last report (µs since the Unix epoch) and its channels' Singer states after it —
#: x = (pos, rate, acc) × (range, azimuth, elevation) and the six covariance terms
#: (P00, P01, P02, P11, P12, P22) × the three channels, component-major
CARRY_SCHEMA = {"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32, "t_us": pl.Int64,
                "x": pl.Array(pl.Float64, 9), "p": pl.Array(pl.Float64, 18)}


def empty_carry() -> pl.DataFrame:
    """A local-tracker carry with no track (the first window)."""
    return pl.DataFrame(schema=CARRY_SCHEMA)


@dataclass(frozen=True)
class _Prior:
    """Carried states lined up with the tracks of one :func:`_filter` call."""

    cont: NDArray[np.bool_]            # (m,) the track continues a carried state
    t_us: NDArray[np.int64]            # (m,) time of its last carried report
    x: NDArray[np.float64]             # (3, 3m) channel states, channels interleaved per track
    p: NDArray[np.float64]             # (6, 3m)


def _key_frame(keys: NDArray[np.int64]) -> pl.DataFrame:
    return pl.DataFrame({c: keys[:, i] for i, c in enumerate(TRACK_KEY)}, schema=dict.fromkeys(TRACK_KEY, pl.Int64))


def _prior_for(carry: pl.DataFrame, keys: NDArray[np.int64]) -> _Prior:
    """The carried state of each track of ``keys`` (m, 3), zeros where it has none."""
    m = len(keys)
    got = _key_frame(keys).join(carry.with_columns(pl.col(TRACK_KEY).cast(pl.Int64)), on=TRACK_KEY, how="left",
                                maintain_order="left")
    cont = got["t_us"].is_not_null().to_numpy()
    x, p = np.zeros((m, 3, 3)), np.zeros((m, 6, 3))
    if cont.any():
        x[cont] = np.stack(got["x"].filter(pl.Series(cont)).to_numpy()).reshape(-1, 3, 3)
        p[cont] = np.stack(got["p"].filter(pl.Series(cont)).to_numpy()).reshape(-1, 6, 3)
    # (track, component, channel) → (component, 3·track + channel), the layout of _filter
    return _Prior(cont, got["t_us"].fill_null(0).to_numpy(), x.transpose(1, 0, 2).reshape(3, 3 * m),
                  p.transpose(1, 0, 2).reshape(6, 3 * m))


def _track(reports: pl.DataFrame, radars: pl.DataFrame, cfg: LocalTrackerConfig,
           carry: pl.DataFrame | None) -> tuple[pl.DataFrame, pl.DataFrame | None]:
    """:func:`track_reports`; with ``carry`` also continue its tracks and return the new carry.
    The tracks of MLAT sensors (:mod:`tertiary.sensors.mlat`) run Cartesian channels, the others polar."""
    df = reports if "run" in reports.columns else reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    df = df.drop([c for c in ESTIMATE_COLUMNS if c in df.columns])
    if not is_sorted_by(df, TRACK_KEY + ["time"]):   # the simulator emits them so
        df = df.sort(TRACK_KEY + ["time"], maintain_order=True)
    cart = mlat.is_mlat(df, radars)
    if not cart.any():
        return _track_part(df, radars, cfg, carry, False)
    parts = []
    for which in (False, True):
        sub = df.filter(pl.Series(cart == which))
        if sub.height:
            got, new_carry = _track_part(sub, radars, cfg, carry, which)
            parts.append(got)
            carry = new_carry if carry is not None else None
    return pl.concat(parts, how="diagonal_relaxed").sort(TRACK_KEY + ["time"], maintain_order=True), carry


def _estimate_columns(est, cov, res, res_var, cartesian: bool) -> list[pl.Series]:
    """The :data:`ESTIMATE_COLUMNS` of :func:`_filter`'s estimates, polar or Cartesian channels."""
    if cartesian:
        c = mlat.cartesian_estimates(est, cov)
        pos, vel, cov_enu = c.pop("pos"), c.pop("vel"), c.pop("cov")
        polar = [pl.Series(k, v) for k, v in c.items()]
    else:
        pos, vel, cov_enu = _to_enu(est, cov)
        deg2 = np.degrees(1.0) ** 2
        polar = [pl.Series("est_range_m", est[0, 0]), pl.Series("est_range_rate_mps", est[1, 0]),
                 pl.Series("est_azimuth_deg", np.mod(np.degrees(est[0, 1]), 360.0)),
                 pl.Series("est_elevation_deg", np.degrees(est[0, 2])), pl.Series("est_range_var_m2", cov[0, 0]),
                 pl.Series("est_azimuth_var_deg2", cov[0, 1] * deg2),
                 pl.Series("est_elevation_var_deg2", cov[0, 2] * deg2)]
    return [*polar,
            pl.Series("x_m", pos[:, 0]), pl.Series("y_m", pos[:, 1]), pl.Series("z_m", pos[:, 2]),
            pl.Series("vx_mps", vel[:, 0]), pl.Series("vy_mps", vel[:, 1]), pl.Series("vz_mps", vel[:, 2]),
            pl.Series("est_cov", cov_enu, dtype=pl.Array(pl.Float64, 36)),
            pl.Series("res_range_m", res), pl.Series("res_range_var_m2", res_var)]


def _track_part(df: pl.DataFrame, radars: pl.DataFrame, cfg: LocalTrackerConfig, carry: pl.DataFrame | None,
                cartesian: bool) -> tuple[pl.DataFrame, pl.DataFrame | None]:
    """:func:`_track` of sorted reports whose tracks all run polar channels or all Cartesian
    ones (an MLAT sensor's plot (MLAT-1), its axis variances: the x-y covariance is left out
    of the decoupled channels)."""
    n = len(df)
    us = df["time"].cast(pl.Datetime("us", "UTC")).dt.epoch("us").to_numpy()
    if cartesian:
        z, r3 = mlat.local_plots(df, radars, cfg.altitude_sigma_m)
        r = np.diagonal(r3, axis1=1, axis2=2).copy()
    else:
        z, r = measurement_polar(df, radars, cfg.altitude_sigma_m)
    keys = df.select(pl.col(TRACK_KEY).cast(pl.Int64)).to_numpy()
    new = np.ones(n, dtype=bool)
    if n:
        new[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    starts = np.flatnonzero(new)
    lengths = np.diff(np.append(starts, n))
    order = np.argsort(-lengths, kind="stable")
    prior = None if carry is None or carry.height == 0 else _prior_for(carry, keys[starts[order]])
    est, cov, res, res_var, x_end, p_end = _filter(us, z, r, starts[order], lengths[order], cfg, prior, cartesian)
    if cfg.range_channel != "singer" and not cartesian:
        t, _ = _seconds(df["time"])
        _chapter3_range(df, radars, t, z, starts, lengths, cfg, est, cov, res, res_var)
    out = df.with_columns(_estimate_columns(est, cov, res, res_var, cartesian))
    if carry is None:
        return out, None
    m = len(starts)
    last = (starts + lengths - 1)[order]
    mine = _key_frame(keys[starts[order]]).with_columns(
        pl.Series("t_us", us[last], pl.Int64),
        pl.Series("x", x_end.reshape(3, m, 3).transpose(1, 0, 2).reshape(m, 9), pl.Array(pl.Float64, 9)),
        pl.Series("p", p_end.reshape(6, m, 3).transpose(1, 0, 2).reshape(m, 18), pl.Array(pl.Float64, 18)),
    ).cast(CARRY_SCHEMA)
    kept = carry.cast(CARRY_SCHEMA).join(mine.select(TRACK_KEY), on=TRACK_KEY, how="anti")
    return out, pl.concat([kept, mine]).sort(TRACK_KEY)


def track_reports(reports: pl.DataFrame, radars: pl.DataFrame,
                  cfg: LocalTrackerConfig = LocalTrackerConfig()) -> pl.DataFrame:
    """Add the radar track estimate, covariance and range innovation columns to plot reports.

    ``reports`` must be valid (see :func:`tertiary.contract.validate`); it is returned sorted by
    (run, radar_id, local_track_id, time) with :data:`ESTIMATE_COLUMNS` added (replacing any
    existing ones). The first report of a track has no innovation (NaN).
    """
    return _track(reports, radars, cfg, None)[0]


def track_reports_step(carry: pl.DataFrame | None, reports: pl.DataFrame, radars: pl.DataFrame,
                       cfg: LocalTrackerConfig = LocalTrackerConfig()) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`track_reports` of the next reports of a stream: a track with a row in ``carry``
    (:data:`CARRY_SCHEMA`, :func:`empty_carry` at first) continues from its carried state
    (predict over the time since its last carried report, then update), a track without one
    starts. Returns the reports with estimates and the carry after them (the input carry's
    rows for tracks absent here, this call's tracks after their last report). Feeding a stream
    in consecutive pieces gives :func:`track_reports` of the whole stream to round-off, when
    every report of a piece is later than the carried report of its track.

    Only the Singer range channel: the chapter 3 channels size their LOS filters from the
    median EHS speed of all a radar's tracks in one call (:class:`OptionError` here).
    """
    if cfg.range_channel != "singer":
        raise OptionError(f"range channel {cfg.range_channel!r} cannot run window by window (it is sized on the "
                          "whole run's EHS speeds); use range_channel='singer' or a single window",
                          option="local_tracker.range_channel")
    out, new_carry = _track(reports, radars, cfg, empty_carry() if carry is None else carry)
    assert new_carry is not None
    return out, new_carry
