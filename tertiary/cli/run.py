"""``tertiary run`` (the batch job, resumable) and ``tertiary evaluate`` (external pictures): parse
the options, call the workflow of :mod:`tertiary.pipeline.workflows`, print its results."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Optional

import polars as pl
import typer

from tertiary.cli.common import (DEFAULT_FILTERS, DEFAULT_METHODS, DEFAULT_SCENARIO, AircraftOpt, BiasStepOpt,
                                 DropoutOpt, DurationOpt, LogFormatOpt, NoiseOpt, NoiseWinOpt, OriginOpt, OutliersOpt,
                                 QuietOpt, RadarsOpt, RequirementsOpt, RunsOpt, SeedOpt, Steps, TruthOpt, build_scenario, console,
                                 names, parse_origin, print_frame, print_note, set_log, window_option)
from tertiary.core.errors import OptionError
from tertiary.pipeline import PipelineConfig, check_config, check_tables
from tertiary.pipeline.workflows import Engine, evaluate_run, run_job
from tertiary.report.html import build_report
from tertiary.runtime.windows import AUTO_WINDOW
from tertiary.sensors.collection import CollectionConfig
from tertiary.stages.association.associate import AssociationConfig
from tertiary.stages.association.gating import GatingConfig
from tertiary.stages.fusion import ALL_METHODS
from tertiary.filters import REGISTRY
from tertiary.store.summary import run_summary


def run(
    dataset: Annotated[Optional[Path], typer.Argument(help="dataset directory [default: simulate --scenario]")] = None,
    scenario: Annotated[str, typer.Option(help="scenario simulated when no DATASET is given")] = DEFAULT_SCENARIO,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="run directory [default: runs/<scenario>, or "
                                                                     "runs/<scenario>-N when that holds a run]")] = None,
    force: Annotated[bool, typer.Option(help="replace a run already in --out")] = False,
    methods: Annotated[str, typer.Option(help="comma-separated fusion methods")] = DEFAULT_METHODS,
    filters: Annotated[str, typer.Option(help="comma-separated secondary tracker filters ('' for none); choose "
                                              f"from {', '.join(sorted(REGISTRY))}")] = DEFAULT_FILTERS,
    centralized: Annotated[bool, typer.Option(help="also run the centralised measurement-level reference")] = True,
    strict: Annotated[bool, typer.Option(help="stop (exit 3) on the first invalid input row")] = False,
    report: Annotated[bool, typer.Option("--report/--no-report",
                                         help="also write RUN_DIR/report.html (plotly, self-contained)")] = True,
    safety_picture: Annotated[str, typer.Option(help="picture conflict prediction runs on: tracks (the tracker's "
                                                     "confirmed tracks, per method+filter) or fused")] = "tracks",
    safety: Annotated[bool, typer.Option("--safety/--no-safety",
                                         help="predict conflicts and score alerts (--no-safety: the picture and its "
                                              "accuracy only)")] = True,
    origin: OriginOpt = None,
    runs: RunsOpt = None, seed: SeedOpt = None, aircraft: AircraftOpt = None, radars: RadarsOpt = None,
    duration: DurationOpt = None, truth: TruthOpt = None, noise_factor: NoiseOpt = None,
    noise_window: NoiseWinOpt = None, dropout: DropoutOpt = None, outliers: OutliersOpt = None,
    bias_step: BiasStepOpt = None,
    quiet: QuietOpt = False, log_format: LogFormatOpt = "text", requirements: RequirementsOpt = None,
    register: Annotated[bool, typer.Option("--register/--no-register",
                                           help="correct each radar's range/azimuth bias and clock offset before "
                                                "alignment: DATASET/registration.parquet (from `tertiary register`) "
                                                "when present, else estimated radar to radar")] = False,
    measure_downlinks: Annotated[bool, typer.Option(
        "--measure-downlinks/--no-measure-downlinks",
        help="the tracker weighs the downlinked ground velocity and vertical rate by their noise measured from "
             "the recording's replies, not the configured σ")] = False,
    indicators: Annotated[bool, typer.Option(help="also write the §1.7/§5.1 indicators of every tracker picture "
                                                  "(metrics stage 'indicators'; needs truth)")] = False,
    assignment: Annotated[str, typer.Option(help="association with >= 3 radars: pairwise (to the reference "
                                                 "radar) or joint (multi-dimensional minimum)")] = "pairwise",
    gate: Annotated[str, typer.Option(help="association gate: box, mahalanobis or bayes (minimum-error "
                                           "H1/H2 threshold)")] = "box",
    radar_health: Annotated[bool, typer.Option(help="also write each radar's health (windowed-NIS divergence "
                                                    "alarm, adaptive R; metrics stage 'radar_health')")] = False,
    collection: Annotated[Optional[str], typer.Option(help="report collection queue ahead of alignment (§1.4): "
                                                           "refusals, waiting or limited; lost reports go to "
                                                           "rejects [default: none]")] = None,
    service_time: Annotated[float, typer.Option(help="mean processing time of one report (s), with --collection")] = 0.01,
    service_model: Annotated[str, typer.Option(help="processing time: exponential or deterministic")] = "exponential",
    max_wait: Annotated[float, typer.Option(help="T_wait of --collection limited (s)")] = 0.1,
    range_channel: Annotated[Optional[str], typer.Option(help="recompute the radars' local tracks with this range "
                                                              "channel: singer, kinematic or kinematic_dynamic "
                                                              "(chapter 3, needs Mode S EHS report columns; Singer "
                                                              "for tracks without) [default: the dataset's "
                                                              "estimates]")] = None,
    range_variant: Annotated[str, typer.Option(help="(3.11)/(3.62) of --range-channel: corrected or printed")]
        = "corrected",
    window: Annotated[str, typer.Option("--window", metavar="SECONDS|auto",
                                        help="process the recording in time windows of this many seconds (>= 1; "
                                             "0: one window; auto: about 50 000 reports in the busiest window divided by "
                                             "the number of fusion methods, 60 s to 1 h, "
                                             "300 s with --engine dask), carrying every stage's state; each "
                                             "window is stored as it completes")]
        = AUTO_WINDOW,
    resume: Annotated[Optional[Path], typer.Option("--resume", help="continue the killed run in RUN_DIR from its "
                                                                    "last complete window (same options and "
                                                                    "dataset)")] = None,
    engine: Annotated[str, typer.Option(help="local (this process) or dask (dask.distributed: Monte-Carlo runs "
                                             "and, with --slice, time slices in parallel)")] = "local",
    workers: Annotated[Optional[int], typer.Option(help="--engine dask: workers of the LocalCluster "
                                                        "[default: one per core]")] = None,
    scheduler: Annotated[Optional[str], typer.Option(help="--engine dask: address of a running scheduler "
                                                          "(tcp://host:8786) instead of a LocalCluster")] = None,
    slice_s: Annotated[Optional[float], typer.Option("--slice", help="--engine dask: cut each run into time slices "
                                                                     "of this many seconds")] = None,
    overlap_s: Annotated[Optional[float], typer.Option("--overlap", help="--engine dask: warm-up before each slice "
                                                                         "(s, a multiple of --window; its outputs "
                                                                         "are discarded, ids stitched in it) "
                                                                         "[default: one window]")] = None,
    tables: Annotated[str, typer.Option("--tables", help="database: copy the streamed tables into "
                                                          "results.duckdb, the columns the report and the named "
                                                          "SQL read; parquet: the same columns kept as Parquet "
                                                          "in RUN_DIR/tables with views over them (long "
                                                          "recordings); full: every column (covariances, "
                                                          "innovations, model probabilities) copied in")
                  ] = "database",
) -> None:
    """The main job: (simulate,) validate, align, associate, fuse, cluster, track, predict conflicts,
    evaluate and store everything in RUN_DIR/results.duckdb, then write RUN_DIR/report.html.

    Scenario options (--runs ... --bias-step) apply when the job simulates (no DATASET)."""
    set_log(quiet, log_format)
    window_s = window_option(window, engine)
    _check_engine(engine, tables, out, resume, range_channel,
                  {"--workers": workers, "--scheduler": scheduler, "--slice": slice_s, "--overlap": overlap_s})
    if resume is not None:
        _check_resume(out, resume)
        out, force = resume, True
    cfg = PipelineConfig(methods=names(methods, ALL_METHODS, "--methods"),
                         filters=names(filters, sorted(REGISTRY), "--filters"),
                         centralized=centralized, strict=strict, safety=safety, safety_picture=safety_picture,
                         indicators=indicators, association=_association(assignment, gate),
                         radar_health=radar_health,
                         requirements_file=None if requirements is None else str(requirements))
    if measure_downlinks:
        cfg = dataclasses.replace(cfg, tracker=dataclasses.replace(cfg.tracker, calibrate_downlinks=True))
    if collection is not None:   # checked here, before any simulation
        cfg = dataclasses.replace(cfg, collection=CollectionConfig(collection, service_time, service_model, max_wait))
    if range_channel is not None:
        cfg = _local_range_channel(cfg, range_channel, range_variant)
    check_config(cfg)
    sim = dict(runs=runs, seed=seed, aircraft=aircraft, radars=radars, duration=duration, truth=truth,
               noise_factor=noise_factor, noise_window=noise_window, dropout=dropout, outliers=outliers,
               bias_step=bias_step)
    given = [k for k, v in sim.items() if v is not None]
    if dataset is not None and given:
        raise OptionError(f"--{given[0].replace('_', '-')} applies only when the job simulates; "
                          "omit DATASET or the option", option=f"--{given[0].replace('_', '-')}")
    scen = build_scenario(scenario, **sim) if dataset is None else None
    job = run_job(cfg, dataset=dataset, scenario=scen, out=out, force=force,
                  origin=parse_origin(origin) if dataset is not None else None,
                  engine=Engine(engine, window_s, resume is not None, workers, scheduler, slice_s, overlap_s, tables),
                  register=register, recompute_local_tracks=range_channel is not None, report=report,
                  steps=Steps, notify=print_note)
    print_summary(job.db, job.report)


def requirements_matrix(requirements: pl.DataFrame) -> pl.DataFrame:
    """One row per requirement, one column per picture, each cell its verdict (FAIL in capitals)."""
    mark = {"pass": "pass", "fail": "FAIL", "insufficient": "?"}
    cells = requirements.select("requirement", "method", pl.col("verdict").replace_strict(mark, default=pl.col("verdict")))
    return cells.pivot(on="method", index="requirement", values="verdict", maintain_order=True)


def _check_engine(engine: str, tables: str, out: Path | None, resume: Path | None, range_channel: str | None,
                  dask_options: dict[str, object]) -> None:
    """The --engine options that go together, checked before any simulation."""
    if engine not in ("local", "dask"):
        raise OptionError(f"choose local or dask, got {engine!r}", option="--engine")
    # before any simulation; the run directory, when not given, is made under this one
    check_tables(tables, out if out is not None else resume if resume is not None else Path.cwd())
    if engine == "local":
        for name, value in dask_options.items():
            if value is not None:
                raise OptionError("applies with --engine dask only", option=name)
    elif resume is not None:
        raise OptionError("a Dask run is not resumable; rerun it", option="--resume")
    elif range_channel is not None:
        raise OptionError("the Dask workers read the dataset's own estimates; use --engine local",
                          option="--range-channel")


def _check_resume(out: Path | None, resume: Path) -> None:
    """``--resume RUN_DIR``: a windowed run's directory, the same as --out when both are given."""
    if out is not None and out.resolve() != resume.resolve():
        raise OptionError("--resume names the run directory; omit --out or give the same directory",
                          option="--resume")
    if not (resume / "manifest.json").is_file():
        raise OptionError(f"{resume} holds no windowed run to resume (no manifest.json)", option="--resume")


