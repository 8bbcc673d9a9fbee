"""Compiled record walker driven by a libasterix specification (numba), for bulk categories
beyond CAT048 (CAT021 ADS-B).

:func:`program` turns a libasterix record class into flat arrays — per UAP slot its kind and
sizes, compound subfields in a side table — and :func:`walk` parses data blocks with them in
compiled code, returning the byte offset of every top-level item of every record (-1 when
absent). Field values are then read with numpy at those offsets (:func:`uint_at`). It accepts
and refuses exactly what libasterix strict parsing does (a failing record refuses its block);
``tests/test_asterix_fast.py`` checks it record for record, fuzzed bytes included.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from tertiary.io.asterix import codec

FIXED, EXTENDED, REP_COUNT, REP_FX, EXPLICIT, COMPOUND, SPARE, UNDEFINED = range(8)
ERRORS = {1: "record truncated in FSPEC", 2: "FSPEC too long", 3: "item truncated",
          4: "extended item: FX set in its last group", 5: "compound item: bad primary subfield",
          6: "explicit item of length 0", 7: "FSPEC bit set for a spare item"}


@dataclass(frozen=True)
class Program:
    """Flat parsing program of one record class (see the module docstring)."""

    names: tuple[str | None, ...]          # item name per UAP slot (None: spare)
    fspec_max: int
    kind: NDArray[np.int64]                # per slot
    p1: NDArray[np.int64]
    p2: NDArray[np.int64]
    sub_start: NDArray[np.int64]           # compound: first subfield row, count in p2
    sub_kind: NDArray[np.int64]
    sub_p1: NDArray[np.int64]
    sub_p2: NDArray[np.int64]
    groups: NDArray[np.int64]              # extended, rows p1 .. p1 + p2: 2 · octets + (group ends in FX)

    def slot(self, name: str) -> int:
        return self.names.index(name)


def _variation_kind(var: Any, groups: list[int]) -> tuple[int, int, int]:
    """(kind, p1, p2) of a non-compound variation; extended groups appended to ``groups``."""
    base, _ = codec.lib()
    if issubclass(var, (base.Element, base.Group)):
        if var.cv_bit_size % 8:
            raise ValueError(f"{var.__name__}: {var.cv_bit_size} bits is not whole octets")
        return FIXED, var.cv_bit_size // 8, 0
    if issubclass(var, base.Extended):
        start = len(groups)
        for g in var.cv_items_list:
            fx = any(x is None for x in g)
            bits = sum(x[1] for x in g if x is not None) + fx
            if bits % 8:
                raise ValueError(f"{var.__name__}: extended group of {bits} bits")
            groups.append(2 * (bits // 8) + fx)
        return EXTENDED, start, len(var.cv_items_list)
    if issubclass(var, base.Repetitive):
        elem = var.cv_variation
        if var.cv_rep_bytes is None:
            if elem.cv_bit_size != 7:
                raise ValueError(f"{var.__name__}: FX repetition of {elem.cv_bit_size} bits")
            return REP_FX, 1, 0
        if elem.cv_bit_size % 8:
            raise ValueError(f"{var.__name__}: element of {elem.cv_bit_size} bits")
        return REP_COUNT, var.cv_rep_bytes, elem.cv_bit_size // 8
    if issubclass(var, base.Explicit):
        return EXPLICIT, 0, 0
    raise ValueError(f"{var.__name__}: variation not supported by the compiled walker")


def program(record: Any) -> Program:
    """The flat program of a libasterix record class (e.g. ``codec.spec(21).cv_record``)."""
    base, _ = codec.lib()
    names, kind, p1, p2, sub_start = [], [], [], [], []
    sub_kind, sub_p1, sub_p2, groups = [], [], [], []
    for uap_item in record.cv_items_list:
        nsp = getattr(uap_item, "cv_non_spare", None)
        if nsp is None:
            names.append(None)
            kind.append(SPARE), p1.append(0), p2.append(0), sub_start.append(0)
            continue
        names.append(nsp.cv_name)
        var = nsp.cv_rule.cv_variation
        if issubclass(var, base.Compound):
            sub_start.append(len(sub_kind))
            kind.append(COMPOUND), p1.append(var.cv_fspec_max_bytes), p2.append(len(var.cv_items_list))
            for sub in var.cv_items_list:
                k = (UNDEFINED, 0, 0) if sub is None else _variation_kind(sub.cv_rule.cv_variation, groups)
                sub_kind.append(k[0]), sub_p1.append(k[1]), sub_p2.append(k[2])
        else:
            k = _variation_kind(var, groups)
            kind.append(k[0]), p1.append(k[1]), p2.append(k[2]), sub_start.append(0)
    a = lambda v: np.asarray(v if v else [0], np.int64)  # noqa: E731 - numba needs non-empty arrays
    return Program(tuple(names), record.cv_fspec_max_bytes, a(kind), a(p1), a(p2), a(sub_start), a(sub_kind),
                   a(sub_p1), a(sub_p2), a(groups))


@numba.njit(cache=True)
def _simple(buf, pos, end, kind, p1, p2, groups):  # noqa: ANN001, ANN202 - numba kernel
    """End offset of a non-compound item at ``pos``, or -code."""
    if kind == FIXED:
        return pos + p1 if pos + p1 <= end else -3
    if kind == EXTENDED:     # libasterix: groups until FX = 0; FX = 1 in the last group is an error
        for g in range(p2):
            pos += groups[p1 + g] >> 1
            if pos > end:
                return -3
            if (groups[p1 + g] & 1) == 0 or (buf[pos - 1] & 1) == 0:
                return pos
            if g == p2 - 1:
                return -4
        return pos
    if kind == REP_COUNT:
        if pos + p1 > end:
            return -3
        n = 0
        for i in range(p1):
            n = (n << 8) | buf[pos + i]
        stop = pos + p1 + n * p2
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
    return -5


@numba.njit(cache=True)
def _fspec(buf, pos, end, fmax):  # noqa: ANN001, ANN202 - numba kernel
    """Octets of the FSPEC at ``pos`` (FX-chained), or -code (libasterix: too long, then cut)."""
    n = 0
    while pos + n < end:
        n += 1
        if (buf[pos + n - 1] & 1) == 0:
            return n if n <= fmax else -2
    if n > fmax:
        return -2
    return -1


@numba.njit(cache=True)
def _compound(buf, pos, end, start, count, fmax, sub_kind, sub_p1, sub_p2, groups):  # noqa: ANN001, ANN202
    nf = _fspec(buf, pos, end, fmax)
    if nf < 0:
        return -5 if nf == -2 else -3
    p = pos + nf
    for o in range(nf):
        octet = buf[pos + o]
        for b in range(7):
            if octet & (0x80 >> b):
                j = o * 7 + b
                if j >= count or sub_kind[start + j] == UNDEFINED:
                    return -5
                p = _simple(buf, p, end, sub_kind[start + j], sub_p1[start + j], sub_p2[start + j], groups)
                if p < 0:
                    return p
    return p


@numba.njit(cache=True)
def _record(buf, pos, end, fmax, kind, p1, p2, sub_start, sub_kind, sub_p1, sub_p2, groups, offs, fill):  # noqa
    """Parse one record; item offsets into ``offs`` when ``fill``. End offset or -code."""
    nf = _fspec(buf, pos, end, fmax)
    if nf < 0:
        return nf
    if fill:
        offs[:] = -1
    p = pos + nf
    for o in range(nf):
        octet = buf[pos + o]
        for b in range(7):
            if octet & (0x80 >> b):
                s = o * 7 + b
                if s >= kind.shape[0] or kind[s] == SPARE:
                    return -7
                if fill:
                    offs[s] = p
                if kind[s] == COMPOUND:
                    q = _compound(buf, p, end, sub_start[s], p2[s], p1[s], sub_kind, sub_p1, sub_p2, groups)
                else:
                    q = _simple(buf, p, end, kind[s], p1[s], p2[s], groups)
                if q < 0:
                    return q
                p = q
    return p


@numba.njit(cache=True)
def _walk(buf, starts, ends, fmax, kind, p1, p2, sub_start, sub_kind, sub_p1, sub_p2, groups, fill, out, block,
          rec_start, rec_end, counts):  # noqa: ANN001, ANN202 - numba kernel
    """Count (fill = False: ``counts`` = records or -code per block) or fill item offsets."""
    scratch = np.empty(kind.shape[0], np.int64)
    r = 0
    for k in range(starts.shape[0]):
        if fill and counts[k] <= 0:
            continue
        pos, end, n = starts[k], ends[k], 0
        while pos < end:
            row = out[r] if fill else scratch
            q = _record(buf, pos, end, fmax, kind, p1, p2, sub_start, sub_kind, sub_p1, sub_p2, groups, row, fill)
            if q < 0:
                n = q
                rec_start[k] = pos      # where the failing record starts (count pass)
                break
            if fill:
                block[r] = k
                rec_start[r] = pos
                rec_end[r] = q
                r += 1
            n += 1
            pos = q
        if not fill:
            counts[k] = n


def walk(blocks: list[bytes], prog: Program) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64],
                                                      NDArray[np.int64], NDArray[np.int64], list[tuple[int, int, str]]]:
    """Parse data blocks: (buffer, item offsets [records × slots], block index, record start,
    record end — offsets into the buffer of the blocks' record parts — and the refused blocks
    as (block index, byte offset in the block, reason))."""
    body = [b[3:] for b in blocks]
    lens = np.fromiter((len(b) for b in body), np.int64, len(body))
    ends = np.cumsum(lens)
    starts = ends - lens
    buf = np.frombuffer(b"".join(body), np.uint8) if body else np.zeros(0, np.uint8)
    args = (prog.fspec_max, prog.kind, prog.p1, prog.p2, prog.sub_start, prog.sub_kind, prog.sub_p1, prog.sub_p2,
            prog.groups)
    counts = np.zeros(len(blocks), np.int64)
    fail_at = np.zeros(len(blocks), np.int64)
    dummy = np.zeros((1, len(prog.kind)), np.int64)
    _walk(buf, starts, ends, *args, False, dummy, counts, fail_at, counts, counts)
    n = int(counts[counts > 0].sum())
    out = np.empty((n, len(prog.kind)), np.int64)
    block, rs, re = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
    _walk(buf, starts, ends, *args, True, out, block, rs, re, counts)
    bad = [(int(k), int(fail_at[k] - starts[k]) + 3, f"CAT{blocks[k][0]:03d} record: {ERRORS[-int(counts[k])]}")
           for k in np.flatnonzero(counts < 0)]
    return buf, out, block, rs, re, bad


def uint_at(buf: NDArray[np.uint8], offs: NDArray[np.int64], start: int, width: int) -> NDArray[np.int64]:
    """Big-endian unsigned integers of ``width`` octets at ``offs + start`` (-1 where offs < 0)."""
    ok = offs >= 0
    pos = np.where(ok, offs + start, 0)
    v = np.zeros(len(offs), np.int64)
    for i in range(width):
        v = (v << 8) | buf[pos + i].astype(np.int64) if len(buf) else v
    return np.where(ok, v, -1)


def signed(v: NDArray[np.int64], bits: int) -> NDArray[np.int64]:
    """Two's complement of ``bits``-bit fields (absent -1 values stay meaningless: mask first)."""
    return np.where(v >= 1 << (bits - 1), v - (1 << bits), v)
