"""The radar's own secondary processing: per-radar, per-local-track Singer channels.

Real radars send, with each plot, their track estimate, its covariance and the range
innovation. This module produces those columns — for the simulator (what a radar would send)
and for plot-only inputs (e.g. ASTERIX CAT048 plots) before tertiary processing.

Each local track is filtered in three decoupled polar channels (range, azimuth, elevation),
each a Singer Kalman filter (monograph eqs. (4.46), (4.53)–(4.71); range channel exactly as the
seed's per-radar range channel). Angular channels use the cross-range manoeuvre intensity
divided by the range, so one σ_m in m/s² describes the aircraft. The polar estimate with its
rates is converted to radar-local ENU position/velocity with the full 6×6 covariance J P Jᵀ.

The recursion is vectorised across all local tracks of all radars and Monte-Carlo runs: the
Python loop runs over the report rank within a track (the scan count), never over reports.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary import geo
from tertiary.schema import is_sorted_by
from tertiary.filters.singer import SingerModel, predict_elementwise, singer_coefficients, update_elementwise

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

    * ``range_model``: range channel, α_ф = 1/30 s⁻¹ (30 s manoeuvre time constant, digest §3)
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
    """

    range_model: SingerModel = field(default_factory=lambda: SingerModel(alpha=1 / 30, sigma_m=2.0))
    cross_sigma_m: float = 2.0
    v0_sigma_mps: float = 300.0
    altitude_sigma_m: float = 30.0
    reinit_gate: float = 25.0


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


def _filter(t: NDArray[np.float64], z: NDArray[np.float64], r: NDArray[np.float64],
            starts: NDArray[np.int64], lengths: NDArray[np.int64], cfg: LocalTrackerConfig):
    """Run the three channels over every track; returns, in report order, the estimates
    (2 (pos, rate), 3 channels, n), covariances (3 (P00, P01, P11), 3 channels, n), the range
    innovation and its variance.

    Reports are laid out rank-major (:func:`_rank_major`) with the channels interleaved, so
    the (track, channel) pairs alive at rank k are a prefix of the state and a contiguous
    slice of every per-report array: each step runs on contiguous 1-D arrays, never gathers.
    The Singer coefficients are computed for all reports before the recursion, and the
    results go to one table put back in report order by a single row gather. State: x
    (3 comps, 3·tracks) and the six unique covariance terms p (6, 3·tracks).
    """
    n, m_tracks = len(t), len(starts)
    perm, alive, offsets = _rank_major(starts, lengths)
    zr, rr = z[perm], r[perm]
    tau = t[perm] - t[perm - 1]                # previous report of the same track (unused at rank 0)
    missing = ~np.isfinite(zr[:, 0])           # no range: the channel scale comes from the state
    rng_now = np.maximum(np.where(missing, 0.0, zr[:, 0]), 100.0)
    a, b, f, q = _coefficients(tau, rng_now, cfg)
    z3, r3, tau3 = zr.ravel(), rr.ravel(), np.repeat(tau, 3)
    has_missing = np.add.reduceat(missing, offsets[:-1]) > 0 if n else np.zeros(0, bool)
    x = np.zeros((3, 3 * m_tracks))
    p = np.zeros((6, 3 * m_tracks))
    out = np.empty((n, OUT_RES + 2))
    out[:alive[0] if n else 0, OUT_RES:] = np.nan     # first reports have no innovation
    for k, m in enumerate(alive):
        sl, rows = slice(3 * offsets[k], 3 * (offsets[k] + m)), slice(offsets[k], offsets[k] + m)
        xs, ps = x[:, :3 * m], p[:, :3 * m]
        if has_missing[k]:
            _patch_missing(q, rng_now, offsets[k], missing[rows], xs, tau, cfg)
        zk, rk = z3[sl], r3[sl]
        if k == 0:
            xs[0], ps[0], ps[3], ps[5] = _initiation(zk, rk, rng_now[rows], cfg)
        else:
            predict_elementwise(xs, ps, tau3[sl], (a[sl], b[sl], f[sl], q[sl]))
            nu = zk - xs[0]
            nu[1::3] = np.mod(nu[1::3] + np.pi, 2 * np.pi) - np.pi   # azimuth wraps
            lost = np.isfinite(nu) & (nu * nu > cfg.reinit_gate * (ps[0] + rk))
            s = update_elementwise(xs, ps, np.where(lost, np.nan, nu), rk)
            if lost.any():
                _reinitiate(xs, ps, lost, _initiation(zk, rk, rng_now[rows], cfg))
            out[rows, OUT_RES], out[rows, OUT_RES + 1] = nu[0::3], s[0::3]
        block = out[rows]
        for col, v in ((OUT_X, xs[0]), (OUT_RATE, xs[1]), (OUT_P00, ps[0]), (OUT_P01, ps[1]), (OUT_P11, ps[3])):
            block[:, col:col + 3] = v.reshape(m, 3)
    back = np.empty(n, np.int64)
    back[perm] = np.arange(n)
    out = out.take(back, axis=0).T             # (column, report)
    return out[:OUT_P00].reshape(2, 3, n), out[OUT_P00:OUT_RES].reshape(3, 3, n), out[OUT_RES], out[OUT_RES + 1]


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


