"""Target confirmation: which fused groups are *tentative* (the ``tentative`` column), a step
function with explicit carried state (:class:`ConfirmState`)."""

from __future__ import annotations

from dataclasses import dataclass

import polars as pl

from tertiary.contract import TIME
from tertiary.stages.fusion.base import CHAIN, GROUP, TRACK

__all__ = ["LIFE_GAP_S", "REPLY_COLUMNS", "ConfirmState", "confirm_associations_step", "confirm_targets_step",
           "replied", "tentative_at"]


@dataclass(frozen=True)
class ConfirmState:
    """Carried state of target confirmation (natural keys, no ranks): per local track the plots
    of its current life in its current target, whether one of them carried a transponder reply,
    the time of its last plot and that target (``tracks``: run, radar_id, local_track_id,
    n_plots, replied, last_time, target_id) and the targets already confirmed (``targets``: run,
    target_id)."""

    tracks: pl.DataFrame
    targets: pl.DataFrame

    @staticmethod
    def empty() -> ConfirmState:
        """The state before the first window: no track, no target."""
        return ConfirmState(
            pl.DataFrame(schema={"run": pl.UInt32, "radar_id": pl.UInt32, "local_track_id": pl.UInt32,
                                 "n_plots": pl.Int64, "replied": pl.Boolean, "last_time": TIME,
                                 "target_id": pl.UInt64}),
            pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64}))


#: a local track silent for longer than this has ended; a plot under the same number after it
#: starts a new life (radars reuse track numbers) whose plots are counted afresh
LIFE_GAP_S = 30.0

#: report columns whose value is a transponder's reply (Mode S address, Mode C, Mode 3/A code):
#: primary clutter carries none of them
REPLY_COLUMNS = ("mode_s", "altitude_m", "mode_3a")


def replied(rows: pl.DataFrame) -> pl.Expr:
    """Per row of ``rows``, whether its report carries a transponder reply (:data:`REPLY_COLUMNS`)."""
    # a NaN altitude is no Mode C reply
    cols = [pl.col(c).is_not_null() & (pl.col(c).is_not_nan() if rows.schema[c].is_float() else True)
            for c in REPLY_COLUMNS if c in rows.columns]
    return pl.any_horizontal(cols) if cols else pl.lit(False)


def confirm_targets_step(state: ConfirmState, rows: pl.DataFrame, min_plots: int = 2,
                         min_plots_primary: int | None = None) -> tuple[pl.DataFrame, ConfirmState]:
    """Which (run, epoch, target_id) groups of ``rows`` are tentative, and the new state.

    A local track supports its target from the epoch at which it has ``min_plots`` plots in
    its current life *in that target* (its fresh rows counted, carried across windows by
    ``state``; a silence longer than :data:`LIFE_GAP_S` starts a new life, since radars reuse
    the numbers of ended tracks, often for a false plot). A track none of whose plots in that
    life carried a transponder reply (:func:`replied`) needs ``min_plots_primary`` plots (None:
    ``min_plots``): a radar's false track on clutter is primary-only and short, while an
    aircraft's reply is evidence of an airframe. A group is supported when one of its
    local tracks is, or when two radars see the target. A target is confirmed from its first
    supported group on and stays so; before that it is *tentative*: made only of one radar's
    unconfirmed one-plot tracks — the clutter signature (a lone false plot never gets a second
    plot of its local track). Counting in the target, not over the local track's life, keeps a
    split-off tentative: one radar's plot that misses the gate with the others for a scan is
    grouped alone under a new id and rejoins its aircraft's target at the next scan (counted
    over the track's life, such one-scan targets would all be confirmed). Returns the groups
    (GROUP + ``tentative``) in ``rows``' group order."""
    key_types = {c: t for c, t in state.tracks.schema.items() if c in TRACK}
    has_time = "time" in rows.columns
    when = pl.col("time").cast(TIME) if has_time else pl.col("epoch").cast(TIME)
    r = rows.select(*GROUP, *[pl.col(c).cast(t) for c, t in key_types.items() if c != "run"],
                    pl.col("fresh").fill_null(False), when.alias("__t"),
                    replied(rows).alias("__reply")).with_row_index("__i")
    r = (r.join(state.tracks.rename({"target_id": "__last_target"}), on=TRACK, how="left", maintain_order="left")
         .sort("epoch", "__i"))
    fresh_t = pl.when(pl.col("fresh")).then(pl.col("__t"))
    prev = pl.coalesce(fresh_t.forward_fill().shift(1).over(TRACK), pl.col("last_time"))
    gap_us = round(LIFE_GAP_S * 1e6)
    brk = pl.col("fresh") & ((pl.col("__t") - prev).dt.total_microseconds() > gap_us).fill_null(False)
    # the track's target at its previous row (this window's, else the carried one)
    before = pl.coalesce(pl.col("target_id").shift(1).over(TRACK), pl.col("__last_target"))
    moved = (pl.col("target_id") != before).fill_null(False)
    r = r.with_columns((brk | moved).cast(pl.Int64).cum_sum().over(TRACK).alias("__life"))
    base = pl.when(pl.col("__life") == 0).then(pl.col("n_plots").fill_null(0)).otherwise(0)
    life = [*TRACK, "__life"]
    was = pl.when(pl.col("__life") == 0).then(pl.col("replied").fill_null(False)).otherwise(False)
    r = r.with_columns((base + pl.col("fresh").cast(pl.Int64).cum_sum().over(life)).alias("__n"),
                       (was | (pl.col("fresh") & pl.col("__reply")).cum_max().over(life)).alias("__ssr"))
    primary = min_plots if min_plots_primary is None else min_plots_primary
    need = pl.when(pl.col("__ssr")).then(min_plots).otherwise(primary)
    grp = (r.group_by(GROUP, maintain_order=True)
           .agg(((pl.col("__n") >= need).any() | (pl.col("radar_id").n_unique() >= 2)).alias("__sup"))
           .join(state.targets.with_columns(pl.lit(True).alias("__was")), on=CHAIN, how="left",
                 maintain_order="left")
           .with_columns((pl.col("__sup") | pl.col("__was").fill_null(False)).cum_max().over(CHAIN)
                         .alias("__conf")))
    order = rows.select(GROUP).unique(maintain_order=True)
    out = order.join(grp.select(*GROUP, (~pl.col("__conf")).alias("tentative")), on=GROUP, how="left",
                     maintain_order="left")
    last = r.group_by(TRACK).agg(pl.col("__n").last().alias("n_plots"), pl.col("__ssr").last().alias("__rp"),
                                 pl.col("__t").filter(pl.col("fresh")).max().alias("__lt"),
                                 pl.col("target_id").last().alias("__tg"))
    tracks = (state.tracks.join(last, on=TRACK, how="full", coalesce=True)
              .select(*TRACK, pl.coalesce("n_plots_right", "n_plots").alias("n_plots"),
                      pl.coalesce("__rp", "replied").alias("replied"),
                      pl.coalesce("__lt", "last_time").alias("last_time"),
                      pl.coalesce("__tg", "target_id").alias("target_id"))
              .cast(state.tracks.schema))
    targets = pl.concat([state.targets, grp.filter("__conf").select(CHAIN).cast(state.targets.schema)]).unique()
    return out, ConfirmState(tracks, targets)


