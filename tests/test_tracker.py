"""Secondary tracker: initiation (three-scan / M-of-N), gating, assignment, coasting, deletion,
run isolation and the ``tracks`` table contract.

The tracker is exercised with a small constant-velocity Kalman filter written here (a real
6-state CV filter implementing the batched ``TrackFilter`` interface), and also with the
registered ``cv``/``singer`` filters when they are available.
"""

from __future__ import annotations

import importlib
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.filters.base import REGISTRY, Innovation, Output, TrackFilter, make_filter
from tertiary.contract import validate
from tertiary.stages.tracking.gating import assign
from tertiary.stages.tracking.tracker import TRACK_COLUMNS, TrackerConfig, track

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
DT = 4.0        # scan period of the test plots (s)


# --------------------------------------------------------------------------- test double


class CVDouble(TrackFilter):
    """Constant-velocity Kalman filter in x, y, z (white-noise acceleration, intensity ``q``),
    batched over tracks — a faithful implementation of the interface, used as a test double."""

    name = "cv_double"

    def __init__(self, q: float = 10.0, v0_sigma: float = 300.0):
        self.q, self.v0 = q, v0_sigma

    def init(self, z, r):
        x = np.zeros((len(z), 6))
        x[:, :3] = z
        p = np.zeros((len(z), 6, 6))
        p[:, [0, 1, 2], [0, 1, 2]] = r
        p[:, [3, 4, 5], [3, 4, 5]] = self.v0 ** 2
        return {"x": x, "P": p}

    def predict(self, state, dt):
        dt = np.asarray(dt, float)
        f = np.tile(np.eye(6), (len(dt), 1, 1))
        f[:, [0, 1, 2], [3, 4, 5]] = dt[:, None]
        q = np.zeros((len(dt), 6, 6))
        for i in range(3):
            q[:, i, i] = self.q * dt ** 3 / 3
            q[:, i, i + 3] = q[:, i + 3, i] = self.q * dt ** 2 / 2
            q[:, i + 3, i + 3] = self.q * dt
        return {"x": np.einsum("bij,bj->bi", f, state["x"]),
                "P": f @ state["P"] @ f.transpose(0, 2, 1) + q}

    def update(self, state, z, r, mask):
        x, p = state["x"], state["P"]
        s = p[:, :3, :3] + r[:, :, None] * np.eye(3)
        nu = z - x[:, :3]
        k = p[:, :, :3] @ np.linalg.inv(s)
        m = np.asarray(mask, bool)
        x_new = np.where(m[:, None], x + np.einsum("bij,bj->bi", k, nu), x)
        p_new = np.where(m[:, None, None], p - k @ p[:, :3, :], p)
        nis = np.einsum("bi,bi->b", nu, np.linalg.solve(s, nu[..., None])[..., 0])
        return ({"x": x_new, "P": p_new},
                Innovation(np.where(m[:, None], nu, np.nan), np.diagonal(s, axis1=1, axis2=2).copy(),
                           np.where(m, nis, np.nan)))

    def output(self, state):
        return Output(state["x"].copy(), np.diagonal(state["P"], axis1=1, axis2=2).copy())


def test_cv_double_is_a_kalman_filter():
    """Sanity of the double: a noise-free straight line is tracked to its velocity."""
    f = CVDouble(q=0.1)
    st = f.init(np.array([[0.0, 0.0, 1000.0]]), np.full((1, 3), 100.0))
    for k in range(1, 8):
        st = f.predict(st, np.array([DT]))
        st, inn = f.update(st, np.array([[200.0 * DT * k, 0.0, 1000.0]]), np.full((1, 3), 100.0), np.array([True]))
    out = f.output(st)
    assert out.x[0, 3] == pytest.approx(200.0, abs=1.0)
    assert np.isfinite(inn.nis[0])


# --------------------------------------------------------------------------- plot builders


def _line(p0, v, ks, tid, run=0, noise=0.0, seed=0):
    """Plots (run, k, tid, x, y, z) of an aircraft at p0 + v·k·DT at scans ``ks``."""
    rng = np.random.default_rng(seed)
    p0, v = np.asarray(p0, float), np.asarray(v, float)
    return [(run, k, tid, *(p0 + v * k * DT + rng.normal(0.0, noise, 3))) for k in ks]


def _fused(rows, sigma=(30.0, 30.0, 60.0), method="aposteriori") -> pl.DataFrame:
    """A ``fused`` frame (one method) from (run, scan, target_id, x, y, z) rows."""
    cov = np.zeros(36)
    cov[[0, 7, 14]] = np.square(sigma)
    cov[[21, 28, 35]] = 25.0
    return pl.DataFrame({
        "run": [r[0] for r in rows],
        "epoch": [T0 + timedelta(seconds=DT * r[1]) for r in rows],
        "target_id": [r[2] for r in rows],
        "method": method,
        "x_m": [r[3] for r in rows], "y_m": [r[4] for r in rows], "z_m": [r[5] for r in rows],
        "vx_mps": 0.0, "vy_mps": 0.0, "vz_mps": 0.0,
        "cov": [cov.tolist()] * len(rows),
    }, schema_overrides={"run": pl.UInt32, "target_id": pl.UInt64, "epoch": pl.Datetime("us", "UTC"),
                         "cov": pl.Array(pl.Float64, 36)})


