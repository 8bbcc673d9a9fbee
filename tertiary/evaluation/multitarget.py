"""The field's standard multi-target metrics of a picture against the truth at its epochs.

Each (run, epoch) of a picture is a pair of finite sets: the picture's track positions
X = {x_1 … x_N} and the truth positions Y = {y_1 … y_M} interpolated at that epoch
(:func:`tertiary.evaluation.matching.reference_at_epochs`, the reference the matcher uses).
Positions are local ENU (x, y, z) in metres; d(x, y) is their Euclidean distance. These metrics
use their own definitions' assignment, not the project's matcher, so that they equal the
literature's and Stone Soup's.

OSPA (Schuhmacher, Vo & Vo 2008), cut-off c, order 1 ≤ p < ∞, n = max(N, M), m = min(N, M)::

    OSPA = ( (1/n) ( min_π Σ_{i≤m} min(d, c)^p + c^p (n − m) ) )^(1/p)

GOSPA (Rahmathullah, García-Fernández & Svensson 2017), α = 2::

    GOSPA = ( min_γ Σ_{(i,j)∈γ} d^p + c^p/2 (N − |γ|) + c^p/2 (M − |γ|) )^(1/p)

over partial assignments γ of pairs with d < c; the three terms are GOSPA's localisation,
false and missed parts (Stone Soup's ``localisation``, ``false``, ``missed``: sums of p-th
powers, not rooted). Both minima are the same problem — a maximum-weight matching of the pairs
with d < c, weights c^p − d^p — solved once for every epoch of a block together
(:func:`_max_weight_matching`). A picture may be given a block of epochs at a time
(:func:`multitarget_step`, :func:`multitarget_result`): the same metrics, its memory a block's.

SIAP (Votruba et al. 2001, as Stone Soup's ``SIAPMetrics`` computes them): each track state
is associated with the nearest truth at its epoch closer than the SIAP threshold (Stone Soup's
``TrackToTruth`` with one confirming and one ending state; several tracks may share a truth).
At epoch t: J truths, JT truths with an associated track, N tracks, NA associated tracks, PA
the sum of their position errors. Over the picture: completeness ΣJT/ΣJ, ambiguity ΣNA/ΣJT,
spuriousness Σ(N − NA)/ΣN, position accuracy ΣPA/ΣNA. ID continuity: a segment is a run of
consecutive states of one track associated with one truth, [first, last] epoch; for truth j,
NU_j is the fewest segments covering its associated epochs (Stone Soup's greedy), TT_j the time
its segments cover, TL_j its longest segment, T_j its lifetime. Rate of track number changes
R = Σ_j (NU_j − 1) / Σ_j TT_j (NU_j > 0), longest segment LS = Σ_j TL_j / Σ_j T_j.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, min_weight_full_bipartite_matching
from scipy.spatial import cKDTree

from tertiary.contract import TABLES, TIME

__all__ = ["METRICS", "MultiTargetConfig", "MultiTargetState", "merge_runs", "multitarget_by_epoch",
           "multitarget_metrics", "multitarget_steps",
           "multitarget_result", "multitarget_step", "siap_continuity", "started", "then"]

#: the metrics :func:`multitarget_metrics` writes (stage ``evaluation``, segment ``all``)
METRICS = ("ospa_m", "gospa_m", "gospa_localisation", "gospa_missed", "gospa_false", "siap_completeness",
           "siap_ambiguity", "siap_spuriousness", "siap_position_accuracy_m", "siap_track_changes_per_hour",
           "siap_longest_segment_frac", "multitarget_epochs")

_TRACK = ("run", "epoch", "track_id", "x_m", "y_m", "z_m")
_TRUTH = ("run", "epoch", "truth_id", "true_x_m", "true_y_m", "true_z_m")


@dataclass(frozen=True)
class MultiTargetConfig:
    """OSPA/GOSPA cut-off ``c_m`` and order ``p``; the SIAP association distance."""

    c_m: float = 1852.0
    p: float = 2.0
    siap_threshold_m: float = 1852.0

    def __post_init__(self) -> None:
        if not (self.c_m > 0 and self.siap_threshold_m > 0):
            raise ValueError("the cut-off and the SIAP threshold must be > 0")
        if not 1.0 <= self.p < np.inf:
            raise ValueError("the order p must be in [1, inf)")


def _epoch_index(tracks: pl.DataFrame, truth: pl.DataFrame) -> tuple[pl.DataFrame, NDArray, NDArray]:
    """The (run, epoch) groups of the picture, and each track / truth row's group."""
    keys = ["run", "epoch"]
    groups = tracks.select(keys).unique().sort(keys).with_row_index("g")
    gt = tracks.select(keys).join(groups, on=keys, how="left", maintain_order="left")["g"].to_numpy()
    # truth rows at epochs without a picture row are not the picture's epochs
    gr = truth.select(keys).join(groups, on=keys, how="left", maintain_order="left")["g"].fill_null(-1).to_numpy()
    return groups, gt.astype(np.int64), gr.astype(np.int64)


