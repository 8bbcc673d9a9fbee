"""The altitude filter's recursion over each track's replies, compiled (numba, ``cache=True``).

The same equations as :func:`tertiary.stages.tracking.altitude.filter_tracks_carry` — (A1)–(A4), the IMM
(A5)–(A9), the garble gate, confirmation, restarts and identity swaps — written per track and
per reply instead of vectorised over tracks per reply rank. The vectorised loop paid a few
dozen numpy calls per rank in the fusion's and the centralised reference's vertical channels;
tracks are independent, so the compiled loop runs them one after another. The Python loop stays the reference (compared in the tests).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import types as nbt

from tertiary.core.jit import register_kernel

_jit = numba.njit(cache=True, error_model="numpy")     # x / 0 is inf or nan, as in numpy


@_jit
def _predict(s, tau, q, out):
    """(A1)–(A2): ``s`` (5,) = (h, ḣ, P_hh, P_hḣ, P_ḣḣ) over ``tau`` into ``out``."""
    t2 = tau * tau
    out[2] = s[2] + 2.0 * tau * s[3] + t2 * s[4] + q * t2 * tau / 3.0
    out[3] = s[3] + tau * s[4] + q * t2 / 2.0
    out[0] = s[0] + tau * s[1]
    out[1] = s[1]
    out[4] = s[4] + q * tau


@_jit
def _mix(states, w, nm, out):
    """(A6)/(A9): Σ w_j N(x_j, P_j) moment-matched into ``out``."""
    h = 0.0
    r = 0.0
    for j in range(nm):
        h = h + w[j] * states[j, 0]
    for j in range(nm):
        r = r + w[j] * states[j, 1]
    phh = 0.0
    phr = 0.0
    prr = 0.0
    for j in range(nm):
        phh = phh + w[j] * (states[j, 2] + (states[j, 0] - h) ** 2)
    for j in range(nm):
        phr = phr + w[j] * (states[j, 3] + (states[j, 0] - h) * (states[j, 1] - r))
    for j in range(nm):
        prr = prr + w[j] * (states[j, 4] + (states[j, 1] - r) ** 2)
    out[0], out[1], out[2], out[3], out[4] = h, r, phh, phr, prr


@_jit
def _rate_step(cur, mu, nm, vrk, vr_var, vr_gate, allow, lik, tmp):
    """The models ``cur`` (nm, 5) and probabilities ``mu`` updated in place with a downlinked
    vertical rate ``vrk`` (H = [0, 1], variance ``vr_var``), each model's rate variance grown by
    ``allow`` first when the rate lies outside the plain gate of the combined estimate (the
    onset of a climb or a level-off); False (nothing changed) outside the grown gate."""
    _mix(cur, mu, nm, tmp)
    d2 = (vrk - tmp[1]) ** 2
    onset = d2 > vr_gate * (tmp[4] + vr_var)
    if not d2 <= vr_gate * (tmp[4] + vr_var + allow):
        return False
    tot = 0.0
    for j in range(nm):
        prr = cur[j, 4] + allow if onset else cur[j, 4]
        sv = prr + vr_var
        nu = vrk - cur[j, 1]
        phr = cur[j, 3]
        kh, kr = phr / sv, prr / sv
        cur[j, 0] = cur[j, 0] + kh * nu
        cur[j, 1] = cur[j, 1] + kr * nu
        cur[j, 2] = cur[j, 2] - kh * phr
        cur[j, 3] = phr - kh * prr
        cur[j, 4] = prr - kr * prr
        lik[j] = np.exp(-0.5 * nu * nu / sv) / np.sqrt(2 * np.pi * sv) * mu[j]
        tot = tot + lik[j]
    if nm > 1 and tot > 0:
        for j in range(nm):
            mu[j] = lik[j] / tot
    return True


@_jit
def _level_consistent(cur, mu, tau, zk, vk, qs, sojourn, hold_sigma):
    """Whether reply ``zk`` lies within ``hold_sigma`` of the level model's (model 0) prediction
    over ``tau`` from ``cur``/``mu`` (A5)–(A6)."""
    p_sw0 = 1.0 - np.exp(-tau / sojourn[0])
    p_sw1 = 1.0 - np.exp(-tau / sojourn[1])
    c0 = (1.0 - p_sw0) * mu[0] + p_sw1 * mu[1]
    c0 = c0 if (c0 > 1e-300 or c0 != c0) else 1e-300
    w = np.empty(2)
    w[0], w[1] = (1.0 - p_sw0) * mu[0] / c0, p_sw1 * mu[1] / c0
    mixed = np.empty(5)
    pred = np.empty(5)
    _mix(cur, w, 2, mixed)
    _predict(mixed, tau, qs[0], pred)
    sv = pred[2] + vk
    return np.abs(zk - pred[0]) <= hold_sigma * np.sqrt(sv if sv > 0.0 else 0.0)


@_jit
def filter_recursion(t, z, var, vr, ids, starts, lengths, qs, sojourn, gate_sigma, gate_floor, max_rejects, v0,
            weak_var, hold_sigma, vr_var, vr_gate, vr_acc, c_models, c_mu, c_t, c_ok, c_conf, c_miss, c_id, c_post, c_has, c_held, c_held_id,
            out, has, rejected):
    """Every track g (rows ``starts[g]`` … in time order) from its carry ``c_*[g]`` (updated in
    place); per row the output state ``out`` (6, n: the state (5) and the last model's
    probability), ``has`` and ``rejected``. ``weak_var`` < 0: unconfirmed filters are not output.
    ``hold_sigma`` > 0 (the IMM only): a reply that a confirmed, level filter would use but that
    lies beyond ``hold_sigma`` of the level model's prediction is held (the row outputs the
    prediction) until the next reply: dropped as a garble when that reply is level-consistent,
    else applied just before it. ``c_held`` (3, k): the held reply's (t, z, R), NaN none. ``vr``:
    each reply's downlinked vertical rate (NaN none): a refused reply whose register differs from
    the filter's rate beyond ``vr_gate`` (with variance ``vr_var``) restarts the filter on it at
    once, with that rate; any other reply's register then updates the rate (:func:`_rate_step`,
    the gate grown by (``vr_acc`` τ)² at an onset)."""
    nm = len(qs)
    cur = np.empty((nm, 5))
    preds = np.empty((nm, 5))
    upd = np.empty((nm, 5))
    mixed = np.empty(5)
    s = np.empty(5)
    u = np.empty(5)
    w = np.empty(nm)
    c = np.empty(nm)
    mu = np.empty(nm)
    mu_u = np.empty(nm)
    lik = np.empty(nm)
    pij = np.empty((nm, nm))
    holding = hold_sigma > 0.0 and nm == 2
    for g in range(len(starts)):
        for j in range(nm):
            mu[j] = c_mu[j, g]
            for f in range(5):
                cur[j, f] = c_models[j, f, g]
        t_last, ok, conf, miss, last_id = c_t[g], c_ok[g], c_conf[g], c_miss[g], c_id[g]
        h_t, h_z, h_v, h_id = c_held[0, g], c_held[1, g], c_held[2, g], c_held_id[g]
        for k in range(lengths[g]):
            i = starts[g] + k
            # a held reply is applied before this one unless this one says the track is level
            n_pass = 1
            if h_z == h_z and np.isfinite(z[i]):
                if holding and _level_consistent(cur, mu, t[i] - t_last, z[i], var[i], qs, sojourn, hold_sigma):
                    h_z = np.nan
                else:
                    n_pass = 2
            for p in range(n_pass):
                last_pass = p == n_pass - 1
                if last_pass:
                    zk, vk, tk, idk = z[i], var[i], t[i], ids[i]
                else:
                    # held before rows without an altitude: applied at the last time (its delay)
                    zk, vk, tk, idk = h_z, h_v, h_t if h_t > t_last else t_last, h_id
                    h_z = np.nan
                valid = np.isfinite(zk)
                zz = zk if valid else 0.0
                tau = tk - t_last
                # (A5)-(A6) and each model's prediction
                if nm == 1:
                    c[0] = 1.0
                    _predict(cur[0], tau, qs[0], preds[0])
                else:
                    for a in range(nm):
                        p_sw = 1.0 - np.exp(-tau / sojourn[a])
                        pij[a, a], pij[a, 1 - a] = 1.0 - p_sw, p_sw
                    for j in range(nm):
                        cj = pij[0, j] * mu[0] + pij[1, j] * mu[1]
                        c[j] = cj if (cj > 1e-300 or cj != cj) else 1e-300
                    for j in range(nm):
                        for a in range(nm):
                            w[a] = pij[a, j] * mu[a] / c[j]
                        _mix(cur, w, nm, mixed)
                        _predict(mixed, tau, qs[j], preds[j])
                # (A7)-(A9)
                tot = 0.0
                for j in range(nm):
                    nu = zz - preds[j, 0]
                    sv = preds[j, 2] + vk
                    kh, kr = preds[j, 2] / sv, preds[j, 3] / sv
                    upd[j, 0], upd[j, 1] = preds[j, 0] + kh * nu, preds[j, 1] + kr * nu
                    upd[j, 2], upd[j, 3] = preds[j, 2] - kh * preds[j, 2], preds[j, 3] - kh * preds[j, 3]
                    upd[j, 4] = preds[j, 4] - kr * preds[j, 3]
                    lik[j] = np.exp(-0.5 * nu * nu / sv) / np.sqrt(2 * np.pi * sv)
                    w[j] = lik[j] * c[j]
                    tot = tot + w[j]
                for j in range(nm):
                    mu_u[j] = w[j] / tot if tot > 0 else c[j]
                _mix(upd, mu_u, nm, u)
                _mix(preds, c, nm, s)                                   # combined prediction
                nu = zz - s[0]
                sv = s[2] + vk
                sv0 = sv if (sv > 0.0 or sv != sv) else 0.0                 # np.maximum: NaN stays NaN
                inside = np.abs(nu) <= gate_sigma * np.sqrt(sv0) + gate_floor
                run = ok
                swapped = valid and run and idk >= 0 and last_id >= 0 and idk != last_id
                if valid and idk >= 0:
                    last_id = idk
                accept = run and valid and inside and not swapped
                bad = run and valid and (not inside) and not swapped
                held_now = False
                vrk = vr[i] if last_pass else np.nan
                # a register that says the vertical motion changed: the reply is no garble to hold
                changed = vrk == vrk and (vrk - s[1]) ** 2 > vr_gate * (s[4] + vr_var)
                if accept and holding and last_pass and conf and c[0] >= 0.5 and not changed:
                    lv = preds[0, 2] + vk
                    if np.abs(zz - preds[0, 0]) > hold_sigma * np.sqrt(lv if lv > 0.0 else 0.0):
                        accept = False              # held: the row is a prediction until the next reply
                        held_now = True
                        h_t, h_z, h_v, h_id = tk, zk, vk, idk
                if accept:
                    miss = 0
                elif bad:
                    miss += 1
                moved = bad and changed
                restart = (valid and not run) or (bad and (miss >= max_rejects or not conf)) or swapped or moved
                if restart:
                    h_z = np.nan
                    r0, prr0 = (vrk, vr_var) if moved else (0.0, v0 * v0)
                    for j in range(nm):
                        cur[j, 0], cur[j, 1], cur[j, 2], cur[j, 3], cur[j, 4] = zz, r0, vk, 0.0, prr0
                        mu[j] = 1.0 / nm
                    out[0, i], out[1, i], out[2, i], out[3, i], out[4, i] = zz, r0, vk, 0.0, prr0
                    miss = 0
                    conf = False
                else:
                    for j in range(nm):
                        for f in range(5):
                            cur[j, f] = upd[j, f] if accept else preds[j, f]
                        mu[j] = mu_u[j] if accept else c[j]
                    for f in range(5):
                        out[f, i] = u[f] if accept else s[f]
                    if bad:
                        out[2, i] = s[2] + nu * nu       # the refused residual (module altitude)
                    conf = conf or accept
                out[5, i] = mu[nm - 1]
                ok = ok or restart
                if (ok and vrk == vrk and not moved and not held_now
                        and _rate_step(cur, mu, nm, vrk, vr_var, vr_gate, (vr_acc * tau) ** 2, lik, mixed)):
                    _mix(cur, mu, nm, u)
                    for f in range(5):
                        out[f, i] = u[f]
                    if bad and not restart:
                        out[2, i] = u[2] + nu * nu
                    out[5, i] = mu[nm - 1]
                t_last = tk
            if weak_var >= 0.0:
                if ok and not conf:
                    ph = out[2, i]
                    out[2, i] = ph if (ph >= weak_var or ph != ph) else weak_var
                has[i] = ok
            else:
                has[i] = ok and conf
            rejected[i] = bad and not restart
        for j in range(nm):
            c_mu[j, g] = mu[j]
            for f in range(5):
                c_models[j, f, g] = cur[j, f]
        c_t[g], c_ok[g], c_conf[g], c_miss[g], c_id[g] = t_last, ok, conf, miss, last_id
        c_held[0, g], c_held[1, g], c_held[2, g], c_held_id[g] = h_t, h_z, h_v, h_id
        last = starts[g] + lengths[g] - 1
        for f in range(5):
            c_post[f, g] = out[f, last]
        c_has[g] = has[last]


def _signature() -> tuple:
    """The one signature :func:`tertiary.stages.tracking.altitude.filter_tracks_carry` calls it with."""
    f1, i1, b1 = (nbt.Array(d, 1, "C") for d in (nbt.float64, nbt.int64, nbt.boolean))
    f2, f3 = nbt.Array(nbt.float64, 2, "C"), nbt.Array(nbt.float64, 3, "C")
    return (f1, f1, f1, f1, i1, i1, i1, f1, f1, nbt.float64, nbt.float64, nbt.int64, nbt.float64, nbt.float64,
            nbt.float64, nbt.float64, nbt.float64, nbt.float64, f3, f2, f1, b1, b1, i1, i1, f2, b1, f2, i1, f2, b1, b1)


register_kernel("altitude", __name__, filter_recursion, _signature)
