"""Alert episodes per pair of aircraft, scored against the truth's losses of separation.

Inputs
------
* ``conflicts`` — :func:`safety.conflicts.predict_conflicts` on one or more pictures (column
  ``method`` names the picture); only ``alert`` rows are used.
* ``id_map`` — (run, epoch, ``id_col``, truth_id[, method]): which aircraft each picture id is
  at each epoch (the matcher's ``gated_truth_id``, :func:`tertiary.evaluation.matching.match_to_reference`).
  Its epochs, with the alert epochs, form the picture's **epoch grid** per (run, method).
* ``truth`` — as :mod:`safety.alerts.separation`.

Alert episodes — :func:`alert_episodes` (the ``alerts`` table)
-------------------------------------------------------------
Alert rows are keyed by the pair of **aircraft**: each picture id pair (run, method, id_a,
id_b) maps to the truth pair that the majority of its alert rows map to (id_map at each row's
epoch), so fragmented or swapped ids cannot inflate episodes; an id coasting on after its
aircraft's truth ended (the matcher maps nothing there) stays that aircraft's. Id pairs without
two distinct truths keep their ids (``truth_a``/``truth_b`` null) and can only be false alerts. An episode is
a maximal sequence of alert epochs of one key whose consecutive alert epochs are adjacent on
the grid or at most ``merge_gap_s`` apart; **flicker** counts the dropouts inside it (alert
epochs not adjacent on the grid). With link window W = [t_start, max(t_end + ``link_s``,
t_cpa)] (``link_s`` default T^пор; t_cpa the latest closest approach its alert epochs
predicted, each at most ``max_link_s`` (default 2 T^пор) after its epoch), an episode is

* **genuine** — a LoS episode of that pair overlaps W (it follows or is under way);
* **nuisance** — no LoS, but a proximity interval of the pair overlaps W;
* **undetermined** — neither, but W reaches past the time the pair's future is observed until:
  the end of the run's truth, or the last sample of an aircraft whose truth ends airborne
  (``AlertConfig.landed_below_m``: it flew out of the recorded area). What the pair did after
  is not known, so the alert cannot be called false (:func:`observed_until`);
* **false** — none of these (also every alert without two distinct truths).

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
``false_alerts``, ``undetermined_alerts``, ``alert_episodes``, ``alerts_per_hour`` (alert episodes
per hour of picture time, summed over runs), ``nuisance_false_per_hour`` (undetermined alerts
left out), ``warning_median_s``, ``warning_p05_s``
(5th percentile; over alerted LoS), ``alert_duration_median_s``, ``flicker_per_alert``,
``picture_hours``. NaN where undefined.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import NDArray

from safety.alerts.config import AlertConfig
from safety.alerts.separation import epoch_micros, to_time, truth_ends, truth_intervals
from tertiary.contract import TABLES, TIME
from tertiary.core import geo
from tertiary.core.units import US

__all__ = ["ALERT_METRICS", "ALERTS_SCHEMA", "LOS_SCHEMA", "picture_grid", "score_pictures", "alert_episodes",
           "los_episodes", "metrics_long", "per_picture", "score_alerts", "scored_conflicts", "scored_ids",
           "alert_ids", "id_rows", "block_id_rows", "IdMap", "SCORED_CONFLICT_COLUMNS", "stca_tables",
           "stca_tables_by_picture", "aircraft_ends", "observed_until"]

ALERT_METRICS = ("los_episodes", "alerted_los", "missed_los", "genuine_alerts", "nuisance_alerts", "false_alerts",
                 "undetermined_alerts", "alert_episodes", "alerts_per_hour", "nuisance_false_per_hour",
                 "warning_median_s", "warning_p05_s", "alert_duration_median_s", "flicker_per_alert", "picture_hours")


#: the ``alerts`` table: one row per alert episode
ALERTS_SCHEMA: dict[str, pl.DataType] = dict(TABLES["alerts"].required)   # columns: tertiary.contract


#: one row per loss-of-separation episode and picture
LOS_SCHEMA: dict[str, pl.DataType] = {
    "run": pl.UInt32(), "method": pl.String(), "truth_a": pl.Int64(), "truth_b": pl.Int64(), "t_start": TIME,
    "t_end": TIME, "alerted": pl.Boolean(), "first_alert": TIME, "warning_s": pl.Float64(),
}


def picture_grid(conflicts: pl.DataFrame, id_map: "pl.DataFrame | IdMap", methods: list[str] | None) -> pl.DataFrame:
    """(run, method, epoch, k, t_us): the picture's epoch grid (id_map epochs ∪ alert epochs),
    dense index k per (run, method)."""
    g = id_map.epochs if isinstance(id_map, IdMap) else _map_epochs(id_map)
    ms = None
    if "method" not in g.columns:
        ms = methods if methods is not None else sorted(conflicts["method"].unique().to_list())
        g = g.join(pl.DataFrame({"method": ms}, schema={"method": pl.String}), how="cross")
    c = conflicts.select(pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String),
                         pl.col("epoch").cast(TIME)).unique()
    if isinstance(id_map, IdMap):
        # the id map's own grid, made once: a setting whose alert epochs are all in it has it
        base = id_map.grid(g, None if ms is None else tuple(ms))
        if c.join(base, on=["run", "method", "epoch"], how="anti").height == 0:
            return base
    return _ranked(pl.concat([g.select("run", "method", "epoch"), c]).unique())


def _ranked(g: pl.DataFrame) -> pl.DataFrame:
    """Epochs (run, method, epoch) sorted, with their dense index k per (run, method) and t_us."""
    return g.sort("run", "method", "epoch").with_columns(
        (pl.col("epoch").rank("dense").over(["run", "method"]).cast(pl.Int64) - 1).alias("k"),
        epoch_micros("epoch").alias("t_us"))


def _map_epochs(id_map: pl.DataFrame) -> pl.DataFrame:
    """The id map's distinct (run, method, epoch); (run, epoch) when it names no picture."""
    if "method" in id_map.columns:
        return id_map.select(pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String),
                             pl.col("epoch").cast(TIME)).unique()
    return id_map.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME)).unique()


