"""Efficiency indicators of an air picture (monograph §1.7, §5.1, §2.2–2.3), as ``metrics`` rows.

A picture is a table in the ``tracks`` schema (run, epoch, track_id, [method, filter], x_m …
vz_mps, cov_diag); the reference is truth (or an ADS-B reference) in the ``truth`` schema. The
picture is matched to the reference once by :func:`tertiary.evaluation.matching.match_to_reference` (one
aircraft per track row and epoch, documented there); every indicator below is an array/polars
computation on that matched table and on the reference interpolated at the picture's epochs
(:func:`tertiary.evaluation.matching.reference_at_epochs`). Definitions (all per picture, pooled over runs):

§1.7 completeness and reliability
  * ``p_detect_track`` — fraction of (epoch, aircraft alive in the reference) samples at which a
    track of the picture is matched to the aircraft; segment ``all`` and per range bin
    ``range_m=[a,b)`` (3-D distance from ``IndicatorConfig.range_from``, the system-frame point
    of interest, e.g. a radar site).
  * ``mean_time_to_detect_s`` — over aircraft ever matched: first matched epoch − first epoch at
    which the aircraft is alive in the picture's window (an aircraft alive at the window start
    counts from the window start); ``aircraft_never_detected`` counts the others.
  * A track is *true* when at least one of its rows is matched, *false* otherwise. Its duration
    is last − first epoch of its rows. ``false_tracks_per_hour`` = false tracks / picture hours
    (Σ over runs of the picture's epoch span); ``mean_false_track_lifetime_s``;
    ``mean_track_duration_s`` (true tracks).
  * ``p_track_loss`` — fraction of true tracks *lost*: the aircraft of the track's last matched
    row is still alive in the reference at a later epoch of the picture (the track ended, or
    stopped following it, while the aircraft was still there).

§5.1 capacity
  * ``traffic_intensity_per_h`` — distinct aircraft alive in the window per hour (segment
    ``truth``), and distinct aircraft held by the picture per hour (segment ``picture``).
  * ``zone_load`` — aircraft simultaneously under control: tracks of the picture matched to an
    aircraft at an epoch (segment ``picture``), aircraft alive (segment ``truth``); metrics
    ``zone_load_mean``, ``zone_load_max`` and the history ``zone_load`` per time bin (segment
    ``<picture|truth> t_s=[a,b)``, the mean over the bin's epochs).

§2.2–2.3 real versus potential accuracy
  * ``rmse_pos_h_m`` = √mean(e_x² + e_y²) over matched rows (real accuracy about the truth,
    (2.15) pooled over runs and epochs), ``potential_pos_h_m`` = √mean(P_xx + P_yy) (the
    filter's own claim), ``real_to_potential_pos_h`` their ratio (1 for a consistent filter,
    > 1 for an optimistic one); likewise ``vel_h``; the ratio history per time bin.
  * Gain histories K(k) are a property of the filter model, not of the picture table (it holds
    P⁺ but not the measurement covariance): :func:`gain_history` runs the Riccati recursion of
    a linear channel and :func:`gain_metrics` writes K_i(k) as rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from tertiary.core.units import US
from tertiary.evaluation.matching import MatchConfig, match_to_reference, reference_at_epochs
from tertiary.contract import TABLES, TIME

__all__ = ["IndicatorConfig", "indicators", "picture_indicators", "gain_history", "gain_metrics", "STAGE"]

STAGE = "indicators"


@dataclass(frozen=True)
class IndicatorConfig:
    """* ``match``: gates of the one track-to-reference matcher.
    * ``range_bins_m``: edges of the range bins of ``p_detect_track``.
    * ``range_from``: system-frame point (x, y, z) the range is measured from.
    * ``time_bin_s``: bin width of the zone-load and accuracy histories."""

    match: MatchConfig = field(default_factory=MatchConfig)
    range_bins_m: tuple[float, ...] = (0.0, 20e3, 40e3, 60e3, 80e3, 100e3, 150e3, 250e3, 500e3)
    range_from: tuple[float, float, float] = (0.0, 0.0, 0.0)
    time_bin_s: float = 300.0


def _rows(picture: str, items: list[tuple[str, str | None, float]], n_runs: int) -> pl.DataFrame:
    spec = TABLES["metrics"].required
    return pl.DataFrame({"stage": [STAGE] * len(items), "method": [picture] * len(items),
                         "metric": [m for m, _, _ in items], "segment": [s for _, s, _ in items],
                         "value": [float(v) for _, _, v in items], "n_runs": [n_runs] * len(items)},
                        schema=spec)


def _bin_labels(edges: NDArray[np.float64], unit: str) -> list[str]:
    return [f"{unit}=[{edges[i]:g},{edges[i + 1]:g})" for i in range(len(edges) - 1)]


def _seconds(col: str) -> pl.Expr:
    return pl.col(col).dt.epoch("us").cast(pl.Float64) / US


def picture_indicators(picture: pl.DataFrame, truth: pl.DataFrame, name: str = "picture",
                       cfg: IndicatorConfig = IndicatorConfig()) -> pl.DataFrame:
    """Every indicator of the module docstring for one picture (``tracks`` schema rows)."""
    tr = picture if "run" in picture.columns else picture.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    tr = tr.with_columns(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                         pl.col("track_id").cast(pl.UInt64), pl.lit(name).alias("method"))
    n_runs = int(tr["run"].n_unique()) if tr.height else 0
    if tr.height == 0:
        return _rows(name, [], 0)
    m = match_to_reference(tr, truth, cfg.match).with_columns(_seconds("epoch").alias("t"))
    alive = reference_at_epochs(tr.select("run", "epoch"), truth, cfg.match.max_gap_s).with_columns(
        _seconds("epoch").alias("t"))
    span = tr.group_by("run").agg(_seconds("epoch").min().alias("t0"), _seconds("epoch").max().alias("t1"))
    hours = float((span["t1"] - span["t0"]).sum()) / 3600.0
    hit = m.filter(pl.col("truth_id").is_not_null()).select(
        "run", "epoch", pl.col("truth_id").cast(pl.Int64)).unique().with_columns(pl.lit(True).alias("det"))
    alive = alive.with_columns(pl.col("truth_id").cast(pl.Int64)).join(
        hit, on=["run", "epoch", "truth_id"], how="left").with_columns(pl.col("det").fill_null(False))
    items: list[tuple[str, str | None, float]] = []
    items += _detection(alive, cfg)
    items += _track_life(m, alive, hours)
    items += _capacity(m, alive, tr, span, hours, cfg)
    items += _accuracy(m, span, cfg)
    return _rows(name, items, n_runs)


def _detection(alive: pl.DataFrame, cfg: IndicatorConfig) -> list[tuple[str, str | None, float]]:
    """p_detect_track (all, per range bin) and the mean time to detect."""
    out: list[tuple[str, str | None, float]] = []
    if alive.height == 0:
        return out
    out.append(("p_detect_track", "all", float(alive["det"].mean())))
    p0 = np.asarray(cfg.range_from, float)
    rng = np.sqrt(sum((alive[f"true_{c}_m"].to_numpy() - p0[i]) ** 2 for i, c in enumerate("xyz")))
    edges = np.asarray(cfg.range_bins_m, float)
    b = np.digitize(rng, edges) - 1
    inside = (b >= 0) & (b < len(edges) - 1)
    n = np.bincount(b[inside], minlength=len(edges) - 1)
    k = np.bincount(b[inside], weights=alive["det"].to_numpy()[inside].astype(float), minlength=len(edges) - 1)
    for lab, ni, ki in zip(_bin_labels(edges, "range_m"), n, k):
        if ni:
            out.append(("p_detect_track", lab, ki / ni))
    per = alive.group_by("run", "truth_id").agg(pl.col("t").min().alias("t_alive"),
                                                 pl.col("t").filter(pl.col("det")).min().alias("t_det"))
    found = per.filter(pl.col("t_det").is_not_null())
    if found.height:
        out.append(("mean_time_to_detect_s", "all", float((found["t_det"] - found["t_alive"]).mean())))
    out.append(("aircraft_never_detected", "all", float(per.height - found.height)))
    return out


def _track_life(m: pl.DataFrame, alive: pl.DataFrame, hours: float) -> list[tuple[str, str | None, float]]:
    """False-track rate and lifetime, true-track duration, probability of track loss."""
    life = m.group_by("run", "track_id").agg(
        pl.col("t").min().alias("t0"), pl.col("t").max().alias("t1"),
        pl.col("truth_id").is_not_null().sum().alias("n_hit"),
        pl.col("t").filter(pl.col("truth_id").is_not_null()).max().alias("t_last_hit"),
        pl.col("truth_id").sort_by("t").drop_nulls().last().cast(pl.Int64).alias("last_truth"))
    life = life.with_columns((pl.col("t1") - pl.col("t0")).alias("dur"))
    false, true = life.filter(pl.col("n_hit") == 0), life.filter(pl.col("n_hit") > 0)
    out: list[tuple[str, str | None, float]] = [("false_tracks", "all", float(false.height)),
                                                ("true_tracks", "all", float(true.height))]
    if hours > 0:
        out.append(("false_tracks_per_hour", "all", false.height / hours))
    if false.height:
        out.append(("mean_false_track_lifetime_s", "all", float(false["dur"].mean())))
    if true.height:
        out.append(("mean_track_duration_s", "all", float(true["dur"].mean())))
        last_alive = alive.group_by("run", "truth_id").agg(pl.col("t").max().alias("t_end"))
        lost = true.join(last_alive, left_on=["run", "last_truth"], right_on=["run", "truth_id"], how="left")
        n_lost = int(lost.select((pl.col("t_end") > pl.col("t_last_hit")).fill_null(False).sum()).item())
        out += [("tracks_lost", "all", float(n_lost)), ("p_track_loss", "all", n_lost / true.height)]
    return out


def _time_bin(t: pl.Expr, span: pl.DataFrame, width: float) -> pl.Expr:
    """Bin index of a time (s) from its run's first epoch (needs ``t0`` joined)."""
    return ((t - pl.col("t0")) / width).floor().cast(pl.Int64)


