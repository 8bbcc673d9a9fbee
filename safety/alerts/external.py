"""Another system's alert list (CAT004 STCA, :func:`tertiary.io.asterix.external_alerts`) scored
like the pictures' alerts.

Identification — :func:`identify_aircraft`
---------------------------------
An external alert names its two aircraft by the alerting system's track numbers and, when it
sent them, their identities. Each aircraft is the truth aircraft whose identity equals the
alert's and whose samples span a time inside the alert episode [t_start, t_end], tried in
this order:

1. ``mode_s_ident`` = the truth's ``icao24`` (24-bit address, hex, case-insensitive);
2. ``callsign`` (else ``mode_s_ident``, CAT004's downlinked identification) = the truth's
   ``callsign`` (blanks removed, case-insensitive, first 7 characters: CAT004 carries 7);
3. ``mode_3a`` = the truth's ``mode_3a`` (or ``squawk``), four octal digits.

A code is reused, by another aircraft later or by several at once (conspicuity codes): an
identity held by more than one truth aircraft alive during the episode identifies none, and
the next item is tried. An alert without two distinct identified aircraft keeps
``truth_a``/``truth_b`` null: it can only be false, and is counted (``unidentified_alerts``).

Scoring — :func:`score_external`
--------------------------------
The rules of :mod:`safety.alerts.episodes` on the same truth intervals: episodes of one pair
of aircraft (of one id pair when unidentified) that overlap or are at most ``merge_gap_s``
apart are one episode (each merged gap counts as flicker); the link window reaches
``link_s`` after the end or the closest approach the first message predicted (TCA, at most
``max_link_s`` ahead); genuine / nuisance / false, warning time, and every loss of separation
in the scored span alerted or missed. The scored span (``picture_hours``) is the truth's span
of each run the list names (intersected with ``recording`` when given); episodes outside it
are not scored. Picture- or predictor-induced does not apply to another system: ``induced``
is null.
"""

from __future__ import annotations

from datetime import datetime

import polars as pl

from safety.alerts.config import AlertConfig
from safety.alerts.episodes import (ALERT_METRICS, ALERTS_SCHEMA, LOS_SCHEMA, classify_episodes, los_table,
                                    metrics_long, observed_until, per_picture)
from safety.alerts.separation import epoch_micros, to_time, truth_ends, truth_intervals
from tertiary.contract import TABLES, TIME
from tertiary.core import geo
from tertiary.core.units import US

__all__ = ["EXTERNAL_PREFIX", "IDENTITY_ORDER", "EXTERNAL_METRICS", "identify_aircraft", "score_external"]

#: the ``method`` of an external alert list starts with this
EXTERNAL_PREFIX = "external:"

#: (alert column stem(s), truth column(s), normalisation) in the order tried
IDENTITY_ORDER: tuple[tuple[tuple[str, ...], tuple[str, ...], str], ...] = (
    (("mode_s_ident",), ("icao24",), "address"),
    (("callsign", "mode_s_ident"), ("callsign",), "callsign"),
    (("mode_3a",), ("mode_3a", "squawk"), "code"),
)

#: the pictures' metrics, and the alerts without two identified aircraft
EXTERNAL_METRICS = (*ALERT_METRICS, "unidentified_alerts")

_EXTRA = {c: t for c, t in TABLES["alerts"].optional.items() if c not in ("induced", "valid")}


def _norm(e: pl.Expr, how: str) -> pl.Expr:
    """An identity compared as text: hex address lower case, callsign without blanks upper case
    cut to 7 characters, code as four digits; empty → null."""
    s = e.cast(pl.String).str.strip_chars()
    if how == "address":
        s = s.str.to_lowercase()
    elif how == "callsign":
        s = s.str.replace_all(" ", "", literal=True).str.to_uppercase().str.slice(0, 7)
    else:
        s = s.str.zfill(4)
    return pl.when(s.str.len_chars() > 0).then(s)


def _spans(truth: pl.LazyFrame, cols: tuple[str, ...], how: str, by_run: bool) -> pl.LazyFrame | None:
    """([run,] __v, truth_id, __t0, __t1): the time each truth aircraft held identity __v."""
    have = truth.collect_schema().names()
    col = next((c for c in cols if c in have), None)
    if col is None:
        return None
    run = [pl.col("run").cast(pl.UInt32)] if by_run else []
    return (truth.select(*run, pl.col("truth_id").cast(pl.Int64), epoch_micros("time").alias("__t"),
                         _norm(pl.col(col), how).alias("__v"))
            .drop_nulls("__v").group_by(*(["run"] if by_run else []), "__v", "truth_id")
            .agg(pl.col("__t").min().alias("__t0"), pl.col("__t").max().alias("__t1")))


