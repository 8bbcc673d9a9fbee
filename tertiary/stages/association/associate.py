"""Association: which aligned reports are the same aircraft (monograph §1.4).

Within each connected component of the gate graph (hypothesis H1 "same target" holds along
every gated edge, H2 "different targets" elsewhere):

1. all reports from one radar → one target per report (a radar never reports an aircraft twice);
2. at most one report per radar → one target;
3. equal counts m from the radars → m targets, paired by the minimum sum of squared distances;
4. unequal counts → the radar with most reports sets the number of targets and the other
   radars' reports are assigned to its reports.

Rules 3–4 are solved with ``scipy.optimize.linear_sum_assignment`` per ambiguous component
(squared distance, or Mahalanobis d² with ``cost="mahalanobis"``); ungated assignments are
refused and the leftovers are grouped again by the same rules. Components obeying rules 1–2 —
nearly all of them — are grouped with array operations, no Python loop.

With ``assignment="joint"`` a component holding reports of three or more radars is solved as
one multi-dimensional (S-D) assignment instead of radar by radar against the reference: the
partition of its reports into groups (at most one report per radar, every pair in a group
gated) that minimises, lexicographically, the number of groups (rule 4: as many targets as
the fullest source, fewer merges only where the gate forbids them) and then the sum of the
pairwise costs inside the groups ("the minimum sum of squared distances over all
combinations", §1.4 rule 3). It is an exact set-partitioning integer programme over the
component's feasible tuples (HiGHS through ``scipy.optimize.milp``); pairwise-to-reference
ignores the costs between non-reference reports and can miss this minimum.

Fine identification (§1.4 "точное отождествление"): beside Mode S (a different address
forbids a pair, :mod:`tertiary.stages.association.gating`), the Mode 3/A code and the callsign, when both
reports carry one and they differ, either forbid the pair (``"forbid"``) or add
``identity_penalty`` gate-sizes of cost to it (``"penalise"``: codes change and garble, so a
conflict is evidence, not proof). They need the aligned columns ``mode_3a``/``callsign``
(``AlignConfig.identity``).

System target ids are carried across epochs: a group inherits the id its members' local tracks
had at their previous epoch (majority vote; a contested id goes to the larger group), so a
target keeps its number while its radars keep theirs (vote ties go to the id carried by the
group's lowest-numbered radar, which resolves a radar swapping its own track numbers). A group
that carries a Mode S address and another id than the one that address last had (or none) takes
the address's id, when that was at most ``address_gap_s`` ago and no group of that address holds
it at this epoch: an aircraft handed from one radar's coverage to another's, whose local tracks
were all dropped and restarted, or whose new local track formed a group of its own beside the
old one until the old one ended, stays one system target (the address is unique to the
airframe); and a group without that address whose local tracks carried the id over from the
aircraft (a local track swapped to another aircraft) gives it back and becomes a new target.
``reassignments`` counts local tracks whose system target changed.

Windowed runs: :func:`associate_step` processes the aligned rows of one window of
epochs, carrying an :class:`AssociateState` (each local track's last system target id and
epoch by (run, radar_id, local_track_id), absolute µs; the next fresh id). Gating and
assignment never span epochs, so that is all a window needs from earlier ones; consecutive
windows give the whole-run table and :class:`AssociationStats` add up to the whole run's.
:func:`associate` is one step over the whole run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Iterable, Literal

import numpy as np
import polars as pl
from numpy.typing import NDArray
from scipy.optimize import Bounds, LinearConstraint, linear_sum_assignment, milp
from scipy.sparse import csr_matrix
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from tertiary.core.distributions import chi2_ppf
from tertiary.core.errors import OptionError
from tertiary.core.stage import T_MIN_US, Window, check_window
from tertiary.stages.association.gating import GatingConfig, Pairs, candidate_pairs, group_index, superseded_rows

BIG = 1e18


@dataclass(frozen=True)
class AssociationConfig:
    """* ``cost``: assignment cost of rules 3–4.
    * ``carry_gap_s``: a local track absent from the aligned picture for longer than this is
      a new track when its number comes back (radars reuse the numbers of deleted tracks):
      it does not inherit the system target id it had before. 30 s bridges two missed scans
      of a 12 s radar (silence 36 s, of which 18 s are covered by the 1.5-scan extrapolation).
    * ``address_gap_s``: how long a Mode S address keeps its system target id through a
      silence. The address is the airframe's, never reused by another aircraft, so it bridges
      what a local track number cannot: an aircraft that leaves every radar's coverage (low,
      or between en-route radars) and comes back under new local tracks a minute later is the
      same system target, not a second one. Five minutes is well below the shortest turnaround
      of an airframe between two flights.
    * ``assignment``: ``"pairwise"`` (each radar to the reference radar) or ``"joint"`` (the
      exact multi-dimensional minimum for components with ≥ 3 radars; module docstring). A
      component with more than ``max_tuples`` feasible tuples falls back to pairwise.
    * ``mode_3a``, ``callsign``: fine identification, ``"off"``, ``"forbid"`` or
      ``"penalise"`` (module docstring); the penalty is ``identity_penalty`` × the squared
      horizontal gate (cost ``sqdist``) or × χ²₃(gate_prob) (cost ``mahalanobis``) per
      conflicting attribute."""

    cost: Literal["sqdist", "mahalanobis"] = "sqdist"
    gating: GatingConfig = field(default_factory=GatingConfig)
    carry_gap_s: float = 30.0
    address_gap_s: float = 300.0
    assignment: Literal["pairwise", "joint"] = "pairwise"
    max_tuples: int = 20_000
    mode_3a: Literal["off", "forbid", "penalise"] = "off"
    callsign: Literal["off", "forbid", "penalise"] = "off"
    identity_penalty: float = 1.0


@dataclass
class AssociationStats:
    """Counts of one call. Additive: every count is a sum over epochs (gating, components and
    assignments never span epochs; ``targets`` counts the system target ids created), so the
    stats of consecutive windows add up (``+`` or :meth:`merge`) to those of the whole run."""

    reports: int = 0
    pairs: int = 0
    components: int = 0
    ambiguous_components: int = 0
    targets: int = 0                # system target ids created (whole run: distinct target ids)
    reassignments: int = 0
    joint_components: int = 0       # components solved by the joint (S-D) assignment
    joint_fallbacks: int = 0        # of those, too many tuples: solved pairwise instead
    identity_conflicts: int = 0     # gated pairs whose Mode 3/A or callsign differ

    def __add__(self, other: "AssociationStats") -> "AssociationStats":
        if not isinstance(other, AssociationStats):
            return NotImplemented
        return AssociationStats(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})

    @classmethod
    def merge(cls, parts: Iterable["AssociationStats"]) -> "AssociationStats":
        """The sum of the stats of consecutive windows."""
        out = cls()
        for p in parts:
            out = out + p
        return out


_TRACK_KEY = ("run", "radar_id", "local_track_id")
_TRACKS_SCHEMA = {"run": pl.Int64, "radar_id": pl.Int64, "local_track_id": pl.Int64,
                  "target_id": pl.Int64, "seen_us": pl.Int64}
_ADDRESS_KEY = ("run", "mode_s")
_ADDRESSES_SCHEMA = {"run": pl.Int64, "mode_s": pl.String, "target_id": pl.Int64, "seen_us": pl.Int64}


@dataclass(frozen=True)
class AssociateState:
    """What target-id continuity needs from earlier windows.

    * ``tracks``: one row per local track (run, radar_id, local_track_id) that can still hand
      its system target id on: ``target_id`` at its last epoch and ``seen_us`` = that epoch
      (absolute µs). Tracks silent for more than ``carry_gap_s`` before the latest epoch seen
      are dropped (they could never vote again), so the state stays bounded.
    * ``t_us``: end of the last window processed (:data:`~tertiary.core.stage.T_MIN_US` before the first).
    * ``run_next``: (run, next fresh target id of that run) — target ids are numbered per
      Monte-Carlo run, like track and cluster ids, so a run processed alone (a Dask partition)
      gets the ids it gets in the whole job.
    * ``addresses``: one row per Mode S address (run, mode_s) seen within ``address_gap_s``: the
      system target id it had at its last epoch and that epoch (``seen_us``).
    """

    tracks: pl.DataFrame
    t_us: int = T_MIN_US
    run_next: tuple[tuple[int, int], ...] = ()
    addresses: pl.DataFrame = field(default_factory=lambda: pl.DataFrame(schema=_ADDRESSES_SCHEMA))

    def live_targets(self) -> pl.DataFrame:
        """(run, target_id) that may still be associated: a target id is only ever continued from
        a local track of ``tracks`` or a Mode S address of ``addresses`` (:func:`carry_step`),
        so no other id ever returns."""
        return pl.concat([self.tracks.select("run", "target_id"),
                          self.addresses.select("run", "target_id")]).unique()

    @property
    def next_id(self) -> int:
        """How many system target ids were created so far (all runs)."""
        return sum(n for _, n in self.run_next)


def init_associate_state() -> AssociateState:
    """The state before the first window: no local track seen, target ids from 0."""
    return AssociateState(pl.DataFrame(schema=_TRACKS_SCHEMA))


def _components(n: int, pairs: Pairs) -> NDArray[np.int64]:
    graph = coo_matrix((np.ones(len(pairs)), (pairs.a, pairs.b)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def feasible_tuples(radar: NDArray, gated: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Every non-empty group of a component's reports with at most one report per radar and
    every pair gated: (T, n_radars) positions, −1 where a radar is absent. Built radar by
    radar, each step vectorised over the tuples so far."""
    tup = np.full((1, 0), -1, np.int64)
    for r in np.unique(radar):
        mine = np.flatnonzero(radar == r)
        # compat[t, j]: report mine[j] is gated with every member of tuple t
        member = tup >= 0
        g = gated[mine[:, None, None], np.where(member, tup, 0)[None, :, :]]      # (m, T, k)
        compat = np.all(g | ~member[None, :, :], axis=2).T                       # (T, m)
        ti, jj = np.nonzero(compat)
        grown = np.column_stack([tup[ti], mine[jj]])
        tup = np.vstack([np.column_stack([tup, np.full(len(tup), -1)]), grown])
    return tup[np.any(tup >= 0, axis=1)]


