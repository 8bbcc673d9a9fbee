"""Tests of clustering ("укрупнение", §1.4) on crafted, hand-checked formations."""

from __future__ import annotations

import time
from datetime import datetime, timedelta, timezone

import numpy as np
import polars as pl
import pytest

from tertiary.stages.clustering import ClusteringConfig, cluster, cluster_summary
from tertiary.contract import TABLES, validate

T0 = datetime(2024, 3, 1, 12, 0, 0, tzinfo=timezone.utc)
ALWAYS = ClusteringConfig(always=True)
STROBE = ClusteringConfig(algorithm="strobe", always=True)


def fused(rows: list[tuple]) -> pl.DataFrame:
    """Rows (target_id, x, y, z, vx, vy[, epoch_s[, run[, method]]]) -> a fused-like frame."""
    full = [tuple(r) + (0.0, 0, "mean")[len(r) - 6:] for r in rows]
    return pl.DataFrame(
        {
            "run": pl.Series([r[7] for r in full], dtype=pl.UInt32),
            "epoch": pl.Series([T0 + timedelta(seconds=r[6]) for r in full]).cast(pl.Datetime("us", "UTC")),
            "method": pl.Series([r[8] for r in full], dtype=pl.String),
            "target_id": pl.Series([r[0] for r in full], dtype=pl.UInt64),
            "x_m": [float(r[1]) for r in full],
            "y_m": [float(r[2]) for r in full],
            "z_m": [float(r[3]) for r in full],
            "vx_mps": [float(r[4]) for r in full],
            "vy_mps": [float(r[5]) for r in full],
            "vz_mps": [0.0] * len(full),
        }
    )


def groups(out: pl.DataFrame) -> list[tuple[int, list[int]]]:
    """(lead, members) per cluster, sorted by lead."""
    return sorted(zip(out["lead_target_id"].to_list(), out["members"].to_list()))


def test_compact_formation_of_four():
    f = fused([
        (7, 1000.0, 0.0, 3000.0, 200.0, 0.0),
        (3, 0.0, 0.0, 3000.0, 200.0, 0.0),
        (9, 0.0, 1500.0, 3100.0, 200.0, 0.0),
        (5, 1200.0, 1200.0, 2900.0, 200.0, 0.0),
        (11, 60_000.0, 0.0, 3000.0, 200.0, 0.0),     # far away: shown alone
        (12, 0.0, 0.0, 9000.0, 200.0, 0.0),          # right above: 6 km vertical = 60 km scaled
    ])
    out = cluster(f, ALWAYS)
    assert out.height == 1
    assert groups(out) == [(3, [3, 5, 7, 9])]
    assert out["count"].to_list() == [4]
    assert out["cluster_id"].to_list() == [1]
    assert out.schema == pl.Schema(TABLES["clusters"].required)
    validate(out, "clusters")                          # keys unique, dtypes as the contract
    assert groups(cluster(f, STROBE)) == [(3, [3, 5, 7, 9])]


def test_velocity_selection_splits_formation():
    # 5 aircraft within 1.5 km; 3 and 5 fly the opposite way
    f = fused([
        (1, 0.0, 0.0, 3000.0, 200.0, 0.0),
        (2, 500.0, 0.0, 3000.0, 210.0, 5.0),
        (3, 1000.0, 0.0, 3000.0, -200.0, 0.0),
        (4, 0.0, 500.0, 3000.0, 230.0, -30.0),          # |Δv| = 30 on both axes: kept (≤ Δv)
        (5, 1000.0, 500.0, 3000.0, -190.0, 10.0),
    ])
    for cfg in (ALWAYS, STROBE):
        out = cluster(f, cfg)
        assert groups(out) == [(1, [1, 2, 4]), (3, [3, 5])]
        assert sorted(out["count"].to_list()) == [2, 3]


def test_split_off_members_that_disagree_stay_single():
    f = fused([
        (1, 0.0, 0.0, 3000.0, 200.0, 0.0),
        (2, 500.0, 0.0, 3000.0, 200.0, 0.0),
        (3, 1000.0, 0.0, 3000.0, -200.0, 0.0),
        (4, 0.0, 500.0, 3000.0, 231.0, 0.0),            # 31 m/s faster: split off
        (5, 1000.0, 500.0, 3000.0, 0.0, 200.0),
    ])
    assert groups(cluster(f, ALWAYS)) == [(1, [1, 2])]


