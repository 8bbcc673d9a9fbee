"""The windowed engine (7): a windowed run's tables equal a one-window run's,
table by table; a killed run resumed from its last complete window ends identical to an
uninterrupted one; incomplete runs say so; batch progress gives one line per window."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from polars.testing import assert_frame_equal

from safety import alerts as safety_alerts
from tertiary import pipeline
from tertiary.pipeline import (ingestion, plan, runner, safety_scoring, scoring, streaming, tables, whole_run,
                               window_evaluation)
from tertiary.core.stage import T_MAX_US
from tertiary.runtime.windows import US, Window, incomplete_message, windows
from tertiary.io.dataset import write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore

#: each table's row key (rows are compared after sorting by it; floats to round-off)
KEYS = {
    "reports": ["run", "report_id"],
    "rejects": ["input_table", "row_index", "stage", "reason"],
    "aligned": ["run", "epoch", "radar_id", "local_track_id", "report_id"],
    "associations": ["run", "epoch", "radar_id", "local_track_id", "report_id"],
    "fused": ["run", "method", "epoch", "target_id"],
    "clusters": ["run", "method", "epoch", "cluster_id"],
    "tracks": ["run", "method", "filter", "epoch", "track_id"],
    "conflicts": ["run", "method", "epoch", "id_a", "id_b"],
    "alerts": None,
    "metrics": ["stage", "method", "metric", "segment"],
}

#: the stages' exactness is checked on these (no reference: the whole-run stages are the same code)
FAST = pipeline.PipelineConfig(stca_lookaheads_s=(), evaluation=False)


def _same(a: pl.DataFrame, b: pl.DataFrame, name: str) -> None:
    assert a.shape == b.shape, f"{name}: {a.shape} rows/columns windowed vs {b.shape} in one window"
    if a.height == 0:
        return
    keys = KEYS.get(name) or [c for c, t in a.schema.items() if t.is_integer() or t == pl.String or t == pl.Boolean
                              or isinstance(t, pl.Datetime)]
    keys = [k for k in keys if k in a.columns]
    a, b = a.sort(keys, nulls_last=True), b.select(a.columns).sort(keys, nulls_last=True)
    assert_frame_equal(a, b, check_dtypes=False, rel_tol=1e-9, abs_tol=1e-6)


def _tables(res: pipeline.Results) -> dict[str, pl.DataFrame]:
    return {"reports": res.ingested.reports, "rejects": res.rejects, "aligned": res.aligned,
            "associations": res.associations, "fused": res.fused, "clusters": res.clusters, "tracks": res.tracks,
            "conflicts": res.conflicts, "alerts": res.alerts, "metrics": res.metrics}


@pytest.fixture(scope="module")
def terminal():
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=420.0,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=30, conflict_pairs=3))
    return simulate(cfg)


@pytest.fixture(scope="module")
def bigbox():
    cfg = load_scenario("big-box")
    return simulate(dataclasses.replace(cfg, runs=3, duration_s=240.0))


@pytest.fixture(scope="module")
def terminal_whole(terminal):
    return _tables(pipeline.process(terminal, FAST, window_s=None))


@pytest.mark.parametrize("window_s", [5.0, 47.0, 150.0])
def test_windowed_tables_equal_one_window_terminal_area(terminal, terminal_whole, window_s):
    """5 s is shorter than the slowest scan period (12 s): most windows hold part of a scan."""
    got = _tables(pipeline.process(terminal, FAST, window_s=window_s))
    for name, frame in terminal_whole.items():
        _same(got[name], frame, name)


@pytest.mark.parametrize("window_s", [7.0, 100.0])
def test_windowed_tables_equal_one_window_big_box(bigbox, window_s):
    whole = _tables(pipeline.process(bigbox, FAST, window_s=None))
    got = _tables(pipeline.process(bigbox, FAST, window_s=window_s))
    assert whole["tracks"].height and whole["fused"].height
    for name, frame in whole.items():
        _same(got[name], frame, name)


def test_a_given_registration_is_applied_window_by_window_as_in_one_window(terminal):
    """A registration table given up front (``tertiary register`` beforehand) needs nothing from
    the whole recording: the run keeps its windows, and they equal one window, clock offsets that
    move a report across a window's edge included."""
    ids = terminal.radars["radar_id"].to_list()
    rows = tuple((float(r), 10.0 * (-1) ** i, 0.02 * (-1) ** i, 0.06 * (-1) ** i, 0.0) for i, r in enumerate(ids))
    cfg = dataclasses.replace(FAST, register=True, registration=rows)
    whole = _tables(pipeline.process(terminal, cfg, window_s=None))
    res = pipeline.process(terminal, cfg, window_s=47.0)
    notes = res.ingested.notes
    assert not any(n.startswith("processed as one window") for n in notes), notes
    assert sum(n.startswith("registration (given) radar") for n in notes) == len(ids), notes
    got = _tables(res)
    for name, frame in whole.items():
        _same(got[name], frame, name)


def test_the_carried_reference_keeps_only_targets_that_can_return(terminal, monkeypatch):
    """Memory bounded by the window: after the last window the centralised reference carries only
    the targets the association can still continue (those a carried local track points at), not
    every target ever seen — the windowed tables above equal one window's with it."""
    seen = {}
    real = runner.finalize_stages

    def spy(ds, cfg, ctx, st, *args, **kw):
        seen["st"] = st
        return real(ds, cfg, ctx, st, *args, **kw)
    monkeypatch.setattr(runner, "finalize_stages", spy)
    res = pipeline.process(terminal, FAST, window_s=20.0)
    st = seen["st"]
    kept = st.centralized.targets.select("run", "target_id")
    ever = res.fused.filter(pl.col("method") == "centralized").select("run", "target_id").unique()
    assert kept.join(st.associate.live_targets(), on=["run", "target_id"], how="anti").height == 0
    assert 0 < kept.height < ever.height / 2
    assert st.centralized.radars.join(kept, on=["run", "target_id"], how="anti").height == 0


def test_association_metrics_are_scored_window_by_window(terminal, terminal_whole, monkeypatch):
    """evaluation accumulators: the association metrics come from the state the
    windows carry (:class:`tertiary.evaluation.association.AssociationScore`), not from the whole run's rows
    read back in finalize — the whole-run function is not called — and equal one window's."""
    def whole_run_scored(*_a, **_k):
        raise AssertionError("association rows scored in finalize")
    monkeypatch.setattr(whole_run, "association_metrics", whole_run_scored)
    got = pipeline.process(terminal, FAST, window_s=5.0)
    rows = got.metrics.filter(pl.col("stage") == "association")
    assert {"assoc_correct_frac", "swaps", "false_targets", "gated_pairs"} <= set(rows["metric"])
    _same(rows, terminal_whole["metrics"].filter(pl.col("stage") == "association"), "metrics")


def test_windowed_evaluation_equals_one_window(terminal):
    """The whole-run stages (matching, accuracy, alert scoring, STCA curves) on windowed tables."""
    cfg = pipeline.PipelineConfig(stca_lookaheads_s=(105.0,))
    whole = pipeline.process(terminal, cfg, window_s=None)
    got = pipeline.process(terminal, cfg, window_s=60.0)
    _same(got.metrics, whole.metrics, "metrics")
    _same(got.alerts, whole.alerts, "alerts")
    assert got.counts == whole.counts


