"""Tests of stage 5, fusion: hand computations, worked numbers, properties."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import hypothesis.extra.numpy as hnp
import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tertiary.core.units import STATE
from tertiary.stages import fusion
from tertiary.stages.fusion import METHODS, FusionConfig, Layout, fuse
from tertiary.contract import FUSED_EXTRA, TABLES

T0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
SIGMA_R = 50.0
LN3 = np.log(3.0)


def report(run=0, k=0, target=1, radar=1, x=(0, 0, 0, 0, 0, 0), cov=None, res=0.0,
           var=None, fresh=True, nominal=(1.0, 1.0, 1.0), track=None) -> dict:
    """One input row; ``cov`` a 6-vector (diagonal) or 6×6; ``var`` defaults to σ_r² + 100."""
    c = np.diag(np.ones(6)) if cov is None else np.asarray(cov, float)
    c = np.diag(c) if c.ndim == 1 else c
    return {
        "run": run, "epoch": T0 + timedelta(seconds=k), "target_id": target, "radar_id": radar,
        "local_track_id": radar if track is None else track, "report_id": 1000 * k + 10 * target + radar,
        **dict(zip(STATE, map(float, x))), "cov": c.reshape(36).tolist(),
        "res_range_m": res, "res_range_var_m2": SIGMA_R**2 + 100.0 if var is None else var,
        "fresh": fresh, "nominal_var": list(map(float, nominal)),
    }


SCHEMA = {
    "run": pl.UInt32, "epoch": pl.Datetime("us", "UTC"), "target_id": pl.UInt64,
    "radar_id": pl.UInt32, "local_track_id": pl.UInt32, "report_id": pl.UInt64,
    **dict.fromkeys(STATE, pl.Float64), "cov": pl.Array(pl.Float64, 36),
    "res_range_m": pl.Float64, "res_range_var_m2": pl.Float64, "fresh": pl.Boolean,
    "nominal_var": pl.Array(pl.Float64, 3),
}


def frame(rows: list[dict]) -> pl.DataFrame:
    return pl.DataFrame(rows, schema=SCHEMA).sort(["run", "epoch", "target_id", "radar_id"])


RADARS = pl.DataFrame({"radar_id": [1, 2, 3, 4], "sigma_range_m": [SIGMA_R] * 4},
                      schema={"radar_id": pl.UInt32, "sigma_range_m": pl.Float64})


def weights_of(out: pl.DataFrame, method: str, target: int = 1, run: int = 0) -> list[list[float]]:
    sel = out.filter((pl.col("method") == method) & (pl.col("target_id") == target) & (pl.col("run") == run))
    return sel.sort("epoch")["weights"].to_list()


def state_of(out: pl.DataFrame, method: str, target: int = 1, k: int = 0) -> np.ndarray:
    sel = out.filter((pl.col("method") == method) & (pl.col("target_id") == target)
                     & (pl.col("epoch") == T0 + timedelta(seconds=k)))
    assert sel.height == 1
    return sel.select(STATE).to_numpy()[0], np.asarray(sel["cov"][0]).reshape(6, 6)


def ratio_rows(n_epochs: int, res2: float = np.sqrt(2 * 100.0 * LN3), target: int = 1, **kw) -> list[dict]:
    """Two radars with D_1 = D_2 = 100 and ΔD chosen so that L_1/L_2 = 3 (L ∝ (0.3, 0.1))."""
    return [report(k=k, target=target, radar=r, res=(0.0 if r == 1 else res2), **kw)
            for k in range(n_epochs) for r in (1, 2)]


# ---------------------------------------------------------------------------
# API and table shape
# ---------------------------------------------------------------------------


def test_unknown_method_lists_methods():
    with pytest.raises(ValueError, match="arithmetic.*covariance_intersection"):
        fuse(frame([report()]), RADARS, methods=["median"])


def test_output_schema_and_rows():
    rows = [report(k=k, target=t, radar=r, x=np.full(6, r), cov=np.full(6, r))
            for k in range(2) for t in (1, 2) for r in ((1, 2, 3) if t == 1 else (2,))]
    out = fuse(frame(rows), RADARS)
    assert dict(out.schema) == {**TABLES["fused"].columns, **FUSED_EXTRA}
    assert out.height == 4 * len(METHODS)
    assert out.filter(pl.col("target_id") == 1)["radar_ids"].to_list()[0] == [1, 2, 3]
    assert set(out["n_sources"].to_list()) == {1, 3}


def test_empty_input():
    out = fuse(frame([]), RADARS)
    assert out.height == 0 and dict(out.schema) == {**TABLES["fused"].columns, **FUSED_EXTRA}


def test_single_source_unchanged():
    c = np.diag([4.0, 5, 6, 1, 2, 3])
    c[0, 1] = c[1, 0] = 0.5
    out = fuse(frame([report(x=(1, 2, 3, 4, 5, 6), cov=c, res=np.nan)]), RADARS)
    for m in METHODS:
        x, p = state_of(out, m)
        np.testing.assert_array_equal(x, [1, 2, 3, 4, 5, 6])
        np.testing.assert_array_equal(p, c)
        assert weights_of(out, m) == [[1.0]]


# ---------------------------------------------------------------------------
# hand computations
# ---------------------------------------------------------------------------


def hand_frame() -> pl.DataFrame:
    """Target 1: radars 1, 2, 3; target 2: radars 1, 2; two epochs."""
    rows = []
    for k in range(2):
        for r, (xv, cv, nv) in {1: (10.0, 1.0, (1, 2, 4)), 2: (20.0, 2.0, (2, 2, 1)),
                                3: (40.0, 4.0, (4, 2, 1))}.items():
            rows.append(report(k=k, target=1, radar=r, x=np.full(6, xv + k), cov=np.full(6, cv), nominal=nv))
            if r < 3:
                rows.append(report(k=k, target=2, radar=r, x=np.full(6, -xv), cov=np.full(6, cv), nominal=nv))
    return frame(rows)


def test_arithmetic_by_hand():
    out = fuse(hand_frame(), RADARS, ["arithmetic"])
    x, p = state_of(out, "arithmetic", target=1, k=1)
    np.testing.assert_allclose(x, np.full(6, (11 + 21 + 41) / 3))
    np.testing.assert_allclose(p, np.diag(np.full(6, (1 + 2 + 4) / 9)))
    x, p = state_of(out, "arithmetic", target=2, k=0)
    np.testing.assert_allclose(x, np.full(6, -15.0))
    np.testing.assert_allclose(p, np.diag(np.full(6, 3 / 4)))
    assert weights_of(out, "arithmetic", 1)[0] == pytest.approx([1 / 3] * 3)


def test_apriori_by_hand():
    out = fuse(hand_frame(), RADARS, ["apriori"])
    # per coordinate: σ² = (1, 2, 4), (2, 2, 2), (4, 1, 1) for radars 1, 2, 3
    b = np.array([[1, 1 / 2, 1 / 4], [1 / 2, 1 / 2, 1 / 2], [1 / 4, 1, 1]]).T  # rows: radar
    b = b / b.sum(axis=0)
    xs, cs = np.array([10.0, 20, 40]), np.array([1.0, 2, 4])
    x, p = state_of(out, "apriori", target=1, k=0)
    np.testing.assert_allclose(x[:3], b.T @ xs)
    np.testing.assert_allclose(x[3:], x[:3])  # velocity uses its position axis's weight
    np.testing.assert_allclose(np.diag(p)[:3], (b**2).T @ cs)
    np.testing.assert_allclose(np.diag(p)[3:], np.diag(p)[:3])
    assert weights_of(out, "apriori", 1)[0] == pytest.approx(b.mean(axis=1).tolist())
    # two radars, (4.4): b_1 = σ_2²/(σ_1² + σ_2²) on x
    x, _ = state_of(out, "apriori", target=2, k=0)
    assert x[0] == pytest.approx((2 * -10 + 1 * -20) / 3)


def test_information_two_independent_closed_form():
    out = fuse(hand_frame(), RADARS, ["information"])
    x, p = state_of(out, "information", target=2, k=0)
    # scalar per coordinate: (x1/σ1² + x2/σ2²)/(1/σ1² + 1/σ2²), σ² = 1/(1/σ1² + 1/σ2²)
    np.testing.assert_allclose(x, np.full(6, (-10 / 1 - 20 / 2) / 1.5))
    np.testing.assert_allclose(p, np.eye(6) / 1.5)
    assert weights_of(out, "information", 2)[0] == pytest.approx([2 / 3, 1 / 3])


def random_spd(rng: np.random.Generator, n: int, scale=(1e4, 1e4, 1e4, 1, 1, 1)) -> np.ndarray:
    a = rng.normal(size=(n, 6, 6))
    c = a @ a.transpose(0, 2, 1) + 0.5 * np.eye(6)
    s = np.sqrt(np.asarray(scale))
    return c * s[:, None] * s[None, :]


def test_information_full_covariance_matches_direct_inverse():
    rng = np.random.default_rng(1)
    c, x = random_spd(rng, 3), rng.normal(size=(3, 6)) * 100
    res = fusion.fuse_information(x, c, np.array([0]))
    info = np.linalg.inv(c)
    p = np.linalg.inv(info.sum(axis=0))
    np.testing.assert_allclose(res.cov[0], p, rtol=1e-9, atol=1e-12 * np.abs(p).max())
    np.testing.assert_allclose(res.x[0], p @ np.einsum("nij,nj->i", info, x), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.weights, [np.trace(p @ i) / 6 for i in info], rtol=1e-9)


def test_ci_identical_covariances_returns_that_covariance():
    rng = np.random.default_rng(2)
    c = random_spd(rng, 1)[0]
    for k in (2, 3):
        for objective in ("trace", "det"):
            res = fusion.fuse_covariance_intersection(
                rng.normal(size=(k, 6)), np.repeat(c[None], k, 0), np.array([0]), objective)
            np.testing.assert_allclose(res.cov[0], c, rtol=1e-9)
            assert res.weights.sum() == pytest.approx(1.0, abs=1e-12)
            if k == 2:  # flat objective: ties go to equal weights
                np.testing.assert_array_equal(res.weights, [0.5, 0.5])


@pytest.mark.parametrize("objective", ["trace", "det"])
def test_ci_two_sources_optimal_and_consistent(objective):
    rng = np.random.default_rng(3)
    g = 20
    c = random_spd(rng, 2 * g)
    x = rng.normal(size=(2 * g, 6)) * 100
    starts = np.arange(0, 2 * g, 2)
    ci = fusion.fuse_covariance_intersection(x, c, starts, objective)
    info = fusion.fuse_information(x, c, starts)
    grid = np.linspace(0, 1, 2001)
    for i in range(g):
        i1, i2 = np.linalg.inv(c[2 * i]), np.linalg.inv(c[2 * i + 1])
        crit = np.linalg.det if objective == "det" else np.trace
        vals = [crit(np.linalg.inv(w * i1 + (1 - w) * i2)) for w in grid]
        w = ci.weights[2 * i]
        assert crit(ci.cov[i]) <= min(vals) * (1 + 1e-9)
        assert ci.weights[2 * i + 1] == pytest.approx(1 - w)
        np.testing.assert_allclose(ci.cov[i], np.linalg.inv(w * i1 + (1 - w) * i2), rtol=1e-7)
        np.testing.assert_allclose(
            ci.x[i], ci.cov[i] @ (w * i1 @ x[2 * i] + (1 - w) * i2 @ x[2 * i + 1]), rtol=1e-7, atol=1e-6)
        # consistency: P_CI − P_information is positive semi-definite
        d = np.linalg.eigvalsh(ci.cov[i] - info.cov[i])
        assert d.min() >= -1e-9 * np.abs(ci.cov[i]).max()


def test_ci_three_sources_fast_weights():
    rng = np.random.default_rng(4)
    c, x = random_spd(rng, 3), rng.normal(size=(3, 6))
    res = fusion.fuse_covariance_intersection(x, c, np.array([0]))
    w = 1 / np.trace(c, axis1=1, axis2=2)
    np.testing.assert_allclose(res.weights, w / w.sum())
    info = np.linalg.inv(c) * (w / w.sum())[:, None, None]
    np.testing.assert_allclose(res.cov[0], np.linalg.inv(info.sum(0)), rtol=1e-9)


# ---------------------------------------------------------------------------
# a-posteriori weights: worked numbers
# ---------------------------------------------------------------------------


def b1_series(out: pl.DataFrame, method: str, target: int = 1) -> list[float]:
    return [w[0] for w in weights_of(out, method, target)]


def test_seed_period_two_oscillation():
    out = fuse(frame(ratio_rows(6)), RADARS, ["aposteriori_seed"])
    np.testing.assert_allclose(b1_series(out, "aposteriori_seed"), [0.75, 0.5] * 3, rtol=1e-12)


def test_seed_fixed_point_under_equal_likelihoods():
    out = fuse(frame(ratio_rows(4, res2=0.0)), RADARS, ["aposteriori_seed", "aposteriori"])
    for m in ("aposteriori_seed", "aposteriori"):
        np.testing.assert_allclose(b1_series(out, m), [0.5] * 4, rtol=1e-12)


def test_markov_numbers_of_digest():
    s = SIGMA_R**2 + 100.0  # per-step S_n(k): ΔD chosen for L_1/L_2 = 3 at this variance
    rows = frame(ratio_rows(40, res2=np.sqrt(2 * s * LN3)))
    b = b1_series(fuse(rows, RADARS, ["aposteriori"]), "aposteriori")
    np.testing.assert_allclose(b[:3], [0.75, 0.8878, 0.944], atol=6e-4)
    fixed = (1.6 + np.sqrt(1.6**2 + 4 * 1.8 * 0.15)) / 3.6  # b = 3c/(2c+1), c = 0.9 b + 0.05
    assert b[-1] == pytest.approx(fixed, abs=1e-9) and fixed == pytest.approx(0.974, abs=5e-4)
    b = b1_series(fuse(rows, RADARS, ["aposteriori"], FusionConfig(p_stay=1.0)), "aposteriori")
    np.testing.assert_allclose(b[:4], [0.75, 0.9, 27 / 28, 81 / 82], rtol=1e-12)  # 3^k/(3^k + 1)
    b = b1_series(fuse(rows, RADARS, ["aposteriori"], FusionConfig(p_stay=0.0, b_min=0)), "aposteriori")
    np.testing.assert_allclose(b[:4], [0.75, 0.5, 0.75, 0.5], rtol=1e-12)  # p_stay = 0 is the seed


def test_markov_uses_per_step_variance_seed_uses_fixed_d():
    # step 1 fixes D = var − σ² = 100; later the reported S grows but the seed ignores it
    rows = ratio_rows(3)
    for r in rows:
        if r["epoch"] > T0:
            r["res_range_var_m2"] = 1e6
    out = fuse(frame(rows), RADARS, ["aposteriori_seed", "aposteriori"])
    np.testing.assert_allclose(b1_series(out, "aposteriori_seed"), [0.75, 0.5, 0.75], rtol=1e-12)
    b = b1_series(out, "aposteriori")
    lr = np.exp(-200 * LN3 / 2e6)  # L_2/L_1 at S = 1e6 (nearly equal)
    c1 = 0.95 * b[0] + 0.05 * (1 - b[0])
    assert b[1] == pytest.approx(c1 / (c1 + lr * (1 - c1)), rel=1e-12)


def test_seed_three_radars_by_hand():
    d = 100.0
    res = {1: 0.0, 2: 10.0, 3: 20.0}
    rows = [report(k=k, radar=r, res=res[r]) for k in range(3) for r in (1, 2, 3)]
    out = fuse(frame(rows), RADARS, ["aposteriori_seed"])
    lik = np.array([np.exp(-res[r] ** 2 / (2 * d)) for r in (1, 2, 3)])
    b, expected = np.full(3, 1 / 3), []
    for _ in range(3):
        b = lik * (1 - b) / np.sum(lik * (1 - b))
        expected.append(b)
    np.testing.assert_allclose(weights_of(out, "aposteriori_seed"), expected, rtol=1e-12)


def test_markov_three_radars_by_hand():
    res = {1: 0.0, 2: 10.0, 3: 20.0}
    var = SIGMA_R**2 + 100.0
    rows = [report(k=k, radar=r, res=res[r]) for k in range(3) for r in (1, 2, 3)]
    out = fuse(frame(rows), RADARS, ["aposteriori"], FusionConfig(p_stay=0.9, b_min=0.2))
    lik = np.array([np.exp(-res[r] ** 2 / (2 * var)) for r in (1, 2, 3)])
    pi = np.full((3, 3), 0.05) + np.eye(3) * 0.85
    b, expected = np.full(3, 1 / 3), []
    for _ in range(3):
        b = lik * (pi.T @ b)
        b = np.maximum(b / b.sum(), 0.2)
        expected.append(b / b.sum())
        b = expected[-1]
    np.testing.assert_allclose(weights_of(out, "aposteriori"), expected, rtol=1e-12)
    x, p = state_of(fuse(frame(rows), RADARS, ["aposteriori"], FusionConfig(p_stay=0.9, b_min=0.2)),
                    "aposteriori", k=0)
    np.testing.assert_allclose(p, np.eye(6) * np.sum(expected[0] ** 2))


def test_seed_fixed_d_per_local_track():
    rows = frame([report(k=k, radar=1, res=np.nan if k == 0 else 1.0, var=np.nan if k == 0 else SIGMA_R**2 + 10 * k)
                  for k in range(3)] + [report(k=k, radar=2, track=7, var=SIGMA_R**2 + 5 + k) for k in range(3)])
    d = fusion.seed_fixed_variance(rows, RADARS)
    np.testing.assert_allclose(d, [10, 5, 10, 5, 10, 5])  # radar 1's first finite row is k = 1


@pytest.mark.parametrize(("method", "var"), [("aposteriori_seed", 100.0), ("aposteriori", SIGMA_R**2 + 100)])
def test_underflowing_likelihoods_stay_finite(method, var):
    # ΔD = 1e4, 1e4 + 1: both L underflow in the linear domain, L_1/L_2 = exp(20001/(2 var))
    rows = frame([report(k=0, radar=1, res=1e4), report(k=0, radar=2, res=1e4 + 1)])
    w = weights_of(fuse(rows, RADARS, [method], FusionConfig(b_min=0)), method)[0]
    a = 20001 / (2 * var)
    assert w == pytest.approx([1 / (1 + np.exp(-a)), 1 / (1 + np.exp(a))], rel=1e-9)


# ---------------------------------------------------------------------------
# recursion continuity: fresh flag, radar sets, runs
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["aposteriori_seed", "aposteriori"])
def test_non_fresh_rows_keep_weights(method):
    rows = ratio_rows(4)
    for r in rows:
        if r["epoch"] == T0 + timedelta(seconds=2):
            r["fresh"] = False
    b = b1_series(fuse(frame(rows), RADARS, [method]), method)
    assert b[2] == b[1]
    # only radar 2 fresh at k = 2: with two radars its mass is its own b(k−1), so no change
    rows = ratio_rows(4)
    for r in rows:
        if r["epoch"] == T0 + timedelta(seconds=2) and r["radar_id"] == 1:
            r["fresh"] = False
    b = b1_series(fuse(frame(rows), RADARS, [method]), method)
    assert b[2] == pytest.approx(b[1], rel=1e-14)


def test_partial_fresh_three_radars_keeps_stale_weight():
    rows = [report(k=k, radar=r, res=[0.0, 10.0, 20.0][r - 1], fresh=(k == 0 or r != 3))
            for k in range(2) for r in (1, 2, 3)]
    out = fuse(frame(rows), RADARS, ["aposteriori_seed", "aposteriori"])
    for m in ("aposteriori_seed", "aposteriori"):
        w0, w1 = np.array(weights_of(out, m))
        assert w1[2] == w0[2]
        assert w1.sum() == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("method", ["aposteriori_seed", "aposteriori"])
def test_radar_appearing_restarts_at_one_over_n(method):
    # k = 0, 1: radars 1, 2; k = 2: radar 3 joins with equal likelihoods for all → prior 1/3
    rows = ratio_rows(2)
    rows += [report(k=2, radar=r, res=0.0) for r in (1, 2, 3)]
    rows += [report(k=3, radar=r, res=0.0) for r in (1, 2, 3)]
    w = weights_of(fuse(frame(rows), RADARS, [method]), method)
    assert w[0][0] > 0.5 and w[1][0] != w[0][0]  # the two-radar history was informative
    np.testing.assert_allclose(w[2], [1 / 3] * 3, rtol=1e-12)
    np.testing.assert_allclose(w[3], [1 / 3] * 3, rtol=1e-12)


def test_set_change_and_return_restart():
    # radars {1,2} → {1} → {1,2}: the third epoch restarts at 1/2, giving 0.75 again
    rows = ratio_rows(1) + [report(k=1, radar=1)] + [
        report(k=2, radar=r, res=(0.0 if r == 1 else np.sqrt(200 * LN3))) for r in (1, 2)]
    w = weights_of(fuse(frame(rows), RADARS, ["aposteriori_seed"]), "aposteriori_seed")
    assert [v[0] for v in w] == pytest.approx([0.75, 1.0, 0.75])


def test_runs_and_targets_do_not_share_state():
    rows = ratio_rows(3, target=1) + ratio_rows(3, target=2, res2=0.0)
    rows += [{**r, "run": 1} for r in ratio_rows(3, target=1)[2:]]  # run 1 starts one epoch later
    out = fuse(frame(rows), RADARS, ["aposteriori_seed"])
    np.testing.assert_allclose(b1_series(out, "aposteriori_seed", 1), [0.75, 0.5, 0.75])
    np.testing.assert_allclose(b1_series(out, "aposteriori_seed", 2), [0.5] * 3)
    run1 = [w[0] for w in weights_of(out, "aposteriori_seed", 1, run=1)]
    np.testing.assert_allclose(run1, [0.75, 0.5])


def test_layout_links():
    rows = frame(ratio_rows(2) + [report(k=2, radar=1)])
    lay = fusion.layout(rows)
    np.testing.assert_array_equal(lay.starts, [0, 2, 4])
    np.testing.assert_array_equal(lay.prev_row, [-1, -1, 0, 1, -1])
    np.testing.assert_array_equal(lay.level, [0, 1, 2])


def test_duplicate_radar_in_group_rejected():
    with pytest.raises(ValueError, match="two reports"):
        fuse(frame([report(radar=1), {**report(radar=1), "report_id": 99}]), RADARS)


def test_kernels_on_hand_arrays():
    x = np.array([[0.0] * 6, [3.0] * 6, [5.0] * 6])
    c = np.stack([np.eye(6), 2 * np.eye(6), np.eye(6)])
    lay = Layout.from_starts(np.array([0, 2]), 3)
    res = fusion.fuse_arithmetic(x, c, lay.starts)
    np.testing.assert_allclose(res.x, [[1.5] * 6, [5.0] * 6])
    np.testing.assert_allclose(res.weights, [0.5, 0.5, 1.0])
    w = fusion.seed_weights(np.array([0.0, np.sqrt(2 * LN3), 7.0]), np.ones(3), np.ones(3, bool), lay)
    np.testing.assert_allclose(w, [0.75, 0.25, 1.0])


def test_config_validation():
    with pytest.raises(ValueError):
        FusionConfig(p_stay=1.5)
    with pytest.raises(ValueError):
        FusionConfig(ci_objective="max")


# ---------------------------------------------------------------------------
# properties
# ---------------------------------------------------------------------------

finite = st.floats(-1e4, 1e4, allow_nan=False)


@settings(max_examples=25, deadline=None)
@given(k=st.integers(2, 4), x=hnp.arrays(np.float64, 6, elements=finite),
       seed=st.integers(0, 2**31), res=st.floats(-100, 100))
def test_identical_reports_return_that_report(k, x, seed, res):
    c = random_spd(np.random.default_rng(seed), 1)[0]
    rows = [report(k=e, radar=r, x=x, cov=c, res=res) for e in range(2) for r in range(1, k + 1)]
    out = fuse(frame(rows), RADARS)
    for m in METHODS:
        for e in range(2):
            xf, pf = state_of(out, m, k=e)
            np.testing.assert_allclose(xf, x, rtol=1e-9, atol=1e-9)
            if m == "covariance_intersection":
                np.testing.assert_allclose(pf, c, rtol=1e-7, atol=1e-9 * np.abs(c).max())


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), n_targets=st.integers(1, 4), n_epochs=st.integers(1, 3))
def test_weights_sum_to_one(seed, n_targets, n_epochs):
    rng = np.random.default_rng(seed)
    rows = []
    for e in range(n_epochs):
        for t in range(1, n_targets + 1):
            radars = sorted(rng.choice([1, 2, 3, 4], size=rng.integers(1, 5), replace=False))
            covs = random_spd(rng, len(radars))
            for r, c in zip(radars, covs):
                rows.append(report(
                    k=e, target=t, radar=int(r), x=rng.normal(size=6) * 1e3, cov=c,
                    res=rng.normal() * rng.choice([1, 100, 1e4]) if rng.random() > 0.1 else np.nan,
                    var=SIGMA_R**2 + rng.uniform(1, 1e4), fresh=bool(rng.random() > 0.2),
                    nominal=rng.uniform(1, 1e4, 3)))
    out = fuse(frame(rows), RADARS)
    sums = out["weights"].list.sum().to_numpy()
    np.testing.assert_allclose(sums, 1.0, atol=1e-12, rtol=0)
    assert (out["weights"].list.len() == out["n_sources"]).all()
    assert np.isfinite(out.select(STATE).to_numpy()).all()


# ---------------------------------------------------------------------------
# Bar-Shalom–Campo (common process noise) fusion
# ---------------------------------------------------------------------------


def test_bar_shalom_campo_two_sources_by_hand():
    """Diagonal C₁ = 4 I, C₂ = 9 I, ρ = 0.5: P₁₂ = ρ·2·3 = 3 I. (BC):
    x = x₁ + (4 − 3)/(4 + 9 − 6)(x₂ − x₁) = x₁ + (x₂ − x₁)/7, P = 4 − 1·1/7 = 27/7 per axis;
    weights 6/7 and 1/7."""
    x = np.array([np.zeros(6), np.full(6, 7.0)])
    cov = np.array([4.0 * np.eye(6), 9.0 * np.eye(6)])
    out = fusion.fuse_bar_shalom_campo(x, cov, np.array([0]), rho=0.5)
    np.testing.assert_allclose(out.x[0], np.full(6, 1.0), atol=1e-12)
    np.testing.assert_allclose(out.cov[0], 27.0 / 7.0 * np.eye(6), atol=1e-12)
    np.testing.assert_allclose(out.weights, [6 / 7, 1 / 7], atol=1e-12)
    # the same pair with ρ = 0 is information fusion: P = 36/13, x = 4·7/13
    info = fusion.fuse_bar_shalom_campo(x, cov, np.array([0]), rho=0.0)
    np.testing.assert_allclose(info.cov[0], 36.0 / 13.0 * np.eye(6), atol=1e-12)
    np.testing.assert_allclose(info.x[0], np.full(6, 28.0 / 13.0), atol=1e-12)


def _spd(rng, k=6):
    a = rng.normal(size=(k, k))
    return a @ a.T + np.eye(k)


def _sqrtm(c):
    w, v = np.linalg.eigh(c)
    return (v * np.sqrt(w)) @ v.T


def test_bar_shalom_campo_two_sources_full_matrices_match_formula():
    """Full covariances: the kernel equals the textbook (BC) expressions with P₁₂ = ρ C₁^½ C₂^½."""
    rng = np.random.default_rng(3)
    c1, c2, x1, x2, rho = _spd(rng), _spd(rng), rng.normal(size=6), rng.normal(size=6), 0.4
    p12 = rho * _sqrtm(c1) @ _sqrtm(c2)
    u = np.linalg.inv(c1 + c2 - p12 - p12.T)
    out = fusion.fuse_bar_shalom_campo(np.stack([x1, x2]), np.stack([c1, c2]), np.array([0]), rho)
    np.testing.assert_allclose(out.x[0], x1 + (c1 - p12) @ u @ (x2 - x1), atol=1e-9)
    np.testing.assert_allclose(out.cov[0], c1 - (c1 - p12) @ u @ (c1 - p12.T), atol=1e-9)


def test_bar_shalom_campo_n_sources_is_the_joint_blue():
    """Three sources: the closed form equals the BLUE (Hᵀ Σ⁻¹ H)⁻¹ Hᵀ Σ⁻¹ x̄ on the explicit
    18×18 joint covariance; a second group in the same call is fused independently."""
    rng = np.random.default_rng(5)
    cs = [_spd(rng) for _ in range(3)]
    xs = [rng.normal(size=6) * 10 for _ in range(3)]
    rho = 0.3
    s = [_sqrtm(c) for c in cs]
    sig = np.block([[cs[i] if i == j else rho * s[i] @ s[j] for j in range(3)] for i in range(3)])
    h = np.vstack([np.eye(6)] * 3)
    si = np.linalg.inv(sig)
    p = np.linalg.inv(h.T @ si @ h)
    x = p @ h.T @ si @ np.concatenate(xs)
    other = [_spd(rng) for _ in range(2)]
    out = fusion.fuse_bar_shalom_campo(np.stack(xs + [np.zeros(6), np.ones(6)]), np.stack(cs + other),
                                       np.array([0, 3]), rho)
    np.testing.assert_allclose(out.x[0], x, atol=1e-8)
    np.testing.assert_allclose(out.cov[0], p, atol=1e-8)
    np.testing.assert_allclose(out.weights[:3].sum(), 1.0)
    pair = fusion.fuse_bar_shalom_campo(np.stack([np.zeros(6), np.ones(6)]), np.stack(other), np.array([0]), rho)
    np.testing.assert_allclose(out.x[1], pair.x[0], atol=1e-12)


def test_bar_shalom_campo_through_fuse_and_bad_rho():
    rows = [report(target=1, radar=r, x=np.full(6, 7.0 * (r - 1)), cov=np.full(6, 4.0 if r == 1 else 9.0))
            for r in (1, 2)]
    out = fuse(frame(rows), RADARS, methods=["bar_shalom_campo"], cfg=FusionConfig(bc_rho=0.5))
    x, c = state_of(out, "bar_shalom_campo")
    np.testing.assert_allclose(x, np.full(6, 1.0), atol=1e-9)
    np.testing.assert_allclose(np.diag(c), np.full(6, 27.0 / 7.0), atol=1e-9)
    with pytest.raises(ValueError, match="bc_rho"):
        FusionConfig(bc_rho=1.0)


# ---------------------------------------------------------------------------
# freshness, plot-level measurement, tentative targets
# ---------------------------------------------------------------------------


def _with_plots(rows: list[dict], plots: dict[int, tuple], ages: dict[int, float]) -> pl.DataFrame:
    """``frame(rows)`` plus plot columns: ``plots[radar] = (z3, R 3×3)``, ``ages[radar]``."""
    f = frame(rows)
    rid = f["radar_id"].to_list()
    z = np.array([plots[r][0] for r in rid], float)
    rr = np.array([np.asarray(plots[r][1], float).reshape(9) for r in rid])
    return f.with_columns(
        *(pl.Series(c, z[:, i]) for i, c in enumerate(("plot_x_m", "plot_y_m", "plot_z_m"))),
        pl.Series("plot_cov", rr, dtype=pl.Array(pl.Float64, 9)),
        pl.Series("age_s", [float(ages[r]) for r in rid]))


def test_information_measurement_of_two_fresh_plots_by_hand():
    """R₁ = diag(100, 400, 900), R₂ = diag(400, 100, 900): R = diag(80, 80, 450),
    z = R (R₁⁻¹ z₁ + R₂⁻¹ z₂); both at age 0. The radars' velocities do not matter at d = 0."""
    rows = [report(radar=r, x=(0, 0, 0, 50.0 * r, 0, 0)) for r in (1, 2)]
    f = _with_plots(rows, {1: ((0, 0, 0), np.diag([100, 400, 900])), 2: ((10, 20, 30), np.diag([400, 100, 900]))},
                    {1: 0.0, 2: 0.0})
    out = fuse(f, RADARS, methods=["information", "arithmetic"])
    info = out.filter(pl.col("method") == "information")
    np.testing.assert_allclose(np.asarray(info["meas_cov"][0]).reshape(3, 3), np.diag([80.0, 80.0, 450.0]))
    np.testing.assert_allclose(info.select("meas_x_m", "meas_y_m", "meas_z_m").row(0), [2.0, 16.0, 15.0])
    ari = out.filter(pl.col("method") == "arithmetic")
    np.testing.assert_allclose(ari.select("meas_x_m", "meas_y_m", "meas_z_m").row(0), [5.0, 10.0, 15.0])
    np.testing.assert_allclose(np.asarray(ari["meas_cov"][0]).reshape(3, 3), np.diag([125.0, 125.0, 450.0]))
    assert info["n_fresh"][0] == 2 and info["age_s"][0] == 0.0


