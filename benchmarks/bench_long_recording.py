"""A long recording of real traffic: the shipped Paris ADS-B trajectories repeated over a day.

The shipped recording holds 3 h of real ADS-B trajectories (213 aircraft). Copy k of it is
shifted by k × 3 h and its aircraft get addresses of their own (the 24-bit address plus
k × 0x100000, modulo 2²⁴; checked distinct), so ``--hours`` (default 17) of real traffic at the
recording's own density fly through the four radars of ``adsb-paris``. The recording is
simulated once (``tertiary simulate``), then ``tertiary run DATA --no-report`` (the default job,
every picture) runs on it in a fresh process for every source tree (``--tree LABEL=DIR``, put
first on ``PYTHONPATH``; default: this tree): wall time, the windows' time and the time after
them, peak memory, the stage timings, and the run directory's size against the input Parquet.

    python benchmarks/bench_long_recording.py [--hours 17] [--work DIR] [--tree before=OLD --tree after=.] [--repeat 3]

Results: ``benchmarks/results/bench_long_recording.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import RESULTS, record  # noqa: E402
from bench_after_windows import _run  # noqa: E402
from bench_national import _child  # noqa: E402

SHIFT_H = 3.0
ADDRESS_STEP = 0x100000


def repeated_truth(hours: float, path: Path) -> dict:
    """The shipped trajectories repeated every 3 h up to ``hours``, written to ``path``."""
    from tertiary.simulate.config import resolve_data_path
    src = pl.read_parquet(resolve_data_path("adsb_paris_2021-10-07.parquet"))
    t0 = src["timestamp"].min()
    copies = []
    addresses = src["icao24"].unique().to_list()
    for k in range(int(-(-hours // SHIFT_H))):
        # the new address of each aircraft (a few hundred), not of each point
        new = {a: f"{(int(a, 16) + k * ADDRESS_STEP) % (1 << 24):06x}" for a in addresses}
        copies.append(src.with_columns(pl.col("timestamp") + pl.duration(hours=k * SHIFT_H),
                                       pl.col("icao24").replace_strict(new, return_dtype=pl.String)))
    out = pl.concat(copies)
    n_src, n_all = src["icao24"].n_unique(), out["icao24"].n_unique()
    if n_all != n_src * len(copies):
        raise RuntimeError(f"the copies' addresses collide: {n_all} distinct, {n_src} × {len(copies)} wanted")
    out = out.filter(pl.col("timestamp") < t0 + pl.duration(seconds=hours * 3600.0))
    n_out = out["icao24"].n_unique()
    out.write_parquet(path)
    return {"rows": out.height, "aircraft": n_out, "copies": len(copies)}


def _size_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=17.0)
    ap.add_argument("--work", type=Path, default=None,
                    help="keep the dataset and runs here (default: a temp dir); a dataset already there is reused")
    ap.add_argument("--tree", action="append", default=None, help="LABEL=DIR (default: this tree)")
    ap.add_argument("--merge", action="store_true", help="keep the recorded runs of the labels not run again")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each tree (the median's figures recorded beside them)")
    args = ap.parse_args()
    from tertiary.simulate import load_scenario
    from tertiary.simulate.config import scenario_toml
    here = Path(__file__).resolve().parents[1]
    trees = dict(t.split("=", 1) for t in args.tree) if args.tree else {"this tree": str(here)}
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        data = work / "long"
        row: dict = {"hours": args.hours}
        if not (data / "scenario.toml").exists():
            row["truth"] = repeated_truth(args.hours, work / "adsb_repeated.parquet")
            base = load_scenario("adsb-paris")
            cfg = dataclasses.replace(base, name="adsb-paris-long", duration_s=args.hours * 3600.0,
                                      adsb=dataclasses.replace(base.adsb,
                                                               truth_file=str(work / "adsb_repeated.parquet")))
            (work / "long.toml").write_text(scenario_toml(cfg))
            sim_wall, sim_peak, _ = _child(["simulate", str(work / "long.toml"), "--out", str(data), "--force",
                                            "--quiet"])
            row["simulation"] = {"wall_s": round(sim_wall, 1), "peak_rss_mib": round(sim_peak, 1)}
        input_mb = _size_mb(data)
        reports = pl.scan_parquet(data / "reports.parquet").select(pl.len()).collect().item()
        truth = pl.scan_parquet(data / "truth.parquet").select(pl.len(), pl.col("truth_id").n_unique()).collect()
        row.update(truth_rows=truth.item(0, 0), aircraft=truth.item(0, 1), reports=reports, input_mb=round(input_mb, 1), runs={},
                   targets={"wall_s": 300.0, "peak_rss_mib": 2048.0, "run_dir_over_input": 2.0})
        for label, tree in trees.items():
            out = work / f"run-{label.replace(' ', '-')}"
            runs = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                run = _run(Path(tree).resolve(), str(data), [], out)
                run_mb = _size_mb(out)
                runs.append({**run, "reports_per_s": round(reports / run["pipeline_s"], 1),
                             "run_dir_mb": round(run_mb, 1), "run_dir_over_input": round(run_mb / input_mb, 2),
                             "bench_s": round(time.perf_counter() - t, 1)})
                print(label, {k: v for k, v in runs[-1].items() if k != "timings_s"}, flush=True)
            median = sorted(runs, key=lambda r: r["pipeline_s"])[len(runs) // 2]
            row["runs"][label] = {**median, "repeats": [{k: v for k, v in r.items() if k != "timings_s"}
                                                        for r in runs]} if len(runs) > 1 else median
        if args.merge and (RESULTS / "bench_long_recording.json").exists():
            old = json.loads((RESULTS / "bench_long_recording.json").read_text())
            row["runs"] = {**{k: v for k, v in old.get("runs", {}).items() if k not in row["runs"]}, **row["runs"]}
            row = {**{k: v for k, v in old.items() if k not in row and k != "machine"}, **row}
        record("bench_long_recording", row)


if __name__ == "__main__":
    main()
