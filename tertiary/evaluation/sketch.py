"""A mergeable quantile sketch for the evaluation's percentiles: DDSketch (Masson, Rim & Lee,
"DDSketch: a fast and fully-mergeable quantile sketch with relative-error guarantees", VLDB 2019),
over polars group-bys.

A positive value v falls in bucket k = ⌈log_γ v⌉, γ = (1 + α)/(1 − α); a sketch is the count of
values per bucket (zero and below the smallest positive double: a bucket of their own, valued 0).
The q-quantile is the representative 2γᵏ/(1 + γ) of the bucket holding the value of rank
⌊q(n − 1)⌋ (0-based) in sorted order. **Bound** (deterministic): that representative is within
relative α of the value of that rank, so it lies in [x₍ᵣ₎(1 − α), x₍ᵣ₎(1 + α)], r = ⌊q(n − 1)⌋;
the linearly interpolated quantile lies in [x₍ᵣ₎, x₍ᵣ₊₁₎]. Merging adds the counts of equal
buckets, so a sketch does not depend on how its rows were split (windows, buckets, partitions):
it is exactly the sketch of their union. Null, NaN and infinite values are not counted.

The package ``ddsketch`` (the authors' reference, one value at a time in Python) is the test
oracle; here every row is bucketed in one vectorised expression (a Python call per value would
cost more than the evaluation it serves)."""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence

import polars as pl

__all__ = ["ALPHA", "ZERO_KEY", "KEY", "COUNT", "bucket", "merge_counts", "quantiles"]

#: the sketch's relative accuracy: a percentile of 100 m is known to ±0.5 m
ALPHA = 0.005
#: the bucket of zero (and of values too small for a logarithm): below every other bucket
ZERO_KEY = -(2 ** 31)
KEY, COUNT = "__key", "__n"


def _gamma(alpha: float) -> float:
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"the relative accuracy must be in (0, 1), got {alpha!r}")
    return 1.0 + 2.0 * alpha / (1.0 - alpha)


def _per_log2(alpha: float) -> float:
    """Buckets per doubling, ln 2 / ln γ (log_γ v = log₂ v · this, computed as the reference
    does, so that a value on a bucket's edge falls on the same side)."""
    return math.log(2.0) / math.log1p(2.0 * alpha / (1.0 - alpha))


def bucket(values: pl.Expr, alpha: float = ALPHA) -> pl.Expr:
    """Each value's bucket key (Int32; null: a value not counted, negative values too)."""
    tiny = sys.float_info.min * _gamma(alpha)
    finite = values.is_not_null() & values.is_finite()
    return (pl.when(finite & (values > tiny)).then((values.log(2.0) * _per_log2(alpha)).ceil())
            .when(finite & (values >= 0.0)).then(pl.lit(float(ZERO_KEY)))
            .otherwise(None).cast(pl.Int32))


def merge_counts(sketches: Sequence[pl.DataFrame], by: Sequence[str]) -> pl.DataFrame:
    """Sketches — rows (``by``…, ``quantity``, ``__key``: :func:`bucket`, ``__n``: its count) —
    merged: the counts of equal buckets added."""
    return (pl.concat(sketches, how="vertical_relaxed").group_by(*by, "quantity", KEY)
            .agg(pl.col(COUNT).sum()))


def quantiles(counts: pl.DataFrame, by: Sequence[str], wanted: Mapping[str, tuple[str, float]],
              alpha: float = ALPHA, interpolation: str = "linear") -> pl.DataFrame:
    """Per ``by`` group of the sketch ``counts`` (as :func:`merge_counts` takes them), each wanted
    column ``name: (quantity, q)``: the q-quantile of that quantity (null where the group has
    none of it). ``linear``: the values of ranks ⌊r⌋ and ⌈r⌉, r = q(n − 1), each from its
    bucket, interpolated as numpy's and polars' default quantile is — so within relative α of
    it; ``lower``: the value of rank ⌊r⌋ (the reference implementation's rule)."""
    if interpolation not in ("linear", "lower"):
        raise ValueError(f"interpolation is linear or lower, got {interpolation!r}")
    gamma, per_log2 = _gamma(alpha), _per_log2(alpha)
    ranked = (counts.sort(*by, "quantity", KEY)
              .with_columns(pl.col(COUNT).cum_sum().over(*by, "quantity").cast(pl.Float64).alias("__cum"),
                            (pl.col(COUNT).sum().over(*by, "quantity") - 1).cast(pl.Float64).alias("__last")))
    value = (pl.when(pl.col(KEY) == ZERO_KEY).then(0.0)
             .otherwise(pl.lit(2.0) ** (pl.col(KEY).cast(pl.Float64) / per_log2) * (2.0 / (1.0 + gamma))))
    out = None
    for name, (quantity, q) in wanted.items():
        if not 0.0 <= q <= 1.0:
            raise ValueError(f"a quantile is in [0, 1], got {q!r} for {name}")
        rows = ranked.filter(pl.col("quantity") == quantity)
        r = pl.lit(q) * pl.col("__last")
        # the bucket of a rank: the first whose cumulative count passes it
        got = rows.group_by(*by).agg(value.filter(pl.col("__cum") > r.floor()).first().alias("__lo"),
                                     value.filter(pl.col("__cum") > r.ceil()).first().alias("__hi"),
                                     (r - r.floor()).first().alias("__w"))
        est = pl.col("__lo") if interpolation == "lower" else pl.col("__lo") + pl.col("__w") * (pl.col("__hi") - pl.col("__lo"))
        got = got.select(*by, est.alias(name))
        out = got if out is None else out.join(got, on=list(by), how="full", coalesce=True, nulls_equal=True)
    return out
