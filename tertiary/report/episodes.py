"""Alert episodes you can open: for one picture, each STCA alert episode (the ``alerts`` table)
and each missed loss of separation drawn as a plan view and a vertical profile of both tracks
and both truths, with the predicted closest approach (CPA), the separation minima, the
classification and the warning time.

* :func:`episodes_section` — the HTML fragment of the report: the :data:`DEFAULT_EPISODES` most
  severe alert episodes of the best picture and every missed loss of separation.
* :func:`episode_figures` — the same as (plotly figure, caption) pairs.
* :func:`write_episodes` — a self-contained page (``tertiary episodes``), any picture or pair.

Severity: the largest ``severity`` (1 − R_min / R_threshold) of the episode's alert rows in the
``conflicts`` table, the report's "most severe conflicts" measure; the closest predicted approach
breaks ties and ranks the truth picture's episodes (its conflicts are not stored). The predicted
CPA is that of the episode's alert row with the smallest R_min: both tracks' states at that epoch
moved on straight for T_min (the prediction's own straight-line model). Missed losses are found
again from the truth (:func:`safety.alerts.loss_of_separation`, the run's minima) and linked to
the picture's alert episodes as the safety stage links them, without the per-epoch closest
approaches the stage extends the link with (not stored): the count is set beside the run's
``missed_los`` metric.
"""

from __future__ import annotations

import html
import json
import math
import os
import tomllib
from dataclasses import dataclass, fields
from datetime import datetime, timedelta
from importlib import resources
from pathlib import Path
from string import Template
from typing import Any

import numpy as np
import plotly.graph_objects as go
import polars as pl
from plotly.offline import get_plotlyjs
from plotly.subplots import make_subplots

from safety.alerts import TRUTH_PICTURE, AlertConfig, loss_of_separation
from safety.conflicts import AerodromeZone, ApproachVolume, ConflictConfig
from tertiary.core.errors import DataError, OptionError
from tertiary.core.geo import LocalFrame
from tertiary.core.units import FT
from tertiary.report.common import Ctx, Section, f32, lean_template, table_html
from tertiary.runtime.windows import incomplete_message
from tertiary.store.files import write_text_atomic
from tertiary.store.run_store import RunStore
from tertiary.store.sql_reports import open_read_only

__all__ = ["DEFAULT_EPISODES", "EPISODES_FILENAME", "Episode", "best_alert_picture", "episode_figure",
           "episode_figures", "episodes_section", "figure_div", "list_episodes", "page_html", "parse_pair",
           "render_episodes", "run_config", "sec_episodes", "write_episodes"]

#: alert episodes drawn by default (most severe first)
DEFAULT_EPISODES = 5
#: the page ``tertiary episodes`` writes in the run directory
EPISODES_FILENAME = "episodes.html"
#: time drawn before and after an episode (s)
PAD_S = 30.0
#: time drawn before a missed loss (s): where the alert should have come
MISSED_LEAD_S = 120.0
#: most truth rows searched again for missed losses of a whole picture (memory and time)
MAX_TRUTH_ROWS = 5_000_000

_A, _B = "#1f77b4", "#d62728"           # aircraft A and B, tracks solid and truths dotted


@dataclass(frozen=True)
class Episode:
    """One episode to draw: an alert episode (``kind`` "alert") or a missed loss ("missed")."""

    kind: str
    picture: str
    run: int
    truth_a: int | None
    truth_b: int | None
    id_a: int | None
    id_b: int | None
    t_start: datetime
    t_end: datetime
    classification: str
    induced: str | None = None
    warning_s: float | None = None
    los_start: datetime | None = None
    r_min_pred_m: float | None = None
    severity: float | None = None
    cpa_epoch: datetime | None = None
    cpa_t_min_s: float | None = None


# --------------------------------------------------------------------------- the run's facts


def _columns(store: RunStore, table: str) -> set[str]:
    return set(store.sql(f"SELECT * FROM {table} LIMIT 0").columns)


def run_config(store: RunStore) -> dict:
    """The run's recorded pipeline configuration (empty when it has none)."""
    raw = store.sql("SELECT value FROM run WHERE key = 'config'") if "run" in store.tables() else pl.DataFrame()
    try:
        return json.loads(raw.item()) if raw.height else {}
    except (json.JSONDecodeError, ValueError):
        return {}


def conflict_config(config: dict) -> ConflictConfig:
    """The run's :class:`ConflictConfig` from its recorded configuration (defaults where absent)."""
    raw = dict(config.get("conflicts") or {})
    known = {f.name for f in fields(ConflictConfig)}
    kw: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in raw.items() if k in known}
    kw["approach_volumes"] = tuple(ApproachVolume(**v) for v in raw.get("approach_volumes") or [])
    kw["aerodrome_zones"] = tuple(AerodromeZone(**v) for v in raw.get("aerodrome_zones") or [])
    try:
        return ConflictConfig(**kw)
    except (TypeError, ValueError):     # a configuration of another version: its airspace's minima
        return ConflictConfig(airspace=raw.get("airspace", "terminal"))


def minima(cc: ConflictConfig, height_m: float | None) -> tuple[float, float]:
    """(horizontal, vertical) minimum in metres at ``height_m`` (en-route above its floor)."""
    if cc.enroute_above_m is not None and height_m is not None and height_m >= cc.enroute_above_m:
        return cc.enroute_h_m, cc.enroute_v_m
    return cc.sep_h_m, cc.sep_v_m


