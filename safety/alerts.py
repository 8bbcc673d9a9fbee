"""Scoring conflict alerts against truth: hits, misses, false alerts, warning time, flicker.

Inputs
------
* ``conflicts`` — the output of :func:`safety.conflicts.predict_conflicts` on a picture
  (fused targets or tracks); only rows with ``alert`` are used.
* ``id_map`` — (run, epoch, ``id_col``, truth_id[, method]): which aircraft each picture id
  is at each epoch (e.g. :func:`tertiary.evaluate.target_truth` renamed). Its epochs define the
  picture's **epoch grid** per (run, method) (per run, shared by all methods, when it has no
  ``method`` column).
* ``truth`` — (truth_id, time, x_m … vz_mps[, run]) in the system frame; without ``run`` the
  truth is shared by all runs (Monte-Carlo). Truth is interpolated linearly in time to the
  grid epochs (not extrapolated beyond an aircraft's span).

True conflicts (``AlertConfig.truth_rule``), evaluated at every grid epoch t_k
-----------------------------------------------------------------------------
* ``"prediction"`` — the pair is a conflict by the *same* prediction rule (5.10)–(5.17)
  (same minima, piloting term, T^пор) applied to the **true** states with **zero estimation
  error** (``threshold_mode="fixed"``, estimation terms 0). The decision rule is
  ``truth_mode`` (default ``"corrected"``: the seed rule would count already-passed pairs as
  true conflicts; ``None`` = the picture's own rule).
* ``"los"`` — an actual loss of separation (horizontal distance < Δr_г **and** |Δh| < Δr_в at
  the same instant, on the true trajectories sampled every ``los_step_s``) occurs within
  [t_k, t_k + T^пор].

Episodes (per run, method and unordered truth pair; consecutive = adjacent grid epochs)
--------------------------------------------------------------------------------------
* A **true episode** is a maximal run of consecutive grid epochs at which the pair is a true
  conflict: [t_start, t_end]. Its LOS time t_LOS is the start of the first loss-of-separation
  interval that reaches into [t_start, t_end + T^пор] (none if no LOS follows, possible with
  ``"prediction"``).
* The picture **alerts on a truth pair** at t_k when some alert row's two ids map (at t_k) to
  those two distinct aircraft. Alert rows whose ids have no truth, or map to the same aircraft
  (a duplicated track conflicting with itself), are keyed by their id pair instead and can
  only be false alerts.
* **Hit**: an alert on the pair at some t_k ∈ [t_start − early, max(t_LOS, t_start)]
  (t_end when there is no LOS): before the loss of separation, during the episode, or up to
  ``early_s`` (default T^пор) before it starts — an alert raised earlier than the zero-error
  truth rule (wider, covariance-inflated thresholds) is an early warning, not a false alert.
  Otherwise a **miss** (also when the picture does not hold the aircraft at all).
* **Warning time** of a hit with a LOS: t_LOS − (first alert in that hit window); may be
  negative when the LOS was already under way at t_start. ``mean_warning_s`` averages over
  hits with a LOS (NaN if none).
* **Flicker** of a hit: the number of on→off transitions of the pair's alert between the
  first alert and t_end that are followed by a new alert on the pair no later than t_end
  (alert at t_k, none at t_{k+1}, again at some t_m ≤ t_end): the alert dropping out and
  coming back. The final switch-off (conflict resolved or passed) is not a flicker.
* **False alert**: a maximal run of consecutive grid epochs with an alert on one key none of
  whose epochs lies in [t_start − early, t_end] of a true episode of that pair.

Metrics (``metrics`` schema, stage ``"safety"``, method = the picture's method, segment
``"all"``): ``hits``, ``misses``, ``false_alerts``, ``mean_warning_s``, ``flicker`` (total over
hits), plus ``episodes`` and ``flicker_per_hit``; ``n_runs`` = runs on the method's grid.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
from scipy.spatial import cKDTree

from safety.conflicts import ConflictConfig, predict_conflicts
from tertiary.schema import TABLES, TIME

__all__ = [
    "AlertConfig",
    "truth_at",
    "loss_of_separation",
    "true_conflicts",
    "alert_episodes",
    "score_alerts",
    "ALERT_METRICS",
]

STATE = ("x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
ALERT_METRICS = ("hits", "misses", "false_alerts", "mean_warning_s", "flicker", "episodes", "flicker_per_hit")
_US = 1_000_000


@dataclass(frozen=True)
class AlertConfig:
    """Alert-scoring options (see the module docstring).

    * ``conflict``: the prediction settings of the picture (minima, piloting, T^пор, rule).
    * ``truth_rule``: ``"prediction"`` (zero-error (5.14) on truth) or ``"los"`` (actual loss
      of separation within the look-ahead).
    * ``truth_mode``: the rule for ``"prediction"`` truth; None = ``conflict.mode``.
    * ``early_s``: how long before a true episode an alert still counts for it (None = T^пор).
    * ``los_step_s``: sampling step of the true trajectories for loss of separation.
    """

    conflict: ConflictConfig = ConflictConfig()
    truth_rule: Literal["prediction", "los"] = "prediction"
    truth_mode: Literal["seed", "corrected"] | None = "corrected"
    early_s: float | None = None
    los_step_s: float = 1.0

    def __post_init__(self) -> None:
        if self.truth_rule not in ("prediction", "los"):
            raise ValueError(f"truth_rule must be 'prediction' or 'los', got {self.truth_rule!r}")
        if self.truth_mode not in (None, "seed", "corrected"):
            raise ValueError(f"truth_mode must be None, 'seed' or 'corrected', got {self.truth_mode!r}")
        if self.early_s is not None and self.early_s < 0:
            raise ValueError(f"early_s must be >= 0, got {self.early_s}")
        if self.los_step_s <= 0:
            raise ValueError(f"los_step_s must be positive, got {self.los_step_s}")

    @property
    def early(self) -> float:
        return self.conflict.t_thr_s if self.early_s is None else float(self.early_s)

    @property
    def truth_conflict(self) -> ConflictConfig:
        """The zero-estimation-error configuration of the truth rule."""
        mode = self.truth_mode or self.conflict.mode
        return dataclasses.replace(self.conflict, threshold_mode="fixed", fixed_est_h_m=0.0,
                                   fixed_est_v_m=0.0, mode=mode)


# --------------------------------------------------------------------------- truth sampling


def _truth_frame(truth: pl.DataFrame) -> pl.DataFrame:
    missing = [c for c in ("truth_id", "time", *STATE) if c not in truth.columns]
    if missing:
        raise ValueError(f"truth: missing column(s) {', '.join(missing)}")
    keys = ["run"] if "run" in truth.columns else []
    run = [pl.col("run").cast(pl.UInt32)] if keys else []
    return (truth.select(*run, pl.col("truth_id").cast(pl.Int64),
                         pl.col("time").cast(TIME), *[pl.col(c).cast(pl.Float64) for c in STATE])
            .sort([*keys, "truth_id", "time"]))


def truth_at(truth: pl.DataFrame, epochs: pl.DataFrame) -> pl.DataFrame:
    """True states at ``epochs`` (column ``epoch`` [, ``run`` when truth has runs]): every aircraft
    whose truth span covers the epoch, linearly interpolated between its two neighbouring
    samples. Returns ([run,] epoch, truth_id, x_m … vz_mps)."""
    tr = _truth_frame(truth)
    keys = ["run"] if "run" in tr.columns else []
    ep = epochs.select(*keys, pl.col("epoch").cast(TIME)).unique()
    span = tr.group_by([*keys, "truth_id"]).agg(pl.col("time").min().alias("__t0"), pl.col("time").max().alias("__t1"))
    grid = (span.join(ep, on=keys, how="inner") if keys else span.join(ep, how="cross"))
    grid = grid.filter((pl.col("epoch") >= pl.col("__t0")) & (pl.col("epoch") <= pl.col("__t1"))
                       ).select(*keys, "truth_id", "epoch").sort("epoch")
    by = [*keys, "truth_id"]
    lo = tr.rename({"time": "__ta", **{c: f"__a_{c}" for c in STATE}})
    hi = tr.rename({"time": "__tb", **{c: f"__b_{c}" for c in STATE}})
    j = (grid.join_asof(lo, left_on="epoch", right_on="__ta", by=by, strategy="backward", check_sortedness=False)
         .join_asof(hi, left_on="epoch", right_on="__tb", by=by, strategy="forward", check_sortedness=False))
    span_us = (pl.col("__tb") - pl.col("__ta")).dt.total_microseconds()
    w = (pl.when(span_us > 0)
         .then((pl.col("epoch") - pl.col("__ta")).dt.total_microseconds() / span_us).otherwise(0.0))
    return (j.select(*keys, "epoch", "truth_id",
                     *[(pl.col(f"__a_{c}") + w * (pl.col(f"__b_{c}") - pl.col(f"__a_{c}"))).alias(c) for c in STATE])
            .sort([*keys, "epoch", "truth_id"]))


def _seconds(col: str) -> pl.Expr:
    return pl.col(col).cast(TIME).dt.epoch("us").cast(pl.Float64) / _US


def loss_of_separation(truth: pl.DataFrame, cfg: AlertConfig = AlertConfig()) -> pl.DataFrame:
    """Loss-of-separation intervals on the true trajectories: ([run,] truth_a, truth_b, t_start,
    t_end) with truth_a < truth_b, horizontal distance < Δr_г and |Δh| < Δr_в at every sample of
    [t_start, t_end] (samples every ``los_step_s`` from the first truth time; KD-tree per sample
    time, all times in one tree)."""
    tr = _truth_frame(truth)
    keys = ["run"] if "run" in tr.columns else []
    schema = {**({"run": pl.UInt32} if keys else {}), "truth_a": pl.Int64, "truth_b": pl.Int64,
              "t_start": TIME, "t_end": TIME}
    if tr.height < 2:
        return pl.DataFrame(schema=schema)
    tus = tr["time"].dt.epoch("us")
    base, last = int(tus.min()), int(tus.max())
    step = max(int(round(cfg.los_step_s * _US)), 1)
    ticks = base + step * np.arange((last - base) // step + 1, dtype=np.int64)
    grid = pl.DataFrame({"epoch": pl.Series(ticks).cast(pl.Datetime("us", "UTC"))})
    if keys:
        grid = grid.join(tr.select("run").unique(), how="cross")
    st = truth_at(tr, grid)
    if st.height < 2:
        return pl.DataFrame(schema=schema)
    cc = cfg.conflict
    dr_h, dr_v = cc.sep_h_m, cc.sep_v_m
    gkey = [*keys, "epoch"]
    g = st.select(pl.struct(gkey).rank("dense").cast(pl.Int64) - 1).to_series().to_numpy()
    xyz = st.select("x_m", "y_m", "z_m").to_numpy()
    span = float(np.max(np.abs(xyz))) + 1.0
    sep = 4.0 * dr_h + 1.0
    pts = np.column_stack([xyz[:, 0], xyz[:, 1], xyz[:, 2] * (dr_h / dr_v), g * sep])
    # the Euclidean ball of radius √2·Δr_г holds the cylinder |Δxy| < Δr_г, |Δz·s| < Δr_г; scipy's
    # p=2 search is about twice as fast as its Chebyshev one here, the exact test below decides
    radius = math.sqrt(2.0) * (dr_h * (1 + 1e-12) + 1e-9 * span)
    pr = cKDTree(pts).query_pairs(radius, p=2.0, output_type="ndarray")
    i, j = pr[:, 0].astype(np.int64), pr[:, 1].astype(np.int64)
    d = xyz[j] - xyz[i]
    ok = (g[i] == g[j]) & (np.hypot(d[:, 0], d[:, 1]) < dr_h) & (np.abs(d[:, 2]) < dr_v)
    i, j = i[ok], j[ok]
    if not len(i):
        return pl.DataFrame(schema=schema)
    tid = st["truth_id"].to_numpy()
    ta, tb = np.minimum(tid[i], tid[j]), np.maximum(tid[i], tid[j])
    k = ((st["epoch"].dt.epoch("us").to_numpy() - base) // step).astype(np.int64)
    rows = pl.DataFrame({**({"run": st["run"].to_numpy()[i]} if keys else {}),
                         "truth_a": ta, "truth_b": tb, "__k": k[i]})
    key = [*keys, "truth_a", "truth_b"]
    rows = rows.sort([*key, "__k"]).with_columns(
        (pl.col("__k").diff().over(key).fill_null(0) != 1).cum_sum().over(key).alias("__iv"))
    out = rows.group_by([*key, "__iv"]).agg(pl.col("__k").min().alias("__k0"), pl.col("__k").max().alias("__k1"))
    return (out.select(*key,
                       (pl.lit(base) + pl.col("__k0") * step).cast(pl.Datetime("us", "UTC")).alias("t_start"),
                       (pl.lit(base) + pl.col("__k1") * step).cast(pl.Datetime("us", "UTC")).alias("t_end"))
            .sort([*key, "t_start"]).cast(schema))


def true_conflicts(truth: pl.DataFrame, epochs: pl.DataFrame, cfg: AlertConfig = AlertConfig(),
                   los: pl.DataFrame | None = None) -> pl.DataFrame:
    """True conflicts at the grid ``epochs``: ([run,] epoch, truth_a, truth_b), truth_a < truth_b,
    by ``cfg.truth_rule`` (``los`` may pass precomputed :func:`loss_of_separation` intervals)."""
    keys = ["run"] if "run" in truth.columns else []
    schema = {**({"run": pl.UInt32} if keys else {}), "epoch": TIME, "truth_a": pl.Int64, "truth_b": pl.Int64}
    ep = epochs.select(*keys, pl.col("epoch").cast(TIME)).unique().sort([*keys, "epoch"])
    if ep.is_empty():
        return pl.DataFrame(schema=schema)
    if cfg.truth_rule == "prediction":
        st = truth_at(truth, ep)
        if not keys:
            st = st.with_columns(pl.lit(0, pl.UInt32).alias("run"))
        c = predict_conflicts(st, cfg.truth_conflict, id_col="truth_id", default_method="truth")
        c = c.filter(pl.col("alert"))
        return c.select(*keys, "epoch", pl.col("id_a").cast(pl.Int64).alias("truth_a"),
                        pl.col("id_b").cast(pl.Int64).alias("truth_b")).cast(schema)
    los = loss_of_separation(truth, cfg) if los is None else los
    t_thr_us = int(round(cfg.conflict.t_thr_s * _US))
    parts = []
    groups = ep.partition_by(keys, as_dict=True) if keys else {(): ep}
    for gk, e in groups.items():
        iv = los.filter(pl.col("run") == gk[0]) if keys else los
        if iv.is_empty():
            continue
        u = e["epoch"].dt.epoch("us").to_numpy()
        s = iv["t_start"].dt.epoch("us").to_numpy()
        f = iv["t_end"].dt.epoch("us").to_numpy()
        lo = np.searchsorted(u, s - t_thr_us, side="left")      # t_k ≥ s − T
        hi = np.searchsorted(u, f, side="right")                # t_k ≤ e
        cnt = np.maximum(hi - lo, 0)
        which = np.repeat(np.arange(len(iv)), cnt)
        kk = np.repeat(lo, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        part = pl.DataFrame({"epoch": pl.Series(u[kk]).cast(pl.Datetime("us", "UTC")),
                             "truth_a": iv["truth_a"].to_numpy()[which], "truth_b": iv["truth_b"].to_numpy()[which]})
        if keys:
            part = part.with_columns(pl.lit(gk[0], pl.UInt32).alias("run"))
        parts.append(part.select(list(schema)))
    if not parts:
        return pl.DataFrame(schema=schema)
    return pl.concat(parts).unique().sort(list(schema)).cast(schema)


# --------------------------------------------------------------------------- episodes


_KEY = ["run", "method", "kind", "ka", "kb"]
# the same key with the method as its integer grid code: cheaper to pack, join and compare
_IKEY = ["run", "__m", "kind", "ka", "kb"]
_BITS = 1 << 62


def _grid(conflicts: pl.DataFrame, id_map: pl.DataFrame, methods: list[str] | None) -> pl.DataFrame:
    """(run, method, epoch, k, t, __m): the picture's epoch grid with a dense index k per
    (run, method) and a dense method code ``__m``."""
    if "method" in id_map.columns:
        g = id_map.select(pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String), pl.col("epoch").cast(TIME))
    else:
        ms = methods if methods is not None else sorted(conflicts["method"].unique().to_list())
        g = (id_map.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME))
             .join(pl.DataFrame({"method": ms}, schema={"method": pl.String}), how="cross"))
    c = conflicts.select(pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String), pl.col("epoch").cast(TIME))
    # conflicts usually come sorted by (run, epoch, method): dropping rows equal to their
    # predecessor first leaves unique() a few thousand rows (correct in any order)
    c = c.filter(pl.any_horizontal([pl.col(x) != pl.col(x).shift(1) for x in c.columns]).fill_null(True))
    g = pl.concat([g.select("run", "method", "epoch"), c]).unique()
    return g.sort("run", "method", "epoch").with_columns(
        (pl.col("epoch").rank("dense").over(["run", "method"]).cast(pl.Int64) - 1).alias("k"),
        _seconds("epoch").alias("t"), (pl.col("method").rank("dense").cast(pl.Int64) - 1).alias("__m"))


def _alert_rows(conflicts: pl.DataFrame, id_map: pl.DataFrame, id_col: str) -> pl.DataFrame:
    """Alert rows keyed by truth pair (kind 0) or, without two distinct truths, by id pair (kind 1);
    may hold duplicate rows (:func:`_runs` drops them)."""
    on = ["run", "epoch"] + (["method"] if "method" in id_map.columns else [])
    m = id_map.select(pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                      *([pl.col("method").cast(pl.String)] if "method" in id_map.columns else []),
                      pl.col(id_col).cast(pl.UInt64).alias("__id"), pl.col("truth_id").cast(pl.Int64)
                      ).unique(subset=[*on, "__id"], keep="first")
    # select before filtering: the filter then copies 6 columns, not the whole conflicts table
    a = (conflicts.select("alert", pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
                          pl.col("method").cast(pl.String), pl.col("id_a").cast(pl.UInt64),
                          pl.col("id_b").cast(pl.UInt64))
         .filter(pl.col("alert")).drop("alert"))
    a = (a.join(m.rename({"__id": "id_a", "truth_id": "__ta"}), on=[*on, "id_a"], how="left")
         .join(m.rename({"__id": "id_b", "truth_id": "__tb"}), on=[*on, "id_b"], how="left"))
    by_truth = pl.col("__ta").is_not_null() & pl.col("__tb").is_not_null() & (pl.col("__ta") != pl.col("__tb"))
    return a.select(
        "run", "epoch", "method",
        pl.when(by_truth).then(0).otherwise(1).cast(pl.UInt8).alias("kind"),
        pl.when(by_truth).then(pl.min_horizontal("__ta", "__tb")).otherwise(pl.col("id_a").cast(pl.Int64)).alias("ka"),
        pl.when(by_truth).then(pl.max_horizontal("__ta", "__tb")).otherwise(pl.col("id_b").cast(pl.Int64)).alias("kb"),
    )


def _packed(cols: list[np.ndarray]) -> np.ndarray:
    """One int64 code per row ordered like the rows' integer columns ``cols`` (lexicographic):
    mixed-radix packing, re-densified (np.unique) only when a radix would overflow."""
    code = np.zeros(len(cols[0]), np.int64)
    for v in cols:
        v = np.asarray(v).astype(np.int64, copy=False)
        lo, span = int(v.min()), int(v.max()) - int(v.min()) + 1
        if (int(code.max()) + 1) * span >= _BITS:
            code = np.unique(code, return_inverse=True)[1].astype(np.int64).ravel()
            if (int(code.max()) + 1) * span >= _BITS:
                v = np.unique(v, return_inverse=True)[1].astype(np.int64).ravel()
                lo, span = 0, int(v.max()) + 1
        code = code * span + (v - lo)
    return code


def _runs(frame: pl.DataFrame) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Maximal runs of consecutive grid indices k per key (``_IKEY``), by one sort and numpy
    (no ``.over()`` windows). Returns the rows sorted by (key, k) without duplicate (key, k),
    with ``__run`` (a run id, unique over all keys) and ``__next_k`` (the key's next k, −1 at its
    last row), and one row per run: the ``_KEY`` columns, ``__m``, ``__run``, k1 (last k), t0, t1."""
    n = frame.height
    if n == 0:
        rows = frame.with_columns(pl.lit(0, pl.Int64).alias("__run"), pl.lit(0, pl.Int64).alias("__next_k"))
        return rows, rows.select(*_KEY, "__m", "__run", pl.col("k").alias("k1"), pl.col("t").alias("t0"),
                                 pl.col("t").alias("t1"))
    key = _packed([frame[c].to_numpy() for c in _IKEY])
    k = frame["k"].to_numpy()
    order = np.argsort(_packed([key, k]), kind="stable")
    key, k = key[order], k[order]
    new_key = np.ones(n, bool)
    new_key[1:] = key[1:] != key[:-1]
    dk = np.diff(k, prepend=k[0])
    keep = new_key | (dk != 0)                   # the same alert from two id pairs counts once
    order, key, k, new_key, dk = order[keep], key[keep], k[keep], new_key[keep], dk[keep]
    start = new_key | (dk != 1)
    run = np.cumsum(start) - 1
    last = np.ones(len(k), bool)
    last[:-1] = new_key[1:]
    next_k = np.where(last, -1, np.roll(k, -1))  # −1 never passes the "next alert later" tests
    rows = frame[order].with_columns(pl.Series("__run", run), pl.Series("__next_k", next_k))
    s = np.flatnonzero(start)
    e = np.append(s[1:], len(k)) - 1
    t = rows["t"].to_numpy()
    runs = rows[s].select(*_KEY, "__m", "__run").with_columns(
        pl.Series("k1", k[e]), pl.Series("t0", t[s]), pl.Series("t1", t[e]))
    return rows, runs


