"""I048/250 Mode S MB data: BDS 4,0, 5,0, 6,0 registers → ``selected_alt_m`` and the EHS columns.

The expected values come from ICAO Doc 9871 Tables A-2-64 (4,0), A-2-80 (5,0), A-2-96 (6,0),
written here field by field as bit strings (MB bit 1 = the first character), not from
:mod:`tertiary.io.asterix.commb`.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tertiary.io.asterix import capture, codec, dataset, encode, fast048, importer
from tertiary.io.asterix.sites import sites_toml

PCAP = Path(__file__).parent / "data" / "cat_034_048.pcap"
FT, KT, FPM = 0.3048, 1852.0 / 3600.0, 0.3048 / 60.0
COLS = ("selected_alt_m", "ehs_gs_mps", "ehs_track_deg", "ehs_track_rate_dps", "ehs_roll_deg", "ehs_vrate_mps")


# --------------------------------------------------------------------------- hand-built records


def _b(value: int, width: int) -> str:
    return format(value, f"0{width}b")


def _mb(*fields: str) -> int:
    """A 56-bit MB word from its fields' bit strings (in the table's order)."""
    text = "".join(fields)
    assert len(text) == 56, len(text)
    return int(text, 2)


# BDS 4,0: MCP/FCU 36 000 ft (2250 · 16 ft), FMS 40 000 ft (must not leak into the column),
# baro 1013.2 mb, reserved, MCP mode bits (VNAV off, ALT HOLD on), reserved, source = MCP
BDS40 = _mb("1" + _b(2250, 12), "1" + _b(2500, 12), "1" + _b(2132, 12), "0" * 8, "1" + "010", "00", "1" + "10")
# BDS 5,0: roll −114 LSB (sign 1, magnitude 512 − 114) = −20.0390625°, true track −256 LSB = −45°
# (315°), GS 220 · 2 kt, track rate −32 LSB = −1 °/s, TAS 460 kt (no column)
BDS50 = _mb("1" + "1" + _b(398, 9), "1" + "1" + _b(768, 10), "1" + _b(220, 10), "1" + "1" + _b(480, 9),
            "1" + _b(230, 10))
# BDS 6,0: magnetic heading 90°, IAS 250 kt, Mach 0.8, baro rate −10 LSB (−320 ft/min), inertial
# vertical velocity −12 LSB (−384 ft/min): the inertial one is the column
BDS60 = _mb("1" + "0" + _b(512, 10), "1" + _b(250, 10), "1" + _b(200, 10), "1" + "1" + _b(502, 9),
            "1" + "1" + _b(500, 9))
# limits: roll −90° (sign 1, magnitude 0), track −1 LSB (359.82…°), GS unavailable, rate +511 LSB
BDS50_EDGE = _mb("1" + "1" + _b(0, 9), "1" + "1" + _b(1023, 10), "0" * 11, "1" + "0" + _b(511, 9), "0" * 11)
# roll +45°, track +90°, GS 2 046 kt (all ones), rate and TAS unavailable
BDS50_POS = _mb("1" + "0" + _b(256, 9), "1" + "0" + _b(512, 10), "1" + _b(1023, 10), "0" * 11, "0" * 11)
# inertial unavailable, baro +511 LSB = +16 352 ft/min
BDS60_BARO = _mb("0" * 12, "0" * 11, "0" * 11, "1" + "0" + _b(511, 9), "0" * 11)
# MCP status 0 with value bits set (a register breaking the all-zeros rule: null, counted)
BDS40_CONFLICT = _mb("0" + _b(2250, 12), "0" * 13, "0" * 13, "0" * 8, "0" * 4, "00", "000")
BDS40_LOW = _mb("1" + _b(100, 12), "0" * 43)


def _record(tod: int, trn: int, regs: list[tuple[int, int]] | None) -> bytes:
    """A CAT048 record: 010, 140, 040, [250], 161 (FSPEC D1 30 / D1 10)."""
    body = bytes([0, 1]) + tod.to_bytes(3, "big") + struct.pack(">HH", 20 * 256, 4096)
    fspec2 = 0x10
    if regs is not None:
        fspec2 |= 0x20
        body += bytes([len(regs)]) + b"".join(mb.to_bytes(7, "big") + bytes([bds]) for mb, bds in regs)
    return bytes([0xD1, fspec2]) + body + trn.to_bytes(2, "big")


#: (registers, expected columns) of each hand-built record
HAND = [
    ([(BDS40, 0x40), (BDS50, 0x50), (BDS60, 0x60)],
     {"selected_alt_m": 36000 * FT, "ehs_roll_deg": -20.0390625, "ehs_track_deg": 315.0, "ehs_gs_mps": 440 * KT,
      "ehs_track_rate_dps": -1.0, "ehs_vrate_mps": -384 * FPM}),
    ([(BDS50_EDGE, 0x50), (BDS60_BARO, 0x60), (BDS40_CONFLICT, 0x40), (BDS40_LOW, 0x40)],   # the first 4,0 counts
     {"ehs_roll_deg": -90.0, "ehs_track_deg": 360 - 90 / 512, "ehs_track_rate_dps": 511 / 32,
      "ehs_vrate_mps": 16352 * FPM}),
    ([(BDS50_POS, 0x50)], {"ehs_roll_deg": 45.0, "ehs_track_deg": 90.0, "ehs_gs_mps": 2046 * KT}),
    # registers named 3,0, 0,5, 5,1 and 4,1: not read, whatever their content
    ([(BDS50, 0x30), (BDS50, 0x05), (BDS50, 0x51), (BDS40, 0x41)], {}),
    (None, {}),
]


def _hand_block() -> bytes:
    body = b"".join(_record(128 * (36000 + k), k, regs) for k, (regs, _) in enumerate(HAND))
    return bytes([48]) + (3 + len(body)).to_bytes(2, "big") + body


def _columns(blocks: list[bytes]) -> pl.DataFrame:
    """The importer's columns of the compiled decoder's raw fields."""
    raw, _, bad = fast048.decode_blocks(blocks)
    assert not bad
    return importer.cat048_values(pl.DataFrame({n: raw[:, i] for i, n in enumerate(fast048.FIELDS)}))


def test_hand_built_registers_decode_to_the_spec_values() -> None:
    vals = _columns([_hand_block()])
    assert vals.height == len(HAND)
    for row, (_, want) in zip(vals.iter_rows(named=True), HAND):
        for c in COLS:
            if c in want:
                assert row[c] == pytest.approx(want[c], abs=1e-9), c
            else:
                assert row[c] is None, c


def _sites(path: Path, codes: list[tuple[int, int]]) -> Path:
    path.write_text(sites_toml(pl.DataFrame([
        {"sac": a, "sic": b, "radar_id": a * 256 + b, "name": f"{a}-{b}", "lat_deg": 45.0, "lon_deg": 16.0,
         "alt_m": 0.0, "sigma_range_m": 70.0, "sigma_azimuth_deg": 0.08, "max_range_m": 463000.0,
         "sigma_elevation_deg": 1.0, "scan_period_s": 4.0} for a, b in codes])))
    return path


def test_a_bad_register_never_drops_the_report(tmp_path: Path) -> None:
    """Every hand-built record is a report (a register breaking its own rules included), the
    EHS columns are report columns, and the conflict is counted."""
    rec = tmp_path / "hand.ast"
    rec.write_bytes(_hand_block())
    res = dataset.import_recordings([rec], sites=_sites(tmp_path / "s.toml", [(0, 1)]), date="2024-01-01")
    assert res.reports.height == len(HAND) and res.rejects.height == 0
    assert res.reports.sort("local_track_id").select(COLS).equals(_columns([_hand_block()]).select(COLS))
    c = res.counts
    assert (c["cat048_bds40"], c["cat048_bds50"], c["cat048_bds60"]) == (2, 3, 2)
    assert c["cat048_mb_status_conflicts"] == 1


# --------------------------------------------------------------------------- fast decoder = libasterix + the spec


def _spec_values(mb: int, bds: int) -> dict[str, float]:
    """The register's columns read field by field off its 56-character bit string."""
    s = format(mb, "056b")

    def val(status: int, first: int, last: int, signed: bool, lsb: float) -> float | None:
        if s[status - 1] == "0":
            return None
        v = int(s[first - 1:last], 2)
        if signed and s[first - 1] == "1":
            v -= 1 << (last - first + 1)
        return v * lsb

    if bds == 0x40:
        return {"selected_alt_m": val(1, 2, 13, False, 16 * FT)}
    if bds == 0x50:
        track = val(12, 13, 23, True, 90 / 512)
        return {"ehs_roll_deg": val(1, 2, 11, True, 45 / 256), "ehs_track_deg": None if track is None else track % 360,
                "ehs_gs_mps": val(24, 25, 34, False, 2 * KT), "ehs_track_rate_dps": val(35, 36, 45, True, 8 / 256)}
    inertial, baro = val(46, 47, 56, True, 32 * FPM), val(35, 36, 45, True, 32 * FPM)
    return {"ehs_vrate_mps": inertial if inertial is not None else baro}


