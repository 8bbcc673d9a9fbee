"""The surveillance metrics (:mod:`tertiary.evaluation.picture_metrics`) stepped window by
window: what a window's matched rows and reference add to every picture's sums, with what
crosses windows carried, so that the end of a run only resolves a few deferred rows and writes
the table (:func:`picture_metrics_finish`).

The same figures as :func:`~tertiary.evaluation.picture_metrics.picture_metrics` of the whole
picture, not an approximation (the percentiles are the same mergeable sketch). A window holds
whole epochs and the windows come in time order; what a row's figures need of other windows is
carried per (picture, run, aircraft):

* the labels: the last reference state (the turn rate differences the heading with it); an
  aircraft seen at one epoch only is held, with its rows, until a second epoch gives its first
  epoch's turn rate (``pending``);
* exposure: the last reference epoch, counted when the next one comes;
* update intervals: the aircraft's first epoch (the bins' origin) and its bins from the last
  reference bin on, still open to updates;
* breaks and identity changes: the last represented epoch and its representative track.

The representative track is chosen by how often each track was matched to the aircraft over the
whole run, which no window knows. It matters only at an *ambiguous* epoch (two tracks or more
on one aircraft): those rows are kept (:attr:`PictureStepState.ambiguous`, with the changes next
to them and the merged-track hits of their candidates) and resolved at the end with the run's
counts; every other epoch's representative is its only track.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.evaluation import sketch
from tertiary.evaluation.picture_buckets import (Partials, accuracy_combined, accuracy_sums, continuity_combined,
                                                 identity_combined)
from tertiary.evaluation.picture_metrics import (MetricsConfig, height_exprs, by_segment, count_tracks,
                                                 error_rows, finish_metrics, gated_rows, identity_checks, merge_hits,
                                                 picture_rows, reference_labels, track_inputs, track_table)

__all__ = ["PictureStepState", "picture_step", "picture_metrics_finish", "merge_runs", "LABELS"]

_KEY = ["method", "run", "truth_id"]
#: the breakdown labels every labelled row carries (``range`` null without radars)
LABELS = ("alt", "range", "phase")
_AT = [*_KEY, "epoch"]


@dataclass(frozen=True)
class PictureStepState:
    """Every picture's carried rows and sums (frames keyed by ``method``); None: nothing yet.

    ``tracks``: (method, run, track_id, __real, __gated, __beyond, __t0, __t1); ``counts``: rows matched per
    (method, run, truth_id, track_id); ``context``: each aircraft's last labelled reference
    state; ``pending_ref`` / ``pending_rows`` / ``pending_hits``: an aircraft's first epoch with
    no second yet (its reference, its matched rows, the merged-track hits of it as the bare
    aircraft); ``exposure``: each aircraft's last reference epoch, labelled; ``origin``: its
    first; ``bins``: its open update intervals; ``last_rep``: its last represented epoch and
    track (null: ambiguous); ``changes``: the representative changes that touch an ambiguous
    epoch; ``ambiguous``: the rows of ambiguous epochs, labelled; ``ambiguous_hits``: the
    merged-track hits of their candidates; ``merged``: distinct merged tracks by label; ``split``,
    ``pending_split``: see below;
    ``sums``: the additive partials by picture, run and labels, a frame per kind."""

    tracks: pl.DataFrame | None = None
    counts: pl.DataFrame | None = None
    context: pl.DataFrame | None = None
    pending_ref: pl.DataFrame | None = None
    pending_rows: tuple[pl.DataFrame, ...] = ()
    pending_hits: pl.DataFrame | None = None
    exposure: pl.DataFrame | None = None
    origin: pl.DataFrame | None = None
    bins: pl.DataFrame | None = None
    last_rep: pl.DataFrame | None = None
    changes: pl.DataFrame | None = None
    ambiguous: pl.DataFrame | None = None
    ambiguous_hits: pl.DataFrame | None = None
    merged: pl.DataFrame | None = None
    #: distinct split tracks by label (:func:`_seconds`), and the second-track rows of aircraft
    #: still waiting for their labels
    split: pl.DataFrame | None = None
    pending_split: pl.DataFrame | None = None
    sums: dict[str, list[pl.DataFrame]] = field(default_factory=dict)
    #: the reference has positions: merged tracks are counted
    merge: bool = False


#: the frames of :class:`PictureStepState`, each keyed by picture and run
_FRAMES = ("tracks", "counts", "context", "pending_ref", "pending_hits", "exposure", "origin", "bins", "last_rep",
           "changes", "ambiguous", "ambiguous_hits", "merged", "split", "pending_split")


def merge_runs(states: Sequence[PictureStepState]) -> PictureStepState:
    """Every picture's state over runs stepped apart (each state holds runs of its own): every
    carried row belongs to one run, the sums are lists of partials that add up."""
    states = list(states)
    if len(states) == 1:
        return states[0]
    sums: dict[str, list[pl.DataFrame]] = {}
    for s in states:
        for kind, parts in s.sums.items():
            sums.setdefault(kind, []).extend(parts)
    return PictureStepState(**{f: _cat(*(getattr(s, f) for s in states)) for f in _FRAMES},
                            pending_rows=tuple(f for s in states for f in s.pending_rows), sums=sums,
                            merge=any(s.merge for s in states))


def _cat(*frames: pl.DataFrame | None) -> pl.DataFrame | None:
    """The frames that exist, stacked (types relaxed); None if none does."""
    have = [f for f in frames if f is not None and f.width]
    if not have:
        return None
    return have[0] if len(have) == 1 else pl.concat(have, how="diagonal_relaxed")


def _nonempty(frame: pl.DataFrame | None) -> bool:
    return frame is not None and frame.height > 0


def _key_cast(frame: pl.DataFrame) -> pl.DataFrame:
    """The key columns in one type whatever the picture: windows' frames stack without casts."""
    casts = {"method": pl.String, "run": pl.UInt32, "truth_id": pl.Int64, "track_id": pl.UInt64}
    return frame.with_columns(pl.col(c).cast(t) for c, t in casts.items() if c in frame.columns)


