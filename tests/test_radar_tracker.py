"""The simulated radars' own plot-to-track association (tertiary.simulate.radar_tracker)."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary import pipeline
from tertiary.simulate import RadarTrackerConfig, TransponderConfig, load_scenario, simulate, simulate_windows
from tertiary.simulate import radar_tracker as rt


def _scans(z: np.ndarray, t: np.ndarray, mode_s: np.ndarray | None = None, sigma: float = 30.0,
           period: float = 4.0) -> rt.ScanPlots:
    """Plots (scan, plot) → one partition's ScanPlots with isotropic noise σ."""
    n = len(t)
    return rt.ScanPlots(part=np.zeros(n, np.int64), t=t, z=z, r=np.broadcast_to(np.eye(2) * sigma ** 2, (n, 2, 2)).copy(),
                        mode_s=np.full(n, -1, np.int64) if mode_s is None else mode_s,
                        mode_3a=np.full(n, -1, np.int64), period=np.full(n, period),
                        drop_misses=np.full(n, 3, np.int64), scanned=np.zeros(0, np.int64))


def _crossing(rng, n_scans=40, period=4.0, sigma=30.0, angle_deg=20.0):
    """Two aircraft at 150 m/s crossing at ``angle_deg`` at scan n_scans/2 (same point, same time)."""
    k = np.arange(n_scans)
    t = k * period
    tc = t[n_scans // 2]
    ang = np.radians([0.0, angle_deg])
    v = 150.0 * np.stack([np.sin(ang), np.cos(ang)], 1)            # (2, 2)
    pos = (t - tc)[:, None, None] * v[None]                         # (scan, aircraft, 2)
    z = pos + rng.normal(0.0, sigma, pos.shape)
    return np.repeat(k, 2), np.repeat(t, 2), z.reshape(-1, 2), np.tile([0, 1], n_scans)


def test_ground_plot_covariance_is_the_jacobian_of_the_polar_noise():
    r, b, e = np.array([80_000.0, 20_000.0]), np.array([30.0, 250.0]), np.array([2.0, 15.0])
    sr, sb, se = 40.0, 0.07, 0.15
    z, cov = rt.ground_plots(r, b, e, sr, sb, se)
    np.testing.assert_allclose(z[:, 0], r * np.cos(np.radians(e)) * np.sin(np.radians(b)))

    def f(p):
        rho = p[0] * np.cos(np.radians(p[2]))
        return np.array([rho * np.sin(np.radians(p[1])), rho * np.cos(np.radians(p[1]))])
    for i in range(2):
        p0 = np.array([r[i], b[i], e[i]])
        h = np.array([1e-3, 1e-7, 1e-7])
        jac = np.column_stack([(f(p0 + dh) - f(p0 - dh)) / (2 * dh[j]) for j, dh in enumerate(np.diag(h))])
        np.testing.assert_allclose(cov[i], jac @ np.diag([sr ** 2, sb ** 2, se ** 2]) @ jac.T, rtol=1e-5)


def test_greedy_assignment_equals_sorted_greedy():
    rng = np.random.default_rng(3)
    for _ in range(20):
        ti, pj = rng.integers(0, 6, 25), rng.integers(0, 6, 25)
        key = np.unique(ti * 10 + pj, return_index=True)[1]
        ti, pj, c = ti[key], pj[key], rng.random(len(key))
        got = set(zip(*rt.greedy_assignment(ti, pj, c)))
        want, used_t, used_p = set(), set(), set()
        for i in np.argsort(c):                                     # the reference: sorted greedy
            if ti[i] not in used_t and pj[i] not in used_p:
                want.add((ti[i], pj[i]))
                used_t.add(ti[i])
                used_p.add(pj[i])
        assert {(int(a), int(b)) for a, b in got} == {(int(a), int(b)) for a, b in want}


def test_lowest_free_numbers_per_partition():
    live_part, live_num = np.array([0, 0, 0, 2]), np.array([1, 2, 4, 1])
    got = rt.lowest_free_numbers(live_part, live_num, np.array([0, 2, 0, 1, 0]))
    assert got.tolist() == [3, 2, 5, 1, 6]


def test_one_aircraft_one_track_and_break_after_misses_with_number_held():
    rng = np.random.default_rng(1)
    k = np.arange(30)
    z = np.column_stack([150.0 * 4.0 * k, np.zeros(30)]) + rng.normal(0, 30.0, (30, 2))
    keep = (k < 10) | (k >= 14)                                     # 4 missed scans: deleted (3 misses)
    scans = _scans(z[keep], 4.0 * k[keep])
    cfg = RadarTrackerConfig(reuse_after_scans=100)
    numbers, st = rt.run_scans(cfg, k[keep], scans, np.array([30]))
    numbers = numbers[:, 0]
    assert numbers[k[keep] < 10].tolist() == [1] * 10
    assert set(numbers[k[keep] >= 14].tolist()) == {2}               # a new track: 1 is still held
    assert len(st) == 1 and st.confirmed.all()
    numbers, _ = rt.run_scans(dataclasses.replace(cfg, reuse_after_scans=1), k[keep], scans, np.array([30]))
    numbers = numbers[:, 0]
    assert set(numbers[k[keep] >= 14].tolist()) == {1}               # number 1 reused


def test_crossing_swaps_without_mode_s_and_not_with_it():
    """Two aircraft crossing at 10°: the position-only tracker's numbers follow the plots, not
    the aircraft, in some crossings (5 of 12 seeds as measured); a Mode S gate keeps every
    track on its aircraft."""
    swapped = 0
    for seed in range(12):
        k, t, z, ac = _crossing(np.random.default_rng(seed), angle_deg=10.0)
        numbers, _ = rt.run_scans(RadarTrackerConfig(), k, _scans(z, t), np.array([40]))
        numbers = numbers[:, 0]
        swapped += int(numbers[(ac == 0) & (k > 22)][-1] != numbers[(ac == 0) & (k < 18)][-1])
        numbers, _ = rt.run_scans(RadarTrackerConfig(), k, _scans(z, t, mode_s=ac.astype(np.int64)), np.array([40]))
        numbers = numbers[:, 0]
        for a in (0, 1):
            assert len(set(numbers[ac == a].tolist())) == 1
    assert swapped >= 2


def test_step_is_a_pure_function_of_its_state():
    k, t, z, _ = _crossing(np.random.default_rng(0))
    scans = _scans(z, t)
    cfg = RadarTrackerConfig()
    whole, end = rt.run_scans(cfg, k, scans, np.array([40]))
    first = k < 17
    n1, mid = rt.run_scans(cfg, k[first], rt.ScanPlots(**{f: getattr(scans, f)[first] if f != "scanned" else scans.scanned
                                                           for f in scans.__dataclass_fields__}), np.array([17]))
    # resume from the carried state: the later scans' numbers are those of one uninterrupted pass
    rest = ~first
    st = mid
    out = []
    for kk in range(17, 40):
        rows = np.flatnonzero(k == kk)
        sc = rt.ScanPlots(**{f: getattr(scans, f)[rows] if f != "scanned" else np.array([0]) for f in scans.__dataclass_fields__})
        st, num = rt.step(cfg, st, sc)
        out.append(num)
    assert np.concatenate([n1, *out]).tolist() == whole.tolist()
    assert np.array_equal(st.number, end.number) and np.allclose(st.x, end.x)
    assert rest.any()


# --------------------------------------------------------------------------- in the simulator


@pytest.fixture(scope="module")
def no_mode_s():
    """Terminal area without Mode S (codes often undecoded): erring and ideal radar trackers."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=900.0, traffic=dataclasses.replace(cfg.traffic, aircraft=60, conflict_pairs=3),
                              transponders=TransponderConfig(mode_s_fraction=0.0, mode_3a_missing_rate=0.2))
    return simulate(cfg), simulate(dataclasses.replace(cfg, radar_tracker=RadarTrackerConfig(ideal=True)))


def _local_swaps(ds) -> int:
    """Consecutive plots of one live local track (gap ≤ 3.5 scans) from two different aircraft."""
    key = ["run", "radar_id", "local_track_id"]
    r = ds.reports.join(ds.radars.select("radar_id", "scan_period_s"), on="radar_id").sort(key + ["time"])
    r = r.with_columns((pl.col("time").diff().over(key).dt.total_microseconds() * 1e-6).alias("gap"),
                       pl.col("truth_id").shift(1).over(key).alias("prev"))
    return r.filter((pl.col("gap") <= 3.5 * pl.col("scan_period_s")) & (pl.col("truth_id") != pl.col("prev"))).height


def test_simulated_local_tracks_err_only_when_the_radars_do(no_mode_s):
    erring, ideal = no_mode_s
    assert _local_swaps(ideal) == 0
    assert _local_swaps(erring) > 5
    # reports are the same plots, numbered differently
    assert erring.reports.height == ideal.reports.height
    per = lambda ds: ds.reports.filter(pl.col("truth_id").is_not_null()).group_by(
        "radar_id", "truth_id").agg(pl.col("local_track_id").n_unique())["local_track_id"].mean()
    assert per(erring) > per(ideal)                                   # breaks and duplicates


@pytest.fixture(scope="module")
def association(no_mode_s):
    cfg = pipeline.PipelineConfig(methods=("arithmetic",), filters=(), centralized=False, safety=False)
    out = []
    for ds in no_mode_s:
        m = pipeline.process(ds, cfg).metrics.filter(pl.col("stage") == "association")
        out.append(dict(zip(m["metric"], m["value"])))
    return out


def test_association_quality_below_one_with_erring_radars_and_high_with_ideal_ones(association):
    erring, ideal = association
    assert erring["assoc_correct_frac"] < 1.0
    assert ideal["assoc_correct_frac"] >= 0.99
    assert erring["assoc_correct_frac"] < ideal["assoc_correct_frac"]
    assert erring["split_targets"] > ideal["split_targets"]
    assert {"swaps", "split_targets", "merged_targets"} <= set(erring)


# --------------------------------------------------------------------------- compiled loop


def _captured_scans(monkeypatch, cfg) -> list[tuple]:
    """The arguments of every :func:`rt.run_scans` call of a simulation of ``cfg`` (run by the
    Python reference, so each call's carried state is the reference's)."""
    calls = []
    reference = rt.run_scans

    def spy(rcfg, scan_index, plots, scans_of_part, state=None, compiled=None, job_plots=None):
        calls.append((rcfg, scan_index, plots, scans_of_part, state))
        return reference(rcfg, scan_index, plots, scans_of_part, state, compiled=False)
    monkeypatch.setattr(rt, "run_scans", spy)
    for _ in simulate_windows(cfg, 600.0)[2]:       # windows of 600 s: the state carried between them
        pass
    monkeypatch.setattr(rt, "run_scans", reference)
    return calls


def _assert_same_state(a: rt.RadarTrackState, b: rt.RadarTrackState) -> None:
    for f in (*rt.TRACK_FIELDS, "held_part", "held_number", "held_scans"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape, f
        if x.dtype.kind == "f":
            np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-9, err_msg=f)
        else:
            assert np.array_equal(x, y), f
    assert a.next_life == b.next_life


def test_compiled_scans_equal_the_python_reference(monkeypatch):
    """The compiled scan loop (radar_scan_kernel) numbers every plot as the Python step does
    and ends in the same state: terminal area in three 600 s blocks (state carried between
    them), 2 runs × 4 radars = 8 partitions, a third of the transponders without Mode S (so
    tracks swap, break and reuse numbers), numbers held 3 scans."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=1800.0, runs=2,
                              traffic=dataclasses.replace(cfg.traffic, aircraft=50, conflict_pairs=3),
                              transponders=TransponderConfig(mode_s_fraction=0.66, mode_3a_missing_rate=0.2),
                              radar_tracker=RadarTrackerConfig(reuse_after_scans=3))
    calls = _captured_scans(monkeypatch, cfg)
    assert len(calls) == 3 and calls[1][4] is not None and sum(len(c[1]) for c in calls) > 5_000  # not vacuous
    reused = 0
    for rcfg, scan_index, plots, scans_of_part, state in calls:
        want, want_state = rt.run_scans(rcfg, scan_index, plots, scans_of_part, state, compiled=False)
        got, got_state = rt.run_scans(rcfg, scan_index, plots, scans_of_part, state, compiled=True)
        assert np.array_equal(got, want)
        _assert_same_state(want_state, got_state)
        reused += len(want_state.held_part)
    assert reused > 0


