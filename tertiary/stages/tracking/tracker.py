"""Secondary tracking of fused plots: track management around a batched :class:`TrackFilter`.

Input is the ``fused`` table of ONE fusion method. Each fused row is a *plot* in two roles:

* **for gating, association and initiation**: its fused position (x_m, y_m, z_m) with the
  per-axis variances of the diagonal of ``cov``'s position block (as before);
* **as the filter's measurement**: only what is independent of the track's past — the fusion
  stage's plot-level fusion of the target's *fresh measured plots* (``meas_x_m``…``meas_z_m``,
  full 3×3 ``meas_cov``), taken at its own time epoch − ``age_s``. The fused states themselves
  are the radars' filtered estimates: correlated from epoch to epoch, and mere
  re-extrapolations where no radar has a new plot; a Kalman filter fed with them counts the
  same information again and again (it ends up worse than its input and over-confident). The
  alternative — decorrelating track estimates into equivalent measurements / tracklets
  (information decorrelation, Drummond 1997; Bar-Shalom, Willett & Tian 2011 §8.6) — needs
  the local filters' predicted covariances in the radars' own models (polar Singer channels
  here), which the fusion centre would have to re-create approximately; the measured plots
  are in every report (``range_m``, ``azimuth_deg``, elevation or Mode C), so the tracker uses
  them (the approach of measurement-level / plot fusion). A row without a fresh plot
  (``n_fresh`` = 0, null measurement) holds its track (it is not a miss) without updating it.
  A ``fused`` table without these columns is used as before, its fused position with the full
  3×3 position block of ``cov`` as the measurement at the epoch.

Filters that declare ``full_r`` (:mod:`tertiary.filters.coupled`) get the full 3×3
covariance, the per-axis filters its diagonal. Rows flagged ``tentative`` (clutter-only
targets) are dropped on input. The fused target ids are not used for association (the tracker
associates by position only); they are reported per row as ``plot_target_id`` so the
evaluation can find the plot's truth. Track output is reported at the epoch (predicted from
the measurement time) with ``cov_diag`` and the full 6×6 ``cov``.

Output is the ``tracks`` table plus ``status`` ("confirmed": the track took a plot at this
epoch — including the confirmation epoch —, or "coasting": no plot, predicted only, memory
mode) and ``plot_target_id`` (the fused target the track took, null when coasting). A
confirmed row is a *measurement update* only when its plot holds a fresh measurement (fused
``n_fresh`` > 0; its ``nis`` is then finite); a plot without one holds the track, un-updated
(NaN ``innovation``/``nis``), so "confirmed" alone does not mean "updated" (a scorer of
updated states must check the plot's freshness, as benchmarks/bench_stonesoup.py does).
Tentative tracks are not emitted.

Per epoch (one loop over the epochs; everything inside vectorised over tracks × runs):

1. **Predict** every object (confirmed track or tentative) of the runs that have plots at this
   epoch by its own dt. Runs without any plot at an epoch are left untouched (a data gap is
   not a miss).
2. **Tracking gate** of confirmed tracks, per axis i ∈ {x, y, z}:
   ``|z_i − x̂_i| ≤ gate_sigma·sqrt(P⁻_ii + r_i) + gate_min_m``. Candidates come from a sorted
   1-D index of the epoch's plots (key = σ-class·C + run·R + x, two ``searchsorted`` per
   gate for all tracks at once; the run offset R is far larger than any gate, so runs never
   mix), then the exact per-axis test. Cost of a gated pair: Σ_i (z_i − x̂_i)²/S_i + ln S_i,
   S_i = P⁻_ii + r_i (−2 ln of the Gaussian likelihood; the ln S term keeps a plot with a huge
   variance from looking close).
3. **Assignment**: ``"hungarian"`` — pairs that are their own component of the gate graph
   (one track, one plot) are assigned directly; all ambiguous components go to
   ``scipy.optimize.linear_sum_assignment`` together as one block-diagonal problem (per
   component if that block would be large), maximising the number of gated assignments
   first, then minimising the summed cost. ``"nearest"`` — every track takes its cheapest
   gated plot, a plot claimed by several tracks goes to the cheapest claimant, and the losers
   try again among the remaining plots (vectorised rounds; the seed's nearest neighbour).
4. **Update** assigned tracks (``mask``), **coast** the others (x⁺ = x⁻, P⁺ = P⁻), and
   **delete** a track at its ``max_misses``-th consecutive epoch without a plot (so
   ``max_misses − 1`` coasting rows at most; ``max_misses = 1`` means no coasting).
5. **Initiation** with the plots no confirmed track took:

   * ``"three_scan"``: the scans of the test are *measured* plots (fused ``n_fresh`` > 0): a
     target's rows between its radars' scans are extrapolations, which neither open, pair nor
     confirm; a tentative or a hypothesis without a measured plot at an epoch waits for one up
     to ``initiation_gap_s`` after its last. Scan 1 — every such plot x₁ opens a
     tentative track. Scan 2 — every plot in the annulus v_min·T ≤ |x₂ − x₁|_h ≤ v_max·T
     (horizontal distance, T = t₂ − t₁; (1.1)) spawns its own hypothesis (x₁, x₂); the stage-1
     track is then dropped. Scan 3 — a circle S₂ of radius ``confirm_gate_m`` (horizontal)
     around x̂₃ = x₂ + (x₂ − x₁)·(t₃ − t₂)/(t₂ − t₁) (= x₂ + (x₂ − x₁) for equal scans);
     hypotheses compete for the plots (``assignment``), competing confirmations of one x₁ or
     one x₂ keep the cheapest; a hypothesis whose wait ends with no plot in S₂ is dropped. The annulus and the
     circle also require a plausible height change:
     ``|Δz| ≤ gate_sigma·sqrt(r_z + r_z') + gate_min_m``.
   * ``"m_of_n"``: every such plot opens a tentative track (hits = 1); at each later scan the
     tentatives compete for the remaining plots — with the annulus gate while they have one
     plot, with the tracking gate afterwards — and a tentative is confirmed as soon as it has
     ``m`` plots within its first ``n`` scans, dropped as soon as that is impossible.

   In both modes the plots used only by stage-1 tentatives (a scan-2 hypothesis, or a
   one-plot M-of-N tentative) still open new tentatives too, so a wrong first pairing never
   costs the aircraft its plot.
6. Newly confirmed tracks get the next track ids of their run (1, 2, …, increasing with the
   confirmation epoch; stable for the track's life).

**Vertical channel.** Every object carries a two-state (h, ḣ) altitude filter
(:mod:`tertiary.stages.tracking.altitude`) beside the horizontal filter: predicted with (A1)–(A2) whenever the
object is, updated with the plot's vertical channel (``alt_m``, ``alt_rate_mps`` and their
covariance from the fused table, Mode C or geodetic fallback) as a measurement of both h and ḣ
(:func:`tertiary.stages.tracking.altitude.update2`), initialised from the first plot that has one. The plots'
heights are already filtered estimates, so a track's altitude variance is slightly optimistic
(successive plot errors are correlated); with the default q_a the gain stays near one and the
track follows the plot's channel without added lag. Output: the ``alt_*`` columns of
``tracks`` (null while the track has no altitude estimate).

A *scan* is an epoch at which the run has at least one plot; T and dt are the real time
differences, so irregular epochs are handled (x̂₃ above). The filter runs on tentatives too
(initialised on x₁, updated with every tentative plot), so a track enters tracking with its
first scans already filtered. Runs (Monte-Carlo) are tracked together in one batch and never
interact; track ids are per run. :func:`track_methods` folds the fusion methods into the same
batch axis (one epoch loop per filter for every (method, run)), so the per-epoch interpreter
cost is paid once per filter, not once per (method, filter).

**Windowed (streaming) use.** :func:`track_step` runs the same loop over the plots of one time
window [t0_us, t1_us), continuing from a :class:`TrackState` (per filter: the objects with their
counters, ids and scan-1/scan-2 plot uids, the filter bank state and the next id of every
(method, run); the batch runs as natural (method, run) keys; the fixed origin of the object
times). Object times are seconds since that origin (the first epoch with plots), so every dt is
right across windows; the tracker acts only at epochs with plots, so a window without plots
changes nothing. Consecutive steps give :func:`track_methods`'s rows bit for bit, and
:func:`track_methods` is :func:`init_track_state` + one step over the whole input.
"""


