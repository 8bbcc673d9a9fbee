"""Real ADS-B trajectories as simulation truth: read, clean, split into flights, resample.

Input is the OpenSky / ``traffic`` schema:

========================  ============================================================
``timestamp``             Datetime (UTC); naive values are taken as UTC, numbers as Unix s
``icao24``                string, the aircraft's transponder address
``latitude, longitude``   degrees WGS-84
``altitude``              feet, barometric (used as height above the ellipsoid)
``groundspeed``           knots                                     (optional)
``track``                 degrees clockwise from true north         (optional)
``vertical_rate``         feet per minute                           (optional)
``onground``              boolean                                   (optional)
``callsign, squawk``      strings                                   (optional)
========================  ============================================================

Missing optional columns are added as nulls (``onground`` as False); a missing required one is
an error naming it.

Cleaning (:func:`clean_adsb`) assigns every input row either to the clean table or to the
removed table with a human-readable ``reason``; the first rule that fires wins, in this order:

1. ``null timestamp``, ``null icao24``, ``null latitude/longitude``,
   ``latitude/longitude out of range``
2. ``altitude out of band (37521 m)`` (a non-null altitude outside the band — checked before
   the on-ground flag so that absurd altitudes are reported as such even on ground fixes)
3. ``on ground`` (``cfg.drop_onground``), then ``null altitude``
4. ``groundspeed out of band (… m/s)``, ``vertical rate out of band (… m/s)``
5. ``duplicate timestamp`` — a second fix of the same aircraft at the same time (first kept)
6. ``stale position (repeated latitude/longitude)`` — an airborne fix whose position is
   bit-identical to the aircraft's previous fix: no new position was received and the old one
   was re-stamped, which would turn the truth into a stair-case (``cfg.drop_stale``)
7. ``altitude spike (implied … m/s)`` and 8. ``position jump (implied … m/s)`` — see below
9. ``flight shorter than 60 s`` — after splitting each aircraft into flights

Spikes and jumps
----------------
Timestamps are floored to ``cfg.time_resolution_s`` (1 s in the OpenSky data), so two fixes
stamped ``dt`` apart may really be up to ``dt + time_resolution_s`` apart; every implied speed
below divides by that bound, so timestamp quantisation alone never flags a fix. Consecutive
fixes of a flight whose implied speed exceeds the threshold are a *break*. Breaks cut the flight
into runs; a run of at most ``cfg.max_excursion_fixes`` fixes is an excursion and is removed
when the fixes on either side of it are consistent with each other (or, at a flight's start or
end, when it is shorter than its neighbouring run). A break that cannot be explained by an
excursion is a discontinuity: the flight is split there (no row is removed; a fragment that
ends up too short is dropped by rule 9). The altitude check (vertical speed, threshold
``max_alt_jump_mps``) runs before the horizontal one (``max_implied_speed_mps``).

Resampling (:func:`adsb_to_trajectories`) interpolates position linearly between the clean
fixes of each flight onto the common grid, so positions at fix times reproduce the fixes
exactly; all flights are done in one ``np.interp`` on a concatenated time axis.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core.errors import DataError
from tertiary.core.geo import EARTH_RADIUS_M, LocalFrame, ecef_to_geodetic, geodetic_to_ecef, wrap_deg
from tertiary.core.units import FT, US
from tertiary.sensors.adsb import REFERENCE_MIN_NACP
from tertiary.simulate.trajectory import SEG_CLIMB, SEG_DESCENT, SEG_STRAIGHT, SEG_TURN, Trajectories

KT = 1852.0 / 3600.0             #: m/s per knot
FPM = FT / 60.0                  #: m/s per foot per minute

REQUIRED_COLUMNS = ("timestamp", "icao24", "latitude", "longitude", "altitude")
OPTIONAL_COLUMNS: dict[str, pl.DataType] = {
    "callsign": pl.String(), "squawk": pl.String(), "groundspeed": pl.Float64(),
    "track": pl.Float64(), "vertical_rate": pl.Float64(), "onground": pl.Boolean(),
}
_TS = pl.Datetime("us", "UTC")

#: segment thresholds (per resampled sample)
TURN_RATE_DPS = 0.5
VERTICAL_SPEED_MPS = 2.5


@dataclass(frozen=True)
class AdsbCleaning:
    """Cleaning and resampling settings; every threshold is configurable."""

    #: altitude band (m, from barometric feet); outside it a fix is removed
    min_alt_m: float = -300.0
    max_alt_m: float = 15_000.0
    #: reported groundspeed above this (m/s) removes the fix
    max_groundspeed_mps: float = 350.0
    #: reported |vertical rate| above this (m/s) removes the fix
    max_vertical_rate_mps: float = 60.0
    #: horizontal speed implied by consecutive fixes above this (m/s) is a position jump
    max_implied_speed_mps: float = 400.0
    #: vertical speed implied by consecutive fixes above this (m/s) is an altitude spike
    max_alt_jump_mps: float = 100.0
    #: remove fixes flagged ``onground``
    drop_onground: bool = True
    #: a gap between consecutive clean fixes longer than this (s) starts a new flight
    max_gap_s: float = 60.0
    #: flights lasting less than this (s, first to last fix) are removed
    min_flight_s: float = 60.0
    #: output grid spacing (s)
    dt: float = 1.0
    #: timestamp quantisation (s): fixes stamped dt apart may be dt + this apart in reality
    time_resolution_s: float = 1.0
    #: remove airborne fixes whose lat/lon repeat the previous fix exactly (re-stamped old fix)
    drop_stale: bool = True
    #: longest run of consecutive fixes removed as one spike/jump excursion
    max_excursion_fixes: int = 4
    #: a fix declaring a NACp below this is not a reference (EPU ≥ 0.05 NM below 8); fixes
    #: without a ``nacp`` column or value are kept
    min_nacp: int = REFERENCE_MIN_NACP


@dataclass
class AdsbTrajectories(Trajectories):
    """:class:`Trajectories` built from ADS-B, remembering the system frame it is expressed in."""

    origin: LocalFrame | None = None


# --------------------------------------------------------------------------- reading


def read_adsb(path: str | Path) -> pl.DataFrame:
    """Read an OpenSky/``traffic`` ADS-B table from parquet or CSV (by suffix) and normalise
    its dtypes (timestamps to Datetime(us, UTC), feet/knots kept as they are)."""
    path = Path(path)
    suffixes = "".join(path.suffixes).lower()
    if ".csv" in suffixes:
        frame = pl.read_csv(path, try_parse_dates=True, infer_schema_length=10_000,
                            schema_overrides={"icao24": pl.String, "callsign": pl.String,
                                              "squawk": pl.String})
    else:
        frame = pl.read_parquet(path)
    return normalise_adsb(frame)


def read_truth_file(path: Path) -> pl.DataFrame:
    """An ADS-B truth file (:func:`read_adsb`), or a :class:`DataError` naming it and what is wrong."""
    try:
        frame = read_adsb(path)
    except (OSError, ValueError, pl.exceptions.PolarsError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"not a readable ADS-B trajectory table (OpenSky/traffic schema): {first}",
                        path=str(path)) from exc
    if frame.filter(pl.col("timestamp").is_not_null()).height == 0:
        raise DataError("no ADS-B row with a timestamp", path=str(path))
    return frame


def normalise_adsb(frame: pl.DataFrame) -> pl.DataFrame:
    """Check the required columns, cast every known column to its canonical dtype and add
    missing optional columns (nulls; ``onground`` False). Idempotent."""
    missing = [c for c in REQUIRED_COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError(f"ADS-B table is missing required column(s) {', '.join(missing)}; "
                         f"expected the OpenSky/traffic schema {', '.join(REQUIRED_COLUMNS)} "
                         f"(+ optional {', '.join(OPTIONAL_COLUMNS)}); got {', '.join(frame.columns)}")
    exprs = [_timestamp_expr(frame.schema["timestamp"]), pl.col("icao24").cast(pl.String)]
    exprs += [pl.col(c).cast(pl.Float64) for c in ("latitude", "longitude", "altitude")]
    for name, dtype in OPTIONAL_COLUMNS.items():
        if name not in frame.columns:
            exprs.append(pl.lit(False if name == "onground" else None, dtype=dtype).alias(name))
        elif name == "onground" and frame.schema[name] == pl.String:
            exprs.append(pl.col(name).str.to_lowercase().is_in(["true", "1", "t", "yes"]).alias(name))
        else:
            exprs.append(pl.col(name).cast(dtype))
    return frame.with_columns(exprs)


def _timestamp_expr(dtype: pl.DataType) -> pl.Expr:
    col = pl.col("timestamp")
    if isinstance(dtype, pl.Datetime):
        col = col.dt.replace_time_zone("UTC") if dtype.time_zone is None else col.dt.convert_time_zone("UTC")
    elif dtype == pl.String:
        col = col.str.to_datetime(time_unit="us", time_zone="UTC")
    elif dtype.is_numeric():
        col = (col.cast(pl.Float64) * 1e6).round(0).cast(pl.Int64).cast(pl.Datetime("us")).dt.replace_time_zone("UTC")
    elif dtype == pl.Date:
        col = col.cast(pl.Datetime("us")).dt.replace_time_zone("UTC")
    return col.cast(_TS).alias("timestamp")


# --------------------------------------------------------------------------- cleaning

# reason codes (0 = keep); templates get the code's value formatted as an integer
_REASONS: dict[int, str] = {
    1: "null timestamp", 2: "null icao24", 3: "null latitude/longitude",
    4: "latitude/longitude out of range", 5: "on ground", 6: "null altitude",
    7: "altitude out of band ({} m)", 8: "groundspeed out of band ({} m/s)",
    9: "vertical rate out of band ({} m/s)", 10: "duplicate timestamp",
    11: "stale position (repeated latitude/longitude)", 12: "altitude spike (implied {} m/s)",
    13: "position jump (implied {} m/s)", 14: "flight shorter than {} s",
    15: "declared quality below the reference bound (NACp {})",
}
_C_SPIKE, _C_JUMP, _C_SHORT = 12, 13, 14


def clean_adsb(frame: pl.DataFrame, cfg: AdsbCleaning = AdsbCleaning()) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Split ``frame`` into (clean, removed).

    Both are sorted by (icao24, timestamp) and keep every input column (normalised, see
    :func:`normalise_adsb`). ``clean`` gains ``flight`` (Int64, 0..F-1 in (icao24, start time)
    order, the ``truth_id`` of :func:`adsb_to_trajectories`); ``removed`` gains ``reason``.
    Every input row is in exactly one of the two.
    """
    df = normalise_adsb(frame)
    df = df.sort(["icao24", "timestamp"], nulls_last=True, maintain_order=True)
    code, value = _static_checks(df, cfg)
    n = df.height

    # numpy views of the columns the stateful checks need
    icao = df["icao24"].fill_null("").to_numpy()
    ts = df["timestamp"].dt.epoch("us")
    ts_us = ts.fill_null(ts.min() if ts.null_count() < n else 0).to_numpy().astype(np.int64)
    t = (ts_us - (ts_us.min() if n else 0)) / 1e6
    lat = df["latitude"].fill_null(np.nan).to_numpy().astype(np.float64)
    lon = df["longitude"].fill_null(np.nan).to_numpy().astype(np.float64)
    alt = df["altitude"].fill_null(np.nan).to_numpy().astype(np.float64) * FT
    res = cfg.time_resolution_s

    # duplicate timestamps and stale positions, against the previous surviving fix
    w = np.flatnonzero(code == 0)
    dup = _as_prev(icao, w) & _as_prev(ts_us, w)
    code[w[dup]] = 10
    if cfg.drop_stale:
        w = np.flatnonzero(code == 0)
        stale = _as_prev(icao, w) & _as_prev(lat, w) & _as_prev(lon, w)
        code[w[stale]] = 11

    # spikes/jumps; unexplained breaks split flights (split[i]: a new flight starts at row i)
    split = np.zeros(n, dtype=bool)

    def vertical(i: NDArray[np.intp], j: NDArray[np.intp]) -> NDArray[np.float64]:
        return np.abs(alt[j] - alt[i]) / (np.abs(t[j] - t[i]) + res)

    def horizontal(i: NDArray[np.intp], j: NDArray[np.intp]) -> NDArray[np.float64]:
        return _haversine(lat[i], lon[i], lat[j], lon[j]) / (np.abs(t[j] - t[i]) + res)

    for speed, limit, reason in ((vertical, cfg.max_alt_jump_mps, _C_SPIKE),
                                 (horizontal, cfg.max_implied_speed_mps, _C_JUMP)):
        w = np.flatnonzero(code == 0)
        start = _flight_starts(w, icao, t, split, cfg.max_gap_s)
        removed, implied, breaks = _excursions(w.size, start, lambda i, j: speed(w[i], w[j]),
                                               limit, cfg.max_excursion_fixes)
        code[w[removed]] = reason
        value[w[removed]] = implied[removed]
        split[w[breaks]] = True

    # flights and their durations
    w = np.flatnonzero(code == 0)
    start = _flight_starts(w, icao, t, split, cfg.max_gap_s)
    fid = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    last = np.r_[first[1:] - 1, w.size - 1] if w.size else first
    short = (t[w[last]] - t[w[first]]) < cfg.min_flight_s
    drop = short[fid] if w.size else np.zeros(0, dtype=bool)
    code[w[drop]] = _C_SHORT
    value[w[drop]] = cfg.min_flight_s
    flight = np.full(n, -1, dtype=np.int64)
    kept = ~drop
    # renumber surviving flights 0..F-1
    flight[w[kept]] = np.cumsum(~short)[fid[kept]] - 1

    df = df.with_columns(pl.Series("_code", code, dtype=pl.Int8), pl.Series("_value", value))
    clean = (df.filter(pl.col("_code") == 0)
             .with_columns(pl.Series("flight", flight[code == 0], dtype=pl.Int64))
             .drop("_code", "_value"))
    removed_df = df.filter(pl.col("_code") != 0).with_columns(_reason_expr()).drop("_code", "_value")
    return clean, removed_df