def _scan(epoch) -> int:
    return int(round((epoch - T0).total_seconds() / DT))


def _by_track(tracks: pl.DataFrame) -> dict:
    """{(run, track_id): list of (scan, status, plot_target_id)} in time order."""
    out: dict = {}
    for r in tracks.sort("run", "track_id", "epoch").iter_rows(named=True):
        out.setdefault((r["run"], r["track_id"]), []).append((_scan(r["epoch"]), r["status"], r["plot_target_id"]))
    return out


A = dict(p0=(0.0, 0.0, 3000.0), v=(200.0, 0.0, 0.0))           # eastbound
B = dict(p0=(0.0, 20000.0, 5000.0), v=(0.0, -150.0, 0.0))      # southbound, far from A


def _two_aircraft(ks=range(20), skip_a=(), noise=20.0, run=0):
    return (_line(**A, ks=[k for k in ks if k not in skip_a], tid=1, run=run, noise=noise, seed=1)
            + _line(**B, ks=ks, tid=2, run=run, noise=noise, seed=2))


# --------------------------------------------------------------------------- initiation & ids


def test_two_straight_aircraft_give_two_stable_tracks():
    tracks = track(_fused(_two_aircraft()), CVDouble())
    per = _by_track(tracks)
    assert sorted(per) == [(0, 1), (0, 2)]
    for rows in per.values():
        scans = [s for s, _, _ in rows]
        assert scans == list(range(2, 20))                # confirmed on scan 3, then every scan
        assert {st for _, st, _ in rows} == {"confirmed"}
        assert len({tid for _, _, tid in rows}) == 1      # one aircraft per track, no swap
    assert {rows[0][2] for rows in per.values()} == {1, 2}
    assert tracks["filter"].unique().to_list() == ["cv_double"]
    assert tracks["method"].unique().to_list() == ["aposteriori"]


def test_three_scan_counts_measured_plots_not_a_targets_extrapolations():
    """One radar scanning every third epoch: each target has a fused row at every epoch, but only
    every third holds a measured plot (``n_fresh`` > 0), the others extrapolate it. A target with
    one measured plot and its extrapolations gets no track (counted as scans, its extrapolations
    would confirm one at epoch 2); a target measured at epochs 0, 3, 6 is confirmed at 6, its
    third measured scan."""
    one = _line(**A, ks=range(9), tid=1)
    slow = _line(**B, ks=range(10), tid=2)
    fresh = [int(k == 0) for _, k, *_ in one] + [int(k % 3 == 0) for _, k, *_ in slow]
    f = _fused(one + slow).with_columns(pl.Series("n_fresh", fresh, pl.UInt32))
    per = _by_track(track(f, CVDouble()))
    assert [rows[0][2] for rows in per.values()] == [2]
    assert next(iter(per.values()))[0][:2] == (6, "confirmed")
    waits = _by_track(track(f, CVDouble(), TrackerConfig(initiation_gap_s=DT * 2.5)))
    assert waits == {}                              # a wait shorter than the scan: never confirmed


def test_track_ids_increase_with_confirmation_time():
    rows = _line(**A, ks=range(12), tid=1, seed=1) + _line(**B, ks=range(5, 12), tid=2, seed=2)
    per = _by_track(track(_fused(rows), CVDouble()))
    first = {k[1]: v[0][0] for k, v in per.items()}
    assert first == {1: 2, 2: 7}


def test_tracks_table_validates_and_has_extra_columns():
    tracks = track(_fused(_two_aircraft(skip_a=(8,))), CVDouble())
    clean = validate(tracks, "tracks")
    assert clean.height == tracks.height
    assert dict(tracks.schema) == TRACK_COLUMNS
    coasting = tracks.filter(pl.col("status") == "coasting")
    assert coasting.height == 1
    assert coasting["innovation"].is_null().all() and coasting["nis"].is_null().all()
    assert coasting["plot_target_id"].is_null().all()
    confirmed = tracks.filter(pl.col("status") == "confirmed")
    assert confirmed["innovation"].list.len().eq(3).all() and confirmed["nis"].is_not_null().all()
    assert tracks["cov_diag"].arr.min().min() > 0
    assert tracks["model_probs"].is_null().all()                # single-model filter


def test_empty_input_gives_empty_tracks():
    out = track(_fused([]), CVDouble())
    assert out.height == 0 and dict(out.schema) == TRACK_COLUMNS


def test_one_method_only():
    rows = _fused(_two_aircraft(range(3)))
    both = pl.concat([rows, rows.with_columns(pl.lit("arithmetic").alias("method"))])
    with pytest.raises(ValueError, match="one method"):
        track(both, CVDouble())


# --------------------------------------------------------------------------- coasting & deletion


def test_missed_plot_coasts_then_continues_with_same_id():
    per = _by_track(track(_fused(_two_aircraft(skip_a=(8,))), CVDouble()))
    a = next(rows for rows in per.values() if rows[0][2] == 1)
    assert len(per) == 2
    assert [s for s, _, _ in a] == list(range(2, 20))
    assert a[6] == (8, "coasting", None)
    assert a[7][:2] == (9, "confirmed") and a[7][2] == 1


