"""The picture metrics of a picture too long to hold whole: :func:`picture_metrics_buckets`
does the row work of :func:`tertiary.evaluation.picture_metrics.picture_metrics` on one bucket of
aircraft at a time and combines the buckets' sums into the same table.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core.errors import OptionError
from tertiary.evaluation import picture_metrics as pm
from tertiary.evaluation import sketch
from tertiary.evaluation.buckets import file_buckets
from tertiary.evaluation.picture_metrics import BREAKDOWNS, MetricsConfig
from tertiary.runtime.fanout import Fanout, serial

__all__ = ["picture_metrics_buckets", "Partials", "RMS_ERRORS", "MEAN_ERRORS", "accuracy_sums", "accuracy_combined",
           "identity_combined", "continuity_combined"]

#: seed of the bucket hash: any fixed value (a row must fall in the same bucket in every scan)
_SEED = 20211007

#: the accuracy metrics that are a root mean square (metric → error column) or a mean
RMS_ERRORS = {"rmse_horizontal_m": "err_h_m", "rmse_height_m": "err_height_m", "along_track_rms_m": "along_m",
        "across_track_rms_m": "across_m", "ground_speed_rms_mps": "err_gs_mps", "track_angle_rms_deg": "err_track_deg",
        "vertical_rate_rms_mps": "err_vrate_mps"}
MEAN_ERRORS = {"along_track_bias_m": "along_m", "across_track_bias_m": "across_m", "latency_s": "latency_sample_s",
         "ground_speed_bias_mps": "err_gs_mps"}


def _aircraft_bucket(schema: pl.Schema, buckets: int, gated: bool = False) -> pl.Expr:
    """The bucket of a row's aircraft (run, truth_id), hashed in ``matched``'s dtypes (``schema``)
    so that an ``expected`` row falls in the bucket of its aircraft's track rows. ``gated``: an
    unmatched row's aircraft is the one whose gate it lies in (``gated_truth_id``)."""
    truth = pl.col("truth_id").cast(schema["truth_id"])
    if gated:
        truth = pl.coalesce(truth, pl.col("gated_truth_id").cast(schema["truth_id"]))
    key = pl.struct(pl.col("run").cast(schema["run"]), truth)
    return key.hash(_SEED) % buckets


def _has_gated(schema: pl.Schema) -> bool:
    return "gated_truth_id" in schema.names()


def _tracked(schema: pl.Schema, gated: bool) -> pl.Expr:
    """The rows of an aircraft: matched, or (``gated``) in its gate."""
    hit = pl.col("truth_id").is_not_null()
    return hit | pl.col("gated_truth_id").is_not_null() if gated and _has_gated(schema) else hit

