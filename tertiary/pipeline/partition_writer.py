"""A partition's sink on a Dask worker (:mod:`tertiary.pipeline.dask_engine`): each window's kept
rows, and the warm-up rows the stitching reads, written as Parquet parts of the partition."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from tertiary.pipeline.tables import PartTrim
from tertiary.runtime.windows import Window
from tertiary.store.run_store import write_parquet_atomic

__all__ = ["EPOCH_TABLES", "SCRATCH", "SLICES", "STITCHED", "PartitionWriter", "read_part", "slice_files"]

#: tables stitched across slice boundaries (their warm-up rows are kept aside for matching)
STITCHED = ("associations", "fused", "clusters", "tracks")
#: tables whose rows belong to a slice by epoch (the others by report time)
EPOCH_TABLES = ("aligned", "associations", "fused", "clusters", "tracks", "conflicts", "curve_rows")
#: the scratch files of a partition, and of the client's finalize stage beside the partitions
SCRATCH = "_scratch"
#: the partitions' folder of a distributed run's output: ``slices/<i>/{kept,overlap}/<table>/w=<k>.parquet``
SLICES = "slices"


class PartitionWriter:
    """A partition's sink for :func:`tertiary.pipeline.stream`: each window's kept rows (and the
    warm-up rows of the stitched tables) as Parquet parts; rejects' ``row_index`` made the row of
    the whole input; association counts taken between the slice's boundaries. ``part``: the
    :class:`~tertiary.pipeline.dask_engine.Partition` it writes."""

    def __init__(self, out: Path, part: Any, rowmap: pl.DataFrame, windowed: bool,
                 trim: PartTrim | None = None) -> None:
        self.out, self.part, self.windowed, self.trim = out, part, windowed, trim
        self.g = rowmap["__g"].to_numpy()
        self.t = rowmap["__t"].to_numpy()
        self.t_null = rowmap["__t"].is_null().to_numpy()
        self.rows: dict[str, int] = {}
        self.c0: dict = {}
        self.c1: dict | None = None
        self.last: dict = {}
        shutil.rmtree(out, ignore_errors=True)

    def write(self, w: Window, outputs: dict[str, pl.DataFrame]) -> None:
        for name, frame in outputs.items():
            if frame.width == 0:
                continue
            frame = frame if self.trim is None else self.trim(name, frame)
            kept, aside = self._split(name, frame)
            for sub, f in (("kept", kept), ("overlap", aside)):
                if f is None or (sub == "overlap" and f.height == 0):
                    continue
                d = self.out / sub / name
                d.mkdir(parents=True, exist_ok=True)
                # named by the window's index, as a local run's parts are (the stages that read
                # their stored windows back find them by it); the radars' prologue is w=-00001
                write_parquet_atomic(f, d / f"w={w.index:06d}.parquet", compression="zstd")
                if sub == "kept":
                    self.rows[name] = self.rows.get(name, 0) + f.height

    def part_files(self, name: str) -> list[Path]:
        """The files of the windows' kept rows of ``name`` written so far, in window order."""
        return sorted((self.out / "kept" / name).glob("w=*.parquet"))

    def scratch(self) -> Path:
        """A directory for the partition's scratch files (its truth as a reference file)."""
        d = self.out / SCRATCH
        d.mkdir(parents=True, exist_ok=True)
        return d

    def checkpoint(self, w: Window, state: Any, **info: Any) -> None:
        counts = {k: v for k, v in state.counts.items() if not k.startswith("_")}
        if w.t1_us == self.part.t0_us:
            self.c0 = counts
        if w.t1_us == self.part.t1_us:
            self.c1 = counts
        self.last = counts

    def counts(self) -> dict[str, int]:
        """Association counts of the kept span (whole input when windows do not meet the bounds)."""
        end = self.c1 if self.c1 is not None else self.last
        return {k: int(end.get(k, 0)) - int(self.c0.get(k, 0)) for k in end}

    def _split(self, name: str, frame: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame | None]:
        p = self.part
        if name == "rejects":
            return self._rejects(frame), None
        if name == "reports":
            t = pl.col("time").dt.epoch("us")
            return frame.filter((t >= p.t0_us) & (t < p.t1_us)), None
        if name not in EPOCH_TABLES or frame.height == 0:
            return frame, (frame.clear() if name in STITCHED else None)
        e = pl.col("epoch").dt.epoch("us")
        kept = frame.filter((e >= p.t0_us) & (e < p.t1_us))
        aside = frame.filter((e >= p.t0_us - p.warm_us) & (e < p.t0_us)) if name in STITCHED and p.warm_us else None
        return kept, aside

    def _rejects(self, frame: pl.DataFrame) -> pl.DataFrame:
        """Rejects of the partition's reports with the row of the whole input; radar rejects only
        in partition 0; a report's reject kept where its time is (null time: the first slice)."""
        p = self.part
        if frame.height == 0:
            return frame
        is_rep = (frame["input_table"] == "reports").to_numpy()
        keep = np.where(is_rep, True, p.index == 0)
        if is_rep.any():
            local = frame["row_index"].to_numpy()
            ok = is_rep & (local < len(self.g))
            li = np.where(ok, local, 0).astype(np.int64)
            t, tnull = self.t[li], self.t_null[li]
            inside = np.where(tnull, p.first_slice, (t >= p.t0_us) & (t < p.t1_us))
            keep &= np.where(is_rep, inside, True)
            frame = frame.with_columns(pl.Series("row_index", np.where(ok, self.g[li], local).astype(np.uint64)))
        return frame.filter(pl.Series(keep))


def slice_files(out: Path, part: int, sub: str, name: str) -> list[Path]:
    """The parts of table ``name`` partition ``part`` wrote (``sub``: kept or overlap), in window order."""
    return sorted((out / SLICES / str(part) / sub / name).glob("w=*.parquet"))


def read_part(out: Path, part: int, name: str, sub: str = "kept", columns: list[str] | None = None
              ) -> pl.DataFrame | None:
    """Partition ``part``'s rows of ``name`` (``columns``: those it has), None when it wrote none."""
    files = slice_files(out, part, sub, name)
    if not files:
        return None
    frames = [pl.read_parquet(f, columns=None if columns is None else
                              [c for c in columns if c in pl.read_parquet_schema(f)]) for f in files]
    return frames[0] if len(frames) == 1 else pl.concat(frames, how="diagonal_relaxed")
