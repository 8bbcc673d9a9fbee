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
                if sub_kind[start + j] == FIXED:
                    p = p + sub_p1[start + j] if p + sub_p1[start + j] <= end else -3
                else:
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
                if kind[s] == FIXED:          # most items: no call
                    q = p + p1[s] if p + p1[s] <= end else -3
                elif kind[s] == COMPOUND:
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


@numba.njit(cache=True)
def _walk_once(buf, starts, ends, fmax, kind, p1, p2, sub_start, sub_kind, sub_p1, sub_p2, groups, out, block,
               rec_start, rec_end, counts, fail_at):  # noqa: ANN001, ANN202 - numba kernel
    """Count and fill in one pass into ``out`` of a guessed size: rows written, or -1 when
    ``out`` is too small. A refused block's rows are taken back (the block is refused whole)."""
    r = 0
    for k in range(starts.shape[0]):
        pos, end, n, r0 = starts[k], ends[k], 0, r
        while pos < end:
            if r >= out.shape[0]:
                return -1
            q = _record(buf, pos, end, fmax, kind, p1, p2, sub_start, sub_kind, sub_p1, sub_p2, groups, out[r], True)
            if q < 0:
                n, fail_at[k], r = q, pos, r0
                break
            block[r], rec_start[r], rec_end[r] = k, pos, q
            r += 1
            n += 1
            pos = q
        counts[k] = n
    return r


def _layout(blocks: list[bytes]) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64]]:
    """The blocks' record parts concatenated, and where each starts and ends."""
    body = [b[3:] for b in blocks]
    lens = np.fromiter((len(b) for b in body), np.int64, len(body))
    ends = np.cumsum(lens)
    buf = np.frombuffer(b"".join(body), np.uint8) if body else np.zeros(0, np.uint8)
    return buf, ends - lens, ends


#: largest offsets matrix a one-pass walk allocates on a guess (bytes)
ONE_PASS_BYTES = 1 << 29


def _guess_rows(buf: NDArray[np.uint8], first_len: int, width: int) -> int:
    """Rows for a one-pass walk: 1.5 × what records as long as the first would fill (one pass
    instead of count + fill); 0 (the two passes) without a first record or when that would
    allocate more than :data:`ONE_PASS_BYTES`. Shorter records later overflow it: two passes."""
    rows = int(1.5 * len(buf) / first_len) + 64 if first_len > 0 else 0
    return rows if rows * width * 8 <= ONE_PASS_BYTES else 0


def walk(blocks: list[bytes], prog: Program) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64],
                                                      NDArray[np.int64], NDArray[np.int64], list[tuple[int, int, str]]]:
    """Parse data blocks: (buffer, item offsets [records × slots], block index, record start,
    record end — offsets into the buffer of the blocks' record parts — and the refused blocks
    as (block index, byte offset in the block, reason))."""
    buf, starts, ends = _layout(blocks)
    args = (prog.fspec_max, prog.kind, prog.p1, prog.p2, prog.sub_start, prog.sub_kind, prog.sub_p1, prog.sub_p2,
            prog.groups)
    counts = np.zeros(len(blocks), np.int64)
    fail_at = np.zeros(len(blocks), np.int64)
    width = len(prog.kind)
    first = _record(buf, starts[0], ends[0], *args, np.zeros(width, np.int64), False) - starts[0] if len(blocks) \
        else 0          # negative when the first record fails: then two passes
    rows = _guess_rows(buf, int(first), width)
    out = np.empty((rows, width), np.int64)
    block, rs, re = np.empty(rows, np.int64), np.empty(rows, np.int64), np.empty(rows, np.int64)
    n = _walk_once(buf, starts, ends, *args, out, block, rs, re, counts, fail_at)
    if n < 0:
        dummy = np.zeros((1, width), np.int64)
        _walk(buf, starts, ends, *args, False, dummy, counts, fail_at, counts, counts)
        n = int(counts[counts > 0].sum())
        out = np.empty((n, width), np.int64)
        block, rs, re = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
        _walk(buf, starts, ends, *args, True, out, block, rs, re, counts)
    bad = [(int(k), int(fail_at[k] - starts[k]) + 3, f"CAT{blocks[k][0]:03d} record: {ERRORS[-int(counts[k])]}")
           for k in np.flatnonzero(counts < 0)]
    return buf, out[:n], block[:n], rs[:n], re[:n], bad


@numba.njit(cache=True)
def _uint_at(buf, offs, start, width):  # noqa: ANN001, ANN202 - numba kernel
    out = np.empty(offs.shape[0], np.int64)
    for i in range(offs.shape[0]):
        if offs[i] < 0:
            out[i] = -1
            continue
        v = 0
        for j in range(width):
            v = (v << 8) | buf[offs[i] + start + j]
        out[i] = v
    return out


