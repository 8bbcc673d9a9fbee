"""Recording containers: pcap / pcapng captures (UDP payloads) and raw ASTERIX data blocks.

A recording becomes a list of *datagrams* (payload bytes, capture time or NaN, line label) and
then a list of *data blocks* (category, bytes). Nothing here raises on bad bytes: every frame or
block that cannot be used is returned as a problem ``(datagram index, byte offset, reason)`` so
the importer can put it in ``rejects``. No libasterix import (it costs ~2.4 s).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from tertiary.core.errors import DataError

PCAP_MAGIC = {b"\xd4\xc3\xb2\xa1": ("<", 1e-6), b"\xa1\xb2\xc3\xd4": (">", 1e-6),
              b"\x4d\x3c\xb2\xa1": ("<", 1e-9), b"\xa1\xb2\x3c\x4d": (">", 1e-9)}
PCAPNG_SHB = b"\x0a\x0d\x0d\x0a"
#: link types whose frames we can strip to an IP packet: Ethernet, raw IP, Linux SLL, BSD loopback
LINK_ETHERNET, LINK_RAW, LINK_RAW4, LINK_SLL, LINK_NULL, LINK_LOOP = 1, 101, 228, 113, 0, 108


@dataclass
class Datagrams:
    """Payloads of one recording in arrival order: UDP payloads (captures) or one raw stream."""

    payloads: list[bytes] = field(default_factory=list)
    capture_s: list[float] = field(default_factory=list)     # seconds since 1970 UTC, NaN for raw files
    line: list[str] = field(default_factory=list)            # "src>dst:port" (redundant lines differ)
    problems: list[tuple[int, int, str]] = field(default_factory=list)   # (frame, byte offset, reason)

    def add(self, payload: bytes, t: float, line: str) -> None:
        self.payloads.append(payload)
        self.capture_s.append(t)
        self.line.append(line)


def _ip_payload(frame: bytes, link: int) -> tuple[bytes, str] | str:
    """The UDP payload of a link-layer frame and its line label, or a reason why not."""
    if link == LINK_ETHERNET:
        off, etype = 14, frame[12:14] if len(frame) >= 14 else b""
        while etype in (b"\x81\x00", b"\x88\xa8") and len(frame) >= off + 4:   # VLAN tags
            etype, off = frame[off + 2:off + 4], off + 4
        if etype != b"\x08\x00":
            return f"not IPv4 over Ethernet (ethertype {etype.hex() or 'truncated'})"
    elif link in (LINK_RAW, LINK_RAW4):
        off = 0
    elif link == LINK_SLL:
        off = 16
    elif link in (LINK_NULL, LINK_LOOP):
        off = 4
    else:
        return f"link type {link} not supported (Ethernet, raw IP, Linux SLL, loopback are)"
    ip = frame[off:]
    if len(ip) < 20 or ip[0] >> 4 != 4:
        return "not an IPv4 packet"
    ihl = (ip[0] & 15) * 4
    if ip[9] != 17:
        return f"IP protocol {ip[9]} is not UDP"
    if struct.unpack(">H", ip[6:8])[0] & 0x3FFF:
        return "fragmented IP packet (reassembly not supported)"
    udp = ip[ihl:]
    if len(udp) < 8:
        return "truncated UDP header"
    sport, dport, ulen = struct.unpack(">HHH", udp[:6])
    if ulen < 8 or ulen > len(udp):
        return f"UDP length {ulen} beyond the captured {len(udp)} bytes (truncated capture?)"
    src, dst = ".".join(map(str, ip[12:16])), ".".join(map(str, ip[16:20]))
    return udp[8:ulen], f"{src}:{sport}>{dst}:{dport}"


def _add_frame(out: Datagrams, frame: bytes, t: float, link: int, index: int) -> None:
    got = _ip_payload(frame, link)
    if isinstance(got, str):
        out.problems.append((index, 0, got))
    else:
        out.add(got[0], t, got[1])


def _pcap_header_ok(data: bytes, off: int, order: str, unit: float, snap: int, sec0: int | None, depth: int = 2) -> bool:
    """A plausible pcap record header at ``off``: fraction below one second, captured length not
    above the original nor the snap length and inside the file, time within a day of ``sec0``,
    followed by the end of the file or (``depth`` deep) another plausible header."""
    if off + 16 > len(data):
        return False
    sec, frac, incl, orig = struct.unpack(order + "IIII", data[off:off + 16])
    if frac * unit >= 1.0 or incl > orig or incl > snap or off + 16 + incl > len(data):
        return False
    if sec0 is not None and abs(sec - sec0) > 86400:
        return False
    nxt = off + 16 + incl
    return nxt == len(data) or depth <= 1 or _pcap_header_ok(data, nxt, order, unit, snap, sec, depth - 1)


def read_pcap(data: bytes) -> Datagrams:
    """UDP payloads of a classic libpcap capture (either byte order, µs or ns stamps).

    A record header that cannot be right (length past the end or above the snap length) is a
    problem; reading resumes at the next plausible record header (see :func:`_pcap_header_ok`).
    """
    order, unit = PCAP_MAGIC[data[:4]]
    out = Datagrams()
    if len(data) < 24:
        out.problems.append((0, 0, "truncated pcap global header"))
        return out
    snap, link = struct.unpack(order + "II", data[16:24])
    link &= 0x0FFFFFFF
    snap = snap if 0 < snap <= 1 << 18 else 1 << 18
    off, index, sec0 = 24, 0, None
    while off < len(data):
        if off + 16 > len(data):
            out.problems.append((index, off, "truncated pcap record header"))
            break
        sec, frac, incl, _orig = struct.unpack(order + "IIII", data[off:off + 16])
        if off + 16 + incl > len(data) or incl > snap:
            out.problems.append((index, off, f"pcap record of {incl} bytes runs past the end of the file"
                                 if off + 16 + incl > len(data) else f"pcap record of {incl} bytes above the snap "
                                 f"length {snap}"))
            nxt = off + 1
            while nxt < len(data) and not _pcap_header_ok(data, nxt, order, unit, snap, sec0):
                nxt += 1
            if nxt < len(data):
                out.problems.append((index, off, f"{nxt - off} byte(s) skipped to the next pcap record"))
            off, index = nxt, index + 1
            continue
        _add_frame(out, data[off + 16:off + 16 + incl], sec + frac * unit, link, index)
        off, index, sec0 = off + 16 + incl, index + 1, sec
    return out


def read_pcapng(data: bytes) -> Datagrams:
    """UDP payloads of a pcapng capture (enhanced and simple packet blocks)."""
    out = Datagrams()
    off, index, order = 0, 0, "<"
    links: list[tuple[int, float]] = []
    while off + 12 <= len(data):
        if data[off:off + 4] == PCAPNG_SHB:
            order = "<" if data[off + 8:off + 12] == b"\x4d\x3c\x2b\x1a" else ">"
            links = []
        btype, blen = struct.unpack(order + "II", data[off:off + 8])
        if blen < 12 or blen % 4 or off + blen > len(data):
            out.problems.append((index, off, f"pcapng block length {blen} invalid"))
            break
        body = data[off + 8:off + blen - 4]
        if btype == 1 and len(body) >= 8:            # interface description: link type, ts resolution
            links.append((struct.unpack(order + "H", body[:2])[0], _if_tsres(body[8:], order)))
        elif btype == 6 and len(body) >= 20:         # enhanced packet
            iface, hi, lo, incl = struct.unpack(order + "IIII", body[:16])
            if iface >= len(links):
                out.problems.append((index, off, f"packet names interface {iface}, not described"))
            else:
                link, res = links[iface]
                _add_frame(out, body[20:20 + incl], ((hi << 32) | lo) * res, link, index)
            index += 1
        elif btype == 3 and len(body) >= 4:          # simple packet: no time stamp
            if links:
                _add_frame(out, body[4:], float("nan"), links[0][0], index)
            index += 1
        off += blen
    return out


def _if_tsres(options: bytes, order: str) -> float:
    """Time-stamp resolution of a pcapng interface (option if_tsresol, default µs)."""
    off = 0
    while off + 4 <= len(options):
        code, length = struct.unpack(order + "HH", options[off:off + 4])
        if code == 0:
            break
        if code == 9 and length >= 1:
            v = options[off + 4]
            return 2.0 ** -(v & 0x7F) if v & 0x80 else 10.0 ** -v
        off += 4 + (length + 3) // 4 * 4
    return 1e-6


def read_recording(path: str | Path) -> Datagrams:
    """The datagrams of a capture file, or the whole file as one raw stream of data blocks."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror or exc}", path=str(p)) from exc
    if data[:4] in PCAP_MAGIC:
        return read_pcap(data)
    if data[:4] == PCAPNG_SHB:
        return read_pcapng(data)
    out = Datagrams()
    out.add(data, float("nan"), "raw")
    return out


