"""A radar's own plot-to-track association: the track numbers it sends with its plots.

Each simulated radar numbers its plots the way a radar tracker does, from what it measured
(plot positions, times and transponder codes, never the truth), so its local tracks err as a
real radar's do: they swap at crossings, break after missed detections, start duplicates,
capture clutter, and their numbers are reused.

Model (per radar, per Monte-Carlo run — a *partition*): a 2-D constant-velocity Kalman filter
per track in the radar's ground plane, state (x, y, ẋ, ẏ), white-noise acceleration of
spectral density q (m²/s³):

    F(τ) = [[I, τI], [0, I]],   Q(τ) = q [[τ³/3 I, τ²/2 I], [τ²/2 I, τ I]]               (1)

A plot (r, β, ε) is measured at ρ = r cos ε, z = ρ (sin β, cos β) with covariance

    R = G diag(σ_ρ², (ρ σ_β)²) Gᵀ,  σ_ρ² = cos²ε σ_r² + (r sin ε σ_ε)²,  G the rotation by β  (2)

Gate: a track predicted to the plot's time with S = P_pos + R passes when ν S⁻¹ ν ≤ γ (2-dof
χ²); the Mode S addresses of plot and track must not differ (``mode_s_gate``); a Mode 3/A code
mismatch costs ``code_mismatch_cost``. Pair cost = ν S⁻¹ ν + ln det S (the negative
log-likelihood, so a wide tentative gate does not win plots from a tight confirmed track).
Assignment: greedy global nearest neighbour (pairs taken in order of cost, each track and plot
once), computed by iterating "accept every mutually best pair" — each iteration vectorised,
a handful per scan. Track management: a plot left over starts a tentative track (one-point
initiation: velocity 0 ± ``v0_sigma_mps``), confirmed after ``confirm_hits`` plots; a
tentative track is deleted after ``tentative_misses`` consecutive misses, a confirmed one when
its silence exceeds the radar's ``track_drop_scans`` scans; a new track takes the lowest track
number free in its partition (a deleted track's number is free again ``reuse_after_scans``
scans later: numbers are reused).

State is explicit (:class:`RadarTrackState`, arrays over the live tracks of every partition)
and :func:`step` maps (state, one scan's plots) to (state, track number per plot); the loop
over scans is outside (:func:`run_scans`), vectorised across tracks, radars and runs. The same
loop compiled (:mod:`tertiary.simulate.radar_scan_kernel`, numba) is what :func:`run_scans`
runs once it is cached or when a job is large enough to repay compiling it
(:func:`compiled_pays`); :func:`step` stays the reference it is tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tertiary.simulate.radar_scan_kernel import is_ready, run_scans_compiled
from tertiary.simulate.radar_track_state import STATE_VERSION, TRACK_FIELDS, RadarTrackState, init_state

#: partitions are laid side by side this far apart (m) in one KD-tree
_PART_OFFSET = 1.0e8


@dataclass(frozen=True)
class RadarTrackerConfig:
    """The radar trackers' association parameters (shared by every simulated radar).

    * ``ideal``: number the plots from the truth instead (one number per aircraft and stretch
      of continuous detection, one per false plot): radars whose local tracks never err — an
      oracle for tests and references.
    * ``gate_chi2``: 2-dof χ² gate, 13.8 = 99.9 %.
    * ``q_m2s3``: white-noise acceleration of (1); 50 m²/s³ keeps a 3°/s turn at 150 m/s
      (7.9 m/s²) inside the gate of a 12 s radar.
    * ``v0_sigma_mps``: initial speed uncertainty per axis of a one-point initiation.
    * ``confirm_hits``, ``tentative_misses``: initiation and deletion of tentative tracks.
    * ``mode_s_gate``: a plot and a track with different Mode S addresses never pair.
    * ``code_mismatch_cost``: added to the cost when both carry different Mode 3/A codes.
    * ``reuse_after_scans``: a deleted track's number is free again this many scans later.
    """

    ideal: bool = False
    gate_chi2: float = 13.8
    q_m2s3: float = 50.0
    v0_sigma_mps: float = 150.0
    confirm_hits: int = 3
    tentative_misses: int = 2
    mode_s_gate: bool = True
    code_mismatch_cost: float = 9.0
    reuse_after_scans: int = 10


@dataclass(frozen=True)
class ScanPlots:
    """One scan's plots of some partitions (see :func:`ground_plots`) and the partitions
    scanned (a track of a scanned partition that gets no plot misses)."""

    part: NDArray[np.int64]
    t: NDArray[np.float64]
    z: NDArray[np.float64]           # (m, 2) ground-plane position
    r: NDArray[np.float64]           # (m, 2, 2) its covariance (2)
    mode_s: NDArray[np.int64]
    mode_3a: NDArray[np.int64]
    period: NDArray[np.float64]
    drop_misses: NDArray[np.int64]
    scanned: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.part)


def ground_plots(range_m, azimuth_deg, elevation_deg, sigma_range_m, sigma_azimuth_deg, sigma_elevation_deg
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Plot position in the radar's ground plane and its covariance, eq. (2); the sigmas are
    the radar's nominal ones (scalars or per plot)."""
    b, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    rho = range_m * np.cos(e)
    sb, cb = np.sin(b), np.cos(b)
    var_rho = (np.cos(e) * sigma_range_m) ** 2 + (range_m * np.sin(e) * np.radians(sigma_elevation_deg)) ** 2
    var_x = (rho * np.radians(sigma_azimuth_deg)) ** 2
    r = np.empty((len(rho), 2, 2))
    r[:, 0, 0] = sb * sb * var_rho + cb * cb * var_x       # G diag(σρ², σx²) Gᵀ, G = [[sβ, cβ], [cβ, −sβ]]
    r[:, 1, 1] = cb * cb * var_rho + sb * sb * var_x
    r[:, 0, 1] = r[:, 1, 0] = sb * cb * (var_rho - var_x)
    return np.stack([rho * sb, rho * cb], axis=1), r


