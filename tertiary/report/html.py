"""``tertiary report``: one self-contained HTML file per run (``RUN_DIR/report.html``).

Every figure and table is drawn from the named SQL reports in ``sql/`` (run read-only through
:mod:`tertiary.store.sql_reports`); only the capacity-model curves of figs. 5.2/5.3 come from
:mod:`safety.capacity`. The plotly.js bundle is embedded inline once, so the file opens offline.

The report opens with a **verdict** block: the accuracy of the best picture against the reference
(horizontal and vertical RMSE, with the centralised reference and the best radar beside it), the
safety performance (losses of separation alerted / missed where the safety stage scores them,
else the alert scores against truth) and the requirements pass/fail table when the run holds a
``requirements`` table. The *best picture* is the fused or tracker picture (not the centralised
reference) with the lowest horizontal RMSE (segment ``all``); the *best radar* the radar whose own
track estimates have the lowest horizontal RMSE. In the accuracy and conflict figures these three
are drawn by default; every other trace is in the legend (click to show).

Edge-of-coverage rule: accuracy curves over time leave out epochs whose number of scored samples
N_k is below :data:`MIN_SAMPLE_FRAC` of the median N_k of that curve (at the start and end of
coverage σ(k) rests on a handful of aircraft and is not a result); the rule is applied in SQL
(``min_sample_frac``) and stated in each caption.

Figures (seed numbering, digest §9):

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
terminal-area run gives a few MB (of which plotly.js is about 4.6 MB).

Browser checks: a small script in the page head records every JavaScript error (``error`` and
``unhandledrejection`` events) into ``<pre id="js-errors">`` and ``body[data-js-errors]``;
each figure increments ``body[data-rendered]`` once plotly has drawn it, and
``body[data-figures]`` holds the number of figures in the file.
"""

from __future__ import annotations

import html
import json
import math
import os
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from tertiary.store.sql_reports import open_read_only, run_report
from tertiary.store.run_store import RunStore, write_text_atomic

__all__ = ["REPORT_FILENAME", "MAX_POINTS", "MIN_SAMPLE_FRAC", "build_report", "render_report", "build_sections",
           "figure_count"]

REPORT_FILENAME = "report.html"
#: most points drawn per time-series trace (longer series are thinned evenly)
MAX_POINTS = 2000
#: aircraft shown in the range / range-rate / acceleration figures
KINEMATICS_AIRCRAFT = 3
#: conflicts listed in the conflicts table
CONFLICT_ROWS = 25
#: accuracy curves over time leave out epochs with fewer samples than this fraction of the curve's median
MIN_SAMPLE_FRAC = 0.25
#: the centralised measurement-level reference picture
CENTRALIZED = "centralized"

Progress = Callable[[str], None]

_COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2",
           "#7f7f7f", "#bcbd22"]
_DASHES = ["solid", "dash", "dot", "dashdot", "longdash", "longdashdot"]


# --------------------------------------------------------------------------- sections


@dataclass
class _Section:
    key: str
    title: str
    text: str = ""
    figures: list[tuple[Any, str]] = field(default_factory=list)   # (plotly figure, caption)
    tables: list[tuple[str, pl.DataFrame]] = field(default_factory=list)
    html: str = ""
    note: str = ""


class _Ctx:
    """The run being reported: store, run record and a few derived facts."""

    def __init__(self, store: RunStore, say: Progress):
        self.store = store
        self.say = say
        self.tables = set(store.tables())
        self.record = {k: v for k, v in store.sql("SELECT key, value FROM run").iter_rows()} if "run" in self.tables else {}
        self.scenario = _toml(self.record.get("scenario_toml", ""))

    def q(self, name: str, **params: Any) -> pl.DataFrame:
        return run_report(self.store, name, params)

    @property
    def best(self) -> "_Best":
        """The best picture, the centralised reference and the best radar (computed once)."""
        if not hasattr(self, "_best"):
            self._best = _best_pictures(self)
        return self._best

    def json(self, key: str) -> Any:
        raw = self.record.get(key)
        if raw is None:
            return None
        try:
            return json.loads(raw)
        except json.JSONDecodeError:
            return raw


def _toml(text: str) -> dict:
    try:
        return tomllib.loads(text) if text else {}
    except tomllib.TOMLDecodeError:
        return {}


# --------------------------------------------------------------------------- best picture, reference, radar


@dataclass
class _Best:
    """Accuracy of the pictures (segment ``all``): ``pictures`` has one row per picture
    (picture, stage, horizontal_m, height_m, pos_m); ``picture`` is the best one (lowest
    horizontal RMSE, the centralised reference excluded), ``fused`` the best picture that has
    accuracy curves over time (a fusion method), ``radar`` the best radar's name and
    ``radars`` one row per radar (radar, horizontal_m, height_m, pos_m)."""

    pictures: pl.DataFrame
    radars: pl.DataFrame
    picture: str | None = None
    fused: str | None = None
    radar: str | None = None
    ranked_by: str = "rmse_horizontal_m"
    unranked: list[str] = field(default_factory=list)

    def best_of(self, names: list[str]) -> str | None:
        """The most accurate of ``names`` (the pictures a figure holds), else the first."""
        key = "horizontal_m" if self.ranked_by == "rmse_horizontal_m" else "pos_m"
        ranked = (self.pictures.filter(pl.col("picture").is_in(names) & pl.col(key).is_not_null()
                                       & (pl.col("picture") != CENTRALIZED)).sort(key))
        return ranked["picture"][0] if ranked.height else (names[0] if names else None)


def _best_pictures(ctx: _Ctx) -> _Best:
    acc = ctx.q("accuracy_by_method", segment="all") if "metrics" in ctx.tables else pl.DataFrame()
    cols = {"rmse_horizontal_m": "horizontal_m", "rmse_height_m": "height_m", "rmse_pos_m": "pos_m"}
    if acc.height:
        pictures = acc.select(
            pl.when(pl.col("filter").is_null()).then(pl.col("method"))
            .otherwise(pl.col("method") + "+" + pl.col("filter")).alias("picture"),
            "stage", *[pl.col(c).alias(a) for c, a in cols.items()])
    else:
        pictures = pl.DataFrame(schema={"picture": pl.String, "stage": pl.String, **{a: pl.Float64 for a in cols.values()}})
    radars = _radar_pooled(ctx)
    best = _Best(pictures, radars)
    cand = pictures.filter(pl.col("picture") != CENTRALIZED)
    key = "horizontal_m" if cand["horizontal_m"].is_not_null().any() else "pos_m"
    best.ranked_by = "rmse_horizontal_m" if key == "horizontal_m" else "rmse_pos_m"
    best.unranked = cand.filter(pl.col(key).is_null())["picture"].to_list()
    ranked = cand.filter(pl.col(key).is_not_null()).sort(key)
    if ranked.height:
        best.picture = ranked["picture"][0]
        fus = ranked.filter(pl.col("stage") == "fusion")
        best.fused = fus["picture"][0] if fus.height else None
    if radars.height:
        best.radar = radars.sort("horizontal_m", nulls_last=True)["radar"][0]
    return best


