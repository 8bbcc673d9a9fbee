"""Which alerts the picture causes: each system picture's alert episodes and missed losses set
against those of the truth picture (the same conflict prediction on the true states,
:mod:`tertiary.evaluation.truth_picture`).

* An alert episode is **predictor-induced** when the truth picture alerts the same pair of
  aircraft (same run) at an overlapping time — within ``AlertConfig.merge_gap_s`` either side —,
  else **picture-induced** (also every episode without two distinct aircraft: the picture made
  the pair up). A better tracker can remove the latter only; the former need a better
  predictor (look-ahead, intent, thresholds).
* A missed loss of separation is **picture-induced** when the truth picture alerted it; else
  **under way** when it had begun by the time the later of its two aircraft was first observed
  (no alert can precede such a loss: the recording starts, or an aircraft enters coverage,
  inside it); else predictor-induced.
* **Valid** (Torres & McKay 2009): a nuisance, undetermined or false alert followed, within the look-ahead
  T^пор of its start, by a manoeuvre of either aircraft (:func:`manoeuvre_onsets`) — the alert
  may have been acted on.

Metrics (stage ``"safety"``, per system picture): :data:`ATTRIBUTION_METRICS`.
"""

from __future__ import annotations

import math

import numpy as np
import polars as pl

from safety.alerts.config import AlertConfig
from safety.alerts.episodes import metrics_long
from tertiary.core.units import US

__all__ = ["ATTRIBUTION_METRICS", "TRUTH_PICTURE", "attribute_alerts", "attribute_los", "attribution_metrics",
           "manoeuvre_onsets", "valid_alerts"]

#: the truth picture's name in ``method``
TRUTH_PICTURE = "truth"

ATTRIBUTION_METRICS = ("alerts_picture_induced", "alerts_predictor_induced", "genuine_alerts_picture_induced",
                       "nuisance_alerts_picture_induced", "nuisance_alerts_predictor_induced",
                       "false_alerts_picture_induced", "false_alerts_predictor_induced",
                       "undetermined_alerts_picture_induced", "undetermined_alerts_predictor_induced",
                       "missed_los_picture_induced", "missed_los_predictor_induced", "missed_los_under_way",
                       "valid_alerts")

_PAIR = ["run", "truth_a", "truth_b"]


def attribute_alerts(alerts: pl.DataFrame, cfg: AlertConfig = AlertConfig(), truth: str = TRUTH_PICTURE
                     ) -> pl.DataFrame:
    """``alerts`` with column ``induced``: ``"picture"`` / ``"predictor"`` for the system
    pictures' episodes, null for the truth picture's own (and for every row when the truth
    picture is not in ``alerts``)."""
    if truth not in set(alerts["method"].unique().to_list()):
        return alerts.with_columns(pl.lit(None, pl.String).alias("induced"))
    tol = pl.duration(microseconds=int(round(cfg.merge_gap_s * US)))
    ref = alerts.filter(pl.col("method") == truth).select(*_PAIR, pl.col("t_start").alias("__s"),
                                                          pl.col("t_end").alias("__e"))
    sys = alerts.with_row_index("__row")
    hit = (sys.filter((pl.col("method") != truth) & pl.col("truth_a").is_not_null())
           .select("__row", *_PAIR, "t_start", "t_end")
           .join(ref, on=_PAIR, how="inner")
           .filter((pl.col("__s") <= pl.col("t_end") + tol) & (pl.col("__e") >= pl.col("t_start") - tol))
           .select("__row").unique().with_columns(pl.lit(True).alias("__hit")))
    induced = (pl.when(pl.col("method") == truth).then(pl.lit(None, pl.String))
               .when(pl.col("__hit").fill_null(False)).then(pl.lit("predictor")).otherwise(pl.lit("picture")))
    return (sys.join(hit, on="__row", how="left").sort("__row")
            .with_columns(induced.alias("induced")).drop("__row", "__hit"))


