"""What a 15-minute chunk of the truth's separation intervals costs on a day's reference.

    python benchmarks/bench_truth_chunks.py --reference RUN/parts/_scratch/reference --every 4

``--reference``: a reference directory of the national scenario (``write_reference_pieces``, with its files'
time ranges; the national day's: 304 files, 79 M samples). For every ``--every``-th chunk of the
day, the chunk's intervals (``stca_scoring._chunk_intervals``) are computed twice: scanning every
file for its edge samples and its slice, and from the files' time ranges. Records each way's
total and per-chunk median, and whether every chunk's intervals are equal, in
``results/bench_truth_chunks.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record  # noqa: E402

from safety import AlertConfig  # noqa: E402
from tertiary.core import geo  # noqa: E402
from tertiary.core.units import US  # noqa: E402
from tertiary.evaluation.evaluate import reference_files  # noqa: E402
from tertiary.evaluation.reference_spans import read_spans  # noqa: E402
from tertiary.pipeline import stca_scoring  # noqa: E402
from tertiary.simulate import load_scenario  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference", type=Path, required=True)
    ap.add_argument("--every", type=int, default=4)
    a = ap.parse_args()
    files = reference_files(a.reference)
    spans = read_spans(files)
    lf = pl.scan_parquet(files)
    cols = [c for c in stca_scoring.ALERT_TRUTH if c in lf.collect_schema()]
    frame = geo.LocalFrame(*load_scenario("national").origin)
    acfg = AlertConfig()
    lo = min(s[0] for s in spans if s[0] is not None)
    hi = max(s[1] for s in spans if s[1] is not None) + 1
    step = int(stca_scoring.TRUTH_CHUNK_S * US)
    times: dict[str, list[float]] = {"scan_every_file": [], "time_ranges": []}
    equal = True
    for a_us in range(lo, hi, step * a.every):
        b_us = min(a_us + step, hi)
        t = time.perf_counter()
        r1 = stca_scoring._chunk_intervals(lf, cols, acfg, frame, a_us, b_us)
        times["scan_every_file"].append(time.perf_counter() - t)
        t = time.perf_counter()
        r2 = stca_scoring._chunk_intervals(lf, cols, acfg, frame, a_us, b_us, (files, spans))
        times["time_ranges"].append(time.perf_counter() - t)
        equal = equal and r1[0].equals(r2[0]) and r1[1].equals(r2[1])
    n_chunks = -(-(hi - lo) // step)
    results = {k: {"chunks_timed": len(v), "total_s": round(sum(v), 2), "median_s": round(statistics.median(v), 3),
                   "day_estimate_s": round(statistics.mean(v) * n_chunks, 1)} for k, v in times.items()}
    print(results, "equal", equal)
    print(record("bench_truth_chunks", {"reference": str(a.reference), "files": len(files), "every": a.every,
                                        "chunks_in_reference": n_chunks, "equal": equal, "results": results}))


if __name__ == "__main__":
    main()
