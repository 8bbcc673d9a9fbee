"""The bound made as the windows pass (:mod:`tertiary.evaluation.bound_streamed`) equals the
whole-run stage's (:func:`tertiary.evaluation.bound.bound_stage`): every aircraft's recursion
carried from window to window, its truth read a stretch at a time, its first Mode S report and
Cartesian plots carried, those still flying at the end finished there."""

from __future__ import annotations

import pickle
from datetime import datetime, timezone
from types import SimpleNamespace

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.core import geo
from tertiary.core.stage import T_MAX_US, Window
from tertiary.core.units import US
from tertiary.evaluation import bound_streamed as bs
from tertiary.evaluation.bound import bound_stage, scan_origins
from tertiary.evaluation.bound_pooling import pool_rows
from tertiary.evaluation.evaluate import write_reference

T0_US = int(datetime(2021, 10, 7, 8, 0, tzinfo=timezone.utc).timestamp()) * US
TIME = pl.Datetime("us", "UTC")
ORIGIN = geo.LocalFrame(48.0, 2.0, 0.0)
#: (truth_id, first s, last s, turn rate rad/s, first Mode S report s or None): two end early, one
#: turns, one is Mode A/C, one's first Mode S report comes late
AIRCRAFT = ((7, 0, 200, 0.0, 0), (8, 20, 420, 0.02, None), (9, 60, 900, 0.0, 0), (10, 300, 900, 0.01, 500))
#: aircraft 9's truth has no sample in this span (s): a gap, as ADS-B truth has
GAP = (400, 470)


def _times(t: np.ndarray) -> pl.Series:
    return pl.Series((T0_US + t * US).astype(np.int64)).cast(TIME)


def _truth() -> pl.DataFrame:
    out = []
    for k, (tid, a, b, w, _) in enumerate(AIRCRAFT):
        t = np.arange(a, b + 1, 1.0)
        heading = w * np.maximum(t - a - 60.0, 0.0)         # a turn from a minute in
        vx, vy = 120.0 * np.sin(heading), 120.0 * np.cos(heading)
        x = 15_000.0 * (k + 1) + np.cumsum(vx) - vx[0]
        y = -40_000.0 + np.cumsum(vy) - vy[0]
        frame = pl.DataFrame({"run": pl.Series(np.zeros(len(t)), dtype=pl.UInt32), "truth_id": tid,
                              "time": _times(t), "x_m": x, "y_m": y, "z_m": np.full_like(t, 3000.0 + 300 * k),
                              "vx_mps": vx, "vy_mps": vy, "vz_mps": 0.0})
        out.append(frame.filter(~pl.Series((t > GAP[0]) & (t < GAP[1]))) if tid == 9 else frame)
    return pl.concat(out).sort("time", "truth_id")


def _radars() -> pl.DataFrame:
    common = {"lat_deg": [48.0, 48.1], "lon_deg": [2.0, 2.1], "alt_m": [0.0, 0.0], "sigma_range_m": [50.0, 30.0],
              "sigma_azimuth_deg": [0.1, 0.0], "sigma_elevation_deg": [0.1, 0.0], "max_range_m": [200_000.0] * 2,
              "min_elevation_deg": [0.0, 0.0], "pd": [0.9, 1.0], "time_offset_s": [0.0, 0.0]}
    return pl.DataFrame({"radar_id": pl.Series([1, 2], dtype=pl.UInt32), "name": ["R", "M"], "kind": ["radar", "mlat"],
                         "scan_period_s": [4.0, 1.0], "timing": ["synchronous", "synchronous"], **common})


def _reports(truth: pl.DataFrame) -> pl.DataFrame:
    """Radar 1's reports (the scan phase; a Mode S address from each aircraft's first Mode S
    report on) every 4 s and the MLAT sensor's plots of aircraft 8 (stated σ on some) every 5 s."""
    since = {tid: -1 if ms is None else T0_US + ms * US for tid, *_, ms in AIRCRAFT}
    first = pl.col("truth_id").replace_strict(since, return_dtype=pl.Int64)
    radar = (truth.filter(pl.col("time").dt.epoch("us") % (4 * US) == US)
             .select(pl.lit(1, pl.UInt32).alias("radar_id"), "truth_id", "time", pl.lit(10.0).alias("azimuth_deg"),
                     pl.when((first >= 0) & (pl.col("time").dt.epoch("us") >= first))
                     .then(pl.format("{}", pl.col("truth_id"))).alias("mode_s")))
    plots = (truth.filter((pl.col("truth_id") == 8) & (pl.col("time").dt.epoch("us") % (5 * US) == 0))
             .select(pl.lit(2, pl.UInt32).alias("radar_id"), "truth_id", "time")
             .with_columns(pl.when(pl.int_range(pl.len()) % 2 == 0).then(20.0).alias("plot_sigma_x_m"),
                           pl.when(pl.int_range(pl.len()) % 2 == 0).then(25.0).alias("plot_sigma_y_m")))
    return pl.concat([radar, plots], how="diagonal_relaxed").sort("time")


