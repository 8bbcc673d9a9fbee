"""ASTERIX decode throughput: CAT048 records/s of the compiled decoder, of libasterix, and of the
whole import (decode + de-duplication + time + values + flags), on one machine.

Input: N distinct CAT048 records of a typical Mode S plot layout (010, 140, 020, 040, 070, 090,
220, 240, 161, 200, 170; 32 bytes), packed 40 per data block, every block sent on two redundant
lines (so the import de-duplicates N of 2N). ``--mb K`` adds I048/250 with K Comm-B registers
(BDS 4,0, 5,0, 6,0 in that order, random MB data; 33 + 8·K bytes), the enhanced-surveillance
layout. The records are laid out with numpy (byte positions of that fixed layout) and a sample
of them is checked against libasterix before timing.

CAT001 (plots and tracks, with a CAT002 north marker per 40 blocks), CAT002, CAT004 (STCA),
CAT020 (MLAT) and CAT021 of an ADS-B ground station (a sites entry of kind adsb: reports, key
``cat021_station``): records encoded by libasterix as templates, made distinct with numpy at
their item offsets (time of day, track numbers, addresses, positions), checked against
libasterix on a sample; decode (compiled walker + numpy) and whole import (decode,
de-duplication, time, values, rejects; CAT002: antenna timing; CAT004: alert episodes) timed
per category, with the 1-minute load average at its start.

    PYTHONPATH=. python benchmarks/bench_asterix.py [--records 1000000] [--only-new] [--cats 1,2,4,20,21]
    PYTHONPATH=. python benchmarks/bench_asterix.py --mb 3 [--records 1000000]

Writes benchmarks/results/bench_asterix.json (``--only-new`` keeps its CAT048/CAT021 entries;
``--mb K`` writes only its CAT048 entries, under keys ending ``_mb``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tertiary.io.asterix import codec, fast048  # noqa: E402

PER_BLOCK = 40


def icao6(text: str) -> int:
    """An 8-character identification as the 48-bit I048/240 value (ICAO 6-bit characters)."""
    v = 0
    for ch in text.ljust(8)[:8]:
        v = (v << 6) | (ord(ch) - 64 if "A" <= ch <= "Z" else ord(ch))
    return v


def records(n: int, seed: int = 1, mb: int = 0) -> np.ndarray:
    """n CAT048 records (n × 32 bytes): FSPEC FD D6 (010 140 020 040 070 090 | 220 240 161 200 170);
    with ``mb`` > 0 also I048/250 (FRN 10) holding ``mb`` registers (n × (33 + 8·mb) bytes)."""
    rng = np.random.default_rng(seed)
    extra = 1 + 8 * mb if mb else 0
    rec = np.zeros((n, 32 + extra), np.uint8)
    rec[:, 0], rec[:, 1] = 0xFD, 0xD6          # FRN 1-6 + FX; FRN 8, 9, 11, 13, 14 (1101 0110)

    def put(col: int, width: int, values: np.ndarray) -> None:
        for b in range(width):
            rec[:, col + b] = (values >> (8 * (width - 1 - b))) & 0xFF

    put(2, 1, np.full(n, 25))                                       # SAC
    put(3, 1, rng.integers(1, 21, n))                               # SIC
    put(4, 3, (np.arange(n) * 128 // 50) % (86400 * 128))           # time of day, 50 records/s
    put(7, 1, np.full(n, 5 << 5))                                   # 020: Mode S roll-call
    put(8, 2, rng.integers(0, 65536, n))                            # RHO
    put(10, 2, rng.integers(0, 65536, n))                           # THETA
    put(12, 2, rng.integers(0, 4096, n))                            # Mode 3/A
    put(14, 2, rng.integers(0, 1600, n))                            # FL x 4
    put(16, 3, rng.integers(0, 2**24, n))                           # aircraft address
    put(19, 6, np.full(n, icao6("CAF1234")))                        # identification
    if mb:
        rec[:, 1] |= 0x20                                           # FRN 10: I048/250
        put(25, 1, np.full(n, mb))                                  # REP
        for k in range(mb):                                         # 56-bit MB data | BDS1 | BDS2
            put(26 + 8 * k, 7, rng.integers(0, 2**56, n, dtype=np.int64))
            put(33 + 8 * k, 1, np.full(n, 0x40 + 0x10 * k))
    put(25 + extra, 2, rng.integers(0, 4096, n))                    # track number
    put(27 + extra, 2, rng.integers(0, 2**14, n))                   # ground speed
    put(29 + extra, 2, rng.integers(0, 65536, n))                   # heading
    put(31 + extra, 1, np.full(n, 2 << 4))                          # 170: RAD=2
    return rec


def blocks(recs: np.ndarray) -> list[bytes]:
    out = []
    for i in range(0, len(recs), PER_BLOCK):
        body = recs[i:i + PER_BLOCK].tobytes()
        out.append(bytes([48]) + (3 + len(body)).to_bytes(2, "big") + body)
    return out


def check_sample(blks: list[bytes], k: int = 5) -> None:
    """The synthetic blocks are valid CAT048 and the compiled decoder agrees with libasterix."""
    raw, _, bad = fast048.decode_blocks(blks[:k])
    assert not bad, bad
    ref = [codec.ref048(r) for b in blks[:k] for r in codec.parse_block(b)]   # type: ignore[union-attr]
    cols = [c for c in fast048.FIELDS if c not in ("offset", "length", "hash")]
    assert [{c: int(row[fast048.FIELDS.index(c)]) for c in cols} for row in raw] == ref


def _cat021_rate(n: int) -> dict[str, float]:
    """CAT021 decode (compiled walker + numpy field reads) against libasterix, on n records made
    by repeating 600 encoded ADS-B reports."""
    import polars as pl
    from tertiary.core import geo
    from tertiary.io.asterix import encode, importer
    m = 600
    rng = np.random.default_rng(2)
    truth = pl.DataFrame({
        "truth_id": pl.Series(np.arange(m) % 50, dtype=pl.Int64),
        "time": pl.Series((1_700_000_000 + np.arange(m) * 0.5) * 1e6).cast(pl.Int64).cast(pl.Datetime("us", "UTC")),
        "x_m": rng.uniform(-2e5, 2e5, m), "y_m": rng.uniform(-2e5, 2e5, m), "z_m": rng.uniform(0, 1.2e4, m),
        "vx_mps": rng.uniform(-250, 250, m), "vy_mps": rng.uniform(-250, 250, m), "vz_mps": rng.uniform(-15, 15, m),
        "alt_m": rng.uniform(0, 1.2e4, m), "icao24": [f"{a:06x}" for a in rng.integers(0, 2**24, m)],
        "callsign": ["AFR1234"] * m})
    recs = [r for _, r in encode.cat021(truth, geo.LocalFrame(48.85, 2.35, 0.0))]
    blks = [codec.datablock(21, recs[i:i + 20]) for i in range(0, m, 20)]
    reps = max(1, n // m)
    items = [(b, {"file": "bench", "datagram": 0}, float("nan"), "raw") for b in blks * reps]
    importer._decode_021(items[:2], [])                      # compile / load the cache
    t = time.perf_counter()
    frame = importer._decode_021(items, [])
    fast_s = time.perf_counter() - t
    t = time.perf_counter()
    k = 0
    for b in blks[:10]:
        for r in codec.parse_block(b):                      # type: ignore[union-attr]
            codec.uint(r, "080"), codec.sub_qty(r, "131", "LAT", "°"), codec.qty(r, "140", "ft")
            k += 1
    lib_s = time.perf_counter() - t
    return {"cat021_records": frame.height, "cat021_fast_records_per_s": round(frame.height / fast_s),
            "cat021_libasterix_records_per_s": round(k / lib_s)}


SITES_NEW = [{"sac": 9, "sic": 1, "radar_id": 9 * 256 + 1, "name": "legacy", "lat_deg": 45.5, "lon_deg": 16.5,
              "alt_m": 300.0, "sigma_range_m": 70.0, "sigma_azimuth_deg": 0.08, "max_range_m": 463000.0,
              "sigma_elevation_deg": 1.0, "scan_period_s": 4.0},
             {"sac": 7, "sic": 20, "radar_id": 7 * 256 + 20, "name": "wam", "kind": "mlat", "lat_deg": 45.0,
              "lon_deg": 16.0, "alt_m": 100.0, "sigma_range_m": 20.0, "sigma_azimuth_deg": 0.5,
              "max_range_m": 200000.0, "sigma_elevation_deg": 1.0, "scan_period_s": 1.0},
             {"sac": 7, "sic": 30, "radar_id": 7 * 256 + 30, "name": "adsb", "kind": "adsb", "lat_deg": 45.2,
              "lon_deg": 16.3, "alt_m": 50.0, "sigma_range_m": 30.0, "sigma_azimuth_deg": 0.5,
              "max_range_m": 400000.0, "sigma_elevation_deg": 1.0, "scan_period_s": 1.0}]


def _templates(cat: int) -> list[object]:
    """libasterix records of one category: the layouts the benchmark repeats."""
    if cat == 20:
        return [codec.spec(20).cv_record.create({
            "010": (("SAC", 7), ("SIC", 20)), "020": (0x40,), "140": 0.0, "041": (("LAT", 45.1), ("LON", 16.1)),
            "042": (("X", 7800.0), ("Y", 11100.0)), "161": (0, ("TRN", 0)), "070": (0, 0, 0, 0, ("MODE3A", "1234")),
            "090": (("V", 0), ("G", 0), ("FL", 350.0)), "220": 0xABCDEF, "245": (("STI", 2), 0, ("CHR", "WAM01   ")),
            "105": 36000.0, "500": {"SDP": (("X", 7.5), ("Y", 10.0), ("XY", 2.0))}})]
    if cat == 21:
        return [codec.spec(21).cv_record.create({
            "010": (("SAC", 7), ("SIC", 30)), "040": (0,), "071": 0.0, "080": 0x3C6500,
            "131": (("LAT", 45.1), ("LON", 16.1)), "145": 350.0, "090": (8, (3 << 4) | 9),
            "070": (0, ("MODE3A", "1234")), "170": "DLH4AB  "})]
    if cat == 1:
        u = codec.spec(1).cv_uap
        return [u.cv_uaps["plot"].create({"010": (("SAC", 9), ("SIC", 1)), "020": (0x10,),
                                          "040": (("RHO", 40.5), ("THETA", 45.0)),
                                          "070": (0, 0, 0, 0, ("MODE3A", "4321")),
                                          "090": (("V", 0), ("G", 0), ("HGT", 120.0)), "141": 0.0}),
                u.cv_uaps["track"].create({"010": (("SAC", 9), ("SIC", 1)), "020": (0x50,), "161": 0,
                                           "040": (("RHO", 100.0), ("THETA", 270.0)),
                                           "070": (0, 0, 0, 0, ("MODE3A", "1200")),
                                           "090": (("V", 0), ("G", 0), ("HGT", 80.0)), "141": 0.0})]
    if cat == 2:
        return [codec.spec(2).cv_record.create({"010": (("SAC", 9), ("SIC", 1)), "000": 2, "020": 0.0, "030": 0.0,
                                                "041": 4.0})]
    return [codec.spec(4).cv_record.create({
        "010": (("SAC", 3), ("SIC", 4)), "000": 7, "020": 0.0, "040": 0, "030": 0, "035": 0,
        "070": {"TCA": 42.5, "MHS": 1800.0, "MVS": 500.0}, "170": {"AI1": "AFR123 ", "M31": (0, ("MODE3A", "1234"))},
        "171": {"AI2": "BAW9   "}})]


#: per category: (item, byte in the item, width, value of record i) made distinct in each copy
_VARY = {
    20: lambda i: [("140", 0, 3, i * 128 // 50 % (86400 * 128)), ("161", 0, 2, i % 4096),
                   ("041", 2, 2, i * 37 % 65536), ("042", 1, 2, i * 91 % 65536)],
    21: lambda i: [("071", 0, 3, i * 128 // 50 % (86400 * 128)), ("080", 0, 3, 0x3C6500 + i % 500),
                   ("131", 2, 2, i * 37 % 65536), ("131", 6, 2, i * 91 % 65536)],
    1: lambda i: [("141", 0, 2, i * 128 // 50 % 65536), ("040", 0, 2, 2000 + i * 7 % 60000),
                  ("040", 2, 2, i * 131 % 65536), ("070", 0, 2, i % 4096)],
    2: lambda i: [("030", 0, 3, i * 128 * 4 // 32 % (86400 * 128)), ("020", 0, 1, i * 8 % 256)],
    4: lambda i: [("020", 0, 3, i * 128 // 20 % (86400 * 128)), ("040", 0, 2, i // 10 % 65536),
                  ("030", 0, 2, (i // 10) * 2 % 65536), ("035", 0, 2, (i // 10) * 2 + 1 % 65536)],
}


def distinct_blocks(cat: int, n: int) -> list[bytes]:
    """``n`` distinct records of ``cat`` in blocks of PER_BLOCK (see the module docstring)."""
    from tertiary.io.asterix import fastcats, fastwalk
    temps = _templates(cat)
    body = b"".join(r.unparse().to_bytes() for r in temps)              # type: ignore[attr-defined]
    if cat == 1:
        buf, offs, uap, *_ = fastwalk.walk_select([bytes([1, 0, 0]) + body], fastcats.program(1, "plot"),
                                                  fastcats.program(1, "track"), 2)
        progs = [fastcats.program(1, "plot" if u == 0 else "track") for u in uap]
    else:
        buf, offs, *_ = fastwalk.walk([bytes([cat, 0, 0]) + body], fastcats.program(cat))
        progs = [fastcats.program(cat)] * len(temps)
    tpl = np.frombuffer(body, np.uint8)
    reps = -(-n // len(temps))
    rec = np.tile(tpl, (reps, 1))
    idx = np.arange(reps)
    for j, prog in enumerate(progs):
        for item, at, width, value in _VARY[cat](idx * len(temps) + j):
            col = offs[j, prog.slot(item)] + at
            for b in range(width):
                rec[:, col + b] = (value >> (8 * (width - 1 - b))) & 0xFF
    size = len(body) // len(temps)
    flat = rec.reshape(-1, size)[:n] if len({len(t.unparse().to_bytes()) for t in temps}) == 1 else None
    rows = [r.tobytes() for r in (flat if flat is not None else rec)]
    per = PER_BLOCK if flat is not None else PER_BLOCK // len(temps)
    out = [bytes([cat]) + (3 + sum(map(len, rows[i:i + per]))).to_bytes(2, "big") + b"".join(rows[i:i + per])
           for i in range(0, len(rows), per)]
    ref = codec.parse_block(out[-1 if len(out) < 2 else 1])
    assert not isinstance(ref, str) and (len(out) < 2 or len(ref) == (PER_BLOCK if flat is not None
                                                                       else per * len(temps))), ref
    return out


def _new_rates(n: int, cats: tuple[int, ...] = (1, 2, 4, 20, 21)) -> dict[str, float]:
    """Decode and whole-import rates of CAT001, CAT002, CAT004, CAT020 and station CAT021 on ``n``
    records each."""
    import polars as pl
    from tertiary.io.asterix import dataset, fastcats, importer
    from tertiary.io.asterix.sites import sites_toml
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        sites = Path(tmp) / "sites.toml"
        sites.write_text(sites_toml(pl.DataFrame(SITES_NEW)))
        for cat in cats:
            load = os.getloadavg()[0]
            blks = distinct_blocks(cat, n)
            items = [(b, {"file": "bench", "datagram": 0}, float("nan"), "raw", k) for k, b in enumerate(blks)]
            decode = importer._decode_021 if cat == 21 else getattr(fastcats, f"decode_{cat:03d}")
            decode(items[:2], [])                                    # compile / load the cache
            t = time.perf_counter()
            frame = decode(items, [])
            out[f"cat{cat:03d}_fast_records_per_s"] = round(frame.height / (time.perf_counter() - t))
            rec = Path(tmp) / f"cat{cat:03d}.ast"
            # CAT001: a north marker (full time of day) per 40 blocks of 40 records at 50 records/s
            north = [codec.datablock(2, [codec.spec(2).cv_record.create({
                "010": (("SAC", 9), ("SIC", 1)), "000": 1, "030": k * PER_BLOCK / 50.0})])
                for k in range(0, len(blks), 40)] if cat == 1 else []
            with rec.open("wb") as fh:
                for k, b in enumerate(blks):
                    if cat == 1 and k % 40 == 0:
                        fh.write(north[k // 40])
                    fh.write(b)
            t = time.perf_counter()
            if cat == 2:
                dec = importer.decode_files([rec])
                importer.antenna_timing(dec.cat002.drop("seq"), importer.parse_date("2024-01-01"))
                kept = dec.cat002.height
            else:
                res = dataset.import_recordings([rec], sites=sites, date="2024-01-01")
                kept = res.alerts.height if cat == 4 else res.reports.height
                assert res.rejects.height == 0, res.rejects.head()
            s = time.perf_counter() - t
            c = "cat021_station" if cat == 21 else f"cat{cat:03d}"
            if cat == 21:
                assert res.counts["cat021_reports"] == frame.height and res.truth.height == 0
                out[f"{c}_fast_records_per_s"] = out.pop("cat021_fast_records_per_s")
            out |= {f"{c}_load_average_1min": round(load, 2), f"{c}_records": frame.height,
                    f"{c}_import_rows_out": kept, f"{c}_import_s": round(s, 2),
                    f"{c}_import_records_per_s": round(frame.height / s)}
    return out


def _write(result: dict[str, object]) -> None:
    out = Path(__file__).parent / "results" / "bench_asterix.json"
    out.parent.mkdir(exist_ok=True)
    old = json.loads(out.read_text()) if out.exists() else {}
    out.write_text(json.dumps(old | result, indent=2) + "\n")


def _cat048_rates(n: int, lib_records: int, mb: int = 0) -> dict[str, object]:
    """CAT048: compiled decode, libasterix decode and whole import of ``n`` distinct records
    (each block sent twice), the records with ``mb`` Comm-B registers (:func:`records`)."""
    import polars as pl
    from tertiary.io.asterix import dataset
    from tertiary.io.asterix.sites import sites_toml
    load = os.getloadavg()[0]
    recs = records(n, mb=mb)
    blks = blocks(recs)
    check_sample(blks)
    fast048.decode_blocks(blks[:2])                       # compile / load the cache
    t = time.perf_counter()
    raw, _, bad = fast048.decode_blocks(blks)
    fast_s = time.perf_counter() - t
    assert raw.shape[0] == n and not bad
    lib_blocks = blks[: max(1, lib_records // PER_BLOCK)]
    t = time.perf_counter()
    n_lib = 0
    for b in lib_blocks:
        n_lib += len([codec.ref048(r) for r in codec.parse_block(b)])   # type: ignore[union-attr]
    lib_s = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as tmp:
        rec_file = Path(tmp) / "day.ast"
        with rec_file.open("wb") as fh:                  # every block twice: two redundant lines
            for b in blks:
                fh.write(b)
                fh.write(b)
        sites = Path(tmp) / "sites.toml"
        sites.write_text(sites_toml(pl.DataFrame([
            {"sac": 25, "sic": s, "radar_id": 25 * 256 + s, "name": f"r{s}", "lat_deg": 45.0, "lon_deg": 16.0,
             "alt_m": 0.0, "sigma_range_m": 70.0, "sigma_azimuth_deg": 0.08, "max_range_m": 463000.0,
             "sigma_elevation_deg": 1.0, "scan_period_s": 4.0} for s in range(1, 21)])))
        t = time.perf_counter()
        res = dataset.import_recordings([rec_file], sites=sites, date="2024-01-01")
        imp_s = time.perf_counter() - t
    return {"load_average_1min": round(load, 2), "records": n, "record_bytes": int(recs.shape[1]),
            "fast_decode_records_per_s": round(n / fast_s), "libasterix_decode_records_per_s": round(n_lib / lib_s),
            "speedup": round((n / fast_s) / (n_lib / lib_s), 1),
            "import_records_in": 2 * n, "import_reports_out": res.reports.height,
            "import_duplicates": res.counts["duplicates"], "import_s": round(imp_s, 2),
            "import_records_per_s": round(2 * n / imp_s)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=1_000_000)
    ap.add_argument("--lib-records", type=int, default=2_000)
    ap.add_argument("--only-new", action="store_true", help="measure CAT001/002/004/020/station CAT021 only")
    ap.add_argument("--cats", default="1,2,4,20,21", help="with --only-new: the categories (21: station CAT021)")
    ap.add_argument("--mb", type=int, default=0, choices=range(4),
                    help="measure CAT048 only, its records carrying I048/250 with this many registers")
    args = ap.parse_args()
    machine = f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"
    if args.only_new:
        cats = tuple(int(c) for c in args.cats.split(","))
        result = {"machine": machine, **_new_rates(args.records // 5, cats)}
    elif args.mb:
        rates = _cat048_rates(args.records, args.lib_records, args.mb)
        result = {"machine": machine, "mb_registers": args.mb, **{f"{k}_mb": v for k, v in rates.items()}}
    else:
        t = time.perf_counter()
        codec.lib()
        import_s = time.perf_counter() - t
        rates = _cat048_rates(args.records, args.lib_records)
        cat021 = _cat021_rate(args.records // 5)
        result = {"machine": machine, **rates, "libasterix_import_s": round(import_s, 2), **cat021,
                  **_new_rates(args.records // 5)}
    print(json.dumps(result, indent=2))
    _write(result)


if __name__ == "__main__":
    main()
