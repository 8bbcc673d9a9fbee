"""When a run writes into its database: what is known before the end (the truth, the windows'
streamed tables, the inputs' fingerprints) while the windows run, so that the end of the run has
little left to write."""

from __future__ import annotations

import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary import pipeline
from tertiary.pipeline import streaming, tables
from tertiary.runtime.windows import Window
from tertiary.store.run_store import RunStore


def _windows_started(monkeypatch) -> list[int]:
    """A list whose length is the number of windows whose processing has begun."""
    started: list[int] = []
    for name in ("process_step", "pipeline_step"):
        monkeypatch.setattr(streaming, name, lambda *a, f=getattr(streaming, name), **k:
                            started.append(1) or f(*a, **k))
    return started


def test_the_truth_is_handed_to_the_writer_before_the_first_window(small_terminal, tmp_path, monkeypatch):
    """An on-disk run validates its truth before the windows: the ``truth`` table is handed to
    the run's writer then, once, and written while the windows run; the database's truth is the
    in-memory run's. Fails if the truth waits for the end, or is written twice."""
    started = _windows_started(monkeypatch)
    handed: list[tuple[str, int]] = []          # (table, windows begun when it was handed over)
    monkeypatch.setattr(tables.SinkThread, "__call__", lambda self, name, frame, f=tables.SinkThread.__call__:
                        handed.append((name, len(started))) or f(self, name, frame))
    pipeline.run(small_terminal, tmp_path / "run", window_s=60.0)
    truth = [n for name, n in handed if name == "truth"]
    assert truth == [0] and len(started) > 3
    assert {name for name, n in handed if n == len(started)} >= {"reports", "fused", "tracks"}
    mem = pipeline.process(small_terminal, window_s=60.0)
    with RunStore.open(tmp_path / "run") as st:
        assert_frame_equal(st.read("truth"), mem.ingested.truth)


def _database(run_dir) -> dict[str, pl.DataFrame]:
    """Every table and view of a run database but the run record, and the physical tables'
    column lists (the lean layout)."""
    with RunStore.open(run_dir) as st:
        out = {name: st.read(name) for name in st.tables() if name != "run"}
        for (name,) in st.con.execute("SELECT table_name FROM duckdb_tables() WHERE table_name LIKE '\\_lean%' "
                                      "ESCAPE '\\'").fetchall():
            out[f"layout:{name}"] = st.sql(f'DESCRIBE "{name}"').select("column_name", "column_type")
    return out


def _same_databases(a: dict[str, pl.DataFrame], b: dict[str, pl.DataFrame]) -> None:
    assert sorted(a) == sorted(b)
    for name in a:
        try:
            assert_frame_equal(a[name], b[name])
        except AssertionError as exc:
            raise AssertionError(f"table {name}") from exc


