"""Coarse gating and the four grouping rules of §1.4, on hand-built epochs."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.stages.association.associate import (AssociationConfig, associate, carry_target_ids, group_reports)
from tertiary.stages.association.gating import GatingConfig, candidate_pairs

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)


def _aligned(rows: list[tuple]) -> pl.DataFrame:
    """rows: (epoch_s, radar_id, local_track_id, x, y, z[, vx, vy, mode_s])."""
    out = []
    for i, r in enumerate(rows):
        e, radar, track, x, y, z = r[:6]
        vx, vy = (r[6], r[7]) if len(r) > 7 else (100.0, 0.0)
        ms = r[8] if len(r) > 8 else None
        out.append({"report_id": i, "run": 0, "radar_id": radar, "local_track_id": track,
                    "epoch": T0.timestamp() + e, "x_m": x, "y_m": y, "z_m": z, "vx_mps": vx, "vy_mps": vy,
                    "vz_mps": 0.0, "cov": np.diag([900.0, 900.0, 90000.0, 25.0, 25.0, 4.0]).ravel().tolist(),
                    "mode_s": ms})
    df = pl.DataFrame(out)
    return df.with_columns(
        pl.col("report_id").cast(pl.UInt64), pl.col("run").cast(pl.UInt32), pl.col("radar_id").cast(pl.UInt32),
        pl.col("local_track_id").cast(pl.UInt32), pl.col("cov").cast(pl.Array(pl.Float64, 36)),
        pl.from_epoch(pl.col("epoch"), time_unit="s").dt.replace_time_zone("UTC").dt.cast_time_unit("us"),
        pl.col("mode_s").cast(pl.String)).sort("epoch", "radar_id", "local_track_id")


def _groups(df: pl.DataFrame, cfg=AssociationConfig()) -> list[set[int]]:
    label, _ = group_reports(df, cfg)
    ids = df["report_id"].to_list()
    groups: dict[int, set[int]] = {}
    for lab, rid in zip(label, ids):
        groups.setdefault(int(lab), set()).add(rid)
    return sorted(groups.values(), key=min)


def test_gate_is_per_epoch_and_across_radars_only():
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 100, 0, 3000), (0, 1, 2, 200, 0, 3000),
                   (4, 2, 1, 50, 0, 3000)])
    p = candidate_pairs(df, GatingConfig())
    pairs = {tuple(sorted((df["report_id"][int(a)], df["report_id"][int(b)]))) for a, b in zip(p.a, p.b)}
    assert pairs == {(0, 1), (1, 2)}          # never same radar, never across epochs
    np.testing.assert_allclose(sorted(p.sqdist), [100.0**2, 100.0**2])


def test_gate_tolerances_position_velocity_altitude():
    cfg = GatingConfig(pos_tol_m=1000.0, alt_tol_m=500.0, vel_tol_mps=30.0)
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 900, 0, 3000),       # in
                   (0, 1, 2, 0, 20000, 3000), (0, 2, 2, 1200, 20000, 3000),   # too far
                   (0, 1, 3, 0, 40000, 3000), (0, 2, 3, 0, 40000, 3700),      # too high
                   (0, 1, 4, 0, 60000, 3000, 100.0, 0.0), (0, 2, 4, 0, 60000, 3000, 160.0, 0.0)])  # too fast
    p = candidate_pairs(df, cfg)
    assert len(p) == 1


def test_mode_s_separates_and_mahalanobis_gate():
    df = _aligned([(0, 1, 1, 0, 0, 3000, 100, 0, "abc123"), (0, 2, 1, 50, 0, 3000, 100, 0, "def456")])
    assert len(candidate_pairs(df, GatingConfig())) == 0
    assert len(candidate_pairs(df, GatingConfig(use_mode_s=False))) == 1
    far = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 2500, 0, 3000)])    # 2.5 km apart, σ 30 m each
    assert len(candidate_pairs(far, GatingConfig())) == 1
    assert len(candidate_pairs(far, GatingConfig(method="mahalanobis"))) == 0


def test_rule1_one_source_gives_one_target_per_report():
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 1, 2, 100, 0, 3000), (0, 1, 3, 200, 0, 3000)])
    assert _groups(df) == [{0}, {1}, {2}]


def test_rule2_one_report_per_source_is_one_target():
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 150, 50, 3100), (0, 3, 1, -100, 80, 2950)])
    assert _groups(df) == [{0, 1, 2}]


def test_rule3_equal_counts_minimum_sum_of_squared_distances():
    # two aircraft 1 km apart seen by two radars; greedy nearest would pair wrongly,
    # the minimum-sum assignment pairs them right
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 1, 2, 1000, 0, 3000),
                   (0, 2, 1, 600, 0, 3000), (0, 2, 2, 1700, 0, 3000)])
    # costs: (a1,b1)=600², (a1,b2)=1700², (a2,b1)=400², (a2,b2)=700²
    # pairing {a1-b1, a2-b2}: 360000+490000 = 850000 < {a1-b2, a2-b1}: 2890000+160000
    g = _groups(df)
    ids = df["report_id"].to_list()
    assert g == sorted([{ids[0], ids[2]}, {ids[1], ids[3]}], key=min)


def test_rule4_unequal_counts_reference_radar_sets_the_number():
    # radar 1 sees three aircraft, radar 2 two of them, radar 3 one
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 1, 2, 1500, 0, 3000), (0, 1, 3, 3000, 0, 3000),
                   (0, 2, 1, 1450, 30, 3000), (0, 2, 2, 60, -20, 3000),
                   (0, 3, 1, 2950, 10, 3000)])
    label, stats = group_reports(df)
    assert stats.ambiguous_components == 1
    assert len(set(label)) == 3
    rid = df["report_id"].to_list()
    by = {r: l for r, l in zip(rid, label)}
    # (radar, track) → report id
    key = {(r, t): i for i, r, t in zip(rid, df["radar_id"], df["local_track_id"])}
    assert by[key[(2, 2)]] == by[key[(1, 1)]]
    assert by[key[(2, 1)]] == by[key[(1, 2)]]
    assert by[key[(3, 1)]] == by[key[(1, 3)]]


def test_ungated_assignment_is_refused():
    # one component A, B (radar 1), C, D (radar 2), E (radar 3) with gate 600 m on a line:
    # C and D are both gated only to A, so the assignment of radar 2 to radar 1 (the reference,
    # tie on counts → lowest radar id) can place one of them; the other is refused and stands alone
    cfg = AssociationConfig(gating=GatingConfig(pos_tol_m=600.0))
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 1, 2, 1000, 0, 3000),
                   (0, 2, 1, 300, 0, 3000), (0, 2, 2, -300, 0, 3000),
                   (0, 3, 1, 500, 0, 3000)])
    label, stats = group_reports(df, cfg)
    assert stats.ambiguous_components == 1
    assert len(set(label)) == 3
    by = dict(zip(zip(df["radar_id"], df["local_track_id"]), label))
    assert by[(2, 1)] != by[(2, 2)]                          # a radar never gives two reports of one aircraft
    assert {by[(2, 1)], by[(2, 2)]} & {by[(1, 1)]}           # one of them joined A
    assert by[(1, 1)] != by[(1, 2)]


def test_target_ids_stable_across_epochs_and_reassignments_counted():
    rows = []
    for e in (0, 4, 8):
        rows += [(e, 1, 1, 0 + 400 * e, 0, 3000), (e, 2, 9, 50 + 400 * e, 0, 3000),
                 (e, 1, 2, 0 + 400 * e, 30000, 3000), (e, 2, 8, 40 + 400 * e, 30000, 3000)]
    df = _aligned(rows)
    assoc, stats = associate(df)
    per = assoc.group_by("radar_id", "local_track_id").agg(pl.col("target_id").n_unique())
    assert per["target_id"].max() == 1
    assert stats.targets == 2 and stats.reassignments == 0
    # radar 2 swaps its local track numbers at epoch 8: both of its tracks change target
    rows2 = rows[:8] + [(8, 1, 1, 3200, 0, 3000), (8, 2, 8, 3250, 0, 3000),
                        (8, 1, 2, 3200, 30000, 3000), (8, 2, 9, 3240, 30000, 3000)]
    assoc2, stats2 = associate(_aligned(rows2))
    assert stats2.targets == 2
    assert stats2.reassignments == 2


def test_costs_are_squared_distance_to_reference():
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 30, 40, 3000)])
    assoc, _ = associate(df)
    assert sorted(assoc["cost"].to_list()) == pytest.approx([0.0, 2500.0])
    assoc_m, _ = associate(df, AssociationConfig(cost="mahalanobis"))
    assert sorted(assoc_m["cost"].to_list()) == pytest.approx([0.0, 2500.0 / 1800.0])


def test_mode_c_separates_stacked_aircraft():
    """Two aircraft 1 000 ft apart above one holding fix, seen by two radars whose elevation
    heights cannot tell them apart (the z of both is the same): Mode C keeps them apart; replies
    of one aircraft climbing 10 m/s taken 8 s apart still gate; a report without Mode C never splits."""
    df = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 50, 0, 3000)])
    ages = pl.Series("age_s", [0.0, 8.0])
    stacked = df.with_columns(pl.Series("altitude_m", [3048.0, 3048.0 + 304.8]), ages)
    assert len(candidate_pairs(stacked, GatingConfig())) == 0
    assert len(candidate_pairs(stacked, GatingConfig(use_mode_c=False))) == 1
    climbing = df.with_columns(pl.Series("altitude_m", [3048.0, 3048.0 - 80.0 - 120.0]), ages)  # 10 m/s × 8 s + 120
    assert len(candidate_pairs(climbing, GatingConfig())) == 1
    missing = df.with_columns(pl.Series("altitude_m", [3048.0, None], dtype=pl.Float64), ages)
    assert len(candidate_pairs(missing, GatingConfig())) == 1


def test_a_garbled_mode_c_code_does_not_split_one_mode_s_address():
    """Two radars' replies of one aircraft at FL351 (one Mode S address): one radar's altitude
    code is one bit off (+25 600 ft, the simulator's and a real transponder's garble). The pair
    still gates and its cost has no vertical term, so the aircraft stays one system target; two
    addresses or no address keep the Mode C test. Nor does a missing code with elevation heights
    kilometres apart split one address."""
    df = _aligned([(0, 1, 1, 0, 0, 10706.0), (0, 2, 1, 200, 0, 10706.0)])
    ages = pl.Series("age_s", [0.0, 0.0])
    garbled = df.with_columns(pl.Series("altitude_m", [10706.1, 10706.1 + 7802.88]), ages,
                              pl.Series("mode_s", ["385ec1", "385ec1"]))
    p = candidate_pairs(garbled, GatingConfig())
    assert len(p) == 1 and p.sqdist[0] == pytest.approx(200.0 ** 2)
    assert _groups(garbled) == [{0, 1}]
    two = garbled.with_columns(pl.Series("mode_s", ["385ec1", "385ec2"]))
    assert len(candidate_pairs(two, GatingConfig())) == 0
    none = garbled.with_columns(pl.Series("mode_s", [None, None], dtype=pl.String))
    assert len(candidate_pairs(none, GatingConfig())) == 0
    # one code missing, the elevation heights 1.8 km apart (en-route range): one address still pairs
    far = _aligned([(0, 1, 1, 0, 0, 10706.0), (0, 2, 1, 200, 0, 10706.0 + 1800.0)]).with_columns(
        pl.Series("altitude_m", [10706.1, None], dtype=pl.Float64), ages, pl.Series("mode_s", ["385ec1", "385ec1"]))
    p = candidate_pairs(far, GatingConfig())
    assert len(p) == 1 and p.sqdist[0] == pytest.approx(200.0 ** 2)
    assert len(candidate_pairs(far.with_columns(pl.lit(None, pl.String).alias("mode_s")), GatingConfig())) == 0


def test_a_radars_older_track_of_an_address_does_not_keep_its_newer_one_from_the_aircraft():
    """Radar 1 still extrapolates its old local track of the aircraft (report 9 s old) beside the
    new one it started (report 1 s old); radar 2 sees the aircraft too. The newer report groups
    with radar 2's, the older one alone: with both in the gate, a radar's two reports make two
    targets and radar 2's could go with the older. Without an address both stay candidates."""
    rows = [(0, 1, 1, 0, 0, 3000, 100.0, 0.0, "4ca1b2"), (0, 1, 2, 400, 0, 3000, 100.0, 0.0, "4ca1b2"),
            (0, 2, 5, 150, 0, 3000, 100.0, 0.0, "4ca1b2")]
    # rows in (radar, local track) order: reports 9 s, 1 s and 2 s old
    df = _aligned(rows).with_columns(pl.Series("time", [T0 - timedelta(seconds=s) for s in (9, 1, 2)]))
    ids = dict(zip(zip(df["radar_id"], df["local_track_id"]), df["report_id"]))
    assert sorted(_groups(df), key=len) == [{ids[(1, 1)]}, {ids[(1, 2)], ids[(2, 5)]}]
    pairs = candidate_pairs(df, GatingConfig())
    assert {(int(a), int(b)) for a, b in zip(pairs.a, pairs.b)} in ({(1, 2)}, {(2, 1)})
    anonymous = df.with_columns(pl.lit(None, pl.String).alias("mode_s"))
    assert len(candidate_pairs(anonymous, GatingConfig())) == 2


