"""Clustering ("укрупнение") of fused targets into displayed groups (monograph §1.4, stage 6).

When an air picture holds more fused marks than the display can take (the "admissible norm",
``display_capacity``), compact groups of aircraft flying together are shown as one mark: a group
anchored on a **lead** target, with the member count. Each (run, epoch, method) is clustered on
its own; the whole table is clustered in one vectorised pass and only the lead bookkeeping steps
through the epochs.

Rules (every choice the monograph leaves open is fixed here):

* **Trigger.** A (run, epoch, method) is clustered only when it holds more than
  ``display_capacity`` fused targets (``always=True`` clusters every group). Other groups give no
  cluster rows: every target is shown on its own.
* **Compact groups** in (x, y, H), all epochs at once — H is the height of the vertical
  channel (``alt_m``: Mode C or geodetic, :mod:`tertiary.stages.tracking.altitude`), ENU z only for a table
  without it; a group index times a large separation is
  an extra coordinate, so points of different (run, epoch, method) are never neighbours.

  - ``"dbscan"``: DBSCAN (``min_samples=2``, i.e. single linkage) with radius ``eps_m`` on
    (x, y, H·h_scale): the connected components of the graph of pairs at most ``eps_m`` apart
    (every point with a neighbour is a core point), targets without a neighbour are noise.
  - ``"strobe"``: a box gate of half-sizes (dx, dy, dH) centred on the lead.

* **Leads and velocity selection (1.2)** — greedy leader clustering. Two targets are
  *compatible* when |vx − vx'| ≤ Δv and |vy − vy'| ≤ Δv and they are in the same DBSCAN group
  (strobe: each is inside the other's gate). Targets are taken in lead-priority order; a target
  not yet taken becomes a lead and takes every compatible target not yet taken. So a compact
  group keeps the members that pass (1.2) against its lead, and the members that fail are split
  off and regrouped the same way around a new lead (5 close aircraft, 2 flying the opposite way
  → clusters of 3 and 2; a split-off member with no compatible partner stays alone). With the
  strobe on a fresh picture this is the greedy strobe "leads in order of target_id". Lead
  priority within a (run, epoch, method):

  1. targets that led a cluster at the previous epoch of the same (run, method) (automatic
     tracking keeps the lead), oldest cluster (smallest id) first;
  2. targets that were members of a previous-epoch cluster: **lead re-selection** when that
     cluster's lead is gone (vanished, left the group or split off): by cluster, the member
     closest to the centroid of the cluster's present members (old lead excluded) first, in the
     clustering metric ((x, y, H·h_scale) for DBSCAN, (x/dx, y/dy, H/dH) for the strobe);
  3. new targets (the group's first appearance) by target_id, so a new group's lead is its
     member with the smallest target_id.

  The greedy is solved in parallel rounds over every group of an epoch index at once (same
  result as the sequential greedy); cost grows with the number of compatible pairs.
* **Groups of one target are not clusters.**
* **Cluster ids** are stable: a cluster keeps the id of the previous-epoch cluster whose lead
  leads it; the other clusters take, by mutual best overlap, the id of the previous-epoch cluster
  they share most members with (ties: the smaller id / the cluster with the smaller lead id);
  the rest get new ids. "Previous epoch" is the preceding epoch of the (run, method) in
  ``fused`` (not the previous epoch of the grid: a stream with no fused row at an epoch
  bridges it); a picture that was not clustered breaks continuity. Ids are numbered from 1 per
  (run, method) in order of creation.
* Rows with a non-finite position or horizontal velocity are never clustered (shown alone).

Windowed runs: :func:`cluster_step` clusters the fused rows of one window of epochs,
carrying a :class:`ClusterState` per (run, method): its last epoch in ``fused`` (absolute µs),
the number of ids it has created, and the targets clustered at that epoch with their cluster
id and lead flag. Consecutive windows give the whole-run table; :func:`cluster` is one step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tertiary.core.stage import T_MIN_US, Window, check_window
from tertiary.contract import TABLES

__all__ = ["ClusteringConfig", "ClusterState", "cluster", "cluster_step", "cluster_summary", "init_cluster_state"]

KEYS = ["run", "epoch", "method"]
_NEEDED = ["run", "epoch", "method", "target_id", "x_m", "y_m", "z_m", "vx_mps", "vy_mps"]
_OUT = TABLES["clusters"].required
# spacing, in query radii, of the group-index coordinate that keeps groups apart in one KD-tree
# (any value > 1 is exact: same-group points share the coordinate exactly); wide spacing lets
# the tree separate the groups first, which made the pair queries about twice as fast as 3
_GAP = 30.0


@dataclass(frozen=True)
class ClusteringConfig:
    """Parameters of clustering.

    * ``algorithm``: ``"dbscan"`` (radius ``eps_m`` on (x, y, H·h_scale)) or ``"strobe"`` (box
      gate of ``half_sizes_m`` = (dx, dy, dH) around the lead).
    * ``h_scale``: vertical-to-horizontal scale of the DBSCAN metric (10: 300 m ≈ 3 km).
    * ``dv_mps``: velocity-selection threshold Δv of (1.2), per horizontal component.
    * ``display_capacity``: a (run, epoch, method) is clustered only above this many targets;
      ``always=True`` clusters regardless.
    """

    algorithm: Literal["dbscan", "strobe"] = "dbscan"
    eps_m: float = 5000.0
    h_scale: float = 10.0
    half_sizes_m: tuple[float, float, float] = (5000.0, 5000.0, 500.0)
    dv_mps: float = 30.0
    display_capacity: int = 150
    always: bool = False

    def __post_init__(self) -> None:
        if self.algorithm not in ("dbscan", "strobe"):
            raise ValueError(f"algorithm must be 'dbscan' or 'strobe', got {self.algorithm!r}")
        if not self.eps_m > 0 or not self.h_scale > 0:
            raise ValueError("eps_m and h_scale must be positive")
        if len(self.half_sizes_m) != 3 or not all(h > 0 for h in self.half_sizes_m):
            raise ValueError("half_sizes_m must be three positive numbers (dx, dy, dH)")
        if not self.dv_mps >= 0:
            raise ValueError("dv_mps must be non-negative")
        if self.display_capacity < 0:
            raise ValueError("display_capacity must be non-negative")


def _empty() -> pl.DataFrame:
    return pl.DataFrame(schema=_OUT)


# ---------------------------------------------------------------------------
# compatibility graph, all epochs at once
# ---------------------------------------------------------------------------


def _single_linkage(feats: NDArray[np.float64], eps: float) -> NDArray[np.int64]:
    """DBSCAN labels for ``min_samples=2`` (−1: noise): with two samples every point that has a
    neighbour within ``eps`` is a core point, so the clusters are the connected components of
    the ε-graph. One KD-tree pair query (several times faster than scikit-learn's ball tree)."""
    n = len(feats)
    pairs = cKDTree(feats).query_pairs(r=eps, p=2.0, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    has_pair = np.zeros(n, dtype=bool)
    has_pair[pairs.ravel()] = True
    return np.where(has_pair, comp, -1).astype(np.int64)


def _pairs(raw: NDArray[np.float64], scaled: NDArray[np.float64], vel: NDArray[np.float64],
           group: NDArray[np.int64], cfg: ClusteringConfig) -> NDArray[np.int64]:
    """Undirected pairs (i, j) that may share a cluster with either as the lead.

    DBSCAN: same DBSCAN cluster and velocity selection (1.2); strobe: each inside the other's
    gate and (1.2). Candidates come from one Chebyshev KD-tree query over every epoch (the group
    index is an extra coordinate), then are checked exactly.
    """
    vscale = 1.0 / cfg.dv_mps if cfg.dv_mps > 0 else 1e9
    if cfg.algorithm == "dbscan":
        label = _single_linkage(np.column_stack([scaled, group * (_GAP * cfg.eps_m)]), cfg.eps_m)
        sel = np.flatnonzero(label >= 0)                # DBSCAN noise: alone
        space = np.column_stack([label[sel] * _GAP, vel[sel] * vscale])
    else:
        sel = np.arange(len(raw))
        space = np.column_stack([scaled, group * _GAP, vel * vscale])
    if len(sel) < 2:
        return np.empty((0, 2), dtype=np.int64)
    pairs = cKDTree(space).query_pairs(r=1.0 + 1e-9, p=np.inf, output_type="ndarray")
    pairs = sel[pairs.astype(np.int64)].reshape(-1, 2)
    i, j = pairs[:, 0], pairs[:, 1]
    ok = (np.abs(vel[i] - vel[j]) <= cfg.dv_mps).all(axis=1)
    if cfg.algorithm == "strobe":
        ok &= (np.abs(raw[i] - raw[j]) <= np.asarray(cfg.half_sizes_m)).all(axis=1)
    return pairs[ok]


# ---------------------------------------------------------------------------
# leads within one epoch index (all streams and groups together)
# ---------------------------------------------------------------------------


def _priority(tid: NDArray[np.uint64], scaled: NDArray[np.float64], prev_cid: NDArray[np.int64],
              prev_lead: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Lead priority rank (0 first): previous leads by cluster id; members of a previous cluster
    by cluster id, then distance to the centroid of that cluster's other present members (its
    old lead excluded); new targets by target_id."""
    n = len(tid)
    cat = np.where(prev_lead, 0, np.where(prev_cid >= 0, 1, 2))
    d2 = np.zeros(n)
    mem = np.flatnonzero(cat == 1)
    if len(mem):
        _, inv = np.unique(prev_cid[mem], return_inverse=True)
        cnt = np.bincount(inv)
        centroid = np.column_stack([np.bincount(inv, weights=scaled[mem, c]) for c in range(3)])
        d2[mem] = ((scaled[mem] - centroid[inv] / cnt[inv, None]) ** 2).sum(axis=1)
    order = np.lexsort((tid, d2, np.where(cat < 2, prev_cid, 0), cat))
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    return rank


def _greedy_leads(rank: NDArray[np.int64], pairs: NDArray[np.int64]) -> NDArray[np.int64]:
    """Greedy leader clustering: in priority order an unassigned target becomes a lead and takes
    every unassigned target joined to it by ``pairs``. Returns each target's lead.

    Solved in parallel rounds with the same result as the sequential greedy: a target whose
    earliest not-yet-taken neighbour (itself included) is itself is a lead; one whose earliest
    such neighbour is a lead is taken by it.
    """
    n = len(rank)
    by_rank = np.argsort(rank)
    u = np.concatenate([pairs[:, 0], pairs[:, 1]])     # directed: v is a neighbour of u
    v = np.concatenate([pairs[:, 1], pairs[:, 0]])
    status = np.zeros(n, dtype=np.int8)                # 0 undecided, 1 lead, 2 taken
    lead = np.full(n, -1, dtype=np.int64)
    while True:
        und = status == 0
        if not und.any():
            return lead
        keep = und[u] & (status[v] != 2)
        u, v = u[keep], v[keep]
        m = rank.copy()
        np.minimum.at(m, u, rank[v])
        new = und & (m == rank)
        status[new] = 1
        lead[new] = np.flatnonzero(new)
        first = by_rank[m]
        taken = und & ~new & (status[first] == 1)
        status[taken] = 2
        lead[taken] = first[taken]


def _match_ids(g_of_member: NDArray[np.int64], cid_of_member: NDArray[np.int64],
               lead_tid: NDArray[np.uint64]) -> NDArray[np.int64]:
    """Mutual-best-overlap matching of groups to previous cluster ids (−1: unmatched)."""
    out = np.full(len(lead_tid), -1, dtype=np.int64)
    if len(g_of_member) == 0:
        return out
    pairs, overlap = np.unique(np.column_stack([g_of_member, cid_of_member]), axis=0,
                               return_counts=True)
    g, c = pairs[:, 0], pairs[:, 1]
    while len(g):
        # best id per group: most members, then smallest id
        o = np.lexsort((c, -overlap, g))
        best_c_of_g = o[np.r_[True, g[o][1:] != g[o][:-1]]]
        # best group per id: most members, then smallest lead id
        o = np.lexsort((lead_tid[g], -overlap, c))
        best_g_of_c = o[np.r_[True, c[o][1:] != c[o][:-1]]]
        mutual = np.intersect1d(best_c_of_g, best_g_of_c)
        if len(mutual) == 0:
            break
        out[g[mutual]] = c[mutual]
        keep = ~np.isin(g, g[mutual]) & ~np.isin(c, c[mutual])
        g, c, overlap = g[keep], c[keep], overlap[keep]
    return out


@dataclass(frozen=True)
class _Index:
    """Rows of ``fused`` in (run, method, epoch, target_id) order, with integer keys computed
    in numpy (multi-column polars sorts and struct ranks dominated the stage).

    ``order``: fused row of each sorted position; per sorted position: ``n`` targets in its
    (run, epoch, method), ``group`` a distinct integer per (run, epoch, method), ``k`` the dense
    rank of its epoch within its (run, method), ``tidx`` a dense index of (run, method,
    target_id) and ``tid`` the target_id; ``duplicated``: a (run, epoch, method, target_id)
    occurs twice."""

    order: NDArray[np.int64]
    n: NDArray[np.int64]
    group: NDArray[np.int64]
    k: NDArray[np.int64]
    tidx: NDArray[np.int64]
    tid: NDArray[np.uint64]
    duplicated: bool
    rm: NDArray[np.int64]

    @classmethod
    def of(cls, fused: pl.DataFrame) -> "_Index":
        # dense codes (u32) from polars ranks: lighter than np.unique on the full table
        codes = [(fused[c].rank("dense").to_numpy() - 1).astype(np.int64)
                 for c in ("run", "method", "epoch", "target_id")]
        sizes = [int(c.max()) + 1 for c in codes]
        if np.prod(np.asarray(sizes, dtype=float)) < 2.0 ** 62:
            key = ((codes[0] * sizes[1] + codes[1]) * sizes[2] + codes[2]) * sizes[3] + codes[3]
            order = np.argsort(key, kind="stable")
            del key
        else:                                          # key would overflow int64
            order = np.lexsort(codes[::-1])
        r, m, e, t = (c[order] for c in codes)
        del codes
        same_rm = (r[1:] == r[:-1]) & (m[1:] == m[:-1])
        same_g = same_rm & (e[1:] == e[:-1])
        duplicated = bool(np.any(same_g & (t[1:] == t[:-1])))
        group = np.concatenate([[0], np.cumsum(~same_g)])
        rm = np.concatenate([[0], np.cumsum(~same_rm)])
        n = np.bincount(group)[group]
        # dense epoch rank within (run, method): group index minus that of the block's first row
        rm_first = np.flatnonzero(np.concatenate([[True], ~same_rm]))
        k = group - np.repeat(group[rm_first], np.diff(np.append(rm_first, len(group))))
        tidx = np.unique((r * sizes[1] + m) * sizes[3] + t, return_inverse=True)[1].reshape(-1)
        tid = fused["target_id"].to_numpy().astype(np.uint64)[order]
        return cls(order, n, group, k, tidx, tid, duplicated, rm)


# ---------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------


def _height(fused: pl.DataFrame) -> NDArray[np.float64]:
    """H of every row: the vertical channel ``alt_m`` (barometric or geodetic height) where the
    table carries it and it is not null, else the ENU ``z_m`` (no origin is known here; z
    falls below the height by ρ²/2R, ~785 m at 100 km, so give fusion's ``alt_m``)."""
    z = fused["z_m"].cast(pl.Float64).to_numpy()
    if "alt_m" not in fused.columns:
        return z
    alt = fused["alt_m"].cast(pl.Float64).fill_null(np.nan).to_numpy()
    return np.where(np.isfinite(alt), alt, z)


_NEVER = T_MIN_US            # a target's last clustered epoch: none carried
_NO_PREV = T_MIN_US + 1         # a stream's previous epoch: none (differs from _NEVER: no match)
_SH = np.int64(1 << 32)      # stride of a stream in the in-step cluster keys (stream · _SH + id)
_STREAM = ["run", "method"]
_STREAMS = {"run": pl.Int64, "method": pl.String, "last_us": pl.Int64, "next_id": pl.Int64}
_TARGETS = {"run": pl.Int64, "method": pl.String, "target_id": pl.UInt64, "cluster_id": pl.Int64,
            "lead": pl.Boolean}


@dataclass(frozen=True)
class ClusterState:
    """What cluster continuity needs from earlier windows, per (run, method) stream.

    * ``streams``: run, method; ``last_us`` the stream's last epoch in ``fused`` (absolute µs:
      the "previous epoch" of its next one) and ``next_id`` the clusters it has created so far
      (cluster ids are 1 + the creation index).
    * ``targets``: run, method, target_id of the targets clustered at their stream's last
      epoch, with that ``cluster_id`` (0-based) and ``lead``; no other target can continue a
      cluster, so nothing else is kept.
    * ``t_us``: end of the last window processed (:data:`~tertiary.core.stage.T_MIN_US` before the first).
    """

    streams: pl.DataFrame
    targets: pl.DataFrame
    t_us: int = T_MIN_US


def init_cluster_state() -> ClusterState:
    """The state before the first window: no stream seen, no cluster."""
    return ClusterState(pl.DataFrame(schema=_STREAMS), pl.DataFrame(schema=_TARGETS))


@dataclass
class _Carry:
    """One step's view of the state, on the step's integer codes (mutated by the epoch loop).

    Per sorted position: ``epoch_us`` and ``prev_us`` (previous epoch of its stream); per stream
    code: ``keys`` (run, method), ``next_id``; per target code: ``keys`` (run, method,
    target_id), ``rm``, ``last_us`` (last clustered epoch), ``gcid`` (stream · _SH + cluster id,
    −1: none) and ``lead``."""

    epoch_us: NDArray[np.int64]
    prev_us: NDArray[np.int64]
    streams: pl.DataFrame
    next_id: NDArray[np.int64]
    targets: pl.DataFrame
    rm: NDArray[np.int64]
    last_us: NDArray[np.int64]
    gcid: NDArray[np.int64]
    lead: NDArray[np.bool_]

    @classmethod
    def of(cls, fused: pl.DataFrame, idx: _Index, state: ClusterState) -> "_Carry":
        ep = fused["epoch"].dt.epoch("us").to_numpy()[idx.order]
        rm_first = np.flatnonzero(np.r_[True, idx.rm[1:] != idx.rm[:-1]])
        first = idx.order[rm_first]
        streams = pl.DataFrame([fused["run"].gather(first).cast(pl.Int64),
                                fused["method"].gather(first).cast(pl.String)])
        known = streams.join(state.streams, on=_STREAM, how="left", maintain_order="left")
        s_prev = known["last_us"].fill_null(_NO_PREV).to_numpy()
        g_first = np.flatnonzero(np.r_[True, idx.group[1:] != idx.group[:-1]])
        prev_g = np.r_[_NO_PREV, ep[g_first][:-1]]          # epoch of the preceding group
        prev = np.where(idx.k == 0, s_prev[idx.rm], prev_g[idx.group])
        _, t_first = np.unique(idx.tidx, return_index=True)
        rm = idx.rm[t_first]
        targets = streams[rm].with_columns(pl.Series("target_id", idx.tid[t_first], pl.UInt64))
        tk = targets.join(state.targets, on=_STREAM + ["target_id"], how="left", maintain_order="left")
        found = tk["cluster_id"].is_not_null().to_numpy()
        # state targets were clustered at their stream's last epoch (ClusterState invariant)
        last_us = np.where(found, s_prev[rm], _NEVER)
        gcid = np.where(found, rm * _SH + tk["cluster_id"].fill_null(0).to_numpy(), -1)
        lead = found & tk["lead"].fill_null(False).to_numpy()
        return cls(ep, prev, streams, known["next_id"].fill_null(0).to_numpy().copy(), targets, rm,
                   last_us, gcid, lead)

    def state(self, state: ClusterState, idx: _Index, t1_us: int) -> ClusterState:
        """The state after this window: its streams' last epochs and ids, and the targets
        clustered at those epochs; streams absent from the window keep theirs."""
        rm_last = np.r_[np.flatnonzero(idx.rm[1:] != idx.rm[:-1]), len(idx.rm) - 1]
        s_last = self.epoch_us[rm_last]
        streams = self.streams.with_columns(pl.Series("last_us", s_last), pl.Series("next_id", self.next_id))
        live = self.last_us == s_last[self.rm]
        targets = self.targets.filter(pl.Series(live)).with_columns(
            pl.Series("cluster_id", (self.gcid - self.rm * _SH)[live]), pl.Series("lead", self.lead[live]))
        return ClusterState(
            pl.concat([state.streams.join(self.streams, on=_STREAM, how="anti"), streams]),
            pl.concat([state.targets.join(self.streams, on=_STREAM, how="anti"), targets]), t1_us)


def _screen(fused: pl.DataFrame) -> pl.DataFrame:
    """The displayed targets of ``fused``: required columns checked, tentative rows left out."""
    missing = [c for c in _NEEDED if c not in fused.columns]
    if missing:
        raise ValueError(f"fused: missing column(s) {', '.join(missing)}")
    if "tentative" in fused.columns:
        fused = fused.filter(~pl.col("tentative").fill_null(False))
    return fused


def cluster_step(state: ClusterState, fused_window: pl.DataFrame, t0_us: int, t1_us: int,
                 cfg: ClusteringConfig = ClusteringConfig()) -> tuple[pl.DataFrame, ClusterState]:
    """One window of :func:`cluster`: (the window's ``clusters`` rows, new state).

    ``fused_window``: the fused rows with epoch in [t0_us, t1_us) (int64 µs since the Unix
    epoch), every method; no margin: a picture is clustered on its own and the only memory of
    earlier epochs (leads, cluster ids, the previous epoch of each (run, method)) is in
    ``state``. Pure: ``state`` is not modified.
    """
    check_window(fused_window, Window(0, t0_us, t1_us), after_us=state.t_us, table="fused")
    fused = _screen(fused_window)
    if fused.height == 0:
        return _empty(), ClusterState(state.streams, state.targets, t1_us)
    idx = _Index.of(fused)
    if idx.duplicated:
        raise ValueError("fused: duplicate target_id within a (run, epoch, method)")
    carry = _Carry.of(fused, idx, state)
    clusters = _cluster_pictures(fused, idx, carry, cfg)
    return clusters, carry.state(state, idx, t1_us)


def cluster(fused: pl.DataFrame, cfg: ClusteringConfig = ClusteringConfig()) -> pl.DataFrame:
    """Cluster the fused picture of every (run, epoch, method): the ``clusters`` table.

    One row per cluster of two or more targets: run, epoch, method, cluster_id, lead_target_id,
    members (target ids, ascending, the lead included) and count. See the module docstring for
    the rules. Tentative targets (``tentative`` True: clutter-only) are not targets on the
    display and are left out. One :func:`cluster_step` over the whole run.
    """
    w = Window.unbounded()
    return cluster_step(init_cluster_state(), fused, w.t0_us, w.t1_us, cfg)[0]


def _cluster_pictures(fused: pl.DataFrame, idx: _Index, carry: _Carry, cfg: ClusteringConfig) -> pl.DataFrame:
    """The clusters of the pictures of ``fused`` (indexed by ``idx``), continuing ``carry``
    (updated in place)."""
    # only the pictures above the display capacity are read (positions in the sorted order)
    cand = np.arange(len(idx.order)) if cfg.always else np.flatnonzero(idx.n > cfg.display_capacity)
    rows_f = idx.order[cand]
    vals = np.column_stack([fused[c].to_numpy().astype(np.float64)[rows_f] for c in _NEEDED[4:]])
    vals[:, 2] = _height(fused)[rows_f]
    finite = np.isfinite(vals).all(axis=1)
    sel_rows, vals = cand[finite], vals[finite]
    if len(sel_rows) < 2:
        return _empty()

    raw = np.ascontiguousarray(vals[:, :3])
    if cfg.algorithm == "dbscan":
        scaled = raw * np.array([1.0, 1.0, cfg.h_scale])
    else:
        scaled = raw / np.asarray(cfg.half_sizes_m, dtype=np.float64)
    vel = np.ascontiguousarray(vals[:, 3:])
    del vals
    pairs = _pairs(raw, scaled, vel, idx.group[sel_rows], cfg)
    if len(pairs) == 0:
        return _empty()

    # order the targets by epoch index (isolated ones simply lead themselves)
    k_all = idx.k[sel_rows]
    sel = np.argsort(k_all, kind="stable")
    k_all = k_all[sel]
    local = np.empty(len(sel_rows), dtype=np.int64)
    local[sel] = np.arange(len(sel_rows))
    pairs = local[pairs]
    pairs = pairs[np.argsort(pairs.min(axis=1), kind="stable")]
    pos = sel_rows[sel]                                  # sorted positions
    scaled = scaled[sel]
    out_rows, out_cid, out_lead = _lead_epochs(k_all, pairs, scaled, idx.tid[pos], idx.tidx[pos],
                                               carry.epoch_us[pos], carry.prev_us[pos], carry)
    if not out_rows:
        return _empty()
    out_idx = idx.order[pos[np.concatenate(out_rows)]]
    gcid = np.concatenate(out_cid)
    # series by series: a gather on the multi-chunk frame rechunked it (+270 MB peak RSS)
    members = (
        pl.DataFrame([fused[c].gather(out_idx) for c in KEYS + ["target_id"]])
        .with_columns(
            cluster_id=pl.Series(gcid % _SH + 1, dtype=pl.UInt64),
            lead_target_id=pl.Series(np.concatenate(out_lead), dtype=pl.UInt64),
        )
    )
    return (
        members.sort("target_id")
        .group_by(KEYS + ["cluster_id"])
        .agg(
            pl.col("lead_target_id").first(),
            members=pl.col("target_id").cast(pl.UInt64),
            count=pl.len().cast(pl.UInt32),
        )
        .select([pl.col(c).cast(t) for c, t in _OUT.items()])
        .sort(["run", "epoch", "method", "cluster_id"])
    )


def _lead_epochs(k_all: NDArray[np.int64], pairs: NDArray[np.int64], scaled: NDArray[np.float64],
                 tid: NDArray[np.uint64], tidx: NDArray[np.int64], epoch_us: NDArray[np.int64],
                 prev_us: NDArray[np.int64], carry: _Carry
                 ) -> tuple[list[NDArray[np.int64]], list[NDArray[np.int64]], list[NDArray[np.uint64]]]:
    """Leads and cluster ids, epoch index by epoch index (the bookkeeping loop). Inputs are per
    candidate target, sorted by epoch index ``k_all`` (then (run, method, target_id)); returns
    per clustered epoch the member positions, their in-step cluster keys and their leads."""
    out_rows, out_cid, out_lead = [], [], []
    ks, starts = np.unique(k_all, return_index=True)
    bounds = np.r_[starts, len(k_all)]
    pair_bounds = np.searchsorted(pairs.min(axis=1), bounds)
    for e in range(len(ks)):                             # loop over epoch index (bookkeeping)
        if pair_bounds[e] == pair_bounds[e + 1]:
            continue                                     # no compatible pair: nothing clusters
        lo, hi = bounds[e], bounds[e + 1]
        s = slice(lo, hi)
        ti, ts = tidx[s], tid[s]
        # continuity: clustered at the previous epoch of the same (run, method) in fused
        cont = carry.last_us[ti] == prev_us[s]
        prev_cid = np.where(cont, carry.gcid[ti], -1)
        prev_lead = cont & carry.lead[ti]
        rank = _priority(ts, scaled[s], prev_cid, prev_lead)
        lead = _greedy_leads(rank, pairs[pair_bounds[e]:pair_bounds[e + 1]] - lo)

        size = np.bincount(lead, minlength=len(lead))
        member = np.flatnonzero(size[lead] >= 2)
        if len(member) == 0:
            continue
        leads, g = np.unique(lead[member], return_inverse=True)
        cid = np.where(prev_lead[leads], prev_cid[leads], -1)
        claimed = cid[cid >= 0]
        cand = (cid[g] < 0) & (prev_cid[member] >= 0) & ~np.isin(prev_cid[member], claimed)
        matched = _match_ids(g[cand], prev_cid[member][cand], ts[leads])
        cid = np.where(cid >= 0, cid, matched)
        cid = _new_ids(cid, carry.rm[ti[leads]], carry.next_id)

        mt = ti[member]
        carry.last_us[mt] = epoch_us[s][member]
        carry.gcid[mt] = cid[g]
        carry.lead[mt] = lead[member] == member
        out_rows.append(np.arange(lo, hi)[member])
        out_cid.append(cid[g])
        out_lead.append(ts[leads][g])
    return out_rows, out_cid, out_lead


def _new_ids(cid: NDArray[np.int64], rm: NDArray[np.int64], next_id: NDArray[np.int64]) -> NDArray[np.int64]:
    """Fresh cluster keys (stream · _SH + id) for the unmatched clusters (``cid`` < 0), numbered
    per stream in order of creation; ``rm`` (each cluster's stream) is non-decreasing.
    Advances ``next_id`` in place."""
    new = np.flatnonzero(cid < 0)
    if len(new) == 0:
        return cid
    r = rm[new]
    nth = np.arange(len(r)) - np.searchsorted(r, r)      # creation index within the stream
    out = cid.copy()
    out[new] = r * _SH + next_id[r] + nth
    np.add.at(next_id, r, 1)
    return out

def cluster_summary(clusters: pl.DataFrame, fused: pl.DataFrame | None = None) -> pl.DataFrame:
    """Per (run, epoch, method): ``n_clusters``, ``mean_size``, ``max_size`` and
    ``targets_clustered`` (targets represented by cluster marks).

    With ``fused`` every (run, epoch, method) of the picture gets a row (zeros where nothing was
    clustered) plus ``n_targets`` and ``n_marks`` = marks on the display (clusters + targets shown
    alone).
    """
    summary = clusters.group_by(KEYS).agg(
        n_clusters=pl.len().cast(pl.UInt32),
        mean_size=pl.col("count").cast(pl.Float64).mean(),
        max_size=pl.col("count").max().cast(pl.UInt32),
        targets_clustered=pl.col("count").sum().cast(pl.UInt32),
    )
    if fused is None:
        return summary.sort(KEYS)
    counts = fused.group_by(KEYS).agg(n_targets=pl.len().cast(pl.UInt32))
    summary = summary.with_columns([pl.col(c).cast(counts.schema[c]) for c in KEYS])
    return (
        counts.join(summary, on=KEYS, how="left")
        .with_columns(
            pl.col("n_clusters", "max_size", "targets_clustered").fill_null(0),
            pl.col("mean_size").fill_null(0.0),
        )
        .with_columns(
            n_marks=(pl.col("n_targets") - pl.col("targets_clustered") + pl.col("n_clusters"))
            .cast(pl.UInt32)
        )
        .select(KEYS + ["n_clusters", "mean_size", "max_size", "targets_clustered",
                        "n_targets", "n_marks"])
        .sort(KEYS)
    )
