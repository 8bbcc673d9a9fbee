"""The bound's metrics (:mod:`tertiary.evaluation.bound`, "Metrics"): the posterior Cramér–Rao
bound pooled over a picture's scored samples as its RMSE is, and the signed gap to that RMSE.
The sums per (method, segment, epoch, run) add up over blocks of aircraft; an epoch whose samples
are all in folds into its (method, segment) pool (:func:`epoch_pools`), which adds up over epochs."""

from __future__ import annotations

import polars as pl

from tertiary.contract import TABLES, TIME

__all__ = ["BOUND_METRICS", "GAP", "UNMEASURED", "bound_metrics", "bound_rows", "bound_sums", "epoch_pools",
           "merged_pools", "pool_rows"]

#: metric → (bound column, accuracy metric it is compared with)
BOUND_METRICS: dict[str, tuple[str, str]] = {
    "pcrb_pos_m": ("b2_pos", "rmse_pos_m"),
    "pcrb_horizontal_m": ("b2_horizontal", "rmse_horizontal_m"),
    "pcrb_vel_mps": ("b2_vel", "rmse_vel_mps"),
}
GAP = {"pcrb_pos_m": "gap_pos_m", "pcrb_horizontal_m": "gap_horizontal_m", "pcrb_vel_mps": "gap_vel_mps"}
#: the scored samples before their aircraft's first measurement: no bound, not pooled
UNMEASURED = "bound_unmeasured_samples"


def bound_metrics(scored: pl.DataFrame, accuracy: pl.DataFrame, bound: pl.DataFrame) -> pl.DataFrame:
    """Metrics rows (stage ``bound``): per picture (``scored.method``) and segment, the bound
    pooled over that picture's scored samples like its RMSE — sqrt(mean_k mean_{j∈k} b²) —
    and the signed gap to the picture's accuracy row (``accuracy``: metrics rows of stages
    fusion/tracker). ``scored``: method, run, epoch, truth_id, seg_class; ``bound``: from
    :func:`tertiary.evaluation.bound.pcrb_at`."""
    return bound_rows(bound_sums(scored, bound), accuracy)


def bound_sums(scored: pl.DataFrame, bound: pl.DataFrame) -> pl.DataFrame:
    """Per (method, segment, epoch, run): the sums of each bound column over the scored samples
    and their count — what :func:`bound_metrics` pools, summable over blocks of aircraft."""
    cols = [c for c, _ in BOUND_METRICS.values()]
    if scored.is_empty() or bound.is_empty():
        return pl.DataFrame(schema={"method": pl.String, "segment": pl.String, "epoch": TIME, "run": pl.UInt32,
                                    **{c: pl.Float64 for c in cols}, "__n": pl.UInt32, "__unmeasured": pl.UInt32})
    s = scored.select("method", pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                      pl.col("truth_id").cast(pl.Int64), "seg_class")
    s = s.join(bound, on=["truth_id", "epoch"], how="inner")
    measured = pl.col(cols[0]).is_not_nan()
    aggs = [*[pl.col(c).filter(measured).sum() for c in cols], measured.sum().cast(pl.UInt32).alias("__n"),
            (~measured).sum().cast(pl.UInt32).alias("__unmeasured")]
    # segment "all" and each sample's straight/turn class grouped in place: the samples of every
    # picture are not copied once per segment (the stage's peak on a long run)
    names = [pl.col("method", "segment").cast(pl.String)]       # the samples' may be categorical
    return pl.concat([s.group_by("method", pl.lit("all").alias("segment"), "epoch", "run").agg(*aggs)
                      .with_columns(names),
                      s.group_by("method", pl.col("seg_class").alias("segment"), "epoch", "run").agg(*aggs)
                      .filter(pl.col("segment").is_not_null()).with_columns(names)])


