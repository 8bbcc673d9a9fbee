"""The posterior Cramér–Rao bound as the windows pass (:mod:`tertiary.evaluation.bound`).

An aircraft's bound is one recursion (T34) over its rows in time order: its illuminations, its
plots from the Cartesian sensors and the epochs it is scored at. The windows carry that
recursion for every aircraft whose truth has begun: its P after its last row, that row's time and
whether it had a measurement (:data:`~tertiary.evaluation.bound.CARRIED`), and how far its rows
are done. Once the windows can take every aircraft :data:`ADVANCE_S` further, they run each
recursion on to the *cut*, :data:`LAG_S` before the window's end (every plot, scored epoch and
first Mode S report of an earlier time has come by then), and add the bound's per-epoch sums
(:func:`~tertiary.evaluation.bound_pooling.bound_sums`). An aircraft whose truth ended before its
cut is done and dropped. A run's last window is open: the end of the run
(:func:`bound_finish`) takes every recursion to the end of its truth, a few minutes of rows.

What the recursion reads of the truth is its samples near its rows: the acceleration fitted at a
sample spans :data:`~tertiary.evaluation.bound_truth.ACCEL_HALF_WINDOW_S` of samples on either
side. The windows read the reference once, a stretch at a time up to :data:`LOOKAHEAD_S` past the
cut, and carry per aircraft its samples from a few before its last row on (``tail``). An
aircraft whose samples past the cut are too few for that (a gap in ADS-B truth) is cut at the
last sample that has them, and goes on next time.

So every row is computed once, from the same truth samples, scan origins, plots and first Mode
S reports as the whole-run stage (:func:`~tertiary.evaluation.bound.bound_stage`), and the sums
equal that stage's whatever the windows, up to the order of the sums. What the bound needs of
the whole recording is known before the first window (:func:`bound_setup`): the truth's first
time and each aircraft's span and sample spacing, and each radar's scan origin.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl

from tertiary.contract import TIME
from tertiary.core import geo
from tertiary.core.stage import T_MAX_US, Window
from tertiary.core.units import US
from tertiary.evaluation import bound as _bound
from tertiary.evaluation.bound_measurements import MODE_S_FIRST, mode_s_first
from tertiary.evaluation.bound_pooling import bound_sums, epoch_pools, merged_pools
from tertiary.evaluation.bound_truth import COLUMNS, Truth, reference_gaps, truth_gaps
from tertiary.evaluation.evaluate import reference_files
from tertiary.evaluation.reference_spans import files_between, read_spans
from tertiary.sensors import mlat

__all__ = ["ADVANCE_S", "BoundSetup", "BoundState", "LAG_S", "LOOKAHEAD_S", "PartFiles", "bound_finish",
           "bound_setup", "bound_step"]

#: the cut lags a window's end by this much (s): no plot, scored epoch or first Mode S report of
#: an earlier time comes later (clock offsets and scan periods are seconds)
LAG_S = 120.0
#: the recursions are taken on once the cut has moved this far (s): each step reads a stretch of
#: the truth and of the stored samples once and makes each aircraft's interpolant once, a dozen
#: times an hour; the end is left the last few minutes
ADVANCE_S = 300.0
#: truth read past the cut (s): the acceleration and positions just before it need samples after it
LOOKAHEAD_S = 60.0
#: a step with this many aircraft or more runs them in two halves at once (:func:`_advance`)
PARALLEL_AIRCRAFT = 64
#: samples carried before an aircraft's last row beyond its acceleration's half-width
MARGIN_SAMPLES = 3
#: what the Cartesian sensors' plots carry into their events (:func:`~tertiary.evaluation.bound._mlat_events`)
PLOT_COLUMNS = ("radar_id", "truth_id", "time", "plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m", "adsb_nacp")
#: the columns of a scored sample (:func:`~tertiary.evaluation.accuracy.scored_samples`)
SAMPLES = {"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64, "seg_class": pl.String}
#: an aircraft the windows carry: how far its rows are done (``done_us``, exclusive) and its
#: recursion (:data:`~tertiary.evaluation.bound.CARRIED`; null before its first row)
AIRCRAFT = {"truth_id": pl.Int64, "done_us": pl.Int64, **{k: v for k, v in _bound.CARRIED.items() if k != "truth_id"}}


@dataclass(frozen=True)
class BoundSetup:
    """What the bound of a run fixes before its first window: the model and elevation limits
    (:func:`~tertiary.evaluation.bound.bound_setup`), the radars and system frame, the truth's
    first time ``t0_us``, each aircraft's truth span ``spans`` (truth_id, first_us, last_us,
    sorted) and sample spacing ``gaps`` (:func:`~tertiary.evaluation.bound_truth.truth_gaps`), the
    radars' scan origins and the reference files the truth is read from."""

    cfg: _bound.BoundConfig
    max_el: dict[str, float]
    radars: pl.DataFrame
    origin: geo.LocalFrame
    t0_us: int
    spans: pl.DataFrame
    gaps: pl.DataFrame
    origins: dict[int, float]
    files: tuple[str, ...]

    @property
    def cartesian(self) -> list[int]:
        """The radar ids of the sensors whose plots are the bound's events (MLAT, ADS-B)."""
        if "kind" not in self.radars.columns:
            return []
        return self.radars.filter(pl.col("kind").is_in(mlat.CARTESIAN_KINDS))["radar_id"].to_list()

    @property
    def lag_us(self) -> int:
        """The cut's lag (µs): :data:`LAG_S`, longer when a first Mode S report counts from
        further back (:func:`~tertiary.evaluation.bound.mode_s_lead_s`)."""
        return int(max(LAG_S, _bound.mode_s_lead_s(self.radars) + 1.0) * US)


