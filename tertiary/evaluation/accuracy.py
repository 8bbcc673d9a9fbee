"""Real accuracy, consistency and track continuity of a *matched* picture (the seed metrics).

Every picture — a fusion method's plots, the centralised reference, a tracker's output or a
picture ``tertiary`` did not produce — is first matched to the reference aircraft by the one
matcher, :func:`tertiary.evaluation.matching.match_to_reference` (geometric, one-to-one per epoch). This
module only computes statistics of the matched rows; it never decides which aircraft a row is.

Scored rows (:func:`scored_rows`)
---------------------------------
The matched rows with a reference aircraft, at least ``skip_first_s`` (default 20 s, tertiary
digest: the filter transient) after the first epoch of their (run, picture, track). Rows the
matcher left unmatched (false tracks, second tracks on an aircraft, gross errors beyond the
gate) are not accuracy samples: they are counted by the continuity and picture metrics.

Real accuracy (monograph (2.15), tertiary digest (4.84))
--------------------------------------------------------
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

Consistency (:func:`consistency_metrics`)
-----------------------------------------
``nees_*`` (position NEES Δpᵀ P_pp⁻¹ Δp, 3 degrees of freedom; from the diagonal ``cov_diag``
when a picture has no full ``cov``), ``nees6_*`` (6-state, 6) and, for pictures that carry a
``nis`` column (the trackers), ``nis_*`` (3): the mean; the Monte-Carlo test ``*_in_band_frac``
— the fraction of epochs whose mean over the N_k samples lies in the two-sided 95 % band
χ²(dN_k)/N_k; and the band of the overall mean from the effective sample size n/τ
(``*_band_lo``/``_hi``, ``*_n_eff``; τ from :func:`integrated_autocorrelation`).
``potential_pos_m``: the mean of sqrt(P_xx + P_yy + P_zz) (potential accuracy, §2.2.1).

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

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.evaluation.buckets import file_buckets
from tertiary.core.distributions import chi2_ppf
from tertiary.contract.schema import TABLES, TIME

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
    "add_nees",
    "chi2_band",
    "integrated_autocorrelation",
    "consistency_metrics",
    "scored_samples",
    "CONSISTENCY",
    "picture_accuracy_buckets",
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

STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
_TRACK = ["run", "method", "track_id"]


@dataclass(frozen=True)
class AccuracyConfig:
    """Options of the seed metrics.

    * ``skip_first_s``: discard rows this many seconds after the first epoch of their
      (run, picture, track) — the filter transient (tertiary digest: the first 20 s).
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
    n_runs, pooled (:func:`_pool_epochs`)."""
    e2 = list(FUSION_METRICS.values())
    agg = matched.group_by(group + ["epoch"]).agg(
        *[pl.col(c).sum() for c in e2], pl.len().alias("n"), pl.col("run").n_unique().alias("n_runs"))
    return _pool_epochs(agg, group, cfg)


def _pool_epochs(agg: pl.DataFrame, group: list[str], cfg: AccuracyConfig) -> pl.DataFrame:
    """:func:`_per_epoch` from its sums per ``group`` + epoch (the e² sums, ``n`` = N_k, ``n_runs``):
    shared with :func:`picture_accuracy_buckets`, which adds those sums up over buckets. With
    ``"n-1"`` the epochs with N_k < 2 of a ``group`` are pooled (module docstring):
    σ²(k) = Σ e² · M / ((M − 1) N_k) with M their total sample count; a pool with M < 2 is dropped."""
    ddof = 1 if cfg.denominator == "n-1" else 0
    e2 = list(FUSION_METRICS.values())
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


def accuracy_from_matched(matched: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig(),
                          stage: str = "fusion") -> pl.DataFrame:
    """Pooled real accuracy (metrics schema, ``stage``) from :func:`scored_rows`:
    RMSE = sqrt(mean_k σ²(k)), σ²(k) from (2.15)/(4.84), per method, metric and segment."""
    if matched.is_empty():
        return _empty_metrics()
    group = ["method", "eval_segment"]
    # segment "all" and each row's straight/turn class grouped in place, never a copy of the rows
    rows = [matched.with_columns(pl.lit("all").alias("eval_segment")),
            matched.with_columns(pl.col("seg_class").alias("eval_segment"))]
    per = pl.concat([_per_epoch(r, group, cfg).filter(pl.col("eval_segment").is_not_null()) for r in rows])
    runs = pl.concat([r.group_by(group).agg(pl.col("run").n_unique().alias("n_runs"))
                      .filter(pl.col("eval_segment").is_not_null()) for r in rows])
    del rows
    return _accuracy_table(per, runs, stage)


def _accuracy_table(per: pl.DataFrame, runs: pl.DataFrame, stage: str) -> pl.DataFrame:
    """The metrics rows of :func:`accuracy_from_matched` from its per-epoch table ``per``
    (:func:`_pool_epochs`, group method + eval_segment) and ``runs`` (n_runs of each group)."""
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
    return _by_epoch_table(_per_epoch(matched, ["method"], cfg))


def _by_epoch_table(per: pl.DataFrame) -> pl.DataFrame:
    """:data:`BY_EPOCH_SCHEMA` rows from the per-epoch table of segment ``all`` (group method)."""
    met_order = pl.col("metric").replace_strict({m: i for i, m in enumerate(FUSION_METRICS)}, return_dtype=pl.Int8)
    return (per.sort([pl.col("method"), met_order, pl.col("epoch")])
            .select("method", "epoch", "metric", pl.col("sigma2").sqrt().alias("value"), "n_runs", "n", "pooled")
            .cast(BY_EPOCH_SCHEMA))


# --------------------------------------------------------------------------- consistency


def _nees_full(p: NDArray[np.float64], e: NDArray[np.float64]) -> NDArray[np.float64]:
    """eᵀ P⁻¹ e per row; NaN on a row whose full covariance is singular (position NEES only), so
    that one singular row never blanks the rows solved with it."""
    try:
        return np.einsum("ni,ni->n", e, np.linalg.solve(p, e[..., None])[..., 0])
    except np.linalg.LinAlgError:
        out = np.full(len(e), np.nan)
        ok = np.linalg.cond(p) < 1.0 / np.finfo(float).eps       # inf for an exactly singular P
        if ok.any():
            out[ok] = np.einsum("ni,ni->n", e[ok], np.linalg.solve(p[ok], e[ok][..., None])[..., 0])
        return out


def add_nees(matched: pl.DataFrame, cov: pl.Series | None = None, block: int = 131_072) -> pl.DataFrame:
    """Add the normalised estimation error squared of each scored row:
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
            b = _nees_full(pk, ek)
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
        lo = chi2_ppf((1 - band) / 2, dof * safe) / safe
        hi = chi2_ppf((1 + band) / 2, dof * safe) / safe
    if arr.ndim == 0:
        return float(lo), float(hi)
    return lo, hi


