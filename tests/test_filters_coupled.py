"""Coupled Cartesian filters (tertiary.filters.coupled): filterpy equality with a full 3×3 R,
equality with the per-axis filters when R is diagonal, the full 6×6 output covariance."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from tertiary.filters.base import full_cov, make_filter
from tertiary.filters.coupled import CoupledCV, CoupledSinger
from tertiary.filters.linear import CVFilter
from tertiary.filters.manoeuvring import SingerFilter
from tertiary.filters.singer import singer_phi, singer_q


def _scenario(seed: int, b: int = 12, steps: int = 40, p_detect: float = 0.8):
    """Irregular dt, random-walk plots, correlated per-plot R (|ρ| up to ~0.9), missed plots."""
    rng = np.random.default_rng(seed)
    dt = rng.uniform(0.5, 12.0, (steps, b))
    z = rng.normal(0, 5e3, (b, 3)) + np.cumsum(rng.normal(0, 150.0, (steps, b, 3)), axis=0)
    a = rng.normal(0, 1, (steps, b, 3, 3)) * rng.uniform(10.0, 80.0, (steps, b, 3, 1))
    r = a @ np.swapaxes(a, -1, -2) + 25.0 * np.eye(3)
    mask = rng.random((steps, b)) < p_detect
    mask[0] = True
    return dt, z, r, mask


def _axis_model(f, tau: float):
    """(φ, q) of one axis built independently of coupled.py."""
    if isinstance(f, CoupledCV):
        return (np.array([[1.0, tau], [0.0, 1.0]]),
                f.q * np.array([[tau**3 / 3, tau**2 / 2], [tau**2 / 2, tau]]))
    return singer_phi(tau, f.alpha, f.variant), singer_q(tau, f.alpha, f.sigma_m, f.variant)


@pytest.mark.parametrize("f", [CoupledCV(q=2.0), CoupledSinger(), CoupledSinger(variant="exact", alpha=0.1)],
                         ids=["cv_full", "singer_full", "singer_full-exact"])
def test_equals_filterpy_with_full_r(f):
    """State, covariance, innovation, S and NIS (with the full S) equal filterpy's 3n-state
    KalmanFilter with F = I₃ ⊗ φ, Q = I₃ ⊗ q, H picking the positions and the full R."""
    dt, z, r, mask = _scenario(3)
    n = f.n
    st = f.init(z[0], r[0])
    pos = np.arange(3) * n
    for j in range(dt.shape[1]):
        kf = KalmanFilter(dim_x=3 * n, dim_z=3)
        kf.x = np.zeros(3 * n)
        kf.x[pos] = z[0, j]
        p0 = np.zeros((3 * n, 3 * n))
        p0[np.ix_(pos, pos)] = r[0, j]
        p0[pos + 1, pos + 1] = f.v0_sigma ** 2
        if n == 3:
            p0[pos + 2, pos + 2] = f.sigma_m ** 2
        kf.P = p0
        kf.H = np.zeros((3, 3 * n))
        kf.H[np.arange(3), pos] = 1.0
        s = {k: v[j:j + 1] for k, v in st.items()}
        for k in range(1, len(dt)):
            phi, q = _axis_model(f, dt[k, j])
            kf.F, kf.Q = np.kron(np.eye(3), phi), np.kron(np.eye(3), q)
            kf.predict()
            s = f.predict(s, dt[k, j:j + 1])
            s, inn = f.update(s, z[k, j:j + 1], r[k, j:j + 1], mask[k, j:j + 1])
            if mask[k, j]:
                kf.R = r[k, j]
                kf.update(z[k, j])
                np.testing.assert_allclose(inn.nu[0], kf.y, rtol=1e-9, atol=1e-7)
                np.testing.assert_allclose(inn.s[0], np.diag(kf.S), rtol=1e-9)
                np.testing.assert_allclose(inn.nis[0], kf.y @ np.linalg.solve(kf.S, kf.y), rtol=1e-8)
            else:
                assert np.isnan(inn.nis[0])
            np.testing.assert_allclose(s["x"][0], kf.x, rtol=1e-9, atol=1e-6)
            np.testing.assert_allclose(s["P"][0], kf.P, rtol=1e-8, atol=1e-6)


@pytest.mark.parametrize("pair", [(CoupledCV(q=3.0), CVFilter(q=3.0)), (CoupledSinger(), SingerFilter())],
                         ids=["cv", "singer"])
def test_diagonal_r_gives_the_per_axis_filter(pair):
    """Axis-separable dynamics: with a diagonal R the coupled filter is the per-axis filter,
    and its 6×6 output covariance equals the per-axis one (cross-axis terms zero)."""
    coupled, per_axis = pair
    dt, z, r, mask = _scenario(5)
    rd = np.einsum("tbii->tbi", r)
    a, b = coupled.init(z[0], rd[0]), per_axis.init(z[0], rd[0])
    for k in range(1, len(dt)):
        a, ia = coupled.update(coupled.predict(a, dt[k]), z[k], rd[k], mask[k])
        b, ib = per_axis.update(per_axis.predict(b, dt[k]), z[k], rd[k], mask[k])
        np.testing.assert_allclose(ia.nis, ib.nis, rtol=1e-8)
    oa, ob = coupled.output(a), per_axis.output(b)
    np.testing.assert_allclose(oa.x, ob.x, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(oa.var, ob.var, rtol=1e-8)
    np.testing.assert_allclose(full_cov(oa), full_cov(ob), rtol=1e-8, atol=1e-6)


def test_correlated_r_changes_the_estimate():
    """The correlation of R is used: the same plots with R and with its diagonal give
    different estimates (a filter reading only the diagonal would not)."""
    f = make_filter("cv_full")
    assert f.full_r
    dt, z, r, mask = _scenario(9)
    a, b = f.init(z[0], r[0]), f.init(z[0], np.einsum("bii->bi", r[0]))
    for k in range(1, len(dt)):
        a, _ = f.update(f.predict(a, dt[k]), z[k], r[k], mask[k])
        b, _ = f.update(f.predict(b, dt[k]), z[k], np.einsum("bii->bi", r[k]), mask[k])
    assert np.abs(f.output(a).x - f.output(b).x).max() > 1.0


def test_full_covariance_output_is_symmetric_and_matches_var():
    f = make_filter("singer_full")
    dt, z, r, mask = _scenario(11)
    s = f.init(z[0], r[0])
    for k in range(1, 10):
        s, _ = f.update(f.predict(s, dt[k]), z[k], r[k], mask[k])
    out = f.output(s)
    np.testing.assert_allclose(out.cov, np.swapaxes(out.cov, 1, 2))
    np.testing.assert_allclose(np.einsum("bii->bi", out.cov), out.var)
    assert (np.linalg.eigvalsh(out.cov) > 0).all()


def test_bad_parameters():
    with pytest.raises(ValueError):
        CoupledSinger(variant="other")
    with pytest.raises(ValueError):
        CoupledCV(q=-1.0)
