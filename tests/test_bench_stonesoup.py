"""benchmarks/bench_stonesoup.py: the plot conversion to Stone Soup's measurement model and the
one scoring rule, with numpy only (Stone Soup itself is not needed; the benchmark checks its real
model against the same conversion before it runs)."""

from __future__ import annotations

import importlib.util
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from tertiary.core import geo

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_stonesoup.py"
sys.path.insert(0, str(_PATH.parent))
_spec = importlib.util.spec_from_file_location("bench_stonesoup", _PATH)
bench = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("bench_stonesoup", bench)   # dataclasses resolve their module
_spec.loader.exec_module(bench)

SYSTEM = geo.LocalFrame(48.85, 2.35, 0.0)
RADARS = pl.DataFrame({"radar_id": [1, 2], "lat_deg": [49.30, 48.60], "lon_deg": [3.10, 1.70],
                       "alt_m": [210.0, 95.0], "sigma_range_m": [30.0, 50.0],
                       "sigma_azimuth_deg": [0.05, 0.08], "sigma_elevation_deg": [0.1, 0.2]})


def test_bearing_is_counter_clockwise_from_east():
    # north (az 0) is +y: bearing +90°; east (az 90) is +x: bearing 0; west (az 270): ±180°
    got = np.degrees(bench.azimuth_to_bearing(np.array([0.0, 90.0, 180.0, 45.0, 359.0])))
    np.testing.assert_allclose(got, [90.0, 0.0, -90.0, 45.0, 91.0], atol=1e-12)
    assert abs(abs(np.degrees(bench.azimuth_to_bearing(np.array([270.0]))[0])) - 180.0) < 1e-12


def test_rotation_angles_rebuild_the_site_rotation():
    for r in RADARS.iter_rows(named=True):
        m = SYSTEM.rotation_to(geo.LocalFrame(r["lat_deg"], r["lon_deg"], r["alt_m"]))
        assert np.abs(m - np.eye(3)).max() > 1e-3          # sites far enough for the rotation to matter
        np.testing.assert_allclose(bench.ss_rotation_matrix(bench.rotation_angles(m)), m, atol=1e-14)


def test_stonesoup_inverse_of_converted_plots_lands_on_tertiary_conversion():
    rng = np.random.default_rng(3)
    geom = bench.site_geometry(RADARS, SYSTEM)
    for r in RADARS.iter_rows(named=True):
        n = 500
        rng_m, az, el = rng.uniform(1e3, 2.5e5, n), rng.uniform(0, 360, n), rng.uniform(-1, 30, n)
        meas = bench.plots_to_measurements(rng_m, az, el)
        ss = bench.ss_inverse(meas, geom[r["radar_id"]])
        ours = bench.tertiary_plot_to_system(rng_m, az, el, r, SYSTEM)
        assert np.abs(ss - ours).max() < 1e-6
        # and a swapped convention (bearing = azimuth) would be km off
        wrong = meas.copy()
        wrong[:, 1] = np.radians(az)
        assert np.abs(bench.ss_inverse(wrong, geom[r["radar_id"]]) - ours).max() > 1e3
    # σ ordering follows the measurement vector (elevation, bearing, range)
    np.testing.assert_allclose(geom[1].sigma, [np.radians(0.1), np.radians(0.05), 30.0])


def test_site_translation_is_the_site_in_the_system_frame():
    g = bench.site_geometry(RADARS, SYSTEM)[2]
    e, n, u = SYSTEM.from_geodetic(48.60, 1.70, 95.0)
    np.testing.assert_allclose(g.translation, [e, n, u], atol=1e-6)


T0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)


def _truth() -> pl.DataFrame:
    """Two aircraft on a 1 s grid: A east at 100 m/s from (0, 0, 3000); B north at 50 m/s from
    (5000, 0, 6000), present from t = 2 s."""
    rows = []
    for k in range(11):
        rows.append((1, T0 + timedelta(seconds=k), 100.0 * k, 0.0, 3000.0, 3000.0))
        if k >= 2:
            rows.append((2, T0 + timedelta(seconds=k), 5000.0, 50.0 * k, 6000.0, 6000.0))
    return pl.DataFrame(rows, schema=["truth_id", "time", "x_m", "y_m", "z_m", "alt_m"], orient="row")


