"""The measurements of the bound (:mod:`tertiary.evaluation.bound`) beside a radar's polar plot:
the Mode C / Mode S altitude a plot carries, and a Mode S aircraft's downlinked ground velocity.
Each is given as its covariance in the system frame's axes at the aircraft, for the recursion's
update; neither is read from the data's values, only from the truth's geometry.
"""

from __future__ import annotations

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.contract import TIME
from tertiary.core import geo
from tertiary.core.units import FT

F64 = NDArray[np.float64]

#: variance ((m/s)²) along the aircraft's vertical of a downlinked ground velocity: a horizontal
#: measurement, no vertical information
VELOCITY_VERTICAL_VAR = 1e10
#: variance (m²) of a plot's barometric height: the finest quantisation's q²/12 (25 ft, Mode S),
#: at least the information any reply holds (a Gaussian stand-in: a quantised reply has no regular
#: Fisher information, and the stand-in's is the larger)
HEIGHT_VAR_M2 = (25.0 * FT) ** 2 / 12.0

__all__ = ["HEIGHT_VAR_M2", "MODE_S_FIRST", "VELOCITY_VERTICAL_VAR", "local_axes", "mode_s_first",
           "velocity_covariance", "with_height"]


def local_axes(pos: F64, origin: geo.LocalFrame) -> F64:
    """(n, 3, 3) L: rows the east, north and up unit vectors at each system-frame point ``pos``
    (n, 3) in the system axes (L v_sys = v_local)."""
    lat, lon, _ = origin.to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
    return np.stack([np.stack(geo.local_vector_to_frame(*e, lat, lon, origin), axis=-1)
                     for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))], axis=1)


def mode_s_first(reports: pl.DataFrame) -> pl.DataFrame:
    """Per aircraft (truth_id) with a report that carries a Mode S address, the time of its first
    such report, ``first_us`` (µs): its downlinked velocity counts from then on."""
    if not {"truth_id", "mode_s"} <= set(reports.columns) or reports.is_empty():
        return pl.DataFrame(schema=MODE_S_FIRST)
    ms = reports.filter(pl.col("mode_s").is_not_null() & pl.col("truth_id").is_not_null())
    return (ms.group_by(pl.col("truth_id").cast(pl.Int64))
            .agg(pl.col("time").cast(TIME).dt.epoch("us").min().alias("first_us")).sort("truth_id"))


#: :func:`mode_s_first`'s columns
MODE_S_FIRST = {"truth_id": pl.Int64, "first_us": pl.Int64}


def velocity_covariance(pos: F64, vel: F64, origin: geo.LocalFrame, speed_sigma_mps: float,
                        track_sigma_deg: float) -> F64:
    """(n, 3, 3) covariance, in the system axes, of a downlinked ground velocity of an aircraft
    at ``pos`` flying ``vel`` (system frame): σ ``speed_sigma_mps`` along its track and its
    speed × ``track_sigma_deg`` across it in the horizontal plane at the aircraft,
    :data:`VELOCITY_VERTICAL_VAR` along its vertical."""
    axes = local_axes(pos, origin)
    v_loc = np.einsum("nij,nj->ni", axes, vel)
    speed = np.hypot(v_loc[:, 0], v_loc[:, 1])
    u = np.where(speed[:, None] > 0, v_loc[:, :2] / np.where(speed > 0, speed, 1.0)[:, None], [0.0, 1.0])
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    r = np.zeros((len(pos), 3, 3))
    cross = (speed * np.radians(track_sigma_deg)) ** 2
    r[:, :2, :2] = (speed_sigma_mps ** 2 * u[:, :, None] * u[:, None, :]
                    + cross[:, None, None] * nrm[:, :, None] * nrm[:, None, :])
    r[:, 2, 2] = VELOCITY_VERTICAL_VAR
    return np.einsum("nki,nkl,nlj->nij", axes, r, axes)


def with_height(r_plot: F64, pos: F64, origin: geo.LocalFrame) -> F64:
    """(n, 3, 3) the inverse information of a polar plot of covariance ``r_plot`` (system axes)
    together with its barometric height: (R⁻¹ + e eᵀ / :data:`HEIGHT_VAR_M2`)⁻¹, e the local
    vertical at the aircraft. The pictures' plots take their elevation from that height, which at
    long range pins the ground range and so the horizontal position as well."""
    up = local_axes(pos, origin)[:, 2]
    info = np.linalg.inv(r_plot) + up[:, :, None] * up[:, None, :] / HEIGHT_VAR_M2
    return np.linalg.inv(info)
