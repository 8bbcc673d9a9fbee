"""The verdict that opens the report: the pictures ranked by their accuracy against the truth,
each with its distance to the posterior Cramér–Rao bound (metrics stage ``bound``), the
centralised reference's own figures beside them (never the yardstick), the best radar, the
safety performance, and the requirements' pass/fail table."""

from __future__ import annotations

import html
import math
from typing import Any

import polars as pl

from tertiary.report.common import CENTRALIZED, Ctx, Section, table_html

def _m(v: Any) -> str:
    """A distance in metres for prose ("41.2 m"; "n/a" when missing)."""
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:,.1f} m"


def _rel(a: float | None, b: float | None) -> str:
    """'23 % smaller than' / '5 % larger than' / 'equal to' for a against b."""
    if a is None or b is None or not b:
        return "not comparable with"
    r = (a - b) / b * 100.0
    if abs(r) < 0.5:
        return "equal to"
    return f"{abs(r):.0f} % {'smaller' if r < 0 else 'larger'} than"


def _gap(gap: float | None, bound: float | None) -> str:
    """'12.3 m above the bound (PCRB 59.5 m …)' for a signed gap RMSE − PCRB."""
    if gap is None or bound is None or math.isnan(gap) or math.isnan(bound):
        return "not comparable with the bound (no PCRB for its samples)"
    side = "above" if gap >= 0 else "below"
    return f"{abs(gap):,.1f} m {side} the posterior Cramér–Rao bound (PCRB {bound:,.1f} m on the same samples)"


#: the figures of a picture beside its accuracy: its bound and gap (stage ``bound``, horizontal and
#: 3-D) and its false tracks per hour (stage ``evaluation``)
_FIGURES = ("pcrb_horizontal_m", "gap_horizontal_m", "pcrb_pos_m", "gap_pos_m", "false_tracks_per_hour")


def _figures(ctx: Ctx) -> pl.DataFrame:
    """Per picture (segment ``all``) the :data:`_FIGURES`; no rows without a metrics table."""
    schema = {"picture": pl.String, **dict.fromkeys(_FIGURES, pl.Float64)}
    if "metrics" not in ctx.tables:
        return pl.DataFrame(schema=schema)
    stage = {c: "evaluation" if c == "false_tracks_per_hour" else "bound" for c in _FIGURES}
    cols = ", ".join(f"max(value) FILTER (WHERE stage = '{stage[c]}' AND metric = '{c}') AS {c}" for c in _FIGURES)
    return ctx.store.sql(f"SELECT method AS picture, {cols} FROM metrics WHERE segment = 'all' "
                         "AND stage IN ('bound', 'evaluation') GROUP BY method").cast(schema)


def _per_hour(v: float | None) -> str:
    return "n/a" if v is None or math.isnan(v) else f"{v:,.1f}"


#: ranked pictures listed in the verdict's table (the full ranking is in the accuracy section)
RANKED_ROWS = 5


def sec_verdict(ctx: Ctx) -> Section:
    sec = Section("verdict", "Verdict")
    if ctx.record.get("kind") == "evaluation":      # requirements first, then the pictures' accuracy
        sec.html = "\n".join([_verdict_requirements(ctx), _verdict_evaluation(ctx)])
    else:
        sec.html = "\n".join([_verdict_accuracy(ctx), _verdict_safety(ctx), _verdict_requirements(ctx)])
    return sec


def _verdict_evaluation(ctx: Ctx) -> str:
    cmp = ctx.q("picture_comparison")
    ranked = cmp.filter(pl.col("method") != CENTRALIZED)      # ordered by horizontal RMS against the truth
    if ranked.height == 0:
        return '<h3>Accuracy</h3><p class="note">No picture could be matched to the reference.</p>'
    best = ranked.row(0, named=True)
    text = (f"<h3>Accuracy</h3><p><b>Most accurate picture: {html.escape(best['method'])}</b> — horizontal RMS "
            f"<b>{_m(best['rmse_horizontal_m'])}</b> (95 % {_m(best['p95_horizontal_m'])}), height RMS "
            f"<b>{_m(best['rmse_height_m'])}</b>, {ranked.height} picture(s) compared below.</p>")
    ref = cmp.filter(pl.col("method") == CENTRALIZED)
    if ref.height:
        r = ref.row(0, named=True)
        text += (f"<p>Centralised reference ({CENTRALIZED}, not ranked): horizontal RMS {_m(r['rmse_horizontal_m'])}, "
                 f"height RMS {_m(r['rmse_height_m'])}, {_per_hour(r['false_tracks_per_hour'])} false tracks per "
                 "hour.</p>")
    return text