def test_truth_is_interpolated_between_grid_samples_and_absent_outside_life():
    grid = bench.truth_grid(_truth(), T0)
    at = bench.truth_at(grid, np.array([0.5, 3.25, 10.0]))
    np.testing.assert_allclose(at[0, :, 0], [50.0, 325.0, 1000.0])
    assert np.isnan(at[1, 0]).all()
    np.testing.assert_allclose(at[1, 1, 1], 162.5)


def test_score_one_rule_horizontal_vertical_and_tracks_per_aircraft():
    grid = bench.truth_grid(_truth(), T0)
    t = np.array([0.5, 1.5, 2.5, 3.5, 2.5, 3.5, 4.0, 5.0])
    states = pl.DataFrame({
        "track_id": [1, 1, 1, 1, 2, 2, 3, 3],
        "t": t,
        # track 1 follows A with 30 m east / 40 m north error; track 2 follows B with 10 m; track 3 is
        # far from everything (false)
        "x_m": [80.0, 180.0, 280.0, 380.0, 5010.0, 5010.0, -9e4, -9e4],
        "y_m": [40.0, 40.0, 40.0, 40.0, 125.0, 175.0, 9e4, 9e4],
        "z_m": [3000.0] * 4 + [6000.0] * 2 + [0.0, 0.0],
        "h_m": [3020.0] * 4 + [5990.0] * 2 + [0.0, 0.0],
        "updated": [True, False, True, False, True, True, True, True],
    })
    s = bench.score(states, grid, gate_m=1000.0)
    assert s["states"] == 8 and s["states_matched_fraction"] == pytest.approx(6 / 8)
    # horizontal e² = 50² for track 1 (4 states), 10² for track 2 (2 states)
    assert s["rmse_horizontal_m"] == pytest.approx(np.sqrt((4 * 2500 + 2 * 100) / 6))
    assert s["rmse_vertical_m"] == pytest.approx(np.sqrt((4 * 400 + 2 * 100) / 6))
    assert s["rmse_horizontal_updated_m"] == pytest.approx(np.sqrt((2 * 2500 + 2 * 100) / 4))
    assert s["tracks"] == 3 and s["false_tracks"] == 1 and s["aircraft_tracked"] == 2
    assert s["tracks_per_aircraft"] == pytest.approx(1.0)
    # a second track on A makes 1.5 tracks per aircraft
    extra = states.head(2).with_columns(pl.lit(4, pl.Int64).alias("track_id"))
    assert bench.score(pl.concat([states, extra]), grid, 1000.0)["tracks_per_aircraft"] == pytest.approx(1.5)


def test_nearest_truth_respects_the_gate():
    grid = bench.truth_grid(_truth(), T0)
    idx, tru = bench.match_nearest(grid, np.array([3.0, 3.0]), np.array([[300.0, 900.0], [300.0, 1100.0]]), 1000.0)
    assert idx.tolist() == [0, -1] and np.isnan(tru[1]).all()


def test_a_state_nearer_another_aircraft_is_scored_against_its_tracks_aircraft():
    """Stacked traffic: C sits 100 m east of A's track point at t = 3 s, 3 km higher. The track
    follows A (its owner by majority), so its t = 3 s state is scored against A, not C."""
    truth = pl.concat([_truth(), pl.DataFrame(
        [(3, T0 + timedelta(seconds=3), 380.0, 0.0, 6000.0, 6000.0)],
        schema=["truth_id", "time", "x_m", "y_m", "z_m", "alt_m"], orient="row")])
    grid = bench.truth_grid(truth, T0)
    states = pl.DataFrame({"track_id": [1] * 4, "t": [1.0, 2.0, 3.0, 4.0], "x_m": [100.0, 200.0, 360.0, 400.0],
                           "y_m": [0.0] * 4, "z_m": [3000.0] * 4, "h_m": [3000.0] * 4, "updated": [True] * 4})
    idx, _ = bench.match_nearest(grid, states["t"].to_numpy(), states.select("x_m", "y_m").to_numpy(), 1000.0)
    assert grid.ids[idx[2]] == 3                      # the per-state nearest is C ...
    s = bench.score(states, grid, 1000.0)
    assert s["rmse_vertical_m"] == pytest.approx(0.0)  # ... but the track is scored against A
    assert s["rmse_horizontal_m"] == pytest.approx(np.sqrt(60.0 ** 2 / 4))
    assert s["tracks_per_aircraft"] == 1.0 and s["aircraft_tracked"] == 1


