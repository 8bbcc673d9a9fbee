"""A run of the job: :func:`process` (every stage, the tables returned) and :func:`run` (window by
window into a run directory, resumable, then ``results.duckdb`` with the run record: its
configuration, versions, input fingerprints, timings and status — also when a stage fails)."""

from __future__ import annotations

import hashlib
import platform
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import polars as pl

from tertiary import contract
from tertiary.core.errors import DataError, TertiaryError
from tertiary.io.dataset import Dataset
from tertiary.pipeline.clock import Progress, StageClock
from tertiary.pipeline.config import PipelineConfig, adapt_to_scenario, check_config, config_dict
from tertiary.pipeline.ingestion import truth_lazy
from tertiary.pipeline.streaming import StreamState, stream_windows
from tertiary.pipeline.tables import Sink, SinkThread, check_tables, make_storable, part_trim, store_sink
from tertiary.pipeline.warmup import kernels_for, warm_kernels
from tertiary.pipeline.whole_run import Results, finalize_stages
from tertiary.runtime.windows import (AUTO_WINDOW, DEFAULT_WINDOW_S, STREAMED, MemoryParts, PartStore, check_window,
                                      config_hash, is_auto, resolve_window)
from tertiary.simulate.config import scenario_toml
from tertiary.store.run_store import TABLES_DIR, RunStore, record_run

__all__ = ["StageError", "fingerprint", "fingerprints", "process", "run", "scenario_text", "versions"]


def fingerprint(frame: pl.DataFrame) -> str:
    """A content hash of a table (row hashes combined), for the run record."""
    if frame.height == 0:
        return "empty"
    h = frame.hash_rows(seed=0)
    return hashlib.sha256(h.to_numpy().tobytes()).hexdigest()[:16]


class StageError(TertiaryError):
    """A stage failed unexpectedly; the completed stages and a run record were stored first."""

    def __init__(self, stage: str, cause: BaseException, db: Path) -> None:
        text = str(cause).strip().splitlines()[0] if str(cause).strip() else ""
        super().__init__(f"stage '{stage}' failed ({type(cause).__name__}: {text}); the completed stages "
                         f"and a run record saying so are in {db}")
        self.stage, self.db = stage, db


def process(ds: Dataset, cfg: PipelineConfig | None = None, progress: Progress | None = None,
            sink: Sink | None = None, notes: list[str] | None = None, window_s: float | None = None,
            parts: Any = None, resume_state: StreamState | None = None, start: int = 0) -> Results:
    """Run every stage and return the tables (``cfg`` None = the defaults).

    The streamed stages see the run in windows of ``window_s`` seconds (None: one window) and
    carry their state across them (:mod:`tertiary.runtime.windows`); ``parts`` receives each window's rows
    (default: kept in memory), then the whole-run stages (evaluation, alert scoring) run on them.
    ``sink(name, frame)`` receives each table once it is final; ``notes`` (if given) collects the
    run's notes as they arise, so they survive a failure. An exception carries the failing
    stage's name in ``exc.tertiary_stage``. No valid report left → :class:`DataError` after the
    rejects are sunk.
    """
    cfg = adapt_to_scenario(check_config(cfg), ds)
    window_s = check_window(window_s)
    # a fresh install compiles the kernels on the other core while the first stages run
    warm_kernels(kernels_for(cfg.filters, bound=truth_lazy(ds) is not None))
    clock = StageClock(progress or (lambda _m: None))
    sink = sink or (lambda _n, _f: None)
    parts = parts if parts is not None else MemoryParts()
    # the tables known before the end (the truth) are written while the windows run
    writer = SinkThread(sink)
    try:
        return _process(ds, cfg, clock, writer, notes, window_s, parts, resume_state, start)
    except Exception as exc:
        # a write's failure is raised in a later stage's time: it names its own
        stage = getattr(exc, "tertiary_stage", None) or clock.name or "validate"
        exc.tertiary_stage = stage  # type: ignore[attr-defined]
        writer.close()          # the writes in flight end before the partial tables are written
        if not getattr(exc, "_sunk", False):
            _sink_partial(parts, sink)
        raise
    finally:
        writer.close()


def _sink_partial(parts: Any, sink: Sink) -> None:
    """After a failure: every streamed table of the windows that completed."""
    for name in ("radars", *STREAMED):
        try:
            frame = parts.table(name)
        except Exception:  # a part that cannot be read back: the record says the run failed anyway
            continue
        if frame is not None:
            sink(name, frame)


