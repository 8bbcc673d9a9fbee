"""Tests for the run store (tertiary.store.run_store)."""

from __future__ import annotations

import datetime as dt
import hashlib
import multiprocessing
from pathlib import Path

import duckdb
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.store.run_store import (DB_FILENAME, RunStore, atomic_path, export_parquet, record_run, write_parquet_atomic, write_text_atomic)

UTC = dt.timezone.utc


def sample_frame() -> pl.DataFrame:
    """Three rows covering every dtype the pipeline stores."""
    t0 = dt.datetime(2024, 5, 1, 12, 0, 0, 123456, tzinfo=UTC)
    cov = [float(i) / 7 for i in range(36)]
    return pl.DataFrame(
        {
            "time": pl.Series([t0, None, t0 + dt.timedelta(seconds=4)], dtype=pl.Datetime("us", "UTC")),
            "radar_id": pl.Series([1, None, 4_000_000_000], dtype=pl.UInt32),
            "report_id": pl.Series([2**64 - 1, 0, None], dtype=pl.UInt64),
            "track_id": pl.Series([-5, None, 2**62], dtype=pl.Int64),
            "range_m": [float("nan"), 1.5, None],
            "callsign": ["AFR123", None, "it's; DROP TABLE x"],
            "cov": pl.Series([cov, None, [0.0] * 36], dtype=pl.Array(pl.Float64, 36)),
            "weights": pl.Series([[1.0, float("nan")], [], None], dtype=pl.List(pl.Float64)),
            "members": pl.Series([[1, 2**64 - 1], None, []], dtype=pl.List(pl.UInt64)),
        }
    )


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def leftovers(directory: Path) -> list[str]:
    """Temp files/dirs our writers may leave behind."""
    return sorted(p.name for p in directory.iterdir() if ".tmp-" in p.name or p.name.endswith(".wal"))


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    with RunStore.create(tmp_path) as store:
        store.write("reports", sample_frame())
    return tmp_path


# ---------------------------------------------------------------- round trips


def test_round_trip_preserves_dtypes_and_values(run_dir: Path) -> None:
    with RunStore.open(run_dir) as store:
        back = store.read("reports")
    assert back.schema == sample_frame().schema
    assert_frame_equal(back, sample_frame())


def test_documented_dtype_changes(tmp_path: Path) -> None:
    frame = pl.DataFrame(
        {
            "paris": pl.Series([dt.datetime(2024, 1, 1, 12)], dtype=pl.Datetime("us", "Europe/Paris")),
            "ms_utc": pl.Series([dt.datetime(2024, 1, 1)], dtype=pl.Datetime("ms", "UTC")),
            "ns_utc": pl.Series([dt.datetime(2024, 1, 1)], dtype=pl.Datetime("ns", "UTC")),
            "naive": pl.Series([dt.datetime(2024, 1, 1)], dtype=pl.Datetime("ms")),
            "cat": pl.Series(["a"], dtype=pl.Categorical),
        }
    )
    with RunStore.create(tmp_path) as store:
        store.write("t", frame)
        back = store.read("t")
    assert back.schema == pl.Schema(
        {
            "paris": pl.Datetime("us", "UTC"),
            "ms_utc": pl.Datetime("us", "UTC"),
            "ns_utc": pl.Datetime("ns", "UTC"),
            "naive": pl.Datetime("ms"),
            "cat": pl.String,
        }
    )
    assert back["paris"][0] == frame["paris"][0]  # same instant, relabelled UTC


def test_utc_even_if_session_zone_changes(run_dir: Path) -> None:
    with RunStore.open(run_dir) as store:
        store.con.execute("SET TimeZone = 'America/New_York'")
        assert store.read("reports")["time"].dtype == pl.Datetime("us", "UTC")
        assert store.sql("SELECT time FROM reports")["time"].dtype == pl.Datetime("us", "UTC")


def test_duration_rejected(tmp_path: Path) -> None:
    with RunStore.create(tmp_path) as store, pytest.raises(TypeError, match="Duration"):
        store.write("d", pl.DataFrame({"d": [dt.timedelta(seconds=1)]}))


