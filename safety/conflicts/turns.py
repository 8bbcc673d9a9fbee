"""Turning aircraft: the horizontal prediction along a bounded constant-turn-rate arc from the
downlinked track-angle rate, decided on a time grid (docs/methods.md, "Conflict prediction
(STCA)": "Turning aircraft")."""

from __future__ import annotations

import math

import numpy as np
import polars as pl
from numpy.typing import ArrayLike, NDArray

from safety.conflicts.config import ConflictConfig
from safety.conflicts.geometry import clamped_dz
from safety.conflicts.thresholds import PointTerms, applied_thresholds
from tertiary.contract import TURN_RATE_COLUMN

__all__ = ["turn_rates", "arc_offsets", "conflict_interval_arc", "ArcTable", "ARC_SCREEN_STEP_S", "arc_lower_bound",
           "arc_rows"]

def turn_rates(tracks: pl.DataFrame, cfg: "ConflictConfig") -> NDArray[np.float64] | None:
    """Per row, the turn rate ω (rad/s, clockwise positive like the track angle) its horizontal
    prediction follows: the downlinked track-angle rate (:data:`TURN_RATE_COLUMN`) where it is
    at least ``cfg.turn_rate_min_dps`` in magnitude, else 0 (straight line). None when no row
    turns (or not corrected mode / ``use_turn_rate`` off / no such column)."""
    if cfg.mode != "corrected" or not cfg.use_turn_rate or TURN_RATE_COLUMN not in tracks.columns:
        return None
    rate = tracks[TURN_RATE_COLUMN].cast(pl.Float64).fill_null(np.nan).to_numpy()
    turning = np.isfinite(rate) & (np.abs(rate) >= cfg.turn_rate_min_dps)
    if not turning.any():
        return None
    return np.where(turning, np.radians(np.where(turning, rate, 0.0)), 0.0)


