"""Tests for ``tertiary.io.adsb``: the real Paris ADS-B file and small hand-built frames.

Oracles: the input rows themselves (row accounting, round trip of positions to lat/lon at the
original timestamps), pymap3d for the per-fix velocity rotation, and straight/turning tracks
built from closed-form kinematics.
"""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import polars as pl
import pymap3d as pm
import pytest
from polars.testing import assert_frame_equal

from tertiary.core.geo import LocalFrame
from tertiary.io.adsb import FPM, FT, KT, AdsbCleaning, adsb_to_trajectories, clean_adsb, read_adsb
from tertiary.simulate.trajectory import SEG_CLIMB, SEG_STRAIGHT, SEG_TURN, Trajectories

# the real sample ships with the project (datasets/, and tertiary/datasets/ in the wheel)
PARIS = Path(__file__).resolve().parents[1] / "datasets" / "adsb_paris_2021-10-07.parquet"
T0 = datetime(2021, 10, 7, 12, 0, 0, tzinfo=timezone.utc)

needs_paris = pytest.mark.skipif(not PARIS.exists(), reason=f"Paris ADS-B sample not found at {PARIS} (it ships in "
                                 "the repository's datasets/ folder; restore it with `git checkout datasets/`)")


# ----------------------------------------------------------------------------- helpers


