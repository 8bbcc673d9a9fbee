"""Scenarios and radar simulation."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings, strategies as st

from tertiary.core import geo
from tertiary.core.errors import DataError
from tertiary.io.dataset import read_dataset, write_dataset
from tertiary.simulate import load_scenario, simulate
from tertiary.simulate.config import (Anomalies, RadarConfig, scenario_toml, from_dict, ScenarioConfig, with_radar_count)
from tertiary.simulate.traffic import big_box, BIG_BOX_SPEED
from tertiary.simulate.traffic.terminal import pair_counts, terminal_traffic
from tertiary.simulate.trajectory import SEG_TURN

import tomllib
from pathlib import Path

from tertiary.pipeline import ingest


# --------------------------------------------------------------------------- big box geometry

def test_big_box_geometry():
    traj = big_box()
    assert traj.duration == 852.0
    assert traj.path_length()[0] == pytest.approx(71_000.0, abs=1.0)
    np.testing.assert_allclose(traj.pos[0, :, 2], 500.0)                       # constant 500 m
    np.testing.assert_allclose(np.linalg.norm(traj.vel[0], axis=1), BIG_BOX_SPEED, rtol=1e-12)
    np.testing.assert_allclose(traj.pos[0, 0], [4000.0, -12000.0, 500.0])
    np.testing.assert_allclose(traj.pos[0, -1], [4000.0, -7000.0, 500.0], atol=1e-6)
    assert traj.vel[0, 0, 1] == pytest.approx(BIG_BOX_SPEED)                  # heading north


def test_big_box_turn_radius_and_legs():
    traj = big_box()
    turn = traj.segment[0] == SEG_TURN
    assert turn.sum() == 4 * 30                                               # four 30 s turns
    # radius from curvature |v|^2 / |a| with a from the exact heading change
    hdg = np.unwrap(np.arctan2(traj.vel[0, :, 0], traj.vel[0, :, 1]))
    rate = np.diff(hdg)[turn[:-1]]
    np.testing.assert_allclose(np.degrees(rate), -3.0, rtol=1e-9)             # left turns, 3 deg/s
    assert BIG_BOX_SPEED / np.radians(3.0) == pytest.approx(1591.55, abs=0.01)
    # the truth moves on circles of that radius during turns (Hermite mid-points included)
    t = np.arange(180.0, 210.0, 0.25)
    pos, _, ok = traj.state_at(np.zeros_like(t, int), t)
    centre = np.array([4000.0 - 1591.549430918954, 3000.0])
    np.testing.assert_allclose(np.linalg.norm(pos[:, :2] - centre, axis=1), 1591.549430918954, atol=0.01)
    assert ok.all()


def test_big_box_dataset(big_box_runs):
    ds = big_box_runs
    assert ds.radars.height == 2
    sites = geo.LocalFrame(*ds.scenario.origin).from_geodetic(ds.radars["lat_deg"], ds.radars["lon_deg"], ds.radars["alt_m"])
    np.testing.assert_allclose(np.column_stack(sites), [[0, 0, 0], [-8000, -6000, 0]], atol=1e-6)
    r = ds.reports
    assert r["run"].n_unique() == 5
    assert r.height == 5 * 2 * 852                     # τ = 1 s, Pd = 1: one report per scan
    times = r.filter((pl.col("run") == 0) & (pl.col("radar_id") == 1))["time"].sort()   # rows are in track order
    assert (times.diff().drop_nulls().dt.total_microseconds() == 1_000_000).all()   # synchronous
    # range noise: sigma 50 m
    truth = ds.truth.select("time", "x_m", "y_m", "z_m")
    j = r.filter(pl.col("radar_id") == 1).join(truth, on="time", suffix="_t")
    true_rng = np.linalg.norm(j.select("x_m_t", "y_m_t", "z_m_t").to_numpy(), axis=1)
    assert np.std(j["range_m"].to_numpy() - true_rng) == pytest.approx(50.0, rel=0.05)


# --------------------------------------------------------------------------- terminal area

def test_terminal_area_content(small_terminal):
    ds = small_terminal
    r, truth, radars = ds.reports, ds.truth, ds.radars
    assert radars.height == 4
    assert sorted(radars["scan_period_s"].to_list()) == [4.0, 5.0, 8.0, 12.0]
    assert set(truth["segment"].unique()) >= {"straight", "turn", "climb", "descent", "hold"}
    # clutter reports exist and carry no truth
    assert r["truth_id"].null_count() > 0
    # Pd < 1: fewer reports than scans × visible aircraft
    per = r.filter(pl.col("truth_id").is_not_null()).group_by("radar_id").len().sort("radar_id")
    assert per.height == 4
    # designed conflict pairs lose 3 NM / 1000 ft at their meeting time
    role = truth["truth_id"].unique().sort()
    assert len(role) == 30


def test_rotating_antenna_timing(small_terminal):
    """A report's time within the scan follows the azimuth of the beam (clock offset aside)."""
    ds = small_terminal
    radars = ds.radars
    r = ds.reports.filter(pl.col("truth_id").is_not_null()).join(radars, on="radar_id")
    t = r["time"].dt.epoch("us").to_numpy() * 1e-6 - ds.reports["time"].dt.epoch("us").min() * 1e-6
    t0 = ds.reports.filter(pl.col("truth_id").is_not_null())["time"].dt.epoch("us").min() * 1e-6
    epoch = ds.truth["time"].dt.epoch("us").min() * 1e-6
    t = r["time"].dt.epoch("us").to_numpy() * 1e-6 - epoch - r["time_offset_s"].to_numpy()
    frac = np.mod(t - r["scan_phase_s"].to_numpy(), r["scan_period_s"].to_numpy()) / r["scan_period_s"].to_numpy()
    az = r["azimuth_deg"].to_numpy() / 360.0
    d = np.abs(np.mod(frac - az + 0.5, 1.0) - 0.5)
    assert np.quantile(d, 0.99) < 0.002        # azimuth noise + movement only