def _pairs(pt: NDArray, gt: NDArray, pr: NDArray, gr: NDArray, radius: float) -> tuple[NDArray, NDArray, NDArray]:
    """(track row, truth row, distance) of every pair at one epoch closer than ``radius``."""
    if len(pt) == 0 or len(pr) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    # one tree for every epoch: the group index offsets x by more than the picture's extent, so
    # epochs never meet; the tree only finds candidates (the offset costs precision), distances
    # come from the raw positions
    xs = np.concatenate([pt[:, 0], pr[:, 0]])
    off = float(xs.max() - xs.min()) + 3.0 * radius
    shift_t = np.column_stack([pt[:, 0] + gt * off, pt[:, 1:]])
    shift_r = np.column_stack([pr[:, 0] + gr * off, pr[:, 1:]])
    near = cKDTree(shift_t).sparse_distance_matrix(cKDTree(shift_r), radius * (1 + 1e-6) + 1e-3,
                                                   output_type="ndarray")
    i, j = near["i"].astype(np.int64), near["j"].astype(np.int64)
    d = np.sqrt(((pt[i] - pr[j]) ** 2).sum(axis=1))
    keep = (gt[i] == gr[j]) & (d < radius)
    order = np.lexsort((j[keep], i[keep]))
    return i[keep][order], j[keep][order], d[keep][order]


def _max_weight_matching(i: NDArray, j: NDArray, w: NDArray, n_t: int, n_r: int) -> NDArray[np.bool_]:
    """Which pairs (i, j) with weights w > 0 form a maximum-weight matching (each row at most
    once). A component with one pair is matched alone; the others are solved together as one
    full matching (LAPJVsp) in which every track and truth may also take its own dummy."""
    chosen = np.zeros(len(i), bool)
    if len(i) == 0:
        return chosen
    graph = coo_matrix((np.ones(len(i)), (i, n_t + j)), shape=(n_t + n_r, n_t + n_r))
    _, label = connected_components(graph, directed=False)
    comp = label[i]
    simple = np.bincount(comp)[comp] == 1
    chosen[simple] = True
    rest = np.flatnonzero(~simple)
    if len(rest) == 0:
        return chosen
    ti, a = np.unique(i[rest], return_inverse=True)
    tj, b = np.unique(j[rest], return_inverse=True)
    na, nb = len(ti), len(tj)
    # rows: tracks, then a dummy per truth; columns: truths, then a dummy per track. Every full
    # matching costs (na + nb)·k − Σ w of its real pairs, so the cheapest is the heaviest;
    # k > max w keeps every cost > 0 (a zero would be a missing edge)
    k = 2.0 * float(w[rest].max()) + 1.0
    ones = np.full(len(rest), k)
    rows = np.concatenate([a, np.arange(na), na + np.arange(nb), na + b])
    cols = np.concatenate([b, nb + np.arange(na), np.arange(nb), nb + a])
    cost = np.concatenate([k - w[rest], np.full(na, k), np.full(nb, k), ones])
    r, c = min_weight_full_bipartite_matching(csr_matrix((cost, (rows, cols)), shape=(na + nb, na + nb)))
    real = (r < na) & (c < nb)
    partner = np.full(na, -1)
    partner[r[real]] = c[real]
    chosen[rest] = partner[a] == b
    return chosen


def _positions(frame: pl.DataFrame, cols: tuple[str, ...]) -> NDArray:
    return frame.select(cols).to_numpy().astype(np.float64)


