"""Fuzz harness over every entry point of ``tertiary``.

A *case* is a JSON-able dict, drawn by the hypothesis strategies below, for one entry point:

* ``validate`` / ``run``: a mutated copy of a small base dataset through ``tertiary validate DIR``
  or ``tertiary run DIR`` (in-process, ``typer.testing.CliRunner``);
* ``simulate``: bad ``tertiary simulate`` options;
* ``sql``: hostile ``tertiary sql RUN_DIR --query`` input (the statement-timeout case runs in a
  subprocess, the only place a hang is possible without a worker);
* ``api``: ``tertiary.validate(obj, kind, strict=...)`` with odd objects and mutated frames.

:func:`execute` runs one case in the current process and returns an :class:`Outcome` whose
``cls`` is exactly one of ``clear_error, rejects, success, traceback, silent, hang`` and whose
``ok`` says whether the contract held: a clear error (exit 2/3/4, one line on stderr, no
traceback) or success with row accounting intact (every input report in ``aligned`` or
``rejects``, read from the run database) and every impossible row in ``rejects``.
:class:`Worker` runs cases in a child process with an address-space limit and a per-case
timeout, so an unbounded allocation or a hang is classified instead of taking the machine.

Replay one case: ``python tests/fuzzing.py replay '<case json>'`` (prints the traceback).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import os
import re
import select
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

from hypothesis import strategies as st

CLASSES = ("clear_error", "rejects", "success", "traceback", "silent", "hang")
ENTRIES = ("validate", "run", "simulate", "sql", "api")
EXPECTED_CODES = (2, 3, 4)
REPO = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve()

# ---------------------------------------------------------------------------
# base datasets (built once per session, cached in a directory)
# ---------------------------------------------------------------------------

BASES = {
    # name: (scenario, overrides) -- tiny, so that a `run` case costs about a second
    "ta": ("terminal-area", {"aircraft": 4, "radars": 2, "duration": 120.0}),
    "bb": ("big-box", {"duration": 60.0}),
    "bb3": ("big-box", {"duration": 30.0, "runs": 3}),   # several Monte-Carlo runs in one dataset
}


def build_bases(root: Path) -> Path:
    """Write the base datasets and one run directory (for ``sql``) under ``root`` unless present."""
    import polars as pl  # noqa: F401  (import cost paid here, not in the first case)

    from tertiary import pipeline
    from tertiary.io.dataset import read_dataset, write_dataset
    from tertiary.simulate import load_scenario, simulate
    from tertiary.simulate.config import with_radar_count

    root.mkdir(parents=True, exist_ok=True)
    for name, (scen, over) in BASES.items():
        d = root / name
        if (d / "reports.parquet").exists():
            continue
        cfg = load_scenario(scen).replace(runs=over.get("runs", 1), duration_s=over["duration"])
        if "aircraft" in over:
            cfg = dataclasses.replace(cfg, traffic=dataclasses.replace(cfg.traffic, aircraft=over["aircraft"]))
        if "radars" in over:
            cfg = with_radar_count(cfg, over["radars"])
        tmp = root / f".{name}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        write_dataset(simulate(cfg), tmp)
        tmp.rename(d)
    run_dir = root / "run_ta"
    if not (run_dir / "results.duckdb").exists():
        cfg = pipeline.PipelineConfig(methods=("arithmetic", "information"), filters=("singer",))
        pipeline.run(read_dataset(root / "ta"), run_dir, cfg)
    return root


# ---------------------------------------------------------------------------
# mutations of a dataset (applied to polars frames, files and scenario.toml)
# ---------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")
MARKUP = ("[/truth]", "[/]", "[bold red]x[/bold red]", "[link=file:///etc/passwd]x[/link]", "[", "\\[/]")

# (column, value, impossible): impossible values must be rejected (or refused) when seen in a
# dataset; the others must only not crash.  "2max" = twice the radar's max_range_m.
REPORT_VALUES: list[tuple[str, Any, bool]] = [
    *[("range_m", v, True) for v in (NAN, INF, -INF, 1e300, -1e300, -5.0, "2max")],
    *[("azimuth_deg", v, True) for v in (NAN, INF, 360.5, 400.0, -1.0, 1e300)],
    *[("elevation_deg", v, True) for v in (95.0, -95.0, INF, -INF)],
    ("elevation_deg", NAN, False),
    *[("altitude_m", v, True) for v in (INF, 1e300, -1e300)],
    *[(c, v, True) for c in ("est_range_var_m2", "est_azimuth_var_deg2", "est_elevation_var_deg2")
      for v in (INF, -1.0, -INF)],
    *[(c, 1e300, False) for c in ("est_range_var_m2", "est_azimuth_var_deg2")],
    *[("res_range_var_m2", v, True) for v in (-1.0, INF)],
    *[("est_cov", v, True) for v in ("asym", "negdiag", "inf")],
    ("est_cov", "big", False),
    *[(c, v, False) for c in ("x_m", "vx_mps", "est_range_m", "res_range_m") for v in (1e300, -1e300)],
    *[("time", f"year:{y}", True) for y in (1, 1970, 2100, 9999)],
    *[("time", f"span:{d}", False) for d in (3.4 * 86400, -3.4 * 86400, 86400.0, 3.6 * 86400)],
    ("radar_id", 999, True),
    *[("local_track_id", v, False) for v in (0, 2**32 - 1)],
    *[(c, None, True) for c in ("radar_id", "time", "local_track_id", "range_m", "azimuth_deg")],
    *[(c, v, False) for c in ("run",) for v in (2**32 - 1, None, 7)],
    ("truth_id", 999999, False), ("truth_id", None, False), ("elevation_deg", None, False),
    *[(c, 0.0, False) for c in ("est_range_var_m2", "est_azimuth_var_deg2", "res_range_var_m2", "range_m")],
    ("azimuth_deg", 359.9999999, False), ("elevation_deg", 90.0, False), ("elevation_deg", -90.0, False),
]
RADAR_VALUES: list[tuple[str, Any, bool]] = [
    *[(c, 1e300, True) for c in ("sigma_range_m", "sigma_azimuth_deg", "sigma_elevation_deg")],
    *[("scan_period_s", v, True) for v in (1e-9, 1e300, 0.0, -1.0, NAN)],
    *[("lat_deg", v, True) for v in (95.0, NAN)],
    ("lon_deg", 200.0, True),
    *[("max_range_m", v, True) for v in (-1.0, NAN, 0.0)],
    ("max_range_m", 1e300, False),
    ("alt_m", 1e300, True),
    ("timing", "[/]", True),
    *[(c, None, True) for c in ("radar_id", "lat_deg", "scan_period_s", "max_range_m")],
    # extreme but legal: poles, date line, zero sigmas (singular weights), a radar that sees nothing
    *[(c, v, False) for c, v in (("lat_deg", 89.999), ("lat_deg", -89.999), ("lon_deg", 180.0), ("lon_deg", -180.0),
                                 ("alt_m", -499.0), ("sigma_range_m", 0.0), ("sigma_azimuth_deg", 0.0),
                                 ("sigma_elevation_deg", 0.0), ("max_range_m", 1.0), ("scan_period_s", 0.5),
                                 ("scan_period_s", 600.0))],
]
TRUTH_VALUES: list[tuple[str, Any, bool]] = [
    *[("time", f"year:{y}", True) for y in (1970, 2100)],
    *[("time", f"span:{d}", False) for d in (3.4 * 86400, -3.4 * 86400, 86400.0)],
    *[("x_m", v, False) for v in (1e300, -1e300)],
    ("x_m", NAN, True),
    *[(c, None, True) for c in ("truth_id", "time", "x_m")],
]
REQUIRED = {
    "reports": ("radar_id", "time", "local_track_id", "range_m", "azimuth_deg"),
    "radars": ("radar_id", "name", "lat_deg", "scan_period_s", "sigma_range_m", "max_range_m"),
    "truth": ("truth_id", "time", "x_m"),
}
SHIFTS = (-30 * 86400.0, 3.5 * 86400.0, 1e-6, 0.5, 50 * 365 * 86400.0, -3600.0)
OPTIONAL_DROPS = ("est_cov", "elevation_deg", "segment", "report_id", "run", "x_m", "est_range_var_m2", "res_range_m",
                  "truth_id", "max_range_m")
CASTS = {  # (column, target dtype, impossible-if-accepted)
    "reports": [("time", t, False) for t in ("int", "float", "date", "duration")]
    + [("est_cov", "string", False), ("range_m", "bool", True), ("callsign", "binary", False),
       ("range_m", "string", False)],
    "radars": [("scan_period_s", "string", False), ("radar_id", "float", False), ("name", "binary", False)],
    "truth": [("time", "int", False)],
}
TEXT_COLS = {"reports": ("callsign", "mode_s", "mode_3a"), "radars": ("name",), "truth": ("callsign",)}
FILES = ("radars.parquet", "reports.parquet", "truth.parquet")
FILE_OPS = ("truncate", "garbage", "csv", "empty", "ipc", "missing")
TOML_OPS = ("garbage", "utf16", "unknown_key", "no_origin", "origin_abc", "origin_nan", "origin_range", "origin_pole",
            "name_path", "name_markup", "missing", "bad_type")


def _row(frac: float, height: int) -> int:
    return min(int(frac * height), height - 1)


@dataclass
class Expect:
    """What a mutated dataset demands: an error, or these rows among the rejects."""

    must_error: bool = False          # a table-level problem: success would be wrong
    impossible: bool = False          # ... and success would accept the impossible (silent)
    # (table, rows, min rejected, context, column): context "any" holds for a table alone, "radars" needs
    # the radars table beside it, "dataset" needs every table (times consistent across tables)
    groups: list[tuple[str, list[int], int, str, str | None]] = field(default_factory=list)
    name_escape: str | None = None    # scenario name that must not become a path outside runs/
    rows_only: bool = False           # only row-level faults in reports/truth: want rejects, not a refusal
    notes: list[str] = field(default_factory=list)


def _cov_value(kind: str, cov: list[float]) -> list[float]:
    out = list(cov)
    if kind == "asym":
        out[1] += 1e4 + abs(out[1])       # (0,1) != (1,0)
    elif kind == "negdiag":
        out[0] = -abs(out[0]) - 1.0
    elif kind == "inf":
        out[7] = INF
    elif kind == "big":
        for i in range(6):
            out[i * 7] = 1e300
    return out


def _set_values(frame, col: str, value: Any, rows: list[int], radars=None):
    """``frame`` with ``col`` replaced by ``value`` at ``rows`` (typed to the column)."""
    import polars as pl

    s = frame[col]
    if col == "est_cov":
        vals = s.to_list()
        for i in rows:
            vals[i] = _cov_value(value, vals[i] if vals[i] is not None else [0.0] * 36)
        return frame.with_columns(pl.Series(col, vals, dtype=s.dtype))
    if isinstance(value, str) and value.startswith("year:"):
        year = int(value.split(":")[1])
        vals = s.to_list()
        for i in rows:
            vals[i] = datetime(year, 1, 1, 12, tzinfo=timezone.utc)
        return frame.with_columns(pl.Series(col, vals, dtype=s.dtype))
    if isinstance(value, str) and value.startswith("span:"):  # median time + offset (inside the allowed span)
        med = s.median()
        vals = s.to_list()
        for i in rows:
            vals[i] = med + timedelta(seconds=float(value.split(":")[1]))
        return frame.with_columns(pl.Series(col, vals, dtype=s.dtype))
    if value == "2max":
        max_range = dict(zip(radars["radar_id"].to_list(), radars["max_range_m"].to_list()))
        ids = frame["radar_id"].to_list()
        vals = s.to_list()
        for i in rows:
            vals[i] = 2.0 * float(max_range.get(ids[i], 1e6))
        return frame.with_columns(pl.Series(col, vals, dtype=s.dtype))
    vals = s.to_list()
    for i in rows:
        vals[i] = value
    return frame.with_columns(pl.Series(col, vals, dtype=s.dtype, strict=False))


def _cast_column(frame, col: str, to: str):
    import polars as pl

    c = pl.col(col)
    if to == "int":
        expr = c.dt.epoch("s") if frame[col].dtype == pl.Datetime("us", "UTC") else c.cast(pl.Int64)
    elif to == "float":
        expr = (c.dt.epoch("ms").cast(pl.Float64) / 1e3) if isinstance(frame[col].dtype, pl.Datetime) \
            else c.cast(pl.Float64)
    elif to == "date":
        expr = c.dt.date()
    elif to == "duration":
        expr = c - pl.datetime(1970, 1, 1, time_zone="UTC")
    elif to == "bool":
        expr = c.cast(pl.Float64) > 0
    elif to == "binary":
        expr = c.cast(pl.String).cast(pl.Binary)
    else:  # string
        expr = c.cast(pl.List(pl.String)).list.join(",") if isinstance(frame[col].dtype, pl.Array) \
            else c.cast(pl.String)
    return frame.with_columns(expr.alias(col))


def apply_frame_ops(frames: dict, ops: list[dict], exp: Expect) -> dict:
    """Apply the frame mutations in phase order; record what they demand in ``exp``."""
    import polars as pl

    order = {"head": 0, "set_all": 0, "shuffle": 0, "shift": 0, "set": 1, "text": 1, "dup": 2, "cast": 3, "drop_col": 3,
             "add_col": 3}
    for op in sorted(ops, key=lambda o: order.get(o["op"], 9)):
        t = op["table"]
        f = frames.get(t)
        if f is None:
            continue
        kind = op["op"]
        try:
            if kind == "head":
                frames[t] = f.head(op["n"])
            elif kind == "set_all" and op["col"] in f.columns and f.height:
                frames[t] = _set_values(f, op["col"], op["value"], list(range(f.height)))
            elif kind in ("set", "text") and op["col"] in f.columns and f.height:
                rows = sorted({_row(x, f.height) for x in op["rows"]})
                frames[t] = _set_values(f, op["col"], op["value"], rows, frames.get("radars"))
                # a later value in the same cell replaces an earlier impossible one
                exp.groups = [g for g in exp.groups if not (g[0] == t and g[4] == op["col"] and g[1][0] in rows)]
                if op.get("impossible"):
                    ctx = ("radars" if op["value"] == "2max" or op["col"] == "radar_id" else
                           "dataset" if op["value"] in ("year:1970", "year:2100") else "any")
                    exp.groups += [(t, [i], 1, ctx, op["col"]) for i in rows]
                    exp.impossible = True
            elif kind == "dup" and f.height:
                rows = sorted({_row(x, f.height) for x in op["rows"]})
                frames[t] = pl.concat([f, f[rows]], how="vertical")
                exp.groups += [(t, [i, f.height + k], 1, "any", None) for k, i in enumerate(rows)]
                exp.impossible = True
            elif kind == "cast" and op["col"] in f.columns:
                frames[t] = _cast_column(f, op["col"], op["to"])
                if op.get("impossible") and f.height:
                    exp.groups.append((t, list(range(f.height)), f.height, "any", None))
                    exp.impossible = True
            elif kind == "drop_col" and op["col"] in f.columns:
                frames[t] = f.drop(op["col"])
                if op["col"] in REQUIRED[t] and (t != "truth" or f.height):
                    exp.must_error = exp.impossible = True
            elif kind == "shift":  # a table moved in time against the others
                frames[t] = f.with_columns(pl.col("time") + pl.duration(microseconds=int(op["seconds"] * 1e6)))
            elif kind == "shuffle":  # rows out of time order: sorted with a note, never lost
                frames[t] = f.sample(fraction=1.0, shuffle=True, seed=op["seed"])
            elif kind == "add_col":
                v = op["value"]
                v = bytes.fromhex(v[6:]) if v.startswith("bytes:") else v
                frames[t] = f.with_columns(pl.lit(v).alias(op["col"]))
        except Exception as exc:  # a mutation that does not apply to this frame is skipped, not a finding
            exp.notes.append(f"skipped {kind} on {t}: {type(exc).__name__}")
    return frames


def _corrupt_file(path: Path, how: str, frame) -> None:
    import polars as pl

    if not path.exists() and how in ("truncate",):  # already removed by an earlier mutation
        return
    if how == "missing":
        path.unlink(missing_ok=True)
    elif how == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif how == "garbage":
        path.write_bytes(bytes(range(256)) * 7 + b"\xff\xfe garbage")
    elif how == "csv":
        cols = [c for c, d in frame.schema.items() if d.is_numeric() or d == pl.String][:4]
        frame.select(cols).write_csv(path) if cols else path.write_text("a,b\n1,2\n")
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "ipc":
        frame.select([c for c, d in frame.schema.items() if not str(d).startswith("Array")]).write_ipc(path)


def _mutate_toml(path: Path, how: str, exp: Expect) -> None:
    text = (path.read_bytes().decode("utf-8", errors="replace") if path.exists()
            else 'name = "x"\nkind = "terminal-area"\n')
    if how == "garbage":
        path.write_bytes(b"\x00\x01 = [[[ not toml \xff")
        exp.must_error = exp.impossible = True
    elif how == "utf16":
        path.write_bytes(text.encode("utf-16"))
        exp.must_error = exp.impossible = True
    elif how == "unknown_key":
        path.write_text("bogus_key = 3\n" + text)
    elif how == "no_origin":
        path.write_text(re.sub(r"(?m)^origin = .*$\n", "", text))
    elif how == "origin_abc":
        path.write_text(re.sub(r"(?m)^origin = .*$", 'origin = "abc"', text))
        exp.must_error = exp.impossible = True
    elif how == "origin_nan":
        path.write_text(re.sub(r"(?m)^origin = .*$", "origin = [nan, 2.35, 0.0]", text))
        exp.must_error = exp.impossible = True
    elif how == "origin_range":
        path.write_text(re.sub(r"(?m)^origin = .*$", "origin = [148.85, 2.35, 0.0]", text))
        exp.must_error = exp.impossible = True
    elif how == "origin_pole":  # legal, far from the radars: a clear error or a run, never a crash
        path.write_text(re.sub(r"(?m)^origin = .*$", "origin = [89.99, 179.99, 0.0]", text))
    elif how == "name_path":
        path.write_text(re.sub(r'(?m)^name = .*$', 'name = "../../../x"', text))
        exp.name_escape = "../../../x"
    elif how == "name_markup":
        path.write_text(re.sub(r'(?m)^name = .*$', 'name = "[/truth]"', text))
    elif how == "missing":
        path.unlink(missing_ok=True)
    elif how == "bad_type":
        path.write_text(re.sub(r"(?m)^runs = .*$", 'runs = "many"', text))
        exp.must_error = exp.impossible = True


def materialise(case: dict, bases: Path, out: Path) -> tuple[Expect, int]:
    """Write the mutated dataset of ``case`` to ``out``; returns the expectation and report count."""
    import polars as pl

    src = bases / case["base"]
    out.mkdir(parents=True, exist_ok=True)
    frames = {t: pl.read_parquet(src / f"{t}.parquet") for t in ("radars", "reports", "truth")}
    exp = Expect()
    frames = apply_frame_ops(frames, [o for o in case["ops"] if o["op"] not in ("file", "toml")], exp)
    for t, f in frames.items():
        f.write_parquet(out / f"{t}.parquet")
    shutil.copy(src / "scenario.toml", out / "scenario.toml")
    toml_exp = Expect()  # what scenario.toml demands; a later "missing" forgets the earlier edits
    for op in case["ops"]:
        if op["op"] == "file":
            _corrupt_file(out / op["file"], op["how"], frames[op["file"].split(".")[0]])
            if op["file"] != "truth.parquet" or op["how"] != "missing":
                exp.must_error = exp.impossible = True
            else:  # no truth table any more: its rows cannot be among the rejects
                exp.groups = [g for g in exp.groups if g[0] != "truth"]
        elif op["op"] == "toml":
            if op["how"] == "missing":
                toml_exp = Expect()
            _mutate_toml(out / "scenario.toml", op["how"], toml_exp)
    exp.must_error |= toml_exp.must_error
    exp.impossible |= toml_exp.impossible
    exp.name_escape = toml_exp.name_escape
    exp.rows_only = not case.get("strict") and all(
        o["op"] in ("set", "text", "dup") and o["table"] in ("reports", "truth") for o in case["ops"])
    return exp, frames["reports"].height


# ---------------------------------------------------------------------------
# hypothesis strategies
# ---------------------------------------------------------------------------

_fracs = st.lists(st.floats(0, 0.999), min_size=1, max_size=3)


def _value_op(table: str, catalogue) -> st.SearchStrategy[dict]:
    return st.tuples(st.sampled_from(catalogue), _fracs).map(
        lambda t: {"op": "set", "table": table, "col": t[0][0], "value": t[0][1], "impossible": t[0][2],
                   "rows": t[1]})


def frame_op() -> st.SearchStrategy[dict]:
    """One mutation of a dataset (frame, file or scenario.toml)."""
    tables = st.sampled_from(("reports", "radars", "truth"))
    return st.one_of(  # value mutations weighted up: file/TOML faults end a case before the rows matter
        *[_value_op("reports", REPORT_VALUES)] * 5,
        *[_value_op("radars", RADAR_VALUES)] * 2,
        *[_value_op("truth", TRUTH_VALUES)] * 2,
        tables.flatmap(lambda t: st.sampled_from(REQUIRED[t] + OPTIONAL_DROPS)
                       .map(lambda c: {"op": "drop_col", "table": t, "col": c})),
        tables.flatmap(lambda t: st.sampled_from(CASTS[t]).map(
            lambda c: {"op": "cast", "table": t, "col": c[0], "to": c[1], "impossible": c[2]})),
        st.tuples(tables, st.sampled_from((0, 1))).map(lambda x: {"op": "head", "table": x[0], "n": x[1]}),
        st.tuples(tables, _fracs).map(lambda x: {"op": "dup", "table": x[0], "rows": x[1]}),
        st.tuples(tables, st.integers(0, 2**16)).map(lambda x: {"op": "shuffle", "table": x[0], "seed": x[1]}),
        st.tuples(st.sampled_from(("reports", "truth")), st.sampled_from(SHIFTS)).map(
            lambda x: {"op": "shift", "table": x[0], "seconds": x[1]}),
        st.sampled_from([("reports", "range_m", -1.0), ("reports", "radar_id", 999), ("radars", "scan_period_s", -1.0),
                         ("reports", "azimuth_deg", NAN), ("reports", "time", "year:2021"),
                         ("radars", "sigma_range_m", 0.0), ("radars", "sigma_azimuth_deg", 0.0),
                         ("reports", "est_cov", "big"), ("reports", "elevation_deg", None)]).map(
            lambda x: {"op": "set_all", "table": x[0], "col": x[1], "value": x[2]}),
        tables.flatmap(lambda t: st.tuples(st.sampled_from(TEXT_COLS[t]), st.sampled_from(MARKUP), _fracs).map(
            lambda x: {"op": "text", "table": t, "col": x[0], "value": x[1], "rows": x[2]})),
        st.tuples(tables, st.sampled_from(("blob", "extra [/]"))).map(
            lambda x: {"op": "add_col", "table": x[0], "col": x[1], "value": "[/]" if x[1] != "blob" else "bytes:00ff"}),
        st.tuples(st.sampled_from(FILES), st.sampled_from(FILE_OPS)).map(
            lambda x: {"op": "file", "file": x[0], "how": x[1]}),
        st.sampled_from(TOML_OPS).map(lambda h: {"op": "toml", "how": h}),
    )


RUN_FILTERS = ("singer", "", "quasi_optimal", "imm_sym", "singer,imm_sym", "cv")
RUN_BAD_OPTS = (None,) * 12 + (["--methods", "nope"], ["--filters", "nope"], ["--methods", "arithmetic,[/]"],
                                ["--out", "{file}"], ["--seed", "-1"], ["--runs", "0"])
RUN_BAD_ORIGINS = (["--origin", "abc"], ["--origin", "95,0"], ["--origin", "nan,1"], ["--origin", "1,2,3,4"],
                   ["--origin", "48.85,2.35,1e300"], ["--origin", "[/]"], ["--safety-picture", "nope"],
                   ["--origin", "48,200"])
RUN_METHODS = ("arithmetic,information", "arithmetic", "information")


@st.composite
def dataset_case(draw, entry: str | None = None) -> dict:
    """A mutated base dataset through ``validate`` or ``run`` (1–4 mixed mutations)."""
    entry = entry or draw(st.sampled_from(("validate", "run")))
    ops = draw(st.lists(frame_op(), min_size=1, max_size=4))
    case = {"entry": entry, "base": draw(st.sampled_from(tuple(BASES))), "ops": ops,
            "strict": draw(st.booleans().map(lambda b: b and draw(st.integers(0, 4)) == 0))}
    if entry == "run":
        case.update(filters=draw(st.sampled_from(RUN_FILTERS)), methods=draw(st.sampled_from(RUN_METHODS)),
                    report=draw(st.integers(0, 9)) == 0, centralized=draw(st.booleans()),
                    default_out=any(o["op"] == "toml" and o["how"] == "name_path" for o in ops),
                    bad_opt=draw(st.sampled_from(RUN_BAD_OPTS + RUN_BAD_ORIGINS)),
                    origin=draw(st.sampled_from((None,) * 6 + ("48.85,2.35", "48.85,2.35,100", "-33.9,151.2"))),
                    safety_picture=draw(st.sampled_from(("tracks", "fused"))))
    return case


SIM_BASE = ["simulate", "terminal-area", "--aircraft", "2", "--radars", "2", "--duration", "30", "--runs", "1"]
SIM_BAD: list[tuple[list[str], bool]] = [  # (extra args, impossible-if-accepted)
    *[(["--runs", v], True) for v in ("-1", "0")],
    (["--aircraft", "-3"], True), (["--aircraft", "0"], True), (["--radars", "0"], True),
    (["--radars", "-2"], True),
    *[(["--duration", v], True) for v in ("0", "nan", "inf", "-10", "-inf", "1e300")],
    (["--seed", "-1"], True), (["--seed", str(2**70)], True),
    *[(["--noise-factor", v], True) for v in ("nan", "inf", "-1", "-inf")],
    (["--outliers", "1.5"], True), (["--outliers", "-0.1"], True), (["--outliers", "nan"], True),
    *[(["--noise-factor", "3", "--noise-window", w], True) for w in ("10", "a:b", "20:10", "1:2:3", "nan:5", ":")],
    *[(["--dropout", d], True) for d in ("TMA-N", "TMA-N:5", "NOPE:0:10", "TMA-N:a:b", "TMA-N:20:10", "TMA-N:nan:1",
                                         "::")],
    *[(["--bias-step", b], True) for b in ("10", "a:b:c", "1:2", "nan:1:1", "10:inf:0", "1:2:3:4")],
    (["--truth", "/nonexistent/truth.parquet"], True),
    (["--scenario-is-not-an-option"], True),
]


RUN_SIM = ["run", "--no-report", "--filters", "singer", "--methods", "arithmetic", "--scenario"]


@st.composite
def simulate_case(draw) -> dict:
    """``tertiary simulate`` (or ``tertiary run`` simulating, no DATASET) with one or two bad options, a bad
    scenario, ``--out`` or ``--truth``."""
    via_run = draw(st.integers(0, 2)) == 0
    head = (lambda scen: RUN_SIM + [scen]) if via_run else (lambda scen: ["simulate", scen])
    kind = draw(st.integers(0, 9))
    if kind == 0:
        return {"entry": "simulate", "args": head(draw(st.sampled_from(("nope", "../x", "[/]", "")))) +
                ["--duration", "30"], "impossible": True, "out": "new"}
    if kind == 1:
        return {"entry": "simulate", "args": head("adsb") + ["--duration", "30"],
                "truth": draw(st.sampled_from(("missing", "garbage", "empty", "csv", "none"))), "impossible": True,
                "out": "new"}
    picks = draw(st.lists(st.sampled_from(SIM_BAD), min_size=1, max_size=2))
    args = head("terminal-area") + SIM_BASE[2:]
    for extra, _ in picks:
        args += extra
    out = draw(st.sampled_from(("new", "new", "new", "file") + (() if via_run else ("existing_dataset",))))
    return {"entry": "simulate", "args": args, "impossible": any(p[1] for p in picks), "out": out}


SQL_WRITES = [
    "CREATE TABLE t AS SELECT 1", "INSERT INTO metrics SELECT * FROM metrics", "DELETE FROM aligned",
    "DROP TABLE aligned", "UPDATE rejects SET reason = 'x'", "ATTACH '{tmp}/x.duckdb' AS x", "INSTALL httpfs",
    "LOAD httpfs", "COPY aligned TO '{tmp}/x.csv'", "SELECT * FROM read_csv('/etc/passwd')",
    "SELECT * FROM read_text('/etc/passwd')", "SELECT * FROM read_parquet('{bases}/ta/reports.parquet')",
    "SET enable_external_access = true", "EXPORT DATABASE '{tmp}/exp'", "CHECKPOINT",
    "SELECT 1; DROP TABLE aligned", "CALL dbgen(sf = 0.01)", "PRAGMA enable_profiling = 'json'",
    "SELECT * FROM glob('/etc/*')", "CREATE MACRO m() AS 1", "DETACH results",
    "SELECT * FROM read_csv_auto('{bases}/ta/scenario.toml')", "SET threads = 1; SELECT 1",
]
SQL_OK = [
    "SELECT * FROM aligned LIMIT 5", "PIVOT (SELECT radar_id, run FROM aligned) ON run USING count(*)",
    "SELECT * FROM pragma_table_info('aligned')", "SELECT INTERVAL 1 DAY AS i, INTERVAL 90 MINUTE AS j",
    "SELECT '[/]' AS x, '[/truth]' AS y, '[bold]z' AS \"[/]\"", "SELECT NULL AS n",
    "SELECT 1e308 * 10 AS inf_value, 'nan'::DOUBLE AS nan_value", "SELECT 'x'::BLOB AS b, '\\xff'::BLOB AS c",
    "SELECT [1, 2] AS l, {'a': 1} AS s", "SELECT DATE '0001-01-01' AS d, TIMESTAMP '9999-12-31 23:59:59' AS t",
    "SELECT 'é\u2603' AS u", "EXPLAIN SELECT 1", "WITH a AS (SELECT 1 AS x) SELECT * FROM a",
    "SELECT * FROM range(100000)", "SELECT reason, count(*) FROM rejects GROUP BY ALL",
    "SELECT 1::HUGEINT * 170141183460469231731687303715884105727 AS big", "SELECT 'a\nb' AS newline",
    "SELECT * FROM (VALUES (1, 'x')) t(a, b)", "SELECT 1 AS a, 2 AS a", "SELECT 1/0 AS z", "SELECT '\x00' AS nul",
]
SQL_ODD_TYPES = [  # result types that CSV and the printed table may not handle: a result or a clear error
    "SELECT 'x'::BLOB AS b", "SELECT MAP {'k': 1} AS m", "SELECT 'infinity'::TIMESTAMP AS ts",
    "SELECT '-infinity'::DATE AS d", "SELECT 'infinity'::DATE AS d", "SELECT TIMESTAMP '294247-01-01 00:00:00' AS far",
    "SELECT 1::UNION(a INT, b VARCHAR) AS un", "SELECT [1, 2]::INT[2] AS arr", "SELECT BIT '1010' AS bits",
    "SELECT TIME '12:00:00' AS t", "SELECT 1.5::DECIMAL(38, 10) AS d", "SELECT 'nan'::FLOAT AS f",
    "SELECT TIMESTAMPTZ '2021-01-01 00:00:00+05' AS tz", "SELECT INTERVAL '-1000000 years' AS iv",
]
SQL_BAD = [
    "SELEC 1", "SELECT * FROM nope", "", "   ", "-- only a comment", "SELECT '\udcff'", "\udcff\udcfe",
    "SELECT 'x'::INTEGER", "SELECT * FROM aligned WHERE", ";",
    "SELECT " + "1+" * 5000 + "1",
]


SQL_NAMED = ("accuracy_by_method", "accuracy_over_time", "alert_scores", "rejects_by_reason", "row_accounting",
             "radar_residuals", "trajectories", "conflicts", "nope", "../x", "[/]")
SQL_PARAMS = ("method", "metric", "min_sample_frac", "radar_id", "skip_first_s", "segment", "stage", "bogus",
              "min_severity")
SQL_PARAM_VALUES = ("null", "1e300", "-1", "nan", "'; DROP TABLE aligned; --", "[/]", "\"x\"", "true", "", "[1,2]",
                    "999999999999999999999", "rmse_pos_m", "aposteriori", "\udcff")
CROSS_JOIN = "SELECT count(*) FROM range(100000000) a, range(100000000) b WHERE a.range + b.range < 0"


@st.composite
def sql_case(draw) -> dict:
    """``tertiary sql RUN --query`` with a hostile, odd or plain query and odd options."""
    pool = draw(st.sampled_from(("write", "ok", "ok", "bad", "text", "opts", "timeout", "named", "odd", "odd")))
    case: dict[str, Any] = {"entry": "sql", "args": [], "expect": "error"}
    if pool == "named":  # a named report with odd parameter values: a clear error or a result
        name = draw(st.sampled_from(SQL_NAMED))
        params = draw(st.lists(st.tuples(st.sampled_from(SQL_PARAMS), st.sampled_from(SQL_PARAM_VALUES)),
                               max_size=3))
        return {"entry": "sql", "name": name, "args": [a for k, v in params for a in ("-p", f"{k}={v}")],
                "expect": "any", "query": ""}
    if pool == "write":
        q = draw(st.sampled_from(SQL_WRITES))
    elif pool == "ok":
        q, case["expect"] = draw(st.sampled_from(SQL_OK)), "ok"
    elif pool == "bad":
        q = draw(st.sampled_from(SQL_BAD))
    elif pool == "odd":
        q, case["expect"] = draw(st.sampled_from(SQL_ODD_TYPES)), "any"
        case["args"] = draw(st.sampled_from(([], ["--format", "csv"], ["--out", "{tmp}/o.csv"],
                                             ["--out", "{tmp}/o.parquet"])))
    elif pool == "text":
        q, case["expect"] = draw(st.text(max_size=60)), "any"
    elif pool == "opts":
        q, case["expect"] = "SELECT 1 AS x", "error"
        case["args"] = draw(st.sampled_from([["--out", "{tmp}"], ["--out", "{run}/results.duckdb"],
                                             ["--out", "{run}"], ["--format", "xml"], ["--out", "{tmp}/no/such/d.csv"],
                                             ["--format", "parquet"], ["--param", "a=1"], ["--limit", "-1"],
                                             ["--limit", "0"], ["--timeout", "0"], ["--timeout", "nan"],
                                             ["--timeout", "-1"], ["--timeout", "inf"]]))
        if case["args"] in (["--out", "{tmp}/no/such/d.csv"], ["--limit", "-1"]):
            case["expect"] = "any"
    else:  # the one case that can hang: a cross join that a statement timeout must stop
        q = CROSS_JOIN
        case["args"], case["subprocess"] = ["--timeout", draw(st.sampled_from(("2", "0.5", "1")))], True
    fmt = draw(st.sampled_from(((), (), ("--format", "csv"), ("--limit", "3"))))
    if pool in ("ok", "write", "bad") and fmt:
        case["args"] = case["args"] + list(fmt)
    case["query"] = q
    return case


API_OBJECTS = ("frame", "frame", "frame", "none", "dict", "numpy", "lazy", "arrow", "list", "str", "columns_dict",
               "pandas")


@st.composite
def api_case(draw) -> dict:
    """``tertiary.validate(obj, kind, strict=...)`` with odd objects or a mutated frame."""
    kind = draw(st.sampled_from(("reports", "reports", "radars", "truth", "nope", "", "aligned", "rejects")))
    t = kind if kind in REQUIRED else "reports"
    cat = {"reports": REPORT_VALUES, "radars": RADAR_VALUES, "truth": TRUTH_VALUES}[t]
    ops = draw(st.lists(st.one_of(
        _value_op(t, cat), _value_op(t, cat),
        st.sampled_from(REQUIRED[t]).map(lambda c: {"op": "drop_col", "table": t, "col": c}),
        st.sampled_from(CASTS[t]).map(lambda c: {"op": "cast", "table": t, "col": c[0], "to": c[1],
                                                 "impossible": c[2]}),
        st.sampled_from((0, 1)).map(lambda n: {"op": "head", "table": t, "n": n}),
        _fracs.map(lambda r: {"op": "dup", "table": t, "rows": r}),
        st.tuples(st.sampled_from(TEXT_COLS[t]), st.sampled_from(MARKUP), _fracs).map(
            lambda x: {"op": "text", "table": t, "col": x[0], "value": x[1], "rows": x[2]}),
    ), max_size=3))
    return {"entry": "api", "obj": draw(st.sampled_from(API_OBJECTS)), "kind": kind, "table": t, "ops": ops,
            "strict": draw(st.booleans()), "with_radars": draw(st.booleans()),
            "base": draw(st.sampled_from(tuple(BASES)))}


def case_strategy(entry: str) -> st.SearchStrategy[dict]:
    return {"validate": dataset_case("validate"), "run": dataset_case("run"), "simulate": simulate_case(),
            "sql": sql_case(), "api": api_case()}[entry]


def draw_cases(entry: str, n: int, seed: int | None = None) -> list[dict]:
    """``n`` cases of one entry point drawn by hypothesis: from ``seed``, or derandomised (CI)."""
    from hypothesis import HealthCheck, Phase, given, settings
    from hypothesis import seed as hseed

    cases: list[dict] = []

    @settings(max_examples=n, database=None, deadline=None, phases=[Phase.generate], derandomize=seed is None,
              suppress_health_check=list(HealthCheck))
    @given(case_strategy(entry))
    def collect(case: dict) -> None:
        cases.append(case)

    (hseed(seed)(collect) if seed is not None else collect)()
    return cases[:n]


def dataset(entry: str, ops: list[dict], base: str = "ta", **kw: Any) -> dict:
    """A hand-written ``validate``/``run`` case (for the regression tests)."""
    case = {"entry": entry, "base": base, "ops": ops, "strict": False}
    if entry == "run":
        case.update(filters="singer", methods="arithmetic,information", report=False, centralized=False,
                    default_out=False)
    case.update(kw)
    return case


# ---------------------------------------------------------------------------
# running one case
# ---------------------------------------------------------------------------


class HarnessError(RuntimeError):
    """The harness itself failed to build a case (reported as such, not as a project finding)."""


@dataclass
class Outcome:
    """The classification of one case."""

    entry: str
    cls: str
    ok: bool
    problems: list[str] = field(default_factory=list)
    exit_code: int | None = None
    exc: str = ""
    where: str = ""
    tb_tail: str = ""
    seconds: float = 0.0
    case: dict = field(default_factory=dict)

    @property
    def signature(self) -> str:
        """Groups failures of one cause: entry, class, exception type and innermost project frame."""
        head = (self.exc.split(":")[0] if self.exc else
                re.sub(r"-?\d[\d.e+-]*|\[.*?\]|'.*?'|\(.*?\)", "#", self.problems[0])[:80] if self.problems else "")
        return f"{self.entry} | {self.cls} | {head} | {self.where}"

    def reproducer(self) -> str:
        return f"python tests/fuzzing.py replay '{json.dumps(self.case)}'"


def _project_frame(tb) -> str:
    """The innermost traceback frame in tertiary/ or safety/ (file:line function)."""
    where = ""
    for fr in traceback.extract_tb(tb):
        p = fr.filename.replace("\\", "/")
        if "/tertiary/" in p or "/safety/" in p:
            tail = p.split("/tertiary/")[-1] if "/tertiary/" in p else p.split("/safety/")[-1]
            pkg = "tertiary" if "/tertiary/" in p else "safety"
            where = f"{pkg}/{tail}:{fr.lineno} {fr.name}"
    return where


def _from_exception(o: Outcome, exc: BaseException) -> Outcome:
    o.cls, o.ok = "traceback", False
    o.exc = f"{type(exc).__name__}: {str(exc).splitlines()[0][:300] if str(exc) else ''}"
    o.where = "tests/fuzzing.py (HARNESS BUG)" if isinstance(exc, HarnessError) else _project_frame(exc.__traceback__)
    o.tb_tail = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)[-4:])[-1500:]
    return o


_runner = None


def invoke(args: list[str]):
    """Run the CLI in-process; returns the click Result (stdout and stderr apart)."""
    global _runner
    from typer.testing import CliRunner

    from tertiary.cli.commands import app

    _runner = _runner or CliRunner()
    return _runner.invoke(app, args, catch_exceptions=True, color=False)


def _fresh_out(args: list[str]) -> list[str]:
    """``args`` for the ``--debug`` re-run: a new ``run --out`` (runs never overwrite a run directory)."""
    if args[0] != "run" or "--out" not in args:
        return args
    i = args.index("--out") + 1
    return [*args[:i], args[i] + "-debug", *args[i + 1:]]


def _message_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


INTERNAL = re.compile(r"internal error \((.*)\); run again", re.S)
UNCHECKED_OOM = "out of memory (reduce"


def classify_cli(o: Outcome, res, expect_codes=EXPECTED_CODES, args: list[str] | None = None) -> bool:
    """Fill ``o`` from a CLI result; True when the command succeeded (exit 0).

    Exit 1 (the boundary's "internal error") and the boundary's generic MemoryError message (an
    allocation nobody estimated) are tracebacks; with ``args`` the command is run again under
    ``--debug`` to find the raising frame."""
    o.exit_code = res.exit_code
    exc = res.exception
    if exc is not None and not isinstance(exc, SystemExit):
        _from_exception(o, exc)
        return False
    err = res.stderr or ""
    if "Traceback (most recent call last)" in err + (res.stdout or ""):
        o.cls, o.ok, o.exc = "traceback", False, "printed traceback"
        o.tb_tail = err[-1500:]
        return False
    if res.exit_code == 0:
        return True
    lines = _message_lines(err)
    internal = INTERNAL.search(err)
    if res.exit_code == 1 or internal or UNCHECKED_OOM in err:
        o.cls, o.ok = "traceback", False
        o.exc = internal.group(1).splitlines()[0][:300] if internal else (lines[-1][:300] if lines else "exit 1")
        if UNCHECKED_OOM in err:
            o.exc = "MemoryError: unchecked allocation (boundary's generic out-of-memory message)"
        if args is not None:
            again = invoke(["--debug", *_fresh_out(args)])
            if again.exception is not None and not isinstance(again.exception, SystemExit):
                o.where = _project_frame(again.exception.__traceback__)
                o.tb_tail = "".join(traceback.format_exception(again.exception)[-4:])[-1500:]
        return False
    o.cls = "clear_error"
    o.exc = lines[-1][:300] if lines else (res.stdout or "").strip()[-300:]
    if res.exit_code not in expect_codes:
        o.problems.append(f"exit code {res.exit_code}, expected one of {list(expect_codes)}")
    usage = res.exit_code == 2 and "Usage:" in err  # typer's own usage error: usage line, hint, error
    if len(lines) != 1 and not usage:
        o.problems.append(f"stderr has {len(lines)} non-blank lines, expected 1: {err[:300]!r}")
    o.ok = not o.problems
    return False


def _accounting(db: Path, n_in: int, exp: Expect, o: Outcome) -> int:
    """Check row accounting and the impossible rows in ``rejects``; returns the reject count."""
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        tables = {r[0] for r in con.execute("SHOW TABLES").fetchall()}
        if "rejects" not in tables:
            o.problems.append("run database has no rejects table")
            return 0
        rej = con.execute("SELECT input_table, row_index FROM rejects").fetchall()
        if con.execute("SELECT count(*) FROM rejects WHERE coalesce(trim(reason), '') = ''").fetchone()[0]:
            o.problems.append("a reject without a reason")
        n_aligned = (con.execute("SELECT count(DISTINCT report_id) FROM aligned").fetchone()[0]
                     if "aligned" in tables else 0)
        if "run" not in tables:
            o.problems.append("run database has no run record")
    finally:
        con.close()
    rep_rows = [r for t, r in rej if t == "reports"]
    if n_aligned + len(rep_rows) != n_in or len(set(rep_rows)) != len(rep_rows):
        o.problems.append(f"row accounting broken: {n_in} reports in, {n_aligned} aligned + "
                          f"{len(rep_rows)} rejected ({len(set(rep_rows))} distinct)")
    by_table: dict[str, set[int]] = {}
    for t, r in rej:
        by_table.setdefault(t, set()).add(int(r))
    for t, rows, need, *_ in exp.groups:
        got = len(by_table.get(t, set()) & set(rows))
        if got < need:
            o.problems.append(f"silent: {t} row(s) {rows[:5]} accepted ({got} of {need} rejected)")
    return len(rej)


def _row_level_refused(o: Outcome, exp: Expect) -> None:
    """A dataset whose faults are all row-level (in reports/truth) must give rejects, not a refusal."""
    if o.cls == "clear_error" and exp.rows_only and o.exit_code == 3:
        o.problems.append(f"row-level faults refused as a whole (want rejects): {o.exc[:200]}")
        o.ok = False


def _degenerate_record(db: Path, n_in: int, o: Outcome) -> None:
    """Nothing valid left: the run database still holds a run record and every report in rejects."""
    if not db.exists():
        o.problems.append("degenerate input: no run database (want a run record)")
    else:
        _accounting(db, n_in, Expect(), o)
    o.ok = not o.problems


def _ingest_rejects(db: Path) -> int:
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        return con.execute("SELECT count(*) FROM rejects WHERE stage = 'ingest'").fetchone()[0]
    finally:
        con.close()


def _settle(o: Outcome, exp: Expect, had_rejects: bool) -> Outcome:
    silent = [p for p in o.problems if p.startswith("silent")]
    if silent:
        o.cls = "silent"
    else:
        o.cls = "rejects" if had_rejects else "success"
    o.ok = not o.problems
    return o


def _run_dataset(case: dict, bases: Path, work: Path, o: Outcome) -> Outcome:
    """A mutated dataset through ``tertiary validate`` or ``tertiary run``."""
    ds = work / "ds"
    try:
        exp, n_in = materialise(case, bases, ds)
    except Exception as exc:  # a bug of this harness, never reported as a finding of the project
        raise HarnessError(f"materialise failed: {type(exc).__name__}: {exc}") from exc
    if case["entry"] == "validate":
        return _validate_dir(case, ds, exp, o)
    return _run_dir(case, ds, work, exp, n_in, o)


def _validate_dir(case: dict, ds: Path, exp: Expect, o: Outcome) -> Outcome:
    args = ["validate", str(ds)] + (["--strict"] if case.get("strict") else [])
    res = invoke(args)
    if not classify_cli(o, res, args=args):
        _row_level_refused(o, exp)
        return o
    n_rej = _validate_count(res.stdout or "")
    singles = {(t, rows[0]) for t, rows, *_ in exp.groups if len(rows) == 1}
    if exp.must_error:
        o.problems.append("silent: table-level problem reported as valid" if exp.impossible
                          else "table-level problem not refused")
    elif exp.groups and n_rej is not None and n_rej < max(1, len(singles)):
        o.problems.append(f"silent: {len(singles) or 1}+ impossible row(s) but validate lists {n_rej} reject(s)")
    elif case.get("strict") and exp.groups:
        o.problems.append("silent: --strict exited 0 with impossible rows")
    elif n_rej is None:
        o.problems.append("validate printed no reject count")
    return _settle(o, exp, bool(n_rej))


def _run_args(case: dict, ds: Path, work: Path, out: Path | None) -> list[str]:
    args = ["run", str(ds), "--filters", case["filters"], "--methods", case["methods"],
            "--report" if case.get("report") else "--no-report"]
    args += [] if case.get("centralized", True) else ["--no-centralized"]
    args += ["--strict"] if case.get("strict") else []
    args += ["--out", str(out)] if out else []
    args += ["--origin", case["origin"]] if case.get("origin") else []
    args += ["--safety-picture", case["safety_picture"]] if case.get("safety_picture") else []
    if case.get("bad_opt"):  # one bad option: refused with exit 2 (or 3 for --out on a file) before any work
        (work / "a_file").write_text("x")
        args += [a.replace("{file}", str(work / "a_file")) for a in case["bad_opt"]]
    return args


def _run_dir(case: dict, ds: Path, work: Path, exp: Expect, n_in: int, o: Outcome) -> Outcome:
    cwd = work / "cwd" / "a" / "b"   # deep enough that "../../../x" stays inside this case's directory
    cwd.mkdir(parents=True)
    out = None if case.get("default_out") else work / "run"
    args = _run_args(case, ds, work, out)
    pre = invoke(["validate", str(ds)])  # validate and run share one code path: "valid" must mean it
    said_valid = pre.exit_code == 0 and _validate_count(pre.stdout or "") == 0
    old = os.getcwd()
    os.chdir(cwd)
    try:
        res = invoke(args)
    finally:
        os.chdir(old)
    if exp.name_escape and (cwd / "runs" / exp.name_escape).resolve().exists():
        o.problems.append(f"silent: scenario name {exp.name_escape!r} wrote outside runs/")
    if not classify_cli(o, res, args=args):
        return _run_refused(o, exp, out, n_in, said_valid)
    if case.get("bad_opt") and case["bad_opt"][0] not in ("--seed", "--runs"):  # these two only shape simulation
        o.problems.append(f"silent: bad run option {case['bad_opt']} accepted")
    if exp.must_error:
        o.problems.append("silent: table-level problem accepted by run" if exp.impossible
                          else "table-level problem not refused")
    db = out / "results.duckdb" if out else next((cwd / "runs").rglob("results.duckdb"), None)
    if db is None or not db.exists():
        o.problems.append("exit 0 but no results.duckdb")
        return _settle(o, exp, False)
    if case.get("strict") and exp.groups:
        o.problems.append("silent: --strict run succeeded with impossible rows")
    n_rej = _accounting(db, n_in, exp, o)
    if said_valid and _ingest_rejects(db):
        o.problems.append("validate said the dataset is valid, run rejected rows at ingest")
    return _settle(o, exp, n_rej > 0)


def _run_refused(o: Outcome, exp: Expect, out: Path | None, n_in: int, said_valid: bool) -> Outcome:
    """Checks on a run that ended in an error (``o`` already classified)."""
    if any(p.startswith("silent") for p in o.problems):
        o.cls, o.ok = "silent", False
    _row_level_refused(o, exp)
    if o.cls == "clear_error" and "no valid report left" in o.exc and out is not None:
        _degenerate_record(out / "results.duckdb", n_in, o)  # item 4: a clear message AND a run record
    if said_valid and o.cls == "clear_error" and o.exit_code == 3:
        o.problems.append("validate said the dataset is valid, run refused it (exit 3)")
        o.ok = False
    return o


def _validate_count(text: str) -> int | None:
    """Rows ``validate`` says would be rejected (None when it does not say)."""
    text = " ".join(text.split())
    if re.search(r"reject nothing|nothing rejected", text):
        return 0
    m = re.search(r"reject (\d[\d,]*) rows?|(\d[\d,]*) rows? would be rejected", text)
    return int((m.group(1) or m.group(2)).replace(",", "")) if m else None


def _truth_file(work: Path, how: str, bases: Path) -> str:
    import polars as pl

    p = work / "truth_in.parquet"
    if how == "missing":
        return str(work / "no_such.parquet")
    if how == "garbage":
        p.write_bytes(b"\x89garbage\x00" * 50)
    elif how == "empty":
        p.write_bytes(b"")
    elif how == "csv":
        pl.read_parquet(bases / "ta" / "truth.parquet").select("truth_id", "x_m").write_csv(p)
    else:  # "none": a Parquet file without the ADS-B columns
        pl.DataFrame({"a": [1, 2]}).write_parquet(p)
    return str(p)


def _run_simulate(case: dict, bases: Path, work: Path, o: Outcome) -> Outcome:
    args = list(case["args"])
    if case.get("truth"):
        args += ["--truth", _truth_file(work, case["truth"], bases)]
    out = work / "sim"
    if case.get("out") == "file":
        out.write_text("not a directory")
    elif case.get("out") == "existing_dataset":
        shutil.copytree(bases / "ta", out)
    args += ["--out", str(out)]
    res = invoke(args)
    if not classify_cli(o, res, (2, 3), args=args):
        return o
    o.problems.append(("silent: " if case.get("impossible") else "") + "bad simulate option accepted (exit 0)")
    o.cls, o.ok = "silent" if case.get("impossible") else "success", False
    return o


def _db_state(db: Path) -> tuple:
    import duckdb

    con = duckdb.connect(str(db), read_only=True)
    try:
        tabs = sorted(r[0] for r in con.execute("SHOW TABLES").fetchall())
        counts = tuple(con.execute(f'SELECT count(*) FROM "{t}"').fetchone()[0] for t in tabs)
        reason = con.execute("SELECT min(reason) FROM rejects").fetchone()[0] if "rejects" in tabs else None
    finally:
        con.close()
    return tuple(tabs), counts, reason


def _sql_subprocess(args: list[str], timeout: float) -> tuple[int | None, str, str, float]:
    code = "import sys; from tertiary.cli.commands import app; sys.argv[0] = 'tertiary'; app()"
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
        return proc.returncode, out.decode(errors="replace"), err.decode(errors="replace"), time.perf_counter() - t
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, 9)
        proc.communicate()
        return None, "", "", time.perf_counter() - t


def _run_sql(case: dict, bases: Path, work: Path, o: Outcome) -> Outcome:
    run = work / "run_copy"
    shutil.copytree(bases / "run_ta", run)
    subst = {"{tmp}": str(work), "{bases}": str(bases), "{run}": str(run)}

    def fill(s: str) -> str:
        for k, v in subst.items():
            s = s.replace(k, v)
        return s

    query = fill(case["query"])
    args = (["sql", str(run), case["name"]] if case.get("name") else ["sql", str(run), "--query", query]) \
        + [fill(a) for a in case["args"]]
    before = _db_state(run / "results.duckdb")
    if case.get("subprocess"):
        code, out, err, secs = _sql_subprocess(args, case.get("timeout", 30.0))
        if code is None:
            o.cls, o.ok = "hang", False
            o.problems.append(f"no answer within {case.get('timeout', 30.0)} s (statement timeout not applied)")
            return o
        res = type("R", (), {"exit_code": code, "exception": None, "stdout": out, "stderr": err})()
        if classify_cli(o, res, (3, 4)):
            o.cls, o.ok = "success", False
            o.problems.append("the cross join returned instead of hitting the timeout")
        return o
    res = invoke(args)
    after = _db_state(run / "results.duckdb") if (run / "results.duckdb").is_file() else None
    if after != before:
        o.problems.append(f"silent: the run database changed ({before} -> {after})")
    leaked = [p for p in (work / "x.duckdb", work / "x.csv", work / "exp") if p.exists()]
    if leaked:
        o.problems.append(f"silent: query wrote {leaked}")
    if not classify_cli(o, res, (2, 3, 4), args=args):
        if case["expect"] == "ok":
            o.problems.append("a read-only query that must work was refused")
            o.ok = False
        if o.problems and any(p.startswith("silent") for p in o.problems):
            o.cls, o.ok = "silent", False
        return o
    stdout = res.stdout or ""
    if "root:" in stdout or "[[radars]]" in stdout:
        o.problems.append("silent: a file was read through the query")
    table_format = not any(a in ("--format", "--out") for a in case["args"])
    if table_format and len(stdout.splitlines()) > 1000:
        o.problems.append(f"printed {len(stdout.splitlines())} lines: no row cap in table format")
    for text in ("[/]", "[/truth]"):
        if f"'{text}'" in query and text not in stdout:
            o.problems.append(f"{text!r} in a result was not printed verbatim (read as markup?)")
    if case["expect"] == "error":
        o.problems.append("silent: hostile or invalid query accepted (exit 0)")
    o.cls = "silent" if any(p.startswith("silent") for p in o.problems) else "success"
    o.ok = not o.problems
    return o


def _api_object(case: dict, frame):
    import numpy as np
    import polars as pl

    obj = case["obj"]
    if obj == "frame":
        return frame
    if obj == "none":
        return None
    if obj == "dict":
        return {"a": [1, 2]}
    if obj == "columns_dict":
        return {c: frame[c].to_list() for c in frame.columns if not isinstance(frame[c].dtype, pl.Array)}
    if obj == "numpy":
        return np.zeros((3, 4))
    if obj == "lazy":
        return frame.lazy()
    if obj == "arrow":
        return frame.to_arrow()
    if obj == "list":
        return [1, 2, 3]
    if obj == "pandas":
        try:
            return frame.to_pandas()
        except Exception:  # pandas absent: a plain object instead
            return object()
    return "reports.parquet"


def _run_api(case: dict, bases: Path, work: Path, o: Outcome) -> Outcome:
    import polars as pl

    import tertiary
    from tertiary.core.errors import TertiaryError

    t = case["table"]
    frames = {x: pl.read_parquet(bases / case["base"] / f"{x}.parquet") for x in ("radars", t)}
    exp = Expect()
    frames = apply_frame_ops(frames, case["ops"], exp)
    frame = frames[t]
    radars_given = bool(case.get("with_radars")) and t == "reports"
    exp.groups = [g for g in exp.groups if g[3] == "any" or (g[3] == "radars" and radars_given)]
    obj = _api_object(case, frame)
    kw = {"radars": frames["radars"]} if radars_given else {}
    try:
        out = tertiary.validate(obj, case["kind"], strict=case["strict"], **kw)
    except TertiaryError as exc:
        o.cls, o.exc = "clear_error", f"{type(exc).__name__}: {exc}"[:300]
        if "\n" in str(exc).strip() or not str(exc).strip():
            o.problems.append("error message is empty or spans several lines")
        rows_only = all(op["op"] in ("set", "text", "dup") for op in case["ops"])
        if (case["obj"] == "frame" and case["kind"] in REQUIRED and not case["strict"] and rows_only
                and frame.height > 1):
            o.problems.append(f"row-level faults refused as a whole with strict=False (want rejects): {exc}"[:300])
        o.ok = not o.problems
        return o
    except BaseException as exc:  # noqa: BLE001 -- classifying every escape is the point
        return _from_exception(o, exc)
    if case["kind"] in ("nope", ""):
        o.problems.append(f"unknown kind {case['kind']!r} accepted")
    if case["kind"] not in REQUIRED:  # an output-table kind: no row expectations from the mutations
        return _settle(o, Expect(), False) if not o.problems else _fail(o)
    if case["obj"] != "frame":
        return _settle(o, exp, False) if not o.problems else _fail(o)
    if exp.must_error:
        o.problems.append("silent: table-level problem accepted")
    if case["strict"]:
        if exp.groups:
            o.problems.append(f"silent: strict=True returned with {len(exp.groups)} impossible row group(s)")
        return _settle(o, exp, False)
    clean, rejects = out
    if clean.height + rejects.height != frame.height:
        o.problems.append(f"row accounting broken: {frame.height} in, {clean.height} clean + {rejects.height} rejected")
    got = set(rejects["row_index"].to_list()) if "row_index" in rejects.columns else set()
    for _, rows, need, *_ in exp.groups:
        if len(got & set(rows)) < need:
            o.problems.append(f"silent: {t} row(s) {rows[:5]} accepted")
    return _settle(o, exp, rejects.height > 0)


def _fail(o: Outcome) -> Outcome:
    o.cls, o.ok = "success", False
    return o


def execute(case: dict, bases: Path, scratch: Path | None = None) -> Outcome:
    """Run one case in this process and classify it."""
    o = Outcome(entry=case["entry"], cls="success", ok=True, case=case)
    work = Path(tempfile.mkdtemp(prefix="case-", dir=scratch))
    t = time.perf_counter()
    try:
        fn = {"validate": _run_dataset, "run": _run_dataset, "simulate": _run_simulate, "sql": _run_sql,
              "api": _run_api}[case["entry"]]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            fn(case, bases, work, o)
    except BaseException as exc:  # noqa: BLE001 -- harness-level escapes (e.g. a Rust panic) are findings
        if isinstance(exc, KeyboardInterrupt):
            raise
        _from_exception(o, exc)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    o.seconds = time.perf_counter() - t
    if o.cls not in CLASSES:
        raise AssertionError(o.cls)
    return o


# ---------------------------------------------------------------------------
# a worker process: memory limit, per-case timeout, crash isolation
# ---------------------------------------------------------------------------

TIMEOUTS = {"validate": 60.0, "run": 120.0, "simulate": 60.0, "sql": 60.0, "api": 60.0}
MEMORY_LIMIT = 4 << 30


class Worker:
    """A child process that executes cases (JSON lines in, JSON lines out on a private pipe).

    The child runs under ``RLIMIT_AS`` so that an unbounded allocation fails there instead of on
    the shared machine; a case past its timeout is classified ``hang`` and the child restarted.
    """

    def __init__(self, bases: Path, scratch: Path, memory: int = MEMORY_LIMIT):
        self.bases, self.scratch, self.memory = bases, scratch, memory
        self.proc: subprocess.Popen | None = None

    def _start(self) -> None:
        r, w = os.pipe()
        mem = self.memory

        def limit() -> None:
            import resource
            resource.setrlimit(resource.RLIMIT_AS, (mem, mem))

        env = {**os.environ, "POLARS_MAX_THREADS": "2"}
        self.proc = subprocess.Popen(
            [sys.executable, str(HERE), "worker", str(w), str(self.bases), str(self.scratch)],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, pass_fds=(w,),
            preexec_fn=limit, env=env, start_new_session=True, cwd=str(self.scratch))
        os.close(w)
        self.out = os.fdopen(r, "r")

    def stop(self) -> None:
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, 9)
            self.proc.wait()
            self.out.close()
            self.proc = None

    def run(self, case: dict, timeout: float | None = None) -> Outcome:
        if self.proc is None or self.proc.poll() is not None:
            self.stop()
            self._start()
        timeout = timeout or max(TIMEOUTS[case["entry"]], case.get("timeout", 0.0) + 30.0)
        t = time.perf_counter()
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write((json.dumps(case) + "\n").encode())
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.out], [], [], timeout + 20.0)  # + start-up time of a new child
        line = self.out.readline() if ready else ""
        if line:
            d = json.loads(line)
            d["case"] = case
            return Outcome(**d)
        code = self.proc.poll()
        self.stop()
        o = Outcome(entry=case["entry"], cls="hang" if code is None else "traceback", ok=False, case=case,
                    seconds=time.perf_counter() - t)
        if code is None:
            o.problems.append(f"no answer within {timeout:.0f} s")
        else:
            o.exc = f"worker process died (exit {code}, signal {-code if code < 0 else 0})"
        return o


def _worker_main(fd: int, bases: str, scratch: str) -> None:
    out = os.fdopen(fd, "w")
    for line in sys.stdin:
        case = json.loads(line)
        o = execute(case, Path(bases), Path(scratch))
        d = dataclasses.asdict(o)
        d.pop("case")
        out.write(json.dumps(d, default=str) + "\n")
        out.flush()


def summarise(outcomes: list[Outcome]) -> tuple[dict, dict]:
    """The per-entry-point table and the first reproducer of each distinct failure."""
    table = {e: {"cases": 0, **{c: 0 for c in CLASSES}, "contract_failures": 0} for e in ENTRIES}
    failures: dict[str, dict] = {}
    for o in outcomes:
        row = table[o.entry]
        row["cases"] += 1
        row[o.cls] += 1
        if not o.ok:
            row["contract_failures"] += 1
            sig = o.signature
            if sig not in failures:
                failures[sig] = {"entry": o.entry, "class": o.cls, "exception": o.exc, "where": o.where,
                                 "problems": o.problems[:3], "tb_tail": o.tb_tail, "reproducer": o.reproducer(),
                                 "count": 0}
            failures[sig]["count"] += 1
    return table, failures


def format_table(table: dict) -> str:
    cols = ("cases", "clear_error", "rejects", "success", "traceback", "silent", "hang", "contract_failures")
    lines = ["| entry point | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for e, row in table.items():
        lines.append(f"| {e} | " + " | ".join(str(row[c]) for c in cols) + " |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    if argv[:1] == ["worker"]:
        _worker_main(int(argv[1]), argv[2], argv[3])
        return
    if argv[:1] == ["replay"]:
        case = json.loads(argv[1])
        bases = build_bases(Path(os.environ.get("FUZZ_BASES", Path(tempfile.gettempdir()) / "tertiary-fuzz-bases")))
        o = execute(case, bases)
        print(json.dumps(dataclasses.asdict(o), indent=1, default=str))
        return
    raise SystemExit("usage: fuzzing.py replay '<case json>' | worker FD BASES SCRATCH")


if __name__ == "__main__":
    try:  # the installed package (CI installs the project); the source tree only when it is not installed
        import tertiary  # noqa: F401
    except ImportError:
        sys.path.insert(0, str(REPO))
    main(sys.argv[1:])
