"""Scaling of the Dask engine on this machine (1 and 2 workers, LocalCluster) on a moderate
terminal-area recording cut into time slices: wall time, per-slice task times, scheduler overhead,
stitching effects against the local engine; an estimate for 8/32/128 workers from the measured
per-slice times and overhead. Results: benchmarks/results/bench_dask.json.

    PYTHONPATH=. python benchmarks/bench_dask.py [--aircraft 60] [--duration 1200] [--slice 300] [--overlap 60]

An existing dataset instead (e.g. an hour of the national day, with ``--config production``:
one fusion method, the ``imm_sym`` tracker, no centralised reference, the STCA curves):

    PYTHONPATH=. python benchmarks/bench_dask.py --dataset DIR --config production --slice 900 --overlap 120 \
        --out benchmarks/results/bench_dask_national.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import polars as pl

from tertiary.pipeline import dask_engine as D
from tertiary import pipeline
from tertiary.io.dataset import read_dataset, write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore

OUT = Path(__file__).parent / "results" / "bench_dask.json"
CFG = pipeline.PipelineConfig(stca_lookaheads_s=(), methods=("information",), filters=("singer",))
CONFIGS = {"light": CFG,
           "production": pipeline.PipelineConfig(methods=("information",), filters=("imm_sym",), centralized=False)}



def _noop(i: int) -> int:
    return i


def _overhead(client, n: int = 200) -> float:
    """Scheduler round trip per task (s): n no-op tasks submitted and gathered."""
    client.gather(client.map(_noop, range(20), pure=False))
    t = time.perf_counter()
    client.gather(client.map(_noop, range(n), pure=False))
    return (time.perf_counter() - t) / n


def _tables(db: Path) -> dict:
    with RunStore.open(db.parent) as s:
        return {n: s.read(n) for n in ("associations", "fused", "tracks", "partitions") if n in s.tables()}


def _dask_run(ds_dir: Path, out: Path, workers: int, window_s, slice_s: float, overlap_s: float,
              cfg: pipeline.PipelineConfig = CFG, tables: str = "database") -> dict:
    from distributed import Client, LocalCluster
    t = time.perf_counter()
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    startup = time.perf_counter() - t
    try:
        per_task = _overhead(client)
        t = time.perf_counter()
        res = D.run_dask_detailed(ds_dir, out, cfg, client=client, window_s=window_s, slice_s=slice_s,
                                  overlap_s=overlap_s, tables=tables)
        wall = time.perf_counter() - t
    finally:
        client.close()
        cluster.close()
    tasks = res.partitions["task_s"].to_list()
    tm = res.timings
    return {"workers": workers, "cluster_startup_s": startup, "wall_s": wall, "scheduler_roundtrip_s": per_task,
            "partition_task_s": tasks, "partition_input_rows": res.partitions["input_rows"].to_list(),
            "partitions_phase_s": tm["partitions_s"],
            # what the partition phase cost beyond the tasks' own work spread over the workers
            "partitions_phase_overhead_s": tm["partitions_s"] - sum(tasks) / workers,
            "stitch_s": tm["stitch_s"], "relabel_s": tm["relabel_s"], "finalize_s": tm["finalize_s"],
            # the boundaries' pieces on the workers: the client's wait for them, their work
            "stitch_pieces_wall_s": tm.get("stitch_pieces_wall_s", 0.0),
            "stitch_task_s_sum": tm.get("stitch_task_s_sum", 0.0),
            "stitch_task_s_max": tm.get("stitch_task_s_max", 0.0),
            # the finalize's pieces run on the workers: the client's wait for them, their work
            "finalize_fanout_wall_s": tm.get("fanout_wall_s", 0.0),
            "finalize_fanout_task_s_sum": tm.get("fanout_task_s_sum", 0.0),
            "finalize_fanout_task_s_max": tm.get("fanout_task_s_max", 0.0),
            "plan_s": tm["plan_s"], "finalize_stages_s": _finalize_stages(res.db), "stitching": res.stitching.to_dicts(),
            "db": str(res.db)}


#: the stages the client runs after the partitions (their times in the run record)
FINALIZE_STAGES = ("validate", "evaluation", "score_alerts", "score_curves", "stca_curves", "evaluate",
                   "write_tables")


def _finalize_stages(db: Path) -> dict[str, float]:
    """The client's whole-run stages and their times (s) from the run record."""
    with RunStore.open(db.parent) as s:
        run = dict(s.read("run").iter_rows())
    timings = json.loads(run["timings"])
    return {k: round(timings[f"{k}_s"], 2) for k in FINALIZE_STAGES if f"{k}_s" in timings}


