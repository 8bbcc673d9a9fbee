"""Window parts written as a run's part store writes them, for the tests of what the end of a run
reads of them."""

from __future__ import annotations

from pathlib import Path

import polars as pl


class NamedParts:
    """Window parts as files, a directory per table and a file per window (``w=NNNNNN``); a None
    frame: that window wrote no part of that table."""

    def __init__(self, root: Path, tables: dict[str, list[pl.DataFrame | None]]) -> None:
        self.dir = root
        for name, frames in tables.items():
            (root / name).mkdir(parents=True)
            for w, frame in enumerate(frames):
                if frame is not None:
                    frame.write_parquet(root / name / f"w={w:06d}.parquet")

    def part_files(self, name: str) -> list[Path]:
        return sorted((self.dir / name).glob("w=*.parquet"))

    def iter_parts(self, name: str):
        for f in self.part_files(name):
            yield pl.read_parquet(f)
