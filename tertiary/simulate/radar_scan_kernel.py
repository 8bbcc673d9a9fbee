"""The radars' plot-to-track association over every scan, compiled (numba, ``cache=True``).

The same model as :func:`tertiary.simulate.radar_tracker.step` — equations (1) and (2) of that
module, its gate, cost, greedy global nearest neighbour, track management and number reuse —
written as one loop over scans and, inside a scan, over each partition's tracks and plots. The
Python :func:`~tertiary.simulate.radar_tracker.step` stays the reference (the two are compared in
the tests): in Python the loop over ~1 000 scans an hour dominates a simulation, each scan a
few milliseconds of small numpy calls.

Order of the pairs (what decides ties of equal cost): the reference breaks them by the pair's
position in the KD-tree's output, this kernel by (track in state order, plot in x order); two
candidate pairs of exactly the same cost do not occur with measured plots.

The tracks live in a pool (one slot per track ever: the initial tracks, then one per plot that
starts a track); :func:`run_scans_compiled` returns the live ones sorted by (partition, number),
as the reference's state is.
"""

from __future__ import annotations

import numba
import numpy as np

from tertiary.core.jit import in_cache
from tertiary.simulate.radar_track_state import TRACK_FIELDS, RadarTrackState, init_state

_jit = numba.njit(cache=True, error_model="numpy")   # x / 0 is inf, as in numpy


@_jit
def _eig_max(a: float, b: float, c: float) -> float:
    """Largest eigenvalue of the symmetric 2×2 [[a, b], [b, c]]."""
    h = 0.5 * (a - c)
    return 0.5 * (a + c) + np.sqrt(h * h + b * b)


@_jit
def _scan_loop(order, bounds, scanned_until, p_part, p_t, p_z, p_r, p_ms, p_a, p_period, p_drop,
               s_part, s_number, s_t, s_x, s_p, s_hits, s_misses, s_conf, s_ms, s_a, s_period, s_drop, s_life,
               active, n_used, h_part, h_number, h_scans, n_held, next_life,
               gate, q, v0, confirm_hits, tent_misses, ms_gate, code_cost, reuse, numbers):
    """Every scan in turn (the reference's :func:`step` per scan); the pool ``s_*``/``active``,
    the held numbers ``h_*`` and ``numbers`` (per plot: track number, life) are filled in place.
    Returns (slots used, numbers held, next life)."""
    n_parts = len(scanned_until)
    w_p, w_kg = np.empty((4, 4)), np.empty((4, 2))
    c_t, c_p, c_cost = np.empty(1024, np.int64), np.empty(1024, np.int64), np.empty(1024)
    took_t, took_p = np.zeros(len(s_part), np.bool_), np.zeros(len(p_part), np.bool_)
    scanned = np.zeros(n_parts, np.bool_)
    for k in range(len(bounds) - 1):
        rows = order[bounds[k]:bounds[k + 1]]
        m = len(rows)
        for pa in range(n_parts):
            scanned[pa] = scanned_until[pa] > k
        counts, start, bucket, bx = _bucket(rows, p_part, p_z, n_parts)
        reach = _reach(rows, p_r, n_used, active, counts, s_part, s_period, s_misses, s_x, s_p, gate, q)
        # candidates within reach (counted first: the pair arrays are sized once), then the
        # exact gate and cost
        n_c = 0
        if reach >= 0.0:
            n_near = _near_pairs(False, n_used, active, counts, s_part, s_period, s_misses, s_x, start, bx, bucket,
                                 p_z, reach, c_t, c_p)
            if n_near > len(c_t):
                c_t, c_p, c_cost = np.empty(2 * n_near, np.int64), np.empty(2 * n_near, np.int64), np.empty(2 * n_near)
            _near_pairs(True, n_used, active, counts, s_part, s_period, s_misses, s_x, start, bx, bucket,
                        p_z, reach, c_t, c_p)
            for e in range(n_near):
                i, r = c_t[e], c_p[e]
                ok, cost = _pair_cost(i, r, s_t, s_x, s_p, s_ms, s_a, p_t, p_z, p_r, p_ms, p_a,
                                      gate, q, ms_gate, code_cost)
                if ok:
                    c_t[n_c], c_p[n_c], c_cost[n_c] = i, r, cost
                    n_c += 1
        n_m = _greedy(c_t, c_p, c_cost, n_c, took_t, took_p)     # matched pairs first in c_t, c_p
        for e in range(n_m):
            i, r = c_t[e], c_p[e]
            numbers[r, 0], numbers[r, 1] = s_number[i], s_life[i]
            _update(i, r, s_t, s_x, s_p, s_hits, s_misses, s_conf, s_ms, s_a, p_t, p_z, p_r, p_ms, p_a,
                    q, confirm_hits, w_p, w_kg)
        n_held = _drop(n_used, active, scanned, took_t, s_part, s_number, s_misses, s_conf, s_drop, tent_misses,
                       h_part, h_number, h_scans, n_held, reuse)
        n_used, next_life = _start(rows, took_p, n_parts, n_used, next_life, active, s_part, s_number, s_t, s_x, s_p,
                                   s_hits, s_misses, s_conf, s_ms, s_a, s_period, s_drop, s_life, h_part, h_number,
                                   n_held, p_part, p_t, p_z, p_r, p_ms, p_a, p_period, p_drop, v0, confirm_hits,
                                   numbers)
        for e in range(n_m):
            took_t[c_t[e]] = False
            took_p[c_p[e]] = False
    return n_used, n_held, next_life


