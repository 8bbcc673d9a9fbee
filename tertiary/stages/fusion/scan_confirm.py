"""Kinematic confirmation of the centralised reference's targets: the secondary tracker's
three-scan test on each target's own plots, a step function with explicit carried state
(:class:`ScanState`).

The fused pictures confirm a target by counting plots (:mod:`tertiary.stages.fusion.confirm`):
a radar's false local track of a few clutter plots passes that count. The secondary tracker
confirms an object only when three successive plots move like an aircraft
(:mod:`tertiary.stages.tracking.tracker`, ``"three_scan"``), which is why its pictures publish
fewer false tracks. The reference applies the same test, with the tracker's parameters, to the
plots the association gave each target:

* a *scan* of a target is one association epoch at which it received fresh plots; its position
  is the last of them (system-frame plot x, y and its time t);
* scans a, b, c in succession confirm the target at c's epoch when b lies in the annulus
  v_min·T ≤ |x_b − x_a|_h ≤ v_max·T, T = t_b − t_a                              ((1.1))
  and c in the circle of radius ``gate_m`` around x_b + (x_b − x_a)·(t_c − t_b)/(t_b − t_a);
* a confirmed target stays confirmed.

The tracker's height-plausibility test is left out: the reference's plot heights come from the
elevation or the Mode C channel, and only the horizontal tests are applied to every plot alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import polars as pl

from tertiary.contract import TIME
from tertiary.stages.fusion.base import CHAIN
from tertiary.stages.fusion.confirm import tentative_at

__all__ = ["ScanState", "scans_of", "three_scan_step"]

_SCAN = {"run": pl.UInt32, "target_id": pl.UInt64, "epoch": TIME, "time": TIME, "x": pl.Float64, "y": pl.Float64}


@dataclass(frozen=True)
class ScanState:
    """Carried state of the three-scan test (natural keys): the last two scans of every target not
    yet confirmed (``scans``: run, target_id, epoch, time, x, y) and the confirmed targets
    (``targets``: run, target_id)."""

    scans: pl.DataFrame
    targets: pl.DataFrame

    @staticmethod
    def empty() -> ScanState:
        """The state before the first window."""
        return ScanState(pl.DataFrame(schema=_SCAN), pl.DataFrame(schema={"run": pl.UInt32, "target_id": pl.UInt64}))

    def keep(self, keys: pl.DataFrame) -> ScanState:
        """Only the targets of ``keys`` (run, target_id)."""
        return ScanState(self.scans.join(keys, on=CHAIN, how="semi", maintain_order="left"),
                         self.targets.join(keys, on=CHAIN, how="semi", maintain_order="left"))


def scans_of(plots: pl.DataFrame) -> pl.DataFrame:
    """One scan per (run, target_id, epoch) of ``plots`` (run, target_id, epoch = the plot's first
    association epoch, time, radar_id, report_id, x, y): its last plot by (time, radar_id,
    report_id)."""
    return (plots.sort("run", "target_id", "epoch", "time", "radar_id", "report_id")
            .group_by("run", "target_id", "epoch", maintain_order=True)
            .agg(pl.col("time").last(), pl.col("x").last(), pl.col("y").last())
            .cast(_SCAN))


def _passes(v_min_mps: float, v_max_mps: float, gate_m: float) -> pl.Expr:
    """Whether a scan is the third of an aircraft-like triple (module docstring), on rows sorted
    by target and epoch (a row's predecessors: the rows before it of the same target)."""
    def same(k: int) -> pl.Expr:
        return (pl.col("run").shift(k) == pl.col("run")) & (pl.col("target_id").shift(k) == pl.col("target_id"))

    def back(c: str, k: int) -> pl.Expr:
        return pl.when(same(k)).then(pl.col(c).shift(k))
    t12 = (back("time", 1) - back("time", 2)).dt.total_microseconds() * 1e-6
    t23 = (pl.col("time") - back("time", 1)).dt.total_microseconds() * 1e-6
    dx, dy = back("x", 1) - back("x", 2), back("y", 1) - back("y", 2)
    d12 = (dx ** 2 + dy ** 2).sqrt()
    annulus = (d12 >= v_min_mps * t12) & (d12 <= v_max_mps * t12) & (t12 > 0)
    k = t23 / t12
    miss = ((pl.col("x") - back("x", 1) - dx * k) ** 2 + (pl.col("y") - back("y", 1) - dy * k) ** 2).sqrt()
    return (annulus & (miss <= gate_m)).fill_null(False)


def three_scan_step(state: ScanState, scans: pl.DataFrame, v_min_mps: float, v_max_mps: float, gate_m: float
                    ) -> tuple[pl.DataFrame, ScanState]:
    """Which of the window's scans (:func:`scans_of`) are tentative, and the new state.

    Returns (run, epoch, target_id, ``tentative``): a target is confirmed from the epoch of the
    first scan that passes the test (with the target's carried scans as its predecessors), or
    throughout when ``state`` had confirmed it. Stepping a run's windows in order gives the flags
    of one whole-run call."""
    new = scans.cast(_SCAN).join(state.targets, on=CHAIN, how="anti")      # confirmed before: no test
    rows = (pl.concat([state.scans, new]).sort("run", "target_id", "epoch")
            .with_columns(_passes(v_min_mps, v_max_mps, gate_m).alias("__pass")))
    # each newly confirmed target's confirming scan, as a group of confirm_targets_step's form
    first = (rows.filter("__pass").group_by(CHAIN).agg(pl.col("epoch").min())
             .with_columns(pl.lit(False).alias("tentative")))
    keys = scans.cast(_SCAN).select("run", "epoch", "target_id")
    out = keys.with_columns(tentative_at(state.targets, first, keys))
    targets = pl.concat([state.targets, first.select(CHAIN)])
    left = (rows.join(first, on=CHAIN, how="anti").group_by(CHAIN, maintain_order=True).tail(2)
            .select(*_SCAN))
    return out, ScanState(left, targets)