def _samples(truth: pl.DataFrame) -> pl.DataFrame:
    k = pl.int_range(pl.len()).over("truth_id")
    base = truth.select("run", pl.col("time").alias("epoch"), "truth_id")
    seg = pl.when(pl.col("truth_id") == 8).then(pl.lit("turn")).otherwise(pl.lit("straight"))
    return (pl.concat([base.filter(k % 2 == 0).with_columns(pl.lit("a").alias("method")),
                       base.filter(k % 3 == 1).with_columns(pl.lit("b").alias("method"))])
            .with_columns(seg.alias("seg_class")).select("method", "run", "epoch", "truth_id", "seg_class"))


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    truth = _truth()
    ref = write_reference(truth, tmp_path_factory.mktemp("bound") / "reference.parquet")
    radars, reports = _radars(), _reports(truth)
    acc = pl.DataFrame({"stage": "fusion", "method": ["a", "b"], "metric": "rmse_pos_m", "segment": "all",
                        "value": [100.0, 90.0], "n_runs": 1})
    ds = SimpleNamespace(origin=ORIGIN, scenario=None)
    samples = _samples(truth)
    whole = bound_stage(ds, truth, radars, reports, samples, acc, [], scan_origins(radars, reports, T0_US))
    return SimpleNamespace(truth=truth, ref=ref, radars=radars, reports=reports, acc=acc, ds=ds, samples=samples,
                           whole=whole)


def _stepped(case, where, window_s: float, roundtrip: bool = False, open_last: bool = False
             ) -> tuple[bs.BoundSetup, bs.BoundState, list[int], bs.PartFiles]:
    """Every window stepped, its scored samples then stored as the run's parts are
    (``w=<index>.parquet`` under ``where``)."""
    setup = bs.bound_setup(case.ds, case.radars, ORIGIN, case.ref, case.reports.lazy())
    state, bounded = bs.BoundState(), []
    where.mkdir()
    w = int(window_s * US)

    def stored() -> list:
        return sorted(where.glob("w=*.parquet"))
    for k, a in enumerate(range(T0_US, T0_US + 901 * US, w)):
        inside = pl.col("epoch").dt.epoch("us").is_between(a, a + w, closed="left")
        now = pl.col("time").dt.epoch("us").is_between(a, a + w, closed="left")
        mine = case.samples.filter(inside)
        last = open_last and a + w > T0_US + 900 * US
        state = bs.bound_step(setup, state, mine, case.reports.filter(now),
                              Window(k, a, T_MAX_US if last else a + w), stored)
        mine.write_parquet(where / f"w={k}.parquet")
        if roundtrip:
            state = pickle.loads(pickle.dumps(state))
        bounded.append(state.bounded)
    return setup, state, bounded, stored


@pytest.mark.parametrize("halves", [False, True])
@pytest.mark.parametrize("advance_s", [0.0, 120.0])
@pytest.mark.parametrize("window_s", [30.0, 97.0, 1000.0])
def test_the_windows_bound_equals_the_whole_run_stage(case, monkeypatch, tmp_path, window_s, advance_s, halves):
    """The recursions are carried across the windows (taken on every window, or every 120 s; the
    aircraft of a step in one part, or in two halves at once),
    aircraft 7 and 8 done in the windows, 9 and 10 at the end; the rows equal the whole-run
    stage's. Fails if a recursion restarts from the prior, a row is counted twice or not at all,
    an aircraft's first Mode S report (10's comes at 500 s), its truth gap (9) or its MLAT plots
    (8) are not carried to it."""
    monkeypatch.setattr(bs, "ADVANCE_S", advance_s)
    monkeypatch.setattr(bs, "PARALLEL_AIRCRAFT", 2 if halves else 10 ** 6)
    setup, state, bounded, stored = _stepped(case, tmp_path / "parts", window_s)
    if window_s < 900:
        assert bounded[-1] == 2 and state.aircraft["truth_id"].to_list() == [9, 10], bounded
        assert state.tail.height < case.truth.height / 4, "the windows hold the truth instead of its tail"
        # the epochs no row can come to any more are pooled, not carried: the state does not
        # grow with the run
        assert state.pools is not None and state.pools["__k"].sum() > 0
        open_from = min(state.cut_us, int(state.aircraft["done_us"].min()))
        assert state.sums.select((pl.col("epoch").dt.epoch("us") >= open_from).all()).item()
    got = pool_rows(bs.bound_finish(setup, state, stored), case.acc)
    assert case.whole.height and set(case.whole["segment"]) == {"all", "straight", "turn"}
    assert_frame_equal(got, case.whole, check_exact=False, rel_tol=1e-9, abs_tol=0.0)