def test_stca_curves_predicted_by_the_windows_equal_the_whole_run_prediction(terminal, monkeypatch):
    """Every point of the STCA curves is predicted window by window (one carried state per
    setting) and only scored at the end: the curves equal those of the prediction run on the
    whole picture after the windows. Fails if a setting's state is not carried, if a window's
    rows are dropped or given to another setting, or if the scoring reads them differently."""
    cfg = pipeline.PipelineConfig(stca_lookaheads_s=(90.0, 120.0))
    streamed_rows: list[int] = []
    monkeypatch.setattr(safety_scoring, "stca_curves", lambda *a, f=safety_scoring.stca_curves:
                        streamed_rows.append(-1 if a[-1] is None else a[-1](0).height) or f(*a))
    got = pipeline.process(terminal, cfg, window_s=60.0)
    monkeypatch.setattr(streaming, "stca_settings", lambda _cfg: ())     # the windows predict no curve
    end = pipeline.process(terminal, cfg, window_s=60.0)
    assert streamed_rows[0] > 0 and streamed_rows[1] == -1
    curve = got.metrics.filter(pl.col("stage") == "safety_tradeoff")
    assert curve.height == end.metrics.filter(pl.col("stage") == "safety_tradeoff").height > 0
    assert curve.filter(pl.col("metric") == "nuisance_false_per_hour")["value"].n_unique() > 3
    _same(got.metrics, end.metrics, "metrics")


def test_on_disk_finalize_equals_in_memory(terminal, tmp_path, monkeypatch):
    """An on-disk run validates the truth before its windows and matches every picture to it as
    the windows make them; its finalize only reduces the matched rows to metrics, a picture at a
    time, and never reads a picture back: the same metrics, alerts, requirements and counts as the
    in-memory run, which matches and scores every picture whole at the end. Fails if a picture
    is skipped or matched differently in the windows. The truth goes from disk to disk too
    (validated in parts, scored from its reference files): the run database's truth is the
    in-memory run's."""
    read, blocks, streamed, copies = [], [], [], []
    # several pictures: the parts are not copied by picture when no picture is read back
    monkeypatch.setattr(pl.DataFrame, "write_parquet", lambda self, f, *a, w=pl.DataFrame.write_parquet, **k:
                        (copies.append(str(f)) if "_by_picture_" in str(f) else None) or w(self, f, *a, **k))

    def counted(self, key, *a, f=tables.OnDiskTable.blocks, **k):
        read.append((self.name, key, "blocks"))
        for b in f(self, key, *a, **k):
            blocks.append((self.name, key))
            yield b

    monkeypatch.setattr(tables.OnDiskTable, "picture", lambda self, key, *a, f=tables.OnDiskTable.picture:
                        read.append((self.name, key, "whole")) or f(self, key, *a))
    monkeypatch.setattr(tables.OnDiskTable, "blocks", counted)
    monkeypatch.setattr(tables, "EVAL_BLOCK_ROWS", 500)        # several blocks per picture
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 1_000)      # the truth in parts and batches
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 0)
    monkeypatch.setattr(ingestion, "TRUTH_BATCH_ROWS", 1_500)
    monkeypatch.setattr(ingestion, "stream_truth", lambda *a, f=ingestion.stream_truth: streamed.append(f(*a))
                        or streamed[-1])
    windowed, seeded = [], []
    monkeypatch.setattr(scoring.WindowedPictures, "__call__", lambda self, name, f=scoring.WindowedPictures.__call__:
                        windowed.append(name) or f(self, name))
    monkeypatch.setattr(scoring.WindowedPictures, "_seed_tables", lambda self, name, *a,
                        f=scoring.WindowedPictures._seed_tables: seeded.append(name) or f(self, name, *a))
    from tertiary.evaluation import bound
    bound_reads: list[tuple[bool, int]] = []         # (from a scan, aircraft) of each truth read

    def truth_reads(truth, ids, f=bound._truth_reads):
        for read, rows in f(truth, ids):
            bound_reads.append((isinstance(truth, pl.LazyFrame), len(read)))
            yield read, rows
    monkeypatch.setattr(bound, "_truth_reads", truth_reads)
    monkeypatch.setattr(bound, "BOUND_READ_AIRCRAFT", 7)
    # on disk the windows carry every aircraft's recursion, reading the truth from the reference
    # a stretch at a time; the end takes the aircraft still flying to the end of their truth
    from tertiary.evaluation import bound_streamed
    stretches: list[tuple[int, int | None, int]] = []          # (from µs, to µs, rows) of each read
    monkeypatch.setattr(bound_streamed, "_read_truth", lambda setup, lo, hi, f=bound_streamed._read_truth:
                        stretches.append((lo, hi, (got := f(setup, lo, hi)).height)) or got)
    monkeypatch.setattr(bound_streamed, "ADVANCE_S", 60.0)          # several stretches in a short run
    # the on-disk run's evaluation keeps the id-map rows of the alerts and curve points alone
    kept: list[int] = []
    monkeypatch.setattr(safety_alerts, "id_rows", lambda ids, keys, id_col, f=safety_alerts.id_rows:
                        kept.append(keys.height) or f(ids, keys, id_col))
    # the truth's separation intervals: the chunks the windows passed computed there, the rest
    # at the end from their state
    steps, finished = [], []
    monkeypatch.setattr(window_evaluation, "intervals_step", lambda *a, f=window_evaluation.intervals_step: steps.append(a[-1])
                        or f(*a))
    monkeypatch.setattr(safety_scoring, "reference_intervals", lambda *a, f=safety_scoring.reference_intervals, **k:
                        finished.append(k.get("state")) or f(*a, **k))
    # the truth picture: predicted in the windows but for their last stretch, never whole at the end
    truth_rows, whole_truth = [], []
    monkeypatch.setattr(window_evaluation, "truth_picture_step", lambda *a, f=window_evaluation.truth_picture_step, **k:
                        truth_rows.append(f(*a, **k)) or truth_rows[-1])
    monkeypatch.setattr(safety_scoring, "truth_conflicts", lambda *a, f=safety_scoring.truth_conflicts, **k:
                        whole_truth.append(a[3].height) or f(*a, **k))
    # the scored samples are read back for the bound only: not once the windows made it
    read_samples: list[pl.LazyFrame] = []

    def counted_samples(frame, f=scoring.scored_samples):
        if isinstance(frame, pl.LazyFrame):            # the windows' stored samples, read back
            read_samples.append(frame)
        return f(frame)
    monkeypatch.setattr(scoring, "scored_samples", counted_samples)
    # τ's lag sums: each track's series summed in the windows once no window scored it for 120 s,
    # 20 series at least at a time, the rest in the last window; nothing left for the end
    from tertiary.evaluation import lags_streamed
    lag_batches: list[int] = []
    monkeypatch.setattr(lags_streamed, "SERIES_BATCH", 20)
    monkeypatch.setattr(lags_streamed, "SERIES_DONE_S", 120.0)
    monkeypatch.setattr(lags_streamed, "_summed", lambda state, due, *a, f=lags_streamed._summed:
                        lag_batches.append(due.height) or f(state, due, *a))
    end_lags: list[tuple[int, bool]] = []          # (rows summed at the end, sums carried)
    monkeypatch.setattr(scoring, "statistic_lags", lambda scan, rows, carried=None, f=scoring.statistic_lags:
                        end_lags.append((rows, carried is not None)) or f(scan, rows, carried))
    # the aircraft still flying at the end are bounded on a thread of their own, beside the
    # end's evaluation
    import threading
    finishing: list[str] = []
    monkeypatch.setattr(whole_run, "bound_finish", lambda *a, f=whole_run.bound_finish:
                        finishing.append(threading.current_thread().name) or f(*a))
    # the reports are not read back once the windows scored the associations and made the bound
    read_back: list[str] = []
    monkeypatch.setattr(whole_run, "table_columns", lambda parts, name, *a, f=whole_run.table_columns:
                        read_back.append(name) or f(parts, name, *a))
    cfg = pipeline.PipelineConfig(stca_lookaheads_s=(105.0,))
    mem = pipeline.process(terminal, cfg, window_s=60.0)
    assert bound_reads == [(False, bound_reads[0][1])]
    assert steps == [] and finished == []            # in memory: the whole truth's at the end
    assert truth_rows == [] and len(whole_truth) == 1
    pipeline.run(terminal, tmp_path / "run", cfg, window_s=60.0)
    assert len(whole_truth) == 1 and len(truth_rows) > 4
    assert read_samples == [] and finishing == ["bound_0"]
    assert "reports" not in read_back
    assert len(lag_batches) > 2 and all(n >= 20 for n in lag_batches[:-1])
    assert end_lags == [(0, True)]
    windows_alerts = [out["truth_conflicts"]["alert"].sum() for out, _ in truth_rows if "truth_conflicts" in out]
    assert sum(windows_alerts) > 0 and all(s.complete for _, s in truth_rows)
    # the bound's truth read from the reference on disk in stretches that follow one another, the
    # last at the end, each sample once; never the whole-run stage's reads
    assert len(bound_reads) == 1 and len(stretches) > 2 and stretches[-1][1] is None
    assert all(a[1] == b[0] for a, b in zip(stretches, stretches[1:]))
    assert sum(n for *_, n in stretches) == mem.ingested.truth.height
    assert len(streamed) == 1 and streamed[0] is not None and streamed[0][0].rows > 3 * 1_500
    assert len(kept) == 1 and kept[0] > 0        # every tracker picture's id map in one pass
    with RunStore.open(tmp_path / "run") as st:
        metrics, alerts, record = st.read("metrics"), st.read("alerts"), st.read("run")
        assert_frame_equal(st.read("truth"), mem.ingested.truth)
    assert metrics.filter(pl.col("stage") == "tracker")["method"].n_unique() == 2 * len(cfg.methods)
    _same(metrics, mem.metrics, "metrics")
    _same(alerts, mem.alerts, "alerts")
    rows = json.loads(record.filter(pl.col("key") == "rows")["value"][0])
    assert rows == json.loads(json.dumps(mem.counts))
    # every picture matched in the windows (each fusion method, the centralised reference, each
    # tracker picture) and its seed metrics stepped there, none read back for the evaluation;
    # the windows predicted the curves
    assert sorted(windowed) == sorted([*cfg.methods, "centralized",
                                       *(f"{m}+{f}" for m in cfg.methods for f in cfg.filters)])
    assert sorted(seeded) == sorted(windowed)
    assert read == [] and blocks == [] and copies == []
    assert len(steps) > 4 and steps == sorted(steps)
    [done] = finished
    assert done is not None and done.merged is not None and done.next_us >= steps[0]


