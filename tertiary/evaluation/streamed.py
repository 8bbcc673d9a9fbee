"""The evaluation's matching as a streamed step: each window's pictures are matched to the
reference and row-scored as they are made (:func:`match_window`), each picture's multi-target
state, every picture's seed metrics (:mod:`tertiary.evaluation.accuracy_streamed`) and its
surveillance metrics (:mod:`tertiary.evaluation.picture_streamed`), one step a window each,
carried from window to window. What is left for the end of the run is to finish them
(:class:`~tertiary.evaluation.evaluate.Matched`).

The matcher is per epoch and the row scores per row, so the rows of a run stepped window by
window are those of the whole run matched at once. Pictures of one id column and one schema are
matched in one call (the matcher's groups are (run, picture, epoch)) and written as one table
(``matched.<group>``, ``expected.<group>``, a picture's rows told by ``method``): a window costs a
few calls and files, not one per picture."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.evaluation import accuracy_streamed, multitarget, picture_streamed
from tertiary.evaluation.accuracy_streamed import SCORED_ROWS, SeedState, Walk, seed_rows, seed_step, walk_step
from tertiary.evaluation.evaluate import MULTITARGET_TRUTH, EvaluationConfig, Reference, metric_columns, match_block
from tertiary.evaluation.matching import picture_epochs, reference_at_epochs
from tertiary.evaluation.multitarget import MultiTargetState, multitarget_steps
from tertiary.evaluation.picture_streamed import PictureStepState, picture_step

__all__ = ["MatchState", "match_window", "merge_runs", "matched_table", "expected_table", "SCORED", "PICTURE_VALUES",
           "ID_ROWS"]

#: the window output of every picture's scored rows (:data:`~tertiary.evaluation.accuracy_streamed.SCORED_ROWS`)
SCORED = "scored"
#: the window output of the surveillance metrics' percentile sketch counts (the ``values`` sums of
#: :class:`~tertiary.evaluation.picture_streamed.PictureStepState`): they add up, so each window
#: writes its own instead of carrying them (a state pickled at every window)
PICTURE_VALUES = "picture_values"
#: the window output of the safety pictures' id map, reduced to the rows the alert scoring may
#: read (:func:`safety.alerts.block_id_rows`): the end reads these, not every matched row
ID_ROWS = "id_rows"


def matched_table(group: str) -> str:
    """The name of a group's matched, row-scored rows among a window's outputs."""
    return f"matched.{group}"


def expected_table(group: str) -> str:
    """The name of the reference at the epochs of a group's pictures (column ``method``)."""
    return f"expected.{group}"


def _group(id_col: str, schema: pl.Schema) -> str:
    """A stable name for the pictures of one id column and one schema."""
    return f"{id_col}-{hashlib.sha1(repr(list(schema.items())).encode()).hexdigest()[:12]}"


@dataclass(frozen=True)
class MatchState:
    """Each picture's :class:`~tertiary.evaluation.multitarget.MultiTargetState` and the groups
    its rows were written in, by name; every picture's seed metrics so far
    (:class:`~tertiary.evaluation.accuracy_streamed.SeedState`) and the run's coverage walk
    (``walk``; None: the seed metrics are not stepped, the run's aligned rows carry no
    aircraft)."""

    pictures: dict[str, MultiTargetState] = field(default_factory=dict)
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    seed: SeedState = field(default_factory=SeedState)
    walk: Walk | None = field(default_factory=Walk)
    #: every picture's surveillance metrics so far (:mod:`tertiary.evaluation.picture_streamed`);
    #: None: not stepped (a checkpoint written without them: the end computes them)
    metrics: PictureStepState | None = field(default_factory=PictureStepState)
    #: merged from runs stepped apart (:func:`merge_runs`): the windows' per-epoch sums of
    #: different parts may share an epoch (one run's windows never do)
    runs_apart: bool = False


def merge_runs(states: Sequence[MatchState]) -> MatchState:
    """The evaluation's state over runs stepped apart, each state holding runs of its own (a
    distributed run's partitions, one Monte-Carlo run each): runs never share a track, an
    aircraft's walk or a segment, so each part of the state is the union of theirs, its sums
    added up. The windows' outputs of every part (matched rows, per-epoch sums, sketch counts)
    are read with it (:class:`tertiary.pipeline.scoring.WindowedPictures`)."""
    states = list(states)
    if len(states) == 1:
        return states[0]
    names = list(dict.fromkeys(n for s in states for n in s.pictures))
    pictures = {n: multitarget.merge_runs([s.pictures[n] for s in states if n in s.pictures]) for n in names}
    groups: dict[str, tuple[str, ...]] = {}
    for s in states:
        for name, gs in s.groups.items():
            groups[name] = tuple(dict.fromkeys((*groups.get(name, ()), *gs)))
    seed, walk = accuracy_streamed.merge_runs([s.seed for s in states], [s.walk for s in states])
    stepped = [getattr(s, "metrics", None) for s in states]
    metrics = None if any(m is None for m in stepped) else picture_streamed.merge_runs(stepped)
    return MatchState(pictures, groups, seed, walk, metrics, runs_apart=True)


