"""Alignment: every report to the system frame and to a common epoch grid (monograph §1.4).

* **Common frame.** Each radar's track estimate (radar-local ENU position, velocity and 6×6
  covariance) is moved into the system frame (ENU at the processing centre) with the exact
  rotation + translation of :func:`tertiary.core.geo.frame_to_frame`. Reports that arrive as plots
  only get an estimate from the package's own per-radar Singer channels first
  (:func:`tertiary.sensors.local_tracks.track_reports`). An MLAT / WAM report (a sensor of kind
  ``mlat``) is a Cartesian plot: its a-priori variance is its own plot covariance moved to the
  system frame ((MLAT-1)–(MLAT-2), :mod:`tertiary.sensors.mlat`), and no polar validity gate applies.
* **Common time.** Epochs ``t0 + k·Δ`` (Δ defaults to the fastest scan period). At each epoch a
  local track is represented by its latest report at or before the epoch, extrapolated under
  uniform straight-line motion x(t_c) = x(t_i) + v(t_i)(t_c − t_i) (§1.4), with the covariance
  grown for the interval: F P Fᵀ + Q(Δt), Q the white-noise-acceleration matrix of intensity
  ``q``. A report stays usable for ``max_age_scans`` scan periods of its radar, so slow radars
  contribute at every epoch of their scan.
* **Row accounting.** A report that is superseded by a newer report of the same local track
  before reaching any epoch, or whose estimate is unusable, goes to ``rejects`` with a reason.
* **Windows.** :func:`align_step` aligns a run window by window (each report handed to the
  window holding its time, no margins): the reports that still give rows at later epochs, or
  whose fate waits for the next report of their local track, and the local tracker's filters
  are carried in :class:`AlignState`; the concatenated outputs equal :func:`align`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from tertiary.core import geo
from tertiary.sensors import adsb, local_tracks, mlat
from tertiary.core.errors import DataError, OptionError, ResourceError
from tertiary.core.units import STATE, US
from tertiary.sensors.local_tracks import LocalTrackerConfig, track_reports


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
    * ``adsb_quality``: the minimum declared quality (NACp, NIC, SIL) of an ADS-B report that is fused;
      a report below it goes to ``rejects`` naming the indicator (:mod:`tertiary.sensors.adsb`).
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
    adsb_quality: adsb.AdsbQuality = adsb.AdsbQuality()


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
    ``sigma_elevation_deg``). An MLAT report (:mod:`tertiary.sensors.mlat`) is a Cartesian plot: no
    polar conversion, always valid."""
    site = reports.select("radar_id").join(
        radars.select("radar_id", "sigma_range_m", "sigma_azimuth_deg", "sigma_elevation_deg"),
        on="radar_id", how="left", maintain_order="left")
    s_el = np.radians(site["sigma_elevation_deg"].cast(pl.Float64).fill_null(np.nan).to_numpy())
    if "elevation_deg" in reports.columns:
        s_el = np.where(reports["elevation_deg"].is_not_null().to_numpy(), s_el, np.nan)
    else:
        s_el = np.full(reports.height, np.nan)
    valid = conversion_valid(reports["range_m"].cast(pl.Float64).fill_null(np.nan).to_numpy(),
                             site["sigma_range_m"].cast(pl.Float64).fill_null(np.nan).to_numpy(),
                             np.radians(site["sigma_azimuth_deg"].cast(pl.Float64).fill_null(np.nan).to_numpy()),
                             s_el)
    return valid | mlat.is_mlat(reports, radars)


def needs_estimates(reports: pl.DataFrame) -> bool:
    """True when the reports lack the radar-track estimate or innovation columns."""
    return any(c not in reports.columns for c in [*STATE, "est_cov", "res_range_m", "res_range_var_m2"])