def test_two_misses_still_continue():
    per = _by_track(track(_fused(_two_aircraft(skip_a=(8, 9))), CVDouble(), TrackerConfig(max_misses=3)))
    assert len(per) == 2
    a = next(rows for rows in per.values() if rows[0][2] == 1)
    assert [st for s, st, _ in a if s in (8, 9, 10)] == ["coasting", "coasting", "confirmed"]


def test_more_than_max_misses_deletes_and_restarts_with_new_id():
    per = _by_track(track(_fused(_two_aircraft(skip_a=(8, 9, 10))), CVDouble(), TrackerConfig(max_misses=3)))
    a_tracks = {k: v for k, v in per.items() if any(t == 1 for _, _, t in v)}
    assert len(a_tracks) == 2
    (old_id, old), (new_id, new) = sorted(a_tracks.items())
    assert [(s, st) for s, st, _ in old[-3:]] == [(7, "confirmed"), (8, "coasting"), (9, "coasting")]
    assert new[0][:2] == (13, "confirmed")           # plots resume at scan 11: 11, 12, 13
    assert new_id[1] == 3                             # after the ids of A and B


def test_max_misses_one_means_no_coasting():
    tracks = track(_fused(_two_aircraft(skip_a=(8,))), CVDouble(), TrackerConfig(max_misses=1))
    assert tracks.filter(pl.col("status") == "coasting").height == 0
    assert tracks["track_id"].n_unique() == 3


def test_data_gap_of_a_whole_run_is_not_a_miss():
    """An epoch without any plot of a run leaves that run's tracks untouched."""
    rows = _two_aircraft(ks=[k for k in range(20) if k not in (8, 9, 10, 11)])
    per = _by_track(track(_fused(rows), CVDouble()))
    assert len(per) == 2
    for v in per.values():
        assert [s for s, _, _ in v] == [k for k in range(2, 20) if k not in (8, 9, 10, 11)]
        assert {st for _, st, _ in v} == {"confirmed"}


# --------------------------------------------------------------------------- clutter


def test_isolated_clutter_never_confirms():
    rng = np.random.default_rng(5)
    clutter = [(0, k, 100 + k, *rng.uniform(-60000, 60000, 2), rng.uniform(500, 9000)) for k in range(20)]
    tracks = track(_fused(_two_aircraft() + clutter), CVDouble())
    assert tracks["track_id"].n_unique() == 2
    assert tracks["plot_target_id"].drop_nulls().is_in([1, 2]).all()


def test_clutter_pair_in_the_annulus_without_third_plot_is_dropped():
    # scan 3 and 4: 600 m apart (inside the 120–1400 m annulus); nothing near x̂ at scan 5
    clutter = [(0, 3, 50, 30000.0, -30000.0, 4000.0), (0, 4, 51, 30600.0, -30000.0, 4000.0),
               (0, 5, 52, 40000.0, -30000.0, 4000.0)]
    tracks = track(_fused(_two_aircraft() + clutter), CVDouble())
    assert tracks["track_id"].n_unique() == 2


def test_annulus_rejects_too_slow_and_too_fast_pairs():
    slow = _line((10000.0, 10000.0, 2000.0), (5.0, 0.0, 0.0), range(6), tid=7)     # 20 m per scan < R_min
    fast = _line((-10000.0, 10000.0, 2000.0), (500.0, 0.0, 0.0), range(6), tid=8)  # 2 km per scan > R_max
    ok = _line((0.0, -10000.0, 2000.0), (100.0, 0.0, 0.0), range(6), tid=9)
    tracks = track(_fused(slow + fast + ok), CVDouble())
    assert tracks["plot_target_id"].drop_nulls().unique().to_list() == [9]


def test_m_of_n_rejects_clutter_pair():
    clutter = [(0, 3, 50, 30000.0, -30000.0, 4000.0), (0, 4, 51, 30600.0, -30000.0, 4000.0)]
    tracks = track(_fused(_two_aircraft() + clutter), CVDouble(), TrackerConfig(initiation="m_of_n"))
    assert tracks["track_id"].n_unique() == 2


# --------------------------------------------------------------------------- M-of-N


def _first_scan_of(per: dict, tid: int) -> tuple[int, str]:
    return next(v[0][:2] for v in per.values() if v[0][2] == tid)


def test_m_of_n_confirms_with_a_missed_scan():
    rows = _two_aircraft(ks=range(10), skip_a=(2,))       # B keeps the run observed on scan 2
    m_of_n = _by_track(track(_fused(rows), CVDouble(), TrackerConfig(initiation="m_of_n", m=3, n=4)))
    assert len(m_of_n) == 2
    assert _first_scan_of(m_of_n, 1) == (3, "confirmed")   # plots on scans 1, 2, 4 of 4
    three = _by_track(track(_fused(rows), CVDouble(), TrackerConfig(initiation="three_scan")))
    assert _first_scan_of(three, 1) == (3, "confirmed")    # the scan-2 hypothesis waits over the miss


