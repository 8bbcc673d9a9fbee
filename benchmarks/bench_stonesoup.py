"""Stone Soup side by side (issue 18 item 4): the same terminal-area reports through Stone Soup's
standard multi-target tracker and through ``tertiary``'s production picture, back to back.

Both jobs run in a fresh process each (``_util.run_isolated``: wall time from reading the
dataset to the tracks written, peak RSS of the process); both are scored here, afterwards,
with ONE rule (:func:`score`).

(a) Stone Soup (``pip install 'tertiary[bench]'``): the reports' plots (``range_m``,
    ``azimuth_deg``, ``elevation_deg``, every report of run 0, false plots included) as
    ``Detection`` s, each with its radar's ``CartesianToElevationBearingRange`` (the site's
    position and axes in the system ENU frame, σ from ``radars``); 3-D constant velocity
    (``ConstantVelocity`` ×3, q = ``--q``), ``ExtendedKalmanPredictor`` /
    ``ExtendedKalmanUpdater``, ``DistanceHypothesiser`` (``Mahalanobis``, missed distance 3),
    ``GNNWith2DAssignment``, ``MultiMeasurementInitiator`` (2 points), ``UpdateTimeStepsDeleter``
    (``--delete-after`` s without update), ``TimeSyncFeeder`` (``--sync`` s) over a
    time-ordered reader. Stone Soup sees the plots only (no Mode C altitude, no radar tracks).
(b) tertiary: ``tertiary.pipeline.run`` with ``information`` fusion, the ``imm_sym`` tracker,
    conflicts, evaluation and the store (``--centralized`` adds the centralised reference).

Conventions: Stone Soup's bearing is atan2(y, x), counter-clockwise from the x axis (east);
a radar azimuth is clockwise from north, so bearing = π/2 − azimuth. Its elevation is
asin(z/ρ), the same as the radar's. Its ``rotation_offset`` angles (a, b, c) give the matrix
Rx(−a) Ry(b) Rz(−c) that takes system-frame vectors to the site's axes (:func:`rotation_angles`).

Scoring rule (both trackers, :func:`score`): every track state at time t is labelled with the
truth aircraft nearest to it in (x, y, reported height) at t among those within ``--gate`` m
horizontally (truth linearly interpolated on its 1 s grid, never extrapolated: none before an
aircraft's first sample, after its last, or after the recording's end; the terminal area has
aircraft stacked on one ground track, which only height tells apart); each track belongs to the
aircraft most of its states are labelled with, and every state is scored against its track's
aircraft at t (so two aircraft crossing or stacked do not swap the truth under a track); a state
farther than the gate from its aircraft, or of a track owning none, or at a time its aircraft
has no truth, is unmatched (``states_matched_fraction``) and not in the RMSE. For Stone Soup
the owner is checked against the majority ``truth_id`` of the detections that updated the
track (``owner_agrees_with_detections``). Horizontal error Δx² + Δy²; vertical error = the
tracker's reported height − true geodetic height, where the reported height is the tracker's
own height channel when it has one (tertiary ``alt_m``), else the geodetic height of its 3-D
position (Stone Soup); the system-frame Δz is reported too. Tracks per aircraft = tracks owning
an aircraft / aircraft owning ≥ 1 track.

Which states (:func:`score_all`). Headline: both pictures at the SAME instants — tertiary's
epoch grid (:func:`picture_at`): each track alive at instant tᵢ with its latest state at or
before tᵢ (Stone Soup: a feeder step ≤ 2·``--sync`` s old, moved to tᵢ by its own CV
prediction; tertiary: its state at the epoch, itself predicted from its last measurement's time
epoch − age). "Updated" = the track's last measurement update is within the preceding epoch
period (Stone Soup: an ``Update``; tertiary: status ``confirmed`` with a fused plot holding a
fresh measurement, ``fused.n_fresh`` > 0). Also reported: ``own_times`` — each tracker at its own
state times (Stone Soup every feeder step, its updates at the plot's own time with no
prediction; tertiary at its epochs) — and ``legacy``, the superseded rule behind the results
before 2026-11-25, which (i) held the truth at an aircraft's last sample past the end of the
recording, so tertiary's states at the epochs after the last report (radar tracks extrapolated
up to 1.5 scans) were scored against where the aircraft had been up to 13 s earlier, within the
1 km gate, and (ii) counted a tertiary track holding a plot without a fresh measurement as
updated. On the 180 s / 50-aircraft run these two alone made tertiary's horizontal RMSE 85.5 m
instead of 41 m.

    python benchmarks/bench_stonesoup.py [--duration 900] [--aircraft 200] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _util import record, run_isolated  # noqa: E402

from tertiary.core import geo  # noqa: E402

BENCH_DIR = Path(__file__).resolve().parent
#: the scoring rule's version recorded with every run (earlier runs: the superseded rule, see score_all)
RULE_VERSION = "2026-11-25 common instants, truth never extrapolated, updated = fresh measurement"
SCORING_RULE = ("both pictures at the same instants (tertiary's epoch grid; Stone Soup's latest state moved to the "
                "instant by its own CV prediction); each state labelled with the truth aircraft nearest in (x, y, "
                "reported height) among those within the gate horizontally; each track owned by its majority label; "
                "every state scored against its track's owner at its time (unmatched beyond the gate or where the "
                "owner has no truth: truth is interpolated, never extrapolated); updated = last measurement update "
                "within the preceding epoch period; vertical = reported height (tertiary alt_m, Stone Soup geodetic "
                "height of its 3-D state) - true geodetic height")


# --------------------------------------------------------------------------- conversions (numpy only)


def azimuth_to_bearing(azimuth_deg: np.ndarray) -> np.ndarray:
    """Radar azimuth (deg, clockwise from north) to Stone Soup bearing (rad, counter-clockwise
    from east, in (−π, π]): φ = π/2 − az."""
    phi = np.pi / 2 - np.radians(np.asarray(azimuth_deg, float))
    return np.mod(phi + np.pi, 2 * np.pi) - np.pi


def ss_rotation_matrix(angles: np.ndarray) -> np.ndarray:
    """Stone Soup's ``build_rotation_matrix`` for angles (a, b, c): Rx(−a) Ry(b) Rz(−c)
    (stonesoup/functions/__init__.py, 1.9)."""
    a, b, c = -angles[0], angles[1], -angles[2]
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rx @ ry @ rz


def rotation_angles(m: np.ndarray) -> np.ndarray:
    """Angles (a, b, c) with Rx(−a) Ry(b) Rz(−c) = m (m a proper rotation, |b| < π/2):
    with A = −a, B = b, C = −c, m[0, 2] = sin B, m[0, :2] = cos B (cos C, −sin C),
    m[1:, 2] = cos B (−sin A, cos A)."""
    big_a = np.arctan2(-m[1, 2], m[2, 2])
    big_b = np.arcsin(np.clip(m[0, 2], -1.0, 1.0))
    big_c = np.arctan2(-m[0, 1], m[0, 0])
    return np.array([-big_a, big_b, -big_c])


@dataclass(frozen=True)
class SiteGeometry:
    """One radar as Stone Soup sees it: its site origin in the system ENU frame, the rotation
    angles of its ENU axes, and its noise σ (elevation rad, bearing rad, range m)."""

    translation: np.ndarray
    angles: np.ndarray
    sigma: np.ndarray


def site_geometry(radars: pl.DataFrame, system: geo.LocalFrame) -> dict[int, SiteGeometry]:
    """Each radar's Stone Soup geometry from ``radars`` (WGS-84 site, nominal σ) and the system frame."""
    out = {}
    for r in radars.iter_rows(named=True):
        site = geo.LocalFrame(r["lat_deg"], r["lon_deg"], r["alt_m"])
        out[int(r["radar_id"])] = SiteGeometry(
            translation=site.offset_in(system), angles=rotation_angles(system.rotation_to(site)),
            sigma=np.array([np.radians(r["sigma_elevation_deg"]), np.radians(r["sigma_azimuth_deg"]),
                            r["sigma_range_m"]]))
    return out