def _reference(blocks: list[bytes]) -> list[dict[str, float | None]]:
    """Per record (libasterix), the columns of its first register of each of 4,0, 5,0, 6,0."""
    out = []
    for block in blocks:
        for rec in codec.parse_block(block):
            row: dict[str, float | None] = dict.fromkeys(COLS)
            seen = set()
            item = rec.get_item("250")
            for reg in [] if item is None else item.variation.get_list():
                bds = reg.get_item("BDS1").as_uint() << 4 | reg.get_item("BDS2").as_uint()
                if bds in (0x40, 0x50, 0x60) and bds not in seen:
                    seen.add(bds)
                    row |= _spec_values(reg.get_item("MBDATA").as_uint(), bds)
            out.append(row)
    return out


def _same_columns(blocks: list[bytes]) -> None:
    vals = _columns(blocks)
    ref = _reference(blocks)
    assert vals.height == len(ref)
    for k, (row, want) in enumerate(zip(vals.iter_rows(named=True), ref)):
        for c in COLS:
            assert (row[c] is None) == (want[c] is None), (k, c, row[c], want[c])
            if want[c] is not None:
                assert row[c] == pytest.approx(want[c], abs=1e-9), (k, c)


def _real_blocks() -> list[bytes]:
    return [b for b in capture.split_blocks(capture.read_recording(PCAP)).data if b[0] == 48]