def test_measurement_uses_only_fresh_plots_moved_to_the_newest():
    """Radar 2's plot is older by 2 s (age 3 vs 1): moved by its velocity (10, 0, 0) m/s × 2 s
    and its variance grown by 2² P_vv; radar 3's row is a re-extrapolation (not fresh): unused.
    A group with no fresh row has no measurement."""
    pvv = np.diag([1.0, 1, 1, 4.0, 4.0, 4.0])
    rows = [report(radar=1, x=(0, 0, 0, 0, 0, 0)), report(radar=2, x=(0, 0, 0, 10.0, 0, 0), cov=pvv),
            report(radar=3, fresh=False), report(k=1, radar=1, fresh=False)]
    plots = {1: ((0, 0, 0), 100 * np.eye(3)), 2: ((0, 0, 0), 100 * np.eye(3)), 3: ((1e4, 0, 0), np.eye(3))}
    f = _with_plots(rows, plots, {1: 1.0, 2: 3.0, 3: 0.5})
    out = fuse(f, RADARS, methods=["information"]).sort("epoch")
    first = out.row(0, named=True)
    assert first["n_fresh"] == 2 and first["age_s"] == pytest.approx(1.0)   # the newest fresh plot
    r2 = 100 + 4 * 4.0                                     # 116 on each axis for radar 2
    r = 1 / (1 / 100 + 1 / r2)
    np.testing.assert_allclose(np.asarray(first["meas_cov"]).reshape(3, 3), r * np.eye(3))
    assert first["meas_x_m"] == pytest.approx(r * 20.0 / r2)
    second = out.row(1, named=True)
    assert second["n_fresh"] == 0 and second["meas_x_m"] is None and second["meas_cov"] is None