def epoch_pools(sums: pl.DataFrame) -> pl.DataFrame:
    """Per (method, segment), what its epochs in :func:`bound_sums` ``sums`` (every sample of
    each) add to the pooled bound: each column's per-epoch mean summed over the measured epochs
    (an epoch whose samples all precede their first plot pools nothing), their count ``__k``, the
    unmeasured samples and the most runs at an epoch."""
    cols = [c for c, _ in BOUND_METRICS.values()]
    per = sums.group_by("method", "segment", "epoch").agg(*[(pl.col(c).sum() / pl.col("__n").sum()).alias(c)
                                                            for c in cols],
                                                          pl.col("__n").sum(), pl.col("__unmeasured").sum(),
                                                          pl.col("run").n_unique().alias("__runs"))
    measured = pl.col("__n") > 0
    return per.group_by("method", "segment").agg(*[pl.col(c).filter(measured).sum() for c in cols],
                                                 measured.sum().cast(pl.UInt64).alias("__k"),
                                                 pl.col("__unmeasured").sum().cast(pl.UInt64),
                                                 pl.col("__runs").max().cast(pl.UInt32))


def merged_pools(*pools: pl.DataFrame | None) -> pl.DataFrame | None:
    """The :func:`epoch_pools` of disjoint sets of epochs as one (None: none given)."""
    have = [p for p in pools if p is not None and p.height]
    if len(have) < 2:
        return have[0] if have else next((p for p in pools if p is not None), None)
    both = pl.concat(have)
    return both.group_by("method", "segment").agg(
        *[pl.col(c).sum() for c in both.columns if c not in ("method", "segment", "__runs")], pl.col("__runs").max())


def bound_rows(sums: pl.DataFrame, accuracy: pl.DataFrame) -> pl.DataFrame:
    """:func:`bound_metrics` rows from the :func:`bound_sums` of every sample."""
    return pool_rows(epoch_pools(sums) if not sums.is_empty() else None, accuracy)


def pool_rows(pools: pl.DataFrame | None, accuracy: pl.DataFrame) -> pl.DataFrame:
    """:func:`bound_metrics` rows from the :func:`epoch_pools` of every epoch: sqrt(mean_k mean_{j∈k} b²)."""
    spec = TABLES["metrics"].required
    if pools is None or pools.is_empty():
        return pl.DataFrame(schema=spec)
    cols = [c for c, _ in BOUND_METRICS.values()]
    k = pl.col("__k")
    pooled = pools.select("method", "segment", *[pl.when(k > 0).then(pl.col(c) / k).sqrt().alias(c) for c in cols],
                          pl.col("__unmeasured").cast(pl.Float64).alias(UNMEASURED),
                          pl.col("__runs").alias("n_runs"))
    long = pooled.unpivot(index=["method", "segment", "n_runs"], on=[*cols, UNMEASURED], variable_name="col",
                          value_name="value")
    name = {c: m for m, (c, _) in BOUND_METRICS.items()} | {UNMEASURED: UNMEASURED}
    long = long.with_columns(pl.col("col").replace_strict(name, return_dtype=pl.String).alias("metric"))
    if "stage" in accuracy.columns:      # the seed accuracy rows (not the surveillance stage's)
        accuracy = accuracy.filter(pl.col("stage").is_in(["fusion", "tracker"]))
    acc = accuracy.filter(pl.col("metric").is_in([a for _, a in BOUND_METRICS.values()])).select(
        "method", "segment", pl.col("metric").alias("__acc"), pl.col("value").alias("__rmse"))
    acc_of = {m: a for m, (_, a) in BOUND_METRICS.items()}
    gap = (long.filter(pl.col("metric").is_in(list(BOUND_METRICS))).with_columns(pl.col("metric").replace_strict(acc_of, return_dtype=pl.String).alias("__acc"))
           .join(acc, on=["method", "segment", "__acc"], how="inner")
           .with_columns((pl.col("__rmse") - pl.col("value")).alias("value"),
                         pl.col("metric").replace_strict(GAP, return_dtype=pl.String).alias("metric")))
    out = pl.concat([long.select("method", "metric", "segment", "value", "n_runs"),
                     gap.select("method", "metric", "segment", "value", "n_runs")])
    order = {m: i for i, m in enumerate([*BOUND_METRICS, *GAP.values(), UNMEASURED])}
    seg = pl.col("segment").replace_strict({"all": 0, "straight": 1, "turn": 2}, default=3, return_dtype=pl.Int8)
    return (out.with_columns(pl.lit("bound").alias("stage"))
            .sort(pl.col("method"), seg, pl.col("metric").replace_strict(order, return_dtype=pl.Int8))
            .select([pl.col(c).cast(t) for c, t in spec.items()]))
