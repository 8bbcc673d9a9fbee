"""The verdict that opens the report, in one screen: three lines (the best picture against the
best radar and the centralised reference, its gap to the posterior Cramér–Rao bound, its alerts
and what causes them), then the requirements × pictures matrix with the failing cells named in
one sentence above it. The figures behind those lines follow in "Verdict in detail" (the pictures
ranked by their accuracy against the truth, each with its gap to the bound; the reference's own
row, never the yardstick; the best radar; the safety table), and the requirements' long form in
an appendix."""

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
#: 3-D) and its false and duplicate tracks per hour (stage ``evaluation``)
_FIGURES = ("pcrb_horizontal_m", "gap_horizontal_m", "pcrb_pos_m", "gap_pos_m", "false_tracks_per_hour",
            "duplicate_tracks_per_hour")


def _figures(ctx: Ctx) -> pl.DataFrame:
    """Per picture (segment ``all``) the :data:`_FIGURES`; no rows without a metrics table."""
    schema = {"picture": pl.String, **dict.fromkeys(_FIGURES, pl.Float64)}
    if "metrics" not in ctx.tables:
        return pl.DataFrame(schema=schema)
    stage = {c: "evaluation" if c.endswith("_tracks_per_hour") else "bound" for c in _FIGURES}
    cols = ", ".join(f"max(value) FILTER (WHERE stage = '{stage[c]}' AND metric = '{c}') AS {c}" for c in _FIGURES)
    return ctx.store.sql(f"SELECT method AS picture, {cols} FROM metrics WHERE segment = 'all' "
                         "AND stage IN ('bound', 'evaluation') GROUP BY method").cast(schema)


def _per_hour(v: float | None) -> str:
    return "n/a" if v is None or math.isnan(v) else f"{v:,.1f}"


#: ranked pictures listed in the verdict's table (the full ranking is in the accuracy section)
RANKED_ROWS = 5


def sec_verdict(ctx: Ctx) -> Section:
    """The one-screen verdict: the headline lines and the requirements matrix."""
    sec = Section("verdict", "Verdict")
    sec.html = _headline(ctx) + _matrix(ctx)
    return sec


def sec_verdict_detail(ctx: Ctx) -> Section:
    """The figures behind the verdict's lines: accuracy ranking (with the bound) and safety."""
    sec = Section("verdict-detail", "Verdict in detail")
    if ctx.record.get("kind") == "evaluation":
        sec.html = _verdict_evaluation(ctx)
    else:
        sec.html = "\n".join([_verdict_accuracy(ctx), _verdict_safety(ctx)])
    return sec


def sec_requirements_long(ctx: Ctx) -> Section:
    """Appendix: one row per requirement × picture (the matrix's cells, with value and samples)."""
    sec = Section("requirements", "Appendix: requirements, one row per picture")
    sec.html = _verdict_requirements(ctx)
    return sec


# --------------------------------------------------------------------------- the headline


def _headline(ctx: Ctx) -> str:
    """Three lines: best picture, bound, alerts (each left out when the run has no such figures)."""
    if ctx.record.get("kind") == "evaluation":
        lines = [_line_evaluation(ctx)]
    else:
        lines = [_line_best(ctx), _line_bound(ctx), _line_alerts(ctx)]
    return '<div class="headline">' + "".join(f"<p>{ln}</p>" for ln in lines if ln) + "</div>"


def _line_best(ctx: Ctx) -> str:
    b = ctx.best
    if b.picture is None:
        return "No accuracy against a reference: the run has no truth (or no picture could be scored)."
    pic = b.pictures.filter(pl.col("picture") == b.picture).row(0, named=True)
    text = (f"<b>Best picture {html.escape(b.picture)}</b>: horizontal RMSE <b>{_m(pic['horizontal_m'])}</b>, "
            f"vertical <b>{_m(pic['height_m'])}</b>")
    if b.radar:
        rad = b.radars.filter(pl.col("radar") == b.radar).row(0, named=True)
        text += (f", {_rel(pic['horizontal_m'], rad['horizontal_m'])} the best {b.radar_kind} alone "
                 f"({html.escape(b.radar)}, {_m(rad['horizontal_m'])})")
    ref = b.pictures.filter(pl.col("picture") == CENTRALIZED)
    if ref.height:
        text += f"; centralised reference {_m(ref['horizontal_m'][0])} (not ranked)"
    return text + "."