def _static_checks(df: pl.DataFrame, cfg: AdsbCleaning) -> tuple[NDArray[np.int8], NDArray[np.float64]]:
    """Row-local rules 1–4 as one vectorised when/then chain: (code, value) per row."""
    lat, lon, alt_m = pl.col("latitude"), pl.col("longitude"), pl.col("altitude") * FT
    gs, vr = pl.col("groundspeed") * KT, pl.col("vertical_rate") * FPM
    rules: list[tuple[pl.Expr, int, pl.Expr | None]] = [
        (pl.col("timestamp").is_null(), 1, None),
        (pl.col("icao24").is_null() | (pl.col("icao24").str.strip_chars() == ""), 2, None),
        (lat.is_null() | lon.is_null() | lat.is_nan() | lon.is_nan(), 3, None),
        ((lat.abs() > 90.0) | (lon.abs() > 180.0), 4, None),
        (((alt_m < cfg.min_alt_m) | (alt_m > cfg.max_alt_m)) & alt_m.is_not_nan(), 7, alt_m),
        (pl.col("onground").fill_null(False) & pl.lit(cfg.drop_onground), 5, None),
        (pl.col("altitude").is_null() | pl.col("altitude").is_nan(), 6, None),
        ((gs > cfg.max_groundspeed_mps).fill_null(False), 8, gs),
        ((vr.abs() > cfg.max_vertical_rate_mps).fill_null(False), 9, vr),
    ]
    if "nacp" in df.columns:
        nacp = pl.col("nacp").cast(pl.Float64)
        rules.append(((nacp < cfg.min_nacp).fill_null(False), 15, nacp))
    code_expr: pl.Expr = pl.lit(0, dtype=pl.Int8)
    value_expr: pl.Expr = pl.lit(np.nan, dtype=pl.Float64)
    for cond, code, val in reversed(rules):
        code_expr = pl.when(cond).then(pl.lit(code, dtype=pl.Int8)).otherwise(code_expr)
        value_expr = pl.when(cond).then(val if val is not None else pl.lit(np.nan)).otherwise(value_expr)
    out = df.select(code_expr.alias("c"), value_expr.cast(pl.Float64).alias("v"))
    return out["c"].to_numpy().astype(np.int8).copy(), out["v"].to_numpy().astype(np.float64).copy()