def alert_episodes(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                   cfg: AlertConfig = AlertConfig(), id_col: str = "id",
                   methods: list[str] | None = None) -> pl.DataFrame:
    """One row per true episode and per false-alert run (definitions in the module docstring):
    run, method, kind (``"truth"`` | ``"false_alert"``), a, b (truth ids, or picture ids for
    alerts without two distinct truths), t_start, t_end, t_los, hit, first_alert, warning_s,
    flicker. ``methods`` lists the picture's methods when ``id_map`` has no method column
    (default: those present in ``conflicts``)."""
    return _episodes(_grid(conflicts, id_map, methods), conflicts, id_map, truth, cfg, id_col)


def _episodes(grid: pl.DataFrame, conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
              cfg: AlertConfig, id_col: str) -> pl.DataFrame:
    """:func:`alert_episodes` on a precomputed :func:`_grid`."""
    truth_keys = ["run"] if "run" in truth.columns else []
    early, t_thr = cfg.early, cfg.conflict.t_thr_s

    los = loss_of_separation(truth, cfg)
    epochs = grid.select(*truth_keys, "epoch").unique()
    tc = true_conflicts(truth, epochs, cfg, los=los)
    true_rows = (grid.join(tc, on=[*truth_keys, "epoch"], how="inner")
                 .select("run", "method", "__m", pl.lit(0, pl.UInt8).alias("kind"),
                         pl.col("truth_a").alias("ka"), pl.col("truth_b").alias("kb"), "k", "t"))
    # __ep / __run are unique over all keys, so they alone identify an episode / alert run
    episodes = _runs(true_rows)[1].rename({"__run": "__ep"})
    # first loss of separation reaching into [t0, t1 + T]
    lv = los.select(*truth_keys, pl.col("truth_a").alias("ka"), pl.col("truth_b").alias("kb"),
                    _seconds("t_start").alias("__s"), _seconds("t_end").alias("__e"))
    ep_los = (episodes.join(lv, on=[*truth_keys, "ka", "kb"], how="inner")
              .filter((pl.col("__e") >= pl.col("t0")) & (pl.col("__s") <= pl.col("t1") + t_thr))
              .group_by("__ep").agg(pl.col("__s").min().alias("t_los")))
    episodes = episodes.join(ep_los, on="__ep", how="left").with_columns(
        pl.coalesce(pl.max_horizontal("t_los", "t0"), "t1").alias("__hit_end"))

    alerts = _alert_rows(conflicts, id_map, id_col).join(grid, on=["run", "method", "epoch"], how="inner")
    alerts, alert_runs = _runs(alerts)
    pairs = (alerts.filter(pl.col("kind") == 0).select("run", "__m", "ka", "kb", "k", "t", "__run", "__next_k")
             .join(episodes.select("run", "__m", "ka", "kb", "__ep", "k1", "t0", "t1", "__hit_end"),
                   on=["run", "__m", "ka", "kb"], how="inner"))
    lo = pl.col("t") >= pl.col("t0") - early
    in_hit = lo & (pl.col("t") <= pl.col("__hit_end"))
    in_ep = lo & (pl.col("t") <= pl.col("t1"))
    first = (pairs.filter(in_hit).group_by("__ep").agg(pl.col("t").min().alias("first_alert")))
    flick = (pairs.join(first, on="__ep", how="inner")
             .filter((pl.col("t") >= pl.col("first_alert")) & (pl.col("__next_k") > pl.col("k") + 1)
                     & (pl.col("__next_k") <= pl.col("k1")))
             .group_by("__ep").agg(pl.len().cast(pl.Int64).alias("flicker")))
    ep = (episodes.join(first, on="__ep", how="left").join(flick, on="__ep", how="left")
          .with_columns(pl.col("first_alert").is_not_null().alias("hit"),
                        pl.when(pl.col("first_alert").is_not_null()).then(pl.col("flicker").fill_null(0))
                        .alias("flicker"),
                        (pl.col("t_los") - pl.col("first_alert")).alias("warning_s"),
                        pl.lit("truth").alias("kind_s")))
    hit_runs = pairs.filter(in_ep).select("__run").unique()
    false_runs = (alert_runs.join(hit_runs, on="__run", how="anti")
                  .with_columns(pl.lit("false_alert").alias("kind_s")))

    def to_time(c: str) -> pl.Expr:
        return (pl.col(c) * _US).round().cast(pl.Int64).cast(pl.Datetime("us", "UTC"))

    cols = [pl.col("run").cast(pl.UInt32), pl.col("method").cast(pl.String), pl.col("kind_s").alias("kind"),
            pl.col("ka").alias("a"), pl.col("kb").alias("b"), to_time("t0").alias("t_start"),
            to_time("t1").alias("t_end")]
    ep_out = ep.select(*cols, to_time("t_los").alias("t_los"), "hit", to_time("first_alert").alias("first_alert"),
                       pl.col("warning_s").cast(pl.Float64), pl.col("flicker").cast(pl.Int64))
    fa_out = false_runs.select(*cols, pl.lit(None, TIME).alias("t_los"), pl.lit(False).alias("hit"),
                               to_time("t0").alias("first_alert"), pl.lit(None, pl.Float64).alias("warning_s"),
                               pl.lit(None, pl.Int64).alias("flicker"))
    out = pl.concat([ep_out, fa_out], how="vertical_relaxed")
    return out.sort("run", "method", "kind", "a", "b", "t_start")


