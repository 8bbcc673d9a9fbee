"""Aerodrome zones: between two aircraft both in one aerodrome's zone (within its radius and below
its ceiling) the tower separates departures and arrivals, so the STCA does not predict the pair
and the truth's scoring counts no loss of separation; a pair with one member outside is treated
as anywhere else. The national scenario's airports are its zones."""

from __future__ import annotations

import dataclasses
from datetime import timedelta

import numpy as np
import polars as pl
import pytest

from safety.alerts import AlertConfig, loss_of_separation
from safety.conflicts import FT_M, NM_M, AerodromeZone, ConflictConfig, predict_conflicts, zone_index
from tertiary.pipeline import PipelineConfig, adapt_to_scenario, note_minima

from test_approach_volumes import T0, _picture     # one track table for the STCA's airspace tests

FIXED = ConflictConfig(threshold_mode="fixed")
ZONE = AerodromeZone(0.0, 0.0, name="LFXX")            # 4 NM (7 408 m), 2 000 ft (609.6 m)
ZONED = dataclasses.replace(FIXED, aerodrome_zones=(AerodromeZone(300e3, 0.0, name="far"), ZONE))


def _departure_and_arrival(h_arrival: float, x_arrival: float = 5_000.0) -> pl.DataFrame:
    """A departure lifting off at the aerodrome reference point (10 m, climbing at 8 m/s, 80 m/s
    east) and an arrival ``x_arrival`` further east at ``h_arrival``, flying west at 70 m/s and
    descending on a 3° path: 2.7 NM and a few hundred feet apart, closing at 150 m/s."""
    return _picture([[0.0, 0.0, 10.0], [x_arrival, 0.0, h_arrival]],
                    [[80.0, 0.0, 8.0], [-70.0, 0.0, -70.0 * np.tan(np.radians(3.0))]])


def test_zone_geometry_and_index():
    pos = np.array([[0.0, 0.0, 10.0], [7_000.0, 2_000.0, 500.0], [7_408.0 + 1.0, 0.0, 100.0],
                    [100.0, 0.0, 2_000 * FT_M + 1.0], [300e3, 1e3, 0.0]])
    assert ZONE.contains(pos).tolist() == [True, True, False, False, False]
    assert zone_index(pos, ZONED.aerodrome_zones).tolist() == [1, 1, -1, -1, 0]
    assert zone_index(pos, ()).tolist() == [-1] * 5


def test_a_departure_and_an_arrival_in_one_zone_are_not_predicted():
    """Both in the zone: no conflict row with the zone, an alert without it. The same pair with
    the arrival above the ceiling (1 000 ft apart is not the case here: a descending arrival
    300 ft above the ceiling, a departure 700 ft below it — within 1 000 ft) is predicted: one
    member outside the zone."""
    both = _departure_and_arrival(260.0)
    assert predict_conflicts(both, FIXED)["alert"].to_list() == [True]
    assert predict_conflicts(both, ZONED).height == 0
    above = _departure_and_arrival(2_000 * FT_M + 300 * FT_M)
    plain = predict_conflicts(above, FIXED)
    assert plain["alert"].to_list() == [True]
    assert predict_conflicts(above, ZONED).equals(plain)


def test_pairs_outside_every_zone_are_unchanged():
    """Thirty tracks around an aerodrome: the rows of the pairs with a member outside the zone
    are those without zones; no row has its two members inside."""
    rng = np.random.default_rng(8)
    n = 30
    pos = np.column_stack([rng.uniform(-12e3, 12e3, n), rng.uniform(-12e3, 12e3, n), rng.uniform(50.0, 1_200.0, n)])
    vel = np.column_stack([rng.uniform(-120, 120, n), rng.uniform(-120, 120, n), rng.uniform(-5, 5, n)])
    df = _picture(pos, vel)
    inside = pl.DataFrame({"id": np.arange(1, n + 1, dtype=np.uint64), "in": ZONE.contains(pos)})

    def flagged(out: pl.DataFrame) -> pl.DataFrame:
        return (out.join(inside.rename({"id": "id_a", "in": "in_a"}), on="id_a")
                .join(inside.rename({"id": "id_b", "in": "in_b"}), on="id_b"))
    plain, zoned = flagged(predict_conflicts(df, FIXED)), flagged(predict_conflicts(df, ZONED))
    both = pl.col("in_a") & pl.col("in_b")
    assert plain.filter(both).height and plain.filter(~both).height
    assert zoned.filter(both).height == 0
    assert zoned.equals(plain.filter(~both))


