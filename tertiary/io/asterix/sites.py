"""The SAC/SIC → radar registry (sites TOML) of an ASTERIX import.

ASTERIX reports name their radar only by SAC/SIC (I048/010); position and nominal accuracy
come from this file::

    [[radar]]
    sac = 25                     # system area code
    sic = 201                    # system identification code
    name = "ZAG-1"               # optional [default: "SAC-SIC"]
    radar_id = 6601              # optional [default: sac * 256 + sic]
    lat_deg = 45.74              # WGS-84 site
    lon_deg = 16.07
    alt_m = 120.0
    sigma_range_m = 70.0         # nominal accuracy (a-priori weights)
    sigma_azimuth_deg = 0.08
    sigma_elevation_deg = 1.0    # optional [default 1.0]: SSR measures no elevation
    max_range_m = 463000.0
    scan_period_s = 4.0          # optional when the recording holds CAT034 antenna messages
    kind = "radar"               # optional [default "radar"]; "mlat": an MLAT / WAM system (CAT020),
                                 # its site the system reference point, scan_period_s its update period;
                                 # "adsb": an ADS-B ground station (its CAT021 are reports, not truth),
                                 # its site the antenna, scan_period_s its update period
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any

import polars as pl

from tertiary.core.errors import DataError, OptionError
from tertiary.store.run_store import write_text_atomic

REQUIRED = ("lat_deg", "lon_deg", "alt_m", "sigma_range_m", "sigma_azimuth_deg", "max_range_m")
OPTIONAL = {"sigma_elevation_deg": 1.0, "scan_period_s": math.nan}
KINDS = ("radar", "mlat", "adsb")
KEYS = {"sac", "sic", "name", "radar_id", "kind", *REQUIRED, *OPTIONAL}


def radar_id(sac: int, sic: int) -> int:
    """Default radar id of a SAC/SIC pair (unique, and both codes readable from it)."""
    return sac * 256 + sic


def _number(entry: dict[str, Any], key: str, where: str) -> float:
    v = entry.get(key, OPTIONAL.get(key))
    if v is None:
        raise DataError(f"{where}: '{key}' missing")
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DataError(f"{where}: '{key}' must be a number, got {v!r}")
    if math.isnan(v) and key not in OPTIONAL:
        raise DataError(f"{where}: '{key}' not filled in (nan in the template)")
    return float(v)


def read_sites(path: str | Path) -> pl.DataFrame:
    """The registry as a frame: sac, sic, radar_id, name and the radars-table columns."""
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DataError(f"cannot read: {exc.strerror or exc}", path=str(p)) from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"not a valid TOML file: {exc}", path=str(p)) from exc
    entries = doc.get("radar", [])
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise DataError("expected [[radar]] tables", path=str(p))
    rows, seen = [], {}
    for i, e in enumerate(entries):
        where = f"{p}: [[radar]] #{i + 1}"
        unknown = sorted(set(e) - KEYS)
        if unknown:
            raise DataError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(KEYS))}")
        sac, sic = e.get("sac"), e.get("sic")
        if not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in (sac, sic)):
            raise DataError(f"{where}: sac and sic must be integers in [0, 255], got {sac!r}, {sic!r}")
        if (sac, sic) in seen:
            raise DataError(f"{where}: SAC/SIC {sac}/{sic} already given in #{seen[(sac, sic)]}")
        seen[(sac, sic)] = i + 1
        rid = e.get("radar_id", radar_id(sac, sic))
        if isinstance(rid, bool) or not isinstance(rid, int) or not 0 <= rid < 2**32:
            raise DataError(f"{where}: radar_id must be an integer in [0, 2^32), got {rid!r}")
        kind = e.get("kind", "radar")
        if kind not in KINDS:
            raise DataError(f"{where}: kind must be one of {', '.join(KINDS)}, got {kind!r}")
        row = {"sac": sac, "sic": sic, "radar_id": rid, "name": str(e.get("name", f"{sac}-{sic}")), "kind": kind}
        row |= {k: _number(e, k, where) for k in (*REQUIRED, *OPTIONAL)}
        rows.append(row)
    frame = pl.DataFrame(rows, schema={"sac": pl.Int64, "sic": pl.Int64, "radar_id": pl.UInt32, "name": pl.String,
                                       "kind": pl.String,
                                       **dict.fromkeys((*REQUIRED, *OPTIONAL), pl.Float64)})
    dup = frame.filter(pl.col("radar_id").is_duplicated())
    if dup.height:
        raise DataError(f"radar_id {dup['radar_id'][0]} given to two SAC/SIC pairs", path=str(p))
    return frame


def sites_toml(sites: pl.DataFrame) -> str:
    """A sites file for ``sites`` (columns as :func:`read_sites` returns); NaN → ``nan``."""
    lines = ["# SAC/SIC -> radar registry for `tertiary import asterix` (see docs/asterix.md)"]
    for row in sites.iter_rows(named=True):
        name = json.dumps(str(row["name"]), ensure_ascii=False)      # a TOML basic string, escaped
        lines += ["", "[[radar]]", f"sac = {row['sac']}", f"sic = {row['sic']}", f"name = {name}",
                  f"radar_id = {row['radar_id']}"]
        if (row.get("kind") or "radar") != "radar":
            lines.append(f"kind = {json.dumps(str(row['kind']))}")
        for k in (*REQUIRED, *OPTIONAL):
            v = row.get(k, math.nan)
            v = math.nan if v is None else float(v)
            lines.append(f"{k} = {'nan' if math.isnan(v) else repr(v)}")
    return "\n".join(lines) + "\n"


def write_template(path: str | Path, codes: list[tuple[int, int]], scan: dict[tuple[int, int], float]) -> Path:
    """Write a sites file for ``codes`` with ``nan`` where the user must fill in a value."""
    p = Path(path)
    if p.is_dir():
        raise OptionError(f"{p} is a directory; give a file name", option="--write-sites-template")
    rows = [{"sac": a, "sic": b, "radar_id": radar_id(a, b), "name": f"{a}-{b}",
             **dict.fromkeys(REQUIRED, math.nan), "sigma_elevation_deg": 1.0,
             "scan_period_s": scan.get((a, b), math.nan)} for a, b in sorted(codes)]
    text = sites_toml(pl.DataFrame(rows)).replace(
        "[[radar]]", "[[radar]]  # fill in every nan", 1)
    return write_text_atomic(p, text)