def _predict_pos(st: RadarTrackState, ti: NDArray[np.int64], dt: NDArray[np.float64], q: float):
    """Predicted position and its 2×2 covariance of tracks ``ti`` after ``dt``, eq. (1)."""
    x, p = st.x[ti], st.p[ti]
    pos = x[:, :2] + dt[:, None] * x[:, 2:]
    d = dt[:, None, None]
    ppos = p[:, :2, :2] + d * (p[:, :2, 2:] + p[:, 2:, :2]) + d * d * p[:, 2:, 2:]
    ppos = ppos + (q * dt ** 3 / 3.0)[:, None, None] * np.eye(2)
    return pos, ppos


def _inv2(s: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Inverse and determinant of 2×2 matrices (n, 2, 2)."""
    det = s[:, 0, 0] * s[:, 1, 1] - s[:, 0, 1] * s[:, 1, 0]
    inv = np.empty_like(s)
    inv[:, 0, 0], inv[:, 1, 1] = s[:, 1, 1] / det, s[:, 0, 0] / det
    inv[:, 0, 1], inv[:, 1, 0] = -s[:, 0, 1] / det, -s[:, 1, 0] / det
    return inv, det


def _candidates(cfg: RadarTrackerConfig, st: RadarTrackState, scan: ScanPlots, live: NDArray[np.int64]):
    """(track, plot) pairs of the same partition within reach: a KD-tree over the plots
    (partitions side by side) queried with the widest gate of the scan; exact gating follows."""
    # where each track's plot is expected: one period per scan since its last plot
    dt = st.period[live] * (st.misses[live] + 1)
    pos, ppos = _predict_pos(st, live, dt, cfg.q_m2s3)
    lam_p = np.linalg.eigvalsh(ppos)[:, 1]
    lam_r = np.linalg.eigvalsh(scan.r)[:, 1].max()
    speed = np.linalg.norm(st.x[live, 2:], axis=1)
    # + the motion over a tenth of a period (rotating antennas: the plot time moves with the
    # azimuth) and 3σ of the speed uncertainty over that tenth
    slack = 0.1 * st.period[live] * (speed + 3.0 * np.sqrt(np.trace(st.p[live, 2:, 2:], axis1=1, axis2=2)))
    reach = float(np.max(np.sqrt(cfg.gate_chi2 * (lam_p + lam_r)) + slack))
    a = cKDTree(np.column_stack([scan.z[:, 0] + scan.part * _PART_OFFSET, scan.z[:, 1]]))
    b = cKDTree(np.column_stack([pos[:, 0] + st.part[live] * _PART_OFFSET, pos[:, 1]]))
    pairs = b.sparse_distance_matrix(a, reach, output_type="ndarray")
    return live[pairs["i"].astype(np.int64)], pairs["j"].astype(np.int64)


def _pair_costs(cfg: RadarTrackerConfig, st: RadarTrackState, scan: ScanPlots, ti, pj):
    """Gate and cost of candidate pairs (module docstring)."""
    pos, ppos = _predict_pos(st, ti, scan.t[pj] - st.t[ti], cfg.q_m2s3)
    s_inv, det = _inv2(ppos + scan.r[pj])
    nu = scan.z[pj] - pos
    d2 = np.einsum("ni,nij,nj->n", nu, s_inv, nu)
    ok = d2 <= cfg.gate_chi2
    ms_t, ms_p = st.mode_s[ti], scan.mode_s[pj]
    if cfg.mode_s_gate:
        ok &= (ms_t < 0) | (ms_p < 0) | (ms_t == ms_p)
    a_t, a_p = st.mode_3a[ti], scan.mode_3a[pj]
    cost = d2 + np.log(det) + np.where((a_t >= 0) & (a_p >= 0) & (a_t != a_p), cfg.code_mismatch_cost, 0.0)
    return ti[ok], pj[ok], cost[ok]


def greedy_assignment(ti: NDArray[np.int64], pj: NDArray[np.int64], cost: NDArray[np.float64]
                      ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Pairs taken in increasing cost, each track and plot at most once (greedy GNN).

    Equal to the sorted greedy: the cheapest remaining pair is always mutually best, and a
    mutually best pair is never pre-empted by a cheaper one. Each round accepts every mutually
    best pair at once (vectorised) and drops the pairs of the matched tracks and plots."""
    out_t, out_p = [], []
    idx = np.arange(len(ti))
    while len(idx):
        t, p, c = ti[idx], pj[idx], cost[idx]
        by_t = np.lexsort((idx, c, t))              # ties resolved by the pair's position: deterministic
        first_t = np.ones(len(idx), bool)
        first_t[1:] = t[by_t][1:] != t[by_t][:-1]
        best_t = np.zeros(len(idx), bool)
        best_t[by_t[first_t]] = True
        by_p = np.lexsort((idx, c, p))
        first_p = np.ones(len(idx), bool)
        first_p[1:] = p[by_p][1:] != p[by_p][:-1]
        best_p = np.zeros(len(idx), bool)
        best_p[by_p[first_p]] = True
        win = best_t & best_p
        out_t.append(t[win])
        out_p.append(p[win])
        idx = idx[~np.isin(t, t[win]) & ~np.isin(p, p[win])]
    if not out_t:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_t), np.concatenate(out_p)