def _capacity(m: pl.DataFrame, alive: pl.DataFrame, tr: pl.DataFrame, span: pl.DataFrame, hours: float,
              cfg: IndicatorConfig) -> list[tuple[str, str | None, float]]:
    """§5.1: traffic intensity per hour and the zone load (mean, max, per time bin)."""
    out: list[tuple[str, str | None, float]] = []
    held = m.filter(pl.col("truth_id").is_not_null())
    if hours > 0:
        out.append(("traffic_intensity_per_h", "truth",
                    alive.select("run", "truth_id").unique().height / hours))
        out.append(("traffic_intensity_per_h", "picture", held.select("run", "truth_id").unique().height / hours))
    epochs = tr.select("run", "epoch").unique()
    for seg, frame in (("picture", held), ("truth", alive)):
        load = epochs.join(frame.group_by("run", "epoch").agg(pl.len().alias("n")), on=["run", "epoch"],
                           how="left").with_columns(pl.col("n").fill_null(0).cast(pl.Float64),
                                                    _seconds("epoch").alias("t"))
        out += [("zone_load_mean", seg, float(load["n"].mean())), ("zone_load_max", seg, float(load["n"].max()))]
        hist = (load.join(span, on="run").with_columns(_time_bin(pl.col("t"), span, cfg.time_bin_s).alias("b"))
                .group_by("b").agg(pl.col("n").mean()).sort("b"))
        w = cfg.time_bin_s
        out += [("zone_load", f"{seg} t_s=[{b * w:g},{(b + 1) * w:g})", v) for b, v in hist.iter_rows()]
    return out