def test_stonesoup_owner_is_checked_against_its_detections_truth():
    grid = bench.truth_grid(_truth(), T0)
    states = pl.DataFrame({"track_id": [1, 1, 2, 2], "t": [2.0, 3.0, 2.0, 3.0],
                           "x_m": [200.0, 300.0, 5000.0, 5000.0], "y_m": [0.0, 0.0, 100.0, 150.0],
                           "z_m": [3000.0, 3000.0, 6000.0, 6000.0], "h_m": [3000.0, 3000.0, 6000.0, 6000.0],
                           "updated": [True] * 4, "truth_id": [1, 1, 1, 1]})   # track 2's detections say A
    assert bench.score(states, grid, 1000.0)["owner_agrees_with_detections"] == pytest.approx(0.5)


def test_stacked_aircraft_are_told_apart_by_reported_height():
    """D flies exactly above A (same ground track, 6 km higher): a track reporting D's height
    belongs to D, a track reporting A's height to A; horizontally both are 0 m from each."""
    rows = [(4, T0 + timedelta(seconds=k), 100.0 * k, 0.0, 9000.0, 9000.0) for k in range(11)]
    grid = bench.truth_grid(pl.concat([_truth(), pl.DataFrame(rows, schema=_truth().schema, orient="row")]), T0)
    t, xy = np.array([3.0, 3.0]), np.array([[300.0, 0.0], [300.0, 0.0]])
    idx, tru = bench.match_nearest(grid, t, xy, 1000.0, h=np.array([9010.0, 3010.0]))
    assert grid.ids[idx].tolist() == [4, 1]
    np.testing.assert_allclose(tru[:, 3], [9000.0, 3000.0])
    states = pl.DataFrame({"track_id": [7, 7], "t": [3.0, 4.0], "x_m": [300.0, 400.0], "y_m": [0.0, 0.0],
                           "z_m": [9000.0, 9000.0], "h_m": [9010.0, 9010.0], "updated": [True, True]})
    assert bench.score(states, grid, 1000.0)["rmse_vertical_m"] == pytest.approx(10.0)


# --------------------------------------------------------------------------- corrected rules (2026-11-25)


def test_truth_is_never_extrapolated_past_a_life_or_the_recording():
    """A's truth ends at t = 10 s (the recording's end), B's starts at t = 2 s. A state at
    10.5 s has no truth (the superseded rule compared it with A at 10 s, 50 m behind); nor has
    B at 1.5 s (the superseded rule used B at 2 s)."""
    grid = bench.truth_grid(_truth(), T0)
    at = bench.truth_at(grid, np.array([1.5, 10.0, 10.5, 12.0]))
    assert np.isnan(at[0, 2:]).all() and at[0, 1, 0] == pytest.approx(1000.0)
    assert np.isnan(at[1, 0]).all() and at[1, 1, 1] == pytest.approx(500.0)
    legacy = bench.truth_at(grid, np.array([1.5, 10.5]), strict=False)
    assert legacy[0, 1, 0] == pytest.approx(1000.0) and legacy[1, 0, 1] == pytest.approx(100.0)


def test_states_after_the_recording_are_unmatched_not_scored_against_stale_truth():
    """A track on A with a 10 m error, held 5 s past the end of the truth at 100 m/s: those
    states are unmatched (they used to count with errors of 100–500 m, inside the gate)."""
    grid = bench.truth_grid(_truth(), T0)
    t = np.arange(4.0, 16.0)
    states = pl.DataFrame({"track_id": [1] * len(t), "t": t, "x_m": 100.0 * t, "y_m": np.full(len(t), 10.0),
                           "z_m": np.full(len(t), 3000.0), "h_m": np.full(len(t), 3000.0),
                           "updated": np.ones(len(t), bool)})
    s = bench.score(states, grid, 1000.0)
    assert s["rmse_horizontal_m"] == pytest.approx(10.0)
    assert s["states_matched_fraction"] == pytest.approx(7 / 12)
    old = bench.score(states, grid, 1000.0, strict=False)
    assert old["rmse_horizontal_m"] > 150.0


def _ss_track(t: np.ndarray, vx: float, updated: np.ndarray, track_id: int = 1, x0: float = 0.0) -> pl.DataFrame:
    return pl.DataFrame({"track_id": np.full(len(t), track_id), "t": t, "x_m": x0 + vx * t, "y_m": np.zeros(len(t)),
                         "z_m": np.full(len(t), 3000.0), "h_m": np.full(len(t), 3000.0), "vx_mps": np.full(len(t), vx),
                         "vy_mps": np.zeros(len(t)), "vz_mps": np.zeros(len(t)), "updated": updated})


