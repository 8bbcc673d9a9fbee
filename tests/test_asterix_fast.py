"""The compiled CAT048 decoder against libasterix, record for record, and bad bytes everywhere."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tertiary.io.asterix import capture, codec, dataset, encode, fast048
from tertiary.core.errors import TertiaryError

DATA = Path(__file__).parent / "data"
PCAP = DATA / "cat_034_048.pcap"
COLS = [c for c in fast048.FIELDS if c not in ("offset", "length", "hash")]


def _real_blocks() -> list[bytes]:
    b = capture.split_blocks(capture.read_recording(PCAP))
    return b.data


def _sim_blocks() -> list[bytes]:
    reports = pl.DataFrame({
        "radar_id": pl.Series([1, 2, 300, 1] * 5, dtype=pl.UInt32),
        "time": pl.datetime_range(pl.datetime(2024, 1, 1, 23, 59, 50, time_zone="UTC"),
                                  pl.datetime(2024, 1, 2, 0, 0, 9, time_zone="UTC"), "1s", eager=True),
        "local_track_id": pl.Series(np.arange(20) % 7 * 500, dtype=pl.UInt32),
        "range_m": np.linspace(100.0, 470000.0, 20), "azimuth_deg": np.linspace(0.0, 359.99, 20),
        "altitude_m": [None, 300.0, -300.0, 12000.0] * 5,
        "mode_s": [None, "abcdef", "000001", "ffffff"] * 5, "mode_3a": ["7777", None, "0000", "1234"] * 5,
        "callsign": ["AFR1", None, "Z9Z9Z9Z9", "A B"] * 5,
    })
    recs = encode.cat048(reports)
    return [codec.datablock(48, recs[i:i + 3]) for i in range(0, len(recs), 3)]


def _reference(block: bytes) -> list[dict[str, int]] | str:
    recs = codec.parse_block(block)
    return recs if isinstance(recs, str) else [codec.ref048(r) for r in recs]


def _same(blocks: list[bytes]) -> None:
    """Accepted/refused blocks and every field of every record equal to libasterix's."""
    raw, block, bad = fast048.decode_blocks(blocks)
    refused = {k for k, _, _ in bad}
    for k, data in enumerate(blocks):
        ref = _reference(data)
        if isinstance(ref, str):
            assert k in refused, (k, data.hex(), ref)
            continue
        assert k not in refused, (k, data.hex(), [b for b in bad if b[0] == k])
        rows = raw[block == k]
        assert len(rows) == len(ref)
        for row, r in zip(rows, ref):
            assert {c: int(row[fast048.FIELDS.index(c)]) for c in COLS} == r


def test_layout_matches_libasterix() -> None:
    """The hand-written UAP table equals the libasterix CAT048 1.32 specification."""
    base, _ = codec.lib()
    rec = codec.spec(48).cv_record
    assert rec.cv_fspec_max_bytes == fast048.FSPEC_MAX
    names = [n for n in rec.cv_items_dict if n is not None]
    assert names == [n for n, _, _ in fast048.LAYOUT]
    for name, kind, size in fast048.LAYOUT:
        var = rec.cv_items_dict[name].cv_rule.cv_variation
        if kind == fast048.FIXED:
            assert var.cv_bit_size == size * 8, name
        elif kind == fast048.EXTENDED:
            assert len(var.cv_items_list) == size, name
        elif kind == fast048.REP_COUNT:
            assert var.cv_rep_bytes == 1 and var.cv_variation.cv_bit_size == size * 8, name
        elif kind == fast048.REP_FX:
            assert var.cv_rep_bytes is None and var.cv_variation.cv_bit_size == 7, name
        elif kind == fast048.EXPLICIT:
            assert issubclass(var, base.Explicit), name
        else:
            subs = [i for i in var.cv_items_list]
            assert var.cv_fspec_max_bytes == 1 and len(subs) == sum(1 for s in size if s), name
            for s, sub in zip(size, subs):
                v = sub.cv_rule.cv_variation
                assert (v.cv_bit_size == s * 8) if s > 0 else (v.cv_rep_bytes == 1 and v.cv_variation.cv_bit_size
                                                               == -s * 8), name


