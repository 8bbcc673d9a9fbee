"""fuse_step: windowed fusion equals the whole-run fuse (the stream contract of the docs)."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

import tertiary.stages.align
import tertiary.stages.association.associate
from tertiary.stages.tracking.altitude import AltitudeConfig, filter_tracks, filter_tracks_carry
from tertiary.stages.fusion import (ALL_METHODS, FusionConfig, fuse, fuse_step, init_fuse_state, measured_plots)
from tertiary.pipeline import PipelineConfig, screen
from tertiary.simulate import load_scenario, simulate

KEYS = ["method", "run", "epoch", "target_id"]
SLOWEST_SCAN_US = 12_000_000          # terminal-area's slowest radar (ENR-E)


@pytest.fixture(scope="module")
def case():
    """Terminal-area, 20 aircraft, 300 s: fusion rows, radars, origin and measured plots."""
    sc = load_scenario("terminal-area")
    sc = dataclasses.replace(sc, duration_s=300.0, traffic=dataclasses.replace(sc.traffic, aircraft=20))
    ds = simulate(sc)
    cfg = PipelineConfig()
    ing = screen(ds, cfg)
    aligned = tertiary.stages.align.expand(ing.plan, cfg.align)
    assoc, _ = tertiary.stages.association.associate.associate(aligned, cfg.association)
    rows = aligned.with_columns(assoc["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    plots = measured_plots(ing.reports, ing.radars, ds.origin, cfg.align.local_tracker.altitude_sigma_m)
    assert ing.radars["scan_period_s"].max() * 1e6 == SLOWEST_SCAN_US
    return rows, ing.radars, ds.origin, plots


def _span(rows: pl.DataFrame) -> tuple[int, int]:
    e = rows["epoch"].dt.epoch("us")
    return int(e.min()), int(e.max()) + 1


def _windowed(case, cuts: list[int], cfg: FusionConfig = FusionConfig()) -> pl.DataFrame:
    rows, radars, origin, plots = case
    lo, hi = _span(rows)
    e = rows["epoch"].dt.epoch("us")
    bounds = [lo, *[lo + c for c in cuts], hi]
    state, outs = init_fuse_state(), []
    for a, b in zip(bounds[:-1], bounds[1:]):
        out, state = fuse_step(state, rows.filter((e >= a) & (e < b)), radars, ALL_METHODS, cfg, origin, plots, a, b)
        outs.append(out)
    return pl.concat(outs)


def _assert_same(got: pl.DataFrame, want: pl.DataFrame) -> None:
    assert got.height == want.height
    assert_frame_equal(got.sort(KEYS), want.sort(KEYS), rel_tol=1e-9, abs_tol=1e-9)


CUTS = {
    "one cut": [100_000_000],
    # 3 s windows: shorter than every scan period (4–12 s) and than the 4 s epoch spacing, so
    # many windows hold no epoch at all
    "3 s windows": list(range(3_000_000, 310_000_000, 3_000_000)),
    # a 1 µs window (empty) between two others, then uneven windows
    "empty window": [50_000_000, 50_000_001, 150_000_000, 151_000_000, 200_000_000],
}


@pytest.mark.parametrize("cuts", list(CUTS.values()), ids=list(CUTS))
def test_windowed_fusion_equals_whole_run_for_every_method(case, cuts):
    rows, radars, origin, plots = case
    whole = fuse(rows, radars, ALL_METHODS, FusionConfig(), origin, plots)
    assert set(whole["method"].unique()) == set(ALL_METHODS)
    # the recursions have something to carry: multi-radar targets spanning the cuts
    assert (whole["n_sources"] > 1).sum() > 100
    _assert_same(_windowed(case, cuts), whole)


@pytest.mark.parametrize("cfg", [FusionConfig(nis_gate="reject"),
                                 FusionConfig(nis_gate="downweight", gate_test="trace", nis_window=2, min_plots=3),
                                 FusionConfig(altitude=AltitudeConfig(model="cv"))],
                         ids=["gate reject", "gate downweight", "altitude cv"])
def test_windowed_fusion_equals_whole_run_with_options(case, cfg):
    rows, radars, origin, plots = case
    whole = fuse(rows, radars, ALL_METHODS, cfg, origin, plots)
    _assert_same(_windowed(case, CUTS["3 s windows"], cfg), whole)












def test_altitude_filter_continued_from_its_carry_equals_one_call():
    rng = np.random.default_rng(3)
    n = 40
    t = np.cumsum(rng.uniform(3.0, 6.0, n))
    z = 3000.0 + 5.0 * t + rng.normal(0.0, 10.0, n)
    z[[5, 17]] = np.nan                              # missing replies
    z[25] += 900.0                                   # a garble
    var = np.full(n, 7.62 ** 2 / 12)
    ident = np.where(np.arange(n) < 30, 0xABC, 0xDEF)  # a swap of aircraft at reply 30
    starts, lengths = np.array([0, 20]), np.array([20, 20])
    whole, has, rej = filter_tracks(t, z, var, starts, lengths, ident=ident)
    for cut in (7, 13):                              # split track 0 (and track 1) at `cut`
        a = np.r_[0:cut, 20:20 + cut]
        b = np.r_[cut:20, 20 + cut:40]
        s, ln = np.array([0, cut]), np.array([cut, cut])
        out1, has1, _, carry = filter_tracks_carry(t[a], z[a], var[a], s, ln, ident=ident[a])
        s2, ln2 = np.array([0, 20 - cut]), np.array([20 - cut, 20 - cut])
        out2, has2, rej2, _ = filter_tracks_carry(t[b], z[b], var[b], s2, ln2, ident=ident[b], init=carry)
        np.testing.assert_array_equal(np.r_[has1, has2], has[np.r_[a, b]])
        np.testing.assert_allclose(np.r_[out1.h, out2.h], whole.h[np.r_[a, b]], rtol=1e-12)
        np.testing.assert_allclose(np.r_[out1.prr, out2.prr], whole.prr[np.r_[a, b]], rtol=1e-12)
        np.testing.assert_array_equal(rej2, rej[b])


def test_the_vertical_channel_takes_the_plots_downlinked_vertical_rates(case):
    """The measured plots' downlinked vertical rates reach the fused vertical channel's
    filters: without them (the same plots, registers blanked) the channel differs. Fails when
    fuse_step does not hand its plots to the vertical channel."""
    rows, radars, origin, plots = case
    assert plots["plot_vrate_mps"].is_not_nan().sum() > 100
    blank = plots.with_columns(pl.lit(float("nan")).alias("plot_vrate_mps"))
    got = fuse(rows, radars, ("information",), FusionConfig(), origin, plots).sort(KEYS)
    without = fuse(rows, radars, ("information",), FusionConfig(), origin, blank).sort(KEYS)
    moved = (got["alt_m"] - without["alt_m"]).abs()
    # on this scene the replies inside the garble gate decide almost everything: the registers
    # change the channel a little (they restart filters on the sources it does not choose)
    assert (moved > 0).sum() > 0, moved.max()