from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import TIME
from tertiary.stages.tracking.banks import Bank, track_batch
from tertiary.stages.tracking.config import STATUS, TRACK_COLUMNS, TrackerConfig
from tertiary.filters.base import TrackFilter, make_filter
from tertiary.stages.tracking.gating import PlotIndex

__all__ = ["TrackerConfig", "TrackState", "Filters", "filter_dict", "init_track_state", "track", "track_methods",
           "track_step", "TRACK_COLUMNS", "STATUS"]

_METHOD_KEY = 1 << 32                 # (method code, run) packed as code·_METHOD_KEY + run (_batch_runs)


def _check_fused(fused: pl.DataFrame) -> None:
    need = {"run", "epoch", "target_id", "x_m", "y_m", "z_m", "cov"}
    missing = sorted(need - set(fused.columns))
    if missing:
        raise ValueError(f"fused plots lack column(s) {', '.join(missing)}")


def _drop_tentative(fused: pl.DataFrame) -> pl.DataFrame:
    """Clutter-only targets never reach a track."""
    if "tentative" in fused.columns:
        return fused.filter(~pl.col("tentative").fill_null(False))
    return fused


@dataclass(frozen=True)
class TrackState:
    """What the secondary tracker carries from one window to the next (picklable).

    * ``keys``: the batch runs as natural keys ``(fusion method, run)``, in order of first
      appearance (sorted within a window); position j is batch run index j of every bank.
    * ``banks``: per filter name, its :class:`Bank` (objects, filter state, next ids).
    * ``origin_us``: int µs since the Unix epoch, the fixed origin of the banks' float object
      times (set by the first window holding plots to its first epoch unless given to
      :func:`init_track_state`). Object times stay float seconds since this fixed origin
      because a measurement time (epoch − ``age_s``) is not a whole µs, and float seconds since
      1970 resolve only ~0.2 µs (dt off by ~1e-7 relative).
    * ``next_uid``: the uid of the next plot (hypotheses are told apart by their plots' uids).
    * ``reached_us``: end (t1_us) of the last window stepped, None before the first.
    """

    keys: tuple[tuple[str, int], ...]
    banks: dict[str, Bank]
    origin_us: int | None = None
    next_uid: int = 0
    reached_us: int | None = None