def _radar_pooled(ctx: _Ctx) -> pl.DataFrame:
    """Each radar's pooled RMSE sqrt(mean_k σ²(k)) — the pooling of the metrics table — from
    sql/radar_accuracy_over_time.sql (every epoch, as the metrics pool every epoch)."""
    schema = {"radar": pl.String, "horizontal_m": pl.Float64, "height_m": pl.Float64, "pos_m": pl.Float64}
    if not {"aligned", "truth", "radars"} <= ctx.tables:
        return pl.DataFrame(schema=schema)
    ra = ctx.q("radar_accuracy_over_time")
    if ra.height == 0:
        return pl.DataFrame(schema=schema)
    return (ra.group_by("name").agg(*[(pl.col(c) ** 2).mean().sqrt().alias(a) for c, a in
                                      (("rmse_horizontal_m", "horizontal_m"), ("rmse_height_m", "height_m"),
                                       ("rmse_pos_m", "pos_m"))])
            .rename({"name": "radar"}).sort("horizontal_m").cast(schema))


def _visible(name: str, shown: set[str]) -> bool | str:
    return True if name in shown else "legendonly"


# --------------------------------------------------------------------------- helpers


def _go():
    import plotly.graph_objects as go
    return go


def _arr(values: Any) -> np.ndarray:
    """float32 array (compact base64 in the HTML); nulls become NaN."""
    if isinstance(values, pl.Series):
        values = values.cast(pl.Float64).fill_null(float("nan")).to_numpy()
    return np.asarray(values, dtype=np.float32)


def _thin(frame: pl.DataFrame, max_points: int = MAX_POINTS) -> pl.DataFrame:
    """Every k-th row so that at most ``max_points`` remain (the last row always kept)."""
    n = frame.height
    if n <= max_points:
        return frame
    step = math.ceil(n / max_points)
    idx = pl.int_range(pl.len())
    return frame.filter((idx % step == 0) | (idx == n - 1))


def _layout(fig, title: str, xtitle: str, ytitle: str, height: int = 460, **kw: Any) -> None:
    fig.update_layout(title=dict(text=title, x=0.01), template="plotly_white", height=height,
                      margin=dict(l=70, r=20, t=60, b=55), legend=dict(orientation="v"),
                      hovermode="closest", **kw)
    fig.update_xaxes(title_text=xtitle)
    fig.update_yaxes(title_text=ytitle)


def _radar_names(frame: pl.DataFrame) -> dict[int, str]:
    return {int(r): str(n) for r, n in frame.select("radar_id", "name").unique().iter_rows()}


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if math.isnan(v):
            return "NaN"
        if math.isinf(v):
            return "∞" if v > 0 else "−∞"
        if v == int(v) and abs(v) < 1e15:
            return f"{int(v):,}"
        a = abs(v)
        if a >= 1000:
            return f"{v:,.1f}"
        if a >= 1e-3:
            return f"{v:.4g}"
        return f"{v:.3g}"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, datetime):
        return v.astimezone(timezone.utc).strftime("%Y-%m-%d %H:%M:%S") if v.tzinfo else v.isoformat(sep=" ")
    if isinstance(v, (list, tuple, dict)):
        return json.dumps(v, default=str)
    return str(v)


_BREAK_AFTER = frozenset("_+/,:;=.-")


def _breakable(text: str) -> str:
    """Escaped cell text with line-break opportunities (``<wbr>``) after ``_ + / , : ; = . -``
    and every 16 characters inside longer unbroken runs (hashes, JSON), so that long names and
    values wrap inside their cell instead of widening the table past the page."""
    if len(text) <= 12:
        return html.escape(text)
    out, run = [], 0
    for ch in text:   # table cells only (at most 200 rows per table): not a hot path
        out.append(html.escape(ch))
        run = 0 if ch.isspace() else run + 1
        if run and (ch in _BREAK_AFTER or run >= 16):
            out.append("<wbr>")
            run = 0
    return "".join(out)


