"""The batched filter interface every secondary tracker filter implements.

A filter works on a batch of B independent tracks at once (tracks × Monte-Carlo runs,
flattened): every array in a filter :data:`State` has the track axis first, so the tracker can
select, drop and append tracks without knowing the filter (:func:`take`, :func:`concat`).

Measurements are plots in the system ENU frame: positions ``z`` (B, 3) with per-axis
variances ``r`` (B, 3) (the diagonal of the measurement covariance) — or the full 3×3
covariance (B, 3, 3) for filters that declare ``full_r = True``. ``dt`` (B,) is each track's time since its last step and
``mask`` (B,) says which tracks have a plot this step (the others coast: x⁺ = x⁻, P⁺ = P⁻,
the monograph's "memory mode", §2.1).

Every filter reports its estimate in one common form, :class:`Output`: the 6-state
(x, y, z, vx, vy, vz), its covariance diagonal, and model probabilities where relevant.

A plot may also carry the aircraft's own turn rate (Mode S BDS 5,0 track-angle rate, downlinked
by an enhanced-surveillance transponder). :meth:`TrackFilter.observe_turn_rate` hands it to the
filter after the position update; a filter with a turn-rate model uses it, the others ignore it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
State = dict[str, NDArray]


def take(state: State, idx: NDArray) -> State:
    """Tracks ``idx`` (integer indices or a boolean mask) of a state."""
    return {k: v[idx] for k, v in state.items()}


def concat(a: State, b: State) -> State:
    """Append the tracks of ``b`` after those of ``a`` (same filter, same keys)."""
    if not a:
        return dict(b)
    if not b:
        return dict(a)
    return {k: np.concatenate([a[k], b[k]], axis=0) for k in a}


def size(state: State) -> int:
    return len(next(iter(state.values()))) if state else 0


@dataclass
class Output:
    """Common estimate of B tracks: state (B, 6) = (x, y, z, vx, vy, vz), its covariance
    diagonal (B, 6), model probabilities (B, M) for multiple-model filters (else None) and,
    where the filter has it, the full 6×6 covariance (B, 6, 6) (else None: see
    :func:`full_cov`)."""

    x: F64
    var: F64
    probs: F64 | None = None
    cov: F64 | None = None


def full_cov(out: Output) -> F64:
    """The 6×6 covariance of an :class:`Output`: its ``cov``, or diag(var) when the filter
    gives only the diagonal (cross terms then unknown, reported as 0)."""
    if out.cov is not None:
        return out.cov
    return out.var[:, :, None] * np.eye(6)


@dataclass
class Innovation:
    """Innovation ν = z − H x⁻ (B, 3), its covariance diagonal S (B, 3) and the normalised
    innovation squared NIS = νᵀ S⁻¹ ν (B,) (NaN where the track had no plot)."""

    nu: F64
    s: F64
    nis: F64


class TrackFilter(ABC):
    """One filter of the family, batched over tracks. Implementations are configured in their
    constructor (frozen parameters) and keep no per-track state outside the ``State`` dict."""

    name: ClassVar[str]
    #: True when ``update`` takes the full measurement covariance ``r`` (B, 3, 3); else the
    #: tracker hands it the diagonal (B, 3)
    full_r: ClassVar[bool] = False

    @abstractmethod
    def init(self, z: F64, r: F64) -> State:
        """Start B tracks from their first plots (position z (B, 3), variances r (B, 3))."""

    @abstractmethod
    def predict(self, state: State, dt: F64) -> State:
        """Extrapolate every track by its ``dt`` (B,) seconds."""

    @abstractmethod
    def update(self, state: State, z: F64, r: F64, mask: NDArray[np.bool_]) -> tuple[State, Innovation]:
        """Correct the tracks with ``mask`` by their plots; the others keep the prediction."""

    @abstractmethod
    def output(self, state: State) -> Output:
        """The common 6-state estimate of every track."""

    def observe_turn_rate(self, state: State, omega: F64, mask: NDArray[np.bool_]) -> State:
        """Use the downlinked turn rate ``omega`` (B,) rad/s, positive counter-clockwise (a left
        turn, as the CT models' ω; NaN where none) of the tracks with ``mask``, after their
        position update. A filter without a turn-rate model returns ``state`` unchanged."""
        return state

    def observe_velocity(self, state: State, v: F64, r: F64, mask: NDArray[np.bool_]) -> State:
        """Use a measured horizontal velocity ``v`` (B, 2) m/s, system east and north, of
        covariance ``r`` (B, 2, 2) (a Mode S aircraft's downlinked ground speed and track; NaN
        where none) of the tracks with ``mask``, at the time of their last update. A filter
        that does not take one returns ``state`` unchanged."""
        return state


REGISTRY: dict[str, Callable[..., TrackFilter]] = {}


def register(cls: type[TrackFilter]) -> type[TrackFilter]:
    """Class decorator adding a filter to :data:`REGISTRY` under its ``name``."""
    REGISTRY[cls.name] = cls
    return cls


def make_filter(name: str, **params) -> TrackFilter:
    """A filter by name with optional parameters, e.g. ``make_filter("singer", variant="exact")``."""
    if name not in REGISTRY:
        raise ValueError(f"unknown filter {name!r}; available: {', '.join(sorted(REGISTRY))}")
    return REGISTRY[name](**params)