@dataclass(frozen=True)
class _BucketScan:
    """One bucket of aircraft of the inputs at a time: the rows of ``matched`` with a truth_id
    (or a ``gated_truth_id``: a second track of the aircraft) and the rows of ``expected`` whose
    (run, truth_id) hash to bucket k."""

    matched_lf: pl.LazyFrame
    expected_lf: pl.LazyFrame | None
    schema: pl.Schema           # of matched
    exp_cols: tuple[str, ...]   # what is read of expected: its keys and reference (true_*) columns
    buckets: int
    #: each bucket's tracked rows of matched and rows of expected, filed once (:meth:`filed`)
    filed_matched: list[pl.LazyFrame] | None = None
    filed_expected: list[pl.LazyFrame] | None = None

    @classmethod
    def filed(cls, matched: pl.LazyFrame, expected: pl.LazyFrame | None, schema: pl.Schema,
              exp_cols: tuple[str, ...], buckets: int, scratch: Path, fanout: Fanout = serial) -> "_BucketScan":
        """The scan with the rows filed by bucket once under ``scratch``
        (:func:`tertiary.evaluation.buckets.file_buckets`, its slices pieces of ``fanout``): a
        bucket reads its own rows only."""
        bucket = _aircraft_bucket(schema, buckets)
        m = file_buckets(matched.filter(_tracked(schema, True)), _aircraft_bucket(schema, buckets, _has_gated(schema)),
                         buckets, scratch / "matched", fanout=fanout)
        e = None
        if expected is not None:
            src = expected.with_columns(bucket.alias("__ab")).select(*exp_cols, "__ab")
            e = [f.drop("__ab") for f in file_buckets(src, pl.col("__ab"), buckets, scratch / "expected",
                                                      fanout=fanout)]
        return cls(matched, expected, schema, exp_cols, buckets, m, e)

    def _where(self, k: int, matched: bool) -> pl.Expr | None:
        """Bucket ``k``'s rows of ``matched`` (else of ``expected``)."""
        return (None if self.buckets == 1 else
                _aircraft_bucket(self.schema, self.buckets, matched and _has_gated(self.schema)) == k)

    def matched(self, k: int, cols: Sequence[str], gated: bool = False) -> pl.DataFrame:
        """Bucket ``k``'s tracked rows of ``matched``, columns ``cols`` (those it has); ``gated``:
        with the unmatched rows in an aircraft's gate."""
        names = [c for c in self.schema.names() if c in cols]
        tracked = _tracked(self.schema, gated)
        if self.filed_matched is not None:
            return self.filed_matched[k].filter(tracked).select(names).collect()
        where = self._where(k, matched=True)
        return self.matched_lf.filter(tracked if where is None else tracked & where).select(names).collect()


    def expected(self, k: int) -> pl.DataFrame | None:
        """Bucket ``k``'s rows of ``expected`` (None without it)."""
        if self.expected_lf is None:
            return None
        if self.filed_expected is not None:
            return self.filed_expected[k].collect()
        where = self._where(k, matched=False)
        return (self.expected_lf if where is None else self.expected_lf.filter(where)).select(self.exp_cols).collect()


def _ratio(num: pl.Expr, den: pl.Expr) -> pl.Expr:
    """num / den, null where den is 0 (the mean of no value)."""
    return pl.when(den > 0).then(num / den)


@dataclass
class Partials:
    """What the buckets leave for the combine step: sums per (method, segment, run) (a few rows
    per segment), the percentiles' sketches (``values``: counts per bucket of the error, a few
    hundred rows per segment), distinct split tracks and the bare expected rows."""

    accuracy: list[pl.DataFrame] = field(default_factory=list)
    values: list[pl.DataFrame] = field(default_factory=list)
    identity: dict[str, list[pl.DataFrame]] = field(default_factory=dict)
    hours: list[pl.DataFrame] = field(default_factory=list)
    events: list[pl.DataFrame] = field(default_factory=list)
    intervals: list[pl.DataFrame] = field(default_factory=list)
    split: list[pl.DataFrame] = field(default_factory=list)
    bare: list[pl.DataFrame] = field(default_factory=list)

    def add(self, other: "Partials") -> None:
        """``other``'s partials after these (another bucket's)."""
        for name in ("accuracy", "values", "hours", "events", "intervals", "split", "bare"):
            getattr(self, name).extend(getattr(other, name))
        for name, sums in other.identity.items():
            self.identity.setdefault(name, []).extend(sums)


def accuracy_sums() -> list[pl.Expr]:
    """The accuracy sums of error rows: their count, the maxima, and each RMS and mean metric's
    sum (of squares) and count (:data:`RMS_ERRORS`, :data:`MEAN_ERRORS`)."""
    aggs = [pl.len().alias("n_points"), pl.col("err_h_m").max().alias("max_horizontal_m"),
            pl.col("err_height_m").abs().max().alias("max_height_m")]
    for name, c in RMS_ERRORS.items():
        aggs += [(pl.col(c) ** 2).sum().alias(name), pl.col(c).count().alias(f"{name}:n")]
    for name, c in MEAN_ERRORS.items():
        aggs += [pl.col(c).sum().alias(name), pl.col(c).count().alias(f"{name}:n")]
    return aggs


