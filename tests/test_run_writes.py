"""When a run's tables are written into its database: the ones known before the end while the
windows run, so that the end of the run has little left to write."""

from __future__ import annotations

import dataclasses

import pytest
from polars.testing import assert_frame_equal

from tertiary import pipeline
from tertiary.pipeline import streaming, tables
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore


@pytest.fixture(scope="module")
def terminal():
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=20, conflict_pairs=2))
    return simulate(cfg)


def _windows_started(monkeypatch) -> list[int]:
    """A list whose length is the number of windows whose processing has begun."""
    started: list[int] = []
    for name in ("process_step", "pipeline_step"):
        monkeypatch.setattr(streaming, name, lambda *a, f=getattr(streaming, name), **k:
                            started.append(1) or f(*a, **k))
    return started


def test_the_truth_is_handed_to_the_writer_before_the_first_window(terminal, tmp_path, monkeypatch):
    """An on-disk run validates its truth before the windows: the ``truth`` table is handed to
    the run's writer then, once, and written while the windows run; the database's truth is the
    in-memory run's. Fails if the truth waits for the end, or is written twice."""
    started = _windows_started(monkeypatch)
    handed: list[tuple[str, int]] = []          # (table, windows begun when it was handed over)
    monkeypatch.setattr(tables.SinkThread, "__call__", lambda self, name, frame, f=tables.SinkThread.__call__:
                        handed.append((name, len(started))) or f(self, name, frame))
    pipeline.run(terminal, tmp_path / "run", window_s=60.0)
    truth = [n for name, n in handed if name == "truth"]
    assert truth == [0] and len(started) > 3
    assert {name for name, n in handed if n == len(started)} >= {"reports", "fused", "tracks"}
    mem = pipeline.process(terminal, window_s=60.0)
    with RunStore.open(tmp_path / "run") as st:
        assert_frame_equal(st.read("truth"), mem.ingested.truth)
