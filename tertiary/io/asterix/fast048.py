"""Compiled CAT048 decoder (numba): the bulk path of the importer.

``libasterix`` (pure Python) decodes ~1 350 CAT048 records/s with field extraction; a national
day holds 50–90 M records. This module walks the same structure — FSPEC, then every item of the
CAT048 edition 1.32 UAP (:data:`LAYOUT`) — over a byte array in compiled code and extracts the
fields the importer uses as raw integers. It accepts and rejects exactly what
``asterix.generated.Cat_048_1_32`` strict parsing does (a record that fails rejects its whole
data block, as in libasterix); ``tests/test_asterix_fast.py`` checks that record for record on
the real recording, simulated recordings and fuzzed bytes. ``libasterix`` stays the reference
and the encoder.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

# item kinds of the UAP
FIXED, EXTENDED, REP_COUNT, REP_FX, EXPLICIT, COMPOUND = 0, 1, 2, 3, 4, 5

#: CAT048 ed. 1.32 UAP, FRN 1..28: (item, kind, size parameter). FIXED: octets; EXTENDED:
#: maximum one-octet groups (the last must end with FX = 0); REP_COUNT: octets per repetition
#: after a one-octet count; REP_FX: one-octet elements chained by FX; COMPOUND: the octet size of
#: each subfield after a one-octet primary subfield (0 = undefined bit).
LAYOUT: tuple[tuple[str, int, object], ...] = (
    ("010", FIXED, 2), ("140", FIXED, 3), ("020", EXTENDED, 6), ("040", FIXED, 4), ("070", FIXED, 2),
    ("090", FIXED, 2), ("130", COMPOUND, (1, 1, 1, 1, 1, 1, 1)),
    ("220", FIXED, 3), ("240", FIXED, 6), ("250", REP_COUNT, 8), ("161", FIXED, 2), ("042", FIXED, 4),
    ("200", FIXED, 4), ("170", EXTENDED, 2),
    ("210", FIXED, 4), ("030", REP_FX, 1), ("080", FIXED, 2), ("100", FIXED, 4), ("110", FIXED, 2),
    ("120", COMPOUND, (2, -6, 0, 0, 0, 0, 0)), ("230", FIXED, 2),     # -6: repetitive, 6 octets each
    ("260", FIXED, 7), ("055", FIXED, 1), ("050", FIXED, 2), ("065", FIXED, 1), ("060", FIXED, 2),
    ("SP", EXPLICIT, 0), ("RE", EXPLICIT, 0),
)
FSPEC_MAX = 4

_KIND = np.array([k for _, k, _ in LAYOUT], np.int64)
_SIZE = np.array([s if isinstance(s, int) else 0 for _, _, s in LAYOUT], np.int64)
_SUB = np.zeros((len(LAYOUT), 7), np.int64)
for _i, (_n, _k, _s) in enumerate(LAYOUT):
    if _k == COMPOUND:
        _SUB[_i] = _s

#: columns of the raw field matrix (value -1 where the item is absent); ``mb40``, ``mb50``,
#: ``mb60``: the 56-bit MB data of the first I048/250 register whose BDS1/BDS2 nibbles say 4,0,
#: 5,0, 6,0 (:mod:`tertiary.io.asterix.commb` reads them)
FIELDS = ("sac", "sic", "tod", "i020", "rho", "theta", "i070", "i090", "i220", "i240", "i161",
          "i042", "gs", "hdg", "i170a", "i170b", "offset", "length", "hash", "mb40", "mb50", "mb60")
_F = {name: i for i, name in enumerate(FIELDS)}
_MB_COL = _F["mb40"]            # mb50, mb60 follow it

ERRORS = {1: "record truncated in FSPEC", 2: "FSPEC longer than 4 octets", 3: "item truncated",
          4: "extended item: FX set in its last octet", 5: "compound item: bad primary subfield",
          6: "explicit item of length 0"}


@numba.njit(cache=True)
def _uint(buf: NDArray[np.uint8], pos: int, n: int) -> int:
    v = 0
    for i in range(n):
        v = (v << 8) | buf[pos + i]
    return v


@numba.njit(cache=True)
def _item(buf, pos, end, kind, size, sub):  # noqa: ANN001, ANN202 - numba kernel
    """End offset of one item starting at ``pos``, or -code."""
    if kind == FIXED:
        return pos + size if pos + size <= end else -3
    if kind == EXTENDED:
        for g in range(size):
            if pos >= end:
                return -3
            fx = buf[pos] & 1
            pos += 1
            if fx == 0:
                return pos
            if g == size - 1:
                return -4
        return pos
    if kind == REP_COUNT:
        if pos >= end:
            return -3
        stop = pos + 1 + buf[pos] * size
        return stop if stop <= end else -3
    if kind == REP_FX:
        while True:
            if pos >= end:
                return -3
            fx = buf[pos] & 1
            pos += 1
            if fx == 0:
                return pos
    if kind == EXPLICIT:
        if pos >= end:
            return -3
        n = buf[pos]
        if n == 0:
            return -6
        return pos + n if pos + n <= end else -3
    # COMPOUND with a one-octet primary subfield
    if pos >= end:
        return -3
    prim = buf[pos]
    pos += 1
    if prim & 1:
        return -5
    for b in range(7):
        if prim & (0x80 >> b):
            s = sub[b]
            if s == 0:
                return -5
            if s > 0:
                pos += s
                if pos > end:
                    return -3
            else:
                if pos >= end:
                    return -3
                pos = pos + 1 + buf[pos] * (-s)
                if pos > end:
                    return -3
    return pos


@numba.njit(cache=True)
def _record(buf, pos, end, kinds, sizes, subs, row, fill):  # noqa: ANN001, ANN202 - numba kernel
    """Parse one record at ``pos``; fill ``row`` (raw fields) when ``fill``. End offset or -code."""
    start = pos
    nf = 0
    while True:            # FSPEC: octets while FX = 1 (libasterix reads it over the whole rest)
        if pos + nf >= end:
            return -1
        nf += 1
        if (buf[pos + nf - 1] & 1) == 0:
            break
    if nf > FSPEC_MAX:
        return -2
    p = pos + nf
    if fill:
        for j in range(row.shape[0]):
            row[j] = -1
    for o in range(nf):
        octet = buf[pos + o]
        for b in range(7):
            if octet & (0x80 >> b):
                frn = o * 7 + b
                q = _item(buf, p, end, kinds[frn], sizes[frn], subs[frn])
                if q < 0:
                    return q
                if fill:
                    _extract(buf, p, frn, row)
                p = q
    if fill:
        row[16] = start
        row[17] = p - start
        h = np.uint64(14695981039346656037)      # FNV-1a 64 of the record bytes (de-duplication key)
        for i in range(start, p):
            h = (h ^ np.uint64(buf[i])) * np.uint64(1099511628211)
        row[18] = np.int64(h)
    return p


@numba.njit(cache=True)
def _extract(buf, p, frn, row):  # noqa: ANN001, ANN202 - numba kernel
    if frn == 0:
        row[0] = buf[p]
        row[1] = buf[p + 1]
    elif frn == 1:
        row[2] = _uint(buf, p, 3)
    elif frn == 2:
        row[3] = buf[p]
    elif frn == 3:
        row[4] = _uint(buf, p, 2)
        row[5] = _uint(buf, p + 2, 2)
    elif frn == 4:
        row[6] = _uint(buf, p, 2)
    elif frn == 5:
        row[7] = _uint(buf, p, 2)
    elif frn == 7:
        row[8] = _uint(buf, p, 3)
    elif frn == 8:
        row[9] = _uint(buf, p, 6)
    elif frn == 10:
        row[10] = _uint(buf, p, 2)
    elif frn == 11:
        row[11] = _uint(buf, p, 4)
    elif frn == 12:
        row[12] = _uint(buf, p, 2)
        row[13] = _uint(buf, p + 2, 2)
    elif frn == 13:
        row[14] = buf[p]
        row[15] = buf[p + 1] if buf[p] & 1 else -1
    elif frn == 9:              # I048/250: REP, then per register MB data (7 octets) | BDS1 BDS2
        for k in range(buf[p]):
            q = p + 1 + 8 * k
            bds = buf[q + 7]
            if bds == 0x40 or bds == 0x50 or bds == 0x60:
                j = _MB_COL + (bds >> 4) - 4
                if row[j] < 0:
                    row[j] = _uint(buf, q, 7)


@numba.njit(cache=True)
def _count(buf, starts, ends, kinds, sizes, subs):  # noqa: ANN001, ANN202 - numba kernel
    """Records per block, or -(code) for a block that fails (and the failing byte offset)."""
    nb = starts.shape[0]
    counts = np.zeros(nb, np.int64)
    where = np.zeros(nb, np.int64)
    scratch = np.empty(len(FIELDS), np.int64)
    for k in range(nb):
        pos, end, n = starts[k], ends[k], 0
        while pos < end:
            q = _record(buf, pos, end, kinds, sizes, subs, scratch, False)
            if q < 0:
                n, where[k] = q, pos
                break
            n += 1
            pos = q
        counts[k] = n
    return counts, where


@numba.njit(cache=True)
def _fill(buf, starts, ends, counts, kinds, sizes, subs, out, block):  # noqa: ANN001, ANN202
    r = 0
    for k in range(starts.shape[0]):
        if counts[k] <= 0:
            continue
        pos, end = starts[k], ends[k]
        while pos < end:
            pos = _record(buf, pos, end, kinds, sizes, subs, out[r], True)
            block[r] = k
            r += 1


def decode_blocks(blocks: list[bytes]) -> tuple[NDArray[np.int64], NDArray[np.int64], list[tuple[int, int, str]]]:
    """Decode CAT048 data blocks (each ``48 | LEN | records``).

    Returns the raw field matrix (one row per record, columns :data:`FIELDS`; ``offset`` is the
    record's byte offset in the concatenation of the blocks' record parts), the block index of
    every row, and the failing blocks as (block index, byte offset in the block, reason).
    """
    if not blocks:
        return np.empty((0, len(FIELDS)), np.int64), np.empty(0, np.int64), []
    body = [b[3:] for b in blocks]
    lens = np.fromiter((len(b) for b in body), np.int64, len(body))
    ends = np.cumsum(lens)
    starts = ends - lens
    buf = np.frombuffer(b"".join(body), np.uint8)
    counts, where = _count(buf, starts, ends, _KIND, _SIZE, _SUB)
    bad = []
    for k in np.flatnonzero(counts < 0):
        code, frn = _describe(buf, int(where[k]), int(ends[k]))
        bad.append((int(k), int(where[k] - starts[k]) + 3, f"CAT048 record: {ERRORS[code]}{frn}"))
    out = np.empty((int(counts[counts > 0].sum()), len(FIELDS)), np.int64)
    block = np.empty(len(out), np.int64)
    _fill(buf, starts, ends, counts, _KIND, _SIZE, _SUB, out, block)
    out[:, 16] -= starts[block]          # offset inside the block's record part
    return out, block, bad


def _describe(buf: NDArray[np.uint8], pos: int, end: int) -> tuple[int, str]:
    """Error code of the record at ``pos`` and the item it stopped in (rare path, Python)."""
    code = -int(_record(buf, pos, end, _KIND, _SIZE, _SUB, np.empty(len(FIELDS), np.int64), False))
    fspec = []
    p = pos
    while p < end:
        fspec.append(int(buf[p]))
        p += 1
        if not fspec[-1] & 1:
            break
    if code in (1, 2) or len(fspec) > FSPEC_MAX:
        return code, ""
    for o, octet in enumerate(fspec):
        for b in range(7):
            if octet & (0x80 >> b):
                frn = o * 7 + b
                q = _item(buf, p, end, _KIND[frn], _SIZE[frn], _SUB[frn])
                if q < 0:
                    return code, f" (I048/{LAYOUT[frn][0]})"
                p = q
    return code, ""


def field(raw: NDArray[np.int64], name: str) -> NDArray[np.int64]:
    """One raw column of :func:`decode_blocks`'s matrix."""
    return raw[:, _F[name]]
