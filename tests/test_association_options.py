"""Association decisions (§1.4, §4.1): the Bayes minimum-error H1/H2 gate, fine identification
by Mode 3/A and callsign, and the joint (multi-dimensional) assignment against brute force."""

from __future__ import annotations

from datetime import datetime, timezone
from itertools import combinations

import numpy as np
import polars as pl
import pytest
from scipy.stats import multivariate_normal

from tertiary.stages.association.associate import (AssociationConfig, _solve_component, feasible_tuples, group_reports, solve_joint)
from tertiary.core.errors import OptionError
from tertiary.stages.association.gating import GatingConfig, bayes_threshold, candidate_pairs, gate_volume

T0 = datetime(2021, 10, 7, 12, 0, tzinfo=timezone.utc)
COV = np.diag([900.0, 900.0, 90000.0, 25.0, 25.0, 4.0])


def _aligned(rows: list[tuple], **ident) -> pl.DataFrame:
    """rows: (epoch_s, radar_id, local_track_id, x, y, z); ident: column → values per row."""
    out = [{"report_id": i, "run": 0, "radar_id": r[1], "local_track_id": r[2], "epoch": T0.timestamp() + r[0],
            "x_m": float(r[3]), "y_m": float(r[4]), "z_m": float(r[5]), "vx_mps": 100.0, "vy_mps": 0.0,
            "vz_mps": 0.0, "cov": COV.ravel().tolist(), "mode_s": None} for i, r in enumerate(rows)]
    df = pl.DataFrame(out).with_columns(**{k: pl.Series(k, v, dtype=pl.String) for k, v in ident.items()})
    return df.with_columns(
        pl.col("report_id").cast(pl.UInt64), pl.col("run").cast(pl.UInt32), pl.col("radar_id").cast(pl.UInt32),
        pl.col("local_track_id").cast(pl.UInt32), pl.col("cov").cast(pl.Array(pl.Float64, 36)),
        pl.from_epoch(pl.col("epoch"), time_unit="s").dt.replace_time_zone("UTC").dt.cast_time_unit("us"),
        pl.col("mode_s").cast(pl.String))


def _groups(df: pl.DataFrame, cfg: AssociationConfig) -> list[set[int]]:
    label, _ = group_reports(df, cfg)
    groups: dict[int, set[int]] = {}
    for lab, rid in zip(label, df["report_id"].to_list()):
        groups.setdefault(int(lab), set()).add(rid)
    return sorted(groups.values(), key=min)


# --------------------------------------------------------------------------- Bayes H1/H2


def test_bayes_threshold_is_the_likelihood_ratio_crossing():
    rng = np.random.default_rng(3)
    for p1, vol in [(0.5, 1e9), (0.2, 5e10), (0.9, 3e8)]:
        a = rng.normal(size=(3, 3)) * [[300], [300], [100]]
        s = a @ a.T + np.diag([1e4, 1e4, 1e4])
        gamma = float(bayes_threshold(np.linalg.det(s), p1, vol))
        assert gamma > 0
        u = rng.normal(size=3)
        u /= np.sqrt(u @ np.linalg.solve(s, u))          # d²(u) = 1
        h2 = (1 - p1) / vol                               # P(H2) × uniform density over the gate
        on = p1 * multivariate_normal(np.zeros(3), s).pdf(np.sqrt(gamma) * u)
        assert on == pytest.approx(h2, rel=1e-9)          # posterior odds are 1 exactly at d² = γ
        assert p1 * multivariate_normal(np.zeros(3), s).pdf(np.sqrt(gamma * 0.99) * u) > h2
        assert p1 * multivariate_normal(np.zeros(3), s).pdf(np.sqrt(gamma * 1.01) * u) < h2
    # a larger prior of H1 or gate volume widens the gate; an impossible prior is refused
    assert bayes_threshold(1e12, 0.8, 1e9) > bayes_threshold(1e12, 0.5, 1e9) > bayes_threshold(1e12, 0.5, 1e8)
    with pytest.raises(ValueError):
        bayes_threshold(1e12, 1.0, 1e9)


