"""Shared ground of the fusion methods: the group layout of the rows, the kernel result, and the
segment reductions and batched linear algebra every method builds on.

The numeric kernels work on numpy arrays whose rows are sorted by group (run, epoch, target_id),
described by ``starts`` (first row of each group) and, for the recursions, by a :class:`Layout`.
They use segment reductions (``np.add.reduceat``); the recursions loop over the rank of the
epoch along each target's history, vectorised across targets and runs.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
import polars as pl
from numpy.typing import NDArray

__all__ = [
    "B", "BLOCK_ROWS", "CHAIN", "EIG_FLOOR", "F", "Fused", "GROUP", "Ix", "Layout", "Levels", "TRACK", "blocks",
    "chol", "inv_spd", "keep_single", "layout", "mix", "per_row", "segsum", "sym", "track_keys",
]

#: the rows of one fused group, of one target's history, of one local track
GROUP = ["run", "epoch", "target_id"]
CHAIN = ["run", "target_id"]
TRACK = ["run", "radar_id", "local_track_id"]
EIG_FLOOR = 1e-12  # relative eigenvalue floor for non-positive-definite covariances

F = NDArray[np.float64]
Ix = NDArray[np.intp]
B = NDArray[np.bool_]


class Fused(NamedTuple):
    """Kernel result: per-group state (G, 6) and covariance (G, 6, 6); per-row weights (n,)."""

    x: F
    cov: F
    weights: F


@dataclass(frozen=True)
class Layout:
    """Rows sorted by group (run, epoch, target_id), radar_id within a group.

    * ``starts`` (G,): first row of each group; ``counts`` (G,): rows per group (N);
    * ``group`` (n,): group index of each row;
    * ``prev_row`` (n,): row holding the same (run, target_id, radar_id) at the target's
      previous fused epoch when the radar set is unchanged, else −1 (restart at 1/N);
    * ``level`` (G,): rank of the group's epoch along its target's history (recursion order).
    """

    starts: Ix
    counts: Ix
    group: Ix
    prev_row: Ix
    level: Ix

    @classmethod
    def from_starts(cls, starts: Ix, n: int, prev_row: Ix | None = None, level: Ix | None = None) -> Layout:
        """Layout of independent groups (no recursion links unless given)."""
        starts = np.asarray(starts, dtype=np.intp)
        counts = np.diff(np.append(starts, n))
        group = np.repeat(np.arange(len(starts)), counts)
        prev = np.full(n, -1, dtype=np.intp) if prev_row is None else np.asarray(prev_row, dtype=np.intp)
        lev = np.zeros(len(starts), dtype=np.intp) if level is None else np.asarray(level, dtype=np.intp)
        return cls(starts, counts, group, prev, lev)

    @cached_property
    def levels(self) -> Levels:
        """The rows permuted into recursion order (computed once, shared by the recursions)."""
        n = len(self.group)
        order = np.argsort(self.level[self.group], kind="stable")
        bounds = np.append(0, np.cumsum(np.bincount(self.level[self.group]))).tolist()  # levels 0…max all occur
        pos = np.empty(n, dtype=np.intp)
        pos[order] = np.arange(n)
        prev = self.prev_row[order]
        prev = np.where(prev >= 0, pos[np.maximum(prev, 0)], -1)
        g = self.group[order]
        first = np.r_[True, g[1:] != g[:-1]][:n]
        return Levels(order, bounds, prev, np.cumsum(first) - 1, first, self.counts[g].astype(float))


class Levels(NamedTuple):
    """Rows of a :class:`Layout` in recursion order (by level, row order within a level).

    ``order``: row at each position; level k holds positions ``bounds[k]:bounds[k+1]``;
    ``prev``: position of the recursion predecessor (−1: restart); ``gid``: running group
    index; ``first``: first position of a group; ``n``: sources of the position's group."""

    order: Ix
    bounds: list[int]
    prev: Ix
    gid: Ix
    first: B
    n: F


# ---------------------------------------------------------------------------
# segment helpers and linear algebra
# ---------------------------------------------------------------------------