def tuple_costs(tup: NDArray[np.int64], cost: NDArray[np.float64]) -> NDArray[np.float64]:
    """Σ of the pairwise costs inside each tuple (loop over radar pairs, vectorised over tuples)."""
    out = np.zeros(len(tup))
    for i in range(tup.shape[1]):
        for j in range(i + 1, tup.shape[1]):
            both = (tup[:, i] >= 0) & (tup[:, j] >= 0)
            out[both] += cost[tup[both, i], tup[both, j]]
    return out


def solve_joint(radar: NDArray, cost: NDArray[np.float64], gated: NDArray[np.bool_],
                max_tuples: int = 20_000) -> list[NDArray[np.int64]] | None:
    """The exact joint assignment of one component (module docstring): minimise
    Σ_groups (M + Σ pair costs) with M = 1 + Σ of all gated costs, so fewer groups always win,
    as a set-partitioning integer programme. Returns groups of positions, or None beyond
    ``max_tuples`` feasible tuples."""
    tup = feasible_tuples(radar, gated)
    if len(tup) > max_tuples:
        return None
    n = len(radar)
    scale = max(float(np.sum(np.where(gated, cost, 0.0))) / 2.0, 1e-300)
    c = 2.0 + tuple_costs(tup, cost) / scale          # costs normalised to ≤ 1 in total: M = 2 > any sum
    ti, slot = np.nonzero(tup >= 0)
    a = csr_matrix((np.ones(len(ti)), (tup[ti, slot], ti)), shape=(n, len(tup)))
    res = milp(c, constraints=LinearConstraint(a, 1.0, 1.0), integrality=np.ones(len(tup)),
               bounds=Bounds(0.0, 1.0), options={"mip_rel_gap": 0.0})
    if res.x is None:                                  # singletons are always feasible
        raise RuntimeError(f"joint assignment: solver failed ({res.message})")
    chosen = tup[res.x > 0.5]
    return [np.sort(t[t >= 0]) for t in chosen]