def plots_to_measurements(range_m, azimuth_deg, elevation_deg) -> np.ndarray:
    """Radar plots to Stone Soup ``CartesianToElevationBearingRange`` measurements (n, 3):
    (elevation rad, bearing rad, range m)."""
    return np.stack([np.radians(np.asarray(elevation_deg, float)), azimuth_to_bearing(azimuth_deg),
                     np.asarray(range_m, float)], axis=1)


def ss_inverse(meas: np.ndarray, g: SiteGeometry) -> np.ndarray:
    """Stone Soup's ``CartesianToElevationBearingRange.inverse_function`` in numpy: the
    measurement (n, 3) to system ENU (n, 3) = M⁻¹ sphere2cart(ρ, φ, θ) + t."""
    theta, phi, rho = meas[:, 0], meas[:, 1], meas[:, 2]
    xyz = np.stack([rho * np.cos(phi) * np.cos(theta), rho * np.sin(phi) * np.cos(theta), rho * np.sin(theta)], 1)
    return xyz @ ss_rotation_matrix(g.angles) + g.translation   # rows: M⁻¹ v = Mᵀ v


def tertiary_plot_to_system(range_m, azimuth_deg, elevation_deg, radar: dict, system: geo.LocalFrame) -> np.ndarray:
    """tertiary's own conversion of plots of one radar to the system ENU frame (n, 3)."""
    site = geo.LocalFrame(radar["lat_deg"], radar["lon_deg"], radar["alt_m"])
    local = np.stack(geo.polar_to_enu(range_m, azimuth_deg, elevation_deg), axis=1)
    return geo.frame_to_frame(local, site, system)[0]


# --------------------------------------------------------------------------- scoring (numpy only)


@dataclass(frozen=True)
class TruthGrid:
    """Truth on its common time grid: ids (A,), t (T,) s, p (A, T, 4) x, y, z, alt (NaN: inactive)."""

    ids: np.ndarray
    t: np.ndarray
    p: np.ndarray


def seconds(col: str, t0) -> pl.Expr:
    return (pl.col(col).dt.convert_time_zone("UTC") - pl.lit(t0)).dt.total_microseconds().cast(pl.Float64) / 1e6


