"""The measurements of the bound (:mod:`tertiary.evaluation.bound`) beside a radar's polar plot:
the Mode C / Mode S altitude a plot carries, and a Mode S aircraft's downlinked ground velocity.
Each is given as its covariance in the system frame's axes at the aircraft, for the recursion's
update; neither is read from the data's values, only from the truth's geometry.
"""

from __future__ import annotations

import numpy as np
import polars as pl
from numpy.typing import NDArray

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

__all__ = ["HEIGHT_VAR_M2", "VELOCITY_VERTICAL_VAR", "local_axes", "mode_s_aircraft", "velocity_covariance",
           "with_height"]


def local_axes(pos: F64, origin: geo.LocalFrame) -> F64:
    """(n, 3, 3) L: rows the east, north and up unit vectors at each system-frame point ``pos``
    (n, 3) in the system axes (L v_sys = v_local)."""
    lat, lon, _ = origin.to_geodetic(pos[:, 0], pos[:, 1], pos[:, 2])
    return np.stack([np.stack(geo.local_vector_to_frame(*e, lat, lon, origin), axis=-1)
                     for e in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))], axis=1)


def mode_s_aircraft(ids: NDArray[np.int64], reports: pl.DataFrame) -> NDArray[np.bool_]:
    """Per aircraft id of ``ids``: whether any of its reports carries a Mode S address."""
    if not {"truth_id", "mode_s"} <= set(reports.columns):
        return np.zeros(len(ids), bool)
    ms = reports.filter(pl.col("mode_s").is_not_null()).select(pl.col("truth_id").cast(pl.Int64)).drop_nulls()
    return np.isin(ids, ms.unique().to_series().to_numpy())


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