def test_picture_moves_the_latest_state_to_the_instant_and_dates_the_last_update():
    """States every 0.25 s from 1.0 to 6.0 s, updates at 1.0 and 2.1 s only: at the instants
    0, 4, 8 the track is absent before its first state and after max_age; at 4.0 its latest
    state (4.0) is taken; at 6.3 (0.3 s after its last state) it is moved 0.3 s along; updated
    only while the last update is within the period."""
    t = np.r_[np.arange(1.0, 6.01, 0.25), 2.1]
    upd = np.isin(t, [1.0, 2.1])
    pic = bench.picture_at(_ss_track(t, 100.0, upd), np.array([0.0, 4.0, 5.0, 6.3, 8.0]), max_age_s=0.5,
                           period_s=4.0).sort("t")
    assert pic["t"].to_list() == [4.0, 5.0, 6.3]
    np.testing.assert_allclose(pic["x_m"].to_numpy(), [400.0, 500.0, 630.0])
    assert pic["updated"].to_list() == [True, True, False]          # 6.3 − 2.1 ≥ 4 s


def test_picture_recovers_velocity_from_predictions_when_not_stored():
    """An output without velocity columns: each state's velocity comes from the CV prediction
    that follows it (exact), not from a difference across an update's jump."""
    t = np.arange(0.0, 3.01, 0.25)
    f = _ss_track(t, 80.0, np.zeros(len(t), bool))
    x = f["x_m"].to_numpy().copy()
    x[8:] += 40.0                                        # an update at t = 2.0 moved the track 40 m
    upd = np.zeros(len(t), bool)
    upd[8] = True
    g = f.with_columns(pl.Series("x_m", x), pl.Series("updated", upd)).drop("vx_mps", "vy_mps", "vz_mps")
    pic = bench.picture_at(g, np.array([2.2]), max_age_s=0.5, period_s=4.0)
    assert pic["x_m"].item() == pytest.approx(80.0 * 2.2 + 40.0)    # backward difference: +32 m


def test_picture_scores_both_trackers_at_the_same_instants():
    """One rule for both: a tertiary-like track at 4 s epochs and a Stone Soup-like track at
    0.25 s steps on the same aircraft, both 20 m off, give the same picture RMSE."""
    grid = bench.truth_grid(_truth(), T0)
    inst = np.array([2.0, 6.0, 10.0])
    fine = np.arange(0.0, 10.01, 0.25)
    ss = _ss_track(fine, 100.0, np.ones(len(fine), bool), x0=20.0)
    te = _ss_track(inst, 100.0, np.ones(len(inst), bool), x0=20.0)
    a = bench.score(bench.picture_at(ss, inst, 0.5, 4.0), grid, 1000.0)
    b = bench.score(bench.picture_at(te, inst, 0.0, 4.0), grid, 1000.0)
    assert a["states"] == b["states"] == 3
    assert a["rmse_horizontal_m"] == pytest.approx(20.0) and b["rmse_horizontal_m"] == pytest.approx(20.0)


def test_tertiary_updated_needs_a_fresh_measurement(tmp_path):
    """A track row holding a plot with no fresh measurement (n_fresh = 0) is confirmed but not
    measurement-updated; the superseded definition kept it as updated."""
    import duckdb
    ep = [T0 + timedelta(seconds=4 * k) for k in range(3)]
    tracks = pl.DataFrame({"track_id": [1, 1, 1], "epoch": ep, "x_m": [0.0, 400.0, 800.0], "y_m": [0.0] * 3,
                           "z_m": [3000.0] * 3, "vx_mps": [100.0] * 3, "vy_mps": [0.0] * 3, "vz_mps": [0.0] * 3,
                           "alt_m": [3000.0] * 3, "status": ["confirmed", "confirmed", "coasting"],
                           "plot_target_id": [5, 5, None], "method": ["information"] * 3, "filter": ["imm_sym"] * 3})
    fused = pl.DataFrame({"epoch": ep[:2], "target_id": [5, 5], "n_fresh": [2, 0], "method": ["information"] * 2})
    db = str(tmp_path / "r.duckdb")
    with duckdb.connect(db) as con:
        con.register("t", tracks.to_arrow())
        con.register("f", fused.to_arrow())
        con.execute("create table tracks as select * from t")
        con.execute("create table fused as select * from f")
    st = bench.tertiary_states(db, T0, SYSTEM).sort("t")
    assert st["updated"].to_list() == [True, False, False]
    assert st["confirmed"].to_list() == [True, True, False]
    np.testing.assert_allclose(bench.picture_instants(db, T0), [0.0, 4.0])


