"""Which files of a reference directory a time slice reads.

A long run's reference is a directory of files written a piece at a time
(:func:`~tertiary.evaluation.evaluate.write_reference_pieces`), and the windows read time
slices of it: the matcher's samples every window, the truth picture's and the bound's every
few. A scan of every file opens each file's metadata to skip its row groups, so a slice would
cost more the longer the run (a national day's reference is some 300 files). Beside the files
the writer keeps each file's time range (:data:`SPANS_FILE`), and a slice scans only the files
that can hold one of its rows: the same rows, in the same order, as the scan of every file.
"""

from __future__ import annotations

import json
import numbers
from collections.abc import Sequence
from datetime import datetime, timedelta, timezone
from pathlib import Path

import polars as pl

__all__ = ["SPANS_FILE", "piece_span", "write_spans", "read_spans", "files_between"]

#: beside a reference directory's files: each file's time range (µs)
SPANS_FILE = "spans.json"
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


def piece_span(piece: pl.DataFrame) -> list[int | None]:
    """[first time, last time, earliest of time and ``__prev``, latest of time and ``__next``]
    of a reference piece, in µs (None without a time: no slice reads a row of it)."""
    us = {c: piece[c].dt.epoch("us") for c in ("time", "__prev", "__next") if c in piece.columns}
    t0, t1 = us["time"].min(), us["time"].max()
    if t0 is None:
        return [None] * 4
    lo = min(v for v in (t0, us["__prev"].min() if "__prev" in us else None) if v is not None)
    hi = max(v for v in (t1, us["__next"].max() if "__next" in us else None) if v is not None)
    return [int(t0), int(t1), int(lo), int(hi)]


def write_spans(directory: Path, spans: dict[str, list[int | None]]) -> None:
    """The spans of a directory's files (name → :func:`piece_span`) beside them."""
    (Path(directory) / SPANS_FILE).write_text(json.dumps(spans), encoding="utf-8")


def read_spans(files: Sequence[Path]) -> list[list[int | None]] | None:
    """The spans of ``files`` (one directory's), None when that directory keeps none for every
    one of them (a single reference file, or files written otherwise)."""
    if len(files) < 2:
        return None
    index = Path(files[0]).parent / SPANS_FILE
    try:
        spans = json.loads(index.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    got = [spans.get(Path(f).name) for f in files]
    return None if any(s is None for s in got) else got


def _us(t: datetime | int) -> int:
    """``t`` in µs since the epoch (a time-zone-aware datetime, or µs already)."""
    if isinstance(t, datetime):
        t = t if t.tzinfo is not None else t.replace(tzinfo=timezone.utc)
        return (t - _EPOCH) // timedelta(microseconds=1)
    if isinstance(t, numbers.Integral):         # numpy's integers too
        return int(t)
    raise TypeError(f"a slice's bound is a datetime or µs since the epoch, not {type(t).__name__}")


def files_between(files: Sequence[Path], spans: list[list[int | None]] | None, lo: datetime | int | None,
                  hi: datetime | int | None, reach: bool = False) -> list[Path]:
    """The files that can hold a row of a slice, in order: a sample whose time lies in
    [``lo``, ``hi``] (None: unbounded), or with ``reach`` one whose neighbour times reach into it
    (the matcher's slice, :func:`~tertiary.evaluation.matching.between_expr`). Every file when
    ``spans`` is None; the first alone when none can (a scan of it filtered gives the slice's
    empty frame)."""
    if spans is None:
        return list(files)
    a, b = (2, 3) if reach else (0, 1)
    lo_us = None if lo is None else _us(lo)
    hi_us = None if hi is None else _us(hi)
    keep = [f for f, s in zip(files, spans) if s[0] is not None
            and (lo_us is None or s[b] >= lo_us) and (hi_us is None or s[a] <= hi_us)]
    return keep or list(files[:1])