def _solve_component(rows: NDArray[np.int64], radar: NDArray, cost: NDArray[np.float64],
                     gated: NDArray[np.bool_], joint: tuple[int, AssociationStats] | None = None
                     ) -> list[NDArray[np.int64]]:
    """Rules 3–4 on one component. ``cost``/``gated`` are dense over the component's rows.
    ``joint`` = (max_tuples, stats): solve components of ≥ 3 radars jointly.
    Returns groups of positions into ``rows``."""
    pos = np.arange(len(rows))
    counts = {r: np.count_nonzero(radar == r) for r in np.unique(radar)}
    if max(counts.values()) <= 1:
        return [pos]
    if joint is not None and len(counts) >= 3:
        joint[1].joint_components += 1
        groups = solve_joint(radar, cost, gated, joint[0])
        if groups is not None:
            return groups
        joint[1].joint_fallbacks += 1
    ref_radar = min(counts, key=lambda r: (-counts[r], r))
    ref = pos[radar == ref_radar]
    groups = [[i] for i in ref]
    leftover: list[int] = []
    for r in sorted(counts):
        if r == ref_radar:
            continue
        mine = pos[radar == r]
        c = np.where(gated[np.ix_(mine, ref)], cost[np.ix_(mine, ref)], BIG)
        ia, ib = linear_sum_assignment(c)
        ok = c[ia, ib] < BIG
        for i, j in zip(ia[ok], ib[ok]):
            groups[j].append(mine[i])
        leftover.extend(np.setdiff1d(mine, mine[ia[ok]]))
    out = [np.array(g) for g in groups]
    if leftover:
        left = np.array(sorted(leftover))
        sub = gated[np.ix_(left, left)]
        n_sub, lab = connected_components(coo_matrix(sub), directed=False)
        for k in range(n_sub):
            part = left[lab == k]
            out.extend(part[g] for g in _solve_component(part, radar[part], cost[np.ix_(part, part)],
                                                         gated[np.ix_(part, part)], joint))
    return out