def _update(cfg: RadarTrackerConfig, st: RadarTrackState, scan: ScanPlots, ti, pj) -> dict[str, NDArray]:
    """Kalman update (1) of tracks ``ti`` with plots ``pj``; the changed columns."""
    dt = scan.t[pj] - st.t[ti]
    n = len(ti)
    f = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    f[:, 0, 2] = f[:, 1, 3] = dt
    q = np.zeros((n, 4, 4))
    for i in range(2):
        q[:, i, i], q[:, i + 2, i + 2] = dt ** 3 / 3.0, dt
        q[:, i, i + 2] = q[:, i + 2, i] = dt ** 2 / 2.0
    x = np.einsum("nij,nj->ni", f, st.x[ti])
    p = f @ st.p[ti] @ f.transpose(0, 2, 1) + cfg.q_m2s3 * q
    s_inv, _ = _inv2(p[:, :2, :2] + scan.r[pj])
    k = p[:, :, :2] @ s_inv                                  # (n, 4, 2)
    x = x + np.einsum("nij,nj->ni", k, scan.z[pj] - x[:, :2])
    p = p - k @ p[:, :2, :]
    p = 0.5 * (p + p.transpose(0, 2, 1))
    hits = st.hits[ti] + 1
    ms, a = scan.mode_s[pj], scan.mode_3a[pj]
    return dict(t=scan.t[pj], x=x, p=p, hits=hits, misses=np.zeros(n, np.int64),
                confirmed=st.confirmed[ti] | (hits >= cfg.confirm_hits),
                mode_s=np.where(ms >= 0, ms, st.mode_s[ti]), mode_3a=np.where(a >= 0, a, st.mode_3a[ti]))


