"""The state of the radars' plot-to-track association (:mod:`tertiary.simulate.radar_tracker`):
the live tracks of every partition, shared by the Python reference and the compiled loop
(:mod:`tertiary.simulate.radar_scan_kernel`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

#: layout version of a :class:`RadarTrackState`
STATE_VERSION = 1


@dataclass(frozen=True)
class RadarTrackState:
    """Live tracks of every partition, sorted by (part, number); carried from scan to scan."""

    part: NDArray[np.int64]          # partition (radar × run)
    number: NDArray[np.int64]        # track number (≥ 1, unique in its partition)
    t: NDArray[np.float64]           # time of the last plot (s)
    x: NDArray[np.float64]           # (n, 4) x, y, ẋ, ẏ at t (radar ground plane, m, m/s)
    p: NDArray[np.float64]           # (n, 4, 4) covariance at t
    hits: NDArray[np.int64]
    misses: NDArray[np.int64]        # consecutive scans without a plot
    confirmed: NDArray[np.bool_]
    mode_s: NDArray[np.int64]        # last Mode S address seen (-1 none)
    mode_3a: NDArray[np.int64]       # last Mode 3/A code seen (-1 none)
    period: NDArray[np.float64]      # the radar's scan period (s)
    drop_misses: NDArray[np.int64]   # a confirmed track is deleted at this many misses
    life: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))   # unique per track life
    next_life: int = 0
    #: numbers of deleted tracks not yet free again: partition, number, scans left
    held_part: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    held_number: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    held_scans: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    version: int = STATE_VERSION

    def __len__(self) -> int:
        return len(self.part)

    def take(self, idx: NDArray[np.int64]) -> "RadarTrackState":
        """The tracks ``idx`` (held numbers unchanged)."""
        return replace(self, **{f: getattr(self, f)[idx] for f in TRACK_FIELDS})


#: per-track columns of :class:`RadarTrackState`
TRACK_FIELDS = ("part", "number", "t", "x", "p", "hits", "misses", "confirmed", "mode_s", "mode_3a", "period",
                "drop_misses", "life")


def init_state() -> RadarTrackState:
    """No track anywhere."""
    i, f = np.zeros(0, np.int64), np.zeros(0)
    return RadarTrackState(part=i, number=i, t=f, x=np.zeros((0, 4)), p=np.zeros((0, 4, 4)), hits=i, misses=i,
                           confirmed=np.zeros(0, bool), mode_s=i, mode_3a=i, period=f, drop_misses=i)