def test_coverage_and_radar_scaling():
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20),
                              radars=tuple(dataclasses.replace(r, max_range_m=40_000.0, clutter_rate=0.0) for r in cfg.radars))
    ds = simulate(cfg)
    assert ds.reports["range_m"].max() < 40_000.0 + 5 * 70.0
    assert len(with_radar_count(cfg, 7).radars) == 7
    assert len(with_radar_count(cfg, 2).radars) == 2
    periods = [r.scan_period_s for r in with_radar_count(cfg, 7).radars]
    assert min(periods) >= 4.0 and max(periods) <= 12.0


def test_same_seed_identical_and_files_roundtrip(tmp_path):
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=120.0, traffic=dataclasses.replace(cfg.traffic, aircraft=10))
    a, b = simulate(cfg), simulate(cfg)
    assert a.reports.equals(b.reports) and a.truth.equals(b.truth)
    c = simulate(cfg.replace(seed=cfg.seed + 1))
    assert not a.reports.equals(c.reports)
    d1, d2 = write_dataset(a, tmp_path / "a"), write_dataset(b, tmp_path / "b")
    for name in ("radars.parquet", "reports.parquet", "truth.parquet", "scenario.toml"):
        assert (d1 / name).read_bytes() == (d2 / name).read_bytes(), name
    back = read_dataset(d1)
    assert back.reports.equals(a.reports)
    assert back.scenario == a.scenario


def test_scenario_toml_roundtrip():
    for name in ("big-box", "terminal-area", "adsb-paris"):
        cfg = load_scenario(name)
        assert from_dict(ScenarioConfig, tomllib.loads(scenario_toml(cfg))) == cfg


