"""The evaluation's matching as a streamed step: each window's pictures are matched to the
reference and row-scored as they are made (:func:`match_window`), each picture's multi-target
state carried from window to window. What is left for the end of the run is the reduction of
the matched rows to metrics (:class:`~tertiary.evaluation.evaluate.Matched`).

The matcher is per epoch and the row scores per row, so the rows of a run stepped window by
window are those of the whole run matched at once."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import polars as pl

from tertiary.evaluation.evaluate import MULTITARGET_TRUTH, EvaluationConfig, Reference, match_block
from tertiary.evaluation.multitarget import MultiTargetState, multitarget_steps

__all__ = ["MatchState", "match_window", "matched_table", "expected_table"]


def matched_table(picture: str) -> str:
    """The name of a picture's matched, row-scored rows among a window's outputs."""
    return f"matched.{picture}"


def expected_table(picture: str) -> str:
    """The name of the reference at a picture's epochs among a window's outputs."""
    return f"expected.{picture}"


@dataclass(frozen=True)
class MatchState:
    """Each picture's :class:`~tertiary.evaluation.multitarget.MultiTargetState`, by name."""

    pictures: dict[str, MultiTargetState] = field(default_factory=dict)


def match_window(state: MatchState, pictures: Sequence[tuple[str, str, pl.DataFrame]], reference: Reference,
                 cfg: EvaluationConfig, multitarget: bool) -> tuple[dict[str, pl.DataFrame], MatchState]:
    """The matched rows (only the columns the metrics read) and the reference at the epochs of
    each picture (name, id column, its rows in the window); a picture without a row gives empty
    tables and keeps its state. ``multitarget``: the OSPA, GOSPA and SIAP state is stepped.

    Pictures of one id column and one schema are matched in one call (the matcher's groups are
    (run, picture, epoch)): a window's cost is a few calls, not one per picture."""
    out: dict[str, pl.DataFrame] = {}
    carried = dict(state.pictures)
    groups: dict[tuple, list[tuple[str, pl.DataFrame]]] = {}
    for name, id_col, rows in pictures:
        out[matched_table(name)] = out[expected_table(name)] = pl.DataFrame()
        if rows.height:
            groups.setdefault((id_col, tuple(rows.schema.items())), []).append((name, rows))
    epochs = [e for named in groups.values() for _, rows in named for e in (rows["epoch"].min(), rows["epoch"].max())]
    # the reference samples every picture of the window reads, sliced once (a superset of any
    # one picture's: the matcher reads only the samples about each of its epochs)
    truth = reference.between(min(epochs), max(epochs)) if epochs else None
    blocks = []
    for (id_col, _), named in groups.items():
        rows = named[0][1] if len(named) == 1 else pl.concat([r for _, r in named], how="vertical")
        scored, expected, _ = match_block(rows, truth, reference, cfg, id_col, None, slim=True)
        del rows
        for name, _ in named:
            mine = scored.filter(pl.col("method") == name) if len(named) > 1 else scored
            seen = expected.join(mine.select("run", "epoch").unique(), on=["run", "epoch"], how="semi",
                                 maintain_order="left") if len(named) > 1 else expected
            out[matched_table(name)], out[expected_table(name)] = mine, seen
            blocks.append((name, mine.select("run", "epoch", pl.col(id_col).alias("track_id"), "x_m", "y_m", "z_m"),
                           seen.select(MULTITARGET_TRUTH)))
    if multitarget:
        carried = multitarget_steps(carried, blocks, cfg.multitarget)
    return out, MatchState(carried)
