"""STCA final-approach volumes: pairs established on one final are decided with the
reduced in-trail minimum and a shorter look-ahead; every other pair, seed mode and the scoring
keep the configured parameters; the pipeline takes the volumes from the scenario's runways."""

from __future__ import annotations

import dataclasses
from datetime import datetime, timezone

import numpy as np
import polars as pl
import pytest

from safety.conflicts import NM_M, ApproachVolume, ConflictConfig, approach_membership, predict_conflicts
from tertiary.pipeline import PipelineConfig, adapt_to_scenario

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
FIXED = ConflictConfig(threshold_mode="fixed")          # R_thr = 5 556 + 500 + 300 = 6 356 m
FINAL = ApproachVolume(1500.0, 0.0, 270.0, length_m=38_500.0)   # runway 27: arrivals fly west
H = 914.0                                                # 3 000 ft


def _picture(pos, vel) -> pl.DataFrame:
    pos, vel = np.asarray(pos, float), np.asarray(vel, float)
    n = len(pos)
    return pl.DataFrame({
        "run": np.zeros(n, np.uint32), "epoch": [T0] * n, "track_id": np.arange(1, n + 1, dtype=np.uint64),
        "x_m": pos[:, 0], "y_m": pos[:, 1], "z_m": pos[:, 2], "vx_mps": vel[:, 0], "vy_mps": vel[:, 1],
        "vz_mps": vel[:, 2], "alt_m": pos[:, 2], "alt_rate_mps": vel[:, 2],
    }).with_columns(pl.col("epoch").cast(pl.Datetime("us", "UTC")))


def _alert(df: pl.DataFrame, cfg: ConflictConfig) -> bool:
    out = predict_conflicts(df, cfg)
    return bool(out["alert"].any()) if out.height else False


def test_volume_membership_geometry():
    pos = np.array([[12_000.0, 0.0, H],        # on the centreline, 10.5 km to go, flying the course
                    [12_000.0, 1_500.0, H],    # 1.5 km off the centreline
                    [12_000.0, 0.0, H],        # flying the reciprocal (a departure's direction)
                    [-3_000.0, 0.0, 200.0],    # past the threshold
                    [45_000.0, 0.0, H],        # beyond the volume's length
                    [12_000.0, 0.0, 2_500.0],  # above the ceiling
                    [12_000.0, 0.0, H]])       # 20° off the course
    c20 = np.radians(20.0)
    vel = np.array([[-100.0, 0, 0], [-100.0, 0, 0], [100.0, 0, 0], [-100.0, 0, 0], [-100.0, 0, 0],
                    [-100.0, 0, 0], [-100.0 * np.cos(c20), 100.0 * np.sin(c20), 0]])
    assert FINAL.contains(pos, vel).tolist() == [True, False, False, False, False, False, False]
    cfg = dataclasses.replace(FIXED, approach_volumes=(FINAL,))
    assert approach_membership(_picture(pos, vel), cfg).tolist() == [0, -1, -1, -1, -1, -1, -1]
    assert (approach_membership(_picture(pos, vel), dataclasses.replace(cfg, mode="seed")) == -1).all()


def test_in_trail_compression_on_final_does_not_alert_in_the_volume():
    """A follower 9 km behind its leader at 3 000 ft, 33 m/s faster (the leader has slowed first
    on the speed schedule): 5.5 km at 105 s under the 6.4 km threshold → an alert with the general
    parameters; with the final's (2.5 NM, 60 s) it is 7.0 km at 60 s, above 5.4 km → none."""
    df = _picture([[12_000.0, 0.0, H], [21_000.0, 0.0, H]], [[-97.0, 0, 0], [-130.0, 0, 0]])
    assert _alert(df, FIXED)
    cfg = dataclasses.replace(FIXED, approach_volumes=(FINAL,))
    assert not _alert(df, cfg)
    # seed mode keeps its rule whatever the volumes: 6 km closing at 60 m/s, T_min = 100 s ≤ 105 s
    seed = dataclasses.replace(FIXED, mode="seed")
    fast = _picture([[12_000.0, 0.0, H], [18_000.0, 0.0, H]], [[-70.0, 0, 0], [-130.0, 0, 0]])
    assert _alert(fast, seed)
    assert predict_conflicts(fast, seed).equals(predict_conflicts(fast, dataclasses.replace(seed, approach_volumes=(FINAL,))))


def test_real_overtake_on_final_still_alerts_with_the_volume_parameters():
    """6.5 km behind and 40 m/s faster: 4.1 km at 60 s, inside the final's 5.43 km threshold."""
    df = _picture([[12_000.0, 0.0, H], [18_500.0, 0.0, H]], [[-90.0, 0, 0], [-130.0, 0, 0]])
    cfg = dataclasses.replace(FIXED, approach_volumes=(FINAL,))
    out = predict_conflicts(df, cfg)
    assert out["alert"][0]
    r_thr = 2.5 * NM_M + cfg.pilot_h_m + cfg.fixed_est_h_m
    assert out["r_thr_m"][0] == pytest.approx(r_thr) and out["t_thr_s"][0] == pytest.approx(60.0)
    assert out["t_in_s"][0] == pytest.approx((6_500.0 - r_thr) / 40.0)


