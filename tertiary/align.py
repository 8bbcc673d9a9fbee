"""Alignment: every report to the system frame and to a common epoch grid (monograph §1.4).

* **Common frame.** Each radar's track estimate (radar-local ENU position, velocity and 6×6
  covariance) is moved into the system frame (ENU at the processing centre) with the exact
  rotation + translation of :func:`tertiary.geo.frame_to_frame`. Reports that arrive as plots
  only get an estimate from the package's own per-radar Singer channels first
  (:func:`tertiary.local_tracks.track_reports`).
* **Common time.** Epochs ``t0 + k·Δ`` (Δ defaults to the fastest scan period). At each epoch a
  local track is represented by its latest report at or before the epoch, extrapolated under
  uniform straight-line motion x(t_c) = x(t_i) + v(t_i)(t_c − t_i) (§1.4), with the covariance
  grown for the interval: F P Fᵀ + Q(Δt), Q the white-noise-acceleration matrix of intensity
  ``q``. A report stays usable for ``max_age_scans`` scan periods of its radar, so slow radars
  contribute at every epoch of their scan.
* **Row accounting.** A report that is superseded by a newer report of the same local track
  before reaching any epoch, or whose estimate is unusable, goes to ``rejects`` with a reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from tertiary import geo
from tertiary.errors import DataError, OptionError, ResourceError
from tertiary.local_tracks import LocalTrackerConfig, track_reports

STATE = ["x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps"]
US = 1_000_000


@dataclass(frozen=True)
class AlignConfig:
    """Epoch grid and extrapolation parameters.

    * ``period_s``: epoch spacing; ``None`` = the fastest radar's scan period.
    * ``max_age_scans``: a report represents its local track at epochs up to this many of its
      radar's scan periods after the report (default 1.5: one missed detection is bridged by
      the next report, a longer silence drops the track from the picture).
    * ``q_m2s3``: white-noise acceleration intensity used to grow the covariance during
      extrapolation (4 m²/s³: σ ≈ 48 m after 12 s).
    * ``max_speed_mps``: a radar track estimate faster than this is physically implausible
      for the aircraft concerned (a diverged local track) and is rejected with that reason.
    * ``max_rows``: refuse (:class:`ResourceError`) an alignment estimated beyond this many
      aligned rows (about ``BYTES_PER_ALIGNED_ROW`` each) instead of allocating it.
    * ``restart_gap_scans``: when plots only arrive, a local track silent for longer than this
      many of its radar's scan periods restarts the package's own filter (radars reuse the
      numbers of deleted tracks: the number then names another track).
    * ``conversion_gate``: the converted-measurement validity gate (seed 002 (13)–(14),
      :func:`conversion_valid`) on each report's measured range and its radar's nominal angle
      sigmas: ``"count"`` only counts the failures (``AlignPlan.conv_valid``), ``"flag"`` also
      adds the boolean column ``conv_valid`` to ``aligned``, ``"reject"`` sends the failing
      reports to ``rejects`` (their J R Jᵀ covariance is not trustworthy).
    * ``identity``: carry the reports' ``mode_3a`` and ``callsign`` into ``aligned`` (as
      strings, null where absent) for fine identification in association.
    """

    period_s: float | None = None
    max_age_scans: float = 1.5
    q_m2s3: float = 4.0
    max_speed_mps: float = 600.0
    max_rows: int = 60_000_000
    local_tracker: LocalTrackerConfig = LocalTrackerConfig()
    restart_gap_scans: float = 4.0
    conversion_gate: Literal["count", "flag", "reject"] = "count"
    identity: bool = False


#: report attributes carried into ``aligned`` with ``AlignConfig.identity``
IDENTITY_COLUMNS = ("mode_3a", "callsign")

#: the linearisation-validity bound of seed 002 (13): r σ_θ²/σ_r < 0.4 and σ_θ < 0.4 rad
VALIDITY_LIMIT = 0.4


def validity_range_limit(sigma_range_m: ArrayLike, sigma_angle_rad: ArrayLike) -> NDArray[np.float64]:
    """Range beyond which the polar → Cartesian linearisation fails, r = 0.4 σ_r/σ_θ² (seed 002
    (14)): 39.39 km for σ_r = 30 m, σ_θ = 1°."""
    return VALIDITY_LIMIT * np.asarray(sigma_range_m, float) / np.asarray(sigma_angle_rad, float) ** 2


def conversion_valid(range_m: ArrayLike, sigma_range_m: ArrayLike, *sigma_angles_rad: ArrayLike
                     ) -> NDArray[np.bool_]:
    """Seed 002 (13) per report: r σ_θ²/σ_r < 0.4 and σ_θ < 0.4 rad for every angle given
    (azimuth and, in 3-D, elevation: the same Taylor argument holds per angle, Lerro &
    Bar-Shalom). A NaN angle sigma (no such measurement) does not fail the gate; a NaN range
    or range sigma does."""
    r = np.asarray(range_m, float)
    sr = np.asarray(sigma_range_m, float)
    ok = np.isfinite(r) & np.isfinite(sr) & (sr > 0)
    for s in sigma_angles_rad:
        s = np.broadcast_to(np.asarray(s, float), r.shape)
        test = (r * s * s / np.where(sr > 0, sr, np.nan) < VALIDITY_LIMIT) & (s < VALIDITY_LIMIT)
        ok &= np.where(np.isfinite(s), test, True)
    return ok


def report_conversion_valid(reports: pl.DataFrame, radars: pl.DataFrame) -> NDArray[np.bool_]:
    """:func:`conversion_valid` of each report (measured ``range_m``; its radar's nominal
    ``sigma_range_m``, ``sigma_azimuth_deg`` and, where the report has an ``elevation_deg``,
    ``sigma_elevation_deg``)."""
    site = reports.select("radar_id").join(
        radars.select("radar_id", "sigma_range_m", "sigma_azimuth_deg", "sigma_elevation_deg"),
        on="radar_id", how="left", maintain_order="left")
    s_el = np.radians(site["sigma_elevation_deg"].cast(pl.Float64).fill_null(np.nan).to_numpy())
    if "elevation_deg" in reports.columns:
        s_el = np.where(reports["elevation_deg"].is_not_null().to_numpy(), s_el, np.nan)
    else:
        s_el = np.full(reports.height, np.nan)
    return conversion_valid(reports["range_m"].cast(pl.Float64).fill_null(np.nan).to_numpy(),
                            site["sigma_range_m"].cast(pl.Float64).fill_null(np.nan).to_numpy(),
                            np.radians(site["sigma_azimuth_deg"].cast(pl.Float64).fill_null(np.nan).to_numpy()),
                            s_el)


def needs_estimates(reports: pl.DataFrame) -> bool:
    """True when the reports lack the radar-track estimate or innovation columns."""
    return any(c not in reports.columns for c in STATE + ["est_cov", "res_range_m", "res_range_var_m2"])


def to_system_frame(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Radar-local estimates to the system frame: state (n, 6), flattened covariance (n, 36)
    and the nominal plot variance per system axis (n, 3) from the radar's nominal sigmas."""
    n = reports.height
    state = np.empty((n, 6))
    cov = np.empty((n, 36))
    nominal = np.empty((n, 3))
    rid = reports["radar_id"].to_numpy()
    local_state = reports.select(STATE).to_numpy()
    local_cov = reports["est_cov"].to_numpy().reshape(n, 6, 6)
    el = reports["est_elevation_deg"].to_numpy() if "est_elevation_deg" in reports.columns else np.zeros(n)
    for row in radars.iter_rows(named=True):          # loop over radars (a handful), not reports
        sel = np.flatnonzero(rid == row["radar_id"])
        if sel.size == 0:
            continue
        site = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
        p, v, c = geo.frame_to_frame(local_state[sel, :3], site, origin, vel=local_state[sel, 3:], cov=local_cov[sel])
        state[sel, :3], state[sel, 3:], cov[sel] = p, v, c.reshape(-1, 36)
        rng = reports["range_m"].to_numpy()[sel]
        az = reports["azimuth_deg"].to_numpy()[sel]
        nom = geo.polar_sigmas_to_enu_cov(rng, az, np.nan_to_num(el[sel]), row["sigma_range_m"],
                                          row["sigma_azimuth_deg"], row["sigma_elevation_deg"])
        rot = site.rotation_to(origin)
        nominal[sel] = np.einsum("ij,njk,ik->ni", rot, nom, rot)
    return state, cov, nominal