def test_measurement_age_is_the_fresh_plots_reference():
    """With only fresh rows, ``age_s`` is the newest plot's age (the measurement time)."""
    rows = [report(radar=1), report(radar=2)]
    f = _with_plots(rows, {1: ((0, 0, 0), np.eye(3)), 2: ((0, 0, 0), np.eye(3))}, {1: 2.0, 2: 0.7})
    out = fuse(f, RADARS, methods=["arithmetic"])
    assert out["age_s"][0] == pytest.approx(0.7)


def test_tentative_until_a_local_track_has_two_plots_then_confirmed_for_good():
    """Target 1: one radar, local track 5, plots at k = 0 (fresh), k = 1 (re-extrapolation),
    k = 2 (second plot) then k = 3 (re-extrapolation): tentative at 0 and 1, confirmed from 2
    on. Target 2: a single clutter plot — tentative. Target 3: two radars at once — confirmed."""
    rows = [report(k=0, target=1, radar=1, track=5), report(k=1, target=1, radar=1, track=5, fresh=False),
            report(k=2, target=1, radar=1, track=5), report(k=3, target=1, radar=1, track=5, fresh=False),
            report(k=0, target=2, radar=2, track=9),
            report(k=0, target=3, radar=1, track=6), report(k=0, target=3, radar=2, track=7)]
    # every plot carries a transponder reply (a primary-only track needs more: the test below)
    f = frame(rows).with_columns(pl.lit("3C6586").alias("mode_s"))
    out = fuse(f, RADARS, methods=["arithmetic"])
    flags = {(t, k.second): v for t, k, v in out.select("target_id", "epoch", "tentative").iter_rows()}
    assert [flags[(1, k)] for k in range(4)] == [True, True, False, False]
    assert flags[(2, 0)] is True and flags[(3, 0)] is False


