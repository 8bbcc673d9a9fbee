"""Streamed simulation: window by window into time parts, read back alike."""

from __future__ import annotations

import dataclasses
import json
from datetime import timedelta

import polars as pl
import pyarrow.parquet as pq
import pytest
from polars.testing import assert_frame_equal

from tertiary.core.errors import DataError, OptionError
from tertiary.io.dataset import Dataset, read_dataset, write_dataset
from tertiary.simulate import load_scenario, simulate, simulate_windows, write_stream


def _small_national(duration: float = 1200.0, peak: int = 150):
    cfg = load_scenario("national")
    return dataclasses.replace(cfg, duration_s=duration,
                               national=dataclasses.replace(cfg.national, peak_airborne=peak, start_s=28800.0))


@pytest.fixture(scope="module")
def whole():
    """The small national scenario simulated in one window (in memory)."""
    return simulate(_small_national())


def test_single_file_and_partitioned_read_back_identical(tmp_path):
    """The same scenario written into single files and window by window into parts reads back
    identical tables, row for row and bit for bit."""
    scen, radars, wins = simulate_windows(_small_national(), 600.0)
    got = list(wins)
    single = Dataset(radars=radars, reports=pl.concat([w.reports for w in got]),
                     truth=pl.concat([w.truth for w in got]), scenario=scen)
    write_dataset(single, tmp_path / "single")
    summary = write_stream(_small_national(), tmp_path / "parts", window_s=600.0)
    assert len(summary["parts"]) == 2
    assert sorted(p.name for p in (tmp_path / "parts" / "reports").iterdir()) == ["part-0000.parquet",
                                                                                 "part-0001.parquet"]
    one, parts = read_dataset(tmp_path / "single"), read_dataset(tmp_path / "parts")
    for name in ("reports", "truth", "radars"):
        a, b = getattr(one, name), getattr(parts, name)
        assert a.height > 0 and a.columns == b.columns and a.equals(b), name
    assert parts.scenario == one.scenario
    # each part in row groups of ≤ 16 384 reports in time order: a reader of one time window
    # skips the others by their statistics (a part reaches back to its tracks' first reports)
    n_groups = []
    for part in sorted((tmp_path / "parts" / "reports").iterdir()):
        meta = pq.ParquetFile(part).metadata
        col = [meta.schema.column(i).name for i in range(meta.num_columns)].index("time")
        groups = [meta.row_group(g) for g in range(meta.num_row_groups)]
        assert all(g.num_rows <= 16_384 for g in groups)
        stats = [g.column(col).statistics for g in groups]
        assert all(a.max <= b.min for a, b in zip(stats[:-1], stats[1:]))
        n_groups.append(len(groups))
    assert max(n_groups) >= 2


def test_windows_equal_one_window_run(whole):
    """Window by window (600 s; the radars' association state and the rows of unfinished local
    tracks carried across the boundary) equals the one-window run: same rows, same track
    numbers and truth ids exactly, estimates to round-off (the batched filters group tracks
    differently)."""
    _, _, wins = simulate_windows(_small_national(), 600.0)
    got = list(wins)
    joined = pl.concat([w.reports for w in got])
    key = ["radar_id", "time", "range_m"]
    a, b = whole.reports.sort(key).drop("report_id"), joined.sort(key).drop("report_id")
    exact = [c for c in a.columns if a[c].dtype not in (pl.Float64,) and not isinstance(a[c].dtype, pl.Array)]
    assert a.height == b.height > 0
    assert a.select(exact).equals(b.select(exact))
    assert_frame_equal(a, b, check_exact=False, rel_tol=1e-9, abs_tol=1e-6)
    tk = ["truth_id", "time"]
    assert pl.concat([w.truth for w in got]).sort(tk).equals(whole.truth.sort(tk))


def test_windows_carry_track_numbers_across_the_boundary(whole):
    """A radar track crossing the window boundary keeps its number and filter: its rows come out
    once, in the window where the track ended."""
    scen, _, wins = simulate_windows(_small_national(), 600.0)
    got = list(wins)
    joined = pl.concat([w.reports for w in got])
    assert sorted(joined["report_id"].to_list()) == list(range(joined.height))
    # each part in time order (its row groups then skip by time), though it reaches back in time
    assert all(w.reports["time"].is_sorted() for w in got)
    boundary = whole.truth["time"].min() + timedelta(seconds=600)
    first, second = got[0].reports, got[1].reports
    # the first part holds only tracks that ended before the boundary (+ one scan and clock offsets) ...
    assert first.height > 0 and first["time"].max() < boundary + timedelta(seconds=12.5)
    # ... the tracks alive at the boundary come out whole in the second, rows before it included
    carried = second.filter(pl.col("time") < boundary)
    assert carried.height > 1000
    assert carried.select("radar_id", "local_track_id").unique().height > 10


