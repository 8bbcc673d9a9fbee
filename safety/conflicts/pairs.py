"""The decision of screened pairs: the staged vertical / horizontal tests, the geometry and
thresholds of the survivors, the rule of ``ConflictConfig.mode`` (straight, levelled or turning
prediction), and the ``conflicts`` rows of a window under several settings at once
(docs/methods.md, "Conflict prediction (STCA)": "Output set")."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence

import numpy as np
import polars as pl
from numpy.typing import NDArray

from safety.conflicts.config import ConflictConfig
from safety.conflicts.geometry import (clamped_dz, clamped_vmin, closest_approach, conflict_interval,
                                       conflict_interval_levelled, endpoint_min, level_off_times, seed_vertical,
                                       state_arrays)
from safety.conflicts.screen import block_candidates, group_index, screen_of, screen_states, union_screen
from safety.conflicts.thresholds import (Bounds, PointTerms, applied_thresholds, point_terms, threshold_bounds,
                                         threshold_time)
from safety.conflicts.turns import ArcTable, arc_lower_bound, arc_rows, turn_rates
from tertiary.contract import CLEARED_ALT_COLUMN, SELECTED_ALT_COLUMN, TABLES, TIME
from tertiary.core import geo

__all__ = ["empty_conflicts", "CONFLICT_EXTRA", "WindowRows", "pair_rows", "Groups", "in_one_group"]

def empty_conflicts() -> pl.DataFrame:
    """An empty ``conflicts`` table with :data:`CONFLICT_EXTRA` (a new frame each call)."""
    return _empty_conflicts().clear()


@functools.cache
def _empty_conflicts() -> pl.DataFrame:
    # built once: a frame from a schema costs a hundred times its clear(), and a window makes thousands
    return pl.DataFrame(schema={**TABLES["conflicts"].required, **CONFLICT_EXTRA})


#: columns of ``conflicts`` beyond ``schema.TABLES["conflicts"]`` (to be added there)
CONFLICT_EXTRA: dict[str, pl.DataType] = dict(TABLES["conflicts"].optional)   # t_in_s, near


def _levelled_rows(tau: NDArray[np.float64] | None, i: NDArray[np.int64], j: NDArray[np.int64], w1: float
                   ) -> NDArray[np.int64]:
    """Pairs (positions in i, j) where either aircraft levels off at its selected level before
    the end of the window (``tau`` None: none)."""
    if tau is None:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.minimum(tau[i], tau[j]) < w1)


def _window_vmin(dz, dvz, vh, tau, i, j, w0: float, w1: float) -> NDArray[np.float64]:
    """min over the window of |Δh(t)|: linear, or clamped at the selected levels where one applies."""
    vmin = endpoint_min(dz + dvz * w0, dz + dvz * w1)
    k = _levelled_rows(tau, i, j, w1)
    if k.size:
        vmin[k] = clamped_vmin(dz[k], vh[i[k]], vh[j[k]], tau[i[k]], tau[j[k]], w0, w1)
    return vmin


def _evaluate_pairs(cfg: ConflictConfig, st: NDArray[np.float64], terms: PointTerms | None,
                    i: NDArray[np.int64], j: NDArray[np.int64], bnd: Bounds,
                    tau: NDArray[np.float64] | None = None,
                    arcs: "ArcTable | None" = None, vmin: NDArray[np.float64] | None = None) -> dict[str, NDArray]:
    """Output-set membership, geometry, thresholds and decision of pairs (i, j); ``st`` holds the
    state columns x, y, h, vx, vy, ḣ as rows; ``bnd`` the per-track threshold bounds
    (:func:`threshold_bounds`); ``tau`` each track's level-off time at its selected level
    (:func:`level_off_times`, corrected mode; None: linear vertical prediction); ``arcs`` each
    track's turn rate as :class:`ArcTable` (:func:`turn_rates`; None: no row turns). Staged: the vertical window
    test, then the horizontal one (cheap upper bounds of the thresholds first), then the full
    geometry of the survivors only. Pairs with a turning member take their horizontal minimum,
    its time and the decision from the arc grid (:func:`conflict_interval_arc`). ``vmin``: the
    pairs' :func:`_window_vmin` when already computed (settings sharing the window and ``tau``)."""
    x, y, h, vx, vy, vh = st
    t_thr = cfg.t_thr_s
    w0, w1 = cfg.window_s
    mh, mv = cfg.near_margin_h_m, cfg.near_margin_v_m
    fixed = cfg.threshold_mode == "fixed" or terms is None
    base_v = bnd.base_v
    # 1. vertical: min over the window of |Δh(t)| ≤ R_в^пор + m_v (upper bound of R_в^пор)
    dz = h[j] - h[i]
    dvz = vh[j] - vh[i]
    excess = (_window_vmin(dz, dvz, vh, tau, i, j, w0, w1) if vmin is None else vmin) - base_v
    if fixed:
        ok = excess <= 0.0
    else:
        ok = (excess <= 0.0) | (excess * excess <= cfg.k_v ** 2 * (bnd.q[i] + bnd.q[j]))
    sel = np.flatnonzero(ok)
    i, j, dz, dvz = i[sel], j[sel], dz[sel], dvz[sel]
    # 2. horizontal: min over the window of |r − v t| ≤ R_г^пор + m_h
    rx, ry = x[j] - x[i], y[j] - y[i]
    vx_, vy_ = vx[i] - vx[j], vy[i] - vy[j]
    vv = vx_ * vx_ + vy_ * vy_
    moving = vv >= cfg.eps_mps ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = np.where(moving, np.clip((rx * vx_ + ry * vy_) / vv, w0, w1), 0.0)
    ex, ey = rx - vx_ * ts, ry - vy_ * ts
    d2 = ex * ex + ey * ey
    arc = _turning_rows(None if arcs is None else arcs.slot, i, j)
    if arc.size:                       # turning pairs: a lower bound of the arc's distance over [0, T]
        lim = (bnd.base_h + bnd.reach[i[arc]] + bnd.reach[j[arc]]) * (1.0 + 1e-6)
        d2[arc] = arc_lower_bound(cfg, st, arcs, i[arc], j[arc], np.sqrt(d2[arc]), lim) ** 2
    if not fixed:
        # R_г^пор(i, j, t) + m_h ≤ base_h + reach_i + reach_j, reach = k_h·sqrt(max_t λ_max)
        # (λ_max(A + B) ≤ λ_max A + λ_max B; 1e-6 guards rounding)
        reach = bnd.reach
        ub = (bnd.base_h + reach[i] + reach[j]) * (1.0 + 1e-6)
        is_arc = np.zeros(len(ub), bool)
        is_arc[arc] = True
        sel = np.flatnonzero(d2 <= ub * ub)
        i, j, dz, dvz, rx, ry, vx_, vy_, d2, is_arc = (a[sel] for a in (i, j, dz, dvz, rx, ry, vx_, vy_, d2, is_arc))
        arc = np.flatnonzero(is_arc)
    # 3. geometry (5.10)–(5.13), thresholds at the time that matters, output-set membership
    _, r_min, t_min, closure, _ = closest_approach(rx, ry, vx_, vy_, cfg.eps_mps)
    t_eval = threshold_time(cfg, t_min)
    r_thr, z_thr, z_full, z_level = applied_thresholds(cfg, terms, i, j, t_eval, vh)
    vmin = _window_vmin(dz, dvz, vh, tau, i, j, w0, w1)
    # a levelled pair's threshold varies by piece: screen it with the largest (z_full)
    z_screen = z_thr.copy()
    lv = _levelled_rows(tau, i, j, w1)
    z_screen[lv] = z_full[lv]
    r_screen = r_thr + mh
    if arc.size:                       # their thresholds come at the arc's closest approach: bound them
        r_screen[arc] = bnd.base_h + bnd.reach[i[arc]] + bnd.reach[j[arc]] if not fixed else r_screen[arc]
        if not fixed:
            z_screen[arc] = bnd.base_v - mv + cfg.k_v * np.sqrt(bnd.q[i[arc]] + bnd.q[j[arc]])
    member = (d2 <= r_screen ** 2) & (vmin <= z_screen + mv)
    sel = np.flatnonzero(member)
    is_arc = np.zeros(len(member), bool)
    is_arc[arc] = True
    i, j, dz, dvz, rx, ry, vx_, vy_, r_thr, z_thr, z_full, z_level, r_min, t_min, closure, t_eval, is_arc, vmin = (
        a[sel] for a in (i, j, dz, dvz, rx, ry, vx_, vy_, r_thr, z_thr, z_full, z_level, r_min, t_min, closure,
                         t_eval, is_arc, vmin))
    arc = np.flatnonzero(is_arc)
    # 4. decision (5.14) as printed, or the same-time rule (interval intersection)
    t_in, t_out = conflict_interval(rx, ry, vx_, vy_, dz, dvz, r_thr, z_thr, t_thr, cfg.eps_mps)
    n_in, n_out = conflict_interval(rx, ry, vx_, vy_, dz, dvz, r_thr + mh, z_thr + mv, t_thr, cfg.eps_mps)
    dz_eval = dz + dvz * t_eval
    lv = _levelled_rows(tau, i, j, w1)
    if lv.size:
        t_in[lv], t_out[lv], n_in[lv], n_out[lv], dz_eval[lv] = _levelled_decision(
            cfg, rx[lv], ry[lv], vx_[lv], vy_[lv], dz[lv], vh[i[lv]], vh[j[lv]], tau[i[lv]], tau[j[lv]], r_thr[lv],
            z_thr[lv], z_full[lv], z_level[lv], t_eval[lv])
    if arc.size:                       # turning pairs: everything from the fine grid of the arcs
        res = arc_rows(cfg, st, arcs, tau, terms, i[arc], j[arc], dz[arc])
        for name, arr in (("r_min", r_min), ("t_min", t_min), ("t_eval", t_eval), ("r_thr", r_thr),
                          ("z_thr", z_thr), ("t_in", t_in), ("t_out", t_out), ("n_in", n_in), ("n_out", n_out),
                          ("dz_eval", dz_eval)):
            arr[arc] = res[name]
        # the output set proper (step 3 screened them with bounds): within R_г^пор + m_h at some t
        keep = np.ones(len(i), bool)
        keep[arc] = (res["r_min"] <= res["r_thr"] + mh) & (vmin[arc] <= res["z_screen"] + mv)
        if not keep.all():
            sel = np.flatnonzero(keep)
            i, j, dz, dvz, r_thr, z_thr, r_min, t_min, closure, t_in, t_out, n_in, n_out, dz_eval = (
                a[sel] for a in (i, j, dz, dvz, r_thr, z_thr, r_min, t_min, closure, t_in, t_out, n_in, n_out,
                                 dz_eval))
    joint = t_in <= t_out
    if cfg.mode == "corrected":
        dz_min = np.abs(dz_eval)                   # vertical separation at the horizontal CPA in [0, T]
        alert = joint
    else:
        dz_min = seed_vertical(dz, dvz, t_min)
        vertical = (np.abs(dz) <= z_thr) | (dz_min <= z_thr)
        alert = (r_min <= r_thr) & (t_min <= t_thr) & vertical
    severity = np.where(alert, np.clip(1.0 - r_min / r_thr, 0.0, 1.0), 0.0)
    return {"i": i, "j": j, "r_min_m": r_min, "t_min_s": t_min, "dz_m": dz, "dz_min_m": dz_min,
            "closure_mps": closure, "r_thr_m": r_thr, "t_thr_s": np.full(len(i), t_thr), "z_thr_m": z_thr,
            "alert": alert, "severity": severity, "t_in_s": np.where(joint, t_in, np.nan),
            "near": alert | (n_in <= n_out)}


