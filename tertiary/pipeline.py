"""The batch job: dataset in, one DuckDB run database out.

Stages are composed here and nowhere else: ingest/validate → align → gate + associate → fuse
(every selected method, plus the centralised measurement-level bound) → cluster → secondary
trackers on every fusion method's picture → conflict prediction on every picture → evaluate
(accuracy, association, trackers, alerts against truth, capacity from the measured accuracy)
→ store. Every input report ends up in ``aligned`` or ``rejects`` (checked, not assumed).
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

import dataclasses


from typing import TYPE_CHECKING

from tertiary import schema
from tertiary.align import AlignConfig, align
from tertiary.associate import AssociationConfig, associate
from tertiary.centralized import CentralizedConfig, centralized_fusion
from tertiary.clustering import ClusteringConfig, cluster
from tertiary.evaluate import (EvaluateConfig, accuracy_by_epoch_from_matched, accuracy_from_matched,
                               association_metrics, match_truth, target_truth)
from tertiary.filters import REGISTRY
from tertiary.fusion import METHODS, FusionConfig, fuse
from tertiary.simulate import Dataset, scenario_toml
from tertiary.track_metrics import TrackMetricsConfig, tracker_metrics
from tertiary.tracker import TrackerConfig, track_methods
from tertiary.store import RunStore, record_run

if TYPE_CHECKING:  # `safety` builds on `tertiary`; at run time it is imported where it is used
    from safety.conflicts import ConflictConfig

Progress = Callable[[str], None]


def _default_conflict_config() -> "ConflictConfig":
    from safety.conflicts import ConflictConfig
    return ConflictConfig()


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


@dataclass(frozen=True)
class PipelineConfig:
    """Configuration of every stage (each stage's own frozen dataclass)."""

    methods: tuple[str, ...] = METHODS
    filters: tuple[str, ...] = ("singer", "imm_sym")
    centralized: bool = True
    strict: bool = False
    align: AlignConfig = field(default_factory=AlignConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    centralized_cfg: CentralizedConfig = field(default_factory=CentralizedConfig)
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    safety: bool = True
    conflicts: ConflictConfig = field(default_factory=_default_conflict_config)
    evaluate: EvaluateConfig = field(default_factory=EvaluateConfig)
    track_metrics: TrackMetricsConfig = field(default_factory=TrackMetricsConfig)


@dataclass
class Results:
    """Every table of a run (also written to ``results.duckdb``)."""

    ingested: Ingested
    aligned: pl.DataFrame
    associations: pl.DataFrame
    fused: pl.DataFrame
    clusters: pl.DataFrame
    tracks: pl.DataFrame
    conflicts: pl.DataFrame
    rejects: pl.DataFrame
    metrics: pl.DataFrame
    accuracy_by_epoch: pl.DataFrame
    timings: dict[str, float]
    counts: dict[str, int]


class _Clock:
    def __init__(self, say: Progress):
        self.say, self.timings, self._t = say, {}, time.perf_counter()
        self._name: str | None = None

    def stage(self, name: str | None) -> None:
        now = time.perf_counter()
        if self._name is not None:
            self.timings[f"{self._name}_s"] = now - self._t
        self._name, self._t = name, now
        if name:
            self.say(name)


def process(ds: Dataset, cfg: PipelineConfig | None = None, progress: Progress | None = None) -> Results:
    """Run every stage in memory and return the tables (``cfg`` None = the defaults)."""
    cfg = cfg or PipelineConfig()
    unknown = set(cfg.methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown fusion method(s) {sorted(unknown)}; choose from {', '.join(METHODS)}")
    bad = set(cfg.filters) - set(REGISTRY)
    if bad:
        raise ValueError(f"unknown filter(s) {sorted(bad)}; choose from {', '.join(sorted(REGISTRY))}")
    clock = _Clock(progress or (lambda _m: None))
    t_all = time.perf_counter()
    clock.stage("validate")
    ing = ingest(ds, strict=cfg.strict)
    clock.stage("align")
    aligned, align_rejects = align(ing.reports, ing.radars, ds.origin, cfg.align)
    rejects = pl.concat([ing.rejects, _stage_rejects(align_rejects, ing.reports, "align")], how="vertical_relaxed")
    _check_accounting(ds.reports.height, aligned, rejects)
    clock.stage("associate")
    associations, stats = associate(aligned, cfg.association)
    clock.stage("fuse")
    rows = aligned.with_columns(associations["target_id"]).sort("run", "epoch", "target_id", "radar_id")
    fused = fuse(rows, ing.radars, cfg.methods, cfg.fusion) if cfg.methods else schema.empty_frame("fused", False)
    if cfg.centralized:
        clock.stage("centralized")
        keys = rows.select("run", "epoch", "target_id").unique(maintain_order=True)
        central = centralized_fusion(ing.reports, ing.radars, associations, keys, ds.origin, cfg.centralized_cfg)
        fused = pl.concat([fused, central.select(fused.columns)], how="vertical")
    clock.stage("cluster")
    clusters = cluster(fused, cfg.clustering)
    clock.stage("track")
    pictures = fused.filter(pl.col("method") != "centralized")
    tracks = (track_methods(pictures, cfg.filters, cfg.tracker) if cfg.filters and pictures.height
              else schema.empty_frame("tracks", False))
    # imported here: `safety` builds on `tertiary` (schema), so a module-level import would be
    # circular when a program imports `safety` first
    from safety import AlertConfig, capacity_from_metrics, predict_conflicts, score_alerts

    conflicts = schema.empty_frame("conflicts", False)
    if cfg.safety:
        clock.stage("conflicts")
        conflicts = predict_conflicts(fused, cfg.conflicts, id_col="target_id")
    clock.stage("evaluate")
    metrics, by_epoch = _evaluate(ing, associations, fused, stats, cfg.evaluate)
    if ing.truth.height and "truth_id" in ing.reports.columns:
        report_truth = ing.reports.select("run", "report_id", "truth_id")
        extra = []
        if cfg.filters and tracks.height:
            extra.append(tracker_metrics(tracks, associations, report_truth, ing.truth, cfg.track_metrics))
        if cfg.safety:
            id_map = target_truth(associations, report_truth)
            extra.append(score_alerts(conflicts, id_map, ing.truth, AlertConfig(conflict=cfg.conflicts),
                                      id_col="target_id", methods=sorted(fused["method"].unique().to_list())))
        metrics = pl.concat([metrics, *extra], how="vertical_relaxed")
        if cfg.safety:
            metrics = pl.concat([metrics, capacity_from_metrics(metrics)], how="vertical_relaxed")
    clock.stage(None)
    clock.timings["alignment_to_clustering_s"] = sum(
        clock.timings.get(f"{k}_s", 0.0) for k in ("align", "associate", "fuse", "centralized", "cluster"))
    clock.timings["total_s"] = time.perf_counter() - t_all
    counts = {"reports_in": ds.reports.height, "reports_aligned": int(aligned["report_id"].n_unique()),
              "reports_rejected": int(rejects.filter(pl.col("input_table") == "reports").height),
              "aligned_rows": aligned.height, "gated_pairs": stats.pairs, "components": stats.components,
              "ambiguous_components": stats.ambiguous_components, "targets": stats.targets,
              "reassignments": stats.reassignments, "fused_rows": fused.height, "clusters": clusters.height,
              "track_rows": tracks.height, "conflict_rows": conflicts.height,
              "alerts": int(conflicts["alert"].sum()) if conflicts.height else 0}
    return Results(ing, aligned, associations, fused, clusters, tracks, conflicts, rejects, metrics, by_epoch,
                   clock.timings, counts)


def _stage_rejects(stage_rejects: pl.DataFrame, reports: pl.DataFrame, stage: str) -> pl.DataFrame:
    """A stage's (report_id, reason) rejects in the canonical ``rejects`` schema."""
    if stage_rejects.height == 0:
        return schema.empty_frame("rejects", False)
    rows = reports.with_row_index("row_index").join(stage_rejects, on="report_id", how="inner")
    packed = schema.rejects_table(rows.with_columns(pl.col("row_index").cast(pl.UInt64)), "reports", stage)
    return packed


def _check_accounting(n_in: int, aligned: pl.DataFrame, rejects: pl.DataFrame) -> None:
    n_ok = aligned["report_id"].n_unique()
    n_rej = rejects.filter(pl.col("input_table") == "reports").height
    if n_ok + n_rej != n_in:
        raise RuntimeError(f"row accounting broken: {n_in} reports in, {n_ok} aligned + {n_rej} rejected")


def _evaluate(ing: Ingested, associations: pl.DataFrame, fused: pl.DataFrame, stats,
              cfg: EvaluateConfig) -> tuple[pl.DataFrame, pl.DataFrame]:
    counts = pl.DataFrame({
        "stage": "association", "method": "assignment",
        "metric": ["gated_pairs", "ambiguous_components", "targets", "reassignments"],
        "segment": "all", "value": [float(stats.pairs), float(stats.ambiguous_components), float(stats.targets),
                                    float(stats.reassignments)],
        "n_runs": int(associations["run"].n_unique()) if associations.height else 0,
    }).with_columns(pl.col("n_runs").cast(pl.UInt32))
    if ing.truth.height == 0 or "truth_id" not in ing.reports.columns:
        return counts, pl.DataFrame()
    report_truth = ing.reports.select("run", "report_id", "truth_id")
    matched = match_truth(fused, associations, report_truth, ing.truth, cfg, keep_cov=False)
    metrics = pl.concat([accuracy_from_matched(matched, cfg), association_metrics(associations, report_truth)],
                        how="vertical")
    by_epoch = accuracy_by_epoch_from_matched(matched, cfg)
    return pl.concat([metrics, counts.select(metrics.columns)], how="vertical_relaxed"), by_epoch


def run(ds: Dataset, out_dir: str | Path, cfg: PipelineConfig | None = None, *,
        progress: Progress | None = None) -> Path:
    """Run the job on a dataset and write ``out_dir/results.duckdb`` atomically."""
    cfg = cfg or PipelineConfig()
    say = progress or (lambda _m: None)
    res = process(ds, cfg, say)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say("store")
    t = time.perf_counter()
    with RunStore.create(out) as store:
        for name in ("radars", "reports", "truth"):
            frame = getattr(res.ingested, name)
            if frame.height:
                store.write(name, frame)
        for name in ("aligned", "associations", "fused", "clusters", "tracks", "conflicts", "rejects", "metrics",
                     "accuracy_by_epoch"):
            frame = getattr(res, name)
            if frame.width:
                store.write(name, frame)
        if ds.removed.height:
            store.write("truth_removed", ds.removed)
        res.timings["store_s"] = time.perf_counter() - t
        record_run(store, {
            "scenario": ds.scenario.name,
            "scenario_toml": scenario_toml(ds.scenario),
            "config": _config_dict(cfg),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "versions": _versions(),
            "fingerprints": {k: fingerprint(getattr(ds, k)) for k in ("radars", "reports", "truth")},
            "rows": res.counts,
            "notes": res.ingested.notes,
            "timings": res.timings,
        })
    return out / "results.duckdb"


def _config_dict(cfg: PipelineConfig) -> dict:
    def conv(v):
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v
    return conv(cfg)


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