def test_fast_equals_libasterix_real_and_simulated() -> None:
    real = [b for b in _real_blocks() if b[0] == 48]
    sim = _sim_blocks()
    _same(real)
    _same(sim)
    raw, _, bad = fast048.decode_blocks(real)
    assert raw.shape[0] == 128 and not bad


def _blk(body: bytes) -> bytes:
    return bytes([48]) + struct.pack(">H", 3 + len(body)) + body


#: one record per failure path of every item kind (and its valid neighbour)
EDGE = [
    _blk(bytes.fromhex("01010104" "00")),            # SP of length 0
    _blk(bytes.fromhex("01010104" "0201")),          # SP of length 2
    _blk(bytes.fromhex("01010102" "03aabb")),        # RE of length 3
    _blk(bytes.fromhex("01010103" "00")),            # FX in the 4th FSPEC octet (5 octets)
    _blk(bytes.fromhex("20" "81818181818100")),      # I048/020 with 7 octets (max 6): FX in the last
    _blk(bytes.fromhex("20" "818181818180")),        # I048/020 with 6 octets, last FX = 0
    _blk(bytes.fromhex("02" "0101")),                # I048/130: FX set in the primary subfield
    _blk(bytes.fromhex("02" "8011")),                # I048/130 SRL
    _blk(bytes.fromhex("010104" "20" "0102")),       # I048/120 with an undefined subfield bit
    _blk(bytes.fromhex("010104" "40" "02" + "11" * 12)),   # I048/120 RDS, 2 repetitions
    _blk(bytes.fromhex("010104" "40" "03" + "11" * 12)),   # I048/120 RDS count beyond the data
    _blk(bytes.fromhex("0120" "02" + "11" * 16)),    # I048/250, 2 repetitions
    _blk(bytes.fromhex("0120" "03" + "11" * 16)),    # I048/250 count beyond the data
    # I048/250 BDS 4,0 twice (the first is kept), 6,0, 5,1 (not kept), 5,0
    _blk(bytes.fromhex("0120" "05" + "11" * 7 + "40" + "22" * 7 + "40" + "33" * 7 + "60" + "44" * 7 + "51"
                       + "55" * 7 + "50")),
    _blk(bytes.fromhex("010140" "0302")),            # I048/030 FX chain
    _blk(bytes.fromhex("010140" "0303")),            # I048/030 FX chain cut
    _blk(bytes.fromhex("0102" "8181")),              # I048/170 with FX set in its last octet
    _blk(bytes.fromhex("0102" "8180")),              # I048/170 two octets
    _blk(bytes.fromhex("00")),                       # empty FSPEC: a record without items
    _blk(bytes.fromhex("81")),                       # FSPEC cut
]


def test_fast_equals_libasterix_edge_cases() -> None:
    _same(EDGE)


SEEDS = [b for b in _real_blocks() if b[0] == 48][:12]


@st.composite
def mutated(draw: st.DrawFn) -> list[bytes]:
    """CAT048 blocks with flipped bits, truncation, splices and wrong length fields."""
    pool = SEEDS + _SIM
    blocks = []
    for _ in range(draw(st.integers(1, 4))):
        data = bytearray(draw(st.sampled_from(pool)))
        op = draw(st.sampled_from(["flip", "truncate", "splice", "length", "byte", "random"]))
        i = draw(st.integers(3, len(data) - 1))
        if op == "random":        # arbitrary record bytes: every FSPEC bit, SP/RE, compounds
            data = bytearray(b"\x30\0\0" + draw(st.binary(min_size=1, max_size=80)))
        elif op == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte":
            data[i] = draw(st.integers(0, 255))
        elif op == "truncate":
            data = data[:i]
        elif op == "splice":
            other = draw(st.sampled_from(pool))
            j = draw(st.integers(3, len(other)))
            data = data[:i] + other[j:]
        else:
            data[1:3] = struct.pack(">H", draw(st.integers(0, 2 * len(data))))
        if op != "length":          # the block header says the true length (the splitter's job otherwise)
            data[1:3] = struct.pack(">H", len(data))
        blocks.append(bytes(data))
    return blocks


_SIM = _sim_blocks()