def test_data_do_not_depend_on_the_window(tmp_path):
    cfg = _small_national(1800.0, 80)
    a = write_stream(cfg, tmp_path / "a", window_s=600.0)
    b = write_stream(cfg, tmp_path / "b", window_s=1200.0)
    assert a["reports"] == b["reports"] and a["truth_rows"] == b["truth_rows"]
    ra = read_dataset(tmp_path / "a").reports.drop("report_id").sort("radar_id", "time", "range_m")
    rb = read_dataset(tmp_path / "b").reports.drop("report_id").sort("radar_id", "time", "range_m")
    assert_frame_equal(ra, rb, check_exact=False, rel_tol=1e-9, abs_tol=1e-6)
    assert ra.select("radar_id", "time", "local_track_id", "truth_id").equals(
        rb.select("radar_id", "time", "local_track_id", "truth_id"))


def test_window_must_be_whole_blocks():
    with pytest.raises(OptionError, match="--window.*multiple of the scenario's block of 600 s"):
        simulate_windows(_small_national(), 450.0)


def test_incomplete_partitioned_dataset_is_refused(tmp_path):
    write_stream(_small_national(600.0, 40), tmp_path / "d", window_s=600.0)
    (tmp_path / "d" / "parts.json").unlink()
    with pytest.raises(DataError, match="parts.json: incomplete"):
        read_dataset(tmp_path / "d")


def test_short_part_is_refused(tmp_path):
    write_stream(_small_national(600.0, 40), tmp_path / "d", window_s=600.0)
    part = tmp_path / "d" / "reports" / "part-0000.parquet"
    pl.read_parquet(part).head(5).write_parquet(part)
    with pytest.raises(DataError, match="part-0000.parquet: 5 rows, parts.json says"):
        read_dataset(tmp_path / "d")


def test_other_scenarios_are_cut_into_time_parts(tmp_path):
    """A big-box scenario (simulated whole) written with a window: the same rows as the single
    file, cut by time."""
    cfg = dataclasses.replace(load_scenario("big-box"), duration_s=300.0)
    ds = simulate(cfg)
    write_stream(cfg, tmp_path / "p", window_s=100.0)
    back = read_dataset(tmp_path / "p")
    assert json.loads((tmp_path / "p" / "parts.json").read_text())["window_s"] == 100.0
    assert back.reports.sort("report_id").equals(ds.reports.sort("report_id"))
    assert back.truth.height == ds.truth.height
    for i in range(3):
        part = pl.read_parquet(tmp_path / "p" / "reports" / f"part-{i:04d}.parquet")
        t0 = ds.truth["time"].min()
        secs = (part["time"] - t0).dt.total_microseconds() / 1e6
        assert part.height and secs.min() >= (100.0 * i if i else -1.0) and secs.max() < 100.0 * (i + 1) + (1e9 if i == 2 else 0)


def _small_terminal(duration: float = 1800.0, aircraft: int = 40):
    cfg = load_scenario("terminal-area")
    return dataclasses.replace(cfg, duration_s=duration, traffic=dataclasses.replace(
        cfg.traffic, aircraft=aircraft, conflict_pairs=2, near_miss_pairs=1))


def test_terminal_area_streams_in_blocks(tmp_path, monkeypatch):
    """Terminal-area traffic is looked up window by window: no truth array
    spans more than a block (+ the scan margin) or a window, whatever the scenario's length.
    Fails if the traffic is built over the whole duration."""
    from tertiary.simulate import block_s
    from tertiary.simulate.traffic import TerminalTraffic
    cfg = _small_terminal()
    assert block_s(cfg) == 600.0                  # scan periods 4, 5, 8, 12 s: 120 s → 600 s
    lengths = []
    real = TerminalTraffic.window

    def spy(self, k0, n, every=False):
        lengths.append(n)
        return real(self, k0, n, every)
    monkeypatch.setattr(TerminalTraffic, "window", spy)
    write_stream(cfg, tmp_path / "d", window_s=600.0)
    assert lengths and max(lengths) <= 600 + 12 + 2 + 1