def _table_html(frame: pl.DataFrame, max_rows: int | None = None,
                cell_class: dict[str, Callable[[Any], str]] | None = None) -> str:
    """An HTML table (long cells wrap; see _CSS); ``cell_class`` maps a column to a function
    giving the CSS class of each of its cells."""
    if frame.width == 0:
        return '<p class="note">(no columns)</p>'
    rows = frame if max_rows is None else frame.head(max_rows)
    head = "".join(f"<th>{_breakable(c)}</th>" for c in frame.columns)
    extra = [(cell_class or {}).get(c) for c in frame.columns]
    body = []
    for row in rows.iter_rows():
        cells = []
        for v, fn in zip(row, extra):
            cls = ["num"] if isinstance(v, (int, float)) and not isinstance(v, bool) else []
            cls += [html.escape(fn(v))] if fn else []
            attr = f' class="{" ".join(cls)}"' if cls else ""
            text = html.escape(_fmt(v)) if cls[:1] == ["num"] else _breakable(_fmt(v))
            cells.append(f"<td{attr}>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    if not body:
        body.append(f'<tr><td colspan="{frame.width}" class="note">no rows</td></tr>')
    more = ""
    if max_rows is not None and frame.height > max_rows:
        more = f'<p class="note">first {max_rows:,} of {frame.height:,} rows</p>'
    return f'<div class="tablewrap"><table><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table></div>{more}'


# --------------------------------------------------------------------------- verdict


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


def _sec_verdict(ctx: _Ctx) -> _Section:
    sec = _Section("verdict", "Verdict")
    if ctx.record.get("kind") == "evaluation":      # requirements first, then the pictures' accuracy
        sec.html = "\n".join([_verdict_requirements(ctx), _verdict_evaluation(ctx)])
    else:
        sec.html = "\n".join([_verdict_accuracy(ctx), _verdict_safety(ctx), _verdict_requirements(ctx)])
    return sec


def _verdict_evaluation(ctx: _Ctx) -> str:
    cmp = ctx.q("picture_comparison")
    if cmp.height == 0:
        return '<h3>Accuracy</h3><p class="note">No picture could be matched to the reference.</p>'
    best = cmp.row(0, named=True)           # ordered by horizontal RMS
    return (f"<h3>Accuracy</h3><p><b>Most accurate picture: {html.escape(best['method'])}</b> — horizontal RMS "
            f"<b>{_m(best['rmse_horizontal_m'])}</b> (95 % {_m(best['p95_horizontal_m'])}), height RMS "
            f"<b>{_m(best['rmse_height_m'])}</b>, {cmp.height} picture(s) compared below.</p>")


def _verdict_accuracy(ctx: _Ctx) -> str:
    b = ctx.best
    if b.picture is None:
        return ('<h3>Accuracy</h3><p class="note">No accuracy against a reference: the run has no truth '
                '(or no fused picture could be scored).</p>')
    pic = b.pictures.filter(pl.col("picture") == b.picture).row(0, named=True)
    ref = b.pictures.filter(pl.col("picture") == CENTRALIZED)
    ref = ref.row(0, named=True) if ref.height else None
    rad = b.radars.filter(pl.col("radar") == b.radar).row(0, named=True) if b.radar else None
    lines = [f"<b>Best picture: {html.escape(b.picture)}</b> — horizontal RMSE <b>{_m(pic['horizontal_m'])}</b>, "
             f"vertical (height) RMSE <b>{_m(pic['height_m'])}</b> (3-D {_m(pic['pos_m'])})."]
    if ref:
        lines.append(f"Centralised reference ({CENTRALIZED}: one Kalman filter on every radar's measurements, a "
                     f"reference, not a bound): horizontal {_m(ref['horizontal_m'])}, vertical {_m(ref['height_m'])}. "
                     f"The best picture's horizontal error is {_rel(pic['horizontal_m'], ref['horizontal_m'])} "
                     "the reference's.")
    if rad:
        lines.append(f"Best radar alone ({html.escape(b.radar)}, its own track estimates): horizontal "
                     f"{_m(rad['horizontal_m'])}, vertical {_m(rad['height_m'])}. The best picture's horizontal "
                     f"error is {_rel(pic['horizontal_m'], rad['horizontal_m'])} the best radar's.")
    rule = (f"Ranked by {b.ranked_by} over all segments, against simulator truth; RMSE pooled as sqrt(mean over "
            "epochs of σ²(k)), first 20 s of each track left out.")
    if b.unranked:
        more = f" and {len(b.unranked) - 6} more" if len(b.unranked) > 6 else ""
        rule += (f" Not ranked ({len(b.unranked)} pictures without a {b.ranked_by} row in this run): "
                 f"{', '.join(b.unranked[:6])}{more}.")
    rows = [(b.picture, "best picture", pic)] + ([(CENTRALIZED, "centralised reference", ref)] if ref else [])
    rows += [(b.radar, "best radar", rad)] if rad else []
    table = pl.DataFrame({"picture": [r[0] for r in rows], "role": [r[1] for r in rows],
                          "horizontal RMSE (m)": [r[2]["horizontal_m"] for r in rows],
                          "vertical RMSE (m)": [r[2]["height_m"] for r in rows],
                          "3-D RMSE (m)": [r[2]["pos_m"] for r in rows]},
                         schema_overrides={c: pl.Float64 for c in ("horizontal RMSE (m)", "vertical RMSE (m)",
                                                                   "3-D RMSE (m)")})
    return ("<h3>Accuracy of the air picture</h3>" + "".join(f"<p>{ln}</p>" for ln in lines)
            + _table_html(table) + f'<p class="note">{html.escape(rule)}</p>')


_SAFETY_COLS = {  # alert_scores column → plain heading with unit
    "method": "picture", "los_episodes": "losses of separation", "alerted_los": "losses alerted",
    "missed_los": "losses missed", "genuine_alerts": "genuine alerts", "nuisance_alerts": "nuisance alerts",
    "alerts_per_hour": "alerts per hour (1/h)", "warning_median_s": "median warning (s)",
    "warning_p05_s": "5th-percentile warning (s)", "episodes": "true conflicts", "hits": "alerted in time",
    "misses": "missed", "false_alerts": "false alerts", "mean_warning_s": "mean warning (s)",
}


def _verdict_safety(ctx: _Ctx) -> str:
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
    else:
        warn = "n/a" if r["mean_warning_s"] is None else f"{r['mean_warning_s']:.0f} s"
        text = (f"On <b>{html.escape(pick)}</b>: {f(r['episodes'])} true-conflict episodes in truth, "
                f"<b>{f(r['hits'])} alerted in time</b>, <b>{f(r['misses'])} missed</b>; "
                f"<b>{f(r['false_alerts'])} false alerts</b>; mean warning time {warn}.")
        cols = ["method", "episodes", "hits", "misses", "false_alerts", "mean_warning_s"]
    table = scores.select(cols).rename({c: _SAFETY_COLS[c] for c in cols})
    note = ("Scored against truth per picture (sql/alert_scores.sql); the full table with flicker is in the "
            "Conflicts section.")
    return head + f"<p>{text}</p>" + _table_html(table) + f'<p class="note">{note}</p>'


def _verdict_requirements(ctx: _Ctx) -> str:
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
    return head + f"<p>{text}</p>" + _table_html(req, cell_class={"verdict": lambda v: f"verdict-{v}"})


# --------------------------------------------------------------------------- figures


def _sec_map(ctx: _Ctx) -> _Section:
    go = _go()
    sec = _Section("map", "Scenario map (seed fig. 4.4)")
    n_aircraft = ctx.store.sql("SELECT count(DISTINCT truth_id) AS n FROM truth").item() if "truth" in ctx.tables else 0
    duration = float(ctx.scenario.get("duration_s") or 0.0)
    # about 60 000 map points in all: the thinning step grows with traffic and duration
    step = max(1, math.ceil(n_aircraft * max(duration, 1.0) / 60_000)) if n_aircraft else 10
    traj = ctx.q("trajectories", step_s=step)
    sites = ctx.q("radar_sites")
    fig = go.Figure()
    if traj.height:
        # one trace, aircraft separated by NaN gaps
        gap = traj.select("truth_id").with_columns(pl.col("truth_id").shift(-1).ne(pl.col("truth_id")).fill_null(False)
                                                   .alias("end"))
        xs, ys = traj["x_m"].to_numpy() / 1000.0, traj["y_m"].to_numpy() / 1000.0
        ends = np.flatnonzero(gap["end"].to_numpy()) + 1
        x = np.insert(xs, ends, np.nan)
        y = np.insert(ys, ends, np.nan)
        fig.add_trace(go.Scatter(x=_arr(x), y=_arr(y), mode="lines", line=dict(width=1, color="#7f9fbf"),
                                 name=f"trajectories ({traj['truth_id'].n_unique()} aircraft)", hoverinfo="skip"))
        starts = traj.group_by("truth_id", maintain_order=True).first()
        fig.add_trace(go.Scatter(x=_arr(starts["x_m"] / 1000.0), y=_arr(starts["y_m"] / 1000.0), mode="markers",
                                 marker=dict(size=4, color="#1f4e79"), name="start of track",
                                 text=[f"aircraft {i}" for i in starts["truth_id"]], hoverinfo="text"))
    enu = _site_enu(ctx, sites)
    if enu is not None:
        fig.add_trace(go.Scatter(x=_arr(enu[0] / 1000.0), y=_arr(enu[1] / 1000.0), mode="markers+text",
                                 marker=dict(symbol="triangle-up", size=14, color="#d62728"),
                                 text=sites["name"].to_list(), textposition="top center", name="radar sites"))
    else:
        sec.note = "Radar sites not drawn: the run record has no processing-centre origin."
    _layout(fig, "Truth trajectories and radar sites (system frame)", "east x (km)", "north y (km)", height=620)
    fig.update_yaxes(scaleanchor="x", scaleratio=1)
    sec.figures.append((fig, f"Truth positions thinned to one point per aircraft every {step} s "
                             "(sql/trajectories.sql); radar sites from sql/radar_sites.sql converted to the "
                             "system ENU frame."))
    sec.tables.append(("Radar sites", sites))
    return sec


def _site_enu(ctx: _Ctx, sites: pl.DataFrame) -> tuple[np.ndarray, np.ndarray] | None:
    origin = ctx.scenario.get("origin")
    if not origin or len(origin) < 2 or sites.height == 0:
        return None
    from tertiary.core.geo import LocalFrame
    frame = LocalFrame(float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) > 2 else 0.0)
    e, n, _u = frame.from_geodetic(sites["lat_deg"].to_numpy(), sites["lon_deg"].to_numpy(), sites["alt_m"].to_numpy())
    return np.asarray(e), np.asarray(n)


def _small_multiples(n: int, titles: list[str], cols: int = 2):
    """A grid of ``n`` panels (``cols`` wide) sharing the x axis, one title per panel."""
    from plotly.subplots import make_subplots
    cols = max(1, min(cols, n))
    rows = max(1, math.ceil(n / cols))
    fig = make_subplots(rows=rows, cols=cols, shared_xaxes=True, subplot_titles=titles,
                        vertical_spacing=min(0.12, 0.35 / rows), horizontal_spacing=0.08)
    return fig, rows, cols