def _empty(schema: dict) -> pl.DataFrame:
    return pl.DataFrame(schema=schema)


@dataclass(frozen=True)
class BoundState:
    """The aircraft carried (:data:`AIRCRAFT`, sorted), the truth samples they need (``tail``)
    and how far the reference is read (``read_us``, exclusive); the cut the recursions were last
    taken to (``cut_us``); the windows whose stored samples may hold rows to come (``windows``:
    index, first and last epoch µs); the Cartesian sensors' ``plots`` still to come; each
    aircraft's first Mode S report (``mode_s``); the sums of the epochs still open to rows (one
    row per (method, segment, epoch, run)), the pools of those no row can come to any more
    (``pools``: :func:`~tertiary.evaluation.bound_pooling.epoch_pools`; a state that grew with
    the run would be pickled again at every window) and how many aircraft are done. ``complete``: every window gave its scored
    samples (else the end of the run bounds the whole recording instead)."""

    aircraft: pl.DataFrame = field(default_factory=lambda: _empty(AIRCRAFT))
    tail: pl.DataFrame = field(default_factory=pl.DataFrame)
    read_us: int | None = None
    cut_us: int | None = None
    windows: tuple[tuple[int, int, int], ...] = ()
    plots: pl.DataFrame = field(default_factory=pl.DataFrame)
    mode_s: pl.DataFrame = field(default_factory=lambda: _empty(MODE_S_FIRST))
    sums: pl.DataFrame = field(default_factory=lambda: bound_sums(_empty(SAMPLES), pl.DataFrame()))
    pools: pl.DataFrame | None = None
    bounded: int = 0
    complete: bool = True


#: the stored scored samples of the windows done, by window index (the run's parts)
PartFiles = Callable[[], list[Path]]


def bound_setup(ds, radars: pl.DataFrame, origin: geo.LocalFrame, reference: Path | str,
                reports: pl.LazyFrame) -> BoundSetup | None:
    """The run's :class:`BoundSetup` from its validated ``radars``, the reference file(s) of its
    truth and its input ``reports`` (a scan: each radar's scan origin); None when the bound
    cannot be made (the end of the run then says why)."""
    files = tuple(str(f) for f in reference_files(Path(reference)))
    truth = pl.scan_parquet(list(files))
    made = _bound.bound_setup(ds, truth.collect_schema().names(), radars, [])
    if made is None:
        return None
    us = pl.col("time").cast(TIME).dt.epoch("us")
    spans = (truth.group_by(pl.col("truth_id").cast(pl.Int64))
             .agg(us.min().alias("first_us"), us.max().alias("last_us")).sort("truth_id").collect())
    if not spans.height:
        return None
    t0 = int(spans["first_us"].min())
    # the reference's own neighbour times give the spacings without sorting its samples
    gaps = reference_gaps(truth, t0) if "__prev" in truth.collect_schema().names() else truth_gaps(truth, t0)
    return BoundSetup(made[0], made[1], radars, origin, t0, spans, gaps,
                      _bound.scan_origins(radars, reports, t0), files)


