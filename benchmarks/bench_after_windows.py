"""How much of a run waits for the end: the time after the last window, beside the windows'.

For every job (``--job NAME=DATASET[:ARG,ARG...]``, extra ``tertiary run`` arguments after the
colon) and every source tree (``--tree LABEL=DIR``, put first on ``PYTHONPATH``; default: this
tree), runs ``tertiary run DATASET --no-report ARGS`` in a fresh process, reads the time of the
last "window K/N done" progress line and the run record's stage timings, and records: wall time,
the windows' time, the time after the last window and its share of the run, peak memory, and the
timings of the stages after the windows. Trees alternate job by job; ``--repeat`` runs each pair
again and keeps every run; ``--warmup`` runs each tree first, uncounted (a fresh source tree
compiles its kernels on its first run); ``--merge`` keeps the recorded jobs not run again.

    python benchmarks/bench_after_windows.py --job default=DATA \
        --job national=NATIONAL:--methods,information,--filters,imm_sym --tree before=OLD --tree after=.

Results: ``benchmarks/results/bench_after_windows.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import duckdb

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, record  # noqa: E402
from bench_memory import _CHILD  # noqa: E402

#: a batch log's line for a finished window: "[   31.0 s] pipeline: window 13/13 done, ..."
WINDOW_LINE = re.compile(r"\[\s*([\d.]+) s\] pipeline: window (\d+)/(\d+) done")
#: the stages that run after the windows (the engine's own names in the run record's timings)
AFTER = ("evaluation_s", "score_alerts_s", "score_curves_s", "evaluate_s", "indicators_s", "store_s")


def _run(tree: Path, data: str, args: list[str], out: Path) -> dict:
    """One run of ``tertiary run`` with ``tree`` first on the path: its wall, windows and peak."""
    env = {**os.environ, "PYTHONPATH": f"{tree}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, "run", data, "--out", str(out), "--force", "--no-report",
                           *args], capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"tertiary run failed ({proc.returncode}): {proc.stderr.strip()[-400:]}")
    windows = [m for m in WINDOW_LINE.finditer(proc.stdout + proc.stderr)]
    peak = [int(line.split()[1]) for line in proc.stdout.splitlines() if line.startswith("PEAK_KIB")]
    with duckdb.connect(str(out / "results.duckdb"), read_only=True) as con:
        timings = json.loads(dict(con.execute("select key, value from run").fetchall())["timings"])
    pipeline_s = timings["wall_s"]
    windows_s = float(windows[-1].group(1)) if windows else float("nan")
    after = pipeline_s - windows_s
    return {"wall_s": round(wall, 1), "pipeline_s": round(pipeline_s, 1), "windows": len(windows),
            "windows_s": round(windows_s, 1), "after_windows_s": round(after, 1),
            "after_windows_share": round(after / pipeline_s, 3), "peak_rss_mib": round(peak[-1] / 1024, 1),
            "timings_s": {k: round(v, 2) for k, v in timings.items()},
            "after_stages_s": {k: round(timings[k], 2) for k in AFTER if k in timings}}


def _median(values: list[float]) -> float:
    v = sorted(values)
    return v[len(v) // 2] if len(v) % 2 else 0.5 * (v[len(v) // 2 - 1] + v[len(v) // 2])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--job", action="append", required=True, help="NAME=DATASET[:ARG,ARG...]")
    ap.add_argument("--tree", action="append", default=None, help="LABEL=DIR (default: this tree)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=0,
                    help="runs of each tree before the counted ones (a fresh tree compiles its kernels on its first)")
    ap.add_argument("--merge", action="store_true", help="keep the recorded jobs these runs do not replace")
    ap.add_argument("--what", default="", help="what the trees are (recorded beside the results)")
    args = ap.parse_args()
    trees = [(t.split("=", 1)[0], Path(t.split("=", 1)[1]).resolve()) for t in
             (args.tree or [f"this={Path(__file__).resolve().parents[1]}"])]
    rows: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.job:
            name, rest = spec.split("=", 1)
            data, _, extra = rest.partition(":")
            run_args = [a for a in extra.split(",") if a]
            job = rows.setdefault(name, {"dataset": data, "args": run_args, "warmup": args.warmup,
                                         "what": args.what, "trees": {label: _commit(t) for label, t in trees},
                                         "runs": {label: [] for label, _ in trees}})
            for _ in range(args.warmup):
                for label, tree in trees:
                    _run(tree, data, run_args, Path(tmp) / f"{name}-{label}")
            for _ in range(args.repeat):
                for label, tree in trees:
                    got = _run(tree, data, run_args, Path(tmp) / f"{name}-{label}")
                    job["runs"][label].append(got)
                    print(json.dumps({"job": name, "tree": label, **{k: v for k, v in got.items()
                                                                      if not k.endswith("timings_s")}}), flush=True)
            job["median"] = {label: {k: round(_median([r[k] for r in runs]), 3) for k in
                                     ("wall_s", "windows_s", "after_windows_s", "after_windows_share", "peak_rss_mib")}
                             for label, runs in job["runs"].items()}
    if args.merge and (RESULTS / "bench_after_windows.json").exists():
        old = json.loads((RESULTS / "bench_after_windows.json").read_text())
        rows = {**old.get("jobs", {}), **rows}
    print("recorded in", record("bench_after_windows", {"what": WHAT, "jobs": rows}))


WHAT = ("each job's runs of each source tree (jobs.*.trees: label -> commit, '+' when the tree had "
        "uncommitted changes; jobs.*.what: what the trees differ by); medians of the repeats")


def _commit(tree: Path) -> str:
    """The tree's commit (short), '+' when it has uncommitted changes; its path when not a git checkout."""
    def git(*a: str) -> str:
        return subprocess.run(["git", "-C", str(tree), *a], capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD")
    return head + ("+" if git("status", "--porcelain", "--untracked-files=no") else "") if head else str(tree)


if __name__ == "__main__":
    main()