def test_a_primary_only_track_needs_a_third_plot_and_one_reply_lifts_it():
    """Clutter is primary-only: a track none of whose plots carried a transponder reply supports
    its target from its third plot (``min_plots_primary``), a track with a reply from its second,
    whichever plot the reply came on; the reply is carried across the window edge and a new life
    of the number forgets it. The fusion stage's default holds a primary-only pair tentative."""
    from datetime import datetime, timedelta, timezone
    t0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)

    def row(k, target, track, alt=None, gap=0.0):
        t = t0 + timedelta(seconds=4.0 * k + gap)
        return {"run": 0, "epoch": t, "target_id": target, "radar_id": 1, "local_track_id": track, "fresh": True,
                "time": t, "altitude_m": alt}
    rows = pl.DataFrame([row(k, 1, 7) for k in range(3)]                     # primary only
                        + [row(0, 2, 8, alt=3000.0), row(1, 2, 8)]           # a reply on the first plot
                        + [row(k, 3, 9, alt=3000.0 if k == 1 else None) for k in range(3)]
                        + [row(2, 4, 8, gap=120.0), row(3, 4, 8, gap=120.0)]   # track 8's next life: clutter
                        + [row(k, 5, 10, alt=float("nan")) for k in range(2)],  # a NaN altitude is no reply
                        schema_overrides={"run": pl.UInt32, "target_id": pl.UInt64, "radar_id": pl.UInt32,
                                          "local_track_id": pl.UInt32}).sort("epoch", "target_id")
    out, _ = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows, 2, 3)
    flags = {tg: out.filter(pl.col("target_id") == tg).sort("epoch")["tentative"].to_list() for tg in (1, 2, 3, 4, 5)}
    assert flags == {1: [True, True, False], 2: [True, False], 3: [True, False, False], 4: [True, True],
                     5: [True, True]}
    for cut in range(1, 4):
        edge = t0 + timedelta(seconds=4.0 * cut)
        a, st = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows.filter(pl.col("epoch") < edge), 2, 3)
        b, _ = fusion.confirm_targets_step(st, rows.filter(pl.col("epoch") >= edge), 2, 3)
        assert pl.concat([a, b]).sort("target_id", "epoch").equals(out.sort("target_id", "epoch"))
    same, _ = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows, 2)
    assert not same.filter(pl.col("target_id") == 1)["tentative"][1]       # None: one count for all
    pair = frame([report(k=0, target=1, radar=1, track=5), report(k=1, target=1, radar=1, track=5)])
    assert fuse(pair, RADARS, methods=["arithmetic"]).sort("epoch")["tentative"].to_list() == [True, True]