def test_three_scan_extrapolates_over_an_epoch_gap():
    """Epochs without any plot of the run are no scans: x̂₃ is extrapolated over the real time."""
    rows = _line(**A, ks=[0, 1, 3, 4], tid=1, seed=3)
    per = _by_track(track(_fused(rows), CVDouble()))
    assert per[(0, 1)][0][:2] == (3, "confirmed")


def test_m_of_n_requires_m_plots_within_n_scans():
    rows = _two_aircraft(ks=range(12), skip_a=(1, 3, 5, 7, 9, 11))     # A on every other scan only

    def first_a(m, n):
        per = _by_track(track(_fused(rows), CVDouble(), TrackerConfig(initiation="m_of_n", m=m, n=n)))
        return next((v[0][0] for v in per.values() if v[0][2] == 1), None)

    assert first_a(3, 4) is None            # never 3 plots within 4 scans
    assert first_a(3, 5) == 4               # scans 0, 2, 4
    assert first_a(2, 3) == 2               # scans 0, 2


def test_m_of_n_two_aircraft():
    per = _by_track(track(_fused(_two_aircraft()), CVDouble(), TrackerConfig(initiation="m_of_n", m=3, n=4)))
    assert sorted(per) == [(0, 1), (0, 2)]
    assert all(v[0][0] == 2 for v in per.values())


# --------------------------------------------------------------------------- assignment


def _crossing_rows():
    """Two aircraft crossing at right angles; on the scan before the crossing the plots are
    displaced along the line between the aircraft (A's 0.7·D behind, B's 0.4·D towards A) so
    that B's plot is the nearest to both predictions."""
    kc = 8                                                      # crossing scan
    pa = lambda k: np.array([100.0 * DT * (k - kc), 0.0, 4000.0])   # noqa: E731  eastbound
    pb = lambda k: np.array([0.0, 100.0 * DT * (k - kc), 4000.0])   # noqa: E731  northbound
    rows = []
    for k in range(16):
        a, b = pa(k), pb(k)
        if k == kc - 1:
            u = b - a
            a, b = a - 0.7 * u, a + 0.4 * u
        rows += [(0, k, 1, *a), (0, k, 2, *b)]
    return rows, kc - 1


def test_crossing_pair_hungarian_keeps_identities():
    rows, k_bad = _crossing_rows()
    per = _by_track(track(_fused(rows, sigma=(20.0, 20.0, 20.0)), CVDouble(q=1.0),
                          TrackerConfig(assignment="hungarian", gate_min_m=300.0)))
    assert len(per) == 2
    for v in per.values():
        assert len({t for _, _, t in v if t is not None}) == 1             # no swap
        assert [st for s, st, _ in v if s == k_bad] == ["confirmed"]


def test_crossing_pair_nearest_neighbour_swaps():
    rows, k_bad = _crossing_rows()
    per = _by_track(track(_fused(rows, sigma=(20.0, 20.0, 20.0)), CVDouble(q=1.0),
                          TrackerConfig(assignment="nearest", gate_min_m=300.0)))
    track_a = next(v for v in per.values() if v[0][2] == 1)
    at_bad = dict((s, t) for s, _, t in track_a)[k_bad]
    assert at_bad == 2                      # A's track took B's plot: the greedy choice


def test_a_track_never_takes_a_plot_of_another_mode_s_address():
    """The greedy swap of the crossing above, with each aircraft's plots carrying its Mode S
    address: A's track holds A's address and B's plot is not in its gate, so no assignment
    (greedy either) can give A's track B's plot, identity and level. Plots without an
    address are gated on position as before."""
    rows, k_bad = _crossing_rows()
    fused = _fused(rows, sigma=(20.0, 20.0, 20.0)).with_columns(
        pl.when(pl.col("target_id") == 1).then(pl.lit("3c6444")).otherwise(pl.lit("4ca123")).alias("mode_s"))
    for assignment in ("nearest", "hungarian"):
        per = _by_track(track(fused, CVDouble(q=1.0), TrackerConfig(assignment=assignment, gate_min_m=300.0)))
        assert len(per) == 2
        for v in per.values():
            assert len({t for _, _, t in v if t is not None}) == 1, assignment      # no swap
    # without addresses (or with the rule off) the greedy tracker swaps, as above
    per = _by_track(track(fused, CVDouble(q=1.0), TrackerConfig(assignment="nearest", gate_min_m=300.0,
                                                                  use_mode_s=False)))
    track_a = next(v for v in per.values() if v[0][2] == 1)
    assert dict((s, t) for s, _, t in track_a)[k_bad] == 2


def _opposite_levels(offset_m: float = 650.0, a_from: int = 1, b_from: int = 0, y0_m: float = -224.0 * DT * 2):
    """Two Mode S aircraft at adjacent levels (300 m apart) on opposite tracks at 224 m/s, ``offset_m``
    apart across the track: A northbound from y0_m with plots from scan ``a_from``, B southbound
    with plots from scan ``b_from``, missing scan 2. With the defaults they pass each other at
    scan 2, so B's initiation hypothesis (B₀, B₁) finds A's plot inside its scan-3 circle, and
    no plot of its own."""
    a = _line((0.0, y0_m, 9479.0), (0.0, 224.0, 0.0), range(a_from, 12), 1, noise=20.0, seed=1)
    b = _line((offset_m, 224.0 * DT * 2, 9179.0), (0.0, -224.0, 0.0), [k for k in range(b_from, 12) if k != 2], 2,
              noise=20.0, seed=2)
    return _fused(a + b).with_columns(
        pl.when(pl.col("target_id") == 1).then(pl.lit("396321")).otherwise(pl.lit("396202")).alias("mode_s"))


