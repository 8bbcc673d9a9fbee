"""Match any air picture to a reference, once: which reference aircraft each track row is.

The evaluation of a picture that ``tertiary`` did not produce (an existing tracker's output,
CAT062, a Parquet file in the ``tracks`` schema) cannot use report labels: it has only track
states and a reference (simulator truth or an ADS-B reference). This module matches by
geometry, the way a surveillance engineer's evaluation tool does.

Assignment rule (documented, deterministic)
-------------------------------------------
1. **Reference at the track's time.** Every reference aircraft alive at a track row's epoch is
   interpolated linearly between its neighbouring samples (:func:`truth_at`;
   never extrapolated: outside an aircraft's span it is absent).
2. **Gate.** A (track row, aircraft) pair is a candidate when the horizontal distance is at most
   ``gate_h_m`` and, where both carry a height (``alt_m``, else the ENU z), the vertical distance
   at most ``gate_v_m``. Candidates are found with one KD-tree over all epochs (the epoch group
   offsets the coordinates), never by a loop over pairs.
3. **One-to-one per epoch.** Within each (run, picture, epoch), each track row is matched to at
   most one aircraft and each aircraft to at most one track row, minimising the sum of squared
   normalised distances (d_h/gate_h)² + (d_v/gate_v)² — the Hungarian algorithm on each
   connected component of the candidate graph; a component of one track and one aircraft (the
   usual case) is matched without it. A second track on an aircraft that already has one is
   therefore *unmatched* at that epoch (a duplicate/split), not a second match.
4. **Beyond the reference.** An aircraft's reference can end while the radars still report it
   (it leaves the simulated airspace, a recording stops, a time slice ends): its radar tracks
   coast on, and a track may even be confirmed after the reference's last sample. A row left in
   no aircraft's gate that lies, at most ``ended_s`` after an aircraft's last reference sample,
   within the gates of that sample dead-reckoned to the row's epoch (its velocity and vertical
   rate) carries that aircraft as ``beyond_truth_id``: the reference cannot judge it, so it is
   neither matched nor counted false.
5. **Swaps and gaps.** The rule is per epoch: when two tracks exchange aircraft the matching
   follows the geometry, so the track id that represents an aircraft changes (counted by the
   continuity metrics); an aircraft with no track row in the gate is a missed update; a track
   row with no aircraft is unmatched (false or duplicate).

Output: the track rows with ``truth_id`` (null when unmatched), the reference state
``true_x_m … true_vz_mps`` (and ``true_alt_m``) and flight ``segment`` of the matched aircraft,
``match_cost``, and ``gated_truth_id``: the aircraft a row *represents* — its match, or for an
unmatched row inside some aircraft's gate the nearest such aircraft (a second track of an
aircraft, which a controller still sees as that aircraft; null only for a row in no gate). The
safety stage scores alerts with it: an alert between an aircraft and its own duplicate track is
a duplicate, not a false alert between two aircraft. ``beyond_truth_id``: rule 4 (null
otherwise).

This is the only matcher of the project: the seed metrics (:mod:`tertiary.evaluation.accuracy`), the
surveillance metrics (:mod:`tertiary.evaluation.picture_metrics`) and alert scoring all read its output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tertiary.contract import TIME
from tertiary.core.units import STATE

__all__ = ["MatchConfig", "truth_at", "reference_at_epochs", "picture_epochs", "match_to_reference",
           "match_with_reference",
           "reference_identity", "with_neighbours", "reference_between",
           "neighbour_times", "between_mask", "between_expr"]


def truth_at(samples: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """Reference state of ``samples`` (truth_id, epoch): exact or linearly interpolated between the
    neighbouring reference samples (never extrapolated: rows outside the aircraft's span are
    dropped), as ``true_<state>`` and the reference ``segment`` at the earlier sample;
    ``true_alt_m`` too when both frames carry ``alt_m``, and then ``true_alt_rate_mps`` when the
    reference has ``alt_rate_mps`` (a height's rate beside the height: the ENU ``vz`` of a level
    flight far from the frame's origin is not zero)."""
    cols = list(STATE) + (["alt_m"] if "alt_m" in truth.columns and "alt_m" in samples.columns else [])
    if "alt_m" in cols and "alt_rate_mps" in truth.columns:
        cols.append("alt_rate_mps")
    has_seg = "segment" in truth.columns
    tr = truth.select(pl.col("truth_id").cast(pl.Int64), pl.col("time").cast(TIME), *cols,
                      (pl.col("segment") if has_seg else pl.lit(None, pl.String)).alias("segment")
                      ).sort("time")
    left = samples.drop("segment", strict=False).with_row_index("__i").sort("epoch")
    lo = tr.rename({"time": "__t0", **{c: f"__lo_{c}" for c in cols}})
    hi = tr.drop("segment").rename({"time": "__t1", **{c: f"__hi_{c}" for c in cols}})
    j = (left.join_asof(lo, left_on="epoch", right_on="__t0", by="truth_id", strategy="backward",
                        check_sortedness=False)
         .join_asof(hi, left_on="epoch", right_on="__t1", by="truth_id", strategy="forward",
                    check_sortedness=False))
    span = (pl.col("__t1") - pl.col("__t0")).dt.total_microseconds()
    w = pl.when(span > 0).then((pl.col("epoch") - pl.col("__t0")).dt.total_microseconds() / span).otherwise(0.0)
    return (j.with_columns([(pl.col(f"__lo_{c}") + w * (pl.col(f"__hi_{c}") - pl.col(f"__lo_{c}"))).alias(f"true_{c}")
                            for c in cols])
            .filter(pl.col("__t0").is_not_null() & pl.col("__t1").is_not_null())
            .sort("__i")
            .select(pl.exclude("^__.*$")))


@dataclass(frozen=True)
class MatchConfig:
    """Gates of the geometric matching (module docstring, rule 2)."""

    gate_h_m: float = 1852.0
    gate_v_m: float = 300.0
    #: a reference gap longer than this is not interpolated across: the aircraft is absent from
    #: the reference there ("not evaluated"); None: interpolate any gap (simulator truth)
    max_gap_s: float | None = None
    #: how long after an aircraft's last reference sample a row in the gates of that sample
    #: dead-reckoned is beyond the reference (rule 4): a radar's coasting and a tracker's
    #: confirmation, a few scans; 0: never
    ended_s: float = 30.0

    def __post_init__(self) -> None:
        if not (self.gate_h_m > 0 and self.gate_v_m > 0):
            raise ValueError("matching gates must be > 0")
        if not self.ended_s >= 0:
            raise ValueError("ended_s must be >= 0")
        if self.max_gap_s is not None and not self.max_gap_s > 0:
            raise ValueError("max_gap_s must be > 0 or None")


def _height(frame: pl.DataFrame, prefix: str = "") -> pl.Expr:
    alt = f"{prefix}alt_m"
    if alt in frame.columns:
        return pl.col(alt).fill_null(pl.col(f"{prefix}z_m")).fill_nan(pl.col(f"{prefix}z_m"))
    return pl.col(f"{prefix}z_m")


def _split_at_gaps(tt: pl.DataFrame, max_gap_s: float) -> pl.DataFrame:
    """Each aircraft's samples cut into pieces at gaps > ``max_gap_s``: ``truth_id`` becomes a
    piece id (``__aircraft`` keeps the aircraft), so that spans and interpolation stop at gaps."""
    keys = ["truth_id"] + (["run"] if "run" in tt.columns else [])
    tt = tt.sort(*keys, "time")
    brk = (pl.col("time").diff().over(keys).dt.total_microseconds() > round(max_gap_s * 1e6)).fill_null(False)
    piece = brk.cast(pl.Int64).cum_sum().over(keys)
    return tt.with_columns(pl.col("truth_id").alias("__aircraft"),
                           (pl.col("truth_id") * 1_000_000 + piece).alias("truth_id"))


def reference_at_epochs(epochs: pl.DataFrame, truth: pl.DataFrame, max_gap_s: float | None = None) -> pl.DataFrame:
    """Every reference aircraft alive at each (run, epoch) of ``epochs``, interpolated (rule 1):
    columns run, epoch, truth_id, true_<state> (and true_alt_m). A ``truth`` without ``run``
    is shared by every run (Monte-Carlo); with ``run``, each run has its own. With
    ``max_gap_s``, an aircraft is absent across gaps in its reference longer than that."""
    tt = truth.with_columns(pl.col("time").cast(TIME), pl.col("truth_id").cast(pl.Int64))
    if max_gap_s is not None:
        pieces = _split_at_gaps(tt, max_gap_s)
        ids = pieces.select("truth_id", "__aircraft").unique()
        ref = reference_at_epochs(epochs, pieces.drop("__aircraft"))
        return (ref.join(ids, on="truth_id", how="left").drop("truth_id")
                .rename({"__aircraft": "truth_id"}).select(ref.columns))
    ep = epochs.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME)).unique()
    if "run" in tt.columns:
        tt = tt.with_columns(pl.col("run").cast(pl.UInt32))
        parts = [_alive(ep.filter(pl.col("run") == r), tt.filter(pl.col("run") == r).drop("run"))
                 for r in ep["run"].unique().sort().to_list()]
        return pl.concat(parts, how="vertical_relaxed") if parts else _alive(ep, tt.drop("run"))
    return _alive(ep, tt)


