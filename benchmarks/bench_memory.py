"""Memory against the length of the recording.

Simulates terminal-area at the default scenario's traffic rate (200 aircraft per hour, so a
longer recording is a longer recording of the same traffic, not the same 200 aircraft spread
thinner) for several durations with ``tertiary simulate --window 1800`` (partitioned Parquet,
simulated from the traffic schedule window by window; its wall time and peak
memory are recorded per duration as ``simulations``), then runs ``tertiary run DATASET`` (the
windowed engine, default ``--window auto``) on it in two
configurations, each in a fresh process, and records wall time, reports/s and the peak resident
memory of the run process (``ru_maxrss`` of the child), and the
run record's peak by the end of each stage (``memory_mib``: where the memory goes):

* ``production``: one fusion method, one tracker, conflicts, evaluation, store
  (``--methods information --filters imm_sym``);
* ``full``: every default fusion method, the centralised reference and both default trackers.

Targets: the peaks of 1 h, 4 h and 12 h within 15 % of each other; < 1.5 GB for
production and < 3 GB for full. The streamed stages hold one window; the finalize stage
(evaluation, alert scoring, building results.duckdb) still reads the streamed tables of the whole
run, so the peak grows with the duration; the benchmark measures by how much.

    python benchmarks/bench_memory.py [--durations 3600,14400,43200] [--configs production,full]
                                      [--aircraft-per-hour 200] [--full-max-s 14400]

Results: ``benchmarks/results/bench_memory.json`` (a configuration not run keeps its recorded
rows, marked with the date they were measured).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record  # noqa: E402

CONFIGS = {
    "production": ["--methods", "information", "--filters", "imm_sym"],
    "full": [],
}
TARGET_MIB = {"production": 1.5 * 1024, "full": 3.0 * 1024}


#: the child runs the CLI and, whatever its exit, prints its own peak RSS (KiB) as the last line
_CHILD = ("import resource, runpy, sys\n"
          "sys.argv = ['tertiary'] + sys.argv[1:]\n"
          "try:\n    runpy.run_module('tertiary.cli.main', run_name='__main__')\n"
          "except SystemExit as e:\n    code = e.code\nelse:\n    code = 0\n"
          "print('PEAK_KIB', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, flush=True)\n"
          "sys.exit(code or 0)\n")


SIMULATIONS: dict[float, dict] = {}


def _dataset(duration_s: float, work: Path, per_hour: float) -> tuple[Path, int]:
    """The terminal-area recording of ``duration_s`` (simulated once, window by window, in a
    child process whose wall time and peak memory go to :data:`SIMULATIONS`)."""
    aircraft = max(1, round(per_hour * duration_s / 3600.0))
    out = work / f"ta-{int(duration_s)}"
    if not (out / "parts.json").exists():
        cmd = [sys.executable, "-c", _CHILD, "simulate", "terminal-area", "--out", str(out), "--duration",
               str(duration_s), "--aircraft", str(aircraft), "--window", "1800", "--quiet"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"simulate failed: {proc.stderr.strip()[-400:]}")
        peak = [int(l.split()[1]) for l in proc.stdout.splitlines() if l.startswith("PEAK_KIB")]
        reports = json.loads((out / "parts.json").read_text())["reports"]
        SIMULATIONS[duration_s] = {"duration_s": duration_s, "aircraft": aircraft, "reports": reports,
                                   "wall_s": round(wall, 2), "reports_per_s": round(reports / wall, 1),
                                   "peak_rss_mib": round(peak[-1] / 1024, 1) if peak else None}
        print(json.dumps({"simulation": SIMULATIONS[duration_s]}), flush=True)
    return out, aircraft


def _one(duration_s: float, config: str, work: Path, per_hour: float) -> dict:
    """One `tertiary run` in a child process: wall time, its own peak RSS and the reports it read."""
    data, aircraft = _dataset(duration_s, work, per_hour)
    out = work / f"{config}-{int(duration_s)}"
    cmd = [sys.executable, "-c", _CHILD, "run", str(data), "--out", str(out),
           "--force", "--no-report", "--quiet", *CONFIGS[config]]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONHASHSEED": "0"})
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[3:])} failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    reports = _reports_in(proc.stdout)
    peak = [int(l.split()[1]) for l in proc.stdout.splitlines() if l.startswith("PEAK_KIB")]
    peak_mib = peak[-1] / 1024 if peak else float("nan")
    db = out / "results.duckdb"
    return {"config": config, "duration_s": duration_s, "aircraft": aircraft, "wall_s": round(wall, 2),
            "reports": reports,
            "reports_per_s": round(reports / wall, 1) if reports else None,
            "peak_rss_mib": round(peak_mib, 1), "db_mb": round(db.stat().st_size / 1e6, 1) if db.exists() else None,
            "window_s": _recorded(db, "window_s"), "peak_by_stage_mib": _recorded(db, "memory_mib") or {},
            "timings_s": {k: round(v, 1) for k, v in (_recorded(db, "timings") or {}).items()}}


def _recorded(db: Path, key: str):
    """A value of the run record: the window length (``--window auto`` sizes it from the
    recording), the peak memory by the end of each stage (where the memory goes), the timings."""
    import duckdb
    if not db.exists():
        return None
    con = duckdb.connect(str(db), read_only=True)
    try:
        got = con.execute("SELECT value FROM run WHERE key = ?", [key]).fetchall()
    finally:
        con.close()
    return json.loads(got[0][0]) if got else None


def _reports_in(stdout: str) -> int:
    for line in stdout.splitlines():
        if "reports in" in line:
            return int(line.split(":", 1)[1].split("reports in")[0].strip().replace(",", ""))
    return 0


def _kept_rows(configs: list[str]) -> list[dict]:
    """The recorded rows of the configurations not run this time, each with the date it was
    measured (``measured_utc``), so that a partial rerun does not erase them."""
    from _util import RESULTS
    path = RESULTS / "bench_memory.json"
    if not path.exists():
        return []
    old = json.loads(path.read_text())
    when = old.get("machine", {}).get("date_utc")
    return [{**r, "measured_utc": r.get("measured_utc", when)} for r in old.get("runs", [])
            if r.get("config") not in configs]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", default="3600,14400,43200")
    ap.add_argument("--configs", default="production,full")
    ap.add_argument("--aircraft-per-hour", type=float, default=200.0)
    ap.add_argument("--full-max-s", type=float, default=14400.0,
                    help="skip longer full-configuration runs (they hold every table of 14 pictures in memory)")
    args = ap.parse_args()
    durations = [float(d) for d in args.durations.split(",")]
    configs = args.configs.split(",")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for config in sorted(configs, key=lambda c: list(CONFIGS).index(c)):
            for d in sorted(durations):
                if config == "full" and d > args.full_max_s:
                    rows.append({"config": config, "duration_s": d, "skipped": f"longer than --full-max-s {args.full_max_s:g}"})
                    continue
                row = _one(d, config, Path(tmp), args.aircraft_per_hour)
                rows.append(row)
                print(json.dumps(row), flush=True)
    verdict = {}
    for config in configs:
        peaks = [r["peak_rss_mib"] for r in rows
                 if r["config"] == config and r.get("peak_rss_mib") == r.get("peak_rss_mib") and "peak_rss_mib" in r]
        if peaks:
            verdict[config] = {"peak_max_mib": max(peaks), "spread": round(max(peaks) / min(peaks) - 1, 3),
                               "within_15_percent": max(peaks) <= 1.15 * min(peaks),
                               "below_target": max(peaks) < TARGET_MIB[config], "target_mib": TARGET_MIB[config]}
    sims = sorted(SIMULATIONS.values(), key=lambda r: r["duration_s"])
    if sims:
        peaks = [r["peak_rss_mib"] for r in sims if r["peak_rss_mib"]]
        verdict["simulation"] = {"peak_max_mib": max(peaks), "spread": round(max(peaks) / min(peaks) - 1, 3)}
    rows += _kept_rows(configs)
    path = record("bench_memory", {"runs": rows, "simulations": sims, "verdict": verdict,
                                   "note": "windowed engine (default window: auto); the finalize stage reads the whole "
                                           "run's streamed tables"})
    print(json.dumps(verdict, indent=2))
    print(f"recorded in {path}")


if __name__ == "__main__":
    main()