def test_fast_decoder_and_libasterix_agree_on_the_columns() -> None:
    _same_columns(_real_blocks() + [_hand_block()] + _encoded_blocks(_edge_reports()))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
def test_fast_decoder_and_libasterix_agree_on_random_registers(seed: int) -> None:
    """Records with 0–5 registers of uniformly random bits (or all zeros / all ones) under the
    nibbles that name a read register and others that do not, or without I048/250."""
    rng = np.random.default_rng(seed)
    nibbles = [0x40, 0x50, 0x60, 0x41, 0x51, 0x30, 0x05, 0x02, 0xFF]
    records = []
    for k in range(20):
        n = int(rng.integers(-1, 6))
        mb = rng.choice([rng.integers(0, 2**56), 0, 2**56 - 1], size=max(n, 0), p=[0.9, 0.05, 0.05])
        regs = None if n < 0 else [(int(v), int(rng.choice(nibbles))) for v in mb]
        records.append(_record(128 * k, k, regs))
    body = b"".join(records)
    _same_columns([bytes([48]) + (3 + len(body)).to_bytes(2, "big") + body])


# --------------------------------------------------------------------------- encode → import


#: per column: LSB and the encodable limits (values beyond come back at the limit)
LIMITS = {"selected_alt_m": (16 * FT, 0.0, 65520 * FT), "ehs_roll_deg": (45 / 256, -90.0, 511 * 45 / 256),
          "ehs_gs_mps": (2 * KT, 0.0, 2046 * KT), "ehs_track_rate_dps": (8 / 256, -16.0, 511 / 32),
          "ehs_vrate_mps": (32 * FPM, -16384 * FPM, 16352 * FPM)}


