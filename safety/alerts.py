"""STCA performance against what really happened: losses of separation in the truth, alert
episodes per pair of aircraft, genuine / nuisance / false alerts, warning time, trade-off curves.

Inputs
------
* ``conflicts`` — :func:`safety.conflicts.predict_conflicts` on one or more pictures (column
  ``method`` names the picture); only ``alert`` rows are used.
* ``id_map`` — (run, epoch, ``id_col``, truth_id[, method]): which aircraft each picture id is
  at each epoch (the matcher's ``gated_truth_id``, :func:`tertiary.evaluation.matching.match_to_reference`).
  Its epochs, with the alert epochs, form the picture's **epoch grid** per (run, method).
* ``truth`` — (truth_id, time, x_m … vz_mps[, run][, alt_m]) in the system ENU frame; without
  ``run`` it is shared by all runs (Monte-Carlo). Heights: ``alt_m`` where present, else the
  geodetic height of the ENU position in ``frame`` (:func:`safety.conflicts.height_and_rate`).

Loss of separation (the default truth) — :func:`loss_of_separation`
---------------------------------------------------------------------
A pair of aircraft loses separation while horizontal distance < Δr_г **and** |Δh| < Δr_в at
the same instant. Between consecutive truth sample times (the union over all aircraft of a
run) every aircraft moves linearly, so within each such segment the pair's horizontal distance
is a quadratic and its height difference linear in t: the LoS part of the segment is the
intersection of two intervals, in closed form (:func:`safety.conflicts.conflict_interval`), no
sampling step. Segments are paired by a KD-tree on their mid points (box half-width = minimum
+ the segments' lengths), intervals of a pair that touch or are at most ``merge_gap_s`` apart
(the alerts' gap, 15 s) are merged — separation regained for a second in the middle of one
encounter is not a second loss: one **LoS episode** = (run, truth_a, truth_b, t_start,
t_end). *Proximity* intervals are the same with both minima × the ``proximity_factor`` (1.5).
The grid is resampled a block of consecutive union times at a time (a segment pair lies in one
union interval, so the blocks' intervals are the whole grid's), and each block is bounded before
it is allocated (``max_grid_rows``, :class:`tertiary.core.errors.ResourceError`).

Level pairs (``AlertConfig.level_pairs``, default on). Two aircraft in level flight at levels
the vertical minimum apart are separated by their levels — the principle the prediction's
level-pair threshold applies (:mod:`safety.conflicts`, "Level pairs"), and how a controller reads
it: reported altitudes of aircraft at adjacent levels differ by 1 000 ft ± the 25 ft / 100 ft
Mode S / Mode C quantum and altimetry error, and 975 ft on the display is not a loss. So on a
segment where both aircraft are level (|ḣ| ≤ ``level_rate_mps`` at both ends, ḣ the truth's
``alt_rate_mps`` — the aircraft's own vertical rate, not the slope of a quantised altitude —
else the segment's slope) the vertical minimum is reduced by ``level_pair_tolerance_m``
(100 ft), both from the prediction's :class:`~safety.conflicts.ConflictConfig`. A level bust
(100–250 ft under the occupied level) stays a loss; a pair where either aircraft climbs or
descends keeps the full minimum. Measured on real traffic (``adsb-paris``, 2021-10-07): without
it, pairs at adjacent levels on CDG's approaches made 36 of the 45 "loss" episodes, each a
second or two long whenever one aircraft's altitude flipped by 25 ft.

Alert episodes — :func:`alert_episodes` (the ``alerts`` table)
-------------------------------------------------------------
Alert rows are keyed by the pair of **aircraft**: each picture id pair (run, method, id_a,
id_b) maps to the truth pair that the majority of its alert rows map to (id_map at each row's
epoch), so fragmented or swapped ids cannot inflate episodes; id pairs without two distinct
truths keep their ids (``truth_a``/``truth_b`` null) and can only be false alerts. An episode is
a maximal sequence of alert epochs of one key whose consecutive alert epochs are adjacent on
the grid or at most ``merge_gap_s`` apart; **flicker** counts the dropouts inside it (alert
epochs not adjacent on the grid). With link window W = [t_start, max(t_end + ``link_s``,
t_cpa)] (``link_s`` default T^пор; t_cpa the latest closest approach its alert epochs
predicted, each at most ``max_link_s`` (default 2 T^пор) after its epoch), an episode is

* **genuine** — a LoS episode of that pair overlaps W (it follows or is under way);
* **nuisance** — no LoS, but a proximity interval of the pair overlaps W;
* **false** — neither (also every alert without two distinct truths).

Why W reaches the predicted closest approach: an alert is raised when the pair is predicted to
enter the threshold, widened by the estimation term, within T^пор; on a converging pair with a
still-uncertain track (minutes after it appears) that entry comes well before the pair is
closest. A pair that then passes at 1.3× the minimum 2 min later, or loses separation 2.5 min
later, was the encounter the alert named: a fixed window of T^пор after the alert called such
alerts false ("nothing close"), which they are not (``link_to_cpa=False`` restores it).

Alert epochs outside the truth's time span (e.g. tracks coasting after the recording's
reference ends) are not scored: there is nothing to judge them by.

LoS episodes — :func:`los_episodes`
----------------------------------
Every LoS episode overlapping a picture's time span (per run) is **alerted** when an alert
episode of that pair in that picture overlaps it within the link window (a.t_start ≤ los.t_end
and the end of the alert's W ≥ los.t_start), else **missed**; warning time = LoS start − the earliest
such alert start (negative when the alert came after the LoS began).

Metrics — :func:`score_alerts` (``metrics`` schema, stage ``"safety"``, per picture)
----------------------------------------------------------------------------------
``los_episodes``, ``alerted_los``, ``missed_los``, ``genuine_alerts``, ``nuisance_alerts``,
``false_alerts``, ``alert_episodes``, ``alerts_per_hour`` (alert episodes per hour of picture
time, summed over runs), ``nuisance_false_per_hour``, ``warning_median_s``, ``warning_p05_s``
(5th percentile; over alerted LoS), ``alert_duration_median_s``, ``flicker_per_alert``,
``picture_hours``. NaN where undefined.

Trade-off — :func:`stca_tradeoff`, :func:`compare_at_equal_nuisance`
-------------------------------------------------------------------
The fraction of LoS episodes alerted with ≥ X s warning against nuisance + false alerts per
hour, as the threshold confidence (covariance thresholds) or the fixed estimation term, and the
look-ahead vary; the two threshold families compared at equal nuisance + false rate.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from safety.conflicts import (AerodromeZone, ConflictConfig, conflict_interval, conflicts_steps, height_and_rate,
                              init_conflict_state, predict_conflicts, zone_index)
from tertiary.core import geo
from tertiary.core.errors import ResourceError
from tertiary.contract.schema import TABLES, TIME

__all__ = [
    "AlertConfig",
    "ALERT_METRICS",
    "ALERTS_SCHEMA",
    "LOS_SCHEMA",
    "truth_heights",
    "separation_intervals",
    "loss_of_separation",
    "truth_intervals",
    "alert_episodes",
    "los_episodes",
    "score_alerts",
    "stca_tables",
    "stca_tradeoff",
    "compare_at_equal_nuisance",
    "tradeoff_metrics",
]

_US = 1_000_000
ALERT_METRICS = ("los_episodes", "alerted_los", "missed_los", "genuine_alerts", "nuisance_alerts", "false_alerts",
                 "alert_episodes", "alerts_per_hour", "nuisance_false_per_hour", "warning_median_s",
                 "warning_p05_s", "alert_duration_median_s", "flicker_per_alert", "picture_hours")
#: the ``alerts`` table: one row per alert episode
ALERTS_SCHEMA: dict[str, pl.DataType] = dict(TABLES["alerts"].required)   # columns: tertiary.contract.schema
#: one row per loss-of-separation episode and picture
LOS_SCHEMA: dict[str, pl.DataType] = {
    "run": pl.UInt32(), "method": pl.String(), "truth_a": pl.Int64(), "truth_b": pl.Int64(), "t_start": TIME,
    "t_end": TIME, "alerted": pl.Boolean(), "first_alert": TIME, "warning_s": pl.Float64(),
}


@dataclass(frozen=True)
class AlertConfig:
    """Scoring options (see the module docstring).

    * ``conflict``: the prediction settings of the picture (minima Δr_г, Δr_в and T^пор).
    * ``proximity_factor``: a nuisance alert's pair came within this × both minima (1.5).
    * ``merge_gap_s``: alert epochs of one pair at most this far apart belong to one episode
      (the dropout is flicker); likewise the truth's loss (and proximity) intervals of a pair.
    * ``link_s``: how long after an alert episode ends a LoS still makes it genuine / alerted
      (None: T^пор).
    * ``link_to_cpa``: the link window also reaches the closest approach each alert epoch
      predicted (its ``t_min_s``), at most ``max_link_s`` (None: 2 T^пор) after that epoch: an
      alert raised when the pair enters the (uncertainty-widened) threshold within T^пор is about
      the encounter it predicted, which can come after T^пор (module docstring). False: the
      fixed window only.
    * ``max_grid_rows``: bound of the resampled truth rows held at once (aircraft × union sample
      times of a block of them; :func:`_resampled_blocks`).
    * ``level_pairs``: the truth's losses and proximities use the prediction's level-pair
      threshold (``conflict.level_pair_tolerance_m`` / ``level_rate_mps``) where both aircraft
      are level (module docstring "Level pairs"); False: the full vertical minimum everywhere.
    """

    conflict: ConflictConfig = ConflictConfig()
    proximity_factor: float = 1.5
    merge_gap_s: float = 15.0
    link_s: float | None = None
    link_to_cpa: bool = True
    max_link_s: float | None = None
    max_grid_rows: int = 50_000_000
    level_pairs: bool = True

    def __post_init__(self) -> None:
        if not self.proximity_factor >= 1.0:
            raise ValueError(f"proximity_factor must be >= 1, got {self.proximity_factor}")
        if self.merge_gap_s < 0:
            raise ValueError(f"merge_gap_s must be >= 0, got {self.merge_gap_s}")
        if self.link_s is not None and self.link_s < 0:
            raise ValueError(f"link_s must be >= 0, got {self.link_s}")
        if self.max_link_s is not None and self.max_link_s < 0:
            raise ValueError(f"max_link_s must be >= 0, got {self.max_link_s}")
        if self.max_grid_rows < 1:
            raise ValueError(f"max_grid_rows must be >= 1, got {self.max_grid_rows}")

    @property
    def link(self) -> float:
        return self.conflict.t_thr_s if self.link_s is None else float(self.link_s)

    @property
    def truth_level_pairs(self) -> tuple[float, float] | None:
        """(tolerance m, level rate m/s) of the truth's level pairs, None when off."""
        tol = self.conflict.level_pair_tolerance_m
        return None if not self.level_pairs or tol is None else (float(tol), float(self.conflict.level_rate_mps))

    @property
    def cpa_reach(self) -> float:
        """How far after an alert epoch its predicted closest approach can extend the link
        window (0 without ``link_to_cpa``)."""
        if not self.link_to_cpa:
            return 0.0
        return 2.0 * self.conflict.t_thr_s if self.max_link_s is None else float(self.max_link_s)


