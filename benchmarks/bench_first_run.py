"""A fresh install's first run against the next ones (compilation must not make
the first ``tertiary run`` slower by more than a few seconds).

Simulates terminal-area once (the default scenario's 200 aircraft over 1 h unless told
otherwise), then runs ``tertiary run DATASET`` in the production configuration
(``--methods information --filters imm_sym``) in fresh processes, in pairs: a *cold* run with an
empty numba cache directory (``NUMBA_CACHE_DIR``: what a fresh install has), then a *warm* run
on the cache the cold one left. Records each run's whole-process wall time, the cold − warm
difference per pair (median over pairs), and the run record's stage times of the stages that
call compiled kernels (fuse, centralized, track).

    python benchmarks/bench_first_run.py [--pairs 3] [--aircraft 200] [--duration 3600]

Results: ``benchmarks/results/bench_first_run.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record  # noqa: E402

CONFIG = ["--methods", "information", "--filters", "imm_sym"]
KERNEL_STAGES = ("fuse_s", "centralized_s", "track_s")
#: "a few seconds", read as at most this
TARGET_EXTRA_S = 5.0


def _timings(db: Path) -> dict:
    import duckdb
    con = duckdb.connect(str(db), read_only=True)
    try:
        got = con.execute("SELECT value FROM run WHERE key = 'timings'").fetchall()
    finally:
        con.close()
    return json.loads(got[0][0]) if got else {}


def _run(data: Path, out: Path, cache: Path) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONHASHSEED": "0"}
    cmd = [sys.executable, "-m", "tertiary.cli.main", "run", str(data), "--out", str(out), "--force", "--quiet",
           "--no-report", *CONFIG]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"run failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    t = _timings(out / "results.duckdb")
    return {"wall_s": round(wall, 2), **{k: round(t.get(k, 0.0), 2) for k in KERNEL_STAGES}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--aircraft", type=int, default=200)
    ap.add_argument("--duration", type=float, default=3600.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        data = work / "ta"
        subprocess.run([sys.executable, "-m", "tertiary.cli.main", "simulate", "terminal-area", "--out", str(data),
                        "--aircraft", str(args.aircraft), "--duration", str(args.duration), "--quiet"],
                       check=True, capture_output=True)
        pairs = []
        for k in range(args.pairs):
            cache = work / f"numba-{k}"           # empty: a fresh install's cache
            cold = _run(data, work / "run", cache)
            warm = _run(data, work / "run", cache)
            pairs.append({"cold": cold, "warm": warm, "extra_s": round(cold["wall_s"] - warm["wall_s"], 2)})
            print(json.dumps(pairs[-1]), flush=True)
    extra = statistics.median(p["extra_s"] for p in pairs)
    path = record("bench_first_run", {
        "scenario": {"kind": "terminal-area", "aircraft": args.aircraft, "duration_s": args.duration},
        "config": CONFIG, "pairs": pairs,
        "cold_wall_s_median": statistics.median(p["cold"]["wall_s"] for p in pairs),
        "warm_wall_s_median": statistics.median(p["warm"]["wall_s"] for p in pairs),
        "extra_s_median": extra, "target_extra_s": TARGET_EXTRA_S, "target_met": extra <= TARGET_EXTRA_S})
    print(f"first run +{extra:.1f} s over a warm one (median of {len(pairs)} pairs); wrote {path}")


if __name__ == "__main__":
    main()