def test_one_picture_on_disk_is_read_in_place_and_scores_as_in_memory(terminal, tmp_path, monkeypatch):
    """A run of one fusion method and one filter: its fused and tracks parts each hold one
    picture, so finalize reads them where they are instead of regrouping them into copies
    (a national day's copies were ~15 GB). The same metrics, alerts and counts as the
    in-memory run; fails if a part is skipped or the in-place reader reads other rows."""
    copies: list[str] = []
    monkeypatch.setattr(pl.DataFrame, "write_parquet", lambda self, f, *a, w=pl.DataFrame.write_parquet, **k:
                        (copies.append(str(f)) if "_by_picture_" in str(f) else None) or w(self, f, *a, **k))
    monkeypatch.setattr(tables, "EVAL_BLOCK_ROWS", 500)
    # a curve point with a wide margin alerts on pairs the production setting never alerts on:
    # the on-disk evaluation keeps their id-map rows too
    cfg = pipeline.PipelineConfig(methods=("information",), filters=("singer",), centralized=False,
                                  stca_lookaheads_s=(105.0,), stca_fixed_m=(0.0, 4000.0))
    mem = pipeline.process(terminal, cfg, window_s=60.0)
    made: list = []
    monkeypatch.setattr(tables.OnDiskTable, "__init__", lambda self, *a, f=tables.OnDiskTable.__init__:
                        f(self, *a) or made.append(self))
    predicted, kept = [], []        # the curve points' rows as the windows keep them; the kept id map
    monkeypatch.setattr(plan, "scored_conflicts", lambda c, f=plan.scored_conflicts: predicted.append(f(c))
                        or predicted[-1])
    monkeypatch.setattr(safety_alerts, "id_rows", lambda ids, keys, id_col, f=safety_alerts.id_rows:
                        kept.append(f(ids, keys, id_col).collect()) or kept[-1].lazy())
    # the safety picture's id map is read from the blocks the windows reduced, not its matched rows
    blocks: list[int] = []
    monkeypatch.setattr(scoring.WindowedPictures, "_ids", lambda self, *a, f=scoring.WindowedPictures._ids:
                        (got := f(self, *a)) is not None and blocks.append(got.collect().height) or got)
    pipeline.run(terminal, tmp_path / "run", cfg, window_s=60.0)
    assert blocks and len(set(blocks)) == 1 and 0 < blocks[0] < mem.tracks.height
    assert not copies
    # every alert of every curve point finds its ids in the kept id map
    on = ["run", "method", "epoch", "track_id"]
    alerting = safety_alerts.alert_ids(pl.concat(predicted), "track_id")
    assert len(kept) == 1 and kept[0].height < mem.tracks.height
    assert alerting.height > 0 and alerting.join(kept[0].select(on), on=on, how="anti").height == 0
    assert {d.name for d in made} == {"fused", "tracks"} and all(d.direct for d in made)
    with RunStore.open(tmp_path / "run") as st:
        _same(st.read("metrics"), mem.metrics, "metrics")
        _same(st.read("alerts"), mem.alerts, "alerts")
        record = st.read("run")
    rows = json.loads(record.filter(pl.col("key") == "rows")["value"][0])
    assert rows == json.loads(json.dumps(mem.counts))


def test_empty_window_in_the_middle(terminal, terminal_whole):
    """A silence longer than a window (no report for 90 s): empty windows carry the state unchanged."""
    from datetime import timedelta
    reports = terminal.reports
    start = reports["time"].min() + timedelta(seconds=180)
    cut = reports.filter((pl.col("time") < start) | (pl.col("time") >= start + timedelta(seconds=90)))
    ds = dataclasses.replace(terminal, reports=cut)
    whole = _tables(pipeline.process(ds, FAST, window_s=None))
    got = _tables(pipeline.process(ds, FAST, window_s=20.0))
    for name, frame in whole.items():
        _same(got[name], frame, name)


def test_windows_cover_the_grid_and_the_last_is_open():
    ws = list(windows(10 * US, 10 * US + 95 * US, 30.0))
    assert [w.index for w in ws] == [0, 1, 2, 3]
    assert ws[0].open_start and ws[-1].t1_us == T_MAX_US and ws[-1].last
    assert all(a.t1_us == b.t0_us for a, b in zip(ws, ws[1:]))
    assert ws[1].t0_us == 40 * US
    assert list(windows(0, 5 * US, None)) == [Window.unbounded()]


# --------------------------------------------------------------------------- run store, resume


def _db_tables(run_dir: Path) -> dict[str, pl.DataFrame]:
    with RunStore.open(run_dir) as store:
        return {n: store.read(n) for n in store.tables() if n != "run"}


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory, terminal):
    return write_dataset(terminal, tmp_path_factory.mktemp("ds") / "ta")