def group_reports(aligned: pl.DataFrame, cfg: AssociationConfig = AssociationConfig(),
                  stale: NDArray[np.bool_] | None = None) -> tuple[NDArray[np.int64], AssociationStats]:
    """Group label per aligned row (same label = same aircraft at that epoch); ``stale``: the
    rows' :func:`~.gating.superseded_rows`, when the caller has them."""
    n = aligned.height
    stats = AssociationStats(reports=n)
    if n == 0:
        return np.zeros(0, np.int64), stats
    groups = group_index(aligned)
    pairs = candidate_pairs(aligned, cfg.gating, groups, stale)
    pairs = fine_identification(aligned, pairs, cfg, stats)
    stats.pairs = len(pairs)
    comp = _components(n, pairs)
    stats.components = int(comp.max()) + 1
    radar = aligned["radar_id"].to_numpy().astype(np.int64)
    # max reports of one radar inside each component
    per = np.unique(comp * (radar.max() + 1) + radar, return_counts=True)
    worst = np.zeros(stats.components, np.int64)
    np.maximum.at(worst, per[0] // (radar.max() + 1), per[1])
    ambiguous = np.flatnonzero(worst > 1)
    stats.ambiguous_components = len(ambiguous)
    label = comp.copy()
    if len(ambiguous):
        label = _split_ambiguous(aligned, pairs, comp, ambiguous, radar, label, cfg, stats)
    return label, stats


def _identity_codes(col: pl.Series, callsign: bool) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """(known, integer code) per row of a Mode 3/A or callsign column (callsigns compared
    upper-case without blanks; empty = unknown)."""
    s = col.cast(pl.String)
    s = s.str.strip_chars().str.to_uppercase().str.replace_all(" ", "") if callsign else s.str.strip_chars()
    s = s.replace("", None)
    return s.is_not_null().to_numpy(), s.cast(pl.Categorical).to_physical().fill_null(0).to_numpy().astype(np.int64)


def fine_identification(aligned: pl.DataFrame, pairs: Pairs, cfg: AssociationConfig,
                        stats: AssociationStats | None = None) -> Pairs:
    """Pairs after the Mode 3/A and callsign checks (module docstring): forbidden pairs are
    dropped, penalised ones cost more (both ``sqdist`` and ``d2``)."""
    todo = [(name, how) for name, how in (("mode_3a", cfg.mode_3a), ("callsign", cfg.callsign)) if how != "off"]
    if not todo or len(pairs) == 0:
        return pairs
    missing = [name for name, _ in todo if name not in aligned.columns]
    if missing:
        raise OptionError(f"fine identification needs aligned column(s) {', '.join(missing)} "
                          "(set AlignConfig.identity)", option="association." + missing[0])
    drop = np.zeros(len(pairs), bool)
    n_pen = np.zeros(len(pairs))
    conflict_any = np.zeros(len(pairs), bool)
    for name, how in todo:
        known, code = _identity_codes(aligned[name], callsign=name == "callsign")
        conflict = known[pairs.a] & known[pairs.b] & (code[pairs.a] != code[pairs.b])
        conflict_any |= conflict
        if how == "forbid":
            drop |= conflict
        elif how == "penalise":
            n_pen += conflict
        else:
            raise OptionError(f"choose off, forbid or penalise, got {how!r}", option=f"association.{name}")
    if stats is not None:
        stats.identity_conflicts = int(np.count_nonzero(conflict_any))
    pen_sq = cfg.identity_penalty * cfg.gating.pos_tol_m ** 2
    pen_d2 = cfg.identity_penalty * chi2_ppf(cfg.gating.gate_prob, 3)
    keep = ~drop
    return Pairs(pairs.a[keep], pairs.b[keep], (pairs.sqdist + n_pen * pen_sq)[keep],
                 (pairs.d2 + n_pen * pen_d2)[keep])


def _split_ambiguous(aligned, pairs, comp, ambiguous, radar, label, cfg, stats=None) -> NDArray[np.int64]:
    """Rules 3–4 on each ambiguous component (loop over those components only)."""
    is_amb = np.isin(comp, ambiguous)
    members = np.flatnonzero(is_amb)
    order = members[np.argsort(comp[members], kind="stable")]
    bounds = np.flatnonzero(np.diff(comp[order])) + 1
    edge_cost = pairs.d2 if cfg.cost == "mahalanobis" else pairs.sqdist
    amb_edge = np.flatnonzero(is_amb[pairs.a])
    amb_edge = amb_edge[np.argsort(comp[pairs.a[amb_edge]], kind="stable")]
    ea, eb, ec = pairs.a[amb_edge], pairs.b[amb_edge], edge_cost[amb_edge]
    edge_bounds = np.searchsorted(comp[ea], comp[order[np.append(0, bounds)]])
    edge_bounds = np.append(edge_bounds, len(ea))
    next_label = int(label.max()) + 1
    local = np.full(len(label), -1, np.int64)
    for k, rows in enumerate(np.split(order, bounds)):
        local[rows] = np.arange(len(rows))
        sel = slice(edge_bounds[k], edge_bounds[k + 1])
        m = len(rows)
        gated = np.zeros((m, m), bool)
        cost = np.zeros((m, m))
        ia, ib = local[ea[sel]], local[eb[sel]]
        gated[ia, ib] = gated[ib, ia] = True
        cost[ia, ib] = cost[ib, ia] = ec[sel]
        joint = (cfg.max_tuples, stats or AssociationStats()) if cfg.assignment == "joint" else None
        for grp in _solve_component(rows, radar[rows], cost, gated, joint):
            label[rows[grp]] = next_label
            next_label += 1
    return label


def _reference_cost(aligned: pl.DataFrame, label: NDArray[np.int64], cfg: AssociationConfig) -> NDArray[np.float64]:
    """Cost of each row against its group's reference report (lowest radar id; itself = 0)."""
    n = aligned.height
    radar = aligned["radar_id"].to_numpy()
    order = np.lexsort((radar, label))
    first = np.ones(n, bool)
    first[1:] = label[order][1:] != label[order][:-1]
    ref_of = np.empty(n, np.int64)
    ref_of[order] = order[np.flatnonzero(first)][np.cumsum(first) - 1]
    pos = aligned.select("x_m", "y_m", "z_m").to_numpy()
    d = pos - pos[ref_of]
    if cfg.cost == "sqdist":
        return np.sum(d * d, axis=1)
    cov = aligned["cov"].to_numpy()[:, [0, 1, 2, 6, 7, 8, 12, 13, 14]].reshape(n, 3, 3)
    s = cov + cov[ref_of]
    return np.where(ref_of == np.arange(n), 0.0, np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0]))


