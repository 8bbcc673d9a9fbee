"""Monte-Carlo runs on the Dask engine: each run one partition on a LocalCluster worker, the
client merging what they return and finishing the whole-run stages. Measures, per source tree
(``--tree NAME=DIR``, that tree first on the path, a fresh interpreter each), the wall time, the
partitions' phase, the client's finalize and its stages, and the metrics' agreement between the
trees. Results: ``benchmarks/results/bench_dask_runs.json``.

    PYTHONPATH=. python benchmarks/bench_dask_runs.py --runs 4 --duration 1200 \
        --tree before=/path/to/worktree --tree after=. [--workers 1 2] [--repeat 1]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, record  # noqa: E402

#: one Dask run in a fresh interpreter: prints its measures as one JSON line
_CHILD = r"""
import json, sys, time
from pathlib import Path
from distributed import Client, LocalCluster
from tertiary.pipeline import dask_engine as D
from tertiary.store.run_store import RunStore
ds, out, workers = sys.argv[1], Path(sys.argv[2]), int(sys.argv[3])
cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
client = Client(cluster)
try:
    t = time.perf_counter()
    res = D.run_dask_detailed(ds, out, None, client=client, window_s=60.0)
    wall = time.perf_counter() - t
finally:
    client.close(); cluster.close()
with RunStore.open(out) as s:
    timings = json.loads(dict(s.read("run").iter_rows())["timings"])
    s.read("metrics").write_parquet(out / "metrics.parquet")
stages = ("validate", "evaluation", "score_alerts", "score_curves", "evaluate", "write_tables")
print(json.dumps({"wall_s": round(wall, 2), "partitions_s": round(res.timings["partitions_s"], 2),
                  "finalize_s": round(res.timings["finalize_s"], 2),
                  "partition_task_s": [round(x, 2) for x in res.partitions["task_s"].to_list()],
                  "finalize_stages_s": {k: round(timings[k + "_s"], 2) for k in stages if k + "_s" in timings}}))
"""


def _simulate(work: Path, runs: int, duration_s: float) -> Path:
    """The terminal-area scenario with ``runs`` Monte-Carlo runs (made once per work directory)."""
    ds = work / f"ta-{runs}x{int(duration_s)}"
    if not (ds / "reports.parquet").exists():
        subprocess.run([sys.executable, "-m", "tertiary.cli.main", "simulate", "terminal-area", "--runs", str(runs),
                        "--duration", str(duration_s), "--out", str(ds)], check=True, capture_output=True)
    return ds


def _run(tree: Path, ds: Path, out: Path, workers: int) -> dict:
    env = {**os.environ, "PYTHONPATH": f"{tree}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(ds), str(out), str(workers)], capture_output=True,
                          text=True, env=env, cwd=tempfile.gettempdir())
    if proc.returncode != 0:
        raise RuntimeError(f"dask run failed: {proc.stderr.strip()[-600:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _agreement(a: Path, b: Path) -> dict:
    """The largest relative difference of the metrics of two runs, and their row counts."""
    import polars as pl
    key = ["stage", "method", "metric", "segment"]
    x, y = pl.read_parquet(a), pl.read_parquet(b)
    j = x.join(y, on=key, how="full", coalesce=True, suffix="_b")
    diff = ((pl.col("value") - pl.col("value_b")).abs() / pl.max_horizontal(pl.col("value").abs(), 1e-12))
    return {"rows": [x.height, y.height], "unmatched": j.filter(pl.col("value").is_null() != pl.col("value_b").is_null()
                                                                ).height,
            "max_rel_diff": j.select(diff.max()).item()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--duration", type=float, default=1200.0)
    ap.add_argument("--workers", type=int, nargs="+", default=[2])
    ap.add_argument("--tree", action="append", required=True, help="NAME=DIR: a source tree to time")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--what", default="")
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-dask-runs-"))
    work.mkdir(parents=True, exist_ok=True)
    ds = _simulate(work, args.runs, args.duration)
    trees = dict(t.split("=", 1) for t in args.tree)
    results: dict = {name: {} for name in trees}
    for workers in args.workers:
        for k in range(args.repeat):
            for name, tree in trees.items():       # the trees alternate: drift affects both alike
                got = _run(Path(tree).resolve(), ds, work / f"{name}-{workers}-{k}", workers)
                results[name].setdefault(str(workers), []).append(got)
                print(name, workers, k, json.dumps(got), flush=True)
    names = list(trees)
    agree = {f"{names[0]} vs {n}": _agreement(work / f"{names[0]}-{args.workers[0]}-0" / "metrics.parquet",
                                              work / f"{n}-{args.workers[0]}-0" / "metrics.parquet")
             for n in names[1:]}
    print("recorded in", record("bench_dask_runs", {
        "what": args.what, "scenario": {"kind": "terminal-area", "runs": args.runs, "duration_s": args.duration},
        "config": "default (every fusion method and filter, the centralised reference, safety, STCA curves)",
        "window_s": 60.0, "trees": trees, "results": results, "metrics_agreement": agree}))


if __name__ == "__main__":
    main()
