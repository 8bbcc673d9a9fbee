"""`tertiary import asterix` and `tertiary export asterix` (typer sub-apps registered by :mod:`tertiary.cli.commands`)."""

from __future__ import annotations

import json
import time
import tomllib
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import polars as pl
import typer
from rich.table import Table

from tertiary.cli.common import Steps, console, parse_origin, print_note
from tertiary.core import geo
from tertiary.core.errors import DataError, OptionError
from tertiary.evaluation.external import score_import
from tertiary.io.asterix.dataset import import_recordings, write_import
from tertiary.io.asterix.encode import export_alerts, export_picture
from tertiary.pipeline.workflows import check_writable_dir
from tertiary.store.run_store import RunStore

import_app = typer.Typer(help="Import recordings from other formats into a dataset directory.",
                         no_args_is_help=True, rich_markup_mode=None)
export_app = typer.Typer(help="Export a run's picture to other formats.", no_args_is_help=True, rich_markup_mode=None)


@import_app.command("asterix")
def import_asterix(
    files: Annotated[list[Path], typer.Argument(
        metavar="FILE", help="pcap/pcapng captures (UDP payloads) or raw ASTERIX data-block files; CAT048, CAT034, "
                             "CAT001, CAT002, CAT020, CAT021, CAT062, CAT004 may be mixed (CAT021 of a sites "
                             "entry of kind adsb: reports; other CAT021: truth)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="dataset directory to write")],
    sites: Annotated[Optional[Path], typer.Option(help="SAC/SIC -> radar registry TOML (required with CAT048, "
                                                       "CAT001, CAT020, and for an ADS-B station's CAT021; "
                                                       "see docs/asterix.md)")] = None,
    date: Annotated[Optional[str], typer.Option(help="YYYY-MM-DD the recording starts on [default: the capture "
                                                     "time stamps; required for raw data blocks]")] = None,
    write_sites_template: Annotated[Optional[Path], typer.Option(
        help="write a sites TOML to fill in for the SAC/SICs missing from --sites")] = None,
    stale_s: Annotated[float, typer.Option(help="a report older than its radar's latest by more than this many "
                                                "seconds is flagged stale")] = 10.0,
    origin: Annotated[Optional[str], typer.Option(help="LAT,LON[,ALT_M] system origin of truth and external tracks "
                                                       "[default: mean radar site]")] = None,
    skip_unknown_sites: Annotated[bool, typer.Option(help="send reports of SAC/SICs missing from --sites to rejects "
                                                          "instead of refusing the import")] = False,
    force: Annotated[bool, typer.Option(help="replace a dataset already in OUT")] = False,
) -> None:
    """Decode ASTERIX recordings into reports/radars/[truth]/[external_tracks]/rejects Parquet files."""
    check_writable_dir(out, "--out")
    if (out / "reports.parquet").exists() and not force:
        raise OptionError(f"{out} already holds a dataset; give --force to replace it", option="--out")
    for f in files:
        if not f.is_file():
            raise DataError("no such file" if not f.exists() else "not a file", path=str(f))
    t = time.perf_counter()
    with Steps("import") as say:
        res = score_import(import_recordings(files, sites=sites, date=date, stale_s=stale_s,
                                             template=write_sites_template, origin=parse_origin(origin),
                                             skip_unknown=skip_unknown_sites, progress=say))
        say("part 4/4 writing the dataset")
        name = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in out.resolve().name).strip("_-") or "asterix"
        write_import(res, out, name[:64])
    c = res.counts
    console.print(f"wrote {out}/ in {time.perf_counter() - t:.1f} s: {c['reports']:,} reports from {c['radars']} "
                  f"radar(s) ({c['cat048_records']:,} CAT048 records, {c['duplicates']:,} redundant copies removed, "
                  f"{c['distinct']:,} distinct), {c['cat034_messages']:,} CAT034 messages{_and_002(c)} "
                  f"({c['cat034_distinct']:,} distinct), {res.truth.height:,} truth rows (CAT021), "
                  f"{res.external_tracks.height:,} external track rows (CAT062), {res.rejects.height:,} rejects",
                  soft_wrap=True)
    more = [f"{c[f'cat{k}_reports']:,} {what} reports (CAT{k})"
            for k, what in (("001", "legacy radar"), ("020", "MLAT"), ("021", "ADS-B ground station"))
            if f"cat{k}_reports" in c]
    if res.alerts.height:
        more.append(f"{res.alerts.height:,} STCA alert episodes (CAT004, alerts.parquet)")
    if more:
        console.print("of which " + ", ".join(more), soft_wrap=True)
    for note in res.notes:
        console.print(f"note: {note}", soft_wrap=True)
    if res.latency.height:
        _latency_table(res.latency)
    for method, metric, value in res.external_metrics.filter(
            (pl.col("segment") == "all") & pl.col("metric").is_in(["rmse_horizontal_m", "rmse_height_m"])
    ).select("method", "metric", "value").iter_rows() if res.external_metrics.height else []:
        console.print(f"external picture {method} against the ADS-B truth: {metric} {value:,.1f} m")


def _and_002(counts: dict[str, int]) -> str:
    """The CAT002 service messages of the recording, when any (distinct ones counted with CAT034's)."""
    return f" and {counts['cat002_messages']:,} CAT002" if counts.get("cat002_messages") else ""


def _latency_table(latency: pl.DataFrame) -> None:
    table = Table(title="per-radar latency: capture time - time of day (s)")
    for col in ("SAC/SIC", "records", "min", "median", "p95", "max", "stale", "out of order"):
        table.add_column(col, justify="right")
    for r in latency.iter_rows(named=True):
        table.add_row(f"{r['sac']}/{r['sic']}", f"{r['records']:,}", *(f"{r[k]:.3f}" for k in (
            "latency_min_s", "latency_median_s", "latency_p95_s", "latency_max_s")), str(r["stale"]),
            str(r["out_of_order"]))
    console.print(table)


def _picture(run_dir: Path, name: str) -> tuple[pl.DataFrame, tuple[float, float, float]]:
    """The rows of picture NAME (FILTER/METHOD from tracks, or fused/METHOD) and the run's origin."""
    if not (run_dir / "results.duckdb").is_file():
        raise DataError("no run database here (expected results.duckdb)", path=str(run_dir))
    kind, sep, method = name.partition("/")
    if not sep or not kind or not method:
        raise OptionError(f"expected FILTER/METHOD (a tracker picture) or fused/METHOD, got {name!r}",
                          option="--picture")
    with RunStore.open(run_dir, read_only=True) as store:
        record = dict(store.sql("SELECT key, value FROM run").iter_rows())
        table = "fused" if kind == "fused" else "tracks"
        if table not in store.tables():
            raise DataError(f"the run has no {table} table", path=str(run_dir))
        frame = store.read(table)
    frame = frame.filter(pl.col("method") == method) if kind == "fused" else \
        frame.filter((pl.col("filter") == kind) & (pl.col("method") == method))
    if frame.height == 0:
        raise OptionError(f"no picture {name!r} in {run_dir}", option="--picture")
    if kind == "fused":
        frame = frame.with_columns(pl.col("target_id").alias("track_id"))
        if "cov" in frame.columns:
            cov = np.stack(frame["cov"].to_numpy()).reshape(-1, 36)[:, ::7]
            frame = frame.with_columns(pl.Series("cov_diag", cov, pl.Array(pl.Float64, 6)))
    try:
        text = record.get("scenario_toml", "")
        text = json.loads(text) if text.startswith('"') else text
        origin = tomllib.loads(text)["origin"]
    except (tomllib.TOMLDecodeError, KeyError, TypeError, json.JSONDecodeError) as exc:
        raise DataError(f"the run records no system origin ({exc})", path=str(run_dir)) from exc
    return frame, (float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) > 2 else 0.0)