def tentative_at(confirmed: pl.DataFrame, groups: pl.DataFrame, keys: pl.DataFrame) -> pl.Series:
    """``tentative`` at arbitrary (run, epoch, target_id) ``keys``, from the targets ``confirmed``
    before a window (run, target_id: a state's ``targets``) and that window's ``groups``
    (:func:`confirm_targets_step`'s output, or any step's of the same form): a target is
    confirmed from its first non-tentative group on, or throughout when it was confirmed before. Keys
    between the target's groups (an estimate predicted to an epoch it has no report at) take
    the status the target has reached by then, as a confirmed target never turns back."""
    first = (groups.filter(~pl.col("tentative")).group_by(CHAIN).agg(pl.col("epoch").min().alias("__from"))
             .cast({"run": confirmed.schema["run"], "target_id": confirmed.schema["target_id"]}))
    k = (keys.select(pl.col("run").cast(confirmed.schema["run"]), pl.col("epoch").cast(TIME),
                     pl.col("target_id").cast(confirmed.schema["target_id"]))
         .join(confirmed.with_columns(pl.lit(True).alias("__was")), on=CHAIN, how="left", maintain_order="left")
         .join(first, on=CHAIN, how="left", maintain_order="left"))
    return k.select((~(pl.col("__was").fill_null(False) | (pl.col("epoch") >= pl.col("__from")).fill_null(False)))
                    .alias("tentative")).to_series()


def confirm_associations_step(before: ConfirmState, associations: pl.DataFrame, new: pl.DataFrame,
                              reports: pl.DataFrame, min_plots: int, min_plots_primary: int | None = None
                              ) -> tuple[pl.DataFrame, ConfirmState]:
    """:func:`confirm_targets_step` on the window's association rows, which are the fused
    pictures' rows: a row is fresh at its report's first association epoch (``new``: the rows of
    the reports not associated before the window), as the aligned row of a report's first epoch
    is; only fresh rows need their report's ``time`` and replies, and those reports are in ``reports``.
    Returns the groups (run, epoch, target_id, ``tentative``) and the new state; an empty window
    leaves the state as it is, as the fusion stage does."""
    if associations.is_empty():
        empty = pl.DataFrame(schema={"run": pl.UInt32, "epoch": TIME, "target_id": pl.UInt64, "tentative": pl.Boolean})
        return empty, before
    first = new.group_by("run", "report_id").agg(pl.col("epoch").min().alias("__first"))
    rows = (associations.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                                pl.col("target_id").cast(pl.UInt64), "radar_id", "local_track_id",
                                pl.col("report_id").cast(pl.UInt64))
            .join(first, on=["run", "report_id"], how="left", maintain_order="left")
            .with_columns((pl.col("epoch") == pl.col("__first")).fill_null(False).alias("fresh"))
            .join(reports.select("run", "report_id", "time", *[c for c in REPLY_COLUMNS if c in reports.columns]),
                  on=["run", "report_id"], how="left", maintain_order="left"))
    return confirm_targets_step(before, rows, min_plots, min_plots_primary)
