"""One evaluation stage for any air picture: match once, score with the metrics
surveillance engineers use, judge against requirements.

    tracks (any picture, ``tracks`` schema) + reference (truth / ADS-B / reconstructed)
        → :func:`tertiary.evaluation.matching.match_to_reference`   (one geometric matcher, documented rule)
        → :func:`tertiary.evaluation.picture_metrics.picture_metrics` (stage ``evaluation``, per picture)
        → :func:`tertiary.evaluation.accuracy.picture_accuracy`     (the seed metrics: (2.15) accuracy,
                                                         NEES/NIS, continuity; stage ``fusion``,
                                                         ``tracker`` … as the caller names it)
        → :func:`tertiary.evaluation.requirements.check_requirements` (the ``requirements`` table)

It scores pictures ``tertiary`` did not produce exactly as its own: ``tertiary evaluate`` on
Parquet or CAT062 files, the pipeline on every fused picture, the centralised reference and
every tracker picture. The matcher's ``gated_truth_id`` is also the identity map alert scoring
uses (:attr:`Evaluation.id_map`). Several pictures in one call give one comparison table
(:func:`comparison`).

The association stage is the one thing judged by report labels, not by this matcher: whether
each *report* was put with its aircraft (:mod:`tertiary.evaluation.association`) is a property of reports,
not of a picture's states.
"""

from __future__ import annotations

import itertools
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path

import numpy as np
import polars as pl

from tertiary.core import geo
from tertiary.evaluation.accuracy import AccuracyConfig, BY_EPOCH_SCHEMA, ROW_SCORES, picture_accuracy, row_scores
from tertiary.evaluation.accuracy_buckets import picture_accuracy_buckets
from tertiary.core.errors import DataError
from tertiary.evaluation.multitarget import MultiTargetConfig, MultiTargetState, multitarget_result, multitarget_step
from tertiary.evaluation.matching import (MatchConfig, between_expr, between_mask, match_with_reference, neighbour_times, reference_identity)
from tertiary.evaluation.picture_metrics import BREAKDOWNS, MetricsConfig, picture_metrics
from tertiary.evaluation.picture_buckets import picture_metrics_buckets
from tertiary.evaluation.reference import adsb_reference, plot_measurements, reconstruct_reference
from tertiary.evaluation.reference_spans import files_between, piece_span, read_spans, write_spans
from tertiary.evaluation.requirements import Requirements, check_requirements
from tertiary.contract import TIME
from tertiary.runtime.fanout import serial
from tertiary.store.files import write_parquet_atomic

__all__ = ["EvaluationConfig", "Evaluation", "Matched", "SeedTables", "Reference", "match_block", "match_blocks",
           "scan_spilled", "evaluate_pictures",
           "evaluate_each", "write_reference", "read_reference", "write_reference_pieces", "reference_files",
           "comparison", "read_picture",
           "COMPARISON_METRICS", "reconstructed_reference", "RECONSTRUCTED", "adsb_reference_table",
           "reference_error_metrics", "read_parquet_file", "radar_sites", "metric_columns"]

#: the picture name under which a reconstructed reference is itself scored against truth
RECONSTRUCTED = "reference(reconstructed)"
_R_EARTH_M = 6_371_000.0

#: the comparison table's columns (segment ``all``), in this order
COMPARISON_METRICS = ("rmse_horizontal_m", "p95_horizontal_m", "rmse_height_m", "along_track_rms_m",
                      "across_track_rms_m", "latency_s", "prob_update", "id_changes_per_hour",
                      "false_tracks_per_hour", "duplicate_tracks_per_hour", "split_tracks", "merged_tracks",
                      "mode_s_correct_frac")

_STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")


@dataclass(frozen=True)
class EvaluationConfig:
    """Matching gates, metric settings and the breakdowns."""

    match: MatchConfig = field(default_factory=MatchConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    breakdown: tuple[str, ...] = BREAKDOWNS
    #: the seed metrics (:mod:`tertiary.evaluation.accuracy`): the transient, the (2.15) denominator, bands
    accuracy: AccuracyConfig = field(default_factory=AccuracyConfig)
    #: OSPA/GOSPA cut-off and order, the SIAP association distance (:mod:`tertiary.evaluation.multitarget`)
    multitarget: MultiTargetConfig = field(default_factory=MultiTargetConfig)


@dataclass
class Evaluation:
    """The stage's outputs: ``matched`` rows (empty unless kept), ``metrics`` (stage evaluation
    and the seed stage), ``requirements`` (empty without a requirements file), the
    ``comparison`` of the pictures, the seed ``by_epoch`` accuracy, the scored ``samples`` (what
    a bound is pooled over) and ``id_map`` (run, method, epoch, id, truth_id: the aircraft each
    picture row represents, for alert scoring)."""

    matched: pl.DataFrame
    metrics: pl.DataFrame
    requirements: pl.DataFrame
    comparison: pl.DataFrame
    by_epoch: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=BY_EPOCH_SCHEMA))
    samples: pl.DataFrame = field(default_factory=pl.DataFrame)
    id_map: pl.DataFrame = field(default_factory=pl.DataFrame)