def truth_grid(truth: pl.DataFrame, t0) -> TruthGrid:
    """Pivot ``truth`` (truth_id, time, x_m, y_m, z_m, alt_m) onto its time grid."""
    f = truth.select("truth_id", seconds("time", t0).alias("t"), "x_m", "y_m", "z_m", "alt_m")
    ids, ia = np.unique(f["truth_id"].to_numpy(), return_inverse=True)
    ts, it = np.unique(f["t"].to_numpy(), return_inverse=True)
    p = np.full((len(ids), len(ts), 4), np.nan)
    p[ia, it] = f.select("x_m", "y_m", "z_m", "alt_m").to_numpy()
    return TruthGrid(ids, ts, p)


def _interp(grid: TruthGrid, a: np.ndarray | slice, t: np.ndarray, strict: bool = True) -> np.ndarray:
    """Truth of aircraft ``a`` at times ``t``: linear between two active grid samples, the
    sample itself at a sample time; NaN elsewhere — before the first or after the last sample
    of the aircraft's life, and after the end of the truth grid (``strict``, the scoring rule:
    truth is never extrapolated). ``strict=False`` is the superseded rule (results before
    2026-11-25): at the ends of a life the active neighbour, and beyond the end of the grid its
    last sample, so a track state after the recording's end was compared with the aircraft
    where it was seconds earlier. ``a`` a slice gives (A, n, 4) for every aircraft, an index
    array (n,) gives (n, 4) for one aircraft per time."""
    k = np.clip(np.searchsorted(grid.t, t, side="right") - 1, 0, len(grid.t) - 1)
    k1 = np.minimum(k + 1, len(grid.t) - 1)
    span = grid.t[k1] - grid.t[k]
    w = np.where(span > 0, (t - grid.t[k]) / np.where(span > 0, span, 1.0), 0.0)[..., None]
    lo, hi = grid.p[a, k], grid.p[a, k1]
    mix = (1 - w) * lo + w * hi
    if strict:
        on_sample = (t == grid.t[k])[..., None]
        inside = ((t >= grid.t[k]) & (t <= grid.t[k1]) & (span > 0))[..., None]
        return np.where(on_sample, lo, np.where(inside, mix, np.nan))   # NaN lo/hi propagate
    mix = np.where(np.isnan(lo), hi, mix)
    return np.where(np.isnan(hi), lo, mix)


def truth_at(grid: TruthGrid, t: np.ndarray, strict: bool = True) -> np.ndarray:
    """Every aircraft's truth (A, n, 4) at times ``t`` (n,) (see :func:`_interp`)."""
    return _interp(grid, slice(None), t, strict)