def _alive(ep: pl.DataFrame, tt: pl.DataFrame) -> pl.DataFrame:
    spans = tt.group_by("truth_id").agg(pl.col("time").min().alias("__t0"), pl.col("time").max().alias("__t1"))
    alive = ep.join_where(spans, pl.col("epoch") >= pl.col("__t0"), pl.col("epoch") <= pl.col("__t1"))
    samples = alive.select("run", "epoch", "truth_id")
    if "alt_m" in tt.columns:               # truth_at interpolates alt_m when both frames have it
        samples = samples.with_columns(pl.lit(0.0).alias("alt_m"))
    return truth_at(samples, tt).drop("alt_m", strict=False)


def _candidates(tr: pl.DataFrame, ref: pl.DataFrame, cfg: MatchConfig) -> tuple[NDArray, NDArray, NDArray]:
    """(track row, reference row, cost) of every gated pair (rule 2)."""
    keys = ["run", "method", "epoch"]
    groups = pl.concat([tr.select(keys), ref.select(keys)]).unique().with_row_index("__g")
    gt = tr.select(keys).join(groups, on=keys, how="left", maintain_order="left")["__g"].to_numpy()
    gr = ref.select(keys).join(groups, on=keys, how="left", maintain_order="left")["__g"].to_numpy()
    # the group index offsets x so that one tree serves every epoch (groups 1e4 gates apart)
    off = 1e4 * cfg.gate_h_m
    pt = np.column_stack([tr["x_m"].to_numpy() + gt * off, tr["y_m"].to_numpy()])
    pr = np.column_stack([ref["true_x_m"].to_numpy() + gr * off, ref["true_y_m"].to_numpy()])
    if len(pt) == 0 or len(pr) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    # every (track row, reference row) within the gate in one call, no Python loop over rows;
    # sorted by (i, j), the order a per-row ball query gave
    near = cKDTree(pt).sparse_distance_matrix(cKDTree(pr), cfg.gate_h_m, output_type="ndarray")
    order = np.lexsort((near["j"], near["i"]))
    i, j = near["i"][order].astype(np.int64), near["j"][order].astype(np.int64)
    ht = tr.select(_height(tr)).to_series().to_numpy()
    hr = ref.select(_height(ref, "true_")).to_series().to_numpy()
    dh2 = ((pt[i] - pr[j]) ** 2).sum(axis=1) / cfg.gate_h_m ** 2
    dv = np.abs(ht[i] - hr[j])
    keep = (gt[i] == gr[j]) & (dv <= cfg.gate_v_m)
    return i[keep], j[keep], dh2[keep] + (dv[keep] / cfg.gate_v_m) ** 2