def _sec_kinematics(ctx: _Ctx) -> _Section:
    go = _go()
    sec = _Section("kinematics", "Range, range rate and acceleration per radar (seed figs. 4.5–4.7)")
    kin = ctx.q("radar_kinematics", max_aircraft=KINEMATICS_AIRCRAFT)
    names = _radar_names(kin) if kin.height else {}
    radars = sorted(names)
    aircraft = sorted(kin["truth_id"].unique().to_list()) if kin.height else []
    specs = [("est_range_m", "Range D(k) (fig. 4.5)", "range D (km)", 1e-3),
             ("est_range_rate_mps", "Range rate V(k) (fig. 4.6)", "range rate V (m/s)", 1.0),
             ("accel_mps2", "Line-of-sight acceleration a(k) = ΔV/Δt (fig. 4.7)", "acceleration a (m/s²)", 1.0)]
    titles = [f"radar {names[r]}" for r in radars] or ["no radar reports"]
    for col, title, ytitle, scale in specs:
        fig, nrows, ncols = _small_multiples(len(titles), titles)
        for i, rid in enumerate(radars):
            row, cc = i // ncols + 1, i % ncols + 1
            for j, ac in enumerate(aircraft):
                part = kin.filter((pl.col("radar_id") == rid) & (pl.col("truth_id") == ac))
                if part.height == 0:
                    continue
                # NaN gaps between local tracks of the same aircraft
                part = _thin(part.sort("local_track_id", "time"))
                brk = np.flatnonzero(np.diff(part["local_track_id"].to_numpy()) != 0) + 1
                x = np.insert(part["t_s"].to_numpy(), brk, np.nan)
                y = np.insert(part[col].cast(pl.Float64).fill_null(float("nan")).to_numpy() * scale, brk, np.nan)
                fig.add_trace(go.Scatter(x=_arr(x), y=_arr(y), mode="lines", name=f"aircraft {ac}",
                                         legendgroup=f"ac{ac}", showlegend=i == 0,
                                         line=dict(color=_COLORS[j % len(_COLORS)], width=1.3)), row=row, col=cc)
        _layout(fig, title + ", one panel per radar", "", "", height=max(300, 250 * nrows + 80))
        fig.update_xaxes(title_text="time t (s)", row=nrows)
        fig.update_yaxes(title_text=ytitle, col=1)
        if col == "accel_mps2" and kin.height:
            # the first seconds of a track (filter transient) would swamp the scale
            lo, hi = kin.select(pl.col(col).quantile(0.005).alias("lo"), pl.col(col).quantile(0.995).alias("hi")).row(0)
            if lo is not None and hi is not None and hi > lo:
                pad = 0.25 * (hi - lo)
                fig.update_yaxes(range=[lo - pad, hi + pad])
        sec.figures.append((fig, ""))
    sec.text = (f"Each radar's own track estimates (est_range_m, est_range_rate_mps) for the first Monte-Carlo "
                f"run and the {len(aircraft)} aircraft seen by the most radars (sql/radar_kinematics.sql, "
                f"{kin.height:,} reports), one panel per radar with the same aircraft colours; the acceleration is "
                "the difference of consecutive range-rate estimates over their time step (axis clipped to the "
                "0.5–99.5 % quantiles, so that track-start transients do not swamp it).")
    return sec


def _bin_s(ctx: _Ctx) -> float:
    duration = float(ctx.scenario.get("duration_s") or 0.0)
    sites = ctx.q("radar_sites")
    scan = sites["scan_period_s"].max() if sites.height else 1.0
    return float(max(1.0, round(max(scan or 1.0, duration / 300.0))))


def _sec_residuals(ctx: _Ctx) -> _Section:
    go = _go()
    sec = _Section("residuals", "Range residuals per radar (seed fig. 4.9)")
    bin_s = _bin_s(ctx)
    res = ctx.q("radar_residuals_over_time", bin_s=bin_s)
    fig = go.Figure()
    for i, (rid, name) in enumerate(sorted(_radar_names(res).items()) if res.height else []):
        part = _thin(res.filter(pl.col("radar_id") == rid))
        color = _COLORS[i % len(_COLORS)]
        fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part["mean_abs_res_m"]), mode="lines",
                                 name=f"{name} mean |ΔD|", line=dict(color=color, width=1.5)))
        fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part["pred_sd_m"]), mode="lines",
                                 name=f"{name} predicted SD", line=dict(color=color, width=1, dash="dot"),
                                 visible="legendonly"))
    _layout(fig, f"Mean |range innovation| per radar, {bin_s:g} s bins", "time t (s)", "|range innovation ΔD| (m)")
    sec.figures.append((fig, "Each radar's own range innovation |res_range_m| averaged over aircraft and runs in "
                             f"{bin_s:g} s bins (sql/radar_residuals_over_time.sql); dotted: mean predicted "
                             "innovation SD (click the legend)."))
    sec.tables.append(("Residual statistics per radar (sql/radar_residuals.sql)", ctx.q("radar_residuals")))
    return sec


def _edge_rule(frac: float = MIN_SAMPLE_FRAC) -> str:
    return (f"Edge-of-coverage rule: an epoch is drawn only if its number of scored samples N_k is at least "
            f"{frac:.0%} of the median N_k of its curve (min_sample_frac = {frac:g} in the SQL report); thinner "
            "epochs, at the start and end of coverage, rest on a handful of aircraft and are not drawn")


def _sec_rmse_time(ctx: _Ctx) -> _Section:
    go = _go()
    from plotly.subplots import make_subplots
    sec = _Section("rmse_time", "Real RMS horizontal and vertical error over time (seed fig. 4.10)")
    b = ctx.best
    radar = ctx.q("radar_accuracy_over_time", min_sample_frac=MIN_SAMPLE_FRAC)
    n_radar_all = ctx.q("radar_accuracy_over_time").height
    panels = (("rmse_horizontal_m", "horizontal"), ("rmse_height_m", "vertical (height)"))
    tert = {m: ctx.q("accuracy_over_time", metric=m, min_sample_frac=MIN_SAMPLE_FRAC) for m, _ in panels}
    n_tert_all = ctx.q("accuracy_over_time", metric=panels[0][0]).height
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.1,
                        subplot_titles=[f"{label.capitalize()} RMS error" for _m, label in panels])
    shown = {b.radar, b.fused, CENTRALIZED} - {None}
    for row, (metric, _label) in enumerate(panels, start=1):
        for i, (rid, name) in enumerate(sorted(_radar_names(radar).items()) if radar.height else []):
            part = _thin(radar.filter(pl.col("radar_id") == rid))
            fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part[metric]), mode="lines",
                                     name=f"radar {name}" + (" (best radar)" if name == b.radar else ""),
                                     legendgroup=f"radar {name}", showlegend=row == 1,
                                     visible=_visible(name, shown),
                                     line=dict(color=_COLORS[i % len(_COLORS)], width=1.2, dash="dot")), row=row, col=1)
        frame = tert[metric]
        methods = frame["method"].unique(maintain_order=True).to_list() if frame.height else []
        for k, m in enumerate(methods):
            part = _thin(frame.filter(pl.col("method") == m))
            main = m == b.fused
            label = m + (" (best picture)" if m == b.picture else " (best fused picture)" if main else
                         " (centralised reference)" if m == CENTRALIZED else "")
            fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part["value"]), mode="lines", name=label,
                                     legendgroup=m, showlegend=row == 1, visible=_visible(m, shown),
                                     line=dict(color="black" if main else "#6a3d9a" if m == CENTRALIZED else None,
                                               width=2.2 if main else 1.4,
                                               dash="solid" if main or m == CENTRALIZED else _DASHES[k % len(_DASHES)])),
                          row=row, col=1)
    _layout(fig, "σ(k) of each picture and of each radar's own tracks", "", "", height=720)
    fig.update_yaxes(title_text="horizontal RMSE (m)", row=1, col=1)
    fig.update_yaxes(title_text="vertical RMSE (m)", row=2, col=1)
    fig.update_xaxes(title_text="time t (s)", row=2, col=1)
    left_out = f"{n_tert_all - tert[panels[0][0]].height:,} of {n_tert_all:,} picture epochs and " \
               f"{n_radar_all - radar.height:,} of {n_radar_all:,} radar epochs left out"
    best_note = "" if b.picture == b.fused or b.picture is None else (
        f" The best picture overall, {b.picture}, is a tracker picture without per-epoch accuracy; its fusion "
        f"input's best, {b.fused}, is drawn instead.")
    sec.figures.append((fig, "Drawn by default: the best fused picture (black), the centralised reference (purple) "
                             "and the best radar (dotted); every other picture and radar is in the legend (click to "
                             "show). Per-radar curves: each radar's own track estimates aligned to the common epochs "
                             "(sql/radar_accuracy_over_time.sql); picture curves: accuracy_by_epoch "
                             "(sql/accuracy_over_time.sql); N − 1 denominator over the aircraft and runs at each "
                             f"epoch, first 20 s of each track left out. {_edge_rule()} ({left_out})."
                        + best_note))
    return sec