def _cli(*args: str, env=None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tertiary.cli.main", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "COLUMNS": "200", **(env or {})})


RUN_ARGS = ("--filters", "singer", "--methods", "information,arithmetic", "--no-report", "--window", "20")


def test_killed_run_resumes_to_identical_tables(dataset_dir, tmp_path):
    ref = tmp_path / "ref"
    p = _cli("run", str(dataset_dir), "--out", str(ref), *RUN_ARGS)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    killed = tmp_path / "killed"
    p = _cli("run", str(dataset_dir), "--out", str(killed), *RUN_ARGS)
    deadline = time.time() + 300
    while time.time() < deadline:       # kill once a few windows are complete, mid-run
        m = killed / "manifest.json"
        if m.is_file() and json.loads(m.read_text()).get("windows_done", 0) >= 3:
            break
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.wait(timeout=60)
    manifest = json.loads((killed / "manifest.json").read_text())
    assert manifest["status"] == "running" and 3 <= manifest["windows_done"] < 22
    assert "incomplete" in incomplete_message(killed)
    q = _cli("sql", str(killed), "--query", "SELECT 1")
    _, err = q.communicate(timeout=120)
    assert q.returncode != 0 and "incomplete" in err
    # a checkpoint whose windows did not all write their block of the safety id map (as one
    # written before the windows wrote it): the end reads the id map from the matched rows
    older = tmp_path / "older"
    shutil.copytree(killed, older)
    import pickle

    from tertiary.runtime.windows import STATE_FILE
    saved = pickle.loads((older / STATE_FILE).read_bytes())
    assert saved["state"].id_rows is True
    saved["state"] = dataclasses.replace(saved["state"], id_rows=None)
    (older / STATE_FILE).write_bytes(pickle.dumps(saved))
    shutil.rmtree(older / "parts" / "id_rows")
    for run_dir in (killed, older):
        r = _cli("run", str(dataset_dir), *RUN_ARGS, "--resume", str(run_dir))
        out, err = r.communicate(timeout=600)
        assert r.returncode == 0, err
        assert "resuming after window" in out
        assert json.loads((run_dir / "manifest.json").read_text())["status"] == "complete"
        assert not (run_dir / "parts").exists()
        a, b = _db_tables(run_dir), _db_tables(ref)
        assert set(a) == set(b)
        for name in a:
            _same(a[name], b[name], name if name in KEYS else "")


def test_windows_are_stored_behind_the_run_in_order_with_the_state_they_were_given(tmp_path):
    """The window store writes a window's parts and state while the next window computes: the
    manifest names a window complete only after its parts, windows in order, the state stored
    is the one handed over (the next window may change the arrays it holds), and a failed
    write stops the run. Fails if the state were pickled on the writer's thread (window 0's
    array would be stored as the caller changed it), or a write's error were lost."""
    import pickle

    import numpy as np

    from tertiary.runtime.windows import STATE_FILE, PartStore
    events: list[tuple[str, int]] = []

    class Recorded(PartStore):
        def write(self, w, outputs):
            time.sleep(0.05)                       # the caller goes on meanwhile
            if w.index == 2:
                raise OSError("disk full")
            events.append(("parts", w.index))
            super().write(w, outputs)

        def commit(self, w, state, **info):
            events.append(("manifest", w.index))
            super().commit(w, state, **info)
    parts = Recorded.start(tmp_path, {"dataset": "x"})
    store = streaming.WindowStore(parts)
    held = {"x": np.zeros(3)}
    store.put(Window(0, 0, 10), {"t": pl.DataFrame({"a": [1]})}, held)
    held["x"][:] = 7.0                             # the next window changes the state's arrays
    store.join()
    with open(tmp_path / STATE_FILE, "rb") as fh:
        saved = pickle.load(fh)
    assert saved["windows_done"] == 1 and saved["state"]["x"].tolist() == [0.0, 0.0, 0.0]
    store.put(Window(1, 10, 20), {"t": pl.DataFrame({"a": [2]})}, held)
    store.put(Window(2, 20, 30), {"t": pl.DataFrame({"a": [3]})}, held)
    with pytest.raises(OSError, match="disk full"):
        store.join()
    store.close()
    assert events == [("parts", 0), ("manifest", 0), ("parts", 1), ("manifest", 1)]
    assert json.loads((tmp_path / "manifest.json").read_text())["windows_done"] == 2


def test_a_window_is_evaluated_on_a_thread_of_its_own_while_the_next_is_processed(terminal, tmp_path, monkeypatch):
    """On disk, window k's evaluation runs beside window k + 1's processing, in window order
    (its tables equal the in-memory run's: :func:`test_on_disk_finalize_equals_in_memory`).
    Each evaluation waits for the next window's processing to start: fails if the evaluation
    ran on the caller's thread or the caller waited for it before processing the next window."""
    import threading
    started: dict[int, threading.Event] = {}
    seen: list[tuple[int, str, bool]] = []

    def process(cfg, ctx, st, raw, w, *a, f=streaming.process_step):
        started.setdefault(w.index, threading.Event()).set()
        return f(cfg, ctx, st, raw, w, *a)

    def evaluate(cfg, ctx, st, h, w, clock, f=streaming.evaluate_step):
        beside = w.t1_us >= T_MAX_US or started.setdefault(w.index + 1, threading.Event()).wait(10.0)
        seen.append((w.index, threading.current_thread().name, beside))
        return f(cfg, ctx, st, h, w, clock)
    monkeypatch.setattr(streaming, "process_step", process)
    monkeypatch.setattr(streaming, "evaluate_step", evaluate)
    pipeline.run(terminal, tmp_path / "run", FAST, window_s=60.0)
    n = json.loads((tmp_path / "run" / "manifest.json").read_text())["windows_done"]
    assert n > 4 and [i for i, _, _ in seen] == list(range(n))
    assert all(name.startswith("window-evaluation") and beside for _, name, beside in seen), seen


@pytest.mark.parametrize("half", ["evaluation", "processing"])
def test_a_failure_in_either_half_names_its_stage_and_loses_no_window_before_it(terminal, tmp_path, monkeypatch, half):
    """A failing evaluation of window 2 stops the run with two windows stored and its stage
    named; a failing processing of window 3 still stores window 2, evaluated beside it. Fails
    if the window in flight were dropped on a failure or the evaluation's stage name lost."""
    def evaluate(cfg, ctx, st, h, w, clock, f=streaming.evaluate_step):
        if half == "evaluation" and w.index == 2:
            clock.stage("match_pictures")
            raise RuntimeError("boom")
        return f(cfg, ctx, st, h, w, clock)

    def process(cfg, ctx, st, raw, w, clock, *a, f=streaming.process_step):
        if half == "processing" and w.index == 3:
            clock.stage("fuse")
            raise RuntimeError("boom")
        return f(cfg, ctx, st, raw, w, clock, *a)
    monkeypatch.setattr(streaming, "evaluate_step", evaluate)
    monkeypatch.setattr(streaming, "process_step", process)
    with pytest.raises(runner.StageError) as err:
        pipeline.run(terminal, tmp_path / "run", FAST, window_s=60.0)
    assert err.value.stage == ("match_pictures" if half == "evaluation" else "fuse")
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["windows_done"] == (2 if half == "evaluation" else 3)


@pytest.mark.parametrize("stage", ["truth_picture", "truth_intervals"])
def test_a_failure_beside_the_matching_names_its_stage(terminal, tmp_path, monkeypatch, stage):
    """The truth picture runs on a thread beside the matching (the truth's intervals on the
    matching's): either failing in window 2 stops the run there with its own stage named and the
    windows before it stored. Fails if the side thread's failure were lost or named after the
    matching's stage."""
    target = {"truth_picture": "truth_picture_step", "truth_intervals": "intervals_step"}[stage]
    calls = []

    def failing(*a, f=getattr(window_evaluation, target), **k):
        calls.append(1)
        if len(calls) == 3:                               # once per window: the third window's
            raise RuntimeError("boom")
        return f(*a, **k)
    monkeypatch.setattr(window_evaluation, target, failing)
    cfg = pipeline.PipelineConfig(methods=("information",), filters=("singer",), stca_lookaheads_s=())
    with pytest.raises(runner.StageError) as err:
        pipeline.run(terminal, tmp_path / "run", cfg, window_s=60.0)
    assert err.value.stage == stage and "boom" in str(err.value)
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["windows_done"] == 2


def test_checkpoints_paced_by_their_cost_resume_to_the_same_tables(terminal, tmp_path, monkeypatch):
    """A state whose checkpoint costs more than CHECKPOINT_FREE_S is checkpointed once the time
    since the last one is its cost over CHECKPOINT_SHARE (made to mean: the first and last
    windows only). The tables are those of a run checkpointing every window; a run failing
    between checkpoints names the last checkpointed window done, and its resume drops the later
    windows' parts and ends with the same tables. Fails if a window without a checkpoint lost
    its parts or its evaluation, or a resume started after a window whose state was not saved."""
    from tertiary.runtime.windows import PartStore
    cfg = pipeline.PipelineConfig(methods=("information",), filters=("singer",), stca_lookaheads_s=())
    pipeline.run(terminal, tmp_path / "ref", cfg, window_s=60.0)
    monkeypatch.setattr(streaming, "CHECKPOINT_FREE_S", 0.0)
    monkeypatch.setattr(streaming, "CHECKPOINT_SHARE", 1e-12)
    committed: list[int] = []
    monkeypatch.setattr(PartStore, "commit", lambda self, w, *a, f=PartStore.commit, **k:
                        committed.append(w.index) or f(self, w, *a, **k))
    pipeline.run(terminal, tmp_path / "paced", cfg, window_s=60.0)
    n = json.loads((tmp_path / "ref" / "manifest.json").read_text())["windows_done"]
    assert n > 4 and committed == [0, n - 1]

    def evaluate(cfg_, ctx, st, h, w, clock, f=streaming.evaluate_step):
        if w.index == 4:
            raise RuntimeError("boom")
        return f(cfg_, ctx, st, h, w, clock)
    monkeypatch.setattr(streaming, "evaluate_step", evaluate)
    with pytest.raises(runner.StageError):
        pipeline.run(terminal, tmp_path / "failed", cfg, window_s=60.0)
    assert json.loads((tmp_path / "failed" / "manifest.json").read_text())["windows_done"] == 1
    assert (tmp_path / "failed" / "parts" / "tracks" / "w=000003.parquet").is_file()
    monkeypatch.undo()
    pipeline.run(terminal, tmp_path / "failed", cfg, window_s=60.0, resume=True)
    ref = _db_tables(tmp_path / "ref")
    for run_dir in ("paced", "failed"):
        got = _db_tables(tmp_path / run_dir)
        assert set(got) == set(ref)
        for name in ref:
            _same(got[name], ref[name], name if name in KEYS else "")


def test_resume_refuses_other_options(dataset_dir, tmp_path):
    run_dir = tmp_path / "r"
    (run_dir).mkdir()
    (run_dir / "manifest.json").write_text(json.dumps({"status": "running", "windows_done": 0,
                                                       "config_hash": "x", "tables": {}}))
    p = _cli("run", str(dataset_dir), *RUN_ARGS, "--resume", str(run_dir))
    _, err = p.communicate(timeout=300)
    assert p.returncode == 2 and "another configuration" in err


def test_batch_progress_one_line_per_window(dataset_dir, tmp_path):
    p = _cli("run", str(dataset_dir), "--out", str(tmp_path / "r"), *RUN_ARGS)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    lines = [ln for ln in out.splitlines() if "window " in ln and "reports/s" in ln]
    n = json.loads((tmp_path / "r" / "manifest.json").read_text())["windows_done"]
    assert len(lines) == n >= 20
    assert "RSS" in lines[-1] and "reports so far" in lines[-1]
    # where the memory goes: the peak by the end of each stage, the whole-run stages apart
    with RunStore.open(tmp_path / "r") as store:
        rec = dict(store.con.sql("SELECT key, value FROM run").fetchall())
    mem = json.loads(rec["memory_mib"])
    streamed = [v for k, v in mem.items() if not k.startswith("finalize:")]
    final = [v for k, v in mem.items() if k.startswith("finalize:")]
    # the copy of the streamed tables into the database is its own stage, not truth validation's
    assert {"align", "track", "finalize:validate", "finalize:write_tables", "finalize:evaluate"} <= set(mem)
    timings = json.loads(rec["timings"])
    assert timings["write_tables_s"] > 0
    assert min(streamed) > 50 and final == sorted(final) and final[0] >= max(streamed)
    p = _cli("run", str(dataset_dir), "--out", str(tmp_path / "j"), *RUN_ARGS, "--log-format", "json")
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    steps = [json.loads(ln)["step"] for ln in out.splitlines() if ln.startswith("{")]
    assert sum(s.startswith("window ") for s in steps) == n


def test_rejects_name_the_input_row_in_every_window(terminal):
    """Invalid rows spread over the recording: a window's rejects carry their row in the whole
    input (not their position in the window), and every report is aligned or rejected once."""
    reports = terminal.reports.with_row_index("__i")
    bad = reports["__i"].gather_every(97, offset=500)
    broken = reports.with_columns(
        pl.when(pl.col("__i").is_in(bad.implode())).then(-1.0).otherwise(pl.col("range_m")).alias("range_m")
    ).drop("__i")
    ds = dataclasses.replace(terminal, reports=broken)
    whole = pipeline.process(ds, FAST, window_s=None)
    got = pipeline.process(ds, FAST, window_s=30.0)
    ingest = got.rejects.filter(pl.col("stage") == "ingest")
    assert ingest.height >= bad.len() - 1 and set(bad.to_list()) <= set(ingest["row_index"].to_list())
    # ``detail`` is the rejected row as JSON: a float column is written as text when a row of the
    # same batch holds NaN/inf (schema.rejects_table), so its spelling depends on the window — the
    # values are the same
    _same(got.rejects.drop("detail"), whole.rejects.drop("detail"), "rejects")
    a, b = (r.sort("row_index")["detail"].str.json_decode() for r in (got.rejects, whole.rejects))
    assert a.struct.field("report_id").to_list() == b.struct.field("report_id").to_list()
    _same(got.aligned, whole.aligned, "aligned")


def test_engine_options_are_checked(dataset_dir, tmp_path):
    for extra, option in ((["--workers", "2"], "--workers"), (["--overlap", "300"], "--overlap"),
                          (["--engine", "spark"], "--engine"), (["--window", "0.5"], "--window"),
                          (["--window", "soon"], "--window")):
        p = _cli("run", str(dataset_dir), "--out", str(tmp_path / option.strip("-")), *extra)
        _, err = p.communicate(timeout=120)
        assert p.returncode == 2 and option in err, err


def test_window_read_is_pushed_into_the_parquet_scan(tmp_path):
    """A window of a partitioned input reads its own files, not all of them (the
    reading was quadratic in the number of windows): the coarse time test sits in the scan
    itself, under the input row index, and the window's rows are exactly the exact test's."""
    from tertiary.runtime.windows import INPUT_ROW, ReportSource
    t0 = 1_700_000_000_000_000
    files = []
    for k in range(3):
        f = tmp_path / f"part-{k}.parquet"
        us = t0 + k * 600 * US + pl.int_range(0, 600, eager=True) * US
        pl.DataFrame({"time": us.cast(pl.Datetime("us")).dt.replace_time_zone("UTC"),
                      "v": pl.int_range(0, 600, eager=True) + 1000 * k}).write_parquet(f)
        files.append(f)
    src = ReportSource(pl.scan_parquet(files))
    w = Window(1, t0 + 600 * US, t0 + 1200 * US)
    plan = src.lf.filter(src._near(w.t0_us, w.t1_us)).explain()
    assert plan.startswith("Parquet SCAN") and "SELECTION" in plan, plan
    got = src.rows(w)
    assert got["v"].to_list() == list(range(1000, 1600))
    assert got[INPUT_ROW].to_list() == list(range(600, 1200))      # global row numbers


def _spoilt_truth(truth: pl.DataFrame, unsorted: bool) -> pl.DataFrame:
    """``truth`` with the faults validation sees: repeated (truth_id, time), a NaN state, a
    missing id, times outside the reports' span and far from the median; with ``unsorted`` one
    aircraft's times decrease."""
    t_end = truth["time"].max()
    bad = pl.concat([
        truth,
        truth[[5, 400]],                                                  # duplicates of earlier rows
        truth[[7]].with_columns(pl.lit(float("nan")).alias("x_m")),
        truth[[9]].with_columns(pl.lit(None, truth.schema["truth_id"]).alias("truth_id")),
        truth[[11]].with_columns((pl.lit(t_end) + pl.duration(hours=5)).alias("time")),
        truth[[13]].with_columns((pl.lit(t_end) + pl.duration(days=5)).alias("time")),   # far from the median
    ])
    if not unsorted:
        return bad
    ids = bad["truth_id"].drop_nulls().unique().sort()
    first = bad.filter(pl.col("truth_id") == ids[3])
    return pl.concat([bad.filter(pl.col("truth_id").ne_missing(ids[3])), first.reverse()])  # one aircraft unsorted


def test_truth_validated_in_parts_equals_one_call(terminal, monkeypatch):
    """Finalize validates a long truth a few aircraft at a time (memory): the clean
    table (in input order), the rejects (their row_index and detail, the duplicate's first row
    named by its input position) and the unsorted-time note are those of one call. The truth is
    spoilt the ways validation sees: repeated (truth_id, time), a group out of time order, a NaN
    state, a missing id and a time outside the reports' span."""
    from types import SimpleNamespace
    truth = terminal.truth
    bad = _spoilt_truth(truth, unsorted=True)
    window = (truth["time"].min(), truth["time"].max(), "the reports' span")
    cfg = pipeline.PipelineConfig()
    results = []
    for rows in (10**9, 700):
        monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", rows)
        monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 10**9 if rows == 10**9 else 0)
        notes: list[str] = []
        clean, rej = ingestion.validate_truth(SimpleNamespace(truth=bad), cfg, notes, window)
        results.append((clean, rej, notes))
    (c1, r1, n1), (c2, r2, n2) = results
    assert r1.height == 6 and any("out of order" in n for n in n1)     # not vacuous
    assert r1.filter(pl.col("reason").str.contains("median")).height == 1
    assert c1.height > 0 and bad.height // 700 >= 3                     # several parts
    assert_frame_equal(c2, c1)
    assert_frame_equal(r2.drop("detail"), r1.drop("detail"))
    # detail: the same values; a float column is spelt as text in a batch holding a NaN
    num = lambda v: float(v) if isinstance(v, str) and v.replace(".", "").replace("-", "").isdigit() else v  # noqa: E731
    for a, b in zip(r1["detail"], r2["detail"]):
        assert {k: num(v) for k, v in json.loads(a).items()} == {k: num(v) for k, v in json.loads(b).items()}
    assert n2 == n1