def match_nearest(grid: TruthGrid, t: np.ndarray, xy: np.ndarray, gate_m: float, h: np.ndarray | None = None,
                  chunk: int = 20_000, strict: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """For each state (t, x, y[, reported height h]): the index into ``grid.ids`` of the nearest
    truth aircraft among those within ``gate_m`` horizontally (−1: none) and that aircraft's
    truth (n, 4) (NaN: none). Nearest in (x, y, h) when ``h`` is given, so that aircraft stacked
    on the same ground track are told apart by height, else horizontally."""
    n = len(t)
    idx = np.full(n, -1, np.int64)
    tru = np.full((n, 4), np.nan)
    for lo in range(0, n, chunk):   # chunks bound the (A, chunk, 4) interpolation
        hi = min(lo + chunk, n)
        at = truth_at(grid, t[lo:hi], strict)
        d2 = (at[..., 0] - xy[None, lo:hi, 0]) ** 2 + (at[..., 1] - xy[None, lo:hi, 1]) ** 2
        d2 = np.where(np.isnan(d2), np.inf, d2)
        rank = d2 if h is None else d2 + np.nan_to_num((at[..., 3] - h[None, lo:hi]) ** 2, nan=0.0)
        rank = np.where(d2 <= gate_m ** 2, rank, np.inf)
        best = np.argmin(rank, axis=0)
        cols = np.arange(hi - lo)
        ok = np.isfinite(rank[best, cols])
        idx[lo:hi] = np.where(ok, best, -1)
        tru[lo:hi] = np.where(ok[:, None], at[best, cols], np.nan)
    return idx, tru


def owners(track_id: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, pl.DataFrame]:
    """Each track's aircraft: the truth most of its states matched (ties: the lower index; −1 =
    none, a false track when most of its states matched nothing). Returns the owner of each
    state's track (n,) and the (track, truth) table."""
    f = pl.DataFrame({"track": track_id, "truth": idx})
    own = (f.group_by("track", "truth").len().sort("len", "truth", descending=[True, False])
           .group_by("track", maintain_order=True).first().select("track", "truth"))
    per_state = f.select("track").join(own, on="track", how="left", maintain_order="left")["truth"].to_numpy()
    return per_state, own


def _rmse(e2: np.ndarray) -> float | None:
    e2 = e2[np.isfinite(e2)]
    return float(np.sqrt(e2.mean())) if len(e2) else None


def score(states: pl.DataFrame, grid: TruthGrid, gate_m: float = 1000.0, strict: bool = True) -> dict:
    """Score track states (track_id, t [s on the grid's clock], x_m, y_m, z_m, h_m reported
    height, updated bool) against truth with the module's one rule: label each state with the
    aircraft nearest in (x, y, reported height) among those within the gate horizontally, give
    each track the aircraft most of its states were labelled with (:func:`owners`), then score
    every state of a track against its owner's truth at the state's time; a state more than the
    gate from its owner (or whose track owns none, or whose owner has no truth at that time) is
    unmatched and not in the RMSE. ``strict=False``: the superseded truth rule (:func:`_interp`)."""
    t = states["t"].to_numpy()
    xyz = states.select("x_m", "y_m", "z_m").to_numpy()
    idx, _ = match_nearest(grid, t, xyz[:, :2], gate_m, states["h_m"].to_numpy(), strict=strict)
    own, table = owners(states["track_id"].to_numpy(), idx)
    tru = np.full((len(t), 4), np.nan)
    has = own >= 0
    tru[has] = _interp(grid, own[has], t[has], strict)
    e2_h = ((xyz[:, :2] - tru[:, :2]) ** 2).sum(axis=1)
    ok = e2_h <= gate_m ** 2            # NaN (no owner / owner not alive) compares False
    e2_h = np.where(ok, e2_h, np.nan)
    e2_v = np.where(ok, (states["h_m"].to_numpy() - tru[:, 3]) ** 2, np.nan)
    e2_z = np.where(ok, (xyz[:, 2] - tru[:, 2]) ** 2, np.nan)
    upd = states["updated"].to_numpy() & ok
    out = {"states": int(len(t)), "states_matched_fraction": float(ok.mean()) if len(t) else 0.0,
           "rmse_horizontal_m": _rmse(e2_h), "rmse_vertical_m": _rmse(e2_v), "rmse_z_enu_m": _rmse(e2_z),
           "rmse_horizontal_updated_m": _rmse(e2_h[upd]), "rmse_vertical_updated_m": _rmse(e2_v[upd]),
           "rmse_z_enu_updated_m": _rmse(e2_z[upd])}
    out |= track_counts(table)
    if "truth_id" in states.columns:   # Stone Soup: the truth ids its updates' detections carried
        out["owner_agrees_with_detections"] = detection_agreement(states, table, grid)
    return out


def picture_at(states: pl.DataFrame, instants: np.ndarray, max_age_s: float, period_s: float) -> pl.DataFrame:
    """Each tracker's picture at common instants (the scoring rule's times): for every track
    alive at instant tᵢ, its latest state at t ≤ tᵢ no older than ``max_age_s``, moved to tᵢ
    with its own velocity (its constant-velocity prediction over tᵢ − t); ``updated`` when the
    track's last measurement update is within (tᵢ − ``period_s``, tᵢ]. ``states``: track_id,
    t, x_m, y_m, z_m, h_m, updated and vx_mps, vy_mps, vz_mps. Without velocity columns (Stone
    Soup outputs written before 2026-11-25) each state's velocity is recovered from its
    constant-velocity predictions: (x_{k+1} − x_k)/Δt when state k+1 is a prediction of state
    k (exact), else (x_k − x_{k−1})/Δt when state k is itself a prediction, else the latter
    difference as an approximation."""
    f = states.sort("track_id", "t")
    if not {"vx_mps", "vy_mps", "vz_mps"} <= set(f.columns):
        nxt_pred = ~pl.col("updated").shift(-1).over("track_id").fill_null(True)
        fwd_dt, back_dt = pl.col("t").diff(-1).over("track_id") * -1.0, pl.col("t").diff().over("track_id")
        f = f.with_columns(*(
            pl.when(nxt_pred & (fwd_dt > 0)).then(pl.col(c).diff(-1).over("track_id") * -1.0 / fwd_dt)
            .when(back_dt > 0).then(pl.col(c).diff().over("track_id") / back_dt)
            .otherwise(0.0).fill_nan(0.0).fill_null(0.0).alias(v)
            for c, v in (("x_m", "vx_mps"), ("y_m", "vy_mps"), ("z_m", "vz_mps"))))
    f = f.with_columns(pl.when(pl.col("updated")).then(pl.col("t")).forward_fill().over("track_id").alias("t_upd"))
    life = f.group_by("track_id").agg(pl.col("t").min().alias("t_first"), pl.col("t").max().alias("t_last"))
    at = (life.join(pl.DataFrame({"t_i": np.asarray(instants, float)}), how="cross")
          .filter((pl.col("t_i") >= pl.col("t_first")) & (pl.col("t_i") <= pl.col("t_last") + max_age_s))
          .select("track_id", "t_i").sort("t_i"))
    # both sides sorted by their time globally, hence within every track (polars cannot check
    # sortedness per ``by`` group itself)
    j = at.join_asof(f.select("track_id", "t", "x_m", "y_m", "z_m", "h_m", "vx_mps", "vy_mps", "vz_mps", "t_upd")
                     .sort("t"), left_on="t_i", right_on="t", by="track_id", strategy="backward",
                     check_sortedness=False)
    j = j.filter(pl.col("t").is_not_null() & (pl.col("t_i") - pl.col("t") <= max_age_s + 1e-9))
    d = pl.col("t_i") - pl.col("t")
    return j.select("track_id", pl.col("t_i").alias("t"), pl.col("x_m") + pl.col("vx_mps") * d,
                    pl.col("y_m") + pl.col("vy_mps") * d, pl.col("z_m") + pl.col("vz_mps") * d,
                    pl.col("h_m") + pl.col("vz_mps") * d,
                    (pl.col("t_upd").is_not_null() & (pl.col("t_i") - pl.col("t_upd") < period_s)).alias("updated"))


def detection_agreement(states: pl.DataFrame, table: pl.DataFrame, grid: TruthGrid) -> float | None:
    """Fraction of tracks whose owner (nearest-truth labels) is also the majority ``truth_id``
    of the detections that updated it (a check of the scoring rule on Stone Soup's tracks)."""
    det = (states.filter(pl.col("truth_id").is_not_null() & (pl.col("truth_id") >= 0))
           .group_by("track_id", "truth_id").len().sort("len", "truth_id", descending=[True, False])
           .group_by("track_id", maintain_order=True).first())
    ids = pl.DataFrame({"truth": np.arange(len(grid.ids)), "owner_id": grid.ids})
    both = table.join(ids, on="truth", how="left").join(det, left_on="track", right_on="track_id", how="inner")
    return float((both["owner_id"] == both["truth_id"]).mean()) if both.height else None


def track_counts(table: pl.DataFrame) -> dict:
    """Tracks, false tracks (owning no aircraft), aircraft owning ≥ 1 track, and tracks per such
    aircraft, from the (track, truth) owner table of :func:`owners`."""
    real = table.filter(pl.col("truth") >= 0)
    aircraft = real["truth"].n_unique()
    return {"tracks": table.height, "false_tracks": table.height - real.height, "aircraft_tracked": aircraft,
            "tracks_per_aircraft": real.height / aircraft if aircraft else None}


# --------------------------------------------------------------------------- the two jobs (child processes)


def stonesoup_job(dataset: str, out: str, q: float, sync_s: float, delete_after_s: float, min_points: int,
                  limit_s: float | None = None) -> dict:
    """Stone Soup's standard multi-target tracker on the plots of ``dataset`` (run 0; only the
    first ``limit_s`` seconds of reports when given); writes the track states to ``out``
    (Parquet) and returns the wall time from reading the dataset to the states written. The
    conversion is checked first against tertiary's geo on a sample of plots (not timed)."""
    import datetime
    import time
    from stonesoup.buffered_generator import BufferedGenerator
    from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
    from stonesoup.deleter.time import UpdateTimeStepsDeleter
    from stonesoup.feeder.time import TimeSyncFeeder
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.initiator.simple import MultiMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.nonlinear import CartesianToElevationBearingRange
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import ExtendedKalmanPredictor
    from stonesoup.reader.base import DetectionReader
    from stonesoup.tracker.simple import MultiTargetTracker
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import CovarianceMatrix, StateVector
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.update import Update
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    from tertiary.io.dataset import read_dataset

    def models_for(radars, system):
        return {rid: CartesianToElevationBearingRange(
            ndim_state=6, mapping=(0, 2, 4), noise_covar=CovarianceMatrix(np.diag(g.sigma ** 2)),
            translation_offset=StateVector(g.translation), rotation_offset=StateVector(g.angles))
            for rid, g in site_geometry(radars, system).items()}

    # conversion check with the real Stone Soup model (not timed)
    ds = read_dataset(dataset)
    models = models_for(ds.radars, ds.origin)
    worst_m = check_conversion(ds, models, Detection, StateVector)

    t_start = time.perf_counter()
    ds = read_dataset(dataset)
    models = models_for(ds.radars, ds.origin)
    rep = ds.reports.filter(pl.col("run") == pl.col("run").min()).sort("time")
    if limit_s is not None:
        rep = rep.filter(pl.col("time") < pl.col("time").min() + datetime.timedelta(seconds=limit_s))
    meas = plots_to_measurements(rep["range_m"].to_numpy(), rep["azimuth_deg"].to_numpy(),
                                 rep["elevation_deg"].to_numpy())
    dets = [Detection(StateVector([Elevation(m[0]), Bearing(m[1]), m[2]]), timestamp=ts,
                      measurement_model=models[rid], metadata={"truth_id": tid})
            for m, ts, rid, tid in zip(meas, rep["time"].to_list(), rep["radar_id"].to_list(),
                                       rep["truth_id"].to_list())]

    class PlotReader(DetectionReader):  # one time-ordered detection at a time
        @BufferedGenerator.generator_method
        def detections_gen(self):
            for d in dets:
                yield d.timestamp, {d}

    cv = CombinedLinearGaussianTransitionModel([ConstantVelocity(q)] * 3)
    predictor = ExtendedKalmanPredictor(cv)
    updater = ExtendedKalmanUpdater(measurement_model=None)
    hyp = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=3)
    assoc = GNNWith2DAssignment(hyp)
    deleter = UpdateTimeStepsDeleter(time_steps_since_update=int(np.ceil(delete_after_s / sync_s)))
    prior = GaussianState(StateVector(np.zeros(6)), CovarianceMatrix(np.diag([0, 200.0, 0, 200.0, 0, 20.0]) ** 2))
    initiator = MultiMeasurementInitiator(prior_state=prior, deleter=deleter, data_associator=assoc,
                                          updater=updater, min_points=min_points)
    feeder = TimeSyncFeeder(PlotReader(), time_window=datetime.timedelta(seconds=sync_s))
    tracker = MultiTargetTracker(initiator=initiator, deleter=deleter, detector=feeder,
                                 data_associator=assoc, updater=updater)
    tracks: set = set()
    for _, current in tracker:
        tracks |= current
    rows = [(k, s.timestamp, *(float(s.state_vector[i, 0]) for i in range(6)), isinstance(s, Update),
             s.hypothesis.measurement.metadata.get("truth_id") if isinstance(s, Update) else None)
            for k, tr in enumerate(tracks) for s in tr.states]
    frame = pl.DataFrame(rows, schema={"track_id": pl.Int64, "time": pl.Datetime("us", "UTC"), "x_m": pl.Float64,
                                       "vx_mps": pl.Float64, "y_m": pl.Float64, "vy_mps": pl.Float64,
                                       "z_m": pl.Float64, "vz_mps": pl.Float64, "updated": pl.Boolean,
                                       "truth_id": pl.Int64}, orient="row")
    frame.write_parquet(out)
    wall = time.perf_counter() - t_start
    return {"reports": rep.height, "wall_s": wall, "tracks": len(tracks), "conversion_check_max_m": worst_m}