def carry_target_ids(aligned: pl.DataFrame, label: NDArray[np.int64], carry_gap_s: float = math.inf
                     ) -> tuple[NDArray[np.int64], int]:
    """Stable system target ids across epochs; returns (target id per row, reassignments).

    A local track votes for the id it had at its last epoch unless that was more than
    ``carry_gap_s`` before (a reused track number). Whole-run form of :func:`carry_step`.
    """
    target, reassigned, _ = carry_step(init_associate_state(), aligned, label, carry_gap_s)
    return target, reassigned


def _address_codes(state: AssociateState, aligned: pl.DataFrame
                   ) -> tuple[NDArray[np.int64], NDArray[np.int64], pl.DataFrame]:
    """Dense codes of (run, mode_s) over the state's addresses and the rows, as
    :func:`_track_codes`; a row without an address gets −1."""
    rows = (aligned.select(pl.col("run").cast(pl.Int64), pl.col("mode_s").cast(pl.String))
            if "mode_s" in aligned.columns else
            aligned.select(pl.col("run").cast(pl.Int64), pl.lit(None, pl.String).alias("mode_s")))
    keys = pl.concat([state.addresses.select(_ADDRESS_KEY), rows])
    known = keys["mode_s"].is_not_null().to_numpy()
    named = keys.filter(pl.Series(known))
    kc = named.select(pl.struct(_ADDRESS_KEY).rank("dense").cast(pl.Int64) - 1).to_series().to_numpy()
    code = np.full(keys.height, -1, np.int64)
    code[known] = kc
    _, first = np.unique(kc, return_index=True)
    ns = state.addresses.height
    return code[:ns], code[ns:], named[first]


