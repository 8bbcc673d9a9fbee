"""Terminal-area traffic that flies procedures, checked with the safety
oracle (closed-form losses of separation on the truth table ``tertiary.simulate`` produces)."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

import safety
from tertiary.core import geo
from tertiary.simulate import load_scenario, simulate
from tertiary.simulate.traffic import AIRWAYS, GLIDE_DEG, THRESHOLD, TCH_M, flight_level_m

SEP_H, SEP_V = safety.SEPARATION_MINIMA["terminal"]


@pytest.fixture(scope="module")
def default_ds():
    return simulate(load_scenario("terminal-area"))


@pytest.fixture(scope="module")
def heights(default_ds):
    """Truth with geodetic heights h_m, role and segment."""
    frame = geo.LocalFrame(*default_ds.scenario.origin)
    tr = default_ds.truth.with_columns(pl.col("time").dt.epoch("us").alias("t_us"))
    h = safety.truth_heights(default_ds.truth, frame)
    return tr.join(h.select("truth_id", "t_us", "h_m"), on=["truth_id", "t_us"])


def _roles(ds) -> dict[int, str]:
    r = ds.truth.select("truth_id", "role").unique()
    return dict(zip(r["truth_id"].to_list(), r["role"].to_list()))


def test_generator_and_scorer_share_the_minima():
    cfg = load_scenario("terminal-area").traffic
    assert (cfg.sep_h_m, cfg.sep_v_m) == pytest.approx((SEP_H, SEP_V), abs=0.5)
    assert (SEP_H, SEP_V) == (safety.ConflictConfig().sep_h_m, safety.ConflictConfig().sep_v_m)


def test_only_designed_pairs_lose_separation(default_ds):
    cfg = default_ds.scenario
    roles = _roles(default_ds)
    assert len(roles) == cfg.traffic.aircraft                      # all of them fly in the hour
    los = safety.loss_of_separation(default_ds.truth, frame=geo.LocalFrame(*cfg.origin))
    designed = sum(r.startswith("conflict-") for r in roles.values()) // 2
    assert designed == cfg.traffic.conflict_pairs == 10
    assert los.height == designed                                  # one episode per designed pair
    pairs = list(zip(los["truth_a"].to_list(), los["truth_b"].to_list()))
    assert len(set(pairs)) == designed
    assert all(roles[a] == roles[b] and roles[a].startswith("conflict-") for a, b in pairs)
    kinds = {roles[a] for a, _ in pairs}
    assert kinds <= {"conflict-crossing", "conflict-converging", "conflict-level-bust"} and len(kinds) >= 2
    # near misses come close (within 1.5x the horizontal minimum at one level) but keep separation
    near = safety.separation_intervals(default_ds.truth, 1.5 * SEP_H, SEP_V, frame=geo.LocalFrame(*cfg.origin))[0]
    near_pairs = {(a, b) for a, b in zip(near["truth_a"].to_list(), near["truth_b"].to_list())
                  if roles[a] == roles[b] == "near-miss"}
    assert len(near_pairs) == cfg.traffic.near_miss_pairs


def test_not_all_at_once(default_ds):
    per_t = default_ds.truth.group_by("time").len()["len"]
    assert per_t.max() < 0.4 * default_ds.scenario.traffic.aircraft


@pytest.mark.parametrize("role", ["arrival", "departure", "overflight", "holding"])
def test_streams_keep_their_spacing(default_ds, role):
    """Within one flow no two aircraft come within the horizontal minimum at less than the
    vertical minimum (holding: the stack is separated vertically only)."""
    tr = default_ds.truth.filter(pl.col("role") == role)
    assert tr["truth_id"].n_unique() >= 5
    frame = geo.LocalFrame(*default_ds.scenario.origin)
    los = safety.separation_intervals(tr, SEP_H, SEP_V, frame=frame)[0]
    assert los.height == 0
    if role in ("arrival", "departure"):                  # in trail: spacing is horizontal alone
        horiz = safety.separation_intervals(tr, SEP_H, 1e6, frame=frame)[0]
        assert horiz.height == 0


def test_final_approach_is_a_3_degree_glide_path(heights):
    arr = heights.filter((pl.col("role") == "arrival") & (pl.col("y_m").abs() < 1.0))
    s = arr["x_m"].to_numpy() - THRESHOLD[0]
    on_gp = (s > 500.0) & (s < 15_000.0)
    assert on_gp.sum() > 200
    want = TCH_M + s[on_gp] * np.tan(np.radians(GLIDE_DEG))
    np.testing.assert_allclose(arr["h_m"].to_numpy()[on_gp], want, atol=1.0)
    speed = np.hypot(arr["vx_mps"].to_numpy(), arr["vy_mps"].to_numpy())
    assert np.all(np.abs(speed[(s > 500.0) & (s < 9_000.0)] - 75.0) < 0.5)      # final approach speed
    assert np.all(np.abs(speed[(s > 31_000.0) & (s < 38_000.0)] - 130.0) < 0.5)  # before the reduction
    vz_ratio = arr["vz_mps"].to_numpy()[on_gp] / speed[on_gp]                    # ENU slope ≈ -tan 3°
    assert np.all(np.abs(vz_ratio + np.tan(np.radians(GLIDE_DEG))) < 0.01)


def test_overflights_at_semicircular_levels(heights):
    buf = load_scenario("terminal-area").traffic.level_buffer_m
    ov = heights.filter(pl.col("role") == "overflight")
    fl = ov["h_m"].to_numpy() / float(flight_level_m(1, buf))
    # on whole 1000 ft levels (≤ 3 m: the truth is converted on the sphere unless simulate passes the frame)
    np.testing.assert_allclose(fl, np.round(fl / 10) * 10, atol=0.1)
    thousands = np.round(fl / 10).astype(int)
    track = np.mod(np.degrees(np.arctan2(ov["vx_mps"].to_numpy(), ov["vy_mps"].to_numpy())), 360.0)
    east = track < 180.0
    assert np.all(thousands[east] % 2 == 1) and np.all(thousands[~east] % 2 == 0)
    assert east.any() and (~east).any()
    assert thousands.min() >= 15 and max(max(a[3]) for a in AIRWAYS) == 390           # above the terminal area


def test_holding_levels_are_1000_ft_apart(heights):
    buf = load_scenario("terminal-area").traffic.level_buffer_m
    hold = heights.filter(pl.col("segment") == "hold")
    assert hold["truth_id"].n_unique() >= 8
    step = 1000 * 0.3048 + buf
    h = hold["h_m"].to_numpy()
    idx = np.round(h / step)
    assert np.abs(h - idx * step).max() < 3.0          # on 1000 ft levels (≤ 3 m: sphere vs WGS-84)
    levels = np.unique(idx)
    assert len(levels) >= 4 and np.all(np.diff(levels) == 1)       # adjacent levels, 1000 ft apart
    # every holding aircraft holds at one level
    per = hold.with_columns(pl.Series("lvl", idx)).group_by("truth_id").agg(pl.col("lvl").n_unique())
    assert (per["lvl"] == 1).all()


def test_heights_to_enu_quiet_on_samples_beyond_the_horizon():
    """A long recording extrapolates idle aircraft thousands of km out: those samples get NaN z
    without a NumPy warning reaching the user, and a real sample's z is the sphere's formula."""
    import warnings

    from tertiary.simulate.traffic import heights_to_enu
    pos = np.array([[[1.0e4, 2.0e4, 3000.0], [-4.5e6, -5.0e6, 2140.0]]])
    vel = np.zeros_like(pos)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        heights_to_enu(pos, vel)
    r = geo.EARTH_RADIUS_M
    assert pos[0, 0, 2] == pytest.approx(np.sqrt((r + 3000.0) ** 2 - 1.0e4 ** 2 - 2.0e4 ** 2) - r, abs=1e-6)
    assert np.isnan(pos[0, 1, 2])
