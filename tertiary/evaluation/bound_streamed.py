"""The posterior Cramér–Rao bound as the windows pass (:mod:`tertiary.evaluation.bound`).

An aircraft's bound is one recursion over its whole truth (its acceleration profile, its
illuminations, the epochs it is scored at), independent of every other aircraft's. So the
windows carry which aircraft were scored, whether a report of each carried a Mode S address and
the plots of the Cartesian sensors (MLAT, ADS-B) on it, and bound an aircraft in the first window
that ends :data:`RETIRE_AFTER_S` after its last truth sample: nothing of it can come later. They
do so a batch of :data:`RETIRE_BATCH` aircraft at a time (fewer after :data:`RETIRE_WAIT_S`),
reading those aircraft's truth from the reference and their scored samples from the windows'
stored parts (the samples are not held: an hour's are millions of rows), and keep the
per-epoch sums the metrics pool (:func:`~tertiary.evaluation.bound_pooling.bound_sums`). A run's
last window is open to the future: it bounds no aircraft, and the end of the run bounds those
still flying (:func:`bound_finish`, which the pipeline runs beside the end's evaluation: the
last window's evaluation would otherwise hold the run on one core) and pools the sums.

Every aircraft is bounded once, by the code of the whole-run stage
(:func:`~tertiary.evaluation.bound.block_sums`) on the same truth, samples, plots and scan
origins, so the rows equal that stage's whatever the windows, up to the order of the sums.
What the bound needs of the whole recording is known before the first window
(:func:`bound_setup`): the truth's first time and each aircraft's last, and each radar's scan
origin (:func:`~tertiary.evaluation.bound.scan_origins` of the input reports).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import TIME
from tertiary.core import geo
from tertiary.core.stage import T_MAX_US, Window
from tertiary.core.units import US
from tertiary.evaluation import bound as _bound
from tertiary.evaluation.bound_pooling import bound_sums
from tertiary.evaluation.evaluate import reference_files
from tertiary.sensors import mlat

__all__ = ["BoundSetup", "BoundState", "PartFiles", "RETIRE_AFTER_S", "RETIRE_BATCH", "RETIRE_WAIT_S", "bound_finish",
           "bound_setup", "bound_step"]

#: an aircraft is bounded once the windows have passed its last truth sample by this much (s):
#: no sample is scored outside its truth, and no report of it comes later than its clock offset
RETIRE_AFTER_S = 120.0
#: aircraft bounded at a time in the windows (one read of the reference and of the stored
#: samples each): a batch is waited for, so that a long run reads them a few times an hour, not
#: once a window ...
RETIRE_BATCH = 256
#: ... but not longer than this (s) after the first aircraft of it could have been bounded: the
#: aircraft of a quiet hour are bounded in the windows too, not at the end
RETIRE_WAIT_S = 600.0
#: what the Cartesian sensors' plots carry into their events (:func:`~tertiary.evaluation.bound._mlat_events`)
PLOT_COLUMNS = ("radar_id", "truth_id", "time", "plot_sigma_x_m", "plot_sigma_y_m", "plot_sigma_xy_m", "adsb_nacp")
#: the columns of a scored sample (:func:`~tertiary.evaluation.accuracy.scored_samples`)
SAMPLES = {"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64, "seg_class": pl.String}


@dataclass(frozen=True)
class BoundSetup:
    """What the bound of a run fixes before its first window: the model and elevation limits
    (:func:`~tertiary.evaluation.bound.bound_setup`), the radars and system frame, the truth's
    first time ``t0_us`` and each aircraft's truth span ``spans`` (truth_id, first_us, last_us,
    sorted), the radars' scan origins and the reference files the truth is read from."""

    cfg: _bound.BoundConfig
    max_el: dict[str, float]
    radars: pl.DataFrame
    origin: geo.LocalFrame
    t0_us: int
    spans: pl.DataFrame
    origins: dict[int, float]
    files: tuple[str, ...]

    @property
    def cartesian(self) -> list[int]:
        """The radar ids of the sensors whose plots are the bound's events (MLAT, ADS-B)."""
        if "kind" not in self.radars.columns:
            return []
        return self.radars.filter(pl.col("kind").is_in(mlat.CARTESIAN_KINDS))["radar_id"].to_list()