def _by_address(assigned: NDArray[np.int64], g_addr: NDArray[np.int64], g_run: NDArray[np.int64],
                a_last: NDArray[np.int64], a_seen: NDArray[np.int64], t_us: int, gap_us: float
                ) -> NDArray[np.int64]:
    """``assigned`` (−1: no carried id) with every group that carries a Mode S address given the
    id that address had last (at most ``gap_us`` before ``t_us``) when its own differs: a fresh
    group, or the younger id of a split whose older part has ended. The address owns its id: a
    group holding it that lacks that address (none, or another: its local tracks swapped to
    another aircraft) gives it up (−1) — a group of the address itself keeps it. Of two groups
    of one address the first takes it."""
    has = g_addr >= 0
    if not has.any():
        return assigned
    at = np.where(has, g_addr, 0)
    want = np.where(has, a_last[at], -1)
    ok = has & (want >= 0) & (want != assigned) & (t_us - a_seen[at] <= gap_us)
    if not ok.any():
        return assigned
    hold = np.flatnonzero(assigned >= 0)
    hq = g_run[hold] * _RUN_Q + assigned[hold]
    o = np.argsort(hq)
    hold, hq = hold[o], hq[o]
    g = np.flatnonzero(ok)
    q = g_run[g] * _RUN_Q + want[g]
    holder = np.full(len(g), -1, np.int64)               # the group holding the wanted id now
    if len(hq):
        k = np.minimum(np.searchsorted(hq, q), len(hq) - 1)
        hit = hq[k] == q
        holder[hit] = hold[k[hit]]
    # a holder of the address itself keeps the id (a split of one aircraft)
    free = (holder < 0) | (g_addr[np.maximum(holder, 0)] != g_addr[g])
    g, q, holder = g[free], q[free], holder[free]
    _, first = np.unique(q, return_index=True)
    g, holder = g[first], holder[first]
    out = assigned.copy()
    out[holder[holder >= 0]] = -1
    out[g] = want[g]
    return out


def _track_codes(state: AssociateState, aligned: pl.DataFrame
                 ) -> tuple[NDArray[np.int64], NDArray[np.int64], pl.DataFrame]:
    """Dense codes of the natural key (run, radar_id, local_track_id) over the state's tracks
    and the rows (codes are local to this call): (code per state track, code per row, key
    frame with one row per code)."""
    keys = pl.concat([state.tracks.select(_TRACK_KEY),
                      aligned.select([pl.col(c).cast(pl.Int64) for c in _TRACK_KEY])])
    code = keys.select(pl.struct(_TRACK_KEY).rank("dense").cast(pl.Int64) - 1).to_series().to_numpy()
    _, first = np.unique(code, return_index=True)
    ns = state.tracks.height
    return code[:ns], code[ns:], keys[first]