def _cat062_blocks() -> list[bytes]:
    from tertiary.core import geo
    n = 6
    tracks = pl.DataFrame({
        "epoch": pl.datetime_range(pl.datetime(2024, 1, 1, 12, time_zone="UTC"),
                                   pl.datetime(2024, 1, 1, 12, 0, 5, time_zone="UTC"), "1s", eager=True),
        "track_id": pl.Series(np.arange(n), dtype=pl.UInt64),
        "x_m": np.linspace(-5e4, 5e4, n), "y_m": np.linspace(1e4, 2e4, n), "z_m": np.full(n, 9000.0),
        "vx_mps": np.full(n, 200.0), "vy_mps": np.full(n, -20.0), "vz_mps": np.zeros(n),
        "cov_diag": pl.Series(np.tile([100.0, 100.0, 400.0, 4.0, 4.0, 1.0], (n, 1)), dtype=pl.Array(pl.Float64, 6)),
        "alt_m": np.full(n, 9100.0), "mode_s": ["abc123"] * n, "callsign": ["KLM1"] * n, "mode_3a": ["1200"] * n,
    })
    recs = encode.cat062(tracks, geo.LocalFrame(52.3, 4.76, 0.0))
    return [codec.datablock(62, [r for _, r in recs[i:i + 2]]) for i in range(0, n, 2)]


_SIM62 = _cat062_blocks()


def _cat021_blocks() -> list[bytes]:
    from tertiary.core import geo
    n = 6
    truth = pl.DataFrame({
        "truth_id": pl.Series(np.arange(n) % 2, dtype=pl.Int64),
        "time": pl.datetime_range(pl.datetime(2024, 1, 1, 12, time_zone="UTC"),
                                  pl.datetime(2024, 1, 1, 12, 0, 5, time_zone="UTC"), "1s", eager=True),
        "x_m": np.linspace(-5e4, 5e4, n), "y_m": np.linspace(1e4, 2e4, n), "z_m": np.full(n, 9000.0),
        "vx_mps": np.full(n, 200.0), "vy_mps": np.full(n, -20.0), "vz_mps": np.linspace(-15.0, 12.0, n),
        "alt_m": [9100.0, None, -200.0, 9000.0, None, 100.0], "icao24": ["abc123", ""] * 3,
        "callsign": ["KLM1", None] * 3,
    })
    recs = encode.cat021(truth, geo.LocalFrame(52.3, 4.76, 0.0))
    return [codec.datablock(21, [r for _, r in recs[i:i + 3]]) for i in range(0, n, 3)]


_SIM21 = _cat021_blocks()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_fast_equals_libasterix_on_fuzzed_blocks(blocks: list[bytes]) -> None:
    ok = [b for b in blocks if len(b) >= 3 and (b[1] << 8 | b[2]) == len(b)]
    _same(ok)


def _pcap(payloads: list[bytes]) -> bytes:
    out = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    for k, p in enumerate(payloads):
        udp = struct.pack(">HHHH", 1000, 2000, 8 + len(p), 0) + p
        ip = bytes([0x45, 0]) + struct.pack(">H", 20 + len(udp)) + b"\0\0\0\0\x40\x11\0\0" + bytes([10, 0, 0, 1]) \
            + bytes([232, 1, 1, 1])
        frame = b"\x01\x00\x5e\x01\x01\x01" + b"\x02" * 6 + b"\x08\x00" + ip + udp
        out.append(struct.pack("<IIII", 1462433756 + k, 0, len(frame), len(frame)) + frame)
    return b"".join(out)