def _sec_post_prior(ctx: _Ctx) -> _Section:
    go = _go()
    from plotly.subplots import make_subplots
    sec = _Section("post_prior", "A-posteriori versus a-priori weights (seed fig. 4.11)")
    pp = ctx.q("aposteriori_vs_apriori", min_sample_frac=MIN_SAMPLE_FRAC)
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.08, row_heights=[0.6, 0.4])
    colors = {"aposteriori": "#d62728", "aposteriori_seed": "#ff7f0e", "apriori": "#1f77b4", "arithmetic": "#2ca02c"}
    drawn = set()
    for (post, prior), part in (pp.group_by("posterior", "prior", maintain_order=True) if pp.height else []):
        part = _thin(part.sort("epoch"))
        for m, col in ((post, "sigma_post"), (prior, "sigma_prior")):
            if m in drawn:
                continue
            drawn.add(m)
            fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part[col]), mode="lines", name=f"σ {m}",
                                     line=dict(color=colors.get(m), width=1.4)), row=1, col=1)
        fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part["gain"] * 100.0), mode="lines",
                                 name=f"gain {post} vs {prior}",
                                 line=dict(color=colors.get(post), dash="solid" if prior == "apriori" else "dot",
                                           width=1.1)), row=2, col=1)
    _layout(fig, "Tertiary RMS range error with a-posteriori and a-priori weights, and the gain", "", "", height=620)
    fig.update_yaxes(title_text="σ range (m)", row=1, col=1)
    fig.update_yaxes(title_text="1 − σ_post/σ_prior (%)", row=2, col=1)
    fig.update_xaxes(title_text="time t (s)", row=2, col=1)
    sec.figures.append((fig, "From accuracy_by_epoch (sql/aposteriori_vs_apriori.sql); gain > 0 where the "
                             "a-posteriori weights beat the reference (solid: a-priori weights, dotted: "
                             f"arithmetic 0.5/0.5). {_edge_rule()}."))
    sec.tables.append((f"Gain summary, same edge rule (sql/aposteriori_gain.sql, min_sample_frac = {MIN_SAMPLE_FRAC:g})",
                       ctx.q("aposteriori_gain", min_sample_frac=MIN_SAMPLE_FRAC)))
    return sec


def _sec_accuracy(ctx: _Ctx) -> _Section:
    go = _go()
    from plotly.subplots import make_subplots
    sec = _Section("accuracy", "Accuracy by picture, filter and segment")
    acc = ctx.q("accuracy_by_method")
    b = ctx.best
    pic = (pl.when(pl.col("filter").is_null()).then(pl.col("method"))
           .otherwise(pl.col("method") + "+" + pl.col("filter")).alias("picture"))
    rows = acc.with_columns(pic) if acc.height else acc
    # one x position per picture, ordered by horizontal RMSE (segment all): best first
    # only pictures with a horizontal or vertical figure get a slot (tracker rows may lack them)
    drawn = b.pictures.filter(pl.col("horizontal_m").is_not_null() | pl.col("height_m").is_not_null())
    order = drawn.sort(["horizontal_m", "pos_m"], nulls_last=True)["picture"].to_list()
    missing = b.pictures.filter(~pl.col("picture").is_in(order))["picture"].to_list()
    if rows.height:
        rows = rows.filter(pl.col("picture").is_in(order))
    fig = make_subplots(rows=1, cols=2, shared_yaxes=False, horizontal_spacing=0.08,
                        subplot_titles=["Horizontal RMS error", "Vertical (height) RMS error"])
    for i, seg in enumerate(["all", "straight", "turn"]):
        part = rows.filter(pl.col("segment") == seg) if rows.height else rows
        if part.height == 0:
            continue
        for col, (metric, _title) in enumerate((("rmse_horizontal_m", ""), ("rmse_height_m", "")), start=1):
            fig.add_trace(go.Bar(x=part["picture"].to_list(), y=_arr(part[metric]), name=f"segment {seg}",
                                 legendgroup=seg, showlegend=col == 1, marker_color=_COLORS[i],
                                 visible=True if seg == "all" else "legendonly"), row=1, col=col)
    _layout(fig, "Real RMS error of every picture (fusion methods, and trackers as method+filter)", "", "",
            height=560, barmode="group")
    fig.update_xaxes(categoryorder="array", categoryarray=order, tickangle=-40)
    fig.update_yaxes(title_text="horizontal RMSE (m)", row=1, col=1)
    fig.update_yaxes(title_text="vertical RMSE (m)", row=1, col=2)
    best = f"best picture: {b.picture}; " if b.picture else ""
    sec.figures.append((fig, f"From the metrics table (sql/accuracy_by_method.sql), pictures ordered by horizontal "
                             f"RMSE, segment all ({best}the centralised measurement-level filter, {CENTRALIZED}, is a "
                             "reference, not a bound); straight and turn segments are in the legend."
                             + (f" Not drawn ({len(missing)} pictures without horizontal and vertical rows in this "
                                f"run): {', '.join(missing)}." if missing else "")))
    sec.tables.append(("RMSE by picture, filter and segment, in metres (sql/accuracy_by_method.sql)", acc))
    return sec


def _sec_quality(ctx: _Ctx) -> _Section:
    sec = _Section("quality", "Association, track and cluster quality")
    sec.tables.append(("Association quality (sql/association_quality.sql)", ctx.q("association_quality")))
    sec.tables.append(("Track quality (sql/track_quality.sql)", ctx.q("track_quality")))
    sec.tables.append(("Cluster statistics (sql/cluster_statistics.sql)", ctx.q("cluster_statistics")))
    return sec