def _line_bound(ctx: Ctx) -> str:
    b = ctx.best
    figs = _figures(ctx)
    if b.picture is None or figs.height == 0:
        return ""
    horizontal = b.ranked_by == "rmse_horizontal_m"
    pcrb, gap = ("pcrb_horizontal_m", "gap_horizontal_m") if horizontal else ("pcrb_pos_m", "gap_pos_m")
    row = figs.filter(pl.col("picture") == b.picture)
    if row.height == 0 or row[gap][0] is None:
        return ""
    g, bound = row[gap][0], row[pcrb][0]
    below = figs.filter(pl.col(gap) < 0)["picture"].to_list()
    tail = ("no picture is below the bound" if not below else
            f"<b>{len(below)} picture(s) below the bound</b>, which must not happen: {html.escape(', '.join(below))}")
    return (f"<b>Bound</b>: its {'horizontal' if horizontal else '3-D'} error is <b>{abs(g):,.1f} m "
            f"{'above' if g >= 0 else 'below'}</b> the posterior Cramér–Rao bound (PCRB {bound:,.1f} m on its own "
            f"samples); {tail}.")


def _line_alerts(ctx: Ctx) -> str:
    scores = ctx.q("alert_scores") if "metrics" in ctx.tables else pl.DataFrame()
    if scores.height == 0 or scores["los_episodes"].is_null().all():
        return ""
    pick = ctx.best.best_of(scores["method"].to_list())
    r = scores.filter(pl.col("method") == pick).row(0, named=True)
    n = lambda v: "n/a" if v is None else f"{v:,.0f}"     # noqa: E731 — counts
    warn = "" if r["warning_median_s"] is None else f", median warning {r['warning_median_s']:.0f} s"
    text = (f"<b>Alerts</b> on {html.escape(pick)}: <b>{n(r['alerted_los'])} of {n(r['los_episodes'])} losses of "
            f"separation alerted</b>{warn}; {n(r['genuine_alerts'])} genuine, {n(r['nuisance_alerts'])} nuisance, "
            f"<b>{n(r['false_alerts'])} false</b>, {n(r.get('undetermined_alerts'))} undetermined")
    if r.get("alerts_picture_induced") is not None:
        total = sum(r.get(k) or 0 for k in ("genuine_alerts", "nuisance_alerts", "false_alerts", "undetermined_alerts"))
        text += (f"; <b>{n(r['alerts_picture_induced'])} picture-induced</b> ({n(r['false_alerts_picture_induced'])} "
                 f"false, {n(r['nuisance_alerts_picture_induced'])} nuisance), "
                 f"{n(total - (r['alerts_picture_induced'] or 0))} predictor-induced")
    return text + "."


def _line_evaluation(ctx: Ctx) -> str:
    cmp = ctx.q("picture_comparison")
    ranked = cmp.filter(pl.col("method") != CENTRALIZED)
    if ranked.height == 0:
        return "No picture could be matched to the reference."
    best = ranked.row(0, named=True)
    return (f"<b>Most accurate picture {html.escape(best['method'])}</b>: horizontal RMS "
            f"<b>{_m(best['rmse_horizontal_m'])}</b>, height RMS <b>{_m(best['rmse_height_m'])}</b>; "
            f"{ranked.height} picture(s) compared.")


# --------------------------------------------------------------------------- the matrix

_MARK = {"pass": "✓", "fail": "✗", "insufficient": "?"}