def check_conversion(ds, models: dict, detection_cls, state_vector_cls, n: int = 200, tol_m: float = 1e-6) -> float:
    """Stone Soup's model inverse of converted plots against tertiary's geo (per radar, first
    ``n`` plots); raises if any differs by more than ``tol_m`` m; returns the largest difference."""
    worst = 0.0
    for r in ds.radars.iter_rows(named=True):
        rep = ds.reports.filter(pl.col("radar_id") == r["radar_id"]).head(n)
        if rep.height == 0:
            continue
        meas = plots_to_measurements(rep["range_m"], rep["azimuth_deg"], rep["elevation_deg"])
        model = models[int(r["radar_id"])]
        ss = np.array([model.inverse_function(detection_cls(state_vector_cls(m), measurement_model=model))[[0, 2, 4], 0]
                       for m in meas], float)
        ours = tertiary_plot_to_system(rep["range_m"].to_numpy(), rep["azimuth_deg"].to_numpy(),
                                       rep["elevation_deg"].to_numpy(), r, ds.origin)
        worst = max(worst, float(np.abs(ss - ours).max()))
    if not worst <= tol_m:
        raise AssertionError(f"Stone Soup inverse differs from tertiary's conversion by {worst:.3g} m")
    return worst


STONESOUP_CODE = """
import sys, json
sys.path.insert(0, {bench!r})
import bench_stonesoup as b
print(json.dumps(b.stonesoup_job({dataset!r}, {out!r}, {q!r}, {sync!r}, {delete_after!r}, {min_points!r}, {limit!r})))
"""