def test_pair_with_one_member_off_the_final_keeps_the_general_parameters():
    """An aircraft crossing the final northbound meets an arrival at t = 100 s (collision
    course): with the final's 60 s look-ahead it would not alert yet, with the general 105 s it
    does — and it must, as only one of the two is established on the final."""
    df = _picture([[12_000.0, 0.0, H], [2_300.0, -10_000.0, H]], [[-97.0, 0, 0], [0.0, 100.0, 0]])
    cfg = dataclasses.replace(FIXED, approach_volumes=(FINAL,))
    assert approach_membership(df, cfg).tolist() == [0, -1]
    out = predict_conflicts(df, cfg)
    assert out["alert"][0] and out["t_thr_s"][0] == pytest.approx(105.0)
    # were both on the final's parameters, it would not alert within 60 s
    assert not _alert(df, FINAL.parameters(FIXED))


def test_parallel_finals_pair_within_each_volume_and_across_them_once_with_the_general_parameters():
    """Two parallel finals 1.5 km apart with equal parameters (predicted in one call): each
    final's in-trail pair is decided with the volume's parameters, and a pair of two arrivals on
    different finals — side by side, 1.5 km apart — once, with the general parameters."""
    north = dataclasses.replace(FINAL, threshold_y_m=1_500.0, name="27L")
    cfg = dataclasses.replace(FIXED, approach_volumes=(FINAL, north))
    df = _picture([[12_000.0, 0.0, H], [18_500.0, 0.0, H], [12_000.0, 1_500.0, H], [18_500.0, 1_500.0, H]],
                  [[-90.0, 0, 0], [-130.0, 0, 0], [-90.0, 0, 0], [-130.0, 0, 0]])
    assert approach_membership(df, cfg).tolist() == [0, 0, 1, 1]
    out = predict_conflicts(df, cfg)
    pairs = list(zip(out["id_a"].to_list(), out["id_b"].to_list()))
    assert len(pairs) == len(set(pairs))
    t_thr = dict(zip(pairs, out["t_thr_s"].to_list()))
    assert t_thr[(1, 2)] == pytest.approx(60.0) and t_thr[(3, 4)] == pytest.approx(60.0)
    assert t_thr[(1, 3)] == pytest.approx(105.0) and t_thr[(2, 4)] == pytest.approx(105.0)
    assert out.sort("id_a", "id_b").equals(out)


def test_volume_validation():
    with pytest.raises(ValueError, match="positive"):
        ApproachVolume(0.0, 0.0, 270.0, t_thr_s=0.0)
    with pytest.raises(ValueError, match="track_tolerance_deg"):
        ApproachVolume(0.0, 0.0, 270.0, track_tolerance_deg=95.0)
    with pytest.raises(ValueError, match="ApproachVolume"):
        ConflictConfig(approach_volumes=((0.0, 0.0, 270.0),))      # type: ignore[arg-type]


def test_pipeline_takes_the_volumes_from_the_scenario(small_terminal):
    """terminal-area: one final, runway 27; its arrivals established on the final (truth) are in
    it — the volume is in the system frame the pictures use; off, or configured, it is left alone."""
    ds = small_terminal
    cfg = adapt_to_scenario(PipelineConfig(), ds)
    (vol,) = cfg.conflicts.approach_volumes
    assert (vol.threshold_x_m, vol.threshold_y_m, vol.course_deg) == (1500.0, 0.0, 270.0)
    tr = ds.truth
    arr = tr.filter(pl.col("role") == "arrival")
    pos = arr.select("x_m", "y_m", "alt_m").to_numpy()
    vel = arr.select("vx_mps", "vy_mps", "alt_rate_mps").to_numpy()
    to_go = pos[:, 0] - 1500.0
    on_final = (np.abs(pos[:, 1]) < 200.0) & (to_go > 1_000.0) & (to_go < 35_000.0)
    assert on_final.sum() > 100 and vol.contains(pos[on_final], vel[on_final]).all()
    others = tr.filter(pl.col("role") != "arrival")
    assert not vol.contains(others.select("x_m", "y_m", "alt_m").to_numpy(),
                            others.select("vx_mps", "vy_mps", "alt_rate_mps").to_numpy()).any()
    assert adapt_to_scenario(PipelineConfig(stca_approach_volumes=False), ds).conflicts.approach_volumes == ()
    mine = ApproachVolume(0.0, 0.0, 90.0)
    own = PipelineConfig(conflicts=dataclasses.replace(PipelineConfig().conflicts, approach_volumes=(mine,)))
    assert adapt_to_scenario(own, ds).conflicts.approach_volumes == (mine,)


def test_national_scenario_has_both_runway_ends_of_every_airport():
    from tertiary.core.geo import LocalFrame
    from tertiary.simulate import load_scenario
    from tertiary.simulate.traffic import final_approaches
    sc = load_scenario("national")
    frame = LocalFrame(*sc.origin)
    fa = final_approaches(sc, frame)
    assert len(fa) == 2 * len(sc.national.airports)
    for (x0, y0, c0, _), (x1, y1, c1, _), ap in zip(fa[::2], fa[1::2], sc.national.airports):
        assert (x0, y0) == (x1, y1) and (c1 - c0) % 360.0 == pytest.approx(180.0)
        e, n, _ = frame.from_geodetic(np.array([ap.lat_deg]), np.array([ap.lon_deg]), 0.0)
        assert (x0, y0) == pytest.approx((float(e[0]), float(n[0])), abs=1e-6)
    assert final_approaches(load_scenario("big-box")) == [] and final_approaches(load_scenario("adsb-paris")) == []