def test_mode_c_is_the_vertical_gate_where_both_reports_carry_it():
    """One aircraft at FL350 seen by two en-route radars 200 km away: their elevation heights
    differ by 1.8 km (0.5° of elevation error), beyond ``alt_tol_m``, while the Mode C altitudes
    agree. The pair gates — with the z box it was split into two targets — and its cost's
    vertical term is the altitude difference (20 m), not the elevation heights' 1.8 km. A pair
    with one report lacking Mode C is still held to the elevation heights' tolerance."""
    df = _aligned([(0, 1, 1, 0, 0, 10668.0), (0, 2, 1, 300, 0, 10668.0 + 1800.0)])
    ages = pl.Series("age_s", [0.0, 0.0])
    both = df.with_columns(pl.Series("altitude_m", [10668.0, 10688.0]), ages)
    p = candidate_pairs(both, GatingConfig())
    assert len(p) == 1 and p.sqdist[0] == pytest.approx(300.0 ** 2 + 20.0 ** 2)
    assert len(candidate_pairs(both, GatingConfig(use_mode_c=False))) == 0
    assert _groups(both) == [{0, 1}]
    one = df.with_columns(pl.Series("altitude_m", [10668.0, None], dtype=pl.Float64), ages)
    assert len(candidate_pairs(one, GatingConfig())) == 0
    # Mode C still separates what it separates, even with equal elevation heights (stacked)
    stacked = _aligned([(0, 1, 1, 0, 0, 3000), (0, 2, 1, 50, 0, 3000)]).with_columns(
        pl.Series("altitude_m", [3048.0, 3048.0 + 304.8]), ages)
    assert len(candidate_pairs(stacked, GatingConfig())) == 0