def _error_partials(err: pl.DataFrame, breakdown: Sequence[str], cfg: MetricsConfig, out: Partials) -> None:
    """Accuracy and identity sums of one bucket's error rows, and the sketch of its percentiles."""
    out.accuracy.append(pm.by_segment(err, breakdown, *accuracy_sums(), by=["run"]))
    out.values.append(pm.percentile_counts(err.with_columns(pl.col("method").cast(pl.Categorical)), breakdown))
    for name, ok in pm.identity_checks(err, cfg):
        out.identity.setdefault(name, []).append(pm.by_segment(
            pm.identity_rows(err, breakdown, ok), breakdown, pl.col("__ok").sum(), pl.len().alias("__n"), by=["run"]))


def _continuity_partials(m: pl.DataFrame, expected: pl.DataFrame | None, labels: pl.DataFrame,
                         methods: pl.DataFrame, breakdown: Sequence[str], cfg: MetricsConfig, merge: bool,
                         out: Partials, gated: pl.DataFrame | None = None) -> None:
    """The continuity sums of one bucket's aircraft (``methods``: every picture with a
    matched row, in any bucket), its split tracks (``gated``: its second tracks' rows,
    :func:`~tertiary.evaluation.picture_metrics.gated_rows`) and (``merge``) its bare expected rows."""
    rep = pm.rep_events(m, labels, cfg)
    expo = pm.exposure_rows(rep, expected, methods, labels, cfg)
    out.hours.append(pm.by_segment(expo, breakdown, pl.col("__hours").sum(), by=["run"]))
    out.events.append(pm.by_segment(rep, breakdown, pl.col("__change").sum().alias("__changes"),
                                  pl.col("__break").sum().alias("track_breaks"),
                                  pl.col("__gap_s").filter(pl.col("__break")).sum().alias("__gaps"), by=["run"]))
    ints = pm.update_intervals(rep, expo, cfg, expected is None)
    out.intervals.append(pm.by_segment(ints, breakdown, pl.col("updated").sum().alias("__updated"),
                                     pl.len().alias("__n"), by=["run"]))
    del ints, expo
    out.split.append(pm.second_tracks(rep, m, labels, gated).select("method", "run", "track_id", *breakdown).unique())
    if merge:
        out.bare.append(pm.bare_rows(m, expected, methods).join(labels, on=["run", "truth_id", "epoch"], how="left")
                        .select(pl.col("method").cast(pl.Categorical), "run", "epoch", "truth_id", "true_x_m",
                                "true_y_m", "__h", *breakdown))


def _bucket_partials(m: pl.DataFrame, expected: pl.DataFrame | None, methods: pl.DataFrame,
                     radar_xy: NDArray[np.float64] | None, breakdown: Sequence[str], cfg: MetricsConfig, merge: bool,
                     out: Partials) -> None:
    """Everything one bucket's rows (``m``: its tracked rows and the unmatched rows in the gate of
    one of its aircraft, ``expected``: its reference rows) leave for the combine step; nothing
    without a row."""
    gated = pm.gated_rows(m, m.schema["truth_id"])
    m = m.filter(pl.col("truth_id").is_not_null())
    if m.height == 0 and (expected is None or expected.height == 0):
        return
    labels = pm.picture_labels(m, expected, radar_xy, cfg)
    _error_partials(pm.error_rows(m, labels, cfg), breakdown, cfg, out)
    if methods.height:                      # continuity of every picture with a matched row
        _continuity_partials(m.select(c for c in m.columns if c in pm.CONTINUITY_INPUTS), expected, labels,
                             methods, breakdown, cfg, merge, out, gated)


def _bucket_piece(scan: _BucketScan, k: int, reads: set[str], methods: pl.DataFrame,
                  radar_xy: NDArray[np.float64] | None, breakdown: Sequence[str], cfg: MetricsConfig, merge: bool
                  ) -> Partials:
    """Bucket ``k``'s partials (a piece of :func:`picture_metrics_buckets`)."""
    out = Partials()
    _bucket_partials(scan.matched(k, reads, gated=True), scan.expected(k), methods, radar_xy, breakdown, cfg, merge,
                     out)
    return out


