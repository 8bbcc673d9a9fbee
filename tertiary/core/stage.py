"""The streamed stage contract: a :class:`Window` of the absolute time grid, the one window check
(:func:`check_window`) and the :class:`Stage` protocol that every streamed stage follows.

A stage is a pure step function of (state, inputs, window) → (outputs, new state): its
configuration and fixed context (radars, origin, methods, filters…) are bound when it is built,
its carried state is an explicit value that pickles, and stepping a run window by window gives
what one step over the whole run gives (``tests/test_stage_conformance.py`` checks every stage
of :data:`tertiary.pipeline.plan.STAGES` for it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import polars as pl

from tertiary.core.errors import DataError, OptionError

#: the earliest time of the grid (µs, int64 minimum): the start of a window open to the past
T_MIN_US: int = int(np.iinfo(np.int64).min)
#: the latest time of the grid (µs, int64 maximum): the end of a window open to the future
T_MAX_US: int = int(np.iinfo(np.int64).max)


@dataclass(frozen=True)
class Window:
    """Epochs (and report times) in [t0_us, t1_us) µs since the Unix epoch; ``index`` counts the
    windows of a run from its grid origin. An end at :data:`T_MIN_US` / :data:`T_MAX_US` is open:
    the first window of a run takes everything before it, the last everything after."""

    index: int
    t0_us: int
    t1_us: int

    @classmethod
    def unbounded(cls, index: int = 0) -> Window:
        """The window over all time: one step is the whole run."""
        return cls(index, T_MIN_US, T_MAX_US)

    @property
    def open_start(self) -> bool:
        """Open to the past (the run's first window)."""
        return self.t0_us <= T_MIN_US

    @property
    def open_end(self) -> bool:
        """Open to the future (the run's last window: every carried row is flushed)."""
        return self.t1_us >= T_MAX_US

    @property
    def last(self) -> bool:
        """The run's last window: the same as :attr:`open_end`."""
        return self.open_end

    @property
    def bounded(self) -> bool:
        """Both ends are finite times."""
        return not (self.open_start or self.open_end)


def check_window(frame: pl.DataFrame, window: Window, *, after_us: int | None = None, column: str = "epoch",
                 table: str = "rows") -> None:
    """The one window check of every stage: ``window`` is not reversed and does not start before
    ``after_us`` (the end of the window the state was carried to; None: a fresh state), and every
    row of ``frame`` has ``column`` (a timestamp) in [t0_us, t1_us).

    Raises :class:`OptionError` for a bad window and :class:`DataError` (naming ``table``) for
    rows outside it or without ``column``."""
    t0, t1 = window.t0_us, window.t1_us
    if t0 > t1:
        raise OptionError(f"window [{t0}, {t1}) µs ends before it starts", option="window")
    if after_us is not None and t0 < after_us:
        raise OptionError(f"window [{t0}, {t1}) µs does not follow the state's end: it starts before the end of "
                          f"the previous one ({after_us} µs)", option="window")
    if frame.height == 0:
        return
    if column not in frame.columns:
        raise DataError(f"no column {column!r}: the rows cannot be placed in the window", path=table)
    t = frame[column].dt.epoch("us")
    lo, hi = t.min(), t.max()
    if lo is None:
        return
    lo, hi = int(lo), int(hi)      # type: ignore[arg-type]
    if lo < t0 or hi >= t1:
        raise DataError(f"{column} outside the window [{t0}, {t1}) µs: rows span [{lo}, {hi}]", path=table)


@runtime_checkable
class Stage(Protocol):
    """One streamed stage, its configuration and fixed context bound at construction.

    ``step`` is pure (the state it is given is not modified) and takes the window's rows of
    each named input; it returns the window's rows of each named output and the state to carry
    to the next window. The state pickles (the engine checkpoints it)."""

    name: str

    def init(self) -> Any:
        """The state before the first window."""
        ...

    def step(self, state: Any, inputs: Mapping[str, pl.DataFrame], window: Window
             ) -> tuple[dict[str, pl.DataFrame], Any]:
        """One window: (outputs, new state)."""
        ...