def _reason_expr() -> pl.Expr:
    code = pl.col("_code")
    value = pl.col("_value").round(0).cast(pl.Int64, strict=False)
    expr: pl.Expr = pl.lit(None, dtype=pl.String)
    for c, template in _REASONS.items():
        text = pl.format(template, value) if "{}" in template else pl.lit(template)
        expr = pl.when(code == c).then(text).otherwise(expr)
    return expr.alias("reason")


def _as_prev(values: NDArray, w: NDArray[np.intp]) -> NDArray[np.bool_]:
    """For the surviving rows ``w``: whether each row's value equals the previous survivor's."""
    out = np.zeros(w.size, dtype=bool)
    out[1:] = values[w[1:]] == values[w[:-1]]
    return out


def _flight_starts(w: NDArray[np.intp], icao: NDArray, t: NDArray[np.float64],
                   split: NDArray[np.bool_], max_gap_s: float) -> NDArray[np.bool_]:
    """For the surviving rows ``w`` (sorted), whether each starts a new flight: a new aircraft,
    a gap longer than ``max_gap_s``, or a recorded split since the previous surviving row."""
    start = np.ones(w.size, dtype=bool)
    if w.size > 1:
        a, b = w[:-1], w[1:]
        seg = np.cumsum(split)
        start[1:] = (icao[b] != icao[a]) | (t[b] - t[a] > max_gap_s) | (seg[b] != seg[a])
    return start