def best_alert_picture(store: RunStore) -> str | None:
    """The most accurate picture that has alert episodes (the report's best picture when it has)."""
    if "alerts" not in store.tables():
        return None
    names = [m for m in store.sql("SELECT DISTINCT method FROM alerts ORDER BY method")["method"].to_list()
             if m != TRUTH_PICTURE]
    if not names:
        return None
    return Ctx(store, lambda _m: None).best.best_of(names)


def _pictures(store: RunStore) -> list[str]:
    tabs = set(store.tables())
    if "alerts" in tabs:
        return store.sql("SELECT DISTINCT method FROM alerts ORDER BY method")["method"].to_list()
    return []


# --------------------------------------------------------------------------- episodes


def parse_pair(text: str) -> tuple[int, int]:
    """``A,B`` (two integer ids) as (min, max)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        a, b = (int(p) for p in parts)
    except ValueError:
        raise OptionError(f"expected two ids A,B, got {text!r}", option="--pair") from None
    return (a, b) if a <= b else (b, a)


_PAIR_SQL = ("($ta IS NULL OR (least(coalesce(a.truth_a, a.id_a), coalesce(a.truth_b, a.id_b)) = $ta "
             "AND greatest(coalesce(a.truth_a, a.id_a), coalesce(a.truth_b, a.id_b)) = $tb))")


def list_episodes(store: RunStore, picture: str, pair: tuple[int, int] | None = None) -> pl.DataFrame:
    """The alert episodes of ``picture`` (of the aircraft ``pair`` when given), most severe first,
    each with its peak severity and the epoch and T_min of its closest predicted approach."""
    has_conf = "conflicts" in store.tables()
    induced = "a.induced" if "induced" in _columns(store, "alerts") else "NULL::VARCHAR"
    conf = ("LEFT JOIN conflicts c ON c.alert AND c.method = a.method AND c.run = a.run AND c.id_a = a.id_a "
            "AND c.id_b = a.id_b AND c.epoch BETWEEN a.t_start AND a.t_end") if has_conf else ""
    agg = ("max(c.severity) AS severity, arg_min(c.epoch, c.r_min_m) AS cpa_epoch, "
           "arg_min(c.t_min_s, c.r_min_m) AS cpa_t_min_s") if has_conf else \
        "NULL::DOUBLE AS severity, NULL::TIMESTAMPTZ AS cpa_epoch, NULL::DOUBLE AS cpa_t_min_s"
    ta, tb = pair if pair else (None, None)
    return store.sql(
        f"SELECT a.run, a.id_a, a.id_b, a.truth_a, a.truth_b, a.t_start, a.t_end, a.classification, "
        f"{induced} AS induced, a.warning_s, a.los_start, a.r_min_pred_m, {agg} "
        f"FROM alerts a {conf} WHERE a.method = $p AND {_PAIR_SQL} "
        "GROUP BY ALL ORDER BY severity DESC NULLS LAST, r_min_pred_m NULLS LAST, a.t_start, a.id_a, a.id_b",
        {"p": picture, "ta": ta, "tb": tb})


def _alert_episode(row: dict, picture: str) -> Episode:
    return Episode("alert", picture, int(row["run"]), row["truth_a"], row["truth_b"], int(row["id_a"]),
                   int(row["id_b"]), row["t_start"], row["t_end"], row["classification"], row["induced"],
                   row["warning_s"], row["los_start"], row["r_min_pred_m"], row["severity"], row["cpa_epoch"],
                   row["cpa_t_min_s"])


def _truth_frame(store: RunStore, pair: tuple[int, int] | None = None) -> tuple[pl.DataFrame, LocalFrame | None]:
    """The truth's kinematics (of the two aircraft of ``pair`` when given) and the system frame."""
    cols = _columns(store, "truth")
    want = [c for c in ("run", "truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "alt_m",
                        "alt_rate_mps") if c in cols]
    where = f" WHERE truth_id IN ({int(pair[0])}, {int(pair[1])})" if pair else ""
    truth = store.sql(f"SELECT {', '.join(want)} FROM truth{where}")
    raw = store.sql("SELECT value FROM run WHERE key = 'scenario_toml'")
    origin = None
    if raw.height:
        try:
            origin = tomllib.loads(raw.item()).get("origin")
        except tomllib.TOMLDecodeError:
            origin = None
    frame = LocalFrame(*(float(v) for v in origin[:3])) if origin and len(origin) >= 3 else None
    return truth, frame


def _linked(los: pl.DataFrame, alerts: pl.DataFrame, link_s: float, reach_s: float) -> pl.Series:
    """Per LoS row: an alert episode of its pair links it (as the safety stage links them)."""
    if alerts.height == 0 or los.height == 0:
        return pl.Series("alerted", [False] * los.height)
    keys = ["run", "truth_a", "truth_b"]
    a = alerts.filter(pl.col("truth_a").is_not_null()).select(
        pl.col("run").cast(pl.Int64), pl.col("truth_a").cast(pl.Int64), pl.col("truth_b").cast(pl.Int64),
        pl.col("t_start").alias("__a0"), pl.col("t_end").alias("__a1"), pl.col("los_start").alias("__ls"),
        (pl.col("t_start") + pl.duration(seconds=pl.col("t_min_first_s").fill_null(0.0).clip(0.0, reach_s))
         ).alias("__cpa"))
    reach = pl.max_horizontal(pl.col("__a1") + timedelta(seconds=link_s), pl.col("__cpa"))
    hit = (los.with_row_index("__row").join(a, on=keys, how="inner")
           .filter(pl.col("__ls").is_between(pl.col("t_start"), pl.col("t_end"))
                   | ((pl.col("__a0") <= pl.col("t_end")) & (reach >= pl.col("t_start"))))
           ["__row"].unique())
    return pl.Series("alerted", np.isin(np.arange(los.height), hit.to_numpy()))