def test_initiation_never_joins_plots_of_two_mode_s_addresses():
    """B's hypothesis may not confirm on A's plot (another address): one track per aircraft,
    each of its own plots only. Without the addresses the hypothesis confirms on A's plot with
    B's velocity, coasts off A's path and dies, and A and B each get a track of their own after
    it (three tracks for two aircraft)."""
    per = _by_track(track(_opposite_levels(), CVDouble(q=1.0)))
    assert len(per) == 2
    assert sorted({t for _, _, t in v if t is not None}.pop() for v in per.values()) == [1, 2]
    assert all(len({t for _, _, t in v if t is not None}) == 1 for v in per.values())
    blind = _by_track(track(_opposite_levels(), CVDouble(q=1.0), TrackerConfig(use_mode_s=False)))
    assert len(blind) == 3


def test_m_of_n_tentative_never_counts_a_plot_of_another_mode_s_address():
    """M-of-N (2 of 3): B's one-plot tentative (B₁) may not take A's plot A₂ from its annulus
    as its second hit (B misses scan 2): one track per aircraft. Without the addresses it is
    confirmed on A's plot, coasts and dies: three tracks for two aircraft."""
    scene = _opposite_levels(offset_m=1000.0, a_from=2, b_from=1, y0_m=0.0)
    cfg = TrackerConfig(initiation="m_of_n", m=2, n=3)
    per = _by_track(track(scene, CVDouble(q=1.0), cfg))
    assert len(per) == 2
    assert all(len({t for _, _, t in v if t is not None}) == 1 for v in per.values())
    blind = _by_track(track(scene, CVDouble(q=1.0), TrackerConfig(initiation="m_of_n", m=2, n=3, use_mode_s=False)))
    assert len(blind) == 3


def test_assign_hungarian_matches_brute_force():
    from scipy.optimize import linear_sum_assignment
    rng = np.random.default_rng(0)
    for trial in range(30):
        n_o, n_p = rng.integers(1, 9, 2)
        dense = rng.uniform(0, 10, (n_o, n_p))
        gated = rng.random((n_o, n_p)) < 0.5
        o, p = np.nonzero(gated)
        out = assign(o, p, dense[o, p], n_o, n_p, "hungarian")
        # reference: most gated assignments, then least cost
        big = 1e6
        ref = np.where(gated, dense, big)
        a, b = linear_sum_assignment(ref)
        keep = ref[a, b] < big
        assert (out >= 0).sum() == keep.sum()
        got = sum(dense[i, j] for i, j in enumerate(out) if j >= 0)
        assert got == pytest.approx(ref[a[keep], b[keep]].sum())
        assert all(gated[i, j] for i, j in enumerate(out) if j >= 0)
        assert len(set(out[out >= 0])) == (out >= 0).sum()


def test_assign_nearest_is_greedy_and_one_to_one():
    # objects 0, 1; plots 0, 1: both prefer plot 0, object 0 is closer to it
    o, p, c = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]), np.array([1.0, 2.0, 1.5, 5.0])
    assert assign(o, p, c, 2, 2, "nearest").tolist() == [0, 1]
    assert assign(o, p, c, 2, 2, "hungarian").tolist() == [1, 0]      # 2.0 + 1.5 < 1.0 + 5.0


# --------------------------------------------------------------------------- Monte-Carlo runs


def test_runs_never_mix():
    # run 0: aircraft A throughout; run 1: A's first two plots only, then a far aircraft C.
    # Mixing runs would let run 1's hypothesis (scan 0, scan 1) be confirmed by run 0's scan 2.
    run0 = _line(**A, ks=range(10), tid=1, run=0, seed=1)
    run1 = (_line(**A, ks=[0, 1], tid=11, run=1, seed=1)
            + _line((50000.0, 50000.0, 6000.0), (-150.0, 0.0, 0.0), range(10), tid=12, run=1, seed=4))
    tracks = track(_fused(run0 + run1), CVDouble())
    per = _by_track(tracks)
    assert sorted(per) == [(0, 1), (1, 1)]                 # ids are per run
    assert {t for _, _, t in per[(0, 1)]} == {1}
    assert {t for _, _, t in per[(1, 1)]} == {12}


def test_identical_runs_give_identical_tracks():
    rows = _two_aircraft(run=0) + _two_aircraft(run=3)
    tracks = track(_fused(rows), CVDouble())
    r0 = tracks.filter(pl.col("run") == 0).drop("run")
    r3 = tracks.filter(pl.col("run") == 3).drop("run")
    assert r0.equals(r3)