def _side(rows: pl.DataFrame, spans: list[tuple[tuple[str, ...], str, pl.DataFrame | None]], side: str,
          by_run: bool) -> pl.Series:
    """The truth aircraft of one side (``a`` or ``b``) of each row, null when none is unique."""
    found = pl.Series(f"truth_{side}", [None] * rows.height, pl.Int64)
    on = ["run", "__v"] if by_run else ["__v"]
    for stems, how, sp in spans:
        names = [f"{s}_{side}" for s in stems if f"{s}_{side}" in rows.columns]
        if sp is None or not names:
            continue
        q = rows.select("__row", "run", "__s", "__e", pl.coalesce(*(_norm(pl.col(n), how) for n in names))
                        .alias("__v")).drop_nulls("__v")
        alive = (pl.col("__t0") <= pl.col("__e")) & (pl.col("__t1") >= pl.col("__s"))
        hit = (q.join(sp, on=on, how="inner").filter(alive)
               .group_by("__row").agg(pl.col("truth_id").unique().alias("__ids"))
               .filter(pl.col("__ids").list.len() == 1).select("__row", pl.col("__ids").list.first().alias("__t")))
        got = rows.select("__row").join(hit, on="__row", how="left", maintain_order="left")["__t"]
        found = found.fill_null(got)
    return found


def identify_aircraft(alerts: pl.DataFrame, truth: pl.DataFrame | pl.LazyFrame) -> pl.DataFrame:
    """``alerts`` with ``truth_a`` < ``truth_b`` the two aircraft of each alert (module
    docstring), both null unless two distinct aircraft are identified."""
    lf = truth.lazy()
    by_run = "run" in lf.collect_schema().names()
    found = [(stems, how, _spans(lf, cols, how, by_run)) for stems, cols, how in IDENTITY_ORDER]
    spans = [(stems, how, None if sp is None else sp.collect()) for stems, how, sp in found]
    rows = alerts.with_row_index("__row").with_columns(
        pl.col("run").cast(pl.UInt32), epoch_micros("t_start").alias("__s"), epoch_micros("t_end").alias("__e"))
    a, b = _side(rows, spans, "a", by_run), _side(rows, spans, "b", by_run)
    ok = pl.col("__a").is_not_null() & pl.col("__b").is_not_null() & (pl.col("__a") != pl.col("__b"))
    return alerts.with_columns(a.alias("__a"), b.alias("__b")).with_columns(
        pl.when(ok).then(pl.min_horizontal("__a", "__b")).cast(pl.Int64).alias("truth_a"),
        pl.when(ok).then(pl.max_horizontal("__a", "__b")).cast(pl.Int64).alias("truth_b")).drop("__a", "__b")


def _span_grid(alerts: pl.DataFrame, truth: pl.LazyFrame, recording: tuple[datetime, datetime] | None
               ) -> pl.DataFrame:
    """(run, method, t_us): the first and last instant scored of each run and list."""
    has_run = "run" in truth.collect_schema().names()
    t = epoch_micros("time")
    ends = (truth.group_by(pl.col("run").cast(pl.UInt32)) if has_run else truth.select(pl.lit(0, pl.UInt32)
            .alias("run"), pl.col("time")).group_by("run")).agg(t.min().alias("__0"), t.max().alias("__1")).collect()
    if recording is not None:
        r0, r1 = (int(pl.Series([v]).cast(TIME).dt.epoch("us")[0]) for v in recording)
        ends = ends.with_columns(pl.col("__0").clip(lower_bound=r0), pl.col("__1").clip(upper_bound=r1))
    lists = alerts.select(pl.col("run").cast(pl.UInt32), "method").unique()
    if not has_run:
        ends = ends.drop("run")
    g = lists.join(ends, on="run", how="inner") if has_run else lists.join(ends, how="cross")
    g = g.filter(pl.col("__1") >= pl.col("__0"))
    return pl.concat([g.select("run", "method", pl.col(c).alias("t_us")) for c in ("__0", "__1")]).sort(
        "run", "method", "t_us")