def lowest_free_numbers(live_part: NDArray[np.int64], live_number: NDArray[np.int64],
                        new_part: NDArray[np.int64]) -> NDArray[np.int64]:
    """For each new track (partition ``new_part``), the lowest track numbers ≥ 1 not used by
    the live tracks of its partition (the k new tracks of a partition take the k lowest, in
    order). Vectorised over partitions: each partition's candidates are 1 … live + new."""
    if len(new_part) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(new_part, kind="stable")
    parts, first, counts = np.unique(new_part[order], return_index=True, return_counts=True)
    live_n = np.zeros(len(parts), np.int64)
    lo, hi = np.searchsorted(live_part, parts, "left"), np.searchsorted(live_part, parts, "right")
    live_n[:] = hi - lo
    size = live_n + counts
    cand_part = np.repeat(parts, size)
    cand = np.arange(size.sum()) - np.repeat(np.cumsum(size) - size, size) + 1
    live_key = np.sort(live_part * (1 << 32) + live_number)
    key = cand_part * (1 << 32) + cand
    used = np.zeros(len(key), bool)
    if len(live_key):
        pos = np.minimum(np.searchsorted(live_key, key), len(live_key) - 1)
        used = live_key[pos] == key
    free_part, free = cand_part[~used], cand[~used]
    start = np.searchsorted(free_part, parts, "left")           # each partition's free numbers, ascending
    rank = np.arange(len(new_part)) - np.repeat(first, counts)
    out = np.empty(len(new_part), np.int64)
    out[order] = free[np.repeat(start, counts) + rank]
    return out


def step(cfg: RadarTrackerConfig, state: RadarTrackState, scan: ScanPlots
         ) -> tuple[RadarTrackState, NDArray[np.int64]]:
    """One scan: associate the scan's plots with the live tracks, update, count misses,
    delete, initiate. Returns the new state and, per plot, (track number, track life): an
    (m, 2) array; the life is unique over the whole run, so a reused number is a new life."""
    st = state
    m = len(scan)
    live = np.flatnonzero(np.isin(st.part, scan.part)) if m else np.zeros(0, np.int64)
    ti = pj = np.zeros(0, np.int64)
    if len(live) and m:
        ti, pj = _candidates(cfg, st, scan, live)
        ti, pj, cost = _pair_costs(cfg, st, scan, ti, pj)
        ti, pj = greedy_assignment(ti, pj, cost)
    numbers = np.zeros((m, 2), np.int64)
    numbers[pj, 0], numbers[pj, 1] = st.number[ti], st.life[ti]
    cols = {f: getattr(st, f).copy() for f in TRACK_FIELDS}
    for name, v in _update(cfg, st, scan, ti, pj).items():
        cols[name][ti] = v
    missed = np.isin(st.part, scan.scanned)
    missed[ti] = False
    cols["misses"][missed] += 1
    limit = np.where(cols["confirmed"], cols["drop_misses"], cfg.tentative_misses)
    alive = cols["misses"] < limit
    # numbers of deleted tracks are held for reuse_after_scans scans of their partition
    held_scans = st.held_scans - np.isin(st.held_part, scan.scanned)
    still = held_scans > 0
    held_part = np.concatenate([st.held_part[still], cols["part"][~alive]])
    held_number = np.concatenate([st.held_number[still], cols["number"][~alive]])
    held_scans = np.concatenate([held_scans[still], np.full(np.count_nonzero(~alive), cfg.reuse_after_scans)])
    kept = {f: v[alive] for f, v in cols.items()}
    new = np.setdiff1d(np.arange(m), pj)
    used_part, used_number = np.concatenate([kept["part"], held_part]), np.concatenate([kept["number"], held_number])
    o = np.lexsort((used_number, used_part))
    numbers[new, 0] = lowest_free_numbers(used_part[o], used_number[o], scan.part[new])
    numbers[new, 1] = st.next_life + np.arange(len(new))
    born = _initiate(cfg, scan, new, numbers[new, 0], numbers[new, 1])
    merged = {f: np.concatenate([kept[f], getattr(born, f)]) for f in TRACK_FIELDS}
    o = np.lexsort((merged["number"], merged["part"]))
    return RadarTrackState(**{f: v[o] for f, v in merged.items()}, next_life=st.next_life + len(new),
                           held_part=held_part, held_number=held_number, held_scans=held_scans), numbers


