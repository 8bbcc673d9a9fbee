"""The national scenario: an hour of the day simulated and processed on one machine.

Simulates ``national`` (16 radars, the daily traffic curve) for ``--duration`` seconds from
``--start-s`` after 00:00 UTC (default: the 08:00 peak hour) with ``tertiary simulate``
(partitioned Parquet, window by window), then runs ``tertiary run`` on it in the production
configuration (one fusion method, one tracker, conflicts, evaluation, store; default
``--window auto``), each in a fresh process, and records for both the wall time, reports/s and
the process's peak resident memory, and for the run its stage timings, its peak by the end of
each stage and its summary lines (system targets per aircraft, alerts, losses of separation).

With ``--causes`` (every table stored) it also records the cause of each picture-induced alert
and why an aircraft has more than one confirmed system target (``bench_trust.target_splits``),
beside an earlier tree's (``--causes-before``, ``--splits-before``).

    python benchmarks/bench_national.py [--start-s 28800] [--duration 3600] [--work DIR] [--record NAME]

Results: ``benchmarks/results/bench_national.json`` (``--record``: another name, e.g. a longer slice).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record  # noqa: E402
from bench_memory import _CHILD, CONFIGS, _recorded, _reports_in  # noqa: E402


def _child(args: list[str]) -> tuple[float, float, str]:
    """(wall s, peak MiB, stdout) of one CLI command in a fresh interpreter."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"tertiary {' '.join(args)} failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    peak = [int(line.split()[1]) for line in proc.stdout.splitlines() if line.startswith("PEAK_KIB")]
    return wall, (peak[-1] / 1024 if peak else float("nan")), proc.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--start-s", type=float, default=8 * 3600.0, help="start of the run after 00:00 UTC")
    ap.add_argument("--duration", type=float, default=3600.0)
    ap.add_argument("--work", type=Path, default=None, help="keep the dataset and run here (default: a temp dir)")
    ap.add_argument("--causes", action="store_true",
                    help="store every table (--tables full) and record the cause of each picture-induced alert")
    ap.add_argument("--causes-before", type=Path, default=None,
                    help="a JSON of the causes on an earlier tree (alert_causes' output) to record beside them")
    ap.add_argument("--splits-before", type=Path, default=None,
                    help="an earlier tree's run database of the same dataset (--tables full): its target splits "
                         "recorded beside this run's")
    ap.add_argument("--record", default="bench_national", help="the results file's name (benchmarks/results/NAME.json)")
    args = ap.parse_args()
    from tertiary.simulate import load_scenario
    from tertiary.simulate.config import scenario_toml
    base = load_scenario("national")
    cfg = dataclasses.replace(base, duration_s=args.duration,
                              national=dataclasses.replace(base.national, start_s=args.start_s))
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        (work / "national.toml").write_text(scenario_toml(cfg))
        data, out = work / "national", work / "run"
        wall_s, peak_s, _ = _child(["simulate", str(work / "national.toml"), "--out", str(data), "--force",
                                    "--quiet"])
        parts = json.loads((data / "parts.json").read_text())
        print(json.dumps({"simulate_s": round(wall_s, 1), "reports": parts["reports"]}), flush=True)
        tables = ["--tables", "full"] if args.causes else []
        wall_r, peak_r, stdout = _child(["run", str(data), "--out", str(out), "--force", "--no-report", *tables,
                                         *CONFIGS["production"]])
        db = out / "results.duckdb"
        reports = _reports_in(stdout)
        row = {
            "scenario": {"name": "national", "start_s": args.start_s, "duration_s": args.duration,
                         "radars": len(cfg.radars), "reports": parts["reports"], "truth_rows": parts["truth_rows"]},
            "simulation": {"wall_s": round(wall_s, 1), "reports_per_s": round(parts["reports"] / wall_s, 1),
                           "peak_rss_mib": round(peak_s, 1)},
            "run": {"config": "production", "args": [*CONFIGS["production"], *tables], "wall_s": round(wall_r, 1),
                    "reports": reports, "reports_per_s": round(reports / wall_r, 1) if reports else None,
                    "peak_rss_mib": round(peak_r, 1), "window_s": _recorded(db, "window_s"),
                    "db_mb": round(db.stat().st_size / 1e6, 1),
                    "timings_s": {k: round(v, 1) for k, v in (_recorded(db, "timings") or {}).items()},
                    "peak_by_stage_mib": _recorded(db, "memory_mib") or {},
                    "summary": [line.strip() for line in stdout.splitlines()
                                if line.strip().startswith(("run ", "system targets", "fusion", "tracker", "safety "))]},
            # a day's reports at this hour's rate, as a yardstick (the curve is lower at night)
            "day_at_this_rate_s": round(wall_r * 86400.0 / args.duration, 0),
        }
        if args.causes:
            from bench_trust import alert_causes, target_splits
            row["picture_induced_causes"] = alert_causes(db, data)
            if args.causes_before is not None:
                row["picture_induced_causes_before"] = json.loads(args.causes_before.read_text())
            row["target_splits"] = target_splits(db)
            if args.splits_before is not None:
                row["target_splits_before"] = target_splits(args.splits_before)
        print(json.dumps(row, indent=2), flush=True)
        print("recorded in", record(args.record, row))


if __name__ == "__main__":
    main()
