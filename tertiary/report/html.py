"""``tertiary report``: one self-contained HTML file per run (``RUN_DIR/report.html``).

Every figure and table is drawn from the named SQL reports in ``sql/`` (run read-only through
:mod:`tertiary.store.sql_reports`); only the capacity-model curves of figs. 5.2/5.3 come from
:mod:`safety.capacity`. The plotly.js bundle is embedded inline once, so the file opens offline.

The report opens with a **verdict** that fits one screen (:mod:`tertiary.report.verdict`): three
lines — the best picture against the best radar and the centralised reference, its gap to the
posterior Cramér–Rao bound, its alerts and how many the picture causes against the truth picture
— then the requirements × pictures matrix, the failing cells named in one sentence above it.
"Verdict in detail" follows the table of contents (the pictures ranked by their accuracy against
the truth, each with its gap to the bound; the centralised reference on a row of its own, never
ranked; the best radar; the safety table), and the requirements' long form is an appendix. The
*best picture* is the fused or tracker picture (not the centralised reference) with the lowest
horizontal RMSE (segment ``all``); the *best radar* the radar whose own track estimates have the
lowest horizontal RMSE. In the accuracy and conflict figures these three are drawn by default;
every other trace is in the legend (click to show).

Edge-of-coverage rule: accuracy curves over time leave out epochs whose number of scored samples
N_k is below :data:`MIN_SAMPLE_FRAC` of the median N_k of that curve (at the start and end of
coverage σ(k) rests on a handful of aircraft and is not a result); the rule is applied in SQL
(``min_sample_frac``) and stated in each caption.

Figures (seed numbering):

* 4.4  scenario map: radar sites and truth trajectories (``trajectories``, ``radar_sites``)
* 4.5–4.7  range, range rate and line-of-sight acceleration over time, first run, a few
  aircraft, one small panel per radar (``radar_kinematics``)
* 4.9  range residuals per radar over time (``radar_residuals_over_time``)
* 4.10 real RMS horizontal and vertical error over time per radar and per picture, in two
  panels (``radar_accuracy_over_time``, ``accuracy_over_time``)
* 4.11 a-posteriori versus a-priori weights (``aposteriori_vs_apriori``, ``aposteriori_gain``)
* accuracy by method, filter and segment, horizontal and vertical panels (``accuracy_by_method``)
* conflict timeline: pairs in alert and new alerts per minute (``conflict_timeline``,
  ``conflicts``, ``alert_scores``)
* alert episodes: the most severe episodes of the best picture and its missed losses, each in
  plan view and vertical profile (:mod:`tertiary.report.episodes`)
* STCA curves: losses alerted with ≥ 30 s warning against nuisance + false alerts per hour,
  covariance vs fixed thresholds, per look-ahead (``stca_tradeoff``,
  :func:`safety.alerts.compare_at_equal_nuisance`)
* 5.2  P_pob against the number of aircraft for several σ (``safety.capacity.ppob_curves``)
* 5.3  capacity against σ with each method's measured point (``safety.capacity.capacity_curve``,
  ``capacity_by_method``)

plus tables of association, track and cluster quality, and the run metadata (configuration,
versions, input fingerprints, timings, row accounting, rejects).

Size is bounded: trajectories are thinned in SQL, time series are capped at
:data:`MAX_POINTS` points per trace and arrays are stored as base64 float32, so the default
terminal-area run gives under 6 MB, of which plotly.js is about 4.8 MB; figures share a lean template
(:func:`tertiary.report.common.lean_template`) and step curves keep only their changes.

Browser checks: a small script in the page head records every JavaScript error (``error`` and
``unhandledrejection`` events) into ``<pre id="js-errors">`` and ``body[data-js-errors]``;
each figure increments ``body[data-rendered]`` once plotly has drawn it, and
``body[data-figures]`` holds the number of figures in the file; ``body[data-verdict-bottom]`` where the
verdict matrix ends (px from the top of the page), so "above the fold" is checked in a browser.
"""


from __future__ import annotations

import html
import json
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import resources
from pathlib import Path
from string import Template

import plotly.io as pio
import polars as pl

from tertiary.report.common import (MAX_POINTS, MIN_SAMPLE_FRAC, Ctx, Progress, Section,
                                    table_html)
from tertiary.report.figures import (sec_accuracy, sec_conflicts, sec_evaluation, sec_kinematics, sec_map,
                                     sec_post_prior, sec_quality, sec_residuals, sec_rmse_time)