def _excursions(m: int, start: NDArray[np.bool_], speed, limit: float, max_run: int
                ) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.bool_]]:
    """Find excursions among ``m`` sorted fixes with flight starts ``start``.

    ``speed(i, j)`` is the implied speed between fixes i and j (index arrays). Returns
    (removed mask, implied speed of the break that flagged each removed fix, mask of fixes at
    which an unexplained break starts a new flight)."""
    removed = np.zeros(m, dtype=bool)
    implied = np.full(m, np.nan)
    breaks_out = np.zeros(m, dtype=bool)
    if m < 2:
        return removed, implied, breaks_out
    idx = np.arange(m)
    v = np.zeros(m)                       # v[i]: implied speed from fix i-1 to i (same flight)
    inner = ~start
    v[inner] = speed(idx[inner] - 1, idx[inner])
    brk = inner & (v > limit)             # a break between i-1 and i
    if not brk.any():
        return removed, implied, breaks_out
    # runs: maximal stretches of fixes without a break or a flight start
    run_start = start | brk
    run = np.cumsum(run_start) - 1
    rs = np.flatnonzero(run_start)
    re = np.r_[rs[1:] - 1, m - 1]
    length = re - rs + 1
    n_runs = rs.size
    fl = np.cumsum(start) - 1
    broken_before = brk[rs]                                   # a break precedes the run
    broken_after = np.r_[brk[rs[1:]], False]                  # a break follows the run
    first_of_flight, last_of_flight = start[rs], np.r_[start[rs[1:]], True]
    prev_len = np.r_[0, length[:-1]]
    next_len = np.r_[length[1:], 0]
    small = length <= max_run
    # interior excursion: both neighbours across it agree
    interior = small & broken_before & broken_after
    ok_interior = np.zeros(n_runs, dtype=bool)
    if interior.any():
        a, b = rs[interior] - 1, re[interior] + 1
        ok_interior[interior] = (fl[a] == fl[b]) & (speed(a, b) <= limit)
    # edge excursion: at the flight's start/end, shorter than the run it breaks away from
    lead = small & first_of_flight & broken_after & ~broken_before & (length < next_len)
    trail = small & last_of_flight & broken_before & ~broken_after & (length < prev_len)
    drop_run = ok_interior | lead | trail
    removed = drop_run[run]
    # implied speed of the break entering the run (leading runs: the one leaving it)
    entering = np.where(broken_before, v[rs], v[np.minimum(re + 1, m - 1)])
    implied = np.where(removed, entering[run], np.nan)
    # breaks not explained by a removed run split the flight
    explained = np.zeros(m, dtype=bool)
    explained[rs[drop_run & broken_before]] = True                       # entering a removed run
    after = re[drop_run & broken_after] + 1
    explained[after[after < m]] = True                                   # leaving a removed run
    breaks_out = brk & ~explained
    # a lone break that one fix explains (the other side of that fix stays under the limit,
    # e.g. a quantised timestamp hides the excursion on that side): drop the fix whose removal
    # leaves its neighbours consistent
    b = np.flatnonzero(breaks_out)
    lone = ~np.isin(b - 1, b) & ~np.isin(b + 1, b)
    b = b[lone & (b >= 2) & (b <= m - 2)]
    a = b - 1
    ok_a = (fl[a - 1] == fl[b]) & ~removed[a - 1]
    ok_b = (fl[b + 1] == fl[a]) & ~removed[b + 1]
    va = np.full(b.size, np.inf)
    vb = np.full(b.size, np.inf)
    va[ok_a] = speed(a[ok_a] - 1, b[ok_a])
    vb[ok_b] = speed(a[ok_b], b[ok_b] + 1)
    fix = np.where(va <= vb, a, b)
    good = np.minimum(va, vb) <= limit
    removed[fix[good]] = True
    implied[fix[good]] = v[b[good]]
    breaks_out[b[good]] = False
    return removed, implied, breaks_out