def _process(ds: Dataset, cfg: PipelineConfig, clock: StageClock, sink: SinkThread, notes: list[str] | None,
             window_s: float | None = None, parts: Any = None, resume_state: StreamState | None = None,
             start: int = 0) -> Results:
    """Stream every window through :func:`pipeline_step`, then finalize on the whole run."""
    t_all = time.perf_counter()
    notes = [] if notes is None else notes
    parts = parts if parts is not None else MemoryParts()
    ctx, st, source = stream_windows(ds, cfg, clock, notes, window_s, parts, resume_state, start, evaluate=True,
                                     sink=sink)
    return finalize_stages(ds, cfg, ctx, st, parts, clock, sink, notes, source.n_rows, t_all)


def scenario_text(ds: Dataset, notes: list[str]) -> str:
    """The dataset's scenario as TOML for the run record ("" with a note when it cannot be written)."""
    try:
        return scenario_toml(ds.scenario)
    except (ValueError, TypeError) as exc:
        notes.append(f"scenario.toml not recorded: {exc}")
        return ""


def _run_window(window_s: float | str | None, ds: Dataset, cfg: PipelineConfig) -> float | None:
    """:func:`tertiary.runtime.windows.resolve_window`; an input whose reports cannot even be scanned gets
    the default window, and the run itself then reports what is wrong with them (in the run
    record and the rejects, not as an error before the run directory exists)."""
    if not is_auto(window_s):
        return check_window(window_s)
    try:
        return resolve_window(window_s, ds.reports, cfg.limits, len(cfg.methods))
    except (pl.exceptions.PolarsError, OSError, ValueError, TypeError):  # fails again in validate, recorded there
        return DEFAULT_WINDOW_S


def run(ds: Dataset, out_dir: str | Path, cfg: PipelineConfig | None = None, *,
        progress: Progress | None = None, window_s: float | str | None = AUTO_WINDOW, resume: bool = False,
        dataset_label: str = "", tables: str = "database") -> Path:
    """Run the job on a dataset in windows of ``window_s`` seconds (``"auto"``: sized by the
    recording's report rate, :func:`tertiary.runtime.windows.auto_window_s`; None: one window) and write
    ``out_dir/results.duckdb`` atomically.

    Each window's streamed tables are written to ``out_dir/parts`` as it completes, with the
    carried state and a manifest (:mod:`tertiary.runtime.windows`); ``resume`` continues a killed run from
    its last complete window (same configuration, window and dataset, else :class:`OptionError`).
    The database is built as the run goes (the truth and the stored windows' tables copied in
    beside the windows, :class:`~tertiary.pipeline.tables.StoreSink`) and put in place at the end,
    when the manifest is marked complete; ``tables="parquet"``
    keeps the streamed tables' window parts as Parquet in ``out_dir/tables`` with views over
    them in the database instead of copying them in (:meth:`RunStore.register_parquet`). If a
    stage fails (including "no valid report left"), the database still holds every completed
    window's tables, the rejects and a run record with ``failed_stage`` and ``error``; then a
    :class:`TertiaryError` is raised (the original one, or :class:`StageError` wrapping an
    unexpected exception).
    """
    t_wall = time.perf_counter()
    cfg = adapt_to_scenario(check_config(cfg), ds)
    check_tables(tables, out_dir)
    # before anything reads the input (process: again, a no-op)
    warm_kernels(kernels_for(cfg.filters, bound=truth_lazy(ds) is not None))
    window_s = _run_window(window_s, ds, cfg)
    say = progress or (lambda _m: None)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create the run directory: {exc.strerror or exc}", path=str(out)) from exc
    notes: list[str] = []
    failure: Exception | None = None
    res: Results | None = None
    trim = part_trim(tables, cfg.radar_health)
    header = {"dataset": dataset_label or ds.scenario.name, "window_s": window_s,
              "config_hash": config_hash(cfg, window_s, _input_identity(ds, dataset_label)),
              "parts": "full" if trim is None else "lean"}
    state, start = None, 0
    if resume:
        parts, state = PartStore.resume(out, header, trim)
        start = int(parts.manifest["windows_done"])
        say(f"resuming after window {start} ({parts.manifest.get('time_done', '?')})")
    else:
        parts = PartStore.start(out, header, trim)
        shutil.rmtree(out / TABLES_DIR, ignore_errors=True)     # a replaced run's registered tables
    with RunStore.create(out) as store, ThreadPoolExecutor(1, thread_name_prefix="fingerprints") as pool:
        # the inputs hashed beside the windows: the end only records them
        prints = pool.submit(fingerprints, ds)
        sink = store_sink(store, notes, tables)
        try:
            res = process(ds, cfg, say, sink=sink, notes=notes, window_s=window_s, parts=parts,
                          resume_state=state, start=start)
        except Exception as exc:  # recorded, then re-raised below
            failure = exc
        say("store")
        t = time.perf_counter()
        if isinstance(ds.removed, pl.DataFrame) and ds.removed.height:
            store.write("truth_removed", make_storable(ds.removed, "truth_removed", notes))
        info = {
            "scenario": ds.scenario.name,
            "scenario_toml": scenario_text(ds, notes),
            "config": config_dict(cfg),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": versions(),
            "fingerprints": prints.result(),
            "window_s": window_s,
            "tables": tables,
        }
        if res is not None:
            res.timings["store_s"] = time.perf_counter() - t
            # the run's one wall time: validate → store, measured once; the CLI summary and the
            # report header both show this figure
            res.timings["wall_s"] = time.perf_counter() - t_wall
            info.update(rows=res.counts, notes=notes, timings=res.timings, memory_mib=res.memory_mib,
                        status="completed")
        else:
            stage = getattr(failure, "tertiary_stage", "validate")
            info.update(status="failed", failed_stage=stage, error=f"{type(failure).__name__}: {failure}",
                        notes=notes)
        record_run(store, info)
    parts.finish("complete" if failure is None else "failed")
    if failure is not None:
        db = out / "results.duckdb"
        if isinstance(failure, TertiaryError):
            failure.add_note(f"the completed stages, the rejects and a run record are in {db}")
            raise failure
        raise StageError(getattr(failure, "tertiary_stage", "validate"), failure, db) from failure
    return out / "results.duckdb"


