"""The end-of-run summary, read from a run database: plain lines a command prints."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import polars as pl

from tertiary.store.run_store import RunStore


def _metric(metrics: pl.DataFrame, stage: str, metric: str) -> pl.DataFrame:
    if metrics.height == 0:
        return metrics
    return metrics.filter((pl.col("stage") == stage) & (pl.col("metric") == metric) & (pl.col("segment") == "all"))


def _value(frame: pl.DataFrame, method: str) -> float | None:
    row = frame.filter(pl.col("method") == method)
    return float(row["value"][0]) if row.height else None


def _m(v: float | None, unit: str = " m") -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:,.1f}{unit}"


def _json_or_text(text: str) -> Any:
    try:
        return json.loads(text)
    except (json.JSONDecodeError, TypeError):
        return text


def _read(db: Path) -> tuple[dict[str, Any], pl.DataFrame, int, int]:
    """The run record, the metrics, the number of reference aircraft and of Monte-Carlo runs."""
    with RunStore.open(db.parent, read_only=True) as store:
        tables = set(store.tables())
        record = {k: _json_or_text(v) for k, v in store.sql("SELECT key, value FROM run").iter_rows()}
        metrics = store.sql("SELECT * FROM metrics") if "metrics" in tables else pl.DataFrame()
        aircraft = (int(store.sql("SELECT count(DISTINCT truth_id) AS n FROM truth")["n"][0])
                    if "truth" in tables else 0)
        n_runs = (int(store.sql("SELECT count(DISTINCT run) AS n FROM reports")["n"][0])
                  if "reports" in tables else 1)
    return record, metrics, aircraft, n_runs


def _accuracy_lines(metrics: pl.DataFrame) -> list[str]:
    """Horizontal, vertical and 3-D RMSE of every fused and tracker picture."""
    lines = []
    tracks = _metric(metrics, "tracker", "tracks")
    for stage in ("fusion", "tracker"):
        horiz, height = _metric(metrics, stage, "rmse_horizontal_m"), _metric(metrics, stage, "rmse_height_m")
        pos = _metric(metrics, stage, "rmse_pos_m")
        for method in sorted(pos["method"].unique().to_list() if pos.height else []):
            n = _value(tracks, method) if stage == "tracker" else None
            lines.append(f"  {stage:8s} {method:28s} RMSE horizontal {_m(_value(horiz, method)):>9s}, "
                         f"vertical {_m(_value(height, method)):>9s}, 3-D {_m(_value(pos, method)):>9s}"
                         + (f"; {n:,.0f} confirmed tracks" if n is not None else ""))
    return lines


def _safety_lines(metrics: pl.DataFrame, rows: dict[str, Any]) -> list[str]:
    """Alert episodes of every picture, scored against the real losses of separation."""
    lines = []
    per_hour = _metric(metrics, "safety", "alerts_per_hour")
    if per_hour.height:
        lines.append("safety (alert episodes per aircraft pair, scored against real losses of separation):")
    for method in sorted(per_hour["method"].unique().to_list() if per_hour.height else []):
        v = {k: _value(_metric(metrics, "safety", k), method) for k in
             ("genuine_alerts", "nuisance_alerts", "false_alerts", "undetermined_alerts", "los_episodes", "alerted_los",
              "missed_los", "warning_median_s", "alerts_picture_induced", "false_alerts_picture_induced",
              "nuisance_alerts_picture_induced", "undetermined_alerts_picture_induced", "missed_los_picture_induced",
              "missed_los_under_way")}
        count = lambda k: "–" if v[k] is None or not math.isfinite(v[k]) else f"{v[k]:,.0f}"  # noqa: E731
        line = (f"  safety   {method:28s} {_m(_value(per_hour, method), ' alerts/h')}: {count('genuine_alerts')} "
                f"genuine, {count('nuisance_alerts')} nuisance, {count('false_alerts')} false, "
                f"{count('undetermined_alerts')} undetermined; losses of "
                f"separation {count('los_episodes')}, alerted {count('alerted_los')}, missed "
                f"{count('missed_los')}; median warning {_m(v['warning_median_s'], ' s')}")
        if v["alerts_picture_induced"] is not None:
            # what a better picture can remove (the truth picture does not raise them)
            line += (f"; picture-induced: {count('alerts_picture_induced')} alerts ({count('false_alerts_picture_induced')}"
                     f" false, {count('nuisance_alerts_picture_induced')} nuisance, "
                     f"{count('undetermined_alerts_picture_induced')} undetermined), "
                     f"{count('missed_los_picture_induced')} missed losses; "
                     f"{count('missed_los_under_way')} missed losses under way when first observed")
        lines.append(line)
    if not per_hour.height and rows.get("alert_rows"):
        lines.append(f"alerts: {rows['alert_rows']:,} alert rows (no truth to score them against)")
    return lines


def run_summary(db: Path) -> list[str]:
    """The end-of-run summary of the run database ``db`` as plain lines: input and rejects, targets
    against aircraft, the horizontal and vertical accuracy of every picture, alerts and losses of
    separation, the first notes."""
    record, metrics, aircraft, n_runs = _read(db)
    rows, timings = record.get("rows", {}), record.get("timings", {})
    wall = timings.get("wall_s", timings.get("total_s"))
    lines = [f"run {record.get('scenario', '?')}: {rows.get('reports_in', 0):,} reports in, "
             f"{rows.get('reports_rejected', 0):,} rejected; wall time {_m(wall, ' s')}"]
    runs_text = f" in each of {n_runs} Monte-Carlo runs" if n_runs > 1 else ""
    for_aircraft = f" for {aircraft} aircraft{runs_text}" if aircraft else ""
    if "confirmed_targets" in rows:
        over = " (summed over runs)" if n_runs > 1 else ""
        lines.append(f"system targets: {rows['confirmed_targets']} confirmed{over}{for_aircraft} "
                     f"({rows.get('tentative_targets', 0)} tentative, clutter-only, kept in fused with their flag)")
    else:
        lines.append(f"system targets (fused, clutter-only ones included): {rows.get('targets', '–')}{for_aircraft}")
    lines += _accuracy_lines(metrics)
    lines += _safety_lines(metrics, rows)
    for note in record.get("notes", [])[:5]:
        lines.append(f"note: {note}")
    return lines
