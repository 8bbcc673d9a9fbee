"""The downlinked turn rate (Mode S BDS 5,0 track-angle rate) as evidence for a multiple-model
filter's turn models: the evidence function, its effect on an IMM through a turn and on a
straight leg, the sign convention from the ``fused`` column to the filters' ω, and the
interface every registered filter keeps.

Oracles: the linear interpolation between neighbouring grid rates written out by hand; the
same filter without the downlink on the same plots.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.filters import REGISTRY, make_filter
from tertiary.filters.imm import SYM_OMEGAS, turn_rate_evidence
from tertiary.stages.tracking.config import TrackerConfig
from tertiary.stages.tracking.gating import downlinked_turn_rate
from tertiary.stages.tracking.tracker import track_methods

DT = 4.0
T0 = datetime(2021, 10, 7, 8, 0, tzinfo=timezone.utc)
RIGHT_3DPS = -np.radians(3.0)          # a right turn at 3 °/s as the filters' ω (counter-clockwise +)


# --------------------------------------------------------------------------- evidence


def test_a_rate_on_a_model_supports_that_model_alone():
    ev = turn_rate_evidence(SYM_OMEGAS, np.array(SYM_OMEGAS), 0.01)
    np.testing.assert_allclose(ev, 0.01 + 0.99 * np.eye(len(SYM_OMEGAS)))


def test_a_rate_between_two_models_is_shared_by_linear_interpolation():
    omegas = (0.0, 0.01, -0.01, 0.025)
    w = np.array([0.004, 0.0175, -0.0025])
    ev = turn_rate_evidence(omegas, w, 0.0 + 1e-9)
    # by hand: 0.004 is 0.4 of the way from 0 to 0.01; 0.0175 halfway between 0.01 and 0.025;
    # -0.0025 a quarter of the way from 0 to -0.01
    expect = np.array([[0.6, 0.4, 0.0, 0.0], [0.0, 0.5, 0.0, 0.5], [0.75, 0.0, 0.25, 0.0]])
    np.testing.assert_allclose(ev, 1e-9 + (1 - 1e-9) * expect, atol=1e-12)


def test_rates_beyond_the_grid_support_the_extreme_model_and_nan_supports_all():
    ev = turn_rate_evidence((0.0, 0.05, -0.05), np.array([0.3, -0.3, np.nan]), 0.02)
    np.testing.assert_allclose(ev, [[0.02, 1.0, 0.02], [0.02, 0.02, 1.0], [1.0, 1.0, 1.0]])


def test_the_rate_error_is_averaged_over_as_a_quadrature_of_the_hats_does():
    omegas = np.array(SYM_OMEGAS)
    sigma = np.radians(0.5)
    w = np.array([0.0, 0.003, 0.02, 0.044, -0.07, 0.12])
    got = turn_rate_evidence(omegas, w, 1e-12, sigma)
    # oracle: the σ = 0 hats averaged over the error on a fine grid (±8σ)
    n = np.linspace(-8 * sigma, 8 * sigma, 20001)
    dens = np.exp(-0.5 * (n / sigma) ** 2)
    dens /= dens.sum()
    sharp = turn_rate_evidence(omegas, (w[:, None] + n[None, :]).ravel(), 1e-12).reshape(len(w), len(n), -1)
    np.testing.assert_allclose(got, np.einsum("bnm,n->bm", sharp, dens), atol=1e-6)


def test_repeated_model_rates_are_refused():
    with pytest.raises(ValueError, match="distinct"):
        turn_rate_evidence((0.0, 0.01, 0.01), np.array([0.005]), 0.01)


@pytest.mark.parametrize("kw", [dict(rate_floor=0.0), dict(rate_floor=1.5), dict(rate_sigma=-0.01),
                                dict(rate_sigma=float("nan"))])
def test_the_rate_floor_and_error_are_checked(kw):
    with pytest.raises(ValueError, match="rate_floor"):
        make_filter("imm_sym", **kw)


# --------------------------------------------------------------------------- one IMM, a turn


def _turn(b: int, steps: int, omega: float, turn_from: int, speed: float, sigma: float, seed: int):
    """``b`` aircraft flying straight, then turning at ``omega`` from scan ``turn_from`` on
    (exact arcs); plots every DT with white noise σ per axis; the true ω per scan."""
    rng = np.random.default_rng(seed)
    hdg = rng.uniform(0.0, 2.0 * np.pi, b)
    pos = np.zeros((b, steps + 1, 2))
    w_true = np.where(np.arange(steps + 1) > turn_from, omega, 0.0)
    for k in range(steps):
        w = w_true[k + 1]
        h1 = hdg + w * DT
        if w == 0.0:
            step = speed * DT * np.stack([np.cos(hdg), np.sin(hdg)], axis=1)
        else:
            step = speed / w * np.stack([np.sin(h1) - np.sin(hdg), np.cos(hdg) - np.cos(h1)], axis=1)
        pos[:, k + 1] = pos[:, k] + step
        hdg = h1
    z = np.concatenate([pos, np.full((b, steps + 1, 1), 9000.0)], axis=2) + rng.normal(0.0, sigma, (b, steps + 1, 3))
    return pos, z, w_true


def _imm_run(pos, z, w_down, sigma, turn_from):
    """imm_sym over the plots, given the downlinked ω per scan (None: no downlink). Returns the
    horizontal RMSE over the turn's first 8 scans, the mean combined velocity σ (m/s) over
    the straight leg's last 5 scans and the mean probability of the models turning at 1.4 °/s
    or faster at its end."""
    filt = make_filter("imm_sym")
    b = len(z)
    r = np.full((b, 3), sigma ** 2)
    st = filt.init(z[:, 0], r)
    e2, sig = [], []
    for k in range(1, z.shape[1]):
        st = filt.predict(st, np.full(b, DT))
        st, _ = filt.update(st, z[:, k], r, np.ones(b, bool))
        if w_down is not None:
            st = filt.observe_turn_rate(st, np.full(b, w_down[k]), np.ones(b, bool))
        out = filt.output(st)
        if turn_from < k <= turn_from + 8:
            e2.append(((out.x[:, :2] - pos[:, k]) ** 2).sum(axis=1))
        if turn_from - 5 < k <= turn_from:
            sig.append(np.sqrt(out.var[:, 3:5].sum(axis=1)))
        if k == turn_from:
            fast = np.abs(np.asarray(SYM_OMEGAS)) >= 0.025
            turning = float(np.mean(st["mu"][:, fast].sum(axis=1)))
    return float(np.sqrt(np.mean(e2))), float(np.mean(sig)), turning


def test_a_downlinked_rate_follows_a_turn_sooner_and_narrows_a_straight_leg():
    pos, z, w_true = _turn(b=300, steps=40, omega=RIGHT_3DPS, turn_from=25, speed=180.0, sigma=60.0, seed=3)
    rng = np.random.default_rng(4)
    # the register's noise (0.05 °/s) and 1/32 °/s quantisation
    w_down = np.round((w_true + np.radians(rng.normal(0.0, 0.05, len(w_true)))) / np.radians(1 / 32)) * np.radians(1 / 32)
    rmse_none, sig_none, turning_none = _imm_run(pos, z, None, 60.0, 25)
    rmse_rate, sig_rate, turning_rate = _imm_run(pos, z, w_down, 60.0, 25)
    rmse_flip, _, _ = _imm_run(pos, z, -w_down, 60.0, 25)
    assert rmse_rate < 0.8 * rmse_none, (rmse_rate, rmse_none)
    # a rate of the wrong sense must not help (the sign convention is what the first assert rests on)
    assert rmse_flip > rmse_rate * 1.2, (rmse_flip, rmse_rate)
    # straight: the fast turn models lose their probability, and with it the spread their offsets add
    assert turning_rate < 0.1 * turning_none, (turning_rate, turning_none)
    assert sig_rate < sig_none, (sig_rate, sig_none)


# --------------------------------------------------------------------------- through the tracker


def test_the_fused_column_is_clockwise_in_degrees_and_the_filters_omega_counter_clockwise():
    f = pl.DataFrame({"ehs_track_rate_dps": [3.0, -1.5, None]})
    np.testing.assert_allclose(downlinked_turn_rate(f), [-np.radians(3.0), np.radians(1.5), np.nan])
    assert np.isnan(downlinked_turn_rate(pl.DataFrame({"x": [1.0]}))).all()


def _fused_turn(rate_dps_sign: float, with_rate: bool = True) -> tuple[pl.DataFrame, np.ndarray]:
    """A ``fused`` frame of 40 aircraft turning right at 3 °/s from scan 25, their truth."""
    pos, z, w_true = _turn(b=40, steps=40, omega=RIGHT_3DPS, turn_from=25, speed=180.0, sigma=60.0, seed=5)
    b, n = z.shape[:2]
    # spread the aircraft apart so that every plot belongs to its own track
    off = np.stack([np.arange(b) * 60_000.0, np.zeros(b)], axis=1)
    pos = pos + off[:, None, :]
    z = z.copy()
    z[:, :, :2] += off[:, None, :]
    cov = np.zeros(36)
    cov[[0, 7, 14]] = 60.0 ** 2
    cov[[21, 28, 35]] = 25.0
    k = np.tile(np.arange(n), b)
    cols = {
        "run": np.zeros(b * n, np.uint32), "epoch": [T0 + timedelta(seconds=DT * int(i)) for i in k],
        "target_id": np.repeat(np.arange(b), n).astype(np.uint64), "method": "information",
        "x_m": z[:, :, 0].ravel(), "y_m": z[:, :, 1].ravel(), "z_m": z[:, :, 2].ravel(),
        "vx_mps": 0.0, "vy_mps": 0.0, "vz_mps": 0.0, "cov": [cov.tolist()] * (b * n),
    }
    if with_rate:
        cols["ehs_track_rate_dps"] = rate_dps_sign * -np.degrees(np.tile(w_true, b))
    frame = pl.DataFrame(cols, schema_overrides={"run": pl.UInt32, "target_id": pl.UInt64,
                                                 "epoch": pl.Datetime("us", "UTC"), "cov": pl.Array(pl.Float64, 36)})
    return frame, pos


def _turn_rmse(tracks: pl.DataFrame, pos: np.ndarray) -> float:
    t = tracks.with_columns(k=((pl.col("epoch") - T0).dt.total_seconds() / DT).round().cast(pl.Int64))
    t = t.filter((pl.col("k") > 25) & (pl.col("k") <= 33))
    # each track's aircraft: the nearest truth at its epoch
    truth = pos[:, t["k"].to_numpy()]                           # (b, rows, 2)
    d = np.hypot(truth[..., 0] - t["x_m"].to_numpy(), truth[..., 1] - t["y_m"].to_numpy()).min(axis=0)
    return float(np.sqrt(np.mean(d ** 2)))


def test_the_tracker_hands_the_fused_rate_to_the_filter_with_its_sense():
    right, pos = _fused_turn(+1.0)
    wrong, _ = _fused_turn(-1.0)
    none, _ = _fused_turn(+1.0, with_rate=False)
    filters = {"imm_sym": make_filter("imm_sym")}
    with_rate = _turn_rmse(track_methods(right, filters), pos)
    off = _turn_rmse(track_methods(right, filters, TrackerConfig(use_turn_rate=False)), pos)
    absent = _turn_rmse(track_methods(none, filters), pos)
    flipped = _turn_rmse(track_methods(wrong, filters), pos)
    assert off == absent                          # switched off = not downlinked
    assert with_rate < 0.8 * off, (with_rate, off)
    assert flipped > 1.2 * with_rate, (flipped, with_rate)


# --------------------------------------------------------------------------- every filter


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_every_filter_takes_a_turn_rate_and_keeps_its_state_form(name):
    filt = make_filter(name)
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 1000.0, (5, 3))
    st = filt.init(z, np.full((5, 3), 50.0 ** 2))
    st = filt.predict(st, np.full(5, DT))
    # no rate (NaN or masked) changes nothing
    same = filt.observe_turn_rate(st, np.full(5, np.nan), np.ones(5, bool))
    masked = filt.observe_turn_rate(st, np.full(5, 0.02), np.zeros(5, bool))
    for other in (same, masked):
        assert other.keys() == st.keys()
        for key in st:
            np.testing.assert_array_equal(other[key], st[key])
    used = filt.observe_turn_rate(st, np.array([0.0, 0.02, -0.05, np.nan, 0.2]), np.ones(5, bool))
    assert used.keys() == st.keys()
    for key in st:
        assert used[key].shape == st[key].shape
        np.testing.assert_array_equal(np.isfinite(used[key]), np.isfinite(st[key]))
    if "mu" in used:
        np.testing.assert_allclose(used["mu"].sum(axis=1), 1.0)
        np.testing.assert_array_equal(used["mu"][3], st["mu"][3])
        # a track without a rate in a batch with rates keeps its probabilities bit for bit
        odd = {**st, "mu": st["mu"] * (1.0 + 1e-12)}
        np.testing.assert_array_equal(filt.observe_turn_rate(odd, np.array([0.02, np.nan, np.nan, np.nan, np.nan]),
                                                             np.ones(5, bool))["mu"][1:], odd["mu"][1:])
