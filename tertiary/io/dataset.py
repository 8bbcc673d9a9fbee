"""Datasets on disk: the ``radars``, ``reports`` and ``truth`` tables (and the optional
``truth_removed``, ``flight_plans`` and another system's alert list ``alerts``) as Parquet files
beside ``scenario.toml``, single files or window by window in parts listed in ``parts.json``. The
run reads its input here, whether the simulator (:mod:`tertiary.simulate`), the ASTERIX importer
or a user wrote it.

A dataset's scenario is a :class:`~tertiary.simulate.config.ScenarioConfig`: this module imports
that configuration module (plain dataclasses and their TOML form) from the simulator package,
nothing else of it.
"""

from __future__ import annotations

import dataclasses
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import polars as pl

from tertiary.core import geo
from tertiary.core.errors import DataError, OptionError
from tertiary.simulate.config import ScenarioConfig, check_name, check_origin, read_scenario_toml, scenario_toml
from tertiary.store.run_store import write_parquet_atomic, write_text_atomic

__all__ = ["Dataset", "read_dataset", "write_dataset", "dataset_dir", "PARTS_MANIFEST", "PARTITIONED", "ROW_GROUPS"]

#: layout of a partitioned dataset: <table>/part-NNNN.parquet, listed in parts.json (written last)
PARTS_MANIFEST = "parts.json"
PARTITIONED = ("reports", "truth")
#: Parquet row groups of the dataset's tables: small enough that a reader of one time window
#: (``tertiary run``, :class:`tertiary.runtime.windows.ReportSource`) skips the groups outside it by their
#: time statistics
ROW_GROUPS = {"row_group_size": 16_384, "statistics": True}


@dataclass
class Dataset:
    """A simulated (or loaded) dataset: the three input tables and the scenario definition."""

    radars: pl.DataFrame
    reports: pl.DataFrame
    truth: pl.DataFrame
    scenario: ScenarioConfig
    removed: pl.DataFrame = field(default_factory=pl.DataFrame)   # truth rows dropped by ADS-B cleaning
    #: the controllers' cleared levels by Mode 3/A code (tertiary.stages.flight_data; empty: none)
    flight_plans: pl.DataFrame = field(default_factory=pl.DataFrame)
    notes: list[str] = field(default_factory=list)                # how the dataset was completed on load
    #: another system's alert list (``alerts`` schema, ``external:SAC/SIC``, unscored; empty: none),
    #: scored beside the pictures' alerts (:func:`safety.alerts.score_external`)
    external_alerts: pl.DataFrame = field(default_factory=pl.DataFrame)

    @property
    def origin(self) -> geo.LocalFrame:
        """The system frame (ENU at the scenario origin); a missing or invalid origin is a
        :class:`DataError` (the frame of every report depends on it)."""
        try:
            return geo.LocalFrame(*check_origin(self.scenario.origin))
        except OptionError as exc:
            raise DataError(f"scenario {self.scenario.name!r}: {exc} (give --origin LAT,LON)") from exc


