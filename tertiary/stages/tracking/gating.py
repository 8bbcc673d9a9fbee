"""Gating and assignment of the secondary tracker: the plots of a window indexed by epoch, σ class,
run and x (:class:`PlotIndex`), the tracking gate's (object, plot, cost) pairs and the
one-to-one assignment (global per ambiguous gate component, or nearest neighbour). The rules
are those of :mod:`tertiary.stages.tracking.tracker` (steps 2 and 3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tertiary.contract import TIME, TURN_RATE_COLUMN
from tertiary.stages.tracking.config import TrackerConfig

__all__ = ["Plots", "PlotIndex", "altitude_cost", "altitude_ok", "downlink_covariance", "likelihood_cost",
           "mode_s_ident", "tracking_pairs", "vertical_ok", "assign"]

_RUN_SEP = 1.0e7                      # metres between runs in the plot sort key (never within a gate)
_DENSE_MAX = 250_000                  # largest dense block solved at once (else per component)


def _window_pairs(keys: NDArray, centers: NDArray, radii: NDArray) -> tuple[NDArray, NDArray]:
    """(centre, plot) index pairs with the plot's sort key within ``radii`` of the centre key.

    The candidates of every centre are one contiguous slice of the sorted ``keys`` (two
    ``searchsorted``), so a whole coarse gate is a handful of vectorised calls.
    """
    if len(keys) == 0 or len(centers) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo = np.searchsorted(keys, centers - radii, side="left")
    hi = np.searchsorted(keys, centers + radii, side="right")
    cnt = hi - lo
    total = int(cnt.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    obj = np.repeat(np.arange(len(centers)), cnt)
    return obj, np.arange(total) - np.repeat(np.cumsum(cnt) - cnt - lo, cnt)


#: plot σ class limits (m): the tracking gate grows with the plot variance, so each σ class of
#: plots gets its own (exact, superset) window — a plot with a σ of kilometres does not widen
#: the search around every track
_SIGMA_CLASSES = np.array([150.0, 1000.0])
_CLASS_SEP = 1.0e13                   # key offset between σ classes (> any run offset)


@dataclass
class Plots:
    """The plots of one epoch (all runs), sorted by the key class·_CLASS_SEP + run·_RUN_SEP + x
    (class = σ class of the plot)."""

    run: NDArray
    z: NDArray
    r: NDArray
    alt: NDArray              # (n, 5) h, ḣ, P_hh, P_hḣ, P_ḣḣ of the plot's vertical channel (NaN: none)
    tid: NDArray
    uid: NDArray
    zm: NDArray               # (n, 3) the measurement: plot-level fusion of the fresh plots
    rm: NDArray               # (n, 3, 3) its full covariance
    age: NDArray              # (n,) measurement time = epoch − age
    fresh: NDArray            # (n,) the fused plot holds a new measurement
    ident: NDArray            # (n,) the plot's Mode S address as an integer (−1: none)
    omega: NDArray            # (n,) the downlinked turn rate, rad/s counter-clockwise (NaN: none)
    vm: NDArray               # (n, 2) the downlinked ground velocity at the measurement's time (NaN: none)
    vr: NDArray               # (n,) the downlinked vertical rate (NaN: none)
    keys: NDArray
    classes: NDArray          # σ classes present
    rmax_x: NDArray           # largest x variance of each present class

    def window(self, run: NDArray, x: NDArray, radius: NDArray) -> tuple[NDArray, NDArray]:
        """(object, plot) pairs with |x_plot − x| ≤ radius in the same run; ``radius`` is (n,)
        or (n_classes_present, n) for a per-class radius."""
        n = len(run)
        if n == 0 or len(self.keys) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        base = run * _RUN_SEP + x
        centers = (self.classes[:, None] * _CLASS_SEP + base[None, :]).ravel()
        radii = (radius if radius.ndim == 2 else np.repeat(radius[None], len(self.classes), axis=0)).ravel()
        o, p = _window_pairs(self.keys, centers, radii)
        return o % n, p


def _plot_alt(f: pl.DataFrame) -> NDArray:
    """(n, 5) vertical channel of the fused plots in AltState order (NaN where absent)."""
    names = ("alt_m", "alt_rate_mps", "alt_var_m2", "alt_cov_m2ps", "alt_rate_var_m2ps2")
    if not all(c in f.columns for c in names):
        return np.full((f.height, 5), np.nan)
    return np.column_stack([f[c].cast(pl.Float64).fill_null(np.nan).to_numpy() for c in names])


class PlotIndex:
    """All plots of one window sorted by (epoch, σ class, run, x) with per-epoch slices, built
    once per window. ``fused["run"]`` is already the batch run index (:class:`TrackState`
    ``keys``); plot uids are ``uid0`` + the row's position in this order, so they continue
    across windows (they equal the whole-run positions when the windows are cut by epoch)."""

    def __init__(self, fused: pl.DataFrame, uid0: int = 0) -> None:
        f = fused.with_columns(pl.col("epoch").cast(TIME))
        cov = f["cov"].to_numpy()
        cov = np.asarray(cov, float).reshape(-1, 36) if cov.dtype != object else np.stack(cov).reshape(-1, 36)
        r = cov[:, [0, 7, 14]].astype(float)
        z = f.select("x_m", "y_m", "z_m").to_numpy().astype(float)
        epoch_us = f["epoch"].dt.epoch("us").to_numpy()
        run = f["run"].cast(pl.Int64).to_numpy()
        cls = np.searchsorted(_SIGMA_CLASSES, np.sqrt(r.max(axis=1)))
        order = np.lexsort((z[:, 0], run, cls, epoch_us))
        self.uid0 = int(uid0)
        self.n = len(order)
        self.run = run.astype(np.int64)[order]
        self.cls = cls[order]
        self.z = np.ascontiguousarray(z[order])
        self.r = np.ascontiguousarray(r[order])
        self.tid = f["target_id"].cast(pl.UInt64).to_numpy()[order]
        self.alt = _plot_alt(f)[order]
        zm, rm, age, fresh = _measurements(f, z, cov)
        self.zm, self.rm = np.ascontiguousarray(zm[order]), np.ascontiguousarray(rm[order])
        self.age, self.fresh = age[order], fresh[order]
        self.ident = mode_s_ident(f)[order]
        self.omega = downlinked_turn_rate(f)[order]
        self.vm = np.ascontiguousarray(downlinked_velocity(f)[order])
        self.vr = downlinked_vertical_rate(f)[order]
        self.keys = self.cls * _CLASS_SEP + self.run * _RUN_SEP + self.z[:, 0]
        self.epochs, starts = np.unique(epoch_us[order], return_index=True)
        self.bounds = np.r_[starts, len(order)]
        # σ-class segments of every epoch and their largest x variance, once for all epochs
        ep = epoch_us[order]
        seg = np.flatnonzero(np.r_[True, (ep[1:] != ep[:-1]) | (self.cls[1:] != self.cls[:-1])])
        self.seg_cls = self.cls[seg].astype(float)
        self.seg_rmax_x = np.maximum.reduceat(self.r[:, 0], seg) if len(seg) else np.zeros(0)
        self.seg_bounds = np.searchsorted(seg, self.bounds)

    def __len__(self) -> int:
        return len(self.epochs)

    def epoch(self, k: int) -> Plots:
        lo, hi = self.bounds[k], self.bounds[k + 1]
        s0, s1 = self.seg_bounds[k], self.seg_bounds[k + 1]
        return Plots(self.run[lo:hi], self.z[lo:hi], self.r[lo:hi], self.alt[lo:hi], self.tid[lo:hi],
                      np.arange(self.uid0 + lo, self.uid0 + hi, dtype=np.int64), self.zm[lo:hi], self.rm[lo:hi], self.age[lo:hi],
                      self.fresh[lo:hi], self.ident[lo:hi], self.omega[lo:hi], self.vm[lo:hi], self.vr[lo:hi],
                      self.keys[lo:hi], self.seg_cls[s0:s1], self.seg_rmax_x[s0:s1])


def _measurements(f: pl.DataFrame, z: NDArray, cov36: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The measurement of every fused row: (z (n, 3), R (n, 3, 3), age (n,), fresh (n,)).

    With the fusion stage's plot-level columns (``meas_x_m``… ``meas_cov``, ``age_s``,
    ``n_fresh``): the fused fresh plots at epoch − ``age_s``; a row without a fresh plot is not
    a measurement (``fresh`` False). Without them (a ``fused`` table from elsewhere): the fused
    position with the full 3×3 position block of ``cov``, at the epoch."""
    n = f.height
    pos = cov36.reshape(n, 6, 6)[:, :3, :3].copy()
    names = ("meas_x_m", "meas_y_m", "meas_z_m", "meas_cov", "age_s")
    if not all(c in f.columns for c in names):
        fresh = (f["n_fresh"].fill_null(1).to_numpy() > 0) if "n_fresh" in f.columns else np.ones(n, bool)
        return z, pos, np.zeros(n), fresh
    zm = f.select(names[:3]).to_numpy().astype(float)
    rm = np.asarray(f["meas_cov"].to_numpy(), float).reshape(n, 3, 3)
    age = f["age_s"].cast(pl.Float64).fill_null(0.0).to_numpy()
    fresh = np.isfinite(zm).all(axis=1) & np.isfinite(rm).all(axis=(1, 2))
    return np.where(fresh[:, None], zm, z), np.where(fresh[:, None, None], rm, pos), np.where(fresh, age, 0.0), fresh