def test_an_aircraft_whose_samples_past_the_cut_are_too_few_waits(case, monkeypatch, tmp_path):
    """With truth read only 3 s past the cut, the acceleration near the cut (±10 s of samples)
    cannot be fitted: each aircraft is taken to the sample that has its samples after it, and on
    from there next time; the rows equal the whole-run stage's. Fails if the cut is not held
    back (the acceleration there clipped to the samples read)."""
    monkeypatch.setattr(bs, "ADVANCE_S", 0.0)
    monkeypatch.setattr(bs, "LOOKAHEAD_S", 3.0)
    setup, state, _, stored = _stepped(case, tmp_path / "parts", 30.0)
    assert (state.aircraft["done_us"] < state.cut_us).all()
    assert_frame_equal(pool_rows(bs.bound_finish(setup, state, stored), case.acc), case.whole, check_exact=False,
                       rel_tol=1e-9, abs_tol=0.0)


def test_a_runs_open_last_window_leaves_the_aircraft_still_flying_to_the_end(case, monkeypatch, tmp_path):
    """The last window of a run is open: it takes no recursion on (the end does, beside its
    evaluation), so aircraft 9 and 10 are carried after it and 7, 8 were done before; the rows
    equal the whole-run stage's. Fails if the open window takes the recursions on."""
    setup, state, bounded, stored = _stepped(case, tmp_path / "parts", 97.0, open_last=True)
    assert bounded[-1] == bounded[-2] == 2 and state.aircraft["truth_id"].to_list() == [9, 10], bounded
    assert int(state.aircraft["done_us"].max()) < T0_US + 800 * US
    assert_frame_equal(pool_rows(bs.bound_finish(setup, state, stored), case.acc), case.whole, check_exact=False,
                       rel_tol=1e-9, abs_tol=0.0)


def test_the_state_pickles(case, tmp_path):
    """A state pickled after each window bounds the same."""
    setup, state, bounded, stored = _stepped(case, tmp_path / "parts", 30.0, roundtrip=True)
    assert bounded[-1] == 2
    assert_frame_equal(pool_rows(bs.bound_finish(setup, state, stored), case.acc), case.whole, check_exact=False,
                       rel_tol=1e-9, abs_tol=0.0)


def test_a_window_without_scored_samples_hands_the_bound_to_the_end(case):
    setup = bs.bound_setup(case.ds, case.radars, ORIGIN, case.ref, case.reports.lazy())
    state = bs.bound_step(setup, bs.BoundState(), case.samples.head(10), case.reports.head(3),
                          Window(0, T0_US, T0_US + 30 * US), list)
    assert state.windows and state.complete
    state = bs.bound_step(setup, state, None, case.reports.clear(), Window(1, T0_US + 30 * US, T0_US + 60 * US), list)
    assert not state.complete and not state.windows
    late = Window(2, T0_US + 60 * US, T0_US + 2000 * US)
    assert not bs.bound_step(setup, state, case.samples, case.reports, late, list).complete


def test_the_scan_origins_read_from_a_scan_equal_those_of_a_frame(case, tmp_path):
    path = tmp_path / "reports.parquet"
    case.reports.write_parquet(path)
    frame = scan_origins(case.radars, case.reports, T0_US)
    assert frame == scan_origins(case.radars, pl.scan_parquet(path), T0_US) and set(frame) == {1}
    assert frame[1] == pytest.approx(1.0)


@pytest.fixture(scope="module")
def mlat_run():
    """A terminal area with an MLAT system (20 aircraft, 300 s) processed in memory."""
    import dataclasses

    from tertiary import pipeline
    from tertiary.simulate import load_scenario, simulate
    sc = load_scenario("terminal-area-mlat")
    sc = dataclasses.replace(sc, radars=sc.radars[:2], duration_s=300.0,
                             traffic=dataclasses.replace(sc.traffic, aircraft=20))
    ds = simulate(sc)
    cfg = pipeline.PipelineConfig(methods=("information",), filters=("singer",), centralized=False, safety=False)
    return ds, cfg, pipeline.process(ds, cfg, window_s=60.0)


