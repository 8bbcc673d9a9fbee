"""What every section of the HTML report shares: the run being reported (:class:`Ctx`), a
section (:class:`Section`), the best picture, reference and radar (:class:`Best`), and the helpers
that draw figures and tables the same way everywhere."""

from __future__ import annotations

import functools
import html
import json
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import numpy as np
import plotly.graph_objects as go
import plotly.io as pio
import polars as pl

from tertiary.store.run_store import RunStore
from tertiary.store.sql_reports import run_report

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

#: trace colours and line dashes, in the order traces take them
COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2",
          "#7f7f7f", "#bcbd22"]
DASHES = ["solid", "dash", "dot", "dashdot", "longdash", "longdashdot"]


# --------------------------------------------------------------------------- sections


@dataclass
class Section:
    """One section of the report: its anchor ``key``, title, prose, figures, tables, raw HTML and
    a closing note."""

    key: str
    title: str
    text: str = ""
    figures: list[tuple[Any, str]] = field(default_factory=list)   # (plotly figure, caption)
    tables: list[tuple[str, pl.DataFrame]] = field(default_factory=list)
    html: str = ""
    note: str = ""


class Ctx:
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
    def best(self) -> "Best":
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
class Best:
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
    #: how the best single sensor is named: "radar", or "sensor (MLAT)" / "sensor (ADS-B)"
    radar_kind: str = "radar"
    ranked_by: str = "rmse_horizontal_m"
    unranked: list[str] = field(default_factory=list)

    def best_of(self, names: list[str]) -> str | None:
        """The most accurate of ``names`` (the pictures a figure holds), else the first."""
        key = "horizontal_m" if self.ranked_by == "rmse_horizontal_m" else "pos_m"
        ranked = (self.pictures.filter(pl.col("picture").is_in(names) & pl.col(key).is_not_null()
                                       & (pl.col("picture") != CENTRALIZED)).sort(key, "picture"))
        return ranked["picture"][0] if ranked.height else (names[0] if names else None)


def _best_pictures(ctx: Ctx) -> Best:
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
    best = Best(pictures, radars)
    cand = pictures.filter(pl.col("picture") != CENTRALIZED)
    key = "horizontal_m" if cand["horizontal_m"].is_not_null().any() else "pos_m"
    best.ranked_by = "rmse_horizontal_m" if key == "horizontal_m" else "rmse_pos_m"
    best.unranked = cand.filter(pl.col(key).is_null())["picture"].to_list()
    # equal figures (trackers that coincide on a short run) are ranked by name: the same choice every run
    ranked = cand.filter(pl.col(key).is_not_null()).sort(key, "picture")
    if ranked.height:
        best.picture = ranked["picture"][0]
        fus = ranked.filter(pl.col("stage") == "fusion")
        best.fused = fus["picture"][0] if fus.height else None
    if radars.height:
        best.radar = radars.sort("horizontal_m", "radar", nulls_last=True)["radar"][0]
        best.radar_kind = _sensor_word(ctx, best.radar)
    return best


_SENSOR_WORDS = {"mlat": "sensor (MLAT)", "adsb": "sensor (ADS-B)"}


def _sensor_word(ctx: Ctx, name: str) -> str:
    """How a sensor of the radars table is named in a sentence, by its kind."""
    if "radars" not in ctx.tables or "kind" not in ctx.store.sql("SELECT * FROM radars LIMIT 0").columns:
        return "radar"
    kind = ctx.store.sql("SELECT kind FROM radars WHERE name = ?", [name])["kind"]
    return _SENSOR_WORDS.get(kind[0] if kind.len() else None, "radar")


def _radar_pooled(ctx: Ctx) -> pl.DataFrame:
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
            .rename({"name": "radar"}).sort("horizontal_m", "radar").cast(schema))


def visible(name: str, shown: set[str]) -> bool | str:
    return True if name in shown else "legendonly"

# --------------------------------------------------------------------------- helpers


