"""The consistency statistics' lag sums made as the windows pass.

τ of a statistic (:func:`~tertiary.evaluation.consistency.integrated_autocorrelation`) needs
every lag inside each series — the scored rows of one track of one picture — and the per-lag
sums of whole series add up (:class:`~tertiary.evaluation.consistency.Lags`). A series no
window has scored for :data:`SERIES_DONE_S` is taken as whole: the windows sum it then, its
rows read back from the stored ``scored`` parts, a batch of series at a time
(:class:`LagState`). Should a retired series be scored again (a track unmatched for longer, then
matched again), the carried sums would miss its lags across the gap: the state says so
(``complete`` False) and the end of the run sums every series as before. The end sums the
series left and adds the carried sums (:func:`~tertiary.evaluation.accuracy_streamed.statistic_lags`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import polars as pl

from tertiary.core.stage import T_MAX_US, Window
from tertiary.core.units import US
from tertiary.evaluation.accuracy_buckets import SeedSums, statistic_rows
from tertiary.evaluation.consistency import CONSISTENCY_ALL

__all__ = ["LagState", "SERIES_DONE_S", "SERIES_BATCH", "SERIES_KEYS", "lags_step", "merge_runs"]

#: a series not scored for this long is taken as whole (s)
SERIES_DONE_S = 300.0
#: series summed at once (or every one due in the last window, or once one has waited an hour):
#: each batch reads back the stored parts of the windows its series span
SERIES_BATCH = 2_000
_WAIT_S = 3600.0
#: what names a series
SERIES_KEYS = ["method", "run", "track_id"]

StoredFiles = Callable[[], list[Path]]


def _no_series() -> pl.DataFrame:
    return pl.DataFrame(schema={"method": pl.String, "run": pl.UInt32, "track_id": pl.UInt64,
                                "first_us": pl.Int64, "last_us": pl.Int64})


@dataclass(frozen=True)
class LagState:
    """The lag sums of the series the windows retired (``sums.lags``), the series scored and
    not retired with their first and last epochs (``open``), the keys retired (``retired``),
    each window's index and epoch range, and ``complete`` (False: the end sums every series)."""

    sums: SeedSums = field(default_factory=SeedSums)
    open: pl.DataFrame = field(default_factory=_no_series)
    retired: pl.DataFrame = field(default_factory=lambda: _no_series().select(SERIES_KEYS))
    windows: tuple[tuple[int, int, int], ...] = ()
    complete: bool = True


def merge_runs(states: Sequence[LagState]) -> LagState:
    """The lag sums of runs stepped apart (each state holds runs of its own; a series is one
    run's track): the retired series' sums add up, the open and retired series are each one
    run's. Not complete if one is not (the end then sums every series)."""
    states = list(states)
    if not all(s.complete for s in states):
        return LagState(complete=False)
    sums = SeedSums()
    for s in states:
        sums.merge(s.sums)
    return LagState(sums, pl.concat([s.open for s in states]), pl.concat([s.retired for s in states]),
                    tuple(w for s in states for w in s.windows))


def _keys(frame: pl.DataFrame) -> pl.DataFrame:
    return frame.select(pl.col("method").cast(pl.String), pl.col("run").cast(pl.UInt32),
                        pl.col("track_id").cast(pl.UInt64))


def lags_step(state: LagState, scored: pl.DataFrame | None, window: Window, stored: StoredFiles) -> LagState:
    """One window: its ``scored`` rows (None: the window scored none, so the end sums every
    series) extend the open series; the series not scored since :data:`SERIES_DONE_S` before the
    window's end are summed once there are :data:`SERIES_BATCH` of them, one has waited an hour,
    or the window is the last (open-ended)."""
    if not state.complete:
        return state
    if scored is None:
        return LagState(complete=False)
    windows = state.windows
    if scored.height:
        us = scored["epoch"].dt.epoch("us")
        windows = (*windows, (window.index, int(us.min()), int(us.max())))
        seen = (_keys(scored).with_columns(us.alias("__t")).group_by(SERIES_KEYS)
                .agg(pl.col("__t").min().alias("first_us"), pl.col("__t").max().alias("last_us")))
        if seen.join(state.retired, on=SERIES_KEYS, how="semi").height:
            return LagState(complete=False)           # a series retired too early: not whole
        both = pl.concat([state.open, seen.select(state.open.columns)])
        state = replace(state, open=both.group_by(SERIES_KEYS).agg(pl.col("first_us").min(), pl.col("last_us").max()),
                        windows=windows)
    last = window.t1_us >= T_MAX_US
    due = state.open.filter(pl.col("last_us") < window.t1_us - int(SERIES_DONE_S * US)) if not last else state.open
    waited = due.filter(pl.col("last_us") < window.t1_us - int((SERIES_DONE_S + _WAIT_S) * US))
    if not due.height or (due.height < SERIES_BATCH and not waited.height and not last):
        return state
    return _summed(state, due, scored, stored)


def _summed(state: LagState, due: pl.DataFrame, current: pl.DataFrame, stored: StoredFiles) -> LagState:
    """``state`` with the ``due`` series summed: their rows read from the stored parts of the
    windows they span and from ``current`` (the window not stored yet)."""
    lo, hi = int(due["first_us"].min()), int(due["last_us"].max())
    wanted = {k for k, a, b in state.windows if b >= lo and a <= hi}
    files = [f for f in stored() if int(f.stem.split("=")[1]) in wanted]
    keys = due.select(SERIES_KEYS)
    parts = [pl.scan_parquet(f).join(keys.lazy(), on=SERIES_KEYS, how="semi").collect() for f in files]
    if current.height:
        parts.append(current.join(keys, on=SERIES_KEYS, how="semi"))
    rows = pl.concat([p for p in parts if p.height], how="vertical_relaxed") if any(p.height for p in parts) else None
    sums = SeedSums(lags=dict(state.sums.lags))
    if rows is not None:
        for prefix, (col, _dof) in CONSISTENCY_ALL.items():
            if col in rows.columns:
                r = statistic_rows(rows, col)
                if r.height:
                    sums.add_lags(r, prefix, col)
    return replace(state, sums=sums, open=state.open.join(keys, on=SERIES_KEYS, how="anti"),
                   retired=pl.concat([state.retired, keys]))
