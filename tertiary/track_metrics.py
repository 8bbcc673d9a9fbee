"""Evaluation of the secondary tracker against truth (metrics stage ``tracker``).

Truth of a track
----------------
A track row updated with a plot takes the truth of that plot's fused target at that epoch —
:func:`tertiary.evaluate.target_truth` (the majority truth of the reports associated with the
target), joined on (run, epoch, plot_target_id). A coasting row carries the truth of the
track's most recent update (null if that plot was clutter).

Metrics (metrics schema; stage ``tracker``; method ``"<fusion method>+<filter>"``)
---------------------------------------------------------------------------------
Scored rows are the track rows with a truth, inside the aircraft's truth span, at least
``skip_first_s`` after the track's first (confirmation) epoch — the same conventions as
:mod:`tertiary.evaluate` (truth interpolated to the epoch; segments ``all``,
``straight`` ← straight|climb|descent, ``turn``; a segment without samples is omitted):

* ``rmse_pos_m``, ``rmse_horizontal_m``, ``rmse_height_m``, ``rmse_range_m``, ``rmse_vel_mps``:
  real accuracy (3-D, east-north, vertical — the height error from the tracks' ``alt_m``
  against truth ``alt_m`` when both carry it, else Δz; see :mod:`tertiary.evaluate`), RMSE = sqrt(mean_k σ²(k)),
  σ²(k) = Σ_j e_j(k)² / (N_k − 1) over the scored rows of epoch k ((2.15)/(4.84)).
* ``potential_pos_m``: mean over scored rows of sqrt(P_xx + P_yy + P_zz) (potential accuracy
  √diag P, §2.2.1, as a 3-D position figure).
* ``nees_*``: position NEES Σ_i e_i²/P_ii (i = x, y, z; ``cov_diag``, so correlations are
  ignored — Δpᵀ P_pp⁻¹ Δp from a full ``cov`` column when the tracks carry one), 3 degrees of
  freedom: ``nees_mean``, the Monte-Carlo ``nees_in_band_frac`` (per-epoch mean over the N_k
  runs × tracks vs χ²(3N_k)/N_k), ``nees_band_lo``/``_hi`` (band of the mean from the
  effective sample size) and ``nees_n_eff`` — :func:`tertiary.evaluate.consistency_metrics`.
* ``nis_*``: the same for the NIS of the rows updated with a plot (3 degrees of freedom).

Per (fusion, filter), segment ``all``:

* ``completeness``: the fraction of truth-aircraft-epochs covered by a confirmed (or
  coasting) track with that truth. The truth-aircraft-epochs are the (run, epoch, truth_id)
  of the fused picture: every non-null target truth of the associations (the aircraft was
  observed then).
* ``breaks``: walking each (run, truth_id)'s truth-aircraft-epochs in time order with its
  covering track (the oldest = smallest track_id if several cover it), a break is a covered
  epoch whose previous covered epoch had another track id, or that follows one or more
  uncovered epochs (coverage stopped and restarted; counted once even if the id changed too).
  Uncovered epochs before the first coverage (initiation) are not breaks.
* ``swaps``: over each track's rows in time order, ignoring rows without truth, the number of
  times the truth changes; summed over tracks.
* ``spurious_tracks``: confirmed tracks (run, track_id) without a truth at every row.
* ``tracks``: the number of confirmed tracks (run, track_id).

``n_runs`` is the number of runs in the tracks of that (fusion, filter).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import polars as pl

from tertiary.evaluate import (EvaluateConfig, accuracy_from_matched, add_nees, chi2_band, consistency_metrics, error_columns,
                               scored_samples, target_truth, truth_at)
from tertiary.schema import TABLES, TIME

__all__ = ["TrackMetricsConfig", "track_truth", "match_tracks", "tracker_metrics", "tracker_evaluation",
           "chi2_band", "TRACKER_METRICS"]

STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
_TRACK = ["label", "run", "track_id"]

#: metric names in output order
TRACKER_METRICS = ("rmse_pos_m", "rmse_horizontal_m", "rmse_height_m", "rmse_range_m", "rmse_vel_mps", "potential_pos_m",
                   "nees_mean", "nees_in_band_frac", "nees_band_lo", "nees_band_hi", "nees_n_eff",
                   "nis_mean", "nis_in_band_frac", "nis_band_lo", "nis_band_hi", "nis_n_eff",
                   "completeness", "breaks", "swaps", "spurious_tracks", "tracks")
#: degrees of freedom of the tracker's NIS: its measurement is the fused 3-D position
NIS_DOF = 3
_ACCURACY = ("rmse_pos_m", "rmse_horizontal_m", "rmse_height_m", "rmse_range_m", "rmse_vel_mps")


@dataclass(frozen=True)
class TrackMetricsConfig:
    """Options: the transient skipped after a track's first epoch, the RMSE denominator
    (``"n-1"`` as (2.15) or ``"n"``), the χ² band probability and the stage label."""

    skip_first_s: float = 20.0
    denominator: Literal["n-1", "n"] = "n-1"
    band: float = 0.95
    stage: str = "tracker"

    def __post_init__(self) -> None:
        if self.denominator not in ("n-1", "n"):
            raise ValueError(f"denominator must be 'n-1' or 'n', got {self.denominator!r}")
        if self.skip_first_s < 0:
            raise ValueError(f"skip_first_s must be >= 0, got {self.skip_first_s}")
        if not 0 < self.band < 1:
            raise ValueError(f"band must be in (0, 1), got {self.band}")


def _labelled(tracks: pl.DataFrame) -> pl.DataFrame:
    return tracks.with_columns(
        pl.col("epoch").cast(TIME),
        pl.format("{}+{}", pl.col("method"), pl.col("filter")).alias("label"))


def track_truth(tracks: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame) -> pl.DataFrame:
    """``tracks`` with ``label`` ("<method>+<filter>") and ``truth_id``: the truth of the fused
    target a row was updated with, carried over the coasting rows that follow."""
    return _track_truth(tracks, _target_truth(associations, report_truth))


def _target_truth(associations: pl.DataFrame, report_truth: pl.DataFrame) -> pl.DataFrame:
    return target_truth(associations.with_columns(pl.col("epoch").cast(TIME)), report_truth)


def _track_truth(tracks: pl.DataFrame, tt: pl.DataFrame) -> pl.DataFrame:
    """:func:`track_truth` from the target truth ``tt`` (:func:`_target_truth`)."""
    t = _labelled(tracks).sort(["label", "run", "track_id", "epoch"])
    tt = tt.select(pl.col("run").cast(t.schema["run"]), "epoch",
                   pl.col("target_id").cast(pl.UInt64).alias("plot_target_id"),
                   pl.col("truth_id").alias("__plot_truth"))
    updated = pl.col("plot_target_id").is_not_null()
    j = t.join(tt, on=["run", "epoch", "plot_target_id"], how="left", maintain_order="left")
    seg = updated.cast(pl.Int64).cum_sum().over(_TRACK)
    return (j.with_columns(seg.alias("__seg"))
            .with_columns(pl.col("__plot_truth").first().over(_TRACK + ["__seg"]).alias("truth_id"))
            .drop("__plot_truth", "__seg"))


def match_tracks(tracks: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
                 truth: pl.DataFrame, cfg: TrackMetricsConfig = TrackMetricsConfig()) -> pl.DataFrame:
    """Scored track rows: :func:`track_truth` rows with a truth, inside its span and after the
    transient, plus ``segment``, ``seg_class``, ``true_<state>``, the squared errors of
    :func:`tertiary.evaluate.match_truth` (``e2_x`` … ``e2_vel``), ``nees_pos`` and ``sd_pos``
    (sqrt of the position variance sum)."""
    return _match_labelled(track_truth(tracks, associations, report_truth), truth, cfg)


def _match_labelled(t: pl.DataFrame, truth: pl.DataFrame, cfg: TrackMetricsConfig) -> pl.DataFrame:
    """:func:`match_tracks` from the :func:`track_truth` rows ``t``."""
    if cfg.skip_first_s > 0:
        first = pl.col("epoch").min().over(_TRACK)
        t = t.filter((pl.col("epoch") - first).dt.total_microseconds() >= round(cfg.skip_first_s * 1e6))
    t = t.filter(pl.col("truth_id").is_not_null())
    keep = ["label", "run", "epoch", "track_id", "status", "truth_id", *STATE, "cov_diag", "nis"]
    keep += ["cov"] if "cov" in t.columns else []
    keep += ["alt_m"] if "alt_m" in t.columns else []
    m = truth_at(t.select(keep), truth)
    d = {c: pl.col(c) - pl.col(f"true_{c}") for c in STATE}
    var = [pl.col("cov_diag").arr.get(i) for i in range(3)]
    m = m.with_columns(
        *error_columns("true_alt_m" in m.columns),
        (d["x_m"] ** 2 / var[0] + d["y_m"] ** 2 / var[1] + d["z_m"] ** 2 / var[2]).alias("nees_pos"),
        (var[0] + var[1] + var[2]).sqrt().alias("sd_pos"),
    )
    if "cov" in m.columns:          # a full covariance: the proper NEES Δpᵀ P_pp⁻¹ Δp
        diag = m["nees_pos"]        # rows without one (a filter that gives only the diagonal) keep it
        m = add_nees(m).drop("nees", "cov")
        m = m.with_columns(pl.col("nees_pos").fill_nan(None).fill_null(diag))
    return m


def _rows(stage: str, label: str, metric: str, segment: str, value: float, n_runs: int) -> dict:
    return {"stage": stage, "method": label, "metric": metric, "segment": segment,
            "value": float(value), "n_runs": int(n_runs)}


def _consistency(matched: pl.DataFrame, cfg: TrackMetricsConfig, n_runs: dict[str, int]) -> list[dict]:
    """``potential_pos_m`` per label and segment, then the NEES / NIS rows of
    :func:`tertiary.evaluate.consistency_metrics` (Monte-Carlo in-band fraction, mean and its
    effective-sample-size band)."""
    out: list[dict] = []
    if matched.is_empty():
        return out
    rows = pl.concat([matched.with_columns(pl.lit("all").alias("eval_segment")),
                      matched.filter(pl.col("seg_class").is_not_null())
                      .with_columns(pl.col("seg_class").alias("eval_segment"))])
    agg = rows.group_by(["label", "eval_segment"]).agg(pl.col("sd_pos").mean().alias("potential_pos_m"))
    for r in agg.iter_rows(named=True):
        out.append(_rows(cfg.stage, r["label"], "potential_pos_m", r["eval_segment"], r["potential_pos_m"],
                         n_runs.get(r["label"], 0)))
    m = matched.rename({"label": "method"})
    for frame in (consistency_metrics(m, "nees_pos", 3, "nees", cfg.stage, "track_id", cfg.band),
                  consistency_metrics(m, "nis", NIS_DOF, "nis", cfg.stage, "track_id", cfg.band)):
        out += [dict(r, n_runs=int(r["n_runs"])) for r in frame.iter_rows(named=True)]
    return out


def _continuity(labelled: pl.DataFrame, tt: pl.DataFrame, cfg: TrackMetricsConfig,
                n_runs: dict[str, int]) -> list[dict]:
    """completeness, breaks, swaps, spurious_tracks, tracks per label (segment ``all``); ``tt``
    is the target truth (:func:`_target_truth`)."""
    out: list[dict] = []
    # only the key columns: the per-label filters below would otherwise copy the wide rows
    labelled = labelled.select("label", "run", "epoch", "track_id", "truth_id")
    run_t = labelled.schema["run"]
    aircraft = (tt.filter(pl.col("truth_id").is_not_null())
                .select(pl.col("run").cast(run_t), "epoch", "truth_id").unique())
    cover = (labelled.filter(pl.col("truth_id").is_not_null())
             .group_by(["label", "run", "epoch", "truth_id"]).agg(pl.col("track_id").min().alias("cover_id")))
    for lab in sorted(n_runs):
        tr = labelled.filter(pl.col("label") == lab)
        nr = n_runs[lab]
        walk = (aircraft.join(cover.filter(pl.col("label") == lab).drop("label"),
                              on=["run", "epoch", "truth_id"], how="left")
                .sort(["run", "truth_id", "epoch"])
                .with_columns(pl.int_range(pl.len()).over(["run", "truth_id"]).alias("__k")))
        completeness = (walk["cover_id"].is_not_null().mean() if walk.height else float("nan"))
        cov = walk.filter(pl.col("cover_id").is_not_null())
        prev_k = pl.col("__k").shift(1).over(["run", "truth_id"])
        prev_id = pl.col("cover_id").shift(1).over(["run", "truth_id"])
        breaks = cov.select((prev_k.is_not_null() & ((pl.col("__k") - prev_k > 1) | (pl.col("cover_id") != prev_id)))
                            .sum()).item() if cov.height else 0
        seq = tr.filter(pl.col("truth_id").is_not_null()).sort(["run", "track_id", "epoch"])
        prev_t = pl.col("truth_id").shift(1).over(["run", "track_id"])
        swaps = seq.select((prev_t.is_not_null() & (pl.col("truth_id") != prev_t)).sum()).item() if seq.height else 0
        per_track = tr.group_by(["run", "track_id"]).agg(pl.col("truth_id").is_null().all().alias("spurious"))
        out += [_rows(cfg.stage, lab, "completeness", "all", completeness, nr),
                _rows(cfg.stage, lab, "breaks", "all", breaks, nr),
                _rows(cfg.stage, lab, "swaps", "all", swaps, nr),
                _rows(cfg.stage, lab, "spurious_tracks", "all", per_track["spurious"].sum(), nr),
                _rows(cfg.stage, lab, "tracks", "all", per_track.height, nr)]
    return out


def tracker_metrics(tracks: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
                    truth: pl.DataFrame, cfg: TrackMetricsConfig = TrackMetricsConfig()) -> pl.DataFrame:
    """All tracker metrics (see the module docstring) in the ``metrics`` table's dtypes, one
    block per "<fusion>+<filter>" of ``tracks``, sorted by method, segment and metric order."""
    return tracker_evaluation(tracks, associations, report_truth, truth, cfg)[0]


def tracker_evaluation(tracks: pl.DataFrame, associations: pl.DataFrame, report_truth: pl.DataFrame,
                       truth: pl.DataFrame, cfg: TrackMetricsConfig = TrackMetricsConfig()
                       ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """:func:`tracker_metrics` and the scored samples (method = "<fusion>+<filter>", run, epoch,
    truth_id, seg_class; :func:`tertiary.evaluate.scored_samples`) that a bound is pooled over."""
    spec = TABLES["metrics"].required
    empty = pl.DataFrame(schema={"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64,
                                 "seg_class": pl.String})
    if tracks.is_empty():
        return pl.DataFrame(schema=spec), empty
    # the target truth and the labelled tracks are shared by every metric (computed once)
    tt = _target_truth(associations, report_truth)
    labelled = _track_truth(tracks, tt)
    n_runs = dict(labelled.group_by("label").agg(pl.col("run").n_unique()).iter_rows())
    matched = _match_labelled(labelled, truth, cfg)
    ecfg = EvaluateConfig(skip_first_s=0.0, denominator=cfg.denominator, stage=cfg.stage)
    acc = accuracy_from_matched(matched.rename({"label": "method"}), ecfg) if matched.height else None
    parts = []
    if acc is not None and acc.height:
        parts.append(acc.filter(pl.col("metric").is_in(list(_ACCURACY)))
                     .with_columns(pl.col("n_runs").cast(pl.Int64)).select(list(spec)))
    extra = _consistency(matched, cfg, n_runs) + _continuity(labelled, tt, cfg, n_runs)
    if extra:
        parts.append(pl.DataFrame(extra, schema={k: (pl.Int64 if k == "n_runs" else v) for k, v in spec.items()}))
    scored = scored_samples(matched.rename({"label": "method"})) if matched.height else empty
    if not parts:
        return pl.DataFrame(schema=spec), scored
    out = pl.concat([p.cast({"n_runs": pl.Int64}) for p in parts], how="vertical")
    seg_order = pl.col("segment").replace_strict({"all": 0, "straight": 1, "turn": 2}, default=3, return_dtype=pl.Int8)
    met_order = pl.col("metric").replace_strict({m: i for i, m in enumerate(TRACKER_METRICS)}, default=99,
                                                return_dtype=pl.Int8)
    return (out.sort([pl.col("method"), seg_order, met_order]).select([pl.col(c).cast(t) for c, t in spec.items()]),
            scored)