def _assign(i: NDArray, j: NDArray, cost: NDArray, n_t: int, n_r: int) -> NDArray[np.int64]:
    """Reference row matched to each track row (−1: none), one-to-one (rule 3)."""
    out = np.full(n_t, -1, np.int64)
    if len(i) == 0:
        return out
    graph = coo_matrix((np.ones(len(i)), (i, n_t + j)), shape=(n_t + n_r, n_t + n_r))
    _, label = connected_components(graph, directed=False)
    comp = label[i]
    size = np.bincount(comp, minlength=label.max() + 1)
    simple = size[comp] == 1                         # one candidate pair in the component
    out[i[simple]] = j[simple]
    rest = np.flatnonzero(~simple)
    if len(rest):
        order = rest[np.argsort(comp[rest], kind="stable")]
        bounds = np.flatnonzero(np.diff(comp[order])) + 1
        for block in np.split(order, bounds):        # ambiguous components only (a few)
            ti, ri = np.unique(i[block], return_inverse=True)
            tj, rj = np.unique(j[block], return_inverse=True)
            big = 1e6
            m = np.full((len(ti), len(tj)), big)
            m[ri, rj] = cost[block]
            rows, cols = linear_sum_assignment(m)
            ok = m[rows, cols] < big
            out[ti[rows[ok]]] = tj[cols[ok]]
    return out