def test_confirmation_state_carries_across_windows():
    """The step function run on two windows with its carried state gives the flags of one run
    on the whole input (plot counts and confirmed targets cross the window edge)."""
    rows = [report(k=k, target=1, radar=1, track=5) for k in range(3)] + \
           [report(k=k, target=2, radar=2, track=8, fresh=(k == 0)) for k in range(3)]
    f = frame(rows)
    whole, _ = fusion.confirm_targets_step(fusion.ConfirmState.empty(), f)
    cut = T0 + timedelta(seconds=1)
    a, st = fusion.confirm_targets_step(fusion.ConfirmState.empty(), f.filter(pl.col("epoch") < cut))
    b, _ = fusion.confirm_targets_step(st, f.filter(pl.col("epoch") >= cut))
    assert pl.concat([a, b]).sort("target_id", "epoch").equals(whole.sort("target_id", "epoch"))
    assert whole.filter(pl.col("target_id") == 1)["tentative"].to_list() == [True, False, False]
    assert whole.filter(pl.col("target_id") == 2)["tentative"].to_list() == [True, True, True]


def test_plots_table_gives_the_same_measurement_as_plot_columns():
    """``fuse(..., plots=)`` joins the per-report plot table on (run, report_id) for the fresh
    rows: the same measurement as rows that carry the plot columns themselves."""
    rows = [report(radar=r, x=(0, 0, 0, 30.0 * r, 0, 0)) for r in (1, 2, 3)] + [report(k=1, radar=1, fresh=False)]
    plots = {1: ((0, 0, 0), np.diag([100, 400, 900])), 2: ((10, 20, 30), np.diag([400, 100, 900])),
             3: ((5, 5, 5), 200 * np.eye(3))}
    own = _with_plots(rows, plots, {1: 0.5, 2: 1.0, 3: 0.2})
    table = own.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64),
                       "plot_x_m", "plot_y_m", "plot_z_m", "plot_cov")
    a = fuse(own, RADARS, methods=["information", "aposteriori"])
    b = fuse(own.drop("plot_x_m", "plot_y_m", "plot_z_m", "plot_cov"), RADARS,
             methods=["information", "aposteriori"], plots=table)
    cols = ["meas_x_m", "meas_y_m", "meas_z_m", "meas_cov", "age_s", "n_fresh"]
    assert a.select(cols).equals(b.select(cols))
    assert a["meas_x_m"].null_count() == 2                        # the k = 1 group has no fresh plot
    none = fuse(own.drop("plot_x_m", "plot_y_m", "plot_z_m", "plot_cov"), RADARS, methods=["information"])
    assert none["meas_x_m"].null_count() == none.height and none["n_fresh"].to_list() == [3, 0]