def test_unknown_scenario_key_is_an_error(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('name = "x"\nkind = "big-box"\nspeed = 3\n')
    with pytest.raises(DataError, match=r"bad.toml: ScenarioConfig: unknown key\(s\) speed"):
        load_scenario(p)


# --------------------------------------------------------------------------- anomalies

def _box(**anom) -> "Dataset":
    cfg = load_scenario("big-box").replace(runs=3)
    return simulate(dataclasses.replace(cfg, anomalies=Anomalies(**anom)))


def _range_err(ds, radar_id=1):
    truth = ds.truth.select("time", "x_m", "y_m", "z_m")
    j = ds.reports.filter(pl.col("radar_id") == radar_id).join(truth, on="time", suffix="_t")
    site = np.array([[0, 0, 0], [-8000, -6000, 0]])[radar_id - 1]
    t = (j["time"].dt.epoch("us").to_numpy() - j["time"].dt.epoch("us").min()) * 1e-6
    return t, j["range_m"].to_numpy() - np.linalg.norm(j.select("x_m_t", "y_m_t", "z_m_t").to_numpy() - site, axis=1)


def test_noise_inflation_window():
    ds = _box(noise_factor=6.0, noise_window_s=(300.0, 500.0), radars=("RLS1",))
    t, e = _range_err(ds, 1)
    inside = (t >= 300) & (t <= 500)
    assert np.std(e[inside]) == pytest.approx(300.0, rel=0.1)
    assert np.std(e[~inside]) == pytest.approx(50.0, rel=0.1)
    _, e2 = _range_err(ds, 2)
    assert np.std(e2) == pytest.approx(50.0, rel=0.1)      # other radar untouched


def test_dropout_outliers_bias_step():
    ds = _box(dropout_radar="RLS2", dropout_window_s=(100.0, 200.0))
    t, _ = _range_err(ds, 2)
    assert not ((t >= 100.5) & (t <= 199.5)).any()
    ds = _box(outlier_fraction=0.05)
    _, e = _range_err(ds, 1)
    frac = np.mean(np.abs(e) > 6 * 50.0)
    # gross errors N(0, (20·50 m)²) exceed 300 m with probability 2·(1 − Φ(0.3)) = 0.764
    assert frac == pytest.approx(0.05 * 0.764, abs=0.012)
    ds = _box(bias_step_time_s=400.0, bias_step_range_m=500.0, radars=("RLS1",))
    t, e = _range_err(ds, 1)
    assert np.mean(e[t > 400]) == pytest.approx(500.0, abs=10.0)
    assert np.mean(e[t < 400]) == pytest.approx(0.0, abs=10.0)


# --------------------------------------------------------------------------- radar secondary processing

def test_radar_track_estimates_consistent(big_box_runs):
    """Each radar's Singer channels: normalised range innovations ~ N(0, 1) and the Cartesian
    estimate's position NEES below its χ²(3) 99 % bound on average."""
    ds = big_box_runs
    r = ds.reports.filter(pl.col("res_range_m").is_not_nan())
    w = (r["res_range_m"] / r["res_range_var_m2"].sqrt()).to_numpy()
    assert np.std(w) == pytest.approx(1.0, abs=0.05)
    assert abs(np.mean(w)) < 0.1
    truth = ds.truth.select("time", "x_m", "y_m", "z_m")
    origin = geo.LocalFrame(*ds.scenario.origin)
    for rid in (1, 2):
        g = ds.reports.filter(pl.col("radar_id") == rid).join(truth, on="time", suffix="_t")
        rad = ds.radars.filter(pl.col("radar_id") == rid)
        site = geo.LocalFrame(rad["lat_deg"][0], rad["lon_deg"][0], rad["alt_m"][0])
        p, _, c = geo.frame_to_frame(g.select("x_m", "y_m", "z_m").to_numpy(), site, origin,
                                     cov=g["est_cov"].to_numpy().reshape(-1, 6, 6)[:, :3, :3])
        e = (p - g.select("x_m_t", "y_m_t", "z_m_t").to_numpy())[g["time"].dt.epoch("s") - g["time"].dt.epoch("s").min() > 20]
        c = c[(g["time"].dt.epoch("s") - g["time"].dt.epoch("s").min() > 20).to_numpy()]
        nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)
        assert 1.0 < nees.mean() < 4.5
        assert np.sqrt((e[:, :2] ** 2).sum(1).mean()) < 60.0


def test_local_track_ids_restart_after_long_gap():
    from tertiary.simulate import RadarTrackerConfig
    cfg = load_scenario("big-box").replace(runs=1)
    cfg = dataclasses.replace(cfg, anomalies=Anomalies(dropout_radar="RLS1", dropout_window_s=(100.0, 120.0)))
    ideal = simulate(dataclasses.replace(cfg, radar_tracker=RadarTrackerConfig(ideal=True)))
    ids = ideal.reports.filter(pl.col("radar_id") == 1)["local_track_id"].unique().sort().to_list()
    assert ids == [1, 2]
    # the radar's own tracker deletes the track in the 20 s silence: while its number is held
    # the aircraft comes back under a new one; once free (10 scans) the number is reused
    for hold, same in ((100, False), (10, True)):
        ds = simulate(dataclasses.replace(cfg, radar_tracker=RadarTrackerConfig(reuse_after_scans=hold)))
        r = ds.reports.filter(pl.col("radar_id") == 1)
        t = (r["time"].dt.epoch("us") - r["time"].dt.epoch("us").min()).to_numpy() * 1e-6
        before, after = r.filter(pl.Series(t < 100.0)), r.filter(pl.Series(t > 121.0))
        assert before["local_track_id"].mode().to_list() == [1]
        assert (after["local_track_id"].mode().to_list() == [1]) is same


def test_transponder_replies_not_copied_from_truth():
    """Mode S on a configurable fraction of aircraft and missing on some replies; Mode 3/A
    codes with duplicates and changes; callsigns ride on Mode S replies only."""
    from tertiary.simulate import TransponderConfig
    cfg = load_scenario("terminal-area")
    tx = TransponderConfig(mode_s_fraction=0.5, mode_s_missing_rate=0.05, duplicate_code_fraction=0.3,
                           code_change_fraction=0.5)
    cfg = dataclasses.replace(cfg, duration_s=900.0, traffic=dataclasses.replace(cfg.traffic, aircraft=60, conflict_pairs=3),
                              transponders=tx)
    r = simulate(cfg).reports.filter(pl.col("truth_id").is_not_null())
    per = r.group_by("truth_id").agg(pl.col("mode_s").drop_nulls().n_unique().alias("addr"),
                                     pl.col("mode_s").null_count().alias("none"), pl.len().alias("n"),
                                     pl.col("mode_3a").drop_nulls().n_unique().alias("codes"),
                                     pl.col("mode_3a").drop_nulls().first().alias("code"))
    with_s = per.filter(pl.col("addr") == 1)
    assert (per["addr"] <= 1).all() and 0.3 < with_s.height / per.height < 0.7
    missing = with_s["none"].sum() / with_s["n"].sum()
    assert missing == pytest.approx(0.05, abs=0.015)
    assert per.filter(pl.col("codes") == 2).height >= 5     # changes (at a time of the scenario, seen if flying)
    assert per["code"].n_unique() < per.height                                  # duplicate codes
    assert r.filter(pl.col("mode_s").is_null())["callsign"].null_count() == r.filter(pl.col("mode_s").is_null()).height


