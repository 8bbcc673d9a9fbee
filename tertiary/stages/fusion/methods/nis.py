"""``invcov_nis`` (optional): information fusion of λ_n C_n, λ_n = max(1, mean of the last
``nis_window`` normalised innovations ν²/S of the (run, radar, local track)), which down-weights
a radar whose filter lags (a manoeuvre) or is inconsistent."""

from __future__ import annotations

import numpy as np
import polars as pl

from tertiary.stages.fusion.base import TRACK, F, Fused, Ix, track_keys
from tertiary.stages.fusion.gate import nis
from tertiary.stages.fusion.methods.weighted import fuse_information
from tertiary.stages.fusion.registry import FusionMethod, register

__all__ = ["empty_nis_carry", "fuse_invcov_nis", "nis_inflation", "nis_inflation_step"]


def nis_inflation(rows: pl.DataFrame, window: int) -> F:
    """λ_n of ``invcov_nis`` per row: max(1, mean of the last ``window`` values of
    ν²/S of the row's (run, radar, local track), counting its fresh rows up to this epoch);
    1 before the track's first usable innovation."""
    return nis_inflation_step(rows, window, None)[0]


def nis_inflation_step(rows: pl.DataFrame, window: int, carry: pl.DataFrame | None
                       ) -> tuple[F, pl.DataFrame]:
    """:func:`nis_inflation` continued across windows: ``carry`` holds per (run, radar, local
    track) its last ``window`` usable NIS values (``hist``, oldest first) and the last moving
    mean (``last_mean``); returns λ per row and the new carry."""
    v = nis(rows["res_range_m"].cast(pl.Float64).fill_null(np.nan).to_numpy(),
            rows["res_range_var_m2"].cast(pl.Float64).fill_null(np.nan).to_numpy())
    use = rows["fresh"].fill_null(False).to_numpy() & np.isfinite(v)
    carry = empty_nis_carry() if carry is None else carry
    k = track_keys(rows.select(*TRACK, "epoch")).with_columns(
        pl.Series("__v", np.where(use, v, np.nan)).fill_nan(None), pl.Series("__u", use)).with_row_index("__i")
    fresh = k.filter("__u").select(*TRACK, "epoch", "__i", "__v", pl.lit(1, pl.Int8).alias("__o"))
    # the carried history goes first in each track's sequence (order 0), oldest value first
    hist = (carry.join(fresh.select(TRACK).unique(), on=TRACK, how="semi").select(*TRACK, "hist")
            .explode("hist").drop_nulls("hist")
            .select(*TRACK, pl.lit(None, k.schema["epoch"]).alias("epoch"), pl.lit(None, pl.UInt32).alias("__i"),
                    pl.col("hist").alias("__v"), pl.lit(0, pl.Int8).alias("__o")))
    seq = (pl.concat([hist, fresh.cast(hist.schema)]).sort([*TRACK, "__o", "epoch"], maintain_order=True)
           .with_columns(pl.col("__v").rolling_mean(window, min_samples=1).over(TRACK).alias("__m")))
    allr = (k.join(seq.filter(pl.col("__o") == 1).select("__i", "__m"), on="__i", how="left")
            .sort([*TRACK, "epoch", "__i"])
            .with_columns(pl.col("__m").forward_fill().over(TRACK))
            .join(carry.select(*TRACK, "last_mean"), on=TRACK, how="left", maintain_order="left")
            .sort("__i"))
    lam = np.maximum(allr["__m"].fill_null(allr["last_mean"]).fill_null(1.0).to_numpy(), 1.0)
    new = seq.group_by(TRACK, maintain_order=True).agg(pl.col("__v").tail(window).alias("hist"),
                                                       pl.col("__m").last().alias("last_mean"))
    new = pl.concat([carry.join(new, on=TRACK, how="anti"), new.cast(carry.schema)])
    return lam, new


def empty_nis_carry() -> pl.DataFrame:
    """The NIS history before the first window: no track."""
    return pl.DataFrame(schema={"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
                                "hist": pl.List(pl.Float64), "last_mean": pl.Float64})


def fuse_invcov_nis(x: F, cov: F, lam: F, starts: Ix) -> Fused:
    """``invcov_nis``: P = (Σ (λ_n C_n)⁻¹)⁻¹, x = P Σ (λ_n C_n)⁻¹ x_n."""
    return fuse_information(x, cov * lam[:, None, None], starts)


register(FusionMethod("invcov_nis", "nis", lambda b: fuse_invcov_nis(b.x, b.cov, b.col("lam"), b.starts), rank=8,
                      default=False, info_plots=True, nis_inflation=True))