def _accuracy(m: pl.DataFrame, span: pl.DataFrame, cfg: IndicatorConfig) -> list[tuple[str, str | None, float]]:
    """§2.2–2.3: real (RMSE about the truth) against potential (√mean P) accuracy and their ratio."""
    hit = m.filter(pl.col("truth_id").is_not_null())
    if hit.height == 0 or "cov_diag" not in hit.columns:
        return []
    e = hit.with_columns(
        ((pl.col("x_m") - pl.col("true_x_m")) ** 2 + (pl.col("y_m") - pl.col("true_y_m")) ** 2).alias("e_pos"),
        ((pl.col("vx_mps") - pl.col("true_vx_mps")) ** 2 + (pl.col("vy_mps") - pl.col("true_vy_mps")) ** 2)
        .alias("e_vel"),
        (pl.col("cov_diag").arr.get(0) + pl.col("cov_diag").arr.get(1)).alias("p_pos"),
        (pl.col("cov_diag").arr.get(3) + pl.col("cov_diag").arr.get(4)).alias("p_vel"),
    ).join(span, on="run").with_columns(_time_bin(pl.col("t"), span, cfg.time_bin_s).alias("b"))
    out: list[tuple[str, str | None, float]] = []
    for q, unit in (("pos", "m"), ("vel", "mps")):
        real, pot = float(np.sqrt(e[f"e_{q}"].mean())), float(np.sqrt(e[f"p_{q}"].mean()))
        out += [(f"rmse_{q}_h_{unit}", "all", real), (f"potential_{q}_h_{unit}", "all", pot),
                (f"real_to_potential_{q}_h", "all", real / pot if pot > 0 else np.nan)]
    hist = e.group_by("b").agg((pl.col("e_pos").mean() / pl.col("p_pos").mean()).sqrt().alias("r")).sort("b")
    w = cfg.time_bin_s
    out += [("real_to_potential_pos_h", f"t_s=[{b * w:g},{(b + 1) * w:g})", r) for b, r in hist.iter_rows()]
    return out


