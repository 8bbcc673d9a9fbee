"""What the whole-run evaluation scores: every picture against the truth (:func:`score_pictures`),
the aircraft continuity expects covered (:func:`observed_aircraft`) and the association metrics
of rows read back a block at a time (:func:`scored_blocks`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from safety import alerts as safety_alerts
from tertiary.contract import TIME
from tertiary.evaluation import sketch
from tertiary.evaluation.accuracy import BY_EPOCH_SCHEMA, AccuracyConfig, empty_metrics, scored_samples
from tertiary.evaluation.accuracy_streamed import seed_tables, statistic_lags, with_epoch_sums
from tertiary.evaluation.association import AssociationScore, score_associations
from tertiary.evaluation.consistency import Lags
from tertiary.evaluation.evaluate import Evaluation, Matched, evaluate_each, scan_spilled
from tertiary.evaluation.lags_streamed import SERIES_KEYS, LagState
from tertiary.evaluation.matched_apart import PictureFiles
from tertiary.evaluation.multitarget import multitarget_results
from tertiary.evaluation.picture_metrics import MetricsConfig
from tertiary.evaluation.picture_streamed import picture_metrics_finish
from tertiary.evaluation.streamed import ID_ROWS, PICTURE_VALUES, SCORED, MatchState, expected_table, matched_table
from tertiary.evaluation.requirements import Requirements, example_path, load_requirements
from tertiary.io.dataset import Dataset
from tertiary.pipeline.config import PipelineConfig
from tertiary.pipeline.ingestion import Ingested
from tertiary.pipeline.pictures import (NOT_SCORED, as_picture, confirmed_only, fused_readers, safety_names,
                                       track_readers)
from tertiary.pipeline.tables import ASSOCIATION_COLUMNS, EVAL_BLOCK_ROWS, OnDiskTable
from tertiary.runtime.fanout import Fanout
from tertiary.runtime.windows import read_part_groups, release_memory
from tertiary.stages.association.associate import AssociationStats

__all__ = ["OBSERVED_BLOCK_ROWS", "ASSOCIATION_BLOCK_ROWS", "AlignedFacts", "DistinctIds", "aligned_facts",
           "association_blocks", "distinct_targets",
           "association_stage_metrics", "observed_aircraft", "report_truth", "score_pictures", "scored_blocks",
           "WindowedPictures"]


#: the columns of a picture's scored samples (:func:`~tertiary.evaluation.accuracy.scored_samples`)
SAMPLE_SCHEMA = {"method": pl.String, "run": pl.UInt32, "epoch": TIME, "truth_id": pl.Int64, "seg_class": pl.String}

#: aligned rows joined to their reports' aircraft at a time (:func:`observed_aircraft`)
OBSERVED_BLOCK_ROWS = 262_144


def report_truth(truth_of: pl.DataFrame) -> Callable[[pl.DataFrame], pl.Series] | None:
    """A lookup of the ``truth_id`` of each (run, report_id) of a frame in ``truth_of`` (one row
    per report; null where absent), through a table indexed by run × (largest report_id + 1) +
    report_id; None when the ids are too sparse for it (the table would be over four times the
    reports). A join of each block of aligned rows with every report rebuilt its hash table a
    block at a time."""
    if truth_of.height == 0 or truth_of["run"].null_count() or truth_of["report_id"].null_count():
        return None
    top, runs = int(truth_of["report_id"].max()) + 1, int(truth_of["run"].max()) + 1
    if top * runs > 4 * truth_of.height + (1 << 20):
        return None
    key = truth_of["run"].cast(pl.UInt64).to_numpy() * top + truth_of["report_id"].cast(pl.UInt64).to_numpy()
    tid = truth_of["truth_id"]
    known = tid.is_not_null().to_numpy()
    table, have = np.zeros(top * runs, np.int64), np.zeros(top * runs, np.bool_)
    table[key[known]] = tid.fill_null(0).cast(pl.Int64).to_numpy()[known]
    have[key[known]] = True

    def lookup(frame: pl.DataFrame) -> pl.Series:
        run, rid = (frame[c].cast(pl.UInt64).fill_null(np.iinfo(np.uint64).max).to_numpy()
                    for c in ("run", "report_id"))
        inside = (run < runs) & (rid < top)
        k = np.where(inside, run * top + np.where(inside, rid, 0), 0)
        found = pl.Series(inside & have[k])
        return pl.select(pl.when(found).then(pl.Series(table[k])).cast(tid.dtype).alias("truth_id")).to_series()
    return lookup


#: association rows scored at a time when read back (:func:`scored_blocks`)
ASSOCIATION_BLOCK_ROWS = 2_000_000


def association_blocks(parts) -> Iterator[pl.DataFrame]:
    """The association rows of ``parts``' windows (what the metrics read), in window order."""
    for f in parts.iter_parts("associations"):
        yield f.select(c for c in ASSOCIATION_COLUMNS if c in f.columns)