def _last_samples(truth: pl.DataFrame, before) -> pl.DataFrame:
    """The last sample in ``truth`` of each aircraft whose samples there all lie before
    ``before`` (its end, unless ``truth`` is a slice it goes on after): run (when given),
    truth_id, time, position, velocity, height and its rate. A hash aggregation and a join on the
    few that ended: no sort of the slice."""
    keys = ["truth_id"] + (["run"] if "run" in truth.columns else [])
    t = pl.col("time").cast(TIME)
    ends = truth.group_by(keys).agg(t.max().alias("__t")).filter(pl.col("__t") < before)
    rate = "alt_rate_mps" if "alt_m" in truth.columns and "alt_rate_mps" in truth.columns else "vz_mps"
    return (truth.join(ends, on=keys, how="inner").filter(t == pl.col("__t"))
            .select(*(pl.col(k) for k in keys), "__t", "x_m", "y_m", "vx_mps", "vy_mps", _height(truth).alias("__h"),
                    pl.col(rate).alias("__hr"))
            .unique(keys, keep="first"))


def _beyond(tr: pl.DataFrame, free: NDArray[np.bool_], truth: pl.DataFrame, cfg: MatchConfig) -> pl.Series:
    """``beyond_truth_id`` of the rows of ``tr`` (rule 4): for each ``free`` row (in no gate),
    the nearest aircraft whose last sample, at most ``ended_s`` before the row's epoch and
    dead-reckoned to it, has the row in its gates (ties: the smaller ``truth_id``); null otherwise."""
    out = np.full(tr.height, -1, np.int64)
    if cfg.ended_s > 0 and free.any() and truth.height:
        rows = tr.filter(pl.Series(free)).select("__row", pl.col("run").cast(pl.UInt32), "epoch", "x_m", "y_m",
                                                 _height(tr).alias("__rh"))
        last = _last_samples(truth, rows["epoch"].max())
        if last.height:
            row, truth_id = _beyond_pairs(rows, last, cfg)
            out[row] = truth_id
    return pl.Series("beyond_truth_id", out).cast(pl.Int64).replace(-1, None)


def _floats(frame: pl.DataFrame, *columns: str) -> list[NDArray[np.float64]]:
    """``columns`` of ``frame`` as float arrays, a null as NaN (it then passes no gate)."""
    return [frame[c].cast(pl.Float64).to_numpy() for c in columns]


def _beyond_pairs(rows: pl.DataFrame, last: pl.DataFrame, cfg: MatchConfig) -> tuple[NDArray, NDArray]:
    """(``__row``, truth_id) of each row of ``rows`` and the nearest aircraft of ``last``
    (:func:`_last_samples`) whose dead-reckoned last sample has it in its gates.

    Only pairs within a radius of the midpoint of the aircraft's dead-reckoned path are tested:
    a row at distance d ≤ gate from the position at dt ∈ (0, ended_s] is at most
    gate + |v|·ended_s/2 from that midpoint, so the radius keeps every pair the gates keep. A
    window where hundreds of aircraft end (the last one of a recording) would otherwise test
    every free row against every ended aircraft (memory of the order of their product)."""
    rx, ry, rh = _floats(rows, "x_m", "y_m", "__rh")
    lx, ly, vx, vy, lh, lhr = _floats(last, "x_m", "y_m", "vx_mps", "vy_mps", "__h", "__hr")
    rt = rows["epoch"].dt.epoch("us").to_numpy()
    lt = last["__t"].dt.epoch("us").to_numpy()
    ended_us = round(cfg.ended_s * 1e6)
    ok_r = np.flatnonzero(np.isfinite(rx) & np.isfinite(ry))
    ok_l = np.flatnonzero(np.isfinite(lx) & np.isfinite(ly) & np.isfinite(vx) & np.isfinite(vy))
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if not (len(ok_r) and len(ok_l)):
        return none
    half = cfg.ended_s / 2.0
    mid = np.column_stack([lx[ok_l] + vx[ok_l] * half, ly[ok_l] + vy[ok_l] * half])
    reach = cfg.gate_h_m + float(np.hypot(vx[ok_l], vy[ok_l]).max()) * half
    near = cKDTree(np.column_stack([rx[ok_r], ry[ok_r]])).sparse_distance_matrix(
        cKDTree(mid), reach * (1 + 1e-9) + 1e-6, output_type="ndarray")
    i, j = ok_r[near["i"]], ok_l[near["j"]]
    live = (rt[i] > lt[j]) & (rt[i] <= lt[j] + ended_us)
    if "run" in last.columns:
        live &= rows["run"].to_numpy()[i] == last["run"].cast(pl.UInt32).to_numpy()[j]
    i, j = i[live], j[live]
    dt = (rt[i] - lt[j]) / 1e6
    d = np.sqrt((rx[i] - lx[j] - vx[j] * dt) ** 2 + (ry[i] - ly[j] - vy[j] * dt) ** 2)
    dv = np.abs(rh[i] - lh[j] - lhr[j] * dt)
    gated = (d <= cfg.gate_h_m) & (dv <= cfg.gate_v_m)
    i, j, d = i[gated], j[gated], d[gated]
    if not len(i):
        return none
    ids = last["truth_id"].to_numpy()[j]
    order = np.lexsort((ids, d, i))                 # per row: the nearest, then the smaller id
    first = order[np.r_[True, np.diff(i[order]) != 0]]
    return rows["__row"].to_numpy()[i[first]], ids[first]


