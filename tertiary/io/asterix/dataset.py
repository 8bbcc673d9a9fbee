"""``tertiary import asterix``: recordings → a dataset directory the pipeline runs on."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import polars as pl

from tertiary.core import geo
from tertiary.contract import TABLES
from tertiary.io.asterix import importer, plots
from tertiary.io.asterix.sites import read_sites, write_template
from tertiary.core.errors import DataError, OptionError
from tertiary.sensors.adsb import REFERENCE_MIN_NACP, REFERENCE_MIN_NIC
from tertiary.simulate.config import ScenarioConfig, scenario_toml
from tertiary.store.run_store import write_parquet_atomic, write_text_atomic


@dataclass
class ImportResult:
    """Tables of one import and its figures (``counts``), notes and the per-radar latency."""

    reports: pl.DataFrame
    radars: pl.DataFrame
    truth: pl.DataFrame
    external_tracks: pl.DataFrame
    rejects: pl.DataFrame
    antenna: pl.DataFrame
    antenna_messages: pl.DataFrame
    latency: pl.DataFrame
    #: the external picture scored (:func:`tertiary.evaluation.external.score_import`); empty until then
    external_metrics: pl.DataFrame = field(default_factory=pl.DataFrame)
    counts: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    origin: tuple[float, float, float] | None = None
    #: CAT004 STCA episodes (``alerts`` schema, picture ``external:SAC/SIC``, unscored)
    alerts: pl.DataFrame = field(default_factory=pl.DataFrame)


def import_recordings(paths: Sequence[str | Path], sites: str | Path | None = None, date: str | None = None,
                      stale_s: float = 10.0, template: str | Path | None = None,
                      origin: tuple[float, float, float] | None = None, skip_unknown: bool = False,
                      progress: Callable[[str], None] | None = None) -> ImportResult:
    """Decode ``paths`` and build the dataset tables (see :mod:`tertiary.io.asterix.importer`).

    ``sites`` is required when CAT048 is present; SAC/SICs missing from it are listed in the
    error, and ``template`` (a path) receives a sites file to fill in for them. ``origin`` (lat,
    lon, alt) is the system frame of truth and external tracks [default: mean radar site].
    ``skip_unknown`` sends reports of SAC/SICs missing from the sites file to ``rejects``
    instead of refusing the import. ``progress`` hears each of the import's parts ("part K/4 …").
    """
    say = progress or (lambda _m: None)
    if not paths:
        raise OptionError("give at least one recording file", option="FILE")
    if not (math.isfinite(stale_s) and stale_s > 0):
        raise OptionError(f"must be a positive number of seconds, got {stale_s}", option="--stale-s")
    day0 = importer.parse_date(date)
    say(f"part 1/4 decoding {len(paths)} file(s)")
    dec = importer.decode_files(paths)
    rejects = list(dec.rejects)
    main = (dec.cat048, dec.cat021, dec.cat062, dec.cat001, dec.cat020, dec.cat004)
    if not any(c.height for c in main):
        first = "; ".join(dict.fromkeys(str(r["reason"]) for r in rejects[:50]))[:300] or "no data block"
        raise DataError(f"no CAT048, CAT021 or CAT062 record decoded (nor CAT001, CAT020 or CAT004) from "
                        f"{', '.join(map(str, paths))} ({len(rejects)} problem(s): {first})")
    undated = [c for c in (*main, dec.cat034, dec.cat002) if c.height and c["capture_s"].is_nan().any()]
    if day0 is None and undated:
        raise OptionError("the recording has no capture time stamps (raw data blocks carry only the time of day); "
                          "give the date of the recording", option="--date")
    codes = pl.concat([c.filter(pl.col("sac") >= 0).select("sac", "sic") for c in (dec.cat048, dec.cat001, dec.cat020)
                       if c.height] or [dec.cat048.select("sac", "sic")]).unique().sort("sac", "sic")
    table = read_sites(sites) if sites is not None else None
    if not (skip_unknown and table is not None):
        _check_sites(codes, table, sites, template, dec.cat034, day0)
    # CAT021 of the ADS-B ground stations of the sites file are reports, the rest truth
    station = plots.adsb_station_rows(dec.cat021, table)
    adsb, cat021 = dec.cat021.filter(station), dec.cat021.filter(~station)
    codes = pl.concat([codes, adsb.select("sac", "sic").unique()]).unique().sort("sac", "sic")
    say("part 2/4 reports")
    reports, rej, latency, counts = importer.build_reports(dec.cat048, table, day0, stale_s)
    rejects += rej
    reports, more = _other_reports(reports, dec, adsb, table, day0, stale_s, rejects)
    counts |= more
    service = pl.concat([dec.cat034, dec.cat002.drop("seq")], how="vertical_relaxed") if dec.cat002.height \
        else dec.cat034
    messages, timing = importer.antenna_timing(service, day0)
    notes: list[str] = []
    if table is not None:
        radars, notes = importer.radars_table(table, timing, codes)
        unknown = codes.join(table, on=["sac", "sic"], how="anti")
        if unknown.height:
            notes.append(f"{counts['unknown_site']:,} report(s) of SAC/SIC "
                         f"{', '.join(f'{a}/{b}' for a, b in unknown.rows())} not in the sites file went to rejects")
    else:
        radars = pl.DataFrame()
    say("part 3/4 truth, external tracks and alerts")
    origin = tuple(origin) if origin is not None else _origin(radars, dec)
    system = geo.LocalFrame(*origin) if origin is not None else None
    truth = tracks = pl.DataFrame()
    if cat021.height and system is not None:
        truth, rej, counts["truth_below_quality"] = importer.truth_table(cat021, system, day0, REFERENCE_MIN_NACP,
                                                                         REFERENCE_MIN_NIC)
        rejects += rej
        notes.append(f"truth (CAT021): the reference keeps points whose I021/090 declares NACp >= "
                     f"{REFERENCE_MIN_NACP} and NIC >= {REFERENCE_MIN_NIC} (points without I021/090 are kept); "
                     f"{counts['truth_below_quality']:,} point(s) below it went to rejects")
    if truth.height and reports.height:
        reports = label_reports(reports, truth)
    if dec.cat062.height and system is not None:
        tracks, rej = importer.external_tracks(dec.cat062, system, day0)
        rejects += rej
    alerts = pl.DataFrame()
    if dec.cat004.height:
        alerts, rej, more = plots.alerts_table(dec.cat004, day0)
        rejects += rej
        counts |= more
    say("part 3/4 done")
    # distinct service messages of both categories (CAT002 joins CAT034 in the antenna timing)
    counts |= dec.counts | {"cat034_messages": dec.cat034.height, "cat002_messages": dec.cat002.height,
                            "cat034_distinct": messages.height,
                            "cat021_records": dec.cat021.height, "cat021_truth_records": cat021.height,
                            "cat062_records": dec.cat062.height,
                            "radars": codes.height, "reports": reports.height, "rejects": len(rejects)}
    return ImportResult(reports, radars, truth, tracks, importer.rejects_frame(rejects), timing, messages,
                        latency.join(radars.select("sac", "sic", "radar_id"), on=["sac", "sic"], how="left")
                        if radars.height else latency, pl.DataFrame(), counts, notes, origin, alerts)


def _other_reports(reports: pl.DataFrame, dec: importer.Decoded, adsb: pl.DataFrame, sites: pl.DataFrame | None,
                   day0: float | None, stale_s: float, rejects: list[dict[str, object]]
                   ) -> tuple[pl.DataFrame, dict[str, int]]:
    """CAT048 reports with the CAT001, CAT020 and ADS-B station (``adsb``: CAT021) reports
    appended (report ids renumbered)."""
    parts, counts = [reports], {}
    if dec.cat001.height:
        rep, rej, c = plots.cat001_reports(dec.cat001, dec.cat002, sites, day0, stale_s)
        parts.append(rep), rejects.extend(rej), counts.update(c)
    if dec.cat020.height:
        rep, rej, c = plots.cat020_reports(dec.cat020, sites, day0, stale_s)
        parts.append(rep), rejects.extend(rej), counts.update(c)
    if adsb.height:
        rep, rej, c = plots.cat021_reports(adsb, sites, day0, stale_s)
        parts.append(rep), rejects.extend(rej), counts.update(c)
    if len(parts) == 1:
        return reports, counts
    out = pl.concat([p for p in parts if p.width], how="diagonal_relaxed")
    return out.with_columns(pl.int_range(pl.len(), dtype=pl.UInt64).alias("report_id")), counts


def external_alerts(paths: Sequence[str | Path], date: str | None = None, gap_s: float = 30.0) -> pl.DataFrame:
    """The CAT004 STCA alerts of recordings as ``alerts`` rows (picture ``external:SAC/SIC``,
    ``classification`` "unscored"): the frame to score against the truth."""
    dec = importer.decode_files(paths)
    if dec.cat004.height == 0:
        return pl.DataFrame(schema=dict(TABLES["alerts"].required) | plots.ALERT_EXTRA)
    return plots.alerts_table(dec.cat004, importer.parse_date(date), gap_s)[0]


def label_reports(reports: pl.DataFrame, truth: pl.DataFrame) -> pl.DataFrame:
    """``truth_id`` of each report = its Mode S address when the ADS-B truth has that address
    (CAT021 truth_id is the 24-bit address); null otherwise, so evaluation can score the picture."""
    address = pl.col("mode_s").str.to_integer(base=16, strict=False)
    known = truth["truth_id"].unique().implode()
    return reports.with_columns(pl.when(address.is_in(known)).then(address).otherwise(None)
                                .cast(pl.Int64).alias("truth_id"))


def _check_sites(codes: pl.DataFrame, table: pl.DataFrame | None, sites: str | Path | None,
                 template: str | Path | None, cat034: pl.DataFrame, day0: float | None) -> None:
    if not codes.height:
        return
    have = set() if table is None else set(table.select("sac", "sic").iter_rows())
    missing = [c for c in codes.iter_rows() if c not in have]
    if not missing:
        return
    listed = ", ".join(f"{a}/{b}" for a, b in missing)
    if template is not None:
        _, timing = importer.antenna_timing(cat034, day0) if cat034.height else (None, pl.DataFrame(
            schema={"sac": pl.Int64, "sic": pl.Int64, "scan_period_s": pl.Float64}))
        scan = {(a, b): p for a, b, p in timing.select("sac", "sic", "scan_period_s").iter_rows()}
        write_template(template, missing, scan)
        raise DataError(f"SAC/SIC {listed} not in the sites file; wrote a template to fill in: {template}")
    if table is None:
        raise OptionError(f"the recording holds CAT048 reports of SAC/SIC {listed}: give --sites SITES.toml "
                          "(or --write-sites-template FILE to get one to fill in)", option="--sites")
    raise DataError(f"SAC/SIC {listed} not in {sites}; add them (--write-sites-template FILE writes a template)")


def _origin(radars: pl.DataFrame, dec: importer.Decoded) -> tuple[float, float, float] | None:
    if radars.height:
        return importer.origin_of(radars, None)
    for frame in (dec.cat021, dec.cat062):
        ok = frame.filter(pl.col("lat_deg").is_between(-90, 90) & pl.col("lon_deg").is_between(-180, 180)) \
            if frame.height else frame
        if ok.height:
            return float(ok["lat_deg"].median()), float(ok["lon_deg"].median()), 0.0
    return None


def write_import(result: ImportResult, out: str | Path, name: str) -> Path:
    """Write the dataset directory (atomic files): reports, radars, [truth], [external_tracks],
    [alerts], rejects, antenna, latency Parquet files and a scenario.toml holding the system origin."""
    d = Path(out)
    if d.exists() and not d.is_dir():
        raise DataError("exists and is not a directory", path=str(d))
    d.mkdir(parents=True, exist_ok=True)
    tables = {"reports": result.reports, "radars": result.radars, "rejects": result.rejects,
              "antenna": result.antenna, "latency": result.latency}
    if result.truth.height:
        tables["truth"] = result.truth
    if result.external_tracks.height:
        tables["external_tracks"] = result.external_tracks
    if result.external_metrics.height:
        tables["external_metrics"] = result.external_metrics
    if result.alerts.height:
        tables["alerts"] = result.alerts
    for key, frame in tables.items():
        write_parquet_atomic(frame, d / f"{key}.parquet")
    for key in {"truth", "external_tracks", "external_metrics", "alerts"} - set(tables):   # of an earlier import
        (d / f"{key}.parquet").unlink(missing_ok=True)
    if result.origin is not None:
        write_text_atomic(d / "scenario.toml", scenario_toml(ScenarioConfig(name=name, kind="terminal-area",
                                                                            origin=result.origin)))
    return d