def scored_blocks(blocks: Iterable[pl.DataFrame], reports: pl.DataFrame) -> AssociationScore:
    """:class:`AssociationScore` of association rows given as frames of whole epochs in time order
    (each run's), gathered to about :data:`ASSOCIATION_BLOCK_ROWS` rows and each scored with its
    reports' aircraft (:func:`report_truth`): a run's rows read back are never held, nor joined,
    whole (a long run's rows and reports joined at once would not fit memory); a step per block
    is what the local engine does per window, so the metrics are the same."""
    truth_of = reports.select("run", "report_id", "truth_id")
    look = report_truth(truth_of)
    state = AssociationScore()

    def step(frames: list[pl.DataFrame]) -> None:
        nonlocal state
        block = pl.concat(frames, how="vertical_relaxed")
        label = (block.select("run", "report_id").with_columns(look(block)) if look is not None
                 else truth_of)
        state = score_associations(state, block, label)
    pending, rows = [], 0
    for frame in blocks:
        if frame.height:
            pending.append(frame)
            rows += frame.height
        if rows >= ASSOCIATION_BLOCK_ROWS:
            step(pending)
            pending, rows = [], 0
    if pending:
        step(pending)
    return state


def observed_aircraft(aligned: pl.DataFrame, reports: pl.DataFrame) -> pl.DataFrame:
    """(run, epoch, truth_id) of every aircraft with a report aligned at the epoch: what
    continuity expects covered. Joined a block of aligned rows at a time: a long run's join is
    not held whole (memory)."""
    keys = aligned.select("run", "epoch", "report_id")
    if "truth_id" not in reports.columns:        # a recording without truth: nobody to expect
        return keys.select("run", "epoch").with_columns(pl.lit(None, pl.Int64).alias("truth_id")).clear()
    truth_of = reports.select("run", "report_id", "truth_id")
    look = report_truth(truth_of)

    def aircraft(block: pl.DataFrame) -> pl.DataFrame:
        if look is not None:
            return block.with_columns(look(block))
        return block.join(truth_of, on=["run", "report_id"], how="left")
    blocks = [aircraft(keys.slice(k, OBSERVED_BLOCK_ROWS)).select("run", "epoch", "truth_id").drop_nulls().unique()
              for k in range(0, keys.height, OBSERVED_BLOCK_ROWS)]
    if not blocks:
        none = pl.lit(None, truth_of.schema["truth_id"]).alias("truth_id")
        return keys.select("run", "epoch").with_columns(none).clear()
    return pl.concat(blocks).unique()


@dataclass(frozen=True)
class AlignedFacts:
    """What the whole-run stages take of the aligned rows: their number, the distinct reports
    among them (the row accounting) and :func:`observed_aircraft` (None: the rows carry no
    ``truth_id``, so it needs the reports)."""

    rows: int
    reports: int
    observed: pl.DataFrame | None


