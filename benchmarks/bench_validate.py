"""Throughput of the data contract's validation (:func:`tertiary.contract.validate`, lenient mode).

Five tables, each with a few per cent of bad rows injected (NaN, infinite and out-of-range
values, an unknown radar, covariances that are not one, times outside the years, nulls in the
key, key duplicates and repeated report ids) so that the rejects path is timed too:

* ``terminal_area``: the reports of ``tertiary simulate terminal-area`` (71 k), against its radars;
* ``terminal_area_x15``: those reports 15 times over (1.07 M; each copy with its own report ids
  and local track ids), against the same radars;
* ``truth_x10``: the scenario's truth 10 times over (1.15 M rows, each copy its own truth ids)
  through :func:`tertiary.pipeline.ingestion.validate_truth`, against the valid reports' span;
* ``national_hour``, ``national_truth``: the reports (270 k, 16 radars, read from the parts the
  simulator writes) and the truth (590 k rows) of ``tertiary simulate national --duration 3600``.

Each result has the wall time (the best of ``--repeat`` calls), the process's CPU time (the
least of those calls, all threads), rows per second of wall time, the clean and rejected counts
and a digest of the outputs (the clean frame's row hashes, the rejects' row indices and
reasons), so that two labels can be compared for identical outputs as well as for speed. The code measured is the ``tertiary``
imported (``PYTHONPATH`` can point at another checkout's to measure it).

    python benchmarks/bench_validate.py --label before [--work DIR] [--only TABLE,...]

Results: ``benchmarks/results/bench_validate.json``, one entry per ``--label`` (other labels kept).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, machine  # noqa: E402

from tertiary import contract  # noqa: E402
from tertiary.pipeline.config import PipelineConfig  # noqa: E402
from tertiary.pipeline.ingestion import truth_window, validate_truth  # noqa: E402

NAME = "bench_validate"
#: fraction of the rows given each kind of bad value
BAD = 0.004


def _simulate(work: Path, scenario: str = "terminal-area", *args: str) -> Path:
    out = work / scenario
    if not (out / "scenario.toml").exists():
        subprocess.run([sys.executable, "-m", "tertiary", "simulate", scenario, "-o", str(out), "--quiet",
                        "--force", *args], check=True)
    return out


def _read(path: Path) -> pl.DataFrame:
    """A table written whole (``NAME.parquet``) or in parts (``NAME/part-*.parquet``)."""
    return pl.read_parquet(path.with_suffix(".parquet") if path.with_suffix(".parquet").exists()
                           else sorted(path.glob("*.parquet")))


def _pick(rng: np.random.Generator, n: int, taken: np.ndarray) -> np.ndarray:
    """``BAD`` of the ``n`` rows, none already given a bad value."""
    free = np.flatnonzero(~taken)
    rows = np.sort(rng.choice(free, size=max(1, int(BAD * n)), replace=False))
    taken[rows] = True
    return rows


def _set(frame: pl.DataFrame, column: str, rows: np.ndarray, value: object) -> pl.DataFrame:
    mask = np.zeros(frame.height, bool)
    mask[rows] = True
    value = value if isinstance(value, pl.Expr) else pl.lit(value, dtype=frame.schema[column])
    return frame.with_columns(pl.when(pl.Series(mask)).then(value).otherwise(pl.col(column)).alias(column))


def spoil_reports(reports: pl.DataFrame, seed: int = 7) -> pl.DataFrame:
    """A few per cent of the rows given each kind of bad value, then some rows repeated (key
    duplicates under a new report id, and repeated report ids)."""
    rng = np.random.default_rng(seed)
    n = reports.height
    taken = np.zeros(n, bool)
    out = reports
    out = _set(out, "range_m", _pick(rng, n, taken), float("nan"))
    out = _set(out, "azimuth_deg", _pick(rng, n, taken), 400.0)
    out = _set(out, "altitude_m", _pick(rng, n, taken), 1e6)
    out = _set(out, "x_m", _pick(rng, n, taken), float("inf"))
    out = _set(out, "est_range_var_m2", _pick(rng, n, taken), -1.0)
    out = _set(out, "radar_id", _pick(rng, n, taken), 99)
    out = _set(out, "local_track_id", _pick(rng, n, taken), None)
    out = _set(out, "time", _pick(rng, n, taken), pl.datetime(1970, 1, 1, time_zone="UTC"))
    cov = out["est_cov"].to_numpy().copy()
    cov[_pick(rng, n, taken), 0] *= -1.0                      # a negative variance: not PSD
    asym = _pick(rng, n, taken)
    cov[asym, 1] += 1e3 * np.abs(cov[asym, 0]) + 1.0          # P[0,1] != P[1,0]
    cov[_pick(rng, n, taken), 7] = np.inf
    out = out.with_columns(pl.Series("est_cov", cov, dtype=contract.COV))
    top = int(out["report_id"].max()) + 1
    dup = out[np.sort(rng.choice(np.flatnonzero(~taken), size=int(BAD * n), replace=False))]
    dup = dup.with_columns(pl.int_range(top, top + dup.height, dtype=pl.UInt64).alias("report_id"))
    again = out[np.sort(rng.choice(np.flatnonzero(~taken), size=int(BAD * n), replace=False))]
    again = again.with_columns(pl.col("local_track_id") + 1_000_000)       # same report_id, another key
    return pl.concat([out, dup, again])


def spoil_truth(truth: pl.DataFrame, seed: int = 11) -> pl.DataFrame:
    rng = np.random.default_rng(seed)
    n = truth.height
    taken = np.zeros(n, bool)
    out = truth
    out = _set(out, "x_m", _pick(rng, n, taken), float("nan"))
    out = _set(out, "vx_mps", _pick(rng, n, taken), 1e5)
    out = _set(out, "z_m", _pick(rng, n, taken), float("-inf"))
    out = _set(out, "alt_m", _pick(rng, n, taken), -9000.0)
    out = _set(out, "time", _pick(rng, n, taken), pl.datetime(2000, 1, 1, time_zone="UTC"))
    out = _set(out, "time", _pick(rng, n, taken), pl.datetime(1970, 1, 1, time_zone="UTC"))
    dup = out[np.sort(rng.choice(np.flatnonzero(~taken), size=int(BAD * n), replace=False))]
    return pl.concat([out, dup.with_columns(pl.col("x_m") + 1.0)])


def replicate(frame: pl.DataFrame, times: int, ids: dict[str, int]) -> pl.DataFrame:
    """``frame`` ``times`` over, copy k with ``ids`` columns shifted by k × their step."""
    return pl.concat([frame.with_columns((pl.col(c) + k * step).cast(frame.schema[c]) for c, step in ids.items())
                      for k in range(times)])


def _digest(clean: pl.DataFrame, rejects: pl.DataFrame) -> dict:
    h = hashlib.sha256()
    body = clean.with_columns(pl.col(c).cast(pl.List(pl.Float64)) for c, t in clean.schema.items()
                              if isinstance(t, pl.Array))
    h.update(body.hash_rows(seed=0).to_numpy().tobytes())
    h.update(json.dumps(clean.columns).encode())
    r = hashlib.sha256()
    r.update(rejects["row_index"].cast(pl.UInt64).to_numpy().tobytes())
    r.update("\n".join(rejects["reason"].to_list()).encode())
    return {"clean_rows": clean.height, "rejected_rows": rejects.height,
            "clean_sha256": h.hexdigest()[:16], "rejects_sha256": r.hexdigest()[:16]}


def _time_reports(reports: pl.DataFrame, radars: pl.DataFrame, repeat: int) -> dict:
    best, cpu, out = float("inf"), float("inf"), None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = contract.validate(reports, "reports", strict=False, radars=radars)
        best, cpu = min(best, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    clean, rejects = out
    return {"rows": reports.height, "seconds": round(best, 3), "cpu_seconds": round(cpu, 3),
            "rows_per_s": round(reports.height / best), **_digest(clean, rejects)}


def _time_truth(truth: pl.DataFrame, window, repeat: int) -> dict:
    cfg = PipelineConfig()
    dt, cpu, out = float("inf"), float("inf"), None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = validate_truth(SimpleNamespace(truth=truth), cfg, [], window)
        dt, cpu = min(dt, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    clean, rejects = out
    return {"rows": truth.height, "seconds": round(dt, 3), "cpu_seconds": round(cpu, 3),
            "rows_per_s": round(truth.height / dt),
            **_digest(clean, rejects)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True, help="the entry's name (e.g. before, after)")
    ap.add_argument("--work", default="/tmp/bench_validate", help="where the simulated dataset is kept")
    ap.add_argument("--repeat", type=int, default=3, help="calls per table (the best is kept)")
    ap.add_argument("--code", default="", help="what code was measured (recorded with the entry)")
    ap.add_argument("--only", default="terminal_area,terminal_area_x15,truth_x10,national_hour,national_truth")
    args = ap.parse_args()
    only = set(args.only.split(","))
    src = _simulate(Path(args.work))
    radars = pl.read_parquet(src / "radars.parquet")
    reports = pl.read_parquet(src / "reports.parquet")
    truth = pl.read_parquet(src / "truth.parquet")
    clean_reports = contract.validate(reports, "reports", strict=False, radars=radars)[0]
    window = truth_window(clean_reports, contract.Limits())
    results: dict[str, dict] = {}
    if "terminal_area" in only:
        results["terminal_area"] = _time_reports(spoil_reports(reports), radars, args.repeat)
        print("terminal_area", results["terminal_area"], flush=True)
    if "terminal_area_x15" in only:
        big = spoil_reports(replicate(reports, 15, {"report_id": reports.height, "local_track_id": 100_000}))
        results["terminal_area_x15"] = _time_reports(big, radars, args.repeat)
        print("terminal_area_x15", results["terminal_area_x15"], flush=True)
        del big
    if "truth_x10" in only:
        long = spoil_truth(replicate(truth, 10, {"truth_id": int(truth["truth_id"].max()) + 1}))
        results["truth_x10"] = _time_truth(long, window, args.repeat)
        print("truth_x10", results["truth_x10"], flush=True)
    if only & {"national_hour", "national_truth"}:
        nat = _simulate(Path(args.work), "national", "--duration", "3600")
        n_radars, n_reports = pl.read_parquet(nat / "radars.parquet"), _read(nat / "reports")
        if "national_hour" in only:
            results["national_hour"] = _time_reports(spoil_reports(n_reports), n_radars, args.repeat)
            print("national_hour", results["national_hour"], flush=True)
        if "national_truth" in only:
            n_clean = contract.validate(n_reports, "reports", strict=False, radars=n_radars)[0]
            results["national_truth"] = _time_truth(spoil_truth(_read(nat / "truth")),
                                                    truth_window(n_clean, contract.Limits()), args.repeat)
            print("national_truth", results["national_truth"], flush=True)
    path = RESULTS / f"{NAME}.json"
    doc = json.loads(path.read_text()) if path.exists() else {}
    doc["note"] = ("wall times on a 2-core machine shared with other engineers' jobs (a long benchmark "
                   "ran beside this one): rates are indicative, the ratio between labels is what matters; "
                   "the digests must agree between labels (identical clean frames and rejects)")
    doc["data"] = {
        "terminal_area": "reports of `tertiary simulate terminal-area` with bad rows injected (spoil_reports)",
        "terminal_area_x15": "the same reports 15 times over (own report_id, local_track_id) with bad rows injected",
        "truth_x10": "the terminal-area truth 10 times over (own truth_id) with bad rows injected, through "
                     "validate_truth",
        "national_hour": "reports of `tertiary simulate national --duration 3600` (16 radars, read from its "
                         "parts) with bad rows injected",
        "national_truth": "that dataset's truth with bad rows injected, through validate_truth",
    }
    entry = doc.setdefault("runs", {}).setdefault(args.label, {})
    entry["machine"] = {**machine(), "shared": True, "polars": pl.__version__, "numpy": np.__version__}
    if args.code:
        entry["code"] = args.code
    entry.setdefault("tables", {}).update(results)
    RESULTS.mkdir(exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