def segsum(a: F, starts: Ix) -> F:
    """Σ over each group of rows (rows sorted by group). Matrices are scattered into a
    zero-padded (N_max, G, ...) block by rank within the group and its N_max slabs added in
    rank order, several times faster than ``np.add.reduceat`` along axis 0 of a
    multi-dimensional array."""
    if a.ndim == 1:
        return np.add.reduceat(a, starts)
    counts = np.diff(np.append(starts, len(a)))
    group = np.repeat(np.arange(len(starts)), counts)
    block = np.zeros((int(counts.max()), len(starts), *a.shape[1:]))
    block[np.arange(len(a)) - starts[group], group] = a
    out = block[0]
    for slab in block[1:]:
        out += slab
    return out


def per_row(a: NDArray, starts: Ix, n: int) -> NDArray:
    """Broadcast a per-group value back to the group's rows."""
    return np.repeat(a, np.diff(np.append(starts, n)), axis=0)


def sym(c: F) -> F:
    """The symmetric part of (a batch of) square matrices."""
    return 0.5 * (c + np.swapaxes(c, -1, -2))


def chol(c: F) -> F:
    """Batched Cholesky factor of symmetric covariances; a matrix that is not positive
    definite is first projected onto PD (eigenvalues floored at 1e-12 × its largest)."""
    c = sym(c)
    try:
        return np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(c)
        w = np.maximum(w, EIG_FLOOR * np.maximum(w.max(axis=-1, keepdims=True), 1e-300))
        return np.linalg.cholesky(sym((v * w[..., None, :]) @ np.swapaxes(v, -1, -2)))


def _inv_lapack(c: F) -> F:
    """Batched inverse on the diagonally scaled matrix by LAPACK; Cholesky with projection onto
    PD (:func:`chol`) when a matrix is singular. The fallback of :func:`inv_spd`."""
    d = 1.0 / np.sqrt(np.maximum(np.einsum("...ii->...i", c), 1e-300))
    r = c * d[..., :, None] * d[..., None, :]
    try:
        inv = np.linalg.inv(r)
        if not np.isfinite(inv).all():
            raise np.linalg.LinAlgError("non-finite inverse")
    except np.linalg.LinAlgError:
        lower = chol(r)               # projects non-positive-definite matrices onto PD
        linv = np.linalg.solve(lower, np.broadcast_to(np.eye(c.shape[-1]), c.shape))
        inv = np.einsum("...ki,...kj->...ij", linv, linv, optimize=True)
    return sym(inv * d[..., :, None] * d[..., None, :])