def dataset_dir(out_dir: str | Path) -> Path:
    """``out_dir`` created if needed, or a :class:`DataError` naming it."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DataError("exists and is not a directory; give a dataset directory", path=str(out))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create the dataset directory: {exc.strerror or exc}", path=str(out)) from exc
    return out


def write_dataset(ds: Dataset, out_dir: str | Path) -> Path:
    """Write radars/reports/truth Parquet files and ``scenario.toml`` atomically (single files;
    window by window into parts: :func:`tertiary.simulate.write_stream`)."""
    out = dataset_dir(out_dir)
    (out / PARTS_MANIFEST).unlink(missing_ok=True)      # a single-file dataset now, not a partitioned one
    for name in ("radars", "reports", "truth"):
        write_parquet_atomic(getattr(ds, name), out / f"{name}.parquet", **ROW_GROUPS)
    if ds.removed.height:
        write_parquet_atomic(ds.removed, out / "truth_removed.parquet")
    if ds.flight_plans.height:
        write_parquet_atomic(ds.flight_plans, out / "flight_plans.parquet")
    else:
        (out / "flight_plans.parquet").unlink(missing_ok=True)
    if ds.external_alerts.height:
        write_parquet_atomic(ds.external_alerts, out / "alerts.parquet")
    write_text_atomic(out / "scenario.toml", scenario_toml(ds.scenario))
    return out


def _read_table(path: Path, required: bool) -> pl.DataFrame:
    """One Parquet table of a dataset; a missing (when required) or unreadable file is a
    :class:`DataError` naming it."""
    if not path.exists():
        if required:
            raise DataError("missing (a dataset needs radars.parquet and reports.parquet)", path=str(path))
        return pl.DataFrame()
    if not path.is_file():
        raise DataError("not a file", path=str(path))
    try:
        return pl.read_parquet(path)
    except Exception as exc:  # polars, pyarrow and OS errors alike: the file is unusable
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        size = path.stat().st_size
        what = "empty file" if size == 0 else f"not a readable Parquet file ({type(exc).__name__}: {text[:160]})"
        raise DataError(what, path=str(path)) from exc


def _scan_table(path: Path, required: bool) -> pl.LazyFrame | pl.DataFrame:
    """One Parquet table as a lazy scan (its schema read now, so an unreadable file is a
    :class:`DataError` here, not in the middle of a run); a missing optional table is empty."""
    if not path.exists():
        return _read_table(path, required)
    try:
        pl.read_parquet_schema(path)
    except Exception:  # the eager reader says precisely why
        return _read_table(path, required)
    return pl.scan_parquet(path)


def _read_parts(d: Path, lazy: bool = False) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Reports and truth of a partitioned dataset (:func:`tertiary.simulate.write_stream`): the parts listed in
    ``parts.json``, in window order, each checked against its row count. A dataset without the
    manifest (a simulation still running or killed) or with a missing or short part is a
    :class:`DataError` naming the file."""
    manifest = d / PARTS_MANIFEST
    if not manifest.is_file():
        raise DataError("partitioned dataset without parts.json: incomplete (still being written, or its "
                        "simulation was interrupted)", path=str(d / "reports"))
    try:
        parts = json.loads(manifest.read_text())["parts"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"unreadable parts manifest: {exc}", path=str(manifest)) from exc
    tables = []
    for name in PARTITIONED:
        frames, files = [], []
        for p in parts:
            path = d / name / f"part-{int(p['window']):04d}.parquet"
            if lazy:
                frame = _scan_table(path, True)
                height = frame.select(pl.len()).collect().item() if isinstance(frame, pl.LazyFrame) else frame.height
            else:
                frame = _read_table(path, True)
                height = frame.height
            if height != p.get(f"{name}_rows", height):
                raise DataError(f"{height} rows, parts.json says {p[f'{name}_rows']}", path=str(path))
            if height or not lazy:
                frames.append(frame)
                files.append(path)
        if lazy:
            tables.append(pl.scan_parquet(files) if files else pl.DataFrame())
            continue
        nonempty = [f for f in frames if f.width]
        tables.append(pl.concat(nonempty, how="vertical") if nonempty else pl.DataFrame())
    return tables[0], tables[1]


def _height(frame: pl.DataFrame | pl.LazyFrame) -> int:
    return frame.select(pl.len()).collect().item() if isinstance(frame, pl.LazyFrame) else frame.height


def _site_origin(radars: pl.DataFrame) -> tuple[float, float, float] | None:
    """Mean site of the radars whose lat/lon are valid numbers on the globe (alt 0), or None."""
    if not {"lat_deg", "lon_deg"} <= set(radars.columns):
        return None
    try:
        sites = radars.select(pl.col("lat_deg").cast(pl.Float64, strict=False),
                              pl.col("lon_deg").cast(pl.Float64, strict=False))
    except pl.exceptions.PolarsError:
        return None
    ok = sites.filter(pl.col("lat_deg").is_between(-90, 90) & pl.col("lon_deg").is_between(-180, 180))
    if ok.height == 0:
        return None
    return float(ok["lat_deg"].mean()), float(ok["lon_deg"].mean()), 0.0