@dataclass(frozen=True)
class IdMap:
    """An id map read once for several scorings of the same pictures (the points of a trade-off
    curve): its rows inside the truth's time span (``rows``), the first row of each id at each
    epoch as the alert rows join it (``first``, on ``on``), its picture epochs (``epochs``)."""

    rows: pl.DataFrame
    first: pl.DataFrame
    epochs: pl.DataFrame
    on: list[str]
    #: :func:`picture_grid` of the map's epochs alone, by the pictures named (None: the map's own)
    grids: dict = field(default_factory=dict, compare=False)

    def grid(self, epochs: pl.DataFrame, methods: tuple[str, ...] | None) -> pl.DataFrame:
        """The grid of the map's ``epochs`` (crossed with ``methods`` when it names no picture)."""
        if methods not in self.grids:
            self.grids[methods] = _ranked(epochs.select("run", "method", "epoch").unique())
        return self.grids[methods]

    @classmethod
    def of(cls, id_map: "pl.DataFrame | IdMap", truth: pl.DataFrame, id_col: str) -> "IdMap":
        if isinstance(id_map, IdMap):
            return id_map
        inside = _inside(truth)
        rows = id_map if inside is None else id_map.filter(inside)
        on = ["run", "epoch"] + (["method"] if "method" in rows.columns else [])
        first = rows.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                            *([pl.col("method").cast(pl.String)] if "method" in rows.columns else []),
                            pl.col(id_col).cast(pl.UInt64).alias("__id"), pl.col("truth_id").cast(pl.Int64)
                            ).unique(subset=[*on, "__id"], keep="first")
        return cls(rows, first, _map_epochs(rows), on)


def _inside(truth: pl.DataFrame) -> pl.Expr | None:
    """Whether an epoch is inside the truth's time span (None: a truth without rows or times)."""
    if not (truth.height and "time" in truth.columns):
        return None
    t0, t1 = truth["time"].min(), truth["time"].max()
    return pl.col("epoch").cast(TIME).is_between(pl.lit(t0).cast(TIME), pl.lit(t1).cast(TIME))


#: the columns of the conflict rows that the alert scoring reads
SCORED_CONFLICT_COLUMNS = ("run", "epoch", "method", "id_a", "id_b", "alert", "r_min_m", "dz_min_m", "t_min_s")