def _tracks(state: PictureStepState, rows: pl.DataFrame) -> pl.DataFrame:
    """The per-track table with this window's rows (:func:`~tertiary.evaluation.picture_metrics.track_table`)."""
    new = track_table(rows)
    both = _cat(state.tracks, new)
    return both.group_by("method", "run", "track_id").agg(pl.col("__real", "__gated", "__beyond").any(),
                                                          pl.col("__t0").min(),
                                                          pl.col("__t1").max())


def _counts(state: PictureStepState, m: pl.DataFrame) -> pl.DataFrame:
    new = m.group_by(*_KEY, "track_id").agg(pl.len().alias("__n"))
    return _cat(state.counts, new).group_by(*_KEY, "track_id").agg(pl.col("__n").sum())


def _labels(state: PictureStepState, ref: pl.DataFrame, radar_xy: NDArray[np.float64] | None,
            cfg: MetricsConfig, final: bool) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(the labels of the reference rows that can be labelled now, the new context, the
    reference still pending). ``ref``: the window's reference with the held one; ``final``:
    nothing comes later, every row is labelled (a lone epoch has no turn rate)."""
    ctx = state.context
    given = _cat(ctx.with_columns(pl.lit(True).alias("__ctx")) if ctx is not None else None,
                 ref.with_columns(pl.lit(False).alias("__ctx")))
    # an aircraft with no earlier labelled state and one epoch so far: its turn rate is the next
    # step's, which a later window brings
    n = given.group_by(_KEY).agg(pl.col("epoch").n_unique().alias("__k"), pl.col("__ctx").any().alias("__had"))
    wait = n.filter(~pl.col("__had") & (pl.col("__k") == 1) & (not final)).select(_KEY)
    ready = given.join(wait, on=_KEY, how="anti") if wait.height else given
    labels = reference_labels(ready.drop("__ctx"), radar_xy, cfg, keys=_KEY)
    if ctx is not None:
        labels = labels.join(ctx.select(_AT), on=_AT, how="anti")
    last = ready.drop("__ctx").sort("epoch").unique(_KEY, keep="last")
    context = _cat(ctx.join(last.select(_KEY), on=_KEY, how="anti") if ctx is not None else None, last)
    return labels, context, ref.join(wait, on=_KEY, how="semi")


def _same_aircraft() -> pl.Expr:
    """In a frame sorted by aircraft: whether a row's aircraft is that of the row before it (a
    mask on plain shifts, not a window function per aircraft)."""
    return ~pl.any_horizontal(pl.col(k).ne_missing(pl.col(k).shift(1)) for k in _KEY)


def _exposure(state: PictureStepState, labelled: pl.DataFrame, cfg: MetricsConfig
              ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(exposure rows counted now, each aircraft's last epoch carried): a reference epoch counts
    until the next one, at most ``gap_s`` (:func:`~tertiary.evaluation.picture_metrics.exposure_rows`)."""
    rows = _cat(state.exposure, labelled.select(*_AT, *LABELS)).sort(_AT)
    nxt = pl.when(_same_aircraft().shift(-1)).then(pl.col("epoch").shift(-1))
    dt = (nxt - pl.col("epoch")).dt.total_microseconds() / 1e6
    dt = pl.when(dt > cfg.gap_s).then(0.0).otherwise(dt)
    rows = rows.with_columns((dt / 3600.0).alias("__hours"))
    return rows.filter(pl.col("__hours").is_not_null()), rows.filter(pl.col("__hours").is_null()).drop("__hours")


