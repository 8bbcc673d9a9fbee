"""Shared fixtures: small, fast simulated datasets."""

from __future__ import annotations

import dataclasses
import os

import pytest

from tertiary.simulate import load_scenario, simulate


# The suite runs without COLUMNS: the CLI's batch tables are as wide as COLUMNS says (160
# without it), and the pytest-xdist workers start with COLUMNS=80 where a plain ``pytest`` has
# none (nor should a developer's shell change what the tests see). A test that wants a width
# sets it for its command.
os.environ.pop("COLUMNS", None)


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


# --------------------------------------------------------------------------- skips in CI

#: tests allowed to skip in CI (node-id prefix → why). Everything else that skips fails CI
#: (CI=true), so a missing file, package or browser cannot pass unnoticed.
ALLOWED_SKIPS: dict[str, str] = {}

_skipped: list[tuple[str, str]] = []


def pytest_runtest_logreport(report):
    if report.skipped:
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        _skipped.append((report.nodeid, reason))


def unexpected_skips(skipped: list[tuple[str, str]], allowed: dict[str, str]) -> list[tuple[str, str]]:
    """The skipped tests whose node id starts with no allowed prefix."""
    return [(node, why) for node, why in skipped if not any(node.startswith(p) for p in allowed)]


def pytest_sessionfinish(session, exitstatus):
    import os
    if os.environ.get("CI", "").lower() not in ("1", "true", "yes"):
        return
    bad = unexpected_skips(_skipped, ALLOWED_SKIPS)
    if bad:
        lines = "\n".join(f"  {node}: {why}" for node, why in bad)
        session.config.get_terminal_writer().line(
            f"\nCI: {len(bad)} test(s) skipped that are not on tests/conftest.py ALLOWED_SKIPS:\n{lines}", red=True)
        if session.exitstatus == 0:
            session.exitstatus = 1