def scored_conflicts(conflicts: pl.DataFrame) -> pl.DataFrame:
    """The conflict rows :func:`score_pictures` reads, in input order: every alert row and one
    row of each picture epoch (for :func:`picture_grid`), with :data:`SCORED_CONFLICT_COLUMNS`.
    Scoring them equals scoring every row: the other rows add no alert and no grid epoch. Parts
    of a table reduced apart and concatenated score the same (a repeated grid row adds nothing)."""
    cols = [c for c in SCORED_CONFLICT_COLUMNS if c in conflicts.columns]
    if conflicts.height == 0:
        return conflicts.select(cols)
    first = pl.struct("run", "method", "epoch").is_first_distinct()
    return conflicts.select(cols).filter(pl.col("alert") | first)


def alert_ids(conflicts: pl.DataFrame, id_col: str) -> pl.DataFrame:
    """(run, method, epoch, ``id_col``): each id of an alert row at its epoch, once."""
    cols = ["run", "method", "epoch"]
    if conflicts.height == 0:
        return conflicts.select(*cols, pl.col("id_a").alias(id_col))
    # lazily: the query's unique holds a third of what an eager one does (on a long recording's
    # million curve alert rows, 90 MiB against 250 MiB)
    a = conflicts.lazy().filter(pl.col("alert"))
    return pl.concat([a.select(*cols, pl.col(side).alias(id_col)) for side in ("id_a", "id_b")]).unique().collect()


def id_rows(id_map: "pl.DataFrame | pl.LazyFrame", keys: pl.DataFrame, id_col: str, last: bool = True
            ) -> "pl.DataFrame | pl.LazyFrame":
    """The rows of ``id_map`` that :func:`score_pictures` reads for alert rows with the ids
    ``keys`` (:func:`alert_ids`), in input order: every row of such an id at its epoch (all of
    them, so the first of duplicates stays first), with ``last`` each such id's last row with
    an aircraft (the one a track coasting past its aircraft's truth was last mapped to,
    :func:`_departed`), and one row of each picture epoch (for :func:`picture_grid`)."""
    schema = id_map.collect_schema()
    on = ["run", "epoch"] + (["method"] if "method" in schema else [])
    lazy = isinstance(id_map, pl.LazyFrame)
    k = (keys.select([pl.col(c).cast(schema[c]) for c in [*on, id_col]]).unique()
         .with_columns(pl.lit(True).alias("__hit")))
    hit = pl.col("__hit").fill_null(False) | pl.struct(on).is_first_distinct()
    joined = id_map.join(k.lazy() if lazy else k, on=[*on, id_col], how="left", nulls_equal=True,
                         maintain_order="left")
    if last:
        idk = [c for c in on if c != "epoch"] + [id_col]
        ids = k.select(idk).unique()
        mapped = id_map.filter(pl.col("truth_id").is_not_null())
        final = (mapped.join(ids.lazy() if lazy else ids, on=idk, how="semi").group_by(idk)
                 .agg(pl.col("epoch").max()).with_columns(pl.lit(True).alias("__last")))
        joined = joined.join(final, on=[*idk, "epoch"], how="left", nulls_equal=True, maintain_order="left")
        hit = hit | pl.col("__last").fill_null(False)
    return joined.filter(hit).drop("__hit", "__last", strict=False)


def block_id_rows(id_map: pl.DataFrame, keys: pl.DataFrame, id_col: str) -> pl.DataFrame:
    """A block of an id map (the epochs of a time window, no epoch shared with another block)
    reduced to the rows :func:`id_rows` may read of it, whatever the alerts of the other blocks:
    the rows of the block's alert ids ``keys`` at their epochs, one row of each picture epoch
    and, for *every* id, its rows at its last epoch with an aircraft in the block (a later
    block's alert may find the id's last mapping here). :func:`id_rows` of the blocks'
    reductions, in block order, with every block's keys equals :func:`id_rows` of the whole map."""
    schema = id_map.collect_schema()
    on = ["run", "epoch"] + (["method"] if "method" in schema else [])
    idk = [c for c in on if c != "epoch"] + [id_col]
    k = (keys.select([pl.col(c).cast(schema[c]) for c in [*on, id_col]]).unique()
         .with_columns(pl.lit(True).alias("__hit")))
    final = (id_map.filter(pl.col("truth_id").is_not_null()).group_by(idk).agg(pl.col("epoch").max())
             .with_columns(pl.lit(True).alias("__last")))
    return (id_map.join(k, on=[*on, id_col], how="left", nulls_equal=True, maintain_order="left")
            .join(final, on=[*idk, "epoch"], how="left", nulls_equal=True, maintain_order="left")
            .filter(pl.col("__hit").fill_null(False) | pl.col("__last").fill_null(False)
                    | pl.struct(on).is_first_distinct())
            .drop("__hit", "__last"))