@pytest.mark.parametrize("in_windows", [True, False])
def test_a_run_on_disk_bounds_mlat_plots_as_in_memory(mlat_run, tmp_path, monkeypatch, in_windows):
    """On disk the bound takes each MLAT plot's stated covariance as a run in memory does, made
    in the windows or (``in_windows`` False) over the whole recording at the end, from the stored
    reports. Fails if either takes the sensor's nominal σ (the stored reports without the plots'
    stated accuracy)."""
    from tertiary import pipeline
    from tertiary.pipeline import streaming
    from tertiary.store.run_store import RunStore
    ds, cfg, mem = mlat_run
    if not in_windows:
        monkeypatch.setattr(streaming, "bound_setup", lambda *a, **k: None)
    pipeline.run(ds, tmp_path / "run", cfg, window_s=60.0)
    with RunStore.open(tmp_path / "run") as st:
        disk = st.read("metrics").filter(pl.col("stage") == "bound")
    want = mem.metrics.filter(pl.col("stage") == "bound")
    assert want.height and "mlat" in ds.radars["kind"].to_list()
    keys = ["method", "metric", "segment"]
    assert_frame_equal(disk.select(*keys, "value").sort(keys), want.select(*keys, "value").sort(keys),
                       check_exact=False, rel_tol=1e-9, abs_tol=0.0)


def test_the_scan_origins_of_an_input_in_other_dtypes_are_those_of_the_cast_columns(case):
    """The scan origins are read from the input before validation: columns in other dtypes are
    cast as validation casts them (a value that cannot be cast left out), and a column that cannot
    be cast at all is the contract's one-line error, not a traceback."""
    from tertiary.contract.errors import SchemaError
    want = scan_origins(case.radars, case.reports, T0_US)
    text = case.reports.select(pl.col("radar_id").cast(pl.String), pl.col("time").dt.to_string("%Y-%m-%dT%H:%M:%S%.f"),
                               pl.col("azimuth_deg").cast(pl.String))
    bad = pl.DataFrame({"radar_id": ["1"], "time": ["not a time"], "azimuth_deg": ["north"]})
    assert scan_origins(case.radars, pl.concat([text, bad]).lazy(), T0_US) == pytest.approx(want, abs=1e-9)
    with pytest.raises(SchemaError, match="column 'time'"):
        scan_origins(case.radars, case.reports.with_columns(pl.col("time").dt.epoch("s").cast(pl.Float64)), T0_US)


def test_truth_gaps_in_parts_equal_the_whole_truth_sorted_at_once():
    """Each aircraft's truth spacing taken over a few aircraft at a time (the memory of a day's
    truth) equals the spacing of the whole truth, with incomplete rows and repeated times left out."""
    from tertiary.evaluation.bound_truth import COLUMNS, _gap_frame, _samples, truth_gaps
    rng = np.random.default_rng(5)
    n = 4_000
    ids = rng.integers(0, 37, n)
    t = np.sort(rng.choice(np.arange(0, 200_000), n, replace=False)) * 50_000
    truth = pl.DataFrame({"truth_id": ids, "time": t}).with_columns(
        pl.col("time").cast(pl.Datetime("us", "UTC")),
        *[pl.Series(c, rng.normal(size=n)) for c in COLUMNS[2:]])
    truth = truth.with_columns(pl.when(pl.int_range(n) % 23 == 0).then(None).otherwise(pl.col("vx_mps"))
                               .alias("vx_mps"))
    truth = pl.concat([truth, truth.gather(np.arange(0, n, 3)).with_columns(pl.col("x_m") + 1.0)])   # times repeated
    whole = _gap_frame(_samples(truth.lazy()), 0).collect().sort("truth_id")
    assert whole.height > 30
    for part_rows in (n, 500, 97):
        assert_frame_equal(truth_gaps(truth.lazy(), 0, part_rows), whole)


def test_reference_gaps_from_neighbour_times_equal_the_sorted_spacings():
    """The spacings read off a reference's neighbour times (rows in time order, as the run's
    reference files hold them, and shuffled) equal those of the truth sorted per aircraft."""
    from tertiary.evaluation.bound_truth import COLUMNS, reference_gaps, truth_gaps
    from tertiary.evaluation.matching import with_neighbours
    rng = np.random.default_rng(11)
    n = 5_000
    ids = rng.integers(0, 41, n)
    t = np.sort(rng.choice(np.arange(0, 300_000), n, replace=False)) * 40_000
    truth = pl.DataFrame({"truth_id": ids, "time": t}).with_columns(
        pl.col("time").cast(pl.Datetime("us", "UTC")), *[pl.Series(c, rng.normal(size=n)) for c in COLUMNS[2:]])
    want = truth_gaps(truth.lazy(), 123)
    reference = with_neighbours(truth)
    assert want.height > 35 and reference["__prev"].null_count() == truth["truth_id"].n_unique()
    for frame in (reference, reference.sample(fraction=1.0, shuffle=True, seed=3)):
        for part_rows in (n, 700, 97):
            assert_frame_equal(reference_gaps(frame.lazy(), 123, part_rows), want)
    with pytest.raises(ValueError, match="__prev"):
        reference_gaps(truth.lazy(), 0)
