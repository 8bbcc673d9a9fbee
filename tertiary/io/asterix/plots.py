"""CAT001 (legacy radar) and CAT020 (MLAT / WAM) target reports → ``reports``; CAT004 STCA
messages → ``alerts`` (an external alert list). Decoding: :mod:`tertiary.io.asterix.fastcats`.

* CAT001: I001/040 → ``range_m`` (RHO 1/128 NM), ``azimuth_deg``; I001/090 → ``altitude_m``;
  I001/070 → ``mode_3a``; I001/161 (tracks) → ``local_track_id``. A plot has no track number:
  its local track is its Mode 3/A code (``PLOT_TRACK_BASE`` + code, ``plot`` = true); a plot
  without a validated code is rejected. I001/141 holds the time of day modulo 512 s: the full
  time is the one nearest the radar's CAT002 time of day (the message nearest in arrival),
  else the capture time stamp.
* CAT020: I020/041 (WGS-84) and/or I020/042 (Cartesian, the sensor's local east/north) →
  ``plot_lat_deg``, ``plot_lon_deg``, ``plot_x_m``, ``plot_y_m``; I020/500 SDP →
  ``plot_sigma_x_m``, ``plot_sigma_y_m``, ``plot_sigma_xy_m``; I020/105 → ``plot_height_m``;
  the position as seen from the sensor's reference point → ``range_m``, ``azimuth_deg`` (so the
  polar stages can place the plot until the Cartesian measurement model is wired).
* CAT021 of a SAC/SIC the sites file names with ``kind = "adsb"`` (an ADS-B ground station):
  the broadcast position I021/131 (or /130) as the same Cartesian plot, in the station's ENU
  frame; I021/145 → ``altitude_m``, I021/140 → ``plot_height_m``, I021/080 → ``mode_s`` and
  ``local_track_id`` (the 24-bit address: one local track per aircraft), I021/090 →
  ``adsb_nacp``, ``adsb_nic``, ``adsb_sil`` and the plot σ from NACp (σ per axis EPU/2.448,
  σxy 0; null without NACp). CAT021 of any other SAC/SIC is truth (:mod:`.importer`).
"""

from __future__ import annotations

import json

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import ADSB_QUALITY_COLUMNS, MLAT_PLOT_COLUMNS, TABLES
from tertiary.core import geo
from tertiary.core.units import FT
from tertiary.io.asterix import fastcats
from tertiary.sensors.adsb import ADSB, sigma_from_nacp
from tertiary.io.asterix.importer import DAY, TIME, absolute_time

Rejects = list[dict[str, object]]
#: CAT001 plots: local_track_id = this + the Mode 3/A code (as an integer of its 12 bits)
PLOT_TRACK_BASE = 1 << 16
#: CAT004 message type of STCA (I004/000)
STCA = 7
UNSCORED = "unscored"

_COMMON = ("mode_s", "mode_3a", "callsign")


def _flags(work: pl.DataFrame, stale_s: float) -> pl.DataFrame:
    """Arrival-order flags as for CAT048: out of order within a local track, stale within a radar."""
    t_ok = pl.col("t").fill_nan(None)
    prev = t_ok.cum_max().forward_fill().shift(1)
    return work.with_columns(
        behind=(prev.over(["sac", "sic"]) - t_ok).fill_null(0.0).clip(lower_bound=0.0),
        track_behind=(prev.over(["sac", "sic", "trn"]) - t_ok).fill_null(0.0),
    ).with_columns(out_of_order=pl.col("track_behind") > 0, stale=pl.col("behind") > stale_s,
                   latency_s=(pl.col("capture_s") - pl.col("t")).fill_nan(None))


def _split(work: pl.DataFrame, reasons: list[tuple[pl.Expr, object]], cat: str
           ) -> tuple[pl.DataFrame, Rejects]:
    """(rows no reason applies to, rejects rows naming every reason that does and the place);
    the reason text is built for the rejected rows only."""
    work = work.with_columns(pl.any_horizontal([c.fill_null(False) for c, _ in reasons]).alias("__bad"))
    bad = work.filter(pl.col("__bad")).with_columns(reason=pl.concat_str(
        [pl.when(c).then(pl.lit(r) if isinstance(r, str) else r) for c, r in reasons], separator="; ",
        ignore_nulls=True))
    rej = [{"reason": f"{cat}: {r.pop('reason')}", "detail": json.dumps(r | {"stage": "import"})}
           for r in bad.select("reason", "file", "datagram", "offset", "sac", "sic", "tod_s").iter_rows(named=True)]
    return work.filter(~pl.col("__bad")).drop("__bad"), rej


