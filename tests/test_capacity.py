"""Accuracy versus capacity (5.18)–(5.21): the worked tables to their printed digits,
the pole and validity flag, the closed-form n_max, and the sounder model's table."""

from __future__ import annotations

import math

import numpy as np
import polars as pl
import pytest

from safety.capacity import (capacity_curve, capacity_from_metrics, conflict_radius, nmax_seed, nmax_sound, p_np,
                             p_pij, ppob_curves, ppob_seed, ppob_sound, rate_per_hour, v_ob)
from tertiary.contract import TABLES, validate


def _sig(x: float, digits: int) -> float:
    """``x`` rounded to ``digits`` significant digits (the worked tables' printing)."""
    return float(f"{x:.{digits - 1}e}")


# worked example: V_ВС = 6000 m³, V_зо = 10¹² m³
NS = [2, 10, 50, 100, 139, 140, 200]
TABLE = {
    50: ("1.131e8", "0.9999470", ["1.131e-4", "1.019e-3", "5.572e-3", "1.132e-2", "1.585e-2", "1.597e-2", "2.302e-2"]),
    100: ("9.048e8", "0.9999934", ["9.056e-4", "8.210e-3", "4.639e-2", "9.839e-2", "1.427e-1", "1.439e-1", "2.196e-1"]),
    200: ("7.238e9", "0.9999992", ["7.291e-3", "6.968e-2", "5.496e-1", "2.528", "888.4", "-164.6", "-3.27"]),
}


def _digits(s: str) -> int:
    mant = s.split("e")[0].lstrip("-").replace(".", "").lstrip("0")
    return len(mant)


@pytest.mark.parametrize("sigma", [50, 100, 200])
def test_seed_table_reproduced(sigma):
    vo, pnp, row = TABLE[sigma]
    assert _sig(float(v_ob(sigma)), 4) == float(vo)
    # P_нп(50 m) = 0.99994695 rounds to 0.9999469; the worked table prints 0.9999470 (last digit off by one)
    assert float(p_np(sigma)) == pytest.approx(float(pnp), abs=1.0e-7 if sigma == 50 else 0.5e-7)
    p, _ = ppob_seed(NS, sigma)
    for got, printed in zip(p, row):
        assert _sig(float(got), _digits(printed)) == float(printed), (sigma, got, printed)


def test_p_pij_unused_constant():
    assert p_pij() == pytest.approx(6.0e-9, rel=1e-8)


def test_pole_and_validity_flag():
    # pole at n = 1 + V_зо/V_об = 139.2 for σ = 200 m
    assert 1 + 1e12 / float(v_ob(200)) == pytest.approx(139.2, abs=0.05)
    p, valid = ppob_seed(NS, 200)
    assert list(valid) == [True, True, True, False, False, False, False]     # (n−1)V_об < V_зо/2
    assert p[3] > 1 and p[4] > 1 and p[5] < 0 and p[6] < 0
    # valid exactly while (n − 1)V_об < V_зо/2: 69 < 1e12/2/7.238e9 = 69.08
    _, v = ppob_seed([70, 71], 200)
    assert list(v) == [True, False]
    p1, v1 = ppob_seed(1, 100)
    assert float(p1) == 0.0 and bool(v1)


def test_nmax_seed_closed_form_and_one_at_1e6():
    assert list(nmax_seed([50, 100, 200], 1e-6)) == [1, 1, 1]
    # the closed form is the largest n with (5.21) ≤ P* (check against the formula itself)
    for s in (10.0, 50.0, 100.0, 200.0):
        for ps in (1e-3, 1e-2, 1e-4):
            n = int(nmax_seed(s, ps))
            assert float(ppob_seed(n, s).p) <= ps
            assert float(ppob_seed(n + 1, s).p) > ps
    # n = 2 feasible only for V_об ≤ 1.0e6 m³ (σ ≤ 10.3 m) at 10¹², or V_зо ≥ 1.13e14 for σ = 50 m
    assert int(nmax_seed(10.3, 1e-6)) == 2 and int(nmax_seed(10.4, 1e-6)) == 1
    assert int(nmax_seed(50, 1e-6, v_zo=1.14e14)) == 2 and int(nmax_seed(50, 1e-6, v_zo=1.12e14)) == 1