def to_system_frame(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
                    altitude_sigma_m: float = LocalTrackerConfig.altitude_sigma_m
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Radar-local estimates to the system frame: state (n, 6), flattened covariance (n, 36)
    and the nominal plot variance per system axis (n, 3): from the radar's nominal sigmas, for
    an MLAT report the diagonal of its own plot covariance (MLAT-2) (:mod:`tertiary.sensors.mlat`;
    height from Mode C with ``altitude_sigma_m``)."""
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
    cart = mlat.is_mlat(reports, radars)
    if cart.any():
        _, r, _ = mlat.system_plots(reports.filter(pl.Series(cart)), radars, origin, altitude_sigma_m)
        nominal[cart] = np.diagonal(r, axis1=1, axis2=2)
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


def epoch_period(radars: pl.DataFrame, cfg: AlignConfig) -> float:
    """Epoch spacing (s): ``cfg.period_s``, else the fastest radar's scan period.

    Raises :class:`OptionError`/:class:`DataError` when it is not finite and positive."""
    period = cfg.period_s if cfg.period_s is not None else radars["scan_period_s"].min()
    if period is None or not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
        if cfg.period_s is not None:
            raise OptionError(f"epoch period must be finite and positive, got {period}", option="align.period_s")
        raise DataError(f"radars: no valid scan_period_s to build the epoch grid from (got {period})")
    return float(period)


def grid_origin_us(t_min_us: int) -> int:
    """The default grid origin: the earliest report time floored to the whole second (µs)."""
    return (int(t_min_us) // US) * US


def epoch_grid(reports: pl.DataFrame, radars: pl.DataFrame, cfg: AlignConfig,
               origin_us: int | None = None) -> tuple[int, float]:
    """Grid origin (µs since the Unix epoch) and period (s). The origin is ``origin_us`` when
    given (a windowed run passes the whole dataset's), else :func:`grid_origin_us` of the
    earliest report.

    Raises :class:`DataError` when there is no report or no scan period to build it from."""
    period = epoch_period(radars, cfg)
    if origin_us is not None:
        return int(origin_us), period
    t_min = reports["time"].dt.epoch("us").min() if reports.height else None
    if t_min is None:
        raise DataError("align: no report to build the epoch grid from")
    return grid_origin_us(int(t_min)), period


def estimates_by_track_life(reports: pl.DataFrame, radars: pl.DataFrame, cfg: AlignConfig = AlignConfig()
                            ) -> pl.DataFrame:
    """:func:`tertiary.sensors.local_tracks.track_reports` with each local track split where it falls
    silent for more than ``cfg.restart_gap_scans`` scan periods (a reused track number): each
    life is filtered from its own first plot, the radar's numbers are kept."""
    return _estimates(reports, radars, cfg, None)[0]


def _restart_gap_s(df: pl.DataFrame, radars: pl.DataFrame, cfg: AlignConfig) -> NDArray[np.float64]:
    """Per row of ``df``: the silence (s) after which its local track restarts (inf: radar unknown)."""
    scan = df.select("radar_id").join(radars.select("radar_id", "scan_period_s"), on="radar_id", how="left",
                                      maintain_order="left")["scan_period_s"].fill_null(np.inf).to_numpy()
    return cfg.restart_gap_scans * scan


def _estimates(reports: pl.DataFrame, radars: pl.DataFrame, cfg: AlignConfig, carry: pl.DataFrame | None
               ) -> tuple[pl.DataFrame, pl.DataFrame | None]:
    """:func:`estimates_by_track_life`; with ``carry`` (a windowed run: the local-tracker carry
    keyed by the radar's numbers) a track's first report here continues its carried life unless
    it comes more than the restart gap after the carried report. Returns the carry after these
    reports (None without one)."""
    df = reports if "run" in reports.columns else reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    key = ["run", "radar_id", "local_track_id"]
    df = df.sort(key + ["time"], maintain_order=True)
    n = df.height
    t_us = df["time"].dt.epoch("us").to_numpy()
    keys = df.select(pl.col(key).cast(pl.Int64)).to_numpy()
    thr = _restart_gap_s(df, radars, cfg)
    first = np.ones(n, bool)
    first[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    gap_s = np.diff(t_us, prepend=t_us[:1]) * 1e-6
    new = first | (gap_s > thr)
    life = pl.Series("local_track_id", np.cumsum(new), dtype=pl.UInt32)
    lives = df.rename({"local_track_id": "__number"}).with_columns(life)
    if carry is None:
        out, lc = track_reports(lives, radars, cfg.local_tracker), None
    else:
        out, lc = _continue_lives(lives, carry, t_us, first, thr, radars, cfg)
    out = out.with_columns(pl.col("__number").alias("local_track_id")).drop("__number").select(
        [c for c in df.columns] + [c for c in out.columns if c not in df.columns and c != "__number"])
    return out, lc


def _continue_lives(lives: pl.DataFrame, carry: pl.DataFrame, t_us: NDArray[np.int64], first: NDArray[np.bool_],
                    thr: NDArray[np.float64], radars: pl.DataFrame, cfg: AlignConfig
                    ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Run the local tracker on ``lives`` (local_track_id = life number, ``__number`` = the
    radar's) continuing the carried lives, and return the carry keyed by the radar's numbers."""
    key = ["run", "radar_id", "local_track_id"]
    heads = lives.filter(pl.Series(first)).select("run", "radar_id", "__number", "local_track_id").with_columns(
        pl.Series("__t", t_us[first]), pl.Series("__thr", thr[first]))
    cont = heads.join(carry.rename({"local_track_id": "__number"}), on=["run", "radar_id", "__number"],
                      how="inner").filter((pl.col("__t") - pl.col("t_us")) * 1e-6 <= pl.col("__thr"))
    prior = cont.select(local_tracks.CARRY_SCHEMA.keys()).cast(local_tracks.CARRY_SCHEMA)
    out, lc = local_tracks.track_reports_step(prior, lives, radars, cfg.local_tracker)
    numbers = lives.select(*key, "__number").unique(key)
    latest = (lc.join(numbers, on=key, how="inner")
              .sort("local_track_id").group_by(["run", "radar_id", "__number"], maintain_order=True).last()
              .drop("local_track_id").rename({"__number": "local_track_id"}).select(local_tracks.CARRY_SCHEMA.keys())
              .cast(local_tracks.CARRY_SCHEMA))
    kept = carry.cast(local_tracks.CARRY_SCHEMA).join(latest.select(key), on=key, how="anti")
    return out, pl.concat([kept, latest]).sort(key)


@dataclass
class AlignPlan:
    """Which reports align to which epochs, before any aligned row is built.

    ``df`` is the reports sorted by (run, radar, local track, time) with estimates; per row of
    ``df``: ``k`` first and ``last_k`` last epoch index, ``keep`` (else ``rejects`` says why),
    the system-frame ``state``/``cov``/``nominal``; ``rows`` = number of aligned rows.
    In a windowed step also ``has_next``/``k_next`` (the next report of the same local track
    is known, its first epoch) and ``pending`` (decision waits for the next report).
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
    has_next: NDArray[np.bool_] | None = None
    k_next: NDArray[np.int64] | None = None
    pending: NDArray[np.bool_] | None = None

    @property
    def conversion_invalid(self) -> int:
        """Reports failing the converted-measurement validity gate."""
        return 0 if self.conv_valid is None else int(np.count_nonzero(~self.conv_valid))


#: bytes held per aligned row (state, 6×6 covariance, nominal variance, keys, extrapolation
#: temporaries) for the memory estimate of :func:`plan`
BYTES_PER_ALIGNED_ROW = 8 * (6 + 36 + 3 + 14) * 2
#: "no next report known" in epoch-index arrays
_NO_K = np.iinfo(np.int64).max


def _epoch_index(x: NDArray[np.float64], what: str) -> NDArray[np.int64]:
    """Float epoch indices to int64, refusing values an int64 cannot hold."""
    if x.size and not np.all(np.abs(x) < 2.0 ** 62):
        raise ResourceError(f"align: {what} epoch index beyond 2^62 (epoch period too small for the time span)")
    return x.astype(np.int64)


def _first_epoch(t_us: NDArray[np.int64] | int, delay_s: NDArray[np.float64] | float, t0_us: int, period: float
                 ) -> NDArray[np.int64]:
    """First epoch index at or after a report's availability (time + collection delay)."""
    rel = (np.asarray(t_us, np.int64) - t0_us) / US
    return _epoch_index(np.atleast_1d(np.ceil((rel + delay_s) / period - 1e-9)), "first")


def plan(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
         cfg: AlignConfig = AlignConfig(), grid_origin_us: int | None = None) -> AlignPlan:
    """The alignment's decisions (epochs per report and every rejection with its reason).
    The epoch grid starts at ``grid_origin_us`` (default: the earliest report, floored to the
    second; :func:`epoch_grid`).

    Estimates the aligned rows before anything is allocated and raises
    :class:`ResourceError` beyond ``cfg.max_rows``."""
    if needs_estimates(reports):
        reports = estimates_by_track_life(reports, radars, cfg)
    if "run" not in reports.columns:
        reports = reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    df = reports.sort(["run", "radar_id", "local_track_id", "time"], maintain_order=True)
    t0_us, period = epoch_grid(df, radars, cfg, grid_origin_us)
    p = _plan_frame(df, radars, origin, cfg, t0_us, period)
    _check_rows(p.rows, period, radars, cfg)
    return p


def _check_rows(n_rows: int, period: float, radars: pl.DataFrame, cfg: AlignConfig) -> None:
    """:class:`ResourceError` when ``n_rows`` aligned rows exceed ``cfg.max_rows``."""
    if n_rows > cfg.max_rows:
        scan = radars["scan_period_s"].to_numpy().astype(float)
        raise ResourceError(
            f"align: {n_rows:,} aligned rows (~{n_rows * BYTES_PER_ALIGNED_ROW / 1e9:.1f} GB) exceed the limit of "
            f"{cfg.max_rows:,} (AlignConfig.max_rows): epochs every {period:g} s with reports kept for "
            f"{cfg.max_age_scans:g} scans of up to {np.nanmax(scan):g} s; set a larger AlignConfig.period_s")


def _plan_frame(df: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame, cfg: AlignConfig, t0_us: int,
                period: float, known_next: NDArray[np.int64] | None = None, k_future: int | None = None
                ) -> AlignPlan:
    """The plan of ``df`` (sorted by run, radar, local track, time; with estimates).

    Whole run: a report's next report is the next row of its local track. Windowed step:
    ``known_next`` (``_NO_K`` = unknown) gives the next report's first epoch already seen for
    held reports, and ``k_future`` is the smallest first epoch any report not yet seen can have:
    a report with no next report yet whose first epoch is ≥ ``k_future`` could still be
    superseded, so it is ``pending`` (neither kept nor rejected)."""
    t_us = df["time"].dt.epoch("us").to_numpy()
    rel = (t_us - t0_us) / US
    # a report is usable from the time it has been collected and processed (§1.4 queue,
    # :mod:`tertiary.sensors.collection`): its first epoch is at or after time + delay; its state is
    # still extrapolated from its own time
    delay = df["collection_delay_s"].fill_null(0.0).to_numpy() if "collection_delay_s" in df.columns else 0.0
    k = _first_epoch(t_us, delay, t0_us, period) if df.height else np.zeros(0, np.int64)

    state, cov, nominal = to_system_frame(df, radars, origin, cfg.local_tracker.altitude_sigma_m)
    finite = np.isfinite(state).all(axis=1) & np.isfinite(cov).all(axis=1)
    plausible = np.linalg.norm(np.nan_to_num(state[:, 3:]), axis=1) <= cfg.max_speed_mps
    conv_ok = report_conversion_valid(df, radars)
    low_quality = adsb.fusion_rejects(df, radars, cfg.adsb_quality)
    eligible = np.equal(low_quality, None)
    usable = finite & plausible & eligible & (conv_ok | (cfg.conversion_gate != "reject"))

    keys = df.select("run", "radar_id", "local_track_id").to_numpy()
    has_next = np.zeros(len(df), bool)
    has_next[:-1] = np.all(keys[1:] == keys[:-1], axis=1)
    k_next = np.where(has_next, np.append(k[1:], _NO_K), _NO_K)
    if known_next is not None:                     # the held report's next was seen in an earlier window
        known = known_next != _NO_K
        k_next, has_next = np.where(known, known_next, k_next), has_next | known
    superseded = has_next & (k_next == k)
    scan = df.select("radar_id").join(radars.select("radar_id", "scan_period_s"), on="radar_id",
                                      how="left", maintain_order="left")["scan_period_s"].to_numpy()
    last_k = _epoch_index(np.floor((rel + cfg.max_age_scans * scan) / period + 1e-9), "last")
    last_k = np.where(has_next, np.minimum(last_k, k_next - 1), last_k)
    pending = (~has_next & usable & (k >= k_future)) if k_future is not None else np.zeros(len(df), bool)
    keep = usable & ~superseded & (last_k >= k) & ~pending
    n_rows = int(np.sum((last_k - k + 1)[keep], dtype=np.float64))

    reason = np.where(~eligible, low_quality.astype(str),
             np.where(~finite, "no usable track estimate (non-finite state or covariance)",
                      np.where(~plausible, f"implausible track speed (> {cfg.max_speed_mps:g} m/s)",
                      np.where(~usable, "polar conversion invalid (seed 002 (13): r sigma_az^2/sigma_r >= 0.4 "
                                        "or sigma >= 0.4 rad)",
                      np.where(superseded, "superseded by a newer report of the same local track before the next epoch",
                               "track estimate too old for any epoch")))))
    rej = ~keep & ~pending
    rejects = df.filter(pl.Series(rej)).select("report_id").with_columns(
        pl.Series("reason", reason[rej], dtype=pl.String))
    return AlignPlan(df, t0_us, period, rel, k, last_k, keep, state, cov, nominal, rejects, n_rows, conv_ok,
                     has_next, k_next, pending)


_ALIGNED_COLUMNS = ["report_id", "run", "radar_id", "local_track_id", "epoch", "time", *STATE, "cov",
                    "res_range_m", "res_range_var_m2", "mode_s", "truth_id", "age_s", "fresh", "nominal_var",
                    "altitude_m", "selected_alt_m", "ehs_track_rate_dps", "cleared_alt_m"]


def empty_aligned(cfg: AlignConfig | None = None) -> pl.DataFrame:
    """An aligned frame with no rows (every report rejected); with ``cfg``, the optional
    columns it adds too (``conv_valid``, identity)."""
    t = pl.Datetime("us", "UTC")
    extra: dict[str, pl.DataType] = {}
    if cfg is not None and cfg.conversion_gate == "flag":
        extra["conv_valid"] = pl.Boolean
    if cfg is not None and cfg.identity:
        extra.update(dict.fromkeys(IDENTITY_COLUMNS, pl.String))
    return pl.DataFrame(schema={
        "report_id": pl.UInt64, "run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
        "epoch": t, "time": t, **dict.fromkeys(STATE, pl.Float64), "cov": pl.Array(pl.Float64, 36),
        "res_range_m": pl.Float64, "res_range_var_m2": pl.Float64, "mode_s": pl.String, "truth_id": pl.Int64,
        "age_s": pl.Float64, "fresh": pl.Boolean, "nominal_var": pl.Array(pl.Float64, 3),
        "altitude_m": pl.Float64, "selected_alt_m": pl.Float64, "ehs_track_rate_dps": pl.Float64,
        "cleared_alt_m": pl.Float64, **extra})


def _epoch_span(p: AlignPlan, k_lo: int | None, k_hi: int | None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per plan row, the first and last epoch index it gives rows at, clipped to [k_lo, k_hi]."""
    start = p.k if k_lo is None else np.maximum(p.k, k_lo)
    end = p.last_k if k_hi is None else np.minimum(p.last_k, k_hi)
    return start, end


def expand(p: AlignPlan, cfg: AlignConfig = AlignConfig(), k_lo: int | None = None,
           k_hi: int | None = None) -> pl.DataFrame:
    """The aligned rows of a plan: each kept report at each of its epochs, extrapolated; only
    epoch indices in [k_lo, k_hi] when given (a window of :func:`align_step`)."""
    start, end = _epoch_span(p, k_lo, k_hi)
    idx = np.flatnonzero(p.keep & (end >= start))
    if idx.size == 0:
        return empty_aligned(cfg) if (k_lo is not None or k_hi is not None) else empty_aligned()
    df, k = p.df, p.k
    keys = df.select("run", "radar_id", "local_track_id").to_numpy()
    counts = (end - start + 1)[idx]
    rows = np.repeat(idx, counts)
    step = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    epoch_k = start[rows] + step
    # output order (run, epoch, radar, local track) computed on integer keys, not by a frame sort
    order = np.lexsort((keys[rows, 2], keys[rows, 1], epoch_k, keys[rows, 0]))
    rows, epoch_k = rows[order], epoch_k[order]
    age = epoch_k * p.period - p.rel[rows]
    x, cov = extrapolate(p.state, p.cov, age, cfg.q_m2s3, rows=rows)

    base = ["report_id", "run", "radar_id", "local_track_id", "time", "res_range_m", "res_range_var_m2"]
    opt = [c for c in ("mode_s", "truth_id", "altitude_m", "selected_alt_m", "ehs_track_rate_dps", "cleared_alt_m")
           if c in df.columns]
    aligned = df.select(base + opt)[rows].with_columns(
        pl.Series("epoch", p.t0_us + _epoch_offset_us(epoch_k, p.period)).cast(pl.Datetime("us", "UTC")),
        *(pl.Series(name, x[:, i]) for i, name in enumerate(STATE)),
        pl.Series("cov", cov, dtype=pl.Array(pl.Float64, 36)),
        pl.Series("age_s", age),
        pl.Series("fresh", epoch_k == k[rows]),
        pl.Series("nominal_var", p.nominal[rows], dtype=pl.Array(pl.Float64, 3)),
        pl.col("res_range_m").fill_null(np.nan), pl.col("res_range_var_m2").fill_null(np.nan),
    )
    if "mode_s" not in aligned.columns:
        aligned = aligned.with_columns(pl.lit(None, pl.String).alias("mode_s"))
    if "truth_id" not in aligned.columns:
        aligned = aligned.with_columns(pl.lit(None, pl.Int64).alias("truth_id"))
    for c in ("altitude_m", "selected_alt_m", "ehs_track_rate_dps", "cleared_alt_m"):
        aligned = aligned.with_columns((pl.col(c) if c in aligned.columns else pl.lit(None)).cast(pl.Float64).alias(c))
    extra = []
    if cfg.conversion_gate == "flag" and p.conv_valid is not None:
        extra.append(pl.Series("conv_valid", p.conv_valid[rows]))
    if cfg.identity:             # fine identification (tertiary.stages.association.associate): the report's code and callsign
        extra.extend(df[c].cast(pl.String)[rows] if c in df.columns else pl.Series(c, [None] * len(rows), pl.String)
                     for c in IDENTITY_COLUMNS)
    return aligned.select(_ALIGNED_COLUMNS).with_columns(extra) if extra else aligned.select(_ALIGNED_COLUMNS)


def _epoch_offset_us(epoch_k: NDArray[np.int64] | int, period: float) -> NDArray[np.int64]:
    """Epoch index → µs after the grid origin (the one rounding every epoch time goes through)."""
    return np.round(np.asarray(epoch_k) * period * US).astype(np.int64)


def align(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
          cfg: AlignConfig = AlignConfig(), grid_origin_us: int | None = None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Align valid reports; returns (aligned, rejects).

    ``aligned`` has one row per (report, epoch at which it represents its local track), with
    ``age_s`` = epoch − report time, ``fresh`` = first epoch of the report, the system-frame
    state/covariance, the radar's range innovation, ``nominal_var`` (a-priori plot variance
    per system axis) and ``altitude_m``: the report's own barometric (Mode C/S) altitude as
    replied, null without one — not extrapolated; with ``time`` it feeds the vertical channel
    (:mod:`tertiary.stages.tracking.altitude`); ``selected_alt_m`` its Mode S selected altitude (BDS 4,0) and
    ``ehs_track_rate_dps`` its track-angle rate (BDS 5,0), ``cleared_alt_m`` its cleared level from
    flight data (:mod:`tertiary.stages.flight_data`), null without. ``rejects`` rows carry
    report_id and reason. No report: both empty.
    The epoch grid starts at ``grid_origin_us`` (default: :func:`epoch_grid`).
    """
    if reports.height == 0:
        return empty_aligned(), pl.DataFrame(schema={"report_id": pl.UInt64, "reason": pl.String})
    p = plan(reports, radars, origin, cfg, grid_origin_us)
    return expand(p, cfg), p.rejects


# --------------------------------------------------------------------------- windowed step


@dataclass(frozen=True)
class AlignState:
    """What :func:`align_step` carries from one window to the next (picklable, never mutated).

    * ``held``: the reports (with their estimates) that still give rows at later epochs or
      whose keep/reject decision waits for the next report of their local track, sorted by
      (run, radar_id, local_track_id, time), with ``__k_next`` = the first epoch index of that
      next report once seen (null before). About one report per live local track.
    * ``tracks``: the local-tracker carry (plot-only inputs, :func:`needs_estimates`) keyed by
      (run, radar_id, local_track_id) = the radar's numbers: last report time and Singer
      channel states (:data:`tertiary.sensors.local_tracks.CARRY_SCHEMA`); a track silent for more
      than ``restart_gap_scans`` scans before the window end is dropped (its next report
      would restart it anyway).
    * ``conversion_invalid``: reports so far failing the seed 002 (13) gate (``AlignPlan.conversion_invalid``).
    """

    held: pl.DataFrame | None = None
    tracks: pl.DataFrame | None = None
    conversion_invalid: int = 0


def init_align_state() -> AlignState:
    """The state before the first window."""
    return AlignState()


def _window_k(t0_grid: int, period: float, t0_us: int | None, t1_us: int | None) -> tuple[int | None, int | None]:
    """The epoch indices whose epoch time (µs, as :func:`expand` rounds it) is in [t0_us, t1_us)."""
    def first_at_or_after(t: int) -> int:
        k = math.ceil((t - t0_grid) / US / period)
        while t0_grid + int(_epoch_offset_us(k - 1, period)) >= t:
            k -= 1
        while t0_grid + int(_epoch_offset_us(k, period)) < t:
            k += 1
        return k
    return (None if t0_us is None else first_at_or_after(t0_us),
            None if t1_us is None else first_at_or_after(t1_us) - 1)


def _window_reports(reports: pl.DataFrame | None, t0_us: int | None, t1_us: int | None) -> pl.DataFrame | None:
    """The window's reports with a ``run`` column; :class:`DataError` for a report outside it
    (each report must go to exactly one window, by time) or with a negative collection delay."""
    if reports is None or reports.height == 0:
        return None
    if "run" not in reports.columns:
        reports = reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    t = reports["time"].dt.epoch("us")
    lo, hi = t.min(), t.max()
    if (t0_us is not None and lo < t0_us) or (t1_us is not None and hi >= t1_us):
        raise DataError(f"reports.time: align_step got reports from {lo} to {hi} µs, outside the window "
                        f"[{t0_us}, {t1_us})")
    if "collection_delay_s" in reports.columns and (reports["collection_delay_s"].fill_null(0.0) < 0).any():
        raise DataError("reports.collection_delay_s: negative delay (align_step needs delays >= 0)")
    return reports


def _prune_tracks(tracks: pl.DataFrame | None, radars: pl.DataFrame, cfg: AlignConfig,
                  t1_us: int | None) -> pl.DataFrame | None:
    """Drop carried local tracks silent for more than the restart gap at the window end: any
    later report of theirs (time ≥ t1) starts a new life, whatever the carried state."""
    if tracks is None or t1_us is None or tracks.height == 0:
        return tracks
    thr = _restart_gap_s(tracks, radars, cfg)
    return tracks.filter(pl.Series((t1_us - tracks["t_us"].to_numpy()) * 1e-6 <= thr))


def align_step(state: AlignState, reports: pl.DataFrame | None, radars: pl.DataFrame, origin: geo.LocalFrame,
               t0_us: int | None, t1_us: int | None, grid_origin_us: int, cfg: AlignConfig = AlignConfig()
               ) -> tuple[tuple[pl.DataFrame, pl.DataFrame], AlignState]:
    """One window [t0_us, t1_us) of :func:`align` (None = unbounded); returns ((aligned, rejects), state).

    * ``reports``: the reports with ``time`` in [t0_us, t1_us) — each report to exactly one
      window, by its time; no margin (hold-back and look-ahead are carried in ``state``).
      Same columns in every window (with or without estimates: plot-only reports get the
      local tracker's estimates, its filters carried across windows).
    * ``grid_origin_us``: the epoch grid origin of the whole run, :func:`grid_origin_us` of the
      dataset's earliest report time for the same grid as :func:`align`.
    * ``aligned``: exactly the rows of ``align(all reports)`` with ``epoch`` in [t0_us, t1_us),
      same order rule (run, epoch, radar_id, local_track_id). Complete: no later window adds
      rows at these epochs (a report not yet seen has time ≥ t1_us, so its first epoch is
      ≥ t1_us and it cannot cut short a held report's rows before t1_us).
    * ``rejects``: (report_id, reason) of the reports whose decision became final here; every
      report is rejected at most once over the windows. A report is decided in its own window,
      except the latest report of a local track whose first epoch (time + collection delay) is
      at or after t1_us: whether the next report supersedes it is unknown, it is decided in
      the window where that next report arrives or where its first epoch falls.
    * The last window must end at ``t1_us=None``: it emits the rows of the held reports at
      later epochs (up to ``max_age_scans`` scans after the last reports) and the last decisions.

    Exact for epoch periods below 500 s (a future report's first epoch is then after every
    epoch before t1_us; larger periods are refused with :class:`OptionError`). Plot-only
    reports: the Singer local tracker only (the chapter 3 range channels are sized on the whole
    run: :class:`OptionError` unless the window is unbounded on both sides). A window beyond
    ``cfg.max_rows`` aligned rows raises :class:`ResourceError`.
    """
    period = epoch_period(radars, cfg)
    new = _window_reports(reports, t0_us, t1_us)
    tracks, conv_bad = state.tracks, state.conversion_invalid
    if new is not None:
        if needs_estimates(new):
            if t0_us is None and t1_us is None and tracks is None:
                new = estimates_by_track_life(new, radars, cfg)
            else:
                new, tracks = _estimates(new, radars, cfg, local_tracks.empty_carry() if tracks is None else tracks)
        conv_bad += int(np.count_nonzero(~report_conversion_valid(new, radars)))
        new = new.with_columns(pl.lit(None, pl.Int64).alias("__k_next"))
    tracks = _prune_tracks(tracks, radars, cfg, t1_us)
    frames = [f for f in (state.held, new) if f is not None]
    if not frames:
        return (empty_aligned(cfg), _empty_rejects()), AlignState(None, tracks, conv_bad)
    df = (pl.concat(frames, how="diagonal_relaxed") if len(frames) > 1 else frames[0]).sort(
        ["run", "radar_id", "local_track_id", "time"], maintain_order=True)

    k_lo, k_hi = _window_k(grid_origin_us, period, t0_us, t1_us)
    k_future = None if t1_us is None else int(_first_epoch(t1_us, 0.0, grid_origin_us, period)[0])
    if k_future is not None and k_hi >= k_future:
        raise OptionError(f"align_step: epoch period {period:g} s too long for windowed alignment (< 500 s)",
                          option="align.period_s")
    known = df["__k_next"].fill_null(_NO_K).to_numpy()
    p = _plan_frame(df.drop("__k_next"), radars, origin, cfg, grid_origin_us, period, known, k_future)
    start, end = _epoch_span(p, k_lo, k_hi)
    _check_rows(int(np.sum((end - start + 1)[p.keep & (end >= start)], dtype=np.float64)), period, radars, cfg)
    aligned = expand(p, cfg, k_lo, k_hi)

    held = None
    if t1_us is not None:
        hold = p.pending | (p.keep & (p.last_k > k_hi))
        if hold.any():
            k_next = pl.Series("__k_next", p.k_next[hold], pl.Int64)
            held = df.filter(pl.Series(hold)).with_columns(
                pl.when(pl.Series(p.has_next[hold])).then(k_next).otherwise(None).alias("__k_next"))
    return (aligned, p.rejects), AlignState(held, tracks, conv_bad)


def _empty_rejects() -> pl.DataFrame:
    return pl.DataFrame(schema={"report_id": pl.UInt64, "reason": pl.String})


# --------------------------------------------------------------------------- registration


#: registration columns applied by :func:`apply_registration` (see :mod:`tertiary.sensors.registration`)
REGISTRATION_COLUMNS = ["radar_id", "range_bias_m", "azimuth_bias_deg", "time_offset_s"]


def apply_registration(reports: pl.DataFrame, table: pl.DataFrame) -> pl.DataFrame:
    """Reports with each radar's systematic errors removed (the inverse of the registration
    model (R1)–(R2) of :mod:`tertiary.sensors.registration`; radars absent from ``table`` unchanged):

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