def test_a_reused_track_number_starts_a_new_life_for_confirmation():
    """Radars reuse the numbers of ended tracks: a false plot under an old number after a
    silence must not inherit the old track's plots (it made ~3 000 clutter targets 'confirmed')."""
    from datetime import datetime, timedelta, timezone
    t0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)
    def row(k, target, gap=0.0):
        t = t0 + timedelta(seconds=4.0 * k + gap)
        return {"run": 0, "epoch": t, "target_id": target, "radar_id": 1, "local_track_id": 7, "fresh": True, "time": t}
    rows = pl.DataFrame([row(0, 1), row(1, 1), row(2, 1),            # an aircraft's track, 3 plots
                         row(3, 2, gap=120.0)],                       # 2 min later: a clutter plot, same number
                        schema_overrides={"run": pl.UInt32, "target_id": pl.UInt64, "radar_id": pl.UInt32,
                                          "local_track_id": pl.UInt32})
    out, state = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows)
    assert out["tentative"].to_list() == [True, False, False, True]
    # carried across windows: the same answer, and the state holds the new life's single plot
    a, st = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows.head(3))
    b, st2 = fusion.confirm_targets_step(st, rows.tail(1))
    assert a["tentative"].to_list() + b["tentative"].to_list() == out["tentative"].to_list()
    assert st2.tracks["n_plots"].to_list() == [1]


