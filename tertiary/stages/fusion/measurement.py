"""The measurement of each fused target for the secondary tracker: freshness and plot-level fusion
(the :data:`tertiary.contract.FUSED_EXTRA` columns but ``tentative``).

``n_fresh`` counts the group's fresh rows (a new report at this epoch) and ``age_s`` is the age of
the newest of them. Given the reports' measured plots (``fuse(..., plots=measured_plots(...))``,
joined to the fresh rows only), each method also gives the plot-level fusion of the fresh plots
(:func:`plot_measurement`: the method's weights, or inverse covariance for the methods that
declare ``info_plots``) with its full 3×3 covariance — the independent measurement the secondary
tracker filters.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import polars as pl
from numpy.typing import NDArray

from tertiary.core import geo
from tertiary.stages.fusion.base import B, F, Ix, Layout, per_row, segsum, sym
from tertiary.stages.fusion.plots import converted_plots, downlinked_velocity, float_column
from tertiary.stages.fusion.registry import REGISTRY

__all__ = ["EHS_PLOT_COLUMNS", "PLOT_COLUMNS", "downlinked_velocity", "ehs_measurement", "measured_plots",
           "measurements", "plot_measurement"]

PLOT_COLUMNS = ["plot_x_m", "plot_y_m", "plot_z_m", "plot_cov"]
#: a measured plot's downlinked ground velocity in the system frame (east, north; m/s), its
#: downlinked turn rate (rad/s, counter-clockwise) and vertical rate (m/s), NaN without them
EHS_PLOT_COLUMNS = ["plot_vx_mps", "plot_vy_mps", "plot_rate_rps", "plot_vrate_mps"]



def measured_plots(reports: pl.DataFrame, radars: pl.DataFrame, origin: geo.LocalFrame,
                   altitude_sigma_m: float = 30.0) -> pl.DataFrame:
    """Each report's *measured* plot in the system frame, one row per report: run, report_id
    and :data:`PLOT_COLUMNS` (position and row-major 3×3 covariance R = M J R_polar Jᵀ Mᵀ from
    the radar's nominal sigmas, seed 002 eq. 12; an MLAT report's Cartesian plot and its own
    covariance, (MLAT-2); :func:`tertiary.stages.fusion.plots.converted_plots`),
    NaN where the plot cannot be converted. Unlike the radars' track estimates, these errors
    are white: independent from scan to scan and between radars. Pass it to :func:`fuse`
    (``plots=``): it is joined to the fresh rows only, so the aligned rows are not widened."""
    rep = reports if "run" in reports.columns else reports.with_columns(pl.lit(0, pl.UInt32).alias("run"))
    z, r, ok = converted_plots(rep, radars, origin, altitude_sigma_m)
    z = np.where(ok[:, None], z, np.nan)
    v = downlinked_velocity(rep, z, origin)
    return rep.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64)).with_columns(
        *(pl.Series(c, z[:, i]) for i, c in enumerate(PLOT_COLUMNS[:3])),
        pl.Series("plot_cov", np.where(ok[:, None], r.reshape(-1, 9), np.nan), dtype=pl.Array(pl.Float64, 9)),
        *(pl.Series(c, v[:, i]) for i, c in enumerate(EHS_PLOT_COLUMNS)))


def _solve3(r: F) -> F:
    """Inverse of 3×3 covariances (rows that are not invertible get NaN)."""
    out = np.full_like(r, np.nan)
    ok = np.isfinite(r).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.where(np.isfinite(r), r, 0.0))) > 0)
    if ok.any():
        out[ok] = np.linalg.inv(sym(r[ok]))
    return out


def plot_measurement(zp: F, rp: F, use: B, age: F, vel: F, pvv: F, w: F | None, starts: Ix
                     ) -> tuple[F, F, F]:
    """Plot-level fusion of each group's fresh measured plots (rows ``use``), at the time of
    its newest one: returns z (G, 3), R (G, 3, 3) and that age (G,) (NaN: no fresh plot).

    A plot of age a_n is moved to the reference age a₀ = min a_n of its group with its radar's
    velocity estimate over d = a_n − a₀ (< one epoch period), z'_n = z_n + v_n d, and its
    covariance grown by d² P_vv,n (that small velocity term is the only correlated part; it is
    included in R, not removed). Then, with the method's weights ``w`` (n,) or per axis (n, 3)
    renormalised over the fresh plots, z = Σ W_n z'_n and R = Σ W_n R'_n W_n (the plots'
    errors are independent); with ``w`` None the inverse-covariance combination
    R = (Σ R'_n⁻¹)⁻¹, z = R Σ R'_n⁻¹ z'_n."""
    n = len(zp)
    use = use & np.isfinite(zp).all(axis=1) & np.isfinite(rp).all(axis=(1, 2)) & np.isfinite(age)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
    a0 = np.minimum.reduceat(np.where(use, age, np.inf), starts)
    d = np.where(use, age - per_row(a0, starts, n), 0.0)
    zs = np.where(use[:, None], zp + np.nan_to_num(vel) * d[:, None], 0.0)
    rs = np.where(use[:, None, None], rp + d[:, None, None] ** 2 * np.nan_to_num(pvv), 0.0)
    if w is None:
        info = np.where(use[:, None, None], np.nan_to_num(_solve3(np.where(use[:, None, None], rs, np.eye(3)))), 0.0)
        r = _solve3(segsum(info, starts))
        z = np.einsum("gij,gj->gi", r, segsum(np.einsum("nij,nj->ni", info, zs), starts))
    else:
        w3 = np.where(use[:, None], np.broadcast_to(w.reshape(n, -1), (n, 3)), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            w3 = w3 / per_row(segsum(w3, starts), starts, n)
        w3 = np.where(use[:, None], np.nan_to_num(w3), 0.0)
        z = segsum(w3 * zs, starts)
        r = segsum(w3[:, :, None] * rs * w3[:, None, :], starts)
    none = ~np.isfinite(a0)
    z[none], r[none] = np.nan, np.nan
    return z, r, np.where(none, np.nan, a0)


def _fresh_plots(rows: pl.DataFrame, idx: Ix, plots: pl.DataFrame | None) -> tuple[F, F, F] | None:
    """Plot position (k, 3), covariance (k, 3, 3) and downlinked velocity and rate (k, 3,
    :data:`EHS_PLOT_COLUMNS`, NaN without) of the rows ``idx``: from ``plots`` (joined on run,
    report_id) or from the rows' own :data:`PLOT_COLUMNS`; None without either."""
    if plots is not None:
        sub = rows.select(pl.col("run").cast(pl.UInt32), pl.col("report_id").cast(pl.UInt64))[idx].join(
            plots, on=["run", "report_id"], how="left", maintain_order="left")
    elif all(c in rows.columns for c in PLOT_COLUMNS):
        sub = rows.select(c for c in (*PLOT_COLUMNS, *EHS_PLOT_COLUMNS) if c in rows.columns)[idx]
    else:
        return None
    zp = sub.select(PLOT_COLUMNS[:3]).cast(pl.Float64).fill_null(np.nan).to_numpy()
    ehs = np.column_stack([float_column(sub, c) for c in EHS_PLOT_COLUMNS])
    return zp, np.asarray(sub["plot_cov"].to_numpy(), float).reshape(len(idx), 3, 3), ehs


def _newest(has: B, age: F, grp: Ix) -> tuple[Ix, Ix]:
    """The row of each group's newest plot among ``has`` (smallest age) and its group."""
    cand = np.flatnonzero(has & np.isfinite(age))
    cand = cand[np.lexsort((age[cand], grp[cand]))]
    first = cand[np.r_[True, grp[cand][1:] != grp[cand][:-1]]] if len(cand) else cand
    return first, grp[first]


def ehs_measurement(ehs: F, age: F, a0: F, starts: Ix) -> F:
    """The downlinked ground velocity and vertical rate of each group (G, 3) at its measurement's
    age ``a0`` (G,). The velocity is that of the group's newest plot carrying one (rows ``ehs``
    (n, 4) of :data:`EHS_PLOT_COLUMNS`, ages ``age`` (n,)), turned by its own downlinked rate
    over d = its age − a0 ≥ 0 (the aircraft turns at that rate meanwhile; without a rate it is
    not turned); the vertical rate that of the newest plot carrying one (a separate register).
    One plot, not an average: every radar reads the same register, so the values of two radars
    share the aircraft's navigation error. NaN where no plot of the group has one."""
    n, g = len(ehs), len(starts)
    out = np.full((g, 3), np.nan)
    if n == 0:
        return out
    grp = np.repeat(np.arange(g), np.diff(np.r_[starts, n]))
    first, gi = _newest(np.isfinite(ehs[:, 3]), age, grp)
    out[gi, 2] = ehs[first, 3]
    first, gi = _newest(np.isfinite(ehs[:, :2]).all(axis=1), age, grp)
    d = np.maximum(age[first] - a0[gi], 0.0)
    turn = np.nan_to_num(ehs[first, 2]) * np.where(np.isfinite(a0[gi]), d, 0.0)
    c, s = np.cos(turn), np.sin(turn)
    vx, vy = ehs[first, 0], ehs[first, 1]
    out[gi, 0], out[gi, 1] = c * vx - s * vy, s * vx + c * vy
    return out


def _plot_weights(method: str, a: Mapping[str, NDArray], lay: Layout, idx: Ix, rp: F, sub_starts: Ix, w: F,
                  axis_w: dict[str, F] | None) -> F | None:
    """The weights of the fresh plots ``idx`` for ``method``: None (inverse covariance) for the
    methods that declare ``info_plots``, else its ``plot_weights``, its per-axis weights, or its
    own per-row weights ``w``."""
    spec = REGISTRY[method]
    if spec.info_plots:
        return None
    if spec.plot_weights is not None:
        return spec.plot_weights(a, lay, idx, rp, sub_starts)
    if axis_w and method in axis_w:
        return axis_w[method][idx]
    return w[idx]


def measurements(rows: pl.DataFrame, methods: list[str], a: dict[str, NDArray], lay: Layout, ws: F,
                  plots: pl.DataFrame | None = None, axis_w: dict[str, F] | None = None) -> dict[str, F]:
    """:data:`~tertiary.contract.FUSED_EXTRA` measurement columns (minus ``tentative``) of every
    (method, group), shape (M, G[, …]), stacked in method order. Only the fresh rows are
    read (their groups are a sorted subset of all groups)."""
    n, g, m = rows.height, len(lay.starts), len(methods)
    fresh = a["fresh"]
    n_fresh = np.add.reduceat(fresh.astype(np.int64), lay.starts) if n else np.zeros(0, np.int64)
    age = (rows["age_s"].cast(pl.Float64).fill_null(np.nan).to_numpy() if "age_s" in rows.columns
           else np.full(n, np.nan))
    with np.errstate(invalid="ignore"):
        newest = np.fmin.reduceat(age, lay.starts) if n else np.zeros(0)
    out = {"n_fresh": np.repeat(n_fresh[None], m, axis=0), "age_s": np.repeat(newest[None], m, axis=0),
           "meas": np.full((m, g, 3), np.nan), "meas_cov": np.full((m, g, 9), np.nan),
           "meas_v": np.full((m, g, 3), np.nan)}
    idx = np.flatnonzero(fresh)
    got = _fresh_plots(rows, idx, plots) if len(idx) and "age_s" in rows.columns else None
    if got is None:
        return out
    zp, rp, ehs = got
    gid = lay.group[idx]
    sub_starts = np.flatnonzero(np.r_[True, gid[1:] != gid[:-1]])
    gsub = gid[sub_starts]
    vel, pvv = a["x"][idx, 3:], a["cov"][idx, 3:, 3:]
    for i, meth in enumerate(methods):
        w = _plot_weights(meth, a, lay, idx, rp, sub_starts, ws[i], axis_w)
        z, r, a0 = plot_measurement(zp, rp, np.ones(len(idx), bool), age[idx], vel, pvv, w, sub_starts)
        out["meas"][i, gsub], out["meas_cov"][i, gsub] = z, r.reshape(-1, 9)
        out["age_s"][i, gsub] = np.where(np.isfinite(a0), a0, newest[gsub])
        out["meas_v"][i, gsub] = ehs_measurement(ehs, age[idx], a0, sub_starts)
    return out
