"""Run-directory size of the default job: ``tertiary run`` stored lean (``--tables database``, the
default: the columns the report and the named SQL read) against ``--tables full`` (every column),
and optionally against a run directory made by an earlier tree (``--before RUN_DIR``).

Runs the default job (``tertiary run DATASET --no-report``; default dataset: the default scenario,
terminal-area, as simulated by ``tertiary simulate terminal-area``) once per mode, in a child
process each, and records each table's size, the database and run-directory sizes and their ratio
to the input Parquet, and checks that every named SQL report (sql/*.sql) gives the same answer on
every run directory (floats to RTOL/ATOL).

    python benchmarks/bench_store.py [--dataset DIR] [--keep DIR] [--before RUN_DIR]
    python benchmarks/bench_store.py --dataset NATIONAL --entry national_slice --modes database,parquet,full \
        --run-args "--methods information --filters imm_sym --no-centralized"   # kept beside the default job's

A run with ``--tables parquet`` keeps its tables as Parquet in ``RUN_DIR/tables/<name>/``: a
table's size there is its files' bytes.

A table's size is measured by copying it alone into a fresh database file (a lean table: its
physical parts) and subtracting an empty database's size; the per-column bytes of the largest
tables come from DuckDB's storage information (each segment up to the next one in its block).
"""

from __future__ import annotations

import argparse
import json
import subprocess
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

from tertiary.store import sql_reports  # noqa: E402
from tertiary.store.run_store import LEAN_PREFIX, TABLES_DIR, RunStore  # noqa: E402

#: float agreement between a table stored as given and in the lean layout: float32 keeps ≤ 6e-8
#: relative on each stored value, so a derived figure (an RMSE, a minimum) moves by that much
RTOL, ATOL = 1e-5, 1e-2
#: agreement of the named SQL between two run directories of the same job: the runs are the same
#: computation, and the SQL read no column the lean layout narrows (tracks and fused states)
SQL_RTOL, SQL_ATOL = 1e-9, 1e-9
#: reports of the run's own measurements (wall times, creation time): they differ between any two runs
VOLATILE_REPORTS = {"stage_timings", "run_summary"}
MODES = ("database", "full")


def process(dataset: Path, cfg=None) -> tuple[list[tuple[str, pl.DataFrame]], dict]:
    """The job's tables (in memory, one window) in the order ``pipeline.run`` stores them, and its run record."""
    from tertiary import pipeline
    from tertiary.io.dataset import read_dataset
    ds = read_dataset(dataset)
    tables: list[tuple[str, pl.DataFrame]] = []
    notes: list[str] = []
    res = pipeline.process(ds, cfg, sink=lambda n, f: tables.append((n, pipeline.make_storable(f, n, notes)))
                           if f.width else None, notes=notes)
    return tables, {"scenario": ds.scenario.name, "rows": res.counts, "notes": notes, "timings": res.timings,
                    "status": "completed"}


def store(tables: list[tuple[str, pl.DataFrame]], info: dict, run_dir: Path, lean: bool,
          mode: str = "full") -> Path:
    """``tables`` written to a new run database: through the run's sink in ``mode`` (``--tables``),
    in the lean layout or (``lean=False``) every table as given."""
    from tertiary.pipeline.tables import store_sink
    from tertiary.store.run_store import record_run
    with RunStore.create(run_dir, lean=lean) as st:
        sink = store_sink(st, [], mode)
        for name, frame in tables:
            sink(name, frame)
        record_run(st, info)
    return run_dir / "results.duckdb"


def run_job(dataset: Path, out: Path, mode: str, args: list[str] = ()) -> float:
    """``tertiary run DATASET --out OUT --no-report --tables MODE [ARGS]`` in a child process; its wall time."""
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "tertiary.cli", "run", str(dataset), "--out", str(out), "--force",
                    "--no-report", "--quiet", "--tables", mode, *args], check=True, cwd=ROOT,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


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


def _physical(db: Path) -> dict[str, list[str]]:
    """Physical tables of each run table (a lean table: its ``_lean_`` parts)."""
    con = duckdb.connect()
    con.execute("ATTACH ? AS src (READ_ONLY)", [str(db)])
    names = [r[0] for r in con.execute(
        "SELECT table_name FROM duckdb_tables() WHERE database_name = 'src'").fetchall()]
    con.close()
    groups: dict[str, list[str]] = {}
    for n in names:
        base = n[len(LEAN_PREFIX):].split("__")[0] if n.startswith(LEAN_PREFIX) else n
        groups.setdefault(base, []).append(n)
    return groups