def test_empty_frame_keeps_schema(tmp_path: Path) -> None:
    empty = sample_frame().clear()
    with RunStore.create(tmp_path) as store:
        store.write("empty", empty)
        assert_frame_equal(store.read("empty"), empty)


# ---------------------------------------------------------------- table ops


def test_write_replaces_and_append_appends(tmp_path: Path) -> None:
    frame = sample_frame()
    with RunStore.create(tmp_path) as store:
        store.append("a", frame)  # creates
        store.append("a", frame.select(reversed(frame.columns)))  # matched by name
        store.write("b", frame)
        store.write("b", frame.head(1))
        assert_frame_equal(store.read("a"), pl.concat([frame, frame]))
        assert store.read("b").height == 1
        assert store.tables() == ["a", "b"]


def test_write_files_is_write_of_their_rows_in_order(tmp_path: Path) -> None:
    """A table written from Parquet files by DuckDB itself (a long truth) reads back
    as :meth:`RunStore.write` of the files' rows in file order without the dropped columns, and
    replaces the table; a table with a lean layout rule is refused (written part by part
    instead). Fails if the files are read out of order, a dropped column is kept, or a type
    (UTC time, unsigned and signed integers, nulls) differs from the frame path's."""
    frame = sample_frame().drop("cov", "weights", "members").with_columns(pl.Series("__prev", [1, 2, 3]))
    files = []
    for k, part in enumerate([frame.slice(2, 1), frame.slice(0, 2)]):      # names order the rows
        files.append(tmp_path / f"{k:02d}.parquet")
        part.write_parquet(files[-1])
    with RunStore.create(tmp_path / "run") as store:
        store.write("truth", frame.head(1))
        assert store.write_files("truth", files, ("__prev",))
        assert not store.write_files("fused", files)                       # lean rules: not here
        want = pl.concat([frame.slice(2, 1), frame.slice(0, 2)]).drop("__prev")
        store.write("frame_path", want)
        assert_frame_equal(store.read("truth"), want)
        assert_frame_equal(store.read("truth"), store.read("frame_path"))
        assert "fused" not in store.tables()


