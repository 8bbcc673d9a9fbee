"""Compiled decoding of CAT001, CAT002, CAT004 and CAT020 (:mod:`tertiary.io.asterix.fastwalk`
programs from the libasterix specifications, numpy field reads at the item offsets).

Units are libasterix's (checked in ``tests/test_asterix_cats.py``): I001/040 RHO 1/128 NM, THETA
360/2¹⁶ °; I001/141 1/128 s (truncated to 16 bits); I001/090, I020/090 1/4 FL; I002/020 360/2⁸ °,
/030 1/128 s, /041 1/128 s; I004/020 1/128 s, /070 TCA 1/128 s, MHS 0.5 m, MVS 25 ft; I020/140
1/128 s, /041 180/2²⁵ °, /042 0.5 m, /105 6.25 ft, /500 SDP 0.25 m.
"""

from __future__ import annotations

import functools
import json
from typing import Any

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.io.asterix import codec, fastwalk

#: (block bytes, where, capture time stamp s, line, arrival sequence number of the block)
Item = tuple[bytes, dict[str, object], float, str, int]
Rejects = list[dict[str, object]]
ICAO_CHARS = np.frombuffer(b"~ABCDEFGHIJKLMNOPQRSTUVWXYZ~~~~~ ~~~~~~~~~~~~~~~0123456789~~~~~~", np.uint8)
HEX = np.frombuffer(b"0123456789abcdef", np.uint8)


@functools.cache
def program(cat: int, uap: str | None = None) -> fastwalk.Program:
    """The walker program of a category's edition (``uap``: the record class of a two-UAP category)."""
    u = codec.spec(cat).cv_uap
    return fastwalk.program(u.cv_uaps[uap] if uap else u.cv_record)


def _reject_blocks(items: list[Item], bad: list[tuple[int, int, str]], cat: int, rejects: Rejects) -> None:
    """Refused blocks as rejects rows (the importer's form), the edition named in the reason."""
    ed = codec.EDITIONS[cat].rsplit("_", 2)
    for k, off, reason in bad:
        detail = {**items[k][1], "block_offset": off, "hex": items[k][0][:32].hex()}
        rejects.append({"reason": reason.replace("record:", f"record (edition {ed[-2]}.{ed[-1]}):", 1),
                        "detail": json.dumps(detail, default=str)})


def _in_block(items: list[Item], block: NDArray[np.int64], rs: NDArray[np.int64]) -> NDArray[np.int64]:
    """Record offsets in their block's record part (``rs`` are offsets in the concatenation)."""
    lens = np.fromiter((len(it[0]) - 3 for it in items), np.int64, len(items))
    return rs - (np.cumsum(lens) - lens)[block] if len(items) else rs


def _meta(items: list[Item], block: NDArray[np.int64]) -> dict[str, pl.Series]:
    """Per-record attributes of their blocks (gathered by block index: a loop over blocks only)."""
    idx = pl.Series(block)
    return {"capture_s": pl.Series(np.array([it[2] for it in items], float)).gather(idx),
            "line": pl.Series([it[3] for it in items], dtype=pl.String).gather(idx),
            "file": pl.Series([str(it[1]["file"]) for it in items], dtype=pl.String).gather(idx),
            "datagram": pl.Series([int(it[1]["datagram"]) for it in items], dtype=pl.Int64).gather(idx),
            "seq": pl.Series(np.array([it[4] for it in items], np.int64)).gather(idx)}


#: the in-block offsets of records, for the decoders of other modules
in_block = _in_block


class Fields:
    """Numpy reads of a walked category: ``u(item, start, width)`` unsigned, -1 where absent."""

    def __init__(self, buf: NDArray[np.uint8], offs: dict[str, NDArray[np.int64]]) -> None:
        self.buf, self.o = buf, offs

    def u(self, name: str, start: int = 0, width: int = 1) -> NDArray[np.int64]:
        return fastwalk.uint_at(self.buf, self.o[name], start, width)

    def has(self, name: str) -> NDArray[np.bool_]:
        return self.o[name] >= 0


def per_value(v: NDArray[np.int64], text: Any) -> pl.Series:
    """``text(values)`` computed once per distinct value (identities repeat over an aircraft's
    reports) and gathered back to every row."""
    u, inv = np.unique(v, return_inverse=True)
    return text(u).gather(pl.Series(inv.ravel()))


