"""Radar health from the radars' own innovations (seed 003 §2.2, §4.3 and §6): windowed-NIS divergence alarm, innovation-based adaptive R (variants A and B)
and the share of reports failing the χ² NIS gate, per radar, as rows of the ``metrics`` table
(stage ``"radar_health"``, method = the radar id).

Input: the ``aligned`` rows (or the fusion input rows): ``run``, ``radar_id``,
``local_track_id``, ``res_range_m``, ``res_range_var_m2``, ``fresh`` and ``time`` (else
``epoch``). Only fresh rows count (each report once), with a finite range innovation ν and
variance S > 0; NIS = ν²/S (m = 1).

* **Windowed NIS** (seed 003 §6, "consistency monitoring"): per (run, radar), the mean NIS
  of the reports of the last ``window_s`` seconds, (t − window_s, t]. For a consistent filter the
  k NIS values of a window are χ²₁, so their mean is χ²_k/k; its bound is χ²_k(``alarm_prob``)/k
  for the k samples actually in the window.
* **Divergence alarm**: raised at the first sample at which the windowed NIS has stayed above
  its bound for ``hold_s`` seconds (the episode's first exceedance to now); one episode per
  unbroken exceedance.
* **Adaptive R** per (run, radar, local track) over its last ``r_window`` innovations, with
  H P⁻ Hᵀ = S − σ²_range (the radar's nominal R): variant A (seed 003 (4.16)–(4.24), the
  mean-removed Myers–Tapley form) R̂_A = 1/(N−1) Σ (ν_j − ν̄)² − (1/N) Σ (H P⁻ Hᵀ)_j (the printed
  (4.24) pulls a (N−1)/N in front of the current H P⁻ Hᵀ instead; with per-sample prior terms it
  is the mean, seed 003 §4.3 safeguard 2), and variant B R̂_B = (1/N) Σ (ν_j² − (H P⁻ Hᵀ)_j)
  (as :class:`tertiary.filters.adaptive_r.AdaptiveR`). Clamped to [``floor_frac``,
  ``ceil_frac``] × σ²_range, used from ``r_min_samples`` samples on. A absorbs an innovation
  bias, B turns it into variance (safeguard 5): their ratio flags a bias.
* **NIS gate flags**: share of reports with NIS above χ²₁(``gate_prob``) (9.0 at 0.9973).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from tertiary.core.distributions import chi2_ppf

__all__ = ["HealthConfig", "nis_samples", "windowed_nis", "adaptive_r", "radar_health", "METRICS"]

TRACK = ["run", "radar_id", "local_track_id"]
METRICS = ("samples", "nis_mean", "nis_window_max", "alarm_episodes", "alarm_share", "first_alarm_s",
           "gate_flag_share", "adaptive_r_ratio_a", "adaptive_r_ratio_b", "adaptive_sigma_range_a_m")


@dataclass(frozen=True)
class HealthConfig:
    """Windowed NIS (``window_s``, bound probability ``alarm_prob``, ``hold_s``), adaptive R
    (``r_window`` N, ``r_min_samples``, ``floor_frac``, ``ceil_frac``) and the gate (``gate_prob``)."""

    window_s: float = 60.0
    alarm_prob: float = 0.99
    hold_s: float = 30.0
    r_window: int = 30
    r_min_samples: int = 10
    floor_frac: float = 0.25
    ceil_frac: float = 1e4
    gate_prob: float = 0.9973002039367398

    def __post_init__(self) -> None:
        if not (self.window_s > 0 and self.hold_s >= 0):
            raise ValueError(f"window_s must be > 0 and hold_s >= 0, got {self.window_s}, {self.hold_s}")
        if not (0 < self.alarm_prob < 1 and 0 < self.gate_prob < 1):
            raise ValueError("alarm_prob and gate_prob must lie in (0, 1)")
        if not 2 <= self.r_min_samples <= self.r_window:
            raise ValueError(f"need 2 <= r_min_samples <= r_window, got {self.r_min_samples}, {self.r_window}")


def nis_samples(rows: pl.DataFrame) -> pl.DataFrame:
    """One row per fresh report with a usable range innovation: run, radar_id, local_track_id,
    time, res, s, nis = ν²/S; sorted by (run, radar_id, time)."""
    when = "time" if "time" in rows.columns else "epoch"
    run = pl.col("run").cast(pl.UInt32) if "run" in rows.columns else pl.lit(0, pl.UInt32).alias("run")
    res, s = pl.col("res_range_m").cast(pl.Float64), pl.col("res_range_var_m2").cast(pl.Float64)
    return (rows.filter(pl.col("fresh").fill_null(False) & res.is_finite() & s.is_finite() & (s > 0))
            .select(run, pl.col("radar_id").cast(pl.UInt32), pl.col("local_track_id"), pl.col(when).alias("time"),
                    res.alias("res"), s.alias("s"), (res * res / s).alias("nis"))
            .sort("run", "radar_id", "time", maintain_order=True))


def windowed_nis(samples: pl.DataFrame, cfg: HealthConfig = HealthConfig()) -> pl.DataFrame:
    """``samples`` (:func:`nis_samples`) with, per (run, radar): ``nis_window`` (mean over
    (t − window_s, t]), ``k`` (samples in it), ``bound`` = χ²_k(alarm_prob)/k, ``above`` and
    ``alarm`` (above its bound without a break for ≥ hold_s)."""
    win = f"{round(cfg.window_s * 1e6)}us"
    key = ["run", "radar_id"]
    out = samples.with_columns(
        pl.col("nis").rolling_mean_by("time", win).over(key).alias("nis_window"),
        pl.col("nis").is_finite().cast(pl.Float64).rolling_sum_by("time", win).over(key).alias("k"))
    k = out["k"].to_numpy()
    out = out.with_columns(pl.Series("bound", chi2_ppf(cfg.alarm_prob, k) / k))
    out = out.with_columns((pl.col("nis_window") > pl.col("bound")).alias("above"))
    episode = (pl.col("above") != pl.col("above").shift(1)).fill_null(True).cum_sum().over(key)
    held = (pl.col("time") - pl.col("time").first().over([*key, "__ep"])).dt.total_microseconds() * 1e-6
    return (out.with_columns(episode.alias("__ep"))
            .with_columns((pl.col("above") & (held >= cfg.hold_s)).alias("alarm")).drop("__ep"))


def adaptive_r(samples: pl.DataFrame, sigma_r2: pl.DataFrame, cfg: HealthConfig = HealthConfig()) -> pl.DataFrame:
    """``samples`` with ``r_a`` and ``r_b`` (m²): the variant A and B estimates of the range
    noise variance from the track's last ``r_window`` innovations (null before
    ``r_min_samples``), clamped to [floor_frac, ceil_frac] × σ²_range; and ``sigma_r2``.
    ``sigma_r2``: radar_id, sigma_r2 (the nominal range variance of each radar)."""
    n, m = cfg.r_window, cfg.r_min_samples
    j = samples.join(sigma_r2.select(pl.col("radar_id").cast(pl.UInt32), "sigma_r2"), on="radar_id", how="left",
                     maintain_order="left").sort([*TRACK, "time"], maintain_order=True)
    hph = pl.col("s") - pl.col("sigma_r2")
    over = lambda e: e.over(TRACK)  # noqa: E731
    r_a = over(pl.col("res").rolling_var(n, min_samples=m, ddof=1)) - over(hph.rolling_mean(n, min_samples=m))
    r_b = over((pl.col("res") ** 2 - hph).rolling_mean(n, min_samples=m))
    lo, hi = cfg.floor_frac * pl.col("sigma_r2"), cfg.ceil_frac * pl.col("sigma_r2")
    return j.with_columns(r_a.clip(lo, hi).alias("r_a"), r_b.clip(lo, hi).alias("r_b"))


def radar_health(rows: pl.DataFrame, radars: pl.DataFrame, cfg: HealthConfig = HealthConfig()) -> pl.DataFrame:
    """Per radar, rows for the ``metrics`` table (stage "radar_health", method = radar id,
    segment "all"): :data:`METRICS` — samples, mean NIS, largest windowed NIS, alarm episodes
    (summed over runs), share of samples in alarm, first alarm (s after the radar's first sample,
    earliest over runs; NaN without one), gate-flag share, the median R̂_A/σ²_r and R̂_B/σ²_r
    over the samples that have them, and √(median R̂_A)."""
    sig = radars.select(pl.col("radar_id").cast(pl.UInt32), (pl.col("sigma_range_m") ** 2).alias("sigma_r2"))
    s = windowed_nis(nis_samples(rows), cfg)
    s = adaptive_r(s, sig, cfg)
    gate = chi2_ppf(cfg.gate_prob, 1)
    key = ["run", "radar_id"]
    t_rel = (pl.col("time") - pl.col("time").min().over(key)).dt.total_microseconds() * 1e-6
    new_alarm = pl.col("alarm") & ~pl.col("alarm").shift(1).over(key).fill_null(False)
    per_run = (s.with_columns(t_rel.alias("__t"), new_alarm.alias("__new"))
               .group_by(key).agg(
                   pl.len().alias("samples"), pl.col("nis").sum().alias("__nis_sum"),
                   pl.col("nis_window").max().alias("nis_window_max"),
                   pl.col("__new").sum().alias("alarm_episodes"), pl.col("alarm").sum().alias("__alarm_n"),
                   pl.col("__t").filter("alarm").min().alias("first_alarm_s"),
                   (pl.col("nis") > gate).sum().alias("__gate_n"),
                   (pl.col("r_a") / pl.col("sigma_r2")).alias("__ra"), (pl.col("r_b") / pl.col("sigma_r2")).alias("__rb"),
                   pl.col("sigma_r2").first()))
    agg = per_run.group_by("radar_id").agg(
        pl.col("samples").sum(), (pl.col("__nis_sum").sum() / pl.col("samples").sum()).alias("nis_mean"),
        pl.col("nis_window_max").max(), pl.col("alarm_episodes").sum().cast(pl.Float64),
        (pl.col("__alarm_n").sum() / pl.col("samples").sum()).alias("alarm_share"),
        pl.col("first_alarm_s").min(), (pl.col("__gate_n").sum() / pl.col("samples").sum()).alias("gate_flag_share"),
        pl.col("__ra").list.explode(keep_nulls=False, empty_as_null=False).median().alias("adaptive_r_ratio_a"),
        pl.col("__rb").list.explode(keep_nulls=False, empty_as_null=False).median().alias("adaptive_r_ratio_b"),
        pl.col("sigma_r2").first(), pl.col("run").n_unique().alias("n_runs"),
    ).with_columns((pl.col("adaptive_r_ratio_a") * pl.col("sigma_r2")).sqrt().alias("adaptive_sigma_range_a_m"))
    return (agg.unpivot(index=["radar_id", "n_runs"], on=list(METRICS), variable_name="metric", value_name="value")
            .select(pl.lit("radar_health").alias("stage"), pl.col("radar_id").cast(pl.String).alias("method"),
                    "metric", pl.lit("all").alias("segment"), pl.col("value").cast(pl.Float64).fill_null(np.nan),
                    pl.col("n_runs").cast(pl.UInt32))
            .sort("method", "metric"))
