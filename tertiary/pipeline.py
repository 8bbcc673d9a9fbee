"""The batch job: dataset in, one DuckDB run database out.

Stages are composed here and nowhere else. At this stage of the project the job ingests and
validates the input tables (every report ends up in ``reports`` or ``rejects``) and records
the run; later stages (alignment, association, fusion, trackers, safety) append their tables.
"""

from __future__ import annotations

import hashlib
import platform
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import polars as pl

from tertiary import schema
from tertiary.simulate import Dataset, scenario_toml
from tertiary.store import RunStore, record_run

Progress = Callable[[str], None]


@dataclass
class Ingested:
    """Validated input tables and every rejected row with its reason."""

    radars: pl.DataFrame
    reports: pl.DataFrame
    truth: pl.DataFrame
    rejects: pl.DataFrame
    notes: list[str] = field(default_factory=list)


def _validate_table(frame: pl.DataFrame, kind: str, strict: bool, notes: list[str], **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", schema.UnsortedTimeWarning)
        out = schema.validate(frame, kind, strict=strict, **kw)
    notes.extend(str(w.message) for w in caught if issubclass(w.category, schema.UnsortedTimeWarning))
    if strict:
        return out, schema.empty_frame("rejects")
    clean, rejects = out
    return clean, schema.rejects_table(rejects, kind, "ingest")


def ingest(ds: Dataset, strict: bool = False) -> Ingested:
    """Validate radars, reports (against the radars) and truth.

    Strict mode raises :class:`tertiary.schema.SchemaError` on the first problem; lenient mode
    moves bad rows to ``rejects`` with a reason.
    """
    notes: list[str] = []
    radars, rej_r = _validate_table(ds.radars, "radars", strict, notes)
    reports, rej_p = _validate_table(ds.reports, "reports", strict, notes, radars=radars)
    truth, rej_t = (_validate_table(ds.truth, "truth", strict, notes) if ds.truth.height
                    else (ds.truth, schema.empty_frame("rejects")))
    rejects = pl.concat([r for r in (rej_r, rej_p, rej_t) if r.height] or [schema.empty_frame("rejects")],
                        how="vertical_relaxed")
    return Ingested(radars, reports, truth, rejects, notes)


def fingerprint(frame: pl.DataFrame) -> str:
    """A content hash of a table (row hashes combined), for the run record."""
    if frame.height == 0:
        return "empty"
    h = frame.hash_rows(seed=0)
    return hashlib.sha256(h.to_numpy().tobytes()).hexdigest()[:16]


def run(ds: Dataset, out_dir: str | Path, *, strict: bool = False, progress: Progress | None = None) -> Path:
    """Run the job on a dataset and write ``out_dir/results.duckdb`` atomically."""
    say = progress or (lambda _m: None)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    say("validate")
    ing = ingest(ds, strict=strict)
    timings["ingest_s"] = time.perf_counter() - t0
    n_in, n_ok, n_rej = ds.reports.height, ing.reports.height, ing.rejects.filter(pl.col("input_table") == "reports").height
    if n_ok + n_rej != n_in:
        raise RuntimeError(f"row accounting broken: {n_in} reports in, {n_ok} valid + {n_rej} rejected")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say("store")
    with RunStore.create(out) as store:
        store.write("radars", ing.radars)
        store.write("reports", ing.reports)
        if ing.truth.height:
            store.write("truth", ing.truth)
        store.write("rejects", ing.rejects)
        if ds.removed.height:
            store.write("truth_removed", ds.removed)
        timings["total_s"] = time.perf_counter() - t0
        record_run(store, {
            "scenario": ds.scenario.name,
            "scenario_toml": scenario_toml(ds.scenario),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": _versions(),
            "fingerprints": {k: fingerprint(getattr(ds, k)) for k in ("radars", "reports", "truth")},
            "rows": {"reports_in": n_in, "reports_valid": n_ok, "reports_rejected": n_rej},
            "notes": ing.notes,
            "timings": timings,
        })
    return out / "results.duckdb"


def _versions() -> dict[str, str]:
    from importlib import metadata
    names = ["tertiary", "polars", "numpy", "scipy", "duckdb", "filterpy", "scikit-learn", "plotly", "pymap3d"]
    out = {"python": platform.python_version()}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            out[n] = "not installed"
    return out
