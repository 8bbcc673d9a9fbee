"""Air-picture metrics (surveillance quality of a picture), computed from a *matched* frame (pure functions).

Input contract
--------------
``matched``: one row per (picture, track row), i.e. per track state a picture reports at an
epoch, after the matcher has paired it with a reference aircraft (or with none).

===========================  =====================================================================
``method`` (str)             the picture's name (becomes ``metrics.method``)
``run`` (u32), ``epoch``     Monte-Carlo run and the state's time (Datetime(us, UTC))
``track_id`` (u64)           the picture's track number
``truth_id`` (i64, null)     the reference aircraft the track row represents; null = unmatched
``x_m … vz_mps``             the track state in the system ENU frame
``alt_m, alt_rate_mps``      optional: the track's height channel (else ``z_m``/``vz_mps``)
``true_x_m … true_vz_mps``   the reference state at ``epoch`` (null when unmatched)
``true_alt_m``,              optional: reference pressure altitude and its rate (else
``true_alt_rate_mps``        ``true_z_m``/``true_vz_mps``)
``mode_s``, ``icao24``       optional: the track's Mode S address and the reference's
===========================  =====================================================================

``expected`` (optional): the reference sampled at the evaluation epochs, one row per
(run, truth_id, epoch) where the aircraft exists and has a usable reference (``"evaluated"``),
with the same ``true_*`` columns. It is what continuity needs: exposure (aircraft-hours),
update intervals with no update, and merged tracks (an aircraft with no track of its own).
Without it, exposure is the span from an aircraft's first to last matched epoch and merged
tracks are not computed.

Definitions (errors are track − reference)
------------------------------------------
* horizontal error e = (x−x*, y−y*); along = e·u, across = u_x e_y − u_y e_x (positive to the
  left of travel), u = v*/|v*| the *reference* horizontal velocity direction (rows with
  |v*| < ``min_speed_mps`` are left out of along/across/latency/track angle).      (1)
* latency τ = −mean(along / |v*|): a track that reports the position of time t − τ lags by
  along = −|v*| τ, so a positive latency is a lagging track.                          (2)
* height error: ``alt_m − true_alt_m`` when both exist, else ``z_m − true_z_m``.
* ``prob_update``: the time of each (run, aircraft) from its first expected epoch is cut into
  intervals of ``expected_interval_s``; the fraction of intervals holding ≥ 1 track update.
* representative track of an aircraft at an epoch: among the tracks matched to it then, the one
  matched to it most often over the run (ties: lowest id) — stable under short splits.
  ``id_changes_per_hour``: changes of the representative id per aircraft-hour; a swap of two
  aircraft's tracks is one change for each.
* a *break*: consecutive represented epochs of an aircraft more than ``break_gap_s`` apart;
  ``mean_reacquire_s`` is the mean length of those gaps.
* ``false_tracks_per_hour``: tracks never inside any aircraft's gate, per hour of picture (sum
  over runs of each run's epoch span), and never beyond an aircraft's reference
  (``beyond_truth_id``, :mod:`tertiary.evaluation.matching` rule 4: ``unassessed_tracks``);
  ``duplicate_tracks_per_hour``: tracks never matched but inside some aircraft's gate at some
  epoch (``gated_truth_id``: a second track of an aircraft, left unmatched by the one-to-one
  matching): which of two tracks of one aircraft the matching keeps depends on which is closer,
  not on which is real, so a second track is counted apart.
  ``split_tracks``: distinct tracks that were, at some epoch, a second track of an aircraft that
  another track represented then (an unmatched row in its gate, ``gated_truth_id``: a track matched
  at other epochs counts, as does a duplicate). ``merged_tracks``: distinct tracks whose position lay within ``merge_gate_m``
  (and ``merge_gate_v_m``) of an expected aircraft with no track of its own while representing
  another aircraft.
* identity correctness, on matched rows where both sides carry the item: ``mode_s_correct_frac``
  (track Mode S address = reference ``icao24``), ``mode_3a_correct_frac`` (track ``mode_3a`` =
  reference ``mode_3a``), ``callsign_correct_frac`` (blank-stripped, case-insensitive), and
  ``flight_level_correct_frac`` (|track alt_m − reference alt_m| ≤ ``flight_level_tolerance_m``,
  200 ft), each with its sample count ``n_mode_s``, ``n_mode_3a``, ``n_callsign``, ``n_flight_level``.
* flight phase from the reference: ``phase:turn`` if |turn rate| > ``turn_rate_dps``, else
  ``phase:climb-descent`` if |vertical rate| > ``vertical_rate_mps``, else ``phase:level``.

Output: the ``metrics`` table (stage ``evaluation``, method = picture, segment = ``all``,
``alt:0-3000m``, ``range:0-50km``, ``phase:turn`` …). Sample sizes ride along as metrics
``n_points`` (accuracy rows), ``n_update_intervals``, ``aircraft_hours``, ``picture_hours`` and
``n_tracks`` so that :mod:`tertiary.evaluation.requirements` can state the confidence of a verdict.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core.errors import DataError, OptionError
from tertiary.evaluation import sketch

__all__ = ["MetricsConfig", "BREAKDOWNS", "accuracy_errors", "band_labels", "reference_labels", "picture_metrics"]

BREAKDOWNS = ("alt", "range", "phase")
STAGE = "evaluation"
_KEY = ["method", "run", "truth_id"]
_US_PER_H = 3.6e9


@dataclass(frozen=True)
class MetricsConfig:
    """Settings of the picture metrics (every threshold documented in the module docstring)."""

    expected_interval_s: float = 5.0
    break_gap_s: float | None = None          # None: 3 × expected_interval_s
    min_speed_mps: float = 10.0
    alt_bands_m: tuple[float, ...] = (0.0, 3000.0, 6000.0, 9000.0, 15000.0)
    range_rings_m: tuple[float, ...] = (0.0, 50_000.0, 100_000.0, 150_000.0, 250_000.0)
    turn_rate_dps: float = 0.5
    vertical_rate_mps: float = 2.5
    merge_gate_m: float = 1000.0
    merge_gate_v_m: float = 300.0
    #: a track's flight level is correct within ± this of the reference pressure altitude
    #: (200 ft: a Mode C code is validated within ±200 ft in ICAO Annex 10 / Doc 8071 practice)
    flight_level_tolerance_m: float = 60.96

    @property
    def gap_s(self) -> float:
        return 3.0 * self.expected_interval_s if self.break_gap_s is None else self.break_gap_s


# --------------------------------------------------------------------------- checks and helpers


def _require(columns: Sequence[str], cols: Sequence[str], what: str) -> None:
    missing = [c for c in cols if c not in columns]
    if missing:
        raise DataError(f"{what} is missing column(s) {', '.join(missing)}")


def height_exprs(frame: pl.DataFrame, prefix: str = "") -> tuple[pl.Expr, pl.Expr]:
    """(height, height rate) expressions: the altitude channel when present, else ENU z/vz."""
    alt, rate = f"{prefix}alt_m", f"{prefix}alt_rate_mps"
    h = pl.col(alt) if alt in frame.columns else pl.col(f"{prefix}z_m")
    hd = pl.col(rate) if rate in frame.columns else pl.col(f"{prefix}vz_mps")
    return h, hd


def band_labels(values: pl.Expr, edges: Sequence[float], prefix: str, scale: float, unit: str) -> pl.Expr:
    """``prefix:lo-hi<unit>`` for values in [lo, hi), null outside every band."""
    out = pl.lit(None, dtype=pl.String)
    for lo, hi in zip(edges[-2::-1], edges[:0:-1]):           # reversed so the first band wins
        label = f"{prefix}:{lo / scale:g}-{hi / scale:g}{unit}"
        out = pl.when((values >= lo) & (values < hi)).then(pl.lit(label)).otherwise(out)
    return out


# --------------------------------------------------------------------------- per-row quantities


def accuracy_errors(matched: pl.DataFrame, cfg: MetricsConfig = MetricsConfig()) -> pl.DataFrame:
    """``matched`` rows with a reference, with the error columns of (1)–(2): ``err_h_m``,
    ``along_m``, ``across_m``, ``err_height_m``, ``err_gs_mps``, ``err_track_deg``,
    ``err_vrate_mps``, ``latency_sample_s`` (null where the reference is too slow)."""
    m = matched.filter(pl.col("truth_id").is_not_null() & pl.col("true_x_m").is_not_null())
    h, hd = height_exprs(m)
    th, thd = height_exprs(m, "true_")
    ex, ey = pl.col("x_m") - pl.col("true_x_m"), pl.col("y_m") - pl.col("true_y_m")
    gs_t = (pl.col("true_vx_mps") ** 2 + pl.col("true_vy_mps") ** 2).sqrt()
    gs = (pl.col("vx_mps") ** 2 + pl.col("vy_mps") ** 2).sqrt()
    fast = gs_t >= cfg.min_speed_mps
    ux, uy = pl.col("true_vx_mps") / gs_t, pl.col("true_vy_mps") / gs_t
    along = ex * ux + ey * uy
    dang = pl.arctan2(pl.col("vx_mps"), pl.col("vy_mps")) - pl.arctan2(pl.col("true_vx_mps"), pl.col("true_vy_mps"))
    dang = (dang + np.pi) % (2 * np.pi) - np.pi            # wrap to [-π, π)
    return m.with_columns(
        (ex * ex + ey * ey).sqrt().alias("err_h_m"),
        pl.when(fast).then(along).alias("along_m"),
        pl.when(fast).then(ux * ey - uy * ex).alias("across_m"),
        (h - th).alias("err_height_m"),
        (gs - gs_t).alias("err_gs_mps"),
        pl.when(fast).then(dang.degrees()).alias("err_track_deg"),
        (hd - thd).alias("err_vrate_mps"),
        pl.when(fast).then(-along / gs_t).alias("latency_sample_s"),
    )


def reference_labels(ref: pl.DataFrame, radar_xy: NDArray[np.float64] | None = None,
                     cfg: MetricsConfig = MetricsConfig(), keys: Sequence[str] = ("run", "truth_id")) -> pl.DataFrame:
    """Breakdown labels of unique reference states (``keys``, epoch, ``true_*``): columns
    ``alt`` (altitude band), ``range`` (ring from the nearest radar in ``radar_xy`` (R, 2), the
    system-frame sites; null without radars) and ``phase`` (from the reference turn and
    vertical rates; turn rate by differencing the reference heading between epochs of the same
    ``keys``)."""
    by = list(keys)
    ref = ref.unique([*by, "epoch"]).sort([*by, "epoch"])
    th, thd = height_exprs(ref, "true_")
    heading = pl.arctan2(pl.col("true_vx_mps"), pl.col("true_vy_mps"))
    # sorted by aircraft: a step is between a row and the one before it of the same aircraft
    # (a mask on plain differences, not a window function per aircraft)
    same = ~pl.any_horizontal(pl.col(k).ne_missing(pl.col(k).shift(1)) for k in by)
    dt = pl.when(same).then(pl.col("epoch").diff().dt.total_microseconds() / 1e6)
    dpsi = pl.when(same).then((heading.diff() + np.pi) % (2 * np.pi) - np.pi)
    rate = (dpsi / dt).degrees().abs()
    rate = pl.coalesce(rate, pl.when(same.shift(-1)).then(rate.shift(-1)))   # first epoch: the next step's rate
    phase = (pl.when(rate > cfg.turn_rate_dps).then(pl.lit("phase:turn"))
             .when(thd.abs() > cfg.vertical_rate_mps).then(pl.lit("phase:climb-descent"))
             .otherwise(pl.lit("phase:level")))
    out = ref.select(*by, "epoch", band_labels(th, cfg.alt_bands_m, "alt", 1.0, "m").alias("alt"),
                     phase.alias("phase"))
    if radar_xy is not None and len(radar_xy):
        xy = ref.select("true_x_m", "true_y_m").to_numpy()
        d = np.min(np.hypot(xy[:, None, 0] - radar_xy[None, :, 0], xy[:, None, 1] - radar_xy[None, :, 1]), axis=1)
        rng = pl.Series("__rng", d)
        out = out.with_columns(band_labels(pl.lit(rng), cfg.range_rings_m, "range", 1000.0, "km").alias("range"))
    else:
        out = out.with_columns(pl.lit(None, dtype=pl.String).alias("range"))
    # categorical inside the stage: a label is repeated on every (aircraft, epoch) of a run and
    # on every copy of a breakdown (4 bytes a row, not a string); the output segments are text
    return out.with_columns(pl.col(c).cast(pl.Categorical) for c in ("alt", "phase", "range"))


#: segment "all", of the labels' type (categorical: see :func:`reference_labels`)
_ALL = pl.lit("all").cast(pl.Categorical)


def by_segment(frame: pl.DataFrame, breakdown: Sequence[str], *aggs: pl.Expr, by: Sequence[str] = ()) -> pl.DataFrame:
    """``aggs`` per (method, segment, ``by``…): segment ``all`` (every row) and each label of each
    breakdown column (the rows that have it). Grouped in place, once per breakdown: the frame
    is never copied per label (the memory of the stage on a long run)."""
    parts = [frame.group_by("method", _ALL.alias("segment"), *by).agg(*aggs)]
    for b in breakdown:
        parts.append(frame.group_by("method", pl.col(b).alias("segment"), *by).agg(*aggs)
                     .filter(pl.col("segment").is_not_null()))
    return pl.concat(parts, how="vertical")


def long_rows(wide: pl.DataFrame, names: Sequence[str]) -> pl.DataFrame:
    """(method, segment, n_runs, metric columns) → metrics rows (NaN/null values dropped)."""
    return (wide.unpivot(index=["method", "segment", "n_runs"], on=list(names), variable_name="metric")
            .filter(pl.col("value").is_not_null() & pl.col("value").is_finite()))


# --------------------------------------------------------------------------- metric groups


#: the accuracy percentiles: (quantity, q) of a quantile sketch (:mod:`tertiary.evaluation.sketch`,
#: within its relative accuracy of the order statistic), mergeable over any split of the rows
PERCENTILES = {"p95_horizontal_m": ("horizontal", 0.95), "p99_horizontal_m": ("horizontal", 0.99),
               "p95_height_m": ("height", 0.95)}


def percentile_counts(err: pl.DataFrame, breakdown: Sequence[str]) -> pl.DataFrame:
    """The sketch of the horizontal and absolute height errors per (method, segment)."""
    parts = []
    for quantity, values in (("horizontal", pl.col("err_h_m")), ("height", pl.col("err_height_m").abs())):
        keyed = err.select("method", *breakdown, sketch.bucket(values).alias(sketch.KEY)).drop_nulls(sketch.KEY)
        parts.append(by_segment(keyed, breakdown, pl.len().cast(pl.UInt64).alias(sketch.COUNT), by=[sketch.KEY])
                     .with_columns(pl.lit(quantity).alias("quantity")))
    return pl.concat(parts).select("method", "segment", "quantity", sketch.KEY, sketch.COUNT)


def percentiles(counts: pl.DataFrame) -> pl.DataFrame:
    """(method, segment, the :data:`PERCENTILES`) of merged :func:`percentile_counts`."""
    return sketch.quantiles(counts, ["method", "segment"], PERCENTILES)


def _accuracy(err: pl.DataFrame, breakdown: Sequence[str]) -> pl.DataFrame:
    def rms(c: str) -> pl.Expr:
        return (pl.col(c) ** 2).mean().sqrt()

    wide = by_segment(
        err, breakdown,
        pl.col("run").n_unique().alias("n_runs"),
        rms("err_h_m").alias("rmse_horizontal_m"),
        rms("err_height_m").alias("rmse_height_m"),
        pl.col("err_h_m").max().alias("max_horizontal_m"),
        pl.col("err_height_m").abs().max().alias("max_height_m"),
        rms("along_m").alias("along_track_rms_m"),
        pl.col("along_m").mean().alias("along_track_bias_m"),
        rms("across_m").alias("across_track_rms_m"),
        pl.col("across_m").mean().alias("across_track_bias_m"),
        pl.col("latency_sample_s").mean().alias("latency_s"),
        rms("err_gs_mps").alias("ground_speed_rms_mps"),
        pl.col("err_gs_mps").mean().alias("ground_speed_bias_mps"),
        rms("err_track_deg").alias("track_angle_rms_deg"),
        rms("err_vrate_mps").alias("vertical_rate_rms_mps"),
        pl.len().cast(pl.Float64).alias("n_points"),
    )
    wide = wide.join(percentiles(percentile_counts(err, breakdown)), on=["method", "segment"], how="left")
    names = [c for c in wide.columns if c not in ("method", "segment", "n_runs")]
    return long_rows(wide, names)


def representatives(m: pl.DataFrame) -> pl.DataFrame:
    """One row per (method, run, truth_id, epoch): the representative track (see docstring)."""
    counts = m.group_by(_KEY + ["track_id"]).agg(pl.len().alias("__n"))
    return (m.join(counts, on=_KEY + ["track_id"])
            .sort(_KEY + ["epoch", "__n", "track_id"], descending=[False] * 4 + [True, False])
            .unique(_KEY + ["epoch"], keep="first", maintain_order=True))


def exposure_rows(rep: pl.DataFrame, expected: pl.DataFrame | None, methods: pl.DataFrame,
              labels: pl.DataFrame, cfg: MetricsConfig) -> pl.DataFrame:
    """Rows carrying the observed time of each aircraft: ``expected`` (crossed with the
    pictures; a row counts until the next one, at most ``gap_s`` — a longer step is a reference
    gap, not evaluated) or, without it, the representative rows (a row counts until the next
    represented epoch: gaps are inside the aircraft's span)."""
    if expected is None:
        rows, cap = rep.select(_KEY + ["epoch"]), None
    else:
        rows, cap = expected.select("run", "truth_id", "epoch").unique().join(methods, how="cross"), cfg.gap_s
    rows = rows.sort(_KEY + ["epoch"])
    dt = (pl.col("epoch").shift(-1).over(_KEY) - pl.col("epoch")).dt.total_microseconds().fill_null(0) / 1e6
    if cap is not None:
        dt = pl.when(dt > cap).then(0.0).otherwise(dt)
    return rows.with_columns((dt / 3600.0).alias("__hours")).join(labels, on=["run", "truth_id", "epoch"], how="left")


def update_intervals(rep: pl.DataFrame, expo: pl.DataFrame, cfg: MetricsConfig, span: bool) -> pl.DataFrame:
    """(method, run, truth_id, bin, labels…, updated) per expected update interval: the
    intervals holding an ``expo`` row, or (``span``) every interval from the first to the last
    ``expo`` row, labelled by the last row at or before its start."""
    t_us = int(round(cfg.expected_interval_s * 1e6))
    t0 = expo.group_by(_KEY).agg(pl.col("epoch").min().alias("__t0"))

    def binned(f: pl.DataFrame) -> pl.DataFrame:
        return f.join(t0, on=_KEY).with_columns(
            ((pl.col("epoch") - pl.col("__t0")).dt.total_microseconds() // t_us).alias("__bin"))

    bins = binned(expo).sort(_KEY + ["epoch"]).unique(_KEY + ["__bin"], keep="first", maintain_order=True)
    if span:
        every = (bins.group_by(_KEY).agg(pl.int_ranges(0, pl.col("__bin").max() + 1).first().alias("__bin"),
                                         pl.col("__t0").first())
                 .explode("__bin").with_columns(
                     (pl.col("__t0") + pl.duration(microseconds=pl.col("__bin") * t_us)).alias("epoch"))
                 .drop("__t0").sort("epoch"))
        labels = [c for c in bins.columns if c not in _KEY + ["__bin", "__t0", "epoch", "__hours"]]
        bins = every.join_asof(bins.select(_KEY + ["epoch"] + labels).sort("epoch"), on="epoch",
                               by=_KEY, strategy="backward", check_sortedness=False)  # sorted by epoch
    upd = binned(rep).select(_KEY + ["__bin"]).unique().with_columns(pl.lit(True).alias("updated"))
    return bins.join(upd, on=_KEY + ["__bin"], how="left").with_columns(pl.col("updated").fill_null(False))


#: what :func:`accuracy_errors` and the identity checks read of a matched picture (beside ``true_*``)
ERROR_INPUTS = (*_KEY, "epoch", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps", "alt_m", "alt_rate_mps",
                 "mode_s", "icao24", "mode_3a", "callsign")
#: the error columns of :func:`accuracy_errors`
_ERRORS = ("err_h_m", "along_m", "across_m", "err_height_m", "err_gs_mps", "err_track_deg", "err_vrate_mps",
           "latency_sample_s")
#: the items :func:`identity_checks` compares
_IDENTITY = ("mode_s", "icao24", "mode_3a", "true_mode_3a", "callsign", "true_callsign", "alt_m", "true_alt_m")
#: what the continuity metrics read of a matched picture
CONTINUITY_INPUTS = (*_KEY, "epoch", "track_id", "x_m", "y_m", "z_m", "alt_m")


def rep_events(m: pl.DataFrame, labels: pl.DataFrame, cfg: MetricsConfig) -> pl.DataFrame:
    """The representative rows with their labels, id change (``__change``), time since the
    aircraft's previous represented epoch (``__gap_s``) and break flag (``__break``)."""
    rep = representatives(m).sort(_KEY + ["epoch"])
    gap = (pl.col("epoch") - pl.col("epoch").shift(1).over(_KEY)).dt.total_microseconds() / 1e6
    rep = rep.with_columns(
        (pl.col("track_id") != pl.col("track_id").shift(1).over(_KEY)).fill_null(False).alias("__change"),
        gap.alias("__gap_s")).join(labels, on=["run", "truth_id", "epoch"], how="left")
    return rep.with_columns((pl.col("__gap_s") > cfg.gap_s).fill_null(False).alias("__break"))


def continuity_rows(hours: pl.DataFrame, events: pl.DataFrame, ints: pl.DataFrame) -> pl.DataFrame:
    """Metrics rows of the continuity groups per (method, segment): ``hours`` (aircraft_hours,
    n_runs), ``events`` (__changes, track_breaks, mean_reacquire_s), ``ints`` (prob_update,
    n_update_intervals); a segment without exposure has none of them."""
    wide = (hours.join(events, on=["method", "segment"], how="left").join(ints, on=["method", "segment"], how="left")
            .with_columns((pl.col("__changes") / pl.col("aircraft_hours")).alias("id_changes_per_hour"),
                          (pl.col("track_breaks") / pl.col("aircraft_hours")).alias("track_breaks_per_hour"),
                          pl.col("track_breaks").cast(pl.Float64)))
    names = ["aircraft_hours", "id_changes_per_hour", "track_breaks", "track_breaks_per_hour",
             "mean_reacquire_s", "prob_update", "n_update_intervals"]
    return long_rows(wide, names)


def _continuity(m: pl.DataFrame, expected: pl.DataFrame | None, labels: pl.DataFrame,
                breakdown: Sequence[str], cfg: MetricsConfig, gated: pl.DataFrame | None = None) -> pl.DataFrame:
    # what the continuity metrics read: a long picture's other columns are not copied through them
    m = m.select(c for c in m.columns if c in CONTINUITY_INPUTS)
    rep = rep_events(m, labels, cfg)
    methods = m.select("method").unique()
    expo = exposure_rows(rep, expected, methods, labels, cfg)
    hours = by_segment(expo, breakdown,
                        pl.col("__hours").sum().alias("aircraft_hours"), pl.col("run").n_unique().alias("n_runs"))
    events = by_segment(rep, breakdown,
                         pl.col("__change").sum().alias("__changes"), pl.col("__break").sum().alias("track_breaks"),
                         pl.col("__gap_s").filter(pl.col("__break")).mean().alias("mean_reacquire_s"))
    ints = by_segment(update_intervals(rep, expo, cfg, expected is None), breakdown,
                       pl.col("updated").mean().alias("prob_update"),
                       pl.len().cast(pl.Float64).alias("n_update_intervals"))
    out = [continuity_rows(hours, events, ints), _split(rep, m, labels, breakdown, gated)]
    if expected is not None and {"true_x_m", "true_y_m"} <= set(expected.columns):
        out.append(_merged(m, rep.select(m.columns), expected, labels, methods, breakdown, cfg))
    return pl.concat(out, how="vertical")


def gated_rows(rows: pl.DataFrame, truth_dtype: pl.DataType) -> pl.DataFrame:
    """The unmatched rows of ``rows`` that lie in an aircraft's gate, as rows of that aircraft
    (``truth_id`` = ``gated_truth_id``): (method, run, truth_id, epoch, track_id). The matching
    is one to one, so a second track of an aircraft is one of these, never a second match."""
    key = ["method", "run", pl.col("gated_truth_id").cast(truth_dtype).alias("truth_id"), "epoch", "track_id"]
    if "gated_truth_id" not in rows.columns:
        return rows.select(*key[:2], pl.lit(None, truth_dtype).alias("truth_id"), *key[3:]).clear()
    return rows.filter(pl.col("truth_id").is_null() & pl.col("gated_truth_id").is_not_null()).select(key)


def second_tracks(rep: pl.DataFrame, m: pl.DataFrame, labels: pl.DataFrame,
                  gated: pl.DataFrame | None = None) -> pl.DataFrame:
    """The rows of ``m`` and ``gated`` (:func:`gated_rows`) whose track is not their aircraft's
    representative at an epoch that has one, labelled."""
    rows = m.select(*_KEY, "epoch", "track_id")
    if gated is not None and gated.height:
        rows = pl.concat([rows, gated.select(rows.columns).cast(rows.schema)])
    return (rows.join(rep.select(_KEY + ["epoch", pl.col("track_id").alias("__rep")]), on=_KEY + ["epoch"])
            .filter(pl.col("track_id") != pl.col("__rep")).join(labels, on=["run", "truth_id", "epoch"], how="left"))


def _split(rep: pl.DataFrame, m: pl.DataFrame, labels: pl.DataFrame, breakdown: Sequence[str],
           gated: pl.DataFrame | None) -> pl.DataFrame:
    base = rep.select("method", "run").unique()
    return count_tracks(second_tracks(rep, m, labels, gated), base, breakdown, "split_tracks")


def count_tracks(events: pl.DataFrame, base: pl.DataFrame, breakdown: Sequence[str], name: str) -> pl.DataFrame:
    """Distinct (run, track_id) per (method, segment); zero in ``all`` for pictures without any."""
    got = by_segment(events, breakdown, pl.struct("run", "track_id").n_unique().cast(pl.Float64).alias(name),
                      pl.col("run").n_unique().alias("n_runs"))
    zero = base.group_by("method").agg(pl.col("run").n_unique().alias("n_runs")).with_columns(
        _ALL.alias("segment"), pl.lit(0.0).alias(name))
    got = pl.concat([got, zero.join(got, on=["method", "segment"], how="anti").select(got.columns)])
    return long_rows(got, [name])


def bare_rows(m: pl.DataFrame, expected: pl.DataFrame, methods: pl.DataFrame) -> pl.DataFrame:
    """The expected rows (× pictures) of an aircraft with no track of its own at their epoch:
    (method, run, epoch, truth_id, true_x_m, true_y_m, ``__h`` its height)."""
    exp = expected.join(methods, how="cross")
    covered = m.filter(pl.col("truth_id").is_not_null()).select("method", "run", "truth_id", "epoch").unique()
    bare = exp.join(covered, on=["method", "run", "truth_id", "epoch"], how="anti")
    th, _ = height_exprs(bare, "true_")
    return bare.select("method", "run", "epoch", "truth_id", "true_x_m", "true_y_m", th.alias("__h"))


def rep_points(rep: pl.DataFrame) -> pl.DataFrame:
    """Where each representative track is: (method, run, epoch, track_id, ``__other`` the aircraft
    it represents, x_m, y_m, ``__th`` its height)."""
    h, _ = height_exprs(rep)
    return rep.select("method", "run", "epoch", "track_id", pl.col("truth_id").alias("__other"), "x_m", "y_m",
                      h.alias("__th"))


def _cells(frame: pl.DataFrame, x: str, y: str, side: float, spread: bool) -> pl.DataFrame:
    """``frame`` with its grid cell (cx, cy) of ``side`` metres; ``spread``: one row per cell of
    its 3 × 3 neighbourhood."""
    out = frame.with_columns((pl.col(x) / side).floor().cast(pl.Int64).alias("cx"),
                             (pl.col(y) / side).floor().cast(pl.Int64).alias("cy"))
    if not spread:
        return out
    nb = pl.DataFrame({"__dx": np.repeat([-1, 0, 1], 3), "__dy": np.tile([-1, 0, 1], 3)})
    return (out.join(nb, how="cross").with_columns(pl.col("cx") + pl.col("__dx"), pl.col("cy") + pl.col("__dy"))
            .drop("__dx", "__dy"))


def merge_hits(bare: pl.DataFrame, trk: pl.DataFrame, cfg: MetricsConfig, spread_bare: bool = True) -> pl.DataFrame:
    """(bare row, representative track) pairs within the merge gates (a grid-cell join: cells of
    side ``merge_gate_m``, one side spread over its 3 × 3 cells — ``spread_bare`` or the
    tracks: the smaller side should be spread, the pairs are the same)."""
    g = cfg.merge_gate_m
    near = ((pl.col("x_m") - pl.col("true_x_m")) ** 2 + (pl.col("y_m") - pl.col("true_y_m")) ** 2) <= g * g
    return (_cells(bare, "true_x_m", "true_y_m", g, spread_bare)
            .join(_cells(trk, "x_m", "y_m", g, not spread_bare), on=["method", "run", "epoch", "cx", "cy"])
            .filter((pl.col("__other") != pl.col("truth_id")) & near
                    & ((pl.col("__th") - pl.col("__h")).abs() <= cfg.merge_gate_v_m)))


def _merged(m: pl.DataFrame, rep: pl.DataFrame, expected: pl.DataFrame, labels: pl.DataFrame,
            methods: pl.DataFrame, breakdown: Sequence[str], cfg: MetricsConfig) -> pl.DataFrame:
    """Representative tracks lying on an expected aircraft that has no track of its own
    (grid-cell join: each bare aircraft looks in its 3 × 3 cells of side ``merge_gate_m``)."""
    hits = (merge_hits(bare_rows(m, expected, methods), rep_points(rep), cfg)
            .join(labels, on=["run", "truth_id", "epoch"], how="left"))
    return count_tracks(hits, m.select("method", "run").unique(), breakdown, "merged_tracks")


def identity_checks(err: pl.DataFrame, cfg: MetricsConfig) -> list[tuple[str, pl.Expr]]:
    """(item, "is correct" expression, null where a side lacks the item) for every identity item
    both the picture and the reference carry."""
    cols = set(err.columns)
    checks = []
    if {"mode_s", "icao24"} <= cols:
        checks.append(("mode_s", pl.col("mode_s").str.to_lowercase() == pl.col("icao24").str.to_lowercase()))
    if {"mode_3a", "true_mode_3a"} <= cols:
        checks.append(("mode_3a", pl.col("mode_3a").cast(pl.String) == pl.col("true_mode_3a").cast(pl.String)))
    if {"callsign", "true_callsign"} <= cols:
        norm = lambda c: pl.col(c).str.replace_all(" ", "").str.to_uppercase()  # noqa: E731
        checks.append(("callsign", norm("callsign") == norm("true_callsign")))
    if {"alt_m", "true_alt_m"} <= cols:
        dh = pl.col("alt_m").cast(pl.Float64).fill_nan(None) - pl.col("true_alt_m")
        checks.append(("flight_level", dh.abs() <= cfg.flight_level_tolerance_m))
    return checks


def identity_rows(err: pl.DataFrame, breakdown: Sequence[str], ok: pl.Expr) -> pl.DataFrame:
    """(method, run, labels…, ``__ok``) of the rows where both sides carry the item."""
    return err.select("method", "run", *breakdown, ok.alias("__ok")).filter(pl.col("__ok").is_not_null())


def _identity(err: pl.DataFrame, breakdown: Sequence[str], name: str, ok: pl.Expr) -> pl.DataFrame:
    w = by_segment(identity_rows(err, breakdown, ok), breakdown, pl.col("run").n_unique().alias("n_runs"),
                    pl.col("__ok").mean().alias(f"{name}_correct_frac"), pl.len().cast(pl.Float64).alias(f"n_{name}"))
    return long_rows(w, [f"{name}_correct_frac", f"n_{name}"])


#: what :func:`track_table` reads of a matched picture (and ``gated_truth_id`` when it has it)
TRACK_INPUTS = ("method", "run", "track_id", "epoch", "truth_id")


def track_inputs(m: pl.DataFrame | pl.LazyFrame) -> pl.DataFrame | pl.LazyFrame:
    """The columns of matched rows ``m`` that :func:`track_table` reads."""
    names = m.collect_schema().names() if isinstance(m, pl.LazyFrame) else m.columns
    return m.select(*TRACK_INPUTS, *(c for c in ("gated_truth_id", "beyond_truth_id") if c in names))


def track_table(m: pl.DataFrame | pl.LazyFrame) -> pl.DataFrame | pl.LazyFrame:
    """One row per (method, run, track_id): ``__real`` (some row has a truth_id), ``__gated``
    (some row lies in an aircraft's gate: matched, or ``gated_truth_id``; rows without that
    column count as matched only), ``__beyond`` (some row is beyond an aircraft's reference,
    ``beyond_truth_id``), its first and last epochs ``__t0``, ``__t1`` (a picture's span is that
    of its tracks' rows)."""
    names = m.collect_schema().names() if isinstance(m, pl.LazyFrame) else m.columns
    hit = pl.col("truth_id").is_not_null()
    gated = (hit | pl.col("gated_truth_id").is_not_null()) if "gated_truth_id" in names else hit
    beyond = pl.col("beyond_truth_id").is_not_null() if "beyond_truth_id" in names else pl.lit(False)
    return m.group_by("method", "run", "track_id").agg(hit.any().alias("__real"), gated.any().alias("__gated"),
                                                       beyond.any().alias("__beyond"),
                                                       pl.col("epoch").min().alias("__t0"),
                                                       pl.col("epoch").max().alias("__t1"))


#: the per-picture counts of :func:`picture_rows`, in their order
PICTURE_COUNTS = ("picture_hours", "n_tracks", "false_tracks", "false_tracks_per_hour", "duplicate_tracks",
                  "duplicate_tracks_per_hour", "unassessed_tracks")


def picture_rows(tracks: pl.DataFrame) -> pl.DataFrame:
    """:data:`PICTURE_COUNTS` per method, from :func:`track_table`: a *false* track never lies in
    an aircraft's gate nor beyond an aircraft's reference; a *duplicate* never represents an
    aircraft but lies in one's gate (a second track of it, which the one-to-one matching leaves to
    the first); an *unassessed* track lies in no gate, but beyond an aircraft's reference at
    some epoch (the matcher's rule 4: a track of an aircraft the reference no longer has)."""
    span = tracks.group_by("method", "run").agg(
        ((pl.col("__t1").max() - pl.col("__t0").min()).dt.total_microseconds() / _US_PER_H).alias("__h"))
    hours = span.group_by("method").agg(pl.col("__h").sum().alias("picture_hours"),
                                        pl.col("run").n_unique().alias("n_runs"))
    beyond = pl.col("__beyond").fill_null(False) if "__beyond" in tracks.columns else pl.lit(False)
    false = tracks.group_by("method").agg((~pl.col("__gated") & ~beyond).sum().cast(pl.Float64).alias("false_tracks"),
                                          (pl.col("__gated") & ~pl.col("__real")).sum().cast(pl.Float64)
                                          .alias("duplicate_tracks"),
                                          (~pl.col("__gated") & beyond).sum().cast(pl.Float64)
                                          .alias("unassessed_tracks"),
                                          pl.len().cast(pl.Float64).alias("n_tracks"))
    wide = hours.join(false, on="method").with_columns(
        _ALL.alias("segment"),
        (pl.col("false_tracks") / pl.col("picture_hours")).alias("false_tracks_per_hour"),
        (pl.col("duplicate_tracks") / pl.col("picture_hours")).alias("duplicate_tracks_per_hour"))
    return long_rows(wide, list(PICTURE_COUNTS))


def _identity_and_false(m: pl.DataFrame, err: pl.DataFrame, breakdown: Sequence[str],
                        cfg: MetricsConfig = MetricsConfig()) -> pl.DataFrame:
    out = [picture_rows(track_table(track_inputs(m)))]
    out += [_identity(err, breakdown, name, ok) for name, ok in identity_checks(err, cfg)]
    return pl.concat(out, how="vertical")


# --------------------------------------------------------------------------- entry point

#: the columns a matched picture must have
_MATCHED_REQUIRED = ("method", "run", "epoch", "track_id", "truth_id", "x_m", "y_m", "z_m", "vx_mps", "vy_mps",
                     "vz_mps", "true_x_m", "true_y_m", "true_z_m", "true_vx_mps", "true_vy_mps", "true_vz_mps")


def checked_breakdown(columns: Sequence[str], exp_columns: Sequence[str] | None, radar_xy: NDArray[np.float64] | None,
             breakdown: Sequence[str], cfg: MetricsConfig) -> list[str]:
    """Checks the inputs; the breakdowns that apply (``range`` needs radars)."""
    bad = [b for b in breakdown if b not in BREAKDOWNS]
    if bad:
        raise OptionError(f"unknown breakdown {', '.join(bad)}; expected any of {', '.join(BREAKDOWNS)}",
                          option="breakdown")
    if cfg.expected_interval_s <= 0:
        raise OptionError("must be > 0", option="expected_interval_s")
    _require(columns, _MATCHED_REQUIRED, "matched table")
    if exp_columns is not None:
        _require(exp_columns, ["run", "truth_id", "epoch"], "expected reference table")
    return [b for b in breakdown if b != "range" or radar_xy is not None]


#: the reference columns :func:`reference_labels` reads (a height and its rate: ``true_alt_*``
#: where there is one, else ENU ``true_z_m``/``true_vz_mps``)
LABEL_INPUTS = ("true_x_m", "true_y_m", "true_vx_mps", "true_vy_mps", "true_alt_m", "true_alt_rate_mps", "true_z_m",
                "true_vz_mps")


def picture_labels(matched: pl.DataFrame, expected: pl.DataFrame | None, radar_xy: NDArray[np.float64] | None,
            cfg: MetricsConfig) -> pl.DataFrame:
    """:func:`reference_labels` of ``expected`` when it has the reference columns the labels read
    that the picture has (:data:`LABEL_INPUTS`), else of the reference on the matched rows (then
    only tracked epochs are labelled)."""
    ref_cols = [c for c in matched.columns if c in LABEL_INPUTS]
    ref = (expected if expected is not None and set(ref_cols) <= set(expected.columns)
           else matched.filter(pl.col("truth_id").is_not_null()).select(["run", "truth_id", "epoch"] + ref_cols))
    return reference_labels(ref, radar_xy, cfg)


def error_rows(matched: pl.DataFrame, labels: pl.DataFrame, cfg: MetricsConfig,
               on: Sequence[str] = ("run", "truth_id", "epoch")) -> pl.DataFrame:
    """:func:`accuracy_errors` with the identity items and the labels (joined ``on``): the
    columns it reads, then the rows (a long picture is never copied whole through the errors'
    joins)."""
    cols = [c for c in matched.columns if c in ERROR_INPUTS or c.startswith("true_")]
    return (accuracy_errors(matched.select(cols), cfg)
            .select(c for c in (*_KEY, "epoch", *_ERRORS, *_IDENTITY) if c in matched.columns or c in _ERRORS)
            .join(labels, on=list(on), how="left"))


def finish_metrics(parts: list[pl.DataFrame]) -> pl.DataFrame:
    """The metrics rows of every group in the ``metrics`` table schema, in a fixed order."""
    out = pl.concat(parts, how="vertical")
    return out.select(pl.lit(STAGE).alias("stage"), "method", "metric", pl.col("segment").cast(pl.String),
                      pl.col("value").cast(pl.Float64), pl.col("n_runs").cast(pl.UInt32)
                      ).sort("method", "metric", "segment")


def picture_metrics(matched: pl.DataFrame, *, expected: pl.DataFrame | None = None,
                    radar_xy: NDArray[np.float64] | None = None, breakdown: Sequence[str] = BREAKDOWNS,
                    cfg: MetricsConfig = MetricsConfig()) -> pl.DataFrame:
    """Every air-picture metric of every picture in ``matched``, in the ``metrics`` table schema.

    ``breakdown``: any of ``alt``, ``range`` (needs ``radar_xy``, the radar sites (R, 2) in the
    system frame), ``phase``; segment ``all`` is always there.
    """
    breakdown = checked_breakdown(matched.columns, None if expected is None else expected.columns, radar_xy, breakdown, cfg)
    labels = picture_labels(matched, expected, radar_xy, cfg)
    # the columns each group reads, then the rows: a long picture is never copied whole through
    # the errors' and the continuity's joins, and each group's rows are released before the next
    # group's are made (memory of the stage)
    err = error_rows(matched, labels, cfg)
    parts = [_accuracy(err, breakdown),
             _identity_and_false(matched, err, breakdown, cfg)]
    del err
    m = matched.select(c for c in matched.columns if c in CONTINUITY_INPUTS).filter(pl.col("truth_id").is_not_null())
    if m.height:
        parts.append(_continuity(m, expected, labels, breakdown, cfg, gated_rows(matched, m.schema["truth_id"])))
    return finish_metrics(parts)