def test_bayes_gate_keeps_exactly_the_pairs_where_h1_is_more_probable():
    # pairs at one epoch each, separated along x; S = 2·diag(900, 900, 90000)
    seps = [50.0, 150.0, 180.0, 200.0, 220.0, 260.0, 400.0]
    rows = []
    for k, d in enumerate(seps):
        rows += [(k, 1, k, 0.0, 0.0, 3000.0), (k, 2, k, d, 0.0, 3000.0)]
    df = _aligned(rows)
    for p1 in (0.5, 0.05):
        cfg = GatingConfig(method="bayes", prior_h1=p1)
        s = 2 * np.diag([900.0, 900.0, 90000.0])
        vol = 4 / 3 * np.pi * 3000.0**2 * 1500.0
        assert gate_volume(cfg) == pytest.approx(vol)
        want = [p1 * multivariate_normal(np.zeros(3), s).pdf([d, 0, 0]) >= (1 - p1) / vol for d in seps]
        p = candidate_pairs(df, cfg)
        kept = sorted(int(df["epoch"][int(a)].timestamp() - T0.timestamp()) for a in p.a)
        assert kept == [k for k, w in enumerate(want) if w]
        assert 0 < sum(want) < len(seps)                 # the threshold falls inside the constructed range
    assert len(candidate_pairs(df, GatingConfig())) == len(seps)      # the box keeps them all


# --------------------------------------------------------------------------- fine identification


def test_conflicting_mode_3a_or_callsign_forbids_or_penalises():
    # one pair 100 m apart: merged on geometry; a conflicting code splits it under "forbid"
    single = [(0, 1, 1, 0, 0, 3000), (0, 2, 1, 100, 0, 3000)]
    df = _aligned(single, mode_3a=["1234", "4321"], callsign=["AFR12", "afr 12"])
    assert _groups(df, AssociationConfig()) == [{0, 1}]
    assert _groups(df, AssociationConfig(mode_3a="forbid")) == [{0}, {1}]
    assert _groups(df, AssociationConfig(callsign="forbid")) == [{0, 1}]      # same callsign after normalising
    assert _groups(df, AssociationConfig(mode_3a="penalise")) == [{0, 1}]    # soft: evidence, not proof
    unknown = _aligned(single, mode_3a=["1234", None], callsign=["AFR12", ""])
    assert _groups(unknown, AssociationConfig(mode_3a="forbid", callsign="forbid")) == [{0, 1}]

    # two aircraft 300 m apart seen by two radars; radar 2's plots are displaced so that geometry
    # alone pairs them crosswise; the codes say otherwise
    cross = [(0, 1, 1, 0, 0, 3000), (0, 1, 2, 300, 0, 3000), (0, 2, 1, 260, 0, 3000), (0, 2, 2, 40, 0, 3000)]
    codes = ["1000", "2000", "1000", "2000"]
    df = _aligned(cross, mode_3a=codes, callsign=["A1", "B2", "A1", "B2"])
    assert _groups(df, AssociationConfig()) == [{0, 3}, {1, 2}]
    for how in ("forbid", "penalise"):
        assert _groups(df, AssociationConfig(mode_3a=how)) == [{0, 2}, {1, 3}]
        assert _groups(df, AssociationConfig(callsign=how)) == [{0, 2}, {1, 3}]
    label, stats = group_reports(df, AssociationConfig(mode_3a="penalise"))
    assert stats.identity_conflicts == 2
    with pytest.raises(OptionError, match="mode_3a"):
        group_reports(_aligned(cross), AssociationConfig(mode_3a="forbid"))


# --------------------------------------------------------------------------- joint assignment


def _partitions(items: list[int]):
    if not items:
        yield []
        return
    first, rest = items[0], items[1:]
    for part in _partitions(rest):
        yield [[first], *part]
        for i in range(len(part)):
            yield [*part[:i], [first, *part[i]], *part[i + 1:]]


def _objective(groups, radar, cost, gated) -> tuple[int, float] | None:
    total = 0.0
    for g in groups:
        g = list(g)
        if len({int(radar[i]) for i in g}) < len(g):
            return None
        for i, j in combinations(g, 2):
            if not gated[i, j]:
                return None
            total += cost[i, j]
    return len(groups), total