def _turning_rows(slot: NDArray[np.int64] | None, i: NDArray[np.int64], j: NDArray[np.int64]
                  ) -> NDArray[np.int64]:
    """Pairs (positions in i, j) with a turning member (``slot`` ≥ 0, :class:`ArcTable`; None: none)."""
    if slot is None:
        return np.zeros(0, np.int64)
    return np.flatnonzero((slot[i] >= 0) | (slot[j] >= 0))


def _levelled_decision(cfg: ConflictConfig, rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j, r_thr, z_now, z_full,
                       z_level, t_eval) -> tuple[NDArray[np.float64], ...]:
    """(t_in, t_out, near t_in, near t_out, Δh(t_eval)) of pairs whose vertical prediction stops
    at a selected level (:func:`conflict_interval_levelled`). Vertical threshold per piece: now
    (``z_now``: the level-pair threshold if both are level now) on the first; on the second the
    level-pair one if the aircraft still moving is level now, else the full (5.16); on the third
    (both at their selected levels, or level) the level-pair one."""
    t_thr, mh, mv = cfg.t_thr_s, cfg.near_margin_h_m, cfg.near_margin_v_m
    moving = np.where(tau_i < tau_j, np.abs(vz_j), np.abs(vz_i))       # the later one to level off
    z2 = np.where(moving <= cfg.level_rate_mps, z_level, z_full)
    zs = (z_now, z2, z_level)
    t_in, t_out = conflict_interval_levelled(rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j, r_thr, zs, t_thr,
                                             cfg.eps_mps)
    n_in, n_out = conflict_interval_levelled(rx, ry, vx, vy, dz, vz_i, vz_j, tau_i, tau_j, r_thr + mh,
                                             tuple(z + mv for z in zs), t_thr, cfg.eps_mps)
    return t_in, t_out, n_in, n_out, clamped_dz(dz, vz_i, vz_j, tau_i, tau_j, t_eval)