def icao_text(v: NDArray[np.int64], chars: int = 8) -> pl.Series:
    """ICAO 6-bit characters (48 bits) → text, trailing spaces removed, null when empty or absent."""
    w = np.maximum(v, 0).astype(np.uint64)
    codes = np.stack([(w >> np.uint64(6 * (chars - 1 - i))) & np.uint64(63) for i in range(chars)], axis=1)
    s = pl.Series(ICAO_CHARS[codes.astype(np.int64)].view(f"S{chars}").ravel()).cast(pl.String)
    s = s.str.replace_all("~", "", literal=True).str.strip_chars_end(" ")
    return s.set(pl.Series(v < 0) | (s == ""), None)


def ascii_text(v: NDArray[np.int64], n: int) -> pl.Series:
    """``n`` ASCII octets held big-endian in ``v`` (-1: absent) → text, trailing spaces removed,
    null when blank or absent; octets outside printable ASCII read as spaces."""
    w = np.maximum(v, 0)
    raw = np.stack([(w >> (8 * (n - 1 - i))) & 0xFF for i in range(n)], axis=1).astype(np.uint8)
    raw = np.where((raw >= 32) & (raw < 127), raw, 32).astype(np.uint8)
    s = pl.Series(np.ascontiguousarray(raw).view(f"S{n}").ravel()).cast(pl.String).str.strip_chars_end(" ")
    return s.set(pl.Series(v < 0) | (s == ""), None)


def hex6(v: NDArray[np.int64]) -> pl.Series:
    """24-bit addresses → six lower-case hex digits, null where absent (-1)."""
    w = np.maximum(v, 0)
    digits = HEX[np.stack([(w >> (4 * (5 - i))) & 15 for i in range(6)], axis=1)]
    return pl.Series(np.ascontiguousarray(digits).view("S6").ravel()).cast(pl.String).set(pl.Series(v < 0), None)


def mode_3a(v: NDArray[np.int64]) -> pl.Series:
    """I0xx/070 (V|G|L|spare|12-bit code) → four octal digits; null when absent, V or G set."""
    code = v & 0x0FFF
    octal = ((code >> 9) & 7) * 1000 + ((code >> 6) & 7) * 100 + ((code >> 3) & 7) * 10 + (code & 7)
    return pl.Series(octal).cast(pl.String).str.zfill(4).set(pl.Series((v < 0) | ((v & 0xC000) != 0)), None)


def flight_level(v: NDArray[np.int64]) -> tuple[pl.Series, pl.Series]:
    """I0xx/090 (V|G|14-bit 1/4 FL, two's complement) → (flight level, valid flight level):
    the first null when absent, the second also when V or G is set."""
    fl = fastwalk.signed(v & 0x3FFF, 14) / 4.0
    return (pl.Series(np.where(v >= 0, fl, np.nan)).fill_nan(None),
            pl.Series(np.where((v >= 0) & ((v & 0xC000) == 0), fl, np.nan)).fill_nan(None))


def identities(frame: pl.DataFrame, suffixes: tuple[str, ...]) -> pl.DataFrame:
    """Raw CAT004 identity columns ``ai_X``, ``m3_X``, ``ms_X`` (X in ``suffixes``) → text
    columns ``callsign_X``, ``mode_3a_X``, ``mode_s_ident_X``."""
    out = []
    for k in suffixes:
        out += [ascii_text(frame[f"ai_{k}"].fill_null(-1).to_numpy(), 7).alias(f"callsign_{k}"),
                mode_3a(frame[f"m3_{k}"].fill_null(-1).to_numpy()).alias(f"mode_3a_{k}"),
                icao_text(frame[f"ms_{k}"].fill_null(-1).to_numpy()).alias(f"mode_s_ident_{k}")]
    return frame.drop(*(f"{c}_{k}" for k in suffixes for c in ("ai", "m3", "ms"))).with_columns(out)


def _nan(ok: NDArray[np.bool_], v: NDArray[Any]) -> pl.Series:
    """``v`` where ``ok``, null elsewhere."""
    return pl.Series(np.where(ok, v, np.nan)).fill_nan(None)


# --------------------------------------------------------------------------- CAT020 (MLAT / WAM)


