"""The align stage as a step function (docs: /work/notes/stream_contract.md): any cut of
the run into consecutive time windows gives the whole-run alignment's rows and rejects."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.stages import align
from tertiary.core.errors import OptionError
from tertiary.sensors.local_tracks import LocalTrackerConfig

US = 1_000_000
ALIGNED_KEY = ["run", "epoch", "radar_id", "local_track_id", "report_id"]
PLOT_COLUMNS = ["report_id", "run", "radar_id", "time", "local_track_id", "range_m", "azimuth_deg",
                "elevation_deg", "altitude_m", "mode_s", "mode_3a", "callsign", "truth_id"]


@dataclasses.dataclass
class Case:
    reports: pl.DataFrame
    radars: pl.DataFrame
    origin: object
    cfg: align.AlignConfig

    @property
    def times(self) -> np.ndarray:
        return self.reports["time"].dt.epoch("us").to_numpy()

    @property
    def grid(self) -> int:
        return align.grid_origin_us(int(self.times.min()))


def _with_estimates(ds) -> Case:
    """Reports with the radars' estimates, an epoch period (12 s) coarser than most scans
    (superseded and too-old rejects), collection delays up to 9 s on 30 % of the reports (first
    epochs after the window end), 1 % diverged estimates, the conversion flag and identity."""
    rng = np.random.default_rng(3)
    n = ds.reports.height
    rep = ds.reports.with_columns(
        pl.Series("collection_delay_s", rng.uniform(0.0, 9.0, n) * (rng.random(n) < 0.3)),
        pl.when(pl.Series(rng.random(n) < 0.01)).then(900.0).otherwise(pl.col("vx_mps")).alias("vx_mps"))
    return Case(rep, ds.radars, ds.origin, align.AlignConfig(period_s=12.0, conversion_gate="flag", identity=True))


def _plots_only(ds) -> Case:
    """Plot-only reports (no estimate columns: the package's local tracker runs), a restart gap
    of 1.2 scans (hundreds of restarted lives), wide azimuth sigmas with the conversion gate
    rejecting (seed 002 (13) fails at long range)."""
    radars = ds.radars.with_columns(pl.col("sigma_azimuth_deg") * 8.0)
    return Case(ds.reports.select(PLOT_COLUMNS), radars, ds.origin,
                align.AlignConfig(restart_gap_scans=1.2, conversion_gate="reject"))


@pytest.fixture(scope="module")
def estimates_case(small_terminal) -> Case:
    return _with_estimates(small_terminal)


@pytest.fixture(scope="module")
def plots_case(small_terminal) -> Case:
    return _plots_only(small_terminal)


def _whole(case: Case) -> tuple[pl.DataFrame, pl.DataFrame, int]:
    p = align.plan(case.reports, case.radars, case.origin, case.cfg)
    return align.expand(p, case.cfg), p.rejects, p.conversion_invalid


def _windowed(case: Case, cuts: list[int], roundtrip: bool = False
              ) -> tuple[pl.DataFrame, pl.DataFrame, align.AlignState]:
    """Concatenated step outputs over (-inf, c0), [c0, c1), ..., [c_last, +inf)."""
    t = case.times
    state = align.init_align_state()
    bounds = [None, *cuts, None]
    aligned, rejects = [], []
    for a, b in zip(bounds[:-1], bounds[1:]):
        sel = np.ones(len(t), bool) if a is None else t >= a
        if b is not None:
            sel &= t < b
        (al, rej), state = align.align_step(state, case.reports.filter(pl.Series(sel)), case.radars, case.origin,
                                            a, b, case.grid, case.cfg)
        if b is not None or a is not None:
            ep = al["epoch"].dt.epoch("us")
            assert (a is None or ep.min() is None or ep.min() >= a) and (b is None or ep.max() is None or ep.max() < b)
        aligned.append(al)
        rejects.append(rej)
        if roundtrip:                      # the engine checkpoints the state with pickle
            state = pickle.loads(pickle.dumps(state))
    return pl.concat(aligned, how="vertical"), pl.concat(rejects, how="vertical"), state


def _cuts(case: Case) -> dict[str, list[int]]:
    """Window cuts: 60 s; 2.5 s (< every scan period but the fastest: 4 s) over the first two
    minutes then 50 s; and an uneven cut with an empty window (between two report times)."""
    t = np.unique(case.times)
    lo, hi = int(t.min()), int(t.max())
    gaps = np.flatnonzero(np.diff(t) > 2)
    gap = gaps[len(gaps) // 2]
    empty = [int(t[gap]) + 1, int(t[gap + 1])]           # [t_a + 1 µs, t_b) holds no report
    return {"60s": list(range(lo + 7 * US, hi, 60 * US)),
            "short": [*range(lo + US // 3, lo + 120 * US, 2_500_000), *range(lo + 150 * US, hi, 50 * US)],
            "uneven+empty": sorted({lo + 33 * US, lo + 41 * US, *empty, hi - 17 * US})}


def _assert_same(case: Case, cuts: list[int], roundtrip: bool = False) -> align.AlignState:
    whole, whole_rej, conv_bad = _whole(case)
    got, got_rej, state = _windowed(case, cuts, roundtrip)
    assert whole.height > 1000 and whole_rej.height > 50          # the cases exercise rows and rejects
    assert_frame_equal(got.sort(ALIGNED_KEY), whole.sort(ALIGNED_KEY), rel_tol=1e-9, abs_tol=1e-9)
    assert_frame_equal(got_rej.sort("report_id"), whole_rej.sort("report_id"))
    assert state.held is None and state.conversion_invalid == conv_bad
    return state


@pytest.mark.parametrize("cut", ["60s", "short", "uneven+empty"])
def test_windows_equal_whole_run_with_estimates(estimates_case, cut):
    _assert_same(estimates_case, _cuts(estimates_case)[cut])


@pytest.mark.parametrize("cut", ["60s", "short", "uneven+empty"])
def test_windows_equal_whole_run_plots_only(plots_case, cut):
    """The local tracker's filters and restart-gap lives carry across windows."""
    assert align.needs_estimates(plots_case.reports)
    state = _assert_same(plots_case, _cuts(plots_case)[cut])
    assert state.tracks is not None


def test_single_unbounded_step_is_the_whole_run(estimates_case):
    _assert_same(estimates_case, [])




def test_rejects_of_pending_reports_come_once(estimates_case):
    """Coarse epochs + delays: some decisions wait for the next window; still one reject each."""
    _, rej, _ = _windowed(estimates_case, _cuts(estimates_case)["short"])
    assert rej["report_id"].is_unique().all()














def test_chapter3_local_tracker_refused_in_windows(plots_case):
    """The chapter 3 range channels are sized on the whole run: windowed, a clear OptionError."""
    case = plots_case
    cfg = dataclasses.replace(case.cfg, local_tracker=LocalTrackerConfig(range_channel="kinematic"))
    t1 = int(np.median(case.times))
    with pytest.raises(OptionError, match="window"):
        align.align_step(align.init_align_state(), case.reports.filter(pl.Series(case.times < t1)), case.radars,
                         case.origin, None, t1, case.grid, cfg)


def test_grid_origin_is_a_parameter(estimates_case):
    """The default origin is the earliest report floored to the second; another origin moves
    every epoch onto its own grid."""
    case = estimates_case
    base, _ = align.align(case.reports, case.radars, case.origin, case.cfg)
    same, _ = align.align(case.reports, case.radars, case.origin, case.cfg, grid_origin_us=case.grid)
    assert_frame_equal(base, same)
    shifted_origin = case.grid - 7 * US - 250_000
    shifted, _ = align.align(case.reports, case.radars, case.origin, case.cfg, grid_origin_us=shifted_origin)
    offsets = (shifted["epoch"].dt.epoch("us").to_numpy() - shifted_origin) % int(12 * US)
    assert shifted.height > 1000 and np.all(offsets == 0)
    assert not np.all((base["epoch"].dt.epoch("us").to_numpy() - shifted_origin) % int(12 * US) == 0)


# --------------------------------------------------------------------------- a held report's next report


def _synthetic(rows: list[tuple[float, float, float]]) -> pl.DataFrame:
    """One local track of a 12 s radar: (time s, collection delay s, vx m/s) per report."""
    t0 = 1_633_608_000 * US
    cov = np.diag([100.0, 100.0, 400.0, 4.0, 4.0, 1.0]).ravel().tolist()
    return pl.DataFrame({
        "report_id": pl.Series(range(len(rows)), dtype=pl.UInt64), "run": pl.Series([0] * len(rows), dtype=pl.UInt32),
        "radar_id": pl.Series([2] * len(rows), dtype=pl.UInt32),
        "local_track_id": pl.Series([3] * len(rows), dtype=pl.UInt32),
        "time": pl.Series([t0 + int(t * US) for t, _, _ in rows]).cast(pl.Datetime("us", "UTC")),
        "collection_delay_s": [d for _, d, _ in rows],
        "x_m": [5000.0 + vx * t for t, _, vx in rows], "y_m": [0.0] * len(rows), "z_m": [2000.0] * len(rows),
        "vx_mps": [vx for _, _, vx in rows], "vy_mps": [0.0] * len(rows), "vz_mps": [0.0] * len(rows),
        "est_cov": pl.Series([cov] * len(rows), dtype=pl.Array(pl.Float64, 36)),
        "range_m": [5400.0] * len(rows), "azimuth_deg": [90.0] * len(rows), "est_elevation_deg": [2.0] * len(rows),
        "res_range_m": [1.0] * len(rows), "res_range_var_m2": [2.0] * len(rows)})


@pytest.mark.parametrize("rows", [
    # A kept until B's first epoch (16 s: 9 s + 5 s delay), B diverged (rejected, not held), C at 21 s
    [(0.5, 0.0, 100.0), (9.0, 5.0, 900.0), (21.0, 0.0, 100.0)],
    # B delayed to epoch 16 is too old once C (9.5 s, epoch 12) arrives; A still ends before B's epoch
    [(0.5, 0.0, 100.0), (9.0, 5.0, 100.0), (9.5, 0.0, 100.0), (30.0, 0.0, 100.0)],
], ids=["next-rejected-unusable", "next-rejected-too-old"])
def test_held_report_keeps_its_next_report_epoch(rows):
    """A report whose next report was seen (and rejected, so not held) keeps that report's first
    epoch as its end: it must not be re-linked to a later report in the next window."""
    from test_align import _radars
    from tertiary.core import geo
    case = Case(_synthetic(rows), _radars(), geo.LocalFrame(48.75, 2.5, 0.0), align.AlignConfig(period_s=4.0))
    whole, whole_rej, _ = _whole(case)
    assert whole_rej.height == 1
    got, got_rej, state = _windowed(case, [int(case.times.min()) + 9_500_000 + 500_000])
    assert_frame_equal(got.sort(ALIGNED_KEY), whole.sort(ALIGNED_KEY), rel_tol=1e-9, abs_tol=1e-9)
    assert_frame_equal(got_rej.sort("report_id"), whole_rej.sort("report_id"))


def test_local_tracker_step_equals_one_call(small_terminal):
    """tertiary.sensors.local_tracks.track_reports_step over time pieces = track_reports on the whole
    stream (no restart gaps here: every track continues its carried Singer channels, the
    innovation of a piece's first report included)."""
    from tertiary.sensors import local_tracks
    plots = small_terminal.reports.select(PLOT_COLUMNS)
    whole = local_tracks.track_reports(plots, small_terminal.radars).sort("report_id")
    t = plots["time"].dt.epoch("us").to_numpy()
    cuts = np.linspace(t.min(), t.max() + 1, 8).astype(np.int64)
    carry, parts = None, []
    for a, b in zip(cuts[:-1], cuts[1:]):
        out, carry = local_tracks.track_reports_step(carry, plots.filter(pl.Series((t >= a) & (t < b))),
                                                     small_terminal.radars)
        parts.append(out)
    got = pl.concat(parts).sort("report_id")
    assert_frame_equal(got.select(local_tracks.ESTIMATE_COLUMNS), whole.select(local_tracks.ESTIMATE_COLUMNS),
                       rel_tol=1e-9, abs_tol=1e-9)
    assert carry.height == plots.select("run", "radar_id", "local_track_id").n_unique()
    with pytest.raises(OptionError, match="range_channel"):
        local_tracks.track_reports_step(None, plots, small_terminal.radars,
                                        LocalTrackerConfig(range_channel="kinematic_dynamic"))
