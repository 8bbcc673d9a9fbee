"""Report collection (§1.4): queue disciplines against closed forms and a brute-force event simulation."""

from __future__ import annotations

import dataclasses
import heapq
import math
from collections import deque
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from tertiary import pipeline
from tertiary.sensors.collection import (ACCEPTED, LOST_BUFFER, LOST_BUSY, LOST_WAIT, CollectionConfig, collect, collection_stage, erlang_b, md1_wait, mm1_limited_loss, mm1_wait, mm1k_loss, queue_kernel)
from tertiary.core.errors import OptionError


def poisson(lam: float, n: int, seed: int) -> np.ndarray:
    return np.cumsum(np.random.default_rng(seed).exponential(1.0 / lam, n))


def one(t: np.ndarray) -> np.ndarray:
    return np.zeros(1, np.int64)


# ---------------------------------------------------------------------------- closed forms

def test_closed_forms_by_hand():
    assert erlang_b(1, 1.0) == pytest.approx(0.5)                       # a/(1+a)
    assert erlang_b(2, 1.0) == pytest.approx(0.2)                       # (a²/2)/(1 + a + a²/2)
    assert mm1_wait(5.0, 10.0) == pytest.approx(0.1)                    # 0.5/5
    assert md1_wait(5.0, 0.1) == pytest.approx(0.05)                    # 0.5·0.1/(2·0.5)
    assert mm1k_loss(1.0, 2.0, 1) == pytest.approx(1.0 / 3.0)           # K = 1 is M/M/1/1 = Erlang B
    assert mm1_limited_loss(1.0, 2.0, 0.0) == pytest.approx(erlang_b(1, 0.5))
    assert mm1_limited_loss(1.0, 2.0, 50.0) < 1e-12


def test_refusals_mm1_matches_erlang_b():
    lam, mu, n = 50.0, 100.0, 200_000
    t = poisson(lam, n, 1)
    s = np.random.default_rng(2).exponential(1 / mu, n)
    wait, st = queue_kernel(t, s, one(t), "refusals")
    assert set(np.unique(st)) <= {ACCEPTED, LOST_BUSY}
    assert np.all(wait[st == ACCEPTED] == 0.0)                           # nobody waits in a loss system
    assert np.mean(st == LOST_BUSY) == pytest.approx(erlang_b(1, lam / mu), abs=0.006)   # 1/3


def test_refusals_two_servers_matches_erlang_b():
    lam, mu, n = 150.0, 100.0, 200_000
    t = poisson(lam, n, 3)
    s = np.random.default_rng(4).exponential(1 / mu, n)
    _, st = queue_kernel(t, s, one(t), "refusals", servers=2)
    assert np.mean(st == LOST_BUSY) == pytest.approx(erlang_b(2, 1.5), abs=0.006)       # 0.3214


def test_waiting_mm1_mean_wait():
    lam, mu, n = 60.0, 100.0, 400_000
    t = poisson(lam, n, 5)
    s = np.random.default_rng(6).exponential(1 / mu, n)
    wait, st = queue_kernel(t, s, one(t), "waiting")
    assert np.all(st == ACCEPTED)
    assert wait.mean() == pytest.approx(mm1_wait(lam, mu), rel=0.05)     # 0.015 s


def test_waiting_md1_mean_wait():
    lam, d, n = 70.0, 0.01, 400_000
    t = poisson(lam, n, 7)
    wait, _ = queue_kernel(t, np.full(n, d), one(t), "waiting")
    assert wait.mean() == pytest.approx(md1_wait(lam, d), rel=0.05)     # 0.011667 s
    assert wait.mean() < mm1_wait(lam, 1 / d)                            # half the M/M/1 wait


def test_waiting_with_buffer_matches_mm1k():
    lam, mu, n, places = 90.0, 100.0, 300_000, 3
    t = poisson(lam, n, 8)
    s = np.random.default_rng(9).exponential(1 / mu, n)
    _, st = queue_kernel(t, s, one(t), "waiting", queue_places=places)
    assert np.mean(st == LOST_BUFFER) == pytest.approx(mm1k_loss(lam, mu, places + 1), abs=0.006)


