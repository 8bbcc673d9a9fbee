"""The evaluation half of a window: the STCA curves' predictions, the pictures matched to the
truth, the truth's separation intervals, the truth picture's prediction, the bound and τ's lag
sums. It reads what the window's processing made (:class:`Handoff`) and carries state of its own
only, so a run on disk evaluates window k on a thread of its own while window k + 1 is processed
(:class:`Overlap`)."""

from __future__ import annotations

import dataclasses
import pickle
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

import polars as pl

from safety import alerts as safety_alerts
from tertiary.evaluation.bound_streamed import BoundState, bound_step
from tertiary.evaluation.lags_streamed import LagState, lags_step
from tertiary.evaluation.streamed import ID_ROWS, SCORED, matched_table
from tertiary.pipeline.clock import StageClock
from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.pictures import safety_id_column
from tertiary.pipeline.plan import window_aircraft
from tertiary.pipeline.stca_scoring import TruthIntervals, intervals_step
from tertiary.pipeline.truth_alerts import TruthPictureState, truth_picture_step
from tertiary.runtime.windows import Window

__all__ = ["EVALUATION_FIELDS", "Handoff", "Overlap", "evaluate_step"]

#: the fields of the stream state the evaluation half carries (the processing half never reads them)
EVALUATION_FIELDS = ("curves", "evaluation", "intervals", "bound", "truth_picture", "lags", "id_rows")


@dataclass(frozen=True)
class Handoff:
    """What a window's processing hands its evaluation."""

    reports: pl.DataFrame
    aligned: pl.DataFrame
    fused: pl.DataFrame
    tracks: pl.DataFrame
    #: the picture the conflict prediction ran on (None: no safety)
    picture: pl.DataFrame | None
    #: the reports carry the evaluation-only truth ids (the STCA curves are scored on them)
    labelled: bool
    #: the conflict rows predicted on ``picture`` (None: no safety)
    conflicts: pl.DataFrame | None = None


def evaluate_step(cfg: PipelineConfig, ctx: Any, st: Any, h: Handoff, w: Window, clock: StageClock
                  ) -> tuple[dict[str, pl.DataFrame], Any]:
    """Window ``w``'s evaluation from its processing's :class:`Handoff`: its output tables and
    ``st`` (a :class:`~tertiary.pipeline.streaming.StreamState`) with the evaluation's fields
    advanced. The STCA curves and the truth picture read neither the matching nor each other's
    state: they run on a thread of their own beside the matching (:func:`_conflict_side`)."""
    if not _has_side(ctx, h):
        out, main = _matching_side(cfg, ctx, st, h, w, clock)
        clock.stage(None)
        return _with_id_rows(cfg, ctx, h, out, dataclasses.replace(st, **main))
    side_clock = StageClock(lambda name: None if f"{name}_s" in clock.timings else clock.say(name))
    with ThreadPoolExecutor(1, thread_name_prefix="evaluation-side") as pool:
        side = pool.submit(_conflict_side, cfg, ctx, st, h, w, side_clock)
        # a failure here leaves the clock on its stage (the run names it); the pool's exit waits
        # for the other thread first
        out_eval, main = _matching_side(cfg, ctx, st, h, w, clock)
        clock.stage(None)
        side_failure = side.exception()
    _merge_clock(clock, side_clock)
    if side_failure is not None:
        if side_clock.name is not None and not hasattr(side_failure, "tertiary_stage"):
            side_failure.tertiary_stage = side_clock.name  # type: ignore[attr-defined]
        raise side_failure
    curves, truth, s_curves, s_truth = side.result()
    return _with_id_rows(cfg, ctx, h, {**curves, **out_eval, **truth},
                         dataclasses.replace(st, curves=s_curves, truth_picture=s_truth, **main))