def downlinked_turn_rate(f: pl.DataFrame) -> NDArray:
    """Each row's downlinked turn rate (BDS 5,0 track-angle rate, ``ehs_track_rate_dps``,
    positive clockwise: a right turn) as the filters' ω: rad/s, positive counter-clockwise
    in the east-north plane; NaN where the row has none."""
    if TURN_RATE_COLUMN not in f.columns:
        return np.full(f.height, np.nan)
    return -np.radians(f[TURN_RATE_COLUMN].cast(pl.Float64).fill_null(np.nan).to_numpy())


def downlinked_velocity(f: pl.DataFrame) -> NDArray:
    """(n, 2): each fused row's downlinked ground velocity in the system frame (``meas_vx_mps``,
    ``meas_vy_mps``; NaN where the row has none)."""
    cols = ("meas_vx_mps", "meas_vy_mps")
    if not all(c in f.columns for c in cols):
        return np.full((f.height, 2), np.nan)
    return np.column_stack([f[c].cast(pl.Float64).fill_null(np.nan).to_numpy() for c in cols])


def downlinked_vertical_rate(f: pl.DataFrame) -> NDArray:
    """(n,): each fused row's downlinked vertical rate (``meas_vrate_mps``; NaN without)."""
    if "meas_vrate_mps" not in f.columns:
        return np.full(f.height, np.nan)
    return f["meas_vrate_mps"].cast(pl.Float64).fill_null(np.nan).to_numpy()