class WindowRows:
    """The rows one window screens, with what every setting reads of them computed once, on
    first use: the group index (after the duplicate check), the ids, the state on height
    (:func:`state_arrays`), the covariance terms, the key columns. The STCA curves predict the
    same rows under many settings. Not thread-safe until :meth:`prepare`d."""

    def __init__(self, tracks: pl.DataFrame, frame: geo.LocalFrame | None, id_col: str = "track_id",
                 method_col: str = "method") -> None:
        self.tracks, self.frame, self.id_col, self.method_col = tracks, frame, id_col, method_col
        self._memo: dict[str, object] = {}

    def _get(self, name: str, fn: Callable[[], object]):
        if name not in self._memo:
            self._memo[name] = fn()
        return self._memo[name]

    def group(self) -> NDArray[np.int64]:
        def make():
            groups = ["run", "epoch", self.method_col]
            dup = self.tracks.select(pl.struct([*groups, self.id_col]).is_duplicated().any()).item()
            if dup:
                raise ValueError(f"tracks: duplicate {self.id_col} within a (run, epoch, {self.method_col}) group")
            return group_index(self.tracks, groups)
        return self._get("g", make)

    def state(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        return self._get("state", lambda: state_arrays(self.tracks, self.frame))

    def terms(self) -> PointTerms:
        _, _, up, from_alt = self.state()
        return self._get("terms", lambda: point_terms(self.tracks, up, from_alt))

    def ids(self) -> NDArray[np.int64]:
        return self._get("ids", lambda: self.tracks[self.id_col].cast(pl.Int64).to_numpy())

    def mode_s(self) -> pl.Series | None:
        """The rows' Mode S addresses as strings (None: the table has none)."""
        return self._get("mode_s", lambda: self.tracks["mode_s"].cast(pl.String)
                         if "mode_s" in self.tracks.columns else None)

    def keys(self) -> pl.DataFrame:
        return self._get("keys", lambda: self.tracks.select(
            pl.col("run").cast(pl.UInt32), pl.col("epoch").cast(TIME),
            pl.col(self.method_col).cast(pl.String).alias("method")))

    def prepare(self, covariance: bool) -> None:
        """Compute what the settings read (before they run in threads)."""
        self.group(), self.state(), self.ids(), self.keys(), self.mode_s()
        if covariance:
            self.terms()

    def subset(self, mask: NDArray[np.bool_]) -> "WindowRows":
        """The rows of ``mask``, with the arrays computed so far sliced, not recomputed."""
        sub = WindowRows(self.tracks.filter(pl.Series(mask)), self.frame, self.id_col, self.method_col)
        idx = np.flatnonzero(mask)
        for name, v in self._memo.items():
            if name == "state":
                sub._memo[name] = tuple(a if a is None else a[idx] for a in v)
            elif name == "terms":
                sub._memo[name] = v.take(idx)
            elif v is not None:                 # g, ids (arrays), keys (a frame), mode_s (a series)
                sub._memo[name] = v[idx]
            else:
                sub._memo[name] = None
        return sub


def _screen_key(cfg: ConflictConfig) -> tuple:
    """Settings with equal keys share one KD-tree screen (same turning rows, same tiers)."""
    return (cfg.mode, cfg.use_turn_rate, cfg.turn_rate_min_dps, cfg.block_points, cfg.bulk_quantile, cfg.v_max_mps)


#: per row, a group number (−1: none); a pair of two rows in one group is not predicted
Groups = tuple[NDArray[np.int64], ...]


def in_one_group(groups: Groups, a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Whether rows ``a`` and ``b`` (pairwise) are in one group of any of ``groups``."""
    out = np.zeros(len(a), bool)
    for g in groups:
        ga = g[a]
        out |= (ga >= 0) & (ga == g[b])
    return out


def pair_rows(rows: WindowRows, cfgs: Sequence[ConflictConfig], map_: Callable[..., Iterable] = map,
              skip: Sequence[Groups] | None = None, scored_only: bool = False,
              within: NDArray[np.int64] | None = None) -> list[pl.DataFrame]:
    """Per setting, the screened pairs of the (established, not coasting) rows with their
    geometry, thresholds and raw decision (``alert`` before confirmation), sorted by (run,
    epoch, method, id_a, id_b). The settings of a :func:`_screen_key` share one screen.
    ``skip[k]``: the pairs setting ``k`` leaves to another prediction (both rows in one group),
    dropped after the screen, before their geometry is computed. ``scored_only``: only the rows
    an alert scoring reads (:func:`_assemble`). ``within``: a label per row; only the pairs of
    two rows with one label are formed (several volumes in one call), and the rows come sorted
    by (run, epoch, method, label, id_a, id_b)."""
    tracks = rows.tracks
    if tracks.height < 2:
        return [empty_conflicts() for _ in cfgs]
    rows.prepare(any(c.threshold_mode == "covariance" for c in cfgs))
    g, ids = rows.group(), rows.ids()
    if within is not None:      # the screen separates (group, label) cells as it separates groups
        g = np.unique(g * (int(within.max()) + 1) + within, return_inverse=True)[1].ravel().astype(np.int64)
    pos, vel, _, from_alt = rows.state()
    st = np.ascontiguousarray(np.concatenate([pos, vel], axis=1).T)
    setup, taus = [], {}
    for c in cfgs:
        terms = rows.terms() if c.threshold_mode == "covariance" else None
        omega = turn_rates(tracks, c)
        key = (c.mode, c.use_selected_level, c.selected_level_tolerance_m, c.window_s[1])
        if key not in taus:        # one object per distinct level-off input: the vertical test is shared by it
            taus[key] = _track_level_off(tracks, c, pos[:, 2], vel[:, 2], from_alt)
        setup.append((terms, threshold_bounds(c, terms, len(g)), taus[key], omega,
                      None if omega is None else ArcTable(c, st, omega)))
    chunks: list[list[dict[str, NDArray]]] = [[] for _ in cfgs]
    by_screen: dict[tuple, list[int]] = {}
    for k, c in enumerate(cfgs):
        by_screen.setdefault(_screen_key(c), []).append(k)
    for ks in by_screen.values():
        sc = union_screen([screen_of(cfgs[k], setup[k][1]) for k in ks])
        pos_s, vel_s = screen_states(0.5 * (sc.t0 + sc.t1), pos, vel, setup[ks[0]][3])
        step = min(cfgs[k].chunk_pairs for k in ks)

        def evaluate(k: int, a: NDArray[np.int64], b: NDArray[np.int64], vmin: NDArray[np.float64]
                     ) -> dict[str, NDArray]:
            terms, bnd, tau, _, arcs = setup[k]
            return _evaluate_pairs(cfgs[k], st, terms, a, b, bnd, tau, arcs, vmin)
        # the pairs each setting leaves to another prediction, dropped once per distinct ``skip``
        # (usually one for every setting of the screen)
        own = [tuple(map(id, skip[k])) if skip is not None else () for k in ks]
        distinct = {key: k for key, k in zip(own, ks) if key}
        for ci, cj in block_candidates(sc, cfgs[ks[0]].block_points, g, pos_s, vel_s):
            kept = {key: ~in_one_group(skip[k], ci, cj) for key, k in distinct.items()}
            if len(set(own)) == 1 and own[0]:
                ci, cj = ci[kept[own[0]]], cj[kept[own[0]]]
                kept = {}
            for s in range(0, len(ci), step):
                a, b = ci[s:s + step], cj[s:s + step]
                swap = ids[a] > ids[b]               # order each pair so that id_a < id_b
                a, b = np.where(swap, b, a), np.where(swap, a, b)
                vmins: dict[tuple, NDArray[np.float64]] = {}
                for k in ks:
                    key = (cfgs[k].window_s, id(setup[k][2]))
                    if key not in vmins:
                        vmins[key] = _window_vmin(pos[b, 2] - pos[a, 2], vel[b, 2] - vel[a, 2], vel[:, 2], setup[k][2],
                                                  a, b, *cfgs[k].window_s)
                mins = [vmins[(cfgs[k].window_s, id(setup[k][2]))] for k in ks]

                def each(n: int, v: NDArray[np.float64]) -> dict[str, NDArray]:
                    m = kept[own[n]][s:s + step] if own[n] in kept else slice(None)
                    return evaluate(ks[n], a[m], b[m], v[m])
                for k, res in zip(ks, map_(each, range(len(ks)), mins)):
                    chunks[k].append(res)
            del ci, cj
    return list(map_(lambda k: _assemble(rows, g, cfgs[k], chunks[k], scored_only), range(len(cfgs))))


def _assemble(rows: WindowRows, g: NDArray[np.int64], cfg: ConflictConfig, chunks: list[dict[str, NDArray]],
              scored_only: bool = False) -> pl.DataFrame:
    """The conflicts rows of one setting's evaluated pairs, in (group ``g``, id_a, id_b) order;
    ``scored_only``: the raw alert rows and the first row of each group alone — what the m-of-n
    confirmation and the alert scoring read (:func:`safety.alerts.episodes.scored_conflicts`):
    the first row of a (run, epoch, method) group in any union of such tables is kept by one of
    them."""
    if not chunks or sum(len(c["i"]) for c in chunks) == 0:
        return empty_conflicts()
    ids = rows.ids()
    cols = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    i, j = cols.pop("i"), cols.pop("j")
    order = _pair_order(g, ids, i, j)
    if scored_only:
        gs = g[i[order]]
        order = order[cols["alert"][order] | np.r_[True, gs[1:] != gs[:-1]]]
    i, j = i[order], j[order]
    keys = rows.keys()[i]
    # one polars gather of all value columns (parallel over columns) instead of one numpy take each
    vals = pl.DataFrame([pl.Series("id_a", ids[i]).cast(pl.UInt64), pl.Series("id_b", ids[j]).cast(pl.UInt64)]
                        ).hstack(pl.DataFrame(cols)[order])
    out = keys.hstack(vals)
    ms = rows.mode_s() if cfg.same_identity_is_duplicate else None
    if ms is not None:
        a, b = ms.gather(i), ms.gather(j)
        dup = (a.is_not_null() & (a == b)).fill_null(False)
        out = out.with_columns(pl.col("alert") & ~pl.Series(dup))
    return out


def _track_level_off(tracks: pl.DataFrame, cfg: ConflictConfig, h: NDArray[np.float64], hdot: NDArray[np.float64],
                     from_alt: NDArray[np.bool_]) -> NDArray[np.float64] | None:
    """Per row, τ of :func:`level_off_times` from its ``selected_alt_m``, or where it has none its
    ``cleared_alt_m`` (flight data) — corrected mode with ``use_selected_level`` only, and only
    on the barometric channel (``from_alt``: both are pressure altitudes); None when no row
    levels off within the look-ahead."""
    cols = [c for c in (SELECTED_ALT_COLUMN, CLEARED_ALT_COLUMN) if c in tracks.columns]
    if cfg.mode != "corrected" or not cfg.use_selected_level or not cols:
        return None
    # the crew's selection where downlinked, else the controller's clearance (tertiary.stages.flight_data)
    sel = tracks.select(pl.coalesce([pl.col(c).cast(pl.Float64).fill_nan(None) for c in cols])).to_series()
    sel = sel.fill_null(np.nan).to_numpy()
    tau = level_off_times(h, hdot, sel, from_alt, cfg.selected_level_tolerance_m)
    return tau if np.any(tau < cfg.window_s[1]) else None


def _pair_order(g: NDArray[np.int64], ids: NDArray[np.int64], i: NDArray[np.int64], j: NDArray[np.int64]
                ) -> NDArray[np.int64]:
    """Permutation sorting pairs (i, j) by (group, id_i, id_j) — g is the dense rank of (run, epoch,
    method), so this is the (run, epoch, method, id_a, id_b) order: one stable argsort of a packed
    int64 key (ids as dense ranks), np.lexsort only when the packed key could overflow."""
    uniq, rank = np.unique(ids, return_inverse=True)
    rank = rank.ravel().astype(np.int64)
    m, n_groups = len(uniq), int(g.max()) + 1
    if n_groups * m * m < 1 << 62:
        return np.argsort((g[i] * m + rank[i]) * m + rank[j], kind="stable")
    return np.lexsort((ids[j], ids[i], g[i]))
