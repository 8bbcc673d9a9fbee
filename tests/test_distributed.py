"""The Dask engine on a LocalCluster of 2 workers: Monte-Carlo runs as partitions
give the local engine's tables; a run cut into time slices gives them outside the warm-up
overlaps, with the stitching effects measured (id changes per boundary, accuracy after it)."""

from __future__ import annotations

import dataclasses
import json
import sys

import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.pipeline import dask_engine as D, stitching
from tertiary.evaluation import matched_apart
from tertiary.pipeline import whole_run
from tertiary import pipeline
from tertiary.io.dataset import read_dataset, write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.store.run_store import RunStore



WINDOW = 60.0
CFG = pipeline.PipelineConfig(stca_lookaheads_s=(), evaluation=False, methods=("arithmetic", "information"),
                              filters=("singer",))
KEYS = {
    "reports": ["run", "report_id"],
    "rejects": ["input_table", "row_index", "stage", "reason"],
    "aligned": ["run", "epoch", "radar_id", "local_track_id", "report_id"],
    "associations": ["run", "epoch", "radar_id", "local_track_id", "report_id"],
    "fused": ["run", "method", "epoch", "target_id"],
    "clusters": ["run", "method", "epoch", "cluster_id"],
    "tracks": ["run", "method", "filter", "epoch", "track_id"],
    "conflicts": ["run", "method", "epoch", "id_a", "id_b"],
    "metrics": ["stage", "method", "metric", "segment"],
}


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def _scenario(runs: int, duration_s: float, aircraft: int):
    cfg = load_scenario("terminal-area")
    return simulate(dataclasses.replace(cfg, duration_s=duration_s, runs=runs,
                                        traffic=dataclasses.replace(cfg.traffic, aircraft=aircraft, conflict_pairs=3)))


@pytest.fixture(scope="module")
def runs_dataset(tmp_path_factory):
    """Two Monte-Carlo runs, with invalid ranges in run 1 and a report without a run (run 0 by default)."""
    ds = _scenario(2, 240.0, 20)
    r = ds.reports.with_row_index("__i")
    bad = r.filter(pl.col("run") == 1)["__i"].head(3).to_list()
    r = r.with_columns(pl.when(pl.col("__i").is_in(bad)).then(-5.0).otherwise(pl.col("range_m")).alias("range_m"),
                       pl.when(pl.col("__i") == 7).then(None).otherwise(pl.col("run")).alias("run")).drop("__i")
    path = tmp_path_factory.mktemp("mc") / "ds"
    write_dataset(dataclasses.replace(ds, reports=r), path)
    return path


def _tables(db) -> dict[str, pl.DataFrame]:
    """Every table of a run database (the local engine's and the Dask engine's alike)."""
    with RunStore.open(db.parent) as s:
        return {n: s.read(n) for n in [*KEYS, "partitions", "run"] if n in s.tables()}


def _alerts(db) -> pl.DataFrame:
    """A run database's alert episodes in a stable order."""
    with RunStore.open(db.parent) as s:
        return s.read("alerts").sort("method", "run", "t_start", "truth_a", "truth_b", nulls_last=True)


def _target_bijection(dask: pl.DataFrame, local: pl.DataFrame) -> pl.DataFrame:
    """(run, target_id → local target_id) through the reports both assign: must be one-to-one."""
    key = KEYS["associations"]
    pairs = (dask.select(*key, "target_id").join(local.select(*key, pl.col("target_id").alias("local")), on=key)
             .select("run", "target_id", "local").unique())
    assert pairs.height == dask.select("run", "target_id").unique().height == \
        local.select("run", "target_id").unique().height, "target ids are not one-to-one with the local engine's"
    return pairs


def _to_local_targets(frame: pl.DataFrame, name: str, m: pl.DataFrame) -> pl.DataFrame:
    old, new = m["target_id"], m["local"]   # one run (time slices): ids unique within it
    rep = lambda c: pl.col(c).replace_strict(old, new, return_dtype=pl.UInt64)
    if name in ("associations", "fused"):
        return frame.with_columns(rep("target_id"))
    if name == "tracks":
        return frame.with_columns(rep("plot_target_id"))
    if name == "clusters":
        return frame.with_columns(rep("lead_target_id"), pl.col("members").list.eval(
            pl.element().replace_strict(old, new, return_dtype=pl.UInt64)).list.sort())
    if name == "conflicts":
        fused_pic = ~pl.col("method").str.contains("+", literal=True)
        return frame.with_columns(*[pl.when(fused_pic).then(rep(c)).otherwise(pl.col(c)).alias(c)
                                    for c in ("id_a", "id_b")])
    return frame


