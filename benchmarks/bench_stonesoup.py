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

Scoring rule (both trackers, :func:`score`): every output track state at time t is labelled
with the truth aircraft nearest to it in (x, y, reported height) at t among those within
``--gate`` m horizontally (truth linearly interpolated on its 1 s grid; the terminal area has
aircraft stacked on one ground track, which only height tells apart); each track belongs to
the aircraft most of its states are labelled with, and every state is scored against its track's aircraft at t (so two aircraft
crossing or stacked do not swap the truth under a track); a state farther than the gate from
its aircraft, or of a track owning none, is unmatched (``states_matched_fraction``) and not in
the RMSE. For Stone Soup the owner is checked against the majority ``truth_id`` of the
detections that updated the track (``owner_agrees_with_detections``). Horizontal error
Δx² + Δy²; vertical error = the tracker's reported height − true geodetic height, where the
reported height is the tracker's own height channel when it has one (tertiary ``alt_m``), else
the geodetic height of its 3-D position (Stone Soup); the system-frame Δz is reported too.
RMSE over all states and over measurement-updated states only (Stone Soup ``Update``,
tertiary ``status = confirmed``). Tracks per aircraft = tracks owning an aircraft / aircraft
owning ≥ 1 track.

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

from tertiary import geo  # noqa: E402

BENCH_DIR = Path(__file__).resolve().parent
SCORING_RULE = ("each state labelled with the truth aircraft nearest in (x, y, reported height) among those within "
                "the gate horizontally; each track owned by its majority label; every state scored against its "
                "track's owner at its time (unmatched beyond the gate); vertical = reported height (tertiary alt_m, "
                "Stone Soup geodetic height of its 3-D state) - true geodetic height")


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


def _interp(grid: TruthGrid, a: np.ndarray | slice, t: np.ndarray) -> np.ndarray:
    """Truth of aircraft ``a`` at times ``t``: linear between grid samples; at the ends of a life
    (one neighbour inactive) the active neighbour; NaN where neither is. ``a`` a slice gives
    (A, n, 4) for every aircraft, an index array (n,) gives (n, 4) for one aircraft per time."""
    k = np.clip(np.searchsorted(grid.t, t, side="right") - 1, 0, len(grid.t) - 1)
    k1 = np.minimum(k + 1, len(grid.t) - 1)
    span = grid.t[k1] - grid.t[k]
    w = np.where(span > 0, (t - grid.t[k]) / np.where(span > 0, span, 1.0), 0.0)[..., None]
    lo, hi = grid.p[a, k], grid.p[a, k1]
    mix = (1 - w) * lo + w * hi
    mix = np.where(np.isnan(lo), hi, mix)
    return np.where(np.isnan(hi), lo, mix)


def truth_at(grid: TruthGrid, t: np.ndarray) -> np.ndarray:
    """Every aircraft's truth (A, n, 4) at times ``t`` (n,) (see :func:`_interp`)."""
    return _interp(grid, slice(None), t)


