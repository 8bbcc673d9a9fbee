"""Real accuracy, consistency and track continuity of a *matched* picture (the seed metrics).

Every picture — a fusion method's plots, the centralised reference, a tracker's output or a
picture ``tertiary`` did not produce — is first matched to the reference aircraft by the one
matcher, :func:`tertiary.evaluation.matching.match_to_reference` (geometric, one-to-one per epoch). This
module only computes statistics of the matched rows; it never decides which aircraft a row is.

Scored rows (:func:`scored_rows`)
---------------------------------
The matched rows with a reference aircraft, at least ``skip_first_s`` (default 20 s: the
filter transient) after the first epoch of their (run, picture, track). Rows the
matcher left unmatched (false tracks, second tracks on an aircraft, gross errors beyond the
gate) are not accuracy samples: they are counted by the continuity and picture metrics.
Where the epochs at which each aircraft was reported are known (``observed``: the pipeline's
aligned reports), an aircraft is scored from its first reported epoch on: a row matched to an
aircraft that no sensor has reported yet is some other object's track inside the matching gate
(an aircraft entering beside another), not an estimate of that aircraft, and no estimator of it
could be nearer than its prior.

Real accuracy (monograph (2.15), (4.84))
----------------------------------------
A scored row is compared with its aircraft's reference state at the row's epoch (interpolated
by the matcher). With e_j(k) the error of sample j at epoch k,

    σ²(k) = Σ_{j=1..N_k} e_j(k)² / (N_k − 1)                                        (2.15)/(4.84)

the squared real accuracy at epoch k, about the **truth** (not the sample mean). The samples of
an epoch are all scored rows of that picture at that epoch — for one aircraft, one per
Monte-Carlo run (N_k = number of runs, the seed's case); with several aircraft they are pooled.
``denominator="n"`` divides by N_k instead. For 3-D position and velocity e² = |e|² (sum of the
three components), for range e = |p| − |p_true| (range from the processing centre = the
system origin).

Horizontal and vertical error. Surveillance specifications judge the two separately, so beside
the 3-D ``rmse_pos_m`` (e² = Δx² + Δy² + Δz²) every picture gets ``rmse_horizontal_m``
(e² = Δx² + Δy², east and north of the system ENU frame) and ``rmse_height_m``. The height error
is e = alt_m − alt_m_true whenever both the picture row and the reference carry the vertical
channel ``alt_m`` (barometric / geodetic height, :mod:`tertiary.stages.tracking.altitude`). Otherwise it falls
back to e = Δz: the frame's z is not the height h — at horizontal distance d from the origin
z = h − d²/(2R) + O(d⁴/R³), so Δz equals the height error to first order only.

Pooling when an epoch has too few samples. With ``"n-1"`` an epoch with N_k = 1 has no (2.15).
Instead of dropping it, the M samples of all such epochs of a (picture, segment) are **pooled**
into one sample with the N − 1 denominator: each of those epochs gets σ²(k) = e_k² · M / (M − 1),
so that their mean is Σ e² / (M − 1), the (2.15) of the pool. Only a pool with M < 2 is left out.
``accuracy_by_epoch`` marks those rows ``pooled`` and gives N_k in ``n``.

The pooled figure of a metric is RMSE = sqrt( (1/K) Σ_k σ²(k) ) over the K scored epochs.
``n_runs`` is the number of distinct Monte-Carlo runs that contributed.

Segments: ``all``; ``straight`` ← reference segments straight|climb|descent; ``turn`` ← turn.
Holding patterns (``hold``) and unknown segments count only in ``all``.

Consistency: ``potential_pos_m``, the mean of sqrt(P_xx + P_yy + P_zz) (potential accuracy,
§2.2.1), and the NEES/NIS statistics of :mod:`tertiary.evaluation.consistency`.

Continuity (:func:`continuity_metrics`, segment ``all``)
--------------------------------------------------------
On the matched rows (every epoch, not only the scored ones) and the aircraft-epochs a picture
should cover (``observed``: in the pipeline the (run, epoch, aircraft) that had at least one
report at that epoch; for an external picture the reference aircraft alive at its epochs):

* ``completeness``: the fraction of those aircraft-epochs covered by a track matched to it.
* ``breaks``: walking each (run, aircraft)'s aircraft-epochs in time order with its covering
  track, a covered epoch whose previous covered epoch had another track id, or that follows
  uncovered epochs. Uncovered epochs before the first coverage (initiation) are not breaks.
* ``swaps``: over each track's matched rows in time order, the number of times its aircraft
  changes; summed over tracks.
* ``spurious_tracks``: tracks (run, track_id) never matched to any aircraft; ``tracks``: all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import polars as pl

from tertiary.contract import TABLES, TIME
from tertiary.core.units import STATE
from tertiary.evaluation.consistency import add_nees, consistency_metrics, consistency_statistics

__all__ = [
    "AccuracyConfig",
    "SEGMENT_CLASSES",
    "FUSION_METRICS",
    "error_columns",
    "scored_rows",
    "row_scores",
    "ROW_SCORES",
    "accuracy_from_matched",
    "accuracy_by_epoch_from_matched",
    "BY_EPOCH_SCHEMA",
    "continuity_metrics",
    "picture_accuracy",
    "scored_samples",
    "first_seen",
]

Denominator = Literal["n-1", "n"]

#: truth segment → evaluation segment (anything else counts only in ``all``)
SEGMENT_CLASSES: dict[str, str] = {"straight": "straight", "climb": "straight", "descent": "straight",
                                   "turn": "turn"}

#: metric name → squared-error column of :func:`scored_rows`
FUSION_METRICS: dict[str, str] = {
    "rmse_pos_m": "e2_pos",
    "rmse_horizontal_m": "e2_horizontal",
    "rmse_height_m": "e2_height",
    "rmse_range_m": "e2_range",
    "rmse_x_m": "e2_x",
    "rmse_y_m": "e2_y",
    "rmse_z_m": "e2_z",
    "rmse_vel_mps": "e2_vel",
}

_TRACK = ["run", "method", "track_id"]


@dataclass(frozen=True)
class AccuracyConfig:
    """Options of the seed metrics.

    * ``skip_first_s``: discard rows this many seconds after the first epoch of their
      (run, picture, track) — the filter transient (the first 20 s by default).
    * ``denominator``: ``"n-1"`` (seed (2.15)/(4.84)) or ``"n"``.
    * ``band``: probability of the two-sided χ² consistency bands.
    """

    skip_first_s: float = 20.0
    denominator: Denominator = "n-1"
    band: float = 0.95

    def __post_init__(self) -> None:
        if self.denominator not in ("n-1", "n"):
            raise ValueError(f"denominator must be 'n-1' or 'n', got {self.denominator!r}")
        if self.skip_first_s < 0:
            raise ValueError(f"skip_first_s must be >= 0, got {self.skip_first_s}")
        if not 0 < self.band < 1:
            raise ValueError(f"band must be in (0, 1), got {self.band}")


def error_columns(alt: bool = False) -> list[pl.Expr]:
    """Expressions on rows holding an estimate (``x_m`` …) and its truth (``true_x_m`` …):
    ``seg_class`` (straight/turn/null) and the squared errors ``e2_x``, ``e2_y``, ``e2_z``,
    ``e2_pos`` (|Δp|²), ``e2_horizontal`` (Δx² + Δy²), ``e2_height`` ((alt_m − true_alt_m)²
    where ``alt`` and both are not null, else Δz², the height error to first order only; module
    docstring), ``e2_range`` ((|p| − |p_true|)², range from the processing
    centre) and ``e2_vel`` (|Δv|²) — shared by the fusion and tracker evaluations."""
    d = {c: pl.col(c) - pl.col(f"true_{c}") for c in STATE}
    r_f = (pl.col("x_m") ** 2 + pl.col("y_m") ** 2 + pl.col("z_m") ** 2).sqrt()
    r_t = (pl.col("true_x_m") ** 2 + pl.col("true_y_m") ** 2 + pl.col("true_z_m") ** 2).sqrt()
    return [
        pl.col("segment").replace_strict(SEGMENT_CLASSES, default=None, return_dtype=pl.String).alias("seg_class"),
        (d["x_m"] ** 2).alias("e2_x"),
        (d["y_m"] ** 2).alias("e2_y"),
        (d["z_m"] ** 2).alias("e2_z"),
        (d["x_m"] ** 2 + d["y_m"] ** 2 + d["z_m"] ** 2).alias("e2_pos"),
        (d["x_m"] ** 2 + d["y_m"] ** 2).alias("e2_horizontal"),
        _e2_height(d["z_m"], alt),
        ((r_f - r_t) ** 2).alias("e2_range"),
        (d["vx_mps"] ** 2 + d["vy_mps"] ** 2 + d["vz_mps"] ** 2).alias("e2_vel"),
    ]


def _e2_height(dz: pl.Expr, alt: bool) -> pl.Expr:
    """(alt_m − true_alt_m)² where both exist (``alt``), else Δz²."""
    if not alt:
        return (dz ** 2).alias("e2_height")
    dh = pl.col("alt_m").cast(pl.Float64).fill_nan(None) - pl.col("true_alt_m")
    return pl.coalesce(dh ** 2, dz ** 2).alias("e2_height")


# --------------------------------------------------------------------------- accuracy


def _per_epoch(matched: pl.DataFrame, group: list[str], cfg: AccuracyConfig) -> pl.DataFrame:
    """Long per-epoch table: ``group`` + epoch, metric, sigma2 (= σ²(k) of (2.15)), n (N_k),
    n_runs, pooled (:func:`pool_epochs`)."""
    e2 = list(FUSION_METRICS.values())
    agg = matched.group_by(group + ["epoch"]).agg(
        *[pl.col(c).sum() for c in e2], pl.len().alias("n"), pl.col("run").n_unique().alias("n_runs"))
    return pool_epochs(agg, group, cfg)


def pool_epochs(agg: pl.DataFrame, group: list[str], cfg: AccuracyConfig) -> pl.DataFrame:
    """The per-epoch table of :func:`accuracy_from_matched` from its sums per ``group`` + epoch
    (the e² sums, ``n`` = N_k, ``n_runs``): shared with
    :func:`~tertiary.evaluation.accuracy_buckets.picture_accuracy_buckets`, which adds those sums
    up over buckets. With
    ``"n-1"`` the epochs with N_k < 2 of a ``group`` are pooled (module docstring):
    σ²(k) = Σ e² · M / ((M − 1) N_k) with M their total sample count; a pool with M < 2 is dropped."""
    e2 = list(FUSION_METRICS.values())
    long = pooled_sigma2(agg, group, cfg).unpivot(index=group + ["epoch", "n", "n_runs", "pooled"], on=e2,
                                                  variable_name="e2", value_name="sigma2")
    name = {v: k for k, v in FUSION_METRICS.items()}
    return long.select(
        *group, "epoch",
        pl.col("e2").replace_strict(name, return_dtype=pl.String).alias("metric"),
        "sigma2", "n", "n_runs", "pooled")


def pooled_sigma2(agg: pl.DataFrame, group: list[str], cfg: AccuracyConfig) -> pl.DataFrame:
    """:func:`pool_epochs` before it is made long: σ²(k) of each metric in its e² sum's column,
    one row per epoch kept (group + epoch, ``n``, ``n_runs``, ``pooled``)."""
    ddof = 1 if cfg.denominator == "n-1" else 0
    e2 = list(FUSION_METRICS.values())
    pooled = pl.col("n") <= ddof
    # M: samples of the thin epochs of the same group (0 when nothing needs pooling)
    agg = agg.with_columns(pooled.alias("pooled"),
                           pl.when(pooled).then(pl.col("n")).otherwise(0).sum().over(group).alias("__m"))
    agg = agg.filter(~pl.col("pooled") | (pl.col("__m") > ddof))
    m = pl.col("__m").cast(pl.Float64)

    def sigma2(c: str) -> pl.Expr:
        return (pl.when(pl.col("pooled")).then(pl.col(c) * m / ((m - ddof) * pl.col("n")))
                .otherwise(pl.col(c) / (pl.col("n") - ddof))).alias(c)
    return agg.select(*group, "epoch", *(sigma2(c) for c in e2), "n", "n_runs", "pooled")


def pooled_means(agg: pl.DataFrame, group: list[str], cfg: AccuracyConfig) -> pl.DataFrame:
    """The mean over epochs of each metric's σ²(k) per ``group`` (:func:`pooled_sigma2`), long
    (group, ``metric``, ``sigma2``): what :func:`accuracy_table` reads of :func:`pool_epochs`,
    without making the per-epoch table long (a long run's epochs × metrics rows)."""
    e2 = list(FUSION_METRICS.values())
    means = pooled_sigma2(agg, group, cfg).group_by(group).agg(pl.col(c).mean() for c in e2)
    name = {v: k for k, v in FUSION_METRICS.items()}
    return means.unpivot(index=group, on=e2, variable_name="e2", value_name="sigma2").select(
        *group, pl.col("e2").replace_strict(name, return_dtype=pl.String).alias("metric"), "sigma2")


def with_segments(matched: pl.DataFrame) -> pl.DataFrame:
    """Rows once with segment ``all`` and once more with their straight/turn class."""
    allrows = matched.with_columns(pl.lit("all").alias("eval_segment"))
    split = matched.filter(pl.col("seg_class").is_not_null()).with_columns(pl.col("seg_class").alias("eval_segment"))
    return pl.concat([allrows, split], how="vertical")


def _metrics_schema(frame: pl.DataFrame) -> pl.DataFrame:
    spec = TABLES["metrics"].required
    return frame.select([pl.col(c).cast(t) for c, t in spec.items()])


def empty_metrics() -> pl.DataFrame:
    return pl.DataFrame(schema=TABLES["metrics"].required)


def accuracy_from_matched(matched: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig(),
                          stage: str = "fusion") -> pl.DataFrame:
    """Pooled real accuracy (metrics schema, ``stage``) from :func:`scored_rows`:
    RMSE = sqrt(mean_k σ²(k)), σ²(k) from (2.15)/(4.84), per method, metric and segment."""
    if matched.is_empty():
        return empty_metrics()
    group = ["method", "eval_segment"]
    # segment "all" and each row's straight/turn class grouped in place, never a copy of the rows
    rows = [matched.with_columns(pl.lit("all").alias("eval_segment")),
            matched.with_columns(pl.col("seg_class").alias("eval_segment"))]
    per = pl.concat([_per_epoch(r, group, cfg).filter(pl.col("eval_segment").is_not_null()) for r in rows])
    runs = pl.concat([r.group_by(group).agg(pl.col("run").n_unique().alias("n_runs"))
                      .filter(pl.col("eval_segment").is_not_null()) for r in rows])
    del rows
    return accuracy_table(per, runs, stage)


def accuracy_table(per: pl.DataFrame, runs: pl.DataFrame, stage: str) -> pl.DataFrame:
    """The metrics rows of :func:`accuracy_from_matched` from its per-epoch table ``per``
    (:func:`pool_epochs`, group method + eval_segment) and ``runs`` (n_runs of each group)."""
    pooled = (per.group_by(["method", "eval_segment", "metric"]).agg(pl.col("sigma2").mean().sqrt().alias("value"))
              .join(runs, on=["method", "eval_segment"], how="left"))
    seg_order = pl.col("eval_segment").replace_strict({"all": 0, "straight": 1, "turn": 2}, default=3,
                                                      return_dtype=pl.Int8)
    met_order = pl.col("metric").replace_strict({m: i for i, m in enumerate(FUSION_METRICS)}, return_dtype=pl.Int8)
    out = (pooled.sort([pl.col("method"), seg_order, met_order])
           .select(pl.lit(stage).alias("stage"), "method", "metric",
                   pl.col("eval_segment").alias("segment"), "value", "n_runs"))
    return _metrics_schema(out)


#: columns of the ``accuracy_by_epoch`` table: ``n`` = N_k (scored samples at the epoch), ``pooled`` =
#: the epoch had N_k < 2 and its σ(k) comes from the pool of such epochs (module docstring)
BY_EPOCH_SCHEMA: dict[str, pl.DataType] = {"method": pl.String, "epoch": TIME, "metric": pl.String,
                                           "value": pl.Float64, "n_runs": pl.UInt32, "n": pl.UInt32,
                                           "pooled": pl.Boolean}


def accuracy_by_epoch_from_matched(matched: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig()) -> pl.DataFrame:
    """:func:`accuracy_by_epoch` from already matched rows (match once, derive both tables)."""
    if matched.is_empty():
        return pl.DataFrame(schema=BY_EPOCH_SCHEMA)
    return by_epoch_table(_per_epoch(matched, ["method"], cfg))


def by_epoch_table(per: pl.DataFrame) -> pl.DataFrame:
    """:data:`BY_EPOCH_SCHEMA` rows from the per-epoch table of segment ``all`` (group method)."""
    met_order = pl.col("metric").replace_strict({m: i for i, m in enumerate(FUSION_METRICS)}, return_dtype=pl.Int8)
    return (per.sort([pl.col("method"), met_order, pl.col("epoch")])
            .select("method", "epoch", "metric", pl.col("sigma2").sqrt().alias("value"), "n_runs", "n", "pooled")
            .cast(BY_EPOCH_SCHEMA))


def _diag_of(m: pl.DataFrame, col: str, idx: tuple[int, ...]) -> list[pl.Expr] | None:
    if col not in m.columns:
        return None
    get = (lambda k: pl.col(col).list.get(k)) if isinstance(m.schema[col], pl.List) else (lambda k: pl.col(col).arr.get(k))
    return [get(k) for k in idx]


def _sd_and_nees_diag(m: pl.DataFrame) -> list[pl.Expr]:
    """``sd_pos`` = sqrt(P_xx + P_yy + P_zz) and the diagonal-only NEES ``__nees_diag``, per row
    from the full ``cov`` (36 values, row-major) where it is set, else from ``cov_diag``; null
    when a row has neither."""
    full, diag = _diag_of(m, "cov", (0, 7, 14)), _diag_of(m, "cov_diag", (0, 1, 2))
    if full is None and diag is None:
        return [pl.lit(None, pl.Float64).alias("sd_pos"), pl.lit(None, pl.Float64).alias("__nees_diag")]
    var = [pl.coalesce(*[v[k] for v in (full, diag) if v is not None]) for k in range(3)]
    d = [pl.col(c) - pl.col(f"true_{c}") for c in ("x_m", "y_m", "z_m")]
    return [(var[0] + var[1] + var[2]).sqrt().alias("sd_pos"),
            (d[0] ** 2 / var[0] + d[1] ** 2 / var[1] + d[2] ** 2 / var[2]).alias("__nees_diag")]


#: the per-row columns :func:`row_scores` adds (what :func:`scored_rows` reads of a row)
ROW_SCORES = ("seg_class", "e2_x", "e2_y", "e2_z", "e2_pos", "e2_horizontal", "e2_height", "e2_range", "e2_vel",
              "sd_pos", "nees_pos", "nees")


def row_scores(matched: pl.DataFrame) -> pl.DataFrame:
    """``matched`` with every :data:`ROW_SCORES` column (:func:`scored_rows`; null on rows
    without a ``truth_id``), its ``cov`` consumed. Each is a function of its row alone, so a
    picture can be scored a block of rows at a time and its covariances never held whole."""
    m = matched
    if "segment" not in m.columns:
        m = m.with_columns(pl.lit(None, pl.String).alias("segment"))
    m = m.with_columns(*error_columns("true_alt_m" in m.columns and "alt_m" in m.columns), *_sd_and_nees_diag(m))
    if "cov" in m.columns and m["cov"].null_count() == m.height:
        m = m.drop("cov")
    if "cov" in m.columns:               # the proper NEES Δpᵀ P_pp⁻¹ Δp and the 6-state one
        m = add_nees(m.drop("cov"), m["cov"])
        m = m.with_columns(pl.col("nees_pos").fill_nan(None).fill_null(pl.col("__nees_diag")),
                           pl.col("nees").fill_nan(None))
    else:
        m = m.with_columns(pl.col("__nees_diag").alias("nees_pos"), pl.lit(None, pl.Float64).alias("nees"))
    return m.drop("__nees_diag")


def scored_rows(matched: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig(),
                first_seen: pl.DataFrame | None = None) -> pl.DataFrame:
    """The accuracy samples of a matched picture (module docstring): rows with a ``truth_id``,
    after the transient, with ``seg_class``, the squared errors ``e2_*`` (:func:`error_columns`),
    ``sd_pos`` and the NEES columns ``nees_pos`` (3 dof) and ``nees`` (6 dof; null without a full
    covariance). The ``cov`` column is consumed (not returned). ``matched`` may carry the
    :func:`row_scores` already (a picture scored in blocks). ``first_seen``
    (:func:`first_seen`): only rows at or after their aircraft's first reported epoch."""
    m = matched
    if first_seen is not None and m.height:
        m = m.join(first_seen, on=["run", "truth_id"], how="left", maintain_order="left")
    keep = pl.col("truth_id").is_not_null()
    if first_seen is not None and m.height:
        keep = keep & (pl.col("epoch") >= pl.col(_FIRST_SEEN))
    if cfg.skip_first_s > 0 and m.height:
        first = pl.col("epoch").min().over(_TRACK)
        keep = keep & ((pl.col("epoch") - first).dt.total_microseconds() >= round(cfg.skip_first_s * 1e6))
    m = m.filter(keep).drop(_FIRST_SEEN, strict=False)      # one filter: the picture copied once
    return m if set(ROW_SCORES) <= set(m.columns) else row_scores(m)


_FIRST_SEEN = "__first_seen"


def first_seen(observed: pl.DataFrame | pl.LazyFrame | None, matched_schema: pl.Schema) -> pl.DataFrame | None:
    """(run, truth_id, first reported epoch) of every aircraft in ``observed`` (run, epoch,
    truth_id), in the types of the matched rows (``matched_schema``), for :func:`scored_rows`;
    None without ``observed``."""
    if observed is None:
        return None
    # an aggregate over the whole of ``observed``, one row per aircraft: streamed, so a long
    # recording's aircraft-epochs on disk are never held
    return (observed.lazy().drop_nulls("truth_id").group_by("run", "truth_id")
            .agg(pl.col("epoch").min().alias(_FIRST_SEEN))
            .select(pl.col("run").cast(matched_schema["run"]), pl.col("truth_id").cast(matched_schema["truth_id"]),
                    pl.col(_FIRST_SEEN).cast(matched_schema["epoch"])).collect(engine="streaming"))


def _consistency(scored: pl.DataFrame, stage: str, band: float) -> list[pl.DataFrame]:
    """``potential_pos_m`` and the NEES (3 and 6 dof) and NIS rows of every picture."""
    out = []
    pot = scored.select("method", "run", "seg_class", "sd_pos").filter(pl.col("sd_pos").is_not_null())
    if pot.height:
        # in order of appearance: the metrics table's rows are the same on every run
        rows = with_segments(pot).group_by("method", "eval_segment", maintain_order=True).agg(
            pl.col("sd_pos").mean().alias("value"), pl.col("run").n_unique().alias("n_runs"))
        out.append(potential_table(rows, stage))
    for prefix, (col, dof) in consistency_statistics(scored.columns).items():
        out.append(consistency_metrics(scored, col, dof, prefix, stage, "track_id", band))
    return out



def potential_table(rows: pl.DataFrame, stage: str) -> pl.DataFrame:
    """``potential_pos_m`` rows from (method, eval_segment, value, n_runs) in their order."""
    return _metrics_schema(rows.select(pl.lit(stage).alias("stage"), "method",
                                       pl.lit("potential_pos_m").alias("metric"),
                                       pl.col("eval_segment").alias("segment"), "value", "n_runs"))


def continuity_metrics(matched: pl.DataFrame, observed: pl.DataFrame | None, stage: str) -> pl.DataFrame:
    """``completeness``, ``breaks``, ``swaps``, ``spurious_tracks`` and ``tracks`` per picture
    (segment ``all``; module docstring). ``observed``: (run, epoch, truth_id) the pictures should
    cover; without it only ``swaps``, ``spurious_tracks`` and ``tracks``."""
    m = continuity_columns(matched)
    coverage = None if observed is None else _coverage(m, observed)
    return continuity_table(track_counts(m), m.select("method", "run").unique(), coverage, stage)


def continuity_columns(matched: pl.DataFrame | pl.LazyFrame, *extra: str) -> pl.DataFrame | pl.LazyFrame:
    return matched.select("method", pl.col("run").cast(pl.UInt32), "epoch", "track_id", "truth_id", *extra)


def track_counts(m: pl.DataFrame) -> pl.DataFrame:
    """(method, spurious_tracks, tracks, swaps) of the rows ``m`` (:func:`continuity_columns`):
    sums over tracks, so that rows partitioned by whole tracks give them as sums over the parts."""
    per_track = m.group_by("method", "run", "track_id").agg(pl.col("truth_id").is_null().all().alias("__spurious"))
    counts = per_track.group_by("method").agg(pl.col("__spurious").sum().cast(pl.Float64).alias("spurious_tracks"),
                                              pl.len().cast(pl.Float64).alias("tracks"))
    seq = m.filter(pl.col("truth_id").is_not_null()).sort("method", "run", "track_id", "epoch")
    prev_t = pl.col("truth_id").shift(1).over(["method", "run", "track_id"])
    swaps = seq.group_by("method").agg(((pl.col("truth_id") != prev_t) & prev_t.is_not_null()).sum()
                                       .cast(pl.Float64).alias("swaps"))
    return counts.join(swaps, on="method", how="left").with_columns(pl.col("swaps").fill_null(0.0))


def continuity_table(counts: pl.DataFrame, runs: pl.DataFrame, coverage: pl.DataFrame | None,
                      stage: str) -> pl.DataFrame:
    """:func:`continuity_metrics` from the :func:`track_counts`, the (method, run) pairs of the
    tracks and the :func:`_coverage` (None: no ``observed``); methods in name order."""
    n_runs = runs.group_by("method").agg(pl.col("run").n_unique().alias("n_runs"))
    wide = counts.join(n_runs, on="method", how="left").sort("method")
    names = ["swaps", "spurious_tracks", "tracks"]
    if coverage is not None:
        wide = wide.join(coverage, on="method", how="left")
        names = ["completeness", "breaks"] + names
    long = wide.unpivot(index=["method", "n_runs"], on=names, variable_name="metric", value_name="value")
    return _metrics_schema(long.select(pl.lit(stage).alias("stage"), "method", "metric", pl.lit("all").alias("segment"),
                                       "value", "n_runs"))


def _coverage(m: pl.DataFrame, observed: pl.DataFrame) -> pl.DataFrame:
    """(method, completeness, breaks) from the walk over each aircraft's observed epochs."""
    aircraft = aircraft_epochs(observed, m.schema["epoch"]).unique()
    return coverage_table(coverage_counts(m, aircraft, m.select("method").unique()))


def aircraft_epochs(observed: pl.DataFrame | pl.LazyFrame, epoch: pl.DataType) -> pl.DataFrame | pl.LazyFrame:
    """(run, epoch, truth_id) of ``observed`` in the types of the matched rows, without nulls."""
    return observed.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(epoch),
                           pl.col("truth_id").cast(pl.Int64)).drop_nulls()