def radar_sites(radars: pl.DataFrame | None, frame: geo.LocalFrame | None) -> np.ndarray | None:
    """The radar sites (R, 2) east, north in the system frame; None without radars or frame."""
    if radars is None or frame is None or radars.height == 0:
        return None
    e, n, _u = frame.from_geodetic(radars["lat_deg"].to_numpy(), radars["lon_deg"].to_numpy(),
                                   radars["alt_m"].to_numpy())
    return np.column_stack([e, n])


def comparison(metrics: pl.DataFrame) -> pl.DataFrame:
    """One row per picture, one column per :data:`COMPARISON_METRICS` (segment ``all``)."""
    rows = metrics.filter((pl.col("stage") == "evaluation") & (pl.col("segment") == "all")
                          & pl.col("metric").is_in(list(COMPARISON_METRICS)))
    if rows.height == 0:
        return pl.DataFrame({"method": []}, schema={"method": pl.String})
    wide = rows.pivot(on="metric", index="method", values="value", aggregate_function="first")
    return wide.select("method", *[c for c in COMPARISON_METRICS if c in wide.columns]).sort("method")


#: what :func:`picture_metrics` reads of a matched picture, beside the reference's ``true_*``
_METRIC_COLUMNS = ("method", "run", "epoch", "track_id", "truth_id", "gated_truth_id", "beyond_truth_id", *_STATE,
                   "alt_m", "alt_rate_mps", "mode_s", "mode_3a", "callsign", "icao24")


def metric_columns(matched: pl.DataFrame | pl.LazyFrame) -> list[str]:
    """The columns of ``matched`` the surveillance metrics read: a picture's covariances and
    diagnostics are not copied through their joins (memory of the stage)."""
    names = matched.collect_schema().names() if isinstance(matched, pl.LazyFrame) else matched.columns
    return [c for c in names if c in _METRIC_COLUMNS or c.startswith("true_")]


def _check_inputs(tracks: pl.DataFrame, truth: pl.DataFrame, id_col: str) -> None:
    missing = [c for c in ("epoch", id_col, *_STATE) if c not in tracks.columns]
    if missing:
        raise DataError(f"tracks: missing column(s) {', '.join(missing)} (the tracks schema)")
    missing = [c for c in ("truth_id", "time", *_STATE) if c not in truth.columns]
    if missing:
        raise DataError(f"reference: missing column(s) {', '.join(missing)} (the truth schema: truth_id, time, "
                        "x_m ... vz_mps[, alt_m])")
    if not (truth.schema["time"].is_temporal() and tracks.schema["epoch"].is_temporal()):
        raise DataError("reference time and track epoch must be date-times (the truth and tracks schemas)")


#: the reference columns :func:`match_with_reference` reads of a time slice
_MATCHED_REF = ("run", "truth_id", "time", *_STATE, "alt_m", "alt_rate_mps", "segment")


#: the internal columns of a reference file (:func:`write_reference`): each sample's aircraft's
#: neighbouring sample times
NEIGHBOUR_COLUMNS = ("__prev", "__next")

#: rows per row group of a reference file: a time slice skips the groups whose times (and
#: neighbour times) miss it
REFERENCE_GROUP_ROWS = 65_536


def write_reference(truth: pl.DataFrame, path: str | Path) -> Path:
    """``truth`` as a reference file the evaluation reads a time slice at a time (give its path
    as ``truth`` to :func:`evaluate_each`): its rows in their order, with each sample's aircraft's
    neighbouring sample times, so a slice is read without the rest of the reference. A long
    run's reference is then not held through the evaluation (memory);
    :func:`read_reference` gives ``truth`` back."""
    times = neighbour_times(truth)          # beside the frame's own columns: no copy of them
    frame = truth.with_columns(times["__prev"], times["__next"])
    return write_parquet_atomic(frame, path, compression="lz4", row_group_size=REFERENCE_GROUP_ROWS)


