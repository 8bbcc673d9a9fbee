"""Shared fixtures: small, fast simulated datasets."""

from __future__ import annotations

import dataclasses

import pytest

from tertiary.simulate import load_scenario, simulate


@pytest.fixture(scope="session")
def small_terminal():
    """Terminal-area with 30 aircraft, 4 radars, 10 minutes (a few seconds to build)."""
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=600.0, traffic=dataclasses.replace(cfg.traffic, aircraft=30, conflict_pairs=3))
    return simulate(cfg)


@pytest.fixture(scope="session")
def big_box_runs():
    """Big box with 5 Monte-Carlo runs."""
    return simulate(load_scenario("big-box").replace(runs=5))