def _times(frame: pl.DataFrame, day0: float | None) -> pl.DataFrame:
    """Absolute time ``t`` (NaN where the time of day is absent or ≥ 1 day) and the day."""
    tod = frame["tod_s"].fill_null(np.nan).to_numpy()
    ok = np.isfinite(tod) & (tod >= 0) & (tod < DAY)
    t = np.full(frame.height, np.nan)
    t[ok] = absolute_time(tod[ok], frame["capture_s"].to_numpy()[ok], day0)
    return frame.with_columns(pl.Series("t", t), (pl.Series(t) // DAY).alias("day"))


def _dedup(frame: pl.DataFrame, counts: dict[str, int], cat: str) -> pl.DataFrame:
    """Redundant lines: the same record bytes of one source on one day, first arrival kept."""
    first = frame.select(pl.struct("sac", "sic", "hash", "length", "day").is_first_distinct()).to_series()
    counts[f"{cat}_duplicates"] = int((~first).sum())
    return frame.filter(first)


def _with_sites(frame: pl.DataFrame, sites: pl.DataFrame | None) -> pl.DataFrame:
    """Each record with its sensor's radar_id, kind and site (null when not in the sites file)."""
    cols = ["sac", "sic", "radar_id", "lat_deg", "lon_deg", "alt_m", "kind"]
    if sites is None:
        return frame.with_columns(pl.lit(None, pl.UInt32).alias("radar_id"), pl.lit(None, pl.String).alias("kind"),
                                  *(pl.lit(None, pl.Float64).alias(c) for c in ("site_lat", "site_lon", "site_alt")))
    s = sites if "kind" in sites.columns else sites.with_columns(pl.lit("radar").alias("kind"))
    return frame.join(s.select(cols).rename({"lat_deg": "site_lat", "lon_deg": "site_lon", "alt_m": "site_alt"}),
                      on=["sac", "sic"], how="left", maintain_order="left")


def _reports(good: pl.DataFrame, extra: list[str]) -> pl.DataFrame:
    """The ``reports`` columns (CAT048's order and types) plus the category's ``extra`` ones."""
    return good.select(
        pl.col("radar_id").cast(pl.UInt32), (pl.col("t") * 1e6).round().cast(pl.Int64).cast(TIME).alias("time"),
        pl.col("trn").cast(pl.UInt32).alias("local_track_id"), "range_m", "azimuth_deg", "altitude_m", *_COMMON,
        pl.lit(0, pl.UInt32).alias("run"), "flight_level", *extra, pl.col("sac").cast(pl.UInt8),
        pl.col("sic").cast(pl.UInt8), "out_of_order", "stale", "latency_s")


def _site_reasons(cat: str, time_item: str) -> list[tuple[pl.Expr, object]]:
    """Reasons every report category shares: source, time, a SAC/SIC missing from the sites file."""
    return [(pl.col("sac") < 0, f"no I{cat}/010 (SAC/SIC)"),
            (pl.col("tod_s").is_null() & (pl.col(time_item) < 0), f"no I{cat} time of day"),
            (pl.col("tod_s") >= DAY, pl.format("time of day {} s not below 86400", pl.col("tod_s"))),
            (pl.col("radar_id").is_null() & (pl.col("sac") >= 0),
             pl.format("SAC/SIC {}/{} not in the sites file", pl.col("sac"), pl.col("sic")))]


# --------------------------------------------------------------------------- CAT001


def cat001_time(plots: pl.DataFrame, cat002: pl.DataFrame) -> pl.Series:
    """Full time of day (s) of CAT001 truncated times (I001/141, period 512 s): the instant
    nearest the reference — the radar's CAT002 time of day nearest in arrival, else the capture
    time of day; null without either."""
    trunc = plots["tod_trunc"].to_numpy() / 128.0
    ref = plots.select("sac", "sic", "seq").with_row_index("__i")
    if cat002.height:
        marks = (cat002.filter(pl.col("tod_s").is_not_null()).select("sac", "sic", "seq", pl.col("tod_s").alias("ref"))
                 .sort("seq"))
        ref = ref.sort("seq").join_asof(marks, on="seq", by=["sac", "sic"], strategy="nearest",
                                        check_sortedness=False).sort("__i")
        r = ref["ref"].fill_null(np.nan).to_numpy()
    else:
        r = np.full(plots.height, np.nan)
    cap = np.mod(plots["capture_s"].to_numpy(), DAY)
    r = np.where(np.isfinite(r), r, cap)
    full = np.mod(r + np.mod(trunc - r + 256.0, 512.0) - 256.0, DAY)
    return pl.Series("tod_s", np.where(np.isfinite(full) & (plots["tod_trunc"].to_numpy() >= 0), full, np.nan)
                     ).fill_nan(None)


def cat001_reports(raw: pl.DataFrame, cat002: pl.DataFrame, sites: pl.DataFrame | None, day0: float | None,
                   stale_s: float) -> tuple[pl.DataFrame, Rejects, dict[str, int]]:
    """CAT001 plots and tracks → (reports, rejects, counts)."""
    counts = {"cat001_records": raw.height}
    frame = raw.with_columns(cat001_time(raw, cat002))
    frame = _dedup(_times(frame, day0), counts, "cat001")
    code = pl.col("mode_3a").str.to_integer(base=8, strict=False)
    frame = frame.with_columns(
        trn=pl.when(pl.col("plot")).then(code + PLOT_TRACK_BASE).otherwise(pl.col("trn")),
        altitude_m=pl.col("fl_valid") * 100.0 * FT, mode_s=pl.lit(None, pl.String), callsign=pl.lit(None, pl.String))
    work = _flags(_with_sites(frame, sites), stale_s)
    reasons = _site_reasons("001", "tod_trunc") + [
        ((pl.col("tod_trunc") >= 0) & pl.col("tod_s").is_null(),
         "no time reference for the truncated time of day I001/141 (no CAT002 of this radar, no capture time)"),
        (pl.col("range_m").is_null(), "no I001/040 (measured position)"),
        (pl.col("plot") & pl.col("trn").is_null(), "plot without a validated Mode 3/A code: no local track"),
        (~pl.col("plot") & (pl.col("trn") < 0), "track without I001/161 (track number)"),
    ]
    good, rej = _split(work, reasons, "CAT001")
    counts |= {"cat001_reports": good.height, "cat001_rejected": len(rej)}
    return _reports(good, ["plot", "detection"]), rej, counts


# --------------------------------------------------------------------------- CAT020


def _site_plot(g: dict[str, NDArray[np.float64]], h: NDArray[np.float64], frame: geo.LocalFrame, site_alt: float
               ) -> tuple[NDArray[np.float64], ...]:
    """(x, y, up, lat, lon) of plots in the site's ENU frame: x, y from I020/042 when sent, else
    from I020/041; lat, lon from I020/041 when sent, else from x, y."""
    wgs = np.isfinite(g["lat_deg"])
    e, n, u = (np.full(len(h), np.nan) for _ in range(3))
    e[wgs], n[wgs], u[wgs] = frame.from_geodetic(g["lat_deg"][wgs], g["lon_deg"][wgs], h[wgs])
    # Cartesian only: the tangent plane falls away from the ellipsoid by d²/2R
    cu = h - site_alt - (g["x_m"] ** 2 + g["y_m"] ** 2) / (2 * geo.EARTH_RADIUS_M)
    cart = ~wgs & np.isfinite(g["x_m"])
    lat, lon = g["lat_deg"].copy(), g["lon_deg"].copy()
    lat[cart], lon[cart], _ = frame.to_geodetic(g["x_m"][cart], g["y_m"][cart], cu[cart])
    x = np.where(np.isfinite(g["x_m"]), g["x_m"], e)
    y = np.where(np.isfinite(g["y_m"]), g["y_m"], n)
    return x, y, np.where(wgs, u, cu), lat, lon


def _mlat_geometry(work: pl.DataFrame) -> pl.DataFrame:
    """Cartesian and WGS-84 plot of every report, and its range and azimuth from the sensor's
    reference point (the site), sensor by sensor (null without a site)."""
    g = {c: work[c].fill_null(np.nan).to_numpy() for c in ("lat_deg", "lon_deg", "x_m", "y_m", "height_ft",
                                                           "altitude_m", "site_lat", "site_lon", "site_alt")}
    rid = work["radar_id"].cast(pl.Int64).fill_null(-1).to_numpy()
    cols = ("plot_x_m", "plot_y_m", "plot_lat_deg", "plot_lon_deg", "range_m", "azimuth_deg")
    out = {c: np.full(work.height, np.nan) for c in cols}
    for r in np.unique(rid[rid >= 0]):
        m = rid == r
        k = int(np.argmax(m))
        site = (g["site_lat"][k], g["site_lon"][k], g["site_alt"][k])
        sub = {c: v[m] for c, v in g.items()}
        h = np.where(np.isfinite(sub["height_ft"]), sub["height_ft"] * FT,
                     np.where(np.isfinite(sub["altitude_m"]), sub["altitude_m"], site[2]))
        x, y, up, lat, lon = _site_plot(sub, h, geo.LocalFrame(*site), site[2])
        values = (x, y, lat, lon, np.sqrt(x ** 2 + y ** 2 + up ** 2), np.mod(np.degrees(np.arctan2(x, y)), 360.0))
        for c, v in zip(cols, values):
            out[c][m] = v
    return work.with_columns(pl.Series(c, v).fill_nan(None) for c, v in out.items())


def cat020_reports(raw: pl.DataFrame, sites: pl.DataFrame | None, day0: float | None, stale_s: float
                   ) -> tuple[pl.DataFrame, Rejects, dict[str, int]]:
    """CAT020 target reports → (reports of sensors of kind ``mlat``, rejects, counts)."""
    counts = {"cat020_records": raw.height}
    frame = raw.with_columns((pl.col("tod") / 128.0).alias("tod_s"))
    frame = frame.with_columns(pl.when(pl.col("tod") >= 0).then(pl.col("tod_s")).alias("tod_s"))
    frame = _dedup(_times(frame, day0), counts, "cat020")
    frame = frame.with_columns(altitude_m=pl.col("fl_valid") * 100.0 * FT)
    work = _flags(_mlat_geometry(_with_sites(frame, sites)), stale_s)
    reasons = _site_reasons("020", "tod") + [
        (pl.col("lat_deg").is_null() & pl.col("x_m").is_null(), "no I020/041 or I020/042 (position)"),
        ((pl.col("lat_deg").abs() > 90) | (pl.col("lon_deg").abs() > 180),
         pl.format("I020/041 position {}, {} off the globe", pl.col("lat_deg"), pl.col("lon_deg"))),
        (pl.col("trn") < 0, "no I020/161 (track number)"),
        (pl.col("radar_id").is_not_null() & (pl.col("kind") != "mlat"),
         pl.format("SAC/SIC {}/{} is not of kind mlat in the sites file", pl.col("sac"), pl.col("sic"))),
    ]
    good, rej = _split(work, reasons, "CAT020")
    good = good.with_columns((pl.col("height_ft") * FT).alias("plot_height_m"),
                             pl.col("sigma_x_m").alias("plot_sigma_x_m"), pl.col("sigma_y_m").alias("plot_sigma_y_m"),
                             pl.col("sigma_xy_m").alias("plot_sigma_xy_m"))
    counts |= {"cat020_reports": good.height, "cat020_rejected": len(rej)}
    return _reports(good, list(MLAT_PLOT_COLUMNS)), rej, counts


# --------------------------------------------------------------------------- CAT021 of ADS-B ground stations


def adsb_station_rows(cat021: pl.DataFrame, sites: pl.DataFrame | None) -> pl.Series:
    """Per CAT021 record: whether its SAC/SIC is an ADS-B ground station (kind "adsb") of the
    sites file."""
    if sites is None or "kind" not in sites.columns or cat021.height == 0:
        return pl.Series("adsb", np.zeros(cat021.height, bool))
    st = sites.filter(pl.col("kind") == ADSB).select("sac", "sic", pl.lit(True).alias("adsb"))
    return cat021.select("sac", "sic").join(st, on=["sac", "sic"], how="left", maintain_order="left")["adsb"] \
        .fill_null(False)


def cat021_reports(raw: pl.DataFrame, sites: pl.DataFrame | None, day0: float | None, stale_s: float
                   ) -> tuple[pl.DataFrame, Rejects, dict[str, int]]:
    """CAT021 records of ADS-B ground stations (:func:`adsb_station_rows`) → (reports, rejects,
    counts); the geometry and the flags as for CAT020."""
    counts = {"cat021_station_records": raw.height}
    frame = _dedup(_times(raw, day0), counts, "cat021")
    frame = frame.with_columns(
        trn=pl.col("address"), altitude_m=pl.col("fl") * 100.0 * FT, flight_level=pl.col("fl"),
        mode_s=fastcats.per_value(frame["address"].fill_null(-1).to_numpy(), fastcats.hex6),
        x_m=pl.lit(None, pl.Float64), y_m=pl.lit(None, pl.Float64),
        callsign=pl.col("callsign").str.strip_chars_end(" ").replace("", None))
    work = _flags(_mlat_geometry(_with_sites(frame, sites)), stale_s)
    reasons = _site_reasons("021", "tod") + [
        (pl.col("address").is_null(), "no I021/080 (target address)"),
        (pl.col("lat_deg").is_null(), "no I021/131 or I021/130 (position)"),
        ((pl.col("lat_deg").abs() > 90) | (pl.col("lon_deg").abs() > 180),
         pl.format("I021/131 position {}, {} off the globe", pl.col("lat_deg"), pl.col("lon_deg"))),
    ]
    good, rej = _split(work, reasons, "CAT021")
    sigma = sigma_from_nacp(good["nacp"].cast(pl.Float64).fill_null(np.nan).to_numpy())
    good = good.with_columns(
        (pl.col("height_ft") * FT).alias("plot_height_m"), pl.Series("plot_sigma_x_m", sigma).fill_nan(None),
        pl.Series("plot_sigma_y_m", sigma).fill_nan(None),
        pl.Series("plot_sigma_xy_m", np.where(np.isfinite(sigma), 0.0, np.nan)).fill_nan(None),
        *(pl.col(c).cast(pl.UInt8).alias(f"adsb_{c}") for c in ("nacp", "nic", "sil")))
    counts |= {"cat021_reports": good.height, "cat021_rejected": len(rej)}
    return _reports(good, [*MLAT_PLOT_COLUMNS, *ADSB_QUALITY_COLUMNS]), rej, counts


# --------------------------------------------------------------------------- CAT004


#: an episode's key: the SDPS, its alert identifier, the (ordered) pair of tracks
_ALERT_KEY = ("sac", "sic", "alert_id", "id_a", "id_b")
#: CAT004 raw identities per aircraft: AI callsign, MS Mode S identification, M3 Mode 3/A
_IDS = ("ai", "ms", "m3")
ALERT_EXTRA = {"alert_id": pl.UInt32, "callsign_a": pl.String, "callsign_b": pl.String, "mode_s_ident_a": pl.String,
               "mode_s_ident_b": pl.String, "mode_3a_a": pl.String, "mode_3a_b": pl.String}


def _stca_messages(raw: pl.DataFrame, day0: float | None, counts: dict[str, int]) -> tuple[pl.DataFrame, Rejects]:
    """The distinct, usable STCA messages with absolute times, each pair ordered (id_a < id_b,
    the identities of each aircraft with its track), and the rejects."""
    frame = raw.filter(pl.col("message_type") == STCA).with_columns(
        pl.when(pl.col("tod") >= 0).then(pl.col("tod") / 128.0).alias("tod_s"))
    frame = _dedup(_times(frame, day0), counts, "cat004")
    reasons = [(pl.col("sac") < 0, "no I004/010 (SAC/SIC)"), (pl.col("tod_s").is_null(), "no I004/020 (time)"),
               (pl.col("tod_s") >= DAY, pl.format("time of day {} s not below 86400", pl.col("tod_s"))),
               ((pl.col("track_1") < 0) | (pl.col("track_2") < 0), "STCA without I004/030 or I004/035 (tracks)")]
    good, rej = _split(frame, reasons, "CAT004")
    swap = pl.col("track_1") > pl.col("track_2")
    pick = lambda a, b: pl.when(swap).then(pl.col(b)).otherwise(pl.col(a))  # noqa: E731
    good = good.with_columns(
        id_a=pick("track_1", "track_2"), id_b=pick("track_2", "track_1"),
        **{f"{c}_a": pick(f"{c}_1", f"{c}_2") for c in _IDS}, **{f"{c}_b": pick(f"{c}_2", f"{c}_1") for c in _IDS},
    ).with_columns(pl.col(f"{c}_{k}").replace(-1, None) for c in _IDS for k in "ab")
    return good, rej


def _episodes(msgs: pl.DataFrame, gap_s: float) -> pl.DataFrame:
    """One row per episode: messages of one key in time order, split where they stop for more
    than ``gap_s`` (sorted by key and time, so no window function is needed)."""
    msgs = msgs.sort(*_ALERT_KEY, "t")
    run = pl.struct(_ALERT_KEY).rle_id()
    msgs = msgs.with_columns(((run.diff().fill_null(1) != 0) | (pl.col("t").diff() > gap_s)).cum_sum().alias("__ep"))
    eps = msgs.group_by("__ep", maintain_order=True).agg(
        *(pl.col(c).first() for c in _ALERT_KEY), pl.col("t").min().alias("t0"), pl.col("t").max().alias("t1"),
        pl.len().alias("alert_epochs"), pl.col("mhs_m").min().alias("r_min_pred_m"),
        (pl.col("mvs_ft").min() * FT).alias("dz_min_pred_m"), pl.col("tca_s").first().alias("t_min_first_s"),
        *(pl.col(f"{c}_{k}").drop_nulls().first() for c in _IDS for k in "ab"))
    return fastcats.identities(eps, ("a", "b"))


def alerts_table(raw: pl.DataFrame, day0: float | None, gap_s: float = 30.0
                 ) -> tuple[pl.DataFrame, Rejects, dict[str, int]]:
    """CAT004 STCA messages → ``alerts`` rows (picture ``external:SAC/SIC``, unscored): one
    episode per SDPS, alert identifier and track pair, split where messages stop for more than
    ``gap_s``; other message types are counted, not kept."""
    counts = {"cat004_records": raw.height, "cat004_other_types": int((raw["message_type"] != STCA).sum())}
    msgs, rej = _stca_messages(raw, day0, counts)
    us = lambda c: (pl.col(c) * 1e6).round().cast(pl.Int64).cast(TIME)  # noqa: E731
    alerts = _episodes(msgs, gap_s).select(
        pl.lit(0, pl.UInt32).alias("run"), pl.format("external:{}/{}", "sac", "sic").alias("method"),
        pl.col("id_a").cast(pl.UInt64), pl.col("id_b").cast(pl.UInt64), pl.lit(None, pl.Int64).alias("truth_a"),
        pl.lit(None, pl.Int64).alias("truth_b"), us("t0").alias("t_start"), us("t1").alias("t_end"),
        (pl.col("t1") - pl.col("t0")).alias("duration_s"), pl.col("alert_epochs").cast(pl.UInt32),
        pl.lit(0, pl.UInt32).alias("flicker"), "r_min_pred_m", "dz_min_pred_m", "t_min_first_s",
        pl.lit(None, TIME).alias("los_start"), pl.lit(None, pl.Float64).alias("warning_s"),
        pl.lit(UNSCORED).alias("classification"), pl.col("alert_id").cast(pl.UInt32),
        *(c for c in ALERT_EXTRA if c != "alert_id"))
    alerts = alerts.cast(dict(TABLES["alerts"].required)).sort("method", "t_start", "id_a", "id_b")
    counts |= {"cat004_alerts": alerts.height, "cat004_rejected": len(rej)}
    return alerts, rej, counts