def bound_step(setup: BoundSetup, state: BoundState, samples: pl.DataFrame | None, reports: pl.DataFrame,
               window: Window, stored: PartFiles) -> BoundState:
    """One window: what its scored ``samples`` (None: the window scored none, so the windows
    cannot bound the run) and validated ``reports`` bring is carried, and every recursion is
    taken on to the cut once it has moved :data:`ADVANCE_S`, reading the stored samples of the
    windows before (``stored``) and this one's. An open-ended window (a run's last) takes none
    on: :func:`bound_finish` does."""
    if not state.complete:
        return state
    if samples is None or not hasattr(state, "aircraft"):      # none scored, or a checkpoint of another layout
        return BoundState(complete=False)
    samples = samples.select([pl.col(c).cast(t) for c, t in SAMPLES.items()])
    state = _carried(setup, state, samples, reports, window)
    if window.t1_us >= T_MAX_US:
        return state
    cut = window.t1_us - setup.lag_us
    if cut - (setup.t0_us if state.cut_us is None else state.cut_us) < int(ADVANCE_S * US):
        return state
    return _advance(setup, state, cut, stored, samples, window.index)


def bound_finish(setup: BoundSetup, state: BoundState, stored: PartFiles) -> pl.DataFrame | None:
    """The epoch pools of every aircraft's samples (:func:`~tertiary.evaluation.bound_pooling.epoch_pools`;
    :func:`~tertiary.evaluation.bound_pooling.pool_rows` makes the metrics of them): every
    recursion taken to its end, the rows left read from ``stored`` (every window's samples)."""
    done = _advance(setup, state, T_MAX_US, stored, _empty(SAMPLES))
    return merged_pools(done.pools, epoch_pools(done.sums) if done.sums.height else None)


def _carried(setup: BoundSetup, state: BoundState, samples: pl.DataFrame, reports: pl.DataFrame,
             window: Window) -> BoundState:
    """``state`` with a window's stored samples' span, first Mode S reports and Cartesian plots."""
    windows = state.windows
    if samples.height:
        us = samples["epoch"].dt.epoch("us")
        windows = (*windows, (window.index, int(us.min()), int(us.max())))
    mode_s = state.mode_s
    if {"truth_id", "mode_s"} <= set(reports.columns):
        mode_s = (pl.concat([mode_s, mode_s_first(reports)]).group_by("truth_id").agg(pl.col("first_us").min())
                  .sort("truth_id"))
    plots = state.plots
    if setup.cartesian and "truth_id" in reports.columns:
        mine = reports.filter(pl.col("radar_id").is_in(setup.cartesian) & pl.col("truth_id").is_not_null())
        mine = mine.select(c for c in PLOT_COLUMNS if c in reports.columns)
        plots = mine if plots.width == 0 else pl.concat([plots, mine], how="diagonal_relaxed")
    return replace(state, windows=windows, plots=plots, mode_s=mode_s)