def extrapolate(state: NDArray[np.float64], cov36: NDArray[np.float64], dt: NDArray[np.float64], q: float,
                rows: NDArray[np.int64] | None = None, chunk: int = 16_384
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Uniform straight-line motion over ``dt`` (m,): x ← F x, P ← F P Fᵀ + Q(dt) with
    F = [[I, dt I], [0, I]] and the white-noise-acceleration Q = q [[dt³/3, dt²/2], [dt²/2, dt]].

    ``cov36`` is the row-major flattened 6×6 covariance. With ``rows`` the inputs are
    ``state[rows]``/``cov36[rows]``, gathered block by block. Blocks of ``chunk`` rows keep
    the entry-by-entry arithmetic in cache; whole-array transposes or gathers of n × 36
    doubles were the slowest part of alignment.
    """
    m = len(dt)
    out_x, out_p = np.empty((m, 6)), np.empty((m, 36))
    for lo in range(0, m, chunk):
        sl = slice(lo, min(lo + chunk, m))
        src = sl if rows is None else rows[sl]
        x, p, d = state[src], cov36[src], dt[sl]
        out_x[sl, :3] = x[:, :3] + d[:, None] * x[:, 3:]
        out_x[sl, 3:] = x[:, 3:]
        g = out_p[sl]
        g[...] = p
        d2, qd3, qd2, qd = d * d, q * d ** 3 / 3.0, q * d * d / 2.0, q * d
        for i in range(3):
            for j in range(3):
                pp, pv, vp, vv = 6 * i + j, 6 * i + j + 3, 6 * (i + 3) + j, 6 * (i + 3) + j + 3
                g[:, pp] += d * (p[:, pv] + p[:, vp]) + d2 * p[:, vv]
                g[:, pv] += d * p[:, vv]
                g[:, vp] += d * p[:, vv]
            g[:, 7 * i] += qd3                   # diagonal of the pos-pos block
            g[:, 6 * i + i + 3] += qd2           # pos-vel diagonal
            g[:, 6 * (i + 3) + i] += qd2         # vel-pos diagonal
            g[:, 7 * (i + 3)] += qd              # vel-vel diagonal
    return out_x, out_p


def epoch_grid(reports: pl.DataFrame, radars: pl.DataFrame, cfg: AlignConfig) -> tuple[int, float]:
    """Grid origin (µs since the Unix epoch, whole second) and period (s).

    Raises :class:`DataError` when there is no report or no scan period to build it from."""
    period = cfg.period_s if cfg.period_s is not None else radars["scan_period_s"].min()
    if period is None or not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
        if cfg.period_s is not None:
            raise OptionError(f"epoch period must be finite and positive, got {period}", option="align.period_s")
        raise DataError(f"radars: no valid scan_period_s to build the epoch grid from (got {period})")
    t_min = reports["time"].dt.epoch("us").min() if reports.height else None
    if t_min is None:
        raise DataError("align: no report to build the epoch grid from")
    return (int(t_min) // US) * US, float(period)


def estimates_by_track_life(reports: pl.DataFrame, radars: pl.DataFrame, cfg: AlignConfig = AlignConfig()
                            ) -> pl.DataFrame:
    """:func:`tertiary.local_tracks.track_reports` with each local track split where it falls
    silent for more than ``cfg.restart_gap_scans`` scan periods (a reused track number): each
    life is filtered from its own first plot, the radar's numbers are kept."""
    df = reports if "run" in reports.columns else reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    key = ["run", "radar_id", "local_track_id"]
    df = df.sort(key + ["time"], maintain_order=True)
    period = df.select("radar_id").join(radars.select("radar_id", "scan_period_s"), on="radar_id", how="left",
                                        maintain_order="left")["scan_period_s"].fill_null(np.inf)
    gap = df.select(pl.col("time").diff().over(key).dt.total_microseconds() * 1e-6).to_series()
    new = (gap.is_null() | (gap > cfg.restart_gap_scans * period)).to_numpy()
    life = pl.Series("local_track_id", np.cumsum(new), dtype=pl.UInt32)
    out = track_reports(df.rename({"local_track_id": "__number"}).with_columns(life), radars, cfg.local_tracker)
    return out.with_columns(pl.col("__number").alias("local_track_id")).drop("__number").select(
        [c for c in df.columns] + [c for c in out.columns if c not in df.columns and c != "__number"])


@dataclass
class AlignPlan:
    """Which reports align to which epochs, before any aligned row is built.

    ``df`` is the reports sorted by (run, radar, local track, time) with estimates; per row of
    ``df``: ``k`` first and ``last_k`` last epoch index, ``keep`` (else ``rejects`` says why),
    the system-frame ``state``/``cov``/``nominal``; ``rows`` = number of aligned rows.
    """

    df: pl.DataFrame
    t0_us: int
    period: float
    rel: NDArray[np.float64]
    k: NDArray[np.int64]
    last_k: NDArray[np.int64]
    keep: NDArray[np.bool_]
    state: NDArray[np.float64]
    cov: NDArray[np.float64]
    nominal: NDArray[np.float64]
    rejects: pl.DataFrame
    rows: int
    #: seed 002 (13) validity of each ``df`` row's polar → Cartesian conversion (AlignConfig.conversion_gate)
    conv_valid: NDArray[np.bool_] | None = None

    @property
    def conversion_invalid(self) -> int:
        """Reports failing the converted-measurement validity gate."""
        return 0 if self.conv_valid is None else int(np.count_nonzero(~self.conv_valid))


#: bytes held per aligned row (state, 6×6 covariance, nominal variance, keys, extrapolation
#: temporaries) for the memory estimate of :func:`plan`
BYTES_PER_ALIGNED_ROW = 8 * (6 + 36 + 3 + 14) * 2


def _epoch_index(x: NDArray[np.float64], what: str) -> NDArray[np.int64]:
    """Float epoch indices to int64, refusing values an int64 cannot hold."""
    if x.size and not np.all(np.abs(x) < 2.0 ** 62):
        raise ResourceError(f"align: {what} epoch index beyond 2^62 (epoch period too small for the time span)")
    return x.astype(np.int64)


def plan(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
         cfg: AlignConfig = AlignConfig()) -> AlignPlan:
    """The alignment's decisions (epochs per report and every rejection with its reason).

    Estimates the aligned rows before anything is allocated and raises
    :class:`ResourceError` beyond ``cfg.max_rows``."""
    if needs_estimates(reports):
        reports = estimates_by_track_life(reports, radars, cfg)
    if "run" not in reports.columns:
        reports = reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    df = reports.sort(["run", "radar_id", "local_track_id", "time"], maintain_order=True)
    t0_us, period = epoch_grid(df, radars, cfg)
    t_us = df["time"].dt.epoch("us").to_numpy()
    rel = (t_us - t0_us) / US
    # a report is usable from the time it has been collected and processed (§1.4 queue,
    # :mod:`tertiary.collection`): its first epoch is at or after time + delay; its state is
    # still extrapolated from its own time
    avail = rel + (df["collection_delay_s"].fill_null(0.0).to_numpy() if "collection_delay_s" in df.columns else 0.0)
    k = _epoch_index(np.ceil(avail / period - 1e-9), "first")      # first epoch at or after availability

    state, cov, nominal = to_system_frame(df, radars, origin)
    finite = np.isfinite(state).all(axis=1) & np.isfinite(cov).all(axis=1)
    plausible = np.linalg.norm(np.nan_to_num(state[:, 3:]), axis=1) <= cfg.max_speed_mps
    conv_ok = report_conversion_valid(df, radars)
    usable = finite & plausible & (conv_ok | (cfg.conversion_gate != "reject"))

    keys = df.select("run", "radar_id", "local_track_id").to_numpy()
    same_next = np.zeros(len(df), bool)
    same_next[:-1] = np.all(keys[1:] == keys[:-1], axis=1)
    k_next = np.append(k[1:], np.iinfo(np.int64).max)
    superseded = same_next & (k_next == k)
    scan = df.select("radar_id").join(radars.select("radar_id", "scan_period_s"), on="radar_id",
                                      how="left", maintain_order="left")["scan_period_s"].to_numpy()
    last_k = _epoch_index(np.floor((rel + cfg.max_age_scans * scan) / period + 1e-9), "last")
    last_k = np.where(same_next, np.minimum(last_k, k_next - 1), last_k)
    keep = usable & ~superseded & (last_k >= k)
    n_rows = int(np.sum((last_k - k + 1)[keep], dtype=np.float64))
    if n_rows > cfg.max_rows:
        raise ResourceError(
            f"align: {n_rows:,} aligned rows (~{n_rows * BYTES_PER_ALIGNED_ROW / 1e9:.1f} GB) exceed the limit of "
            f"{cfg.max_rows:,} (AlignConfig.max_rows): epochs every {period:g} s with reports kept for "
            f"{cfg.max_age_scans:g} scans of up to {np.nanmax(scan):g} s; set a larger AlignConfig.period_s")

    reason = np.where(~finite, "no usable track estimate (non-finite state or covariance)",
                      np.where(~plausible, f"implausible track speed (> {cfg.max_speed_mps:g} m/s)",
                      np.where(~usable, "polar conversion invalid (seed 002 (13): r sigma_az^2/sigma_r >= 0.4 "
                                        "or sigma >= 0.4 rad)",
                      np.where(superseded, "superseded by a newer report of the same local track before the next epoch",
                               "track estimate too old for any epoch"))))
    rejects = df.filter(pl.Series(~keep)).select("report_id").with_columns(
        pl.Series("reason", reason[~keep], dtype=pl.String))
    return AlignPlan(df, t0_us, period, rel, k, last_k, keep, state, cov, nominal, rejects, n_rows, conv_ok)


_ALIGNED_COLUMNS = ["report_id", "run", "radar_id", "local_track_id", "epoch", "time", *STATE, "cov",
                    "res_range_m", "res_range_var_m2", "mode_s", "truth_id", "age_s", "fresh", "nominal_var",
                    "altitude_m"]


def empty_aligned() -> pl.DataFrame:
    """An aligned frame with no rows (every report rejected)."""
    t = pl.Datetime("us", "UTC")
    return pl.DataFrame(schema={
        "report_id": pl.UInt64, "run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
        "epoch": t, "time": t, **dict.fromkeys(STATE, pl.Float64), "cov": pl.Array(pl.Float64, 36),
        "res_range_m": pl.Float64, "res_range_var_m2": pl.Float64, "mode_s": pl.String, "truth_id": pl.Int64,
        "age_s": pl.Float64, "fresh": pl.Boolean, "nominal_var": pl.Array(pl.Float64, 3),
        "altitude_m": pl.Float64})


def expand(p: AlignPlan, cfg: AlignConfig = AlignConfig()) -> pl.DataFrame:
    """The aligned rows of a plan: each kept report at each of its epochs, extrapolated."""
    idx = np.flatnonzero(p.keep)
    if idx.size == 0:
        return empty_aligned()
    df, k = p.df, p.k
    keys = df.select("run", "radar_id", "local_track_id").to_numpy()
    counts = (p.last_k - k + 1)[idx]
    rows = np.repeat(idx, counts)
    step = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    epoch_k = k[rows] + step
    # output order (run, epoch, radar, local track) computed on integer keys, not by a frame sort
    order = np.lexsort((keys[rows, 2], keys[rows, 1], epoch_k, keys[rows, 0]))
    rows, step, epoch_k = rows[order], step[order], epoch_k[order]
    age = epoch_k * p.period - p.rel[rows]
    x, cov = extrapolate(p.state, p.cov, age, cfg.q_m2s3, rows=rows)

    base = ["report_id", "run", "radar_id", "local_track_id", "time", "res_range_m", "res_range_var_m2"]
    opt = [c for c in ("mode_s", "truth_id", "altitude_m") if c in df.columns]
    aligned = df.select(base + opt)[rows].with_columns(
        pl.Series("epoch", p.t0_us + np.round(epoch_k * p.period * US).astype(np.int64)).cast(pl.Datetime("us", "UTC")),
        *(pl.Series(name, x[:, i]) for i, name in enumerate(STATE)),
        pl.Series("cov", cov, dtype=pl.Array(pl.Float64, 36)),
        pl.Series("age_s", age),
        pl.Series("fresh", step == 0),
        pl.Series("nominal_var", p.nominal[rows], dtype=pl.Array(pl.Float64, 3)),
        pl.col("res_range_m").fill_null(np.nan), pl.col("res_range_var_m2").fill_null(np.nan),
    )
    if "mode_s" not in aligned.columns:
        aligned = aligned.with_columns(pl.lit(None, pl.String).alias("mode_s"))
    if "truth_id" not in aligned.columns:
        aligned = aligned.with_columns(pl.lit(None, pl.Int64).alias("truth_id"))
    if "altitude_m" not in aligned.columns:
        aligned = aligned.with_columns(pl.lit(None, pl.Float64).alias("altitude_m"))
    extra = []
    if cfg.conversion_gate == "flag" and p.conv_valid is not None:
        extra.append(pl.Series("conv_valid", p.conv_valid[rows]))
    if cfg.identity:             # fine identification (tertiary.associate): the report's code and callsign
        extra.extend(df[c].cast(pl.String)[rows] if c in df.columns else pl.Series(c, [None] * len(rows), pl.String)
                     for c in IDENTITY_COLUMNS)
    return aligned.select(_ALIGNED_COLUMNS).with_columns(extra) if extra else aligned.select(_ALIGNED_COLUMNS)


def align(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
          cfg: AlignConfig = AlignConfig()) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Align valid reports; returns (aligned, rejects).

    ``aligned`` has one row per (report, epoch at which it represents its local track), with
    ``age_s`` = epoch − report time, ``fresh`` = first epoch of the report, the system-frame
    state/covariance, the radar's range innovation, ``nominal_var`` (a-priori plot variance
    per system axis) and ``altitude_m``: the report's own barometric (Mode C/S) altitude as
    replied, null without one — not extrapolated; with ``time`` it feeds the vertical channel
    (:mod:`tertiary.altitude`). ``rejects`` rows carry report_id and reason. No report: both empty.
    """
    if reports.height == 0:
        return empty_aligned(), pl.DataFrame(schema={"report_id": pl.UInt64, "reason": pl.String})
    p = plan(reports, radars, origin, cfg)
    return expand(p, cfg), p.rejects


# --------------------------------------------------------------------------- registration


#: registration columns applied by :func:`apply_registration` (see :mod:`tertiary.registration`)
REGISTRATION_COLUMNS = ["radar_id", "range_bias_m", "azimuth_bias_deg", "time_offset_s"]


def apply_registration(reports: pl.DataFrame, table: pl.DataFrame) -> pl.DataFrame:
    """Reports with each radar's systematic errors removed (the inverse of the registration
    model (R1)–(R2) of :mod:`tertiary.registration`; radars absent from ``table`` unchanged):

    * time stamp t ← t̃ − δ_r; plots ρ ← (ρ̃ − b_r)/(1 + g_r), β ← β̃ − a_r (also ``est_range_m``,
      ``est_azimuth_deg``);
    * the radar-local track state: position and velocity turned by −a_r about the site's
      vertical, the position scaled along the line of sight to the corrected range (elevation
      kept), the velocity by 1/(1 + g_r); the 6×6 covariance turned with them (the range
      scaling, |b/ρ| < 10⁻³, is left out of the covariance).

    ``table`` needs ``radar_id``, ``range_bias_m``, ``azimuth_bias_deg``, ``time_offset_s``
    (optional ``range_gain``, NaN/absent = 0); a missing column is a :class:`DataError`."""
    missing = [c for c in REGISTRATION_COLUMNS if c not in table.columns]
    if missing:
        raise DataError(f"registration table: column(s) {', '.join(missing)} missing")
    if reports.height == 0 or table.height == 0:
        return reports
    gain = pl.col("range_gain").fill_nan(0.0).fill_null(0.0) if "range_gain" in table.columns else pl.lit(0.0)
    values = [c.cast(pl.Float64).fill_nan(0.0).fill_null(0.0).alias(name) for c, name in (
        (pl.col("range_bias_m"), "__b"), (pl.col("azimuth_bias_deg"), "__a"), (pl.col("time_offset_s"), "__d"),
        (gain, "__g"))]
    corr = table.select(pl.col("radar_id").cast(reports.schema["radar_id"]), *values)
    df = reports.join(corr, on="radar_id", how="left", maintain_order="left").with_columns(
        pl.col("__b", "__a", "__d", "__g").fill_null(0.0))
    b, a, g = (df[c].to_numpy() for c in ("__b", "__a", "__g"))
    fixes = [(pl.col("time") - pl.duration(microseconds=(pl.col("__d") * US).round(0).cast(pl.Int64))).alias("time"),
             ((pl.col("range_m") - pl.col("__b")) / (1.0 + pl.col("__g"))).alias("range_m"),
             ((pl.col("azimuth_deg") - pl.col("__a")) % 360.0).alias("azimuth_deg")]
    if "est_range_m" in df.columns:
        fixes.append(((pl.col("est_range_m") - pl.col("__b")) / (1.0 + pl.col("__g"))).alias("est_range_m"))
    if "est_azimuth_deg" in df.columns:
        fixes.append(((pl.col("est_azimuth_deg") - pl.col("__a")) % 360.0).alias("est_azimuth_deg"))
    if all(c in df.columns for c in STATE):
        fixes.extend(_registered_state(df, b, a, g))
    return df.with_columns(fixes).drop("__b", "__a", "__d", "__g").select(reports.columns)


def _registered_state(df: pl.DataFrame, b: NDArray[np.float64], a_deg: NDArray[np.float64],
                      g: NDArray[np.float64]) -> list[pl.Series]:
    """Corrected local state columns (and ``est_cov``) of :func:`apply_registration`."""
    x = df.select(STATE).to_numpy().astype(float)
    ca, sa = np.cos(np.radians(a_deg)), np.sin(np.radians(a_deg))
    rot = np.zeros((len(x), 3, 3))                 # azimuth (clockwise from north) decreased by a
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = ca, -sa, sa, ca, 1.0
    p = np.einsum("nij,nj->ni", rot, x[:, :3])
    v = np.einsum("nij,nj->ni", rot, x[:, 3:]) / (1.0 + g)[:, None]
    rho = np.linalg.norm(p, axis=1)
    scale = np.where(rho > 0, (rho - b) / (1.0 + g) / np.where(rho > 0, rho, 1.0), 1.0)
    p *= scale[:, None]
    out = [pl.Series(name, col) for name, col in zip(STATE, np.hstack([p, v]).T)]
    if "est_cov" in df.columns:
        cov = df["est_cov"].to_numpy().reshape(-1, 6, 6)
        m = np.zeros((len(x), 6, 6))
        m[:, :3, :3], m[:, 3:, 3:] = rot, rot
        out.append(pl.Series("est_cov", np.einsum("nij,njk,nlk->nil", m, cov, m).reshape(-1, 36),
                             dtype=df.schema["est_cov"]))
    return out
