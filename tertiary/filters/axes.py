"""Per-axis layout and elementwise kernels shared by the linear filter family
(:mod:`.linear`, :mod:`.manoeuvring`): the three Cartesian axes of a fused plot as independent
scalar channels, all arithmetic elementwise over (B, 3) arrays (tracks × axes).

State layout (track axis first, as :mod:`tertiary.filters.base` requires):

``x``  (B, 3, n)  per-axis state, n = 2 ([p, v]) or 3 ([p, v, a])
``P``  (B, 3, m)  per-axis covariance, packed upper triangle: (P00, P01, P11) for n = 2,
                  (P00, P01, P02, P11, P12, P22) for n = 3 (:func:`full_covariance` unpacks)

Internally the component axis is moved to the front — (n, B, 3) contiguous arrays — so each
component is one flat array (see :func:`tertiary.filters.singer.predict_elementwise`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tertiary.filters.base import F64, Innovation, Output

__all__ = ["PerAxis", "PAIRS", "full_covariance", "per_axis", "axis_param", "components", "state_layout", "tau3",
           "mask3", "masked_innovation", "masked_variance", "innovation", "init_state", "output6", "predict2",
           "update2", "gain_update"]

PerAxis = float | Sequence[float]

#: packed upper-triangle index pairs of a symmetric n×n matrix (row-major)
PAIRS = {2: ((0, 0), (0, 1), (1, 1)), 3: ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))}


# ----------------------------------------------------------------------------- layout helpers

def full_covariance(p: ArrayLike) -> F64:
    """Unpack a packed covariance (..., 3) or (..., 6) into full matrices (..., n, n)."""
    p = np.asarray(p, float)
    n = {3: 2, 6: 3}[p.shape[-1]]
    out = np.empty(p.shape[:-1] + (n, n))
    for m, (i, j) in enumerate(PAIRS[n]):
        out[..., i, j] = out[..., j, i] = p[..., m]
    return out


def per_axis(value: PerAxis, name: str, *, positive: bool = False) -> F64:
    """A per-axis parameter (scalar or 3-sequence) as a checked (3,) array."""
    a = np.broadcast_to(np.asarray(value, float), (3,)).copy()
    if not np.all(np.isfinite(a)) or np.any(a < 0) or (positive and np.any(a <= 0)):
        raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'} per axis, got {value!r}")
    return a


def axis_param(v: F64, b: int) -> float | F64:
    """A per-axis parameter (3,) for (B, 3) arithmetic: a scalar when the axes agree, else a
    contiguous (B, 3) tile (broadcasting a (3,) row runs numpy's slow 3-element inner loop)."""
    return float(v[0]) if v[0] == v[1] == v[2] else np.tile(v, (b, 1))


def components(a: NDArray) -> NDArray:
    """State array (B, 3, n) → a fresh contiguous component-first copy (n, B, 3)."""
    return a.transpose(2, 0, 1).copy()


def state_layout(a: NDArray) -> NDArray:
    """Component-first (n, B, 3) → state layout (B, 3, n) (a view)."""
    return a.transpose(1, 2, 0)


def tau3(dt: ArrayLike) -> F64:
    """Per-track intervals (B,) → contiguous (B, 3): same-shape elementwise operations are several
    times faster than broadcasting a (B, 1) column."""
    dt = np.asarray(dt, float).reshape(-1, 1)
    return np.repeat(dt, 3, axis=1)


def mask3(mask: ArrayLike) -> NDArray[np.bool_]:
    """Plot mask (B,) → contiguous (B, 3)."""
    return np.repeat(np.asarray(mask, bool).reshape(-1, 1), 3, axis=1)


def masked_innovation(z: F64, x0: F64, m3: NDArray[np.bool_]) -> F64:
    """Innovation ν (B, 3), NaN where the track has no plot (``m3`` from :func:`mask3`)."""
    return np.where(m3, np.asarray(z, float) - x0, np.nan)


def masked_variance(r: F64, m3: NDArray[np.bool_]) -> F64:
    """Measurement variances with masked-out (possibly NaN) rows replaced by 1."""
    return np.where(m3, np.asarray(r, float), 1.0)


def innovation(nu: F64, s: F64) -> Innovation:
    """The :class:`Innovation` of per-axis ν and S (NaN S and no NIS term where ν is NaN)."""
    s = np.where(np.isfinite(nu), s, np.nan)
    return Innovation(nu=nu, s=s, nis=np.sum(nu * nu / s, axis=1))


def init_state(z: F64, r: F64, n: int, v0_var: float, a_var: F64 | None = None) -> tuple[F64, F64]:
    """x (B, 3, n), packed P (B, 3, m) from the first plots."""
    z = np.asarray(z, float)
    b = len(z)
    x = np.zeros((b, 3, n))
    x[..., 0] = z
    p = np.zeros((b, 3, len(PAIRS[n])))
    p[..., 0] = np.asarray(r, float)
    p[..., PAIRS[n].index((1, 1))] = v0_var
    if n == 3:
        p[..., 5] = a_var
    return x, p


def output6(x: NDArray, p: NDArray) -> Output:
    """6-state (x, y, z, vx, vy, vz) from per-axis [p, v, …] state and packed covariance."""
    vv = 2 if p.shape[-1] == 3 else 3            # index of P11 in the packed layout
    var = np.concatenate([p[..., 0], p[..., vv]], axis=1)
    cov = np.zeros((len(p), 6, 6))
    ax = np.arange(3)
    cov[:, ax, ax] = p[..., 0]
    cov[:, ax + 3, ax + 3] = p[..., vv]
    cov[:, ax, ax + 3] = cov[:, ax + 3, ax] = p[..., 1]   # per-axis position–velocity terms
    return Output(x=np.concatenate([x[..., 0], x[..., 1]], axis=1), var=var, cov=cov)


# ----------------------------------------------------------------------------- elementwise kernels

def predict2(x: F64, p: F64, tau: F64, f11: F64 | float, q: tuple) -> None:
    """In place x ← Φx, P ← ΦPΦᵀ + Q for Φ = [[1, τ], [0, f11]], packed Q = (q00, q01, q11)."""
    x[0] += tau * x[1]
    x[1] *= f11
    p00, p01, p11 = p
    a0 = p00 + tau * p01                    # row 0 of ΦP
    a1 = p01 + tau * p11
    n00 = a0 + tau * a1 + q[0]
    n01 = f11 * a1 + q[1]
    n11 = f11 * f11 * p11 + q[2]
    p[0], p[1], p[2] = n00, n01, n11


def update2(x: F64, p: F64, nu: F64, r: F64) -> F64:
    """In place scalar Kalman update with H = [1, 0]; returns S = P00 + R (no-op where ν is NaN)."""
    s = p[0] + r
    ok = np.isfinite(nu)
    g = np.where(ok, 1.0 / s, 0.0)
    nu0 = np.where(ok, nu, 0.0)
    c0, c1 = p[0].copy(), p[1].copy()
    x[0] += c0 * g * nu0
    x[1] += c1 * g * nu0
    p[0] -= c0 * c0 * g
    p[1] -= c0 * c1 * g
    p[2] -= c1 * c1 * g
    return s


def gain_update(x: F64, p: F64, nu: F64, r: F64, gains: Sequence[F64]) -> F64:
    """In place update with a given (not necessarily optimal) gain K and H = [1, 0, …]:
    x ← x + Kν, P ← (I − KH)P(I − KH)ᵀ + KRKᵀ (Joseph form, valid for any gain).

    Elementwise, P⁺ᵢⱼ = Pᵢⱼ − KᵢP₀ⱼ − KⱼP₀ᵢ + KᵢKⱼS with S = P00 + R. Returns S."""
    n = len(gains)
    s = p[0] + r
    ok = np.isfinite(nu)
    nu0 = np.where(ok, nu, 0.0)
    k = [np.where(ok, g, 0.0) for g in gains]
    row0 = [p[j].copy() for j in range(n)]      # P0j are the first n packed entries
    for i in range(n):
        x[i] += k[i] * nu0
    for m, (i, j) in enumerate(PAIRS[n]):
        p[m] += k[i] * k[j] * s - k[i] * row0[j] - k[j] * row0[i]
    return s