def carry_step(state: AssociateState, aligned: pl.DataFrame, label: NDArray[np.int64],
               carry_gap_s: float = math.inf, address_gap_s: float | None = None,
               stale: NDArray[np.bool_] | None = None) -> tuple[NDArray[np.int64], int, AssociateState]:
    """Target ids of one window's rows, continuing ``state``: (target id per row, reassignments,
    new state; its ``t_us`` is left to the caller). A local track hands its id on through a
    silence of at most ``carry_gap_s``, a Mode S address through one of at most
    ``address_gap_s`` (None: ``carry_gap_s``). ``stale``: the rows' :func:`~.gating.superseded_rows`
    (None: found here).

    Sequential over epochs (a loop over the window's epochs, vectorised across runs, groups
    and reports within each epoch). Fresh ids within an epoch follow the order of ``label``.
    """
    n = aligned.height
    if n == 0:
        return np.zeros(0, np.int64), 0, state
    code_state, keys, key_frame = _track_codes(state, aligned)
    a_state, addr, a_frame = _address_codes(state, aligned)
    # a radar's superseded row (its newer report of the address is at this epoch too) counts as
    # one without the address: it cannot keep the address's id from the group of the newer
    # report, which takes it (:func:`~.gating.superseded_rows`, :func:`_by_address`)
    addr = np.where(superseded_rows(aligned) if stale is None else stale, -1, addr)
    epoch = aligned["epoch"].dt.epoch("us").to_numpy()
    radar = aligned["radar_id"].to_numpy().astype(np.int64)
    runs = aligned["run"].to_numpy().astype(np.int64)
    nxt = dict(state.run_next)
    order = np.argsort(epoch, kind="stable")
    bounds = np.flatnonzero(np.diff(epoch[order])) + 1
    last = np.full(key_frame.height, -1, np.int64)    # system target id at each local track's last row
    seen = np.zeros(len(last), np.int64)                # epoch (µs) of that row
    last[code_state] = state.tracks["target_id"].to_numpy()
    seen[code_state] = state.tracks["seen_us"].to_numpy()
    a_last = np.full(a_frame.height, -1, np.int64)     # system target id at each address's last row
    a_seen = np.zeros(len(a_last), np.int64)
    a_last[a_state] = state.addresses["target_id"].to_numpy()
    a_seen[a_state] = state.addresses["seen_us"].to_numpy()
    gap_us = carry_gap_s * 1e6
    a_gap_us = (carry_gap_s if address_gap_s is None else address_gap_s) * 1e6
    target = np.empty(n, np.int64)
    reassigned = 0
    for rows in np.split(order, bounds):
        g = label[rows]
        ug, first, gi = np.unique(g, return_index=True, return_inverse=True)
        kr = keys[rows]
        cand = np.where(epoch[rows] - seen[kr] <= gap_us, last[kr], -1)
        assigned = np.full(len(ug), -1, np.int64)
        ok = cand >= 0
        if ok.any():
            # ids are numbered per run: two runs' groups may hold the same id without a conflict,
            # so votes are on (run, id)
            q = runs[rows][ok] * _RUN_Q + cand[ok]
            assigned = _vote(gi[ok], q, radar[rows][ok], assigned)
            assigned = np.where(assigned >= 0, assigned % _RUN_Q, -1)
        g_addr = np.full(len(ug), -1, np.int64)          # the gate never joins two addresses
        np.maximum.at(g_addr, gi, addr[rows])
        g_run = runs[rows][first]
        assigned = _by_address(assigned, g_addr, g_run, a_last, a_seen, int(epoch[rows[0]]), a_gap_us)
        fresh = assigned < 0
        if fresh.any():
            assigned[fresh] = _fresh_ids(g_run[fresh], nxt)
        # an address follows its group; of two groups of one address, the one holding its id
        ga = np.flatnonzero(g_addr >= 0)
        ga = ga[np.argsort(assigned[ga] == a_last[g_addr[ga]], kind="stable")]
        a_last[g_addr[ga]] = assigned[ga]
        a_seen[g_addr[ga]] = epoch[rows[0]]
        new = assigned[gi]
        reassigned += int(np.count_nonzero(ok & (cand != new)))
        last[kr] = new
        seen[kr] = epoch[rows]
        target[rows] = new
    # a track silent for more than the gap before the latest epoch can never vote again
    live = (last >= 0) & (seen >= float(epoch.max()) - gap_us)
    tracks = key_frame.with_columns(pl.Series("target_id", last), pl.Series("seen_us", seen)).filter(pl.Series(live))
    a_live = (a_last >= 0) & (a_seen >= float(epoch.max()) - a_gap_us)
    addresses = a_frame.with_columns(pl.Series("target_id", a_last), pl.Series("seen_us", a_seen)
                                     ).filter(pl.Series(a_live)).cast(_ADDRESSES_SCHEMA)
    return target, reassigned, AssociateState(tracks, state.t_us, tuple(sorted(nxt.items())), addresses)