@pytest.mark.parametrize("v_zo,p_star,expected", [
    (1e12, 1e-3, [9, 2, 1]),
    (1e12, 1e-2, [88, 11, 2]),
    (1e14, 1e-4, [89, 12, 2]),
    (1e14, 1e-3, [884, 111, 14]),
])
def test_threshold_table(v_zo, p_star, expected):
    assert list(nmax_seed([50, 100, 200], p_star, v_zo=v_zo)) == expected


def test_nmax_scales_as_sigma_minus_three():
    n = nmax_seed([25.0, 50.0], 1e-3, v_zo=1e14)
    assert (n[0] - 1) / (n[1] - 1) == pytest.approx(8.0, rel=0.01)


def test_sound_table_reproduced():
    # R_c = 12σ, V_зо = 10¹²
    assert _sig(float(ppob_sound(2, 50, "12sigma", which="one")), 3) == 9.05e-4
    assert _sig(float(ppob_sound(10, 50, "12sigma")), 3) == 3.99e-2
    assert _sig(float(ppob_sound(50, 50, "12sigma")), 3) == 0.670
    assert _sig(float(ppob_sound(2, 100, "12sigma", which="one")), 3) == 7.24e-3
    assert _sig(float(ppob_sound(10, 100, "12sigma")), 3) == 0.279
    assert float(ppob_sound(50, 100, "12sigma")) == pytest.approx(1.0, abs=2e-4)
    # check: R_c = 6σ, σ = 100, n = 2 → p = 9.048e-4 against 9.056e-4 from (5.21)
    assert _sig(float(ppob_sound(2, 100, "6sigma", which="one")), 4) == 9.048e-4
    assert _sig(float(ppob_seed(2, 100).p), 4) == 9.056e-4


def test_sound_nmax_closed_form():
    for s in (5.0, 10.0, 20.0):
        for which in ("one", "any"):
            n = int(nmax_sound(s, 1e-3, which=which))
            assert float(ppob_sound(n, s, which=which)) <= 1e-3 < float(ppob_sound(n + 1, s, which=which))
    assert int(nmax_sound(50, 1e-6)) == 1
    assert conflict_radius(100, "separation", dr_m=5556) == pytest.approx(5556 + 300 * math.sqrt(2))
    assert conflict_radius(100, 1000.0) == 1000.0
    with pytest.raises(ValueError):
        conflict_radius(100, "8sigma")


def test_rate_per_hour():
    assert float(rate_per_hour(1 - math.exp(-2.0), 0.5)) == pytest.approx(4.0)


def test_curves_frames():
    c = ppob_curves(n=range(2, 201), sigmas=(50, 100, 200))
    assert set(c["model"]) == {"seed", "sound_one", "sound_any"}
    seed200 = c.filter((pl.col("model") == "seed") & (pl.col("sigma_m") == 200))
    assert seed200.filter(pl.col("n") == 140)["p"][0] == pytest.approx(-164.6, abs=0.05)
    assert not seed200.filter(pl.col("n") == 140)["valid"][0]
    # P rises with n and σ where valid (fig. 5.2)
    valid = c.filter(pl.col("valid") & (pl.col("model") == "seed"))
    for s in (50, 100):
        assert (np.diff(valid.filter(pl.col("sigma_m") == s)["p"].to_numpy()) > 0).all()
    cap = capacity_curve(np.arange(10.0, 201.0, 10.0), p_star=1e-3, v_zo=1e14)
    seed = cap.filter(pl.col("model") == "seed")["n_max"].to_numpy()
    assert (np.diff(seed) <= 0).all() and seed[0] > seed[-1]
    assert set(cap.columns) == {"model", "sigma_m", "p_star", "v_zo_m3", "n_max"}