def haversine_m(lat1, lon1, lat2, lon2):
    p1, p2 = np.radians(lat1), np.radians(lat2)
    h = np.sin((p2 - p1) / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(np.radians(lon2 - lon1) / 2) ** 2
    return 2 * 6371008.8 * np.arcsin(np.sqrt(h))


def track(icao: str, n: int = 120, *, start_s: float = 0.0, speed: float = 200.0, heading: float = 90.0,
          turn_dps: float = 0.0, vz: float = 0.0, alt_ft: float = 20_000.0, lat0: float = 48.8,
          lon0: float = 2.4, callsign: str | None = "TST1") -> pl.DataFrame:
    """A flight sampled every second: exact coordinated-turn/straight kinematics in the ENU
    frame at (lat0, lon0), converted to the OpenSky schema."""
    t = np.arange(n, dtype=float)
    psi = np.radians(heading + turn_dps * t)
    if turn_dps == 0:
        e, nn = speed * t * np.sin(psi), speed * t * np.cos(psi)
    else:
        w = np.radians(turn_dps)
        psi0 = np.radians(heading)
        e = speed * (np.cos(psi0) - np.cos(psi)) / w
        nn = speed * (np.sin(psi) - np.sin(psi0)) / w
    u = alt_ft * FT + vz * t
    lat, lon, _ = LocalFrame(lat0, lon0, 0.0).to_geodetic(e, nn, u)
    return pl.DataFrame({
        "timestamp": [T0 + timedelta(seconds=start_s + s) for s in t],
        "icao24": [icao] * n,
        "callsign": [callsign] * n,
        "latitude": lat, "longitude": lon,
        "altitude": u / FT,                               # feet, as in OpenSky
        "groundspeed": np.full(n, speed / KT),
        "track": np.mod(np.degrees(psi), 360.0),
        "vertical_rate": np.full(n, vz / FPM),
        "onground": [False] * n,
        "squawk": ["1000"] * n,
    }).with_columns(pl.col("timestamp").cast(pl.Datetime("us", "UTC")))


# ----------------------------------------------------------------------------- the Paris file


@pytest.fixture(scope="module")
def raw() -> pl.DataFrame:
    return pl.read_parquet(PARIS)


@pytest.fixture(scope="module")
def cleaned(raw):
    return clean_adsb(read_adsb(PARIS))


@pytest.fixture(scope="module")
def paris(raw) -> tuple[Trajectories, pl.DataFrame]:
    return adsb_to_trajectories(raw)


@needs_paris
def test_row_accounting(raw, cleaned):
    clean, removed = cleaned
    assert clean.height + removed.height == raw.height
    # every input row, unchanged, in exactly one of the two
    both = pl.concat([clean.drop("flight"), removed.drop("reason")]).select(raw.columns)
    key = ["icao24", "timestamp"]
    assert_frame_equal(both.sort(key), raw.sort(key))
    assert removed["reason"].null_count() == 0
    assert not clean.select(pl.struct("icao24", "timestamp").is_duplicated().any()).item()
    counts = dict(removed.group_by(pl.col("reason").str.replace(r" \(.*\)$", "")).len().iter_rows())
    assert counts["on ground"] > 50_000
    assert counts["altitude out of band"] >= 3
    assert not clean["onground"].any()


@needs_paris
def test_absurd_altitude_removed_with_altitude_reason(cleaned):
    clean, removed = cleaned
    row = removed.filter(pl.col("altitude") == 123_100.0)
    assert row.height == 1
    assert row["reason"].item() == "altitude out of band (37521 m)"
    assert (clean["altitude"] * FT).max() <= 15_000.0
    assert clean["altitude"].null_count() == 0


@needs_paris
def test_altitude_spikes_and_position_jumps_on_real_data(cleaned):
    clean, removed = cleaned
    spikes = removed.filter(pl.col("reason").str.starts_with("altitude spike"))
    assert spikes.height > 20
    # 06a2b1 reports 34 000 ft for one second while descending through 13 000 ft
    one = spikes.filter((pl.col("icao24") == "06a2b1") & (pl.col("timestamp") == T0 + timedelta(minutes=25, seconds=24)))
    assert one.height == 1 and one["altitude"].item() == 34_000.0
    # 3991e0 jumps 1.5 km north for one fix at 14:54:53 (the other side hidden by a stale fix)
    jump = removed.filter((pl.col("icao24") == "3991e0")
                          & (pl.col("timestamp") == T0 + timedelta(hours=2, minutes=54, seconds=53)))
    assert jump["reason"].item().startswith("position jump (implied ")
    # what survives is consistent: vertical speed between consecutive clean fixes is plausible
    d = clean.with_columns(
        dz=(pl.col("altitude").diff().over("flight") * FT).abs(),
        dts=pl.col("timestamp").diff().over("flight").dt.total_seconds() + 1.0)
    assert (d["dz"] / d["dts"]).max() < 100.0


@needs_paris
def test_null_lat_lon_handled(raw):
    idx = [10, 5_000, 123_456]
    bad = raw.with_row_index("_i").with_columns(
        latitude=pl.when(pl.col("_i").is_in(idx[:2])).then(None).otherwise(pl.col("latitude")),
        longitude=pl.when(pl.col("_i") == idx[2]).then(None).otherwise(pl.col("longitude")),
    )
    clean, removed = clean_adsb(bad)
    assert clean.height + removed.height == raw.height
    hit = removed.filter(pl.col("_i").is_in(idx))
    assert hit.height == 3
    assert set(hit["reason"]) == {"null latitude/longitude"}
    assert clean["latitude"].null_count() == 0 and clean["longitude"].null_count() == 0


@needs_paris
def test_trajectories_shape_and_meta(paris, cleaned):
    traj, removed = paris
    clean, removed2 = cleaned
    assert_frame_equal(removed, removed2)
    n_flights = clean["flight"].n_unique()
    assert traj.n_aircraft == n_flights == clean["flight"].max() + 1
    assert traj.truth_id.tolist() == list(range(n_flights))
    assert traj.epoch == clean["timestamp"].min().replace(microsecond=0)
    assert traj.dt == 1.0
    assert traj.origin is not None and traj.origin.alt_m == 0.0
    assert 48.0 < traj.origin.lat_deg < 50.0 and 1.0 < traj.origin.lon_deg < 4.0
    # meta per flight, from the clean rows
    first = clean.group_by("flight").agg(pl.col("icao24").first()).sort("flight")
    assert traj.meta["icao24"].tolist() == first["icao24"].to_list()
    assert len(traj.meta["callsign"]) == n_flights
    # each flight is active on one contiguous block spanning its first to last fix
    span = clean.group_by("flight").agg(pl.col("timestamp").min().alias("a"), pl.col("timestamp").max().alias("b")).sort("flight")
    dur = (span["b"] - span["a"]).dt.total_seconds().to_numpy()
    assert (traj.active.sum(axis=1) == dur + 1).all()
    k = np.arange(traj.n_times)
    first_k = np.where(traj.active, k, traj.n_times).min(axis=1)
    last_k = np.where(traj.active, k, -1).max(axis=1)
    assert (last_k - first_k + 1 == traj.active.sum(axis=1)).all()
    assert np.isfinite(traj.pos[traj.active]).all() and np.isfinite(traj.vel[traj.active]).all()
    assert np.isnan(traj.pos[~traj.active]).all()
    frame = traj.to_frame(stride=60)
    assert set(frame["segment"].unique()) <= {"straight", "turn", "climb", "descent"}


@needs_paris
def test_no_active_sample_above_15_km(paris):
    traj, _ = paris
    p = traj.pos[traj.active]
    _, _, h = traj.origin.to_geodetic(p[:, 0], p[:, 1], p[:, 2])
    assert h.max() <= 15_000.0 + 1e-6
    assert h.min() >= -300.0 - 1e-6


@needs_paris
def test_positions_round_trip_to_input(paris, cleaned):
    traj, _ = paris
    clean, _ = cleaned
    t = (clean["timestamp"] - traj.epoch).dt.total_microseconds().to_numpy() / 1e6
    k = np.round(t / traj.dt).astype(int)
    assert np.allclose(k * traj.dt, t)              # 1 s stamps land on the 1 s grid
    f = clean["flight"].to_numpy()
    assert traj.active[f, k].all()
    p = traj.pos[f, k]
    lat, lon, h = traj.origin.to_geodetic(p[:, 0], p[:, 1], p[:, 2])
    horiz = haversine_m(lat, lon, clean["latitude"].to_numpy(), clean["longitude"].to_numpy())
    assert horiz.max() < 1.0
    assert np.abs(h - clean["altitude"].to_numpy() * FT).max() < 1.0


@needs_paris
def test_velocity_consistent_with_positions(paris, cleaned):
    traj, _ = paris
    # OpenSky stamps are floored to 1 s, so 1-s position differences carry up to ±1 s of
    # travel of timing noise; compare the displacement over a 10 s baseline with the
    # trapezoid integral of the velocity over the same interval.
    h = 10
    ok = np.ones_like(traj.active[:, h:])
    for j in range(h + 1):
        ok &= traj.active[:, j:traj.n_times - h + j]
    v = np.nan_to_num(traj.vel)
    trap = np.cumsum(0.5 * (v[:, 1:] + v[:, :-1]) * traj.dt, axis=1)
    trap = np.concatenate([np.zeros_like(trap[:, :1]), trap], axis=1)
    dp = (traj.pos[:, h:] - traj.pos[:, :-h]) / (h * traj.dt)
    dv = (trap[:, h:] - trap[:, :-h]) / (h * traj.dt)
    err = np.linalg.norm(dp - dv, axis=-1)[ok]
    assert err.size > 100_000
    assert np.median(err) < 5.0
    assert np.percentile(err, 95) < 15.0

    # at the fixes the velocity is the reported one, rotated per fix into the system frame
    clean, _ = cleaned
    rep = clean.filter(pl.col("track").is_not_null() & pl.col("groundspeed").is_not_null()
                       & pl.col("vertical_rate").is_not_null())
    t = (rep["timestamp"] - traj.epoch).dt.total_microseconds().to_numpy() / 1e6
    k = np.round(t / traj.dt).astype(int)
    vel = traj.vel[rep["flight"].to_numpy(), k]
    gs = rep["groundspeed"].to_numpy() * KT
    trk = np.radians(rep["track"].to_numpy())
    vu = rep["vertical_rate"].to_numpy() * FPM
    lat, lon = rep["latitude"].to_numpy(), rep["longitude"].to_numpy()
    ux, uy, uz = pm.enu2uvw(gs * np.sin(trk), gs * np.cos(trk), vu, lat, lon)
    o = traj.origin
    want = np.stack(pm.uvw2enu(ux, uy, uz, o.lat_deg, o.lon_deg), axis=-1)
    assert np.abs(vel - want).max() < 1e-6


@needs_paris
def test_flights_split_on_gaps(cleaned, paris):
    clean, _ = cleaned
    traj, _ = paris
    d = clean.with_columns(
        gap=pl.col("timestamp").diff().dt.total_seconds(fractional=True),
        same_ac=pl.col("icao24") == pl.col("icao24").shift(),
        new=pl.col("flight") != pl.col("flight").shift())
    inside = d.filter(pl.col("same_ac") & ~pl.col("new"))
    assert inside["gap"].max() <= 60.0
    # 0a0047 disappears for 7879 s: two flights, same icao24
    per_ac = clean.group_by("icao24").agg(pl.col("flight").n_unique().alias("n"))
    assert per_ac.filter(pl.col("icao24") == "0a0047")["n"].item() == 2
    assert per_ac["n"].max() >= 2
    ids = clean.filter(pl.col("icao24") == "0a0047")["flight"].unique().sort().to_list()
    assert traj.meta["icao24"][ids].tolist() == ["0a0047", "0a0047"]
    assert not (traj.active[ids[0]] & traj.active[ids[1]]).any()
    # flights are numbered in (icao24, start time) order
    order = clean.group_by("flight").agg(pl.col("icao24").first(), pl.col("timestamp").min()).sort("flight")
    assert order.sort(["icao24", "timestamp"])["flight"].to_list() == order["flight"].to_list()


# ----------------------------------------------------------------------------- hand-built frames


def test_position_jump_removed_with_reason():
    f = track("aaaaaa", 120)
    lat = f["latitude"].to_numpy().copy()
    lat[60] += 0.05                                     # 5.6 km north for one fix
    f = f.with_columns(pl.Series("latitude", lat))
    clean, removed = clean_adsb(f)
    assert removed.height == 1
    row = removed.row(0, named=True)
    assert row["timestamp"] == T0 + timedelta(seconds=60)
    assert row["reason"].startswith("position jump (implied ")
    implied = int(row["reason"].split("implied ")[1].split(" ")[0])
    assert 2_000 < implied < 3_500                      # ~5.6 km over (1 s + 1 s quantisation)
    assert clean.height == 119 and clean["flight"].unique().to_list() == [0]


def test_altitude_spike_and_short_run_removed():
    f = track("aaaaaa", 120)
    alt = f["altitude"].to_numpy().copy()
    alt[30] = 34_000.0                                   # single spike
    alt[70:73] = 5_000.0                                 # three-fix excursion
    f = f.with_columns(pl.Series("altitude", alt))
    clean, removed = clean_adsb(f)
    assert sorted((removed["timestamp"] - T0).dt.total_seconds().to_list()) == [30, 70, 71, 72]
    assert all(r.startswith("altitude spike (implied ") for r in removed["reason"])
    assert clean["flight"].n_unique() == 1


def test_duplicate_timestamps():
    f = track("bbbbbb", 90)
    dup = f.slice(10, 2).with_columns(pl.col("callsign").str.replace("TST1", "DUP"))
    g = pl.concat([f, dup])                              # unsorted on purpose
    clean, removed = clean_adsb(g)
    assert clean.height == 90 and removed.height == 2
    assert set(removed["reason"]) == {"duplicate timestamp"}
    assert set(removed["callsign"]) == {"DUP"}           # the first occurrence is kept
    assert clean["timestamp"].is_sorted()


def test_stale_onground_and_band_rules():
    f = track("cccccc", 100)
    lat, lon = f["latitude"].to_numpy().copy(), f["longitude"].to_numpy().copy()
    lat[41], lon[41] = lat[40], lon[40]                  # re-stamped old position
    onground = np.zeros(100, dtype=bool)
    onground[80:] = True
    gs = f["groundspeed"].to_numpy().copy()
    gs[5] = 900.0                                        # 463 m/s
    f = f.with_columns(pl.Series("latitude", lat), pl.Series("longitude", lon),
                       pl.Series("onground", onground), pl.Series("groundspeed", gs))
    clean, removed = clean_adsb(f)
    reasons = dict(zip(removed["timestamp"].dt.second().to_list(), removed["reason"].to_list()))
    assert reasons[41] == "stale position (repeated latitude/longitude)"
    assert reasons[5] == "groundspeed out of band (463 m/s)"
    assert sum(r == "on ground" for r in reasons.values()) == 20
    keep, _ = clean_adsb(f, AdsbCleaning(drop_onground=False, drop_stale=False, max_groundspeed_mps=500))
    assert keep.height == 100


def test_gap_splits_and_short_flights():
    f = pl.concat([track("dddddd", 100),
                   track("dddddd", 100, start_s=200),     # 101 s gap -> second flight
                   track("dddddd", 30, start_s=400),      # 30 s flight -> dropped
                   track("eeeeee", 70, callsign=None)])
    clean, removed = clean_adsb(f)
    assert set(removed["reason"]) == {"flight shorter than 60 s"} and removed.height == 30
    assert clean.group_by("icao24").agg(pl.col("flight").n_unique()).sort("icao24")["flight"].to_list() == [2, 1]
    traj, _ = adsb_to_trajectories(f)
    assert traj.n_aircraft == 3
    assert traj.meta["icao24"].tolist() == ["dddddd", "dddddd", "eeeeee"]
    assert traj.meta["callsign"].tolist() == ["TST1", "TST1", None]
    assert traj.active.sum(axis=1).tolist() == [100, 100, 70]
    assert not traj.active[0, 100:200].any()


def test_missing_column_error_names_it():
    f = track("ffffff", 10).drop("latitude", "altitude")
    with pytest.raises(ValueError, match=r"latitude, altitude"):
        clean_adsb(f)
    # optional columns may be absent: velocity then comes from the positions
    g = track("ffffff", 80, speed=150.0, heading=30.0).drop("groundspeed", "track", "vertical_rate", "onground",
                                                           "squawk", "callsign")
    traj, removed = adsb_to_trajectories(g, origin=LocalFrame(48.8, 2.4, 0.0))
    assert removed.height == 0
    v = traj.vel[0, traj.active[0]]
    assert np.allclose(np.linalg.norm(v, axis=-1), 150.0, rtol=1e-3)


def test_csv_input(tmp_path):
    f = pl.concat([track("344487", 90), track("0101de", 90, heading=200.0)])   # numeric-looking icao24
    csv, pq = tmp_path / "a.csv", tmp_path / "a.parquet"
    f.write_csv(csv)
    f.write_parquet(pq)
    a, b = read_adsb(csv), read_adsb(pq)
    assert a.schema["timestamp"] == pl.Datetime("us", "UTC")
    assert a.schema["icao24"] == pl.String and a.schema["squawk"] == pl.String
    assert set(a["icao24"]) == {"344487", "0101de"}
    ca, ra = clean_adsb(a)
    cb, rb = clean_adsb(b)
    assert_frame_equal(ca, cb, check_exact=False, rel_tol=1e-12)
    assert ra.height == rb.height == 0
    traj, _ = adsb_to_trajectories(a)
    assert traj.n_aircraft == 2


def test_resampling_kinematics_and_segments():
    origin = LocalFrame(48.8, 2.4, 0.0)
    f = pl.concat([track("a00001", 180, speed=150.0, heading=0.0),
                   track("a00002", 180, speed=120.0, heading=90.0, turn_dps=3.0),
                   track("a00003", 180, speed=140.0, heading=270.0, vz=10.0, alt_ft=5_000.0)])
    # a 0.5 s grid starting 1 s early: half-second samples interpolate linearly between fixes
    traj, _ = adsb_to_trajectories(f, origin, AdsbCleaning(dt=0.5), epoch=T0 - timedelta(seconds=1))
    assert traj.epoch == T0 - timedelta(seconds=1)
    k = np.flatnonzero(traj.active[0])
    assert k[0] == 2 and k.size == 2 * 179 + 1
    # straight flight: system-frame speed equals the reported one everywhere
    assert np.allclose(np.linalg.norm(traj.vel[0, k], axis=-1), 150.0, atol=1e-6)
    mid = traj.pos[0, k[1:-1:2]]                        # half-second points
    ends = 0.5 * (traj.pos[0, k[0:-2:2]] + traj.pos[0, k[2::2]])
    assert np.abs(mid - ends).max() < 1e-6
    seg = [np.bincount(traj.segment[a, traj.active[a]], minlength=5) for a in range(3)]
    assert seg[0].argmax() == SEG_STRAIGHT and seg[0][SEG_TURN] == 0
    assert seg[1].argmax() == SEG_TURN
    assert seg[2].argmax() == SEG_CLIMB
