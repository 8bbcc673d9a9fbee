"""Singer channel: elementwise forms equal the matrix forms; the filter equals filterpy."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from tertiary.filters.singer import (predict_elementwise, singer_coefficients, singer_phi, singer_q, update_elementwise)

PAIRS = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def _pack(p):
    return np.stack([p[..., i, j] for i, j in PAIRS])


@pytest.mark.parametrize("variant", ["printed", "exact"])
def test_elementwise_prediction_matches_matrix_form(variant):
    rng = np.random.default_rng(3)
    a = rng.normal(size=(50, 3, 3))
    p = a @ a.transpose(0, 2, 1)
    x = rng.normal(size=(50, 3))
    tau = rng.uniform(0.1, 12.0, 50)
    phi, q = singer_phi(tau, 1 / 30, variant), singer_q(tau, 1 / 30, 2.0, variant)
    xe, pe = x.T.copy(), _pack(p)
    predict_elementwise(xe, pe, tau, singer_coefficients(tau, 1 / 30, 2.0, variant))
    np.testing.assert_allclose(xe.T, np.einsum("nij,nj->ni", phi, x), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(pe, _pack(phi @ p @ phi.transpose(0, 2, 1) + q), rtol=1e-12, atol=1e-9)


def test_printed_phi_is_first_order_in_alpha_tau():
    """Digest: exact − printed is −ατ²/2 for Φ₂₃ and +α²τ²/2 for Φ₃₃ to leading order."""
    tau, alpha = 0.1, 0.05
    d = singer_phi(tau, alpha, "exact") - singer_phi(tau, alpha, "printed")
    assert d[1, 2] == pytest.approx(-alpha * tau**2 / 2, rel=1e-2)
    assert d[2, 2] == pytest.approx(alpha**2 * tau**2 / 2, rel=1e-2)


def test_stationary_acceleration_variance():
    """D_a keeps Var(a) = σ_m² for both discretisations."""
    for variant in ("printed", "exact"):
        _, _, f, q = singer_coefficients(2.0, 1 / 30, 3.0, variant)
        assert q / (1 - f**2) == pytest.approx(9.0, rel=1e-12)


@pytest.mark.parametrize("variant", ["printed", "exact"])
def test_batched_range_channel_matches_filterpy(variant):
    """Seed (4.53)–(4.71) recursion, 200 tracks at once, against filterpy step by step."""
    rng = np.random.default_rng(11)
    n_tracks, steps, r = 200, 60, 50.0**2
    tau = rng.uniform(0.8, 12.0, (steps, n_tracks))
    z = 30_000 + np.cumsum(rng.normal(0, 80, (steps, n_tracks)), axis=0)
    x = np.zeros((3, n_tracks))
    x[0] = z[0]
    p = np.zeros((6, n_tracks))
    p[0], p[3], p[5] = r, 300.0**2, 4.0
    ours = [x.copy()]
    for k in range(1, steps):
        predict_elementwise(x, p, tau[k], singer_coefficients(tau[k], 1 / 30, 2.0, variant))
        update_elementwise(x, p, z[k] - x[0], np.full(n_tracks, r))
        ours.append(x.copy())
    ours = np.array(ours)
    for j in range(0, n_tracks, 37):
        kf = KalmanFilter(dim_x=3, dim_z=1)
        kf.x = np.array([z[0, j], 0.0, 0.0])
        kf.P = np.diag([r, 300.0**2, 4.0])
        kf.H = np.array([[1.0, 0.0, 0.0]])
        kf.R = np.array([[r]])
        for k in range(1, steps):
            kf.F = singer_phi(tau[k, j], 1 / 30, variant)
            kf.Q = singer_q(tau[k, j], 1 / 30, 2.0, variant)
            kf.predict()
            kf.update(np.array([z[k, j]]))
            np.testing.assert_allclose(ours[k, :, j], kf.x.ravel(), rtol=1e-9, atol=1e-9)
        final = np.array([[p[0, j], p[1, j], p[2, j]], [p[1, j], p[3, j], p[4, j]], [p[2, j], p[4, j], p[5, j]]])
        np.testing.assert_allclose(final, kf.P, rtol=1e-9, atol=1e-9)


def test_missing_measurement_is_pure_prediction():
    x = np.array([[1000.0], [10.0], [0.5]])
    p = np.array([[100.0], [1.0], [0.1], [4.0], [0.2], [1.0]])
    x0, p0 = x.copy(), p.copy()
    s = update_elementwise(x, p, np.array([np.nan]), np.array([25.0]))
    assert s[0] == pytest.approx(125.0)
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(p, p0)