def accuracy_combined(out: Partials, breakdown: Sequence[str], method: pl.DataType) -> pl.DataFrame:
    """The accuracy rows from the buckets' sums, and the percentiles from their merged sketches."""
    aggs = [pl.col("run").n_unique().alias("n_runs"), pl.col("n_points").sum().cast(pl.Float64),
            pl.col("max_horizontal_m").max(), pl.col("max_height_m").max()]
    aggs += [_ratio(pl.col(n).sum(), pl.col(f"{n}:n").sum()).sqrt().alias(n) for n in RMS_ERRORS]
    aggs += [_ratio(pl.col(n).sum(), pl.col(f"{n}:n").sum()).alias(n) for n in MEAN_ERRORS]
    wide = pl.concat(out.accuracy).group_by("method", "segment").agg(*aggs)
    q = pm.percentiles(sketch.merge_counts(out.values, ["method", "segment"])).with_columns(pl.col("method").cast(method))
    out.values.clear()
    wide = wide.join(q, on=["method", "segment"], how="left")
    return pm.long_rows(wide, [c for c in wide.columns if c not in ("method", "segment", "n_runs")])


def identity_combined(name: str, sums: list[pl.DataFrame]) -> pl.DataFrame:
    """The identity rows of one item from the buckets' sums."""
    w = pl.concat(sums).group_by("method", "segment").agg(
        pl.col("run").n_unique().alias("n_runs"),
        (pl.col("__ok").sum() / pl.col("__n").sum()).alias(f"{name}_correct_frac"),
        pl.col("__n").sum().cast(pl.Float64).alias(f"n_{name}"))
    return pm.long_rows(w, [f"{name}_correct_frac", f"n_{name}"])


def continuity_combined(out: Partials, base: pl.DataFrame, breakdown: Sequence[str]) -> list[pl.DataFrame]:
    """The continuity rows (but merged tracks) from the buckets' sums; ``base``: the
    (method, run) with a matched row."""
    by = ["method", "segment"]
    hours = pl.concat(out.hours).group_by(by).agg(pl.col("__hours").sum().alias("aircraft_hours"),
                                                  pl.col("run").n_unique().alias("n_runs"))
    breaks = pl.col("track_breaks").sum()
    events = pl.concat(out.events).group_by(by).agg(pl.col("__changes").sum(), breaks,
                                                    _ratio(pl.col("__gaps").sum(), breaks).alias("mean_reacquire_s"))
    ints = pl.concat(out.intervals).group_by(by).agg(
        _ratio(pl.col("__updated").sum(), pl.col("__n").sum()).alias("prob_update"),
        pl.col("__n").sum().cast(pl.Float64).alias("n_update_intervals"))
    return [pm.continuity_rows(hours, events, ints),
            pm.count_tracks(pl.concat(out.split), base, breakdown, "split_tracks")]


def _merged_buckets(scan: _BucketScan, bare: pl.DataFrame, base: pl.DataFrame, breakdown: Sequence[str],
                    cfg: MetricsConfig, fanout: Fanout = serial) -> pl.DataFrame:
    """The merged tracks with the bare rows of every bucket (``bare``, labelled, held whole: one
    row per uncovered expected aircraft-epoch) against each bucket's representative tracks in
    turn (a second pass: a track may lie on a bare aircraft of another bucket), each bucket a
    piece of ``fanout``."""
    schema = scan.schema
    hits = [pl.DataFrame(schema={"method": pl.Categorical, "run": schema["run"], "track_id": schema["track_id"],
                                 **{b: pl.Categorical for b in breakdown}})]
    hits += fanout(_merged_piece, [(scan, k, bare, breakdown, cfg) for k in range(scan.buckets if bare.height else 0)])
    events = pl.concat([h for h in hits if h is not None], how="vertical_relaxed").with_columns(
        pl.col("method").cast(schema["method"]))
    return pm.count_tracks(events, base, breakdown, "merged_tracks")


