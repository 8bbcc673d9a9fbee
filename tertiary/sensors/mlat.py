"""The Cartesian measurement model of a multilateration / WAM sensor (``radars.kind == "mlat"``),
shared by ADS-B ground stations (kind ``"adsb"``, :mod:`tertiary.sensors.adsb`): both report a
position, not a range and azimuth.

An MLAT report is a plot (x, y) in the sensor's local ENU frame at its site, with the accuracy
(σx, σy, σxy-term) the system states for it (``tertiary.contract.MLAT_PLOT_COLUMNS``). Its height
is not multilaterated here: like a radar plot without elevation, the plot is placed at its
Mode C altitude (or at ``plot_height_m``, the geometric height, when given). So

    z_local = (x, y, u(x, y, h)),     R_local = [[σx², c, 0], [c, σy², 0], [0, 0, σ_h²]],
    c = sign(t)·t²  (t = plot_sigma_xy_m, the ASTERIX I020/500 convention)          (MLAT-1)

with u from :func:`tertiary.core.geo.up_at_height` and σ_h the Mode C accuracy (an ADS-B report
without stated σ takes σx = σy from its NACp, (ADSB-1), and c = 0); to the system frame
by the exact affine transform of :func:`tertiary.core.geo.frame_to_frame`:

    z = M z_local + o,     R = M R_local Mᵀ                                          (MLAT-2)

(M the site-to-system rotation, o the site in the system frame). No polar conversion enters:
the measurement is linear in the position (H = [I₃ 0]), so R is exact and no linearisation
validity rule applies. A report without σ gets its sensor's nominal ``sigma_range_m`` on x and y.
"""

from __future__ import annotations

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.sensors.adsb import ADSB, sigma_from_nacp

__all__ = ["CARTESIAN_KINDS", "MLAT", "cartesian_estimates", "is_mlat", "local_plots", "mlat_ids", "plot_cov_xy", "radial_innovation",
           "system_plots"]

F64 = NDArray[np.float64]

#: the ``radars.kind`` of a multilateration / WAM sensor
MLAT = "mlat"
#: the sensor kinds whose reports are Cartesian plots (this module's measurement model)
CARTESIAN_KINDS = (MLAT, ADSB)


def mlat_ids(radars: pl.DataFrame) -> NDArray[np.int64]:
    """The radar_ids of the sensors whose reports are Cartesian plots (kinds
    :data:`CARTESIAN_KINDS`; none without a ``kind`` column)."""
    if "kind" not in radars.columns or radars.height == 0:
        return np.zeros(0, np.int64)
    return radars.filter(pl.col("kind").is_in(CARTESIAN_KINDS))["radar_id"].cast(pl.Int64).to_numpy()


def is_mlat(reports: pl.DataFrame, radars: pl.DataFrame) -> NDArray[np.bool_]:
    """Per report: whether its sensor reports Cartesian plots (MLAT / WAM or ADS-B)."""
    ids = mlat_ids(radars)
    if ids.size == 0 or reports.height == 0:
        return np.zeros(reports.height, bool)
    return np.isin(reports["radar_id"].cast(pl.Int64).to_numpy(), ids)


def plot_cov_xy(sigma_x: F64, sigma_y: F64, sigma_xy_term: F64) -> F64:
    """(n, 2, 2) horizontal covariance of (MLAT-1): σx², σy² and the x-y covariance sign(t)·t²."""
    sx, sy, t = (np.asarray(v, float) for v in (sigma_x, sigma_y, sigma_xy_term))
    r = np.empty(sx.shape + (2, 2))
    r[..., 0, 0], r[..., 1, 1] = sx * sx, sy * sy
    r[..., 0, 1] = r[..., 1, 0] = np.sign(t) * t * t
    return r


def _col(df: pl.DataFrame, name: str) -> F64:
    return (df[name].cast(pl.Float64).fill_null(np.nan).to_numpy() if name in df.columns
            else np.full(df.height, np.nan))


def local_plots(reports: pl.DataFrame, radars: pl.DataFrame, altitude_sigma_m: float
                ) -> tuple[F64, F64]:
    """(MLAT-1) per report: z (n, 3) in its sensor's local ENU and R (n, 3, 3); NaN on the rows
    of other sensors and where no height is known (no Mode C, no ``plot_height_m``)."""
    n = reports.height
    z, r = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    rows = np.flatnonzero(is_mlat(reports, radars))
    if rows.size == 0:
        return z, r
    sub = reports[rows]
    site = sub.select(pl.col("radar_id").cast(pl.Int64)).join(
        radars.select(pl.col("radar_id").cast(pl.Int64), "lat_deg", "lon_deg", "alt_m", "sigma_range_m"),
        on="radar_id", how="left", maintain_order="left")
    x, y = _col(sub, "plot_x_m"), _col(sub, "plot_y_m")
    h = np.where(np.isfinite(_col(sub, "plot_height_m")), _col(sub, "plot_height_m"), _col(sub, "altitude_m"))
    nominal = site["sigma_range_m"].to_numpy()
    sx, sy = _col(sub, "plot_sigma_x_m"), _col(sub, "plot_sigma_y_m")
    stated = np.isfinite(sx) & np.isfinite(sy)
    declared = sigma_from_nacp(_col(sub, "adsb_nacp"))       # (ADSB-1) where σ is not stated
    nominal = np.where(np.isfinite(declared), declared, nominal)
    sxy = np.where(stated & np.isfinite(_col(sub, "plot_sigma_xy_m")), _col(sub, "plot_sigma_xy_m"), 0.0)
    rl = np.zeros((rows.size, 3, 3))
    rl[:, :2, :2] = plot_cov_xy(np.where(stated, sx, nominal), np.where(stated, sy, nominal), sxy)
    rl[:, 2, 2] = altitude_sigma_m ** 2
    u = np.full(rows.size, np.nan)
    rid = site["radar_id"].to_numpy()
    for row in site.unique("radar_id").iter_rows(named=True):     # a few sensors, not reports
        sel = np.flatnonzero((rid == row["radar_id"]) & np.isfinite(h))
        if sel.size:
            frame = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
            u[sel] = geo.up_at_height(frame, x[sel], y[sel], h[sel])
    z[rows] = np.column_stack([x, y, u])
    r[rows] = rl
    return z, r