@export_app.command("asterix")
def export_asterix(
    run_dir: Annotated[Path, typer.Argument(help="run directory holding results.duckdb")],
    picture: Annotated[str, typer.Option(help="FILTER/METHOD (e.g. singer/information) or fused/METHOD")],
    out: Annotated[Path, typer.Option("--out", "-o", help="ASTERIX file to write (CAT062 data blocks)")],
    run: Annotated[int, typer.Option(help="Monte-Carlo run to export")] = 0,
    alerts: Annotated[bool, typer.Option(help="write the picture's STCA alert episodes as CAT004 instead of its "
                                              "tracks")] = False,
) -> None:
    """Write a picture of a run as CAT062 system tracks (position, velocity, accuracy, identity),
    or with --alerts its STCA alerts as CAT004."""
    if out.is_dir():
        raise OptionError(f"{out} is a directory; give a file name", option="--out")
    if alerts:
        _export_alerts(run_dir, picture, out, run)
        return
    frame, origin = _picture(run_dir, picture)
    frame = frame.filter(pl.col("run") == run)
    if frame.height == 0:
        raise OptionError(f"picture {picture!r} has no rows in run {run}", option="--run")
    t = time.perf_counter()
    n = export_picture(frame, geo.LocalFrame(*origin), out)
    console.print(f"wrote {out} ({n:,} CAT062 records, {out.stat().st_size / 1e6:.2f} MB) in "
                  f"{time.perf_counter() - t:.1f} s; system origin {origin[0]:.5f}, {origin[1]:.5f}", soft_wrap=True)
    if "cov_diag" not in frame.columns:
        print_note("I062/500 accuracy not written: the run stored no covariances (run it with --tables full "
                   "to keep them)")


def _export_alerts(run_dir: Path, picture: str, out: Path, run: int) -> None:
    """The alerts rows of PICTURE (the ``method`` of the run's ``alerts`` table) as CAT004."""
    if not (run_dir / "results.duckdb").is_file():
        raise DataError("no run database here (expected results.duckdb)", path=str(run_dir))
    with RunStore.open(run_dir, read_only=True) as store:
        if "alerts" not in store.tables():
            raise DataError("the run has no alerts table (run with conflict alerts and a truth)", path=str(run_dir))
        frame = store.read("alerts")
    rows = frame.filter((pl.col("method") == picture) & (pl.col("run") == run))
    if rows.height == 0:
        known = ", ".join(sorted(frame["method"].unique().to_list())) or "none"
        raise OptionError(f"no alerts of picture {picture!r} in run {run} (pictures with alerts: {known})",
                          option="--picture")
    t = time.perf_counter()
    n = export_alerts(rows, out)
    console.print(f"wrote {out} ({n:,} CAT004 STCA records of {rows.height:,} alert episodes) in "
                  f"{time.perf_counter() - t:.1f} s", soft_wrap=True)
