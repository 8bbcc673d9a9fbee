"""The seed metrics (:mod:`tertiary.evaluation.accuracy`) stepped window by window: what a
window's matched rows add to a picture's sums, with what crosses windows carried, so that the
end of a run only finishes the tables (:func:`seed_tables`).

The same figures as :func:`~tertiary.evaluation.accuracy.picture_accuracy` on the whole
picture, not an approximation. A run's windows hold disjoint epochs, so the (2.15) sums per
epoch, the consistency sums per epoch and the potential accuracy add up
(:class:`~tertiary.evaluation.accuracy_buckets.SeedSums`). What a row's verdict needs from
earlier windows is carried:

* per track (:attr:`SeedState.tracks`): its first epoch (the transient cut), whether it was ever
  matched (spurious tracks) and the aircraft it was last matched to (swaps);
* per aircraft (:class:`Walk`, shared by every picture): its first reported epoch (scored from
  then on) and how many reported epochs the coverage walk has passed (each epoch's position in
  the walk, so that a gap across windows is a break);
* per aircraft and picture (:attr:`SeedState.cover`): the walk position and the track of its
  last covered epoch.

τ of the consistency bands is the one figure a window cannot give: its lag sums pair the rows of
a track up to :data:`~tertiary.evaluation.consistency.MAX_LAG` rows apart, across any number of
windows (:class:`~tertiary.evaluation.consistency.Lags`). The windows write each scored row's
statistics and aircraft (:data:`SCORED_ROWS`: the bound's samples too); the end reads them
once, a bucket of whole tracks at a time (:func:`statistic_lags`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import polars as pl

from tertiary.contract import TIME
from tertiary.evaluation.accuracy import (ACCURACY_COLUMNS, AccuracyConfig, BY_EPOCH_SCHEMA, coverage_table,
                                          empty_metrics)
from tertiary.evaluation.accuracy_buckets import SeedSums, statistic_rows, table_keys
from tertiary.evaluation.consistency import CONSISTENCY_ALL, Lags, WholeSeries

__all__ = ["Walk", "SeedState", "walk_step", "seed_rows", "seed_step", "statistic_lags", "seed_tables",
           "with_epoch_sums", "merge_runs", "SCORED_ROWS", "SEED_COLUMNS", "LAG_BUCKET_ROWS", "EPOCH_SUMS"]

_AIRCRAFT = ["run", "truth_id"]
_TRACK = ["method", "run", "track_id"]
_COVER = ["method", "run", "truth_id"]
#: the row index of a picture's matched rows (the order :class:`SeedSums` keeps for potential accuracy)
_ROW = "__row"
_STATISTICS = tuple(c for c, _ in CONSISTENCY_ALL.values())
#: what the windows write of each scored row: the bound's samples and τ's series
SCORED_ROWS: dict[str, pl.DataType] = {"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64,
                                       "track_id": pl.UInt64, "seg_class": pl.String,
                                       **{c: pl.Float64 for c in _STATISTICS}}
#: what :func:`seed_step` reads of a picture's matched, row-scored rows
SEED_COLUMNS = (*ACCURACY_COLUMNS, "method")
#: scored rows whose per-lag sums are made at a time at the end of a run (whole tracks)
LAG_BUCKET_ROWS = 2_000_000
#: the per-epoch sums of :class:`SeedSums` (its table → the window table it is written to): a
#: window's epochs are complete when it ends, so they are written with the window instead of
#: carried (a carried state that grows with the run is pickled again at every window)
EPOCH_SUMS = {"epochs": "seed_epochs", **{f"{p}:epochs": f"seed_{p}_epochs" for p in CONSISTENCY_ALL}}


def _aircraft_schema() -> dict[str, pl.DataType]:
    return {"run": pl.UInt32, "truth_id": pl.Int64, "first": TIME, "walked": pl.UInt32}


@dataclass(frozen=True)
class Walk:
    """Every picture's coverage walk so far: per (run, aircraft) its first reported epoch and the
    number of its reported epochs walked (``aircraft``), and their ``total``."""

    aircraft: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_aircraft_schema()))
    total: int = 0


def _observed(observed: pl.DataFrame) -> pl.DataFrame:
    """(run, epoch, truth_id) of the aircraft reported at each epoch, once, without nulls."""
    return (observed.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                            pl.col("truth_id").cast(pl.Int64))
            .drop_nulls().unique().sort("run", "truth_id", "epoch"))


def walk_step(walk: Walk, observed: pl.DataFrame) -> tuple[pl.DataFrame, Walk]:
    """(the window's walk: run, epoch, truth_id and ``k``, each aircraft-epoch's position in its
    aircraft's walk; the walk after the window) from the window's ``observed`` (run, epoch,
    truth_id: the aligned reports' aircraft)."""
    obs = _observed(observed)
    before = walk.aircraft
    rows = (obs.join(before.select(*_AIRCRAFT, "walked"), on=_AIRCRAFT, how="left", maintain_order="left")
            .with_columns((pl.col("walked").fill_null(0).cast(pl.Int64)
                           + pl.int_range(pl.len(), dtype=pl.Int64).over(_AIRCRAFT)).alias("k"))
            .drop("walked"))
    new = obs.group_by(_AIRCRAFT).agg(pl.col("epoch").min().alias("first"), pl.len().cast(pl.UInt32).alias("n"))
    # a window's epochs follow every earlier one's: an aircraft seen before keeps its first epoch
    aircraft = (before.join(new, on=_AIRCRAFT, how="full", coalesce=True)
                .select(*_AIRCRAFT, pl.coalesce("first", "first_right").alias("first"),
                        (pl.col("walked").fill_null(0) + pl.col("n").fill_null(0)).cast(pl.UInt32).alias("walked")))
    return rows, Walk(aircraft, walk.total + obs.height)


def _tracks_schema() -> dict[str, pl.DataType]:
    return {"method": pl.String, "run": pl.UInt32, "track_id": pl.UInt64, "first": TIME, "matched": pl.Boolean,
            "last_truth": pl.Int64}


def _cover_schema() -> dict[str, pl.DataType]:
    return {"method": pl.String, "run": pl.UInt32, "truth_id": pl.Int64, "last_k": pl.Int64, "last_id": pl.UInt64}


def _counts_schema() -> dict[str, pl.DataType]:
    return {"method": pl.String, "rows": pl.Int64, "swaps": pl.Int64, "covered": pl.Int64, "breaks": pl.Int64}


@dataclass(frozen=True)
class SeedState:
    """Every picture's seed metrics so far, keyed by ``method``: the sums (``sums``; the
    per-epoch ones each window writes instead, :data:`EPOCH_SUMS`), per track
    (``tracks``: first epoch, ever matched, last aircraft), per aircraft the walk position and
    track of its last covered epoch (``cover``), and per picture (``counts``) its matched rows
    seen, swaps, covered epochs and breaks."""

    sums: SeedSums = field(default_factory=SeedSums)
    tracks: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_tracks_schema()))
    cover: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_cover_schema()))
    counts: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_counts_schema()))