@pytest.mark.parametrize("unsorted", [False, True])
def test_truth_streamed_to_disk_equals_one_call(terminal, monkeypatch, tmp_path, unsorted):
    """An on-disk run validates its truth from disk to disk (memory): batches of input
    rows filed by aircraft part, each part validated, the clean rows written as a reference in
    input batches (or, when an aircraft's times decrease, by part in (truth_id, time) order).
    With batches and parts that cut across each other, a time-major input (aircraft
    interleaved) read from a Parquet scan, and the faults validation sees, the reference holds
    exactly the clean table of one call (rows and order), each sample's neighbour times, and the
    rejects and notes are that call's. Fails if the batches are not merged back into input order
    (the time-major rows would come out by aircraft), a part's neighbour times cross aircraft, a
    row is lost between batch and part, or the unsorted note counts one part only."""
    from types import SimpleNamespace
    from tertiary.evaluation.evaluate import read_reference, reference_files
    from tertiary.evaluation.matching import neighbour_times
    bad = _spoilt_truth(terminal.truth, unsorted)
    if not unsorted:                               # time-major: the aircraft interleaved
        bad = bad.sort("time", maintain_order=True, nulls_last=True)
    bad.write_parquet(tmp_path / "truth.parquet")
    window = (terminal.truth["time"].min(), terminal.truth["time"].max(), "the reports' span")
    cfg = pipeline.PipelineConfig()
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 10**9)
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 10**9)
    notes1: list[str] = []
    clean, rej = ingestion.validate_truth(SimpleNamespace(truth=bad), cfg, notes1, window)
    monkeypatch.setattr(ingestion, "TRUTH_PART_ROWS", 700)
    monkeypatch.setattr(ingestion, "TRUTH_WHOLE_ROWS", 0)
    monkeypatch.setattr(ingestion, "TRUTH_BATCH_ROWS", 900)
    notes2: list[str] = []
    got = ingestion.stream_truth(SimpleNamespace(truth=pl.scan_parquet(tmp_path / "truth.parquet")), cfg, notes2,
                                 window, tmp_path / "scratch")
    assert got is not None
    on_disk, rej2 = got
    assert rej.height == 6 and clean.height > 3 * 900 and len(reference_files(on_disk.reference)) >= 3
    assert (any("out of order" in n for n in notes1)) == unsorted          # not vacuous
    if not unsorted:                                                        # the input order is kept
        assert not clean["truth_id"].is_sorted()
    assert on_disk.rows == clean.height
    assert_frame_equal(read_reference(on_disk.reference), clean)
    assert_frame_equal(pl.concat(list(on_disk.pieces())), clean)
    files = pl.read_parquet(reference_files(on_disk.reference))
    assert_frame_equal(files.select("time", "__prev", "__next"), neighbour_times(clean))
    assert_frame_equal(rej2.drop("detail"), rej.drop("detail"))
    assert notes2 == notes1
    assert not (tmp_path / "scratch" / "truth").exists()                   # the parts' files are gone