def _edge_reports(n: int = 400, seed: int = 7) -> pl.DataFrame:
    """Reports with EHS columns: random values, nulls, negative rolls and rates, tracks around
    0/360 (either convention), values at and beyond each field's limits."""
    rng = np.random.default_rng(seed)
    cols = {
        "selected_alt_m": rng.uniform(-500.0, 21000.0, n), "ehs_roll_deg": rng.uniform(-100.0, 100.0, n),
        "ehs_track_deg": rng.uniform(-180.0, 360.0, n),
        "ehs_gs_mps": rng.uniform(0.0, 1100.0, n), "ehs_track_rate_dps": rng.uniform(-18.0, 18.0, n),
        "ehs_vrate_mps": rng.uniform(-90.0, 90.0, n)}
    for c, (lsb, lo, hi) in LIMITS.items():
        cols[c][:4] = [lo, hi, lo - 3 * lsb, hi + 3 * lsb]
    for c in cols:
        cols[c][rng.random(n) < 0.2] = np.nan
    near = rng.random(n) < 0.3                 # around north, from either side and in either convention
    cols["ehs_track_deg"][near] = rng.choice([0.0, 360.0, -360.0], near.sum()) + rng.uniform(-0.2, 0.2, near.sum())
    cols["ehs_track_deg"][4:10] = [-0.05, 359.99, 0.0, -180.0, 179.95, 180.0]
    for v in cols.values():
        v[8] = np.nan                      # a report without any register
    return pl.DataFrame({
        "radar_id": pl.Series([1] * n, dtype=pl.UInt32),
        "time": pl.Series((1_704_110_400 + np.arange(n) * 0.25) * 1e6).cast(pl.Int64).cast(pl.Datetime("us", "UTC")),
        "local_track_id": pl.Series(np.arange(n) % 4000, dtype=pl.UInt32), "range_m": np.full(n, 50000.0),
        "azimuth_deg": np.linspace(0, 359, n), "mode_s": ["abcdef"] * n,
        **{c: pl.Series(c, v).fill_nan(None) for c, v in cols.items()}})


def _encoded_blocks(reports: pl.DataFrame) -> list[bytes]:
    recs = encode.cat048(reports)
    return [codec.datablock(48, recs[i:i + 20]) for i in range(0, len(recs), 20)]


def test_encode_import_round_trip_within_quantisation(tmp_path: Path) -> None:
    rep = _edge_reports()
    rec = tmp_path / "ehs.ast"
    rec.write_bytes(b"".join(_encoded_blocks(rep)))
    res = dataset.import_recordings([rec], sites=_sites(tmp_path / "s.toml", [(0, 1)]), date="2024-01-01")
    out = res.reports.sort("time")
    assert out.height == rep.height and res.rejects.height == 0
    for c in COLS:
        a, b = rep[c].to_numpy().astype(float), out[c].to_numpy().astype(float)
        assert np.array_equal(np.isnan(a), np.isnan(b)), c
        ok = ~np.isnan(a)
        if c == "ehs_track_deg":
            assert ((b[ok] >= 0) & (b[ok] < 360)).all()
            err = np.abs((b[ok] - a[ok] + 180) % 360 - 180)
            assert err.max() <= 90 / 1024 + 1e-9, c
            continue
        lsb, lo, hi = LIMITS[c]
        err = np.abs(b[ok] - np.clip(a[ok], lo, hi))
        assert err.max() <= lsb / 2 + 1e-9, (c, err.max())
        assert b[ok].min() >= lo - 1e-9 and b[ok].max() <= hi + 1e-9, c
    assert res.counts["cat048_bds40"] == rep["selected_alt_m"].is_not_null().sum()


def test_round_trip_keeps_signs_and_limits_exactly() -> None:
    """Values on the LSB grid come back bit for bit, the limits and both signs included."""
    rep = _edge_reports(n=12).with_columns(
        ehs_roll_deg=pl.Series([-90.0, 89.82421875, -0.17578125, 0.17578125, -45.0, 20.0390625] * 2),
        ehs_track_rate_dps=pl.Series([-16.0, 15.96875, -0.03125, 0.03125, -1.0, 3.0] * 2),
        ehs_vrate_mps=pl.Series([-16384 * FPM, 16352 * FPM, -32 * FPM, 32 * FPM, 0.0, -992 * FPM] * 2),
        ehs_track_deg=pl.Series([0.0, 359.82421875, 180.0, 0.17578125, 315.0, 90.0] * 2),
        selected_alt_m=pl.Series([0.0, 65520 * FT, 16 * FT, 36000 * FT, 15008 * FT, None] * 2),
        ehs_gs_mps=pl.Series([0.0, 2046 * KT, 2 * KT, 440 * KT, 1000 * KT, None] * 2))
    vals = _columns(_encoded_blocks(rep))
    for c in COLS:
        assert vals[c].to_list() == pytest.approx(rep.sort("time")[c].to_list(), abs=1e-9), c


