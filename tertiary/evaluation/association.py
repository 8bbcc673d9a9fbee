"""The association stage's metrics. Association is judged on reports (was each report put with
its own aircraft?), so by the reports' evaluation-only truth labels; pictures are judged by the
matcher (:mod:`tertiary.evaluation.evaluate`). Scored window by window with the state carried
(:class:`AssociationScore`), or at once (:func:`association_metrics`): the same rows."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import polars as pl

from tertiary.contract import TABLES, TIME

__all__ = ["AssociationScore", "association_metrics", "score_associations", "association_score",
           "merge_association_scores", "relabel_association_score"]


_KEY = ["run", "epoch", "target_id"]


def _report_truth(associations: pl.DataFrame, report_truth: pl.DataFrame) -> pl.DataFrame:
    """Association rows with the truth_id of their report (null for clutter/unknown)."""
    on = ["report_id"]
    if "run" in report_truth.columns and "run" in associations.columns:
        on = ["run", "report_id"]
    rt = report_truth.select(*[pl.col(c).cast(associations.schema[c]) for c in on],
                             pl.col("truth_id").cast(pl.Int64)).unique(subset=on, keep="first")
    # a block of rows joined at a time: a long run's join scratch is a block's (memory)
    size = max(1, LABEL_BLOCK_ROWS)
    return pl.concat([associations.slice(k, size).join(rt, on=on, how="left", maintain_order="left")
                      for k in range(0, max(associations.height, 1), size)])


#: association rows labelled with their reports' aircraft at a time (:func:`_report_truth`)
LABEL_BLOCK_ROWS = 262_144


def _majority(labelled: pl.DataFrame, key: list[str]) -> pl.DataFrame:
    """Majority non-null truth_id per ``key`` (ties → smallest truth_id; null if none)."""
    keys = labelled.select(key).unique()
    votes = (labelled.filter(pl.col("truth_id").is_not_null())
             .group_by(key + ["truth_id"]).agg(pl.len().alias("__votes"))
             .sort(key + ["__votes", "truth_id"], descending=[False] * len(key) + [True, False])
             .unique(subset=key, keep="first", maintain_order=True)
             .select(key + ["truth_id"]))
    return keys.join(votes, on=key, how="left")


def association_metrics(associations: pl.DataFrame, report_truth: pl.DataFrame,
                        confirmed: pl.DataFrame | None = None) -> pl.DataFrame:
    """Association correctness (metrics schema, stage ``association``, method ``assignment``,
    segment ``all``):

    * ``swaps``: for each (run, target_id), over the epochs at which the target exists in time
      order, consecutive epochs whose majority truth_ids (of the reports associated with it;
      clutter does not vote; ties → smallest id) are both non-null and differ; summed;
    * ``targets_per_truth``: for each (run, truth_id) with at least one associated report, the
      number of distinct target ids that had it as majority truth at some epoch; the mean;
    * ``confirmed_targets_per_truth`` (with ``confirmed``: the (run, target_id) ever shown
      confirmed): the same count of confirmed targets only — the system targets a controller
      sees per aircraft; a tentative target of a plot or two that never confirms is not one;
    * ``false_targets``: (run, target_id) whose associated reports are all clutter;

    * ``assoc_correct_frac``: among association rows whose report has a truth_id, the fraction
      whose target both has that truth as majority and is the aircraft's principal target at
      the epoch (the one holding most of its reports; ties: lowest id) — a report put in a
      second, duplicate target of its aircraft is not correctly associated;

    * ``split_targets``: number of (run, epoch, truth_id) whose reports went to two or more
      system targets at that epoch (one aircraft shown as several targets);
    * ``merged_targets``: number of (run, epoch, target_id) whose reports come from two or
      more aircraft (several aircraft shown as one target).

    Computed as one :func:`score_associations` step and :func:`association_score`: the same
    rows as a run scored window by window.
    """
    return association_score(score_associations(AssociationScore(), associations, report_truth), confirmed)


_TARGET = ["run", "target_id"]


@dataclass
class AssociationScore:
    """What :func:`association_metrics` needs of the association rows seen so far, carried
    across windows (evaluation accumulators, a step function's explicit state). A
    window holds whole epochs, so the per-epoch counts add up; what spans epochs is carried
    per target or aircraft: each target's majority aircraft at its last epoch (swaps), whether
    it ever had a real report (false targets), every (aircraft, target) majority pair and the
    aircraft with a labelled report (targets per aircraft). Its size grows with the targets and
    aircraft of the run, not with its reports."""

    rows: int = 0
    correct: int = 0
    real: int = 0
    swaps: int = 0
    split: int = 0
    merged: int = 0
    runs: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema={"run": pl.UInt32}))
    last: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(
        schema={"run": pl.UInt32, "target_id": pl.UInt64, "target_truth": pl.Int64}))
    seen: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(
        schema={"run": pl.UInt32, "target_id": pl.UInt64, "__real": pl.Boolean}))
    truths: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema={"run": pl.UInt32, "truth_id": pl.Int64}))
    pairs: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(
        schema={"run": pl.UInt32, "truth_id": pl.Int64, "target_id": pl.UInt64}))
    #: each target's majority aircraft at its first epoch scored here: what a state of the
    #: time before it compares with its ``last`` when the two are merged (:func:`merge_association_scores`)
    first: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(
        schema={"run": pl.UInt32, "target_id": pl.UInt64, "target_truth": pl.Int64}))


def _keys(frame: pl.DataFrame, schema: pl.DataFrame) -> pl.DataFrame:
    """``frame``'s key columns in the state's types (a state is concatenated window by window)."""
    return frame.select(pl.col(c).cast(t) for c, t in schema.schema.items())


def score_associations(state: AssociationScore, associations: pl.DataFrame, report_truth: pl.DataFrame
                       ) -> AssociationScore:
    """``state`` after the association rows of whole epochs (a window's) are scored: the window
    scored alone, merged after ``state`` (:func:`merge_association_scores`); ``report_truth``:
    (run, report_id, truth_id) of at least their reports."""
    if associations.is_empty():
        return state
    return merge_association_scores(state, _window_score(associations, report_truth))


def _window_score(associations: pl.DataFrame, report_truth: pl.DataFrame) -> AssociationScore:
    """The :class:`AssociationScore` of the association rows of whole epochs on their own."""
    empty = AssociationScore()
    # the columns read, then the join: a long run's associations are not copied whole through it
    keep = [c for c in ("run", "epoch", "target_id", "report_id") if c in associations.columns]
    labelled = _report_truth(associations.select(keep).with_columns(pl.col("epoch").cast(TIME)), report_truth)
    maj = _majority(labelled, _KEY).rename({"truth_id": "target_truth"})
    seen = labelled.group_by(_TARGET).agg(pl.col("truth_id").is_not_null().any().alias("__real"))
    real = labelled.filter(pl.col("truth_id").is_not_null()).join(maj, on=_KEY, how="left")
    del labelled
    # the aircraft's principal target at the epoch: most of its reports (ties: lowest id)
    principal = (real.group_by(["run", "epoch", "truth_id", "target_id"]).agg(pl.len().alias("__n"))
                 .sort(["run", "epoch", "truth_id", "__n", "target_id"], descending=[False, False, False, True, False])
                 .unique(subset=["run", "epoch", "truth_id"], keep="first", maintain_order=True)
                 .select("run", "epoch", "truth_id", pl.col("target_id").alias("__principal")))
    real = real.join(principal, on=["run", "epoch", "truth_id"], how="left")
    correct = int(real.select(((pl.col("truth_id") == pl.col("target_truth"))
                               & (pl.col("target_id") == pl.col("__principal"))).fill_null(False).sum()).item())
    # each target's majority aircraft epoch by epoch: a change between two known ones is a swap
    seq = _keys(maj, empty.last).with_columns(maj["epoch"]).sort(["run", "target_id", "epoch"])
    same = (pl.col("run") == pl.col("run").shift(1)) & (pl.col("target_id") == pl.col("target_id").shift(1))
    prev = pl.when(same).then(pl.col("target_truth").shift(1))
    swaps = int(seq.select(((pl.col("target_truth") != prev) & prev.is_not_null()
                            & pl.col("target_truth").is_not_null()).fill_null(False).sum()).item())
    ends = seq.group_by(_TARGET).agg(pl.col("target_truth").first().alias("__first"),
                                     pl.col("target_truth").last().alias("target_truth"))
    split = real.group_by(["run", "epoch", "truth_id"]).agg(pl.col("target_id").n_unique().alias("n")
                                                             ).filter(pl.col("n") > 1).height
    merged = real.group_by(_KEY).agg(pl.col("truth_id").n_unique().alias("n")).filter(pl.col("n") > 1).height
    pairs = (maj.filter(pl.col("target_truth").is_not_null())
             .select("run", pl.col("target_truth").alias("truth_id"), "target_id"))
    return AssociationScore(
        rows=associations.height, correct=correct, real=real.height, swaps=swaps, split=split, merged=merged,
        runs=_keys(associations, empty.runs).unique(), last=ends.select(empty.last.columns),
        seen=_keys(seen, empty.seen), truths=_keys(real, empty.truths).unique(),
        pairs=_keys(pairs, empty.pairs).unique(),
        first=ends.select("run", "target_id", pl.col("__first").alias("target_truth")).select(empty.first.columns))


def merge_association_scores(earlier: AssociationScore, later: AssociationScore) -> AssociationScore:
    """The state of :func:`score_associations` over the epochs of ``earlier`` then those of
    ``later`` (scored apart, e.g. by two time slices of a distributed run, with the same target
    ids): the per-epoch counts add up, a target's majority aircraft at its first epoch in
    ``later`` is compared with its last in ``earlier`` (a swap across the boundary), and the
    sets are united. Equal to one state scored over both."""
    prev = earlier.last.join(later.first, on=_TARGET, how="inner", suffix="__b")
    across = int(prev.select((pl.col("target_truth") != pl.col("target_truth__b")).fill_null(False).sum()).item())
    last = pl.concat([earlier.last.join(later.last.select(_TARGET), on=_TARGET, how="anti"), later.last])
    first = pl.concat([earlier.first, later.first.join(earlier.first.select(_TARGET), on=_TARGET, how="anti")])
    seen = pl.concat([earlier.seen, later.seen]).group_by(_TARGET).agg(pl.col("__real").any())
    return AssociationScore(
        rows=earlier.rows + later.rows, correct=earlier.correct + later.correct, real=earlier.real + later.real,
        swaps=earlier.swaps + later.swaps + across, split=earlier.split + later.split,
        merged=earlier.merged + later.merged, runs=pl.concat([earlier.runs, later.runs]).unique(), last=last,
        seen=seen.select(earlier.seen.columns), truths=pl.concat([earlier.truths, later.truths]).unique(),
        pairs=pl.concat([earlier.pairs, later.pairs]).unique(), first=first)


def relabel_association_score(state: AssociationScore, targets: pl.DataFrame) -> AssociationScore:
    """``state`` with its target ids through ``targets`` (columns ``old``, ``new``; an id not
    in it is kept): a distributed run's slice scored with its own ids, put in the run's."""
    if targets.height == 0:
        return state
    m = targets.select(pl.col("old").cast(pl.UInt64), pl.col("new").cast(pl.UInt64)).unique("old")

    def ids(frame: pl.DataFrame) -> pl.DataFrame:
        return (frame.join(m, left_on="target_id", right_on="old", how="left", maintain_order="left")
                .with_columns(pl.coalesce("new", "target_id").alias("target_id")).select(frame.columns))
    return dataclasses.replace(state, last=ids(state.last), seen=ids(state.seen), pairs=ids(state.pairs).unique(),
                               first=ids(state.first))


def _per_truth(state: AssociationScore, pairs: pl.DataFrame) -> float:
    """Mean over the aircraft with a labelled report of their distinct targets in ``pairs``."""
    got = pairs.group_by(["run", "truth_id"]).agg(pl.len().alias("n_targets"))
    per_truth = (state.truths.join(got, on=["run", "truth_id"], how="left")
                 .with_columns(pl.col("n_targets").fill_null(0)))
    return float(per_truth["n_targets"].mean()) if per_truth.height else float("nan")


def association_score(state: AssociationScore, confirmed: pl.DataFrame | None = None) -> pl.DataFrame:
    """The :func:`association_metrics` rows of every association row scored into ``state``
    (``confirmed``: the targets ever shown confirmed, for ``confirmed_targets_per_truth``)."""
    if state.rows == 0:
        return pl.DataFrame(schema=TABLES["metrics"].required)
    correct = state.correct / state.real if state.real else float("nan")
    false_targets = int((~state.seen["__real"]).sum())
    metric = ["assoc_correct_frac", "swaps", "targets_per_truth", "false_targets", "split_targets", "merged_targets"]
    value = [float(correct), float(state.swaps), _per_truth(state, state.pairs), float(false_targets),
             float(state.split), float(state.merged)]
    if confirmed is not None:
        shown = state.pairs.join(_keys(confirmed, AssociationScore().first.select(_TARGET)).unique(), on=_TARGET,
                                 how="semi")
        metric.append("confirmed_targets_per_truth")
        value.append(_per_truth(state, shown))
    out = pl.DataFrame({"stage": "association", "method": "assignment", "metric": metric, "segment": "all",
                        "value": value, "n_runs": state.runs.height})
    return out.select([pl.col(c).cast(t) for c, t in TABLES["metrics"].required.items()])