# --------------------------------------------------------------------------- truth: heights, intervals


def _micros(col: str) -> pl.Expr:
    """Microseconds since the Unix epoch of a time column (exact integers)."""
    return pl.col(col).cast(TIME).dt.epoch("us").cast(pl.Int64)


#: truth samples converted to geodetic height at a time (:func:`truth_heights`)
_HEIGHT_BLOCK = 262_144


def truth_heights(truth: pl.DataFrame, frame: geo.LocalFrame | None = None) -> pl.DataFrame:
    """([run,] truth_id, t_us, x_m, y_m, h_m, hdot_mps) sorted by ([run,] truth_id, t_us):
    horizontal on the system tangent plane, h = ``alt_m`` where present (not null), else the
    geodetic height of the ENU position (:func:`safety.conflicts.height_and_rate`); ḣ the
    truth's ``alt_rate_mps`` where present, else NaN (unknown)."""
    need = ["truth_id", "time", "x_m", "y_m", "z_m"]
    missing = [c for c in need if c not in truth.columns]
    if missing:
        raise ValueError(f"truth: missing column(s) {', '.join(missing)}")
    keys = ["run"] if "run" in truth.columns else []
    run = [pl.col("run").cast(pl.UInt32)] if keys else []
    tr = truth.select(*run, pl.col("truth_id").cast(pl.Int64),
                      _micros("time").alias("t_us"), *[pl.col(c).cast(pl.Float64) for c in ("x_m", "y_m", "z_m")],
                      *([pl.col("alt_m").cast(pl.Float64)] if "alt_m" in truth.columns else []),
                      *([pl.col("alt_rate_mps").cast(pl.Float64)] if "alt_rate_mps" in truth.columns else []))
    tr = tr.sort([*keys, "truth_id", "t_us"])
    pos = tr.select("x_m", "y_m", "z_m").to_numpy()
    # in blocks: the geodetic conversion's scratch is that of a block, not of the whole truth
    h = np.empty(len(pos))
    for lo in range(0, len(pos), _HEIGHT_BLOCK):
        block = pos[lo:lo + _HEIGHT_BLOCK]
        h[lo:lo + len(block)] = height_and_rate(block, np.zeros_like(block), frame)[0]
    if "alt_m" in tr.columns:
        alt = tr["alt_m"].to_numpy()
        h = np.where(np.isfinite(alt), alt, h)
    if not np.all(np.isfinite(pos)) or not np.all(np.isfinite(h)):
        raise ValueError("truth: positions and heights must be finite")
    rate = (tr["alt_rate_mps"].fill_null(np.nan).to_numpy() if "alt_rate_mps" in tr.columns
            else np.full(tr.height, np.nan))
    return tr.select(*keys, "truth_id", "t_us", "x_m", "y_m").with_columns(pl.Series("h_m", h),
                                                                           pl.Series("hdot_mps", rate))


#: resampled truth rows held at once (:func:`_resampled_blocks`): the national hour's grid of
#: 5 M rows took 1.4 GB over its truth when resampled whole (memory, issue 18)
RESAMPLE_ROWS = 1_000_000


def _resampled_blocks(tr: pl.DataFrame, max_rows: int, rows: int = RESAMPLE_ROWS) -> Iterator[dict[str, NDArray]]:
    """Every aircraft at every union sample time of its run within its own span (linear
    interpolation between its samples), a block of consecutive union times at a time: rows
    ordered by (aircraft, time) in a block, blocks of one run in time order, each sharing its
    first union time with the previous block's last, so that every segment between two
    consecutive union times of an aircraft lies in exactly one block. A block holds at most
    ``min(rows, max_rows)`` rows; two consecutive union times needing more than ``max_rows``
    raise before anything is allocated. ``ac`` indexes the run's aircraft in ``tid``/``run``;
    ``gk`` is the union-time index within the run."""
    run = tr["run"].to_numpy().astype(np.int64) if "run" in tr.columns else np.zeros(tr.height, np.int64)
    tid = tr["truth_id"].to_numpy()
    t = tr["t_us"].to_numpy()
    xyz = tr.select("x_m", "y_m", "h_m").to_numpy()
    rate = tr["hdot_mps"].to_numpy() if "hdot_mps" in tr.columns else None
    del tr
    new_ac = np.ones(len(t), bool)
    new_ac[1:] = (run[1:] != run[:-1]) | (tid[1:] != tid[:-1])
    ac_start = np.flatnonzero(new_ac)
    ac_end = np.append(ac_start[1:], len(t))
    ac_run = run[ac_start]
    # the sample interval of each row: search within the aircraft's own samples (a packed key)
    span = int(t.max() - t.min()) + 1 if len(t) else 1
    if len(ac_start) * span >= 1 << 62:
        raise ResourceError("truth: time span too long for the packed interpolation key")
    key_s = np.repeat(np.arange(len(ac_start)), ac_end - ac_start) * span + (t - t.min())
    cap = max(min(int(rows), int(max_rows)), 1)
    for r in np.unique(ac_run):
        acs = np.flatnonzero(ac_run == r)                          # the run's aircraft, consecutive
        u = np.unique(t[ac_start[acs[0]]:ac_end[acs[-1]]])
        lo = np.searchsorted(u, t[ac_start[acs]], "left")          # the aircraft spans u[lo:hi]
        hi = np.searchsorted(u, t[ac_end[acs] - 1], "right")
        alive = np.cumsum(np.bincount(lo, minlength=len(u) + 1) - np.bincount(hi, minlength=len(u) + 1))[:-1]
        before = np.concatenate([[0], np.cumsum(alive)])           # rows of u[:i]
        i0 = 0
        while i0 < len(u) - 1:
            # the last union time whose block from i0 holds at most ``cap`` rows, at least i0 + 1
            i1 = max(int(np.searchsorted(before, before[i0] + cap, "right")) - 2, i0 + 1)
            i1 = min(i1, len(u) - 1)
            need = int(before[i1 + 1] - before[i0])
            if need > max_rows:
                raise ResourceError(f"truth: resampling {int(alive[i0:i1 + 1].max())} aircraft at two consecutive "
                                    f"union sample times needs {need} rows > max_grid_rows={max_rows} (AlertConfig)")
            sel = np.flatnonzero((lo <= i1) & (hi > i0))
            klo, khi = np.maximum(lo[sel], i0), np.minimum(hi[sel], i1 + 1)
            cnt = khi - klo
            total = int(cnt.sum())
            ac = np.repeat(acs[sel], cnt)
            k = np.repeat(klo, cnt) + (np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt))
            tt = u[k]
            j = np.searchsorted(key_s, ac * span + (tt - t.min()), "right") - 1
            j = np.clip(j, ac_start[ac], np.maximum(ac_end[ac] - 2, ac_start[ac]))
            j1 = np.minimum(j + 1, ac_end[ac] - 1)
            dt = (t[j1] - t[j]).astype(np.float64)
            w = np.where(dt > 0, (tt - t[j]) / np.where(dt > 0, dt, 1.0), 0.0)
            out = {"ac": ac, "gk": k, "t": tt, "pos": xyz[j] + w[:, None] * (xyz[j1] - xyz[j]),
                   "tid": tid[ac_start], "run": ac_run}
            if rate is not None:
                out["hdot"] = rate[j] + w * (rate[j1] - rate[j])
            del j, j1, dt, w
            yield out
            i0 = i1