def missed_losses(store: RunStore, picture: str, pair: tuple[int, int] | None = None
                  ) -> tuple[list[Episode], str]:
    """The losses of separation in the truth that ``picture`` did not alert, and a note (how
    they were found, and the run's own count)."""
    tabs = set(store.tables())
    if not {"truth", "alerts"} <= tabs or picture == TRUTH_PICTURE:
        return [], ""
    metric = (store.sql("SELECT value FROM metrics WHERE stage = 'safety' AND metric = 'missed_los' "
                        "AND method = $p", {"p": picture}) if "metrics" in tabs else pl.DataFrame())
    n_run = int(metric.item()) if metric.height and metric.item() is not None and not math.isnan(metric.item()) \
        else None
    if n_run == 0 and pair is None:
        return [], "No missed loss of separation on this picture (the run's missed_los metric is 0)."
    if "losses" in tabs:
        return _stored_missed(store, picture, pair)
    rows = store.sql("SELECT count(*) FROM truth").item()
    if pair is None and rows > MAX_TRUTH_ROWS:      # the stage's own search runs an hour at a time
        return [], (f"Missed losses not drawn: the truth ({rows:,} rows) is too large to search again here; "
                    f"`tertiary episodes RUN_DIR --pair A,B` draws a pair's (the run's missed_los metric: {n_run}).")
    cc = conflict_config(run_config(store))
    acfg = AlertConfig(conflict=cc)
    truth, frame = _truth_frame(store, pair)
    los = loss_of_separation(truth, acfg, frame)
    if "run" not in los.columns:
        runs = store.sql("SELECT DISTINCT run FROM alerts WHERE method = $p", {"p": picture})["run"].to_list() or [0]
        los = los.join(pl.DataFrame({"run": runs}, schema={"run": pl.Int64}), how="cross")
    los = los.with_columns(pl.col("run").cast(pl.Int64), pl.col("truth_a").cast(pl.Int64),
                           pl.col("truth_b").cast(pl.Int64))
    if pair is not None:
        los = los.filter((pl.col("truth_a") == pair[0]) & (pl.col("truth_b") == pair[1]))
    span = store.sql("SELECT min(epoch) AS t0, max(epoch) AS t1 FROM conflicts WHERE method = $p", {"p": picture}) \
        if "conflicts" in tabs else pl.DataFrame()
    if span.height and span["t0"][0] is not None:
        los = los.filter((pl.col("t_end") >= span["t0"][0]) & (pl.col("t_start") <= span["t1"][0]))
    alerts = store.sql("SELECT * FROM alerts WHERE method IN ($p, $t)", {"p": picture, "t": TRUTH_PICTURE})
    mine = alerts.filter(pl.col("method") == picture)
    ref = alerts.filter(pl.col("method") == TRUTH_PICTURE)
    los = los.with_columns(_linked(los, mine, acfg.link, acfg.cpa_reach),
                           _linked(los, ref, acfg.link, acfg.cpa_reach).alias("__ref"))
    missed = los.filter(~pl.col("alerted")).sort("run", "t_start", "truth_a", "truth_b")
    eps = [Episode("missed", picture, int(r["run"]), int(r["truth_a"]), int(r["truth_b"]), None, None, r["t_start"],
                   r["t_end"], "missed loss", ("picture" if r["__ref"] else "predictor") if ref.height else None,
                   los_start=r["t_start"])
           for r in missed.iter_rows(named=True)]
    note = (f"{len(eps)} missed loss(es) of separation found again from the truth with the run's minima "
            f"({cc.sep_h_m / 1852:.1f} NM, {cc.sep_v_m / FT:.0f} ft)")
    if pair is None and n_run is not None:
        note += f"; the run's missed_los metric counts {n_run}"
    return eps, note + "."


def _stored_missed(store: RunStore, picture: str, pair: tuple[int, int] | None) -> tuple[list[Episode], str]:
    """The missed losses the run's scoring stored (table ``losses``): exactly what its
    ``missed_los`` counts, picture-induced when the truth picture alerted the same loss."""
    where = "" if pair is None else f" AND truth_a = {int(pair[0])} AND truth_b = {int(pair[1])}"
    los = store.sql("SELECT run, method, truth_a, truth_b, t_start, t_end, alerted FROM losses "
                    f"WHERE method IN ($p, $t){where} ORDER BY run, t_start, truth_a, truth_b",
                    {"p": picture, "t": TRUTH_PICTURE})
    ref = los.filter(pl.col("method") == TRUTH_PICTURE).select("run", "truth_a", "truth_b", "t_start",
                                                                 pl.col("alerted").alias("__ref"))
    mine = los.filter((pl.col("method") == picture) & ~pl.col("alerted"))
    missed = mine.join(ref, on=["run", "truth_a", "truth_b", "t_start"], how="left")
    eps = [Episode("missed", picture, int(r["run"]), int(r["truth_a"]), int(r["truth_b"]), None, None, r["t_start"],
                   r["t_end"], "missed loss", None if r["__ref"] is None else ("picture" if r["__ref"] else "predictor"),
                   los_start=r["t_start"])
           for r in missed.iter_rows(named=True)]
    return eps, f"{len(eps)} missed loss(es) of separation (the run's scoring, table losses)."