def test_monte_carlo_batch_matches_single_runs():
    rows = []
    for run in range(5):
        rows += _line(**A, ks=range(12), tid=1, run=run, noise=30.0, seed=10 + run)
        rows += _line(**B, ks=range(12), tid=2, run=run, noise=30.0, seed=20 + run)
    batch = track(_fused(rows), CVDouble())
    for run in range(5):
        single = track(_fused([r for r in rows if r[0] == run]), CVDouble())
        got = batch.filter(pl.col("run") == run)
        cols = ["track_id", "plot_target_id", "status"]
        assert got.select(cols).equals(single.select(cols))
        np.testing.assert_allclose(got["x_m"].to_numpy(), single["x_m"].to_numpy(), rtol=1e-9)


# --------------------------------------------------------------------------- configuration


@pytest.mark.parametrize("kw", [dict(initiation="two_scan"), dict(assignment="gnn"), dict(m=5, n=4),
                                dict(max_misses=0), dict(v_min_mps=400.0), dict(confirm_gate_m=0.0),
                                dict(alt_gate_m=-1.0), dict(alt_gate_m=float("nan"))])
def test_bad_config(kw):
    with pytest.raises(ValueError):
        TrackerConfig(**kw)


# --------------------------------------------------------------------------- registered filters


def _registered(name: str) -> TrackFilter:
    # an import error is a failure here, never a skip: the registry must hold every shipped filter
    for mod in ("linear", "singer", "imm", "turn"):
        importlib.import_module(f"tertiary.filters.{mod}")
    assert name in REGISTRY, f"filter {name!r} is not registered"
    return make_filter(name)


@pytest.mark.parametrize("name", ["cv", "singer", "imm_sym", "imm_ct"])
def test_registered_filters_track_two_aircraft(name):
    filt = _registered(name)
    tracks = track(_fused(_two_aircraft(skip_a=(8,))), filt)
    validate(tracks, "tracks")
    per = _by_track(tracks)
    assert len(per) == 2
    for v in per.values():
        assert v[0][0] == 2 and len({t for _, _, t in v if t is not None}) == 1
    assert tracks["filter"].unique().to_list() == [filt.name]


@pytest.mark.parametrize("name", ["cv", "singer", "imm_ct"])
def test_registered_filters_crossing_pair(name):
    filt = _registered(name)
    rows, _ = _crossing_rows()
    per = _by_track(track(_fused(rows, sigma=(20.0, 20.0, 20.0)), filt, TrackerConfig(gate_min_m=300.0)))
    assert all(len({t for _, _, t in v if t is not None}) == 1 for v in per.values())


# --------------------------------------------------------------------------- several methods / filters


class TwoModelDouble(CVDouble):
    """The CV double reporting (fixed) model probabilities, as a multiple-model filter does."""

    name = "two_model_double"

    def output(self, state):
        out = super().output(state)
        return Output(out.x, out.var, np.tile([0.75, 0.25], (len(out.x), 1)))


def test_model_probabilities_are_reported():
    tracks = track(_fused(_two_aircraft(ks=range(6))), TwoModelDouble())
    validate(tracks, "tracks")
    assert tracks["model_probs"].to_list() == [[0.75, 0.25]] * tracks.height


def test_track_methods_covers_every_method_and_filter():
    from tertiary.stages.tracking.tracker import track_methods
    rows = _fused(_two_aircraft(ks=range(8)))
    fused = pl.concat([rows, rows.with_columns(pl.lit("arithmetic").alias("method"))])
    out = track_methods(fused, {"a": CVDouble(), "b": TwoModelDouble()})
    validate(out, "tracks")
    counts = out.group_by("method", "filter").agg(pl.col("track_id").n_unique().alias("n")).sort("method", "filter")
    assert counts.rows() == [("aposteriori", "cv_double", 2), ("aposteriori", "two_model_double", 2),
                             ("arithmetic", "cv_double", 2), ("arithmetic", "two_model_double", 2)]


# --------------------------------------------------------------------------- measurements, freshness, tentative


def _with_meas(f: pl.DataFrame, zm: np.ndarray, rm: np.ndarray, age: np.ndarray, fresh=None) -> pl.DataFrame:
    """``f`` plus the fusion stage's measurement columns (``fresh`` False → null measurement)."""
    fresh = np.ones(f.height, bool) if fresh is None else np.asarray(fresh, bool)
    return f.with_columns(
        *(pl.Series(c, np.where(fresh, zm[:, i], np.nan)).fill_nan(None)
          for i, c in enumerate(("meas_x_m", "meas_y_m", "meas_z_m"))),
        pl.Series("meas_cov", rm.reshape(-1, 9), dtype=pl.Array(pl.Float64, 9)),
        pl.Series("age_s", age.astype(float)), pl.Series("n_fresh", fresh.astype(np.uint32)),
    ).with_columns(pl.when(pl.col("meas_x_m").is_not_null()).then(pl.col("meas_cov")).alias("meas_cov"))


