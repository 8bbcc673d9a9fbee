"""The noise of the downlinked Mode S registers, measured from the recording itself.

The tracker weighs a downlinked ground velocity (BDS 5,0 ground speed and true track) and
vertical rate (BDS 6,0) by their error variances. Fixed a priori they are a guess about avionics
no one on the ground knows; too large, the tracks' velocity covariance overstates the error, and
the conflict prediction, which grows that covariance by t² over its look-ahead, widens its
thresholds for nothing. So they are measured before the first window, from the replies.

Estimator: a register read by one radar from one aircraft, scan after scan, is the aircraft's
value plus an error. Over three consecutive, equally spaced replies (k−1, k, k+1) the second
difference y₊ − 2y + y₋ cancels a constant value and a constant rate of change (a steady
acceleration, a constant-rate turn or climb) and leaves the errors' combination, of variance
6σ² for independent errors. The onsets and ends of manoeuvres are few and large: the largest
``1 − TRIM`` of the |second differences| are left out and the trimmed second moment corrected
for the trimming of a normal distribution (:func:`trimmed_sigma`). The error measured is the
register's whole error as it reaches the ground, its quantisation (the LSB) included; an error
correlated over more than a scan (a slowly drifting navigation solution) cancels partly and is
under-measured — the figure is the scan-to-scan noise.

The track angle's second difference (wrapped, degrees) is taken only above
:data:`MIN_SPEED_MPS`, where the angle is defined well; it is the σ of
``velocity_track_sigma_deg``. A register with fewer than :data:`MIN_TRIPLES` usable triples keeps
the configured value.
"""

from __future__ import annotations

import dataclasses
import math
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
import polars as pl

__all__ = ["DownlinkNoise", "MIN_TRIPLES", "SAMPLE_ROWS", "TRIM", "downlink_noise", "trimmed_sigma", "with_noise"]

#: the least number of usable triples a register's σ is measured from
MIN_TRIPLES = 200
#: the replies read (in the input's order): the noise of a register does not change over a day
SAMPLE_ROWS = 2_000_000
#: the fraction of the smallest |second differences| kept
TRIM = 0.95
#: the speed above which a true track angle is used (m/s)
MIN_SPEED_MPS = 50.0
#: consecutive replies further apart than this are not of one series (s)
MAX_GAP_S = 30.0
#: two intervals of a triple count as equal within this fraction of the longer
SPACING_TOL = 0.1

_KEYS = ("radar_id", "mode_s")
_FIELDS = {"speed": "ehs_gs_mps", "track": "ehs_track_deg", "vrate": "ehs_vrate_mps"}


class DownlinkNoise(NamedTuple):
    """Measured σ of each register (None: not measured) and the triples each rests on."""

    speed_mps: float | None
    track_deg: float | None
    vrate_mps: float | None
    triples: dict[str, int]

    def describe(self) -> str:
        """One line for the run's notes."""
        parts = []
        for name, key, value, unit in (("ground speed", "speed", self.speed_mps, " m/s"),
                                       ("true track", "track", self.track_deg, "°"),
                                       ("vertical rate", "vrate", self.vrate_mps, " m/s")):
            n = self.triples.get(key, 0)
            parts.append(f"{name} σ {value:.3g}{unit} ({n:,} triples)" if value is not None
                         else f"{name} not measured ({n:,} triples)")
        return "downlinked registers' noise measured from scan-to-scan replies: " + ", ".join(parts)


def trimmed_sigma(d2: np.ndarray, trim: float = TRIM) -> float:
    """σ of the errors behind second differences ``d2`` of independent errors (variance 6σ²):
    the mean of d2² over the ``trim`` fraction of smallest |d2|, divided by 6 and by the
    fraction of a normal variance that trimming keeps, 1 − 2zφ(z)/p with z the p = ``trim``
    two-sided quantile."""
    d2 = np.asarray(d2, float)
    d2 = d2[np.isfinite(d2)]
    if not d2.size:
        return math.nan
    keep = np.sort(np.abs(d2))[: max(1, int(math.floor(trim * d2.size)))]
    z = NormalDist().inv_cdf(0.5 + trim / 2.0)
    kept = 1.0 - 2.0 * z * NormalDist().pdf(z) / trim
    return float(math.sqrt(np.mean(keep ** 2) / (6.0 * kept)))


