"""Run-database size: the lean layout (tertiary.store.run_store) against every table stored as given.

Runs the job once on a dataset (default: the default job's input, terminal-area as simulated by
``tertiary simulate terminal-area``), stores its tables twice — ``RunStore.create(lean=False)``
(the layout before issue 16 item 5: every table as given, covariances already float32 upper
triangles) and the lean layout — and records each table's size in both, the database sizes and
their ratio to the input Parquet, and checks that every SQL report (sql/*.sql) and every table read
back agree between the two (to float32 round-off where a column is narrowed).

    python benchmarks/bench_store.py [--dataset DIR] [--keep DIR]

A table's size is measured by copying it alone into a fresh database file (a lean table: its
physical parts) and subtracting an empty database's size.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import duckdb
import numpy as np
import polars as pl

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from tertiary import pipeline
from tertiary.store import sql_reports  # noqa: E402
from tertiary.io.dataset import read_dataset  # noqa: E402
from tertiary.store.run_store import LEAN_PREFIX, RunStore  # noqa: E402

#: float agreement allowed between the two layouts: float32 keeps ≤ 6e-8 relative on each stored
#: value, so ≤ 0.008 m on a coordinate of 1e5 m; a derived figure (an RMSE, a minimum) moves by
#: that much in absolute terms
RTOL, ATOL = 1e-5, 1e-2


def process(dataset: Path, cfg: pipeline.PipelineConfig | None = None) -> tuple[list[tuple[str, pl.DataFrame]], dict]:
    """The job's tables in the order ``pipeline.run`` stores them, and its run record."""
    ds = read_dataset(dataset)
    tables: list[tuple[str, pl.DataFrame]] = []
    notes: list[str] = []
    res = pipeline.process(ds, cfg, sink=lambda n, f: tables.append((n, pipeline.make_storable(f, n, notes)))
                           if f.width else None, notes=notes)
    return tables, {"scenario": ds.scenario.name, "rows": res.counts, "notes": notes, "timings": res.timings,
                    "status": "completed"}


def store(tables: list[tuple[str, pl.DataFrame]], info: dict, run_dir: Path, lean: bool) -> Path:
    from tertiary.store.run_store import record_run
    with RunStore.create(run_dir, lean=lean) as st:
        for name, frame in tables:
            st.write(name, frame)
        record_run(st, info)
    return run_dir / "results.duckdb"


def _copy_size(db: Path, tables: list[str], work: Path) -> int:
    f = work / "one.duckdb"
    f.unlink(missing_ok=True)
    con = duckdb.connect(str(f))
    con.execute("ATTACH ? AS src (READ_ONLY)", [str(db)])
    for t in tables:
        con.execute(f'CREATE TABLE "{t}" AS SELECT * FROM src."{t}"')
    con.execute("CHECKPOINT")
    con.close()
    return f.stat().st_size


def table_sizes(db: Path) -> dict[str, int]:
    """Bytes each run table takes (a lean table: its physical parts together)."""
    con = duckdb.connect()
    con.execute("ATTACH ? AS src (READ_ONLY)", [str(db)])
    names = [r[0] for r in con.execute(
        "SELECT table_name FROM duckdb_tables() WHERE database_name = 'src'").fetchall()]
    con.close()
    groups: dict[str, list[str]] = {}
    for n in names:
        base = n[len(LEAN_PREFIX):].split("__")[0] if n.startswith(LEAN_PREFIX) else n
        groups.setdefault(base, []).append(n)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        f = work / "empty.duckdb"
        c = duckdb.connect(str(f))
        c.execute("CREATE TABLE e (x INT)")
        c.execute("CHECKPOINT")
        c.close()
        empty = f.stat().st_size
        return {base: _copy_size(db, parts, work) - empty for base, parts in sorted(groups.items())}