@st.composite
def bad_recordings(draw: st.DrawFn) -> bytes:
    """A real or simulated recording (raw blocks or pcap) with bytes flipped, cut or spliced."""
    raw = bytearray(draw(st.sampled_from([PCAP.read_bytes(), b"".join(_SIM), _pcap(_SIM), b"".join(_SIM62),
                                          b"".join(_SIM62 + _SIM),
                                          b"".join(_SIM21 + _SIM62), _pcap(_SIM21 + _SIM)])))
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["flip", "truncate", "splice", "delete"]))
        i = draw(st.integers(0, max(len(raw) - 1, 0)))
        if op == "flip" and raw:
            raw[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "truncate":
            raw = raw[:i]
        elif op == "delete":
            raw = raw[:i] + raw[i + draw(st.integers(1, 8)):]
        else:
            j = draw(st.integers(0, len(raw)))
            raw = raw[:i] + raw[j:j + draw(st.integers(1, 64))] + raw[i:]
    return bytes(raw)


@pytest.fixture(scope="module")
def sites(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("fz") / "sites.toml"
    rows = "".join(f"[[radar]]\nsac = {a}\nsic = {b}\nlat_deg = 45.0\nlon_deg = 16.0\nalt_m = 0.0\nsigma_range_m = 50.0\n"
                   f"sigma_azimuth_deg = 0.1\nmax_range_m = 463000.0\nscan_period_s = 5.0\n\n"
                   for a, b in [(25, 11), (25, 12), (25, 13), (25, 14), (25, 201), (25, 204), (25, 205),
                                (0, 1), (0, 2), (1, 44)])
    p.write_text(rows)
    return p


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(bad_recordings())
def test_bad_bytes_never_crash(sites: Path, tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    """Any damage ends in rejects with reasons (or a clear TertiaryError), never a traceback, and
    every distinct CAT048 record is either a report or a reject."""
    f = tmp_path_factory.mktemp("bad") / "rec.bin"
    f.write_bytes(data)
    try:
        res = dataset.import_recordings([f], sites=sites, date="2024-01-01", skip_unknown=True)
    except TertiaryError as exc:
        assert str(exc)
        return
    c = res.counts
    assert c["distinct"] == res.reports.height + c["rejected"]
    assert res.rejects["reason"].str.len_chars().min() or res.rejects.height == 0
    if res.reports.height:
        assert res.reports["range_m"].is_finite().all() and (res.reports["range_m"] >= 0).all()
        assert res.reports["time"].is_not_null().all()


def test_vectorised_values_equal_libasterix_quantities() -> None:
    """The importer's vectorised unit conversions against libasterix's own quantities, record
    for record (negative flight levels, absent items, every identity format included)."""
    from tertiary.io.asterix import importer
    blocks = [b for b in _real_blocks() if b[0] == 48] + _SIM
    raw, _, bad = fast048.decode_blocks(blocks)
    assert not bad
    vals = importer.cat048_values(pl.DataFrame({n: raw[:, i] for i, n in enumerate(fast048.FIELDS)}))
    recs = [r for b in blocks for r in codec.parse_block(b)]
    assert len(recs) == vals.height
    for rec, v in zip(recs, vals.iter_rows(named=True)):
        rho = codec.sub_qty(rec, "040", "RHO", "NM")
        if rho is None:
            assert v["range_m"] is None and v["azimuth_deg"] is None
        else:
            assert v["range_m"] == pytest.approx(rho * 1852.0, abs=1e-9)
            assert v["azimuth_deg"] == pytest.approx(codec.sub_qty(rec, "040", "THETA", "°"), abs=1e-12)
        fl = codec.sub_qty(rec, "090", "FL", "FL")
        assert v["flight_level"] == fl
        if fl is not None:
            assert v["altitude_m"] == pytest.approx(fl * 100 * 0.3048)
        m3a = rec.get_item("070")
        assert v["mode_3a"] == (None if m3a is None else m3a.variation.get_item("MODE3A").variation.content.as_string())
        addr = codec.uint(rec, "220")
        assert v["mode_s"] == (None if addr is None else f"{addr:06x}")
        cs = codec.text(rec, "240")
        assert v["callsign"] == (None if cs is None or not cs.strip() else cs.rstrip())
        i170 = rec.get_item("170")
        if i170 is None:
            assert v["tentative"] is None and v["track_end"] is None
        else:
            st = i170.variation
            assert v["tentative"] == bool(st.get_item("CNF").as_uint())
            assert v["doubtful"] == bool(st.get_item("DOU").as_uint())
            assert v["manoeuvre"] == bool(st.get_item("MAH").as_uint())
            assert v["climb_mode"] == st.get_item("CDM").as_uint()
            tre = st.get_item("TRE")
            assert v["track_end"] == (None if tre is None else bool(tre.as_uint()))
            assert v["ghost"] == (None if tre is None else bool(st.get_item("GHO").as_uint()))
        gs = codec.sub_qty(rec, "200", "GSP", "NM/s")
        assert v["ground_speed_mps"] == (None if gs is None else pytest.approx(gs * 1852.0))


# --------------------------------------------------------------------------- CAT021 (spec-driven walker)


def _same_walk(blocks: list[bytes], cat: int) -> None:
    """The spec-driven walker accepts/refuses each block as libasterix does and cuts the same records."""
    from tertiary.io.asterix import fastwalk
    prog = fastwalk.program(codec.spec(cat).cv_record)
    buf, offs, block, rs, re, bad = fastwalk.walk(blocks, prog)
    refused = {k for k, _, _ in bad}
    for k, data in enumerate(blocks):
        recs = codec.parse_block(data)
        if isinstance(recs, str):
            assert k in refused, (k, data.hex(), recs)
            continue
        assert k not in refused, (k, data.hex(), [b for b in bad if b[0] == k])
        mine = [bytes(buf[a:b]) for a, b, bb in zip(rs, re, block) if bb == k]
        assert mine == [r.unparse().to_bytes() for r in recs]
        rows = offs[block == k]
        for row, rec in zip(rows, recs):        # present items = the items libasterix found
            assert {prog.names[s] for s in np.flatnonzero(row >= 0)} == set(rec.items_regular)


def test_walker_cat021_and_cat048_equal_libasterix() -> None:
    _same_walk(_SIM21, 21)
    _same_walk([b for b in _real_blocks() if b[0] == 48] + _SIM + EDGE, 48)


EDGE21 = [bytes([21]) + struct.pack(">H", 3 + len(b)) + b for b in (
    bytes.fromhex("00"), bytes.fromhex("01010101010101" "00"),            # FSPEC of 8 octets
    bytes.fromhex("40" "81818180"), bytes.fromhex("40" "8181818181"),     # I021/040 with 4 / 5 octets
    bytes.fromhex("40" "818181818181"),                                    # 6 octets: beyond its 5 groups
    bytes.fromhex("0101010101010102"), bytes.fromhex("01010101010110" "00"),   # spare UAP bits
    bytes.fromhex("010101010180" "8000" "0000"), bytes.fromhex("010101010180" "0101"),   # I021/295 compound
)]


def test_walker_cat021_edge_cases() -> None:
    _same_walk(EDGE21, 21)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(_SIM21), st.sampled_from(["flip", "truncate", "random", "byte"]),
                          st.integers(0, 10**6), st.integers(0, 255), st.binary(min_size=1, max_size=60)),
                min_size=1, max_size=4))
