"""The national day: the 24 h ``national`` recording processed on one machine, with
the local engine or with Dask, in the production configuration (one fusion method, one tracker,
conflicts, evaluation; the streamed tables registered as Parquet, ``--tables parquet``).

    tertiary simulate national --out DATA --window 3600
    python benchmarks/bench_national_day.py --dataset DATA --out RUN [--engine dask --workers 2 --slice 7200]
    python benchmarks/bench_national_day.py --dataset DATA --out RUN --resume   # a killed run's rest

Runs ``tertiary run`` in a child process and samples its process tree every 2 s: each process's
peak resident memory (the client and each Dask worker apart), the tree's peak sum, and the disk
free. A run killed and resumed is recorded as its phases (``--time-log`` adds a phase measured by
``/usr/bin/time -v`` instead); a run that fails keeps its phase beside its log
(``<out>.<k>.failed.json``) for the ``--resume`` after it, whose log is the next
``<out>.<k>.log``. Records the run's own stage timings, peak by stage and counts from its
database, and the size of its tables and database.

Results: ``benchmarks/results/bench_national_day.json`` (one entry per engine).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, machine  # noqa: E402

PRODUCTION = ["--no-report", "--methods", "information", "--filters", "imm_sym", "--no-centralized",
              "--tables", "parquet"]


def _watched(cmd: list[str], log: Path) -> dict:
    """Run ``cmd``; its wall time, exit code and the peaks of its process tree."""
    import psutil
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        root = psutil.Process(proc.pid)
        peaks: dict[int, tuple[str, float]] = {}
        tree_peak, min_free = 0.0, float("inf")
        while proc.poll() is None:
            try:
                procs = [root, *root.children(recursive=True)]
            except psutil.Error:
                break
            total = 0.0
            for p in procs:
                try:
                    rss = p.memory_info().rss / 2**20
                    # a LocalCluster's workers are spawned by multiprocessing
                    kind = ("client" if p == root else
                            "worker" if "multiprocessing" in " ".join(p.cmdline()) else "other")
                except psutil.Error:
                    continue
                total += rss
                if rss > peaks.get(p.pid, ("", 0.0))[1]:
                    peaks[p.pid] = (kind, rss)
            tree_peak = max(tree_peak, total)
            min_free = min(min_free, shutil.disk_usage(log.parent).free / 1e9)
            time.sleep(2.0)
    wall = time.perf_counter() - t0
    by = sorted(({"pid": k, "kind": v[0], "peak_rss_mib": round(v[1], 1)} for k, v in peaks.items()
                 if v[1] > 100), key=lambda d: -d["peak_rss_mib"])
    return {"cmd": " ".join(cmd[1:]), "exit": proc.returncode, "wall_s": round(wall, 1),
            "tree_peak_rss_mib": round(tree_peak, 1), "processes": by, "min_disk_free_gb": round(min_free, 1)}


def _time_log(path: Path) -> dict:
    """A phase measured by ``/usr/bin/time -v`` (wall, peak RSS of the process)."""
    text = path.read_text()
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", text).group(1)
    secs = sum(float(x) * 60 ** i for i, x in enumerate(reversed(wall.split(":"))))
    peak = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", text).group(1)) / 1024
    # a process killed by a signal is reported with "Exit status: 0": its signal, negated, instead
    signal = re.search(r"Command terminated by signal (\d+)", text)
    status = re.search(r"Exit status: (\d+)", text)
    code = -int(signal.group(1)) if signal else int(status.group(1)) if status else None
    return {"cmd": f"(from {path.name})", "exit": code, "wall_s": round(secs, 1),
            "tree_peak_rss_mib": round(peak, 1), "processes": [{"kind": "client", "peak_rss_mib": round(peak, 1)}]}


def _free_log(out: Path, first: int) -> Path:
    """The run's log ``<out>.<k>.log`` for the first k from ``first`` not taken: a resumed run's
    log is written beside the killed run's, not over it."""
    k = first
    while (out.parent / f"{out.name}.{k}.log").exists():
        k += 1
    return out.parent / f"{out.name}.{k}.log"


def _size_gb(path: Path) -> float:
    if path.is_file():
        return round(path.stat().st_size / 1e9, 2)
    return round(sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e9, 2) if path.exists() else 0.0


def _from_db(run: Path) -> dict:
    from tertiary.store.run_store import RunStore
    with RunStore.open(run) as store:
        rec = dict(store.sql("SELECT key, value FROM run").iter_rows())
    out = {k: json.loads(rec[k]) for k in ("rows", "timings", "memory_mib") if k in rec}
    out["status"] = rec.get("status")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--engine", default="local", choices=["local", "dask"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--slice", type=float, default=7200.0, help="--engine dask: time slice (s)")
    ap.add_argument("--key", help="the entry's name in the results (default: the engine's)")
    ap.add_argument("--resume", action="store_true", help="resume the killed run in --out (local engine)")
    ap.add_argument("--time-log", type=Path, action="append", default=[],
                    help="a phase already run under /usr/bin/time -v (its output), recorded first")
    args = ap.parse_args()
    cmd = [sys.executable, "-m", "tertiary.cli.main", "run", str(args.dataset), *PRODUCTION]
    if args.engine == "dask":
        cmd += ["--out", str(args.out), "--engine", "dask", "--workers", str(args.workers), "--slice",
                str(args.slice)]
    elif args.resume:
        cmd += ["--resume", str(args.out)]
    else:
        cmd += ["--out", str(args.out)]
    phases = [_time_log(p) for p in args.time_log]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.resume:         # the failed attempts before this one, as they were recorded
        phases += [json.loads(p.read_text()) for p in sorted(args.out.parent.glob(f"{args.out.name}.*.failed.json"))]
    log = _free_log(args.out, len(phases))
    phases.append(_watched(cmd, log))
    if phases[-1]["exit"] != 0:
        log.with_suffix(".failed.json").write_text(json.dumps(phases[-1], indent=1) + "\n")
        raise SystemExit(f"tertiary run failed: see {log}")
    got = _from_db(args.out)
    reports = got["rows"]["reports_in"]
    wall = sum(p["wall_s"] for p in phases)
    entry = {"dataset": str(args.dataset), "config": "production " + " ".join(PRODUCTION),
             "engine": args.engine, **({"workers": args.workers, "slice_s": args.slice} if args.engine == "dask"
                                       else {}),
             "phases": phases, "wall_s": round(wall, 1), "reports": reports,
             "reports_per_s": round(reports / wall, 1),
             "peak_rss_mib_by_kind": {k: max(q["peak_rss_mib"] for p in phases for q in p["processes"]
                                             if q["kind"] == k)
                                      for k in {q["kind"] for p in phases for q in p["processes"]}},
             "disk_gb": {"tables": _size_gb(args.out / "tables"), "database": _size_gb(args.out / "results.duckdb"),
                         "input": _size_gb(args.dataset)},
             **got}
    path = RESULTS / "bench_national_day.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    old.pop("machine", None)
    old[args.key or args.engine] = entry
    path.write_text(json.dumps({"machine": machine(), **old}, indent=2) + "\n")
    print(json.dumps({k: entry[k] for k in ("wall_s", "reports", "reports_per_s", "peak_rss_mib_by_kind",
                                            "disk_gb")}, indent=1))


if __name__ == "__main__":
    main()
