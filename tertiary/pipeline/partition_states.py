"""What the partitions of a distributed run return besides their parts, and how the client
merges it (:mod:`tertiary.pipeline.dask_engine`): each partition's association score, in its own
ids, relabelled with the stitched ids and merged in time order; each whole run's evaluation
state and lag sums, merged across runs (runs share no id)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tertiary.evaluation import lags_streamed, streamed
from tertiary.evaluation.association import AssociationScore, merge_association_scores, relabel_association_score

__all__ = ["merged_evaluation", "merged_lags", "merged_scores"]


def merged_scores(parts: Sequence[Any], infos: Sequence[dict], maps: dict[int, dict]) -> AssociationScore | None:
    """The association metrics' state of the whole run: each partition's (its kept span, its own
    target ids) relabelled by the stitching and merged in time order within each run; None when
    a partition with input has none (the finalize then scores the relabelled rows)."""
    merged = AssociationScore()

    def when(k: int) -> tuple[int, int]:       # a run's slices in time order
        return 0 if parts[k].run is None else int(parts[k].run), parts[k].t0_us
    for k in sorted(range(len(parts)), key=when):
        p, info = parts[k], infos[k]
        if not info["n_input"]:
            continue
        state = info.get("scores")
        if state is None:
            return None
        targets = maps.get(p.index, {}).get("target")
        merged = merge_association_scores(merged, state if targets is None else
                                          relabel_association_score(state, targets))
    return merged


def merged_evaluation(parts: Sequence[Any], infos: Sequence[dict]) -> streamed.MatchState | None:
    """The evaluation's state of the whole run when every partition with input is a whole run
    that evaluated its windows (:func:`tertiary.evaluation.streamed.merge_runs`: runs share
    nothing); None otherwise (the finalize matches the pictures it reads back)."""
    states = _whole_runs(parts, infos, "evaluation")
    return None if states is None else streamed.merge_runs(states)


def merged_lags(parts: Sequence[Any], infos: Sequence[dict]) -> lags_streamed.LagState | None:
    """The consistency statistics' lag sums of the whole run, as :func:`merged_evaluation`
    merges the evaluation (None: the end sums every series)."""
    states = _whole_runs(parts, infos, "lags")
    return None if states is None else lags_streamed.merge_runs(states)


def _whole_runs(parts: Sequence[Any], infos: Sequence[dict], key: str) -> list[Any] | None:
    """Each partition's state ``key`` when every partition with input is a whole run that
    returned one; else None."""
    states = [info.get(key) for info in infos if info["n_input"]]
    if not states or any(s is None for s in states) or not all(p.whole_run for p in parts):
        return None
    return states
