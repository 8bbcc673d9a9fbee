"""The seed metrics of a picture too long to hold whole: :func:`picture_accuracy_buckets` reads
the matched rows a bucket of whole tracks (and of whole aircraft for the coverage walk) at a time,
adds up exactly what crosses buckets, and finishes with the code of
:func:`tertiary.evaluation.accuracy.picture_accuracy`, so the tables are the same.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import polars as pl

from tertiary.contract import TABLES
from tertiary.core.units import STATE
from tertiary.evaluation.accuracy import (ACCURACY_COLUMNS, BY_EPOCH_SCHEMA, FUSION_METRICS, ROW_SCORES,
                                          AccuracyConfig, accuracy_table, aircraft_epochs, by_epoch_table,
                                          continuity_columns, continuity_table, coverage_counts, coverage_table,
                                          empty_metrics, first_seen, metrics_concat, picture_accuracy, pool_epochs,
                                          pooled_means, potential_table, scored_rows, scored_samples, track_counts,
                                          with_segments)
from tertiary.evaluation.buckets import file_buckets
from tertiary.evaluation.consistency import (CONSISTENCY_ALL, Lags, WholeSeries, chi2_band, consistency_rows,
                                             consistency_statistics, series_codes)
from tertiary.runtime.fanout import Fanout, serial

__all__ = ["SeedSums", "picture_accuracy_buckets", "statistic_rows", "table_keys"]

#: what :func:`row_scores` and :func:`picture_accuracy` read of a picture not yet row-scored
_ROW_INPUTS = (*ACCURACY_COLUMNS, "segment", *STATE, *(f"true_{c}" for c in STATE), "alt_m", "true_alt_m", "cov",
               "cov_diag")
#: the row index :func:`picture_accuracy_buckets` gives ``matched``: the order of the samples
_ROW = "__row"


def picture_accuracy_buckets(matched: pl.LazyFrame, stage: str, cfg: AccuracyConfig = AccuracyConfig(),
                             observed: pl.DataFrame | pl.LazyFrame | None = None, buckets: int = 1,
                             scratch: Path | None = None, fanout: Fanout = serial
                             ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """:func:`picture_accuracy` of ``matched.collect()`` (and ``observed`` collected), with the
    rows read ``buckets`` parts at a time, never whole: a long recording's picture (a scan of
    Parquet parts) is scored with the memory of about 1/``buckets`` of its rows, plus the
    scored samples (five columns a row, whole-picture by nature).

    Whole tracks (hash of (method, run, track_id)) make a part: the transient cut, the NEES/NIS
    series, spurious tracks and swaps are per track. Whole aircraft (hash of (run, truth_id))
    make a part of the coverage walk, with ``observed`` cut the same way. What crosses parts is
    added up exactly: the (2.15) sums per (method, segment, epoch, run), the consistency sums per
    epoch and per lag (:class:`Lags`), the counts and sets of runs; then finished by the code of
    :func:`picture_accuracy`. ``matched`` may carry the :data:`ROW_SCORES` (else each part is
    row-scored: :func:`row_scores` is row-wise). With a ``scratch`` directory the rows are filed
    by bucket once (:func:`tertiary.evaluation.buckets.file_buckets`) and each bucket reads its own; without,
    each bucket filters the whole of ``matched``. Each bucket of tracks is a piece of ``fanout``;
    their sums are merged in bucket order."""
    if buckets < 1:
        raise ValueError(f"buckets must be >= 1, got {buckets}")
    schema = matched.collect_schema()          # a scan's schema: no row is read
    wanted = (*ACCURACY_COLUMNS, *ROW_SCORES) if set(ROW_SCORES) <= set(schema.names()) else _ROW_INPUTS
    lf = matched.lazy().with_row_index(_ROW)
    cols = [_ROW, *(c for c in schema.names() if c in wanted)]
    filed = scratch is not None and buckets > 1
    by_track = (file_buckets(lf.select(cols), _bucket_of(_track_key(), buckets), buckets, scratch / "tracks",
                             fanout=fanout)
                if filed else [lf.filter(_in_bucket(_track_key(), buckets, k)).select(cols) for k in range(buckets)])
    parts = SeedSums()
    seen_from = first_seen(observed, schema)
    for got in fanout(_track_piece, [(by_track[k], cfg, seen_from) for k in range(buckets)]):
        parts.merge(got)
    if not parts.rows:
        return picture_accuracy(pl.DataFrame(), stage, cfg)
    coverage = None if observed is None else _coverage_buckets(
        lf, observed, schema["epoch"], parts.tables["tracks"].select("method"), buckets,
        scratch / "aircraft" if filed else None, fanout)
    return parts.finish(stage, cfg, coverage)


def _track_piece(rows: pl.LazyFrame, cfg: AccuracyConfig, seen_from: pl.DataFrame | None) -> "SeedSums":
    """The sums of one bucket of whole tracks (a piece of :func:`picture_accuracy_buckets`)."""
    sums, part = SeedSums(), rows.collect()
    if part.height:
        sums.add_tracks(part, cfg, seen_from)
    return sums


def _in_bucket(key: list[pl.Expr], buckets: int, k: int) -> pl.Expr:
    return pl.lit(True) if buckets == 1 else _bucket_of(key, buckets) == k


def _bucket_of(key: list[pl.Expr], buckets: int) -> pl.Expr:
    return pl.struct(key).hash() % buckets


def _track_key() -> list[pl.Expr]:
    return [pl.col("method"), pl.col("run"), pl.col("track_id")]


def _aircraft_key() -> list[pl.Expr]:
    """(run, truth_id) in the types of :func:`aircraft_epochs`: matched rows and ``observed``
    hash alike."""
    return [pl.col("run").cast(pl.UInt32), pl.col("truth_id").cast(pl.Int64)]


def _coverage_buckets(lf: pl.LazyFrame, observed: pl.DataFrame | pl.LazyFrame, epoch: pl.DataType,
                      methods: pl.DataFrame, buckets: int, scratch: Path | None = None,
                      fanout: Fanout = serial) -> pl.DataFrame:
    """The coverage (completeness, breaks) of the matched rows ``lf`` with whole (run, aircraft)
    walked per bucket (the rows filed by bucket once in ``scratch``, if given), each bucket a
    piece of ``fanout``."""
    seen = aircraft_epochs(observed.lazy(), epoch)
    tracked = lf.filter(pl.col("truth_id").is_not_null())
    by_aircraft = None
    if scratch is not None:
        # each row's bucket as the filter below makes it: hashed before ``run`` is cast
        src = tracked.with_columns(_bucket_of(_aircraft_key(), buckets).alias("__ab"))
        by_aircraft = [f.drop("__ab") for f in
                       file_buckets(continuity_columns(src, "__ab"), pl.col("__ab"), buckets, scratch, fanout=fanout)]
    seen_by = None
    if scratch is not None:         # the aircraft seen, cut once too
        s = seen.with_columns(_bucket_of(_aircraft_key(), buckets).alias("__ab")).collect()
        seen_by = {k: f.drop("__ab") for (k,), f in s.partition_by("__ab", as_dict=True).items()}
        empty = s.drop("__ab").clear()
        del s
    pieces = [(by_aircraft[k] if by_aircraft is not None else
               continuity_columns(tracked.filter(_in_bucket(_aircraft_key(), buckets, k))),
               seen_by.get(k, empty) if seen_by is not None else seen.filter(_in_bucket(_aircraft_key(), buckets, k)),
               methods) for k in range(buckets)]
    return coverage_table(pl.concat(list(fanout(_coverage_piece, pieces))))


def _coverage_piece(rows: pl.LazyFrame, seen: pl.DataFrame | pl.LazyFrame, methods: pl.DataFrame) -> pl.DataFrame:
    """The coverage counts of one bucket of whole aircraft (a piece of :func:`_coverage_buckets`)."""
    return coverage_counts(rows.collect(), seen.lazy().unique().collect(), methods)


def statistic_rows(scored: pl.DataFrame, col: str, ordered: bool = True) -> pl.DataFrame:
    """The rows of a consistency statistic ``col`` (finite values), sorted along each series
    (``ordered``)."""
    r = scored.select("method", "run", "epoch", "track_id", "seg_class", col).filter(
        pl.col(col).is_not_null() & pl.col(col).is_finite())
    return r.sort("method", "run", "track_id", "epoch") if ordered else r


#: the key columns of each :class:`SeedSums` table (every other column adds up, ``__first`` is a
#: minimum); a consistency statistic's tables are named "<prefix>:epochs" and "<prefix>:runs"
_TABLE_KEYS = {"epochs": ("method", "eval_segment", "epoch", "run"), "potential": ("method", "eval_segment"),
               "potential_runs": ("method", "eval_segment", "run"), "tracks": ("method",),
               "track_runs": ("method", "run"), ":epochs": ("method", "eval_segment", "epoch"),
               ":runs": ("method", "eval_segment", "run")}


def table_keys(name: str) -> list[str]:
    """The key columns of the :class:`SeedSums` table ``name``."""
    prefix, colon, kind = name.rpartition(":")
    return list(_TABLE_KEYS[colon + kind if prefix else name])


@dataclass
class SeedSums:
    """What the seed metrics keep of the rows seen (the track buckets of
    :func:`picture_accuracy_buckets`, or the windows of
    :mod:`tertiary.evaluation.accuracy_streamed`): small tables (``tables``: per method,
    segment, epoch and run at most), the per-lag sums of each consistency series set (``lags``:
    (prefix, method, segment) → :class:`Lags`) and the scored samples with their row index."""

    rows: int = 0
    tables: dict[str, pl.DataFrame] = field(default_factory=dict)
    lags: dict[tuple[str, str, str], Lags] = field(default_factory=dict)
    samples: list[pl.DataFrame] = field(default_factory=list)

    def fold(self, name: str, part: pl.DataFrame, keys: list[str]) -> None:
        """Add ``part`` (sums per ``keys``, ``__first`` a minimum; keys only: a set) to ``name``."""
        old = self.tables.get(name)
        both = part if old is None else pl.concat([old, part])
        aggs = [pl.col(c).min() if c == "__first" else pl.col(c).sum() for c in both.columns if c not in keys]
        self.tables[name] = both.group_by(keys).agg(aggs) if aggs else both.unique()

    def merge(self, other: "SeedSums") -> None:
        """Add the sums of rows this has not seen (another run's, or another bucket's)."""
        self.rows += other.rows
        for name, table in other.tables.items():
            self.fold(name, table, table_keys(name))
        for key, lags in other.lags.items():
            self.lags[key] = lags if key not in self.lags else self.lags[key] + lags
        self.samples.extend(other.samples)

    def add_tracks(self, part: pl.DataFrame, cfg: AccuracyConfig, seen_from: pl.DataFrame | None = None) -> None:
        """The partial sums of one bucket of whole tracks (the columns :func:`picture_accuracy` reads);
        ``seen_from``: each aircraft's first reported epoch (:func:`first_seen`)."""
        self.rows += part.height
        m = continuity_columns(part)
        self.fold("tracks", track_counts(m), ["method"])
        self.fold("track_runs", m.select("method", "run").unique(), ["method", "run"])
        del m
        scored = scored_rows(part, cfg, seen_from)
        scored = scored.select(c for c in scored.columns if c in ACCURACY_COLUMNS or c == _ROW)
        self.samples.append(pl.concat([scored.select(_ROW), scored_samples(scored)], how="horizontal"))
        if scored.height:
            self.add_scored(scored)

    def add_scored(self, scored: pl.DataFrame, lags: bool = True) -> None:
        """The partial sums of a bucket's scored rows: (2.15), potential accuracy, consistency
        (``lags``: with the per-lag sums of each series, which need its rows whole)."""
        key = ["method", "eval_segment", "epoch", "run"]
        e2 = [pl.col(c).sum() for c in FUSION_METRICS.values()]
        self.fold("epochs", pl.concat([
            r.group_by(key).agg(*e2, pl.len().alias("n")).filter(pl.col("eval_segment").is_not_null())
            for r in (scored.with_columns(pl.lit("all").alias("eval_segment")),
                      scored.with_columns(pl.col("seg_class").alias("eval_segment")))]), key)
        pot = scored.select("method", "run", "seg_class", "sd_pos", _ROW).filter(pl.col("sd_pos").is_not_null())
        if pot.height:
            pot = with_segments(pot)
            self.fold("potential", pot.group_by("method", "eval_segment").agg(
                pl.col("sd_pos").sum().alias("__sum"), pl.len().alias("__n"), pl.col(_ROW).min().alias("__first")),
                ["method", "eval_segment"])
            self.fold("potential_runs", pot.select("method", "eval_segment", "run").unique(),
                      ["method", "eval_segment", "run"])
        for prefix, (col, _dof) in consistency_statistics(scored.columns).items():
            self.add_statistic(scored, prefix, col, lags)

    def add_statistic(self, scored: pl.DataFrame, prefix: str, col: str, lags: bool = True) -> None:
        """Per-epoch sums and (``lags``) per-lag sums of one NEES/NIS statistic
        (:func:`consistency_metrics`)."""
        # the rows in series order only for the lag sums: the per-epoch sums need no order
        r = statistic_rows(scored, col, ordered=lags)
        if r.is_empty():
            return
        both = with_segments(r)
        self.fold(f"{prefix}:epochs", both.group_by("method", "eval_segment", "epoch").agg(
            pl.col(col).sum().alias("__sum"), pl.len().alias("__n")), ["method", "eval_segment", "epoch"])
        self.fold(f"{prefix}:runs", both.select("method", "eval_segment", "run").unique(),
                  ["method", "eval_segment", "run"])
        del both
        if lags:
            self.add_lags(r, prefix, col)

    def add_lags(self, r: pl.DataFrame, prefix: str, col: str, whole: bool = False) -> None:
        """The per-lag sums of a statistic's rows ``r`` (:func:`statistic_rows`: whole series);
        ``whole``: ``r`` holds every row of its pictures, nothing will be added to them, and τ
        is summed directly (:class:`WholeSeries`)."""
        for method in r["method"].unique().to_list():
            m = r.filter(pl.col("method") == method)
            for seg in ["all", *m["seg_class"].drop_nulls().unique().to_list()]:
                g = m if seg == "all" else m.filter(pl.col("seg_class") == seg)
                lags = (WholeSeries if whole else Lags).of(g[col].to_numpy(), series_codes(g, "track_id"))
                old = self.lags.get((prefix, method, seg))
                self.lags[(prefix, method, seg)] = lags if old is None else old + lags

    def finish(self, stage: str, cfg: AccuracyConfig, coverage: pl.DataFrame | None
               ) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
        """:func:`picture_accuracy`'s three tables from the sums of every bucket."""
        metrics, by_epoch = self.tables_of(stage, cfg, coverage)
        return metrics, by_epoch, pl.concat(self.samples).sort(_ROW).drop(_ROW)

    def tables_of(self, stage: str, cfg: AccuracyConfig, coverage: pl.DataFrame | None
                  ) -> tuple[pl.DataFrame, pl.DataFrame]:
        """(the seed metrics, the per-epoch accuracy) from the sums (``tables`` ``tracks`` and
        ``track_runs``: :func:`continuity_table`'s inputs)."""
        t = self.tables
        accuracy, by_epoch = empty_metrics(), pl.DataFrame(schema=BY_EPOCH_SCHEMA)
        if "epochs" in t:
            e = t["epochs"]
            if e["run"].n_unique() == 1:       # a row per epoch already: no copy of a long run's epochs
                agg = e.drop("run").with_columns(pl.lit(1, pl.UInt32).alias("n_runs"))
            else:
                agg = e.group_by("method", "eval_segment", "epoch").agg(
                    *[pl.col(c).sum() for c in FUSION_METRICS.values()], pl.col("n").sum(), pl.len().alias("n_runs"))
            runs = e.group_by("method", "eval_segment").agg(pl.col("run").n_unique().alias("n_runs"))
            accuracy = accuracy_table(pooled_means(agg, ["method", "eval_segment"], cfg), runs, stage)
            whole = agg.filter(pl.col("eval_segment") == "all").drop("eval_segment")
            by_epoch = by_epoch_table(pool_epochs(whole, ["method"], cfg))
        out = [accuracy]
        if "potential" in t:
            out.append(potential_table(self._potential(), stage))
        for prefix, (_col, dof) in CONSISTENCY_ALL.items():
            if f"{prefix}:epochs" in t:
                out.append(self._statistic(prefix, dof, stage, cfg.band))
        out.append(continuity_table(t["tracks"], t["track_runs"], coverage, stage))
        return metrics_concat(out), by_epoch

    def _potential(self) -> pl.DataFrame:
        """(method, eval_segment, value, n_runs) in :func:`picture_accuracy`'s order of appearance:
        segment ``all`` first, then each group by its first row."""
        n_runs = self.tables["potential_runs"].group_by("method", "eval_segment").agg(
            pl.col("run").n_unique().alias("n_runs"))
        return (self.tables["potential"].join(n_runs, on=["method", "eval_segment"], how="left")
                .sort(pl.col("eval_segment") != "all", "__first")
                .select("method", "eval_segment", (pl.col("__sum") / pl.col("__n")).alias("value"), "n_runs"))

    def _statistic(self, prefix: str, dof: int, stage: str, band: float) -> pl.DataFrame:
        """:func:`consistency_metrics` of one statistic from its sums."""
        epochs = self.tables[f"{prefix}:epochs"]
        n_runs = {(m, s): n for m, s, n in self.tables[f"{prefix}:runs"].group_by("method", "eval_segment")
                  .agg(pl.col("run").n_unique()).iter_rows()}
        # each epoch's mean against the band of its count: the band once per distinct count (an
        # iterative quantile), every picture's epochs in one query, not a copy of them per picture
        counts = epochs["__n"].unique()
        lo, hi = chi2_band(counts.to_numpy(), dof, band)
        mean_k = pl.col("__sum") / pl.col("__n")
        inside = ((mean_k >= pl.col("__n").replace_strict(counts, lo, return_dtype=pl.Float64))
                  & (mean_k <= pl.col("__n").replace_strict(counts, hi, return_dtype=pl.Float64)))
        in_band = {(m, s): v for m, s, v in epochs.select("method", "eval_segment", inside.alias("__in")).group_by(
            "method", "eval_segment").agg(pl.col("__in").mean()).iter_rows()}
        out = []
        for method, seg in sorted(k[1:] for k in self.lags if k[0] == prefix):
            lags = self.lags[(prefix, method, seg)]
            out += consistency_rows(stage, method, seg, prefix, dof, band, lags.total / lags.n,
                                    in_band.get((method, seg), math.nan), lags.n, lags.tau(), n_runs[(method, seg)])
        return pl.DataFrame(out, schema=TABLES["metrics"].required)
