"""The reference an air picture is scored against when there is no simulator truth: ADS-B, or
a reference reconstructed offline from the radar plots.

ADS-B reference
---------------
:func:`adsb_reference` keeps a fix only when it is usable as a reference:

1. the cleaning of :func:`tertiary.io.adsb.clean_adsb` (null/out-of-band values, on
   ground, duplicate timestamps, stale = re-stamped positions, altitude spikes and position
   jumps by implied speed, too-short flights), then
2. its declared quality, where the recording carries it: ``nacp`` ≥ ``min_nacp``, else ``nucp``
   ≥ ``min_nucp``; ``nic`` ≥ ``min_nic`` when present.

Every fix states its own error: σ per horizontal axis from the 95 % bound the quality declares
(NACp → EPU, NUCp → HFOM), σ = bound95 / √(−2 ln 0.05) = bound95 / 2.448 for a circular Gaussian
radial error (P(ρ ≤ k σ) = 1 − exp(−k²/2))                                             (1)
Without any quality column (OpenSky state vectors) the assumed ``default_epu95_m`` is used and
``quality_declared`` is false. :func:`interpolate_reference` gives the reference at any
(aircraft, time), linearly between two fixes at most ``max_gap_s`` apart; anything else is
``not evaluated`` with the reason, never scored.

Reconstructed reference
-----------------------
:func:`rts_smooth` is a fixed-interval Rauch–Tung–Striebel smoother on a nearly-constant-
velocity (white-acceleration) model per axis, state [x, y, h, vx, vy, vh]:
F = [[1, Δt], [0, 1]], Q = q [[Δt³/3, Δt²/2], [Δt²/2, Δt]]                          (2)
forward Kalman pass, then  C_k = P_k Fᵀ P⁻_{k+1}⁻¹,  x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂⁻_{k+1}),
Pˢ_k = P_k + C_k (Pˢ_{k+1} − P⁻_{k+1}) C_kᵀ                                            (3)
vectorised over aircraft (the loop runs over measurement index only; aircraft are padded to
the longest). Choice: a single CV model with a manoeuvre-sized q (default 1 m²/s³ horizontal,
0.3 vertical) instead of a two-model IMM smoother: it is linear (exact RTS, testable against
filterpy), and with the future in view the smoother's lag through a turn is small; its
covariance is that of the CV model, i.e. optimistic inside turns. :func:`reconstruct_reference`
builds the measurements from radar plots (range, azimuth, and elevation from the Mode C
altitude when replied) and ADS-B reference points, groups them by a key (``truth_id`` in
simulation, else the Mode S address or the picture's target id) and smooths each aircraft.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.sensors import mlat
from tertiary.sensors.adsb import K95_2D, NACP_EPU95_M, REFERENCE_MIN_NACP, REFERENCE_MIN_NIC
from tertiary.core import geo
from tertiary.core.errors import DataError
from tertiary.core.units import FT
from tertiary.io.adsb import AdsbCleaning, clean_adsb, reported_velocity

__all__ = ["ReferenceConfig", "adsb_quality_note", "SmootherConfig", "adsb_reference", "interpolate_reference", "rts_smooth",
           "plot_measurements", "reconstruct_reference", "NACP_EPU95_M", "NUCP_HFOM95_M"]

#: NUCp → horizontal figure of merit, 95 % bound (m) (DO-260, version 0 messages)
NUCP_HFOM95_M = {9: 3.0, 8: 10.0, 7: 92.6, 6: 185.2, 5: 463.0, 4: 926.0, 3: 1852.0, 2: 9260.0, 1: 18520.0}


@dataclass(frozen=True)
class ReferenceConfig:
    """ADS-B reference settings."""

    min_nacp: int = REFERENCE_MIN_NACP  # EPU < 0.05 NM
    min_nucp: int = 7                  # HFOM < 0.05 NM
    min_nic: int = REFERENCE_MIN_NIC
    default_epu95_m: float = 30.0      # assumed without declared quality (NACp 9, typical GNSS)
    sigma_alt_m: float = 25 * FT / np.sqrt(12.0)   # 25 ft barometric quantisation
    max_gap_s: float = 10.0            # interpolate only across gaps up to this
    cleaning: AdsbCleaning = field(default_factory=AdsbCleaning)


# --------------------------------------------------------------------------- ADS-B reference


def _quality(clean: pl.DataFrame, cfg: ReferenceConfig) -> tuple[pl.Expr, pl.Expr, pl.Expr]:
    """(reason or null, 95 % bound (m), declared) expressions from nacp / nucp / nic columns."""
    cols = {c.lower(): c for c in clean.columns}
    reason = pl.lit(None, dtype=pl.String)
    bound = pl.lit(None, dtype=pl.Float64)
    for name, table, lo in (("nucp", NUCP_HFOM95_M, cfg.min_nucp), ("nacp", NACP_EPU95_M, cfg.min_nacp)):
        if name in cols:                                  # NACp wins over NUCp (applied last)
            q = pl.col(cols[name]).cast(pl.Int64)
            b = q.replace_strict(table, default=None, return_dtype=pl.Float64)
            bound = pl.when(q.is_not_null()).then(b).otherwise(bound)
            low = pl.format(f"declared quality below the reference bound ({name.upper()} {{}} < {lo})", q)
            reason = pl.when(q.is_not_null()).then(pl.when((q < lo) | b.is_null()).then(low)).otherwise(reason)
    if "nic" in cols:
        nic = pl.col(cols["nic"]).cast(pl.Int64)
        reason = pl.coalesce(reason, pl.when(nic < cfg.min_nic).then(
            pl.format(f"declared integrity below the reference bound (NIC {{}} < {cfg.min_nic})", nic)))
    declared = bound.is_not_null()
    return reason, pl.coalesce(bound, pl.lit(cfg.default_epu95_m)), declared


def adsb_reference(frame: pl.DataFrame, origin: geo.LocalFrame, cfg: ReferenceConfig = ReferenceConfig()
                   ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(points, removed) from an OpenSky/``traffic`` ADS-B table (optional ``nacp``, ``nucp``,
    ``nic`` columns). ``points``: ``truth_id`` (flight), ``icao24``, ``callsign``, ``time``,
    ``x_m, y_m, z_m`` (system ENU), ``alt_m`` (barometric), reported ``vx_mps, vy_mps,
    alt_rate_mps`` (NaN when not reported), ``sigma_h_m`` (per axis, eq. 1), ``sigma_v_m``,
    ``epu95_m`` and ``quality_declared``. ``removed``: every other input row with ``reason``."""
    clean, removed = clean_adsb(frame, dataclasses.replace(cfg.cleaning, min_nacp=0))   # NACp judged below
    reason, bound, declared = _quality(clean, cfg)
    clean = clean.with_columns(reason.alias("reason"), bound.alias("epu95_m"), declared.alias("quality_declared"))
    bad = clean.filter(pl.col("reason").is_not_null())
    clean = clean.filter(pl.col("reason").is_null()).drop("reason")
    lat, lon = clean["latitude"].to_numpy(), clean["longitude"].to_numpy()
    alt = clean["altitude"].to_numpy() * FT
    x, y, z = origin.from_geodetic(lat, lon, alt)
    vel = reported_velocity(clean, lat, lon, origin)
    points = clean.select(
        pl.col("flight").cast(pl.Int64).alias("truth_id"), "icao24", "callsign", pl.col("timestamp").alias("time"),
        pl.Series("x_m", x), pl.Series("y_m", y), pl.Series("z_m", z), pl.Series("alt_m", alt),
        pl.Series("vx_mps", vel[:, 0]), pl.Series("vy_mps", vel[:, 1]),
        (pl.col("vertical_rate").cast(pl.Float64) * FT / 60.0).fill_null(np.nan).alias("alt_rate_mps"),
        (pl.col("epu95_m") / K95_2D).alias("sigma_h_m"), pl.lit(cfg.sigma_alt_m).alias("sigma_v_m"),
        "epu95_m", "quality_declared")
    removed = pl.concat([removed, bad.drop("flight", "epu95_m", "quality_declared").select(removed.columns)],
                        how="vertical_relaxed")
    return points, removed