#: union sample intervals per box of the loss-of-separation screen: each aircraft's segments in
#: a block of this many intervals are boxed together, so the KD-tree holds (aircraft, block)
#: boxes instead of segments (on the national hour's 1 Hz truth the tree of 5 M segments took
#: 16.5 s; see :func:`_pair_segments`)
SCREEN_BLOCK = 32


def _pair_segments(rs: dict[str, NDArray], reach_h: float, reach_v: float, block: int = SCREEN_BLOCK
                   ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Candidate pairs (row indices of segment starts) of segments in the same (run, union
    interval) that may come within (reach_h, reach_v): a superset of the pairs whose two
    segments' bounding boxes are that close (the exact test follows in the caller).

    Screen in two steps. (1) Boxes: the segments of one aircraft in one block of ``block``
    union intervals (consecutive rows, consecutive intervals) are boxed; a KD-tree on the box
    centres (Chebyshev, the block index as a fourth coordinate far apart) pairs boxes of one
    block whose gaps are within the reach — the widest 1 % of boxes (gaps in ADS-B truth, fast
    aircraft) queried one by one with their own radius. (2) Segments: each box pair is expanded
    to its segments in the same union intervals, kept when the two segments' own boxes are
    within the reach. Two segments within reach lie in boxes within reach, so nothing the
    exact test would find is screened out."""
    ac, gk, pos = rs["ac"], rs["gk"], rs["pos"]
    none = np.zeros(0, np.int64), np.zeros(0, np.int64)
    seg = np.flatnonzero(ac[1:] == ac[:-1])                       # row s → s + 1 of one aircraft
    if len(seg) < 2:
        return none
    s_lo = np.minimum(pos[seg], pos[seg + 1])
    s_hi = np.maximum(pos[seg], pos[seg + 1])
    blk = gk[seg] // max(int(block), 1)
    new = np.ones(len(seg), bool)
    new[1:] = (ac[seg[1:]] != ac[seg[:-1]]) | (blk[1:] != blk[:-1])
    first = np.flatnonzero(new)                                   # box k: segments first[k] .. last[k]
    last = np.append(first[1:], len(seg)) - 1
    lo = np.minimum.reduceat(s_lo, first, axis=0)
    hi = np.maximum.reduceat(s_hi, first, axis=0)
    i, j = _near_boxes(0.5 * (lo + hi), 0.5 * (hi - lo), blk[first].astype(np.float64), reach_h, reach_v)
    if not len(i):
        return none
    ok = _within(lo[i], hi[i], lo[j], hi[j], reach_h, reach_v)
    i, j = i[ok], j[ok]
    # the union intervals both boxes cover (each box's are consecutive, from gk of its first)
    g0i, g0j = gk[seg[first[i]]], gk[seg[first[j]]]
    g_lo = np.maximum(g0i, g0j)
    n = np.maximum(np.minimum(gk[seg[last[i]]], gk[seg[last[j]]]) - g_lo + 1, 0)
    k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    a = np.repeat(first[i] + g_lo - g0i, n) + k                  # indices into seg
    b = np.repeat(first[j] + g_lo - g0j, n) + k
    keep = _within(s_lo[a], s_hi[a], s_lo[b], s_hi[b], reach_h, reach_v)
    return seg[a[keep]], seg[b[keep]]


def _within(lo_a: NDArray, hi_a: NDArray, lo_b: NDArray, hi_b: NDArray, reach_h: float, reach_v: float
            ) -> NDArray[np.bool_]:
    """Whether axis-aligned boxes (rows: x, y, height) are within (reach_h, reach_v) per axis."""
    gap = np.maximum(np.maximum(lo_b - hi_a, lo_a - hi_b), 0.0)
    return (gap[:, 0] <= reach_h) & (gap[:, 1] <= reach_h) & (gap[:, 2] <= reach_v)


def _near_boxes(c: NDArray, e: NDArray, blk: NDArray, reach_h: float, reach_v: float
                ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Pairs (i < j not required) of boxes (centres ``c``, half sizes ``e``) of one block whose
    centres are within reach + both half sizes on every axis: one KD-tree query for the bulk of
    the boxes, one query each for the widest 1 %."""
    eh, ev = np.maximum(e[:, 0], e[:, 1]), e[:, 2]
    qh, qv = float(np.quantile(eh, 0.99)), float(np.quantile(ev, 0.99))
    bulk = (eh <= qh) & (ev <= qv)
    rh, rv = reach_h + 2 * qh, reach_v + 2 * qv
    s = rh / rv
    big_h = reach_h + 2 * float(eh.max())
    sep = 4.0 * (big_h + (reach_v + 2 * float(ev.max())) * s) + 1.0
    pad = 1.0 + 1e-9 * (float(np.abs(c).max()) + sep * float(blk.max() + 1))
    pts = np.column_stack([c[:, 0], c[:, 1], c[:, 2] * s, blk * sep])
    bi = np.flatnonzero(bulk)
    pr = cKDTree(pts[bi]).query_pairs(rh + pad, p=np.inf, output_type="ndarray")
    a, b = [bi[pr[:, 0]]], [bi[pr[:, 1]]]
    wi = np.flatnonzero(~bulk)
    if len(wi):
        rad = np.maximum(reach_h + eh[wi] + eh.max(), (reach_v + ev[wi] + ev.max()) * s) + pad
        hits = cKDTree(pts).query_ball_point(pts[wi], rad, p=np.inf, return_sorted=False)
        cnt = np.fromiter((len(x) for x in hits), np.int64, len(wi))
        jj = np.concatenate([np.asarray(x, np.int64) for x in hits]) if cnt.sum() else np.zeros(0, np.int64)
        ii = np.repeat(wi, cnt)
        keep = (ii != jj) & (bulk[jj] | (ii < jj))                # wide–wide pairs come twice
        a.append(ii[keep])
        b.append(jj[keep])
    return np.concatenate(a), np.concatenate(b)


def separation_intervals(truth: pl.DataFrame, dr_h_m: float, dr_v_m: float, factors: Sequence[float] = (1.0,),
                         frame: geo.LocalFrame | None = None, max_rows: int = 50_000_000,
                         level_pairs: tuple[float, float] | None = None, merge_gap_s: float = 0.0,
                         enroute: tuple[float, float, float] | None = None,
                         zones: Sequence[AerodromeZone] = (),
                         clip_us: tuple[int, int] | None = None) -> list[pl.DataFrame]:
    """For each factor f: the merged intervals during which pairs of aircraft are within
    f·Δr_г horizontally **and** f·Δr_в vertically at the same instant, exact under linear
    motion between the union sample times (see the module docstring). ``level_pairs`` =
    (tolerance m, level rate m/s): on segments where both aircraft are level the vertical bound
    is f·Δr_в − tolerance (module docstring "Level pairs"). ``enroute`` = (floor m, Δr_г m,
    Δr_в m): a segment pair with any of its four end heights at or above the floor is judged by
    these minima instead (:mod:`safety.conflicts`, "En-route airspace"). ``zones``: aerodrome
    zones; a segment pair whose four ends are in one zone is not a loss (:mod:`safety.conflicts`,
    "Aerodrome zones"). Intervals of a pair at
    most ``merge_gap_s`` apart are one episode. ``clip_us`` = [lo, hi) µs: only the part of each
    segment pair's interval inside it, cut before merging (a time chunk of a long truth:
    :func:`merge_intervals` of the chunks' frames is then the whole truth's). One frame per
    factor: (run, truth_a, truth_b, t_start_us, t_end_us), truth_a < truth_b (run 0 without a
    run column)."""
    tr = truth_heights(truth, frame)
    out_schema = {"run": pl.UInt32, "truth_a": pl.Int64, "truth_b": pl.Int64, "t_start_us": pl.Int64,
                  "t_end_us": pl.Int64}
    empty = [pl.DataFrame(schema=out_schema) for _ in factors]
    if tr.height < 2:
        return empty
    fmax = max(factors)
    reach_h, reach_v = (dr_h_m, dr_v_m) if enroute is None else (max(dr_h_m, enroute[1]), max(dr_v_m, enroute[2]))
    pieces: list[list[tuple[NDArray, ...]]] = [[] for _ in factors]
    # a block of union sample times at a time: a segment pair lies in one union interval, so the
    # blocks' pieces are the whole grid's (memory, issue 18)
    blocks = _resampled_blocks(tr, max_rows)
    del tr                        # the blocks hold its columns as arrays, not the frame too
    for rs in blocks:
        for got, f_pieces in zip(_block_pieces(rs, fmax * reach_h, fmax * reach_v, dr_h_m, dr_v_m, factors,
                                               level_pairs, enroute, zones), pieces):
            f_pieces.append(got)
        del rs
    gap_us = int(round(merge_gap_s * _US))
    return [_merge(*_clipped([np.concatenate([p[k] for p in f_pieces]) for k in range(5)], clip_us), out_schema,
                   gap_us)
            if f_pieces else pl.DataFrame(schema=out_schema) for f_pieces in pieces]


def _clipped(cols: list[NDArray], clip_us: tuple[int, int] | None) -> list[NDArray]:
    """Pieces (run, truth_a, truth_b, start µs, end µs) cut to [lo, hi); empty ones dropped."""
    if clip_us is None:
        return cols
    s, e = np.maximum(cols[3], clip_us[0]), np.minimum(cols[4], clip_us[1])
    keep = e > s
    return [cols[0][keep], cols[1][keep], cols[2][keep], s[keep], e[keep]]


def merge_intervals(chunks: Sequence[tuple[pl.DataFrame, pl.DataFrame]], cfg: AlertConfig = AlertConfig()
                    ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The (LoS, proximity) intervals of a truth from those of its time chunks
    (:func:`truth_intervals` with ``clip_us`` over a partition of its time span): each pair's
    intervals merged again by the same rule, so an episode cut at a chunk's edge is one again
    and the result is the whole truth's (exact: a partition's pieces cover what the whole's do)."""
    gap_us = int(round(cfg.merge_gap_s * _US))
    out = []
    for k in range(2):
        frames = [c[k] for c in chunks if c[k].height]
        if not frames:
            out.append(chunks[0][k].clear() if chunks else pl.DataFrame())
            continue
        f = pl.concat(frames)
        out.append(_merge(*(f[c].to_numpy() for c in ("run", "truth_a", "truth_b", "t_start_us", "t_end_us")),
                          f.schema, gap_us))
    return out[0], out[1]


def _block_pieces(rs: dict[str, NDArray], reach_h: float, reach_v: float, dr_h_m: float, dr_v_m: float,
                  factors: Sequence[float], level_pairs: tuple[float, float] | None,
                  enroute: tuple[float, float, float] | None, zones: Sequence[AerodromeZone]
                  ) -> list[tuple[NDArray, ...]]:
    """Per factor, (run, truth_a, truth_b, start µs, end µs) of every segment pair of one
    resampled block within the factor's minima (before merging), exact under linear motion."""
    none = (np.zeros(0, np.uint32), *[np.zeros(0, np.int64)] * 4)
    a, b = _pair_segments(rs, reach_h, reach_v)
    same = rs["gk"][a] == rs["gk"][b]
    a, b = a[same], b[same]
    if len(zones) and len(a):
        # two aircraft both in one aerodrome zone over the whole segment: aerodrome control
        z = zone_index(rs["pos"], zones)
        za = z[a]
        inside = (za >= 0) & (z[a + 1] == za) & (z[b] == za) & (z[b + 1] == za)
        a, b = a[~inside], b[~inside]
    if not len(a):
        return [none for _ in factors]
    pos, t, ac = rs["pos"], rs["t"], rs["ac"]
    if enroute is not None:
        low = np.maximum(np.maximum(pos[a, 2], pos[a + 1, 2]), np.maximum(pos[b, 2], pos[b + 1, 2])) < enroute[0]
        dr_h_m, dr_v_m = np.where(low, dr_h_m, enroute[1]), np.where(low, dr_v_m, enroute[2])
    dt = (t[a + 1] - t[a]).astype(np.float64) / _US
    r0 = pos[b] - pos[a]
    w = ((pos[b + 1] - pos[a + 1]) - r0) / dt[:, None]
    ta_, tb_ = rs["tid"][ac[a]], rs["tid"][ac[b]]
    run = rs["run"][ac[a]].astype(np.uint32)
    tol = 0.0 if level_pairs is None else np.where(_both_level(rs, a, b, dt, level_pairs[1]), level_pairs[0], 0.0)
    out = []
    for f in factors:
        # closed ≤ in the interval, strict < for LoS: they differ on a null set (t_out > t_in)
        t_in, t_out = _segment_interval(r0, w, f * dr_h_m, f * dr_v_m - tol, dt)
        ok = t_out > t_in
        s_us = t[a][ok] + np.round(t_in[ok] * _US).astype(np.int64)
        e_us = t[a][ok] + np.round(t_out[ok] * _US).astype(np.int64)
        out.append((run[ok], np.minimum(ta_, tb_)[ok].astype(np.int64), np.maximum(ta_, tb_)[ok].astype(np.int64),
                    s_us, e_us))
    return out


def _both_level(rs: dict[str, NDArray], a: NDArray, b: NDArray, dt: NDArray, level_rate: float) -> NDArray[np.bool_]:
    """Per segment pair: both aircraft level, |ḣ| ≤ ``level_rate`` at both ends of the segment
    (the truth's own rate; where unknown, the segment's height slope)."""
    pos = rs["pos"]
    hdot = rs.get("hdot")

    def level(s: NDArray) -> NDArray[np.bool_]:
        slope = np.abs(pos[s + 1, 2] - pos[s, 2]) / dt
        if hdot is None:
            return slope <= level_rate
        rate = np.maximum(np.abs(hdot[s]), np.abs(hdot[s + 1]))        # NaN where either end is unknown
        return np.where(np.isfinite(rate), rate <= level_rate, slope <= level_rate)
    return level(a) & level(b)


def _segment_interval(r0: NDArray, w: NDArray, d_h: float | NDArray, d_v: float | NDArray, dt: NDArray
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The part [t_in, t_out] ⊂ [0, dt] (per segment) where |r0_h + w_h s| ≤ d_h and
    |r0_z + w_z s| ≤ d_v (:func:`safety.conflicts.conflict_interval` with v = −w and a
    per-segment horizon)."""
    t_in, t_out = conflict_interval(r0[:, 0], r0[:, 1], -w[:, 0], -w[:, 1], r0[:, 2], w[:, 2], d_h, d_v,
                                    np.inf, eps=1e-9)
    return t_in, np.minimum(t_out, dt)


def _merge(run, ta, tb, s_us, e_us, schema, gap_us: int = 0) -> pl.DataFrame:
    """Merge overlapping intervals of each pair, and those at most ``gap_us`` apart, into episodes."""
    if not len(s_us):
        return pl.DataFrame(schema=schema)
    df = pl.DataFrame({"run": run.astype(np.uint32), "truth_a": ta, "truth_b": tb, "s": s_us, "e": e_us})
    df = df.sort("run", "truth_a", "truth_b", "s")
    key = ["run", "truth_a", "truth_b"]
    prev_end = pl.col("e").cum_max().shift(1).over(key)
    new_ep = prev_end.is_null() | (pl.col("s") > prev_end + max(gap_us, 1))
    df = df.with_columns(new_ep.cum_sum().over(key).alias("__ep"))
    out = df.group_by([*key, "__ep"]).agg(pl.col("s").min().alias("t_start_us"), pl.col("e").max().alias("t_end_us"))
    return out.drop("__ep").sort(key + ["t_start_us"]).cast(schema)


def loss_of_separation(truth: pl.DataFrame, cfg: AlertConfig = AlertConfig(), frame: geo.LocalFrame | None = None
                       ) -> pl.DataFrame:
    """LoS episodes of the truth: ([run,] truth_a, truth_b, t_start, t_end), truth_a < truth_b —
    horizontal < Δr_г and |Δh| < Δr_в at the same instant, closed form between samples."""
    cc = cfg.conflict
    los = separation_intervals(truth, cc.sep_h_m, cc.sep_v_m, (1.0,), frame, cfg.max_grid_rows,
                               cfg.truth_level_pairs, cfg.merge_gap_s, _enroute(cc), cc.aerodrome_zones)[0]
    keys = ["run"] if "run" in truth.columns else []
    return los.select(*keys, "truth_a", "truth_b", _to_time("t_start_us", "t_start"), _to_time("t_end_us", "t_end"))


def _to_time(col: str, name: str) -> pl.Expr:
    return pl.col(col).cast(pl.Datetime("us", "UTC")).alias(name)


def truth_intervals(truth: pl.DataFrame, cfg: AlertConfig = AlertConfig(), frame: geo.LocalFrame | None = None,
                    clip_us: tuple[int, int] | None = None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """(LoS intervals, proximity intervals) of the truth in the internal form of
    :func:`separation_intervals` (compute once, pass to :func:`alert_episodes` & co. as
    ``intervals`` when scoring many pictures or settings); ``clip_us``: of a time chunk
    (:func:`merge_intervals`)."""
    cc = cfg.conflict
    los, prox = separation_intervals(truth, cc.sep_h_m, cc.sep_v_m, (1.0, cfg.proximity_factor), frame,
                                     cfg.max_grid_rows, cfg.truth_level_pairs, cfg.merge_gap_s, _enroute(cc),
                                     cc.aerodrome_zones, clip_us)
    return los, prox


def _enroute(cc: ConflictConfig) -> tuple[float, float, float] | None:
    """(floor, Δr_г, Δr_в) of the en-route airspace of ``cc`` (None: one set of minima)."""
    return None if cc.enroute_above_m is None else (cc.enroute_above_m, cc.enroute_h_m, cc.enroute_v_m)


# --------------------------------------------------------------------------- picture grid and alert rows


def _grid(conflicts: pl.DataFrame, id_map: pl.DataFrame, methods: list[str] | None) -> pl.DataFrame:
    """(run, method, epoch, k, t_us): the picture's epoch grid (id_map epochs ∪ alert epochs),
    dense index k per (run, method)."""
    if "method" in id_map.columns:
        g = id_map.select(pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String), pl.col("epoch").cast(TIME))
    else:
        ms = methods if methods is not None else sorted(conflicts["method"].unique().to_list())
        g = (id_map.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME)).unique()
             .join(pl.DataFrame({"method": ms}, schema={"method": pl.String}), how="cross"))
    c = conflicts.select(pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String), pl.col("epoch").cast(TIME))
    g = pl.concat([g.select("run", "method", "epoch"), c.unique()]).unique()
    return g.sort("run", "method", "epoch").with_columns(
        (pl.col("epoch").rank("dense").over(["run", "method"]).cast(pl.Int64) - 1).alias("k"),
        _micros("epoch").alias("t_us"))


def _alert_rows(conflicts: pl.DataFrame, id_map: pl.DataFrame, id_col: str) -> pl.DataFrame:
    """Alert rows with the pair of aircraft of their id pair: truth_a/truth_b = the truth pair
    that most of the id pair's alert rows map to (null without two distinct truths)."""
    on = ["run", "epoch"] + (["method"] if "method" in id_map.columns else [])
    m = id_map.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                      *([pl.col("method").cast(pl.String)] if "method" in id_map.columns else []),
                      pl.col(id_col).cast(pl.UInt64).alias("__id"), pl.col("truth_id").cast(pl.Int64)
                      ).unique(subset=[*on, "__id"], keep="first")
    opt = [pl.col(c).cast(pl.Float64) if c in conflicts.columns else pl.lit(None, pl.Float64).alias(c)
           for c in ("r_min_m", "dz_min_m", "t_min_s")]
    # select before filtering: the filter then copies a few columns, not the whole table
    a = (conflicts.select("alert", pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                          pl.col("method").cast(pl.String), pl.col("id_a").cast(pl.UInt64),
                          pl.col("id_b").cast(pl.UInt64), *opt)
         .filter(pl.col("alert")).drop("alert"))
    a = (a.join(m.rename({"__id": "id_a", "truth_id": "__ta"}), on=[*on, "id_a"], how="left")
         .join(m.rename({"__id": "id_b", "truth_id": "__tb"}), on=[*on, "id_b"], how="left"))
    valid = pl.col("__ta").is_not_null() & pl.col("__tb").is_not_null() & (pl.col("__ta") != pl.col("__tb"))
    pair = ["run", "method", "id_a", "id_b"]
    votes = (a.filter(valid)
             .group_by([*pair, pl.min_horizontal("__ta", "__tb").alias("truth_a"),
                        pl.max_horizontal("__ta", "__tb").alias("truth_b")]).len()
             .sort([*pair, "len", "truth_a", "truth_b"], descending=[False] * 4 + [True, False, False])
             .unique(subset=pair, keep="first", maintain_order=True).drop("len"))
    a = a.drop("__ta", "__tb").join(votes, on=pair, how="left")
    known = pl.col("truth_a").is_not_null()
    return a.with_columns(pl.when(known).then(0).otherwise(1).cast(pl.UInt8).alias("kind"),
                          pl.when(known).then(pl.col("truth_a")).otherwise(pl.col("id_a").cast(pl.Int64)).alias("ka"),
                          pl.when(known).then(pl.col("truth_b")).otherwise(pl.col("id_b").cast(pl.Int64)).alias("kb"))


_BITS = 1 << 62


def _packed(cols: list[NDArray]) -> NDArray[np.int64]:
    """One int64 per row ordered like the rows' integer columns ``cols`` (lexicographic):
    mixed-radix packing, re-densified (np.unique) only when a radix would overflow."""
    code = np.zeros(len(cols[0]), np.int64)
    for v in cols:
        v = np.asarray(v).astype(np.int64, copy=False)
        if not len(v):
            return code
        lo, span = int(v.min()), int(v.max()) - int(v.min()) + 1
        if (int(code.max()) + 1) * span >= _BITS:
            code = np.unique(code, return_inverse=True)[1].astype(np.int64).ravel()
            if (int(code.max()) + 1) * span >= _BITS:
                v = np.unique(v, return_inverse=True)[1].astype(np.int64).ravel()
                lo, span = 0, int(v.max()) + 1
        code = code * span + (v - lo)
    return code


def _episodes_of(rows: pl.DataFrame, grid: pl.DataFrame, merge_gap_s: float, cpa_reach_s: float = 0.0
                 ) -> pl.DataFrame:
    """Alert episodes per key (run, method, kind, ka, kb): consecutive alert epochs belong to one
    episode when adjacent on the grid or ≤ ``merge_gap_s`` apart; non-adjacent ones are flicker.
    ``t_cpa``: the latest closest approach its alert epochs predicted (epoch + T_min clipped
    to [0, ``cpa_reach_s``]; a parallel pair's T_min = ∞ counts as now). One sort, then numpy
    over the sorted rows (no per-group windows)."""
    key = ["run", "method", "kind", "ka", "kb"]
    r = rows.join(grid.select("run", "method", "epoch", "k", "t_us"), on=["run", "method", "epoch"], how="inner")
    n = r.height
    codes = [r[c].to_physical().to_numpy() if c != "method" else r[c].cast(pl.Categorical).to_physical().to_numpy()
             for c in key]
    # one packed integer key and a numpy sort: several times faster than a multi-column frame sort
    pk = _packed([*codes, r["k"].to_numpy()])
    order = np.lexsort((r["r_min_m"].fill_null(np.inf).to_numpy(), pk)) if n else np.zeros(0, np.int64)
    r = r[order]
    codes = [c[order] for c in codes]
    k, t = r["k"].to_numpy(), r["t_us"].to_numpy()
    same = np.zeros(n, bool)
    if n:
        same[1:] = True
        for c in codes:
            same[1:] &= c[1:] == c[:-1]
    dk = np.diff(k, prepend=0)
    keep = ~same | (dk != 0)                     # one alert epoch of an aircraft pair counts once (closest kept)
    r, same, k, t = r.filter(pl.Series(keep)), same[keep], k[keep], t[keep]
    if keep.size and not keep.all():             # re-link: a dropped row's successor follows the kept one
        same = np.zeros(len(k), bool)
        codes = [c[keep] for c in codes]
        if len(k):
            same[1:] = True
            for c in codes:
                same[1:] &= c[1:] == c[:-1]
    dk, dt = np.diff(k, prepend=0), np.diff(t, prepend=0)
    new = ~same | ((dk > 1) & (dt > int(round(merge_gap_s * _US))))
    flick = (~new & (dk > 1)).astype(np.int64)
    starts = np.flatnonzero(new)
    if not len(starts):
        return pl.DataFrame(schema={"__ep": pl.Int64, **{c: r.schema[c] for c in (*key, "id_a", "id_b", "truth_a",
                                                                                      "truth_b")},
                                    "t0": pl.Int64, "t1": pl.Int64, "t_cpa": pl.Int64, "alert_epochs": pl.UInt32,
                                    "flicker": pl.Int64,
                                    "r_min_pred_m": pl.Float64, "dz_min_pred_m": pl.Float64,
                                    "t_min_first_s": pl.Float64})
    ends = np.append(starts[1:], len(k)) - 1
    with np.errstate(invalid="ignore"):
        r_min = np.fmin.reduceat(r["r_min_m"].fill_null(np.nan).to_numpy(), starts)
        dz_min = np.fmin.reduceat(r["dz_min_m"].fill_null(np.nan).to_numpy(), starts)
        t_min = r["t_min_s"].cast(pl.Float64).fill_null(0.0).to_numpy()
        ahead = np.where(np.isfinite(t_min), np.clip(t_min, 0.0, cpa_reach_s), 0.0)
    t_cpa = np.maximum.reduceat(t + np.round(ahead * _US).astype(np.int64), starts)
    first = r[starts].select(*key, "id_a", "id_b", "truth_a", "truth_b", "t_min_s")
    return first.with_columns(
        pl.Series("__ep", np.arange(len(starts), dtype=np.int64)), pl.Series("t0", t[starts]),
        pl.Series("t1", t[ends]), pl.Series("t_cpa", t_cpa), pl.Series("alert_epochs", (ends - starts + 1).astype(np.uint32)),
        pl.Series("flicker", np.add.reduceat(flick, starts)), pl.Series("r_min_pred_m", r_min),
        pl.Series("dz_min_pred_m", dz_min), pl.col("t_min_s").alias("t_min_first_s")).drop("t_min_s")


def _reach(link_us: int) -> pl.Expr:
    """The end of an episode's link window: ``link`` after its end, or its latest predicted
    closest approach (``t_cpa``) when later."""
    return pl.max_horizontal(pl.col("t1") + link_us, pl.col("t_cpa"))


def _linked(left: pl.DataFrame, iv: pl.DataFrame, link_us: int, shared: bool, on: list[str]) -> pl.DataFrame:
    """Rows of ``left`` (alert episodes [t0, t1]) joined with the intervals ``iv`` of their pair
    that overlap their link window [t0, :func:`_reach`]."""
    keys = on + ([] if shared else ["run"])
    ivs = iv.drop("run") if shared else iv
    return (left.join(ivs, on=keys, how="inner")
            .filter((pl.col("t_start_us") <= _reach(link_us)) & (pl.col("t_end_us") >= pl.col("t0"))))


def _classify(eps: pl.DataFrame, los: pl.DataFrame, prox: pl.DataFrame, link_us: int, shared: bool) -> pl.DataFrame:
    pairs = ["truth_a", "truth_b"]
    known = eps.filter(pl.col("kind") == 0).select("__ep", "run", *pairs, "t0", "t1", "t_cpa")
    g = (_linked(known, los, link_us, shared, pairs)
         .group_by("__ep").agg(pl.col("t_start_us").min().alias("los_start_us")))
    n = _linked(known, prox, link_us, shared, pairs).select("__ep").unique().with_columns(
        pl.lit(True).alias("__near"))
    e = eps.join(g, on="__ep", how="left").join(n, on="__ep", how="left")
    cls = (pl.when(pl.col("los_start_us").is_not_null()).then(pl.lit("genuine"))
           .when(pl.col("__near").fill_null(False)).then(pl.lit("nuisance")).otherwise(pl.lit("false")))
    return e.with_columns(cls.alias("classification"),
                          ((pl.col("los_start_us") - pl.col("t0")) / _US).alias("warning_s"))


def _los_table(grid: pl.DataFrame, eps: pl.DataFrame, los: pl.DataFrame, link_us: int, shared: bool) -> pl.DataFrame:
    spans = grid.group_by("run", "method").agg(pl.col("t_us").min().alias("__g0"), pl.col("t_us").max().alias("__g1"))
    base = spans.join(los.drop("run"), how="cross") if shared else spans.join(los, on="run", how="inner")
    base = base.filter((pl.col("t_end_us") >= pl.col("__g0")) & (pl.col("t_start_us") <= pl.col("__g1"))
                       ).with_row_index("__los")
    al = eps.filter(pl.col("kind") == 0).select("run", "method", "truth_a", "truth_b", "t0", "t1", "t_cpa")
    first = (base.join(al, on=["run", "method", "truth_a", "truth_b"], how="inner")
             .filter((pl.col("t0") <= pl.col("t_end_us")) & (_reach(link_us) >= pl.col("t_start_us")))
             .group_by("__los").agg(pl.col("t0").min().alias("__first")))
    out = base.join(first, on="__los", how="left")
    return out.select(
        pl.col("run").cast(pl.UInt32), "method", "truth_a", "truth_b", _to_time("t_start_us", "t_start"),
        _to_time("t_end_us", "t_end"), pl.col("__first").is_not_null().alias("alerted"),
        _to_time("__first", "first_alert"), ((pl.col("t_start_us") - pl.col("__first")) / _US).alias("warning_s"),
    ).sort("run", "method", "truth_a", "truth_b", "t_start").cast(LOS_SCHEMA)


def _score(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame, cfg: AlertConfig, id_col: str,
           methods: list[str] | None, frame: geo.LocalFrame | None,
           intervals: tuple[pl.DataFrame, pl.DataFrame] | None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(alerts table, LoS table, grid) of the pictures in ``conflicts``; only epochs inside the
    truth's time span are scored (after the reference ends nothing can judge an alert)."""
    if truth.height and "time" in truth.columns:
        t0, t1 = truth["time"].min(), truth["time"].max()
        inside = pl.col("epoch").cast(TIME).is_between(pl.lit(t0).cast(TIME), pl.lit(t1).cast(TIME))
        conflicts, id_map = conflicts.filter(inside), id_map.filter(inside)
    los, prox = truth_intervals(truth, cfg, frame) if intervals is None else intervals
    shared = "run" not in truth.columns
    link_us = int(round(cfg.link * _US))
    grid = _grid(conflicts, id_map, methods)
    eps = _episodes_of(_alert_rows(conflicts, id_map, id_col), grid, cfg.merge_gap_s, cfg.cpa_reach)
    eps = _classify(eps, los, prox, link_us, shared)
    alerts = eps.select(
        "run", "method", "id_a", "id_b", "truth_a", "truth_b", _to_time("t0", "t_start"), _to_time("t1", "t_end"),
        ((pl.col("t1") - pl.col("t0")) / _US).alias("duration_s"), "alert_epochs", "flicker", "r_min_pred_m",
        "dz_min_pred_m", "t_min_first_s", _to_time("los_start_us", "los_start"), "warning_s", "classification",
    ).sort("run", "method", "t_start", "id_a", "id_b").cast(ALERTS_SCHEMA)
    return alerts, _los_table(grid, eps, los, link_us, shared), grid


def alert_episodes(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                   cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                   frame: geo.LocalFrame | None = None,
                   intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> pl.DataFrame:
    """The ``alerts`` table (:data:`ALERTS_SCHEMA`): one row per alert episode per picture, with
    its pair of ids and of aircraft, start, end, minimum predicted separation, warning time and
    ``classification`` (genuine / nuisance / false) — see the module docstring."""
    return _score(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)[0]


def los_episodes(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                 cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                 frame: geo.LocalFrame | None = None,
                 intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> pl.DataFrame:
    """One row per LoS episode and picture (:data:`LOS_SCHEMA`): alerted or missed, warning."""
    return _score(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)[1]


def _hours(grid: pl.DataFrame) -> pl.DataFrame:
    return (grid.group_by("run", "method").agg(((pl.col("t_us").max() - pl.col("t_us").min()) / _US).alias("__s"))
            .group_by("method").agg((pl.col("__s").sum() / 3600.0).alias("picture_hours"),
                                    pl.col("run").n_unique().alias("n_runs")))


def _per_method(alerts: pl.DataFrame, los: pl.DataFrame, grid: pl.DataFrame) -> pl.DataFrame:
    cls = pl.col("classification")
    a = alerts.group_by("method").agg(
        pl.len().cast(pl.Float64).alias("alert_episodes"),
        (cls == "genuine").sum().cast(pl.Float64).alias("genuine_alerts"),
        (cls == "nuisance").sum().cast(pl.Float64).alias("nuisance_alerts"),
        (cls == "false").sum().cast(pl.Float64).alias("false_alerts"),
        pl.col("duration_s").median().alias("alert_duration_median_s"),
        pl.col("flicker").cast(pl.Float64).mean().alias("flicker_per_alert"))
    w = pl.col("warning_s").filter(pl.col("alerted"))
    lo = los.group_by("method").agg(
        pl.len().cast(pl.Float64).alias("los_episodes"), pl.col("alerted").sum().cast(pl.Float64).alias("alerted_los"),
        w.median().alias("warning_median_s"), w.quantile(0.05, "linear").alias("warning_p05_s"))
    per = _hours(grid).join(a, on="method", how="left").join(lo, on="method", how="left")
    counts = ["alert_episodes", "genuine_alerts", "nuisance_alerts", "false_alerts", "los_episodes", "alerted_los"]
    per = per.with_columns(pl.col(counts).fill_null(0.0))
    hrs = pl.when(pl.col("picture_hours") > 0).then(pl.col("picture_hours"))
    return per.with_columns(
        (pl.col("los_episodes") - pl.col("alerted_los")).alias("missed_los"),
        (pl.col("alert_episodes") / hrs).alias("alerts_per_hour"),
        ((pl.col("nuisance_alerts") + pl.col("false_alerts")) / hrs).alias("nuisance_false_per_hour"),
    ).with_columns(pl.col(ALERT_METRICS).cast(pl.Float64).fill_null(float("nan")))


def score_alerts(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                 cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                 frame: geo.LocalFrame | None = None,
                 intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> pl.DataFrame:
    """STCA performance per picture in the ``metrics`` schema (stage ``"safety"``, segment
    ``"all"``): :data:`ALERT_METRICS` — see the module docstring."""
    alerts, los, grid = _score(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)
    return _metrics_long(_per_method(alerts, los, grid))


def _metrics_long(per: pl.DataFrame) -> pl.DataFrame:
    long = per.unpivot(index=["method", "n_runs"], on=list(ALERT_METRICS), variable_name="metric",
                       value_name="value")
    order = pl.col("metric").replace_strict({m: i for i, m in enumerate(ALERT_METRICS)}, return_dtype=pl.Int8)
    out = long.sort([pl.col("method"), order]).select(
        pl.lit("safety").alias("stage"), "method", "metric", pl.lit("all").alias("segment"), "value", "n_runs")
    spec = TABLES["metrics"].required
    return out.select([pl.col(c).cast(t) for c, t in spec.items()])


def stca_tables(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                frame: geo.LocalFrame | None = None,
                intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None
                ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(metrics, alerts, LoS episodes) in one pass: :func:`score_alerts`,
    :func:`alert_episodes` and :func:`los_episodes` without scoring twice (pipeline use)."""
    alerts, los, grid = _score(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)
    return _metrics_long(_per_method(alerts, los, grid)), alerts, los


def stca_tables_by_picture(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                           cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                           frame: geo.LocalFrame | None = None,
                           intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None
                           ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """:func:`stca_tables` one picture at a time, the same three tables: a picture's alerts,
    LoS episodes and metrics depend on its own conflicts and id map alone (``id_map`` without a
    ``method`` column serves every picture), and the union is sorted as one call sorts it. A
    pass's joins hold one picture's rows: the full comparison's 14 tracker pictures at once
    took 830 MiB over a 12 h run's finalize (issue 16, memory)."""
    # the pictures one call scores (:func:`_grid`): an id map's own pictures when it names them
    if "method" in id_map.columns:
        names = sorted(set(id_map["method"].unique().to_list()) | set(conflicts["method"].unique().to_list()))
    else:
        names = methods if methods is not None else sorted(conflicts["method"].unique().to_list())
    if len(names) <= 1:
        return stca_tables(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)
    if intervals is None:
        intervals = truth_intervals(truth, cfg, frame)
    parts = []
    for name in names:
        ids = id_map.filter(pl.col("method") == name) if "method" in id_map.columns else id_map
        parts.append(stca_tables(conflicts.filter(pl.col("method") == name), ids, truth, cfg, id_col, [name],
                                 frame, intervals))
    metrics, alerts, los = (pl.concat([p[k] for p in parts], how="vertical") for k in range(3))
    # each part is sorted as one call sorts its tables: the union sorted again by the same keys
    return (metrics.sort("method", maintain_order=True),
            alerts.sort("run", "method", "t_start", "id_a", "id_b", maintain_order=True),
            los.sort("run", "method", "truth_a", "truth_b", "t_start", maintain_order=True))


# --------------------------------------------------------------------------- trade-off curves


def _settings(base: ConflictConfig, confidences, fixed_est_h_m, lookaheads_s):
    """(threshold_mode, parameter, ConflictConfig) of every point of the curves."""
    ratio = base.fixed_est_v_m / base.fixed_est_h_m if base.fixed_est_h_m > 0 else 50.0 / 300.0
    t0 = base.t_thr_s - base.t_margin_s
    out = []
    for t in lookaheads_s:
        common = dict(t_margin_s=float(t) - t0, near_margin_h_m=0.0, near_margin_v_m=0.0)
        out += [("covariance", float(c), dataclasses.replace(base, threshold_mode="covariance", confidence=c, **common))
                for c in confidences]
        out += [("fixed", float(e), dataclasses.replace(base, threshold_mode="fixed", fixed_est_h_m=e,
                                                        fixed_est_v_m=e * ratio, **common)) for e in fixed_est_h_m]
    return out


def stca_tradeoff(picture: "pl.DataFrame | Iterable[pl.DataFrame]", id_map: pl.DataFrame, truth: pl.DataFrame,
                  cfg: AlertConfig = AlertConfig(),
                  id_col: str = "target_id", methods: list[str] | None = None, frame: geo.LocalFrame | None = None,
                  map_id_col: str | None = None,
                  confidences: Sequence[float] = (0.5, 0.8, 0.9, 0.95, 0.99, 0.999),
                  fixed_est_h_m: Sequence[float] = (0.0, 150.0, 300.0, 600.0, 1200.0, 2400.0),
                  lookaheads_s: Sequence[float] | None = None,
                  warning_s: Sequence[float] = (0.0, 30.0, 60.0),
                  intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None,
                  spill: "str | os.PathLike[str] | None" = None) -> pl.DataFrame:
    """Trade-off curves of every picture of ``picture`` (a fused or track table; ``method`` names
    the picture; ``id_col`` its id column, ``map_id_col`` that of ``id_map``, default the
    same): for each look-ahead T (default: ``cfg.conflict``'s) and each point — covariance
    thresholds at each ``confidences``, fixed thresholds at each ``fixed_est_h_m`` (vertical
    term scaled like the configured fixed pair) — conflicts are predicted, scored, and the row
    gives the fraction of LoS episodes alerted with ≥ X s warning (X in ``warning_s``) against
    nuisance + false alerts per hour. Columns: method, threshold_mode, parameter (confidence or
    fixed_est_h_m), t_thr_s, warning_s, los_episodes, alerted_fraction, genuine_alerts,
    nuisance_alerts, false_alerts, nuisance_false_per_hour, picture_hours, n_runs. ``intervals``:
    :func:`truth_intervals` of ``truth`` when already computed (curves drawn a picture at a time).
    ``spill``: a scratch directory where each setting's predicted rows wait for their scoring
    on disk, so one setting's rows are held at a time; ``picture`` may come as blocks in time
    order (:func:`_scored_rows`). Each picture's rows depend on that picture alone."""
    if intervals is None:
        intervals = truth_intervals(truth, cfg, frame)
    looks = (cfg.conflict.t_thr_s,) if lookaheads_s is None else tuple(lookaheads_s)
    rows = []
    settings = _settings(cfg.conflict, confidences, fixed_est_h_m, looks)
    scored = _scored_rows(picture, [cc for _, _, cc in settings], id_col, frame, spill=spill)
    for (mode, par, cc), c in zip(settings, scored):
        c = c() if callable(c) else c         # a spilled setting's rows, read back now
        acfg = dataclasses.replace(cfg, conflict=cc)
        alerts, los, grid = _score(c, id_map, truth, acfg, map_id_col or id_col, methods, frame, intervals)
        per = _per_method(alerts, los, grid)
        for x in warning_s:
            frac = (los.group_by("method").agg(
                (pl.col("alerted") & (pl.col("warning_s") >= x)).sum().alias("__n"), pl.len().alias("__d")))
            part = per.join(frac, on="method", how="left").select(
                "method", pl.lit(mode).alias("threshold_mode"), pl.lit(par).alias("parameter"),
                pl.lit(cc.t_thr_s).alias("t_thr_s"), pl.lit(float(x)).alias("warning_s"), "los_episodes",
                pl.when(pl.col("__d") > 0).then(pl.col("__n") / pl.col("__d")).otherwise(float("nan"))
                .alias("alerted_fraction"),
                "genuine_alerts", "nuisance_alerts", "false_alerts", "nuisance_false_per_hour", "picture_hours",
                pl.col("n_runs").cast(pl.UInt32))
            rows.append(part)
    return pl.concat(rows, how="vertical_relaxed").sort("method", "t_thr_s", "warning_s", "threshold_mode", "parameter")


#: the time windows the trade-off curves predict conflicts in (memory bounded by the window) ...
CURVE_WINDOW_S = 3600.0
#: ... and the most picture rows a window starts with (more only when one epoch holds more)
CURVE_WINDOW_ROWS = 100_000

#: settings of the curves predicted at once, in threads: each setting's prediction is
#: independent and most of its time is spent in numpy, polars and the KD-tree, outside the GIL
CURVE_THREADS = min(2, os.cpu_count() or 1)


#: the columns of predicted conflict rows the alert scoring reads
_SCORED_CONFLICT_COLUMNS = ("alert", "run", "method", "epoch", "id_a", "id_b", "r_min_m", "dz_min_m", "t_min_s")


def _scored_rows(picture: "pl.DataFrame | Iterable[pl.DataFrame]", cfgs: Sequence[ConflictConfig], id_col: str,
                 frame: geo.LocalFrame | None, window_s: float | None = None,
                 spill: "str | os.PathLike[str] | None" = None) -> list["pl.DataFrame | Callable[[], pl.DataFrame]"]:
    """What scoring reads of :func:`~safety.conflicts.predict_conflicts` of ``picture`` under
    each configuration of ``cfgs``: its alert rows and one row per (run, method, epoch) (the
    epoch grid of :func:`_grid`), predicted window by window
    (:func:`~safety.conflicts.conflicts_steps`, each configuration's confirmation state
    carried), so that a long picture's every screened pair is never held at once. Each window
    of the picture is cut, prepared and screened once for every configuration; the
    per-configuration work runs :data:`CURVE_THREADS` at a time. The scores equal those of the
    whole table. ``picture`` may come as blocks in time order (each block's epochs after the
    previous block's but its last; a block's last epoch is completed by the next block's rows):
    the picture is then never held whole (a national day's tracker picture with its covariances
    is ~10 GB; issue 18, memory). With ``spill`` each window's rows of each configuration are
    written there and a reader of each configuration's rows is returned instead (a national
    day's alert rows of twelve settings held together outgrew 24 GB)."""
    blocks = iter([picture] if isinstance(picture, pl.DataFrame) else picture)
    first = next(blocks, None)
    if first is None:
        raise ValueError("_scored_rows: a picture of no block (give an empty frame instead)")
    step = int(round((CURVE_WINDOW_S if window_s is None else window_s) * _US))
    states = [init_conflict_state() for _ in cfgs]
    parts: list[list[pl.DataFrame]] = [[] for _ in cfgs]

    def scored(out: pl.DataFrame) -> pl.DataFrame:
        # only what the scoring reads (:func:`_grid`, :func:`_alert_rows`): every setting's rows of
        # a whole day are held until scored (a national day's 12 settings peaked at ~20 GB)
        out = out.select([c for c in _SCORED_CONFLICT_COLUMNS if c in out.columns])
        grid = out.unique(["run", "method", "epoch"], keep="first", maintain_order=True)
        return pl.concat([out.filter(pl.col("alert")), grid.filter(~pl.col("alert"))])
    dirs = None if spill is None else [Path(spill) / f"setting-{k:03d}" for k in range(len(cfgs))]
    for d in dirs or ():
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    w = 0
    with ThreadPoolExecutor(CURVE_THREADS) as pool:
        for block in _whole_epochs(first, blocks):
            us = block["epoch"].cast(TIME).dt.epoch("us").to_numpy()
            order = np.argsort(us, kind="stable")
            us = us[order]
            # a dense picture is cut finer: every setting's screened pairs of a window are held
            # together
            edges = np.unique(np.concatenate([np.arange(int(us[0]), int(us[-1]) + 1, step),
                                              us[::CURVE_WINDOW_ROWS], [int(us[-1]) + 1]])).tolist()
            for t0, t1 in zip(edges[:-1], edges[1:]):
                lo, hi = np.searchsorted(us, [t0, t1])
                steps = conflicts_steps(states, block[order[lo:hi]], cfgs, id_col, frame, t0, t1, slim=False,
                                        map_=pool.map)
                states = [state for _, state in steps]
                for k, rows in enumerate(pool.map(scored, [out for out, _ in steps])):
                    if dirs is None:
                        parts[k].append(rows)
                    else:
                        rows.write_parquet(dirs[k] / f"w={w:06d}.parquet", compression="lz4")
                w += 1
    if w == 0:                  # an empty picture
        for d in dirs or ():
            shutil.rmtree(d, ignore_errors=True)
        return [predict_conflicts(first.clear(), cfg, id_col=id_col, frame=frame) for cfg in cfgs]
    if dirs is None:
        return [pl.concat(p) for p in parts]
    return [functools.partial(_read_spilled, d) for d in dirs]


def _whole_epochs(first: pl.DataFrame, rest: Iterator[pl.DataFrame]) -> Iterator[pl.DataFrame]:
    """The blocks ``first``, ``*rest`` with rows, each ending on a whole epoch: the rows of a
    block's last epoch move to the next block (a window of the prediction holds whole epochs)."""
    held = first
    for block in rest:
        if block.height == 0:
            continue
        if held.height:
            last = held["epoch"].max()
            tail = held["epoch"] == last
            if held.height > int(tail.sum()):
                yield held.filter(~tail)
            held = pl.concat([held.filter(tail), block], how="vertical_relaxed")
        else:
            held = block
    if held.height:
        yield held


def _read_spilled(d: Path) -> pl.DataFrame:
    """A configuration's spilled rows (:func:`_scored_rows`) in window order; the files removed."""
    files = sorted(d.glob("w=*.parquet"))
    out = pl.concat([pl.read_parquet(f) for f in files])
    shutil.rmtree(d, ignore_errors=True)
    return out


def compare_at_equal_nuisance(curve: pl.DataFrame, warning_s: float = 30.0, t_thr_s: float | None = None,
                              rate: float | None = None, reference_confidence: float = 0.95) -> pl.DataFrame:
    """Covariance vs fixed thresholds at equal nuisance + false alert rate: per picture, each
    family's alerted fraction (≥ ``warning_s`` warning) linearly interpolated at ``rate``
    (default: the covariance family's rate at ``reference_confidence``), at look-ahead
    ``t_thr_s`` (default: the curve's largest); NaN outside a family's range (no
    extrapolation). Columns: method, threshold_mode, t_thr_s, warning_s,
    nuisance_false_per_hour, alerted_fraction."""
    cur = curve.filter(pl.col("warning_s") == warning_s)
    if t_thr_s is None and cur.height:
        t_thr_s = float(cur["t_thr_s"].max())
    cur = cur.filter(pl.col("t_thr_s") == t_thr_s)
    out = []
    for (method,), g in cur.partition_by("method", as_dict=True, maintain_order=True).items():
        cov = g.filter(pl.col("threshold_mode") == "covariance")
        r = rate
        if r is None and cov.height:
            r = float(cov.sort((pl.col("parameter") - reference_confidence).abs())["nuisance_false_per_hour"][0])
        for mode in ("covariance", "fixed"):
            fam = (g.filter((pl.col("threshold_mode") == mode) & pl.col("nuisance_false_per_hour").is_not_nan())
                   .group_by("nuisance_false_per_hour").agg(pl.col("alerted_fraction").max())
                   .sort("nuisance_false_per_hour"))
            x, y = fam["nuisance_false_per_hour"].to_numpy(), fam["alerted_fraction"].to_numpy()
            ok = r is not None and len(x) and x[0] <= r <= x[-1]
            val = float(np.interp(r, x, y)) if ok else float("nan")
            out.append({"method": method, "threshold_mode": mode, "t_thr_s": t_thr_s, "warning_s": float(warning_s),
                        "nuisance_false_per_hour": float("nan") if r is None else float(r), "alerted_fraction": val})
    schema = {"method": pl.String, "threshold_mode": pl.String, "t_thr_s": pl.Float64, "warning_s": pl.Float64,
              "nuisance_false_per_hour": pl.Float64, "alerted_fraction": pl.Float64}
    return pl.DataFrame(out, schema=schema)


def tradeoff_metrics(curve: pl.DataFrame) -> pl.DataFrame:
    """The curves in the ``metrics`` schema (stage ``"safety_tradeoff"``, per picture): metrics
    ``alerted_fraction`` and ``nuisance_false_per_hour``, one segment per curve point,
    ``mode=<covariance|fixed>;p=<parameter>;T=<t_thr_s>;X=<warning_s>`` (read by
    ``sql/stca_tradeoff.sql``)."""
    seg = pl.format("mode={};p={};T={};X={}", "threshold_mode", pl.col("parameter").round(6),
                    pl.col("t_thr_s").round(3), pl.col("warning_s").round(3))
    long = curve.with_columns(seg.alias("segment")).unpivot(
        index=["method", "segment", "n_runs"], on=["alerted_fraction", "nuisance_false_per_hour"],
        variable_name="metric", value_name="value")
    spec = TABLES["metrics"].required
    out = long.select(pl.lit("safety_tradeoff").alias("stage"), "method", "metric", "segment", "value", "n_runs")
    return out.select([pl.col(c).cast(t) for c, t in spec.items()]).sort("method", "segment", "metric")