def velocity_covariance(v: NDArray, omega: NDArray, cfg: TrackerConfig) -> NDArray:
    """(n, 2, 2) covariance of downlinked ground velocities ``v`` (n, 2) with turn rates ``omega``
    (n,) rad/s (NaN: none, counted as straight): :func:`downlink_covariance` with the
    :class:`TrackerConfig` ``velocity_*`` noise."""
    return downlink_covariance(v, omega, cfg.velocity_speed_sigma_mps, cfg.velocity_track_sigma_deg,
                               cfg.velocity_refresh_s)


def downlink_covariance(v: NDArray, omega: NDArray, speed_sigma_mps: float, track_sigma_deg: float,
                        refresh_s: float) -> NDArray:
    """(n, 2, 2) covariance of downlinked ground velocities ``v`` (n, 2) with turn rates ``omega``
    (n,) rad/s (NaN: none, counted as straight): σ_s² along the track, (s σ_χ)² + (ω s τ)²/3
    across it (s the speed, τ the register's refresh period: its value may be that old, and a
    turn of rate ω has turned the velocity by up to ω s τ since)."""
    s = np.hypot(v[:, 0], v[:, 1])
    u = np.where(s[:, None] > 0, v / np.where(s > 0, s, 1.0)[:, None], np.array([1.0, 0.0]))
    turn = np.nan_to_num(omega) * s * refresh_s
    cross = (s * np.radians(track_sigma_deg)) ** 2 + turn ** 2 / 3.0
    along = speed_sigma_mps ** 2
    n = np.stack([-u[:, 1], u[:, 0]], axis=1)
    return along * u[:, :, None] * u[:, None, :] + cross[:, None, None] * n[:, :, None] * n[:, None, :]