# the real sample ships with the project (datasets/, and tertiary/datasets/ in the wheel)
PARIS = Path(__file__).resolve().parents[1] / "datasets" / "adsb_paris_2021-10-07.parquet"
PARIS_MISSING = (f"Paris ADS-B sample not found at {PARIS} (it ships in the repository's datasets/ folder; "
                 "restore it with `git checkout datasets/`)")


@pytest.mark.skipif(not PARIS.exists(), reason=PARIS_MISSING)
def test_adsb_paris_preset_observed_by_radars():
    cfg = load_scenario("adsb-paris")
    cfg = dataclasses.replace(cfg, duration_s=600.0, adsb=dataclasses.replace(cfg.adsb, truth_file=str(PARIS)))
    ds = simulate(cfg)
    assert ds.removed.height > 0 and "reason" in ds.removed.columns
    assert ds.truth["truth_id"].n_unique() > 10
    assert ds.truth["z_m"].max() < 15_000.0
    ing = ingest(ds)
    assert ing.rejects.height == 0
    assert ing.reports.filter(pl.col("mode_s").is_not_null()).height > 0.9 * ing.reports["truth_id"].count()


@pytest.mark.skipif(not PARIS.exists(), reason=PARIS_MISSING)
def test_adsb_generic_places_radars_around_traffic():
    cfg = load_scenario("adsb")
    cfg = dataclasses.replace(cfg, duration_s=300.0, adsb=dataclasses.replace(cfg.adsb, truth_file=str(PARIS)))
    ds = simulate(cfg)
    assert len(ds.scenario.radars) == 4 and ds.scenario.origin is not None
    lat0, lon0, _ = ds.scenario.origin
    assert 48.0 < lat0 < 49.8 and 1.5 < lon0 < 3.5
    assert ds.reports.height > 1000


def test_every_shipped_scenario_passes_its_own_checks():
    """check_scenario runs before every simulation: it must accept what the package ships (the
    generic adsb scenario needs --truth, and says so)."""
    from tertiary.core.errors import OptionError
    from tertiary.simulate import builtin_scenarios
    from tertiary.simulate.config import check_scenario
    for name in builtin_scenarios():
        cfg = load_scenario(name)
        if name == "adsb":
            with pytest.raises(OptionError, match=r"adsb.truth_file \(--truth\)"):
                check_scenario(cfg)
        else:
            assert check_scenario(cfg) is cfg


@settings(max_examples=60, deadline=None)
@given(duration=st.floats(120.0, 4000.0), aircraft=st.integers(0, 300), conflicts=st.integers(0, 30),
       near=st.integers(0, 30), seed=st.integers(0, 2**31))
def test_designed_pairs_fit_any_duration_and_fleet(duration, aircraft, conflicts, near, seed):
    """A short or small terminal area gets the designed pairs that fit (never a "do not fit"
    error), exactly as many as :func:`pair_counts` promises, and every requested aircraft."""
    cfg = load_scenario("terminal-area")
    tc = dataclasses.replace(cfg.traffic, aircraft=aircraft, conflict_pairs=conflicts, near_miss_pairs=near)
    tr = terminal_traffic(tc, duration, cfg.dt, np.random.default_rng(seed))
    roles = tr.meta["role"]
    placed = (sum(r.startswith("conflict-") for r in roles) // 2, sum(r == "near-miss" for r in roles) // 2)
    assert placed == pair_counts(conflicts, near, aircraft, duration)
    assert len(roles) == aircraft


def test_default_terminal_area_keeps_every_designed_pair():
    cfg = load_scenario("terminal-area")
    assert pair_counts(cfg.traffic.conflict_pairs, cfg.traffic.near_miss_pairs, cfg.traffic.aircraft,
                       cfg.duration_s) == (cfg.traffic.conflict_pairs, cfg.traffic.near_miss_pairs)
    assert pair_counts(10, 5, 200, 600.0) == (10, 2)         # near misses give way first