def _prepared(tracks: pl.DataFrame, truth: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The columns read, a shared ``run``, truth at the picture's epochs only."""
    def run(f: pl.DataFrame) -> pl.DataFrame:
        return f if "run" in f.columns else f.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    tr = run(tracks).select(_TRACK).with_columns(pl.col("run").cast(pl.UInt32))
    ref = run(truth).select(_TRUTH).with_columns(pl.col("run").cast(pl.UInt32))
    ref = ref.join(tr.select("run", "epoch").unique(), on=["run", "epoch"], how="semi", maintain_order="left")
    return tr, ref


@dataclass(frozen=True)
class _Scene:
    """One picture's rows and truth, their (run, epoch) groups and every pair of a track and a
    truth at one epoch closer than the larger of the cut-off and the SIAP distance."""

    tracks: pl.DataFrame
    truth: pl.DataFrame
    groups: pl.DataFrame
    gt: NDArray
    gr: NDArray
    i: NDArray
    j: NDArray
    d: NDArray
    #: the SIAP association: (track row, its nearest truth row, distance)
    nearest: tuple[NDArray, NDArray, NDArray]


def _scene(tracks: pl.DataFrame, truth: pl.DataFrame, cfg: MultiTargetConfig) -> _Scene:
    tr, ref = _prepared(tracks, truth)
    groups, gt, gr = _epoch_index(tr, ref)
    i, j, d = _pairs(_positions(tr, _TRACK[3:]), gt, _positions(ref, _TRUTH[3:]), gr,
                     max(cfg.c_m, cfg.siap_threshold_m))
    return _Scene(tr, ref.with_columns(pl.col("truth_id").cast(pl.Int64)), groups, gt, gr, i, j, d,
                  _nearest(i, j, d, cfg.siap_threshold_m))


def multitarget_by_epoch(tracks: pl.DataFrame, truth: pl.DataFrame,
                         cfg: MultiTargetConfig = MultiTargetConfig()) -> pl.DataFrame:
    """Per (run, epoch) of ``tracks`` (run, epoch, track_id, x_m, y_m, z_m): OSPA, GOSPA and its
    parts, and the SIAP counts (module docstring) against ``truth`` (run, epoch, truth_id,
    true_x_m, true_y_m, true_z_m: the truth at the picture's epochs). Columns: run, epoch,
    n_tracks (N), n_truths (J), ospa_m, gospa_m, gospa_localisation, gospa_missed, gospa_false,
    siap_truths_assoc (JT), siap_tracks_assoc (NA), siap_error_sum_m (PA)."""
    return _by_epoch(_scene(tracks, truth, cfg), cfg)


def _by_epoch(sc: _Scene, cfg: MultiTargetConfig) -> pl.DataFrame:
    c, p, gt, gr, n_g = cfg.c_m, cfg.p, sc.gt, sc.gr, sc.groups.height
    cut = sc.d < c
    i, d = sc.i[cut], sc.d[cut]
    won = _max_weight_matching(i, sc.j[cut], c ** p - d ** p, sc.tracks.height, sc.truth.height)
    matched = np.bincount(gt[i[won]], minlength=n_g).astype(np.float64)
    loc = np.bincount(gt[i[won]], weights=d[won] ** p, minlength=n_g)
    n_t = np.bincount(gt, minlength=n_g).astype(np.float64)
    n_r = np.bincount(gr[gr >= 0], minlength=n_g).astype(np.float64)
    n = np.maximum(n_t, n_r)
    ospa = ((loc + c ** p * (n - matched)) / n) ** (1.0 / p)
    missed, false = c ** p / 2 * (n_r - matched), c ** p / 2 * (n_t - matched)
    it, jt, dt = sc.nearest
    return sc.groups.select("run", "epoch").with_columns(
        pl.Series("n_tracks", n_t.astype(np.int64)), pl.Series("n_truths", n_r.astype(np.int64)),
        pl.Series("ospa_m", ospa), pl.Series("gospa_m", (loc + missed + false) ** (1.0 / p)),
        pl.Series("gospa_localisation", loc), pl.Series("gospa_missed", missed), pl.Series("gospa_false", false),
        pl.Series("siap_truths_assoc", np.bincount(gr[np.unique(jt)], minlength=n_g)),
        pl.Series("siap_tracks_assoc", np.bincount(gt[it], minlength=n_g)),
        pl.Series("siap_error_sum_m", np.bincount(gt[it], weights=dt, minlength=n_g)))


def _nearest(i: NDArray, j: NDArray, d: NDArray, threshold: float) -> tuple[NDArray, NDArray, NDArray]:
    """(track row, its nearest truth row, distance) for each track row with a truth closer
    than ``threshold`` (the SIAP association)."""
    near = d < threshold
    i, j, d = i[near], j[near], d[near]
    order = np.lexsort((d, i))
    first = order[np.r_[True, np.diff(i[order]) != 0]] if len(order) else order
    return i[first], j[first], d[first]


def _associations(sc: _Scene) -> pl.DataFrame:
    """Each track row (run, epoch, track_id) with its SIAP truth (``truth_id``, null: none)."""
    it, jt, _ = sc.nearest
    ids = np.full(sc.tracks.height, -1, np.int64)
    ids[it] = sc.truth["truth_id"].to_numpy()[jt]
    return sc.tracks.select("run", "epoch", "track_id").with_columns(
        pl.when(pl.Series(ids >= 0)).then(pl.Series(ids)).otherwise(None).alias("truth_id"))


def _segments(assoc: pl.DataFrame) -> pl.DataFrame:
    """Runs of consecutive states of one track associated with one truth: run, truth_id,
    track_id, start, end."""
    seq = assoc.sort("run", "track_id", "epoch")
    same = ((pl.col("track_id") == pl.col("track_id").shift(1)) & (pl.col("run") == pl.col("run").shift(1))
            & (pl.col("truth_id") == pl.col("truth_id").shift(1))).fill_null(False)
    return (seq.with_columns((~same).cum_sum().alias("__seg")).filter(pl.col("truth_id").is_not_null())
            .group_by("__seg").agg(pl.col("run", "truth_id", "track_id").first(),
                                   pl.col("epoch").min().alias("start"), pl.col("epoch").max().alias("end"))
            .drop("__seg"))


def _tracks_needed(seg: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """NU_j of each (run, truth_id) with a segment, by Stone Soup's greedy cover: at the first
    uncovered truth epoch, of the segments there take the one whose track's association with
    the truth ends last (Stone Soup merges a track's segments with a truth into one
    association), and continue at the truth epoch after that segment's end. A segment reaches
    back to the truth epoch before its start (``reach``): "there at the epoch after the covered
    end" is "reaches the covered end and ends after it". Each pass of the loop advances every
    truth at once."""
    return _greedy_cover(_with_reach(seg, truth).with_columns(
        pl.col("reach").fill_null(pl.col("start") - pl.duration(microseconds=1))))


def _with_reach(seg: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """``seg`` with ``reach``: its truth's epoch before its start in ``truth`` (null: none)."""
    key = ["run", "truth_id"]
    times = truth.select(*key, pl.col("epoch").alias("reach")).sort("reach")
    return seg.sort("start").join_asof(times, left_on="start", right_on="reach", by=key, strategy="backward",
                                       allow_exact_matches=False, check_sortedness=False)


def _greedy_cover(seg: pl.DataFrame, key: Sequence[str] = ("run", "truth_id")) -> pl.DataFrame:
    """:func:`_tracks_needed` of segments with their ``reach``, by ``key`` (a truth; before it,
    a picture's key when the segments of several are covered at once)."""
    key = list(key)
    seg = (seg.with_columns(pl.col("end").max().over(*key, "track_id").alias("last"))
           .sort(*key, "last", "end", "track_id"))
    t0 = seg["reach"].min()
    reach, end, last = ((seg[c] - t0).dt.total_microseconds().to_numpy() + 1 for c in ("reach", "end", "last"))
    new = pl.any_horizontal(pl.col(k) != pl.col(k).shift(1) for k in key)
    grp = seg.select(new.fill_null(True).cum_sum() - 1).to_series().to_numpy().astype(np.int64)
    n_grp = int(grp[-1]) + 1
    covered = np.zeros(n_grp, np.int64)
    count = np.zeros(n_grp, np.int64)
    live = np.ones(n_grp, bool)
    while live.any():
        ahead = live[grp] & (end > covered[grp])
        here = ahead & (reach <= covered[grp])
        # rows are in (truth, last, end) order: the last candidate row of a truth is its pick
        rows = np.flatnonzero(here)
        pick = rows[np.r_[grp[rows][1:] != grp[rows][:-1], True]] if len(rows) else rows
        covered[grp[pick]] = end[pick]
        count[grp[pick]] += 1
        # nothing there: resume at the nearest reach ahead
        idle = np.flatnonzero(ahead & ~np.isin(grp, grp[pick]))
        if len(idle):
            first = np.full(n_grp, np.iinfo(np.int64).max)
            np.minimum.at(first, grp[idle], reach[idle])
            gi = np.unique(grp[idle])
            covered[gi] = first[gi]
        live[:] = False
        live[grp[ahead]] = True
    out = seg.select(key).with_columns(pl.Series("__g", grp)).unique("__g", keep="first").sort("__g")
    return out.select(key).with_columns(pl.Series("nu", count))


def _union_s(seg: pl.DataFrame, key: Sequence[str] = ("run", "truth_id")) -> pl.DataFrame:
    """TT_j: seconds of each ``key`` (a truth) covered by the union of its segments."""
    key = list(key)
    prev = pl.col("end").cum_max().shift(1).over(key, order_by="start")
    lo = pl.max_horizontal("start", prev.fill_null(pl.col("start")))
    piece = pl.max_horizontal((pl.col("end") - lo).dt.total_microseconds(), pl.lit(0))
    return seg.group_by(key).agg((piece / 1e6).sum().alias("tt_s"))


def siap_continuity(tracks: pl.DataFrame, truth: pl.DataFrame,
                    cfg: MultiTargetConfig = MultiTargetConfig()) -> tuple[float, float]:
    """(R in track number changes per second, LS): the SIAP continuity of ``tracks`` against
    ``truth`` (the frames of :func:`multitarget_by_epoch`; module docstring)."""
    return _continuity(_scene(tracks, truth, cfg))


def _continuity(sc: _Scene) -> tuple[float, float]:
    seg = _segments(_associations(sc))
    return _continuity_of(seg, sc.truth, _lifetimes(sc.truth))


def _lifetimes(ref: pl.DataFrame) -> pl.DataFrame:
    """(run, truth_id, first, last) epoch of each truth at the picture's epochs."""
    return ref.group_by("run", "truth_id").agg(pl.col("epoch").min().alias("first"),
                                               pl.col("epoch").max().alias("last"))


def _continuity_of(seg: pl.DataFrame, ref: pl.DataFrame | None, life: pl.DataFrame) -> tuple[float, float]:
    """(R, LS) of the segments ``seg`` (with ``reach`` when ``ref`` is None) and lifetimes."""
    key = ["run", "truth_id"]
    total = float(((life["last"] - life["first"]).dt.total_microseconds() / 1e6).sum()) if life.height else 0.0
    if seg.height == 0:
        return 0.0, 0.0
    # a track's segments with one truth are one association in Stone Soup: TL_j is the longest
    # total time one track is associated with the truth
    per_track = seg.group_by(*key, "track_id").agg(
        ((pl.col("end") - pl.col("start")).dt.total_microseconds() / 1e6).sum().alias("s"))
    longest = float(per_track.group_by(key).agg(pl.col("s").max())["s"].sum())
    tt = float(_union_s(seg)["tt_s"].sum())
    cover = (_tracks_needed(seg, ref) if ref is not None else _greedy_cover(seg.with_columns(
        pl.col("reach").fill_null(pl.col("start") - pl.duration(microseconds=1)))))
    changes = float((cover["nu"] - 1).sum())
    return (changes / tt if tt else 0.0), (longest / total if total else 0.0)


def multitarget_metrics(tracks: pl.DataFrame, truth: pl.DataFrame, method: str,
                        cfg: MultiTargetConfig = MultiTargetConfig()) -> pl.DataFrame:
    """The :data:`METRICS` rows of one picture (metrics schema, stage ``evaluation``, segment
    ``all``): OSPA, GOSPA and its parts as means over the picture's (run, epoch), the SIAP
    measures pooled over them as Stone Soup pools them (module docstring)."""
    sc = _scene(tracks, truth, cfg)
    ep = _by_epoch(sc, cfg)
    return _metric_rows(method, _sums(ep), _continuity(sc), ep["run"].unique())


#: what the epochs' rows add up to (:func:`_sums`): the epoch means' numerators, then the SIAP counts
_MEANS = ("ospa_m", "gospa_m", "gospa_localisation", "gospa_missed", "gospa_false")
_COUNTS = ("n_truths", "siap_truths_assoc", "n_tracks", "siap_tracks_assoc", "siap_error_sum_m")


def _sums(ep: pl.DataFrame) -> NDArray:
    """(epochs, Σ of each of :data:`_MEANS` and :data:`_COUNTS`) of :func:`_by_epoch` rows."""
    return np.array([float(ep.height), *(float(ep[c].sum()) for c in (*_MEANS, *_COUNTS))])


def _metric_rows(method: str, sums: NDArray, continuity: tuple[float, float], runs: pl.Series) -> pl.DataFrame:
    n_ep, means, (j, jt, n, na, pa) = sums[0], sums[1:1 + len(_MEANS)], sums[1 + len(_MEANS):]
    rate, longest = continuity
    values = [*(float(m / n_ep) if n_ep else float("nan") for m in means),
              jt / j if j else 0.0, na / jt if jt else 1.0, (n - na) / n if n else 0.0,
              pa / na if na else 0.0, 3600.0 * rate, longest, float(n_ep)]
    return pl.DataFrame({"stage": "evaluation", "method": method, "metric": list(METRICS), "segment": "all",
                         "value": values, "n_runs": runs.n_unique()}
                        ).select([pl.col(c).cast(t) for c, t in TABLES["metrics"].required.items()])


@dataclass(frozen=True)
class MultiTargetState:
    """:func:`multitarget_metrics` of a picture given in blocks of whole epochs in time order
    (:func:`multitarget_step`): the epoch sums, the runs, each truth's lifetime, the closed
    SIAP segments, and the open ones — a track's segment holding its latest state, which its
    next state (in a later block) may continue. Its size is the segments', not the rows'."""

    sums: NDArray = field(default_factory=lambda: np.zeros(1 + len(_MEANS) + len(_COUNTS)))
    runs: pl.Series = field(default_factory=lambda: pl.Series("run", [], pl.UInt32))
    life: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_LIFE))
    closed: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_SEGMENT))
    open: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_SEGMENT))
    #: each track's first state stepped in (run, track_id, its SIAP truth ``head``, ``head_epoch``),
    #: kept by a state that starts a later stretch of the picture (:func:`started`) for
    #: :func:`then`; None: not kept
    heads: pl.DataFrame | None = None