def _same(a: pl.DataFrame, b: pl.DataFrame, name: str) -> None:
    assert a.shape == b.shape, f"{name}: {a.shape} with Dask vs {b.shape} locally"
    if a.height == 0:
        return
    keys = [k for k in KEYS[name] if k in a.columns]
    if name == "clusters":
        b = b.with_columns(pl.col("members").list.sort())
    a, b = a.sort(keys, nulls_last=True), b.select(a.columns).sort(keys, nulls_last=True)
    assert_frame_equal(a, b, check_dtypes=False, rel_tol=1e-9, abs_tol=1e-6)


def test_monte_carlo_runs_as_partitions_equal_the_local_engine(client, runs_dataset, tmp_path):
    """Every table, the metrics included: the STCA curves, whose points the partitions predict on
    the workers, equal the local engine's."""
    cfg = dataclasses.replace(CFG, stca_lookaheads_s=(105.0,))
    import safety.alerts
    with pytest.MonkeyPatch.context() as mp:     # the client scores the points, it does not predict them
        mp.setattr(safety.alerts, "stca_tradeoff", lambda *a, **k: pytest.fail("curves predicted on the client"))
        db = D.run_dask(runs_dataset, tmp_path / "run", cfg, client=client, window_s=WINDOW)
    got = _tables(db)
    want = _tables(pipeline.run(read_dataset(runs_dataset, lazy=True), tmp_path / "local", cfg, window_s=WINDOW))
    curve = got["metrics"].filter(pl.col("stage") == "safety_tradeoff")
    assert curve.height and curve.filter(pl.col("metric") == "nuisance_false_per_hour")["value"].max() > 0
    # predicted by the partitions, not by the client's finalize
    assert len({f.parent for f in (tmp_path / "run" / D.SLICES).rglob("curve_rows/*.parquet")}) == 2
    # the 3 bad ranges rejected at their rows of the whole input (a null run is run 0: kept)
    assert got["rejects"].filter(pl.col("input_table") == "reports").height >= 3
    # target ids are numbered per run in both engines: identical, not merely one-to-one
    m = _target_bijection(got["associations"], want["associations"])
    assert m["target_id"].to_list() == m["local"].to_list()
    for name in KEYS:
        _same(got[name], want[name], name)
    parts = got["partitions"]
    assert parts.height == 2 and sorted(parts["run"].to_list()) == [0, 1]
    assert dict(got["run"].iter_rows())["engine"] == "dask"
    # the finalize stage's scratch (the truth as a reference file) does not outlive it
    assert (tmp_path / "run" / D.SLICES).is_dir() and not (tmp_path / "run" / D.SLICES / D.SCRATCH).exists()


