"""Innovation-based adaptive measurement noise (seed 003) as a wrapper
around any *linear* :class:`~tertiary.filters.base.TrackFilter`.

Covariance matching: the innovation covariance is H P⁻ Hᵀ + R, so R is estimated from a
sliding window of the last N innovations of each track (variant B of the source, per-channel
diagonal, each sample's own prior term subtracted — safeguard 2):

    R̂_ii = (1/n) Σ_{j in window} (ν_{i,j}² − (H P⁻ Hᵀ)_{ii,j})

The wrapper needs nothing from the inner filter but its :class:`Innovation`: for a linear
filter S = H P⁻ Hᵀ + R, so (H P⁻ Hᵀ)_ii = S_ii − R_ii with the R the wrapper passed in. (For
nonlinear / converted filters, e.g. ``ekf_spherical``, S is not of that form and the wrapper
does not apply.)

Safeguards: warm-up — the nominal R (the plots' ``r``) is used until a track has
``n_min`` samples; floor and ceiling — R̂ is clamped to [floor_frac, ceil_frac] × nominal per
axis; optional gate — once adapted, innovations with NIS above ``gate`` do not enter the window
(during warm-up everything enters, otherwise a mismatched nominal R would lock the estimator
out). The R̂ used at each update comes from the window *before* the current innovation, so the
reported NIS is a genuine prediction check. ``mode="scale"`` estimates one factor per axis,
R̂ = r · Σ(ν² − HPHᵀ)/Σ r_nominal, which tracks plot-to-plot changes of the nominal variance
(e.g. range-dependent cross-range noise); the default ``"absolute"`` is the source's formula.

Only a diagonal R is adapted: a full ``r`` (B, 3, 3) is reduced to its diagonal.
The adapted R of the last update is kept in the state as ``aekf_r`` (B, 3) for logging as a
radar-health indicator.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

from tertiary.filters.base import (F64, Innovation, Output, State, TrackFilter, make_filter, register)

PREFIX = "aekf_"


def _resolve(inner: str | TrackFilter, params: dict) -> TrackFilter:
    if isinstance(inner, TrackFilter):
        if params:
            raise ValueError("inner filter parameters apply only when `inner` is a registry name")
        return inner
    return make_filter(inner, **params)


@register
class AdaptiveR(TrackFilter):
    """Adaptive-R wrapper (seed 003 "AEKF") around a linear filter.

    Parameters:
        inner:      registry name or a TrackFilter instance, default "singer"
        window:     sliding-window length N (source: 10–50), default 50. With N = 20 (the
                    source's sketch) the estimator is unstable when H P⁻ Hᵀ is comparable to R
                    (e.g. the default Singer inner filter under a 6× mismatch: NIS mean ≈ 6 of 3,
                    4 % of errors outside 3σ); N = 50 is consistent (see the tests)
        n_min:      samples before R̂ replaces the nominal R (warm-up), default 20 (None: min(20, window))
        floor_frac: lower clamp of R̂ as a fraction of the nominal R, default 0.25
        ceil_frac:  upper clamp, default 1e4
        mode:       "absolute" (R̂ = mean(ν² − HP⁻Hᵀ), default) or "scale"
        gate:       NIS threshold for entering the window once adapted (None = no gate)
        **inner_params: constructor parameters of ``inner`` when given by name
    """

    name = "aekf"

    def __init__(self, inner: str | TrackFilter = "singer", window: int = 50, n_min: int | None = 20,
                 floor_frac: float = 0.25, ceil_frac: float = 1e4, mode: Literal["absolute", "scale"] = "absolute",
                 gate: float | None = None, **inner_params):
        n_min = min(20, window) if n_min is None else n_min
        if not 1 <= n_min <= window:
            raise ValueError("need 1 <= n_min <= window")
        if mode not in ("absolute", "scale"):
            raise ValueError(f"unknown mode {mode!r}")
        self.inner = _resolve(inner, inner_params)
        self.window, self.n_min = int(window), int(n_min)
        self.floor_frac, self.ceil_frac = float(floor_frac), float(ceil_frac)
        self.mode = mode
        self.gate = gate

    # ---- state helpers
    @staticmethod
    def _split(state: State) -> tuple[State, State]:
        inner = {k: v for k, v in state.items() if not k.startswith(PREFIX)}
        own = {k: v for k, v in state.items() if k.startswith(PREFIX)}
        return inner, own

    def _fresh(self, b: int, r: F64) -> State:
        return {PREFIX + "buf": np.zeros((b, self.window, 3)), PREFIX + "rbuf": np.zeros((b, self.window, 3)),
                PREFIX + "n": np.zeros(b, np.int64), PREFIX + "i": np.zeros(b, np.int64),
                PREFIX + "r": np.array(r, float)}

    @staticmethod
    def _diag(r: F64) -> F64:
        r = np.asarray(r, float)
        return np.einsum("bii->bi", r) if r.ndim == 3 else r

    def r_hat(self, state: State, r_nominal: F64) -> F64:
        """The R (B, 3) the next update would use, from the window of ``state``."""
        r0 = self._diag(r_nominal)
        n = state[PREFIX + "n"]
        total = state[PREFIX + "buf"].sum(axis=1)
        nn = np.maximum(n, 1)[:, None]
        if self.mode == "absolute":
            est = total / nn
        else:
            rsum = state[PREFIX + "rbuf"].sum(axis=1)
            est = r0 * total / np.where(rsum > 0, rsum, 1.0)
        est = np.clip(est, self.floor_frac * r0, self.ceil_frac * r0)
        return np.where((n >= self.n_min)[:, None], est, r0)

    # ---- TrackFilter
    def init(self, z: F64, r: F64) -> State:
        st = self.inner.init(z, r)
        clash = [k for k in st if k.startswith(PREFIX)]
        if clash:
            raise ValueError(f"inner state keys clash with the wrapper's: {clash}")
        return {**st, **self._fresh(len(z), self._diag(r))}

    def predict(self, state: State, dt: F64) -> State:
        inner, own = self._split(state)
        return {**self.inner.predict(inner, dt), **own}

    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        inner, own = self._split(state)
        r0 = self._diag(r)
        rh = self.r_hat(own, r0)
        new_inner, innov = self.inner.update(inner, z, rh, mask)
        hph = innov.s - rh
        sample = innov.nu ** 2 - hph
        ok = np.asarray(mask, bool) & np.all(np.isfinite(sample), axis=1)
        n, i = own[PREFIX + "n"], own[PREFIX + "i"]
        if self.gate is not None:
            ok &= (n < self.n_min) | (innov.nis <= self.gate)
        buf, rbuf = own[PREFIX + "buf"].copy(), own[PREFIX + "rbuf"].copy()
        rows = np.nonzero(ok)[0]
        buf[rows, i[rows]] = sample[rows]
        rbuf[rows, i[rows]] = r0[rows]
        new_own = {PREFIX + "buf": buf, PREFIX + "rbuf": rbuf,
                   PREFIX + "n": np.where(ok, np.minimum(n + 1, self.window), n),
                   PREFIX + "i": np.where(ok, (i + 1) % self.window, i),
                   PREFIX + "r": np.where(np.asarray(mask, bool)[:, None], rh, own[PREFIX + "r"])}
        return {**new_inner, **new_own}, innov

    def output(self, state: State) -> Output:
        inner, _ = self._split(state)
        return self.inner.output(inner)