def merge_runs(states: Sequence[MultiTargetState]) -> MultiTargetState:
    """One picture's state over runs stepped apart (each state holds runs of its own): the
    epochs' terms add up, and every lifetime and segment belongs to one run."""
    states = list(states)
    if len(states) == 1:
        return states[0]
    return MultiTargetState(sums=np.sum([s.sums for s in states], axis=0),
                            runs=pl.concat([s.runs for s in states]).unique(),
                            life=pl.concat([s.life for s in states]), closed=pl.concat([s.closed for s in states]),
                            open=pl.concat([s.open for s in states]))


_LIFE = {"run": pl.UInt32, "truth_id": pl.Int64, "first": TIME, "last": TIME}
_SEGMENT = {"run": pl.UInt32, "truth_id": pl.Int64, "track_id": pl.UInt64, "start": TIME, "end": TIME,
            "reach": TIME}


def multitarget_step(state: MultiTargetState, tracks: pl.DataFrame, truth: pl.DataFrame,
                     cfg: MultiTargetConfig = MultiTargetConfig()) -> MultiTargetState:
    """``state`` after one block of a picture (the frames of :func:`multitarget_by_epoch`; its
    epochs after every earlier block's). The per-epoch terms only add up; a SIAP segment runs
    over consecutive states of a track, so the segment holding a track's latest state stays
    open until its next state shows another truth or none."""
    if tracks.height == 0:
        return state
    sc = _scene(tracks, truth, cfg)
    ep = _by_epoch(sc, cfg)
    life, closed, still, firsts = _carried(state, sc)
    heads = state.heads
    if heads is not None:
        new = firsts.select("run", "track_id", "head", "head_epoch").join(heads, on=["run", "track_id"], how="anti")
        heads = pl.concat([heads, new.cast(_HEAD)])
    return MultiTargetState(sums=state.sums + _sums(ep), runs=pl.concat([state.runs, ep["run"].unique()]).unique(),
                            life=life, closed=closed, open=still, heads=heads)