from tertiary.report.safety_figures import sec_capacity, sec_ppob, sec_stca
from tertiary.report.episodes import sec_episodes
from tertiary.report.verdict import sec_requirements_long, sec_verdict, sec_verdict_detail
from tertiary.store.files import write_text_atomic
from tertiary.store.sql_reports import open_read_only

__all__ = ["REPORT_FILENAME", "MAX_POINTS", "MIN_SAMPLE_FRAC", "build_report", "render_report", "build_sections",
           "figure_count"]

REPORT_FILENAME = "report.html"


def sec_metadata(ctx: Ctx) -> Section:
    sec = Section("metadata", "Run metadata")
    parts = []
    kv = [("scenario", ctx.record.get("scenario", "")), ("created (UTC)", ctx.record.get("created_utc", "")),
          ("database", str(ctx.store.path))]
    notes = ctx.json("notes") or []
    if notes:
        kv.append(("notes", "; ".join(map(str, notes))))
    parts.append(table_html(pl.DataFrame({"item": [k for k, _ in kv], "value": [str(v) for _, v in kv]})))
    for key, title in (("versions", "Versions"), ("fingerprints", "Input fingerprints")):
        d = ctx.json(key)
        if isinstance(d, dict):
            parts.append(f"<h3>{title}</h3>" + table_html(
                pl.DataFrame({"name": list(d), "value": [str(v) for v in d.values()]})))
    sec.html = "\n".join(parts)
    if ctx.record.get("kind") == "evaluation":     # pictures and a reference: no pipeline tables
        kv2 = [(k, ctx.record.get(k, "")) for k in ("pictures", "tracks_files", "reference", "requirements")]
        sec.tables.append(("What was evaluated", pl.DataFrame({"item": [k for k, _ in kv2],
                                                               "value": [str(v) for _, v in kv2]})))
    else:
        sec.tables.append(("Stage timings (sql/stage_timings.sql)", ctx.q("stage_timings")))
        sec.tables.append(("Row accounting (sql/row_accounting.sql)", ctx.q("row_accounting")))
        sec.tables.append(("Rejects by reason (sql/rejects_by_reason.sql)", ctx.q("rejects_by_reason")))
        sec.tables.append(("Reports per radar (sql/reports_by_radar.sql)", ctx.q("reports_by_radar")))
    config = ctx.json("config")
    details = []
    if config is not None:
        details.append(("Pipeline configuration", json.dumps(config, indent=2)))
    if ctx.record.get("scenario_toml"):
        details.append(("Scenario (TOML)", ctx.record["scenario_toml"]))
    sec.note = "".join(f"<details><summary>{html.escape(t)}</summary><pre>{html.escape(body)}</pre></details>"
                       for t, body in details)
    return sec


def _template(name: str) -> str:
    """The text of ``tertiary/report/templates/<name>``: the page skeleton, its style and its script."""
    return resources.files("tertiary.report").joinpath("templates", name).read_text(encoding="utf-8")


_SECTIONS: list[tuple[str, Callable[[Ctx], Section]]] = [
    ("verdict", sec_verdict),
    ("verdict in detail", sec_verdict_detail),
    ("scenario map", sec_map),
    ("range, rate, acceleration", sec_kinematics),
    ("residuals", sec_residuals),
    ("RMSE over time", sec_rmse_time),
    ("a-posteriori vs a-priori", sec_post_prior),
    ("accuracy", sec_accuracy),
    ("evaluation", sec_evaluation),
    ("quality", sec_quality),
    ("conflicts", sec_conflicts),
    ("alert episodes", sec_episodes),
    ("STCA curves", sec_stca),
    ("P_pob", sec_ppob),
    ("capacity", sec_capacity),
    ("requirements", sec_requirements_long),
    ("metadata", sec_metadata),
]


_EVAL_SECTIONS = [("verdict", sec_verdict), ("verdict in detail", sec_verdict_detail), ("evaluation", sec_evaluation),
                  ("requirements", sec_requirements_long), ("metadata", sec_metadata)]

@dataclass
class _Built:
    """The report's sections and the run facts of its header."""

    sections: list[Section]
    scenario: str
    created: str
    rows: dict
    timings: dict


