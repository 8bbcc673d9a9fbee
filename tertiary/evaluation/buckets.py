"""A long picture's rows filed once by bucket: the evaluation's buckets read their own rows
only.

:func:`~tertiary.evaluation.accuracy_buckets.picture_accuracy_buckets` and
:func:`~tertiary.evaluation.picture_buckets.picture_metrics_buckets` compute a spilled picture's metrics a
bucket of whole tracks or whole aircraft at a time. Were each bucket to filter the whole spilled
picture, a picture of n rows in ⌈n / 150 000⌉ buckets would be read that many times: quadratic in
the recording's length. :func:`file_buckets` reads the rows once, a slice at a time, and writes each slice's rows of
bucket k to ``where/b=k/``; bucket k is then a scan of its own files, its rows in the input's
order.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import polars as pl

from tertiary.runtime.fanout import Fanout, serial

#: rows of the input filed at a time (the memory of the filing pass)
FILE_SLICE_ROWS = 500_000


def file_buckets(lf: pl.LazyFrame, bucket: pl.Expr, buckets: int, where: Path,
                 slice_rows: int | None = None, fanout: Fanout = serial) -> list[pl.LazyFrame]:
    """``lf``'s rows in ``buckets`` lazy frames: row r goes to the frame ``bucket`` (an
    expression with values in [0, buckets)) gives it, rows kept in ``lf``'s order. ``lf`` is
    read once, ``slice_rows`` (default :data:`FILE_SLICE_ROWS`) at a time, and filed as Parquet
    under ``where`` (emptied first; the caller removes it), LZ4-compressed: scratch is read once,
    and zstd's encoding is a third of the filing's time. Each slice is a piece of ``fanout``
    (slices are independent: slice g writes its rows of bucket k as ``b=k/g``)."""
    slice_rows = FILE_SLICE_ROWS if slice_rows is None else slice_rows
    shutil.rmtree(where, ignore_errors=True)
    where.mkdir(parents=True)
    schema = lf.collect_schema()
    n = lf.select(pl.len()).collect().item()
    filed = sum(fanout(_file_slice, [(lf, bucket, off, slice_rows, g, where)
                                     for g, off in enumerate(range(0, n, slice_rows))]))
    if filed != n:          # a slice read short (its input changed under it): never score a part
        raise RuntimeError(f"filing by bucket read {filed} of {n} rows under {where}")
    out = []
    for k in range(buckets):
        files = sorted((where / f"b={k:06d}").glob("*.parquet"))
        out.append(pl.scan_parquet(files, schema=schema) if files else pl.LazyFrame(schema=schema))
    return out


def _file_slice(lf: pl.LazyFrame, bucket: pl.Expr, off: int, rows: int, g: int, where: Path) -> int:
    """Slice ``g`` of ``lf`` (its ``rows`` rows from ``off``) filed by bucket; its row count."""
    chunk = lf.slice(off, rows).with_columns(bucket.cast(pl.Int64).alias("__bucket")).collect()
    for (k,), part in chunk.partition_by("__bucket", as_dict=True, maintain_order=True).items():
        d = where / f"b={int(k):06d}"
        d.mkdir(exist_ok=True)
        part.drop("__bucket").write_parquet(d / f"{g:06d}.parquet", statistics=False, compression="lz4")
    return chunk.height