_HEAD = {"run": pl.UInt32, "track_id": pl.UInt64, "head": pl.Int64, "head_epoch": TIME}


def started() -> MultiTargetState:
    """The state from which a later stretch of a picture is stepped apart (it keeps each track's
    first state), to be joined to the stretch before it by :func:`then`."""
    return MultiTargetState(heads=pl.DataFrame(schema=_HEAD))


def then(before: MultiTargetState, after: MultiTargetState) -> MultiTargetState:
    """The state of a picture stepped through ``before``'s blocks and then ``after``'s, from
    ``after`` stepped alone from :func:`started`: what one state carried through both gives. The
    epoch sums add; a segment of ``after`` whose reach is unknown reaches back to its truth's
    last epoch in ``before``; a segment ``before`` left open goes on where its track's first
    state in ``after`` shows its truth (the segment starting there takes its start and reach),
    ends where it shows another or none, and stays open where the track is not in ``after``."""
    if after.heads is None:
        raise ValueError("then: the later state must be stepped from started()")
    key = ["run", "truth_id"]
    life = pl.concat([before.life, after.life]).group_by(key).agg(pl.col("first").min(), pl.col("last").max())
    last = before.life.select(*key, pl.col("last").alias("__before"))

    def reached(seg: pl.DataFrame) -> pl.DataFrame:
        return (seg.join(last, on=key, how="left", maintain_order="left")
                .with_columns(pl.coalesce("reach", "__before").alias("reach")).drop("__before"))
    opened = before.open.join(after.heads, on=["run", "track_id"], how="left")
    goes_on = (pl.col("head") == pl.col("truth_id")).fill_null(False)
    carried = opened.filter(goes_on).select("run", "track_id", "truth_id", pl.col("start").alias("start_old"),
                                             pl.col("reach").alias("reach_old"), "head_epoch")
    ended = opened.filter(~goes_on & pl.col("head_epoch").is_not_null()).select(list(_SEGMENT))
    still = opened.filter(pl.col("head_epoch").is_null()).select(list(_SEGMENT))

    def continued(seg: pl.DataFrame) -> pl.DataFrame:
        j = reached(seg).join(carried, left_on=["run", "track_id", "truth_id", "start"],
                              right_on=["run", "track_id", "truth_id", "head_epoch"], how="left",
                              maintain_order="left")
        merged = pl.col("start_old").is_not_null()
        return j.with_columns(pl.when(merged).then("start_old").otherwise("start").alias("start"),
                              pl.when(merged).then("reach_old").otherwise("reach").alias("reach")
                              ).select(list(_SEGMENT))
    return MultiTargetState(sums=before.sums + after.sums, runs=pl.concat([before.runs, after.runs]).unique(),
                            life=life, closed=pl.concat([before.closed, ended, continued(after.closed)]),
                            open=pl.concat([still, continued(after.open)]),
                            heads=None if before.heads is None else pl.concat(
                                [before.heads, after.heads.join(before.heads, on=["run", "track_id"], how="anti")]))


