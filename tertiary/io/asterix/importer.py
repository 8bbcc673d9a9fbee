"""ASTERIX recordings → a tertiary dataset (reports, radars, truth, external tracks, rejects).

* CAT048 → ``reports`` (compiled decoder :mod:`tertiary.io.asterix.fast048`, checked against
  libasterix); range ρ = RHO · 1/256 NM, azimuth θ = THETA · 360/2¹⁶ ° (I048/040), flight level
  FL · 1/4 → ``altitude_m`` = FL · 100 ft (I048/090, pressure altitude), I048/161 → local track,
  I048/220, /240, /070, /200, /170, /020 kept; the I048/250 Comm-B registers the radar names BDS
  4,0, 5,0, 6,0 → ``selected_alt_m`` and the EHS columns (:mod:`tertiary.io.asterix.commb`).
* CAT034 → antenna timing per radar (scan period from I034/041, else north-marker intervals,
  else the slope of sector crossings; north-crossing instants).
* CAT021 → ``truth`` (ADS-B reference; points below the reference's declared quality, I021/090
  NACp / NIC, to ``rejects``), except the CAT021 of ADS-B ground stations (sites of kind
  ``adsb``: reports, :mod:`tertiary.io.asterix.plots`); CAT062 → ``external_tracks`` (``tracks``
  schema + ids).
* CAT001, CAT020 → ``reports``, CAT002 → antenna timing, CAT004 → ``alerts``: decoded by
  :mod:`tertiary.io.asterix.fastcats`, built by :mod:`tertiary.io.asterix.plots`.

Time: t = midnight(date) + time of day, the date from ``date`` or else from the capture time
stamp, taking the instant nearest the capture (midnight roll-over either way); without either,
the time of day sequence of a raw file is unwrapped (period 86 400 s) from ``date``.
Redundant lines repeat records byte for byte: the first arrival is kept. A report older than an
earlier report of its local track is flagged ``out_of_order``; older than its radar's latest
earlier report by more than ``stale_s``, ``stale``; both stay in ``reports``. Every block or record that cannot be used is a ``rejects`` row.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import date as Date, datetime, timezone
from pathlib import Path

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.io.asterix import capture, codec, commb, fast048, fastcats, fastwalk
from tertiary.core.units import FT
from tertiary.core.errors import DataError, OptionError
from tertiary.contract import TABLES

DAY = 86400.0
TIME = pl.Datetime("us", "UTC")
#: ICAO 6-bit alphabet ("~" marks codes outside it, dropped as libasterix drops them), hex digits
ICAO_CHARS, HEX = fastcats.ICAO_CHARS, fastcats.HEX


@dataclass
class Decoded:
    """Everything decoded from a set of recordings, before the sites registry is applied."""

    cat048: pl.DataFrame
    cat034: pl.DataFrame
    cat021: pl.DataFrame
    cat062: pl.DataFrame
    rejects: list[dict[str, object]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    #: CAT001 plots/tracks, CAT002 service messages, CAT004 safety-net messages, CAT020 MLAT reports
    cat001: pl.DataFrame = field(default_factory=pl.DataFrame)
    cat002: pl.DataFrame = field(default_factory=pl.DataFrame)
    cat004: pl.DataFrame = field(default_factory=pl.DataFrame)
    cat020: pl.DataFrame = field(default_factory=pl.DataFrame)


# --------------------------------------------------------------------------- time


def absolute_time(tod_s: NDArray[np.float64], capture_s: NDArray[np.float64], day0: float | None) -> NDArray[np.float64]:
    """Seconds since 1970 (UTC) of times of day ``tod_s`` (arrival order).

    With ``day0`` (midnight of the given date, s): the sequence is unwrapped with period 86 400 s
    from that day (a jump back by more than 12 h is a midnight crossing). Else each record takes
    the instant with its time of day nearest its capture time stamp.
    """
    if day0 is not None:
        if len(tod_s) == 0:
            return tod_s.copy()
        return day0 + np.unwrap(tod_s, period=DAY)
    base = np.floor(capture_s / DAY) * DAY
    t = base + tod_s
    t = np.where(t - capture_s > DAY / 2, t - DAY, t)
    return np.where(capture_s - t > DAY / 2, t + DAY, t)


def _midnight(d: Date) -> float:
    return datetime(d.year, d.month, d.day, tzinfo=timezone.utc).timestamp()


# --------------------------------------------------------------------------- decoding


def _reject(out: list[dict[str, object]], reason: str, **detail: object) -> None:
    out.append({"reason": reason, "detail": json.dumps(detail, default=str)})


def _records_libasterix(blocks: list[bytes], where: list[dict[str, object]], rejects: list[dict[str, object]]
                        ) -> list[tuple[int, object]]:
    """(block index, record) of every block libasterix parses; failing blocks to rejects."""
    out = []
    for k, block in enumerate(blocks):
        recs = codec.parse_block(block)
        if isinstance(recs, str):
            _reject(rejects, recs, **where[k], hex=block[:32].hex())
            continue
        out += [(k, r) for r in recs]
    return out


def decode_files(paths: Sequence[str | Path]) -> Decoded:
    """Decode every data block of ``paths`` (pcap, pcapng or raw blocks)."""
    rejects: list[dict[str, object]] = []
    parts: dict[int, list[tuple[bytes, dict[str, object], float, str, int]]] = {c: [] for c in codec.EDITIONS}
    counts = {"datagrams": 0, "blocks": 0}
    for path in paths:
        grams = capture.read_recording(path)
        blocks = capture.split_blocks(grams)
        counts["datagrams"] += len(grams.payloads)
        seq0 = counts["blocks"]          # arrival order of blocks across files (CAT001 time reference)
        counts["blocks"] += len(blocks.data)
        for g, off, reason in blocks.problems:
            _reject(rejects, reason, file=str(path), datagram=g, offset=off)
        for k, (cat, data) in enumerate(zip(blocks.cat, blocks.data)):
            g = int(blocks.datagram[k])
            where = {"file": str(path), "datagram": g, "offset": int(blocks.offset[k])}
            if int(cat) not in parts:
                _reject(rejects, f"category {int(cat)} not supported ({codec.SUPPORTED} are)",
                        **where, hex=data[:32].hex())
                continue
            parts[int(cat)].append((data, where, grams.capture_s[g], grams.line[g], seq0 + k))
    counts |= {f"cat{c:03d}_blocks": len(v) for c, v in parts.items()}
    more = {f"cat{c:03d}": getattr(fastcats, f"decode_{c:03d}")(parts[c], rejects) for c in (1, 2, 4, 20)}
    return Decoded(_decode_048(parts[48], rejects), _decode_034(parts[34], rejects), _decode_021(parts[21], rejects),
                   _decode_062(parts[62], rejects), rejects, counts, **more)


def _decode_048(items: list[tuple[bytes, dict[str, object], float, str]], rejects: list[dict[str, object]]
                ) -> pl.DataFrame:
    raw, block, bad = fast048.decode_blocks([d for d, *_ in items])
    for k, off, reason in bad:
        _reject(rejects, reason, **items[k][1], block_offset=off, hex=items[k][0][:32].hex())
    cols = {name: raw[:, i] for i, name in enumerate(fast048.FIELDS)}
    # per-block attributes gathered to records by block index (a loop over blocks, not records)
    idx = pl.Series(block)
    per_block = pl.DataFrame({
        "capture_s": np.array([it[2] for it in items], float), "line": [it[3] for it in items],
        "file": [str(it[1]["file"]) for it in items], "datagram": [int(it[1]["datagram"]) for it in items],
    }, schema={"capture_s": pl.Float64, "line": pl.String, "file": pl.String, "datagram": pl.Int64})
    return pl.DataFrame(cols).with_columns(pl.Series("block", block), *(per_block[c].gather(idx) for c in per_block.columns))


def _decode_034(items: list[tuple[bytes, dict[str, object], float, str]], rejects: list[dict[str, object]]
                ) -> pl.DataFrame:
    rows = []
    for k, rec in _records_libasterix([d for d, *_ in items], [w for _, w, *_ in items], rejects):
        rows.append({"sac": codec.sub_uint(rec, "010", "SAC"), "sic": codec.sub_uint(rec, "010", "SIC"),
                     "message_type": codec.uint(rec, "000"), "tod_s": codec.qty(rec, "030", "s"),
                     "sector_deg": codec.qty(rec, "020", "°"), "rotation_period_s": codec.qty(rec, "041", "s"),
                     "capture_s": items[k][2], "line": items[k][3], "bytes": rec.unparse().to_bytes()})
    schema = {"sac": pl.Int64, "sic": pl.Int64, "message_type": pl.Int64, "tod_s": pl.Float64,
              "sector_deg": pl.Float64, "rotation_period_s": pl.Float64, "capture_s": pl.Float64,
              "line": pl.String, "bytes": pl.Binary}
    return pl.DataFrame(rows, schema=schema)


_CAT021_SCHEMA = {"sac": pl.Int64, "sic": pl.Int64, "address": pl.Int64, "tod_s": pl.Float64, "lat_deg": pl.Float64,
                  "lon_deg": pl.Float64, "height_ft": pl.Float64, "fl": pl.Float64, "gs_nmps": pl.Float64,
                  "ta_deg": pl.Float64, "gvr_ftpm": pl.Float64, "callsign": pl.String, "capture_s": pl.Float64,
                  "nic": pl.Int64, "nacp": pl.Int64, "sil": pl.Int64, "mode_3a": pl.String, "tod": pl.Int64,
                  "hash": pl.Int64, "length": pl.Int64, "offset": pl.Int64, "line": pl.String, "file": pl.String,
                  "datagram": pl.Int64}


def _decode_021(items: list[tuple[bytes, dict[str, object], float, str]], rejects: list[dict[str, object]]
                ) -> pl.DataFrame:
    """CAT021 2.7 records with the compiled walker and numpy field reads (units as libasterix's:
    I021/071, /073 1/128 s; /131 180/2³⁰ °, /130 180/2²³ °; /140 6.25 ft; /145 1/4 FL; /160 GS
    2⁻¹⁴ NM/s, TA 360/2¹⁶ °; /157 6.25 ft/min; /170 ICAO characters; /090 octet 1 bits 4-1
    NUCp/NIC, octet 2 (when octet 1's FX is set) bits 6-5 SIL, 4-1 NACp; /070 12-bit code)."""
    if not items:
        return pl.DataFrame(schema=_CAT021_SCHEMA)
    prog = _program(21)
    buf, offs, block, rs, re, bad = fastwalk.walk([d for d, *_ in items], prog)
    for k, off, reason in bad:
        _reject(rejects, reason, **items[k][1], block_offset=off, hex=items[k][0][:32].hex())
    o = {name: offs[:, prog.slot(name)] for name in ("010", "070", "071", "073", "080", "090", "130", "131", "140",
                                                      "145", "157", "160", "170")}
    u = lambda name, start, width: fastwalk.uint_at(buf, o[name], start, width)  # noqa: E731

    def q(v: NDArray[np.int64], ok: NDArray[np.bool_], lsb: float) -> NDArray[np.float64]:
        return np.where(ok, v * lsb, np.nan)

    t071, t073 = u("071", 0, 3), u("073", 0, 3)
    tod = np.where(t071 >= 0, t071, t073) / 128.0
    hi = o["131"] >= 0
    lat = np.where(hi, fastwalk.signed(u("131", 0, 4), 32) * (180 / 2**30),
                   fastwalk.signed(u("130", 0, 3), 24) * (180 / 2**23))
    lon = np.where(hi, fastwalk.signed(u("131", 4, 4), 32) * (180 / 2**30),
                   fastwalk.signed(u("130", 3, 3), 24) * (180 / 2**23))
    pos_ok = hi | (o["130"] >= 0)
    gs = u("160", 0, 2)
    gvr = u("157", 0, 2)
    calls = pl.Series(_callsign(np.maximum(u("170", 0, 6), 0))).str.replace_all("~", "", literal=True)
    q1 = u("090", 0, 1)
    q2 = fastwalk.uint_at(buf, np.where((q1 >= 0) & ((q1 & 1) == 1), o["090"] + 1, -1), 0, 1)
    m3a = u("070", 0, 2)
    idx = pl.Series(block)
    meta = {"capture_s": pl.Series(np.array([it[2] for it in items], float)).gather(idx),
            "line": pl.Series([it[3] for it in items], dtype=pl.String).gather(idx),
            "file": pl.Series([str(it[1]["file"]) for it in items], dtype=pl.String).gather(idx),
            "datagram": pl.Series([int(it[1]["datagram"]) for it in items], dtype=pl.Int64).gather(idx)}
    return pl.DataFrame({
        "sac": u("010", 0, 1), "sic": u("010", 1, 1), "address": u("080", 0, 3),
        "tod_s": np.where((t071 >= 0) | (t073 >= 0), tod, np.nan),
        "lat_deg": np.where(pos_ok, lat, np.nan), "lon_deg": np.where(pos_ok, lon, np.nan),
        "height_ft": q(fastwalk.signed(u("140", 0, 2), 16), o["140"] >= 0, 6.25),
        "fl": q(fastwalk.signed(u("145", 0, 2), 16), o["145"] >= 0, 0.25),
        "gs_nmps": q(gs & 0x7FFF, gs >= 0, 2.0**-14), "ta_deg": q(u("160", 2, 2), gs >= 0, 360 / 65536),
        "gvr_ftpm": q(fastwalk.signed(gvr & 0x7FFF, 15), gvr >= 0, 6.25),
        "callsign": calls.set(pl.Series(o["170"] < 0), None), "capture_s": meta["capture_s"],
        "nic": np.where(q1 >= 0, (q1 >> 1) & 15, -1), "nacp": np.where(q2 >= 0, (q2 >> 1) & 15, -1),
        "sil": np.where(q2 >= 0, (q2 >> 5) & 3, -1),
        "mode_3a": fastcats.per_value(np.where(m3a >= 0, m3a & 0x0FFF, -1), fastcats.mode_3a),
        "tod": np.where(t071 >= 0, t071, t073),
        "hash": fastwalk.record_hash(buf, rs, re), "length": re - rs, "offset": fastcats.in_block(items, block, rs),
        **{k: meta[k] for k in ("line", "file", "datagram")},
    }, schema=_CAT021_SCHEMA).with_columns(
        *(pl.col(c).replace(-1, None) for c in ("sac", "sic", "address", "nic", "nacp", "sil")),
        *(pl.col(c).fill_nan(None) for c in _CAT021_SCHEMA if _CAT021_SCHEMA[c] == pl.Float64 and c != "capture_s"))


@functools.cache
def _program(cat: int) -> fastwalk.Program:
    return fastwalk.program(codec.spec(cat).cv_record)


def _decode_062(items: list[tuple[bytes, dict[str, object], float, str]], rejects: list[dict[str, object]]
                ) -> pl.DataFrame:
    rows = []
    for k, rec in _records_libasterix([d for d, *_ in items], [w for _, w, *_ in items], rejects):
        acc = rec.get_item("500")
        def a(sub: str, name: str | None, unit: str) -> float | None:
            if acc is None or acc.variation.get_item(sub) is None:
                return None
            v = acc.variation.get_item(sub).variation
            return (v.get_item(name).variation.content if name else v.content).as_quantity(unit)
        adr = rec.get_item("380")
        address = adr.variation.get_item("ADR") if adr is not None else None
        ident = adr.variation.get_item("ID") if adr is not None else None
        m3a = rec.get_item("060")
        rows.append({
            "sac": codec.sub_uint(rec, "010", "SAC"), "sic": codec.sub_uint(rec, "010", "SIC"),
            "track_number": codec.uint(rec, "040"), "tod_s": codec.qty(rec, "070", "s"),
            "lat_deg": codec.sub_qty(rec, "105", "LAT", "°"), "lon_deg": codec.sub_qty(rec, "105", "LON", "°"),
            "x_sdps_m": codec.sub_qty(rec, "100", "X", "m"), "y_sdps_m": codec.sub_qty(rec, "100", "Y", "m"),
            "vx_mps": codec.sub_qty(rec, "185", "VX", "m/s"), "vy_mps": codec.sub_qty(rec, "185", "VY", "m/s"),
            "fl": codec.qty(rec, "136", "FL"), "height_ft": codec.qty(rec, "130", "ft"),
            "rocd_ftpm": codec.qty(rec, "220", "ft/min"),
            "mode_3a": None if m3a is None else m3a.variation.get_item("MODE3A").variation.content.as_string(),
            "mode_s": None if address is None else f"{address.as_uint():06x}",
            "callsign": None if ident is None else ident.variation.content.as_string().rstrip(),
            "sx_m": a("APC", "X", "m"), "sy_m": a("APC", "Y", "m"), "sz_ft": a("AGA", None, "ft"),
            "svx_mps": a("ATV", "X", "m/s"), "svy_mps": a("ATV", "Y", "m/s"), "svz_ftpm": a("ARC", None, "ft/min"),
            "capture_s": items[k][2], "bytes": rec.unparse().to_bytes()})
    schema = {"sac": pl.Int64, "sic": pl.Int64, "track_number": pl.Int64, "tod_s": pl.Float64,
              **dict.fromkeys(("lat_deg", "lon_deg", "x_sdps_m", "y_sdps_m", "vx_mps", "vy_mps", "fl", "height_ft",
                               "rocd_ftpm"), pl.Float64),
              "mode_3a": pl.String, "mode_s": pl.String, "callsign": pl.String,
              **dict.fromkeys(("sx_m", "sy_m", "sz_ft", "svx_mps", "svy_mps", "svz_ftpm", "capture_s"), pl.Float64),
              "bytes": pl.Binary}
    return pl.DataFrame(rows, schema=schema)


# --------------------------------------------------------------------------- CAT048 → reports


def _hex6(v: NDArray[np.int64]) -> NDArray[np.str_]:
    """24-bit addresses as 6 lower-case hex digits (vectorised)."""
    nib = (v[:, None] >> np.arange(20, -1, -4)) & 15
    return np.ascontiguousarray(HEX[nib]).view("S6").ravel().astype("U6")


def _callsign(v: NDArray[np.int64]) -> NDArray[np.str_]:
    """I048/240: eight 6-bit ICAO characters (A-Z = 1-26, space = 32, digits = 48-57)."""
    idx = (v[:, None] >> np.arange(42, -1, -6)) & 63
    return np.ascontiguousarray(ICAO_CHARS[idx]).view("S8").ravel().astype("U8")


def _octal4(v: NDArray[np.int64]) -> NDArray[np.int64]:
    """The 12-bit Mode 3/A code as the decimal number its 4 octal digits spell."""
    code = v & 0x0FFF
    return ((code >> 9) & 7) * 1000 + ((code >> 6) & 7) * 100 + ((code >> 3) & 7) * 10 + (code & 7)


def cat048_values(raw: pl.DataFrame) -> pl.DataFrame:
    """Physical values of the raw CAT048 fields (units exactly as the contract wants them)."""
    g = {c: raw[c].to_numpy() for c in ("i090", "i070", "i220", "i240", "i161", "gs", "hdg", "i020", "i170a",
                                        "i170b")}
    fl14 = g["i090"] & 0x3FFF
    fl = np.where(fl14 >= 0x2000, fl14 - 0x4000, fl14) / 4.0            # two's complement, 1/4 FL
    alt_ok = (g["i090"] >= 0) & ((g["i090"] & 0xC000) == 0)            # present, validated, not garbled
    m3a_ok = (g["i070"] >= 0) & ((g["i070"] & 0xC000) == 0)
    calls = pl.Series("callsign", _callsign(np.maximum(g["i240"], 0))).str.replace_all("~", "", literal=True) \
        .str.strip_chars_end(" ")
    return pl.DataFrame({
        "range_m": pl.Series(np.where(raw["rho"].to_numpy() >= 0, raw["rho"].to_numpy() / 256.0 * codec.NM, np.nan))
        .fill_nan(None),                                                 # I048/040 RHO: 1/256 NM
        "azimuth_deg": pl.Series(np.where(raw["theta"].to_numpy() >= 0, raw["theta"].to_numpy() * (360.0 / 65536.0),
                                          np.nan)).fill_nan(None),       # THETA: 360/2^16 deg
        "altitude_m": pl.Series(np.where(alt_ok, fl * 100.0 * FT, np.nan)).fill_nan(None),
        "flight_level": pl.Series(np.where(g["i090"] >= 0, fl, np.nan)).fill_nan(None),
        "mode_3a": pl.Series(_octal4(g["i070"])).cast(pl.String).str.zfill(4).set(pl.Series(~m3a_ok), None),
        "mode_s": pl.Series(_hex6(np.maximum(g["i220"], 0))).set(pl.Series(g["i220"] < 0), None),
        "callsign": calls.set(pl.Series((g["i240"] < 0)) | (calls == ""), None),
        "ground_speed_mps": pl.Series(np.where(g["gs"] >= 0, g["gs"] * 2.0**-14 * codec.NM, np.nan)).fill_nan(None),
        "heading_deg": pl.Series(np.where(g["hdg"] >= 0, g["hdg"] * (360.0 / 65536.0), np.nan)).fill_nan(None),
        "detection_type": pl.Series(np.where(g["i020"] >= 0, g["i020"] >> 5, -1)).cast(pl.Int8).replace(-1, None),
        **_track_status(g["i170a"], g["i170b"]),
        **_enhanced_surveillance(raw),
    })


def _enhanced_surveillance(raw: pl.DataFrame) -> dict[str, pl.Series]:
    """I048/250 BDS 4,0, 5,0, 6,0 registers → ``selected_alt_m`` and the EHS columns
    (:mod:`tertiary.io.asterix.commb`); null where the register or the field's status is absent."""
    cols = commb.decode(*(raw[c].to_numpy() for c in ("mb40", "mb50", "mb60")))
    return {name: pl.Series(name, v, pl.Float64).fill_nan(None) for name, v in cols.items()}


def _track_status(a: NDArray[np.int64], b: NDArray[np.int64]) -> dict[str, pl.Series]:
    """I048/170 octet 1 CNF|RAD(2)|DOU|MAH|CDM(2)|FX, octet 2 TRE|GHO|SUP|TCC|spare|FX; null
    where the item (or its second octet) is absent."""
    def bit(v: NDArray[np.int64], shift: int, width: int = 1) -> pl.Series:
        return pl.Series(np.where(v >= 0, (v >> shift) & ((1 << width) - 1), -1)).replace(-1, None)
    return {"tentative": bit(a, 7).cast(pl.Boolean), "doubtful": bit(a, 4).cast(pl.Boolean),
            "manoeuvre": bit(a, 3).cast(pl.Boolean), "climb_mode": bit(a, 1, 2).cast(pl.Int8),
            "track_end": bit(b, 7).cast(pl.Boolean), "ghost": bit(b, 6).cast(pl.Boolean)}


def _raw_rejects(frame: pl.DataFrame, stage: str) -> list[dict[str, object]]:
    out = []
    for row in frame.select("reason", "file", "datagram", "offset", "sac", "sic", "tod").iter_rows(named=True):
        reason = row.pop("reason")
        out.append({"reason": reason, "detail": json.dumps(row | {"stage": stage})})
    return out


def build_reports(raw: pl.DataFrame, sites: pl.DataFrame | None, day0: float | None, stale_s: float,
                  ) -> tuple[pl.DataFrame, list[dict[str, object]], pl.DataFrame, dict[str, int]]:
    """CAT048 raw fields → (reports, rejects, per-radar latency, counts) in arrival order."""
    counts = {"cat048_records": raw.height}
    raw = raw.with_row_index("record")
    # only valid times of day take part in the unwrapping and the stale / out-of-order flags
    tod = raw["tod"].to_numpy()
    ok = (tod >= 0) & (tod < 86400 * 128)
    t = np.full(raw.height, np.nan)
    t[ok] = absolute_time(tod[ok] / 128.0, raw["capture_s"].to_numpy()[ok], day0)
    # redundant lines: the same record bytes from the same radar on the same day, first kept
    raw = raw.with_columns(pl.Series("t", t), (pl.Series(t) // DAY).alias("day"))
    first = raw.select(pl.struct("sac", "sic", "hash", "length", "day").is_first_distinct()).to_series()
    counts["duplicates"] = int((~first).sum())
    raw = raw.filter(first)
    counts["distinct"] = raw.height
    vals = cat048_values(raw)
    work = pl.concat([raw, vals], how="horizontal")
    if sites is not None:
        work = work.join(sites.select("sac", "sic", "radar_id"), on=["sac", "sic"], how="left", maintain_order="left")
    else:
        work = work.with_columns(pl.lit(None, pl.UInt32).alias("radar_id"))
    reasons = [
        (pl.col("sac") < 0, "no I048/010 (SAC/SIC)"),
        (pl.col("tod") < 0, "no I048/140 (time of day)"),
        (pl.col("tod") >= 86400 * 128, pl.format("I048/140 time of day {} s not below 86400", pl.col("tod") / 128)),
        (pl.col("rho") < 0, "no I048/040 (measured position)"),
        (pl.col("i161") < 0, "no I048/161 (track number)"),
        (pl.col("radar_id").is_null() & (pl.col("sac") >= 0), pl.format("SAC/SIC {}/{} not in the sites file",
                                                                         pl.col("sac"), pl.col("sic"))),
    ]
    # arrival order: out of order = older than an earlier report of the same local track (a radar
    # sends a sector's reports in track order, not time order); stale = older than the radar's
    # latest earlier report by more than stale_s
    t_ok = pl.col("t").fill_nan(None)
    prev = t_ok.cum_max().forward_fill().shift(1)
    work = work.with_columns((pl.col("i161") & 0x0FFF).alias("trn")).with_columns(
        behind=(prev.over(["sac", "sic"]) - t_ok).fill_null(0.0).clip(lower_bound=0.0),
        track_behind=(prev.over(["sac", "sic", "trn"]) - t_ok).fill_null(0.0))
    work = work.with_columns(out_of_order=pl.col("track_behind") > 0, stale=pl.col("behind") > stale_s,
                             latency_s=(pl.col("capture_s") - pl.col("t")).fill_nan(None))
    reason = pl.concat_str([pl.when(c).then(pl.lit(r) if isinstance(r, str) else r) for c, r in reasons],
                           separator="; ", ignore_nulls=True)
    work = work.with_columns(reason=reason)
    bad = work.filter(pl.col("reason").is_not_null() & (pl.col("reason") != ""))
    bad = bad.with_columns(pl.when(pl.col("stale")).then(pl.format("{}; stale ({} s behind its radar)",
                                                                   pl.col("reason"), pl.col("behind").round(1)))
                           .otherwise(pl.col("reason")).alias("reason"))
    good = work.filter(pl.col("reason").is_null() | (pl.col("reason") == ""))
    counts["rejected"] = bad.height
    counts["unknown_site"] = bad.filter(pl.col("radar_id").is_null() & (pl.col("sac") >= 0)).height
    reports = good.select(
        pl.col("radar_id").cast(pl.UInt32),
        (pl.col("t") * 1e6).round().cast(pl.Int64).cast(TIME).alias("time"),
        (pl.col("i161") & 0x0FFF).cast(pl.UInt32).alias("local_track_id"),
        "range_m", "azimuth_deg", "altitude_m", "mode_s", "mode_3a", "callsign",
        pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id"), pl.lit(0, pl.UInt32).alias("run"),
        "flight_level", "ground_speed_mps", "heading_deg", "detection_type",
        "tentative", "doubtful", "manoeuvre", "climb_mode", "track_end", "ghost",
        pl.col("sac").cast(pl.UInt8), pl.col("sic").cast(pl.UInt8),
        "out_of_order", "stale", "latency_s", *commb.COLUMNS,
    )
    counts |= _register_counts(good)
    latency = _latency(work)
    return reports, _raw_rejects(bad, "import"), latency, counts


def _register_counts(work: pl.DataFrame) -> dict[str, int]:
    """Reports carrying each Comm-B register (``cat048_bds40`` …) and the fields of those
    registers with status 0 but value bits set (``cat048_mb_status_conflicts``: left null)."""
    mb = {bds: work[f"mb{bds:x}"].to_numpy() for bds in commb.LAYOUT}
    conflicts = sum(int(commb.status_conflicts(v, bds).sum()) for bds, v in mb.items())
    return {**{f"cat048_bds{bds:x}": int((v >= 0).sum()) for bds, v in mb.items()},
            "cat048_mb_status_conflicts": conflicts}


def _latency(work: pl.DataFrame) -> pl.DataFrame:
    """Per radar: capture time − time of day of its distinct records (s), when captured."""
    lat = pl.col("latency_s")
    return (work.filter(lat.is_not_null())
            .group_by("sac", "sic", maintain_order=True)
            .agg(pl.len().alias("records"), lat.min().alias("latency_min_s"), lat.median().alias("latency_median_s"),
                 lat.quantile(0.95).alias("latency_p95_s"), lat.max().alias("latency_max_s"),
                 pl.col("stale").sum().alias("stale"), pl.col("out_of_order").sum().alias("out_of_order"))
            .sort("sac", "sic"))


# --------------------------------------------------------------------------- CAT034 → antenna timing


def antenna_timing(cat034: pl.DataFrame, day0: float | None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(distinct CAT034 messages with absolute times, per-radar scan period and north crossing).

    Scan period: median I034/041 when sent, else median interval of north markers (≥ 2), else
    360° over the slope of the sector-crossing azimuths unwrapped in time (least squares).
    """
    msgs = cat034.filter(pl.col("tod_s").is_not_null())
    t = absolute_time(msgs["tod_s"].to_numpy(), msgs["capture_s"].to_numpy(), day0)
    msgs = msgs.with_columns(pl.Series("t", t)).filter(pl.struct("sac", "sic", "bytes").is_first_distinct())
    rows = []
    for (sac, sic), grp in msgs.sort("t").group_by(["sac", "sic"], maintain_order=True):
        rows.append({"sac": sac, "sic": sic, "messages": grp.height, **_scan(grp)})
    timing = pl.DataFrame(rows, schema={"sac": pl.Int64, "sic": pl.Int64, "messages": pl.UInt32,
                                        "scan_period_s": pl.Float64, "scan_source": pl.String,
                                        "north_time": TIME})
    return msgs.drop("bytes"), timing


def _scan(grp: pl.DataFrame) -> dict[str, object]:
    ars = grp["rotation_period_s"].drop_nulls()
    north = grp.filter(pl.col("message_type") == 1)["t"].to_numpy()
    sector = grp.filter((pl.col("message_type") == 2) & pl.col("sector_deg").is_not_null())
    period, source = math.nan, "none"
    if ars.len():
        period, source = float(ars.median()), "I034/041"
    elif len(north) >= 2:
        period, source = float(np.median(np.diff(north))), "north markers"
    elif sector.height >= 2:
        ts, az = sector["t"].to_numpy(), np.unwrap(np.radians(sector["sector_deg"].to_numpy()))
        slope = np.polyfit(ts - ts[0], np.degrees(az), 1)[0]
        if slope > 0:
            period, source = 360.0 / slope, "sector crossings"
    t_north = north[-1] if len(north) else math.nan
    if not len(north) and sector.height and math.isfinite(period):
        last = sector.row(-1, named=True)
        t_north = last["t"] - last["sector_deg"] / 360.0 * period
    north_time = None if not math.isfinite(t_north) else datetime.fromtimestamp(t_north, timezone.utc)
    return {"scan_period_s": period, "scan_source": source, "north_time": north_time}


# --------------------------------------------------------------------------- radars


def radars_table(sites: pl.DataFrame, timing: pl.DataFrame, used: pl.DataFrame) -> tuple[pl.DataFrame, list[str]]:
    """The ``radars`` table of the sites used by the recording; scan period from the sites file,
    else from CAT034 (a note when both are given and differ by more than 5 %)."""
    notes = []
    frame = sites.join(used.select("sac", "sic").unique(), on=["sac", "sic"], how="semi")
    frame = frame.join(timing.select("sac", "sic", pl.col("scan_period_s").alias("measured")),
                       on=["sac", "sic"], how="left")
    for r in frame.filter(pl.col("measured").is_not_nan() & pl.col("scan_period_s").is_not_nan()).iter_rows(named=True):
        if abs(r["measured"] - r["scan_period_s"]) > 0.05 * r["scan_period_s"]:
            notes.append(f"radar {r['sac']}/{r['sic']}: scan period {r['scan_period_s']} s in the sites file, "
                         f"{r['measured']:.3f} s measured from CAT034")
    frame = frame.with_columns(pl.when(pl.col("scan_period_s").is_nan()).then(pl.col("measured"))
                               .otherwise(pl.col("scan_period_s")).alias("scan_period_s"))
    missing = frame.filter(pl.col("scan_period_s").is_null() | pl.col("scan_period_s").is_nan())
    if missing.height:
        codes = ", ".join(f"{a}/{b}" for a, b in missing.select("sac", "sic").iter_rows())
        raise DataError(f"no scan period for radar(s) {codes}: the recording has no CAT034 or CAT002 antenna "
                        "messages for them; give scan_period_s in the sites file")
    cols = list(TABLES["radars"].required) + (["kind"] if "kind" in frame.columns else [])
    return frame.select(*cols, "sac", "sic").cast({"radar_id": pl.UInt32}), notes


# --------------------------------------------------------------------------- CAT021 → truth, CAT062 → tracks


def enu_velocity(lat_deg: NDArray[np.float64], lon_deg: NDArray[np.float64], ve: NDArray[np.float64],
                 vn: NDArray[np.float64], vu: NDArray[np.float64], system: geo.LocalFrame
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """A velocity given in the local ENU frame at (lat, lon) expressed in the system ENU frame."""
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl, so, co = np.sin(la), np.cos(la), np.sin(lo), np.cos(lo)
    x = -so * ve - sl * co * vn + cl * co * vu          # ECEF components (ENU rotation transposed)
    y = co * ve - sl * so * vn + cl * so * vu
    z = cl * vn + sl * vu
    r = system.rotation
    return r[0, 0] * x + r[0, 1] * y + r[0, 2] * z, r[1, 0] * x + r[1, 1] * y + r[1, 2] * z, \
        r[2, 0] * x + r[2, 1] * y + r[2, 2] * z


def truth_table(cat021: pl.DataFrame, system: geo.LocalFrame, day0: float | None, min_nacp: int = 0,
                min_nic: int = 0) -> tuple[pl.DataFrame, list[dict[str, object]], int]:
    """CAT021 reports → (``truth`` (truth_id = 24-bit address) in the system frame, rejects, the
    number of points below the declared quality). A record whose I021/090 declares NACp below
    ``min_nacp`` or NIC below ``min_nic`` is not a reference point (a record without I021/090
    declares nothing and is kept), as :class:`tertiary.evaluation.reference.ReferenceConfig`
    filters an ADS-B reference."""
    need = pl.col("address").is_not_null() & pl.col("tod_s").is_not_null() & pl.col("lat_deg").is_not_null() \
        & pl.col("height_ft").is_not_null()
    impossible = (pl.col("lat_deg").abs() > 90) | (pl.col("lon_deg").abs() > 180) | (pl.col("tod_s") >= DAY)
    bad = cat021.filter(~need | impossible.fill_null(False))
    rejects = [{"reason": "CAT021 without address, time, position or geometric height" if r["lat_deg"] is None
                or r["tod_s"] is None or r["address"] is None or r["height_ft"] is None
                else "CAT021 position or time out of range",
                "detail": json.dumps({k: r[k] for k in ("sac", "sic", "address", "tod_s", "lat_deg", "lon_deg")})}
               for r in bad.iter_rows(named=True)]
    # redundant lines: the same report (source, aircraft, time, position) once
    key = pl.struct("sac", "sic", "address", "tod_s", "lat_deg", "lon_deg", "height_ft")
    cat021 = cat021.filter(need & ~impossible.fill_null(False)).filter(key.is_first_distinct())
    low = pl.coalesce(
        pl.when(pl.col("nacp") < min_nacp).then(
            pl.format(f"declared quality below the reference bound (NACp {{}} < {min_nacp})", pl.col("nacp"))),
        pl.when(pl.col("nic") < min_nic).then(
            pl.format(f"declared integrity below the reference bound (NIC {{}} < {min_nic})", pl.col("nic"))))
    cat021 = cat021.with_columns(low.alias("__low"))
    poor = cat021.filter(pl.col("__low").is_not_null())
    detail = pl.struct("sac", "sic", "address", "tod_s", "nacp", "nic", "file", "datagram", "offset")
    rejects += poor.select(pl.col("__low").alias("reason"), detail.struct.json_encode().alias("detail")).to_dicts()
    ok = cat021.filter(pl.col("__low").is_null()).drop("__low")
    t = absolute_time(ok["tod_s"].to_numpy(), ok["capture_s"].to_numpy(), day0)
    lat, lon = ok["lat_deg"].to_numpy(), ok["lon_deg"].to_numpy()
    h = ok["height_ft"].to_numpy() * FT
    x, y, z = system.from_geodetic(lat, lon, h)
    gs = ok["gs_nmps"].fill_null(np.nan).to_numpy() * codec.NM
    ta = np.radians(ok["ta_deg"].fill_null(np.nan).to_numpy())
    vu = ok["gvr_ftpm"].fill_null(0.0).to_numpy() * FT / 60.0
    vx, vy, vz = enu_velocity(lat, lon, gs * np.sin(ta), gs * np.cos(ta), vu, system)
    truth = pl.DataFrame({
        "truth_id": ok["address"], "time": pl.Series((t * 1e6).round().astype(np.int64)).cast(TIME),
        "x_m": x, "y_m": y, "z_m": z, "vx_mps": vx, "vy_mps": vy, "vz_mps": vz,
        "lat_deg": lat, "lon_deg": lon,
        "alt_m": (ok["fl"] * 100.0 * FT),
        "icao24": pl.Series(_hex6(ok["address"].to_numpy()), dtype=pl.String),
        "callsign": ok["callsign"].str.strip_chars_end(" ").replace("", None),
    }).with_columns(pl.col(c).fill_nan(None) for c in ("vx_mps", "vy_mps", "vz_mps"))
    truth = truth.filter(pl.all_horizontal(pl.col("vx_mps", "vy_mps").is_not_null())) \
        .unique(["truth_id", "time"], keep="first", maintain_order=True).sort("truth_id", "time")
    return truth, rejects, poor.height


def external_tracks(cat062: pl.DataFrame, system: geo.LocalFrame, day0: float | None,
                    ) -> tuple[pl.DataFrame, list[dict[str, object]]]:
    """CAT062 system tracks → the ``tracks`` schema (+ ids) in the system frame.

    Position from I062/105 (WGS-84) and I062/130 (geometric height), velocity I062/185 in the
    SDPS Cartesian plane taken as the system plane (true for our own export, a tangent-plane
    approximation for a foreign SDPS), accuracy I062/500 → ``cov_diag``; I062/136 → ``alt_m``.
    """
    need = pl.all_horizontal(pl.col("track_number", "tod_s", "lat_deg", "height_ft", "vx_mps").is_not_null())
    impossible = (pl.col("lat_deg").abs() > 90) | (pl.col("lon_deg").abs() > 180) | (pl.col("tod_s") >= DAY)
    bad = cat062.filter(~need | impossible.fill_null(False))
    rejects = [{"reason": "CAT062 without track number, time, WGS-84 position, geometric height or velocity"
                if not all(r[k] is not None for k in ("track_number", "tod_s", "lat_deg", "height_ft", "vx_mps"))
                else "CAT062 position or time out of range",
                "detail": json.dumps({k: r[k] for k in ("sac", "sic", "track_number", "tod_s", "lat_deg")})}
               for r in bad.iter_rows(named=True)]
    ok = cat062.filter(need & ~impossible.fill_null(False)).filter(pl.struct("bytes").is_first_distinct())
    t = absolute_time(ok["tod_s"].to_numpy(), ok["capture_s"].to_numpy(), day0)
    lat, lon = ok["lat_deg"].to_numpy(), ok["lon_deg"].to_numpy()
    x, y, z = system.from_geodetic(lat, lon, ok["height_ft"].to_numpy() * FT)
    vz = ok["rocd_ftpm"].fill_null(0.0).to_numpy() * FT / 60.0
    sig = {k: ok[k].fill_null(np.nan).to_numpy() for k in ("sx_m", "sy_m", "sz_ft", "svx_mps", "svy_mps", "svz_ftpm")}
    cov = np.stack([sig["sx_m"] ** 2, sig["sy_m"] ** 2, (sig["sz_ft"] * FT) ** 2, sig["svx_mps"] ** 2,
                    sig["svy_mps"] ** 2, (sig["svz_ftpm"] * FT / 60.0) ** 2], axis=1)
    n = ok.height
    tracks = pl.DataFrame({
        "run": pl.Series(np.zeros(n, np.uint32)), "epoch": pl.Series((t * 1e6).round().astype(np.int64)).cast(TIME),
        "track_id": ok["track_number"].cast(pl.UInt64), "filter": pl.Series(["cat062"] * n, dtype=pl.String),
        "method": pl.Series([f"sdps-{a}-{b}" for a, b in ok.select("sac", "sic").iter_rows()], dtype=pl.String),
        "x_m": x, "y_m": y, "z_m": z, "vx_mps": ok["vx_mps"], "vy_mps": ok["vy_mps"], "vz_mps": vz,
        "cov_diag": pl.Series(cov, dtype=pl.Array(pl.Float64, 6)),
        "innovation": pl.Series([None] * n, dtype=pl.List(pl.Float64)), "nis": pl.Series([None] * n, dtype=pl.Float64),
        "model_probs": pl.Series([None] * n, dtype=pl.List(pl.Float64)),
        "alt_m": ok["fl"] * 100.0 * FT,
        "track_number": ok["track_number"].cast(pl.UInt32), "mode_s": ok["mode_s"], "mode_3a": ok["mode_3a"],
        "callsign": ok["callsign"], "lat_deg": lat, "lon_deg": lon, "flight_level": ok["fl"],
    })
    return tracks.sort("epoch", "track_id"), rejects


def rejects_frame(rows: list[dict[str, object]]) -> pl.DataFrame:
    """Import rejects in the canonical ``rejects`` schema (row_index = order of the problem)."""
    n = len(rows)
    return pl.DataFrame({
        "input_table": ["asterix"] * n, "stage": ["import"] * n, "report_id": pl.Series([None] * n, dtype=pl.UInt64),
        "row_index": pl.Series(np.arange(n, dtype=np.uint64)), "reason": [str(r["reason"]) for r in rows],
        "detail": [str(r["detail"]) for r in rows],
    }, schema=TABLES["rejects"].required)


def parse_date(text: str | None) -> float | None:
    """Midnight (s since 1970 UTC) of a YYYY-MM-DD option value."""
    if text is None:
        return None
    try:
        return _midnight(Date.fromisoformat(text))
    except ValueError:
        raise OptionError(f"expected a date YYYY-MM-DD, got {text!r}", option="--date") from None


def origin_of(radars: pl.DataFrame, fallback: tuple[float, float] | None) -> tuple[float, float, float]:
    """System origin: mean radar site (as :func:`tertiary.io.dataset.read_dataset` places it), else ``fallback``."""
    if radars.height:
        return float(radars["lat_deg"].mean()), float(radars["lon_deg"].mean()), 0.0
    if fallback is None:
        raise DataError("no radar site and no position to place the system origin")
    return fallback[0], fallback[1], 0.0
