"""Every table of three small runs (one window, windowed, Dask), kept as the golden reference.

``tests/data/golden.json`` holds a summary of every table that the suite compares against
(``test_golden.py``): an exact hash of the non-float columns in a canonical row order, and per
float column the null count, sum, sum of squares and the row-weighted sum (which moves when values
move between rows). Floats are compared to 1e-9 relative: sums aggregated in parallel differ in
the last bits from one run to the next. ``python tests/golden.py`` rewrites the file from the
current tree, which is only right when a change is meant to alter results.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import polars as pl

GOLDEN = Path(__file__).parent / "data" / "golden.json"
#: run-record keys that differ between two runs of the same code (wall times, paths, versions, the
#: finalize pieces' times)
VOLATILE_KEYS = {"created_utc", "versions", "timings", "memory_mib", "notes", "fanout"}
#: tables that hold only measurements of the run itself (times, memory)
VOLATILE_TABLES = {"stage_timings", "partitions"}


def small_dataset():
    from tertiary.simulate import load_scenario, simulate
    cfg = load_scenario("terminal-area")
    return simulate(dataclasses.replace(cfg, duration_s=240.0, runs=1,
                                        traffic=dataclasses.replace(cfg.traffic, aircraft=20, conflict_pairs=3)))


def _sortable(frame: pl.DataFrame) -> list[str]:
    """Plain columns, exact ones first: rows tied on every exact key are rare and then ordered by floats."""
    plain = [c for c, t in frame.schema.items() if not t.is_nested() and t != pl.Object]
    return sorted(plain, key=lambda c: (frame.schema[c].is_float(), c))


def canonical(frame: pl.DataFrame) -> pl.DataFrame:
    """Columns by name, rows sorted on every plain column: two equal tables compare equal."""
    frame = frame.select(sorted(frame.columns))
    return frame.sort(_sortable(frame), nulls_last=True) if frame.height else frame


def summary(frame: pl.DataFrame) -> dict:
    """What two tables equal to 1e-9 share: shape, exact hash of the exact columns, float sums."""
    floats = [c for c, t in frame.schema.items() if t.is_float()]
    exact = frame.drop(floats)
    h = exact.hash_rows(seed=0).to_numpy().tobytes() if exact.width and frame.height else b""
    w = pl.int_range(1, pl.len() + 1).cast(pl.Float64) / max(frame.height, 1)
    sums = frame.select(
        *[pl.struct(pl.col(c).null_count().alias("nulls"), pl.col(c).fill_nan(None).sum().alias("sum"),
                    (pl.col(c).fill_nan(None) ** 2).sum().alias("sumsq"),
                    (pl.col(c).fill_nan(None) * w).sum().alias("wsum"),
                    pl.col(c).is_nan().sum().alias("nans")).alias(c) for c in floats]
    ).row(0, named=True) if floats else {}
    return {"rows": frame.height, "columns": frame.columns, "exact": hashlib.sha256(h).hexdigest()[:20],
            "floats": sums}


def run_tables(db: Path) -> dict[str, pl.DataFrame]:
    from tertiary import RunStore
    out: dict[str, pl.DataFrame] = {}
    with RunStore.open(db.parent) as s:
        for name in sorted(s.tables()):
            if name in VOLATILE_TABLES:
                continue
            frame = s.read(name)
            if name == "run":
                frame = frame.filter(~pl.col("key").is_in(sorted(VOLATILE_KEYS)))
            out[name] = canonical(frame)
    return out


def compute(work: Path) -> dict[str, dict[str, pl.DataFrame]]:
    from tertiary.io.dataset import write_dataset
    from tertiary import pipeline
    ds = small_dataset()
    path = work / "ds"
    write_dataset(ds, path)
    from tertiary.io.dataset import read_dataset
    ds = read_dataset(path)
    # every column stored (``full``): the lean modes' columns are a subset, checked equal to these
    # by the named SQL (tests/test_lean_tables.py)
    res = {"one_window": run_tables(pipeline.run(ds, work / "one", window_s=None, dataset_label="golden",
                                                 tables="full")),
           "windowed": run_tables(pipeline.run(ds, work / "win", window_s=60.0, dataset_label="golden",
                                               tables="full"))}
    from distributed import Client, LocalCluster
    from tertiary.pipeline import dask_engine as D
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        res["dask"] = run_tables(D.run_dask(path, work / "dask", client=client, window_s=60.0, tables="full"))
    return res


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as d:
        result = compute(Path(d))
    golden = {v: {n: summary(f) for n, f in t.items()} for v, t in result.items()}
    GOLDEN.write_text(json.dumps(golden, indent=1, sort_keys=True) + "\n")
    print({v: {n: f.shape for n, f in t.items()} for v, t in result.items()}, file=sys.stderr)
