"""Every table of the default job (one window, windowed, Dask) equals the golden reference.

The reference (``tests/data/golden.json``) was written by ``tests/golden.py`` from the tree whose
results the package must keep; a change that alters any table's contents fails here.
"""

from __future__ import annotations

import json
import math

import pytest

import golden

VARIANTS = ("one_window", "windowed", "dask")


@pytest.fixture(scope="module")
def current(tmp_path_factory):
    tables = golden.compute(tmp_path_factory.mktemp("golden"))
    return {v: {n: golden.summary(f) for n, f in t.items()} for v, t in tables.items()}


def _close(a: float | None, b: float | None, scale: float) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9 * scale)


def differences(got: dict, want: dict) -> list[str]:
    """What differs between two table summaries (empty: equal to 1e-9)."""
    out = [f"{k}: {got[k]} != {want[k]}" for k in ("rows", "columns", "exact") if got[k] != want[k]]
    for col, w in want["floats"].items():
        g = got["floats"].get(col)
        if g is None:
            continue        # a missing column is already in "columns"
        scale = math.sqrt(max(w["sumsq"] or 0.0, 0.0) * max(want["rows"], 1))
        for k in ("nulls", "nans"):
            if g[k] != w[k]:
                out.append(f"{col}.{k}: {g[k]} != {w[k]}")
        for k in ("sum", "sumsq", "wsum"):
            s = scale if k != "sumsq" else (w["sumsq"] or 0.0)
            if not _close(g[k], w[k], s):
                out.append(f"{col}.{k}: {g[k]!r} != {w[k]!r}")
    return out


def test_differences_catch_a_moved_value():
    import polars as pl
    a = golden.summary(golden.canonical(pl.DataFrame({"k": [1, 2], "x": [1.0, 2.0]})))
    b = golden.summary(golden.canonical(pl.DataFrame({"k": [1, 2], "x": [2.0, 1.0]})))
    c = golden.summary(golden.canonical(pl.DataFrame({"k": [1, 2], "x": [1.0, 2.0 + 1e-13]})))
    assert differences(b, a) and not differences(c, a)


@pytest.mark.parametrize("variant", VARIANTS)
def test_tables_equal_the_golden_reference(current, variant):
    want = json.loads(golden.GOLDEN.read_text())[variant]
    got = current[variant]
    assert sorted(got) == sorted(want)
    bad = {name: d for name in want if (d := differences(got[name], want[name]))}
    assert not bad, bad