def match_nearest(grid: TruthGrid, t: np.ndarray, xy: np.ndarray, gate_m: float, h: np.ndarray | None = None,
                  chunk: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """For each state (t, x, y[, reported height h]): the index into ``grid.ids`` of the nearest
    truth aircraft among those within ``gate_m`` horizontally (−1: none) and that aircraft's
    truth (n, 4) (NaN: none). Nearest in (x, y, h) when ``h`` is given, so that aircraft stacked
    on the same ground track are told apart by height, else horizontally."""
    n = len(t)
    idx = np.full(n, -1, np.int64)
    tru = np.full((n, 4), np.nan)
    for lo in range(0, n, chunk):   # chunks bound the (A, chunk, 4) interpolation
        hi = min(lo + chunk, n)
        at = truth_at(grid, t[lo:hi])
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


def score(states: pl.DataFrame, grid: TruthGrid, gate_m: float = 1000.0) -> dict:
    """Score track states (track_id, t [s on the grid's clock], x_m, y_m, z_m, h_m reported
    height, updated bool) against truth with the module's one rule: label each state with the
    aircraft nearest in (x, y, reported height) among those within the gate horizontally, give
    each track the aircraft most of its states were labelled with (:func:`owners`), then score
    every state of a track against its owner's truth at the state's time; a state more than the
    gate from its owner (or whose track owns none) is unmatched and not in the RMSE."""
    t = states["t"].to_numpy()
    xyz = states.select("x_m", "y_m", "z_m").to_numpy()
    idx, _ = match_nearest(grid, t, xyz[:, :2], gate_m, states["h_m"].to_numpy())
    own, table = owners(states["track_id"].to_numpy(), idx)
    tru = np.full((len(t), 4), np.nan)
    has = own >= 0
    tru[has] = _interp(grid, own[has], t[has])
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

    from tertiary.simulate import read_dataset

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
    rows = [(k, s.timestamp, float(s.state_vector[0, 0]), float(s.state_vector[2, 0]),
             float(s.state_vector[4, 0]), isinstance(s, Update),
             s.hypothesis.measurement.metadata.get("truth_id") if isinstance(s, Update) else None)
            for k, tr in enumerate(tracks) for s in tr.states]
    frame = pl.DataFrame(rows, schema={"track_id": pl.Int64, "time": pl.Datetime("us", "UTC"), "x_m": pl.Float64,
                                       "y_m": pl.Float64, "z_m": pl.Float64, "updated": pl.Boolean,
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
from tertiary.simulate import read_dataset
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
    from tertiary.simulate import load_scenario, simulate, write_dataset
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
    the tracks' height channel ``alt_m`` (the geodetic height of z where it is null)."""
    import duckdb
    with duckdb.connect(db, read_only=True) as con:
        f = con.sql("select track_id, epoch as time, x_m, y_m, z_m, alt_m, status from tracks "
                    "where method = 'information' and filter = 'imm_sym'").pl()
    h_geo = system.to_geodetic(*f.select("x_m", "y_m", "z_m").to_numpy().T)[2]
    return f.with_columns(seconds("time", t0).alias("t"),
                          pl.col("alt_m").fill_null(pl.Series(h_geo)).alias("h_m"),
                          (pl.col("status") == "confirmed").alias("updated"))


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
    ap.add_argument("--no-record", action="store_true", help="do not write benchmarks/results/bench_stonesoup.json")
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_stonesoup_"))
    work.mkdir(parents=True, exist_ok=True)
    data = make_dataset(work / f"ta_{int(args.duration)}s_{args.aircraft}ac", args.duration, args.aircraft, args.seed)

    ss_out, jobs = work / "stonesoup_states.parquet", work / "jobs.json"
    if args.rescore:   # score the outputs of an earlier invocation again (development)
        ss, te = json.loads(jobs.read_text())
    else:
        ss = run_isolated(STONESOUP_CODE.format(bench=str(BENCH_DIR), dataset=str(data), out=str(ss_out), q=args.q,
                                                sync=args.sync, delete_after=args.delete_after,
                                                min_points=args.min_points, limit=args.stonesoup_seconds))
        te = run_isolated(TERTIARY_CODE.format(dataset=str(data), out=str(work / "tertiary_run"),
                                               centralized=args.centralized))
        jobs.write_text(json.dumps([ss, te]))

    from tertiary.simulate import read_dataset
    ds = read_dataset(data)
    t0 = ds.truth["time"].min()
    grid = truth_grid(ds.truth, t0)
    ss_states, te_states = stonesoup_states(ss_out, t0, ds.origin), tertiary_states(te["db"], t0, ds.origin)
    if args.stonesoup_seconds is not None:   # the same window for both
        t_end = ds.reports.select(seconds("time", t0).min()).item() + args.stonesoup_seconds
        te_states = te_states.filter(pl.col("t") < t_end)
    ss_score, te_score = score(ss_states, grid, args.gate), score(te_states, grid, args.gate)
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
        "ratio": te_rate / ss_rate, "scoring_gate_m": args.gate,
    }
    tag = f"{int(args.duration)}s_{args.aircraft}ac" + (f"_window{int(args.stonesoup_seconds)}s"
                                                        if args.stonesoup_seconds is not None else "")
    if not args.no_record:
        print(f"recorded in {record('bench_stonesoup', summary(tag, result))}")
    print(json.dumps(result, indent=2))


def summary(tag: str, result: dict) -> dict:
    """The results file: every measured size under ``runs`` (earlier ones kept), the headline
    names from the largest complete run (Stone Soup over the whole recording), else this one."""
    path = BENCH_DIR / "results" / "bench_stonesoup.json"
    runs = json.loads(path.read_text()).get("runs", {}) if path.exists() else {}
    runs[tag] = result
    complete = [r for r in runs.values() if r["scenario"]["stonesoup_window_s"] is None]
    head = max(complete, key=lambda r: r["scenario"]["reports"]) if complete else result
    rmse = lambda r: {"horizontal": r["rmse_horizontal_m"], "vertical": r["rmse_vertical_m"],  # noqa: E731
                      "horizontal_updated": r["rmse_horizontal_updated_m"],
                      "vertical_updated": r["rmse_vertical_updated_m"]}
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