def _picture_order(ctx: Ctx, names: list[str]) -> list[str]:
    """Most accurate first (the verdict's ranking), then the unranked by name, the reference last."""
    b = ctx.best
    key = "horizontal_m" if b.ranked_by == "rmse_horizontal_m" else "pos_m"
    ranked = b.pictures.filter(pl.col(key).is_not_null()).sort(key, "picture")["picture"].to_list()
    rank = {p: i for i, p in enumerate(ranked)}
    return sorted(names, key=lambda p: (p == CENTRALIZED, rank.get(p, len(rank)), p))


def _family(picture: str) -> str:
    """A picture's family: its tracker filter (``+imm_sym``), ``fused`` for a fusion method, or the
    centralised reference on its own."""
    if picture == CENTRALIZED:
        return CENTRALIZED
    return "+" + picture.split("+", 1)[1] if "+" in picture else "fused"


def _name_pictures(fails: list[str], pictures: list[str]) -> str:
    """The failing pictures named compactly: a family that fails whole is named once ("every
    +singer picture"), the others as fusion methods under their family's filter."""
    if len(fails) == len(pictures):
        return "every picture"
    parts = []
    for fam in dict.fromkeys(map(_family, pictures)):
        members = [p for p in pictures if _family(p) == fam]
        bad = [p for p in members if p in fails]
        if not bad:
            continue
        if len(bad) == len(members) and len(members) > 1:
            parts.append(f"every {fam} picture" if fam != "fused" else "every fused picture")
        elif not fam.startswith("+") or len(bad) == 1:
            parts.append(", ".join(bad))
        else:
            parts.append(f"{', '.join(p.split('+', 1)[0] for p in bad)} (each {fam})")
    return "; ".join(parts) if len(parts) < 2 else ", ".join(parts[:-1]) + " and " + parts[-1]


def _failing_sentence(req: pl.DataFrame, pictures: list[str]) -> str:
    """The failing cells in one sentence, one clause per failing requirement."""
    clauses = []
    for name in req["requirement"].unique(maintain_order=True):
        failing = set(req.filter((pl.col("requirement") == name) & (pl.col("verdict") == "fail"))["method"])
        fails = [p for p in pictures if p in failing]
        if fails:
            clauses.append(f"<b>{html.escape(name)}</b> on {html.escape(_name_pictures(fails, pictures))}")
    unsure = int((req["verdict"] == "insufficient").sum())
    tail = f" {unsure} cell(s) have too few samples for a verdict." if unsure else ""
    if not clauses:
        return f"No requirement fails on any picture.{tail}"
    return "Failing: " + "; ".join(clauses) + "." + tail


def _cell_title(r: dict) -> str:
    value = "n/a" if r.get("value") is None else f"{r['value']:,.4g}"
    op = r.get("op") or ("≤" if r.get("metric", "").endswith("_m") else "")
    n = "" if r.get("n_samples") is None else f", {r['n_samples']:,.0f} samples"
    return (f"{r['requirement']} on {r['method']}: {r.get('metric', '')} ({r.get('breakdown', '')}) = {value}, "
            f"required {op} {r['threshold']:,.4g}{n}: {r['verdict']}")