@pytest.mark.parametrize("t_wait", [0.0, 0.005, 0.02])
def test_limited_waiting_matches_closed_form(t_wait):
    lam, mu, n = 80.0, 100.0, 300_000
    t = poisson(lam, n, 10)
    s = np.random.default_rng(11).exponential(1 / mu, n)
    wait, st = queue_kernel(t, s, one(t), "limited", max_wait_s=t_wait)
    assert np.nanmax(wait) <= t_wait
    assert np.mean(st == LOST_WAIT) == pytest.approx(mm1_limited_loss(lam, mu, t_wait), abs=0.006)


# ---------------------------------------------------------------------------- brute force

def brute_force(t, service, discipline, max_wait=0.0, servers=1, places=None):
    """Event simulation: arrivals and departures from a heap, a FIFO list of waiting reports,
    and (limited waiting) reneging: a waiting report leaves when its deadline passes unserved."""
    n = len(t)
    wait, status = np.full(n, np.nan), np.zeros(n, np.int8)
    idle, done, queue = servers, [], deque()

    def start(i, now):
        nonlocal idle
        idle -= 1
        wait[i] = now - t[i]
        heapq.heappush(done, now + service[i])

    def renege(now):
        while queue and discipline == "limited" and t[queue[0]] + max_wait < now:
            status[queue.popleft()] = LOST_WAIT      # FIFO: the head has the earliest deadline

    def advance(until):
        nonlocal idle
        while done and done[0] <= until:
            now = heapq.heappop(done)
            idle += 1
            renege(now)
            if queue:
                start(queue.popleft(), now)

    for i in range(n):
        advance(t[i])
        renege(t[i])
        if idle:
            start(i, t[i])
        elif discipline == "refusals":
            status[i] = LOST_BUSY
        elif places is not None and len(queue) >= places:
            status[i] = LOST_BUFFER
        else:
            queue.append(i)
    advance(np.inf)
    renege(np.inf)
    return wait, status


@pytest.mark.parametrize("discipline,servers,places", [
    ("refusals", 1, None), ("refusals", 3, None), ("waiting", 1, None), ("waiting", 2, 2),
    ("limited", 1, None), ("limited", 2, None)])
def test_kernel_equals_brute_force(discipline, servers, places):
    rng = np.random.default_rng(12)
    t = np.sort(rng.uniform(0, 10, 300))
    s = rng.exponential(0.05 * servers, 300)
    w_ref, s_ref = brute_force(t, s, discipline, 0.04, servers, places)
    w, st = queue_kernel(t, s, one(t), discipline, 0.04, servers, places)
    np.testing.assert_array_equal(st, s_ref)
    np.testing.assert_allclose(w, w_ref, atol=1e-12)
    assert len(np.unique(st)) > 1 or discipline == "waiting"        # the case exercises losses


def test_segments_are_independent_queues():
    t = np.array([0.0, 0.001, 0.0, 0.001])
    w, st = queue_kernel(t, np.full(4, 0.01), np.array([0, 2]), "refusals")
    np.testing.assert_array_equal(st, [ACCEPTED, LOST_BUSY, ACCEPTED, LOST_BUSY])


# ---------------------------------------------------------------------------- frames and pipeline

def reports_frame(times_s, runs=None):
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    n = len(times_s)
    return pl.DataFrame({
        "run": pl.Series(runs if runs is not None else [0] * n, dtype=pl.UInt32),
        "report_id": pl.Series(np.arange(n), dtype=pl.UInt64),
        "radar_id": pl.Series([1] * n, dtype=pl.UInt32),
        "time": [t0 + timedelta(seconds=float(s)) for s in times_s],
    })


def test_collect_deterministic_by_hand():
    # D = 1 s, T_wait = 1.5 s: 0 served 0–1; 0.2 waits 0.8 (1–2); 0.4 would wait 1.6 → lost;
    # 0.6 would wait 1.4 → served 2–3; 5 served at once. Listed out of order: sorted by arrival.
    rep = reports_frame([5.0, 0.6, 0.0, 0.4, 0.2])
    cfg = CollectionConfig("limited", service_time_s=1.0, service_model="deterministic", max_wait_s=1.5)
    got = collect(rep, cfg)
    acc = got.accepted.sort("report_id")
    assert acc["report_id"].to_list() == [0, 1, 2, 4]
    np.testing.assert_allclose(acc["collection_wait_s"].to_numpy(), [0.0, 1.4, 0.0, 0.8])
    np.testing.assert_allclose(acc["collection_delay_s"].to_numpy(), [1.0, 2.4, 1.0, 1.8])
    assert got.lost["report_id"].to_list() == [3]
    assert "T_wait = 1.5 s" in got.lost["reason"][0]
    assert got.stats.select("offered", "accepted", "lost_wait").row(0) == (5, 4, 1)


