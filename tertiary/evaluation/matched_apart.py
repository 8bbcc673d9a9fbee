"""A picture on disk matched to the truth a stretch of windows at a time, each stretch a piece
of a fanout (:mod:`tertiary.runtime.fanout`): the evaluation of a distributed run's time
slices, which the client would otherwise match alone.

The matcher is per epoch and the row scores per row, so each stretch's rows are those of the
picture matched at once; each stretch spills them to files named in time order. The OSPA,
GOSPA and SIAP state of each stretch is stepped from
:func:`~tertiary.evaluation.multitarget.started` and joined to the stretches before it
(:func:`~tertiary.evaluation.multitarget.then`): one state carried through the picture.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import polars as pl
import pyarrow.parquet as pq

from tertiary.evaluation.evaluate import Reference, match_blocks, match_block, scan_spilled
from tertiary.evaluation.multitarget import MultiTargetState, multitarget_result, started, then
from tertiary.runtime.fanout import Fanout
from tertiary.runtime.windows import window_blocks

__all__ = ["PIECE_ROWS", "PictureFiles"]

#: rows per piece at least (whole window files): a piece costs a dispatch, a read of the
#: reference and its files, so a short recording's picture is one piece (matched on the client)
PIECE_ROWS = 250_000


@dataclass(frozen=True)
class PictureFiles:
    """A picture on disk: its window files in window order, the columns read, what is made of
    each block read (``shape``: e.g. its confirmed targets, or its tracker picture's name), its
    name, the rows per block and where its stretches are matched."""

    name: str
    files: Sequence[Path]
    columns: Sequence[str]
    shape: Callable[[pl.DataFrame], pl.DataFrame]
    block_rows: int
    fanout: Fanout

    def match_apart(self, reference: Reference, cfg, id_col: str, spill: Path, multitarget: bool
                    ) -> tuple[pl.LazyFrame | pl.DataFrame, pl.LazyFrame | pl.DataFrame, pl.DataFrame | None] | None:
        """(matched rows with their row scores, the reference at the picture's epochs, its OSPA,
        GOSPA and SIAP rows when ``multitarget``) of the picture against ``reference`` (a
        reference on disk), or None when it has no row: the result of
        :func:`~tertiary.evaluation.evaluate.match_blocks` with ``spill``. A picture of one
        stretch is matched here as that function does (held in memory when it is one block);
        the stretches of a longer one are the fanout's pieces, their rows spilled and scanned."""
        stretches = _stretches(list(self.files))
        if len(stretches) <= 1:
            return match_blocks(self.blocks(), reference, cfg, id_col, slim=True, spill=spill,
                                 multitarget=multitarget)
        pieces = [(files, list(self.columns), self.shape, self.block_rows, reference.path, cfg, id_col, spill, k,
                   multitarget) for k, files in enumerate(stretches)]
        state, rows = None, 0
        for mt, n in self.fanout(_match_piece, pieces):
            rows += n
            if mt is not None and n:
                state = mt if state is None else then(state, mt)
        if not rows:
            return None
        mt_rows = multitarget_result(state or MultiTargetState(), self.name) if multitarget else None
        return (*(scan_spilled(sorted((spill / k).glob("*.parquet"))) for k in ("matched", "expected")), mt_rows)

    def blocks(self) -> Iterator[pl.DataFrame]:
        """The picture's blocks read here, in time order (its stretches matched in this process)."""
        for _, block in _blocks(list(self.files), list(self.columns), self.shape, self.block_rows):
            yield block


def _stretches(files: list[Path]) -> list[list[Path]]:
    """Consecutive window files of :data:`PIECE_ROWS` rows or more each (but the last), by their
    footers' row counts."""
    out, held, n = [], [], 0
    for f in files:
        held.append(f)
        n += pq.read_metadata(f).num_rows
        if n >= PIECE_ROWS:
            out.append(held)
            held, n = [], 0
    return out + [held] if held else out


def _blocks(files: list[Path], columns: list[str], shape: Callable[[pl.DataFrame], pl.DataFrame], block_rows: int
            ) -> Iterator[tuple[int, pl.DataFrame]]:
    """(index, block) of whole windows' rows (:func:`~tertiary.runtime.windows.window_blocks`),
    shaped; empty blocks skipped."""
    k = 0
    for block in map(shape, window_blocks(files, columns, block_rows)):
        if block.height:
            yield k, block
            k += 1


def _match_piece(files: list[Path], columns: list[str], shape: Callable[[pl.DataFrame], pl.DataFrame],
                 block_rows: int, reference: Path, cfg, id_col: str, spill: Path, piece: int, multitarget: bool
                 ) -> tuple[MultiTargetState | None, int]:
    """One stretch of windows matched block by block (blocks of whole windows, ``block_rows``
    rows or more but the last), its rows spilled as ``<piece>-<block>`` files: (its OSPA, GOSPA
    and SIAP state stepped from :func:`started`, None without them; its rows)."""
    ref = Reference(reference)
    mt = started() if multitarget else None
    rows = 0
    for k, block in _blocks(files, columns, shape, block_rows):
        scored, expected, mt = match_block(block, None, ref, cfg, id_col, mt, True)
        rows += block.height
        for name, frame in (("matched", scored), ("expected", expected)):
            (spill / name).mkdir(parents=True, exist_ok=True)
            frame.write_parquet(spill / name / f"{piece:05d}-{k:05d}.parquet", statistics=False, compression="lz4")
    return mt, rows