def uint_at(buf: NDArray[np.uint8], offs: NDArray[np.int64], start: int, width: int) -> NDArray[np.int64]:
    """Big-endian unsigned integers of ``width`` octets at ``offs + start`` (-1 where offs < 0)."""
    return _uint_at(buf, np.ascontiguousarray(offs, np.int64), start, width)


def signed(v: NDArray[np.int64], bits: int) -> NDArray[np.int64]:
    """Two's complement of ``bits``-bit fields (absent -1 values stay meaningless: mask first)."""
    return np.where(v >= 1 << (bits - 1), v - (1 << bits), v)


# --------------------------------------------------------------------------- two record classes (CAT001)

#: error of a two-UAP record whose selector item is absent
NO_SELECTOR = 8
ERRORS[NO_SELECTOR] = "no selector item: plot or track record unknown"


@numba.njit(cache=True)
def _select(buf, pos, end, fmax, lead_bytes):  # noqa: ANN001, ANN202 - numba kernel
    """The selector bit (first bit of FRN 2, after a fixed FRN 1 of ``lead_bytes``), or -code."""
    nf = _fspec(buf, pos, end, fmax)
    if nf < 0:
        return nf
    if (buf[pos] & 0x40) == 0:
        return -NO_SELECTOR
    p = pos + nf + (lead_bytes if buf[pos] & 0x80 else 0)
    if p >= end:
        return -3
    return np.int64(buf[p] >> 7)


@numba.njit(cache=True)
def _walk_sel(buf, starts, ends, fmax, lead, a, b, fill, out, uap, block, rec_start, rec_end, counts):  # noqa
    """:func:`_walk` for records whose class is chosen per record by :func:`_select` (0: ``a``, 1: ``b``)."""
    scratch = np.empty(out.shape[1], np.int64)
    r = 0
    for k in range(starts.shape[0]):
        if fill and counts[k] <= 0:
            continue
        pos, end, n = starts[k], ends[k], 0
        while pos < end:
            row = out[r] if fill else scratch
            sel = _select(buf, pos, end, fmax, lead)
            if sel < 0:
                q = sel
            elif sel == 0:
                q = _record(buf, pos, end, a[0][0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], row, fill)
            else:
                q = _record(buf, pos, end, b[0][0], b[1], b[2], b[3], b[4], b[5], b[6], b[7], b[8], row, fill)
            if q < 0:
                n = q
                rec_start[k] = pos
                break
            if fill:
                uap[r] = sel
                block[r] = k
                rec_start[r] = pos
                rec_end[r] = q
                r += 1
            n += 1
            pos = q
        if not fill:
            counts[k] = n


@numba.njit(cache=True)
def _walk_sel_once(buf, starts, ends, fmax, lead, a, b, out, uap, block, rec_start, rec_end, counts, fail_at):  # noqa
    """:func:`_walk_once` for two record classes (:func:`_walk_sel`)."""
    r = 0
    for k in range(starts.shape[0]):
        pos, end, n, r0 = starts[k], ends[k], 0, r
        while pos < end:
            if r >= out.shape[0]:
                return -1
            sel = _select(buf, pos, end, fmax, lead)
            if sel < 0:
                q = sel
            elif sel == 0:
                q = _record(buf, pos, end, a[0][0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], out[r], True)
            else:
                q = _record(buf, pos, end, b[0][0], b[1], b[2], b[3], b[4], b[5], b[6], b[7], b[8], out[r], True)
            if q < 0:
                n, fail_at[k], r = q, pos, r0
                break
            uap[r], block[r], rec_start[r], rec_end[r] = sel, k, pos, q
            r += 1
            n += 1
            pos = q
        counts[k] = n
    return r


def _arrays(prog: Program, width: int) -> tuple[NDArray[np.int64], ...]:
    """A program's arrays for the kernel; the slot arrays padded to ``width`` with spare slots."""
    pad = width - len(prog.kind)
    k = np.concatenate([prog.kind, np.full(pad, SPARE, np.int64)])
    z = np.zeros(pad, np.int64)
    return (np.array([prog.fspec_max], np.int64), k, np.concatenate([prog.p1, z]), np.concatenate([prog.p2, z]),
            np.concatenate([prog.sub_start, z]), prog.sub_kind, prog.sub_p1, prog.sub_p2, prog.groups)


def _first_length(buf: NDArray[np.uint8], starts: NDArray[np.int64], ends: NDArray[np.int64], fmax: int,
                  lead: int, pa: tuple[NDArray[np.int64], ...], pb: tuple[NDArray[np.int64], ...], width: int) -> int:
    """Length of the first record of the first block (0 when none parses)."""
    if not len(starts):
        return 0
    one, end = np.zeros(1, np.int64), np.zeros(1, np.int64)
    # one row: stops after the first record (its end in ``end``), or takes it back when it fails
    _walk_sel_once(buf, starts[:1], ends[:1], fmax, lead, pa, pb, np.zeros((1, width), np.int64), one, one.copy(),
                   one.copy(), end, one.copy(), one.copy())
    return int(end[0] - starts[0]) if end[0] > starts[0] else 0