def _with_id_rows(cfg: PipelineConfig, ctx: Any, h: Handoff, out: dict[str, pl.DataFrame], st: Any
                  ) -> tuple[dict[str, pl.DataFrame], Any]:
    """``out`` with the window's block of the safety pictures' id map reduced to the rows the
    alert scoring may read (:data:`ID_ROWS`, :func:`safety.alerts.block_id_rows`), when the end
    reduces the id map to the run's alerts (``ctx.id_rows``); the state says whether every
    window wrote its block."""
    if not ctx.id_rows:
        return out, st
    id_col = safety_id_column(cfg)
    prefix = matched_table(f"{id_col}-")
    blocks = [t.select("run", "method", "epoch", id_col, pl.coalesce("truth_id", "gated_truth_id").alias("truth_id"))
              for name, t in out.items() if name.startswith(prefix) and t.height]
    if blocks:
        keys = [safety_alerts.alert_ids(h.conflicts, id_col)] if h.conflicts is not None else []
        if "curve_rows" in out:       # a point of the curves alerts on ids the production setting does not
            keys.append(safety_alerts.alert_ids(out["curve_rows"], id_col))
        keys = [k.select("run", "method", "epoch", id_col) for k in keys if k.height]
        ids = pl.concat(blocks, how="vertical_relaxed")
        hits = (pl.concat(keys, how="vertical_relaxed") if keys
                else ids.clear().select("run", "method", "epoch", id_col))
        out = {**out, ID_ROWS: safety_alerts.block_id_rows(ids, hits, id_col)}
    return out, dataclasses.replace(st, id_rows=getattr(st, "id_rows", None) is not False)


def _has_side(ctx: Any, h: Handoff) -> bool:
    """Whether the window has STCA curves or a truth picture to predict."""
    return _curves_due(ctx, h) or ctx.truth_slice is not None


def _curves_due(ctx: Any, h: Handoff) -> bool:
    """Whether the window's picture is predicted under the STCA curves' settings (scored on the
    reports' evaluation-only truth ids)."""
    return h.picture is not None and bool(ctx.curves) and h.labelled


def _conflict_side(cfg: PipelineConfig, ctx: Any, st: Any, h: Handoff, w: Window, clock: StageClock
                   ) -> tuple[dict[str, pl.DataFrame], dict[str, pl.DataFrame], Any, Any]:
    """The STCA curves' predictions and the truth picture's: their tables and states."""
    curves: dict[str, pl.DataFrame] = {}
    s_curves = st.curves
    if _curves_due(ctx, h):
        # every point of the trade-off curves predicted as the run goes: the whole-run stage
        # only scores their rows
        clock.stage("stca_curves")
        stage = ctx.stages["stca_curves"]
        o, s_curves = stage.step(stage.init() if s_curves is None else s_curves, {"picture": h.picture}, w)
        curves["curve_rows"] = o["curve_rows"]
    truth: dict[str, pl.DataFrame] = {}
    s_truth = st.truth_picture
    if ctx.truth_slice is not None:
        # the truth picture predicted as the run goes, but for the last stretch no later report
        # can change (the alert scoring attributes every picture's alerts by it)
        clock.stage("truth_picture")
        seen = window_aircraft(h.aligned, w)
        truth, s_truth = truth_picture_step(st.truth_picture or TruthPictureState(), seen, w.t1_us, cfg.conflicts,
                                            ctx.truth_slice, safety_id_column(cfg), ctx.origin)
    # a failure above leaves the clock on its stage: the caller names it
    clock.stage(None)
    return curves, truth, s_curves, s_truth


def _matching_side(cfg: PipelineConfig, ctx: Any, st: Any, h: Handoff, w: Window, clock: StageClock
                   ) -> tuple[dict[str, pl.DataFrame], dict[str, Any]]:
    """The pictures matched and scored, the truth's separation intervals, the bound and τ's lag
    sums: their tables and the state's fields they advance."""
    s_eval, out_eval = st.evaluation, {}
    if ctx.reference is not None:
        # matched and seed-scored as the run goes: the whole-run evaluation finishes the metrics
        clock.stage("match_pictures")
        stage = ctx.stages["evaluation"]
        out_eval, s_eval = stage.step(stage.init() if s_eval is None else s_eval,
                                      {"fused": h.fused, "tracks": h.tracks, "aligned": h.aligned}, w)
    s_int = st.intervals
    if ctx.truth_span is not None and ctx.reference is not None and ctx.reference.path is not None:
        # the truth's separation intervals of every chunk the windows have passed: the alert
        # scoring at the end merges the last chunks only
        clock.stage("truth_intervals")
        s_int = intervals_step(s_int or TruthIntervals(), ctx.reference.path, ctx.truth_span,
                               safety_alerts.AlertConfig(conflict=cfg.conflicts), ctx.origin, w.t1_us)
    s_bound = st.bound
    if ctx.bound is not None and ctx.reference is not None:
        # every aircraft's recursion carried on to the cut: the last window, open-ended, leaves the rest to the end
        clock.stage("bound")
        s_bound = bound_step(ctx.bound, s_bound or BoundState(), out_eval.get(SCORED), h.reports, w,
                             ctx.stored_scored)
    s_lags = st.lags
    if ctx.lags and ctx.reference is not None:
        # τ's lag sums of each track's scored series once no window has scored it for a while
        clock.stage("lag_sums")
        s_lags = lags_step(s_lags or LagState(), out_eval.get(SCORED), w, ctx.stored_scored)
    return out_eval, {"evaluation": s_eval, "intervals": s_int, "bound": s_bound, "lags": s_lags}