def _advance(setup: BoundSetup, state: BoundState, cut: int, stored: PartFiles, current: pl.DataFrame,
             now: int | None = None) -> BoundState:
    """``state`` with every aircraft whose truth began before ``cut`` taken on to its cut: the
    truth read up to :data:`LOOKAHEAD_S` past ``cut`` (all of it at the end), each aircraft's
    events and scored epochs from where it was done (the samples of the ``current`` window,
    index ``now``, not stored yet) run from its carried P, the sums added, the aircraft done dropped."""
    end = cut >= T_MAX_US
    read_us = setup.t0_us if state.read_us is None else state.read_us
    hi = None if end else cut + int(LOOKAHEAD_S * US)
    tail = _append(state.tail, _read_truth(setup, read_us, hi))
    aircraft = _joined(setup, state.aircraft, state.cut_us, cut)
    cuts = _cuts(setup, aircraft, tail, cut, hi)
    go = cuts.filter(pl.col("cut_us") > pl.col("done_us"))
    sums = state.sums
    if go.height:
        lo = int(go["done_us"].min())
        samples = _within(pl.concat([_stored_samples(state, lo, cut, stored, now), current]), go, "epoch")
        # two halves of the aircraft at once (each recursion is its own; numpy, polars and the
        # compiled kernel release the GIL): the step takes the core the processing leaves idle
        # while it waits for the evaluation
        half = (go.height + 1) // 2
        parts = [go.slice(0, half), go.slice(half)] if go.height >= PARALLEL_AIRCRAFT else [go]
        with ThreadPoolExecutor(len(parts), thread_name_prefix="bound-step") as pool:
            made = list(pool.map(lambda g: _recursed(setup, state, tail, g, samples), parts))
        sums = _summed(state.sums, pl.concat([m[0] for m in made]))
        aircraft = _updated(aircraft, go, pl.concat([m[1] for m in made]))
    aircraft, done = _retired(setup, aircraft)
    # the epochs before every carried aircraft's done point and the cut have all their rows
    lo = min(cut, int(aircraft["done_us"].min())) if aircraft.height else cut
    closed = pl.col("epoch").dt.epoch("us") < lo
    pools = state.pools
    if sums.height and sums.select(closed.any()).item():
        pools = merged_pools(pools, epoch_pools(sums.filter(closed)))
        sums = sums.filter(~closed)
    return replace(state, aircraft=aircraft, tail=_trimmed(setup, tail, aircraft, done), read_us=hi,
                   cut_us=cut, plots=_kept_plots(state.plots, aircraft, done), sums=sums, pools=pools,
                   bounded=state.bounded + done.height,
                   windows=_kept_windows(state.windows, aircraft, cut))


def _kept_windows(windows: tuple[tuple[int, int, int], ...], aircraft: pl.DataFrame, cut: int
                  ) -> tuple[tuple[int, int, int], ...]:
    """The windows whose stored samples may still be rows: an epoch at or after where the
    aircraft carried are done, or ``cut`` (an aircraft not yet begun has no row before it)."""
    lo = min(cut, int(aircraft["done_us"].min())) if aircraft.height else cut
    return tuple(w for w in windows if w[2] >= lo)