def attribute_los(los: pl.DataFrame, truth: str = TRUTH_PICTURE, spans: pl.DataFrame | None = None
                  ) -> pl.DataFrame:
    """The LoS table (one row per loss and picture) with column ``induced`` for the system
    pictures' missed losses: ``"picture"`` when the truth picture alerted that loss, else
    ``"under_way"`` when the loss began no later than the later first observation of its two
    aircraft (``spans``: run, truth_id, first, one row or more per aircraft —
    :func:`tertiary.evaluation.truth_picture.observed_spans`),
    else ``"predictor"``; null for alerted losses and for the truth picture's rows."""
    ref = (los.filter(pl.col("method") == truth)
           .select(*_PAIR, "t_start", pl.col("alerted").alias("__ref_alerted")))
    out = los.join(ref, on=[*_PAIR, "t_start"], how="left", maintain_order="left")
    out = out.with_columns(_under_way(out, spans).alias("__under_way"))
    induced = (pl.when((pl.col("method") == truth) | pl.col("alerted") | pl.col("__ref_alerted").is_null())
               .then(pl.lit(None, pl.String))
               .when(pl.col("__ref_alerted")).then(pl.lit("picture"))
               .when(pl.col("__under_way")).then(pl.lit("under_way")).otherwise(pl.lit("predictor")))
    return out.with_columns(induced.alias("induced")).drop("__ref_alerted", "__under_way")


def _under_way(los: pl.DataFrame, spans: pl.DataFrame | None) -> pl.Series:
    """Per row of ``los``: whether the loss had begun when the later of its two aircraft was
    first observed (False without ``spans`` or for an aircraft never observed)."""
    if spans is None or not los.height:
        return pl.Series([False] * los.height, dtype=pl.Boolean)
    # an aircraft may have several observed spans: its first observation is the earliest's
    first = (spans.select(pl.col("run").cast(pl.UInt32), pl.col("truth_id").cast(pl.Int64),
                          pl.col("first").cast(los.schema["t_start"]))
             .group_by("run", "truth_id").agg(pl.col("first").min()))
    seen = los.select("run", "truth_a", "truth_b", "t_start").with_row_index("__r")
    for side in ("a", "b"):
        seen = seen.join(first.rename({"truth_id": f"truth_{side}", "first": f"__first_{side}"}),
                         on=["run", f"truth_{side}"], how="left")
    later = pl.when(pl.col("__first_a") > pl.col("__first_b")).then("__first_a").otherwise("__first_b")
    return seen.sort("__r").select((later >= pl.col("t_start")).fill_null(False)).to_series()


def manoeuvre_onsets(truth: pl.DataFrame, turn_dps: float = 0.5, climb_mps: float = 2.5, min_s: float = 10.0
                     ) -> pl.DataFrame:
    """(truth_id, t_us) of each aircraft's manoeuvre onsets in the truth: the start of every
    stretch of at least ``min_s`` in a new motion state — turning left / straight / right
    (track-angle rate beyond ``turn_dps``) × climbing / level / descending (vertical rate
    beyond ``climb_mps``; ``alt_rate_mps`` when the truth has it, else ``vz_mps``) — that
    follows a stretch in another state."""
    rate = "alt_rate_mps" if "alt_rate_mps" in truth.columns else "vz_mps"
    t = truth.select(pl.col("truth_id").cast(pl.Int64), pl.col("time").dt.epoch("us").alias("t_us"),
                     pl.arctan2("vx_mps", "vy_mps").alias("__hdg"), pl.col(rate).alias("__vr")).sort("truth_id",
                                                                                                       "t_us")
    dh = (pl.col("__hdg").diff().over("truth_id") + math.pi) % (2 * math.pi) - math.pi
    dt = pl.col("t_us").diff().over("truth_id") / US
    w = np.radians(turn_dps)
    t = t.with_columns((dh / dt).alias("__w"))
    state = (pl.when(pl.col("__w") > w).then(1).when(pl.col("__w") < -w).then(-1).otherwise(0) * 3
             + pl.when(pl.col("__vr") > climb_mps).then(1).when(pl.col("__vr") < -climb_mps).then(-1).otherwise(0))
    t = t.with_columns(state.fill_null(0).alias("__st"))
    t = t.with_columns((pl.col("__st") != pl.col("__st").shift().over("truth_id")).fill_null(True)
                       .cum_sum().over("truth_id").alias("__run"))
    runs = (t.group_by("truth_id", "__run").agg(pl.col("t_us").min().alias("t_us"), pl.col("t_us").max().alias("__end"),
                                               pl.col("__st").first().alias("__st"))
            .filter(pl.col("__end") - pl.col("t_us") >= int(min_s * US)).sort("truth_id", "t_us"))
    # a change of the kept stretches' state is an onset; the first stretch of an aircraft is not
    changed = (pl.col("__st") != pl.col("__st").shift().over("truth_id")) & pl.col("__st").shift().over(
        "truth_id").is_not_null()
    return runs.filter(changed).select("truth_id", "t_us")