@pytest.fixture(scope="module")
def end_only(small_terminal, tmp_path_factory):
    """The database of a run whose streamed tables are all written at its end."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tables, "LIVE_FLUSH_ROWS", 10**12)
        out = tmp_path_factory.mktemp("end_only") / "run"
        pipeline.run(small_terminal, out, window_s=60.0)
    return _database(out)


def test_the_windows_parts_are_appended_as_the_run_goes_and_the_database_is_the_same(
        small_terminal, end_only, tmp_path, monkeypatch):
    """With a flush every window, each streamed table is appended to the database while the
    windows run and the end appends only the last windows' parts: no table with rows is written
    whole.
    The database — every table, and the lean layout of each physical table — is the one the run
    writes at its end. Fails if the end wrote a table again, skipped the parts not yet
    appended, or appended them in another order."""
    monkeypatch.setattr(tables, "LIVE_FLUSH_ROWS", 1)
    started = _windows_started(monkeypatch)
    appended: list[tuple[str, int]] = []           # (table, windows begun when it was appended)
    whole: list[str] = []
    monkeypatch.setattr(RunStore, "append_parts", lambda self, given, f=RunStore.append_parts:
                        appended.extend((name, len(started)) for name in given) or f(self, given))
    monkeypatch.setattr(RunStore, "write_parts", lambda self, name, parts, f=RunStore.write_parts:
                        whole.append(name) or f(self, name, parts))
    pipeline.run(small_terminal, tmp_path / "run", window_s=60.0)
    n = len(started)
    assert n > 4
    for name in tables.LIVE_TABLES:
        assert any(t == name and k < n for t, k in appended) or end_only[name].height == 0, name
    assert sum(end_only[name].height > 0 for name in tables.LIVE_TABLES) >= 5
    assert not {name for name in whole if name in tables.LIVE_TABLES and end_only[name].height}
    _same_databases(_database(tmp_path / "run"), end_only)


def test_a_resumed_run_appends_the_windows_stored_before_it(small_terminal, end_only, tmp_path, monkeypatch):
    """A run that fails in its fourth window and is resumed: the resumed run's database is new,
    so its first catch-up appends the windows the failed run stored, and no table with rows is
    written whole at the end; the tables are those of a run that never failed. Fails if the
    catch-up began at the resumed window."""
    monkeypatch.setattr(tables, "LIVE_FLUSH_ROWS", 1)

    def failing(cfg, ctx, st, raw, w, clock, *a, f=streaming.process_step):
        if w.index == 3:
            raise RuntimeError("killed")
        return f(cfg, ctx, st, raw, w, clock, *a)
    with monkeypatch.context() as mp:
        mp.setattr(streaming, "process_step", failing)
        with pytest.raises(Exception, match="killed"):
            pipeline.run(small_terminal, tmp_path / "run", window_s=60.0)
    whole: list[str] = []
    monkeypatch.setattr(RunStore, "write_parts", lambda self, name, parts, f=RunStore.write_parts:
                        whole.append(name) or f(self, name, parts))
    pipeline.run(small_terminal, tmp_path / "run", window_s=60.0, resume=True)
    assert not {name for name in whole if name in tables.LIVE_TABLES and end_only[name].height}
    _same_databases(_database(tmp_path / "run"), end_only)


def test_a_table_whose_layout_changes_between_flushes_is_written_whole(tmp_path, monkeypatch):
    """A streamed table whose later parts cannot share the first part's physical table (here a
    column that appears) is left out of the appends once that shows, and written whole when the
    end hands it over: the table of every part, as the end alone writes it. The flush it broke
    still appends the other tables. Fails if that flush were dropped or the broken table kept
    in the appends."""
    from tertiary.runtime.windows import PartStore
    monkeypatch.setattr(tables, "LIVE_FLUSH_ROWS", 1)
    parts = PartStore.start(tmp_path / "run", {"parts": "full"})
    frames = [pl.DataFrame({"run": [0, 0], "a": [1.0, 2.0]}), pl.DataFrame({"run": [0], "a": [3.0]}),
              pl.DataFrame({"run": [1], "a": [4.0], "b": ["x"]}), pl.DataFrame({"run": [1], "a": [5.0], "b": ["y"]})]
    other = [pl.DataFrame({"run": [k], "n": [k * 10]}) for k in range(len(frames))]
    with RunStore.create(tmp_path / "run") as store:
        sink = tables.store_sink(store, [], "full")
        for k, frame in enumerate(frames):
            parts.write(Window(k, k, k + 1), {"conflicts": frame, "clusters": other[k]})
            parts.checkpoint(Window(k, k, k + 1), None)
            sink.catch_up(parts)
        assert sink.broken == {"conflicts"} and store.read("conflicts").height == 3
        assert_frame_equal(store.read("clusters"), pl.concat(other))
        for name in ("conflicts", "clusters"):
            sink(name, tables.for_sink(parts, name, pl.DataFrame()))
        assert_frame_equal(store.read("conflicts"), pl.concat(frames, how="diagonal_relaxed"))
        assert_frame_equal(store.read("clusters"), pl.concat(other))


@pytest.mark.parametrize("batch_rows", [1 << 20, 7_777])
def test_a_lazy_input_is_fingerprinted_as_the_table_in_memory_would_be(tmp_path, monkeypatch, batch_rows):
    """The run record's fingerprint of an input read lazily is hashed a batch at a time, beside
    the windows: the same as the whole table's hashed in memory, rows in their order, whatever
    the batch (one, or batches across the file's row groups). Fails if the batches were hashed
    in another order or the rows hashed otherwise."""
    import hashlib

    import numpy as np

    from tertiary.pipeline import runner
    monkeypatch.setattr(runner, "FINGERPRINT_BATCH_ROWS", batch_rows)
    n = 300_000
    frame = pl.DataFrame({"a": np.arange(n), "b": np.random.default_rng(1).normal(size=n),
                          "c": ["x", "y", "z"] * (n // 3)})
    frame.write_parquet(tmp_path / "t.parquet", row_group_size=20_000)
    whole = frame.select(pl.struct(pl.all()).hash(seed=0)).to_series().to_numpy()
    assert runner._fingerprint_any(pl.scan_parquet(tmp_path / "t.parquet")) == \
        hashlib.sha256(whole.tobytes()).hexdigest()[:16]


def test_freed_memory_is_released_after_every_window(small_terminal, tmp_path, monkeypatch):
    """glibc's freed pages are handed back once per window
    (:func:`~tertiary.core.memory.release_freed_memory`), after it is processed, so that they do not
    add up over a long run.
    Fails if the windows stop releasing, or release before processing."""
    started = _windows_started(monkeypatch)
    released: list[int] = []                    # windows begun at each release
    monkeypatch.setattr(streaming, "release_freed_memory", lambda: released.append(len(started)) or True)
    pipeline.run(small_terminal, tmp_path / "run", window_s=60.0)
    assert len(started) > 3 and released == list(range(1, len(started) + 1))