class DistinctIds:
    """How many distinct values of a non-negative integer id were added, a frame at a time: a
    bitmap over the id space (a day's 35 M report ids in 35 MB, where a hash set of them is GBs),
    or the frames' unique values when the ids are negative or too sparse for it."""

    #: id space the bitmap may span beyond eight per id added (sparse ids fall back to values)
    SLACK = 1 << 24

    def __init__(self) -> None:
        self.seen: np.ndarray | None = np.zeros(0, np.bool_)
        self.values: list[pl.Series] = []
        self.added, self.null = 0, False

    def add(self, ids: pl.Series) -> None:
        self.null |= ids.null_count() > 0
        ids = ids.drop_nulls()
        self.added += ids.len()
        if self.seen is not None and ids.len():
            top, low = ids.max(), ids.min()
            if low < 0 or top >= 8 * self.added + self.SLACK:
                self.values.append(pl.Series(np.flatnonzero(self.seen)).cast(ids.dtype))
                self.seen = None
            else:
                if top >= self.seen.size:
                    self.seen = np.concatenate([self.seen, np.zeros(max(top + 1, 2 * self.seen.size) - self.seen.size,
                                                                    np.bool_)])
                self.seen[ids.cast(pl.Int64).to_numpy()] = True
                return
        if ids.len():
            self.values.append(ids.unique())

    def count(self) -> int:
        """The distinct values added (a null counted as one, as ``n_unique``)."""
        if self.seen is not None:
            return int(np.count_nonzero(self.seen)) + self.null
        return (pl.concat(self.values).n_unique() if self.values else 0) + self.null


def aligned_facts(files: Sequence[Path]) -> AlignedFacts:
    """:class:`AlignedFacts` of the aligned rows in ``files`` (a run's window parts), read a group
    of parts at a time (:func:`read_part_groups`): neither the aligned rows nor the reports are
    held whole (memory: a day's are several GB), and the distinct reports are counted in a
    bitmap (:class:`DistinctIds`). Each aligned row carries its report's ``truth_id``; when each
    group's epochs follow the previous group's (a run's windows), each group's observed
    aircraft are its own and are not made unique again over the run (a hash of every
    aircraft-epoch)."""
    rows, ids, seen, schema, last, ordered = 0, DistinctIds(), [], None, None, True
    for part in read_part_groups(list(files), ["run", "epoch", "report_id", "truth_id"]):
        if part.height == 0:
            continue
        rows += part.height
        ids.add(part["report_id"])
        first = part["epoch"].min()
        ordered &= last is None or first is None or first > last
        last = part["epoch"].max() if last is None else max(last, part["epoch"].max())
        if "truth_id" not in part.columns:
            schema = False
        elif schema is not False:
            keys = part.select("run", "epoch", "truth_id")
            schema = keys.schema
            seen.append(keys.drop_nulls().unique())
    if not schema:
        return AlignedFacts(rows, ids.count(), None)
    if not seen:
        return AlignedFacts(rows, ids.count(), pl.DataFrame(schema=schema))
    observed = pl.concat(seen)
    return AlignedFacts(rows, ids.count(), observed if ordered else observed.unique())


def distinct_targets(files: Sequence[Path]) -> tuple[int, int]:
    """(association rows, distinct (run, target_id)) of the association parts ``files``, read a
    group of parts at a time (:func:`read_part_groups`) and counted in a bitmap per run
    (:class:`DistinctIds`): a day's 67 M rows' keys made unique at once peak at 4 GB."""
    rows, per_run = 0, {}
    for part in read_part_groups(list(files), ["run", "target_id"]):
        rows += part.height
        for (run,), keys in part.partition_by("run", as_dict=True).items():
            per_run.setdefault(run, DistinctIds()).add(keys["target_id"])
    return rows, sum(ids.count() for ids in per_run.values())