def walk_select(blocks: list[bytes], a: Program, b: Program, lead_bytes: int
                ) -> tuple[NDArray[np.uint8], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64],
                           NDArray[np.int64], NDArray[np.int64], list[tuple[int, int, str]]]:
    """:func:`walk` for a category with two record classes chosen by the first bit of the item
    at FRN 2 (CAT001 I001/020 TYP: 0 plot, 1 track); FRN 1 is fixed, ``lead_bytes`` long.
    Returns (buffer, offsets, record class 0/1, block, record start, record end, refused)."""
    buf, starts, ends = _layout(blocks)
    width = max(len(a.kind), len(b.kind))
    pa, pb = _arrays(a, width), _arrays(b, width)
    # the selector's FSPEC bound is the larger one; each class then checks its own
    fmax = max(a.fspec_max, b.fspec_max)
    counts = np.zeros(len(blocks), np.int64)
    fail_at = np.zeros(len(blocks), np.int64)
    first = _first_length(buf, starts, ends, fmax, lead_bytes, pa, pb, width)
    rows = _guess_rows(buf, first, width)
    out = np.empty((rows, width), np.int64)
    uap, block = np.empty(rows, np.int64), np.empty(rows, np.int64)
    rs, re = np.empty(rows, np.int64), np.empty(rows, np.int64)
    n = _walk_sel_once(buf, starts, ends, fmax, lead_bytes, pa, pb, out, uap, block, rs, re, counts, fail_at)
    if n < 0:
        dummy = np.zeros((1, width), np.int64)
        _walk_sel(buf, starts, ends, fmax, lead_bytes, pa, pb, False, dummy, counts, counts, fail_at, counts, counts)
        n = int(counts[counts > 0].sum())
        out = np.empty((n, width), np.int64)
        uap, block = np.empty(n, np.int64), np.empty(n, np.int64)
        rs, re = np.empty(n, np.int64), np.empty(n, np.int64)
        _walk_sel(buf, starts, ends, fmax, lead_bytes, pa, pb, True, out, uap, block, rs, re, counts)
    out, uap, block, rs, re = out[:n], uap[:n], block[:n], rs[:n], re[:n]
    bad = [(int(k), int(fail_at[k] - starts[k]) + 3, f"CAT{blocks[k][0]:03d} record: {ERRORS[-int(counts[k])]}")
           for k in np.flatnonzero(counts < 0)]
    return buf, out, uap, block, rs, re, bad


@numba.njit(cache=True)
def record_hash(buf, rs, re):  # noqa: ANN001, ANN201 - numba kernel
    """FNV-1a 64 of each record's bytes (the de-duplication key of redundant lines)."""
    out = np.empty(rs.shape[0], np.int64)
    for i in range(rs.shape[0]):
        h = np.uint64(14695981039346656037)
        for j in range(rs[i], re[i]):
            h = (h ^ np.uint64(buf[j])) * np.uint64(1099511628211)
        out[i] = np.int64(h)
    return out


@numba.njit(cache=True)
def _sub_offsets(buf, offs, sizes):  # noqa: ANN001, ANN202 - numba kernel
    out = np.full((sizes.shape[0], offs.shape[0]), -1, np.int64)
    for i in range(offs.shape[0]):
        pos = offs[i]
        if pos < 0:
            continue
        nf = 1
        while buf[pos + nf - 1] & 1:
            nf += 1
        p = pos + nf
        for j in range(sizes.shape[0]):
            if j // 7 >= nf or (buf[pos + j // 7] & (0x80 >> (j % 7))) == 0:
                continue
            out[j, i] = p
            if sizes[j] > 0:
                p += sizes[j]
            elif sizes[j] == 0:
                p += 1
                while buf[p - 1] & 1:
                    p += 1
            else:
                break            # a subfield not read here: those after it are not placed
    return out


def sub_offsets(buf: NDArray[np.uint8], offs: NDArray[np.int64], sizes: tuple[int, ...]) -> list[NDArray[np.int64]]:
    """Offsets of the subfields of a compound item at ``offs`` (-1 where item or subfield is
    absent). ``sizes``: octets per subfield in FSPEC order, 0 for an extended subfield of
    one-octet groups (its length read from the FX bits), -1 for one not read (the subfields
    after it are not placed). The item was validated by the walker."""
    out = _sub_offsets(buf, np.ascontiguousarray(offs, np.int64), np.asarray(sizes, np.int64))
    return list(out)
