"""Tables → ASTERIX bytes with libasterix: reports of radars as CAT048 (+ CAT034 north markers
per scan), of MLAT sensors as CAT020, of ADS-B ground stations as CAT021 under the station's
SAC/SIC; truth as CAT021 under a SAC/SIC no sensor has (:func:`truth_sac_sic`); pictures as
CAT062 system tracks; alerts as CAT004.

Values are rounded to the item's resolution by libasterix (I048/040: 1/256 NM, 360/2¹⁶ °;
I048/140, I020/140, I021/071: 1/128 s; I048/090, I020/090, I021/145: 1/4 FL; I020/041: 180/2²⁵ °;
I020/042: 0.5 m; I020/500: 0.25 m; I021/131: 180/2³⁰ °). A value outside an item's range would
wrap silently in the bit field, so it is refused here with the rows named; the Comm-B registers
of I048/250 are the exception: their fields saturate at their limits, as Doc 9871 has an
aircraft send a parameter beyond a field's range (:mod:`tertiary.io.asterix.commb`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl

from tertiary.core import geo
from tertiary.io.asterix import codec, commb
from tertiary.io.asterix.sites import sites_toml
from tertiary.core.units import FT
from tertiary.core.errors import DataError
from tertiary.store.run_store import atomic_path, write_text_atomic

#: SAC/SIC of the truth's CAT021 when no sensor has it (else :func:`truth_sac_sic` picks another)
ADSB_SAC_SIC = (0, 250)
#: I020/500 SDP and the ADS-B quality indicators of I021/090 (2.x): field ranges
SDP_MAX_M = (2**16 - 1) * 0.25
NACP_MAX, NIC_MAX, SIL_MAX = 15, 15, 3


def _seconds(col: pl.Series) -> np.ndarray:
    return col.cast(pl.Datetime("us", "UTC")).dt.epoch("us").to_numpy() / 1e6


def _check(ok: np.ndarray, what: str, table: str) -> None:
    if not ok.all():
        rows = np.flatnonzero(~ok)
        raise DataError(f"{table}: {len(rows)} row(s) cannot be encoded: {what} (e.g. row {rows[0]})")


def sac_sic(radar_ids: pl.Series) -> tuple[np.ndarray, np.ndarray]:
    """SAC/SIC of radar ids (id = SAC · 256 + SIC, the importer's default); ids ≥ 2¹⁶ are refused."""
    ids = radar_ids.cast(pl.Int64).to_numpy()
    _check(ids < 65536, "radar_id above 65535 has no SAC/SIC", "radars")
    return ids // 256, ids % 256


def cat048(reports: pl.DataFrame) -> list[object]:
    """CAT048 records of ``reports`` (one run), in time order. I048/250 carries the BDS 4,0
    (``selected_alt_m``), 5,0 (``ehs_roll_deg``, ``ehs_track_deg``, ``ehs_gs_mps``,
    ``ehs_track_rate_dps``) and 6,0 (``ehs_vrate_mps``, as the inertial vertical velocity)
    registers of a row that has any of their columns (:func:`tertiary.io.asterix.commb.registers`)."""
    s = codec.spec(48).cv_record
    rep = reports.sort("time")
    rng_nm = rep["range_m"].to_numpy() / codec.NM
    _check((rng_nm >= 0) & (rng_nm < 256 - 1 / 512), "range beyond 256 NM (I048/040)", "reports")
    trk = rep["local_track_id"].cast(pl.Int64).to_numpy()
    _check(trk < 4096, "local_track_id above 4095 (I048/161 has 12 bits)", "reports")
    sac, sic = sac_sic(rep["radar_id"])
    tod = np.fmod(_seconds(rep["time"]), 86400.0)
    alt = rep["altitude_m"].fill_null(np.nan).to_numpy() if "altitude_m" in rep.columns else np.full(rep.height, np.nan)
    fl = alt / FT / 100.0
    _check(~np.isfinite(fl) | ((fl >= -12) & (fl < 1500)), "altitude outside FL -12..1500 (I048/090)", "reports")
    get = lambda c: rep[c].to_list() if c in rep.columns else [None] * rep.height  # noqa: E731
    az = np.mod(rep["azimuth_deg"].to_numpy(), 360.0)
    mb = commb.registers({c: _floats(rep, c) for c in commb.COLUMNS}, rep.height)
    out = []
    for i, (m3a, ms, cs) in enumerate(zip(get("mode_3a"), get("mode_s"), get("callsign"))):
        items: dict[str, object] = {
            "010": (("SAC", int(sac[i])), ("SIC", int(sic[i]))), "140": float(tod[i]),
            "020": ((5 if ms else 2) << 4,),   # first octet TYP|SIM|RDP|SPI|RAB: Mode S roll-call / SSR
            "040": (("RHO", float(rng_nm[i])), ("THETA", float(az[i]))),
            "161": (0, ("TRN", int(trk[i]))), "170": (2 << 4,),     # CNF=0 confirmed, RAD=2 SSR/Mode S track
        }
        if m3a:
            items["070"] = (0, 0, 0, 0, ("MODE3A", str(m3a).zfill(4)))
        if math.isfinite(fl[i]):
            items["090"] = (("V", 0), ("G", 0), ("FL", float(fl[i])))
        if ms:
            items["220"] = int(ms, 16)
        if cs:
            items["240"] = str(cs)[:8].ljust(8)
        regs = [(("MBDATA", int(v[i])), ("BDS1", bds >> 4), ("BDS2", bds & 15)) for bds, v in mb.items() if v[i] >= 0]
        if regs:
            items["250"] = regs
        out.append(s.create(items))
    return out


def cat034_north(radars: pl.DataFrame, t0: float, t1: float) -> list[tuple[float, object]]:
    """(time, CAT034 north marker) of every scan of every radar in [t0, t1] (I034/041 sent)."""
    s = codec.spec(34).cv_record
    out = []
    for r in radars.iter_rows(named=True):
        period = float(r["scan_period_s"])
        phase = float(r.get("scan_phase_s") or 0.0)
        k0 = math.ceil((t0 - phase) / period)
        sac, sic = int(r["radar_id"]) // 256, int(r["radar_id"]) % 256
        for k in range(k0, int(math.floor((t1 - phase) / period)) + 1):
            t = phase + k * period
            out.append((t, s.create({"010": (("SAC", sac), ("SIC", sic)), "000": 1,
                                     "030": float(math.fmod(t, 86400.0)), "041": period})))
    return out


def truth_sac_sic(radar_ids: pl.Series | None = None) -> tuple[int, int]:
    """SAC/SIC of the truth's CAT021: 0/250 (:data:`ADSB_SAC_SIC`), else the first of 0/251 … 0/255,
    0/249 … 0/0 that no sensor of ``radar_ids`` has (id = SAC·256 + SIC). The importer reads CAT021
    of a SAC/SIC that is not an ADS-B station of the sites file as truth."""
    taken = set() if radar_ids is None else set(radar_ids.cast(pl.Int64).to_list())
    for sic in (*range(250, 256), *range(249, -1, -1)):
        if sic not in taken:
            return 0, sic
    raise DataError("no SAC/SIC 0/x is free for the truth's CAT021: the sensors take 0/0 … 0/255")


def _ints(frame: pl.DataFrame, col: str) -> np.ndarray:
    """An integer column as int64, -1 where null or absent."""
    if col not in frame.columns:
        return np.full(frame.height, -1, np.int64)
    return frame[col].cast(pl.Int64).fill_null(-1).to_numpy()


def _floats(frame: pl.DataFrame, col: str) -> np.ndarray:
    """A float column, NaN where null or absent."""
    if col not in frame.columns:
        return np.full(frame.height, np.nan)
    return frame[col].cast(pl.Float64).fill_null(np.nan).to_numpy()


def _texts(frame: pl.DataFrame, col: str) -> list[object]:
    return frame[col].to_list() if col in frame.columns else [None] * frame.height


def quality_090(nic: np.ndarray, nacp: np.ndarray, sil: np.ndarray, table: str) -> list[tuple[int, ...] | None]:
    """I021/090 (2.x) octets per row, without their FX bits: octet 1 NUCr/NACv (3 bits, 0) |
    NUCp/NIC (4), octet 2 NICbaro (1, 0) | SIL (2) | NACp (4). Octet 2 is sent when NACp or SIL is
    known, octet 1 when any is (an unknown one of a sent octet is 0, "unknown"); -1 = unknown."""
    for v, hi, name in ((nic, NIC_MAX, "NIC"), (nacp, NACP_MAX, "NACp"), (sil, SIL_MAX, "SIL")):
        _check(v <= hi, f"{name} above {hi} (I021/090)", table)
    o1 = np.maximum(nic, 0)
    o2 = (np.maximum(sil, 0) << 4) | np.maximum(nacp, 0)
    two = (nacp >= 0) | (sil >= 0)
    one = two | (nic >= 0)
    return [(int(a), int(b)) if t else (int(a),) if o else None for a, b, t, o in zip(o1, o2, two, one)]


def cat021(truth: pl.DataFrame, system: geo.LocalFrame, sac_sic: tuple[int, int] = ADSB_SAC_SIC
           ) -> list[tuple[float, object]]:
    """(time, CAT021 record) per truth row under ``sac_sic``: address = icao24 (else truth_id),
    I021/131 position, I021/140 geometric height, I021/145 flight level (from alt_m), I021/160
    ground vector and I021/157 geometric rate in the aircraft's local ENU frame, I021/090 when the
    rows carry ``nacp``, ``nic`` or ``sil`` (:func:`quality_090`)."""
    s = codec.spec(21).cv_record
    x, y, z = (truth[c].to_numpy() for c in ("x_m", "y_m", "z_m"))
    lat, lon, h = system.to_geodetic(x, y, z)
    # velocity system frame → local ENU at the aircraft: the transpose of importer.enu_velocity
    r = system.rotation
    v = [truth[c].to_numpy() for c in ("vx_mps", "vy_mps", "vz_mps")]
    ex, ey, ez = (r[0, j] * v[0] + r[1, j] * v[1] + r[2, j] * v[2] for j in range(3))
    la, lo = np.radians(lat), np.radians(lon)
    ve = -np.sin(lo) * ex + np.cos(lo) * ey
    vn = -np.sin(la) * np.cos(lo) * ex - np.sin(la) * np.sin(lo) * ey + np.cos(la) * ez
    vu = np.cos(la) * np.cos(lo) * ex + np.cos(la) * np.sin(lo) * ey + np.sin(la) * ez
    gs, ta = np.hypot(ve, vn) / codec.NM, np.degrees(np.arctan2(ve, vn)) % 360.0
    t = _seconds(truth["time"])
    icao = _texts(truth, "icao24")
    addr = [int(a, 16) if a else int(tid) for a, tid in zip(icao, truth["truth_id"].to_list())]
    _check(np.array([0 <= a < 2**24 for a in addr]), "address (icao24 or truth_id) beyond 24 bits", "truth")
    alt = _floats(truth, "alt_m")
    calls = _texts(truth, "callsign")
    q090 = quality_090(_ints(truth, "nic"), _ints(truth, "nacp"), _ints(truth, "sil"), "truth")
    out = []
    for i in range(truth.height):
        items: dict[str, object] = {
            "010": (("SAC", sac_sic[0]), ("SIC", sac_sic[1])), "040": (0,),
            "071": float(math.fmod(t[i], 86400.0)), "080": addr[i],
            "131": (("LAT", float(lat[i])), ("LON", float(lon[i]))), "140": float(h[i] / FT),
            "160": (("RE", 0), ("GS", float(gs[i])), ("TA", float(ta[i]))),
            "157": (("RE", 0), ("GVR", float(vu[i] / FT * 60.0))),
        }
        if math.isfinite(alt[i]):
            items["145"] = float(alt[i] / FT / 100.0)
        if calls[i]:
            items["170"] = str(calls[i])[:8].ljust(8)
        if q090[i] is not None:
            items["090"] = q090[i]
        out.append((t[i], s.create(items)))
    return out


def _flight_levels(rep: pl.DataFrame, item: str) -> np.ndarray:
    """``altitude_m`` as flight levels (NaN where null), refused outside FL -12 … 1500."""
    fl = _floats(rep, "altitude_m") / FT / 100.0
    _check(~np.isfinite(fl) | ((fl >= -12) & (fl < 1500)), f"altitude outside FL -12..1500 ({item})", "reports")
    return fl


def cat020(reports: pl.DataFrame) -> list[tuple[float, object]]:
    """(time, CAT020 record) per report of an MLAT sensor (edition 1.11): I020/010 SAC/SIC of its
    radar_id, /020 Mode S multilateration, /140 time of day, /041 WGS-84 (``plot_lat_deg``,
    ``plot_lon_deg``) and /042 Cartesian (``plot_x_m``, ``plot_y_m``) plot, each when the row
    has it, /161 ``local_track_id``, /500 SDP (σx, σy, σxy from the plot σ columns: σ clipped at
    16 383.75 m; libasterix's XY is unsigned, so a negative σxy term is sent as 0), /105
    ``plot_height_m``, /090 flight level (``altitude_m``), /070, /220, /245 identities."""
    s = codec.spec(20).cv_record
    rep = reports.sort("time")
    t = _seconds(rep["time"])
    sac, sic = sac_sic(rep["radar_id"])
    lat, lon, x, y = (_floats(rep, c) for c in ("plot_lat_deg", "plot_lon_deg", "plot_x_m", "plot_y_m"))
    wgs, cart = np.isfinite(lat) & np.isfinite(lon), np.isfinite(x) & np.isfinite(y)
    _check(wgs | cart, "MLAT report without a plot (plot_lat_deg, plot_lon_deg or plot_x_m, plot_y_m)", "reports")
    _check(~cart | ((np.abs(x) < 2**22) & (np.abs(y) < 2**22)), "plot beyond ±4 194 km (I020/042)", "reports")
    trk = _ints(rep, "local_track_id")
    _check(trk < 4096, "local_track_id above 4095 (I020/161 has 12 bits)", "reports")
    sx, sy, sxy = (_floats(rep, c) for c in ("plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m"))
    sdp = np.isfinite(sx) & np.isfinite(sy)
    sx, sy = np.clip(np.nan_to_num(sx), 0.0, SDP_MAX_M), np.clip(np.nan_to_num(sy), 0.0, SDP_MAX_M)
    sxy = np.clip(np.nan_to_num(sxy), 0.0, SDP_MAX_M)
    hft = _floats(rep, "plot_height_m") / FT
    _check(~np.isfinite(hft) | (np.abs(hft) < 2**15 * 6.25), "plot_height_m beyond ±204 800 ft (I020/105)", "reports")
    fl = _flight_levels(rep, "I020/090")
    tod = np.fmod(t, 86400.0)
    m3a, ms, cs = _texts(rep, "mode_3a"), _texts(rep, "mode_s"), _texts(rep, "callsign")
    out = []
    for i in range(rep.height):
        items: dict[str, object] = {"010": (("SAC", int(sac[i])), ("SIC", int(sic[i]))), "020": (0x40,),
                                    "140": float(tod[i]), "161": (0, ("TRN", int(trk[i])))}
        if wgs[i]:
            items["041"] = (("LAT", float(lat[i])), ("LON", float(lon[i])))
        if cart[i]:
            items["042"] = (("X", float(x[i])), ("Y", float(y[i])))
        if sdp[i]:
            items["500"] = {"SDP": (("X", float(sx[i])), ("Y", float(sy[i])), ("XY", float(sxy[i])))}
        if math.isfinite(hft[i]):
            items["105"] = float(hft[i])
        if math.isfinite(fl[i]):
            items["090"] = (("V", 0), ("G", 0), ("FL", float(fl[i])))
        if m3a[i]:
            items["070"] = (0, 0, 0, 0, ("MODE3A", str(m3a[i]).zfill(4)))
        if ms[i]:
            items["220"] = int(ms[i], 16)
        if cs[i]:
            items["245"] = (("STI", 2), 0, ("CHR", str(cs[i])[:8].ljust(8)))
        out.append((float(t[i]), s.create(items)))
    return out


def _station_wgs84(rep: pl.DataFrame, radars: pl.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """(lat, lon) of each ADS-B report: ``plot_lat_deg``, ``plot_lon_deg`` where given, else its
    ``plot_x_m``, ``plot_y_m`` in the station's ENU frame at its height (``plot_height_m``, else
    ``altitude_m``, else the site's), station by station."""
    lat, lon, x, y = (_floats(rep, c) for c in ("plot_lat_deg", "plot_lon_deg", "plot_x_m", "plot_y_m"))
    need = ~(np.isfinite(lat) & np.isfinite(lon)) & np.isfinite(x) & np.isfinite(y)
    if need.any():
        h = np.where(np.isfinite(_floats(rep, "plot_height_m")), _floats(rep, "plot_height_m"),
                     _floats(rep, "altitude_m"))
        rid = rep["radar_id"].cast(pl.Int64).to_numpy()
        for r in radars.filter(pl.col("radar_id").cast(pl.Int64).is_in(np.unique(rid[need]).tolist())
                               ).iter_rows(named=True):
            m = need & (rid == int(r["radar_id"]))
            site = geo.LocalFrame(float(r["lat_deg"]), float(r["lon_deg"]), float(r["alt_m"]))
            hh = np.where(np.isfinite(h[m]), h[m], float(r["alt_m"]))
            up = geo.up_at_height(site, x[m], y[m], hh)
            lat[m], lon[m], _ = site.to_geodetic(x[m], y[m], up)
    return lat, lon


def cat021_reports(reports: pl.DataFrame, radars: pl.DataFrame) -> list[tuple[float, object]]:
    """(time, CAT021 record) per report of an ADS-B ground station (edition 2.7) under the
    station's SAC/SIC: I021/080 address (``mode_s``), /071 time of applicability for position,
    /131 position (:func:`_station_wgs84`), /140 ``plot_height_m``, /145 flight level
    (``altitude_m``), /090 NIC, SIL, NACp (``adsb_nic``, ``adsb_sil``, ``adsb_nacp``,
    :func:`quality_090`), /070 Mode 3/A, /170 callsign. CAT021 has no position σ: the plot σ
    columns are not sent (the importer takes σ from NACp)."""
    s = codec.spec(21).cv_record
    rep = reports.sort("time")
    t = _seconds(rep["time"])
    sac, sic = sac_sic(rep["radar_id"])
    lat, lon = _station_wgs84(rep, radars)
    _check(np.isfinite(lat) & np.isfinite(lon), "ADS-B report without a plot (plot_lat_deg, plot_lon_deg or "
           "plot_x_m, plot_y_m)", "reports")
    ms = _texts(rep, "mode_s")
    _check(np.array([bool(a) for a in ms], bool), "ADS-B report without mode_s (I021/080 address)", "reports")
    hft = _floats(rep, "plot_height_m") / FT
    _check(~np.isfinite(hft) | (np.abs(hft) < 2**15 * 6.25), "plot_height_m beyond ±204 800 ft (I021/140)", "reports")
    fl = _flight_levels(rep, "I021/145")
    q090 = quality_090(_ints(rep, "adsb_nic"), _ints(rep, "adsb_nacp"), _ints(rep, "adsb_sil"), "reports")
    m3a, cs = _texts(rep, "mode_3a"), _texts(rep, "callsign")
    tod = np.fmod(t, 86400.0)
    out = []
    for i in range(rep.height):
        items: dict[str, object] = {
            "010": (("SAC", int(sac[i])), ("SIC", int(sic[i]))), "040": (0,), "071": float(tod[i]),
            "080": int(str(ms[i]), 16), "131": (("LAT", float(lat[i])), ("LON", float(lon[i])))}
        if math.isfinite(hft[i]):
            items["140"] = float(hft[i])
        if math.isfinite(fl[i]):
            items["145"] = float(fl[i])
        if q090[i] is not None:
            items["090"] = q090[i]
        if m3a[i]:
            items["070"] = (0, ("MODE3A", str(m3a[i]).zfill(4)))
        if cs[i]:
            items["170"] = str(cs[i])[:8].ljust(8)
        out.append((float(t[i]), s.create(items)))
    return out


def interleave(items: list[tuple[float, int, object]], max_bytes: int = 1400) -> bytes:
    """(time, category, record) → data blocks in time order; consecutive records of one category
    share a block of at most ``max_bytes``."""
    items = sorted(items, key=lambda x: x[0])
    out, batch, cat, size = [], [], None, 3
    for _t, c, rec in items:
        n = len(rec.unparse().to_bytes())
        if batch and (c != cat or size + n > max_bytes):
            out.append(codec.datablock(cat, batch))
            batch, size = [], 3
        batch.append(rec)
        cat, size = c, size + n
    if batch:
        out.append(codec.datablock(cat, batch))
    return b"".join(out)


def _kinds(radars: pl.DataFrame) -> pl.DataFrame:
    """``radars`` with ``kind`` filled ("radar" where absent or null)."""
    kind = pl.col("kind").fill_null("radar") if "kind" in radars.columns else pl.lit("radar")
    return radars.with_columns(kind.alias("kind"))


def write_recording(ds: object, out_dir: str | Path) -> tuple[Path, Path, str]:
    """``recording.ast`` and ``sites.toml`` beside the Parquet files of a dataset. The recording
    holds, in time order, the reports of run 0 (radars: CAT048, with a CAT034 north marker per
    scan; MLAT sensors: CAT020; ADS-B ground stations: CAT021 under the station's SAC/SIC) and
    the truth as CAT021 under :func:`truth_sac_sic`. The sites file names every sensor (``kind``
    for MLAT and ADS-B). Returns the two paths and the date (YYYY-MM-DD) the recording starts on,
    for ``import --date``."""
    reports: pl.DataFrame = ds.reports  # type: ignore[attr-defined]
    radars: pl.DataFrame = _kinds(ds.radars)  # type: ignore[attr-defined]
    truth: pl.DataFrame = ds.truth  # type: ignore[attr-defined]
    if "run" in reports.columns:
        reports = reports.filter(pl.col("run") == 0)
    if reports.height == 0:
        raise DataError("no report of run 0 to encode", path=str(out_dir))
    unknown = sorted(set(radars["kind"].unique().to_list()) - {"radar", "mlat", "adsb"})
    if unknown:
        raise DataError(f"radars of kind {', '.join(map(str, unknown))} have no ASTERIX category here",
                        path=str(out_dir))
    kind = reports.select("radar_id").join(radars.select(pl.col("radar_id").cast(reports["radar_id"].dtype), "kind"),
                                           on="radar_id", how="left", maintain_order="left")["kind"].fill_null("radar")
    t = _seconds(reports["time"])
    t0, t1 = float(t.min()), float(t.max())
    items: list[tuple[float, int, object]] = []
    radar_rows = reports.filter(kind == "radar")
    if radar_rows.height:
        ts = _seconds(radar_rows.sort("time")["time"])
        items += [(float(ti), 48, r) for ti, r in zip(ts, cat048(radar_rows))]
    items += [(ti, 34, r) for ti, r in cat034_north(radars.filter(pl.col("kind") == "radar"), t0, t1)]
    items += [(ti, 20, r) for ti, r in cat020(reports.filter(kind == "mlat"))]
    items += [(ti, 21, r) for ti, r in cat021_reports(reports.filter(kind == "adsb"), radars)]
    if truth.height:
        code = truth_sac_sic(radars["radar_id"])
        items += [(float(ti), 21, r) for ti, r in cat021(truth, ds.origin, code)]  # type: ignore[attr-defined]
    d = Path(out_dir)
    rec_path, sites_path = d / "recording.ast", d / "sites.toml"
    with atomic_path(rec_path) as tmp:
        tmp.write_bytes(interleave(items))
    sac, sic = sac_sic(radars["radar_id"])
    sites = radars.select("radar_id", "name", "kind", "lat_deg", "lon_deg", "alt_m", "sigma_range_m",
                          "sigma_azimuth_deg", "max_range_m", "sigma_elevation_deg", "scan_period_s")
    write_text_atomic(sites_path, sites_toml(sites.with_columns(pl.Series("sac", sac), pl.Series("sic", sic))))
    day = reports["time"].min().strftime("%Y-%m-%d")  # type: ignore[union-attr]
    return rec_path, sites_path, day


def cat062(tracks: pl.DataFrame, system: geo.LocalFrame, sac: int = 0, sic: int = 1) -> list[tuple[float, object]]:
    """(time, CAT062 record) per picture row (``tracks`` schema, system frame): I062/040 track
    number (track_id mod 2¹⁶), /070 time of track, /105 WGS-84 and /100 Cartesian position (the
    system frame), /185 velocity, /130 geometric height, /136 flight level (alt_m), /220 rate,
    /080 track status, /060, /380 ADR + ID when the picture carries them, /500 accuracies
    (σ from ``cov_diag``, clipped to each field's range) when it has them (a lean run does not
    store them)."""
    s = codec.spec(62).cv_record
    x, y, z = (tracks[c].to_numpy() for c in ("x_m", "y_m", "z_m"))
    lat, lon, h = system.to_geodetic(x, y, z)
    t = _seconds(tracks["epoch"])
    vx, vy, vz = (tracks[c].to_numpy() for c in ("vx_mps", "vy_mps", "vz_mps"))
    _check((np.abs(x) < 2**23 * 0.5) & (np.abs(y) < 2**23 * 0.5), "position beyond ±4 194 km (I062/100)", "tracks")
    _check((np.abs(vx) < 8192) & (np.abs(vy) < 8192), "speed beyond 8 192 m/s (I062/185)", "tracks")
    accuracy = "cov_diag" in tracks.columns
    cov = np.stack(tracks["cov_diag"].to_numpy()) if tracks.height and accuracy else np.zeros((tracks.height, 6))
    sig = np.sqrt(np.clip(np.nan_to_num(cov, nan=0.0), 0.0, None))
    alt = tracks["alt_m"].fill_null(np.nan).to_numpy() if "alt_m" in tracks.columns else np.full(tracks.height, np.nan)
    col = lambda c: tracks[c].to_list() if c in tracks.columns else [None] * tracks.height  # noqa: E731
    m3a, ms, cs = col("mode_3a"), col("mode_s"), col("callsign")
    ids = tracks["track_id"].cast(pl.Int64).to_numpy() % 65536
    out = []
    for i in range(tracks.height):
        items: dict[str, object] = {
            "010": (("SAC", sac), ("SIC", sic)), "040": int(ids[i]), "070": float(math.fmod(t[i], 86400.0)),
            "105": (("LAT", float(lat[i])), ("LON", float(lon[i]))), "100": (("X", float(x[i])), ("Y", float(y[i]))),
            "185": (("VX", float(vx[i])), ("VY", float(vy[i]))), "130": float(h[i] / FT),
            "220": float(np.clip(vz[i] / FT * 60.0, -204800, 204799)),
            "080": (0,),
        }
        if accuracy:
            items["500"] = {"APC": (("X", float(min(sig[i, 0], 32767.0))), ("Y", float(min(sig[i, 1], 32767.0)))),
                            "AGA": float(min(sig[i, 2] / FT, 1593.0)),
                            "ATV": (("X", float(min(sig[i, 3], 63.75))), ("Y", float(min(sig[i, 4], 63.75)))),
                            "ARC": float(min(sig[i, 5] / FT * 60.0, 1593.0))}
        if math.isfinite(alt[i]):
            items["136"] = float(alt[i] / FT / 100.0)
        if m3a[i]:
            items["060"] = (0, 0, 0, 0, ("MODE3A", str(m3a[i]).zfill(4)))
        adr: dict[str, object] = {}
        if ms[i]:
            adr["ADR"] = int(ms[i], 16)
        if cs[i]:
            adr["ID"] = str(cs[i])[:8].ljust(8)
        if adr:
            items["380"] = adr
        out.append((t[i], s.create(items)))
    return out


def export_picture(tracks: pl.DataFrame, system: geo.LocalFrame, out: str | Path) -> int:
    """Write a picture as CAT062 data blocks to ``out`` (atomic); returns the record count."""
    recs = cat062(tracks.sort("epoch", "track_id"), system)
    with atomic_path(Path(out)) as tmp:
        tmp.write_bytes(interleave([(t, 62, r) for t, r in recs]))
    return len(recs)


#: the update cycle of an exported STCA alert: an operational STCA repeats each active alert at
#: every cycle, and an importer ends an episode at a silence (``alerts_table``'s gap)
STCA_CYCLE_S = 4.0


def cat004(alerts: pl.DataFrame, sac: int = 0, sic: int = 1, cycle_s: float = STCA_CYCLE_S
           ) -> list[tuple[float, object]]:
    """(time, CAT004 STCA record) per alert episode (``alerts`` schema) and cycle: a message at
    its start, every ``cycle_s`` while it lasts and at its end, each with I004/040 alert identifier (row number mod 2¹⁶, or
    ``alert_id``), /030 and /035 track numbers (id mod 2¹⁶, as the CAT062 export numbers
    tracks), /070 TCA (``t_min_first_s``), MHS (``r_min_pred_m``), MVS (``dz_min_pred_m``) and
    /170, /171 callsign and Mode 3/A when the rows carry them."""
    s = codec.spec(4).cv_record
    rows = alerts.sort("t_start", "id_a", "id_b")
    ids = rows["alert_id"].to_list() if "alert_id" in rows.columns else [None] * rows.height
    get = lambda c: rows[c].to_list() if c in rows.columns else [None] * rows.height  # noqa: E731
    out = []
    for i, r in enumerate(rows.iter_rows(named=True)):
        items: dict[str, object] = {
            "010": (("SAC", sac), ("SIC", sic)), "000": 7, "040": int(ids[i] if ids[i] is not None else i) % 65536,
            "030": int(r["id_a"]) % 65536, "035": int(r["id_b"]) % 65536}
        timing = _timing(r)
        if timing:
            items["070"] = timing
        for item, k, n in (("170", "a", 1), ("171", "b", 2)):
            ident = _identity(get(f"callsign_{k}")[i], get(f"mode_3a_{k}")[i], n)
            if ident:
                items[item] = ident
        t0, t1 = (_seconds(pl.Series([r[c]]))[0] for c in ("t_start", "t_end"))
        for t in sorted({*np.arange(t0, t1, cycle_s).tolist(), t1}):
            out.append((float(t), s.create({**items, "020": float(math.fmod(t, 86400.0))})))
    return out


def _timing(r: dict[str, object]) -> dict[str, object]:
    """I004/070 subfields of an alert row (values outside a subfield's range left out)."""
    out: dict[str, object] = {}
    tca, mhs, mvs = (r.get(k) for k in ("t_min_first_s", "r_min_pred_m", "dz_min_pred_m"))
    if isinstance(tca, float) and 0 <= tca < 2**24 / 128:
        out["TCA"] = tca
    if isinstance(mhs, float) and 0 <= mhs < 2**16 * 0.5:
        out["MHS"] = mhs
    if isinstance(mvs, float) and 0 <= mvs / FT < 2**16 * 25:
        out["MVS"] = mvs / FT
    return out


def _identity(callsign: object, mode_3a: object, n: int) -> dict[str, object]:
    """I004/170 (n = 1) or /171 (n = 2) subfields: AIn callsign, M3n Mode 3/A."""
    out: dict[str, object] = {}
    if callsign:
        out[f"AI{n}"] = str(callsign)[:7].ljust(7)
    if mode_3a:
        out[f"M3{n}"] = (0, ("MODE3A", str(mode_3a).zfill(4)))
    return out


def export_alerts(alerts: pl.DataFrame, out: str | Path, sac: int = 0, sic: int = 1) -> int:
    """Write alert episodes as CAT004 STCA messages to ``out`` (atomic); returns the record count."""
    recs = cat004(alerts, sac, sic)
    with atomic_path(Path(out)) as tmp:
        tmp.write_bytes(interleave([(t, 4, r) for t, r in recs]))
    return len(recs)
