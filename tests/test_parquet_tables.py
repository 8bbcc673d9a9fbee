"""Registered Parquet tables: ``tertiary run --tables parquet`` keeps the
streamed tables' window parts beside the database, with views over them, instead of copying
them in. The run's tables read the same as a copied run's (to the copy's float32 narrowing),
from any working directory, and nothing of them is left in ``parts``."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from tertiary import pipeline
from tertiary.pipeline import ingestion
from tertiary.core.errors import OptionError
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import TABLES_DIR, RunStore

#: each streamed table's row key (rows compared in this order)
KEYS = {
    "reports": ["run", "report_id"],
    "aligned": ["run", "epoch", "radar_id", "local_track_id", "report_id"],
    "associations": ["run", "epoch", "radar_id", "local_track_id", "report_id"],
    "fused": ["run", "method", "epoch", "target_id"],
    "tracks": ["run", "method", "filter", "epoch", "track_id"],
    "conflicts": ["run", "method", "epoch", "id_a", "id_b"],
}
#: the copied database narrows a picture's floats to float32 (tertiary.store.run_store, lean layout)
F32 = 3e-7


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    cfg = load_scenario("terminal-area")
    ds = simulate(dataclasses.replace(cfg, duration_s=420.0,
                                      traffic=dataclasses.replace(cfg.traffic, aircraft=30, conflict_pairs=3)))
    pc = pipeline.PipelineConfig(methods=("information",), filters=("singer",), centralized=False)
    base = tmp_path_factory.mktemp("tables")
    with pytest.MonkeyPatch.context() as mp:
        # the truth validated to disk in parts (a long run's path): its reference files registered
        mp.setattr(ingestion, "TRUTH_PART_ROWS", 1_000)
        mp.setattr(ingestion, "TRUTH_WHOLE_ROWS", 0)
        for mode in pipeline.TABLE_MODES:
            pipeline.run(ds, base / mode, pc, window_s=60.0, tables=mode)
    return base / "database", base / "parquet"


def _floats(a: pl.Series, b: pl.Series) -> bool:
    """Equal to float32 round-off (lists and arrays element by element), nulls in place."""
    if isinstance(a.dtype, (pl.List, pl.Array)):
        if not (a.is_null() == b.is_null()).all():
            return False
        a, b = a.drop_nulls(), b.drop_nulls()
        if isinstance(a.dtype, pl.List) and not (a.list.len() == b.list.len()).all():
            return False
        a, b = a.explode() if isinstance(a.dtype, pl.List) else a.arr.explode(), (
            b.explode() if isinstance(b.dtype, pl.List) else b.arr.explode())
    x, y = a.to_numpy().astype(float), b.to_numpy().astype(float)
    if not np.array_equal(np.isnan(x), np.isnan(y)):
        return False
    ok = ~np.isnan(x)
    return bool(np.all(np.abs(x[ok] - y[ok]) <= F32 * np.maximum(np.abs(y[ok]), 1e-3)))


def test_registered_tables_read_as_the_copied_ones(runs, tmp_path, monkeypatch):
    copied, registered = runs
    monkeypatch.chdir(tmp_path)            # the views' files are found from any working directory
    with RunStore.open(copied) as a, RunStore.open(registered) as b:
        assert a.tables() == b.tables()
        views = {n for (n,) in b.con.execute("SELECT view_name FROM duckdb_views() WHERE NOT internal").fetchall()}
        assert set(KEYS) | {"truth"} <= views        # the truth: its validated reference files
        for name in a.tables():
            if name == "run":
                continue
            x, y = a.read(name), b.read(name)
            assert x.schema == y.schema, name
            assert x.height == y.height, name
            if name in KEYS:        # the parts' rows in window order; the copy's in the same order
                assert x.select(KEYS[name]).equals(y.select(KEYS[name])), name
            for c in x.columns:
                same = x[c].equals(y[c], null_equal=True)
                assert same or _floats(y[c], x[c]), f"{name}.{c}"
    assert not (registered / "parts").exists()
    for name in KEYS:
        files = sorted((registered / TABLES_DIR / name).glob("part-*.parquet"))
        assert files, name
        assert sum(pl.scan_parquet(f).select(pl.len()).collect().item() for f in files) == \
            RunStore.open(registered).sql(f"SELECT count(*) AS n FROM {name}")["n"][0]
    assert not (copied / TABLES_DIR).exists()


def test_the_registered_database_holds_no_copy(runs):
    copied, registered = runs
    size = {p.name: (p / "results.duckdb").stat().st_size for p in runs}
    # the copy holds the streamed tables; the registered database only what is not streamed
    assert size["parquet"] < size["database"] / 2


def test_register_parquet_keeps_the_given_order_array_types_and_skips_empty_files(tmp_path):
    cov = pl.Array(pl.Float64, 36)
    src = tmp_path / "src"
    src.mkdir()
    # named against their order: the view must follow the order given, not the names
    frames = [pl.DataFrame({"k": [1, 2], "cov": [[1.0] * 36, [2.0] * 36], "x": ["a", "b"]},
                           schema={"k": pl.Int64, "cov": cov, "x": pl.String}),
              pl.DataFrame({"k": []}, schema={"k": pl.Int64}),            # an empty window, fewer columns
              pl.DataFrame({"k": [3], "cov": [[3.0] * 36], "x": ["c"]}, schema={"k": pl.Int64, "cov": cov,
                                                                              "x": pl.String})]
    files = []
    for name, f in zip(["w=3.parquet", "w=2.parquet", "w=1.parquet"], frames):
        f.write_parquet(src / name)
        files.append(src / name)
    with RunStore.create(tmp_path / "run") as store:
        assert store.register_parquet("t", files, drop=["x"]) == 3
        got = store.read("t")
    assert got.schema == pl.Schema({"k": pl.Int64, "cov": cov})
    assert got["k"].to_list() == [1, 2, 3]
    assert got["cov"].arr.first().to_list() == [1.0, 2.0, 3.0]
    kept = sorted((tmp_path / "run" / TABLES_DIR / "t").glob("*.parquet"))
    assert len(kept) == 2                                  # the empty file left out
    assert os.path.samefile(kept[0], files[0])             # linked, not copied
    # registered again: the previous files replaced, not added to
    with RunStore.update(tmp_path / "run") as store:
        store.register_parquet("t", files[2:])
    with RunStore.open(tmp_path / "run") as store:
        assert store.read("t")["k"].to_list() == [3]


def test_the_tables_option_is_checked(tmp_path):
    with pytest.raises(OptionError, match="database or parquet"):
        pipeline.check_tables("duckdb", tmp_path)
    with pytest.raises(OptionError, match="comma"):
        pipeline.check_tables("parquet", Path(tmp_path) / "a,b")
    pipeline.check_tables("parquet", tmp_path / "run")
