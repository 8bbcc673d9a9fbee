"""Runs side by side (``tertiary compare``): each picture's accuracy and safety figures and each
requirement's verdict per run, with the deltas to the first run and the changes of verdict, what
differs between the runs (dataset, scenario, configuration) said first, as one table
(:func:`compare_table`, for scripts) and one self-contained HTML page (:func:`write_compare`).

The first run is the baseline: ``Δ <run>`` = that run's value − the first run's. A delta is
*better* or *worse* by the quantity's direction (:data:`BETTER`: lower RMSE, fewer missed
losses and false alerts, longer warnings are better); quantities without a direction (counts of
losses in truth, genuine alerts) are only marked as changed.
"""

from __future__ import annotations

import html
import json
import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import plotly.graph_objects as go
import polars as pl

from tertiary.core.errors import DataError, OptionError
from tertiary.report.common import COLORS, Ctx, breakable, fmt_cell, lean_template
from tertiary.report.episodes import figure_div, page_html
from tertiary.runtime.windows import incomplete_message
from tertiary.store.files import write_text_atomic
from tertiary.store.sql_reports import open_read_only

__all__ = ["BETTER", "RunFacts", "compare_table", "differences", "headline", "load_runs", "render_compare",
           "summary_lines", "verdict_changes", "write_compare"]

#: quantity → +1 when higher is better, −1 when lower is better (others: no direction)
BETTER: dict[str, int] = {
    "horizontal RMSE (m)": -1, "vertical RMSE (m)": -1, "3-D RMSE (m)": -1,
    "losses alerted": 1, "losses missed": -1, "nuisance alerts": -1, "false alerts": -1,
    "alerts per hour (1/h)": -1, "median warning (s)": 1, "5th-percentile warning (s)": 1,
    "picture-induced alerts": -1, "picture-induced missed losses": -1, "wall time (s)": -1,
}

_ACCURACY = {"horizontal_m": "horizontal RMSE (m)", "height_m": "vertical RMSE (m)", "pos_m": "3-D RMSE (m)"}
_SAFETY = {"los_episodes": "losses of separation", "alerted_los": "losses alerted", "missed_los": "losses missed",
           "genuine_alerts": "genuine alerts", "nuisance_alerts": "nuisance alerts", "false_alerts": "false alerts",
           "alerts_per_hour": "alerts per hour (1/h)", "warning_median_s": "median warning (s)",
           "warning_p05_s": "5th-percentile warning (s)", "alerts_picture_induced": "picture-induced alerts",
           "missed_los_picture_induced": "picture-induced missed losses"}


@dataclass
class RunFacts:
    """One run to compare: its label, directory, run record and the long table of its figures
    (section, picture, quantity, value, verdict)."""

    label: str
    path: Path
    record: dict[str, str]
    figures: pl.DataFrame
    best: str | None = None

    def json(self, key: str) -> Any:
        try:
            return json.loads(self.record.get(key, "null"))
        except json.JSONDecodeError:
            return self.record.get(key)


_LONG = {"section": pl.String, "picture": pl.String, "quantity": pl.String, "value": pl.Float64,
         "verdict": pl.String}


def _long(frame: pl.DataFrame, section: str, picture: str, names: dict[str, str]) -> pl.DataFrame:
    cols = [c for c in names if c in frame.columns]
    if frame.height == 0 or not cols:
        return pl.DataFrame(schema=_LONG)
    return (frame.select(pl.col(picture).alias("picture"), *[pl.col(c).cast(pl.Float64) for c in cols])
            .unpivot(index="picture", variable_name="quantity", value_name="value")
            .with_columns(pl.lit(section).alias("section"), pl.col("quantity").replace_strict(names),
                          pl.lit(None, pl.String).alias("verdict"))
            .select(list(_LONG)))


def _requirement(columns: list[str]) -> pl.Expr:
    """A requirement's name with its rule ("H-RMS: rmse_horizontal_m <= 350 (range:0-50km)")."""
    if not {"metric", "op", "threshold"} <= set(columns):
        return pl.col("requirement")
    rule = pl.format("{}: {} {} {}", "requirement", "metric", "op", pl.col("threshold").round(6))
    if "breakdown" not in columns:
        return rule
    part = pl.when(pl.col("breakdown").is_null() | (pl.col("breakdown") == "all")).then(pl.lit("")).otherwise(
        pl.format(" ({})", "breakdown"))
    return pl.concat_str(rule, part)