def score_alerts(conflicts: pl.DataFrame, id_map: pl.DataFrame, truth: pl.DataFrame,
                 cfg: AlertConfig = AlertConfig(), id_col: str = "id",
                 methods: list[str] | None = None) -> pl.DataFrame:
    """Alert quality per picture method in the ``metrics`` schema (stage ``"safety"``, segment
    ``"all"``): ``hits``, ``misses``, ``false_alerts``, ``mean_warning_s``, ``flicker``,
    ``episodes``, ``flicker_per_hit`` — see the module docstring for the definitions."""
    grid = _grid(conflicts, id_map, methods)
    ep = _episodes(grid, conflicts, id_map, truth, cfg, id_col)
    n_runs = grid.group_by("method").agg(pl.col("run").n_unique().alias("n_runs"))
    tru = ep.filter(pl.col("kind") == "truth")
    per = n_runs.join(
        tru.group_by("method").agg(
            pl.col("hit").sum().cast(pl.Float64).alias("hits"),
            (~pl.col("hit")).sum().cast(pl.Float64).alias("misses"),
            pl.col("warning_s").drop_nulls().mean().alias("mean_warning_s"),
            pl.col("flicker").drop_nulls().sum().cast(pl.Float64).alias("flicker"),
            pl.len().cast(pl.Float64).alias("episodes")),
        on="method", how="left").join(
        ep.filter(pl.col("kind") == "false_alert").group_by("method")
        .agg(pl.len().cast(pl.Float64).alias("false_alerts")), on="method", how="left")
    per = per.with_columns(pl.col("hits", "misses", "flicker", "episodes", "false_alerts").fill_null(0.0),
                           pl.col("mean_warning_s").fill_null(float("nan")))
    per = per.with_columns(pl.when(pl.col("hits") > 0).then(pl.col("flicker") / pl.col("hits"))
                           .otherwise(float("nan")).alias("flicker_per_hit"))
    long = per.unpivot(index=["method", "n_runs"], on=list(ALERT_METRICS), variable_name="metric", value_name="value")
    order = pl.col("metric").replace_strict({m: i for i, m in enumerate(ALERT_METRICS)}, return_dtype=pl.Int8)
    out = long.sort([pl.col("method"), order]).select(
        pl.lit("safety").alias("stage"), "method", "metric", pl.lit("all").alias("segment"), "value", "n_runs")
    spec = TABLES["metrics"].required
    return out.select([pl.col(c).cast(t) for c, t in spec.items()])
