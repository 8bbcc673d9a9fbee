"""What a window's time slice of the reference costs as the reference grows to a day.

    python benchmarks/bench_reference_slices.py --source RUN/parts/_scratch/reference --copies 7

``--source``: a reference directory a run wrote (``write_reference_pieces``; the national 3 hours'
is 44 files, 11.4 M samples). The benchmark writes it, then it and ``--copies`` more copies of it
shifted by its span each (7 more of 3 hours: 24 hours, 352 files, 91 M samples), and times, at
times spread over each, the windows' slices: the matcher's (``Reference.between``, a minute; every
window) and the truth picture's (``reference_slice``, a minute and its margin; every fifth window,
as the bound's), each reading only the files that can hold its rows and reading every file.
Records the medians in ``results/bench_reference_slices.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path
from unittest import mock

import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record  # noqa: E402

from tertiary.evaluation.evaluate import Reference, reference_files, write_reference_pieces  # noqa: E402
from tertiary.pipeline.truth_alerts import reference_slice  # noqa: E402

_TIMES = ("time", "__prev", "__next")


def _day(source: Path, copies: int, out: Path) -> Path:
    """``source``'s files, then ``copies`` more of them shifted by its span each, as one reference."""
    files = reference_files(source)
    span = pl.scan_parquet(files).select(pl.col("time").max() - pl.col("time").min()).collect().item()
    shift = span + timedelta(seconds=1)

    def pieces():
        for k in range(copies + 1):
            for f in files:
                yield pl.read_parquet(f).with_columns(pl.col(c) + k * shift for c in _TIMES)
    return write_reference_pieces(pieces(), out)


def _median_ms(fn, repeat: int = 3) -> float:
    fn()                                       # the first read warms the page cache
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1000)
    return statistics.median(out)


def _slices(path: Path, at: list[datetime]) -> dict:
    pruned, every = Reference(path), Reference(path)
    every._spans = None
    us = [int((t - datetime(1970, 1, 1, tzinfo=timezone.utc)) / timedelta(microseconds=1)) for t in at]
    sl_pruned = reference_slice(pruned.files)
    with mock.patch("tertiary.pipeline.truth_alerts.read_spans", return_value=None):
        sl_every = reference_slice(pruned.files)           # the same slice, of every file
    margin = 120 * 10**6

    def matcher(ref):
        return lambda: [ref.between(t, t + timedelta(seconds=59)) for t in at]

    def truth(files_of):
        return lambda: [files_of(u - margin, u + 60 * 10**6 + margin) for u in us]
    out = {"files": len(pruned.files), "slices": len(at),
           "matcher_ms_per_slice": {"pruned": _median_ms(matcher(pruned)) / len(at),
                                    "every_file": _median_ms(matcher(every)) / len(at)},
           "truth_picture_ms_per_slice": {"pruned": _median_ms(truth(sl_pruned)) / len(at),
                                          "every_file": _median_ms(truth(sl_every)) / len(at)}}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", type=Path, required=True)
    ap.add_argument("--copies", type=int, default=7)
    ap.add_argument("--work", type=Path, default=None)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=a.work) as tmp:
        results = {}
        for name, copies in (("source", 0), ("day", a.copies)):
            path = _day(a.source, copies, Path(tmp) / name)
            scan = pl.scan_parquet(reference_files(path))
            lo, hi, n = scan.select(pl.col("time").min().alias("lo"), pl.col("time").max().alias("hi"),
                                    pl.len()).collect().row(0)
            at = [lo + (hi - lo) * k / 12 for k in range(1, 12)]      # eleven minutes spread over it
            results[name] = {"samples": n, **_slices(path, at)}
            print(name, results[name], flush=True)
    print(record("bench_reference_slices", {"source": str(a.source), "copies": a.copies, "results": results}))


if __name__ == "__main__":
    main()