def test_truth_files_go_to_the_database_as_the_frame_path_would(tmp_path):
    """The store sink writes a streamed truth straight from its reference files, unless a column
    needs making storable (a user's extra Duration column): then it goes part by part through
    the same conversion as a frame, with its note. Fails if the files path skipped the
    conversion (the column would be stored as an INTERVAL, not Int64 microseconds)."""
    from tertiary.store.run_store import RunStore
    rows = pl.DataFrame({"truth_id": [1, 2], "__prev": [None, None],
                         "wait": pl.Series([1_500_000, 3], dtype=pl.Duration("us"))})
    plain = rows.drop("wait")
    for name, frame in (("with_duration", rows), ("plain", plain)):
        frame.write_parquet(tmp_path / f"{name}.parquet")
    notes: list[str] = []
    with RunStore.create(tmp_path / "run") as store:
        sink = pipeline.store_sink(store, notes)
        for name, frame in (("with_duration", rows), ("plain", plain)):
            sink(name, pipeline.StreamedTable(lambda f=frame: iter([f.drop("__prev")]),
                                              (tmp_path / f"{name}.parquet",), ("__prev",)))
        got = store.read("with_duration")
        assert got.schema["wait"] == pl.Int64 and got["wait"].to_list() == [1_500_000, 3]
        assert_frame_equal(store.read("plain"), plain.drop("__prev"))
    assert any("Duration stored as Int64" in n for n in notes)