#: (run, target id) packed into one int64 for the vote (ids of a run stay below 2^40)
_RUN_Q = np.int64(1) << 40


def _fresh_ids(group_run: NDArray[np.int64], nxt: dict[int, int]) -> NDArray[np.int64]:
    """Fresh target ids of new groups (in group order), numbered per run from ``nxt`` (updated)."""
    ur, inv, cnt = np.unique(group_run, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    rank = np.empty(len(inv), np.int64)
    rank[order] = np.arange(len(inv)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    base = np.array([nxt.get(int(r), 0) for r in ur], np.int64)
    for r, c in zip(ur.tolist(), cnt.tolist()):
        nxt[r] = nxt.get(r, 0) + c
    return base[inv] + rank


def _vote(vg: NDArray[np.int64], vc: NDArray[np.int64], vr: NDArray[np.int64],
          assigned: NDArray[np.int64]) -> NDArray[np.int64]:
    """Carried id per group from the votes (group, candidate id, radar): most votes, then the id
    its lowest radar carries; a contested id goes to the group with most votes (then the
    lowest radar). Groups without a winning id keep −1."""
    o = np.lexsort((vr, vc, vg))
    vg, vc, vr = vg[o], vc[o], vr[o]
    start = np.ones(len(vg), bool)
    start[1:] = (vg[1:] != vg[:-1]) | (vc[1:] != vc[:-1])
    first = np.flatnonzero(start)
    cg, cc, cr = vg[first], vc[first], vr[first]
    cnt = np.diff(np.append(first, len(vg)))
    o = np.lexsort((cc, cr, -cnt, cg))
    cg, cc, cr, cnt = cg[o], cc[o], cr[o], cnt[o]
    best = np.ones(len(cg), bool)
    best[1:] = cg[1:] != cg[:-1]
    bg, bc, bn, br = cg[best], cc[best], cnt[best], cr[best]
    o = np.lexsort((bg, br, -bn, bc))
    win = np.ones(len(o), bool)
    win[1:] = bc[o][1:] != bc[o][:-1]
    out = assigned.copy()
    out[bg[o][win]] = bc[o][win]
    return out


def associate_step(state: AssociateState, aligned_window: pl.DataFrame, t0_us: int, t1_us: int,
                   cfg: AssociationConfig = AssociationConfig()
                   ) -> tuple[tuple[pl.DataFrame, AssociationStats], AssociateState]:
    """One window of :func:`associate`: ((associations, stats), new state).

    ``aligned_window``: the aligned rows with epoch in [t0_us, t1_us) (int64 µs since the Unix
    epoch), in the order :func:`tertiary.stages.align.expand` gives them ((run, epoch, radar_id,
    local_track_id)); no margin is needed: gating and assignment never span epochs, and the
    only memory of earlier epochs (target-id continuity) is in ``state``. ``stats`` are this
    window's counts (:class:`AssociationStats` add up over windows). Pure: ``state`` is not
    modified.
    """
    check_window(aligned_window, Window(0, t0_us, t1_us), after_us=state.t_us, table="aligned")
    stale = superseded_rows(aligned_window)         # the gate's and the id carry's, found once
    label, stats = group_reports(aligned_window, cfg, stale)
    target, stats.reassignments, new = carry_step(state, aligned_window, label, cfg.carry_gap_s, cfg.address_gap_s,
                                                  stale)
    stats.targets = new.next_id - state.next_id
    cost = _reference_cost(aligned_window, label, cfg) if aligned_window.height else np.zeros(0)
    out = aligned_window.select("run", "epoch", "radar_id", "local_track_id", "report_id").with_columns(
        pl.Series("target_id", target.astype(np.uint64)), pl.Series("cost", cost))
    return (out, stats), AssociateState(new.tracks, t1_us, new.run_next, new.addresses)


def associate(aligned: pl.DataFrame, cfg: AssociationConfig = AssociationConfig()
              ) -> tuple[pl.DataFrame, AssociationStats]:
    """The ``associations`` table (run, epoch, radar_id, local_track_id, report_id,
    target_id, cost) for every aligned row, and run statistics: one
    :func:`associate_step` over the whole run."""
    w = Window.unbounded()
    (out, stats), _ = associate_step(init_associate_state(), aligned, w.t0_us, w.t1_us, cfg)
    return out, stats