def _local_range_channel(cfg: PipelineConfig, channel: str, variant: str) -> PipelineConfig:
    """``--range-channel``/``--range-variant`` into ``cfg.align.local_tracker`` (the reports' own
    estimates are then dropped, so alignment recomputes every local track with it)."""
    try:
        tracker = dataclasses.replace(cfg.align.local_tracker, range_channel=channel, range_variant=variant)
    except OptionError as exc:
        option = "--range-channel" if "channel" in str(exc) else "--range-variant"
        raise OptionError(str(exc).split(": ", 1)[-1], option=option) from exc
    return dataclasses.replace(cfg, align=dataclasses.replace(cfg.align, local_tracker=tracker))


def _association(assignment: str, gate: str) -> AssociationConfig:
    """The association options of ``tertiary run`` (--assignment, --gate)."""
    if assignment not in ("pairwise", "joint"):
        raise OptionError(f"choose pairwise or joint, got {assignment!r}", option="--assignment")
    if gate not in ("box", "mahalanobis", "bayes"):
        raise OptionError(f"choose box, mahalanobis or bayes, got {gate!r}", option="--gate")
    return AssociationConfig(assignment=assignment, gating=GatingConfig(method=gate))  # type: ignore[arg-type]


def print_summary(db: Path, html_path: Path | None) -> None:
    """The end-of-run summary (:func:`tertiary.store.summary.run_summary`) and where the results are."""
    for line in run_summary(db):
        console.print(line, soft_wrap=True)
    console.print(f"results: {db}", soft_wrap=True)
    if html_path is not None:
        console.print(f"report:  {html_path} ({html_path.stat().st_size / 1e6:.1f} MB)", soft_wrap=True)