def test_a_window_is_released_before_the_next_is_made(monkeypatch):
    """A streamed simulation does not hold the last window's tables while it makes the next
    one (beside the next one's they would double the peak memory). With the consumer done with window k, its reports and truth are gone when window
    k + 1's first block is observed. Fails if the generator keeps them bound until the next
    window's names are bound again."""
    import gc
    import importlib
    import weakref
    sim = importlib.import_module("tertiary.simulate.simulator")
    cfg = _small_terminal()
    alive: list[bool] = []
    last: list[weakref.ref] = []
    real = sim._observe_block

    def spy(*args, **kwargs):
        gc.collect()
        alive.extend(r() is not None for r in last)
        return real(*args, **kwargs)
    monkeypatch.setattr(sim, "_observe_block", spy)
    _, _, windows = simulate_windows(cfg, 600.0)
    n = 0
    for w in windows:
        last[:] = [weakref.ref(w.reports), weakref.ref(w.truth)]
        n += 1
        del w
    assert n >= 2 and len(alive) >= 2 and not any(alive)


def test_terminal_area_data_do_not_depend_on_the_window(tmp_path):
    """Window by window (600 s, 1 200 s) equals the one-window simulation: same rows, track
    numbers, truth ids, EHS columns and flight plans; estimates to round-off."""
    cfg = _small_terminal()
    whole = simulate(cfg)
    assert whole.flight_plans.height and whole.reports["ehs_gs_mps"].is_not_null().any()
    key = ["radar_id", "time", "range_m"]
    for w in (600.0, 1200.0):
        write_stream(cfg, tmp_path / f"w{w:g}", window_s=w)
        got = read_dataset(tmp_path / f"w{w:g}")
        a, b = whole.reports.sort(key).drop("report_id"), got.reports.sort(key).drop("report_id")
        exact = [c for c in a.columns if a[c].dtype != pl.Float64 and not isinstance(a[c].dtype, pl.Array)]
        assert a.height == b.height > 0 and a.columns == b.columns
        assert a.select(exact).equals(b.select(exact))
        assert_frame_equal(a, b, check_exact=False, rel_tol=1e-9, abs_tol=1e-6)
        tk = ["truth_id", "time"]
        assert got.truth.sort(tk).equals(whole.truth.sort(tk))
        assert got.flight_plans.equals(whole.flight_plans)


def test_terminal_area_window_must_be_whole_blocks():
    with pytest.raises(OptionError, match="--window.*multiple of the scenario's block of 600 s"):
        simulate_windows(_small_terminal(), 200.0)


def test_terminal_block_is_a_common_multiple_of_the_scan_periods():
    from tertiary.simulate import block_s
    cfg = _small_terminal()
    odd = dataclasses.replace(cfg, radars=tuple(dataclasses.replace(r, scan_period_s=p, scan_phase_s=0.0)
                                                for r, p in zip(cfg.radars, (4.0, 5.0, 7.0, 4.5))))
    assert block_s(odd) == 1260.0                  # lcm(4, 5, 7, 4.5) = 1 260 s


def test_ehs_refresh_phase_does_not_depend_on_the_window():
    """Register staleness (``refresh_s``) samples each aircraft on its own phase of the absolute
    clock: a window looked up from a later sample, holding other aircraft in other rows, gives
    the values of the whole scenario's truth. Fails with a phase keyed by row or by the epoch."""
    import numpy as np
    from tertiary.core import geo
    from tertiary.simulate.ehs import EHS_COLUMNS, EhsConfig, ehs_parameters
    from tertiary.simulate.traffic import terminal_traffic
    cfg = _small_terminal()
    traffic = terminal_traffic(cfg.traffic, cfg.duration_s, cfg.dt, np.random.default_rng(3),
                               geo.LocalFrame(*cfg.origin))
    whole = traffic.window(0, traffic.steps + 1, every=True)
    k0 = 437                                      # not a multiple of the refresh period
    part = traffic.window(k0, 600)
    ehs = EhsConfig(**{c: 0.0 for c in EHS_COLUMNS}, refresh_s=4.0)
    rows = np.arange(len(part.truth_id))
    t = np.full(len(rows), 250.3)
    got, ok_p = ehs_parameters(part, rows, t, np.random.default_rng(0), ehs)
    want, ok_w = ehs_parameters(whole, part.truth_id, t + k0 * cfg.dt, np.random.default_rng(0), ehs)
    assert len(rows) > 5 and len(rows) < whole.n_aircraft and ok_p.sum() > 5
    assert np.array_equal(ok_p, ok_w)
    for c in EHS_COLUMNS:
        assert np.allclose(got[c][ok_p], want[c][ok_p], atol=1e-6), c