def _initiate(cfg: RadarTrackerConfig, scan: ScanPlots, new: NDArray[np.int64], numbers: NDArray[np.int64],
              lives: NDArray[np.int64]) -> RadarTrackState:
    """Tentative tracks on the plots ``new``: position = plot, velocity 0 ± v0."""
    n = len(new)
    x = np.zeros((n, 4))
    x[:, :2] = scan.z[new]
    p = np.zeros((n, 4, 4))
    p[:, :2, :2] = scan.r[new]
    p[:, 2, 2] = p[:, 3, 3] = cfg.v0_sigma_mps ** 2
    return RadarTrackState(part=scan.part[new], number=numbers, t=scan.t[new], x=x, p=p,
                           hits=np.ones(n, np.int64), misses=np.zeros(n, np.int64),
                           confirmed=np.full(n, cfg.confirm_hits <= 1), mode_s=scan.mode_s[new],
                           mode_3a=scan.mode_3a[new], period=scan.period[new], drop_misses=scan.drop_misses[new],
                           life=lives)


def drop_misses(track_drop_scans: float) -> int:
    """Misses at which a confirmed track is deleted: its silence, (misses + 1) scan periods,
    then exceeds ``track_drop_scans`` periods."""
    return max(1, int(np.floor(track_drop_scans)))


#: plots of a job from which compiling the scan loop pays on a fresh install: the Python loop
#: costs ~20–30 µs a plot on the 2-core machine, the first compilation 12–20 s, the compiled
#: loop ~1.5 µs a plot (measured on the default scenario)
COMPILE_PAYS_PLOTS = 400_000


def compiled_pays(job_plots: int) -> bool:
    """Whether :func:`run_scans` should run the compiled loop for a job of ``job_plots`` plots:
    when the loop is compiled already (in this process or in numba's cache: it then loads in
    about a second) or when the job is large enough to repay compiling it."""
    return job_plots >= COMPILE_PAYS_PLOTS or is_ready()


def run_scans(cfg: RadarTrackerConfig, scan_index: NDArray[np.int64], plots: ScanPlots,
              scans_of_part: NDArray[np.int64], state: RadarTrackState | None = None,
              compiled: bool | None = None, job_plots: int | None = None
              ) -> tuple[NDArray[np.int64], RadarTrackState]:
    """:func:`step` over scans 0, 1, …: ``plots`` holds every scan's plots (``scan_index`` per
    plot, ``plots.scanned`` unused) and ``scans_of_part[p]`` is the number of scans of
    partition p (partitions with fewer scans drop out). Returns (track number, track life) per
    plot, (n, 2), and the final state. ``compiled``: the loop compiled
    (:mod:`tertiary.simulate.radar_scan_kernel`, the same model); False: :func:`step` in
    Python, the reference; None: compiled when it pays (:func:`compiled_pays` of ``job_plots``,
    the whole job's plots, default this call's), so that a fresh install's first small
    simulation does not wait for the compiler."""
    if compiled is None:
        compiled = compiled_pays(len(scan_index) if job_plots is None else job_plots)
    if compiled:
        return run_scans_compiled(cfg, scan_index, plots, scans_of_part, state)
    st = state if state is not None else init_state()
    order = np.argsort(scan_index, kind="stable")
    n_steps = int(scans_of_part.max(initial=0))
    bounds = np.searchsorted(scan_index[order], np.arange(n_steps + 1))
    numbers = np.zeros((len(scan_index), 2), np.int64)
    all_parts = np.arange(len(scans_of_part))
    for k in range(n_steps):
        rows = order[bounds[k]:bounds[k + 1]]
        scan = ScanPlots(part=plots.part[rows], t=plots.t[rows], z=plots.z[rows], r=plots.r[rows],
                         mode_s=plots.mode_s[rows], mode_3a=plots.mode_3a[rows], period=plots.period[rows],
                         drop_misses=plots.drop_misses[rows], scanned=all_parts[scans_of_part > k])
        st, numbers[rows] = step(cfg, st, scan)
    return numbers, st


__all__ = ["RadarTrackerConfig", "RadarTrackState", "ScanPlots", "TRACK_FIELDS", "STATE_VERSION", "init_state", "step", "run_scans", "compiled_pays",
           "ground_plots", "greedy_assignment", "lowest_free_numbers", "drop_misses"]