def _truth(h_arrival: float, x0_arrival: float = 5_000.0) -> pl.DataFrame:
    """:func:`_departure_and_arrival`'s two aircraft flown for 60 s from 4 s before lift-off,
    sampled every second (the departure on the runway at 10 m until it lifts off)."""
    t = np.arange(61.0)
    times = [T0 + timedelta(seconds=float(s)) for s in t]
    up = np.maximum(t - 4.0, 0.0)
    dep = dict(truth_id=1, x=80.0 * up, h=10.0 + 8.0 * up, vx=80.0)
    arr = dict(truth_id=2, x=x0_arrival - 70.0 * t, h=h_arrival - 70.0 * np.tan(np.radians(3.0)) * t, vx=-70.0)
    frames = [pl.DataFrame({"truth_id": np.full(len(t), d["truth_id"], np.int64), "time": times, "x_m": d["x"],
                            "y_m": np.zeros(len(t)), "z_m": d["h"], "vx_mps": np.full(len(t), d["vx"]),
                            "vy_mps": np.zeros(len(t)), "vz_mps": np.zeros(len(t)), "alt_m": d["h"]})
              for d in (dep, arr)]
    return pl.concat(frames).with_columns(pl.col("time").cast(pl.Datetime("us", "UTC")))


def test_the_truth_counts_no_loss_inside_one_zone():
    """The departure and the arrival are within 3 NM and 1 000 ft from the start until the
    departure has climbed 1 000 ft above the arrival (about 50 s): one loss of separation without
    zones, none with the 4 NM zone (both inside throughout); with a 2 NM zone, which the arrival
    enters after about 19 s, the loss is counted until then — same start, earlier end."""
    tr = _truth(260.0)
    plain = loss_of_separation(tr, AlertConfig(conflict=FIXED))
    assert plain.height == 1
    assert loss_of_separation(tr, AlertConfig(conflict=ZONED)).height == 0
    small = dataclasses.replace(FIXED, aerodrome_zones=(AerodromeZone(0.0, 0.0, radius_m=2 * NM_M),))
    part = loss_of_separation(tr, AlertConfig(conflict=small))
    assert part["t_start"][0] == plain["t_start"][0]
    assert (part["t_end"][0] - T0).total_seconds() == pytest.approx((5_000.0 - 2 * NM_M) / 70.0, abs=1.0)
    # the exclusion is per truth segment (1 s here): at most the segment in which the departure
    # leaves the zone is counted again
    rest = ((part["t_end"] - part["t_start"]).dt.total_microseconds() / 1e6)[1:]
    assert rest.len() <= 1 and rest.sum() <= 1.0
    assert (plain["t_end"][0] - T0).total_seconds() > 45.0


def test_validation():
    with pytest.raises(ValueError, match="radius_m"):
        AerodromeZone(0.0, 0.0, radius_m=0.0)
    with pytest.raises(ValueError, match="finite"):
        AerodromeZone(float("nan"), 0.0)
    with pytest.raises(ValueError, match="AerodromeZone"):
        ConflictConfig(aerodrome_zones=((0.0, 0.0),))


def test_pipeline_takes_the_zones_from_the_national_airports(small_terminal):
    """national: one zone per airport, at its reference point; terminal-area: none; off, or
    configured, they are left alone; the run notes say so."""
    from tertiary.core.geo import LocalFrame
    from tertiary.simulate import load_scenario

    scen = load_scenario("national")

    class _Ds:
        scenario = scen
        origin = LocalFrame(*scen.origin)
    cfg = adapt_to_scenario(PipelineConfig(stca_approach_volumes=False), _Ds())
    zones = cfg.conflicts.aerodrome_zones
    assert [z.name for z in zones] == [a.name for a in scen.national.airports]
    a = scen.national.airports[0]
    x, y, _ = _Ds.origin.from_geodetic(a.lat_deg, a.lon_deg, 0.0)
    assert (zones[0].x_m, zones[0].y_m) == pytest.approx((float(x), float(y)))
    assert adapt_to_scenario(PipelineConfig(), small_terminal).conflicts.aerodrome_zones == ()
    off = PipelineConfig(stca_approach_volumes=False, stca_aerodrome_zones=False)
    assert adapt_to_scenario(off, _Ds()).conflicts.aerodrome_zones == ()
    mine = PipelineConfig(stca_approach_volumes=False, conflicts=ZONED)
    assert adapt_to_scenario(mine, _Ds()).conflicts.aerodrome_zones == ZONED.aerodrome_zones
    notes: list[str] = []
    note_minima(cfg.conflicts, notes)
    assert notes[0].startswith("aerodrome zones: no STCA alert and no loss of separation scored between two "
                               f"aircraft both within 4 NM and below 2,000 ft of one of {len(zones)} aerodromes")