def test_monte_carlo_runs_are_evaluated_on_the_workers(client, runs_dataset, tmp_path):
    """Each run's partition matches its pictures to the truth and steps every metric in its
    windows (seed, surveillance, OSPA/GOSPA/SIAP, the consistency lag sums); the client merges
    the runs' states and only finishes them: it matches no picture and sums no lag, and every
    metric and per-epoch row equals the local engine's, which steps both runs in the same windows."""
    from tertiary.evaluation import evaluate
    from tertiary.pipeline import scoring
    cfg = dataclasses.replace(CFG, evaluation=True)
    summed: list[int] = []

    def lags(scored, rows, carried=None):        # the rows whose lag sums the client makes
        summed.append(rows)
        return real_lags(scored, rows, carried)
    real_lags = scoring.statistic_lags
    with pytest.MonkeyPatch.context() as mp:     # the client's finalize must not match a picture again
        mp.setattr(evaluate, "match_block", lambda *a, **k: pytest.fail("pictures matched on the client"))
        mp.setattr(scoring, "statistic_lags", lags)
        res = D.run_dask_detailed(runs_dataset, tmp_path / "run", cfg, client=client, window_s=WINDOW)
    # every series' lag sums made by its run's partition: the client sums none
    assert summed == [0]
    got = _tables(res.db)
    with RunStore.open(res.db.parent) as s:
        got_epochs = s.read("accuracy_by_epoch")
    local = pipeline.run(read_dataset(runs_dataset, lazy=True), tmp_path / "local", cfg, window_s=WINDOW)
    want = _tables(local)
    with RunStore.open(local.parent) as s:
        want_epochs = s.read("accuracy_by_epoch")
    metrics = got["metrics"]
    for stage in ("fusion", "tracker", "evaluation"):       # seed, surveillance and multi-target rows
        assert metrics.filter(pl.col("stage") == stage).height > 20, stage
    assert metrics.filter(pl.col("metric") == "rmse_horizontal_m")["n_runs"].max() == 2
    _same(metrics, want["metrics"], "metrics")
    key = [c for c in ("stage", "method", "epoch") if c in got_epochs.columns]
    assert got_epochs.height and got_epochs.height == want_epochs.height
    assert_frame_equal(got_epochs.sort(key), want_epochs.select(got_epochs.columns).sort(key), check_dtypes=False,
                       rel_tol=1e-9, abs_tol=1e-9)
    # the matched rows are the partitions' own, one directory per run
    assert len({f.parent.parent.parent for f in (tmp_path / "run" / D.SLICES).rglob("matched.*/*.parquet")}) == 2