def test_a_one_scan_split_off_stays_tentative():
    """Radars 1 and 2 see an aircraft as target 1 for three scans; at scan 3 radar 2's plot
    misses the gate and is grouped alone as target 2, and at scan 4 it is back in target 1.
    Target 2 holds one plot of an established local track: counted over the track's life it
    was confirmed at once (a one-scan duplicate of the aircraft in the picture); counted in the
    target it is tentative. A split that lasts (target 3 from scan 6 on, two plots) is
    confirmed at its second plot, and the window edge changes nothing."""
    from datetime import datetime, timedelta, timezone
    t0 = datetime(2021, 10, 7, 12, tzinfo=timezone.utc)

    def row(k, target, radar, track):
        t = t0 + timedelta(seconds=4.0 * k)
        return {"run": 0, "epoch": t, "target_id": target, "radar_id": radar, "local_track_id": track,
                "fresh": True, "time": t}
    seen = {0: 1, 1: 1, 2: 1, 3: 2, 4: 1, 5: 1, 6: 3, 7: 3}      # radar 2's target at each scan
    rows = pl.DataFrame([row(k, 1, 1, 7) for k in range(8)] + [row(k, seen[k], 2, 4) for k in range(8)],
                        schema_overrides={"run": pl.UInt32, "target_id": pl.UInt64, "radar_id": pl.UInt32,
                                          "local_track_id": pl.UInt32}).sort("epoch", "radar_id")
    out, _ = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows)
    flags = dict(zip(zip(out["target_id"], out["epoch"]), out["tentative"]))
    assert flags[(2, t0 + timedelta(seconds=12))] is True
    assert [flags[(3, t0 + timedelta(seconds=4.0 * k))] for k in (6, 7)] == [True, False]
    assert not any(v for (tg, _), v in flags.items() if tg == 1 and _ > t0)
    for cut in (3, 4, 6, 7):          # the target change seen across the window edge
        edge = t0 + timedelta(seconds=4.0 * cut)
        a, st = fusion.confirm_targets_step(fusion.ConfirmState.empty(), rows.filter(pl.col("epoch") < edge))
        b, _ = fusion.confirm_targets_step(st, rows.filter(pl.col("epoch") >= edge))
        assert pl.concat([a, b]).sort("target_id", "epoch").equals(out.sort("target_id", "epoch"))