def decode_020(items: list[Item], rejects: Rejects) -> pl.DataFrame:
    """CAT020 target reports: position (WGS-84 and/or Cartesian), accuracy, identities, time."""
    prog = program(20)
    buf, offs, block, rs, re, bad = fastwalk.walk([d for d, *_ in items], prog)
    _reject_blocks(items, bad, 20, rejects)
    f = Fields(buf, {n: offs[:, prog.slot(n)] for n in ("010", "140", "041", "042", "161", "070", "090", "105",
                                                         "220", "245", "500")})
    sdp = fastwalk.sub_offsets(buf, f.o["500"], _sizes(prog, "500"))[1]
    s = Fields(buf, {"sdp": sdp})
    fl, alt_fl = flight_level(f.u("090", 0, 2))
    return pl.DataFrame({
        "sac": f.u("010", 0, 1), "sic": f.u("010", 1, 1), "tod": f.u("140", 0, 3),
        "lat_deg": _nan(f.has("041"), fastwalk.signed(f.u("041", 0, 4), 32) * (180 / 2**25)),
        "lon_deg": _nan(f.has("041"), fastwalk.signed(f.u("041", 4, 4), 32) * (180 / 2**25)),
        "x_m": _nan(f.has("042"), fastwalk.signed(f.u("042", 0, 3), 24) * 0.5),
        "y_m": _nan(f.has("042"), fastwalk.signed(f.u("042", 3, 3), 24) * 0.5),
        "trn": pl.Series(np.where(f.has("161"), f.u("161", 0, 2) & 0x0FFF, -1)),
        "mode_3a": per_value(f.u("070", 0, 2), mode_3a), "flight_level": fl, "fl_valid": alt_fl,
        "height_ft": _nan(f.has("105"), fastwalk.signed(f.u("105", 0, 2), 16) * 6.25),
        "mode_s": per_value(f.u("220", 0, 3), hex6), "callsign": per_value(f.u("245", 1, 6), icao_text),
        "sigma_x_m": _nan(s.has("sdp"), s.u("sdp", 0, 2) * 0.25),
        "sigma_y_m": _nan(s.has("sdp"), s.u("sdp", 2, 2) * 0.25),
        "sigma_xy_m": _nan(s.has("sdp"), s.u("sdp", 4, 2) * 0.25),
        "hash": fastwalk.record_hash(buf, rs, re), "length": re - rs, "offset": _in_block(items, block, rs),
        **_meta(items, block),
    })


def _sizes(prog: fastwalk.Program, name: str) -> tuple[int, ...]:
    """Octet sizes of a compound item's subfields (0: extended of one-octet groups)."""
    s = prog.slot(name)
    out = []
    for j in range(prog.p2[s]):
        kind, p1, p2 = prog.sub_kind[prog.sub_start[s] + j], prog.sub_p1[prog.sub_start[s] + j], \
            prog.sub_p2[prog.sub_start[s] + j]
        if kind == fastwalk.FIXED:
            out.append(int(p1))
        elif kind == fastwalk.EXTENDED and all(prog.groups[p1 + g] >> 1 == 1 for g in range(p2)):
            out.append(0)
        else:
            out.append(-1)           # not read here; fields after it are not read either
    return tuple(out)


# --------------------------------------------------------------------------- CAT001 / CAT002 (legacy radar)


def decode_001(items: list[Item], rejects: Rejects) -> pl.DataFrame:
    """CAT001 plots and tracks (record class by I001/020 TYP): polar position, Mode 3/A, Mode C,
    truncated time of day, track number (tracks)."""
    plot, track = program(1, "plot"), program(1, "track")
    buf, offs, uap, block, rs, re, bad = fastwalk.walk_select([d for d, *_ in items], plot, track, 2)
    _reject_blocks(items, bad, 1, rejects)
    is_track = uap == 1

    def off(name: str) -> NDArray[np.int64]:
        a = offs[:, plot.slot(name)] if name in plot.names else np.full(len(uap), -1)
        b = offs[:, track.slot(name)] if name in track.names else np.full(len(uap), -1)
        return np.where(is_track, b, a)

    f = Fields(buf, {n: off(n) for n in ("010", "020", "040", "070", "090", "141", "161")})
    fl, alt_fl = flight_level(f.u("090", 0, 2))
    rho, theta = f.u("040", 0, 2), f.u("040", 2, 2)
    return pl.DataFrame({
        "sac": f.u("010", 0, 1), "sic": f.u("010", 1, 1), "plot": ~is_track, "tod_trunc": f.u("141", 0, 2),
        "range_m": _nan(rho >= 0, rho / 128.0 * codec.NM), "azimuth_deg": _nan(theta >= 0, theta * (360 / 65536)),
        "trn": f.u("161", 0, 2), "mode_3a": per_value(f.u("070", 0, 2), mode_3a), "flight_level": fl,
        "fl_valid": alt_fl,
        "detection": pl.Series(np.where(f.has("020"), (f.u("020") >> 4) & 3, -1)).cast(pl.Int8).replace(-1, None),
        "hash": fastwalk.record_hash(buf, rs, re), "length": re - rs, "offset": _in_block(items, block, rs),
        **_meta(items, block),
    })