def scored_ids(id_map: pl.DataFrame, conflicts: pl.DataFrame, id_col: str, last: bool = True) -> pl.DataFrame:
    """:func:`id_rows` of ``id_map`` for the alert rows of ``conflicts``."""
    if id_map.height == 0:
        return id_map
    return id_rows(id_map, alert_ids(conflicts, id_col), id_col, last)


def _departed(a: pl.DataFrame, m: pl.DataFrame, ends: pl.DataFrame | None, on: list[str]) -> pl.DataFrame:
    """``a`` with each side's unmapped alert rows (``__ta``/``__tb`` null) mapped to the aircraft
    their id was last mapped to, when that aircraft's truth ended before the row's epoch (so
    did the mapping, which needs the truth): a track coasting on after its aircraft left the
    recording (or landed) is still that aircraft's track, and the matcher, which only maps
    within the truth, cannot say so. The id's last row of ``m`` with an aircraft is its last
    mapping (:func:`id_rows` keeps it), however the id map was cut into blocks."""
    if ends is None or not a.height:
        return a
    keys = [k for k in on if k != "epoch"]
    lk = ["run"] if "run" in ends.columns and "run" in keys else []
    last = ends.select(*(pl.col(k).cast(pl.UInt32) for k in lk), pl.col("truth_id").cast(pl.Int64).alias("__prev"),
                       epoch_micros("time").alias("__gone"))
    for side, col in (("a", "__ta"), ("b", "__tb")):
        ids = a.filter(pl.col(col).is_null()).select(*keys, pl.col(f"id_{side}").alias("__id")).unique()
        if not ids.height:
            continue
        final = (m.filter(pl.col("truth_id").is_not_null()).join(ids, on=[*keys, "__id"], how="semi")
                 .sort("epoch")
                 .group_by(*keys, "__id").agg(pl.col("truth_id").last().alias("__prev"))
                 .join(last, on=[*lk, "__prev"], how="inner").rename({"__id": f"id_{side}"}))
        a = (a.join(final, on=[*keys, f"id_{side}"], how="left", maintain_order="left")
             .with_columns(pl.when(pl.col(col).is_null() & (pl.col("__gone") < epoch_micros("epoch")))
                           .then(pl.col("__prev")).otherwise(pl.col(col)).alias(col))
             .drop("__prev", "__gone"))
    return a


def _alert_rows(conflicts: pl.DataFrame, id_map: "pl.DataFrame | IdMap", id_col: str,
                ends: pl.DataFrame | None = None) -> pl.DataFrame:
    """Alert rows with the pair of aircraft of their id pair: truth_a/truth_b = the truth pair
    that most of the id pair's alert rows map to (null without two distinct truths); a row of
    an id coasting past its aircraft's last truth sample maps to that aircraft
    (:func:`_departed`; ``ends``: :func:`aircraft_ends`)."""
    ids = id_map if isinstance(id_map, IdMap) else IdMap.of(id_map, pl.DataFrame(), id_col)
    on, m = ids.on, ids.first
    opt = [pl.col(c).cast(pl.Float64) if c in conflicts.columns else pl.lit(None, pl.Float64).alias(c)
           for c in ("r_min_m", "dz_min_m", "t_min_s")]
    # select before filtering: the filter then copies a few columns, not the whole table
    a = (conflicts.select("alert", pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                          pl.col("method").cast(pl.String), pl.col("id_a").cast(pl.UInt64),
                          pl.col("id_b").cast(pl.UInt64), *opt)
         .filter(pl.col("alert")).drop("alert"))
    a = (a.join(m.rename({"__id": "id_a", "truth_id": "__ta"}), on=[*on, "id_a"], how="left")
         .join(m.rename({"__id": "id_b", "truth_id": "__tb"}), on=[*on, "id_b"], how="left"))
    a = _departed(a, m, ends, on)
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
    new = ~same | ((dk > 1) & (dt > int(round(merge_gap_s * US))))
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
    t_cpa = np.maximum.reduceat(t + np.round(ahead * US).astype(np.int64), starts)
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


