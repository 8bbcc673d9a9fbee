"""The percentiles' quantile sketch (DDSketch): the authors' implementation as the oracle, the
stated bound on any data, and a merge that does not depend on how the rows were split."""

from __future__ import annotations

import math

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from polars.testing import assert_frame_equal

from tertiary.evaluation import sketch

QS = (0.0, 0.01, 0.25, 0.5, 0.9, 0.95, 0.99, 1.0)


def _counts(values, groups=None) -> pl.DataFrame:
    f = pl.DataFrame({"g": groups if groups is not None else [0] * len(values), "v": pl.Series(values, dtype=pl.Float64)})
    return (f.select("g", sketch.bucket(pl.col("v")).alias(sketch.KEY)).drop_nulls(sketch.KEY)
            .group_by("g", sketch.KEY).agg(pl.len().cast(pl.UInt64).alias(sketch.COUNT))
            .with_columns(pl.lit("v").alias("quantity")))


def _quantile(counts: pl.DataFrame, q: float, interpolation: str = "linear") -> float:
    return sketch.quantiles(counts, ["g"], {"p": ("v", q)}, interpolation=interpolation)["p"][0]


def test_equals_the_reference_ddsketch():
    """The same quantiles as the authors' ``ddsketch.DDSketch`` fed one value at a time (its
    rule: the value of rank ⌊q(n − 1)⌋)."""
    ddsketch = pytest.importorskip("ddsketch")
    rng = np.random.default_rng(7)
    x = np.concatenate([rng.lognormal(4.0, 1.5, 5_000), np.zeros(20), rng.uniform(0.0, 1e-3, 20)])
    ref = ddsketch.DDSketch(sketch.ALPHA)
    for v in x:
        ref.add(float(v))
    counts = _counts(x)
    for q in QS:
        assert _quantile(counts, q, "lower") == pytest.approx(ref.get_quantile_value(q), rel=1e-12, abs=0.0), q


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0.0, 1e7, allow_nan=False), min_size=1, max_size=300),
       st.floats(0.0, 1.0))
def test_within_the_relative_accuracy_of_the_exact_quantile(values, q):
    """The stated bound: within relative α of the linearly interpolated quantile (numpy's and
    polars' default), and the ``lower`` rule of the value of rank ⌊q(n − 1)⌋."""
    x = np.sort(np.asarray(values))
    counts = _counts(values)
    for exact, got in ((np.quantile(x, q), _quantile(counts, q)),
                       (x[math.floor(q * (len(x) - 1))], _quantile(counts, q, "lower"))):
        tol = sketch.ALPHA * exact + 1e-9 * exact + 1e-300        # float round-off of the interpolation
        assert abs(got - exact) <= tol, (exact, got)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(0.0, 1e6, allow_nan=False), min_size=2, max_size=200), st.data())
def test_a_merge_of_any_split_is_the_sketch_of_the_whole(values, data):
    """Sketches of the rows split anywhere (windows, buckets, partitions), merged: the whole's."""
    cuts = sorted(data.draw(st.lists(st.integers(0, len(values)), max_size=4)))
    pieces = [values[a:b] for a, b in zip([0, *cuts], [*cuts, len(values)]) if b > a]
    merged = sketch.merge_counts([_counts(p) for p in pieces], ["g"])
    whole = _counts(values)
    key = ["g", "quantity", sketch.KEY]
    assert_frame_equal(merged.sort(key), whole.select(merged.columns).sort(key))


def test_values_not_counted_and_groups_apart():
    """Null, NaN, infinite and negative values are not counted; each group has its own sketch."""
    counts = _counts([1.0, None, math.nan, math.inf, -5.0, 3.0, 0.0, 100.0], groups=[0, 0, 0, 0, 0, 0, 1, 1])
    assert counts.filter(pl.col("g") == 0)[sketch.COUNT].sum() == 2
    got = sketch.quantiles(counts, ["g"], {"lo": ("v", 0.0), "hi": ("v", 1.0)}).sort("g")
    assert got["lo"].to_list()[1] == 0.0 and got["hi"].to_list()[0] == pytest.approx(3.0, rel=sketch.ALPHA)
    assert got["hi"].to_list()[1] == pytest.approx(100.0, rel=sketch.ALPHA)
    with pytest.raises(ValueError, match="relative accuracy"):
        sketch.bucket(pl.col("v"), alpha=1.0)