def read_dataset(path: str | Path, origin: tuple[float, ...] | None = None, lazy: bool = False) -> Dataset:
    """Load a dataset directory written by :func:`write_dataset` (or hand-made with the same files).

    ``origin`` (lat, lon[, alt]) overrides the scenario's system origin. Without
    ``scenario.toml`` the origin is ``origin`` or else the mean of the radar sites (a note in
    ``Dataset.notes`` says so; truth, whose ENU positions need the frame's origin, is then not
    used, with a note) and the scenario name is the directory name made an identifier.
    Every problem (missing or unreadable file, malformed TOML, bad origin or name) is a
    :class:`DataError` naming the file. ``lazy``: reports and truth are Parquet scans
    (:class:`polars.LazyFrame`), read window by window by the run (:mod:`tertiary.runtime.windows`).
    """
    d = Path(path)
    if not d.is_dir():
        raise DataError("not a dataset directory" if d.exists() else "no such dataset directory", path=str(d))
    radars = _read_table(d / "radars.parquet", True)
    if (d / PARTS_MANIFEST).exists() or ((d / "reports").is_dir() and not (d / "reports.parquet").exists()):
        reports, truth = _read_parts(d, lazy)
    else:
        read = _scan_table if lazy else _read_table
        reports = read(d / "reports.parquet", True)
        truth = read(d / "truth.parquet", False)
    removed = _read_table(d / "truth_removed.parquet", False)
    plans = _read_table(d / "flight_plans.parquet", False)
    external = _read_table(d / "alerts.parquet", False)
    notes: list[str] = []
    if origin is not None:
        try:
            origin = check_origin(origin)
        except OptionError as exc:
            raise OptionError(str(exc).split(": ", 1)[-1], option="origin (--origin)") from exc
    toml = d / "scenario.toml"
    if toml.exists():
        scen = read_scenario_toml(toml)
        try:
            check_name(scen.name)
            # the file is validated whole: a bad origin is an error even when --origin overrides it
            if scen.origin is not None:
                check_origin(scen.origin)
            elif origin is None:
                raise OptionError("missing (give origin = [lat, lon, alt] or --origin LAT,LON)", option="origin")
        except OptionError as exc:
            raise DataError(str(exc), path=str(toml)) from exc
    else:
        name = re.sub(r"[^A-Za-z0-9_-]", "_", d.resolve().name).lstrip("_-")[:64] or "dataset"
        scen = ScenarioConfig(name=name, kind="terminal-area")
        notes.append(f"{d}: no scenario.toml; scenario name {name!r}")
        if origin is None:
            origin = _site_origin(radars)
            if origin is None:
                raise DataError("no scenario.toml and no radar site to place the system origin: give the origin "
                                "(--origin LAT,LON)", path=str(d))
            notes.append(f"system origin = mean radar site ({origin[0]:.5f}, {origin[1]:.5f}, 0 m)")
            if _height(truth):
                # truth holds ENU positions of a frame whose origin only scenario.toml (or the user)
                # knows; scored in a guessed frame it would give kilometre "errors" that are not
                notes.append(f"{d / 'truth.parquet'}: not used — its ENU positions are in a frame this dataset "
                             "does not name (no scenario.toml); give --origin LAT,LON of that frame to score "
                             "against it")
                truth = truth.clear()
    if origin is not None:
        scen = dataclasses.replace(scen, origin=tuple(origin))
    return Dataset(radars=radars, reports=reports, truth=truth, scenario=scen, removed=removed, notes=notes,
                   flight_plans=plans, external_alerts=external)
