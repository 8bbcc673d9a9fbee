"""The national day's strategic plan (:func:`tertiary.simulate.traffic.national.allocate_levels`),
compiled (numba, ``cache=True``).

The plan is sequential by nature: flights in order of entry, each taking the first (delay,
level) that conflicts with no flight planned before it. The Python loop over the day's ~20 000
flights, a few dozen numpy calls each, would weigh on every national simulation, whatever its
length (the whole day is planned). Here each flight's choices are
tested against the flights airborne with it in plain loops. The Python function stays the
reference (compared in the tests).
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


@_jit
def _key(a, b, m, T, bits):
    """:func:`tertiary.simulate.traffic.national.conflict_key` of one (template, template, offset)."""
    half = 1 << (bits - 1)
    m = min(max(m, -half + 1), half - 1)
    return (a * T + b) * (1 << bits) + m + half


@_jit
def plan(order, route, entry, land, lv_ptr, lv_idx, group, length, keys, pair_any, stride, origin, dest,
         take_off_gap, landing_gap, delays, reach, bits, out_r, out_e):
    """(T templates, ``keys`` sorted): each flight ``order[rank]`` in turn gets ``out_r`` /
    ``out_e`` as :func:`tertiary.simulate.traffic.national.allocate_levels` gives them; ``levels[g]`` is
    ``lv_idx[lv_ptr[g]:lv_ptr[g + 1]]``. Returns the flights left in conflict."""
    n, T = len(route), len(length)
    big = np.iinfo(np.int64).max // 4
    ends = np.full(n, -big)
    lands = np.full(n, -big)
    done_e = np.zeros(n, np.int64)
    sorted_entries = entry[order]
    nd = len(delays)
    left = 0
    for rank in range(n):
        f = order[rank]
        r0 = route[f]
        g = group[r0]
        nl = lv_ptr[g + 1] - lv_ptr[g]
        lv = np.empty(nl, np.int64)                    # its drawn level first, then the others
        lv[0] = r0
        k = 1
        for i in range(lv_ptr[g], lv_ptr[g + 1]):
            if lv_idx[i] != r0 and k < nl:
                lv[k] = lv_idx[i]
                k += 1
        nc = nl * nd
        cand = np.empty(nc, np.int64)
        d = np.empty(nc, np.int64)
        e = np.empty(nc, np.int64)
        domestic = land[f] >= 0
        for c in range(nc):                            # (delay, level), shortest delay first
            cand[c] = lv[c % nl]
            d[c] = delays[c // nl]
            e[c] = (land[f] + d[c] - length[cand[c]]) if domestic else entry[f] + d[c]
        e_min = e.min()
        lo = np.searchsorted(sorted_entries, e_min - reach)
        near = np.empty(max(rank - lo, 0), np.int64)
        m = 0
        for i in range(lo, rank):
            if ends[order[i]] >= e_min:
                near[m] = order[i]
                m += 1
        # the flights using its runways (a domestic flight keeps its airports at every choice)
        same_o = np.empty(m, np.int64)
        same_d = np.empty(m, np.int64)
        no = nd_ = 0
        if domestic:
            o, gd = origin[cand[0]], dest[cand[0]]
            for i in range(m):
                if origin[out_r[near[i]]] == o:
                    same_o[no] = near[i]
                    no += 1
                if dest[out_r[near[i]]] == gd:
                    same_d[nd_] = near[i]
                    nd_ += 1
        ok = np.ones(nc, np.bool_)
        hits = np.zeros(nc, np.int64)
        last = nc - 1
        for c in range(nc):
            for i in range(no):                        # the runways' spacing at both ends
                if abs(e[c] - done_e[same_o[i]]) < take_off_gap:
                    ok[c] = False
            for i in range(nd_):
                if abs(land[f] + d[c] - lands[same_d[i]]) < landing_gap:
                    ok[c] = False
            for i in range(m):
                h = near[i]
                if pair_any[cand[c] * T + out_r[h]]:
                    q = _key(cand[c], out_r[h], np.int64(np.rint((e[c] - done_e[h]) / stride)), T, bits)
                    at = min(np.searchsorted(keys, q), len(keys) - 1)
                    if keys[at] == q:
                        hits[c] += 1
            if hits[c] == 0 and ok[c]:
                last = c
                break
        # the first free choice; else the fewest conflicts, keeping the runways' spacing if any can
        best, best_score = 0, big
        for c in range(last + 1):
            s = hits[c] + (0 if ok[c] else 1 << 20)
            if s < best_score:
                best, best_score = c, s
        if hits[best] > 0:
            left += 1
        out_r[f], out_e[f] = cand[best], e[best]
        done_e[f], ends[f] = e[best], e[best] + length[cand[best]]
        lands[f] = land[f] + d[best] if domestic else -big
    return left
