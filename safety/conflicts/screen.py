"""Candidate pairs: a conservative KD-tree screen of the (run, epoch, method) groups, no O(N²)
loop (docs/methods.md, "Conflict prediction (STCA)": "Candidate search")."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from safety.conflicts.config import ConflictConfig
from safety.conflicts.geometry import state_arrays
from safety.conflicts.thresholds import Bounds, point_terms, threshold_bounds
from tertiary.core import geo

__all__ = ["group_index", "Screen", "screen_of", "union_screen", "block_candidates", "conflict_candidates",
           "screen_states"]

def group_index(tracks: pl.DataFrame, keys: list[str]) -> NDArray[np.int64]:
    """Dense index of the (run, epoch[, method]) group per row (in sorted key order)."""
    if not tracks.height:
        return np.zeros(0, np.int64)
    expr = pl.struct(keys) if len(keys) > 1 else pl.col(keys[0])
    return (tracks.select(expr.rank("dense").cast(pl.Int64) - 1).to_series().to_numpy())


def _flatten(lists) -> NDArray[np.int64]:
    parts = [np.asarray(x, dtype=np.int64) for x in lists]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


class Screen(NamedTuple):
    """What the KD-tree screen of a set of settings reads: the window W = [t0, t1], the
    horizontal / vertical threshold bases (plus the near margins) and, per track, the squared
    covariance reaches lam2 = k_h²·λ and q2 = k_v²·q of :class:`Bounds` — a pair (i, j) can be
    kept by a setting only if it comes within base_h + sqrt(lam2_i + lam2_j) horizontally and
    base_v + sqrt(q2_i + q2_j) vertically at some t ∈ W."""

    t0: float
    t1: float
    base_h: float
    base_v: float
    lam2: NDArray[np.float64]
    q2: NDArray[np.float64]
    bulk_quantile: float
    v_max_mps: float | None

    def take(self, idx: NDArray[np.int64]) -> "Screen":
        return self._replace(lam2=self.lam2[idx], q2=self.q2[idx])


def screen_of(cfg: ConflictConfig, b: Bounds) -> Screen:
    """The screen of one setting with bounds ``b``."""
    t0, t1 = cfg.window_s
    return Screen(t0, t1, b.base_h, b.base_v, cfg.k_h ** 2 * b.lam, cfg.k_v ** 2 * b.q, cfg.bulk_quantile,
                   cfg.v_max_mps)


def union_screen(screens: Sequence[Screen]) -> Screen:
    """A screen that keeps every pair any of ``screens`` keeps: the widest window, the largest
    bases and per-track reaches (sqrt(max_c a_c + max_c b_c) ≥ sqrt(a_c + b_c) for every c)."""
    first = screens[0]
    return first._replace(t0=min(s.t0 for s in screens), t1=max(s.t1 for s in screens),
                          base_h=max(s.base_h for s in screens), base_v=max(s.base_v for s in screens),
                          lam2=np.maximum.reduce([s.lam2 for s in screens]),
                          q2=np.maximum.reduce([s.q2 for s in screens]))


def _candidates(sc: Screen, g: NDArray[np.int64], pos: NDArray[np.float64], vel: NDArray[np.float64]
                ) -> Iterator[tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """Screened pairs (i ≠ j, each unordered pair once, same group) in up to three parts — see
    "Candidate search" in docs/methods.md. Parts are yielded one at a time (memory)."""
    n = len(g)
    if n < 2:
        return
    t0, t1 = sc.t0, sc.t1
    tw, tc = 0.5 * (t1 - t0), 0.5 * (t0 + t1)                # half-length and centre of W
    lam, qv = sc.lam2, sc.q2
    vh = np.hypot(vel[:, 0], vel[:, 1])
    vz = np.abs(vel[:, 2])

    def reach(m1: NDArray[np.bool_], m2: NDArray[np.bool_]) -> tuple[float, float]:
        """Upper bounds of the horizontal / vertical reach of any pair (i ∈ m1, j ∈ m2)."""
        rh = (vh[m1].max() + vh[m2].max()) * tw + sc.base_h + math.sqrt(lam[m1].max() + lam[m2].max())
        rv = (vz[m1].max() + vz[m2].max()) * tw + sc.base_v + math.sqrt(qv[m1].max() + qv[m2].max())
        return float(rh), float(rv)

    qq = sc.bulk_quantile
    v_b = sc.v_max_mps if sc.v_max_mps is not None else float(np.quantile(vh, qq))
    vz_b, lam_b, q_b = (float(np.quantile(x, qq)) for x in (vz, lam, qv))
    bulk = (vh <= v_b) & (vz <= vz_b) & (lam <= lam_b) & (qv <= q_b)
    if bulk.sum() < 2:
        bulk[:] = True
    # the bulk in two tiers: the level half (small vertical reach) and the rest
    level = bulk & (vz <= float(np.median(vz[bulk])))
    climb = bulk & ~level
    wide = ~bulk
    allm = np.ones(n, bool)
    r_ll = reach(level, level) if level.sum() >= 2 else (0.0, 1.0)
    r_cc = reach(climb, climb) if climb.sum() >= 2 else (0.0, 1.0)
    r_cl = reach(climb, level) if climb.any() and level.any() else (0.0, 1.0)
    w_idx = np.flatnonzero(wide)
    w_h = (vh[w_idx] + vh.max()) * tw + sc.base_h + np.sqrt(lam[w_idx] + lam.max())
    w_v = (vz[w_idx] + vz.max()) * tw + sc.base_v + np.sqrt(qv[w_idx] + qv.max())
    r_all = reach(allm, allm)
    scale = float(np.max(np.abs(pos))) + float(vh.max() + vz.max()) * max(abs(t0), abs(t1)) + 1.0
    pad = 1.0 + 1e-9 * scale                                   # rounding safety (metres)
    # Chebyshev radius and z scale of each query; the wide radii are ≤ r_all (same scale)
    s_ll, s_cc, s_cl, s_all = (r[0] / r[1] for r in (r_ll, r_cc, r_cl, r_all))
    q_ll, q_cc, q_cl = (r[0] + pad * max(1.0, s) for r, s in ((r_ll, s_ll), (r_cc, s_cc), (r_cl, s_cl)))
    q_w = np.maximum(w_h, w_v * s_all) + pad * max(1.0, s_all)
    sep = 2.0 * max(q_ll, q_cc, q_cl, r_all[0] + pad * max(1.0, s_all)) + 1.0
    # every track at the window centre; the 4th coordinate separates the groups by more than
    # any query radius, so one tree serves all (run, epoch, method) groups of the block
    c = pos + vel * tc
    gc = g.astype(np.float64) * sep

    def points(idx: NDArray[np.int64], s: float) -> NDArray[np.float64]:
        return np.column_stack([c[idx, 0], c[idx, 1], c[idx, 2] * s, gc[idx]])

    def pairs_within(idx: NDArray[np.int64], s: float, r: float):
        pr = cKDTree(points(idx, s)).query_pairs(r, p=np.inf, output_type="ndarray")
        a = idx[pr[:, 0]]
        return a, idx[pr[:, 1]]

    li, ci = np.flatnonzero(level), np.flatnonzero(climb)
    if len(li) >= 2:                                           # level × level
        yield pairs_within(li, s_ll, q_ll)
    if len(ci) >= 2:                                           # climbing/descending × climbing/descending
        yield pairs_within(ci, s_cc, q_cc)
    if len(ci) and len(li):                                    # climbing/descending × level
        sm = cKDTree(points(ci, s_cl)).sparse_distance_matrix(cKDTree(points(li, s_cl)), q_cl, p=np.inf,
                                                             output_type="ndarray")
        yield ci[sm["i"]], li[sm["j"]]
        del sm
    if len(w_idx):                                             # the few wide tracks × all, own radii
        pts = points(np.arange(n), s_all)
        hits = cKDTree(pts).query_ball_point(pts[w_idx], q_w, p=np.inf, return_sorted=False)
        counts = np.fromiter((len(x) for x in hits), np.int64, len(w_idx))
        jj = _flatten(hits)
        ii = np.repeat(w_idx, counts)
        keep = (ii != jj) & (bulk[jj] | (ii < jj))             # wide–wide pairs come twice
        yield ii[keep], jj[keep]


def _blocks(g: NDArray[np.int64], block_points: int):
    """Row indices of consecutive whole groups, about ``block_points`` rows per block (a larger
    group is a block of its own): one KD-tree per block bounds the memory of the candidate pairs
    while keeping the number of trees tiny (a block holds many small epochs)."""
    order = np.argsort(g, kind="stable")
    counts = np.bincount(g)
    ends = np.cumsum(counts)
    start, acc = 0, 0
    for k, c in enumerate(counts):
        if acc and acc + c > block_points:
            yield order[start:ends[k - 1]]
            start, acc = int(ends[k - 1]), 0
        acc += int(c)
    if acc:
        yield order[start:]


def block_candidates(sc: Screen, block_points: int, g, pos, vel):
    """(i, j) per part of each block: global row indices of screened pairs."""
    for idx in _blocks(g, block_points):
        for ci, cj in _candidates(sc.take(idx), g[idx], pos[idx], vel[idx]):
            yield idx[ci], idx[cj]


def conflict_candidates(tracks: pl.DataFrame, cfg: ConflictConfig = ConflictConfig(), method_col: str = "method",
                        frame: geo.LocalFrame | None = None) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Screened row-index pairs (i < j, same (run, epoch, method) group) of ``tracks``: a superset
    of the pairs that come within R_г^пор + m_h horizontally and R_в^пор + m_v vertically (the
    near margins) at some t of the screening window (KD-tree, docs/methods.md "Candidate search"), on
    height (:func:`vertical_state`). Exposed for tests and benchmarks. Unlike
    :func:`predict_conflicts` it keeps tentative tracks (no ``max_vel_sigma_mps``)."""
    g = group_index(tracks, _group_cols(tracks, method_col))
    pos, vel, up, from_alt = state_arrays(tracks, frame)
    terms = point_terms(tracks, up, from_alt) if cfg.threshold_mode == "covariance" else None
    sc = screen_of(cfg, threshold_bounds(cfg, terms, len(g)))
    parts = list(block_candidates(sc, cfg.block_points, g, pos, vel))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i = np.concatenate([p[0] for p in parts])
    j = np.concatenate([p[1] for p in parts])
    return np.minimum(i, j), np.maximum(i, j)


def _group_cols(tracks: pl.DataFrame, method_col: str = "method") -> list[str]:
    cols = [c for c in ("run", "epoch") if c in tracks.columns]
    if method_col in tracks.columns:
        cols.append(method_col)
    return cols


def screen_states(tc: float, pos: NDArray[np.float64], vel: NDArray[np.float64],
                  omega: NDArray[np.float64] | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """States the KD-tree screen places the tracks with: as they are, except turning rows (ω ≠ 0),
    which the screen must find wherever their arc takes them: an arc of length |v|·t stays
    within |v|·t of its start, so such a row is centred at its current position with twice its
    horizontal speed (reach 2|v|·T/2 = |v|·T over the corrected window [0, T], centre ``tc``) —
    conservative."""
    if omega is None:
        return pos, vel
    turn = omega != 0.0
    vel_s = vel.copy()
    vel_s[turn, :2] *= 2.0
    pos_s = pos.copy()
    pos_s[turn, :2] -= vel_s[turn, :2] * tc          # centre pos_s + vel_s·t_c = the current position
    return pos_s, vel_s