@_jit
def _bucket(rows, p_part, p_z, n_parts):
    """The scan's plots bucketed by partition (``start``: each bucket's first index, ``counts``
    shifted by one), each bucket sorted by x (``bx``)."""
    m = len(rows)
    counts = np.zeros(n_parts + 1, np.int64)
    xs = np.empty(m)
    for j in range(m):
        counts[p_part[rows[j]] + 1] += 1
        xs[j] = p_z[rows[j], 0]
    start, fill = np.empty(n_parts + 1, np.int64), np.empty(n_parts + 1, np.int64)
    start[0] = fill[0] = 0
    for pa in range(n_parts):
        start[pa + 1] = fill[pa + 1] = start[pa] + counts[pa + 1]
    bucket, bx = np.empty(m, np.int64), np.empty(m)
    for j in _argsort(xs):
        r = rows[j]
        bucket[fill[p_part[r]]], bx[fill[p_part[r]]] = r, xs[j]
        fill[p_part[r]] += 1
    return counts, start, bucket, bx


@_jit
def _reach(rows, p_r, n_used, active, counts, s_part, s_period, s_misses, s_x, s_p, gate, q):
    """The reach of the candidate search: the widest gate of the scan's live tracks, at one
    period per scan since their last plot, plus a tenth of a period's motion (−1: no track)."""
    lam_r = 0.0
    for j in range(len(rows)):
        r = rows[j]
        lam = _eig_max(p_r[r, 0, 0], p_r[r, 0, 1], p_r[r, 1, 1])
        if j == 0 or lam > lam_r:
            lam_r = lam
    reach = -1.0
    for i in range(n_used):
        if not active[i] or counts[s_part[i] + 1] == 0:
            continue
        dt = s_period[i] * (s_misses[i] + 1)
        a = s_p[i, 0, 0] + dt * (s_p[i, 0, 2] + s_p[i, 2, 0]) + dt * dt * s_p[i, 2, 2] + q * dt ** 3 / 3.0
        b = s_p[i, 1, 0] + dt * (s_p[i, 1, 2] + s_p[i, 3, 0]) + dt * dt * s_p[i, 3, 2]
        c = s_p[i, 1, 1] + dt * (s_p[i, 1, 3] + s_p[i, 3, 1]) + dt * dt * s_p[i, 3, 3] + q * dt ** 3 / 3.0
        speed = np.sqrt(s_x[i, 2] ** 2 + s_x[i, 3] ** 2)
        slack = 0.1 * s_period[i] * (speed + 3.0 * np.sqrt(s_p[i, 2, 2] + s_p[i, 3, 3]))
        g = np.sqrt(gate * (_eig_max(a, b, c) + lam_r)) + slack
        if g > reach:
            reach = g
    return reach


