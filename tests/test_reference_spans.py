"""A time slice of a reference written in pieces reads only the files that can hold its rows
(:mod:`tertiary.evaluation.reference_spans`), and gets the rows a scan of every file gets."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from unittest import mock

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from tertiary.evaluation.evaluate import Reference, write_reference_pieces
from tertiary.evaluation.matching import neighbour_times
from tertiary.evaluation.reference_spans import SPANS_FILE, files_between, read_spans
from tertiary.pipeline.truth_alerts import reference_slice

T0 = datetime(2021, 10, 7, 8, tzinfo=timezone.utc)


def _truth() -> pl.DataFrame:
    """Twenty aircraft sampled every 4 s over 30 min, and one sampled every 400 s (its
    neighbouring samples lie pieces apart), sorted by time as the streamed truth is written."""
    rows = []
    rng = np.random.default_rng(3)
    for k in range(21):
        step = 400 if k == 20 else 4
        t = np.arange(0, 1800, step) + (0 if k == 20 else int(rng.integers(0, 4)))
        n = len(t)
        rows.append(pl.DataFrame({"truth_id": k, "time": [T0 + timedelta(seconds=int(s)) for s in t],
                                  "x_m": rng.normal(0, 1e4, n), "y_m": rng.normal(0, 1e4, n),
                                  "z_m": np.full(n, 3000.0), "vx_mps": np.full(n, 100.0),
                                  "vy_mps": np.zeros(n), "vz_mps": np.zeros(n)}))
    truth = pl.concat(rows).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC"))).sort("time", "truth_id")
    times = neighbour_times(truth)
    return truth.with_columns(times["__prev"], times["__next"])


@pytest.fixture
def reference(tmp_path) -> tuple[pl.DataFrame, Reference]:
    truth = _truth()
    pieces = [truth.slice(k, 600) for k in range(0, truth.height, 600)]
    return truth, Reference(write_reference_pieces(pieces, tmp_path / "reference"))


def _windows() -> list[tuple[datetime, datetime]]:
    return [(T0 + timedelta(seconds=a), T0 + timedelta(seconds=a + w))
            for a in (-60, 0, 413, 901, 1250, 1790, 1900) for w in (0, 59, 300)]


def test_a_matchers_slice_reads_fewer_files_and_gets_the_rows_of_every_file(reference):
    """The matcher's slice (samples inside, and each aircraft's neighbours outside) of the
    pruned files equals that of every file, in the same order, for slices before, inside and
    after the truth. Fails if the files are chosen by their samples' times alone: the sparse
    aircraft's sample before a slice lies in a file of earlier times."""
    truth, ref = reference
    assert len(ref.files) >= 10 and (ref.path / SPANS_FILE).exists()
    every = Reference(ref.path)
    every._spans = None
    fewer = 0
    for t0, t1 in _windows():
        got, want = ref.between(t0, t1), every.between(t0, t1)
        assert_frame_equal(got, want)
        fewer += len(files_between(ref.files, ref._spans, t0, t1, reach=True)) < len(ref.files)
        sparse = want.filter(pl.col("truth_id") == 20)
        if T0 + timedelta(seconds=400) < t0 < T0 + timedelta(seconds=1600):
            assert sparse.height >= 2           # the sparse aircraft's neighbours, pieces apart
    assert fewer >= len(_windows()) - 3


def test_a_truth_pictures_slice_reads_fewer_files_and_gets_the_rows_of_every_file(reference):
    """The truth picture's slice (the samples in [t0, t1]) of the pruned files equals that of
    every file, and the truth's own rows in that time. Fails if a file is kept only when its
    whole time range lies inside the slice."""
    truth, ref = reference
    us = [int((t - datetime(1970, 1, 1, tzinfo=timezone.utc)) / timedelta(microseconds=1))
          for w in _windows() for t in w]
    pruned = reference_slice(ref.files)
    with mock.patch("tertiary.pipeline.truth_alerts.read_spans", return_value=None):
        every = reference_slice(ref.files)              # the same slice, of every file
    for a, b in zip(us[::2], us[1::2]):
        want = truth.filter(pl.col("time").dt.epoch("us").is_between(a, b))
        got = pruned(a, b)
        assert_frame_equal(got, every(a, b))
        assert_frame_equal(got, want.select(got.columns))
    assert len(files_between(ref.files, read_spans(ref.files), us[2], us[3])) < len(ref.files)


def test_files_without_spans_are_all_read(tmp_path):
    """A reference written otherwise (no spans beside its files, or a spans file missing one of
    them) is read whole: nothing is skipped on a guess."""
    files = [tmp_path / f"{k:06d}.parquet" for k in range(3)]
    assert read_spans(files) is None
    (tmp_path / SPANS_FILE).write_text('{"000000.parquet": [0, 1, 0, 1]}')
    assert read_spans(files) is None
    assert files_between(files, None, 5, 6) == files


def test_a_piece_without_a_time_has_no_span():
    """An empty piece (or one whose times are all missing) holds no row of any slice."""
    from tertiary.evaluation.reference_spans import piece_span
    empty = _truth().clear()
    assert piece_span(empty) == [None] * 4
    no_time = _truth().head(3).with_columns(pl.lit(None, pl.Datetime("us", "UTC")).alias("time"))
    assert piece_span(no_time) == [None] * 4
    assert piece_span(_truth().head(1))[0] == piece_span(_truth().head(1))[1]


def test_a_bound_of_another_type_is_an_error_not_a_guess(tmp_path):
    """A numpy time's integer depends on its unit: it is refused, never read as µs."""
    files = [tmp_path / "a.parquet", tmp_path / "b.parquet"]
    spans = [[0, 10, 0, 10], [11, 20, 11, 20]]
    assert files_between(files, spans, 12, 15) == files[1:]
    with pytest.raises(TypeError, match="datetime or µs"):
        files_between(files, spans, np.datetime64("1970-01-01T00:00:00.000012", "ns"), 15)
    assert files_between(files, spans, np.int64(12), np.int64(15)) == files[1:]