def _second_differences(lf: pl.LazyFrame, column: str, keys: list[str], angle: bool) -> np.ndarray:
    """Second differences of ``column`` over equally spaced consecutive replies of one series."""
    y = pl.col(column)
    t = pl.col("time").dt.epoch("us").cast(pl.Float64) / 1e6
    f = (lf.filter(y.is_not_null() & y.is_not_nan() & pl.col("mode_s").is_not_null())
         .sort(*keys, "time")
         .with_columns(t.alias("__t"))
         .with_columns(dt1=pl.col("__t").diff().over(keys), dt2=(-pl.col("__t").diff(-1)).over(keys),
                       d1=y.diff().over(keys), d2=(-y.diff(-1)).over(keys)))
    if angle:      # wrapped to (−180, 180]: a track across north is not a 360° jump
        f = f.with_columns(((pl.col(c) + 180.0) % 360.0 - 180.0).alias(c) for c in ("d1", "d2"))
    longer = pl.max_horizontal("dt1", "dt2")
    ok = ((pl.col("dt1") > 0) & (pl.col("dt2") > 0) & (longer <= MAX_GAP_S)
          & ((pl.col("dt1") - pl.col("dt2")).abs() <= SPACING_TOL * longer))
    if angle:
        ok = ok & (pl.col("ehs_gs_mps") >= MIN_SPEED_MPS)
    return f.filter(ok).select(pl.col("d2") - pl.col("d1")).collect()[:, 0].to_numpy()


def downlink_noise(reports: pl.DataFrame | pl.LazyFrame, sample_rows: int = SAMPLE_ROWS) -> DownlinkNoise:
    """The σ of each downlinked register measured from the first ``sample_rows`` replies that
    carry one (module docstring); None for a register the reports lack or too few triples of."""
    lf = reports.lazy()
    names = lf.collect_schema().names()
    keys = [*(["run"] if "run" in names else []), *_KEYS]
    present = [c for c in _FIELDS.values() if c in names]
    schema = lf.collect_schema()
    if not present or any(k not in names for k in (*_KEYS, "time")) or not isinstance(schema["time"], pl.Datetime):
        return DownlinkNoise(None, None, None, {})
    # the input as it came, before validation: a value that is not a number is not a reply's
    cols = [*keys, "time", *(pl.col(c).cast(pl.Float64, strict=False) for c in present)]
    sample = (lf.select(cols).filter(pl.col("mode_s").is_not_null()
                                     & pl.any_horizontal(pl.col(c).is_not_null() for c in present))
              .head(sample_rows).collect().lazy())
    out: dict[str, float | None] = {}
    counts: dict[str, int] = {}
    for name, column in _FIELDS.items():
        if column not in present or (name == "track" and "ehs_gs_mps" not in present):
            out[name] = None
            continue
        d2 = _second_differences(sample, column, keys, angle=name == "track")
        counts[name] = int(d2.size)
        out[name] = trimmed_sigma(d2) if d2.size >= MIN_TRIPLES else None
    return DownlinkNoise(out["speed"], out["track"], out["vrate"], counts)


def with_noise(cfg, noise: DownlinkNoise):  # noqa: ANN001, ANN201 - a PipelineConfig (import cycle)
    """``cfg`` (a :class:`tertiary.pipeline.PipelineConfig`) with the measured σ in every filter
    that weighs a downlinked register: the tracker's ground velocity and vertical rate, and the
    vertical rate of each altitude channel (tracker, fusion, centralised reference); a register
    not measured keeps its configured σ."""
    tr = cfg.tracker
    v = noise.vrate_mps
    alt = lambda a: a if v is None else dataclasses.replace(a, vertical_rate_sigma_mps=v)   # noqa: E731
    tr = dataclasses.replace(
        tr, calibrate_downlinks=False, altitude=alt(tr.altitude),
        measured_downlinks=noise.describe() if any(x is not None for x in noise[:3]) else "",
        velocity_speed_sigma_mps=tr.velocity_speed_sigma_mps if noise.speed_mps is None else noise.speed_mps,
        velocity_track_sigma_deg=tr.velocity_track_sigma_deg if noise.track_deg is None else noise.track_deg,
        vertical_rate_sigma_mps=tr.vertical_rate_sigma_mps if v is None else v)
    return dataclasses.replace(
        cfg, tracker=tr, fusion=dataclasses.replace(cfg.fusion, altitude=alt(cfg.fusion.altitude)),
        centralized_cfg=dataclasses.replace(cfg.centralized_cfg, altitude=alt(cfg.centralized_cfg.altitude)))
