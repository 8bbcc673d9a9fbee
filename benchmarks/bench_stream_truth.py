"""What validating a long run's truth from disk to disk costs before its first window.

    python benchmarks/bench_stream_truth.py --dataset DATA [--label after] [--tree DIR] [--commit ID]

``--dataset``: a dataset directory whose truth is in parts (the national day's: 144 files,
79 M samples). Each run calls ``tertiary.pipeline.ingestion.stream_truth`` once in a fresh
process, as an on-disk run does at its start (the time window left open), and records its wall
time, the process's peak resident memory, the reference it wrote (files, rows) and a digest of
that reference's rows and order, which must be the same for every tree. ``--tree``: run the code
of another checkout (the tree before a change). The results go to
``results/bench_stream_truth.json`` under ``--label``; other labels, and the entries recorded by
hand beside them (``pipeline_check``: whole runs of the day to their first windows), are kept.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, machine, record, run_isolated  # noqa: E402

_CODE = """
import sys, time, json
{path}
import polars as pl
from pathlib import Path
from tertiary.io.dataset import read_dataset
from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.ingestion import stream_truth
from tertiary.evaluation.evaluate import reference_files
ds = read_dataset({dataset!r}, lazy=True)
t = time.perf_counter()
on_disk, rejects = stream_truth(ds, PipelineConfig(), [], None, Path({scratch!r}))
wall = time.perf_counter() - t
files = reference_files(on_disk.reference)
# the rows and their order: a digest of each row's hash and its position
digest = (pl.scan_parquet(files).with_row_index("__i")
          .select((pl.struct(pl.all()).hash(7) // 2).sum()).collect().item())
print(json.dumps({{"wall_s": round(wall, 1), "rows": on_disk.rows,
                   "rejects": rejects.height, "reference_files": len(files), "digest": str(digest)}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--label", default="after")
    ap.add_argument("--tree", type=Path, default=None)
    ap.add_argument("--commit", default=None, help="the tree's commit, recorded beside its figures")
    ap.add_argument("--work", type=Path, default=None)
    a = ap.parse_args()
    path = f"sys.path.insert(0, {str(a.tree.resolve())!r})" if a.tree else ""
    with tempfile.TemporaryDirectory(dir=a.work) as tmp:
        got = run_isolated(_CODE.format(path=path, dataset=str(a.dataset), scratch=tmp))
    got["peak_rss_mib"] = round(got["peak_rss_mib"], 1)
    print(got, flush=True)
    old = RESULTS / "bench_stream_truth.json"
    kept = json.loads(old.read_text()) if old.exists() else {}
    kept.pop("machine", None)
    runs = kept.pop("runs", {})
    runs[a.label] = {"machine": machine(), "commit": a.commit, **got}
    print(record("bench_stream_truth", {**kept, "dataset": str(a.dataset), "runs": runs}))


if __name__ == "__main__":
    main()