def test_measurements_are_used_at_their_own_time():
    """Noise-free straight flight at 200 m/s; every plot was measured 1.5 s before its epoch
    (age_s = 1.5). The track, reported at the epoch, sits on the true epoch position; had the
    plots been taken as measured at the epoch it would lag by v·age = 300 m."""
    rows = _line(**A, ks=range(15), tid=1)
    f = _fused(rows)
    zm = f.select("x_m", "y_m", "z_m").to_numpy() - np.array([200.0 * 1.5, 0, 0])
    f = _with_meas(f, zm, np.tile(np.diag([30.0, 30.0, 60.0]) ** 2, (f.height, 1, 1)), np.full(f.height, 1.5))
    tr = track(f, make_filter("cv_full", q=0.01)).sort("epoch")
    last = tr.row(-1, named=True)
    assert abs(last["x_m"] - (200.0 * 14 * DT)) < 5.0
    naive = track(f.with_columns(pl.lit(0.0).alias("age_s")), make_filter("cv_full", q=0.01)).sort("epoch")
    assert abs(naive.row(-1, named=True)["x_m"] - (200.0 * 14 * DT)) > 250.0


def test_a_row_without_a_fresh_plot_holds_the_track_but_does_not_update_it():
    """At scan 10 the fused row is a re-extrapolation (n_fresh = 0, no measurement) displaced by
    300 m: the track keeps its prediction there (same estimate as with the plot missing) and
    is not counted a miss (status confirmed, it still names the plot's target)."""
    rows = _line(**A, ks=range(14), tid=1) + _line(**B, ks=range(14), tid=2)   # row 10: A at scan 10
    f = _fused(rows)
    z = f.select("x_m", "y_m", "z_m").to_numpy()
    z_shift = z.copy()
    z_shift[10, 1] += 300.0
    fresh = np.arange(f.height) != 10
    g = _with_meas(f.with_columns(pl.Series("y_m", z_shift[:, 1])), z,
                   np.tile(np.diag([30.0, 30.0, 60.0]) ** 2, (f.height, 1, 1)), np.zeros(f.height), fresh)
    at10 = (pl.col("epoch") == T0 + timedelta(seconds=DT * 10)) & (pl.col("track_id") == 1)
    held = track(g, CVDouble()).filter(at10).row(0, named=True)
    missing = track(_with_meas(f.filter(pl.Series(fresh)), z[fresh], np.tile(np.diag([30.0, 30.0, 60.0]) ** 2,
                                                                                (int(fresh.sum()), 1, 1)),
                               np.zeros(int(fresh.sum()))), CVDouble())
    coast = missing.filter(at10).row(0, named=True)
    assert held["status"] == "confirmed" and held["plot_target_id"] == 1 and coast["status"] == "coasting"
    assert held["y_m"] == pytest.approx(coast["y_m"], abs=1e-6)
    assert held["nis"] is None or np.isnan(held["nis"])


class _Spy(CVDouble):
    """Records the measurement covariances it is handed."""

    name = "spy"
    full_r = True

    def __init__(self):
        super().__init__()
        self.seen: list[np.ndarray] = []

    def init(self, z, r):
        return super().init(z, np.einsum("bii->bi", r))

    def update(self, state, z, r, mask):
        self.seen.append(np.asarray(r)[np.asarray(mask, bool)])
        return super().update(state, z, np.einsum("bii->bi", r), mask)


def test_full_measurement_covariance_reaches_full_r_filters():
    """A filter declaring ``full_r`` receives the 3×3 ``meas_cov`` (correlated terms intact)."""
    rows = _line(**A, ks=range(6), tid=1)
    f = _fused(rows)
    rm = np.array([[900.0, 500.0, 0.0], [500.0, 900.0, 0.0], [0.0, 0.0, 3600.0]])
    spy = _Spy()
    track(_with_meas(f, f.select("x_m", "y_m", "z_m").to_numpy(), np.tile(rm, (f.height, 1, 1)),
                     np.zeros(f.height)), spy)
    seen = np.concatenate([s for s in spy.seen if len(s)])
    assert seen.shape[1:] == (3, 3) and np.allclose(seen, rm)


def test_tentative_targets_never_reach_the_tracks():
    rows = _two_aircraft()
    f = _fused(rows).with_columns((pl.col("target_id") == 2).alias("tentative"))
    out = track(f, CVDouble())
    assert out["plot_target_id"].drop_nulls().unique().to_list() == [1]
    assert track(f.with_columns(pl.lit(True).alias("tentative")), CVDouble()).height == 0


def test_tracks_carry_the_full_six_by_six_covariance():
    """``cov`` (row-major 6×6): symmetric, its diagonal is ``cov_diag``, and it holds the
    position–velocity cross terms a Kalman filter builds up (non-zero)."""
    out = track(_fused(_two_aircraft()), make_filter("singer_full"))
    cov = np.asarray(out["cov"].to_numpy(), float).reshape(-1, 6, 6)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-9)
    np.testing.assert_allclose(np.einsum("nii->ni", cov), np.asarray(out["cov_diag"].to_numpy(), float))
    assert np.abs(cov[:, 0, 3]).min() > 0
    per_axis = track(_fused(_two_aircraft()), make_filter("singer"))
    c2 = np.asarray(per_axis["cov"].to_numpy(), float).reshape(-1, 6, 6)
    np.testing.assert_allclose(np.einsum("nii->ni", c2), np.asarray(per_axis["cov_diag"].to_numpy(), float))
    assert np.abs(c2[:, 0, 3]).min() > 0 and np.abs(c2[:, 0, 1]).max() == 0.0


# --------------------------------------------------------------------------- the tracker improves on its input


