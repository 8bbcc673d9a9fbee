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
        derived = np.radians(geo.elevation_from_altitude(rng, alt, site["alt_m"].to_numpy()))
        el = np.where(use, derived, el)
        var_el = np.where(use, (altitude_sigma_m / np.maximum(rng, 1.0)) ** 2, var_el)
    z = np.stack([rng, az, el], axis=1)
    r = np.stack([site["sigma_range_m"].to_numpy() ** 2,
                  np.radians(site["sigma_azimuth_deg"].to_numpy()) ** 2, var_el], axis=1)
    return z, r


def _filter(t: NDArray[np.float64], z: NDArray[np.float64], r: NDArray[np.float64],
            starts: NDArray[np.int64], lengths: NDArray[np.int64], cfg: LocalTrackerConfig):
    """Run the three channels over every track.

    Tracks are sorted by decreasing length, so the tracks alive at rank k are a prefix and the
    state arrays are sliced, not gathered. State layout: x (3 comps, 3 channels, tracks) and
    the six unique covariance terms p (6, 3 channels, tracks).
    """
    n, m_tracks = len(t), len(starts)
    model = cfg.range_model
    x = np.zeros((3, 3, m_tracks))
    p = np.zeros((6, 3, m_tracks))
    t_last = np.zeros(m_tracks)
    out_x = np.full((n, 2, 3), np.nan)      # (pos, rate) per channel
    out_p = np.full((n, 3, 3), np.nan)      # (P00, P01, P11) per channel
    res = np.full(n, np.nan)
    res_var = np.full(n, np.nan)
    zt, rt = np.ascontiguousarray(z.T), np.ascontiguousarray(r.T)
    # lengths are sorted descending, so the number of tracks longer than k is a searchsorted
    alive_count = np.searchsorted(-lengths, -np.arange(lengths.max(initial=0)), side="left")
    for k, m in enumerate(alive_count):
        idx = starts[:m] + k
        zk, rk = zt[:, idx], rt[:, idx]
        xs, ps = x[:, :, :m], p[:, :, :m]
        rng_now = np.maximum(np.where(np.isfinite(zk[0]), zk[0], xs[0, 0]), 100.0)
        sig = np.stack([np.full(m, model.sigma_m), cfg.cross_sigma_m / rng_now, cfg.cross_sigma_m / rng_now])
        init_x, init_p = _initial(zk, rk, rng_now, sig, cfg.v0_sigma_mps)
        if k == 0:
            xs[...], ps[...] = init_x, init_p
        else:
            tau = t[idx] - t_last[:m]
            predict_elementwise(xs, ps, tau, model_coefficients(model, tau, sig))
            nu = zk - xs[0]
            nu[1] = np.mod(nu[1] + np.pi, 2 * np.pi) - np.pi   # azimuth wraps
            lost = np.isfinite(nu) & (nu * nu > cfg.reinit_gate * (ps[0] + rk))
            s = update_elementwise(xs, ps, np.where(lost, np.nan, nu), rk)
            xs[...] = np.where(lost, init_x, xs)
            ps[...] = np.where(lost, init_p, ps)
            res[idx], res_var[idx] = nu[0], s[0]
        t_last[:m] = t[idx]
        out_x[idx] = xs[:2].transpose(2, 0, 1)
        out_p[idx] = ps[[0, 1, 3]].transpose(2, 0, 1)
    return out_x, out_p, res, res_var


def _initial(z, r, rng_now, sig, v0_sigma):
    """One-point initiation of every channel: position = plot, rate and acceleration 0 with
    variances (v0/range)² and σ_m² (angular channels scaled by the range)."""
    ok = np.isfinite(z)
    m = z.shape[1]
    x = np.zeros((3,) + z.shape)
    x[0] = np.where(ok, z, 0.0)
    p = np.zeros((6,) + z.shape)
    p[0] = np.where(ok, r, 1e12)
    p[3] = (v0_sigma / np.stack([np.ones(m), rng_now, rng_now])) ** 2
    p[5] = sig ** 2
    return x, p


def model_coefficients(model: SingerModel, tau: NDArray[np.float64], sigma_m: NDArray[np.float64]):
    return singer_coefficients(tau[None, :], model.alpha, sigma_m, model.variant)


def _to_enu(est: NDArray[np.float64], cov: NDArray[np.float64], chunk: int = 32_768):
    """Polar track states (n, channel, (pos, rate)) with per-channel (P00, P01, P11) to
    radar-local ENU position, velocity and flattened 6×6 covariance (n, 36).

    Converted in cache-sized chunks into preallocated outputs: whole-array temporaries of
    n × 36 doubles made this step slow and its timing erratic.
    """
    n = len(est)
    pos, vel, cov36 = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 36))
    ch = np.arange(3)

    def convert(lo: int) -> None:
        sl = slice(lo, min(lo + chunk, n))
        e, c = est[sl], cov[sl]
        cov6 = np.zeros((len(e), 6, 6))
        cov6[:, ch, ch] = c[:, :, 0]
        cov6[:, ch, ch + 3] = cov6[:, ch + 3, ch] = c[:, :, 1]
        cov6[:, ch + 3, ch + 3] = c[:, :, 2]
        p, v, cc = geo.polar_state_to_enu(e[:, 0, 0], np.degrees(e[:, 1, 0]), np.degrees(e[:, 2, 0]),
                                          e[:, 0, 1], np.degrees(e[:, 1, 1]), np.degrees(e[:, 2, 1]), cov=cov6)
        pos[sl], vel[sl], cov36[sl] = p, v, cc.reshape(len(e), 36)

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
    df = df.drop([c for c in ESTIMATE_COLUMNS if c in df.columns]).sort(TRACK_KEY + ["time"], maintain_order=True)
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
    out_x, out_p, res, res_var = _filter(t, z, r, starts[order], lengths[order], cfg)

    est = out_x.transpose(0, 2, 1)          # (n, channel, (pos, rate))
    cov = out_p.transpose(0, 2, 1)          # (n, channel, (P00, P01, P11))
    pos, vel, cov_enu = _to_enu(est, cov)
    el_deg = np.degrees(est[:, 2, 0])
    deg2 = np.degrees(1.0) ** 2
    return df.with_columns(
        pl.Series("est_range_m", est[:, 0, 0]),
        pl.Series("est_range_rate_mps", est[:, 0, 1]),
        pl.Series("est_azimuth_deg", np.mod(np.degrees(est[:, 1, 0]), 360.0)),
        pl.Series("est_elevation_deg", el_deg),
        pl.Series("est_range_var_m2", cov[:, 0, 0]),
        pl.Series("est_azimuth_var_deg2", cov[:, 1, 0] * deg2),
        pl.Series("est_elevation_var_deg2", cov[:, 2, 0] * deg2),
        pl.Series("x_m", pos[:, 0]), pl.Series("y_m", pos[:, 1]), pl.Series("z_m", pos[:, 2]),
        pl.Series("vx_mps", vel[:, 0]), pl.Series("vy_mps", vel[:, 1]), pl.Series("vz_mps", vel[:, 2]),
        pl.Series("est_cov", cov_enu, dtype=pl.Array(pl.Float64, 36)),
        pl.Series("res_range_m", res),
        pl.Series("res_range_var_m2", res_var),
    )
