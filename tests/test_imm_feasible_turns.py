"""The IMM's predicted mode probabilities are conditioned on the turn rates an aircraft can fly
at its speed (limit load factor), so a turn no aircraft can fly does not widen a straight track's
velocity covariance between two scans."""

from __future__ import annotations

import numpy as np
import pytest

from tertiary.core.units import G0
from tertiary.filters.base import make_filter
from tertiary.filters.imm import SYM_OMEGAS, feasible_modes, imm_combine

R = np.diag([40.0 ** 2, 40.0 ** 2, 10.0 ** 2])[None]


def test_feasible_rates_are_the_load_factor_bound():
    """|ω|·v ≤ g·sqrt(n² − 1): at n = 2.5 the bound on ω·v is 22.470 m/s² (closed form)."""
    a_max = G0 * np.sqrt(2.5 ** 2 - 1.0)
    assert a_max == pytest.approx(22.470, abs=1e-3)
    v_edge = a_max / 0.11
    ok = feasible_modes((0.11, -0.11, 0.055, 0.0), np.array([v_edge * 0.999, v_edge * 1.001, 400.0]), 2.5)
    assert ok.tolist() == [[True, True, True, True], [False, False, True, True], [False, False, True, True]]
    assert feasible_modes((0.11, 0.0), np.array([1e4]), None).all()
    assert feasible_modes((0.11, 0.0), np.array([1e4]), 1.0).tolist() == [[False, True]]   # level flight: CV only


def _straight(speed: float, **kw):
    """A straight track at ``speed`` (m/s) east (``imm_sym`` with ``kw``, else its defaults): a
    plot, a downlinked velocity and a zero turn rate every 12 s, predicted every 4 s; the state
    8 s after the last plot and before it."""
    f = make_filter("imm_sym", **kw)
    rng = np.random.default_rng(3)
    st = f.init(np.array([[0.0, 0.0, 9000.0]]), R)
    yes = np.array([True])
    for k in range(1, 31):
        before = st
        st = f.predict(st, np.array([4.0]))
        if k % 3 == 0 and k < 30:
            z = np.array([[speed * 4 * k + rng.normal(0, 40), rng.normal(0, 40), 9000.0]])
            st, _ = f.update(st, z, R, yes)
            st = f.observe_velocity(st, np.array([[speed + rng.normal(0, 1), rng.normal(0, 1)]]), np.eye(2)[None], yes)
            st = f.observe_turn_rate(st, np.array([0.0]), yes)
    return f, before, st


def test_an_infeasible_turn_does_not_widen_a_straight_tracks_velocity():
    """At 215 m/s the 0.11 rad/s models (2.6 g) get no probability, and the cross-track velocity
    σ 8 s after a plot is the feasible models' mixture, computed here from the unconditioned
    prediction (numpy path) by dropping the infeasible models and renormalising."""
    f, before, st = _straight(215.0)
    fast = np.abs(np.asarray(SYM_OMEGAS)) == 0.11
    assert (st["mu"][0, fast] == 0.0).all() and (st["mu"][0, ~fast] > 0).all()
    free = make_filter("imm_sym", compiled=False, max_load_factor=None)
    raw = free.predict(before, np.array([4.0]))
    mu = np.where(fast, 0.0, raw["mu"])
    _, p_ref = imm_combine(raw["x"], raw["P"], mu / mu.sum())
    sigma = np.sqrt(f.output(st).cov[0, 4, 4])
    assert sigma == pytest.approx(np.sqrt(p_ref[0, 3, 3]), rel=1e-6)
    _, _, wide = _straight(215.0, max_load_factor=None)
    assert sigma < 0.7 * np.sqrt(f.output(wide).cov[0, 4, 4])      # 2.9 against 4.8 m/s


def test_a_slower_track_keeps_every_model():
    """Below g·sqrt(n² − 1)/0.11 = 204 m/s the conditioning changes nothing."""
    _, _, a = _straight(150.0)
    _, _, b = _straight(150.0, max_load_factor=None)
    assert (a["mu"] > 0).all()
    np.testing.assert_allclose(a["mu"], b["mu"], rtol=1e-12)
    np.testing.assert_allclose(a["P"], b["P"], rtol=1e-9, atol=1e-9)


def test_compiled_and_numpy_paths_condition_alike():
    _, _, a = _straight(230.0, compiled=True)
    _, _, b = _straight(230.0, compiled=False)
    np.testing.assert_allclose(a["mu"], b["mu"], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(a["P"], b["P"], rtol=1e-8, atol=1e-9)


def test_load_factor_below_one_is_refused():
    with pytest.raises(ValueError, match="max_load_factor"):
        make_filter("imm_sym", max_load_factor=0.5)
