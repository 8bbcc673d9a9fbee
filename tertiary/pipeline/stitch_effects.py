"""What stitching a sliced run changes: :func:`stitching_effects` compares a sliced run's tables
(:mod:`tertiary.pipeline.dask_engine`) with an unsliced run's, by time since the nearest slice
boundary."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

import polars as pl

from tertiary.core.units import US
from tertiary.core.stage import T_MAX_US, T_MIN_US


def boundary_utc(us: int) -> str:
    """A slice boundary (µs since the Unix epoch) as UTC text; "open" for an open end."""
    if us <= T_MIN_US or us >= T_MAX_US:
        return "open"
    return datetime.fromtimestamp(us / US, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def _since(epoch: pl.Expr, bounds: list[int]) -> pl.Expr:
    """Seconds since the last slice boundary at or before ``epoch`` (null before the first)."""
    b = pl.Series(sorted(bounds), dtype=pl.Int64)
    e = epoch.dt.epoch("us")
    last = pl.lit(None, pl.Int64)
    for x in b:      # a handful of boundaries: one when/then per boundary, vectorised over rows
        last = pl.when(e >= x).then(pl.lit(x)).otherwise(last)
    return ((e - last) / US).alias("since_s")


def _target_link(dask_assoc: pl.DataFrame, local_assoc: pl.DataFrame) -> pl.DataFrame:
    """(run, epoch, target_id → target_id_local): the local target most of a distributed target's
    reports belong to at that epoch."""
    key = ["run", "epoch", "radar_id", "local_track_id", "report_id"]
    j = dask_assoc.select(*key, "target_id").join(local_assoc.select(*key, pl.col("target_id").alias("local")),
                                                  on=key)
    return (j.group_by("run", "epoch", "target_id", "local").len().sort("len", descending=True)
            .group_by("run", "epoch", "target_id").agg(pl.col("local").first()))


def stitching_effects(dask: dict[str, pl.DataFrame], local: dict[str, pl.DataFrame], bounds_us: list[int],
                      bins_s: tuple[float, ...] = (0, 5, 10, 20, 30, 60, 120, 300, 1e9), around_s: float = 30.0
                      ) -> dict[str, Any]:
    """What slicing and stitching change against the local engine's tables (same dataset, same
    configuration): per table the rows equal to the local engine's, by seconds since the last
    slice boundary (``bins_s``); per boundary the local targets/tracks alive within ``around_s``
    on both sides whose distributed id changes across it."""
    link = _target_link(dask["associations"], local["associations"])
    out: dict[str, Any] = {"boundaries": [boundary_utc(b) for b in bounds_us]}
    f = dask["fused"].join(link, on=["run", "epoch", "target_id"], how="left")
    fused = _rowwise(f.rename({"target_id": "dask_id", "local": "target_id"}), local["fused"],
                     ["run", "method", "epoch", "target_id"], bounds_us, bins_s)
    out["fused"] = fused
    out["target_id_changes"] = _id_changes(f.rename({"target_id": "dask_id", "local": "target_id"}),
                                           ["run"], "target_id", bounds_us, around_s)
    if dask.get("tracks") is not None and dask["tracks"].height and local["tracks"].height:
        lt = local["tracks"].join(local["fused"].select("run", "epoch", "method", pl.col("target_id")
                                                        .alias("plot_target_id")).unique(), how="semi",
                                  on=["run", "epoch", "method", "plot_target_id"])
        dt = (dask["tracks"].join(link.rename({"target_id": "plot_target_id"}), on=["run", "epoch", "plot_target_id"],
                                  how="left")
              .rename({"track_id": "dask_id"}))
        # a distributed track row ↔ the local track updated by the same aircraft's plot at that epoch
        pair = dt.join(lt.select("run", "method", "filter", "epoch", pl.col("plot_target_id").alias("local"),
                                 "track_id"), on=["run", "method", "filter", "epoch", "local"], how="left")
        # each distributed track (within a slice) ↔ the local track most of its updated rows match,
        # so that coasting rows (no plot) are compared too
        grp = ["run", "method", "filter"]
        slice_of = sum((pl.col("epoch").dt.epoch("us") >= b).cast(pl.Int32) for b in bounds_us) if bounds_us \
            else pl.lit(0)
        link_t = (pair.filter(pl.col("track_id").is_not_null()).with_columns(slice_of.alias("__s"))
                  .group_by(*grp, "__s", "dask_id", "track_id").len().sort("len", descending=True)
                  .group_by(*grp, "__s", "dask_id").agg(pl.col("track_id").first()))
        rows = (dt.drop("local").with_columns(slice_of.alias("__s"))
                .join(link_t, on=[*grp, "__s", "dask_id"], how="left").drop("__s"))
        out["tracks"] = _rowwise(rows, local["tracks"], [*grp, "epoch", "track_id"], bounds_us, bins_s)
        out["track_id_changes"] = _id_changes(pair, ["run", "method", "filter"], "track_id", bounds_us, around_s)
    return out


def _rowwise(d: pl.DataFrame, loc: pl.DataFrame, key: list[str], bounds: list[int], bins: tuple[float, ...]
             ) -> list[dict]:
    """Per bin of seconds since the last boundary: local rows, distributed rows matched to them,
    rows identical (positions within 1e-6 m), the RMS and max position difference (m)."""
    pos = ["x_m", "y_m", "z_m"]
    loc = loc.with_columns(_since(pl.col("epoch"), bounds))
    j = loc.select(*key, *pos, "since_s").join(d.filter(pl.col(key[-1]).is_not_null()).select(*key, *pos)
                                               .unique(subset=key, keep="first"), on=key, how="left", suffix="_d")
    err = sum((pl.col(c) - pl.col(f"{c}_d")) ** 2 for c in pos).sqrt().alias("err")
    j = j.with_columns(err, pl.col("since_s").fill_null(-1.0)
                       .bin_intervals([float(b) for b in bins], labels=_interval_labels(bins)).alias("bin"))
    g = (j.group_by("bin").agg(pl.len().alias("local_rows"), pl.col("err").is_not_null().sum().alias("matched"),
                               (pl.col("err") <= 1e-6).sum().alias("identical"),
                               (pl.col("err") ** 2).mean().sqrt().alias("rms_m"), pl.col("err").max().alias("max_m"))
         .sort("bin"))
    return g.with_columns(pl.col("bin").cast(pl.String)).to_dicts()


def _interval_labels(bins: tuple[float, ...]) -> list[str]:
    """"[a, b)" for each left-closed bin the breakpoints ``bins`` make, −inf and inf at the ends."""
    edges = ["-inf", *(str(int(b)) if float(b).is_integer() else str(float(b)) for b in bins), "inf"]
    return [f"[{a}, {b})" for a, b in zip(edges[:-1], edges[1:])]


def _id_changes(pair: pl.DataFrame, group: list[str], local_col: str, bounds: list[int], around_s: float
                ) -> list[dict]:
    """Per boundary: local ids alive on both sides (±``around_s``) and those whose distributed id
    (majority over their rows) differs across the boundary."""
    w = int(around_s * US)
    res = []
    e = pl.col("epoch").dt.epoch("us")
    p = pair.filter(pl.col(local_col).is_not_null() & pl.col("dask_id").is_not_null())
    for b in bounds:
        side = []
        for lo, hi in ((b - w, b), (b, b + w)):
            side.append(p.filter((e >= lo) & (e < hi)).group_by(*group, local_col, "dask_id").len()
                        .sort("len", descending=True).group_by(*group, local_col).agg(pl.col("dask_id").first()))
        both = side[0].join(side[1], on=[*group, local_col], suffix="_after")
        res.append({"boundary_utc": boundary_utc(b), "alive": both.height,
                    "id_changed": int((both["dask_id"] != both["dask_id_after"]).sum())})
    return res


def parse_utc(text: str) -> int:
    """µs since the Unix epoch of a ``%Y-%m-%d %H:%M:%S`` UTC text (the ``partitions`` table's)."""
    return int(datetime.strptime(text, "%Y-%m-%d %H:%M:%S").replace(tzinfo=timezone.utc).timestamp()) * US
