"""STCA trade-off curves.

Trade-off — :func:`stca_tradeoff`, :func:`compare_at_equal_nuisance`
-------------------------------------------------------------------
The fraction of LoS episodes alerted with ≥ X s warning against nuisance + false alerts per
hour, as the threshold confidence (covariance thresholds) or the fixed estimation term, and the
look-ahead vary; the two threshold families compared at equal nuisance + false rate.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import polars as pl

from safety.alerts.config import AlertConfig
from safety.alerts.episodes import IdMap, per_picture, score_pictures, scored_conflicts
from safety.alerts.separation import truth_intervals, truth_span
from safety.conflicts import ConflictConfig, conflicts_steps, init_conflict_state, predict_conflicts
from tertiary.contract import TABLES, TIME
from tertiary.core import geo
from tertiary.core.units import US

__all__ = ["stca_tradeoff", "CURVE_WINDOW_S", "CURVE_WINDOW_ROWS", "CURVE_THREADS", "scored_rows", "curve_settings",
           "tradeoff_from_rows", "compare_at_equal_nuisance", "tradeoff_metrics"]


def curve_settings(base: ConflictConfig, confidences: Sequence[float], fixed_est_h_m: Sequence[float],
                   lookaheads_s: Sequence[float]) -> list[tuple[str, float, ConflictConfig]]:
    """(threshold_mode, parameter, ConflictConfig) of every point of the curves, in curve order:
    for each look-ahead, the covariance thresholds at each confidence, then the fixed ones at
    each estimation term (vertical term scaled like ``base``'s fixed pair)."""
    ratio = base.fixed_est_v_m / base.fixed_est_h_m if base.fixed_est_h_m > 0 else 50.0 / 300.0
    t0 = base.t_thr_s - base.t_margin_s
    out = []
    for t in lookaheads_s:
        common = dict(t_margin_s=float(t) - t0, near_margin_h_m=0.0, near_margin_v_m=0.0)
        out += [("covariance", float(c), dataclasses.replace(base, threshold_mode="covariance", confidence=c, **common))
                for c in confidences]
        out += [("fixed", float(e), dataclasses.replace(base, threshold_mode="fixed", fixed_est_h_m=e,
                                                        fixed_est_v_m=e * ratio, **common)) for e in fixed_est_h_m]
    return out


def stca_tradeoff(picture: "pl.DataFrame | Iterable[pl.DataFrame]", id_map: pl.DataFrame, truth: pl.DataFrame,
                  cfg: AlertConfig = AlertConfig(),
                  id_col: str = "target_id", methods: list[str] | None = None, frame: geo.LocalFrame | None = None,
                  map_id_col: str | None = None,
                  confidences: Sequence[float] = (0.5, 0.8, 0.9, 0.95, 0.99, 0.999),
                  fixed_est_h_m: Sequence[float] = (0.0, 150.0, 300.0, 600.0, 1200.0, 2400.0),
                  lookaheads_s: Sequence[float] | None = None,
                  warning_s: Sequence[float] = (0.0, 30.0, 60.0),
                  intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None,
                  spill: "str | os.PathLike[str] | None" = None) -> pl.DataFrame:
    """Trade-off curves of every picture of ``picture`` (a fused or track table; ``method`` names
    the picture; ``id_col`` its id column, ``map_id_col`` that of ``id_map``, default the
    same): for each look-ahead T (default: ``cfg.conflict``'s) and each point — covariance
    thresholds at each ``confidences``, fixed thresholds at each ``fixed_est_h_m`` (vertical
    term scaled like the configured fixed pair) — conflicts are predicted, scored, and the row
    gives the fraction of LoS episodes alerted with ≥ X s warning (X in ``warning_s``) against
    nuisance + false alerts per hour. Columns: method, threshold_mode, parameter (confidence or
    fixed_est_h_m), t_thr_s, warning_s, los_episodes, alerted_fraction, genuine_alerts,
    nuisance_alerts, false_alerts, nuisance_false_per_hour, picture_hours, n_runs. ``intervals``:
    :func:`truth_intervals` of ``truth`` when already computed (curves drawn a picture at a time).
    ``spill``: a scratch directory where each setting's predicted rows wait for their scoring
    on disk, so one setting's rows are held at a time; ``picture`` may come as blocks in time
    order (:func:`scored_rows`). Each picture's rows depend on that picture alone."""
    looks = (cfg.conflict.t_thr_s,) if lookaheads_s is None else tuple(lookaheads_s)
    settings = curve_settings(cfg.conflict, confidences, fixed_est_h_m, looks)
    scored = scored_rows(picture, [cc for _, _, cc in settings], id_col, frame, spill=spill)
    return tradeoff_from_rows(scored, settings, id_map, truth, cfg, map_id_col or id_col, methods, frame, warning_s,
                              intervals)


def tradeoff_from_rows(scored: Sequence["pl.DataFrame | Callable[[], pl.DataFrame]"],
                       settings: Sequence[tuple[str, float, ConflictConfig]], id_map: pl.DataFrame,
                       truth: pl.DataFrame, cfg: AlertConfig, map_id_col: str, methods: list[str] | None,
                       frame: geo.LocalFrame | None, warning_s: Sequence[float] = (0.0, 30.0, 60.0),
                       intervals: tuple[pl.DataFrame, pl.DataFrame] | None = None) -> pl.DataFrame:
    """The curves of :func:`stca_tradeoff` from each setting's predicted rows already made
    (``scored[k]`` of ``settings[k]``: :func:`~safety.alerts.episodes.scored_conflicts` of the
    prediction, or a reader of them), e.g. by the pipeline's windows, which predict every
    setting as the run goes."""
    if intervals is None:
        intervals = truth_intervals(truth, cfg, frame)
    if "truth_id" in truth.columns and "airborne" not in truth.columns:
        truth = truth_span(truth, cfg, frame)       # each aircraft's end read once, not per setting
    ids = IdMap.of(id_map, truth, map_id_col)      # the id map's rows and epochs read once, not per setting
    rows = []
    for (mode, par, cc), c in zip(settings, scored):
        c = c() if callable(c) else c         # a spilled setting's rows, read back now
        acfg = dataclasses.replace(cfg, conflict=cc)
        alerts, los, grid = score_pictures(c, ids, truth, acfg, map_id_col, methods, frame, intervals)
        per = per_picture(alerts, los, grid)
        for x in warning_s:
            frac = (los.group_by("method").agg(
                (pl.col("alerted") & (pl.col("warning_s") >= x)).sum().alias("__n"), pl.len().alias("__d")))
            part = per.join(frac, on="method", how="left").select(
                "method", pl.lit(mode).alias("threshold_mode"), pl.lit(par).alias("parameter"),
                pl.lit(cc.t_thr_s).alias("t_thr_s"), pl.lit(float(x)).alias("warning_s"), "los_episodes",
                pl.when(pl.col("__d") > 0).then(pl.col("__n") / pl.col("__d")).otherwise(float("nan"))
                .alias("alerted_fraction"),
                "genuine_alerts", "nuisance_alerts", "false_alerts", "nuisance_false_per_hour", "picture_hours",
                pl.col("n_runs").cast(pl.UInt32))
            rows.append(part)
    return pl.concat(rows, how="vertical_relaxed").sort("method", "t_thr_s", "warning_s", "threshold_mode", "parameter")


#: the time windows the trade-off curves predict conflicts in (memory bounded by the window) ...
CURVE_WINDOW_S = 3600.0


#: ... and the most picture rows a window starts with (more only when one epoch holds more)
CURVE_WINDOW_ROWS = 100_000


#: settings of the curves predicted at once, in threads: each setting's prediction is
#: independent and most of its time is spent in numpy, polars and the KD-tree, outside the GIL
CURVE_THREADS = min(2, os.cpu_count() or 1)


def scored_rows(picture: "pl.DataFrame | Iterable[pl.DataFrame]", cfgs: Sequence[ConflictConfig], id_col: str,
                frame: geo.LocalFrame | None, window_s: float | None = None,
                spill: "str | os.PathLike[str] | None" = None) -> list["pl.DataFrame | Callable[[], pl.DataFrame]"]:
    """What scoring reads of :func:`~safety.conflicts.predict_conflicts` of ``picture`` under
    each configuration of ``cfgs``: its alert rows and one row per (run, method, epoch) (the
    epoch grid of :func:`picture_grid`), predicted window by window
    (:func:`~safety.conflicts.conflicts_steps`, each configuration's confirmation state
    carried), so that a long picture's every screened pair is never held at once. Each window
    of the picture is cut, prepared and screened once for every configuration; the
    per-configuration work runs :data:`CURVE_THREADS` at a time. The scores equal those of the
    whole table. ``picture`` may come as blocks in time order (each block's epochs after the
    previous block's but its last; a block's last epoch is completed by the next block's rows):
    the picture is then never held whole. With ``spill`` each window's rows of each
    configuration are written there and a reader of each configuration's rows is returned
    instead (the alert rows of many settings of a long picture need not fit in memory together)."""
    blocks = iter([picture] if isinstance(picture, pl.DataFrame) else picture)
    first = next(blocks, None)
    if first is None:
        raise ValueError("scored_rows: a picture of no block (give an empty frame instead)")
    step = int(round((CURVE_WINDOW_S if window_s is None else window_s) * US))
    states = [init_conflict_state() for _ in cfgs]
    parts: list[list[pl.DataFrame]] = [[] for _ in cfgs]

    dirs = None if spill is None else [Path(spill) / f"setting-{k:03d}" for k in range(len(cfgs))]
    for d in dirs or ():
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
    w = 0
    with ThreadPoolExecutor(CURVE_THREADS) as pool:
        for block in _whole_epochs(first, blocks):
            us = block["epoch"].cast(TIME).dt.epoch("us").to_numpy()
            order = np.argsort(us, kind="stable")
            us = us[order]
            # a dense picture is cut finer: every setting's screened pairs of a window are held
            # together
            edges = np.unique(np.concatenate([np.arange(int(us[0]), int(us[-1]) + 1, step),
                                              us[::CURVE_WINDOW_ROWS], [int(us[-1]) + 1]])).tolist()
            for t0, t1 in zip(edges[:-1], edges[1:]):
                lo, hi = np.searchsorted(us, [t0, t1])
                steps = conflicts_steps(states, block[order[lo:hi]], cfgs, id_col, frame, t0, t1, slim=False,
                                        map_=pool.map, scored_only=True)
                states = [state for _, state in steps]
                for k, rows in enumerate(pool.map(scored_conflicts, [out for out, _ in steps])):
                    if dirs is None:
                        parts[k].append(rows)
                    else:
                        rows.write_parquet(dirs[k] / f"w={w:06d}.parquet", compression="lz4")
                w += 1
    if w == 0:                  # an empty picture
        for d in dirs or ():
            shutil.rmtree(d, ignore_errors=True)
        return [predict_conflicts(first.clear(), cfg, id_col=id_col, frame=frame) for cfg in cfgs]
    if dirs is None:
        return [pl.concat(p) for p in parts]
    return [functools.partial(_read_spilled, d) for d in dirs]


def _whole_epochs(first: pl.DataFrame, rest: Iterator[pl.DataFrame]) -> Iterator[pl.DataFrame]:
    """The blocks ``first``, ``*rest`` with rows, each ending on a whole epoch: the rows of a
    block's last epoch move to the next block (a window of the prediction holds whole epochs)."""
    held = first
    for block in rest:
        if block.height == 0:
            continue
        if held.height:
            last = held["epoch"].max()
            tail = held["epoch"] == last
            if held.height > int(tail.sum()):
                yield held.filter(~tail)
            held = pl.concat([held.filter(tail), block], how="vertical_relaxed")
        else:
            held = block
    if held.height:
        yield held


def _read_spilled(d: Path) -> pl.DataFrame:
    """A configuration's spilled rows (:func:`scored_rows`) in window order; the files removed."""
    files = sorted(d.glob("w=*.parquet"))
    out = pl.concat([pl.read_parquet(f) for f in files])
    shutil.rmtree(d, ignore_errors=True)
    return out


def compare_at_equal_nuisance(curve: pl.DataFrame, warning_s: float = 30.0, t_thr_s: float | None = None,
                              rate: float | None = None, reference_confidence: float = 0.95) -> pl.DataFrame:
    """Covariance vs fixed thresholds at equal nuisance + false alert rate: per picture, each
    family's alerted fraction (≥ ``warning_s`` warning) linearly interpolated at ``rate``
    (default: the covariance family's rate at ``reference_confidence``), at look-ahead
    ``t_thr_s`` (default: the curve's largest); NaN outside a family's range (no
    extrapolation). Columns: method, threshold_mode, t_thr_s, warning_s,
    nuisance_false_per_hour, alerted_fraction."""
    cur = curve.filter(pl.col("warning_s") == warning_s)
    if t_thr_s is None and cur.height:
        t_thr_s = float(cur["t_thr_s"].max())
    cur = cur.filter(pl.col("t_thr_s") == t_thr_s)
    out = []
    for (method,), g in cur.partition_by("method", as_dict=True, maintain_order=True).items():
        cov = g.filter(pl.col("threshold_mode") == "covariance")
        r = rate
        if r is None and cov.height:
            r = float(cov.sort((pl.col("parameter") - reference_confidence).abs())["nuisance_false_per_hour"][0])
        for mode in ("covariance", "fixed"):
            fam = (g.filter((pl.col("threshold_mode") == mode) & pl.col("nuisance_false_per_hour").is_not_nan())
                   .group_by("nuisance_false_per_hour").agg(pl.col("alerted_fraction").max())
                   .sort("nuisance_false_per_hour"))
            x, y = fam["nuisance_false_per_hour"].to_numpy(), fam["alerted_fraction"].to_numpy()
            ok = r is not None and len(x) and x[0] <= r <= x[-1]
            val = float(np.interp(r, x, y)) if ok else float("nan")
            out.append({"method": method, "threshold_mode": mode, "t_thr_s": t_thr_s, "warning_s": float(warning_s),
                        "nuisance_false_per_hour": float("nan") if r is None else float(r), "alerted_fraction": val})
    schema = {"method": pl.String, "threshold_mode": pl.String, "t_thr_s": pl.Float64, "warning_s": pl.Float64,
              "nuisance_false_per_hour": pl.Float64, "alerted_fraction": pl.Float64}
    return pl.DataFrame(out, schema=schema)


def tradeoff_metrics(curve: pl.DataFrame) -> pl.DataFrame:
    """The curves in the ``metrics`` schema (stage ``"safety_tradeoff"``, per picture): metrics
    ``alerted_fraction`` and ``nuisance_false_per_hour``, one segment per curve point,
    ``mode=<covariance|fixed>;p=<parameter>;T=<t_thr_s>;X=<warning_s>`` (read by
    ``sql/stca_tradeoff.sql``)."""
    seg = pl.format("mode={};p={};T={};X={}", "threshold_mode", pl.col("parameter").round(6),
                    pl.col("t_thr_s").round(3), pl.col("warning_s").round(3))
    long = curve.with_columns(seg.alias("segment")).unpivot(
        index=["method", "segment", "n_runs"], on=["alerted_fraction", "nuisance_false_per_hour"],
        variable_name="metric", value_name="value")
    spec = TABLES["metrics"].required
    out = long.select(pl.lit("safety_tradeoff").alias("stage"), "method", "metric", "segment", "value", "n_runs")
    return out.select([pl.col(c).cast(t) for c, t in spec.items()]).sort("method", "segment", "metric")