def _verdict_accuracy(ctx: Ctx) -> str:
    b = ctx.best
    if b.picture is None:
        return ('<h3>Accuracy</h3><p class="note">No accuracy against a reference: the run has no truth '
                '(or no fused picture could be scored).</p>')
    horizontal = b.ranked_by == "rmse_horizontal_m"
    key, pcrb, gap = (("horizontal_m", "pcrb_horizontal_m", "gap_horizontal_m") if horizontal
                      else ("pos_m", "pcrb_pos_m", "gap_pos_m"))
    what = "horizontal" if horizontal else "3-D"
    figs = b.pictures.join(_figures(ctx), on="picture", how="left")
    ranked = (figs.filter((pl.col("picture") != CENTRALIZED) & pl.col(key).is_not_null())
              .sort(key, "picture").head(RANKED_ROWS).with_row_index("rank", offset=1))
    pic = figs.filter(pl.col("picture") == b.picture).row(0, named=True)
    ref = figs.filter(pl.col("picture") == CENTRALIZED)
    ref = ref.row(0, named=True) if ref.height else None
    rad = b.radars.filter(pl.col("radar") == b.radar).row(0, named=True) if b.radar else None
    lines = [f"<b>Best picture: {html.escape(b.picture)}</b> — horizontal RMSE <b>{_m(pic['horizontal_m'])}</b>, "
             f"vertical (height) RMSE <b>{_m(pic['height_m'])}</b> (3-D {_m(pic['pos_m'])}). Its {what} error is "
             f"<b>{_gap(pic[gap], pic[pcrb])}</b>."]
    if ref:
        lines.append(f"Centralised reference ({CENTRALIZED}: one Kalman filter on every radar's measurements, its "
                     "targets confirmed as the pictures' are; a reference, not a bound, and not ranked): horizontal "
                     f"RMSE {_m(ref['horizontal_m'])}, vertical {_m(ref['height_m'])}, its {what} error "
                     f"{_gap(ref[gap], ref[pcrb])}; {_per_hour(ref['false_tracks_per_hour'])} false tracks per hour.")
    if rad:
        lines.append(f"Best radar alone ({html.escape(b.radar)}, its own track estimates): horizontal "
                     f"{_m(rad['horizontal_m'])}, vertical {_m(rad['height_m'])}. The best picture's horizontal "
                     f"error is {_rel(pic['horizontal_m'], rad['horizontal_m'])} the best radar's.")
    rule = (f"Ranked by {b.ranked_by} over all segments, against simulator truth; RMSE pooled as sqrt(mean over "
            "epochs of σ²(k)), first 20 s of each track left out. Gap to the bound = RMSE − PCRB on the picture's "
            "own scored samples (below zero the picture beats the bound's motion model on this truth). The "
            "centralised reference is not ranked: its own figures are its row.")
    if b.unranked:
        more = f" and {len(b.unranked) - 6} more" if len(b.unranked) > 6 else ""
        rule += (f" Not ranked ({len(b.unranked)} pictures without a {b.ranked_by} row in this run): "
                 f"{', '.join(b.unranked[:6])}{more}.")
    rows = [(r["rank"], r["picture"], "best picture" if r["picture"] == b.picture else "picture", r)
            for r in ranked.iter_rows(named=True)]
    rows += [(None, CENTRALIZED, "centralised reference (not ranked)", ref)] if ref else []
    rows += [(None, b.radar, "best radar alone", {**rad, **dict.fromkeys(_FIGURES)})] if rad else []
    num = ("horizontal RMSE (m)", "vertical RMSE (m)", "3-D RMSE (m)", f"{what} PCRB (m)",
           f"{what} gap to PCRB (m)", "false tracks per hour")
    src = ("horizontal_m", "height_m", "pos_m", pcrb, gap, "false_tracks_per_hour")
    table = pl.DataFrame({"rank": [r[0] for r in rows], "picture": [r[1] for r in rows], "role": [r[2] for r in rows],
                          **{h: [r[3][c] for r in rows] for h, c in zip(num, src)}},
                         schema_overrides={"rank": pl.UInt32, **dict.fromkeys(num, pl.Float64)})
    return ("<h3>Accuracy of the air picture</h3>" + "".join(f"<p>{ln}</p>" for ln in lines)
            + table_html(table) + f'<p class="note">{html.escape(rule)}</p>')