# --------------------------------------------------------------------------- one episode's data


def _picture_sql(store: RunStore, picture: str) -> tuple[str, str, str, dict]:
    """(table, id column, time column, extra filter params) holding the states of ``picture``."""
    if picture == TRUTH_PICTURE:
        return "truth", "truth_id", "time", {}
    if "+" in picture:
        method, _, filt = picture.partition("+")
        return "tracks", "track_id", "epoch", {"method": method, "filter": filt}
    return "fused", "target_id", "epoch", {"method": picture}


def _states(store: RunStore, table: str, id_col: str, t_col: str, ids: list[int], run: int, t0: datetime,
            t1: datetime, match: dict) -> pl.DataFrame:
    """(id, t, x_m, y_m, h_m, vx_mps, vy_mps, vh_mps) of ``ids`` in [t0, t1]; heights from
    ``alt_m`` where present (the channel the prediction uses), else ``z_m``."""
    cols = _columns(store, table)
    h = "coalesce(alt_m, z_m)" if "alt_m" in cols else "z_m"
    vh = "coalesce(alt_rate_mps, vz_mps)" if "alt_rate_mps" in cols else "vz_mps"
    where = [f"{id_col} IN ({', '.join(str(int(i)) for i in ids)})", f"{t_col} BETWEEN $t0 AND $t1"]
    where += ["run = $run"] if "run" in cols else []
    where += [f"{k} = ${k}" for k in match]
    params = {"t0": t0, "t1": t1, **match, **({"run": run} if "run" in cols else {})}
    # float32 values (the lean store's, and a figure's resolution): every figure drawn from them is
    # the same whether the run's tables were stored narrowed or not
    f32 = lambda e, name: f"({e})::FLOAT::DOUBLE AS {name}"      # noqa: E731
    cols_sql = ", ".join(f32(e, n) for e, n in (("x_m", "x_m"), ("y_m", "y_m"), (h, "h_m"), ("vx_mps", "vx_mps"),
                                                 ("vy_mps", "vy_mps"), (vh, "vh_mps")))
    return store.sql(f"SELECT {id_col}::BIGINT AS id, {t_col} AS t, {cols_sql} FROM {table} "
                     f"WHERE {' AND '.join(where)} ORDER BY id, t", params)


def _ids_of(store: RunStore, ep: Episode, t0: datetime, t1: datetime, truth: pl.DataFrame) -> tuple[int | None, ...]:
    """A missed loss's picture ids: per aircraft, the id of the picture closest to its truth at
    the most epochs of the window (within 1 NM)."""
    table, id_col, t_col, match = _picture_sql(store, ep.picture)
    cols = _columns(store, table)
    where = " AND ".join([f"{t_col} BETWEEN $t0 AND $t1", *[f"{k} = ${k}" for k in match],
                          *(["run = $run"] if "run" in cols else [])])
    rows = store.sql(f"SELECT {id_col}::BIGINT AS id, {t_col} AS t, x_m, y_m FROM {table} WHERE {where} ORDER BY t",
                     {"t0": t0, "t1": t1, **match, **({"run": ep.run} if "run" in cols else {})})
    out = []
    for tid in (ep.truth_a, ep.truth_b):
        tr = truth.filter(pl.col("id") == tid).select("t", pl.col("x_m").alias("__x"), pl.col("y_m").alias("__y"))
        if rows.height == 0 or tr.height == 0:
            out.append(None)
            continue
        near = (rows.join_asof(tr.sort("t"), on="t", strategy="nearest")
                .filter(((pl.col("x_m") - pl.col("__x")) ** 2 + (pl.col("y_m") - pl.col("__y")) ** 2) < 1852.0 ** 2)
                .group_by("id").len().sort("len", "id", descending=[True, False]))
        out.append(int(near["id"][0]) if near.height else None)
    return tuple(out)


@dataclass
class _Data:
    """What one episode's figure draws."""

    tracks: pl.DataFrame
    truth: pl.DataFrame
    ids: tuple[int | None, int | None]
    t_ref: datetime
    cpa: tuple[np.ndarray, np.ndarray, float] | None     # (A at CPA, B at CPA, seconds after t_ref)


def _episode_data(store: RunStore, ep: Episode) -> _Data:
    t_stop = max(ep.t_end, ep.los_start or ep.t_end)
    if ep.cpa_epoch is not None and ep.cpa_t_min_s is not None and math.isfinite(ep.cpa_t_min_s):
        t_stop = max(t_stop, ep.cpa_epoch + timedelta(seconds=max(ep.cpa_t_min_s, 0.0)))
    lead = MISSED_LEAD_S if ep.kind == "missed" else PAD_S
    t0, t1 = ep.t_start - timedelta(seconds=lead), t_stop + timedelta(seconds=PAD_S)
    truths = [i for i in (ep.truth_a, ep.truth_b) if i is not None]
    truth = (_states(store, "truth", "truth_id", "time", truths, ep.run, t0, t1, {}) if truths and "truth" in
             store.tables() else pl.DataFrame(schema={"id": pl.Int64, "t": pl.Datetime("us", "UTC")}))
    ids = (ep.id_a, ep.id_b) if ep.kind == "alert" else _ids_of(store, ep, t0, t1, truth)
    table, id_col, t_col, match = _picture_sql(store, ep.picture)
    known = [i for i in ids if i is not None]
    tracks = _states(store, table, id_col, t_col, known, ep.run, t0, t1, match) if known else truth.clear()
    t_ref = ep.t_start if ep.kind == "alert" else ep.los_start or ep.t_start
    return _Data(tracks, truth, ids, t_ref, _predicted_cpa(tracks, ep, ids, t_ref))