Filters = dict[str, TrackFilter] | list[str] | tuple[str, ...]


def filter_dict(filters: Filters) -> dict[str, TrackFilter]:
    """``filters`` as name → filter (names are built with :func:`make_filter`)."""
    return dict(filters) if isinstance(filters, dict) else {name: make_filter(name) for name in filters}


def init_track_state(filters: Filters, origin_us: int | None = None) -> TrackState:
    """The empty tracker state (before the first window) for ``filters`` (names or name →
    filter, as :func:`track_step` will get them). ``origin_us``: the origin of the object
    times; None (recommended) takes the first epoch with plots, as :func:`track_methods` does,
    so a windowed run equals the whole-run call bit for bit."""
    return TrackState(keys=(), banks={name: Bank.empty() for name in filter_dict(filters)},
                      origin_us=None if origin_us is None else int(origin_us))


def _window_rows(fused: pl.DataFrame, t0_us: int, t1_us: int) -> pl.DataFrame:
    """The non-tentative plots of the window, checked to lie in [t0_us, t1_us)."""
    if fused.height == 0:
        return fused
    _check_fused(fused)
    if "method" not in fused.columns:
        raise ValueError("fused plots lack column method")
    rows = _drop_tentative(fused)
    if rows.height:
        us = rows["epoch"].cast(TIME).dt.epoch("us")
        lo, hi = int(us.min()), int(us.max())
        if lo < t0_us or hi >= t1_us:
            raise ValueError(f"fused epoch {lo if lo < t0_us else hi} µs outside the window [{t0_us}, {t1_us}) µs")
    return rows