def _events(state: PictureStepState, m: pl.DataFrame, labels: pl.DataFrame, cfg: MetricsConfig
            ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(representative rows with their break and change flags, the changes that touch an
    ambiguous epoch, the rows of the ambiguous epochs, each aircraft's last represented epoch)."""
    per = m.group_by(_AT).agg(pl.col("track_id").n_unique().alias("__k"), pl.col("track_id").first())
    per = per.with_columns(pl.when(pl.col("__k") == 1).then(pl.col("track_id")).alias("track_id")).drop("__k")
    ambiguous = (m.join(per.filter(pl.col("track_id").is_null()).select(_AT), on=_AT, how="semi")
                 .select(*_AT, "track_id").unique().join(labels, on=_AT, how="left"))
    carried = state.last_rep
    rows = _cat(carried.with_columns(pl.lit(True).alias("__old")) if carried is not None else None,
                per.with_columns(pl.lit(False).alias("__old"))).sort(_AT)
    same = _same_aircraft()
    prev_t, prev_e = pl.when(same).then(pl.col("track_id").shift(1)), pl.when(same).then(pl.col("epoch").shift(1))
    rows = rows.with_columns(prev_t.alias("__prev"), prev_e.alias("__prev_epoch"),
                             ((pl.col("epoch") - prev_e).dt.total_microseconds() / 1e6).alias("__gap_s"))
    last = rows.unique(_KEY, keep="last").select(*_AT, "track_id")
    rows = rows.filter(~pl.col("__old")).join(labels, on=_AT, how="left")
    unknown = pl.col("__prev_epoch").is_not_null() & (pl.col("track_id").is_null() | pl.col("__prev").is_null())
    changes = rows.filter(unknown).select(*_AT, "track_id", "__prev", "__prev_epoch", *LABELS)
    rep = rows.with_columns((pl.col("track_id") != pl.col("__prev")).fill_null(False).alias("__change"),
                            (pl.col("__gap_s") > cfg.gap_s).fill_null(False).alias("__break"))
    return rep, changes, ambiguous, last


def _intervals(state: PictureStepState, labelled: pl.DataFrame, rep: pl.DataFrame, cfg: MetricsConfig
               ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(intervals closed now, the open ones, each aircraft's origin): the reference epochs' bins
    from the aircraft's first epoch, updated when a representative row falls in them
    (:func:`~tertiary.evaluation.picture_metrics.update_intervals`). An aircraft's bins from its
    last reference bin on stay open: a later window may update them."""
    t_us = int(round(cfg.expected_interval_s * 1e6))
    first = labelled.group_by(_KEY).agg(pl.col("epoch").min().alias("__t0"))
    origin = _cat(state.origin, first).group_by(_KEY).agg(pl.col("__t0").min())

    def binned(f: pl.DataFrame) -> pl.DataFrame:
        return f.join(origin, on=_KEY).with_columns(
            ((pl.col("epoch") - pl.col("__t0")).dt.total_microseconds() // t_us).alias("__bin")).drop("__t0")
    ref_bins = binned(labelled.select(*_AT, *LABELS)).with_columns(pl.lit(False).alias("updated"))
    rep_bins = binned(rep.select(_AT)).select(*_KEY, "__bin").unique().with_columns(
        pl.lit(True).alias("updated"))
    bins = (_cat(state.bins, ref_bins, rep_bins).sort([*_KEY, "__bin", "epoch"], nulls_last=True)
            .group_by(*_KEY, "__bin", maintain_order=True)
            .agg(pl.col("epoch").first(), *(pl.col(c).first() for c in LABELS), pl.col("updated").any()))
    top = pl.col("__bin").filter(pl.col("epoch").is_not_null()).max().over(_KEY)
    bins = bins.with_columns(top.alias("__top"))
    closed = bins.filter(pl.col("epoch").is_not_null() & (pl.col("__bin") < pl.col("__top")))
    open_ = bins.filter(pl.col("__top").is_null() | (pl.col("__bin") >= pl.col("__top"))).drop("__top")
    return closed.drop("__top"), open_, origin


def _representative_points(m: pl.DataFrame) -> pl.DataFrame:
    """Where each aircraft's representative is at each epoch, or each candidate at an ambiguous
    epoch (``__amb``): (method, run, epoch, track_id, __other, x_m, y_m, __th, __amb), as
    :func:`~tertiary.evaluation.picture_metrics.rep_points` gives them; ``m``: (method, run,
    truth_id, epoch, track_id, x_m, y_m, __th its height)."""
    k = m.group_by(_AT).agg(pl.col("track_id").n_unique().alias("__k"))
    if k.height == m.height:            # one row per aircraft and epoch: each is its representative
        rows = m.with_columns(pl.lit(False).alias("__amb"))
    else:
        rows = m.join(k, on=_AT).with_columns((pl.col("__k") > 1).alias("__amb"))
        rows = pl.concat([rows.filter(~pl.col("__amb")).unique(_AT, keep="first", maintain_order=True),
                          rows.filter(pl.col("__amb"))])
    return rows.select("method", "run", "epoch", "track_id", pl.col("truth_id").alias("__other"), "x_m", "y_m",
                       "__th", "__amb")


def _seconds(given: Sequence[pl.DataFrame], keys: pl.DataFrame | None) -> pl.DataFrame | None:
    """The window's second-track rows (:func:`~tertiary.evaluation.picture_metrics.gated_rows`)
    of an aircraft that another track represents at that epoch: (method, run, truth_id, epoch,
    track_id). ``keys``: the window's matched rows (a window holds whole epochs, so an epoch's
    representative is among them)."""
    rows = _cat(*(gated_rows(f, pl.Int64) for f in given))
    if rows is None or keys is None or rows.height == 0:
        return None
    return (rows.join(keys.rename({"track_id": "__rep"}), on=_AT).filter(pl.col("track_id") != pl.col("__rep"))
            .select(*_AT, "track_id"))


def _hits(points: pl.DataFrame | None, ref: pl.DataFrame, cfg: MetricsConfig) -> pl.DataFrame:
    """Merged-track hits of one window: a representative (or candidate) track within the gates of
    another aircraft that has no track of its own then (:func:`~tertiary.evaluation.picture_metrics.merge_hits`);
    ``points``: the matched rows' (method, run, truth_id, epoch, track_id, x_m, y_m, __th)."""
    bare = ref if points is None else ref.join(points.select(_AT).unique(), on=_AT, how="anti")
    th, _ = height_exprs(bare, "true_")
    bare = bare.select(*_AT, "true_x_m", "true_y_m", th.alias("__h"))
    if bare.height == 0 or points is None:
        return pl.DataFrame(schema={**{c: bare.schema[c] for c in _AT}, "track_id": pl.UInt64, "__other": pl.Int64,
                                    "__amb": pl.Boolean})
    trk = _representative_points(points)
    return (merge_hits(bare, trk, cfg, spread_bare=bare.height < trk.height)
            .select(*_AT, "track_id", "__other", "__amb"))


#: what the sums are kept by: each picture, run and combination of labels (a few hundred rows);
#: the segments are made of them at the end (:func:`_segment_partials`)
_FINE = ["method", "run", *LABELS]


def _fine(frame: pl.DataFrame, *aggs: pl.Expr, by: Sequence[str] = ()) -> pl.DataFrame:
    return frame.group_by(*_FINE, *by).agg(*aggs)


def _error_sums(err: pl.DataFrame, cfg: MetricsConfig) -> dict[str, pl.DataFrame]:
    """The accuracy and identity sums of error rows and the counts of their percentiles' sketch
    by labels."""
    out = {"accuracy": _fine(err, *accuracy_sums())}
    values = []
    for quantity, v in (("horizontal", pl.col("err_h_m")), ("height", pl.col("err_height_m").abs())):
        keyed = err.select(*_FINE, sketch.bucket(v).alias(sketch.KEY)).drop_nulls(sketch.KEY)
        values.append(_fine(keyed, pl.len().cast(pl.UInt64).alias(sketch.COUNT), by=[sketch.KEY])
                      .with_columns(pl.lit(quantity).alias("quantity")))
    out["values"] = pl.concat(values)
    for name, ok in identity_checks(err, cfg):
        rows = err.select(*_FINE, ok.alias("__ok")).filter(pl.col("__ok").is_not_null())
        out[f"identity:{name}"] = _fine(rows, pl.col("__ok").sum(), pl.len().alias("__n"))
    return out


def _fold(name: str, frames: list[pl.DataFrame]) -> pl.DataFrame:
    """The partial sums of one kind as one frame (sums added, maxima kept)."""
    both = pl.concat(frames, how="diagonal_relaxed")
    keys = [*_FINE, *((sketch.KEY, "quantity") if name == "values" else ())]
    return both.group_by(keys).agg(pl.col(c).max() if c.startswith("max_") else pl.col(c).sum()
                                   for c in both.columns if c not in keys)


def _added(sums: dict[str, list[pl.DataFrame]], new: dict[str, pl.DataFrame]) -> dict[str, list[pl.DataFrame]]:
    """``sums`` with ``new`` added, kind by kind, each kind one frame: the state is the same
    whatever the windows."""
    out = dict(sums)
    for name, frame in new.items():
        if frame.height == 0:
            continue
        out[name] = [_fold(name, [*out[name], frame])] if name in out else [frame]
    return out


def _counted(sums: dict[str, list[pl.DataFrame]], err: Sequence[pl.DataFrame], hours: pl.DataFrame | None,
             rep: pl.DataFrame | None, closed: pl.DataFrame | None, cfg: MetricsConfig
             ) -> dict[str, list[pl.DataFrame]]:
    """``sums`` with those of the labelled rows added."""
    for e in err:                   # a frame per picture schema
        if e.height:
            sums = _added(sums, _error_sums(e, cfg))
    new = {}
    if _nonempty(hours):
        new["hours"] = _fine(hours, pl.col("__hours").sum())
    if _nonempty(rep):
        new["events"] = _fine(rep, pl.col("__change").sum().alias("__changes"),
                              pl.col("__break").sum().alias("track_breaks"),
                              pl.col("__gap_s").filter(pl.col("__break")).sum().alias("__gaps"))
    if _nonempty(closed):
        new["intervals"] = _fine(closed, pl.col("updated").sum().alias("__updated"), pl.len().alias("__n"))
    return _added(sums, new)


def _segment_partials(partial: dict[str, list[pl.DataFrame]], breakdown: Sequence[str]) -> Partials:
    """The sums by (method, segment, run) that the whole-picture combine steps read."""
    sums = {name: _fold(name, frames) for name, frames in partial.items()}
    def seg(name: str, by: Sequence[str] = ("run",)) -> list[pl.DataFrame]:
        f = sums.get(name)
        if f is None:
            return []
        keys = {*_FINE, *by}
        aggs = [pl.col(c).max() if c.startswith("max_") else pl.col(c).sum() for c in f.columns if c not in keys]
        return [by_segment(f, breakdown, *aggs, by=list(by))]
    values = [v.with_columns(pl.lit(q).alias("quantity")).select("method", "segment", "quantity", sketch.KEY,
                                                                 sketch.COUNT)
              for q in ("horizontal", "height") for v in _seg_values(sums, q, breakdown)]
    return Partials(accuracy=seg("accuracy"), values=values,
                     identity={k.split(":", 1)[1]: seg(k) for k in sums if k.startswith("identity:")},
                     hours=seg("hours"), events=seg("events"), intervals=seg("intervals"))


def _seg_values(sums: dict[str, pl.DataFrame], quantity: str, breakdown: Sequence[str]) -> list[pl.DataFrame]:
    """The sketch counts of one quantity by (method, segment)."""
    f = sums.get("values")
    if f is None:
        return []
    f = f.filter(pl.col("quantity") == quantity)
    return [by_segment(f, breakdown, pl.col(sketch.COUNT).sum(), by=[sketch.KEY])]


def picture_step(state: PictureStepState, matched: pl.DataFrame | Sequence[pl.DataFrame], expected: pl.DataFrame,
                 radar_xy: NDArray[np.float64] | None, cfg: MetricsConfig = MetricsConfig()) -> PictureStepState:
    """Every picture's surveillance sums stepped by one window: ``matched`` (the window's
    matched rows of every picture, ``method`` naming it, id column ``track_id``; at least the
    columns :func:`~tertiary.evaluation.picture_metrics.picture_metrics` reads; a frame per
    picture schema: a height is ``alt_m`` where a picture has it, else ``z_m``) and
    ``expected`` (the reference at each picture's epochs, with ``method``). Windows come in
    time order, each with whole epochs. ``radar_xy``: the radar sites in the system frame
    (the range rings; None: no range label)."""
    return _step(state, [matched] if isinstance(matched, pl.DataFrame) else matched, expected, radar_xy, cfg,
                 final=False)


def _step(state: PictureStepState, matched: Sequence[pl.DataFrame], expected: pl.DataFrame,
          radar_xy: NDArray[np.float64] | None, cfg: MetricsConfig, final: bool) -> PictureStepState:
    """:func:`picture_step`; ``final``: the end of the run, every held aircraft labelled."""
    given = [_key_cast(f) for f in matched if f.height]
    expected = _key_cast(expected)
    tracks = _tracks(state, _cat(*(track_inputs(f) for f in given))) if given else state.tracks
    m_frames = [f for f in (f.filter(pl.col("truth_id").is_not_null()) for f in given) if f.height]
    keys = _cat(*(f.select(*_AT, "track_id") for f in m_frames))
    counts = _counts(state, keys) if keys is not None else state.counts
    ref_cols = [c for c in expected.columns if c in _AT or c.startswith("true_")]
    ref_new = expected.select(ref_cols)
    can_merge = {"true_x_m", "true_y_m"} <= set(ref_cols)
    hits = None
    if can_merge and m_frames:
        points = _cat(*(f.select(*_AT, "track_id", "x_m", "y_m", height_exprs(f)[0].alias("__th")) for f in m_frames))
        hits = _hits(points, ref_new, cfg)
    elif can_merge:
        hits = _hits(None, ref_new, cfg)
    ref = _cat(state.pending_ref, ref_new)
    labels, context, pending_ref = _labels(state, ref, radar_xy, cfg, final)
    split, pending_split = _split_step(state, _seconds(given, keys), labels, pending_ref)
    if pending_ref.height or state.pending_rows or _nonempty(state.pending_hits):
        # the rows of an aircraft still waiting for its labels wait with it; each frame keeps
        # its picture's columns (a height is ``alt_m`` where a picture has it, else ``z_m``)
        waiting = pending_ref.select(_KEY).unique()
        frames = [*state.pending_rows, *m_frames]
        pending_rows = tuple(f for f in (f.join(waiting, on=_KEY, how="semi") for f in frames) if f.height)
        ready = [f for f in (f.join(waiting, on=_KEY, how="anti") for f in frames) if f.height]
        all_hits = _cat(state.pending_hits, hits)
        pending_hits = all_hits.join(waiting, on=_KEY, how="semi") if all_hits is not None else None
        hits = all_hits.join(waiting, on=_KEY, how="anti") if all_hits is not None else None
    else:
        pending_rows, ready, pending_hits = (), m_frames, None
    hits = hits.join(labels, on=_AT, how="left") if hits is not None else None
    rows = _cat(*(f.select(*_AT, "track_id") for f in ready))
    if rows is None:                    # no row of the window represents an aircraft
        rows = ref_new.select(*_AT).clear().with_columns(pl.lit(None, pl.UInt64).alias("track_id"))
    err = [error_rows(f, labels, cfg, on=_AT) for f in ready]
    hours, exposure = _exposure(state, labels, cfg) if labels.height else (None, state.exposure)
    rep, changes, ambiguous, last_rep = (_events(state, rows, labels, cfg) if rows.height
                                         else (None, None, None, state.last_rep))
    closed, bins, origin = (_intervals(state, labels, rep if rep is not None else rows.select(_AT).clear(), cfg)
                            if labels.height or rep is not None else (None, state.bins, state.origin))
    merged, amb_hits = state.merged, state.ambiguous_hits
    if _nonempty(hits):
        sure = hits.filter(~pl.col("__amb")).select("method", "run", "track_id", *LABELS).unique()
        merged = _cat(merged, sure).unique() if sure.height else merged
        amb_hits = _cat(amb_hits, hits.filter(pl.col("__amb")).select("method", "run", "epoch", "track_id", "__other",
                                                                      *LABELS))
    return PictureStepState(
        tracks=tracks, counts=counts, context=context, pending_ref=pending_ref, pending_rows=pending_rows,
        pending_hits=pending_hits, exposure=exposure, origin=origin, bins=bins, last_rep=last_rep,
        changes=_cat(state.changes, changes), ambiguous=_cat(state.ambiguous, ambiguous),
        ambiguous_hits=amb_hits, merged=merged, split=split, pending_split=pending_split,
        merge=state.merge or can_merge,
        sums=_counted(state.sums, err, hours, rep, closed, cfg))


def _split_step(state: PictureStepState, seconds: pl.DataFrame | None, labels: pl.DataFrame,
                pending_ref: pl.DataFrame) -> tuple[pl.DataFrame | None, pl.DataFrame | None]:
    """(distinct split tracks by label, the second-track rows still waiting for their aircraft's
    labels) with the window's ``seconds`` added."""
    rows = _cat(state.pending_split, seconds)
    if rows is None or rows.height == 0:
        return state.split, None
    waiting = pending_ref.select(_KEY).unique()
    held = rows.join(waiting, on=_KEY, how="semi") if waiting.height else None
    rows = rows.join(waiting, on=_KEY, how="anti") if waiting.height else rows
    new = rows.join(labels, on=_AT, how="left").select("method", "run", "track_id", *LABELS).unique()
    return _cat(state.split, new).unique(), held if held is not None and held.height else None


def _flushed(state: PictureStepState, radar_xy: NDArray[np.float64] | None, cfg: MetricsConfig) -> PictureStepState:
    """The state with what waited for a later window counted as the end of the run leaves it:
    the held aircraft labelled with what they have, each aircraft's last exposure epoch (0 h)
    and its open intervals."""
    if _nonempty(state.pending_ref):
        state = _step(state, [], state.pending_ref.clear(), radar_xy, cfg, final=True)
    last = state.exposure.with_columns(pl.lit(0.0).alias("__hours")) if state.exposure is not None else None
    opened = (state.bins.filter(pl.col("epoch").is_not_null()) if state.bins is not None else None)
    return replace(state, exposure=None, bins=None,
                   sums=_counted(state.sums, (), last, None, opened, cfg))


def _resolved(state: PictureStepState) -> pl.DataFrame:
    """The representative of every ambiguous epoch: the track matched to the aircraft most often
    over the run (ties: the lowest id), as :func:`~tertiary.evaluation.picture_metrics.representatives`."""
    return (state.ambiguous.select(*_AT, "track_id").unique().join(state.counts, on=[*_KEY, "track_id"])
            .sort([*_AT, "__n", "track_id"], descending=[False] * 4 + [True, False])
            .unique(_AT, keep="first", maintain_order=True).select(*_AT, pl.col("track_id").alias("__rep")))


def _changes(changes: pl.DataFrame, reps: pl.DataFrame | None) -> pl.DataFrame:
    """The representative changes that touch an ambiguous epoch, decided with its representative."""
    if reps is not None:
        changes = (changes.join(reps, on=_AT, how="left")
                   .with_columns(pl.coalesce("track_id", "__rep").alias("track_id")).drop("__rep")
                   .join(reps.rename({"epoch": "__prev_epoch", "__rep": "__prev_rep"}), on=[*_KEY, "__prev_epoch"],
                         how="left")
                   .with_columns(pl.coalesce("__prev", "__prev_rep").alias("__prev")))
    return changes.with_columns((pl.col("track_id") != pl.col("__prev")).fill_null(False).alias("__change"))


def picture_metrics_finish(state: PictureStepState, radar_xy: NDArray[np.float64] | None,
                           breakdown: Sequence[str], cfg: MetricsConfig = MetricsConfig()) -> pl.DataFrame:
    """Every picture's surveillance metrics from the carried state, in the ``metrics`` table
    schema: the rows :func:`~tertiary.evaluation.picture_metrics.picture_metrics` gives for
    the run's matched rows and reference."""
    if state.tracks is None:
        return pl.DataFrame()
    state = _flushed(state, radar_xy, cfg)
    out = _segment_partials(state.sums, breakdown)
    real = state.tracks.filter(pl.col("__real"))
    base = real.select("method", "run").unique()
    parts = [picture_rows(state.tracks)]
    if out.accuracy:
        parts.append(accuracy_combined(out, breakdown, pl.String))
    parts += [identity_combined(name, sums) for name, sums in out.identity.items()]
    if base.height:
        reps = _resolved(state) if _nonempty(state.ambiguous) else None
        if _nonempty(state.changes):
            out.events.append(by_segment(_changes(state.changes, reps), breakdown,
                                         pl.col("__change").sum().alias("__changes"),
                                         pl.lit(0, pl.UInt32).alias("track_breaks"), pl.lit(0.0).alias("__gaps"),
                                         by=["run"]))
        split = [pl.DataFrame(schema={"method": pl.String, "run": pl.UInt32, "track_id": pl.UInt64,
                                      **{c: pl.Categorical for c in LABELS}})]
        if state.split is not None:
            split.append(state.split)
        if reps is not None:
            split.append(state.ambiguous.join(reps, on=_AT).filter(pl.col("track_id") != pl.col("__rep"))
                         .select("method", "run", "track_id", *LABELS).unique())
        # continuity of every picture with a matched row, as the whole run gives it
        methods = base.select("method").unique()

        def mine(frames: list[pl.DataFrame]) -> list[pl.DataFrame]:
            return [f.join(methods, on="method", how="semi") for f in frames]
        out = replace(out, hours=mine(out.hours), events=mine(out.events), intervals=mine(out.intervals),
                      split=[pl.concat(split, how="vertical_relaxed")])
        parts += continuity_combined(out, base, breakdown)
        if state.merge:
            hits = [state.merged] if state.merged is not None else []
            if _nonempty(state.ambiguous_hits) and reps is not None:
                amb = state.ambiguous_hits.join(reps.rename({"truth_id": "__other"}), on=["method", "run", "__other",
                                                                                        "epoch"])
                hits.append(amb.filter(pl.col("track_id") == pl.col("__rep"))
                            .select("method", "run", "track_id", *LABELS))
            events = (pl.concat(hits, how="vertical_relaxed") if hits else
                      pl.DataFrame(schema={"method": pl.String, "run": pl.UInt32, "track_id": pl.UInt64,
                                           **{c: pl.Categorical for c in LABELS}}))
            parts.append(count_tracks(events.join(methods, on="method", how="semi"), base, breakdown,
                                         "merged_tracks"))
    return finish_metrics(parts)
