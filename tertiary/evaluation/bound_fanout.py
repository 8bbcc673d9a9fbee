"""The bound of a run whose truth is on disk, its aircraft computed apart: each aircraft's
bound is its own recursion over its truth and its illuminations, so blocks of aircraft are
independent pieces (:mod:`tertiary.runtime.fanout`), each reading its own aircraft's truth
from the reference's files. The blocks of :data:`~tertiary.evaluation.bound.BOUND_AIRCRAFT`
aircraft and their order are :func:`~tertiary.evaluation.bound.bound_stage`'s, so the rows are
the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from tertiary.contract import TABLES, TIME
from tertiary.core import geo
from tertiary.evaluation.bound import (BOUND_AIRCRAFT, BoundConfig, bound_rows, bound_setup, bound_sums, read_sums,
                                       scan_origins)
from tertiary.evaluation.bound_measurements import mode_s_first
from tertiary.runtime.fanout import Fanout
from tertiary.sensors import mlat

__all__ = ["PIECE_AIRCRAFT", "bound_stage_apart"]

#: aircraft per piece: a piece scans the reference once for them (a multiple of BOUND_AIRCRAFT,
#: so that the blocks are the serial stage's)
PIECE_AIRCRAFT = 4 * BOUND_AIRCRAFT


def bound_stage_apart(ds, fanout: Fanout, files: list[Path], columns: list[str], radars: pl.DataFrame,
                      reports: pl.DataFrame, scored: pl.DataFrame, accuracy: pl.DataFrame, notes: list[str],
                      origins: dict[int, float] | None = None) -> pl.DataFrame:
    """:func:`~tertiary.evaluation.bound.bound_stage` of the truth's ``columns`` in the reference
    ``files``, :data:`PIECE_AIRCRAFT` aircraft a piece of ``fanout``. A piece is shipped its
    aircraft's scored samples, first Mode S times and Cartesian sensors' plots only."""
    truth = pl.scan_parquet(files)
    names = [c for c in columns if c in truth.collect_schema().names()]
    setup = bound_setup(ds, names, radars, notes, not scored.is_empty())
    if setup is None:
        return pl.DataFrame(schema=TABLES["metrics"].required)
    cfg, max_el = setup
    t0 = int(truth.select(pl.col("time").cast(TIME).dt.epoch("us").min()).collect().item())
    origins = scan_origins(radars, reports, t0) if origins is None else origins
    mode_s = mode_s_first(reports)
    cart_ids = radars.filter(pl.col("kind").is_in(list(mlat.CARTESIAN_KINDS)))["radar_id"] \
        if "kind" in radars.columns else pl.Series([], dtype=pl.Int64)
    cart = reports.filter(pl.col("radar_id").is_in(cart_ids.implode())) if cart_ids.len() else reports.clear()
    ids = np.sort(scored["truth_id"].drop_nulls().unique().cast(pl.Int64).to_numpy())
    pieces = []
    for lo in range(0, len(ids), PIECE_AIRCRAFT):
        read = ids[lo:lo + PIECE_AIRCRAFT]
        mine = pl.col("truth_id").cast(pl.Int64).is_in(read.tolist())
        pieces.append((files, names, read, scored.filter(mine), radars,
                       cart.filter(mine) if "truth_id" in cart.columns else cart, ds.origin, cfg, max_el, t0,
                       origins, mode_s.filter(mine)))
    sums = [s for got in fanout(_piece, pieces) for s in got]
    return bound_rows(pl.concat(sums) if sums else bound_sums(scored.clear(), pl.DataFrame()), accuracy)


def _piece(files: list[Path], names: list[str], read: np.ndarray, scored: pl.DataFrame, radars: pl.DataFrame,
           reports: pl.DataFrame, origin: geo.LocalFrame, cfg: BoundConfig, max_el: dict[str, float], t0: int,
           origins: dict[int, float], mode_s: pl.DataFrame) -> list[pl.DataFrame]:
    """The bound sums of the aircraft ``read`` (:func:`~tertiary.evaluation.bound.read_sums`)."""
    held = (pl.scan_parquet(files).select(names)
            .filter(pl.col("truth_id").cast(pl.Int64).is_in(read.tolist())).collect())
    return read_sums(held, read, scored, radars, reports, origin, cfg, max_el, t0, origins, mode_s)
