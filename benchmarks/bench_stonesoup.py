"""Stone Soup side by side: the same terminal-area reports through Stone Soup, configured and
tuned as its users would run it for many targets, and through ``tertiary``'s production picture.

Reports: the terminal area, 200 aircraft, 15 min, nine radars (the scenario's four and five
sites added by ``with_radar_count``: the four alone give ~47 000 reports in 15 min, nine give
~103 000). Two recordings: the tuning seed (``--tune-seed``) for the sweep, the evaluation seed
(``--seed``) for the comparison. Each job runs in a fresh process (``_util.run_isolated``: wall
and CPU time from reading the dataset to the tracks written, peak RSS of the process); both are
scored afterwards with ONE rule (:func:`score_one`).

(a) Stone Soup (``pip install 'tertiary[bench]' rtree``), :func:`stonesoup_job`: every plot of
    run 0 (false plots included) is a ``Detection`` with its radar's measurement model: the
    plot's (elevation, bearing, range) by ``CartesianToElevationBearingRange`` (the site's
    position and axes in the system ENU frame, σ from ``radars``) stacked with its Mode C
    height by a ``LinearGaussian`` on z in a ``CombinedReversibleGaussianMeasurementModel``
    (4-D; the height as the system frame's z at the plot's position, :func:`mode_c_to_z`, σ its
    quantisation, 25 ft with a Mode S address else 100 ft, :func:`mode_c_sigma`); a plot
    without Mode C keeps the 3-D polar model. Radar plots are polar with range-dependent
    cross-range error, so the nonlinear model with an EKF is what Stone Soup's radar tutorials
    use; a fixed-covariance ``LinearGaussian`` on converted positions would misstate the noise
    by a factor of ~3 between near and far plots. Motion: ``ConstantVelocity`` (q_h) ×2 and
    (q_v) in a ``CombinedLinearGaussianTransitionModel``; ``KalmanPredictor``,
    ``ExtendedKalmanUpdater``; ``DistanceHypothesiser`` (``Mahalanobis``, ``missed_distance`` =
    gate); association by Stone Soup's tree associator for many targets, ``TPRTreeGNN2D`` (an
    rtree TPR-tree of the tracks in x-y, queried with each detection's inverse): the k-d tree
    associators (``DetectionKDTreeGNN2D``) need every detection of a step under one measurement
    model, which nine radars' plots in one feeder window are not; ``MultiMeasurementInitiator``
    (its own ``TPRTreeGNN2D``, ``UpdateTimeDeleter``, ``min_points``), ``UpdateTimeDeleter``,
    ``TimeSyncFeeder`` over a time-ordered reader, ``MultiTargetTracker``. Second tracks: nine
    radars give ~1.5 plots per aircraft per second, so a 0.25 s feeder window often holds two
    plots of one aircraft; GNN assigns a track one of them and ``MultiTargetTracker`` hands the
    other, although inside the track's gate, to the initiator, which grows it into a second
    track of the same aircraft that then shares its plots (counted by the job:
    ``plots_unassigned_in_confirmed_gate``, ``tracks_started_from_confirmed_gate_plots``). The
    fix is Stone Soup's own rule for mixture trackers (``MultiTargetMixtureTracker`` initiates
    only from plots with no hypothesis better than a miss) applied to GNN by a thin initiator
    wrapper, ``OutsideTrackGates``, for the confirmed tracks and for the initiator's tentative
    ones (``initiate_inside_gates``, swept). Feeding the plots one at a time (``sync_s`` = 0)
    also avoids it, but every step predicts every track, and on the first 30 s of the tuning
    recording it was stopped unfinished after 190 s of CPU, 8.7× the 22 s that 0.25 s windows
    took for the whole 30 s. Three workarounds,
    each marked where it is: Stone Soup's combined inverse adds its models' inverses (z
    counted twice when two models map it), so the inverse takes x, y from the plot and z from
    the height; the TPR tree's track box (3σ of the track alone) is widened by
    ``tree_margin_m`` for the plot's own noise (without it, plots missed settled tracks and
    started second tracks: ``sweep.preliminary`` in the results); where rtree refuses a query (a detection older than the tree's current time)
    the tree is rebuilt as Stone Soup does after a ``KeyError`` (counted: ``tree_rebuilds``).
    Tuning (``sweep``): the base configuration and one parameter changed at a time
    (:data:`SWEEP_AXES`: initiation inside gates, feeder window, q horizontal and vertical,
    initiator points, gate, deleter) on the first ``--tune-window`` s of the tuning recording
    (150 s: long enough for second tracks to form, 7 plots left over by a track take ~20 s),
    each point in its own process (``--jobs`` at once), chosen by :data:`SELECTION_RULE`
    (tracks per aircraft ≤ 1.2), frozen in the results file and run by ``compare`` on the
    whole evaluation recording.
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
position (Stone Soup, whose z carries the Mode C height); the system-frame Δz is reported too.
Tracks per aircraft = tracks owning an aircraft / aircraft owning ≥ 1 track. Coverage
(:func:`coverage`) = the share of (aircraft, instant) pairs between the aircraft's first and
last report that hold a state of a track it owns.

Which states (:func:`score_one`). Headline: both pictures at the SAME instants — tertiary's
epoch grid (:func:`picture_at`): each track alive at instant tᵢ with its latest state at or
before tᵢ (Stone Soup: a state ≤ 2 feeder windows, and ≤ 0.5 s, old, moved to tᵢ by its own CV
prediction; tertiary: its state at the epoch, itself predicted from its last measurement's time
epoch − age). "Updated" = the track's last measurement update is within the preceding epoch
period (Stone Soup: an ``Update``; tertiary: status ``confirmed`` with a fused plot holding a
fresh measurement, ``fused.n_fresh`` > 0). Also reported: ``own_times`` — each tracker at its own
state times (Stone Soup every feeder step, its updates at the plot's own time with no
prediction; tertiary at its epochs).

    python benchmarks/bench_stonesoup.py sweep   --workdir DIR    # the recorded sweep, frozen choice
    python benchmarks/bench_stonesoup.py compare --workdir DIR    # both systems on the evaluation seed
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
#: the scoring rule's name recorded with every run
RULE_VERSION = "common instants, truth never extrapolated, updated = fresh measurement, coverage in reported span"
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
    truth is never extrapolated). ``strict=False`` is a looser rule kept for comparison: at
    the ends of a life the active neighbour, and beyond the end of the grid its last sample, so
    a track state after the recording's end is compared with the aircraft where it was seconds
    earlier. ``a`` a slice gives (A, n, 4) for every aircraft, an index
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
    unmatched and not in the RMSE. ``strict=False``: the looser truth rule (:func:`_interp`)."""
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
    out |= overlaps(states["track_id"].to_numpy(), own, t)
    if "truth_id" in states.columns:   # Stone Soup: the truth ids its updates' detections carried
        out["owner_agrees_with_detections"] = detection_agreement(states, table, grid)
    return out