_SAFETY_COLS = {  # alert_scores column → plain heading with unit
    "method": "picture", "los_episodes": "losses of separation", "alerted_los": "losses alerted",
    "missed_los": "losses missed", "genuine_alerts": "genuine alerts", "nuisance_alerts": "nuisance alerts",
    "alerts_per_hour": "alerts per hour (1/h)", "warning_median_s": "median warning (s)",
    "warning_p05_s": "5th-percentile warning (s)", "episodes": "true conflicts", "hits": "alerted in time",
    "misses": "missed", "false_alerts": "false alerts", "mean_warning_s": "mean warning (s)",
    "false_alerts_picture_induced": "false, picture-induced", "nuisance_alerts_picture_induced":
    "nuisance, picture-induced", "missed_los_picture_induced": "missed, picture-induced",
}


def _verdict_safety(ctx: Ctx) -> str:
    head = "<h3>Safety performance (conflict alerts)</h3>"
    scores = ctx.q("alert_scores") if "metrics" in ctx.tables else pl.DataFrame()
    if scores.height == 0:
        return head + '<p class="note">No conflict alerts were scored in this run (no safety stage, or no truth).</p>'
    los = scores["los_episodes"].is_not_null().any()
    b = ctx.best
    pick = b.best_of(scores["method"].to_list())     # the most accurate of the scored pictures
    r = scores.filter(pl.col("method") == pick).row(0, named=True)
    f = lambda v, unit="": "n/a" if v is None else f"{v:,.0f}{unit}"   # noqa: E731 — counts
    if los and r["los_episodes"] is not None:
        text = (f"On <b>{html.escape(pick)}</b>: {f(r['los_episodes'])} losses of separation in truth, "
                f"<b>{f(r['alerted_los'])} alerted</b>, <b>{f(r['missed_los'])} missed</b>; "
                f"{f(r['genuine_alerts'])} genuine, {f(r['nuisance_alerts'])} nuisance and "
                f"{f(r['false_alerts'])} false alerts ({r['alerts_per_hour'] or 0:.1f} alerts per hour); median "
                f"warning {f(r['warning_median_s'], ' s')}, 5th percentile {f(r['warning_p05_s'], ' s')}.")
        cols = ["method", "los_episodes", "alerted_los", "missed_los", "genuine_alerts", "nuisance_alerts",
                "false_alerts", "alerts_per_hour", "warning_median_s", "warning_p05_s"]
        if r.get("alerts_picture_induced") is not None:
            # what a better picture can remove, and what only a better predictor can
            text += (f" Of its alerts <b>{f(r['alerts_picture_induced'])} are picture-induced</b> "
                     f"({f(r['false_alerts_picture_induced'])} false, {f(r['nuisance_alerts_picture_induced'])} "
                     f"nuisance): the same prediction on the truth picture does not raise them; the others are the "
                     f"predictor's. {f(r['missed_los_picture_induced'])} of its missed losses were alerted on the "
                     f"truth picture.")
            cols += ["false_alerts_picture_induced", "nuisance_alerts_picture_induced", "missed_los_picture_induced"]
    else:
        warn = "n/a" if r["mean_warning_s"] is None else f"{r['mean_warning_s']:.0f} s"
        text = (f"On <b>{html.escape(pick)}</b>: {f(r['episodes'])} true-conflict episodes in truth, "
                f"<b>{f(r['hits'])} alerted in time</b>, <b>{f(r['misses'])} missed</b>; "
                f"<b>{f(r['false_alerts'])} false alerts</b>; mean warning time {warn}.")
        cols = ["method", "episodes", "hits", "misses", "false_alerts", "mean_warning_s"]
    table = scores.select(cols).rename({c: _SAFETY_COLS[c] for c in cols})
    note = ("Scored against truth per picture (sql/alert_scores.sql); the full table with flicker is in the "
            "Conflicts section.")
    return head + f"<p>{text}</p>" + table_html(table) + f'<p class="note">{note}</p>'


def _verdict_requirements(ctx: Ctx) -> str:
    head = "<h3>Requirements</h3>"
    if "requirements" not in ctx.tables:
        return head + ('<p class="note">Not evaluated: the run database has no <code>requirements</code> table, so '
                       "no pass/fail verdict is given.</p>")
    req = ctx.store.sql("SELECT * FROM requirements")
    if "verdict" not in req.columns or req.height == 0:
        return head + '<p class="note">The requirements table is empty or has no verdict column.</p>'
    counts = dict(req.group_by("verdict").len().iter_rows())
    parts = [f"{counts.get(v, 0)} {label}" for v, label in (("pass", "pass"), ("fail", "fail"),
                                                           ("insufficient", "insufficient samples"))]
    text = f"<b>{', '.join(parts)}</b> (of {req.height} requirements)."
    return head + f"<p>{text}</p>" + table_html(req, cell_class={"verdict": lambda v: f"verdict-{v}"})