def test_walker_cat021_fuzzed(cases: list) -> None:
    blocks = []
    for seed, op, where, value, junk in cases:
        data = bytearray(seed)
        i = 3 + where % (len(data) - 3)
        if op == "flip":
            data[i] ^= 1 << (value % 8)
        elif op == "byte":
            data[i] = value
        elif op == "truncate":
            data = data[:i]
        else:
            data = bytearray(b"\x15\0\0" + junk)
        data[1:3] = struct.pack(">H", len(data))
        blocks.append(bytes(data))
    _same_walk(blocks, 21)


def test_cat021_values_equal_libasterix_quantities() -> None:
    from tertiary.io.asterix import importer
    items = [(b, {"file": "x", "datagram": 0}, float("nan"), "raw") for b in _SIM21]
    frame = importer._decode_021(items, [])
    recs = [r for b in _SIM21 for r in codec.parse_block(b)]
    assert frame.height == len(recs)
    for rec, v in zip(recs, frame.iter_rows(named=True)):
        assert v["address"] == codec.uint(rec, "080")
        assert v["tod_s"] == codec.qty(rec, "071", "s")
        assert v["lat_deg"] == pytest.approx(codec.sub_qty(rec, "131", "LAT", "°"), abs=1e-12)
        assert v["lon_deg"] == pytest.approx(codec.sub_qty(rec, "131", "LON", "°"), abs=1e-12)
        assert v["height_ft"] == codec.qty(rec, "140", "ft")
        assert v["fl"] == codec.qty(rec, "145", "FL")
        assert v["gs_nmps"] == pytest.approx(codec.sub_qty(rec, "160", "GS", "NM/s"))
        assert v["ta_deg"] == pytest.approx(codec.sub_qty(rec, "160", "TA", "°"))
        assert v["gvr_ftpm"] == codec.sub_qty(rec, "157", "GVR", "ft/min")
        cs = codec.text(rec, "170")
        assert v["callsign"] == cs