def test_a_wide_truth_too_large_for_the_writers_pool_goes_part_by_part(tmp_path):
    """A streamed truth with many columns (a user's extra ones): DuckDB's scan of its files needs
    more buffer pool than the run database's writer has (a 4-hour run with 30 extra truth
    columns failed with OutOfMemoryException). The sink then writes it part by part (whose
    Arrow inserts run out of the pool too, and are retried with a larger one), and the table is
    whole, the database usable and no scratch view left. Fails if the scan's error escapes, or
    the inserts' (hidden before behind "Current transaction is aborted")."""
    import numpy as np
    from tertiary.store.run_store import RunStore
    n, k = 100_000, 80
    wide = pl.DataFrame({"truth_id": np.arange(n) // 1_000, "__prev": [None] * n,
                         **{f"extra_{i}": np.arange(n, dtype=float) * (i + 1) for i in range(k)}})
    halves = [wide.slice(0, n // 2), wide.slice(n // 2)]
    files = []
    for j, half in enumerate(halves):
        files.append(tmp_path / f"{j}.parquet")
        half.write_parquet(files[-1])
    with RunStore.create(tmp_path / "run") as store:
        sink = pipeline.store_sink(store, [])
        sink("truth", pipeline.StreamedTable(lambda: (h.drop("__prev") for h in halves), tuple(files), ("__prev",)))
        assert_frame_equal(store.read("truth"), wide.drop("__prev"))
        sink("after", pl.DataFrame({"x": [1]}))                    # the connection still writes
        assert store.read("after")["x"].to_list() == [1]
        left = store.con.sql("SELECT count(*) FROM duckdb_views() WHERE starts_with(view_name, '_tertiary_')")
        assert left.fetchall()[0][0] == 0                         # no scratch view held after the retry


def _timed_reports(n: int, span_s: float, t0_us: int = 1_700_000_000_000_000) -> pl.DataFrame:
    us = t0_us + (pl.int_range(0, n, eager=True).cast(pl.Float64) * (span_s * US / max(n - 1, 1))).cast(pl.Int64)
    return pl.DataFrame({"time": us.cast(pl.Datetime("us")).dt.replace_time_zone("UTC")})


def test_auto_window_holds_about_the_report_budget():
    """``--window auto``: windows of about the report budget (at the mean rate for a uniform
    recording), in whole minutes, within 60 s – 1 h; one report dated year 9999 does not stretch
    the span (it would make the window a thousand times longer), an untimed input gets the fixed
    default."""
    from tertiary.runtime.windows import (AUTO_WINDOW_BOUNDS_S, DEFAULT_WINDOW_S, ReportSource, auto_window_s, resolve_window)
    src = ReportSource(_timed_reports(36_000, 3600.0))                  # 10 reports/s
    assert auto_window_s(src, 6_000) == 600.0
    assert auto_window_s(src, 6_200) == 600.0                           # 620 s: whole minutes
    assert auto_window_s(src, 10) == AUTO_WINDOW_BOUNDS_S[0]           # a busy recording: short windows
    assert auto_window_s(src, 10_000_000) == AUTO_WINDOW_BOUNDS_S[1]   # a sparse one: long ones
    from datetime import datetime, timezone
    year_9999 = pl.DataFrame({"time": [datetime(9999, 1, 1, tzinfo=timezone.utc)]},
                             schema={"time": pl.Datetime("us", "UTC")})
    late = pl.concat([_timed_reports(36_000, 3600.0), year_9999])
    assert auto_window_s(ReportSource(late), 6_000) == 600.0
    assert auto_window_s(ReportSource(pl.DataFrame({"time": ["noon"] * 10})), 6_000) == DEFAULT_WINDOW_S
    assert resolve_window("auto", _timed_reports(36_000, 3600.0).lazy()) == auto_window_s(src)
    # five fusion methods: a fifth of the reports a window (each method adds its picture's rows)
    assert resolve_window("auto", _timed_reports(36_000, 3600.0), methods=5) == auto_window_s(src, 10_000) == 1020.0
    assert resolve_window(90, None) == 90.0 and resolve_window(None, None) is None


def test_auto_window_is_sized_by_the_busiest_stretch_not_the_mean():
    """A recording with a busy hour between two quiet ones: the mean rate would size windows that
    hold three times the budget at the peak; the auto window holds about the budget there (a
    window's memory grows with its rows: memory bounded by the window)."""
    from tertiary.runtime.windows import ReportSource, auto_window_s
    t0 = 1_700_000_000_000_000
    quiet = [_timed_reports(3_600, 3600.0, t0), _timed_reports(3_600, 3600.0, t0 + 7200 * US)]
    busy = _timed_reports(36_000, 3600.0, t0 + 3600 * US)                 # 10 reports/s
    src = ReportSource(pl.concat([quiet[0], busy, quiet[1]]))
    mean_rate = 43_200 / (3 * 3600.0)
    assert round(6_000 / mean_rate / 60) * 60 == 1500.0                   # what the mean gave
    w = auto_window_s(src, 6_000)
    assert w == 600.0
    counts = src.minute_counts()
    assert counts.sum() == src.n_rows and len(counts) == 181      # the last report opens minute 180
    m = int(w // 60)
    busiest = max(counts[i:i + m].sum() for i in range(len(counts) - m + 1))
    assert busiest <= 6_000 * 1.02


def test_the_default_run_window_is_the_auto_window(dataset_dir, tmp_path):
    """The CLI's default ``--window`` is ``auto``, resolved once from the dataset and recorded in
    the run record (which a resume compares)."""
    from tertiary.runtime.windows import ReportSource, auto_window_s
    from tertiary.io.dataset import read_dataset
    p = _cli("run", str(dataset_dir), "--out", str(tmp_path / "a"), "--filters", "", "--methods", "arithmetic",
             "--no-centralized", "--no-report", "--quiet")
    _, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    with RunStore.open(tmp_path / "a") as store:
        rec = dict(store.con.sql("SELECT key, value FROM run").fetchall())
    want = auto_window_s(ReportSource(read_dataset(dataset_dir, lazy=True).reports))
    assert float(rec["window_s"]) == want


def test_prefetched_keeps_order_reads_one_ahead_and_raises_where_the_item_is_taken():
    from tertiary.runtime.windows import prefetched
    made: list[int] = []

    def items(fail_at: int | None = None):
        for k in range(6):
            if k == fail_at:
                raise ValueError(f"item {k}")
            made.append(k)
            yield k

    got = []
    for k in prefetched(items()):
        time.sleep(0.01)                      # the producer has time to run ahead, if it would
        assert len(made) <= k + 2             # never more than one item ahead of the caller
        got.append(k)
    assert got == list(range(6))
    made.clear()
    seen = []
    with pytest.raises(ValueError, match="item 3"):
        for k in prefetched(items(fail_at=3)):
            seen.append(k)
    assert seen == [0, 1, 2]                  # the items before the failure were all handed over
    made.clear()
    for k in prefetched(items()):             # a caller that stops early: no hang, no further reads
        if k == 1:
            break
    assert made == [0, 1, 2]


def test_alerts_on_the_fused_picture_are_scored_with_its_id_map(terminal):
    """The evaluation keeps the id map of the safety picture only (memory): with
    ``safety_picture="fused"`` the fusion pictures' map scores the alerts — every fused
    method's safety rows are there and some alerts are genuine (fails if the fusion pictures'
    map is not kept: no alert then names an aircraft)."""
    cfg = dataclasses.replace(FAST, safety_picture="fused")
    res = pipeline.process(terminal, cfg, window_s=60.0)
    fused = {*cfg.methods, "centralized"}
    rows = res.metrics.filter((pl.col("stage") == "safety") & (pl.col("metric") == "alert_episodes")
                              & (pl.col("method") != "truth"))
    alerts = res.alerts.filter(pl.col("method") != "truth")         # the truth picture: the yardstick
    assert set(rows["method"]) == fused and rows["value"].sum() == alerts.height > 0
    assert set(res.conflicts["method"]) <= fused and set(alerts["method"]) <= fused
    # an alert is genuine only when the map names the aircraft of its targets
    genuine = res.metrics.filter((pl.col("stage") == "safety") & (pl.col("metric") == "genuine_alerts"))
    assert genuine["value"].sum() > 0


def test_the_command_hands_polars_freed_pages_back_at_once():
    """jemalloc (polars' allocator) reads its decay once, when polars loads: the command's entry
    configures it first, appending a zero muzzy decay to polars' own setting (purged pages leave
    the resident set at once); a caller's own setting wins; importing the package sets nothing.
    Fails if the setting comes after polars is loaded, or overrides the caller's."""
    code = ("import os, sys, tertiary, tertiary.cli.main; assert '_RJEM_MALLOC_CONF' not in os.environ; "
            "from tertiary.core.memory import configure_allocator; configure_allocator(); "
            "import polars; print(os.environ['_RJEM_MALLOC_CONF'])")
    env = {k: v for k, v in os.environ.items() if k != "_RJEM_MALLOC_CONF"}
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    # after polars' own setting (whatever its defaults): the last value of an option wins
    assert got.stdout.strip().endswith(",muzzy_decay_ms:0")
    env["_RJEM_MALLOC_CONF"] = "dirty_decay_ms:250"
    code = code.replace("assert '_RJEM_MALLOC_CONF' not in os.environ; ", "")
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert got.stdout.strip().endswith(",dirty_decay_ms:250") and "muzzy_decay_ms:0" not in got.stdout

@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(st.one_of(st.none(), st.integers(-5, 3_000), st.integers(0, 2**40)), max_size=40),
                max_size=6))
def test_distinct_ids_count_as_n_unique_whatever_the_id_space(frames):
    """The bitmap count of distinct ids, with its fallback for negative or sparse ids, equals
    polars' ``n_unique`` of all the frames together (a null counted once)."""
    from tertiary.pipeline.scoring import DistinctIds
    ids = DistinctIds()
    for f in frames:
        ids.add(pl.Series(f, dtype=pl.Int64))
    whole = pl.Series([v for f in frames for v in f], dtype=pl.Int64)
    assert ids.count() == whole.n_unique()


def test_aligned_facts_read_part_by_part_equal_the_whole_tables(terminal, tmp_path):
    """The row accounting and the observed aircraft taken from the aligned parts one at a time
    (their own ``truth_id``) equal those of the whole aligned rows joined to their reports; a
    report aligned in two parts is one report; parts without ``truth_id`` leave the observed
    aircraft to the reports."""
    from tertiary.pipeline.scoring import aligned_facts, observed_aircraft
    mem = pipeline.process(terminal, FAST, window_s=60.0)
    aligned, reports = mem.aligned, mem.ingested.reports
    epochs = aligned["epoch"].unique().sort()
    cuts = [epochs[k] for k in (len(epochs) // 3, 2 * len(epochs) // 3)]
    parts = [aligned.filter(pl.col("epoch") < cuts[0]),
             aligned.filter(pl.col("epoch").is_between(cuts[0], cuts[1], closed="left")),
             aligned.filter(pl.col("epoch") >= cuts[1]), aligned.clear()]
    files = []
    for i, p in enumerate(parts):
        files.append(tmp_path / f"w={i:06d}.parquet")
        p.write_parquet(files[-1])
    got = aligned_facts(files)
    # a report's plot is aligned at more than one epoch, across parts too: not vacuous
    assert aligned.height > aligned["report_id"].n_unique()
    assert got.rows == aligned.height and got.reports == aligned["report_id"].n_unique()
    want = observed_aircraft(aligned, reports)
    assert got.observed.height == want.height > 100
    assert_frame_equal(got.observed.sort(want.columns), want.sort(want.columns))
    aligned.drop("truth_id").write_parquet(files[0])
    assert aligned_facts(files).observed is None


def test_distinct_targets_read_part_by_part_equal_the_whole_count(terminal, tmp_path):
    """The association rows and distinct (run, target_id) counted a part at a time equal the
    whole table's, with a second run sharing the first run's target ids."""
    from tertiary.pipeline.scoring import distinct_targets
    assoc = pipeline.process(terminal, FAST, window_s=60.0).associations.select("run", "epoch", "target_id")
    both = pl.concat([assoc, assoc.head(5_000).with_columns(pl.lit(1, pl.UInt32).alias("run"))])
    files = []
    for i, p in enumerate(both.sort("epoch").iter_slices(7_000)):
        files.append(tmp_path / f"w={i:06d}.parquet")
        p.write_parquet(files[-1])
    assert distinct_targets(files) == (both.height, both.select("run", "target_id").n_unique())
    assert both.select("run", "target_id").n_unique() > both["target_id"].n_unique()    # the runs count apart


def test_alert_keys_of_a_run_without_conflict_parts_keep_a_row_per_epoch():
    """A run whose windows wrote no conflict part and no curve point has no alert: the
    evaluation's id map then keeps one row per picture epoch (the grid), not an error. Fails if
    the keys come back without columns (the id map's filter cannot join on them)."""
    class NoParts:
        def part_files(self, name):
            return []
    none = tables.DeferredTable(lambda: pl.DataFrame(), 0, blocks=lambda: iter([]), alerts=0)
    keys = whole_run._alert_keys(none, NoParts(), "track_id")
    from datetime import datetime, timedelta, timezone
    t = datetime(2021, 10, 7, 8, tzinfo=timezone.utc)
    ids = pl.DataFrame({"run": [0, 0, 0], "method": ["m"] * 3, "epoch": [t, t, t + timedelta(seconds=4)],
                        "track_id": [1, 2, 1], "truth_id": [5, 6, 5]}).with_columns(
        pl.col("run").cast(pl.UInt32), pl.col("track_id").cast(pl.UInt64), pl.col("epoch").dt.cast_time_unit("us"))
    kept = safety_alerts.id_rows(ids, keys, "track_id")
    assert keys.height == 0 and kept["track_id"].to_list() == [1, 1] and kept["epoch"].n_unique() == 2


def test_the_conflict_rows_the_windows_reduced_are_those_the_end_would_read(tmp_path, monkeypatch):
    """Each window writes the conflict rows the alert scoring reads (every alert row, one row per
    picture epoch: :func:`safety.alerts.scored_conflicts`): the end takes them, and the rows
    and alert rows from the parts' footers and those rows, without reading a conflict part; a
    window that did not write them (an older checkpoint's) makes the end read the parts. Fails
    if the end reads the conflict parts, or counts rows from the reduced ones."""
    from datetime import datetime, timedelta, timezone

    import numpy as np
    from parts import NamedParts
    rng = np.random.default_rng(2)
    t0 = datetime(2021, 10, 7, 8, tzinfo=timezone.utc)

    windows = []
    for w in range(4):
        n = 0 if w == 1 else 300
        windows.append(pl.DataFrame({
            "run": np.zeros(n, np.uint32), "epoch": [t0 + timedelta(seconds=60 * w + int(s)) for s in
                                                     np.sort(rng.integers(0, 60, n))],
            "method": rng.choice(["a+imm", "b+imm"], n), "id_a": rng.integers(1, 9, n).astype(np.uint64),
            "id_b": rng.integers(9, 19, n).astype(np.uint64), "alert": rng.random(n) < 0.2,
            "r_min_m": rng.random(n) * 9000, "dz_min_m": rng.random(n) * 300, "t_min_s": rng.random(n) * 100,
            "extra": rng.random(n)}, schema_overrides={"epoch": pl.Datetime("us", "UTC")}))
    scored = [safety_alerts.scored_conflicts(f) for f in windows]
    both = NamedParts(tmp_path / "both", {"conflicts": windows, tables.SCORED_CONFLICTS: scored})
    plain = NamedParts(tmp_path / "plain", {"conflicts": windows})
    older = NamedParts(tmp_path / "older", {"conflicts": windows,
                                            tables.SCORED_CONFLICTS: [scored[0], None, None, scored[3]]})
    want = whole_run._scored_conflict_parts(plain)
    scans: list[str] = []
    monkeypatch.setattr(pl, "scan_parquet", lambda f, *a, s=pl.scan_parquet, **k: scans.append(str(f)) or s(f, *a, **k))
    got = whole_run._scored_conflict_parts(both)
    assert scans == []
    assert want[:2] == got[:2] == (pl.concat(windows).height, int(pl.concat(windows)["alert"].sum()))
    assert pl.concat(got[2]).equals(pl.concat(want[2]))
    again = whole_run._scored_conflict_parts(older)
    assert again[:2] == want[:2] and pl.concat(again[2]).equals(pl.concat(want[2])) and scans
