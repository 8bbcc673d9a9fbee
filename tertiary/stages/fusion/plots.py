"""Each report's plot in the system frame, as the measurement-level consumers take it (the
centralised reference, :mod:`tertiary.stages.fusion.centralized`, and the fusion stage's plot
fusion, :mod:`tertiary.stages.fusion.measurement`): a radar's polar plot converted with its
nominal covariance (seed 002 eq. 12), an MLAT plot as it is, and a Mode S reply's downlinked
velocity turned into the system frame's axes."""

from __future__ import annotations

from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.sensors import mlat
from tertiary.sensors.local_tracks import measurement_polar
from tertiary.stages.align import conversion_valid

__all__ = ["EHS_VELOCITY_COLUMNS", "converted_plots", "debias_enu", "downlinked_velocity", "float_column",
           "plot_validity"]

F64 = NDArray[np.float64]


def debias_enu(local: F64, var_az: F64, var_el: F64) -> F64:
    """Multiplicative unbiased conversion of radar-local ENU plots (Mo Longbin et al. 1998;
    seed 002 §2.4 "debiased conversion"): with Gaussian angle errors E[cos(β + w)] = λ cos β,
    λ = exp(−σ²/2), so the measured (e, n) are shrunk by λ_β λ_ε and u by λ_ε on average;
    dividing by those factors removes the bias. The covariance stays the linearised J R Jᵀ."""
    lam_az, lam_el = np.exp(-0.5 * var_az), np.exp(-0.5 * var_el)
    out = local.copy()
    out[:, :2] /= (lam_az * lam_el)[:, None]
    out[:, 2] /= lam_el
    return out


def plot_validity(reports: pl.DataFrame, radars: pl.DataFrame, altitude_sigma_m: float = 30.0) -> NDArray[np.bool_]:
    """Seed 002 (13) validity gate of each plot's conversion (:func:`tertiary.stages.align.conversion_valid`)
    with the variances the centralised filter uses (elevation from Mode C where the plot has none)."""
    polar, var = measurement_polar(reports, radars, altitude_sigma_m)
    return (conversion_valid(polar[:, 0], np.sqrt(var[:, 0]), np.sqrt(var[:, 1]), np.sqrt(var[:, 2]))
            | mlat.is_mlat(reports, radars))


#: the report columns of a downlinked ground velocity and its turn rate (Mode S BDS 5,0)
EHS_VELOCITY_COLUMNS = ("ehs_gs_mps", "ehs_track_deg", "ehs_track_rate_dps", "ehs_vrate_mps")


def float_column(frame: pl.DataFrame, name: str) -> F64:
    """Column ``name`` of ``frame`` as float64 with NaN for null (all NaN when it is absent)."""
    if name not in frame.columns:
        return np.full(frame.height, np.nan)
    return frame[name].cast(pl.Float64).fill_null(np.nan).to_numpy()


def downlinked_velocity(reports: pl.DataFrame, z: F64, origin: geo.LocalFrame) -> F64:
    """(n, 4): each report's downlinked ground velocity (Mode S BDS 5,0 ground speed
    ``ehs_gs_mps`` along the true track ``ehs_track_deg``) as system-frame east and north
    components, its track-angle rate ``ehs_track_rate_dps`` as ω (rad/s, counter-clockwise:
    the register's rate is clockwise positive) and its vertical rate ``ehs_vrate_mps`` (BDS 6,0,
    along the local vertical: the rate of the altitude channel). The track is over true north at the aircraft
    (the plot ``z``), so the velocity is turned into the system frame's axes there
    (:func:`tertiary.core.geo.local_vector_to_frame`: the meridian convergence, several degrees
    at a national system's edge), with the vertical rate along the local vertical where the
    report has one: away from the origin the local vertical leans over the system frame's
    (the great-circle angle to the origin), so a climb at 20 m/s 300 km out moves the aircraft
    1 m/s horizontally in the system frame. NaN where the report or its plot has none."""
    gs, track = float_column(reports, "ehs_gs_mps"), np.radians(float_column(reports, "ehs_track_deg"))
    out = np.full((len(gs), 4), np.nan)
    out[:, 2] = -np.radians(float_column(reports, "ehs_track_rate_dps"))
    out[:, 3] = float_column(reports, "ehs_vrate_mps")
    ok = np.isfinite(gs) & np.isfinite(track) & np.isfinite(z).all(axis=1)
    if ok.any():
        lat, lon, _ = origin.to_geodetic(z[ok, 0], z[ok, 1], z[ok, 2])
        up = np.nan_to_num(out[ok, 3])         # no vertical rate: the horizontal velocity alone
        e, n, _ = geo.local_vector_to_frame(gs[ok] * np.sin(track[ok]), gs[ok] * np.cos(track[ok]), up,
                                            lat, lon, origin)
        out[ok, 0], out[ok, 1] = e, n
    return out


def converted_plots(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
                    altitude_sigma_m: float = 30.0, *, conversion: Literal["linear", "debiased"] = "linear",
                    gate: bool = False) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Each report's plot in the system frame: z (n, 3), R (n, 3, 3) = M J R_polar Jᵀ Mᵀ from the
    radar's nominal sigmas (seed 002 eq. 12), and a validity mask (False where neither an
    elevation nor a Mode C altitude is available, and with ``gate`` where the seed 002 (13)
    linearisation condition fails). ``conversion="debiased"``: :func:`debias_enu`.

    An MLAT report's plot is Cartesian: z and R of (MLAT-1)–(MLAT-2)
    (:func:`tertiary.sensors.mlat.system_plots`), neither converted nor gated."""
    n = reports.height
    polar, var = measurement_polar(reports, radars, altitude_sigma_m)   # (range, az rad, el rad)
    cart = mlat.is_mlat(reports, radars)
    ok = np.all(np.isfinite(polar), axis=1) & ~cart
    if gate:
        ok &= conversion_valid(polar[:, 0], np.sqrt(var[:, 0]), np.sqrt(var[:, 1]), np.sqrt(var[:, 2]))
    z = np.full((n, 3), np.nan)
    r = np.full((n, 3, 3), np.nan)
    rid = reports["radar_id"].to_numpy()
    for row in radars.iter_rows(named=True):            # a handful of radars, not reports
        sel = np.flatnonzero((rid == row["radar_id"]) & ok)
        if sel.size == 0:
            continue
        site = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
        rng, az, el = polar[sel, 0], np.degrees(polar[sel, 1]), np.degrees(polar[sel, 2])
        local = np.stack(geo.polar_to_enu(rng, az, el), axis=-1)
        if conversion == "debiased":
            local = debias_enu(local, var[sel, 1], var[sel, 2])
        z[sel] = geo.frame_to_frame(local, site, origin)[0]
        # G = M J as one (n·3, 3) @ (3, 3) product; R = G R_polar Gᵀ with R_polar diagonal
        # (cheaper than two generic batched sandwiches)
        jac = geo.polar_jacobian(rng, az, el)
        g = (jac.swapaxes(1, 2).reshape(-1, 3) @ site.rotation_to(origin).T).reshape(-1, 3, 3).swapaxes(1, 2)
        r[sel] = (g * var[sel][:, None, :]) @ g.swapaxes(1, 2)
    if cart.any():
        rows = np.flatnonzero(cart)
        zc, rc, okc = mlat.system_plots(reports[rows], radars, origin, altitude_sigma_m)
        z[rows], r[rows], ok[rows] = zc, rc, okc
    ok &= np.all(np.isfinite(z), axis=1)
    return z, r, ok