def _episodes(alerts: pl.DataFrame, grid: pl.DataFrame, cfg: AlertConfig) -> pl.DataFrame:
    """The identified alerts inside the scored span as episodes of the pictures' scoring
    (``__ep``, ``kind``, t0, t1, t_cpa µs): one pair's episodes ≤ ``merge_gap_s`` apart merged."""
    span = grid.group_by("run", "method").agg(pl.col("t_us").min().alias("__g0"), pl.col("t_us").max().alias("__g1"))
    known = pl.col("truth_a").is_not_null()
    reach = int(round(cfg.cpa_reach * US))
    tca = (pl.col("t_min_first_s").fill_nan(None).fill_null(0.0).clip(0.0) * US).round().cast(pl.Int64)
    a = (alerts.with_columns(epoch_micros("t_start").alias("t0"), epoch_micros("t_end").alias("t1"))
         .join(span, on=["run", "method"], how="inner")
         .filter((pl.col("t1") >= pl.col("__g0")) & (pl.col("t0") <= pl.col("__g1")))
         .with_columns(pl.when(known).then(0).otherwise(1).cast(pl.UInt8).alias("kind"),
                       pl.coalesce("truth_a", pl.col("id_a").cast(pl.Int64)).alias("ka"),
                       pl.coalesce("truth_b", pl.col("id_b").cast(pl.Int64)).alias("kb"),
                       pl.max_horizontal(pl.col("t0") + tca.clip(upper_bound=reach), "t1").alias("t_cpa"))
         .sort("run", "method", "kind", "ka", "kb", "t0"))
    key = ["run", "method", "kind", "ka", "kb"]
    prev_end = pl.col("t1").cum_max().shift(1).over(key)
    gap = int(round(cfg.merge_gap_s * US))
    a = a.with_columns((prev_end.is_null() | (pl.col("t0") > prev_end + gap)).cum_sum().cast(pl.Int64).alias("__ep"))
    extra = [pl.col(c).first() for c in _EXTRA if c in a.columns]
    return a.group_by("__ep", maintain_order=True).agg(
        *(pl.col(c).first() for c in (*key, "id_a", "id_b", "truth_a", "truth_b", "t_min_first_s")),
        pl.col("t0").min(), pl.col("t1").max(), pl.col("t_cpa").max(),
        pl.col("alert_epochs").sum().cast(pl.UInt32), (pl.col("flicker").sum() + pl.len() - 1).alias("flicker"),
        pl.col("r_min_pred_m").min(), pl.col("dz_min_pred_m").min(), *extra)


def score_external(alerts: pl.DataFrame, truth: pl.DataFrame | pl.LazyFrame, cfg: AlertConfig = AlertConfig(),
                   frame: geo.LocalFrame | None = None, intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None,
                   recording: tuple[datetime, datetime] | None = None
                   ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """(metrics, alerts, losses) of external alert lists (``method`` ``external:…``): each alert
    identified (:func:`identify_aircraft`) and scored by the pictures' rules against the truth's losses
    of separation (module docstring). ``truth`` needs ``time`` and ``truth_id`` (and the
    identity columns; the positions too unless ``intervals`` = :func:`truth_intervals` of it);
    ``recording``: the list's recording span, when known. Metrics: :data:`EXTERNAL_METRICS`."""
    lf = truth.lazy()
    if intervals is None:
        intervals = truth_intervals(lf.collect(), cfg, frame)
    los_iv, prox_iv = intervals
    shared = "run" not in lf.collect_schema().names()
    link_us = int(round(cfg.link * US))
    ident = identify_aircraft(alerts, lf)
    grid = _span_grid(ident, lf, recording)
    eps = classify_episodes(_episodes(ident, grid, cfg), los_iv, prox_iv, link_us, shared,
                            observed_until(truth_ends(lf, cfg, frame), cfg, frame))
    extra = [pl.col(c).cast(t) for c, t in _EXTRA.items() if c in eps.columns]
    scored = eps.select(
        *(pl.col(c).cast(t) for c, t in ALERTS_SCHEMA.items() if c in ("run", "method", "id_a", "id_b",
                                                                         "truth_a", "truth_b")),
        to_time("t0", "t_start"), to_time("t1", "t_end"), ((pl.col("t1") - pl.col("t0")) / US).alias("duration_s"),
        "alert_epochs", pl.col("flicker").cast(pl.UInt32), "r_min_pred_m", "dz_min_pred_m", "t_min_first_s",
        to_time("los_start_us", "los_start"), "warning_s", "classification", *extra,
        pl.lit(None, pl.String).alias("induced"),
    ).cast(ALERTS_SCHEMA).sort("run", "method", "t_start", "id_a", "id_b")
    los = los_table(grid, eps, los_iv, link_us, shared).cast(LOS_SCHEMA)
    per = per_picture(scored, los, grid).join(
        ident.group_by("method").agg(pl.col("truth_a").is_null().sum().cast(pl.Float64).alias("unidentified_alerts")),
        on="method", how="left").with_columns(pl.col("unidentified_alerts").fill_null(0.0))
    return metrics_long(per, EXTERNAL_METRICS), scored, los
