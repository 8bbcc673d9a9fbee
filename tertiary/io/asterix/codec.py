"""libasterix as codec: the editions used, record decoding to plain values, record encoding.

``libasterix`` (module ``asterix``) takes ~2.4 s to import: :func:`lib` imports it on first use,
so that ``import tertiary`` and the CLI stay fast (``tests/test_asterix.py::test_import_is_lazy``).
Each data block is parsed on its own (a whole multi-block file in one call hits a
RecursionError). Parsing never raises: libasterix returns ``ValueError`` objects, which become
reject reasons.
"""

from __future__ import annotations

import functools
from types import ModuleType
from typing import Any

#: category -> edition name in asterix.generated (decode and encode)
EDITIONS = {1: "Cat_001_1_4", 2: "Cat_002_1_2", 4: "Cat_004_1_13", 20: "Cat_020_1_11", 21: "Cat_021_2_7",
            34: "Cat_034_1_29", 48: "Cat_048_1_32", 62: "Cat_062_1_21"}
SUPPORTED = ", ".join(f"CAT{c:03d}" for c in EDITIONS)
NM = 1852.0


@functools.cache
def lib() -> tuple[ModuleType, ModuleType]:
    """(asterix.base, asterix.generated), imported on first use: deferred for its import time,
    as an optional dependency is (the modules that import this one load with the CLI)."""
    import asterix.base as base
    import asterix.generated as gen
    return base, gen


def spec(cat: int) -> Any:
    """The libasterix specification class of a category's edition."""
    return getattr(lib()[1], EDITIONS[cat])


def parse_block(block: bytes) -> list[Any] | str:
    """The records of one data block (``CAT | LEN | records``), or the libasterix reason."""
    base, _ = lib()
    cat = block[0]
    if cat not in EDITIONS:
        return f"category {cat} not supported ({SUPPORTED} are)"
    try:
        bits = base.Bits.from_bytes(block[3:])
        recs = parse_selected(cat, bits) if cat == 1 else spec(cat).cv_uap.parse(bits)
    except RecursionError:   # pragma: no cover - one block is small; kept as a guard
        return "record structure too deep to parse"
    if isinstance(recs, ValueError):
        return f"CAT{cat:03d} record: {recs}"
    return recs


def parse_selected(cat: int, bits: Any) -> list[Any] | ValueError:
    """Records of a two-UAP category (CAT001: plot / track by I001/020 TYP), which libasterix
    parses only with a given UAP: each record is parsed with each class and kept with the one
    its own selector names (none: the block is refused)."""
    base, _ = lib()
    uap = spec(cat).cv_uap
    (items, table) = uap.cv_selector
    out = []
    while len(bits):
        for name, record in uap.cv_uaps.items():
            res = record.parse(base.ParsingMode.StrictParsing, bits)
            if isinstance(res, ValueError):
                continue
            rec, rest = res
            sel = rec.get_item(items[0])
            if sel is not None and table.get(sel.variation.get_item(items[1]).as_uint()) == name:
                out.append(rec)
                bits = rest
                break
        else:
            return ValueError("no record class (plot or track) parses this record with its own selector")
    return out


# --------------------------------------------------------------------------- field access


def sub_uint(rec: Any, name: str, sub: str) -> int | None:
    it = rec.get_item(name)
    return None if it is None else it.variation.get_item(sub).as_uint()


def sub_qty(rec: Any, name: str, sub: str, unit: str) -> float | None:
    it = rec.get_item(name)
    return None if it is None else it.variation.get_item(sub).variation.content.as_quantity(unit)


def qty(rec: Any, name: str, unit: str) -> float | None:
    it = rec.get_item(name)
    return None if it is None else it.variation.content.as_quantity(unit)


def uint(rec: Any, name: str) -> int | None:
    it = rec.get_item(name)
    return None if it is None else it.as_uint()


def text(rec: Any, name: str) -> str | None:
    it = rec.get_item(name)
    return None if it is None else it.variation.content.as_string()


def ref048(rec: Any) -> dict[str, int]:
    """The raw CAT048 fields of :data:`tertiary.io.asterix.fast048.FIELDS` through libasterix's own
    subitem accessors (the reference the compiled decoder is checked against); -1 = absent."""
    def g(v: int | None) -> int:
        return -1 if v is None else int(v)
    i020, i170 = rec.get_item("020"), rec.get_item("170")
    tre = i170.variation.get_item("TRE") if i170 is not None else None
    row = {
        "sac": g(sub_uint(rec, "010", "SAC")), "sic": g(sub_uint(rec, "010", "SIC")), "tod": g(uint(rec, "140")),
        "i020": -1 if i020 is None else i020.variation.unparse().to_bytes()[0],
        "rho": g(sub_uint(rec, "040", "RHO")), "theta": g(sub_uint(rec, "040", "THETA")),
        "i070": g(uint(rec, "070")), "i090": g(uint(rec, "090")), "i220": g(uint(rec, "220")),
        "i240": g(uint(rec, "240")), "i161": g(uint(rec, "161")), "i042": g(uint(rec, "042")),
        "gs": g(sub_uint(rec, "200", "GSP")), "hdg": g(sub_uint(rec, "200", "HDG")),
        "i170a": -1 if i170 is None else i170.variation.unparse().to_bytes()[0],
        "i170b": -1 if tre is None else i170.variation.unparse().to_bytes()[1],
        "mb40": -1, "mb50": -1, "mb60": -1,
    }
    i250 = rec.get_item("250")
    for reg in [] if i250 is None else i250.variation.get_list():    # the first register of each kind
        key = f"mb{reg.get_item('BDS1').as_uint():x}{reg.get_item('BDS2').as_uint():x}"
        if row.get(key) == -1:
            row[key] = reg.get_item("MBDATA").as_uint()
    return row


# --------------------------------------------------------------------------- encoding


def datablock(cat: int, records: list[Any]) -> bytes:
    """One data block holding ``records`` (libasterix records of ``cat``)."""
    return spec(cat).create(records).unparse().to_bytes()