def _brute_force(radar, cost, gated) -> tuple[int, float]:
    best = None
    for part in _partitions(list(range(len(radar)))):
        obj = _objective(part, radar, cost, gated)
        if obj is not None and (best is None or obj[0] < best[0] or (obj[0] == best[0] and obj[1] < best[1] - 1e-9)):
            best = obj
    return best


def _case(rng, n_radars: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    counts = rng.integers(1, 4, n_radars)
    while counts.sum() > 9:
        counts = rng.integers(1, 4, n_radars)
    radar = np.repeat(np.arange(n_radars), counts)
    truth = rng.uniform(0, 800, (counts.max(), 2))
    pos = truth[rng.integers(0, counts.max(), len(radar))] + rng.normal(0, 120, (len(radar), 2))
    cost = ((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1)
    gated = (cost <= 500.0**2) & (radar[:, None] != radar[None, :])
    return radar, cost, gated


def test_joint_assignment_equals_brute_force_and_never_loses_to_pairwise():
    rng = np.random.default_rng(11)
    strictly_better = checked = infeasible = 0
    for trial in range(60):
        radar, cost, gated = _case(rng, int(rng.integers(3, 5)))
        groups = solve_joint(radar, cost, gated)
        got = _objective(groups, radar, cost, gated)
        assert got is not None and sorted(np.concatenate(groups).tolist()) == list(range(len(radar)))
        want = _brute_force(radar, cost, gated)
        assert got[0] == want[0] and got[1] == pytest.approx(want[1], rel=1e-9, abs=1e-6), trial
        # pairwise-to-reference gates members against the reference only: its groups may hold
        # two non-reference reports that are not gated with each other (then not comparable)
        pair = _objective(_solve_component(np.arange(len(radar)), radar, cost, gated), radar, cost, gated)
        if pair is None:
            infeasible += 1
            continue
        assert (pair[0], pair[1] + 1e-6) >= got
        strictly_better += pair[0] == got[0] and pair[1] > got[1] * (1 + 1e-9) + 1e-6
        checked += 1
    assert checked >= 30 and strictly_better >= 1       # the option changes decisions somewhere


def test_feasible_tuples_are_the_gated_cliques():
    radar = np.array([0, 0, 1, 2])
    gated = np.zeros((4, 4), bool)
    for i, j in [(0, 2), (0, 3), (2, 3), (1, 2)]:
        gated[i, j] = gated[j, i] = True
    tups = {tuple(sorted(int(v) for v in t if v >= 0)) for t in feasible_tuples(radar, gated)}
    assert tups == {(0,), (1,), (2,), (3,), (0, 2), (0, 3), (2, 3), (1, 2), (0, 2, 3)}


def test_joint_option_in_group_reports():
    """Through group_reports: each ambiguous connected component (some radar with two reports)
    of ≥ 3 radars is solved to the brute-force optimum; rule-2 components stay one group."""
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(5)
    n_joint = 0
    for _ in range(40):
        radar = np.repeat(np.arange(3), rng.integers(1, 4, 3))
        xy = rng.uniform(0, 900, (len(radar), 2))
        df = _aligned([(0, int(radar[i]) + 1, i, xy[i, 0], xy[i, 1], 3000.0) for i in range(len(radar))])
        cfg = AssociationConfig(gating=GatingConfig(pos_tol_m=500.0), assignment="joint")
        label, stats = group_reports(df, cfg)
        c2 = ((xy[:, None] - xy[None]) ** 2).sum(-1)
        g2 = (c2 <= 500.0**2) & (radar[:, None] != radar[None, :])
        _, comp = connected_components(g2, directed=False)
        for k in np.unique(comp):
            idx = np.flatnonzero(comp == k)
            got = [np.flatnonzero(label[idx] == v) for v in np.unique(label[idx])]
            assert not set(label[idx]) & set(label[comp != k])          # groups stay inside components
            r = radar[idx]
            if np.bincount(r).max() <= 1:
                assert len(got) == 1
                continue
            sub_c, sub_g = c2[np.ix_(idx, idx)], g2[np.ix_(idx, idx)]
            obj, want = _objective(got, r, sub_c, sub_g), _brute_force(r, sub_c, sub_g)
            assert obj[0] == want[0] and obj[1] == pytest.approx(want[1], rel=1e-9, abs=1e-6)
        n_joint += stats.joint_components
    assert n_joint >= 5