def likelihood_cost(d: NDArray, s: NDArray) -> NDArray:
    """−2 ln of the Gaussian likelihood up to a constant: Σ_i d_i²/S_i + ln S_i."""
    return (d * d / s + np.log(s)).sum(axis=1)


def mode_s_ident(f: pl.DataFrame) -> NDArray:
    """Each row's Mode S address as an integer (−1 where it has none)."""
    if "mode_s" not in f.columns:
        return np.full(f.height, -1, np.int64)
    return (f["mode_s"].cast(pl.String).str.to_integer(base=16, strict=False).fill_null(-1)
            .cast(pl.Int64).to_numpy())


def tracking_pairs(plots: Plots, free: NDArray, run: NDArray, xp: NDArray, vp: NDArray,
                   cfg: TrackerConfig, ident: NDArray | None = None,
                   alt: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
    """Gated (object, plot, cost) triples of the tracking gate around the predictions ``xp``.
    ``ident``: the objects' Mode S addresses (−1: none); a plot carrying another address than
    its track's is never in its gate — a track must not take another aircraft's plot (the
    swap that gives it the other's identity and level), however close it is. ``alt``: the
    objects' predicted barometric altitude and its variance (n, 2), NaN where none; with the
    plot's own (:func:`altitude_ok`, :func:`altitude_cost`) it gates and costs the pairs, so an
    aircraft without an address does not take the plot of one flying above or below it."""
    if len(run) == 0 or not free.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    radius = cfg.gate_sigma * np.sqrt(vp[None, :, 0] + plots.rmax_x[:, None]) + cfg.gate_min_m
    o, p = plots.window(run, xp[:, 0], radius)
    if not free.all():
        keep = free[p]
        o, p = o[keep], p[keep]
    if ident is not None:
        keep = identity_ok(ident[o], plots.ident[p], cfg)
        o, p = o[keep], p[keep]
    # one axis at a time on 1-D gathers, y first: the x window leaves most candidates to fail
    # on y, so the full 3-axis rows are gathered only for the few that pass
    for axis in (1, 0, 2):
        d = plots.z[p, axis] - xp[o, axis]
        ok = np.abs(d) <= cfg.gate_sigma * np.sqrt(vp[o, axis] + plots.r[p, axis]) + cfg.gate_min_m
        o, p = o[ok], p[ok]
    cost = likelihood_cost(plots.z[p] - xp[o], vp[o] + plots.r[p])
    if alt is not None and cfg.alt_gate_m is not None:
        ok = altitude_ok(alt[o], plots.alt[p], cfg)
        o, p = o[ok], p[ok]
        cost = cost[ok] + altitude_cost(alt[o], plots.alt[p])
    return o, p, cost


def identity_ok(obj: NDArray, plot: NDArray, cfg: TrackerConfig) -> NDArray:
    """Whether plots of Mode S address ``plot`` may belong to objects holding ``obj`` (−1: none):
    with ``use_mode_s``, unless both are known and differ. Two aircraft crossing at adjacent
    levels are closer than any position or altitude gate can tell apart; their addresses do."""
    if not cfg.use_mode_s:
        return np.ones(len(obj), bool)
    return (obj < 0) | (plot < 0) | (obj == plot)


def altitude_ok(obj: NDArray, plot: NDArray, cfg: TrackerConfig) -> NDArray:
    """Whether plots of barometric altitude ``plot[:, 0]`` (variance ``plot[:, 2]``, the
    :class:`Plots` ``alt`` layout) may belong to objects predicted at ``obj[:, 0]`` (variance
    ``obj[:, 1]``): within ``gate_sigma`` standard deviations plus ``alt_gate_m``. A pair
    without an altitude on either side passes (Mode A/C-only plots without Mode C, new objects)."""
    d = plot[:, 0] - obj[:, 0]
    lim = cfg.gate_sigma * np.sqrt(np.maximum(obj[:, 1], 0.0) + np.maximum(plot[:, 2], 0.0)) + cfg.alt_gate_m
    return ~np.isfinite(d) | ~np.isfinite(lim) | (np.abs(d) <= lim)


def altitude_cost(obj: NDArray, plot: NDArray) -> NDArray:
    """The barometric altitude's normalised squared distance d²/S, added to a pair's
    :func:`likelihood_cost` (0 where either side has no altitude): the assignment then prefers,
    between two plots in a track's gate, the one at its own level."""
    d = plot[:, 0] - obj[:, 0]
    s = np.maximum(obj[:, 1], 0.0) + np.maximum(plot[:, 2], 0.0) + 1.0     # +1 m²: exact levels
    c = d * d / s
    return np.where(np.isfinite(c), c, 0.0)


def vertical_ok(dz: NDArray, rz_a: NDArray, rz_b: NDArray, cfg: TrackerConfig) -> NDArray:
    """Whether a height change ``dz`` is plausible between plots of height variances ``rz_a``, ``rz_b``."""
    return np.abs(dz) <= cfg.gate_sigma * np.sqrt(rz_a + rz_b) + cfg.gate_min_m


def _compact(v: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """``np.unique(v, return_inverse=True)`` for indices 0 ≤ v < n, without sorting."""
    present = np.zeros(n, bool)
    present[v] = True
    return np.flatnonzero(present), (np.cumsum(present) - 1)[v]


def assign(o: NDArray, p: NDArray, cost: NDArray, n_obj: int, n_plot: int, method: str) -> NDArray:
    """Plot index per object (−1 if none) from gated pairs; one plot per object and vice versa."""
    out = np.full(n_obj, -1, np.int64)
    if len(o) == 0:
        return out
    if method == "nearest":
        return _nearest(o, p, cost, out, n_plot)
    n_o = np.bincount(o, minlength=n_obj)
    n_p = np.bincount(p, minlength=n_plot)
    single = (n_o[o] == 1) & (n_p[p] == 1)        # a pair that is its own gate component
    out[o[single]] = p[single]
    if single.all():
        return out
    amb = np.flatnonzero(~single)
    ro, ri = _compact(o[amb], n_obj)
    co, ci = _compact(p[amb], n_plot)
    if len(ro) * len(co) <= _DENSE_MAX:
        # all ambiguous components in one block-diagonal problem (off-block = not gated)
        blocks = [(amb, ro, ri, co, ci)]
    else:
        graph = coo_matrix((np.ones(len(amb)), (ri, len(ro) + ci)), shape=(len(ro) + len(co),) * 2)
        _, label = connected_components(graph, directed=False)
        comp = label[ri]
        order = np.argsort(comp, kind="stable")
        cuts = np.flatnonzero(np.diff(comp[order]) != 0) + 1
        blocks = []
        for seg in np.split(amb[order], cuts):          # one loop per ambiguous component
            bro, bri = np.unique(o[seg], return_inverse=True)
            bco, bci = np.unique(p[seg], return_inverse=True)
            blocks.append((seg, bro, bri, bco, bci))
    for seg, bro, bri, bco, bci in blocks:
        # shifted costs ≥ 0 and a "not gated" cost above any sum of them: the solution has the
        # most gated assignments possible, then the least cost among those
        c = cost[seg] - cost[seg].min()
        big = (c.max() + 1.0) * (min(len(bro), len(bco)) + 1)
        dense = np.full((len(bro), len(bco)), big)
        dense[bri, bci] = c
        a, b = linear_sum_assignment(dense)
        good = dense[a, b] < big
        out[bro[a[good]]] = bco[b[good]]
    return out


def _nearest(o: NDArray, p: NDArray, cost: NDArray, out: NDArray, n_plot: int) -> NDArray:
    """Vectorised nearest neighbour: each object claims its cheapest plot, the cheapest claimant
    of each plot wins, losers retry among the plots still free."""
    taken = np.zeros(n_plot, bool)
    while len(o):
        order = np.lexsort((cost, o))
        o, p, cost = o[order], p[order], cost[order]
        first = np.r_[True, o[1:] != o[:-1]]               # each object's cheapest plot
        co, cp, cc = o[first], p[first], cost[first]
        order = np.lexsort((cc, cp))
        co, cp = co[order], cp[order]
        win = np.r_[True, cp[1:] != cp[:-1]]               # each plot's cheapest claimant
        out[co[win]] = cp[win]
        taken[cp[win]] = True
        keep = (out[o] < 0) & ~taken[p]
        o, p, cost = o[keep], p[keep], cost[keep]
    return out


# --------------------------------------------------------------------------- the tracker