def _empty_samples() -> pl.DataFrame:
    return pl.DataFrame(schema=SAMPLES)


@dataclass(frozen=True)
class BoundState:
    """The aircraft scored and not yet bounded (``pending``, sorted ids), the windows whose
    stored samples may hold them (``windows``: index, first and last epoch µs), the Cartesian
    sensors' ``plots`` of them; the aircraft with a Mode S report so far (``mode_s``, sorted
    ids); the sums of those bounded (``sums``, one row per (method, segment, epoch, run)) and how
    many they are. ``complete``: every window gave its scored samples (else the end of the run
    bounds the whole recording instead)."""

    pending: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    windows: tuple[tuple[int, int, int], ...] = ()
    plots: pl.DataFrame = field(default_factory=pl.DataFrame)
    mode_s: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    sums: pl.DataFrame = field(default_factory=lambda: bound_sums(_empty_samples(), pl.DataFrame()))
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
    return BoundSetup(made[0], made[1], radars, origin, t0, spans, _bound.scan_origins(radars, reports, t0), files)


def bound_step(setup: BoundSetup, state: BoundState, samples: pl.DataFrame | None, reports: pl.DataFrame,
               window: Window, stored: PartFiles) -> BoundState:
    """One window: which aircraft its scored ``samples`` hold (None: the window scored none, so
    the windows cannot bound the run) and what its validated ``reports`` tell carried; the
    aircraft whose truth ended :data:`RETIRE_AFTER_S` before the window's end bounded once there
    are :data:`RETIRE_BATCH` of them or one has waited :data:`RETIRE_WAIT_S`, their samples read
    from ``stored`` (the windows before this one) and ``samples``. An open-ended window (a run's
    last) bounds none: they are left to :func:`bound_finish`."""
    if not state.complete:
        return state
    if samples is None:
        return BoundState(complete=False)
    samples = samples.select([pl.col(c).cast(t) for c, t in SAMPLES.items()])
    state = _carried(setup, state, samples, reports, window)
    if window.t1_us >= T_MAX_US:
        return state
    due = _due(setup, state.pending, window.t1_us - int(RETIRE_AFTER_S * US))
    waited = _due(setup, due, window.t1_us - int((RETIRE_AFTER_S + RETIRE_WAIT_S) * US))
    return (_bounded(setup, state, due, stored, samples, window.index) if len(due) >= RETIRE_BATCH or len(waited)
            else state)


def bound_finish(setup: BoundSetup, state: BoundState, stored: PartFiles) -> pl.DataFrame:
    """The per-epoch sums of every aircraft (:func:`~tertiary.evaluation.bound_pooling.bound_rows`
    pools them): those bounded in the windows and any aircraft left at the end, their
    samples read from ``stored`` (every window's)."""
    return _bounded(setup, state, state.pending, stored, _empty_samples()).sums


def _carried(setup: BoundSetup, state: BoundState, samples: pl.DataFrame, reports: pl.DataFrame,
             window: Window) -> BoundState:
    """``state`` with a window's scored aircraft, Mode S aircraft and Cartesian plots added."""
    pending, windows = state.pending, state.windows
    if samples.height:
        pending = np.union1d(pending, samples["truth_id"].unique().to_numpy())
        us = samples["epoch"].dt.epoch("us")
        windows = (*windows, (window.index, int(us.min()), int(us.max())))
    mode_s = state.mode_s
    if {"truth_id", "mode_s"} <= set(reports.columns):
        ids = reports.filter(pl.col("mode_s").is_not_null())["truth_id"].drop_nulls().cast(pl.Int64).to_numpy()
        mode_s = np.union1d(mode_s, ids)
    plots = state.plots
    if setup.cartesian and "truth_id" in reports.columns:
        mine = reports.filter(pl.col("radar_id").is_in(setup.cartesian) & pl.col("truth_id").is_not_null())
        mine = mine.select(c for c in PLOT_COLUMNS if c in reports.columns)
        plots = mine if plots.width == 0 else pl.concat([plots, mine], how="diagonal_relaxed")
    return replace(state, pending=pending, windows=windows, plots=plots, mode_s=mode_s)