@_jit
def _greedy(c_t, c_p, c_cost, n_c, took_t, took_p):
    """Greedy global nearest neighbour: pairs in increasing cost, each track and plot once.
    The matched pairs are moved to the front of ``c_t``, ``c_p`` and flagged in ``took_*``;
    returns their number."""
    order = _argsort(c_cost[:n_c])
    mt, mp = np.empty(n_c, np.int64), np.empty(n_c, np.int64)
    n_m = 0
    for e in order:
        i, r = c_t[e], c_p[e]
        if took_t[i] or took_p[r]:
            continue
        took_t[i] = took_p[r] = True
        mt[n_m], mp[n_m] = i, r
        n_m += 1
    for e in range(n_m):
        c_t[e], c_p[e] = mt[e], mp[e]
    return n_m


@_jit
def _drop(n_used, active, scanned, took_t, s_part, s_number, s_misses, s_conf, s_drop, tent_misses,
          h_part, h_number, h_scans, n_held, reuse):
    """Misses of the scanned partitions' tracks without a plot, deletions, and the numbers held
    for reuse (the deleted ones appended in (partition, number) order). Returns the number held."""
    n_del = 0
    dele = np.empty(n_used, np.int64)
    for i in range(n_used):
        if not active[i]:
            continue
        if scanned[s_part[i]] and not took_t[i]:
            s_misses[i] += 1
        if s_misses[i] >= (s_drop[i] if s_conf[i] else tent_misses):
            active[i] = False
            dele[n_del] = i
            n_del += 1
    kept = 0
    for h in range(n_held):
        left = h_scans[h] - (1 if scanned[h_part[h]] else 0)
        if left > 0:
            h_part[kept], h_number[kept], h_scans[kept] = h_part[h], h_number[h], left
            kept += 1
    key = np.empty(n_del)
    for e in range(n_del):
        key[e] = s_part[dele[e]] * 4294967296.0 + s_number[dele[e]]
    for e in _argsort(key):
        i = dele[e]
        h_part[kept], h_number[kept], h_scans[kept] = s_part[i], s_number[i], reuse
        kept += 1
    return kept


