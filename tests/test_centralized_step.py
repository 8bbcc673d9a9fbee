"""centralized_step: the windowed centralised reference equals the whole-run one."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

import tertiary.stages.align
import tertiary.stages.association.associate
from tertiary.stages.fusion.centralized import (CentralizedConfig, centralized_filter, centralized_filter_carry, centralized_fusion, centralized_step, init_centralized_state)
from tertiary.pipeline import PipelineConfig, screen
from tertiary.simulate import load_scenario, simulate

KEYS = ["run", "epoch", "target_id"]


@pytest.fixture(scope="module")
def case():
    """Terminal-area, 20 aircraft, 300 s: reports, radars, associations, output keys, origin."""
    sc = load_scenario("terminal-area")
    sc = dataclasses.replace(sc, duration_s=300.0, traffic=dataclasses.replace(sc.traffic, aircraft=20))
    ds = simulate(sc)
    cfg = PipelineConfig()
    ing = screen(ds, cfg)
    aligned = tertiary.stages.align.expand(ing.plan, cfg.align)
    assoc, _ = tertiary.stages.association.associate.associate(aligned, cfg.association)
    rows = aligned.with_columns(assoc["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    keys = rows.select("run", "epoch", "target_id").unique(maintain_order=True)
    return ing.reports, ing.radars, assoc, keys, ds.origin


def _span(keys: pl.DataFrame) -> tuple[int, int]:
    e = keys["epoch"].dt.epoch("us")
    return int(e.min()), int(e.max()) + 1


def _windowed(case, cuts: list[int], margin_us: int, cfg: CentralizedConfig = CentralizedConfig()) -> pl.DataFrame:
    reports, radars, assoc, keys, origin = case
    lo, hi = _span(keys)
    ek, ea, tr = (keys["epoch"].dt.epoch("us"), assoc["epoch"].dt.epoch("us"), reports["time"].dt.epoch("us"))
    bounds = [lo, *[lo + c for c in cuts], hi]
    state, outs = init_centralized_state(), []
    for a, b in zip(bounds[:-1], bounds[1:]):
        out, state = centralized_step(state, reports.filter((tr >= a - margin_us) & (tr < b)), radars,
                                      assoc.filter((ea >= a) & (ea < b)), keys.filter((ek >= a) & (ek < b)),
                                      origin, cfg, a, b)
        outs.append(out)
    return pl.concat(outs)


def _assert_same(got: pl.DataFrame, want: pl.DataFrame) -> None:
    assert got.height == want.height
    assert_frame_equal(got.sort(KEYS), want.sort(KEYS), rel_tol=1e-9, abs_tol=1e-9)


CUTS = {
    "one cut": [100_000_000],
    "3 s windows": list(range(3_000_000, 310_000_000, 3_000_000)),   # < every scan period (4–12 s)
    "empty window": [50_000_000, 50_000_001, 150_000_000, 151_000_000, 200_000_000],
}


@pytest.mark.parametrize("cuts", list(CUTS.values()), ids=list(CUTS))
@pytest.mark.parametrize("margin_s", [4, 30], ids=["reports of one epoch period before", "30 s of reports before"])
def test_windowed_reference_equals_whole_run(case, cuts, margin_s):
    reports, radars, assoc, keys, origin = case
    whole = centralized_fusion(reports, radars, assoc, keys, origin)
    assert whole.height > 1000 and (whole["n_sources"] > 1).any()
    assert whole["tentative"].any() and not whole["tentative"].all()     # the confirmation is compared too
    _assert_same(_windowed(case, cuts, margin_s * 1_000_000), whole)


def test_windowed_reference_equals_whole_run_with_options(case):
    reports, radars, assoc, keys, origin = case
    cfg = CentralizedConfig(variant="exact", conversion="debiased", conversion_gate="reject")
    whole = centralized_fusion(reports, radars, assoc, keys, origin, cfg)
    _assert_same(_windowed(case, CUTS["3 s windows"], 30_000_000, cfg), whole)










def test_filter_continued_from_its_carry_equals_one_call():
    rng = np.random.default_rng(5)
    n = 30
    t = np.cumsum(rng.uniform(2.0, 8.0, n))
    z = np.column_stack([100.0 * t, 50.0 * t, np.full(n, 3000.0)]) + rng.normal(0, 50.0, (n, 3))
    r = np.broadcast_to(np.diag([2500.0, 2500.0, 900.0]), (n, 3, 3)).copy()
    starts, lengths = np.array([0, 18]), np.array([18, 12])
    xs, ps = centralized_filter(t, z, r, starts, lengths)
    a, b = np.r_[0:7, 18:23], np.r_[7:18, 23:30]
    x1, p1, carry = centralized_filter_carry(t[a], z[a], r[a], np.array([0, 7]), np.array([7, 5]))
    x2, p2, _ = centralized_filter_carry(t[b], z[b], r[b], np.array([0, 11]), np.array([11, 7]), init=carry)
    np.testing.assert_allclose(np.r_[x1, x2], xs[np.r_[a, b]], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(np.r_[p1, p2], ps[np.r_[a, b]], rtol=1e-12, atol=1e-9)


def test_the_state_keeps_only_the_live_targets(case):
    """With ``live``, every part of the carried state (filters, radars, both confirmations) holds
    only those targets; live = every target seen keeps the state ``live=None`` keeps."""
    reports, radars, assoc, keys, origin = case
    lo, _ = _span(keys)
    b = lo + 150_000_000
    ek, ea, tr = (keys["epoch"].dt.epoch("us"), assoc["epoch"].dt.epoch("us"), reports["time"].dt.epoch("us"))
    args = (init_centralized_state(), reports.filter(tr < b), radars, assoc.filter(ea < b), keys.filter(ek < b), origin)
    _, full = centralized_step(*args)
    seen = full.targets.select("run", "target_id")
    live = seen.filter(pl.col("target_id") % 2 == 0)
    _, kept = centralized_step(*args, live=live)
    parts = {"targets": kept.targets, "radars": kept.radars, "confirm": kept.confirm.targets,
             "scans": kept.scan.scans, "scan targets": kept.scan.targets}
    for name, frame in parts.items():
        assert frame.height and frame.join(live, on=["run", "target_id"], how="anti").is_empty(), name
    assert full.scan.scans.height > kept.scan.scans.height and full.scan.targets.height > kept.scan.targets.height
    _, same = centralized_step(*args, live=seen)
    assert_frame_equal(same.scan.scans.sort(pl.all()), full.scan.scans.sort(pl.all()))
    assert_frame_equal(same.scan.targets.sort(pl.all()), full.scan.targets.sort(pl.all()))
