"""Helper functions of the benchmarks/reproduce_seed*.py scripts (hand cases only; fast)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import reproduce_seed002_landing as s002  # noqa: E402


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