def test_a_worker_killed_in_the_middle_of_a_partition_changes_no_table(client, runs_dataset, tmp_path):
    """A worker process killed (SIGKILL) while it runs a partition: the scheduler gives the
    partition to a worker again, which rewrites its parts from scratch, and every table equals
    the local engine's; the partition's recorded worker is not the killed one."""
    import os
    import signal
    import threading
    import time
    out: dict[str, object] = {}

    def run() -> None:
        try:
            out["db"] = D.run_dask(runs_dataset, tmp_path / "run", CFG, client=client, window_s=WINDOW)
        except BaseException as exc:            # re-raised in the test's thread below
            out["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    killed, deadline = None, time.time() + 120
    while killed is None and time.time() < deadline and thread.is_alive():
        busy = {w: keys for w, keys in client.processing().items()
                if any(str(k).startswith("tertiary-partition-") for k in keys)}
        if busy:
            worker = sorted(busy)[0]
            time.sleep(0.5)                     # inside the partition: it reads, then streams windows
            killed = client.run(os.getpid, workers=[worker])[worker]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    thread.join(timeout=600)
    assert killed is not None, "no partition was seen running"
    if "error" in out:
        raise out["error"]
    got = _tables(out["db"])
    want = _tables(pipeline.run(read_dataset(runs_dataset, lazy=True), tmp_path / "local", CFG, window_s=WINDOW))
    for name in KEYS:
        _same(got[name], want[name], name)
    assert killed not in got["partitions"]["worker_pid"].to_list()
    client.wait_for_workers(2, timeout=120)     # the nanny's new worker, for the next tests


@pytest.fixture(scope="module")
def long_run(tmp_path_factory):
    path = tmp_path_factory.mktemp("long") / "ds"
    write_dataset(_scenario(1, 530.0, 30), path)
    return path


def test_time_slices_equal_the_local_engine_outside_the_overlaps(client, long_run, tmp_path, monkeypatch):
    said: list[str] = []
    # the association metrics come from the partitions' merged states: no row is read back for them
    monkeypatch.setattr(whole_run, "scored_blocks", lambda *a: pytest.fail("association rows scored on the client"))
    monkeypatch.setattr(matched_apart, "PIECE_ROWS", 1)
    # the truth is validated while the partitions run, not by the finalize after them
    for name in ("stream_truth", "validate_truth"):
        monkeypatch.setattr(whole_run, name, lambda *a, n=name: pytest.fail(f"the finalize ran {n}"))
    res = D.run_dask_detailed(long_run, tmp_path / "run", CFG, client=client, window_s=WINDOW, slice_s=180.0,
                              overlap_s=60.0, progress=said.append)
    # the client's whole-run stages are said as they start, after "finalize"
    assert said.index("finalize") < said.index("evaluation") < said.index("score_alerts"), said
    got = _tables(res.db)
    local = pipeline.run(read_dataset(long_run, lazy=True), tmp_path / "local", CFG, window_s=WINDOW)
    want = _tables(local)
    assert got["partitions"].height == 3 and res.stitching.height == 2
    # each boundary's matching ran on the workers, in the slices' own ids
    assert res.timings["stitch_task_s_sum"] > 0 and res.timings["stitch_pieces_wall_s"] > 0
    # the finalize's pieces: the run record names each call's function, pieces and where they
    # ran; the truth picture's alerts are the local run's
    record = json.loads(dict(got["run"].iter_rows())["fanout"])
    where = {(r["piece"], r["pieces"], r["where"]) for r in record}
    # each picture's window files a piece (pieces of one row at least): on the workers
    assert any(p == "_match_piece" and n > 1 and w == "workers" for p, n, w in where), record
    # the 9 minutes of truth are one chunk and one block: a single piece runs on the client,
    # which would only wait for it
    assert {("_chunk_task", 1, "client"), ("_predict_part", 1, "client")} <= where, record
    truth_alerts = [_alerts(db).filter(pl.col("method") == "truth") for db in (res.db, local)]
    assert truth_alerts[1].height
    assert_frame_equal(*truth_alerts)
    # every report is in exactly one slice, at its row of the whole input
    for name in ("reports", "rejects", "aligned"):
        _same(got[name], want[name], name)
    # the same reports grouped into the same targets, with one target id each across boundaries
    _target_bijection(got["associations"], want["associations"])
    # so the association metrics, scored by each slice on its kept span and merged, are the local ones
    assoc = (pl.col("stage") == "association") & pl.col("metric").is_in(
        ["assoc_correct_frac", "swaps", "targets_per_truth", "confirmed_targets_per_truth", "false_targets",
         "split_targets", "merged_targets"])
    assert got["metrics"].filter(assoc).height == 7
    _same(got["metrics"].filter(assoc), want["metrics"].filter(assoc), "metrics")
    bounds = sorted(D.parse_utc(x) for x in got["partitions"]["kept_from_utc"].to_list()[1:])
    eff = D.stitching_effects(got, want, bounds)
    assert all(b["id_changed"] == 0 for b in eff["target_id_changes"])
    assert all(b["id_changed"] <= 0.1 * b["alive"] for b in eff["track_id_changes"]), eff["track_id_changes"]
    for table in ("fused", "tracks"):
        for row in eff[table]:
            lo = float(row["bin"].strip("[(").split(",")[0])
            if lo < 0 or lo >= 120:          # before the first boundary, or 2 overlaps after one
                assert row["matched"] >= 0.95 * row["local_rows"], (table, row)
                assert row["max_m"] < 0.05, (table, row)


def test_gated_pairs_equal_brute_force():
    """The grid-cell candidate search of the stitching finds exactly the pairs within the gate."""
    import numpy as np
    rng = np.random.default_rng(3)

    def frame(n, ids):
        return pl.DataFrame({"run": np.zeros(n, np.uint32), "epoch": rng.integers(0, 3, n), "track_id": ids,
                             "x_m": rng.uniform(-5e3, 5e3, n), "y_m": rng.uniform(-5e3, 5e3, n),
                             "z_m": rng.uniform(0, 300, n)})
    a, b = frame(400, np.arange(400)), frame(400, np.arange(1000, 1400))
    got = stitching._pairs(a, b, ["run", "epoch"], ["run"], "track_id", 500.0).sort("a", "b")
    j = a.join(b, on=["run", "epoch"], suffix="_b").filter(
        ((pl.col("x_m") - pl.col("x_m_b")) ** 2 + (pl.col("y_m") - pl.col("y_m_b")) ** 2
         + (pl.col("z_m") - pl.col("z_m_b")) ** 2).sqrt() <= 500.0)
    want = j.group_by("run", pl.col("track_id").alias("a"), pl.col("track_id_b").alias("b")).len().sort("a", "b")
    assert got.height == want.height > 10
    assert got["n"].to_list() == want["len"].to_list() and got["a"].to_list() == want["a"].to_list()


def test_a_partition_reads_its_windows_from_a_scan_that_takes_their_time_test(long_run, tmp_path):
    """A partition's input (:func:`~tertiary.pipeline.dask_engine.partition_input`) is the rows of its
    input expression in input order (a row without a time in the first slice), and a window
    of it is read by a scan that takes the window's time test. On ``lf.filter(...)`` the
    stream's row index came after the filter and every window read the partition's whole
    input (2.4 s instead of 0.25 s a window on a national hour)."""
    from tertiary.runtime.windows import ReportSource
    reports = read_dataset(long_run, lazy=True).reports.collect()
    reports = reports.with_columns(pl.when(pl.int_range(pl.len()) == 5).then(None).otherwise(pl.col("time"))
                                   .alias("time"))
    reports.write_parquet(tmp_path / "reports.parquet", row_group_size=500)
    lf = pl.scan_parquet(tmp_path / "reports.parquet")
    origin, _n, parts = D.plan(long_run, CFG, WINDOW, 180.0, 60.0)
    assert len(parts) == 3
    for part in parts:
        got = D.partition_input(lf, part, tmp_path / f"{part.index}.parquet")
        want = lf.filter(part.input_expr()).collect()
        assert_frame_equal(got.collect(), want)
        assert want.height > 1000 and (want["time"].null_count() == 1) == part.first_slice
        src = ReportSource(got)
        t0 = max(part.t0_us, src.first_us)
        plan = src.lf.filter(src._near(t0, t0 + int(WINDOW * 1e6))).explain()
        assert plan.lstrip().startswith("Parquet SCAN") and "SELECTION" in plan, plan


def test_the_union_of_partitions_reads_only_the_columns_asked_for(tmp_path, monkeypatch):
    """The client's finalize reads a few columns of each partition's reports and aligned rows
    (a national day's aligned rows read whole before the selection took the client
    past 23 GB). Only those columns are read, a partition without an optional one gives the
    others, and the rows are every partition's in order."""
    for i, frame in enumerate([pl.DataFrame({"a": [1, 2], "big": [0.0, 0.0], "opt": ["x", "y"]}),
                               pl.DataFrame({"a": [3], "big": [0.0]})]):
        d = tmp_path / D.SLICES / str(i) / "kept" / "t"
        d.mkdir(parents=True)
        frame.write_parquet(d / "w=000000.parquet")
    asked: list = []
    monkeypatch.setattr(D.pl, "read_parquet", lambda f, *a, r=pl.read_parquet, **k:
                        asked.append(k.get("columns")) or r(f, *a, **k))
    got = D.UnionParts(tmp_path, 2).table("t", ["a", "opt"])
    assert got.columns == ["a", "opt"] and got["a"].to_list() == [1, 2, 3]
    assert got["opt"].to_list() == ["x", "y", None]
    assert asked and all(cols is not None and "big" not in cols for cols in asked)


def test_a_registered_run_is_one_partition_on_the_grid_of_its_corrected_times(long_run):
    """A given registration moves reports by their radar's clock offset: the Dask plan keeps the
    run in one partition (a slice reads the reports' own times) and puts its grid where the local
    engine's windows put it, at the first corrected time."""
    from tertiary.runtime.windows import US, ReportSource
    reports = read_dataset(long_run, lazy=True).reports.collect()
    first = reports.sort("time").row(0, named=True)
    # the first report's radar 2.5 s late: its corrected time falls into another whole second
    rows = tuple((float(r), 0.0, 0.0, 2.5 if r == first["radar_id"] else 0.0, 0.0)
                 for r in reports["radar_id"].unique().to_list())
    cfg = dataclasses.replace(CFG, register=True, registration=rows)
    notes: list[str] = []
    origin, _n, parts = D.plan(long_run, cfg, WINDOW, 180.0, 60.0, notes=notes)
    local = ReportSource(reports, clock_offsets=pipeline.streaming.clock_offsets(cfg))
    assert len(parts) == 1 and any("clock offsets" in n for n in notes), notes
    assert origin == (local.first_us // US) * US != (ReportSource(reports).first_us // US) * US
