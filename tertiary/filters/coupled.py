"""Coupled Cartesian Kalman filters that use the full 3×3 measurement covariance.

The per-axis filters of :mod:`tertiary.filters.linear` treat x, y, z as independent scalar
channels and so can only take the diagonal of a plot's covariance. A radar plot converted from
polar to Cartesian coordinates has strongly correlated errors (range along the line of sight,
azimuth across it: |ρ| up to ~0.8 between E and N), and that correlation is information the
diagonal throws away. These filters keep one joint state per track:

    state  s = (x, ẋ, [ẍ,] y, ẏ, [ÿ,] z, ż, [z̈])   (axis-major, n = 2 or 3 per axis)
    Φ(τ) = I₃ ⊗ φ(τ),  Q(τ) = I₃ ⊗ q(τ),   H = I₃ ⊗ [1, 0(, 0)]

with the per-axis model φ, q of the Singer filter (monograph (2.49)–(2.63), seed (4.46), as
:func:`tertiary.filters.singer.singer_phi` / ``singer_q``) or of the continuous white-noise
acceleration CV model (q [[τ³/3, τ²/2], [τ²/2, τ]]). The update is the standard Kalman update
(2.10)–(2.14) with the full R (B, 3, 3), in Joseph form:

    S = H P⁻ Hᵀ + R,  K = P⁻ Hᵀ S⁻¹,  x⁺ = x⁻ + K ν,  P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ

NIS = νᵀ S⁻¹ ν (the full S). The dynamics are axis-separable, so with a diagonal R these
filters give exactly the per-axis filters' estimates (tested). Batched (B, 3n, 3n) linear
algebra over tracks; no loop over tracks. ``update`` accepts R as (B, 3, 3) or (B, 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from tertiary.filters.base import F64, Innovation, Output, State, TrackFilter, register
from tertiary.filters.singer import Variant, singer_phi, singer_q

__all__ = ["CoupledCV", "CoupledSinger", "full_r"]


def full_r(r: F64) -> F64:
    """Measurement covariances as (B, 3, 3): a (B, 3) array is taken as the diagonal."""
    r = np.asarray(r, float)
    return r if r.ndim == 3 else r[:, :, None] * np.eye(3)


class _Coupled(TrackFilter):
    """Shared machinery: subclasses give the per-axis φ(τ), q(τ) (B, n, n) and the initial
    per-axis variances of the derivatives."""

    full_r: ClassVar[bool] = True
    n: ClassVar[int]
    v0_sigma: float

    def axis_model(self, tau: F64) -> tuple[F64, F64]:
        raise NotImplementedError

    def init_var(self) -> list[float]:
        return [self.v0_sigma ** 2]

    def _pos(self) -> NDArray[np.intp]:
        return np.arange(3) * self.n

    def _blocks(self, tau: F64) -> tuple[F64, F64]:
        phi, q = self.axis_model(np.asarray(tau, float))
        b, n = len(phi), self.n
        big_phi = np.zeros((b, 3 * n, 3 * n))
        big_q = np.zeros((b, 3 * n, 3 * n))
        for i in range(3):
            sl = slice(i * n, (i + 1) * n)
            big_phi[:, sl, sl] = phi
            big_q[:, sl, sl] = q
        return big_phi, big_q

    def init(self, z: F64, r: F64) -> State:
        z = np.asarray(z, float)
        b, n = len(z), self.n
        x = np.zeros((b, 3 * n))
        p = np.zeros((b, 3 * n, 3 * n))
        pos = self._pos()
        x[:, pos] = z
        p[:, pos[:, None], pos[None, :]] = full_r(r)
        for k, var in enumerate(self.init_var(), start=1):
            p[:, pos + k, pos + k] = var
        return {"x": x, "P": p}

    def predict(self, state: State, dt: F64) -> State:
        phi, q = self._blocks(np.broadcast_to(np.asarray(dt, float), (len(state["x"]),)))
        x = np.einsum("bij,bj->bi", phi, state["x"])
        p = phi @ state["P"] @ np.swapaxes(phi, 1, 2) + q
        return {"x": x, "P": 0.5 * (p + np.swapaxes(p, 1, 2))}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        x, p = state["x"], state["P"]
        b = len(x)
        pos = self._pos()
        ok = np.asarray(mask, bool) & np.isfinite(z).all(axis=1)
        rr = full_r(r)
        ok &= np.isfinite(rr).all(axis=(1, 2))
        zs = np.where(ok[:, None], z, x[:, pos])
        rs = np.where(ok[:, None, None], rr, np.eye(3))
        nu = zs - x[:, pos]
        ph = p[:, :, pos]                                  # P Hᵀ (B, 3n, 3)
        s = ph[:, pos, :] + rs
        s = 0.5 * (s + np.swapaxes(s, 1, 2))
        s_inv = np.linalg.inv(s)
        k = ph @ s_inv
        xu = x + np.einsum("bij,bj->bi", k, nu)
        a = np.broadcast_to(np.eye(3 * self.n), (b, 3 * self.n, 3 * self.n)).copy()
        a[:, :, pos] -= k
        pu = a @ p @ np.swapaxes(a, 1, 2) + k @ rs @ np.swapaxes(k, 1, 2)
        pu = 0.5 * (pu + np.swapaxes(pu, 1, 2))
        nis = np.einsum("bi,bij,bj->b", nu, s_inv, nu)
        bad = ~ok
        innov = Innovation(np.where(bad[:, None], np.nan, nu),
                           np.where(bad[:, None], np.nan, np.einsum("bii->bi", s)),
                           np.where(bad, np.nan, nis))
        return {"x": np.where(ok[:, None], xu, x), "P": np.where(ok[:, None, None], pu, p)}, innov

    def output(self, state: State) -> Output:
        pos = self._pos()
        idx = np.concatenate([pos, pos + 1])
        cov = state["P"][:, idx[:, None], idx[None, :]]
        return Output(state["x"][:, idx], np.einsum("bii->bi", cov), None, cov)


@register
@dataclass(frozen=True)
class CoupledSinger(_Coupled):
    """Singer model per axis (as :class:`tertiary.filters.manoeuvring.SingerFilter`: α_ф ``alpha``
    s⁻¹, σ_m ``sigma_m`` m/s², ``variant``), coupled through the full 3×3 R."""

    name: ClassVar[str] = "singer_full"
    n: ClassVar[int] = 3
    alpha: float = 1.0 / 30.0
    sigma_m: float = 2.0
    variant: Variant = "printed"
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        if self.variant not in ("printed", "exact"):
            raise ValueError(f"unknown variant {self.variant!r}; use 'printed' or 'exact'")
        if not (self.alpha >= 0 and self.sigma_m >= 0 and self.v0_sigma > 0):
            raise ValueError("need alpha >= 0, sigma_m >= 0, v0_sigma > 0")

    def axis_model(self, tau: F64) -> tuple[F64, F64]:
        phi = singer_phi(tau, self.alpha, self.variant)
        q = singer_q(tau, self.alpha, self.sigma_m, self.variant)
        if self.variant == "printed":            # the linear family's guard for α_фτ > 1
            long = self.alpha * tau > 1.0
            phi[long, 2, 2] = 0.0
            q[long, 2, 2] = self.sigma_m ** 2
        return phi, q

    def init_var(self) -> list[float]:
        return [self.v0_sigma ** 2, self.sigma_m ** 2]


@register
@dataclass(frozen=True)
class CoupledCV(_Coupled):
    """Constant velocity per axis with continuous white-noise acceleration of spectral density
    ``q`` (m²/s³), Q = q [[τ³/3, τ²/2], [τ²/2, τ]], coupled through the full 3×3 R."""

    name: ClassVar[str] = "cv_full"
    n: ClassVar[int] = 2
    q: float = 1.0
    v0_sigma: float = 300.0

    def __post_init__(self) -> None:
        if not (self.q >= 0 and self.v0_sigma > 0):
            raise ValueError("need q >= 0, v0_sigma > 0")

    def axis_model(self, tau: F64) -> tuple[F64, F64]:
        b = len(tau)
        phi = np.broadcast_to(np.eye(2), (b, 2, 2)).copy()
        phi[:, 0, 1] = tau
        q = np.empty((b, 2, 2))
        q[:, 0, 0] = self.q * tau ** 3 / 3.0
        q[:, 0, 1] = q[:, 1, 0] = self.q * tau ** 2 / 2.0
        q[:, 1, 1] = self.q * tau
        return phi, q
