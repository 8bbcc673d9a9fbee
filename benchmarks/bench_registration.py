"""Radar registration at scale: ``tertiary register`` on the national peak 15 minutes.

Radar to radar (``--method multi``: every radar's range bias, azimuth bias and clock offset
jointly with a B-spline trajectory per Mode S aircraft, no reference) and against the
reference (``--method reference``), each in a fresh process: wall time, peak memory, and the
estimates against the biases the scenario injected (the scenario file, read here for the
evaluation only): the largest error per quantity and the share of radars whose error lies
within 3 of its own σ.

    python benchmarks/bench_registration.py [--work DIR]

Results: ``benchmarks/results/bench_registration.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import each_dataset  # noqa: E402
from bench_trust import _child, _national15  # noqa: E402

DATASETS = ("national15",)
METHODS = ("multi", "reference")
#: (registration table column, scenario radar key)
QUANTITIES = (("range_bias_m", "bias_range_m"), ("azimuth_bias_deg", "bias_azimuth_deg"),
              ("time_offset_s", "time_offset_s"))
SIGMA = {"range_bias_m": "range_bias_sigma_m", "azimuth_bias_deg": "azimuth_bias_sigma_deg",
         "time_offset_s": "time_offset_sigma_s"}


def accuracy(table_path: Path, scenario: Path) -> dict:
    """Largest |estimate − injected| per quantity and the share within 3σ; clock offsets radar to
    radar are relative (their sum is fixed at 0), so they are compared after removing the mean."""
    import numpy as np
    import polars as pl
    table = pl.read_parquet(table_path)
    injected = {r["name"]: r for r in tomllib.loads(scenario.read_text())["radars"]}
    rows = table.filter(pl.col("name").is_in(list(injected)))
    out = {"radars": rows.height}
    for col, key in QUANTITIES:
        est = rows[col].to_numpy()
        true = np.array([injected[n].get(key, 0.0) for n in rows["name"]])
        if col == "time_offset_s" and rows["method"][0] == "multi":
            est, true = est - est.mean(), true - true.mean()
        err = np.abs(est - true)
        sigma = rows[SIGMA[col]].to_numpy()
        out[col] = {"max_abs_error": round(float(err.max()), 6),
                    "within_3_sigma": round(float(np.mean(err <= 3 * sigma)), 3)}
    return out


def run_dataset(name: str, work: Path) -> dict:
    data = work / name
    sim = _national15(work, name)
    if not (data / "parts.json").exists():
        _child(["simulate", *sim, "--out", str(data), "--force", "--quiet"])
    out = {"simulate": sim}
    for method in METHODS:
        wall, stdout = _child(["register", str(data), "--method", method])
        peak = [int(line.split()[1]) for line in stdout.splitlines() if line.startswith("PEAK_KIB")]
        out[method] = {"wall_s": round(wall, 1), "peak_rss_mib": round(peak[-1] / 1024, 1) if peak else None,
                       **accuracy(data / "registration.parquet", data / "scenario.toml")}
        print(name, method, json.dumps(out[method]), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=None, help="keep the dataset here (default: a temp dir)")
    args = ap.parse_args()
    each_dataset("bench_registration", ",".join(DATASETS), DATASETS, args.work, run_dataset)


if __name__ == "__main__":
    main()