def _merged_piece(scan: _BucketScan, k: int, bare: pl.DataFrame, breakdown: Sequence[str], cfg: MetricsConfig
                  ) -> pl.DataFrame | None:
    """Bucket ``k``'s tracks that lie on a bare aircraft (a piece of :func:`_merged_buckets`); None: no row."""
    m = scan.matched(k, pm.CONTINUITY_INPUTS)
    if not m.height:
        return None
    trk = pm.rep_points(pm.representatives(m)).with_columns(pl.col("method").cast(pl.Categorical))
    return (pm.merge_hits(bare, trk, cfg, spread_bare=bare.height < trk.height)
            .select("method", "run", "track_id", *breakdown).unique())


def picture_metrics_buckets(matched: pl.LazyFrame, *, expected: pl.LazyFrame | None = None,
                            radar_xy: NDArray[np.float64] | None = None, breakdown: Sequence[str] = BREAKDOWNS,
                            cfg: MetricsConfig = MetricsConfig(), buckets: int = 1,
                            scratch: Path | None = None, fanout: Fanout = serial) -> pl.DataFrame:
    """:func:`picture_metrics` of ``matched.collect()`` (and ``expected.collect()``) with the row
    work done on one of ``buckets`` buckets of aircraft at a time (a long recording's picture is
    never held whole).

    The rows with a truth_id and the expected rows are bucketed by a hash of (run, truth_id):
    every per-aircraft quantity (labels, errors, pm.representatives, exposure, intervals, breaks)
    is exact in its bucket, and each bucket leaves sums per (method, segment, run) that add up.
    Held whole: the per-track table (false tracks, picture hours; one streamed scan of five
    columns) and the bare expected rows for merged tracks, joined in a second pass with each bucket's representative tracks.
    With a ``scratch`` directory the rows are filed by bucket once
    (:func:`tertiary.evaluation.buckets.file_buckets`); without, each bucket filters the whole input.
    Each bucket is a piece of ``fanout``; their partials are combined in bucket order.
    """
    if buckets < 1:
        raise OptionError("must be ≥ 1", option="buckets")
    schema = matched.collect_schema()
    exp_names = None if expected is None else expected.collect_schema().names()
    breakdown = pm.checked_breakdown(schema.names(), exp_names, radar_xy, breakdown, cfg)
    tracks = pm.track_table(pm.track_inputs(matched)).collect(engine="streaming")
    real = tracks.filter(pl.col("__real"))
    methods, base = real.select("method").unique(), real.select("method", "run").unique()
    del real
    merge = exp_names is not None and {"true_x_m", "true_y_m"} <= set(exp_names)
    exp_cols = tuple(c for c in exp_names or () if c in ("run", "truth_id", "epoch") or c.startswith("true_"))
    filed = scratch is not None and buckets > 1
    scan = (_BucketScan.filed(matched, expected, schema, exp_cols, buckets, scratch, fanout) if filed
            else _BucketScan(matched, expected, schema, exp_cols, buckets))
    reads = {*pm.ERROR_INPUTS, *pm.CONTINUITY_INPUTS, "gated_truth_id",
             *(c for c in schema.names() if c.startswith("true_"))}
    out = Partials()
    pieces = [(scan, k, reads, methods, radar_xy, breakdown, cfg, merge) for k in range(buckets)]
    for got in fanout(_bucket_piece, pieces):
        out.add(got)
    parts = [pm.picture_rows(tracks)]
    if out.accuracy:
        parts.append(accuracy_combined(out, breakdown, schema["method"]))
    parts += [identity_combined(name, sums) for name, sums in out.identity.items()]
    if methods.height:
        parts += continuity_combined(out, base, breakdown)
        if merge:
            parts.append(_merged_buckets(scan, pl.concat(out.bare), base, breakdown, cfg, fanout))
    return pm.finish_metrics(parts)