def _spread(work_s: float, longest_s: float, workers: int) -> float:
    """Pieces of ``work_s`` in all spread over ``workers``, no less than the longest piece."""
    return max(work_s / workers, longest_s) if work_s else 0.0


def _estimate(run: dict, n_slices_day: int, workers: int, task_s: float, stitch_per_boundary_s: float,
              finalize_s: float, fanout_s: float = 0.0, fanout_max_s: float = 0.0,
              stitch_pieces_s: float = 0.0, write_tables_s: float = 0.0) -> dict:
    """Wall time of ``n_slices_day`` slices on ``workers`` workers: waves of tasks, the scheduler's
    round trip per task, the stitching (its pieces, ``stitch_pieces_s`` of work spread over the
    workers, and the client's threading per boundary), the finalize stage on the client
    (``finalize_s``) and its pieces on the workers (``fanout_s`` of work spread over them, no
    less than the longest piece); the tables are written on the client beside the finalize
    (``write_tables_s``, one writer), which takes no less than that."""
    waves = math.ceil(n_slices_day / workers)
    part = waves * task_s + n_slices_day * run["scheduler_roundtrip_s"]
    relabel = waves * run["relabel_s"] / max(1, math.ceil(len(run["partition_task_s"]) / run["workers"]))
    fan = _spread(fanout_s, fanout_max_s, workers)
    stitch = stitch_per_boundary_s * (n_slices_day - 1) + _spread(stitch_pieces_s, run.get("stitch_task_s_max", 0.0),
                                                                  workers)
    total = part + relabel + stitch + max(finalize_s + fan, write_tables_s)
    return {"workers": workers, "partitions_phase_s": part, "stitch_s": stitch,
            "relabel_s": relabel, "finalize_client_s": finalize_s, "finalize_pieces_s": fan,
            "write_tables_s": write_tables_s, "total_s": total}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--aircraft", type=int, default=60)
    ap.add_argument("--duration", type=float, default=1200.0)
    ap.add_argument("--slice", type=float, default=300.0)
    ap.add_argument("--overlap", type=float, default=60.0)
    ap.add_argument("--dataset", type=Path, default=None, help="an existing dataset instead of a simulated one")
    ap.add_argument("--config", choices=sorted(CONFIGS), default="light")
    ap.add_argument("--work", type=Path, default=None, help="work directory [default: a new temporary one]")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--tables", choices=("database", "parquet"), default="database",
                    help="where the runs' tables go (the national day is run with parquet)")
    ap.add_argument("--day-reports", type=float, default=None,
                    help="reports in the day of the estimate [default: 24 h at this recording's rate]")
    a = ap.parse_args()
    window_s = 60.0
    run_cfg = CONFIGS[a.config]
    tmp = a.work or Path(tempfile.mkdtemp(prefix="bench_dask_"))
    tmp.mkdir(parents=True, exist_ok=True)
    if a.dataset is None:
        cfg = load_scenario("terminal-area")
        cfg = dataclasses.replace(cfg, duration_s=a.duration - 10.0, runs=1,
                                  traffic=dataclasses.replace(cfg.traffic, aircraft=a.aircraft))
        ds = simulate(cfg)
        write_dataset(ds, tmp / "ds")
        ds_dir, scenario = tmp / "ds", {"kind": "terminal-area", "aircraft": a.aircraft}
    else:
        ds_dir = a.dataset
        ds = read_dataset(ds_dir, lazy=True)
        scenario = {"kind": ds.scenario.name, "dataset": str(ds_dir)}
    lf = read_dataset(ds_dir, lazy=True).reports
    n_reports = int(lf.select(pl.len()).collect().item())
    span = lf.select(pl.col("time").min().alias("a"), pl.col("time").max().alias("b")).collect()
    a.duration = (span["b"][0] - span["a"][0]).total_seconds() if a.dataset is not None else a.duration
    t = time.perf_counter()
    local_db = pipeline.run(read_dataset(ds_dir, lazy=True), tmp / "local", run_cfg, window_s=window_s,
                            tables=a.tables)
    local_s = time.perf_counter() - t
    runs = [_dask_run(ds_dir, tmp / f"dask{w}", w, window_s, a.slice, a.overlap, run_cfg, a.tables) for w in (1, 2)]
    dk, lc = _tables(Path(runs[-1]["db"])), _tables(local_db)
    bounds = sorted(D.parse_utc(x) for x in dk["partitions"]["kept_from_utc"].to_list()[1:])
    effects = D.stitching_effects(dk, lc, bounds)
    # per-slice model from the 2-worker run: a slice's task time per input report, the client's
    # stitching per boundary, the finalize stage per report
    r2 = runs[-1]
    rows = sum(r2["partition_input_rows"])
    s_per_row = sum(r2["partition_task_s"]) / rows
    boundaries = max(1, len(r2["partition_task_s"]) - 1)
    day_s = 86400.0
    n_day = math.ceil(day_s / a.slice)
    rate = n_reports / a.duration                       # this recording's report rate (reports/s of data)
    if a.day_reports:                                   # a day's mean rate (the national day's curve)
        rate = a.day_reports / day_s
    task_day = s_per_row * rate * (a.slice + a.overlap)
    per_day = rate * day_s / n_reports
    fin_day = (r2["finalize_s"] - r2["finalize_fanout_wall_s"]) * per_day
    fan_day = r2["finalize_fanout_task_s_sum"] * per_day
    # the boundaries' pieces scale with the slices' reports; the client threads them per boundary
    stitch_client = (r2["stitch_s"] - r2["stitch_pieces_wall_s"]) / boundaries
    stitch_day = r2["stitch_task_s_sum"] * per_day
    write_day = r2["finalize_stages_s"].get("write_tables", 0.0) * per_day
    est = [_estimate(r2, n_day, w, task_day, stitch_client, fin_day, fan_day, r2["finalize_fanout_task_s_max"],
                     stitch_day, write_day) for w in (8, 32, 128)]
    result = {
        "window_s": window_s, "config": {"name": a.config, "methods": list(run_cfg.methods),
                                         "filters": list(run_cfg.filters), "centralized": run_cfg.centralized,
                                         "stca_curves": bool(run_cfg.stca_lookaheads_s)},
        "scenario": {**scenario, "duration_s": a.duration, "reports": n_reports},
        "slice_s": a.slice, "overlap_s": a.overlap, "tables": a.tables, "machine_cores": 2,
        "local": {"wall_s": local_s, "reports_per_s": n_reports / local_s},
        "dask": [{k: v for k, v in r.items() if k != "db"} | {"reports_per_s": n_reports / r["wall_s"]}
                 for r in runs],
        "speedup_2_vs_1": runs[0]["wall_s"] / runs[1]["wall_s"],
        "stitching_effects": effects,
        "estimate_day": {"model": "24 h at this recording's report rate (or --day-reports over 24 h), "
                                  "slices of slice_s with overlap_s warm-up; "
                                  "task time = measured s per input report x slice input; waves of tasks over the "
                                  "workers + scheduler round trip per task + the stitching's pieces (measured task s "
                                  "per report over the workers) + the client's threading of them per boundary "
                                  "(sequential) + finalize on the client (measured s per report, its pieces "
                                  "on the workers taken out) + the finalize's pieces (measured task s per report "
                                  "over the workers, no less than the longest measured piece), or the client's "
                                  "writing of the tables beside them (measured s per report) where that is longer",
                         "slices": n_day, "task_s_per_slice": task_day, "estimates": est},
    }
    a.out.write_text(json.dumps(result, indent=1, default=str))
    print(json.dumps({k: result[k] for k in ("local", "speedup_2_vs_1")}, indent=1))
    for r in result["dask"]:
        print(r["workers"], "workers:", f"{r['wall_s']:.1f} s", f"tasks {r['partition_task_s']}",
              f"overhead/task {r['scheduler_roundtrip_s'] * 1e3:.1f} ms")
    print(json.dumps(est, indent=1))


if __name__ == "__main__":
    main()