def match_to_reference(tracks: pl.DataFrame, truth: pl.DataFrame, cfg: MatchConfig = MatchConfig(),
                       id_col: str = "track_id") -> pl.DataFrame:
    """The rows of ``tracks`` (run, epoch, ``id_col``, method, x_m … vz_mps[, alt_m]) with the
    matched reference aircraft (module docstring): ``truth_id`` (null if unmatched),
    ``true_x_m … true_vz_mps`` (``true_alt_m`` when the reference has heights),
    ``match_cost``, ``gated_truth_id`` and, when the reference has them, the aircraft's
    ``icao24``, ``true_callsign`` and ``true_mode_3a``."""
    return match_with_reference(tracks, truth, cfg, id_col)[0]


def reference_identity(truth: pl.DataFrame) -> pl.DataFrame | None:
    """(truth_id, icao24, true_callsign, true_mode_3a) of each reference aircraft, from its first
    sample (the items the reference has; None when it has none): what identity correctness
    compares a picture's items with."""
    items = {c: n for c, n in (("icao24", "icao24"), ("callsign", "true_callsign"), ("mode_3a", "true_mode_3a"))
             if c in truth.columns}
    if not items:
        return None
    return (truth.select(pl.col("truth_id").cast(pl.Int64), *[pl.col(c).cast(pl.String).alias(n)
                                                             for c, n in items.items()])
            .unique("truth_id", keep="first", maintain_order=True))


def with_neighbours(truth: pl.DataFrame) -> pl.DataFrame:
    """``truth`` with each sample's neighbouring sample times of the same aircraft (``__prev``,
    ``__next``): what :func:`reference_between` cuts a time slice with."""
    return truth.hstack(neighbour_times(truth).drop("time").get_columns())


def neighbour_times(truth: pl.DataFrame) -> pl.DataFrame:
    """(time, ``__prev``, ``__next``) of each sample of ``truth``, in its row order: the sample's
    time and its aircraft's previous and next sample times — :func:`between_mask` cuts a time
    slice with these three columns alone, never a copy of the reference (memory of the
    evaluation)."""
    keys = ["truth_id"] + (["run"] if "run" in truth.columns else [])
    t = pl.col("time").cast(TIME)
    return truth.select(pl.col("time"), t.shift(1).over(keys, order_by=t).alias("__prev"),
                        t.shift(-1).over(keys, order_by=t).alias("__next"))


def between_mask(times: pl.DataFrame, t0, t1) -> pl.Series:
    """Which samples the reference at any time in [t0, t1] reads (rule 1): those inside, and
    each aircraft's last sample before and first after — so spans, gaps and interpolation on
    the slice are those of the whole reference. ``times``: :func:`neighbour_times`."""
    return times.select(between_expr(t0, t1).alias("keep"))["keep"]


def between_expr(t0, t1) -> pl.Expr:
    """:func:`between_mask` as an expression on ``time``, ``__prev`` and ``__next`` (a lazy scan
    of a reference file filters with it)."""
    t = pl.col("time")
    keep = t.is_between(t0, t1) | ((t < t0) & (pl.col("__next") >= t0)) | ((t > t1) & (pl.col("__prev") <= t1))
    return keep.fill_null(False)