def adsb_quality_note(cfg: ReferenceConfig, removed: pl.DataFrame) -> str:
    """The quality filter an ADS-B reference used, in words, with what it dropped."""
    low = removed.filter(pl.col("reason").str.starts_with("declared")).height if "reason" in removed.columns else 0
    return (f"reference: ADS-B points kept when NACp >= {cfg.min_nacp} (else NUCp >= {cfg.min_nucp}) and "
            f"NIC >= {cfg.min_nic}; {low:,} point(s) below that quality and {removed.height - low:,} removed by the "
            f"cleaning are in rejects")


_REF_COLS = ("true_x_m", "true_y_m", "true_z_m", "true_vx_mps", "true_vy_mps", "true_vz_mps", "true_alt_m",
             "true_alt_rate_mps", "ref_sigma_h_m", "ref_gap_s")


def _seconds(s: pl.Series) -> NDArray[np.float64]:
    return s.dt.epoch("us").to_numpy().astype(np.float64) / 1e6


def interpolate_reference(points: pl.DataFrame, requests: pl.DataFrame, max_gap_s: float = 10.0) -> pl.DataFrame:
    """``requests`` (``truth_id``, ``time``, anything else kept) with the reference state
    ``true_x_m, true_y_m, true_z_m, true_vx_mps, true_vy_mps, true_vz_mps, true_alt_m,
    true_alt_rate_mps``, ``ref_sigma_h_m`` and ``status``: ``evaluated`` or ``not evaluated: …``
    (no reference for the aircraft / outside its reference / a gap longer than ``max_gap_s``).

    Position is linear between the two bracketing points; velocity is the points' own
    (interpolated) when they carry one, else the difference quotient of the two points.
    Vectorised: one ``searchsorted`` on (aircraft rank, time) keys."""
    for c in ("truth_id", "time", "x_m", "y_m"):
        if c not in points.columns:
            raise DataError(f"reference points are missing column {c}")
    pts = points.sort("truth_id", "time")
    if not pts.height:                                    # nothing usable: nothing is evaluated
        return requests.with_columns(*[pl.lit(None, dtype=pl.Float64).alias(c) for c in _REF_COLS],
                                     pl.lit("not evaluated: no reference for the aircraft").alias("status"))
    ids = pts["truth_id"].unique(maintain_order=True)
    rank_of = pl.DataFrame({"truth_id": ids, "__rank": np.arange(len(ids), dtype=np.int64)})
    tp = _seconds(pts["time"])
    tq = _seconds(requests["time"])
    t0 = min(tp.min(initial=0.0), tq.min(initial=0.0)) if len(tp) else 0.0
    stride = (max(tp.max(initial=0.0), tq.max(initial=0.0)) - t0) + 4 * max_gap_s + 10.0
    rp = pts.join(rank_of, on="truth_id", how="left")["__rank"].to_numpy()
    rq = requests.select("truth_id").join(rank_of, on="truth_id", how="left", maintain_order="left")["__rank"]
    known = rq.is_not_null().to_numpy()
    rq = rq.fill_null(-1).to_numpy()
    kp, kq = rp * stride + (tp - t0), rq * stride + (tq - t0)
    n = len(kp)
    i = np.clip(np.searchsorted(kp, kq, side="right") - 1, 0, n - 1)
    j = np.clip(i + 1, 0, n - 1)
    exact = known & (rp[i] == rq) & (tp[i] == tq)
    inside = known & (rp[i] == rq) & (kq >= kp[i]) & (j > i) & (rp[j] == rq) & (kq <= kp[j])
    gap = np.where(inside, tp[j] - tp[i], np.nan)
    ok = exact | (inside & (gap <= max_gap_s))
    # for an exact hit at an aircraft's last point, difference with the previous one
    j = np.where(exact & ~inside, i, j)
    i = np.where(exact & ~inside, np.clip(i - 1, 0, None), i)
    same = rp[i] == rp[j]
    dt = np.where(same & (tp[j] > tp[i]), tp[j] - tp[i], np.nan)
    w = np.clip(np.where(np.isfinite(dt), (tq - tp[i]) / dt, 0.0), 0.0, 1.0)
    w = np.where(exact, np.where(tp[j] == tq, 1.0, 0.0), w)
    alt = "alt_m" if "alt_m" in pts.columns else "z_m"
    z = "z_m" if "z_m" in pts.columns else alt
    cols: dict[str, NDArray[np.float64]] = {}
    for name, src in (("x", "x_m"), ("y", "y_m"), ("z", z), ("alt", alt)):
        v = pts[src].to_numpy()
        cols[name] = (1 - w) * v[i] + w * v[j]
        cols[f"d{name}"] = (v[j] - v[i]) / dt
    out: dict[str, NDArray[np.float64]] = {}
    for name, src, diff in (("vx_mps", "vx_mps", "dx"), ("vy_mps", "vy_mps", "dy"), ("vz_mps", "vz_mps", "dz"),
                            ("alt_rate_mps", "alt_rate_mps", "dalt")):
        own = ((1 - w) * pts[src].to_numpy()[i] + w * pts[src].to_numpy()[j]) if src in pts.columns else np.nan
        out[name] = np.where(np.isfinite(own), own, cols[diff])
    sig = pts["sigma_h_m"].to_numpy() if "sigma_h_m" in pts.columns else np.zeros(n)
    sigma = np.maximum(sig[i], sig[j])
    status = np.where(ok, "evaluated", np.where(~known, "not evaluated: no reference for the aircraft",
                      np.where(np.isnan(gap), "not evaluated: outside the aircraft's reference",
                               "not evaluated: reference gap longer than the interpolation limit")))
    nan = np.where(ok, 1.0, np.nan)
    return requests.with_columns(
        pl.Series("true_x_m", cols["x"] * nan), pl.Series("true_y_m", cols["y"] * nan),
        pl.Series("true_z_m", cols["z"] * nan), pl.Series("true_vx_mps", out["vx_mps"] * nan),
        pl.Series("true_vy_mps", out["vy_mps"] * nan), pl.Series("true_vz_mps", out["vz_mps"] * nan),
        pl.Series("true_alt_m", cols["alt"] * nan), pl.Series("true_alt_rate_mps", out["alt_rate_mps"] * nan),
        pl.Series("ref_sigma_h_m", sigma * nan), pl.Series("ref_gap_s", gap), pl.Series("status", status),
    ).with_columns(pl.col(c).fill_nan(None) for c in _REF_COLS)