def _haversine(lat1: NDArray, lon1: NDArray, lat2: NDArray, lon2: NDArray) -> NDArray[np.float64]:
    """Great-circle distance (m) on the mean Earth sphere; inputs in degrees."""
    p1, p2 = np.radians(lat1), np.radians(lat2)
    dp, dl = p2 - p1, np.radians(lon2 - lon1)
    h = np.sin(dp / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    return 2.0 * EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(h, 0.0, 1.0)))


# --------------------------------------------------------------------------- resampling


def adsb_to_trajectories(frame: pl.DataFrame, origin: LocalFrame | None = None,
                         cfg: AdsbCleaning = AdsbCleaning(), *, epoch: datetime | None = None
                         ) -> tuple[AdsbTrajectories, pl.DataFrame]:
    """Clean ``frame``, split it into flights and resample them onto a common grid.

    * ``origin``: the system ENU frame; default the centroid of the clean positions at ground
      level (0 m), recorded as ``trajectories.origin``.
    * grid: ``t[k] = epoch + k·cfg.dt``; ``epoch`` defaults to the first clean timestamp
      floored to the second; it runs to the last clean fix. Fixes before ``epoch`` are ignored.
    * position: linear interpolation between the fixes of each flight; samples outside a
      flight are inactive (pos/vel NaN there).
    * velocity: reported groundspeed/track/vertical rate (aircraft-local ENU, rotated into the
      system frame per fix, interpolated linearly) where both bracketing fixes report it, else
      central differences of the resampled positions.
    * segment: turn if the heading rate over ±2 s exceeds 0.5 deg/s, else climb/descent if
      |vz| > 2.5 m/s, else straight.
    * truth_id = flight index (0..F-1, (icao24, start) order, = ``clean["flight"]``); meta has
      ``icao24`` and ``callsign`` (most frequent non-null callsign of the flight).

    Returns (trajectories, removed) with ``removed`` from :func:`clean_adsb`.
    """
    clean, removed = clean_adsb(frame, cfg)
    if clean.height == 0:
        raise ValueError(f"no ADS-B fix survives cleaning ({removed.height} rows removed)")
    dt = float(cfg.dt)

    lat = clean["latitude"].to_numpy()
    lon = clean["longitude"].to_numpy()
    alt = clean["altitude"].to_numpy() * FT
    if origin is None:
        x, y, z = geodetic_to_ecef(lat, lon, np.zeros_like(lat))
        lat0, lon0, _ = ecef_to_geodetic(x.mean(), y.mean(), z.mean())
        origin = LocalFrame(float(lat0), float(lon0), 0.0)
    ts_us = clean["timestamp"].dt.epoch("us").to_numpy().astype(np.int64)
    if epoch is None:
        epoch_us = int(ts_us.min() // US * US)
    else:
        if epoch.tzinfo is None:
            epoch = epoch.replace(tzinfo=timezone.utc)
        epoch_us = round(epoch.timestamp() * 1e6)
    epoch_dt = datetime.fromtimestamp(epoch_us // US, tz=timezone.utc).replace(
        microsecond=int(epoch_us % US))
    t = (ts_us - epoch_us) / 1e6                       # s since epoch, per fix
    fid = clean["flight"].to_numpy()
    n_flights = int(fid.max()) + 1

    # fixes -> system ENU
    e, n, u = origin.from_geodetic(lat, lon, alt)
    v_fix = reported_velocity(clean, lat, lon, origin)

    # flight extents on the grid
    first = np.flatnonzero(np.r_[True, fid[1:] != fid[:-1]])
    last = np.r_[first[1:] - 1, fid.size - 1]
    eps = 1e-9
    k0 = np.maximum(np.ceil(t[first] / dt - eps), 0).astype(np.int64)
    k1 = np.floor(t[last] / dt + eps).astype(np.int64)
    n_times = max(int(k1.max()) + 1, 1)
    count = np.maximum(k1 - k0 + 1, 0)
    qf = np.repeat(np.arange(n_flights), count)                         # sample -> flight
    offsets = np.r_[0, np.cumsum(count)[:-1]]
    qk = k0[qf] + (np.arange(qf.size) - offsets[qf])                    # sample -> grid index

    # one interpolation over all flights: flights laid end to end on a shifted time axis
    span = float(max(t.max(), n_times * dt) - min(t.min(), 0.0)) + 10.0 * dt + 1.0
    x_fix = t + fid * span
    x_q = qk * dt + qf * span
    pos = np.stack([np.interp(x_q, x_fix, c) for c in (e, n, u)], axis=-1)
    vel = np.stack([np.interp(x_q, x_fix, v_fix[:, i]) for i in range(3)], axis=-1)

    # fallback velocity: central differences within each flight (one-sided at the ends)
    s_idx = np.arange(qf.size)
    prev = np.where((s_idx > 0) & (qf == np.roll(qf, 1)), s_idx - 1, s_idx)
    nxt = np.where((s_idx < qf.size - 1) & (qf == np.roll(qf, -1)), s_idx + 1, s_idx)
    span_k = np.maximum(nxt - prev, 1) * dt
    v_diff = (pos[nxt] - pos[prev]) / span_k[:, None]
    missing = ~np.isfinite(vel).all(axis=1)
    vel[missing] = v_diff[missing]

    segment = _classify(vel, qf, dt)

    shape = (n_flights, n_times)
    pos_out = np.full(shape + (3,), np.nan)
    vel_out = np.full(shape + (3,), np.nan)
    active = np.zeros(shape, dtype=bool)
    seg_out = np.full(shape, SEG_STRAIGHT, dtype=np.int8)
    pos_out[qf, qk] = pos
    vel_out[qf, qk] = vel
    active[qf, qk] = True
    seg_out[qf, qk] = segment

    meta = (clean.group_by("flight")
            .agg(pl.col("icao24").first(),
                 pl.col("callsign").str.strip_chars().replace("", None).drop_nulls()
                 .mode().sort().first().alias("callsign"))
            .sort("flight"))
    traj = AdsbTrajectories(
        dt=dt, pos=pos_out, vel=vel_out, active=active, segment=seg_out,
        truth_id=np.arange(n_flights, dtype=np.int64), epoch=epoch_dt,
        meta={"icao24": meta["icao24"].to_numpy().astype(object),
              "callsign": meta["callsign"].to_numpy().astype(object)},
        origin=origin)
    return traj, removed


def reported_velocity(clean: pl.DataFrame, lat: NDArray, lon: NDArray, origin: LocalFrame) -> NDArray[np.float64]:
    """(N, 3) velocity of each fix in the system ENU from groundspeed/track/vertical rate,
    rotated per fix from the aircraft's local ENU through ECEF; NaN where any is null."""
    gs = clean["groundspeed"].fill_null(np.nan).to_numpy().astype(np.float64) * KT
    trk = np.radians(clean["track"].fill_null(np.nan).to_numpy().astype(np.float64))
    vz = clean["vertical_rate"].fill_null(np.nan).to_numpy().astype(np.float64) * FPM
    ve, vn = gs * np.sin(trk), gs * np.cos(trk)
    phi, lam = np.radians(lat), np.radians(lon)
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    ecef = np.stack([-sl * ve - sp * cl * vn + cp * cl * vz,
                     cl * ve - sp * sl * vn + cp * sl * vz,
                     cp * vn + sp * vz], axis=-1)
    return ecef @ origin.rotation.T


def _classify(vel: NDArray[np.float64], qf: NDArray[np.int64], dt: float) -> NDArray[np.int8]:
    """Segment code per resampled sample: turn rate over ±2 s, then vertical speed."""
    m = qf.size
    if m == 0:
        return np.zeros(0, dtype=np.int8)
    h = max(1, int(round(2.0 / dt)))
    s = np.arange(m)
    # window [s-h, s+h] clipped to the sample's own flight
    first = np.r_[True, qf[1:] != qf[:-1]]
    starts = np.flatnonzero(first)
    ends = np.r_[starts[1:] - 1, m - 1]
    fi = np.cumsum(first) - 1
    lo = np.maximum(s - h, starts[fi])
    hi = np.minimum(s + h, ends[fi])
    heading = np.degrees(np.arctan2(vel[:, 0], vel[:, 1]))
    span = np.maximum(hi - lo, 1) * dt
    rate = np.abs(wrap_deg(heading[hi] - heading[lo])) / span
    seg = np.full(m, SEG_STRAIGHT, dtype=np.int8)
    seg[vel[:, 2] > VERTICAL_SPEED_MPS] = SEG_CLIMB
    seg[vel[:, 2] < -VERTICAL_SPEED_MPS] = SEG_DESCENT
    seg[rate > TURN_RATE_DPS] = SEG_TURN
    return seg