def picture_at(states: pl.DataFrame, instants: np.ndarray, max_age_s: float, period_s: float) -> pl.DataFrame:
    """Each tracker's picture at common instants (the scoring rule's times): for every track
    alive at instant tᵢ, its latest state at t ≤ tᵢ no older than ``max_age_s``, moved to tᵢ
    with its own velocity (its constant-velocity prediction over tᵢ − t); ``updated`` when the
    track's last measurement update is within (tᵢ − ``period_s``, tᵢ]. ``states``: track_id,
    t, x_m, y_m, z_m, h_m, updated and vx_mps, vy_mps, vz_mps. Without velocity columns (Stone
    Soup outputs without them) each state's velocity is recovered from its
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


def overlaps(track_id: np.ndarray, own: np.ndarray, t: np.ndarray) -> dict:
    """Second tracks of one aircraft: ``extra_tracks`` = tracks owning an aircraft that already
    owns an earlier-starting track; ``extra_concurrent`` = those alive (first to last state)
    while an earlier track of the same aircraft is; ``median_overlap_s`` = the median time each
    such track shares with the earlier one it overlaps most (None: none)."""
    f = (pl.DataFrame({"track": track_id, "owner": own, "t": t}).filter(pl.col("owner") >= 0)
         .group_by("track").agg(pl.col("owner").first(), pl.col("t").min().alias("a"), pl.col("t").max().alias("b"))
         .sort("owner", "a", "track"))
    extra, shared = 0, []
    for _, g in f.group_by("owner", maintain_order=True):
        a, b = g["a"].to_numpy(), g["b"].to_numpy()
        for k in range(1, len(a)):
            extra += 1
            o = float((np.minimum(b[k], b[:k]) - np.maximum(a[k], a[:k])).max())
            if o > 0:
                shared.append(o)
    return {"extra_tracks": extra, "extra_concurrent": len(shared),
            "median_overlap_s": float(np.median(shared)) if shared else None}


def track_counts(table: pl.DataFrame) -> dict:
    """Tracks, false tracks (owning no aircraft), aircraft owning ≥ 1 track, and tracks per such
    aircraft, from the (track, truth) owner table of :func:`owners`."""
    real = table.filter(pl.col("truth") >= 0)
    aircraft = real["truth"].n_unique()
    return {"tracks": table.height, "false_tracks": table.height - real.height, "aircraft_tracked": aircraft,
            "tracks_per_aircraft": real.height / aircraft if aircraft else None}


# --------------------------------------------------------------------------- Stone Soup as its users run it


@dataclass(frozen=True)
class StoneSoupConfig:
    """The tuned parameters of the Stone Soup tracker (:func:`stonesoup_job`).

    ``q_h_m2ps3`` / ``q_v_m2ps3``: ``ConstantVelocity`` noise diffusion coefficient of the two
    horizontal axes / the vertical axis; ``min_points``: ``MultiMeasurementInitiator``
    confirmation updates; ``delete_after_s``: ``UpdateTimeDeleter`` of confirmed tracks (time
    without update); ``gate``: ``DistanceHypothesiser`` ``missed_distance`` (Mahalanobis, on the
    4-D measurement); ``sync_s``: ``TimeSyncFeeder`` window; ``tentative_delete_after_s``: the
    initiator's own ``UpdateTimeDeleter`` of tracks not yet confirmed; ``prior_speed_mps`` /
    ``prior_vspeed_mps``: the initiator prior's velocity σ; ``tree_margin_m``: added to each side
    of the TPR tree's track boxes (the largest plot noise, 3 cross-range σ at 100 km, ~500 m);
    ``initiate_inside_gates``: whether a plot left unassigned although inside a track's gate
    goes to the initiator (Stone Soup's ``MultiTargetTracker`` as shipped: True) or starts no
    track (``OutsideTrackGates`` in :func:`stonesoup_job`); ``sync_s`` = 0 feeds the plots one
    at a time (no ``TimeSyncFeeder``)."""

    q_h_m2ps3: float = 200.0
    q_v_m2ps3: float = 20.0
    min_points: int = 7
    delete_after_s: float = 20.0
    gate: float = 4.0
    sync_s: float = 0.25
    tentative_delete_after_s: float = 6.0
    prior_speed_mps: float = 200.0
    prior_vspeed_mps: float = 20.0
    tree_margin_m: float = 500.0
    initiate_inside_gates: bool = False


def mode_c_to_z(xyz: np.ndarray, altitude_m: np.ndarray, system: geo.LocalFrame) -> np.ndarray:
    """A plot's Mode C height as the system frame's z: the point at the plot's latitude and
    longitude (from its converted 3-D position ``xyz`` (n, 3)) and at height ``altitude_m``,
    in the system ENU frame (the curvature drop, ≈ (x² + y²) / 2R, is ~280 m at 60 km).
    NaN where the plot has no Mode C."""
    lat, lon, _ = system.to_geodetic(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    return np.asarray(system.from_geodetic(lat, lon, np.asarray(altitude_m, float))[2], float)


def mode_c_sigma(mode_s: np.ndarray) -> np.ndarray:
    """σ (m) of a Mode C height: its quantisation, 25 ft with a Mode S address, else 100 ft (q/√12)."""
    quantum = np.where(np.asarray(mode_s, bool), 25.0, 100.0) * 0.3048
    return quantum / np.sqrt(12.0)


def stonesoup_job(dataset: str, out: str, cfg: dict, limit_s: float | None = None) -> dict:
    """Stone Soup's multi-target tracker, configured as its users would for many targets and
    radar plots with Mode C (module docstring), on the plots of ``dataset`` (run 0; only the
    first ``limit_s`` seconds of reports when given); writes the track states to ``out``
    (Parquet) and returns the wall time from reading the dataset to the states written. The
    conversion is checked first against tertiary's geo on a sample of plots (not timed)."""
    import datetime
    import time
    from stonesoup.buffered_generator import BufferedGenerator
    from rtree.exceptions import RTreeError
    from stonesoup.dataassociator.tree import TPRTreeGNN2D
    from stonesoup.deleter.time import UpdateTimeDeleter
    from stonesoup.feeder.time import TimeSyncFeeder
    from stonesoup.hypothesiser.distance import DistanceHypothesiser
    from stonesoup.base import Property
    from stonesoup.initiator.base import Initiator
    from stonesoup.initiator.simple import MultiMeasurementInitiator, SimpleMeasurementInitiator
    from stonesoup.measures import Mahalanobis
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.measurement.nonlinear import (CartesianToElevationBearingRange,
                                                        CombinedReversibleGaussianMeasurementModel)
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.reader.base import DetectionReader
    from stonesoup.tracker.simple import MultiTargetTracker
    from stonesoup.types.angle import Bearing, Elevation
    from stonesoup.types.array import CovarianceMatrix, StateVector
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.update import Update
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    from tertiary.io.dataset import read_dataset

    c = StoneSoupConfig(**cfg)

    class PolarWithHeight(CombinedReversibleGaussianMeasurementModel):
        """(elevation, bearing, range) of the site plus the Mode C height as z. Stone Soup's
        combined inverse adds the models' inverses, which counts z twice when two models map
        it; here x, y come from the plot and z from the height."""

        def inverse_function(self, detection, **kwargs):
            polar, _ = self.model_list
            sv = polar.inverse_function(Detection(detection.state_vector[:3, :], measurement_model=polar))
            sv[4, 0] = detection.state_vector[3, 0]
            return sv

    def polar_models(radars, system):
        return {rid: CartesianToElevationBearingRange(
            ndim_state=6, mapping=(0, 2, 4), noise_covar=CovarianceMatrix(np.diag(g.sigma ** 2)),
            translation_offset=StateVector(g.translation), rotation_offset=StateVector(g.angles))
            for rid, g in site_geometry(radars, system).items()}

    def height_models(polar):   # per radar: with a Mode S (25 ft) or Mode C (100 ft) height
        return {(rid, s): PolarWithHeight([m, LinearGaussian(ndim_state=6, mapping=(4,), noise_covar=CovarianceMatrix(
            [[float(mode_c_sigma(np.array([s]))[0]) ** 2]]))]) for rid, m in polar.items() for s in (True, False)}

    # conversion check with the real Stone Soup model (not timed)
    ds = read_dataset(dataset)
    worst_m = check_conversion(ds, polar_models(ds.radars, ds.origin), Detection, StateVector)

    t_start, cpu_start = time.perf_counter(), time.process_time()
    ds = read_dataset(dataset)
    polar = polar_models(ds.radars, ds.origin)
    with_h = height_models(polar)
    rep = ds.reports.filter(pl.col("run") == pl.col("run").min()).sort("time")
    if limit_s is not None:
        rep = rep.filter(pl.col("time") < pl.col("time").min() + datetime.timedelta(seconds=limit_s))
    meas = plots_to_measurements(rep["range_m"].to_numpy(), rep["azimuth_deg"].to_numpy(),
                                 rep["elevation_deg"].to_numpy())
    rid = rep["radar_id"].to_numpy()
    xyz = np.empty((rep.height, 3))
    geom = site_geometry(ds.radars, ds.origin)
    for r in np.unique(rid):
        xyz[rid == r] = ss_inverse(meas[rid == r], geom[int(r)])
    alt = rep["altitude_m"].cast(pl.Float64).fill_null(np.nan).to_numpy()
    z_h = mode_c_to_z(xyz, alt, ds.origin)
    mode_s = rep["mode_s"].is_not_null().to_numpy()
    dets = []
    for m, zh, s, ts, r, tid in zip(meas, z_h, mode_s, rep["time"].to_list(), rid.tolist(), rep["truth_id"].to_list()):
        if np.isfinite(zh):
            sv, model = StateVector([Elevation(m[0]), Bearing(m[1]), m[2], zh]), with_h[(r, bool(s))]
        else:
            sv, model = StateVector([Elevation(m[0]), Bearing(m[1]), m[2]]), polar[r]
        dets.append(Detection(sv, timestamp=ts, measurement_model=model, metadata={"truth_id": tid}))

    class PlotReader(DetectionReader):  # one time-ordered detection at a time
        @BufferedGenerator.generator_method
        def detections_gen(self):
            for d in dets:
                yield d.timestamp, {d}

    cv = CombinedLinearGaussianTransitionModel([ConstantVelocity(c.q_h_m2ps3), ConstantVelocity(c.q_h_m2ps3),
                                                ConstantVelocity(c.q_v_m2ps3)])
    predictor = KalmanPredictor(cv)
    updater = ExtendedKalmanUpdater(measurement_model=None)
    hyp = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=c.gate)
    class TPRTree(TPRTreeGNN2D):
        """Stone Soup's TPR-tree GNN with its track boxes (3σ of the track's position) widened by
        ``tree_margin_m``: the box holds the track's uncertainty only, not the plot's noise, so
        a plot a cross-range σ off a well-settled track would never reach the Mahalanobis gate.
        Where rtree refuses a query (a detection older than the
        tree's current time, as in the initiator's tree of tentative tracks), the tree is rebuilt
        from the current tracks as Stone Soup itself does after a KeyError, and failing that
        the step is hypothesised without the tree."""

        def _track_tree_coordinates(self, track):
            (lo_hi, vel, t) = super()._track_tree_coordinates(track)
            n = len(lo_hi) // 2
            return (tuple(v - c.tree_margin_m for v in lo_hi[:n]) + tuple(v + c.tree_margin_m for v in lo_hi[n:]),
                    vel, t)

        def generate_hypotheses(self, tracks, detections, timestamp, **kwargs):
            hyps = self._tree_hypotheses(tracks, detections, timestamp, **kwargs)
            # the plots inside some track's gate at this step (hypotheses better than a miss)
            self.gated = (timestamp, {h.measurement for hs in hyps.values() for h in hs if h})
            return hyps

        def _tree_hypotheses(self, tracks, detections, timestamp, **kwargs):
            try:
                return super().generate_hypotheses(tracks, detections, timestamp, **kwargs)
            except RTreeError:
                self.rebuilds += 1
                self._reset_tree()
            try:
                return super().generate_hypotheses(tracks, detections, timestamp, **kwargs)
            except RTreeError:
                self.untreed += 1
                self._reset_tree()
                return {t: self.hypothesiser.hypothesise(t, detections, timestamp, **kwargs) for t in tracks}

    class OutsideTrackGates(Initiator):
        """Passes to ``initiator`` the unassigned plots that lie in no gate of the tracks
        ``associator`` hypothesised at this step, when ``drop`` (else all of them, counting).
        With nine radars a feeder window often holds two plots of one aircraft; GNN assigns a
        track one, and the other, inside the track's gate, would start a second track of the
        same aircraft. Stone Soup's ``MultiTargetMixtureTracker`` keeps from its initiator
        every plot with a hypothesis better than a miss; this applies the same rule to
        ``MultiTargetTracker``'s GNN. Counts: ``in_gate`` plots left unassigned inside a gate,
        ``seen`` their ids."""
        initiator: Initiator = Property(doc="the wrapped initiator")
        associator: object = Property(doc="the TPRTree whose hypotheses give the gates")
        drop: bool = Property(default=True, doc="keep plots inside a gate from the initiator")

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.in_gate, self.seen = 0, set()

        def initiate(self, detections, timestamp, **kwargs):
            t, gated = getattr(self.associator, "gated", (None, set()))
            inside = detections & gated if t == timestamp else set()
            self.in_gate += len(inside)
            self.seen |= {id(d) for d in inside}
            return self.initiator.initiate(detections - inside if self.drop else detections, timestamp, **kwargs)

    def tree():   # one tree per track set: the tracker's and the initiator's
        a = TPRTree(hyp, measurement_model=next(iter(polar.values())), pos_mapping=(0, 2), vel_mapping=(1, 3),
                    horizon_time=datetime.timedelta(seconds=c.delete_after_s))
        a.rebuilds = a.untreed = 0
        return a
    assoc = tree()
    deleter = UpdateTimeDeleter(time_since_update=datetime.timedelta(seconds=c.delete_after_s))
    prior = GaussianState(StateVector(np.zeros(6)), CovarianceMatrix(np.diag(
        [0, c.prior_speed_mps, 0, c.prior_speed_mps, 0, c.prior_vspeed_mps]) ** 2))
    init_assoc = tree()
    drop = not c.initiate_inside_gates
    # the initiator's tentative tracks gate the plots they leave over, the confirmed tracks those the tracker leaves
    tentative_gates = OutsideTrackGates(SimpleMeasurementInitiator(prior_state=prior), init_assoc, drop)
    initiator = MultiMeasurementInitiator(
        prior_state=prior, data_associator=init_assoc, updater=updater, min_points=c.min_points,
        deleter=UpdateTimeDeleter(time_since_update=datetime.timedelta(seconds=c.tentative_delete_after_s)),
        initiator=tentative_gates)
    confirmed_gates = OutsideTrackGates(initiator, assoc, drop)
    feeder = (TimeSyncFeeder(PlotReader(), time_window=datetime.timedelta(seconds=c.sync_s)) if c.sync_s > 0
              else PlotReader())
    tracker = MultiTargetTracker(initiator=confirmed_gates, deleter=deleter, detector=feeder,
                                 data_associator=assoc, updater=updater)
    tracks: set = set()
    for _, current in tracker:
        tracks |= current
    # tracks confirmed mostly from plots left unassigned inside a confirmed track's gate
    first_plots = ([s.hypothesis.measurement for s in tr.states if isinstance(s, Update)][:c.min_points]
                   for tr in tracks)
    from_gated = sum(1 for ps in first_plots if 2 * sum(id(d) in confirmed_gates.seen for d in ps) >= len(ps))
    rows = [(k, s.timestamp, *(float(s.state_vector[i, 0]) for i in range(6)), isinstance(s, Update),
             s.hypothesis.measurement.metadata.get("truth_id") if isinstance(s, Update) else None)
            for k, tr in enumerate(tracks) for s in tr.states]
    frame = pl.DataFrame(rows, schema={"track_id": pl.Int64, "time": pl.Datetime("us", "UTC"), "x_m": pl.Float64,
                                       "vx_mps": pl.Float64, "y_m": pl.Float64, "vy_mps": pl.Float64,
                                       "z_m": pl.Float64, "vz_mps": pl.Float64, "updated": pl.Boolean,
                                       "truth_id": pl.Int64}, orient="row")
    frame.write_parquet(out)
    wall = time.perf_counter() - t_start
    return {"reports": rep.height, "wall_s": wall, "cpu_s": time.process_time() - cpu_start, "tracks": len(tracks),
            "conversion_check_max_m": worst_m, "tree_rebuilds": [assoc.rebuilds, init_assoc.rebuilds],
            "tree_bypassed_steps": [assoc.untreed, init_assoc.untreed],
            "plots_unassigned_in_confirmed_gate": confirmed_gates.in_gate,
            "plots_unassigned_in_tentative_gate": tentative_gates.in_gate,
            "tracks_started_from_confirmed_gate_plots": from_gated,
            "mode_c_fraction": float(np.isfinite(z_h).mean())}


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
print(json.dumps(b.stonesoup_job({dataset!r}, {out!r}, {cfg!r}, {limit!r})))
"""

TERTIARY_CODE = """
import json, time
from tertiary.io.dataset import read_dataset
from tertiary import pipeline
t0, c0 = time.perf_counter(), time.process_time()   # as for Stone Soup: from reading the dataset to the tracks stored
ds = read_dataset({dataset!r})
cfg = pipeline.PipelineConfig(methods=("information",), filters=("imm_sym",), centralized={centralized!r})
import shutil; shutil.rmtree({out!r}, ignore_errors=True)
# every column stored: the scoring reads each track row's status and the fused plots' fresh count
db = pipeline.run(ds, {out!r}, cfg, tables="full")
print(json.dumps({{"reports": ds.reports.height, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                  "db": str(db)}}))
"""


# --------------------------------------------------------------------------- driver


def make_dataset(path: Path, duration_s: float, aircraft: int, seed: int | None, radars: int | None = None) -> Path:
    """A terminal-area recording (1 run) written to ``path`` unless already there, with
    ``radars`` radars (the scenario's four, then sites added by ``with_radar_count``); designed
    conflict pairs scaled down for recordings shorter than 15 min so that they fit."""
    from tertiary.io.dataset import write_dataset
    from tertiary.simulate import load_scenario, simulate
    from tertiary.simulate.config import with_radar_count
    if (path / "reports.parquet").exists():
        return path
    cfg = load_scenario("terminal-area")
    k = min(1.0, duration_s / 900.0)
    traffic = dataclasses.replace(cfg.traffic, aircraft=aircraft,
                                  conflict_pairs=int(round(cfg.traffic.conflict_pairs * k)),
                                  near_miss_pairs=int(round(cfg.traffic.near_miss_pairs * k)))
    cfg = dataclasses.replace(cfg, duration_s=duration_s, runs=1, traffic=traffic)
    if radars is not None:
        cfg = with_radar_count(cfg, radars)
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
    radars' tracks holds a track without updating it (tertiary.stages.tracking.tracker). ``confirmed``: status only."""
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


def detection_spans(reports: pl.DataFrame, grid: TruthGrid, t0) -> np.ndarray:
    """(A, 2) first and last report time (s) of every truth aircraft (NaN: never reported)."""
    f = (reports.filter(pl.col("truth_id").is_not_null() & (pl.col("truth_id") >= 0))
         .group_by("truth_id").agg(seconds("time", t0).min().alias("a"), seconds("time", t0).max().alias("b")))
    spans = np.full((len(grid.ids), 2), np.nan)
    pos = np.searchsorted(grid.ids, f["truth_id"].to_numpy())
    ok = (pos < len(grid.ids)) & (grid.ids[np.minimum(pos, len(grid.ids) - 1)] == f["truth_id"].to_numpy())
    spans[pos[ok]] = f.select("a", "b").to_numpy()[ok]
    return spans


def coverage(picture: pl.DataFrame, grid: TruthGrid, gate_m: float, instants: np.ndarray, spans: np.ndarray) -> float:
    """Share of the (aircraft, instant) pairs inside the aircraft's reported span (first to last
    report, truth present) that hold a state of a track owned by that aircraft within the gate."""
    t = picture["t"].to_numpy()
    xyz = picture.select("x_m", "y_m", "z_m").to_numpy()
    idx, _ = match_nearest(grid, t, xyz[:, :2], gate_m, picture["h_m"].to_numpy())
    own, _ = owners(picture["track_id"].to_numpy(), idx)
    tru = np.full((len(t), 4), np.nan)
    has = own >= 0
    tru[has] = _interp(grid, own[has], t[has])
    ok = ((xyz[:, :2] - tru[:, :2]) ** 2).sum(axis=1) <= gate_m ** 2
    got = {(int(a), float(b)) for a, b in zip(own[ok], t[ok])}
    at = truth_at(grid, instants)[..., 0]                                   # (A, n)
    inside = (instants[None, :] >= spans[:, :1]) & (instants[None, :] <= spans[:, 1:]) & np.isfinite(at)
    a_i, t_i = np.nonzero(inside)
    n = len(a_i)
    hit = sum((int(a), float(instants[k])) in got for a, k in zip(a_i, t_i))
    return hit / n if n else 0.0


def score_all(ss_states: pl.DataFrame, te_states: pl.DataFrame, instants: np.ndarray, grid: TruthGrid,
              gate_m: float, sync_s: float, spans: np.ndarray | None = None) -> tuple[dict, dict]:
    """Both trackers scored with the same rule: the headline at common instants
    (:func:`picture_at` on tertiary's epoch grid: Stone Soup's latest state ≤ :func:`ss_max_age`
    old, moved to the instant by its own CV prediction; tertiary's state at the epoch), its
    ``coverage`` (with ``spans``), and ``own_times`` at each tracker's own state times."""
    return tuple(score_one(states, instants, grid, gate_m, max_age, spans)
                 for states, max_age in ((ss_states, ss_max_age(sync_s)), (te_states, 0.0)))


def ss_max_age(sync_s: float) -> float:
    """How old Stone Soup's latest state may be at a scoring instant: 2 feeder windows, at least 0.5 s."""
    return 2.0 * max(sync_s, 0.25)


def score_one(states: pl.DataFrame, instants: np.ndarray, grid: TruthGrid, gate_m: float, max_age_s: float,
              spans: np.ndarray | None = None) -> dict:
    """One tracker's states scored with the module's rule (see :func:`score_all`)."""
    period = float(np.median(np.diff(instants))) if len(instants) > 1 else 1.0
    pic = picture_at(states, instants, max_age_s, period)
    s = score(pic, grid, gate_m)
    own = score(states, grid, gate_m)
    if "owner_agrees_with_detections" in own:
        s["owner_agrees_with_detections"] = own.pop("owner_agrees_with_detections")
    if spans is not None:
        s["coverage"] = coverage(pic, grid, gate_m, instants, spans)
    return {**s, "picture_period_s": period, "own_times": own}


#: what the sweep minimises (one number per configuration, the same scoring rule as the comparison)
SELECTION_RULE = ("minimise rmse_horizontal_m + rmse_vertical_m (picture at the common instants) among the "
                  "configurations with tracks_per_aircraft <= 1.2 and coverage >= 0.9 x the best coverage of the "
                  "sweep; coordinate-wise from the base configuration: each swept parameter takes its best value")

#: the sweep: the base configuration, then one parameter changed at a time (the first axis is
#: Stone Soup's own rule for plots left unassigned inside a gate, the cause of second tracks)
SWEEP_BASE = StoneSoupConfig()
SWEEP_AXES = {"initiate_inside_gates": (True,), "sync_s": (0.1,), "q_h_m2ps3": (50.0, 800.0), "q_v_m2ps3": (2.0,),
              "min_points": (5,), "gate": (5.0,), "delete_after_s": (10.0,)}


def sweep_points(base: StoneSoupConfig = SWEEP_BASE, axes: dict = SWEEP_AXES) -> list[StoneSoupConfig]:
    """The base configuration then each axis value with the other parameters at the base."""
    return [base] + [dataclasses.replace(base, **{k: v}) for k, vs in axes.items() for v in vs]


def select(points: list[dict], base: dict, axes: tuple[str, ...]) -> dict:
    """The frozen configuration from scored sweep points (:data:`SELECTION_RULE`): each point
    {"config": {...}, "score": {...}}; returns the chosen config."""
    best_cov = max((p["score"].get("coverage") or 0.0) for p in points)

    def admissible(p):
        s = p["score"]
        return ((s.get("tracks_per_aircraft") or 99.0) <= 1.2 and (s.get("coverage") or 0.0) >= 0.9 * best_cov
                and s.get("rmse_horizontal_m") is not None and s.get("rmse_vertical_m") is not None)

    def cost(p):
        return p["score"]["rmse_horizontal_m"] + p["score"]["rmse_vertical_m"]

    chosen = dict(base)
    for ax in axes:   # points on this axis: the base and the points differing from it only on ax
        on_axis = [p for p in points if all(p["config"][k] == base[k] for k in base if k != ax) and admissible(p)]
        if on_axis:
            chosen[ax] = min(on_axis, key=cost)["config"][ax]
    return chosen


def run_tertiary(data: Path, out: Path, centralized: bool = False) -> dict:
    return run_isolated(TERTIARY_CODE.format(dataset=str(data), out=str(out), centralized=centralized))


def run_stonesoup(data: Path, out: Path, cfg: StoneSoupConfig, limit_s: float | None) -> dict:
    return run_isolated(STONESOUP_CODE.format(bench=str(BENCH_DIR), dataset=str(data), out=str(out),
                                              cfg=dataclasses.asdict(cfg), limit=limit_s))


RESULTS = BENCH_DIR / "results" / "bench_stonesoup.json"


def _load() -> dict:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else {}


def _save(doc: dict) -> None:
    doc.pop("machine", None)
    print(f"recorded in {record('bench_stonesoup', doc)}")


def scenario_of(ds, args, seed: int, window_s: float | None) -> dict:
    return {"name": "terminal-area", "aircraft": args.aircraft, "duration_s": args.duration, "radars": ds.radars.height,
            "seed": seed, "reports": ds.reports.height, "window_s": window_s}


def sweep(args, work: Path) -> None:
    """The recorded sweep on the tuning seed: Stone Soup on the first ``--tune-window`` s of
    the tuning recording, each configuration in a fresh process, scored at tertiary's epochs."""
    from tertiary.io.dataset import read_dataset
    data = make_dataset(work / f"tune_seed{args.tune_seed}", args.duration, args.aircraft, args.tune_seed, args.radars)
    ds = read_dataset(data)
    t0 = ds.truth["time"].min()
    grid = truth_grid(ds.truth, t0)
    db = work / "tune_tertiary" / "results.duckdb"   # tertiary's epochs on the tuning recording: run once
    te = {"db": str(db)} if db.exists() else run_tertiary(data, work / "tune_tertiary")
    t_end = ds.reports.select(seconds("time", t0).min()).item() + args.tune_window
    instants = picture_instants(te["db"], t0)
    instants = instants[instants < t_end]
    spans = detection_spans(ds.reports.filter(seconds("time", t0) < t_end), grid, t0)
    te_score = score_one(tertiary_states(te["db"], t0, ds.origin).filter(pl.col("t") < t_end), instants, grid,
                         args.gate, 0.0, spans)
    old = _load()
    done = {json.dumps(p["config"], sort_keys=True): p for p in old.get("sweep", {}).get("points", [])
            if old["sweep"].get("scenario", {}).get("window_s") == args.tune_window and "score" in p}
    doc = {k: v for k, v in old.items() if k == "evaluation"}
    doc["sweep"] = {"scenario": scenario_of(ds, args, args.tune_seed, args.tune_window),
                    "selection_rule": SELECTION_RULE, "base": dataclasses.asdict(SWEEP_BASE),
                    "axes": {k: list(v) for k, v in SWEEP_AXES.items()},
                    "tertiary_on_the_window": {k: te_score[k] for k in _TABLE if k in te_score}, "points": []}
    from concurrent.futures import ThreadPoolExecutor

    def measure(i_cfg):   # one point: Stone Soup in a fresh process, then scored here
        i, cfg = i_cfg
        out = work / f"tune_stonesoup_{i}.parquet"
        try:
            ss = run_stonesoup(data, out, cfg, args.tune_window)
        except Exception as exc:   # noqa: BLE001 — a failed configuration is recorded, not fatal
            return {"config": dataclasses.asdict(cfg), "error": repr(exc)[:300]}
        s = score_one(stonesoup_states(out, t0, ds.origin), instants, grid, args.gate, ss_max_age(cfg.sync_s),
                      spans)
        return {"config": dataclasses.asdict(cfg), "wall_s": ss["wall_s"], "cpu_s": ss.get("cpu_s"),
                "reports": ss["reports"], "reports_per_s": ss["reports"] / ss["wall_s"],
                "peak_rss_mib": ss["peak_rss_mib"], "score": {k: s[k] for k in _TABLE if k in s},
                "job": {k: ss[k] for k in _SS_COUNTERS if k in ss}}

    todo = []
    for i, cfg in enumerate(sweep_points()):
        key = json.dumps(dataclasses.asdict(cfg), sort_keys=True)
        if key in done:   # a point measured by an earlier, interrupted sweep of the same window
            doc["sweep"]["points"].append(done[key])
        else:
            todo.append((i, cfg))
    doc["sweep"]["parallel_jobs"] = args.jobs
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:   # each point is its own process
        for point in pool.map(measure, todo):
            doc["sweep"]["points"].append(point)
            print(json.dumps(point), flush=True)
            ok = [p for p in doc["sweep"]["points"] if "score" in p]
            doc["sweep"]["frozen"] = select(ok, dataclasses.asdict(SWEEP_BASE), tuple(SWEEP_AXES))
            _save(doc)


_TABLE = ("states", "states_matched_fraction", "rmse_horizontal_m", "rmse_vertical_m", "rmse_horizontal_updated_m",
          "rmse_vertical_updated_m", "rmse_z_enu_m", "tracks", "false_tracks", "aircraft_tracked",
          "tracks_per_aircraft", "coverage", "owner_agrees_with_detections", "extra_tracks", "extra_concurrent",
          "median_overlap_s")
#: Stone Soup job counters recorded with each run (:func:`stonesoup_job`)
_SS_COUNTERS = ("tracks", "tree_rebuilds", "tree_bypassed_steps", "plots_unassigned_in_confirmed_gate",
                "plots_unassigned_in_tentative_gate", "tracks_started_from_confirmed_gate_plots")


def compare(args, work: Path) -> None:
    """The frozen configuration and tertiary's production picture on the evaluation seed, the
    whole recording for both, each in a fresh process, scored with the one rule."""
    from tertiary.io.dataset import read_dataset
    doc = _load()
    frozen = StoneSoupConfig(**doc["sweep"]["frozen"]) if "sweep" in doc and "frozen" in doc["sweep"] \
        else StoneSoupConfig()
    data = make_dataset(work / f"eval_seed{args.seed}", args.duration, args.aircraft, args.seed, args.radars)
    ss_out, jobs = work / "eval_stonesoup.parquet", work / "eval_jobs.json"
    if args.rescore:
        ss, te = json.loads(jobs.read_text())
    elif args.tertiary_only:      # Stone Soup's job of an earlier call kept; tertiary run again, fresh
        ss = json.loads(jobs.read_text())[0]
        te = run_tertiary(data, work / "eval_tertiary", args.centralized)
        jobs.write_text(json.dumps([ss, te]))
    else:
        ss = run_stonesoup(data, ss_out, frozen, None)
        te = run_tertiary(data, work / "eval_tertiary", args.centralized)
        jobs.write_text(json.dumps([ss, te]))
    ds = read_dataset(data)
    t0 = ds.truth["time"].min()
    grid = truth_grid(ds.truth, t0)
    instants = picture_instants(te["db"], t0)
    spans = detection_spans(ds.reports, grid, t0)
    ss_score, te_score = score_all(stonesoup_states(ss_out, t0, ds.origin), tertiary_states(te["db"], t0, ds.origin),
                                   instants, grid, args.gate, frozen.sync_s, spans)
    detected = int(np.isfinite(spans[:, 0]).sum())
    ss_rate, te_rate = ss["reports"] / ss["wall_s"], te["reports"] / te["wall_s"]
    row = lambda job, rate, s: {"wall_s": job["wall_s"], "cpu_s": job.get("cpu_s"), "reports_per_s": rate,  # noqa: E731
                                "peak_rss_mib": job["peak_rss_mib"], **{k: s[k] for k in _TABLE if k in s},
                                "aircraft_detected": detected, "own_times": s["own_times"]}
    doc["evaluation"] = {
        "scenario": {**scenario_of(ds, args, args.seed, None), "stonesoup_reports": ss["reports"],
                     "tertiary_reports": te["reports"]},
        "stonesoup": {"version": _version("stonesoup"), "config": dataclasses.asdict(frozen),
                      "components": STONESOUP_COMPONENTS, "mode_c_fraction": ss.get("mode_c_fraction"),
                      "conversion_check_max_m": ss.get("conversion_check_max_m"), **row(ss, ss_rate, ss_score),
                      "job": {k: ss[k] for k in _SS_COUNTERS if k in ss}},
        "tertiary": {"config": {"methods": ["information"], "filters": ["imm_sym"], "centralized": args.centralized,
                                "conflicts": True, "store": True}, **row(te, te_rate, te_score)},
        "ratio": te_rate / ss_rate}
    doc["ratio"] = te_rate / ss_rate
    doc["ratio_cpu"] = (te["reports"] / te["cpu_s"]) / (ss["reports"] / ss["cpu_s"]) if ss.get("cpu_s") else None
    doc["stonesoup_better_on"] = where_better(doc["evaluation"]["stonesoup"], doc["evaluation"]["tertiary"])
    doc["target"] = {"ratio": 300, "accuracy": "clearly better RMSE", "ratio_met": te_rate / ss_rate >= 300}
    doc["scoring"] = {"gate_m": args.gate, "rule": SCORING_RULE, "version": RULE_VERSION}
    doc["requirements"] = requirements(doc)
    _save(doc)
    print(json.dumps(doc["evaluation"], indent=2))


def requirements(doc: dict) -> dict:
    """The benchmark's requirements, each met or not with its numbers, from the results."""
    ev, sw = doc["evaluation"], doc.get("sweep", {})
    ss, te = ev["stonesoup"], ev["tertiary"]
    frozen = [p for p in sw.get("points", []) if p.get("config") == sw.get("frozen") and "score" in p]
    tpa = ss["tracks_per_aircraft"]
    return {
        "reports_ge_100k": ev["scenario"]["reports"] >= 100_000,
        "same_reports_both": ev["scenario"]["stonesoup_reports"] == ev["scenario"]["tertiary_reports"],
        "recorded_sweep": {"points": len(sw.get("points", [])), "window_s": sw.get("scenario", {}).get("window_s"),
                           "tuning_seed": sw.get("scenario", {}).get("seed"), "evaluation_seed": ev["scenario"]["seed"],
                           "frozen_config_evaluated": ss["config"] == sw.get("frozen")},
        "stonesoup_tracks_per_aircraft_le_1_2": {
            "tuning_window": frozen[0]["score"]["tracks_per_aircraft"] if frozen else None,
            "evaluation": tpa, "met": tpa is not None and tpa <= 1.2},
        "ratio_ge_300": {"ratio_wall": doc["ratio"], "ratio_cpu": doc.get("ratio_cpu"),
                         "met": doc["ratio"] >= 300 and (doc.get("ratio_cpu") or 0) >= 300},
        "clearly_better_accuracy": {
            "horizontal_m": {"tertiary": te["rmse_horizontal_m"], "stonesoup": ss["rmse_horizontal_m"]},
            "vertical_m": {"tertiary": te["rmse_vertical_m"], "stonesoup": ss["rmse_vertical_m"]},
            "met": te["rmse_horizontal_m"] < ss["rmse_horizontal_m"] and te["rmse_vertical_m"] < ss["rmse_vertical_m"]},
    }


#: the compared figures and whether lower is better
_BETTER_LOW = {"rmse_horizontal_m": True, "rmse_vertical_m": True, "rmse_horizontal_updated_m": True,
               "rmse_vertical_updated_m": True, "rmse_z_enu_m": True, "tracks_per_aircraft": True,
               "false_tracks": True, "peak_rss_mib": True, "wall_s": True, "coverage": False,
               "states_matched_fraction": False, "aircraft_tracked": False}


def where_better(ss: dict, te: dict) -> dict:
    """The figures on which Stone Soup beats tertiary: {name: [stonesoup, tertiary]}."""
    out = {}
    for k, low in _BETTER_LOW.items():
        a, b = ss.get(k), te.get(k)
        if a is not None and b is not None and ((a < b) if low else (a > b)):
            out[k] = [a, b]
    return out


#: the Stone Soup components of :func:`stonesoup_job`, recorded with the results
STONESOUP_COMPONENTS = {
    "tracker": "stonesoup.tracker.simple.MultiTargetTracker",
    "feeder": "stonesoup.feeder.time.TimeSyncFeeder over a time-ordered DetectionReader",
    "measurement_model": "per radar CombinedReversibleGaussianMeasurementModel(CartesianToElevationBearingRange, "
                         "LinearGaussian on z = Mode C height); CartesianToElevationBearingRange alone without Mode C",
    "transition_model": "CombinedLinearGaussianTransitionModel(ConstantVelocity(q_h) x 2, ConstantVelocity(q_v))",
    "predictor": "stonesoup.predictor.kalman.KalmanPredictor",
    "updater": "stonesoup.updater.kalman.ExtendedKalmanUpdater",
    "hypothesiser": "stonesoup.hypothesiser.distance.DistanceHypothesiser(Mahalanobis, missed_distance = gate)",
    "data_associator": "stonesoup.dataassociator.tree.TPRTreeGNN2D (rtree TPR-tree of the tracks, x-y, "
                       "horizon = delete_after_s, boxes widened by tree_margin_m, rebuilt where rtree refuses a query)",
    "initiator": "stonesoup.initiator.simple.MultiMeasurementInitiator (its own TPRTreeGNN2D, "
                 "UpdateTimeDeleter(tentative_delete_after_s), min_points)",
    "deleter": "stonesoup.deleter.time.UpdateTimeDeleter(delete_after_s)",
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("sweep", "compare"), help="sweep: tune Stone Soup on the tuning seed; "
                    "compare: the frozen configuration and tertiary on the evaluation seed")
    ap.add_argument("--duration", type=float, default=900.0, help="recording length, s")
    ap.add_argument("--aircraft", type=int, default=200)
    ap.add_argument("--radars", type=int, default=9, help="radars (the scenario's 4, then added sites)")
    ap.add_argument("--seed", type=int, default=5, help="evaluation seed")
    ap.add_argument("--tune-seed", type=int, default=11, help="tuning seed (sweep)")
    ap.add_argument("--tune-window", type=float, default=150.0, help="sweep: Stone Soup on the first S s")
    ap.add_argument("--jobs", type=int, default=1, help="sweep: points run at once (each its own process)")
    ap.add_argument("--workdir", type=Path, default=None, help="datasets and outputs [default: a temp dir]")
    ap.add_argument("--gate", type=float, default=1000.0, help="scoring gate, m (horizontal)")
    ap.add_argument("--centralized", action="store_true", help="tertiary also runs the centralised reference")
    ap.add_argument("--rescore", action="store_true", help="compare: re-score the jobs already run in --workdir")
    ap.add_argument("--tertiary-only", action="store_true",
                    help="compare: keep the Stone Soup job already run in --workdir, run tertiary again")
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="bench_stonesoup_"))
    work.mkdir(parents=True, exist_ok=True)
    (sweep if args.mode == "sweep" else compare)(args, work)


def _version(name: str) -> str | None:
    from importlib import metadata
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


if __name__ == "__main__":
    main()
