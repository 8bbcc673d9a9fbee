"""ASTERIX decode throughput: CAT048 records/s of the compiled decoder, of libasterix, and of the
whole import (decode + de-duplication + time + values + flags), on one machine.

Input: N distinct CAT048 records of a typical Mode S plot layout (010, 140, 020, 040, 070, 090,
220, 240, 161, 200, 170; 32 bytes), packed 40 per data block, every block sent on two redundant
lines (so the import de-duplicates N of 2N). The records are laid out with numpy (byte positions
of that fixed layout) and a sample of them is checked against libasterix before timing.

    PYTHONPATH=. python benchmarks/bench_asterix.py [--records 1000000]

Writes benchmarks/results/asterix.json.
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


def records(n: int, seed: int = 1) -> np.ndarray:
    """n CAT048 records (n × 32 bytes): FSPEC FD D6 (010 140 020 040 070 090 | 220 240 161 200 170)."""
    rng = np.random.default_rng(seed)
    rec = np.zeros((n, 32), np.uint8)
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
    put(25, 2, rng.integers(0, 4096, n))                            # track number
    put(27, 2, rng.integers(0, 2**14, n))                           # ground speed
    put(29, 2, rng.integers(0, 65536, n))                           # heading
    put(31, 1, np.full(n, 2 << 4))                                  # 170: RAD=2
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=1_000_000)
    ap.add_argument("--lib-records", type=int, default=2_000)
    args = ap.parse_args()
    t = time.perf_counter()
    codec.lib()
    import_s = time.perf_counter() - t
    recs = records(args.records)
    blks = blocks(recs)
    check_sample(blks)
    fast048.decode_blocks(blks[:2])                       # compile / load the cache
    t = time.perf_counter()
    raw, _, bad = fast048.decode_blocks(blks)
    fast_s = time.perf_counter() - t
    assert raw.shape[0] == args.records and not bad
    lib_blocks = blks[: max(1, args.lib_records // PER_BLOCK)]
    t = time.perf_counter()
    n_lib = 0
    for b in lib_blocks:
        n_lib += len([codec.ref048(r) for r in codec.parse_block(b)])   # type: ignore[union-attr]
    lib_s = time.perf_counter() - t
    from tertiary.io.asterix import dataset
    from tertiary.io.asterix.sites import sites_toml
    import polars as pl
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
    cat021 = _cat021_rate(args.records // 5)
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "records": args.records, "record_bytes": int(recs.shape[1]),
        "libasterix_import_s": round(import_s, 2),
        "fast_decode_records_per_s": round(args.records / fast_s),
        "libasterix_decode_records_per_s": round(n_lib / lib_s),
        "speedup": round((args.records / fast_s) / (n_lib / lib_s), 1),
        "import_records_in": 2 * args.records, "import_reports_out": res.reports.height,
        "import_duplicates": res.counts["duplicates"], "import_s": round(imp_s, 2),
        "import_records_per_s": round(2 * args.records / imp_s),
        **cat021,
    }
    print(json.dumps(result, indent=2))
    out = Path(__file__).parent / "results" / "asterix.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