# --------------------------------------------------------------------------- the shipped capture


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> dataset.ImportResult:
    codes = [(25, 11), (25, 12), (25, 13), (25, 14), (25, 201), (25, 204), (25, 205)]
    return dataset.import_recordings([PCAP], sites=_sites(tmp_path_factory.mktemp("mb") / "s.toml", codes))


def _capture_status_counts() -> dict[str, int]:
    """Per column, the distinct reports (records with I048/040) whose first register of its kind
    has the field's status bit set, through libasterix's generic I048/250 (BDS nibbles, MB data)."""
    status = {"selected_alt_m": (0x40, (1,)), "ehs_roll_deg": (0x50, (1,)), "ehs_track_deg": (0x50, (12,)),
              "ehs_gs_mps": (0x50, (24,)), "ehs_track_rate_dps": (0x50, (35,)), "ehs_vrate_mps": (0x60, (35, 46))}
    counts = dict.fromkeys(status, 0)
    seen = set()
    for block in _real_blocks():
        for rec in codec.parse_block(block):
            key = rec.unparse().to_bytes()
            if key in seen or rec.get_item("040") is None or rec.get_item("250") is None:
                continue
            seen.add(key)
            first: dict[int, int] = {}
            for reg in rec.get_item("250").variation.get_list():
                first.setdefault(reg.get_item("BDS1").as_uint() << 4 | reg.get_item("BDS2").as_uint(),
                                 reg.get_item("MBDATA").as_uint())
            for c, (bds, bits) in status.items():
                counts[c] += bds in first and any(first[bds] >> (56 - b) & 1 for b in bits)
    return counts


def test_capture_reports_carry_the_registers_it_holds(real: dataset.ImportResult) -> None:
    """45 of the 64 distinct records carry I048/250: 41 of the 63 reports a BDS 4,0 (39 with the
    MCP/FCU selected altitude), 2 a BDS 5,0, 18 a BDS 6,0."""
    have = {c: int(real.reports[c].is_not_null().sum()) for c in COLS}
    assert have == _capture_status_counts()
    assert have == {"selected_alt_m": 39, "ehs_gs_mps": 2, "ehs_track_deg": 2, "ehs_track_rate_dps": 2,
                    "ehs_roll_deg": 2, "ehs_vrate_mps": 18}
    c = real.counts
    assert (c["cat048_bds40"], c["cat048_bds50"], c["cat048_bds60"], c["cat048_mb_status_conflicts"]) == (41, 2, 18, 0)


def test_capture_values_are_plausible(real: dataset.ImportResult) -> None:
    """Selected altitudes on the 16 ft grid between FL 60 and FL 400; the BDS 5,0 ground vector
    within a few m/s and degrees of the radar's own I048/200; vertical rates of an airliner."""
    r = real.reports
    sel = r["selected_alt_m"].drop_nulls().to_numpy() / FT
    assert np.allclose(sel / 16, np.round(sel / 16)) and sel.min() > 5000 and sel.max() < 41000
    ehs = r.filter(pl.col("ehs_gs_mps").is_not_null())
    assert (ehs["ehs_gs_mps"] - ehs["ground_speed_mps"]).abs().max() < 6.0
    assert (((ehs["ehs_track_deg"] - ehs["heading_deg"] + 180) % 360) - 180).abs().max() < 2.0
    assert ehs["ehs_roll_deg"].abs().max() < 5 and ehs["ehs_track_rate_dps"].abs().max() < 1
    assert r["ehs_vrate_mps"].drop_nulls().abs().max() < 6000 * FPM
    # the one BDS 5,0 aircraft climbing fast (I048/090 FL 290, selected 33 000 ft) says so in BDS 6,0
    climb = r.filter(pl.col("mode_s") == "400c4a").row(0, named=True)
    assert climb["ehs_vrate_mps"] > 5 and climb["selected_alt_m"] > climb["altitude_m"]