#: the lags of :func:`integrated_autocorrelation`'s sum: 0 … _MAX_LAG − 1
_MAX_LAG = 1000


def integrated_autocorrelation(x: np.ndarray, series: np.ndarray, max_lag: int = _MAX_LAG) -> float:
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

    def term(lag: int) -> float:
        same = series[lag:] == series[:-lag]
        return float(np.sum((y[lag:] * y[:-lag])[same])) / (n * g0)
    return _geyer_tau(term, n, max_lag)


def _geyer_tau(term: Callable[[int], float], n: int, max_lag: int) -> float:
    """τ = 1 + 2 Σ_l term(l), term(l) = (P_l/n) ρ_l for 1 ≤ l < n, truncated by Geyer's initial
    positive sequence rule (:func:`integrated_autocorrelation`); the terms are asked for in lag
    order and only up to the truncation (a term costs a pass over the rows)."""
    terms = [1.0]          # (P_l / n) ρ_l, lag 0 first
    tau = -1.0
    for m in range(max_lag // 2):
        for lag in (2 * m, 2 * m + 1):
            if lag == 0:
                continue
            terms.append(term(lag) if lag < n else 0.0)
        pair = terms[2 * m] + terms[2 * m + 1]
        if pair <= 0:
            break
        tau += 2 * pair
    return max(tau, 1.0)


#: consistency statistic → (column, degrees of freedom)
CONSISTENCY = {"nees": ("nees_pos", 3), "nees6": ("nees", 6)}


def consistency_metrics(rows: pl.DataFrame, column: str, dof: int, prefix: str, stage: str,
                        obj: str = "track_id", band: float = 0.95) -> pl.DataFrame:
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
    # the columns read, then the rows, sorted once along each (run, obj) series: the scored
    # picture is never copied whole, and a segment's rows are a filter of these (memory of the
    # stage on a long run, issue 16)
    r = rows.select("method", "run", "epoch", obj, "seg_class", column).filter(
        pl.col(column).is_not_null() & pl.col(column).is_finite()).sort("method", "run", obj, "epoch")
    if r.is_empty():
        return pl.DataFrame(schema=spec)
    out = []
    for method in sorted(r["method"].unique().to_list()):
        m = r.filter(pl.col("method") == method) if r["method"].n_unique() > 1 else r
        segments = sorted(["all", *m["seg_class"].drop_nulls().unique().to_list()])
        for seg in segments:
            g = m if seg == "all" else m.filter(pl.col("seg_class") == seg)
            out += _consistency_rows(g, column, dof, prefix, stage, obj, band, method, seg)
            del g
    return pl.DataFrame(out, schema=spec)


def _consistency_rows(g: pl.DataFrame, column: str, dof: int, prefix: str, stage: str, obj: str, band: float,
                      method: str, seg: str) -> list[dict]:
    """The five :func:`consistency_metrics` rows of one picture's segment ``g`` (sorted by run,
    ``obj``, epoch)."""
    per = g.group_by("epoch").agg(pl.col(column).mean().alias("__m"), pl.len().alias("__n"))
    x = g[column].to_numpy()
    tau = integrated_autocorrelation(x, _series_codes(g, obj))
    return _consistency_dicts(stage, method, seg, prefix, dof, band, float(x.mean()), per["__m"].to_numpy(),
                              per["__n"].to_numpy(), len(x), tau, g["run"].n_unique())


def _series_codes(g: pl.DataFrame, obj: str) -> NDArray[np.int64]:
    """One code per (run, ``obj``) series of ``g``, whose rows are sorted along the series."""
    run, who = g["run"].to_numpy(), g[obj].to_numpy()
    return np.cumsum(np.r_[True, (run[1:] != run[:-1]) | (who[1:] != who[:-1])])


def _consistency_dicts(stage: str, method: str, seg: str, prefix: str, dof: int, band: float, mean: float,
                       mean_k: NDArray[np.float64], n_k: NDArray, n: int, tau: float, n_runs: int) -> list[dict]:
    """The five :func:`consistency_metrics` rows of one picture's segment from its overall
    ``mean``, the per-epoch means ``mean_k`` of ``n_k`` samples, its ``n`` samples and their τ."""
    lo, hi = chi2_band(n_k, dof, band)
    in_band = float(np.mean((mean_k >= lo) & (mean_k <= hi)))
    n_eff = n / tau
    b_lo, b_hi = chi2_band(n_eff, dof, band)
    return [{"stage": stage, "method": method, "metric": f"{prefix}_{metric}", "segment": seg, "value": value,
             "n_runs": n_runs}
            for metric, value in (("mean", mean), ("in_band_frac", in_band), ("band_lo", b_lo),
                                  ("band_hi", b_hi), ("n_eff", n_eff))]


#: consistency statistics of a picture that carries a ``nis`` column (its innovations): the
#: tracker's measurement is the fused 3-D position
NIS_DOF = 3


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


def scored_rows(matched: pl.DataFrame, cfg: AccuracyConfig = AccuracyConfig()) -> pl.DataFrame:
    """The accuracy samples of a matched picture (module docstring): rows with a ``truth_id``,
    after the transient, with ``seg_class``, the squared errors ``e2_*`` (:func:`error_columns`),
    ``sd_pos`` and the NEES columns ``nees_pos`` (3 dof) and ``nees`` (6 dof; null without a full
    covariance). The ``cov`` column is consumed (not returned). ``matched`` may carry the
    :func:`row_scores` already (a picture scored in blocks)."""
    m = matched
    keep = pl.col("truth_id").is_not_null()
    if cfg.skip_first_s > 0 and m.height:
        first = pl.col("epoch").min().over(_TRACK)
        keep = keep & ((pl.col("epoch") - first).dt.total_microseconds() >= round(cfg.skip_first_s * 1e6))
    m = m.filter(keep)                   # one filter: the picture copied once
    return m if set(ROW_SCORES) <= set(m.columns) else row_scores(m)


def _consistency(scored: pl.DataFrame, stage: str, band: float) -> list[pl.DataFrame]:
    """``potential_pos_m`` and the NEES (3 and 6 dof) and NIS rows of every picture."""
    out = []
    pot = scored.select("method", "run", "seg_class", "sd_pos").filter(pl.col("sd_pos").is_not_null())
    if pot.height:
        # in order of appearance: the metrics table's rows are the same on every run
        rows = _with_segments(pot).group_by("method", "eval_segment", maintain_order=True).agg(
            pl.col("sd_pos").mean().alias("value"), pl.col("run").n_unique().alias("n_runs"))
        out.append(_potential_table(rows, stage))
    for prefix, (col, dof) in _statistics(scored.columns).items():
        out.append(consistency_metrics(scored, col, dof, prefix, stage, "track_id", band))
    return out


#: every consistency statistic a picture may have (NIS: a picture with a ``nis`` column), in order
_CONSISTENCY_ALL = {**CONSISTENCY, "nis": ("nis", NIS_DOF)}


def _statistics(columns: list[str]) -> dict[str, tuple[str, int]]:
    """The consistency statistics (prefix → column, dof) of a scored picture with ``columns``."""
    return {p: (c, d) for p, (c, d) in _CONSISTENCY_ALL.items() if c in columns}


def _potential_table(rows: pl.DataFrame, stage: str) -> pl.DataFrame:
    """``potential_pos_m`` rows from (method, eval_segment, value, n_runs) in their order."""
    return _metrics_schema(rows.select(pl.lit(stage).alias("stage"), "method",
                                       pl.lit("potential_pos_m").alias("metric"),
                                       pl.col("eval_segment").alias("segment"), "value", "n_runs"))


def continuity_metrics(matched: pl.DataFrame, observed: pl.DataFrame | None, stage: str) -> pl.DataFrame:
    """``completeness``, ``breaks``, ``swaps``, ``spurious_tracks`` and ``tracks`` per picture
    (segment ``all``; module docstring). ``observed``: (run, epoch, truth_id) the pictures should
    cover; without it only ``swaps``, ``spurious_tracks`` and ``tracks``."""
    m = _continuity_columns(matched)
    coverage = None if observed is None else _coverage(m, observed)
    return _continuity_table(_track_counts(m), m.select("method", "run").unique(), coverage, stage)


def _continuity_columns(matched: pl.DataFrame | pl.LazyFrame, *extra: str) -> pl.DataFrame | pl.LazyFrame:
    return matched.select("method", pl.col("run").cast(pl.UInt32), "epoch", "track_id", "truth_id", *extra)


def _track_counts(m: pl.DataFrame) -> pl.DataFrame:
    """(method, spurious_tracks, tracks, swaps) of the rows ``m`` (:func:`_continuity_columns`):
    sums over tracks, so that rows partitioned by whole tracks give them as sums over the parts."""
    per_track = m.group_by("method", "run", "track_id").agg(pl.col("truth_id").is_null().all().alias("__spurious"))
    counts = per_track.group_by("method").agg(pl.col("__spurious").sum().cast(pl.Float64).alias("spurious_tracks"),
                                              pl.len().cast(pl.Float64).alias("tracks"))
    seq = m.filter(pl.col("truth_id").is_not_null()).sort("method", "run", "track_id", "epoch")
    prev_t = pl.col("truth_id").shift(1).over(["method", "run", "track_id"])
    swaps = seq.group_by("method").agg(((pl.col("truth_id") != prev_t) & prev_t.is_not_null()).sum()
                                       .cast(pl.Float64).alias("swaps"))
    return counts.join(swaps, on="method", how="left").with_columns(pl.col("swaps").fill_null(0.0))


def _continuity_table(counts: pl.DataFrame, runs: pl.DataFrame, coverage: pl.DataFrame | None,
                      stage: str) -> pl.DataFrame:
    """:func:`continuity_metrics` from the :func:`_track_counts`, the (method, run) pairs of the
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
    aircraft = _aircraft_epochs(observed, m.schema["epoch"]).unique()
    return _coverage_table(_coverage_counts(m, aircraft, m.select("method").unique()))


def _aircraft_epochs(observed: pl.DataFrame | pl.LazyFrame, epoch: pl.DataType) -> pl.DataFrame | pl.LazyFrame:
    """(run, epoch, truth_id) of ``observed`` in the types of the matched rows, without nulls."""
    return observed.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(epoch),
                           pl.col("truth_id").cast(pl.Int64)).drop_nulls()


def _coverage_table(counts: pl.DataFrame) -> pl.DataFrame:
    """(method, completeness, breaks) from :func:`_coverage_counts` of one or more parts."""
    c = counts.group_by("method").agg(pl.col("__walk", "__covered", "breaks").sum())
    return c.select("method", (pl.col("__covered").cast(pl.Float64) / pl.col("__walk")).alias("completeness"),
                    "breaks")


def _coverage_counts(m: pl.DataFrame, aircraft: pl.DataFrame, methods: pl.DataFrame) -> pl.DataFrame:
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
_KEEP = (*_TRACK, "epoch", "truth_id", "seg_class", *FUSION_METRICS.values(), "sd_pos", "nees_pos", "nees", "nis")


def picture_accuracy(matched: pl.DataFrame, stage: str, cfg: AccuracyConfig = AccuracyConfig(),
                     observed: pl.DataFrame | None = None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """Every seed metric of the matched pictures (column ``method`` names each): real accuracy,
    potential accuracy, NEES/NIS consistency and continuity (metrics schema, ``stage``); the
    per-epoch accuracy (:data:`BY_EPOCH_SCHEMA`); the scored samples (:func:`scored_samples`)."""
    if matched.height == 0:
        return _empty_metrics(), pl.DataFrame(schema=BY_EPOCH_SCHEMA), scored_samples(pl.DataFrame(
            schema={"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64, "seg_class": pl.String}))
    # what the metrics below read: the picture's other columns are not copied through them
    scored = scored_rows(matched.select(c for c in matched.columns if c in _KEEP or c in ROW_SCORES)
                         if set(ROW_SCORES) <= set(matched.columns) else matched, cfg)
    scored = scored.select(c for c in scored.columns if c in _KEEP)
    parts = [accuracy_from_matched(scored, cfg, stage), *_consistency(scored, stage, cfg.band),
             continuity_metrics(matched, observed, stage)]
    return _metrics_concat(parts), accuracy_by_epoch_from_matched(scored, cfg), scored_samples(scored)


def _metrics_concat(parts: list[pl.DataFrame]) -> pl.DataFrame:
    """The seed metrics table of the non-empty ``parts``, in their order."""
    metrics = pl.concat([p for p in parts if p.height], how="vertical_relaxed") if any(p.height for p in parts) \
        else _empty_metrics()
    return _metrics_schema(metrics)


def scored_samples(matched: pl.DataFrame) -> pl.DataFrame:
    """(method, run, epoch, truth_id, seg_class) of scored rows: what a bound is pooled over."""
    return matched.select("method", "run", pl.col("epoch").cast(TIME), pl.col("truth_id").cast(pl.Int64),
                          "seg_class")


# --------------------------------------------------------------------------- in buckets

#: what :func:`row_scores` and :func:`picture_accuracy` read of a picture not yet row-scored
_ROW_INPUTS = (*_KEEP, "segment", *STATE, *(f"true_{c}" for c in STATE), "alt_m", "true_alt_m", "cov", "cov_diag")
#: the row index :func:`picture_accuracy_buckets` gives ``matched``: the order of the samples
_ROW = "__row"
#: cells of one zero-padded FFT block of :func:`_lag_products` (16 MiB of float64)
_FFT_CELLS = 1 << 21


def picture_accuracy_buckets(matched: pl.LazyFrame, stage: str, cfg: AccuracyConfig = AccuracyConfig(),
                             observed: pl.DataFrame | pl.LazyFrame | None = None, buckets: int = 1,
                             scratch: Path | None = None) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """:func:`picture_accuracy` of ``matched.collect()`` (and ``observed`` collected), with the
    rows read ``buckets`` parts at a time, never whole: a long recording's picture (a scan of
    Parquet parts) is scored with the memory of about 1/``buckets`` of its rows, plus the
    scored samples (five columns a row, whole-picture by nature).

    Whole tracks (hash of (method, run, track_id)) make a part: the transient cut, the NEES/NIS
    series, spurious tracks and swaps are per track. Whole aircraft (hash of (run, truth_id))
    make a part of the coverage walk, with ``observed`` cut the same way. What crosses parts is
    added up exactly: the (2.15) sums per (method, segment, epoch, run), the consistency sums per
    epoch and per lag (:class:`_Lags`), the counts and sets of runs; then finished by the code of
    :func:`picture_accuracy`. ``matched`` may carry the :data:`ROW_SCORES` (else each part is
    row-scored: :func:`row_scores` is row-wise). With a ``scratch`` directory the rows are filed
    by bucket once (:func:`tertiary.evaluation.buckets.file_buckets`) and each bucket reads its own; without,
    each bucket filters the whole of ``matched``."""
    if buckets < 1:
        raise ValueError(f"buckets must be >= 1, got {buckets}")
    schema = matched.collect_schema()          # a scan's schema: no row is read
    wanted = (*_KEEP, *ROW_SCORES) if set(ROW_SCORES) <= set(schema.names()) else _ROW_INPUTS
    lf = matched.lazy().with_row_index(_ROW)
    cols = [_ROW, *(c for c in schema.names() if c in wanted)]
    filed = scratch is not None and buckets > 1
    by_track = (file_buckets(lf.select(cols), _bucket_of(_track_key(), buckets), buckets, scratch / "tracks")
                if filed else [lf.filter(_in_bucket(_track_key(), buckets, k)).select(cols) for k in range(buckets)])
    parts = _Parts()
    for k in range(buckets):
        part = by_track[k].collect()
        if part.height:
            parts.add_tracks(part, cfg)
        del part
    if not parts.rows:
        return picture_accuracy(pl.DataFrame(), stage, cfg)
    coverage = None if observed is None else _coverage_buckets(
        lf, observed, schema["epoch"], parts.tables["tracks"].select("method"), buckets,
        scratch / "aircraft" if filed else None)
    return parts.finish(stage, cfg, coverage)


def _in_bucket(key: list[pl.Expr], buckets: int, k: int) -> pl.Expr:
    return pl.lit(True) if buckets == 1 else _bucket_of(key, buckets) == k


def _bucket_of(key: list[pl.Expr], buckets: int) -> pl.Expr:
    return pl.struct(key).hash() % buckets


def _track_key() -> list[pl.Expr]:
    return [pl.col("method"), pl.col("run"), pl.col("track_id")]


def _aircraft_key() -> list[pl.Expr]:
    """(run, truth_id) in the types of :func:`_aircraft_epochs`: matched rows and ``observed``
    hash alike."""
    return [pl.col("run").cast(pl.UInt32), pl.col("truth_id").cast(pl.Int64)]


def _coverage_buckets(lf: pl.LazyFrame, observed: pl.DataFrame | pl.LazyFrame, epoch: pl.DataType,
                      methods: pl.DataFrame, buckets: int, scratch: Path | None = None) -> pl.DataFrame:
    """:func:`_coverage` of the matched rows ``lf`` with whole (run, aircraft) walked per bucket
    (the rows filed by bucket once in ``scratch``, if given)."""
    seen = _aircraft_epochs(observed.lazy(), epoch)
    tracked = lf.filter(pl.col("truth_id").is_not_null())
    by_aircraft = None
    if scratch is not None:
        # each row's bucket as the filter below makes it: hashed before ``run`` is cast
        src = tracked.with_columns(_bucket_of(_aircraft_key(), buckets).alias("__ab"))
        by_aircraft = [f.drop("__ab") for f in
                       file_buckets(_continuity_columns(src, "__ab"), pl.col("__ab"), buckets, scratch)]
    seen_by = None
    if scratch is not None:         # the aircraft seen, cut once too
        s = seen.with_columns(_bucket_of(_aircraft_key(), buckets).alias("__ab")).collect()
        seen_by = {k: f.drop("__ab") for (k,), f in s.partition_by("__ab", as_dict=True).items()}
        empty = s.drop("__ab").clear()
        del s
    counts = []
    for k in range(buckets):
        m = (by_aircraft[k].collect() if by_aircraft is not None else
             _continuity_columns(tracked.filter(_in_bucket(_aircraft_key(), buckets, k))).collect())
        aircraft = (seen_by.get(k, empty).unique() if seen_by is not None else
                    seen.filter(_in_bucket(_aircraft_key(), buckets, k)).unique().collect())
        counts.append(_coverage_counts(m, aircraft, methods))
        del m, aircraft
    return _coverage_table(pl.concat(counts))


@dataclass
class _Parts:
    """What :func:`picture_accuracy_buckets` keeps of the track buckets seen: small tables
    (``tables``: per method, segment, epoch and run at most), the per-lag sums of each
    consistency series set (``lags``: (prefix, method, segment) → :class:`_Lags`) and the scored
    samples with their row index."""

    rows: int = 0
    tables: dict[str, pl.DataFrame] = field(default_factory=dict)
    lags: dict[tuple[str, str, str], _Lags] = field(default_factory=dict)
    samples: list[pl.DataFrame] = field(default_factory=list)

    def fold(self, name: str, part: pl.DataFrame, keys: list[str]) -> None:
        """Add ``part`` (sums per ``keys``, ``__first`` a minimum; keys only: a set) to ``name``."""
        old = self.tables.get(name)
        both = part if old is None else pl.concat([old, part])
        aggs = [pl.col(c).min() if c == "__first" else pl.col(c).sum() for c in both.columns if c not in keys]
        self.tables[name] = both.group_by(keys).agg(aggs) if aggs else both.unique()

    def add_tracks(self, part: pl.DataFrame, cfg: AccuracyConfig) -> None:
        """The partial sums of one bucket of whole tracks (the columns :func:`picture_accuracy` reads)."""
        self.rows += part.height
        m = _continuity_columns(part)
        self.fold("tracks", _track_counts(m), ["method"])
        self.fold("track_runs", m.select("method", "run").unique(), ["method", "run"])
        del m
        scored = scored_rows(part, cfg)
        scored = scored.select(c for c in scored.columns if c in _KEEP or c == _ROW)
        self.samples.append(pl.concat([scored.select(_ROW), scored_samples(scored)], how="horizontal"))
        if scored.height:
            self.add_scored(scored)

    def add_scored(self, scored: pl.DataFrame) -> None:
        """The partial sums of a bucket's scored rows: (2.15), potential accuracy, consistency."""
        key = ["method", "eval_segment", "epoch", "run"]
        e2 = [pl.col(c).sum() for c in FUSION_METRICS.values()]
        self.fold("epochs", pl.concat([
            r.group_by(key).agg(*e2, pl.len().alias("n")).filter(pl.col("eval_segment").is_not_null())
            for r in (scored.with_columns(pl.lit("all").alias("eval_segment")),
                      scored.with_columns(pl.col("seg_class").alias("eval_segment")))]), key)
        pot = scored.select("method", "run", "seg_class", "sd_pos", _ROW).filter(pl.col("sd_pos").is_not_null())
        if pot.height:
            pot = _with_segments(pot)
            self.fold("potential", pot.group_by("method", "eval_segment").agg(
                pl.col("sd_pos").sum().alias("__sum"), pl.len().alias("__n"), pl.col(_ROW).min().alias("__first")),
                ["method", "eval_segment"])
            self.fold("potential_runs", pot.select("method", "eval_segment", "run").unique(),
                      ["method", "eval_segment", "run"])
        for prefix, (col, _dof) in _statistics(scored.columns).items():
            self.add_statistic(scored, prefix, col)

    def add_statistic(self, scored: pl.DataFrame, prefix: str, col: str) -> None:
        """Per-epoch sums and per-lag sums of one NEES/NIS statistic (:func:`consistency_metrics`)."""
        r = scored.select("method", "run", "epoch", "track_id", "seg_class", col).filter(
            pl.col(col).is_not_null() & pl.col(col).is_finite()).sort("method", "run", "track_id", "epoch")
        if r.is_empty():
            return
        both = _with_segments(r)
        self.fold(f"{prefix}:epochs", both.group_by("method", "eval_segment", "epoch").agg(
            pl.col(col).sum().alias("__sum"), pl.len().alias("__n")), ["method", "eval_segment", "epoch"])
        self.fold(f"{prefix}:runs", both.select("method", "eval_segment", "run").unique(),
                  ["method", "eval_segment", "run"])
        del both
        for method in r["method"].unique().to_list():
            m = r.filter(pl.col("method") == method)
            for seg in ["all", *m["seg_class"].drop_nulls().unique().to_list()]:
                g = m if seg == "all" else m.filter(pl.col("seg_class") == seg)
                lags = _Lags.of(g[col].to_numpy(), _series_codes(g, "track_id"))
                old = self.lags.get((prefix, method, seg))
                self.lags[(prefix, method, seg)] = lags if old is None else old + lags

    def finish(self, stage: str, cfg: AccuracyConfig, coverage: pl.DataFrame | None
               ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
        """:func:`picture_accuracy`'s three tables from the sums of every bucket."""
        t = self.tables
        accuracy, by_epoch = _empty_metrics(), pl.DataFrame(schema=BY_EPOCH_SCHEMA)
        if "epochs" in t:
            agg = t["epochs"].group_by("method", "eval_segment", "epoch").agg(
                *[pl.col(c).sum() for c in FUSION_METRICS.values()], pl.col("n").sum(), pl.len().alias("n_runs"))
            runs = t["epochs"].group_by("method", "eval_segment").agg(pl.col("run").n_unique().alias("n_runs"))
            accuracy = _accuracy_table(_pool_epochs(agg, ["method", "eval_segment"], cfg), runs, stage)
            whole = agg.filter(pl.col("eval_segment") == "all").drop("eval_segment")
            by_epoch = _by_epoch_table(_pool_epochs(whole, ["method"], cfg))
        out = [accuracy]
        if "potential" in t:
            out.append(_potential_table(self._potential(), stage))
        for prefix, (_col, dof) in _CONSISTENCY_ALL.items():
            if f"{prefix}:epochs" in t:
                out.append(self._statistic(prefix, dof, stage, cfg.band))
        out.append(_continuity_table(t["tracks"], t["track_runs"], coverage, stage))
        samples = pl.concat(self.samples).sort(_ROW).drop(_ROW)
        return _metrics_concat(out), by_epoch, samples

    def _potential(self) -> pl.DataFrame:
        """(method, eval_segment, value, n_runs) in :func:`_consistency`'s order of appearance:
        segment ``all`` first, then each group by its first row."""
        n_runs = self.tables["potential_runs"].group_by("method", "eval_segment").agg(
            pl.col("run").n_unique().alias("n_runs"))
        return (self.tables["potential"].join(n_runs, on=["method", "eval_segment"], how="left")
                .sort(pl.col("eval_segment") != "all", "__first")
                .select("method", "eval_segment", (pl.col("__sum") / pl.col("__n")).alias("value"), "n_runs"))

    def _statistic(self, prefix: str, dof: int, stage: str, band: float) -> pl.DataFrame:
        """:func:`consistency_metrics` of one statistic from its sums."""
        epochs = self.tables[f"{prefix}:epochs"]
        n_runs = {(m, s): n for m, s, n in self.tables[f"{prefix}:runs"].group_by("method", "eval_segment")
                  .agg(pl.col("run").n_unique()).iter_rows()}
        out = []
        for method, seg in sorted(k[1:] for k in self.lags if k[0] == prefix):
            lags = self.lags[(prefix, method, seg)]
            e = epochs.filter((pl.col("method") == method) & (pl.col("eval_segment") == seg))
            out += _consistency_dicts(stage, method, seg, prefix, dof, band, lags.total / lags.n,
                                      (e["__sum"] / e["__n"]).to_numpy(), e["__n"].to_numpy(), lags.n, lags.tau(),
                                      n_runs[(method, seg)])
        return pl.DataFrame(out, schema=TABLES["metrics"].required)


@dataclass(frozen=True)
class _Lags:
    """Sums over the pairs of rows at lag l = 0 … _MAX_LAG − 1 inside the series of a set of rows
    (:func:`integrated_autocorrelation`), about a centre c: ``s[l]`` = Σ (x_a − c)(x_b − c),
    ``a[l]`` = Σ (x_a − c) + (x_b − c), ``p[l]`` the number of pairs; ``n`` rows summing to
    ``total``. Moved to another centre exactly (Σ (y_a + d)(y_b + d) = s + d a + p d²), so the
    sums of parts of the rows (whole series each) add up to those of their union about its
    mean: τ without holding the rows, and without the cancellation of raw Σ x_a x_b."""

    n: int
    total: float
    centre: float
    s: NDArray[np.float64]
    a: NDArray[np.float64]
    p: NDArray[np.float64]

    @classmethod
    def of(cls, x: NDArray[np.float64], series: NDArray) -> _Lags:
        """The sums of rows ``x`` sorted along their ``series`` (codes), about their mean."""
        n, c = len(x), float(x.mean())
        y = x - c
        starts = np.flatnonzero(np.r_[True, series[1:] != series[:-1]])
        lengths = np.diff(np.r_[starts, n])
        first = np.repeat(starts, lengths)
        end = first + np.repeat(lengths, lengths)
        lag = np.arange(n) - first                  # each lag < its series' length, once a series
        cum = np.r_[0.0, np.cumsum(y)]
        # Σ y over the first and the last L − lag rows of a series: its pairs at that lag
        ends = cum[end - lag] - cum[first] + cum[end] - cum[first + lag]
        k = lag < _MAX_LAG
        p = np.bincount(lag[k], weights=(end - first - lag)[k], minlength=_MAX_LAG)
        a = np.bincount(lag[k], weights=ends[k], minlength=_MAX_LAG)
        s = _lag_products(y, starts, lengths)
        s[0] = float(np.dot(y, y))
        return cls(n, float(x.sum()), c, s, a, p)

    def moved(self, centre: float) -> _Lags:
        """The same sums about ``centre``."""
        d = self.centre - centre
        return _Lags(self.n, self.total, centre, self.s + d * self.a + d * d * self.p, self.a + 2 * d * self.p,
                     self.p)

    def __add__(self, other: _Lags) -> _Lags:
        n, total = self.n + other.n, self.total + other.total
        u, v = self.moved(total / n), other.moved(total / n)
        return _Lags(n, total, total / n, u.s + v.s, u.a + v.a, u.p + v.p)

    def tau(self) -> float:
        """:func:`integrated_autocorrelation` of the rows summed."""
        n = self.n
        if n < 3:
            return 1.0
        y = self.moved(self.total / n)
        g0 = float(y.s[0]) / n
        if not g0 > 0:
            return 1.0
        s = np.where(y.p > 0, y.s, 0.0)             # no pair at a lag: exactly 0, not FFT round-off
        return _geyer_tau(lambda lag: float(s[lag]) / (n * g0), n, _MAX_LAG)


def _lag_products(y: NDArray[np.float64], starts: NDArray, lengths: NDArray) -> NDArray[np.float64]:
    """Σ over the series (rows ``starts`` … + ``lengths``) of Σ_t y_t y_{t+l}, for every lag
    l < _MAX_LAG at once: each series' autocorrelation by FFT, zero-padded to twice the power of
    two above its length, the series of one such width in blocks. O(n log n): which lags τ needs
    is known only once every bucket is summed, and a lag by lag sum costs O(n) per lag."""
    out = np.zeros(_MAX_LAG)
    width = (1 << np.ceil(np.log2(lengths)).astype(np.int64)).astype(np.int64)
    for w in np.unique(width[lengths > 1]):        # a series of one row has no lag ≥ 1
        sel = np.flatnonzero(width == w)
        step = max(1, _FFT_CELLS // (2 * int(w)))
        for lo in range(0, len(sel), step):
            block = sel[lo:lo + step]
            k = min(int(w), _MAX_LAG)
            out[:k] += _autocorrelation(y, starts[block], lengths[block], int(w))[:k]
    return out


def _autocorrelation(y: NDArray[np.float64], starts: NDArray, lengths: NDArray, w: int) -> NDArray[np.float64]:
    """Σ over the given series (each at most ``w`` rows) of their autocorrelation at lags 0 … w − 1."""
    first = np.cumsum(lengths) - lengths
    pos = np.arange(int(lengths.sum())) - np.repeat(first, lengths)
    mat = np.zeros((len(lengths), 2 * w))
    mat[np.repeat(np.arange(len(lengths)), lengths), pos] = y[np.repeat(starts, lengths) + pos]
    f = np.fft.rfft(mat, axis=1)
    return np.fft.irfft(f.real ** 2 + f.imag ** 2, n=2 * w, axis=1)[:, :w].sum(axis=0)