def aircraft_ends(truth: pl.DataFrame, cfg: AlertConfig, frame: geo.LocalFrame | None) -> pl.DataFrame | None:
    """([run,] truth_id, time, airborne) of each aircraft's last truth sample
    (:func:`~safety.alerts.separation.truth_ends`). ``truth``: the truth itself, or its span
    with these rows (``airborne``, as :func:`~safety.alerts.separation.truth_span` gives it);
    None when it names no aircraft."""
    if not truth.height or "truth_id" not in truth.columns:
        return None
    if "airborne" in truth.columns:
        return truth.filter(pl.col("truth_id").is_not_null())
    return truth_ends(truth, cfg, frame)


def observed_until(truth: pl.DataFrame, cfg: AlertConfig, frame: geo.LocalFrame | None,
                   ends: pl.DataFrame | None = None) -> pl.DataFrame | None:
    """([run,] truth_id, __obs_us): until when each aircraft's future is observed — its last
    sample when it ends airborne (:func:`aircraft_ends`, or ``ends`` when given), and the
    run's last truth sample for every aircraft (the recording stops). ``truth`` as
    :func:`aircraft_ends`'s."""
    ends = aircraft_ends(truth, cfg, frame) if ends is None else ends
    if ends is None:
        return None
    keys = ["run"] if "run" in truth.columns else []
    run_end = (truth.group_by(keys).agg(epoch_micros("time").max().alias("__end")) if keys
               else truth.select(epoch_micros("time").max().alias("__end")))
    t = epoch_micros("time")
    obs = ends.select(*(pl.col(k).cast(pl.UInt32) for k in keys), pl.col("truth_id").cast(pl.Int64),
                      pl.when(pl.col("airborne").fill_null(False)).then(t).otherwise(None).alias("__own"))
    obs = obs.join(run_end, on=keys, how="left") if keys else obs.join(run_end, how="cross")
    return obs.select(*keys, "truth_id", pl.min_horizontal("__own", "__end").alias("__obs_us"))


def classify_episodes(eps: pl.DataFrame, los: pl.DataFrame, prox: pl.DataFrame, link_us: int, shared: bool,
                      observed: pl.DataFrame | None = None) -> pl.DataFrame:
    """Each alert episode genuine (linked to a loss of separation of its pair: ``los_start_us``
    and the warning time), nuisance (linked only to a proximity interval), undetermined (neither,
    but its link window reaches past the time either aircraft's future is observed until:
    ``observed`` from :func:`observed_until`) or false."""
    pairs = ["truth_a", "truth_b"]
    known = eps.filter(pl.col("kind") == 0).select("__ep", "run", *pairs, "t0", "t1", "t_cpa")
    g = (_linked(known, los, link_us, shared, pairs)
         .group_by("__ep").agg(pl.col("t_start_us").min().alias("los_start_us")))
    n = _linked(known, prox, link_us, shared, pairs).select("__ep").unique().with_columns(
        pl.lit(True).alias("__near"))
    e = eps.join(g, on="__ep", how="left").join(n, on="__ep", how="left")
    unseen = pl.lit(False)
    if observed is not None:
        on = [] if shared else ["run"]
        obs = observed.drop("run", strict=False) if shared else observed
        for side in ("a", "b"):
            e = e.join(obs.rename({"truth_id": f"truth_{side}", "__obs_us": f"__obs_{side}"}),
                       on=[*on, f"truth_{side}"], how="left")
        seen_to = pl.min_horizontal("__obs_a", "__obs_b")
        unseen = (pl.col("kind") == 0) & seen_to.is_not_null() & (_reach(link_us) > seen_to)
    cls = (pl.when(pl.col("los_start_us").is_not_null()).then(pl.lit("genuine"))
           .when(pl.col("__near").fill_null(False)).then(pl.lit("nuisance"))
           .when(unseen).then(pl.lit("undetermined")).otherwise(pl.lit("false")))
    return e.with_columns(cls.alias("classification"),
                          ((pl.col("los_start_us") - pl.col("t0")) / US).alias("warning_s")
                          ).drop("__obs_a", "__obs_b", strict=False)