def test_mode_c_height_becomes_the_system_z_with_the_curvature_drop():
    e, n = np.array([0.0, 60_000.0, 0.0]), np.array([0.0, 0.0, -30_000.0])
    h = np.array([3000.0, 3000.0, 900.0])
    lat, lon, _ = SYSTEM.to_geodetic(e, n, np.zeros(3))
    xyz = np.stack([e, n, np.zeros(3)], axis=1)
    z = bench.mode_c_to_z(xyz, h, SYSTEM)
    np.testing.assert_allclose(z, SYSTEM.from_geodetic(lat, lon, h)[2], atol=1e-6)
    # a point 60 km away at 3000 m sits ~280 m lower in the system frame; no Mode C gives NaN
    assert 250.0 < 3000.0 - z[1] < 310.0 and abs(z[0] - 3000.0) < 1e-6
    assert np.isnan(bench.mode_c_to_z(xyz[:1], np.array([np.nan]), SYSTEM)).all()


def test_mode_c_sigma_is_the_quantisation():
    np.testing.assert_allclose(bench.mode_c_sigma(np.array([True, False])),
                               [25 * 0.3048 / np.sqrt(12), 100 * 0.3048 / np.sqrt(12)])


def test_sweep_points_change_one_parameter_at_a_time():
    pts = bench.sweep_points()
    base = bench.SWEEP_BASE
    assert pts[0] == base and len(pts) == 1 + sum(len(v) for v in bench.SWEEP_AXES.values())
    for p in pts[1:]:
        diff = [k for k in bench.SWEEP_AXES if getattr(p, k) != getattr(base, k)]
        assert len(diff) == 1


def test_selection_rule_respects_tracks_per_aircraft_and_coverage():
    base = {"q": 1.0, "m": 5}

    def pt(q, m, h, v, tpa, cov):
        return {"config": {"q": q, "m": m}, "score": {"rmse_horizontal_m": h, "rmse_vertical_m": v,
                                                      "tracks_per_aircraft": tpa, "coverage": cov}}
    points = [pt(1.0, 5, 80, 20, 1.1, 0.95), pt(2.0, 5, 60, 20, 1.1, 0.95), pt(4.0, 5, 40, 20, 1.5, 0.95),
              pt(1.0, 3, 50, 20, 1.1, 0.50), pt(1.0, 7, 70, 20, 1.0, 0.94)]
    # q: 4 has too many tracks per aircraft, 2 is best; m: 3 covers too little, 7 beats the base
    assert bench.select(points, base, ("q", "m")) == {"q": 2.0, "m": 7}


def test_coverage_counts_owned_states_inside_the_reported_span():
    grid = bench.truth_grid(_truth(), T0)
    instants = np.array([2.0, 4.0, 6.0, 8.0])
    spans = np.array([[0.0, 10.0], [2.0, 5.0]])   # B reported from 2 s to 5 s only
    pic = pl.DataFrame({"track_id": [1, 1, 1, 2], "t": [2.0, 4.0, 6.0, 4.0],
                        "x_m": [200.0, 400.0, 600.0, 5000.0], "y_m": [0.0, 0.0, 0.0, 200.0],
                        "z_m": [3000.0, 3000.0, 3000.0, 6000.0], "h_m": [3000.0, 3000.0, 3000.0, 6000.0]})
    # A: 3 of 4 instants; B: 1 of 2 (2 s and 4 s inside its span)
    assert bench.coverage(pic, grid, 1000.0, instants, spans) == pytest.approx(4 / 6)


def test_where_better_lists_the_figures_stone_soup_wins():
    ss = {"rmse_horizontal_m": 50.0, "coverage": 0.99, "peak_rss_mib": 900.0, "tracks_per_aircraft": 1.0}
    te = {"rmse_horizontal_m": 40.0, "coverage": 0.95, "peak_rss_mib": 500.0, "tracks_per_aircraft": 1.0}
    assert bench.where_better(ss, te) == {"coverage": [0.99, 0.95]}
