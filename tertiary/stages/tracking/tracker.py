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

Filters that declare ``full_r`` (:mod:`tertiary.stages.tracking.filters.coupled`) get the full 3×3
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

   * ``"three_scan"`` (kalman-filters digest §1): scan 1 — every such plot x₁ opens a
     tentative track. Scan 2 — every plot in the annulus v_min·T ≤ |x₂ − x₁|_h ≤ v_max·T
     (horizontal distance, T = t₂ − t₁; (1.1)) spawns its own hypothesis (x₁, x₂); the stage-1
     track is then dropped. Scan 3 — a circle S₂ of radius ``confirm_gate_m`` (horizontal)
     around x̂₃ = x₂ + (x₂ − x₁)·(t₃ − t₂)/(t₂ − t₁) (= x₂ + (x₂ − x₁) for equal scans);
     hypotheses compete for the plots (``assignment``), competing confirmations of one x₁ or
     one x₂ keep the cheapest; a hypothesis with no plot in S₂ is dropped. The annulus and the
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
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tertiary.stages.tracking.altitude import (ALT_COLUMNS, AltitudeConfig, AltState, predict as alt_predict, update2 as alt_update)
from tertiary.stages.tracking.filters.base import (State, TrackFilter, concat, full_cov, make_filter, size, take)
from tertiary.contract.schema import TABLES, TIME

__all__ = ["TrackerConfig", "TrackState", "init_track_state", "track", "track_methods", "track_step",
           "TRACK_COLUMNS", "STATUS"]

STATUS = ("tentative", "confirmed", "coasting")
STATE_COLS = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")

#: the ``tracks`` table columns plus the tracker's extra columns
TRACK_COLUMNS: dict[str, pl.DataType] = {
    **TABLES["tracks"].required,
    **{c: TABLES["tracks"].optional[c] for c in ALT_COLUMNS},
    "cov": TABLES["tracks"].optional["cov"],
    "status": pl.String(),
    "plot_target_id": pl.UInt64(),
}

_TENT, _HYP, _CONF = 0, 1, 2          # object kinds: tentative (stage 1 / M-of-N), scan-2 hypothesis, confirmed
_RUN_SEP = 1.0e7                      # metres between runs in the plot sort key (never within a gate)
_DENSE_MAX = 250_000                  # largest dense block solved at once (else per component)
_METHOD_KEY = 1 << 32                 # (method code, run) packed as code·_METHOD_KEY + run (_batch_runs)


@dataclass(frozen=True)
class TrackerConfig:
    """Track management options (see the module docstring for the rules).

    * ``initiation``: ``"three_scan"`` (annulus S₁ then circle S₂) or ``"m_of_n"``.
    * ``v_min_mps``, ``v_max_mps``: annulus radii R_min = v_min·T, R_max = v_max·T (1.1).
    * ``confirm_gate_m``: radius of the scan-3 circle S₂.
    * ``m``, ``n``: M-of-N confirmation (``m`` plots within the first ``n`` scans).
    * ``gate_sigma``, ``gate_min_m``: tracking gate half-width per axis
      gate_sigma·sqrt(P⁻_ii + r_i) + gate_min_m.
    * ``assignment``: ``"hungarian"`` (global, per ambiguous gate component) or ``"nearest"``.
    * ``max_misses``: a track is deleted at this many consecutive epochs without a plot.
    * ``altitude``: the vertical-channel filter (q_a of (A1)).
    """

    initiation: Literal["three_scan", "m_of_n"] = "three_scan"
    v_min_mps: float = 30.0
    v_max_mps: float = 350.0
    confirm_gate_m: float = 1500.0
    m: int = 3
    n: int = 4
    gate_sigma: float = 4.0
    gate_min_m: float = 500.0
    assignment: Literal["nearest", "hungarian"] = "hungarian"
    max_misses: int = 3
    altitude: AltitudeConfig = AltitudeConfig()

    def __post_init__(self) -> None:
        if self.initiation not in ("three_scan", "m_of_n"):
            raise ValueError(f"initiation must be 'three_scan' or 'm_of_n', got {self.initiation!r}")
        if self.assignment not in ("nearest", "hungarian"):
            raise ValueError(f"assignment must be 'nearest' or 'hungarian', got {self.assignment!r}")
        if not 0 <= self.v_min_mps < self.v_max_mps:
            raise ValueError(f"need 0 <= v_min_mps < v_max_mps, got {self.v_min_mps}, {self.v_max_mps}")
        if not 1 <= self.m <= self.n:
            raise ValueError(f"need 1 <= m <= n, got m={self.m}, n={self.n}")
        if self.max_misses < 1:
            raise ValueError(f"max_misses must be >= 1, got {self.max_misses}")
        if self.confirm_gate_m <= 0 or self.gate_sigma <= 0 or self.gate_min_m < 0:
            raise ValueError("confirm_gate_m and gate_sigma must be > 0, gate_min_m >= 0")


# --------------------------------------------------------------------------- object bookkeeping