def write_reference_pieces(pieces: Iterable[pl.DataFrame], path: str | Path) -> Path:
    """A reference written a piece at a time, in order, as a directory of reference files (one
    per piece, read back in name order): each piece already carries its samples' ``__prev``/
    ``__next`` (:func:`neighbour_times` of whole aircraft), so a truth that is never held whole
    is written without a second copy (memory), and each file's time range beside them
    (:mod:`tertiary.evaluation.reference_spans`: a slice reads only its own files). :func:`read_reference`,
    :func:`evaluate_each` and the run database read the directory as one reference. The
    directory appears whole (renamed from a temporary one when the last piece is written)."""
    final = Path(path)
    tmp = final.with_name(final.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    spans = {}
    for n, piece in enumerate(pieces):
        name = f"{n:06d}.parquet"
        piece.write_parquet(tmp / name, compression="lz4", row_group_size=REFERENCE_GROUP_ROWS)
        spans[name] = piece_span(piece)
    if not spans:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ValueError("write_reference_pieces: no piece to write")
    write_spans(tmp, spans)
    shutil.rmtree(final, ignore_errors=True)
    tmp.rename(final)
    return final


def reference_files(path: str | Path) -> list[Path]:
    """The files of a reference (:func:`write_reference`, :func:`write_reference_pieces`), in
    order."""
    path = Path(path)
    return sorted(path.glob("*.parquet")) if path.is_dir() else [path]


def read_reference(path: str | Path, columns: Sequence[str] | None = None) -> pl.DataFrame:
    """The truth a reference file holds (:func:`write_reference`); ``columns``: only those."""
    files = reference_files(path)
    names = [c for c in pl.read_parquet_schema(files[0]) if c not in NEIGHBOUR_COLUMNS]
    return pl.read_parquet(files, columns=names if columns is None else [c for c in names if c in columns])


def _identity_of(files: Sequence[Path], columns: list[str]) -> pl.DataFrame | None:
    """:func:`reference_identity` of a reference on disk, read a file at a time: each aircraft's
    items from its first sample. Its identity columns read whole are strings a sample (a
    national day's: 6 GB) for a few thousand aircraft."""
    out = None
    for f in files:
        part = reference_identity(pl.read_parquet(f, columns=columns))
        if part is None:
            return None
        # the earlier files' first samples come first: keep="first" keeps them
        out = part if out is None else pl.concat([out, part]).unique("truth_id", keep="first", maintain_order=True)
    return out


class Reference:
    """The reference of one evaluation: whole, its aircraft's identity items, and its time
    slices (:meth:`between`). Held in memory (a frame; the neighbour times are made when a
    picture first comes in blocks) or read from a reference file (:func:`write_reference`)."""

    def __init__(self, truth: pl.DataFrame | str | Path) -> None:
        self._times = None
        if isinstance(truth, pl.DataFrame):
            self._truth, self.path = truth, None
            self.empty = truth.clear()
            self.identity = reference_identity(truth)
            return
        self._truth, self.path = None, Path(truth)
        self.files = reference_files(self.path)
        self._spans = read_spans(self.files)
        schema = {k: v for k, v in pl.read_parquet_schema(self.files[0]).items() if k not in NEIGHBOUR_COLUMNS}
        self.empty = pl.DataFrame(schema=schema)
        self.identity = _identity_of(self.files, [c for c in ("truth_id", "icao24", "callsign", "mode_3a")
                                                   if c in schema])

    def whole(self) -> pl.DataFrame:
        return self._truth if self.path is None else read_reference(self.path)

    def between(self, t0, t1, ended_s: float = 0.0) -> pl.DataFrame:
        """The samples the reference at any time in [t0, t1] reads (:func:`between_mask`), and
        with ``ended_s`` the last samples of the aircraft whose reference ended in the
        ``ended_s`` before ``t0`` (the matcher's rule 4)."""
        cols = [c for c in self.empty.columns if c in _MATCHED_REF]
        if ended_s > 0:
            t_end = t0 - timedelta(microseconds=round(ended_s * 1e6))
            ended = (pl.col("__next").is_null() & (pl.col("time") >= t_end) & (pl.col("time") < t0))
        if self.path is not None:
            # the reader keeps the rows' order: the frame's slice. It takes a coarse test on the
            # columns themselves (every row the exact one keeps passes it: its time is ≥ t0 or
            # its next sample's is, and ≤ t1 or its previous one's is), which skips the row
            # groups of other times; the exact test alone, with ``fill_null``, would skip none,
            # and every block of a long picture would read the whole reference
            coarse = (((pl.col("time") >= t0) | (pl.col("__next") >= t0))
                      & ((pl.col("time") <= t1) | (pl.col("__prev") <= t1)))
            keep = between_expr(t0, t1)
            if ended_s > 0:
                coarse, keep = coarse | ended, keep | ended
            files = files_between(self.files, self._spans, t_end if ended_s > 0 else t0, t1, reach=True)
            return (pl.scan_parquet(files).filter(coarse).select(*cols, *NEIGHBOUR_COLUMNS).collect()
                    .filter(keep).select(cols))
        if self._times is None:
            # three time columns beside the reference, not a neighboured copy of it: a slice
            # copies only its own rows of the columns the matcher reads (memory)
            self._times = neighbour_times(self._truth)
        mask = between_mask(self._times, t0, t1)
        if ended_s > 0:
            mask = mask | self._times.select(ended.fill_null(False)).to_series()
        return self._truth.select(cols).filter(mask)


#: what the evaluation reads of a matched, row-scored picture beside the reference's ``true_*``
#: (:func:`picture_accuracy`, :func:`picture_metrics`, the id map) and its id column
_SCORED_COLUMNS = (*_METRIC_COLUMNS, *ROW_SCORES, "nis")


def _scored_only(matched: pl.DataFrame, id_col: str) -> pl.DataFrame:
    """The columns of a matched, row-scored block that the metrics and the id map read: a long
    picture's other columns (the fusion's and tracker's diagnostics, the reference's segment
    once classified) are not held whole until its metrics run (memory of the stage)."""
    return matched.select(c for c in matched.columns
                          if c in _SCORED_COLUMNS or c == id_col or c.startswith("true_"))


def match_block(block: pl.DataFrame, truth: pl.DataFrame | None, reference: "Reference", cfg: EvaluationConfig,
                id_col: str, mt: MultiTargetState | None, slim: bool, expected: pl.DataFrame | None = None
                ) -> tuple[pl.DataFrame, pl.DataFrame, MultiTargetState | None]:
    """(row-scored matched rows, reference at the block's epochs, ``mt`` stepped; None: no
    multi-target metrics) of one block of a picture (whole epochs, after every earlier block's),
    matched against ``truth`` (None: the reference samples its epochs read,
    :meth:`Reference.between`). ``expected``: the reference at a superset of the block's epochs,
    made once for several blocks (:func:`~tertiary.evaluation.matching.match_with_reference`).
    The matcher is per epoch and the row scores per row: the step of :func:`match_blocks`, and
    of the evaluation's window stage."""
    _check_inputs(block, reference.empty, id_col)
    if "method" not in block.columns:
        block = block.with_columns(pl.lit("picture").alias("method"))
    if truth is None:
        truth = reference.between(block["epoch"].min(), block["epoch"].max(), cfg.match.ended_s)
    m, ref = match_with_reference(block, truth, cfg.match, id_col, reference.identity, expected)
    del block, truth
    if mt is not None:
        mt = multitarget_step(mt, m.select("run", "epoch", pl.col(id_col).alias("track_id"), *_STATE[:3]),
                              ref.select(MULTITARGET_TRUTH), cfg.multitarget)
    scored = row_scores(m)
    return (_scored_only(scored, id_col) if slim else scored), ref, mt


def match_blocks(blocks: Iterable[pl.DataFrame], reference: Reference, cfg: EvaluationConfig,
                  id_col: str, slim: bool = False, spill: Path | None = None, multitarget: bool = False
                  ) -> tuple[pl.DataFrame | pl.LazyFrame, pl.DataFrame | pl.LazyFrame, pl.DataFrame | None] | None:
    """(matched rows with their :func:`row_scores`, reference at the picture's epochs, the
    picture's OSPA, GOSPA and SIAP rows when ``multitarget``, stepped a block at a time:
    :func:`~tertiary.evaluation.multitarget.multitarget_step`) of one picture given in blocks,
    or None when it has no row. A block is matched against the
    reference samples its epochs read (:func:`reference_between`): the matcher is per epoch
    and the row scores per row, so the result is that of the whole picture at once. ``slim``:
    only the columns the metrics read are kept (:func:`_scored_only`). ``spill`` (a picture of
    several blocks): each block's rows go to Parquet files there as they are made, and both
    come back as scans of those files, never held whole (memory)."""
    it = (b for b in blocks if b.height)
    first = next(it, None)
    if first is None:
        return None
    second = next(it, None)
    whole = second is None                  # one block: matched against the whole reference
    if whole:
        spill = None
    matched, expected, last, mt = [], [], None, MultiTargetState()
    method = str(first["method"][0]) if "method" in first.columns else "picture"
    for block in itertools.chain([first], [] if whole else [second], it):
        _check_inputs(block, reference.empty, id_col)
        t0 = block["epoch"].min()
        if last is not None and t0 <= last:
            raise DataError("a picture's blocks must be in time order, no epoch in two blocks")
        last = block["epoch"].max()
        scored, ref, mt = match_block(block, reference.whole() if whole else None, reference, cfg, id_col,
                                      mt if multitarget else None, slim)
        del block
        matched.append(scored)
        expected.append(ref)
        del scored
        if spill is not None:
            matched, expected = _spilled(spill, matched, expected)
    mt_rows = multitarget_result(mt, method) if multitarget else None
    if spill is not None:
        return (*(scan_spilled(sorted((spill / k).glob("*.parquet"))) for k in ("matched", "expected")), mt_rows)
    return _concat(matched), _concat(expected), mt_rows


def scan_spilled(files: list[Path], schemas: dict[Path, pl.Schema] | None = None) -> pl.LazyFrame:
    """The spilled blocks ``files`` as one scan: of the files together when they share a schema
    (a slice of it then reads only its own files: the metrics' buckets are filed a slice at a
    time), else of each, relaxed (a block whose column is all null may have stored it with
    another type; a slice of that concatenation reads every file before it). ``schemas``: the
    files' schemas already read, and where those read here are kept (files scanned again)."""
    known = {} if schemas is None else schemas

    def schema(f: Path) -> pl.Schema:
        if f not in known:
            known[f] = pl.read_parquet_schema(f)
        return known[f]
    first = schema(files[0])
    if all(schema(f) == first for f in files[1:]):
        return pl.scan_parquet(files)
    return pl.concat([pl.scan_parquet(f) for f in files], how="vertical_relaxed")


def _spilled(spill: Path, matched: list[pl.DataFrame], expected: list[pl.DataFrame]
             ) -> tuple[list[pl.DataFrame], list[pl.DataFrame]]:
    """The block just made (the last of each list) written to ``spill``; empty lists back."""
    for name, frames in (("matched", matched), ("expected", expected)):
        d = spill / name
        d.mkdir(parents=True, exist_ok=True)
        frames[-1].write_parquet(d / f"{len(list(d.glob('*.parquet'))):06d}.parquet", statistics=False,
                                 compression="lz4")
    return [], []


#: rows of a spilled picture whose metrics are computed at a time (:func:`evaluate_each`): the
#: stage's memory is a bucket's, not the picture's
EVAL_BUCKET_ROWS = 150_000


def _buckets(matched: pl.LazyFrame, rows: int) -> int:
    """How many buckets keep each at about ``rows`` rows of ``matched`` (at least one)."""
    n = matched.select(pl.len()).collect().item()
    return max(1, -(-n // max(1, rows)))


def _held_if_small(picture: Matched, rows: int, surveillance: bool
                   ) -> tuple[pl.DataFrame | pl.LazyFrame, pl.DataFrame | pl.LazyFrame | None, pl.DataFrame | None]:
    """A matched picture's (matched, expected, multi-target rows): read into memory when it has at
    most ``rows`` rows (its metrics then need no bucket), else left as scans."""
    mt = picture.multitarget if surveillance else None
    if picture.matched.select(pl.len()).collect().item() > rows:
        return picture.matched, picture.expected, mt
    return picture.matched.collect(), None if picture.expected is None else picture.expected.collect(), mt


def _concat(frames: list[pl.DataFrame]) -> pl.DataFrame:
    return frames[0] if len(frames) == 1 else pl.concat(frames, how="vertical_relaxed")


#: what the multi-target metrics read of the reference at a picture's epochs
MULTITARGET_TRUTH = ("run", "epoch", "truth_id", "true_x_m", "true_y_m", "true_z_m")


#: a picture's seed metrics finished from its carried state, given the stage name and the
#: options: (metrics, per-epoch accuracy, scored samples), as :func:`picture_accuracy` gives them
SeedTables = Callable[[str, AccuracyConfig], tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]]


@dataclass(frozen=True)
class Matched:
    """A picture matched as it was made (the evaluation's window stage): its slim, row-scored
    matched rows and the reference at its epochs as scans, its OSPA, GOSPA and SIAP rows, and
    its seed metrics when the windows stepped them (``seed``). :func:`evaluate_each` scores it
    as a picture it matched itself: in memory when it is small, else in buckets (its
    ``spill``)."""

    matched: pl.LazyFrame
    expected: pl.LazyFrame | None
    multitarget: pl.DataFrame | None
    seed: SeedTables | None = None
    #: its surveillance metrics finished from the windows' carried state, given the radar sites,
    #: the breakdowns and the settings (:func:`~tertiary.evaluation.picture_streamed.picture_metrics_finish`)
    metrics: "Callable[[np.ndarray | None, Sequence[str], MetricsConfig], pl.DataFrame] | None" = None
    #: its id map as the windows reduced it, a block each (:func:`safety.alerts.block_id_rows`):
    #: read instead of the matched rows when the id map is reduced to the run's alerts
    ids: pl.LazyFrame | None = None


def evaluate_pictures(tracks: pl.DataFrame, truth: pl.DataFrame, *, radars: pl.DataFrame | None = None,
                      frame: geo.LocalFrame | None = None, requirements: Requirements | None = None,
                      cfg: EvaluationConfig = EvaluationConfig(), id_col: str = "track_id",
                      seed_stage: str = "tracker", observed: pl.DataFrame | None = None,
                      keep_matched: bool = True, surveillance: bool = True) -> Evaluation:
    """Score every picture of ``tracks`` (column ``method`` names it) against ``truth`` (the
    reference in the same system frame): the module's steps, one picture at a time. ``radars``
    + ``frame`` give the range-ring breakdown; ``seed_stage`` labels the seed metrics;
    ``observed`` (run, epoch, truth_id) is what continuity expects covered (default: the
    reference aircraft alive at the picture's epochs); ``surveillance=False`` leaves out the
    stage-``evaluation`` metrics (and so the requirements)."""
    _check_inputs(tracks, truth, id_col)
    if "method" not in tracks.columns:
        tracks = tracks.with_columns(pl.lit("picture").alias("method"))
    return evaluate_each(tracks.partition_by("method", maintain_order=True), truth, radars=radars, frame=frame,
                         requirements=requirements, cfg=cfg, id_col=id_col, seed_stage=seed_stage,
                         observed=observed, keep_matched=keep_matched, surveillance=surveillance,
                         empty=tracks.clear())


def evaluate_each(pictures: Iterable["pl.DataFrame | Iterable[pl.DataFrame] | Matched"],
                  truth: pl.DataFrame | str | Path, *,
                  radars: pl.DataFrame | None = None,
                  frame: geo.LocalFrame | None = None, requirements: Requirements | None = None,
                  cfg: EvaluationConfig = EvaluationConfig(), id_col: str = "track_id",
                  seed_stage: str = "tracker", observed: pl.DataFrame | None = None,
                  keep_matched: bool = True, surveillance: bool = True,
                  empty: pl.DataFrame | None = None,
                  id_map: "bool | Callable[[pl.LazyFrame], pl.LazyFrame]" = True, spill: Path | None = None,
                  bucket_rows: int | None = None) -> Evaluation:
    """:func:`evaluate_pictures` on pictures given one at a time (each frame one ``method``):
    a caller that reads each picture from disk as it is scored (the pipeline's on-disk runs)
    holds one picture, never all of them. A picture may come as blocks of rows in time order
    (an iterable of frames, epochs not shared between blocks): each block is matched against
    its time slice of the reference and row-scored alone (:func:`match_blocks`), so the
    picture's covariances and the matcher's scratch are never held whole. The same metrics as
    one call on their union. ``truth`` may be a reference file or directory
    (:func:`write_reference`, :func:`write_reference_pieces`): then only the slices a picture's
    blocks read are held. ``id_map=False``: no id map (a caller that scores no alert on these
    pictures does not hold one row per picture row through its later stages); a function: the
    id map of the rows it keeps (of each picture's, as a lazy frame). ``spill`` (a
    scratch directory; with ``keep_matched=False``): a picture of several blocks is matched to
    Parquet files there, and its metrics are computed in buckets of at most ``bucket_rows``
    rows (default :data:`EVAL_BUCKET_ROWS`) of aircraft or tracks
    (:func:`~tertiary.evaluation.accuracy_buckets.picture_accuracy_buckets`,
    :func:`~tertiary.evaluation.picture_buckets.picture_metrics_buckets`): the same metrics, with the
    stage's memory bounded by a bucket, not by the recording. A picture with a ``match_apart``
    method (:class:`~tertiary.evaluation.matched_apart.PictureFiles`, spilled, the truth a file)
    is matched a stretch of its windows at a time, each a piece of its fanout."""
    breakdown = [b for b in cfg.breakdown if b != "range" or (radars is not None and frame is not None)]
    radar_xy = radar_sites(radars, frame)
    parts: dict[str, list[pl.DataFrame]] = {k: [] for k in ("matched", "metrics", "by_epoch", "samples", "id_map")}
    reference = Reference(truth)
    # one picture at a time: the memory of the stage is that of one picture, not of all of them
    for i, picture in enumerate(pictures):
        where = None if spill is None or keep_matched else spill / f"picture-{i:03d}"
        if where is not None:
            shutil.rmtree(where, ignore_errors=True)        # an interrupted evaluation's files
        seeded, surveyed = None, None
        if isinstance(picture, Matched):
            if surveillance and picture.metrics is not None:
                surveyed = picture.metrics(radar_xy, [b for b in breakdown if b != "range" or radar_xy is not None],
                                           cfg.metrics)
            seeded = None if picture.seed is None else picture.seed(seed_stage, cfg.accuracy)
            if seeded is not None and (surveyed is not None or not surveillance):
                # finished from the windows' state: the rows are read only for the id map
                got = (picture.matched, picture.expected, picture.multitarget if surveillance else None)
            else:
                got = _held_if_small(picture, EVAL_BUCKET_ROWS if bucket_rows is None else bucket_rows, surveillance)
        elif callable(getattr(picture, "match_apart", None)):
            # a picture on disk whose stretches are matched apart (a distributed run's slices)
            got = (picture.match_apart(reference, cfg, id_col, where, surveillance)
                   if where is not None and reference.path is not None else
                   match_blocks(picture.blocks(), reference, cfg, id_col, slim=not keep_matched, spill=where,
                                 multitarget=surveillance))
        else:
            got = match_blocks([picture] if isinstance(picture, pl.DataFrame) else picture, reference, cfg, id_col,
                                slim=not keep_matched, spill=where, multitarget=surveillance)
        if got is None:
            continue
        matched, expected, mt_rows = got
        if id_col != "track_id":
            matched = matched.rename({id_col: "track_id"})
        seen = observed if observed is not None else expected.select("run", "epoch", "truth_id")
        if seeded is not None:          # stepped by the windows: only finished here
            seed, by_epoch, samples = seeded
        if isinstance(matched, pl.LazyFrame):
            # a picture matched apart has its buckets computed where its stretches were
            fanout = getattr(picture, "fanout", serial)
            if seeded is None or (surveyed is None and surveillance):
                k = _buckets(matched, EVAL_BUCKET_ROWS if bucket_rows is None else bucket_rows)
            if seeded is None:
                # each bucket reads its own rows, filed once beside the spilled picture (linear
                # in the picture's rows, not rows × buckets)
                seed, by_epoch, samples = picture_accuracy_buckets(matched, seed_stage, cfg.accuracy, seen,
                                                                   buckets=k, scratch=where / "accuracy",
                                                                   fanout=fanout)
                # its filed rows go before the metrics file theirs: the scratch's peak is the
                # spilled picture and one filing, not two
                shutil.rmtree(where / "accuracy", ignore_errors=True)
            if surveyed is not None:
                parts["metrics"].append(surveyed)
            elif surveillance:
                parts["metrics"].append(picture_metrics_buckets(
                    matched.select(metric_columns(matched)), expected=expected, radar_xy=radar_xy,
                    breakdown=breakdown, cfg=cfg.metrics, buckets=k, scratch=where / "metrics", fanout=fanout))
        else:
            if seeded is None:
                seed, by_epoch, samples = picture_accuracy(matched, seed_stage, cfg.accuracy, seen)
            if surveyed is not None:
                parts["metrics"].append(surveyed)
            elif surveillance:
                parts["metrics"].append(picture_metrics(matched.select(metric_columns(matched)), expected=expected,
                                                        radar_xy=radar_xy, breakdown=breakdown, cfg=cfg.metrics))
        if surveillance:
            parts["metrics"].append(mt_rows)
        parts["metrics"].append(seed)
        parts["by_epoch"].append(by_epoch)
        parts["samples"].append(samples)
        if id_map:
            reduced = picture.ids if isinstance(picture, Matched) and callable(id_map) else None
            ids = reduced if reduced is not None else matched.lazy().select(
                "run", "method", "epoch", pl.col("track_id").alias(id_col),
                pl.coalesce("truth_id", "gated_truth_id").alias("truth_id"))
            parts["id_map"].append((id_map(ids) if callable(id_map) else ids).collect())
        if keep_matched:
            parts["matched"].append(matched.drop(*ROW_SCORES, strict=False))
        # released before the next picture is matched: two pictures' rows are never held at once
        del got, matched, expected, seed, by_epoch, samples, mt_rows, seeded
        if where is not None:
            shutil.rmtree(where, ignore_errors=True)

    def cat(k: str, none: pl.DataFrame) -> pl.DataFrame:
        return pl.concat(parts[k], how="diagonal_relaxed") if parts[k] else none

    metrics = cat("metrics", pl.DataFrame())
    reqs = check_requirements(metrics, requirements) if requirements is not None else pl.DataFrame()
    return Evaluation(cat("matched", empty if empty is not None else pl.DataFrame()), metrics, reqs,
                      comparison(metrics), cat("by_epoch", pl.DataFrame(schema=BY_EPOCH_SCHEMA)),
                      cat("samples", pl.DataFrame()), cat("id_map", pl.DataFrame()))


def reconstructed_reference(reports: pl.DataFrame, radars: pl.DataFrame, frame: geo.LocalFrame,
                            key: str = "truth_id") -> pl.DataFrame:
    """A reference per aircraft reconstructed offline from every radar plot by a
    fixed-interval smoother (:func:`tertiary.evaluation.reference.reconstruct_reference`: forward Kalman pass
    + Rauch–Tung–Striebel backward pass), in the truth schema (truth_id, time, x_m … vz_mps,
    alt_m, sigma_h_m). The smoother's state is (x, y, height); the ENU z of the truth schema is
    derived from the height (z ≈ h − ρ²/2R, ≤ 1 m error below 150 km) only so that the frame is
    complete; heights are compared through ``alt_m``. ``key``: the aircraft identity of the
    plots (``truth_id`` in simulation, ``mode_s`` on a recording)."""
    rec = reconstruct_reference(plot_measurements(reports, radars, frame, key=key), key=key)
    rho2 = pl.col("x_m") ** 2 + pl.col("y_m") ** 2
    return rec.select(pl.col("truth_id").cast(pl.Int64) if key == "truth_id" else "truth_id", "time", "x_m", "y_m",
                      (pl.col("alt_m") - rho2 / (2 * _R_EARTH_M)).alias("z_m"), "vx_mps", "vy_mps",
                      pl.col("alt_rate_mps").alias("vz_mps"), "alt_m", "sigma_h_m")


def adsb_reference_table(raw: pl.DataFrame, frame: geo.LocalFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """An ADS-B recording (OpenSky / ``traffic`` schema) as the reference, in the
    truth schema: points filtered by their declared quality (NACp/NIC/NUCp where present), jumps
    and stale positions (:func:`tertiary.evaluation.reference.adsb_reference`), with the reference's own
    horizontal σ per point (``sigma_h_m``). Returns (reference, removed rows with reasons). Use it
    with ``MatchConfig(max_gap_s=...)`` so that only short gaps are interpolated."""
    points, removed = adsb_reference(raw, frame)
    ref = points.with_columns(pl.col("alt_rate_mps").fill_nan(None).fill_null(0.0).alias("vz_mps"),
                              pl.col("vx_mps").fill_nan(None), pl.col("vy_mps").fill_nan(None))
    return ref, removed


def reference_error_metrics(metrics: pl.DataFrame, reference: pl.DataFrame) -> pl.DataFrame:
    """The reference's own horizontal error beside every picture's accuracy: metric
    ``reference_sigma_h_m`` (RMS of the reference points' per-axis σ × √2), stage evaluation."""
    if "sigma_h_m" not in reference.columns or metrics.height == 0:
        return metrics.clear()
    sig = float(reference.select((2.0 * pl.col("sigma_h_m").pow(2)).mean().sqrt()).item())
    pics = metrics.filter(pl.col("stage") == "evaluation").select("method", "n_runs").unique("method")
    return pics.select(pl.lit("evaluation").alias("stage"), "method", pl.lit("reference_sigma_h_m").alias("metric"),
                       pl.lit("all").alias("segment"), pl.lit(sig).alias("value"), "n_runs"
                       ).cast(metrics.schema)


def read_parquet_file(path: str | Path) -> pl.DataFrame:
    """A Parquet file given on the command line; missing, not a file or unreadable is a
    :class:`DataError` naming it (one line, never a traceback)."""
    p = Path(path)
    if not p.exists():
        raise DataError("file not found", path=str(p))
    if not p.is_file():
        raise DataError("not a file", path=str(p))
    try:
        return pl.read_parquet(p)
    except (OSError, pl.exceptions.PolarsError) as exc:
        raise DataError(f"not a readable Parquet file ({type(exc).__name__})", path=str(p)) from exc


def read_picture(path: str | Path) -> pl.DataFrame:
    """A picture file: Parquet in the ``tracks`` schema (at least epoch, track_id, x_m … vz_mps;
    ``run`` defaults to 0). Its name (``method``) is ``method[+filter]`` when the file carries
    them (a ``tertiary`` export), else the file's stem."""
    p = Path(path)
    frame = read_parquet_file(p)
    missing = [c for c in ("epoch", "track_id", *_STATE) if c not in frame.columns]
    if missing:
        raise DataError(f"missing column(s) {', '.join(missing)}: a picture needs epoch, track_id and the "
                        "ENU state x_m … vz_mps (the tracks schema)", path=str(p))
    if "run" not in frame.columns:
        frame = frame.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    if "method" in frame.columns and "filter" in frame.columns:
        name = pl.format("{}+{}", "method", "filter")
    elif "method" in frame.columns:
        name = pl.col("method")
    else:
        name = pl.lit(p.stem)
    return frame.with_columns(name.alias("method"), pl.col("epoch").cast(TIME), pl.col("run").cast(pl.UInt32),
                              pl.col("track_id").cast(pl.UInt64)).drop("filter", strict=False)


def read_pictures(paths: Sequence[str | Path]) -> pl.DataFrame:
    """Several picture files as one table; two files with the same picture name are an error."""
    frames = [read_picture(p) for p in paths]
    names = [sorted(f["method"].unique().to_list()) for f in frames]
    flat = [n for ns in names for n in ns]
    dup = sorted({n for n in flat if flat.count(n) > 1})
    if dup:
        raise DataError(f"two TRACKS files hold the same picture {dup[0]!r}: rename one file")
    keep = sorted(set().union(*(set(f.columns) for f in frames)))
    return pl.concat([f.select([c for c in keep if c in f.columns]) for f in frames], how="diagonal_relaxed")


__all__ += ["read_pictures"]