def test_lead_disappears_and_is_reselected():
    def epoch(t, members):
        return [(tid, x + 200.0 * t, y, 3000.0, 200.0, 0.0, t) for tid, x, y in members]

    rows = (
        epoch(0, [(1, 0.0, 0.0), (2, -3000.0, 0.0), (3, 1000.0, 100.0), (4, 2500.0, 0.0)])
        # epoch 1: lead 1 vanishes; centroid of {2, 3, 4} is (167, 33): 3 is nearest, not min id 2
        + epoch(1, [(2, -3000.0, 0.0), (3, 1000.0, 100.0), (4, 2500.0, 0.0)])
        # epoch 2: 3 is no longer nearest the centroid, but stays the lead; 8 joins
        + epoch(2, [(2, -3000.0, 0.0), (3, 1000.0, 100.0), (4, 2500.0, 0.0), (8, -1000.0, 0.0)])
    )
    out = cluster(fused(rows), ALWAYS).sort("epoch")
    assert out["cluster_id"].to_list() == [1, 1, 1]
    assert out["lead_target_id"].to_list() == [1, 3, 3]
    assert out["members"].to_list() == [[1, 2, 3, 4], [2, 3, 4], [2, 3, 4, 8]]


def test_lead_leaving_the_group_keeps_id_with_the_rest():
    rows = [
        (1, 0.0, 0.0, 3000.0, 200.0, 0.0, 0), (2, 1000.0, 0.0, 3000.0, 200.0, 0.0, 0),
        (3, 2000.0, 0.0, 3000.0, 200.0, 0.0, 0), (4, 90_000.0, 0.0, 3000.0, 200.0, 0.0, 0),
        (5, 91_000.0, 0.0, 3000.0, 200.0, 0.0, 0),
        # epoch 1: lead 1 is now 50 km away (still present, alone); 4 and 5 keep their cluster
        (1, 50_000.0, 0.0, 3000.0, 200.0, 0.0, 1), (2, 1000.0, 0.0, 3000.0, 200.0, 0.0, 1),
        (3, 2000.0, 0.0, 3000.0, 200.0, 0.0, 1), (4, 90_000.0, 0.0, 3000.0, 200.0, 0.0, 1),
        (5, 91_000.0, 0.0, 3000.0, 200.0, 0.0, 1),
    ]
    out = cluster(fused(rows), ALWAYS).sort("epoch", "cluster_id")
    assert out.select("cluster_id", "lead_target_id", "members").rows() == [
        (1, 1, [1, 2, 3]), (2, 4, [4, 5]),
        (1, 2, [2, 3]), (2, 4, [4, 5]),            # tie in distance to centroid -> smaller id
    ]


def test_velocity_split_keeps_ids_across_epochs():
    # the {1,2,4} / {3,5} split of a converging pair of formations persists with stable ids
    rows = []
    for t in range(3):
        rows += [
            (1, 0.0, 0.0, 3000.0, 200.0, 0.0, t), (2, 500.0, 0.0, 3000.0, 200.0, 0.0, t),
            (4, 0.0, 500.0, 3000.0, 200.0, 0.0, t),
            (3, 1000.0, 0.0, 3000.0, -200.0, 0.0, t), (5, 1000.0, 500.0, 3000.0, -200.0, 0.0, t),
        ]
    out = cluster(fused(rows), ALWAYS).sort("epoch", "cluster_id")
    assert out.select("cluster_id", "lead_target_id").rows() == [(1, 1), (2, 3)] * 3