# Every object (tentative, hypothesis or confirmed track) is a row of two packed arrays, so the
# bookkeeping follows the filter state with two fancy-indexing operations per selection.
# float columns:
# _T: time of the filter state (the last measurement's time, epoch − age); _TA: time of the
# altitude filter (updated with the plot's vertical channel, which is at the epoch)
_T, _P1, _T1, _RZ1, _P2, _T2, _RZ2 = 0, slice(1, 4), 4, 5, slice(6, 9), 9, 10
_ALT = slice(11, 16)                  # altitude filter h, ḣ, P_hh, P_hḣ, P_ḣḣ (NaN: none yet)
_TA = 16
_NF = 17
# int columns: run index, kind, track id (0 until confirmed), consecutive misses, M-of-N hits
# and scans, uid of the scan-1 plot, uid of the scan-2 plot
_RUN, _KIND, _ID, _MISS, _HITS, _SCANS, _ROOT, _UID2 = range(8)
_NI = 8


@dataclass
class _Objects:
    f: NDArray      # (B, _NF) float64
    i: NDArray      # (B, _NI) int64

    @staticmethod
    def empty() -> "_Objects":
        return _Objects(np.zeros((0, _NF)), np.zeros((0, _NI), np.int64))

    def __len__(self) -> int:
        return len(self.i)

    def take(self, idx: NDArray) -> "_Objects":
        return _Objects(self.f[idx], self.i[idx])

    @staticmethod
    def concat(*objs: "_Objects") -> "_Objects":
        objs = tuple(o for o in objs if len(o))
        if not objs:
            return _Objects.empty()
        if len(objs) == 1:
            return objs[0]
        return _Objects(np.concatenate([o.f for o in objs]), np.concatenate([o.i for o in objs]))

    @staticmethod
    def new(run: NDArray, t: float, z: NDArray, rz: NDArray, uid: NDArray, alt: NDArray) -> "_Objects":
        n = len(run)
        f = np.zeros((n, _NF))
        f[:, _ALT] = alt
        f[:, _T] = f[:, _T1] = f[:, _TA] = t
        f[:, _P1] = z
        f[:, _RZ1] = rz
        i = np.zeros((n, _NI), np.int64)
        i[:, _RUN] = run
        i[:, _KIND] = _TENT
        i[:, _HITS] = i[:, _SCANS] = 1
        i[:, _ROOT] = uid
        i[:, _UID2] = -1
        return _Objects(f, i)


def _alt_step(f: NDArray, t: float, plot_alt: NDArray, mask: NDArray, q: float) -> NDArray:
    """The altitude filter of objects ``f`` (rows of _Objects.f) predicted to ``t`` and updated
    with their plots' vertical channel where ``mask`` and the plot has one; objects without an
    estimate start from the plot's. Returns the new (n, 5) block."""
    cur = AltState(*(f[:, _ALT.start + i] for i in range(5)))
    pred = alt_predict(cur, t - f[:, _TA], q)
    meas = AltState(*(plot_alt[:, i] for i in range(5)))
    have_m = mask & np.isfinite(plot_alt).all(axis=1)
    have_t = np.isfinite(pred.h)
    with np.errstate(invalid="ignore", divide="ignore"):
        upd = alt_update(pred, meas)
    cols = []
    for name in ("h", "r", "phh", "phr", "prr"):
        p, u, m = getattr(pred, name), getattr(upd, name), getattr(meas, name)
        cols.append(np.where(have_m, np.where(have_t, u, m), p))
    return np.column_stack(cols) if len(f) else np.zeros((0, 5))


def _take_state(state: State, idx: NDArray, n: int) -> State:
    """``take`` that skips the copy when ``idx`` selects every track in order."""
    if len(idx) == n and (n == 0 or (idx[0] == 0 and (n == 1 or bool((np.diff(idx) == 1).all())))):
        return state
    return take(state, idx)


def _join_states(*states: State) -> State:
    out: State = {}
    for s_ in states:
        if s_ and size(s_):
            out = concat(out, s_)
    return out


# --------------------------------------------------------------------------- gating