def test_capacity_from_metrics():
    metrics = pl.DataFrame({
        "stage": ["fusion"] * 5 + ["tracking"],
        "method": ["arith", "arith", "markov", "markov", "seed", "arith"],
        "metric": ["rmse_pos_m", "rmse_range_m", "rmse_pos_m", "rmse_vel_mps", "rmse_range_m", "rmse_pos_m"],
        "segment": ["all", "all", "all", "all", "turn", "all"],
        "value": [80.0, 10.0, 50.0, 3.0, 20.0, 20.0],
        "n_runs": [100, 100, 100, 100, 100, 100],
    }).cast(TABLES["metrics"].required)
    out = capacity_from_metrics(metrics, p_star=1e-6, v_zo=1e12, n_fixed=None)
    validate(out, "metrics")
    assert set(out["metric"]) == {"capacity_n_1e-6", "capacity_n_1e-6_sound"}
    # arith is in two stages → labelled by stage; fusion/arith uses rmse_range_m (10 m) first
    vals = {(r["method"], r["metric"]): r["value"] for r in out.to_dicts()}
    assert vals[("fusion/arith", "capacity_n_1e-6")] == 2.0      # σ = 10 m ≤ 10.3 m admits a second aircraft
    assert vals[("tracking/arith", "capacity_n_1e-6")] == 1.0
    assert vals[("markov", "capacity_n_1e-6")] == 1.0            # σ = 50 m: n = 1 at 10⁻⁶
    assert ("seed", "capacity_n_1e-6") not in vals                # only a 'turn' segment
    loose = capacity_from_metrics(metrics, p_star=1e-3, v_zo=1e14, n_fixed=None)
    assert set(loose["metric"]) == {"capacity_n_1e-3", "capacity_n_1e-3_sound"}
    assert dict(loose.filter(pl.col("metric") == "capacity_n_1e-3").select("method", "value").iter_rows())["markov"] \
        == float(nmax_seed(50, 1e-3, v_zo=1e14))
    assert capacity_from_metrics(metrics.filter(pl.col("metric") == "rmse_vel_mps")).height == 0


def test_run_capacity_figures_vary_with_the_measured_sigma():
    """no per-method capacity figure is constant over realistic σ."""
    sig = [40.0, 60.0, 90.0, 150.0]
    metrics = pl.DataFrame({"stage": "fusion", "method": [f"m{i}" for i in range(4)], "metric": "rmse_pos_m",
                            "segment": "all", "value": sig, "n_runs": 1}).cast(TABLES["metrics"].required)
    out = capacity_from_metrics(metrics)                 # the run's defaults
    assert set(out["metric"]) == {"capacity_n_1e-3", "capacity_n_1e-3_sound", "p_conflict_n20",
                                  "p_conflict_n20_sound"}
    for name in out["metric"].unique():
        v = out.filter(pl.col("metric") == name).sort("method")["value"].to_numpy()
        assert len(np.unique(v)) == len(v), (name, v)    # every σ gives its own value
        # worse accuracy: fewer aircraft, higher conflict probability
        assert (np.diff(v) < 0).all() if name.startswith("capacity") else (np.diff(v) > 0).all(), (name, v)
    p = dict(out.filter(pl.col("metric") == "p_conflict_n20").select("method", "value").iter_rows())
    v_ob = 4.0 / 3.0 * np.pi * (6 * 60.0) ** 3           # (5.18) at σ = 60 m, by hand
    p_np_ = (v_ob - 6000.0) / v_ob                       # (5.20)
    assert p["m1"] == pytest.approx(19 * v_ob / (1e14 - 19 * v_ob) * p_np_, rel=1e-12)   # (5.21), n = 20