def _t_min(ep: Episode) -> float:
    """The episode's T_min as drawn: a parallel pair (∞) or a diverging one (< 0) is closest now."""
    t = ep.cpa_t_min_s
    return max(t, 0.0) if t is not None and math.isfinite(t) else 0.0


def _predicted_cpa(tracks: pl.DataFrame, ep: Episode, ids: tuple, t_ref: datetime
                   ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Both tracks at the closest approach predicted by the episode's closest alert row: their
    states at that epoch moved on straight for T_min."""
    if ep.cpa_epoch is None or ep.cpa_t_min_s is None or tracks.height == 0:
        return None
    t_min = _t_min(ep)
    at = []
    for i in ids:
        row = tracks.filter((pl.col("id") == i) & (pl.col("t") == ep.cpa_epoch))
        if row.height == 0:
            return None
        s = row.row(0, named=True)
        at.append(np.array([s["x_m"] + s["vx_mps"] * t_min, s["y_m"] + s["vy_mps"] * t_min,
                            s["h_m"] + (s["vh_mps"] or 0.0) * t_min]))
    return at[0], at[1], (ep.cpa_epoch - t_ref).total_seconds() + t_min


# --------------------------------------------------------------------------- the figure


def _title(ep: Episode, rank: int | None) -> str:
    head = f"#{rank} " if rank else ""
    if ep.kind == "missed":
        what = "missed loss of separation" + (f" ({ep.induced}-induced)" if ep.induced else "") + ", no alert"
    else:
        what = ep.classification + (f", {ep.induced}-induced" if ep.induced else "")
        what += f", warning {ep.warning_s:.0f} s" if ep.warning_s is not None and math.isfinite(ep.warning_s) \
            else ", no loss followed"
    pair = (f"aircraft {ep.truth_a} & {ep.truth_b}" if ep.truth_a is not None
            else f"ids {ep.id_a} & {ep.id_b} (no two aircraft)")
    return f"{head}{what} — {ep.picture}, {pair}, run {ep.run}, {ep.t_start:%H:%M:%S} UTC"


def _secs(t: pl.Series, t_ref: datetime) -> np.ndarray:
    return ((t - t_ref).dt.total_microseconds() / 1e6).to_numpy()


def _lines(fig: go.Figure, frame: pl.DataFrame, ids: tuple, names: tuple[str, str], dash: str, t_ref: datetime,
           ) -> None:
    for i, name, color in zip(ids, names, (_A, _B)):
        part = frame.filter(pl.col("id") == i) if i is not None else frame.clear()
        if part.height == 0:
            continue
        t = _secs(part["t"], t_ref)
        ft = part["h_m"].to_numpy() / FT
        style = dict(color=color, dash=dash, width=2.0 if dash == "solid" else 1.5)
        fig.add_trace(go.Scatter(x=f32(part["x_m"] / 1e3), y=f32(part["y_m"] / 1e3), mode="lines",
                                 name=name, legendgroup=name, line=style, customdata=f32(np.c_[t, ft]),
                                 hovertemplate="t = %{customdata[0]:.0f} s, %{customdata[1]:.0f} ft<extra>"
                                               + name + "</extra>"), row=1, col=1)
        if dash == "solid" and (t >= 0).any():      # where the track was when the alert (or the loss) began
            k = int(np.argmax(t >= 0))
            fig.add_trace(go.Scatter(x=[part["x_m"][k] / 1e3], y=[part["y_m"][k] / 1e3], mode="markers",
                                     marker=dict(symbol="circle-open", size=10, color=color, line=dict(width=2)),
                                     legendgroup=name, showlegend=False, hovertemplate="t = 0 s<extra>" + name
                                     + "</extra>"), row=1, col=1)
        fig.add_trace(go.Scatter(x=f32(t), y=f32(ft), mode="lines", name=name, legendgroup=name, showlegend=False,
                                 line=style, customdata=f32(ft / 100.0),
                                 hovertemplate="%{y:.0f} ft (FL%{customdata:.0f})<extra>" + name + "</extra>"),
                      row=1, col=2)


#: the truth drawn every this many seconds (its closest approach is found on every sample): a
#: straight or turning aircraft is still a smooth line, and the report stays small
TRUTH_DRAW_STEP_S = 4


def _thinned(truth: pl.DataFrame) -> pl.DataFrame:
    """Each aircraft's truth every :data:`TRUTH_DRAW_STEP_S` seconds, its first and last sample kept."""
    if truth.height == 0:
        return truth
    t0 = truth["t"].min()
    k = ((pl.col("t") - t0).dt.total_seconds() // TRUTH_DRAW_STEP_S)
    keep = (k != k.shift(1).over("id")) | (pl.col("t") == pl.col("t").max().over("id"))
    return truth.sort("id", "t").filter(keep)


def _true_cpa(truth: pl.DataFrame, ep: Episode, t_ref: datetime) -> tuple[pl.DataFrame, float, float] | None:
    """The truths' closest horizontal approach in the window: (both rows, distance m, Δh m)."""
    if ep.truth_a is None or truth.height == 0:
        return None
    a = truth.filter(pl.col("id") == ep.truth_a)
    b = truth.filter(pl.col("id") == ep.truth_b).select("t", *[pl.col(c).alias(c + "_b") for c in ("x_m", "y_m",
                                                                                                     "h_m")])
    j = a.join(b, on="t", how="inner").with_columns(
        ((pl.col("x_m") - pl.col("x_m_b")) ** 2 + (pl.col("y_m") - pl.col("y_m_b")) ** 2).sqrt().alias("__d"))
    if j.height == 0:
        return None
    r = j.sort("__d").head(1)
    return r, float(r["__d"][0]), float(abs(r["h_m"][0] - r["h_m_b"][0]))


def episode_figure(store: RunStore, ep: Episode, rank: int | None = None, cc: ConflictConfig | None = None
                   ) -> tuple[go.Figure, str]:
    """One episode: plan view (ENU km) beside the vertical profile (ft against seconds from the
    first alert, or from the start of a missed loss), and its caption."""
    cc = cc or conflict_config(run_config(store))
    d = _episode_data(store, ep)
    fig = make_subplots(rows=1, cols=2, column_widths=[0.5, 0.5], horizontal_spacing=0.09,
                        subplot_titles=["plan view (system ENU frame)", "vertical profile"])
    id_names = tuple(f"track {i}" if i is not None else "no track" for i in d.ids)
    ac = (ep.truth_a, ep.truth_b)
    if ep.picture != TRUTH_PICTURE:
        _lines(fig, d.tracks, d.ids, (f"A: {id_names[0]}", f"B: {id_names[1]}"), "solid", d.t_ref)
    _lines(fig, _thinned(d.truth), ac, (f"A: truth of aircraft {ac[0]}", f"B: truth of aircraft {ac[1]}"), "dot",
           d.t_ref)
    true = _true_cpa(d.truth, ep, d.t_ref)
    h_min, v_min = _draw_cpa(fig, d, cc, true)
    if true is not None:
        r, dist, dh = true
        t = float(_secs(r["t"], d.t_ref)[0])
        fig.add_trace(go.Scatter(x=[r["x_m"][0] / 1e3, r["x_m_b"][0] / 1e3], y=[r["y_m"][0] / 1e3, r["y_m_b"][0] / 1e3],
                                 mode="lines+markers", line=dict(color="#444", width=1), marker=dict(size=6),
                                 name=f"true closest approach: {dist / 1e3:.2f} km, {dh / FT:.0f} ft, t = {t:.0f} s"),
                      row=1, col=1)
    _shade_times(fig, ep, d.t_ref, v_min, d)
    fig.update_layout(title=dict(text=html.escape(_title(ep, rank)), x=0.01, font=dict(size=14)), height=470,
                      template=lean_template(), margin=dict(l=60, r=20, t=70, b=50), hovermode="closest",
                      legend=dict(orientation="h", y=-0.18, font=dict(size=11)))
    fig.update_xaxes(title_text="east x (km)", row=1, col=1)
    fig.update_yaxes(title_text="north y (km)", scaleanchor="x", scaleratio=1, row=1, col=1)
    fig.update_xaxes(title_text=("time from the first alert (s)" if ep.kind == "alert"
                                 else "time from the start of the loss (s)"), row=1, col=2)
    fig.update_yaxes(title_text="altitude (ft; FL = ft / 100)", row=1, col=2)
    return fig, _caption(ep, h_min, v_min, d)


def _draw_cpa(fig: go.Figure, d: _Data, cc: ConflictConfig, true: tuple | None) -> tuple[float, float]:
    """The predicted CPA of both tracks and the minima around A's; without a prediction (a
    missed loss) the minima around A's truth at the true closest approach."""
    if d.cpa is None:
        if true is None:
            return minima(cc, d.truth["h_m"].median() if d.truth.height else None)
        r = true[0]
        a = np.array([r["x_m"][0], r["y_m"][0], r["h_m"][0]])
        h_min, v_min = minima(cc, float(min(r["h_m"][0], r["h_m_b"][0])))
        _minima(fig, a, h_min, v_min, "the true closest approach")
        return h_min, v_min
    a, b, t = d.cpa
    h_min, v_min = minima(cc, float(min(a[2], b[2])))
    _minima(fig, a, h_min, v_min, "the predicted CPA")
    sep = math.hypot(*(a[:2] - b[:2]))
    for p, name, color in ((a, "A", _A), (b, "B", _B)):
        fig.add_trace(go.Scatter(x=[p[0] / 1e3], y=[p[1] / 1e3], mode="markers", showlegend=name == "A",
                                 marker=dict(symbol="x", size=11, color=color, line=dict(width=1)),
                                 name=f"predicted CPA in {t:.0f} s: {sep / 1e3:.2f} km, "
                                      f"{abs(a[2] - b[2]) / FT:.0f} ft apart", legendgroup="cpa",
                                 hovertemplate=f"{name} at the predicted CPA<extra></extra>"), row=1, col=1)
        fig.add_trace(go.Scatter(x=[t], y=[p[2] / FT], mode="markers", showlegend=False, legendgroup="cpa",
                                 marker=dict(symbol="x", size=11, color=color),
                                 hovertemplate=f"{name} at the predicted CPA: %{{y:.0f}} ft<extra></extra>"),
                      row=1, col=2)
    return h_min, v_min


def _minima(fig: go.Figure, a: np.ndarray, h_min: float, v_min: float, where: str) -> None:
    """A circle of the horizontal minimum around ``a`` (plan view) and a band of ± the vertical
    minimum around its altitude (vertical profile): B inside both is a loss of separation."""
    ang = np.linspace(0.0, 2.0 * math.pi, 73)
    fig.add_trace(go.Scatter(x=(a[0] + h_min * np.cos(ang)) / 1e3, y=(a[1] + h_min * np.sin(ang)) / 1e3,
                             mode="lines", line=dict(color="#ff7f0e", width=1.2), fill="toself",
                             fillcolor="rgba(255,127,14,0.08)", hoverinfo="skip",
                             name=f"horizontal minimum {h_min / 1852:.1f} NM around A at {where}"), row=1, col=1)
    fig.add_hrect(y0=(a[2] - v_min) / FT, y1=(a[2] + v_min) / FT, fillcolor="#ff7f0e", opacity=0.10,
                  line=dict(color="#ff7f0e", width=1), row=1, col=2)
    fig.add_trace(go.Scatter(x=[None], y=[None], mode="lines", line=dict(color="#ff7f0e", width=6),
                             name=f"vertical minimum ±{v_min / FT:.0f} ft around A at {where}"), row=1, col=2)


def _shade_times(fig: go.Figure, ep: Episode, t_ref: datetime, v_min: float, d: _Data) -> None:
    """The alert span (yellow) and the loss of separation's start (red line), vertical profile."""
    if ep.kind == "alert":
        fig.add_vrect(x0=0.0, x1=(ep.t_end - t_ref).total_seconds(), fillcolor="#ffd54f", opacity=0.25,
                      line_width=0, row=1, col=2)
    if ep.los_start is not None:
        x = (ep.los_start - t_ref).total_seconds()
        fig.add_vline(x=x, line=dict(color="#b71c1c", dash="dash", width=1.5), row=1, col=2)
    if ep.kind == "missed":
        fig.add_vrect(x0=0.0, x1=(ep.t_end - t_ref).total_seconds(), fillcolor="#ef9a9a", opacity=0.3,
                      line_width=0, row=1, col=2)


def _caption(ep: Episode, h_min: float, v_min: float, d: _Data) -> str:
    parts = [f"Solid: the picture's tracks ({ep.picture}); dotted: the truth of both aircraft."]
    if ep.kind == "alert":
        parts.append(f"Circles: the tracks at the first alert. Yellow: the alert episode "
                     f"({(ep.t_end - ep.t_start).total_seconds():.0f} s); "
                     + ("dashed red line: start of the loss of separation it warned of. " if ep.los_start else ""))
        if d.cpa is not None:
            parts.append(f"x: both tracks at the closest approach the episode's closest alert predicted (states at "
                         f"{ep.cpa_epoch:%H:%M:%S} moved straight on for T_min = {_t_min(ep):.0f} s); the circle "
                         f"is the horizontal minimum ({h_min:,.0f} m) around A, the band the vertical minimum "
                         f"(±{v_min / FT:.0f} ft) around A.")
        else:
            parts.append("No predicted CPA drawn (the picture's conflicts or tracks at the alert are not stored).")
    else:
        parts.append(f"Red: the loss of separation, which the picture did not alert; the circle and the band are "
                     f"the minima ({h_min:,.0f} m, ±{v_min / FT:.0f} ft) around A at the true closest approach; "
                     "tracks are the picture's ids nearest each aircraft's truth, circles where they were when "
                     "the loss began.")
        if ep.induced:
            parts.append("Picture-induced: the same prediction on the truth picture alerted it." if ep.induced ==
                         "picture" else "Predictor-induced: the truth picture did not alert it either.")
    return " ".join(parts)


# --------------------------------------------------------------------------- selection and HTML


def _store_of(run_dir_or_store: RunStore | str | os.PathLike[str]) -> tuple[RunStore, bool]:
    if isinstance(run_dir_or_store, RunStore):
        return run_dir_or_store, False
    text = incomplete_message(Path(run_dir_or_store))
    if text:
        raise DataError(text, path=str(run_dir_or_store))
    return open_read_only(run_dir_or_store), True


def _selected(store: RunStore, picture: str | None, n: int, pair: tuple[int, int] | None
              ) -> tuple[str | None, list[tuple[Episode, int | None]], str]:
    """(picture, [(episode, rank)], note): the ``n`` most severe alert episodes and every missed
    loss of the picture; with ``pair``, every episode of those two aircraft."""
    pics = _pictures(store)
    if picture is None:
        picture = best_alert_picture(store)
        if picture is None:
            return None, [], "No alert episodes in this run (no safety stage, no truth, or no alert)."
    elif picture not in pics:
        raise OptionError(f"no alert episodes of picture {picture!r}; the run has {', '.join(pics) or 'none'}",
                          option="--picture")
    alerts = list_episodes(store, picture, pair)
    rows = list(alerts.iter_rows(named=True)) if pair else list(alerts.head(n).iter_rows(named=True))
    chosen = [(_alert_episode(r, picture), i + 1) for i, r in enumerate(rows)]
    missed, note = missed_losses(store, picture, pair)
    note = (f"{len(rows)} of {alerts.height} alert episode(s) of {picture}, most severe first. " + note).strip()
    return picture, chosen + [(m, None) for m in missed], note


def episode_figures(run_dir_or_store: RunStore | str | os.PathLike[str], picture: str | None = None,
                    n: int = DEFAULT_EPISODES, pair: tuple[int, int] | None = None
                    ) -> tuple[str | None, list[tuple[go.Figure, str]], str]:
    """(picture, [(figure, caption)], note) of :func:`episodes_section`: the ``n`` most severe
    alert episodes of ``picture`` (default: the best picture) and every missed loss; with
    ``pair`` (two aircraft), every episode of that pair."""
    store, owned = _store_of(run_dir_or_store)
    try:
        picture, chosen, note = _selected(store, picture, n, pair)
        cc = conflict_config(run_config(store))
        return picture, [episode_figure(store, ep, rank, cc) for ep, rank in chosen], note
    finally:
        if owned:
            store.close()


def figure_div(fig: go.Figure, div_id: str) -> str:
    """A plotly figure as a ``<div>`` and a script that draws it once plotly.js is loaded (it
    may come later in the page) and then tells the page (``window.__reportDone``)."""
    spec = fig.to_json().replace("</", "<\\/")
    height = int(fig.layout.height or 460)
    return (f'<div id="{div_id}" class="plotly-graph-div" style="height:{height}px; width:100%;"></div>'
            f'<script>(function () {{ var f = {spec}; function draw() {{ Plotly.newPlot("{div_id}", f.data, '
            'f.layout, {"displaylogo": false, "responsive": true}).then(function () { if (window.__reportDone) '
            f'{{ window.__reportDone("{div_id}"); }} }}); }} if (window.Plotly) {{ draw(); }} else '
            '{ window.addEventListener("DOMContentLoaded", draw); } })();</script>')


def _figures_html(figs: list[tuple[go.Figure, str]], prefix: str) -> str:
    return "".join(f'<div class="figure">{figure_div(fig, f"{prefix}-{i}")}<p class="caption">'
                   f'{html.escape(cap)}</p></div>' for i, (fig, cap) in enumerate(figs))


def sec_episodes(ctx: Ctx) -> Section:
    """The report's section (``_SECTIONS`` form): :func:`episode_figures` of the best picture."""
    _picture, figs, note = episode_figures(ctx.store)
    return Section("episodes", "Alert episodes", text=note, figures=figs)


def episodes_section(run_dir_or_store: RunStore | str | os.PathLike[str], picture: str | None = None,
                     n: int = DEFAULT_EPISODES) -> str:
    """HTML fragment: the ``n`` most severe alert episodes of ``picture`` (default: the best
    picture) and every missed loss, one figure each, in ``<div class="episodes"
    data-figures="K">`` (K figures; each calls ``window.__reportDone`` when drawn). It needs
    plotly.js once anywhere in the page (before or after it)."""
    picture, figs, note = episode_figures(run_dir_or_store, picture, n)
    body = _figures_html(figs, "fig-episode")
    return (f'<div class="episodes" data-figures="{len(figs)}"><p class="note">{html.escape(note)}</p>'
            f'{body}</div>')


def _template(name: str) -> str:
    return resources.files("tertiary.report").joinpath("templates", name).read_text(encoding="utf-8")


_PAGE = Template("""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>$title</title>
<script>$head_script</script>
<style>$css</style>
<script>$plotly</script>
</head>
<body data-figures="$n_figures" data-rendered="0" data-js-errors="0">
<pre id="js-errors" hidden></pre>
<h1>$title</h1>
$body
</body>
</html>
""")


def page_html(title: str, body: str, n_figures: int) -> str:
    """A self-contained page in the report's style (plotly.js inline once, the report's
    JavaScript-error and rendered-figure counters on ``<body>``)."""
    return _PAGE.substitute(title=html.escape(title), head_script=_template("head.js"), css=_template("report.css"),
                            plotly=get_plotlyjs() if n_figures else "", n_figures=n_figures, body=body)


def render_episodes(run_dir_or_store: RunStore | str | os.PathLike[str], picture: str | None = None,
                    n: int = DEFAULT_EPISODES, pair: tuple[int, int] | None = None) -> tuple[str, int, str]:
    """(page, number of figures, note) of :func:`write_episodes`."""
    picture, figs, note = episode_figures(run_dir_or_store, picture, n, pair)
    title = f"Alert episodes: {picture}" if picture else "Alert episodes"
    if pair:
        title += f", aircraft {pair[0]} & {pair[1]}"
    titles = [html.unescape(f.layout.title.text) for f, _c in figs]
    index = pl.DataFrame({"figure": list(range(1, len(figs) + 1)), "episode": titles},
                         schema={"figure": pl.UInt32, "episode": pl.String})
    body = (f'<p>{html.escape(note)}</p>' + (table_html(index) if figs else "")
            + _figures_html(figs, "fig-episode"))
    return page_html(title, body, len(figs)), len(figs), note


def write_episodes(run_dir: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
                   picture: str | None = None, n: int = DEFAULT_EPISODES, pair: tuple[int, int] | None = None
                   ) -> tuple[Path, int, str]:
    """Write the episodes page (default ``RUN_DIR/episodes.html``) atomically: (path, figures, note)."""
    page, k, note = render_episodes(run_dir, picture, n, pair)
    target = Path(out) if out is not None else Path(run_dir) / EPISODES_FILENAME
    return write_text_atomic(target, page), k, note