def _batch_runs(rows: pl.DataFrame, keys: tuple[tuple[str, int], ...]) -> tuple[NDArray, tuple[tuple[str, int], ...]]:
    """The batch run index of every row and the keys extended with the window's new
    (method, run) pairs (sorted among themselves)."""
    meth = rows["method"].cast(pl.String)
    names = sorted(meth.unique().to_list())
    code = meth.replace_strict(pl.Series(names, dtype=pl.String),
                               pl.Series(np.arange(len(names), dtype=np.int64)), return_dtype=pl.Int64).to_numpy()
    ukey, inv = np.unique(code * _METHOD_KEY + rows["run"].cast(pl.Int64).to_numpy(), return_inverse=True)
    index = {k: j for j, k in enumerate(keys)}
    out = list(keys)
    pos = np.empty(len(ukey), np.int64)
    for n, k in enumerate(ukey.tolist()):                  # one per (method, run) of the window
        pair = (names[k // _METHOD_KEY], int(k % _METHOD_KEY))
        if pair not in index:
            index[pair] = len(out)
            out.append(pair)
        pos[n] = index[pair]
    return pos[inv.ravel()], tuple(out)


def track_step(state: TrackState, fused: pl.DataFrame, filters: Filters, cfg: TrackerConfig,
               t0_us: int, t1_us: int) -> tuple[pl.DataFrame, TrackState]:
    """One window of :func:`track_methods`: the tracks of the fused plots with epoch in
    [t0_us, t1_us) (every fusion method of ``fused`` × every filter, the layout of
    :func:`track_methods`), continuing from ``state`` (never modified); returns them and the
    state at the end of the window. No margin is needed: the tracker only looks at the
    current epoch's plots and its own objects.

    ``filters`` must name the filters of :func:`init_track_state` (pass the same dict every
    window: building filters per window repeats their set-up). Windows must come in time order
    (t0_us ≥ the previous t1_us). An empty window changes nothing but ``reached_us``: the
    tracker only acts at epochs with plots, a data gap is not a miss (module docstring)."""
    filters = filter_dict(filters)
    if set(filters) != set(state.banks):
        raise ValueError(f"track_step got filters {sorted(filters)}, the state holds {sorted(state.banks)}")
    if t1_us < t0_us or (state.reached_us is not None and t0_us < state.reached_us):
        raise ValueError(f"window [{t0_us}, {t1_us}) µs is not after the state's end {state.reached_us} µs")
    rows = _window_rows(fused, t0_us, t1_us)
    if rows.height == 0:
        return pl.DataFrame(schema=TRACK_COLUMNS), replace(state, reached_us=int(t1_us))
    run, keys = _batch_runs(rows, state.keys)
    ix = PlotIndex(rows.with_columns(pl.Series("run", run)), state.next_uid)
    origin = int(ix.epochs[0]) if state.origin_us is None else state.origin_us
    names = sorted({m for m, _ in keys})
    runs = np.array([r for _, r in keys], np.int64)
    run_method = np.array([names.index(m) for m, _ in keys], np.int64)
    banks, per_filter = {}, {}
    for name, filt in filters.items():
        emitted, banks[name] = track_batch(ix, filt, cfg, state.banks[name], len(keys), origin)
        per_filter[name] = emitted.frame(runs, filt.name, names, run_method)
    # the per-(method, filter) order of the unfolded loop: method-major, then filter
    parts = [part for meth in names for frame in per_filter.values()
             for part in [frame.filter(pl.col("method") == meth)] if part.height]
    tracks = pl.concat(parts, how="vertical") if parts else pl.DataFrame(schema=TRACK_COLUMNS)
    return tracks, TrackState(keys=keys, banks=banks, origin_us=origin, next_uid=state.next_uid + ix.n,
                              reached_us=int(t1_us))


def track(fused_one_method: pl.DataFrame, filt: TrackFilter, cfg: TrackerConfig = TrackerConfig()) -> pl.DataFrame:
    """Track the fused plots of one fusion method with ``filt``; returns the ``tracks`` table
    (plus ``status`` and ``plot_target_id``) with a row per confirmed/coasting track per epoch
    of its run, sorted by (run, epoch, track_id)."""
    _check_fused(fused_one_method)
    methods = (fused_one_method["method"].unique().to_list()
               if "method" in fused_one_method.columns else ["unknown"])
    if len(methods) > 1:
        raise ValueError(f"track() takes the fused rows of one method, got {sorted(map(str, methods))}")
    method = str(methods[0]) if methods else "unknown"
    return track_methods(fused_one_method.with_columns(pl.lit(method, pl.String).alias("method")),
                         {filt.name: filt}, cfg)


def track_methods(fused: pl.DataFrame, filters: Filters, cfg: TrackerConfig = TrackerConfig()) -> pl.DataFrame:
    """:func:`track` for every fusion method of ``fused`` × every filter (names are built with
    :func:`make_filter`); the tables concatenated (method-major, then filter, each sorted by
    (run, epoch, track_id)). It is :func:`init_track_state` + one :func:`track_step` over the
    whole input.

    (method, run) is folded into the batch axis: each filter runs ONE epoch loop over every
    method's picture at once, so the per-epoch interpreter overhead is paid once per filter
    instead of once per (method, filter). Batch runs never interact (see the module
    docstring), so each (method, run) gets exactly the tracks of its own :func:`track` call,
    with its own track ids.
    """
    filters = filter_dict(filters)
    _check_fused(fused)
    rows = _drop_tentative(fused)
    if rows.height == 0 or not filters:
        return pl.DataFrame(schema=TRACK_COLUMNS)
    us = rows["epoch"].cast(TIME).dt.epoch("us")
    tracks, _ = track_step(init_track_state(filters), rows, filters, cfg, int(us.min()), int(us.max()) + 1)
    return tracks