def system_plots(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame, altitude_sigma_m: float
                 ) -> tuple[F64, F64, NDArray[np.bool_]]:
    """(MLAT-2): each MLAT report's plot z (n, 3) and covariance R (n, 3, 3) in the system frame
    and a mask of the rows that have a plot (other sensors' rows and plots without height:
    False; R does not depend on the height, so it is given on those too)."""
    z, r = local_plots(reports, radars, altitude_sigma_m)
    ok = np.isfinite(z).all(axis=1) & np.isfinite(r).all(axis=(1, 2))
    has_r = np.isfinite(r).all(axis=(1, 2))
    rid = reports["radar_id"].cast(pl.Int64).to_numpy() if reports.height else np.zeros(0, np.int64)
    out_z, out_r = np.full_like(z, np.nan), np.full_like(r, np.nan)
    for row in radars.filter(pl.col("radar_id").cast(pl.Int64).is_in(mlat_ids(radars).tolist())).iter_rows(named=True):
        mine = rid == row["radar_id"]
        site = geo.LocalFrame(row["lat_deg"], row["lon_deg"], row["alt_m"])
        sel = np.flatnonzero(ok & mine)
        if sel.size:
            out_z[sel] = geo.frame_to_frame(z[sel], site, origin)[0]
        sel = np.flatnonzero(has_r & mine)
        if sel.size:
            out_r[sel] = geo.congruence(site.rotation_to(origin), r[sel])
    return out_z, out_r, ok


# --------------------------------------------------------------------------- the sensor's own tracks


def radial_innovation(nu: F64, s: F64, z: F64) -> tuple[F64, F64]:
    """Innovation along the line of sight from the site, ν_r = ûᵀν, and its variance Σ û_i² S_i
    (decoupled axes), û = z/|z| the plot's direction; per track from (m, 3) axis innovations ν,
    variances S and plots z. Axes without a measurement (NaN, no height) are left out."""
    ok = np.isfinite(nu) & np.isfinite(z) & np.isfinite(s)
    zz = np.where(ok, z, 0.0)
    rho = np.linalg.norm(zz, axis=1)
    u = zz / np.where(rho > 0, rho, np.nan)[:, None]
    return (u * np.where(ok, nu, 0.0)).sum(axis=1), (u * u * np.where(ok, s, 0.0)).sum(axis=1)


def cartesian_estimates(est: F64, cov: F64) -> dict[str, F64]:
    """The estimate columns of tracks filtered on the east, north, up axes (``est`` (2 (pos,
    rate), 3 axes, n), ``cov`` (3 (P00, P01, P11), 3 axes, n)): the local ENU state and its 6×6
    covariance (decoupled axes: blocks [[P00, P01], [P01, P11]] per axis), and the polar view
    of the same estimate from the site with its variances by the Jacobian of (range, azimuth,
    elevation) at the estimate."""
    pos, vel = est[0].T, est[1].T
    n = pos.shape[0]
    c = np.zeros((n, 6, 6))
    for a in range(3):
        c[:, a, a], c[:, a, a + 3], c[:, a + 3, a], c[:, a + 3, a + 3] = cov[0, a], cov[1, a], cov[1, a], cov[2, a]
    rng, az, el = geo.enu_to_polar(pos[:, 0], pos[:, 1], pos[:, 2])
    rho_h2 = np.maximum(pos[:, 0] ** 2 + pos[:, 1] ** 2, 1e-6)
    r2 = np.maximum(rng * rng, 1e-6)
    u = pos / np.sqrt(r2)[:, None]
    g_az = np.column_stack([pos[:, 1], -pos[:, 0], np.zeros(n)]) / rho_h2[:, None]
    g_el = np.column_stack([-pos[:, 2] * pos[:, 0], -pos[:, 2] * pos[:, 1], rho_h2]) / (np.sqrt(rho_h2) * r2)[:, None]
    pp = c[:, :3, :3]
    quad = lambda g: np.einsum("ni,nij,nj->n", g, pp, g)            # noqa: E731
    deg2 = np.degrees(1.0) ** 2
    return {"est_range_m": rng, "est_range_rate_mps": np.einsum("ni,ni->n", u, vel), "est_azimuth_deg": az,
            "est_elevation_deg": el, "est_range_var_m2": quad(u), "est_azimuth_var_deg2": quad(g_az) * deg2,
            "est_elevation_var_deg2": quad(g_el) * deg2, "pos": pos, "vel": vel, "cov": c.reshape(n, 36)}
