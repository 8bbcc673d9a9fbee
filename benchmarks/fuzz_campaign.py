"""The long fuzz campaign: thousands of hypothesis-drawn cases over every
entry point, each run in a memory-limited worker process with a per-case timeout.

    python benchmarks/fuzz_campaign.py --cases 2000 --seed 15

Prints and writes ``benchmarks/results/fuzz_campaign.json``: per entry point the number of cases,
clear errors, rejects, successes, tracebacks, silent acceptances and hangs (and contract
failures: any case that is not a clear error or a clean, fully accounted success), plus the
first reproducer line of each distinct failure (``python tests/fuzzing.py replay '<case>'``).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import fuzzing  # noqa: E402  (the shared harness lives beside the tests)

SHARES = {"validate": 0.25, "run": 0.25, "simulate": 0.08, "sql": 0.08, "api": 0.34}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=2000, help="total cases over all entry points")
    ap.add_argument("--seed", type=int, default=15)
    ap.add_argument("--entries", default=",".join(fuzzing.ENTRIES), help="comma-separated entry points")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "fuzz_campaign.json")
    ap.add_argument("--bases", type=Path, default=None, help="cache directory of the base datasets")
    args = ap.parse_args()

    entries = [e for e in args.entries.split(",") if e]
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    share = sum(SHARES[e] for e in entries)
    counts = {e: max(1, round(args.cases * SHARES[e] / share)) for e in entries}
    root = Path(tempfile.mkdtemp(prefix="tertiary-fuzz-"))
    bases = fuzzing.build_bases(args.bases or root / "bases")
    scratch = root / "scratch"
    scratch.mkdir()
    worker = fuzzing.Worker(bases, scratch)
    outcomes: list[fuzzing.Outcome] = []
    seen: set[str] = set()
    t0 = time.perf_counter()
    try:
        for entry in entries:
            cases = fuzzing.draw_cases(entry, counts[entry], args.seed)
            if entry == "sql":  # the default statement timeout must stop a cross join too (one slow case)
                cases.append({"entry": "sql", "args": [], "expect": "error", "subprocess": True, "timeout": 150.0,
                              "query": fuzzing.CROSS_JOIN})
            t = time.perf_counter()
            for i, case in enumerate(cases):
                o = worker.run(case)
                outcomes.append(o)
                if not o.ok and o.signature not in seen:
                    seen.add(o.signature)
                    print(f"[{entry} {i}] {o.cls}: {o.exc or '; '.join(o.problems)[:200]}  {o.where}", flush=True)
            print(f"{entry}: {len(cases)} cases in {time.perf_counter() - t:.0f} s", flush=True)
    finally:
        worker.stop()
        shutil.rmtree(scratch, ignore_errors=True)
        if args.bases is None:
            shutil.rmtree(root, ignore_errors=True)
    table, failures = fuzzing.summarise(outcomes)
    table = {e: r for e, r in table.items() if r["cases"]}
    print(fuzzing.format_table(table))
    print(f"{len(failures)} distinct failures; {time.perf_counter() - t0:.0f} s")
    for sig, f in failures.items():
        print(f"- {sig} (x{f['count']})\n    {f['reproducer'][:400]}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "commit": head, "started_utc": started, "cases_requested": args.cases, "cases_run": len(outcomes), "seed": args.seed, "seconds": round(time.perf_counter() - t0, 1),
        "machine": f"{platform.machine()} {platform.python_version()}",
        "classes": "clear_error: exit 2/3/4, one stderr line, no traceback (Python: a TertiaryError); rejects/success: "
                   "exit 0 with row accounting intact in the run database; traceback: uncaught, the CLI's exit-1 "
                   "internal error, or its generic out-of-memory message; silent: an impossible value accepted; "
                   "hang: past the per-case timeout; contract_failures: any case breaking the contract",
        "table": table,
        "failures": sorted(failures.values(), key=lambda f: (f["entry"], -f["count"])),
    }, indent=1, default=str) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