TERTIARY_CODE = """
import json, time
from tertiary.io.dataset import read_dataset
from tertiary import pipeline
t0 = time.perf_counter()   # as for Stone Soup: from reading the dataset to the tracks stored
ds = read_dataset({dataset!r})
cfg = pipeline.PipelineConfig(methods=("information",), filters=("imm_sym",), centralized={centralized!r})
import shutil; shutil.rmtree({out!r}, ignore_errors=True)
db = pipeline.run(ds, {out!r}, cfg)
print(json.dumps({{"reports": ds.reports.height, "wall_s": time.perf_counter() - t0, "db": str(db)}}))
"""


# --------------------------------------------------------------------------- driver


def make_dataset(path: Path, duration_s: float, aircraft: int, seed: int | None) -> Path:
    """A terminal-area recording (1 run) written to ``path`` unless already there; designed
    conflict pairs scaled down for recordings shorter than 15 min so that they fit."""
    from tertiary.io.dataset import write_dataset
    from tertiary.simulate import load_scenario, simulate
    if (path / "reports.parquet").exists():
        return path
    cfg = load_scenario("terminal-area")
    k = min(1.0, duration_s / 900.0)
    traffic = dataclasses.replace(cfg.traffic, aircraft=aircraft,
                                  conflict_pairs=int(round(cfg.traffic.conflict_pairs * k)),
                                  near_miss_pairs=int(round(cfg.traffic.near_miss_pairs * k)))
    cfg = dataclasses.replace(cfg, duration_s=duration_s, runs=1, traffic=traffic)
    if seed is not None:
        cfg = cfg.replace(seed=seed)
    write_dataset(simulate(cfg), path)
    return path


def stonesoup_states(path: Path, t0, system: geo.LocalFrame) -> pl.DataFrame:
    """Stone Soup's states with the scoring columns; reported height = geodetic height of the state."""
    f = pl.read_parquet(path)
    h = system.to_geodetic(*f.select("x_m", "y_m", "z_m").to_numpy().T)[2]
    return f.with_columns(seconds("time", t0).alias("t"), pl.Series("h_m", h))