def track_reports(reports: pl.DataFrame, radars: pl.DataFrame,
                  cfg: LocalTrackerConfig = LocalTrackerConfig()) -> pl.DataFrame:
    """Add the radar track estimate, covariance and range innovation columns to plot reports.

    ``reports`` must be valid (see :func:`tertiary.schema.validate`); it is returned sorted by
    (run, radar_id, local_track_id, time) with :data:`ESTIMATE_COLUMNS` added (replacing any
    existing ones). The first report of a track has no innovation (NaN).
    """
    df = reports if "run" in reports.columns else reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    df = df.drop([c for c in ESTIMATE_COLUMNS if c in df.columns])
    if not is_sorted_by(df, TRACK_KEY + ["time"]):   # the simulator emits them so
        df = df.sort(TRACK_KEY + ["time"], maintain_order=True)
    n = len(df)
    t, _ = _seconds(df["time"])
    z, r = measurement_polar(df, radars, cfg.altitude_sigma_m)
    keys = df.select(TRACK_KEY).to_numpy()
    new = np.ones(n, dtype=bool)
    if n:
        new[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    starts = np.flatnonzero(new)
    lengths = np.diff(np.append(starts, n))
    order = np.argsort(-lengths, kind="stable")
    est, cov, res, res_var = _filter(t, z, r, starts[order], lengths[order], cfg)
    pos, vel, cov_enu = _to_enu(est, cov)
    deg2 = np.degrees(1.0) ** 2
    return df.with_columns(
        pl.Series("est_range_m", est[0, 0]),
        pl.Series("est_range_rate_mps", est[1, 0]),
        pl.Series("est_azimuth_deg", np.mod(np.degrees(est[0, 1]), 360.0)),
        pl.Series("est_elevation_deg", np.degrees(est[0, 2])),
        pl.Series("est_range_var_m2", cov[0, 0]),
        pl.Series("est_azimuth_var_deg2", cov[0, 1] * deg2),
        pl.Series("est_elevation_var_deg2", cov[0, 2] * deg2),
        pl.Series("x_m", pos[:, 0]), pl.Series("y_m", pos[:, 1]), pl.Series("z_m", pos[:, 2]),
        pl.Series("vx_mps", vel[:, 0]), pl.Series("vy_mps", vel[:, 1]), pl.Series("vz_mps", vel[:, 2]),
        pl.Series("est_cov", cov_enu, dtype=pl.Array(pl.Float64, 36)),
        pl.Series("res_range_m", res),
        pl.Series("res_range_var_m2", res_var),
    )