def _matrix(ctx: Ctx) -> str:
    """Requirements (rows) × pictures (columns), each cell coloured by its verdict, the value on
    hover; the failing cells named in one sentence above it."""
    if "requirements" not in ctx.tables:
        return ('<p class="note">Requirements: not evaluated (the run database has no <code>requirements</code> '
                "table).</p>")
    req = ctx.store.sql("SELECT * FROM requirements")
    if req.height == 0 or not {"requirement", "method", "verdict"} <= set(req.columns):
        return '<p class="note">Requirements: the requirements table is empty.</p>'
    pictures = _picture_order(ctx, req["method"].unique().to_list())
    cells = {(r["requirement"], r["method"]): r for r in req.iter_rows(named=True)}
    head = "".join(f'<th class="vm-pic"><span>{html.escape(p)}</span></th>' for p in pictures)
    body = []
    for name in req["requirement"].unique(maintain_order=True):
        first = req.filter(pl.col("requirement") == name).row(0, named=True)
        what = (f"{first.get('metric', '')} ({first.get('breakdown', '')}) {first.get('op') or ''} "
                f"{first['threshold']:,.4g}")
        row = [f'<th class="vm-req" title="{html.escape(what)}">{html.escape(name)}</th>']
        for p in pictures:
            r = cells.get((name, p))
            if r is None:
                row.append('<td class="vm" title="not judged">·</td>')
                continue
            v = r["verdict"]
            row.append(f'<td class="vm verdict-{html.escape(v)}" title="{html.escape(_cell_title(r))}">'
                       f"{_MARK.get(v, v)}</td>")
        body.append("<tr>" + "".join(row) + "</tr>")
    legend = ('<span class="vm-legend"><span class="verdict-pass">✓ pass</span> <span class="verdict-fail">✗ fail'
              '</span> <span class="verdict-insufficient">? too few samples</span>; hover a cell for its value; '
              'pictures most accurate first; every row in the appendix</span>')
    return (f'<p class="vm-sentence">{_failing_sentence(req, pictures)} {legend}</p>'
            f'<div class="tablewrap"><table id="verdict-matrix" class="vmatrix"><thead><tr><th></th>{head}</tr>'
            f'</thead><tbody>{"".join(body)}</tbody></table></div>')


# --------------------------------------------------------------------------- in detail


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
                 f"height RMS {_m(r['rmse_height_m'])}, {_per_hour(r['false_tracks_per_hour'])} false and "
                 f"{_per_hour(r.get('duplicate_tracks_per_hour'))} duplicate tracks per hour.</p>")
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
                     "targets confirmed by the pictures' plot count and the trackers' three-scan test; a reference, "
                     "not a bound, and not ranked): horizontal "
                     f"RMSE {_m(ref['horizontal_m'])}, vertical {_m(ref['height_m'])}, its {what} error "
                     f"{_gap(ref[gap], ref[pcrb])}; {_per_hour(ref['false_tracks_per_hour'])} false and "
                     f"{_per_hour(ref['duplicate_tracks_per_hour'])} duplicate tracks per hour.")
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
    rows += [(None, b.radar, f"best {b.radar_kind} alone", {**rad, **dict.fromkeys(_FIGURES)})] if rad else []
    num = ("horizontal RMSE (m)", "vertical RMSE (m)", "3-D RMSE (m)", f"{what} PCRB (m)",
           f"{what} gap to PCRB (m)", "false tracks per hour", "duplicate tracks per hour")
    src = ("horizontal_m", "height_m", "pos_m", pcrb, gap, "false_tracks_per_hour", "duplicate_tracks_per_hour")
    table = pl.DataFrame({"rank": [r[0] for r in rows], "picture": [r[1] for r in rows], "role": [r[2] for r in rows],
                          **{h: [r[3][c] for r in rows] for h, c in zip(num, src)}},
                         schema_overrides={"rank": pl.UInt32, **dict.fromkeys(num, pl.Float64)})
    return ("<h3>Accuracy of the air picture</h3>" + "".join(f"<p>{ln}</p>" for ln in lines)
            + table_html(table) + f'<p class="note">{html.escape(rule)}</p>')


_SAFETY_COLS = {  # alert_scores column → plain heading with unit
    "method": "picture", "los_episodes": "losses of separation", "alerted_los": "losses alerted",
    "missed_los": "losses missed", "genuine_alerts": "genuine alerts", "nuisance_alerts": "nuisance alerts",
    "alerts_per_hour": "alerts per hour (1/h)", "warning_median_s": "median warning (s)",
    "warning_p05_s": "5th-percentile warning (s)", "false_alerts": "false alerts",
    "undetermined_alerts": "undetermined alerts",
    "false_alerts_picture_induced": "false, picture-induced", "nuisance_alerts_picture_induced":
    "nuisance, picture-induced", "missed_los_picture_induced": "missed, picture-induced",
}