def arc_offsets(vx: ArrayLike, vy: ArrayLike, omega: ArrayLike, t: ArrayLike, max_turn_rad: float
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Horizontal displacement (east, north) after time t of an aircraft with velocity (vx, vy)
    turning at ω (rad/s, clockwise positive: the track angle χ = atan2(vx, vy) grows) — a
    constant-rate arc for t ≤ t_b = max_turn/|ω|, then straight on the track reached:

        θ = ω·min(t, t_b),  S = sin θ / ω,  C = (1 − cos θ) / ω          (ω = 0: S = t, C = 0)
        Δx = vx·S + vy·C + vx'·(t − t_b)₊,   Δy = −vx·C + vy·S + vy'·(t − t_b)₊,
        (vx', vy') = (vx cos θ + vy sin θ, −vx sin θ + vy cos θ)   (the velocity turned by θ)

    Arguments broadcast together (e.g. (n, 1) states against (K,) times)."""
    vx, vy, w, t = (np.asarray(a, np.float64) for a in (vx, vy, omega, t))
    aw = np.abs(w)
    with np.errstate(divide="ignore", invalid="ignore"):
        te = np.minimum(t, np.where(aw > 0, max_turn_rad / np.where(aw > 0, aw, 1.0), np.inf))
        th = w * te
        sn, cs = np.sin(th), np.cos(th)
        big_s = np.where(aw > 0, sn / np.where(aw > 0, w, 1.0), te)
        big_c = np.where(aw > 0, (1.0 - cs) / np.where(aw > 0, w, 1.0), 0.0)
    rest = t - te
    dx = vx * big_s + vy * big_c + (vx * cs + vy * sn) * rest
    dy = -vx * big_c + vy * big_s + (-vx * sn + vy * cs) * rest
    return dx, dy


def conflict_interval_arc(p_i: ArrayLike, v_i: ArrayLike, w_i: ArrayLike, p_j: ArrayLike, v_j: ArrayLike,
                          w_j: ArrayLike, dz: ArrayLike, vz_i: ArrayLike, vz_j: ArrayLike,
                          r_thr: NDArray | float, z_thr: NDArray | float | tuple, t_thr: float,
                          dt: float = 0.5, max_turn_rad: float = math.pi / 6,
                          tau_i: ArrayLike | None = None, tau_j: ArrayLike | None = None,
                          max_elements: int = 1 << 21) -> tuple[NDArray[np.float64], ...]:
    """The same-time rule for pairs with turning members, on a time grid (docs/methods.md
    "Turning aircraft"): each aircraft's horizontal position along its bounded arc
    (:func:`arc_offsets`; ω = 0 is a straight line), heights as :func:`conflict_interval_levelled`
    (stopped at the level-off times τ; None: linear). ``p_*``, ``v_*``: (n, 2) horizontal
    positions / velocities; ``z_thr`` one threshold or one per vertical piece (a 3-tuple, pieces
    split at min τ and max τ). Grid t_k = k·T/K, K = ceil(T/dt); vectorised over pairs × times
    (chunks of ``max_elements``). Returns (t_in, t_out, d_min, t_star): the first grid time
    inside both thresholds and the end of that run of grid times (t_in > t_out: none), the
    minimum horizontal distance over the grid and its time. Between grid times the horizontal
    distance moves by at most (|v_i| + |v_j|)·Δt/2 from the nearest sample and |Δh| by
    |ḣ_i − ḣ_j|·Δt/2: a conflict that enters the thresholds by less than that, or for less than
    Δt, can be missed, and t_in is late by < Δt; a grid alert is always a true one."""
    p_i, v_i, p_j, v_j = (np.asarray(a, np.float64).reshape(-1, 2) for a in (p_i, v_i, p_j, v_j))
    n = len(p_i)
    w_i, w_j, dz, vz_i, vz_j = (np.broadcast_to(np.asarray(a, np.float64), (n,))
                                for a in (w_i, w_j, dz, vz_i, vz_j))
    inf = np.full(n, np.inf)
    tau_i = inf if tau_i is None else np.broadcast_to(np.asarray(tau_i, np.float64), (n,))
    tau_j = inf if tau_j is None else np.broadcast_to(np.asarray(tau_j, np.float64), (n,))
    r_thr = np.broadcast_to(np.asarray(r_thr, np.float64), (n,))
    z = z_thr if isinstance(z_thr, tuple) else (z_thr,) * 3
    z = tuple(np.broadcast_to(np.asarray(zk, np.float64), (n,)) for zk in z)
    k = max(1, int(math.ceil(t_thr / dt - 1e-9)))
    tk = np.linspace(0.0, t_thr, k + 1)
    out = tuple(np.empty(n) for _ in range(4))
    both = np.concatenate([v_i, v_j])
    ox, oy = arc_offsets(both[:, 0, None], both[:, 1, None], np.concatenate([w_i, w_j])[:, None], tk, max_turn_rad)
    idx = np.arange(n)
    for c, d2, hz in _arc_grid_chunks(p_j[:, 0] - p_i[:, 0], p_j[:, 1] - p_i[:, 1], idx, idx + n, ox, oy,
                                      (dz, vz_i, vz_j, tau_i, tau_j), tk, max_elements):
        zk = _piece_grid(tuple(zz[c] for zz in z), tau_i[c], tau_j[c], tk)
        out[0][c], out[1][c] = _first_run((d2 <= r_thr[c, None] ** 2) & (hz <= zk), tk)
        kmin = np.argmin(d2, axis=1)
        out[2][c] = np.sqrt(d2[np.arange(len(kmin)), kmin])
        out[3][c] = tk[kmin]
    return out


def _arc_grid_chunks(dx0: NDArray, dy0: NDArray, a: NDArray[np.int64], b: NDArray[np.int64], ox: NDArray,
                     oy: NDArray, vert, tk: NDArray[np.float64], max_elements: int = 1 << 21):
    """Per chunk of pairs (slice c): the squared horizontal distance (m, K+1) at the grid times
    ``tk`` of pairs whose current separation is (dx0, dy0) = p_j − p_i and whose members'
    displacements are rows ``a`` (i) and ``b`` (j) of ``ox``, ``oy`` (per track, computed once:
    :func:`arc_offsets` at ``tk``); with ``vert`` = (dz, ḣ_i, ḣ_j, τ_i, τ_j) also |Δh| (else None)."""
    n = len(dx0)
    step = max(1, max_elements // len(tk))
    for s in range(0, n, step):
        c = slice(s, min(n, s + step))
        ex = ox[b[c]]
        ex -= ox[a[c]]
        ex += dx0[c, None]
        ey = oy[b[c]]
        ey -= oy[a[c]]
        ey += dy0[c, None]
        ex *= ex
        ey *= ey
        ex += ey
        hz = None
        if vert is not None:
            dz, vz_i, vz_j, tau_i, tau_j = (v[c, None] for v in vert)
            hz = np.abs(clamped_dz(dz, vz_i, vz_j, tau_i, tau_j, tk))
        yield c, ex, hz


class ArcTable:
    """The displacements of the turning rows (ω ≠ 0) at the coarse screening grid and the fine
    decision grid, computed once per call of :func:`pair_rows` (the trigonometry is per track,
    not per pair); other rows move on straight lines (v·t, no table)."""

    def __init__(self, cfg: ConflictConfig, st: NDArray[np.float64], omega: NDArray[np.float64]) -> None:
        t_thr, th = cfg.t_thr_s, math.radians(cfg.max_turn_deg)
        self.turn = np.flatnonzero(omega != 0.0)
        self.slot = np.full(len(omega), -1, np.int64)
        self.slot[self.turn] = np.arange(len(self.turn))
        vx, vy = st[3][self.turn, None], st[4][self.turn, None]
        w = omega[self.turn, None]
        self.grids = {}
        for name, step in (("coarse", ARC_SCREEN_STEP_S), ("fine", cfg.turn_grid_s)):
            tk = np.linspace(0.0, t_thr, max(1, int(math.ceil(t_thr / step - 1e-9))) + 1)
            self.grids[name] = (tk, *arc_offsets(vx, vy, w, tk, th))

    def offsets(self, st: NDArray[np.float64], i: NDArray[np.int64], j: NDArray[np.int64], grid: str):
        """(tk, dx0, dy0, a, b, ox, oy) of pairs (i, j) for :func:`_arc_grid_chunks`: one row
        of displacements per distinct track of the pairs."""
        tk, tx, ty = self.grids[grid]
        x, y, _, vx, vy, _ = st
        rows, inv = np.unique(np.concatenate([i, j]), return_inverse=True)
        inv = inv.ravel()
        ox, oy = vx[rows, None] * tk, vy[rows, None] * tk
        k = self.slot[rows]
        t = k >= 0
        ox[t], oy[t] = tx[k[t]], ty[k[t]]
        return tk, x[j] - x[i], y[j] - y[i], inv[:len(i)], inv[len(i):], ox, oy


def _piece_grid(z: tuple, tau_i: NDArray, tau_j: NDArray, tk: NDArray) -> NDArray[np.float64]:
    """The vertical threshold of each piece (before min τ, between, after max τ) on the grid."""
    k1, k2 = np.minimum(tau_i, tau_j)[:, None], np.maximum(tau_i, tau_j)[:, None]
    return np.where(tk < k1, z[0][:, None], np.where(tk < k2, z[1][:, None], z[2][:, None]))


def _first_run(inside: NDArray[np.bool_], tk: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(first grid time inside, last grid time of that run) per row; (inf, −inf) if never."""
    k = inside.shape[1] - 1
    first = np.argmax(inside, axis=1)
    got = inside[np.arange(len(first)), first]
    gap = ~inside & (np.arange(k + 1)[None, :] > first[:, None])
    last = np.where(gap.any(axis=1), np.argmax(gap, axis=1) - 1, k)
    return np.where(got, tk[first], np.inf), np.where(got, tk[last], -np.inf)


#: coarse grid step (s) of the turning pairs' screening bound (:func:`arc_lower_bound`)
ARC_SCREEN_STEP_S = 5.0


def arc_lower_bound(cfg: ConflictConfig, st: NDArray[np.float64], arcs: ArcTable,
                    i: NDArray[np.int64], j: NDArray[np.int64], d_line: NDArray[np.float64],
                    limit: NDArray[np.float64]) -> NDArray[np.float64]:
    """A lower bound of the arcs' horizontal distance over [0, T] (screening only). First the
    straight lines' minimum ``d_line`` minus how far bounded arcs can leave their tangents
    (|v(s) − v0| ≤ 2|v|·sin(θ_max/2), so by ≤ 2|v|·sin(θ_max/2)·T); the pairs that bound does not
    settle (bound ≤ ``limit``, the largest reach that could keep the pair), on a coarse grid of
    step Δc = :data:`ARC_SCREEN_STEP_S`: min_k d(t_k) − (|v_i| + |v_j|)·Δc/2 (the distance moves
    by at most that between samples)."""
    t_thr, th = cfg.t_thr_s, math.radians(cfg.max_turn_deg)
    x, y, _, vx, vy, _ = st
    sp_i, sp_j = np.hypot(vx[i], vy[i]), np.hypot(vx[j], vy[j])
    lb = np.maximum(d_line - 2.0 * math.sin(min(th, math.pi) / 2.0) * t_thr * (sp_i + sp_j), 0.0)
    near = np.flatnonzero(lb <= limit)
    if near.size:
        tk, *grid = arcs.offsets(st, i[near], j[near], "coarse")
        d_min = np.empty(len(near))
        for c, d2, _ in _arc_grid_chunks(*grid, None, tk):
            d_min[c] = np.sqrt(d2.min(axis=1))
        lb[near] = np.maximum(lb[near], d_min - (sp_i[near] + sp_j[near]) * tk[1] / 2.0)
    return np.maximum(lb, 0.0)


def arc_rows(cfg: ConflictConfig, st: NDArray[np.float64], arcs: ArcTable,
             tau: NDArray[np.float64] | None, terms: PointTerms | None, i: NDArray[np.int64],
             j: NDArray[np.int64], dz: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """Pairs with a turning member on the fine grid (one pass per chunk): the arc's closest
    approach over [0, T] (``r_min``, ``t_min`` = ``t_eval``), the thresholds there, the
    decision and the near test (vertical threshold per piece as :func:`_levelled_decision`),
    Δh at t*, and ``z_screen`` (the largest vertical threshold, for the output set)."""
    t_thr, mh, mv = cfg.t_thr_s, cfg.near_margin_h_m, cfg.near_margin_v_m
    tk, *grid = arcs.offsets(st, i, j, "fine")
    vzi, vzj = st[5][i], st[5][j]
    n = len(i)
    ti = np.full(n, np.inf) if tau is None else tau[i]
    tj = np.full(n, np.inf) if tau is None else tau[j]
    names = ("r_min", "t_min", "t_eval", "r_thr", "z_thr", "z_screen", "t_in", "t_out", "n_in", "n_out", "dz_eval")
    out = {name: np.empty(n) for name in names}
    vert = (dz, vzi, vzj, ti, tj)
    for c, d2, hz in _arc_grid_chunks(*grid, vert, tk):
        rows = np.arange(c.start, c.stop)
        kmin = np.argmin(d2, axis=1)
        t_star = tk[kmin]
        r_thr, z_now, z_full, z_level = applied_thresholds(cfg, terms, i[c], j[c], t_star, st[5])
        moving = np.where(ti[c] < tj[c], np.abs(vzj[c]), np.abs(vzi[c]))
        z2 = np.where(moving <= cfg.level_rate_mps, z_level, z_full)
        levelled = np.minimum(ti[c], tj[c]) < t_thr
        zs = (z_now, np.where(levelled, z2, z_now), np.where(levelled, z_level, z_now))
        zk = _piece_grid(zs, ti[c], tj[c], tk)
        t_in, t_out = _first_run((d2 <= r_thr[:, None] ** 2) & (hz <= zk), tk)
        n_in, n_out = _first_run((d2 <= (r_thr[:, None] + mh) ** 2) & (hz <= zk + mv), tk)
        vals = (np.sqrt(d2[np.arange(len(kmin)), kmin]), t_star, t_star, r_thr, z_now,
                np.where(levelled, z_full, z_now), t_in, t_out, n_in, n_out,
                clamped_dz(dz[c], vzi[c], vzj[c], ti[c], tj[c], t_star))
        for name, v in zip(names, vals):
            out[name][rows] = v
    return out