def _input_identity(ds: Dataset, label: str) -> str:
    """What a resumed run must be given again: the dataset's name and its reports' size and span."""
    try:
        lf = ds.reports.lazy() if isinstance(ds.reports, (pl.DataFrame, pl.LazyFrame)) else None
        span = (lf.select(pl.len(), pl.col("time").cast(pl.String).min(), pl.col("time").cast(pl.String).max())
                .collect().row(0) if lf is not None else ())
    except Exception:  # an unreadable time column: the size alone
        span = ()
    return f"{label or ds.scenario.name}|{span}"


#: rows of a lazy input table :func:`_fingerprint_any` hashes at a time (a day's truth: 80 M rows)
FINGERPRINT_BATCH_ROWS = 1 << 20


def fingerprints(ds: Dataset) -> dict[str, str]:
    """The dataset's input tables' fingerprints (:func:`fingerprint`), as the run record keeps them."""
    return {k: _fingerprint_any(getattr(ds, k)) for k in ("radars", "reports", "truth")}


def _fingerprint_any(frame: Any) -> str:
    """:func:`fingerprint` of a table in any form the dataset holds it (lazy: without holding it)."""
    try:
        if isinstance(frame, pl.LazyFrame):   # hashed a batch at a time: not even the row hashes held whole
            n = frame.select(pl.len()).collect().item()
            digest = hashlib.sha256()
            for off in range(0, n, FINGERPRINT_BATCH_ROWS):
                h = (frame.slice(off, FINGERPRINT_BATCH_ROWS).select(pl.struct(pl.all()).hash(seed=0))
                     .collect(engine="streaming"))
                digest.update(h.to_series().to_numpy().tobytes())
            return digest.hexdigest()[:16]
        return fingerprint(contract.as_frame(frame, "table"))
    except Exception:  # an unhashable column type: the record says so instead of failing
        return "unavailable"


def versions() -> dict[str, str]:
    """The Python version and the installed versions of the packages a run's numbers depend on."""
    names = ["tertiary", "polars", "numpy", "scipy", "duckdb", "filterpy", "scikit-learn", "plotly", "pymap3d"]
    out = {"python": platform.python_version()}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            out[n] = "not installed"
    return out