@dataclass
class Blocks:
    """ASTERIX data blocks of a recording: category, bytes, and where each came from."""

    cat: NDArray[np.int64]
    data: list[bytes]
    datagram: NDArray[np.int64]      # index into Datagrams
    offset: NDArray[np.int64]        # byte offset inside the datagram
    problems: list[tuple[int, int, str]]


KNOWN = frozenset((21, 34, 48, 62))


def _plausible(payload: bytes, p: int, depth: int = 2) -> bool:
    """A block header of a known category at ``p`` whose length fits, followed by the end of the
    payload or (``depth`` headers deep) another such header."""
    if len(payload) - p < 3 or payload[p] not in KNOWN:
        return False
    n = (payload[p + 1] << 8) | payload[p + 2]
    if n < 4 or p + n > len(payload):
        return False
    return p + n == len(payload) or depth <= 1 or _plausible(payload, p + n, depth - 1)


def _resync(payload: bytes, start: int) -> int:
    """Offset of the next plausible data block after a broken one (len(payload) if none)."""
    p = start
    while p < len(payload) and not _plausible(payload, p):
        p += 1
    return p


def split_blocks(grams: Datagrams) -> Blocks:
    """Cut every payload into ``CAT | LEN | records`` data blocks (EUROCONTROL Part 1 §4).

    A length field below 3 or beyond the payload breaks the chain of blocks: that block is a
    problem and reading resumes at the next plausible header (a known category whose length fits
    and is followed by the end of the payload or another such header); the bytes skipped are a
    problem of their own. A raw recording thus loses one block, not its remainder.
    """
    cats, data, gram, offs, problems = [], [], [], [], list(grams.problems)
    for g, payload in enumerate(grams.payloads):
        off = 0
        while off < len(payload):
            if len(payload) - off < 3:
                problems.append((g, off, f"{len(payload) - off} trailing byte(s), shorter than a data block header"))
                break
            n = (payload[off + 1] << 8) | payload[off + 2]
            if n < 3 or off + n > len(payload):
                problems.append((g, off, f"CAT{payload[off]:03d} data block length {n} "
                                         f"{'below 3' if n < 3 else f'beyond the {len(payload) - off} bytes left'}"))
                nxt = _resync(payload, off + 1)
                if nxt < len(payload) and nxt > off + 1:
                    problems.append((g, off + 1, f"{nxt - off - 1} byte(s) skipped to the next data block"))
                off = nxt
                continue
            cats.append(payload[off])
            data.append(payload[off:off + n])
            gram.append(g)
            offs.append(off)
            off += n
    return Blocks(np.asarray(cats, np.int64), data, np.asarray(gram, np.int64), np.asarray(offs, np.int64), problems)