#: the bits of a run number in the joint key of several pictures (:func:`multitarget_steps`)
_RUN_BITS = 24


def multitarget_steps(states: Mapping[str, MultiTargetState], blocks: Sequence[tuple[str, pl.DataFrame, pl.DataFrame]],
                      cfg: MultiTargetConfig = MultiTargetConfig()) -> dict[str, MultiTargetState]:
    """:func:`multitarget_step` of several pictures' blocks (name, tracks, truth) at once: each
    picture's ``run`` is keyed apart (picture index above the run's bits), so every group,
    segment and lifetime stays the picture's, and a window's few dozen table operations are paid
    once, not once per picture. Pictures absent from ``states`` start from the initial state."""
    out = dict(states)
    blocks = [b for b in blocks if b[1].height]
    runs = [b[1]["run"].max() for b in blocks] + [b[2]["run"].max() for b in blocks if b[2].height]
    if len(blocks) <= 1 or len(blocks) >= 1 << (32 - _RUN_BITS) or max(int(r or 0) for r in runs) >= 1 << _RUN_BITS:
        for name, tracks, truth in blocks:
            out[name] = multitarget_step(out.get(name, MultiTargetState()), tracks, truth, cfg)
        return out

    def keyed(frames: Sequence[pl.DataFrame]) -> pl.DataFrame:
        return pl.concat([f.with_columns(pl.col("run").cast(pl.UInt32) + pl.lit(k << _RUN_BITS, pl.UInt32))
                          for k, f in enumerate(frames)])
    before = [out.get(name, MultiTargetState()) for name, _, _ in blocks]
    # the closed segments only grow: each picture's are not copied through the joint frames
    # (a long run's would be, at every window), the window's new ones are added to them
    joint = MultiTargetState(life=keyed([b.life for b in before]), open=keyed([b.open for b in before]))
    sc = _scene(keyed([b[1] for b in blocks]), keyed([b[2] for b in blocks]), cfg)
    ep = _by_epoch(sc, cfg)
    life, closed, still, _ = _carried(joint, sc)
    # each picture's rows, its own run numbers back: one pass per frame, not one per picture
    split = [_by_picture(f) for f in (ep, life, closed, still)]
    for k, ((name, _, _), prev) in enumerate(zip(blocks, before)):
        mine = [part.get(k, f.clear()) for part, f in zip(split, (ep, life, closed, still))]
        out[name] = MultiTargetState(sums=prev.sums + _sums(mine[0]),
                                     runs=pl.concat([prev.runs, mine[0]["run"].unique()]).unique(),
                                     life=mine[1], closed=pl.concat([prev.closed, mine[2]]), open=mine[3])
    return out