def _merge_clock(clock: StageClock, other: StageClock) -> None:
    """Add ``other``'s stage times and peaks to ``clock``'s."""
    for k, v in other.timings.items():
        clock.timings[k] = clock.timings.get(k, 0.0) + v
    for k, v in other.memory.items():
        clock.memory[k] = max(v, clock.memory.get(k, 0.0))


class _Halves:
    """A stream state to pickle as its processing half, already pickled (``blob``), and its
    evaluation fields: it unpickles as the whole state."""

    def __init__(self, blob: bytes, st: Any) -> None:
        self.blob, self.evaluation = blob, {k: getattr(st, k) for k in EVALUATION_FIELDS}

    def __reduce__(self) -> tuple:
        return _joined, (self.blob, self.evaluation)


def _joined(blob: bytes, evaluation: dict[str, Any]) -> Any:
    """The stream state of :class:`_Halves`."""
    return dataclasses.replace(pickle.loads(blob), **evaluation)


class Overlap:
    """Window k's evaluation and storing on a thread of their own while the caller processes
    window k + 1: the two cores share a run that otherwise keeps one of them idle. One window
    in flight, in window order, so every stored window is whole (its parts and a state that has
    both halves after it) and every evaluation step sees the previous one's state. The
    processing half of a checkpointed window's state is pickled before the next window runs (a
    stage may reuse its state's arrays); the evaluation's stage times are kept on a clock of their own
    (:meth:`timings`)."""

    def __init__(self, evaluate: Callable[[Any, Handoff, Window, StageClock], tuple[dict, Any]],
                 say: Callable[[str], None]) -> None:
        self._evaluate = evaluate
        self.clock = StageClock(say)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="window-evaluation")
        self._pending: Future | None = None
        #: seconds the last checkpoint's processing half took to pickle
        self.pickle_s = 0.0

    def submit(self, w: Window, out: dict[str, pl.DataFrame], processed: Any, h: Handoff | None, last: Any,
               store: Callable[[Window, dict, Any], None], checkpoint: bool = True) -> None:
        """Evaluate window ``w`` (``processed``: the state after its processing; ``h`` None:
        nothing to evaluate; ``last``: the state after the previous window) and ``store`` its
        tables and, with ``checkpoint``, its whole state (else None). Call :meth:`result` for
        the previous window first."""
        assert self._pending is None, "one window in flight"
        blob = None
        if checkpoint:
            t = time.perf_counter()
            blob = pickle.dumps(dataclasses.replace(processed, **dict.fromkeys(EVALUATION_FIELDS)),
                                protocol=pickle.HIGHEST_PROTOCOL)
            self.pickle_s = time.perf_counter() - t
        self._pending = self._pool.submit(self._job, w, out, blob, processed, h, last, store)

    def _job(self, w: Window, out: dict, blob: bytes | None, processed: Any, h: Handoff | None, last: Any,
             store: Callable[[Window, dict, Any], None]) -> Any:
        # without a checkpoint nothing reads the processing half here: the live state is not copied
        evaluation = {k: getattr(last, k) for k in EVALUATION_FIELDS}
        st = dataclasses.replace(processed if blob is None else pickle.loads(blob), **evaluation)
        try:
            if h is not None:
                more, st = self._evaluate(st, h, w, self.clock)
                out = {**out, **more}
        except Exception as exc:
            # the run names the failing stage; raised on the caller's thread, its clock's is another
            if self.clock.name is not None and not hasattr(exc, "tertiary_stage"):
                exc.tertiary_stage = self.clock.name  # type: ignore[attr-defined]
            raise
        # the checkpoint pickles the processing half's blob as it is: pickled once a window
        store(w, out, None if blob is None else _Halves(blob, st))
        return st

    def result(self) -> Any:
        """The whole state after the window in flight (None: none in flight); its failure raised here."""
        pending, self._pending = self._pending, None
        return None if pending is None else pending.result()

    def close(self) -> None:
        """Wait for the window in flight, its failure left to :meth:`result`."""
        if self._pending is not None:
            self._pending.exception()
        self._pool.shutdown(wait=True)

    def timings(self, clock: StageClock) -> None:
        """Add the evaluation's stage times and peaks to ``clock``'s."""
        _merge_clock(clock, self.clock)