def coverage_table(counts: pl.DataFrame) -> pl.DataFrame:
    """(method, completeness, breaks) from :func:`coverage_counts` of one or more parts."""
    c = counts.group_by("method").agg(pl.col("__walk", "__covered", "breaks").sum())
    return c.select("method", (pl.col("__covered").cast(pl.Float64) / pl.col("__walk")).alias("completeness"),
                    "breaks")


def coverage_counts(m: pl.DataFrame, aircraft: pl.DataFrame, methods: pl.DataFrame) -> pl.DataFrame:
    """(method, __walk, __covered, breaks): the aircraft-epochs walked, those covered and the
    breaks of each method (``methods``: all of the picture's) over the unique ``aircraft``
    epochs. Sums over aircraft: rows and aircraft partitioned by whole (run, aircraft) give
    them as sums over the parts."""
    cover = (m.filter(pl.col("truth_id").is_not_null())
             .group_by("method", "run", "epoch", "truth_id").agg(pl.col("track_id").min().alias("cover_id")))
    walk = (aircraft.join(methods, how="cross")
            .join(cover, on=["method", "run", "epoch", "truth_id"], how="left")
            .sort("method", "run", "truth_id", "epoch")
            .with_columns(pl.int_range(pl.len()).over(["method", "run", "truth_id"]).alias("__k")))
    key = ["method", "run", "truth_id"]
    cov = walk.filter(pl.col("cover_id").is_not_null())
    prev_k = pl.col("__k").shift(1).over(key)
    prev_id = pl.col("cover_id").shift(1).over(key)
    brk = cov.group_by("method").agg((prev_k.is_not_null() & ((pl.col("__k") - prev_k > 1)
                                                             | (pl.col("cover_id") != prev_id))).sum()
                                     .cast(pl.Float64).alias("breaks"))
    comp = walk.group_by("method").agg(pl.len().alias("__walk"),
                                       pl.col("cover_id").is_not_null().sum().alias("__covered"))
    return comp.join(brk, on="method", how="left").with_columns(pl.col("breaks").fill_null(0.0))