def los_table(grid: pl.DataFrame, eps: pl.DataFrame, los: pl.DataFrame, link_us: int, shared: bool) -> pl.DataFrame:
    """Each loss of separation inside a picture's scored span, alerted or missed, with its first
    linked alert and warning time (:data:`LOS_SCHEMA`)."""
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
        pl.col("run").cast(pl.UInt32), "method", "truth_a", "truth_b", to_time("t_start_us", "t_start"),
        to_time("t_end_us", "t_end"), pl.col("__first").is_not_null().alias("alerted"),
        to_time("__first", "first_alert"), ((pl.col("t_start_us") - pl.col("__first")) / US).alias("warning_s"),
    ).sort("run", "method", "truth_a", "truth_b", "t_start").cast(LOS_SCHEMA)


def score_pictures(conflicts: pl.DataFrame, id_map: "pl.DataFrame | IdMap", truth: pl.DataFrame, cfg: AlertConfig,
                   id_col: str,
                   methods: list[str] | None, frame: geo.LocalFrame | None,
                   intervals: tuple[pl.DataFrame, pl.DataFrame] | None
                   ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(alerts table, LoS table, grid) of the pictures in ``conflicts``; only epochs inside the
    truth's time span are scored (after the reference ends nothing can judge an alert)."""
    inside = _inside(truth)
    if inside is not None:
        conflicts = conflicts.filter(inside)
    # the id map's rows inside the span, read once when the caller scores several settings
    id_map = IdMap.of(id_map, truth, id_col)
    los, prox = truth_intervals(truth, cfg, frame) if intervals is None else intervals
    shared = "run" not in truth.columns
    link_us = int(round(cfg.link * US))
    grid = picture_grid(conflicts, id_map, methods)
    ends = aircraft_ends(truth, cfg, frame)
    eps = _episodes_of(_alert_rows(conflicts, id_map, id_col, ends), grid, cfg.merge_gap_s, cfg.cpa_reach)
    eps = classify_episodes(eps, los, prox, link_us, shared, observed_until(truth, cfg, frame, ends))
    alerts = eps.select(
        "run", "method", "id_a", "id_b", "truth_a", "truth_b", to_time("t0", "t_start"), to_time("t1", "t_end"),
        ((pl.col("t1") - pl.col("t0")) / US).alias("duration_s"), "alert_epochs", "flicker", "r_min_pred_m",
        "dz_min_pred_m", "t_min_first_s", to_time("los_start_us", "los_start"), "warning_s", "classification",
    ).sort("run", "method", "t_start", "id_a", "id_b").cast(ALERTS_SCHEMA)
    return alerts, los_table(grid, eps, los, link_us, shared), grid


def alert_episodes(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                   cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                   frame: geo.LocalFrame | None = None,
                   intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> pl.DataFrame:
    """The ``alerts`` table (:data:`ALERTS_SCHEMA`): one row per alert episode per picture, with
    its pair of ids and of aircraft, start, end, minimum predicted separation, warning time and
    ``classification`` (genuine / nuisance / undetermined / false)."""
    return score_pictures(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)[0]


def los_episodes(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                 cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                 frame: geo.LocalFrame | None = None,
                 intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> pl.DataFrame:
    """One row per LoS episode and picture (:data:`LOS_SCHEMA`): alerted or missed, warning."""
    return score_pictures(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)[1]


def _hours(grid: pl.DataFrame) -> pl.DataFrame:
    return (grid.group_by("run", "method").agg(((pl.col("t_us").max() - pl.col("t_us").min()) / US).alias("__s"))
            .group_by("method").agg((pl.col("__s").sum() / 3600.0).alias("picture_hours"),
                                    pl.col("run").n_unique().alias("n_runs")))


def per_picture(alerts: pl.DataFrame, los: pl.DataFrame, grid: pl.DataFrame) -> pl.DataFrame:
    cls = pl.col("classification")
    a = alerts.group_by("method").agg(
        pl.len().cast(pl.Float64).alias("alert_episodes"),
        (cls == "genuine").sum().cast(pl.Float64).alias("genuine_alerts"),
        (cls == "nuisance").sum().cast(pl.Float64).alias("nuisance_alerts"),
        (cls == "false").sum().cast(pl.Float64).alias("false_alerts"),
        (cls == "undetermined").sum().cast(pl.Float64).alias("undetermined_alerts"),
        pl.col("duration_s").median().alias("alert_duration_median_s"),
        pl.col("flicker").cast(pl.Float64).mean().alias("flicker_per_alert"))
    w = pl.col("warning_s").filter(pl.col("alerted"))
    lo = los.group_by("method").agg(
        pl.len().cast(pl.Float64).alias("los_episodes"), pl.col("alerted").sum().cast(pl.Float64).alias("alerted_los"),
        w.median().alias("warning_median_s"), w.quantile(0.05, "linear").alias("warning_p05_s"))
    per = _hours(grid).join(a, on="method", how="left").join(lo, on="method", how="left")
    counts = ["alert_episodes", "genuine_alerts", "nuisance_alerts", "false_alerts", "undetermined_alerts",
              "los_episodes", "alerted_los"]
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
    ``"all"``): :data:`ALERT_METRICS`."""
    alerts, los, grid = score_pictures(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)
    return metrics_long(per_picture(alerts, los, grid))


def metrics_long(per: pl.DataFrame, names: tuple[str, ...] = ALERT_METRICS) -> pl.DataFrame:
    """``per`` (one row per picture: ``method``, ``n_runs`` and the columns ``names``) in the
    ``metrics`` schema, stage ``"safety"``, segment ``"all"``, metrics in the order of ``names``."""
    long = per.unpivot(index=["method", "n_runs"], on=list(names), variable_name="metric", value_name="value")
    order = pl.col("metric").replace_strict({m: i for i, m in enumerate(names)}, return_dtype=pl.Int8)
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
    alerts, los, grid = score_pictures(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)
    return metrics_long(per_picture(alerts, los, grid)), alerts, los


#: the conflict and id-map rows one pass of :func:`stca_tables_by_picture` scores together at most
PASS_ROWS = 1_000_000


def _passes(names: list[str], conflicts: pl.DataFrame, id_map: pl.DataFrame, budget: int) -> list[list[str]]:
    """``names`` in order, cut into runs whose conflict and id-map rows sum to at most ``budget``
    (a picture above it alone)."""
    def rows(frame: pl.DataFrame) -> dict[str, int]:
        return dict(frame.group_by("method").len().iter_rows())
    own, shared = rows(conflicts), (id_map.height if "method" not in id_map.columns else 0)
    ids = rows(id_map) if "method" in id_map.columns else {}
    out: list[list[str]] = []
    held = budget + 1
    for name in names:
        n = own.get(name, 0) + ids.get(name, 0) + shared
        if held + n > budget:
            out.append([])
            held = 0
        out[-1].append(name)
        held += n
    return out


def stca_tables_by_picture(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                           cfg: AlertConfig = AlertConfig(), id_col: str = "id", methods: list[str] | None = None,
                           frame: geo.LocalFrame | None = None,
                           intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None
                           ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """:func:`stca_tables` a few pictures at a time, the same three tables: a picture's alerts,
    LoS episodes and metrics depend on its own conflicts and id map alone (``id_map`` without a
    ``method`` column serves every picture), and the union is sorted as one call sorts it. A
    pass's joins hold at most :data:`PASS_ROWS` rows, or one picture's (memory); small pictures
    share a pass (a pass's fixed cost is paid once for them)."""
    # the pictures one call scores (:func:`picture_grid`): an id map's own pictures when it names them
    if "method" in id_map.columns:
        names = sorted(set(id_map["method"].unique().to_list()) | set(conflicts["method"].unique().to_list()))
    else:
        names = methods if methods is not None else sorted(conflicts["method"].unique().to_list())
    if len(names) <= 1:
        return stca_tables(conflicts, id_map, truth, cfg, id_col, methods, frame, intervals)
    if intervals is None:
        intervals = truth_intervals(truth, cfg, frame)
    parts = []
    for batch in _passes(names, conflicts, id_map, PASS_ROWS):
        mine = pl.col("method").is_in(batch)
        ids = id_map.filter(mine) if "method" in id_map.columns else id_map
        parts.append(stca_tables(conflicts.filter(mine), ids, truth, cfg, id_col, batch, frame, intervals))
    metrics, alerts, los = (pl.concat([p[k] for p in parts], how="vertical") for k in range(3))
    # each part is sorted as one call sorts its tables: the union sorted again by the same keys
    return (metrics.sort("method", maintain_order=True),
            alerts.sort("run", "method", "t_start", "id_a", "id_b", maintain_order=True),
            los.sort("run", "method", "truth_a", "truth_b", "t_start", maintain_order=True))