def _recursed(setup: BoundSetup, state: BoundState, tail: pl.DataFrame, go: pl.DataFrame, samples: pl.DataFrame
              ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(the bound's sums, the recursions after) of the aircraft ``go`` over their events and
    scored ``samples`` in [done_us, cut_us), from their carried recursion."""
    ids = go["truth_id"].implode()
    between = ((int(go["done_us"].min()) - setup.t0_us) / US - 1.0, (int(go["cut_us"].max()) - setup.t0_us) / US + 1.0)
    # the truth's interpolant made once, for the illuminations and the recursion
    mine = Truth.of(tail.filter(pl.col("truth_id").cast(pl.Int64).is_in(ids)), setup.t0_us,
                    setup.cfg.accel_half_window_s, setup.gaps)
    events = _bound.illuminations(mine, setup.radars, _plots(state.plots), setup.origin, setup.cfg,
                                  setup.max_el, setup.t0_us, setup.origins, state.mode_s, between)
    events = _within(events, go, "time")
    samples = samples.filter(pl.col("truth_id").is_in(ids))
    carried = go.filter(pl.col("last_us").is_not_null()).select(list(_bound.CARRIED))
    rows, after = _bound.pcrb_carried(samples, events, setup.cfg, mine, setup.t0_us, carried, setup.gaps)
    return bound_sums(samples, rows), after


def _joined(setup: BoundSetup, aircraft: pl.DataFrame, since: int | None, cut: int) -> pl.DataFrame:
    """The aircraft carried and those whose truth begins in [``since``, ``cut``) (done to their
    first truth sample: no row of an aircraft comes before it): every aircraft that began before
    the last cut was joined then."""
    begins = pl.col("first_us") < cut
    if since is not None:
        begins &= pl.col("first_us") >= since
    fresh = setup.spans.filter(begins).select("truth_id", pl.col("first_us").alias("done_us"))
    return pl.concat([aircraft, fresh], how="diagonal_relaxed").select(aircraft.columns).cast(AIRCRAFT).sort("truth_id")


def _half_width(setup: BoundSetup) -> pl.DataFrame:
    """Per aircraft, the samples its acceleration spans on either side (as
    :attr:`~tertiary.evaluation.bound_truth.Truth.accel` counts them) plus :data:`MARGIN_SAMPLES`."""
    w = (setup.cfg.accel_half_window_s / (pl.col("gap_s") / 1.5)).round().fill_nan(0.0).fill_null(0.0)
    return setup.gaps.select("truth_id", (w.cast(pl.Int64) + MARGIN_SAMPLES).alias("w"))


def _cuts(setup: BoundSetup, aircraft: pl.DataFrame, tail: pl.DataFrame, cut: int, hi: int | None) -> pl.DataFrame:
    """``aircraft`` with each one's ``cut_us``: ``cut``, or, while its truth goes on past what is
    read (``hi``), the sample :func:`_half_width` samples before the last one read, if earlier."""
    if hi is None:
        return aircraft.with_columns(pl.lit(cut, pl.Int64).alias("cut_us"))
    us = pl.col("time").cast(TIME).dt.epoch("us")
    last = (tail.select(pl.col("truth_id").cast(pl.Int64), us.alias("us")).unique()
            .join(_half_width(setup), on="truth_id", how="left").sort("truth_id", "us")
            .group_by("truth_id").agg(pl.col("us").get(pl.len() - pl.col("w").first().fill_null(MARGIN_SAMPLES) - 1,
                                                       null_on_oob=True).alias("__last")))
    whole = pl.col("__end") < hi
    reach = pl.min_horizontal("__last", pl.lit(cut, pl.Int64)).fill_null(pl.col("done_us"))
    return (aircraft.join(setup.spans.select("truth_id", pl.col("last_us").alias("__end")), on="truth_id", how="left")
            .join(last, on="truth_id", how="left")
            .with_columns(pl.when(whole).then(pl.lit(cut, pl.Int64)).otherwise(reach).alias("cut_us"))
            .drop("__end", "__last"))


def _within(frame: pl.DataFrame, go: pl.DataFrame, col: str) -> pl.DataFrame:
    """The rows of ``frame`` whose aircraft is in ``go`` and whose ``col`` lies in its
    [done_us, cut_us)."""
    us = pl.col(col).cast(TIME).dt.epoch("us")
    return (frame.with_columns(pl.col("truth_id").cast(pl.Int64))
            .join(go.select("truth_id", pl.col("done_us").alias("__lo"), pl.col("cut_us").alias("__hi")),
                  on="truth_id", how="inner")
            .filter((us >= pl.col("__lo")) & (us < pl.col("__hi"))).drop("__lo", "__hi"))


def _updated(aircraft: pl.DataFrame, go: pl.DataFrame, after: pl.DataFrame) -> pl.DataFrame:
    """``aircraft`` with those of ``go`` done to their cut and their recursion as ``after`` left it."""
    done = go.select("truth_id", "cut_us").join(after, on="truth_id", how="left")
    merged = (aircraft.join(done, on="truth_id", how="left", suffix="__new")
              .with_columns(pl.coalesce("cut_us", "done_us").alias("done_us"),
                            *[pl.when(pl.col("last_us__new").is_not_null()).then(pl.col(f"{c}__new"))
                              .otherwise(pl.col(c)).alias(c) for c in ("last_us", "seen", "p")]))
    return merged.select(list(AIRCRAFT)).cast(AIRCRAFT)


def _retired(setup: BoundSetup, aircraft: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(the aircraft still going on, those done: their rows done past the end of their truth)."""
    end = aircraft.join(setup.spans.select("truth_id", "last_us").rename({"last_us": "__end"}), on="truth_id",
                        how="left")
    over = pl.col("done_us") > pl.col("__end")
    return end.filter(~over).drop("__end"), end.filter(over).select("truth_id")


def _trimmed(setup: BoundSetup, tail: pl.DataFrame, aircraft: pl.DataFrame, done: pl.DataFrame) -> pl.DataFrame:
    """The truth samples still needed: none of the aircraft ``done``; of one carried, from
    :func:`_half_width` samples before its last row (or where its rows are done) on; all of the
    others (they have begun past the cut)."""
    if not tail.height:
        return tail
    us = pl.col("time").cast(TIME).dt.epoch("us")
    refs = aircraft.select("truth_id", pl.coalesce("last_us", "done_us").alias("__ref"))
    t = (tail.with_columns(pl.col("truth_id").cast(pl.Int64))
         .filter(~pl.col("truth_id").is_in(done["truth_id"].implode()))
         .join(refs, on="truth_id", how="left").join(_half_width(setup), on="truth_id", how="left")
         .sort("truth_id", "time"))         # the sample counts below are in time order
    k = pl.int_range(pl.len()).over("truth_id")
    at = ((us <= pl.col("__ref")).sum() - 1).over("truth_id")
    keep = pl.col("__ref").is_null() | (k >= at - pl.col("w").fill_null(MARGIN_SAMPLES))
    return t.filter(keep).drop("__ref", "w")


def _kept_plots(plots: pl.DataFrame, aircraft: pl.DataFrame, done: pl.DataFrame) -> pl.DataFrame:
    """The Cartesian plots that may still be rows: not of an aircraft done, nor :data:`LAG_S`
    before where its rows are done (a plot's event is its time less its sensor's clock offset)."""
    if not plots.height:
        return plots
    us = pl.col("time").cast(TIME).dt.epoch("us")
    mine = plots.with_columns(pl.col("truth_id").cast(pl.Int64)).join(
        aircraft.select("truth_id", pl.col("done_us").alias("__d")), on="truth_id", how="left")
    keep = ~pl.col("truth_id").is_in(done["truth_id"].implode()) & (
        pl.col("__d").is_null() | (us >= pl.col("__d") - int(LAG_S * US)))
    return mine.filter(keep).drop("__d")


def _plots(plots: pl.DataFrame) -> pl.DataFrame:
    """The plots as :func:`~tertiary.evaluation.bound.illuminations` reads them (none: an empty frame)."""
    return plots if plots.width else pl.DataFrame(schema={"radar_id": pl.UInt32, "truth_id": pl.Int64, "time": TIME})


def _summed(sums: pl.DataFrame, more: pl.DataFrame) -> pl.DataFrame:
    """Two sums tables as one (:func:`~tertiary.evaluation.bound_pooling.bound_sums` add up)."""
    keys = ["method", "segment", "epoch", "run"]
    return (pl.concat([sums, more.select(sums.columns).cast(sums.schema)]).group_by(keys).agg(pl.all().sum())
            .sort(keys).select(sums.columns).cast(sums.schema))


def _append(tail: pl.DataFrame, new: pl.DataFrame) -> pl.DataFrame:
    return new if tail.width == 0 else pl.concat([tail, new], how="diagonal_relaxed")


def _stored_samples(state: BoundState, lo: int, hi: int, stored: PartFiles, now: int | None) -> pl.DataFrame:
    """The scored samples with an epoch in [``lo``, ``hi``) of the stored windows that hold any."""
    wanted = {k for k, a, b in state.windows if b >= lo and a < hi and k != now}
    files = [f for f in stored() if _window_index(f) in wanted]
    if not files:
        return _empty(SAMPLES)
    us = pl.col("epoch").cast(TIME).dt.epoch("us")
    cols = [pl.col(c).cast(t) for c, t in SAMPLES.items()]
    return pl.concat([pl.scan_parquet(f).select(cols).filter((us >= lo) & (us < hi)) for f in files]).collect()


def _window_index(path: Path) -> int:
    """A window part's index from its name (``w=<index>.parquet``)."""
    return int(Path(path).stem.split("=")[-1])


def _read_truth(setup: BoundSetup, lo_us: int, hi_us: int | None) -> pl.DataFrame:
    """The bound's truth columns with a time in [``lo_us``, ``hi_us``) (no end: to the end), read
    from the reference (in time order: the other times' row groups are skipped)."""
    def at(v: int) -> datetime:
        return datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=int(v))
    lf = pl.scan_parquet(files_between(setup.files, read_spans(setup.files), lo_us, hi_us))
    keep = pl.col("time") >= at(lo_us)
    if hi_us is not None:
        keep &= pl.col("time") < at(hi_us)
    return lf.filter(keep).select(COLUMNS).collect()