def seed_rows(rows: pl.DataFrame, id_col: str) -> pl.DataFrame:
    """What :func:`seed_step` reads of a picture's matched, row-scored ``rows`` (id column
    ``id_col``), in the carried types: the rows of several schemas then stack."""
    if id_col != "track_id":
        rows = rows.rename({id_col: "track_id"})
    return rows.select(c for c in rows.columns if c in SEED_COLUMNS).with_columns(
        pl.col("run").cast(pl.UInt32), pl.col("track_id").cast(pl.UInt64), pl.col("truth_id").cast(pl.Int64),
        pl.col("epoch").cast(TIME), pl.col("method").cast(pl.String))


def _first_of(keys: list[str]) -> pl.Expr:
    """Whether a row is the first of its ``keys`` in rows sorted by them (a shift, not a group)."""
    return pl.any_horizontal((pl.col(k) != pl.col(k).shift(1)).fill_null(True) for k in keys)


def _tracks_step(state: SeedState, m: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(every track so far with its first epoch, ever matched and last aircraft; per method the
    swaps the window adds): a track's first matched row of the window is compared with its
    last before."""
    seq = (m.filter(pl.col("truth_id").is_not_null()).select(*_TRACK, "epoch", "truth_id")
           .sort(*_TRACK, "epoch")
           .join(state.tracks.select(*_TRACK, "last_truth"), on=_TRACK, how="left", maintain_order="left"))
    prev = pl.when(_first_of(_TRACK)).then(pl.col("last_truth")).otherwise(pl.col("truth_id").shift(1))
    swaps = seq.group_by("method").agg((prev.is_not_null() & (pl.col("truth_id") != prev)).sum().alias("swaps"))
    win = (m.group_by(_TRACK).agg(pl.col("epoch").min().alias("first"),
                                  pl.col("truth_id").is_not_null().any().alias("matched"))
           .join(seq.group_by(_TRACK).agg(pl.col("truth_id").last().alias("last_truth")), on=_TRACK, how="left"))
    tracks = (state.tracks.join(win, on=_TRACK, how="full", coalesce=True)
              .select(*_TRACK, pl.coalesce("first", "first_right").alias("first"),
                      (pl.col("matched").fill_null(False) | pl.col("matched_right").fill_null(False)).alias("matched"),
                      pl.coalesce("last_truth_right", "last_truth").alias("last_truth")))
    return tracks.cast(_tracks_schema()), swaps


def _cover_step(state: SeedState, m: pl.DataFrame, walk_rows: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(the carried last covered walk position and track per picture and aircraft; per method
    the covered epochs and breaks the window adds) of
    :func:`~tertiary.evaluation.accuracy.coverage_counts`."""
    cover = (m.filter(pl.col("truth_id").is_not_null()).group_by("method", "run", "epoch", "truth_id")
             .agg(pl.col("track_id").min().alias("cover_id")))
    cov = (cover.join(walk_rows, on=["run", "epoch", "truth_id"], how="inner").sort(*_COVER, "k")
           .join(state.cover, on=_COVER, how="left", maintain_order="left"))
    first_row = _first_of(_COVER)
    prev_k = pl.when(first_row).then(pl.col("last_k")).otherwise(pl.col("k").shift(1))
    prev_id = pl.when(first_row).then(pl.col("last_id")).otherwise(pl.col("cover_id").shift(1))
    brk = (prev_k.is_not_null() & ((pl.col("k") - prev_k > 1) | (pl.col("cover_id") != prev_id))).fill_null(False)
    counts = cov.group_by("method").agg(pl.len().alias("covered"), brk.sum().alias("breaks"))
    last = cov.group_by(_COVER).agg(pl.col("k").last().alias("last_k"), pl.col("cover_id").last().alias("last_id"))
    carried = pl.concat([state.cover.join(last, on=_COVER, how="anti"), last.cast(_cover_schema())])
    return carried, counts


def _added(counts: pl.DataFrame, *parts: pl.DataFrame) -> pl.DataFrame:
    """``counts`` with each part's per-method columns added."""
    both = pl.concat([counts, *(p.cast({c: pl.Int64 for c in p.columns if c != "method"}) for p in parts)],
                     how="diagonal_relaxed")
    cols = [c for c in _counts_schema() if c != "method"]
    return both.group_by("method").agg(pl.col(c).fill_null(0).sum() for c in cols).cast(_counts_schema())


def seed_step(state: SeedState, rows: pl.DataFrame, walk_rows: pl.DataFrame, walk: Walk, cfg: AccuracyConfig
              ) -> tuple[pl.DataFrame, dict[str, pl.DataFrame], SeedState]:
    """(the window's scored rows, :data:`SCORED_ROWS`; its per-epoch sums by window table,
    :data:`EPOCH_SUMS`; the state after the window) of every picture's matched, row-scored
    ``rows`` of a window (:func:`seed_rows`; each picture's in its order), the window's coverage
    walk ``walk_rows`` (:func:`walk_step`) and the walk after it (``walk``: each aircraft's first
    reported epoch, the window's included)."""
    offset = state.counts.select("method", pl.col("rows").alias("__offset"))
    m = (rows.join(offset, on="method", how="left", maintain_order="left")
         .with_columns((pl.col("__offset").fill_null(0) + pl.int_range(pl.len()).over("method")).alias(_ROW))
         .drop("__offset"))
    tracks, swaps = _tracks_step(state, m)
    cover, covered = _cover_step(state, m, walk_rows)
    # scored as :func:`~tertiary.evaluation.accuracy.scored_rows` scores a whole picture: from the
    # aircraft's first reported epoch, after the transient of the track's first epoch
    s = (m.join(walk.aircraft.select(*_AIRCRAFT, pl.col("first").alias("__seen")), on=_AIRCRAFT, how="left",
                maintain_order="left")
         .join(tracks.select(*_TRACK, pl.col("first").alias("__t0")), on=_TRACK, how="left", maintain_order="left"))
    keep = pl.col("truth_id").is_not_null() & (pl.col("epoch") >= pl.col("__seen"))
    if cfg.skip_first_s > 0:
        keep = keep & ((pl.col("epoch") - pl.col("__t0")).dt.total_microseconds() >= round(cfg.skip_first_s * 1e6))
    scored = s.filter(keep).select(c for c in s.columns if c in ACCURACY_COLUMNS or c == _ROW)
    sums = SeedSums(0, {k: v for k, v in state.sums.tables.items() if k not in EPOCH_SUMS})
    if scored.height:
        sums.add_scored(scored, lags=False)
    epochs = {EPOCH_SUMS[k]: sums.tables.pop(k) for k in list(sums.tables) if k in EPOCH_SUMS}
    counts = _added(state.counts, m.group_by("method").agg(pl.len().alias("rows")), swaps, covered)
    out = scored.select(pl.col(c).cast(t) if c in scored.columns else pl.lit(None, t).alias(c)
                        for c, t in SCORED_ROWS.items())
    return out, epochs, SeedState(sums, tracks, cover, counts)


def with_epoch_sums(state: SeedState, read: Callable[[str], pl.DataFrame | None], shared: bool = False) -> SeedState:
    """``state`` with the per-epoch sums every window wrote (``read``: a window table's rows of
    every window, None without any), as one :class:`SeedSums` over the run holds them: one run's
    windows hold disjoint epochs, so their rows are the run's. ``shared``: the rows come from
    runs stepped apart (:func:`merge_runs`), whose windows share epochs: added up by key."""
    sums = SeedSums(state.sums.rows, dict(state.sums.tables), state.sums.lags, state.sums.samples)
    for name, table in EPOCH_SUMS.items():
        rows = read(table)
        if rows is None or not rows.height:
            continue
        if shared:
            sums.fold(name, rows, table_keys(name))
        else:
            old = sums.tables.get(name)
            sums.tables[name] = rows if old is None else pl.concat([old, rows], how="vertical_relaxed")
    return SeedState(sums, state.tracks, state.cover, state.counts)


def merge_runs(states: Sequence[SeedState], walks: Sequence[Walk | None]) -> tuple[SeedState, Walk | None]:
    """The seed metrics' state and walk over runs stepped apart (each pair holds runs of its
    own): sums and counts add up, every track, cover and aircraft row belongs to one run. No
    walk where one is missing (the seed metrics were not stepped there)."""
    sums = SeedSums()
    for s in states:
        sums.merge(s.sums)
    seed = SeedState(sums, pl.concat([s.tracks for s in states]), pl.concat([s.cover for s in states]),
                     _added(states[0].counts, *(s.counts for s in states[1:])))
    if any(w is None for w in walks):
        return seed, None
    return seed, Walk(pl.concat([w.aircraft for w in walks]), sum(w.total for w in walks))


def statistic_lags(scored: pl.LazyFrame, rows: int, carried: dict[tuple[str, str, str], Lags] | None = None
                   ) -> dict[tuple[str, str, str], Lags | WholeSeries]:
    """The per-lag sums (:class:`Lags`) of every consistency statistic of the pictures' scored
    rows (:data:`SCORED_ROWS`, a scan of the windows' parts of ``rows`` rows), read a bucket of
    whole tracks at a time: each series is whole in one bucket. Rows that fit one bucket give
    τ summed directly (:class:`WholeSeries`), unless ``carried``: the sums of other whole series
    (:mod:`tertiary.evaluation.lags_streamed`), which these are added to."""
    buckets = max(1, -(-rows // LAG_BUCKET_ROWS))
    sums = SeedSums(lags=dict(carried or {}))
    whole = buckets == 1 and carried is None
    for k in range(buckets):
        part = scored if buckets == 1 else scored.filter(pl.struct("method", "run", "track_id").hash() % buckets == k)
        part = part.collect(engine="streaming")
        for prefix, (col, _dof) in CONSISTENCY_ALL.items():
            r = statistic_rows(part, col)
            if r.height:
                sums.add_lags(r, prefix, col, whole=whole)
        del part
    return sums.lags


def seed_tables(state: SeedState, walk: Walk, stage: str, cfg: AccuracyConfig,
                lags: dict[tuple[str, str, str], Lags | WholeSeries]) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(the seed metrics, the per-epoch accuracy) of every picture with scored rows, from the
    state at the end of the run, the run's walk and the pictures' consistency ``lags``
    (:func:`statistic_lags`). One set of queries over every picture: the end of a run pays
    a query's overhead once, not once per picture; a picture's rows are those of its own."""
    c = state.counts.filter(pl.col("rows") > 0)
    if not c.height:
        return empty_metrics(), pl.DataFrame(schema=BY_EPOCH_SCHEMA)
    t = state.tracks.join(c.select("method"), on="method", how="semi")
    counts = (t.group_by("method").agg((~pl.col("matched")).sum().cast(pl.Float64).alias("spurious_tracks"),
                                       pl.len().cast(pl.Float64).alias("tracks"))
              .join(c.select("method", pl.col("swaps").cast(pl.Float64)), on="method", how="right")
              .select("method", pl.col("spurious_tracks", "tracks").fill_null(0.0), "swaps"))
    walked = (c.filter(pl.lit(walk.total > 0))
              .select("method", pl.lit(walk.total, pl.UInt32).alias("__walk"),
                      pl.col("covered").cast(pl.UInt32).alias("__covered"), pl.col("breaks").cast(pl.Float64)))
    names = set(c["method"].to_list())
    # a picture without a row is left out; tables of only those with rows are not copied (a long
    # run's per-epoch tables)
    tables = {k: v if set(v["method"].unique().to_list()) <= names else v.filter(pl.col("method").is_in(names))
              for k, v in state.sums.tables.items()}
    runs = t.select("method", "run").unique()
    sums = SeedSums(int(c["rows"].sum()), {**tables, "tracks": counts, "track_runs": runs},
                    {k: v for k, v in lags.items() if k[1] in names})
    return sums.tables_of(stage, cfg, coverage_table(walked))