def indicators(tracks: pl.DataFrame, truth: pl.DataFrame, cfg: IndicatorConfig = IndicatorConfig()) -> pl.DataFrame:
    """``metrics`` rows (stage ``indicators``) of every picture of ``tracks``: a picture is
    ``<method>+<filter>`` when both columns exist (as the pipeline names tracker pictures),
    else ``method``, else ``picture``. One picture at a time (memory of one picture)."""
    if "filter" in tracks.columns and "method" in tracks.columns:
        tracks = tracks.with_columns(pl.format("{}+{}", "method", "filter").alias("__pic"))
    elif "method" in tracks.columns:
        tracks = tracks.with_columns(pl.col("method").alias("__pic"))
    else:
        tracks = tracks.with_columns(pl.lit("picture").alias("__pic"))
    parts = [picture_indicators(p.drop("__pic"), truth, p["__pic"][0], cfg)
             for p in tracks.partition_by("__pic", maintain_order=True)]
    return pl.concat(parts) if parts else _rows("picture", [], 0)


# --------------------------------------------------------------------------- gain histories


def gain_history(phi: ArrayLike, q: ArrayLike, h: ArrayLike, r: ArrayLike, p0: ArrayLike, steps: int
                 ) -> NDArray[np.float64]:
    """Kalman gains K(k), k = 1 … steps, of a linear channel from the Riccati recursion
    P⁻ = Φ P⁺ Φᵀ + Q, K = P⁻ Hᵀ (H P⁻ Hᵀ + R)⁻¹, P⁺ = (I − K H) P⁻ (monograph (2.10)–(2.14);
    the data-independent histories of figs. 2.3–2.4). Returns (steps, n_state, n_meas).
    A loop over the steps, not over tracks or reports."""
    phi, q, h = (np.atleast_2d(np.asarray(a, float)) for a in (phi, q, h))
    r, p = np.atleast_2d(np.asarray(r, float)), np.atleast_2d(np.asarray(p0, float))
    out = np.empty((steps, phi.shape[0], h.shape[0]))
    eye = np.eye(phi.shape[0])
    for k in range(steps):
        pm = phi @ p @ phi.T + q
        gain = pm @ h.T @ np.linalg.inv(h @ pm @ h.T + r)
        p = (eye - gain @ h) @ pm
        out[k] = gain
    return out


def gain_metrics(gains: NDArray[np.float64], name: str, every: int = 1) -> pl.DataFrame:
    """Gain history as ``metrics`` rows: metric ``gain_K<i><j>`` (state i, measurement j,
    1-based), segment ``k=<step>`` for every ``every``-th step and ``steady`` for the last."""
    items: list[tuple[str, str | None, float]] = []
    steps, n_x, n_z = gains.shape
    for i in range(n_x):
        for j in range(n_z):
            metric = f"gain_K{i + 1}{j + 1}"
            items += [(metric, f"k={k + 1}", gains[k, i, j]) for k in range(0, steps, every)]
            items.append((metric, "steady", gains[-1, i, j]))
    return _rows(name, items, 1)