def _chol_inv_small(c: F) -> tuple[F, B]:
    """Inverse of m symmetric k×k matrices c (m, k, k) on their diagonally scaled form
    r = D c D, D = diag(c)^-1/2: Cholesky L Lᵀ = r, M = L⁻¹, c⁻¹ = D Mᵀ M D. Written element by
    element, each step one vector operation over the m matrices (several times faster than
    LAPACK's per-matrix calls for 6×6). Returns the inverse and a mask of the matrices found
    positive definite (the others hold garbage)."""
    k = c.shape[-1]
    d = [1.0 / np.sqrt(np.maximum(c[:, i, i], 1e-300)) for i in range(k)]
    low: list[list[F]] = [[d[0]] * k for _ in range(k)]   # filled below the diagonal
    dinv: list[F] = [d[0]] * k                          # 1 / L_jj
    ok = np.ones(len(c), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for j in range(k):
            s = c[:, j, j] * (d[j] * d[j])
            for p in range(j):
                s = s - low[j][p] * low[j][p]
            ok &= s > 0
            dinv[j] = 1.0 / np.sqrt(s)
            for i in range(j + 1, k):
                t = (0.5 * (c[:, i, j] + c[:, j, i])) * (d[i] * d[j])
                for p in range(j):
                    t -= low[i][p] * low[j][p]
                low[i][j] = t * dinv[j]
        m = [[dinv[i]] * k for i in range(k)]           # M_ii = 1 / L_ii; below it next
        for j in range(k):
            for i in range(j + 1, k):
                t = low[i][j] * m[j][j]
                for p in range(j + 1, i):
                    t += low[i][p] * m[p][j]
                m[i][j] = -t * dinv[i]
        out = np.empty_like(c)
        for i in range(k):
            for j in range(i + 1):
                t = m[i][i] * m[i][j]
                for p in range(i + 1, k):
                    t += m[p][i] * m[p][j]
                t *= d[i] * d[j]
                out[:, i, j] = t
                out[:, j, i] = t
    return out, ok & np.isfinite(out).all(axis=(1, 2))


_INV_CHUNK = 8_192  # matrices per call of _chol_inv_small: its per-element vectors stay in cache


def inv_spd(c: F) -> F:
    """Batched inverse of symmetric positive-definite matrices, computed on the diagonally
    scaled (correlation-like) matrix via Cholesky (:func:`_chol_inv_small`); matrices that are
    not numerically positive definite go through :func:`_inv_lapack`."""
    flat = c.reshape(-1, *c.shape[-2:])
    out = np.empty_like(flat)
    for lo in range(0, len(flat), _INV_CHUNK):
        part, ok = _chol_inv_small(flat[lo:lo + _INV_CHUNK])
        out[lo:lo + _INV_CHUNK] = part
        if not ok.all():
            bad = lo + np.flatnonzero(~ok)
            out[bad] = _inv_lapack(flat[bad])
    return out.reshape(c.shape)


def mix(x: F, cov: F, w: F, starts: Ix) -> tuple[F, F]:
    """x = Σ w_n x_n and P = Σ W_n C_n W_n for per-row weights w of shape (n,) or (n, 6)."""
    w6 = np.broadcast_to(w[:, None], x.shape) if w.ndim == 1 else w
    xf = segsum(w6 * x, starts)
    pf = segsum(w6[:, :, None] * cov * w6[:, None, :], starts)
    return xf, pf


def keep_single(res: Fused, x: F, cov: F, starts: Ix) -> Fused:
    """Single-source groups: the report unchanged, weight 1."""
    n = len(x)
    single = np.diff(np.append(starts, n)) == 1
    rows = starts[single]
    res.x[single] = x[rows]
    res.cov[single] = cov[rows]
    res.weights[rows] = 1.0
    return res


def layout(keys: pl.DataFrame) -> Layout:
    """Group layout and recursion links of rows sorted by (run, epoch, target_id, radar_id)."""
    n = keys.height
    k = keys.select(*GROUP, "radar_id").with_row_index("__i")
    grp = k.group_by(GROUP, maintain_order=True).agg(
        pl.col("radar_id").alias("__set"), pl.col("__i").first().alias("__start"), pl.len().alias("__n"))
    grp = grp.with_columns(
        pl.int_range(pl.len()).over(CHAIN).alias("__level"),
        (pl.col("__set") == pl.col("__set").shift(1)).over(CHAIN).fill_null(False).alias("__cont"))
    starts = grp["__start"].to_numpy().astype(np.intp)
    counts = grp["__n"].to_numpy().astype(np.intp)
    if not np.array_equal(np.append(starts, n)[1:] - starts, counts):
        raise ValueError("rows must be sorted by (run, epoch, target_id, radar_id)")
    group = np.repeat(np.arange(len(starts)), counts)
    radar = keys["radar_id"].to_numpy()
    if n > 1 and np.any((group[1:] == group[:-1]) & (radar[1:] == radar[:-1])):
        raise ValueError("a radar contributes two reports to one (run, epoch, target_id)")
    prev = k.select(pl.col("__i").shift(1).over(CHAIN + ["radar_id"]))["__i"]
    prev = prev.fill_null(-1).to_numpy().astype(np.intp)
    prev = np.where(grp["__cont"].to_numpy()[group], prev, -1)
    return Layout(starts, counts, group, prev, grp["__level"].to_numpy().astype(np.intp))


def track_keys(df: pl.DataFrame) -> pl.DataFrame:
    """``df`` with its (run, radar_id, local_track_id) keys cast to the state's types."""
    return df.with_columns(pl.col("run").cast(pl.UInt32), pl.col("radar_id").cast(pl.UInt32),
                           pl.col("local_track_id").cast(pl.UInt32))


BLOCK_ROWS = 65_536


def blocks(starts: Ix, n: int, block: int = BLOCK_ROWS) -> Iterator[tuple[slice, Ix]]:
    """(row slice, group-local starts) of runs of whole groups holding about ``block`` rows."""
    firsts = np.unique(np.searchsorted(starts, np.arange(0, n, block), side="right") - 1)
    bounds = np.append(firsts, len(starts))
    for g0, g1 in zip(bounds[:-1], bounds[1:]):
        r0 = int(starts[g0])
        r1 = int(starts[g1]) if g1 < len(starts) else n
        yield slice(r0, r1), starts[g0:g1] - r0