def _due(setup: BoundSetup, pending: NDArray[np.int64], before_us: int) -> NDArray[np.int64]:
    """The sorted ids of the ``pending`` aircraft whose truth ended before ``before_us``."""
    if not len(pending):
        return pending
    span = setup.spans.filter(pl.col("truth_id").is_in(pending.tolist()))
    return np.sort(span.filter(pl.col("last_us") < before_us)["truth_id"].to_numpy())


def _bounded(setup: BoundSetup, state: BoundState, ids: NDArray[np.int64], stored: PartFiles,
             current: pl.DataFrame, now: int | None = None) -> BoundState:
    """``state`` with the aircraft ``ids`` bounded: their truth and stored samples (with those of
    the ``current`` window, index ``now``, not stored yet) read at once, their sums made a block of
    :data:`~tertiary.evaluation.bound.BOUND_AIRCRAFT` at a time and added to the sums."""
    if not len(ids):
        return state
    mine = pl.col("truth_id").is_in(ids.tolist())
    truth = _truth_of(setup, ids)
    samples = pl.concat([_stored_samples(setup, state, ids, stored, now), current.filter(mine)])
    plots = state.plots if state.plots.width else pl.DataFrame(schema={"radar_id": pl.UInt32, "truth_id": pl.Int64,
                                                                        "time": TIME})
    sums = [state.sums]
    for lo in range(0, len(ids), _bound.BOUND_AIRCRAFT):
        block = pl.col("truth_id").cast(pl.Int64).is_in(ids[lo:lo + _bound.BOUND_AIRCRAFT].tolist())
        sums.append(_bound.block_sums(truth.filter(block), samples.filter(block), setup.radars, plots.filter(block),
                                      setup.origin, setup.cfg, setup.max_el, setup.t0_us, setup.origins,
                                      mode_s_ids=state.mode_s))
    keys = ["method", "segment", "epoch", "run"]
    merged = pl.concat(sums).group_by(keys).agg(pl.all().sum()).sort(keys)
    return replace(state, pending=np.setdiff1d(state.pending, ids), sums=merged.select(state.sums.columns).cast(
        state.sums.schema), plots=state.plots.filter(~mine) if state.plots.width else state.plots,
        bounded=state.bounded + len(ids))


def _stored_samples(setup: BoundSetup, state: BoundState, ids: NDArray[np.int64], stored: PartFiles,
                    now: int | None) -> pl.DataFrame:
    """The scored samples of the aircraft ``ids`` in the stored windows that span their truth."""
    span = setup.spans.filter(pl.col("truth_id").is_in(ids.tolist()))
    lo, hi = int(span["first_us"].min()), int(span["last_us"].max())
    wanted = {k for k, a, b in state.windows if b >= lo and a <= hi and k != now}
    files = [f for f in stored() if _window_index(f) in wanted]
    if not files:
        return _empty_samples()
    cols = [pl.col(c).cast(t) for c, t in SAMPLES.items()]
    return pl.concat([pl.scan_parquet(f).filter(pl.col("truth_id").is_in(ids.tolist())).select(cols) for f in files]
                     ).collect()


def _window_index(path: Path) -> int:
    """A window part's index from its name (``w=<index>.parquet``)."""
    return int(Path(path).stem.split("=")[-1])


def _truth_of(setup: BoundSetup, ids: NDArray[np.int64]) -> pl.DataFrame:
    """The bound's truth columns of the aircraft ``ids``, read from the reference within their
    spans (the reference is in time order: the other times' row groups are skipped)."""
    span = setup.spans.filter(pl.col("truth_id").is_in(ids.tolist()))
    lo, hi = (datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=int(v))
              for v in (span["first_us"].min(), span["last_us"].max()))
    lf = pl.scan_parquet(list(setup.files))
    cols = [c for c in ("run", "truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
            if c in lf.collect_schema().names()]
    return (lf.filter((pl.col("time") >= lo) & (pl.col("time") <= hi)
                      & pl.col("truth_id").cast(pl.Int64).is_in(ids.tolist()))
            .select(cols).collect())