def test_trigger_display_capacity():
    def formation(t, n):
        return [(i, 800.0 * i, 0.0, 3000.0, 200.0, 0.0, t) for i in range(1, n + 1)]

    f = fused(formation(0, 5) + formation(1, 8))
    assert cluster(f, ClusteringConfig(display_capacity=8)).is_empty()
    out = cluster(f, ClusteringConfig(display_capacity=6))
    assert out["epoch"].to_list() == [T0 + timedelta(seconds=1)]
    assert groups(out) == [(1, list(range(1, 9)))]
    assert cluster(f, ClusteringConfig(display_capacity=6, always=True)).height == 2
    # default norm: 150 targets are shown individually, 151 are clustered
    big = [(i, 800.0 * (i % 10), 10_000.0 * (i // 10), 3000.0, 200.0, 0.0) for i in range(151)]
    assert cluster(fused(big[:150])).is_empty()
    assert cluster(fused(big)).height == 15


def test_strobe_hand_case():
    f = fused([
        (1, 0.0, 0.0, 1000.0, 200.0, 0.0),
        (2, 4000.0, 0.0, 1000.0, 200.0, 0.0),     # in 1's gate
        (3, 8000.0, 0.0, 1000.0, 200.0, 0.0),     # 8 km from 1: outside its gate, inside 2's
        (4, 0.0, 0.0, 1600.0, 200.0, 0.0),        # 600 m above 1: outside dH = 500
        (5, 9000.0, 0.0, 1000.0, 200.0, 0.0),
        (6, 9000.0, 4900.0, 1000.0, 200.0, 0.0),  # in 3's gate (dx 1000, dy 4900)
    ])
    # greedy by target id: 1 takes {1, 2}; 3 (smallest unassigned) takes {3, 5, 6}; 4 alone
    assert groups(cluster(f, STROBE)) == [(1, [1, 2]), (3, [3, 5, 6])]
    # DBSCAN (eps 5 km, H×10) chains 1-2-3-5-6; 4 is 6 km (scaled) from everyone
    assert groups(cluster(f, ALWAYS)) == [(1, [1, 2, 3, 5, 6])]


def test_two_far_apart_groups():
    f = fused([
        (1, 0.0, 0.0, 3000.0, 200.0, 0.0), (2, 1000.0, 0.0, 3000.0, 200.0, 0.0),
        (3, 100_000.0, 0.0, 3000.0, 200.0, 0.0), (4, 101_000.0, 0.0, 3000.0, 200.0, 0.0),
        (5, 100_500.0, 800.0, 3000.0, 200.0, 0.0),
    ])
    for cfg in (ALWAYS, STROBE):
        out = cluster(f, cfg)
        assert groups(out) == [(1, [1, 2]), (3, [3, 4, 5])]
        assert sorted(out["cluster_id"].to_list()) == [1, 2]


def test_same_position_in_other_epochs_runs_methods_never_clustered():
    rows = []
    for t in range(3):
        for run in range(2):
            for method in ("mean", "apriori"):
                rows.append((1, 0.0, 0.0, 3000.0, 200.0, 0.0, t, run, method))
    f = fused(rows)
    for cfg in (ALWAYS, STROBE):
        assert cluster(f, cfg).is_empty()
    # a second target in one (run, epoch, method) clusters only there
    f2 = fused(rows + [(2, 10.0, 0.0, 3000.0, 200.0, 0.0, 1, 1, "apriori")])
    for cfg in (ALWAYS, STROBE):
        out = cluster(f2, cfg)
        assert out.select("run", "method", "members").rows() == [(1, "apriori", [1, 2])]
        assert out["epoch"].to_list() == [T0 + timedelta(seconds=1)]


def test_ids_and_bookkeeping_per_run_and_method():
    rows = []
    for run in (0, 3):
        for method in ("mean", "apriori"):
            for t in range(2):
                rows += [(1, 0.0, 0.0, 3000.0, 200.0, 0.0, t, run, method),
                         (2, 500.0, 0.0, 3000.0, 200.0, 0.0, t, run, method)]
    out = cluster(fused(rows), ALWAYS)
    assert out.height == 8
    assert set(out["cluster_id"].to_list()) == {1}
    assert set(out["lead_target_id"].to_list()) == {1}


def test_non_finite_rows_are_not_clustered_and_errors():
    f = fused([(1, 0.0, 0.0, 3000.0, 200.0, 0.0), (2, 500.0, 0.0, 3000.0, 200.0, 0.0),
               (3, float("nan"), 0.0, 3000.0, 200.0, 0.0)])
    assert groups(cluster(f, ALWAYS)) == [(1, [1, 2])]
    assert cluster(f.clear(), ALWAYS).schema == pl.Schema(TABLES["clusters"].required)
    with pytest.raises(ValueError, match="vx_mps"):
        cluster(f.drop("vx_mps"), ALWAYS)
    with pytest.raises(ValueError, match="duplicate"):
        cluster(pl.concat([f, f]), ALWAYS)
    with pytest.raises(ValueError):
        ClusteringConfig(algorithm="kmeans")  # type: ignore[arg-type]


def test_cluster_summary():
    f = fused([
        (1, 0.0, 0.0, 3000.0, 200.0, 0.0), (2, 1000.0, 0.0, 3000.0, 200.0, 0.0),
        (3, 100_000.0, 0.0, 3000.0, 200.0, 0.0), (4, 101_000.0, 0.0, 3000.0, 200.0, 0.0),
        (5, 100_500.0, 800.0, 3000.0, 200.0, 0.0), (6, 50_000.0, 0.0, 3000.0, 200.0, 0.0),
        (1, 0.0, 0.0, 3000.0, 200.0, 0.0, 1),
    ])
    out = cluster(f, ALWAYS)
    s = cluster_summary(out)
    assert s.select("n_clusters", "mean_size", "max_size", "targets_clustered").rows() == [(2, 2.5, 3, 5)]
    s = cluster_summary(out, f)
    assert s.select("n_clusters", "targets_clustered", "n_targets", "n_marks").rows() == [
        (2, 5, 6, 3), (0, 0, 1, 1),
    ]


def _traffic(n_epochs: int = 50, n_form: int = 100, size: int = 4, seed: int = 1) -> pl.DataFrame:
    """n_form formations of ``size`` on a 30 km grid, 1 s epochs, never closer than 15 km."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n_form)))
    centre = np.column_stack([(np.arange(n_form) % side) * 30_000.0, (np.arange(n_form) // side) * 30_000.0])
    vel = rng.uniform(-100.0, 100.0, (n_form, 2))
    offs = rng.uniform(-500.0, 500.0, (n_form, size, 2))
    jitter = rng.uniform(-10.0, 10.0, (n_form, size, 2))
    t = np.arange(n_epochs, dtype=float)
    pos = centre[None, :, None, :] + offs[None] + vel[None, :, None, :] * t[:, None, None, None]
    v = np.broadcast_to(vel[:, None, :] + jitter, pos.shape)
    n = n_form * size
    tid = rng.permutation(n).astype(np.uint64) + 1
    return pl.DataFrame({
        "run": pl.Series(np.zeros(n_epochs * n, dtype=np.uint32)),
        "epoch": pl.Series(np.datetime64("2024-03-01T12:00:00", "us")
                           + np.repeat(t * 1e6, n).astype("timedelta64[us]")).dt.replace_time_zone("UTC"),
        "method": ["mean"] * (n_epochs * n),
        "target_id": np.tile(tid, n_epochs),
        "x_m": pos[..., 0].ravel(), "y_m": pos[..., 1].ravel(),
        "z_m": np.full(n_epochs * n, 3000.0),
        "vx_mps": v[..., 0].ravel(), "vy_mps": v[..., 1].ravel(),
        "vz_mps": np.zeros(n_epochs * n),
    })


@pytest.mark.parametrize("algorithm", ["dbscan", "strobe"])
def test_performance_50_epochs_400_targets(algorithm):
    f = _traffic()
    cfg = ClusteringConfig(algorithm=algorithm, half_sizes_m=(3000.0, 3000.0, 500.0))
    cluster(f.head(800), cfg)                            # warm-up (imports, JIT-free caches)
    t0 = time.perf_counter()
    out = cluster(f, cfg)
    elapsed = time.perf_counter() - t0
    assert elapsed < 5.0, elapsed
    # every formation is one cluster of 4 at every epoch, with a fixed id and lead
    assert out.height == 50 * 100
    assert set(out["count"].to_list()) == {4}
    assert out["cluster_id"].n_unique() == 100
    assert out.group_by("cluster_id").agg(pl.col("lead_target_id").n_unique())["lead_target_id"].max() == 1
    s = cluster_summary(out, f)
    assert set(s["n_marks"].to_list()) == {100}


def test_parallel_greedy_equals_sequential_greedy():
    from tertiary.stages.clustering import _greedy_leads

    rng = np.random.default_rng(7)
    for _ in range(50):
        n = int(rng.integers(1, 60))
        adj = np.triu(rng.random((n, n)) < rng.uniform(0.02, 0.5), 1)
        pairs = np.argwhere(adj)
        rank = rng.permutation(n)
        expect = np.full(n, -1)
        for i in np.argsort(rank):                     # reference: the sequential greedy
            if expect[i] < 0:
                expect[i] = i
                nb = np.r_[pairs[pairs[:, 0] == i, 1], pairs[pairs[:, 1] == i, 0]]
                expect[nb[expect[nb] < 0]] = i
        np.testing.assert_array_equal(_greedy_leads(rank, pairs.reshape(-1, 2)), expect)


@pytest.mark.parametrize("algorithm", ["dbscan", "strobe"])
def test_invariants_on_random_traffic(algorithm):
    rng = np.random.default_rng(3)
    rows = []
    for t in range(5):
        for i in range(120):
            x, y = rng.uniform(0, 40_000, 2)
            rows.append((i, x, y, rng.uniform(2000, 3000), *rng.choice([-200.0, 0.0, 200.0], 2) + rng.uniform(-20, 20, 2), t, t % 2))
    f = fused(rows)
    cfg = ClusteringConfig(algorithm=algorithm, display_capacity=100)
    out = cluster(f, cfg)
    assert out.height > 0
    validate(out, "clusters")
    m = (
        out.explode("members").rename({"members": "target_id"})
        .join(f, on=["run", "epoch", "method", "target_id"])
        .join(f.rename(lambda c: c if c in ("run", "epoch", "method") else "lead_" + c),
              on=["run", "epoch", "method", "lead_target_id"])
    )
    assert m.height == out["count"].sum()
    assert not m.select(pl.struct("run", "epoch", "method", "target_id").is_duplicated().any()).item()
    assert ((m["vx_mps"] - m["lead_vx_mps"]).abs() <= 30.0).all()
    assert ((m["vy_mps"] - m["lead_vy_mps"]).abs() <= 30.0).all()
    if algorithm == "strobe":
        assert ((m["x_m"] - m["lead_x_m"]).abs() <= 5000.0).all()
        assert ((m["z_m"] - m["lead_z_m"]).abs() <= 500.0).all()
    assert (out["count"] >= 2).all()
    assert (out["members"].list.len() == out["count"]).all()
    assert out.select(pl.col("members").list.contains(pl.col("lead_target_id")).all()).item()


# --------------------------------------------------------------------------- oracle: scikit-learn DBSCAN

from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.cluster import DBSCAN

from tertiary.stages.clustering import _single_linkage


def _partition(labels: np.ndarray) -> set[frozenset[int]]:
    """Clusters as sets of point indices (noise points each alone), independent of label values."""
    out: dict[int, set[int]] = {}
    for i, lab in enumerate(labels):
        out.setdefault(int(lab) if lab >= 0 else -1 - i, set()).add(i)
    return {frozenset(s) for s in out.values()}


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 120), spread=st.floats(500.0, 40_000.0), seed=st.integers(0, 2**31 - 1))
def test_single_linkage_equals_sklearn_dbscan(n, spread, seed):
    """The KD-tree ε-graph components are exactly scikit-learn's DBSCAN with min_samples=2."""
    rng = np.random.default_rng(seed)
    feats = rng.uniform(0.0, spread, (n, 3))
    eps = 5000.0
    ours = _single_linkage(feats, eps)
    ref = DBSCAN(eps=eps, min_samples=2).fit(feats).labels_
    assert _partition(ours) == _partition(ref)
    assert np.array_equal(ours < 0, ref < 0)