def tertiary_states(db: str, t0, system: geo.LocalFrame) -> pl.DataFrame:
    """tertiary's information+imm_sym track rows with the scoring columns; reported height =
    the tracks' height channel ``alt_m`` (the geodetic height of z where it is null).
    ``updated``: the track took a plot at this epoch (status ``confirmed``) AND that fused plot
    held a fresh measurement (``fused.n_fresh`` > 0): a plot that only re-extrapolates the
    radars' tracks holds a track without updating it (tertiary.stages.tracking.tracker). ``confirmed``: the
    superseded definition (status only)."""
    import duckdb
    with duckdb.connect(db, read_only=True) as con:
        f = con.sql("select track_id, epoch as time, x_m, y_m, z_m, vx_mps, vy_mps, vz_mps, alt_m, status, "
                    "plot_target_id from tracks where method = 'information' and filter = 'imm_sym'").pl()
        cols = {r[0] for r in con.sql("describe fused").fetchall()}
        fresh = (con.sql("select epoch as time, target_id as plot_target_id, n_fresh > 0 as fresh from fused "
                         "where method = 'information'").pl() if "n_fresh" in cols else None)
    if fresh is not None:
        f = f.join(fresh, on=["time", "plot_target_id"], how="left", maintain_order="left")
    else:
        f = f.with_columns(pl.lit(True).alias("fresh"))
    h_geo = system.to_geodetic(*f.select("x_m", "y_m", "z_m").to_numpy().T)[2]
    confirmed = pl.col("status") == "confirmed"
    return f.with_columns(seconds("time", t0).alias("t"),
                          pl.col("alt_m").fill_null(pl.Series(h_geo)).alias("h_m"),
                          confirmed.alias("confirmed"), (confirmed & pl.col("fresh").fill_null(False)).alias("updated"))


def picture_instants(db: str, t0) -> np.ndarray:
    """The common scoring instants: tertiary's epoch grid (every epoch of its fused output), s."""
    import duckdb
    with duckdb.connect(db, read_only=True) as con:
        ep = con.sql("select distinct epoch as time from fused order by 1").pl()
    return ep.select(seconds("time", t0)).to_series().to_numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=900.0, help="recording length, s")
    ap.add_argument("--aircraft", type=int, default=200)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--workdir", type=Path, default=None, help="dataset and outputs [default: a temp dir]")
    ap.add_argument("--q", type=float, default=1.0, help="Stone Soup CV noise diffusion coefficient, m²/s³")
    ap.add_argument("--sync", type=float, default=0.25, help="Stone Soup TimeSyncFeeder window, s")
    ap.add_argument("--delete-after", type=float, default=20.0, help="Stone Soup deletion, s without update")
    ap.add_argument("--min-points", type=int, default=2, help="Stone Soup initiator confirmation points")
    ap.add_argument("--gate", type=float, default=1000.0, help="scoring gate, m (horizontal)")
    ap.add_argument("--centralized", action="store_true", help="tertiary also runs the centralised reference")
    ap.add_argument("--stonesoup-seconds", type=float, default=None,
                    help="Stone Soup processes only the first S seconds of reports (its cost grows with tracks x "
                         "detections); both trackers are then scored on that window only")
    ap.add_argument("--rescore", action="store_true", help="re-score the jobs already run in --workdir")
    ap.add_argument("--rerun-tertiary", action="store_true",
                    help="re-run only the tertiary job, re-score with the Stone Soup job already run in --workdir")
    ap.add_argument("--no-record", action="store_true", help="do not write benchmarks/results/bench_stonesoup.json")
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_stonesoup_"))
    work.mkdir(parents=True, exist_ok=True)
    data = make_dataset(work / f"ta_{int(args.duration)}s_{args.aircraft}ac", args.duration, args.aircraft, args.seed)

    ss_out, jobs = work / "stonesoup_states.parquet", work / "jobs.json"
    if args.rescore or args.rerun_tertiary:   # score the outputs of an earlier invocation again (development)
        ss, te = json.loads(jobs.read_text())
        if args.rerun_tertiary:
            te = run_isolated(TERTIARY_CODE.format(dataset=str(data), out=str(work / "tertiary_run"),
                                                   centralized=args.centralized))
            jobs.write_text(json.dumps([ss, te]))
    else:
        ss = run_isolated(STONESOUP_CODE.format(bench=str(BENCH_DIR), dataset=str(data), out=str(ss_out), q=args.q,
                                                sync=args.sync, delete_after=args.delete_after,
                                                min_points=args.min_points, limit=args.stonesoup_seconds))
        te = run_isolated(TERTIARY_CODE.format(dataset=str(data), out=str(work / "tertiary_run"),
                                               centralized=args.centralized))
        jobs.write_text(json.dumps([ss, te]))

    from tertiary.io.dataset import read_dataset
    ds = read_dataset(data)
    t0 = ds.truth["time"].min()
    grid = truth_grid(ds.truth, t0)
    ss_states, te_states = stonesoup_states(ss_out, t0, ds.origin), tertiary_states(te["db"], t0, ds.origin)
    instants = picture_instants(te["db"], t0)
    if args.stonesoup_seconds is not None:   # the same window for both
        t_end = ds.reports.select(seconds("time", t0).min()).item() + args.stonesoup_seconds
        te_states = te_states.filter(pl.col("t") < t_end)
        instants = instants[instants < t_end]
    ss_score, te_score = score_all(ss_states, te_states, instants, grid, args.gate, args.sync)
    detected = ds.reports["truth_id"].drop_nulls().filter(ds.reports["truth_id"].drop_nulls() >= 0).n_unique()
    for s in (ss_score, te_score):
        s["aircraft_detected"] = detected
    ss_rate, te_rate = ss["reports"] / ss["wall_s"], te["reports"] / te["wall_s"]
    result = {
        "scenario": {"name": "terminal-area", "aircraft": args.aircraft, "duration_s": args.duration,
                     "radars": ds.radars.height, "reports": ds.reports.height,
                     "stonesoup_window_s": args.stonesoup_seconds, "stonesoup_reports": ss["reports"]},
        "stonesoup": {"version": _version("stonesoup"), "wall_s": ss["wall_s"], "reports_per_s": ss_rate,
                      "peak_rss_mib": ss["peak_rss_mib"], "conversion_check_max_m": ss.get("conversion_check_max_m"),
                      "config": {"q_m2ps3": args.q, "sync_s": args.sync, "delete_after_s": args.delete_after,
                                 "min_points": args.min_points, "missed_distance": 3.0}, **ss_score},
        "tertiary": {"wall_s": te["wall_s"], "reports_per_s": te_rate, "peak_rss_mib": te["peak_rss_mib"],
                     "config": {"methods": ["information"], "filters": ["imm_sym"],
                                "centralized": args.centralized, "conflicts": True, "store": True}, **te_score},
        "ratio": te_rate / ss_rate, "scoring_gate_m": args.gate, "scoring_rule_version": RULE_VERSION,
    }
    tag = f"{int(args.duration)}s_{args.aircraft}ac" + (f"_window{int(args.stonesoup_seconds)}s"
                                                        if args.stonesoup_seconds is not None else "")
    if not args.no_record:
        print(f"recorded in {record('bench_stonesoup', summary(tag, result))}")
    print(json.dumps(result, indent=2))