def decode_002(items: list[Item], rejects: Rejects) -> pl.DataFrame:
    """CAT002 service messages in the CAT034 message frame (north / sector / south markers),
    with ``seq`` (arrival order) for the CAT001 time of day."""
    prog = program(2)
    buf, offs, block, rs, re, bad = fastwalk.walk([d for d, *_ in items], prog)
    _reject_blocks(items, bad, 2, rejects)
    f = Fields(buf, {n: offs[:, prog.slot(n)] for n in ("010", "000", "020", "030", "041")})
    meta = _meta(items, block)
    raw = bytes(buf)
    return pl.DataFrame({
        "sac": f.u("010", 0, 1), "sic": f.u("010", 1, 1), "message_type": f.u("000"),
        "tod_s": _nan(f.has("030"), f.u("030", 0, 3) / 128.0),
        "sector_deg": _nan(f.has("020"), f.u("020") * (360 / 256)),
        "rotation_period_s": _nan(f.has("041"), f.u("041", 0, 2) / 128.0),
        "capture_s": meta["capture_s"], "line": meta["line"],
        "bytes": pl.Series([raw[a:b] for a, b in zip(rs.tolist(), re.tolist())], dtype=pl.Binary),
        "seq": meta["seq"],
    }).with_columns(pl.col("sac", "sic", "message_type").replace(-1, None))


# --------------------------------------------------------------------------- CAT004 (safety nets)


def decode_004(items: list[Item], rejects: Rejects) -> pl.DataFrame:
    """CAT004 safety-net messages: type, time, alert id and status, the two tracks with their
    identities (I004/170, /171: AI callsign, M31 Mode 3/A, MS Mode S identification), and the
    conflict timing and separation (I004/070 TCA, MHS, MVS)."""
    prog = program(4)
    buf, offs, block, rs, re, bad = fastwalk.walk([d for d, *_ in items], prog)
    _reject_blocks(items, bad, 4, rejects)
    f = Fields(buf, {n: offs[:, prog.slot(n)] for n in ("010", "000", "020", "040", "045", "030", "035")})
    cols: dict[str, object] = {
        "sac": f.u("010", 0, 1), "sic": f.u("010", 1, 1), "message_type": f.u("000"), "tod": f.u("020", 0, 3),
        "alert_id": f.u("040", 0, 2), "status": np.where(f.has("045"), (f.u("045") >> 1) & 7, -1),
        "track_1": f.u("030", 0, 2), "track_2": f.u("035", 0, 2),
    }
    for item, k in (("170", "1"), ("171", "2")):
        sub = fastwalk.sub_offsets(buf, offs[:, prog.slot(item)], _sizes(prog, item))
        g = Fields(buf, {"ai": sub[0], "m3": sub[1], "ms": sub[7]})
        m3 = g.u("m3", 0, 2)           # spare(4) | code(12): no V/G bits
        # raw values: text is made per alert episode (:func:`identities`), not per message
        cols |= {f"ai_{k}": g.u("ai", 0, 7), f"m3_{k}": np.where(m3 >= 0, m3 & 0x0FFF, -1), f"ms_{k}": g.u("ms", 0, 6)}
    tc = fastwalk.sub_offsets(buf, offs[:, prog.slot("070")], _sizes(prog, "070"))
    g = Fields(buf, {"tca": tc[1], "mhs": tc[3], "mvs": tc[5]})
    meta = _meta(items, block)
    return pl.DataFrame({
        **cols,
        "tca_s": _nan(g.has("tca"), g.u("tca", 0, 3) / 128.0),
        "mhs_m": _nan(g.has("mhs"), g.u("mhs", 0, 2) * 0.5),
        "mvs_ft": _nan(g.has("mvs"), g.u("mvs", 0, 2) * 25.0),
        "hash": fastwalk.record_hash(buf, rs, re), "length": re - rs, "offset": _in_block(items, block, rs), **meta,
    })
