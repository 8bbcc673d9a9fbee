"""Losses of separation and proximities in the truth, exact under linear motion between samples.

Inputs
------
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
level-pair threshold applies (docs/methods.md, "Level pairs"), and how a controller reads
it: reported altitudes of aircraft at adjacent levels differ by 1 000 ft ± the 25 ft / 100 ft
Mode S / Mode C quantum and altimetry error, and 975 ft on the display is not a loss. So on a
segment where both aircraft are level (|ḣ| ≤ ``level_rate_mps`` at both ends, ḣ the truth's
``alt_rate_mps`` — the aircraft's own vertical rate, not the slope of a quantised altitude —
else the segment's slope) the vertical minimum is reduced by ``level_pair_tolerance_m``
(100 ft), both from the prediction's :class:`~safety.conflicts.ConflictConfig`. A level bust
(100–250 ft under the occupied level) stays a loss; a pair where either aircraft climbs or
descends keeps the full minimum. Measured on real traffic (``adsb-paris``): without
it, pairs at adjacent levels on CDG's approaches made 36 of the 45 "loss" episodes, each a
second or two long whenever one aircraft's altitude flipped by 25 ft.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from safety.alerts.config import AlertConfig
from safety.conflicts import AerodromeZone, ConflictConfig, conflict_interval, height_and_rate, zone_index
from tertiary.contract import TIME
from tertiary.core import geo
from tertiary.core.errors import ResourceError
from tertiary.core.units import US

__all__ = ["epoch_micros", "to_time", "HEIGHT_BLOCK", "truth_heights", "truth_ends", "truth_span", "RESAMPLE_ROWS",
           "resampled_blocks", "SCREEN_BLOCK", "pair_segments", "separation_intervals", "merge_intervals",
           "merge_pair_intervals", "loss_of_separation", "truth_intervals"]

def epoch_micros(col: str) -> pl.Expr:
    """Microseconds since the Unix epoch of a time column (exact integers)."""
    return pl.col(col).cast(TIME).dt.epoch("us").cast(pl.Int64)


#: truth samples converted to geodetic height at a time (:func:`truth_heights`)
HEIGHT_BLOCK = 262_144


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
                      epoch_micros("time").alias("t_us"), *[pl.col(c).cast(pl.Float64) for c in ("x_m", "y_m", "z_m")],
                      *([pl.col("alt_m").cast(pl.Float64)] if "alt_m" in truth.columns else []),
                      *([pl.col("alt_rate_mps").cast(pl.Float64)] if "alt_rate_mps" in truth.columns else []))
    tr = tr.sort([*keys, "truth_id", "t_us"])
    pos = tr.select("x_m", "y_m", "z_m").to_numpy()
    # in blocks: the geodetic conversion's scratch is that of a block, not of the whole truth
    h = np.empty(len(pos))
    for lo in range(0, len(pos), HEIGHT_BLOCK):
        block = pos[lo:lo + HEIGHT_BLOCK]
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


def truth_ends(truth: pl.DataFrame | pl.LazyFrame, cfg: AlertConfig = AlertConfig(),
               frame: geo.LocalFrame | None = None) -> pl.DataFrame:
    """([run,] truth_id, time, airborne): each aircraft's last truth sample, and whether it was
    above ``cfg.landed_below_m`` there (height as :func:`truth_heights`; null without positions
    or altitude): an aircraft that ends airborne left the recording, one that ends below it
    landed. Reads one row per aircraft."""
    lf = truth.lazy()
    have = lf.collect_schema().names()
    keys = ["run"] if "run" in have else []
    cols = [c for c in ("x_m", "y_m", "z_m", "alt_m") if c in have]
    # two streamed passes (a day's truth is tens of millions of rows): each aircraft's last time,
    # then its rows at that time
    last = lf.group_by(*keys, "truth_id").agg(pl.col("time").max()).collect(engine="streaming")
    rows = (lf.select(*keys, "truth_id", "time", *cols)
            .join(last.lazy(), on=[*keys, "truth_id", "time"], how="semi").collect(engine="streaming")
            .unique([*keys, "truth_id"], keep="first", maintain_order=True).sort(*keys, "truth_id"))
    if not rows.height:
        return rows.select(*keys, pl.col("truth_id").cast(pl.Int64), "time",
                           pl.lit(None, pl.Boolean).alias("airborne"))
    if all(c in cols for c in ("x_m", "y_m", "z_m")):
        h = truth_heights(rows.with_columns(pl.col("truth_id").cast(pl.Int64)), frame)["h_m"]
    else:                       # no positions: the altitude where there is one, else unknown
        h = rows["alt_m"].cast(pl.Float64) if "alt_m" in cols else pl.Series([None] * rows.height, dtype=pl.Float64)
    return rows.select(*(pl.col(k).cast(pl.UInt32) for k in keys), pl.col("truth_id").cast(pl.Int64), "time",
                       (h > cfg.landed_below_m).alias("airborne"))


def truth_span(truth: pl.DataFrame | pl.LazyFrame, cfg: AlertConfig | None = None,
               frame: geo.LocalFrame | None = None) -> pl.DataFrame:
    """What the alert scoring reads of the truth besides its intervals: each run's first and
    last sample time (``run`` and ``time``; no ``run`` column without one); with ``cfg``, also
    each aircraft's last sample (``truth_id``, ``time``, ``airborne``: :func:`truth_ends`),
    which tells the alerts whose outcome the recording does not show."""
    keys = ["run"] if "run" in truth.collect_schema() else []
    ends = [truth.group_by(keys).agg(f(pl.col("time"))) if keys else truth.select(f(pl.col("time")))
            for f in (pl.Expr.min, pl.Expr.max)]
    out = pl.concat([e.collect() if isinstance(e, pl.LazyFrame) else e for e in ends])
    out = out.sort(*keys, "time") if keys else out.sort("time")
    if cfg is None:
        return out
    return pl.concat([out, truth_ends(truth, cfg, frame)], how="diagonal_relaxed")


#: resampled truth rows held at once (:func:`resampled_blocks`): memory is bounded by a block, not
#: by the whole grid
RESAMPLE_ROWS = 1_000_000


def resampled_blocks(tr: pl.DataFrame, max_rows: int, rows: int = RESAMPLE_ROWS) -> Iterator[dict[str, NDArray]]:
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
#: boxes instead of segments, a much smaller tree (see :func:`pair_segments`)
SCREEN_BLOCK = 32


def pair_segments(rs: dict[str, NDArray], reach_h: float, reach_v: float, block: int = SCREEN_BLOCK
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
    motion between the union sample times (module docstring). ``level_pairs`` =
    (tolerance m, level rate m/s): on segments where both aircraft are level the vertical bound
    is f·Δr_в − tolerance (module docstring "Level pairs"). ``enroute`` = (floor m, Δr_г m,
    Δr_в m): a segment pair with any of its four end heights at or above the floor is judged by
    these minima instead (docs/methods.md, "En-route airspace"). ``zones``: aerodrome
    zones; a segment pair whose four ends are in one zone is not a loss (docs/methods.md,
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
    # blocks' pieces are the whole grid's (memory)
    blocks = resampled_blocks(tr, max_rows)
    del tr                        # the blocks hold its columns as arrays, not the frame too
    for rs in blocks:
        for got, f_pieces in zip(_block_pieces(rs, fmax * reach_h, fmax * reach_v, dr_h_m, dr_v_m, factors,
                                               level_pairs, enroute, zones), pieces):
            f_pieces.append(got)
        del rs
    gap_us = int(round(merge_gap_s * US))
    return [merge_pair_intervals(*_clipped([np.concatenate([p[k] for p in f_pieces]) for k in range(5)], clip_us),
                                 out_schema, gap_us)
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
    gap_us = int(round(cfg.merge_gap_s * US))
    out = []
    for k in range(2):
        frames = [c[k] for c in chunks if c[k].height]
        if not frames:
            out.append(chunks[0][k].clear() if chunks else pl.DataFrame())
            continue
        f = pl.concat(frames)
        cols = ("run", "truth_a", "truth_b", "t_start_us", "t_end_us")
        out.append(merge_pair_intervals(*(f[c].to_numpy() for c in cols), f.schema, gap_us))
    return out[0], out[1]


def _block_pieces(rs: dict[str, NDArray], reach_h: float, reach_v: float, dr_h_m: float, dr_v_m: float,
                  factors: Sequence[float], level_pairs: tuple[float, float] | None,
                  enroute: tuple[float, float, float] | None, zones: Sequence[AerodromeZone]
                  ) -> list[tuple[NDArray, ...]]:
    """Per factor, (run, truth_a, truth_b, start µs, end µs) of every segment pair of one
    resampled block within the factor's minima (before merging), exact under linear motion."""
    none = (np.zeros(0, np.uint32), *[np.zeros(0, np.int64)] * 4)
    a, b = pair_segments(rs, reach_h, reach_v)
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
    dt = (t[a + 1] - t[a]).astype(np.float64) / US
    r0 = pos[b] - pos[a]
    w = ((pos[b + 1] - pos[a + 1]) - r0) / dt[:, None]
    ta_, tb_ = rs["tid"][ac[a]], rs["tid"][ac[b]]
    run = rs["run"][ac[a]].astype(np.uint32)
    tol = 0.0 if level_pairs is None else np.where(_both_level(rs, a, b, dt, level_pairs[1]), level_pairs[0], 0.0)
    out = []
    for f in factors:
        # a loss is strictly inside both minima; the closed interval differs from it on a null
        # set (t_out > t_in) except where a height difference stays exactly at the vertical
        # minimum — two quantised altitudes 1 000 ft apart, one of them jittering by a quantum
        # (not "level"): the pair is separated, so the vertical bound is taken just inside
        d_v = f * dr_v_m - tol
        t_in, t_out = _segment_interval(r0, w, f * dr_h_m, d_v - _AT_MINIMUM_REL * np.maximum(d_v, 1.0), dt)
        ok = t_out > t_in
        s_us = t[a][ok] + np.round(t_in[ok] * US).astype(np.int64)
        e_us = t[a][ok] + np.round(t_out[ok] * US).astype(np.int64)
        out.append((run[ok], np.minimum(ta_, tb_)[ok].astype(np.int64), np.maximum(ta_, tb_)[ok].astype(np.int64),
                    s_us, e_us))
    return out


#: relative margin inside the vertical minimum of a loss: a height difference equal to the
#: minimum (to the rounding of a quantised altitude converted to metres) is no loss
_AT_MINIMUM_REL = 1e-9


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


def merge_pair_intervals(run, ta, tb, s_us, e_us, schema, gap_us: int = 0) -> pl.DataFrame:
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
    return los.select(*keys, "truth_a", "truth_b", to_time("t_start_us", "t_start"), to_time("t_end_us", "t_end"))


def to_time(col: str, name: str) -> pl.Expr:
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