def score_all(ss_states: pl.DataFrame, te_states: pl.DataFrame, instants: np.ndarray, grid: TruthGrid,
              gate_m: float, sync_s: float) -> tuple[dict, dict]:
    """Both trackers scored with the same rules: the headline at common instants
    (:func:`picture_at` on tertiary's epoch grid: Stone Soup's latest state ≤ 2 feeder windows
    old, moved to the instant by its own CV prediction; tertiary's state at the epoch),
    ``own_times`` at each tracker's own state times, and ``legacy`` — the superseded rule
    (truth held at the ends of lives and past the end of the recording; tertiary "updated" =
    status confirmed) that produced the results before 2026-11-25."""
    period = float(np.median(np.diff(instants))) if len(instants) > 1 else 1.0
    out = []
    for states, max_age in ((ss_states, 2.0 * sync_s), (te_states, 0.0)):
        s = score(picture_at(states, instants, max_age, period), grid, gate_m)
        own = score(states, grid, gate_m)
        legacy_states = states.with_columns(pl.col("confirmed").alias("updated")) if "confirmed" in states.columns \
            else states
        legacy = score(legacy_states, grid, gate_m, strict=False)
        if "owner_agrees_with_detections" in own:
            s["owner_agrees_with_detections"] = own.pop("owner_agrees_with_detections")
            legacy.pop("owner_agrees_with_detections", None)
        out.append({**s, "picture_period_s": period, "own_times": own, "legacy": legacy})
    return out[0], out[1]


def summary(tag: str, result: dict) -> dict:
    """The results file: every measured size under ``runs`` (earlier ones kept), the headline
    names from the largest complete run (Stone Soup over the whole recording), else this one."""
    path = BENCH_DIR / "results" / "bench_stonesoup.json"
    runs = json.loads(path.read_text()).get("runs", {}) if path.exists() else {}
    for r in runs.values():   # earlier runs keep their figures, marked with the rule that made them
        r.setdefault("scoring_rule_version", "legacy (superseded: truth held past the recording's end, "
                                             "tertiary updated = status confirmed)")
    runs[tag] = result
    complete = [r for r in runs.values() if r["scenario"]["stonesoup_window_s"] is None
                and r["scoring_rule_version"] == RULE_VERSION]
    head = max(complete, key=lambda r: r["scenario"]["reports"]) if complete else result
    def rmse(r: dict) -> dict:
        one = lambda d: {"horizontal": d["rmse_horizontal_m"], "vertical": d["rmse_vertical_m"],  # noqa: E731
                         "horizontal_updated": d["rmse_horizontal_updated_m"],
                         "vertical_updated": d["rmse_vertical_updated_m"]}
        return {**one(r), **({"own_times": one(r["own_times"]), "legacy": one(r["legacy"])} if "legacy" in r else {})}

    return {"headline_run": next(k for k, v in runs.items() if v is head),
            "tertiary_reports_per_s": head["tertiary"]["reports_per_s"],
            "stonesoup_reports_per_s": head["stonesoup"]["reports_per_s"], "ratio": head["ratio"],
            "tertiary_rmse_m": rmse(head["tertiary"]), "stonesoup_rmse_m": rmse(head["stonesoup"]),
            "tracks_per_aircraft": {"tertiary": head["tertiary"]["tracks_per_aircraft"],
                                    "stonesoup": head["stonesoup"]["tracks_per_aircraft"]},
            "peak_rss_mib": {"tertiary": head["tertiary"]["peak_rss_mib"],
                             "stonesoup": head["stonesoup"]["peak_rss_mib"]},
            "target": {"ratio": 300, "accuracy": "equal or better RMSE"},
            "scoring": {"gate_m": head["scoring_gate_m"], "rule": SCORING_RULE},
            "runs": runs}


def _version(name: str) -> str | None:
    from importlib import metadata
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


if __name__ == "__main__":
    main()
