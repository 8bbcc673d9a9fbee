"""The truth as the bound reads it (:mod:`tertiary.evaluation.bound`, model M): its samples per
aircraft, the cubic Hermite positions between them, the piecewise-constant acceleration fitted to
their velocities and the deviations (M2) of that trajectory from a constant acceleration."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import TIME
from tertiary.core.units import US

__all__ = ["ACCEL_HALF_WINDOW_S", "COLUMNS", "Truth", "reference_gaps", "truth_gaps"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: half-width (s) of the centred velocity difference that fits the truth's acceleration (model M):
#: long enough to average out the jitter of ADS-B truth's vertical rate, short beside a manoeuvre
ACCEL_HALF_WINDOW_S = 10.0
#: the truth columns the bound reads
COLUMNS = ("truth_id", "time", "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")


def _samples(truth: pl.LazyFrame) -> pl.LazyFrame:
    """The samples the bound uses: complete rows, an aircraft's duplicate times once, in
    (truth_id, time) order (``us``: the time in µs)."""
    return (truth.select(pl.col("truth_id").cast(pl.Int64), pl.col("time").cast(TIME).dt.epoch("us").alias("us"),
                         "x_m", "y_m", "z_m", "vx_mps", "vy_mps", "vz_mps")
            .drop_nulls().unique(["truth_id", "us"], keep="first").sort("truth_id", "us"))


def _gap_frame(samples: pl.LazyFrame, t0_us: int) -> pl.LazyFrame:
    """Per aircraft of :func:`_samples`, ``gap_s``: 1.5 × the median spacing of its samples (in
    seconds from ``t0_us``, the times :class:`Truth` holds), the largest spacing that is not a
    truth gap; none for an aircraft of one sample."""
    t = (pl.col("us") - t0_us) / US
    return (samples.select("truth_id", t.diff().over("truth_id").alias("d"))
            .drop_nulls().group_by("truth_id").agg((1.5 * pl.col("d").median()).alias("gap_s")))


#: rows of the truth :func:`truth_gaps` sorts at a time (memory: a day's 80 M samples sorted at
#: once, with the columns :func:`_samples` keeps, hold about 6 GB)
GAP_PART_ROWS = 8_000_000


def truth_gaps(truth: pl.LazyFrame, t0_us: int, part_rows: int = GAP_PART_ROWS) -> pl.DataFrame:
    """Each aircraft's ``gap_s`` (:func:`_gap_frame`) over its whole ``truth`` (a scan): what a
    :class:`Truth` of a part of its samples takes (:meth:`Truth.of`). The aircraft are taken in
    parts of about ``part_rows`` samples (truth_id modulo the number of parts), each part's
    times alone sorted: the spacing reads no position or velocity, only whether they are there."""
    n = truth.select(pl.len()).collect().item()
    parts = max(1, -(-n // part_rows))
    complete = pl.all_horizontal(pl.col(c).is_not_null() for c in COLUMNS)
    out = []
    for k in range(parts):
        mine = truth.filter(complete & (pl.col("truth_id").cast(pl.Int64) % parts == k))
        samples = (mine.select(pl.col("truth_id").cast(pl.Int64), pl.col("time").cast(TIME).dt.epoch("us").alias("us"))
                   .unique().sort("truth_id", "us"))
        out.append(_gap_frame(samples, t0_us).collect())
    return pl.concat(out).sort("truth_id")


def reference_gaps(reference: pl.LazyFrame, t0_us: int, part_rows: int = GAP_PART_ROWS) -> pl.DataFrame:
    """:func:`truth_gaps` of the run's validated reference (a scan of its files): its rows are
    complete and its (truth_id, time) unique (the truth's contract), and each carries its
    aircraft's previous sample time ``__prev``, so an aircraft's spacings are ``time − __prev``
    as they lie, grouped without sorting the samples and read from three columns."""
    if not {"__prev", "truth_id", "time"} <= set(reference.collect_schema().names()):
        raise ValueError("reference_gaps: the reference files carry truth_id, time and __prev")
    n = reference.select(pl.len()).collect().item()
    parts = max(1, -(-n // part_rows))
    d = (pl.col("time").cast(TIME) - pl.col("__prev").cast(TIME)).dt.total_microseconds() / US
    out = []
    for k in range(parts):
        ident = pl.col("truth_id").cast(pl.Int64)
        mine = reference.filter(ident % parts == k).select(ident, d.alias("d")).drop_nulls()
        out.append(mine.group_by("truth_id").agg((1.5 * pl.col("d").median()).alias("gap_s")).collect())
    return pl.concat(out).sort("truth_id")


@dataclass
class Truth:
    """Truth samples sorted by (aircraft index, time), times in seconds from ``t0_us``; ``key`` =
    index · span + t is increasing, so one ``searchsorted`` brackets every query."""

    ids: NDArray[np.int64]
    first: I64
    count: I64
    t: F64
    pos: F64
    vel: F64
    span: float
    key: F64
    gap_s: F64
    half_window_s: float = ACCEL_HALF_WINDOW_S
    t0_us: int = 0

    @classmethod
    def of(cls, truth: pl.DataFrame, t0_us: int, half_window_s: float = ACCEL_HALF_WINDOW_S,
           gaps: pl.DataFrame | None = None) -> "Truth":
        """The samples of ``truth`` (the bound's columns; an aircraft's duplicate times once)
        from ``t0_us``; ``gaps``: each aircraft's :func:`truth_gaps` when ``truth`` is a part of
        its samples (the largest spacing that is not a gap, and the acceleration's half-width in
        samples, are the whole truth's), else taken from ``truth``."""
        tr = _samples(truth.lazy()).collect()
        ids, first, count = np.unique(tr["truth_id"].to_numpy(), return_index=True, return_counts=True)
        t = (tr["us"].to_numpy() - t0_us) / US
        span = 2.0 * float(np.abs(t).max(initial=0.0)) + 10.0
        owner = np.repeat(np.arange(len(ids)), count)
        known = _gap_frame(tr.lazy(), t0_us).collect() if gaps is None else gaps
        gap = (pl.DataFrame({"truth_id": ids}).join(known, on="truth_id", how="left",
                                                         maintain_order="left")["gap_s"]
               .fill_null(np.inf).to_numpy())
        return cls(ids, first, count, t, tr.select("x_m", "y_m", "z_m").to_numpy(),
                   tr.select("vx_mps", "vy_mps", "vz_mps").to_numpy(), span, owner * span + t, gap, half_window_s,
                   t0_us)

    @functools.cached_property
    def accel(self) -> F64:
        """ā (n, 3) on the interval that starts at each sample: the centred velocity difference
        over ± ``half_window_s`` (W samples of the aircraft's median spacing), clipped to the
        aircraft's span (module docstring, M1–M2); 0 for an aircraft of one sample."""
        owner = np.repeat(np.arange(len(self.ids)), self.count)
        lo_a, hi_a = self.first[owner], self.first[owner] + self.count[owner] - 1
        spacing = self.gap_s[owner] / 1.5
        w = np.where(np.isfinite(spacing), np.round(self.half_window_s / np.where(spacing > 0, spacing, 1.0)), 0.0)
        j = np.arange(len(self.t))
        hi = np.minimum(j + 1 + w.astype(np.int64), hi_a)
        lo = np.minimum(np.maximum(j - w.astype(np.int64), lo_a), np.maximum(hi - 1, lo_a))
        h = self.t[hi] - self.t[lo]
        return np.where((h > 0)[:, None], (self.vel[hi] - self.vel[lo]) / np.where(h > 0, h, 1.0)[:, None], 0.0)

    @functools.cached_property
    def _steps(self) -> tuple[F64, F64, F64]:
        """Per aircraft, the running sums C_r = Σ_{m ≤ j} Δa_m τ_m^r (r = 0, 1, 2; τ from the
        aircraft's first sample) of the acceleration steps Δa_m = ā_m − ā_{m−1} (none at the
        first sample): (M2) over any interval is a difference of them."""
        owner = np.repeat(np.arange(len(self.ids)), self.count)
        acc = self.accel
        step = np.zeros_like(acc)
        same = owner[1:] == owner[:-1]
        step[1:][same] = (acc[1:] - acc[:-1])[same]
        tau = (self.t - self.t[self.first[owner]])[:, None]
        cols = {f"{r}{k}": (step * tau ** r)[:, k] for r in range(3) for k in range(3)}
        c = pl.DataFrame({"a": owner, **cols}).select(pl.exclude("a").cum_sum().over("a")).to_numpy()
        return c[:, 0:3], c[:, 3:6], c[:, 6:9]

    def deviations(self, a: I64, t: F64, first: NDArray[np.bool_]) -> tuple[F64, F64]:
        """For rows of aircraft index ``a`` (−1: not in the truth) at times ``t`` in sequence
        order (``first``: a sequence's first row): d (n, 3 axes, 3) of (M2) over the interval
        from the previous row (0 at a first row) and the truth's ā (n, 3) at each row."""
        known = a >= 0
        ak = np.where(known, a, 0)
        lo, hi = self.first[ak], self.first[ak] + self.count[ak] - 1
        j = np.clip(np.searchsorted(self.key, ak * self.span + t, side="right") - 1, lo, hi)
        c0, c1, c2 = (c[j] for c in self._steps)
        prev = np.r_[0, np.arange(len(t) - 1)]
        d0, d1, d2 = c0 - c0[prev], c1 - c1[prev], c2 - c2[prev]
        big_t = (t - self.t[lo])[:, None]
        dev = np.stack([0.5 * (big_t * big_t * d0 - 2.0 * big_t * d1 + d2), big_t * d0 - d1, d0], axis=-1)
        dev[first | ~known] = 0.0
        return dev, np.where(known[:, None], self.accel[j], 0.0)

    @functools.cached_property
    def top_speed(self) -> float:
        """The fastest any aircraft moves (m/s): its largest velocity sample, or the chord
        between two consecutive samples (gaps included) when that is faster."""
        same = np.repeat(np.arange(len(self.ids)), self.count)
        one = same[1:] == same[:-1]
        dt = np.diff(self.t)[one]
        chord = np.linalg.norm(np.diff(self.pos, axis=0)[one], axis=1) / np.where(dt > 0, dt, np.inf)
        return float(max(np.linalg.norm(self.vel, axis=1).max(initial=0.0), chord.max(initial=0.0)))

    def velocity_at(self, a: I64, t: F64) -> F64:
        """The truth's sampled velocities of aircraft index ``a`` interpolated linearly to ``t``
        (clipped to the aircraft's span)."""
        lo, hi = self.first[a], self.first[a] + self.count[a] - 1
        j = np.clip(np.searchsorted(self.key, a * self.span + t, side="right") - 1, lo, np.maximum(hi - 1, lo))
        j1 = np.minimum(j + 1, hi)
        h = self.t[j1] - self.t[j]
        s = np.clip((t - self.t[j]) / np.where(h > 0, h, 1.0), 0.0, 1.0)[:, None]
        return (1.0 - s) * self.vel[j] + s * self.vel[j1]

    def at(self, a: I64, t: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Cubic Hermite position of aircraft index ``a`` at ``t`` (the simulator's
        interpolation) and its validity: inside the aircraft's span and not across a truth gap."""
        lo, hi = self.first[a], self.first[a] + self.count[a] - 1
        j = np.searchsorted(self.key, a * self.span + t, side="right") - 1
        ok = (j >= lo) & (j <= hi)
        j = np.clip(j, lo, np.maximum(hi - 1, lo))
        j1 = np.minimum(j + 1, hi)
        h = self.t[j1] - self.t[j]
        ok &= ((h > 0) & (h <= self.gap_s[a]) & (t <= self.t[j1])) | (j1 == j)
        s = np.clip((t - self.t[j]) / np.where(h > 0, h, 1.0), 0.0, 1.0)[:, None]
        p0, p1, v0, v1 = self.pos[j], self.pos[j1], self.vel[j] * h[:, None], self.vel[j1] * h[:, None]
        s2, s3 = s * s, s * s * s
        pos = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * v0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * v1
        return pos, ok & (np.abs(t - self.t[j]) <= np.maximum(h, 0.0) + 1e-9)