def _verdict_safety(ctx: Ctx) -> str:
    head = "<h3>Safety performance (conflict alerts)</h3>"
    scores = ctx.q("alert_scores") if "metrics" in ctx.tables else pl.DataFrame()
    if scores.height == 0:
        return head + '<p class="note">No conflict alerts were scored in this run (no safety stage, or no truth).</p>'
    if scores["los_episodes"].is_null().all():
        return head + ('<p class="note">No losses of separation were scored in this run (the truth has no '
                       "minima to score against).</p>")
    b = ctx.best
    pick = b.best_of(scores["method"].to_list())     # the most accurate of the scored pictures
    r = scores.filter(pl.col("method") == pick).row(0, named=True)
    f = lambda v, unit="": "n/a" if v is None else f"{v:,.0f}{unit}"   # noqa: E731 — counts
    text = (f"On <b>{html.escape(pick)}</b>: {f(r['los_episodes'])} losses of separation in truth, "
            f"<b>{f(r['alerted_los'])} alerted</b>, <b>{f(r['missed_los'])} missed</b>; "
            f"{f(r['genuine_alerts'])} genuine, {f(r['nuisance_alerts'])} nuisance and "
            f"{f(r['false_alerts'])} false alerts, {f(r.get('undetermined_alerts'))} undetermined (the truth "
            f"ends before their outcome) ({r['alerts_per_hour'] or 0:.1f} alerts per hour); median "
            f"warning {f(r['warning_median_s'], ' s')}, 5th percentile {f(r['warning_p05_s'], ' s')}.")
    cols = ["method", "los_episodes", "alerted_los", "missed_los", "genuine_alerts", "nuisance_alerts",
            "false_alerts", "undetermined_alerts", "alerts_per_hour", "warning_median_s", "warning_p05_s"]
    if r.get("alerts_picture_induced") is not None:
        # what a better picture can remove, and what only a better predictor can
        text += (f" Of its alerts <b>{f(r['alerts_picture_induced'])} are picture-induced</b> "
                 f"({f(r['false_alerts_picture_induced'])} false, {f(r['nuisance_alerts_picture_induced'])} "
                 f"nuisance): the same prediction on the truth picture does not raise them; the others are the "
                 f"predictor's. {f(r['missed_los_picture_induced'])} of its missed losses were alerted on the "
                 f"truth picture; {f(r.get('missed_los_under_way'))} were under way when their aircraft were first "
                 f"observed (no alert can precede them).")
        cols += ["false_alerts_picture_induced", "nuisance_alerts_picture_induced", "missed_los_picture_induced"]
    table = scores.select(cols).rename({c: _SAFETY_COLS[c] for c in cols})
    note = ("Scored against truth per picture (sql/alert_scores.sql); the full table with flicker is in the "
            "Conflicts section.")
    return head + f"<p>{text}</p>" + table_html(table) + f'<p class="note">{note}</p>'


def _verdict_requirements(ctx: Ctx) -> str:
    if "requirements" not in ctx.tables:
        return ('<p class="note">Not evaluated: the run database has no <code>requirements</code> table, so no '
                "pass/fail verdict is given.</p>")
    req = ctx.store.sql("SELECT * FROM requirements")
    if "verdict" not in req.columns or req.height == 0:
        return '<p class="note">The requirements table is empty or has no verdict column.</p>'
    counts = dict(req.group_by("verdict").len().iter_rows())
    parts = [f"{counts.get(v, 0)} {label}" for v, label in (("pass", "pass"), ("fail", "fail"),
                                                           ("insufficient", "insufficient samples"))]
    text = (f"<b>{', '.join(parts)}</b> (of {req.height} requirement × picture cells; the same rows: "
            "<code>tertiary sql RUN_DIR requirements_verdicts</code>).")
    return f"<p>{text}</p>" + table_html(req, cell_class={"verdict": lambda v: f"verdict-{v}"})
