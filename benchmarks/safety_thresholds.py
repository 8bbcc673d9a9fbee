"""STCA settings on terminal-area: alert confirmation × threshold family, on the controller's picture.

Runs the pipeline once on the default scenario (200 aircraft, procedures, 10 designed losses of
separation) with one picture (``information`` fusion + ``imm_sym`` tracker, or those given),
then predicts conflicts on its confirmed tracks for every setting and scores them against the
losses of separation in the truth: genuine / nuisance / false alerts, losses alerted, warning
time (safety.alerts). This is the study behind the pipeline's default confirmation
(safety.conflicts.STCA_CONFIRMATION). Every other setting is the pipeline's, as a run applies it
(the scenario's final-approach volumes, ``pipeline.adapt_to_scenario``).

    python benchmarks/safety_thresholds.py [METHOD FILTER]
"""

from __future__ import annotations

import dataclasses
import sys

import polars as pl

from _util import record
from safety import AlertConfig, predict_conflicts, slim_conflicts, stca_tables
from tertiary import pipeline
from tertiary.pipeline.pictures import safety_picture
from tertiary.evaluation.evaluate import evaluate_pictures
from tertiary.simulate import load_scenario, simulate

SETTINGS = [("covariance", c, mn) for c in (0.5, 0.8, 0.95) for mn in ((1, 1), (2, 3), (3, 4), (4, 5))] + \
           [("fixed", e, mn) for e in (0.0, 300.0) for mn in ((1, 1), (3, 4))]


def main(method: str = "information", filt: str = "imm_sym") -> None:
    ds = simulate(load_scenario("terminal-area"))
    cfg = pipeline.PipelineConfig(methods=(method,), filters=(filt,), safety=False)
    # the pipeline's rule as a run applies it: the scenario's final-approach volumes included
    base = pipeline.adapt_to_scenario(cfg, ds).conflicts
    res = pipeline.process(ds, cfg)
    picture, id_col = safety_picture(cfg, res.fused, res.tracks, [])
    # which aircraft each track is at each epoch: the evaluation's matcher, as the pipeline scores alerts
    id_map = evaluate_pictures(picture, ds.truth, radars=ds.radars, frame=ds.origin, id_col=id_col,
                               keep_matched=False, surveillance=False).id_map
    rows = []
    for mode, par, (m, n) in SETTINGS:
        extra = {"confidence": par} if mode == "covariance" else {"fixed_est_h_m": par}
        cc = dataclasses.replace(base, threshold_mode=mode, confirm_m=m, confirm_n=n, **extra)
        c = slim_conflicts(predict_conflicts(picture, cc, id_col=id_col, frame=ds.origin))
        metrics, _, _ = stca_tables(c, id_map, ds.truth, AlertConfig(conflict=cc), id_col=id_col, frame=ds.origin)
        w = dict(zip(metrics["metric"], metrics["value"]))
        rows.append({"picture": f"{method}+{filt}", "thresholds": mode, "parameter": par, "confirm": f"{m}/{n}",
                     **{k: w[k] for k in ("genuine_alerts", "nuisance_alerts", "false_alerts", "los_episodes",
                                          "alerted_los", "warning_median_s", "warning_p05_s", "alerts_per_hour")},
                     "median_z_thr_m": float(c.filter("alert")["z_thr_m"].median() or float("nan"))})
    table = pl.DataFrame(rows)
    with pl.Config(tbl_rows=40, tbl_cols=14, tbl_width_chars=220):
        print(table)
    print(f"recorded in {record('safety_thresholds', {'table': rows})}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