class WindowedPictures:
    """The pictures as the windows matched them (the evaluation's window stage), by name
    (:meth:`__call__`); every picture's scored rows read once, when a first picture's seed
    metrics are finished (:meth:`scored`). ``samples`` False: the scored samples are not read
    back (the bound, their only reader, was made in the windows); each picture's are empty.
    ``lags``: the lag sums the windows made of the series they retired (complete, else unused)."""

    def __init__(self, parts: Any, state: MatchState, surveillance: bool, samples: bool = True,
                 lags: LagState | None = None, id_rows: str | None = None) -> None:
        self.parts, self.state, self.surveillance, self.samples = parts, state, surveillance, samples
        self.id_rows = id_rows
        self.lags = lags if lags is not None and lags.complete else None
        self._finished: pl.DataFrame | None = None
        self._seeded: dict[AccuracyConfig, tuple[dict, dict]] = {}
        # the pictures of a group share its part files: each file's schema is read once
        self._schemas: dict[Path, pl.Schema] = {}

    def __call__(self, name: str) -> Matched | None:
        """Picture ``name``: scans of its rows of the matched and expected parts of the groups it
        was written in, its OSPA, GOSPA and SIAP rows from the carried state when
        ``surveillance``, its seed metrics from the carried state; None when no window had a row
        of it."""
        state = self.state
        groups = state.groups.get(name, ())
        files = [f for g in groups for f in self.parts.part_files(matched_table(g))]
        if not files:
            return None
        expected = [f for g in groups for f in self.parts.part_files(expected_table(g))]
        mine = pl.col("method") == name
        mt = state.pictures.get(name)
        seed = None if state.walk is None else functools.partial(self._seed_tables, name)
        stepped = getattr(state, "metrics", None)
        surveyed = (functools.partial(self._surveyed, name) if self.surveillance and stepped is not None
                    and stepped.tracks is not None else None)
        return Matched(scan_spilled(files, self._schemas).filter(mine),
                       scan_spilled(expected, self._schemas).filter(mine).drop("method") if expected else None,
                       self._multitarget.get(name) if self.surveillance and mt is not None else None, seed,
                       surveyed, self._ids(name, groups))

    @functools.cached_property
    def _multitarget(self) -> dict[str, pl.DataFrame]:
        """Every picture's OSPA, GOSPA and SIAP rows from the carried state, finished at once."""
        return multitarget_results(self.state.pictures)

    def _ids(self, name: str, groups: Sequence[str]) -> pl.LazyFrame | None:
        """Picture ``name``'s id map as the windows reduced it (None: not reduced there, or not a
        picture of the safety id column ``id_rows``)."""
        files = self.parts.part_files(ID_ROWS) if self.id_rows is not None else []
        if not files or not all(g.startswith(f"{self.id_rows}-") for g in groups):
            return None
        return scan_spilled(files, self._schemas).filter(pl.col("method") == name)

    def id_map(self, names: Sequence[str], keys: pl.DataFrame, id_col: str) -> pl.DataFrame | None:
        """The id map :func:`evaluate_each` gives of pictures ``names`` (those with a row) with the
        rows of the alert ``keys`` (:func:`safety.alerts.id_rows`), from the blocks the windows
        reduced, in one pass over them; None when they reduced no block of ``id_col``'s pictures."""
        if self.id_rows != id_col:
            return None
        scored = []
        for name in names:
            groups = self.state.groups.get(name, ())
            if not any(self.parts.part_files(matched_table(g)) for g in groups):
                continue            # no row: not a picture the evaluation scores
            if self._ids(name, groups) is None:
                return None
            scored.append(name)
        if not scored:
            return pl.DataFrame()
        blocks = scan_spilled(self.parts.part_files(ID_ROWS), self._schemas).filter(pl.col("method").is_in(scored))
        # id_rows works picture by picture (its keys hold the method): the pictures then in the
        # evaluation's order, each one's rows in theirs
        got = safety_alerts.id_rows(blocks, keys=keys, id_col=id_col).collect()
        order = pl.col("method").replace_strict(scored, range(len(scored)), return_dtype=pl.UInt32)
        return got.sort(order, maintain_order=True)

    def _surveyed(self, name: str, radar_xy: np.ndarray | None, breakdown: Sequence[str], cfg: MetricsConfig
                  ) -> pl.DataFrame:
        """Picture ``name``'s surveillance metrics, every picture's finished once from the carried state."""
        if self._finished is None:
            stepped = self.state.metrics
            files = self.parts.part_files(PICTURE_VALUES)
            if files:           # the sketch counts each window wrote, added up as they are read
                scan = scan_spilled(files)
                keys = [c for c in scan.collect_schema().names() if c != sketch.COUNT]
                counts = scan.group_by(keys).agg(pl.col(sketch.COUNT).sum()).collect(engine="streaming")
                values = [*stepped.sums.get("values", []), counts]
                stepped = replace(stepped, sums={**stepped.sums, "values": values})
            self._finished = picture_metrics_finish(stepped, radar_xy, breakdown, cfg)
        got = self._finished
        return got.filter(pl.col("method") == name) if got.height else got

    @functools.cached_property
    def scored(self) -> tuple[dict[tuple[str, str, str], Lags], dict[str, pl.DataFrame]]:
        """(τ's lag sums of every picture, each picture's scored samples) from the windows'
        scored rows, in one pass: a bucket of whole tracks at a time for the lag sums."""
        files = self.parts.part_files(SCORED)
        if not files:
            return {}, {}
        scan = scan_spilled(files)
        # the series the windows summed are left out, their sums added
        carried = None if self.lags is None else self.lags.sums.lags
        rest = scan if self.lags is None else scan.join(self.lags.retired.lazy(), on=SERIES_KEYS, how="anti")
        lags = statistic_lags(rest, rest.select(pl.len()).collect(engine="streaming").item(), carried)
        if not self.samples:
            return lags, {}
        # the two names categorical as they are read: a long run's samples are held to the end
        samples = scored_samples(scan.select(list(SAMPLE_SCHEMA))).collect()
        return lags, {str(name): part for (name,), part in
                      samples.partition_by("method", as_dict=True, maintain_order=True).items()}

    def _epoch_sums(self, table: str) -> pl.DataFrame | None:
        """Every window's rows of a per-epoch sums table (:data:`EPOCH_SUMS`)."""
        files = self.parts.part_files(table)
        return scan_spilled(files).collect() if files else None

    def _seed_tables(self, name: str, stage: str, cfg: AccuracyConfig
                     ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
        """Picture ``name``'s seed metrics (labelled ``stage``), per-epoch accuracy and scored
        samples finished: every picture's at once, the first time one is asked for."""
        lags, samples = self.scored
        if cfg not in self._seeded:
            seed = with_epoch_sums(self.state.seed, self._epoch_sums, getattr(self.state, "runs_apart", False))
            metrics, by_epoch = seed_tables(seed, self.state.walk, stage, cfg, lags)
            self._seeded[cfg] = (metrics.partition_by("method", as_dict=True),
                                 by_epoch.partition_by("method", as_dict=True))
        metrics, by_epoch = self._seeded[cfg]
        mine = samples.get(name)
        seeded = metrics.get((name,))
        return (empty_metrics() if seeded is None else seeded.with_columns(pl.lit(stage).alias("stage")),
                by_epoch.get((name,), pl.DataFrame(schema=BY_EPOCH_SCHEMA)),
                mine if mine is not None else scored_samples(pl.DataFrame(schema=SAMPLE_SCHEMA)))


def run_requirements(cfg: PipelineConfig) -> Requirements:
    """The requirements a run is judged against (``cfg.requirements_file``, else the shipped
    example), read and checked."""
    return load_requirements(cfg.requirements_file or example_path())


def score_pictures(cfg: PipelineConfig, fused: "pl.DataFrame | OnDiskTable", tracks: "pl.DataFrame | OnDiskTable",
                   observed: pl.DataFrame, reference: "pl.DataFrame | Path", ing: Ingested, ds: Dataset,
                   spill: Path | None = None, alert_keys: pl.DataFrame | None = None,
                   matched: Callable[[str], Matched | None] | None = None,
                   requirements: Requirements | None = None, id_maps: bool = True,
                   fanout: Fanout | None = None) -> tuple[Evaluation, Evaluation]:
    """Every picture scored by the one evaluation stage against the truth: each fusion method's
    confirmed targets and the centralised reference (seed stage "fusion", id ``target_id``),
    each tracker picture "<fusion>+<filter>" (seed stage "tracker"). Continuity expects every
    aircraft covered at the epochs it had a report (``observed``). Pictures are read one at a
    time; ``reference``: the truth, or its reference file (:func:`write_reference`); ``spill``: a
    scratch directory where a picture of several blocks is matched to disk and scored in
    buckets (:func:`tertiary.evaluation.evaluate.evaluate_each`). ``alert_keys``: the ids of
    every alert the safety picture's scoring will read (:func:`safety.alerts.alert_ids`): its id
    map keeps only their rows and a row per epoch (:func:`safety.alerts.id_rows`). ``id_maps``
    False: no picture's id map (the alerts are scored from the windows' own, :meth:`WindowedPictures.id_map`).
    ``fanout``: where the stretches of a picture on disk that no window matched are matched
    (:class:`~tertiary.evaluation.matched_apart.PictureFiles`)."""
    reqs = (requirements if requirements is not None else run_requirements(cfg)) if cfg.evaluation else None
    kw = dict(radars=ing.radars, frame=ds.origin, requirements=reqs, cfg=cfg.scoring, observed=observed,
              keep_matched=False, surveillance=cfg.evaluation, spill=spill)
    none = Evaluation(pl.DataFrame(), pl.DataFrame(), pl.DataFrame(), pl.DataFrame())
    # the id map of the safety picture only: the alert scoring reads no other (memory)
    safety_ids = safety_names(cfg, fused, tracks)[1] if cfg.safety and id_maps else None

    def id_map(col: str) -> "bool | Callable[[pl.LazyFrame], pl.LazyFrame]":
        if safety_ids != col or alert_keys is None:
            return safety_ids == col
        return functools.partial(safety_alerts.id_rows, keys=alert_keys, id_col=col)
    if matched is not None and isinstance(fused, OnDiskTable) and isinstance(tracks, OnDiskTable):
        # matched as the windows made them: the pictures are only reduced to metrics here
        fused_pictures = [functools.partial(matched, key[0]) for key in fused.shown]
        track_pictures = [functools.partial(matched, f"{m}+{f}") for m, f in tracks.pictures]
    elif fanout is not None and isinstance(fused, OnDiskTable) and isinstance(tracks, OnDiskTable):
        def files(table: OnDiskTable, key: tuple, name: str, shape: Callable) -> PictureFiles:
            return PictureFiles(name, *table.picture_files(key, NOT_SCORED), shape, EVAL_BLOCK_ROWS, fanout)
        fused_pictures = [functools.partial(files, fused, key, key[0], confirmed_only) for key in fused.shown]
        track_pictures = [functools.partial(files, tracks, (m, f), f"{m}+{f}", as_picture) for m, f in tracks.pictures]
    else:
        fused_pictures = list(fused_readers(fused, NOT_SCORED, blocks=True))
        track_pictures = list(track_readers(tracks, NOT_SCORED, blocks=True))

    def each(readers: list) -> Iterator:
        # the heap the last picture freed is handed back before the next is read (memory); a
        # picture the windows matched is only finished here, from their state: nothing to hand back
        got = (get() for get in readers) if matched is not None else (_released(get) for get in readers)
        return (p for p in got if p is not None)
    ev_fused = (evaluate_each(each(fused_pictures), reference, id_col="target_id", seed_stage="fusion",
                              id_map=id_map("target_id"), **kw)
                if fused_pictures else none)
    if not track_pictures:
        return ev_fused, none
    return ev_fused, evaluate_each(each(track_pictures), reference, seed_stage="tracker", id_map=id_map("track_id"),
                                   **kw)


def _released(get: Callable[[], Any]) -> Any:
    """``get()`` after the heap's freed pages are handed back."""
    release_memory()
    return get()


def association_stage_metrics(n_runs: int, stats: AssociationStats, scored: pl.DataFrame | None) -> pl.DataFrame:
    """The association stage's counts over ``n_runs`` runs, after its correctness rows
    (``scored``: :func:`tertiary.evaluation.evaluate.association_metrics`) when the run has truth labels."""
    counts = pl.DataFrame({
        "stage": "association", "method": "assignment",
        "metric": ["gated_pairs", "ambiguous_components", "targets", "reassignments"],
        "segment": "all", "value": [float(stats.pairs), float(stats.ambiguous_components), float(stats.targets),
                                    float(stats.reassignments)],
        "n_runs": n_runs,
    }).with_columns(pl.col("n_runs").cast(pl.UInt32))
    if scored is None:
        return counts
    return pl.concat([scored, counts], how="vertical_relaxed")