def table_sizes(db: Path) -> dict[str, int]:
    """Bytes each run table takes (a lean table: its physical parts together)."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        f = work / "empty.duckdb"
        c = duckdb.connect(str(f))
        c.execute("CREATE TABLE e (x INT)")
        c.execute("CHECKPOINT")
        c.close()
        empty = f.stat().st_size
        sizes = {base: _copy_size(db, parts, work) - empty for base, parts in sorted(_physical(db).items())}
    registered = db.parent / TABLES_DIR          # ``--tables parquet``: the registered tables' files
    if registered.is_dir():
        for d in registered.iterdir():
            sizes[d.name] = sizes.get(d.name, 0) + sum(f.stat().st_size for f in d.rglob("*.parquet"))
    return sizes


def column_bytes(db: Path, top: int = 25) -> list[dict]:
    """The ``top`` largest physical columns: each segment's bytes up to the next segment in its
    block (the block's end for the last), plus its additional blocks."""
    con = duckdb.connect()
    con.execute("ATTACH ? AS src (READ_ONLY)", [str(db)])
    block = con.sql("SELECT block_size FROM pragma_database_size() WHERE database_name = 'src'").fetchall()[0][0]
    frames = []
    for parts in _physical(db).values():
        for t in parts:
            frames.append(con.sql(
                f"SELECT '{t}' AS table_name, column_name, compression, block_id, block_offset, "
                f"coalesce(len(additional_block_ids), 0) AS extra FROM pragma_storage_info('src.{t}')").pl())
    con.close()
    seg = pl.concat(frames).filter(pl.col("block_id") >= 0).sort("block_id", "block_offset")
    seg = seg.with_columns(
        ((pl.col("block_offset").shift(-1).over("block_id").fill_null(block) - pl.col("block_offset"))
         + pl.col("extra") * block).alias("bytes"))
    col = (seg.group_by("table_name", "column_name")
           .agg(pl.col("bytes").sum(), pl.col("compression").unique().sort().str.join(","))
           .sort("bytes", descending=True).head(top))
    return [{"table": r["table_name"], "column": r["column_name"], "mb": round(r["bytes"] / 1e6, 3),
             "compression": r["compression"]} for r in col.iter_rows(named=True)]


def _same(a: pl.DataFrame, b: pl.DataFrame, what: str, rtol: float = RTOL, atol: float = ATOL) -> list[str]:
    """Differences between two frames (floats to rtol/atol, everything else exactly)."""
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
            if not np.allclose(xn, yn, rtol=rtol, atol=atol, equal_nan=True) or \
                    not (x.is_null() == y.is_null()).all():
                err = np.nanmax(np.abs(xn - yn)) if xn.size else 0.0
                out.append(f"{what}.{c}: floats differ (max |d| = {err:g})")
        elif not x.equals(y, check_dtypes=True, check_names=True, null_equal=True):
            out.append(f"{what}.{c}: values differ")
    return out


def compare_sql(ref: Path, other: Path, params: dict[str, dict] | None = None) -> dict[str, list[str]]:
    """Every named SQL report run on both run directories (but :data:`VOLATILE_REPORTS` when they
    are two runs): {report: differences}."""
    diffs: dict[str, list[str]] = {}
    with RunStore.open(ref) as b, RunStore.open(other) as a:
        same_run = b.sql("SELECT value FROM run WHERE key = 'created_utc'").equals(
            a.sql("SELECT value FROM run WHERE key = 'created_utc'"))
        for rep in sql_reports.list_reports():
            if rep.name in VOLATILE_REPORTS and not same_run:
                continue
            p = (params or {}).get(rep.name)
            try:
                rb = sql_reports.run_report(b, rep, p)
            except Exception as exc:  # a report this run cannot answer must fail the same way in the other
                try:
                    sql_reports.run_report(a, rep, p)
                    diffs[rep.name] = [f"fails on {ref} ({exc}) but not on {other}"]
                except Exception as exc2:
                    if type(exc2) is not type(exc):
                        diffs[rep.name] = [f"{exc!r} != {exc2!r}"]
                continue
            try:
                diffs[rep.name] = _same(rb, sql_reports.run_report(a, rep, p), rep.name, SQL_RTOL, SQL_ATOL)
            except Exception as exc:
                diffs[rep.name] = [f"fails on {other} only: {exc}"]
    return {k: v for k, v in diffs.items() if v}


def compare(before: Path, after: Path, params: dict[str, dict] | None = None) -> dict[str, list[str]]:
    """Every SQL report and every table, run/read on both databases (floats to RTOL/ATOL):
    {name: differences}."""
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


def dir_bytes(run_dir: Path) -> int:
    return sum(p.stat().st_size for p in run_dir.rglob("*") if p.is_file())


def main() -> None:
    from _util import record
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=None,
                    help="dataset directory [default: simulate terminal-area into the work directory]")
    ap.add_argument("--keep", type=Path, default=None, help="keep the run directories here")
    ap.add_argument("--before", type=Path, default=None,
                    help="a run directory of the same job by an earlier tree, measured as 'before'")
    ap.add_argument("--shared", action="store_true", help="record that the machine was shared (timings noisy)")
    ap.add_argument("--reuse", action="store_true", help="measure the run directories already in --keep")
    ap.add_argument("--modes", default=",".join(MODES), help="--tables modes run (the first is the reference)")
    ap.add_argument("--run-args", default="", help="further options of tertiary run")
    ap.add_argument("--entry", default=None,
                    help="record under this key of store_size.json, keeping what it holds (default: replace it)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        dataset = args.dataset
        if dataset is None:
            dataset = work / "dataset"
            subprocess.run([sys.executable, "-m", "tertiary.cli", "simulate", "terminal-area", "--out", str(dataset),
                            "--force"], check=True, cwd=ROOT)
        modes = args.modes.split(",")
        runs = {m: work / f"run_{m}" for m in modes}
        extra = args.run_args.split()
        wall = {m: None if args.reuse and (d / "results.duckdb").is_file() else round(run_job(dataset, d, m, extra), 1)
                for m, d in runs.items()}
        if args.before is not None:
            runs = {"before": args.before, **runs}
        dbs = {k: d / "results.duckdb" for k, d in runs.items()}
        sizes = {k: table_sizes(v) for k, v in dbs.items()}
        ref = modes[0]
        diffs = {f"{k} vs {ref}": compare_sql(dbs[k], dbs[ref]) for k in dbs if k != ref}
        t = time.perf_counter()
        with RunStore.open(dbs[ref]) as st:
            for name in st.tables():
                st.read(name)
        t_read = time.perf_counter() - t
        with RunStore.open(dbs[ref]) as st:
            reports = st.sql("SELECT count(*) FROM reports").item()
        inp = parquet_bytes(dataset)
        mb = lambda n: round(n / 1e6, 2)  # noqa: E731
        order = sorted({t for s in sizes.values() for t in s}, key=lambda t: -max(s.get(t, 0) for s in sizes.values()))
        result = {
            "shared_machine": args.shared,
            "dataset": str(dataset), "reports": int(reports),
            "command": " ".join(["tertiary run DATASET --no-report --tables MODE", *extra]),
            "before": None if args.before is None else f"{args.before} (the same job by an earlier tree)",
            "input_parquet_mb": mb(inp),
            "database_mb": {k: mb(v.stat().st_size) for k, v in dbs.items()},
            "run_dir_mb": {k: mb(dir_bytes(d)) for k, d in runs.items()},
            "ratio_to_input": {k: round(dir_bytes(d) / inp, 2) for k, d in runs.items()},
            "target_ratio": 2.0,
            "tables_mb": {t: {k: mb(s.get(t, 0)) for k, s in sizes.items()} for t in order},
            "largest_columns_mb": {k: column_bytes(v, 15) for k, v in dbs.items()},
            "run_wall_s": wall,
            f"read_all_tables_{ref}_s": round(t_read, 2),
            "sql_reports_equal": not any(diffs.values()),
            "sql_differences": diffs,
        }
        if args.entry is None:
            path = record("store_size", result)
        else:
            from _util import RESULTS, machine
            path = RESULTS / "store_size.json"
            kept = json.loads(path.read_text())
            kept[args.entry] = {"machine": machine(), **result}
            path.write_text(json.dumps(kept, indent=2) + "\n")
        print(json.dumps(result, indent=2))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
