"""Mode S Comm-B registers of I048/250 ↔ the ``reports`` enhanced-surveillance columns.

I048/250 repeats (56-bit MB data, BDS1, BDS2): the nibbles name the register the radar extracted.
Only registers the radar names 4,0, 5,0 or 6,0 are read (no register is inferred from its
content). Layouts from ICAO Doc 9871, Tables A-2-64 (BDS 4,0), A-2-80 (5,0) and A-2-96 (6,0); MB
bit 1 is the most significant. Every field has a status bit (0: not available, the column is
null); a signed field is a sign bit followed by its magnitude, the two read together as two's
complement:

======================  ========  ==========================  =========  ========================
column                  register  MB bits: status, value      LSB        encodable range
======================  ========  ==========================  =========  ========================
``selected_alt_m``      BDS 4,0   1, 2–13 (MCP/FCU)           16 ft      0 … 65 520 ft
``ehs_roll_deg``        BDS 5,0   1, 2–11 (signed)            45/256 °   −90 … +89.82 °
``ehs_track_deg``       BDS 5,0   12, 13–23 (signed, true)    90/512 °   wrapped to [0, 360)
``ehs_gs_mps``          BDS 5,0   24, 25–34                   2 kt       0 … 2 046 kt
``ehs_track_rate_dps``  BDS 5,0   35, 36–45 (signed)          8/256 °/s  −16 … +15.97 °/s
``ehs_vrate_mps``       BDS 6,0   46, 47–56 or 35, 36–45 (s)  32 ft/min  −16 384 … +16 352 ft/min
======================  ========  ==========================  =========  ========================

``ehs_vrate_mps`` is the inertial vertical velocity (bits 46–56) when its status is set, else
the barometric altitude rate (bits 35–45): the inertial value is the smoothed one and the one the
``reports`` contract names. Right wing down and clockwise turns are positive, as the registers
define them. The FMS selected altitude (BDS 4,0), true airspeed (5,0), magnetic heading, IAS and
Mach (6,0) have no column and are not read.

Doc 9871's declared range of each field equals what its bits can hold (the table's last column),
so a register the radar names cannot carry an out-of-range value of these fields: a field's
status bit is its only validity. A field whose status is 0 but whose value bits are not all zero
breaks the register's rule for an unavailable parameter (all its bits zero); it stays null and
is counted (:func:`status_conflicts`), as a sign of a damaged or mislabelled register.

The encoder (:func:`registers`) rounds to the LSB and saturates at the encodable limits (Doc 9871:
a value beyond the range is sent as the largest one of its sign); the true track wraps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tertiary.core.units import FT

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]
KT_MPS = 1852.0 / 3600.0
FPM_MPS = FT / 60.0
MB_BITS = 56


@dataclass(frozen=True)
class Field:
    """One field of a register: MB bit numbers (1 = most significant) and the LSB in the column's unit."""

    status: int          # the status bit
    first: int           # the first value bit (a signed field's sign bit)
    bits: int            # value bits, sign included
    lsb: float
    signed: bool = False
    circular: bool = False   # an angle: wraps to [0, 360) instead of saturating

    @property
    def limits(self) -> tuple[int, int]:
        """The smallest and largest raw value the bits hold."""
        if self.signed:
            return -(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1
        return 0, (1 << self.bits) - 1


SELECTED_ALT = Field(1, 2, 12, 16.0 * FT)
ROLL = Field(1, 2, 10, 45.0 / 256.0, signed=True)
TRACK = Field(12, 13, 11, 90.0 / 512.0, signed=True, circular=True)
GROUND_SPEED = Field(24, 25, 10, 2.0 * KT_MPS)
TRACK_RATE = Field(35, 36, 10, 8.0 / 256.0, signed=True)
BARO_RATE = Field(35, 36, 10, 32.0 * FPM_MPS, signed=True)
INERTIAL_RATE = Field(46, 47, 10, 32.0 * FPM_MPS, signed=True)

#: register (BDS1·16 + BDS2, the I048/250 octet after the MB data) → its fields with a column, in
#: the order the encoder fills them; ``ehs_vrate_mps`` is written to the inertial field
LAYOUT: dict[int, dict[str, Field]] = {
    0x40: {"selected_alt_m": SELECTED_ALT},
    0x50: {"ehs_roll_deg": ROLL, "ehs_track_deg": TRACK, "ehs_gs_mps": GROUND_SPEED,
           "ehs_track_rate_dps": TRACK_RATE},
    0x60: {"ehs_vrate_mps": INERTIAL_RATE},
}
#: the columns :func:`decode` returns
COLUMNS = ("selected_alt_m", "ehs_gs_mps", "ehs_track_deg", "ehs_track_rate_dps", "ehs_roll_deg", "ehs_vrate_mps")


def _bits(mb: I64, first: int, n: int) -> I64:
    """MB bits ``first`` … ``first + n − 1`` as an unsigned integer."""
    return (mb >> (MB_BITS + 1 - first - n)) & ((1 << n) - 1)


def field(mb: I64, f: Field) -> F64:
    """The value of field ``f`` of registers ``mb`` (−1: no register), NaN where absent or its status is 0."""
    raw = _bits(mb, f.first, f.bits)
    if f.signed:
        raw = np.where(raw >> (f.bits - 1) == 1, raw - (1 << f.bits), raw)
    ok = (mb >= 0) & (_bits(mb, f.status, 1) == 1)
    value = np.where(ok, raw * f.lsb, np.nan)
    return np.mod(value, 360.0) if f.circular else value


def decode(mb40: I64, mb50: I64, mb60: I64) -> dict[str, F64]:
    """The :data:`COLUMNS` (NaN = null) of each record's BDS 4,0, 5,0 and 6,0 MB data (−1: not sent)."""
    inertial, baro = field(mb60, INERTIAL_RATE), field(mb60, BARO_RATE)
    return {"selected_alt_m": field(mb40, SELECTED_ALT), "ehs_gs_mps": field(mb50, GROUND_SPEED),
            "ehs_track_deg": field(mb50, TRACK), "ehs_track_rate_dps": field(mb50, TRACK_RATE),
            "ehs_roll_deg": field(mb50, ROLL), "ehs_vrate_mps": np.where(np.isnan(inertial), baro, inertial)}


#: every field with a status bit of each register: (status bit, first value bit, value bits)
_STATUS_FIELDS = {
    0x40: ((1, 2, 12), (14, 15, 12), (27, 28, 12), (48, 49, 3), (54, 55, 2)),
    0x50: ((1, 2, 10), (12, 13, 11), (24, 25, 10), (35, 36, 10), (46, 47, 10)),
    0x60: ((1, 2, 11), (13, 14, 10), (24, 25, 10), (35, 36, 10), (46, 47, 10)),
}


def status_conflicts(mb: I64, bds: int) -> I64:
    """Per register of kind ``bds`` (0x40, 0x50, 0x60; −1: none), how many of its fields have
    status 0 but value bits set."""
    n = np.zeros(len(mb), np.int64)
    for status, first, bits in _STATUS_FIELDS[bds]:
        n += (mb >= 0) & (_bits(mb, status, 1) == 0) & (_bits(mb, first, bits) != 0)
    return n


def pack(values: F64, f: Field) -> I64:
    """Field ``f`` holding ``values`` (NaN: status 0, all bits 0) as bits of a 56-bit MB word:
    rounded to the LSB, saturated at the field's limits (an angle wraps)."""
    ok = np.isfinite(values)
    q = np.round(np.where(ok, values, 0.0) / f.lsb)
    lo, hi = f.limits
    raw = np.mod(q, 1 << f.bits) if f.circular else np.clip(q, lo, hi)
    raw = raw.astype(np.int64) & ((1 << f.bits) - 1)
    word = (1 << (MB_BITS - f.status)) | (raw << (MB_BITS + 1 - f.first - f.bits))
    return np.where(ok, word, 0)


def registers(columns: dict[str, F64], n: int) -> dict[int, I64]:
    """BDS 4,0, 5,0 and 6,0 MB data (keyed 0x40, 0x50, 0x60; −1 where the register is not sent:
    none of its columns known) of ``n`` reports from their columns (absent columns: null)."""
    out = {}
    for bds, fields in LAYOUT.items():
        word = np.zeros(n, np.int64)
        sent = np.zeros(n, bool)
        for name, f in fields.items():
            v = np.asarray(columns.get(name, np.full(n, np.nan)), float)
            word |= pack(v, f)
            sent |= np.isfinite(v)
        out[bds] = np.where(sent, word, -1)
    return out
