"""Alert quality on terminal-area: thresholds from track covariance vs a fixed threshold.

Runs the pipeline once (default terminal-area: 200 aircraft with designed losses of
separation), then predicts conflicts on every fusion method's picture with
``threshold_mode="covariance"`` and ``"fixed"`` (same minima, piloting term and look-ahead)
and scores both against truth: hits, misses, false alerts, mean warning time, flicker.

    python benchmarks/safety_thresholds.py
"""

from __future__ import annotations

import dataclasses
import json

import polars as pl

from _util import record
from safety import AlertConfig, ConflictConfig, predict_conflicts, score_alerts
from tertiary import pipeline
from tertiary.evaluate import target_truth
from tertiary.simulate import load_scenario, simulate


def main() -> None:
    ds = simulate(load_scenario("terminal-area"))
    res = pipeline.process(ds, pipeline.PipelineConfig(filters=(), safety=False))
    id_map = target_truth(res.associations, ds.reports.select("run", "report_id", "truth_id"))
    methods = sorted(res.fused["method"].unique().to_list())
    rows = []
    for mode in ("covariance", "fixed"):
        cfg = ConflictConfig(threshold_mode=mode)
        conflicts = predict_conflicts(res.fused, cfg, id_col="target_id")
        m = score_alerts(conflicts, id_map, ds.truth, AlertConfig(conflict=cfg), id_col="target_id", methods=methods)
        wide = m.pivot(on="metric", index="method", values="value").with_columns(pl.lit(mode).alias("thresholds"))
        thr = conflicts.group_by("method").agg(pl.col("r_thr_m").median().alias("median_r_thr_m"),
                                                pl.col("z_thr_m").median().alias("median_z_thr_m"))
        rows.append(wide.join(thr, on="method", how="left"))
    table = pl.concat(rows, how="diagonal_relaxed").sort("method", "thresholds")
    with pl.Config(tbl_rows=40, tbl_cols=12, tbl_width_chars=200):
        print(table.select("method", "thresholds", "hits", "misses", "false_alerts", "mean_warning_s",
                           "flicker_per_hit", "median_r_thr_m", "median_z_thr_m"))
    print(f"recorded in {record('safety_thresholds', {'table': table.to_dicts()})}")


if __name__ == "__main__":
    main()