def _figures(ctx: Ctx) -> pl.DataFrame:
    """A run's figures, long: accuracy and safety per picture, requirements with verdicts, run."""
    parts = [_long(ctx.best.pictures, "accuracy", "picture", _ACCURACY)]
    if "metrics" in ctx.tables:
        parts.append(_long(ctx.q("alert_scores"), "safety", "method", _SAFETY))
    if "requirements" in ctx.tables:
        req = ctx.store.sql("SELECT * FROM requirements")
        if {"requirement", "method", "value", "verdict"} <= set(req.columns):
            parts.append(req.select(pl.lit("requirements").alias("section"), pl.col("method").alias("picture"),
                                    _requirement(req.columns).alias("quantity"), pl.col("value").cast(pl.Float64),
                                    pl.col("verdict").cast(pl.String)))
    timings = ctx.json("timings") or {}
    wall = timings.get("wall_s", timings.get("total_s")) if isinstance(timings, dict) else None
    rows = ctx.json("rows") or {}
    run = [("wall time (s)", wall), ("reports in", rows.get("reports_in") if isinstance(rows, dict) else None)]
    parts.append(pl.DataFrame({"section": ["run"] * len(run), "picture": [""] * len(run),
                               "quantity": [q for q, _ in run], "value": [v for _, v in run],
                               "verdict": [None] * len(run)}, schema=_LONG))
    return pl.concat([p.cast(_LONG) for p in parts])


def _labels(paths: list[Path]) -> list[str]:
    """Each run's name: its directory's name, its path when two runs share a name."""
    names = [p.resolve().name for p in paths]
    return [str(p) if names.count(n) > 1 else n for p, n in zip(paths, names)]


def load_runs(run_dirs: list[str | os.PathLike[str]]) -> list[RunFacts]:
    """The runs to compare; a missing or incomplete run is refused (:class:`DataError`, one
    line with the resume hint)."""
    paths = [Path(p) for p in run_dirs]
    if len(paths) < 2:
        raise OptionError("give at least two run directories to compare")
    for p in paths:
        text = incomplete_message(p)
        if text:
            raise DataError(text, path=str(p))
        if not (p / "results.duckdb").is_file():
            raise DataError("no run database here (expected results.duckdb; write one with `tertiary run DATASET "
                            f"--out {p}`)", path=str(p))
    out = []
    for label, p in zip(_labels(paths), paths):
        with open_read_only(p) as store:
            ctx = Ctx(store, lambda _m: None)
            out.append(RunFacts(label, p, dict(ctx.record), _figures(ctx), ctx.best.picture))
    return out