def reference_between(neighboured: pl.DataFrame, t0, t1) -> pl.DataFrame:
    """The reference samples that the reference at any time in [t0, t1] reads
    (:func:`between_mask`). ``neighboured``: :func:`with_neighbours` of the reference."""
    return neighboured.filter(between_mask(neighboured, t0, t1)).drop("__prev", "__next")


def picture_epochs(tracks: pl.DataFrame) -> pl.DataFrame:
    """The (run, epoch) of each row of a picture as the matcher keys them (run 0 without a
    ``run`` column)."""
    run = pl.col("run").cast(pl.UInt32) if "run" in tracks.columns else pl.lit(0, pl.UInt32).alias("run")
    return tracks.select(run, pl.col("epoch").cast(TIME))


def match_with_reference(tracks: pl.DataFrame, truth: pl.DataFrame, cfg: MatchConfig = MatchConfig(),
                         id_col: str = "track_id", identity: pl.DataFrame | None = None,
                         expected: pl.DataFrame | None = None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`match_to_reference`, and the reference at the picture's epochs
    (:func:`reference_at_epochs` of its (run, epoch)), computed once for both: what the
    evaluation expects covered. ``identity``: :func:`reference_identity` of the whole reference
    when ``truth`` is a time slice of it (:func:`reference_between`). ``expected``: the reference
    at a superset of the picture's (run, epoch) (:func:`picture_epochs`), made once for several
    pictures of the same epochs; it is cut to the picture's."""
    tr = tracks
    if "run" not in tr.columns:
        tr = tr.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    if "method" not in tr.columns:
        tr = tr.with_columns(pl.lit("picture").alias("method"))
    tr = tr.with_columns(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME)).with_row_index("__row")
    if expected is None:
        expected = reference_at_epochs(tr.select("run", "epoch"), truth, cfg.max_gap_s)
    else:
        expected = expected.join(tr.select("run", "epoch").unique(), on=["run", "epoch"], how="semi",
                                 maintain_order="left")
    methods = tr.select("method").unique()
    ref = expected.join(methods, how="cross").join(tr.select("run", "method", "epoch").unique(),
                                                   on=["run", "method", "epoch"], how="semi")
    i, j, cost = _candidates(tr, ref, cfg)
    best = _assign(i, j, cost, tr.height, ref.height)
    cost_of = np.full(tr.height, np.nan)
    gated = np.where(best >= 0, best, -1)
    if len(i):
        hit = best[i] == j
        cost_of[i[hit]] = cost[hit]
        order = np.lexsort((cost, i))                # per track row, its cheapest candidate first
        first = order[np.r_[True, np.diff(i[order]) != 0]]
        free = best[i[first]] < 0
        gated[i[first][free]] = j[first][free]
    true_cols = [c for c in ref.columns if c.startswith("true_")] + (["segment"] if "segment" in ref.columns else [])
    matched = best >= 0
    if ref.height == 0:                       # no reference aircraft alive at any track epoch
        ref_rows = pl.DataFrame(schema=ref.select("truth_id", *true_cols).schema).clear(n=tr.height)
    else:
        ref_rows = ref.select("truth_id", *true_cols)[np.where(matched, best, 0)]
    ref_rows = ref_rows.select(*(pl.when(pl.Series(matched)).then(pl.col(c)).otherwise(None).alias(c)
                                 for c in ref_rows.columns))
    ids = ref["truth_id"].to_numpy() if ref.height else np.zeros(1, np.int64)
    gated_id = (pl.when(pl.Series(gated >= 0)).then(pl.Series(ids[np.maximum(gated, 0)] if ref.height
                                                              else np.zeros(tr.height, np.int64)))
                .otherwise(None).cast(pl.Int64).alias("gated_truth_id"))
    beyond = _beyond(tr, gated < 0, truth, cfg)
    out = (tr.drop("__row").drop([c for c in ("truth_id", *true_cols, "icao24", "gated_truth_id", "beyond_truth_id")
                                  if c in tr.columns])
           .hstack(ref_rows).with_columns(pl.Series("match_cost", cost_of), gated_id, beyond))
    # the reference's identity items, for identity correctness: Mode S address, callsign, Mode 3/A
    ident = reference_identity(truth) if identity is None else identity
    if ident is not None:
        out = out.drop([n for n in ident.columns if n != "truth_id" and n in out.columns]).join(
            ident, on="truth_id", how="left", maintain_order="left")
    return out, expected