def _window_pairs(keys: NDArray, centers: NDArray, radii: NDArray) -> tuple[NDArray, NDArray]:
    """(centre, plot) index pairs with the plot's sort key within ``radii`` of the centre key.

    The candidates of every centre are one contiguous slice of the sorted ``keys`` (two
    ``searchsorted``), so a whole coarse gate is a handful of vectorised calls.
    """
    if len(keys) == 0 or len(centers) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo = np.searchsorted(keys, centers - radii, side="left")
    hi = np.searchsorted(keys, centers + radii, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    obj = np.repeat(np.arange(len(centers)), cnt)
    return obj, np.arange(total) - np.repeat(np.cumsum(cnt) - cnt - lo, cnt)


#: plot σ class limits (m): the tracking gate grows with the plot variance, so each σ class of
#: plots gets its own (exact, superset) window — a plot with a σ of kilometres does not widen
#: the search around every track
_SIGMA_CLASSES = np.array([150.0, 1000.0])
_CLASS_SEP = 1.0e13                   # key offset between σ classes (> any run offset)


@dataclass
class _Plots:
    """The plots of one epoch (all runs), sorted by the key class·_CLASS_SEP + run·_RUN_SEP + x
    (class = σ class of the plot)."""

    run: NDArray
    z: NDArray
    r: NDArray
    alt: NDArray              # (n, 5) h, ḣ, P_hh, P_hḣ, P_ḣḣ of the plot's vertical channel (NaN: none)
    tid: NDArray
    uid: NDArray
    zm: NDArray               # (n, 3) the measurement: plot-level fusion of the fresh plots
    rm: NDArray               # (n, 3, 3) its full covariance
    age: NDArray              # (n,) measurement time = epoch − age
    fresh: NDArray            # (n,) the fused plot holds a new measurement
    keys: NDArray
    classes: NDArray          # σ classes present
    rmax_x: NDArray           # largest x variance of each present class

    def window(self, run: NDArray, x: NDArray, radius: NDArray) -> tuple[NDArray, NDArray]:
        """(object, plot) pairs with |x_plot − x| ≤ radius in the same run; ``radius`` is (n,)
        or (n_classes_present, n) for a per-class radius."""
        n = len(run)
        if n == 0 or len(self.keys) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        base = run * _RUN_SEP + x
        centers = (self.classes[:, None] * _CLASS_SEP + base[None, :]).ravel()
        radii = (radius if radius.ndim == 2 else np.repeat(radius[None], len(self.classes), axis=0)).ravel()
        o, p = _window_pairs(self.keys, centers, radii)
        return o % n, p


def _plot_alt(f: pl.DataFrame) -> NDArray:
    """(n, 5) vertical channel of the fused plots in AltState order (NaN where absent)."""
    names = ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_cov_m2ps", "alt_rate_var_m2ps2")
    if not all(c in f.columns for c in names):
        return np.full((f.height, 5), np.nan)
    return np.column_stack([f[c].cast(pl.Float64).fill_null(np.nan).to_numpy() for c in names])


class _PlotIndex:
    """All plots of one window sorted by (epoch, σ class, run, x) with per-epoch slices, built
    once per window. ``fused["run"]`` is already the batch run index (:class:`TrackState`
    ``keys``); plot uids are ``uid0`` + the row's position in this order, so they continue
    across windows (they equal the whole-run positions when the windows are cut by epoch)."""

    def __init__(self, fused: pl.DataFrame, uid0: int = 0) -> None:
        f = fused.with_columns(pl.col("epoch").cast(TIME))
        cov = f["cov"].to_numpy()
        cov = np.asarray(cov, float).reshape(-1, 36) if cov.dtype != object else np.stack(cov).reshape(-1, 36)
        r = cov[:, [0, 7, 14]].astype(float)
        z = f.select("x_m", "y_m", "z_m").to_numpy().astype(float)
        epoch_us = f["epoch"].dt.epoch("us").to_numpy()
        run = f["run"].cast(pl.Int64).to_numpy()
        cls = np.searchsorted(_SIGMA_CLASSES, np.sqrt(r.max(axis=1)))
        order = np.lexsort((z[:, 0], run, cls, epoch_us))
        self.uid0 = int(uid0)
        self.n = len(order)
        self.run = run.astype(np.int64)[order]
        self.cls = cls[order]
        self.z = np.ascontiguousarray(z[order])
        self.r = np.ascontiguousarray(r[order])
        self.tid = f["target_id"].cast(pl.UInt64).to_numpy()[order]
        self.alt = _plot_alt(f)[order]
        zm, rm, age, fresh = _measurements(f, z, cov)
        self.zm, self.rm = np.ascontiguousarray(zm[order]), np.ascontiguousarray(rm[order])
        self.age, self.fresh = age[order], fresh[order]
        self.keys = self.cls * _CLASS_SEP + self.run * _RUN_SEP + self.z[:, 0]
        self.epochs, starts = np.unique(epoch_us[order], return_index=True)
        self.bounds = np.r_[starts, len(order)]
        # σ-class segments of every epoch and their largest x variance, once for all epochs
        ep = epoch_us[order]
        seg = np.flatnonzero(np.r_[True, (ep[1:] != ep[:-1]) | (self.cls[1:] != self.cls[:-1])])
        self.seg_cls = self.cls[seg].astype(float)
        self.seg_rmax_x = np.maximum.reduceat(self.r[:, 0], seg) if len(seg) else np.zeros(0)
        self.seg_bounds = np.searchsorted(seg, self.bounds)

    def __len__(self) -> int:
        return len(self.epochs)

    def epoch(self, k: int) -> _Plots:
        lo, hi = self.bounds[k], self.bounds[k + 1]
        s0, s1 = self.seg_bounds[k], self.seg_bounds[k + 1]
        return _Plots(self.run[lo:hi], self.z[lo:hi], self.r[lo:hi], self.alt[lo:hi], self.tid[lo:hi],
                      np.arange(self.uid0 + lo, self.uid0 + hi, dtype=np.int64), self.zm[lo:hi], self.rm[lo:hi], self.age[lo:hi],
                      self.fresh[lo:hi], self.keys[lo:hi], self.seg_cls[s0:s1], self.seg_rmax_x[s0:s1])


def _measurements(f: pl.DataFrame, z: NDArray, cov36: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The measurement of every fused row: (z (n, 3), R (n, 3, 3), age (n,), fresh (n,)).

    With the fusion stage's plot-level columns (``meas_x_m``… ``meas_cov``, ``age_s``,
    ``n_fresh``): the fused fresh plots at epoch − ``age_s``; a row without a fresh plot is not
    a measurement (``fresh`` False). Without them (a ``fused`` table from elsewhere): the fused
    position with the full 3×3 position block of ``cov``, at the epoch."""
    n = f.height
    pos = cov36.reshape(n, 6, 6)[:, :3, :3].copy()
    names = ("meas_x_m", "meas_y_m", "meas_z_m", "meas_cov", "age_s")
    if not all(c in f.columns for c in names):
        fresh = (f["n_fresh"].fill_null(1).to_numpy() > 0) if "n_fresh" in f.columns else np.ones(n, bool)
        return z, pos, np.zeros(n), fresh
    zm = f.select(names[:3]).to_numpy().astype(float)
    rm = np.asarray(f["meas_cov"].to_numpy(), float).reshape(n, 3, 3)
    age = f["age_s"].cast(pl.Float64).fill_null(0.0).to_numpy()
    fresh = np.isfinite(zm).all(axis=1) & np.isfinite(rm).all(axis=(1, 2))
    return np.where(fresh[:, None], zm, z), np.where(fresh[:, None, None], rm, pos), np.where(fresh, age, 0.0), fresh


def _likelihood_cost(d: NDArray, s: NDArray) -> NDArray:
    """−2 ln of the Gaussian likelihood up to a constant: Σ_i d_i²/S_i + ln S_i."""
    return (d * d / s + np.log(s)).sum(axis=1)


def _tracking_pairs(plots: _Plots, free: NDArray, run: NDArray, xp: NDArray, vp: NDArray,
                    cfg: TrackerConfig) -> tuple[NDArray, NDArray, NDArray]:
    """Gated (object, plot, cost) triples of the tracking gate around the predictions ``xp``."""
    if len(run) == 0 or not free.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    radius = cfg.gate_sigma * np.sqrt(vp[None, :, 0] + plots.rmax_x[:, None]) + cfg.gate_min_m
    o, p = plots.window(run, xp[:, 0], radius)
    if not free.all():
        keep = free[p]
        o, p = o[keep], p[keep]
    # one axis at a time on 1-D gathers, y first: the x window leaves most candidates to fail
    # on y, so the full 3-axis rows are gathered only for the few that pass
    for axis in (1, 0, 2):
        d = plots.z[p, axis] - xp[o, axis]
        ok = np.abs(d) <= cfg.gate_sigma * np.sqrt(vp[o, axis] + plots.r[p, axis]) + cfg.gate_min_m
        o, p = o[ok], p[ok]
    return o, p, _likelihood_cost(plots.z[p] - xp[o], vp[o] + plots.r[p])


def _vertical_ok(dz: NDArray, rz_a: NDArray, rz_b: NDArray, cfg: TrackerConfig) -> NDArray:
    return np.abs(dz) <= cfg.gate_sigma * np.sqrt(rz_a + rz_b) + cfg.gate_min_m


def _annulus_pairs(plots: _Plots, free: NDArray, objs: _Objects, t: float,
                   cfg: TrackerConfig) -> tuple[NDArray, NDArray]:
    """(object, plot) pairs with the plot in the annulus S₁ around the object's last plot:
    v_min·T ≤ horizontal distance ≤ v_max·T, T = t − t₁ (1.1), and a plausible height change."""
    if len(objs) == 0 or not free.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    p1, dt = objs.f[:, _P1], t - objs.f[:, _T1]
    o, p = plots.window(objs.i[:, _RUN], p1[:, 0], cfg.v_max_mps * dt)
    keep = free[p]
    o, p = o[keep], p[keep]
    dh = np.hypot(plots.z[p, 0] - p1[o, 0], plots.z[p, 1] - p1[o, 1])
    ok = ((dh >= cfg.v_min_mps * dt[o]) & (dh <= cfg.v_max_mps * dt[o])
          & _vertical_ok(plots.z[p, 2] - p1[o, 2], objs.f[o, _RZ1], plots.r[p, 2], cfg))
    return o[ok], p[ok]


def _confirm_pairs(plots: _Plots, free: NDArray, hyp: _Objects, t: float,
                   cfg: TrackerConfig) -> tuple[NDArray, NDArray, NDArray]:
    """(hypothesis, plot, cost) of plots inside the scan-3 circle S₂ around
    x̂₃ = x₂ + (x₂ − x₁)·(t − t₂)/(t₂ − t₁); cost = (d_h/R_S₂)² + (Δz/tolerance)²."""
    if len(hyp) == 0 or not free.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    p1, p2 = hyp.f[:, _P1], hyp.f[:, _P2]
    ratio = (t - hyp.f[:, _T2]) / np.maximum(hyp.f[:, _T2] - hyp.f[:, _T1], 1e-9)
    x3 = p2 + (p2 - p1) * ratio[:, None]
    o, p = plots.window(hyp.i[:, _RUN], x3[:, 0], np.full(len(hyp), cfg.confirm_gate_m))
    keep = free[p]
    o, p = o[keep], p[keep]
    dz = plots.z[p, 2] - x3[o, 2]
    dh2 = (plots.z[p, 0] - x3[o, 0]) ** 2 + (plots.z[p, 1] - x3[o, 1]) ** 2
    tol = cfg.gate_sigma * np.sqrt(hyp.f[o, _RZ2] + plots.r[p, 2]) + cfg.gate_min_m
    ok = (np.abs(dz) <= tol) & (dh2 <= cfg.confirm_gate_m ** 2)
    return o[ok], p[ok], dh2[ok] / cfg.confirm_gate_m ** 2 + (dz[ok] / tol[ok]) ** 2


# --------------------------------------------------------------------------- assignment


def _compact(v: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """``np.unique(v, return_inverse=True)`` for indices 0 ≤ v < n, without sorting."""
    present = np.zeros(n, bool)
    present[v] = True
    return np.flatnonzero(present), (np.cumsum(present) - 1)[v]


def _assign(o: NDArray, p: NDArray, cost: NDArray, n_obj: int, n_plot: int, method: str) -> NDArray:
    """Plot index per object (−1 if none) from gated pairs; one plot per object and vice versa."""
    out = np.full(n_obj, -1, np.int64)
    if len(o) == 0:
        return out
    if method == "nearest":
        return _nearest(o, p, cost, out, n_plot)
    n_o = np.bincount(o, minlength=n_obj)
    n_p = np.bincount(p, minlength=n_plot)
    single = (n_o[o] == 1) & (n_p[p] == 1)        # a pair that is its own gate component
    out[o[single]] = p[single]
    if single.all():
        return out
    amb = np.flatnonzero(~single)
    ro, ri = _compact(o[amb], n_obj)
    co, ci = _compact(p[amb], n_plot)
    if len(ro) * len(co) <= _DENSE_MAX:
        # all ambiguous components in one block-diagonal problem (off-block = not gated)
        blocks = [(amb, ro, ri, co, ci)]
    else:
        graph = coo_matrix((np.ones(len(amb)), (ri, len(ro) + ci)), shape=(len(ro) + len(co),) * 2)
        _, label = connected_components(graph, directed=False)
        comp = label[ri]
        order = np.argsort(comp, kind="stable")
        cuts = np.flatnonzero(np.diff(comp[order]) != 0) + 1
        blocks = []
        for seg in np.split(amb[order], cuts):          # one loop per ambiguous component
            bro, bri = np.unique(o[seg], return_inverse=True)
            bco, bci = np.unique(p[seg], return_inverse=True)
            blocks.append((seg, bro, bri, bco, bci))
    for seg, bro, bri, bco, bci in blocks:
        # shifted costs ≥ 0 and a "not gated" cost above any sum of them: the solution has the
        # most gated assignments possible, then the least cost among those
        c = cost[seg] - cost[seg].min()
        big = (c.max() + 1.0) * (min(len(bro), len(bco)) + 1)
        dense = np.full((len(bro), len(bco)), big)
        dense[bri, bci] = c
        a, b = linear_sum_assignment(dense)
        good = dense[a, b] < big
        out[bro[a[good]]] = bco[b[good]]
    return out


def _nearest(o: NDArray, p: NDArray, cost: NDArray, out: NDArray, n_plot: int) -> NDArray:
    """Vectorised nearest neighbour: each object claims its cheapest plot, the cheapest claimant
    of each plot wins, losers retry among the plots still free."""
    taken = np.zeros(n_plot, bool)
    while len(o):
        order = np.lexsort((cost, o))
        o, p, cost = o[order], p[order], cost[order]
        first = np.r_[True, o[1:] != o[:-1]]               # each object's cheapest plot
        co, cp, cc = o[first], p[first], cost[first]
        order = np.lexsort((cc, cp))
        co, cp = co[order], cp[order]
        win = np.r_[True, cp[1:] != cp[:-1]]               # each plot's cheapest claimant
        out[co[win]] = cp[win]
        taken[cp[win]] = True
        keep = (out[o] < 0) & ~taken[p]
        o, p, cost = o[keep], p[keep], cost[keep]
    return out


# --------------------------------------------------------------------------- the tracker


class _Emitted:
    """Output rows accumulated epoch by epoch."""

    def __init__(self) -> None:
        self.parts: dict[str, list[NDArray]] = {k: [] for k in
                                                ("run", "epoch", "track_id", "x", "var", "cov", "nu", "nis", "upd",
                                                 "tid", "alt")}
        self.probs: list[NDArray | None] = []

    def add(self, **arrays) -> None:
        probs = arrays.pop("probs")
        for k, v in arrays.items():
            self.parts[k].append(v)
        self.probs.append(probs)

    def _probs(self, n: int) -> NDArray | None:
        """Model probabilities of every row (NaN-padded to the widest), None if no filter has any."""
        if all(pr is None for pr in self.probs):
            return None
        width = max(pr.shape[1] for pr in self.probs if pr is not None)
        probs = np.full((n, width), np.nan)
        at = 0
        for pr, part in zip(self.probs, self.parts["run"]):
            if pr is not None:
                probs[at:at + len(part), :pr.shape[1]] = pr
            at += len(part)
        return probs

    def frame(self, runs: NDArray, filt_name: str, methods: list[str], run_method: NDArray) -> pl.DataFrame:
        """The rows as a ``tracks`` table; batch run index j is run ``runs[j]`` of fusion method
        ``methods[run_method[j]]``. Sorted by (batch run, epoch, track_id)."""
        if not self.parts["run"] or sum(len(a) for a in self.parts["run"]) == 0:
            return pl.DataFrame(schema=TRACK_COLUMNS)
        c = {k: np.concatenate(v, axis=0) for k, v in self.parts.items()}
        n = len(c["run"])
        probs = self._probs(n)
        # sort by (run, epoch, track_id) in numpy (unique keys, runs sorted): cheaper than
        # sorting the wide polars frame
        order = np.lexsort((c["track_id"], c["epoch"], c["run"]))
        c = {k: v[order] for k, v in c.items()}
        upd = c["upd"]
        nu = pl.Series("innovation", c["nu"]).cast(pl.List(pl.Float64))
        if probs is not None:
            probs = probs[order]
            has = ~np.isnan(probs).all(axis=1)
            model_probs = pl.Series("model_probs", probs).cast(pl.List(pl.Float64))
        else:
            has = np.zeros(n, bool)
            model_probs = pl.Series("model_probs", [None] * n, dtype=pl.List(pl.Float64))
        frame = pl.DataFrame({
            "run": runs[c["run"]].astype(np.uint32),
            "epoch": pl.Series(c["epoch"]).cast(pl.Datetime("us")).dt.replace_time_zone("UTC"),
            "track_id": c["track_id"].astype(np.uint64),
            # constant and two-valued strings built by polars: numpy object/str arrays convert slowly
            "filter": pl.repeat(filt_name, n, dtype=pl.String, eager=True),
            "method": (pl.repeat(methods[0], n, dtype=pl.String, eager=True) if len(methods) == 1 else
                       pl.Series(methods, dtype=pl.String).gather(run_method[c["run"]])),
            **{col: c["x"][:, i] for i, col in enumerate(STATE_COLS)},
            "cov_diag": c["var"],
            "cov": c["cov"],
            # AltState order h, ḣ, P_hh, P_hḣ, P_ḣḣ → ALT_COLUMNS
            **{col: c["alt"][:, j] for col, j in zip(ALT_COLUMNS, (0, 1, 2, 4, 3))},
            "innovation": nu,
            "nis": c["nis"],
            "model_probs": model_probs,
            "plot_target_id": c["tid"],
            "__upd": upd,
            "__has_probs": has,
        })
        upd_col = pl.col("__upd")
        frame = frame.with_columns(
            pl.when(upd_col).then(pl.col("innovation")).alias("innovation"),
            pl.when(upd_col).then(pl.col("nis")).alias("nis"),
            pl.when(upd_col).then(pl.col("plot_target_id")).alias("plot_target_id"),
            pl.when(pl.col("__has_probs")).then(pl.col("model_probs")).alias("model_probs"),
            pl.when(upd_col).then(pl.lit("confirmed")).otherwise(pl.lit("coasting")).alias("status"),
        )
        frame = frame.with_columns(pl.col(list(ALT_COLUMNS)).fill_nan(None))
        return frame.select(list(TRACK_COLUMNS)).cast(TRACK_COLUMNS)


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


def _track_batch(ix: "_PlotIndex", filt: TrackFilter, cfg: TrackerConfig, bank: "_Bank", n_runs: int,
                 origin_us: int) -> tuple["_Emitted", "_Bank"]:
    """The tracker's epoch loop over the plots of one window (``ix``, batch run indices
    0 ≤ j < ``n_runs``; batch runs never interact), starting from ``bank`` (never modified).
    Object times are float seconds since ``origin_us``. Returns the emitted rows and the bank
    at the end of the window."""
    secs = (ix.epochs - origin_us) / 1e6
    state: State = bank.filt_state
    objs = _Objects(bank.f, bank.i)
    next_id = np.r_[bank.next_id, np.ones(n_runs - len(bank.next_id), np.int64)]
    emitted = _Emitted()
    three = cfg.initiation == "three_scan"
    empty = np.zeros(0, np.int64)

    for k, t in enumerate(secs):
        plots = ix.epoch(k)
        n_plot = len(plots.run)

        # --- predict the objects of the runs that have plots now
        if n_runs == 1:
            act, idle = np.arange(len(objs)), empty
        else:
            run_on = np.zeros(n_runs, bool)
            run_on[plots.run] = True
            on = run_on[objs.i[:, _RUN]]
            act, idle = np.flatnonzero(on), np.flatnonzero(~on)
        m = objs.take(act) if len(idle) else objs
        prev = _take_state(state, act, len(objs))
        if len(m):
            st = filt.predict(prev, t - m.f[:, _T])
            pred = filt.output(st)
            xp, vp = pred.x[:, :3], pred.var[:, :3]
        else:
            st, xp, vp = {}, np.zeros((0, 3)), np.zeros((0, 3))
        kind = m.i[:, _KIND]
        free = np.ones(n_plot, bool)

        # --- confirmed tracks: gate and assign
        conf = np.flatnonzero(kind == _CONF)
        o, p, c = _tracking_pairs(plots, free, m.i[conf, _RUN], xp[conf], vp[conf], cfg)
        plot_of_conf = _assign(o, p, c, len(conf), n_plot, cfg.assignment)
        free[plot_of_conf[plot_of_conf >= 0]] = False
        opens = free.copy()                      # plots that open new tentative tracks

        # --- initiation
        win, plot_of_win = empty, empty          # three-scan: hypotheses confirmed now
        pair_obj, pair_plot = empty, empty       # three-scan: new hypotheses (stage-1 object, plot)
        tent, plot_of_tent = empty, empty        # M-of-N: tentatives (their plot or −1)
        if three:
            hyp = np.flatnonzero(kind == _HYP)
            o, p, c = _confirm_pairs(plots, free, m.take(hyp), t, cfg)
            if len(o):
                plot_of_hyp = _assign(o, p, c, len(hyp), n_plot, cfg.assignment)
                chosen = plot_of_hyp[o] == p
                cost_of = np.full(len(hyp), np.inf)
                cost_of[o[chosen]] = c[chosen]
                got = np.flatnonzero(plot_of_hyp >= 0)
                got = _resolve_conflicts(got, cost_of[got], m.i[hyp[got], _ROOT], m.i[hyp[got], _UID2])
                win, plot_of_win = hyp[got], plot_of_hyp[got]
                free[plot_of_win] = False
                opens &= free
            s1 = np.flatnonzero(kind == _TENT)
            if len(s1):
                o, p = _annulus_pairs(plots, free, m.take(s1), t, cfg)
                pair_obj, pair_plot = s1[o], p
        else:
            tent = np.flatnonzero(kind == _TENT)
            one = m.i[tent, _HITS] == 1
            o1, p1 = _annulus_pairs(plots, free, m.take(tent[one]), t, cfg)
            o1 = np.flatnonzero(one)[o1]
            c1 = _likelihood_cost(plots.z[p1] - xp[tent[o1]], vp[tent[o1]] + plots.r[p1])
            many = np.flatnonzero(~one)
            o2, p2, c2 = _tracking_pairs(plots, free, m.i[tent[many], _RUN], xp[tent[many]], vp[tent[many]], cfg)
            plot_of_tent = _assign(np.r_[o1, many[o2]], np.r_[p1, p2], np.r_[c1, c2], len(tent), n_plot,
                                   cfg.assignment)
            used = plot_of_tent >= 0
            free[plot_of_tent[used]] = False
            opens[plot_of_tent[used & ~one]] = False

        # --- one filter update for everything that continues
        misses = np.where(plot_of_conf >= 0, 0, m.i[conf, _MISS] + 1)
        alive = misses < cfg.max_misses
        idx = np.concatenate([conf[alive], win, pair_obj, tent])
        pidx = np.concatenate([plot_of_conf[alive], plot_of_win, pair_plot, plot_of_tent])
        mask = pidx >= 0
        safe = np.where(mask, pidx, 0)
        z, r = plots.z[safe], plots.r[safe]
        mu = m.take(idx)
        # the filter takes only new measurements, at their own time epoch − age
        fresh = mask & plots.fresh[safe]
        age = np.where(fresh, plots.age[safe], 0.0)
        if len(idx):
            base = _take_state(st, idx, len(m))
            if (age > 0).any():
                base = filt.predict(_take_state(prev, idx, len(m)), np.maximum(t - age - mu.f[:, _T], 0.0))
            rm = plots.rm[safe]
            su, inn = filt.update(base, plots.zm[safe], rm if filt.full_r else np.einsum("bii->bi", rm), fresh)
        else:
            su, inn = {}, None
        mu.f[:, _ALT] = _alt_step(mu.f, t, plots.alt[safe], mask, cfg.altitude.q_m2ps3)
        mu.f[:, _T] = t - age
        mu.f[:, _TA] = t
        n_c, n_w, n_p = int(alive.sum()), len(win), len(pair_obj)
        mu.i[:n_c, _MISS] = misses[alive]
        newly = np.zeros(len(idx), bool)
        if three:
            mu.i[n_c:n_c + n_w, _KIND] = _CONF
            newly[n_c:n_c + n_w] = True
            hs = slice(n_c + n_w, n_c + n_w + n_p)
            mu.i[hs, _KIND] = _HYP
            mu.f[hs, _P2] = plots.z[pair_plot]
            mu.f[hs, _RZ2] = plots.r[pair_plot, 2]
            mu.f[hs, _T2] = t
            mu.i[hs, _UID2] = plots.uid[pair_plot]
            keep = np.ones(len(idx), bool)
        else:
            ts = slice(n_c, len(idx))
            hit = mask[ts]
            mu.i[ts, _HITS] += hit
            mu.i[ts, _SCANS] += 1
            mu.f[ts, _P1] = np.where(hit[:, None], z[ts], mu.f[ts, _P1])
            mu.f[ts, _T1] = np.where(hit, t, mu.f[ts, _T1])
            mu.f[ts, _RZ1] = np.where(hit, r[ts, 2], mu.f[ts, _RZ1])
            ok = mu.i[ts, _HITS] >= cfg.m
            newly[ts] = ok
            mu.i[ts, _KIND] = np.where(ok, _CONF, _TENT)
            keep = np.ones(len(idx), bool)
            keep[ts] = ok | (mu.i[ts, _HITS] + (cfg.n - mu.i[ts, _SCANS]) >= cfg.m)

        # --- track ids of the newly confirmed: the next ids of their run, in plot order
        nid = np.flatnonzero(newly)
        if len(nid):
            rr = mu.i[nid, _RUN]
            order = np.argsort(rr, kind="stable")
            srt = rr[order]
            rank = np.empty(len(nid), np.int64)
            rank[order] = np.arange(len(nid)) - np.searchsorted(srt, srt)
            mu.i[nid, _ID] = next_id[rr] + rank
            next_id += np.bincount(rr, minlength=n_runs)

        # --- emit the confirmed and coasting rows
        emit = np.flatnonzero(mu.i[:, _KIND] == _CONF)
        if len(emit):
            se = _take_state(su, emit, len(idx))
            if (age[emit] > 0).any():               # reported at the epoch
                se = filt.predict(se, t - mu.f[emit, _T])
            oe = filt.output(se)
            upd = mask[emit]
            emitted.add(run=mu.i[emit, _RUN], epoch=np.full(len(emit), ix.epochs[k]), track_id=mu.i[emit, _ID],
                        x=oe.x, var=oe.var, cov=full_cov(oe).reshape(-1, 36), nu=inn.nu[emit], nis=inn.nis[emit],
                        upd=upd, alt=mu.f[emit, _ALT],
                        tid=plots.tid[safe[emit]], probs=oe.probs)

        # --- new tentatives from the plots no track or confirmation took
        newp = np.flatnonzero(opens)
        rn = plots.rm[newp]
        sn = filt.init(plots.zm[newp], rn if filt.full_r else np.einsum("bii->bi", rn)) if len(newp) else {}
        mn = _Objects.new(plots.run[newp], t, plots.z[newp], plots.r[newp, 2], plots.uid[newp], plots.alt[newp])
        mn.f[:, _T] = t - plots.age[newp]
        kept = np.flatnonzero(keep)
        state = _join_states(_take_state(state, idle, len(objs)) if len(idle) else {},
                             _take_state(su, kept, len(idx)) if len(idx) else {}, sn)
        objs = _Objects.concat(objs.take(idle) if len(idle) else _Objects.empty(), mu.take(kept), mn)

    return emitted, _Bank(f=objs.f, i=objs.i, next_id=next_id, filt_state=state)


def _resolve_conflicts(got: NDArray, cost: NDArray, root: NDArray, uid2: NDArray) -> NDArray:
    """Among confirming hypotheses, keep the cheapest per scan-1 plot, then per scan-2 plot."""
    if len(got) < 2:
        return got
    order = np.argsort(cost, kind="stable")
    got, root, uid2 = got[order], root[order], uid2[order]
    _, first = np.unique(root, return_index=True)
    sel = np.sort(first)
    got, uid2 = got[sel], uid2[sel]
    _, first = np.unique(uid2, return_index=True)
    return np.sort(got[np.sort(first)])


# --------------------------------------------------------------------------- state and step (windowed engine)


@dataclass(frozen=True)
class _Bank:
    """One filter's tracker over every batch run of a :class:`TrackState`.

    ``f``/``i``: the objects (stage-1 tentatives, scan-2 hypotheses, confirmed tracks) as the
    packed rows of ``_Objects`` — times in float seconds since ``TrackState.origin_us``,
    ``_RUN`` = batch run index, track ids, miss/hit/scan counters, the uids of their scan-1 and
    scan-2 plots; ``filt_state``: the filter bank :data:`State` of the same objects (object axis
    first, same order); ``next_id``: the next track id of every batch run."""

    f: NDArray
    i: NDArray
    next_id: NDArray
    filt_state: State

    @staticmethod
    def empty() -> "_Bank":
        return _Bank(np.zeros((0, _NF)), np.zeros((0, _NI), np.int64), np.zeros(0, np.int64), {})


@dataclass(frozen=True)
class TrackState:
    """What the secondary tracker carries from one window to the next (picklable).

    * ``keys``: the batch runs as natural keys ``(fusion method, run)``, in order of first
      appearance (sorted within a window); position j is batch run index j of every bank.
    * ``banks``: per filter name, its :class:`_Bank` (objects, filter state, next ids).
    * ``origin_us``: int µs since the Unix epoch, the fixed origin of the banks' float object
      times (set by the first window holding plots to its first epoch unless given to
      :func:`init_track_state`). Object times stay float seconds since this fixed origin
      because a measurement time (epoch − ``age_s``) is not a whole µs, and float seconds since
      1970 resolve only ~0.2 µs (dt off by ~1e-7 relative).
    * ``next_uid``: the uid of the next plot (hypotheses are told apart by their plots' uids).
    * ``reached_us``: end (t1_us) of the last window stepped, None before the first.
    """

    keys: tuple[tuple[str, int], ...]
    banks: dict[str, _Bank]
    origin_us: int | None = None
    next_uid: int = 0
    reached_us: int | None = None


Filters = dict[str, TrackFilter] | list[str] | tuple[str, ...]


def _filter_dict(filters: Filters) -> dict[str, TrackFilter]:
    return dict(filters) if isinstance(filters, dict) else {name: make_filter(name) for name in filters}


def init_track_state(filters: Filters, origin_us: int | None = None) -> TrackState:
    """The empty tracker state (before the first window) for ``filters`` (names or name →
    filter, as :func:`track_step` will get them). ``origin_us``: the origin of the object
    times; None (recommended) takes the first epoch with plots, as :func:`track_methods` does,
    so a windowed run equals the whole-run call bit for bit."""
    return TrackState(keys=(), banks={name: _Bank.empty() for name in _filter_dict(filters)},
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
    filters = _filter_dict(filters)
    if set(filters) != set(state.banks):
        raise ValueError(f"track_step got filters {sorted(filters)}, the state holds {sorted(state.banks)}")
    if t1_us < t0_us or (state.reached_us is not None and t0_us < state.reached_us):
        raise ValueError(f"window [{t0_us}, {t1_us}) µs is not after the state's end {state.reached_us} µs")
    rows = _window_rows(fused, t0_us, t1_us)
    if rows.height == 0:
        return pl.DataFrame(schema=TRACK_COLUMNS), replace(state, reached_us=int(t1_us))
    run, keys = _batch_runs(rows, state.keys)
    ix = _PlotIndex(rows.with_columns(pl.Series("run", run)), state.next_uid)
    origin = int(ix.epochs[0]) if state.origin_us is None else state.origin_us
    names = sorted({m for m, _ in keys})
    runs = np.array([r for _, r in keys], np.int64)
    run_method = np.array([names.index(m) for m, _ in keys], np.int64)
    banks, per_filter = {}, {}
    for name, filt in filters.items():
        emitted, banks[name] = _track_batch(ix, filt, cfg, state.banks[name], len(keys), origin)
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
    filters = _filter_dict(filters)
    _check_fused(fused)
    rows = _drop_tentative(fused)
    if rows.height == 0 or not filters:
        return pl.DataFrame(schema=TRACK_COLUMNS)
    us = rows["epoch"].cast(TIME).dt.epoch("us")
    tracks, _ = track_step(init_track_state(filters), rows, filters, cfg, int(us.min()), int(us.max()) + 1)
    return tracks