def match_window(state: MatchState, pictures: Sequence[tuple[str, str, pl.DataFrame]], reference: Reference,
                 cfg: EvaluationConfig, multitarget: bool, observed: pl.DataFrame | None = None,
                 radar_xy: NDArray[np.float64] | None = None) -> tuple[dict[str, pl.DataFrame], MatchState]:
    """The matched rows (only the columns the metrics read) and the reference at the epochs of
    each picture (name, id column, its rows in the window), by group; a group seen before but
    not in this window gives empty tables, a picture without a row keeps its state.
    ``multitarget``: the OSPA, GOSPA and SIAP states are stepped. ``observed``: the window's
    (run, epoch, truth_id) of the aligned reports; with it each picture's seed metrics are
    stepped and their scored rows written (:data:`SCORED`); None, in any window: not. With
    ``multitarget`` the surveillance metrics are stepped too (``radar_xy``: the radar sites in
    the system frame, for the range breakdown)."""
    carried, where, seed, walk = dict(state.pictures), dict(state.groups), state.seed, state.walk
    metrics = getattr(state, "metrics", None)
    out = {t(g): pl.DataFrame() for gs in where.values() for g in gs for t in (matched_table, expected_table)}
    walk_rows = None
    if walk is not None and observed is not None:
        walk_rows, walk = walk_step(walk, observed)
    else:
        seed, walk = SeedState(), None
    to_seed = []
    groups: dict[str, tuple[str, list[tuple[str, pl.DataFrame]]]] = {}
    for name, id_col, rows in pictures:
        if rows.height:
            groups.setdefault(_group(id_col, rows.schema), (id_col, []))[1].append((name, rows))
    epochs = [e for _, named in groups.values() for _, rows in named for e in (rows["epoch"].min(),
                                                                              rows["epoch"].max())]
    # the reference samples every picture of the window reads, sliced once (a superset of any
    # one picture's: the matcher reads only the samples about each of its epochs)
    truth = reference.between(min(epochs), max(epochs), cfg.match.ended_s) if epochs else None
    # the pictures of a window share their epochs (the fused picture and its trackers'): the
    # reference at them is interpolated once for every group
    at = (reference_at_epochs(pl.concat([picture_epochs(r) for _, named in groups.values() for _, r in named])
                              .unique(), truth, cfg.match.max_gap_s) if len(groups) > 1 else None)
    blocks, surveyed = [], []
    for group, (id_col, named) in groups.items():
        rows = named[0][1] if len(named) == 1 else pl.concat([r for _, r in named], how="vertical")
        scored, expected, _ = match_block(rows, truth, reference, cfg, id_col, None, slim=True, expected=at)
        del rows
        seen_all = []
        for name, _ in named:
            mine = scored.filter(pl.col("method") == name) if len(named) > 1 else scored
            seen = expected.join(mine.select("run", "epoch").unique(), on=["run", "epoch"], how="semi",
                                 maintain_order="left") if len(named) > 1 else expected
            seen_all.append(seen.with_columns(pl.lit(name).alias("method")))
            if walk_rows is not None:
                to_seed.append(seed_rows(mine, id_col))
            if group not in where.get(name, ()):
                where[name] = (*where.get(name, ()), group)
            blocks.append((name, mine.select("run", "epoch", pl.col(id_col).alias("track_id"), "x_m", "y_m", "z_m"),
                           seen.select(MULTITARGET_TRUTH)))
        out[matched_table(group)] = scored
        out[expected_table(group)] = pl.concat(seen_all, how="vertical")
        if multitarget:         # what the surveillance metrics read, the id column as track_id
            keep = set(metric_columns(scored))
            slim = scored.select(c for c in scored.columns if c == id_col or c in keep)
            surveyed.append(slim.rename({id_col: "track_id"}) if id_col != "track_id" else slim)
    if walk_rows is not None:
        # one step for every picture of the window (their rows told by ``method``)
        rows = pl.concat(to_seed, how="diagonal_relaxed") if to_seed else pl.DataFrame()
        if rows.height:
            out[SCORED], epoch_sums, seed = seed_step(seed, rows, walk_rows, walk, cfg.accuracy)
            out.update(epoch_sums)
        else:
            out[SCORED] = pl.DataFrame(schema=SCORED_ROWS)
    if multitarget:
        carried = multitarget_steps(carried, blocks, cfg.multitarget)
        if surveyed and metrics is not None:    # one step for every group: a frame per schema
            seen = pl.concat([out[expected_table(g)] for g in groups], how="diagonal_relaxed")
            metrics = picture_step(metrics, surveyed, seen, radar_xy, cfg.metrics)
            values = metrics.sums.get("values")
            if values:
                out[PICTURE_VALUES] = values[0]
                metrics = replace(metrics, sums={k: v for k, v in metrics.sums.items() if k != "values"})
    return out, MatchState(carried, where, seed, walk, metrics)
