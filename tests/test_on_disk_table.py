"""The whole-run view of a streamed table left on disk (:class:`OnDiskTable`): its facts from a
few columns, its pictures read back one at a time, copied by picture only when first read."""

from __future__ import annotations

import threading
from pathlib import Path

import polars as pl
from polars.testing import assert_frame_equal

from parts import NamedParts
from tertiary.pipeline import tables


class _Parts:
    """Window parts as files, as a run's part store holds them."""

    def __init__(self, root: Path, frames: list[pl.DataFrame]) -> None:
        self.dir = root
        self.files = []
        for w, frame in enumerate(frames):
            f = root / f"w={w:06d}.parquet"
            frame.write_parquet(f)
            self.files.append(f)

    def part_files(self, name: str) -> list[Path]:
        return list(self.files)

    def iter_parts(self, name: str):
        for f in self.files:
            yield pl.read_parquet(f)


def _window(w: int, methods: list[str]) -> pl.DataFrame:
    rows = [(0, m, "singer", 10 * w + i, i == 2, float(100 * w + i)) for m in methods for i in range(3)]
    return pl.DataFrame(rows, schema=["run", "method", "filter", "target_id", "tentative", "x_m"], orient="row")


def _copies(table: tables.OnDiskTable) -> list[Path]:
    return sorted(table.dir.rglob("*.parquet"))


def test_pictures_are_copied_by_picture_only_when_one_is_first_read(tmp_path):
    frames = [_window(0, ["b", "a"]), _window(1, []).clear(), _window(2, ["a", "c"]), _window(3, ["b"])]
    table = tables.OnDiskTable(_Parts(tmp_path, frames), "fused", pl.DataFrame())
    whole = pl.concat(frames)
    assert _copies(table) == []
    assert table.height == whole.height and table.pictures == [("b",), ("a",), ("c",)]
    assert table.empty.schema == whole.schema and table.direct is None
    assert table.target_counts == tables.target_counts(whole)
    written = []
    orig = pl.DataFrame.write_parquet

    def counted(self, f, *a, **k):
        written.append(f)
        return orig(self, f, *a, **k)
    pl.DataFrame.write_parquet = counted
    try:
        got: dict[str, pl.DataFrame] = {}
        readers = [threading.Thread(target=lambda m=m: got.__setitem__(m, table.picture((m,))))
                   for m in ("a", "b", "c")]
        for t in readers:
            t.start()
        for t in readers:
            t.join()
    finally:
        pl.DataFrame.write_parquet = orig
    assert len(written) == sum(f.select("method").n_unique() for f in frames if f.height)   # one copy
    for m in ("a", "b", "c"):
        assert_frame_equal(got[m], whole.filter(pl.col("method") == m))
        assert_frame_equal(pl.concat(list(table.blocks((m,), rows=1))), got[m])
    assert table.picture(("z",)).height == 0


def test_one_picture_is_read_where_it_is(tmp_path):
    frames = [_window(0, ["a"]), _window(1, []).clear(), _window(2, ["a"])]
    parts = _Parts(tmp_path, frames)
    table = tables.OnDiskTable(parts, "fused", pl.DataFrame())
    assert table.direct == [parts.files[0], parts.files[2]]
    assert_frame_equal(table.picture(("a",)), pl.concat(frames))
    assert _copies(table) == []


def test_the_facts_the_windows_wrote_give_the_facts_of_their_parts(tmp_path):
    """What the end knows of a fused table (its rows, pictures in order of appearance, pictures
    shown confirmed, targets ever confirmed or only tentative, the confirmed targets) is the
    same from the windows' facts (:func:`tables.window_facts`) as from the parts' columns, and
    the parts are read only for their footers. A window without rows, targets confirmed after
    being tentative, a picture first seen tentative, two runs; a window whose facts are
    missing (an older checkpoint's) makes the end read the parts. Fails if the facts lose the
    order of first appearance, or the rows are counted from the facts."""
    import numpy as np
    rng = np.random.default_rng(4)
    frames = []
    for w in range(6):
        n = 0 if w == 2 else 400
        methods = ["centralized", "information", "arithmetic", "covariance_intersection", "apriori"]
        frames.append(pl.DataFrame({
            "run": rng.integers(0, 2, n).astype(np.uint32), "method": rng.choice(methods[: 2 + w % 4], n),
            "target_id": rng.integers(1, 60, n).astype(np.uint64), "tentative": rng.random(n) < 0.3 + 0.1 * w,
            "x_m": rng.normal(size=n)}))
    facts = [tables.window_facts(f) for f in frames]
    both = NamedParts(tmp_path / "both", {"fused": frames, "fused.facts": facts})
    plain = NamedParts(tmp_path / "plain", {"fused": frames})
    older = NamedParts(tmp_path / "older", {"fused": frames, "fused.facts": [*facts[:3], None, *facts[4:]]})
    read: list[list[str] | None] = []
    orig = pl.read_parquet
    pl.read_parquet = lambda f, *a, **k: read.extend((Path(g).parent.name, k.get("columns"))
                                                     for g in (f if isinstance(f, list) else [f])) or orig(f, *a, **k)
    try:
        got = tables.OnDiskTable(both, "fused", pl.DataFrame())
        assert {name for name, _ in read} == {"fused.facts"}
        want = tables.OnDiskTable(plain, "fused", pl.DataFrame())
        fallback = tables.OnDiskTable(older, "fused", pl.DataFrame())
    finally:
        pl.read_parquet = orig
    whole = pl.concat(frames)
    assert got.height == whole.height and len(got.pictures) == 5
    for t in (got, fallback):
        assert (t.height, t.pictures, t.shown, t.target_counts, t.direct) == \
            (want.height, want.pictures, want.shown, want.target_counts, want.direct)
        assert t.confirmed.sort("run", "target_id").equals(want.confirmed.sort("run", "target_id"))
        assert t.empty.schema == want.empty.schema