def test_compiled_scans_resume_from_a_carried_state():
    """Half the scans by the Python reference, the rest compiled from its state: the numbers
    and the end state of one reference pass (the kernel takes a state it did not make)."""
    k, t, z, _ = _crossing(np.random.default_rng(4), n_scans=60, angle_deg=8.0)
    scans = _scans(z, t)
    cfg = RadarTrackerConfig(reuse_after_scans=2)
    whole, end = rt.run_scans(cfg, k, scans, np.array([60]), compiled=False)
    first = k < 25

    def sub(rows):
        return rt.ScanPlots(**{f: getattr(scans, f)[rows] if f != "scanned" else scans.scanned
                               for f in scans.__dataclass_fields__})
    n1, mid = rt.run_scans(cfg, k[first], sub(first), np.array([25]), compiled=False)
    n2, got = rt.run_scans(cfg, k[~first] - 25, sub(~first), np.array([35]), mid, compiled=True)
    assert np.concatenate([n1, n2]).tolist() == whole.tolist()
    _assert_same_state(end, got)


def test_compiled_scans_with_empty_scans_and_partitions_that_stop():
    """Scans without a plot still count misses; a partition with fewer scans stops missing
    (``scans_of_part``); both paths agree, track for track."""
    rng = np.random.default_rng(9)
    k = np.repeat(np.arange(20), 2)
    part = np.tile([0, 1], 20)
    keep = ~np.isin(k, [5, 6, 7, 8]) & ~((part == 1) & (k >= 12))
    z = np.column_stack([600.0 * k, 5_000.0 * part]) + rng.normal(0, 30.0, (len(k), 2))
    n = int(keep.sum())
    scans = rt.ScanPlots(part=part[keep].astype(np.int64), t=4.0 * k[keep], z=z[keep],
                         r=np.broadcast_to(np.eye(2) * 900.0, (n, 2, 2)).copy(), mode_s=np.full(n, -1, np.int64),
                         mode_3a=np.full(n, -1, np.int64), period=np.full(n, 4.0),
                         drop_misses=np.full(n, 3, np.int64), scanned=np.zeros(0, np.int64))
    for held in (0, 1, 5):
        cfg = RadarTrackerConfig(reuse_after_scans=held)
        want, ws = rt.run_scans(cfg, k[keep], scans, np.array([20, 12]), compiled=False)
        got, gs = rt.run_scans(cfg, k[keep], scans, np.array([20, 12]), compiled=True)
        assert np.array_equal(got, want)
        _assert_same_state(ws, gs)
    assert len(set(want[:, 1].tolist())) > 2                   # the gap broke the tracks: new lives


def test_a_small_job_does_not_wait_for_the_compiler(monkeypatch):
    """With the loop neither compiled nor cached, a job below ``COMPILE_PAYS_PLOTS`` runs the
    Python reference (a fresh install's first simulation is not slowed by ~12 s of
    compilation); a large job, or a ready loop, runs compiled."""
    k, t, z, _ = _crossing(np.random.default_rng(2))
    scans = _scans(z, t)
    used = []
    real = rt.run_scans_compiled
    monkeypatch.setattr(rt, "run_scans_compiled", lambda *a: used.append(True) or real(*a))
    for ready, job, want in ((False, 1_000, False), (False, rt.COMPILE_PAYS_PLOTS, True), (True, 1_000, True)):
        monkeypatch.setattr(rt, "is_ready", lambda ready=ready: ready)
        used.clear()
        rt.run_scans(RadarTrackerConfig(), k, scans, np.array([40]), job_plots=job)
        assert bool(used) is want, (ready, job)