def _same(a: pl.DataFrame, b: pl.DataFrame, what: str) -> list[str]:
    """Differences between two frames (floats to RTOL/ATOL, everything else exactly)."""
    if a.columns != b.columns or a.schema != b.schema:
        return [f"{what}: schema {a.schema} != {b.schema}"]
    if a.height != b.height:
        return [f"{what}: {a.height} rows != {b.height}"]
    out = []
    for c in a.columns:
        x, y = a[c], b[c]
        dt = x.dtype
        base = dt.inner if isinstance(dt, (pl.List, pl.Array)) else dt
        if base in (pl.Float32, pl.Float64):
            if isinstance(dt, (pl.List, pl.Array)):
                if not (x.is_null() == y.is_null()).all():
                    out.append(f"{what}.{c}: nulls differ")
                    continue
                x, y = x.drop_nulls().explode(), y.drop_nulls().explode()
                if x.len() != y.len():
                    out.append(f"{what}.{c}: list lengths differ")
                    continue
            xn, yn = x.cast(pl.Float64).to_numpy(), y.cast(pl.Float64).to_numpy()
            if not np.allclose(xn, yn, rtol=RTOL, atol=ATOL, equal_nan=True) or \
                    not (x.is_null() == y.is_null()).all():
                err = np.nanmax(np.abs(xn - yn)) if xn.size else 0.0
                out.append(f"{what}.{c}: floats differ (max |d| = {err:g})")
        elif not x.equals(y, check_dtypes=True, check_names=True, null_equal=True):
            out.append(f"{what}.{c}: values differ")
    return out


def compare(before: Path, after: Path, params: dict[str, dict] | None = None) -> dict[str, list[str]]:
    """Every SQL report and every table, run/read on both databases: {name: differences}."""
    diffs: dict[str, list[str]] = {}
    with RunStore.open(before) as b, RunStore.open(after) as a:
        if b.tables() != a.tables():
            diffs["tables()"] = [f"{b.tables()} != {a.tables()}"]
        for rep in sql_reports.list_reports():
            p = (params or {}).get(rep.name)
            try:
                rb = sql_reports.run_report(b, rep, p)
            except Exception as exc:  # a report this run cannot answer must fail the same way after
                try:
                    sql_reports.run_report(a, rep, p)
                    diffs[f"sql:{rep.name}"] = [f"fails before ({exc}) but not after"]
                except Exception as exc2:
                    if type(exc2) is not type(exc):
                        diffs[f"sql:{rep.name}"] = [f"{exc!r} != {exc2!r}"]
                continue
            diffs[f"sql:{rep.name}"] = _same(rb, sql_reports.run_report(a, rep, p), rep.name)
        for t in b.tables():
            if t in a.tables():
                diffs[f"table:{t}"] = _same(b.read(t), a.read(t), t)
    return {k: v for k, v in diffs.items() if v}


def parquet_bytes(dataset: Path) -> int:
    return sum(p.stat().st_size for p in dataset.rglob("*.parquet"))


def main() -> None:
    from _util import record
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=None,
                    help="dataset directory [default: simulate terminal-area into a temp directory]")
    ap.add_argument("--keep", type=Path, default=None, help="keep the two run directories here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        dataset = args.dataset
        if dataset is None:
            from tertiary.io.dataset import write_dataset
            from tertiary.simulate import load_scenario, simulate
            dataset = work / "dataset"
            write_dataset(simulate(load_scenario("terminal-area")), dataset)
        t = time.perf_counter()
        tables, info = process(dataset)
        t_proc = time.perf_counter() - t
        dbs, t_store = {}, {}
        for label, lean in (("before", False), ("after", True)):
            t = time.perf_counter()
            dbs[label] = store(tables, info, work / f"run_{label}", lean)
            t_store[label] = time.perf_counter() - t
        diffs = compare(dbs["before"], dbs["after"])
        sizes = {k: table_sizes(v) for k, v in dbs.items()}
        t = time.perf_counter()
        with RunStore.open(dbs["after"]) as st:
            for name in st.tables():
                st.read(name)
        t_read = time.perf_counter() - t
        inp = parquet_bytes(dataset)
        mb = lambda n: round(n / 1e6, 2)  # noqa: E731
        result = {
            "dataset": str(dataset), "reports": int(info["rows"]["reports_in"]),
            "input_parquet_mb": mb(inp),
            "database_mb": {k: mb(v.stat().st_size) for k, v in dbs.items()},
            "ratio_to_input": {k: round(v.stat().st_size / inp, 2) for k, v in dbs.items()},
            "target_ratio": 2.0,
            "tables_mb": {t: {"before": mb(sizes["before"].get(t, 0)), "after": mb(sizes["after"].get(t, 0))}
                          for t in sorted(sizes["before"], key=lambda t: -sizes["before"][t])},
            "store_s": {k: round(v, 2) for k, v in t_store.items()},
            "read_all_tables_after_s": round(t_read, 2),
            "process_s": round(t_proc, 1),
            "sql_reports_and_tables_equal": not diffs,
            "differences": diffs,
        }
        path = record("store_size", result)
        print(json.dumps(result, indent=2))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
