"""Helper functions of the benchmarks/reproduce_seed*.py scripts (hand cases only; fast)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import reproduce_seed002_landing as s002  # noqa: E402
import reproduce_seed003_sources as s003  # noqa: E402
import reproduce_seed004 as s004  # noqa: E402

from tertiary.filters.ekf import initial_state_seed004, run_seed004  # noqa: E402


def test_dip_below_one_finds_the_longest_run_after_first_scan():
    r = np.ones(100) * 2.0
    r[5:15] = 0.5          # before first_scan: ignored
    r[40:43] = 0.9
    r[60:80] = 0.7
    r[70] = 0.4
    got = s002.dip_below_one(r, start=55, first_scan=20)
    assert got == {"scans": 20, "min_ratio": 0.4, "starts_after_step": 5}
    assert s002.dip_below_one(np.full(50, 1.5), 10, 20)["scans"] == 0
    tail = np.r_[np.full(30, 2.0), np.full(10, 0.8)]          # a dip reaching the last scan
    assert s002.dip_below_one(tail, 25, 20) == {"scans": 10, "min_ratio": 0.8, "starts_after_step": 5}


def test_settle_time_and_order_helpers():
    e = np.array([10.0, 8.0, 5.0, 1.5, 2.5, 1.2, 1.0])
    assert s004.settle_time(e, 2.0, dt=0.5) == 2.5         # last value above 2.0 is e[4] -> stays from step 5
    assert s004.settle_time(np.ones(5)) == 0.0
    assert s004.strictly_decreasing([3.0, 2.0, 1.0]) and not s004.strictly_decreasing([3.0, 3.0, 1.0])


def test_midpoint_initialisation_by_hand():
    rng = np.random.default_rng(0)
    truth0 = np.array([10_000.0, 0.03, 0.1, 416.67, np.pi, 0.0])
    meas0 = np.array([[10_050.0, 0.031, 0.099], [9_950.0, 0.029, 0.101]])
    rm = np.diag([100.0 ** 2, 1e-5, 1e-5])
    x, p = initial_state_seed004(meas0, truth0, rm, rng, "midpoint", range_bounds=(1_000.0, 21_000.0),
                                 speed_bounds=(100.0, 500.0))
    assert np.all(x[:, 0] == 11_000.0) and np.all(x[:, 3] == 300.0)
    np.testing.assert_array_equal(x[:, 1:3], meas0[:, 1:])
    assert p[0, 0, 0] == pytest.approx(20_000.0 ** 2 / 12) and p[0, 3, 3] == pytest.approx(400.0 ** 2 / 12)
    assert np.all(p[:, 0, 1:] == 0) and np.all(p[:, 3, [0, 1, 2, 4, 5]] == 0)
    assert p[0, 1, 1] == rm[1, 1] and p[0, 4, 4] == pytest.approx(np.radians(5.0) ** 2)
    xm, pm = initial_state_seed004(meas0, truth0, rm, np.random.default_rng(0), "measurement")
    np.testing.assert_array_equal(xm[:, :3], meas0)
    assert pm[0, 0, 0] == rm[0, 0]
    with pytest.raises(ValueError, match="midpoint"):
        initial_state_seed004(meas0, truth0, rm, rng, "centre")


def test_midpoint_run_starts_far_and_is_pulled_in_by_the_first_plot():
    err_mid, truth = run_seed004(20, 50, init="midpoint")
    assert err_mid[0, 0] == pytest.approx(15_250.0 - truth[0, 0])     # every run at the midpoint
    assert err_mid[1, 0] < 200.0                                       # the first update takes D to the plot
    err_meas, _ = run_seed004(20, 50)
    assert err_meas[0, 0] < 200.0


def test_geometry_factor_by_hand():
    sig = np.array([1.0, 2.0, 3.0, 4.0])
    assert s003.geometry_factor(np.eye(4), sig) == pytest.approx(np.sqrt(30.0))     # √Σσ²
    assert s003.geometry_factor(np.eye(4)[:3], sig[:3]) == float("inf")            # 3 rows, 4 unknowns
    # two equal range-like rows along x: the information doubles, the variance halves
    h = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    assert s003.geometry_factor(h, np.ones(3)) == pytest.approx(np.sqrt(0.5 + 1.0))
    pos, sg = s003.sources(3, 1)
    assert pos.shape == (4, 3) and np.allclose(np.linalg.norm(pos[:3], axis=1), 20_200e3)
    assert sg.tolist() == pytest.approx([np.sqrt(30.0)] * 3 + [np.sqrt(10.0)])