def evaluate(
    tracks: Annotated[list[Path], typer.Argument(help="picture file(s): Parquet in the tracks schema (epoch, "
                                                       "track_id, x_m ... vz_mps in the reference's ENU frame); "
                                                       "several files give a comparison")],
    out: Annotated[Path, typer.Option("--out", "-o", help="run directory for results.duckdb and report.html")],
    truth: Annotated[Optional[Path], typer.Option(help="reference: Parquet in the truth schema (truth_id, time, "
                                                       "x_m ... vz_mps[, alt_m]) in the same frame")] = None,
    dataset: Annotated[Optional[Path], typer.Option(help="dataset directory whose truth.parquet is the reference "
                                                         "(its radars give the range rings)")] = None,
    requirements: RequirementsOpt = None,
    reference: Annotated[str, typer.Option(help="with --dataset: truth (the dataset's truth.parquet), "
                                                "reconstruct (smoothed offline from every radar plot; scored "
                                                "against the truth too when there is one) or adsb (the --adsb "
                                                "recording, quality-filtered)")] = "truth",
    adsb: Annotated[Optional[Path], typer.Option(help="ADS-B recording (OpenSky/traffic-schema Parquet) for "
                                                      "--reference adsb")] = None,
    force: Annotated[bool, typer.Option(help="replace a run already in --out")] = False,
    report: Annotated[bool, typer.Option("--report/--no-report", help="also write RUN_DIR/report.html")] = True,
) -> None:
    """Score pictures that tertiary did not produce (or did) against a reference: one geometric
    matching, the surveillance metrics (accuracy, along/across track, latency, update
    probability, continuity, false/split/merged tracks, identity) by altitude band, range ring
    and flight phase, and requirements with pass/fail."""
    if (truth is None) == (dataset is None):
        raise OptionError("give the reference with exactly one of --truth FILE or --dataset DIR", option="--truth")
    if reference not in ("truth", "reconstruct", "adsb"):
        raise OptionError(f"choose truth, reconstruct or adsb, got {reference!r}", option="--reference")
    if reference in ("reconstruct", "adsb") and dataset is None:
        raise OptionError(f"--reference {reference} needs --dataset DIR (its frame and radars)", option="--reference")
    if (reference == "adsb") != (adsb is not None):
        raise OptionError("--adsb FILE goes with --reference adsb", option="--adsb")
    res = evaluate_run(tracks, out, truth=truth, dataset=dataset, reference=reference, adsb=adsb,
                       requirements=requirements, force=force, steps=Steps)
    pictures, ev = res.pictures, res.evaluation
    console.print(f"evaluated {pictures['method'].n_unique()} picture(s), {pictures.height:,} track rows, "
                  f"against {res.reference['truth_id'].n_unique():,} reference aircraft in {res.wall_s:.1f} s")
    for note in res.notes:
        print_note(note)
    print_frame(ev.comparison, "Pictures compared (segment all)", 50)
    if res.with_requirements:
        print_frame(requirements_matrix(ev.requirements), "Requirements × pictures", 200)
        console.print("pass, FAIL or ? (too few samples); values: tertiary sql RUN_DIR requirements_verdicts",
                      soft_wrap=True)
    console.print(f"results: {res.db}", soft_wrap=True)
    if report:
        with Steps("report") as say:
            html = build_report(out, progress=say)
        console.print(f"report:  {html}", soft_wrap=True)
