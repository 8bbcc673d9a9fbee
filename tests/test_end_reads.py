"""What the end of a run reads of its windows' parts: groups of parts read at once, and the safety
picture's id map read once for every picture."""

from __future__ import annotations

from datetime import datetime, timedelta
from types import SimpleNamespace

import numpy as np
import polars as pl
from polars.testing import assert_frame_equal

from safety import alerts as safety_alerts
from tertiary.evaluation.streamed import ID_ROWS, matched_table
from tertiary.pipeline.scoring import WindowedPictures
from tertiary.runtime.windows import concat_parts, read_part_groups

from parts import NamedParts


def test_parts_read_in_groups_are_the_parts_in_their_order(tmp_path):
    """Groups of parts read at once give every part's rows once, in file order, a group at most
    ``group`` files; a group holding a part whose column has another type or that lacks one
    comes a file at a time with the columns each has. Fails if a group's files are
    skipped or read twice, if the order changes, or if a mismatched group raises."""
    rng = np.random.default_rng(5)
    frames = [pl.DataFrame({"w": np.full(n, w, np.int64), "x": rng.normal(size=n)}) for w, n in
              enumerate([4, 0, 3, 5, 2, 6, 1])]
    frames[4] = pl.DataFrame({"w": [4, 4], "x": ["a", "b"]})
    frames[6] = frames[6].drop("x")
    parts = NamedParts(tmp_path, {"t": frames})
    files = parts.part_files("t")
    got = list(read_part_groups(files, ["w", "x"], group=3))
    # the first group reads at once; the other two hold a mismatched part: a file at a time
    assert [f.height for f in got] == [7, 5, 2, 6, 1]
    assert got[-1].columns == ["w"]
    want = concat_parts([pl.read_parquet(f) for f in files])
    assert_frame_equal(concat_parts(got), want)
    whole = list(read_part_groups(files[:4], group=3))
    assert [f.height for f in whole] == [7, 5]


def _id_blocks(rng: np.random.Generator, names: list[str], windows: int) -> list[pl.DataFrame]:
    """Blocks of an id map (one per window) of the pictures ``names``, rows in no picture order,
    with duplicate (epoch, id) rows whose first must stay first."""
    t0 = datetime(2026, 1, 1)
    out = []
    for w in range(windows):
        n = 60
        epochs = [t0 + timedelta(seconds=10 * w + int(s)) for s in rng.integers(0, 10, n)]
        out.append(pl.DataFrame({
            "run": np.zeros(n, np.uint32), "method": rng.choice(names, n), "epoch": epochs,
            "track_id": rng.integers(1, 8, n).astype(np.uint64),
            "truth_id": pl.Series(rng.integers(0, 5, n), dtype=pl.Int64)}).with_columns(
            pl.when(pl.col("truth_id") == 0).then(None).otherwise(pl.col("truth_id")).alias("truth_id"),
            pl.col("epoch").cast(pl.Datetime("us", "UTC"))))
    return out


def test_the_id_map_read_once_is_the_evaluations_picture_by_picture(tmp_path):
    """The safety picture's id map read once from the blocks the windows reduced equals the one the
    evaluation builds picture by picture (:func:`safety.alerts.id_rows` of each picture's blocks,
    concatenated in its order of pictures, a picture without a matched row skipped). Fails if the
    pictures come in another order or if a picture without rows is kept."""
    rng = np.random.default_rng(11)
    names = ["c+x", "a+x", "d+x", "b+x"]
    blocks = _id_blocks(rng, ["a+x", "b+x", "c+x", "d+x"], 4)
    whole = pl.concat(blocks)
    keys = whole.filter(pl.col("track_id") <= 3).select("run", "method", "epoch", "track_id").unique()
    parts = NamedParts(tmp_path, {ID_ROWS: blocks, matched_table("track_id-1"): [whole.head(1)]})
    groups = {"a+x": ["track_id-1"], "b+x": ["track_id-1"], "c+x": ["track_id-1"], "d+x": ["track_id-2"]}
    pictures = WindowedPictures(parts, SimpleNamespace(groups=groups), surveillance=False, id_rows="track_id")
    got = pictures.id_map(names, keys, "track_id")
    want = pl.concat([safety_alerts.id_rows(whole.lazy().filter(pl.col("method") == name), keys=keys,
                                            id_col="track_id").collect() for name in names if name != "d+x"])
    assert got.height > 0 and "d+x" not in got["method"].to_list()
    assert_frame_equal(got, want)
    assert pictures.id_map(names, keys, "target_id") is None        # not the column the windows reduced