@pytest.mark.parametrize("fixture", ["small_terminal", "big_box_runs"])
def test_best_tracker_beats_its_fused_input(fixture, request):
    """End to end on simulated data: for every fusion method the best tracker's 3-D position
    RMSE is below that of the fused picture it tracks. With the tracker filtering
    the fused estimates themselves (before this change), this fixture's big-box gave
    information 22.47 m fused vs 22.76 m for the best tracker and arithmetic 26.62 vs 26.75:
    the test fails on a return to filtering the radars' correlated estimates. The tracker NEES stays near its 3 degrees of
    freedom (the χ² band is the evaluation stage's business; 1.5–6 catches a filter that
    counts the same information twice)."""
    from tertiary import pipeline

    ds = request.getfixturevalue(fixture)
    cfg = pipeline.PipelineConfig(methods=("arithmetic", "information", "bar_shalom_campo"),
                                  filters=("singer", "imm_sym"), safety=False, centralized=False)
    res = pipeline.process(ds, cfg)
    m = res.metrics.filter((pl.col("segment") == "all") & (pl.col("metric") == "rmse_pos_m"))
    for meth in cfg.methods:
        fused = m.filter((pl.col("stage") == "fusion") & (pl.col("method") == meth))["value"][0]
        best = m.filter((pl.col("stage") == "tracker") & pl.col("method").str.starts_with(f"{meth}+"))["value"].min()
        assert best < fused, (fixture, meth, best, fused)
    nees = res.metrics.filter((pl.col("segment") == "all") & (pl.col("metric") == "nees_mean")
                              & (pl.col("method").str.ends_with("+imm_sym")))["value"]
    assert len(nees) == 3 and ((nees > 1.5) & (nees < 6.0)).all()
    assert res.counts["confirmed_targets"] > 0
    assert res.tracks["cov"].null_count() == 0


# --------------------------------------------------------------------------- barometric altitude in association


def _stacked(skip_upper=(10, 11), climb_mps=0.0, gap_m=1830.0):
    """Two aircraft at one plan position, ``gap_m`` apart vertically (a radar's elevation makes
    their ENU heights ±600 m): the upper one without a Mode S address, missing ``skip_upper``
    scans; the lower one (Mode S) appears at scan 9. ``climb_mps``: the upper one climbs from
    scan 12 on. Fused rows with the barometric vertical channel."""
    rows, alt, ident = [], [], []
    rng = np.random.default_rng(7)
    for k in range(20):
        x, y = 200.0 * DT * k, 0.0
        h_up = 10700.0 + gap_m + climb_mps * DT * max(k - 12, 0)
        if k not in skip_upper:
            rows.append((0, k, 1, x + rng.normal(0, 20), y + rng.normal(0, 20), h_up + rng.normal(0, 600)))
            alt.append(h_up)
            ident.append(None)
        if k >= 9:
            rows.append((0, k, 2, x + rng.normal(0, 20), y + rng.normal(0, 20), 10700.0 + rng.normal(0, 600)))
            alt.append(10700.0)
            ident.append("3b24a4")
    f = _fused(rows, sigma=(30.0, 30.0, 600.0))
    return f.with_columns(pl.Series("alt_m", alt), pl.lit(0.0).alias("alt_rate_mps"), pl.lit(60.0).alias("alt_var_m2"),
                          pl.lit(0.0).alias("alt_cov_m2ps"), pl.lit(4.0).alias("alt_rate_var_m2ps2"),
                          pl.Series("mode_s", ident, dtype=pl.String))


def test_a_track_without_an_address_does_not_take_the_plot_of_an_aircraft_below_it():
    f = _stacked()
    first = lambda tracks: tracks.filter(pl.col("track_id") == tracks["track_id"].min())  # noqa: E731
    upper = first(track(f, make_filter("cv")))
    # the upper aircraft's track coasts through its missed scans: never the lower one's plot or level
    assert set(upper["plot_target_id"].drop_nulls().to_list()) == {1}
    assert (upper["alt_m"] > 12000.0).all()
    # without the altitude in association the same scene swaps (the scene is one that can)
    swapped = first(track(f, make_filter("cv"), TrackerConfig(alt_gate_m=None)))
    assert 2 in swapped["plot_target_id"].drop_nulls().to_list()


def test_a_track_without_an_address_does_not_take_the_plot_of_the_aircraft_one_level_below():
    """Adjacent flight levels are 1 000 ft (304.8 m) apart: the altitude gate must not reach the
    next level, or a track that misses its own plot takes the one of the aircraft beneath."""
    f = _stacked(gap_m=304.8)
    first = lambda tracks: tracks.filter(pl.col("track_id") == tracks["track_id"].min())  # noqa: E731
    upper = first(track(f, make_filter("cv")))
    assert set(upper["plot_target_id"].drop_nulls().to_list()) == {1}
    assert (upper["alt_m"] > 10700.0 + 152.4).all()


def test_a_climb_stays_in_the_altitude_gate():
    f = _stacked(skip_upper=(), climb_mps=15.0)
    per = _by_track(track(f, make_filter("cv")))
    # two aircraft, two tracks, each on its own plots throughout
    assert len(per) == 2
    assert all(len({t for _, _, t in v if t is not None}) == 1 for v in per.values())