@_jit
def _start(rows, took_p, n_parts, n_used, next_life, active, s_part, s_number, s_t, s_x, s_p, s_hits, s_misses,
           s_conf, s_ms, s_a, s_period, s_drop, s_life, h_part, h_number, n_held, p_part, p_t, p_z, p_r, p_ms, p_a,
           p_period, p_drop, v0, confirm_hits, numbers):
    """Plots left over start tentative tracks (position = plot, velocity 0 ± v0), in the
    scan's plot order, each taking the lowest number free in its partition (live or held
    numbers are not). Returns (slots used, next life)."""
    m = len(rows)
    new = np.empty(m, np.int64)
    n_new = 0
    for j in range(m):          # in the scan's plot order, as the reference's setdiff1d
        if not took_p[rows[j]]:
            new[n_new] = rows[j]
            n_new += 1
    if n_new == 0:
        return n_used, next_life
    for pa in range(n_parts):
        n_here = 0
        for e in range(n_new):
            if p_part[new[e]] == pa:
                n_here += 1
        if n_here == 0:
            continue
        top = 0
        for i in range(n_used):
            if active[i] and s_part[i] == pa and s_number[i] > top:
                top = s_number[i]
        for h in range(n_held):
            if h_part[h] == pa and h_number[h] > top:
                top = h_number[h]
        used = np.zeros(top + n_here + 2, np.bool_)
        for i in range(n_used):
            if active[i] and s_part[i] == pa:
                used[s_number[i]] = True
        for h in range(n_held):
            if h_part[h] == pa:
                used[h_number[h]] = True
        cand = 1
        for e in range(n_new):
            r = new[e]
            if p_part[r] == pa:
                while used[cand]:
                    cand += 1
                used[cand] = True
                numbers[r, 0] = cand
    for e in range(n_new):
        r, i = new[e], n_used + e
        numbers[r, 1] = next_life + e
        s_part[i], s_number[i], s_t[i], s_life[i] = p_part[r], numbers[r, 0], p_t[r], next_life + e
        s_x[i, 0], s_x[i, 1], s_x[i, 2], s_x[i, 3] = p_z[r, 0], p_z[r, 1], 0.0, 0.0
        for u in range(4):
            for v in range(4):
                s_p[i, u, v] = 0.0
        s_p[i, 0, 0], s_p[i, 0, 1] = p_r[r, 0, 0], p_r[r, 0, 1]
        s_p[i, 1, 0], s_p[i, 1, 1] = p_r[r, 1, 0], p_r[r, 1, 1]
        s_p[i, 2, 2] = s_p[i, 3, 3] = v0 * v0
        s_hits[i], s_misses[i], s_conf[i] = 1, 0, confirm_hits <= 1
        s_ms[i], s_a[i], s_period[i], s_drop[i] = p_ms[r], p_a[r], p_period[r], p_drop[r]
        active[i] = True
    return n_used + n_new, next_life + n_new


@_jit
def _argsort(key):
    """Stable argsort (bottom-up merge sort): ties keep their order. Written out because
    numba's ``np.argsort`` costs seconds of compilation per key type on a fresh install."""
    n = len(key)
    a = np.arange(n)
    b = np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            i, j, o = lo, mid, lo
            while i < mid and j < hi:
                if key[a[j]] < key[a[i]]:
                    b[o] = a[j]
                    j += 1
                else:
                    b[o] = a[i]
                    i += 1
                o += 1
            while i < mid:
                b[o] = a[i]
                i += 1
                o += 1
            while j < hi:
                b[o] = a[j]
                j += 1
                o += 1
        a, b = b, a
        width *= 2
    return a


