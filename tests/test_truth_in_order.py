"""The on-disk truth validated in one pass when its aircraft's times increase across the input
batches (a recording written a time span per file, each file sorted by aircraft)."""

from __future__ import annotations

import dataclasses
import json
from datetime import timedelta
from types import SimpleNamespace

import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary import pipeline
from tertiary.evaluation.evaluate import read_reference, reference_files
from tertiary.evaluation.matching import neighbour_times
from tertiary.pipeline import ingestion
from tertiary.simulate import load_scenario, simulate

BATCH = 900


@pytest.fixture(scope="module")
def truth() -> pl.DataFrame:
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=420.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=30, conflict_pairs=3))
    return simulate(cfg).truth


def _spans_by_aircraft(truth: pl.DataFrame, span_s: int = 60) -> pl.DataFrame:
    """The truth a time span at a time, each span sorted by aircraft: an aircraft's rows recur in
    every span, batches cut across aircraft and spans."""
    t0 = truth["time"].min()
    span = ((pl.col("time") - t0).dt.total_seconds() // span_s).alias("__span")
    return truth.with_columns(span).sort("__span", "truth_id", "time").drop("__span")


def _inside(laid: pl.DataFrame, first: bool) -> int:
    """A row of an aircraft that also has rows in an earlier batch: the first of its rows in a
    later batch (``first``), or one with rows of the same aircraft on both sides in its batch."""
    ids, batch = laid["truth_id"], pl.int_range(0, laid.height, eager=True) // BATCH
    for r in range(2 * BATCH, laid.height - 1):
        earlier = (ids.slice(0, int(batch[r]) * BATCH) == ids[r]).any()
        if not earlier:
            continue
        starts = r == 0 or ids[r - 1] != ids[r] or batch[r - 1] != batch[r]
        if first and starts:
            return r
        if not first and not starts and ids[r + 1] == ids[r] and batch[r + 1] == batch[r]:
            return r
    raise AssertionError("no such row")


def _spoilt(truth: pl.DataFrame, edge: bool) -> pl.DataFrame:
    """The laid-out truth with a NaN state inside a batch, a repeated (truth_id, time) next to
    its first row, and (``edge``) a NaN state on an aircraft's first row of a later batch."""
    laid = _spans_by_aircraft(truth)
    nan = [_inside(laid, first=False)] + ([_inside(laid, first=True)] if edge else [])
    x = laid["x_m"].to_list()
    for r in nan:
        x[r] = float("nan")
    laid = laid.with_columns(pl.Series("x_m", x))
    d = _inside(laid, first=False) + 40
    return pl.concat([laid.slice(0, d + 1), laid.slice(d, 1), laid.slice(d + 1)])


@pytest.mark.parametrize("edge", [False, True])
def test_truth_in_time_spans_streams_in_one_pass_as_one_call(truth, monkeypatch, tmp_path, edge):
    """A truth a time span per stretch, each sorted by aircraft, with a NaN state and a repeated
    key inside a batch and times before the reports' span: one pass gives the reference of one
    call (rows, input order, every sample's neighbour times across batches) and its rejects,
    without filing rows by aircraft part. A NaN on an aircraft's first row of a later batch
    decides its neighbour time in the batch before: the parts then do it, with the same result.
    Fails if a batch's first or last sample per aircraft takes no neighbour from the batches
    around it, if the carried last sample is not the last clean one, or if the edge is not
    caught (the earlier batch's last sample would name the rejected row's time as its next)."""
    bad = _spoilt(truth, edge)
    bad.write_parquet(tmp_path / "truth.parquet")
    t0, t1 = truth["time"].min(), truth["time"].max()
    window = (t0 + timedelta(seconds=20), t1, "the reports' span")
    cfg = pipeline.PipelineConfig()
    notes1: list[str] = []
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 10**9)
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 10**9)
    clean, rej = ingestion.validate_truth(SimpleNamespace(truth=bad), cfg, notes1, window)
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 700)
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 0)
    monkeypatch.setattr(ingestion, "TRUTH_BATCH_ROWS", BATCH)
    filed: list[int] = []
    monkeypatch.setattr(ingestion, "_file_by_part", lambda *a, f=ingestion._file_by_part: filed.append(1) or f(*a))
    notes2: list[str] = []
    got = ingestion.stream_truth(SimpleNamespace(truth=pl.scan_parquet(tmp_path / "truth.parquet")), cfg, notes2,
                                 window, tmp_path / "scratch")
    assert got is not None
    on_disk, rej2 = got
    assert bool(filed) == edge                                   # one pass, unless a rejected row is an edge
    n_early = bad.filter(pl.col("time") < window[0]).height
    assert rej.height == n_early + 2 + edge and n_early > 0      # not vacuous
    assert len(reference_files(on_disk.reference)) >= 5 and not clean["truth_id"].is_sorted()
    assert on_disk.rows == clean.height
    assert_frame_equal(read_reference(on_disk.reference), clean)
    files = pl.read_parquet(reference_files(on_disk.reference))
    assert_frame_equal(files.select("time", "__prev", "__next"), neighbour_times(clean))
    assert_frame_equal(rej2.drop("detail"), rej.drop("detail"))
    # detail: the same values; a float column is spelt as text in a part holding a NaN
    num = lambda v: float(v) if isinstance(v, str) and v.replace(".", "").replace("-", "").isdigit() else v  # noqa: E731
    for a, b in zip(rej["detail"], rej2["detail"]):
        assert {k: num(v) for k, v in json.loads(a).items()} == {k: num(v) for k, v in json.loads(b).items()}
    assert notes2 == notes1


@pytest.mark.parametrize("case", ["step back", "narrow ids"])
def test_an_aircraft_back_in_an_earlier_time_goes_by_parts(truth, monkeypatch, tmp_path, case):
    """An aircraft whose times step back across batches (or repeat a key of an earlier batch):
    one pass could not keep the first row of the key, so the parts do it, and the reference is
    one call's. Ids of another integer type than the contract's go through the one pass (its
    carried ids and the batches' cast ones join) to the same reference. Fails if the order pass
    lets the step back through, or if narrow ids were refused the one pass or changed it."""
    laid = _spans_by_aircraft(truth)
    bad = (pl.concat([laid, laid.slice(10, 1)]) if case == "step back"      # a key of the first batch, repeated at the end
           else laid.with_columns(pl.col("truth_id").cast(pl.Int32)))
    bad.write_parquet(tmp_path / "truth.parquet")
    window = (truth["time"].min(), truth["time"].max(), "the reports' span")
    cfg = pipeline.PipelineConfig()
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 10**9)
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 10**9)
    clean, rej = ingestion.validate_truth(SimpleNamespace(truth=bad), cfg, [], window)
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 700)
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 0)
    monkeypatch.setattr(ingestion, "TRUTH_BATCH_ROWS", BATCH)
    if case == "step back":
        assert ingestion._batch_order(pl.scan_parquet(tmp_path / "truth.parquet")) is None
    filed: list[int] = []
    monkeypatch.setattr(ingestion, "_file_by_part", lambda *a, f=ingestion._file_by_part: filed.append(1) or f(*a))
    on_disk, rej2 = ingestion.stream_truth(SimpleNamespace(truth=pl.scan_parquet(tmp_path / "truth.parquet")), cfg,
                                           [], window, tmp_path / "scratch")
    assert rej.height == (case == "step back") and bool(filed) == (case == "step back")
    assert_frame_equal(read_reference(on_disk.reference), clean)
    assert_frame_equal(rej2.drop("detail"), rej.drop("detail"))