def _by_picture(frame: pl.DataFrame) -> dict[int, pl.DataFrame]:
    """The rows of a joint frame of :func:`multitarget_steps` by picture index, with their own runs."""
    pic = (pl.col("run") // (1 << _RUN_BITS)).alias("__pic")
    parts = frame.with_columns(pic, pl.col("run") % (1 << _RUN_BITS)).partition_by("__pic", as_dict=True,
                                                                                    include_key=False)
    return {int(k[0]): v for k, v in parts.items()}


def _carried(state: MultiTargetState, sc: _Scene
             ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(lifetimes, closed segments, open segments) of ``state`` after the block of ``sc``, and
    each track's first state in the block (run, track_id, head, head_epoch, __last)."""
    key = ["run", "truth_id"]
    assoc = _associations(sc).with_columns(pl.col("track_id").cast(pl.UInt64))
    seg = _with_reach(_segments(assoc), sc.truth).join(
        state.life.select(*key, pl.col("last").alias("__before")), on=key, how="left")
    seg = seg.with_columns(pl.coalesce("reach", "__before").alias("reach")).drop("__before")
    firsts = assoc.sort("epoch").group_by("run", "track_id").agg(pl.col("truth_id").first().alias("head"),
                                                                 pl.col("epoch").first().alias("head_epoch"),
                                                                 pl.col("epoch").last().alias("__last"))
    # an open segment goes on where its track's first state here shows its truth
    opened = state.open.join(firsts, on=["run", "track_id"], how="left")
    goes_on = (pl.col("head") == pl.col("truth_id")).fill_null(False)
    carried = opened.filter(goes_on).select("run", "track_id", "truth_id", "start", "reach", "head_epoch")
    ended = opened.filter(~goes_on & pl.col("head_epoch").is_not_null()).select(list(_SEGMENT))
    still = opened.filter(pl.col("head_epoch").is_null()).select(list(_SEGMENT))
    joined = seg.join(carried, left_on=["run", "track_id", "truth_id", "start"],
                      right_on=["run", "track_id", "truth_id", "head_epoch"], how="left", suffix="_old")
    merged = pl.col("start_old").is_not_null()
    seg = joined.with_columns(pl.when(merged).then("start_old").otherwise("start").alias("start"),
                              pl.when(merged).then("reach_old").otherwise("reach").alias("reach")
                              ).select(list(_SEGMENT))
    # the segment holding a track's latest state here stays open
    seg = seg.join(firsts.select("run", "track_id", "__last"), on=["run", "track_id"], how="left")
    is_open = pl.col("end") == pl.col("__last")
    life = pl.concat([state.life, _lifetimes(sc.truth).select(list(_LIFE))]).group_by(key).agg(
        pl.col("first").min(), pl.col("last").max())
    return (life, pl.concat([state.closed, ended, seg.filter(~is_open).select(list(_SEGMENT))]),
            pl.concat([still, seg.filter(is_open).select(list(_SEGMENT))]), firsts)


def multitarget_result(state: MultiTargetState, method: str) -> pl.DataFrame:
    """The :data:`METRICS` rows of the blocks stepped into ``state`` (:func:`multitarget_metrics`
    of their union)."""
    seg = pl.concat([state.closed, state.open])
    return _metric_rows(method, state.sums, _continuity_of(seg, None, state.life), state.runs)


def multitarget_results(states: Mapping[str, MultiTargetState]) -> dict[str, pl.DataFrame]:
    """:func:`multitarget_result` of every picture's state (by name), their continuity in one
    pass over every picture's segments (a picture is a key beside each truth's)."""
    if not states:
        return {}
    tag = [pl.lit(i, pl.UInt32).alias("__p") for i in range(len(states))]
    seg = pl.concat([pl.concat([s.closed, s.open]).with_columns(t) for s, t in zip(states.values(), tag)])
    life = pl.concat([s.life.with_columns(t) for s, t in zip(states.values(), tag)])
    continuity = _continuity_each(seg, life)
    return {name: _metric_rows(name, s.sums, continuity.get(i, (0.0, 0.0)), s.runs)
            for i, (name, s) in enumerate(states.items())}


def _continuity_each(seg: pl.DataFrame, life: pl.DataFrame) -> dict[int, tuple[float, float]]:
    """:func:`_continuity_of` (segments with ``reach``) of each picture ``__p`` of ``seg`` and
    ``life``; a picture without a segment has none."""
    key = ["__p", "run", "truth_id"]
    if seg.height == 0:
        return {}
    total = life.group_by("__p").agg(((pl.col("last") - pl.col("first")).dt.total_microseconds() / 1e6).sum()
                                     .alias("total"))
    per_track = seg.group_by(*key, "track_id").agg(
        ((pl.col("end") - pl.col("start")).dt.total_microseconds() / 1e6).sum().alias("s"))
    longest = per_track.group_by(key).agg(pl.col("s").max()).group_by("__p").agg(pl.col("s").sum().alias("longest"))
    tt = _union_s(seg, key).group_by("__p").agg(pl.col("tt_s").sum())
    cover = _greedy_cover(seg.with_columns(pl.col("reach").fill_null(pl.col("start") - pl.duration(microseconds=1))),
                          key)
    changes = cover.group_by("__p").agg((pl.col("nu") - 1).sum().cast(pl.Float64).alias("changes"))
    got = (longest.join(tt, on="__p", how="left").join(changes, on="__p", how="left")
           .join(total, on="__p", how="left").fill_null(0.0))
    return {p: ((c / t if t else 0.0), (lg / tot if tot else 0.0))
            for p, lg, t, c, tot in got.select("__p", "longest", "tt_s", "changes", "total").iter_rows()}