#: what :func:`picture_accuracy` reads of a row-scored picture beside :data:`ROW_SCORES`
ACCURACY_COLUMNS = (*_TRACK, "epoch", "truth_id", "seg_class", *FUSION_METRICS.values(), "sd_pos", "nees_pos", "nees", "nis")


def picture_accuracy(matched: pl.DataFrame, stage: str, cfg: AccuracyConfig = AccuracyConfig(),
                     observed: pl.DataFrame | None = None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """Every seed metric of the matched pictures (column ``method`` names each): real accuracy,
    potential accuracy, NEES/NIS consistency and continuity (metrics schema, ``stage``); the
    per-epoch accuracy (:data:`BY_EPOCH_SCHEMA`); the scored samples (:func:`scored_samples`)."""
    if matched.height == 0:
        return empty_metrics(), pl.DataFrame(schema=BY_EPOCH_SCHEMA), scored_samples(pl.DataFrame(
            schema={"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64, "seg_class": pl.String}))
    # what the metrics below read: the picture's other columns are not copied through them
    scored = scored_rows(matched.select(c for c in matched.columns if c in ACCURACY_COLUMNS or c in ROW_SCORES)
                         if set(ROW_SCORES) <= set(matched.columns) else matched, cfg,
                         first_seen(observed, matched.schema))
    scored = scored.select(c for c in scored.columns if c in ACCURACY_COLUMNS)
    parts = [accuracy_from_matched(scored, cfg, stage), *_consistency(scored, stage, cfg.band),
             continuity_metrics(matched, observed, stage)]
    return metrics_concat(parts), accuracy_by_epoch_from_matched(scored, cfg), scored_samples(scored)


def metrics_concat(parts: list[pl.DataFrame]) -> pl.DataFrame:
    """The seed metrics table of the non-empty ``parts``, in their order."""
    metrics = pl.concat([p for p in parts if p.height], how="vertical_relaxed") if any(p.height for p in parts) \
        else empty_metrics()
    return _metrics_schema(metrics)


def scored_samples(matched: pl.DataFrame) -> pl.DataFrame:
    """(method, run, epoch, truth_id, seg_class) of scored rows: what a bound is pooled over,
    held through the evaluation for every row of every picture (a national day's two pictures:
    40 M rows). The two names are categorical: 28 bytes a row, against 46 as strings."""
    return matched.select(pl.col("method").cast(pl.Categorical), "run", pl.col("epoch").cast(TIME),
                          pl.col("truth_id").cast(pl.Int64), pl.col("seg_class").cast(pl.Categorical))