# --------------------------------------------------------------------------- what differs


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts as {dotted key: leaf} (lists kept whole)."""
    if not isinstance(value, dict):
        return {prefix: value}
    out: dict[str, Any] = {}
    for k, v in value.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def _toml(text: str) -> dict:
    try:
        return tomllib.loads(text) if text else {}
    except tomllib.TOMLDecodeError:
        return {}


def _differing(dicts: list[dict[str, Any]]) -> dict[str, list[Any]]:
    flat = [_flat(d) for d in dicts]
    keys = sorted(set().union(*flat))
    return {k: [f.get(k) for f in flat] for k in keys if len({json.dumps(f.get(k), default=str) for f in flat}) > 1}


def differences(runs: list[RunFacts]) -> pl.DataFrame:
    """What differs between the runs: one row per differing item (``what``: dataset, scenario
    or configuration; ``item``; one column per run holding its value as text)."""
    groups = [("dataset", [r.json("fingerprints") or {} for r in runs]),
              ("scenario", [{"name": r.record.get("scenario"), **_toml(r.record.get("scenario_toml", ""))}
                            for r in runs]),
              ("configuration", [r.json("config") or {} for r in runs])]
    rows = [(what, key, vals) for what, dicts in groups for key, vals in _differing(dicts).items()]
    data: dict[str, list] = {"what": [w for w, _, _ in rows], "item": [k for _, k, _ in rows]}
    for i, r in enumerate(runs):
        data[r.label] = ["" if v[i] is None else (json.dumps(v[i]) if isinstance(v[i], (list, dict)) else str(v[i]))
                         for _, _, v in rows]
    return pl.DataFrame(data, schema={"what": pl.String, "item": pl.String, **{r.label: pl.String for r in runs}})


def summary_lines(diff: pl.DataFrame) -> list[str]:
    """One line per kind of difference (what a user reads before the comparison)."""
    if diff.height == 0:
        return ["the runs share their dataset, scenario and configuration"]
    lines = []
    for what in ("dataset", "scenario", "configuration"):
        items = diff.filter(pl.col("what") == what)["item"].to_list()
        if items:
            more = f" and {len(items) - 8} more" if len(items) > 8 else ""
            lines.append(f"{what} differs: {', '.join(items[:8])}{more}")
    return lines


# --------------------------------------------------------------------------- the table


def compare_table(runs: list[RunFacts]) -> pl.DataFrame:
    """One row per (section, picture, quantity): the value in each run, ``Δ <run>`` against the
    first run, for requirements the verdict in each run, and ``changed`` (a value or verdict
    differs from the first run's)."""
    keys = ["section", "picture", "quantity"]
    wide = None
    for r in runs:
        part = r.figures.unique(subset=keys, keep="first", maintain_order=True).rename(
            {"value": r.label, "verdict": f"verdict {r.label}"})
        wide = part if wide is None else wide.join(part, on=keys, how="full", coalesce=True, maintain_order="left")
    base = runs[0].label
    deltas = [(pl.col(r.label) - pl.col(base)).alias(f"Δ {r.label}") for r in runs[1:]]
    wide = wide.with_columns(deltas)
    moved = [(pl.col(f"Δ {r.label}").abs() > 1e-9 * (1.0 + pl.col(base).abs())).fill_null(False)
             | (pl.col(r.label).is_null() != pl.col(base).is_null())
             | (pl.col(f"verdict {r.label}").fill_null("") != pl.col(f"verdict {base}").fill_null(""))
             for r in runs[1:]]
    order = pl.col("section").replace_strict({"accuracy": 0, "safety": 1, "requirements": 2, "run": 3},
                                             default=4, return_dtype=pl.Int8)
    cols = [*keys, *[r.label for r in runs], *[f"Δ {r.label}" for r in runs[1:]]]
    if wide.select(pl.col(f"verdict {r.label}").is_not_null().any() for r in runs).row(0).count(True):
        cols += [f"verdict {r.label}" for r in runs]
    return (wide.with_columns(pl.any_horizontal(moved).alias("changed"), order.alias("__o"))
            .sort("__o", "picture", maintain_order=True).select(*cols, "changed"))


def verdict_changes(table: pl.DataFrame, labels: list[str]) -> pl.DataFrame:
    """The requirement rows whose verdict in some run differs from the baseline's (both given)."""
    cols = [f"verdict {x}" for x in labels]
    if cols[0] not in table.columns:
        return table.clear()
    flip = [pl.col(c).is_not_null() & pl.col(cols[0]).is_not_null() & (pl.col(c) != pl.col(cols[0])) for c in cols[1:]]
    return table.filter((pl.col("section") == "requirements") & pl.any_horizontal(flip))


def headline(runs: list[RunFacts]) -> pl.DataFrame:
    """One row per run: its best picture's accuracy and safety, and its requirement verdicts."""
    rows = []
    for r in runs:
        f = r.figures
        pick = f.filter(pl.col("picture") == (r.best or ""))
        val = dict(zip(pick["quantity"].to_list(), pick["value"].to_list()))
        n = dict(f.filter(pl.col("section") == "requirements").group_by("verdict").len().iter_rows())
        rows.append({"run": r.label, "best picture": r.best, **{q: val.get(q) for q in (
            _ACCURACY["horizontal_m"], _ACCURACY["height_m"], _SAFETY["alerted_los"], _SAFETY["missed_los"],
            _SAFETY["nuisance_alerts"], _SAFETY["false_alerts"])},
            "requirements pass": n.get("pass", 0), "fail": n.get("fail", 0), "insufficient": n.get("insufficient", 0)})
    return pl.DataFrame(rows)


def _direction(quantity: str, delta: float | None) -> str:
    if delta is None or (isinstance(delta, float) and math.isnan(delta)) or abs(delta) < 1e-12:
        return ""
    sign = BETTER.get(quantity, 0)
    return "changed" if sign == 0 else ("better" if sign * delta > 0 else "worse")


_CSS = """<style>
td.better { background: #dafbe1; } td.worse { background: #ffebe9; } td.changed { background: #fff8c5; }
td.verdict-change { outline: 2px solid #cf222e; font-weight: bold; }
</style>"""


def table_html(table: pl.DataFrame, labels: list[str]) -> str:
    """The comparison table with better / worse deltas and changed verdicts highlighted."""
    head = "".join(f"<th>{breakable(c)}</th>" for c in table.columns)
    base = f"verdict {labels[0]}"
    body = []
    for row in table.iter_rows(named=True):
        cells = []
        for c, v in row.items():
            cls = ["num"] if isinstance(v, (int, float)) and not isinstance(v, bool) else []
            if c.startswith("Δ "):
                cls.append(_direction(row["quantity"], v))
            if c.startswith("verdict ") and v is not None:
                cls.append(f"verdict-{v}")
                if c != base and v != row.get(base):
                    cls.append("verdict-change")
            text = html.escape(fmt_cell(v)) if cls[:1] == ["num"] else breakable(fmt_cell(v))
            attr = f' class="{" ".join(x for x in cls if x)}"' if any(cls) else ""
            cells.append(f"<td{attr}>{text}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    return f'<div class="tablewrap"><table><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table></div>'


# --------------------------------------------------------------------------- the page


def _accuracy_figure(table: pl.DataFrame, labels: list[str]) -> go.Figure | None:
    acc = table.filter((pl.col("section") == "accuracy") & (pl.col("quantity") == _ACCURACY["horizontal_m"]))
    if acc.height == 0:
        return None
    fig = go.Figure()
    for i, label in enumerate(labels):
        fig.add_trace(go.Bar(x=acc["picture"].to_list(), y=acc[label].to_list(), name=label,
                             marker_color=COLORS[i % len(COLORS)]))
    fig.update_layout(title=dict(text="Horizontal RMSE per picture and run", x=0.01), barmode="group", height=460,
                      template=lean_template(), margin=dict(l=70, r=20, t=60, b=140),
                      legend=dict(orientation="h", y=1.12, x=0.4))
    fig.update_xaxes(title_text="picture", tickangle=-40)
    fig.update_yaxes(title_text="horizontal RMSE (m)")
    return fig


def _runs_html(runs: list[RunFacts]) -> str:
    rows = "".join(f"<tr><td>{breakable(r.label)}</td><td>{breakable(str(r.path))}</td>"
                   f"<td>{html.escape(r.record.get('scenario', ''))}</td>"
                   f"<td>{html.escape(r.record.get('created_utc', ''))}</td></tr>" for r in runs)
    return ("<table><thead><tr><th>run</th><th>directory</th><th>scenario</th><th>created (UTC)</th></tr></thead>"
            f"<tbody>{rows}</tbody></table>")


def render_compare(runs: list[RunFacts]) -> tuple[str, pl.DataFrame, pl.DataFrame]:
    """(page, comparison table, differences) of the runs."""
    labels = [r.label for r in runs]
    table, diff = compare_table(runs), differences(runs)
    n_changed = int(table["changed"].sum())
    flips = verdict_changes(table, labels)
    parts = [_CSS, f"<p>Baseline: <b>{html.escape(labels[0])}</b>; Δ = run − baseline. {n_changed} of "
                   f"{table.height} figures differ; {flips.height} requirement verdict(s) change.</p>",
             _runs_html(runs),
             "<h2>What differs</h2><ul>" + "".join(f"<li>{html.escape(s)}</li>" for s in summary_lines(diff))
             + "</ul>"]
    if diff.height:
        parts.append(f"<details><summary>every differing item ({diff.height})</summary>"
                     f"{table_html(diff, labels)}</details>")
    parts.append("<h2>Headline</h2>" + table_html(headline(runs), labels))
    fig = _accuracy_figure(table, labels)
    if fig is not None:
        parts.append(f'<div class="figure">{figure_div(fig, "fig-compare-0")}</div>')
    if flips.height:
        parts.append(f"<h2>Verdicts that change ({flips.height})</h2>" + table_html(flips, labels))
    parts.append("<h2>Figures side by side</h2><p class=\"note\">Green: better than the baseline, red: worse, "
                 "yellow: changed (no better direction); a requirement whose verdict changes is outlined.</p>"
                 + table_html(table, labels))
    title = "Comparison of runs: " + ", ".join(labels)
    return page_html(title, "".join(parts), int(fig is not None)), table, diff


def write_compare(runs: list[RunFacts] | list[str | os.PathLike[str]], out: str | os.PathLike[str]
                  ) -> tuple[Path, pl.DataFrame, pl.DataFrame]:
    """Write the comparison page of ``runs`` (loaded, or run directories) to ``out`` atomically:
    (path, comparison table, differences)."""
    facts = runs if all(isinstance(r, RunFacts) for r in runs) else load_runs(runs)   # type: ignore[arg-type]
    page, table, diff = render_compare(facts)                                          # type: ignore[arg-type]
    return write_text_atomic(Path(out), page), table, diff