def test_collect_runs_are_separate():
    rep = reports_frame([0.0, 0.1, 0.0, 0.1], runs=[0, 0, 1, 1])
    got = collect(rep, CollectionConfig("refusals", service_time_s=1.0, service_model="deterministic"))
    assert sorted(got.lost["report_id"].to_list()) == [1, 3]
    assert got.stats["lost_refused"].to_list() == [1, 1]


def test_collection_stage_rejects_rows():
    rep = reports_frame([0.0, 0.1, 0.2, 3.0])
    rows = rep.select("report_id", (pl.col("report_id") + 10).alias("row_index"))
    keep, rej, notes = collection_stage(rep, rows, CollectionConfig("refusals", 1.0, "deterministic"))
    assert keep["report_id"].to_list() == [0, 3]
    assert rej["report_id"].to_list() == [1, 2] and rej["row_index"].to_list() == [11, 12]
    assert set(rej["stage"]) == {"collection"} and rej["reason"][0].startswith("collection: all 1 processor")
    assert "2 refused" in notes[0]


def test_config_errors_are_option_errors():
    with pytest.raises(OptionError, match="--collection"):
        CollectionConfig("queue")
    with pytest.raises(OptionError, match="--service-time"):
        CollectionConfig(service_time_s=0.0)
    with pytest.raises(OptionError, match="--max-wait"):
        CollectionConfig(max_wait_s=-1.0)


def test_pipeline_screen_accounts_for_lost_reports(small_terminal):
    cfg = pipeline.PipelineConfig(collection=CollectionConfig("refusals", service_time_s=0.02))
    ing = pipeline.screen(small_terminal, cfg)
    lost = ing.rejects.filter(pl.col("stage") == "collection")
    assert lost.height > 0
    assert set(lost["report_id"].to_list()).isdisjoint(ing.reports["report_id"].to_list())
    base = pipeline.screen(small_terminal, pipeline.PipelineConfig())
    assert ing.reports.height + lost.height == base.reports.height
    assert any(n.startswith("collection (refusals") for n in ing.notes)


def test_cli_run_with_collection(tmp_path):
    import duckdb
    from typer.testing import CliRunner

    from tertiary.cli.commands import app
    runner = CliRunner()
    bad = runner.invoke(app, ["run", "--out", str(tmp_path / "x"), "--collection", "queue"])
    assert bad.exit_code == 2 and "--collection" in bad.output           # refused before simulating
    ds = tmp_path / "ds"
    assert runner.invoke(app, ["simulate", "terminal-area", "--out", str(ds), "--aircraft", "8",
                               "--duration", "120", "--runs", "1"]).exit_code == 0
    res = runner.invoke(app, ["run", str(ds), "--out", str(tmp_path / "run"), "--filters", "",
                              "--methods", "information,best_source", "--no-report", "--collection", "refusals",
                              "--service-time", "0.05", "--service-model", "deterministic"])
    assert res.exit_code == 0, res.output
    with duckdb.connect(str(tmp_path / "run" / "results.duckdb"), read_only=True) as con:
        n = con.sql("select count(*) from rejects where stage = 'collection'").fetchall()[0][0]
        methods = {r[0] for r in con.sql("select distinct method from fused").fetchall()}
    assert n > 0 and {"information", "best_source"} <= methods


def test_alignment_uses_a_report_from_its_collection_time_on(small_terminal):
    """A report delayed by the queue (collection_delay_s) reaches its first epoch one epoch later
    when the delay is one epoch period; its time (and so its extrapolation) is unchanged."""
    import numpy as np
    from tertiary.stages import align
    ds = small_terminal
    p0 = align.plan(ds.reports, ds.radars, ds.origin, align.AlignConfig())
    p1 = align.plan(ds.reports.with_columns(pl.lit(p0.period).alias("collection_delay_s")), ds.radars, ds.origin,
                    align.AlignConfig())
    inner = p0.k < p0.k.max()
    assert inner.mean() > 0.9
    assert np.array_equal(p1.k[inner], p0.k[inner] + 1)
    assert np.array_equal(p1.rel, p0.rel)