def _sec_conflicts(ctx: _Ctx) -> _Section:
    go = _go()
    from plotly.subplots import make_subplots
    sec = _Section("conflicts", "Conflicts")
    tl = ctx.q("conflict_timeline")
    b = ctx.best
    methods = tl["method"].unique(maintain_order=True).to_list() if tl.height else []
    main = b.best_of(methods)
    shown = {main, CENTRALIZED}
    fig = make_subplots(rows=2, cols=1, shared_xaxes=True, vertical_spacing=0.1,
                        subplot_titles=["Aircraft pairs in alert at each epoch", "New alerts per minute"])
    for i, m in enumerate(methods):
        part = tl.filter(pl.col("method") == m)
        minute = (part.with_columns((pl.col("t_s") // 60.0 * 60.0).alias("t0"))
                  .group_by("t0").agg(pl.col("new_alerts").sum()).sort("t0"))
        color = "black" if m == main else _COLORS[i % len(_COLORS)]
        label = m + (" (best picture)" if m == main else " (centralised reference)" if m == CENTRALIZED else "")
        part = _thin(part)
        fig.add_trace(go.Scatter(x=_arr(part["t_s"]), y=_arr(part["alerts"]), mode="lines", name=label,
                                 legendgroup=m, visible=_visible(m, shown),
                                 line=dict(color=color, width=1.2, shape="hv")), row=1, col=1)
        # per whole minute of the run: the rate is the count in that minute (alerts/min)
        fig.add_trace(go.Scatter(x=_arr(minute["t0"] + 30.0), y=_arr(minute["new_alerts"]), mode="lines+markers",
                                 name=label, legendgroup=m, showlegend=False, visible=_visible(m, shown),
                                 marker=dict(size=4), line=dict(color=color, width=1.2)), row=2, col=1)
    _layout(fig, "Conflict alerts over time, per picture", "", "", height=620)
    fig.update_yaxes(title_text="pairs in alert (pairs)", row=1, col=1)
    fig.update_yaxes(title_text="new alerts per minute (1/min)", row=2, col=1)
    fig.update_xaxes(title_text="time t (s)", row=2, col=1)
    sec.figures.append((fig, "Conflict prediction (5.10)–(5.17) on every picture (sql/conflict_timeline.sql). Top: "
                             "pairs in alert at each epoch; bottom: alerts that start (pair not in alert at its "
                             "previous epoch) counted per minute of the run, drawn at the middle of the minute. Drawn "
                             "by default: the best picture and the centralised reference; the others are in the "
                             "legend." if methods else "No aircraft pairs were evaluated (single-aircraft scenario?)."))
    sec.tables.append(("Alert scores against truth (sql/alert_scores.sql)", ctx.q("alert_scores")))
    conflicts = ctx.q("conflicts")
    sec.tables.append((f"Most severe conflicts (sql/conflicts.sql; {conflicts.height:,} alerted pairs)",
                       conflicts.head(CONFLICT_ROWS)))
    return sec


EVAL_BAR_METRICS = (("rmse_horizontal_m", "horizontal RMS"), ("p95_horizontal_m", "horizontal p95"),
                    ("along_track_rms_m", "along-track RMS"), ("across_track_rms_m", "across-track RMS"),
                    ("rmse_height_m", "height RMS"))


def _sec_evaluation(ctx: _Ctx) -> _Section:
    """The evaluation stage (tertiary.evaluation.evaluate): pictures side by side, and the horizontal RMS
    by altitude band, range ring and flight phase."""
    go = _go()
    sec = _Section("evaluation", "Pictures against the reference (evaluation stage)")
    cmp = ctx.q("picture_comparison")
    if cmp.height == 0:
        sec.note = "Not computed in this run: no picture was scored by the evaluation stage."
        return sec
    fig = go.Figure()
    for i, (metric, label) in enumerate(EVAL_BAR_METRICS):
        if metric in cmp.columns:
            fig.add_trace(go.Bar(x=cmp["method"].to_list(), y=_arr(cmp[metric]), name=label,
                                 marker_color=_COLORS[i % len(_COLORS)]))
    _layout(fig, "Position errors per picture", "", "error (m)", barmode="group")
    sec.figures.append((fig, "tertiary.evaluation.evaluate: every picture matched once to the reference (tertiary.evaluation.matching:"
                             " interpolated reference, 1 NM horizontal / 300 m vertical gate, one-to-one per epoch), errors split into "
                             "horizontal, along-track, across-track and height (sql/picture_comparison.sql)."))
    sec.tables.append(("Pictures compared (sql/picture_comparison.sql)", cmp))
    by = ctx.store.sql("SELECT method, segment, value FROM metrics WHERE stage = 'evaluation' "
                       "AND metric = 'rmse_horizontal_m' ORDER BY segment")
    if by.height:
        wide = by.pivot(on="method", index="segment", values="value", aggregate_function="first")
        sec.tables.append(("Horizontal RMS (m) by altitude band, range ring from the nearest radar and flight "
                           "phase", wide))
    return sec


STCA_WARNING_S = 30.0   # the warning requirement the curves are drawn for (issue 11: ≥ 30 s)


def _sec_stca(ctx: _Ctx) -> _Section:
    """Trade-off curves: losses alerted with ≥ 30 s warning against nuisance + false alerts per
    hour, covariance thresholds (by confidence) beside fixed thresholds, per look-ahead."""
    go = _go()
    from plotly.subplots import make_subplots
    from safety.alerts import compare_at_equal_nuisance
    sec = _Section("stca", "STCA performance curves")
    curve = ctx.q("stca_tradeoff", warning_s=STCA_WARNING_S)
    if curve.height == 0:
        sec.note = ("Not computed in this run: the curves need truth and a safety stage with look-aheads "
                    "(PipelineConfig.stca_lookaheads_s).")
        return sec
    looks = sorted(curve["t_thr_s"].unique().to_list())
    methods = curve["method"].unique(maintain_order=True).to_list()
    main = ctx.best.best_of(methods) or methods[0]
    fig = make_subplots(rows=1, cols=len(looks), shared_yaxes=True,
                        subplot_titles=[f"look-ahead T = {t:g} s" for t in looks])
    for c, t in enumerate(looks, start=1):
        for i, m in enumerate(methods):
            color = "black" if m == main else _COLORS[i % len(_COLORS)]
            for mode, dash in (("covariance", "solid"), ("fixed", "dash")):
                part = curve.filter((pl.col("method") == m) & (pl.col("t_thr_s") == t)
                                    & (pl.col("threshold_mode") == mode)).sort("nuisance_false_per_hour")
                label = f"{m} — {mode}" + (" (best picture)" if m == main else "")
                fig.add_trace(go.Scatter(
                    x=_arr(part["nuisance_false_per_hour"]), y=_arr(part["alerted_fraction"] * 100.0),
                    mode="lines+markers", name=label, legendgroup=label, showlegend=c == 1,
                    visible=_visible(m, {main}), line=dict(color=color, dash=dash, width=1.4),
                    text=[f"{'confidence' if mode == 'covariance' else 'fixed term'} {v:g}" for v in part["parameter"]],
                    hovertemplate="%{text}: %{x:.0f} /h, %{y:.0f} %<extra></extra>"), row=1, col=c)
    _layout(fig, f"Losses of separation alerted with ≥ {STCA_WARNING_S:g} s warning against nuisance + false "
                 "alerts", "", "", height=480)
    for c in range(1, len(looks) + 1):
        fig.update_xaxes(title_text="nuisance + false alerts per hour (1/h)", row=1, col=c)
    fig.update_yaxes(title_text="losses alerted in time (%)", row=1, col=1)
    par = {m: curve.filter(pl.col("threshold_mode") == m)["parameter"] for m in ("covariance", "fixed")}
    span = {m: f"{p.min():g} … {p.max():g}" if p.len() else "none" for m, p in par.items()}
    sec.figures.append((fig, "Each point is one setting of the whole safety stage on the picture (sql/stca_tradeoff.sql,"
                             f" metrics stage safety_tradeoff): solid — thresholds from the track covariance at "
                             f"confidence {span['covariance']}; dashed — fixed thresholds with an estimation term of "
                             f"{span['fixed']} m (vertical scaled alike). Up and to the left is better. Drawn by "
                             "default: the best picture; the others are in the legend."))
    t_cmp = 105.0 if 105.0 in looks else looks[-1]
    cmp = compare_at_equal_nuisance(curve.with_columns(pl.col("warning_s").cast(pl.Float64)),
                                    warning_s=STCA_WARNING_S, t_thr_s=t_cmp)
    wide = cmp.pivot(on="threshold_mode", index=["method", "nuisance_false_per_hour"], values="alerted_fraction")
    # the other reading of the same curves: the lowest alert rate at which a family still alerts
    # ≥ 95 % of the losses in time (a family that never does is null)
    need = (curve.filter((pl.col("t_thr_s") == t_cmp) & (pl.col("alerted_fraction") >= 0.95))
            .group_by("method", "threshold_mode").agg(pl.col("nuisance_false_per_hour").min())
            .pivot(on="threshold_mode", index="method", values="nuisance_false_per_hour"))
    wide = wide.with_columns(*(pl.lit(None, pl.Float64).alias(c) for c in ("covariance", "fixed") if c not in wide.columns))
    need = need.with_columns(*(pl.lit(None, pl.Float64).alias(c) for c in ("covariance", "fixed") if c not in need.columns))
    table = wide.join(need, on="method", how="left", suffix="_rate").select(
        pl.col("method").alias("picture"),
        pl.col("nuisance_false_per_hour").alias("rate compared (1/h): covariance at 0.95"),
        pl.col("covariance").alias("alerted in time at that rate, covariance (fraction)"),
        pl.col("fixed").alias("alerted in time at that rate, fixed (fraction)"),
        pl.col("covariance_rate").alias("lowest rate with ≥ 95 % alerted in time, covariance (1/h)"),
        pl.col("fixed_rate").alias("lowest rate with ≥ 95 % alerted in time, fixed (1/h)"))
    sec.tables.append((f"Covariance against fixed thresholds (T = {t_cmp:g} s, warning ≥ {STCA_WARNING_S:g} s): "
                       "alerted fraction at equal nuisance + false rate (empty where a family does not reach that "
                       "rate: no extrapolation), and the alert rate each family needs to alert 95 % in time",
                       table))
    return sec


def _sec_ppob(ctx: _Ctx) -> _Section:
    go = _go()
    from safety.capacity import V_BC_M3, V_ZO_M3, ppob_curves
    sec = _Section("ppob", "Conflict probability against traffic (seed fig. 5.2)")
    sigmas = (50.0, 100.0, 200.0)
    cur = ppob_curves(n=tuple(range(2, 201)), sigmas=sigmas)
    fig = go.Figure()
    dashes = {"seed": "solid", "sound_one": "dash", "sound_any": "dot"}
    for i, s in enumerate(sigmas):
        for model in ("seed", "sound_one", "sound_any"):
            part = cur.filter((pl.col("sigma_m") == s) & (pl.col("model") == model))
            p = part.select(pl.when(pl.col("valid") & (pl.col("p") > 0)).then(pl.col("p"))).to_series()
            fig.add_trace(go.Scatter(x=_arr(part["n"]), y=_arr(p), mode="lines", name=f"σ = {s:g} m, {model}",
                                     line=dict(color=_COLORS[i], dash=dashes[model], width=1.5)))
    _layout(fig, "P_pob against the number of aircraft n", "number of aircraft n (aircraft)",
            "probability of a conflict P_pob (dimensionless)")
    fig.update_yaxes(type="log", exponentformat="power")
    sec.figures.append((fig, f"safety.capacity.ppob_curves with V_zo = {V_ZO_M3:.0e} m³ and V_BC = {V_BC_M3:g} m³: "
                             "seed = (5.21) as printed, drawn only where valid ((n − 1)V_ob < V_zo/2; it has a "
                             "pole beyond); sound_one / sound_any = the sounder model (conflict radius 12σ), one "
                             "given aircraft / any pair."))
    return sec


def _sec_capacity(ctx: _Ctx) -> _Section:
    go = _go()
    from safety.capacity import CAPACITY_V_ZO_M3, V_ZO_M3, capacity_curve, nmax_seed, nmax_sound
    sec = _Section("capacity", "Capacity against accuracy (seed fig. 5.3)")
    cap = ctx.q("capacity_by_method")
    p_run = float(cap["p_star"].drop_nulls()[0]) if cap.height and cap["p_star"].drop_nulls().len() else 1e-3
    settings = [(p_run, CAPACITY_V_ZO_M3), (1e-6, V_ZO_M3)]
    sigmas = np.arange(10.0, 201.0, 2.0)
    fig = go.Figure()
    measured = cap.filter(pl.col("sigma_m").is_not_null() & (pl.col("stage") == "fusion")) if cap.height else cap
    for i, (p_star, v_zo) in enumerate(settings):
        curve = capacity_curve(sigmas, p_star=p_star, v_zo=v_zo)
        for model, dash in (("seed", "solid"), ("sound", "dash")):
            part = curve.filter(pl.col("model") == model)
            fig.add_trace(go.Scatter(x=_arr(part["sigma_m"]), y=_arr(part["n_max"]), mode="lines",
                                     name=f"{model}: P* = {p_star:g}, V_zo = {v_zo:.0e} m³",
                                     line=dict(color=_COLORS[i], dash=dash, width=1.6)))
            if measured.height:
                s = measured["sigma_m"].to_numpy()
                if i == 0:   # the run's own capacity rows (metrics table)
                    n = measured["n_max_seed" if model == "seed" else "n_max_sound"].to_numpy()
                else:
                    n = nmax_seed(s, p_star, v_zo=v_zo) if model == "seed" else nmax_sound(s, p_star, v_zo=v_zo)
                fig.add_trace(go.Scatter(x=_arr(s), y=_arr(n), mode="markers",
                                         name=f"measured ({model}, P* = {p_star:g})",
                                         marker=dict(color=_COLORS[i], symbol="circle" if model == "seed" else "diamond",
                                                     size=9, line=dict(color="black", width=0.5)),
                                         text=measured["method"].to_list(),
                                         hovertemplate="%{text}: σ = %{x:.1f} m, n_max = %{y}<extra></extra>"))
    _layout(fig, "Largest number of aircraft n_max against the RMS error σ", "RMS error σ (m)",
            "largest number of aircraft n_max (aircraft)")
    fig.update_xaxes(type="log")
    fig.update_yaxes(type="log")
    sec.figures.append((fig, f"safety.capacity.capacity_curve for the run's P* = {p_run:g} with V_zo = "
                             f"{CAPACITY_V_ZO_M3:.0e} m³ (a 100 km × 100 km × 10 km zone, as in the metrics table; "
                             "n_max ∝ σ⁻³) and for the printed P* = 1e-6, V_zo = 1e12 m³, which admits a single "
                             "aircraft at every realistic σ, as the digest notes. The seed model (5.18)–(5.21) is "
                             "drawn as printed and is illustrative (odds-shaped); the sounder model beside it. "
                             "Markers: each fusion method's measured RMSE σ (rmse_range_m, segment all) and its "
                             "n_max; the table adds P(n) with a fixed number of aircraft, which varies continuously "
                             "with σ (sql/capacity_by_method.sql)."))
    sec.tables.append(("Capacity by method (sql/capacity_by_method.sql)", cap))
    return sec


def _sec_metadata(ctx: _Ctx) -> _Section:
    sec = _Section("metadata", "Run metadata")
    parts = []
    kv = [("scenario", ctx.record.get("scenario", "")), ("created (UTC)", ctx.record.get("created_utc", "")),
          ("database", str(ctx.store.path))]
    notes = ctx.json("notes") or []
    if notes:
        kv.append(("notes", "; ".join(map(str, notes))))
    parts.append(_table_html(pl.DataFrame({"item": [k for k, _ in kv], "value": [str(v) for _, v in kv]})))
    for key, title in (("versions", "Versions"), ("fingerprints", "Input fingerprints")):
        d = ctx.json(key)
        if isinstance(d, dict):
            parts.append(f"<h3>{title}</h3>" + _table_html(
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


_SECTIONS: list[tuple[str, Callable[[_Ctx], _Section]]] = [
    ("verdict", _sec_verdict),
    ("scenario map", _sec_map),
    ("range, rate, acceleration", _sec_kinematics),
    ("residuals", _sec_residuals),
    ("RMSE over time", _sec_rmse_time),
    ("a-posteriori vs a-priori", _sec_post_prior),
    ("accuracy", _sec_accuracy),
    ("evaluation", _sec_evaluation),
    ("quality", _sec_quality),
    ("conflicts", _sec_conflicts),
    ("STCA curves", _sec_stca),
    ("P_pob", _sec_ppob),
    ("capacity", _sec_capacity),
    ("metadata", _sec_metadata),
]


_EVAL_SECTIONS = [("verdict", _sec_verdict), ("evaluation", _sec_evaluation), ("metadata", _sec_metadata)]


# --------------------------------------------------------------------------- HTML


_HEAD_SCRIPT = """
(function () {
  var errors = [];
  function show() {
    var el = document.getElementById('js-errors');
    if (!el || !document.body) { return; }
    el.textContent = errors.join('\\n');
    el.hidden = errors.length === 0;
    document.body.dataset.jsErrors = String(errors.length);
  }
  function record(msg) { errors.push(String(msg)); show(); }
  window.addEventListener('error', function (e) {
    record('error: ' + (e.message || e) + ' (' + (e.filename || '') + ':' + (e.lineno || 0) + ')');
  });
  window.addEventListener('unhandledrejection', function (e) {
    var r = e.reason;
    record('unhandled rejection: ' + ((r && (r.stack || r.message)) || r));
  });
  document.addEventListener('DOMContentLoaded', show);
  window.__reportRendered = 0;
  window.__reportDone = function (id) {
    var el = document.getElementById(id);
    if (el) { el.dataset.rendered = '1'; }
    window.__reportRendered += 1;
    document.body.dataset.rendered = String(window.__reportRendered);
  };
})();
"""

_CSS = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 0 auto; max-width: 1300px;
       padding: 0 24px 60px; color: #1b1f24; }
h1 { margin-top: 28px; } h2 { border-bottom: 1px solid #d0d7de; padding-bottom: 4px; margin-top: 40px; }
h3 { margin-bottom: 6px; }
nav ol { columns: 2; }
.caption, .note { color: #57606a; font-size: 0.9em; }
.figure { margin: 14px 0 22px; }
/* tables never clip: long cells wrap (names, JSON, reasons), wide tables shrink to the page */
.tablewrap { max-width: 100%; }
table { border-collapse: collapse; font-size: 0.85em; margin: 6px 0 14px; max-width: 100%; table-layout: auto; }
th, td { border: 1px solid #d0d7de; padding: 3px 6px; overflow-wrap: break-word; white-space: normal;
         vertical-align: top; }
th { background: #f6f8fa; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.verdict-pass { background: #dafbe1; } td.verdict-fail { background: #ffebe9; font-weight: bold; }
td.verdict-insufficient { background: #fff8c5; }
#verdict { border: 2px solid #1f6feb; border-radius: 6px; padding: 4px 18px 10px; background: #f6faff; }
#verdict h2 { margin-top: 12px; border-bottom: none; }
pre { background: #f6f8fa; padding: 10px; white-space: pre-wrap; overflow-wrap: anywhere; font-size: 0.8em; }
#js-errors { color: #b00020; background: #fff0f0; }
@media print {
  body { max-width: none; padding: 0; font-size: 10pt; }
  nav, .modebar-container { display: none !important; }
  section { break-before: auto; }
  h2, h3 { break-after: avoid; }
  .figure { break-inside: avoid; }
  table { font-size: 8pt; width: 100%; }
  thead { display: table-header-group; }   /* repeat the header on every printed page */
  tr { break-inside: avoid; }
  details { display: block; } details > pre { display: block; }
  #verdict { break-after: page; }
}
"""


@dataclass
class _Built:
    """The report's sections and the run facts of its header."""

    sections: list[_Section]
    scenario: str
    created: str
    rows: dict
    timings: dict


def build_sections(run_dir: str | os.PathLike[str], progress: Progress | None = None) -> _Built:
    """Every section of the report (plotly figures, tables, HTML), verdict first; a section
    whose data is missing holds a "Not available" note instead of failing the report."""
    say = progress or (lambda _m: None)
    sections: list[_Section] = []
    with open_read_only(run_dir) as store:
        ctx = _Ctx(store, say)
        # a run of `tertiary evaluate` holds pictures and a reference, no pipeline stages
        sections_of_run = _EVAL_SECTIONS if ctx.record.get("kind") == "evaluation" else _SECTIONS
        for label, build in sections_of_run:
            say(f"report: {label}")
            try:
                sections.append(build(ctx))
            except Exception as exc:   # one missing table must not lose the whole report
                sections.append(_Section(build.__name__.removeprefix("_sec_"), label.capitalize(),
                                         note=f"Not available for this run: {type(exc).__name__}: {exc}"))
        return _Built(sections, ctx.record.get("scenario", "run"), ctx.record.get("created_utc", ""),
                      ctx.json("rows") or {}, ctx.json("timings") or {})


def _section_html(sec: _Section, n_fig: int) -> tuple[str, int]:
    import plotly.io as pio
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
        body.append(f"<h3>{html.escape(title)}</h3>{_table_html(frame, max_rows=200)}")
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
    scenario = built.scenario
    page = f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>tertiary report: {html.escape(scenario)}</title>
<script>{_HEAD_SCRIPT}</script>
<style>{_CSS}</style>
</head>
<body data-figures="{n_fig}" data-rendered="0" data-js-errors="0">
<pre id="js-errors" hidden></pre>
<h1>Tertiary processing report: {html.escape(scenario)}</h1>
<p>Run created {html.escape(built.created)} UTC. {html.escape(summary)}. Report built
{datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M:%S')} UTC in {time.perf_counter() - t_all:.1f} s from the named SQL
reports in <code>sql/</code> (run them with <code>tertiary sql RUN_DIR NAME</code>).</p>
{''.join(top)}
<nav><ol>{''.join(toc)}</ol></nav>
{''.join(body)}
</body>
</html>
"""
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
    import re
    m = re.search(r'<body[^>]*data-figures="(\d+)"', html_text)
    return int(m.group(1)) if m else 0