def test_a_table_too_wide_for_the_writers_pool_is_written_whole(tmp_path: Path) -> None:
    """DuckDB builds a row group in the writer's buffer pool before writing it, about 1 MB a
    float64 column: a frame of 100 such columns does not fit in WRITER_MEMORY_LIMIT. ``write``,
    ``write_parts`` and ``append`` retry with a larger pool and set it back; no scratch view is
    left registered. Fails if DuckDB's OutOfMemoryException escapes (before: it did, hidden
    behind "Current transaction is aborted" from the view's unregistration), or if the pool
    stays raised (every later table's written blocks would be held in it)."""
    import numpy as np

    n, k = 130_000, 100
    wide = pl.DataFrame({f"c{i}": np.arange(n, dtype=float) * (i + 1) for i in range(k)})

    def pool(store: RunStore) -> str:
        return store.con.sql("SELECT current_setting('memory_limit')").fetchall()[0][0]
    with RunStore.create(tmp_path / "run") as store:
        before = pool(store)
        store.write("whole", wide)
        store.write_parts("parts", lambda: iter([wide.slice(0, n // 2), wide.slice(n // 2)]))
        store.append("appended", wide)
        for name in ("whole", "parts", "appended"):
            assert_frame_equal(store.read(name), wide)
        assert pool(store) == before
        left = store.con.sql("SELECT count(*) FROM duckdb_views() WHERE view_name LIKE '_tertiary_src_%'")
        assert left.fetchall()[0][0] == 0


class _Recording:
    """A connection that records the writer's pool at every commit and checkpoint."""

    def __init__(self, con: duckdb.DuckDBPyConnection, seen: list[tuple[str, str]]) -> None:
        self._con, self._seen = con, seen

    def _pool(self) -> str:
        return self._con.sql("SELECT current_setting('memory_limit')").fetchall()[0][0]

    def commit(self):
        self._seen.append(("commit", self._pool()))
        return self._con.commit()

    def execute(self, sql, *a, **k):
        if isinstance(sql, str) and sql.startswith("CHECKPOINT"):
            self._seen.append(("checkpoint", self._pool()))
        return self._con.execute(sql, *a, **k)

    def __getattr__(self, name):
        return getattr(self._con, name)


def test_commits_and_the_last_checkpoint_run_in_a_pool_of_their_own(tmp_path: Path) -> None:
    """A checkpoint (the last one, or one a commit triggers when the write-ahead log has grown)
    that runs out of the writer's small pool fails and invalidates the database ("Checkpoint
    failed ... could not allocate block ... 61.0 MiB", as a one-window national quarter-hour with
    every table needs). Each runs in CHECKPOINT_MEMORY_MB, and the pool is set back after."""
    from tertiary.store import run_store
    seen: list[tuple[str, str]] = []
    with RunStore.create(tmp_path / "run") as store:
        small = store.con.sql("SELECT current_setting('memory_limit')").fetchall()[0][0]
        store._con = _Recording(store._con, seen)
        store.write("a", pl.DataFrame({"x": [1.0, 2.0]}))
        store.append("a", pl.DataFrame({"x": [3.0]}))
        assert store.con.sql("SELECT current_setting('memory_limit')").fetchall()[0][0] == small
    probe = duckdb.connect()
    probe.execute(f"SET memory_limit = '{run_store.CHECKPOINT_MEMORY_MB}MB'")
    big = probe.sql("SELECT current_setting('memory_limit')").fetchall()[0][0]
    assert {k for k, _ in seen} == {"commit", "checkpoint"} and seen[-1][0] == "checkpoint"
    assert all(pool == big for _, pool in seen), seen
    with RunStore.open(tmp_path / "run") as store:
        assert store.read("a")["x"].to_list() == [1.0, 2.0, 3.0]


def test_tables_hides_registered_views(run_dir: Path) -> None:
    with RunStore.open(run_dir) as store:
        store.con.register("scratch", pl.DataFrame({"x": [1]}).to_arrow())
        assert store.tables() == ["reports"]


def test_read_missing_table(run_dir: Path) -> None:
    with RunStore.open(run_dir) as store, pytest.raises(KeyError):
        store.read("nope")


@pytest.mark.parametrize("name", ["", "1abc", "a-b", "a b", 'x"; DROP TABLE reports; --', "reports;"])
def test_invalid_table_name_rejected(tmp_path: Path, name: str) -> None:
    with RunStore.create(tmp_path) as store:
        for op in (store.write, store.append):
            with pytest.raises(ValueError):
                op(name, sample_frame())
        with pytest.raises(ValueError):
            store.read(name)
        assert store.tables() == []


def test_sql_binds_parameters(run_dir: Path) -> None:
    with RunStore.open(run_dir) as store:
        got = store.sql("SELECT radar_id FROM reports WHERE track_id = ?", [-5])
        assert got["radar_id"].to_list() == [1]
        got = store.sql("SELECT count(*) AS n FROM reports WHERE radar_id >= $lo", {"lo": 2})
        assert got["n"].to_list() == [1]


def test_sql_malicious_param_stays_data(run_dir: Path) -> None:
    evil = "x'; DROP TABLE reports; --"
    with RunStore.update(run_dir) as store:
        assert store.sql("SELECT ?::VARCHAR AS s", [evil])["s"].to_list() == [evil]
        assert store.sql("SELECT count(*) AS n FROM reports WHERE callsign = ?", [evil])["n"][0] == 0
        assert store.tables() == ["reports"]
    with RunStore.open(run_dir) as store:
        assert store.read("reports").height == 3


def test_sql_without_result(tmp_path: Path) -> None:
    with RunStore.create(tmp_path) as store:
        assert store.sql("CREATE TABLE t AS SELECT 1 AS x").to_dicts() == [{"Count": 1}]
        assert store.sql("SET threads = 2").is_empty()
        assert store.tables() == ["t"]


# ---------------------------------------------------------------- atomicity


def test_failed_create_leaves_old_database_identical(run_dir: Path) -> None:
    db = run_dir / DB_FILENAME
    before = digest(db)
    with pytest.raises(RuntimeError, match="boom"), RunStore.create(run_dir) as store:
        store.write("other", sample_frame())
        raise RuntimeError("boom")
    assert digest(db) == before
    assert leftovers(run_dir) == []
    with RunStore.open(run_dir) as store:
        assert store.tables() == ["reports"]


def test_failed_first_create_leaves_nothing(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError), RunStore.create(tmp_path) as store:
        store.write("t", sample_frame())
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_create_replaces_previous_database(run_dir: Path) -> None:
    with RunStore.create(run_dir) as store:
        store.write("fresh", pl.DataFrame({"x": [1]}))
    with RunStore.open(run_dir) as store:
        assert store.tables() == ["fresh"]
    assert leftovers(run_dir) == []


def test_reader_keeps_its_snapshot_while_writer_replaces(run_dir: Path) -> None:
    with RunStore.open(run_dir) as old:
        with RunStore.update(run_dir) as store:
            store.write("tracks", pl.DataFrame({"x": [1]}))
        assert old.tables() == ["reports"]
        with RunStore.open(run_dir) as new:  # not served from DuckDB's instance cache
            assert new.tables() == ["reports", "tracks"]


def test_update_keeps_existing_and_adds(run_dir: Path) -> None:
    with RunStore.update(run_dir) as store:
        store.write("tracks", pl.DataFrame({"track_id": pl.Series([1, 2], dtype=pl.UInt64)}))
        store.append("reports", sample_frame().head(1))
    with RunStore.open(run_dir) as store:
        assert store.tables() == ["reports", "tracks"]
        assert store.read("reports").height == 4
        assert store.read("tracks")["track_id"].to_list() == [1, 2]
    assert leftovers(run_dir) == []


def test_failed_update_leaves_database_identical(run_dir: Path) -> None:
    db = run_dir / DB_FILENAME
    before = digest(db)
    with pytest.raises(ValueError), RunStore.update(run_dir) as store:
        store.write("tracks", sample_frame())
        store.write("bad name", sample_frame())
    assert digest(db) == before
    assert leftovers(run_dir) == []


def test_update_missing_database(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError), RunStore.update(tmp_path):
        pass
    with pytest.raises(FileNotFoundError):
        RunStore.open(tmp_path)


def test_nested_writers_in_one_process_rejected(run_dir: Path) -> None:
    with RunStore.update(run_dir), pytest.raises(RuntimeError, match="already open"):
        with RunStore.create(run_dir):
            pass


def _append_rows(run_dir: str, n: int) -> None:
    for i in range(n):
        with RunStore.update(run_dir) as store:
            store.append("counter", pl.DataFrame({"i": [i]}))


def test_concurrent_updates_lose_nothing(run_dir: Path) -> None:
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_append_rows, args=(str(run_dir), 5)) for _ in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    with RunStore.open(run_dir) as store:
        assert store.read("counter").height == 15


def test_read_only_cannot_write(run_dir: Path) -> None:
    before = digest(run_dir / DB_FILENAME)
    with RunStore.open(run_dir) as store:
        with pytest.raises(PermissionError):
            store.write("x", sample_frame())
        with pytest.raises(PermissionError):
            store.append("reports", sample_frame())
        with pytest.raises(duckdb.Error):
            store.con.execute("CREATE TABLE x AS SELECT 1 AS a")
        with pytest.raises(duckdb.Error):
            store.sql("DROP TABLE reports")
        assert store.tables() == ["reports"]
    assert digest(run_dir / DB_FILENAME) == before


# ---------------------------------------------------------------- files


def test_export_parquet_matches_tables(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "parquet"
    with RunStore.update(run_dir) as store:
        store.write("tracks", pl.DataFrame({"x": [1.0, None]}))
    paths = export_parquet(run_dir, out)
    assert sorted(p.name for p in paths) == ["reports.parquet", "tracks.parquet"]
    assert sorted(p.name for p in out.iterdir()) == ["reports.parquet", "tracks.parquet"]
    with RunStore.open(run_dir) as store:
        for name in store.tables():
            assert_frame_equal(pl.read_parquet(out / f"{name}.parquet"), store.read(name))
        export_parquet(store, out, tables=["tracks"])  # from an open store, subset
    assert_frame_equal(pl.read_parquet(out / "reports.parquet"), sample_frame())


def test_write_parquet_atomic_replaces_and_cleans(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "f.parquet"
    write_parquet_atomic(pl.DataFrame({"a": [1]}), target)
    assert write_parquet_atomic(sample_frame(), target) == target
    assert_frame_equal(pl.read_parquet(target), sample_frame())
    assert [p.name for p in target.parent.iterdir()] == ["f.parquet"]


def test_atomic_path_failure_keeps_original(tmp_path: Path) -> None:
    target = tmp_path / "note.txt"
    write_text_atomic(target, "old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp != target
        tmp.write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["note.txt"]
    write_text_atomic(target, "new")
    assert target.read_text() == "new"


def test_record_run(tmp_path: Path) -> None:
    info = {"seed": 42, "scenario": "paris_tma", "radars": ["R1", "R2"], "ok": True}
    with RunStore.create(tmp_path) as store:
        record_run(store, info)
    with RunStore.open(tmp_path) as store:
        run = store.read("run")
    assert run.schema == pl.Schema({"key": pl.String, "value": pl.String})
    assert dict(run.iter_rows()) == {"seed": "42", "scenario": "paris_tma", "radars": '["R1", "R2"]', "ok": "true"}


def test_covariances_are_stored_as_float32_upper_triangles_and_read_back_whole(tmp_path):
    """A lean run database: 21 float32 instead of 36 float64 per matrix."""
    import numpy as np
    from tertiary.store.run_store import RunStore
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 6, 6)) * 30.0
    cov = a @ a.transpose(0, 2, 1) + np.eye(6) * 100.0
    frame = pl.DataFrame({"k": np.arange(50), "cov": cov.reshape(50, 36), "x": np.ones(50)},
                         schema_overrides={"cov": pl.Array(pl.Float64, 36)})
    frame = frame.with_columns(pl.when(pl.col("k") == 3).then(None).otherwise(pl.col("cov")).alias("cov"))
    with RunStore.create(tmp_path) as store:
        store.write("t", frame)
        stored = store.sql('DESCRIBE "t"')
        back = store.read("t")
    assert dict(zip(stored["column_name"], stored["column_type"]))["cov_ut"] == "FLOAT[21]"
    assert back.columns == ["k", "cov", "x"] and back.schema["cov"] == pl.Array(pl.Float64, 36)
    got = back["cov"].to_numpy().reshape(-1, 6, 6)
    ok = np.arange(50) != 3
    assert back["cov"].is_null().to_list() == (~ok).tolist()
    np.testing.assert_allclose(got[ok], cov[ok], rtol=1e-6)
    assert (got[ok] == got[ok].transpose(0, 2, 1)).all()


def test_a_commit_keeps_a_pool_raised_for_a_wide_table(tmp_path: Path, monkeypatch) -> None:
    """A commit inside :meth:`RunStore._sized`'s retry, whose pool it raised for a table too wide
    for the writer's, runs in that raised pool, never in a smaller checkpoint pool; the pool
    is set back to the raised one after."""
    from tertiary.store import run_store
    monkeypatch.setattr(run_store, "CHECKPOINT_MEMORY_MB", 16)
    seen: list[tuple[str, str]] = []
    probe = duckdb.connect()

    def shown(mb: int) -> str:
        probe.execute(f"SET memory_limit = '{mb}MB'")
        return probe.sql("SELECT current_setting('memory_limit')").fetchall()[0][0]
    with RunStore.create(tmp_path / "run") as store:
        store._pool_mb = 256                      # as _sized leaves it while it retries
        store.con.execute("SET memory_limit = '256MB'")
        store._con = _Recording(store._con, seen)
        store.write("a", pl.DataFrame({"x": [1.0]}))
        assert store.con.sql("SELECT current_setting('memory_limit')").fetchall()[0][0] == shown(256)
    assert [p for kind, p in seen if kind == "commit"] == [shown(256)]