# --------------------------------------------------------------------------- smoother


@dataclass(frozen=True)
class SmootherConfig:
    """CV process noise (m²/s³) per axis (x, y, height) and the velocity prior (m/s)."""

    q: tuple[float, float, float] = (1.0, 1.0, 0.3)
    v0_sigma_mps: float = 300.0
    p0_sigma_m: float = 1e5            # diffuse position prior: the first measurement sets it
    block: int = 512                   # aircraft per block (memory: block × K × 2 × 36 floats)


def _fq(dt: NDArray[np.float64], q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """F and Q of eq. (2) for a stack of Δt (A,): (A, 6, 6) each; Δt = 0 gives I and 0."""
    a = dt.shape[0]
    f = np.broadcast_to(np.eye(6), (a, 6, 6)).copy()
    qq = np.zeros((a, 6, 6))
    for ax in range(3):
        f[:, ax, ax + 3] = dt
        qq[:, ax, ax] = q[ax] * dt ** 3 / 3
        qq[:, ax, ax + 3] = qq[:, ax + 3, ax] = q[ax] * dt ** 2 / 2
        qq[:, ax + 3, ax + 3] = q[ax] * dt
    return f, qq


def rts_smooth(t: NDArray[np.float64], z: NDArray[np.float64], r: NDArray[np.float64], valid: NDArray[np.bool_],
               cfg: SmootherConfig = SmootherConfig(), x0: NDArray[np.float64] | None = None,
               p0: NDArray[np.float64] | None = None) -> tuple[NDArray[np.float64], ...]:
    """Forward Kalman + RTS backward pass (eqs. 2–3) for A aircraft padded to K measurements.

    ``t`` (A, K) s, ``z`` (A, K, 3) positions [x, y, h], ``r`` (A, K, 3, 3) their covariance,
    ``valid`` (A, K) with every aircraft's measurements first (padding at the end). The prior
    (``x0`` (A, 6), ``p0`` (A, 6, 6)) holds at the first measurement time; default: diffuse
    position, zero velocity with σ ``v0_sigma_mps``. Returns (x_filt, P_filt, x_smooth, P_smooth),
    (A, K, 6) and (A, K, 6, 6); padded entries repeat the last valid one."""
    a, k = valid.shape
    q = np.asarray(cfg.q, float)
    if x0 is None:
        x0 = np.concatenate([np.nan_to_num(z[:, 0]), np.zeros((a, 3))], axis=1)
    if p0 is None:
        p0 = np.broadcast_to(np.diag([cfg.p0_sigma_m ** 2] * 3 + [cfg.v0_sigma_mps ** 2] * 3), (a, 6, 6)).copy()
    xf, pf = np.empty((a, k, 6)), np.empty((a, k, 6, 6))
    xp, pp = np.empty((a, k, 6)), np.empty((a, k, 6, 6))
    x, p = x0.astype(float).copy(), p0.astype(float).copy()
    for i in range(k):                                    # loop over measurement index only
        if i:
            dt = np.where(valid[:, i], t[:, i] - t[:, i - 1], 0.0)
            f, qq = _fq(dt, q)
            x = np.einsum("aij,aj->ai", f, x)
            p = f @ p @ f.transpose(0, 2, 1) + qq
        xp[:, i], pp[:, i] = x, p
        v = valid[:, i]
        s = p[:, :3, :3] + np.where(v[:, None, None], r[:, i], np.eye(3))
        innov = np.where(v[:, None], np.nan_to_num(z[:, i]) - x[:, :3], 0.0)
        gain = np.linalg.solve(s, p[:, :3, :]).transpose(0, 2, 1)           # P Hᵀ S⁻¹ (S symmetric)
        x = x + np.einsum("aij,aj->ai", gain, innov)
        p_new = p - gain @ p[:, :3, :]
        p_new = 0.5 * (p_new + p_new.transpose(0, 2, 1))                   # keep it symmetric
        p = np.where(v[:, None, None], p_new, p)
        xf[:, i], pf[:, i] = x, p
    xs, ps = xf.copy(), pf.copy()
    for i in range(k - 2, -1, -1):
        dt = np.where(valid[:, i + 1], t[:, i + 1] - t[:, i], 0.0)
        f, _ = _fq(dt, q)
        c = np.linalg.solve(pp[:, i + 1], f @ pf[:, i]).transpose(0, 2, 1)  # P Fᵀ P⁻⁻¹
        xs[:, i] = xf[:, i] + np.einsum("aij,aj->ai", c, xs[:, i + 1] - xp[:, i + 1])
        ps[:, i] = pf[:, i] + c @ (ps[:, i + 1] - pp[:, i + 1]) @ c.transpose(0, 2, 1)
    return xf, pf, xs, ps


def plot_measurements(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame, key: str = "truth_id",
                      sigma_alt_m: float = 100 * FT / np.sqrt(12.0) + 10.0, alt_outlier_m: float = 150.0
                      ) -> pl.DataFrame:
    """Radar plots as smoother measurements in the system frame: (x, y) from range, azimuth and
    the elevation implied by the Mode C altitude (measured elevation without it), h = Mode C
    altitude (variance 1e12, i.e. no height update, without it); covariance from the radar's
    nominal σ; an MLAT plot (sensor of kind mlat) is its own Cartesian position and covariance
    (:func:`tertiary.sensors.mlat.system_plots`). A Mode C altitude more than ``alt_outlier_m`` from the median of the aircraft's
    (``key``) five nearest altitudes in time is a garbled code and is not used (neither for h
    nor for the elevation, where 2 km of height error would move a 15 km plot by ~600 m).
    Columns: every input column + ``mx_m, my_m, mh_m, r_cov`` (Array 9), input order kept."""
    if "altitude_m" in reports.columns and key in reports.columns:
        med = (reports.with_row_index("__i").sort(key, "time")
               .with_columns(pl.col("altitude_m").rolling_median(5, min_samples=1, center=True).over(key).alias("__med"))
               .sort("__i")["__med"])
        reports = reports.with_columns(pl.when((pl.col("altitude_m") - med).abs() <= alt_outlier_m)
                                       .then(pl.col("altitude_m")).alias("__alt"))
    n = reports.height
    mx, my, mh = np.empty(n), np.empty(n), np.full(n, np.nan)
    cov = np.zeros((n, 3, 3))
    rid = reports["radar_id"].to_numpy()
    rng, az = reports["range_m"].to_numpy(), reports["azimuth_deg"].to_numpy()
    alt = reports["__alt"].fill_null(np.nan).to_numpy() if "__alt" in reports.columns else np.full(n, np.nan)
    el_meas = reports["elevation_deg"].fill_null(0.0).to_numpy() if "elevation_deg" in reports.columns else np.zeros(n)
    for row in radars.iter_rows(named=True):               # a handful of radars, not per report
        sel = np.flatnonzero(rid == row["radar_id"])
        if not sel.size:
            continue
        site = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
        el = np.where(np.isfinite(alt[sel]), geo.elevation_from_altitude(rng[sel], alt[sel], row["alt_m"]), el_meas[sel])
        p, _, c = geo.frame_to_frame(np.stack(geo.polar_to_enu(rng[sel], az[sel], el), axis=1), site, origin,
                                     cov=geo.polar_sigmas_to_enu_cov(rng[sel], az[sel], el, row["sigma_range_m"],
                                                                     row["sigma_azimuth_deg"], row["sigma_elevation_deg"]))
        mx[sel], my[sel], cov[sel, :2, :2] = p[:, 0], p[:, 1], c[:, :2, :2]
    # an MLAT plot is Cartesian: its own position and covariance, not a polar conversion (MLAT-2)
    z, r, ok = mlat.system_plots(reports, radars, origin, sigma_alt_m)
    cart = mlat.is_mlat(reports, radars) & np.isfinite(r).all(axis=(1, 2))
    mx[ok], my[ok] = z[ok, 0], z[ok, 1]
    cov[cart, :2, :2] = r[cart, :2, :2]
    has_h = np.isfinite(alt)
    mh[has_h] = alt[has_h]
    cov[:, 2, 2] = np.where(has_h, sigma_alt_m ** 2, 1e12)
    return reports.with_columns(pl.Series("mx_m", mx), pl.Series("my_m", my), pl.Series("mh_m", mh),
                                pl.Series("r_cov", cov.reshape(n, 9)).cast(pl.Array(pl.Float64, 9))
                                ).drop("__alt", strict=False)


def adsb_measurements(points: pl.DataFrame) -> pl.DataFrame:
    """ADS-B reference points (:func:`adsb_reference`) as smoother measurements."""
    n = points.height
    cov = np.zeros((n, 3, 3))
    sh, sv = points["sigma_h_m"].to_numpy(), points["sigma_v_m"].to_numpy()
    cov[:, 0, 0] = cov[:, 1, 1] = sh ** 2
    cov[:, 2, 2] = sv ** 2
    return points.with_columns(pl.col("x_m").alias("mx_m"), pl.col("y_m").alias("my_m"), pl.col("alt_m").alias("mh_m"),
                               pl.Series("r_cov", cov.reshape(n, 9)).cast(pl.Array(pl.Float64, 9)))


def reconstruct_reference(meas: pl.DataFrame, key: str = "truth_id", cfg: SmootherConfig = SmootherConfig()
                          ) -> pl.DataFrame:
    """Smoothed reference per aircraft from measurements (``key``, ``time``, ``mx_m, my_m, mh_m,
    r_cov`` from :func:`plot_measurements` / :func:`adsb_measurements`, concatenated). One row
    per measurement: ``truth_id`` (= key), ``time``, smoothed ``x_m, y_m, alt_m, vx_mps,
    vy_mps, alt_rate_mps``, ``cov`` (Array 36, state order [x, y, h, vx, vy, vh]),
    ``sigma_h_m`` (√ of the mean horizontal variance) and the forward (online) pass as
    ``filt_x_m, filt_y_m, filt_alt_m`` for comparison."""
    m = meas.filter(pl.col(key).is_not_null()).sort(key, "time")
    if not m.height:
        raise DataError(f"no measurement with a {key} to reconstruct a reference from")
    keys = m[key].to_numpy()
    start = np.r_[0, np.flatnonzero(keys[1:] != keys[:-1]) + 1]
    group = np.repeat(np.arange(start.size), np.diff(np.r_[start, keys.size]))
    col = np.arange(keys.size) - start[group]
    t = _seconds(m["time"])
    z = m.select("mx_m", "my_m", "mh_m").to_numpy()
    r = m["r_cov"].to_numpy().reshape(-1, 3, 3)
    z[:, 2] = np.nan_to_num(z[:, 2])
    xs_all, ps_all, xf_all = np.empty((keys.size, 6)), np.empty((keys.size, 36)), np.empty((keys.size, 6))
    for lo in range(0, start.size, cfg.block):           # blocks of aircraft bound the memory
        g = (group >= lo) & (group < lo + cfg.block)
        a, c = group[g] - lo, col[g]
        shape = (min(cfg.block, start.size - lo), c.max() + 1)
        tt, zz, rr = np.zeros(shape), np.zeros(shape + (3,)), np.broadcast_to(np.eye(3), shape + (3, 3)).copy()
        valid = np.zeros(shape, bool)
        tt[a, c], zz[a, c], rr[a, c], valid[a, c] = t[g] - t[g].min(), z[g], r[g], True
        xf, _, xs, ps = rts_smooth(tt, zz, rr, valid, cfg)
        xs_all[g], ps_all[g], xf_all[g] = xs[a, c], ps[a, c].reshape(-1, 36), xf[a, c]
    return m.select(pl.col(key).alias("truth_id") if key != "truth_id" else "truth_id", "time").with_columns(
        *[pl.Series(n, xs_all[:, i]) for i, n in enumerate(("x_m", "y_m", "alt_m", "vx_mps", "vy_mps", "alt_rate_mps"))],
        pl.Series("cov", ps_all).cast(pl.Array(pl.Float64, 36)),
        pl.Series("sigma_h_m", np.sqrt(0.5 * (ps_all[:, 0] + ps_all[:, 7]))),
        *[pl.Series(f"filt_{n}", xf_all[:, i]) for i, n in enumerate(("x_m", "y_m", "alt_m"))])
