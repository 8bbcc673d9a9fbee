"""Benchmark helpers: run a job in a fresh interpreter and read its wall time and peak RSS."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def run_isolated(code: str) -> dict:
    """Execute ``code`` (which must print one JSON object as its last line) in a new Python
    process; add the process's peak resident memory in MiB (ru_maxrss of the child)."""
    wrapper = code + "\nimport resource, json as _j\nprint(_j.dumps({'peak_rss_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))\n"
    out = subprocess.run([sys.executable, "-c", wrapper], check=True, capture_output=True, text=True,
                         env={**os.environ, "PYTHONHASHSEED": "0"})
    lines = [json.loads(l) for l in out.stdout.strip().splitlines() if l.startswith("{")]
    merged: dict = {}
    for d in lines:
        merged.update(d)
    return merged


def machine() -> dict:
    return {"python": platform.python_version(), "cpu_count": os.cpu_count(), "machine": platform.machine(),
            "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def record(name: str, payload: dict) -> Path:
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps({"machine": machine(), **payload}, indent=2) + "\n")
    return path


def each_dataset(bench: str, only: str, known: "tuple[str, ...]", work: "Path | None", run, **extra) -> dict:
    """``run(name, work)`` for each dataset of ``only`` (comma-separated, each one of ``known``)
    in ``work`` (None: a temporary directory), ``bench``'s results recorded after each one with
    ``extra`` beside them; the recorded entries of the datasets not run are kept. Returns the
    datasets' entries."""
    import tempfile
    names = [n for n in only.split(",") if n]
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise SystemExit(f"unknown datasets {unknown}; choose from {list(known)}")
    old = RESULTS / f"{bench}.json"
    results = json.loads(old.read_text()).get("datasets", {}) if old.exists() else {}
    with tempfile.TemporaryDirectory() as tmp:
        where = work or Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for name in names:
            results[name] = run(name, where)
            record(bench, {**extra, "datasets": results})
    return results