def build_sections(run_dir: str | os.PathLike[str], progress: Progress | None = None) -> _Built:
    """Every section of the report (plotly figures, tables, HTML), verdict first; a section
    whose data is missing holds a "Not available" note instead of failing the report."""
    say = progress or (lambda _m: None)
    sections: list[Section] = []
    with open_read_only(run_dir) as store:
        ctx = Ctx(store, say)
        # a run of `tertiary evaluate` holds pictures and a reference, no pipeline stages
        sections_of_run = _EVAL_SECTIONS if ctx.record.get("kind") == "evaluation" else _SECTIONS
        for label, build in sections_of_run:
            say(f"report: {label}")
            try:
                sections.append(build(ctx))
            except Exception as exc:   # one missing table must not lose the whole report
                sections.append(Section(build.__name__.removeprefix("sec_"), label.capitalize(),
                                         note=f"Not available for this run: {type(exc).__name__}: {exc}"))
        return _Built(sections, ctx.record.get("scenario", "run"), ctx.record.get("created_utc", ""),
                      ctx.json("rows") or {}, ctx.json("timings") or {})


def _section_html(sec: Section, n_fig: int) -> tuple[str, int]:
    body = [f'<section id="{sec.key}"><h2>{html.escape(sec.title)}</h2>']
    if sec.text:
        body.append(f'<p>{html.escape(sec.text)}</p>')
    if sec.html:
        body.append(sec.html)
    for fig, caption in sec.figures:
        div = pio.to_html(fig, include_plotlyjs=(n_fig == 0), full_html=False, div_id=f"fig-{sec.key}-{n_fig}",
                          default_height=f"{fig.layout.height or 460}px",
                          config={"displaylogo": False, "responsive": True},
                          post_script="window.__reportDone('{plot_id}');")
        body.append(f'<div class="figure">{div}')
        if caption:
            body.append(f'<p class="caption">{html.escape(caption)}</p>')
        body.append("</div>")
        n_fig += 1
    for title, frame in sec.tables:
        body.append(f"<h3>{html.escape(title)}</h3>{table_html(frame, max_rows=200)}")
    if sec.note:
        body.append(sec.note if sec.note.startswith("<") else f'<p class="note">{html.escape(sec.note)}</p>')
    body.append("</section>")
    return "".join(body), n_fig


def render_report(run_dir: str | os.PathLike[str], progress: Progress | None = None) -> tuple[str, int]:
    """The report's HTML text and its number of figures (nothing written)."""
    say = progress or (lambda _m: None)
    t_all = time.perf_counter()
    built = build_sections(run_dir, say)
    say("report: html")
    top, body, toc = [], [], []
    n_fig = 0
    for sec in built.sections:
        text, n_fig = _section_html(sec, n_fig)
        if sec.key == "verdict":     # the verdicts open the report, before the table of contents
            top.append(text)
            continue
        toc.append(f'<li><a href="#{sec.key}">{html.escape(sec.title)}</a></li>')
        body.append(text)
    rows, timings = built.rows, built.timings
    summary = (f"{rows.get('reports_in', 0):,} reports in, {rows.get('reports_aligned', 0):,} aligned, "
               f"{rows.get('reports_rejected', 0):,} rejected; "
               + (f"{rows['confirmed_targets']:,} system targets ({rows.get('tentative_targets', 0):,} tentative, "
                  "clutter-only, not counted); " if "confirmed_targets" in rows
                  else f"{rows.get('targets', 0):,} system targets; ")
               + f"wall time {float(timings.get('wall_s', timings.get('total_s', 0.0))):.1f} s") if rows else ""
    built_at = datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M:%S')
    page = Template(_template("page.html")).substitute(
        title=html.escape(built.scenario), head_script=_template("head.js"),
        css=_template("report.css"), n_figures=n_fig, created=html.escape(built.created[:19].replace('T', ' ')),
        summary=html.escape(summary), built=built_at, seconds=f"{time.perf_counter() - t_all:.1f}",
        verdict="".join(top), toc="".join(toc), body="".join(body))
    return page, n_fig


def build_report(run_dir: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
                 progress: Progress | None = None) -> Path:
    """Write the run's report (default ``RUN_DIR/report.html``) atomically and return its path."""
    page, _n = render_report(run_dir, progress)
    base = Path(run_dir)
    base = base.parent if base.is_file() else base          # RUN_DIR or RUN_DIR/results.duckdb
    target = Path(out) if out is not None else base / REPORT_FILENAME
    return write_text_atomic(target, page)


def figure_count(html_text: str) -> int:
    """Number of figures a report says it holds (``body[data-figures]``)."""
    m = re.search(r'<body[^>]*data-figures="(\d+)"', html_text)
    return int(m.group(1)) if m else 0
