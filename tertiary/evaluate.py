"""Evaluation against truth: real accuracy of fused states and association correctness (stage 9).

Truth of a system target
------------------------
Each (run, epoch, target_id) of the ``associations`` table gets the **majority truth_id** of the
reports associated with it at that epoch (``report_id`` → ``truth_id`` from the reports). Clutter
reports (null ``truth_id``) do not vote; a target whose reports are all clutter has a null truth.
Ties go to the smallest truth_id, so the result is deterministic.

Real accuracy (monograph (2.15), tertiary digest (4.84))
--------------------------------------------------------
A fused row is compared with its truth aircraft at ``time == epoch``; truth is sampled on a
1 s grid and is interpolated linearly when an epoch falls between two samples (epochs outside
the aircraft's truth span are not scored). With e_j(k) the error of sample j at epoch k,

    σ²(k) = Σ_{j=1..N_k} e_j(k)² / (N_k − 1)                                        (2.15)/(4.84)

the squared real accuracy at epoch k, about the **truth** (not the sample mean). The samples of
an epoch are all scored fused rows of that method at that epoch — for one aircraft, one per
Monte-Carlo run (N_k = number of runs, the seed's case); with several aircraft they are pooled.
``denominator="n"`` divides by N_k instead. For 3-D position and velocity e² = |e|² (sum of the
three components), for range e = |p_fused| − |p_true| (range from the processing centre = the
system origin).

Horizontal and vertical error. Surveillance specifications judge the two separately, so beside
the 3-D ``rmse_pos_m`` (e² = Δx² + Δy² + Δz²) every picture gets ``rmse_horizontal_m``
(e² = Δx² + Δy², east and north of the system ENU frame) and ``rmse_height_m``. The height error
is e = alt_m − alt_m_true whenever both the picture row and the truth carry the vertical
channel ``alt_m`` (barometric / geodetic height, :mod:`tertiary.altitude`; the simulator's
truth does). Otherwise it falls back to e = Δz: the frame's z is not the height h — at
horizontal distance d from the origin z = h − d²/(2R) + O(d⁴/R³) (R the Earth radius), so
z_est − z_true = (h_est − h_true) − (d_est² − d_true²)/(2R); at the same horizontal point
Δz = Δh·cos(d/R) (> 0.9998 Δh within 100 km) and a horizontal error Δd adds the cross term
−(d/R)·Δd (1.6 % of Δd at d = 100 km) — Δz equals the height error to first order only.

Pooling when an epoch has too few samples. With ``"n-1"`` an epoch with N_k = 1 (one aircraft
in one run, or the edge of coverage) has no (2.15). Instead of dropping it, the M samples of all
such epochs of a (method, segment) are **pooled** into one sample with the N − 1 denominator:
each of those epochs gets σ²(k) = e_k² · M / (M − 1), so that their mean is Σ e² / (M − 1),
the (2.15) of the pool. Only a pool with M < 2 is left out. ``accuracy_by_epoch`` marks those
rows ``pooled`` and gives N_k in ``n``, so a reader (and the report) can tell a well-sampled
epoch from a thin one.

The **pooled** figure of a metric is

    RMSE = sqrt( (1/K) Σ_k σ²(k) )

the root of the mean over the K scored epochs of the per-epoch squared real accuracy.
``n_runs`` is the number of distinct Monte-Carlo runs that contributed.

Segments: ``all``; ``straight`` ← truth segments straight|climb|descent; ``turn`` ← turn.
Holding patterns (``hold``) and unknown segments count only in ``all``. A segment without
samples is omitted. The split is by the truth segment at the epoch.

The filter transient is discarded: rows less than ``skip_first_s`` (default 20 s, tertiary
digest) after the first epoch of their (run, method, target_id) are not scored.

Consistency (:func:`consistency_metrics`, :func:`fusion_consistency`)
--------------------------------------------------------------------
``nees_*`` (position NEES Δpᵀ P_pp⁻¹ Δp, 3 degrees of freedom) and ``nees6_*`` (6-state, 6)
of every fused picture: the mean; the Monte-Carlo test ``*_in_band_frac`` — the fraction of
epochs whose mean over the N_k samples (runs × targets) lies in the two-sided 95 % band
χ²(dN_k)/N_k; and the band of the overall mean from the effective sample size n/τ
(``*_band_lo``/``_hi``, ``*_n_eff``; τ from :func:`integrated_autocorrelation`), which makes
the band right for one run as well as for N runs.

Association metrics (stage ``association``, method ``assignment``, segment ``all``)
-----------------------------------------------------------------------------------
* ``assoc_correct_frac``: among association rows whose report has a truth_id, the fraction
  whose target's majority truth_id equals the report's own (counted per association row, i.e.
  per (run, epoch, report): each epoch's assignment is a separate decision).
* ``swaps``: for each (run, target_id), walk the epochs at which the target exists in
  time order; a swap is a pair of consecutive such epochs whose majority truth_ids are both
  non-null and differ. Summed over targets and runs.
* ``targets_per_truth``: for each (run, truth_id) with at least one associated report, the
  number of distinct target ids that had it as majority truth at some epoch; the mean over
  those (run, truth_id) pairs (1 is ideal; > 1 means track breaks or splits).
* ``false_targets``: number of (run, target_id) whose associated reports are all clutter,
  summed over runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
from scipy.stats import chi2

from tertiary.schema import TABLES, TIME

__all__ = [
    "EvaluateConfig",
    "SEGMENT_CLASSES",
    "FUSION_METRICS",
    "target_truth",
    "match_truth",
    "accuracy",
    "accuracy_by_epoch",
    "BY_EPOCH_SCHEMA",
    "association_metrics",
    "metrics_frame",
    "add_nees",
    "chi2_band",
    "integrated_autocorrelation",
    "consistency_metrics",
    "fusion_consistency",
    "scored_samples",
    "CONSISTENCY",
]

Denominator = Literal["n-1", "n"]

#: truth segment → evaluation segment (anything else counts only in ``all``)
SEGMENT_CLASSES: dict[str, str] = {"straight": "straight", "climb": "straight", "descent": "straight",
                                   "turn": "turn"}

#: metric name → squared-error column of :func:`match_truth`
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

STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
_KEY = ["run", "epoch", "target_id"]


@dataclass(frozen=True)
class EvaluateConfig:
    """Evaluation options.

    * ``skip_first_s``: discard fused rows this many seconds after the first epoch of their
      (run, method, target_id) — the filter transient (tertiary digest: the first 20 s).
    * ``denominator``: ``"n-1"`` (seed (2.15)/(4.84)) or ``"n"``.
    * ``stage``: the ``stage`` label of the accuracy rows in the metrics table.
    """

    skip_first_s: float = 20.0
    denominator: Denominator = "n-1"
    stage: str = "fusion"

    def __post_init__(self) -> None:
        if self.denominator not in ("n-1", "n"):
            raise ValueError(f"denominator must be 'n-1' or 'n', got {self.denominator!r}")
        if self.skip_first_s < 0:
            raise ValueError(f"skip_first_s must be >= 0, got {self.skip_first_s}")


# --------------------------------------------------------------------------- truth of targets


def _report_truth(associations: pl.DataFrame, report_truth: pl.DataFrame) -> pl.DataFrame:
    """Association rows with the truth_id of their report (null for clutter/unknown)."""
    on = ["report_id"]
    if "run" in report_truth.columns and "run" in associations.columns:
        on = ["run", "report_id"]
    rt = report_truth.select(*[pl.col(c).cast(associations.schema[c]) for c in on],
                             pl.col("truth_id").cast(pl.Int64)).unique(subset=on, keep="first")
    return associations.join(rt, on=on, how="left", maintain_order="left")


def _majority(labelled: pl.DataFrame, key: list[str]) -> pl.DataFrame:
    """Majority non-null truth_id per ``key`` (ties → smallest truth_id; null if none)."""
    keys = labelled.select(key).unique()
    votes = (labelled.filter(pl.col("truth_id").is_not_null())
             .group_by(key + ["truth_id"]).agg(pl.len().alias("__votes"))
             .sort(key + ["__votes", "truth_id"], descending=[False] * len(key) + [True, False])
             .unique(subset=key, keep="first", maintain_order=True)
             .select(key + ["truth_id"]))
    return keys.join(votes, on=key, how="left")


def target_truth(associations: pl.DataFrame, report_truth: pl.DataFrame) -> pl.DataFrame:
    """(run, epoch, target_id, truth_id): the majority truth of each target at each epoch.

    ``report_truth`` is any frame with ``report_id`` and ``truth_id`` (e.g. the reports table;
    if both frames have ``run`` the join is on (run, report_id)).
    """
    labelled = _report_truth(associations, report_truth)
    return _majority(labelled, _KEY).sort(_KEY)


# --------------------------------------------------------------------------- truth matching


def truth_at(samples: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """Truth state of ``samples`` (truth_id, epoch): exact or linearly interpolated between the
    neighbouring truth samples; null outside the aircraft's truth span. ``true_alt_m`` too when
    both frames carry ``alt_m``."""
    cols = list(STATE) + (["alt_m"] if "alt_m" in truth.columns and "alt_m" in samples.columns else [])
    has_seg = "segment" in truth.columns
    tr = truth.select(pl.col("truth_id").cast(pl.Int64), pl.col("time").cast(TIME), *cols,
                      (pl.col("segment") if has_seg else pl.lit(None, pl.String)).alias("segment")
                      ).sort("time")
    left = samples.with_row_index("__i").sort("epoch")
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


def match_truth(fused: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
                truth: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig(), *, keep_cov: bool = True,
                nees: bool = False) -> pl.DataFrame:
    """Scored fused rows: the ``fused`` columns plus ``truth_id``, ``segment`` (truth segment),
    ``seg_class`` (straight/turn/null), ``true_<state>`` and the squared errors ``e2_x``,
    ``e2_y``, ``e2_z``, ``e2_pos`` (|Δp|²), ``e2_range`` ((|p| − |p_true|)²), ``e2_vel`` (|Δv|²).

    Rows without a truth (clutter targets, epochs outside the truth span) and rows within
    ``cfg.skip_first_s`` of their (run, method, target_id)'s first epoch are dropped. Only the
    key, state (and, with ``keep_cov``, covariance) columns are carried through the joins.
    With ``nees`` the rows also get ``nees_pos`` and ``nees`` (:func:`add_nees`), computed from
    the fused covariances without carrying them through the joins.
    """
    keep = ["run", "epoch", "target_id", "method", *STATE] + (["cov"] if keep_cov and "cov" in fused.columns else [])
    keep += ["alt_m"] if "alt_m" in fused.columns else []
    nees = nees and "cov" in fused.columns
    f = fused.select(keep).with_columns(pl.col("epoch").cast(TIME))
    if nees:
        f = f.with_row_index("_fused_row")
    if cfg.skip_first_s > 0:
        first = pl.col("epoch").min().over(["run", "method", "target_id"])
        f = f.filter((pl.col("epoch") - first).dt.total_microseconds() >= round(cfg.skip_first_s * 1e6))
    tt = target_truth(associations.with_columns(pl.col("epoch").cast(TIME)), report_truth)
    f = (f.join(tt.with_columns(pl.col(c).cast(f.schema[c]) for c in _KEY), on=_KEY, how="inner")
         .filter(pl.col("truth_id").is_not_null()))
    m = truth_at(f, truth)
    m = m.with_columns(error_columns("true_alt_m" in m.columns))
    if nees:
        m = add_nees(m, fused["cov"].gather(m["_fused_row"])).drop("_fused_row")
    return m


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


def _per_epoch(matched: pl.DataFrame, group: list[str], cfg: EvaluateConfig) -> pl.DataFrame:
    """Long per-epoch table: ``group`` + epoch, metric, sigma2 (= σ²(k) of (2.15)), n (N_k),
    n_runs, pooled. With ``"n-1"`` the epochs with N_k < 2 of a ``group`` are pooled (module
    docstring): σ²(k) = Σ e² · M / ((M − 1) N_k) with M their total sample count; a pool with
    M < 2 is dropped."""
    ddof = 1 if cfg.denominator == "n-1" else 0
    e2 = list(FUSION_METRICS.values())
    agg = matched.group_by(group + ["epoch"]).agg(
        *[pl.col(c).sum() for c in e2], pl.len().alias("n"), pl.col("run").n_unique().alias("n_runs"))
    pooled = pl.col("n") <= ddof
    # M: samples of the thin epochs of the same group (0 when nothing needs pooling)
    agg = agg.with_columns(pooled.alias("pooled"),
                           pl.when(pooled).then(pl.col("n")).otherwise(0).sum().over(group).alias("__m"))
    agg = agg.filter(~pl.col("pooled") | (pl.col("__m") > ddof))
    long = agg.unpivot(index=group + ["epoch", "n", "n_runs", "pooled", "__m"], on=e2, variable_name="e2",
                       value_name="sum_e2")
    name = {v: k for k, v in FUSION_METRICS.items()}
    m = pl.col("__m").cast(pl.Float64)
    sigma2 = (pl.when(pl.col("pooled")).then(pl.col("sum_e2") * m / ((m - ddof) * pl.col("n")))
              .otherwise(pl.col("sum_e2") / (pl.col("n") - ddof)))
    return long.select(
        *group, "epoch",
        pl.col("e2").replace_strict(name, return_dtype=pl.String).alias("metric"),
        sigma2.alias("sigma2"),
        "n", "n_runs", "pooled")


def _with_segments(matched: pl.DataFrame) -> pl.DataFrame:
    """Rows once with segment ``all`` and once more with their straight/turn class."""
    allrows = matched.with_columns(pl.lit("all").alias("eval_segment"))
    split = matched.filter(pl.col("seg_class").is_not_null()).with_columns(pl.col("seg_class").alias("eval_segment"))
    return pl.concat([allrows, split], how="vertical")


def _metrics_schema(frame: pl.DataFrame) -> pl.DataFrame:
    spec = TABLES["metrics"].required
    return frame.select([pl.col(c).cast(t) for c, t in spec.items()])


def _empty_metrics() -> pl.DataFrame:
    return pl.DataFrame(schema=TABLES["metrics"].required)


def accuracy_from_matched(matched: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig()) -> pl.DataFrame:
    """Pooled real accuracy (metrics schema) from :func:`match_truth` rows:
    RMSE = sqrt(mean_k σ²(k)), σ²(k) from (2.15)/(4.84), per method, metric and segment."""
    if matched.is_empty():
        return _empty_metrics()
    rows = _with_segments(matched)
    per = _per_epoch(rows, ["method", "eval_segment"], cfg)
    runs = (rows.group_by(["method", "eval_segment"])
            .agg(pl.col("run").n_unique().alias("n_runs")))
    pooled = (per.group_by(["method", "eval_segment", "metric"]).agg(pl.col("sigma2").mean().sqrt().alias("value"))
              .join(runs, on=["method", "eval_segment"], how="left"))
    seg_order = pl.col("eval_segment").replace_strict({"all": 0, "straight": 1, "turn": 2}, default=3,
                                                      return_dtype=pl.Int8)
    met_order = pl.col("metric").replace_strict({m: i for i, m in enumerate(FUSION_METRICS)}, return_dtype=pl.Int8)
    out = (pooled.sort([pl.col("method"), seg_order, met_order])
           .select(pl.lit(cfg.stage).alias("stage"), "method", "metric",
                   pl.col("eval_segment").alias("segment"), "value", "n_runs"))
    return _metrics_schema(out)


def accuracy(fused: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
             truth: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig()) -> pl.DataFrame:
    """Real accuracy of every fusion method (metrics schema, stage ``cfg.stage``):
    ``rmse_pos_m``, ``rmse_horizontal_m``, ``rmse_height_m``, ``rmse_range_m``, ``rmse_x_m``,
    ``rmse_y_m``, ``rmse_z_m``, ``rmse_vel_mps`` per segment all/straight/turn, pooled as sqrt of the mean over epochs of (2.15)/(4.84)."""
    return accuracy_from_matched(match_truth(fused, associations, report_truth, truth, cfg), cfg)


#: columns of the ``accuracy_by_epoch`` table: ``n`` = N_k (scored samples at the epoch), ``pooled`` =
#: the epoch had N_k < 2 and its σ(k) comes from the pool of such epochs (module docstring)
BY_EPOCH_SCHEMA: dict[str, pl.DataType] = {"method": pl.String, "epoch": TIME, "metric": pl.String,
                                           "value": pl.Float64, "n_runs": pl.UInt32, "n": pl.UInt32,
                                           "pooled": pl.Boolean}


def accuracy_by_epoch(fused: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
                      truth: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig()) -> pl.DataFrame:
    """Per-epoch real accuracy σ(k) = sqrt(Σ_j e_j(k)² / (N_k − 1)) ((2.15)/(4.84)) for the
    report's accuracy curves (seed figs. 4.10/4.11): columns (method, epoch, metric, value,
    n_runs, n, pooled) — :data:`BY_EPOCH_SCHEMA` — with one row per :data:`FUSION_METRICS`
    metric (``rmse_horizontal_m`` and ``rmse_height_m`` beside ``rmse_pos_m``), all segments
    together, sorted by method, metric, epoch; epochs with N_k < 2 are pooled, not dropped.
    Pass ``EvaluateConfig(skip_first_s=0)`` to include the transient."""
    return accuracy_by_epoch_from_matched(match_truth(fused, associations, report_truth, truth, cfg), cfg)


def accuracy_by_epoch_from_matched(matched: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig()) -> pl.DataFrame:
    """:func:`accuracy_by_epoch` from already matched rows (match once, derive both tables)."""
    if matched.is_empty():
        return pl.DataFrame(schema=BY_EPOCH_SCHEMA)
    per = _per_epoch(matched, ["method"], cfg)
    met_order = pl.col("metric").replace_strict({m: i for i, m in enumerate(FUSION_METRICS)}, return_dtype=pl.Int8)
    return (per.sort([pl.col("method"), met_order, pl.col("epoch")])
            .select("method", "epoch", "metric", pl.col("sigma2").sqrt().alias("value"), "n_runs", "n", "pooled")
            .cast(BY_EPOCH_SCHEMA))


# --------------------------------------------------------------------------- consistency


def add_nees(matched: pl.DataFrame, cov: pl.Series | None = None, block: int = 131_072) -> pl.DataFrame:
    """Add the normalised estimation error squared of each :func:`match_truth` row:
    ``nees_pos`` = Δpᵀ P_pp⁻¹ Δp (3 degrees of freedom, mean 3 when consistent) and ``nees``
    over the full 6-state (mean 6). The flattened 6×6 covariance (x, y, z, vx, vy, vz) is the
    row's ``cov`` column, or ``cov`` given aligned with the rows; computed in blocks of rows
    so the (n, 6, 6) arrays stay small. A singular covariance gives NaN."""
    if matched.is_empty():
        return matched.with_columns(pl.lit(None, pl.Float64).alias("nees_pos"), pl.lit(None, pl.Float64).alias("nees"))
    cov = matched["cov"] if cov is None else cov
    err = np.stack([(matched[c] - matched[f"true_{c}"]).to_numpy() for c in STATE], axis=1)
    nees_pos, nees = np.full(len(err), np.nan), np.full(len(err), np.nan)
    for lo in range(0, len(err), block):
        sl = slice(lo, lo + block)
        p = cov.slice(lo, block).to_numpy().reshape(-1, 6, 6)
        e = err[sl]
        ok = np.all(np.isfinite(p.reshape(-1, 36)), axis=1) & np.all(np.isfinite(e), axis=1)
        ok &= np.linalg.det(p[:, :3, :3]) > 0
        if not ok.any():
            continue
        pk, ek = p[ok], e[ok]
        with np.errstate(all="ignore"):
            a = np.einsum("ni,ni->n", ek[:, :3], np.linalg.solve(pk[:, :3, :3], ek[:, :3, None])[..., 0])
            try:
                b = np.einsum("ni,ni->n", ek, np.linalg.solve(pk, ek[..., None])[..., 0])
            except np.linalg.LinAlgError:        # a singular full covariance: position NEES only
                b = np.full(len(ek), np.nan)
        idx = np.flatnonzero(ok) + lo
        nees_pos[idx], nees[idx] = a, b
    return matched.with_columns(pl.Series("nees_pos", nees_pos), pl.Series("nees", nees))


def chi2_band(n, dof: int, band: float = 0.95):
    """Two-sided ``band`` interval of the mean of ``n`` independent χ²(``dof``) samples:
    χ²_{(1∓band)/2}(dof·n)/n. ``n`` may be an array (also non-integer: an effective sample
    size); n ≤ 0 gives NaN. Scalars in, a (lo, hi) tuple of floats out."""
    arr = np.asarray(n, dtype=float)
    with np.errstate(all="ignore"):
        safe = np.where(arr > 0, arr, np.nan)
        lo = chi2.ppf((1 - band) / 2, dof * safe) / safe
        hi = chi2.ppf((1 + band) / 2, dof * safe) / safe
    if arr.ndim == 0:
        return float(lo), float(hi)
    return lo, hi


def integrated_autocorrelation(x: np.ndarray, series: np.ndarray, max_lag: int = 1000) -> float:
    """Integrated autocorrelation time τ of a sequence observed as several series (``series``
    codes; rows sorted by series then time, consecutive rows of a series one step apart), so
    that the mean of the n rows has the variance of n/τ independent ones.

    Var(Σ x) = n γ₀ + 2 Σ_{l≥1} Σ_{pairs at lag l inside one series} Cov, hence

        τ = 1 + 2 Σ_{l≥1} (P_l/n) ρ_l,    ρ_l = γ_l/γ₀,

    with P_l the number of pairs at lag l inside a series (P_l/n → 1 for long series: the
    usual 1 + 2 Σ ρ_l), γ_l the mean of (x_t − x̄)(x_{t+l} − x̄) over those pairs and x̄ the mean
    of all rows (the series are runs or targets of one picture). The sum is truncated by
    Geyer's initial positive sequence rule (Geyer 1992, Stat. Sci. 7(4)): the pair sums of
    consecutive terms (lags 2m, 2m + 1, lag 0 counting 1) are added while positive.
    τ ≥ 1 (independent samples: τ = 1)."""
    x = np.asarray(x, float)
    n = len(x)
    if n < 3:
        return 1.0
    y = x - x.mean()
    g0 = float(np.mean(y * y))
    if not g0 > 0:
        return 1.0
    terms = [1.0]          # (P_l / n) ρ_l, lag 0 first
    tau = -1.0
    for m in range(max_lag // 2):
        for lag in (2 * m, 2 * m + 1):
            if lag == 0:
                continue
            if lag >= n:
                terms.append(0.0)
                continue
            same = series[lag:] == series[:-lag]
            terms.append(float(np.sum((y[lag:] * y[:-lag])[same])) / (n * g0))
        pair = terms[2 * m] + terms[2 * m + 1]
        if pair <= 0:
            break
        tau += 2 * pair
    return max(tau, 1.0)


#: consistency statistic → (column, degrees of freedom)
CONSISTENCY = {"nees": ("nees_pos", 3), "nees6": ("nees", 6)}


def consistency_metrics(rows: pl.DataFrame, column: str, dof: int, prefix: str, stage: str,
                        obj: str = "target_id", band: float = 0.95) -> pl.DataFrame:
    """Consistency of a normalised squared error ``column`` (NEES or NIS, χ²(``dof``) when the
    covariance is right) per ``method`` and segment (all/straight/turn), in the metrics schema:

    * ``<prefix>_mean``: the mean over all samples.
    * ``<prefix>_in_band_frac``: the Monte-Carlo test — at each epoch k the N_k samples (one
      per run and object; independent draws) are averaged and compared with the two-sided
      ``band`` interval χ²(dof·N_k)/N_k of such an average; the fraction of epochs inside.
      With one run and one object N_k = 1: the χ²(dof) interval of a single sample.
    * ``<prefix>_band_lo`` / ``_band_hi``: the interval of ``<prefix>_mean`` itself, from the
      effective sample size n_eff = n/τ (τ: :func:`integrated_autocorrelation` along each
      (run, ``obj``) series in epoch order) — consecutive errors of a filter are correlated,
      so the n samples are worth n/τ independent ones.
    * ``<prefix>_n_eff``: that effective sample size.
    """
    spec = TABLES["metrics"].required
    r = rows.filter(pl.col(column).is_not_null() & pl.col(column).is_finite())
    if r.is_empty():
        return pl.DataFrame(schema=spec)
    r = r.select("method", "run", "epoch", obj, "seg_class", column)
    r = pl.concat([r.with_columns(pl.lit("all").alias("eval_segment")),
                   r.filter(pl.col("seg_class").is_not_null()).with_columns(pl.col("seg_class").alias("eval_segment"))])
    per = r.group_by("method", "eval_segment", "epoch").agg(pl.col(column).mean().alias("__m"), pl.len().alias("__n"))
    lo, hi = chi2_band(per["__n"].to_numpy(), dof, band)
    per = per.with_columns(pl.Series("__in", (per["__m"].to_numpy() >= lo) & (per["__m"].to_numpy() <= hi)))
    frac = per.group_by("method", "eval_segment").agg(pl.col("__in").mean().alias("in_band"))
    out = []
    for (method, seg), g in r.sort("method", "eval_segment", "run", obj, "epoch").group_by(
            ["method", "eval_segment"], maintain_order=True):
        keys = g.select(pl.struct("run", obj).rank("dense").alias("k"))["k"].to_numpy()
        x = g[column].to_numpy()
        tau = integrated_autocorrelation(x, keys)
        n_eff = len(x) / tau
        b_lo, b_hi = chi2_band(n_eff, dof, band)
        f = frac.filter((pl.col("method") == method) & (pl.col("eval_segment") == seg))["in_band"].item()
        nr = g["run"].n_unique()
        for metric, value in (("mean", float(x.mean())), ("in_band_frac", float(f)), ("band_lo", b_lo),
                              ("band_hi", b_hi), ("n_eff", n_eff)):
            out.append({"stage": stage, "method": method, "metric": f"{prefix}_{metric}", "segment": seg,
                        "value": value, "n_runs": nr})
    return pl.DataFrame(out, schema=spec)


def fusion_consistency(matched: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig(), band: float = 0.95
                       ) -> pl.DataFrame:
    """``nees_*`` (position, 3 degrees of freedom, the full 3×3 covariance) and ``nees6_*`` (the
    6-state) of every fused picture (:func:`consistency_metrics`) from :func:`match_truth`
    rows with NEES (``nees=True``)."""
    parts = [consistency_metrics(matched, col, dof, prefix, cfg.stage, "target_id", band)
             for prefix, (col, dof) in CONSISTENCY.items() if col in matched.columns]
    return pl.concat(parts) if parts else _empty_metrics()


def scored_samples(matched: pl.DataFrame) -> pl.DataFrame:
    """(method, run, epoch, truth_id, seg_class) of scored rows: what a bound is pooled over."""
    return matched.select("method", "run", pl.col("epoch").cast(TIME), pl.col("truth_id").cast(pl.Int64),
                          "seg_class")


# --------------------------------------------------------------------------- association


def association_metrics(associations: pl.DataFrame, report_truth: pl.DataFrame) -> pl.DataFrame:
    """Association correctness (metrics schema, stage ``association``, method ``assignment``,
    segment ``all``): ``swaps``, ``targets_per_truth``, ``false_targets`` as defined in the
    module docstring, and

    * ``assoc_correct_frac``: among association rows whose report has a truth_id, the fraction
      whose target both has that truth as majority and is the aircraft's principal target at
      the epoch (the one holding most of its reports; ties: lowest id) — a report put in a
      second, duplicate target of its aircraft is not correctly associated;

    * ``split_targets``: number of (run, epoch, truth_id) whose reports went to two or more
      system targets at that epoch (one aircraft shown as several targets);
    * ``merged_targets``: number of (run, epoch, target_id) whose reports come from two or
      more aircraft (several aircraft shown as one target).
    """
    if associations.is_empty():
        return _empty_metrics()
    labelled = _report_truth(associations.with_columns(pl.col("epoch").cast(TIME)), report_truth)
    maj = _majority(labelled, _KEY).rename({"truth_id": "target_truth"})
    rows = labelled.join(maj, on=_KEY, how="left")
    n_runs = associations["run"].n_unique()

    real = rows.filter(pl.col("truth_id").is_not_null())
    # the aircraft's principal target at the epoch: most of its reports (ties: lowest id)
    principal = (real.group_by(["run", "epoch", "truth_id", "target_id"]).agg(pl.len().alias("__n"))
                 .sort(["run", "epoch", "truth_id", "__n", "target_id"], descending=[False, False, False, True, False])
                 .unique(subset=["run", "epoch", "truth_id"], keep="first", maintain_order=True)
                 .select("run", "epoch", "truth_id", pl.col("target_id").alias("__principal")))
    real = real.join(principal, on=["run", "epoch", "truth_id"], how="left")
    correct = (real.select(((pl.col("truth_id") == pl.col("target_truth"))
                            & (pl.col("target_id") == pl.col("__principal"))).fill_null(False).mean()).item()
               if real.height else float("nan"))

    seq = maj.sort(["run", "target_id", "epoch"])
    prev = pl.col("target_truth").shift(1).over(["run", "target_id"])
    swaps = seq.select(((pl.col("target_truth") != prev) & prev.is_not_null()
                        & pl.col("target_truth").is_not_null()).fill_null(False).sum()).item()

    truths = real.select("run", "truth_id").unique()
    got = (maj.filter(pl.col("target_truth").is_not_null())
           .group_by(["run", "target_truth"]).agg(pl.col("target_id").n_unique().alias("n_targets"))
           .rename({"target_truth": "truth_id"}))
    per_truth = truths.join(got, on=["run", "truth_id"], how="left").with_columns(pl.col("n_targets").fill_null(0))
    tpt = float(per_truth["n_targets"].mean()) if per_truth.height else float("nan")

    false_targets = (labelled.group_by(["run", "target_id"]).agg(pl.col("truth_id").is_null().all().alias("clutter"))
                     ["clutter"].sum())
    split = (real.group_by(["run", "epoch", "truth_id"]).agg(pl.col("target_id").n_unique().alias("n"))
             .filter(pl.col("n") > 1).height)
    merged = (real.group_by(_KEY).agg(pl.col("truth_id").n_unique().alias("n")).filter(pl.col("n") > 1).height)

    out = pl.DataFrame({
        "stage": "association", "method": "assignment",
        "metric": ["assoc_correct_frac", "swaps", "targets_per_truth", "false_targets", "split_targets",
                   "merged_targets"],
        "segment": "all",
        "value": [float(correct), float(swaps), tpt, float(false_targets), float(split), float(merged)],
        "n_runs": n_runs,
    })
    return _metrics_schema(out)


def metrics_frame(fused: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
                  truth: pl.DataFrame, cfg: EvaluateConfig = EvaluateConfig()) -> pl.DataFrame:
    """All evaluation rows — fusion accuracy then association metrics — in the ``metrics``
    table's dtypes (stage, method, metric, segment, value, n_runs)."""
    parts = [accuracy(fused, associations, report_truth, truth, cfg),
             association_metrics(associations, report_truth)]
    return pl.concat(parts, how="vertical")