def valid_alerts(alerts: pl.DataFrame, onsets: pl.DataFrame, cfg: AlertConfig = AlertConfig()) -> pl.DataFrame:
    """``alerts`` with column ``valid``: a nuisance, undetermined or false episode of two known aircraft with a
    manoeuvre onset of either within [t_start, t_start + T^пор] (Torres & McKay 2009); false
    for genuine episodes and unknown pairs."""
    look = int(round(cfg.conflict.t_thr_s * US))
    on = onsets.select(pl.col("truth_id").cast(pl.Int64), pl.col("t_us").alias("__m"))
    rows = alerts.with_row_index("__row").with_columns(pl.col("t_start").dt.epoch("us").alias("__t0"))
    cand = rows.filter(pl.col("classification").is_in(["nuisance", "undetermined", "false"])
                       & pl.col("truth_a").is_not_null())
    hits = [cand.join(on, left_on=side, right_on="truth_id", how="inner")
            .filter((pl.col("__m") >= pl.col("__t0")) & (pl.col("__m") <= pl.col("__t0") + look)).select("__row")
            for side in ("truth_a", "truth_b")]
    hit = pl.concat(hits).unique().with_columns(pl.lit(True).alias("valid"))
    return (rows.join(hit, on="__row", how="left").sort("__row")
            .with_columns(pl.col("valid").fill_null(False)).drop("__row", "__t0"))


def attribution_metrics(alerts: pl.DataFrame, los: pl.DataFrame, truth: str = TRUTH_PICTURE) -> pl.DataFrame:
    """:data:`ATTRIBUTION_METRICS` per system picture in the ``metrics`` schema (``alerts`` from
    :func:`attribute_alerts` (+ :func:`valid_alerts`), ``los`` from :func:`attribute_los`)."""
    a = alerts.filter(pl.col("method") != truth)
    if "valid" not in a.columns:
        a = a.with_columns(pl.lit(False).alias("valid"))
    cls, ind = pl.col("classification"), pl.col("induced")
    pic, pred = ind == "picture", ind == "predictor"
    per = a.group_by("method").agg(
        pic.sum().alias("alerts_picture_induced"), pred.sum().alias("alerts_predictor_induced"),
        (pic & (cls == "genuine")).sum().alias("genuine_alerts_picture_induced"),
        (pic & (cls == "nuisance")).sum().alias("nuisance_alerts_picture_induced"),
        (pred & (cls == "nuisance")).sum().alias("nuisance_alerts_predictor_induced"),
        (pic & (cls == "false")).sum().alias("false_alerts_picture_induced"),
        (pred & (cls == "false")).sum().alias("false_alerts_predictor_induced"),
        (pic & (cls == "undetermined")).sum().alias("undetermined_alerts_picture_induced"),
        (pred & (cls == "undetermined")).sum().alias("undetermined_alerts_predictor_induced"),
        pl.col("valid").sum().alias("valid_alerts"))
    lo = los.filter(pl.col("method") != truth).group_by("method").agg(
        (pl.col("induced") == "picture").sum().alias("missed_los_picture_induced"),
        (pl.col("induced") == "predictor").sum().alias("missed_los_predictor_induced"),
        (pl.col("induced") == "under_way").sum().alias("missed_los_under_way"))
    names = (pl.concat([a.select("method", "run"), los.filter(pl.col("method") != truth).select("method", "run")])
             .group_by("method").agg(pl.col("run").n_unique().alias("n_runs")))
    per = names.join(per, on="method", how="left").join(lo, on="method", how="left").with_columns(
        pl.col(list(ATTRIBUTION_METRICS)).cast(pl.Float64).fill_null(0.0))
    return metrics_long(per, ATTRIBUTION_METRICS)