@_jit
def _first_at_least(x, lo, hi, v):
    """The first index in [lo, hi) of the sorted ``x`` with x ≥ v (hi if none)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if x[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo



@_jit
def _near_pairs(keep, n_used, active, counts, s_part, s_period, s_misses, s_x, start, bx, bucket, p_z, reach,
                c_t, c_p):
    """(track, plot) pairs of a partition whose plot lies within ``reach`` of the track's
    expected position (one period per scan since its last plot): their number, and with
    ``keep`` the pairs themselves in ``c_t``, ``c_p``."""
    n = 0
    for i in range(n_used):
        pa = s_part[i]
        if not active[i] or counts[pa + 1] == 0:
            continue
        dt = s_period[i] * (s_misses[i] + 1)
        px, py = s_x[i, 0] + dt * s_x[i, 2], s_x[i, 1] + dt * s_x[i, 3]
        hi = start[pa + 1]
        for jj in range(_first_at_least(bx, start[pa], hi, px - reach), hi):
            if bx[jj] > px + reach:
                break
            r = bucket[jj]
            dx, dy = p_z[r, 0] - px, p_z[r, 1] - py
            if dx * dx + dy * dy <= reach * reach:
                if keep:
                    c_t[n], c_p[n] = i, r
                n += 1
    return n

@_jit
def _pair_cost(i, r, s_t, s_x, s_p, s_ms, s_a, p_t, p_z, p_r, p_ms, p_a, gate, q, ms_gate, code_cost):
    """Gate and cost of track ``i`` with plot ``r`` (the reference's ``_pair_costs``)."""
    if ms_gate and s_ms[i] >= 0 and p_ms[r] >= 0 and s_ms[i] != p_ms[r]:
        return False, 0.0
    dt = p_t[r] - s_t[i]
    px, py = s_x[i, 0] + dt * s_x[i, 2], s_x[i, 1] + dt * s_x[i, 3]
    qd = q * dt ** 3 / 3.0
    s00 = s_p[i, 0, 0] + dt * (s_p[i, 0, 2] + s_p[i, 2, 0]) + dt * dt * s_p[i, 2, 2] + qd + p_r[r, 0, 0]
    s01 = s_p[i, 0, 1] + dt * (s_p[i, 0, 3] + s_p[i, 2, 1]) + dt * dt * s_p[i, 2, 3] + p_r[r, 0, 1]
    s10 = s_p[i, 1, 0] + dt * (s_p[i, 1, 2] + s_p[i, 3, 0]) + dt * dt * s_p[i, 3, 2] + p_r[r, 1, 0]
    s11 = s_p[i, 1, 1] + dt * (s_p[i, 1, 3] + s_p[i, 3, 1]) + dt * dt * s_p[i, 3, 3] + qd + p_r[r, 1, 1]
    det = s00 * s11 - s01 * s10
    n0, n1 = p_z[r, 0] - px, p_z[r, 1] - py
    d2 = n0 * (s11 / det * n0 - s01 / det * n1) + n1 * (-s10 / det * n0 + s00 / det * n1)
    if not d2 <= gate:
        return False, 0.0
    cost = d2 + np.log(det)
    if s_a[i] >= 0 and p_a[r] >= 0 and s_a[i] != p_a[r]:
        cost += code_cost
    return True, cost


@_jit
def _update(i, r, s_t, s_x, s_p, s_hits, s_misses, s_conf, s_ms, s_a, p_t, p_z, p_r, p_ms, p_a, q, confirm_hits,
            p, kg):
    """Kalman update (1) of track ``i`` with plot ``r`` (the reference's ``_update``); ``p``,
    ``kg``: scratch arrays (4, 4) and (4, 2)."""
    dt = p_t[r] - s_t[i]
    sp = s_p[i]
    # F P Fᵀ + q Q, F = [[I, dt I], [0, I]], by 2×2 blocks (u, v ∈ {0, 1})
    for u in range(2):
        for v in range(2):
            p[u, v] = sp[u, v] + dt * (sp[u, v + 2] + sp[u + 2, v]) + dt * dt * sp[u + 2, v + 2]
            p[u, v + 2] = sp[u, v + 2] + dt * sp[u + 2, v + 2]
            p[u + 2, v] = sp[u + 2, v] + dt * sp[u + 2, v + 2]
            p[u + 2, v + 2] = sp[u + 2, v + 2]
        p[u, u] += q * dt ** 3 / 3.0
        p[u + 2, u + 2] += q * dt
        p[u, u + 2] += q * dt ** 2 / 2.0
        p[u + 2, u] += q * dt ** 2 / 2.0
    s00, s01 = p[0, 0] + p_r[r, 0, 0], p[0, 1] + p_r[r, 0, 1]
    s10, s11 = p[1, 0] + p_r[r, 1, 0], p[1, 1] + p_r[r, 1, 1]
    det = s00 * s11 - s01 * s10
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    for u in range(4):
        kg[u, 0] = p[u, 0] * i00 + p[u, 1] * i10
        kg[u, 1] = p[u, 0] * i01 + p[u, 1] * i11
    n0 = p_z[r, 0] - (s_x[i, 0] + dt * s_x[i, 2])
    n1 = p_z[r, 1] - (s_x[i, 1] + dt * s_x[i, 3])
    s_x[i, 0] += dt * s_x[i, 2]
    s_x[i, 1] += dt * s_x[i, 3]
    for u in range(4):
        s_x[i, u] += kg[u, 0] * n0 + kg[u, 1] * n1
    # P − K H P, symmetrised
    for u in range(4):
        for v in range(u, 4):
            a = p[u, v] - (kg[u, 0] * p[0, v] + kg[u, 1] * p[1, v])
            b = p[v, u] - (kg[v, 0] * p[0, u] + kg[v, 1] * p[1, u])
            sp[u, v] = sp[v, u] = 0.5 * (a + b)
    s_t[i] = p_t[r]
    s_hits[i] += 1
    s_misses[i] = 0
    s_conf[i] = s_conf[i] or s_hits[i] >= confirm_hits
    if p_ms[r] >= 0:
        s_ms[i] = p_ms[r]
    if p_a[r] >= 0:
        s_a[i] = p_a[r]


def is_ready() -> bool:
    """The loop is compiled in this process, or numba's cache holds it for this source (then
    it loads in about a second instead of compiling for 12–20 s on the 2-core machine)."""
    return bool(_scan_loop.signatures) or in_cache(_scan_loop)


def run_scans_compiled(cfg, scan_index, plots, scans_of_part, state):
    """:func:`tertiary.simulate.radar_tracker.run_scans` through the compiled loop: the same
    arguments and the same (numbers, state)."""
    st = state if state is not None else init_state()
    n0, n = len(st), len(scan_index)
    order = np.argsort(scan_index, kind="stable")
    scans_of_part = np.asarray(scans_of_part, np.int64)
    n_steps = int(scans_of_part.max(initial=0))
    bounds = np.searchsorted(scan_index[order], np.arange(n_steps + 1)).astype(np.int64)
    n_parts = max(len(scans_of_part), int(plots.part.max(initial=-1)) + 1, int(st.part.max(initial=-1)) + 1,
                  int(st.held_part.max(initial=-1)) + 1)
    until = np.zeros(n_parts, np.int64)
    until[:len(scans_of_part)] = scans_of_part
    # the pool: the carried tracks, then a slot for each plot (each starts at most one track)
    pool = {}
    for f in TRACK_FIELDS:
        v = getattr(st, f)
        out = np.zeros((n0 + n, *v.shape[1:]), v.dtype if f != "confirmed" else np.bool_)
        out[:n0] = v
        pool[f] = out
    nh = len(st.held_part)
    held = [np.zeros(nh + n0 + n, np.int64) for _ in range(3)]
    for h, v in zip(held, (st.held_part, st.held_number, st.held_scans)):
        h[:nh] = v
    active = np.zeros(n0 + n, np.bool_)
    active[:n0] = True
    numbers = np.zeros((n, 2), np.int64)
    f64 = lambda a: np.ascontiguousarray(a, np.float64)      # noqa: E731
    i64 = lambda a: np.ascontiguousarray(a, np.int64)        # noqa: E731
    n_used, n_held, next_life = _scan_loop(
        i64(order), bounds, until, i64(plots.part), f64(plots.t), f64(plots.z), f64(plots.r), i64(plots.mode_s),
        i64(plots.mode_3a), f64(plots.period), i64(plots.drop_misses),
        pool["part"], pool["number"], pool["t"], pool["x"], pool["p"], pool["hits"], pool["misses"],
        pool["confirmed"], pool["mode_s"], pool["mode_3a"], pool["period"], pool["drop_misses"], pool["life"],
        active, n0, held[0], held[1], held[2], nh, int(st.next_life),
        float(cfg.gate_chi2), float(cfg.q_m2s3), float(cfg.v0_sigma_mps), int(cfg.confirm_hits),
        int(cfg.tentative_misses), bool(cfg.mode_s_gate), float(cfg.code_mismatch_cost), int(cfg.reuse_after_scans),
        numbers)
    live = np.flatnonzero(active[:n_used])
    live = live[np.lexsort((pool["number"][live], pool["part"][live]))]
    out = RadarTrackState(**{f: pool[f][live] for f in TRACK_FIELDS}, next_life=int(next_life),
                          held_part=held[0][:n_held].copy(), held_number=held[1][:n_held].copy(),
                          held_scans=held[2][:n_held].copy())
    return numbers, out
