"""The reports' est_cov check (tertiary.contract.validation._cov_codes): the factorisation that clears most matrices
before their eigenvalues are computed gives exactly the codes of the eigenvalues alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import polars as pl
import pytest

from tertiary.contract import validation as schema


def _reference(cov: np.ndarray, limits: schema.Limits) -> np.ndarray:
    a = cov.reshape(-1, 6, 6)
    code = np.zeros(len(a), np.int8)
    for i, m in enumerate(a):
        if np.isnan(m).any():
            continue
        if np.isinf(m).any():
            code[i] = 1
            continue
        scale = np.abs(np.diag(m)).max()
        tol = limits.cov_rel_tol * scale
        if scale > limits.variance_max:
            code[i] = 2
        elif np.abs(m - m.T).max() > tol:
            code[i] = 3
        elif np.linalg.eigvalsh(0.5 * (m + m.T))[0] < -tol:
            code[i] = 4
    return code


def _series(cov: np.ndarray) -> pl.Series:
    return pl.Series("est_cov", cov.reshape(-1, 36), dtype=pl.Array(pl.Float64, 36))


def _matrices(rng: np.random.Generator, n: int, tol_rel: float) -> np.ndarray:
    """Covariances with the spread of a radar track's (positions 1e2-1e8 m², velocities 1e-2-1e3),
    random orientation, and a smallest eigenvalue placed around −tolerance: far below, just
    below, at, just above, far above, and exactly singular."""
    q, _ = np.linalg.qr(rng.normal(size=(n, 6, 6)))
    lam = np.exp(rng.uniform(np.log(1e-2), np.log(1e8), size=(n, 6)))
    lam.sort(axis=1)
    top = lam[:, -1]
    where = rng.choice([-10.0, -1.0 - 1e-6, -1.0, -1.0 + 1e-6, -0.5, -0.4999, 0.0, 1e-3, 1.0], size=n)
    # the smallest eigenvalue relative to the tolerance of the matrix's largest diagonal ~ top
    lam[:, 0] = where * tol_rel * top
    lam[rng.random(n) < 0.3, 0] = rng.uniform(1e-2, 1.0)          # plain covariances
    m = np.einsum("nij,nj,nkj->nik", q, lam, q)
    return 0.5 * (m + m.transpose(0, 2, 1))


@pytest.mark.parametrize("tol_rel", [1e-6, 1e-9, 1e-12])
def test_the_psd_check_equals_the_eigenvalues_alone(tol_rel: float) -> None:
    rng = np.random.default_rng(7)
    limits = dataclasses.replace(schema.Limits(), cov_rel_tol=tol_rel)
    cov = _matrices(rng, 20_000, tol_rel)
    bad = rng.choice(len(cov), 50, replace=False)
    cov[bad[:10], 2, 2] = np.nan
    cov[bad[10:20], 0, 5] = np.inf
    cov[bad[20:30], 1, 3] += 1.0                                     # asymmetric
    cov[bad[30:40], 4, 4] = 1e15                                     # too large
    got = schema._cov_codes(_series(cov), limits)
    want = _reference(cov, limits)
    assert (got == want).all(), np.flatnonzero(got != want)[:10]
    # the cases near the boundary are there: both codes, and matrices just either side of it
    assert (want == 4).sum() > 1000 and (want == 0).sum() > 1000


def test_the_factorisation_clears_a_covariance_and_never_one_below_the_tolerance() -> None:
    rng = np.random.default_rng(11)
    tol_rel = 1e-6
    cov = _matrices(rng, 5_000, tol_rel)
    scale = np.abs(np.diagonal(cov, axis1=1, axis2=2)).max(axis=1)
    ok = schema._cholesky_ok(cov, 0.5 * tol_rel * scale)
    lam0 = np.linalg.eigvalsh(cov)[:, 0]
    assert not (ok & (lam0 < -tol_rel * scale)).any()
    assert ok[lam0 > 0].all() and ok.mean() > 0.3
