"""What each aircraft's truth spacing (the bound's setup) costs on a day's reference.

    python benchmarks/bench_truth_gaps.py --reference RUN/tables/truth

``--reference``: the reference files of a run (each sample with its aircraft's ``__prev`` and
``__next``; the national day's: 304 files, 79 M samples). Each aircraft's spacing is computed two
ways, each in a fresh process: sorting every aircraft's samples by time (``truth_gaps``) and
reading the reference's own neighbour times (``reference_gaps``). Records each way's wall time and
peak memory, and whether both give the same frame, in ``results/bench_truth_gaps.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record, run_isolated  # noqa: E402

_CHILD = """
import json, time, polars as pl
from tertiary.evaluation.bound_truth import {fn}
from tertiary.evaluation.evaluate import reference_files
truth = pl.scan_parquet(reference_files({ref!r}))
t0 = truth.select(pl.col("time").min()).collect().item()
t = time.perf_counter()
gaps = {fn}(truth, int(t0.timestamp() * 1e6))
wall = time.perf_counter() - t
gaps.write_parquet({out!r})
print(json.dumps({{"wall_s": wall, "aircraft": gaps.height}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference", type=Path, required=True)
    ap.add_argument("--scratch", type=Path, default=Path("/tmp"))
    a = ap.parse_args()
    import polars as pl
    out, frames = {}, {}
    for fn in ("truth_gaps", "reference_gaps"):
        path = a.scratch / f"bench_truth_gaps_{fn}.parquet"
        out[fn] = run_isolated(_CHILD.format(fn=fn, ref=str(a.reference), out=str(path)))
        frames[fn] = pl.read_parquet(path)
        path.unlink()
    equal = frames["truth_gaps"].equals(frames["reference_gaps"])
    samples = pl.scan_parquet(str(a.reference / "*.parquet")).select(pl.len()).collect().item()
    payload = {"reference": str(a.reference), "samples": samples, "equal": equal, **out,
               "speedup": out["truth_gaps"]["wall_s"] / out["reference_gaps"]["wall_s"]}
    record("bench_truth_gaps", payload)
    print(json.dumps(payload, indent=1))


if __name__ == "__main__":
    main()
