"""Whole workflows over the library, as the command line runs them: the batch job (simulate or read
a dataset, run the pipeline on the local or the Dask engine, write the report) and the evaluation of
external pictures. They take plain arguments and return what a caller prints; progress goes to a
``steps`` factory (``steps(title)`` is a context manager yielding ``say(message)``)."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import polars as pl

from tertiary.core import geo
from tertiary.core.errors import DataError, OptionError
from tertiary.evaluation.evaluate import (RECONSTRUCTED, Evaluation, EvaluationConfig, adsb_reference_table,
                                         evaluate_pictures, read_parquet_file, read_pictures,
                                         reconstructed_reference, reference_error_metrics)
from tertiary.evaluation.matching import MatchConfig
from tertiary.evaluation.radar_eval import radar_metrics
from tertiary.evaluation.reference import ReferenceConfig, adsb_quality_note
from tertiary.evaluation.requirements import Requirements, example_path, load_requirements
from tertiary.io.dataset import Dataset, read_dataset, write_dataset
from tertiary.pipeline.runner import run
from tertiary.pipeline.config import PipelineConfig
from tertiary.report.html import build_report
from tertiary.pipeline.dask_engine import run_dask
from tertiary.pipeline.warmup import kernels_for, warm_kernels
from tertiary.sensors.local_tracks import ESTIMATE_COLUMNS
from tertiary.sensors.registration import read_table
from tertiary.simulate import simulate
from tertiary.simulate.config import ScenarioConfig
from tertiary.store.run_store import RunStore, record_run

#: a stage's progress: ``steps(title)`` is a context manager yielding ``say(message)``
Steps = Callable[[str], AbstractContextManager[Callable[[str], None]]]

#: where runs go when no run directory is given
RUNS_DIR = Path("runs")


@contextmanager
def no_steps(title: str) -> Iterator[Callable[[str], None]]:
    """Progress that reports nothing."""
    yield lambda message: None


def _ignore(note: str) -> None:
    pass


# --------------------------------------------------------------------------- run directories


def check_writable_dir(path: Path, option: str) -> None:
    """Refuse an output directory that cannot be created or written, before any work is done
    (an :class:`OptionError` naming ``option``)."""
    if path.exists() and not path.is_dir():
        raise OptionError(f"{path} is a file, not a directory", option=option)
    parent = path if path.exists() else next((p for p in path.parents if p.exists()), Path("."))
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise OptionError(f"cannot create or write {path} ({parent} is not writable)", option=option)


def holds_run(path: Path) -> bool:
    """True when ``path`` already holds a run (its database, report or a windowed run's manifest)."""
    return any((path / f).exists() for f in ("results.duckdb", "report.html", "manifest.json"))


def choose_run_dir(out: Path | None, scenario_name: str, force: bool) -> tuple[Path, str | None]:
    """Where this run goes, and a note when it is not where the user may expect.

    An explicit ``--out`` that already holds a run is refused unless ``force``; without ``--out``
    the run goes to ``runs/<scenario>``, or to the first free ``runs/<scenario>-N`` when that holds
    an earlier run, so that no run is ever overwritten silently."""
    if out is not None:
        check_writable_dir(out, "--out")
        if holds_run(out) and not force:
            raise OptionError(f"{out} already holds a run; give --force to replace it, or another --out",
                              option="--out")
        return out, None
    if not scenario_name.replace("-", "_").isidentifier():
        raise OptionError(f"scenario name {scenario_name!r} cannot name a run directory; give --out", option="--out")
    base = RUNS_DIR / scenario_name
    check_writable_dir(base, "--out")
    if force or not holds_run(base):
        return base, None
    n = 2
    while holds_run(RUNS_DIR / f"{scenario_name}-{n}"):
        n += 1
    new = RUNS_DIR / f"{scenario_name}-{n}"
    return new, f"{base} holds an earlier run; this run goes to {new} (--force replaces {base})"


# --------------------------------------------------------------------------- the batch job


def stored_registration(dataset: Path | None) -> tuple[tuple[float, ...], ...]:
    """Rows of DATASET/registration.parquet for :attr:`PipelineConfig.registration` (() = estimate)."""
    path = None if dataset is None else dataset / "registration.parquet"
    if path is None or not path.exists():
        return ()
    table = read_table(path)
    gain = table["range_gain"].fill_nan(0.0).fill_null(0.0) if "range_gain" in table.columns else \
        pl.Series([0.0] * table.height)
    return tuple(zip(table["radar_id"].cast(pl.Float64).to_list(), table["range_bias_m"].to_list(),
                     table["azimuth_bias_deg"].to_list(), table["time_offset_s"].to_list(), gain.to_list()))


@dataclass
class JobResult:
    """Where a job wrote its results: the run database and the HTML report (None: not written)."""
    db: Path
    report: Path | None


@dataclass
class Engine:
    """How the pipeline runs: ``local`` (this process, windows of ``window_s``, resumable) or
    ``dask`` (dask.distributed: Monte-Carlo runs and, with ``slice_s``, time slices in parallel)."""
    name: str = "local"
    window_s: float | str | None = None
    resume: bool = False
    workers: int | None = None
    scheduler: str | None = None
    slice_s: float | None = None
    overlap_s: float | None = None
    tables: str = "database"


def _job_input(dataset: Path | None, scenario: ScenarioConfig | None, out: Path | None, force: bool,
               origin: tuple[float, float, float] | None, steps: Steps) -> tuple[Dataset, Path, str | None]:
    """The job's dataset (read window by window, or simulated), its run directory and a note on it;
    the run directory is chosen (or refused) before any simulation."""
    if dataset is not None:
        ds = read_dataset(dataset, origin=origin, lazy=True)
        run_dir, note = choose_run_dir(out, ds.scenario.name, force)
        return ds, run_dir, note
    if scenario is None:
        raise OptionError("give a dataset or a scenario to simulate")
    run_dir, note = choose_run_dir(out, scenario.name, force)
    with steps(f"simulate {scenario.name}") as say:
        ds = simulate(scenario, progress=say)
    return ds, run_dir, note


def _run_engine(ds: Dataset, dataset: Path | None, run_dir: Path, cfg: PipelineConfig, engine: Engine,
                steps: Steps) -> Path:
    """The pipeline on the chosen engine; the run database's path."""
    if engine.name == "dask":
        source = dataset
        if source is None:     # the workers read the dataset from disk
            source = write_dataset(ds, run_dir / "input")
        with steps("pipeline (dask)") as say:
            overlap = engine.overlap_s if engine.overlap_s is not None else (engine.window_s or 120.0)
            return run_dask(source, run_dir, cfg, workers=engine.workers, scheduler=engine.scheduler,
                            window_s=engine.window_s, slice_s=engine.slice_s, overlap_s=overlap, progress=say,
                            tables=engine.tables)
    with steps("pipeline") as say:
        return run(ds, run_dir, cfg, progress=say, window_s=engine.window_s, resume=engine.resume,
                   dataset_label=str(dataset) if dataset is not None else "", tables=engine.tables)


def run_job(cfg: PipelineConfig, *, dataset: Path | None = None, scenario: ScenarioConfig | None = None,
            out: Path | None = None, force: bool = False, origin: tuple[float, float, float] | None = None,
            engine: Engine = Engine(), register: bool = False, recompute_local_tracks: bool = False,
            report: bool = True, steps: Steps = no_steps, notify: Callable[[str], None] = _ignore) -> JobResult:
    """The batch job: read ``dataset`` (or simulate ``scenario``), run the pipeline with ``cfg`` into
    ``out`` (see :func:`choose_run_dir`), then write the HTML report.

    ``register`` corrects each radar's biases (DATASET/registration.parquet when present, else
    estimated); ``recompute_local_tracks`` drops the reports' own local-track estimates so that
    alignment recomputes them with ``cfg.align.local_tracker``. Notes on the run go to ``notify``."""
    # a fresh install compiles the kernels in the background from here, while the job simulates
    # or reads its input (the pipeline would start it only once the input is read)
    warm_kernels(kernels_for(cfg.filters))
    ds, run_dir, note = _job_input(dataset, scenario, out, force, origin, steps)
    if note:
        notify(note)
    if register:
        cfg = dataclasses.replace(cfg, register=True, registration=stored_registration(dataset))
    if recompute_local_tracks:
        ds = dataclasses.replace(ds, reports=ds.reports.drop([c for c in ESTIMATE_COLUMNS if c in ds.reports.columns]))
    db = _run_engine(ds, dataset, run_dir, cfg, engine, steps)
    html_path = None
    if report:
        with steps("report") as say:
            html_path = build_report(run_dir, progress=say)
    return JobResult(Path(db), html_path)


# --------------------------------------------------------------------------- evaluation


@dataclass
class EvaluationRun:
    """An evaluation written to ``db``: the pictures and reference scored, and the scores."""
    evaluation: Evaluation
    pictures: pl.DataFrame
    reference: pl.DataFrame
    db: Path
    wall_s: float
    with_requirements: bool
    notes: list[str] = dataclasses.field(default_factory=list)


@dataclass
class _Reference:
    table: pl.DataFrame
    truth: pl.DataFrame | None = None          # the dataset's truth when the reference is not it
    radars: pl.DataFrame | None = None
    frame: geo.LocalFrame | None = None
    reports: pl.DataFrame | None = None
    cfg: EvaluationConfig = dataclasses.field(default_factory=EvaluationConfig)
    #: the reference rows left out, with their reasons (an ADS-B reference's quality filter)
    removed: pl.DataFrame | None = None
    #: how the reference was built, in words
    notes: list[str] = dataclasses.field(default_factory=list)


def _reference(truth: Path | None, dataset: Path | None, kind: str, adsb: Path | None) -> _Reference:
    """The reference to score against: a truth file, or a dataset's truth, reconstruction or ADS-B."""
    if dataset is None:
        return _Reference(read_parquet_file(truth))
    ds = read_dataset(dataset)
    ref = _Reference(ds.truth, None, ds.radars, ds.origin, ds.reports)
    reports = ds.reports
    if kind == "reconstruct":
        key = "truth_id" if "truth_id" in reports.columns and reports["truth_id"].null_count() < reports.height \
            else "mode_s"
        ref.truth, ref.table = ref.table, reconstructed_reference(reports, ds.radars, ds.origin, key=key)
    elif kind == "adsb":
        raw = read_parquet_file(adsb)
        ref.truth, (ref.table, ref.removed) = ref.table, adsb_reference_table(raw, ds.origin)
        ref.cfg = EvaluationConfig(match=MatchConfig(max_gap_s=10.0))   # short gaps only
        ref.notes.append(adsb_quality_note(ReferenceConfig(), ref.removed))
    if ref.table.height == 0:
        raise DataError("the dataset has no usable truth.parquet to evaluate against", path=str(dataset))
    return ref


def _score(pictures: pl.DataFrame, ref: _Reference, kind: str, reqs: Requirements | None, say: Callable[[str], None]) -> Evaluation:
    """Match and score the pictures, plus the reference's own error, the reconstructed reference
    against the truth and the per-radar evaluation when the data allow."""
    say("match and score")
    ev = evaluate_pictures(pictures, ref.table, radars=ref.radars, frame=ref.frame, requirements=reqs, cfg=ref.cfg)
    extra = [reference_error_metrics(ev.metrics, ref.table)]
    if kind == "reconstruct" and ref.truth is not None and ref.truth.height:
        say("reconstructed reference against the truth")
        as_picture = ref.table.with_columns(pl.lit(0, pl.UInt32).alias("run"), pl.col("time").alias("epoch"),
                                            pl.col("truth_id").cast(pl.UInt64).alias("track_id"),
                                            pl.lit(RECONSTRUCTED).alias("method"))
        extra.append(evaluate_pictures(as_picture, ref.truth, radars=ref.radars, frame=ref.frame).metrics)
    reports = ref.reports
    if reports is not None and "truth_id" in reports.columns and reports["truth_id"].null_count() < reports.height:
        say("per-radar evaluation")
        extra.append(radar_metrics(reports, ref.radars, ref.truth if ref.truth is not None else ref.table, ref.frame))
    if extra:
        ev.metrics = pl.concat([ev.metrics, *extra], how="vertical_relaxed")
    return ev


def evaluate_run(tracks: list[Path], out: Path, *, truth: Path | None = None, dataset: Path | None = None,
                 reference: str = "truth", adsb: Path | None = None, requirements: Path | None = None,
                 force: bool = False, steps: Steps = no_steps) -> EvaluationRun:
    """Score the pictures in ``tracks`` against a reference (``truth`` file, or ``dataset`` with
    ``reference`` truth, reconstruct or adsb) and store everything in ``out``/results.duckdb."""
    ref = _reference(truth, dataset, reference, adsb)
    reqs = load_requirements(requirements or example_path())      # the same default as the main job's
    if out.exists() and (out / "results.duckdb").exists() and not force:
        raise OptionError(f"{out} already holds a run; choose another --out or add --force", option="--out")
    pictures = read_pictures(tracks)
    t = time.perf_counter()
    with steps("evaluate") as say:
        ev = _score(pictures, ref, reference, reqs, say)
        say("store")
        with RunStore.create(out) as store:
            store.write("tracks", pictures)
            store.write("truth", ref.table)
            store.write("metrics", ev.metrics)
            store.write("evaluation_matched", ev.matched.select(
                "run", "epoch", "method", "track_id", "truth_id", "match_cost"))
            if reqs is not None:
                store.write("requirements", ev.requirements)
            if ref.removed is not None:
                store.write("rejects", ref.removed.select(pl.lit("truth").alias("table"), "reason"))
            record_run(store, {"kind": "evaluation", "scenario": "evaluation", "notes": ref.notes,
                               "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                               "pictures": sorted(pictures["method"].unique().to_list()),
                               "tracks_files": [str(p) for p in tracks],
                               "reference": f"{truth or dataset} ({reference})",
                               "requirements": str(requirements or example_path()),
                               "status": "complete", "timings": {"wall_s": time.perf_counter() - t}})
    return EvaluationRun(ev, pictures, ref.table, out / "results.duckdb", time.perf_counter() - t, reqs is not None,
                         ref.notes)