def f32(values: Any) -> np.ndarray:
    """float32 array (compact base64 in the HTML); nulls become NaN."""
    if isinstance(values, pl.Series):
        values = values.cast(pl.Float64).fill_null(float("nan")).to_numpy()
    return np.asarray(values, dtype=np.float32)


def thin(frame: pl.DataFrame, max_points: int = MAX_POINTS) -> pl.DataFrame:
    """Every k-th row so that at most ``max_points`` remain (the last row always kept)."""
    n = frame.height
    if n <= max_points:
        return frame
    step = math.ceil(n / max_points)
    idx = pl.int_range(pl.len())
    return frame.filter((idx % step == 0) | (idx == n - 1))


@functools.cache
def lean_template() -> go.layout.Template:
    """plotly's ``plotly_white`` look with only what 2-D scatter and bar figures use: the full
    template (every trace type, colour scales, 3-D and map defaults) is ~7 kB in each figure."""
    full = pio.templates["plotly_white"]
    layout = {k: v for k, v in full.layout.to_plotly_json().items()
              if k not in ("polar", "ternary", "scene", "geo", "mapbox", "colorscale", "coloraxis")}
    data = {k: v for k, v in full.data.to_plotly_json().items() if k in ("scatter", "bar")}
    return go.layout.Template(layout=layout, data=data)


def step_changes(frame: pl.DataFrame, y: str) -> pl.DataFrame:
    """The rows of a step curve (drawn with ``shape="hv"``, in x order) where ``y`` changes, and
    the last: the same line, drawn from a fraction of the points when the value mostly holds."""
    if frame.height < 3:
        return frame
    prev = pl.col(y).shift(1)
    keep = prev.is_null() | (pl.col(y) != prev) | (pl.int_range(pl.len()) == pl.len() - 1)
    return frame.filter(keep)


def style(fig, title: str, xtitle: str, ytitle: str, height: int = 460, **kw: Any) -> None:
    fig.update_layout(title=dict(text=title, x=0.01), template=lean_template(), height=height,
                      margin=dict(l=70, r=20, t=60, b=55), legend=dict(orientation="v"),
                      hovermode="closest", **kw)
    fig.update_xaxes(title_text=xtitle)
    fig.update_yaxes(title_text=ytitle)


def radar_names(frame: pl.DataFrame) -> dict[int, str]:
    return {int(r): str(n) for r, n in frame.select("radar_id", "name").unique().iter_rows()}


def fmt_cell(v: Any) -> str:
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


def breakable(text: str) -> str:
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


def table_html(frame: pl.DataFrame, max_rows: int | None = None,
                cell_class: dict[str, Callable[[Any], str]] | None = None) -> str:
    """An HTML table (long cells wrap; see _CSS); ``cell_class`` maps a column to a function
    giving the CSS class of each of its cells."""
    if frame.width == 0:
        return '<p class="note">(no columns)</p>'
    rows = frame if max_rows is None else frame.head(max_rows)
    head = "".join(f"<th>{breakable(c)}</th>" for c in frame.columns)
    extra = [(cell_class or {}).get(c) for c in frame.columns]
    body = []
    for row in rows.iter_rows():
        cells = []
        for v, fn in zip(row, extra):
            cls = ["num"] if isinstance(v, (int, float)) and not isinstance(v, bool) else []
            cls += [html.escape(fn(v))] if fn else []
            attr = f' class="{" ".join(cls)}"' if cls else ""
            text = html.escape(fmt_cell(v)) if cls[:1] == ["num"] else breakable(fmt_cell(v))
            cells.append(f"<td{attr}>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    if not body:
        body.append(f'<tr><td colspan="{frame.width}" class="note">no rows</td></tr>')
    more = ""
    if max_rows is not None and frame.height > max_rows:
        more = f'<p class="note">first {max_rows:,} of {frame.height:,} rows</p>'
    return f'<div class="tablewrap"><table><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table></div>{more}'

